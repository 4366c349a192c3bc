"""A PLC simulator behind a real pymodbus ``ModbusTcpServer`` (docs/protocols/modbus-plc.md).

The PLC program is the ``SimDevice`` action hook: a write of ``CMD_SEQ`` + ``CMD`` starts the
command; the PLC sets ``STATUS`` busy, runs it (a motion of the shared :class:`SimWorld`
robot, a table check, ...), then publishes ``ACTUAL``, ``ERROR_CODE``, ``STATUS`` and last
``ACK_SEQ``. Motion takes time (the world robot sweeps to the target). ``ABORT`` (CMD 9) halts
the robot where it is at once, even while a move is running or an error is latched; the
aborted move is never acknowledged, and the ABORT's ``CMD_SEQ`` becomes ``ACK_SEQ`` (so
``ACK_SEQ`` only ever moves forward). Reads of the status area are served from the PLC's
own state. A heartbeat task
increments ``PLC_HEARTBEAT``; if ``client_heartbeat_timeout_s`` is set the PLC latches
``HEARTBEAT_LOST`` when the client's heartbeat stops changing, until ``RESET``. Both
heartbeat times run on the simulator's :class:`~robocal._core.clock.Clock`.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time

import structlog
from pydantic import BaseModel, ConfigDict, Field

from robocal._core.clock import SYSTEM_CLOCK, Clock
from robocal.drivers.sim._modbus_server import HOLDING_FCS, WRITE_FCS, ExcCodes, ModbusSimServer
from robocal.drivers.sim._server import WorldSimulator
from robocal.drivers.sim.faults import FaultConfig
from robocal.drivers.sim.world import SimWorld
from robocal.errors import ProtocolError
from robocal.protocols import modbus as mb

__all__ = ["ModbusPlcSimulator", "ModbusSimOptions"]

_log = structlog.get_logger(__name__)


class ModbusSimOptions(BaseModel):
    """Behaviour of the simulated PLC.

    ``time_scale`` multiplies simulated motion time (0 = instantaneous). ``heartbeat_stalled``
    freezes ``PLC_HEARTBEAT`` (a hung PLC).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    register_map: mb.RegisterMap = Field(default_factory=mb.RegisterMap)
    time_scale: float = Field(default=0.001, ge=0.0)
    max_joint_speed_deg_s: float = Field(default=180.0, gt=0.0)
    min_motion_s: float = Field(default=0.012, ge=0.0)
    plc_heartbeat_hz: float = Field(default=4.0, gt=0.0)
    heartbeat_stalled: bool = False
    client_heartbeat_timeout_s: float | None = Field(default=None, gt=0.0)
    joint_limits_deg: tuple[tuple[float, float], ...] | None = None


class ModbusPlcSimulator(WorldSimulator):
    """Simulated PLC driving the world robot through the default register handshake.

    Parameters
    ----------
    world : SimWorld
        The robot being moved.
    options : ModbusSimOptions, optional
        PLC behaviour and register map.
    faults : FaultConfig, optional
        Injected faults (``alarm_rate`` per motion, ``slow_rate``/``slow_s`` per command).
    clock : Clock, optional
        Time source of the PLC heartbeat and the client heartbeat timeout (default: system).

    Attributes
    ----------
    commands : list of (int, int)
        ``(CMD, CMD_SEQ)`` of every command started.
    writes : list of (int, int, int)
        ``(function code, address, count)`` of every register write received.
    applied_table : list of int or None
        Registers of the last table block that passed the PLC's CRC check.
    acks : list of int
        Every ``ACK_SEQ`` value published, in order.
    """

    def __init__(
        self,
        world: SimWorld,
        options: ModbusSimOptions | None = None,
        faults: FaultConfig | None = None,
        *,
        clock: Clock = SYSTEM_CLOCK,
    ) -> None:
        super().__init__(world, faults)
        self.clock = clock
        self.options = options or ModbusSimOptions()
        self.map = self.options.register_map
        m = self.map
        lim = self.options.joint_limits_deg or world.joint_limits_deg
        self.joint_limits_deg = tuple(lim)
        self.commands: list[tuple[int, int]] = []
        self.writes: list[tuple[int, int, int]] = []
        self.applied_table: list[int] | None = None
        self.acks: list[int] = []
        self.frame: list[float] = [0.0] * 6
        self.joint_offsets: list[float] = [0.0] * m.joints
        s0, s1 = m.status_span()
        self._status_base = s0
        self._status = [0] * (s1 - s0)
        self._set("map_version", [1])
        self._hr: list[int] | None = None
        self._hr_start = 0
        self._last_seq: int | None = None
        self._latched = False
        self._abort_gen = 0
        self._aborted = asyncio.Event()
        self._client_hb: int | None = None
        self._client_hb_time = clock.monotonic()
        self._t0 = time.monotonic()
        self._server = ModbusSimServer(
            holding_size=m.holding_size(),
            input_size=m.input_size(),
            action=self._action,
            device_id=m.device_id,
        )
        self.port = 0
        self._publish_actual()

    @property
    def latched(self) -> bool:
        """True while ``HEARTBEAT_LOST`` is latched (until ``RESET``)."""
        return self._latched

    # --- status area ---------------------------------------------------------------------------
    def _set(self, name: str, words: list[int]) -> None:
        first, _ = self.map.status_fields()[name]
        i = first + self.map.status_offset - self._status_base
        self._status[i : i + len(words)] = words

    def _get(self, name: str) -> list[int]:
        first, end = self.map.status_fields()[name]
        i = first + self.map.status_offset - self._status_base
        return self._status[i : i + end - first]

    def _publish_actual(self) -> None:
        wo = self.map.word_order
        q = [math.degrees(v) for v in self.world.q_actual_rad][: self.map.joints]
        q += [0.0] * (self.map.joints - len(q))
        self._set("actual", mb.encode_f32(q, wo))
        ts = int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF
        self._set("actual_ts", mb.encode_u32(ts, wo))

    def _finish(self, seq: int, status: mb.Status, error: mb.PlcError = mb.PlcError.NONE) -> None:
        self._set("error_code", [int(error)])
        self._set("status", [int(status)])
        # ACK_SEQ last: a client polling it sees status and results already in place.
        self._set("ack_seq", [seq])
        self.acks.append(seq)

    # --- pymodbus action hook ------------------------------------------------------------------
    async def _action(
        self,
        fc: int,
        start: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        m = self.map
        s0, s1 = m.status_span()
        status_fc = 4 if m.status_area == "input" else 3
        if fc in HOLDING_FCS:
            self._hr, self._hr_start = registers, start
        if fc in WRITE_FCS and set_values is not None:
            # (pymodbus also calls back without values when it reads a write back for its echo)
            values = [int(v) for v in set_values]
            self.writes.append((fc, address, len(values)))
            end = address + len(values)
            if m.status_area == "holding" and address < s1 and s0 < end:
                return ExcCodes.ILLEGAL_ADDRESS  # PLC-owned registers
            self._on_write(address, values, registers, start)
            return None
        if fc == status_fc and address < s1 and s0 < address + count:
            if self.world.moving:
                self._publish_actual()  # a PLC shows the joints live while they move
            registers[s0 - start : s1 - start] = self._status
        return None

    def _on_write(self, address: int, values: list[int], regs: list[int], start: int) -> None:
        m = self.map
        end = address + len(values)
        if address <= m.client_heartbeat < end:
            hb = values[m.client_heartbeat - address]
            if hb != self._client_hb:
                self._client_hb = hb
                self._client_hb_time = self.clock.monotonic()
        lo = min(m.cmd, m.cmd_seq)
        if address <= lo and lo + 1 < end:

            def word(a: int) -> int:
                return values[a - address]

            cmd, seq = word(m.cmd), word(m.cmd_seq)
            if seq != self._last_seq and seq != 0:
                self._last_seq = seq
                self.commands.append((cmd, seq))
                if cmd == mb.Cmd.ABORT:
                    self._abort()  # at once, not after whatever is running
                self._set("status", [int(mb.Status.BUSY)])
                # Run after pymodbus has stored this write in the register block.
                self._track(self._run(cmd, seq, self._abort_gen))

    def _hr_words(self, address: int, count: int) -> list[int]:
        if self._hr is None:
            return [0] * count
        i = address - self._hr_start
        return list(self._hr[i : i + count])

    # --- PLC program ---------------------------------------------------------------------------
    def _abort(self) -> None:
        """Halt the robot where it is and cancel every command started before."""
        self.world.halt()
        self._abort_gen += 1
        self._aborted.set()
        self._aborted = asyncio.Event()
        self._publish_actual()
        _log.info("plc sim: abort", q_deg=[round(float(v), 4) for v in self._actual_deg()])

    def _actual_deg(self) -> list[float]:
        return [math.degrees(v) for v in self.world.q_actual_rad]

    async def _run(self, cmd: int, seq: int, gen: int) -> None:
        await asyncio.sleep(0)
        m, wo = self.map, self.map.word_order
        faults = self.faults
        if faults.fire("slow"):
            await asyncio.sleep(faults.config.slow_s)
        if gen != self._abort_gen:
            return  # superseded by a later ABORT: never acknowledged
        if cmd == mb.Cmd.ABORT:
            self._publish_actual()
            self._finish(seq, mb.Status.DONE)
            return
        if self._latched and cmd != mb.Cmd.RESET:
            self._finish(seq, mb.Status.ERROR, mb.PlcError.HEARTBEAT_LOST)
            return
        if cmd == mb.Cmd.MOVE_JOINT:
            await self._move_joint(seq, gen)
        elif cmd == mb.Cmd.READ_ACTUAL:
            self._publish_actual()
            self._finish(seq, mb.Status.DONE)
        elif cmd == mb.Cmd.WRITE_JOINT_OFFSETS:
            self.joint_offsets = mb.decode_f32(self._hr_words(m.offset, 2 * m.joints), wo)
            self._finish(seq, mb.Status.DONE)
        elif cmd == mb.Cmd.WRITE_FRAME:
            self.frame = mb.decode_f32(self._hr_words(m.frame, 12), wo)
            self._finish(seq, mb.Status.DONE)
        elif cmd == mb.Cmd.APPLY_TABLE:
            self._apply_table(seq)
        elif cmd == mb.Cmd.RESET:
            self._latched = False
            self._client_hb_time = self.clock.monotonic()
            self._finish(seq, mb.Status.DONE)
        elif cmd == mb.Cmd.IDLE:
            self._finish(seq, mb.Status.DONE)
        else:
            self._finish(seq, mb.Status.ERROR, mb.PlcError.UNKNOWN_CMD)

    async def _move_joint(self, seq: int, gen: int) -> None:
        """MOVE_JOINT: check the target and speed, move, acknowledge (unless aborted)."""
        m, wo, faults = self.map, self.map.word_order, self.faults
        q_deg = mb.decode_f32(self._hr_words(m.target, 2 * m.joints), wo)[: self.world.dof]
        speed = self._hr_words(m.speed, 1)[0]
        if not 1 <= speed <= 100 or not all(map(math.isfinite, q_deg)):
            self._finish(seq, mb.Status.ERROR, mb.PlcError.BAD_ARGUMENT)
            return
        for v, (lo, hi) in zip(q_deg, self.joint_limits_deg, strict=False):
            if not lo <= v <= hi:
                self._finish(seq, mb.Status.ERROR, mb.PlcError.LIMIT)
                return
        if faults.fire("alarm"):
            self._finish(seq, mb.Status.ERROR, mb.PlcError.MOTION_FAULT)
            return
        current = [math.degrees(v) for v in self.world.q_cmd_rad]
        dist = max(abs(a - b) for a, b in zip(q_deg, current, strict=False))
        rate = self.options.max_joint_speed_deg_s * speed / 100.0
        duration = max(dist / rate, self.options.min_motion_s) * self.options.time_scale
        if duration <= 0:
            self.world.move([math.radians(v) for v in q_deg])
        else:
            aborted = self._aborted
            motion = self.world.start_motion([math.radians(v) for v in q_deg], duration)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(duration):
                    await aborted.wait()
            if not self.world.finish_motion(motion) or gen != self._abort_gen:
                return  # halted by ABORT, which is acknowledged instead
        self._publish_actual()
        self._finish(seq, mb.Status.DONE)

    def _apply_table(self, seq: int) -> None:
        m, wo = self.map, self.map.word_order
        header = self._hr_words(m.table, mb.TABLE_HEADER_WORDS)
        try:
            total = mb.table_block_length(header, wo)
        except ProtocolError:
            self._finish(seq, mb.Status.ERROR, mb.PlcError.TABLE_HEADER)
            return
        if total > m.table_words:
            self._finish(seq, mb.Status.ERROR, mb.PlcError.TABLE_HEADER)
            return
        words = self._hr_words(m.table, total)
        body = words[mb.TABLE_HEADER_WORDS :]
        crc = mb.crc16_modbus(body)
        self._set("table_crc", [crc])
        if crc != words[8]:
            self._finish(seq, mb.Status.ERROR, mb.PlcError.TABLE_CRC)
            return
        self.applied_table = words
        self._finish(seq, mb.Status.DONE)

    async def _heartbeat(self) -> None:
        o = self.options
        period = 1.0 / o.plc_heartbeat_hz
        while True:
            await self.clock.sleep(period)
            if not o.heartbeat_stalled:
                hb = (self._get("plc_heartbeat")[0] + 1) & 0xFFFF
                self._set("plc_heartbeat", [hb])
            limit = o.client_heartbeat_timeout_s
            stale = self.clock.monotonic() - self._client_hb_time
            if limit is not None and self._client_hb is not None and stale > limit:
                if not self._latched:
                    _log.warning("plc sim: client heartbeat lost", stale_s=round(stale, 3))
                self._latched = True
                self._set("status", [int(mb.Status.ERROR)])
                self._set("error_code", [int(mb.PlcError.HEARTBEAT_LOST)])

    # --- lifecycle -----------------------------------------------------------------------------
    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Serve Modbus-TCP on ``host:port`` (0 picks a free port); return the bound port."""
        self.host = host
        self.port = await self._server.start(host, port)
        self._track(self._heartbeat())
        _log.info("modbus plc sim listening", port=self.port)
        return self.port

    async def stop(self) -> None:
        """Stop the server and the PLC tasks; idempotent."""
        await self._server.stop()
        await self._stop_serving()
