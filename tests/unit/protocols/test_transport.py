"""Transports chosen by URL: TCP, serial on a pty, socket://, loop://; LineStream."""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robocal.errors import ConfigError, FramingError, TransportError, TransportTimeout
from robocal.protocols import (
    LineStream,
    SerialTransport,
    TcpTransport,
    ThreadSerialTransport,
    open_transport,
)


@contextlib.asynccontextmanager
async def echo_server(*, greeting: bytes = b"", close_after: bool = False):
    writers = []

    async def handle(reader, writer):
        writers.append(writer)
        if greeting:
            writer.write(greeting)
            await writer.drain()
        if close_after:
            writer.close()
            return
        while data := await reader.read(4096):
            writer.write(data)
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        server.close()
        for w in writers:
            w.close()
        await server.wait_closed()


def test_open_transport_picks_by_url():
    assert isinstance(open_transport("tcp://127.0.0.1:7710"), TcpTransport)
    t = open_transport("serial:///dev/ttyUSB0?baudrate=115200&parity=E&stopbits=2&rtscts=1")
    assert isinstance(t, SerialTransport) and t.url == "/dev/ttyUSB0"
    assert t.serial_options == {"baudrate": 115200, "parity": "E", "stopbits": 2, "rtscts": True}
    assert isinstance(open_transport("/dev/ttyS0"), SerialTransport)
    assert isinstance(open_transport("socket://127.0.0.1:7"), SerialTransport)
    assert isinstance(open_transport("loop://"), ThreadSerialTransport)
    assert isinstance(open_transport("rfc2217://127.0.0.1:7"), ThreadSerialTransport)


@pytest.mark.parametrize(
    "url",
    [
        "tcp://host",
        "tcp://:80",
        "tcp://h:notaport",
        "serial://",
        "serial:///dev/x?baud=9600",
        "serial:///dev/x?rtscts=maybe",
        "serial:///dev/x?baudrate=fast",
        "ftp://x",
        "pair://a",
    ],
)
def test_bad_urls_raise_config_error(url):
    with pytest.raises(ConfigError):
        open_transport(url)


async def test_tcp_round_trip_timeout_and_eof():
    async with echo_server() as port:
        t = open_transport(f"tcp://127.0.0.1:{port}")
        await t.open(timeout=2)
        assert t.is_open
        await t.write(b"hello")
        got = b""
        while len(got) < 5:
            got += await t.read(3, timeout=2)
        assert got == b"hello"
        with pytest.raises(TransportTimeout):
            await t.read(timeout=0.05)
        await t.close()
        await t.close()
        assert not t.is_open
        with pytest.raises(TransportError):
            await t.write(b"x")


async def test_tcp_peer_close_raises_transport_error_after_data():
    async with echo_server(greeting=b"bye", close_after=True) as port:
        t = TcpTransport("127.0.0.1", port)
        await t.open(timeout=2)
        assert await t.read(timeout=2) == b"bye"
        with pytest.raises(TransportError):
            await t.read(timeout=2)
        await t.close()


async def test_tcp_connection_refused():
    server = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    server.close()
    await server.wait_closed()
    t = TcpTransport("127.0.0.1", port)
    with pytest.raises(TransportError):
        await t.open(timeout=2)
    await t.close()


async def test_socket_url_through_serial_asyncio_fast():
    async with echo_server() as port:
        t = open_transport(f"socket://127.0.0.1:{port}")
        await t.open(timeout=2)
        stream = LineStream(t)
        await stream.write_line(b"1 HELLO")
        assert await stream.read_line(timeout=2) == b"1 HELLO"
        await t.close()


async def test_pty_serial_transport():
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        t = open_transport(f"serial://{os.ttyname(slave)}?baudrate=115200")
        await t.open(timeout=2)
        await t.write(b"ping\r\n")
        loop = asyncio.get_running_loop()
        data = await asyncio.wait_for(loop.run_in_executor(None, os.read, master, 100), 2)
        assert data == b"ping\r\n"
        os.write(master, b"pong\r\n")
        stream = LineStream(t)
        assert await stream.read_line(timeout=2) == b"pong"
        with pytest.raises(TransportTimeout):
            await t.read(timeout=0.05)
        await t.close()
        await t.close()
    finally:
        os.close(master)
        os.close(slave)


async def test_missing_serial_device():
    t = open_transport("serial:///dev/does-not-exist-robocal")
    with pytest.raises(TransportError):
        await t.open(timeout=2)
    await t.close()


async def test_loop_url_thread_fallback():
    t = open_transport("loop://")
    await t.open(timeout=2)
    stream = LineStream(t)
    await stream.write_line("1 OK a=1")
    assert await stream.read_line(timeout=2) == b"1 OK a=1"
    with pytest.raises(TransportTimeout):
        await t.read(timeout=0.05)
    await t.close()
    await t.close()
    with pytest.raises(TransportError):
        await t.read(timeout=0.1)


async def test_line_stream_timeout_and_overlong_resync():
    t = open_transport("loop://")
    await t.open(timeout=2)
    stream = LineStream(t, max_length=8)
    await t.write(b"1 OK")  # no line end yet
    with pytest.raises(TransportTimeout):
        await stream.read_line(timeout=0.05)
    await t.write(b"\r\n" + b"x" * 30 + b"\r\nshort\r\n")
    assert await stream.read_line(timeout=2) == b"1 OK"
    with pytest.raises(FramingError):
        await stream.read_line(timeout=2)
    assert await stream.read_line(timeout=2) == b"short"
    await t.close()


@given(st.text(max_size=60))
def test_arbitrary_urls_give_a_transport_or_config_error(url):
    try:
        t = open_transport(url)
    except ConfigError:
        return
    assert isinstance(t, TcpTransport | SerialTransport | ThreadSerialTransport)
