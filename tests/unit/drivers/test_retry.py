"""measure_with_retry: recoverable failures retried with backoff."""

from __future__ import annotations

import asyncio

import pytest

from robocal.drivers import TrackerReading, measure_with_retry
from robocal.errors import BeamLost, DriverTimeout, MeasurementError, Unstable

OK = TrackerReading((1.0, 0.0, 0.0), None, 1, None, 0.0)


class Scripted:
    def __init__(self, outcomes):
        self.outcomes = list(outcomes)
        self.calls: list[dict] = []

    async def measure(self, *, samples, timeout, point_id=None):
        self.calls.append({"samples": samples, "timeout": timeout, "point_id": point_id})
        outcome = self.outcomes.pop(0)
        if isinstance(outcome, Exception):
            raise outcome
        return outcome


class RecordingClock:
    """A clock whose sleeps return at once and are recorded (the backoff, in seconds)."""

    def __init__(self):
        self.now = 0.0
        self.delays: list[float] = []

    def monotonic(self):
        return self.now

    async def sleep(self, seconds):
        self.delays.append(seconds)
        self.now += seconds
        await asyncio.sleep(0)


@pytest.fixture
def clock():
    return RecordingClock()


async def test_retries_recoverable_failures_with_backoff(clock):
    t = Scripted([BeamLost("b"), Unstable("u"), DriverTimeout("t"), OK])
    r = await measure_with_retry(
        t, samples=5, timeout=2.0, point_id="P1", attempts=4, backoff_s=0.1, clock=clock
    )
    assert r is OK
    assert clock.delays == [0.1, 0.2, 0.4]
    assert t.calls == [{"samples": 5, "timeout": 2.0, "point_id": "P1"}] * 4


async def test_gives_up_after_attempts(clock):
    t = Scripted([BeamLost("1"), BeamLost("2"), BeamLost("3")])
    with pytest.raises(BeamLost, match="3"):
        await measure_with_retry(
            t, samples=1, timeout=1.0, attempts=3, backoff_s=1.0, max_backoff_s=1.5,
            clock=clock,
        )
    assert clock.delays == [1.0, 1.5]


async def test_other_errors_are_not_retried(clock):
    t = Scripted([MeasurementError("smr mismatch"), OK])
    with pytest.raises(MeasurementError):
        await measure_with_retry(t, samples=1, timeout=1.0, clock=clock)
    assert len(t.calls) == 1 and clock.delays == []


async def test_attempts_must_be_positive():
    with pytest.raises(ValueError):
        await measure_with_retry(Scripted([OK]), samples=1, timeout=1.0, attempts=0)


async def test_with_retry_reports_each_retry_before_waiting(clock):
    """The daemon's per-pose loop runs on with_retry: it counts and reports every retry."""
    from robocal.drivers import with_retry
    from robocal.errors import MeasurementRejected

    t = Scripted([MeasurementRejected("noisy"), BeamLost("b"), OK])
    seen: list[tuple[int, str, float]] = []

    async def operation():
        return await t.measure(samples=1, timeout=1.0)

    r = await with_retry(operation, attempts=5, backoff_s=0.5, backoff_factor=3.0,
                         retry_on=(BeamLost, MeasurementRejected), clock=clock,
                         on_retry=lambda n, err, d: seen.append((n, type(err).__name__, d)))
    assert r is OK
    assert seen == [(1, "MeasurementRejected", 0.5), (2, "BeamLost", 1.5)]
    assert clock.delays == [0.5, 1.5]
