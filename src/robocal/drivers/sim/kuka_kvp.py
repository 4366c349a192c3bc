"""A KUKA KRC4/KRC5 simulator: KUKAVARPROXY on TCP and the KRL loop robocal deploys.

The proxy side answers KVP reads and writes (:mod:`robocal.protocols.kuka_kvp`) of the
global variables of ``deploy/kuka/robocal_loop.dat`` and of a few system variables
(``$AXIS_ACT``, ``$POS_ACT``, ``$ROBNAME[]``, ``$PRO_STATE1``, ``$MODE_OP``, ``$OV_PRO``,
``$SOFTN_END[i]``, ``$SOFTP_END[i]``) and of what the controller applies of its own
calibration (``$ABS_ACCUR``, ``$MAMES[i]`` and kinematic machine data, in
:attr:`KukaKvpSimulator.calibration_vars`, which tests change). REAL values are kept as
32-bit floats, as KRL keeps them. The robot side reproduces
``deploy/kuka/robocal_loop.src``: when ``RC_CMD_SEQ`` differs from ``RC_ACK_SEQ`` it checks
``RC_SPEED`` and the software limits, moves to ``RC_TARGET`` (simulated time), sets
``RC_STATUS`` and copies the sequence number to ``RC_ACK_SEQ``; ``RC_STOP=TRUE`` runs the
stop interrupt at once (halt where the robot is, ``RC_STATUS`` 4, acknowledge every command
written so far, ``RC_STOP=FALSE``). Protocol and loop: docs/protocols/kuka-kvp.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import struct
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from robocal.compensation import nominal_fk
from robocal.drivers.sim._server import WorldSimulator, port_of
from robocal.drivers.sim.faults import FaultConfig
from robocal.drivers.sim.world import SimWorld
from robocal.errors import FramingError, ProtocolError
from robocal.kinematics import matrix_to_wpr
from robocal.protocols import kuka_kvp as kvp

__all__ = ["KukaKvpSimulator", "KukaSimOptions"]

_log = structlog.get_logger(__name__)

VarType = Literal["INT", "REAL", "BOOL", "E6AXIS", "CHAR"]

#: RC_STATUS values of robocal_loop.src.
IDLE, MOVING, DONE, ERROR, STOPPED = 0, 1, 2, 3, 4
#: RC_ERROR values with RC_STATUS 3.
ERR_LIMIT, ERR_MOTION, ERR_SPEED = 1, 2, 3


class KukaSimOptions(BaseModel):
    """Behaviour of the simulated controller.

    ``time_scale`` multiplies simulated motion times (0 = instantaneous, 1 = real time).
    ``program_running`` False leaves robocal_loop unselected: ``$PRO_STATE1`` reads
    ``#P_STOP`` and nothing serves the handshake. ``comp_size`` is the length of ``RC_COMP``;
    ``robot_name`` what ``$ROBNAME[]`` reads. ``joint_limits_deg`` overrides the world's
    limits as the software limits ``$SOFTN_END``/``$SOFTP_END``. ``abs_accur`` is what
    ``$ABS_ACCUR`` reads (KSS 8: the positionally accurate robot model is ``#ACTIVATED``,
    ``#SUPPRESSED`` or there is ``#NONE``), ``mames_deg`` the mastering offsets ``$MAMES[i]``
    and ``machine_data`` further read-only machine data (KRL text by name).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    time_scale: float = Field(default=0.001, ge=0.0)
    max_joint_speed_deg_s: float = Field(default=180.0, gt=0.0)
    min_motion_s: float = Field(default=0.012, ge=0.0)
    program_running: bool = True
    comp_size: int = Field(default=100, ge=1, le=10000)
    robot_name: str = "KR6 R900-2"
    joint_limits_deg: tuple[tuple[float, float], ...] | None = None
    abs_accur: Literal["#ACTIVATED", "#SUPPRESSED", "#NONE"] = "#NONE"
    mames_deg: tuple[float, ...] = (0.0, -90.0, 90.0, 0.0, 0.0, 0.0)
    machine_data: dict[str, str] = Field(default_factory=lambda: {
        "$LENGTH_A": "25.0", "$LENGTH_B": "35.0",
        "$TIRORO": "{FRAME: X 0.0, Y 0.0, Z 400.0, A 0.0, B 0.0, C 0.0}",
        "$TFLWP": "{FRAME: X 0.0, Y 0.0, Z 80.0, A 0.0, B 0.0, C 0.0}",
        "$TX3P3": "{FRAME: X 420.0, Y 0.0, Z 35.0, A 0.0, B 0.0, C 0.0}"})


@dataclass
class _Var:
    """A KRL variable: its type, value (an array of values when ``size``) and CHAR length."""

    type: VarType
    value: Any
    size: int = 0
    chars: int = 0


def _f32(x: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", x))[0])


def _e6axis(values: Any) -> list[float]:
    out = [_f32(float(v)) for v in values][:12]
    return out + [0.0] * (12 - len(out))


_ACCESS = re.compile(r"([$A-Za-z_][A-Za-z0-9_$]*)(?:\[(\d*)\])?")


@dataclass
class _Loop:
    """State of the simulated robocal_loop program."""

    wake: asyncio.Event = field(default_factory=asyncio.Event)
    stopped: asyncio.Event = field(default_factory=asyncio.Event)


class KukaKvpSimulator(WorldSimulator):
    """Simulated KRC with KUKAVARPROXY and robocal_loop, serving on loopback.

    Parameters
    ----------
    world : SimWorld
        The robot being moved.
    options : KukaSimOptions, optional
        Controller behaviour.
    faults : FaultConfig, optional
        Injected faults: slow replies (``slow_rate``), dropped connections (``drop_rate``),
        motion faults (``alarm_rate``: RC_STATUS 3, RC_ERROR 2).

    Attributes
    ----------
    requests : list of kvp.Request
        Every request received (tests assert on it).
    port : int
        The bound KVP port (after :meth:`start`).
    """

    def __init__(self, world: SimWorld, options: KukaSimOptions | None = None,
                 faults: FaultConfig | None = None) -> None:
        super().__init__(world, faults)
        self.options = options or KukaSimOptions()
        self.requests: list[kvp.Request] = []
        self.port = 0
        self.clients = 0
        lim = self.options.joint_limits_deg or world.joint_limits_deg
        self.joint_limits_deg = tuple(lim)
        self.override = 100
        size = self.options.comp_size
        self.vars: dict[str, _Var] = {
            "RC_TARGET": _Var("E6AXIS", _e6axis([])),
            "RC_SPEED": _Var("INT", 10),
            "RC_CMD_SEQ": _Var("INT", 0),
            "RC_ACK_SEQ": _Var("INT", 0),
            "RC_RUN_SEQ": _Var("INT", 0),
            "RC_STATUS": _Var("INT", IDLE),
            "RC_ERROR": _Var("INT", 0),
            "RC_STOP": _Var("BOOL", False),
            "RC_COMP": _Var("E6AXIS", [_e6axis([]) for _ in range(size)], size=size),
            "RC_COMP_N": _Var("INT", 0),
            "RC_COMP_ID": _Var("CHAR", "", chars=64),
        }
        self._loop = _Loop()
        self.moves = 0
        self.stops = 0
        o = self.options
        #: read-only calibration variables by access text (``$MAMES[2]``) -> KRL text
        self.calibration_vars: dict[str, str] = {"$ABS_ACCUR": o.abs_accur, **{
            f"$MAMES[{i}]": kvp.format_real(_f32(v), 4) for i, v in enumerate(o.mames_deg, 1)},
            **o.machine_data}

    # --- lifecycle -----------------------------------------------------------------------------
    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen (0 picks a free port) and start the KRL loop; return the port."""
        self._loop = _Loop()
        self.port = port_of(await self._listen(self._on_client, host, port))
        if self.options.program_running:
            self._track(self._krl_loop())
        _log.info("kvp sim listening", port=self.port)
        return self.port

    async def stop(self) -> None:
        """Close the listener, the clients and the KRL loop; idempotent."""
        self._close_listeners()
        await self._stop_serving()

    # --- variables -----------------------------------------------------------------------------
    def _int(self, name: str) -> int:
        return int(self.vars[name].value)

    def _set(self, name: str, value: Any) -> None:
        self.vars[name].value = value

    def _system(self, name: str, index: str | None) -> str | None:
        """Text of a read-only system variable, or None when ``name`` is none of them."""
        dof = self.world.dof
        access = name if index is None else f"{name}[{index}]"
        if access in self.calibration_vars:
            return self.calibration_vars[access]
        if name == "$AXIS_ACT" and index is None:
            return kvp.format_e6axis(_e6axis(np.degrees(self.world.q_actual_rad)), 4)
        if name == "$POS_ACT" and index is None:
            T = nominal_fk(self.world.cell.robot, self.world.q_actual_rad)[0]
            c, b, a = (math.degrees(v) for v in matrix_to_wpr(T[:3, :3]))
            x, y, z = (1000.0 * float(v) for v in T[:3, 3])
            parts = zip("XYZABC", (x, y, z, a, b, c), strict=True)
            text = ", ".join(f"{k} {kvp.format_real(_f32(v), 4)}" for k, v in parts)
            externals = ", ".join(f"E{i} 0.0" for i in range(1, 7))
            return "{E6POS: " + text + ", S 2, T 35, " + externals + "}"
        if name == "$ROBNAME" and index == "":
            return kvp.format_string(self.options.robot_name)
        if name == "$PRO_STATE1" and index is None:
            return "#P_ACTIVE" if self.options.program_running else "#P_STOP"
        if name == "$MODE_OP" and index is None:
            return "#AUT"
        if name in ("$SOFTN_END", "$SOFTP_END") and index:
            i = int(index)
            if not 1 <= i <= dof:
                return None
            lo, hi = self.joint_limits_deg[i - 1]
            return kvp.format_real(_f32(lo if name == "$SOFTN_END" else hi), 4)
        return None

    def _format(self, var: _Var, value: Any) -> str:
        if var.type == "INT":
            return kvp.format_int(int(value))
        if var.type == "BOOL":
            return kvp.format_bool(bool(value))
        if var.type == "REAL":
            return kvp.format_real(float(value))
        if var.type == "CHAR":
            return kvp.format_string(str(value))
        return kvp.format_e6axis(value)

    def read(self, access: str) -> tuple[str, bool]:
        """KRL text of variable ``access`` and whether it exists."""
        m = _ACCESS.fullmatch(access.strip())
        if m is None:
            return "", False
        name, index = m.group(1).upper(), m.group(2)
        if name == "$OV_PRO" and index is None:
            return kvp.format_int(self.override), True
        system = self._system(name, index)
        if system is not None:
            return system, True
        var = self.vars.get(name)
        if var is None:
            return "", False
        if var.size:
            if not index or not 1 <= int(index) <= var.size:
                return "", False
            return self._format(var, var.value[int(index) - 1]), True
        if index is not None and not (var.type == "CHAR" and index == ""):
            return "", False
        return self._format(var, var.value), True

    def _parse(self, var: _Var, text: str, old: Any) -> Any:
        """The new value of ``var`` from KRL ``text``; raises ProtocolError when it does not fit."""
        if var.type == "INT":
            value = kvp.parse_int(text)
            if not -(2**31) <= value < 2**31:
                raise FramingError("INT overflow")
            return value
        if var.type == "BOOL":
            return kvp.parse_bool(text)
        if var.type == "REAL":
            return _f32(kvp.parse_real(text))
        if var.type == "CHAR":
            s = kvp.parse_string(text)
            if len(s) > var.chars:
                raise FramingError(f"string longer than {var.chars} characters")
            return s
        kind, fields = kvp.parse_struct(text)
        if kind not in (None, "E6AXIS", "AXIS") or set(fields) - set(kvp.AXIS_NAMES):
            raise FramingError(f"not an E6AXIS aggregate: {text[:40]!r}")
        # KRL assigns the components given and keeps the others.
        new = list(old)
        for i, name in enumerate(kvp.AXIS_NAMES):
            if name in fields:
                new[i] = _f32(kvp.parse_real(fields[name]))
        return new

    def write(self, access: str, text: str) -> tuple[str, bool]:
        """Assign KRL ``text`` to variable ``access``; return its value text and success."""
        m = _ACCESS.fullmatch(access.strip())
        if m is None:
            return "", False
        name, index = m.group(1).upper(), m.group(2)
        if name == "$OV_PRO" and index is None:
            try:
                value = kvp.parse_int(text)
            except ProtocolError:
                return self.read(access)[0], False
            if not 0 <= value <= 100:
                return self.read(access)[0], False
            self.override = value
            return self.read(access)[0], True
        var = self.vars.get(name)
        if var is None:
            return self.read(access)[0], False  # system variables are read-only here
        if var.size:
            if not index or not 1 <= int(index) <= var.size:
                return "", False
            i = int(index) - 1
            try:
                var.value[i] = self._parse(var, text, var.value[i])
            except ProtocolError:
                return self.read(access)[0], False
        else:
            if index is not None and not (var.type == "CHAR" and index == ""):
                return "", False
            try:
                var.value = self._parse(var, text, var.value)
            except ProtocolError:
                return self.read(access)[0], False
            self._written(name)
        return self.read(access)[0], True

    def _written(self, name: str) -> None:
        """What robocal_loop does when a handshake variable changes."""
        if name == "RC_CMD_SEQ":
            self._loop.wake.set()
        elif name == "RC_STOP" and self.vars["RC_STOP"].value and self.options.program_running:
            # The interrupt fires within an interpolation cycle, after this write's reply.
            asyncio.get_running_loop().call_soon(self._on_stop)

    def _on_stop(self) -> None:
        """Interrupt RC_ON_STOP: BRAKE, report, acknowledge, clear the request, RESUME."""
        if not self.vars["RC_STOP"].value:
            return
        self.world.halt()
        self.stops += 1
        self._loop.stopped.set()
        self._set("RC_STATUS", STOPPED)
        self._set("RC_ACK_SEQ", self._int("RC_CMD_SEQ"))
        self._set("RC_STOP", False)
        _log.info("kvp sim: stop interrupt",
                  q_deg=[round(math.degrees(v), 4) for v in self.world.q_actual_rad])

    # --- the KRL loop --------------------------------------------------------------------------
    async def _krl_loop(self) -> None:
        """LOOP: WAIT FOR RC_CMD_SEQ<>RC_ACK_SEQ; RC_RUN_SEQ=RC_CMD_SEQ; RC_MOVE();
        unless stopped (the interrupt acknowledged), RC_ACK_SEQ=RC_RUN_SEQ."""
        self._set("RC_ACK_SEQ", self._int("RC_CMD_SEQ"))
        self._set("RC_RUN_SEQ", self._int("RC_CMD_SEQ"))
        loop = self._loop
        while True:
            await loop.wake.wait()
            loop.wake.clear()
            while self._int("RC_CMD_SEQ") != self._int("RC_ACK_SEQ"):
                loop.stopped.clear()
                self._set("RC_RUN_SEQ", self._int("RC_CMD_SEQ"))
                await self._rc_move(loop)
                if self._int("RC_STATUS") != STOPPED:
                    self._set("RC_ACK_SEQ", self._int("RC_RUN_SEQ"))

    async def _rc_move(self, loop: _Loop) -> None:
        speed = self._int("RC_SPEED")
        if not 1 <= speed <= 100:
            self._set("RC_ERROR", ERR_SPEED)
            self._set("RC_STATUS", ERROR)
            return
        dof = self.world.dof
        q_deg = list(self.vars["RC_TARGET"].value[:dof])
        for v, (lo, hi) in zip(q_deg, self.joint_limits_deg, strict=True):
            if not lo <= v <= hi:
                self._set("RC_ERROR", ERR_LIMIT)
                self._set("RC_STATUS", ERROR)
                return
        if self.faults.fire("alarm"):
            self._set("RC_ERROR", ERR_MOTION)
            self._set("RC_STATUS", ERROR)
            return
        self._set("RC_ERROR", 0)
        self._set("RC_STATUS", MOVING)
        current = np.degrees(self.world.q_cmd_rad)
        dist = float(np.max(np.abs(np.asarray(q_deg) - current)))
        rate = self.options.max_joint_speed_deg_s * speed / 100.0 * self.override / 100.0
        duration = max(dist / max(rate, 1e-9), self.options.min_motion_s) * self.options.time_scale
        target = np.radians(q_deg)
        self.moves += 1
        if duration <= 0:
            self.world.move(target)
        else:
            motion = self.world.start_motion(target, duration)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(duration):
                    await loop.stopped.wait()
            if loop.stopped.is_set() or not self.world.finish_motion(motion):
                return  # the stop interrupt has reported (RESUME)
        self._set("RC_STATUS", DONE)

    # --- KVP clients ---------------------------------------------------------------------------
    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.clients += 1
        framer = kvp.KvpFramer()
        while True:
            data = await reader.read(4096)
            if not data:
                return
            framer.feed(data)
            while True:
                try:
                    msg = framer.next_message()
                except FramingError:
                    return  # a length-prefixed stream cannot be resynchronised
                if msg is None:
                    break
                try:
                    req = kvp.decode_request(msg)
                except FramingError:
                    return
                self.requests.append(req)
                if self.faults.fire("drop"):
                    _log.info("kvp sim: dropping the connection (injected)")
                    return
                if self.faults.fire("slow"):
                    await asyncio.sleep(self.faults.config.slow_s)
                if req.mode == kvp.MODE_READ:
                    value, ok = self.read(req.name)
                else:
                    value, ok = self.write(req.name, req.value or "")
                writer.write(kvp.encode_reply(kvp.Reply(req.msg_id, req.mode, value, ok)))
                await writer.drain()
