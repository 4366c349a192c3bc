"""Universal Robots e-Series / CB3 controller: Dashboard server, RTDE and the primary interface.

Protocol as robocal speaks it: ``docs/protocols/universal-robots.md`` (ADR 0028).

Connect: the Dashboard server (29999) is asked for the PolyScope version, remote control,
safety status and robot mode; a powered-off robot is powered on and its brakes released
(``power_on`` option). RTDE (30004) is negotiated at protocol version 2 with one output
recipe (``actual_q``, modes, runtime state and the handshake registers) and started; a task
keeps the newest data package. The primary interface (30001) carries URScript to the
controller and brings the kinematics info (the controller's calibrated DH table and its
per-joint checksums, :attr:`UniversalRobotsRobot.kinematics`) and runtime exceptions back.

Every program robocal sends starts by writing a fresh token to
``output_int_register_<base + 1>`` and ends by writing it to ``output_int_register_<base>``;
the program is done when an RTDE package shows the end token, and failed when a runtime
exception arrives first, or a package shows the start token with no program running and no
end token (stopped from the pendant or dashboard), or the arm leaves RUNNING/NORMAL.
``move_to`` sends ``movej`` this way; ``stop`` sends ``stopj``,
which replaces the running program (a new program always does on a UR), and fails the
waiting ``move_to`` with MotionStopped.

Compensation: ``targets`` tables become installation variables ``<prefix>wp_<index>`` (the
corrected program waypoints, joint radians, as a program's ``movej`` takes them); ``joint``
tables ``<prefix>jq_<joint>`` and ``<prefix>jdq_<joint>`` (radians). The variables must be
declared in the robot's installation (``deploy/config/ur.toml`` lists them); values are
read back by a program that copies them into ``output_double_register_<base>...<base+23>``.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from pydantic import Field, field_validator

from robocal import errors
from robocal.compensation import CompensationTable, JointCorrection, TargetRow
from robocal.drivers import api
from robocal.drivers._base import CompensatingRobotBase, DriverOptions, RobotOptions
from robocal.drivers._compensation import ControllerSnapshot, snapshot_diff, table_diff
from robocal.protocols import TcpTransport
from robocal.protocols import ur_dashboard as dash
from robocal.protocols import ur_primary as prim
from robocal.protocols import ur_rtde as rtde
from robocal.protocols.framing import LineFramer
from robocal.protocols.session import Window
from robocal.protocols.transport import received
from robocal.protocols.ur_rtde import RobotMode, RuntimeState, SafetyMode

__all__ = ["UniversalRobotsOptions", "UniversalRobotsRobot"]

#: Double registers a read-back program fills at a time.
_READ_CHUNK = 24
#: Assignments per write program (keeps each program short).
_WRITE_CHUNK = 16


class UniversalRobotsOptions(RobotOptions):
    """Options of :class:`UniversalRobotsRobot`.

    Attributes
    ----------
    host, dashboard_port, primary_port, rtde_port
        Controller address and ports (29999, 30001, 30004 on a robot).
    rtde_frequency_hz
        Output recipe frequency (CB3: up to 125 Hz, e-Series: 500 Hz).
    reply_timeout_s
        Timeout for dashboard replies, RTDE set-up and non-motion programs, seconds.
    power_on
        Power the arm on and release the brakes at connect when it is off.
    power_on_timeout_s
        How long power-on and brake release may take, seconds.
    max_joint_speed_rad_s, acceleration_rad_s2
        ``movej`` speed at 100 % and its acceleration.
    stop_deceleration_rad_s2
        ``stopj`` deceleration.
    register_base
        First output int/double register robocal's programs write (24..47 are the ones
        PolyScope leaves to external clients on e-Series).
    variable_prefix
        Prefix of the installation variables that hold compensation.
    verify_tol
        Read-back tolerance, degrees.
    """

    host: str = "127.0.0.1"
    dashboard_port: int = Field(default=dash.DEFAULT_PORT, ge=1, le=65535)
    primary_port: int = Field(default=prim.PRIMARY_PORT, ge=1, le=65535)
    rtde_port: int = Field(default=rtde.DEFAULT_PORT, ge=1, le=65535)
    rtde_frequency_hz: float = Field(default=125.0, gt=0.0, le=500.0)
    reply_timeout_s: float = Field(default=5.0, gt=0.0)
    power_on: bool = True
    power_on_timeout_s: float = Field(default=60.0, gt=0.0)
    max_joint_speed_rad_s: float = Field(default=math.pi, gt=0.0, le=2 * math.pi)
    acceleration_rad_s2: float = Field(default=1.4, gt=0.0)
    stop_deceleration_rad_s2: float = Field(default=4.0, gt=0.0)
    register_base: int = Field(default=24, ge=0, le=24)
    variable_prefix: str = Field(default="rc_", pattern=r"^[A-Za-z_]\w*$")
    verify_tol: float = Field(default=1e-6, ge=0.0)

    @field_validator("joint_limits_deg")
    @classmethod
    def _six_joints(cls, v: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
        if len(v) != 6:
            raise ValueError(f"a UR arm has 6 joints, joint_limits_deg gives {len(v)}")
        return v


class _ProgramFailed(Exception):
    """A robocal program ended in a runtime exception."""


class UniversalRobotsRobot(CompensatingRobotBase, api.ControllerCalibrationReadable):
    """A UR e-Series or CB3 arm (PolyScope 3.x/5.x) through its network interfaces.

    Parameters
    ----------
    options : UniversalRobotsOptions or mapping
        Validated options (``joint_limits_deg`` with six joints is required).

    Attributes
    ----------
    controller_version : tuple of 4 int or None
        ``(major, minor, bugfix, build)`` from RTDE.
    kinematics : KinematicsInfo or None
        The controller's calibrated DH table and checksums (primary interface).
    """

    kind: ClassVar[str] = "universal_robots"
    Options: ClassVar[type[DriverOptions]] = UniversalRobotsOptions
    options: UniversalRobotsOptions
    supported_compensation: ClassVar[frozenset[str]] = frozenset({"targets", "joint"})

    def __init__(self,
                 options: UniversalRobotsOptions | Mapping[str, Any] | None = None) -> None:
        super().__init__(options)
        self.controller_version: tuple[int, int, int, int] | None = None
        self.polyscope_version = ""
        self.kinematics: prim.KinematicsInfo | None = None
        self.runtime_exceptions: list[str] = []
        self._dash: TcpTransport | None = None
        self._dash_framer = LineFramer(max_length=dash.MAX_LINE)
        self._dash_lock = asyncio.Lock()
        #: The Dashboard server answers one command at a time with one line (no ids).
        self._dash_window: Window[str] = Window(1)
        self._rtde: TcpTransport | None = None
        self._primary: TcpTransport | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._reg_int = f"output_int_register_{self.options.register_base}"
        self._reg_start = f"output_int_register_{self.options.register_base + 1}"
        self._names: list[str] = []
        self._types: list[str] = []
        self._state: dict[str, Any] = {}
        self._state_time = 0.0
        self._fresh = asyncio.Event()
        self._kin_event = asyncio.Event()
        self._lost: Exception | None = None
        self._token = 0
        self._waiters: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._motion: set[int] = set()
        self._program_lock = asyncio.Lock()
        self._stop_gen = 0
        self._last_table: CompensationTable | None = None

    # --- connection ----------------------------------------------------------------------------
    async def _connect_impl(self, timeout: float) -> None:
        try:
            await self._connect_steps(timeout)
        except errors.UnexpectedReply as err:
            raise errors.ConnectFailed(
                f"unexpected dashboard reply: {err}", kind=self.kind) from err

    async def _connect_steps(self, timeout: float) -> None:
        o = self.options
        deadline = time.monotonic() + timeout
        self._lost = None
        self._state = {}
        self._kin_event = asyncio.Event()
        self._dash_framer = LineFramer(max_length=dash.MAX_LINE)
        self._dash = TcpTransport(o.host, o.dashboard_port)
        await self._dash.open(timeout=timeout)
        greeting = await self._dash_line(deadline - time.monotonic())
        if not greeting.startswith("Connected: Universal Robots Dashboard Server"):
            raise errors.ConnectFailed(f"not a UR dashboard server: {greeting!r}", kind=self.kind)
        self.polyscope_version = await self.dashboard("PolyscopeVersion")
        if not dash.parse_true(await self.dashboard("is in remote control")):
            raise errors.ConnectFailed(
                "the robot is in local mode: switch PolyScope to remote control and connect "
                "again", kind=self.kind)
        safety = dash.parse_safety(await self.dashboard("safetystatus"))
        if safety != "NORMAL":
            raise errors.ConnectFailed(
                f"safety status is {safety}: inspect the robot, clear it on the teach pendant "
                "(or 'unlock protective stop') and connect again", kind=self.kind)
        await self._ensure_running()
        await self._open_rtde(deadline)
        self._primary = TcpTransport(o.host, o.primary_port)
        await self._primary.open(timeout=max(0.1, deadline - time.monotonic()))
        self._tasks.append(asyncio.create_task(self._primary_loop(self._primary),
                                               name="ur-primary"))
        try:
            async with asyncio.timeout(max(0.1, deadline - time.monotonic())):
                await self._kin_event.wait()
                while "robot_mode" not in self._state:
                    await self._next_state(deadline - time.monotonic())
        except TimeoutError as err:
            raise errors.DriverTimeout("no kinematics info or RTDE data in time",
                                       kind=self.kind) from err
        self._token = int(self._state[self._reg_int])
        self.log.info("ur session", polyscope=self.polyscope_version,
                      controller=self.controller_version,
                      kinematics=self.kinematics.fingerprint() if self.kinematics else None)

    async def _ensure_running(self) -> None:
        """Power on and release the brakes if needed; raise ConnectFailed if not allowed."""
        o = self.options
        mode = dash.parse_robot_mode(await self.dashboard("robotmode"))
        if mode == "RUNNING":
            return
        if not o.power_on:
            raise errors.ConnectFailed(f"robot mode is {mode}, not RUNNING (power_on is off)",
                                       kind=self.kind)
        deadline = time.monotonic() + o.power_on_timeout_s
        if mode in ("POWER_OFF", "CONFIRM_SAFETY", "BOOTING"):
            reply = await self.dashboard("power on")
            if not reply.startswith("Powering on"):
                raise errors.ConnectFailed(f"power on refused: {reply!r}", kind=self.kind)
            await self._wait_mode({"IDLE", "RUNNING"}, deadline)
        reply = await self.dashboard("brake release")
        if not reply.startswith("Brake releasing"):
            raise errors.ConnectFailed(f"brake release refused: {reply!r}", kind=self.kind)
        await self._wait_mode({"RUNNING"}, deadline)

    async def _wait_mode(self, modes: set[str], deadline: float) -> None:
        delay = 0.005
        while True:
            mode = dash.parse_robot_mode(await self.dashboard("robotmode"))
            if mode in modes:
                return
            if time.monotonic() + delay > deadline:
                raise errors.DriverTimeout(f"robot mode still {mode}, waiting for {sorted(modes)}",
                                           kind=self.kind)
            await asyncio.sleep(delay)
            delay = min(2 * delay, 0.25)

    async def _open_rtde(self, deadline: float) -> None:
        o = self.options
        self._rtde = conn = TcpTransport(o.host, o.rtde_port)
        await conn.open(timeout=max(0.1, deadline - time.monotonic()))
        framer = rtde.RtdeFramer()

        async def ask(request: bytes, ptype: int) -> rtde.RtdePackage:
            await conn.write(request)
            while True:
                for pkg in framer.packages():
                    if pkg.type == ptype:
                        return pkg
                    if pkg.type == rtde.TEXT_MESSAGE:
                        self.log.info("rtde message", text=rtde.parse_text_message(pkg.payload))
                framer.feed(await conn.read(65536, timeout=max(0.01, deadline
                                                               - time.monotonic())))

        pkg = await ask(rtde.request_protocol_version(2), rtde.REQUEST_PROTOCOL_VERSION)
        if not pkg.payload or not pkg.payload[0]:
            raise errors.ConnectFailed("the controller refused RTDE protocol version 2",
                                       kind=self.kind)
        pkg = await ask(rtde.encode(rtde.GET_URCONTROL_VERSION), rtde.GET_URCONTROL_VERSION)
        self.controller_version = rtde.parse_controller_version(pkg.payload)
        base = o.register_base
        names = ["timestamp", "actual_q", "target_q", "robot_mode", "safety_mode",
                 "runtime_state", "joint_temperatures", self._reg_int, self._reg_start,
                 *(f"output_double_register_{base + k}" for k in range(_READ_CHUNK))]
        pkg = await ask(rtde.setup_outputs(names, o.rtde_frequency_hz), rtde.SETUP_OUTPUTS)
        rid, types = rtde.parse_recipe_reply(pkg.payload)
        if rid == 0 or len(types) != len(names):
            bad = [n for n, t in zip(names, types, strict=False) if t in ("NOT_FOUND", "IN_USE")]
            raise errors.ConnectFailed(f"RTDE output recipe refused (variables {bad or types})",
                                       kind=self.kind)
        self._names, self._types = names, types
        pkg = await ask(rtde.encode(rtde.START), rtde.START)
        if not pkg.payload or not pkg.payload[0]:
            raise errors.ConnectFailed("RTDE start refused", kind=self.kind)
        self._tasks.append(asyncio.create_task(self._rtde_loop(conn, framer), name="ur-rtde"))

    async def _close_impl(self) -> None:
        if self._rtde is not None and self._rtde.is_open and self._lost is None:
            with contextlib.suppress(Exception):
                await self._rtde.write(rtde.encode(rtde.PAUSE))
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self._tasks = []
        for conn in (self._rtde, self._primary, self._dash):
            if conn is not None:
                await conn.close()
        self._rtde = self._primary = self._dash = None
        self._fail_waiters(errors.ConnectFailed("driver closed", kind=self.kind))

    def _fail_waiters(self, exc: Exception, only: set[int] | None = None) -> None:
        for token, fut in list(self._waiters.items()):
            if only is not None and token not in only:
                continue
            if not fut.done():
                fut.set_exception(exc)
                fut.exception()  # retrieved: nobody may await it any more

    def _lose(self, err: Exception) -> None:
        if self._lost is None:
            self._lost = errors.ConnectFailed(f"connection lost: {err}", kind=self.kind)
        self._fail_waiters(self._lost)
        self._fresh.set()

    def _live(self) -> None:
        self._ensure_connected()
        if self._lost is not None:
            raise self._lost

    # --- dashboard -----------------------------------------------------------------------------
    async def _dash_line(self, timeout: float) -> str:
        conn = self._dash
        if conn is None:
            raise errors.ConnectFailed("dashboard not connected", kind=self.kind)
        deadline = time.monotonic() + timeout
        while True:
            line = self._dash_framer.next_line()
            if line is not None:
                return line.decode("utf-8", errors="replace").strip()
            self._dash_framer.feed(await conn.read(4096, timeout=max(0.01, deadline
                                                                     - time.monotonic())))

    async def dashboard(self, command: str) -> str:
        """Send one Dashboard server command and return its reply line."""
        conn = self._dash
        if conn is None:
            raise errors.ConnectFailed("dashboard not connected", kind=self.kind)
        async with self._dash_lock:
            sent = self._dash_window.open(
                "dashboard", command, time.monotonic() + self.options.reply_timeout_s
            )
            try:
                with self.translate_errors():
                    await conn.write(dash.encode(command))
                    return await self._dash_line(sent.deadline - time.monotonic())
            finally:
                self._dash_window.drop(sent)

    # --- RTDE ----------------------------------------------------------------------------------
    async def _rtde_loop(self, conn: TcpTransport, framer: rtde.RtdeFramer) -> None:
        try:
            async for data in received(conn):
                framer.feed(data)
                for pkg in framer.packages():
                    if pkg.type == rtde.DATA_PACKAGE and pkg.payload[:1] == b"\x01":
                        self._on_state(rtde.values_by_name(self._names, self._types,
                                                           pkg.payload[1:]))
                    elif pkg.type == rtde.TEXT_MESSAGE:
                        self.log.warning("rtde message",
                                         text=rtde.parse_text_message(pkg.payload))
        except (errors.TransportError, errors.FramingError, errors.ProtocolError) as err:
            self._lose(err)

    def _on_state(self, state: dict[str, Any]) -> None:
        self._state = state
        self._state_time = time.monotonic()
        token = int(state[self._reg_int])
        fut = self._waiters.get(token)
        if fut is not None and not fut.done():
            fut.set_result(state)
        pending = [t for t, f in self._waiters.items() if not f.done()]
        if pending:
            self._watch_programs(state, pending)
        self._fresh.set()
        self._fresh = asyncio.Event()

    def _watch_programs(self, state: dict[str, Any], pending: list[int]) -> None:
        """Fail waiting programs the controller ended without their token: a protective or
        emergency stop, or a stop from the pendant or dashboard after the program ran."""
        running = int(state["runtime_state"]) == RuntimeState.PLAYING
        if not self._modes_ok():
            lost = errors.MotionRejected(f"program ended: {self._modes()}", kind=self.kind,
                                         code=int(state["safety_mode"]))
            self._fail_waiters(lost, only=set(pending))
            return
        started = int(state[self._reg_start])
        if not running and started in pending:
            # Our program wrote its start token, is no longer running and never wrote its
            # end token (the package showing it would have resolved it above).
            self._fail_waiters(_ProgramFailed("the program stopped before it finished "
                                              "(stopped on the pendant or dashboard?)"),
                               only={started})

    async def _next_state(self, timeout: float) -> dict[str, Any]:
        event = self._fresh
        async with asyncio.timeout(max(0.001, timeout)):
            await event.wait()
        if self._lost is not None:
            raise self._lost
        return self._state

    # --- primary interface ---------------------------------------------------------------------
    async def _primary_loop(self, conn: TcpTransport) -> None:
        framer = prim.PrimaryFramer()
        try:
            async for data in received(conn):
                framer.feed(data)
                for mtype, body in framer.messages():
                    try:
                        msg = prim.decode_message(mtype, body)
                    except errors.ProtocolError as err:
                        self.log.warning("bad primary message", error=str(err)[:120])
                        continue
                    if isinstance(msg, prim.RobotState) and msg.kinematics is not None:
                        self.kinematics = msg.kinematics
                        self._kin_event.set()
                    elif isinstance(msg, prim.RuntimeException):
                        self.runtime_exceptions.append(msg.text)
                        self.log.warning("runtime exception", text=msg.text, line=msg.line)
                        self._fail_waiters(_ProgramFailed(msg.text))
        except (errors.TransportError, errors.FramingError) as err:
            self._lose(err)

    async def _run(self, body: Sequence[str], *, timeout: float, motion: bool = False,
                   gen: int | None = None) -> dict[str, Any]:
        """Send ``body`` as a program ending in a token write; return the RTDE state that
        shows the token. Raises _ProgramFailed on a runtime exception, MotionStopped when
        stop() intervenes, DriverTimeout."""
        conn = self._primary
        if conn is None:
            raise errors.ConnectFailed("not connected", kind=self.kind)
        async with self._program_lock:
            if gen is not None and gen != self._stop_gen:
                raise errors.MotionStopped(
                    "stop requested before the move was sent", kind=self.kind)
            self._token = (self._token + 1) % (1 << 31)
            token = self._token
            fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
            self._waiters[token] = fut
            if motion:
                self._motion.add(token)
            base = self.options.register_base
            program = "\n".join([f"def rc_{token}():",
                                 f"  write_output_integer_register({base + 1}, {token})",
                                 *(f"  {line}" for line in body),
                                 f"  write_output_integer_register({base}, {token})", "end", ""])
            try:
                with self.translate_errors():
                    await conn.write(program.encode())
            except BaseException:
                self._waiters.pop(token, None)
                self._motion.discard(token)
                raise
        try:
            async with asyncio.timeout(timeout):
                return await fut
        except TimeoutError as err:
            raise errors.DriverTimeout(f"program rc_{token} did not finish within {timeout:.3g} s",
                                       kind=self.kind) from err
        finally:
            self._waiters.pop(token, None)
            self._motion.discard(token)

    # --- motion --------------------------------------------------------------------------------
    async def move_to(self, q_rad: Sequence[float], *, speed_pct: float | None = None,
                      timeout: float = 60.0) -> api.JointReading:
        """Move with ``movej`` to ``q_rad`` (radians), wait in position, return the joints.

        Raises
        ------
        LimitViolation
            Target outside the configured joint limits (nothing is sent).
        MotionRejected
            The robot is not running normally, or the program ended in a runtime exception
            (joint limit, protective stop).
        MotionStopped
            :meth:`stop` halted the motion.
        DriverTimeout
            The motion did not complete within ``timeout`` seconds.
        """
        q, speed = self._move_target(q_rad, speed_pct)
        self._live()
        gen = self._stop_gen
        self._check_modes()
        o = self.options
        v = max(1e-4, min(100.0, speed) / 100.0 * o.max_joint_speed_rad_s)
        line = f"movej({prim.script_literal(q)}, a={o.acceleration_rad_s2!r}, v={v!r})"
        try:
            state = await self._run([line], timeout=timeout, motion=True, gen=gen)
        except _ProgramFailed as err:
            raise errors.MotionRejected(f"movej failed: {err}", kind=self.kind) from err
        return api.JointReading(tuple(float(x) for x in state["actual_q"]), time.time())

    def _modes(self) -> str:
        mode = int(self._state.get("robot_mode", RobotMode.NO_CONTROLLER))
        safety = int(self._state.get("safety_mode", 0))
        return (f"robot mode {RobotMode.NAMES.get(mode, mode)}, safety mode "
                f"{SafetyMode.NAMES.get(safety, safety)}")

    def _modes_ok(self) -> bool:
        """True when the arm runs normally (robot mode RUNNING, safety NORMAL or REDUCED)."""
        mode = int(self._state.get("robot_mode", RobotMode.NO_CONTROLLER))
        safety = int(self._state.get("safety_mode", 0))
        return mode == RobotMode.RUNNING and safety in (SafetyMode.NORMAL, SafetyMode.REDUCED)

    def _check_modes(self) -> None:
        if not self._modes_ok():
            raise errors.MotionRejected(f"{self._modes()}: cannot move", kind=self.kind,
                                        code=int(self._state.get("safety_mode", 0)))

    def _recent_state(self) -> dict[str, Any]:
        """The newest RTDE package; DriverTimeout when it is older than the reply timeout."""
        self._live()
        if time.monotonic() - self._state_time > self.options.reply_timeout_s:
            raise errors.DriverTimeout("no RTDE data for longer than the reply timeout",
                                       kind=self.kind)
        return self._state

    async def read_joints(self) -> api.JointReading:
        """Return ``actual_q`` from the newest RTDE package (radians)."""
        state = self._recent_state()
        return api.JointReading(tuple(float(x) for x in state["actual_q"]), time.time())

    async def read_joint_temperatures(self) -> api.JointTemperatures:
        """Return ``joint_temperatures`` (°C) from the newest RTDE package, stamped with its
        ``timestamp`` (seconds since the controller started)."""
        state = self._recent_state()
        return api.JointTemperatures(tuple(float(x) for x in state["joint_temperatures"]),
                                     float(state["timestamp"]))

    async def stop(self) -> None:
        """Halt motion with ``stopj`` (a program of its own, which replaces the running one).

        Returns once an RTDE package shows the stop program finished; a waiting ``move_to``
        raises MotionStopped. A no-op when not connected, and nothing is sent when the
        controller has halted the arm itself (protective or emergency stop, power off).

        Raises
        ------
        ConnectFailed
            The session is lost.
        DriverTimeout
            The controller did not confirm the stop in time.
        OperationError
            The stop program failed.
        """
        if self.state != "connected":
            return
        if self._lost is not None:
            raise self._lost
        self._stop_gen += 1
        stopped = errors.MotionStopped("motion stopped by request (stopj)", kind=self.kind)
        self._fail_waiters(stopped, only=set(self._motion))
        if not self._modes_ok():
            # A protective or emergency stop, or power off: the controller has halted the
            # arm already and would refuse to run a program.
            self.log.info("stop: the arm is halted by the controller", state=self._modes())
            return
        decel = self.options.stop_deceleration_rad_s2
        try:
            await self._run([f"stopj({decel!r})"], timeout=self.options.reply_timeout_s)
        except _ProgramFailed as err:
            raise errors.OperationError(f"stopj failed: {err}", kind=self.kind) from err
        self.log.info("stopped")

    # --- controller calibration ----------------------------------------------------------------
    async def controller_calibration(self) -> api.ControllerCalibration:
        """The controller's own kinematic calibration (the kinematics info: its DH table, SI,
        per-joint checksums and calibration status); UR has no absolute-accuracy option.

        Waits (at most ``reply_timeout_s``) for a kinematics info sent after the call: the
        second one to arrive (the first may have been on its way already, 10 Hz); a
        controller that sends it only when a client connects gives the one of this session
        (a new calibration takes effect after a reboot, which ends the session).
        """
        if self.kinematics is None or self._lost is not None:
            raise errors.ConnectFailed("no kinematics info received; connect first", kind=self.kind)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self.options.reply_timeout_s):
                for _ in range(2):
                    self._kin_event.clear()
                    await self._kin_event.wait()
        k = self.kinematics
        facts = {"checksums": k.fingerprint(), "calibration_status": k.calibration_status,
                 "dh_theta_rad": list(k.dh_theta), "dh_a_m": list(k.dh_a),
                 "dh_d_m": list(k.dh_d), "dh_alpha_rad": list(k.dh_alpha)}
        return api.ControllerCalibration("ur-kinematics-info", facts, absolute_accuracy=False)

    # --- compensation --------------------------------------------------------------------------
    def _slots(self, table: CompensationTable) -> dict[str, int]:
        """Installation variable -> number of values, for the slots ``table`` writes."""
        p = self.options.variable_prefix
        if table.kind == "targets":
            return {f"{p}wp_{r.index}": self.dof for r in table.targets or [] if r.status == "ok"}
        if table.kind == "joint":
            out: dict[str, int] = {}
            for c in table.joints or []:
                out[f"{p}jq_{c.joint}"] = len(c.q_deg)
                out[f"{p}jdq_{c.joint}"] = len(c.dq_deg)
            return out
        raise errors.CompensationError(
            f"{self.kind} stores only 'targets' and 'joint' tables, not {table.kind!r}")

    def _values(self, table: CompensationTable) -> dict[str, list[float]]:
        """Installation variable -> values (radians) for ``table``."""
        p = self.options.variable_prefix
        out: dict[str, list[float]] = {}
        if table.kind == "targets":
            for r in table.targets or []:
                if r.status != "ok":
                    continue
                q = [math.radians(v) for v in r.q_deg]
                api.check_joint_target(q, self.joint_limits_rad, kind=self.kind)
                out[f"{p}wp_{r.index}"] = q
        else:
            for c in table.joints or []:
                if not 1 <= c.joint <= self.dof:
                    raise errors.CompensationError(f"joint {c.joint} is not a joint of this robot")
                out[f"{p}jq_{c.joint}"] = [math.radians(v) for v in c.q_deg]
                out[f"{p}jdq_{c.joint}"] = [math.radians(v) for v in c.dq_deg]
        return out

    async def _write_variables(self, values: Mapping[str, Sequence[float]]) -> None:
        items = list(values.items())
        for i in range(0, len(items), _WRITE_CHUNK):
            body = [f"{name} = {prim.script_literal(v)}" for name, v in items[i:i + _WRITE_CHUNK]]
            try:
                await self._run(body, timeout=self.options.reply_timeout_s)
            except _ProgramFailed as err:
                raise errors.CompensationError(
                    f"writing installation variables failed: {err}") from err

    async def _read_variables(self, slots: Mapping[str, int]) -> dict[str, list[float]]:
        refs = [(name, k) for name, n in slots.items() for k in range(n)]
        base = self.options.register_base
        flat: list[float] = []
        for i in range(0, len(refs), _READ_CHUNK):
            chunk = refs[i:i + _READ_CHUNK]
            body = [f"write_output_float_register({base + m}, {name}[{k}])"
                    for m, (name, k) in enumerate(chunk)]
            try:
                state = await self._run(body, timeout=self.options.reply_timeout_s)
            except _ProgramFailed as err:
                raise errors.CompensationError(
                    f"reading installation variables failed ({err}); are they declared in "
                    "the installation with enough elements?") from err
            flat += [float(state[f"output_double_register_{base + m}"])
                     for m in range(len(chunk))]
        out: dict[str, list[float]] = {}
        for (name, _), v in zip(refs, flat, strict=True):
            out.setdefault(name, []).append(v)
        return out

    async def write_compensation(self, table: CompensationTable) -> None:
        """Write a ``targets`` or ``joint`` table as installation variables, read it back and
        compare.

        Raises
        ------
        CompensationError
            Unsupported kind, or the variables cannot be written (not declared).
        LimitViolation
            A target row lies outside the joint limits (nothing is written).
        VerificationMismatch
            The controller holds different values after writing.
        """
        self._live()
        values = self._values(table)  # every row checked before anything is written
        await self._write_variables(values)
        self._last_table = table
        back = await self.read_compensation()
        diff = table_diff(table, back, tol=self.options.verify_tol)
        self._check_read_back(diff, "compensation read back differs")

    async def read_compensation(self) -> CompensationTable | None:
        """The last table written in this session, its numbers re-read from the controller
        (None before any write: installation variables carry no table metadata)."""
        self._live()
        if self._last_table is None:
            return None
        return await self.read_compensation_like(self._last_table)

    async def read_compensation_like(self, table: CompensationTable) -> CompensationTable:
        """``table`` with its numbers replaced by what the installation variables hold."""
        self._live()
        got = await self._read_variables(self._slots(table))
        p = self.options.variable_prefix
        update: dict[str, Any]
        if table.kind == "targets":
            rows: list[TargetRow] = []
            for r in table.targets or []:
                if r.status != "ok":
                    rows.append(r)
                    continue
                q = [math.degrees(v) for v in got[f"{p}wp_{r.index}"]][: len(r.q_deg)]
                rows.append(r.model_copy(update={"q_deg": q}))
            update = {"targets": rows}
        else:
            joints: list[JointCorrection] = []
            for c in table.joints or []:
                joints.append(c.model_copy(update={
                    "q_deg": [math.degrees(v) for v in got[f"{p}jq_{c.joint}"]],
                    "dq_deg": [math.degrees(v) for v in got[f"{p}jdq_{c.joint}"]],
                }))
            update = {"joints": joints}
        back = table.model_copy(update=update)
        return back.model_copy(update={"checksum": back.compute_checksum()})

    async def snapshot_compensation(self, table: CompensationTable) -> ControllerSnapshot:
        """Read the installation variables ``table`` would write (radians, verbatim)."""
        self._live()
        got = await self._read_variables(self._slots(table))
        return ControllerSnapshot(driver=self.kind, covers=table.kind,
                                  items={f"var:{k}": v for k, v in got.items()})

    async def restore_snapshot(self, snapshot: ControllerSnapshot) -> None:
        """Write a snapshot's variables back, read them again and compare.

        Raises
        ------
        VerificationMismatch
            The controller holds different values afterwards.
        """
        self._live()
        values: dict[str, list[float]] = {}
        for key, value in snapshot.items.items():
            slot, _, name = key.partition(":")
            if slot != "var" or not name.startswith(self.options.variable_prefix):
                raise errors.CompensationError(f"snapshot slot {key!r} is not a {self.kind} slot")
            values[name] = [float(v) for v in value]
        await self._write_variables(values)
        self._last_table = None
        back = await self._read_variables({k: len(v) for k, v in values.items()})
        diff = snapshot_diff(snapshot, ControllerSnapshot(
            driver=self.kind, covers=snapshot.covers,
            items={f"var:{k}": v for k, v in back.items()}), tol=self.options.verify_tol)
        self._check_read_back(diff, "restored values read back differ")
