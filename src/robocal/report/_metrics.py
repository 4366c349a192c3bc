"""The numbers of the report: error statistics, "% described", ISO 9283, joint-error bands,
identifiability, workspace uncertainty and the verdict. Pure functions, SI in and out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.measurements import MeasurementSet
from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel, ParameterLayout
from robocal.report._input import Acceptance, IsoPoseSeries

Array = NDArray[np.float64]

SUCCEEDED, MARGINAL, FAILED = "succeeded", "marginal", "failed"
PASS, WARN, FAIL, INFO = "pass", "warn", "fail", "info"


# -- error statistics -----------------------------------------------------------------------
@dataclass(frozen=True)
class ErrorStats:
    """Statistics of position-error magnitudes (m)."""

    n: int
    rms_m: float
    mean_m: float
    max_m: float
    p95_m: float | None = None

    @classmethod
    def of(cls, norms: Array) -> ErrorStats:
        """Statistics of error magnitudes ``norms`` (n,) m."""
        d = np.asarray(norms, dtype=float)
        if d.size == 0:
            nan = float("nan")
            return cls(0, nan, nan, nan, nan)
        return cls(int(d.size), float(np.sqrt(np.mean(d**2))), float(np.mean(d)),
                   float(np.max(d)), float(np.percentile(d, 95)))

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly, mm."""
        return {"n": self.n, "rms_mm": _mm(self.rms_m), "mean_mm": _mm(self.mean_m),
                "max_mm": _mm(self.max_m), "p95_mm": _mm(self.p95_m)}


def _mm(v: float | None) -> float | None:
    if v is None or not math.isfinite(v):
        return None
    return float(v) * 1e3


@dataclass(frozen=True)
class Described:
    """Share of the baseline error a model describes, in % (paper §6.4).

    ``rms``: 1 - sqrt(sum r^2 / sum e^2); ``mean``: 1 - mean|r| / mean|e|; ``r2``: 1 - sum r^2 /
    sum e^2, with e the baseline (nominal, base + reflector fitted) and r the model residuals
    on the same poses.
    """

    rms: float | None
    mean: float | None
    r2: float | None

    def to_dict(self) -> dict[str, float | None]:
        """JSON-friendly, %."""
        return {"percent_rms": self.rms, "percent_mean": self.mean, "percent_r2": self.r2}


def described(baseline: Array, residual: Array) -> Described:
    """Paper §6.4 metrics from error magnitudes (n,) of the baseline and the model."""
    e = np.asarray(baseline, dtype=float)
    r = np.asarray(residual, dtype=float)
    if e.shape != r.shape:
        raise ConfigError("baseline and residual need the same poses")
    se, sr = float(np.sum(e**2)), float(np.sum(r**2))
    if e.size == 0 or se <= 0:
        return Described(None, None, None)
    return Described(100.0 * (1.0 - math.sqrt(sr / se)),
                     100.0 * (1.0 - float(np.mean(r)) / float(np.mean(e))),
                     100.0 * (1.0 - sr / se))


def residual_vectors(cm: CalibratedModel, data: MeasurementSet) -> Array:
    """Measured minus predicted positions (n, 3) m."""
    return data.p - cm.predict(data.q)


def stats_from_stored(d: Mapping[str, Any] | None
                      ) -> tuple[ErrorStats | None, Described | None, ErrorStats | None]:
    """Read accuracy numbers stored by identification (``rms_m`` or ``rms_mm`` style keys).

    Returns (model statistics, % described, baseline statistics), each None when absent.
    """
    if not isinstance(d, Mapping) or not d:
        return None, None, None

    def num(k: str) -> float | None:
        v = d.get(k)
        if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v):
            return float(v)
        return None

    def get(key: str) -> float | None:
        for k, f in ((f"{key}_m", 1.0), (f"{key}_mm", 1e-3)):
            v = num(k)
            if v is not None:
                return v * f
        return None

    def stats(prefix: str) -> ErrorStats | None:
        rms = get(f"{prefix}rms")
        if rms is None:
            return None
        n = num("n")
        mean, mx = get(f"{prefix}mean"), get(f"{prefix}max")
        return ErrorStats(0 if n is None else int(n), rms,
                          float("nan") if mean is None else mean,
                          float("nan") if mx is None else mx, get(f"{prefix}p95"))

    def pct(*keys: str) -> float | None:
        for k in keys:
            v = num(k)
            if v is not None:
                return v
        return None

    desc: Described | None = Described(
        pct("percent_described_rms", "percent_rms"),
        pct("percent_described_mean", "percent_mean"),
        pct("percent_described_r2", "percent_r2"))
    assert desc is not None
    if desc.rms is None and desc.mean is None and desc.r2 is None:
        desc = None
    return stats(""), desc, stats("baseline_")


# -- nominal baseline -------------------------------------------------------------------------
def fit_nominal_baseline(reference: CalibratedModel, data: MeasurementSet, *,
                         iterations: int = 8) -> CalibratedModel:
    """The nominal robot with only base and reflector fitted to ``data`` (Gauss-Newton).

    Starts from ``reference``'s base and reflector; used when no ``nominal`` fit is given.
    """
    model = KinematicModel(reference.robot, ErrorModelSpec(reference.robot.dof, (),
                                                           label="nominal"),
                           reference.model.T_ref)
    x = model.nominal_params()
    for part in (ParameterLayout.BASE, ParameterLayout.TOOL):  # base and reflector
        x[part] = reference.params[part]
    for _ in range(iterations):
        p, J = model.jacobian(data.q, x)
        A = J.reshape(-1, model.size)
        step, *_ = np.linalg.lstsq(A, (data.p - p).ravel(), rcond=None)
        x = x + step
        if float(np.max(np.abs(step))) < 1e-12:
            break
    return CalibratedModel(model, x, kind="nominal", fit={"note": "fitted by the report"})


# -- ISO 9283 ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class IsoResult:
    """ISO 9283 pose accuracy AP and repeatability RP of one pose (m).

    ``ap_model_m``: AP against the calibrated model's prediction (None when not given).
    """

    name: str
    n: int
    ap_m: float
    ap_xyz_m: tuple[float, float, float]
    rp_m: float | None                 # None with a single cycle: RP needs repeats
    mean_dist_m: float
    std_dist_m: float
    ap_model_m: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly, mm."""
        return {"pose": self.name, "n": self.n, "AP_mm": self.ap_m * 1e3,
                "AP_xyz_mm": [v * 1e3 for v in self.ap_xyz_m], "RP_mm": _mm(self.rp_m),
                "mean_distance_mm": self.mean_dist_m * 1e3,
                "std_distance_mm": self.std_dist_m * 1e3,
                "AP_after_calibration_mm": _mm(self.ap_model_m)}


def iso9283(series: IsoPoseSeries) -> IsoResult:
    """ISO 9283 §7.2.1 / §7.2.2 for one pose.

    AP = |x̄ - x_c| (x̄ the barycentre of the attained positions, x_c the command), with
    components x̄ - x_c; RP = l̄ + 3 S_l with l_j = |x_j - x̄|, l̄ their mean and S_l their
    sample standard deviation (n - 1); RP is None for a single cycle.
    """
    a = series.attained
    bary = a.mean(axis=0)
    d = bary - series.command
    dist = np.linalg.norm(a - bary, axis=1)
    n = a.shape[0]
    mean = float(dist.mean())
    std = float(dist.std(ddof=1)) if n > 1 else 0.0
    ap_model = (None if series.predicted is None
                else float(np.linalg.norm(bary - series.predicted)))
    return IsoResult(series.name, n, float(np.linalg.norm(d)),
                     (float(d[0]), float(d[1]), float(d[2])),
                     mean + 3.0 * std if n > 1 else None, mean, std, ap_model)


def iso_series_from_measurements(data: MeasurementSet, purposes: Sequence[str], *,
                                 command: Array | CalibratedModel,
                                 predicted: Array | CalibratedModel | None = None
                                 ) -> list[IsoPoseSeries]:
    """Group repeated ISO measurements by purpose (``iso-P1`` .. ``iso-P5`` or ``P1``..).

    ``data.q`` are the commanded joints, ``purposes`` (n,) each pose's purpose. ``command``:
    the commanded positions (n, 3) m, or a model (typically the nominal one, base and
    reflector fitted) evaluated at ``data.q``; ``predicted`` likewise for the calibrated model.
    Poses whose purpose is not an ISO pose are ignored.
    """
    if len(purposes) != len(data):
        raise ConfigError("purposes need one entry per pose")

    def positions(v: Array | CalibratedModel) -> Array:
        if isinstance(v, CalibratedModel):
            return v.predict(data.q)
        a = np.atleast_2d(np.asarray(v, dtype=float))
        if a.shape != (len(data), 3):
            raise ConfigError("command/predicted positions need shape (n, 3)")
        return a

    cmd = positions(command)
    pred = None if predicted is None else positions(predicted)
    groups: dict[str, list[int]] = {}
    for i, p in enumerate(purposes):
        name = str(p)
        if name.lower().startswith("iso-"):
            name = name[4:]
        if name.upper() in ("P1", "P2", "P3", "P4", "P5"):
            groups.setdefault(name.upper(), []).append(i)
    return [IsoPoseSeries(name, cmd[idx].mean(axis=0), data.p[idx],
                          None if pred is None else pred[idx].mean(axis=0))
            for name, idx in sorted(groups.items())]


# -- joint-dependent errors -------------------------------------------------------------------
@dataclass(frozen=True)
class ComponentCurve:
    """One error component of one joint over the joint angle (SI), with 1-sigma."""

    component: str
    value: Array
    sigma: Array | None
    n_terms: int


@dataclass(frozen=True)
class JointCurves:
    """The joint-dependent part (all terms but ``const`` and ``gravity``) of joint ``joint``."""

    joint: int
    angle: Array
    covered: tuple[float, float] | None
    curves: tuple[ComponentCurve, ...]


def joint_curves(cm: CalibratedModel, joint: int, *, points: int = 181,
                 removed: Sequence[str] = ()) -> JointCurves:
    """Evaluate the identified joint-dependent errors of ``joint`` (0-based) over its range.

    The value of a component is ``B_c(q) · x_c`` over its non-constant terms, centred on its
    mean over the covered range (``B_c`` minus its mean rows); its variance is
    ``B_c C_cc B_c^T`` (the centred basis columns are the gradient of the component with
    respect to its parameters). The other joints sit at the middle of their range (only ``gravity``
    terms depend on them, and those are left out).
    """
    robot = cm.robot
    lim = robot.joint_limits
    lo, hi = float(lim[joint, 0]), float(lim[joint, 1])
    covered = None
    if cm.coverage is not None:
        covered = (float(cm.coverage[joint, 0]), float(cm.coverage[joint, 1]))
    q = np.tile(lim.mean(axis=1), (points, 1))
    q[:, joint] = np.linspace(lo, hi, points)
    _, _, B = cm.model.joint_errors(q, cm.params)
    inside = np.ones(points, dtype=bool)
    if covered is not None:
        inside = (q[:, joint] >= covered[0]) & (q[:, joint] <= covered[1])
        if not inside.any():
            inside[:] = True
    terms = cm.model.spec.terms
    cov = cm.covariance
    sig = cm.sigma
    gone = set(removed)
    fixed = {k for k, t in enumerate(terms)
             if t.name in gone or (sig is not None and sig[ParameterLayout.OFFSET + k] == 0
                                   and cm.params[ParameterLayout.OFFSET + k] == 0)}
    curves = []
    for comp in ("dx", "dy", "dz", "ex", "ey", "ez"):
        cols = [k for k, t in enumerate(terms) if t.joint == joint and t.component == comp
                and t.family not in ("const", "gravity") and k not in fixed]
        if not cols:
            continue
        # centred on its mean over the covered range: the constant part of a component is not
        # separable from the constant terms (and from neighbouring joints' errors)
        Bc = B[:, cols] - B[inside][:, cols].mean(axis=0)
        pidx = [ParameterLayout.OFFSET + k for k in cols]
        value = Bc @ cm.params[pidx]
        sigma = None
        if cov is not None:
            C = cov[np.ix_(pidx, pidx)]
            sigma = np.sqrt(np.clip(np.einsum("np,pq,nq->n", Bc, C, Bc), 0.0, None))
        curves.append(ComponentCurve(comp, value, sigma, len(cols)))
    return JointCurves(joint, q[:, joint].copy(), covered, tuple(curves))


# -- identifiability --------------------------------------------------------------------------
@dataclass
class Identifiability:
    """Scaled-Jacobian SVD, correlations and per-parameter sigmas of one model."""

    singular_values: Array | None = None
    condition: float | None = None
    rank: int | None = None
    n_free: int = 0
    n_params: int = 0
    removed: tuple[str, ...] = ()
    correlations: list[tuple[str, str, float]] = field(default_factory=list)
    parameters: list[dict[str, Any]] = field(default_factory=list)
    source: str = "column-normalised position Jacobian at the calibration poses (report)"

    def use_fit(self, info: Mapping[str, Any]) -> None:
        """Take rank, condition and singular values the fit reported, when it did."""
        sv = info.get("singular_values")
        if sv:
            self.singular_values = np.asarray(sv, dtype=float)
            self.source = str(info.get("note") or "identification Jacobian (from the fit)")
            if info.get("condition_number") is not None:
                self.condition = float(info["condition_number"])
            elif self.singular_values[-1] > 0:
                self.condition = float(self.singular_values[0] / self.singular_values[-1])
            self.rank = int(info["rank"]) if info.get("rank") is not None else None

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly."""
        return {
            "source": self.source,
            "condition_number": self.condition, "rank": self.rank, "n_free": self.n_free,
            "n_parameters": self.n_params, "removed": list(self.removed),
            "singular_values": None if self.singular_values is None
            else [float(v) for v in self.singular_values],
            "strongest_correlations": [{"a": a, "b": b, "rho": r}
                                       for a, b, r in self.correlations],
        }


_TO_SCREEN = {"m": (1e3, "mm"), "rad": (180.0 / math.pi, "deg"),
              "rad/(N m)": (180.0 / math.pi, "deg/(N m)")}


def identifiability(cm: CalibratedModel, q: Array | None, removed: Sequence[str] = (), *,
                    top: int = 12, rel_tol: float = 1e-8, svd: bool = True) -> Identifiability:
    """SVD of the column-normalised position Jacobian at poses ``q`` over the free parameters
    (those not ``removed`` and, when a covariance exists, with non-zero variance), plus the
    strongest correlations and a value ± sigma table (mm, deg). ``svd=False`` skips the SVD
    (when the fit already reported its singular values)."""
    names = cm.model.names
    units = cm.model.layout.units
    removed_set = set(removed)
    sig = cm.sigma
    free = np.array([n not in removed_set for n in names])
    if sig is not None:
        free &= sig > 0
    out = Identifiability(n_params=len(names), n_free=int(free.sum()), removed=tuple(removed))
    if svd and q is not None and len(q) and free.any():
        _, J = cm.model.jacobian(q, cm.params)
        A = J.reshape(-1, cm.model.size)[:, free]
        scale = np.linalg.norm(A, axis=0)
        scale[scale == 0] = 1.0
        s = np.linalg.svd(A / scale, compute_uv=False)
        out.singular_values = s
        tol = rel_tol * s[0] if s.size else 0.0
        out.rank = int(np.sum(s > tol))
        smin = s[-1] if s.size else 0.0
        out.condition = float(s[0] / smin) if smin > 0 else float("inf")
    cov = cm.covariance
    if cov is not None and sig is not None:
        ok = np.flatnonzero(sig > 0)
        if ok.size > 1:
            C = cov[np.ix_(ok, ok)] / np.outer(sig[ok], sig[ok])
            iu = np.triu_indices(ok.size, 1)
            rho = C[iu]
            order = np.argsort(-np.abs(rho))[:top]
            out.correlations = [(names[ok[iu[0][k]]], names[ok[iu[1][k]]], float(rho[k]))
                                for k in order]
    for k, name in enumerate(names):
        f, u = _TO_SCREEN[units[k]]
        sd = None if sig is None else float(sig[k] * f)
        v = float(cm.params[k] * f)
        out.parameters.append({"name": name, "value": v, "sigma": sd, "unit": u,
                               "removed": name in removed_set})
    return out


# -- workspace --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Workspace:
    """Predicted 1-sigma position uncertainty (3-D norm, m) at sampled joint configurations."""

    q: Array
    position: Array
    sigma: Array
    within: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly, mm."""
        s = self.sigma * 1e3
        return {"samples": int(s.size), "within": self.within,
                "sigma_mm": {"median": float(np.median(s)), "p95": float(np.percentile(s, 95)),
                             "max": float(np.max(s))}}


def workspace(cm: CalibratedModel, n: int, seed: int = 0, *, chunk: int = 500) -> Workspace | None:
    """Sample ``n`` joint configurations uniformly inside the covered range (or the joint
    limits) and evaluate :meth:`CalibratedModel.prediction_sigma` there."""
    if cm.covariance is None or n <= 0:
        return None
    rng = np.random.default_rng(seed)
    if cm.coverage is not None:
        lim, within = np.asarray(cm.coverage, dtype=float), "calibrated joint range"
    else:
        lim, within = cm.robot.joint_limits, "joint limits"
    q = rng.uniform(lim[:, 0], lim[:, 1], (n, cm.robot.dof))
    # as CalibratedModel.prediction_sigma (J C J^T per pose, its diagonal), restricted to the
    # parameters with non-zero variance and done as one matrix product per chunk
    var = np.clip(np.diag(cm.covariance), 0.0, None)
    idx = np.flatnonzero(var > 0)
    C = cm.covariance[np.ix_(idx, idx)]
    sig = np.empty(n)
    pos = np.empty((n, 3))
    for i in range(0, n, chunk):
        p, J = cm.model.jacobian(q[i:i + chunk], cm.params)
        Jf = J[:, :, idx].reshape(-1, idx.size)
        v = np.einsum("kp,kp->k", Jf @ C, Jf).reshape(-1, 3)
        sig[i:i + chunk] = np.sqrt(np.clip(v, 0.0, None).sum(axis=1))
        pos[i:i + chunk] = p
    return Workspace(q, pos, sig, within)


# -- verdict ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Check:
    """One acceptance check: ``status`` in pass / warn / fail / info."""

    name: str
    status: str
    message: str

    def to_dict(self) -> dict[str, str]:
        """JSON-friendly."""
        return {"check": self.name, "status": self.status, "message": self.message}


@dataclass(frozen=True)
class Verdict:
    """Overall outcome with its reason and the checks behind it."""

    outcome: str
    headline: str
    checks: tuple[Check, ...]
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly."""
        return {"outcome": self.outcome, "headline": self.headline, "reason": self.reason,
                "checks": [c.to_dict() for c in self.checks]}


@dataclass(frozen=True)
class Judged:
    """What the verdict looks at (SI)."""

    model: str
    on: str                          # "validation" or "calibration"
    stats: ErrorStats | None
    baseline: ErrorStats | None
    described: Described | None
    calibration_rms_m: float | None = None
    n_outliers: int = 0
    n_poses: int = 0
    status: str = ""
    expected_ratio: float = 1.0      # validation/calibration RMS expected from fitting alone
    extrapolation: str = ""          # "N of M validation poses lie where ...", or ""


def _f(v: float | None, unit: str = " mm", digits: int = 3) -> str:
    if v is None or not math.isfinite(v):
        return "n/a"
    return f"{v:.{digits}f}{unit}"


def _improvement(j: Judged, acc: Acceptance, rms_mm: float, base_mm: float | None
                 ) -> tuple[Check, float | None]:
    """The improvement-over-nominal check and the percentage described (None: unknown)."""
    pct = None if j.described is None else j.described.rms
    if pct is None and base_mm is not None and base_mm > 0:
        pct = 100.0 * (1.0 - rms_mm / base_mm)
    if pct is None:
        return Check("improvement", WARN, "no nominal baseline: the improvement over the "
                                          "nominal model cannot be shown"), pct
    if pct <= 0.0:
        return Check("improvement", FAIL,
                     f"{j.on} RMS {_f(rms_mm)} is not below the nominal "
                     f"{_f(base_mm)}: the model does not improve accuracy"), pct
    if pct < acc.min_percent_described:
        return Check("improvement", WARN,
                     f"describes only {pct:.1f} % of the nominal error (RMS-based); "
                     f"threshold {acc.min_percent_described:.0f} %"), pct
    return Check("improvement", PASS,
                 f"describes {pct:.1f} % of the nominal error (RMS-based; "
                 f"threshold {acc.min_percent_described:.0f} %)"), pct


def _limits(j: Judged, stats: ErrorStats, acc: Acceptance, rms_mm: float) -> list[Check]:
    """The absolute checks: plausibility, RMS limit, max-error limit."""
    checks: list[Check] = []
    if rms_mm > acc.implausible_rms_mm:
        checks.append(Check("plausibility", FAIL,
                            f"{j.on} RMS {_f(rms_mm)} is implausible for a calibrated robot "
                            f"(> {_f(acc.implausible_rms_mm)}): check the units of the data "
                            "(joints in degrees, positions in mm) and the robot description"))
    if acc.max_rms_mm is not None:
        ok = rms_mm <= acc.max_rms_mm
        checks.append(Check("RMS limit", PASS if ok else FAIL,
                            f"{j.on} RMS {_f(rms_mm)} {'≤' if ok else '>'} limit "
                            f"{_f(acc.max_rms_mm)}"))
    mx = stats.max_m * 1e3
    if acc.max_error_mm is not None and math.isfinite(mx):
        ok = mx <= acc.max_error_mm
        checks.append(Check("max-error limit", PASS if ok else FAIL,
                            f"{j.on} max error {_f(mx)} {'≤' if ok else '>'} limit "
                            f"{_f(acc.max_error_mm)}"))
    return checks


def _held_out(j: Judged, acc: Acceptance, rms_mm: float) -> list[Check]:
    """Held-out data, over-fitting, extrapolation and outlier checks."""
    checks: list[Check] = []
    if j.on != "validation":
        checks.append(Check("held-out poses", WARN,
                            "no validation poses: judged on the calibration poses, which "
                            "flatters the model"))
    elif j.calibration_rms_m is not None and math.isfinite(j.calibration_rms_m):
        cal = j.calibration_rms_m * 1e3
        ratio = rms_mm / cal if cal > 0 else math.inf
        limit = acc.max_overfit_ratio * j.expected_ratio
        over = ratio > limit and rms_mm - cal > acc.overfit_floor_mm
        expl = (f"; {j.expected_ratio:.2f} expected from the parameter count alone"
                if j.expected_ratio > 1.0 else "")
        checks.append(Check("over-fitting", WARN if over else PASS,
                            f"validation RMS {_f(rms_mm)} vs calibration {_f(cal)} "
                            f"(ratio {ratio:.2f}{expl}; limit {limit:.2f})"))
    if j.extrapolation:
        checks.append(Check("extrapolation", WARN, j.extrapolation))
    if j.n_poses > 0:
        frac = j.n_outliers / j.n_poses
        status = (FAIL if frac > acc.fail_outlier_fraction
                  else WARN if frac > acc.max_outlier_fraction else PASS)
        checks.append(Check("outliers", status,
                            f"{j.n_outliers} of {j.n_poses} poses rejected as outliers "
                            f"({100 * frac:.1f} %; limit {100 * acc.max_outlier_fraction:.0f} %)"))
    return checks


def verdict(j: Judged | None, acc: Acceptance) -> Verdict:
    """Apply the acceptance thresholds (see :class:`Acceptance`) to ``j``."""
    if j is None or j.stats is None:
        why = "no calibrated model with accuracy figures to judge."
        return Verdict(FAILED, f"Calibration failed: {why}",
                       (Check("model", FAIL, "no calibrated model"),), why.capitalize())
    checks: list[Check] = []
    rms_mm = j.stats.rms_m * 1e3
    base_mm = None if j.baseline is None else j.baseline.rms_m * 1e3
    st = j.status.lower()
    if st and any(w in st for w in ("fail", "not converged", "notconverged", "error")):
        checks.append(Check("fit status", FAIL, f"the fit reported status {j.status!r}"))
    improvement, pct = _improvement(j, acc, rms_mm, base_mm)
    checks.append(improvement)
    checks += _limits(j, j.stats, acc, rms_mm)
    checks += _held_out(j, acc, rms_mm)
    worst = max((c.status for c in checks), key=lambda s: {PASS: 0, INFO: 0, WARN: 1,
                                                           FAIL: 2}[s])
    outcome = {PASS: SUCCEEDED, INFO: SUCCEEDED, WARN: MARGINAL, FAIL: FAILED}[worst]
    numbers = f"{j.on} RMS {_f(rms_mm)}" + (f" vs {_f(base_mm)} nominal" if base_mm else "")
    if pct is not None:
        numbers += f", {pct:.1f} % of the measured error described"
    if outcome == SUCCEEDED:
        reason = numbers[0].upper() + numbers[1:] + "."
        headline = f"Calibration succeeded: {numbers}."
    else:
        why = "; ".join(c.message for c in checks if c.status == (
            FAIL if outcome == FAILED else WARN)) + f". ({numbers}.)"
        reason = why[0].upper() + why[1:]
        word = "failed" if outcome == FAILED else "is marginal"
        headline = f"Calibration {word}: {why}"
    return Verdict(outcome, headline, tuple(checks), reason)
