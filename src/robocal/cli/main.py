"""The ``robocal`` command line.

Each subcommand lives in its own module ``robocal.cli._<name>`` exposing
``register(subparsers)``; the handler gets the parsed namespace and returns an exit code.
Errors from robocal's exception tree are printed as one line, exit code 2; nothing else
is printed on failure.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from robocal import __version__
from robocal.errors import RobocalError

# (module, is-it-there-yet) -- modules are imported at start-up but keep heavy imports lazy.
_COMMAND_MODULES = (
    "demo", "fit", "predict", "compensate", "table", "plan", "report", "daemon", "campaign",
    "compensation", "sim", "simulate", "robots", "drivers", "config",
)


def build_parser() -> argparse.ArgumentParser:
    """Return the top-level parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog="robocal",
        description="Calibrate industrial robots: measure with a laser tracker, fit constant and "
                    "high-order joint-dependent error models, compensate.",
    )
    parser.add_argument("--version", action="version", version=f"robocal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMAND_MODULES:
        try:
            mod = importlib.import_module(f"robocal.cli._{name}")
        except ModuleNotFoundError as err:
            if err.name == f"robocal.cli._{name}":
                continue
            raise
        mod.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 0 if args.command is None else 2
    try:
        return int(args.handler(args) or 0)
    except RobocalError as err:
        sys.stderr.write(f"robocal {args.command}: error: {err}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write("interrupted\n")
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
