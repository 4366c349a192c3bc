"""Coverage of the joint ranges: multi-turn joints, the production program's targets, what the
capsule checks exclude, and the per-joint figure a plan records (ADR 0026).

A calibrated model is trusted only inside the joint ranges its poses covered (MODEL.json's
``coverage_deg``); joint errors such as transmission or scale errors do not repeat after a
turn, so a joint that turns more than one revolution is planned over its whole range. Angles
in rad inside, degrees in the records.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from robocal._core.measurements import read_joints_csv, read_table
from robocal.compensation import read_targets_csv
from robocal.kinematics import RobotDescription
from robocal.planning._feasibility import FeasibilityChecker, one_revolution
from robocal.planning._geometry import range_scaled, segment_box_distance, segment_distance
from robocal.planning._motion import MotionChecker

Array = NDArray[np.float64]
Index = NDArray[np.intp]

#: Share of each joint's feasible span the calibration poses must reach at both ends.
SPAN_SHARE = 0.95
#: The program's joint ranges are covered this far beyond their ends, deg.
TARGET_MARGIN_DEG = 5.0


def read_program_joints(path: str | Path, *, dof: int) -> Array:
    """Joint values (n, dof) rad of a production program: a TARGETS.csv (``x, y, z`` and the
    seed joints ``q1..qN``) or a JOINTS.csv (``q1..qN``), both as in
    ``docs/compensation-tables.md``; raises :class:`robocal.errors.DataError` naming the row."""
    header, _ = read_table(path)  # a missing or unreadable file is a DataError naming it
    if {"x", "y", "z"} <= set(header):
        return read_targets_csv(path, dof=dof).q_seed
    return read_joints_csv(path, dof=dof)


def winding_ranges(motion: MotionChecker, home: Array, ranges: Array
                   ) -> tuple[Array, list[str]]:
    """Keep the whole range of each joint wider than one revolution only if that joint can
    turn through it safely.

    The joint is swept alone from one end of ``ranges`` (dof, 2) rad to the other, the other
    joints at ``home`` (dof,) rad, and the swept path checked (:meth:`MotionChecker.check_moves`).
    A joint that cannot (the UR10's shoulder would pass through the floor) is cut to the
    revolution centred on home: past one turn its poses repeat and no safe move leads there.

    Returns
    -------
    ranges : ndarray, shape (dof, 2)
        The ranges to plan in, rad.
    notes : list of str
        One sentence per joint cut, naming where and why the sweep fails.
    """
    out = ranges.copy()
    wide = np.flatnonzero(ranges[:, 1] - ranges[:, 0] > 2.0 * math.pi)
    if not wide.size:
        return out, []
    a = np.repeat(home[None, :], len(wide), axis=0)
    b = a.copy()
    a[np.arange(len(wide)), wide] = ranges[wide, 0]
    b[np.arange(len(wide)), wide] = ranges[wide, 1]
    res = motion.check_moves(a, b)
    cut = one_revolution(ranges, home)
    notes = []
    for k, j in enumerate(wide):
        if res.safe[k]:
            continue
        out[j] = cut[j]
        notes.append(
            f"J{j + 1} cannot turn through its whole range "
            f"[{math.degrees(ranges[j, 0]):.0f}, {math.degrees(ranges[j, 1]):.0f}] deg from "
            f"home ({res.reasons[k]} at J{j + 1} = {math.degrees(res.q_bad[k, j]):.0f} deg): "
            f"planned in [{math.degrees(out[j, 0]):.0f}, {math.degrees(out[j, 1]):.0f}] deg")
    return out, notes


def widen_for_targets(ranges: Array, limits: Array, targets: Array, margin: float
                      ) -> tuple[Array, list[str]]:
    """Widen ``ranges`` (dof, 2) rad to the program's joint range (``targets`` (n, dof) rad)
    plus ``margin`` rad, within the robot ``limits`` (dof, 2); a note per joint widened."""
    out = ranges.copy()
    lo = np.maximum(targets.min(axis=0) - margin, limits[:, 0])
    hi = np.minimum(targets.max(axis=0) + margin, limits[:, 1])
    notes = []
    for j in range(len(out)):
        if lo[j] < out[j, 0] - 1e-9 or hi[j] > out[j, 1] + 1e-9:
            new = (min(out[j, 0], lo[j]), max(out[j, 1], hi[j]))
            notes.append(f"J{j + 1} working range [{math.degrees(out[j, 0]):.0f}, "
                         f"{math.degrees(out[j, 1]):.0f}] deg widened to "
                         f"[{math.degrees(new[0]):.0f}, {math.degrees(new[1]):.0f}] deg to cover "
                         "the program's targets")
            out[j] = new
    return out, notes


def required_span(q_c: Array, targets: Array | None, margin: float,
                  share: float = SPAN_SHARE) -> Array:
    """Per joint, the range (dof, 2) rad the calibration poses must reach: ``share`` of the
    feasible candidates' span (``q_c`` (n, dof) rad), and the program's targets plus
    ``margin`` rad, both within that span."""
    lo, hi = q_c.min(axis=0), q_c.max(axis=0)
    cut = 0.5 * (1.0 - share) * (hi - lo)
    need = np.stack([lo + cut, hi - cut], axis=1)
    if targets is not None and len(targets):
        need[:, 0] = np.maximum(np.minimum(need[:, 0], targets.min(axis=0) - margin), lo)
        need[:, 1] = np.minimum(np.maximum(need[:, 1], targets.max(axis=0) + margin), hi)
    return need


def ensure_span(q_c: Array, chosen: Index, allowed: NDArray[np.bool_], need: Array) -> Index:
    """Swap calibration poses so that every joint reaches both ends of ``need`` (dof, 2) rad.

    For each end not reached, the allowed candidate beyond it (or, if none, the one farthest
    out) that lies nearest to a chosen pose in range-scaled joint space replaces that pose;
    poses holding an end of any joint are never replaced. At most two swaps per joint, so
    the stratified, D-optimal character of the design is kept.

    Returns
    -------
    ndarray of int, shape (len(chosen),)
    """
    chosen = np.array(chosen, dtype=np.intp)
    x = range_scaled(q_c)
    dof = q_c.shape[1]
    for j in range(dof):
        for end in (0, 1):
            qj = q_c[chosen, j]
            reached = qj.min() <= need[j, 0] + 1e-9 if end == 0 else qj.max() >= need[j, 1] - 1e-9
            if reached:
                continue
            free = allowed.copy()
            free[chosen] = False
            beyond = free & ((q_c[:, j] <= need[j, 0]) if end == 0 else (q_c[:, j] >= need[j, 1]))
            if not beyond.any():
                better = free & ((q_c[:, j] < qj.min()) if end == 0 else (q_c[:, j] > qj.max()))
                if not better.any():
                    continue
                extreme = (q_c[better, j].min() if end == 0 else q_c[better, j].max())
                beyond = better & (q_c[:, j] == extreme)
            holders = np.unique(np.concatenate([np.argmin(q_c[chosen], axis=0),
                                                np.argmax(q_c[chosen], axis=0)]))
            swappable = np.setdiff1d(np.arange(len(chosen)), holders)
            if not swappable.size:
                continue
            cand = np.flatnonzero(beyond)
            d = np.sum((x[cand, None, :] - x[chosen[swappable]][None, :, :]) ** 2, axis=2)
            c, s = np.unravel_index(int(np.argmin(d)), d.shape)
            chosen[swappable[s]] = cand[c]
    return chosen


def joint_coverage(robot: RobotDescription, working: Array, planned: Array,
                   targets: Array | None, margin: float) -> list[dict[str, object]]:
    """The per-joint coverage record of a plan (degrees, rounded).

    ``working`` (dof, 2) rad: the planner's ranges; ``planned`` (n, dof) rad: the calibration
    poses; ``targets`` (m, dof) rad or None: the program's joints. ``of_limits`` is the share
    of the robot's range the calibration poses span; ``targets_covered`` whether they span
    the targets' range plus ``margin`` rad (clipped to the robot limits).
    """
    lim = robot.joint_limits
    out: list[dict[str, object]] = []

    def deg(a: float, b: float) -> list[float]:
        return [round(math.degrees(a), 3), round(math.degrees(b), 3)]

    for j in range(robot.dof):
        p_lo, p_hi = float(planned[:, j].min()), float(planned[:, j].max())
        rec: dict[str, object] = {
            "joint": j + 1, "limits_deg": deg(lim[j, 0], lim[j, 1]),
            "working_deg": deg(working[j, 0], working[j, 1]), "planned_deg": deg(p_lo, p_hi),
            "of_limits": round((p_hi - p_lo) / (lim[j, 1] - lim[j, 0]), 4),
            "targets_deg": None, "targets_covered": None}
        if targets is not None and len(targets):
            t_lo, t_hi = float(targets[:, j].min()), float(targets[:, j].max())
            rec["targets_deg"] = deg(t_lo, t_hi)
            n_lo = max(t_lo - margin, lim[j, 0])
            n_hi = min(t_hi + margin, lim[j, 1])
            # rounding of the file (1e-6 deg) must not flip the verdict
            rec["targets_covered"] = bool(p_lo <= n_lo + 1e-7 and p_hi >= n_hi - 1e-7)
        out.append(rec)
    return out


def excluded_families(checker: FeasibilityChecker, q: Array, screened: int, *,
                      limit: int = 20000) -> list[dict[str, object]]:
    """Group candidates ``q`` (n, dof) rad that fail a collision check by their cause.

    The cause of a pose is its worst violation: the capsule pair of a self-collision, the
    capsule below the floor clearance, or the capsule and keep-out box. Per cause: how many
    candidates (of ``screened`` that faced the tracker) and, per joint, the range of their
    joint values (5th to 95th percentile, deg), so that a user sees which part of the joint
    space was left out and why. Most frequent first; at most ``limit`` poses are examined.
    """
    q = np.atleast_2d(q)[:limit]
    if not len(q):
        return []
    f = checker.check(q, visibility=False)
    bad = ~f.collision_free
    q = q[bad]
    if not len(q):
        return []
    cm = checker.capsules
    A, B, _, _ = cm.segments(q)
    r = cm.radius
    n = len(q)
    moving = np.flatnonzero(~cm.static)
    causes = np.full(n, "", dtype=object)
    worst = np.full(n, np.inf)

    def take(margin: Array, text: NDArray[np.object_]) -> None:
        better = margin < np.minimum(worst, 0.0)
        causes[better] = text[better]
        worst[better] = margin[better]

    if len(cm.pairs):
        i, j = cm.pairs[:, 0], cm.pairs[:, 1]
        d, _, _ = segment_distance(A[:, i], B[:, i], A[:, j], B[:, j])
        g = d - r[i] - r[j] - checker.clearance
        k = np.argmin(g, axis=1)
        names = np.array([f"self-collision of capsules {cm.names[a]} and {cm.names[b]}"
                          for a, b in cm.pairs], dtype=object)
        take(g[np.arange(n), k], names[k])
    if moving.size:
        zlow = np.minimum(A[:, moving, 2], B[:, moving, 2]) - r[moving]
        k = np.argmin(zlow, axis=1)
        names = np.array([f"capsule {cm.names[m]} below the floor clearance" for m in moving],
                         dtype=object)
        take(zlow[np.arange(n), k] - checker.floor_z - checker.clearance, names[k])
    if len(checker.box_lo) and moving.size:
        d, _ = segment_box_distance(A[:, moving, None, :], B[:, moving, None, :],
                                    checker.box_lo[None, None], checker.box_hi[None, None])
        g = (d - r[moving][None, :, None] - checker.clearance).reshape(n, -1)
        k = np.argmin(g, axis=1)
        boxes = [b.name or f"#{i + 1}" for i, b in enumerate(checker.cell.keep_out)]
        names = np.array([f"capsule {cm.names[m]} in keep-out box {b!r}"
                          for m in moving for b in boxes], dtype=object)
        take(g[np.arange(n), k], names[k])
    limits = ~f.within_limits[bad]
    causes[limits & (causes == "")] = "outside the joint working range"
    return [family(str(cause) or "collision", q[causes == cause], screened)
            for cause in sorted(set(causes.tolist()), key=lambda c: -int(np.sum(causes == c)))]


def family(reason: str, q: Array, screened: int) -> dict[str, object]:
    """The record of one excluded family: its ``reason``, the number of candidates ``q``
    (n, dof) rad, of how many ``screened``, and their 5-95 % joint ranges, deg."""
    lo = np.degrees(np.percentile(q, 5, axis=0))
    hi = np.degrees(np.percentile(q, 95, axis=0))
    return {"reason": reason, "candidates": len(q), "of_screened": screened,
            "joint_ranges_deg": [[round(float(a), 1), round(float(b), 1)]
                                 for a, b in zip(lo, hi, strict=True)]}
