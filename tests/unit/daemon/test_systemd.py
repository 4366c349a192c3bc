"""sd_notify over a temporary datagram socket (filesystem and abstract), and the watchdog."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket

import pytest

from robocal.daemon import systemd
from tests._waiting import eventually


@pytest.fixture
def notify_socket(tmp_path, monkeypatch):
    path = tmp_path / "notify"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(str(path))
    s.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    yield s
    s.close()


def test_notify_without_systemd_is_a_no_op(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert systemd.notify("READY=1") is False


def test_notify_sends_one_datagram(notify_socket):
    assert systemd.notify("READY=1\nSTATUS=serving")
    assert notify_socket.recv(4096) == b"READY=1\nSTATUS=serving"


def test_abstract_socket(monkeypatch):
    name = f"robocal-test-{os.getpid()}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind("\0" + name)
    s.settimeout(2.0)
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert systemd.notify("WATCHDOG=1")
        assert s.recv(100) == b"WATCHDOG=1"
    finally:
        s.close()


def test_watchdog_interval(monkeypatch):
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    assert systemd.watchdog_interval() is None
    monkeypatch.setenv("WATCHDOG_USEC", "30000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert systemd.watchdog_interval() == 15.0
    monkeypatch.setenv("WATCHDOG_PID", "1")
    assert systemd.watchdog_interval() is None


async def test_watchdog_pings_from_the_loop(notify_socket, monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "40000")  # ping every 20 ms
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    notify_socket.setblocking(False)
    pings: list[bytes] = []

    def received() -> int:
        with contextlib.suppress(BlockingIOError):
            while True:
                pings.append(notify_socket.recv(100))
        return len(pings)

    task = asyncio.create_task(systemd.watchdog())
    try:
        await eventually(lambda: received() >= 3)
    finally:
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    assert set(pings) == {b"WATCHDOG=1"}
