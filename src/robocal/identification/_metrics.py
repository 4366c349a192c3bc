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
from robocal.identification._linalg import median
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

    rms_m: float  # of the position errors, m
    mean_m: float
    max_m: float
    n: int  # poses
    #: share of the baseline's error the model describes, %
    percent_described_rms: float | None = None  # of the RMS
    percent_described_mean: float | None = None  # of the mean
    percent_described_r2: float | None = None  # of the summed squares (variance explained)
    #: the baseline's errors on the same poses, m
    baseline_rms_m: float | None = None
    baseline_mean_m: float | None = None
    baseline_max_m: float | None = None
    #: ids of poses left out of the figures
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
    """Distance |measured - predicted| (n,) m for every pose of ``data``; a model's thermal
    term (ADR 0042) is applied at the poses' joint temperatures where ``data`` has them."""
    predict = model.predict if isinstance(model, CalibratedModel) else model
    pred = predict(data.q)
    if isinstance(model, CalibratedModel) and data.temps is not None \
            and model.fit.get("thermal"):
        from robocal.identification._thermal import thermal_shift  # builds on auto

        pred = pred + thermal_shift(model, data.q, data.temps)
    return np.linalg.norm(data.p - pred, axis=1)


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


#: A validation pose whose predicted position is this many times less certain than the
#: median training pose lies where the training poses do not determine the model.
EXTRAPOLATION_FACTOR = 10.0


@dataclass(frozen=True)
class Extrapolation:
    """Poses whose predicted position the fit leaves nearly free (see :func:`extrapolation`)."""

    far: NDArray[np.bool_]       # (n,) the flagged poses
    sigma_m: Array               # (n,) 1-sigma of each pose's predicted position, m
    reference_m: float           # median 1-sigma over the training poses, m
    joints: tuple[int, ...]      # 0-based joints whose angles at the flagged poses training lacks

    @property
    def n(self) -> int:
        """Number of flagged poses."""
        return int(self.far.sum())

    def message(self) -> str:
        """"lie where ...": the rest of a sentence that starts with the pose count."""
        lack = (f", with {'/'.join(f'J{j + 1}' for j in self.joints)} angles the training "
                "poses lack" if self.joints else "")
        return ("lie where the training poses leave the model nearly free: their predicted "
                f"positions are up to {self.sigma_m.max() * 1e3:.3g} mm uncertain (1 sigma; "
                f"median training pose {self.reference_m * 1e3:.3g} mm); add training poses "
                f"like them (robocal plan){lack}")


def extrapolation(cal: CalibratedModel, train_q: Array, q: Array) -> Extrapolation | None:
    """Which poses ``q`` (n, dof) rad the training poses ``train_q`` (m, dof) leave nearly free.

    A pose is flagged when the 1-sigma of its predicted position (base, reflector and constant
    block of ``cal``'s covariance) exceeds ``EXTRAPOLATION_FACTOR`` times the median over the
    training poses. None without a covariance or poses.
    """
    if cal.covariance is None or len(train_q) == 0 or len(q) == 0:
        return None
    step = max(1, len(train_q) // 500)
    ref = median(_constant_part_sigma(cal, train_q[::step]))
    sv = _constant_part_sigma(cal, q)
    far = sv > EXTRAPOLATION_FACTOR * ref if ref > 0 else np.zeros(len(q), dtype=bool)
    return Extrapolation(far, sv, ref, _unseen_joints(train_q, q[far]) if far.any() else ())


def _constant_part_sigma(cal: CalibratedModel, q: Array, chunk: int = 512) -> Array:
    """1-sigma (n,) m of the predicted position from the base, reflector and constant terms.

    Only that block of the covariance is used: it is what a design can leave nearly free
    (the joint-dependent terms outside their coverage are replaced by the fallback).
    """
    cov = cal.covariance
    assert cov is not None
    sel = np.array([i for i, n in enumerate(cal.model.names)
                    if (n.startswith(("base.", "tool.")) or n.endswith(".const"))
                    and cov[i, i] > 0], dtype=np.intp)
    C = cov[np.ix_(sel, sel)]
    out = np.empty(len(q))
    for a in range(0, len(q), chunk):
        _, J = cal.model.jacobian(q[a:a + chunk], cal.params)
        Js = J[:, :, sel]
        out[a:a + chunk] = np.sqrt(np.clip(
            np.einsum("nip,pq,niq->n", Js, C, Js, optimize=True), 0.0, None))
    return out


def _unseen_joints(train_q: Array, q: Array, min_deg: float = 10.0) -> tuple[int, ...]:
    """Joints whose values at ``q`` (n, dof) rad lie typically more than ``min_deg`` from
    every training value (``train_q`` (m, dof))."""
    names = []
    for j in range(q.shape[1]):
        t = np.sort(train_q[:, j])
        k = np.clip(np.searchsorted(t, q[:, j]), 1, len(t) - 1) if len(t) > 1 else None
        if k is None:
            d = np.abs(q[:, j] - t[0])
        else:
            d = np.minimum(np.abs(q[:, j] - t[k - 1]), np.abs(q[:, j] - t[k]))
        if median(np.degrees(d)) > min_deg:
            names.append(j)
    return tuple(names)


