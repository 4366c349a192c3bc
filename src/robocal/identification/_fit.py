"""Public fitting API: :func:`fit`, :func:`refit_frozen`, :class:`FitOptions`, :class:`FitResult`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.measurements import MeasurementSet
from robocal._core.model_names import MODELS
from robocal._core.threads import blas_threads
from robocal.errors import ConfigError, DataError, NotConverged, NotIdentifiable
from robocal.identification._auto import auto_select
from robocal.identification._engine import Solution, screen
from robocal.identification._fitter import FitOptions, Fitter
from robocal.identification._linalg import median
from robocal.identification._metrics import (
    BASELINE_DESCRIPTION,
    Accuracy,
    accuracy,
    extrapolation,
)
from robocal.identification._models import (
    MapPrior,
    knot_counts,
    map_terms,
)
from robocal.identification._solver import Identifiability
from robocal.kinematics import (
    CalibratedModel,
    ErrorModelSpec,
    KinematicModel,
    ParameterLayout,
    RobotDescription,
    load_robot,
    rigid_fit,
)

Array = NDArray[np.float64]
SOLVER = ("Levenberg-Marquardt (Nielsen damping) on column-scaled whitened normal equations, "
          "Cholesky; analytic Jacobian")


@dataclass
class FitResult:
    """Outcome of :func:`fit`.

    ``calibrated``: the model (``kind`` = model name), ready to save. ``baseline``: the nominal
    model with only base and reflector fitted (reference of the % described). ``constant``:
    the constant model fitted on the same poses (also the stored fallback).
    """

    model: str
    calibrated: CalibratedModel
    baseline: CalibratedModel
    constant: CalibratedModel | None
    train: Accuracy
    validation: Accuracy | None
    outliers: list[str]
    removed: list[str]
    identifiability: Identifiability
    variance_factor: float
    dof_effective: float
    n_params: int
    n_free: int
    iterations: int
    converged: bool
    selection: list[dict[str, Any]]
    options: FitOptions
    elapsed_s: float
    validation_all: Accuracy | None = None
    validation_outliers: list[str] = field(default_factory=list)
    status: str = "converged"
    warnings: list[str] = field(default_factory=list)

    def correlations(self) -> tuple[list[str], Array]:
        """Names and correlation matrix (k, k) of the estimated parameters."""
        return _correlations(self.calibrated)

    @property
    def rank(self) -> int:
        """Numerical rank of the identification Jacobian (unpenalised parameters)."""
        return self.identifiability.rank

    def summary(self) -> dict[str, Any]:
        """JSON-friendly summary (mm, %)."""
        return {
            "model": self.model,
            "model_id": self.calibrated.model_id,
            "robot": self.calibrated.robot.name,
            "baseline": BASELINE_DESCRIPTION,
            "train": self.train.to_dict(),
            "validation": None if self.validation is None else self.validation.to_dict(),
            "validation_all_poses": (None if self.validation_all is None
                                     else self.validation_all.to_dict()),
            "outliers": list(self.outliers),
            "validation_outliers": list(self.validation_outliers),
            "removed": list(self.removed),
            "rank": self.identifiability.rank,
            "condition_number": _finite(self.identifiability.cond),
            "variance_factor": _finite(self.variance_factor),
            "sigma0": _finite(math.sqrt(self.variance_factor)),
            "dof_effective": round(self.dof_effective, 3),
            "n_params": self.n_params,
            "n_free": self.n_free,
            "iterations": self.iterations,
            "converged": self.converged,
            "status": self.status,
            "terms": _term_summary(self.calibrated.model.spec),
            "selection": self.selection,
            "warnings": list(self.warnings),
            "elapsed_s": round(self.elapsed_s, 3),
        }


def _correlations(cal: CalibratedModel) -> tuple[list[str], Array]:
    cov = cal.covariance
    if cov is None:
        return [], np.zeros((0, 0))
    d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    free = np.flatnonzero(d > 0)
    corr = cov[np.ix_(free, free)] / np.outer(d[free], d[free])
    return [cal.model.names[i] for i in free], corr


def _top_correlations(cal: CalibratedModel, k: int = 10) -> list[dict[str, Any]]:
    names, corr = _correlations(cal)
    if len(names) < 2:
        return []
    iu = np.triu_indices(len(names), 1)
    vals = corr[iu]
    order = np.argsort(-np.abs(vals))[:k]
    return [{"a": names[iu[0][i]], "b": names[iu[1][i]], "rho": float(vals[i])} for i in order]


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _term_summary(spec: ErrorModelSpec) -> dict[str, int]:
    out: dict[str, int] = {}
    for t in spec.terms:
        out[t.family] = out.get(t.family, 0) + 1
    return out


# ----------------------------------------------------------------------------------------------
def _check_inputs(robot: RobotDescription | str, data: MeasurementSet,
                  model: str | ErrorModelSpec, validation: MeasurementSet | None
                  ) -> RobotDescription:
    rob = load_robot(robot) if isinstance(robot, str) else robot
    if isinstance(model, ErrorModelSpec):
        if model.dof != rob.dof:
            raise ConfigError(f"error model has {model.dof} joints, robot has {rob.dof}")
    elif model not in MODELS:
        raise ConfigError(f"unknown model {model!r} (choose from {', '.join(MODELS)})")
    for name, ds in (("data", data), ("validation", validation)):
        if ds is None:
            continue
        if ds.dof != rob.dof:
            raise DataError(f"{name} has {ds.dof} joint columns, robot {rob.name!r} has "
                            f"{rob.dof} joints")
        if not (np.all(np.isfinite(ds.q)) and np.all(np.isfinite(ds.p))):
            raise DataError(f"{name} contains non-finite values")
        if ds.sigma is not None and not (np.all(np.isfinite(ds.sigma)) and np.all(ds.sigma > 0)):
            raise DataError(f"{name} has non-positive or non-finite sigmas")
    if len(data) < 4:
        raise DataError(f"need at least 4 poses, got {len(data)}")
    for name, ds in (("data", data), ("validation", validation)):
        # beyond any robot: a value like this would only overflow the kinematics
        if ds is not None and float(np.abs(ds.q).max(initial=0.0)) > _MAX_JOINT_RAD:
            raise DataError(f"{name}: a joint value of "
                            f"{math.degrees(float(np.abs(ds.q).max())):.3g} deg is not plausible")
        if ds is not None and float(np.abs(ds.p).max(initial=0.0)) > _MAX_POSITION_M:
            raise DataError(f"{name}: a position of {float(np.abs(ds.p).max()) * 1e3:.3g} mm "
                            "from the tracker is not plausible")
    return rob


_MAX_JOINT_RAD = 100 * 2 * math.pi
_MAX_POSITION_M = 1e3
#: A revolute joint's value in radians lies within +-(2 pi + margin): read as degrees, that
#: is this many radians (6.38 deg).
_RADIANS_LOOK_RAD = math.radians(2 * math.pi + 0.1)
#: ... and the robot must be one whose joints range over far more than that
_RADIANS_WIDE_RAD = math.radians(60.0)


def looks_like_radians(robot: RobotDescription, q: Array) -> bool:
    """Whether joint values ``q`` (n, dof), read from a file as degrees, are radians.

    The rule (docs/adr/0032): every value, read as degrees, lies within +-(2 pi + 0.1) deg
    = +-6.38 deg (a radian value of a revolute joint within one turn each way); the
    robot's widest joint range exceeds 60 deg (so degree data of its workspace would spread
    further); the data move at all; and read as radians the values lie within the robot's
    joint limits (+-1 deg), so the reading in radians is a plausible one. Data of a small
    robot whose joints stay within, say, +-114 deg are far outside the first bound and are
    never refused.
    """
    if q.size == 0:
        return False
    lim = robot.joint_limits
    if float(np.max(lim[:, 1] - lim[:, 0])) <= _RADIANS_WIDE_RAD:
        return False
    if float(np.abs(q).max()) > _RADIANS_LOOK_RAD or float(np.ptp(q, axis=0).max()) <= 0:
        return False
    as_rad = q * (180.0 / math.pi)
    tol = math.radians(1.0)
    return bool(np.all(as_rad >= lim[:, 0] - tol) and np.all(as_rad <= lim[:, 1] + tol))


def sanity_check(robot: RobotDescription, data: MeasurementSet, *, what: str = "data",
                 tool: Array | None = None) -> None:
    """Refuse data whose units look wrong, with a one-line hint (:class:`DataError`).

    * Joints: see :func:`looks_like_radians` (every joint value within +-6.38 deg although
      the robot's joints range over far more, and the values are within the limits when
      read as radians: the file most likely holds radians where degrees belong).
    * Positions: the spread of the measured points is compared with the spread of the
      nominal reflector positions for the same joints; about 1/1000 of it means metres where
      millimetres belong, about 1000 times micrometres.
    """
    if len(data) < 6:
        return
    q = data.q
    if looks_like_radians(robot, q):
        qmax = float(np.abs(q).max())
        raise DataError(
            f"{what}: every joint value lies within +-{math.degrees(qmax):.2f} deg; the joints "
            "look like radians, but robocal's files give joints in degrees (convert, or "
            "override the check with --no-sanity)")
    m0 = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    x0 = m0.nominal_params()
    x0[ParameterLayout.TOOL] = robot.tool if tool is None else tool
    src = m0.positions(q, x0)
    nominal = float(np.sqrt(np.mean(np.sum((src - src.mean(axis=0)) ** 2, axis=1))))
    measured = float(np.sqrt(np.mean(np.sum((data.p - data.p.mean(axis=0)) ** 2, axis=1))))
    if nominal <= 1e-3:
        return
    ratio = measured / nominal
    if ratio < 0.02:
        raise DataError(
            f"{what}: the measured points spread {measured * 1e3:.3g} mm, but the nominal "
            f"robot moves the reflector {nominal * 1e3:.0f} mm over these joints; the positions "
            "look like metres, but robocal's files give positions in millimetres (convert, or "
            "override the check with --no-sanity)")
    if ratio > 50:
        raise DataError(
            f"{what}: the measured points spread {measured * 1e3:.3g} mm, but the nominal "
            f"robot moves the reflector only {nominal * 1e3:.0f} mm over these joints; the "
            "positions look like micrometres or another unit, robocal's files give "
            "millimetres (convert, or override the check with --no-sanity)")


def _baseline_hint(robot: RobotDescription, rms_m: float | None) -> str:
    left = "does not converge" if rms_m is None else f"leaves {rms_m * 1e3:.1f} mm RMS"
    return (f"the nominal {robot.name} with only the tracker<-base transform and the reflector "
            f"fitted {left}: is this the right robot/variant (and joint order, zero offsets, "
            "units)? Override the check with --no-sanity")


def _coverage(q: Array, margin_deg: float = 0.0) -> Array:
    m = math.radians(margin_deg)
    return np.stack([q.min(axis=0) - m, q.max(axis=0) + m], axis=1)


_PERIODIC = {"const", "cos", "sin", "swcos", "swsin", "map", "gravity"}


def _model_coverage(spec: ErrorModelSpec, robot: RobotDescription, q: Array,
                    margin_deg: float) -> Array:
    """Joint ranges (dof, 2) rad inside which the model's corrections are trusted.

    The training range of each joint widened by ``margin_deg``; the whole joint range for a
    joint without joint-dependent terms, or whose terms are all periodic in the joint angle
    (harmonics, strain wave, maps; gravity is a function of the configuration) when the data
    cover a full revolution. A linear term (pitch) extrapolates: on a joint whose other
    dependent terms are trusted everywhere (none, or periodic over a full turn) the range
    widens by half the data span on each side, where a fitted slope's prediction error is
    still under twice the one at the edge of the data (uniform data: sqrt(1 + 12 (1/2 +
    d/S)^2) over 2 at a distance d beyond a span S), instead of falling back to the constant
    model a few degrees past the last pose.
    """
    cov = _coverage(q, margin_deg)
    lim = robot.joint_limits
    for j in range(robot.dof):
        terms = [t for t in spec.terms if t.joint == j]
        fams = {t.family for t in terms}
        dependent = fams - {"const", "gravity"}
        full_turn = cov[j, 1] - cov[j, 0] >= 2 * math.pi
        linear = "poly" in fams and all(t.index == 1 for t in terms if t.family == "poly")
        others_everywhere = fams - {"poly"} <= _PERIODIC and (
            full_turn or not fams & (_PERIODIC - {"const", "gravity"}))
        if not dependent or (fams <= _PERIODIC and full_turn):
            cov[j] = lim[j]
        elif linear and others_everywhere:
            half = 0.5 * float(np.ptp(q[:, j])) if len(q) else 0.0
            widen = max(half, math.radians(margin_deg))
            cov[j] = [max(lim[j][0], q[:, j].min() - widen), min(lim[j][1], q[:, j].max() + widen)]
    return cov


def _calibrated(sol: Solution, kind: str) -> CalibratedModel:
    # the thermal term from the start: the accuracy figures apply it (ADR 0042)
    return CalibratedModel(model=sol.model, params=sol.x.copy(), covariance=sol.covariance,
                           kind=kind, fit={} if sol.thermal is None else {
                               "thermal": sol.thermal})


def fit(robot: RobotDescription | str, data: MeasurementSet,
        model: str | ErrorModelSpec = "constant", *,
        options: FitOptions | None = None, validation: MeasurementSet | None = None
        ) -> FitResult:
    """Identify an error model from measured poses by maximum likelihood.

    Parameters
    ----------
    robot
        Robot description or built-in name / TOML path.
    data
        Training poses: joint values (n, dof) rad, reflector positions (n, 3) m in the tracker
        frame, optional per-point sigmas.
    model
        ``"constant"`` (6-DoF constant error per joint), ``"high-order"`` (constant + Fourier,
        pitch and strain-wave terms) or ``"auto"`` (terms, orders, joint-angle maps and their
        smoothness chosen by cross-validation), or an explicit :class:`ErrorModelSpec` (e.g. a
        known structure; kind = its label).
    options
        :class:`FitOptions`.
    validation
        Held-out poses for :attr:`FitResult.validation`.

    Returns
    -------
    FitResult

    Raises
    ------
    DataError
        Wrong joint count, non-finite values, degenerate poses.
    NotIdentifiable
        Too few poses for the model.
    NotConverged
        The solver did not converge.
    """
    with blas_threads(1):
        return _fit(robot, data, model, options, validation)


def _fit(robot: RobotDescription | str, data: MeasurementSet, model: str | ErrorModelSpec,
         options: FitOptions | None, validation: MeasurementSet | None) -> FitResult:
    t0 = time.perf_counter()
    opts = options or FitOptions()
    rob = _check_inputs(robot, data, model, validation)
    f, base0 = _start(rob, data, opts, validation)
    const = f.constant(base0)
    selection: list[dict[str, Any]] = []
    if isinstance(model, ErrorModelSpec):
        m = f.model(model)
        final = f.engine.solve(m, const.model.transfer(const.x, m), inliers=const.inliers,
                               what=f"{model.label} model")
        kind = model.label
    elif model == "constant":
        final, kind = const, model
    elif model == "high-order":
        final, kind = f.high_order(const), model
    else:
        final, selection = auto_select(f, const)
        kind = model
    return _finish(f, kind, final, const, selection, validation, t0)


def _start(rob: RobotDescription, data: MeasurementSet, opts: FitOptions,
           validation: MeasurementSet | None) -> tuple[Fitter, Solution]:
    """Unit sanity checks, the fitter, and the nominal (base + reflector) baseline fit."""
    tool = None if opts.tool_m is None else np.asarray(opts.tool_m, float)
    if opts.sanity:
        sanity_check(rob, data, what="data", tool=tool)
        if validation is not None:
            sanity_check(rob, validation, what="validation", tool=tool)
    f = Fitter(rob, data, opts)
    try:
        base0 = f.baseline()
    except NotConverged as err:
        if opts.sanity:
            raise NotConverged(f"{err}; {_baseline_hint(rob, None)}") from None
        raise
    if opts.sanity:
        r = base0.model.positions(data.q, base0.x) - data.p
        d = np.sqrt(np.sum(r * r, axis=1))
        # the median pose error, so that a few gross glitches cannot trip the check
        med = median(d)
        if med > opts.sanity_baseline_mm * 1e-3:
            raise DataError(_baseline_hint(rob, float(np.sqrt(np.mean(d * d)))))
    return f, base0


def _finish(f: Fitter, kind: str, final: Solution, const: Solution | None,
            selection: list[dict[str, Any]], validation: MeasurementSet | None,
            t0: float, extra_fit: dict[str, Any] | None = None,
            coverage: Array | None = None,
            prior_support: dict[int, NDArray[np.intp]] | None = None) -> FitResult:
    data, opts = f.data, f.opts
    inl = final.inliers
    base = f.baseline(inliers=inl, robust=False)
    baseline_cm = _calibrated(base, "nominal+base+reflector")
    cal = _calibrated(final, kind)
    const_cm = None
    if const is not None:
        const_cm = cal if final is const else _calibrated(const, "constant")
    cal.coverage = _model_coverage(final.model.spec, f.robot, data.q[inl],
                                   opts.coverage_margin_deg)
    if kind != "constant" and opts.fallback and const_cm is not None and const_cm is not cal:
        cal.fallback = const_cm
    if coverage is not None and cal.fallback is not None:
        # a refit is trusted where the frozen terms were learnt and where it was fitted now
        cal.coverage = np.stack([np.minimum(coverage[:, 0], cal.coverage[:, 0]),
                                 np.maximum(coverage[:, 1], cal.coverage[:, 1])], axis=1)
    outliers = [data.pose_id[i] for i in np.flatnonzero(~inl)]
    train = accuracy(cal, data, baseline=baseline_cm, exclude=outliers)
    val = val_all = None
    val_out: list[str] = []
    if validation is not None:
        val_all = accuracy(cal, validation, baseline=baseline_cm)
        if opts.detect_outliers:
            t = screen(f.engine, final, validation)
            val_out = [validation.pose_id[i]
                       for i in np.flatnonzero(t > f.engine.threshold(len(validation)))]
        val = accuracy(cal, validation, baseline=baseline_cm, exclude=val_out)
    elapsed = time.perf_counter() - t0
    ident = final.ident
    cal.metrics = {
        "baseline": BASELINE_DESCRIPTION,
        "train": train.to_dict(),
        "validation": None if val is None else val.to_dict(),
        "validation_all_poses": None if val_all is None else val_all.to_dict(),
        "validation_outliers": val_out,
    }
    cal.fit = {
        "model": kind,
        "solver": {"method": SOLVER, "iterations": final.info.iterations,
                   "converged": final.info.converged, "status": final.info.status,
                   "message": final.info.message,
                   "cost": final.info.cost, "max_iter": opts.max_iter, "ftol": opts.ftol,
                   "rank_tol": opts.rank_tol},
        "options": opts.to_dict(),
        "identifiability": {
            "rank": ident.rank, "condition_number": _finite(ident.cond),
            "removed": list(final.removed),
            "singular_values": [float(v) for v in ident.singular_values],
            "note": "column-scaled whitened Jacobian of the unpenalised parameters",
        },
        "n_params": final.model.size, "n_free": final.n_free,
        "dof_effective": final.dof_effective,
        "variance_factor": _finite(final.variance_factor),
        "sigma0": _finite(math.sqrt(final.variance_factor)),
        "covariance": "a-posteriori: variance factor x inverse (normal matrix + prior)",
        "largest_correlations": _top_correlations(cal),
        "outliers": {
            "pose_ids": outliers,
            "test": "normalised (deletion) residual, chi-square 3 dof, robust scale",
            "threshold_chi2": _finite(final.outlier_threshold),
            "robust_sigma": _finite(final.robust_sigma),
            "rounds": final.rounds,
        },
        "map_priors": [p.to_dict() for p in final.priors],
        "selection": selection,
        "baseline_params_mm_deg": {
            n: float(v * (1e3 if n.startswith(("base.d", "tool")) else 180 / math.pi))
            for n, v in zip(base.model.names, base.x, strict=True)},
        "elapsed_s": elapsed,
    }
    if final.thermal is not None:
        cal.fit["thermal"] = final.thermal
        cal.model_id = cal.compute_id()  # the hash covers the thermal term (scheme 3)
    if extra_fit:
        cal.fit.update(extra_fit)
    warnings = _warnings(cal, data.q[inl], validation, val_out, val_all)
    cal.fit["warnings"] = warnings
    cal.data = {
        # every column of the data (sigmas and orientation too; options say which weighted)
        "digest": data.digest(),
        "n_poses": len(data),
        "n_used": int(inl.sum()),
        "sigma_source": f.engine.sigma_source,
        "coverage_deg": np.degrees(_coverage(data.q[inl])).tolist(),
        "map_support": _map_support(final.model.spec, data.q[inl], prior_support),
        "validation_digest": None if validation is None else validation.digest(),
        "validation_n_poses": None if validation is None else len(validation),
    }
    cal.model_id = cal.compute_id()
    return FitResult(
        model=kind, calibrated=cal, baseline=baseline_cm, constant=const_cm, train=train,
        validation=val, outliers=outliers, removed=list(final.removed), identifiability=ident,
        variance_factor=final.variance_factor, dof_effective=final.dof_effective,
        n_params=final.model.size, n_free=final.n_free, iterations=final.info.iterations,
        converged=final.info.converged, selection=selection, options=opts, elapsed_s=elapsed,
        validation_all=val_all, validation_outliers=val_out, status=final.info.status,
        warnings=warnings)


#: More screened validation poses than this fraction (and than 2) get a warning.
SCREENED_FRACTION = 0.02


def _warnings(cal: CalibratedModel, train_q: Array, validation: MeasurementSet | None,
              val_out: list[str], val_all: Accuracy | None) -> list[str]:
    """What an operator must know about a fit that its RMS figures do not show."""
    out = []
    ex = None if validation is None else extrapolation(cal, train_q, validation.q)
    if ex is not None and ex.n:
        out.append(f"{ex.n} of {len(ex.sigma_m)} validation poses " + ex.message())
    if val_all is not None and len(val_out) > max(2, SCREENED_FRACTION * val_all.n):
        out.append(f"{len(val_out)} of {val_all.n} validation poses "
                   f"({100 * len(val_out) / val_all.n:.0f} %) were screened as gross errors and "
                   "are not in the validation figures; so many usually means poses the "
                   "training data do not cover, not glitches (all validation poses: RMS "
                   f"{val_all.rms_m * 1e3:.3f} mm)")
    return out


def refit_frozen(previous: CalibratedModel, data: MeasurementSet, *,
                 options: FitOptions | None = None, validation: MeasurementSet | None = None
                 ) -> FitResult:
    """Re-use a model's joint-dependent terms on a new session; refit mainly the constant part.

    The joint-dependent terms of ``previous`` (maps, gravity, harmonics, ...) keep their
    values; the joint offsets, the tracker <- base transform and the reflector offset are
    fitted to ``data`` (re-mastering, new tracker placement, re-mounted reflector), the other
    constant link errors with a prior around their earlier values (``reuse_link_mm``,
    ``reuse_link_deg``). Map knots the earlier data did not support, which its fit only
    bridged, are refitted where ``data`` reach them (``reuse_fill_gaps``; needs the
    ``map_support`` counts models record since issue 14, older files stay fully frozen).
    Coverage is the union of the previous model's (where the frozen maps were learnt) and of
    ``data``'s joint ranges (where the refit was checked against measurements); outside it
    the fallback is a constant model fitted on ``data``.
    """
    with blas_threads(1):
        return _refit_frozen(previous, data, options, validation)


def _refit_frozen(previous: CalibratedModel, data: MeasurementSet, options: FitOptions | None,
                  validation: MeasurementSet | None) -> FitResult:
    t0 = time.perf_counter()
    opts = options or FitOptions()
    rob = _check_inputs(previous.robot, data, "constant", validation)
    support = _earlier_support(previous)           # a malformed file fails before any fit
    settings = _earlier_map_settings(previous)
    f, base0 = _start(rob, data, opts, validation)
    # The constant fit is the fallback and the screen for gross errors. On a small new data
    # set of a robot with parallel axes it may not converge (a few nearly unidentifiable
    # combinations); the refit does not need it, since it starts from the previous model.
    const: Solution | None = _anchored_constant(f, previous, data, base0, opts)
    if const is None:
        try:
            const = f.constant(base0)
        except NotConverged:
            const = None
    inl = base0.inliers if const is None else const.inliers
    m, xp = _registered(previous, data, inl)
    anchors = _link_anchors(m.names, opts)
    start = xp.copy()
    if const is not None:
        # joint offsets from the constant fit; the link geometry stays at the earlier values
        xc = const.model.transfer(const.x, m)
        take = np.array([n.endswith(".const") and n not in anchors for n in m.names])
        start[take] = xc[take]
    frozen = {n for n in m.names if not (n.startswith(("base.", "tool.")) or n.endswith(".const"))}
    priors = (_gap_priors(previous, data.q[inl], opts, support, settings)
              if opts.reuse_fill_gaps else [])
    for pr in priors:
        frozen -= {t.name for t in map_terms(pr.joint, pr.knots)}
    sol = f.engine.solve(m, start, fixed=sorted(frozen), priors=priors, target=xp.copy(),
                         anchors=anchors, inliers=inl, what="frozen-map refit")
    # the maps' own smoothness settings carry over unchanged to the next reuse; the priors of
    # this refit (on the change, x reuse_smoothing, anchored) are recorded beside them
    extra = {"frozen_from": previous.model_id, "frozen_terms": len(frozen),
             "refreshed_map_knots": {f"j{pr.joint + 1}": len(pr.knots) - len(pr.anchored)
                                     for pr in priors},
             "map_priors": list(previous.fit.get("map_priors") or []),
             "reuse_priors": [pr.to_dict() for pr in priors]}
    return _finish(f, "refit:" + previous.kind, sol, const, [], validation, t0,
                   extra_fit=extra, coverage=previous.coverage,
                   prior_support=support)


def _anchored_constant(f: Fitter, previous: CalibratedModel, data: MeasurementSet,
                       base0: Solution, opts: FitOptions) -> Solution | None:
    """The earlier session's constant model refitted like the main refit, or None.

    A free constant fit on a few dozen poses can land on a mirrored solution (two J6 angles
    leave the reflector direction and the wrist offsets nearly free) that puts unseen
    configurations hundreds of mm off; as the fallback outside coverage that would be worse
    than no fallback. So the earlier constant model (``previous.fallback``, or ``previous``
    itself when it has only constant terms) is registered to the new session and refitted
    with the link constants held near their earlier values.
    """
    src = previous.fallback
    if src is None and all(t.family == "const" for t in previous.model.spec.terms):
        src = previous
    if src is None:
        return None
    mc, xf = _registered(src, data, base0.inliers)
    try:
        return f.engine.solve(mc, xf, anchors=_link_anchors(mc.names, opts), target=xf.copy(),
                              what="anchored constant refit")
    except (NotConverged, NotIdentifiable):
        return None


def _registered(cm: CalibratedModel, data: MeasurementSet, inliers: NDArray[np.bool_]
                ) -> tuple[KinematicModel, Array]:
    """``cm``'s model and parameters with its base registered to ``data``'s tracker frame.

    The base correction is zeroed and the reference pose refitted rigidly on the inliers.
    """
    x = cm.params.copy()
    x[ParameterLayout.BASE] = 0.0
    spec = cm.model.spec
    T = rigid_fit(KinematicModel(cm.robot, spec).positions(data.q[inliers], x),
                  data.p[inliers])
    return KinematicModel(cm.robot, spec, T), x


def _link_anchors(names: tuple[str, ...], opts: FitOptions) -> dict[str, float]:
    """Prior sigmas (SI) of the constant link errors for a refit: all but the joint offsets.

    Re-mastering moves the joint zeros (``jN.ez.const``); the links themselves do not change
    between sessions beyond thermal growth, so holding them near the earlier values keeps a
    small new data set from trading them against the base and reflector.
    """
    out = {}
    for n in names:
        if not n.endswith(".const") or n.endswith(".ez.const"):
            continue
        sig = opts.reuse_link_mm * 1e-3 if ".d" in n else math.radians(opts.reuse_link_deg)
        if math.isfinite(sig):
            out[n] = sig
    return out


def _earlier_support(previous: CalibratedModel) -> dict[int, NDArray[np.intp]]:
    """``data.map_support`` of an earlier model, checked: 0-based joint -> counts (n_knots,).

    Empty for files written before models recorded it. Raises :class:`ConfigError` naming
    the key when the entry is malformed (a hand-edited file).
    """
    raw = previous.data.get("map_support")
    if raw is None:
        return {}
    src = f"model {previous.model_id or '<unnamed>'}"
    if not isinstance(raw, dict):
        raise ConfigError("must be an object of per-joint knot counts", source=src,
                          key="data.map_support")
    out = {}
    for j, nk in enumerate(previous.model.spec.map_knots):
        v = raw.get(f"j{j + 1}")
        if nk == 0 or v is None:
            continue
        if not (isinstance(v, list) and len(v) == nk
                and all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in v)):
            raise ConfigError(f"must be a list of {nk} non-negative integers (one per knot)",
                              source=src, key=f"data.map_support.j{j + 1}")
        out[j] = np.asarray(v, dtype=np.intp)
    return out


def _earlier_map_settings(previous: CalibratedModel) -> dict[int, tuple[float, float]]:
    """Smoothness weight (1/rad^2) and ridge sigma (rad) of each earlier map (0-based joint)."""
    src = f"model {previous.model_id or '<unnamed>'}"
    out = {}
    raw = previous.fit.get("map_priors") or []
    if not isinstance(raw, list):
        raise ConfigError("must be a list", source=src, key="fit.map_priors")
    for i, d in enumerate(raw):
        try:
            j = int(d["joint"]) - 1
            lam, ridge = float(d["lambda_per_rad2"]), math.radians(float(d["ridge_sigma_deg"]))
        except (TypeError, KeyError, ValueError):
            raise ConfigError("needs joint, lambda_per_rad2 and ridge_sigma_deg", source=src,
                              key=f"fit.map_priors[{i}]") from None
        if not (0 <= j < previous.robot.dof and math.isfinite(lam) and lam >= 0
                and math.isfinite(ridge) and ridge > 0):
            raise ConfigError("joint out of range, or a weight that is not finite and positive",
                              source=src, key=f"fit.map_priors[{i}]")
        out[j] = (lam, ridge)
    return out


def _gap_knots(knots: tuple[int, ...], support: NDArray[np.intp], n_knots: int,
               min_points: int, min_gap_deg: float) -> set[int]:
    """Knots of ``knots`` in runs of consecutive weakly supported knots at least
    ``min_gap_deg`` wide: the earlier data's real gaps, not the odd thin knot of a random
    design (those keep their bridged values)."""
    present = set(knots)
    weak = {k for k in knots if support[k] < min_points}
    out: set[int] = set()
    seen: set[int] = set()
    for k in sorted(weak):
        if k in seen:
            continue
        run = [k]
        a = (k - 1) % n_knots                       # walk back and forth around the circle
        while a in weak and a in present and a not in run:
            run.insert(0, a)
            a = (a - 1) % n_knots
        b = (k + 1) % n_knots
        while b in weak and b in present and b not in run:
            run.append(b)
            b = (b + 1) % n_knots
        seen.update(run)
        if len(run) * 360.0 / n_knots >= min_gap_deg:
            out.update(run)
    return out


def _gap_priors(previous: CalibratedModel, q: Array, opts: FitOptions,
                support: dict[int, NDArray[np.intp]],
                settings: dict[int, tuple[float, float]]) -> list[MapPrior]:
    """Priors that let the new data fill the gaps of the earlier model's angle maps.

    Knots in runs of at least ``reuse_min_gap_deg`` where fewer than ``map_min_points``
    earlier poses lay (gaps the earlier fit only bridged) are refitted where the new data
    ``q`` (n, dof) rad reach them, with the earlier smoothness prior acting on the change; all
    other knots keep their values (prior sigma ``reuse_anchor_deg`` on the change). Maps
    without such gaps stay frozen.
    """
    spec = previous.model.spec
    out = []
    for j, nk in enumerate(spec.map_knots):
        knots = tuple(sorted(t.index for t in spec.terms if t.joint == j and t.family == "map"))
        if not knots or j not in support or j not in settings:
            continue
        gap = _gap_knots(knots, support[j], nk, opts.map_min_points, opts.reuse_min_gap_deg)
        anchored = tuple(k for k in knots if k not in gap)
        new = knot_counts(q[:, j], nk)
        if not any(new[k] > 0 for k in knots if k not in set(anchored)):
            continue
        lam, ridge = settings[j]
        out.append(MapPrior(j, nk, knots, lam * opts.reuse_smoothing, ridge, anchored=anchored,
                            anchor_sigma=math.radians(opts.reuse_anchor_deg)))
    return out


def _map_support(spec: ErrorModelSpec, q: Array,
                 earlier: dict[int, NDArray[np.intp]] | None) -> dict[str, list[int]]:
    """Poses in each map knot's support, per mapped joint (``{"j2": [counts...]}``).

    A refit adds its new poses to the earlier model's counts (0-based joint -> counts).
    """
    out = {}
    for j, nk in enumerate(spec.map_knots):
        if nk == 0:
            continue
        c = knot_counts(q[:, j], nk)
        prev = (earlier or {}).get(j)
        if prev is not None and len(prev) == nk:
            c = c + prev
        out[f"j{j + 1}"] = [int(v) for v in c]
    return out
