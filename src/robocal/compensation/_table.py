"""Compensation tables: the versioned, checksummed artefact pushed to a controller or PLC.

A table carries one payload kind:

``targets``
    corrected joint targets for a list of program targets (a "filtered program");
``joint``
    per-joint correction tables ``dq_i(q_i)`` on a grid over each joint's range, to be applied
    by the controller as an encoder-side offset (linear interpolation between grid points,
    held constant beyond the ends). An entry with ``source_joint`` set adds a correction to
    ``joint`` that is tabulated over another joint's value: robots whose chain angle couples
    two joint values (FANUC J2/J3) need it. The command for program joints ``q`` is
    ``q + joint_offsets_deg(q)``;
``frames``
    updated user (base) and tool frames, ``x, y, z`` in mm and ``w, p, r`` in degrees
    (FANUC convention: fixed-axis XYZ rotations, ``R = Rz(r) Ry(p) Rx(w)``). ``base`` is the
    tracker (cell) frame expressed in the robot base frame, ``T_base_tracker``: what a
    controller's user frame holds so that targets given in tracker coordinates are reached;
    ``tool`` is the TCP (reflector) in the flange frame.

Everything in a table is in mm and degrees. The ``checksum`` is the SHA-256 of the canonical
JSON of every other field, so a controller-side copy can be verified byte for byte.
See ``docs/compensation-tables.md``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Final, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from robocal._core.files import atomic_write_text
from robocal.errors import CompensationError, ConfigError

TABLE_FORMAT: Final = "robocal.compensation/1"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# Physical bounds of a table's numbers (a loaded table is refused beyond them): joint
# values within ten turns, corrections within one, frames within 100 m of the tracker.
JointDeg = Annotated[float, Field(ge=-3600.0, le=3600.0)]
CorrectionDeg = Annotated[float, Field(ge=-360.0, le=360.0)]
FrameMm = Annotated[float, Field(ge=-1e5, le=1e5)]
FrameDeg = Annotated[float, Field(ge=-360.0, le=360.0)]


class TargetRow(_Model):
    """One corrected program target: command ``q_deg`` reaches the target under the model."""

    index: int = Field(ge=0)
    q_deg: list[JointDeg]
    status: Literal["ok", "not-converged", "out-of-limits", "unreachable"]
    model_residual_mm: float = Field(ge=0.0, le=1e5)


class JointCorrection(_Model):
    """Correction ``dq_deg`` (add to joint ``joint``'s command) sampled at ``q_deg``.

    ``q_deg`` is a strictly increasing grid of program values of ``source_joint`` (default:
    ``joint`` itself); between grid points the correction is interpolated linearly, beyond
    the ends it is held. ``interpolation_error_bound_deg`` bounds the difference between that
    interpolation and the model's correction.
    """

    joint: int = Field(ge=1)
    q_deg: list[JointDeg]
    dq_deg: list[CorrectionDeg]
    interpolation_error_bound_deg: float = Field(ge=0.0)
    source_joint: int | None = Field(default=None, ge=1)

    @model_validator(mode="after")
    def _grid(self) -> JointCorrection:
        if len(self.q_deg) != len(self.dq_deg):
            raise ValueError(f"q_deg has {len(self.q_deg)} points, dq_deg {len(self.dq_deg)}")
        if len(self.q_deg) < 2:
            raise ValueError("a correction grid needs at least 2 points")
        if any(b <= a for a, b in zip(self.q_deg, self.q_deg[1:], strict=False)):
            raise ValueError("q_deg must be strictly increasing")
        return self

    @property
    def source(self) -> int:
        """1-based joint whose value indexes the grid."""
        return self.source_joint or self.joint

    def evaluate(self, q_deg: NDArray[np.float64]) -> NDArray[np.float64]:
        """Interpolated correction (deg) at source-joint values ``q_deg`` (any shape, deg)."""
        return np.interp(np.asarray(q_deg, dtype=float), self.q_deg, self.dq_deg)


class Frame(_Model):
    """A frame as ``x, y, z`` (mm) and ``w, p, r`` (deg), R = Rz(r) Ry(p) Rx(w)."""

    x: FrameMm
    y: FrameMm
    z: FrameMm
    w: FrameDeg
    p: FrameDeg
    r: FrameDeg


class FramesPayload(_Model):
    """Updated user frame and tool frame.

    ``base``: the tracker (cell) frame in the robot base frame, ``T_base_tracker`` (what a
    controller's user frame holds; invert it for the robot base in tracker coordinates).
    ``tool``: the TCP (reflector) in the flange frame.
    """

    base: Frame
    tool: Frame


class CompensationTable(_Model):
    """A compensation table as written to (and read back from) a controller."""

    format: Literal["robocal.compensation/1"] = TABLE_FORMAT
    kind: Literal["targets", "joint", "frames"]
    model_id: str
    robot: str
    units: dict[str, str] = Field(default_factory=lambda: {"length": "mm", "angle": "deg"})
    valid_range_deg: list[tuple[JointDeg, JointDeg]]
    predicted_residual_mm: float = Field(ge=0.0)
    created: str = ""
    targets: list[TargetRow] | None = None
    joints: list[JointCorrection] | None = None
    frames: FramesPayload | None = None
    stats: dict[str, float] = Field(default_factory=dict)
    checksum: str = ""

    @model_validator(mode="after")
    def _payload(self) -> CompensationTable:
        payloads = {"targets": self.targets, "joints": self.joints, "frames": self.frames}
        want = "joints" if self.kind == "joint" else self.kind
        if payloads[want] is None:
            raise ValueError(f"a {self.kind!r} table needs the {want!r} payload")
        extra = [k for k, v in payloads.items() if k != want and v is not None]
        if extra:
            raise ValueError(f"a {self.kind!r} table carries only {want!r}, not {extra[0]!r}")
        for lo, hi in self.valid_range_deg:
            if lo > hi:
                raise ValueError(f"valid range ({lo}, {hi}) is empty")
        if self.targets:
            dofs = {len(r.q_deg) for r in self.targets}
            if len(dofs) > 1:
                raise ValueError("target rows have different joint counts")
        return self

    @property
    def dof(self) -> int:
        """Number of joints the table is for (from the valid range, else the payload)."""
        if self.valid_range_deg:
            return len(self.valid_range_deg)
        if self.targets:
            return len(self.targets[0].q_deg)
        if self.joints:
            return max(max(j.joint, j.source) for j in self.joints)
        return 0

    def joint_offsets_deg(self, q_deg: NDArray[np.float64]) -> NDArray[np.float64]:
        """Corrections (deg) to add to program joints ``q_deg`` ((dof,) or (n, dof), deg).

        Only for ``joint`` tables: the sum, per joint, of every entry's interpolated value.
        """
        if self.kind != "joint" or self.joints is None:
            raise CompensationError(f"a {self.kind!r} table holds no joint corrections")
        q = np.asarray(q_deg, dtype=float)
        single = q.ndim == 1
        q2 = np.atleast_2d(q)
        out = np.zeros_like(q2)
        for e in self.joints:
            if max(e.joint, e.source) > q2.shape[1]:
                raise CompensationError(
                    f"table entry for joint {e.joint} (source {e.source}) needs "
                    f"{max(e.joint, e.source)} joints, got {q2.shape[1]}")
            out[:, e.joint - 1] += e.evaluate(q2[:, e.source - 1])
        return out[0] if single else out

    def payload_dict(self) -> dict[str, Any]:
        """Return every field but the checksum, as plain JSON types."""
        d = self.model_dump(mode="json")
        d.pop("checksum", None)
        return d

    def compute_checksum(self) -> str:
        """Return the SHA-256 hex digest of the canonical JSON of the payload."""
        blob = json.dumps(self.payload_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(blob.encode()).hexdigest()

    def sealed(self) -> CompensationTable:
        """Return a copy with the checksum filled in."""
        return self.model_copy(update={"checksum": self.compute_checksum()})

    def with_temperatures(self, temps_c: Sequence[float]) -> CompensationTable:
        """A copy that records the joint temperatures (°C) it compensates for in its stats
        (``temp1_c``..), sealed again when this one was sealed."""
        stats = {**self.stats, **{f"temp{j + 1}_c": float(t) for j, t in enumerate(temps_c)}}
        out = self.model_copy(update={"stats": stats, "checksum": ""})
        return out.sealed() if self.checksum else out

    @property
    def temperatures_c(self) -> list[float]:
        """The joint temperatures (°C) the table compensates for (see
        :meth:`with_temperatures`); empty when it does not say."""
        out: list[float] = []
        while f"temp{len(out) + 1}_c" in self.stats:
            out.append(self.stats[f"temp{len(out) + 1}_c"])
        return out

    def verify(self) -> None:
        """Raise :class:`CompensationError` unless the checksum matches the content."""
        if not self.checksum:
            raise CompensationError("compensation table has no checksum")
        actual = self.compute_checksum()
        if actual != self.checksum:
            raise CompensationError(
                f"compensation table checksum mismatch: stored {self.checksum[:12]}..., "
                f"content gives {actual[:12]}..."
            )

    def to_json(self) -> str:
        """Serialise, sealing the table if it has no checksum yet."""
        table = self if self.checksum else self.sealed()
        return table.model_dump_json(indent=2)

    def write(self, path: str | Path) -> None:
        """Write atomically to ``path`` (temporary file then rename; nothing left on error)."""
        atomic_write_text(path, self.to_json())

    @classmethod
    def read(cls, path: str | Path) -> CompensationTable:
        """Read and verify a table file; raise :class:`ConfigError` naming the problem."""
        path = Path(path)
        try:
            table = cls.model_validate_json(path.read_text())
        except FileNotFoundError as err:
            raise ConfigError("file not found", source=str(path)) from err
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"cannot read: {err}", source=str(path)) from err
        except ValidationError as err:
            first = err.errors()[0]
            key = ".".join(str(p) for p in first["loc"])
            raise ConfigError(first["msg"], source=str(path), key=key) from err
        try:
            table.verify()
        except CompensationError as err:
            raise ConfigError(str(err), source=str(path)) from err
        return table
