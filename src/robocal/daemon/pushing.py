"""Compensation tables from an approved fit: building, safety bounds, push and rollback.

A push writes the table through the robot driver's ``CompensationSink``, reads it back,
compares content and checksum, and activates it when the driver can; the table before the
first push is read from the controller and kept as the baseline. Tables beyond the configured
bounds (joint correction, frame change) are refused before anything is written.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal.compensation import CompensationTable, Frame, build_table
from robocal.daemon.config import LimitsConfig
from robocal.drivers import CompensationSink
from robocal.errors import CompensationError, VerificationMismatch
from robocal.kinematics import CalibratedModel, ErrorModelSpec, RobotDescription, wpr_to_matrix

__all__ = [
    "build_campaign_table",
    "check_bounds",
    "ideal_positions",
    "write_and_verify",
]

Array = NDArray[np.float64]


def ideal_positions(cal: CalibratedModel, q: Array) -> Array:
    """Reflector positions (n, 3) m of the *error-free* robot with the calibrated base and tool.

    These are the Cartesian targets a program taught with joint values ``q`` (n, dof) rad
    means; compensation finds the joints that reach them on the real (modelled) robot.
    """
    nominal = cal.model.with_spec(ErrorModelSpec(cal.robot.dof, ()))
    x = cal.model.transfer(cal.params, nominal)
    return nominal.positions(np.atleast_2d(np.asarray(q, dtype=float)), x)


def build_campaign_table(cal: CalibratedModel, kind: str, *,
                         targets_q: Array | None = None) -> CompensationTable:
    """Build a sealed table of ``kind`` from ``cal`` (:func:`robocal.compensation.build_table`).

    ``targets`` tables correct the program targets ``targets_q`` (n, dof) rad, i.e. the
    positions the error-free robot would reach there (:func:`ideal_positions`).

    Raises
    ------
    CompensationError
        If a ``targets`` table is asked for without targets.
    """
    if kind == "targets":
        if targets_q is None:
            raise CompensationError("a targets table needs program targets")
        q = np.atleast_2d(np.asarray(targets_q, dtype=float))
        table = build_table(cal, "targets", targets_p=ideal_positions(cal, q), seeds_q=q)
    elif kind in ("frames", "joint"):
        table = build_table(cal, kind)  # type: ignore[arg-type]
    else:
        raise CompensationError(f"unknown compensation table kind {kind!r}")
    return table if table.checksum else table.sealed()


def _frame_change(a: Frame, b: Frame) -> tuple[float, float]:
    """Translation (mm) and rotation angle (deg) between two frames."""
    dt = math.dist((a.x, a.y, a.z), (b.x, b.y, b.z))
    Ra = wpr_to_matrix(math.radians(a.w), math.radians(a.p), math.radians(a.r))
    Rb = wpr_to_matrix(math.radians(b.w), math.radians(b.p), math.radians(b.r))
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return dt, math.degrees(math.acos(max(-1.0, min(1.0, float(c)))))


def check_bounds(table: CompensationTable, limits: LimitsConfig, robot: RobotDescription, *,
                 seeds_q_deg: Sequence[Sequence[float]] | None = None,
                 previous: CompensationTable | None = None) -> None:
    """Refuse a table whose corrections exceed the configured bounds.

    ``joint`` tables: every ``dq_deg``; ``targets``: every row's change from its seed
    (``seeds_q_deg``), and no row may be anything but ``ok``; ``frames``: the tool against the
    robot description's tool offset, the base against the previous frames table, if any.

    Raises
    ------
    CompensationError
        Naming the first violation (nothing has been written).
    """
    max_dq = limits.max_joint_correction_deg
    max_t, max_r = limits.max_frame_translation_mm, limits.max_frame_rotation_deg
    problems: list[str] = []
    if table.kind == "joint":
        for jc in table.joints or []:
            worst = max((abs(v) for v in jc.dq_deg), default=0.0)
            if not math.isfinite(worst) or worst > max_dq:
                problems.append(f"J{jc.joint} correction {worst:.4f} deg > {max_dq} deg")
    elif table.kind == "targets":
        for row in table.targets or []:
            if row.status != "ok":
                problems.append(f"target {row.index}: {row.status}")
                continue
            if seeds_q_deg is not None and row.index < len(seeds_q_deg):
                seed = seeds_q_deg[row.index]
                worst = max(abs(a - b) for a, b in zip(row.q_deg, seed, strict=True))
                if not math.isfinite(worst) or worst > max_dq:
                    problems.append(f"target {row.index}: correction {worst:.4f} deg > "
                                    f"{max_dq} deg")
            lim = robot.joint_limits
            for j, v in enumerate(row.q_deg):
                if not math.radians(v) >= lim[j, 0] or not math.radians(v) <= lim[j, 1]:
                    problems.append(f"target {row.index}: J{j + 1} {v:.3f} deg outside limits")
    elif table.kind == "frames":
        if table.frames is None:
            problems.append("frames table without frames")
        else:
            t = robot.tool
            nominal_tool = Frame(x=t[0] * 1e3, y=t[1] * 1e3, z=t[2] * 1e3, w=0.0, p=0.0, r=0.0)
            dt, dr = _frame_change(nominal_tool, table.frames.tool)
            if dt > max_t or dr > max_r:
                problems.append(f"tool frame changes by {dt:.3f} mm / {dr:.4f} deg "
                                f"(limits {max_t} mm / {max_r} deg)")
            if previous is not None and previous.kind == "frames" and previous.frames:
                dt, dr = _frame_change(previous.frames.base, table.frames.base)
                if dt > max_t or dr > max_r:
                    problems.append(f"base frame changes by {dt:.3f} mm / {dr:.4f} deg "
                                    f"(limits {max_t} mm / {max_r} deg)")
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise CompensationError(f"compensation refused: {problems[0]}{more}")


def _differences(path: str, a: Any, b: Any, *, tol: float) -> list[str]:
    """Readable differences between two JSON values; numbers agree within ``tol``."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{path}.{k}: present on one side only")
            else:
                out += _differences(f"{path}.{k}", a[k], b[k], tol=tol)
        return out
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} written, {len(b)} read back"]
        out = []
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            out += _differences(f"{path}[{i}]", x, y, tol=tol)
        return out
    if (isinstance(a, int | float) and isinstance(b, int | float)
            and not isinstance(a, bool) and not isinstance(b, bool)):
        ok = math.isfinite(float(a)) and abs(float(a) - float(b)) <= tol
        return [] if ok else [f"{path}: {a!r} written, {b!r} read back"]
    return [] if a == b else [f"{path}: {a!r} written, {b!r} read back"]


async def write_and_verify(robot: object, table: CompensationTable) -> CompensationTable:
    """Write ``table``, read it back, compare content and checksum, activate; return read-back.

    Raises
    ------
    CompensationError
        If the driver cannot store compensation tables.
    VerificationMismatch
        If what the controller holds differs from what was written.
    """
    if not isinstance(robot, CompensationSink):
        raise CompensationError(f"{type(robot).__name__} cannot store compensation tables")
    sealed = table if table.checksum else table.sealed()
    await robot.write_compensation(sealed)  # drivers verify too; we check independently
    back = await robot.read_compensation()
    if back is None:
        raise VerificationMismatch("the controller holds no table after writing")
    details = _differences("table", sealed.payload_dict(), back.payload_dict(), tol=1e-3)
    if details:
        raise VerificationMismatch(f"read-back differs: {details[0]}", diff=details)
    if back.compute_checksum() != back.checksum and back.checksum:
        raise VerificationMismatch("read-back table fails its own checksum")
    activate = getattr(robot, "activate_compensation", None)
    if callable(activate):
        await activate(sealed)
    return back
