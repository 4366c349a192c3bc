"""Bounded waits for tests: poll a condition until a deadline instead of sleeping a fixed time.

A fixed sleep is either too long (slow suite) or too short under load (flaky test); polling
returns as soon as the condition holds and fails with a clear message when it never does.
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Callable
from typing import Any

__all__ = ["eventually", "eventually_sync"]

#: Poll period, seconds (well below the 50 ms limit on any single sleep in tests).
POLL_S = 0.005


def _fail(what: str | None, pred: Callable[[], Any], timeout: float) -> AssertionError:
    name = what or getattr(pred, "__name__", repr(pred))
    return AssertionError(f"condition not met within {timeout:g} s: {name}")


async def eventually(
    pred: Callable[[], Any],
    timeout: float = 5.0,
    *,
    what: str | None = None,
    interval: float = POLL_S,
) -> Any:
    """Await until ``pred()`` is truthy (it may return an awaitable); return its value.

    Polls every ``interval`` seconds; raises AssertionError when ``timeout`` seconds pass first.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value
        if time.monotonic() > deadline:
            raise _fail(what, pred, timeout)
        await asyncio.sleep(interval)


def eventually_sync(
    pred: Callable[[], Any],
    timeout: float = 5.0,
    *,
    what: str | None = None,
    interval: float = POLL_S,
) -> Any:
    """Block until ``pred()`` is truthy; return its value (AssertionError after ``timeout`` s)."""
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            raise _fail(what, pred, timeout)
        time.sleep(interval)
