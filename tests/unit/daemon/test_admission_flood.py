"""A flood of half-open TCP connections from many loopback addresses does not lock out a
client with the token (issue 25, item 6; the p99 figure is in bench/bench_api_flood.py).

The whole of 127/8 is loopback on Linux: each attacker binds its socket to 127.0.0.x before
connecting, so the daemon sees 50 different source addresses.
"""

from __future__ import annotations

import asyncio
import contextlib
import resource

import pytest

from robocal.daemon.api import ApiServer
from robocal.daemon.service import CalibrationService

TOKEN = "flood-token-0123456789abcdef"
ADDRESSES = 50
PER_ADDRESS = 6
ROUNDS = 20


@pytest.fixture
async def api(make_config, tmp_path):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 2048 <= hard or (soft < 2048 and hard == resource.RLIM_INFINITY):
        resource.setrlimit(resource.RLIMIT_NOFILE, (2048, hard))
    tok = tmp_path / "token"
    tok.write_text(TOKEN)
    tok.chmod(0o600)
    # the shipped limits (64 connections, 8 per client, 10 s header deadline)
    cfg = make_config(api={"socket": str(tmp_path / "api.sock"), "tcp_port": 0,
                           "token_file": str(tok)})
    svc = CalibrationService(cfg)
    await svc.start()
    # A pool smaller than the flood (the daemon sizes it from its descriptors, up to 4,096):
    # every cut connection is reopened at once, so admission works under constant churn.
    server = ApiServer(svc, cfg, max_unauthenticated=64)
    await server.start()
    yield server
    await server.stop()
    await svc.stop()
    resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


async def _attacker(port: int, source: str, stop: asyncio.Event, opened: list[int]) -> None:
    """Keep one half-open request open from ``source``; open another whenever it is cut."""
    while not stop.is_set():
        try:
            r, w = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))
        except OSError:
            await asyncio.sleep(0.01)
            continue
        opened[0] += 1
        try:
            w.write(b"GET /campaigns HTTP/1.1\r\nHost: robocal\r\nX-Slow: ")
            await w.drain()
            stopped = asyncio.ensure_future(stop.wait())
            cut = asyncio.ensure_future(r.read())
            await asyncio.wait({stopped, cut}, return_when=asyncio.FIRST_COMPLETED)
            stopped.cancel()
            cut.cancel()
            await asyncio.gather(stopped, cut, return_exceptions=True)
        except OSError:
            pass
        finally:
            w.close()


async def _health(port: int) -> int:
    """One request on a fresh connection with the token; its status (0: connection cut)."""
    try:
        r, w = await asyncio.open_connection("127.0.0.1", port)
    except OSError:
        return 0
    try:
        w.write(f"GET /health HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n"
                "Connection: close\r\n\r\n".encode())
        await w.drain()
        line = await r.readline()
        return int(line.split()[1]) if line else 0
    except (OSError, IndexError, ValueError):
        return 0
    finally:
        w.close()


async def test_authenticated_client_is_served_through_a_flood_from_fifty_addresses(api):
    gate = api.tcp_gate
    assert gate is not None
    stop = asyncio.Event()
    opened = [0]
    sources = [f"127.0.0.{2 + i % ADDRESSES}" for i in range(ADDRESSES * PER_ADDRESS)]
    flood = [asyncio.create_task(_attacker(api.tcp_port, s, stop, opened)) for s in sources]
    try:
        async with asyncio.timeout(30):
            # every attacker has connected once, and the daemon holds a pool's worth
            while opened[0] < len(sources) or gate.open < 64:
                await asyncio.sleep(0.01)
        statuses = []
        for _ in range(ROUNDS):
            async with asyncio.timeout(10):  # generous: this asserts service, not latency
                statuses.append(await _health(api.tcp_port))
        assert statuses == [200] * ROUNDS
        assert gate.cut >= len(sources) - 64  # the pool was full and cutting
        assert gate.unauthenticated <= gate.max_unauthenticated
        assert len(gate.pool) > 1  # the attackers' addresses share the pool
    finally:
        stop.set()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(10):
                await asyncio.gather(*flood, return_exceptions=True)
        for task in flood:
            task.cancel()
