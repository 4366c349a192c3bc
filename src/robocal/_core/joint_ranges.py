"""Joint vectors against joint ranges, without numpy-heavy imports beyond numpy itself
(the report and the daemon's push check use it; the planner too)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def targets_outside(ranges: Array, q: Array, *, limit: int = 10
                    ) -> tuple[NDArray[np.bool_], list[str]]:
    """Which joint vectors ``q`` (n, dof) rad lie outside ``ranges`` (dof, 2) rad (n,), and up
    to ``limit`` of them named by their first joint out (``"target 12: J6 250.0 deg outside
    [-180.0, 180.0]"``)."""
    q = np.atleast_2d(q)
    lo, hi = ranges[:, 0], ranges[:, 1]
    out = np.any((q < lo) | (q > hi), axis=1)
    names = []
    for i in np.flatnonzero(out)[:limit]:
        j = int(np.argmax(np.maximum(lo - q[i], q[i] - hi)))
        names.append(f"target {int(i)}: J{j + 1} {math.degrees(q[i, j]):.1f} deg outside "
                     f"[{math.degrees(lo[j]):.1f}, {math.degrees(hi[j]):.1f}]")
    return out, names
