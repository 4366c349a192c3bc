"""Async byte transports behind one interface, chosen by URL.

=================================================  ===============================================
URL                                                transport
=================================================  ===============================================
``tcp://HOST:PORT``                                :class:`TcpTransport` (asyncio streams)
``serial:///dev/ttyUSB0?baudrate=115200&...``      :class:`SerialTransport` (serial_asyncio_fast)
``/dev/ttyUSB0`` (a bare path)                     same as ``serial://``
``socket://HOST:PORT``                             :class:`SerialTransport` (pyserial raw TCP)
``loop://``, ``rfc2217://``, ``spy://``, other     :class:`ThreadSerialTransport` (pyserial in a
pyserial URL handlers                              worker thread: those have no file descriptor)
=================================================  ===============================================

Serial query parameters: ``baudrate``, ``bytesize``, ``parity`` (N/E/O/M/S), ``stopbits``,
``rtscts``, ``xonxoff``, ``dsrdtr`` (booleans as 0/1/true/false).

A read never returns short data silently: it returns at least one byte, raises
:class:`~robocal.errors.TransportTimeout` when nothing arrived in time and
:class:`~robocal.errors.TransportError` when the peer closed the connection.

No timeout fires while the answer is already readable. After the process was stopped
(SIGSTOP/SIGCONT, a suspended VM, a long pause) every deadline is past when it runs again,
and the event loop may run the expired timers before it has looked at the sockets: Linux
interrupts ``epoll_wait`` on SIGCONT, and Python (PEP 475) does not poll again once the
wait's own timeout is over. So before a read or a reply wait gives up it lets the loop poll
once more without blocking (:func:`poll_ready_io`) and takes what that delivers.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
import urllib.parse
from collections.abc import AsyncIterator, Callable
from typing import Any, Protocol, TypeVar, runtime_checkable

import serial
import serial_asyncio_fast
import structlog

from robocal.errors import ConfigError, TransportError, TransportTimeout

__all__ = [
    "SerialTransport",
    "TcpTransport",
    "ThreadSerialTransport",
    "Transport",
    "await_reply",
    "open_transport",
    "poll_ready_io",
]

_log = structlog.get_logger(__name__)
_T = TypeVar("_T")

#: Loop iterations a last look may take: one to poll the descriptors, a few more for what the
#: delivery wakes (a reader task that parses the line and resolves a reply future).
_LAST_LOOK_ROUNDS = 8


async def poll_ready_io(done: Callable[[], bool]) -> bool:
    """Let the event loop poll its descriptors without blocking and run what they deliver,
    until ``done()`` is true or a few loop iterations have passed; return ``done()``.

    Call it right before declaring a timeout: data that was already waiting is then
    delivered instead of being reported as missing (see the module docstring).
    """
    for _ in range(_LAST_LOOK_ROUNDS):
        if done():
            return True
        await asyncio.sleep(0)  # each yield is one loop iteration with a select(0)
    return done()


async def await_reply(fut: asyncio.Future[_T], timeout: float) -> _T:
    """Return ``fut``'s result once it is resolved, within ``timeout`` seconds (monotonic).

    ``fut`` is never cancelled by the wait, so a reply delivered at the last moment can still
    resolve it; a reply that was readable when the time ran out is taken (a last look with
    :func:`poll_ready_io`).

    Raises
    ------
    TimeoutError
        If ``fut`` is not resolved in time.
    """
    if not fut.done():
        await asyncio.wait({fut}, timeout=max(0.0, timeout))
    if not fut.done() and not await poll_ready_io(fut.done):
        raise TimeoutError
    return fut.result()


async def received(transport: Transport, max_bytes: int = 65536) -> AsyncIterator[bytes]:
    """Yield what ``transport`` receives, for as long as it is open.

    For reader tasks of connections that may stay quiet: a read timeout is not an error
    here; TransportError (the peer closed, the link failed) ends the iteration by raising.
    """
    while True:
        try:
            yield await transport.read(max_bytes, timeout=3600.0)
        except TransportTimeout:
            continue


#: pyserial URL schemes served without a file descriptor (they need the thread fallback).
_THREAD_SCHEMES = frozenset({"loop", "rfc2217", "spy", "alt", "hwgrep", "cp2110"})


@runtime_checkable
class Transport(Protocol):
    """A bidirectional byte stream. All waits are bounded by an explicit timeout (seconds)."""

    url: str

    @property
    def is_open(self) -> bool:
        """True between a successful :meth:`open` and :meth:`close` (or loss of the peer)."""
        ...

    async def open(self, *, timeout: float) -> None:
        """Open the connection or device."""
        ...

    async def write(self, data: bytes) -> None:
        """Send ``data`` (queued to the OS; raises TransportError when closed)."""
        ...

    async def read(self, max_bytes: int = 4096, *, timeout: float) -> bytes:
        """Return 1..max_bytes bytes; raise TransportTimeout or TransportError, never b""."""
        ...

    async def close(self) -> None:
        """Close; idempotent and never raises."""
        ...


class _BufferProtocol(asyncio.Protocol):
    """Collect received bytes; signal arrival, flow control and loss of the connection."""

    def __init__(self) -> None:
        loop = asyncio.get_running_loop()
        self.buffer = bytearray()
        self.data_ready = asyncio.Event()
        self.can_write = asyncio.Event()
        self.can_write.set()
        self.lost: asyncio.Future[None] = loop.create_future()
        self.exc: BaseException | None = None

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        self.data_ready.set()

    def eof_received(self) -> bool | None:
        self.data_ready.set()
        return None

    def connection_lost(self, exc: Exception | None) -> None:
        self.exc = exc
        self.data_ready.set()
        self.can_write.set()
        if not self.lost.done():
            self.lost.set_result(None)

    def pause_writing(self) -> None:
        self.can_write.clear()

    def resume_writing(self) -> None:
        self.can_write.set()


class _ProtocolTransport:
    """Shared open/read/write logic for transports built on :class:`_BufferProtocol`.

    Subclasses say how to create the asyncio transport (:meth:`_create`), what opening is
    called in messages (``_VERB``) and which exceptions mean it failed (``_OPEN_ERRORS``).
    """

    _VERB = "open"
    _OPEN_ERRORS: tuple[type[Exception], ...] = (OSError,)

    def __init__(self, url: str) -> None:
        self.url = url
        self._proto: _BufferProtocol | None = None
        self._transport: asyncio.BaseTransport | None = None

    async def _create(
        self, loop: asyncio.AbstractEventLoop, proto: _BufferProtocol
    ) -> asyncio.BaseTransport:
        raise NotImplementedError

    async def open(self, *, timeout: float) -> None:
        """Open; raise TransportError (refused, unreachable, missing device) or
        TransportTimeout."""
        if self.is_open:
            return
        proto = _BufferProtocol()
        try:
            async with asyncio.timeout(timeout):
                transport = await self._create(asyncio.get_running_loop(), proto)
        except TimeoutError as err:
            raise TransportTimeout(
                f"{self.url}: {self._VERB} timed out after {timeout:.3g} s"
            ) from err
        except self._OPEN_ERRORS as err:
            raise TransportError(f"{self.url}: cannot {self._VERB}: {err}") from err
        self._proto, self._transport = proto, transport

    @property
    def is_open(self) -> bool:
        return self._proto is not None and not self._proto.lost.done()

    async def write(self, data: bytes) -> None:
        proto, transport = self._proto, self._transport
        if proto is None or transport is None or proto.lost.done():
            raise TransportError(f"{self.url}: not open")
        transport.write(data)  # type: ignore[attr-defined]
        if not proto.can_write.is_set():
            try:
                async with asyncio.timeout(10.0):
                    await proto.can_write.wait()
            except TimeoutError as err:
                raise TransportTimeout(f"{self.url}: write blocked for 10 s") from err

    async def read(self, max_bytes: int = 4096, *, timeout: float) -> bytes:
        proto = self._proto
        if proto is None:
            raise TransportError(f"{self.url}: not open")
        deadline = time.monotonic() + timeout
        while not proto.buffer:
            if proto.lost.done():
                raise TransportError(f"{self.url}: connection closed by peer")
            proto.data_ready.clear()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                # A last, non-blocking look: bytes that were waiting are not "no data".
                if not await poll_ready_io(lambda: bool(proto.buffer) or proto.lost.done()):
                    raise TransportTimeout(f"{self.url}: no data within {timeout:.3g} s")
                continue
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(remaining):
                    await proto.data_ready.wait()
        data = bytes(proto.buffer[:max_bytes])
        del proto.buffer[:max_bytes]
        return data

    async def close(self) -> None:
        proto, transport = self._proto, self._transport
        self._transport = None
        if transport is None or proto is None:
            return
        try:
            transport.close()
            # serial_asyncio_fast closes the port in an executor; wait so no thread or fd leaks.
            async with asyncio.timeout(2.0):
                await asyncio.shield(proto.lost)
        except Exception as err:  # close() must never raise
            _log.debug("transport close", url=self.url, error=repr(err))
            with contextlib.suppress(Exception):
                transport.abort()  # type: ignore[attr-defined]


class TcpTransport(_ProtocolTransport):
    """A TCP client connection (asyncio).

    Parameters
    ----------
    host, port : str, int
        Peer address.
    """

    def __init__(self, host: str, port: int) -> None:
        super().__init__(f"tcp://{host}:{port}")
        self.host = host
        self.port = port

    _VERB = "connect"

    async def _create(
        self, loop: asyncio.AbstractEventLoop, proto: _BufferProtocol
    ) -> asyncio.BaseTransport:
        transport, _ = await loop.create_connection(lambda: proto, self.host, self.port)
        return transport


class SerialTransport(_ProtocolTransport):
    """A serial port (tty, pty) or ``socket://`` peer through ``serial_asyncio_fast``.

    Parameters
    ----------
    url : str
        A device path or a pyserial URL with a file descriptor (``socket://``).
    serial_options : dict
        Keyword arguments for ``serial.serial_for_url`` (``baudrate``, ...).
    """

    def __init__(self, url: str, **serial_options: Any) -> None:
        super().__init__(url)
        self.serial_options = serial_options

    _OPEN_ERRORS = (OSError, serial.SerialException, ValueError)

    async def _create(
        self, loop: asyncio.AbstractEventLoop, proto: _BufferProtocol
    ) -> asyncio.BaseTransport:
        transport, _ = await serial_asyncio_fast.create_serial_connection(
            loop, lambda: proto, self.url, **self.serial_options
        )
        return transport


class ThreadSerialTransport:
    """A pyserial port without a file descriptor (``loop://``, ``rfc2217://``) in worker threads.

    Reads poll the port in short slices so a read never blocks longer than its timeout.
    """

    _SLICE_S = 0.02

    def __init__(self, url: str, **serial_options: Any) -> None:
        self.url = url
        self.serial_options = serial_options
        self._ser: serial.SerialBase | None = None

    @property
    def is_open(self) -> bool:
        """True while the port is open."""
        return self._ser is not None and bool(self._ser.is_open)

    async def open(self, *, timeout: float) -> None:
        """Open the port in a worker thread."""
        if self.is_open:
            return
        opts = {**self.serial_options, "timeout": self._SLICE_S, "write_timeout": 5.0}
        try:
            async with asyncio.timeout(timeout):
                self._ser = await asyncio.to_thread(serial.serial_for_url, self.url, **opts)
        except TimeoutError as err:
            raise TransportTimeout(f"{self.url}: open timed out after {timeout:.3g} s") from err
        except (OSError, serial.SerialException, ValueError) as err:
            raise TransportError(f"{self.url}: cannot open: {err}") from err

    def _port(self) -> serial.SerialBase:
        if self._ser is None:
            raise TransportError(f"{self.url}: not open")
        return self._ser

    async def write(self, data: bytes) -> None:
        """Write in a worker thread."""
        ser = self._port()
        try:
            await asyncio.to_thread(ser.write, data)
        except (OSError, serial.SerialException) as err:
            raise TransportError(f"{self.url}: write failed: {err}") from err

    async def read(self, max_bytes: int = 4096, *, timeout: float) -> bytes:
        """Read in worker-thread slices until data arrives or ``timeout`` expires."""
        ser = self._port()
        deadline = time.monotonic() + timeout
        while True:
            try:
                waiting = ser.in_waiting
                data = await asyncio.to_thread(ser.read, max(1, min(max_bytes, waiting or 1)))
                if data and len(data) < max_bytes and ser.in_waiting:
                    data += ser.read(min(max_bytes - len(data), ser.in_waiting))
            except (OSError, serial.SerialException) as err:
                raise TransportError(f"{self.url}: read failed: {err}") from err
            if data:
                return bytes(data)
            if time.monotonic() >= deadline:
                raise TransportTimeout(f"{self.url}: no data within {timeout:.3g} s")

    async def close(self) -> None:
        """Close the port; idempotent and never raises."""
        ser, self._ser = self._ser, None
        if ser is not None:
            with contextlib.suppress(Exception):
                await asyncio.to_thread(ser.close)


def _parse_bool(value: str, key: str, url: str) -> bool:
    v = value.strip().lower()
    if v in {"1", "true", "yes", "on"}:
        return True
    if v in {"0", "false", "no", "off"}:
        return False
    raise ConfigError(f"expected a boolean, got {value!r}", source=url, key=key)


_SERIAL_KEYS = {
    "baudrate": int,
    "bytesize": int,
    "parity": str,
    "stopbits": float,
    "rtscts": bool,
    "xonxoff": bool,
    "dsrdtr": bool,
}


def _serial_options(url: str, query: str) -> dict[str, Any]:
    opts: dict[str, Any] = {}
    for key, value in urllib.parse.parse_qsl(query, keep_blank_values=True):
        kind = _SERIAL_KEYS.get(key)
        if kind is None:
            raise ConfigError(
                f"unknown serial option; known: {', '.join(sorted(_SERIAL_KEYS))}",
                source=url,
                key=key,
            )
        try:
            if kind is bool:
                opts[key] = _parse_bool(value, key, url)
            elif key == "stopbits":
                sb = float(value)
                opts[key] = int(sb) if sb.is_integer() else sb
            else:
                opts[key] = kind(value)
        except ValueError as err:
            raise ConfigError(f"bad value {value!r}", source=url, key=key) from err
    return opts


def open_transport(url: str) -> Transport:
    """Build (not open) the transport for ``url``; see the module docstring for the schemes.

    Raises
    ------
    ConfigError
        If the URL is malformed or names an unknown scheme or serial option.
    """
    parsed = urllib.parse.urlsplit(url)
    scheme = parsed.scheme.lower()
    if scheme == "tcp":
        try:
            port = parsed.port
        except ValueError as err:
            raise ConfigError("bad port", source=url, key="url") from err
        if not parsed.hostname or port is None:
            raise ConfigError("expected tcp://HOST:PORT", source=url, key="url")
        return TcpTransport(parsed.hostname, port)
    if scheme == "serial" or (not scheme and url.startswith("/")):
        device = parsed.path
        if not device:
            raise ConfigError("expected serial:///dev/NAME", source=url, key="url")
        return SerialTransport(device, **_serial_options(url, parsed.query))
    if scheme == "socket":
        return SerialTransport(url)
    if scheme in _THREAD_SCHEMES:
        return ThreadSerialTransport(url)
    raise ConfigError(
        "unknown transport scheme; use tcp://, serial://, socket://, loop:// or rfc2217://",
        source=url,
        key="url",
    )
