"""``robocal robots``: list built-in robot descriptions or show one."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any


def register(sub: Any) -> None:
    """Add the ``robots`` subcommand."""
    p = sub.add_parser("robots", help="list built-in robots, or show/validate one",
                       description="List built-in robot descriptions, or show one (by name or "
                                   "TOML file) after validation.")
    p.add_argument("robot", nargs="?", help="built-in name or path to a robot TOML file")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Print the list or one description."""
    from robocal.kinematics import builtin_robots, load_robot

    if not args.robot:
        names = builtin_robots()
        if args.json:
            sys.stdout.write(json.dumps(names) + "\n")
        else:
            for n in names:
                r = load_robot(n)
                sys.stdout.write(f"{n:22s} {r.name} ({r.dof} joints)\n")
        return 0
    r = load_robot(args.robot)
    if args.json:
        sys.stdout.write(json.dumps(r.to_dict(), indent=1) + "\n")
        return 0
    sys.stdout.write(f"{r.name}  ({r.manufacturer or 'unknown maker'}, {r.dof} joints)\n")
    sys.stdout.write("  j   a[mm]    d[mm]  alpha[deg] offset[deg]   min[deg]  max[deg]  gear\n")
    for i, j in enumerate(r.joints, 1):
        sys.stdout.write(
            f"  {i} {j.a * 1e3:8.2f} {j.d * 1e3:8.2f} {math.degrees(j.alpha):10.2f} "
            f"{math.degrees(j.theta_offset):10.2f} {math.degrees(j.q_min):10.1f} "
            f"{math.degrees(j.q_max):9.1f}  {j.gear_ratio or '-'}\n")
    return 0
