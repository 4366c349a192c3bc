"""Leica emScon tracker driver: the binary TPI C-API over TCP (port 700), no vendor SDK.

Covers trackers whose controller runs an emScon server (AT4xx, AT901; AT930/AT960 only
where the unit answers on port 700). See ``docs/protocols/emscon.md`` for the session, the
options that settle the open points of the protocol, and the capture procedure.

Session (:meth:`EmsconTracker.connect`): ``GetSystemStatus`` → ``SetUnits`` (mm, rad, °C,
mbar, %RH) → read-modify-write ``SetSystemSettings`` (unsolicited messages on, frame
transforms off) → ``SetEnvironmentParams`` (optional) → ``Initialize`` (when needed) →
``SetMeasurementMode`` → ``SetStatisticMode`` → ``SetCoordinateSystemType`` → reflector
selection. A measurement is ``SetStationaryModeParams`` (when the time changes) then
``StartMeasurement``, whose reply and result packet (type 2 or 9) may come in either order.

Exactly one command is in flight; replies are matched by the echoed command ID. Events,
live positions, unknown packet types and stale packets are handled between replies. Every
wait is bounded. A bad size field closes the link (emScon has no resynchronisation) and the
driver reconnects once.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Mapping
from typing import Any, ClassVar, Literal, NoReturn

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from robocal.drivers._base import DriverBase, DriverOptions
from robocal.drivers.api import TrackerReading
from robocal.errors import (
    ConfigError,
    ConnectFailed,
    DriverTimeout,
    EmsconBeamLost,
    EmsconBusy,
    EmsconMeasurementError,
    EmsconNotInitialized,
    EmsconStatusError,
    EmsconTimeout,
    EmsconUnstable,
    FramingError,
    TransportError,
    TransportTimeout,
    UnexpectedReply,
)
from robocal.protocols import Transport, emscon, open_transport
from robocal.protocols.emscon import Cmd, CoordSys, Event, Status
from robocal.protocols.session import BadFrame, Disposition, EmsconExchange, EmsconSession

__all__ = [
    "EmsconBeamLost",
    "EmsconBusy",
    "EmsconEnvironment",
    "EmsconMeasurementError",
    "EmsconNotInitialized",
    "EmsconOptions",
    "EmsconStatusError",
    "EmsconTimeout",
    "EmsconTracker",
    "EmsconUnstable",
]

_MM_PER_M = 1000.0
# SetUnits: millimetre, radian, Celsius, mbar, relative humidity (note 7.1).
_UNITS = {
    "length_unit": 1,
    "angle_unit": 0,
    "temperature_unit": 0,
    "pressure_unit": 0,
    "humidity_unit": 0,
}
_WMS = {"off": 0, "read_only": 1, "calculate": 2}
_TPS_INITIALIZED = 5


class _EventBeamLost(EmsconBeamLost):
    """Event 25 ended the wait: the measurement is still pending on the server."""


# --- options -----------------------------------------------------------------------------------
class EmsconEnvironment(BaseModel):
    """Meteo values sent with ``SetEnvironmentParams`` (°C, hPa = mbar, % relative humidity)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    temp_c: float = Field(ge=-40.0, le=60.0)
    press_hpa: float = Field(ge=300.0, le=1200.0)
    hum_pct: float = Field(ge=0.0, le=100.0)


class EmsconOptions(DriverOptions):
    """Options of :class:`EmsconTracker`. ``[10.n]`` marks an open point of the note's section 10.

    Attributes
    ----------
    host, port
        The emScon server (factory address 192.168.0.1, port 700). [10.12]
    request_timeout_s
        Wait for the reply to an ordinary command, seconds (note: 10 s).
    initialize_timeout_s
        Wait for ``Initialize``, seconds (note: 120 s; the duration is unknown). [10.13]
    move_timeout_s
        Wait for ``GoPosition``, ``FindReflector``, ``GoBirdBath``, seconds. [10.13]
    busy_retries, busy_backoff_s
        A ``ServerBusy`` reply is retried this often, this long apart, then raised.
    reconnect
        After a lost link or a bad size field, reconnect once and repeat the command.
    initialize
        ``if_needed``: when ``GetSystemStatus`` reports a tracker processor status other
        than 5 (Initialized); ``always``; ``never``.
    initialize_ok_statuses
        Non-zero ``Initialize`` statuses to accept as success (KEK saw 705). [10.11]
    reinitialize
        Initialize once and repeat a measurement refused with ``TrackerNotInitialized``.
    connect_drain_s
        After connecting, read (and log) unsolicited packets this long before the first
        command (a server may announce itself with event 999). [10.10]
    clear_queue_on_connect
        Send ``ClearCommandQueue(1)`` first (left-overs of an unclean disconnect). [10.10]
    verify_units
        Read the units back with ``GetUnits`` after ``SetUnits`` (defaults and persistence
        of units are unknown, so they are always set). [10.7]
    coordinate_system
        ``RHR`` (x, y, z; default), ``SCC`` or ``SCW`` (Hz, zenith V, distance; converted to
        x, y, z here). Cylindrical and left-handed types are not supported. [10.9]
    scc_hz_counterclockwise
        Sense of Hz in ``SCC`` (SCW is the opposite): x = d sinV cosHz, y = ±d sinV sinHz.
        [10.9]
    raw_tracker_frame
        Turn off ``bApplyTransformationParams`` and ``bApplyStationOrientationParams``.
    weather_monitor
        ``keep`` the setting, or set it (``off``, ``read_only``, ``calculate``) in
        ``SetSystemSettings``; with ``calculate`` the tracker may override the values of
        ``environment``. [10.8]
    environment
        Meteo values to send after connecting (None: send none). Range checked locally
        with wide bounds; the tracker's own range is unknown (it answers 57). [10.8]
    meas_mode
        ``SetMeasurementMode``: 0 Stationary, or a profile 20-23 (Fast, Standard, Precise,
        Outdoor) on AT4xx firmware >= 2.0. [10.6]
    meas_mode_fallback
        Profile to use when ``meas_mode`` is refused (status 2-10 or 10023); None: fail.
        [10.6]
    stationary_params_with_profile
        Also send ``SetStationaryModeParams`` under a profile (whether ``lMeasTime`` applies
        then is unknown). [10.6]
    samples_mode, sample_time_ms
        ``time``: one ``StartMeasurement`` with ``lMeasTime = samples * sample_time_ms``
        (the tracker averages internally; ``n`` of the reading is ``samples``). ``repeat``:
        ``samples`` measurements of ``sample_time_ms`` each, averaged here.
    min_meas_time_ms, max_meas_time_ms
        Clamp of ``lMeasTime``, milliseconds.
    statistic_mode
        ``SetStatisticMode`` for stationary measurements: ``extended`` (results of type 9
        with covariances, if the tracker follows this setting), ``standard`` (type 2) or
        ``keep`` (send nothing). Both result types are accepted either way. [10.5]
    result_order
        ``any``: accept the ``StartMeasurement`` reply before or after the result packet;
        ``reply_first``/``result_first``: the other order is an UnexpectedReply. [10.2]
    failed_reply_size
        ``any``; ``basic`` (16 bytes) or ``full``: log a warning when the other form is
        seen (failed replies are always framed by size and read to offset 16). [10.3]
    beam_broken_statuses
        Statuses meaning "no lock / beam broken" (no documented code exists). [10.1]
    unstable_statuses
        Statuses meaning "target not stable".
    fail_on_not_ready_event, not_ready_grace_s
        Event 25 (MeasStatus_NotReady) during a measurement fails it as a broken beam when
        the server has not failed the command itself within ``not_ready_grace_s`` seconds
        (some servers may send only the event, some only a type-1 error). [10.1], [10.4]
    wait_event_after_initialize
        Event to wait for after ``Initialize`` succeeded (e.g. 151), up to
        ``request_timeout_s``; None: wait for none. [10.4]
    reacquire
        After a broken beam: ``wait`` (poll ``GetMeasurementStatusInfo`` for the lock bit),
        ``find`` (``FindReflector``), ``go_find`` (``GoPosition`` to the last measured point,
        then ``FindReflector``), ``birdbath`` (``GoBirdBath``) or ``none``. A lock reported
        by ``GetMeasurementStatusInfo`` skips the motion.
    reacquire_attempts
        Measurements repeated after re-acquisition before BeamLost is raised.
    find_distance_mm
        Approximate distance for ``FindReflector`` before any point was measured.
    find_distance_units
        Unit of ``FindReflector``'s distance: ``length_unit`` (mm here, the assumption of
        the note) or ``m`` (as the Leica sample passes it). [10.14]
    search_radius_mm, search_timeout_ms
        ``SetSearchParams`` (None: leave the tracker's).
    reflector
        Reflector to select by name (``RRR15``) or internal ID; None: keep the current one.
    reflector_position_stream
        Ask for type-7 live positions (kept in :attr:`EmsconTracker.live_position_m`).
    abort_drain_s
        After an abandoned measurement (timeout, event 25), ``StopMeasurement`` is sent and
        stale packets of the old measurement are read and dropped for this long.
    """

    host: str = Field(default="192.168.0.1", min_length=1)
    port: int = Field(default=emscon.DEFAULT_PORT, ge=1, le=65535)
    request_timeout_s: float = Field(default=10.0, gt=0.0)
    initialize_timeout_s: float = Field(default=120.0, gt=0.0)
    move_timeout_s: float = Field(default=60.0, gt=0.0)
    busy_retries: int = Field(default=5, ge=0, le=100)
    busy_backoff_s: float = Field(default=0.05, ge=0.0, le=10.0)
    reconnect: bool = True
    initialize: Literal["if_needed", "always", "never"] = "if_needed"
    initialize_ok_statuses: tuple[int, ...] = ()
    reinitialize: bool = True
    connect_drain_s: float = Field(default=0.0, ge=0.0, le=10.0)
    clear_queue_on_connect: bool = False
    verify_units: bool = True
    coordinate_system: Literal["RHR", "SCC", "SCW"] = "RHR"
    scc_hz_counterclockwise: bool = True
    raw_tracker_frame: bool = True
    weather_monitor: Literal["keep", "off", "read_only", "calculate"] = "keep"
    environment: EmsconEnvironment | None = None
    meas_mode: Literal[0, 20, 21, 22, 23] = 0
    meas_mode_fallback: Literal[20, 21, 22, 23] | None = 22
    stationary_params_with_profile: bool = True
    samples_mode: Literal["time", "repeat"] = "time"
    sample_time_ms: int = Field(default=100, ge=1, le=60_000)
    min_meas_time_ms: int = Field(default=1, ge=1)
    max_meas_time_ms: int = Field(default=60_000, ge=1)
    statistic_mode: Literal["extended", "standard", "keep"] = "extended"
    result_order: Literal["any", "reply_first", "result_first"] = "any"
    failed_reply_size: Literal["any", "basic", "full"] = "any"
    beam_broken_statuses: tuple[int, ...] = (10004, 10009, 10014, 37)
    unstable_statuses: tuple[int, ...] = (10013,)
    fail_on_not_ready_event: bool = True
    not_ready_grace_s: float = Field(default=0.2, ge=0.0, le=10.0)
    wait_event_after_initialize: int | None = None
    reacquire: Literal["wait", "find", "go_find", "birdbath", "none"] = "go_find"
    reacquire_attempts: int = Field(default=2, ge=0, le=20)
    find_distance_mm: float = Field(default=3000.0, gt=0.0)
    find_distance_units: Literal["length_unit", "m"] = "length_unit"
    search_radius_mm: float | None = Field(default=None, gt=0.0)
    search_timeout_ms: int = Field(default=10_000, ge=1)
    reflector: str | int | None = None
    reflector_position_stream: bool = False
    abort_drain_s: float = Field(default=0.2, ge=0.0, le=10.0)

    @field_validator("max_meas_time_ms")
    @classmethod
    def _max_ge_min(cls, v: int, info: Any) -> int:
        lo = info.data.get("min_meas_time_ms", 1)
        if v < lo:
            raise ValueError(f"max_meas_time_ms {v} below min_meas_time_ms {lo}")
        return v


class EmsconTracker(DriverBase):
    """A Leica laser tracker through the emScon TPI binary protocol.

    Parameters
    ----------
    options : EmsconOptions or mapping
        Validated options.

    Attributes
    ----------
    system_status : dict
        The ``GetSystemStatus`` reply of the last connect.
    reflectors : list of dict
        ``GetReflectors`` replies (when a reflector was selected).
    events : list of int
        Event codes received, most recent last (bounded to 200).
    async_errors : list of (command, status)
        Unsolicited type-1 packets received (bounded to 200).
    live_position_m : tuple or None
        Last type-7 position, metres, tracker frame (with ``reflector_position_stream``).
    bad_packets : int
        Packets that could not be decoded and were skipped.
    """

    kind: ClassVar[str] = "emscon"
    Options: ClassVar[type[DriverOptions]] = EmsconOptions
    options: EmsconOptions

    def __init__(self, options: EmsconOptions | Mapping[str, Any] | None = None) -> None:
        super().__init__(options)
        self.system_status: dict[str, Any] = {}
        self.reflectors: list[dict[str, Any]] = []
        self.events: list[int] = []
        self._events_total = 0
        self.async_errors: list[tuple[int, int]] = []
        self.live_position_m: tuple[float, float, float] | None = None
        self.bad_packets = 0
        self.meas_mode = self.options.meas_mode
        self._transport: Transport | None = None
        self._framer = emscon.PacketFramer()
        # Packets read but not yet handled when an exchange ended early (same batch).
        self._backlog: deque[emscon.Packet | BadFrame] = deque()
        #: Request matching (sans-I/O): the command in flight and what has arrived for it.
        self._session = EmsconSession(
            result_order=self.options.result_order,
            fail_on_not_ready_event=self.options.fail_on_not_ready_event,
            not_ready_grace_s=self.options.not_ready_grace_s,
        )
        self._lock = asyncio.Lock()
        self._meas_time_sent: int | None = None
        self._last_vals: tuple[float, float, float] | None = None
        self._reconnecting = False

    # --- connection ----------------------------------------------------------------------------
    async def _connect_impl(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        delay = 0.02
        while True:
            await self._open(deadline)
            try:
                await self._setup(deadline, initialise=True)
                return
            except EmsconStatusError as err:
                # The server still holds a session that was just closed (ours, a moment ago,
                # or a client that went away): it refuses a second one until it notices.
                # Wait for it within the connect timeout instead of failing at once.
                if err.status != int(Status.MULTI_CONNECTIONS_NOT_ALLOWED) \
                        or time.monotonic() + delay >= deadline:
                    raise
            transport, self._transport = self._transport, None
            if transport is not None:
                await transport.close()
            await asyncio.sleep(delay)
            delay = min(2 * delay, 0.5)

    async def _open(self, deadline: float) -> None:
        o = self.options
        transport = open_transport(f"tcp://{o.host}:{o.port}")
        self._framer.reset()
        self._backlog.clear()
        self._session.abandon()
        await transport.open(timeout=max(0.05, deadline - time.monotonic()))
        self._transport = transport
        self._meas_time_sent = None
        if o.connect_drain_s > 0:
            await self._drain(o.connect_drain_s)

    async def _setup(self, deadline: float, *, initialise: bool) -> None:
        """Bring the server into robocal's state (units, settings, modes, reflector)."""
        o = self.options

        def left() -> float:
            return max(0.05, min(o.request_timeout_s, deadline - time.monotonic()))

        if o.clear_queue_on_connect:
            await self._call(Cmd.CLEAR_COMMAND_QUEUE, {"queue_type": 1}, timeout=left())
        status = await self._call(Cmd.GET_SYSTEM_STATUS, timeout=left())
        self.system_status = dict(status.data)
        await self._call(Cmd.SET_UNITS, _UNITS, timeout=left())
        if o.verify_units:
            units = await self._call(Cmd.GET_UNITS, timeout=left(), ok_statuses=(2,))
            if units.ok and dict(units.data) != _UNITS:
                raise UnexpectedReply(f"units read back {dict(units.data)}, set {_UNITS}")
        settings = dict((await self._call(Cmd.GET_SYSTEM_SETTINGS, timeout=left())).data)
        settings["send_unsolicited_messages"] = 1
        settings["keep_last_position"] = 1
        settings["send_reflector_position_data"] = int(o.reflector_position_stream)
        if o.raw_tracker_frame:
            settings["apply_transformation_params"] = 0
            settings["apply_station_orientation_params"] = 0
        if o.weather_monitor != "keep":
            settings["weather_monitor_status"] = _WMS[o.weather_monitor]
        await self._call(Cmd.SET_SYSTEM_SETTINGS, settings, timeout=left())
        if o.environment is not None:
            await self.set_environment(
                o.environment.temp_c, o.environment.press_hpa, o.environment.hum_pct
            )
        tps = self.system_status.get("tracker_processor_status")
        if initialise and (
            o.initialize == "always" or (o.initialize == "if_needed" and tps != _TPS_INITIALIZED)
        ):
            await self.initialize()
        await self._set_meas_mode(left())
        if o.statistic_mode != "keep":
            mode = 1 if o.statistic_mode == "extended" else 0
            # Optional: a server without it (NotImplemented) sends type-2 results.
            await self._call(
                Cmd.SET_STATISTIC_MODE,
                {"stationary_mode": mode, "continuous_mode": 0},
                timeout=left(),
                ok_statuses=(2,),
            )
        await self._call(
            Cmd.SET_COORDINATE_SYSTEM_TYPE,
            {"coord_sys_type": int(CoordSys[o.coordinate_system])},
            timeout=left(),
        )
        if o.reflector is not None:
            await self.select_reflector(o.reflector)
        if o.search_radius_mm is not None:
            await self._call(
                Cmd.SET_SEARCH_PARAMS,
                {"search_radius": o.search_radius_mm, "timeout": o.search_timeout_ms},
                timeout=left(),
            )
        self.log.info(
            "tracker ready",
            serial=self.system_status.get("tracker_serial_number"),
            version=(
                f"{self.system_status.get('version_major')}."
                f"{self.system_status.get('version_minor')}."
                f"{self.system_status.get('version_build')}"
            ),
            meas_mode=self.meas_mode,
        )

    async def _set_meas_mode(self, timeout: float) -> None:
        o = self.options
        try:
            await self._call(Cmd.SET_MEASUREMENT_MODE, {"meas_mode": o.meas_mode}, timeout=timeout)
            self.meas_mode = o.meas_mode
        except EmsconStatusError as err:
            refused = 2 <= err.status <= 10 or err.status == 10023
            if o.meas_mode_fallback is None or not refused:
                raise
            self.log.warning(
                "measurement mode refused; using the fallback profile",
                mode=o.meas_mode,
                status=err.status,
                fallback=o.meas_mode_fallback,
            )
            await self._call(
                Cmd.SET_MEASUREMENT_MODE, {"meas_mode": o.meas_mode_fallback}, timeout=timeout
            )
            self.meas_mode = o.meas_mode_fallback

    async def _close_impl(self) -> None:
        # Just close the socket: never send ExitApplication (it stops the server).
        transport, self._transport = self._transport, None
        if transport is not None:
            await transport.close()

    async def _reconnect(self) -> None:
        transport, self._transport = self._transport, None
        if transport is not None:
            await transport.close()
        self.log.warning("link lost; reconnecting")
        deadline = time.monotonic() + self.options.request_timeout_s
        self._reconnecting = True  # no nested reconnects from the set-up's own commands
        try:
            with self.translate_errors(connecting=True):
                await self._open(deadline)
                await self._setup(deadline, initialise=False)
        finally:
            self._reconnecting = False

    # --- packet exchange -----------------------------------------------------------------------
    async def _read_packets(self, deadline: float) -> list[emscon.Packet | BadFrame]:
        """Read until at least one frame is complete; return the decoded packets."""
        transport = self._transport
        if transport is None:
            raise TransportError("not connected")
        if self._backlog:
            backlog = list(self._backlog)
            self._backlog.clear()
            return backlog
        while True:
            try:
                frames = list(self._framer.frames())
            except FramingError as err:
                # No resynchronisation marker: the link is unusable.
                await transport.close()
                raise TransportError(f"emScon framing lost: {err}") from err
            if frames:
                break
            # At or past the deadline this still takes bytes already received.
            remaining = max(0.0, deadline - time.monotonic())
            self._framer.feed(await transport.read(65536, timeout=remaining))
        packets: list[emscon.Packet | BadFrame] = []
        for frame in frames:
            try:
                packets.append(emscon.decode(frame, direction="from_server"))
            except (UnexpectedReply, FramingError) as err:
                self.bad_packets += 1
                self.log.warning("undecodable packet", error=str(err)[:120])
                packets.append(BadFrame.of(frame, err))
        return packets

    async def _drain(self, seconds: float) -> None:
        """Read and handle unsolicited packets for ``seconds``; drop stale replies."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                packets = await self._read_packets(deadline)
            except TransportTimeout:
                return
            for p in packets:
                if not self._on_async(p):
                    self.log.debug("stale packet dropped", packet=type(p).__name__)

    def _on_async(self, p: emscon.Packet | BadFrame) -> bool:
        """Handle a packet that is not an answer to the pending command; True if consumed."""
        if isinstance(p, BadFrame):
            return True
        if isinstance(p, emscon.StatusChange):
            self.events.append(p.event)
            self._events_total += 1
            del self.events[:-200]
            self.log.debug("tracker event", code=p.event, name=emscon.event_name(p.event))
            return True
        if isinstance(p, emscon.ErrorResponse):
            self.async_errors.append((p.command, p.status))
            del self.async_errors[:-200]
            self.log.warning(
                "unsolicited error",
                command=p.command,
                status=p.status,
                name=emscon.status_name(p.status),
            )
            return True
        if isinstance(p, emscon.ReflectorPosResult):
            if p.status == 0:
                self.live_position_m = self._to_xyz_m((p.val1, p.val2, p.val3))
            return True
        if isinstance(p, emscon.NivelResult | emscon.UnknownPacket):
            self.log.debug("packet ignored", packet=type(p).__name__)
            return True
        return False

    async def _exchange(
        self, cmd: int, params: Mapping[str, Any], timeout: float, *, measurement: bool
    ) -> EmsconExchange:
        """Send one command; wait for its reply (and result packet) or a type-1 error."""
        transport = self._transport
        if transport is None:
            raise TransportError("not connected")
        await self._flush_received()
        out = self._session.send(cmd, time.monotonic() + timeout, measurement=measurement)
        try:
            await transport.write(emscon.command(cmd, **params))
            while not out.done:
                await self._next_batch(out)
        finally:
            if not out.done:
                self._session.abandon()
        return out

    async def _next_batch(self, out: EmsconExchange) -> None:
        """Read one batch of packets and feed it to the session until ``out`` is done."""
        try:
            batch = deque(await self._read_packets(self._session.wait_until()))
        except TransportTimeout:
            ended = self._session.timeout(max(time.monotonic(), self._session.wait_until()))
            if ended != "not_ready":
                raise
            raise _EventBeamLost(
                "event 25 (MeasStatus_NotReady) during the measurement, no result",
                status=int(Event.MEAS_STATUS_NOT_READY),
                command=out.command,
            ) from None
        try:
            while batch and not out.done:
                self._feed(batch.popleft(), out)
        finally:
            self._backlog.extendleft(reversed(batch))

    def _feed(self, p: emscon.Packet | BadFrame, out: EmsconExchange) -> None:
        """Hand one packet to the session; log what it drops, handle what is unsolicited."""
        disposition = self._session.receive(p, time.monotonic())
        if disposition is Disposition.UNSOLICITED:
            self._on_async(p)
        elif disposition is Disposition.ANSWER and isinstance(p, emscon.Reply):
            self._check_failed_size(p)
        elif disposition is Disposition.STALE and isinstance(p, emscon.Reply):
            self.log.warning("stale reply dropped", command=p.command, expected=out.command)
        elif disposition is Disposition.STALE:
            self.log.warning("stale measurement result dropped")

    async def _flush_received(self) -> None:
        """Handle everything received so far: none of it can answer a command not yet sent."""
        while True:
            try:
                packets = await self._read_packets(time.monotonic())
            except TransportTimeout:
                return
            for p in packets:
                if not self._on_async(p):
                    self.log.warning("stale packet dropped", packet=type(p).__name__)

    def _check_failed_size(self, p: emscon.Reply) -> None:
        if p.status == 0 or self.options.failed_reply_size == "any":
            return
        size = 16 + len(p.raw)
        basic = size == 16
        if basic != (self.options.failed_reply_size == "basic"):
            self.log.warning("failed reply of unexpected size", command=p.command, size=size)

    async def _call(
        self, cmd: int, params: Mapping[str, Any] | None = None, **how: Any
    ) -> emscon.Reply:
        """:meth:`_call_full` (same arguments), returning only the reply."""
        result = await self._call_full(cmd, params, **how)
        assert result.reply is not None
        return result.reply

    async def _call_full(
        self,
        cmd: int,
        params: Mapping[str, Any] | None = None,
        *,
        timeout: float | None = None,
        measurement: bool = False,
        ok_statuses: tuple[int, ...] = (),
    ) -> EmsconExchange:
        """Run one command with busy retries and one reconnect; raise on a failed status.

        ``timeout`` (seconds; default ``request_timeout_s``); ``measurement``: also await the
        result packet; ``ok_statuses``: non-zero statuses that count as success.
        """
        o = self.options
        wait = o.request_timeout_s if timeout is None else timeout
        busy = 0
        reconnected = False
        while True:
            try:
                async with self._lock:
                    with self.translate_errors():
                        try:
                            out = await self._exchange(
                                cmd, params or {}, wait, measurement=measurement
                            )
                            if out.reply_owed and o.abort_drain_s > 0:
                                await self._drain(o.abort_drain_s)
                        except TransportTimeout:
                            if not measurement and o.abort_drain_s > 0:
                                # Its late reply would answer the next command of this ID.
                                await self._drain(o.abort_drain_s)
                            raise
            except ConnectFailed:
                if (
                    reconnected
                    or self._reconnecting
                    or not o.reconnect
                    or self.state != "connected"
                ):
                    raise
                reconnected = True
                await self._reconnect()
                continue
            reply = out.reply
            assert reply is not None
            if reply.status == emscon.Status.SERVER_BUSY and busy < o.busy_retries:
                busy += 1
                self.log.info("server busy; retrying", command=reply.name, attempt=busy)
                await asyncio.sleep(o.busy_backoff_s * busy)
                continue
            if reply.status != 0 and reply.status not in ok_statuses:
                self._raise(cmd, reply.status)
            if out.result is not None and out.result.status != 0:
                self._raise(cmd, out.result.status, where="result")
            return out

    def _raise(self, cmd: int, status: int, *, where: str = "reply") -> NoReturn:
        o = self.options
        name = emscon.SPECS[cmd].name if cmd in emscon.SPECS else f"command {cmd}"
        text = f"{name}: {where} status {status} ({emscon.status_name(status)})"
        args: dict[str, Any] = {"kind": self.kind, "status": status, "command": cmd}
        if status == emscon.Status.SERVER_BUSY:
            raise EmsconBusy(text, **args)
        if status == emscon.Status.TRACKER_NOT_INITIALIZED:
            raise EmsconNotInitialized(text, **args)
        if status == emscon.Status.MODULE_TIMED_OUT:
            raise EmsconTimeout(text, **args)
        if status in o.beam_broken_statuses:
            raise EmsconBeamLost(text, **args)
        if status in o.unstable_statuses:
            raise EmsconUnstable(text, **args)
        if cmd == Cmd.START_MEASUREMENT:
            raise EmsconMeasurementError(text, **args)
        raise EmsconStatusError(text, **args)

    # --- tracker API ---------------------------------------------------------------------------
    async def initialize(self) -> None:
        """Send ``Initialize`` (slow: up to ``initialize_timeout_s``)."""
        o = self.options
        mark = self._events_total
        await self._call(
            Cmd.INITIALIZE, timeout=o.initialize_timeout_s, ok_statuses=o.initialize_ok_statuses
        )
        if o.wait_event_after_initialize is not None:
            await self._wait_event(o.wait_event_after_initialize, o.request_timeout_s, mark)

    def _seen_since(self, event: int, mark: int) -> bool:
        new = min(self._events_total - mark, len(self.events))
        return new > 0 and event in self.events[-new:]

    async def _wait_event(self, event: int, seconds: float, mark: int) -> None:
        deadline = time.monotonic() + seconds
        async with self._lock:
            while not self._seen_since(event, mark):
                if time.monotonic() >= deadline:
                    raise DriverTimeout(f"event {event} not received", kind=self.kind)
                try:
                    for p in await self._read_packets(deadline):
                        self._on_async(p)
                except TransportTimeout:
                    continue

    async def set_environment(self, temp_c: float, press_hpa: float, hum_pct: float) -> None:
        """Send meteo values (°C, hPa = mbar, % RH; the session's units)."""
        try:
            env = EmsconEnvironment(temp_c=temp_c, press_hpa=press_hpa, hum_pct=hum_pct)
        except ValidationError as err:
            raise ConfigError(str(err.errors()[0]["msg"]), source="set_environment") from err
        await self._call(
            Cmd.SET_ENVIRONMENT_PARAMS,
            {"temperature": env.temp_c, "pressure": env.press_hpa, "humidity": env.hum_pct},
        )

    async def select_reflector(self, reflector: str | int) -> dict[str, Any]:
        """Select a reflector by name (case-insensitive) or internal ID; return its entry."""
        self.reflectors = await self.list_reflectors()
        for r in self.reflectors:
            if (isinstance(reflector, int) and r["internal_reflector_id"] == reflector) or (
                isinstance(reflector, str)
                and r["reflector_name"].strip().lower() == reflector.strip().lower()
            ):
                await self._call(
                    Cmd.SET_REFLECTOR, {"internal_reflector_id": r["internal_reflector_id"]}
                )
                return r
        known = ", ".join(
            f"{r['internal_reflector_id']}:{r['reflector_name']}" for r in self.reflectors
        )
        raise ConfigError(f"no reflector {reflector!r} (tracker has {known})", key="reflector")

    async def list_reflectors(self) -> list[dict[str, Any]]:
        """``GetReflectors``: one reply packet per reflector, collected until all arrived."""
        async with self._lock:
            with self.translate_errors():
                return await self._collect_reflectors()

    async def _collect_reflectors(self) -> list[dict[str, Any]]:
        transport = self._transport
        if transport is None:
            raise TransportError("not connected")
        await transport.write(emscon.command(Cmd.GET_REFLECTORS))
        deadline = time.monotonic() + self.options.request_timeout_s
        found: list[dict[str, Any]] = []
        total: int | None = None
        while total is None or len(found) < total:
            for p in await self._read_packets(deadline):
                if isinstance(p, BadFrame) and p.command == Cmd.GET_REFLECTORS:
                    raise UnexpectedReply(str(p.error)) from p.error
                if isinstance(p, emscon.Reply) and p.command == Cmd.GET_REFLECTORS:
                    if p.status != 0:
                        self._raise(Cmd.GET_REFLECTORS, p.status)
                    total = int(p.data["total_reflectors"])
                    found.append(dict(p.data))
                elif not self._on_async(p):
                    self.log.warning("stale packet dropped", packet=type(p).__name__)
            if total is not None and total < 1:
                break
        return found

    async def measurement_status_info(self) -> int:
        """``GetMeasurementStatusInfo`` bitmask (2048: reflector found, 65536: initialised)."""
        reply = await self._call(Cmd.GET_MEASUREMENT_STATUS_INFO)
        return int(reply.data["measurement_status_info"])

    async def find_reflector(self, distance_m: float) -> None:
        """``FindReflector`` around the current direction at about ``distance_m``."""
        o = self.options
        d = distance_m if o.find_distance_units == "m" else distance_m * _MM_PER_M
        await self._call(Cmd.FIND_REFLECTOR, {"approx_distance": d}, timeout=o.move_timeout_s)

    async def go_position(self, vals: tuple[float, float, float]) -> None:
        """``GoPosition`` to ``vals`` in the session's CS type and units (mm / rad)."""
        v1, v2, v3 = vals
        await self._call(
            Cmd.GO_POSITION,
            {"val1": v1, "val2": v2, "val3": v3, "use_adm": 0},
            timeout=self.options.move_timeout_s,
        )

    async def go_birdbath(self) -> None:
        """``GoBirdBath``: point the beam at the home position."""
        await self._call(Cmd.GO_BIRD_BATH, timeout=self.options.move_timeout_s)

    async def reacquire(self) -> None:
        """Re-acquire the reflector after a broken beam (see the ``reacquire`` option)."""
        o = self.options
        if o.reacquire == "none":
            return
        try:
            if await self.measurement_status_info() & emscon.MSI_REFLECTOR_FOUND:
                return
            if o.reacquire == "wait":
                deadline = time.monotonic() + o.move_timeout_s
                while time.monotonic() < deadline:
                    await asyncio.sleep(0.02)
                    if await self.measurement_status_info() & emscon.MSI_REFLECTOR_FOUND:
                        return
                return
            if o.reacquire == "birdbath":
                await self.go_birdbath()
                return
            distance_m = o.find_distance_mm / _MM_PER_M
            if self._last_vals is not None:
                distance_m = math.dist(self._to_xyz_m(self._last_vals), (0.0, 0.0, 0.0))
                if o.reacquire == "go_find":
                    await self.go_position(self._last_vals)
            await self.find_reflector(distance_m)
        except (EmsconStatusError, DriverTimeout) as err:
            # The next measurement attempt reports the beam state; re-acquisition is best effort.
            self.log.warning("re-acquisition failed", error=str(err))

    async def measure(
        self, *, samples: int = 10, timeout: float = 10.0, point_id: str | None = None
    ) -> TrackerReading:
        """Measure the reflector (stationary); position in metres, tracker frame.

        ``samples`` sets the measuring time (``samples_mode``); ``timeout`` (seconds) is the
        allowance beyond the measuring time for the result to arrive.

        Raises
        ------
        BeamLost (EmsconBeamLost)
            No lock, after ``reacquire_attempts`` re-acquisitions.
        Unstable, MeasurementError, EmsconBusy, EmsconNotInitialized
            Other refusals, typed by status code.
        DriverTimeout
            No reply or result in time (the measurement is then stopped).
        """
        self._ensure_connected()
        if samples < 1:
            raise ConfigError("samples must be at least 1", source="measure", key="samples")
        o = self.options
        if o.samples_mode == "time":
            meas_ms, repeats = samples * o.sample_time_ms, 1
        else:
            meas_ms, repeats = o.sample_time_ms, samples
        meas_ms = min(max(meas_ms, o.min_meas_time_ms), o.max_meas_time_ms)
        if meas_ms != self._meas_time_sent and (
            self.meas_mode == 0 or o.stationary_params_with_profile
        ):
            await self._call(Cmd.SET_STATIONARY_MODE_PARAMS, {"meas_time": meas_ms, "use_adm": 0})
            self._meas_time_sent = meas_ms
        results = [await self._measure_point(meas_ms, timeout) for _ in range(repeats)]
        return self._reading(results, samples, point_id)

    async def _measure_point(
        self, meas_ms: int, timeout: float
    ) -> emscon.SingleMeasResult | emscon.SingleMeasResult2:
        o = self.options
        reinitialised = False
        attempt = 0
        while True:
            try:
                return await self._start_measurement(meas_ms / 1000.0 + timeout)
            except EmsconNotInitialized:
                if reinitialised or not o.reinitialize:
                    raise
                reinitialised = True
                await self.initialize()
            except EmsconBeamLost:
                attempt += 1
                if attempt > o.reacquire_attempts or o.reacquire == "none":
                    raise
                await self.reacquire()

    async def _start_measurement(
        self, wait_s: float
    ) -> emscon.SingleMeasResult | emscon.SingleMeasResult2:
        try:
            out = await self._call_full(Cmd.START_MEASUREMENT, timeout=wait_s, measurement=True)
        except (DriverTimeout, EmsconBeamLost) as err:
            if not isinstance(err, EmsconStatusError) or isinstance(err, _EventBeamLost):
                await self._abort()
            raise
        assert out.result is not None
        self._last_vals = (out.result.val1, out.result.val2, out.result.val3)
        return out.result

    async def _abort(self) -> None:
        """Stop an abandoned measurement and drop its late reply and result."""
        o = self.options
        try:
            await self._call(Cmd.STOP_MEASUREMENT, timeout=min(o.request_timeout_s, 2.0))
        except Exception as err:  # best effort: the measurement may have ended already
            self.log.debug("StopMeasurement after an abandoned measurement", error=repr(err))
        if o.abort_drain_s > 0 and self._transport is not None:
            async with self._lock:
                try:
                    with self.translate_errors():
                        await self._drain(o.abort_drain_s)
                except ConnectFailed as err:
                    self.log.debug("link lost while draining", error=repr(err))

    # --- conversion ----------------------------------------------------------------------------
    def _to_xyz_m(self, vals: tuple[float, float, float]) -> tuple[float, float, float]:
        """Session coordinates (mm or rad/mm) to Cartesian metres, tracker frame."""
        if self.options.coordinate_system == "RHR":
            return (vals[0] / _MM_PER_M, vals[1] / _MM_PER_M, vals[2] / _MM_PER_M)
        hz, v, d = vals
        sign = self._hz_sign()
        d_m = d / _MM_PER_M
        return (
            d_m * math.sin(v) * math.cos(hz),
            sign * d_m * math.sin(v) * math.sin(hz),
            d_m * math.cos(v),
        )

    def _hz_sign(self) -> float:
        ccw = self.options.scc_hz_counterclockwise
        if self.options.coordinate_system == "SCW":
            ccw = not ccw
        return 1.0 if ccw else -1.0

    def _cov_m2(self, r: emscon.SingleMeasResult | emscon.SingleMeasResult2) -> list[list[float]]:
        """3x3 covariance of the Cartesian position, m², from the result's stds/covariances."""
        c12 = c13 = c23 = 0.0
        if isinstance(r, emscon.SingleMeasResult2):
            c12, c13, c23 = r.covar12, r.covar13, r.covar23
        c = [
            [r.std1**2, c12, c13],
            [c12, r.std2**2, c23],
            [c13, c23, r.std3**2],
        ]
        if self.options.coordinate_system == "RHR":
            jac = [[1.0 / _MM_PER_M if i == j else 0.0 for j in range(3)] for i in range(3)]
        else:
            hz, v, d = r.val1, r.val2, r.val3 / _MM_PER_M
            s = self._hz_sign()
            sv, cv, sh, ch = math.sin(v), math.cos(v), math.sin(hz), math.cos(hz)
            # d(x, y, z) / d(hz [rad], v [rad], d [mm])
            jac = [
                [-d * sv * sh, d * cv * ch, sv * ch / _MM_PER_M],
                [s * d * sv * ch, s * d * cv * sh, s * sv * sh / _MM_PER_M],
                [0.0, -d * sv, cv / _MM_PER_M],
            ]
        jc = [[sum(jac[i][k] * c[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
        return [[sum(jc[i][k] * jac[j][k] for k in range(3)) for j in range(3)] for i in range(3)]

    def _reading(
        self,
        results: list[emscon.SingleMeasResult | emscon.SingleMeasResult2],
        samples: int,
        point_id: str | None,
    ) -> TrackerReading:
        points = [self._to_xyz_m((r.val1, r.val2, r.val3)) for r in results]
        if not all(math.isfinite(v) for p in points for v in p):
            raise UnexpectedReply("measurement result has non-finite coordinates")
        k = len(points)
        mean = tuple(sum(p[i] for p in points) / k for i in range(3))
        covs = [self._cov_m2(r) for r in results]
        # Independent repeats: the covariance of the mean is the mean covariance / k.
        cov = tuple(
            tuple(sum(c[i][j] for c in covs) / (k * k) for j in range(3)) for i in range(3)
        )
        std = tuple(math.sqrt(max(cov[i][i], 0.0)) for i in range(3))
        rms = None
        if k > 1:
            rms = math.sqrt(sum(math.dist(p, mean) ** 2 for p in points) / k)
        last = results[-1]
        weather = {"temp_c": last.temperature, "press_hpa": last.pressure, "hum_pct": last.humidity}
        return TrackerReading(
            position_m=(mean[0], mean[1], mean[2]),
            std_m=(std[0], std[1], std[2]),
            n=samples,
            rms_m=rms,
            timestamp=time.time(),
            status="ok",
            weather=weather,
            point_id=point_id,
            cov_m2=tuple((row[0], row[1], row[2]) for row in cov),
        )
