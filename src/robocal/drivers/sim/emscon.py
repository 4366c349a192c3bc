"""A wire-faithful Leica emScon TPI tracker simulator (binary packets over TCP).

It measures the reflector of the shared :class:`SimWorld` robot, like the LTP/1 simulator,
but speaks the emScon C-API byte for byte (:mod:`robocal.protocols.emscon`): one command
pending at a time (a second one gets ``ServerBusy``), replies echo the command ID,
``StartMeasurement`` answers with a reply and a separate result packet, events are type-8
packets.

Where public sources leave the behaviour open (the note's section 10), :class:`EmsconSimOptions`
makes it selectable, so the driver can be tested against every plausible server. Faults come
from the shared :class:`FaultConfig` (beam breaks, unstable target, glitches, garbage = packets
of unknown type, slow = late replies, dropped connections) plus the emScon-specific rates of
:class:`EmsconFaults` (busy, split and merged TCP writes, bad size fields, ...).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import struct
from collections.abc import Awaitable, Callable
from typing import Any, ClassVar, Literal

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from robocal.drivers.sim._server import SessionServer, port_of
from robocal.drivers.sim.faults import FaultConfig, RateInjector
from robocal.drivers.sim.world import SimWorld
from robocal.errors import FramingError, UnexpectedReply
from robocal.protocols import emscon
from robocal.protocols.emscon import Cmd, Event

__all__ = ["EmsconFaults", "EmsconSimOptions", "EmsconTrackerSimulator", "SimReflector"]

_log = structlog.get_logger(__name__)

_P = Field(default=0.0, ge=0.0, le=1.0)
# Factors from the base units (m, rad, °C, mbar) to each enum value (note, section 6).
_LENGTH = {0: 1.0, 1: 1000.0, 2: 1e6, 3: 3.280839895, 4: 1.093613298, 5: 39.37007874}
_ANGLE = {0: 1.0, 1: 57.29577951308232, 2: 63.66197723675813}
_PRESSURE = {0: 1.0, 1: 1.0, 2: 0.1, 3: 1 / 1.33322, 4: 1 / 68.94757, 5: 1 / 2.49082,
             6: 1 / 33.86379}
_UNIT_FIELDS = ("length_unit", "angle_unit", "temperature_unit", "pressure_unit",
                "humidity_unit")
_UNIT_RANGE: dict[str, dict[int, float]] = {
    "length_unit": _LENGTH, "angle_unit": _ANGLE, "temperature_unit": {0: 1.0, 1: 1.0},
    "pressure_unit": _PRESSURE, "humidity_unit": {0: 1.0},
}


class EmsconFaults(BaseModel):
    """emScon-specific fault rates (each drawn per opportunity).

    Attributes
    ----------
    busy_rate
        Per command: answered with ``ServerBusy`` (1) instead of being executed.
    split_rate
        Per packet sent: written in several pieces, even inside the 8-byte header.
    merge_rate
        Per packet sent: held back and written together with the next packet.
    bad_size_rate
        Per reply: a packet with an impossible size field is sent first (the stream is then
        lost; the client must reconnect).
    unknown_type_rate
        Per reply: a packet of an unknown data type is sent first (clients skip it).
    error_packet_rate
        Per reply: an unrelated unsolicited type-1 error packet is sent first.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    busy_rate: float = _P
    split_rate: float = _P
    merge_rate: float = _P
    bad_size_rate: float = _P
    unknown_type_rate: float = _P
    error_packet_rate: float = _P


class SimReflector(BaseModel):
    """A reflector the simulated tracker knows (``GetReflectors``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: int
    name: str = Field(max_length=32)
    target_type: int = 5
    surface_offset_mm: float = 19.05


_DEFAULT_REFLECTORS = (
    SimReflector(id=1, name="RRR15", target_type=5, surface_offset_mm=19.05),
    SimReflector(id=2, name="RRR05", target_type=6, surface_offset_mm=6.35),
    SimReflector(id=3, name="BRR15", target_type=7, surface_offset_mm=19.05),
)


class EmsconSimOptions(BaseModel):
    """Behaviour of the simulated emScon server. ``[10.n]``: an open point of the note.

    Attributes
    ----------
    time_scale
        Multiplies every simulated duration (measuring time, Initialize, motions); 0 answers
        at once.
    sample_period_s
        Simulated sampling period: a measurement of ``lMeasTime`` averages
        ``lMeasTime / sample_period_s`` samples of the world's noise (at most 20000); the
        result carries the noise model's full covariance of that mean.
    max_world_samples
        Samples actually drawn from the virtual robot per measurement (see
        :meth:`EmsconTrackerSimulator.measurement`).
    initialize_s, motion_s
        Durations of ``Initialize`` and of ``GoPosition``/``FindReflector``/``GoBirdBath``.
    initialized
        Start initialised (tracker processor status 5) instead of 4.
    beam_broken_start_status
        Reply status of ``StartMeasurement`` when nothing is locked. [10.1]
    beam_lost_status
        Status reported when the beam is lost during a measurement. [10.1]
    beam_lost_signal
        How a loss during the measurement is reported: ``error`` (type-1 packet naming
        command 49), ``event`` (event 25 only), ``both``, ``result`` (a result packet with
        a non-zero status) or ``reply`` (a failed reply, in result-first order). [10.1, 10.2]
    beam_break_at
        Where an injected beam break happens: ``start``, ``during`` or ``either``.
    relock_after_s
        A broken beam locks again by itself after this long (None: only FindReflector,
        GoBirdBath re-acquire). [10.1]
    find_fail_status
        Non-zero: ``FindReflector`` fails with this status and event 25. [10.1]
    result_order
        ``reply_first`` or ``result_first`` for ``StartMeasurement``. [10.2]
    failed_reply_size
        ``basic`` (16 bytes) or ``full`` (the command's full reply size, zero-filled). [10.3]
    events
        ``ms``: the MS simulator's pattern (events after Set commands; 151, 27, 24 after
        Initialize); ``none``. [10.4]
    result_type
        ``by_statistic_mode`` (Standard → 2, Extended → 9), ``always_2``, ``always_9``. [10.5]
    stationary_mode
        ``accept`` mode 0 or ``reject`` it with ``stationary_reject_status`` (profile-only
        firmware). [10.6]
    initial_units
        Units before ``SetUnits`` (length, angle, temperature, pressure, humidity). [10.7]
    keep_state_across_connections
        Keep units, settings and initialisation when a client disconnects. [10.7, 10.10]
    temp_range_c, press_range_hpa, hum_range_pct
        Meteo accepted by ``SetEnvironmentParams`` (else status 57). [10.8]
    monitor_overrides_meteo
        With weather monitor status 2 the station's own values replace the ones set. [10.8]
    scc_hz_counterclockwise
        Sense of Hz in SCC (SCW is the opposite). [10.9]
    second_client
        ``refuse`` (close at once) or ``status`` (answer every command with 10011). [10.10]
    announce_on_connect
        Send event 999 (ServerStarted) when a client connects. [10.10]
    initialize_status
        Status of a successful ``Initialize`` (KEK saw 705). [10.11]
    position_stream_period_s
        Period of type-7 packets while locked and enabled (note: up to 10 Hz).
    temp_c, press_hpa, hum_pct
        The station's meteo (used when the monitor calculates).
    serial, version
        Reported by ``GetSystemStatus``.
    reflectors
        The reflectors ``GetReflectors`` lists.
    not_implemented
        Command IDs answered with ``NotImplemented`` (2), as an older or smaller server.
    faults
        emScon-specific fault rates.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    time_scale: float = Field(default=0.001, ge=0.0)
    sample_period_s: float = Field(default=0.001, gt=0.0)
    initialize_s: float = Field(default=30.0, ge=0.0)
    motion_s: float = Field(default=2.0, ge=0.0)
    initialized: bool = False
    beam_broken_start_status: int = 10004
    beam_lost_status: int = 10009
    beam_lost_signal: Literal["error", "event", "both", "result", "reply"] = "both"
    beam_break_at: Literal["start", "during", "either"] = "either"
    relock_after_s: float | None = Field(default=None, ge=0.0)
    find_fail_status: int = 0
    result_order: Literal["reply_first", "result_first"] = "reply_first"
    failed_reply_size: Literal["basic", "full"] = "basic"
    events: Literal["ms", "none"] = "ms"
    result_type: Literal["by_statistic_mode", "always_2", "always_9"] = "by_statistic_mode"
    stationary_mode: Literal["accept", "reject"] = "accept"
    stationary_reject_status: int = 10023
    initial_units: tuple[int, int, int, int, int] = (0, 0, 0, 0, 0)
    keep_state_across_connections: bool = True
    temp_range_c: tuple[float, float] = (-10.0, 50.0)
    press_range_hpa: tuple[float, float] = (500.0, 1200.0)
    hum_range_pct: tuple[float, float] = (0.0, 100.0)
    monitor_overrides_meteo: bool = True
    scc_hz_counterclockwise: bool = True
    second_client: Literal["refuse", "status"] = "status"
    announce_on_connect: bool = False
    initialize_status: int = 0
    position_stream_period_s: float = Field(default=0.1, gt=0.0)
    temp_c: float = 20.4
    press_hpa: float = 1012.6
    hum_pct: float = 41.0
    serial: int = 390123
    version: tuple[int, int, int] = (3, 8, 7)
    reflectors: tuple[SimReflector, ...] = _DEFAULT_REFLECTORS
    max_world_samples: int = Field(default=32, ge=1, le=20_000)
    not_implemented: tuple[int, ...] = ()
    faults: EmsconFaults = EmsconFaults()


_SLOW = {Cmd.INITIALIZE, Cmd.START_MEASUREMENT, Cmd.GO_POSITION, Cmd.GO_POSITION_HVD,
         Cmd.FIND_REFLECTOR, Cmd.GO_BIRD_BATH, Cmd.GO_BIRD_BATH2, Cmd.PARK, Cmd.CHANGE_FACE,
         Cmd.POINT_LASER, Cmd.POINT_LASER_HVD, Cmd.GO_LAST_MEASURED_POINT}


_Handler = Callable[["EmsconTrackerSimulator", emscon.Command, "_Session"], Awaitable[None]]


class _State:
    """Server state that may survive a connection (``keep_state_across_connections``)."""

    def __init__(self, o: EmsconSimOptions) -> None:
        self.units = dict(zip(_UNIT_FIELDS, o.initial_units, strict=True))
        self.initialized = o.initialized
        self.locked = True
        self.meas_mode = 0
        self.statistic_mode = (0, 0)
        self.coord_sys = 0
        self.meas_time_ms = 1000
        self.use_adm = 0
        self.reflector_id = o.reflectors[0].id if o.reflectors else 0
        self.search = (0.2, 10_000)
        self.env = (o.temp_c, o.press_hpa, o.hum_pct)  # base units
        self.settings = {
            "weather_monitor_status": 2, "apply_transformation_params": 1,
            "apply_station_orientation_params": 1, "keep_last_position": 1,
            "send_unsolicited_messages": 0, "send_reflector_position_data": 0,
            "try_measurement_mode": 0, "has_nivel": 1, "has_video_camera": 1,
        }
        self.long_params: dict[int, int] = {}
        self.double_params: dict[int, float] = {}
        # the beam's direction (hz, v) rad where GoPosition left it; while the tracker is
        # locked and has not been sent elsewhere since, it follows the reflector
        self.direction = (0.0, math.pi / 2)
        self.follow = True
        self.face = 1
        self.last_measured: tuple[float, float, float] | None = None   # tracker frame, m
        self.refraction = (1.000272, 1.000272)     # IFM and ADM group refractive indices


class _Session:
    """One client connection: framing, the pending command, and paced writes."""

    def __init__(self, sim: EmsconTrackerSimulator, writer: asyncio.StreamWriter,
                 *, refused: bool = False) -> None:
        self.sim = sim
        self.writer = writer
        self.refused = refused
        self.framer = emscon.PacketFramer()
        self.pending: asyncio.Task[None] | None = None
        self.pending_cmd: int | None = None
        self.closed = False
        self._held = b""
        self._wlock = asyncio.Lock()
        self._stream: asyncio.Task[None] | None = None

    # --- writing -------------------------------------------------------------------------------
    async def send(self, data: bytes) -> None:
        """Write one packet, perhaps split into pieces or merged with the next one."""
        if self.closed:
            return
        f = self.sim.emscon_faults
        async with self._wlock:
            try:
                if f.fire("merge") and not self._held:
                    self._held = data
                    self.sim._track(self._flush_later())
                    return
                data, self._held = self._held + data, b""
                if f.fire("split") and len(data) > 1:
                    cuts = sorted(self.sim.rng.sample(range(1, len(data)), min(3, len(data) - 1)))
                    pieces = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)],
                                                        strict=True)]
                    for piece in pieces:
                        self.writer.write(piece)
                        await self.writer.drain()
                        await asyncio.sleep(0.001)
                else:
                    self.writer.write(data)
                    await self.writer.drain()
            except (OSError, ConnectionError, RuntimeError):
                self.closed = True

    async def _flush_later(self) -> None:
        await asyncio.sleep(0.005)
        async with self._wlock:
            if self._held and not self.closed:
                data, self._held = self._held, b""
                try:
                    self.writer.write(data)
                    await self.writer.drain()
                except (OSError, ConnectionError, RuntimeError):
                    self.closed = True

    async def event(self, code: int) -> None:
        await self.send(emscon.encode(emscon.StatusChange(int(code))))

    async def open(self) -> None:
        """Announce the server (event 999) if so configured, unless this client is refused."""
        if self.sim.options.announce_on_connect and not self.refused:
            await self.event(Event.SERVER_STARTED)

    async def reply(self, cmd: int, status: int = 0, **data: Any) -> None:
        """Send the reply to ``cmd`` (with the injected pre-reply faults and delays)."""
        sim = self.sim
        if sim.faults.fire("slow"):
            await asyncio.sleep(sim.faults.config.slow_s)
        if sim.emscon_faults.fire("bad_size"):
            await self.send(struct.pack("<ii", sim.rng.choice([3, 5, 1 << 20, -12]), 0))
        if sim.faults.fire("garbage") or sim.emscon_faults.fire("unknown_type"):
            kind = sim.rng.choice([3, 4, 5, 10, 11, 12, 57, 1000])
            body = bytes(sim.rng.randrange(256) for _ in range(sim.rng.randrange(4, 41)))
            await self.send(emscon.encode(emscon.UnknownPacket(kind, body)))
        if sim.emscon_faults.fire("error_packet"):
            await self.send(emscon.encode(emscon.ErrorResponse(66, 10015)))
        await self.send(self.sim.reply_bytes(cmd, status, data))

    # --- reading -------------------------------------------------------------------------------
    async def feed(self, data: bytes) -> None:
        self.framer.feed(data)
        try:
            frames = list(self.framer.frames())
        except FramingError as err:
            _log.warning("emscon sim: bad size from the client; closing", error=str(err))
            self.close()
            return
        for frame in frames:
            if self.closed:
                return
            await self.handle(frame)

    async def handle(self, frame: bytes) -> None:
        sim = self.sim
        try:
            packet = emscon.decode(frame, direction="from_client")
        except (UnexpectedReply, FramingError):
            (cmd,) = struct.unpack_from("<i", frame, 8) if len(frame) >= 12 else (-1,)
            await self.reply(cmd, 3)  # WrongParameter: the command has the wrong size
            return
        if not isinstance(packet, emscon.Command):
            await self.send(emscon.encode(emscon.ErrorResponse(-1, 3)))
            return
        sim.commands.append(packet)
        cmd = packet.command
        if cmd == Cmd.EXIT_APPLICATION:
            _log.warning("emscon sim: ExitApplication received; the server stops")
            sim.exit_received = True
            self.close()
            return
        if self.refused:
            await self.reply(cmd, emscon.Status.MULTI_CONNECTIONS_NOT_ALLOWED)
            return
        if sim.faults.fire("drop"):
            _log.info("emscon sim: dropping the connection (injected)")
            self.close()
            return
        if self.pending is not None and not self.pending.done():
            if cmd == Cmd.STOP_MEASUREMENT and self.pending_cmd == Cmd.START_MEASUREMENT:
                self.pending.cancel()
                await self.reply(cmd)
            else:
                await self.reply(cmd, emscon.Status.SERVER_BUSY)
            return
        if cmd in sim.options.not_implemented:
            await self.reply(cmd, emscon.Status.NOT_IMPLEMENTED)
            return
        if sim.emscon_faults.fire("busy"):
            await self.reply(cmd, emscon.Status.SERVER_BUSY)
            return
        if cmd in _SLOW:
            self.pending_cmd = cmd
            self.pending = asyncio.create_task(self._slow(packet), name="emscon-sim-cmd")
            return
        await sim.answer(packet, self)

    async def _slow(self, packet: emscon.Command) -> None:
        try:
            await self.sim.answer(packet, self)
        except asyncio.CancelledError:
            _log.info("emscon sim: command cancelled", command=packet.command)

    def start_stream(self) -> None:
        if self._stream is None or self._stream.done():
            self._stream = asyncio.create_task(self._position_stream())

    async def _position_stream(self) -> None:
        sim = self.sim
        while not self.closed and sim.state.settings["send_reflector_position_data"]:
            await asyncio.sleep(sim.options.position_stream_period_s)
            if sim.state.locked and (self.pending is None or self.pending.done()):
                v = sim.values(*sim.measurement(1))
                await self.send(emscon.encode(emscon.ReflectorPosResult(0, *v[:3])))

    def close(self) -> None:
        self.closed = True
        self.writer.close()

    async def stop(self) -> None:
        self.closed = True
        for task in (self.pending, self._stream):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task


class EmsconTrackerSimulator(SessionServer["_Session"]):
    """Simulated emScon server on TCP.

    Parameters
    ----------
    world, faults
        As for every :class:`WorldSimulator` (the reflector sits on the world's robot).
    options : EmsconSimOptions, optional
        Server behaviour and emScon-specific faults.

    Attributes
    ----------
    commands : list of emscon.Command
        Every command received (tests assert on it).
    exit_received : bool
        True once a client sent ExitApplication (command 0).
    state
        The server state (units, settings, lock, initialisation).
    """

    def __init__(self, world: SimWorld, options: EmsconSimOptions | None = None,
                 faults: FaultConfig | None = None) -> None:
        super().__init__(world, faults)
        self.options = options or EmsconSimOptions()
        seed = self.faults.config.seed
        self.emscon_faults = RateInjector(self.options.faults, seed + 7)
        self.rng = random.Random(seed + 3)
        self.state = _State(self.options)
        self.commands: list[emscon.Command] = []
        self.exit_received = False
        #: Tests: break the beam at the next StartMeasurement ("start" or "during").
        self.next_beam_break: Literal["start", "during"] | None = None
        self.port = 0
        self._session: _Session | None = None
        self._relock: asyncio.TimerHandle | None = None

    # --- units ---------------------------------------------------------------------------------
    def _len(self) -> float:
        return _LENGTH[self.state.units["length_unit"]]

    def _ang(self) -> float:
        return _ANGLE[self.state.units["angle_unit"]]

    def _temp_out(self, c: float) -> float:
        return c * 1.8 + 32.0 if self.state.units["temperature_unit"] == 1 else c

    def _temp_in(self, t: float) -> float:
        return (t - 32.0) / 1.8 if self.state.units["temperature_unit"] == 1 else t

    def _press(self) -> float:
        return _PRESSURE[self.state.units["pressure_unit"]]

    def _env_out(self) -> tuple[float, float, float]:
        t, p, h = self.state.env
        return self._temp_out(t), p * self._press(), h

    # --- measurement values --------------------------------------------------------------------
    def measurement(self, n: int, *, glitch: bool = False) -> tuple[Any, Any]:
        """Mean (3,) and its covariance (3, 3) of ``n`` simulated samples, metres, tracker frame.

        At most ``max_world_samples`` samples go through the virtual robot (each is a forward
        kinematics evaluation); their mean's deviation from the truth is scaled to the
        spread of ``n`` samples, which has the same distribution for zero-mean noise.
        """
        world = self.world
        m_n = min(n, self.options.max_world_samples)
        m = world.measure(m_n)
        truth = world.true_reflector_position()
        mean = truth + (np.asarray(m.mean_m) - truth) * math.sqrt(m_n / n)
        noise = getattr(getattr(world.cell, "noise", None), "covariances", None)
        if noise is not None:
            cov = np.asarray(noise(truth[None, :]), dtype=float)[0] / n
        else:
            cov = np.diag(np.square(m.sigma_m)) / n
        if glitch:
            mean = np.asarray(world.cell.outlier(mean[None, :], world.rng), dtype=float)[0]
        return mean, cov

    def values(self, mean_m: Any, cov_m2: Any) -> tuple[float, ...]:
        """(val1..3, std1..3, covar12, covar13, covar23) in the session's CS type and units."""
        k, a = self._len(), self._ang()
        x, y, z = (float(v) for v in mean_m)
        cov = np.asarray(cov_m2, dtype=float)
        cs = self.state.coord_sys
        if cs in (emscon.CoordSys.SCC, emscon.CoordSys.SCW):
            ccw = self.options.scc_hz_counterclockwise
            sign = 1.0 if (ccw if cs == emscon.CoordSys.SCC else not ccw) else -1.0
            ys = sign * y
            d = math.sqrt(x * x + ys * ys + z * z)
            rho = math.hypot(x, ys)
            hz, v = math.atan2(ys, x), math.atan2(rho, z)
            # d(hz, v, d)/d(x, y, z); y enters with its sign.
            jac = np.array([
                [-ys / rho**2, sign * x / rho**2, 0.0],
                [x * z / (d * d * rho), sign * ys * z / (d * d * rho), -rho / (d * d)],
                [x / d, sign * ys / d, z / d],
            ])
            c = jac @ cov @ jac.T
            scale = np.array([a, a, k])
            c = c * np.outer(scale, scale)
            vals = (hz * a, v * a, d * k)
        else:
            c = cov * k * k
            vals = (x * k, y * k, z * k)
        std = np.sqrt(np.diag(c))
        return (*vals, *map(float, std), float(c[0, 1]), float(c[0, 2]), float(c[1, 2]))

    def result_bytes(self, status: int, m: tuple[Any, Any] | None) -> bytes:
        """A type-2 or type-9 result packet of ``m`` = (mean, cov); zeros when None."""
        st = self.state
        o = self.options
        vals = self.values(*m) if m is not None else (0.0,) * 9
        t, p, h = self._env_out()
        nine = o.result_type == "always_9" or (
            o.result_type == "by_statistic_mode" and st.statistic_mode[0] == 1)
        std_total = math.sqrt(sum(s * s for s in vals[3:6])) if m is not None else 0.0
        if nine:
            return emscon.encode(emscon.SingleMeasResult2(
                status=status, meas_mode=st.meas_mode, val1=vals[0], val2=vals[1], val3=vals[2],
                std1=vals[3], std2=vals[4], std3=vals[5], std_total=std_total,
                covar12=vals[6], covar13=vals[7], covar23=vals[8], apriori_std1=vals[3],
                apriori_std2=vals[4], apriori_std3=vals[5], apriori_std_total=std_total,
                temperature=t, pressure=p, humidity=h))
        return emscon.encode(emscon.SingleMeasResult(
            status=status, meas_mode=st.meas_mode, val1=vals[0], val2=vals[1], val3=vals[2],
            std1=vals[3], std2=vals[4], std3=vals[5], std_total=std_total,
            apriori_std1=vals[3], apriori_std2=vals[4], apriori_std3=vals[5],
            apriori_std_total=std_total, temperature=t, pressure=p, humidity=h))

    def reply_bytes(self, cmd: int, status: int, data: dict[str, Any]) -> bytes:
        """A reply packet; failed replies are 16 bytes or full size (``failed_reply_size``)."""
        if status != 0:
            spec = emscon.SPECS.get(cmd)
            head = emscon.reply(cmd, status)
            if self.options.failed_reply_size == "full" and spec is not None:
                pad = spec.reply_size - 16
                return struct.pack("<ii", spec.reply_size, 0) + head[8:] + b"\x00" * pad
            return head
        return emscon.reply(cmd, 0, **data)

    # --- commands ------------------------------------------------------------------------------
    async def _sleep(self, seconds: float) -> None:
        s = seconds * self.options.time_scale
        if s > 0:
            await asyncio.sleep(s)

    def _ms_event(self, s: _Session, code: int) -> None:
        if self.options.events == "ms":
            self._track(s.event(code))

    def _beam_broken(self, s: _Session, *, announce: bool = True) -> None:
        st = self.state
        st.locked = False
        if announce:
            self._track(s.event(Event.MEAS_STATUS_NOT_READY))
        if self.options.relock_after_s is not None:
            loop = asyncio.get_running_loop()
            if self._relock is not None:
                self._relock.cancel()
            self._relock = loop.call_later(self.options.relock_after_s, self._lock_again, s)

    def _lock_again(self, s: _Session) -> None:
        self.state.follow = True
        if not self.state.locked:
            self.state.locked = True
            self._track(s.event(Event.MEAS_STATUS_READY))

    async def answer(self, c: emscon.Command, s: _Session) -> None:
        """Execute one command and send its reply (and result or events); see ``_COMMANDS``."""
        handler = self._COMMANDS.get(c.command)
        if handler is None:
            await s.reply(c.command, emscon.Status.NOT_IMPLEMENTED)
            return
        await handler(self, c, s)

    async def _ok(self, c: emscon.Command, s: _Session) -> None:
        """A command that only needs a successful reply (StopMeasurement, ...)."""
        await s.reply(c.command)

    async def _get_system_status(self, c: emscon.Command, s: _Session) -> None:
        o, st = self.options, self.state
        await s.reply(c.command, last_result_status=0,
                      tracker_processor_status=5 if st.initialized else 4, laser_status=3,
                      adm_status=2, version_major=o.version[0], version_minor=o.version[1],
                      version_build=o.version[2],
                      weather_monitor_status=st.settings["weather_monitor_status"],
                      flags_value=0, tracker_serial_number=o.serial)

    async def _get_tracker_status(self, c: emscon.Command, s: _Session) -> None:
        st = self.state
        await s.reply(c.command, tracker_status=2 if st.initialized and st.locked else 0)

    async def _set_units(self, c: emscon.Command, s: _Session) -> None:
        for i, name in enumerate(_UNIT_FIELDS):
            if c.params[name] not in _UNIT_RANGE[name]:
                await s.reply(c.command, 4 + i)
                return
        self.state.units = dict(c.params)
        await s.reply(c.command)
        self._ms_event(s, Event.UNITS_CHANGED)

    async def _get_units(self, c: emscon.Command, s: _Session) -> None:
        await s.reply(c.command, **self.state.units)

    async def _initialize(self, c: emscon.Command, s: _Session) -> None:
        o = self.options
        await self._sleep(o.initialize_s)
        self.state.initialized = True
        await s.reply(c.command, o.initialize_status)
        if o.events == "ms":
            for ev in (Event.INITIALIZATION_STATUS_CHANGED, Event.MEAS_STATUS_READY,
                       Event.STATISTIC_MODE_CHANGED):
                await s.event(ev)

    async def _set_environment_params(self, c: emscon.Command, s: _Session) -> None:
        o, st, p = self.options, self.state, c.params
        t = self._temp_in(p["temperature"])
        pr = p["pressure"] / self._press()
        h = p["humidity"]
        for i, (v, (lo, hi)) in enumerate(
                ((t, o.temp_range_c), (pr, o.press_range_hpa), (h, o.hum_range_pct))):
            if not lo <= v <= hi:
                await s.reply(c.command, emscon.Status.METEO_DATA_OUT_OF_RANGE)
                _log.info("emscon sim: meteo out of range", index=i, value=v)
                return
        if not (o.monitor_overrides_meteo and st.settings["weather_monitor_status"] == 2):
            st.env = (t, pr, h)
        await s.reply(c.command)
        self._ms_event(s, Event.ENVIRONMENT_PARAMS_CHANGED)

    async def _get_environment_params(self, c: emscon.Command, s: _Session) -> None:
        t, pr, h = self._env_out()
        await s.reply(c.command, temperature=t, pressure=pr, humidity=h)

    async def _set_measurement_mode(self, c: emscon.Command, s: _Session) -> None:
        o, mode = self.options, c.params["meas_mode"]
        if mode == 0 and o.stationary_mode == "reject":
            await s.reply(c.command, o.stationary_reject_status)
        elif mode not in (0, 20, 21, 22, 23):
            await s.reply(c.command, 4)
        else:
            self.state.meas_mode = mode
            await s.reply(c.command)
            self._ms_event(s, Event.MEASUREMENT_MODE_CHANGED)

    async def _get_measurement_mode(self, c: emscon.Command, s: _Session) -> None:
        await s.reply(c.command, meas_mode=self.state.meas_mode)

    async def _set_coordinate_system_type(self, c: emscon.Command, s: _Session) -> None:
        if c.params["coord_sys_type"] not in (0, 6, 7):
            await s.reply(c.command, emscon.Status.NOT_IMPLEMENTED)
            return
        self.state.coord_sys = c.params["coord_sys_type"]
        await s.reply(c.command)
        self._ms_event(s, Event.COORDINATE_SYSTEM_TYPE_CHANGED)

    async def _get_coordinate_system_type(self, c: emscon.Command, s: _Session) -> None:
        await s.reply(c.command, coord_sys_type=self.state.coord_sys)

    async def _set_stationary_mode_params(self, c: emscon.Command, s: _Session) -> None:
        st, p = self.state, c.params
        if p["meas_time"] <= 0:
            await s.reply(c.command, 4)
            return
        st.meas_time_ms, st.use_adm = p["meas_time"], p["use_adm"]
        await s.reply(c.command)
        self._ms_event(s, Event.STATIONARY_MODE_PARAMS_CHANGED)

    async def _get_stationary_mode_params(self, c: emscon.Command, s: _Session) -> None:
        st = self.state
        await s.reply(c.command, meas_time=st.meas_time_ms, use_adm=st.use_adm)

    async def _set_reflector(self, c: emscon.Command, s: _Session) -> None:
        if c.params["internal_reflector_id"] not in {r.id for r in self.options.reflectors}:
            await s.reply(c.command, 4)
            return
        self.state.reflector_id = c.params["internal_reflector_id"]
        await s.reply(c.command)
        self._ms_event(s, Event.REFLECTOR_CHANGED)

    async def _get_reflector(self, c: emscon.Command, s: _Session) -> None:
        await s.reply(c.command, internal_reflector_id=self.state.reflector_id)

    async def _get_reflectors(self, c: emscon.Command, s: _Session) -> None:
        """One reply per reflector (a failed reply when there are none)."""
        reflectors = self.options.reflectors
        if not reflectors:
            await s.reply(c.command, emscon.Status.WRONG_PARAMETER)
        for r in reflectors:
            await s.reply(c.command, total_reflectors=len(reflectors),
                          internal_reflector_id=r.id, target_type=r.target_type,
                          surface_offset=r.surface_offset_mm / 1000 * self._len(),
                          reflector_name=r.name)

    async def _set_search_params(self, c: emscon.Command, s: _Session) -> None:
        self.state.search = (c.params["search_radius"], c.params["timeout"])
        await s.reply(c.command)

    async def _get_search_params(self, c: emscon.Command, s: _Session) -> None:
        radius, timeout = self.state.search
        await s.reply(c.command, search_radius=radius, timeout=timeout)

    async def _set_system_settings(self, c: emscon.Command, s: _Session) -> None:
        st = self.state
        st.settings = dict(c.params)
        await s.reply(c.command)
        self._ms_event(s, Event.SYSTEM_SETTINGS_CHANGED)
        if st.settings["send_reflector_position_data"]:
            s.start_stream()

    async def _get_system_settings(self, c: emscon.Command, s: _Session) -> None:
        await s.reply(c.command, **self.state.settings)

    async def _set_statistic_mode(self, c: emscon.Command, s: _Session) -> None:
        self.state.statistic_mode = (c.params["stationary_mode"], c.params["continuous_mode"])
        await s.reply(c.command)
        self._ms_event(s, Event.STATISTIC_MODE_CHANGED)

    async def _get_statistic_mode(self, c: emscon.Command, s: _Session) -> None:
        stationary, continuous = self.state.statistic_mode
        await s.reply(c.command, stationary_mode=stationary, continuous_mode=continuous)

    async def _go_bird_bath(self, c: emscon.Command, s: _Session) -> None:
        """GoBirdBath, GoBirdBath2: a motion that locks onto the reflector again."""
        await self._sleep(self.options.motion_s)
        await s.reply(c.command)
        self._lock_again(s)

    async def _go_position(self, c: emscon.Command, s: _Session) -> None:
        """GoPosition, GoPositionHVD: a motion that takes ``motion_s``; the beam then points
        where it was sent (FindReflector or GoBirdBath lock it onto the reflector again)."""
        await self._sleep(self.options.motion_s)
        target = self._target_direction(c)
        if target is not None:
            self.state.direction, self.state.follow = target, False
        await s.reply(c.command)

    def _spherical(self, x: float, y: float, z: float) -> tuple[float, float]:
        """(hz, v) rad of a tracker-frame point, hz counted as the session's SCC counts it."""
        sign = 1.0 if self.options.scc_hz_counterclockwise else -1.0
        return math.atan2(sign * y, x), math.atan2(math.hypot(x, y), z)

    def _target_direction(self, c: emscon.Command) -> tuple[float, float] | None:
        """Direction (hz, v) rad a GoPosition or PointLaser command sends the beam to (None:
        a coordinate system type whose targets the simulator does not convert)."""
        p, k, a = c.params, self._len(), self._ang()
        if c.command in (Cmd.GO_POSITION_HVD, Cmd.POINT_LASER_HVD):
            return float(p["hz_angle"]) / a, float(p["vt_angle"]) / a
        cs = self.state.coord_sys
        if cs == emscon.CoordSys.RHR:
            return self._spherical(*(float(p[f"val{i}"]) / k for i in (1, 2, 3)))
        if cs == emscon.CoordSys.SCC:
            return float(p["val1"]) / a, float(p["val2"]) / a
        return None

    def direction_rad(self) -> tuple[float, float]:
        """The head's angles (hz, v) rad: at the reflector while locked on it; in face 2 the
        same beam has hz + pi and v = 2 pi - v."""
        st = self.state
        if st.locked and st.follow:
            st.direction = self._spherical(*map(float, self.world.true_reflector_position()))
        hz, v = st.direction
        if st.face == 2:
            return math.remainder(hz + math.pi, 2 * math.pi), 2 * math.pi - v
        return hz, v

    def _point(self, s: _Session, target: tuple[float, float] | None) -> None:
        """Send the beam to ``target`` (hz, v) rad: off the reflector unless it is there."""
        st = self.state
        if target is None:
            return
        at = self._spherical(*map(float, self.world.true_reflector_position()))
        st.direction, st.follow = target, False
        if st.locked and max(abs(math.remainder(target[0] - at[0], 2 * math.pi)),
                             abs(target[1] - at[1])) > 1e-3:
            self._beam_broken(s)

    async def _point_laser(self, c: emscon.Command, s: _Session) -> None:
        """PointLaser, PointLaserHVD: the beam points at a location (and leaves a reflector
        that is not there); a zenith angle beyond a turn is a wrong parameter."""
        target = self._target_direction(c)
        if c.command == Cmd.POINT_LASER_HVD and target is not None and not (
                math.isfinite(target[0]) and 0.0 <= target[1] <= 2 * math.pi):
            await s.reply(c.command, emscon.Status.WRONG_PARAMETER)
            return
        await self._sleep(self.options.motion_s)
        await s.reply(c.command)
        self._point(s, target)

    async def _park(self, c: emscon.Command, s: _Session) -> None:
        """Park: the head turns to its rest position, pointing down; the beam is off any
        reflector."""
        await self._sleep(self.options.motion_s)
        await s.reply(c.command)
        self.state.face = 1
        self._point(s, (0.0, math.pi))

    async def _change_face(self, c: emscon.Command, s: _Session) -> None:
        """ChangeFace: the head turns over to the other face and locks on the same beam."""
        await self._sleep(self.options.motion_s)
        self.state.face = 3 - self.state.face
        await s.reply(c.command)

    async def _get_face(self, c: emscon.Command, s: _Session) -> None:
        await s.reply(c.command, tracker_face=self.state.face)

    async def _go_last_measured_point(self, c: emscon.Command, s: _Session) -> None:
        """GoLastMeasuredPoint: the beam goes back to the last measured point and locks when
        the reflector is still there (within 1 mm); status 28 without a measurement."""
        st = self.state
        if st.last_measured is None:
            await s.reply(c.command, 28)   # NoLastMeasuredPoint
            return
        await self._sleep(self.options.motion_s)
        await s.reply(c.command)
        there = np.linalg.norm(self.world.true_reflector_position()
                               - np.asarray(st.last_measured)) <= 1e-3
        if there:
            self._lock_again(s)
        else:
            self._point(s, self._spherical(*st.last_measured))

    async def _set_refraction_params(self, c: emscon.Command, s: _Session) -> None:
        p = c.params
        ifm, adm = float(p["ifm_refraction_index"]), float(p["adm_refraction_index"])
        if not (1.0 <= ifm < 1.01 and 1.0 <= adm < 1.01):
            await s.reply(c.command, emscon.Status.WRONG_PARAMETER)
            return
        self.state.refraction = (ifm, adm)
        await s.reply(c.command)
        self._ms_event(s, 3)   # RefractionParamsChanged

    async def _get_refraction_params(self, c: emscon.Command, s: _Session) -> None:
        ifm, adm = self.state.refraction
        await s.reply(c.command, ifm_refraction_index=ifm, adm_refraction_index=adm)

    async def _find_reflector(self, c: emscon.Command, s: _Session) -> None:
        o = self.options
        await self._sleep(o.motion_s)
        if o.find_fail_status:
            await s.reply(c.command, o.find_fail_status)
            await s.event(Event.MEAS_STATUS_NOT_READY)
            return
        await s.reply(c.command)
        self._lock_again(s)

    async def _get_direction(self, c: emscon.Command, s: _Session) -> None:
        hz, vt = self.direction_rad()
        await s.reply(c.command, hz_angle=hz * self._ang(), vt_angle=vt * self._ang())

    async def _get_measurement_status_info(self, c: emscon.Command, s: _Session) -> None:
        st = self.state
        bits = 1 | 2 | 4 | 8 | 4096
        bits |= emscon.MSI_REFLECTOR_FOUND if st.locked else 0
        bits |= emscon.MSI_INITIALIZED if st.initialized else 0
        await s.reply(c.command, last_result_status=0, measurement_status_info=bits)

    async def _set_long_system_parameter(self, c: emscon.Command, s: _Session) -> None:
        """Stores the value; parameter 10 switches the reflector position stream."""
        st, p = self.state, c.params
        st.long_params[p["system_param"]] = p["parameter"]
        if p["system_param"] == 10:
            st.settings["send_reflector_position_data"] = int(p["parameter"] != 0)
            s.start_stream()
        await s.reply(c.command)

    async def _get_long_system_parameter(self, c: emscon.Command, s: _Session) -> None:
        param = c.params["system_param"]
        await s.reply(c.command, system_param=param,
                      parameter=self.state.long_params.get(param, 0))

    async def _set_double_system_parameter(self, c: emscon.Command, s: _Session) -> None:
        self.state.double_params[c.params["system_param"]] = c.params["parameter"]
        await s.reply(c.command)

    async def _get_double_system_parameter(self, c: emscon.Command, s: _Session) -> None:
        param = c.params["system_param"]
        await s.reply(c.command, system_param=param,
                      parameter=self.state.double_params.get(param, 0.0))

    async def _get_tracker_info(self, c: emscon.Command, s: _Session) -> None:
        o = self.options
        await s.reply(c.command, tracker_type=70, tracker_name="AT401 (robocal sim)",
                      tracker_serial_number=o.serial, compensation_id=1, has_adm=1,
                      has_overview_camera=1, has_nivel=1, nivel_mount_offset=0.0,
                      max_distance=160.0 * self._len(), min_distance=0.8 * self._len(),
                      max_data_rate=1000, number_of_faces=2,
                      hz_angle_range=2 * math.pi * self._ang(),
                      vt_angle_range=(145 / 180 * math.pi) * self._ang(), accuracy_model=0,
                      lcp_firmware_major=2, lcp_firmware_minor=1)

    async def _get_system_software_version(self, c: emscon.Command, s: _Session) -> None:
        v = self.options.version
        await s.reply(c.command, version=f"emScon {v[0]}.{v[1]}.{v[2]} (robocal sim)")

    async def _start_measurement(self, c: emscon.Command, s: _Session) -> None:
        """StartMeasurement: a reply and a result packet, in ``result_order``, or a failure."""
        o, st, cmd = self.options, self.state, Cmd.START_MEASUREMENT
        if not st.initialized:
            await s.reply(cmd, emscon.Status.TRACKER_NOT_INITIALIZED)
            return
        broken_at: str | None = self.next_beam_break
        self.next_beam_break = None
        if broken_at is None and self.faults.fire("beam_break"):
            broken_at = o.beam_break_at
            if broken_at == "either":
                broken_at = self.rng.choice(["start", "during"])
        if broken_at == "start":
            await s.event(Event.MEAS_STATUS_NOT_READY)
            self._beam_broken(s, announce=False)
        if not st.locked:
            await s.reply(cmd, o.beam_broken_start_status)
            return
        if self.faults.fire("unstable"):
            await s.reply(cmd, emscon.Status.SENSOR_NOT_STABLE)
            return
        first = o.result_order == "reply_first"
        if first:
            await s.reply(cmd)
        duration = st.meas_time_ms / 1000.0
        if broken_at == "during":
            await self._sleep(duration / 2)
            await self._lost_during(s, first)
            return
        await self._sleep(duration)
        n = max(1, min(20_000, round(duration / o.sample_period_s)))
        m = self.measurement(n, glitch=self.faults.fire("glitch"))
        st.last_measured = (float(m[0][0]), float(m[0][1]), float(m[0][2]))
        await s.send(self.result_bytes(0, m))
        if not first:
            await s.reply(cmd)

    async def _lost_during(self, s: _Session, replied: bool) -> None:
        o, cmd = self.options, Cmd.START_MEASUREMENT
        self.state.locked = False
        signal = o.beam_lost_signal
        if signal == "reply" and replied:
            signal = "error"  # the reply went out already
        if signal in ("event", "both"):
            await s.event(Event.MEAS_STATUS_NOT_READY)
        if signal in ("error", "both"):
            await s.send(emscon.encode(emscon.ErrorResponse(cmd, o.beam_lost_status)))
        elif signal == "result":
            await s.send(self.result_bytes(o.beam_lost_status, None))
            if not replied:
                await s.reply(cmd)
        elif signal == "reply":
            await s.reply(cmd, o.beam_lost_status)
        if o.relock_after_s is not None:
            self._beam_broken(s, announce=False)

    _COMMANDS: ClassVar[dict[int, _Handler]] = {
        Cmd.GET_SYSTEM_STATUS: _get_system_status,
        Cmd.GET_TRACKER_STATUS: _get_tracker_status,
        Cmd.SET_UNITS: _set_units,
        Cmd.GET_UNITS: _get_units,
        Cmd.INITIALIZE: _initialize,
        Cmd.SET_ENVIRONMENT_PARAMS: _set_environment_params,
        Cmd.GET_ENVIRONMENT_PARAMS: _get_environment_params,
        Cmd.SET_MEASUREMENT_MODE: _set_measurement_mode,
        Cmd.GET_MEASUREMENT_MODE: _get_measurement_mode,
        Cmd.SET_COORDINATE_SYSTEM_TYPE: _set_coordinate_system_type,
        Cmd.GET_COORDINATE_SYSTEM_TYPE: _get_coordinate_system_type,
        Cmd.SET_STATIONARY_MODE_PARAMS: _set_stationary_mode_params,
        Cmd.GET_STATIONARY_MODE_PARAMS: _get_stationary_mode_params,
        Cmd.SET_REFLECTOR: _set_reflector,
        Cmd.GET_REFLECTOR: _get_reflector,
        Cmd.GET_REFLECTORS: _get_reflectors,
        Cmd.SET_SEARCH_PARAMS: _set_search_params,
        Cmd.GET_SEARCH_PARAMS: _get_search_params,
        Cmd.SET_SYSTEM_SETTINGS: _set_system_settings,
        Cmd.GET_SYSTEM_SETTINGS: _get_system_settings,
        Cmd.SET_STATISTIC_MODE: _set_statistic_mode,
        Cmd.GET_STATISTIC_MODE: _get_statistic_mode,
        Cmd.START_MEASUREMENT: _start_measurement,
        Cmd.STOP_MEASUREMENT: _ok,
        Cmd.GO_BIRD_BATH: _go_bird_bath,
        Cmd.GO_BIRD_BATH2: _go_bird_bath,
        Cmd.GO_POSITION: _go_position,
        Cmd.GO_POSITION_HVD: _go_position,
        Cmd.POSITION_RELATIVE_HV: _ok,
        Cmd.FIND_REFLECTOR: _find_reflector,
        Cmd.GET_DIRECTION: _get_direction,
        Cmd.GET_MEASUREMENT_STATUS_INFO: _get_measurement_status_info,
        Cmd.SET_LONG_SYSTEM_PARAMETER: _set_long_system_parameter,
        Cmd.GET_LONG_SYSTEM_PARAMETER: _get_long_system_parameter,
        Cmd.SET_DOUBLE_SYSTEM_PARAMETER: _set_double_system_parameter,
        Cmd.GET_DOUBLE_SYSTEM_PARAMETER: _get_double_system_parameter,
        Cmd.CLEAR_COMMAND_QUEUE: _ok,
        Cmd.GET_TRACKER_INFO: _get_tracker_info,
        Cmd.GET_SYSTEM_SOFTWARE_VERSION: _get_system_software_version,
        Cmd.PARK: _park,
        Cmd.CHANGE_FACE: _change_face,
        Cmd.GET_FACE: _get_face,
        Cmd.POINT_LASER: _point_laser,
        Cmd.POINT_LASER_HVD: _point_laser,
        Cmd.GO_LAST_MEASURED_POINT: _go_last_measured_point,
        Cmd.SET_REFRACTION_PARAMS: _set_refraction_params,
        Cmd.GET_REFRACTION_PARAMS: _get_refraction_params,
    }

    # --- TCP -----------------------------------------------------------------------------------
    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Serve on ``host:port`` (0 picks a free port); return the bound port."""
        self.port = port_of(await self._listen(self._on_client, host, port))
        _log.info("emscon sim listening", port=self.port)
        return self.port

    async def _on_client(self, reader: asyncio.StreamReader,
                         writer: asyncio.StreamWriter) -> None:
        busy = self._session is not None and not self._session.closed
        if busy and self.options.second_client == "refuse":
            return
        session = _Session(self, writer, refused=busy)
        if not busy:
            self._session = session
        try:
            await self._serve_session(reader, session, 65536)
        finally:
            if self._session is session:
                self._session = None
                if not self.options.keep_state_across_connections:
                    self.state = _State(self.options)

    async def stop(self) -> None:
        """Stop serving; idempotent."""
        self._close_listeners()
        if self._relock is not None:
            self._relock.cancel()
        for session in list(self._sessions):
            session.close()
            await session.stop()
        await self._stop_serving()

