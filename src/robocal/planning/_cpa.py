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
               grid_step: float = math.radians(2.0)) -> list[CpaSweep]:
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

    Returns
    -------
    list of CpaSweep
        One per joint that has at least ``points`` feasible grid points in a row; joints
        without are left out (the caller reports them).
    """
    robot = checker.robot
    dof = robot.dof
    C = robot.coupling_matrix
    Cinv = np.linalg.inv(C)
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
        best: tuple[int, int, int] | None = None
        for b in range(len(base)):
            i0, i1 = _longest_run(ok[b])
            if i1 - i0 + 1 >= max(points, 2) and (best is None or i1 - i0 > best[2] - best[1]):
                best = (b, i0, i1)
        if best is None:
            continue
        b, i0, i1 = best
        t0, t1 = float(dtheta[b, i0]), float(dtheta[b, i1])
        a, c = min(t0, t1), max(t0, t1)
        edges = np.linspace(a, c, points + 1)
        t = edges[:-1] + rng.uniform(0.2, 0.8, points) * np.diff(edges)
        t[0], t[-1] = a, c  # use the full feasible width for the circle fit
        q = base[b] + t[:, None] * direction[None, :]
        feas = checker.check(q)
        if not feas.ok.all():
            # between grid points a check may fail: fall back to the nearest feasible grid point
            grid_t = dtheta[b, i0:i1 + 1]
            for m in np.flatnonzero(~feas.ok):
                t[m] = grid_t[np.argmin(np.abs(grid_t - t[m]))]
            t = np.unique(t)
            q = base[b] + t[:, None] * direction[None, :]
            feas = checker.check(q)
        order = np.argsort(q[:, k])
        out.append(CpaSweep(joint=k + 1, q=q[order], span=(a, c),
                            feasibility=feas.subset(order)))
    return out
