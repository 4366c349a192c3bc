"""``robocal fleet report``: every robot in the fleet database (ADR 0035) by serial, with its
last calibration, last check, the checks' drift trend and the active compensation."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from robocal.cli._command import command
from robocal.daemon.fleet import fleet_report


def register(sub: Any) -> None:
    """Add the ``fleet`` subcommand."""
    p = command(sub, "fleet", None)
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    rp = command(verbs, "report", report, parent="fleet")
    rp.add_argument("--url", default=os.environ.get("ROBOCAL_FLEET_URL"),
                    help="PostgreSQL URI, e.g. postgresql://user@host/db?sslmode=verify-full "
                         "(default: $ROBOCAL_FLEET_URL)")
    rp.add_argument("--password-file", type=Path,
                    help="file holding the database password (mode 0600)")
    rp.add_argument("--json", action="store_true", help="print the robots as JSON")


def _mm(v: Any) -> str:
    return f"{v:.4f}" if isinstance(v, int | float) else "-"


def _text(robot: dict[str, Any]) -> str:
    cells = ", ".join(f"{c['cell_name']} (last seen {c['last_seen']})" for c in robot["cells"])
    lines = [f"{robot['robot_serial']}  {robot['robot']}  cells: {cells}"]
    cal = robot["last_calibration"]
    if cal is None:
        lines.append(f"  last calibration: none ({robot['campaigns']} campaigns)")
    else:
        lines.append(f"  last calibration: {cal['at']}  campaign {cal['campaign']} "
                     f"({cal['state']}, model {cal['model']}, held-out RMS "
                     f"{_mm(cal['held_out_rms_mm'])} mm)")
    trend = robot["drift_trend"]
    if not trend:
        lines.append("  last check: no checks yet (no drift trend)")
    else:
        last = trend[-1]
        advice = f"; recommendation: {last['recommendation']}" \
            if last.get("recommendation") else ""
        lines.append(f"  last check: {last['at']}  {last['verdict'] or '-'}  RMS "
                     f"{_mm(last['rms_mm'])} mm{advice}")
        lines.append("  drift trend (RMS mm, oldest first): "
                     + " -> ".join(_mm(t["rms_mm"]) for t in trend))
    act = robot["active_compensation"]
    if act is None:
        lines.append("  active compensation: none pushed by robocal")
    else:
        lines.append(f"  active compensation: table {act['table_id']} ({act['kind']}, "
                     f"{str(act['checksum'])[:16]}, from {act['campaign'] or 'controller'}) "
                     f"since {act['since']}")
    return "\n".join(lines) + "\n"


def report(args: argparse.Namespace) -> int:
    """Print the fleet report."""
    if not args.url:
        sys.stderr.write("robocal fleet report: error: --url (or ROBOCAL_FLEET_URL) is "
                         "required\n")
        return 2
    try:
        robots = fleet_report(args.url, password_file=args.password_file)
    except Exception as err:  # psycopg's errors: the database is out of reach or refuses
        if type(err).__module__.split(".")[0] != "psycopg":
            raise
        sys.stderr.write(f"robocal fleet report: error: {err}\n")
        return 2
    if args.json:
        sys.stdout.write(json.dumps(robots, indent=2, default=str) + "\n")
        return 0
    if not robots:
        sys.stdout.write("no robots in the fleet database yet\n")
    for r in robots:
        sys.stdout.write(_text(r))
    return 0
