"""The time source of code that waits on time (heartbeats, retry backoff, simulated motion).

Production code uses :data:`SYSTEM_CLOCK` (``time.monotonic`` and ``asyncio.sleep``); tests
pass a clock they advance by hand, so a heartbeat timeout or a backoff is reached without
waiting for it on the wall clock.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol, runtime_checkable

__all__ = ["SYSTEM_CLOCK", "Clock", "SystemClock"]


@runtime_checkable
class Clock(Protocol):
    """A monotonic time source in seconds and a sleep on that same time."""

    def monotonic(self) -> float:
        """Seconds since an arbitrary fixed point; never goes backwards."""
        ...

    async def sleep(self, seconds: float) -> None:
        """Return once ``seconds`` have passed on this clock (at once for ``seconds <= 0``)."""
        ...


class SystemClock:
    """The real clock: ``time.monotonic`` and ``asyncio.sleep``."""

    def monotonic(self) -> float:
        """``time.monotonic()``, seconds."""
        return time.monotonic()

    async def sleep(self, seconds: float) -> None:
        """``asyncio.sleep(seconds)``."""
        await asyncio.sleep(seconds)


#: The default of every ``clock`` argument.
SYSTEM_CLOCK: Clock = SystemClock()
