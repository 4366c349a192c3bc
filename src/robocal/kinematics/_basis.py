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
    cosine. ``const`` are the constant terms, ``rest`` the other terms' indices and
    ``rest_spec`` a spec of them alone.
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
                                 spec.map_knots, spec.label))


def _harmonic_values(plan: BasisPlan, q: Array) -> tuple[Array, Array]:
    """cos and sin (n, U) of each distinct harmonic argument, each evaluated once."""
    arg = q[:, plan.joint] * plan.freq
    return np.cos(arg), np.sin(arg)


def error_components(plan: BasisPlan, robot: RobotDescription, q: Array, coef: Array,
                     cols: NDArray[np.intp], width: int, *, derivative: bool = False
                     ) -> tuple[Array, Array | None]:
    """``(B @ S).T`` and ``(dB @ S).T`` (width, n) without forming B: S scatters term k,
    weighted by ``coef[k]``, into column ``cols[k]`` (error component joint * 6 + axis).

    The harmonics are combined by two matrix products with their cosines and sines
    (computed once per distinct argument, as (U, n) rows), the constants are added as they
    are, and the other terms go through :func:`evaluate_basis` of ``plan.rest_spec``.
    """
    n = q.shape[0]
    E = np.zeros((width, n))
    dE = np.zeros((width, n)) if derivative else None
    if plan.const.size:
        e0 = np.zeros(width)
        np.add.at(e0, cols[plan.const], coef[plan.const])
        E += e0[:, None]
    if plan.h_terms.size:
        arg = plan.freq[:, None] * q.T[plan.joint]                   # (U, n)
        c, s = np.cos(arg), np.sin(arg)
        U = plan.freq.size
        Mc = np.zeros((width, U))
        Ms = np.zeros((width, U))
        hc = plan.h_cos
        w = coef[plan.h_terms]
        np.add.at(Mc, (cols[plan.h_terms[hc]], plan.h_feature[hc]), w[hc])
        np.add.at(Ms, (cols[plan.h_terms[~hc]], plan.h_feature[~hc]), w[~hc])
        E += Mc @ c + Ms @ s
        if dE is not None:
            dE += (Ms * plan.freq) @ c - (Mc * plan.freq) @ s
    if plan.rest.size:
        Br, dBr = evaluate_basis(plan.rest_spec, robot, q, derivative=derivative)
        S = np.zeros((width, plan.rest.size))
        S[cols[plan.rest], np.arange(plan.rest.size)] = coef[plan.rest]
        E += S @ Br.T
        if dE is not None and dBr is not None:
            dE += S @ dBr.T
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
