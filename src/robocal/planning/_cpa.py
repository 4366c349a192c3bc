"""Circle-point-analysis (CPA) sweeps: one physical axis moves, every other one holds still.

A sweep varies the chain angle ``theta_k`` of one joint (the physical axis; for coupled joints
such as FANUC J2/J3 that moves the controller's joint values of the coupled joint too, so that
the other axes really stand still) and keeps the other chain angles at a base configuration.
For every joint the planner tries several feasible base configurations, samples the sweep on
a fine grid, and keeps the base whose longest run of feasible grid points (reflector visible,
no collision, within limits) is widest. The N points are spread over that run by stratified
jitter (one point per equal slice, seeded), which avoids the regular spacing that would alias
strain-wave terms at multiples of the gear ratio.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal._core.threads import single_threaded
from robocal.planning._feasibility import Feasibility, FeasibilityChecker

Array = NDArray[np.float64]


@dataclass(frozen=True)
class CpaSweep:
    """One single-axis sweep.

    ``joint``: 1-based joint number; ``q`` (points, dof) rad in sweep order; ``span`` the
    feasible range of the chain-angle change around the base configuration, rad (low, high);
    ``feasibility`` the check results of ``q``.
    """

    joint: int
    q: Array
    span: tuple[float, float]
    feasibility: Feasibility

    @property
    def width(self) -> float:
        """Width of the feasible sub-range, rad."""
        return self.span[1] - self.span[0]


def _longest_run(mask: NDArray[np.bool_]) -> tuple[int, int]:
    """Start and end (inclusive) of the longest run of True in a 1-D mask, (-1, -2) if none."""
    best = (-1, -2)
    start = -1
    for i, v in enumerate(np.append(mask, False)):
        if v and start < 0:
            start = i
        elif not v and start >= 0:
            if i - 1 - start > best[1] - best[0]:
                best = (start, i - 1)
            start = -1
    return best


@single_threaded
def cpa_sweeps(checker: FeasibilityChecker, q_feasible: Array, *, points: int,
               rng: np.random.Generator, bases: int = 32,
               grid_step: float = math.radians(2.0),
               reachable: Callable[[Array], NDArray[np.bool_]] | None = None,
               tries: int = 16, min_width_ratio: float = 0.25) -> list[CpaSweep]:
    """Plan one sweep per joint.

    Parameters
    ----------
    checker
        Feasibility checker of the robot in its cell.
    q_feasible : ndarray, shape (n, dof)
        Feasible poses to take base configurations from (evenly spaced picks).
    points
        Points per sweep (at least 3 for a circle).
    rng
        Seeded generator for the stratified jitter.
    bases
        Base configurations tried per joint.
    grid_step
        Resolution of the sweep grid, rad.
    reachable
        Whether each of the poses (m, dof) rad is reachable (from home, by a safe move).
        Then of the ``tries`` widest sweeps per joint the widest whose points are all
        reachable is taken, if it is at least ``min_width_ratio`` as wide as the widest;
        otherwise the widest (the router may still find detours to it).

    Returns
    -------
    list of CpaSweep
        One per joint that has at least ``points`` feasible grid points in a row; joints
        without are left out (the caller reports them).
    """
    robot = checker.robot
    dof = robot.dof
    C = robot.coupling_matrix
    Cinv = np.asarray(np.linalg.inv(C), dtype=np.float64)
    ranges = checker.ranges
    if len(q_feasible) == 0:
        return []
    pick = np.unique(np.linspace(0, len(q_feasible) - 1, min(bases, len(q_feasible))).astype(int))
    base = q_feasible[pick]
    out: list[CpaSweep] = []
    for k in range(dof):
        direction = Cinv[:, k]  # dq per unit of chain angle k, other chain angles fixed
        lo, hi = ranges[k]
        g = math.ceil((hi - lo) / grid_step) + 1
        # chain-angle change so that joint k's own value runs through its whole range
        dq_k = np.linspace(lo, hi, g)[None, :] - base[:, k:k + 1]       # (b, g)
        dtheta = dq_k / direction[k]
        qs = base[:, None, :] + dtheta[:, :, None] * direction[None, None, :]
        flat = qs.reshape(-1, dof)
        ok = checker.screen(flat)
        if ok.any():
            ok[ok] = checker.check(flat[ok]).ok
        ok = ok.reshape(len(base), g)
        runs = []
        for b in range(len(base)):
            i0, i1 = _longest_run(ok[b])
            if i1 - i0 + 1 >= max(points, 2):
                runs.append((b, i0, i1))
        if not runs:
            continue
        # widest first (stable: the earlier base among equals)
        runs.sort(key=lambda r: -(r[2] - r[1]))
        draw = rng.uniform(0.2, 0.8, points)       # the same jitter for every base tried
        sweep = None
        for b, i0, i1 in runs[:max(1, tries) if reachable is not None else 1]:
            if i1 - i0 < min_width_ratio * (runs[0][2] - runs[0][1]):
                break
            cand = _sweep(checker, base[b], direction, dtheta[b, i0:i1 + 1], draw, k)
            if reachable is None or reachable(cand.q).all():
                sweep = cand
                break
        out.append(sweep if sweep is not None
                   else _sweep(checker, base[runs[0][0]], direction,
                               dtheta[runs[0][0], runs[0][1]:runs[0][2] + 1], draw, k))
    return out


def _sweep(checker: FeasibilityChecker, base: Array, direction: Array, grid_t: Array,
           draw: Array, k: int) -> CpaSweep:
    """The sweep of joint ``k`` (0-based) from ``base`` (dof,) rad over the feasible run of
    chain-angle changes ``grid_t`` (rad, in grid order): one point per equal slice at the
    relative positions ``draw`` (points,), the run's ends included."""
    points = len(draw)
    a, c = float(min(grid_t[0], grid_t[-1])), float(max(grid_t[0], grid_t[-1]))
    edges = np.linspace(a, c, points + 1)
    t = edges[:-1] + draw * np.diff(edges)
    t[0], t[-1] = a, c  # use the full feasible width for the circle fit
    q = base + t[:, None] * direction[None, :]
    feas = checker.check(q)
    if not feas.ok.all():
        # between grid points a check may fail: fall back to the nearest feasible grid point
        for m in np.flatnonzero(~feas.ok):
            t[m] = grid_t[np.argmin(np.abs(grid_t - t[m]))]
        t = np.unique(t)
        q = base + t[:, None] * direction[None, :]
        feas = checker.check(q)
    order = np.argsort(q[:, k])
    return CpaSweep(joint=k + 1, q=q[order], span=(a, c), feasibility=feas.subset(order))
