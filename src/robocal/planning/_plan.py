"""PLAN.json: the measurement plan the daemon executes (``format = "robocal.plan/1"``).

Layout (JSON object; lengths in mm, angles in degrees, robot base frame)::

    format              "robocal.plan/1"
    robocal_version     version that wrote the plan
    robot               {name, source, description}: description is the robot file layout
    cell                the cell description (file layout, see docs/cell-format.md)
    cell_source         where the cell came from ("builtin:demo" or a path)
    seed                the seed; the same inputs and seed give the same file
    model               {name, label, parameters}: error model the selection optimised
    candidates          {drawn, screened, feasible, rejected: {check: count}}
    observability       {calibration, random_baseline}: O1..O5, condition_number, poses,
                        parameters, identifiable, min_poses, recommended_poses
    unidentifiable      parameter names removed as redundant before the selection
    motion              {max_joint_step_deg, speed_fraction, home_deg, move_time_s,
                        joint_travel_deg, via_points, blocked_moves}
    iso9283             {centre_mm, side_mm, recommended_cycles, cycles} or null
    cpa                 [{joint, span_deg, points, radius_mm}]
    warnings            [str]
    dropped             [{purpose, joints_deg, reason}]: targets left out because no safe
                        route to them was found
    coverage            [{joint, limits_deg, working_deg, planned_deg, of_limits, targets_deg,
                        targets_covered}]: per joint, the range the calibration poses span
                        against the robot limits, the planner's working range and the
                        production program's targets (``--targets``; null without)
    targets_source      the program file whose joint ranges the plan covers, or null
    capsules            {link_radii_mm, tool_radius_mm, source}: the collision model used
    excluded            [{reason, candidates, of_screened, joint_ranges_deg}]: candidate
                        families the collision checks excluded, by cause (which capsules),
                        with the 5-95 % joint ranges of the excluded candidates
    poses               ordered list, executed in this order:
        index               0, 1, 2, ...
        purpose             calibration | validation | via | cpa-jK | iso-P1 .. iso-P5
        measure             false only for via-points (move through, do not measure)
        joints_deg          joint targets (controller joint values)
        reflector_mm        nominal reflector centre, base frame
        angle_margin_deg    acceptance angle left (null for via-points)
        sight_margin_mm     beam clearance left (null for via-points)
        collision_margin_mm clearance left to floor, keep-out boxes, other links
        range_mm            nominal tracker-reflector distance
        move_clear          the joint-interpolated move from the previous target (or from
                            home) was checked collision free

Margins are what is left beyond the cell's required clearances: zero or more means the check
passes.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Annotated, Any, Final, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from robocal._core.files import atomic_write_text
from robocal.errors import ConfigError
from robocal.planning._cell import Cell, pydantic_config_error

PLAN_FORMAT: Final = "robocal.plan/1"

# a JSON list holding only numbers (or null), as json.dumps(indent=...) spreads it over lines
_NUM = r"(?:-?[0-9][0-9.eE+-]*|null)"
_FLAT_LIST = re.compile(rf"\[\s*({_NUM}(?:,\s*{_NUM})*)\s*\]")

Purpose = Annotated[str, Field(pattern=r"^(calibration|validation|via|cpa-j[1-9][0-9]?"
                                       r"|iso-P[1-5])$")]


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class PlannedPose(_Frozen):
    """One target of the plan (see the module docstring for the fields)."""

    index: int = Field(ge=0)
    purpose: Purpose
    measure: bool = True
    joints_deg: list[float] = Field(min_length=1)
    reflector_mm: list[float] = Field(min_length=3, max_length=3)
    angle_margin_deg: float | None = None
    sight_margin_mm: float | None = None
    collision_margin_mm: float
    range_mm: float = Field(ge=0.0)
    move_clear: bool = True


class DroppedTarget(_Frozen):
    """A target the planner left out because no safe route to it was found."""

    purpose: Purpose
    joints_deg: list[float] = Field(min_length=1)
    reason: str


class JointCoverage(_Frozen):
    """Per joint: the range the calibration poses span against limits and targets, deg."""

    joint: int = Field(ge=1)
    limits_deg: list[float] = Field(min_length=2, max_length=2)
    working_deg: list[float] = Field(min_length=2, max_length=2)
    planned_deg: list[float] = Field(min_length=2, max_length=2)
    of_limits: float = Field(ge=0.0)
    targets_deg: list[float] | None = None
    targets_covered: bool | None = None


class ExcludedFamily(_Frozen):
    """Candidates the collision checks excluded for one cause."""

    reason: str
    candidates: int = Field(ge=0)
    of_screened: int = Field(ge=0)
    joint_ranges_deg: list[list[float]]


class CapsuleInfo(_Frozen):
    """The capsule model the collision checks used, and where its radii come from."""

    link_radii_mm: list[float]
    tool_radius_mm: float = Field(gt=0.0)
    source: str


class RobotInfo(_Frozen):
    """The robot the plan was made for."""

    name: str
    source: str
    description: dict[str, Any]


class ModelInfo(_Frozen):
    """The error model the selection optimised, and how the poses were chosen."""

    name: str
    label: str
    parameters: int = Field(ge=0)
    # plans written before the stratified design existed were plain D-optimal
    design: Literal["stratified", "d-optimal"] = "d-optimal"
    design_note: str = ""


class CandidateInfo(_Frozen):
    """How many candidates were drawn, survived the cheap screen, and passed every check."""

    drawn: int = Field(ge=0)
    screened: int = Field(ge=0)
    feasible: int = Field(ge=0)
    rejected: dict[str, int]


class ObservabilityInfo(_Frozen):
    """Observability indices of a pose set (condition_number null when rank deficient)."""

    poses: int = Field(ge=0)
    parameters: int = Field(ge=0)
    identifiable: int = Field(ge=0)
    min_poses: int = Field(ge=0)
    recommended_poses: int = Field(ge=0)
    O1: float
    O2: float
    O3: float
    O4: float
    O5: float
    condition_number: float | None


class ObservabilitySection(_Frozen):
    """Figures of the calibration set and of a random feasible set of the same size."""

    calibration: ObservabilityInfo
    random_baseline: ObservabilityInfo | None = None


class MotionInfo(_Frozen):
    """Ordering settings and the resulting motion summary."""

    max_joint_step_deg: float = Field(gt=0.0)
    speed_fraction: float = Field(gt=0.0, le=1.0)
    home_deg: list[float]
    move_time_s: float = Field(ge=0.0)
    joint_travel_deg: list[float]
    via_points: int = Field(ge=0)
    blocked_moves: int = Field(ge=0)


class IsoInfo(_Frozen):
    """The ISO 9283 cube (base frame)."""

    centre_mm: list[float] = Field(min_length=3, max_length=3)
    side_mm: float = Field(gt=0.0)
    recommended_cycles: int = Field(default=30, ge=1)
    #: Cycles of P1..P5 in the plan (1 in plans written before cycles were planned).
    cycles: int = Field(default=1, ge=1)


class CpaInfo(_Frozen):
    """One single-axis sweep."""

    joint: int = Field(ge=1)
    span_deg: list[float] = Field(min_length=2, max_length=2)
    points: int = Field(ge=1)
    radius_mm: float | None = Field(
        default=None, ge=0.0, description="radius of the reflector's circle about the axis")


class Plan(_Frozen):
    """A measurement plan (PLAN.json). Load with :meth:`load`, write with :meth:`save`."""

    format: Literal["robocal.plan/1"] = PLAN_FORMAT
    robocal_version: str
    robot: RobotInfo
    cell: Cell
    cell_source: str
    seed: int
    model: ModelInfo
    candidates: CandidateInfo
    observability: ObservabilitySection
    unidentifiable: list[str] = Field(default_factory=list)
    motion: MotionInfo
    iso9283: IsoInfo | None = None
    cpa: list[CpaInfo] = Field(default_factory=list)
    warnings: list[str] = Field(default_factory=list)
    dropped: list[DroppedTarget] = Field(default_factory=list)
    # plans written before ADR 0026 have no coverage record
    coverage: list[JointCoverage] = Field(default_factory=list)
    targets_source: str | None = None
    capsules: CapsuleInfo | None = None
    excluded: list[ExcludedFamily] = Field(default_factory=list)
    poses: list[PlannedPose]

    @model_validator(mode="after")
    def _consistent(self) -> Plan:
        dof = len(self.motion.home_deg)
        for i, p in enumerate(self.poses):
            if p.index != i:
                raise ValueError(f"poses[{i + 1}].index is {p.index}, expected {i}")
            if len(p.joints_deg) != dof:
                raise ValueError(f"poses[{i + 1}] has {len(p.joints_deg)} joints, the plan "
                                 f"{dof}")
            if p.measure == (p.purpose == "via"):
                raise ValueError(f"poses[{i + 1}]: via-points are not measured, all other "
                                 "poses are")
        iso = [p.purpose for p in self.poses if p.purpose.startswith("iso-")]
        cycles = self.iso9283.cycles if self.iso9283 is not None else 1
        counts = {name: iso.count(name) for name in set(iso)}
        if any(n != cycles for n in counts.values()):
            raise ValueError(f"each ISO 9283 pose must appear once per cycle ({cycles} "
                             f"cycles): found {dict(sorted(counts.items()))}")
        return self

    # -- views -----------------------------------------------------------------------------------
    @property
    def dof(self) -> int:
        """Number of joints."""
        return len(self.motion.home_deg)

    def joint_targets(self, purpose: str | None = None) -> NDArray[np.float64]:
        """Joint targets (n, dof) rad, all or those of one purpose (prefix match: ``"cpa"``)."""
        rows = [p.joints_deg for p in self.poses
                if purpose is None or p.purpose == purpose or p.purpose.startswith(purpose + "-")]
        return np.radians(np.array(rows, dtype=float).reshape(-1, self.dof))

    def count(self, purpose: str) -> int:
        """Number of poses of one purpose (prefix match as in :meth:`joint_targets`)."""
        return sum(1 for p in self.poses
                   if p.purpose == purpose or p.purpose.startswith(purpose + "-"))

    # -- files -----------------------------------------------------------------------------------
    def to_json(self) -> str:
        """The file text: indented JSON with number lists on one line, trailing newline."""
        text = json.dumps(self.model_dump(mode="json"), indent=1)
        return _FLAT_LIST.sub(lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(","))
                              + "]", text) + "\n"

    def save(self, path: str | Path) -> None:
        """Write the plan atomically (a temporary file renamed over ``path``).

        Raises
        ------
        ConfigError
            When the directory does not exist or cannot be written.
        """
        path = Path(path)
        text = self.to_json()
        d = path.parent if str(path.parent) else Path(".")
        if not d.is_dir():
            raise ConfigError("directory does not exist", source=str(path))
        try:
            atomic_write_text(path, text)
        except OSError as err:
            raise ConfigError(f"cannot write: {err}", source=str(path)) from err
    @classmethod
    def from_json(cls, text: str, *, source: str = "<plan>") -> Plan:
        """Parse and validate plan text; raise :class:`ConfigError` naming the key."""
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as err:
            raise ConfigError(f"not valid JSON: {err}", source=source) from None
        if not isinstance(data, dict):
            raise ConfigError("a plan must be a JSON object", source=source)
        fmt = data.get("format")
        if fmt != PLAN_FORMAT:
            raise ConfigError(f"unsupported plan format {fmt!r} (expected {PLAN_FORMAT!r})",
                              source=source, key="format")
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise pydantic_config_error(err, source, cls) from None

    @classmethod
    def load(cls, path: str | Path) -> Plan:
        """Read and validate a PLAN.json file.

        Raises
        ------
        ConfigError
            When the file is missing or unreadable, not JSON, of another format version, or
            a key is missing, unknown or invalid.
        """
        try:
            text = Path(path).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"cannot read: {err}", source=str(path)) from err
        return cls.from_json(text, source=str(path))
