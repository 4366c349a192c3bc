"""An LTP/1 laser-tracker simulator served over TCP and over a pty pair.

It implements the protocol as ``docs/protocols/ltp1.md`` describes it, including every
``ERR 3 BAD_ARG`` check, tagged ``ERR 1 SYNTAX`` replies and the WEATHER override.

The simulated tracker measures the reflector of the shared :class:`SimWorld` robot: the true
reflector position for the robot's actual joints plus the virtual tracker's noise, averaged
over ``n`` samples. Faults (beam breaks, unstable target, glitches, garbage lines, slow
replies, dropped connections) come from a :class:`FaultConfig`.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import random
import re
import time
import tty
from collections.abc import Awaitable, Callable, Mapping
from datetime import UTC, datetime
from typing import Any

import structlog
from pydantic import BaseModel, ConfigDict, Field

from robocal.drivers.sim._server import SessionServer, port_of
from robocal.drivers.sim.faults import FaultConfig
from robocal.drivers.sim.world import SimWorld
from robocal.errors import FramingError
from robocal.protocols import LineFramer, ltp

__all__ = ["LtpSimOptions", "LtpTrackerSimulator"]

_log = structlog.get_logger(__name__)

_UNIT_SCALE = {"mm": 1000.0, "m": 1.0, "in": 1000.0 / 25.4}

#: Arguments each verb accepts (anything else is ``ERR 3 BAD_ARG``).
_ARGS: dict[str, frozenset[str]] = {
    "HELLO": frozenset({"proto"}),
    "STATUS?": frozenset(),
    "INIT": frozenset({"mode"}),
    "SMR": frozenset({"type", "offset_mm"}),
    "UNITS": frozenset({"len", "ang"}),
    "FRAME": frozenset({"name"}),
    "WEATHER": frozenset({"temp", "press", "hum"}),
    "MEAS": frozenset({"id", "mode", "n", "dur_ms", "stab_mm", "stab_ms", "timeout_ms"}),
    "STOP": frozenset(),
    "HOME": frozenset(),
    "FIND": frozenset({"x", "y", "z", "radius_mm"}),
    "BYE": frozenset(),
}
#: A point id as docs/protocols/ltp1.md defines it.
POINT_ID = re.compile(r"[A-Za-z0-9_.:-]{1,64}")
_SMR_TYPE = re.compile(r"[A-Za-z0-9_.-]{1,16}")
_DECIMAL = re.compile(r"[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)")
_INTEGER = re.compile(r"[0-9]{1,12}")
#: Operating range of the simulated tracker: temp degC, press hPa, hum %.
_WEATHER_RANGE = {"temp": (0.0, 40.0), "press": (700.0, 1100.0), "hum": (0.0, 95.0)}


class _BadArg(Exception):
    """An argument is missing, unknown or malformed (answered ``ERR 3 BAD_ARG``)."""


def _only(args: Mapping[str, str], allowed: frozenset[str]) -> None:
    unknown = sorted(set(args) - allowed)
    if unknown:
        raise _BadArg(f"unknown argument {unknown[0][:20]}")


def _choice(args: Mapping[str, str], key: str, options: tuple[str, ...]) -> str | None:
    value = args.get(key)
    if value is not None and value not in options:
        raise _BadArg(f"{key} must be one of {'|'.join(options)}")
    return value


def _number(
    args: Mapping[str, str],
    key: str,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
) -> float | None:
    raw = args.get(key)
    if raw is None:
        return None
    if not _DECIMAL.fullmatch(raw):
        raise _BadArg(f"{key} must be a decimal number")
    value = float(raw)
    if (lo is not None and (value < lo or (lo_open and value == lo))) or (
        hi is not None and value > hi
    ):
        raise _BadArg(f"{key}={raw[:20]} out of range")
    return value


def _integer(args: Mapping[str, str], key: str, *, lo: int, hi: int) -> int | None:
    raw = args.get(key)
    if raw is None:
        return None
    if not _INTEGER.fullmatch(raw) or not lo <= int(raw) <= hi:
        raise _BadArg(f"{key} must be an integer in {lo}..{hi}")
    return int(raw)


class LtpSimOptions(BaseModel):
    """Behaviour of the simulated tracker bridge.

    ``time_scale`` multiplies the simulated settling (``stab_ms``) and sampling time
    (``n * sample_period_s``); 0 answers at once. ``event_rate`` is the probability of an
    unrelated ``* EVT WEATHER`` line before a reply (drivers must tolerate events).
    ``frames`` are the named frames ``FRAME`` may select besides ``tracker``: the pose of
    each in the tracker frame as ``(x_mm, y_mm, z_mm, rz_deg)``; ``initial_frame`` is the
    frame the bridge starts in (a bridge left in another frame by an earlier client).
    The weather station reads ``temp_c``, ``press_hpa``, ``hum_pct``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    time_scale: float = Field(default=0.001, ge=0.0)
    sample_period_s: float = Field(default=0.001, ge=0.0)
    event_rate: float = Field(default=0.0, ge=0.0, le=1.0)
    require_init: bool = False
    vendor: str = "robocal"
    model: str = "LT-SIM"
    serial: str = "0001"
    fw: str = "1.0"
    proto: str = ltp.PROTO
    temp_c: float = 20.4
    press_hpa: float = 1012.6
    hum_pct: float = 41.0
    frames: dict[str, tuple[float, float, float, float]] = Field(
        default_factory=lambda: {"cell": (1000.0, -500.0, 0.0, 90.0)}
    )
    initial_frame: str = "tracker"


Writer = Callable[[bytes], Awaitable[None]]


class _Session:
    """One client connection; requests are answered strictly one at a time."""

    def __init__(self, sim: LtpTrackerSimulator, write: Writer, close: Callable[[], None]) -> None:
        self.sim = sim
        self._write = write
        self._close = close
        self.framer = LineFramer(max_length=ltp.MAX_LINE)
        self.closed = False
        self.busy: asyncio.Task[None] | None = None
        self.lock = asyncio.Lock()
        #: Manual ``WEATHER`` override for this session (None: the station's values).
        self.weather: dict[str, float] | None = None

    async def open(self) -> None:
        """An LTP/1 bridge sends nothing before the first request."""

    async def send(self, line: str, *, garbage_ok: bool = True) -> None:
        if self.closed:
            return
        faults = self.sim.faults
        async with self.lock:
            try:
                if garbage_ok and faults.fire("garbage"):
                    await self._write(faults.garbage() + b"\r\n")
                await self._write(line.encode("ascii") + b"\r\n")
            except (OSError, ConnectionError, RuntimeError):
                self.closed = True

    async def reply(self, line: str) -> None:
        faults = self.sim.faults
        if faults.fire("slow"):
            await asyncio.sleep(faults.config.slow_s)
        if self.sim._event():
            await self.send(ltp.format_event("WEATHER", self.sim._weather_values(self)))
        await self.send(line)

    async def feed(self, data: bytes) -> None:
        self.framer.feed(data)
        for item in self.framer.lines():
            if self.closed:
                return
            if isinstance(item, FramingError):
                await self.refuse(
                    self.framer.dropped_head, f"line longer than {ltp.MAX_LINE} bytes"
                )
                continue
            await self.handle(item)

    async def refuse(self, line: bytes, why: str) -> None:
        """Answer a line that is not a request: tagged ERR 1 SYNTAX if a tag is readable."""
        tag = ltp.readable_tag(line)
        if tag is not None:
            await self.send(ltp.format_err(tag, ltp.ErrorCode.SYNTAX, msg=why[:120]))
        else:
            await self.send(ltp.format_event("FAULT", {"code": 1, "msg": "SYNTAX"}))

    async def handle(self, line: bytes) -> None:
        sim = self.sim
        try:
            req = ltp.parse_request(line)
        except FramingError as err:
            await self.refuse(line, str(err))
            return
        sim.requests.append(req)
        if sim.faults.fire("drop"):
            _log.info("ltp sim: dropping the connection (injected)")
            self._close()
            return
        if self.busy is not None and not self.busy.done():
            if req.verb == "STOP" and req.args:
                await self.send(sim.answer(req, self))  # ERR 3 BAD_ARG; the MEAS runs on
            elif req.verb == "STOP":
                # The aborted MEAS answers first (ERR 16 ABORTED), then STOP.
                self.busy.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await self.busy
                await self.send(ltp.format_ok(req.tag))
            else:
                await self.send(
                    ltp.format_err(req.tag, ltp.ErrorCode.BUSY, msg="a MEAS is running")
                )
            return
        if req.verb == "MEAS":
            self.busy = asyncio.create_task(self._meas(req), name="ltp-sim-meas")
            return
        await self.reply(sim.answer(req, self))
        if req.verb == "BYE" and not req.args:
            self._close()

    async def _meas(self, req: ltp.Request) -> None:
        try:
            await self.reply(await self.sim.measure(req, self))
        except asyncio.CancelledError:
            await self.send(ltp.format_err(req.tag, ltp.ErrorCode.ABORTED, msg="stopped"))

    async def stop(self) -> None:
        self.closed = True
        if self.busy is not None:
            self.busy.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self.busy


class LtpTrackerSimulator(SessionServer["_Session"]):
    """Simulated tracker bridge speaking LTP/1.

    Parameters
    ----------
    world, faults
        As for every :class:`WorldSimulator` (the reflector sits on the world's robot).
    options : LtpSimOptions, optional
        Tracker behaviour.

    Attributes
    ----------
    requests : list of ltp.Request
        Every request received (tests assert on it).
    """

    def __init__(
        self,
        world: SimWorld,
        options: LtpSimOptions | None = None,
        faults: FaultConfig | None = None,
    ) -> None:
        super().__init__(world, faults)
        self.options = options or LtpSimOptions()
        self.requests: list[ltp.Request] = []
        self.initialized = not self.options.require_init
        self.smr = "RRR15"
        self.smr_offset_mm = 0.0
        self.units = "mm"
        self.angle_units = "deg"
        self.frame = self.options.initial_frame
        self.beam = "LOCKED"
        self.port = 0
        self.pty_path: str | None = None
        self._tcp_session: _Session | None = None
        self._pty: tuple[int, int] | None = None
        self._pty_session: _Session | None = None
        self._t0 = time.monotonic()
        self._events = random.Random(self.faults.config.seed + 1)

    def _event(self) -> bool:
        return self.options.event_rate > 0 and self._events.random() < self.options.event_rate

    # --- protocol logic ------------------------------------------------------------------------
    def _now(self) -> str:
        return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"

    def _weather_values(self, session: _Session) -> dict[str, str]:
        o = self.options
        w = session.weather or {}
        return {
            "temp": f"{w.get('temp', o.temp_c):.2f}",
            "press": f"{w.get('press', o.press_hpa):.1f}",
            "hum": f"{w.get('hum', o.hum_pct):.1f}",
        }

    def answer(self, req: ltp.Request, session: _Session) -> str:
        """Return the reply line to a request other than MEAS."""
        try:
            return self._answer(req, session)
        except _BadArg as err:
            return ltp.format_err(req.tag, ltp.ErrorCode.BAD_ARG, msg=str(err))

    def _answer(self, req: ltp.Request, session: _Session) -> str:
        answer = _ANSWERS.get(req.verb)
        if req.verb not in _ARGS:
            return ltp.format_err(
                req.tag, ltp.ErrorCode.UNKNOWN_VERB, msg=f"unknown verb {req.verb}"
            )
        _only(req.args, _ARGS[req.verb])
        if answer is None:
            # STOP with nothing running, and BYE.
            return ltp.format_ok(req.tag)
        return answer(self, req.tag, req.args, session)

    # One method per verb (the table _ANSWERS below the class); ``a`` holds the arguments.
    def _verb_hello(self, tag: str, a: Mapping[str, str], _session: _Session) -> str:
        o = self.options
        if a.get("proto") != ltp.PROTO:
            raise _BadArg(f"proto must be {ltp.PROTO}")
        return ltp.format_ok(
            tag,
            {
                "proto": o.proto,
                "vendor": o.vendor,
                "model": o.model,
                "serial": o.serial,
                "fw": o.fw,
                "bridge": "robocal-sim/0.2",
            },
        )

    def _verb_status(self, tag: str, _a: Mapping[str, str], session: _Session) -> str:
        return ltp.format_ok(
            tag,
            {
                "ready": int(self.initialized),
                "beam": self.beam,
                "init": int(self.initialized),
                "smr": self.smr,
                "units": self.units,
                "frame": self.frame,
                **self._weather_values(session),
                "t": self._now(),
            },
        )

    def _verb_init(self, tag: str, a: Mapping[str, str], _session: _Session) -> str:
        _choice(a, "mode", ("smart", "full"))
        self.initialized = True
        return ltp.format_ok(tag)

    def _verb_smr(self, tag: str, a: Mapping[str, str], _session: _Session) -> str:
        smr = a.get("type")
        if smr is None or not _SMR_TYPE.fullmatch(smr):
            raise _BadArg("type=<reflector type> required")
        offset = _number(a, "offset_mm", lo=-1000.0, hi=1000.0)
        self.smr = smr
        self.smr_offset_mm = 0.0 if offset is None else offset
        return ltp.format_ok(tag, {"type": smr, "offset_mm": f"{self.smr_offset_mm:.3f}"})

    def _verb_units(self, tag: str, a: Mapping[str, str], _session: _Session) -> str:
        length = _choice(a, "len", tuple(_UNIT_SCALE)) or self.units
        ang = _choice(a, "ang", ("deg", "rad")) or self.angle_units
        self.units, self.angle_units = length, ang
        return ltp.format_ok(tag, {"len": length, "ang": ang})

    def _verb_frame(self, tag: str, a: Mapping[str, str], _session: _Session) -> str:
        name = a.get("name")
        if name is None:
            raise _BadArg("name= required")
        if name != "tracker" and name not in self.options.frames:
            raise _BadArg(f"unknown frame {name[:32]}")
        self.frame = name
        return ltp.format_ok(tag, {"name": name})

    def _verb_weather(self, tag: str, a: Mapping[str, str], session: _Session) -> str:
        given = {k: _number(a, k) for k in ("temp", "press", "hum") if k in a}
        for key, value in given.items():
            lo, hi = _WEATHER_RANGE[key]
            if value is None or not lo <= value <= hi:
                return ltp.format_err(
                    tag,
                    ltp.ErrorCode.ENV_OUT_OF_RANGE,
                    msg=f"{key}={a[key]} outside {lo:g}..{hi:g}",
                )
        if given:
            session.weather = {**(session.weather or {}), **given}  # type: ignore[dict-item]
        source = "manual" if session.weather else "station"
        return ltp.format_ok(tag, {**self._weather_values(session), "source": source})

    def _verb_home(self, tag: str, _a: Mapping[str, str], _session: _Session) -> str:
        self.beam = "LOCKED"
        return ltp.format_ok(tag, {"beam": self.beam})

    def _verb_find(self, tag: str, a: Mapping[str, str], _session: _Session) -> str:
        for key in ("x", "y", "z"):
            if _number(a, key) is None:
                raise _BadArg("FIND needs x= y= z= (current length units)")
        _number(a, "radius_mm", lo=0.0, lo_open=True)
        self.beam = "LOCKED"
        return ltp.format_ok(tag, {"beam": self.beam})

    async def measure(self, req: ltp.Request, session: _Session) -> str:
        """Run one MEAS: settle, sample, average; return the reply line."""
        o, a, tag = self.options, req.args, req.tag
        try:
            _only(a, _ARGS["MEAS"])
            point_id = a.get("id")
            if point_id is not None and not POINT_ID.fullmatch(point_id):
                raise _BadArg("id must be 1..64 of A-Z a-z 0-9 _ . : -")
            _choice(a, "mode", ("stationary", "fast"))
            n_arg = _integer(a, "n", lo=1, hi=100_000)
            dur_ms = _integer(a, "dur_ms", lo=1, hi=3_600_000)
            if n_arg is not None and dur_ms is not None:
                raise _BadArg("give n= or dur_ms=, not both")
            _number(a, "stab_mm", lo=0.0, lo_open=True)
            stab_ms = _integer(a, "stab_ms", lo=0, hi=3_600_000)
            timeout_ms = _integer(a, "timeout_ms", lo=1, hi=86_400_000)
        except _BadArg as err:
            return ltp.format_err(tag, ltp.ErrorCode.BAD_ARG, msg=str(err))
        if dur_ms is not None:
            n = max(1, int(dur_ms / 1000.0 / o.sample_period_s)) if o.sample_period_s else 1
        else:
            n = 10 if n_arg is None else n_arg
        stab_ms = 500 if stab_ms is None else stab_ms
        timeout_ms = 10_000 if timeout_ms is None else timeout_ms
        if not self.initialized:
            return ltp.format_err(tag, ltp.ErrorCode.NOT_INITIALIZED, msg="send INIT first")
        scale = o.time_scale
        if self.faults.fire("beam_break"):
            self.beam = "BROKEN"
            await session.send(ltp.format_event("BEAM", {"state": "BROKEN", "t": self._now()}))
            if timeout_ms / 1000 * scale > 0:
                await asyncio.sleep(min(timeout_ms / 1000 * scale, 1.0))
            reply = ltp.format_err(
                tag, ltp.ErrorCode.BEAM_BROKEN, msg="beam interrupted while settling"
            )
            # The beam comes back on its own (the SMR was only briefly occluded).
            self._track(self._relock(session))
            return reply
        if self.beam != "LOCKED":
            self.beam = "LOCKED"
            await session.send(ltp.format_event("BEAM", {"state": "LOCKED", "t": self._now()}))
        if self.faults.fire("unstable"):
            if timeout_ms / 1000 * scale > 0:
                await asyncio.sleep(min(timeout_ms / 1000 * scale, 1.0))
            return ltp.format_err(tag, ltp.ErrorCode.UNSTABLE, msg="stability not reached")
        settle = (stab_ms / 1000.0 + n * o.sample_period_s) * scale
        if settle > 0:
            await asyncio.sleep(settle)
        m = self.world.measure(n, glitch=self.faults.fire("glitch"))
        mean = self._in_frame(self._with_offset(m.mean_m))
        k = _UNIT_SCALE[self.units]
        tk = int((time.monotonic() - self._t0) * 1e6)
        values: dict[str, Any] = {}
        if point_id is not None:
            values["id"] = point_id
        values.update(
            {
                "x": f"{mean[0] * k:.5f}",
                "y": f"{mean[1] * k:.5f}",
                "z": f"{mean[2] * k:.5f}",
                "sx": f"{m.std_m[0] * k:.6f}",
                "sy": f"{m.std_m[1] * k:.6f}",
                "sz": f"{m.std_m[2] * k:.6f}",
                "n": m.n,
                "rms": f"{m.rms_m * k:.6f}",
                "t": self._now(),
                "tk": tk,
                **self._weather_values(session),
                "smr": self.smr,
            }
        )
        return ltp.format_ok(tag, values)

    def _with_offset(self, p_m: tuple[float, float, float]) -> tuple[float, float, float]:
        """Add the announced SMR distance offset along the beam (tracker frame, metres)."""
        r = math.sqrt(sum(v * v for v in p_m))
        if r == 0.0 or self.smr_offset_mm == 0.0:
            return p_m
        f = 1.0 + self.smr_offset_mm * 1e-3 / r
        return (p_m[0] * f, p_m[1] * f, p_m[2] * f)

    def _in_frame(self, p_m: tuple[float, float, float]) -> tuple[float, float, float]:
        """Express a tracker-frame point (metres) in the current frame."""
        if self.frame == "tracker":
            return p_m
        x, y, z, rz = self.options.frames[self.frame]
        dx, dy, dz = p_m[0] - x * 1e-3, p_m[1] - y * 1e-3, p_m[2] - z * 1e-3
        c, s = math.cos(math.radians(rz)), math.sin(math.radians(rz))
        return (c * dx + s * dy, -s * dx + c * dy, dz)

    async def _relock(self, session: _Session) -> None:
        await asyncio.sleep(0.001)
        if self.beam == "BROKEN":
            self.beam = "LOCKED"
            await session.send(ltp.format_event("BEAM", {"state": "LOCKED", "t": self._now()}))

    # --- TCP -----------------------------------------------------------------------------------
    async def start_tcp(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Serve LTP/1 on ``host:port`` (0 picks a free port); return the bound port."""
        self.port = port_of(await self._listen(self._on_client, host, port))
        _log.info("ltp sim listening", port=self.port)
        return self.port

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async def write(data: bytes) -> None:
            writer.write(data)
            await writer.drain()

        if self._tcp_session is not None and not self._tcp_session.closed:
            # One client at a time, as a real bridge.
            line = ltp.format_event("FAULT", {"code": 14, "msg": "BUSY"})
            with contextlib.suppress(Exception):
                await write(line.encode() + b"\r\n")
            return

        def close() -> None:
            session.closed = True
            writer.close()

        session = _Session(self, write, close)
        self._tcp_session = session
        try:
            await self._serve_session(reader, session, 4096)
        finally:
            if self._tcp_session is session:
                self._tcp_session = None

    # --- pty -------------------------------------------------------------------------------------
    async def start_pty(self) -> str:
        """Serve LTP/1 on a new pty pair; return the path of the device end (``/dev/pts/N``).

        The simulator works on the controlling side and keeps the device end open too, so a
        client may open and close it repeatedly.
        """
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._pty = (master, slave)
        self.pty_path = os.ttyname(slave)
        loop = asyncio.get_running_loop()

        async def write(data: bytes) -> None:
            view = memoryview(data)
            deadline = time.monotonic() + 5.0
            while view:
                try:
                    n = os.write(master, view)
                    view = view[n:]
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        raise
                    await asyncio.sleep(0.001)

        def line_stays_up() -> None:
            # A serial line has no connection to drop or close: BYE and an injected drop
            # only end the current exchange (a dropped request gets no reply).
            return None

        self._pty_session = _Session(self, write, line_stays_up)
        queue: asyncio.Queue[bytes] = asyncio.Queue()

        def readable() -> None:
            try:
                data = os.read(master, 4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                data = b""
            if data:
                queue.put_nowait(data)

        loop.add_reader(master, readable)

        async def pump() -> None:
            while True:
                data = await queue.get()
                session = self._pty_session
                if session is not None:
                    await session.feed(data)

        self._track(pump())
        _log.info("ltp sim on pty", path=self.pty_path)
        return self.pty_path

    # --- shutdown ------------------------------------------------------------------------------
    async def stop(self) -> None:
        """Stop serving (TCP and pty); idempotent."""
        self._close_listeners()
        for session in list(self._sessions):
            session.closed = True
            session._close()
        if self._pty_session is not None:
            await self._pty_session.stop()
        await self._stop_serving()
        if self._pty is not None:
            master, slave = self._pty
            asyncio.get_running_loop().remove_reader(master)
            for fd in (master, slave):
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._pty = None


#: The simulator's answer to each verb other than MEAS, STOP and BYE.
_ANSWERS: dict[str, Callable[[LtpTrackerSimulator, str, Mapping[str, str], _Session], str]] = {
    "HELLO": LtpTrackerSimulator._verb_hello,
    "STATUS?": LtpTrackerSimulator._verb_status,
    "INIT": LtpTrackerSimulator._verb_init,
    "SMR": LtpTrackerSimulator._verb_smr,
    "UNITS": LtpTrackerSimulator._verb_units,
    "FRAME": LtpTrackerSimulator._verb_frame,
    "WEATHER": LtpTrackerSimulator._verb_weather,
    "HOME": LtpTrackerSimulator._verb_home,
    "FIND": LtpTrackerSimulator._verb_find,
}
