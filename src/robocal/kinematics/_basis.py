"""Basis functions of the joint error terms, evaluated for many poses at once."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal.kinematics._robot import RobotDescription
from robocal.kinematics._spec import COMPONENTS, ErrorModelSpec

Array = NDArray[np.float64]
TWO_PI = 2.0 * math.pi


def _legendre(s: Array, kmax: int) -> tuple[Array, Array]:
    """Legendre P_k(s) and dP_k/ds for k = 0..kmax; shapes (kmax+1, n)."""
    # Legendre rather than powers of s: orthogonal on [-1, 1] (the joint range), so pitch and
    # higher polynomial columns stay well conditioned against the constant and each other.
    # Bonnet's recursion for P and P'_{k+1} = P'_{k-1} + (2k+1) P_k are stable on [-1, 1].
    P = np.empty((kmax + 1, s.size))
    dP = np.empty_like(P)
    P[0], dP[0] = 1.0, 0.0
    if kmax >= 1:
        P[1], dP[1] = s, 1.0
    for k in range(1, kmax):
        P[k + 1] = ((2 * k + 1) * s * P[k] - k * P[k - 1]) / (k + 1)
        dP[k + 1] = dP[k - 1] + (2 * k + 1) * P[k]
    return P, dP


def spline_weights(q: Array, n_knots: int) -> tuple[NDArray[np.intp], Array, Array]:
    """Periodic uniform cubic B-spline over one revolution.

    Returns knot indices (n, 4), weights (n, 4) and d(weight)/dq (n, 4) for angles ``q`` (n,)
    in rad. The map value is ``sum(c[idx] * w, axis=1)``.
    """
    h = TWO_PI / n_knots
    # mod 2 pi: the errors a map models (gear, encoder and bearing errors) repeat every
    # revolution, so q and q + 2 pi share coefficients and a joint with a +-360 deg range needs
    # no extra knots; uniform knots keep the basis a fixed polynomial in the local t.
    u = np.mod(q, TWO_PI) / h
    i = np.floor(u)
    t = u - i
    i = i.astype(np.intp)
    idx = (i[:, None] + np.arange(-1, 3)[None, :]) % n_knots
    t2, t3 = t * t, t * t * t
    omt = 1.0 - t
    # the four uniform cubic B-spline pieces (knot r centred at q = r h): non-negative, sum to
    # one, C2 across knots; tests/unit/kinematics/test_spline_basis.py checks them against scipy
    w = np.stack([omt**3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], axis=1) / 6.0
    dw = np.stack([-3 * omt**2, 9 * t2 - 12 * t, -9 * t2 + 6 * t + 3, 3 * t2], axis=1) / (6.0 * h)
    return idx, w, dw


def gravity_torques(robot: RobotDescription, q: Array) -> Array:
    """Gravity torque about each joint axis (N m), nominal kinematics; shape (n, dof).

    Link j's centre of mass is given in DH frame j; joint i turns about z of frame i-1.
    """
    n, dof = q.shape
    if not robot.has_masses:
        return np.zeros((n, dof))
    theta = q @ robot.coupling_matrix.T + np.array([j.theta_offset for j in robot.joints])
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    o = np.zeros((n, 3))
    axes = np.empty((n, dof, 3))
    origins = np.empty((n, dof, 3))
    coms = np.empty((n, dof, 3))
    # gravity is given in the robot root frame; the chain below starts at DH frame 0
    g = robot.T_root_dh0[:3, :3].T @ np.asarray(robot.gravity, dtype=float)
    for i, jt in enumerate(robot.joints):
        axes[:, i] = R[:, :, 2]
        origins[:, i] = o
        c, s = np.cos(theta[:, i]), np.sin(theta[:, i])
        x0, y0 = R[:, :, 0].copy(), R[:, :, 1].copy()
        R[:, :, 0] = c[:, None] * x0 + s[:, None] * y0
        R[:, :, 1] = -s[:, None] * x0 + c[:, None] * y0
        o = o + jt.d * R[:, :, 2] + jt.a * R[:, :, 0]
        ca, sa = math.cos(jt.alpha), math.sin(jt.alpha)
        y1, z1 = R[:, :, 1].copy(), R[:, :, 2].copy()
        R[:, :, 1] = ca * y1 + sa * z1
        R[:, :, 2] = -sa * y1 + ca * z1
        assert jt.com is not None and jt.mass is not None
        coms[:, i] = o + R @ np.asarray(jt.com)
    masses = np.array([jt.mass for jt in robot.joints], dtype=float)
    force = masses[:, None] * g[None, :]  # (dof, 3)
    tau = np.empty((n, dof))
    for i in range(dof):
        lever = coms[:, i:] - origins[:, i][:, None, :]          # (n, dof-i, 3)
        moment = np.cross(lever, force[i:][None, :, :]).sum(axis=1)  # (n, 3)
        tau[:, i] = np.einsum("nk,nk->n", moment, axes[:, i])
    return tau


_HARMONIC = ("cos", "sin", "swcos", "swsin")


@dataclass(frozen=True)
class BasisPlan:
    """What :func:`evaluate_basis` and :func:`error_components` need of a spec, once.

    Harmonic terms (``cos``/``sin``/``swcos``/``swsin``) share their argument ``f q_j``
    across the six error components and between cosine and sine: ``freq`` (U,) and
    ``joint`` (U,) list each distinct harmonic once; ``h_terms`` (H,) are the harmonic
    terms, ``h_feature`` (H,) the harmonic each uses and ``h_cos`` (H,) whether it is the
    cosine. ``const`` are the constant terms, ``rest`` the terms other than constants and
    harmonics and ``rest_spec`` a spec of them alone. ``features``: how
    :func:`error_components` lays them out.
    """

    n_terms: int
    const: NDArray[np.intp]
    joint: NDArray[np.intp]
    freq: Array
    h_terms: NDArray[np.intp]
    h_feature: NDArray[np.intp]
    h_cos: NDArray[np.bool_]
    rest: NDArray[np.intp]
    rest_spec: ErrorModelSpec
    features: FeatureLayout


@dataclass(frozen=True)
class FeatureLayout:
    """Per joint, the functions of its own value its error components combine.

    Joint j's block of ``size`` rows holds the cosines (rows ``0 .. K-1``) and sines
    (``K .. 2K-1``) of its distinct harmonics, then the Legendre polynomials of its
    ``poly`` terms (``2K .. 2K+L-1``) and their derivatives by the joint value
    (``2K+L ..``). Rows are numbered over all blocks (``j * size + row``).

    ``harmonic_row`` (U,): the cosine row of each distinct harmonic of the
    :class:`BasisPlan`. ``direct`` (D,): harmonics whose cosine and sine are evaluated;
    ``doubled``: per level, ``(u, v)`` index arrays of harmonics whose argument is twice
    that of v (double-angle formulas; a level only uses earlier ones). ``poly_joints`` (J,),
    ``poly_order`` (J, L) (-1: unused) and ``poly_row`` (J, L): the Legendre features;
    ``p_terms``, ``p_row`` (P,): the poly terms and the row of their polynomial.
    ``maps``: per joint with a map, (joint, knots per revolution, its map terms, their knot
    indices); a map's value comes from each pose's four spline weights.
    ``rest``: terms left to :func:`evaluate_basis` (gravity).
    """

    K: int
    L: int
    size: int
    harmonic_row: NDArray[np.intp]
    direct: NDArray[np.intp]
    doubled: tuple[tuple[NDArray[np.intp], NDArray[np.intp]], ...]
    poly_joints: NDArray[np.intp]
    poly_order: NDArray[np.intp]
    poly_row: NDArray[np.intp]
    p_terms: NDArray[np.intp]
    p_row: NDArray[np.intp]
    maps: tuple[tuple[int, int, NDArray[np.intp], NDArray[np.intp]], ...]
    rest: NDArray[np.intp]
    rest_spec: ErrorModelSpec


def _feature_layout(spec: ErrorModelSpec, keys: list[tuple[int, float]],
                    rest: list[int]) -> FeatureLayout:
    dof = spec.dof
    index = {k: u for u, k in enumerate(keys)}
    slot = [0] * len(keys)
    count = [0] * dof
    for u, (j, _) in enumerate(keys):
        slot[u] = count[j]
        count[j] += 1
    K = max(count, default=0)
    p_terms = [k for k in rest if spec.terms[k].family == "poly"]
    orders: list[list[int]] = [[] for _ in range(dof)]
    for k in p_terms:
        t = spec.terms[k]
        if t.index not in orders[t.joint]:
            orders[t.joint].append(t.index)
    L = max((len(o) for o in orders), default=0)
    size = 2 * K + 2 * L
    harmonic_row = [j * size + slot[u] for u, (j, _) in enumerate(keys)]
    # a harmonic whose half is also in the model: by the double-angle formulas, level by
    # level (its half first)
    level = [0] * len(keys)
    for u in sorted(range(len(keys)), key=lambda u: keys[u][1]):
        j, f = keys[u]
        half = index.get((j, f / 2.0))
        level[u] = level[half] + 1 if half is not None and f > 0.0 else 0
    doubled = tuple(
        (np.array(us, dtype=np.intp),
         np.array([index[(keys[u][0], keys[u][1] / 2.0)] for u in us], dtype=np.intp))
        for lv in range(1, max(level, default=0) + 1)
        for us in [[u for u in range(len(keys)) if level[u] == lv]])
    poly_joints = [j for j in range(dof) if orders[j]]
    poly_order = np.full((len(poly_joints), L), -1, dtype=np.intp)
    poly_row = np.zeros((len(poly_joints), L), dtype=np.intp)
    for r, j in enumerate(poly_joints):
        for i, k in enumerate(orders[j]):
            poly_order[r, i] = k
            poly_row[r, i] = j * size + 2 * K + i
    p_row = [spec.terms[k].joint * size + 2 * K + orders[spec.terms[k].joint].index(
        spec.terms[k].index) for k in p_terms]
    by_joint: dict[int, list[int]] = {}
    for k in rest:
        if spec.terms[k].family == "map":
            by_joint.setdefault(spec.terms[k].joint, []).append(k)
    maps = tuple((j, int(spec.map_knots[j]), np.array(ks, dtype=np.intp),
                  np.array([spec.terms[k].index for k in ks], dtype=np.intp))
                 for j, ks in sorted(by_joint.items()))
    others = [k for k in rest if spec.terms[k].family not in ("poly", "map")]
    return FeatureLayout(
        K=K, L=L, size=size, harmonic_row=np.array(harmonic_row, dtype=np.intp),
        direct=np.array([u for u in range(len(keys)) if level[u] == 0], dtype=np.intp),
        doubled=doubled, poly_joints=np.array(poly_joints, dtype=np.intp),
        poly_order=poly_order, poly_row=poly_row, p_terms=np.array(p_terms, dtype=np.intp),
        p_row=np.array(p_row, dtype=np.intp), maps=maps, rest=np.array(others, dtype=np.intp),
        rest_spec=ErrorModelSpec(spec.dof, tuple(spec.terms[k] for k in others),
                                 spec.map_knots, spec.label))


def basis_plan(spec: ErrorModelSpec, robot: RobotDescription) -> BasisPlan:
    """The :class:`BasisPlan` of ``spec`` on ``robot``."""
    feats: dict[tuple[int, float], int] = {}
    h_terms, h_feat, h_cos, rest, const = [], [], [], [], []
    for k, t in enumerate(spec.terms):
        if t.family == "const":
            const.append(k)
            continue
        if t.family not in _HARMONIC:
            rest.append(k)
            continue
        f = float(t.index)
        if t.family.startswith("sw"):
            f *= robot.joints[t.joint].gear_ratio or 0.0
        h_terms.append(k)
        h_feat.append(feats.setdefault((t.joint, f), len(feats)))
        h_cos.append(t.family.endswith("cos"))
    keys = list(feats)
    return BasisPlan(
        n_terms=len(spec.terms), const=np.array(const, dtype=np.intp),
        joint=np.array([j for j, _ in keys], dtype=np.intp),
        freq=np.array([f for _, f in keys], dtype=float),
        h_terms=np.array(h_terms, dtype=np.intp), h_feature=np.array(h_feat, dtype=np.intp),
        h_cos=np.array(h_cos, dtype=bool), rest=np.array(rest, dtype=np.intp),
        rest_spec=ErrorModelSpec(spec.dof, tuple(spec.terms[k] for k in rest),
                                 spec.map_knots, spec.label),
        features=_feature_layout(spec, keys, rest))


def _harmonic_values(plan: BasisPlan, q: Array) -> tuple[Array, Array]:
    """cos and sin (n, U) of each distinct harmonic argument, each evaluated once."""
    arg = q[:, plan.joint] * plan.freq
    return np.cos(arg), np.sin(arg)


@dataclass(frozen=True)
class ComponentWeights:
    """The coefficients of one parameter vector arranged for :func:`error_components`.

    ``W`` (dof, 12, size): per joint, rows 0-5 combine its block of features
    (:class:`FeatureLayout`) into its six error components, rows 6-11 into their
    derivatives by the joint value. ``e0`` (6 dof,): the constant terms summed per
    component. ``maps``: per map of the layout, its component row and its coefficient per
    knot of the revolution (zero where the map has no term). ``S`` (6 dof, R): scatter of
    the remaining terms (weighted) to components.
    """

    W: Array
    e0: Array
    S: Array
    maps: tuple[tuple[int, Array], ...] = ()


def component_weights(plan: BasisPlan, coef: Array, cols: NDArray[np.intp], dof: int
                      ) -> ComponentWeights:
    """:class:`ComponentWeights` of the term coefficients ``coef`` (n_terms,)."""
    lay = plan.features
    K, L, size = lay.K, lay.L, lay.size
    W = np.zeros((dof, 12, size))
    if plan.h_terms.size:
        u = plan.h_feature
        c = cols[plan.h_terms]
        j, comp = c // 6, c % 6
        k = lay.harmonic_row[u] - j * size                         # cosine row in the block
        w = coef[plan.h_terms]
        f = plan.freq[u]
        hc, hs = plan.h_cos, ~plan.h_cos
        # E += w cos(f q) | w sin(f q);  dE += -w f sin(f q) | w f cos(f q)
        np.add.at(W, (j[hc], comp[hc], k[hc]), w[hc])
        np.add.at(W, (j[hc], comp[hc] + 6, K + k[hc]), -w[hc] * f[hc])
        np.add.at(W, (j[hs], comp[hs], K + k[hs]), w[hs])
        np.add.at(W, (j[hs], comp[hs] + 6, k[hs]), w[hs] * f[hs])
    if lay.p_terms.size:
        c = cols[lay.p_terms]
        j, comp = c // 6, c % 6
        k = lay.p_row - j * size
        w = coef[lay.p_terms]
        np.add.at(W, (j, comp, k), w)
        np.add.at(W, (j, comp + 6, k + L), w)
    e0 = np.zeros(dof * 6)
    np.add.at(e0, cols[plan.const], coef[plan.const])
    S = np.zeros((dof * 6, lay.rest.size))
    S[cols[lay.rest], np.arange(lay.rest.size)] = coef[lay.rest]
    maps = []
    for _, K, terms, knots in lay.maps:
        by_knot = np.zeros(K)
        np.add.at(by_knot, knots, coef[terms])
        maps.append((int(cols[terms[0]]), by_knot))
    return ComponentWeights(W=W, e0=e0, S=S, maps=tuple(maps))


def joint_features(plan: BasisPlan, robot: RobotDescription, q: Array) -> Array:
    """Every joint's block of features (:class:`FeatureLayout`) at ``q`` (n, dof):
    (dof, size, n).

    Each harmonic argument's cosine and sine are evaluated once; a harmonic whose half is
    also in the model comes from its half by the double-angle formulas.
    """
    n, dof = q.shape
    lay = plan.features
    F = np.zeros((dof, lay.size, n))
    flat = F.reshape(dof * lay.size, n)
    qt = np.ascontiguousarray(q.T)
    row, K = lay.harmonic_row, lay.K
    d = lay.direct
    if d.size:
        arg = plan.freq[d, None] * qt[plan.joint[d]]
        flat[row[d]] = np.cos(arg)
        flat[row[d] + K] = np.sin(arg)
    for u, v in lay.doubled:
        c, s = flat[row[v]], flat[row[v] + K]
        flat[row[u]] = 2.0 * c * c - 1.0
        flat[row[u] + K] = 2.0 * s * c
    if lay.poly_joints.size:
        lim = robot.joint_limits[lay.poly_joints]
        lo, hi = lim[:, :1], lim[:, 1:]
        s = (2.0 * qt[lay.poly_joints] - (lo + hi)) / (hi - lo)        # (J, n)
        P, dP = _legendre(s.ravel(), int(lay.poly_order.max()))
        J = lay.poly_joints.size
        P, dP = P.reshape(-1, J, n), dP.reshape(-1, J, n) * (2.0 / (hi - lo))
        used = lay.poly_order >= 0
        r = np.nonzero(used)[0]
        k = lay.poly_order[used]
        flat[lay.poly_row[used]] = P[k, r]
        flat[lay.poly_row[used] + lay.L] = dP[k, r]
    return F


def error_components(plan: BasisPlan, robot: RobotDescription, q: Array,
                     weights: ComponentWeights, *, derivative: bool = False
                     ) -> tuple[Array, Array | None]:
    """Error components E (6 dof, n) and optionally dE/dq_j (6 dof, n) as rows
    (row ``6 j + axis``), without forming the basis matrix.

    Each joint's harmonics and polynomials are combined by one small matrix product per
    joint with their values (:func:`joint_features`), the constants are added as they
    are, maps from their four spline weights per pose, and gravity terms through
    :func:`evaluate_basis`.
    """
    n, dof = q.shape
    width = dof * 6
    lay = plan.features
    if lay.size:
        W = weights.W if derivative else weights.W[:, :6]
        out = W @ joint_features(plan, robot, q)                   # (dof, 12 | 6, n)
        E = out[:, :6].reshape(width, n) + weights.e0[:, None]
        dE = out[:, 6:].reshape(width, n) if derivative else None
    else:
        E = np.repeat(weights.e0[:, None], n, axis=1)
        dE = np.zeros((width, n)) if derivative else None
    for (j, K, _, _), (row, by_knot) in zip(lay.maps, weights.maps, strict=True):
        # a map is four spline weights per pose: no column per knot
        idx, w, dw = spline_weights(q[:, j], K)
        c = by_knot[idx]
        E[row] += np.einsum("nk,nk->n", c, w)
        if dE is not None:
            dE[row] += np.einsum("nk,nk->n", c, dw)
    if lay.rest.size:
        Br, dBr = evaluate_basis(lay.rest_spec, robot, q, derivative=derivative)
        E += weights.S @ Br.T
        if dE is not None and dBr is not None:
            dE += weights.S @ dBr.T
    return E, dE


def evaluate_basis(spec: ErrorModelSpec, robot: RobotDescription, q: Array,
                   *, derivative: bool = False, plan: BasisPlan | None = None
                   ) -> tuple[Array, Array | None]:
    """Evaluate every term's basis function at joint values ``q`` (n, dof) rad.

    Returns ``B`` (n, n_terms) and, if asked, ``dB`` (n, n_terms): the derivative of each
    basis function with respect to its own joint value (zero for ``gravity``, whose
    configuration dependence is left out of joint Jacobians; it is micro-radians).
    ``plan``: :func:`basis_plan` of ``spec`` (computed when not given).
    """
    q = np.asarray(q, dtype=float)
    n = q.shape[0]
    T = len(spec.terms)
    B = np.zeros((n, T))
    dB = np.zeros((n, T)) if derivative else None
    if T == 0:
        return B, dB
    terms = spec.terms
    joints = np.array([t.joint for t in terms])
    fam = np.array([t.family for t in terms])
    order = np.array([t.index for t in terms], dtype=float)

    m = fam == "const"
    B[:, m] = 1.0

    if np.isin(fam, _HARMONIC).any():
        plan = plan if plan is not None else basis_plan(spec, robot)
        c, s = _harmonic_values(plan, q)
        hc, u = plan.h_cos, plan.h_feature
        B[:, plan.h_terms[hc]] = c[:, u[hc]]
        B[:, plan.h_terms[~hc]] = s[:, u[~hc]]
        if dB is not None:
            f = plan.freq[u]
            dB[:, plan.h_terms[hc]] = -f[hc] * s[:, u[hc]]
            dB[:, plan.h_terms[~hc]] = f[~hc] * c[:, u[~hc]]

    m = fam == "poly"
    if m.any():
        lim = robot.joint_limits
        for j in np.unique(joints[m]):
            sel = np.flatnonzero(m & (joints == j))
            lo, hi = lim[j]
            s = (2.0 * q[:, j] - (lo + hi)) / (hi - lo)
            kmax = int(order[sel].max())
            P, dP = _legendre(s, kmax)
            ks = order[sel].astype(int)
            B[:, sel] = P[ks].T
            if dB is not None:
                dB[:, sel] = dP[ks].T * (2.0 / (hi - lo))

    m = fam == "map"
    if m.any():
        for j in np.unique(joints[m]):
            sel = np.flatnonzero(m & (joints == j))
            K = spec.map_knots[j]
            # column of map knot r for this joint
            col_of_knot = np.full(K, -1, dtype=np.intp)
            col_of_knot[order[sel].astype(int)] = sel
            idx, w, dw = spline_weights(q[:, j], K)
            cols = col_of_knot[idx]  # (n, 4)
            # the four knots of a row are distinct (K >= 8), so plain assignment suffices
            rows = np.repeat(np.arange(n), 4)
            ok = cols.ravel() >= 0
            B[rows[ok], cols.ravel()[ok]] = w.ravel()[ok]
            if dB is not None:
                dB[rows[ok], cols.ravel()[ok]] = dw.ravel()[ok]

    m = fam == "gravity"
    if m.any():
        tau = gravity_torques(robot, q)
        B[:, m] = tau[:, joints[m]]
    return B, dB


def component_columns(spec: ErrorModelSpec) -> NDArray[np.intp]:
    """Index (joint * 6 + component) of each term, shape (n_terms,)."""
    return np.array([t.joint * 6 + COMPONENTS.index(t.component) for t in spec.terms],
                    dtype=np.intp)
