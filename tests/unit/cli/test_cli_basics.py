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
