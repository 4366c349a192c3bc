"""``robocal simulate``: measurement files from the virtual robot, to try the offline commands."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robocal.cli._command import command, seed
from robocal.cli._defaults import (
    DEFAULT_SEED,
    SCENARIO_HELP,
    VALIDATION_HELP,
    default_validation,
)

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from robocal.kinematics import RobotDescription
    from robocal.planning import Plan

def register(sub: Any) -> None:
    """Add the ``simulate`` subcommand."""
    p = command(sub, "simulate", run)
    p.add_argument("--robot", default=None,
                   help="built-in name or robot TOML (default: the plan's robot with --plan, "
                        "else fanuc_lrmate200i); with --plan it must be the plan's robot")
    p.add_argument("--scenario", default="paper", help=SCENARIO_HELP)
    p.add_argument("--seed", type=seed, default=DEFAULT_SEED,
                   help=f"seed of the planted errors and noise (default {DEFAULT_SEED}, as "
                        "plan, demo and sim)")
    p.add_argument("--plan", type=Path, help="PLAN.json whose poses to measure")
    p.add_argument("--poses", type=int, default=250, help="random poses when no --plan")
    p.add_argument("--validation", type=int, default=None,
                   help=VALIDATION_HELP + "; random, when no --plan")
    p.add_argument("--outliers", type=float, default=0.0,
                   help="fraction of calibration readings with a beam-break glitch")
    p.add_argument("--out", type=Path, required=True, help="calibration MEAS.csv to write")
    p.add_argument("--validation-out", type=Path,
                   help="validation CSV (default: OUT with '-val' before the suffix)")
    p.add_argument("--targets-out", type=Path,
                   help="TARGETS.csv of the validation poses: where the nominal robot puts "
                        "the reflector (tracker frame), i.e. where a program written with "
                        "nominal kinematics wants it, with the program's joints; "
                        "'robocal compensate' corrects the joints towards it (default: OUT "
                        "with '-targets' before the suffix)")


def run(args: argparse.Namespace) -> int:
    """Simulate and write the files."""
    from robocal._core.robot_names import check_robot_spec

    if args.robot is not None:
        check_robot_spec(args.robot)  # before numpy: a typo is answered at once
    import numpy as np

    from robocal._core.measurements import MeasurementSet
    from robocal.errors import ConfigError
    from robocal.simulation import VirtualCell

    if args.validation is None:
        args.validation = default_validation(args.poses)
    if args.poses < 1 or args.validation < 0 or not 0.0 <= args.outliers < 0.5:
        raise ConfigError("--poses must be >= 1, --validation >= 0, --outliers in [0, 0.5)")
    plan = None if args.plan is None else _load_plan(args.plan)
    robot = _robot_for(args.robot, plan, args.plan)
    cell = VirtualCell.create(robot, args.scenario, seed=args.seed)
    rng = np.random.default_rng(args.seed + 1000)
    if plan is not None:
        q_cal = np.asarray(plan.joint_targets("calibration"), dtype=float)
        q_val = np.asarray(plan.joint_targets("validation"), dtype=float)
        if q_cal.shape[1:] != (cell.robot.dof,):
            raise ConfigError(f"plan poses have {q_cal.shape[1] if q_cal.ndim == 2 else 0} "
                              f"joints, robot has {cell.robot.dof}", source=str(args.plan))
        _check_within_limits(cell.robot, np.vstack([q_cal, q_val]), str(args.plan))
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
    if len(q_val):
        from robocal.compensation import TargetSet

        targets_out = args.targets_out or args.out.with_name(
            f"{args.out.stem}-targets{args.out.suffix}")
        ids = tuple(f"V{i:04d}" for i in range(len(q_val)))
        TargetSet(p=cell.nominal_position(q_val), q_seed=q_val, labels=ids,
                  id_column="pose_id").write_csv(targets_out)
        written.append((targets_out, len(q_val), 0))
    for path, n, n_bad in written:
        extra = f", {n_bad} with planted glitches" if n_bad else ""
        sys.stdout.write(f"wrote {path} ({n} poses{extra})\n")
    sys.stdout.write(f"virtual {cell.robot.name}, scenario {args.scenario!r}, seed {args.seed}\n")
    return 0


def _load_plan(path: Path) -> Plan:
    """The plan file, every reading problem as one :class:`ConfigError`."""
    from robocal.errors import ConfigError
    from robocal.planning import Plan

    try:
        return Plan.load(path)
    except ConfigError:
        raise
    except ValueError as err:  # e.g. an integer longer than Python reads (4,300 digits)
        raise ConfigError(f"not a readable plan: {str(err)[:120]}", source=str(path)) from None


def _robot_for(robot: str | None, plan: Plan | None, plan_path: Path | None
               ) -> RobotDescription:
    """The robot to simulate: the plan's own unless ``--robot`` names it (a different robot
    is refused: its joint limits and geometry are not the plan's)."""
    from robocal.errors import ConfigError
    from robocal.kinematics import RobotDescription, load_robot

    if plan is None:
        return load_robot(robot or "fanuc_lrmate200i")
    planned = RobotDescription.from_dict(dict(plan.robot.description),
                                         source=f"{plan_path} (robot)")
    if robot is None:
        return planned
    given = load_robot(robot)
    if not _same_robot(given, planned):
        raise ConfigError(f"the plan was made for {plan.robot.name!r}, not {robot!r}; leave "
                          "out --robot to simulate the plan's robot", source=str(plan_path))
    return given


def _same_robot(a: RobotDescription, b: RobotDescription) -> bool:
    """Same name and the same numbers (to rounding: a plan stores the robot as JSON)."""
    import numpy as np

    def numbers(r: RobotDescription) -> list[float]:
        return [v for j in r.joints
                for v in (j.a, j.d, j.alpha, j.theta_offset, j.q_min, j.q_max)]

    return (a.name == b.name and len(a.joints) == len(b.joints)
            and bool(np.allclose(numbers(a), numbers(b), rtol=1e-9, atol=1e-12)))


def _check_within_limits(robot: RobotDescription, q_rad: NDArray[np.float64],
                         source: str) -> None:
    """Refuse joint targets that are not finite or lie outside the robot's joint limits."""
    import numpy as np

    from robocal.errors import ConfigError

    lo = np.array([j.q_min for j in robot.joints]) - 1e-6
    hi = np.array([j.q_max for j in robot.joints]) + 1e-6
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(q_rad) | (q_rad < lo) | (q_rad > hi)
    if bad.any():
        n = int(bad.any(axis=1).sum())
        i, j = (int(v) for v in np.argwhere(bad)[0])
        raise ConfigError(f"{n} plan pose(s) outside the joint limits of {robot.name}, the first "
                          f"J{j + 1} = {np.degrees(q_rad[i, j]):.6g} deg", source=source)
