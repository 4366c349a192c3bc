"""What changes between two compensation tables (for review before a push, and read-back)."""

from __future__ import annotations

import math
from collections.abc import Callable
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


@dataclass
class _Changes:
    """What one kind's comparison found (the kind-specific part of a :class:`TableDiff`)."""

    lines: list[str] = field(default_factory=list)
    rows: list[int] = field(default_factory=list)
    max_q: float = 0.0
    max_t: float = 0.0
    max_r: float = 0.0


def _targets(a: CompensationTable, b: CompensationTable, tol_deg: float, tol_mm: float
             ) -> _Changes:
    """Rows only in one table, joint counts, statuses and commands that changed."""
    out = _Changes()
    ra = {r.index: r for r in a.targets or []}
    rb = {r.index: r for r in b.targets or []}
    for i in sorted(set(ra) ^ set(rb)):
        out.rows.append(i)
        out.lines.append(f"target {i}: only in {'a' if i in ra else 'b'}")
    for i in sorted(set(ra) & set(rb)):
        x, y = ra[i], rb[i]
        if len(x.q_deg) != len(y.q_deg):
            out.rows.append(i)
            out.lines.append(f"target {i}: {len(x.q_deg)} joints -> {len(y.q_deg)}")
            continue
        d = float(np.max(np.abs(np.subtract(x.q_deg, y.q_deg)))) if x.q_deg else 0.0
        if x.status == "ok" and y.status == "ok":
            out.max_q = max(out.max_q, d)
        if x.status != y.status or d > tol_deg:
            out.rows.append(i)
            out.lines.append(f"target {i}: status {x.status} -> {y.status}, "
                             f"max |dq| {d:.6f} deg")
    return out


def _joint(a: CompensationTable, b: CompensationTable, tol_deg: float, tol_mm: float
           ) -> _Changes:
    """Corrections compared on the union of their grids; entries only in one table."""
    out = _Changes()
    ea = {(e.joint, e.source): e for e in a.joints or []}
    eb = {(e.joint, e.source): e for e in b.joints or []}
    for key in sorted(set(ea) | set(eb)):
        ca, cb = ea.get(key), eb.get(key)
        grid = np.union1d(ca.q_deg if ca else [], cb.q_deg if cb else [])
        va = ca.evaluate(grid) if ca else np.zeros_like(grid)
        vb = cb.evaluate(grid) if cb else np.zeros_like(grid)
        d = float(np.max(np.abs(va - vb))) if grid.size else 0.0
        out.max_q = max(out.max_q, d)
        if ca is None or cb is None or d > tol_deg:
            what = "only in " + ("b" if ca is None else "a") if (ca is None or cb is None) \
                else f"max change {d:.6f} deg"
            out.lines.append(f"joint {key[0]} (from joint {key[1]}): {what}")
    return out


def _frames(a: CompensationTable, b: CompensationTable, tol_deg: float, tol_mm: float
            ) -> _Changes:
    """How far the base and tool frames move and turn."""
    out = _Changes()
    if a.frames is None or b.frames is None:
        return out
    for name in ("base", "tool"):
        Ta = _frame_matrix(getattr(a.frames, name))
        Tb = _frame_matrix(getattr(b.frames, name))
        dt = float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]))
        R = Ta[:3, :3].T @ Tb[:3, :3]
        # angle of R from its sine and cosine: acos of the cosine alone loses small angles to
        # rounding (a frame against itself turned by 1e-6 deg)
        s = 0.5 * math.hypot(R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1])
        dr = math.degrees(math.atan2(s, (np.trace(R) - 1.0) * 0.5))
        out.max_t, out.max_r = max(out.max_t, dt), max(out.max_r, dr)
        if dt > tol_mm or dr > tol_deg:
            out.lines.append(f"{name} frame: moves {dt:.6f} mm, turns {dr:.6f} deg")
    return out


#: the comparison of each table kind (a kind not listed compares its frames, if any)
_BY_KIND: dict[str, Callable[[CompensationTable, CompensationTable, float, float],
                             _Changes]] = {"targets": _targets, "joint": _joint}


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
    meta = tuple(k for k in _META if getattr(a, k) != getattr(b, k))
    lines = [f"{k}: {getattr(a, k)!r} -> {getattr(b, k)!r}" for k in meta]
    if a.kind != b.kind:
        return TableDiff(same_kind=False, metadata=meta, lines=tuple(lines))
    c = _BY_KIND.get(a.kind, _frames)(a, b, tol_deg, tol_mm)
    return TableDiff(same_kind=True, metadata=meta, max_joint_deg=c.max_q,
                     max_translation_mm=c.max_t, max_rotation_deg=c.max_r,
                     rows_changed=tuple(c.rows), lines=tuple(lines + c.lines))
