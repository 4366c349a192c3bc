"""The command line: help lists the commands, errors are one line with a non-zero exit."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from robocal.cli.main import main


def test_help_lists_commands(capsys: pytest.CaptureFixture[str]) -> None:
    """``--help`` lists every subcommand of main.COMMANDS with its line, and COMMANDS names
    every module of robocal.cli that registers a subcommand."""
    import robocal.cli
    from robocal.cli.main import COMMANDS, command_module

    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert re.findall(r"^    (\S+)", out, flags=re.MULTILINE) == list(COMMANDS)
    flat = " ".join(out.split())  # long names wrap their help line
    for name, text in COMMANDS.items():
        assert f" {name} {text} " in flat
    modules = {f"robocal.cli.{f.stem}" for f in Path(robocal.cli.__path__[0]).glob("_*.py")
               if "\ndef register(" in f.read_text(encoding="utf-8")}
    assert modules == {command_module(name) for name in COMMANDS}


def test_a_subcommand_that_fails_to_import_is_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    from robocal.cli.main import build_parser

    monkeypatch.setitem(sys.modules, "robocal.cli._robots", None)  # import raises ImportError
    with pytest.raises(ImportError, match=r"robocal\.cli\._robots"):
        build_parser()
    with pytest.raises(ImportError, match=r"robocal\.cli\._robots"):
        main(["robots"])


def test_demo_planner_failure_is_a_one_line_error(tmp_path, monkeypatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """No fallback to random poses: the demo stops with the planner's error, exit 2."""
    import robocal.planning
    from robocal.errors import ConfigError

    def no_plan(*args: object, **kwargs: object) -> None:
        raise ConfigError("no feasible poses in the cell")

    monkeypatch.setattr(robocal.planning, "plan_campaign", no_plan)
    assert main(["demo", "--out", str(tmp_path / "demo"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err == "robocal demo: error: no feasible poses in the cell\n"
    assert not (tmp_path / "demo" / "PLAN.json").exists()


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

    from robocal._core.model_names import DEFAULT_MODEL
    from robocal.cli._defaults import default_validation

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


def _loaded_after(imports: list[str], heavy: list[str]) -> list[str]:
    """Which of ``heavy`` a fresh interpreter has loaded after importing ``imports``."""
    src = (f"import json, sys, {', '.join(imports)}\n"
           f"print(json.dumps(sorted(m for m in {heavy!r} if m in sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", src], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return list(json.loads(out.stdout.strip().splitlines()[-1]))


def test_light_packages_leave_heavy_modules_unimported() -> None:
    """Why robocal.daemon and robocal.report keep lazy attributes: the client commands import
    robocal.daemon for its light modules, the configuration check robocal.report for
    Acceptance; neither may pull in the service, the planner or the report's figures."""
    assert _loaded_after(["robocal.daemon.client", "robocal.report"],
                         ["robocal.daemon.service", "robocal.daemon._plan", "robocal.daemon.main",
                          "robocal.report._write", "robocal.report._figures"]) == []


def test_the_campaign_report_reads_its_rows_without_the_daemons_logging() -> None:
    """``robocal report CAMPAIGN`` imports what input_from_campaign needs (store, config, the
    rows helpers of robocal.daemon.fitting) and the report writer; structlog (with rich,
    ~0.07 s) and asyncio (~0.02 s) are the daemon's and stay unimported."""
    assert _loaded_after(["robocal.cli._report", "robocal.daemon.fitting", "robocal.daemon.store",
                          "robocal.daemon.config", "robocal.report._write"],
                         ["structlog", "rich", "matplotlib", "asyncio"]) == []


def test_every_verb_has_a_description_and_no_empty_default_is_shown() -> None:
    from robocal.cli.main import build_parser

    for path, p in _parsers(build_parser()):
        if len(path) >= 1:
            assert p.description, f"robocal {' '.join(path)}: no description in --help"
        assert "(default: )" not in p.format_help(), f"robocal {' '.join(path)}"


@pytest.mark.parametrize(("typed", "meant"), [("fitt", "'fit'"), ("campaing", "'campaign'"),
                                              ("simualte", "'simulate'")])
def test_a_misspelt_command_gets_a_suggestion(capsys: pytest.CaptureFixture[str], typed: str,
                                              meant: str) -> None:
    assert main([typed, "--data", "x.csv"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"unknown command '{typed}'; did you mean {meant}" in err
    assert main(["zzzz"]) == 2
    assert "did you mean" not in capsys.readouterr().err


def test_state_errors_are_plain_english() -> None:
    from robocal.daemon.campaign import check_transition
    from robocal.errors import InvalidTransition

    with pytest.raises(InvalidTransition) as info:
        check_transition("paused", "paused")
    assert str(info.value).startswith("the campaign is already paused")
    with pytest.raises(InvalidTransition) as info:
        check_transition("measured", "approved")
    assert "a campaign that is measured cannot be approved" in str(info.value)
    assert "cannot go from" not in str(info.value)


def test_sim_simulate_and_demo_agree_on_scenarios_and_seed(capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    """One scenario list and one seed default; sim --help shows defaults and units."""
    from robocal.simulation import SCENARIOS

    with pytest.raises(SystemExit):
        main(["sim", "--help"])
    sim = " ".join(capsys.readouterr().out.split())
    assert "1000x faster than real time" in sim and "(default: 0.001)" in sim
    assert "(default: None)" not in sim and "(default: False)" not in sim
    assert "{" + ",".join(SCENARIOS) + "}" in sim and "(default: 1)" in sim
    for cmd in ("simulate", "demo", "plan"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "default 1, as" in text, cmd
        if cmd != "plan":
            assert all(s in text for s in SCENARIOS), cmd
