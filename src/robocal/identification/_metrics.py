"""Position-accuracy metrics and the "% of measured error described" figures.

The baseline of every percentage is the *nominal model with only the tracker <- base transform
and the reflector offset fitted* (on the training poses): its errors are the "measured
error" a calibration can explain. With ``e_j`` the baseline's error and ``r_j`` the
calibrated model's residual at pose j:

- ``percent_described_rms  = 100 (1 - RMS(|r|) / RMS(|e|))``
- ``percent_described_mean = 100 (1 - mean(|r|) / mean(|e|))``
- ``percent_described_r2   = 100 (1 - sum |r|^2 / sum |e|^2)`` (variance explained)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.measurements import MeasurementSet
from robocal.kinematics import CalibratedModel

Array = NDArray[np.float64]
BASELINE_DESCRIPTION = ("nominal kinematics with only the tracker<-base transform and the "
                        "reflector offset fitted (on the training poses)")


@dataclass(frozen=True)
class Accuracy:
    """Position errors of a model on a set of poses (metres) and % of error described.

    ``n``: number of poses evaluated. The ``percent_*`` fields and ``baseline_*`` are None
    when no baseline was given.
    """

    rms_m: float
    mean_m: float
    max_m: float
    n: int
    percent_described_rms: float | None = None
    percent_described_mean: float | None = None
    percent_described_r2: float | None = None
    baseline_rms_m: float | None = None
    baseline_mean_m: float | None = None
    baseline_max_m: float | None = None
    excluded: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form in mm and %."""

        def mm(v: float | None) -> float | None:
            return None if v is None else round(v * 1e3, 9)

        def pc(v: float | None) -> float | None:
            return None if v is None else round(v, 3)

        return {
            "n": self.n, "rms_mm": mm(self.rms_m), "mean_mm": mm(self.mean_m),
            "max_mm": mm(self.max_m),
            "percent_described_rms": pc(self.percent_described_rms),
            "percent_described_mean": pc(self.percent_described_mean),
            "percent_described_r2": pc(self.percent_described_r2),
            "baseline_rms_mm": mm(self.baseline_rms_m),
            "baseline_mean_mm": mm(self.baseline_mean_m),
            "baseline_max_mm": mm(self.baseline_max_m),
            "baseline": BASELINE_DESCRIPTION if self.baseline_rms_m is not None else None,
            "excluded_poses": list(self.excluded),
        }


def error_norms(model: CalibratedModel | Callable[[Array], Array], data: MeasurementSet
                ) -> Array:
    """Distance |measured - predicted| (n,) m for every pose of ``data``."""
    predict = model.predict if isinstance(model, CalibratedModel) else model
    return np.linalg.norm(data.p - predict(data.q), axis=1)


def accuracy_from_errors(err: Array, baseline_err: Array | None = None) -> Accuracy:
    """Build an :class:`Accuracy` from per-pose error norms (n,) m."""
    err = np.asarray(err, dtype=float)
    n = int(err.size)
    if n == 0:
        return Accuracy(math.nan, math.nan, math.nan, 0)
    rms = float(np.sqrt(np.mean(err**2)))
    mean = float(np.mean(err))
    mx = float(np.max(err))
    if baseline_err is None:
        return Accuracy(rms, mean, mx, n)
    b = np.asarray(baseline_err, dtype=float)
    brms = float(np.sqrt(np.mean(b**2)))
    bmean = float(np.mean(b))
    pr = 100.0 * (1.0 - rms / brms) if brms > 0 else math.nan
    pm = 100.0 * (1.0 - mean / bmean) if bmean > 0 else math.nan
    r2 = 100.0 * (1.0 - (rms / brms) ** 2) if brms > 0 else math.nan
    return Accuracy(rms, mean, mx, n, pr, pm, r2, brms, bmean, float(np.max(b)))


def accuracy(model: CalibratedModel | Callable[[Array], Array], data: MeasurementSet, *,
             baseline: CalibratedModel | Callable[[Array], Array] | None = None,
             exclude: Sequence[str] = ()) -> Accuracy:
    """Accuracy of ``model`` on ``data``, optionally with % described relative to ``baseline``.

    Parameters
    ----------
    model
        A :class:`CalibratedModel` or any callable mapping joints (n, dof) rad to points (n, 3) m.
    data
        Measured poses.
    baseline
        The nominal-with-base-and-reflector-fitted model (``FitResult.baseline``); enables the
        ``percent_described_*`` fields.
    exclude
        Pose ids to leave out (e.g. detected outliers).
    """
    gone = set(exclude)
    if gone:
        keep = np.array([pid not in gone for pid in data.pose_id], dtype=bool)
        data = data.subset(keep)
    err = error_norms(model, data)
    berr = None if baseline is None else error_norms(baseline, data)
    acc = accuracy_from_errors(err, berr)
    if gone:
        acc = replace(acc, excluded=tuple(sorted(gone)))
    return acc
