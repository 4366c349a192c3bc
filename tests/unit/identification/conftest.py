"""Virtual-cell data for the identification tests (small pose counts: the suite must be fast)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.simulation import VirtualCell


@dataclass
class CellData:
    """A virtual cell with training and held-out measurements."""

    cell: VirtualCell
    train: MeasurementSet
    val: MeasurementSet
    planted: list[str]


def make_data(robot: str, scenario: str, seed: int, *, n_train: int = 250, n_val: int = 400,
              outlier_fraction: float = 0.0, with_sigma: bool = False) -> CellData:
    """Random training poses (optionally with glitches) and separate clean held-out poses."""
    cell = VirtualCell.create(robot, scenario, seed=seed)
    rng = np.random.default_rng(1000 + seed)
    q, p, s, idx = cell.simulate(cell.random_joints(n_train, rng), rng,
                                 outlier_fraction=outlier_fraction)
    train = MeasurementSet(q, p, s if with_sigma else None)
    qv, pv, _, _ = cell.simulate(cell.random_joints(n_val, rng), rng)
    return CellData(cell, train, MeasurementSet(qv, pv), [train.pose_id[i] for i in idx])


@pytest.fixture(scope="session")
def paper_data() -> CellData:
    """LR Mate 200i, ``paper`` scenario, 250 training poses."""
    return make_data("fanuc_lrmate200i", "paper", seed=11)
