"""Shared fixtures: seeded RNGs and the location of the shared datasets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATASET = SHARED / "datasets" / "ipa-ur10-lasertracker"


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator, fresh per test."""
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def dataset_dir() -> Path:
    """The IPA UR10 dataset directory; skips the test when it is absent."""
    if not (DATASET / "Series_C").is_dir():
        pytest.skip(f"dataset not found at {DATASET}")
    return DATASET
