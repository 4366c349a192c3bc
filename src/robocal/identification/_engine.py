"""The fitting engine: one measurement set, robust ML/MAP solves of any error model on it."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robocal._core.arrays import Array, BoolArray, IntArray
from robocal._core.measurements import MeasurementSet
from robocal.errors import NotConverged, NotIdentifiable
from robocal.identification._linalg import CHI2_3_MEDIAN, chi2_3_isf, median
from robocal.identification._models import MapPrior, map_terms, penalty_for
from robocal.identification._solver import (
    MAX_ITERATIONS,
    Identifiability,
    Problem,
    SolveInfo,
    analyse_jacobian,
    inverse_spd,
    levenberg_marquardt,
)
from robocal.identification._structured import has_maps, hat_blocks
from robocal.identification._weights import (
    TrackerSigma,
    euler_xyz_matrices,
    orientation_whitening,
    whitening,
)
from robocal.kinematics import KinematicModel, RobotDescription


@dataclass(frozen=True)
class EngineSettings:
    """Numerical settings the engine needs (a subset of :class:`FitOptions`)."""

    #: the tracker's noise, and whether the points' own sigmas (with this floor) weigh them
    noise: TrackerSigma = field(default_factory=TrackerSigma)
    use_point_sigma: bool = True
    point_sigma_floor_m: float | None = None
    #: relative singular-value threshold of the identifiability analysis
    rank_tol: float = 3e-4
    #: Levenberg-Marquardt: iterations and relative cost decrease at convergence; a run at
    #: max_iter still creeping (decrease or remaining below these) is kept
    max_iter: int = 300
    ftol: float = 1e-10
    creep_ftol: float = 1e-7
    creep_remaining: float = 1e-3
    #: outlier rejection
    detect_outliers: bool = True
    outlier_alpha: float = 0.01  # family-wise false-rejection rate over the poses
    outlier_sigma: float | None = None  # a fixed threshold instead, in sigmas
    outlier_sigma_min: float = 8.0  # the threshold is never below this many sigmas
    outlier_max_rounds: int = 6
    outlier_max_fraction: float = 0.2  # of the poses, at most
    min_redundancy: float = 0.1
    chunk: int = 2048


def point_sigmas(data: MeasurementSet, settings: EngineSettings, floor_m: float = 0.0
                 ) -> Array | None:
    """Per-point sigmas (n, 3) m the fit weights with, or None (tracker model): the data's
    ``sx, sy, sz`` combined in quadrature with ``floor_m`` (see :meth:`Engine.reweight`)."""
    if not settings.use_point_sigma or data.sigma is None:
        return None
    return np.hypot(data.sigma, floor_m) if floor_m > 0 else data.sigma


def model_error_sigma(data: MeasurementSet, sol: Solution) -> float:
    """Per-coordinate sigma (m) of what the per-point sigmas leave out: the variance
    component ``max(0, r^T r / (m - p) - mean(s^2))`` of the inlier residuals of ``sol``
    (m coordinates, p free parameters), 0 without per-point sigmas.

    A tracker's sigmas (about 0.01 mm) describe its own scatter; a robot model leaves
    0.05-0.1 mm of model error that no sigma column carries, so weighting by the sigmas alone
    trusts some poses far more than the model deserves (docs/adr/0032).
    """
    if data.sigma is None:
        return 0.0
    inl = sol.inliers
    r = sol.model.positions(data.q[inl], sol.x) - data.p[inl]
    m = r.size
    if m <= sol.n_free:
        return 0.0
    tau2 = float(np.sum(r * r)) / (m - sol.n_free) - float(np.mean(data.sigma[inl] ** 2))
    return math.sqrt(tau2) if tau2 > 0 else 0.0


def min_poses(identifiable: int, *, min_redundancy: float = 0.1) -> int:
    """Fewest poses a fit accepts for ``identifiable`` parameters (3 coordinates per pose).

    The fit needs a redundancy (coordinates minus identifiable parameters) of at least 6 and
    at least ``min_redundancy`` of the coordinates, so that the variance factor and the
    outlier test mean something. The planner uses this too, so a plan of this many poses for
    a model always fits (when its poses identify as many parameters as the planner counted).
    """
    if identifiable < 0 or not 0 <= min_redundancy < 1:
        raise ValueError("identifiable must be >= 0 and min_redundancy in [0, 1)")
    n = max(1, math.ceil((identifiable + 6) / 3))
    while 3 * n - identifiable < max(6, math.ceil(min_redundancy * 3 * n)):
        n += 1
    return n


@dataclass
class Solution:
    """A solved model: parameters, which were free, identifiability, outliers, covariance."""

    model: KinematicModel
    x: Array
    free: IntArray
    priors: tuple[MapPrior, ...]
    ident: Identifiability
    removed: list[str]
    info: SolveInfo
    inliers: BoolArray                 # over the engine's poses
    variance_factor: float
    dof_effective: float
    covariance: Array                  # (P, P) SI, a-posteriori (scaled by variance factor)
    outlier_threshold: float
    robust_sigma: float
    rounds: int
    stats: Array                       # per-pose outlier statistic (n,), in robust sigma^2
    #: the linear thermal term solved in by ``auto`` (``fit.thermal`` of MODEL.json), or None
    thermal: dict[str, Any] | None = None

    @property
    def n_free(self) -> int:
        """Number of estimated parameters."""
        return len(self.free)


class Engine:
    """Holds one measurement set and its whitening; solves models on it."""

    def __init__(self, robot: RobotDescription, data: MeasurementSet,
                 settings: EngineSettings) -> None:
        self.robot = robot
        self.data = data
        self.s = settings
        self.sigma_floor_m = settings.point_sigma_floor_m or 0.0
        self.reweight(self.sigma_floor_m)
        # 6-DoF probe: orientation residuals weighted by their own sigmas
        self.R_probe = self.W_rot = None
        if data.rot is not None:
            self.R_probe = euler_xyz_matrices(data.rot)
            self.W_rot = orientation_whitening(
                data.rot, data.rot_sigma if settings.use_point_sigma else None)

    def reweight(self, floor_m: float) -> None:
        """Whiten with the per-point sigmas combined with ``floor_m`` (m) in quadrature."""
        self.sigma_floor_m = floor_m
        sig = point_sigmas(self.data, self.s, floor_m)
        self.W = whitening(self.data.p, self.s.noise, sig)
        self.sigma_source = "tracker model" if sig is None else "per-point sx,sy,sz"
        if sig is not None and floor_m > 0:
            self.sigma_source += f" + {floor_m * 1e3:.3g} mm model error in quadrature"

    @property
    def n(self) -> int:
        """Number of poses."""
        return len(self.data)

    def problem(self, model: KinematicModel, priors: Sequence[MapPrior] = (),
                target: Array | None = None, anchors: Mapping[str, float] | None = None
                ) -> Problem:
        """The whitened problem of ``model`` on all poses.

        The map ``priors`` and the ``anchors`` (parameter name -> prior sigma, SI) are centred
        on ``target`` (P,) (None: on zero).
        """
        pen = penalty_for(model.names, priors)
        if anchors:
            if pen is None:
                pen = np.zeros((model.size, model.size))
            idx = {n: i for i, n in enumerate(model.names)}
            for name, sigma in anchors.items():
                pen[idx[name], idx[name]] += 1.0 / sigma**2
        return Problem(model, self.data.q, self.data.p, self.W, penalty=pen, target=target,
                       chunk=self.s.chunk, R_probe=self.R_probe, W_rot=self.W_rot)

    # ------------------------------------------------------------------------------------
    def solve(self, model: KinematicModel, x0: Array, *, priors: Sequence[MapPrior] = (),
              fixed: Sequence[str] = (), inliers: BoolArray | None = None,
              robust: bool | None = None, what: str = "model",
              target: Array | None = None, anchors: Mapping[str, float] | None = None
              ) -> Solution:
        """Robust ML (MAP with ``priors``) fit of ``model`` starting at ``x0``.

        ``anchors`` (parameter name -> prior sigma, SI) add independent priors; all priors
        are centred on ``target`` (P,) (None: on zero). Penalised parameters are always free.

        Parameters named in ``fixed`` are held at their ``x0`` values. Redundant and
        unobservable parameters (rank analysis of the unpenalised columns at ``x0``) are held
        too and reported. With outlier detection on, poses failing the normalised residual
        test are excluded and the fit repeated until the set is stable.

        Raises
        ------
        NotIdentifiable
            Too few poses for the number of identifiable parameters.
        NotConverged
            The solver did not converge.
        """
        prob = self.problem(model, priors, target, anchors)
        names = model.names
        pen = {t.name for pr in priors for t in map_terms(pr.joint, pr.knots)} | set(anchors or ())
        fixed_set = set(fixed)
        cand = np.array([i for i, nm in enumerate(names) if nm not in pen and nm not in fixed_set],
                        dtype=np.intp)
        pen_idx = np.array([i for i, nm in enumerate(names) if nm in pen], dtype=np.intp)
        active = np.ones(self.n, dtype=bool) if inliers is None else inliers.copy()
        rows = np.flatnonzero(active)
        ident, keep, _ = analyse_jacobian(prob, x0, rows, cand, tol=self.s.rank_tol)
        free = np.sort(np.concatenate([cand[keep], pen_idx])).astype(np.intp)
        removed = [names[i] for i in cand[~keep]]
        if len(rows) < min_poses(ident.rank, min_redundancy=self.s.min_redundancy) \
                or ident.rank == 0:
            raise NotIdentifiable(
                f"too few poses for the {what}: {len(rows)} poses give {3 * len(rows)} "
                f"coordinates for {ident.rank} identifiable parameters (need at least "
                f"{min_poses(ident.rank, min_redundancy=self.s.min_redundancy)} poses)",
                parameters=removed)
        robust = self.s.detect_outliers if robust is None else robust
        pen_free = None if prob.penalty is None else prob.penalty[np.ix_(free, free)]

        def run(x_start: Array, act: BoolArray,
                start: tuple[Array, Array, float] | None = None) -> tuple[SolveInfo, Array]:
            info = levenberg_marquardt(prob, x_start, free, np.flatnonzero(act),
                                       max_iter=self.s.max_iter, ftol=self.s.ftol,
                                       start=start)
            # a run that hits max_iter while creeping along a flat valley is kept (reported
            # as not converged, with its status): its last step gained almost nothing, or
            # the Gauss-Newton model says the minimum is within creep_remaining of its cost
            # (a curved valley of a nearly unidentifiable combination, where LM's damping
            # cannot shrink: 50 UR10 poses). Every other failure is an error.
            creeping = (info.status == MAX_ITERATIONS
                        and (info.last_decrease <= self.s.creep_ftol
                             or info.remaining <= self.s.creep_remaining))
            if not (info.converged or creeping):
                raise NotConverged(f"the {what} fit did not converge after {info.iterations} "
                                   f"iterations ({info.status}: {info.message})")
            N = info.normal if pen_free is None else info.normal + pen_free
            return info, inverse_spd(N)

        info, Ninv = run(np.array(x0, dtype=float), active)
        rounds = 0
        thr = math.nan
        s2 = math.nan
        tstat = np.zeros(self.n)
        while robust:
            tstat, s2, thr = self._outlier_statistics(prob, info.x, free, Ninv, active)
            flagged = tstat > thr
            cap = int(self.s.outlier_max_fraction * self.n)
            if flagged.sum() > cap:
                flagged = np.zeros(self.n, dtype=bool)
                flagged[np.argsort(-tstat)[:cap]] = True
            rounds += 1
            if np.array_equal(~flagged, active):
                break
            start = _moved_normals(prob, info, free, active, ~flagged)
            active = ~flagged
            info, Ninv = run(info.x, active, start)
            if rounds >= self.s.outlier_max_rounds:
                break
        x = info.x
        rows = np.flatnonzero(active)
        A = info.normal
        edf = float(np.sum(Ninv * A)) if len(free) else 0.0   # trace(Ninv @ A), A symmetric
        redundancy = max(3 * len(rows) - edf, 1.0)
        vf = info.data_cost / redundancy
        cov = np.zeros((model.size, model.size))
        cov[np.ix_(free, free)] = vf * Ninv
        return Solution(model=model, x=x, free=free, priors=tuple(priors), ident=ident,
                        removed=removed, info=info, inliers=active, variance_factor=vf,
                        dof_effective=edf, covariance=cov, outlier_threshold=thr,
                        robust_sigma=math.sqrt(s2) if np.isfinite(s2) else math.nan,
                        rounds=rounds, stats=tstat)

    def threshold(self, n: int) -> float:
        """Outlier threshold on the normalised statistic (chi-square 3 dof units)."""
        if self.s.outlier_sigma is not None:
            return float(self.s.outlier_sigma**2)
        return max(chi2_3_isf(self.s.outlier_alpha / n),
                   float(self.s.outlier_sigma_min**2))

    def _outlier_statistics(self, prob: Problem, x: Array, free: IntArray, Ninv: Array,
                            active: BoolArray) -> tuple[Array, float, float]:
        """Normalised residual statistic per pose, robust variance, threshold.

        ``t_j = r_j^T (I - H_jj)^{-1} r_j`` for poses in the fit (the deletion residual: how
        far the pose is from a fit without it) and ``r_j^T (I + H_jj)^{-1} r_j`` for excluded
        poses (prediction residual), ``H_jj`` the 3x3 hat block. Under the model ``t_j / s2``
        is chi-square with 3 degrees of freedom; ``s2`` is estimated robustly from the median.
        A pose is an outlier when ``t_j / s2`` exceeds the Bonferroni quantile at
        ``outlier_alpha`` and ``outlier_sigma_min**2`` (real residuals are dominated by
        heavy-tailed model error, so only gross errors are flagged).
        """
        t = hat_statistics(prob, x, free, Ninv, active)
        s2 = max(median(t[active]) / CHI2_3_MEDIAN, 1e-300)
        return t / s2, s2, self.threshold(self.n)


def _moved_normals(prob: Problem, info: SolveInfo, free: IntArray, before: BoolArray,
                   after: BoolArray) -> tuple[Array, Array, float] | None:
    """The normal equations at ``info.x`` over the poses ``after``, from the last run's over
    ``before`` with the poses that left or joined the fit taken out or added (a pass over a
    few poses instead of all); None when many changed."""
    out = np.flatnonzero(before & ~after)
    into = np.flatnonzero(after & ~before)
    if len(out) + len(into) > 0.25 * max(int(after.sum()), 1):
        return None
    A, g, c = info.normal.copy(), info.gradient.copy(), info.data_cost
    for rows, sign in ((out, -1.0), (into, 1.0)):
        if len(rows):
            dA, dg, dc = prob.normal_equations(info.x, rows, free)
            A += sign * dA
            g += sign * dg
            c += sign * dc
    return A, g, c


def hat_statistics(prob: Problem, x: Array, free: IntArray, Ninv: Array,
                   in_fit: BoolArray) -> Array:
    """``r^T (I -/+ H_jj)^{-1} r`` per pose (whitened), minus for poses in the fit."""
    n = prob.n
    if has_maps(prob, free):
        # map columns are four knots per pose: the hat blocks from the factored Jacobian
        H, r = hat_blocks(prob, x, np.arange(n), free, Ninv)
        return _deletion_statistic(H, r, in_fit)
    t = np.empty(n)
    k = len(free)
    for ch in prob.chunks(np.arange(n)):
        Jw, rw = prob.whitened_jacobian(x, ch, free)
        c = len(ch)
        # position rows only (6-DoF poses add orientation rows after them)
        Jc = Jw.reshape(c, -1, k)[:, :3]
        H = np.einsum("nik,kl,njl->nij", Jc, Ninv, Jc, optimize=True)
        t[ch] = _deletion_statistic(H, rw.reshape(c, -1)[:, :3], in_fit[ch])
    return t


def _deletion_statistic(H: Array, r: Array, in_fit: BoolArray) -> Array:
    """``r^T (I -/+ H) ^{-1} r`` (n,) from hat blocks H (n, 3, 3) and residuals r (n, 3)."""
    eye = np.eye(3)
    sign = np.where(in_fit, -1.0, 1.0)[:, None, None]
    sol = np.linalg.solve(eye + sign * H + 1e-9 * eye, r[:, :, None])[:, :, 0]
    return np.asarray(np.einsum("ni,ni->n", r, sol), dtype=np.float64)


def screen(engine: Engine, sol: Solution, data: MeasurementSet) -> Array:
    """Normalised prediction statistic (n,) of new poses under a solved model.

    Uses the solution's robust scale, so values compare directly with
    ``engine.threshold(...)``; large values are gross measurement errors of the new poses.
    """
    W = whitening(data.p, engine.s.noise, point_sigmas(data, engine.s, engine.sigma_floor_m))
    prob = Problem(sol.model, data.q, data.p, W, chunk=engine.s.chunk)
    vf = sol.variance_factor if sol.variance_factor > 0 else 1.0
    Ninv = sol.covariance[np.ix_(sol.free, sol.free)] / vf
    t = hat_statistics(prob, sol.x, sol.free, Ninv, np.zeros(len(data), dtype=bool))
    s2 = sol.robust_sigma**2 if np.isfinite(sol.robust_sigma) else 1.0
    return t / s2
