"""An asyncio Universal Robots controller simulator (docs/protocols/universal-robots.md).

Five listening sockets around one :class:`SimWorld` robot, as an e-Series controller has:

* Dashboard server (29999): power on/off, brake release, load/play/stop/pause of ``.urp``
  programs, robot mode, safety status and mode, remote control, program state.
* Primary (30001) and secondary (30002) interfaces: a version message on connect, then robot
  state messages (robot mode data, joint data, kinematics info with its checksums) at 10 Hz
  (scaled); URScript received on either is compiled as robocal's subset and run: a ``def``
  program or a single line replaces the running program (halting any motion), a ``sec``
  program runs at once beside it and may not move the robot.
* RTDE (30004): protocol version 2, controller version, output and input recipes, start and
  pause, data packages streamed at the recipe frequency (capped by ``rtde_max_hz``), inputs
  applied to the standard, configurable and tool digital outputs, the speed slider and the
  input registers.
* Real-time interface (30003): URScript in, as on 30001/30002 (no state stream out).
  ur-rtde's control program (``def rtde_control():``) runs as an emulation of its command
  loop (:class:`_RtdeControl`).

The TCP pose (RTDE ``actual_TCP_pose``, ``target_TCP_pose``) is the controller's forward
kinematics: the DH table it reports and the active TCP offset.

Installation variables are the names assigned by a program that start with
``installation_prefix``; they keep their values after the program ends (as variables
declared in the PolyScope installation do). Reading an undefined variable is a runtime
exception: the program stops and a runtime-exception message goes to the primary and
secondary clients.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from robocal.drivers.sim._server import WorldSimulator, port_of, received
from robocal.drivers.sim.faults import FaultConfig
from robocal.drivers.sim.world import SimWorld
from robocal.errors import FramingError, ProtocolError
from robocal.kinematics import matrix_to_rotvec, rotvec_to_matrix
from robocal.protocols import ur_dashboard as dash
from robocal.protocols import ur_primary as prim
from robocal.protocols import ur_rtde as rtde
from robocal.protocols.framing import LineFramer
from robocal.protocols.ur_rtde import RobotMode, RuntimeState, SafetyMode

__all__ = ["UrSimOptions", "UrSimulator"]

_log = structlog.get_logger(__name__)


class UrSimOptions(BaseModel):
    """Behaviour of the simulated controller.

    ``time_scale`` multiplies motion, power-up and brake-release times (0: instantaneous,
    1: real time). ``controller_version`` is what RTDE and the version message report (5.x:
    e-Series, 3.x: CB3). ``programs`` are the ``.urp`` files on the controller.
    ``remote_control``: False makes the dashboard refuse power, play and load (local mode);
    ``start_powered``: begin in RUNNING instead of POWER_OFF. The installation declares
    ``rc_wp_0`` .. ``rc_wp_<declared_waypoints - 1>`` (six zeros each) and ``rc_jq_<j>``,
    ``rc_jdq_<j>`` (``declared_joint_points`` zeros), as ``deploy/config/ur.toml`` asks of a
    real robot's installation.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    time_scale: float = Field(default=0.001, ge=0.0)
    controller_version: tuple[int, int, int, int] = (5, 12, 2, 1101534)
    robot_model: str = "UR10"
    serial_number: str = "20235500001"
    programs: tuple[str, ...] = ("calibration.urp", "robocal.urp")
    remote_control: bool = True
    start_powered: bool = False
    power_on_s: float = Field(default=1.0, ge=0.0)
    brake_release_s: float = Field(default=2.0, ge=0.0)
    max_joint_speed_rad_s: float = Field(default=math.pi, gt=0.0)
    min_motion_s: float = Field(default=0.012, ge=0.0)
    state_hz: float = Field(default=10.0, gt=0.0)
    rtde_max_hz: float = Field(default=500.0, gt=0.0)
    installation_prefix: str = "rc_"
    declared_waypoints: int = Field(default=200, ge=0)
    declared_joint_points: int = Field(default=64, ge=0)
    calibration_status: int = 0


class _RtdeSession:
    """One RTDE client's recipes and streaming task."""

    def __init__(self, sim: UrSimulator, writer: asyncio.StreamWriter) -> None:
        self.sim = sim
        self.writer = writer
        self.version = 1
        self.out_names: list[str] = []
        self.out_types: list[str] = []
        self.frequency = 125.0
        self.inputs: dict[int, tuple[list[str], list[str]]] = {}
        self.streaming: asyncio.Task[None] | None = None
        self.closed = False

    async def send(self, data: bytes) -> None:
        if self.closed:
            return
        try:
            self.writer.write(data)
            await self.writer.drain()
        except (ConnectionError, RuntimeError):
            self.closed = True

    async def handle(self, pkg: rtde.RtdePackage) -> None:
        sim = self.sim
        t = pkg.type
        if t == rtde.REQUEST_PROTOCOL_VERSION:
            v = int.from_bytes(pkg.payload[:2], "big") if len(pkg.payload) >= 2 else 0
            ok = v in (1, 2)
            if ok:
                self.version = v
            await self.send(rtde.accepted(t, ok))
        elif t == rtde.GET_URCONTROL_VERSION:
            await self.send(rtde.controller_version(*sim.options.controller_version))
        elif t == rtde.SETUP_OUTPUTS:
            if self.version >= 2:
                freq, names = rtde.parse_setup_outputs_request(pkg.payload)
            else:
                freq, names = 125.0, rtde.parse_names(pkg.payload)
            types = [rtde.output_type(n) for n in names]
            ok = bool(names) and "NOT_FOUND" not in types and 0 < freq <= 500.0
            if ok:
                self.out_names, self.out_types, self.frequency = names, types, freq
            await self.send(rtde.recipe_reply(t, 1 if ok else 0, types))
        elif t == rtde.SETUP_INPUTS:
            names = rtde.parse_names(pkg.payload)
            types = [rtde.input_type(n) for n in names]
            types = ["IN_USE" if ty != "NOT_FOUND" and sim.input_owner(n, self) else ty
                     for n, ty in zip(names, types, strict=True)]
            ok = bool(names) and not ({"NOT_FOUND", "IN_USE"} & set(types))
            rid = 0
            if ok:
                rid = len(self.inputs) + 1
                self.inputs[rid] = (names, types)
            await self.send(rtde.recipe_reply(t, rid, types))
        elif t == rtde.START:
            ok = bool(self.out_names)
            await self.send(rtde.accepted(t, ok))
            if ok and self.streaming is None:
                self.streaming = asyncio.create_task(self._stream())
        elif t == rtde.PAUSE:
            await self._pause()
            await self.send(rtde.accepted(t, True))
        elif t == rtde.DATA_PACKAGE:
            if not pkg.payload or pkg.payload[0] not in self.inputs:
                await self.send(rtde.text_message("unknown input recipe", "RTDE", 2))
                return
            names, types = self.inputs[pkg.payload[0]]
            try:
                values = rtde.values_by_name(names, types, pkg.payload[1:])
            except ProtocolError as err:
                await self.send(rtde.text_message(str(err)[:200], "RTDE", 2))
                return
            sim.apply_inputs(values)
        else:
            await self.send(rtde.text_message(f"unknown package type {pkg.letter}", "RTDE", 2))

    async def _pause(self) -> None:
        task, self.streaming = self.streaming, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _stream(self) -> None:
        period = 1.0 / min(self.frequency, self.sim.options.rtde_max_hz)
        nxt = time.monotonic()
        while not self.closed:
            values = self.sim.output_values(self.out_names)
            await self.send(rtde.data_package(1, self.out_types, values))
            nxt += period
            delay = nxt - time.monotonic()
            if delay < -period:  # fell behind: do not burst
                nxt = time.monotonic()
                delay = 0.0
            await asyncio.sleep(max(0.0, delay))

    async def stop(self) -> None:
        self.closed = True
        await self._pause()


class UrSimulator(WorldSimulator):
    """Simulated Universal Robots e-Series (or CB3) controller on loopback.

    Attributes
    ----------
    variables : dict
        Installation variables: name -> number, string or list of floats.
    scripts : list of str
        Every program received on the primary or secondary interface.
    dashboard_log : list of str
        Every dashboard command line received.
    """

    def __init__(self, world: SimWorld, options: UrSimOptions | None = None,
                 faults: FaultConfig | None = None) -> None:
        super().__init__(world, faults)
        self.options = options or UrSimOptions()
        self.robot_mode = RobotMode.RUNNING if self.options.start_powered else RobotMode.POWER_OFF
        self.safety_mode = SafetyMode.NORMAL
        self.remote_control = self.options.remote_control
        self.loaded_program = ""
        self.program_state = "STOPPED"  # of the loaded .urp: STOPPED, PLAYING, PAUSED
        self.variables: dict[str, Any] = self._declared()
        self.scripts: list[str] = []
        self.dashboard_log: list[str] = []
        self.int_out = [0] * 48
        self.double_out = [0.0] * 48
        self.bool_out = [False] * 128
        self.int_in = [0] * 48
        self.double_in = [0.0] * 48
        self.bool_in = [False] * 128
        self.digital_out = 0  # bits 0-7 standard, 8-15 configurable, 16-17 tool
        self.speed_slider = 1.0
        self.analog_out = [0.0, 0.0]
        self.tcp = [0.0] * 6               # active TCP offset p[x, y, z, rx, ry, rz] (m, rad)
        self.payload: tuple[float, list[float]] = (0.0, [0.0, 0.0, 0.0])   # kg, CoG m
        self.script_runs = 0
        self.runtime_errors: list[str] = []
        self.ports: dict[str, int] = {}
        self._program: asyncio.Task[None] | None = None
        self._program_kind = ""
        self._input_owners: dict[str, _RtdeSession] = {}
        self._state_writers: set[asyncio.StreamWriter] = set()
        self._mode_task: asyncio.Task[None] | None = None
        self._t0 = time.monotonic()
        self._dh = self._nominal_dh()
        signs = [j.sign for j in world.cell.robot.joints][:6]
        self._signs = signs + [1] * (6 - len(signs))

    def _declared(self) -> dict[str, Any]:
        o = self.options
        p = o.installation_prefix
        out: dict[str, Any] = {f"{p}wp_{i}": [0.0] * 6 for i in range(o.declared_waypoints)}
        for j in range(1, 7):
            out[f"{p}jq_{j}"] = [0.0] * o.declared_joint_points
            out[f"{p}jdq_{j}"] = [0.0] * o.declared_joint_points
        return out

    # --- lifecycle -----------------------------------------------------------------------------
    async def start(self, host: str = "127.0.0.1", *, dashboard: int = 0, primary: int = 0,
                    secondary: int = 0, rtde_port: int = 0, realtime: int = 0
                    ) -> dict[str, int]:
        """Listen on the five ports (0: free ones); return them by name."""
        for name, handler, port in (
            ("dashboard", self._on_dashboard, dashboard),
            ("primary", self._on_primary, primary),
            ("secondary", self._on_primary, secondary),
            ("realtime", self._on_realtime, realtime),
            ("rtde", self._on_rtde, rtde_port),
        ):
            self.ports[name] = port_of(await self._listen(handler, host, port))
        self._track(self._broadcast_state())
        _log.info("ur sim listening", host=host, **self.ports)
        return dict(self.ports)

    async def stop(self) -> None:
        """Stop serving; idempotent."""
        self._close_listeners()
        await self._end_program()
        await self._stop_serving()

    # --- world state ---------------------------------------------------------------------------
    def _nominal_dh(self) -> tuple[tuple[float, ...], ...]:
        robot = self.world.cell.robot
        joints = list(robot.joints)[:6]
        joints += [joints[-1]] * (6 - len(joints))
        return (tuple(float(j.theta_offset) for j in joints), tuple(float(j.a) for j in joints),
                tuple(float(j.d) for j in joints), tuple(float(j.alpha) for j in joints))

    def kinematics(self) -> prim.KinematicsInfo:
        """The kinematics info the controller reports (its calibrated DH table)."""
        theta, a, d, alpha = self._dh
        checks = tuple(prim.dh_checksum(*v) for v in zip(theta, a, d, alpha, strict=True))
        return prim.KinematicsInfo(checks, theta, a, d, alpha, self.options.calibration_status)

    def set_kinematics(self, theta: Sequence[float], a: Sequence[float], d: Sequence[float],
                       alpha: Sequence[float]) -> None:
        """Replace the controller's DH table (as a new factory calibration would)."""
        self._dh = (tuple(theta), tuple(a), tuple(d), tuple(alpha))

    def tcp_pose(self, q: Sequence[float], tcp: Sequence[float] | None = None) -> list[float]:
        """The controller's forward kinematics: the TCP pose ``p[x, y, z, rx, ry, rz]`` (m,
        rotation vector) in the base frame for joints ``q`` (6,) rad, from the DH table it
        reports (:meth:`kinematics`) and the TCP offset ``tcp`` (default: the active one)."""
        theta, a, d, alpha = self._dh
        T = np.eye(4)
        for i in range(6):
            th = self._signs[i] * float(q[i]) + theta[i]
            ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(alpha[i]), math.sin(alpha[i])
            T = T @ np.array([[ct, -st * ca, st * sa, a[i] * ct],
                              [st, ct * ca, -ct * sa, a[i] * st],
                              [0.0, sa, ca, d[i]], [0.0, 0.0, 0.0, 1.0]])
        off = self.tcp if tcp is None else [float(v) for v in tcp]
        T_tcp = np.eye(4)
        T_tcp[:3, :3] = rotvec_to_matrix(np.array(off[3:6]))
        T_tcp[:3, 3] = off[:3]
        T = T @ T_tcp
        return [float(v) for v in T[:3, 3]] + [float(v) for v in matrix_to_rotvec(T[:3, :3])]

    @property
    def runtime_state(self) -> int:
        """RTDE ``runtime_state``: a script program or the loaded .urp playing, or stopped."""
        if self._program is not None and not self._program.done():
            return RuntimeState.PLAYING
        return {"PLAYING": RuntimeState.PLAYING, "PAUSED": RuntimeState.PAUSED}.get(
            self.program_state, RuntimeState.STOPPED)

    def _q6(self, q: Any) -> list[float]:
        vals = [float(v) for v in q][:6]
        return vals + [0.0] * (6 - len(vals))

    def output_values(self, names: Sequence[str]) -> list[Any]:
        """Current values of RTDE output variables ``names`` (recipe order)."""
        state = self._output_state()
        out: list[Any] = []
        for n in names:
            t = rtde.output_type(n)
            if n in state:
                out.append(state[n])
            elif n in _TCP_POSE_OF:    # forward kinematics only for the recipes asking
                out.append(self.tcp_pose(state[_TCP_POSE_OF[n]]))
            elif "_register" in n:
                out.append(self._register_value(n, t))
            else:
                out.append(_zero(t))
        return out

    def _output_state(self) -> dict[str, Any]:
        """RTDE outputs other than registers, by name (one consistent snapshot)."""
        world = self.world
        motion = world.motion
        qd = [0.0] * 6
        if motion is not None and motion.duration_s > 0:
            qd = self._q6((motion.q_to_rad - motion.q_from_rad) / motion.duration_s)
        running = self.runtime_state == RuntimeState.PLAYING
        power = self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
        return {
            "timestamp": time.monotonic() - self._t0,
            "actual_q": self._q6(world.q_actual_rad),
            "target_q": self._q6(world.q_cmd_rad),
            "actual_qd": qd,
            "target_qd": qd,
            "robot_mode": self.robot_mode,
            "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode,
            "runtime_state": self.runtime_state,
            "joint_mode": [253 if self.robot_mode == RobotMode.RUNNING else 251] * 6,
            "robot_status_bits": int(power) | (int(running) << 1),
            "safety_status_bits": 1 << (self.safety_mode - 1) if self.safety_mode >= 1 else 0,
            "speed_scaling": self.speed_slider,
            "target_speed_fraction": self.speed_slider,
            "actual_digital_output_bits": self.digital_out,
            "standard_analog_output0": self.analog_out[0],
            "standard_analog_output1": self.analog_out[1],
            "actual_main_voltage": 48.0 if power else 0.0,
            "actual_robot_voltage": 48.0 if power else 0.0,
            "joint_temperatures": self._q6(world.joint_temperatures()[0]),
        }

    def _register_value(self, n: str, t: str) -> Any:
        """An ``input_``/``output_`` int, double or bit register (or 32 bits of them)."""
        if n.endswith(("registers0_to_31", "registers32_to_63")):
            bits = self.bool_out if n.startswith("output") else self.bool_in
            base = 0 if n.endswith("0_to_31") else 32
            return sum(1 << k for k in range(32) if bits[base + k])
        banks: dict[str, Sequence[Any]] = {
            "output_int": self.int_out, "output_double": self.double_out,
            "input_int": self.int_in, "input_double": self.double_in,
            "output_bit": self.bool_out, "input_bit": self.bool_in,
        }
        bank, sep, index = n.partition("_register_")
        if not sep or bank not in banks or not index.isdigit():
            return _zero(t)
        return banks[bank][int(index)]

    def input_owner(self, name: str, session: _RtdeSession) -> bool:
        """True when another live RTDE session has ``name`` in an input recipe (IN_USE)."""
        owner = self._input_owners.get(name)
        if owner is not None and owner is not session and not owner.closed:
            return True
        self._input_owners[name] = session
        return False

    def apply_inputs(self, values: dict[str, Any]) -> None:
        """Apply an RTDE input data package."""
        for mask_name, value_name, shift in (
            ("standard_digital_output_mask", "standard_digital_output", 0),
            ("configurable_digital_output_mask", "configurable_digital_output", 8),
            ("tool_digital_output_mask", "tool_digital_output", 16),
        ):
            if mask_name in values and value_name in values:
                mask = int(values[mask_name]) << shift
                self.digital_out = (self.digital_out & ~mask) | ((int(values[value_name])
                                                                  << shift) & mask)
        if values.get("speed_slider_mask") and "speed_slider_fraction" in values:
            self.speed_slider = min(1.0, max(0.0, float(values["speed_slider_fraction"])))
        if "standard_analog_output_mask" in values:
            mask = int(values["standard_analog_output_mask"])
            for k in (0, 1):
                if mask & (1 << k) and f"standard_analog_output_{k}" in values:
                    self.analog_out[k] = float(values[f"standard_analog_output_{k}"])
        for name, value in values.items():
            if name.startswith("input_int_register_"):
                self.int_in[int(name.rsplit("_", 1)[1])] = int(value)
            elif name.startswith("input_double_register_"):
                self.double_in[int(name.rsplit("_", 1)[1])] = float(value)
            elif name.startswith("input_bit_register_"):
                self.bool_in[int(name.rsplit("_", 1)[1])] = bool(value)
            elif name.startswith("input_bit_registers") and name.endswith(("0_to_31",
                                                                          "32_to_63")):
                base = 0 if name.endswith("0_to_31") else 32
                for k in range(32):
                    self.bool_in[base + k] = bool(int(value) >> k & 1)

    # --- dashboard -----------------------------------------------------------------------------
    async def _on_dashboard(self, reader: asyncio.StreamReader,
                            writer: asyncio.StreamWriter) -> None:
        framer = LineFramer(max_length=dash.MAX_LINE)
        writer.write(dash.encode(dash.GREETING))
        await writer.drain()
        async for data in received(reader, 4096):
            framer.feed(data)
            for line in framer.lines():
                if isinstance(line, FramingError):
                    reply = "could not understand: (line too long)"
                else:
                    text = line.decode("utf-8", errors="replace").strip()
                    if not text:
                        continue
                    self.dashboard_log.append(text)
                    reply = await self._dashboard(text)
                # One write per reply: clients read a reply with one recv.
                writer.write(dash.encode(reply))
                await writer.drain()
                if reply == "Disconnected":
                    return

    async def _dashboard(self, text: str) -> str:
        cmd = dash.parse_command(text)
        if cmd is None:
            return f"could not understand: '{text}'"
        if cmd.word in _REMOTE_ONLY and not self.remote_control:
            return f"Command is not allowed due to safety reasons: {cmd.word}"
        if cmd.word in _FIXED_REPLIES:
            return _FIXED_REPLIES[cmd.word]
        answer = _QUERIES.get(cmd.word)
        if answer is not None:
            return answer(self, cmd.argument)
        action = _ACTIONS.get(cmd.word)
        if action is not None:
            return await action(self, cmd.argument)
        return "Disconnected"  # quit

    # Dashboard commands that change state (the table _ACTIONS below the class).
    async def _dash_power_on(self, _arg: str) -> str:
        if self.robot_mode in (RobotMode.POWER_OFF,):
            self._change_mode(RobotMode.POWER_ON, RobotMode.IDLE, self.options.power_on_s)
        return "Powering on"

    async def _dash_power_off(self, _arg: str) -> str:
        await self._end_program()
        self.world.halt()
        self.program_state = "STOPPED"
        self._cancel_mode_change()
        self.robot_mode = RobotMode.POWER_OFF
        return "Powering off"

    async def _dash_brake_release(self, _arg: str) -> str:
        if self.robot_mode in (RobotMode.IDLE, RobotMode.POWER_ON):
            self._change_mode(RobotMode.IDLE, RobotMode.RUNNING,
                              self.options.brake_release_s, wait_idle=True)
        elif self.robot_mode == RobotMode.POWER_OFF:
            return "Brake release failed: robot is powered off"
        return "Brake releasing"

    async def _dash_load(self, arg: str) -> str:
        name = arg.rsplit("/", 1)[-1]
        if not name.endswith(".urp") or name not in self.options.programs:
            return f"File not found: {arg}"
        await self._end_program()
        self.program_state = "STOPPED"
        self.loaded_program = "/programs/" + name
        return f"Loading program: {arg}"

    async def _dash_play(self, _arg: str) -> str:
        if (not self.loaded_program or self.robot_mode != RobotMode.RUNNING
                or self.safety_mode != SafetyMode.NORMAL):
            return "Failed to execute: play"
        await self._end_program()
        self.program_state = "PLAYING"
        return "Starting program"

    async def _dash_stop(self, _arg: str) -> str:
        if self.runtime_state == RuntimeState.STOPPED:
            return "Failed to execute: stop"
        await self._end_program()
        self.world.halt()
        self.program_state = "STOPPED"
        return "Stopped"

    async def _dash_pause(self, _arg: str) -> str:
        if self.program_state != "PLAYING":
            return "Failed to execute: pause"
        self.program_state = "PAUSED"
        return "Pausing program"

    async def _dash_unlock(self, _arg: str) -> str:
        if self.safety_mode != SafetyMode.PROTECTIVE_STOP:
            return "Cannot unlock protective stop until 5s after occurrence. Always inspect "\
                   "cause of protective stop before unlocking"
        self.safety_mode = SafetyMode.NORMAL
        return "Protective stop releasing"

    async def _dash_restart_safety(self, _arg: str) -> str:
        self.safety_mode = SafetyMode.NORMAL
        self.robot_mode = RobotMode.POWER_OFF
        return "Restarting safety"

    def _program_name(self) -> str:
        return self.loaded_program.rsplit("/", 1)[-1] or "<unnamed>"

    def _cancel_mode_change(self) -> None:
        if self._mode_task is not None:
            self._mode_task.cancel()
            self._mode_task = None

    def _change_mode(self, now: int, then: int, seconds: float, *,
                     wait_idle: bool = False) -> None:
        """Go to ``now`` at once and to ``then`` after ``seconds`` (scaled)."""
        self._cancel_mode_change()
        if not wait_idle:
            self.robot_mode = now
        delay = seconds * self.options.time_scale

        async def later() -> None:
            if wait_idle and self.robot_mode == RobotMode.POWER_ON:
                await asyncio.sleep(self.options.power_on_s * self.options.time_scale)
            await asyncio.sleep(delay)
            self.robot_mode = then

        task = asyncio.create_task(later())
        self._mode_task = task
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # --- RTDE ----------------------------------------------------------------------------------
    async def _on_rtde(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        session = _RtdeSession(self, writer)
        framer = rtde.RtdeFramer()
        try:
            if session.closed:
                return
            async for data in received(reader):
                framer.feed(data)
                try:
                    for pkg in framer.packages():
                        await session.handle(pkg)
                except FramingError:
                    return  # the stream cannot be resynchronised: drop the client
                if session.closed:
                    return
        finally:
            await session.stop()
            for name in [n for n, s in self._input_owners.items() if s is session]:
                del self._input_owners[name]

    # --- primary / secondary -------------------------------------------------------------------
    def _state_message(self) -> bytes:
        world = self.world
        running = self.runtime_state == RuntimeState.PLAYING
        mode = prim.RobotModeData(
            int((time.monotonic() - self._t0) * 1e6), True, True,
            self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING),
            self.safety_mode in (SafetyMode.SYSTEM_EMERGENCY_STOP,
                                 SafetyMode.ROBOT_EMERGENCY_STOP),
            self.safety_mode == SafetyMode.PROTECTIVE_STOP, running,
            self.program_state == "PAUSED", self.robot_mode, 0, 1.0, self.speed_slider, 1.0)
        q = self._q6(world.q_actual_rad)
        joints = prim.JointData(tuple(q), tuple(self._q6(world.q_cmd_rad)), (0.0,) * 6,
                                (253,) * 6)
        return prim.encode_robot_state(prim.RobotState(mode, joints, self.kinematics()))

    async def _on_primary(self, reader: asyncio.StreamReader,
                          writer: asyncio.StreamWriter) -> None:
        v = self.options.controller_version
        writer.write(prim.encode_version(
            prim.VersionMessage("URControl", v[0], v[1], v[2], v[3], "12-01-2023, 10:18:46")))
        writer.write(self._state_message())
        await writer.drain()
        self._state_writers.add(writer)
        try:
            await self._read_programs(reader)
        finally:
            self._state_writers.discard(writer)

    async def _on_realtime(self, reader: asyncio.StreamReader,
                           writer: asyncio.StreamWriter) -> None:
        # URScript in, as on 30001/30002 (ur-rtde's ScriptClient sends its control program
        # here); the realtime state stream a controller also sends on 30003 is not simulated
        await self._read_programs(reader)

    async def _read_programs(self, reader: asyncio.StreamReader) -> None:
        buffer = ""
        async for data in received(reader):
            buffer += data.decode("utf-8", errors="replace").replace("\r", "")
            programs, buffer = prim.split_programs(buffer)
            for program in programs:
                await self._run_script(program)
            if len(buffer) > 1 << 20:
                buffer = ""

    async def _broadcast_state(self) -> None:
        period = 1.0 / self.options.state_hz
        while True:
            await asyncio.sleep(period)
            if not self._state_writers:
                continue
            msg = self._state_message()
            for w in list(self._state_writers):
                try:
                    w.write(msg)
                except (ConnectionError, RuntimeError):
                    self._state_writers.discard(w)

    def _runtime_exception(self, text: str, line: int = 0) -> None:
        self.runtime_errors.append(text)
        _log.info("ur sim: runtime exception", text=text)
        msg = prim.encode_runtime_exception(
            prim.RuntimeException(line, 0, text), int((time.monotonic() - self._t0) * 1e6))
        for w in list(self._state_writers):
            with contextlib.suppress(ConnectionError, RuntimeError):
                w.write(msg)

    async def _run_script(self, program: str) -> None:
        self.scripts.append(program)
        offsets = _RtdeControl.offsets(program)
        if offsets is not None:
            # ur-rtde's control program: run as an emulation of its command loop
            if not set(offsets) <= {0, 24}:
                self._runtime_exception(f"rtde_control: register offsets {offsets} are "
                                        "neither 0 (lower range) nor 24 (upper range)")
                return
            if await self._may_start("rtde_control"):
                control = _RtdeControl(self, *offsets)
                self._program = asyncio.create_task(control.run())
            return
        try:
            name, statements = prim.parse_script(program)
        except prim.ScriptError as err:
            self._runtime_exception(f"compile error: {err}")
            return
        secondary = program.lstrip().startswith("sec ")
        if secondary:
            if any(s.kind == "call" and s.name in ("movej", "stopj") for s in statements):
                self._runtime_exception("secondary programs may not move the robot")
                return
            await self._execute(statements, name)
            return
        if await self._may_start(name or "<line>"):
            self._program = asyncio.create_task(self._execute(statements, name))

    async def _may_start(self, name: str) -> bool:
        """End the running program; whether a new one may start (else a runtime exception)."""
        await self._end_program()
        if self.robot_mode != RobotMode.RUNNING or self.safety_mode != SafetyMode.NORMAL:
            self._runtime_exception(
                f"program {name} not started: robot mode "
                f"{RobotMode.NAMES.get(self.robot_mode)}, safety "
                f"{SafetyMode.NAMES.get(self.safety_mode)}")
            return False
        self.program_state = "STOPPED"
        self.script_runs += 1
        return True

    async def _end_program(self) -> None:
        task, self._program = self._program, None
        await _cancel_and_halt(task, self.world)

    async def _execute(self, statements: Sequence[prim.Statement], name: str) -> None:
        local: dict[str, Any] = {}
        try:
            for n, s in enumerate(statements, start=1):
                await self._statement(s, local, n)
        except _RuntimeError as err:
            self._runtime_exception(f"{name or 'script'}: {err}", err.line)
        except _ProgramHalted:
            pass

    def _value(self, v: Any, local: dict[str, Any], line: int) -> Any:
        if isinstance(v, tuple) and len(v) == 2 and v[0] == "ref":
            ref: str = v[1]
            base, _, idx = ref.partition("[")
            if base in local:
                value = local[base]
            elif base in self.variables:
                value = self.variables[base]
            else:
                raise _RuntimeError(f"variable {base} is not defined", line)
            if idx:
                try:
                    return value[int(idx.rstrip("]"))]
                except (IndexError, TypeError):
                    raise _RuntimeError(f"index out of range: {ref}", line) from None
            return value
        return v

    async def _statement(self, s: prim.Statement, local: dict[str, Any], line: int) -> None:
        args = [self._value(a, local, line) for a in s.args]
        kw = {k: self._value(v, local, line) for k, v in s.kwargs.items()}
        if s.kind == "assign":
            value = args[0]
            if s.name.startswith(self.options.installation_prefix):
                self.variables[s.name] = value
            else:
                local[s.name] = value
            return
        f = s.name
        try:
            if f == "movej":
                await self._movej(args[0], float(kw.get("a", 1.4)), float(kw.get("v", 1.05)),
                                  line)
            elif f == "stopj":
                self.world.halt()
            elif f == "write_output_integer_register":
                self.int_out[int(args[0])] = int(args[1])
            elif f == "write_output_float_register":
                self.double_out[int(args[0])] = float(args[1])
            elif f == "write_output_boolean_register":
                self.bool_out[int(args[0])] = bool(args[1])
            elif f == "set_standard_digital_out":
                bit = 1 << int(args[0])
                self.digital_out = (self.digital_out | bit) if args[1] else \
                    (self.digital_out & ~bit)
            elif f == "sleep":
                await asyncio.sleep(float(args[0]) * self.options.time_scale)
            elif f in ("sync", "textmsg"):
                await asyncio.sleep(0)
            else:
                raise _RuntimeError(f"unknown function {f}", line)
        except (IndexError, TypeError, ValueError) as err:
            raise _RuntimeError(f"{f}: bad arguments ({err})", line) from err

    async def _movej(self, q: Any, a: float, v: float, line: int) -> None:
        world = self.world
        target = [float(x) for x in q]
        if len(target) != 6 or not world.within_limits(target[:world.dof]):
            raise _RuntimeError(f"movej target {target} outside the joint limits", line)
        if self.faults.fire("alarm"):
            # A protective stop ends the program without a runtime exception; clients see it
            # in the safety mode (RTDE, robot mode data) and the dashboard's safetystatus.
            world.halt()
            self.safety_mode = SafetyMode.PROTECTIVE_STOP
            raise _ProgramHalted
        v = max(1e-6, min(v, self.options.max_joint_speed_rad_s) * self.speed_slider)
        dist = max(abs(t - c) for t, c in zip(target[:world.dof], world.q_cmd_rad, strict=True))
        ramp = v / max(a, 1e-6)
        duration = max(dist / v + ramp, self.options.min_motion_s) * self.options.time_scale
        if duration <= 0.0:
            world.move(target[:world.dof])
            await asyncio.sleep(0)
            return
        motion = world.start_motion(target[:world.dof], duration)
        await asyncio.sleep(duration)
        world.finish_motion(motion)


# RTDE TCP pose outputs and the joint outputs (same snapshot) they are computed from
_TCP_POSE_OF = {"actual_TCP_pose": "actual_q", "target_TCP_pose": "target_q"}

_REMOTE_ONLY = frozenset({"power on", "power off", "brake release", "load", "play",
                          "unlock protective stop", "restart safety"})
_FIXED_REPLIES = {
    "close popup": "closing popup",
    "close safety popup": "closing safety popup",
    "popup": "showing popup",
    "addtolog": "Added log message",
    "shutdown": "Shutting down",
}


def _safety_name(sim: UrSimulator) -> str:
    return SafetyMode.NAMES.get(sim.safety_mode, "FAULT")


def _version_text(sim: UrSimulator) -> str:
    v = sim.options.controller_version
    return f"URSoftware {v[0]}.{v[1]}.{v[2]}.{v[3]} (Jan 12 2023)"


#: Dashboard commands answered from the state, without changing it.
_QUERIES: dict[str, Callable[[UrSimulator, str], str]] = {
    "robotmode": lambda sim, _: f"Robotmode: {RobotMode.NAMES.get(sim.robot_mode, 'UNKNOWN')}",
    "safetystatus": lambda sim, _: f"Safetystatus: {_safety_name(sim)}",
    "safetymode": lambda sim, _: f"Safetymode: {_safety_name(sim)}",
    "is in remote control": lambda sim, _: "true" if sim.remote_control else "false",
    "get loaded program": lambda sim, _: (
        f"Loaded program: {sim.loaded_program}" if sim.loaded_program else "No program loaded"
    ),
    "programstate": lambda sim, _: f"{sim.program_state} {sim._program_name()}",
    "running": lambda sim, _: "Program running: "
    + ("true" if sim.runtime_state == RuntimeState.PLAYING else "false"),
    "polyscopeversion": lambda sim, _: _version_text(sim),
    "get robot model": lambda sim, _: sim.options.robot_model[:4],
    "get serial number": lambda sim, _: sim.options.serial_number,
    "isprogramsaved": lambda sim, _: f"true {sim._program_name()}",
    "setuserrole": lambda _, arg: f"Setting user role: {arg}",
}
#: Dashboard commands that change the controller's state.
_ACTIONS: dict[str, Callable[[UrSimulator, str], Awaitable[str]]] = {
    "power on": UrSimulator._dash_power_on,
    "power off": UrSimulator._dash_power_off,
    "brake release": UrSimulator._dash_brake_release,
    "load": UrSimulator._dash_load,
    "play": UrSimulator._dash_play,
    "stop": UrSimulator._dash_stop,
    "pause": UrSimulator._dash_pause,
    "unlock protective stop": UrSimulator._dash_unlock,
    "restart safety": UrSimulator._dash_restart_safety,
}


class _ProgramHalted(Exception):
    """The program was ended by the controller (protective stop), without an exception."""


class _RuntimeError(Exception):
    def __init__(self, message: str, line: int) -> None:
        super().__init__(message)
        self.line = line


def _zero(t: str) -> Any:
    if t.startswith("VECTOR"):
        return [0.0 if t.endswith("D") else 0] * (3 if t == "VECTOR3D" else 6)
    if t == "DOUBLE":
        return 0.0
    if t == "BOOL":
        return False
    return 0


class _RtdeControl:
    """ur-rtde's control program (``def rtde_control():``), emulated.

    RTDEControlInterface (ur-rtde 1.6) uploads a URScript program of about 1,200 lines
    (threads, loops), beyond the subset this simulator interprets, and drives it through
    RTDE registers; this runs its command loop with the program's register protocol. With
    the program's register offsets ``oi`` (integers) and ``of`` (doubles), 0 or 24:

    * ``output_int_register_<oi>``: 1 ready for a command, 2 done with it; the client then
      clears the command (``input_int_register_<oi>`` = 0) and the program signals ready;
    * commands in ``input_int_register_<oi>``: 1 ``moveJ`` (joints in the double registers
      ``of``..``of + 5``, speed ``of + 6``, acceleration ``of + 7``, asynchronous when
      ``input_int_register_<oi + 1>`` is 1), 33 ``stopL`` and 34 ``stopJ`` (halt; also
      asynchronous), 17 ``setPayload``, 29 ``setTcp``, 31 ``triggerProtectiveStop`` (ends
      the program), 37 ``isJointsWithinSafetyLimits`` and 47 ``isSteady`` (answer in
      ``output_int_register_<oi + 1>``), 43/44 ``getForwardKinematics`` (pose in the double
      output registers ``of``..``of + 5``, from :meth:`UrSimulator.tcp_pose`), 255 end the
      program;
    * ``output_int_register_<oi + 2>``: asynchronous progress. Bits 24-30 count the
      operations started and bits 16-23 the writes (both modulo 128); while an operation
      runs, bit 15 is set and bits 0-14 hold its progress (0 here).

    Any other command is a runtime exception naming it: the program ends, as a real one
    does on an error, and ur-rtde's call returns false.
    """

    PERIOD_S = 0.002        # one controller cycle (sync()) of an e-Series controller
    STOP_SCRIPT = 255

    def __init__(self, sim: UrSimulator, oi: int, of: int) -> None:
        self.sim, self.oi, self.of = sim, oi, of
        self.writes = 0
        self.operations = 0
        self.move: asyncio.Task[None] | None = None

    @staticmethod
    def offsets(program: str) -> tuple[int, int] | None:
        """The integer and double register offsets of ur-rtde's control program, or None
        when ``program`` is not that program. ur-rtde writes each offset on the line after
        its marker comment (``global reg_offset_int = # int register offset``)."""
        if not re.match(r"\s*def\s+rtde_control\s*\(\s*\)\s*:", program):
            return None
        found = []
        for kind in ("int", "float"):
            m = re.search(rf"#\s*{kind} register offset\s*\n\s*(\d+)", program)
            found.append(int(m.group(1)) if m else 0)
        return found[0], found[1]

    def _signal(self, value: int) -> None:
        self.sim.int_out[self.oi] = value

    def _progress(self, value: int) -> None:
        """Write the asynchronous progress register: ``value`` >= 0 running, < 0 finished."""
        self.writes = (self.writes + 1) % 128
        if value == 0:
            self.operations = (self.operations + 1) % 128
        reg = self.writes * 65536 + self.operations * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.sim.int_out[self.oi + 2] = reg

    async def run(self) -> None:
        """The command loop, until command 255 or a runtime exception."""
        sim = self.sim
        self._progress(-1)
        self._signal(1)
        executing = False
        try:
            while True:
                cmd = sim.int_in[self.oi]
                if cmd == 0:
                    executing = False
                    self._signal(1)
                elif not executing:
                    executing = True
                    if cmd == self.STOP_SCRIPT:
                        return
                    await self._command(cmd)
                    self._signal(2)
                await asyncio.sleep(self.PERIOD_S)
        except _RuntimeError as err:
            sim._runtime_exception(f"rtde_control: {err}", err.line)
        except _ProgramHalted:
            pass
        finally:
            await self._stop_move()

    async def _command(self, cmd: int) -> None:
        sim, of = self.sim, self.of
        asynchronous = sim.int_in[self.oi + 1] == 1
        if cmd == 1:
            q = sim.double_in[of:of + 6]
            v, a = sim.double_in[of + 6], sim.double_in[of + 7]
            await self._stop_move()
            if asynchronous:
                self._progress(0)
                self.move = asyncio.create_task(self._async_move(q, a, v))
            else:
                await sim._movej(q, a, v, 0)
        elif cmd in (33, 34):
            await self._stop_move()
            sim.world.halt()          # the simulated robot stops at once
            if asynchronous:
                self._progress(0)
                self._progress(-1)
        elif cmd == 17:               # setPayload: a zero CoG keeps the current one
            cog = sim.double_in[of + 1:of + 4]
            sim.payload = (sim.double_in[of], cog if any(cog) else sim.payload[1])
        elif cmd == 29:               # setTcp
            sim.tcp = sim.double_in[of:of + 6]
        elif cmd == 31:               # triggerProtectiveStop
            await self._stop_move()
            sim.world.halt()
            sim.safety_mode = SafetyMode.PROTECTIVE_STOP
            raise _ProgramHalted
        elif cmd == 37:               # isJointsWithinSafetyLimits
            q = sim.double_in[of:of + sim.world.dof]
            sim.int_out[self.oi + 1] = int(bool(sim.world.within_limits(q)))
        elif cmd in (43, 44):         # getForwardKinematics(), (q, tcp_offset)
            if cmd == 43:
                pose = sim.tcp_pose(sim._q6(sim.world.q_actual_rad))
            else:
                pose = sim.tcp_pose(sim.double_in[of:of + 6], sim.double_in[of + 6:of + 12])
            sim.double_out[of:of + 6] = pose
        elif cmd == 47:               # isSteady
            sim.int_out[self.oi + 1] = 0 if sim.world.moving else 1
        else:
            raise _RuntimeError(f"command {cmd} is not simulated (see "
                                "docs/protocols/universal-robots.md, section 6)", 0)

    async def _async_move(self, q: list[float], a: float, v: float) -> None:
        try:
            await self.sim._movej(q, a, v, 0)
        except (_RuntimeError, _ProgramHalted) as err:
            if isinstance(err, _RuntimeError):
                self.sim._runtime_exception(f"rtde_control: {err}", err.line)
            program = self.sim._program
            if program is not None:
                program.cancel()       # an error in a thread ends the whole program
        else:
            self.move = None
            self._progress(-1)

    async def _stop_move(self) -> None:
        task, self.move = self.move, None
        if await _cancel_and_halt(task, self.sim.world):
            self._progress(-1)       # a killed move thread cannot signal it


async def _cancel_and_halt(task: asyncio.Task[None] | None, world: SimWorld) -> bool:
    """Cancel ``task`` if it still runs and stop the robot where it is; whether it ran."""
    if task is None or task.done():
        return False
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    world.halt()
    return True
