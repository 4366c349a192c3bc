"""``robocal drivers``: list installed robot and tracker drivers, or show one's options."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Literal

from robocal.cli._command import command


def register(sub: Any) -> None:
    """Add the ``drivers`` subcommand."""
    p = command(sub, "drivers", run)
    p.add_argument("kind", nargs="?", help="driver name, e.g. fanuc_rmi or ltp")
    p.add_argument("--role", choices=("robot", "tracker"), default=None,
                   help="which group to look in (default: robots, then trackers)")
    p.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    """List drivers, or print one driver's options as JSON schema."""
    from robocal.drivers import available, driver_class
    from robocal.errors import DriverNotFound

    names = available()
    if not args.kind:
        if args.json:
            sys.stdout.write(json.dumps(names) + "\n")
        else:
            sys.stdout.write("robots:   " + ", ".join(names["robots"]) + "\n")
            sys.stdout.write("trackers: " + ", ".join(names["trackers"]) + "\n")
        return 0
    roles: list[Literal["robot", "tracker"]] = [args.role] if args.role else ["robot", "tracker"]
    last: DriverNotFound | None = None
    for role in roles:
        try:
            cls = driver_class(args.kind, role=role)
        except DriverNotFound as err:
            last = err
            continue
        schema = cls.Options.model_json_schema()
        if args.json:
            sys.stdout.write(json.dumps({"kind": args.kind, "role": role,
                                         "options": schema}, indent=1) + "\n")
        else:
            sys.stdout.write(f"{args.kind} ({role} driver, {cls.__module__}.{cls.__name__})\n")
            req = set(schema.get("required", []))
            for key, prop in schema.get("properties", {}).items():
                default = "" if key in req else f" = {prop.get('default')!r}"
                mark = " (required)" if key in req else ""
                sys.stdout.write(f"  {key}{default}{mark}\n")
        return 0
    assert last is not None
    if args.role:
        raise last
    raise DriverNotFound(f"no driver named {args.kind!r} (robots: {', '.join(names['robots'])}; "
                         f"trackers: {', '.join(names['trackers'])})")
