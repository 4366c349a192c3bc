"""``robocal sim ...``: run the protocol simulators (a thin wrapper of robocal.drivers.sim)."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    """Add the ``sim`` subcommand; every argument goes to ``robocal.drivers.sim.main``."""
    p = sub.add_parser("sim", help="run the robot/tracker simulators or the emScon relay",
                       description="Run protocol simulators on loopback until SIGTERM/SIGINT, "
                                   "e.g. 'robocal sim all --ports-file ports.json' "
                                   "(options: 'robocal sim --help').",
                       add_help=False, prefix_chars="+")  # every "-..." is the sim's
    p.add_argument("sim_args", nargs=argparse.REMAINDER, help="simulator arguments")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Hand over to the simulators' own command line."""
    from robocal.drivers.sim import main

    return main(list(args.sim_args) or ["--help"])
