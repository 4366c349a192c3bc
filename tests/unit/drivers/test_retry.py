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


@pytest.fixture
def sleeps(monkeypatch):
    delays: list[float] = []
    real_sleep = asyncio.sleep

    async def fake_sleep(d):
        delays.append(d)
        await real_sleep(0)

    monkeypatch.setattr("robocal.drivers._retry.asyncio.sleep", fake_sleep)
    return delays


async def test_retries_recoverable_failures_with_backoff(sleeps):
    t = Scripted([BeamLost("b"), Unstable("u"), DriverTimeout("t"), OK])
    r = await measure_with_retry(
        t, samples=5, timeout=2.0, point_id="P1", attempts=4, backoff_s=0.1
    )
    assert r is OK
    assert sleeps == [0.1, 0.2, 0.4]
    assert t.calls == [{"samples": 5, "timeout": 2.0, "point_id": "P1"}] * 4


async def test_gives_up_after_attempts(sleeps):
    t = Scripted([BeamLost("1"), BeamLost("2"), BeamLost("3")])
    with pytest.raises(BeamLost, match="3"):
        await measure_with_retry(
            t, samples=1, timeout=1.0, attempts=3, backoff_s=1.0, max_backoff_s=1.5
        )
    assert sleeps == [1.0, 1.5]


async def test_other_errors_are_not_retried(sleeps):
    t = Scripted([MeasurementError("smr mismatch"), OK])
    with pytest.raises(MeasurementError):
        await measure_with_retry(t, samples=1, timeout=1.0)
    assert len(t.calls) == 1 and sleeps == []


async def test_attempts_must_be_positive():
    with pytest.raises(ValueError):
        await measure_with_retry(Scripted([OK]), samples=1, timeout=1.0, attempts=0)
