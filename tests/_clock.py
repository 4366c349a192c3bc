"""A :class:`robocal._core.clock.Clock` that only moves when a test advances it."""

from __future__ import annotations

import asyncio


class ManualClock:
    """Monotonic time that stands still until :meth:`advance`; sleepers wake when it passes them.

    ``sleepers`` counts the coroutines currently asleep on this clock, so a test can wait
    (with :func:`tests._waiting.eventually`) until the code under test is idle again.
    """

    def __init__(self, start: float = 1000.0) -> None:
        self._now = start
        self._waiting: list[tuple[float, asyncio.Future[None]]] = []

    def monotonic(self) -> float:
        """The current time, seconds."""
        return self._now

    async def sleep(self, seconds: float) -> None:
        """Return once the clock has been advanced by ``seconds`` (yields once if <= 0)."""
        if seconds <= 0:
            await asyncio.sleep(0)
            return
        entry = (self._now + seconds, asyncio.get_running_loop().create_future())
        self._waiting.append(entry)
        try:
            await entry[1]
        finally:
            if entry in self._waiting:
                self._waiting.remove(entry)

    @property
    def sleepers(self) -> int:
        """Coroutines asleep on this clock right now."""
        return sum(not f.done() for _, f in self._waiting)

    def advance(self, seconds: float) -> None:
        """Move time forward by ``seconds`` and wake every sleeper whose time has come."""
        if seconds < 0:
            raise ValueError("a monotonic clock cannot go backwards")
        self._now += seconds
        for due, fut in list(self._waiting):
            if due <= self._now and not fut.done():
                fut.set_result(None)
