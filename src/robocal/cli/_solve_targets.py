"""``robocal compensate``: corrected joint commands for program targets.

    robocal compensate --model MODEL.json --targets TARGETS.csv --out JOINTS.csv

Reads the model and the targets (see ``robocal.compensation._targets`` for TARGETS.csv),
solves every target under the model and writes JOINTS.csv (``q1..qN`` deg, ``status``,
``model_residual_mm``) atomically. Exit codes: 0 every target solved, 1 some targets did not
(the file is still written, their joint cells empty), 2 bad input (nothing written).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from robocal.cli._command import command


def register(sub: Any) -> None:
    """Add the ``compensate`` subcommand."""
    p = command(sub, "compensate", run)
    p.add_argument("--model", required=True, metavar="MODEL.json", help="calibrated model")
    p.add_argument("--targets", required=True, metavar="TARGETS.csv", help="program targets")
    p.add_argument("--out", required=True, metavar="JOINTS.csv", help="output file")
    p.add_argument("--table", metavar="TABLE.json",
                   help="also write a sealed 'targets' compensation table")
    p.add_argument("--start", choices=("auto", "nominal", "seed"), default="auto",
                   help="where the iteration starts (default: nominal IK where the robot has "
                        "a closed form, else the seed)")
    p.add_argument("--tol-um", type=float, default=0.1,
                   help="position tolerance under the model, micrometres (default 0.1)")
    p.add_argument("--max-iter", type=int, default=20, help="iteration limit (default 20)")
    p.add_argument("--temps", metavar="T1,...,TN",
                   help="joint temperatures (degC, one per joint) to compensate for: the "
                        "model's thermal term is applied at them (default: the model's "
                        "reference temperatures)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _check_out(path: str, what: str) -> Path:
    from robocal.errors import ConfigError

    out = Path(path)
    if out.is_dir():
        raise ConfigError(f"{what} is a directory", source=path)
    if not out.parent.is_dir():
        raise ConfigError(f"{what}: directory {str(out.parent)!r} does not exist", source=path)
    return out


def _temperatures(text: str, cal: Any) -> list[float] | None:
    """``--temps``: one temperature per joint; ``cal`` is replaced in the caller by the model
    at them. None (with a note on stderr) when the model has no thermal term."""
    from robocal._core.thermal import TEMPERATURE_RANGE_C
    from robocal.errors import ConfigError
    from robocal.identification import thermal_term

    lo, hi = TEMPERATURE_RANGE_C
    try:
        temps = [float(v) for v in text.split(",")]
    except ValueError:
        raise ConfigError(f"--temps must be {cal.robot.dof} numbers separated by commas "
                          f"(degC), got {text!r}") from None
    if len(temps) != cal.robot.dof or not all(lo <= v <= hi for v in temps):
        raise ConfigError(f"--temps must be {cal.robot.dof} temperatures between {lo:g} and "
                          f"{hi:g} degC, got {text!r}")
    if thermal_term(cal) is None:
        sys.stderr.write("note: the model has no thermal term; --temps changes nothing\n")
        return None
    return temps


def run(args: argparse.Namespace) -> int:
    """Compensate the targets; return the exit code."""
    import numpy as np

    from robocal._core.files import atomic_write_text
    from robocal.compensation import (
        compensate,
        compensated_joints_csv_text,
        read_targets_csv,
        targets_table,
    )
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel

    if not args.tol_um > 0:
        raise ConfigError(f"--tol-um must be positive, got {args.tol_um}")
    if args.max_iter < 1:
        raise ConfigError(f"--max-iter must be at least 1, got {args.max_iter}")
    out = _check_out(args.out, "--out")
    table_out = _check_out(args.table, "--table") if args.table else None
    cal = CalibratedModel.load(args.model)
    temps = _temperatures(args.temps, cal) if args.temps is not None else None
    if temps is not None:
        from robocal.identification import at_temperatures

        model_id = cal.model_id
        cal = at_temperatures(cal, temps)
        cal.model_id = model_id      # tables and summaries name the model as approved
    targets = read_targets_csv(args.targets, dof=cal.robot.dof)
    opts = {"start": args.start, "tol_m": args.tol_um * 1e-6, "max_iter": args.max_iter}
    res = compensate(cal, targets.p, targets.q_seed, R_targets=targets.R, **opts)
    text = compensated_joints_csv_text(res, targets)
    table = targets_table(cal, targets, res) if table_out is not None else None
    if table is not None and temps is not None:
        table = table.with_temperatures(temps)
    try:
        atomic_write_text(out, text)
        if table is not None and table_out is not None:
            table.write(table_out)
    except OSError as err:
        raise ConfigError(f"cannot write: {err}", source=str(out)) from err
    counts = res.counts()
    ok = res.ok
    summary: dict[str, Any] = {
        "targets": len(res), **counts,
        "max_model_residual_um": float(res.residual_m[ok].max() * 1e6) if ok.any() else None,
        "max_iterations": int(res.iterations.max()) if len(res) else 0,
        "outside_coverage": int(np.sum(ok & ~res.in_coverage)),
        "model_id": cal.model_id, "out": str(out),
        "temperatures_c": temps,
    }
    if table is not None:
        from robocal.compensation import describe_table

        d = describe_table(table)
        summary["table"] = {k: d[k] for k in ("kind", "checksum", "predicted_residual_mm",
                                              "nominal_residual_mm", "model_accuracy_mm",
                                              "warnings")}
    if args.json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        failed = ", ".join(f"{v} {k}" for k, v in counts.items() if k != "ok" and v)
        resid = summary["max_model_residual_um"]
        sys.stdout.write(
            f"compensated {len(res)} targets with model {cal.model_id}: {counts['ok']} ok"
            + (f", {failed}" if failed else "")
            + (f"; max model residual {resid:.3f} um" if resid is not None else "")
            + (f"; {summary['outside_coverage']} outside the calibrated range"
               if summary["outside_coverage"] else "")
            + (f"; at {', '.join(f'{v:g}' for v in temps)} degC" if temps else "")
            + f"; wrote {out}\n")
        if table is not None:
            from robocal.compensation import summary_line

            sys.stdout.write(f"wrote {table_out}: {summary_line(table)} (nominal at the seed "
                             "joints)\n")
    return 0 if counts["ok"] == len(res) else 1
