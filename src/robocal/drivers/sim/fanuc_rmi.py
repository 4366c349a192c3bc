"""An asyncio FANUC RMI controller simulator (docs/protocols/fanuc-rmi.md).

Two listening sockets on loopback: ``FRC_Connect`` is accepted only on the connect port, whose
reply names the session port; the simulator then closes that connection. On the session port:
commands reply at once; instructions are queued (at most 8 in flight, RMIT-028 beyond),
SequenceIDs must be consecutive from 1 after ``FRC_Initialize`` (a gap gives RMIT-029 and
HOLD until ``FRC_Reset``), and each instruction replies when its simulated motion ends.
A target outside the joint limits, or an injected alarm, pushes ``FRC_SystemFault`` and holds.
Motion takes time (the world robot sweeps to the target); ``FRC_Abort`` halts it where it is
at once, drops the queued and running instructions without replies, and leaves RMI stopped
until the next ``FRC_Initialize``.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
import structlog
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from robocal.compensation import nominal_fk, nominal_ik
from robocal.drivers.sim._server import WorldSimulator, port_of
from robocal.drivers.sim.faults import FaultConfig
from robocal.drivers.sim.world import SimWorld
from robocal.errors import FramingError, ProtocolError, UnexpectedReply
from robocal.kinematics import matrix_to_wpr, wpr_to_matrix
from robocal.protocols import LineFramer
from robocal.protocols import fanuc_rmi as rmi

__all__ = ["FanucRmiSimulator", "FanucSimOptions"]

_log = structlog.get_logger(__name__)
_ABORTED = -1  # execute(): the instruction was cut short by FRC_Abort and gets no reply


class FanucSimOptions(BaseModel):
    """Behaviour of the simulated controller.

    ``time_scale`` multiplies simulated motion and wait times (0 = instantaneous, 1 = real
    time); the default is fast. ``joint_limits_deg`` overrides the world's robot limits.

    Behaviours of real controllers, each a switch (docs/protocols/fanuc-rmi.md):
    ``number_style="no_leading_zero"`` writes numbers in (-1, 1) as ``-.0123`` and `` .0456``;
    ``sequence_persists`` keeps NextSequenceID across ``FRC_Initialize`` and sessions
    (starting at ``initial_sequence_id``) and silently drops instructions with stale IDs;
    ``joint_key`` is the key of ``FRC_ReadJointAngles`` replies (older firmware: plural);
    ``alarm_at_connect`` starts with a resettable alarm (servo off until ``FRC_Reset``);
    ``session_port_delay_s`` is how long after ``FRC_Connect`` the session port starts
    listening (connections before that are refused). ``n_digital_io`` is the number of
    DIN/DOUT ports (1..n); ``max_linear_speed_mm_s`` bounds linear motion speed.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    major_version: int = 7
    minor_version: int = 0
    time_scale: float = Field(default=0.001, ge=0.0)
    number_style: Literal["json", "no_leading_zero"] = "json"
    sequence_persists: bool = False
    initial_sequence_id: int = Field(default=1, ge=1)
    joint_key: Literal["JointAngle", "JointAngles"] = "JointAngle"
    alarm_at_connect: bool = False
    session_port_delay_s: float = Field(default=0.0, ge=0.0)
    max_joint_speed_deg_s: float = Field(default=180.0, gt=0.0)
    min_motion_s: float = Field(default=0.012, ge=0.0)
    check_sequence_ids: bool = True
    idle_timeout_s: float | None = Field(default=None, gt=0.0)
    servo_ready: bool = True
    tp_enabled: bool = False
    rmi_move_selected: bool = False
    n_uframes: int = 9
    n_utools: int = 10
    n_position_registers: int = 200
    n_digital_io: int = Field(default=512, ge=1)
    max_linear_speed_mm_s: float = Field(default=2000.0, gt=0.0)
    joint_limits_deg: tuple[tuple[float, float], ...] | None = None


_ZERO_FRAME = {"X": 0.0, "Y": 0.0, "Z": 0.0, "W": 0.0, "P": 0.0, "R": 0.0}
_NO_LEADING_ZERO = re.compile(rb"(?<=[:,\[])( ?)(-?)0\.(?=[0-9])")


def _stale(seq: int, expected: int) -> bool:
    """True if ``seq`` was used before ``expected`` (within half the wrapping ID range)."""
    return 0 < (expected - seq) % rmi.MAX_SEQUENCE_ID < rmi.MAX_SEQUENCE_ID // 2


def normalise_wpr(w: float, p: float, r: float) -> tuple[float, float, float]:
    """Return the canonical W/P/R (degrees) of the same orientation: P in [-90, 90],
    W and R in (-180, 180], as a controller stores a Cartesian orientation."""
    cw, sw = math.cos(math.radians(w)), math.sin(math.radians(w))
    cp, sp = math.cos(math.radians(p)), math.sin(math.radians(p))
    cr, sr = math.cos(math.radians(r)), math.sin(math.radians(r))
    # R = Rz(r) Ry(p) Rx(w); read back the angles from its entries.
    r20, r21, r22 = -sp, cp * sw, cp * cw
    r10, r00 = sr * cp, cr * cp
    p2 = math.degrees(math.asin(max(-1.0, min(1.0, -r20))))
    if abs(r20) < 1.0 - 1e-12:
        w2 = math.degrees(math.atan2(r21, r22))
        r2 = math.degrees(math.atan2(r10, r00))
    else:  # gimbal lock: only W - R (or W + R) is defined; keep R
        w2, r2 = w - r if r20 < 0 else w + r, r
    return tuple(_wrap180(a) for a in (w2, p2, r2))  # type: ignore[return-value]


def _wrap180(a: float) -> float:
    a = math.fmod(a, 360.0)
    if a <= -180.0:
        a += 360.0
    elif a > 180.0:
        a -= 360.0
    return 0.0 if a == 0.0 else a


class _Session:
    """One client on the session port."""

    def __init__(
        self,
        sim: FanucRmiSimulator,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        self.sim = sim
        self.reader = reader
        self.writer = writer
        self.framer = LineFramer(max_length=rmi.MAX_LINE)
        self.write_lock = asyncio.Lock()
        self.queue: asyncio.Queue[tuple[int, rmi.Packet]] = asyncio.Queue()
        self.in_flight = 0
        self.closed = False
        self.executor: asyncio.Task[None] | None = None
        self.paused = asyncio.Event()
        self.paused.set()
        self.aborted = asyncio.Event()

    # --- output --------------------------------------------------------------------------------
    async def send(self, packet: Mapping[str, Any], *, delay_ok: bool = True) -> None:
        if self.closed:
            return
        faults = self.sim.faults
        if delay_ok and faults.fire("slow"):
            await asyncio.sleep(faults.config.slow_s)
        async with self.write_lock:
            try:
                if faults.fire("garbage"):
                    self.writer.write(faults.garbage() + b"\r\n")
                self.writer.write(self.sim.render(packet) + b"\r\n")
                await self.writer.drain()
            except (ConnectionError, RuntimeError):
                self.closed = True

    # --- input ---------------------------------------------------------------------------------
    async def run(self) -> None:
        self.executor = asyncio.create_task(self._execute(), name="rmi-sim-executor")
        idle = self.sim.options.idle_timeout_s
        try:
            while not self.closed:
                try:
                    async with asyncio.timeout(idle):
                        data = await self.reader.read(4096)
                except TimeoutError:
                    await self.send({"Communication": "FRC_Terminate"}, delay_ok=False)
                    break
                if not data:
                    break
                self.framer.feed(data)
                for item in self.framer.lines():
                    if isinstance(item, FramingError):
                        await self.send({"Command": "Unknown", "ErrorID": rmi.rmit(22)})
                        continue
                    if self.sim.faults.fire("drop"):
                        _log.info("rmi sim: dropping the connection (injected)")
                        self.closed = True
                        break
                    await self.handle(item)
                    if self.closed:
                        break
        except ConnectionError:
            pass
        finally:
            await self.shutdown()

    async def shutdown(self) -> None:
        self.closed = True
        if self.executor is not None:
            self.executor.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self.executor
        self.writer.close()
        with contextlib.suppress(Exception):
            await self.writer.wait_closed()

    async def handle(self, line: bytes) -> None:
        try:
            packet = rmi.decode(line)
        except ProtocolError:
            await self.send({"Command": "Unknown", "ErrorID": rmi.rmit(22)})
            return
        self.sim.received.append(dict(packet.body))
        if packet.category == "Communication":
            if packet.name == "FRC_Disconnect":
                await self.send({"Communication": "FRC_Disconnect", "ErrorID": 0}, delay_ok=False)
                self.closed = True
            else:
                await self.send({"Communication": packet.name, "ErrorID": rmi.rmit(26)})
        elif packet.category == "Command":
            await self.send(self.sim.command(packet, self))
        else:
            await self.instruction(packet)

    async def instruction(self, packet: rmi.Packet) -> None:
        sim = self.sim
        try:
            seq = packet.sequence_id
        except UnexpectedReply:
            seq = None
        reply: dict[str, Any] = {"Instruction": packet.name}
        if seq is not None:
            reply["SequenceID"] = seq
        if not sim.initialized:
            await self.send({**reply, "ErrorID": rmi.rmit(9)})
            return
        if seq is None:
            sim.hold = True
            await self.send({**reply, "ErrorID": rmi.rmit(29)})
            return
        if sim.hold:
            await self.send({**reply, "ErrorID": rmi.rmit(24)})
            return
        if self.in_flight >= rmi.MAX_IN_FLIGHT:
            await self.send({**reply, "ErrorID": rmi.rmit(28)})
            return
        persists = sim.options.sequence_persists and sim.options.check_sequence_ids
        if persists and _stale(seq, sim.next_sequence_id):
            # Newer controllers drop an instruction with an already used ID silently.
            sim.dropped_stale += 1
            return
        if sim.options.check_sequence_ids and seq != sim.next_sequence_id:
            sim.hold = True
            sim.last_alarm = f"RMIT-029 Invalid sequence ID {seq}, expected {sim.next_sequence_id}"
            await self.send({**reply, "ErrorID": rmi.rmit(29)})
            return
        sim.next_sequence_id = rmi.next_sequence_id(seq)
        self.in_flight += 1
        sim.max_in_flight = max(sim.max_in_flight, self.in_flight)
        await self.queue.put((seq, packet))

    async def _execute(self) -> None:
        sim = self.sim
        while True:
            seq, packet = await self.queue.get()
            await self.paused.wait()
            if not sim.initialized:
                self.in_flight = max(0, self.in_flight - 1)
                continue
            sim.moving = True
            try:
                error_id = await sim.execute(seq, packet, self)
            finally:
                sim.moving = False
                self.in_flight = max(0, self.in_flight - 1)
            if error_id == _ABORTED:  # FRC_Abort already flushed the queue: no reply
                continue
            if error_id is None:  # faulted: no reply, queue flushed
                self.flush()
                continue
            await self.send({"Instruction": packet.name, "ErrorID": error_id, "SequenceID": seq})

    def flush(self) -> None:
        while not self.queue.empty():
            self.queue.get_nowait()
        self.in_flight = 0

    def abort(self) -> None:
        """FRC_Abort: halt the robot where it is; queued and running instructions get no reply."""
        self.sim.world.halt()
        self.flush()
        self.aborted.set()
        self.aborted = asyncio.Event()
        self.paused.set()

    async def run_for(self, seconds: float) -> bool:
        """Wait ``seconds`` of motion or dwell; False if FRC_Abort came first."""
        aborted = self.aborted
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(seconds):
                await aborted.wait()
        return not aborted.is_set()


@dataclass(frozen=True)
class _Request:
    """A command or instruction being handled, with the session it came on."""

    packet: rmi.Packet
    session: _Session

    @property
    def name(self) -> str:
        """The packet's name (``FRC_...``)."""
        return self.packet.name

    @property
    def body(self) -> Mapping[str, Any]:
        """Every field of the packet."""
        return self.packet.body

    def ok(self, **fields: Any) -> dict[str, Any]:
        """A successful command reply carrying ``fields``."""
        return {"Command": self.name, "ErrorID": 0, **fields}

    def fail(self, error_id: int) -> dict[str, Any]:
        """A failed command reply with this ErrorID."""
        return {"Command": self.name, "ErrorID": error_id}

    def err(self, n: int) -> dict[str, Any]:
        """A command reply failing with alarm RMIT-``n``."""
        return self.fail(rmi.rmit(n))


_CommandHandler = Callable[["FanucRmiSimulator", _Request], dict[str, Any]]
_InstructionHandler = Callable[["FanucRmiSimulator", int, _Request], Awaitable[int | None]]


class FanucRmiSimulator(WorldSimulator):
    """Simulated R-30iB Plus controller with the RMI option, serving on loopback.

    Parameters
    ----------
    world : SimWorld
        The robot being moved.
    options : FanucSimOptions, optional
        Controller behaviour.
    faults : FaultConfig, optional
        Injected faults (garbage lines, slow replies, dropped connections, alarms).

    Attributes
    ----------
    received : list of dict
        Every packet received on the session port (tests assert on it).
    max_in_flight : int
        Most instructions ever accepted and not yet completed at once.
    sessions : int
        Number of sessions opened on the session port.
    uframes, utools : dict
        Stored user and tool frames (mm, degrees), by number.
    position_registers : dict
        Stored PRs: number -> ``{"Configuration": ..., "Position": ...}``.
    """

    def __init__(
        self,
        world: SimWorld,
        options: FanucSimOptions | None = None,
        faults: FaultConfig | None = None,
    ) -> None:
        super().__init__(world, faults)
        self.options = options or FanucSimOptions()
        lim = self.options.joint_limits_deg or world.joint_limits_deg
        self.joint_limits_deg = tuple(lim)
        self.received: list[dict[str, Any]] = []
        self.max_in_flight = 0
        self.sessions = 0
        self.uframes: dict[int, dict[str, float]] = {}
        self.utools: dict[int, dict[str, float]] = {}
        self.position_registers: dict[int, dict[str, Any]] = {}
        self.active_uframe = 0
        self.active_utool = 1
        self.digital_inputs: dict[int, bool] = {}
        self.digital_outputs: dict[int, bool] = {}
        self.override = 100
        self.next_sequence_id = self.options.initial_sequence_id
        self.dropped_stale = 0
        self.alarm_active = self.options.alarm_at_connect
        self.connect_port = 0
        self.main_port = 0
        self._session: _Session | None = None
        self._handshake_pending = False
        self._main_server: asyncio.Server | None = None
        self._t0 = time.monotonic()
        self._reset_state()

    def _reset_state(self) -> None:
        self.initialized = False
        self.hold = False
        self.moving = False
        if not self.options.sequence_persists:
            self.next_sequence_id = 1
        self.last_alarm = "SRVO-037 IMSTP input (Group:1)" if self.alarm_active else ""

    def render(self, packet: Mapping[str, Any]) -> bytes:
        """Encode a packet as this controller writes it (``number_style``)."""
        data = rmi.encode(packet)
        if self.options.number_style == "no_leading_zero":
            data = _NO_LEADING_ZERO.sub(
                lambda m: m.group(1) + (b"-." if m.group(2) else b" ."), data
            )
        return data

    # --- lifecycle -----------------------------------------------------------------------------
    async def start(
        self, host: str = "127.0.0.1", connect_port: int = 0, main_port: int = 0
    ) -> tuple[int, int]:
        """Listen on both ports (0 picks free ones); return ``(connect_port, main_port)``."""
        main = await self._listen(self._on_main, host, main_port)
        self.main_port = port_of(main)
        if self.options.session_port_delay_s > 0:
            # Not listening until a while after each FRC_Connect (see _listen_late).
            self._forget(main)
            await main.wait_closed()
        else:
            self._main_server = main
        self.connect_port = port_of(await self._listen(self._on_connect, host, connect_port))
        _log.info("rmi sim listening", connect_port=self.connect_port, main_port=self.main_port)
        return self.connect_port, self.main_port

    async def stop(self) -> None:
        """Close the listeners and any session; idempotent."""
        self._close_listeners()
        if self._session is not None:
            self._session.closed = True
            self._session.writer.close()
        await self._stop_serving()

    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Answer one FRC_Connect; then the controller closes the connection (``_listen``)."""
        try:
            framer = LineFramer(max_length=rmi.MAX_LINE)
            async with asyncio.timeout(10.0):
                while True:
                    data = await reader.read(4096)
                    if not data:
                        return
                    framer.feed(data)
                    try:
                        line = framer.next_line()
                    except FramingError:
                        line = b""
                    if line is not None:
                        break
            try:
                packet = rmi.decode(line)
            except ProtocolError:
                packet = None
            if packet is None or packet.body != {"Communication": "FRC_Connect"}:
                reply: dict[str, Any] = {"Communication": "FRC_Connect", "ErrorID": rmi.rmit(22)}
            elif self._session is not None and not self._session.closed:
                reply = {"Communication": "FRC_Connect", "ErrorID": rmi.rmit(26)}
            else:
                self._handshake_pending = True
                if self.options.session_port_delay_s > 0 and self._main_server is None:
                    self._track(self._listen_late())
                reply = {
                    "Communication": "FRC_Connect",
                    "ErrorID": 0,
                    "PortNumber": self.main_port,
                    "MajorVersion": self.options.major_version,
                    "MinorVersion": self.options.minor_version,
                }
            writer.write(rmi.encode(reply) + b"\r\n")
            await writer.drain()
        except (TimeoutError, ConnectionError):
            pass

    async def _listen_late(self) -> None:
        """Start listening on the session port ``session_port_delay_s`` after FRC_Connect."""
        await asyncio.sleep(self.options.session_port_delay_s)
        if self._main_server is None:
            self._main_server = await self._listen(self._on_main, self.host, self.main_port)

    async def _stop_listening_late(self) -> None:
        """After a session, the next FRC_Connect again finds the session port closed."""
        server, self._main_server = self._main_server, None
        if server is not None and self.options.session_port_delay_s > 0:
            self._forget(server)

    async def _on_main(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self._handshake_pending or (self._session is not None and not self._session.closed):
            return  # refused: _listen closes the connection
        self._handshake_pending = False
        await self._stop_listening_late()
        self._reset_state()
        self.sessions += 1
        session = _Session(self, reader, writer)
        self._session = session
        try:
            await session.run()
        finally:
            self._reset_state()
            if self._session is session:
                self._session = None

    # --- commands ------------------------------------------------------------------------------
    def _time_tag(self) -> int:
        return int((time.monotonic() - self._t0) * 1000) & 0x7FFFFFFF

    def command(self, packet: rmi.Packet, session: _Session) -> dict[str, Any]:
        """Return the reply to one command packet (the handler in ``_COMMANDS``)."""
        req = _Request(packet, session)
        handler = self._COMMANDS.get(packet.name)
        if handler is None:
            return req.err(13)
        return handler(self, req)

    def _get_status(self, req: _Request) -> dict[str, Any]:
        """FRC_GetStatus: servo, pendant, RMI and program state."""
        return req.ok(
            ServoReady=int(self.options.servo_ready and not self.alarm_active),
            TPMode=int(self.options.tp_enabled),
            RMIMotionStatus=int(self.initialized),
            ProgramStatus=0 if self.initialized and not self.hold else 1,
            SingleStepMode=0,
            NumberUTool=self.options.n_utools,
            NumberUFrame=self.options.n_uframes,
            NextSequenceID=self.next_sequence_id,
            Override=self.override,
        )

    def _initialize(self, req: _Request) -> dict[str, Any]:
        """FRC_Initialize: start RMI (refused with the pendant on, servo off or RMI running)."""
        if self.options.tp_enabled:
            return req.err(8)
        if not self.options.servo_ready or self.alarm_active:
            return req.err(7)
        if self.options.rmi_move_selected:
            return req.fail(7015)  # MEMO-015: RMI_MOVE is selected on the pendant
        if self.initialized:
            return req.err(15)
        self.initialized = True
        self.hold = False
        if not self.options.sequence_persists:
            self.next_sequence_id = 1
        return req.ok(GroupMask=int(req.body.get("GroupMask", 1) or 1))

    def _abort(self, req: _Request) -> dict[str, Any]:
        """FRC_Abort: halt at once, drop every instruction unanswered, stop RMI."""
        if not self.initialized:
            return req.err(9)
        self.initialized = False
        req.session.abort()
        q_deg = [round(math.degrees(v), 4) for v in self.world.q_actual_rad]
        _log.info("rmi sim: abort", q_deg=q_deg)
        return req.ok()

    def _reset(self, req: _Request) -> dict[str, Any]:
        """FRC_Reset: clear HOLD and the alarm."""
        self.hold = False
        self.alarm_active = False
        self.last_alarm = ""
        return req.ok()

    def _pause(self, req: _Request) -> dict[str, Any]:
        """FRC_Pause: hold the instruction queue."""
        req.session.paused.clear()
        return req.ok()

    def _continue(self, req: _Request) -> dict[str, Any]:
        """FRC_Continue: release the instruction queue."""
        req.session.paused.set()
        return req.ok()

    def _read_error(self, req: _Request) -> dict[str, Any]:
        """FRC_ReadError: the last alarm text."""
        return req.ok(Count=1, ErrorData=self.last_alarm or "")

    def _set_override(self, req: _Request) -> dict[str, Any]:
        """FRC_SetOverRide: speed override 1..100 %."""
        value = req.body.get("Value")
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 100:
            return req.err(5)
        self.override = value
        return req.ok()

    def _read_joint_angles(self, req: _Request) -> dict[str, Any]:
        """FRC_ReadJointAngles: where the robot is now (J1..J9, degrees)."""
        q = [math.degrees(v) for v in self.world.q_actual_rad]
        angles = {f"J{i + 1}": (q[i] if i < len(q) else 0.0) for i in range(9)}
        return req.ok(TimeTag=self._time_tag(), **{self.options.joint_key: angles})

    def _get_uframe_utool(self, req: _Request) -> dict[str, Any]:
        """FRC_GetUFrameUTool: the active user frame and tool numbers."""
        return req.ok(UFrameNumber=self.active_uframe, UToolNumber=self.active_utool)

    def _set_uframe_utool(self, req: _Request) -> dict[str, Any]:
        """FRC_SetUFrameUTool: select a user frame (0..n) and a tool (1..n)."""
        uf, ut = req.body.get("UFrameNumber"), req.body.get("UToolNumber")
        if not isinstance(uf, int) or not 0 <= uf <= self.options.n_uframes:
            return req.err(3)
        if not isinstance(ut, int) or not 1 <= ut <= self.options.n_utools:
            return req.err(2)
        self.active_uframe, self.active_utool = uf, ut
        return req.ok()

    def _uframe_data(self, req: _Request) -> dict[str, Any]:
        """FRC_ReadUFrameData and FRC_WriteUFrameData."""
        return self._frame_cmd(req, "FrameNumber", self.uframes, 3, self.options.n_uframes)

    def _utool_data(self, req: _Request) -> dict[str, Any]:
        """FRC_ReadUToolData and FRC_WriteUToolData."""
        return self._frame_cmd(req, "ToolNumber", self.utools, 2, self.options.n_utools)

    def _frame_cmd(
        self, req: _Request, key: str, store: dict[int, dict[str, float]], bad: int, count: int
    ) -> dict[str, Any]:
        """Read (or write, then read) frame ``body[key]`` of ``store``; RMIT-``bad`` if the
        number is not within 1..``count``."""
        n = req.body.get(key)
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= count:
            return req.err(bad)
        if req.name.startswith("FRC_Write"):
            if self.moving:
                return req.err(15)
            try:
                frame = rmi.parse_frame(req.body, "Frame")
            except ProtocolError:
                return req.err(23)
            store[n] = dict(zip("XYZWPR", frame, strict=True))
        return req.ok(**{key: n, "Frame": dict(store.get(n, _ZERO_FRAME))})

    def _register_number(self, req: _Request) -> int | None:
        """The command's RegisterNumber, or None when it is not a configured PR."""
        n = req.body.get("RegisterNumber")
        if isinstance(n, bool) or not isinstance(n, int):
            return None
        return n if 1 <= n <= self.options.n_position_registers else None

    def _read_position_register(self, req: _Request) -> dict[str, Any]:
        """FRC_ReadPositionRegister (zeros where nothing was written)."""
        n = self._register_number(req)
        if n is None:
            return req.err(4)
        stored = self.position_registers.get(
            n, {"Configuration": rmi.Configuration().fields(), "Position": dict(_ZERO_FRAME)}
        )
        return req.ok(RegisterNumber=n, **stored)

    def _write_position_register(self, req: _Request) -> dict[str, Any]:
        """FRC_WritePositionRegister, keeping W/P/R as a controller does."""
        n = self._register_number(req)
        if n is None:
            return req.err(4)
        try:
            pos = rmi.parse_frame(req.body, "Position")
        except ProtocolError:
            return req.err(23)
        config = req.body.get("Configuration")
        if not isinstance(config, Mapping):
            return req.err(23)
        uf = config.get("UFrameNumber")
        if not isinstance(uf, int) or not 0 <= uf <= self.options.n_uframes:
            return req.err(3)
        # UToolNumber is stored as given: whether a controller accepts 0 is not
        # documented, and the driver sends only configured tools (1..10).
        # A Cartesian PR holds an orientation: the controller keeps W/P/R in their
        # canonical ranges, so angles beyond them do not read back as written.
        position = dict(zip("XYZWPR", (*pos[:3], *normalise_wpr(*pos[3:])), strict=True))
        self.position_registers[n] = {"Configuration": dict(config), "Position": position}
        return req.ok(RegisterNumber=n)

    def _read_cartesian_position(self, req: _Request) -> dict[str, Any]:
        """FRC_ReadCartesianPosition: the tool centre in the active user frame (mm, degrees),
        by the controller's nominal kinematics from the actual joints."""
        uf, ut = self.active_uframe, self.active_utool
        position = self.tcp_position(self.world.q_actual_rad, uf, ut)
        config = rmi.Configuration(utool_number=ut, uframe_number=uf).fields()
        return req.ok(TimeTag=self._time_tag(), Configuration=config, Position=position,
                      Group=int(req.body.get("Group", 1) or 1))

    def _port_number(self, req: _Request) -> int | None:
        n = req.body.get("PortNumber")
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= self.options.n_digital_io:
            return None
        return n

    def _read_din(self, req: _Request) -> dict[str, Any]:
        """FRC_ReadDIN: one digital input, ``"ON"`` or ``"OFF"`` (inputs never set read OFF)."""
        n = self._port_number(req)
        if n is None:
            return req.err(38)
        on = self.digital_inputs.get(n, False)
        return req.ok(PortNumber=n, PortValue="ON" if on else "OFF")

    def _write_dout(self, req: _Request) -> dict[str, Any]:
        """FRC_WriteDOUT: set one digital output ON or OFF."""
        n = self._port_number(req)
        if n is None:
            return req.err(38)
        try:
            self.digital_outputs[n] = rmi.port_value(req.body)
        except ProtocolError:
            return req.err(21)
        return req.ok()

    _COMMANDS: ClassVar[dict[str, _CommandHandler]] = {
        "FRC_GetStatus": _get_status,
        "FRC_Initialize": _initialize,
        "FRC_Abort": _abort,
        "FRC_Reset": _reset,
        "FRC_Pause": _pause,
        "FRC_Continue": _continue,
        "FRC_ReadError": _read_error,
        "FRC_SetOverRide": _set_override,
        "FRC_ReadJointAngles": _read_joint_angles,
        "FRC_GetUFrameUTool": _get_uframe_utool,
        "FRC_SetUFrameUTool": _set_uframe_utool,
        "FRC_ReadUFrameData": _uframe_data,
        "FRC_WriteUFrameData": _uframe_data,
        "FRC_ReadUToolData": _utool_data,
        "FRC_WriteUToolData": _utool_data,
        "FRC_ReadPositionRegister": _read_position_register,
        "FRC_WritePositionRegister": _write_position_register,
        "FRC_ReadCartesianPosition": _read_cartesian_position,
        "FRC_ReadDIN": _read_din,
        "FRC_WriteDOUT": _write_dout,
    }

    # --- Cartesian positions -------------------------------------------------------------------
    def _frame(self, store: dict[int, dict[str, float]], n: int) -> NDArray[np.float64]:
        """Stored user or tool frame ``n`` as a (4, 4) transform, metres (identity if unset)."""
        return _matrix(store.get(n, _ZERO_FRAME))

    def tcp_position(self, q_rad: Any, uframe: int, utool: int) -> dict[str, float]:
        """Tool ``utool``'s centre at joints ``q_rad`` in user frame ``uframe`` (X..R, mm and
        degrees), by the nominal kinematics a controller uses."""
        T_base_flange = nominal_fk(self.world.cell.robot, np.asarray(q_rad, dtype=float))[0]
        T_base_tcp = T_base_flange @ self._frame(self.utools, utool)
        return _fields(np.linalg.inv(self._frame(self.uframes, uframe)) @ T_base_tcp)

    def joints_for(self, position: Mapping[str, float], uframe: int, utool: int,
                   seed_rad: Any) -> NDArray[np.float64] | None:
        """Joints (radians) putting tool ``utool``'s centre at ``position`` of user frame
        ``uframe``, closest to ``seed_rad``; None when unreachable within the limits."""
        T_uf_tcp = _matrix(position)
        T_base_flange = (self._frame(self.uframes, uframe) @ T_uf_tcp
                         @ np.linalg.inv(self._frame(self.utools, utool)))
        ik = nominal_ik(self.world.cell.robot, T_base_flange, np.asarray(seed_rad, dtype=float))
        return np.asarray(ik.q[0], dtype=float) if bool(ik.found[0]) else None

    # --- instructions --------------------------------------------------------------------------
    def _fault(self, seq: int, text: str, session: _Session) -> None:
        self.hold = True
        self.last_alarm = text
        _log.info("rmi sim: system fault", sequence_id=seq, alarm=text)
        self._track(session.send({"Communication": "FRC_SystemFault", "SequenceID": seq}))

    async def execute(self, seq: int, packet: rmi.Packet, session: _Session) -> int | None:
        """Run one instruction; return its reply ErrorID, None after a system fault, or
        ``_ABORTED`` when FRC_Abort cut it short (neither gets a reply)."""
        handler = self._INSTRUCTIONS.get(packet.name)
        if handler is None:
            return rmi.rmit(13)
        return await handler(self, seq, _Request(packet, session))

    async def _joint_motion_jrep(self, seq: int, req: _Request) -> int | None:
        """FRC_JointMotionJRep and FRC_JointRelativeJRep: a joint move (absolute angles, or
        increments added to the commanded ones) that takes simulated time."""
        body = req.body
        try:
            q_deg = rmi.joint_angles(body, self.world.dof)
        except ProtocolError:
            return rmi.rmit(23)
        if body.get("SpeedType", "Percent") != "Percent":
            return rmi.rmit(30)
        speed = body.get("Speed")
        if isinstance(speed, bool) or not isinstance(speed, int | float) or not 0 < speed <= 100:
            return rmi.rmit(31)
        if body.get("TermType", "FINE") not in ("FINE", "CNT", "CR"):
            return rmi.rmit(32)
        current = [math.degrees(v) for v in self.world.q_cmd_rad]
        if req.name == "FRC_JointRelativeJRep":
            q_deg = [a + b for a, b in zip(current, q_deg, strict=True)]
        dist = max(abs(a - b) for a, b in zip(q_deg, current, strict=True))
        rate = self.options.max_joint_speed_deg_s * speed / 100.0 * self.override / 100.0
        return await self._sweep(seq, q_deg, dist / rate, req.session)

    async def _linear_motion(self, seq: int, req: _Request) -> int | None:
        """FRC_LinearMotion and FRC_LinearRelative: a move of the tool centre to a position of
        the configuration's user frame (or by a displacement in it: translation added,
        rotation applied about the user frame's axes at the tool centre).

        The simulated robot sweeps its joints to the inverse-kinematics solution closest to
        the commanded joints over the time the straight line takes at ``Speed``; the end point
        and the duration are the controller's, the path in between is not a straight line.
        """
        body = req.body
        config = body.get("Configuration")
        if not isinstance(config, Mapping):
            return rmi.rmit(23)
        uf, ut = config.get("UFrameNumber"), config.get("UToolNumber")
        if isinstance(uf, bool) or not isinstance(uf, int) or not 0 <= uf <= self.options.n_uframes:
            return rmi.rmit(3)
        if isinstance(ut, bool) or not isinstance(ut, int) or not 0 <= ut <= self.options.n_utools:
            return rmi.rmit(2)
        try:
            pos = rmi.parse_frame(body, "Position")
        except ProtocolError:
            return rmi.rmit(23)
        factor = rmi.LINEAR_SPEED_TYPES.get(str(body.get("SpeedType", "mmSec")))
        if factor is None:
            return rmi.rmit(30)
        speed = body.get("Speed")
        if isinstance(speed, bool) or not isinstance(speed, int | float) or not speed > 0:
            return rmi.rmit(31)
        speed_mm_s = min(speed * factor, self.options.max_linear_speed_mm_s)
        if body.get("TermType", "FINE") not in ("FINE", "CNT", "CR"):
            return rmi.rmit(32)
        q_now = self.world.q_cmd_rad
        start = _matrix(self.tcp_position(q_now, uf, ut))
        target = dict(zip("XYZWPR", pos, strict=True))
        if req.name == "FRC_LinearRelative":
            T = _matrix(target)
            moved = np.eye(4)
            moved[:3, :3] = T[:3, :3] @ start[:3, :3]
            moved[:3, 3] = start[:3, 3] + T[:3, 3]
            target = _fields(moved)
        q = self.joints_for(target, uf, ut, q_now)
        if q is None:
            self._fault(seq, "MOTN-018 Position not reachable", req.session)
            return None
        dist_mm = 1000.0 * float(np.linalg.norm(_matrix(target)[:3, 3] - start[:3, 3]))
        rate = speed_mm_s * self.override / 100.0
        return await self._sweep(seq, [math.degrees(v) for v in q], dist_mm / rate, req.session)

    async def _sweep(self, seq: int, q_deg: list[float], duration_s: float,
                     session: _Session) -> int | None:
        """Move to ``q_deg`` over ``duration_s`` (scaled by ``time_scale``): a system fault
        outside the joint limits or on an injected alarm, ``_ABORTED`` when FRC_Abort cut
        it short, else 0."""
        for i, (v, (lo, hi)) in enumerate(zip(q_deg, self.joint_limits_deg, strict=True)):
            if not lo <= v <= hi:
                self._fault(seq, f"MOTN-017 Limit error (G:1^J{i + 1})", session)
                return None
        if self.faults.fire("alarm"):
            self._fault(seq, "SRVO-050 Collision Detect alarm (injected)", session)
            return None
        duration = max(duration_s, self.options.min_motion_s) * self.options.time_scale
        if duration <= 0:
            self.world.move([math.radians(v) for v in q_deg])
            return 0
        motion = self.world.start_motion([math.radians(v) for v in q_deg], duration)
        if not await session.run_for(duration) or not self.world.finish_motion(motion):
            return _ABORTED
        return 0

    async def _wait_time(self, seq: int, req: _Request) -> int | None:
        """FRC_WaitTime: dwell ``Time`` seconds (scaled)."""
        t = req.body.get("Time", 0)
        if isinstance(t, bool) or not isinstance(t, int | float) or t < 0:
            return rmi.rmit(21)
        wait = t * self.options.time_scale
        if wait > 0 and not await req.session.run_for(wait):
            return _ABORTED
        return 0

    async def _set_uframe(self, seq: int, req: _Request) -> int | None:
        """FRC_SetUFrame instruction."""
        n = req.body.get("FrameNumber")
        if not isinstance(n, int):
            return rmi.rmit(3)
        self.active_uframe = n
        return 0

    async def _set_utool(self, seq: int, req: _Request) -> int | None:
        """FRC_SetUTool instruction."""
        n = req.body.get("ToolNumber")
        if not isinstance(n, int):
            return rmi.rmit(2)
        self.active_utool = n
        return 0

    _INSTRUCTIONS: ClassVar[dict[str, _InstructionHandler]] = {
        "FRC_JointMotionJRep": _joint_motion_jrep,
        "FRC_JointRelativeJRep": _joint_motion_jrep,
        "FRC_LinearMotion": _linear_motion,
        "FRC_LinearRelative": _linear_motion,
        "FRC_WaitTime": _wait_time,
        "FRC_SetUFrame": _set_uframe,
        "FRC_SetUTool": _set_utool,
    }


def _matrix(frame: Mapping[str, float]) -> NDArray[np.float64]:
    """An RMI frame (X..R, mm and degrees) as a (4, 4) transform, metres."""
    T = np.eye(4)
    T[:3, :3] = wpr_to_matrix(*(math.radians(float(frame[k])) for k in "WPR"))
    T[:3, 3] = [float(frame[k]) / 1000.0 for k in "XYZ"]
    return T


def _fields(T: NDArray[np.float64]) -> dict[str, float]:
    """A (4, 4) transform (metres) as an RMI frame (X..R, mm and degrees)."""
    w, p, r = (math.degrees(a) for a in matrix_to_wpr(T[:3, :3]))
    x, y, z = (1000.0 * float(v) for v in T[:3, 3])
    return rmi.frame_fields(x, y, z, w, p, r)
