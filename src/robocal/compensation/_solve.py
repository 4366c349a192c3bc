"""Batch compensation: gradient-search inverse kinematics on the identified model.

For each target (a reflector/TCP position in the tracker frame, optionally with a flange
orientation) find joint commands ``q_c`` whose pose under the calibrated model equals the
target. All targets are solved together: every iteration is one vectorised model evaluation
and one batched 6x6 solve, with no Python loop over targets.

The damped Gauss-Newton iteration itself is :func:`~robocal.compensation._dls.solve_pose`.
"""

from __future__ import annotations

import math
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal._core.threads import blas_threads
from robocal.compensation._dls import Evaluator, rotation_error, solve_pose
from robocal.compensation._ik import has_closed_form, nominal_ik
from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel, KinematicModel, ParameterLayout

Array = NDArray[np.float64]

STATUSES = ("ok", "not-converged", "out-of-limits", "unreachable")


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
    # the batches' small matrix products gain nothing from a second BLAS thread and lose
    # ~20 % CPU to its synchronisation (ADR 0046); setting the limit costs ~1 ms
    with blas_threads(1) if p_t.shape[0] >= 1000 else nullcontext():
        return _compensate(cal, p_t, seeds, R_in, start=start, tol_m=tol_m, tol_rad=tol_rad,
                           max_iter=max_iter, rot_weight_m=rot_weight_m,
                           relax_orientation=relax_orientation, max_change_deg=max_change_deg)


def _compensate(cal: CalibratedModel, p_t: Array, seeds: Array, R_in: Array | None, *,
                start: str, tol_m: float, tol_rad: float, max_iter: int, rot_weight_m: float,
                relax_orientation: bool, max_change_deg: float | None) -> CompensationResult:
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
