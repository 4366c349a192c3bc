"""The API's admission control over real sockets on 127.0.0.1: header deadline, connection
limits per listener and per client, body deadline (the rate-limited logs: test_logging.py)."""

from __future__ import annotations

import asyncio
import contextlib
import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.daemon._gate import ConnectionGate, _Guard
from robocal.daemon.api import ApiServer
from robocal.daemon.service import CalibrationService
from tests._clock import ManualClock
from tests._waiting import eventually

TOKEN = "gate-token-0123456789abcdef"


@pytest.fixture
def clock() -> ManualClock:
    """The gates' clock: header deadlines pass only when a test advances it."""
    return ManualClock()


@pytest.fixture
async def api(make_config, tmp_path, clock):
    tok = tmp_path / "token"
    tok.write_text(TOKEN)
    tok.chmod(0o600)
    cfg = make_config(api={"socket": str(tmp_path / "api.sock"), "tcp_port": 0,
                           "token_file": str(tok), "header_timeout_s": 0.3,
                           "body_timeout_s": 0.3, "max_connections": 6,
                           "max_connections_per_client": 4})
    svc = CalibrationService(cfg)
    await svc.start()
    # a pool of 6 unauthenticated connections (the daemon sizes it from its descriptors)
    server = ApiServer(svc, cfg, clock=clock, max_unauthenticated=6)
    await server.start()
    yield server
    await server.stop()
    await svc.stop()


async def _closed_by_peer(reader: asyncio.StreamReader, timeout: float) -> bool:
    """True if the server closes (or resets) the connection within ``timeout`` s."""
    try:
        async with asyncio.timeout(timeout):
            data = await reader.read(65536)
            while data:
                data = await reader.read(65536)
    except TimeoutError:
        return False
    except ConnectionError:
        return True
    return True


async def _still_open(reader: asyncio.StreamReader) -> bool:
    """The connection is not closed within a moment (20 ms; the fake clock stands still)."""
    return not await _closed_by_peer(reader, 0.02)


async def _advance(clock: ManualClock, seconds: float) -> None:
    """Advance the gates' clock and let the deadlines that came due run."""
    clock.advance(seconds)
    for _ in range(5):
        await asyncio.sleep(0)


def _head(path: str, token: str = TOKEN) -> bytes:
    return (f"GET {path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
            "\r\n").encode()


async def _status(reader: asyncio.StreamReader) -> int:
    """Read one response; its status code."""
    async with asyncio.timeout(5):
        status = int((await reader.readline()).split()[1])
        length = 0
        while (line := await reader.readline()) not in (b"\r\n", b""):
            if line.lower().startswith(b"content-length:"):
                length = int(line.split(b":")[1])
        await reader.readexactly(length)
    return status


async def _get(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, path: str,
               token: str = TOKEN) -> int:
    writer.write(_head(path, token))
    await writer.drain()
    return await _status(reader)


async def test_partial_headers_are_cut_off_at_the_deadline(api, clock):
    gate = api.tcp_gate
    assert gate is not None and gate.clock is clock
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    await eventually(lambda: gate.awaiting_headers == 1)  # runs from the connection
    w.write(b"GET /health HTTP/1.1\r\nHost: x\r\n")  # never finished
    await w.drain()
    await _advance(clock, 0.29)
    assert await _still_open(r) and gate.timed_out == 0
    await _advance(clock, 0.02)
    assert await _closed_by_peer(r, 3.0)
    assert gate.timed_out == 1 and gate.awaiting_headers == 0
    w.close()


async def test_a_long_response_is_not_cut_by_the_next_header_deadline(api, clock):
    """An event stream outlives the header deadline (0.3 s here): campaign watch needs it."""
    gate = api.tcp_gate
    assert gate is not None
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    w.write(f"GET /events?after=0 HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n"
            "Accept: text/event-stream\r\n\r\n".encode())
    await w.drain()
    async with asyncio.timeout(5):
        assert b" 200 " in await r.readline()
    await _advance(clock, 1.0)  # > 3 header deadlines
    assert await _still_open(r)  # stream still open
    assert gate.timed_out == 0 and gate.awaiting_headers == 0
    w.close()
    # the stream's handler notices its client gone at the next event (else the server's
    # shutdown waits 2 s for it)
    await eventually(lambda: gate.open == 0)
    api.service.events.emit("log", None, text="nobody listens")
    # and a slow next request on a kept-alive connection is still cut off
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    assert await _get(r, w, "/health") == 200
    w.write(b"GET /health HTTP/1.1\r\n")  # started, never finished
    await w.drain()
    await eventually(lambda: gate.awaiting_headers == 1)
    await _advance(clock, 0.31)
    assert await _closed_by_peer(r, 3.0)
    assert gate.timed_out == 1
    w.close()


async def test_keep_alive_requests_each_get_the_full_deadline(api, clock):
    gate = api.tcp_gate
    assert gate is not None
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    head = _head("/health")
    for _ in range(3):  # 1.2 s on one connection, four header deadlines
        w.write(head[:12])  # each request arrives slowly, within its own deadline
        await w.drain()
        await eventually(lambda: gate.awaiting_headers == 1)
        await _advance(clock, 0.2)
        w.write(head[12:])
        await w.drain()
        assert await _status(r) == 200
        assert gate.awaiting_headers == 0
        await _advance(clock, 0.2)  # between requests no deadline runs
    assert gate.timed_out == 0
    body = json.dumps({"reason": "x"}).encode()
    w.write(b"POST /campaigns/nope/pause HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
            + TOKEN.encode() + b"\r\nContent-Type: application/json\r\nContent-Length: "
            + str(len(body)).encode() + b"\r\n\r\n" + body)
    await w.drain()
    async with asyncio.timeout(5):
        assert b" 404 " in await r.readline()
    w.close()


async def test_a_stream_outlives_the_header_deadline(api, clock):
    """Server-Sent Events (and long polls) run far longer than the 0.3 s header deadline."""
    gate = api.tcp_gate
    assert gate is not None
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    w.write(b"GET /events?after=0 HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
            + TOKEN.encode() + b"\r\n\r\n")
    await w.drain()
    async with asyncio.timeout(5):
        assert b" 200 " in await r.readline()
    await _advance(clock, 1.0)  # three header deadlines
    api.service.events.emit("log", None, text="still here")
    async with asyncio.timeout(5):
        while b"still here" not in await r.readline():
            pass
    w.close()
    # the long poll, likewise
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    await eventually(lambda: gate.awaiting_headers == 1)  # the poll's connection is in
    after = api.service.events.last_seq
    w.write(f"GET /events/poll?after={after}&timeout=5 HTTP/1.1\r\nHost: x\r\n"
            f"Authorization: Bearer {TOKEN}\r\n\r\n".encode())
    await w.drain()
    await eventually(lambda: gate.awaiting_headers == 0)  # and its headers are
    await _advance(clock, 0.8)
    api.service.events.emit("log", None, text="polled")
    async with asyncio.timeout(5):
        assert b" 200 " in await r.readline()
    assert gate.timed_out == 0
    w.close()


async def test_a_slow_body_is_408(api):
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    w.write(b"POST /campaigns HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + TOKEN.encode()
            + b"\r\nContent-Length: 100\r\n\r\n{\"plan\"")
    await w.drain()
    async with asyncio.timeout(5):
        assert b" 408 " in await r.readline()
    assert await _closed_by_peer(r, 5.0)  # and the server is done with it
    w.close()
    await w.wait_closed()


async def test_oversized_headers_are_cut_off(api):
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    with contextlib.suppress(ConnectionError):
        w.write(b"GET /health HTTP/1.1\r\n" + b"X-Pad: " + b"a" * 40_000 + b"\r\n")
        await w.drain()
    assert await _closed_by_peer(r, 3.0)
    w.close()


async def _half_open(host: str, port: int, source: str = "127.0.0.1"
                     ) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """A connection from ``source`` that sent part of a request head and nothing more."""
    r, w = await asyncio.open_connection(host, port, local_addr=(source, 0))
    w.write(b"GET /health HTTP/1.1\r\nHost: x\r\n")
    await w.drain()
    return r, w


async def test_a_client_behind_a_proxy_is_not_locked_out_by_its_address(api):
    """Half-open connections from one address (a local reverse proxy): with room in the pool
    the real client on that address is simply served; with the pool full of that address's
    half-open connections it displaces their oldest."""
    gate = api.tcp_gate
    assert gate is not None
    held = [await _half_open("127.0.0.1", api.tcp_port) for _ in range(5)]
    await eventually(lambda: gate.open == 5)
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    assert await _get(r, w, "/health") == 200
    assert gate.cut == 0 and gate.refused == 0  # beyond the per-client 4, but room: no cut
    w.close()
    held.append(await _half_open("127.0.0.1", api.tcp_port))
    await eventually(lambda: gate.open == 6)  # the pool is full, all from one address
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    assert await _get(r, w, "/health") == 200
    assert await _closed_by_peer(held[0][0], 3.0)  # the oldest half-open one made room
    assert gate.cut == 1 and gate.refused == 0
    assert all([await _still_open(hr) for hr, _ in held[1:]])
    w.close()
    for _, hw in held:
        hw.close()


async def test_token_holders_have_their_own_budget_and_the_unix_socket_is_separate(api):
    """Half-open connections from six addresses fill the unauthenticated pool (6 here): they
    take nothing from the six authenticated slots; a seventh authenticated connection is
    reset, the Unix socket's budget is untouched."""
    gate = api.tcp_gate
    assert gate is not None
    held = [await _half_open("127.0.0.1", api.tcp_port, f"127.0.0.{i}") for i in range(2, 8)]
    await eventually(lambda: gate.open == 6)
    clients = []
    for _ in range(6):
        r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
        assert await _get(r, w, "/health") == 200  # kept alive: holds an authenticated slot
        clients.append((r, w))
    assert gate.authenticated == 6
    # each newcomer cut the oldest half-open connection of the address holding the most
    assert gate.unauthenticated == 6 - gate.cut and gate.refused == 0
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    w.write(_head("/health"))
    await w.drain()
    assert await _closed_by_peer(r, 3.0)
    assert gate.refused == 1
    w.close()
    ur, uw = await asyncio.open_unix_connection(str(api.socket_path))
    assert await _get(ur, uw, "/health", token="") == 200
    uw.close()
    for _, cw in clients:
        cw.close()
    await eventually(lambda: gate.authenticated == 0)
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    assert await _get(r, w, "/health") == 200  # and the slots are free again
    w.close()
    for _, hw in held:
        hw.close()


async def test_a_wrong_token_does_not_authenticate(api):
    gate = api.tcp_gate
    assert gate is not None
    r, w = await asyncio.open_connection("127.0.0.1", api.tcp_port)
    assert await _get(r, w, "/health", token="wrong-token-0123456789") == 401
    assert gate.authenticated == 0 and gate.unauthenticated == 1
    assert await _get(r, w, "/health") == 200  # the middleware still checks each request
    assert gate.authenticated == 1 and gate.unauthenticated == 0  # and now it has the token
    w.close()


async def test_a_full_pool_cuts_the_address_holding_the_most(api):
    """Pool of 6: four half-open from one address, two from another; a newcomer from a third
    cuts the oldest of the four, never one of the two."""
    gate = api.tcp_gate
    assert gate is not None
    heavy = [await _half_open("127.0.0.1", api.tcp_port, "127.0.0.2") for _ in range(4)]
    light = [await _half_open("127.0.0.1", api.tcp_port, "127.0.0.3") for _ in range(2)]
    await eventually(lambda: gate.open == 6)
    newcomer = await _half_open("127.0.0.1", api.tcp_port, "127.0.0.4")
    assert await _closed_by_peer(heavy[0][0], 3.0)
    assert gate.cut == 1 and gate.unauthenticated == 6
    assert all([await _still_open(r) for r, _ in heavy[1:] + light + [newcomer]])
    for _, w in heavy + light + [newcomer]:
        w.close()


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["arrive", "leave", "token"]), st.integers(0, 5),
                          st.integers(0, 40)), max_size=120),
       st.integers(1, 8), st.integers(1, 4))
def test_gate_bookkeeping_stays_consistent(ops, pool, per_client):
    """Random arrivals (from six addresses), departures and authentications: the pool never
    exceeds its size, the counts and buckets agree with the pool, a newcomer is always
    admitted, and nothing is cut while there is room."""
    gate = ConnectionGate(max_connections=3, max_per_client=per_client, header_timeout_s=1.0,
                          token="t" * 16, max_unauthenticated=pool)
    live: list[_Guard] = []
    for op, address, pick in ops:
        if op == "arrive":
            g = _Guard(gate, lambda: asyncio.Protocol())
            g.client = f"127.0.0.{address + 2}"
            full, cut = gate.unauthenticated >= pool, gate.cut
            assert gate._admit(g)
            assert gate.cut == cut + full
            live.append(g)
        elif live:
            g = live[pick % len(live)]
            if op == "leave":
                gate._leave(g)
                live.remove(g)
            elif g.state == "pool":
                gate._authenticate(g)
        held = {a: len(gs) for a, gs in gate.pool.items()}
        assert all(n > 0 for n in held.values())
        assert gate.unauthenticated == sum(held.values()) <= pool
        assert gate._top == max(held.values(), default=0)
        assert {n: set(b) for n, b in gate._buckets.items()} == {
            n: {a for a, m in held.items() if m == n} for n in set(held.values())}
        assert gate.authenticated == sum(g.state == "auth" for g in live) <= 3
        assert all(g.state in ("pool", "auth", "gone") for g in live)
