"""Compensation tables: the versioned, checksummed artefact pushed to a controller or PLC.

A table carries one payload kind:

``targets``
    corrected joint targets for a list of program targets (a "filtered program");
``joint``
    per-joint correction tables ``dq_i(q_i)`` on a grid over each joint's range, to be applied
    by the controller as an encoder-side offset (linear interpolation between grid points);
``frames``
    updated base (user frame) and tool frames, ``x, y, z`` in mm and ``w, p, r`` in degrees
    (FANUC convention: fixed-axis XYZ rotations, ``R = Rz(r) Ry(p) Rx(w)``).

Everything in a table is in mm and degrees. The ``checksum`` is the SHA-256 of the canonical
JSON of every other field, so a controller-side copy can be verified byte for byte.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from robocal.errors import CompensationError, ConfigError

TABLE_FORMAT = "robocal.compensation/1"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TargetRow(_Model):
    """One corrected program target: command ``q_deg`` reaches the target under the model."""

    index: int
    q_deg: list[float]
    status: Literal["ok", "not-converged", "out-of-limits", "unreachable"]
    model_residual_mm: float


class JointCorrection(_Model):
    """Correction ``dq_deg`` (add to the commanded angle) sampled at ``q_deg`` for one joint."""

    joint: int = Field(ge=1)
    q_deg: list[float]
    dq_deg: list[float]
    interpolation_error_bound_deg: float = Field(ge=0.0)


class Frame(_Model):
    """A frame as ``x, y, z`` (mm) and ``w, p, r`` (deg), R = Rz(r) Ry(p) Rx(w)."""

    x: float
    y: float
    z: float
    w: float
    p: float
    r: float


class FramesPayload(_Model):
    """Updated base (user frame, tracker <- base) and tool (flange -> reflector/TCP) frames."""

    base: Frame
    tool: Frame


class CompensationTable(_Model):
    """A compensation table as written to (and read back from) a controller."""

    format: Literal["robocal.compensation/1"] = TABLE_FORMAT
    kind: Literal["targets", "joint", "frames"]
    model_id: str
    robot: str
    units: dict[str, str] = Field(default_factory=lambda: {"length": "mm", "angle": "deg"})
    valid_range_deg: list[tuple[float, float]]
    predicted_residual_mm: float = Field(ge=0.0)
    created: str = ""
    targets: list[TargetRow] | None = None
    joints: list[JointCorrection] | None = None
    frames: FramesPayload | None = None
    checksum: str = ""

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
        """Write atomically to ``path`` (temporary file then rename)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(self.to_json())
        tmp.replace(path)

    @classmethod
    def read(cls, path: str | Path) -> CompensationTable:
        """Read and verify a table file; raise :class:`ConfigError` naming the problem."""
        path = Path(path)
        try:
            table = cls.model_validate_json(path.read_text())
        except FileNotFoundError as err:
            raise ConfigError("file not found", source=str(path)) from err
        except ValidationError as err:
            first = err.errors()[0]
            key = ".".join(str(p) for p in first["loc"])
            raise ConfigError(first["msg"], source=str(path), key=key) from err
        try:
            table.verify()
        except CompensationError as err:
            raise ConfigError(str(err), source=str(path)) from err
        return table
