"""Retry of recoverable tracker failures with exponential backoff."""

from __future__ import annotations

import structlog

from robocal._core.clock import SYSTEM_CLOCK, Clock
from robocal.drivers.api import PointMeasurer, TrackerReading
from robocal.errors import BeamLost, DriverTimeout, Unstable

__all__ = ["RETRYABLE", "measure_with_retry"]

_log = structlog.get_logger(__name__)

#: Failures worth another try: the beam came back, the target settled, a reply was late.
RETRYABLE: tuple[type[Exception], ...] = (BeamLost, Unstable, DriverTimeout)


async def measure_with_retry(
    tracker: PointMeasurer,
    *,
    samples: int,
    timeout: float,
    point_id: str | None = None,
    attempts: int = 4,
    backoff_s: float = 0.05,
    backoff_factor: float = 2.0,
    max_backoff_s: float = 2.0,
    retry_on: tuple[type[Exception], ...] = RETRYABLE,
    clock: Clock = SYSTEM_CLOCK,
) -> TrackerReading:
    """Measure, retrying ``retry_on`` failures up to ``attempts`` times in total.

    Waits ``backoff_s``, then ``backoff_s * backoff_factor``, ... (capped at
    ``max_backoff_s``) between attempts. The last failure is re-raised.

    Parameters
    ----------
    tracker : PointMeasurer
        A connected tracker driver.
    samples, timeout, point_id
        Passed to ``tracker.measure`` (``timeout`` in seconds, per attempt).
    attempts : int
        Total number of attempts (at least 1).
    clock : Clock, optional
        Whose ``sleep`` waits out the backoff (default: the system clock).
    """
    if attempts < 1:
        raise ValueError("attempts must be at least 1")
    delay = backoff_s
    for attempt in range(1, attempts + 1):
        try:
            return await tracker.measure(samples=samples, timeout=timeout, point_id=point_id)
        except retry_on as err:
            if attempt == attempts:
                raise
            _log.info(
                "measurement failed; retrying",
                point_id=point_id,
                attempt=attempt,
                error=type(err).__name__,
                delay_s=delay,
            )
            await clock.sleep(delay)
            delay = min(delay * backoff_factor, max_backoff_s)
    raise AssertionError("unreachable")  # pragma: no cover
