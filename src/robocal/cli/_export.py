"""``robocal export``: a calibrated model in another tool's format (URDF)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from robocal.cli._command import command


def register(sub: Any) -> None:
    """Add the ``export`` subcommand."""
    p = command(sub, "export", run)
    p.add_argument("--model", required=True, help="MODEL.json")
    p.add_argument("--format", choices=("urdf",), default="urdf", help="output format")
    p.add_argument("--out", required=True, help="file to write (atomically), e.g. robot.urdf")
    p.add_argument("--json", action="store_true", help="print a JSON summary")


def side_table_path(out: Path) -> Path:
    """Where the side table of ``out`` goes: next to it, ``<stem>.joint_dependent.json``."""
    return out.with_name(f"{out.stem}.joint_dependent.json")


def run(args: argparse.Namespace) -> int:
    """Export and report what could not be represented."""
    from robocal._core.files import atomic_write_text, json_default
    from robocal.errors import ConfigError
    from robocal.kinematics import CalibratedModel, calibrated_to_urdf

    model = CalibratedModel.load(args.model)
    out = Path(args.out)
    if not out.parent.exists():
        raise ConfigError("directory does not exist", source=str(out.parent))
    text, side = calibrated_to_urdf(model)
    side_path = side_table_path(out)
    side["urdf"] = out.name
    atomic_write_text(out, text)
    atomic_write_text(side_path, json.dumps(side, indent=1, default=json_default) + "\n")
    nr = side["not_representable"]
    summary = {"urdf": str(out), "side_table": str(side_path), "model_id": model.model_id,
               "joint_dependent_terms": len(nr["terms"]),
               "coupled_joints": [c["joint"] for c in nr["joint_couplings"]],
               "fallback_model": nr["fallback_model"]}
    if args.json:
        sys.stdout.write(json.dumps(summary) + "\n")
        return 0
    sys.stdout.write(f"wrote {out} (constant part of model {model.model_id})\n")
    notes = []
    if nr["terms"]:
        notes.append(f"{len(nr['terms'])} joint-dependent terms")
    if nr["joint_couplings"]:
        notes.append("joint couplings (URDF joint value = q_i + c q_j for joints "
                     + ", ".join(str(c["joint"]) for c in nr["joint_couplings"]) + ")")
    if nr["fallback_model"]:
        notes.append("the fallback model")
    if notes:
        sys.stdout.write(f"not representable in URDF, listed in {side_path}: "
                         + "; ".join(notes) + "\n")
    else:
        sys.stdout.write(f"everything is in the URDF; side table {side_path}\n")
    return 0
