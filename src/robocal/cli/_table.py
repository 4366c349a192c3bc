"""``robocal table``: build, check or compare compensation tables.

    robocal table --model MODEL.json --kind targets|joint|frames --out FILE [--targets T.csv]
    robocal table --check TABLE.json
    robocal table --diff A.json B.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    """Add the ``table`` subcommand."""
    p = sub.add_parser(
        "table", help="build, check or compare compensation tables",
        description="Build a sealed compensation table from a calibrated model: 'targets' "
                    "(corrected joints for TARGETS.csv), 'joint' (per-joint correction grids) "
                    "or 'frames' (user and tool frames). --check verifies a table file's "
                    "checksum; --diff compares two tables.")
    p.add_argument("--model", metavar="MODEL.json", help="calibrated model")
    p.add_argument("--kind", choices=("targets", "joint", "frames"), help="table kind")
    p.add_argument("--out", metavar="FILE", help="output table (JSON)")
    p.add_argument("--targets", metavar="TARGETS.csv", help="program targets (kind targets)")
    p.add_argument("--interp-tol-deg", type=float, default=1e-4,
                   help="joint tables: linear-interpolation error bound per joint, deg "
                        "(default 1e-4)")
    p.add_argument("--joint-method", choices=("ez", "fit"), default="ez",
                   help="joint tables: 'ez' derives the corrections from the model's rotations "
                        "about the joint axes; 'fit' fits them (with the frames) for the least "
                        "predicted residual (default ez)")
    p.add_argument("--with-joint-table", action="store_true",
                   help="frames: fit the frames for use together with the joint table")
    p.add_argument("--samples", type=int, default=2000,
                   help="poses sampled in the coverage to fit frames / predict residuals")
    p.add_argument("--check", metavar="TABLE.json", help="verify a table file and summarise it")
    p.add_argument("--diff", nargs=2, metavar=("A.json", "B.json"), help="compare two tables")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(handler=run)


def _summary(table: Any) -> dict[str, Any]:
    size = {"targets": len(table.targets or []), "joint": len(table.joints or []),
            "frames": 2}[table.kind]
    return {"kind": table.kind, "model_id": table.model_id, "robot": table.robot,
            "entries": size, "predicted_residual_mm": table.predicted_residual_mm,
            "checksum": table.checksum, "stats": table.stats}


def run(args: argparse.Namespace) -> int:
    """Dispatch on the mode; return the exit code."""
    from robocal.compensation import CompensationTable, build_table, diff_tables, read_targets_csv
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel

    build_opts = (args.model, args.kind, args.out, args.targets)
    modes = sum([args.check is not None, args.diff is not None, any(build_opts)])
    if modes != 1:
        raise ConfigError("give either --model/--kind/--out, or --check FILE, or --diff A B")
    if args.check:
        table = CompensationTable.read(args.check)
        s = _summary(table)
        if args.json:
            sys.stdout.write(json.dumps(s) + "\n")
        else:
            sys.stdout.write(f"{args.check}: checksum ok; {s['kind']} table, {s['entries']} "
                             f"entries, model {s['model_id']}, robot {s['robot']}, predicted "
                             f"residual {s['predicted_residual_mm']:.4f} mm\n")
        return 0
    if args.diff:
        a, b = (CompensationTable.read(f) for f in args.diff)
        d = diff_tables(a, b)
        if args.json:
            sys.stdout.write(json.dumps({"identical": d.identical, "lines": list(d.lines),
                                         "max_joint_deg": d.max_joint_deg,
                                         "max_translation_mm": d.max_translation_mm,
                                         "max_rotation_deg": d.max_rotation_deg}) + "\n")
        else:
            sys.stdout.write("tables agree\n" if d.identical else
                             "".join(f"{line}\n" for line in d.lines))
        return 0 if d.identical else 1
    for flag, value in (("--model", args.model), ("--kind", args.kind), ("--out", args.out)):
        if not value:
            raise ConfigError(f"{flag} is required to build a table")
    if args.kind == "targets" and not args.targets:
        raise ConfigError("--kind targets needs --targets TARGETS.csv")
    if args.kind != "targets" and args.targets:
        raise ConfigError(f"--targets is only used with --kind targets, not {args.kind}")
    if not args.interp_tol_deg > 0:
        raise ConfigError(f"--interp-tol-deg must be positive, got {args.interp_tol_deg}")
    if args.samples < 50:
        raise ConfigError(f"--samples must be at least 50, got {args.samples}")
    out = Path(args.out)
    if out.is_dir() or not out.parent.is_dir():
        raise ConfigError("not a writable file path", source=args.out)
    cal = CalibratedModel.load(args.model)
    targets = read_targets_csv(args.targets, dof=cal.robot.dof) if args.targets else None
    table = build_table(cal, args.kind, targets=targets, interp_tol_deg=args.interp_tol_deg,
                        with_joint_table=args.with_joint_table, samples=args.samples,
                        joint_method=args.joint_method)
    try:
        table.write(out)
    except OSError as err:
        raise ConfigError(f"cannot write: {err}", source=str(out)) from err
    s = _summary(table)
    if args.json:
        sys.stdout.write(json.dumps(s) + "\n")
    else:
        sys.stdout.write(f"wrote {args.kind} table {out} ({s['entries']} entries, model "
                         f"{s['model_id']}, predicted residual "
                         f"{s['predicted_residual_mm']:.4f} mm, checksum "
                         f"{table.checksum[:12]}...)\n")
    ok = table.kind != "targets" or all(r.status == "ok" for r in table.targets or [])
    return 0 if ok else 1
