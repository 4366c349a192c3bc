"""Batch compensation: gradient-search inverse kinematics on the identified model.

For each target (a reflector/TCP position in the tracker frame, optionally with a flange
orientation) find joint commands ``q_c`` whose pose under the calibrated model equals the
target. All targets are solved together: every iteration is one vectorised model evaluation
and one batched 6x6 solve, with no Python loop over targets.

Iteration (damped Gauss-Newton / Levenberg-Marquardt with step control, chord updates)::

    e      = [p_t - p(q);  w * log(R_t R(q)^T)]                 (6,) per target
    dq     = J^T (J J^T + lambda^2 I)^-1 e                       J: weighted 6 x dof
    q_new  = clip(q + gamma dq, limits)
    accept if |e(q_new)| < |e(q)|  (gamma <- min(1, 2 gamma), lambda <- lambda / 10)
    else   gamma <- gamma / 2, lambda <- 10 lambda, Jacobian refreshed at q

The Jacobian is refreshed only where a step was rejected or reduced the error by less than
a factor of 10: the model Jacobian changes little over the sub-millimetre corrections a
calibration makes, so one analytic Jacobian plus two or three forward passes usually
reach the 0.1 um default tolerance.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal.compensation._ik import has_closed_form, nominal_ik
from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel, KinematicModel, ParameterLayout

Array = NDArray[np.float64]
Evaluator = Callable[[Array, bool], tuple[Array, Array, Array | None]]

STATUSES = ("ok", "not-converged", "out-of-limits", "unreachable")


# --- small vectorised helpers -----------------------------------------------------------------
def rotation_error(R_target: Array, R: Array) -> Array:
    """Rotation vectors (n, 3) rad, tracker frame, with ``R_target = Exp(w) R``."""
    E = R_target @ np.swapaxes(R, -1, -2)
    tr = np.clip((np.einsum("nii->n", E) - 1.0) * 0.5, -1.0, 1.0)
    ang = np.arccos(tr)
    v = np.stack([E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], 1)
    s = np.sin(ang)
    small = ang < 1e-6
    fac = np.where(small, 0.5 + ang**2 / 12.0, ang / (2.0 * np.where(small, 1.0, s)))
    w = v * fac[:, None]
    near_pi = ang > math.pi - 1e-4
    if near_pi.any():
        # axis from the symmetric part, (E + E^T) / 4 + I / 2 = a a^T + O((pi - angle)^2)
        En = E[near_pi]
        B = (En + np.swapaxes(En, 1, 2)) * 0.25 + 0.5 * np.eye(3)
        k = np.argmax(np.einsum("nii->ni", B), axis=1)
        a = B[np.arange(len(k)), :, k]
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        sgn = np.sign(np.einsum("ni,ni->n", a, v[near_pi]))
        a *= np.where(sgn == 0, 1.0, sgn)[:, None]
        w[near_pi] = a * ang[near_pi, None]
    return w


def _model_evaluator(model: KinematicModel, params: Array) -> Evaluator:
    def evaluate(q: Array, jac: bool) -> tuple[Array, Array, Array | None]:
        if jac:
            return model.joint_jacobian(q, params)
        p, R, _ = model.flange_poses(q, params)
        return p, R, None

    return evaluate


def model_evaluator(cal: CalibratedModel) -> Evaluator:
    """Evaluator of reflector position, flange rotation and 6 x dof Jacobian under ``cal``.

    Joint values outside the model's coverage are evaluated with its fallback model, exactly
    as :meth:`CalibratedModel.predict` does.
    """
    main = _model_evaluator(cal.model, cal.params)
    if cal.fallback is None:
        return main
    fb = model_evaluator(cal.fallback)

    def evaluate(q: Array, jac: bool) -> tuple[Array, Array, Array | None]:
        inside = cal.inside_coverage(q)
        if inside.all():
            return main(q, jac)
        n, dof = q.shape
        p = np.empty((n, 3))
        R = np.empty((n, 3, 3))
        J = np.empty((n, 6, dof)) if jac else None
        for mask, ev in ((inside, main), (~inside, fb)):
            if mask.any():
                pp, RR, JJ = ev(q[mask], jac)
                p[mask], R[mask] = pp, RR
                if J is not None and JJ is not None:
                    J[mask] = JJ
        return p, R, J

    return evaluate


@dataclass(frozen=True)
class PoseSolution:
    """Raw result of :func:`solve_pose` for n targets (SI)."""

    q: Array                         # (n, dof) rad, last accepted iterate
    pos_residual: Array              # (n,) m
    rot_residual: Array              # (n,) rad
    iterations: NDArray[np.int_]     # (n,)
    converged: NDArray[np.bool_]     # (n,)
    at_limit: NDArray[np.bool_]      # (n,) some joint sits on a limit


def solve_pose(evaluate: Evaluator, q0: Array, p_target: Array, R_target: Array, limits: Array,
               *, tol_pos: float = 1e-7, tol_rot: float = 1e-6, max_iter: int = 20,
               rot_weight: float = 0.2, damping: float = 1e-6,
               initial: tuple[Array, Array, Array] | None = None) -> PoseSolution:
    """Solve ``pose(q) = (p_target, R_target)`` for n targets at once.

    Parameters
    ----------
    evaluate
        ``evaluate(q (m, dof), jac) -> (p (m, 3), R (m, 3, 3), J (m, 6, dof) or None)``.
    q0
        Start joints (n, dof) rad.
    p_target, R_target
        Target positions (n, 3) m and orientations (n, 3, 3).
    limits
        Joint limits (dof, 2) rad; iterates are clipped into them.
    tol_pos, tol_rot
        Convergence: position error below ``tol_pos`` (m) and orientation error below
        ``tol_rot`` (rad).
    max_iter
        Iteration limit (accepted or rejected steps).
    rot_weight
        Length (m per rad) that weights orientation against position in the step.
    damping
        Smallest damping ``lambda`` of the least-squares step (m).
    initial
        ``(p, R, J)`` already evaluated at ``q0`` (must lie inside the limits), to save a pass.
    """
    lo, hi = limits[:, 0], limits[:, 1]
    q = np.clip(np.array(q0, dtype=float), lo, hi)
    n = q.shape[0]
    w = np.array([1.0, 1.0, 1.0, rot_weight, rot_weight, rot_weight])

    def error(idx: slice | NDArray[np.intp], p: Array, R: Array) -> Array:
        return np.concatenate([p_target[idx] - p, rotation_error(R_target[idx], R)], axis=1)

    def conv_of(e: Array) -> NDArray[np.bool_]:
        return ((np.linalg.norm(e[:, :3], axis=1) < tol_pos)
                & (np.linalg.norm(e[:, 3:], axis=1) < tol_rot))

    p, R, J = initial if initial is not None else evaluate(q, True)
    assert J is not None
    J = J.copy()
    e = error(slice(None), p, R)
    cost = np.sum((e * w) ** 2, axis=1)
    conv = conv_of(e)
    gamma = np.ones(n)
    lam = np.full(n, damping)
    iters = np.zeros(n, dtype=np.int_)
    eye = np.eye(6)
    for _ in range(max_iter):
        act = np.flatnonzero(~conv & (gamma >= 1.0 / 64.0))
        if act.size == 0:
            break
        Jw = J[act] * w[None, :, None]
        ew = e[act] * w
        A = Jw @ np.swapaxes(Jw, 1, 2) + (lam[act] ** 2)[:, None, None] * eye
        try:
            y = np.linalg.solve(A, ew[:, :, None])
        except np.linalg.LinAlgError:
            y = np.linalg.lstsq(A.reshape(-1, 6), ew.reshape(-1), rcond=None)[0]  # pragma: no cover
        dq = (np.swapaxes(Jw, 1, 2) @ y)[:, :, 0]
        q_try = np.clip(q[act] + gamma[act, None] * dq, lo, hi)
        ok_num = np.all(np.isfinite(q_try), axis=1)
        q_try[~ok_num] = q[act][~ok_num]
        p_t, R_t, _ = evaluate(q_try, False)
        e_try = error(act, p_t, R_t)
        c_try = np.sum((e_try * w) ** 2, axis=1)
        acc = (c_try < cost[act]) & ok_num
        ia, ir = act[acc], act[~acc]
        slow = c_try[acc] > 1e-2 * cost[ia]
        q[ia], e[ia], cost[ia] = q_try[acc], e_try[acc], c_try[acc]
        conv[ia] = conv_of(e_try[acc])
        gamma[ia] = np.minimum(1.0, 2.0 * gamma[ia])
        lam[ia] = np.maximum(lam[ia] * 0.1, damping)
        gamma[ir] *= 0.5
        lam[ir] *= 10.0
        iters[act] += 1
        refresh = np.concatenate([ia[slow & ~conv[ia]], ir])
        if refresh.size:
            _, _, Jr = evaluate(q[refresh], True)
            assert Jr is not None
            J[refresh] = Jr
    span = 1e-9
    at_limit = np.any((q <= lo + span) | (q >= hi - span), axis=1)
    return PoseSolution(q=q, pos_residual=np.linalg.norm(e[:, :3], axis=1),
                        rot_residual=np.linalg.norm(e[:, 3:], axis=1), iterations=iters,
                        converged=conv, at_limit=at_limit)


# --- public compensation ----------------------------------------------------------------------
@dataclass(frozen=True)
class CompensationResult:
    """Compensated joint commands for n targets.

    Attributes
    ----------
    q
        Joint commands (n, dof) rad; rows whose status is not ``"ok"`` hold NaN, so a failed
        target can never be executed by mistake (see ``q_last``).
    status
        (n,) one of ``"ok"``; ``"unreachable"`` (no configuration of the nominal robot
        reaches the pose, and for a position-only target no other orientation helped);
        ``"out-of-limits"`` (reachable, but only beyond a joint limit: the nominal IK found
        no branch inside the limits or the iteration stopped on a limit);
        ``"not-converged"`` (anything else, e.g. at a singularity).
    residual_m
        (n,) distance between the target and the model's reflector position at ``q_last``, m.
    rotation_residual_rad
        (n,) orientation error of the flange at ``q_last``, rad.
    iterations
        (n,) solver iterations (0: the start already met the tolerance).
    q_last
        (n, dof) rad: the last iterate of every target, including failed ones (diagnostics).
    q_start
        (n, dof) rad: where the iteration started (nominal IK or the seed).
    orientation_relaxed
        (n,) bool: a position-only target whose seed orientation could not be kept (the
        6-D pose lies beyond the workspace, typically near a stretched elbow); it was solved
        for position alone, changing the orientation by ``rotation_residual_rad``.
    in_coverage
        (n,) bool: the command lies inside the joint range the calibration data covered.
    """

    q: Array
    status: NDArray[np.str_]
    residual_m: Array
    rotation_residual_rad: Array
    iterations: NDArray[np.int_]
    q_last: Array
    q_start: Array
    orientation_relaxed: NDArray[np.bool_]
    in_coverage: NDArray[np.bool_]

    @property
    def ok(self) -> NDArray[np.bool_]:
        """(n,) True where the status is ``"ok"``."""
        return self.status == "ok"

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def counts(self) -> dict[str, int]:
        """Number of targets per status (every status listed)."""
        return {s: int(np.sum(self.status == s)) for s in STATUSES}


def _check_inputs(cal: CalibratedModel, targets_p: Array, seeds_q: Array,
                  R_targets: Array | None) -> tuple[Array, Array, Array | None]:
    dof = cal.robot.dof
    p = np.asarray(targets_p, dtype=float)
    if p.ndim == 1:
        p = p[None]
    if p.ndim != 2 or p.shape[1] != 3:
        raise ConfigError(f"targets must have shape (n, 3), got {np.shape(targets_p)}")
    n = p.shape[0]
    q = np.asarray(seeds_q, dtype=float)
    if q.ndim == 1:
        q = np.broadcast_to(q, (n, q.shape[0]))
    if q.shape != (n, dof):
        raise ConfigError(f"seed joints must have shape ({n}, {dof}), got {np.shape(seeds_q)}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise ConfigError("targets and seed joints must be finite")
    R = None
    if R_targets is not None:
        R = np.asarray(R_targets, dtype=float)
        if R.ndim == 2:
            R = np.broadcast_to(R, (n, 3, 3))
        if R.shape != (n, 3, 3) or not np.all(np.isfinite(R)):
            raise ConfigError(f"target orientations must be finite (n, 3, 3), got {R.shape}")
        ortho = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
        if np.any(ortho > 1e-6) or np.any(np.linalg.det(R) < 0):
            bad = int(np.flatnonzero((ortho > 1e-6) | (np.linalg.det(R) < 0))[0])
            raise ConfigError(f"target {bad}: orientation is not a rotation matrix")
    return p, np.array(q), R


def compensate(cal: CalibratedModel, targets_p: Array, seeds_q: Array, *,
               R_targets: Array | None = None, start: str = "auto", tol_m: float = 1e-7,
               tol_rad: float = 1e-6, max_iter: int = 20, rot_weight_m: float = 0.2,
               relax_orientation: bool = True, max_change_deg: float | None = None
               ) -> CompensationResult:
    """Joint commands that put the model's reflector exactly on each target.

    Parameters
    ----------
    cal
        The identified model (its fallback is used outside the covered joint range).
    targets_p
        Target reflector/TCP positions (n, 3) m in the tracker frame.
    seeds_q
        Seed joints (n, dof) or (dof,) rad: the program's joints. They choose the
        configuration (branch, whole turns) and, for position-only targets, the orientation.
    R_targets
        Optional flange orientations (n, 3, 3) (or one (3, 3)) in the tracker frame. Without
        them each target keeps the orientation its seed has under the model, and the 6-D
        problem is solved.
    start
        ``"auto"``: nominal closed-form IK (calibrated base and tool) where the robot has one,
        else the seed; ``"nominal"``: nominal IK (numeric when no closed form); ``"seed"``.
        With ``auto``/``nominal`` the better of the IK start and the seed is used.
    tol_m, tol_rad
        Convergence tolerance on position (m) and orientation (rad) under the model.
    max_iter
        Iteration limit per target.
    rot_weight_m
        Length (m/rad) weighting orientation against position in the steps.
    relax_orientation
        Position-only targets whose 6-D problem fails are solved again for position alone
        (minimum-norm steps from the best 6-D iterate); see
        :attr:`CompensationResult.orientation_relaxed`.
    max_change_deg
        Position-only targets whose 6-D solution moves a joint farther than this from its
        seed (near the wrist singularity holding the orientation can turn J4/J6 by tens of
        degrees) are solved again for position alone, from the seed, with minimum-norm
        steps; kept when that stays within the bound (flagged ``orientation_relaxed``).

    Returns
    -------
    CompensationResult
    """
    if start not in ("auto", "nominal", "seed"):
        raise ConfigError(f"unknown start {start!r} (auto, nominal, seed)")
    p_t, seeds, R_in = _check_inputs(cal, targets_p, seeds_q, R_targets)
    robot = cal.robot
    n = p_t.shape[0]
    lim = robot.joint_limits
    ev = model_evaluator(cal)
    q_seed = np.clip(seeds, lim[:, 0], lim[:, 1])
    if n == 0:
        e = np.empty((0, robot.dof))
        return CompensationResult(e, np.empty(0, dtype="<U13"), np.empty(0), np.empty(0),
                                  np.empty(0, dtype=np.int_), e, e, np.empty(0, dtype=bool),
                                  np.empty(0, dtype=bool))
    p_s, R_s, _ = ev(q_seed, False)
    R_t = R_s if R_in is None else np.ascontiguousarray(R_in)
    q0 = q_seed.copy()
    initial: tuple[Array, Array, Array] | None = None
    # certainly out of reach: farther from the base than all links and the tool together
    T_tb = cal.model.base_transform(cal.params)
    reach = sum(abs(j.a) + abs(j.d) for j in robot.joints) + float(np.linalg.norm(
        cal.params[ParameterLayout.TOOL])) + 0.05
    reachable = np.linalg.norm(p_t - T_tb[:3, 3], axis=1) <= reach   # ... and, with the
    in_limits = np.ones(n, dtype=bool)      # closed form: some branch reaches, within limits
    use_ik = start == "nominal" or (start == "auto" and has_closed_form(robot))
    if use_ik:
        tool = cal.params[ParameterLayout.TOOL]
        Rb = T_tb[:3, :3].T
        R_bf = Rb @ R_t
        o_bf = (p_t - R_t @ tool - T_tb[:3, 3]) @ Rb.T
        T_bf = np.zeros((n, 4, 4))
        T_bf[:, :3, :3] = R_bf
        T_bf[:, :3, 3] = o_bf
        T_bf[:, 3, 3] = 1.0
        ik = nominal_ik(robot, T_bf, seeds)
        reachable, in_limits = reachable & ik.reachable, ik.found
        q0 = np.where(ik.found[:, None], ik.q, q_seed)
        # the start and its Jacobian in one pass; keep the seed where it is closer
        p0, R0, J0 = ev(q0, True)
        assert J0 is not None
        w = np.array([1.0, 1.0, 1.0, rot_weight_m, rot_weight_m, rot_weight_m])
        e_c = np.concatenate([p_t - p0, rotation_error(R_t, R0)], 1) * w
        e_s = np.concatenate([p_t - p_s, rotation_error(R_t, R_s)], 1) * w
        back = np.flatnonzero(ik.found & (np.sum(e_s**2, 1) <= np.sum(e_c**2, 1)))
        if back.size:
            q0[back] = q_seed[back]
            pb, Rb_, Jb = ev(q0[back], True)
            assert Jb is not None
            p0[back], R0[back], J0[back] = pb, Rb_, Jb
        initial = (p0, R0, J0)
    sol = solve_pose(ev, q0, p_t, R_t, lim, tol_pos=tol_m, tol_rot=tol_rad,
                     max_iter=max_iter, rot_weight=rot_weight_m, initial=initial)
    q_last, pos_res, rot_res = sol.q, sol.pos_residual, sol.rot_residual
    iters, conv, at_limit = sol.iterations, sol.converged, sol.at_limit
    relaxed = np.zeros(n, dtype=bool)
    if relax_orientation and R_in is None and not conv.all():
        f = np.flatnonzero(~conv)
        pos = solve_pose(ev, q_last[f], p_t[f], R_t[f], lim, tol_pos=tol_m, tol_rot=math.inf,
                         max_iter=max_iter, rot_weight=0.0)
        win = pos.converged
        g = f[win]
        q_last, pos_res, rot_res = q_last.copy(), pos_res.copy(), rot_res.copy()
        iters, conv, at_limit = iters.copy(), conv.copy(), at_limit.copy()
        q_last[g], pos_res[g], rot_res[g] = pos.q[win], pos.pos_residual[win], pos.rot_residual[win]
        iters[f] += pos.iterations
        conv[g] = True
        at_limit[f[~win]] = pos.at_limit[~win]
        relaxed[g] = True
    if max_change_deg is not None and R_in is None:
        big = np.max(np.abs(q_last - q_seed), axis=1) > math.radians(max_change_deg)
        f = np.flatnonzero(conv & big)
        if f.size:
            pos = solve_pose(ev, q_seed[f], p_t[f], R_t[f], lim, tol_pos=tol_m,
                             tol_rot=math.inf, max_iter=max_iter, rot_weight=0.0)
            small = np.max(np.abs(pos.q - q_seed[f]), axis=1) <= math.radians(max_change_deg)
            win = pos.converged & small
            g = f[win]
            q_last, pos_res, rot_res = q_last.copy(), pos_res.copy(), rot_res.copy()
            q_last[g], pos_res[g], rot_res[g] = (pos.q[win], pos.pos_residual[win],
                                                 pos.rot_residual[win])
            iters = iters.copy()
            iters[f] += pos.iterations
            relaxed = relaxed.copy()
            relaxed[g] = True
    status = np.full(n, "ok", dtype="<U13")
    bad = ~conv
    limited = bad & reachable & (at_limit | ~in_limits)
    status[bad & ~reachable] = "unreachable"
    status[limited] = "out-of-limits"
    status[bad & reachable & ~limited] = "not-converged"
    q = q_last.copy()
    q[bad] = np.nan
    return CompensationResult(q=q, status=status, residual_m=pos_res,
                              rotation_residual_rad=rot_res, iterations=iters, q_last=q_last,
                              q_start=q0, orientation_relaxed=relaxed,
                              in_coverage=cal.inside_coverage(q_last))
