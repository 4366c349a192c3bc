"""Nominal inverse kinematics: closed form for ortho-parallel arms with a spherical wrist,
damped least squares for every other robot.

The closed form is derived from the robot description itself (standard DH, chain angle
``theta = C q + offset``), so sign flips, theta offsets and the FANUC J2/J3 coupling need no
special cases. A description qualifies when

* it has six joints,
* the axes of joints 1 and 2 are perpendicular (``alpha_1 = +-90 deg``), those of joints 2
  and 3 parallel (``alpha_2 = 0``), and ``alpha_3 = +-90 deg`` (the forearm points along the
  next axis),
* joints 4-6 form a spherical wrist: ``alpha_4 = +-90 deg``, ``alpha_5 = +-90 deg``,
  ``a_4 = a_5 = a_6 = 0`` and ``d_5 = 0``,

which covers the OPW family (FANUC, KUKA, ABB, Staubli...). ``d_2 + d_3`` (a lateral shoulder
offset) may be non-zero. There are up to eight solutions: two for joint 1 (front/back), two
for the elbow (up/down), two for the wrist (flip/no flip); each joint angle is then shifted
by whole turns into the joint limits, closest to the seed. At a wrist singularity
(``theta_5 = 0``) joint 4 keeps its seed value.

Everything here is SI (m, rad). Poses are ``T_base_flange``: the flange frame (the last DH
frame) in the robot base frame (DH frame 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal.compensation._dls import solve_pose
from robocal.errors import ConfigError
from robocal.kinematics import ErrorModelSpec, KinematicModel, RobotDescription

Array = NDArray[np.float64]
_TWO_PI = 2.0 * math.pi
_AXIS_TOL = 1e-9


@dataclass(frozen=True)
class _OPW:
    """Closed-form data derived from a qualifying DH table (SI)."""

    d1: float
    a1: float
    sa1: float          # sin(alpha_1) = +-1
    a2: float
    doff: float         # d_2 + d_3: lateral offset of the arm plane from joint 1's axis
    L: float            # hypot(a_3, d_4): elbow -> wrist centre
    phi: float          # angle of (a_3, -sin(alpha_3) d_4) in the forearm frame
    sa3: float
    sa4: float
    eps6: float         # cos(alpha_4 + alpha_5) = +-1: does the wrist reverse joint 6?
    R_post: Array       # Rx(alpha_6)^T Rx(alpha_4 + alpha_5)^T (3, 3)
    d6: float
    z_tool: Array       # flange -> wrist centre direction in the flange frame (3,)


def _rx(a: float) -> Array:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rz_batch(t: Array) -> Array:
    """Rotations about z, shape t.shape + (3, 3)."""
    c, s = np.cos(t), np.sin(t)
    z, o = np.zeros_like(t), np.ones_like(t)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1),
                     np.stack([z, z, o], -1)], -2)


def _is_pm90(alpha: float) -> bool:
    return abs(math.cos(alpha)) < _AXIS_TOL


def opw_geometry(robot: RobotDescription) -> _OPW | None:
    """Return the closed-form data for ``robot``, or None when it does not qualify."""
    if robot.dof != 6:
        return None
    j = robot.joints
    if not (_is_pm90(j[0].alpha) and abs(math.sin(j[1].alpha)) < _AXIS_TOL
            and math.cos(j[1].alpha) > 0 and _is_pm90(j[2].alpha) and _is_pm90(j[3].alpha)
            and _is_pm90(j[4].alpha)):
        return None
    if max(abs(j[3].a), abs(j[4].a), abs(j[5].a), abs(j[4].d)) > 1e-12:
        return None
    if abs(j[1].a) < 1e-9 or math.hypot(j[2].a, j[3].d) < 1e-9:
        return None
    if abs(np.linalg.det(robot.coupling_matrix)) < 1e-9:
        return None
    sa3 = math.sin(j[2].alpha)
    a4, a5, a6 = j[3].alpha, j[4].alpha, j[5].alpha
    eps6 = round(math.cos(a4 + a5))
    R_post = _rx(a6).T @ _rx(a4 + a5).T
    # the wrist centre is o_5 = o_6 - d_6 z_5 and z_5 = R_6 Rx(alpha_6)^T e_z
    z_tool = _rx(a6).T @ np.array([0.0, 0.0, 1.0])
    return _OPW(
        d1=j[0].d, a1=j[0].a, sa1=math.sin(j[0].alpha), a2=j[1].a, doff=j[1].d + j[2].d,
        L=math.hypot(j[2].a, j[3].d), phi=math.atan2(-sa3 * j[3].d, j[2].a), sa3=sa3,
        sa4=math.sin(a4), eps6=float(eps6), R_post=R_post, d6=j[5].d, z_tool=z_tool,
    )


def has_closed_form(robot: RobotDescription) -> bool:
    """True when :func:`nominal_ik` solves ``robot`` in closed form."""
    return opw_geometry(robot) is not None


@dataclass(frozen=True)
class IKResult:
    """Nominal inverse kinematics of n poses.

    Attributes
    ----------
    q
        Chosen joint values (n, dof) rad: the valid solution closest to the seed. Rows
        without a solution hold NaN.
    found
        (n,) bool: a solution inside the joint limits exists.
    solutions
        All candidate solutions (n, k, dof) rad (k = 8 in closed form, 1 numerically),
        each shifted by whole turns into the limits, closest to the seed.
    valid
        (n, k) bool: the candidate exists (the pose is reachable on that branch) and lies
        inside the joint limits.
    reachable
        (n,) bool: some branch reaches the pose, inside the joint limits or not.
    method
        ``"closed-form"`` or ``"numeric"``.
    """

    q: Array
    found: NDArray[np.bool_]
    solutions: Array
    valid: NDArray[np.bool_]
    reachable: NDArray[np.bool_]
    method: str


def nominal_model(robot: RobotDescription) -> KinematicModel:
    """The robot's nominal kinematics (no error terms, identity base, zero tool)."""
    return KinematicModel(robot, ErrorModelSpec(robot.dof, ()))


def nominal_fk(robot: RobotDescription, q: Array) -> Array:
    """Nominal flange poses ``T_base_flange`` (n, 4, 4) m for joint values (n, dof) rad."""
    m = nominal_model(robot)
    x = np.zeros(m.size)
    q = np.atleast_2d(np.asarray(q, dtype=float))
    _, R, o = m.flange_poses(q, x)
    T = np.zeros((q.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = o
    T[:, 3, 3] = 1.0
    return T


def _theta_candidates(g: _OPW, robot: RobotDescription, T: Array, seed_theta4: Array
                      ) -> tuple[Array, NDArray[np.bool_]]:
    """Chain angles of all 8 branches (n, 8, 6) and whether each exists (n, 8)."""
    n = T.shape[0]
    R6 = T[:, :3, :3]
    W = T[:, :3, 3] - g.d6 * (R6 @ g.z_tool)                       # wrist centre (n, 3)
    # joint 1: z_1 . (W - o_1) = d_2 + d_3, with z_1 = sa1 (sin t1, -cos t1, 0)
    r = np.hypot(W[:, 0], W[:, 1])
    psi = np.arctan2(W[:, 1], W[:, 0])
    s = g.sa1 * g.doff / np.maximum(r, 1e-300)
    ok1 = np.abs(s) <= 1.0
    asn = np.arcsin(np.clip(s, -1.0, 1.0))
    th1 = np.stack([psi + asn, psi + math.pi - asn], axis=1)        # (n, 2)
    R1 = _rz_batch(th1) @ _rx(robot.joints[0].alpha)                # (n, 2, 3, 3)
    o1 = np.stack([g.a1 * np.cos(th1), g.a1 * np.sin(th1), np.full_like(th1, g.d1)], -1)
    W1 = np.einsum("nkji,nkj->nki", R1, W[:, None, :] - o1)         # W in frame 1
    # joints 2, 3: planar two-link a2 -> L in frame 1's xy plane
    rho2 = W1[..., 0] ** 2 + W1[..., 1] ** 2
    c3 = (rho2 - g.a2**2 - g.L**2) / (2.0 * g.a2 * g.L)
    ok23 = np.abs(c3) <= 1.0 + 1e-12
    acs = np.arccos(np.clip(c3, -1.0, 1.0))
    u = np.stack([acs, -acs], axis=2)                               # th3 + phi, (n, 2, 2)
    th3 = u - g.phi
    th2 = (np.arctan2(W1[..., 1], W1[..., 0])[..., None]
           - np.arctan2(g.L * np.sin(u), g.a2 + g.L * np.cos(u)))
    R3 = (R1[:, :, None] @ _rz_batch(th2 + th3)) @ _rx(robot.joints[2].alpha)  # (n,2,2,3,3)
    # wrist: N = R3^T R6 R_post = Rz(t4) Ry(-sa4 t5) Rz(eps6 t6)
    N = np.swapaxes(R3, -1, -2) @ (R6[:, None, None] @ g.R_post)
    sB = np.hypot(N[..., 0, 2], N[..., 1, 2])
    B = np.arctan2(sB, N[..., 2, 2])
    A = np.arctan2(N[..., 1, 2], N[..., 0, 2])
    G = np.arctan2(N[..., 2, 1], -N[..., 2, 0])
    sing = sB < 1e-9
    if sing.any():
        # B ~ 0: N = Rz(A + G); B ~ pi: N = Rz(A - G) Ry(pi). Joint 4 keeps the seed.
        A0 = np.broadcast_to(seed_theta4[:, None, None], A.shape)
        tot = np.arctan2(N[..., 1, 0], N[..., 0, 0])
        tot_pi = np.arctan2(-N[..., 1, 0], -N[..., 0, 0])
        G_sing = np.where(N[..., 2, 2] > 0, tot - A0, A0 - tot_pi)
        A = np.where(sing, A0, A)
        G = np.where(sing, G_sing, G)
    A = np.stack([A, A + math.pi], axis=3)
    B = np.stack([B, -B], axis=3)
    G = np.stack([G, G + math.pi], axis=3)                          # (n, 2, 2, 2)
    shape = (n, 2, 2, 2)
    theta = np.stack([
        np.broadcast_to(th1[:, :, None, None], shape),
        np.broadcast_to(th2[..., None], shape),
        np.broadcast_to(th3[..., None], shape),
        A, -g.sa4 * B, g.eps6 * G,
    ], axis=-1).reshape(n, 8, 6)
    exists = np.broadcast_to((ok1[:, None] & ok23)[:, :, None, None], shape).reshape(n, 8)
    return theta, exists


def _wrap_to_limits(robot: RobotDescription, q: Array, seed: Array
                    ) -> tuple[Array, NDArray[np.bool_]]:
    """Shift joint values by whole turns of the chain angles into the limits, near the seed.

    Adding 2 pi to chain angle j moves the joint values by ``2 pi Cinv[:, j]``, which leaves
    the pose unchanged (for the FANUC coupling: J2 and J3 together). Chain angles are taken
    in order; each picks the turn that brings its own joint value inside the limits and
    closest to the seed (the turn nearest the seed or a neighbour: the seed is inside the
    limits). Returns the shifted values (..., dof) and whether every joint ended inside.
    """
    lim = robot.joint_limits
    lo, hi = lim[:, 0], lim[:, 1]
    D = _TWO_PI * np.linalg.inv(robot.coupling_matrix)                    # (dof, dof)
    shape = np.broadcast_shapes(q.shape, np.shape(seed))
    # joint by joint on contiguous (dof, ...) rows; a turn of chain angle j moves only the
    # joints m with D[m, j] != 0
    qs = np.moveaxis(np.broadcast_to(q, shape), -1, 0).copy()
    ss = np.moveaxis(np.broadcast_to(seed, shape), -1, 0).copy()
    tol = 1e-9
    for j in range(qs.shape[0]):
        djj = D[j, j]
        if abs(djj) < 1e-12:
            continue
        qj, sj = qs[j], ss[j]
        k0 = np.round((sj - qj) / djj)
        best_k = np.zeros_like(k0)
        dist = np.full(k0.shape, np.inf)
        for dk in (0.0, -1.0, 1.0):
            k = k0 + dk
            cand = qj + k * djj
            d = np.abs(cand - sj)
            take = (cand >= lo[j] - tol) & (cand <= hi[j] + tol) & (d < dist)
            best_k = np.where(take, k, best_k)
            dist = np.where(take, d, dist)
        for m in np.flatnonzero(D[:, j]):
            qs[m] += best_k * D[m, j]
    q = np.moveaxis(qs, 0, -1)
    ok = np.all((q >= lo - tol) & (q <= hi + tol), axis=-1)
    return np.clip(q, lo, hi), ok


def _as_poses(T: Array) -> Array:
    T = np.asarray(T, dtype=float)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ConfigError(f"poses must have shape (4, 4) or (n, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ConfigError("poses must be finite")
    return T


def _as_seeds(robot: RobotDescription, seed: Array | None, n: int) -> Array:
    if seed is None:
        lim = robot.joint_limits
        mid = np.clip(np.zeros(robot.dof), lim[:, 0], lim[:, 1])
        return np.broadcast_to(mid, (n, robot.dof)).copy()
    s = np.asarray(seed, dtype=float)
    if s.ndim == 1:
        s = np.broadcast_to(s, (n, s.shape[0]))
    if s.shape != (n, robot.dof):
        raise ConfigError(f"seed must have shape ({robot.dof},) or ({n}, {robot.dof}), "
                          f"got {np.shape(seed)}")
    if not np.all(np.isfinite(s)):
        raise ConfigError("seed joints must be finite")
    return s.copy()


def ik_solutions(robot: RobotDescription, T_base_flange: Array, seed: Array | None = None
                 ) -> tuple[Array, NDArray[np.bool_]]:
    """All closed-form solutions (n, 8, dof) rad and their validity (n, 8).

    Invalid candidates (branch does not reach the pose, or a joint cannot be brought inside
    its limits) still hold numbers; check the mask.

    Raises
    ------
    ConfigError
        The robot is not an ortho-parallel arm with a spherical wrist.
    """
    q, exists, in_lim = _closed_form(robot, T_base_flange, seed)
    return q, exists & in_lim


def _closed_form(robot: RobotDescription, T_base_flange: Array, seed: Array | None
                 ) -> tuple[Array, NDArray[np.bool_], NDArray[np.bool_]]:
    g = opw_geometry(robot)
    if g is None:
        raise ConfigError(f"robot {robot.name!r} has no closed-form inverse kinematics "
                          "(not an ortho-parallel arm with a spherical wrist)")
    T = _as_poses(T_base_flange)
    n = T.shape[0]
    lim = robot.joint_limits
    seeds = np.clip(_as_seeds(robot, seed, n), lim[:, 0], lim[:, 1])
    off = np.array([j.theta_offset for j in robot.joints])
    C = robot.coupling_matrix
    seed_theta = seeds @ C.T + off
    theta, exists = _theta_candidates(g, robot, T, seed_theta[:, 3])
    q = (theta - off) @ np.linalg.inv(C).T                                  # (n, 8, dof)
    q, in_lim = _wrap_to_limits(robot, q, seeds[:, None, :])
    return q, exists, in_lim


def nominal_ik(robot: RobotDescription, T_base_flange: Array, seed: Array | None = None, *,
               method: str = "auto", tol: float = 1e-10, max_iter: int = 50) -> IKResult:
    """Joint values that put the nominal flange at ``T_base_flange``, closest to ``seed``.

    Parameters
    ----------
    robot
        Nominal robot description.
    T_base_flange
        Flange poses in the robot base frame, (4, 4) or (n, 4, 4), metres.
    seed
        Seed joints (dof,) or (n, dof) rad; picks the branch and the whole-turn shift of each
        joint. Default: zeros clipped into the limits.
    method
        ``"auto"`` (closed form where the robot qualifies, else numeric), ``"closed-form"``
        or ``"numeric"`` (damped least squares from the seed, one solution).
    tol
        Numeric method: position tolerance (m) and orientation tolerance (rad).
    max_iter
        Numeric method: iteration limit.

    Returns
    -------
    IKResult
    """
    T = _as_poses(T_base_flange)
    n = T.shape[0]
    seeds = _as_seeds(robot, seed, n)
    if method not in ("auto", "closed-form", "numeric"):
        raise ConfigError(f"unknown IK method {method!r} (auto, closed-form, numeric)")
    if method == "closed-form" or (method == "auto" and has_closed_form(robot)):
        sols, exists, in_lim = _closed_form(robot, T, seeds)
        valid = exists & in_lim
        d = np.where(valid, np.sum((sols - seeds[:, None, :]) ** 2, axis=2), np.inf)
        k = np.argmin(d, axis=1)
        found = np.isfinite(d[np.arange(n), k])
        q = sols[np.arange(n), k].copy()
        q[~found] = np.nan
        return IKResult(q=q, found=found, solutions=sols, valid=valid,
                        reachable=np.asarray(exists.any(axis=1)), method="closed-form")
    # numeric: damped least squares on the nominal model from the seed
    m = nominal_model(robot)
    x = np.zeros(m.size)

    def evaluate(qs: Array, jac: bool) -> tuple[Array, Array, Array | None]:
        if jac:
            p, R, J = m.joint_jacobian(qs, x)
            return p, R, J
        p, R, _ = m.flange_poses(qs, x)
        return p, R, None

    sol = solve_pose(evaluate, seeds, T[:, :3, 3], T[:, :3, :3], robot.joint_limits,
                     tol_pos=tol, tol_rot=tol, max_iter=max_iter)
    found = sol.converged
    q = sol.q.copy()
    q[~found] = np.nan
    return IKResult(q=q, found=found, solutions=sol.q[:, None, :].copy(),
                    valid=found[:, None].copy(), reachable=found.copy(), method="numeric")
