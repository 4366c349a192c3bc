"""Declarative registration of a subcommand or verb (ADR 0045).

The texts live in ``robocal/data/commands.toml`` (each subcommand's description, each verb's
help line and description; a subcommand's help line is its line of
:data:`robocal.cli.main.COMMANDS`), so a module's ``register`` says only which handler and
which arguments a command has.
"""

from __future__ import annotations

import argparse
import functools
from collections.abc import Callable
from importlib import resources
from typing import Any

from robocal._core.files import read_toml

Handler = Callable[[argparse.Namespace], int]


@functools.cache
def _texts() -> dict[str, Any]:
    return read_toml(resources.files("robocal.data") / "commands.toml")


def command(sub: Any, name: str, run: Handler | None, *, parent: str | None = None,
            **defaults: Any) -> argparse.ArgumentParser:
    """Add the subcommand ``name`` (or, with ``parent``, that subcommand's verb ``name``) to
    the subparsers ``sub`` with its texts and the handler ``run`` (None: the verbs below it
    have theirs); ``defaults`` go into the parsed namespace too."""
    if parent is None:
        from robocal.cli.main import COMMANDS

        help, description = COMMANDS[name], _texts()[name]["description"]
    else:
        verb = _texts()[parent][name]
        help, description = verb["help"], verb["description"]
    p: argparse.ArgumentParser = sub.add_parser(name, help=help, description=description)
    if run is not None:
        p.set_defaults(handler=run, **defaults)
    return p


def seed(text: str) -> int:
    """argparse type of a ``--seed``: a non-negative integer (numpy's generators refuse
    negative seeds with a traceback)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid integer {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {value}")
    return value
