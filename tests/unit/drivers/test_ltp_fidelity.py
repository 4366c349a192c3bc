"""The LTP/1 driver against bridges that hold it to docs/protocols/ltp1.md (issue 13, 8-11)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

import numpy as np
import pytest

from robocal.drivers.ltp import LtpTracker, decimal_text, wire_point_id
from robocal.drivers.sim import LtpSimOptions, LtpTrackerSimulator
from robocal.errors import ConfigError, ConnectFailed, DriverTimeout, MeasurementError

GOOD = "x=1000 y=2000 z=-500 sx=0.001 sy=0.001 sz=0.002 n=1 rms=0.002 t=2026-01-05T10:11:13.101Z"
#: verb -> (delay in seconds, reply after the tag) for the strict bridge.
Script = dict[str, tuple[float, str]]


class StrictBridge:
    """A TCP bridge that enforces one outstanding request (STOP may interrupt a MEAS).

    Replies come after the scripted delay; a request that arrives while another is
    unanswered is a ``violation`` and gets ``ERR 14 BUSY``, as a real bridge would answer.
    """

    def __init__(self, script: Script, meas_reply: Callable[[str], str] | None = None) -> None:
        self.script = script
        self.meas_reply = meas_reply
        self.received: list[str] = []
        self.violations: list[str] = []
        self.port = 0
        self._outstanding: dict[str, tuple[str, asyncio.Task[None]]] = {}
        self._server: asyncio.Server | None = None
        self._writers: list[asyncio.StreamWriter] = []

    async def __aenter__(self) -> StrictBridge:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._server is not None
        self._server.close()
        for _, task in list(self._outstanding.values()):
            task.cancel()
        for w in self._writers:
            w.close()
        with contextlib.suppress(Exception):
            async with asyncio.timeout(2):
                await self._server.wait_closed()

    @property
    def url(self) -> str:
        return f"tcp://127.0.0.1:{self.port}"

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        # A new connection is a new session: whatever the last one left running is dropped.
        for _, task in self._outstanding.values():
            task.cancel()
        self._outstanding = {}
        self._writers.append(writer)
        with contextlib.suppress(
            ConnectionError, asyncio.IncompleteReadError, asyncio.CancelledError
        ):
            while True:
                line = (await reader.readuntil(b"\r\n"))[:-2].decode("ascii")
                self.received.append(line)
                tag, verb = line.split(" ")[:2]
                busy = [v for v, _ in self._outstanding.values()]
                if busy and not (verb == "STOP" and busy == ["MEAS"]):
                    self.violations.append(f"{verb} while {busy} unanswered")
                    writer.write(f'{tag} ERR 14 BUSY msg="{busy[0]} unanswered"\r\n'.encode())
                    continue
                if verb == "STOP" and busy:
                    ((mtag, (_, mtask)),) = self._outstanding.items()
                    mtask.cancel()
                    del self._outstanding[mtag]
                    writer.write(f'{mtag} ERR 16 ABORTED msg="stopped"\r\n'.encode())
                delay, text = self.script.get(verb, (0.0, "OK"))
                if verb == "MEAS" and self.meas_reply is not None:
                    text = self.meas_reply(line)
                task = asyncio.create_task(self._answer(writer, tag, delay, text))
                self._outstanding[tag] = (verb, task)

    async def _answer(
        self, writer: asyncio.StreamWriter, tag: str, delay: float, text: str
    ) -> None:
        if delay:
            await asyncio.sleep(delay)
        self._outstanding.pop(tag, None)
        if text != "never":
            writer.write(f"{tag} {text}\r\n".encode())


SETUP: Script = {
    "HELLO": (0.0, "OK proto=LTP/1 vendor=x model=y serial=1 fw=1 bridge=strict"),
    "STATUS?": (0.0, "OK ready=1 init=1 beam=LOCKED units=mm frame=tracker"),
    "SMR": (0.0, "OK type=RRR15 offset_mm=0.000"),
    "UNITS": (0.0, "OK len=mm ang=deg"),
    "FRAME": (0.0, "OK name=tracker"),
}


async def test_backslash_in_a_device_fault_message_is_not_lost():
    """Item 8: a Windows path in msg= used to be dropped as garbage, surfacing as a timeout."""
    script = {**SETUP, "MEAS": (0.0, r'ERR 50 DEVICE_FAULT msg="C:\trk\emscon.cfg: no link"')}
    async with StrictBridge(script) as bridge:
        t = LtpTracker({"url": bridge.url, "request_timeout_s": 1.0, "reply_margin_s": 0.2})
        await t.connect(timeout=2)
        with pytest.raises(
            MeasurementError, match=r"DEVICE_FAULT \(C:\\trk\\emscon.cfg: no link\)"
        ):
            await t.measure(samples=1, timeout=0.3)
        assert t.bad_lines == 0
        await t.close()


async def test_no_second_request_while_stop_is_unanswered():
    """Item 9: after a MEAS timeout the driver waits for the late STOP before the next MEAS."""
    script = {**SETUP, "MEAS": (0.4, "never"), "STOP": (0.25, "OK")}
    async with StrictBridge(script) as bridge:
        t = LtpTracker({"url": bridge.url, "request_timeout_s": 0.1, "reply_margin_s": 0.0})
        await t.connect(timeout=2)
        with pytest.raises(DriverTimeout):
            await t.measure(samples=1, timeout=0.05, point_id="P1")
        assert [line.split(" ")[1] for line in bridge.received[-2:]] == ["MEAS", "STOP"]
        bridge.script["MEAS"] = (0.0, "OK id=P2 " + GOOD)
        r = await t.measure(samples=1, timeout=1.0, point_id="P2")
        assert r.position_m == pytest.approx((1.0, 2.0, -0.5))
        await t.close()
        assert bridge.violations == []
        assert bridge.received[-1].endswith(" BYE")


async def test_no_bye_while_hello_is_unanswered():
    async with StrictBridge({**SETUP, "HELLO": (5.0, "never")}) as bridge:
        t = LtpTracker({"url": bridge.url})
        with pytest.raises(DriverTimeout):
            await t.connect(timeout=0.1)
        assert [line.split(" ")[1] for line in bridge.received] == ["HELLO"]
        assert bridge.violations == []


async def test_a_reply_that_never_comes_reopens_the_link():
    script = {**SETUP, "MEAS": (30.0, "never"), "STOP": (30.0, "never")}
    async with StrictBridge(script) as bridge:
        t = LtpTracker({"url": bridge.url, "request_timeout_s": 0.1, "reply_margin_s": 0.0})
        await t.connect(timeout=2)
        with pytest.raises(DriverTimeout):
            await t.measure(samples=1, timeout=0.05)
        hellos = sum(1 for line in bridge.received if line.split(" ")[1] == "HELLO")
        bridge.script.update({"MEAS": (0.0, "OK " + GOOD), "STOP": (0.0, "OK")})
        # The stuck bridge session is left for a fresh one, which answers.
        r = await t.measure(samples=1, timeout=0.5)
        assert r.position_m == pytest.approx((1.0, 2.0, -0.5))
        assert sum(1 for line in bridge.received if line.split(" ")[1] == "HELLO") == hellos + 1
        await t.close()


async def test_busy_is_retried():
    answers = iter(["ERR 14 BUSY", 'ERR 14 BUSY msg="still measuring"', "OK " + GOOD])
    async with StrictBridge(SETUP, meas_reply=lambda line: next(answers)) as bridge:
        t = LtpTracker({"url": bridge.url})
        await t.connect(timeout=2)
        r = await t.measure(samples=1, timeout=1.0)
        assert r.position_m == pytest.approx((1.0, 2.0, -0.5))
        assert sum(1 for line in bridge.received if " MEAS " in line) == 3
        await t.close()


async def test_frame_is_set_and_checked(world):
    """Item 10: a bridge left in another frame is put back into the tracker frame."""
    world.move([0.25] * world.dof)
    sim = LtpTrackerSimulator(world, LtpSimOptions(time_scale=0.0, initial_frame="cell"))
    await sim.start_tcp()
    try:
        t = LtpTracker({"url": f"tcp://127.0.0.1:{sim.port}"})
        await t.connect(timeout=2)
        assert sim.frame == "tracker"
        r = await t.measure(samples=5, timeout=1.0)
        sigma = np.asarray(world.measure(1).sigma_m)
        assert np.all(
            np.abs(np.asarray(r.position_m) - world.true_reflector_position()) < 6 * sigma
        )
        await t.close()
    finally:
        await sim.stop()


async def test_a_bridge_that_keeps_its_frame_is_refused():
    script = {**SETUP, "FRAME": (0.0, "OK name=cell")}
    async with StrictBridge(script) as bridge:
        t = LtpTracker({"url": bridge.url})
        with pytest.raises(ConnectFailed, match="frame"):
            await t.connect(timeout=2)
    script = {**SETUP, "STATUS?": (0.0, "OK ready=1 init=1 units=mm frame=cell")}
    async with StrictBridge(script) as bridge:
        with pytest.raises(ConnectFailed, match="frame"):
            await LtpTracker({"url": bridge.url}).connect(timeout=2)


async def test_point_ids_are_made_valid_or_refused(world):
    """Item 11: an id with a space used to go out as id="P 7"."""
    assert wire_point_id("P 7") == "P_7"
    assert wire_point_id('c"1/2') == "c_1_2"
    assert wire_point_id("cafe\u0301-3") == "cafe_-3"
    for bad in ("", "x" * 65):
        with pytest.raises(ConfigError):
            wire_point_id(bad)
    sim = LtpTrackerSimulator(world, LtpSimOptions(time_scale=0.0))
    await sim.start_tcp()
    try:
        t = LtpTracker({"url": f"tcp://127.0.0.1:{sim.port}"})
        await t.connect(timeout=2)
        r = await t.measure(samples=1, timeout=1.0, point_id="P 7")
        assert r.point_id == "P 7"
        assert sim.requests[-1].args["id"] == "P_7"
        n = len(sim.requests)
        with pytest.raises(ConfigError):
            await t.measure(samples=1, timeout=1.0, point_id="y" * 80)
        assert len(sim.requests) == n
        await t.close()
    finally:
        await sim.stop()


def test_decimals_are_sent_without_exponent():
    assert decimal_text(0.01) == "0.01" and decimal_text(1e-5) == "0.00001"
    assert (
        decimal_text(2.0) == "2" and decimal_text(-1e-9) == "0" and decimal_text(-1.25) == "-1.25"
    )


async def test_small_stability_band_is_a_valid_decimal(world):
    sim = LtpTrackerSimulator(world, LtpSimOptions(time_scale=0.0))
    await sim.start_tcp()
    try:
        t = LtpTracker({"url": f"tcp://127.0.0.1:{sim.port}", "stab_mm": 1e-5})
        await t.connect(timeout=2)
        await t.measure(samples=1, timeout=1.0)  # "1e-05" used to get ERR 3 BAD_ARG
        assert sim.requests[-1].args["stab_mm"] == "0.00001"
        await t.close()
    finally:
        await sim.stop()
