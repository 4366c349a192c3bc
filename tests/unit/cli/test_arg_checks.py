"""Wrong arguments are answered before the heavy imports (issue 32, item 11).

Timing is measured in bench/bench_arg_errors.py; here: the answer comes without numpy, the
planner or the daemon being imported (a fresh interpreter, so that the check is real).
"""

from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = """
import sys
from robocal.cli.main import main
code = main({argv!r})
heavy = sorted(m for m in ("numpy", "scipy", "robocal.planning", "robocal.daemon.config",
                           "aiohttp", "pydantic") if m in sys.modules)
print("HEAVY", ",".join(heavy))
sys.exit(code)
"""


@pytest.mark.parametrize("argv", [
    ["plan", "--robot", "nosuch", "--cell", "demo", "--count", "30", "--out", "p.json"],
    ["daemon", "--config", "nosuch.toml"],
])
def test_a_wrong_argument_is_reported_before_heavy_imports(tmp_path, argv):
    out = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv)], cwd=tmp_path,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr
    assert out.stderr.count("\n") == 1 and "nosuch" in out.stderr
    assert "HEAVY \n" in out.stdout, out.stdout


def test_a_robot_alias_or_file_passes_the_early_check(tmp_path):
    from robocal._core.robot_names import builtin_robot_key, check_robot_spec
    from robocal.errors import ConfigError

    assert builtin_robot_key("KR210") == "kuka_kr210_r3100"
    assert builtin_robot_key("ur10") == "ur10"
    robot = tmp_path / "arm.toml"
    robot.write_text("")
    check_robot_spec(str(robot))
    check_robot_spec("lrmate200i")
    with pytest.raises(ConfigError, match="not a built-in robot"):
        check_robot_spec(str(tmp_path / "missing.toml"))
