"""Compensation tables from an approved fit: building, safety bounds, push and rollback.

A push writes the table through the robot driver's ``CompensationSink``, reads it back and
compares content and checksum. Before robocal first writes a kind of table, the controller's
own values in those slots are read (:func:`snapshot`, a driver's ``CompensationSnapshots``)
and journaled, so a rollback restores them. Tables beyond the configured
bounds (joint correction, frame change) are refused before anything is written, and so are
tables whose predicted residual is not clearly below the nominal one
(:func:`robocal.compensation.improvement_refusal`) unless forced.

``ROBOCAL_FAULT_POINT`` (comma-separated names) makes the daemon ``os._exit`` at those
journaled points (:func:`fault_point`); the crash tests use it, nothing else should.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from robocal._core.joint_ranges import targets_outside
from robocal._core.measurements import read_joints_csv
from robocal.compensation import CompensationTable, Frame, build_table, read_targets_csv
from robocal.compensation import ideal_positions as _ideal_positions
from robocal.daemon.config import LimitsConfig
from robocal.drivers import (
    CompensationSink,
    CompensationSlots,
    CompensationSnapshots,
    ControllerSnapshot,
    RobotDriver,
    snapshot_diff,
    table_diff,
)
from robocal.errors import CompensationError, VerificationMismatch
from robocal.kinematics import CalibratedModel, RobotDescription, wpr_to_matrix

__all__ = [
    "FAULT_POINTS",
    "Baseline",
    "Capabilities",
    "Entry",
    "build_campaign_table",
    "capabilities",
    "check_bounds",
    "commanded_joints",
    "coverage_refusal",
    "fault_point",
    "ideal_positions",
    "outside_coverage",
    "read_like",
    "restore",
    "snapshot",
    "verification_errors",
    "verification_indices",
    "write_and_verify",
]

#: Journaled points where ``ROBOCAL_FAULT_POINT`` can kill the daemon (crash tests).
FAULT_POINTS = (
    "approve:before-commit", "approve:after-commit",
    "push:after-snapshot", "push:after-intent", "push:after-write", "push:after-complete",
    "rollback:after-intent", "rollback:after-write", "rollback:after-complete",
)


def fault_point(name: str) -> None:
    """Exit the process at once (like kill -9) if ``ROBOCAL_FAULT_POINT`` names ``name``."""
    wanted = os.environ.get("ROBOCAL_FAULT_POINT", "")
    if wanted and name in {w.strip() for w in wanted.split(",")}:
        os._exit(86)

Array = NDArray[np.float64]


def ideal_positions(cal: CalibratedModel, q: Array) -> Array:
    """Reflector positions (n, 3) m the error-free robot reaches at ``q`` (n, dof) rad
    (:func:`robocal.compensation.ideal_positions`)."""
    return _ideal_positions(cal, q)


@dataclass(frozen=True)
class Program:
    """Production targets: joints ``q`` (n, dof) rad as taught (the seeds), and for a
    TARGETS.csv the positions ``p`` (n, 3) m in the tracker frame and optional flange
    orientations ``R`` (n, 3, 3)."""

    q: Array
    p: Array | None = None
    R: Array | None = None


def read_program(path: str | Path, *, dof: int) -> Program:
    """A JOINTS-style CSV (``q1..qN`` deg: the targets are where the error-free robot goes
    there) or a TARGETS.csv (``x, y, z`` mm tracker frame, seeds ``q1..qN``, optional
    ``w, p, r``); raise :class:`robocal.errors.DataError` naming file, column and row."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        head = fh.readline().lower().replace(";", ",").replace("\t", ",")
    cols = {c.strip() for c in head.split(",")}
    if {"x", "y", "z"} <= cols:
        t = read_targets_csv(path, dof=dof)
        return Program(q=t.q_seed, p=t.p, R=t.R)
    return Program(q=read_joints_csv(path, dof=dof))


def build_campaign_table(cal: CalibratedModel, kind: str, *,
                         targets_q: Array | None = None, targets_p: Array | None = None,
                         targets_R: Array | None = None,
                         max_change_deg: float | None = None) -> CompensationTable:
    """Build a sealed table of ``kind`` from ``cal`` (:func:`robocal.compensation.build_table`).

    ``targets`` tables correct the program targets ``targets_q`` (n, dof) rad, i.e. the
    positions the error-free robot would reach there (:func:`ideal_positions`), or the
    positions ``targets_p`` (n, 3) m (orientations ``targets_R``) seeded there; a target
    whose 6-D correction exceeds ``max_change_deg`` (near the wrist singularity) is solved
    for position alone (:func:`robocal.compensation.compensate`).

    Raises
    ------
    CompensationError
        If a ``targets`` table is asked for without targets.
    """
    if kind == "targets":
        if targets_q is None:
            raise CompensationError("a targets table needs program targets")
        q = np.atleast_2d(np.asarray(targets_q, dtype=float))
        # the program joints are the right branch and within a fraction of a degree of the
        # answer: start there, never from a closed-form IK that may pick another branch
        p = ideal_positions(cal, q) if targets_p is None else np.atleast_2d(targets_p)
        table = build_table(cal, "targets", targets_p=p, seeds_q=q, R_targets=targets_R,
                            start="seed" if targets_p is None else "auto",
                            max_change_deg=max_change_deg)
    elif kind in ("frames", "joint"):
        table = build_table(cal, kind)  # type: ignore[arg-type]
    else:
        raise CompensationError(f"unknown compensation table kind {kind!r}")
    return table if table.checksum else table.sealed()


def outside_coverage(cal: CalibratedModel, q_program: Array, kind: str) -> dict[str, object]:
    """Which program targets (n, dof) rad lie outside the model's calibrated joint coverage.

    Returns ``{"targets", "outside", "share", "names"}``: the number of targets, how many lie
    outside, their share, and up to ten of them named (``"target 12: J6 250.0 deg outside
    [-180.0, 180.0]"``, first joint out). ``frames`` tables do not use the model at the
    targets: nothing is counted then; nor for models without a coverage record.
    """
    q = np.atleast_2d(np.asarray(q_program, dtype=float))
    n = len(q)
    if kind == "frames" or cal.coverage is None or n == 0:
        return {"targets": n, "outside": 0, "share": 0.0, "names": []}
    out, names = targets_outside(np.asarray(cal.coverage), q)
    return {"targets": n, "outside": int(out.sum()), "share": round(float(out.sum()) / n, 4),
            "names": names}


def coverage_refusal(coverage: dict[str, object], max_share: float) -> str | None:
    """Why a push is refused for targets outside calibrated coverage (from
    :func:`outside_coverage`), or None when at most ``max_share`` (0..1) of them lie outside."""
    share = float(coverage["share"])  # type: ignore[arg-type]
    if share <= max_share:
        return None
    names = coverage["names"]
    assert isinstance(names, list)
    more = int(coverage["outside"]) - len(names)  # type: ignore[call-overload]
    return (f"{coverage['outside']} of {coverage['targets']} targets ({share:.0%}) lie outside "
            f"the calibrated joint coverage (at most {max_share:.0%} allowed): "
            + "; ".join(names) + (f"; and {more} more" if more > 0 else "")
            + " (plan with 'robocal plan --targets' to cover the program)")


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
    robot description's tool offset, the base against the previous frames table, if any, and
    always within ``max_base_distance_mm`` of the tracker (so a first push is bounded too).

    Raises
    ------
    CompensationError
        Naming the first violation (nothing has been written).
    """
    if table.kind == "joint":
        problems = _joint_problems(table, limits)
    elif table.kind == "targets":
        problems = _target_problems(table, limits, robot, seeds_q_deg)
    elif table.kind == "frames":
        problems = _frame_problems(table, limits, robot, previous)
    else:
        problems = []
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise CompensationError(f"compensation refused: {problems[0]}{more}")


def _joint_problems(table: CompensationTable, limits: LimitsConfig) -> list[str]:
    """Joint corrections beyond ``max_joint_correction_deg``."""
    max_dq = limits.max_joint_correction_deg
    problems: list[str] = []
    for jc in table.joints or []:
        worst = max((abs(v) for v in jc.dq_deg), default=0.0)
        if not math.isfinite(worst) or worst > max_dq:
            problems.append(f"J{jc.joint} correction {worst:.4f} deg > {max_dq} deg")
    return problems


def _target_problems(table: CompensationTable, limits: LimitsConfig, robot: RobotDescription,
                     seeds_q_deg: Sequence[Sequence[float]] | None) -> list[str]:
    """Target rows not ``ok``, changed too far from their seeds, or outside joint limits."""
    max_dq = limits.max_joint_correction_deg
    problems: list[str] = []
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
    return problems


def _frame_problems(table: CompensationTable, limits: LimitsConfig, robot: RobotDescription,
                    previous: CompensationTable | None) -> list[str]:
    """Tool and base frames changed beyond the bounds, or a base too far from the tracker."""
    if table.frames is None:
        return ["frames table without frames"]
    max_t, max_r = limits.max_frame_translation_mm, limits.max_frame_rotation_deg
    problems: list[str] = []
    t = robot.tool
    nominal_tool = Frame(x=t[0] * 1e3, y=t[1] * 1e3, z=t[2] * 1e3, w=0.0, p=0.0, r=0.0)
    dt, dr = _frame_change(nominal_tool, table.frames.tool)
    if dt > max_t or dr > max_r:
        problems.append(f"tool frame changes by {dt:.3f} mm / {dr:.4f} deg "
                        f"(limits {max_t} mm / {max_r} deg)")
    b = table.frames.base
    reach = math.sqrt(b.x * b.x + b.y * b.y + b.z * b.z)
    if not reach <= limits.max_base_distance_mm:
        problems.append(f"base frame {reach:.1f} mm from the tracker (limit "
                        f"{limits.max_base_distance_mm} mm)")
    if previous is not None and previous.kind == "frames" and previous.frames:
        dt, dr = _frame_change(previous.frames.base, table.frames.base)
        if dt > max_t or dr > max_r:
            problems.append(f"base frame changes by {dt:.3f} mm / {dr:.4f} deg "
                            f"(limits {max_t} mm / {max_r} deg)")
    return problems


class Capabilities(NamedTuple):
    """The optional compensation capabilities of a robot driver (None where it lacks one)."""

    sink: CompensationSink | None
    slots: CompensationSlots | None
    snapshots: CompensationSnapshots | None


def capabilities(robot: RobotDriver) -> Capabilities:
    """What ``robot`` can do with compensation tables: the one runtime check of the optional
    capability protocols (drivers declare them; the daemon's hub hands out a RobotDriver)."""
    return Capabilities(robot if isinstance(robot, CompensationSink) else None,
                        robot if isinstance(robot, CompensationSlots) else None,
                        robot if isinstance(robot, CompensationSnapshots) else None)


def _sink(robot: RobotDriver) -> CompensationSink:
    sink = capabilities(robot).sink
    if sink is None:
        raise CompensationError(f"{type(robot).__name__} cannot store compensation tables")
    return sink


async def write_and_verify(robot: RobotDriver, table: CompensationTable) -> CompensationTable:
    """Write ``table``, read it back, compare content and checksum; return the read-back.

    Raises
    ------
    CompensationError
        If the driver cannot store compensation tables.
    VerificationMismatch
        If what the controller holds differs from what was written.
    """
    sink = _sink(robot)
    sealed = table if table.checksum else table.sealed()
    await sink.write_compensation(sealed)  # drivers verify too; we check independently
    back = await sink.read_compensation()
    if back is None:
        raise VerificationMismatch("the controller holds no table after writing")
    details = table_diff(sealed, back, tol=1e-3)
    if details:
        raise VerificationMismatch(f"read-back differs: {details[0]}", diff=details)
    if back.compute_checksum() != back.checksum and back.checksum:
        raise VerificationMismatch("read-back table fails its own checksum")
    return back


# --- controller snapshots and journal reconciliation -------------------------------------------
async def snapshot(robot: RobotDriver, table: CompensationTable) -> ControllerSnapshot | None:
    """What the controller holds in ``table``'s slots, or None if the driver cannot say."""
    snapshots = capabilities(robot).snapshots
    if snapshots is None:
        return None
    return await snapshots.snapshot_compensation(table)


async def read_like(robot: RobotDriver, table: CompensationTable) -> CompensationTable | None:
    """The controller's values in ``table``'s slots, as a table (None: nothing there)."""
    can = capabilities(robot)
    if can.slots is not None:
        return await can.slots.read_compensation_like(table)
    return await _sink(robot).read_compensation()


#: The item of a stored snapshot that holds :attr:`Baseline.template` (as table JSON text).
_TEMPLATE_ITEM = "template"


class Baseline(BaseModel):
    """The controller's own values, read before robocal first wrote these slots, and the
    table whose slots they are (the drivers read slots from a table: ``template``; None in a
    snapshot stored without it, which cannot be read again).

    Stored as one :class:`ControllerSnapshot` whose ``items`` hold the template's JSON under
    ``"template"`` (:meth:`stored`, :meth:`from_stored`): the format of every store so far.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    snapshot: ControllerSnapshot
    template: CompensationTable | None

    @property
    def covers(self) -> str:
        """The table kind whose slots were read."""
        return self.snapshot.covers

    @classmethod
    def from_stored(cls, snap: ControllerSnapshot) -> Baseline:
        """Split a stored snapshot into its values and its template."""
        items = dict(snap.items)
        raw = items.pop(_TEMPLATE_ITEM, None)
        template = CompensationTable.model_validate_json(raw) if isinstance(raw, str) else None
        return cls(snapshot=snap.model_copy(update={"items": items}), template=template)

    def stored(self) -> ControllerSnapshot:
        """The snapshot as stored (and checksummed): the template inside its items."""
        if self.template is None:
            return self.snapshot
        return self.snapshot.model_copy(update={"items": {
            **self.snapshot.items, _TEMPLATE_ITEM: self.template.model_dump_json()}})

    def slots(self) -> CompensationTable:
        """The template, or CompensationError when the snapshot does not say its slots."""
        if self.template is None:
            raise CompensationError("snapshot does not say which slots it covers")
        return self.template


Entry = CompensationTable | Baseline


async def holds(robot: RobotDriver, entry: Entry) -> bool:
    """Whether the controller holds ``entry`` (a table or a snapshot) right now."""
    if isinstance(entry, Baseline):
        snapshots = capabilities(robot).snapshots
        if snapshots is None:
            return False
        current = await snapshots.snapshot_compensation(entry.slots())
        return not snapshot_diff(entry.snapshot, current)
    back = await read_like(robot, entry)
    return back is not None and not table_diff(entry, back, tol=1e-3)


async def take_snapshot(robot: RobotDriver, table: CompensationTable) -> Baseline | None:
    """:func:`snapshot`, remembering the slots (a copy of ``table``) to read them again."""
    snap = await snapshot(robot, table)
    return None if snap is None else Baseline(snapshot=snap, template=table)


async def restore(robot: RobotDriver, entry: Entry) -> CompensationTable | None:
    """Write ``entry`` back (a table: :func:`write_and_verify`; a snapshot: the driver's
    ``restore_snapshot``, which verifies the read-back)."""
    if isinstance(entry, CompensationTable):
        return await write_and_verify(robot, entry)
    snapshots = capabilities(robot).snapshots
    if snapshots is None:
        raise CompensationError(f"{type(robot).__name__} cannot restore controller snapshots")
    await snapshots.restore_snapshot(entry.snapshot)
    return None


def parse_entry(kind: str, text: str) -> Entry:
    """A stored ``tables`` row: a snapshot (kind ``snapshot``) or a sealed table."""
    if kind == "snapshot":
        return Baseline.from_stored(ControllerSnapshot.model_validate_json(text))
    return CompensationTable.model_validate_json(text)


# --- verification: the pushed targets measured again ---------------------------------------------
def verification_indices(n: int, count: int) -> list[int]:
    """``count`` indices spread evenly over ``range(n)`` (all of them when ``count >= n``)."""
    if count <= 0 or n <= 0:
        return []
    if count >= n:
        return list(range(n))
    return sorted({int(x) for x in np.rint(np.linspace(0, n - 1, count))})


def commanded_joints(entry: Entry | None, q_program: Array
                     ) -> tuple[Array, NDArray[np.bool_]]:
    """Joints (n, dof) rad the robot runs for program joints ``q_program`` under ``entry``,
    and which rows are compensated.

    ``targets``: the table's row for each program target (``ok`` rows only); ``joint``:
    program joints plus the table's offsets; anything else (frames, a controller snapshot,
    nothing): the program joints themselves.
    """
    q = np.atleast_2d(np.asarray(q_program, dtype=float))
    out = q.copy()
    comp = np.zeros(len(q), dtype=bool)
    if isinstance(entry, CompensationTable) and entry.kind == "targets":
        for row in entry.targets or []:
            if row.status == "ok" and 0 <= row.index < len(q):
                out[row.index] = np.radians(row.q_deg)
                comp[row.index] = True
    elif isinstance(entry, CompensationTable) and entry.kind == "joint":
        out = q + np.radians(entry.joint_offsets_deg(np.degrees(q)))
        comp[:] = True
    return out, comp


def verification_errors(p_target_m: Array, p_measured_m: Array) -> dict[str, float]:
    """RMS, mean and max (mm) of the distances between (n, 3) m targets and measurements."""
    e = np.linalg.norm(np.asarray(p_measured_m) - np.asarray(p_target_m), axis=1) * 1e3
    if e.size == 0:
        return {"n": 0}
    return {"n": int(e.size), "rms_mm": round(float(np.sqrt(np.mean(e**2))), 5),
            "mean_mm": round(float(np.mean(e)), 5), "max_mm": round(float(np.max(e)), 5)}
