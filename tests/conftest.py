"""Shared fixtures: seeded RNGs, the location of the shared datasets, and leak checks."""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import threading
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import numpy as np
import pytest
import pytest_asyncio
from hypothesis import HealthCheck, settings

# Hypothesis' per-example deadline and its "input generation is slow" health check measure
# wall time: the suite runs one process per core on a 2-core machine, where a neighbour's fit
# can stall a worker for a second (a fresh clone's run failed a codec round-trip test that way)
settings.register_profile("robocal", deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("robocal")

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATASET = SHARED / "datasets" / "ipa-ur10-lasertracker"


#: Outcomes of the tests marked ``dataset`` (real UR10 data), counted in the controlling
#: process (xdist workers send their reports there).
_DATASET_OUTCOMES: dict[str, int] = {"passed": 0, "failed": 0, "skipped": 0}


def _dataset_present() -> bool:
    return (DATASET / "Series_C").is_dir()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if "dataset" not in report.keywords:
        return
    if report.when == "call" or (report.when == "setup" and report.outcome != "passed"):
        _DATASET_OUTCOMES[report.outcome] += 1


@pytest.hookimpl(tryfirst=True)
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """A real-data test skipped while the data set is there is a failure of the run: the
    acceptance figures on real data would silently not have been checked."""
    if (_dataset_present() and _DATASET_OUTCOMES["skipped"]
            and exitstatus == pytest.ExitCode.OK):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter, exitstatus: int,
                            config: pytest.Config) -> None:
    ran, skipped = (_DATASET_OUTCOMES["passed"] + _DATASET_OUTCOMES["failed"],
                    _DATASET_OUTCOMES["skipped"])
    if not ran and not skipped:
        return
    where = f"data set {'present' if _dataset_present() else 'absent'} at {DATASET}"
    line = f"real-data tests: {ran} ran, {skipped} skipped ({where})"
    if _dataset_present() and skipped:
        terminalreporter.write_line(line + ": FAILED, the data set is present but tests "
                                    "that need it were skipped", red=True)
    else:
        terminalreporter.write_line(line)


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator, fresh per test."""
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def dataset_dir() -> Path:
    """The IPA UR10 dataset directory; skips the test when it is absent."""
    if not _dataset_present():
        pytest.skip(f"dataset not found at {DATASET}")
    return DATASET


#: How long leftover tasks and threads get to finish after a test before they count as leaked.
LEAK_GRACE_S = 1.0


def _leaked_threads(before: set[threading.Thread]) -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t not in before and not t.daemon and t.is_alive()]


def _fail_on_leaked_threads(before: set[threading.Thread]) -> None:
    deadline = time.monotonic() + LEAK_GRACE_S
    while _leaked_threads(before) and time.monotonic() < deadline:
        time.sleep(0.005)
    left = _leaked_threads(before)
    if left:
        pytest.fail(f"test left non-daemon thread(s) running: {left}", pytrace=False)


@pytest_asyncio.fixture
async def _no_leaked_tasks_or_threads() -> AsyncIterator[None]:
    """Fail an async test that leaves tasks pending on its loop, or threads running."""
    threads_before = set(threading.enumerate())
    tasks_before = asyncio.all_tasks()
    yield
    current = asyncio.current_task()

    def pending() -> list[asyncio.Task[object]]:
        return [t for t in asyncio.all_tasks() - tasks_before if t is not current and not t.done()]

    deadline = time.monotonic() + LEAK_GRACE_S
    while pending() and time.monotonic() < deadline:
        await asyncio.sleep(0.005)
    left = pending()
    if left:
        for t in left:
            t.cancel()
        await asyncio.wait(left, timeout=LEAK_GRACE_S)
        pytest.fail(f"test left {len(left)} asyncio task(s) pending: {left}", pytrace=False)
    # The loop's default executor (asyncio.to_thread) belongs to the loop: join its idle
    # workers as asyncio.run would, so only threads still busy after the grace count.
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(LEAK_GRACE_S):
            await asyncio.get_running_loop().shutdown_default_executor()
    _fail_on_leaked_threads(threads_before)


@pytest.fixture(autouse=True)
def _no_leaks(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail a test that leaves non-daemon threads running, or (async tests) tasks pending."""
    if inspect.iscoroutinefunction(getattr(request, "function", None)):
        # Checked inside the test's loop, before the loop and its executor are closed.
        request.getfixturevalue("_no_leaked_tasks_or_threads")
        yield
        return
    before = set(threading.enumerate())
    yield
    _fail_on_leaked_threads(before)


@pytest.fixture(scope="session")
def postgres() -> Iterator[object]:
    """A throw-away PostgreSQL server (tests/_postgres.py); skipped without its binaries."""
    from tests._postgres import postgres_server

    with postgres_server() as server:
        if isinstance(server, str):
            pytest.skip(server)
        yield server
