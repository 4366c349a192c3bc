"""Nominal link geometry as capsules, and vectorised distance queries.

Each DH link ``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` contributes up to two segments: the
``d`` segment along the previous z axis (from frame i-1's origin to the "knee") and the ``a``
segment along the new x axis (from the knee to frame i's origin). Both belong to body i (the
part that moves with joint i). A capsule is such a segment swept by a sphere of the body's
radius; a final capsule runs from the flange centre to the reflector (the SMR nest).

Everything is in the robot base frame, metres, for ``n`` joint vectors at once.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from robocal.errors import ConfigError
from robocal.kinematics import RobotDescription

#: array aliases of the planning modules: values (m, rad, ...), masks and indices
Array = NDArray[np.float64]
Mask = NDArray[np.bool_]
Index = NDArray[np.intp]
T = TypeVar("T")

#: batches of at least this many poses are checked on two threads
PARALLEL_ROWS = 2048

_EPS = 1e-12
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def range_scaled(q: Array) -> Array:
    """Joint values (n, dof) divided by each joint's range over the rows, so that distances
    weigh every joint alike (a joint that does not vary keeps its values)."""
    span = np.ptp(q, axis=0)
    return np.asarray(q / np.where(span > 0, span, 1.0), dtype=np.float64)


def nearest_rows(x: Array, c: Array) -> Index:
    """For each row of ``x`` (n, d) the index of the nearest row of ``c`` (m, d)."""
    # argmin_c |x - c|^2 = argmin_c (|c|^2 - 2 x.c): |x|^2 is the same for every c
    d = x @ c.T
    d *= -2.0
    d += np.sum(c**2, axis=1)
    return np.argmin(d, axis=1)


def map_rows(fn: Callable[[slice], T], n: int, chunk: int) -> list[T]:
    """``fn`` over consecutive slices that cover rows 0..n, each at most ``chunk`` rows.

    From :data:`PARALLEL_ROWS` rows on, the slices (at least two) run on two threads: the
    capsule checks are numpy work on large arrays, which releases the GIL, and they are most
    of a plan's time. Each row's result does not depend on how the rows are split.
    """
    parts = max(1, math.ceil(n / chunk))
    if n >= PARALLEL_ROWS:
        parts = max(parts, 2)
    edges = [round(k * n / parts) for k in range(parts + 1)]
    pieces = [slice(a, b) for a, b in itertools.pairwise(edges)]
    if parts == 1:
        return [fn(pieces[0])]
    with ThreadPoolExecutor(2, thread_name_prefix="capsule-checks") as pool:
        return list(pool.map(fn, pieces))


def link_frames(robot: RobotDescription, q: Array) -> tuple[Array, Array, Array]:
    """Nominal DH frames for joint values ``q`` (n, dof) rad.

    Returns
    -------
    origins : ndarray, shape (n, dof + 1, 3)
        Frame origins 0..dof (0 = base, dof = flange), m.
    rotations : ndarray, shape (n, dof + 1, 3, 3)
        Frame orientations (columns: x, y, z axes) in the base frame.
    knees : ndarray, shape (n, dof, 3)
        End of the ``d`` segment of each link (origin i-1 + d_i z_{i-1}), m.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n, dof = q.shape
    theta = q @ robot.coupling_matrix.T + np.array([j.theta_offset for j in robot.joints])
    O = np.zeros((n, dof + 1, 3))
    Rs = np.zeros((n, dof + 1, 3, 3))
    K = np.zeros((n, dof, 3))
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    o = np.zeros((n, 3))
    Rs[:, 0] = R
    for i, jt in enumerate(robot.joints):
        c, s = np.cos(theta[:, i]), np.sin(theta[:, i])
        x = R[:, :, 0].copy()
        y = R[:, :, 1].copy()
        R[:, :, 0] = c[:, None] * x + s[:, None] * y          # Rz(theta)
        R[:, :, 1] = -s[:, None] * x + c[:, None] * y
        knee = o + jt.d * R[:, :, 2]
        o = knee + jt.a * R[:, :, 0]
        ca, sa = math.cos(jt.alpha), math.sin(jt.alpha)
        y = R[:, :, 1].copy()
        z = R[:, :, 2].copy()
        R[:, :, 1] = ca * y + sa * z                           # Rx(alpha)
        R[:, :, 2] = -sa * y + ca * z
        K[:, i] = knee
        O[:, i + 1] = o
        Rs[:, i + 1] = R
    return O, Rs, K


def segment_distance(P1: Array, Q1: Array, P2: Array, Q2: Array
                     ) -> tuple[Array, Array, Array]:
    """Closest distance between segments P1-Q1 and P2-Q2 (broadcast over leading axes).

    Parameters
    ----------
    P1, Q1, P2, Q2 : ndarray, shape (..., 3)
        Segment end points, m (any broadcastable leading shape).

    Returns
    -------
    dist : ndarray, shape (...)
        Euclidean distance between the closest points, m.
    s, t : ndarray, shape (...)
        Parameters in [0, 1] of the closest points along the first and second segment.

    Notes
    -----
    Ericson, *Real-Time Collision Detection*, section 5.1.9, with degenerate (point) segments
    handled by ``np.where`` branches so that the whole batch runs without Python loops.
    """
    d1 = Q1 - P1
    d2 = Q2 - P2
    r = P1 - P2
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    f = np.einsum("...i,...i->...", d2, r)
    c = np.einsum("...i,...i->...", d1, r)
    b = np.einsum("...i,...i->...", d1, d2)
    a_ok = a > _EPS
    e_ok = e > _EPS
    a_safe = np.where(a_ok, a, 1.0)
    e_safe = np.where(e_ok, e, 1.0)
    denom = a * e - b * b
    # general case: s from the infinite-line solution (0 when parallel), then t, then re-clip s
    s = np.where(denom > _EPS * np.maximum(a * e, _EPS),
                 np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e_safe
    s = np.where(t < 0.0, np.clip(-c / a_safe, 0.0, 1.0),
                 np.where(t > 1.0, np.clip((b - c) / a_safe, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    # degenerate segments
    s = np.where(a_ok, np.where(e_ok, s, np.clip(-c / a_safe, 0.0, 1.0)), 0.0)
    t = np.where(e_ok, np.where(a_ok, t, np.clip(f / e_safe, 0.0, 1.0)), 0.0)
    diff = (P1 + s[..., None] * d1) - (P2 + t[..., None] * d2)
    return np.sqrt(np.einsum("...i,...i->...", diff, diff)), s, t


def point_box_distance(p: Array, lo: Array, hi: Array) -> Array:
    """Distance (...) from points ``p`` (..., 3) to axis-aligned boxes [lo, hi] (0 inside)."""
    g = np.maximum(np.maximum(lo - p, p - hi), 0.0)
    return np.sqrt(np.einsum("...i,...i->...", g, g))


def segment_box_distance(P: Array, Q: Array, lo: Array, hi: Array, *, iterations: int = 32
                         ) -> tuple[Array, Array]:
    """Distance from segments P-Q (..., 3) to boxes [lo, hi] (..., 3), and its parameter t.

    The distance from a point moving along a line to a convex set is convex in the line
    parameter, so a golden-section search on t in [0, 1] finds the minimum; 32 iterations
    shrink the bracket to 2e-7 of the segment length.
    """
    P, Q, lo, hi = np.broadcast_arrays(P, Q, lo, hi)
    d = Q - P
    shape = P.shape[:-1]
    a = np.zeros(shape)
    b = np.ones(shape)
    x1 = b - _GOLDEN * (b - a)
    x2 = a + _GOLDEN * (b - a)
    f1 = point_box_distance(P + x1[..., None] * d, lo, hi)
    f2 = point_box_distance(P + x2[..., None] * d, lo, hi)
    for _ in range(iterations):
        left = f1 < f2  # minimum in [a, x2]
        b = np.where(left, x2, b)
        a = np.where(left, a, x1)
        x2n = np.where(left, x1, a + _GOLDEN * (b - a))
        x1n = np.where(left, b - _GOLDEN * (b - a), x2)
        f_new = point_box_distance(P + np.where(left, x1n, x2n)[..., None] * d, lo, hi)
        f1, f2 = np.where(left, f_new, f2), np.where(left, f1, f_new)
        x1, x2 = x1n, x2n
    t = 0.5 * (a + b)
    best = point_box_distance(P + t[..., None] * d, lo, hi)
    # the end points are candidates too (the bracket never quite reaches them)
    for tt in (0.0, 1.0):
        fe = point_box_distance(P + tt * d, lo, hi)
        better = fe < best
        best = np.where(better, fe, best)
        t = np.where(better, tt, t)
    return best, t


@dataclass(frozen=True)
class CapsuleModel:
    """Capsules of a robot's links plus the reflector mount, with self-collision pairs.

    Parameters
    ----------
    robot
        Nominal description.
    radii
        Capsule radius per body (dof,), m.
    tool_offset
        Reflector centre in the flange frame (3,), m.
    tool_radius
        Radius of the flange-to-reflector capsule, m.

    Attributes
    ----------
    names : tuple of str
        ``"j2.a"``, ``"j4.d"``, ..., ``"tool"``: one per capsule (K capsules).
    radius : ndarray, shape (K,)
        Capsule radii, m.
    body : ndarray, shape (K,)
        1-based body (joint) index each capsule moves with.
    static : ndarray, shape (K,)
        True for capsules that never move (the base column on joint 1's axis); they are
        skipped by the floor and keep-out checks.
    pairs : ndarray, shape (M, 2)
        Capsule index pairs checked for self-collision: not neighbours along the chain, and
        separated along the chain by more than the sum of their radii (pairs closer than that
        touch by construction of the simplified geometry, e.g. across a short elbow offset).
    """

    robot: RobotDescription
    radii: tuple[float, ...]
    tool_offset: tuple[float, float, float]
    tool_radius: float
    names: tuple[str, ...] = field(init=False)
    radius: Array = field(init=False, repr=False)
    body: NDArray[np.intp] = field(init=False, repr=False)
    static: NDArray[np.bool_] = field(init=False, repr=False)
    pairs: NDArray[np.intp] = field(init=False, repr=False)
    _segs: tuple[tuple[int, str], ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        rob = self.robot
        if len(self.radii) != rob.dof:
            raise ConfigError(f"link_radii_mm needs {rob.dof} entries (one per joint), "
                              f"got {len(self.radii)}")
        segs: list[tuple[int, str]] = []
        lengths: list[float] = []
        for i, jt in enumerate(rob.joints):
            if abs(jt.d) > 1e-9:
                segs.append((i, "d"))
                lengths.append(abs(jt.d))
            if abs(jt.a) > 1e-9:
                segs.append((i, "a"))
                lengths.append(abs(jt.a))
        segs.append((rob.dof, "tool"))
        lengths.append(float(np.linalg.norm(self.tool_offset)))
        names = tuple("tool" if k == "tool" else f"j{i + 1}.{k}" for i, k in segs)
        radius = np.array([self.tool_radius if k == "tool" else self.radii[i] for i, k in segs])
        body = np.array([min(i + 1, rob.dof) for i, _ in segs], dtype=np.intp)
        object.__setattr__(self, "_segs", tuple(segs))
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "radius", radius)
        object.__setattr__(self, "body", body)
        # static capsules: end points do not move when every joint moves
        rng = np.random.default_rng(0)
        lim = rob.joint_limits
        qs = rng.uniform(lim[:, 0], lim[:, 1], (4, rob.dof))
        A, B, _, _ = self.segments(qs)
        moved = (np.ptp(A, axis=0).max(axis=1) + np.ptp(B, axis=0).max(axis=1))
        object.__setattr__(self, "static", moved < 1e-9)
        pairs = []
        K = len(segs)
        cum = np.concatenate([[0.0], np.cumsum(lengths)])
        for k in range(K):
            for m in range(k + 2, K):
                between = cum[m] - cum[k + 1]  # chain length strictly between the two
                if between > radius[k] + radius[m]:
                    pairs.append((k, m))
        object.__setattr__(self, "pairs", np.array(pairs, dtype=np.intp).reshape(-1, 2))

    def __len__(self) -> int:
        return len(self.names)

    @property
    def tool_index(self) -> int:
        """Index of the flange-to-reflector capsule (the last one)."""
        return len(self.names) - 1

    def lowest(self, A: Array, B: Array) -> Array:
        """Height of the lowest point of the moving capsules (n,), m, for axes A-B (n, K, 3)
        (inf when none moves): the lower end of a capsule's axis less its radius."""
        moving = ~self.static
        if not moving.any():
            return np.full(A.shape[0], np.inf)
        return (np.minimum(A[:, moving, 2], B[:, moving, 2]) - self.radius[moving]).min(axis=1)

    def self_gap(self, A: Array, B: Array) -> Array:
        """Smallest surface distance between the self-collision pairs (n,), m, for axes
        A-B (n, K, 3) (inf without pairs)."""
        if not len(self.pairs):
            return np.full(A.shape[0], np.inf)
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        d, _, _ = segment_distance(A[:, i], B[:, i], A[:, j], B[:, j])
        return (d - self.radius[i] - self.radius[j]).min(axis=1)

    def segments(self, q: Array) -> tuple[Array, Array, Array, Array]:
        """Capsule axes and the flange/reflector state for ``q`` (n, dof) rad.

        Returns
        -------
        A, B : ndarray, shape (n, K, 3)
            Start and end points of every capsule axis, base frame, m.
        R_flange : ndarray, shape (n, 3, 3)
            Flange orientation in the base frame.
        reflector : ndarray, shape (n, 3)
            Reflector centre in the base frame, m.
        """
        O, R, Kn = link_frames(self.robot, q)
        n = O.shape[0]
        A = np.empty((n, len(self._segs), 3))
        B = np.empty_like(A)
        p = O[:, -1] + R[:, -1] @ np.asarray(self.tool_offset)
        for k, (i, kind) in enumerate(self._segs):
            if kind == "d":
                A[:, k], B[:, k] = O[:, i], Kn[:, i]
            elif kind == "a":
                A[:, k], B[:, k] = Kn[:, i], O[:, i + 1]
            else:
                A[:, k], B[:, k] = O[:, -1], p
        return A, B, R[:, -1], p
