"""The command line: help lists the commands, errors are one line with a non-zero exit."""

from __future__ import annotations

import subprocess
import sys

import pytest

from robocal.cli.main import main


def test_help_lists_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for cmd in ("robots", "drivers"):
        assert cmd in out


def test_robots_and_drivers(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["robots"]) == 0
    assert "ur10" in capsys.readouterr().out
    assert main(["drivers", "--json"]) == 0
    assert "fanuc_rmi" in capsys.readouterr().out
    assert main(["drivers", "fanuc_rmi"]) == 0
    assert "joint_limits_deg" in capsys.readouterr().out


def test_errors_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["robots", "no-such-robot.toml"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no-such-robot.toml" in err
    assert main(["drivers", "warp-drive"]) == 2
    assert "warp-drive" in capsys.readouterr().err


def test_python_dash_m() -> None:
    out = subprocess.run([sys.executable, "-m", "robocal", "--version"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith("robocal ")


def test_commands_share_their_defaults(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    """One default model and one default validation count across simulate, plan and fit."""
    import json

    from robocal.cli._defaults import DEFAULT_MODEL, default_validation

    meas = tmp_path / "m.csv"
    assert main(["simulate", "--scenario", "constant", "--poses", "60", "--out", str(meas)]) == 0
    out = capsys.readouterr().out
    assert f"({default_validation(60)} poses)" in out          # m-val.csv: a fifth, >= 10
    model = tmp_path / "model.json"
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--out",
                 str(model)]) == 0
    capsys.readouterr()
    assert json.loads(model.read_text())["fit"]["model"] == DEFAULT_MODEL
    plan = tmp_path / "plan.json"
    assert main(["plan", "--robot", "fanuc_lrmate200i", "--cell", "demo", "--count", "80",
                 "--candidates", "256", "--no-iso", "--out", str(plan), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["by_purpose"]["validation"] == default_validation(80)
    assert json.loads(plan.read_text())["model"]["name"] == DEFAULT_MODEL


def test_version_comes_from_the_package_metadata() -> None:
    from importlib.metadata import version

    import robocal

    assert robocal.__version__ == version("robocal")


def _parsers(parser, path=()):
    """Every (sub)command parser with its command path."""
    import argparse

    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


def test_every_command_verb_and_option_is_explained() -> None:
    """Help text for every sub-verb and option; defaults shown where there is one."""
    import argparse

    from robocal.cli.main import COMMANDS, build_parser

    parser = build_parser()
    seen = set()
    for path, p in _parsers(parser):
        seen.add(path[:1])
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for choice in action._choices_actions:
                    assert choice.help, f"robocal {' '.join(path)} {choice.dest}: no help"
                continue
            if action.option_strings and action.help != argparse.SUPPRESS:
                assert action.help, f"robocal {' '.join(path)} {action.option_strings}: no help"
        text = p.format_help()
        for action in p._actions:
            if (action.option_strings and isinstance(action.default, int | float | str)
                    and not isinstance(action.default, bool) and action.default != ""
                    and action.default is not argparse.SUPPRESS):
                assert "default" in (action.help or "") or "(default:" in text, \
                    f"robocal {' '.join(path)} {action.option_strings}: default not shown"
    assert {p[0] for p in seen if p} == set(COMMANDS)


def test_version_option(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out == f"robocal {version('robocal')}\n"
