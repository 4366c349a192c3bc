"""The ``robocal`` command line.

Each subcommand lives in its own module ``robocal.cli._<name>`` exposing
``register(subparsers)`` and is listed in :data:`COMMANDS`; the handler gets the parsed
namespace and returns an exit code.
Errors from robocal's exception tree are printed as one line, exit code 2; nothing else
is printed on failure.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from robocal.errors import RobocalError

# Every subcommand with its one-line help, in the order ``--help`` lists them. Only the
# module of the command being run is imported (``robocal --help`` and ``robocal fit`` stay
# fast); a test checks that these lines equal the ones each module registers.
COMMANDS: dict[str, str] = {
    "demo": "run a whole calibration campaign against simulators",
    "fit": "fit an error model to tracker measurements",
    "predict": "predict reflector positions with a calibrated model",
    "export": "export a calibrated model (URDF with a side table)",
    "compensate": "corrected joint commands for program targets",
    "table": "build, check or compare compensation tables",
    "plan": "choose, check and order measurement poses; write PLAN.json",
    "report": "write the HTML calibration report (and a JSON summary)",
    "daemon": "run the calibration daemon (systemd Type=notify)",
    "campaign": "start, watch and control campaigns on the daemon",
    "compensation": "list pushed compensation tables or roll back",
    "sim": "run the robot/tracker simulators or the emScon relay",
    "simulate": "write MEAS.csv files measured on the virtual robot",
    "robots": "list built-in robots, or show/validate one",
    "drivers": "list installed drivers or show a driver's options",
    "config": "check a daemon configuration or print its schema",
    "fleet": "report on the robots in the shared fleet database",
    "check": "run a drift check of the active model, or show the checks",
}


# Modules whose name is not ``_<command>``: the commands' own names are near-namesakes
# (compensate / compensation, sim / simulate), the modules say what they do (ADR 0038).
_MODULES: dict[str, str] = {
    "compensate": "_solve_targets",
    "compensation": "_controller_compensation",
    "sim": "_simulators",
    "simulate": "_simulated_measurements",
}


def command_module(name: str) -> str:
    """The module that registers the subcommand ``name``."""
    return f"robocal.cli.{_MODULES.get(name, '_' + name)}"


class _HelpFormatter(argparse.HelpFormatter):
    """Shows every option's default where the help text does not already state it."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (not action.option_strings or "default" in text or default is None
                or default is argparse.SUPPRESS or isinstance(default, bool)
                or default == [] or default == ""):
            return text
        return f"{text} (default: %(default)s)"


class _Parser(argparse.ArgumentParser):
    """Every (sub)command parser: the help formatter above."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]


class _Version(argparse.Action):
    """``--version``, resolved only when asked (reading package metadata is not free)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS, help: str = "show the version and exit"
                 ) -> None:
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: str | None = None) -> None:
        import robocal

        sys.stdout.write(f"robocal {robocal.__version__}\n")
        parser.exit()


def _first_word(argv: Sequence[str]) -> str | None:
    """The first argument that is not an option (the command as typed), or None."""
    for a in argv:
        if a == "--":
            return None
        if not a.startswith("-"):
            return a
    return None


def _unknown_command(word: str) -> int:
    """One line for a misspelt command, with the closest commands (exit 2)."""
    import difflib

    close = difflib.get_close_matches(word, COMMANDS, n=3, cutoff=0.6)
    hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
    sys.stderr.write(f"robocal: error: unknown command {word!r}{hint} (robocal --help lists "
                     "the commands)\n")
    return 2


def _command_of(argv: Sequence[str]) -> str | None:
    """The subcommand named in ``argv`` (top-level options take no values), or None."""
    word = _first_word(argv)
    return word if word in COMMANDS else None


def build_parser(only: str | None = None, *, lazy: bool = False) -> argparse.ArgumentParser:
    """Return the top-level parser.

    With ``lazy`` false every subcommand module is imported and registered (an import error
    propagates: no command is dropped silently). With ``lazy`` true only ``only`` is imported
    and registered, alone (argparse parsers cost ~0.6 ms each); without ``only`` every command
    is listed with its help line and no arguments, for ``--help`` and the error on a
    misspelt command.
    """
    parser = _Parser(
        prog="robocal",
        description="Calibrate industrial robots: measure with a laser tracker, fit constant and "
                    "high-order joint-dependent error models, compensate.",
    )
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, text in COMMANDS.items():
        if lazy and only is not None and name != only:
            continue
        if lazy and name != only:
            sub.add_parser(name, help=text, add_help=False)
            continue
        importlib.import_module(command_module(name)).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the process exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    word = _first_word(argv)
    if word is not None and word not in COMMANDS:
        return _unknown_command(word)
    parser = build_parser(_command_of(argv), lazy=True)
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
