"""LTP/1 over a real pty: a reply the tracker never sent must not cost the next measurement.

A scripted bridge sits on the pty's master side and answers the driver line by line; it
"misses" chosen replies (a lost line on a serial link) and puts garbage lines before others.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty
from collections.abc import AsyncIterator, Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.drivers.ltp import LtpTracker
from robocal.errors import DriverTimeout, TransportTimeout
from robocal.protocols import LineStream, ltp

HANDSHAKE = {
    "HELLO": "OK proto=LTP/1 vendor=script model=PTY serial=1 fw=1 bridge=script",
    "STATUS?": "OK ready=1 beam=LOCKED init=1 smr=RRR15 units=mm frame=tracker",
    "SMR": "OK type=RRR15 offset_mm=0.000",
    "UNITS": "OK len=mm ang=deg",
    "FRAME": "OK name=tracker",
    "STOP": "OK",
    "BYE": "OK",
}
POINT = "x=1000 y=2000 z=-500 sx=0.001 sy=0.001 sz=0.002 n=1 rms=0.002"

#: (request, nth MEAS so far) -> the bytes the bridge sends back (b"" for a lost reply).
Script = Callable[[ltp.Request, int], bytes]


class PtyBridge:
    """A scripted LTP/1 bridge on the master side of a pty."""

    def __init__(self, script: Script) -> None:
        self.script = script
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.requests: list[ltp.Request] = []
        self._buf = b""
        self._meas = 0

    def start(self) -> None:
        asyncio.get_running_loop().add_reader(self.master, self._readable)

    def _readable(self) -> None:
        try:
            self._buf += os.read(self.master, 4096)
        except OSError:
            return
        while b"\r\n" in self._buf:
            line, self._buf = self._buf.split(b"\r\n", 1)
            req = ltp.parse_request(line)
            self.requests.append(req)
            if req.verb == "MEAS":
                self._meas += 1
                out = self.script(req, self._meas)
            else:
                out = f"{req.tag} {HANDSHAKE[req.verb]}\r\n".encode()
            if out:
                os.write(self.master, out)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            asyncio.get_running_loop().remove_reader(self.master)
        os.close(self.master)
        os.close(self.slave)


@contextlib.asynccontextmanager
async def bridge(script: Script) -> AsyncIterator[tuple[PtyBridge, LtpTracker]]:
    b = PtyBridge(script)
    b.start()
    t = LtpTracker({"url": f"serial://{b.path}?baudrate=115200", "request_timeout_s": 1.0,
                    "reply_margin_s": 0.2})
    try:
        await t.connect(timeout=5)
        yield b, t
    finally:
        await asyncio.wait_for(t.close(), 5)
        b.close()


def ok(req: ltp.Request) -> bytes:
    return f"{req.tag} OK id={req.args['id']} {POINT}\r\n".encode()


GARBAGE = [b"\x00\xff\xfe garbage \x1b[0m", b"7 OK x=\"unterminated", b"%%%%", b"!" * 600]


@pytest.mark.parametrize("garbage", GARBAGE)
async def test_lost_meas_reply_then_garbage_then_reply(garbage: bytes) -> None:
    """MEAS 1 is never answered; MEAS 2 is answered after a garbage line: MEAS 2 succeeds,
    within its own deadline, without reopening the line."""

    def script(req: ltp.Request, n: int) -> bytes:
        if n == 1:
            return b""
        return garbage + b"\r\n" + ok(req)

    async with bridge(script) as (b, t):
        with pytest.raises(DriverTimeout):
            await t.measure(samples=1, timeout=0.2, point_id="P1")
        reading = await asyncio.wait_for(t.measure(samples=1, timeout=0.2, point_id="P2"), 0.4)
        assert reading.point_id == "P2"
        assert reading.position_m == pytest.approx((1.0, 2.0, -0.5))
        assert [r.verb for r in b.requests].count("HELLO") == 1  # the line was not reopened
        assert t.bad_lines >= 1


async def test_lost_reply_after_stop_and_stale_reply_discarded() -> None:
    """MEAS 1 lost; MEAS 2 answered with a stale reply to MEAS 1's tag first, then its own."""
    first: list[str] = []

    def script(req: ltp.Request, n: int) -> bytes:
        if n == 1:
            first.append(req.tag)
            return b""
        stale = f"{first[0]} OK id=P1 {POINT.replace('x=1000', 'x=9')}\r\n".encode()
        return stale + b"junk\r\n" + ok(req)

    async with bridge(script) as (_, t):
        with pytest.raises(DriverTimeout):
            await t.measure(samples=1, timeout=0.2, point_id="P1")
        reading = await asyncio.wait_for(t.measure(samples=1, timeout=0.2, point_id="P2"), 0.4)
        assert reading.point_id == "P2" and reading.position_m[0] == pytest.approx(1.0)



@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.lists(st.sampled_from(GARBAGE), max_size=2)),
                min_size=1, max_size=6))
def test_every_answered_measurement_succeeds_whatever_was_lost_before(plan) -> None:
    """Property: MEAS replies lost at random, garbage before the others; every MEAS that is
    answered succeeds with its own reading, every lost one is a DriverTimeout, and no lost
    reply costs a later measurement."""

    def reply(tag: str, verb: str) -> bytes:
        if verb == "MEAS":
            lost, junk = plan[int(t.point_id_sent[-1][1:])]
            if lost:
                return b""
            return b"".join(j + b"\r\n" for j in junk) + (
                f"{tag} OK id={t.point_id_sent[-1]} {POINT}\r\n".encode())
        return f"{tag} {HANDSHAKE[verb]}\r\n".encode()

    t = _ScriptedTracker(reply)

    async def run() -> list[str]:
        outcome = []
        for i in range(len(plan)):
            t.point_id_sent.append(f"P{i}")
            try:
                r = await t.measure(samples=1, timeout=0.02, point_id=f"P{i}")
                outcome.append(r.point_id or "")
            except DriverTimeout:
                outcome.append("timeout")
        return outcome

    got = asyncio.run(run())
    assert got == ["timeout" if lost else f"P{i}" for i, (lost, _) in enumerate(plan)]


class _ScriptedTracker(LtpTracker):
    """An LtpTracker already connected over an in-memory transport answering by script."""

    def __init__(self, reply: Callable[[str, str], bytes]) -> None:
        super().__init__({"url": "tcp://127.0.0.1:1", "request_timeout_s": 0.05,
                          "reply_margin_s": 0.0})
        self.point_id_sent: list[str] = []
        self._stream = LineStream(_Scripted(reply))
        self.state = "connected"


class _Scripted:
    """A transport that answers each request line written with ``reply(tag, verb)``."""

    url = "scripted://"
    is_open = True

    def __init__(self, reply: Callable[[str, str], bytes]) -> None:
        self.reply = reply
        self.inbox = bytearray()

    async def open(self, *, timeout: float) -> None:
        return None

    async def write(self, data: bytes) -> None:
        tag, verb = data.decode().split()[:2]
        self.inbox += self.reply(tag, verb)

    async def read(self, max_bytes: int = 4096, *, timeout: float) -> bytes:
        if not self.inbox:
            await asyncio.sleep(min(timeout, 0.005))
            raise TransportTimeout("nothing")
        data = bytes(self.inbox[:max_bytes])
        del self.inbox[:max_bytes]
        return data

    async def close(self) -> None:
        self.is_open = False
