"""``robocal simulate``: measurement files from the virtual robot, to try the offline commands."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from robocal.cli._defaults import VALIDATION_HELP, default_validation

SCENARIO_HELP = ("planted truth: nominal, constant, paper (constant + joint-dependent harmonics "
                 "and pitch), strain-wave (paper + gear ripple), fine-map (fine joint-angle "
                 "errors, gravity torsion)")


def register(sub: Any) -> None:
    """Add the ``simulate`` subcommand."""
    p = sub.add_parser(
        "simulate", help="write MEAS.csv files measured on the virtual robot",
        description="Measure poses on robocal's virtual robot (planted errors, laser-tracker "
                    "noise) and write measurement CSVs (q1..qN deg, x,y,z mm, sx,sy,sz mm), "
                    "e.g. to try 'robocal fit'. Poses come from a PLAN.json (calibration and "
                    "validation purposes) or are drawn at random within the joint limits.")
    p.add_argument("--robot", default="fanuc_lrmate200i", help="built-in name or robot TOML")
    p.add_argument("--scenario", default="paper", help=SCENARIO_HELP)
    p.add_argument("--seed", type=int, default=1, help="seed of the planted errors and noise")
    p.add_argument("--plan", type=Path, help="PLAN.json whose poses to measure")
    p.add_argument("--poses", type=int, default=250, help="random poses when no --plan")
    p.add_argument("--validation", type=int, default=None,
                   help=VALIDATION_HELP + "; random, when no --plan")
    p.add_argument("--outliers", type=float, default=0.0,
                   help="fraction of calibration readings with a beam-break glitch")
    p.add_argument("--out", type=Path, required=True, help="calibration MEAS.csv to write")
    p.add_argument("--validation-out", type=Path,
                   help="validation CSV (default: OUT with '-val' before the suffix)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Simulate and write the files."""
    import numpy as np

    from robocal._core.measurements import MeasurementSet
    from robocal.errors import ConfigError
    from robocal.simulation import VirtualCell

    if args.validation is None:
        args.validation = default_validation(args.poses)
    if args.poses < 1 or args.validation < 0 or not 0.0 <= args.outliers < 0.5:
        raise ConfigError("--poses must be >= 1, --validation >= 0, --outliers in [0, 0.5)")
    cell = VirtualCell.create(args.robot, args.scenario, seed=args.seed)
    rng = np.random.default_rng(args.seed + 1000)
    if args.plan is not None:
        from robocal.planning import Plan

        plan = Plan.load(args.plan)
        q_cal = np.asarray(plan.joint_targets("calibration"), dtype=float)
        q_val = np.asarray(plan.joint_targets("validation"), dtype=float)
        if q_cal.shape[1:] != (cell.robot.dof,):
            raise ConfigError(f"plan poses have {q_cal.shape[1] if q_cal.ndim == 2 else 0} "
                              f"joints, robot has {cell.robot.dof}", source=str(args.plan))
    else:
        q_cal = cell.random_joints(args.poses, rng)
        q_val = cell.random_joints(args.validation, rng)
    val_out = args.validation_out or args.out.with_name(f"{args.out.stem}-val{args.out.suffix}")
    written = []
    for q, path, frac, tag in ((q_cal, args.out, args.outliers, "C"), (q_val, val_out, 0.0, "V")):
        if len(q) == 0:
            continue
        qq, p, s, bad = cell.simulate(q, rng, outlier_fraction=frac)
        ids = tuple(f"{tag}{i:04d}" for i in range(len(qq)))
        MeasurementSet(qq, p, s, ids).write_csv(path)
        written.append((path, len(qq), len(bad)))
    for path, n, n_bad in written:
        extra = f", {n_bad} with planted glitches" if n_bad else ""
        sys.stdout.write(f"wrote {path} ({n} poses{extra})\n")
    sys.stdout.write(f"virtual {cell.robot.name}, scenario {args.scenario!r}, seed {args.seed}\n")
    return 0
