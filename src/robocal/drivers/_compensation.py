"""Comparison of compensation tables for write-then-read-back verification, and snapshots of
what a controller held before robocal wrote to it."""

from __future__ import annotations

import hashlib
import json
import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from robocal.compensation import CompensationTable

__all__ = ["ControllerSnapshot", "snapshot_diff", "table_diff"]


def _walk(path: str, a: Any, b: Any, tol: float, out: list[str]) -> None:
    if len(out) >= 20:
        return
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                out.append(f"{path}.{key}: present on one side only")
            else:
                _walk(f"{path}.{key}", a[key], b[key], tol, out)
    elif isinstance(a, list | tuple) and isinstance(b, list | tuple):
        if len(a) != len(b):
            out.append(f"{path}: length {len(a)} written, {len(b)} read back")
            return
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _walk(f"{path}[{i}]", x, y, tol, out)
    elif (
        isinstance(a, int | float)
        and isinstance(b, int | float)
        and not isinstance(a, bool)
        and not isinstance(b, bool)
    ):
        if not math.isclose(float(a), float(b), rel_tol=0.0, abs_tol=tol):
            out.append(f"{path}: {a!r} written, {b!r} read back")
    elif a != b:
        out.append(f"{path}: {a!r} written, {b!r} read back")


def table_diff(
    written: CompensationTable,
    read: CompensationTable | None,
    *,
    tol: float = 0.0,
    ignore: frozenset[str] = frozenset({"checksum"}),
) -> list[str]:
    """Return readable differences between two tables (empty when they agree).

    Numbers (mm, degrees) agree within ``tol``; every other field must be equal. Top-level
    fields in ``ignore`` are skipped (the checksum by default, which is compared separately).
    """
    if read is None:
        return ["nothing read back"]
    a = {k: v for k, v in written.model_dump(mode="json").items() if k not in ignore}
    b = {k: v for k, v in read.model_dump(mode="json").items() if k not in ignore}
    out: list[str] = []
    _walk("table", a, b, tol, out)
    return out


class ControllerSnapshot(BaseModel):
    """What a controller held in the places a compensation table is written to, verbatim.

    Read *before* robocal first writes there, so a rollback can put the controller's own
    values back even though they were never a robocal table (FANUC user/tool frames and
    position registers, the PLC's table registers). ``items`` maps a driver-specific slot
    name (``"uframe:1"``, ``"pr:7"``, ``"hr:100"``) to the values read there; ``covers``
    is the table kind whose slots were read.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    format: Literal["robocal.controller-snapshot/1"] = "robocal.controller-snapshot/1"
    driver: str
    covers: Literal["targets", "joint", "frames"]
    items: dict[str, Any] = Field(default_factory=dict)

    def checksum(self) -> str:
        """SHA-256 of the canonical JSON (identifies the snapshot in the audit log)."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(blob.encode()).hexdigest()


def snapshot_diff(expected: ControllerSnapshot, read: ControllerSnapshot, *,
                  tol: float = 1e-3) -> list[str]:
    """Readable differences between two snapshots of the same slots (empty when equal)."""
    out: list[str] = []
    _walk("snapshot", expected.items, read.items, tol, out)
    return out
