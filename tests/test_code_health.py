"""CI's static checks, run by the test command itself: ruff and mypy (lint-imports runs in
``tests/test_readme.py``). A new lint or type error fails CI like a failing test."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _run(*cmd: str, timeout: float) -> subprocess.CompletedProcess[str]:
    exe = BIN / cmd[0]
    if not exe.exists():
        pytest.fail(f"{cmd[0]} is a test dependency and must be installed")
    return subprocess.run([str(exe), *cmd[1:]], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def test_ruff_is_clean() -> None:
    out = _run("ruff", "check", "--no-cache", "src", "tests", "bench", "tools", timeout=120)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-2000:]


@pytest.mark.slow
def test_mypy_is_clean() -> None:
    out = _run("mypy", timeout=600)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-2000:]
