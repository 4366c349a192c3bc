"""Motion safety: every move of a plan checked along its swept path, vectorised over samples.

A move is the joint-interpolated path from one target to the next (``q(s) = a + s (b - a)``,
``s`` in [0, 1]), which is what a joint move of an industrial controller follows up to servo
lag. It is sampled so finely that no capsule axis point travels more than ``fraction`` of its
capsule's radius, nor more than the cell's clearance, between two samples. The travel of a
capsule is bounded by ``sum_i lever[i, k] |d theta_i|``, where ``lever[i, k]`` is the chain
length from joint i's axis to the far end of capsule k (an upper bound on the distance of any
point of the capsule from that axis). Between samples a capsule therefore comes at most half a
step closer to an obstacle than at the nearer sample, and two capsules at most one step closer
to each other: with every sample ``clearance`` clear, nothing ever touches.

Each sample is checked against the joint limits, the floor, the keep-out boxes (the pedestal is
one in the demo cell) and self-collision between non-neighbouring capsules (the static base
column included). The beam is not checked while moving: it may break and is re-acquired.

Lengths in m, angles in rad, robot base frame; the messages use mm and degrees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal._core.threads import single_threaded
from robocal.kinematics import RobotDescription
from robocal.planning._cell import Cell
from robocal.planning._feasibility import FeasibilityChecker
from robocal.planning._geometry import (
    Array,
    Index,
    Mask,
    map_rows,
    segment_box_distance,
    segment_distance,
)

#: Largest capsule travel between two samples, as a fraction of the capsule's radius.
SAMPLE_FRACTION = 0.25

# every _COARSE-th sample of a move is checked first
_COARSE = 8
# margin kept back when a sample's margin vouches for its neighbours, m (and rad for limits):
# far above the rounding of the distances and the golden-section box search (2e-7 m per m)
_ROOM_SLACK = 1e-5

# per-sample failure kinds, in the order they are reported
_LIMIT, _FLOOR, _BOX, _SELF = 0, 1, 2, 3


@dataclass(frozen=True)
class UnsafeMove:
    """One move of a plan that fails the swept-path check.

    Attributes
    ----------
    index
        Plan index of the move's target (the move comes from pose ``index - 1``, or from
        home for index 0).
    purpose
        Purpose of that pose (``calibration``, ``via``, ...), when known.
    reason
        What fails first along the move, e.g. ``"capsule j3.a 12 mm below the floor
        clearance"``.
    at
        Fraction of the move where it first fails (0 = start, 1 = target).
    q_deg
        Joint values there, deg.
    target_deg
        The target of the move, deg.
    """

    index: int
    purpose: str | None
    reason: str
    at: float
    q_deg: tuple[float, ...]
    target_deg: tuple[float, ...]

    def describe(self) -> str:
        """One line naming the pose, the reason and the joint values in degrees."""
        what = f"pose {self.index}" + (f" ({self.purpose})" if self.purpose else "")
        q = ", ".join(f"{v:.2f}" for v in self.q_deg)
        t = ", ".join(f"{v:.2f}" for v in self.target_deg)
        where = ("at the target" if self.at >= 1.0 - 1e-12
                 else "at the start" if self.at <= 1e-12
                 else f"at {100.0 * self.at:.0f} % of the move")
        return (f"{what}: {self.reason} {where}, joints [{q}] deg (target [{t}] deg)")


@dataclass(frozen=True)
class MoveCheck:
    """Per-move results of :meth:`MotionChecker.check_moves` for m moves.

    Attributes
    ----------
    safe : ndarray of bool, shape (m,)
        Every sample of the move passes.
    samples : ndarray of int, shape (m,)
        Intervals the move was cut into (samples = intervals + 1, both ends included).
    at : ndarray, shape (m,)
        Fraction of the move at its first failing sample (NaN for safe moves).
    q_bad : ndarray, shape (m, dof)
        Joint values at that sample, rad (NaN for safe moves).
    reasons : list of str
        Reason of the first failing sample per move ("" for safe moves).
    """

    safe: Mask
    samples: NDArray[np.int64]
    at: Array
    q_bad: Array
    reasons: list[str]


class MotionChecker:
    """Swept-path checks of joint moves for one robot in one cell.

    Parameters
    ----------
    robot
        Nominal robot description.
    cell
        The cell: floor, keep-out boxes, link radii, clearance (the tracker is not used).
    limits : ndarray, shape (dof, 2), optional
        Joint limits every sample must respect, rad (default: the planner's working ranges
        of the cell, i.e. robot limits, ``joint_ranges_deg`` and ``joint_margin_deg``).
    fraction
        Largest capsule travel between samples as a fraction of its radius.

    Raises
    ------
    ConfigError
        When the cell does not fit the robot (see :class:`FeasibilityChecker`).
    """

    def __init__(self, robot: RobotDescription, cell: Cell, *, limits: Array | None = None,
                 fraction: float = SAMPLE_FRACTION) -> None:
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        self.robot = robot
        self.cell = cell
        self.feasibility = FeasibilityChecker(robot, cell)
        self.capsules = self.feasibility.capsules
        self.limits = (self.feasibility.ranges if limits is None
                       else np.asarray(limits, dtype=float).reshape(robot.dof, 2))
        self.clearance = self.feasibility.clearance
        self.floor_z = self.feasibility.floor_z
        self.box_lo, self.box_hi, _ = cell.boxes_m()
        self.box_names = [b.name or f"#{i + 1}" for i, b in enumerate(cell.keep_out)]
        cm = self.capsules
        step = fraction * cm.radius
        if self.clearance > 0.0:
            step = np.minimum(step, self.clearance)
        #: largest travel of each capsule's axis between two samples (K,), m
        self.step = step
        #: bound on each capsule's travel per rad of each joint angle theta (dof, K), m/rad
        self.lever = _levers(robot, cm.names, self.feasibility.tool_offset)
        self.lever[:, cm.static] = 0.0
        self._C_abs = np.abs(robot.coupling_matrix)
        # swept-path verdicts of legs the planner has checked (see leg_verdicts) and moves
        # check_moves found safe (start + end bytes), both valid for the geometry they were
        # checked against (the planner narrows the limits in place once)
        self._leg_verdicts: dict[bytes, tuple[bool, str]] = {}
        self._safe_moves: set[bytes] = set()
        self._checked_under = self._geometry()

    def _geometry(self) -> bytes:
        """Everything a verdict depends on that can change in place: the limits, the floor,
        the keep-out boxes, the clearance and the capsules' radii."""
        return b"|".join(np.ascontiguousarray(a, dtype=float).tobytes() for a in (
            self.limits, self.box_lo, self.box_hi, [self.floor_z, self.clearance],
            self.capsules.radius, self.step))

    def _valid(self) -> None:
        now = self._geometry()
        if now != self._checked_under:
            self._leg_verdicts.clear()
            self._safe_moves.clear()
            self._checked_under = now

    @property
    def leg_verdicts(self) -> dict[bytes, tuple[bool, str]]:
        """Swept-path verdicts of legs the planner has checked: (start, end, max step) bytes
        -> (safe, reason or "" when not explained), so that a leg is checked once per plan;
        emptied when the limits, the floor, the boxes, the clearance or the radii change."""
        self._valid()
        return self._leg_verdicts

    # -- sampling --------------------------------------------------------------------------------
    def intervals(self, q_from: Array, q_to: Array) -> NDArray[np.int64]:
        """Intervals each move q_from[k] -> q_to[k] (m, dof) rad is cut into (m,), >= 1."""
        dtheta = np.abs(np.atleast_2d(q_to) - np.atleast_2d(q_from)) @ self._C_abs.T
        travel = dtheta @ self.lever                               # (m, K) m
        n = np.ceil(np.max(travel / self.step, axis=1) - 1e-9)
        return np.maximum(n, 1).astype(np.int64)

    def samples(self, q_from: Array, q_to: Array) -> tuple[Array, Index, Array]:
        """Samples of every move, both ends included.

        Returns
        -------
        q : ndarray, shape (S, dof)
            Joint values of all samples, move after move, rad.
        owner : ndarray of int, shape (S,)
            Move index of each sample.
        s : ndarray, shape (S,)
            Fraction of its move, 0 .. 1.
        """
        q_from = np.atleast_2d(np.asarray(q_from, dtype=float))
        q_to = np.atleast_2d(np.asarray(q_to, dtype=float))
        n = self.intervals(q_from, q_to)
        per = n + 1
        owner = np.repeat(np.arange(len(n)), per)
        first = np.concatenate([[0], np.cumsum(per)[:-1]])
        s = (np.arange(int(per.sum())) - np.repeat(first, per)) / np.repeat(n, per)
        q = q_from[owner] + s[:, None] * (q_to[owner] - q_from[owner])
        return q, owner, s

    # -- checks --------------------------------------------------------------------------------
    @single_threaded
    def check_moves(self, q_from: Array, q_to: Array, *, chunk: int = 8192,
                    explain: bool = True) -> MoveCheck:
        """Check the moves q_from[k] -> q_to[k] (m, dof) rad along their swept paths
        (``explain=False`` leaves the reasons empty, which saves time)."""
        q_from = np.atleast_2d(np.asarray(q_from, dtype=float))
        q_to = np.atleast_2d(np.asarray(q_to, dtype=float))
        m = len(q_from)
        if m == 0:
            return MoveCheck(safe=np.ones(0, dtype=bool), samples=np.zeros(0, dtype=np.int64),
                             at=np.zeros(0), q_bad=np.zeros((0, self.robot.dof)), reasons=[])
        q, owner, s = self.samples(q_from, q_to)
        bad = np.zeros(len(q), dtype=bool)
        # coarse pass first (every 8th sample and the ends): most unsafe moves fail there, and
        # only the samples of moves that pass it are checked in full
        n = self.intervals(q_from, q_to)
        first = np.concatenate([[0], np.cumsum(n + 1)[:-1]])
        offset = np.arange(len(q)) - np.repeat(first, n + 1)
        coarse = (offset % _COARSE == 0) | (s == 1.0)
        room = np.full(len(q), -np.inf)      # samples of clearance to spare (coarse samples)
        idx = np.flatnonzero(coarse)
        room[idx] = self._rooms(q, owner, idx, q_from, q_to, n, chunk)
        bad[idx] = room[idx] < 0.0
        failed = np.zeros(m, dtype=bool)
        failed[owner[bad]] = True
        # a sample within ``room`` intervals of a checked sample that passes passes too (see
        # _room), so it needs no check of its own. The fine samples are visited by halving
        # (offsets 4, then 2, 6, then the odd ones between checked or vouched-for samples), and
        # a vouched-for sample passes on what is left of its voucher's room. Every sample of a
        # move that passed the coarse pass is thus checked or shown to pass: the verdicts and
        # first failing samples are those of checking every sample.
        base = first[owner]
        end = base + n[owner]
        for h in (_COARSE // 2, _COARSE // 4, 1):
            at_h = np.flatnonzero((offset % (2 * h) == h) & ~coarse & ~failed[owner])
            prev_i = at_h - h
            next_i = np.minimum(at_h + h, end[at_h])
            room_v = np.maximum(room[prev_i] - h, room[next_i] - (next_i - at_h))
            vouched = room_v >= 0.0
            room[at_h[vouched]] = room_v[vouched]
            idx = at_h[~vouched]
            room[idx] = self._rooms(q, owner, idx, q_from, q_to, n, chunk)
            bad[idx] = room[idx] < 0.0
        safe = np.ones(m, dtype=bool)
        at = np.full(m, np.nan)
        q_bad = np.full((m, self.robot.dof), np.nan)
        reasons = [""] * m
        idx = np.flatnonzero(bad)
        if idx.size:
            moves, first = np.unique(owner[idx], return_index=True)
            where = idx[first]                     # first failing sample of each unsafe move
            safe[moves] = False
            at[moves] = s[where]
            q_bad[moves] = q[where]
            if explain:
                for mv, text in zip(moves, self.explain(q[where]), strict=True):
                    reasons[int(mv)] = text
        self._remember(q_from[safe], q_to[safe])
        return MoveCheck(safe=safe, samples=n, at=at, q_bad=q_bad,
                         reasons=reasons)

    def _move_keys(self, q_from: Array, q_to: Array) -> list[bytes]:
        both = np.ascontiguousarray(np.hstack([q_from, q_to]), dtype=float)
        return [row.tobytes() for row in both]

    def _known_safe(self) -> set[bytes]:
        self._valid()
        return self._safe_moves

    def _remember(self, q_from: Array, q_to: Array) -> None:
        self._known_safe().update(self._move_keys(q_from, q_to))

    def moves_safe(self, q_from: Array, q_to: Array) -> Mask:
        """Whether each move q_from[k] -> q_to[k] is safe (m,) (see :meth:`check_moves`)."""
        return self.check_moves(q_from, q_to).safe

    def check_sequence(self, q: Array, home: Array | None = None,
                       purposes: Sequence[str] | None = None) -> list[UnsafeMove]:
        """Unsafe moves of a whole plan: home -> q[0] -> q[1] -> ... (n, dof) rad.

        Without ``home`` the first target is checked as a pose on its own.
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        start = q[:1] if home is None else np.asarray(home, dtype=float)[None, :]
        q_from = np.vstack([start, q[:-1]])
        # a move this checker has already found safe (exactly these end points, these
        # limits) is not swept again: the planner's final check costs nothing for the legs
        # it routed
        known = self._known_safe()
        todo = np.array([k not in known for k in self._move_keys(q_from, q)], dtype=bool)
        res = self.check_moves(q_from[todo], q[todo])
        out = []
        rows = np.flatnonzero(todo)
        for j in np.flatnonzero(~res.safe):
            i = int(rows[j])
            out.append(UnsafeMove(
                index=i, purpose=None if purposes is None else purposes[i],
                reason=res.reasons[j], at=float(res.at[j]),
                q_deg=tuple(round(float(v), 4) for v in np.degrees(res.q_bad[j])),
                target_deg=tuple(round(float(v), 4) for v in np.degrees(q[i]))))
        return out

    def margins(self, q: Array) -> tuple[Array, Array, Array, Array]:
        """Signed margins of poses ``q`` (n, dof) rad: limits (rad), floor, boxes, self (m).

        Zero or more passes; the floor, box and self margins are beyond ``clearance``.
        """
        cm = self.capsules
        q = np.atleast_2d(q)
        n = len(q)
        lim = np.minimum(q - self.limits[:, 0], self.limits[:, 1] - q).min(axis=1)
        A, B, _, _ = cm.segments(q)
        r = cm.radius
        moving = ~cm.static
        floor = cm.lowest(A, B) - self.floor_z - self.clearance
        box = np.full(n, np.inf)
        if len(self.box_lo) and moving.any():
            d = self._box_distance(A[:, moving], B[:, moving], r[moving])
            box = (d - r[moving][None, :, None]).min(axis=(1, 2)) - self.clearance
        selfm = cm.self_gap(A, B) - self.clearance
        return lim, floor, box, selfm

    def _box_distance(self, A: Array, B: Array, r: Array) -> Array:
        """Distance (n, K, nbox) from segments A-B (n, K, 3) to the keep-out boxes, m.

        Exact (golden-section search) where the segment's bounding box comes within
        ``r + clearance`` of a keep-out box; elsewhere the gap between the two bounding boxes,
        a lower bound that already clears the box, stands in (it saves most of the work).
        """
        seg_lo = np.minimum(A, B)[:, :, None, :]
        seg_hi = np.maximum(A, B)[:, :, None, :]
        gap = np.maximum(np.maximum(self.box_lo - seg_hi, seg_lo - self.box_hi), 0.0)
        d = np.sqrt(np.einsum("...i,...i->...", gap, gap))
        near = np.nonzero(d < r[None, :, None] + self.clearance)
        if near[0].size:
            i, k, b = near
            d[near], _ = segment_box_distance(A[i, k], B[i, k], self.box_lo[b], self.box_hi[b])
        return d

    def bad(self, q: Array, *, chunk: int = 8192) -> Mask:
        """Poses ``q`` (n, dof) rad that fail a limit, floor, keep-out or self check (n,)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        out = np.zeros(len(q), dtype=bool)
        for i in range(0, len(q), chunk):
            out[i:i + chunk] = self._bad(q[i:i + chunk])
        return out

    def _rooms(self, q: Array, owner: Index, idx: Index, q_from: Array, q_to: Array,
               n: NDArray[np.int64], chunk: int) -> Array:
        """:meth:`_room` of the samples ``idx`` of all samples ``q`` (of moves ``owner``)."""
        def one(sl: slice) -> Array:
            part = idx[sl]
            return self._room(q[part], owner[part], q_from, q_to, n)

        return np.concatenate([np.zeros(0), *map_rows(one, len(idx), chunk)])

    def _room(self, q: Array, owner: Index, q_from: Array, q_to: Array,
              n: NDArray[np.int64]) -> Array:
        """Whole sampling intervals each sample ``q`` (S, dof) of move ``owner`` can be moved
        along its move and still pass (S,), -inf where it fails itself.

        Per interval a capsule travels at most ``t = max_k travel_k / n`` (see
        :meth:`intervals`), so a floor or box margin shrinks by at most ``t`` and a self margin
        by at most ``2 t``; a joint's distance to its limits shrinks by at most its own step.
        """
        lim, floor, box, selfm = self.margins(q)
        fails = (lim < -1e-12) | (floor < 0) | (box < 0) | (selfm < 0)
        d = np.abs(q_to[owner] - q_from[owner]) / n[owner][:, None]          # (S, dof) rad
        t = np.max((d @ self._C_abs.T) @ self.lever, axis=1)                # (S,) m
        gap = np.minimum(np.minimum(floor, box), selfm) - _ROOM_SLACK
        with np.errstate(divide="ignore", invalid="ignore"):
            by_space = np.where(t > 0.0, gap / (2.0 * t), np.inf)
            by_limit = np.where(d.max(axis=1) > 0.0,
                                (lim - _ROOM_SLACK) / d.max(axis=1), np.inf)
        room = np.floor(np.minimum(by_space, by_limit))
        room[fails] = -np.inf
        return np.maximum(room, np.where(fails, -np.inf, 0.0))

    def _bad(self, q: Array) -> Mask:
        lim, floor, box, selfm = self.margins(q)
        return (lim < -1e-12) | (floor < 0) | (box < 0) | (selfm < 0)

    def explain(self, q: Array) -> list[str]:
        """The first failing check of each pose ``q`` (n, dof) rad, in words (mm, deg)."""
        cm = self.capsules
        q = np.atleast_2d(q)
        out: list[str] = []
        lim, floor, box, selfm = self.margins(q)
        A, B, _, _ = cm.segments(q)
        r = cm.radius
        moving = np.flatnonzero(~cm.static)
        for n in range(len(q)):
            parts: list[str] = []
            if lim[n] < -1e-12:
                lo, hi = self.limits[:, 0], self.limits[:, 1]
                j = int(np.argmax(np.maximum(lo - q[n], q[n] - hi)))
                parts.append(f"J{j + 1} at {math.degrees(q[n, j]):.2f} deg outside "
                             f"[{math.degrees(lo[j]):.2f}, {math.degrees(hi[j]):.2f}] deg")
            if floor[n] < 0:
                zlow = np.minimum(A[n, moving, 2], B[n, moving, 2]) - r[moving]
                k = int(moving[np.argmin(zlow)])
                parts.append(f"capsule {cm.names[k]} {-1e3 * floor[n]:.0f} mm into the floor "
                             f"clearance (floor z = {1e3 * self.floor_z:.0f} mm, clearance "
                             f"{1e3 * self.clearance:.0f} mm)")
            if box[n] < 0:
                d, _ = segment_box_distance(A[n, moving, None, :], B[n, moving, None, :],
                                            self.box_lo[None], self.box_hi[None])
                g = d - r[moving][:, None]
                kk, bb = np.unravel_index(int(np.argmin(g)), g.shape)
                parts.append(f"capsule {cm.names[int(moving[kk])]} {-1e3 * box[n]:.0f} mm into "
                             f"the clearance of keep-out box {self.box_names[int(bb)]!r}")
            if selfm[n] < 0:
                pi, pj = cm.pairs[:, 0], cm.pairs[:, 1]
                d, _, _ = segment_distance(A[n, pi], B[n, pi], A[n, pj], B[n, pj])
                p = int(np.argmin(d - r[pi] - r[pj]))
                parts.append(f"self-collision of capsules {cm.names[int(pi[p])]} and "
                             f"{cm.names[int(pj[p])]} ({-1e3 * selfm[n]:.0f} mm into the "
                             "clearance)")
            out.append("; ".join(parts))
        return out


def _levers(robot: RobotDescription, names: Sequence[str], tool: Sequence[float]) -> Array:
    """Lever arms (dof, K), m: chain length from joint i's axis to capsule k's far end.

    Joint i turns about the z axis of frame i-1, through that frame's origin; every point of
    a capsule distal to it is at most the chain length (sum of |d| and |a| along the way, plus
    the reflector offset) from that origin, hence from the axis.
    """
    dof = robot.dof
    frame = np.concatenate([[0.0], np.cumsum([abs(j.d) + abs(j.a) for j in robot.joints])])
    tool_len = float(np.linalg.norm(tool))
    lever = np.zeros((dof, len(names)))
    for k, name in enumerate(names):
        if name == "tool":
            link, end = dof - 1, frame[dof] + tool_len
        else:
            link = int(name[1:name.index(".")]) - 1
            end = frame[link] + abs(robot.joints[link].d) if name.endswith(".d") \
                else frame[link + 1]
        for i in range(link + 1):
            lever[i, k] = max(0.0, end - frame[i])
    return lever
