"""``robocal robots``: list built-in robot descriptions or show one."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from robocal.cli._command import command


def register(sub: Any) -> None:
    """Add the ``robots`` subcommand."""
    p = command(sub, "robots", run)
    p.add_argument("robot", nargs="?",
                   help="built-in name or path to a robot TOML or URDF file")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--from-urdf", metavar="FILE",
                   help="import the serial chain of a URDF file (standard DH) and write it "
                        "as robot TOML")
    p.add_argument("--tip", metavar="LINK",
                   help="with --from-urdf: link ending the chain (default tool0, flange or "
                        "the deepest leaf)")
    p.add_argument("--out", metavar="FILE",
                   help="with --from-urdf: write the TOML here (default: standard output)")


def _from_urdf(args: argparse.Namespace) -> int:
    from robocal._core.files import atomic_write_text
    from robocal.errors import ConfigError
    from robocal.kinematics import load_urdf, robot_to_toml

    if args.robot:
        raise ConfigError("give either a robot or --from-urdf FILE, not both")
    r = load_urdf(args.from_urdf, tip=args.tip)
    text = robot_to_toml(r, header=f"Imported by robocal from {args.from_urdf} (standard DH; "
                                   "lengths mm, angles deg).\nSet tool_mm to the reflector "
                                   "offset from the flange.")
    if args.out:
        atomic_write_text(args.out, text)
        sys.stderr.write(f"wrote {args.out}: {r.name}, {r.dof} joints\n")
    else:
        sys.stdout.write(text)
    return 0


def run(args: argparse.Namespace) -> int:
    """Print the list or one description."""
    from robocal.kinematics import builtin_robots, link_radii, load_robot

    if args.from_urdf:
        return _from_urdf(args)
    if args.tip or args.out:
        from robocal.errors import ConfigError

        raise ConfigError("--tip and --out go with --from-urdf")
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
    radii, source = link_radii(r)
    sys.stdout.write("  link capsule radii [mm] (planner's collision model): "
                     + ", ".join(f"{v * 1e3:.0f}" for v in radii) + f"\n    from {source}\n")
    return 0
