"""Admission control in front of the HTTP server: connection limits and a header deadline.

aiohttp bounds neither the number of connections nor the time a client may take to send its
request headers, so a few hundred half-open requests (sent before any token check) can use
up the daemon's file descriptors. :class:`ConnectionGate` wraps the server's protocol
factory: a connection over the listener's limit, or over the per-client limit (TCP: per
address), is reset at once, before aiohttp allocates anything for it; a connection whose
request headers are not complete within ``header_timeout_s`` (or exceed ``max_header_bytes``)
is reset; the deadline never runs while a response is produced or streamed (Server-Sent
Events, long polls). Refusals are counted, not logged one by one. Deadlines run on the gate's
:class:`~robocal._core.clock.Clock` (tests advance a manual one).
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Callable
from typing import Any

from aiohttp import web, web_runner

from robocal._core.clock import SYSTEM_CLOCK, Clock

__all__ = ["ConnectionGate", "GatedTCPSite", "GatedUnixSite"]

_END = b"\r\n\r\n"


class ConnectionGate:
    """Limits shared by every connection of one listener.

    Parameters
    ----------
    max_connections : int
        Open connections at most (others are reset on arrival).
    max_per_client : int or None
        Open connections per client address at most (None: no per-client limit).
    header_timeout_s : float
        Time from connection (or from the end of the previous request) to the end of the
        request headers.
    max_header_bytes : int
        Size of the request line and headers at most.
    clock : Clock, optional
        Time source of the header deadline (default: the system clock).
    """

    def __init__(self, *, max_connections: int, max_per_client: int | None,
                 header_timeout_s: float, max_header_bytes: int = 32 * 1024,
                 clock: Clock = SYSTEM_CLOCK) -> None:
        self.max_connections = max_connections
        self.max_per_client = max_per_client
        self.header_timeout_s = header_timeout_s
        self.max_header_bytes = max_header_bytes
        self.clock = clock
        self.open = 0
        #: Connections whose header deadline is running (a request's headers still to come).
        self.awaiting_headers = 0
        self.per_client: Counter[str] = Counter()
        self.refused = 0
        self.timed_out = 0

    def factory(self, make: Callable[[], asyncio.Protocol]) -> Callable[[], asyncio.Protocol]:
        """Wrap the server's protocol factory ``make``."""
        return lambda: _Guard(self, make)

    def stats(self) -> dict[str, int]:
        """Open connections and refusals so far."""
        return {"open": self.open, "refused": self.refused, "header_timeouts": self.timed_out}


def _client(transport: asyncio.BaseTransport) -> str:
    peer = transport.get_extra_info("peername")
    if isinstance(peer, tuple) and peer:
        return str(peer[0])
    return ""


class _Guard(asyncio.Protocol):
    """One connection: admitted or reset; forwards everything to aiohttp's handler."""

    def __init__(self, gate: ConnectionGate, make: Callable[[], asyncio.Protocol]) -> None:
        self.gate = gate
        self.make = make
        self.inner: Any = None
        self.transport: asyncio.Transport | None = None
        self.client = ""
        self.timer: asyncio.Task[None] | None = None
        self.head = bytearray()
        self.mode = "head"  # head: reading request headers; body: its body; idle: neither
        self.body_left: int | None = 0  # bytes of the current body still to come; None: unknown
        # Between requests no deadline runs: the response may stream for minutes (SSE,
        # long-poll) and idle keep-alive is aiohttp's to close. The next request's first byte
        # starts its header deadline.
        self.between = False

    # -- admission ----------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        gate = self.gate
        client = _client(transport)
        if gate.open >= gate.max_connections or (
                gate.max_per_client is not None and client
                and gate.per_client[client] >= gate.max_per_client):
            gate.refused += 1
            transport.abort()
            return
        gate.open += 1
        if client:
            gate.per_client[client] += 1
        self.client = client
        self.transport = transport
        self._arm()
        self.inner = self.make()
        self.inner.connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.transport is None:
            return
        self._disarm()
        gate = self.gate
        gate.open -= 1
        if self.client:
            gate.per_client[self.client] -= 1
            if gate.per_client[self.client] <= 0:
                del gate.per_client[self.client]
        self.transport = None
        self.inner.connection_lost(exc)

    # -- header deadline ------------------------------------------------------------------------
    def _arm(self) -> None:
        self._disarm()
        self.head = bytearray()
        due = self.gate.clock.monotonic() + self.gate.header_timeout_s
        self.timer = asyncio.get_running_loop().create_task(self._deadline(due))
        self.gate.awaiting_headers += 1

    def _disarm(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
            self.gate.awaiting_headers -= 1

    async def _deadline(self, due: float) -> None:
        """Reset the connection at ``due`` (gate clock) unless disarmed (cancelled) first."""
        clock = self.gate.clock
        await clock.sleep(due - clock.monotonic())
        self.timer = None  # done: _expire must not cancel this task
        self.gate.awaiting_headers -= 1
        self._expire()

    def _expire(self) -> None:
        self._disarm()
        if self.transport is not None:
            self.gate.timed_out += 1
            self.transport.abort()

    def _request_done(self) -> None:
        self._disarm()
        self.between = True

    def _track(self, data: bytes) -> None:
        """Follow request boundaries: the deadline runs from a request's first byte (or the
        connection) to the end of its headers; never while a response is being produced or
        streamed (idle keep-alive is aiohttp's ``keepalive_timeout``)."""
        while data:
            if self.mode == "idle":
                self.mode = "head"
                self._arm()
            if self.mode == "body":
                if self.body_left is None:
                    return  # chunked: the app's body deadline and keep-alive bound it
                used = min(self.body_left, len(data))
                self.body_left -= used
                data = data[used:]
                if self.body_left == 0:
                    self.mode = "idle"
                continue
            self.head += data
            end = self.head.find(_END)
            if end < 0:
                if len(self.head) > self.gate.max_header_bytes:
                    self._expire()
                return
            if end > self.gate.max_header_bytes:
                self._expire()
                return
            self._disarm()
            self.body_left = _body_length(bytes(self.head[:end]).decode("latin-1"))
            data = bytes(self.head[end + len(_END):])
            self.head = bytearray()
            self.mode = "idle" if self.body_left == 0 else "body"

    def data_received(self, data: bytes) -> None:
        if self.transport is None:
            return
        self._track(data)
        if not self.transport.is_closing():
            self.inner.data_received(data)

    # -- everything else goes straight through -----------------------------------------------------
    def eof_received(self) -> bool | None:
        if self.inner is None:
            return None
        return self.inner.eof_received()

    def pause_writing(self) -> None:
        if self.inner is not None:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.inner is not None:
            self.inner.resume_writing()


def _body_length(head: str) -> int | None:
    """Content-Length of a request head (0 if absent), None for chunked bodies."""
    length = 0
    for line in head.split("\r\n")[1:]:
        name, _, value = line.partition(":")
        key = name.strip().lower()
        if key == "transfer-encoding" and "chunked" in value.lower():
            return None
        if key == "content-length":
            try:
                length = max(0, int(value.strip()))
            except ValueError:
                return None
    return length


class GatedTCPSite(web.TCPSite):
    """``web.TCPSite`` whose connections pass a :class:`ConnectionGate` first."""

    def __init__(self, runner: web_runner.BaseRunner, host: str, port: int, *,
                 gate: ConnectionGate, backlog: int = 128) -> None:
        super().__init__(runner, host, port, backlog=backlog)
        self.gate = gate

    async def start(self) -> None:
        await web_runner.BaseSite.start(self)
        server = self._runner.server
        assert server is not None
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            self.gate.factory(server), self._host, self._port, backlog=self._backlog,
            reuse_address=self._reuse_address)
        sockets = self._server.sockets
        self.bound: int = int(sockets[0].getsockname()[1]) if sockets else int(self._port or 0)
        self._bound_port = self.bound

    @property
    def port(self) -> int:
        """The bound port (useful with port 0)."""
        return self.bound


class GatedUnixSite(web.UnixSite):
    """``web.UnixSite`` whose connections pass a :class:`ConnectionGate` first."""

    def __init__(self, runner: web_runner.BaseRunner, path: str, *, gate: ConnectionGate,
                 backlog: int = 128) -> None:
        super().__init__(runner, path, backlog=backlog)
        self.gate = gate

    async def start(self) -> None:
        await web_runner.BaseSite.start(self)
        server = self._runner.server
        assert server is not None
        loop = asyncio.get_running_loop()
        self._server = await loop.create_unix_server(
            self.gate.factory(server), self._path, backlog=self._backlog)
