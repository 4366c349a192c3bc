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
