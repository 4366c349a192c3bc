"""Admission control in front of the HTTP server: connection budgets and a header deadline.

aiohttp bounds neither the number of connections nor the time a client may take to send its
request headers, so a few hundred half-open requests (sent before any token check) could use
up the daemon's file descriptors or every connection slot. :class:`ConnectionGate` wraps the
server's protocol factory and keeps two budgets per listener (ADR 0025):

* **Authenticated** connections (the request headers carried the listener's bearer token;
  on the Unix socket, whose file mode is the access control, every connection) have
  ``max_connections`` slots of their own. Nothing unauthenticated can take them.
* **Unauthenticated** connections (no complete request head yet, or no valid token) share a
  pool of ``max_unauthenticated`` slots, counted over all source addresses. A full pool never
  refuses a newcomer: it cuts the oldest unauthenticated connection of the address that holds
  the most (the newcomer's own address included), so a flood from many addresses cannot lock
  a real client out, and a client behind a local reverse proxy, whose address it shares with
  half-open connections, displaces the oldest of them. An address that holds
  ``max_per_client`` or more loses its own oldest first. A pool with room cuts nothing.

A connection whose request headers are not complete within ``header_timeout_s`` (or exceed
``max_header_bytes``) is reset (while more unauthenticated connections are open than
``max_connections``, within a random 50-100 % of it, so a flood is not cut all at once);
the deadline never runs while a response is produced or streamed (Server-Sent Events, long
polls). aiohttp's protocol object is created only once a connection's first request head is
complete, so a half-open connection costs a socket, a timer and the bytes it sent. Refusals
and cuts are counted, not logged one by one. Deadlines run on the gate's
:class:`~robocal._core.clock.Clock` (tests advance a manual one).
"""

from __future__ import annotations

import asyncio
import hmac
import itertools
import random
from collections.abc import Awaitable, Callable
from typing import Any

from aiohttp import web, web_runner

from robocal._core.clock import SYSTEM_CLOCK, Clock

__all__ = ["ConnectionGate", "GatedTCPSite", "GatedUnixSite"]

_END = b"\r\n\r\n"
_ORDER = itertools.count()


class ConnectionGate:
    """Budgets shared by every connection of one listener.

    Parameters
    ----------
    max_connections : int
        Authenticated connections at most (more are reset when their token arrives).
    max_per_client : int or None
        When the pool is full, a newcomer from an address holding this many unauthenticated
        connections or more cuts that address's oldest one (None: the fair choice only).
    header_timeout_s : float
        Time from connection (or from the first byte of a later request) to the end of the
        request headers.
    max_header_bytes : int
        Size of the request line and headers at most.
    token : str or None
        Bearer token that authenticates a connection; None: every connection is authenticated
        on arrival (the Unix socket).
    max_unauthenticated : int or None
        Size of the unauthenticated pool (default: ``max_connections``).
    clock : Clock, optional
        Time source of the header deadline (default: the system clock).
    """

    def __init__(self, *, max_connections: int, max_per_client: int | None,
                 header_timeout_s: float, max_header_bytes: int = 32 * 1024,
                 token: str | None = None, max_unauthenticated: int | None = None,
                 clock: Clock = SYSTEM_CLOCK) -> None:
        self.max_connections = max_connections
        self.max_per_client = max_per_client
        self.header_timeout_s = header_timeout_s
        self.max_header_bytes = max_header_bytes
        self.max_unauthenticated = (max_connections if max_unauthenticated is None
                                    else max_unauthenticated)
        self.clock = clock
        self._expected = None if token is None else f"Bearer {token}".encode()
        self.open = 0
        #: Connections whose header deadline is running (a request's headers still to come).
        self.awaiting_headers = 0
        self.authenticated = 0
        #: Unauthenticated connections per client address, oldest first.
        self.pool: dict[str, dict[_Guard, None]] = {}
        #: Addresses by how many unauthenticated connections they hold, in the order they got
        #: there; ``_top`` is the largest such count.
        self._buckets: dict[int, dict[str, None]] = {}
        self._top = 0
        self.unauthenticated = 0
        self.refused = 0
        self.cut = 0
        self.timed_out = 0

    def factory(self, make: Callable[[], asyncio.Protocol]) -> Callable[[], asyncio.Protocol]:
        """Wrap the server's protocol factory ``make``."""
        return lambda: _Guard(self, make)

    def stats(self) -> dict[str, int]:
        """Open connections, refusals and cuts so far."""
        return {"open": self.open, "authenticated": self.authenticated,
                "unauthenticated": self.unauthenticated, "refused": self.refused,
                "cut": self.cut, "header_timeouts": self.timed_out}

    # -- the two budgets ------------------------------------------------------------------------
    def _admit(self, guard: _Guard) -> bool:
        """Take ``guard`` in: authenticated at once (no token), else into the pool."""
        if self._expected is None:
            return self._authenticate(guard)
        if self.unauthenticated >= self.max_unauthenticated:
            # Only a full pool cuts: a connection cut while there is room is reopened at
            # once, and a flood that cycles keeps the accept queue full (ADR 0025).
            same = self.pool.get(guard.client, {})
            if self.max_per_client is not None and len(same) >= self.max_per_client:
                self._cut(next(iter(same)))
            else:
                self._cut(self._victim(guard.client))
        same = self.pool.setdefault(guard.client, {})
        same[guard] = None
        self._recount(guard.client, len(same) - 1, len(same))
        self.unauthenticated += 1
        guard.state = "pool"
        return True

    def _victim(self, newcomer: str) -> _Guard:
        """The oldest unauthenticated connection of the address that holds the most, the
        newcomer's own address counted with the newcomer; among equals, the address that got
        to that count first. Constant time: addresses are kept in buckets by count."""
        own = len(self.pool.get(newcomer, ()))
        top = self._top
        address = newcomer if own + 1 > top else next(iter(self._buckets[top]))
        return next(iter(self.pool[address]))

    def _recount(self, address: str, before: int, after: int) -> None:
        """Move ``address`` from the bucket of ``before`` connections to that of ``after``."""
        if before:
            bucket = self._buckets[before]
            del bucket[address]
            if not bucket:
                del self._buckets[before]
        if after:
            self._buckets.setdefault(after, {})[address] = None
        if after > self._top:
            self._top = after
        while self._top and self._top not in self._buckets:
            self._top -= 1

    def _cut(self, guard: _Guard) -> None:
        self.cut += 1
        self._leave(guard)
        if guard.transport is not None:
            guard.transport.abort()

    def _authenticate(self, guard: _Guard) -> bool:
        """Move ``guard`` to the authenticated budget; False (and reset) if that is full."""
        self._leave(guard)
        if self.authenticated >= self.max_connections:
            self.refused += 1
            return False
        self.authenticated += 1
        guard.state = "auth"
        return True

    def _leave(self, guard: _Guard) -> None:
        if guard.state == "pool":
            same = self.pool[guard.client]
            del same[guard]
            self._recount(guard.client, len(same) + 1, len(same))
            if not same:
                del self.pool[guard.client]
            self.unauthenticated -= 1
        elif guard.state == "auth":
            self.authenticated -= 1
        guard.state = "gone"

    def _check_token(self, head: str) -> bool:
        expected = self._expected
        if expected is None:
            return True
        for line in head.split("\r\n")[1:]:
            name, _, value = line.partition(":")
            if name.strip().lower() == "authorization":
                return hmac.compare_digest(value.strip().encode("latin-1"), expected)
        return False


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
        self.order = next(_ORDER)
        self.state = "new"  # new, pool (unauthenticated), auth, gone
        self.inner: Any = None
        self.transport: asyncio.Transport | None = None
        self.client = ""
        self.timer: asyncio.Task[None] | None = None
        self.head = bytearray()
        self.mode = "head"  # head: reading request headers; body: its body; idle: neither
        self.body_left: int | None = 0  # bytes of the current body still to come; None: unknown
        self.head_done = False  # the first request head is complete
        self.early = bytearray()  # bytes received before it was (at most max_header_bytes)

    # -- admission ----------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.client = _client(transport)
        self.transport = transport
        self.gate.open += 1
        if not self.gate._admit(self):
            self.transport = None
            self.gate.open -= 1
            transport.abort()
            return
        self._arm()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.transport is None:
            return
        self._disarm()
        self.gate._leave(self)
        self.gate.open -= 1
        self.transport = None
        if self.inner is not None:
            self.inner.connection_lost(exc)

    # -- header deadline ------------------------------------------------------------------------
    def _arm(self) -> None:
        self._disarm()
        self.head = bytearray()
        gate = self.gate
        timeout = gate.header_timeout_s
        if self.state == "pool" and gate.unauthenticated > gate.max_connections:
            # Under a flood, half-open connections are cut sooner and at spread-out times:
            # a flood opened at once would otherwise be cut, and reopened, all at once.
            timeout *= random.uniform(0.5, 1.0)  # timing only, not a secret
        due = gate.clock.monotonic() + timeout
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

    def _track(self, data: bytes) -> None:
        """Follow request boundaries: the deadline runs from a request's first byte (or the
        connection) to the end of its headers; never while a response is being produced or
        streamed (idle keep-alive is aiohttp's ``keepalive_timeout``). The first complete
        head with the token moves the connection to the authenticated budget."""
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
            head = bytes(self.head[:end]).decode("latin-1")
            if self.state == "pool" and self.gate._check_token(head) \
                    and not self.gate._authenticate(self):
                self._drop()
                return
            self.head_done = True
            self.body_left = _body_length(head)
            data = bytes(self.head[end + len(_END):])
            self.head = bytearray()
            self.mode = "idle" if self.body_left == 0 else "body"

    def _drop(self) -> None:
        """Reset a connection the authenticated budget has no room for."""
        transport = self.transport
        if transport is not None:
            transport.abort()

    def data_received(self, data: bytes) -> None:
        if self.transport is None or self.state == "gone":
            return
        self._track(data)
        if self.transport is None or self.transport.is_closing() or self.state == "gone":
            return
        if self.inner is None:
            # aiohttp's handler is created once the first request head is complete: a
            # half-open connection costs a socket, a timer and its bytes so far, no handler.
            self.early += data
            if not self.head_done:
                return
            data, self.early = bytes(self.early), bytearray()
            self.inner = self.make()
            self.inner.connection_made(self.transport)
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


_Listen = Callable[[Callable[[], asyncio.Protocol]], Awaitable[asyncio.Server]]


async def _listen(site: web_runner.BaseSite, gate: ConnectionGate,
                  listen: _Listen) -> asyncio.Server:
    """Start ``site`` as aiohttp does, but serve through ``gate``: ``listen`` opens the
    listening socket with the protocol factory it is given."""
    await web_runner.BaseSite.start(site)
    server = site._runner.server
    assert server is not None
    return await listen(gate.factory(server))


class GatedTCPSite(web.TCPSite):
    """``web.TCPSite`` whose connections pass a :class:`ConnectionGate` first."""

    def __init__(self, runner: web_runner.BaseRunner, host: str, port: int, *,
                 gate: ConnectionGate, backlog: int = 1024) -> None:
        super().__init__(runner, host, port, backlog=backlog)
        self.gate = gate

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        self._server = await _listen(self, self.gate, lambda protocol: loop.create_server(
            protocol, self._host, self._port, backlog=self._backlog,
            reuse_address=self._reuse_address))
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
        loop = asyncio.get_running_loop()
        self._server = await _listen(self, self.gate, lambda protocol: loop.create_unix_server(
            protocol, self._path, backlog=self._backlog))
