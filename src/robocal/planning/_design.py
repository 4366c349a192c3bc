"""Observability of an error model over a pose set, and D-optimal pose selection.

The identification Jacobian ``J`` (3 rows per pose, one column per parameter) is evaluated at
the nominal parameters in the robot base frame. Columns are scaled to unit RMS over the
candidate set (so metres and radians compare), and columns that are linear combinations of
others over the candidate set (redundant or unobservable with position-only data) are removed
by QR with column pivoting. On what is left, with singular values s_1 >= ... >= s_L of the
stacked matrix (m = 3 n rows), the observability indices of Sun & Hollerbach (2008) are

* O1 = (s_1 s_2 ... s_L)^(1/L) / sqrt(m)   (Borm & Menq; D-optimality),
* O2 = s_L / s_1                          (inverse condition number, Driels & Pathre),
* O3 = s_L                                (minimum singular value, Nahvi et al.),
* O4 = s_L^2 / s_1                        (noise amplification index, Nahvi & Hollerbach),
* O5 = 1 / (1/s_1 + ... + 1/s_L)          (Sun & Hollerbach; A-optimality).

Selection maximises O1 (the log-determinant of the information matrix) greedily and then by
Fedorov exchange; both only ever apply rank-3 (one pose) Woodbury updates to the inverse
information matrix and to each candidate's 3 x 3 prediction-variance block, so a step costs
O(n_candidates x L) instead of a refactorisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from robocal._core.model_names import MODELS
from robocal._core.threads import single_threaded
from robocal.errors import ConfigError
from robocal.identification import min_poses
from robocal.kinematics import (
    ErrorModelSpec,
    KinematicModel,
    ParameterLayout,
    RobotDescription,
    Term,
)
from robocal.planning._geometry import Array, Index, nearest_rows, range_scaled

#: Equations per identifiable parameter the recommended pose count aims for (3 per pose).
REDUNDANCY = 3.0

#: Pose-selection designs: ``stratified`` (default; one pose per k-means stratum of the joint
#: space, D-optimal within strata) and ``d-optimal`` (greedy + Fedorov exchange, no coverage).
DESIGNS = ("stratified", "d-optimal")


def design_note(model: str, design: str) -> str:
    """One sentence on what a plan's pose selection is good for (shown by ``robocal plan``).

    The figures are the measurements recorded in docs/adr/0004 (virtual LR Mate 200i in the
    demo cell, 10 seeds, held-out RMS against random feasible poses).
    """
    if design == "d-optimal":
        return (f"plain D-optimal for the {model} model: the most information for it, with poses "
                "at the extremes of the workspace, where a model lacking some of the robot's "
                "errors is most biased; prefer the stratified design unless the model is "
                "complete")
    if model == "constant":
        return ("stratified, D-optimal for the constant model within strata: representative of "
                "the workspace, so a constant fit is its best average there even when the robot "
                "has joint-dependent errors (measured: no worse than random poses at 60-250 "
                "poses; 0.78x random on a robot with constant errors only)")
    return (f"stratified, D-optimal for the high-order model within strata: for {model} fits "
            "(measured: 0.35x the held-out error of random poses at 100 poses) while a constant "
            "fit on the same poses stays no worse than on random ones")


def model_spec(robot: RobotDescription, model: str | ErrorModelSpec) -> ErrorModelSpec:
    """The error-model structure a plan is optimised for.

    ``"constant"``: a constant 6-DoF error per joint. ``"high-order"``: orders 0-2 Fourier
    terms of every error component, a pitch term (linear in q) on each joint's angle, and
    strain-wave ripple at 1 and 2 times the gear ratio where the robot file gives one (the
    structure of Ma et al., RCIM 2018; docs/adr/0002 decision 4). ``"auto"``: identification
    picks the model on validation data among these, so the plan is optimised for the
    richest, ``high-order``.
    An :class:`ErrorModelSpec` is used as given.

    Raises
    ------
    ConfigError
        For an unknown model name.
    """
    if isinstance(model, ErrorModelSpec):
        return model
    if model == "constant":
        return ErrorModelSpec.constant(robot.dof)
    if model in ("high-order", "auto"):
        spec = ErrorModelSpec.build(robot.dof, fourier=2, strain_wave=(1, 2),
                                    gear_ratios=robot.gear_ratios, label="high-order")
        pitch = [Term(j, "ez", "poly", 1) for j in range(robot.dof)]
        return spec.with_terms(pitch, label="high-order")
    raise ConfigError(f"unknown error model {model!r} (choose from {', '.join(MODELS)})")


def identification_jacobian(robot: RobotDescription, spec: ErrorModelSpec, q: Array,
                            tool_offset: Array, *, chunk: int = 2048) -> Array:
    """d(reflector position)/d(parameters) at the nominal parameters, base frame.

    Parameters
    ----------
    q : ndarray, shape (n, dof)
        Joint values, rad.
    tool_offset : ndarray, shape (3,)
        Reflector centre in the flange frame, m.

    Returns
    -------
    ndarray, shape (n, 3, P)
        m per parameter unit (m or rad), P = 9 + number of joint terms.
    """
    model = KinematicModel(robot, spec)
    x = model.nominal_params()
    x[ParameterLayout.TOOL] = tool_offset
    q = np.atleast_2d(q)
    out = np.empty((len(q), 3, model.size))
    for i in range(0, len(q), chunk):
        out[i:i + chunk] = model.jacobian(q[i:i + chunk], x)[1]
    return out


@dataclass(frozen=True)
class Observability:
    """Observability of the identifiable parameters over one pose set.

    ``parameters``: all model parameters; ``identifiable``: the rank kept after removing
    redundant columns; ``min_poses``: the fit's minimum (``identification.min_poses``);
    ``recommended_poses``: 3 equations per identifiable parameter (:data:`REDUNDANCY`), at
    least ``min_poses + 10``.
    """

    poses: int
    parameters: int
    identifiable: int
    min_poses: int
    recommended_poses: int
    O1: float
    O2: float
    O3: float
    O4: float
    O5: float
    condition_number: float

    def as_dict(self) -> dict[str, float | int]:
        """Plain-dict form (for PLAN.json)."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def observability_indices(J: Array) -> tuple[float, float, float, float, float, float]:
    """O1..O5 and the condition number of a stacked, scaled Jacobian ``J`` (m, L).

    Rank-deficient sets give O2 = O3 = O4 = O5 = 0 and an infinite condition number.
    """
    m, L = J.shape
    s = np.linalg.svd(J, compute_uv=False)
    if L == 0 or s.size < L or s[0] <= 0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, math.inf
    s = s[:L]
    tiny = s[-1] <= s[0] * 1e-12
    o1 = float(np.exp(np.mean(np.log(np.maximum(s, 1e-300)))) / math.sqrt(m))
    if tiny:
        return o1, 0.0, 0.0, 0.0, 0.0, math.inf
    return (o1, float(s[-1] / s[0]), float(s[-1]), float(s[-1] ** 2 / s[0]),
            float(1.0 / np.sum(1.0 / s)), float(s[0] / s[-1]))


class _Blocks:
    """Each candidate's 3 x 3 block ``G_c = J_c Minv J_c^T``, stored component-major.

    ``g`` has shape (3, 3, n): one contiguous array per matrix entry, which makes the
    per-candidate 3 x 3 algebra a handful of vectorised elementwise operations.
    """

    def __init__(self, Jt: Array, Minv: Array) -> None:
        self.Jt = Jt  # (3, L, n): row a of every candidate's Jacobian block, transposed
        n = Jt.shape[2]
        self.g = np.empty((3, 3, n))
        W = Minv @ Jt  # (3, L, n)
        for a in range(3):
            for b in range(a, 3):
                v = np.einsum("in,in->n", Jt[a], W[b])
                self.g[a, b] = v
                self.g[b, a] = v

    def block(self, c: int) -> Array:
        """G_c (3, 3)."""
        return self.g[:, :, c].copy()

    def logdet_i_plus(self, sign: float = 1.0) -> Array:
        """log det(I + sign * G_c) for every candidate (n,)."""
        g = self.g
        a = 1.0 + sign * g[0, 0]
        e = 1.0 + sign * g[1, 1]
        i = 1.0 + sign * g[2, 2]
        b, c, f = sign * g[0, 1], sign * g[0, 2], sign * g[1, 2]
        det = a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c)
        return np.log(np.maximum(det, 1e-300))

    def update(self, V: Array, sign: float) -> None:
        """G_c += sign * (J_c V)(J_c V)^T for every candidate; V (L, 3)."""
        X = np.ascontiguousarray(V.T) @ self.Jt  # X[a, k] = (J_c V)[a, k], shape (3, 3, n)
        for a in range(3):
            for b in range(a, 3):
                v = X[a][0] * X[b][0] + X[a][1] * X[b][1] + X[a][2] * X[b][2]
                self.g[a, b] += sign * v
                if a != b:
                    self.g[b, a] += sign * v


def _sym_sqrt_factor(K: Array) -> Array:
    """C with C C^T = K^-1 for a symmetric positive definite 3 x 3 ``K``."""
    return np.linalg.cholesky(np.linalg.inv(0.5 * (K + K.T)))


@dataclass
class DesignSpace:
    """Scaled, reduced identification Jacobian of a candidate set, and selection on it.

    Parameters
    ----------
    robot, spec
        Robot and error-model structure.
    q : ndarray, shape (n, dof)
        Candidate joint values, rad (feasible poses).
    tool_offset : ndarray, shape (3,)
        Reflector centre in the flange frame, m.
    rank_tol : float
        Relative pivot threshold of the rank-revealing QR.
    weights : ndarray, shape (n, 3, 3), optional
        Whitening matrix ``Sigma^-1/2`` of each candidate's measurement (any common scale;
        it is normalised), so that the design maximises the information of the weighted
        (maximum-likelihood) fit rather than of an unweighted one.
    rank_sample : int
        At most this many candidates (evenly spaced) are used for the QR.

    Attributes
    ----------
    names : tuple of str
        All parameter names.
    keep : ndarray of int
        Indices of the identifiable columns kept (sorted).
    scale : ndarray, shape (P,)
        Column scale (RMS over candidates), m per parameter unit.
    J : ndarray, shape (n, 3, L)
        The scaled Jacobian of the kept columns.
    """

    robot: RobotDescription
    spec: ErrorModelSpec
    q: Array
    tool_offset: Array
    weights: Array | None = None
    rank_tol: float = 1e-7
    rank_sample: int = 4096
    names: tuple[str, ...] = field(init=False)
    keep: Index = field(init=False)
    scale: Array = field(init=False)
    J: Array = field(init=False, repr=False)

    @single_threaded
    def __post_init__(self) -> None:
        self.q = np.atleast_2d(np.asarray(self.q, dtype=float))
        n = len(self.q)
        if n == 0:
            raise ConfigError("no candidate poses to choose from")
        Jfull = identification_jacobian(self.robot, self.spec, self.q,
                                         np.asarray(self.tool_offset))
        self.names = KinematicModel(self.robot, self.spec).names
        if self.weights is not None:
            W = np.asarray(self.weights, dtype=float)
            if W.shape != (n, 3, 3) or not np.all(np.isfinite(W)):
                raise ConfigError(f"weights must be finite with shape ({n}, 3, 3)")
            W = W / np.sqrt(np.mean(np.einsum("nij,nij->n", W, W)) / 3.0)
            Jfull = np.einsum("nab,nbi->nai", W, Jfull)
        scale = np.sqrt(np.mean(Jfull**2, axis=(0, 1)))
        live = scale > 1e-12 * max(float(scale.max()), 1e-300)
        scale = np.where(live, scale, 1.0)
        Js = Jfull / scale
        sub = np.unique(np.linspace(0, n - 1, min(n, self.rank_sample)).astype(int))
        A = Js[sub][:, :, live].reshape(-1, int(live.sum()))
        _, R, piv = scipy.linalg.qr(A, mode="economic", pivoting=True)
        d = np.abs(np.diag(R))
        rank = int(np.count_nonzero(d > self.rank_tol * d[0])) if d.size else 0
        self.keep = np.sort(np.flatnonzero(live)[piv[:rank]])
        self.scale = scale
        self.J = np.ascontiguousarray(Js[:, :, self.keep])

    # -- figures -------------------------------------------------------------------------------
    @property
    def identifiable(self) -> int:
        """Number of identifiable parameter combinations kept (L)."""
        return int(self.keep.size)

    @property
    def unidentifiable(self) -> tuple[str, ...]:
        """Names of the columns removed as redundant or unobservable."""
        gone = np.setdiff1d(np.arange(len(self.names)), self.keep)
        return tuple(self.names[i] for i in gone)

    @property
    def min_poses(self) -> int:
        """Fewest poses the fit accepts for the kept parameters (identification's rule)."""
        return min_poses(self.identifiable)

    @property
    def recommended_poses(self) -> int:
        """Recommended number of calibration poses (see :data:`REDUNDANCY`)."""
        return max(math.ceil(REDUNDANCY * self.identifiable / 3), self.min_poses + 10)

    @single_threaded
    def observability(self, idx: Index) -> Observability:
        """Observability figures of candidate poses ``idx``."""
        idx = np.asarray(idx, dtype=np.intp)
        A = self.J[idx].reshape(-1, self.identifiable)
        o1, o2, o3, o4, o5, cond = observability_indices(A)
        return Observability(
            poses=int(idx.size), parameters=len(self.names), identifiable=self.identifiable,
            min_poses=self.min_poses, recommended_poses=self.recommended_poses,
            O1=o1, O2=o2, O3=o3, O4=o4, O5=o5, condition_number=cond)

    # -- selection -----------------------------------------------------------------------------
    @single_threaded
    def select(self, count: int, *, allowed: NDArray[np.bool_] | None = None,
               exchange_passes: int = 2, exchange_pool: int = 2048, delta: float = 1e-6,
               batch: int = 256) -> Index:
        """Choose ``count`` candidates maximising det(J^T J) (D-optimal, O1).

        Parameters
        ----------
        count
            Number of poses to choose.
        allowed : ndarray of bool, shape (n,), optional
            Candidates that may be chosen (default: all).
        exchange_passes
            Maximum Fedorov exchange passes after the greedy build-up.
        exchange_pool
            The exchange considers the chosen poses and this many other candidates: those
            with the largest greedy gain bounds at the end of the build-up (all candidates
            when ``exchange_pool >= n``).
        delta
            Ridge ``delta * I`` added to the (column-scaled, so unit-RMS) information matrix
            so that the first poses (fewer than L / 3) have a finite determinant.
        batch
            Candidates whose gain is re-evaluated at once in the lazy greedy step.

        Returns
        -------
        ndarray of int, shape (count,)
            Chosen candidate indices, in the order they were chosen (then exchanged).

        Raises
        ------
        ConfigError
            When fewer than ``count`` candidates are allowed.

        Notes
        -----
        Greedy step: the gain of adding candidate c is ``log det(I + J_c M^-1 J_c^T)``; it
        can only fall as poses are added (M grows), so gains computed earlier are upper bounds
        and only the candidates whose bound is largest are re-evaluated (lazy greedy, exact).
        ``M^-1`` is kept by rank-3 Woodbury updates. Exchange: each chosen pose is tried
        against every pool candidate with per-candidate 3 x 3 blocks downdated/updated by
        rank-3 terms (see :class:`_Blocks`).
        """
        n, _, L = self.J.shape
        ok = np.ones(n, dtype=bool) if allowed is None else np.asarray(allowed, dtype=bool)
        if count > int(ok.sum()):
            raise ConfigError(f"{count} poses requested but only {int(ok.sum())} feasible "
                              "candidates are available")
        if count <= 0:
            return np.zeros(0, dtype=np.intp)
        J = self.J
        I3 = np.eye(3)
        Minv = np.eye(L) / delta
        ub = _logdet3(I3 + np.einsum("nai,nbi->nab", J, J) / delta)
        ub[~ok] = -np.inf
        fresh = np.ones(n, dtype=bool)  # ub is the exact gain under the current Minv
        chosen: list[int] = []
        k = min(batch, n)
        for _ in range(count):
            while True:
                c = int(np.argmax(ub))
                if fresh[c]:
                    break
                top = np.argpartition(-ub, k - 1)[:k]
                top = top[np.isfinite(ub[top]) & ~fresh[top]]
                Jk = J[top]
                X = (Jk.reshape(-1, L) @ Minv).reshape(-1, 3, L)
                ub[top] = _logdet3(I3 + np.einsum("kai,kbi->kab", X, Jk))
                fresh[top] = True
            chosen.append(c)
            ub[c] = -np.inf
            U = Minv @ J[c].T
            Minv = Minv - U @ np.linalg.solve(I3 + J[c] @ U, U.T)
            Minv = 0.5 * (Minv + Minv.T)
            fresh[:] = False
        if exchange_passes <= 0:
            return np.array(chosen, dtype=np.intp)
        # exchange among the chosen poses and the best-bounded others
        others = np.flatnonzero(np.isfinite(ub))
        if others.size > exchange_pool:
            others = others[np.argpartition(-ub[others], exchange_pool - 1)[:exchange_pool]]
        pool = np.concatenate([np.array(chosen, dtype=np.intp), np.sort(others)])
        local = _fedorov(J[pool], list(range(count)), exchange_passes, delta)
        return pool[np.array(local, dtype=np.intp)]


    @single_threaded
    def select_stratified(self, count: int, *, allowed: NDArray[np.bool_] | None = None,
                          exchange_passes: int = 3, iterations: int = 12,
                          delta: float = 1e-6) -> Index:
        """Choose ``count`` candidates, one per stratum of the joint space, D-optimally.

        The allowed candidates are split into ``count`` strata by k-means on the joint values
        (each joint scaled by its candidate range); each stratum contributes one pose, and
        Fedorov exchange within strata maximises det(J^T J). The design is thus as
        representative of the workspace as a space-filling one (which is what a model that
        cannot describe every error needs: its fit is then the best average approximation
        over the region it will be used in) and as informative as that constraint allows.
        """
        ok = (np.ones(len(self.q), dtype=bool) if allowed is None
              else np.asarray(allowed, dtype=bool))
        return self.stratify(count, allowed=ok, exchange_passes=exchange_passes,
                             iterations=iterations, delta=delta)[0]

    @single_threaded
    def stratify(self, count: int, *, allowed: NDArray[np.bool_], exchange_passes: int = 3,
                 iterations: int = 12, delta: float = 1e-6) -> tuple[Index, Index]:
        """:meth:`select_stratified`, and the stratum of every candidate (n,), -1 for those
        not allowed: :meth:`refill_strata` reuses them."""
        pool = np.flatnonzero(allowed)
        strata = np.full(len(self.q), -1, dtype=np.intp)
        if count > len(pool):
            raise ConfigError(f"{count} poses requested but only {len(pool)} feasible "
                              "candidates are available")
        if count <= 0:
            return np.zeros(0, dtype=np.intp), strata
        labels, start = _kmeans_strata(self.q[pool], count, iterations)
        members = [np.flatnonzero(labels == i) for i in range(count)]
        local = _exchange_within(self.J[pool], members, start, exchange_passes, delta)
        strata[pool] = labels
        return pool[local], strata

    @single_threaded
    def refill_strata(self, chosen: Index, strata: Index, allowed: NDArray[np.bool_], *,
                      prefer: NDArray[np.bool_] | None = None,
                      release: NDArray[np.bool_] | None = None, exchange_passes: int = 3,
                      delta: float = 1e-6) -> Index | None:
        """Replace the chosen poses (k,) that are no longer allowed, D-optimally given the
        other poses, which stay. Each takes an allowed member of its own stratum (``strata``
        (n,) from :meth:`stratify`), one of the ``prefer`` (n,) candidates when the stratum
        has any; a slot marked in ``release`` (k,), or whose stratum has no allowed member
        left, takes any allowed candidate (preferred ones first). None when none is left.

        A campaign finds some chosen poses unreachable only after choosing them; stratifying
        the remaining candidates again would move most of the other poses too, and each
        moved pose must then be checked again. A stratum lying in a pocket no move reaches
        is released rather than tried member by member.
        """
        chosen = np.array(chosen, dtype=np.intp)
        redo = np.flatnonzero(~allowed[chosen])
        if not len(redo):
            return chosen
        pref = allowed if prefer is None else allowed & prefer
        anywhere = np.setdiff1d(np.flatnonzero(pref) if pref.any() else np.flatnonzero(allowed),
                                chosen)
        x = range_scaled(self.q)
        members = [np.zeros(0, dtype=np.intp) for _ in chosen]
        for i in redo:
            own = np.flatnonzero(allowed & (strata == i))
            if len(own) and (release is None or not release[i]):
                cand = np.setdiff1d(own[pref[own]] if pref[own].any() else own, chosen)
            else:
                # the stratum is given up: the candidates nearest its centre elsewhere
                other = anywhere[strata[anywhere] != i]
                if not len(other):
                    return None
                centre = x[strata == i].mean(axis=0)
                d = np.sum((x[other] - centre) ** 2, axis=1)
                cand = other[np.argsort(d)[:_RELEASED_POOL]]
            if not len(cand):
                return None
            members[i] = cand
            chosen[i] = cand[0]
        return _exchange_within(self.J, members, chosen, exchange_passes, delta)


# candidates a released stratum's pose is chosen from (nearest its centre)
_RELEASED_POOL = 16


def _kmeans_strata(q: Array, k: int, iterations: int) -> tuple[Index, Index]:
    """k-means strata of joint values ``q`` (n, dof) and one member per stratum.

    Starts from the first ``k`` rows (the candidates are low-discrepancy draws, so these are
    already spread out), scales each joint by its range, runs Lloyd iterations and returns the
    stratum label of every row (n,) and, per stratum, the row nearest its centre (k,).
    Empty strata keep their previous centre.
    """
    span = np.ptp(q, axis=0)
    x = (q - q.min(axis=0)) / np.where(span > 0, span, 1.0)
    n, dof = x.shape
    centres = x[:k].copy()

    for _ in range(iterations):
        labels = nearest_rows(x, centres)
        counts = np.bincount(labels, minlength=k)
        filled = counts > 0
        for j in range(dof):
            sums = np.bincount(labels, weights=x[:, j], minlength=k)
            centres[filled, j] = sums[filled] / counts[filled]
    labels = nearest_rows(x, centres)
    d_own = np.sum((x - centres[labels]) ** 2, axis=1)
    # nearest row to each centre, among the stratum's members; a stratum that lost all its
    # members takes the nearest row not yet taken
    members = np.full(k, -1, dtype=np.intp)
    order = np.lexsort((d_own, labels))             # by stratum, nearest first
    first = np.r_[True, labels[order][1:] != labels[order][:-1]]
    members[labels[order][first]] = order[first]
    taken = np.zeros(n, dtype=bool)
    taken[members[members >= 0]] = True
    for c in np.flatnonzero(members < 0):
        free = np.flatnonzero(~taken)
        i = int(free[np.argmin(np.sum((x[free] - centres[c]) ** 2, axis=1))])
        members[c] = i
        labels[i] = c
        taken[i] = True
    return labels, members


def _exchange_within(J: Array, members: list[Index], chosen: Index, passes: int,
                     delta: float) -> Index:
    """Exchange each chosen pose for the candidate of its slot that maximises det(M).

    ``J`` (m, 3, L) candidates, ``chosen`` (k,) one candidate per slot and ``members`` (k,)
    the candidates each slot may take (its stratum; none: the slot keeps its pose), never
    one another slot holds. Only a slot's members are evaluated for its pose (the members'
    3 x 3 blocks under the information without that pose, by a rank-3 downdate), so a pass
    over strata costs O(m L^2) however many there are.
    """
    L = J.shape[2]
    chosen = np.array(chosen, dtype=np.intp)
    I3 = np.eye(3)
    for _ in range(passes):
        Js = J[chosen].reshape(-1, L)
        cf = scipy.linalg.cho_factor(delta * np.eye(L) + Js.T @ Js)
        Minv = scipy.linalg.cho_solve(cf, np.eye(L))
        swapped = False
        for i, mem in enumerate(members):
            if len(mem) < 2:
                continue
            s = int(chosen[i])
            Ks = I3 - J[s] @ Minv @ J[s].T     # det(Ks) = det(M - Js^T Js) / det(M)
            det_s = float(np.linalg.det(Ks))
            if det_s <= 1e-12:
                continue
            V = (Minv @ J[s].T) @ _sym_sqrt_factor(Ks)   # Minv without s = Minv + V V^T
            Jm = J[mem]
            JV = Jm @ V
            X = (Jm.reshape(-1, L) @ Minv).reshape(Jm.shape)
            B = X @ Jm.transpose(0, 2, 1) + JV @ JV.transpose(0, 2, 1)
            gain = _logdet3(I3 + B)
            gain[np.isin(mem, chosen)] = -np.inf
            j = int(np.argmax(gain))
            if math.log(det_s) + gain[j] <= 1e-9:
                continue
            c = int(mem[j])
            Minv = Minv + V @ V.T
            U = Minv @ J[c].T
            Minv = Minv - U @ np.linalg.solve(I3 + J[c] @ U, U.T)
            Minv = 0.5 * (Minv + Minv.T)
            chosen[i] = c
            swapped = True
        if not swapped:
            break
    return chosen


def _logdet3(K: Array) -> Array:
    """log det of symmetric positive definite 3 x 3 matrices K (n, 3, 3)."""
    det = (K[:, 0, 0] * (K[:, 1, 1] * K[:, 2, 2] - K[:, 1, 2] * K[:, 2, 1])
           - K[:, 0, 1] * (K[:, 1, 0] * K[:, 2, 2] - K[:, 1, 2] * K[:, 2, 0])
           + K[:, 0, 2] * (K[:, 1, 0] * K[:, 2, 1] - K[:, 1, 1] * K[:, 2, 0]))
    return np.log(np.maximum(det, 1e-300))


def _fedorov(J: Array, chosen: list[int], passes: int, delta: float) -> list[int]:
    """Fedorov exchange on candidates J (m, 3, L), starting from ``chosen`` (indices)."""
    m, _, L = J.shape
    I3 = np.eye(3)
    Jt = np.ascontiguousarray(J.transpose(1, 2, 0))  # (3, L, m)
    taken = np.zeros(m, dtype=bool)
    taken[chosen] = True
    chosen = list(chosen)
    for _ in range(passes):
        # refresh from scratch once per pass: bounds the drift of the rank-3 updates
        Js = J[np.array(chosen)].reshape(-1, L)
        cf = scipy.linalg.cho_factor(delta * np.eye(L) + Js.T @ Js)
        Minv = scipy.linalg.cho_solve(cf, np.eye(L))
        blocks = _Blocks(Jt, Minv)
        swapped = False
        for pos in range(len(chosen)):
            s = chosen[pos]
            Ks = I3 - blocks.block(s)  # det(Ks) = det(M - Js^T Js) / det(M)
            det_s = float(np.linalg.det(Ks))
            if det_s <= 1e-12:
                continue
            # blocks as if pose s were removed (Woodbury downdate) ...
            V = (Minv @ J[s].T) @ _sym_sqrt_factor(Ks)
            blocks.update(V, +1.0)
            gain = blocks.logdet_i_plus()
            gain[taken] = -np.inf
            c = int(np.argmax(gain))
            if math.log(det_s) + gain[c] <= 1e-9:
                blocks.update(V, -1.0)  # ... put it back: no improving swap
                continue
            # ... then add c: (M_-s + Jc^T Jc)^-1 by Woodbury, blocks updated alike
            Minv = Minv + V @ V.T
            U = Minv @ J[c].T
            Vc = U @ _sym_sqrt_factor(I3 + blocks.block(c))
            blocks.update(Vc, -1.0)
            Minv = Minv - Vc @ Vc.T
            taken[s] = False
            taken[c] = True
            chosen[pos] = c
            swapped = True
        if not swapped:
            break
    return chosen
