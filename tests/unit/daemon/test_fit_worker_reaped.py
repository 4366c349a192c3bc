"""Stopping the fit runner reaps its worker process (no zombie left for init)."""

from __future__ import annotations

import os

import pytest

from robocal.daemon.fitting import FitRunner


def test_shutdown_reaps_the_killed_fit_worker() -> None:
    runner = FitRunner(executor="process", timeout_s=60.0)
    pool = runner._executor()
    pid = pool.submit(os.getpid).result(timeout=60.0)
    assert pid != os.getpid()
    runner.shutdown()
    # reaped: no longer a child of this process, neither running nor a zombie
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)
