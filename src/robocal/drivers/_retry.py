"""Retry of recoverable failures with exponential backoff: the one retry loop of robocal
(:func:`with_retry`), and :func:`measure_with_retry` for a bare tracker."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import TypeVar

import structlog

from robocal._core.clock import SYSTEM_CLOCK, Clock
from robocal.drivers.api import PointMeasurer, TrackerReading
from robocal.errors import BeamLost, DriverTimeout, Unstable

__all__ = ["RETRYABLE", "measure_with_retry", "with_retry"]

_log = structlog.get_logger(__name__)
T = TypeVar("T")

#: Failures worth another try: the beam came back, the target settled, a reply was late.
RETRYABLE: tuple[type[Exception], ...] = (BeamLost, Unstable, DriverTimeout)


async def with_retry(
    operation: Callable[[], Awaitable[T]],
    *,
    attempts: int,
    backoff_s: float = 0.05,
    backoff_factor: float = 2.0,
    max_backoff_s: float = 2.0,
    retry_on: tuple[type[Exception], ...] = RETRYABLE,
    on_retry: Callable[[int, Exception, float], None] | None = None,
    clock: Clock = SYSTEM_CLOCK,
) -> T:
    """Await ``operation()`` until it succeeds, ``attempts`` times at most in total.

    A ``retry_on`` failure is tried again after ``backoff_s``, then ``backoff_s *
    backoff_factor``, ... (capped at ``max_backoff_s``), waited on ``clock``;
    ``on_retry(attempt, error, delay_s)`` is called before each wait. The last failure, and
    any other exception at once, is re-raised.
    """
    if attempts < 1:
        raise ValueError("attempts must be at least 1")
    delay = backoff_s
    for attempt in range(1, attempts + 1):
        try:
            return await operation()
        except retry_on as err:
            if attempt == attempts:
                raise
            if on_retry is not None:
                on_retry(attempt, err, delay)
            await clock.sleep(delay)
            delay = min(delay * backoff_factor, max_backoff_s)
    raise AssertionError("unreachable")  # pragma: no cover


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
    """Measure, retrying ``retry_on`` failures up to ``attempts`` times in total
    (:func:`with_retry`; each retry is logged).

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

    def log(attempt: int, err: Exception, delay: float) -> None:
        _log.info("measurement failed; retrying", point_id=point_id, attempt=attempt,
                  error=type(err).__name__, delay_s=delay)

    async def measure() -> TrackerReading:
        return await tracker.measure(samples=samples, timeout=timeout, point_id=point_id)

    return await with_retry(measure, attempts=attempts, backoff_s=backoff_s,
                            backoff_factor=backoff_factor, max_backoff_s=max_backoff_s,
                            retry_on=retry_on, on_retry=log, clock=clock)
