"""``robocal predict``: reflector positions of a calibrated model for joint values."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    """Add the ``predict`` subcommand."""
    p = sub.add_parser(
        "predict", help="predict reflector positions with a calibrated model",
        description="Read joint values (CSV with q1..qN in degrees, optional pose_id) and "
                    "write predicted reflector positions x,y,z [mm] in the tracker frame, "
                    "their 1-sigma uncertainty sx,sy,sz [mm] (when the model has a "
                    "covariance) and whether the pose lies inside the calibrated joint range "
                    "(outside, the model's low-order fallback is used).")
    p.add_argument("--model", required=True, help="MODEL.json")
    p.add_argument("--joints", required=True, help="joint values (CSV)")
    p.add_argument("--out", required=True, help="PRED.csv to write (atomically)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(handler=run)


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


def run(args: argparse.Namespace) -> int:
    """Predict and write PRED.csv."""
    from robocal._core.measurements import read_joints_csv, write_points_csv
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel

    model = CalibratedModel.load(args.model)
    q = read_joints_csv(args.joints, dof=model.robot.dof)
    out = Path(args.out)
    if not out.parent.exists():
        raise ConfigError("directory does not exist", source=str(out.parent))
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
