"""``robocal plan``: plan a calibration campaign and write PLAN.json.

    robocal plan --robot ROBOT --cell CELL.toml --model constant|high-order|auto --count N
                 --out PLAN.json [--design stratified|d-optimal] [--validation M] [--cpa]
                 [--cpa-points K] [--no-iso]
                 [--seed S] [--candidates C] [--targets TARGETS.csv] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from robocal._core.model_names import DEFAULT_MODEL, MODELS
from robocal.cli._command import command, seed
from robocal.cli._defaults import DEFAULT_SEED, VALIDATION_HELP, default_validation


def register(sub: Any) -> None:
    """Add the ``plan`` subcommand."""
    p = command(sub, "plan", run)
    p.add_argument("--robot", required=True, help="built-in robot name or robot TOML file")
    p.add_argument("--cell", required=True,
                   help="cell description TOML file, or a built-in cell name (demo)")
    p.add_argument("--model", default=DEFAULT_MODEL, choices=MODELS,
                   help=f"error model the poses are optimised for (default {DEFAULT_MODEL})")
    p.add_argument("--count", required=True, type=int, help="number of calibration poses")
    p.add_argument("--design", default="stratified", choices=("stratified", "d-optimal"),
                   help="pose selection: stratified (default; represents the workspace, so "
                        "that a model lacking some of the robot's errors is not biased by "
                        "extreme poses) or d-optimal (most information for the model alone)")
    p.add_argument("--out", required=True, type=Path, metavar="PLAN.json", help="output file")
    p.add_argument("--validation", type=int, default=None, metavar="M",
                   help=VALIDATION_HELP + "; disjoint from the calibration poses")
    p.add_argument("--cpa", action="store_true", help="add single-joint CPA sweeps")
    p.add_argument("--cpa-points", type=int, default=12, metavar="K",
                   help="points per CPA sweep (default 12)")
    p.add_argument("--no-iso", action="store_true", help="leave out the ISO 9283 cube poses")
    p.add_argument("--iso-cycles", type=int, default=30, metavar="N",
                   help="cycles through the ISO 9283 poses P1..P5 (the standard asks for 30)")
    p.add_argument("--seed", type=seed, default=DEFAULT_SEED,
                   help=f"random seed (default {DEFAULT_SEED}, as simulate, demo and sim)")
    p.add_argument("--candidates", type=int, default=4096,
                   help="feasible candidates to choose from (default 4096)")
    p.add_argument("--targets", type=Path, default=None, metavar="FILE",
                   help="the production program (TARGETS.csv or JOINTS.csv, see "
                        "docs/compensation-tables.md): its joint ranges, plus a margin, are "
                        "covered by the calibration poses")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _summary(plan: Any, out: Path) -> dict[str, Any]:
    o = plan.observability.calibration
    b = plan.observability.random_baseline
    return {
        "out": str(out), "robot": plan.robot.name, "cell": plan.cell.name, "seed": plan.seed,
        "model": plan.model.name, "design": plan.model.design,
        "design_note": plan.model.design_note, "poses": len(plan.poses),
        "by_purpose": {k: plan.count(k) for k in
                       ("calibration", "validation", "cpa", "iso", "via") if plan.count(k)},
        "candidates": plan.candidates.model_dump(),
        "observability": o.model_dump(), "random_baseline": b.model_dump() if b else None,
        "move_time_s": plan.motion.move_time_s, "warnings": list(plan.warnings),
        "dropped": [d.model_dump() for d in plan.dropped],
        "coverage": [c.model_dump() for c in plan.coverage],
        "excluded": [e.model_dump() for e in plan.excluded],
    }


def run(args: argparse.Namespace) -> int:
    """Plan, write the file atomically, print a summary; return the exit code."""
    from robocal._core.robot_names import check_robot_spec
    from robocal.errors import ConfigError

    # the arguments are checked before the planner (numpy, scipy) is imported: a typo is
    # answered at once
    check_robot_spec(args.robot)
    out: Path = args.out
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise ConfigError("output directory does not exist", source=str(out))
    if out.is_dir():
        raise ConfigError("is a directory", source=str(out))
    validation = default_validation(args.count) if args.validation is None else args.validation
    from robocal.planning import plan_campaign

    plan = plan_campaign(args.robot, args.cell, count=args.count, model=args.model,
                         validation=validation, cpa=args.cpa, cpa_points=args.cpa_points,
                         iso=not args.no_iso, iso_cycles=args.iso_cycles, seed=args.seed,
                         candidates=args.candidates, design=args.design,
                         targets=args.targets)
    plan.save(out)
    s = _summary(plan, out)
    if args.json:
        sys.stdout.write(json.dumps(s) + "\n")
        return 0
    o = plan.observability.calibration
    b = plan.observability.random_baseline
    c = plan.candidates
    parts = ", ".join(f"{v} {k}" for k, v in s["by_purpose"].items())
    w = sys.stdout.write
    w(f"wrote {out}: {len(plan.poses)} poses ({parts})\n")
    w(f"  robot {plan.robot.name}, cell {plan.cell.name}, model {plan.model.name}, "
      f"seed {plan.seed}\n")
    w(f"  design: {plan.model.design_note}\n")
    w(f"  candidates: {c.drawn} drawn, {c.screened} facing the tracker, {c.feasible} feasible\n")
    cond = "inf" if o.condition_number is None else f"{o.condition_number:.1f}"
    w(f"  parameters: {o.parameters}, identifiable {o.identifiable}; needs >= {o.min_poses} "
      f"poses, {o.recommended_poses} recommended\n")
    w(f"  observability O1 {o.O1:.4g}  O2 {o.O2:.4g}  O3 {o.O3:.4g}  O4 {o.O4:.4g}  "
      f"O5 {o.O5:.4g}  cond {cond}\n")
    if b is not None:
        bc = "inf" if b.condition_number is None else f"{b.condition_number:.1f}"
        w(f"  (random feasible set of the same size: O1 {b.O1:.4g}, cond {bc})\n")
    if plan.iso9283 is not None:
        w(f"  ISO 9283 cube: side {plan.iso9283.side_mm:.0f} mm at "
          f"[{', '.join(f'{v:.0f}' for v in plan.iso9283.centre_mm)}] mm\n")
    m = plan.motion
    w(f"  moves: {m.move_time_s / 60:.1f} min at {m.speed_fraction:.0%} joint speed, "
      f"{m.via_points} via-points (max step {m.max_joint_step_deg:g} deg)\n")
    if plan.capsules is not None:
        w("  link capsules: " + ", ".join(f"{v:.0f}" for v in plan.capsules.link_radii_mm)
          + f" mm ({plan.capsules.source})\n")
    _write_coverage(plan, w)
    for msg in plan.warnings:
        w(f"  warning: {msg}\n")
    for d in plan.dropped:
        q = ", ".join(f"{v:.2f}" for v in d.joints_deg)
        w(f"  dropped {d.purpose} target [{q}] deg: {d.reason}\n")
    if not math.isfinite(o.O1):  # pragma: no cover - defensive
        return 1
    return 0


def _write_coverage(plan: Any, w: Any) -> None:
    """Per joint: the calibrated range against limits and targets; the excluded families."""
    tgt = plan.targets_source
    w("  coverage of the calibration poses (deg)" + (f", program {tgt}" if tgt else "") + ":\n")
    for c in plan.coverage:
        line = (f"    J{c.joint}: [{c.planned_deg[0]:.0f}, {c.planned_deg[1]:.0f}] of limits "
                f"[{c.limits_deg[0]:.0f}, {c.limits_deg[1]:.0f}] ({c.of_limits:.0%})")
        if c.targets_deg is not None:
            verdict = "covered" if c.targets_covered else "NOT covered"
            line += (f", targets [{c.targets_deg[0]:.0f}, {c.targets_deg[1]:.0f}] {verdict}")
        w(line + "\n")
    work = [c.working_deg for c in plan.coverage]
    for e in plan.excluded[:6]:
        # name only the joints the family is confined to (under 70 % of the working range)
        ranges = ", ".join(f"J{j + 1} {a:.0f}..{b:.0f}"
                           for j, (a, b) in enumerate(e.joint_ranges_deg)
                           if j < len(work) and b - a < 0.7 * (work[j][1] - work[j][0]))
        w(f"  excluded {e.candidates} of {e.of_screened} candidates: {e.reason} ("
          + (f"{ranges} deg" if ranges else "spread over the working ranges") + ")\n")
    if len(plan.excluded) > 6:
        w(f"  ... and {len(plan.excluded) - 6} more excluded families (see 'excluded')\n")
