"""Damped least-squares pose solver shared by compensation and the numeric nominal IK.

Apart from :mod:`robocal.compensation._solve` so that :mod:`robocal.compensation._ik` can use
it without importing the compensation that imports the IK (ADR 0038).

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

__all__ = ["Evaluator", "PoseSolution", "rotation_error", "solve_pose"]

Array = NDArray[np.float64]
# trial points of batches up to this size are evaluated with their Jacobian (ADR 0046)
_JOINT_PASS_BELOW = 2000
Evaluator = Callable[[Array, bool], tuple[Array, Array, Array | None]]


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
    fresh = np.all(q == q0, axis=1)             # J was evaluated at the current q
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
        # small batches (the few hard targets, iterating long): the trial point's Jacobian
        # in the same pass, for the steps that will need it, saves a second pass
        p_t, R_t, J_t = evaluate(q_try, act.size <= _JOINT_PASS_BELOW)
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
        fresh[ia] = False
        need = slow & ~conv[ia]                 # accepted but slow: Jacobian at the new q
        if J_t is not None:
            J[ia[need]] = J_t[acc][need]
            fresh[ia[need]] = True
            need[:] = False
        # a rejected step leaves q where it was: where J was evaluated there, it stays
        refresh = np.concatenate([ia[need], ir[~fresh[ir]]])
        if refresh.size:
            _, _, Jr = evaluate(q[refresh], True)
            assert Jr is not None
            J[refresh] = Jr
            fresh[refresh] = True
    span = 1e-9
    at_limit = np.any((q <= lo + span) | (q >= hi - span), axis=1)
    return PoseSolution(q=q, pos_residual=np.linalg.norm(e[:, :3], axis=1),
                        rot_residual=np.linalg.norm(e[:, 3:], axis=1), iterations=iters,
                        converged=conv, at_limit=at_limit)
