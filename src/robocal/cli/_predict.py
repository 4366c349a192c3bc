"""``robocal predict``: reflector positions of a calibrated model, or of a nominal robot,
for joint values."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any

from robocal.cli._command import command


def register(sub: Any) -> None:
    """Add the ``predict`` subcommand."""
    p = command(sub, "predict", run)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", help="MODEL.json")
    src.add_argument("--robot", help="nominal robot: built-in name, robot TOML or URDF")
    p.add_argument("--tip", metavar="LINK",
                   help="with --robot FILE.urdf: link ending the chain (joints below it, "
                        "such as a gripper's, are left out)")
    p.add_argument("--tool", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="with --robot: flange -> reflector offset [mm] (default: the robot's)")
    p.add_argument("--joints", required=True, help="joint values (CSV)")
    p.add_argument("--out", required=True, help="PRED.csv to write (atomically)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")


def _pose_ids(path: str, n: int) -> list[str] | None:
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            sample = fh.read(4096)
            fh.seek(0)
            delim = ";" if sample.count(";") > sample.count(",") else ","
            rows = [r for r in csv.reader(fh, delimiter=delim) if r and any(c.strip() for c in r)]
    except OSError:
        return None
    head = [h.strip() for h in rows[0]] if rows else []
    if "pose_id" not in head or len(rows) - 1 != n:
        return None
    k = head.index("pose_id")
    return [r[k].strip() for r in rows[1:]]


def _out_path(text: str) -> Path:
    from robocal.errors import ConfigError

    out = Path(text)
    if not out.parent.exists():
        raise ConfigError("directory does not exist", source=str(out.parent))
    return out


def _nominal(args: argparse.Namespace) -> int:
    """Nominal reflector positions of a robot description (base frame), no MODEL.json."""
    import numpy as np

    from robocal._core.measurements import read_joints_csv, write_points_csv
    from robocal.errors import ConfigError
    from robocal.kinematics import ErrorModelSpec, KinematicModel, ParameterLayout, load_robot

    if args.tip is not None:
        if not str(args.robot).lower().endswith(".urdf"):
            raise ConfigError("--tip goes with a URDF robot", key="tip")
        from robocal.kinematics import load_urdf

        robot = load_urdf(args.robot, tip=args.tip)
    else:
        robot = load_robot(args.robot)
    q = read_joints_csv(args.joints, dof=robot.dof)
    out = _out_path(args.out)
    model = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    x = model.nominal_params()
    if args.tool is not None:
        x[ParameterLayout.TOOL] = np.asarray(args.tool, dtype=float) * 1e-3
    p = model.positions(q, x)
    extra: dict[str, list[object]] = {}
    ids = _pose_ids(args.joints, len(q))
    if ids is not None:
        extra["pose_id"] = list(ids)
    write_points_csv(out, p, extra)
    if args.json:
        sys.stdout.write(json.dumps({"model_id": None, "kind": "nominal", "robot": robot.name,
                                     "frame": "robot base", "n": len(q),
                                     "out": str(out)}) + "\n")
    else:
        sys.stdout.write(f"robocal predict: {len(q)} poses with the nominal {robot.name} "
                         f"(robot base frame, no calibration); wrote {out}\n")
    return 0


def run(args: argparse.Namespace) -> int:
    """Predict and write PRED.csv."""
    from robocal._core.measurements import read_joints_csv, write_points_csv
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel

    if args.robot is not None:
        return _nominal(args)
    if args.tip is not None or args.tool is not None:
        raise ConfigError("--tip and --tool go with --robot")
    model = CalibratedModel.load(args.model)
    q = read_joints_csv(args.joints, dof=model.robot.dof)
    out = _out_path(args.out)
    p = model.predict(q)
    inside = model.inside_coverage(q)
    extra: dict[str, list[object]] = {}
    ids = _pose_ids(args.joints, len(q))
    if ids is not None:
        extra["pose_id"] = list(ids)
    if model.covariance is not None:
        sig = model.prediction_sigma(q) * 1e3
        if model.fallback is not None and model.fallback.covariance is not None \
                and (~inside).any():
            sig[~inside] = model.fallback.prediction_sigma(q[~inside]) * 1e3
        for k, name in enumerate(("sx", "sy", "sz")):
            extra[name] = [float(v) for v in sig[:, k]]
    extra["in_coverage"] = [int(v) for v in inside]
    write_points_csv(out, p, extra)
    summary = {"model_id": model.model_id, "kind": model.kind, "n": len(q),
               "outside_coverage": int((~inside).sum()),
               "fallback": None if model.fallback is None else model.fallback.kind,
               "out": str(out)}
    if args.json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        note = ""
        if summary["outside_coverage"]:
            fb = f"fallback {summary['fallback']}" if model.fallback else "no fallback"
            note = f"; {summary['outside_coverage']} outside the calibrated joint range ({fb})"
        sys.stdout.write(f"robocal predict: {len(q)} poses with model {model.model_id} "
                         f"({model.kind}){note}; wrote {out}\n")
    return 0
