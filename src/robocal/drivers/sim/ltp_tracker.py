"""An LTP/1 laser-tracker simulator served over TCP and over a pty pair.

The simulated tracker measures the reflector of the shared :class:`SimWorld` robot: the true
reflector position for the robot's actual joints plus the virtual tracker's noise, averaged
over ``n`` samples. Faults (beam breaks, unstable target, glitches, garbage lines, slow
replies, dropped connections) come from a :class:`FaultConfig`.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import time
import tty
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from typing import Any

import structlog
from pydantic import BaseModel, ConfigDict, Field

from robocal.drivers.sim.faults import FaultConfig, FaultInjector
from robocal.drivers.sim.world import SimWorld
from robocal.errors import FramingError
from robocal.protocols import LineFramer, ltp

__all__ = ["LtpSimOptions", "LtpTrackerSimulator"]

_log = structlog.get_logger(__name__)

_UNIT_SCALE = {"mm": 1000.0, "m": 1.0, "in": 1000.0 / 25.4}


class LtpSimOptions(BaseModel):
    """Behaviour of the simulated tracker bridge.

    ``time_scale`` multiplies the simulated settling (``stab_ms``) and sampling time
    (``n * sample_period_s``); 0 answers at once. ``event_rate`` is the probability of an
    unrelated ``* EVT WEATHER`` line before a reply (drivers must tolerate events).
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
            await self.send(
                ltp.format_event(
                    "WEATHER",
                    {
                        "temp": f"{self.sim.options.temp_c:.2f}",
                        "press": f"{self.sim.options.press_hpa:.1f}",
                        "hum": f"{self.sim.options.hum_pct:.1f}",
                    },
                )
            )
        await self.send(line)

    async def feed(self, data: bytes) -> None:
        self.framer.feed(data)
        for item in self.framer.lines():
            if self.closed:
                return
            if isinstance(item, FramingError):
                await self.send(ltp.format_event("FAULT", {"code": 1, "msg": "line too long"}))
                continue
            await self.handle(item)

    async def handle(self, line: bytes) -> None:
        sim = self.sim
        try:
            req = ltp.parse_request(line)
        except FramingError as err:
            tag = line.split(b" ", 1)[0].decode("ascii", "replace")
            if tag.isalnum() and tag.isascii() and len(tag) <= 8:
                await self.send(ltp.format_err(tag, ltp.ErrorCode.SYNTAX, msg=str(err)[:80]))
            else:
                await self.send(ltp.format_event("FAULT", {"code": 1, "msg": "syntax error"}))
            return
        sim.requests.append(req)
        if sim.faults.fire("drop"):
            _log.info("ltp sim: dropping the connection (injected)")
            self._close()
            return
        if self.busy is not None and not self.busy.done():
            if req.verb == "STOP":
                self.busy.cancel()
                await self.send(ltp.format_ok(req.tag))
            else:
                await self.send(ltp.format_err(req.tag, ltp.ErrorCode.BUSY))
            return
        if req.verb == "MEAS":
            self.busy = asyncio.create_task(self._meas(req), name="ltp-sim-meas")
            return
        await self.reply(sim.answer(req, self))
        if req.verb == "BYE":
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


class LtpTrackerSimulator:
    """Simulated tracker bridge speaking LTP/1.

    Parameters
    ----------
    world : SimWorld
        The robot whose reflector is measured.
    options : LtpSimOptions, optional
        Tracker behaviour.
    faults : FaultConfig, optional
        Injected faults.

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
        self.world = world
        self.options = options or LtpSimOptions()
        self.faults = FaultInjector(faults)
        self.requests: list[ltp.Request] = []
        self.initialized = not self.options.require_init
        self.smr = "RRR15"
        self.units = "mm"
        self.beam = "LOCKED"
        self.host = "127.0.0.1"
        self.port = 0
        self.pty_path: str | None = None
        self._server: asyncio.Server | None = None
        self._sessions: set[_Session] = set()
        self._tcp_session: _Session | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._pty: tuple[int, int] | None = None
        self._pty_session: _Session | None = None
        self._t0 = time.monotonic()
        self._events = random.Random(self.faults.config.seed + 1)

    def _event(self) -> bool:
        return self.options.event_rate > 0 and self._events.random() < self.options.event_rate

    # --- protocol logic ------------------------------------------------------------------------
    def _now(self) -> str:
        return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"

    def answer(self, req: ltp.Request, session: _Session) -> str:
        """Return the reply line to a request other than MEAS."""
        o, a, tag = self.options, req.args, req.tag
        if req.verb == "HELLO":
            if a.get("proto") != ltp.PROTO:
                return ltp.format_err(tag, ltp.ErrorCode.BAD_ARG, msg=f"proto must be {ltp.PROTO}")
            return ltp.format_ok(
                tag,
                {
                    "proto": o.proto,
                    "vendor": o.vendor,
                    "model": o.model,
                    "serial": o.serial,
                    "fw": o.fw,
                    "bridge": "robocal-sim/0.1",
                },
            )
        if req.verb == "STATUS?":
            return ltp.format_ok(
                tag,
                {
                    "ready": int(self.initialized),
                    "beam": self.beam,
                    "init": int(self.initialized),
                    "smr": self.smr,
                    "units": self.units,
                    "frame": "tracker",
                    "temp": f"{o.temp_c:.2f}",
                    "press": f"{o.press_hpa:.1f}",
                    "hum": f"{o.hum_pct:.1f}",
                    "t": self._now(),
                },
            )
        if req.verb == "INIT":
            self.initialized = True
            return ltp.format_ok(tag)
        if req.verb == "SMR":
            smr = a.get("type")
            if not smr:
                return ltp.format_err(tag, ltp.ErrorCode.BAD_ARG, msg="type= required")
            self.smr = smr
            return ltp.format_ok(tag, {"type": smr, "offset_mm": "0.000"})
        if req.verb == "UNITS":
            length, ang = a.get("len", "mm"), a.get("ang", "deg")
            if length not in _UNIT_SCALE or ang not in ("deg", "rad"):
                return ltp.format_err(tag, ltp.ErrorCode.BAD_ARG, msg="len=mm|m|in ang=deg|rad")
            self.units = length
            return ltp.format_ok(tag, {"len": length, "ang": ang})
        if req.verb == "FRAME":
            if a.get("name", "tracker") != "tracker":
                return ltp.format_err(tag, ltp.ErrorCode.BAD_ARG, msg="only frame tracker")
            return ltp.format_ok(tag, {"name": "tracker"})
        if req.verb == "WEATHER":
            return ltp.format_ok(
                tag,
                {
                    "temp": f"{o.temp_c:.2f}",
                    "press": f"{o.press_hpa:.1f}",
                    "hum": f"{o.hum_pct:.1f}",
                    "source": "station",
                },
            )
        if req.verb in ("HOME", "FIND"):
            self.beam = "LOCKED"
            return ltp.format_ok(tag, {"beam": self.beam})
        if req.verb == "STOP":
            return ltp.format_ok(tag)
        if req.verb == "BYE":
            return ltp.format_ok(tag)
        return ltp.format_err(tag, ltp.ErrorCode.UNKNOWN_VERB, msg=req.verb)

    async def measure(self, req: ltp.Request, session: _Session) -> str:
        """Run one MEAS: settle, sample, average; return the reply line."""
        o, a, tag = self.options, req.args, req.tag
        try:
            n = int(a.get("n", "10"))
            stab_ms = float(a.get("stab_ms", "500"))
            timeout_ms = float(a.get("timeout_ms", "10000"))
            float(a.get("stab_mm", "0.010"))
        except ValueError:
            return ltp.format_err(tag, ltp.ErrorCode.BAD_ARG, msg="numeric argument expected")
        if not 1 <= n <= 100_000 or stab_ms < 0 or timeout_ms <= 0:
            return ltp.format_err(tag, ltp.ErrorCode.BAD_ARG, msg="argument out of range")
        if not self.initialized:
            return ltp.format_err(tag, ltp.ErrorCode.NOT_INITIALIZED)
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
        k = _UNIT_SCALE[self.units]
        tk = int((time.monotonic() - self._t0) * 1e6)
        values: dict[str, Any] = {}
        if "id" in a:
            values["id"] = a["id"]
        values.update(
            {
                "x": f"{m.mean_m[0] * k:.5f}",
                "y": f"{m.mean_m[1] * k:.5f}",
                "z": f"{m.mean_m[2] * k:.5f}",
                "sx": f"{m.std_m[0] * k:.6f}",
                "sy": f"{m.std_m[1] * k:.6f}",
                "sz": f"{m.std_m[2] * k:.6f}",
                "n": m.n,
                "rms": f"{m.rms_m * k:.6f}",
                "t": self._now(),
                "tk": tk,
                "temp": f"{o.temp_c:.2f}",
                "press": f"{o.press_hpa:.1f}",
                "hum": f"{o.hum_pct:.1f}",
                "smr": self.smr,
            }
        )
        return ltp.format_ok(tag, values)

    async def _relock(self, session: _Session) -> None:
        await asyncio.sleep(0.001)
        if self.beam == "BROKEN":
            self.beam = "LOCKED"
            await session.send(ltp.format_event("BEAM", {"state": "LOCKED", "t": self._now()}))

    def _track(self, coro: Any) -> None:
        task = asyncio.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # --- TCP -----------------------------------------------------------------------------------
    async def start_tcp(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Serve LTP/1 on ``host:port`` (0 picks a free port); return the bound port."""
        self.host = host
        self._server = await asyncio.start_server(self._on_client, host, port)
        self.port = self._server.sockets[0].getsockname()[1]
        _log.info("ltp sim listening", port=self.port)
        return self.port

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)

        async def write(data: bytes) -> None:
            writer.write(data)
            await writer.drain()

        try:
            if self._tcp_session is not None and not self._tcp_session.closed:
                # One client at a time, as a real bridge.
                line = ltp.format_event("FAULT", {"code": 14, "msg": "another client is connected"})
                with contextlib.suppress(Exception):
                    await write(line.encode() + b"\r\n")
                return

            def close() -> None:
                session.closed = True
                writer.close()

            session = _Session(self, write, close)
            self._tcp_session = session
            self._sessions.add(session)
            try:
                while not session.closed:
                    data = await reader.read(4096)
                    if not data:
                        break
                    await session.feed(data)
            except ConnectionError:
                pass
            except asyncio.CancelledError:
                # stop() cancels handlers; end normally, or asyncio's stream callback on
                # Python 3.11 logs the cancelled task as an error.
                pass
            finally:
                await session.stop()
                self._sessions.discard(session)
                if self._tcp_session is session:
                    self._tcp_session = None
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()
            if task is not None:
                self._tasks.discard(task)

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
        if self._server is not None:
            self._server.close()
        for session in list(self._sessions):
            session.closed = True
            session._close()
        if self._pty_session is not None:
            await self._pty_session.stop()
        tasks = list(self._tasks)
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        if self._server is not None:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(2.0):
                    await self._server.wait_closed()
            self._server = None
        if self._pty is not None:
            master, slave = self._pty
            asyncio.get_running_loop().remove_reader(master)
            for fd in (master, slave):
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._pty = None
