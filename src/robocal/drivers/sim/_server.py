"""What every simulator's serving side shares: listeners, tracked tasks, client sessions, an
orderly stop, and the process mode that publishes the bound ports and serves until SIGTERM or
SIGINT.

A simulator subclasses :class:`SimServer`, accepts connections with :meth:`SimServer._listen`
(each handler runs as a tracked task and its writer is closed when it returns), starts helper
tasks with :meth:`SimServer._track`, and ends everything with :meth:`SimServer._stop_serving`,
after closing its own sessions between :meth:`SimServer._close_listeners` and that call.
A :class:`SessionServer` also feeds each connection's bytes to a :class:`Session`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import sys
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

from robocal.drivers.sim.faults import FaultConfig, FaultInjector

if TYPE_CHECKING:
    from robocal.drivers.sim.world import SimWorld

__all__ = [
    "Handler",
    "Session",
    "SessionServer",
    "SimServer",
    "WorldSimulator",
    "port_of",
    "publish_ports",
    "until_signalled",
]

#: A connection handler, as ``asyncio.start_server`` takes it.
Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


def port_of(server: asyncio.Server) -> int:
    """The port ``server`` is bound to."""
    return int(server.sockets[0].getsockname()[1])


async def received(reader: asyncio.StreamReader, chunk: int = 65536) -> AsyncIterator[bytes]:
    """What the client sends, ``chunk`` bytes at most at a time, until it closes the
    connection or the connection breaks."""
    while True:
        try:
            data = await reader.read(chunk)
        except ConnectionError:
            return
        if not data:
            return
        yield data


class SimServer:
    """Base of the simulators: their listening sockets and every task they run.

    Attributes
    ----------
    host : str
        The address listened on (set by :meth:`_listen`).
    """

    def __init__(self) -> None:
        self.host = "127.0.0.1"
        self._servers: list[asyncio.Server] = []
        self._tasks: set[asyncio.Task[Any]] = set()

    async def _listen(self, handler: Handler, host: str, port: int) -> asyncio.Server:
        """Accept connections on ``host:port`` (0: a free port) with ``handler``."""
        server = await asyncio.start_server(self._connection(handler), host, port)
        self.host = host
        self._servers.append(server)
        return server

    def _forget(self, server: asyncio.Server) -> None:
        """Stop listening on ``server`` (its connections go on) and drop it."""
        server.close()
        if server in self._servers:
            self._servers.remove(server)

    def _connection(self, handler: Handler) -> Handler:
        """``handler`` run as a tracked task that ends quietly when cancelled and closes the
        connection when it returns."""
        async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            task = asyncio.current_task()
            if task is not None:
                self._tasks.add(task)
            try:
                await handler(reader, writer)
            except asyncio.CancelledError:
                # stop() cancels handlers; end normally, or asyncio's stream callback on
                # Python 3.11 logs the cancelled task as an error.
                pass
            finally:
                writer.close()
                with contextlib.suppress(Exception, asyncio.CancelledError):
                    await writer.wait_closed()
                if task is not None:
                    self._tasks.discard(task)

        return serve

    def _track(self, coro: Coroutine[Any, Any, Any]) -> None:
        """Run ``coro`` as a task that :meth:`_stop_serving` cancels."""
        task = asyncio.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _close_listeners(self) -> None:
        """Stop accepting connections; idempotent."""
        for server in self._servers:
            server.close()

    async def _stop_serving(self) -> None:
        """Stop listening, cancel every connection handler and tracked task, and wait for
        them and for the listeners to close (at most 2 s); idempotent."""
        self._close_listeners()
        tasks = list(self._tasks)
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        for server in self._servers:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(2.0):
                    await server.wait_closed()
        self._servers.clear()


class WorldSimulator(SimServer):
    """A simulated device around the shared world: the robot it serves and the faults the
    cell injects.

    Parameters
    ----------
    world : SimWorld
        The robot the device drives or measures.
    faults : FaultConfig, optional
        Faults shared by the cell's simulators.
    """

    def __init__(self, world: SimWorld, faults: FaultConfig | None) -> None:
        super().__init__()
        self.world = world
        self.faults = FaultInjector(faults)


class Session(Protocol):
    """One client's protocol state, as :meth:`SessionServer._serve_session` drives it."""

    closed: bool

    async def open(self) -> None:
        """Greet a client that has just connected (if the protocol does)."""

    async def feed(self, data: bytes) -> None:
        """Handle bytes received from the client."""

    async def stop(self) -> None:
        """End whatever the session still runs; idempotent."""


S = TypeVar("S", bound=Session)


class SessionServer(WorldSimulator, Generic[S]):
    """A :class:`WorldSimulator` whose connections each carry a session of type ``S``."""

    def __init__(self, world: SimWorld, faults: FaultConfig | None) -> None:
        super().__init__(world, faults)
        self._sessions: set[S] = set()

    async def _serve_session(self, reader: asyncio.StreamReader, session: S, chunk: int) -> None:
        """Greet, then feed ``session`` what ``reader`` receives (``chunk`` bytes at most at a
        time) until the client closes, the connection breaks or the session closes; then stop
        it. It is in ``_sessions`` meanwhile."""
        self._sessions.add(session)
        try:
            await session.open()
            while not session.closed:
                data = await reader.read(chunk)
                if not data:
                    break
                await session.feed(data)
        except ConnectionError:
            pass
        finally:
            await session.stop()
            self._sessions.discard(session)


# --- process mode (robocal sim ...) ----------------------------------------------------------
@contextlib.asynccontextmanager
async def until_signalled() -> AsyncIterator[asyncio.Event]:
    """Yield an event that SIGTERM or SIGINT sets; the handlers go again on exit."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    try:
        yield stop
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(Exception):
                loop.remove_signal_handler(sig)


def publish_ports(ports: dict[str, Any], ports_file: Path | None) -> None:
    """Print the bound ports as one JSON line and, atomically, write them to ``ports_file``."""
    blob = json.dumps(ports, sort_keys=True)
    if ports_file is not None:
        tmp = ports_file.with_name(ports_file.name + ".tmp")
        tmp.write_text(blob + "\n")
        os.replace(tmp, ports_file)
    sys.stdout.write(blob + "\n")
    sys.stdout.flush()
