"""The subcommands' and verbs' texts in robocal/data/commands.toml (ADR 0045): each one is
the description (and a verb's help line) of a registered parser, and none is left over."""

from __future__ import annotations

import argparse
import tomllib
from importlib import resources

from robocal.cli.main import COMMANDS, build_parser


def _subparsers(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def test_every_text_is_a_registered_parsers_and_none_is_left_over() -> None:
    texts = tomllib.loads((resources.files("robocal.data") / "commands.toml").read_text())
    used: set[tuple[str, ...]] = set()
    for name, p in _subparsers(build_parser()).items():
        entry = texts.get(name)
        if entry is None:  # a command of its own kind (sim hands its arguments on)
            assert name == "sim"
            continue
        assert p.description == entry["description"]
        used.add((name,))
        helps = {choice.dest: choice.help for action in p._actions
                 if isinstance(action, argparse._SubParsersAction)
                 for choice in action._choices_actions}
        for verb, vp in _subparsers(p).items():
            assert vp.description == entry[verb]["description"]
            assert helps[verb] == entry[verb]["help"]
            used.add((name, verb))
    listed = {(k,) for k in texts} | {(k, v) for k, t in texts.items() for v, e in t.items()
                                      if isinstance(e, dict)}
    assert listed == used
    assert {n for (n, *_) in used} == set(COMMANDS) - {"sim"}
