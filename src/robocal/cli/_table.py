"""``robocal table``: build, check or compare compensation tables.

    robocal table --model MODEL.json --kind targets|joint|frames --out FILE [--targets T.csv]
    robocal table --model MODEL.json --kind vendor --out FILE [--vendor-style generic|ur]
    robocal table --check TABLE.json

Every table is printed with its kind and purpose, checksum, predicted residual and the
nominal residual it is compared with: only ``targets`` compensates the whole model; ``frames``
is base/tool alignment, not compensation; ``joint`` states its bound next to the model's
accuracy and warns when it is far worse. ``vendor`` writes the constant errors as per-joint
zero offsets and DH deltas (see ``docs/compensation-tables.md`` for what they cannot carry).
    robocal table --diff A.json B.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from robocal.cli._command import command


def register(sub: Any) -> None:
    """Add the ``table`` subcommand."""
    p = command(sub, "table", run)
    p.add_argument("--model", metavar="MODEL.json", help="calibrated model")
    p.add_argument("--kind", choices=("targets", "joint", "frames", "vendor"),
                   help="table kind (vendor: zero offsets and DH deltas, not a table)")
    p.add_argument("--vendor-style", choices=("generic", "ur"), default="generic",
                   help="vendor: JSON with zero offsets and DH deltas (generic), or the DH "
                        "deltas as [mounting] arrays like a UR calibration.conf (ur)")
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


def _summary(table: Any) -> dict[str, Any]:
    from robocal.compensation import describe_table

    size = {"targets": len(table.targets or []), "joint": len(table.joints or []),
            "frames": 2}[table.kind]
    d = describe_table(table)
    return {"kind": table.kind, "purpose": d["purpose"], "model_id": table.model_id,
            "robot": table.robot, "entries": size,
            "predicted_residual_mm": table.predicted_residual_mm,
            "nominal_residual_mm": d["nominal_residual_mm"],
            "model_accuracy_mm": d["model_accuracy_mm"], "warnings": d["warnings"],
            "checksum": table.checksum, "stats": table.stats}


def _say(s: dict[str, Any], head: str) -> None:
    """Kind and purpose, checksum, predicted vs nominal residual, model accuracy, warnings."""
    nominal = s["nominal_residual_mm"]
    model = s["model_accuracy_mm"]
    sys.stdout.write(
        f"{head}: {s['kind']} table ({s['purpose']}), {s['entries']} entries, model "
        f"{s['model_id']}, checksum {s['checksum'][:16]}\n"
        f"  predicted residual {s['predicted_residual_mm']:.4f} mm; nominal "
        + ("unknown" if nominal is None else f"{nominal:.4f} mm")
        + ("" if model is None else f"; model accuracy (held-out) {model:.4f} mm") + "\n")
    for w in s["warnings"]:
        sys.stdout.write(f"  warning: {w}\n")


def run(args: argparse.Namespace) -> int:
    """Dispatch on the mode; return the exit code."""
    from robocal.errors import ConfigError

    build_opts = (args.model, args.kind, args.out, args.targets)
    modes = sum([args.check is not None, args.diff is not None, any(build_opts)])
    if modes != 1:
        raise ConfigError("give either --model/--kind/--out, or --check FILE, or --diff A B")
    if args.check:
        return _check(args)
    if args.diff:
        return _diff(args)
    for flag, value in (("--model", args.model), ("--kind", args.kind), ("--out", args.out)):
        if not value:
            raise ConfigError(f"{flag} is required to build a table")
    if args.kind == "vendor":
        return _vendor(args)
    return _build(args)


def _check(args: argparse.Namespace) -> int:
    """``--check``: verify a table file and summarise it."""
    from robocal.compensation import CompensationTable

    s = _summary(CompensationTable.read(args.check))
    if args.json:
        sys.stdout.write(json.dumps(s) + "\n")
    else:
        _say(s, f"{args.check}: checksum ok")
    return 0


def _diff(args: argparse.Namespace) -> int:
    """``--diff A B``: 0 when the tables agree, else 1 with the differences."""
    from robocal.compensation import CompensationTable, diff_tables

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


def _out_path(args: argparse.Namespace) -> Path:
    """``--out`` as a path whose folder exists."""
    from robocal.errors import ConfigError

    out = Path(args.out)
    if out.is_dir() or not out.parent.is_dir():
        raise ConfigError("not a writable file path", source=args.out)
    return out


def _build(args: argparse.Namespace) -> int:
    """Build, write and summarise a targets, joint or frames table."""
    from robocal.compensation import build_table, read_targets_csv
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel

    if args.kind == "targets" and not args.targets:
        raise ConfigError("--kind targets needs --targets TARGETS.csv")
    if args.kind != "targets" and args.targets:
        raise ConfigError(f"--targets is only used with --kind targets, not {args.kind}")
    if not args.interp_tol_deg > 0:
        raise ConfigError(f"--interp-tol-deg must be positive, got {args.interp_tol_deg}")
    if args.samples < 50:
        raise ConfigError(f"--samples must be at least 50, got {args.samples}")
    out = _out_path(args)
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
        _say(s, f"wrote {out}")
    ok = table.kind != "targets" or all(r.status == "ok" for r in table.targets or [])
    return 0 if ok else 1


def _vendor(args: argparse.Namespace) -> int:
    """Write the zero offsets / DH deltas of the model's constant errors."""
    from robocal.compensation import write_vendor_export
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel

    if args.targets:
        raise ConfigError("--targets is only used with --kind targets, not vendor")
    out = _out_path(args)
    cal = CalibratedModel.load(args.model)
    try:
        doc = write_vendor_export(cal, out, style=args.vendor_style)
    except OSError as err:
        raise ConfigError(f"cannot write: {err}", source=str(out)) from err
    if args.json:
        sys.stdout.write(json.dumps(doc) + "\n")
        return 0
    offs = ", ".join(f"J{j['joint']} {j['zero_offset_deg']:+.4f}" for j in doc["joints"])
    sys.stdout.write(
        f"wrote {out} ({args.vendor_style}): zero offsets (deg) {offs}; DH deltas per joint\n"
        f"  zero offsets alone predict {doc['predicted_residual_zero_offsets_only_mm']:.4f} mm "
        f"against {doc['nominal_residual_mm']:.4f} mm nominal; not carried: "
        + "; ".join(doc["not_carried"]) + "\n")
    for w in doc["warnings"]:
        sys.stdout.write(f"  warning: {w}\n")
    return 0
