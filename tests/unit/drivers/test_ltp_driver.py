"""LTP/1 tracker driver against the tracker simulator (TCP, socket://, pty) and scripted bridges."""

from __future__ import annotations

import asyncio
import contextlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robocal.drivers.ltp import LtpTracker
from robocal.drivers.sim import FaultConfig, LtpSimOptions, LtpTrackerSimulator
from robocal.errors import (
    BeamLost,
    ConfigError,
    ConnectFailed,
    DriverTimeout,
    MeasurementError,
    OperationError,
    ProtocolError,
    RobocalError,
    TransportError,
    TransportTimeout,
    UnexpectedReply,
    Unstable,
)
from robocal.protocols import LineStream


@contextlib.asynccontextmanager
async def tracker_sim(world, options=None, faults=None, pty=False):
    sim = LtpTrackerSimulator(world, options or LtpSimOptions(time_scale=0.0), faults)
    await sim.start_tcp()
    if pty:
        await sim.start_pty()
    try:
        yield sim
    finally:
        await sim.stop()


def url(sim, via):
    if via == "pty":
        return f"serial://{sim.pty_path}?baudrate=115200"
    return f"{via}://127.0.0.1:{sim.port}"


@pytest.mark.parametrize("via", ["tcp", "socket", "pty"])
async def test_session_and_measurement_in_metres(world, via):
    async with tracker_sim(world, pty=True) as sim:
        t = LtpTracker({"url": url(sim, via), "smr": "RRR05", "stab_ms": 250})
        await t.connect(timeout=5)
        assert t.info["proto"] == "LTP/1" and t.info["model"] == "LT-SIM"
        assert [r.verb for r in sim.requests] == [
            "HELLO",
            "STATUS?",
            "SMR",
            "UNITS",
            "FRAME",
            "STATUS?",
        ]
        assert sim.smr == "RRR05"
        world.move([0.3] * world.dof)
        r = await t.measure(samples=12, timeout=2, point_id="P0042")
        truth = world.true_reflector_position()
        sigma = np.asarray(world.measure(1).sigma_m)
        assert np.all(np.abs(np.asarray(r.position_m) - truth) < 5 * sigma + 1e-8)
        assert r.n == 12 and r.point_id == "P0042" and r.status == "ok"
        assert all(0 < s < 1e-4 for s in r.std_m)
        assert r.weather == {"temp_c": 20.4, "press_hpa": 1012.6, "hum_pct": 41.0}
        meas = sim.requests[-1]
        assert dict(meas.args) == {
            "id": "P0042",
            "mode": "stationary",
            "n": "12",
            "stab_mm": "0.01",
            "stab_ms": "250",
            "timeout_ms": "2000",
        }
        await t.close()
        await t.close()
        assert sim.requests[-1].verb == "BYE"


async def test_init_sent_when_tracker_not_initialised(world):
    async with tracker_sim(world, LtpSimOptions(time_scale=0.0, require_init=True)) as sim:
        t = LtpTracker({"url": url(sim, "tcp"), "smr": None})
        await t.connect(timeout=5)
        assert [r.verb for r in sim.requests] == [
            "HELLO",
            "STATUS?",
            "INIT",
            "UNITS",
            "FRAME",
            "STATUS?",
        ]
        await t.measure(samples=1, timeout=1)
        await t.close()


async def test_wrong_protocol_refused(world):
    async with tracker_sim(world, LtpSimOptions(proto="LTP/2")) as sim:
        t = LtpTracker({"url": url(sim, "tcp")})
        with pytest.raises(ConnectFailed, match="LTP/2"):
            await t.connect(timeout=5)
        assert t.state == "closed"


async def test_beam_break_and_unstable(world):
    async with tracker_sim(world, faults=FaultConfig(beam_break_rate=1.0)) as sim:
        t = LtpTracker({"url": url(sim, "tcp")})
        await t.connect(timeout=5)
        with pytest.raises(BeamLost, match="BEAM_BROKEN"):
            await t.measure(samples=1, timeout=1)
        assert t.beam == "BROKEN"
        sim.faults.config = FaultConfig(unstable_rate=1.0)
        with pytest.raises(Unstable, match="UNSTABLE"):
            await t.measure(samples=1, timeout=1)
        assert t.beam == "LOCKED"  # the relock event arrived before the next reply
        sim.faults.config = FaultConfig()
        await t.measure(samples=1, timeout=1)
        await t.close()


async def test_events_and_garbage_between_request_and_reply(world):
    faults = FaultConfig(garbage_rate=0.5, seed=11)
    async with tracker_sim(world, LtpSimOptions(time_scale=0.0, event_rate=1.0), faults) as sim:
        t = LtpTracker({"url": url(sim, "tcp")})
        await t.connect(timeout=5)
        for i in range(20):
            r = await t.measure(samples=2, timeout=1, point_id=f"P{i}")
            assert r.point_id == f"P{i}"
        assert t.bad_lines >= sim.faults.counts["garbage"] > 0
        assert t.weather["temp_c"] == 20.4
        await t.close()


async def test_late_reply_discarded_after_timeout(world):
    async with tracker_sim(world) as sim:
        t = LtpTracker({"url": url(sim, "tcp"), "reply_margin_s": 0.0})
        await t.connect(timeout=5)
        sim.faults.config = FaultConfig(slow_rate=1.0, slow_s=0.3)
        with pytest.raises(DriverTimeout):
            await t.measure(samples=1, timeout=0.1, point_id="late")
        assert sim.requests[-1].verb == "STOP"
        sim.faults.config = FaultConfig()
        r = await t.measure(samples=1, timeout=1, point_id="next")
        assert r.point_id == "next"
        await t.close()


async def test_dropped_link_reconnects_once(world):
    async with tracker_sim(world) as sim:
        t = LtpTracker({"url": url(sim, "tcp")})
        await t.connect(timeout=5)
        sim.faults.config = FaultConfig(drop_rate=1.0)
        with pytest.raises(ConnectFailed):
            await t.measure(samples=1, timeout=1)
        sim.faults.config = FaultConfig()
        r = await t.measure(samples=1, timeout=1, point_id="after")
        assert r.point_id == "after"
        hellos = [r for r in sim.requests if r.verb == "HELLO"]
        assert len(hellos) >= 2
        await t.close()
        no_retry = LtpTracker({"url": url(sim, "tcp"), "reconnect": False})
        await no_retry.connect(timeout=5)
        sim.faults.config = FaultConfig(drop_rate=1.0)
        with pytest.raises(ConnectFailed, match="lost"):
            await no_retry.measure(samples=1, timeout=1)
        await no_retry.close()


async def test_samples_validated_before_sending(world):
    async with tracker_sim(world) as sim:
        t = LtpTracker({"url": url(sim, "tcp")})
        await t.connect(timeout=5)
        n = len(sim.requests)
        with pytest.raises(ConfigError):
            await t.measure(samples=0, timeout=1)
        assert len(sim.requests) == n
        await t.close()


async def test_connect_refused_and_timeout():
    silent = []
    server = await asyncio.start_server(lambda r, w: silent.append(w), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    t = LtpTracker({"url": f"tcp://127.0.0.1:{port}"})
    with pytest.raises(DriverTimeout):
        await t.connect(timeout=0.2)  # the server never answers HELLO
    server.close()
    for w in silent:
        w.close()
    await server.wait_closed()
    with pytest.raises(ConnectFailed):
        await t.connect(timeout=1)
    await t.close()


# --- scripted bridges over an in-memory transport ------------------------------------------------
class ScriptedTransport:
    """Answers each written request line with ``reply(tag, verb) -> bytes``."""

    url = "scripted://"

    def __init__(self, reply):
        self.reply = reply
        self.inbox = bytearray()
        self.written: list[bytes] = []
        self.is_open = True

    async def open(self, *, timeout):
        return None

    async def write(self, data):
        self.written.append(data)
        tag, verb = data.decode().split()[:2]
        self.inbox += self.reply(tag, verb)

    async def read(self, max_bytes=4096, *, timeout):
        if not self.inbox:
            if not self.is_open:
                raise TransportError("closed")
            await asyncio.sleep(min(timeout, 0.01))
            raise TransportTimeout("nothing")
        data = bytes(self.inbox[:max_bytes])
        del self.inbox[:max_bytes]
        return data

    async def close(self):
        self.is_open = False


def connected_tracker(reply) -> LtpTracker:
    t = LtpTracker({"url": "tcp://127.0.0.1:1", "request_timeout_s": 0.3, "reply_margin_s": 0.0})
    t._stream = LineStream(ScriptedTransport(reply))
    t.state = "connected"
    return t


GOOD = "x=1000 y=2000 z=-500 sx=0.001 sy=0.001 sz=0.002 n=3 rms=0.002 t=2026-01-05T10:11:13.101Z"


@pytest.mark.parametrize(
    ("reply", "error"),
    [
        ("{tag} ERR 11 NO_TARGET", BeamLost),
        ("{tag} ERR 15 TIMEOUT", DriverTimeout),
        ("{tag} ERR 16 ABORTED", MeasurementError),
        ("{tag} ERR 14 BUSY", DriverTimeout),  # retried until the deadline, then retryable
        ('{tag} ERR 77 NEW_CODE msg="from the future"', MeasurementError),
        ("{tag} OK y=1 z=2", UnexpectedReply),
        ("{tag} OK x=a y=1 z=2", UnexpectedReply),
        ("{tag} OK x=nan y=1 z=2", UnexpectedReply),
        ("{tag} OK id=OTHER x=1 y=1 z=2", UnexpectedReply),
        ("999 OK " + GOOD, DriverTimeout),  # only a stale reply: the real one never comes
        ("garbage\x01\x02", DriverTimeout),
    ],
)
async def test_bad_replies_give_typed_errors(reply, error):
    t = connected_tracker(lambda tag, verb: (reply.format(tag=tag) + "\r\n").encode())
    with pytest.raises(error):
        await t.measure(samples=3, timeout=0.2, point_id="P1")
    await t.close()


async def test_units_conversion_and_timestamp():
    t = connected_tracker(lambda tag, verb: f"{tag} OK {GOOD}\r\n".encode())
    r = await t.measure(samples=3, timeout=1)
    assert r.position_m == pytest.approx((1.0, 2.0, -0.5))
    assert r.std_m == pytest.approx((1e-6, 1e-6, 2e-6)) and r.rms_m == pytest.approx(2e-6)
    assert r.timestamp == pytest.approx(1767607873.101)
    with pytest.raises(OperationError, match="ERR 2"):
        t2 = connected_tracker(lambda tag, verb: f"{tag} ERR 2 UNKNOWN_VERB\r\n".encode())
        await t2.status()


lines = st.one_of(
    st.binary(max_size=80).map(lambda b: b.replace(b"\n", b"")),
    st.sampled_from(
        [b"* EVT BEAM state=BROKEN", b"* EVT FAULT code=50", b"* EVT", b"1 OK", b"x" * 700]
    ),
)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.lists(lines, max_size=6), st.booleans())
def test_arbitrary_noise_before_reply_never_crashes(noise, answer):
    async def run():
        def reply(tag, verb):
            out = b"".join(n + b"\r\n" for n in noise)
            if answer:
                out += f"{tag} OK {GOOD}\r\n".encode()
            return out

        t = connected_tracker(reply)
        try:
            r = await t.measure(samples=1, timeout=0.05)
        except RobocalError as err:
            assert isinstance(err, DriverTimeout | ProtocolError | MeasurementError)
            return None
        finally:
            await t.close()
        return r

    result = asyncio.run(run())
    if answer and result is not None:
        assert result.position_m == pytest.approx((1.0, 2.0, -0.5))
