"""Cell description files (TOML): where the tracker stands, what the robot must not touch.

The file layout is documented in ``docs/cell-format.md``. Everything is given in the **robot
base frame**, lengths in mm and angles in degrees; :class:`Cell` keeps the file layout (so a
plan can embed it verbatim) and offers SI accessors (metres, radians) for the planner.
Unknown keys are rejected, naming the file and the key.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from robocal._core.files import read_toml
from robocal.errors import ConfigError

Array = NDArray[np.float64]

__all__ = ["Cell", "builtin_cells", "load_cell"]


_MAX_ABS_MM = 1e6


def _finite3(v: list[float], what: str = "value") -> list[float]:
    # a bound well beyond any cell (1 km) keeps absurd numbers from overflowing later sums
    if len(v) != 3 or not all(math.isfinite(x) and abs(x) <= _MAX_ABS_MM for x in v):
        raise ValueError(f"{what} must be 3 finite numbers within +-{_MAX_ABS_MM:g} mm")
    return [float(x) for x in v]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class TrackerSection(_Strict):
    """``[tracker]``: the laser tracker head, robot base frame."""

    position_mm: list[float] = Field(
        description="tracker head (beam origin) in the robot base frame, mm; ~100 mm accuracy "
                    "is enough")
    position_tolerance_mm: float = Field(
        100.0, ge=0.0, le=2000.0,
        description="how far the real tracker may be from position_mm; the acceptance angle "
                    "and the line-of-sight clearance are reduced accordingly")
    min_range_mm: float = Field(800.0, ge=0.0, description="closest reflector distance")
    max_range_mm: float = Field(20000.0, gt=0.0, description="farthest reflector distance")
    beam_clearance_mm: float = Field(
        10.0, ge=0.0, description="minimum gap between the beam and any link surface")

    @field_validator("position_mm")
    @classmethod
    def _pos(cls, v: list[float]) -> list[float]:
        return _finite3(v, "position_mm")

    @model_validator(mode="after")
    def _ranges(self) -> TrackerSection:
        if self.min_range_mm >= self.max_range_mm:
            raise ValueError("min_range_mm must be below max_range_mm")
        return self


class ReflectorSection(_Strict):
    """``[reflector]``: the SMR nest on the flange."""

    offset_mm: list[float] | None = Field(
        default=None, description="SMR centre in the flange frame, mm (default: the robot "
                                  "file's tool_mm)")
    direction: list[float] = Field(
        default_factory=lambda: [0.0, 0.0, 1.0],
        description="opening direction of the nest in the flange frame (any length)")
    acceptance_deg: float = Field(default=30.0, gt=0.0, le=90.0,
                                  description="half-angle of the SMR acceptance cone")

    @field_validator("offset_mm")
    @classmethod
    def _off(cls, v: list[float] | None) -> list[float] | None:
        return None if v is None else _finite3(v, "offset_mm")

    @field_validator("direction")
    @classmethod
    def _dir(cls, v: list[float]) -> list[float]:
        v = _finite3(v, "direction")
        if math.hypot(*v) < 1e-9:
            raise ValueError("direction must not be the zero vector")
        return v


class RobotSection(_Strict):
    """``[robot]``: the capsule model of the links and the joint working ranges."""

    link_radii_mm: list[float] | None = Field(
        default=None, description="capsule radius per joint body (one per joint), mm; default "
                                  "from the robot's size")
    tool_radius_mm: float = Field(default=25.0, gt=0.0,
                                  description="radius of the flange-to-reflector capsule")
    clearance_mm: float = Field(
        default=10.0, ge=0.0, description="minimum gap of link surfaces to floor, keep-out "
                                          "boxes and other links")
    joint_margin_deg: float = Field(default=5.0, ge=0.0, le=45.0,
                                    description="stay this far inside every joint range")
    joint_ranges_deg: list[list[float]] | None = Field(
        default=None, description="optional working range [min, max] per joint, deg; "
                                  "intersected with the robot's limits")
    one_revolution: bool = Field(
        default=False,
        description="cut every joint range wider than 360 deg to the revolution centred on "
                    "motion.home_deg (the same positions, but joint errors that do not repeat "
                    "after a turn are then not calibrated beyond it)")

    @field_validator("link_radii_mm")
    @classmethod
    def _radii(cls, v: list[float] | None) -> list[float] | None:
        if v is None:
            return None
        if not v or not all(math.isfinite(x) and x > 0 for x in v):
            raise ValueError("link_radii_mm must be positive finite numbers, one per joint")
        return [float(x) for x in v]

    @field_validator("joint_ranges_deg")
    @classmethod
    def _ranges(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is None:
            return None
        for i, r in enumerate(v, 1):
            if len(r) != 2 or not all(math.isfinite(x) for x in r) or r[0] >= r[1]:
                raise ValueError(f"joint_ranges_deg[{i}] must be [min, max] with min < max")
        return [[float(a), float(b)] for a, b in v]


class FloorSection(_Strict):
    """``[floor]``: the floor (or table top) plane z = z_mm of the base frame."""

    z_mm: float = Field(default=0.0, description="floor height in the base frame, mm")

    @field_validator("z_mm")
    @classmethod
    def _z(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("z_mm must be finite")
        return v


class KeepOutBox(_Strict):
    """``[[keep_out]]``: an axis-aligned box (base frame) no link may enter."""

    name: str = ""
    min_mm: list[float]
    max_mm: list[float]
    blocks_beam: bool = Field(True, description="a solid obstacle: it also blocks the beam")

    @field_validator("min_mm", "max_mm")
    @classmethod
    def _corner(cls, v: list[float]) -> list[float]:
        return _finite3(v, "corner")

    @model_validator(mode="after")
    def _order(self) -> KeepOutBox:
        if not all(a < b for a, b in zip(self.min_mm, self.max_mm, strict=True)):
            raise ValueError("min_mm must be below max_mm on every axis")
        return self


class MotionSection(_Strict):
    """``[motion]``: limits for ordering the poses."""

    max_joint_step_deg: float = Field(
        default=90.0, gt=0.0, le=720.0,
        description="largest joint change of one move; longer moves get via-points")
    speed_fraction: float = Field(default=0.25, gt=0.0, le=1.0,
                                  description="fraction of each joint's max speed assumed")
    home_deg: list[float] | None = Field(
        default=None,
        description="where the campaign starts (default: all zeros, clipped to ranges)")

    @field_validator("home_deg")
    @classmethod
    def _home(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and not all(math.isfinite(x) for x in v):
            raise ValueError("home_deg must be finite")
        return v


class Cell(_Strict):
    """A measurement cell: tracker placement, floor, keep-out boxes, reflector mount, motion.

    The model mirrors the TOML file (mm, deg, robot base frame); the ``*_m`` / ``*_rad``
    accessors return SI values. Build it with :func:`load_cell` or :meth:`from_dict`.
    """

    name: str = "cell"
    description: str = ""
    tracker: TrackerSection
    reflector: ReflectorSection = Field(default_factory=ReflectorSection)
    robot: RobotSection = Field(default_factory=RobotSection)
    floor: FloorSection = Field(default_factory=FloorSection)
    keep_out: list[KeepOutBox] = Field(default_factory=list)
    motion: MotionSection = Field(default_factory=MotionSection)

    @model_validator(mode="after")
    def _tracker_above_floor(self) -> Cell:
        if self.tracker.position_mm[2] <= self.floor.z_mm:
            raise ValueError(f"the tracker (z = {self.tracker.position_mm[2]:g} mm) must stand "
                             f"above the floor (z_mm = {self.floor.z_mm:g})")
        return self

    # -- SI accessors ------------------------------------------------------------------------
    @property
    def tracker_position_m(self) -> Array:
        """Tracker head in the robot base frame (3,), m."""
        return np.asarray(self.tracker.position_mm) * 1e-3

    @property
    def nest_direction(self) -> Array:
        """Unit opening direction of the nest in the flange frame (3,)."""
        d = np.asarray(self.reflector.direction, dtype=float)
        return d / np.linalg.norm(d)

    @property
    def acceptance_rad(self) -> float:
        """Acceptance half-angle, rad."""
        return math.radians(self.reflector.acceptance_deg)

    @property
    def floor_z_m(self) -> float:
        """Floor height in the base frame, m."""
        return self.floor.z_mm * 1e-3

    def boxes_m(self) -> tuple[Array, Array, NDArray[np.bool_]]:
        """Keep-out boxes: lower corners (B, 3) m, upper corners (B, 3) m, blocks-beam (B,)."""
        if not self.keep_out:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=bool)
        lo = np.array([b.min_mm for b in self.keep_out]) * 1e-3
        hi = np.array([b.max_mm for b in self.keep_out]) * 1e-3
        return lo, hi, np.array([b.blocks_beam for b in self.keep_out])

    # -- files ---------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "<cell>") -> Cell:
        """Validate the file layout; raise :class:`ConfigError` naming ``source`` and the key."""
        if not isinstance(data, dict):
            raise ConfigError("a cell description must be a table", source=source)
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise pydantic_config_error(err, source, Cell) from None

    def to_dict(self) -> dict[str, Any]:
        """Return the file layout (None values left out, so it can be written back as TOML)."""
        return self.model_dump(mode="json", exclude_none=True)


def _loc_name(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part + 1}]"
        else:
            out += ("." if out else "") + part
    return out


def _model_at(loc: tuple[int | str, ...], root: type[BaseModel]) -> type[BaseModel] | None:
    """The pydantic model class that owns the last element of ``loc``."""
    model: type[BaseModel] = root
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        field = model.model_fields.get(part)
        if field is None:
            return None
        ann = field.annotation
        args = getattr(ann, "__args__", ())
        nxt = next((a for a in (ann, *args) if isinstance(a, type) and issubclass(a, BaseModel)),
                   None)
        if nxt is None:
            return None
        model = nxt
    return model


def pydantic_config_error(err: ValidationError, source: str, root: type[BaseModel]
                          ) -> ConfigError:
    """Turn the first problem of a pydantic ``ValidationError`` into a one-line ConfigError.

    The key is the dotted path (1-based list positions: ``keep_out[2].min_mm``); unknown keys
    list the keys allowed at that place.
    """
    e = err.errors(include_url=False)[0]
    loc = tuple(e.get("loc", ()))
    key = _loc_name(loc) or None
    if e["type"] == "extra_forbidden":
        owner = _model_at(loc, root)
        allowed = ", ".join(sorted(owner.model_fields)) if owner else "?"
        return ConfigError(f"unknown key (allowed here: {allowed})", source=source, key=key)
    if e["type"] == "missing":
        return ConfigError("required key is missing", source=source, key=key)
    msg = str(e.get("msg", "invalid value"))
    msg = msg.removeprefix("Value error, ")
    more = len(err.errors()) - 1
    if more:
        msg += f" (and {more} more problem{'s' if more > 1 else ''})"
    return ConfigError(msg, source=source, key=key)


def builtin_cells() -> list[str]:
    """Return the names of the cell descriptions shipped with robocal."""
    root = resources.files("robocal.data") / "cells"
    try:
        return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))
    except (FileNotFoundError, NotADirectoryError):  # pragma: no cover - broken install
        return []


def load_cell(spec: str | Path) -> Cell:
    """Load a cell by built-in name (see :func:`builtin_cells`) or from a TOML file path.

    Parameters
    ----------
    spec
        ``"demo"`` (or another built-in name) or a path to a ``.toml`` file.

    Returns
    -------
    Cell
        The validated description.

    Raises
    ------
    ConfigError
        When the name is unknown, the file is unreadable or not TOML, or a key is invalid or
        unknown (the message names the file and the key).
    """
    text = str(spec)
    if not text.endswith(".toml") and text in builtin_cells():
        res = resources.files("robocal.data") / "cells" / f"{text}.toml"
        return Cell.from_dict(read_toml(res), source=f"builtin:{text}")
    path = Path(text)
    if not path.is_file():
        raise ConfigError(
            f"no such file, and not a built-in cell (built-in: {', '.join(builtin_cells())})",
            source=text)
    return Cell.from_dict(read_toml(path), source=text)
