"""What changes between two compensation tables (for review before a push, and read-back)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from robocal.compensation._table import CompensationTable
from robocal.kinematics import wpr_to_matrix

_META = ("format", "kind", "model_id", "robot", "units", "valid_range_deg",
         "predicted_residual_mm")


@dataclass(frozen=True)
class TableDiff:
    """Differences from table ``a`` to table ``b``.

    ``max_joint_deg``: largest change of a joint command (``targets``: rows present in both)
    or of a correction (``joint``: entries compared on the union of their grids), deg.
    ``max_translation_mm``/``max_rotation_deg``: largest change of a frame (``frames``).
    ``rows_changed``: target indices whose status or command changed beyond the tolerance.
    ``lines``: human-readable summary, one difference per line.
    """

    same_kind: bool
    metadata: tuple[str, ...] = ()
    max_joint_deg: float = 0.0
    max_translation_mm: float = 0.0
    max_rotation_deg: float = 0.0
    rows_changed: tuple[int, ...] = ()
    lines: tuple[str, ...] = field(default=())

    @property
    def identical(self) -> bool:
        """True when no difference beyond the tolerances was found."""
        return not self.lines


def _frame_matrix(f: object) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = wpr_to_matrix(*(math.radians(getattr(f, k)) for k in "wpr"))
    T[:3, 3] = [getattr(f, k) for k in "xyz"]
    return T


def diff_tables(a: CompensationTable, b: CompensationTable, *, tol_deg: float = 1e-9,
                tol_mm: float = 1e-9) -> TableDiff:
    """Compare two tables by meaning (joint commands, corrections, frames), not bytes.

    Parameters
    ----------
    a, b
        The tables (e.g. the one on the controller and the one about to be pushed).
    tol_deg, tol_mm
        Changes at or below these are ignored.
    """
    lines: list[str] = []
    meta = tuple(k for k in _META if getattr(a, k) != getattr(b, k))
    for k in meta:
        lines.append(f"{k}: {getattr(a, k)!r} -> {getattr(b, k)!r}")
    if a.kind != b.kind:
        return TableDiff(same_kind=False, metadata=meta, lines=tuple(lines))
    max_q = max_t = max_r = 0.0
    rows: list[int] = []
    if a.kind == "targets":
        ra = {r.index: r for r in a.targets or []}
        rb = {r.index: r for r in b.targets or []}
        for i in sorted(set(ra) ^ set(rb)):
            rows.append(i)
            lines.append(f"target {i}: only in {'a' if i in ra else 'b'}")
        for i in sorted(set(ra) & set(rb)):
            x, y = ra[i], rb[i]
            if len(x.q_deg) != len(y.q_deg):
                rows.append(i)
                lines.append(f"target {i}: {len(x.q_deg)} joints -> {len(y.q_deg)}")
                continue
            d = float(np.max(np.abs(np.subtract(x.q_deg, y.q_deg)))) if x.q_deg else 0.0
            if x.status == "ok" and y.status == "ok":
                max_q = max(max_q, d)
            if x.status != y.status or d > tol_deg:
                rows.append(i)
                lines.append(f"target {i}: status {x.status} -> {y.status}, "
                             f"max |dq| {d:.6f} deg")
    elif a.kind == "joint":
        ea = {(e.joint, e.source): e for e in a.joints or []}
        eb = {(e.joint, e.source): e for e in b.joints or []}
        for key in sorted(set(ea) | set(eb)):
            ca, cb = ea.get(key), eb.get(key)
            grid = np.union1d(ca.q_deg if ca else [], cb.q_deg if cb else [])
            va = ca.evaluate(grid) if ca else np.zeros_like(grid)
            vb = cb.evaluate(grid) if cb else np.zeros_like(grid)
            d = float(np.max(np.abs(va - vb))) if grid.size else 0.0
            max_q = max(max_q, d)
            if ca is None or cb is None or d > tol_deg:
                what = "only in " + ("b" if ca is None else "a") if (ca is None or cb is None) \
                    else f"max change {d:.6f} deg"
                lines.append(f"joint {key[0]} (from joint {key[1]}): {what}")
    elif a.frames is not None and b.frames is not None:
        for name in ("base", "tool"):
            Ta = _frame_matrix(getattr(a.frames, name))
            Tb = _frame_matrix(getattr(b.frames, name))
            dt = float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]))
            c = (np.trace(Ta[:3, :3].T @ Tb[:3, :3]) - 1.0) * 0.5
            dr = math.degrees(math.acos(max(-1.0, min(1.0, c))))
            max_t, max_r = max(max_t, dt), max(max_r, dr)
            if dt > tol_mm or dr > tol_deg:
                lines.append(f"{name} frame: moves {dt:.6f} mm, turns {dr:.6f} deg")
    return TableDiff(same_kind=True, metadata=meta, max_joint_deg=max_q,
                     max_translation_mm=max_t, max_rotation_deg=max_r,
                     rows_changed=tuple(rows), lines=tuple(lines))
