"""Sans-I/O codec of the Universal Robots primary/secondary client interface (ports
30001/30002), and the subset of URScript robocal sends over it.

Controller to client, big-endian (``docs/protocols/universal-robots.md``)::

    int32 length (whole message) | uint8 message type | body

Message type 16 (robot state) carries sub-packages ``int32 length | uint8 type | data``;
decoded here: robot mode data (0), joint data (1) and kinematics info (5, the controller's
calibrated DH parameters with one checksum per joint). Message type 20 (robot message) with
robot-message type 3 is the version message sent first after connecting. Unknown message and
sub-package types are skipped by their length, as a client must.

Client to controller: URScript text. A ``def``/``sec`` block is one program; a line outside a
block is a one-line program. :func:`parse_script` reads the statements robocal's driver and
the simulator use (``movej``, ``stopj``, assignments of numbers, lists and strings,
``write_output_*_register``, ``set_standard_digital_out``, ``sleep``, ``sync``, ``textmsg``).
"""

from __future__ import annotations

import ast
import re
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from robocal.errors import FramingError, ProtocolError

__all__ = [
    "PRIMARY_PORT",
    "SECONDARY_PORT",
    "JointData",
    "KinematicsInfo",
    "PrimaryFramer",
    "RobotModeData",
    "RobotState",
    "RuntimeException",
    "ScriptError",
    "Statement",
    "VersionMessage",
    "decode_message",
    "dh_checksum",
    "encode_robot_state",
    "encode_runtime_exception",
    "encode_version",
    "parse_script",
    "script_literal",
    "split_programs",
]

PRIMARY_PORT = 30001
SECONDARY_PORT = 30002
MAX_MESSAGE = 1 << 20

ROBOT_STATE = 16
ROBOT_MESSAGE = 20
VERSION_MESSAGE = 3
RUNTIME_EXCEPTION = 10
SUB_ROBOT_MODE = 0
SUB_JOINT_DATA = 1
SUB_KINEMATICS = 5

_ROBOT_MODE = struct.Struct(">Q7?BBdddB")
_JOINT = struct.Struct(">dddffffB")
_KIN = struct.Struct(">6I6d6d6d6dI")


@dataclass(frozen=True, slots=True)
class RobotModeData:
    """Robot mode sub-package (e-Series layout)."""

    timestamp_us: int
    real_robot_connected: bool
    real_robot_enabled: bool
    power_on: bool
    emergency_stopped: bool
    protective_stopped: bool
    program_running: bool
    program_paused: bool
    robot_mode: int
    control_mode: int
    target_speed_fraction: float
    speed_scaling: float
    target_speed_fraction_limit: float


@dataclass(frozen=True, slots=True)
class JointData:
    """Joint data sub-package: per joint actual and target angle (rad), speed (rad/s), mode."""

    q_actual: tuple[float, ...]
    q_target: tuple[float, ...]
    qd_actual: tuple[float, ...]
    joint_mode: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class KinematicsInfo:
    """Kinematics info sub-package: the DH parameters the controller applies (m, rad), one
    checksum per joint and the calibration status."""

    checksum: tuple[int, ...]
    dh_theta: tuple[float, ...]
    dh_a: tuple[float, ...]
    dh_d: tuple[float, ...]
    dh_alpha: tuple[float, ...]
    calibration_status: int

    def fingerprint(self) -> str:
        """The six checksums as one hex string (what robocal records per campaign)."""
        return "-".join(f"{c:08x}" for c in self.checksum)


@dataclass(frozen=True, slots=True)
class RobotState:
    """A robot state message: the sub-packages robocal decodes (None when absent)."""

    mode: RobotModeData | None = None
    joints: JointData | None = None
    kinematics: KinematicsInfo | None = None


@dataclass(frozen=True, slots=True)
class VersionMessage:
    """The version message: project name and software version."""

    project: str
    major: int
    minor: int
    bugfix: int
    build: int
    build_date: str


@dataclass(frozen=True, slots=True)
class RuntimeException:
    """A runtime-exception robot message: the program stopped at ``line``, ``column``."""

    line: int
    column: int
    text: str


def dh_checksum(theta: float, a: float, d: float, alpha: float) -> int:
    """robocal's simulator checksum of one joint's DH values (CRC-32 of the four doubles).

    The real controller's checksum algorithm is not published; drivers treat the value as
    opaque and only compare it.
    """
    return zlib.crc32(struct.pack(">4d", theta, a, d, alpha))


def _sub(stype: int, data: bytes) -> bytes:
    return struct.pack(">iB", 5 + len(data), stype) + data


def encode_robot_state(state: RobotState) -> bytes:
    """A whole robot state message (type 16) with the sub-packages present in ``state``."""
    body = b""
    if state.mode is not None:
        m = state.mode
        body += _sub(SUB_ROBOT_MODE, _ROBOT_MODE.pack(
            m.timestamp_us, m.real_robot_connected, m.real_robot_enabled, m.power_on,
            m.emergency_stopped, m.protective_stopped, m.program_running, m.program_paused,
            m.robot_mode & 0xFF, m.control_mode, m.target_speed_fraction, m.speed_scaling,
            m.target_speed_fraction_limit, 0))
    if state.joints is not None:
        j = state.joints
        body += _sub(SUB_JOINT_DATA, b"".join(
            _JOINT.pack(q, qt, qd, 0.0, 48.0, 33.0, 0.0, mode)
            for q, qt, qd, mode in zip(j.q_actual, j.q_target, j.qd_actual, j.joint_mode,
                                       strict=True)))
    if state.kinematics is not None:
        k = state.kinematics
        body += _sub(SUB_KINEMATICS, _KIN.pack(*k.checksum, *k.dh_theta, *k.dh_a, *k.dh_d,
                                               *k.dh_alpha, k.calibration_status))
    return struct.pack(">iB", 5 + len(body), ROBOT_STATE) + body


def encode_version(v: VersionMessage, timestamp_us: int = 0) -> bytes:
    """A whole version message (type 20, robot-message type 3, source -2)."""
    name = v.project.encode()[:127]
    body = (struct.pack(">QbBb", timestamp_us, -2, VERSION_MESSAGE, len(name)) + name
            + struct.pack(">BBii", v.major, v.minor, v.bugfix, v.build) + v.build_date.encode())
    return struct.pack(">iB", 5 + len(body), ROBOT_MESSAGE) + body


def encode_runtime_exception(e: RuntimeException, timestamp_us: int = 0) -> bytes:
    """A whole runtime-exception message (type 20, robot-message type 10, source -2)."""
    body = (struct.pack(">QbBii", timestamp_us, -2, RUNTIME_EXCEPTION, e.line, e.column)
            + e.text.encode()[:1000])
    return struct.pack(">iB", 5 + len(body), ROBOT_MESSAGE) + body


def _decode_state(body: bytes) -> RobotState:
    mode = joints = kin = None
    i = 0
    while i + 5 <= len(body):
        (n,) = struct.unpack_from(">i", body, i)
        if n < 5 or i + n > len(body):
            raise ProtocolError(f"robot state sub-package length {n} at {i} is invalid",
                                last_frames=[body[:64]])
        stype, data = body[i + 4], body[i + 5:i + n]
        i += n
        if stype == SUB_ROBOT_MODE and len(data) >= _ROBOT_MODE.size - 1:
            f = _ROBOT_MODE.unpack(data[:_ROBOT_MODE.size].ljust(_ROBOT_MODE.size, b"\0"))
            rm = f[8] if f[8] < 128 else f[8] - 256
            mode = RobotModeData(f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], rm, f[9], f[10],
                                 f[11], f[12])
        elif stype == SUB_JOINT_DATA and len(data) == 6 * _JOINT.size:
            rows = [_JOINT.unpack_from(data, k * _JOINT.size) for k in range(6)]
            joints = JointData(tuple(r[0] for r in rows), tuple(r[1] for r in rows),
                               tuple(r[2] for r in rows), tuple(r[7] for r in rows))
        elif stype == SUB_KINEMATICS and len(data) >= _KIN.size:
            f = _KIN.unpack_from(data)
            kin = KinematicsInfo(tuple(f[0:6]), tuple(f[6:12]), tuple(f[12:18]),
                                 tuple(f[18:24]), tuple(f[24:30]), f[30])
    return RobotState(mode, joints, kin)


def _decode_robot_message(body: bytes) -> VersionMessage | RuntimeException | None:
    if len(body) >= 18 and body[9] == RUNTIME_EXCEPTION:
        line, column = struct.unpack_from(">ii", body, 10)
        return RuntimeException(line, column, body[18:].decode("utf-8", errors="replace"))
    if len(body) < 11 or body[9] != VERSION_MESSAGE:
        return None
    n = body[10]
    try:
        project = body[11:11 + n].decode("utf-8", errors="replace")
        major, minor, bugfix, build = struct.unpack_from(">BBii", body, 11 + n)
    except struct.error as err:
        raise ProtocolError("truncated version message", last_frames=[body]) from err
    date = body[11 + n + 10:].decode("utf-8", errors="replace")
    return VersionMessage(project, major, minor, bugfix, build, date)


def decode_message(mtype: int, body: bytes
                   ) -> RobotState | VersionMessage | RuntimeException | None:
    """Decode one message body; None for message types robocal does not read."""
    if mtype == ROBOT_STATE:
        return _decode_state(body)
    if mtype == ROBOT_MESSAGE:
        return _decode_robot_message(body)
    return None


class PrimaryFramer:
    """Split the controller's byte stream into ``(message type, body)`` pairs."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        """Append received bytes."""
        self._buf += data

    def messages(self) -> Iterator[tuple[int, bytes]]:
        """Yield every complete message buffered so far."""
        while len(self._buf) >= 5:
            (n,) = struct.unpack_from(">i", self._buf)
            if n < 5 or n > MAX_MESSAGE:
                head = bytes(self._buf[:16])
                self._buf.clear()
                raise FramingError(f"primary interface message length {n} is invalid",
                                   last_frames=[head])
            if len(self._buf) < n:
                return
            mtype, body = self._buf[4], bytes(self._buf[5:n])
            del self._buf[:n]
            yield mtype, body


# --- URScript subset -------------------------------------------------------------------------
class ScriptError(ProtocolError):
    """A URScript program robocal's subset cannot read (the controller's compile error)."""


@dataclass(frozen=True, slots=True)
class Statement:
    """One statement: a call ``name(args, key=value)`` or an assignment ``target = value``."""

    kind: str  # "call" or "assign"
    name: str
    args: tuple[Any, ...] = ()
    kwargs: dict[str, Any] = field(default_factory=dict)


_BLOCK_START = re.compile(r"^\s*(def|sec)\s+([A-Za-z_]\w*)\s*\(\s*\)\s*:\s*$")
# a line opening a nested block (closed by its own ``end``); ``elif``/``else`` continue one
_INNER_BLOCK = re.compile(r"^(def|thread|sec)\s+\w+\s*\(.*\)\s*:$|^(if|while|for)\b.*:$")
_ASSIGN = re.compile(r"^\s*(?:global\s+|local\s+)?([A-Za-z_]\w*)\s*=(?!=)\s*(.+)$")
_CALL = re.compile(r"^\s*([A-Za-z_]\w*)\s*\((.*)\)\s*$")
_POSE = re.compile(r"\bp\[")


def split_programs(buffer: str) -> tuple[list[str], str]:
    """Split received text into complete programs and the incomplete rest.

    A ``def``/``sec`` header starts a program that ends at its matching ``end`` line:
    blocks inside it (``def``, ``thread``, ``if``, ``while``, ``for``) each end with an ``end``
    of their own, as in ur-rtde's control program. Any other non-empty line is a program of
    its own.
    """
    programs: list[str] = []
    lines = buffer.split("\n")
    rest_start = len(lines) - 1  # the text after the last LF is incomplete
    i = 0
    while i < rest_start:
        line = lines[i]
        if not line.strip() or line.strip().startswith("#"):
            i += 1
            continue
        if _BLOCK_START.match(line):
            depth, j = 1, i + 1
            while j < rest_start:
                code = lines[j].split("#", 1)[0].strip()
                if code == "end":
                    depth -= 1
                    if depth == 0:
                        break
                elif _INNER_BLOCK.match(code):
                    depth += 1
                j += 1
            if j >= rest_start:
                return programs, "\n".join(lines[i:])
            programs.append("\n".join(lines[i:j + 1]))
            i = j + 1
            continue
        programs.append(line)
        i += 1
    return programs, lines[rest_start]


def _literal(text: str) -> Any:
    text = text.strip()
    if text in ("True", "False"):
        return text == "True"
    if _POSE.search(text):
        raise ScriptError(f"poses are outside robocal's URScript subset: {text!r}")
    if re.fullmatch(r"[A-Za-z_]\w*(\[\d+\])?", text):
        return ("ref", text)
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError) as err:
        raise ScriptError(f"cannot read URScript value {text!r}") from err
    if isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, list) and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value
    ):
        return [float(v) for v in value]
    raise ScriptError(f"URScript value {text!r} is outside robocal's subset")


def _split_args(text: str) -> list[str]:
    parts: list[str] = []
    depth, cur, quote = 0, "", ""
    for ch in text:
        if quote:
            cur += ch
            if ch == quote:
                quote = ""
            continue
        if ch in "\"'":
            quote = ch
        elif ch in "([":
            depth += 1
        elif ch in ")]":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    if cur.strip():
        parts.append(cur)
    return parts


def parse_script(program: str) -> tuple[str, list[Statement]]:
    """Parse one program (see :func:`split_programs`) into ``(name, statements)``.

    Raises
    ------
    ScriptError
        On anything outside robocal's URScript subset.
    """
    lines = [ln for ln in program.split("\n") if ln.strip() and not ln.strip().startswith("#")]
    name = ""
    if lines and (m := _BLOCK_START.match(lines[0])):
        name = m.group(2)
        lines = lines[1:-1]
    out: list[Statement] = []
    for line in lines:
        if (a := _ASSIGN.match(line)) and not _CALL.match(line.split("=", 1)[0]):
            out.append(Statement("assign", a.group(1), (_literal(a.group(2)),)))
            continue
        c = _CALL.match(line)
        if c is None:
            raise ScriptError(f"cannot read URScript line {line.strip()!r}")
        args: list[Any] = []
        kwargs: dict[str, Any] = {}
        for part in _split_args(c.group(2)):
            key, eq, value = part.partition("=")
            if eq and re.fullmatch(r"\s*[A-Za-z_]\w*\s*", key) and not value.startswith("="):
                kwargs[key.strip()] = _literal(value)
            else:
                args.append(_literal(part))
        out.append(Statement("call", c.group(1), tuple(args), kwargs))
    return name, out


def script_literal(value: float | str | bool | Sequence[float]) -> str:
    """A value as URScript source (numbers with 17 significant digits, exact on read-back)."""
    if isinstance(value, bool):
        return "True" if value else "False"
    if isinstance(value, str):
        if '"' in value or "\n" in value:
            raise ValueError("URScript strings here may not contain quotes or newlines")
        return f'"{value}"'
    if isinstance(value, int | float):
        return repr(float(value))
    return "[" + ", ".join(repr(float(v)) for v in value) + "]"
