"""structlog configuration: JSON lines on stdout (journald keeps each as MESSAGE) or console.

Logs are rate-limited per event: at most ``burst`` records of one event (one message text)
per ``window_s``; the next record after a quiet spell says how many were dropped. A flood of
identical errors (a client hammering the API, a failing accept loop) costs a few lines, not
hundreds of megabytes. The stdlib loggers of aiohttp and asyncio (the event loop's exception
handler) go through the same limit, on stderr.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import MutableMapping
from typing import Any, Literal

import structlog

__all__ = ["RateLimiter", "configure_logging"]

_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING,
           "error": logging.ERROR}


class RateLimiter:
    """Allow ``burst`` records per key per ``window_s``; count the rest.

    ``allow(key)`` returns None to drop, else the number dropped since the last allowed one.
    """

    def __init__(self, burst: int = 20, window_s: float = 10.0, max_keys: int = 1000) -> None:
        self.burst = burst
        self.window_s = window_s
        self.max_keys = max_keys
        self._state: dict[str, list[float]] = {}  # key -> [window start, count, dropped]

    def allow(self, key: str, now: float | None = None) -> int | None:
        t = time.monotonic() if now is None else now
        st = self._state.get(key)
        if st is None:
            if len(self._state) >= self.max_keys:
                self._state.clear()
            self._state[key] = [t, 1.0, 0.0]
            return 0
        if t - st[0] >= self.window_s:
            dropped = int(st[2])
            st[:] = [t, 1.0, 0.0]
            return dropped
        if st[1] < self.burst:
            st[1] += 1
            return 0
        st[2] += 1
        return None


class _StructlogLimit:
    def __init__(self, limiter: RateLimiter) -> None:
        self.limiter = limiter

    def __call__(self, logger: Any, method: str, event: MutableMapping[str, Any]
                 ) -> MutableMapping[str, Any]:
        dropped = self.limiter.allow(f"{method}:{event.get('event')}")
        if dropped is None:
            raise structlog.DropEvent
        if dropped:
            event["suppressed"] = dropped
        return event


class _StdlibLimit(logging.Filter):
    def __init__(self, limiter: RateLimiter) -> None:
        super().__init__()
        self.limiter = limiter

    def filter(self, record: logging.LogRecord) -> bool:
        dropped = self.limiter.allow(f"{record.name}:{record.levelno}:{record.msg}")
        if dropped is None:
            return False
        if dropped:
            record.msg = f"{record.msg} ({dropped} similar records suppressed)"
        return True


def configure_logging(level: Literal["debug", "info", "warning", "error"] = "info",
                      fmt: Literal["json", "console"] = "json", *, burst: int = 20,
                      window_s: float = 10.0) -> None:
    """Configure structlog once for the process (the daemon's entry point calls it)."""
    limiter = RateLimiter(burst, window_s)
    processors: list[structlog.typing.Processor] = [
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        _StructlogLimit(limiter),
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    if fmt == "json":
        processors += [structlog.processors.dict_tracebacks, structlog.processors.JSONRenderer()]
    else:
        processors.append(structlog.dev.ConsoleRenderer(colors=False))
    structlog.configure(
        processors=processors,
        wrapper_class=structlog.make_filtering_bound_logger(_LEVELS[level]),
        logger_factory=structlog.WriteLoggerFactory(file=sys.stdout),
        cache_logger_on_first_use=True,
    )
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(_StdlibLimit(limiter))
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    for name in ("aiohttp", "asyncio"):
        lg = logging.getLogger(name)
        lg.handlers[:] = [handler]
        lg.propagate = False
        lg.setLevel(max(_LEVELS[level], logging.WARNING))
