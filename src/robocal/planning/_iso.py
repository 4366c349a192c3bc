"""ISO 9283 test-cube poses P1..P5 and a damped-least-squares inverse kinematics.

ISO 9283 places a cube, edges parallel to the base axes, in the most used part of the
workspace. P1 is the cube centre; P2..P5 lie on a diagonal plane of the cube (one through two
opposite edges), on the cube diagonals, at 10 % of the diagonal length from the corners, i.e.
``P = centre + 0.8 (corner - centre)``. Here the plane is the one through the edge at
(x-, z-) and the opposite edge at (x+, z+), both parallel to the base y axis; it faces the
+x/+z quadrant. All five poses keep the flange orientation of the P1 pose (pose accuracy and
repeatability are measured at one orientation).

The cube centre is the reflector position of a feasible candidate near the centroid of all
feasible reflector positions; the side is the largest (from 60 % of the smallest extent of
those positions, shrinking by 20 % steps) at which all five poses solve and pass every
feasibility check.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal._core.threads import single_threaded
from robocal.kinematics import (
    ErrorModelSpec,
    KinematicModel,
    ParameterLayout,
    RobotDescription,
    matrix_to_rotvec,
)
from robocal.planning._feasibility import Feasibility, FeasibilityChecker

Array = NDArray[np.float64]

#: Corners (in units of half the side) that P2..P5 approach, in that order.
ISO_CORNERS = np.array([[-1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 1.0]])

#: Cycles of P1..P5 that ISO 9283 asks for to state pose accuracy and repeatability.
ISO_CYCLES = 30


@single_threaded
def solve_ik(robot: RobotDescription, tool_offset: Array, p_target: Array, R_target: Array,
             q0: Array, *, limits: Array | None = None, iterations: int = 200,
             damping: float = 1e-2, tol: float = 1e-7) -> tuple[Array, NDArray[np.bool_]]:
    """Damped-least-squares IK on the nominal model for reflector position and flange attitude.

    Parameters
    ----------
    robot
        Nominal description.
    tool_offset : ndarray, shape (3,)
        Reflector centre in the flange frame, m.
    p_target : ndarray, shape (n, 3)
        Reflector targets in the base frame, m.
    R_target : ndarray, shape (n, 3, 3) or (3, 3)
        Flange orientation targets in the base frame.
    q0 : ndarray, shape (n, dof) or (dof,)
        Start configurations, rad (the solution stays on their branch).
    limits : ndarray, shape (dof, 2), optional
        Joint values are clipped into these ranges, rad (default: robot limits).
    iterations, damping, tol
        Iteration cap, damping factor (m-equivalent) and convergence tolerance on the
        position (m) and orientation (rad) error.

    Returns
    -------
    q : ndarray, shape (n, dof)
        Solutions, rad.
    converged : ndarray of bool, shape (n,)
    """
    p_target = np.atleast_2d(p_target)
    n = len(p_target)
    R_target = np.broadcast_to(R_target, (n, 3, 3))
    q = np.array(np.broadcast_to(q0, (n, robot.dof)), dtype=float)
    lim = robot.joint_limits if limits is None else limits
    model = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    x = model.nominal_params()
    x[ParameterLayout.TOOL] = tool_offset
    lam2 = damping**2
    done = np.zeros(n, dtype=bool)
    best = np.full(n, np.inf)
    stall = np.zeros(n, dtype=int)
    for _ in range(iterations):
        p, R, J = model.joint_jacobian(q, x)
        e = np.concatenate(
            [p_target - p, matrix_to_rotvec(R_target @ np.transpose(R, (0, 2, 1)))], 1)
        err = np.maximum(np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1))
        done = err < tol
        # give up on targets whose error has not dropped by 1 % in 25 iterations
        better = err < 0.99 * best
        best = np.where(better, err, best)
        stall = np.where(better, 0, stall + 1)
        if np.all(done | (stall > 25)):
            break
        A = J @ np.transpose(J, (0, 2, 1)) + lam2 * np.eye(6)
        dq = np.einsum("nji,nj->ni", J, np.linalg.solve(A, e[:, :, None])[:, :, 0])
        step = np.abs(dq).max(axis=1, keepdims=True)
        dq *= np.minimum(1.0, 0.3 / np.maximum(step, 1e-300))  # at most 0.3 rad per iteration
        q = np.where(done[:, None], q, np.clip(q + dq, lim[:, 0], lim[:, 1]))
    return q, done


@dataclass(frozen=True)
class IsoCube:
    """The ISO 9283 cube and its five poses.

    ``centre`` (3,) m and ``side`` m in the base frame; ``q`` (5, dof) rad for P1..P5;
    ``targets`` (5, 3) m the reflector targets; ``feasibility`` the check results of ``q``.
    """

    centre: Array
    side: float
    q: Array
    targets: Array
    feasibility: Feasibility


@single_threaded
def iso_cube(checker: FeasibilityChecker, q_feasible: Array, feas: Feasibility, *,
             references: int = 24, sizes: int = 10, min_side: float = 0.05) -> IsoCube | None:
    """Find the largest ISO 9283 cube whose five poses are feasible (None if none is).

    Parameters
    ----------
    checker
        Feasibility checker of the robot in its cell.
    q_feasible : ndarray, shape (n, dof)
        Feasible candidates, rad; ``feas`` their check results.
    references
        How many candidates nearest the workspace centroid are tried as P1.
    sizes
        Number of cube sides tried per reference (20 % smaller each time, from 60 % of the
        smallest extent of the feasible reflector positions).
    min_side
        Smallest acceptable side, m.

    Notes
    -----
    All (reference, side, corner) targets are solved in one vectorised IK call, each started
    from its reference pose, so the search costs one batch of DLS iterations.
    """
    if len(q_feasible) == 0:
        return None
    P = feas.reflector
    centroid = P.mean(axis=0)
    extent = float(np.ptp(P, axis=0).min())
    # P1 candidates: near the centroid, joints well inside their ranges (the other four poses
    # need room to move) and generous visibility margins (their view direction differs)
    lim = checker.ranges
    centrality = np.min(np.minimum(q_feasible - lim[:, 0], lim[:, 1] - q_feasible)
                        / (lim[:, 1] - lim[:, 0]), axis=1)
    dist = np.linalg.norm(P - centroid, axis=1)
    for c_min, a_min, s_min in ((0.15, 0.15, 0.02), (0.1, 0.08, 0.01), (0.0, 0.0, 0.0)):
        good = ((centrality >= c_min) & (feas.angle_margin >= a_min)
                & (feas.sight_margin >= s_min))
        if good.sum() >= references:
            break
    order = np.argsort(np.where(good, dist, np.inf), kind="stable")
    refs = order[:min(references, int(good.sum()))]
    if refs.size == 0:
        return None
    sides = 0.6 * extent * 0.8 ** np.arange(sizes)
    sides = sides[sides >= min_side]
    if sides.size == 0:
        return None
    nr, ns = len(refs), len(sides)
    R_ref = checker.capsules.segments(q_feasible[refs])[2]               # (nr, 3, 3)
    centres = P[refs]                                                     # (nr, 3)
    offs = 0.8 * 0.5 * sides[:, None, None] * ISO_CORNERS[None]           # (ns, 4, 3)
    targets = centres[:, None, None, :] + offs[None]                      # (nr, ns, 4, 3)
    q0 = np.broadcast_to(q_feasible[refs][:, None, None, :], (nr, ns, 4, checker.robot.dof))
    Rt = np.broadcast_to(R_ref[:, None, None], (nr, ns, 4, 3, 3))
    q, conv = solve_ik(checker.robot, np.asarray(checker.tool_offset), targets.reshape(-1, 3),
                       Rt.reshape(-1, 3, 3), q0.reshape(-1, checker.robot.dof),
                       limits=checker.ranges)
    ok = conv.copy()
    if ok.any():
        ok[ok] = checker.check(q[ok]).ok
    ok = np.asarray(ok.reshape(nr, ns, 4).all(axis=2))
    q = q.reshape(nr, ns, 4, -1)
    # largest side first; among equal sides the reference nearest the centroid
    for s in range(ns):
        for r in range(nr):
            if ok[r, s]:
                q5 = np.vstack([q_feasible[refs[r]][None], q[r, s]])
                return IsoCube(centre=centres[r], side=float(sides[s]), q=q5,
                               targets=np.vstack([centres[r][None], targets[r, s]]),
                               feasibility=checker.check(q5))
    return None
