"""Per-joint coverage of the judged model: robot limits, the calibrated (trusted) range, the
range the calibration poses measured, and the production program's targets (ADR 0026)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.joint_ranges import targets_outside
from robocal.kinematics import CalibratedModel, RobotDescription

Array = NDArray[np.float64]


@dataclass(frozen=True)
class JointCoverageRow:
    """One joint, ranges in degrees ([low, high]; None when unknown)."""

    joint: int
    limits_deg: tuple[float, float]
    calibrated_deg: tuple[float, float] | None
    measured_deg: tuple[float, float] | None
    targets_deg: tuple[float, float] | None
    targets_outside: int


@dataclass(frozen=True)
class Coverage:
    """Coverage table, the targets (n, dof) rad and how many lie outside the calibrated range.

    ``outside`` counts targets with any joint outside; ``names`` the first ten of them.
    """

    rows: list[JointCoverageRow]
    targets: Array | None
    outside: int
    names: list[str]

    def to_dict(self) -> dict[str, Any]:
        """The report.json layout (degrees)."""
        return {"joints": [{"joint": r.joint, "limits_deg": list(r.limits_deg),
                            "calibrated_deg": None if r.calibrated_deg is None
                            else list(r.calibrated_deg),
                            "measured_deg": None if r.measured_deg is None
                            else list(r.measured_deg),
                            "targets_deg": None if r.targets_deg is None
                            else list(r.targets_deg),
                            "targets_outside": r.targets_outside} for r in self.rows],
                "targets": 0 if self.targets is None else len(self.targets),
                "targets_outside": self.outside, "outside_names": list(self.names)}


def _deg(lo: float, hi: float) -> tuple[float, float]:
    return round(math.degrees(lo), 3), round(math.degrees(hi), 3)


def coverage(robot: RobotDescription, cm: CalibratedModel | None, q_cal: Array | None,
             targets: Array | None) -> Coverage:
    """The coverage of model ``cm`` (its ``coverage``; the robot limits when it has none),
    the calibration poses ``q_cal`` (n, dof) rad and the program ``targets`` (m, dof) rad."""
    lim = robot.joint_limits
    cov = None if cm is None or cm.coverage is None else np.asarray(cm.coverage)
    t = None if targets is None or not len(targets) else np.atleast_2d(targets)
    rows = []
    out_any = np.zeros(0 if t is None else len(t), dtype=bool)
    for j in range(robot.dof):
        outside = 0
        if t is not None and cov is not None:
            bad = (t[:, j] < cov[j, 0]) | (t[:, j] > cov[j, 1])
            outside = int(bad.sum())
            out_any |= bad
        rows.append(JointCoverageRow(
            joint=j + 1, limits_deg=_deg(lim[j, 0], lim[j, 1]),
            calibrated_deg=None if cov is None else _deg(cov[j, 0], cov[j, 1]),
            measured_deg=None if q_cal is None or not len(q_cal)
            else _deg(float(q_cal[:, j].min()), float(q_cal[:, j].max())),
            targets_deg=None if t is None else _deg(float(t[:, j].min()), float(t[:, j].max())),
            targets_outside=outside))
    names = [] if t is None or cov is None else targets_outside(cov, t)[1]
    return Coverage(rows=rows, targets=t, outside=int(out_any.sum()), names=names)
