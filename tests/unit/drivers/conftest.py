"""Fixtures: a simulated world and simulators on loopback, shut down after each test."""

from __future__ import annotations

import pytest

from robocal.drivers.sim import SimWorld


@pytest.fixture
def world() -> SimWorld:
    return SimWorld.create(seed=3)
