"""Reading PLAN.json documents into the ordered pose list a campaign executes, and checking
that every move of it is safe.

The plan format belongs to :mod:`robocal.planning` (:class:`~robocal.planning.Plan`,
``"robocal.plan/1"``), which validates the document strictly: unknown keys, missing keys and
wrong types are one :class:`ConfigError` naming the key. In-process verification runs use a
bare form, ``{"format", "robot", "poses": [{"q_deg", "purpose", "measure"}]}``, validated as
strictly (:func:`plan_from_poses` writes it).

Motion safety is recomputed here (:func:`unsafe_moves`): the flags a plan carries
(``move_clear``, margins) are not trusted, and nothing in a plan can switch the check off.
A plan found safe is remembered by a digest of exactly what was checked (its moves, the
robot description, the cell and the limits; :func:`unsafe_moves`): submitting it again to
the same daemon process is not swept again (the swept-path check costs seconds). The
digest lives in the process only; a restarted daemon checks again. The first move of every
run starts where the robot actually stands, never at the plan's
declared home: :func:`check_first_legs` checks it from the joints read from the controller.
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from robocal.daemon.store import PoseRow
from robocal.errors import ConfigError, MotionRejected
from robocal.kinematics import RobotDescription
from robocal.planning import (
    PLAN_FORMAT,
    SAMPLE_FRACTION,
    Cell,
    MotionChecker,
    Plan,
    UnsafeMove,
    pydantic_config_error,
)

__all__ = ["CampaignPlan", "check_first_legs", "first_stops", "parse_plan", "plan_from_poses",
           "stored_plan", "unsafe_moves"]

_PURPOSE: Final = r"^[a-z][a-z0-9-]*$"

#: plans this process found safe, by :func:`_check_key` (most recent last, bounded)
_VERIFIED: OrderedDict[str, None] = OrderedDict()
_VERIFIED_MAX: Final = 64
_VERIFIED_LOCK = threading.Lock()


class _BarePose(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)

    q_deg: list[float] = Field(min_length=1, description="joint target, deg")
    purpose: str = Field(default="calibration", pattern=_PURPOSE)
    measure: bool | None = None


class _BarePlan(BaseModel):
    """The in-process form: joint targets only (no cell, so no collision check)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)

    format: str = PLAN_FORMAT
    robot: str | None = None
    poses: list[_BarePose] = Field(min_length=1)


@dataclass(frozen=True)
class CampaignPlan:
    """A validated plan reduced to what the daemon executes.

    ``cell`` and ``home_deg`` come from a full ``robocal.plan/1`` document (None for the bare
    in-process form).
    """

    robot: str | None
    poses: tuple[PoseRow, ...]
    document: dict[str, Any]
    digest: str
    cell: Cell | None = None
    home_deg: tuple[float, ...] | None = None

    @property
    def text(self) -> str:
        """Canonical JSON of the document (stored with the campaign)."""
        return json.dumps(self.document, sort_keys=True, separators=(",", ":"))


def parse_plan(data: Mapping[str, Any] | str | bytes, *, source: str = "plan",
               strict: bool = True) -> CampaignPlan:
    """Validate a PLAN.json document (mapping or JSON text) and list its poses.

    With ``strict`` (the default) the document must be a complete ``robocal.plan/1`` plan
    (validated by :class:`robocal.planning.Plan`); otherwise the bare in-process form
    ``{"poses": [{"q_deg": [...], "purpose": ..., "measure": ...}]}`` (verification runs).

    Raises
    ------
    ConfigError
        One error naming the source and the first offending key: not a JSON object, another
        format, a missing, unknown or invalid key, joints of differing length, nothing to
        measure.
    """
    if isinstance(data, str | bytes):
        try:
            data = json.loads(data)
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as err:
            raise ConfigError(f"not valid JSON: {err}", source=source) from None
    if not isinstance(data, Mapping):
        raise ConfigError("a plan must be a JSON object", source=source)
    doc = dict(data)
    fmt = doc.get("format", PLAN_FORMAT if not strict else None)
    if fmt != PLAN_FORMAT:
        raise ConfigError(f"unsupported plan format {fmt!r} (expected {PLAN_FORMAT!r})",
                          source=source, key="format")
    rows: list[tuple[list[float], str, bool]]
    cell: Cell | None = None
    home: tuple[float, ...] | None = None
    if strict:
        try:
            plan = Plan.model_validate(doc)
        except ValidationError as err:
            raise pydantic_config_error(err, source, Plan) from None
        rows = [(p.joints_deg, p.purpose, p.measure) for p in plan.poses]
        robot: str | None = plan.robot.name
        cell = plan.cell
        home = tuple(plan.motion.home_deg)
    else:
        try:
            bare = _BarePlan.model_validate(doc)
        except ValidationError as err:
            raise pydantic_config_error(err, source, _BarePlan) from None
        rows = [(p.q_deg, p.purpose, p.purpose != "via" if p.measure is None else p.measure)
                for p in bare.poses]
        robot = bare.robot
    if not rows:
        raise ConfigError("a plan needs a non-empty 'poses' list", source=source, key="poses")
    dof = len(rows[0][0])
    poses = []
    for i, (q, purpose, measure) in enumerate(rows):
        if len(q) != dof:
            raise ConfigError(f"{len(q)} joints, earlier poses have {dof}", source=source,
                              key=f"poses[{i + 1}]")
        poses.append(PoseRow(i, purpose, tuple(float(v) for v in q), measure))
    if home is not None and len(home) != dof:
        raise ConfigError(f"home_deg has {len(home)} joints, the poses {dof}", source=source,
                          key="motion.home_deg")
    if not any(p.measure for p in poses):
        raise ConfigError("the plan has no pose to measure", source=source, key="poses")
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    return CampaignPlan(robot, tuple(poses), doc, digest, cell=cell, home_deg=home)


def unsafe_moves(plan: CampaignPlan, robot: RobotDescription, cell: Cell,
                 limits_rad: Sequence[tuple[float, float]]) -> list[UnsafeMove]:
    """Every move of ``plan`` that is not safe for ``robot`` in ``cell``, along its swept path.

    The moves are home -> pose 0 -> pose 1 -> ... (home: the plan's ``motion.home_deg``; a
    bare plan's first pose is checked on its own). The move to home, or to the first pose,
    starts where the robot stands: the engine checks it when the run starts
    (:func:`check_first_legs`). Each is sampled finely enough for the link
    capsules and checked against ``limits_rad`` (dof pairs), the floor, the keep-out boxes
    and self-collision (:class:`robocal.planning.MotionChecker`); the plan's own flags are
    ignored.

    Raises
    ------
    ConfigError
        When the plan's joint count differs from the robot's, or the cell does not fit it.
    """
    q = np.radians(np.array([p.q_deg for p in plan.poses], dtype=float))
    if q.shape[1] != robot.dof:
        raise ConfigError(f"the plan has {q.shape[1]} joints, robot {robot.name!r} has "
                          f"{robot.dof}", source="plan", key="poses")
    limits = np.asarray(limits_rad, dtype=float)
    home = None if plan.home_deg is None else np.radians(np.asarray(plan.home_deg))
    key = _check_key(q, home, robot, cell, limits)
    with _VERIFIED_LOCK:
        if key in _VERIFIED:
            _VERIFIED.move_to_end(key)
            return []
    checker = MotionChecker(robot, cell, limits=limits)
    unsafe = checker.check_sequence(q, home, [p.purpose for p in plan.poses])
    if not unsafe:
        with _VERIFIED_LOCK:
            _VERIFIED[key] = None
            while len(_VERIFIED) > _VERIFIED_MAX:
                _VERIFIED.popitem(last=False)
    return unsafe


def _check_key(q: NDArray[np.float64], home: NDArray[np.float64] | None,
               robot: RobotDescription, cell: Cell, limits: NDArray[np.float64]) -> str:
    """Digest of everything a swept-path check of moves ``q`` (n, dof) rad depends on: the
    targets and home as checked (rad bytes), the robot description, the cell, the limits
    (rad) and the sampling fraction."""
    h = hashlib.sha256()
    for part in (np.ascontiguousarray(q, dtype=float).tobytes(),
                 b"-" if home is None else np.ascontiguousarray(home, dtype=float).tobytes(),
                 json.dumps(robot.to_dict(), sort_keys=True, default=str).encode(),
                 cell.model_dump_json().encode(),
                 np.ascontiguousarray(limits, dtype=float).tobytes(),
                 repr(SAMPLE_FRACTION).encode()):
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    return h.hexdigest()


def stored_plan(text: str, *, source: str = "stored plan") -> CampaignPlan:
    """A campaign's stored plan document (full ``robocal.plan/1`` or the bare form) parsed
    again."""
    doc = json.loads(text)
    return parse_plan(doc, source=source, strict=isinstance(doc, dict) and "motion" in doc)


def first_stops(plan: CampaignPlan, target: PoseRow, *, via_home: bool
                ) -> list[tuple[str, tuple[float, ...]]]:
    """Where a run's first moves go, as (label, joints deg): home first when ``via_home`` and
    the plan has one (a fresh run), then ``target``, the first pose still to run."""
    stops: list[tuple[str, tuple[float, ...]]] = []
    if via_home and plan.home_deg is not None:
        stops.append(("home (the plan's motion.home_deg)", plan.home_deg))
    stops.append((f"pose {target.idx} ({target.purpose})", target.q_deg))
    return stops


def _deg(q_deg: Sequence[float]) -> str:
    return "[" + ", ".join(f"{v:.2f}" for v in q_deg) + "]"


def _outside(q_deg: Sequence[float], limits_rad: Sequence[tuple[float, float]]) -> str | None:
    """The first joint of ``q_deg`` outside ``limits_rad`` in words, or None."""
    for i, (v, (lo, hi)) in enumerate(zip(q_deg, np.degrees(limits_rad), strict=True)):
        if not (np.isfinite(v) and lo <= v <= hi):
            return f"J{i + 1} at {v:.2f} deg outside [{lo:.2f}, {hi:.2f}] deg"
    return None


def check_first_legs(robot: RobotDescription, cell: Cell | None,
                     limits_rad: Sequence[tuple[float, float]], start_deg: Sequence[float],
                     stops: Sequence[tuple[str, Sequence[float]]]) -> None:
    """Check a run's first moves, from the joints the robot actually stands at.

    ``start_deg`` (dof,) is what the controller reported; ``stops`` come from
    :func:`first_stops`. The start and every stop must lie within ``limits_rad`` (a joint move
    between two points inside the limits stays inside them); with a ``cell`` every move is
    also checked along its swept path (floor, keep-out boxes, self-collision; the same
    :class:`MotionChecker` as :func:`unsafe_moves`).

    Raises
    ------
    MotionRejected
        Naming the actual start pose (deg) and what is wrong; nothing may move then.
    """
    start = tuple(float(v) for v in start_deg)
    where = (f"first move refused before any motion: the robot stands at {_deg(start)} deg "
             "(joints read from the controller)")
    if len(start) != robot.dof:
        raise MotionRejected(f"{where}; the controller reports {len(start)} joints, robot "
                             f"{robot.name!r} has {robot.dof}", kind="daemon")
    bad = _outside(start, limits_rad)
    if bad is not None:
        raise MotionRejected(f"{where}; that start is outside the joint limits with margin: "
                             f"{bad}. Jog the robot inside its limits, then resume",
                             kind="daemon")
    for label, q in stops:
        bad = _outside(q, limits_rad)
        if bad is not None:
            raise MotionRejected(f"{where}; {label} is outside the joint limits: {bad}",
                                 kind="daemon")
    if cell is None:
        return
    q_rad = np.radians(np.array([start, *(tuple(q) for _, q in stops)], dtype=float))
    checker = MotionChecker(robot, cell, limits=np.asarray(limits_rad, dtype=float))
    res = checker.check_moves(q_rad[:-1], q_rad[1:])
    for k in (int(i) for i in np.flatnonzero(~res.safe)):
        origin = "the actual start" if k == 0 else stops[k - 1][0]
        raise MotionRejected(
            f"{where}; the move from {origin} to {stops[k][0]} {_deg(stops[k][1])} deg is "
            f"unsafe in cell {cell.name!r}: {res.reasons[k]} at {100.0 * res.at[k]:.0f} % of "
            f"the move, joints {_deg(np.degrees(res.q_bad[k]))} deg. Move the robot to a "
            "safe start (e.g. the plan's home), then resume", kind="daemon")


def plan_from_poses(q_deg: Sequence[Sequence[float]], *, purpose: str = "calibration",
                    robot: str | None = None, purposes: Sequence[str] | None = None
                    ) -> dict[str, Any]:
    """A bare plan document listing joint targets (degrees), for in-process verification runs.

    Parse it with ``parse_plan(doc, strict=False)``.
    """
    poses = [{"q_deg": [float(v) for v in q],
              "purpose": purposes[i] if purposes is not None else purpose}
             for i, q in enumerate(q_deg)]
    return {"format": PLAN_FORMAT, "robot": robot, "poses": poses}
