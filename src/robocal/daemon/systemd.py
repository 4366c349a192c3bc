"""systemd integration without a dependency: ``sd_notify`` and a watchdog task.

The protocol is one datagram per message on the AF_UNIX socket named by ``$NOTIFY_SOCKET``
(a leading ``@`` is the abstract namespace). Outside systemd every call is a no-op. The
watchdog pings from the event loop at half of ``$WATCHDOG_USEC``, so a blocked loop (or a
fit accidentally run on it) lets systemd restart the daemon.
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Callable

import structlog

__all__ = ["notify", "watchdog", "watchdog_interval"]

_log = structlog.get_logger(__name__)


def notify(message: str) -> bool:
    """Send ``message`` (e.g. ``"READY=1"``) to systemd; False when not under systemd."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):
        addr = "\0" + addr[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall(message.encode())
    except OSError as err:
        _log.warning("sd_notify failed", error=str(err))
        return False
    return True


def watchdog_interval() -> float | None:
    """Seconds between pings (half of ``$WATCHDOG_USEC``), or None without a watchdog."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 2e6 if value > 0 else None


async def watchdog(healthy: Callable[[], bool] = lambda: True) -> None:
    """Ping ``WATCHDOG=1`` while ``healthy()``; returns at once without a watchdog."""
    interval = watchdog_interval()
    if interval is None:
        return
    _log.info("watchdog enabled", interval_s=interval)
    while True:
        if healthy():
            notify("WATCHDOG=1")
        await asyncio.sleep(interval)
