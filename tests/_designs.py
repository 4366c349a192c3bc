"""Calibration designs shared by tests in several layers."""

from __future__ import annotations

import numpy as np

from robocal._core.measurements import MeasurementSet
from robocal.simulation import VirtualCell


def thin_j6_design(n: int = 60, seed: int = 3
                   ) -> tuple[VirtualCell, np.random.Generator, MeasurementSet]:
    """Virtual UR10 (``paper``) and ``n`` random training poses with J6 at 0 and 2 deg only.

    The reflector's direction about J6 is then nearly free: poses with J6 elsewhere are
    extrapolated. The returned generator continues the draws (for validation poses).
    """
    cell = VirtualCell.create("ur10", "paper", seed=seed)
    rng = np.random.default_rng(seed)
    q = cell.random_joints(n, rng)
    q[:, 5] = np.radians(rng.choice([0.0, 2.0], len(q)))
    q, p, _, _ = cell.simulate(q, rng)
    return cell, rng, MeasurementSet(q, p)
