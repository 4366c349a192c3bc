"""Logging configuration: one stream of JSON lines (or console text) for every logger.

robocal's structlog loggers and the stdlib loggers of libraries (pymodbus, aiohttp, asyncio's
exception handler, any other) end in one :class:`logging.StreamHandler` on the root logger,
formatted by structlog's ``ProcessorFormatter``: each record is one line with the same keys
(``timestamp``, ``level``, ``logger``, ``event``) on the same stream (stdout by default).

Records are rate-limited per logger, level and event (message text): at most ``burst`` per
``window_s``; the next record after a quiet spell carries ``suppressed``, the number dropped.
A flood of identical errors (a client hammering the API, a failing accept loop) costs a few
lines, not hundreds of megabytes.

Under systemd with the stream connected to the journal (``JOURNAL_STREAM`` names the stream's
device and inode), every line starts with its syslog priority (``<3>`` for an error), which
journald strips and stores as ``PRIORITY``; ``journalctl -p warning`` then works.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from collections.abc import Mapping, MutableMapping
from typing import Any, Literal, TextIO

import structlog

from robocal._core.clock import SYSTEM_CLOCK, Clock

__all__ = ["RateLimiter", "configure_logging", "journal_priorities"]

_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING,
           "error": logging.ERROR}

#: syslog priority of each structlog level name (sd-daemon(3), syslog(3)).
_PRIORITY = {"debug": 7, "info": 6, "warning": 4, "error": 3, "critical": 2}

#: LogRecord attribute where the limiter leaves the number of records it dropped before.
_SUPPRESSED = "robocal_suppressed"

#: The handler the last configure_logging installed (replaced by the next call).
_installed: logging.Handler | None = None


class RateLimiter:
    """Allow ``burst`` records per key per ``window_s``; count the rest.

    ``allow(key)`` returns None to drop, else the number dropped since the last allowed one.
    Windows are measured on ``clock`` (seconds).
    """

    def __init__(self, burst: int = 20, window_s: float = 10.0, max_keys: int = 1000, *,
                 clock: Clock = SYSTEM_CLOCK) -> None:
        self.burst = burst
        self.window_s = window_s
        self.max_keys = max_keys
        self.clock = clock
        self._state: dict[str, list[float]] = {}  # key -> [window start, count, dropped]
        self._lock = threading.Lock()  # fit threads log too

    def allow(self, key: str, now: float | None = None) -> int | None:
        """None to drop the record under ``key``, else how many were dropped before it."""
        t = self.clock.monotonic() if now is None else now
        with self._lock:
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


class _Limit(logging.Filter):
    """The rate limit, for structlog's records and foreign ones alike."""

    def __init__(self, limiter: RateLimiter) -> None:
        super().__init__()
        self.limiter = limiter

    def filter(self, record: logging.LogRecord) -> bool:
        # structlog's records carry their event dict as ``msg`` (ProcessorFormatter.wrap_for_
        # formatter); a foreign record's ``msg`` is its format string, the same for every
        # record of one call site whatever its arguments.
        msg = record.msg
        event = msg.get("event") if isinstance(msg, Mapping) else msg
        dropped = self.limiter.allow(f"{record.name}:{record.levelno}:{event}")
        if dropped is None:
            return False
        setattr(record, _SUPPRESSED, dropped)
        return True


def _add_suppressed(logger: Any, method: str, event: MutableMapping[str, Any]
                    ) -> MutableMapping[str, Any]:
    """Copy the limiter's count of dropped records into the event (``suppressed``)."""
    dropped = getattr(event.get("_record"), _SUPPRESSED, 0)
    if dropped:
        event["suppressed"] = dropped
    return event


class _JournalPrefix:
    """Wrap a renderer: start each output line with the event's syslog priority ``<N>``."""

    def __init__(self, render: structlog.typing.Processor) -> None:
        self.render = render

    def __call__(self, logger: Any, method: str, event: MutableMapping[str, Any]) -> str:
        prefix = f"<{_PRIORITY.get(str(event.get('level', '')), 6)}>"
        text = self.render(logger, method, event)
        assert isinstance(text, str)
        # journald reads the prefix per line: a console traceback keeps its priority too
        return "\n".join(prefix + line for line in text.split("\n"))


def journal_priorities(stream: TextIO, environ: Mapping[str, str] | None = None) -> bool:
    """True if ``stream`` is the journal stream systemd connected (``JOURNAL_STREAM``).

    systemd sets ``JOURNAL_STREAM=DEVICE:INODE`` (decimal) for a service whose stdout or
    stderr goes to the journal; a stream with the same device and inode is that connection,
    one redirected elsewhere (a file, a pipe) is not (systemd.exec(5)).
    """
    value = (os.environ if environ is None else environ).get("JOURNAL_STREAM", "")
    dev, sep, ino = value.partition(":")
    if not sep:
        return False
    try:
        st = os.fstat(stream.fileno())
        return (int(dev), int(ino)) == (st.st_dev, st.st_ino)
    except (AttributeError, ValueError, OSError):  # no descriptor (io.UnsupportedOperation)
        return False


def configure_logging(level: Literal["debug", "info", "warning", "error"] = "info",
                      fmt: Literal["json", "console"] = "json", *, burst: int = 20,
                      window_s: float = 10.0, stream: TextIO | None = None,
                      clock: Clock = SYSTEM_CLOCK) -> None:
    """Send structlog and every stdlib logger to ``stream`` (default stdout), one line each.

    robocal's own loggers log from ``level``, other libraries' from ``warning`` (or
    ``level`` if higher); ``burst``/``window_s`` is the rate limit (``window_s`` on
    ``clock``). Calling it again replaces the previous configuration.
    """
    global _installed
    out = sys.stdout if stream is None else stream
    threshold = _LEVELS[level]
    # Keys every line has, whichever logger made it.
    shared: list[structlog.typing.Processor] = [
        structlog.contextvars.merge_contextvars,
        structlog.stdlib.add_log_level,
        structlog.stdlib.add_logger_name,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    render: structlog.typing.Processor
    tail: list[structlog.typing.Processor] = [
        _add_suppressed, structlog.stdlib.ProcessorFormatter.remove_processors_meta]
    if fmt == "json":
        # Tracebacks as data, without each frame's locals: those can hold secrets (the API's
        # auth middleware holds the client's bearer token) and would then reach the journal.
        tail.append(structlog.processors.ExceptionRenderer(
            structlog.tracebacks.ExceptionDictTransformer(show_locals=False)))
        render = structlog.processors.JSONRenderer()
    else:
        render = structlog.dev.ConsoleRenderer(colors=False)
    if journal_priorities(out):
        render = _JournalPrefix(render)
    handler = logging.StreamHandler(out)
    handler.addFilter(_Limit(RateLimiter(burst, window_s, clock=clock)))
    handler.setFormatter(structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=shared, processors=[*tail, render]))

    root = logging.getLogger()
    if _installed is not None:
        root.removeHandler(_installed)
    root.addHandler(handler)
    root.setLevel(max(threshold, logging.WARNING))
    logging.getLogger("robocal").setLevel(threshold)
    _installed = handler
    structlog.configure(
        processors=[*shared, structlog.stdlib.ProcessorFormatter.wrap_for_formatter],
        wrapper_class=structlog.make_filtering_bound_logger(threshold),
        logger_factory=structlog.stdlib.LoggerFactory(),
        cache_logger_on_first_use=True,
    )
