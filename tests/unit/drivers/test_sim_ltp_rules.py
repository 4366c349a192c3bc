"""The LTP/1 simulator follows docs/protocols/ltp1.md, checked with a raw line client."""

from __future__ import annotations

import asyncio
import contextlib
import math
import re

import pytest

from robocal.drivers.sim import LtpSimOptions, LtpTrackerSimulator

ERR_LINE = re.compile(r'[A-Za-z0-9]{1,8} ERR [0-9]+ [A-Z][A-Z0-9_]*(?: msg="[ -!#-~]*")?')
EVENT_LINE = re.compile(r"\* EVT [A-Z][A-Z0-9_]*(?: [a-z_]+=[!#-~]+)*")


class Client:
    """A minimal LTP/1 client on a raw socket: one request, read to its tagged reply."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.events: list[str] = []
        self.lines: list[str] = []

    async def line(self, timeout: float = 2.0) -> str:
        raw = await asyncio.wait_for(self.reader.readuntil(b"\r\n"), timeout)
        text = raw[:-2].decode("ascii")
        self.lines.append(text)
        return text

    async def send(self, line: bytes | str) -> None:
        self.writer.write((line.encode() if isinstance(line, str) else line) + b"\r\n")
        await self.writer.drain()

    async def ask(self, line: str) -> str:
        await self.send(line)
        tag = line.split(" ", 1)[0]
        while True:
            got = await self.line()
            if got.startswith("* "):
                self.events.append(got)
                continue
            assert got.split(" ", 1)[0] == tag, got
            return got


@contextlib.asynccontextmanager
async def client(world, **options):
    sim = LtpTrackerSimulator(world, LtpSimOptions(time_scale=0.0, **options))
    port = await sim.start_tcp()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    c = Client(reader, writer)
    try:
        yield sim, c
    finally:
        writer.close()
        with contextlib.suppress(Exception):
            await writer.wait_closed()
        await sim.stop()
    for line in c.lines:
        if " ERR " in line:
            assert ERR_LINE.fullmatch(line), line
        if line.startswith("* "):
            assert EVENT_LINE.fullmatch(line), line


def values(reply: str) -> dict[str, str]:
    return dict(tok.split("=", 1) for tok in reply.split(" ")[2:])


async def test_weather_with_explicit_values_overrides_the_station(world):
    async with client(world) as (_, c):
        assert values(await c.ask("1 WEATHER"))["source"] == "station"
        got = values(await c.ask("2 WEATHER temp=25.5 press=1000 hum=50"))
        assert got == {"temp": "25.50", "press": "1000.0", "hum": "50.0", "source": "manual"}
        meas = values(await c.ask("3 MEAS n=2"))
        assert (meas["temp"], meas["press"], meas["hum"]) == ("25.50", "1000.0", "50.0")
        status = values(await c.ask("4 STATUS?"))
        assert status["temp"] == "25.50"
        assert (await c.ask("5 WEATHER temp=abc")).startswith("5 ERR 3 BAD_ARG")
        assert (await c.ask("6 WEATHER temp=80")).startswith("6 ERR 30 ENV_OUT_OF_RANGE")
        assert values(await c.ask("7 WEATHER"))["temp"] == "25.50"


async def test_error_messages_are_always_quoted(world):
    async with client(world) as (_, c):
        assert await c.ask("1 FRAME name=FLY") == '1 ERR 3 BAD_ARG msg="unknown frame FLY"'
        assert (await c.ask("2 NOPE")).startswith('2 ERR 2 UNKNOWN_VERB msg="')


@pytest.mark.parametrize(
    "line",
    ["7 MEAS n", "7 MEAS  n=1", "7 hello", '7 MEAS id="a"b', "7", "7 MEAS n=1 n=2"],
)
async def test_syntax_errors_get_a_tagged_err_1(world, line):
    async with client(world) as (_, c):
        reply = await c.ask(line)
        assert reply.startswith('7 ERR 1 SYNTAX msg="'), reply


async def test_untagged_garbage_gets_an_event_without_spaces(world):
    async with client(world) as (_, c):
        await c.send("!! what")
        assert await c.line() == "* EVT FAULT code=1 msg=SYNTAX"
        assert (await c.ask("1 HELLO proto=LTP/1")).startswith("1 OK")


async def test_over_long_request_with_readable_tag_gets_a_tagged_reply(world):
    async with client(world) as (_, c):
        reply = await c.ask("42 MEAS id=" + "x" * 600)
        assert reply.startswith('42 ERR 1 SYNTAX msg="line longer than 512')
        assert (await c.ask("43 STATUS?")).startswith("43 OK")


async def test_smr_offset_moves_the_reading_along_the_beam(world):
    world.move([0.2] * world.dof)
    async with client(world) as (sim, c):
        assert values(await c.ask("1 SMR type=RRR15 offset_mm=5"))["offset_mm"] == "5.000"
        assert sim.smr_offset_mm == 5.0
        shifted = values(await c.ask("2 MEAS n=1"))
        assert values(await c.ask("3 SMR type=RRR15"))["offset_mm"] == "0.000"
        plain = values(await c.ask("4 MEAS n=1"))
        r = [math.dist((0, 0, 0), [float(v[k]) for k in "xyz"]) for v in (shifted, plain)]
        sigma = 1e3 * max(world.measure(1).sigma_m)
        assert r[0] - r[1] == pytest.approx(5.0, abs=10 * sigma)
        assert (await c.ask("5 SMR type=RRR15 offset_mm=far")).startswith("5 ERR 3 BAD_ARG")


@pytest.mark.parametrize(
    "request_",
    [
        "INIT mode=quick",
        "MEAS mode=slow",
        "MEAS n=0",
        "MEAS n=2 dur_ms=100",
        "MEAS id=a/b",
        "MEAS timeout_ms=-1",
        "WEATHER temp=abc",
        "FIND",
        "FIND x=1 y=2",
        "FIND x=a y=1 z=2",
        "FIND x=1 y=2 z=3 radius_mm=0",
        "FRAME",
        "UNITS len=furlong",
        "HELLO",
        "STATUS? extra=1",
        "SMR",
    ],
)
async def test_invalid_arguments_get_err_3_bad_arg(world, request_):
    async with client(world) as (_, c):
        reply = await c.ask("9 " + request_)
        assert reply.startswith('9 ERR 3 BAD_ARG msg="'), reply


async def test_valid_find_frame_and_units(world):
    async with client(world) as (sim, c):
        assert await c.ask("1 FIND x=1000 y=-20.5 z=3 radius_mm=50") == "1 OK beam=LOCKED"
        assert await c.ask("2 FRAME name=cell") == "2 OK name=cell"
        assert values(await c.ask("3 STATUS?"))["frame"] == "cell"
        assert await c.ask("4 UNITS len=m") == "4 OK len=m ang=deg"
        assert sim.units == "m"


async def test_stop_aborts_a_running_meas_which_answers_first(world):
    sim_opts = {"time_scale": 1.0, "sample_period_s": 0.0}
    sim = LtpTrackerSimulator(world, LtpSimOptions(**sim_opts))
    port = await sim.start_tcp()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    c = Client(reader, writer)
    try:
        await c.send("1 MEAS n=1 stab_ms=5000")
        assert (await c.ask("2 STATUS?")).startswith('2 ERR 14 BUSY msg="')
        assert (await c.ask("5 STOP now=1")).startswith('5 ERR 3 BAD_ARG msg="')
        await c.send("3 STOP")
        assert (await c.line()).startswith('1 ERR 16 ABORTED msg="')
        assert await c.line() == "3 OK"
        assert (await c.ask("4 STOP")) == "4 OK"  # nothing to abort
    finally:
        writer.close()
        await sim.stop()


def _doc_examples() -> list[list[str]]:
    """The code blocks of section 9 of docs/protocols/ltp1.md, as lists of lines."""
    from pathlib import Path

    doc = Path(__file__).resolve().parents[3] / "docs" / "protocols" / "ltp1.md"
    section = doc.read_text().split("## 9. Examples", 1)[1].split("## 10.", 1)[0]
    return [block.strip().splitlines() for block in section.split("```")[1::2]]


async def test_documented_examples_hold_against_the_simulator(world):
    """The description's session and malformed-line examples, replayed: same tags, same
    OK/ERR and codes, same reply keys (values depend on the device)."""
    blocks = _doc_examples()
    picked = ("11 ", "12 ", "13 ", "!!", "* EVT FAULT")
    malformed = [ln for ln in blocks[1] if ln[2:].startswith(picked)]
    for lines in (blocks[0], malformed):
        replies = [ln[2:] for ln in lines if ln.startswith("< ") and "EVT BEAM" not in ln]
        sent = [ln[2:] for ln in lines if ln.startswith("> ")]
        assert len(sent) == len(replies) > 2
        async with client(world) as (_, c):
            for request, want in zip(sent, replies, strict=True):
                await c.send(request)
                got = await c.line()
                while got.startswith("* EVT BEAM"):
                    got = await c.line()
                head = 2 if want.split(" ")[1] == "OK" else 3
                assert got.split(" ")[:head] == want.split(" ")[:head], (request, got)
                if head == 2:
                    assert set(values(got)) == set(values(want)), (request, got)
