"""Feasibility of measurement poses in a cell, vectorised over candidate joint vectors.

A pose is feasible when

* every joint is inside its working range (robot limits, cell ranges, minus the margin);
* the reflector faces the tracker: the angle between the nest's opening direction and the
  direction to the tracker is below the acceptance half-angle, less the angle the tracker
  position's uncertainty subtends (``asin(tolerance / range)``);
* the beam from tracker to reflector clears every link capsule (and every keep-out box that
  blocks the beam) by ``beam_clearance``; near the tracker end the uncertain tracker position
  adds up to ``position_tolerance`` of required clearance, tapering to zero at the reflector;
* the reflector is within the tracker's range;
* every moving capsule is ``clearance`` above the floor and outside every keep-out box;
* no two capsules of non-neighbouring links come closer than ``clearance``.

Margins are signed: zero or more passes, negative fails; angles in rad, lengths in m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robocal._core.threads import single_threaded
from robocal.errors import ConfigError
from robocal.kinematics import RobotDescription, link_radii
from robocal.planning._cell import Cell
from robocal.planning._geometry import (
    Array,
    CapsuleModel,
    Mask,
    link_frames,
    map_rows,
    segment_box_distance,
    segment_distance,
)

_CHECKS = ("within_limits", "facing", "line_of_sight", "in_range", "above_floor",
           "outside_keep_out", "no_self_collision")


@dataclass(frozen=True)
class Feasibility:
    """Per-pose results of :meth:`FeasibilityChecker.check` for n poses.

    Attributes
    ----------
    q : ndarray, shape (n, dof)
        The joint values checked, rad.
    reflector : ndarray, shape (n, 3)
        Nominal reflector centre in the robot base frame, m.
    range : ndarray, shape (n,)
        Distance tracker (guess) to reflector, m.
    within_limits, in_range : ndarray of bool, shape (n,)
        Joint-range and tracker-range checks.
    angle_margin : ndarray, shape (n,)
        Acceptance half-angle minus the incidence angle minus the tracker-position allowance,
        rad (NaN where visibility was not checked).
    sight_margin : ndarray, shape (n,)
        Smallest beam clearance to a link surface or beam-blocking box beyond what is
        required, m (NaN where visibility was not checked).
    floor_margin, keep_out_margin, self_margin : ndarray, shape (n,)
        Smallest gap beyond the required clearance to floor, keep-out boxes and other links,
        m (+inf when there is nothing to check).
    """

    q: Array
    reflector: Array
    range: Array
    within_limits: Mask
    in_range: Mask
    angle_margin: Array
    sight_margin: Array
    floor_margin: Array
    keep_out_margin: Array
    self_margin: Array

    def __len__(self) -> int:
        return int(self.q.shape[0])

    @property
    def facing(self) -> Mask:
        """The reflector faces the tracker within the acceptance angle (n,)."""
        return ~(self.angle_margin < 0)

    @property
    def line_of_sight(self) -> Mask:
        """The beam is not blocked (n,)."""
        return ~(self.sight_margin < 0)

    @property
    def above_floor(self) -> Mask:
        """Every moving link is above the floor (n,)."""
        return self.floor_margin >= 0

    @property
    def outside_keep_out(self) -> Mask:
        """No link enters a keep-out box (n,)."""
        return self.keep_out_margin >= 0

    @property
    def no_self_collision(self) -> Mask:
        """No two non-neighbouring links collide (n,)."""
        return self.self_margin >= 0

    @property
    def collision_margin(self) -> Array:
        """Smallest of the floor, keep-out and self-collision margins (n,), m."""
        return np.minimum(np.minimum(self.floor_margin, self.keep_out_margin), self.self_margin)

    @property
    def collision_free(self) -> Mask:
        """Within limits, above the floor, outside keep-out boxes, no self-collision (n,)."""
        return self.within_limits & (self.collision_margin >= 0)

    @property
    def ok(self) -> Mask:
        """Every check passes (n,)."""
        out = self.collision_free & self.in_range & self.facing & self.line_of_sight
        return np.asarray(out, dtype=bool)

    def rejected(self) -> dict[str, int]:
        """Number of poses failing each check (a pose can fail several)."""
        return {name: int(np.count_nonzero(~getattr(self, name))) for name in _CHECKS}

    def reasons(self, i: int) -> list[str]:
        """Names of the checks pose ``i`` fails (empty when it is feasible)."""
        return [name for name in _CHECKS if not bool(getattr(self, name)[i])]

    def subset(self, idx: NDArray[np.intp] | Mask) -> Feasibility:
        """The results of the selected poses."""
        return Feasibility(**{k: getattr(self, k)[idx] for k in self.__dataclass_fields__})


class FeasibilityChecker:
    """Check candidate poses of one robot in one cell.

    Parameters
    ----------
    robot
        Nominal robot description.
    cell
        The cell (tracker guess, floor, keep-out boxes, reflector mount, link radii).

    Raises
    ------
    ConfigError
        When the cell does not fit the robot (wrong number of radii or ranges, empty working
        range, the reflector inside the last link's capsule).
    """

    def __init__(self, robot: RobotDescription, cell: Cell) -> None:
        self.robot = robot
        self.cell = cell
        radii_mm = cell.robot.link_radii_mm
        radii, self.radii_source = link_radii(robot)
        if radii_mm is not None:
            radii, self.radii_source = [r * 1e-3 for r in radii_mm], "cell robot.link_radii_mm"
        off = cell.reflector.offset_mm
        tool = tuple(v * 1e-3 for v in off) if off is not None else tuple(robot.tool)
        self.tool_offset: tuple[float, float, float] = (tool[0], tool[1], tool[2])
        self.capsules = CapsuleModel(robot, tuple(radii), self.tool_offset,
                                     cell.robot.tool_radius_mm * 1e-3)
        self.ranges = working_ranges(robot, cell)
        self.tracker = cell.tracker_position_m
        t = cell.tracker
        self.tolerance = t.position_tolerance_mm * 1e-3
        self.beam_clearance = t.beam_clearance_mm * 1e-3
        self.min_range = t.min_range_mm * 1e-3
        self.max_range = t.max_range_mm * 1e-3
        self.clearance = cell.robot.clearance_mm * 1e-3
        self.acceptance = cell.acceptance_rad
        self.nest = cell.nest_direction
        self.floor_z = cell.floor_z_m
        self.box_lo, self.box_hi, self.box_beam = cell.boxes_m()
        self._check_reflector_outside_links()

    def _check_reflector_outside_links(self) -> None:
        """The reflector must sit outside the capsules of the body that carries it."""
        cm = self.capsules
        q0 = self.ranges.mean(axis=1)[None, :]
        A, B, _, p = cm.segments(q0)
        last = np.flatnonzero((cm.body == self.robot.dof) & (np.arange(len(cm)) != cm.tool_index))
        for k in last:
            d, _, _ = segment_distance(p, p, A[:, k], B[:, k])
            need = cm.radius[k] + self.beam_clearance
            if d[0] < need:
                raise ConfigError(
                    f"the reflector ({1e3 * d[0]:.0f} mm from the axis of capsule "
                    f"{cm.names[k]}) lies inside that link's radius plus the beam clearance "
                    f"({1e3 * need:.0f} mm): lengthen reflector.offset_mm or reduce "
                    f"robot.link_radii_mm", source=f"cell {self.cell.name!r}",
                    key="reflector.offset_mm")

    # -- checks --------------------------------------------------------------------------------
    @single_threaded
    def screen(self, q: Array, *, chunk: int = 32768) -> Mask:
        """Cheap first pass over ``q`` (n, dof) rad: limits, tracker range and facing only.

        Poses failing it fail :meth:`check` too; the planner runs the costlier capsule checks
        only on the survivors.

        Returns
        -------
        ndarray of bool, shape (n,)
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        parts = map_rows(lambda sl: self._screen(q[sl]), len(q), chunk)
        return np.concatenate([np.zeros(0, dtype=bool), *parts])

    def _screen(self, qc: Array) -> Mask:
        lim = self.ranges
        O, R, _ = link_frames(self.robot, qc)
        p = O[:, -1] + R[:, -1] @ np.asarray(self.tool_offset)
        v = self.tracker - p
        rng_ = np.linalg.norm(v, axis=1)
        cosang = np.einsum("ni,ni->n", R[:, -1] @ self.nest, v) / np.maximum(rng_, 1e-9)
        allowance = np.arcsin(np.clip(self.tolerance / np.maximum(rng_, 1e-9), 0.0, 1.0))
        facing = np.arccos(np.clip(cosang, -1.0, 1.0)) <= self.acceptance - allowance
        return (facing & (rng_ >= self.min_range) & (rng_ <= self.max_range)
                & np.all((qc >= lim[:, 0] - 1e-12) & (qc <= lim[:, 1] + 1e-12), axis=1))

    @single_threaded
    def check(self, q: Array, *, visibility: bool = True, chunk: int = 8192) -> Feasibility:
        """Check poses ``q`` (n, dof) rad; ``visibility=False`` skips facing/line of sight.

        Returns
        -------
        Feasibility
            Masks and signed margins per pose.
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if q.shape[1] != self.robot.dof:
            raise ConfigError(f"joint array has {q.shape[1]} columns, robot has "
                              f"{self.robot.dof} joints")
        parts = map_rows(lambda sl: self._check(q[sl], visibility), len(q), chunk)
        return Feasibility(**{k: np.concatenate([getattr(p, k) for p in parts])
                              for k in Feasibility.__dataclass_fields__})

    def _check(self, q: Array, visibility: bool) -> Feasibility:
        cm = self.capsules
        n = q.shape[0]
        lim = self.ranges
        within = np.all((q >= lim[:, 0] - 1e-12) & (q <= lim[:, 1] + 1e-12), axis=1)
        A, B, Rf, p = cm.segments(q)
        to_tracker = self.tracker - p
        rng_ = np.linalg.norm(to_tracker, axis=1)
        in_range = (rng_ >= self.min_range) & (rng_ <= self.max_range)
        r = cm.radius
        moving = ~cm.static

        floor_margin = cm.lowest(A, B) - self.floor_z - self.clearance

        # keep-out boxes
        keep = np.full(n, np.inf)
        if len(self.box_lo) and moving.any():
            Am = A[:, moving, None, :]
            Bm = B[:, moving, None, :]
            d, _ = segment_box_distance(Am, Bm, self.box_lo[None, None], self.box_hi[None, None])
            keep = (d - r[moving][None, :, None]).min(axis=(1, 2)) - self.clearance

        selfm = cm.self_gap(A, B) - self.clearance

        angle = np.full(n, np.nan)
        sight = np.full(n, np.nan)
        if visibility:
            u = to_tracker / np.maximum(rng_, 1e-9)[:, None]
            nest = Rf @ self.nest
            incidence = np.arccos(np.clip(np.einsum("ni,ni->n", nest, u), -1.0, 1.0))
            allowance = np.arcsin(np.clip(self.tolerance / np.maximum(rng_, 1e-9), 0.0, 1.0))
            angle = self.acceptance - incidence - allowance
            # line of sight: segment tracker -> reflector against every link capsule but the
            # reflector's own mount; s = 0 at the tracker, 1 at the reflector
            links = np.arange(len(cm)) != cm.tool_index
            T = np.broadcast_to(self.tracker, p.shape)[:, None, :]
            d, s, _ = segment_distance(T, p[:, None, :], A[:, links], B[:, links])
            need = r[links] + self.beam_clearance + self.tolerance * (1.0 - s)
            sight = (d - need).min(axis=1)
            if self.box_beam.any():
                lo = self.box_lo[self.box_beam][None]
                hi = self.box_hi[self.box_beam][None]
                db, t = segment_box_distance(T, p[:, None, :], lo, hi)
                mb = db - self.beam_clearance - self.tolerance * (1.0 - t)
                sight = np.minimum(sight, mb.min(axis=1))
        return Feasibility(q=q, reflector=p, range=rng_, within_limits=within,
                           in_range=in_range, angle_margin=angle, sight_margin=sight,
                           floor_margin=floor_margin, keep_out_margin=keep, self_margin=selfm)

    def path_clear(self, q_from: Array, q_to: Array, *, resolution: float = math.radians(5.0)
                   ) -> Mask:
        """Whether joint-interpolated moves q_from[k] -> q_to[k] (m, dof) stay collision free.

        Each move is sampled so that no joint changes by more than ``resolution`` rad between
        samples; the samples are checked against limits, floor, keep-out boxes and
        self-collision (not visibility: the beam may break while the robot moves).

        Returns
        -------
        ndarray of bool, shape (m,)
        """
        q_from = np.atleast_2d(q_from)
        q_to = np.atleast_2d(q_to)
        steps = np.maximum(1, np.ceil(np.abs(q_to - q_from).max(axis=1) / resolution)).astype(int)
        owner = np.repeat(np.arange(len(steps)), steps - 1)
        if owner.size == 0:
            return np.ones(len(steps), dtype=bool)
        frac = np.concatenate([np.arange(1, k) / k for k in steps])
        qs = q_from[owner] + frac[:, None] * (q_to[owner] - q_from[owner])
        bad = ~self.check(qs, visibility=False).collision_free
        out = np.ones(len(steps), dtype=bool)
        out[np.unique(owner[bad])] = False
        return out


def working_ranges(robot: RobotDescription, cell: Cell) -> Array:
    """Joint ranges (dof, 2) rad the planner may use: robot limits, intersected with the
    cell's ``joint_ranges_deg``, shrunk by ``joint_margin_deg`` at both ends. A range wider
    than one revolution is kept whole (a joint's errors need not repeat after a turn) unless
    the cell sets ``robot.one_revolution``: then it is cut to the revolution centred on
    ``motion.home_deg`` (default 0). :func:`robocal.planning.winding_ranges` narrows joints
    that cannot turn a whole revolution safely.

    Raises
    ------
    ConfigError
        When the cell gives ranges for the wrong number of joints or a range is empty.
    """
    lim = robot.joint_limits.copy()
    cr = cell.robot.joint_ranges_deg
    if cr is not None:
        if len(cr) != robot.dof:
            raise ConfigError(f"joint_ranges_deg needs {robot.dof} entries, got {len(cr)}",
                              source=f"cell {cell.name!r}", key="robot.joint_ranges_deg")
        c = np.radians(np.asarray(cr))
        lim[:, 0] = np.maximum(lim[:, 0], c[:, 0])
        lim[:, 1] = np.minimum(lim[:, 1], c[:, 1])
    m = math.radians(cell.robot.joint_margin_deg)
    lim[:, 0] += m
    lim[:, 1] -= m
    bad = np.flatnonzero(lim[:, 0] >= lim[:, 1])
    if bad.size:
        raise ConfigError(f"joint {bad[0] + 1}: empty working range after the robot limits, "
                          f"joint_ranges_deg and joint_margin_deg", source=f"cell {cell.name!r}",
                          key="robot.joint_ranges_deg")
    if cell.robot.one_revolution:
        wide = lim[:, 1] - lim[:, 0] > 2.0 * math.pi
        lim[wide] = one_revolution(lim, home_of(robot, cell))[wide]
    return lim


def home_of(robot: RobotDescription, cell: Cell) -> Array:
    """The cell's ``motion.home_deg`` (dof,) rad, zeros when it is not given (or mis-sized)."""
    h = cell.motion.home_deg
    return (np.radians(np.asarray(h, dtype=float)) if h is not None and len(h) == robot.dof
            else np.zeros(robot.dof))


def one_revolution(lim: Array, centre: Array) -> Array:
    """Ranges ``lim`` (dof, 2) rad cut to the revolution centred on ``centre`` (dof,) rad
    (moved inside ``lim`` where needed); ranges of one revolution or less are unchanged."""
    out = lim.copy()
    wide = lim[:, 1] - lim[:, 0] > 2.0 * math.pi
    c = np.clip(centre, lim[:, 0] + math.pi, lim[:, 1] - math.pi)
    out[wide, 0] = c[wide] - math.pi
    out[wide, 1] = c[wide] + math.pi
    return out
