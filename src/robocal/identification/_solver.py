"""Weighted nonlinear least squares (MAP with quadratic priors) and identifiability analysis.

Everything works on the whitened problem ``r_j = W_j (y_j - h(q_j; x))`` with ``W_j`` the
inverse square root of the point covariance, so the data cost is ``sum_j |r_j|^2`` and a
unit-variance factor means the residuals match the tracker model. A quadratic prior
``(x - t)^T Pm (x - t)`` (smoothness of joint-angle maps, weak ridge) is added to the cost.
Jacobians are evaluated in chunks of poses and reduced to normal equations on the fly, so
memory stays bounded and the cost per iteration is linear in the number of poses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from robocal.errors import NotConverged, NotIdentifiable
from robocal.identification._linalg import spd_inverse, spd_solve
from robocal.identification._structured import has_maps, normal_blocks
from robocal.kinematics import KinematicModel, Term

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]


# ----------------------------------------------------------------------------------------------
# problem

# bytes of one chunk's Jacobian (see Problem.chunks)
JACOBIAN_CHUNK_BYTES = 32_000_000


@dataclass
class Problem:
    """A whitened least-squares problem over the poses of one measurement set.

    ``q`` (n, dof) rad, ``y`` (n, 3) m, ``W`` (n, 3, 3) 1/m. ``penalty`` (P, P) and
    ``target`` (P,) define the prior ``(x - target)^T penalty (x - target)`` (None: no prior).
    ``R_probe`` (n, 3, 3): measured 6-DoF probe orientations (tracker frame) or None, with
    whitening ``W_rot`` (n, 3, 3) 1/rad. With them every pose has 6 residuals: position, then
    the rotation vector ``log(R_obs R_flange(x)^T)``, where ``R_obs = R_probe R_tool^T`` and
    the flange -> probe rotation ``R_tool`` is aligned once on the model's nominal parameters
    (the last joint's constant rotation terms absorb what remains).
    """

    model: KinematicModel
    q: Array  # (n, dof) rad
    y: Array  # (n, 3) m
    W: Array  # (n, 3, 3) 1/m
    #: the prior (None: none)
    penalty: Array | None = None
    target: Array | None = None
    #: poses per Jacobian block (bounds the memory of one evaluation)
    chunk: int = 2048
    #: Jacobians evaluated so far (bench/bench_solver.py counts them)
    n_jacobians: int = field(default=0, init=False)
    R_probe: Array | None = None
    W_rot: Array | None = None
    R_obs: Array | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        if self.R_probe is not None:
            _, R, _ = self.model.flange_poses(self.q, self.model.nominal_params())
            U, _, Vt = np.linalg.svd(np.einsum("nji,njk->ik", R, self.R_probe))
            D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
            R_tool = U @ D @ Vt        # argmin sum |R_probe - R R_tool|, a rotation
            self.R_obs = self.R_probe @ R_tool.T
            if self.W_rot is None:
                raise ValueError("R_probe needs W_rot")

    @property
    def n(self) -> int:
        """Number of poses."""
        return int(self.q.shape[0])

    def residuals(self, x: Array, rows: IntArray | None = None) -> Array:
        """Whitened residuals (n, 3) (rows: subset of poses)."""
        q = self.q if rows is None else self.q[rows]
        y = self.y if rows is None else self.y[rows]
        W = self.W if rows is None else self.W[rows]
        if self.R_obs is not None:
            return self._pose_residuals(x, np.arange(self.n) if rows is None else rows)
        out = np.empty((q.shape[0], 3))
        for a in range(0, q.shape[0], self.chunk):
            sl = slice(a, a + self.chunk)
            p = self.model.positions(q[sl], x)
            out[sl] = np.einsum("nij,nj->ni", W[sl], y[sl] - p)
        return out

    def _pose_residuals(self, x: Array, rows: IntArray) -> Array:
        """Whitened position and orientation residuals (len(rows), 6)."""
        assert self.R_obs is not None and self.W_rot is not None
        out = np.empty((len(rows), 6))
        for a in range(0, len(rows), self.chunk):
            ch = rows[a:a + self.chunk]
            p, R, _ = self.model.flange_poses(self.q[ch], x)
            out[a:a + len(ch), :3] = np.einsum("nij,nj->ni", self.W[ch], self.y[ch] - p)
            out[a:a + len(ch), 3:] = np.einsum("nij,nj->ni", self.W_rot[ch],
                                               rotation_vectors(self.R_obs[ch], R))
        return out

    def prior_cost(self, x: Array) -> float:
        """Value of the quadratic prior at ``x``."""
        if self.penalty is None:
            return 0.0
        d = x - (self.target if self.target is not None else 0.0)
        return float(d @ self.penalty @ d)

    def prior_gradient(self, x: Array) -> Array:
        """``penalty (x - target)`` (P,)."""
        if self.penalty is None:
            return np.zeros_like(x)
        return self.penalty @ (x - (self.target if self.target is not None else 0.0))

    def cost(self, x: Array, rows: IntArray) -> float:
        """Data cost over ``rows`` plus the prior."""
        r = self.residuals(x, rows)
        return float(np.sum(r * r)) + self.prior_cost(x)

    def whitened_jacobian(self, x: Array, rows: IntArray, cols: IntArray
                          ) -> tuple[Array, Array]:
        """Whitened Jacobian (m len(rows), len(cols)) and residual (m len(rows),) of a chunk;
        m = 3, or 6 with orientations (position rows first in each pose's block)."""
        self.n_jacobians += 1
        if self.R_obs is not None:
            assert self.W_rot is not None
            p, R, J6 = self.model.pose_jacobian(self.q[rows], x)
            Jw6 = np.empty((len(rows), 6, len(cols)))
            J6 = np.take(J6, cols, axis=2)
            Jw6[:, :3] = np.einsum("nij,njk->nik", self.W[rows], J6[:, :3])
            Jw6[:, 3:] = np.einsum("nij,njk->nik", self.W_rot[rows], J6[:, 3:])
            rw6 = np.empty((len(rows), 6))
            rw6[:, :3] = np.einsum("nij,nj->ni", self.W[rows], self.y[rows] - p)
            rw6[:, 3:] = np.einsum("nij,nj->ni", self.W_rot[rows],
                                   rotation_vectors(self.R_obs[rows], R))
            return Jw6.reshape(-1, len(cols)), rw6.ravel()
        p, J = self.model.jacobian(self.q[rows], x)
        W = self.W[rows]
        # np.take, not J[:, :, cols]: a fancy index on the last axis is ~5x slower
        Jw = np.einsum("nij,njk->nik", W, np.take(J, cols, axis=2)).reshape(-1, len(cols))
        rw = np.einsum("nij,nj->ni", W, self.y[rows] - p).ravel()
        return Jw, rw

    def whitened_factors(self, x: Array, rows: IntArray, terms: IntArray | None = None
                         ) -> tuple[Array, Array, Array, Array]:
        """The whitened Jacobian of a chunk in factored form (see
        ``KinematicModel.jacobian_factors``): ``head`` (c, m, 9), ``sens`` (c, m, 6 dof), the
        basis ``B`` (c, len(terms)) of the terms ``terms`` (None: all) and the whitened
        residual (c, m), c = len(rows)."""
        self.n_jacobians += 1
        W = self.W[rows]
        if self.R_obs is not None:
            assert self.W_rot is not None
            Wr = self.W_rot[rows]
            p, R, head, sens, B = self.model.jacobian_factors(self.q[rows], x, orientation=True,
                                                               terms=terms)
            for M in (head, sens):
                M[:, :3] = np.einsum("nij,njk->nik", W, M[:, :3])
                M[:, 3:] = np.einsum("nij,njk->nik", Wr, M[:, 3:])
            rw = np.empty((len(rows), 6))
            rw[:, :3] = np.einsum("nij,nj->ni", W, self.y[rows] - p)
            rw[:, 3:] = np.einsum("nij,nj->ni", Wr, rotation_vectors(self.R_obs[rows], R))
            return head, sens, B, rw
        p, _, head, sens, B = self.model.jacobian_factors(self.q[rows], x, terms=terms)
        return (np.einsum("nij,njk->nik", W, head), np.einsum("nij,njk->nik", W, sens), B,
                np.einsum("nij,nj->ni", W, self.y[rows] - p))

    def chunks(self, rows: IntArray) -> list[IntArray]:
        """Split ``rows`` into chunks of at most ``self.chunk`` poses, and of at most about
        ``JACOBIAN_CHUNK_BYTES`` of Jacobian: an ``auto`` model with joint-angle maps has
        ~1,700 parameters, and 2,048 poses of its Jacobian (and the whitened copy and the
        products made from it) held several hundred MB at once."""
        m = 3 if self.R_obs is None else 6
        step = max(64, min(self.chunk, JACOBIAN_CHUNK_BYTES // (8 * m * max(self.model.size, 1))))
        return [rows[a:a + step] for a in range(0, len(rows), step)] or [rows]

    def normal_equations(self, x: Array, rows: IntArray, cols: IntArray
                         ) -> tuple[Array, Array, float]:
        """Data normal matrix ``J^T J`` (k, k), ``J^T r`` (k,) and data cost over ``rows``."""
        if has_maps(self, cols):
            # joint-angle map columns are sparse: their blocks are formed per pose
            G_g, b_g, c_g, _ = normal_blocks(self, x, rows, cols)
            return G_g[0], b_g[0], float(c_g[0])
        k = len(cols)
        A = np.zeros((k, k))
        g = np.zeros(k)
        c = 0.0
        for ch in self.chunks(rows):
            if len(ch) == 0:
                continue
            Jw, rw = self.whitened_jacobian(x, ch, cols)
            A += Jw.T @ Jw
            g += Jw.T @ rw
            c += float(rw @ rw)
        return A, g, c


def rotation_vectors(R_obs: Array, R: Array) -> Array:
    """Rotation vectors (n, 3) rad of ``R_obs R^T`` (tracker frame), angles up to pi."""
    M = np.einsum("nij,nkj->nik", R_obs, R)
    v = 0.5 * np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0],
                        M[:, 1, 0] - M[:, 0, 1]], axis=1)
    s = np.linalg.norm(v, axis=1)
    c = 0.5 * (np.einsum("nii->n", M) - 1.0)
    ang = np.arctan2(s, c)
    scale = np.where(s > 1e-12, ang / np.where(s > 1e-12, s, 1.0), 1.0)
    return v * scale[:, None]


# ----------------------------------------------------------------------------------------------
# Levenberg-Marquardt
#: Solver outcomes (like scipy's ``status``): only ``converged`` is a success.
CONVERGED = "converged"
MAX_ITERATIONS = "max-iterations"
NON_FINITE = "non-finite"
NO_PROGRESS = "no-progress"


@dataclass
class SolveInfo:
    """Outcome of :func:`levenberg_marquardt`.

    ``status`` is one of :data:`CONVERGED`, :data:`MAX_ITERATIONS` (``last_decrease`` tells
    whether it was still creeping), :data:`NON_FINITE` (the model gave non-finite values at the
    start or on every trial step) or :data:`NO_PROGRESS` (no damped step lowers the cost
    although the gradient says one should).
    """

    x: Array
    cost: float
    data_cost: float
    iterations: int
    status: str
    message: str
    normal: Array       # data normal matrix at the solution (k, k), free columns
    gradient: Array     # J^T r at the solution (k,)
    last_decrease: float = math.inf   # relative cost decrease of the last accepted step
    # relative cost decrease the undamped (Gauss-Newton) step still predicts at the end of a
    # run that hit max_iter: how far from the minimum it stopped (nan otherwise)
    remaining: float = math.nan

    @property
    def converged(self) -> bool:
        """True only for status :data:`CONVERGED`."""
        return self.status == CONVERGED


def levenberg_marquardt(prob: Problem, x0: Array, free: IntArray, rows: IntArray, *,
                        max_iter: int = 50, ftol: float = 1e-10, xtol: float = 1e-10,
                        mu0: float = 1e-9, gtol: float = 1e-7,
                        start: tuple[Array, Array, float] | None = None) -> SolveInfo:
    """Minimise data cost over ``rows`` + prior, varying parameters ``free`` only.

    Column-scaled Levenberg-Marquardt on the normal equations (Cholesky; a truncated
    eigen-solve if the damped matrix is numerically singular), Nielsen's damping update.
    Converged when the (predicted or actual) relative cost decrease falls below ``ftol``, the
    scaled step below ``xtol``, or the undamped Gauss-Newton step predicts a relative decrease
    below ``gtol``. When the damping grows past 1e12 without an accepted step,
    the point counts as converged only if the undamped model predicts a relative decrease
    below ``gtol`` (a minimum within rounding); otherwise the status is ``no-progress``, or
    ``non-finite`` when the trial steps produced non-finite model values. Hitting
    ``max_iter`` is status ``max-iterations``, never "converged".

    ``start``: the data normal matrix, ``J^T r`` and data cost at ``x0`` over ``rows`` when
    the caller has them (an outlier round updates the last run's), saving one pass.
    """
    x = np.array(x0, dtype=float)
    free = np.asarray(free, dtype=np.intp)
    if len(free) == 0:
        c = prob.cost(x, rows)
        st = CONVERGED if math.isfinite(c) else NON_FINITE
        return SolveInfo(x, c, c - prob.prior_cost(x), 0, st, "no free parameters",
                         np.zeros((0, 0)), np.zeros(0))
    Pm = None if prob.penalty is None else prob.penalty[np.ix_(free, free)]
    A, g, cd = prob.normal_equations(x, rows, free) if start is None else start
    cost = cd + prob.prior_cost(x)
    if not (math.isfinite(cost) and np.all(np.isfinite(A)) and np.all(np.isfinite(g))):
        return SolveInfo(x, cost, cd, 0, NON_FINITE,
                         "the model gives non-finite values at the starting point", A, g)
    At = A if Pm is None else A + Pm
    # Marquardt's column scaling: the damping mu I then weighs metres, radians and basis
    # functions of very different size (gravity torques, unit harmonics) alike, so mu0 and the
    # step test xtol need no per-model tuning
    scale = np.sqrt(np.clip(np.diag(At), 0.0, None))
    scale[scale <= 1e-300] = 1.0
    mu, nu = mu0, 2.0
    last_decrease = math.inf
    status, message = MAX_ITERATIONS, f"maximum number of iterations ({max_iter}) reached"
    it = 0
    while it < max_iter:
        it += 1
        At = A if Pm is None else A + Pm
        gs = (g - prob.prior_gradient(x)[free]) / scale
        As = At / np.outer(scale, scale)
        d = _damped_solve(As, gs, mu)
        # decrease of sum r^2 + prior predicted by the linearised model (factor 2: the cost is
        # not halved as in scipy): |r|^2 - |r - J d|^2 = 2 d.g - d.A.d
        predicted = float(2.0 * d @ gs - d @ As @ d)
        step = float(np.linalg.norm(d))
        xs = float(np.linalg.norm(x[free] * scale))
        # the convergence tests only count after an accepted step: after rejections the
        # damping shrinks the step, which says nothing about being at the minimum
        if nu == 2.0 and (predicted <= ftol * cost or step <= xtol * (xs + xtol)):
            status, message = CONVERGED, "converged"
            break
        if nu == 2.0 and predicted <= 1e3 * gtol * cost:
            # LM's damping can stay large in a curved valley and crawl for hundreds of steps
            # (UR10 high-order fits); when even the undamped Gauss-Newton step predicts less
            # than gtol, the point is a minimum within that tolerance
            d0 = _damped_solve(As, gs, mu0)
            if float(2.0 * d0 @ gs - d0 @ As @ d0) <= gtol * cost:
                status, message = CONVERGED, "converged (Gauss-Newton step below gtol)"
                break
        x_new = x.copy()
        x_new[free] += d / scale
        c_new = prob.cost(x_new, rows)
        finite = bool(np.isfinite(c_new))
        rho = (cost - c_new) / predicted if finite else -1.0
        if rho > 0:
            decrease = cost - c_new
            x = x_new
            A, g, cd = prob.normal_equations(x, rows, free)
            cost = cd + prob.prior_cost(x)
            # Nielsen's update: the better the quadratic model predicted the decrease (rho
            # near 1), the more the damping shrinks, by at most 3x; repeated rejections grow
            # it geometrically (nu doubles)
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            last_decrease = decrease / max(cost, 1e-300)
            if decrease <= ftol * cost:
                status, message = CONVERGED, "converged"
                break
        else:
            mu *= nu
            nu *= 2.0
            if mu > 1e12:
                d0 = _damped_solve(As, gs, mu0)
                pred0 = float(2.0 * d0 @ gs - d0 @ As @ d0)
                if pred0 <= gtol * cost:
                    status = CONVERGED
                    message = "converged (no further decrease within rounding)"
                elif not finite:
                    status = NON_FINITE
                    message = "every trial step gives non-finite model values"
                else:
                    status = NO_PROGRESS
                    message = (f"no step reduces the cost although a relative decrease of "
                               f"{pred0 / cost:.2g} is predicted")
                break
    remaining = math.nan
    if status == MAX_ITERATIONS:
        At = A if Pm is None else A + Pm
        gs = (g - prob.prior_gradient(x)[free]) / scale
        As = At / np.outer(scale, scale)
        d0 = _damped_solve(As, gs, mu0)
        remaining = float(2.0 * d0 @ gs - d0 @ As @ d0) / max(cost, 1e-300)
    return SolveInfo(x=x, cost=cost, data_cost=cd, iterations=it, status=status,
                     message=message, normal=A, gradient=g, last_decrease=last_decrease,
                     remaining=remaining)


def _damped_solve(As: Array, gs: Array, mu: float) -> Array:
    k = len(gs)
    try:
        d = spd_solve(As + mu * np.eye(k), gs)
        if np.all(np.isfinite(d)):
            return d
    except np.linalg.LinAlgError:
        pass
    # Cholesky fails only when the damped matrix is indefinite within rounding (tiny mu and
    # nearly dependent columns): step in the well-determined eigen-directions only, never
    # along directions that are rounding noise
    if not (np.all(np.isfinite(As)) and np.all(np.isfinite(gs))):
        return np.zeros(k)
    try:
        w, V = np.linalg.eigh(As)
    except np.linalg.LinAlgError:
        return np.zeros(k)
    keep = w > 1e-13 * max(w.max(), 1e-300)
    return V[:, keep] @ ((V[:, keep].T @ gs) / (w[keep] + mu))


def inverse_spd(A: Array) -> Array:
    """Inverse of a symmetric positive (semi-)definite matrix, column-scaled for stability."""
    s = np.sqrt(np.clip(np.diag(A), 0.0, None))
    s[s <= 1e-300] = 1.0
    As = A / np.outer(s, s)
    try:
        inv = spd_inverse(As)
    except np.linalg.LinAlgError:
        if not np.all(np.isfinite(As)):
            raise NotConverged("the normal matrix is not finite (non-finite model values)") \
                from None
        try:
            inv = np.linalg.pinv(As, rcond=1e-12, hermitian=True)
        except np.linalg.LinAlgError as err:
            raise NotConverged(f"the normal matrix cannot be inverted ({err})") from None
    return inv / np.outer(s, s)


# ----------------------------------------------------------------------------------------------
# identifiability
class Identifiability(NamedTuple):
    """Result of :func:`identifiability` (column-scaled identification Jacobian)."""

    rank: int
    cond: float
    removed: list[str]
    singular_values: Array


def term_tier(name: str) -> int:
    """Priority of a parameter when choosing which of a redundant set to keep (low = keep)."""
    if name.startswith(("base.", "tool.")):
        return 0
    t = Term.parse(name)
    if t.family == "const":
        return 1
    if t.family in ("poly", "cos", "sin"):
        return 2 + t.index
    if t.family in ("swcos", "swsin"):
        return 200 + t.index
    if t.family == "gravity":
        return 300
    return 400


def _normal_and_r(prob: Problem, x: Array, rows: IntArray, cols: IntArray
                  ) -> tuple[Array, Array]:
    """Normal matrix ``J^T J`` (k, k) and an R factor (<= k, k) of the whitened Jacobian of
    ``cols``, from one pass over the Jacobian chunks (each chunk's Jacobian costs as much as
    the two products together)."""
    k = len(cols)
    A = np.zeros((k, k))
    R: Array | None = None
    for ch in prob.chunks(rows):
        if len(ch) == 0:
            continue
        Jw, _ = prob.whitened_jacobian(x, ch, cols)
        A += Jw.T @ Jw
        if not np.all(np.isfinite(Jw)):
            return A, np.zeros((0, k))      # the caller reports the non-finite matrix
        X = Jw if R is None else np.vstack([R, Jw])
        # numpy stub types every mode as QRResult; mode="r" returns the R array alone
        R = np.linalg.qr(X, mode="r")  # type: ignore[assignment]
    if R is None:
        R = np.zeros((0, k))
    return A, R


def analyse_jacobian(prob: Problem, x: Array, rows: IntArray, cols: IntArray, *,
                     tol: float = 1e-6, factor: tuple[Array, Array] | None = None
                     ) -> tuple[Identifiability, BoolArray, Array]:
    """Rank analysis of the columns ``cols`` at ``x`` over poses ``rows``.

    ``factor``: ``(A, R)`` already accumulated by the caller in its own pass over the
    Jacobian: the normal matrix ``J^T J`` (k, k) of ``cols`` and an R factor (<= k, k) of
    the unscaled whitened Jacobian of ``cols`` (``R^T R = J^T J``); then no Jacobian is
    evaluated here.

    Returns the report, a mask over ``cols`` of the kept (identifiable) columns, and the
    column norms. Redundant columns are removed in order of :func:`term_tier` (higher-order
    terms go first; inside a tier, threshold pivoting prefers spec order), so e.g. a joint's
    constant offset is kept and the base correction it duplicates is kept too, while the
    duplicate joint constant goes.
    """
    names = prob.model.names
    cols = np.asarray(cols, dtype=np.intp)
    k = len(cols)
    if factor is None:
        factor = _normal_and_r(prob, x, rows, cols)
    A = factor[0]
    norms = np.sqrt(np.clip(np.diag(A), 0.0, None))
    nz = norms > 1e-12 * max(float(norms.max()), 1e-300)
    keep = np.zeros(k, dtype=bool)
    if not nz.any():
        rep = Identifiability(0, math.inf, [names[c] for c in cols], np.zeros(0))
        return rep, keep, norms
    sub = cols[nz]
    if not np.all(np.isfinite(A)):
        raise NotIdentifiable("the measurement Jacobian is not finite at the starting point "
                              "(check units and the robot description)")
    # rank from the R factor of J itself, not from J^T J: the normal matrix squares the
    # singular values, so a direction at 1e-8 of the largest would sink to 1e-16, i.e. into
    # rounding, and tol could not be resolved
    # Householder QR is invariant to column scaling up to rounding, so a factor of the
    # unscaled Jacobian, scaled afterwards, serves as well
    R = factor[1][:, nz] / norms[nz]
    try:
        _, S, Vt = np.linalg.svd(R, full_matrices=False)
    except np.linalg.LinAlgError:
        # LAPACK's divide-and-conquer SVD occasionally fails on ill-scaled input; the
        # symmetric eigen-decomposition of R^T R gives the same subspaces (squared values)
        try:
            w, V = np.linalg.eigh(R.T @ R)
        except np.linalg.LinAlgError as err:
            raise NotIdentifiable(f"rank analysis failed ({err}); the poses or the model are "
                                  "degenerate") from None
        order = np.argsort(w)[::-1]
        S = np.sqrt(np.clip(w[order], 0.0, None))
        Vt = V[:, order].T
    if not S[0] > 0:
        rep = Identifiability(0, math.inf, [names[c] for c in cols], np.zeros(0))
        return rep, keep, norms
    rank = int(np.count_nonzero(S / S[0] > tol))
    cond = float(S[0] / S[rank - 1]) if rank else math.inf
    M = S[:rank, None] * Vt[:rank]                      # (rank, k_nz): columns in row space
    tiers = np.array([term_tier(names[c]) for c in sub])
    chosen = _select_columns(M, tiers, rank, tau=max(30.0 * tol, 1e-5))
    kept_nz = np.zeros(len(sub), dtype=bool)
    kept_nz[chosen] = True
    keep[np.flatnonzero(nz)] = kept_nz
    removed = [names[c] for c, kk in zip(cols, keep, strict=True) if not kk]
    full_S = np.concatenate([S, np.zeros(max(0, len(sub) - len(S)))])
    return Identifiability(rank, cond, removed, full_S), keep, norms


def _select_columns(M: Array, tiers: NDArray[np.int_], rank: int, tau: float) -> list[int]:
    """Pick ``rank`` independent columns of ``M`` (rank, k), tier by tier (Gram-Schmidt)."""
    Rm = M.copy()
    nrm0 = np.linalg.norm(M, axis=0)
    nrm0[nrm0 == 0] = 1.0
    chosen: list[int] = []
    avail = np.ones(M.shape[1], dtype=bool)

    def take(j: int) -> None:
        v = Rm[:, j] / np.linalg.norm(Rm[:, j])
        Rm[:] -= np.outer(v, v @ Rm)
        Rm[:] -= np.outer(v, v @ Rm)   # re-orthogonalise
        chosen.append(j)
        avail[j] = False

    for t in sorted(set(tiers.tolist())):   # np.unique would import numpy.ma (17 ms)
        while len(chosen) < rank:
            cand = np.flatnonzero(avail & (tiers == t))
            if len(cand) == 0:
                break
            res = np.linalg.norm(Rm[:, cand], axis=0) / nrm0[cand]
            best = float(res.max())
            if best < tau:
                break
            take(int(cand[np.flatnonzero(res >= 0.5 * best)[0]]))
    while len(chosen) < rank and avail.any():  # rescue: fill up with the best remaining
        cand = np.flatnonzero(avail)
        res = np.linalg.norm(Rm[:, cand], axis=0)
        take(int(cand[int(np.argmax(res))]))
    return sorted(chosen)


def identifiability(model: KinematicModel, q: Array, x: Array, *, W: Array | None = None,
                    tol: float = 3e-4, params: list[str] | None = None) -> Identifiability:
    """Which parameters the poses ``q`` can identify, from the measurement Jacobian at ``x``.

    Parameters
    ----------
    model
        The error model.
    q
        Joint values (n, dof) rad of the actual poses.
    x
        Parameter vector (P,) SI at which to linearise (nominal is fine).
    W
        Optional whitening matrices (n, 3, 3); identity if None (column scaling makes units
        irrelevant).
    tol
        Relative singular-value threshold of the column-scaled Jacobian (default as
        :attr:`FitOptions.rank_tol`; directions weaker than this are only identifiable through
        second-order effects, e.g. offsets along parallel axes, and are held fixed).
    params
        Restrict the analysis to these parameter names (default: all).

    Returns
    -------
    Identifiability
        ``(rank, cond, removed_names, singular_values)``: numerical rank, condition number of
        the identifiable part, names of the parameters to hold fixed (redundant or
        unobservable), singular values (descending) of the column-scaled Jacobian.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    x = np.asarray(x, dtype=float)
    p = model.positions(q, x)
    Wm = np.broadcast_to(np.eye(3), (len(q), 3, 3)) if W is None else W
    prob = Problem(model, q, p, np.ascontiguousarray(Wm))
    if params is None:
        cols = np.arange(model.size)
    else:
        idx = {nm: i for i, nm in enumerate(model.names)}
        cols = np.array([idx[nm] for nm in params], dtype=np.intp)
    rep, _, _ = analyse_jacobian(prob, x, np.arange(len(q)), cols, tol=tol)
    return rep
