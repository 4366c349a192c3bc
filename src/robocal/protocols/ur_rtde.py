"""Sans-I/O codec of Universal Robots' RTDE (Real-Time Data Exchange, TCP port 30004).

Protocol as robocal speaks it: ``docs/protocols/universal-robots.md``. Every package is::

    uint16 size (whole package, header included) | uint8 type | payload

big-endian. Types used here (protocol version 2):

====  ===================================  ===============================================
type  request payload                      reply payload
====  ===================================  ===============================================
'V'   uint16 protocol version              uint8 accepted
'v'   (none)                               uint32 major, minor, bugfix, build
'O'   double frequency, names "a,b,c"      uint8 recipe id, types "DOUBLE,VECTOR6D,..."
'I'   names "a,b"                          uint8 recipe id, types (``IN_USE``/``NOT_FOUND``)
'S'   (none)                               uint8 accepted
'P'   (none)                               uint8 accepted
'U'   uint8 recipe id, values (inputs)     uint8 recipe id, values (outputs, streamed)
'M'   uint8 n, text, uint8 n, source,      (controller to client only)
      uint8 warning level
====  ===================================  ===============================================

A recipe whose types contain ``NOT_FOUND`` or ``IN_USE`` is refused by the controller (the
recipe id is 0 then).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from robocal.errors import FramingError, ProtocolError

__all__ = [
    "DEFAULT_PORT",
    "INPUTS",
    "OUTPUTS",
    "PROTOCOL_VERSION",
    "RobotMode",
    "RtdeFramer",
    "RtdePackage",
    "RuntimeState",
    "SafetyMode",
    "decode_values",
    "encode",
    "encode_values",
    "input_type",
    "output_type",
    "parse_names",
    "text_message",
]

DEFAULT_PORT = 30004
PROTOCOL_VERSION = 2
MAX_PACKAGE = 65535

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")


class RobotMode:
    """``robot_mode`` values (RTDE and the primary interface agree from -1 on)."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8

    #: Value -> name, from the constants above.
    NAMES: ClassVar[dict[int, str]]


class SafetyMode:
    """``safety_mode`` values."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11

    #: Value -> name, from the constants above.
    NAMES: ClassVar[dict[int, str]]


def _names(constants: type) -> dict[int, str]:
    """``{value: NAME}`` of a class's upper-case integer constants."""
    return {v: k for k, v in vars(constants).items() if k.isupper() and type(v) is int}


RobotMode.NAMES = _names(RobotMode)
SafetyMode.NAMES = _names(SafetyMode)


class RuntimeState:
    """``runtime_state`` values (program execution)."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


# struct format of each RTDE type (big-endian, no header)
_TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_VECTOR_LEN = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


def _by_type(names_by_type: dict[str, str]) -> dict[str, str]:
    """``{type: "name name ..."}`` to ``{name: type}``."""
    return {name: t for t, names in names_by_type.items() for name in names.split()}


# Output variables (RTDE guide, controller to client) by type; registers are added below.
OUTPUTS: dict[str, str] = _by_type({
    "DOUBLE": (
        "timestamp actual_execution_time speed_scaling target_speed_fraction "
        "actual_momentum actual_main_voltage actual_robot_voltage actual_robot_current "
        "standard_analog_input0 standard_analog_input1 standard_analog_output0 "
        "standard_analog_output1 io_current euromap67_24V_voltage euromap67_24V_current "
        "tool_analog_input0 tool_analog_input1 tool_output_current tool_temperature "
        "tcp_force_scalar payload joint_position_deviation_ratio "
        "collision_detection_ratio"
    ),
    "VECTOR6D": (
        "target_q target_qd target_qdd target_current target_moment actual_q actual_qd "
        "actual_current actual_current_window joint_control_output actual_TCP_pose "
        "actual_TCP_speed actual_TCP_force target_TCP_pose target_TCP_speed "
        "joint_temperatures actual_joint_voltage payload_inertia ft_raw_wrench "
        "actual_current_as_torque"
    ),
    "UINT64": "actual_digital_input_bits actual_digital_output_bits",
    "INT32": "robot_mode safety_mode safety_status tool_output_voltage",
    "VECTOR6INT32": "joint_mode",
    "VECTOR3D": "actual_tool_accelerometer elbow_position elbow_velocity payload_cog",
    "UINT32": (
        "runtime_state robot_status_bits safety_status_bits analog_io_types "
        "euromap67_input_bits euromap67_output_bits tool_mode tool_analog_input_types "
        "output_bit_registers0_to_31 output_bit_registers32_to_63 "
        "input_bit_registers0_to_31 input_bit_registers32_to_63 script_control_line "
        "time_scale_source"
    ),
    "UINT8": "tool_output_mode tool_digital_output0_mode tool_digital_output1_mode",
})
# Input variables (client to controller) by type.
INPUTS: dict[str, str] = _by_type({
    "UINT32": "speed_slider_mask input_bit_registers0_to_31 input_bit_registers32_to_63",
    "DOUBLE": "speed_slider_fraction standard_analog_output_0 standard_analog_output_1",
    "UINT8": (
        "standard_digital_output_mask standard_digital_output "
        "configurable_digital_output_mask configurable_digital_output "
        "tool_digital_output_mask tool_digital_output standard_analog_output_mask "
        "standard_analog_output_type"
    ),
    "VECTOR6D": "external_force_torque",
    "BOOL": "ft_rtde_input_enable",
})
for _i in range(48):
    OUTPUTS[f"output_int_register_{_i}"] = "INT32"
    OUTPUTS[f"output_double_register_{_i}"] = "DOUBLE"
    OUTPUTS[f"input_int_register_{_i}"] = "INT32"
    OUTPUTS[f"input_double_register_{_i}"] = "DOUBLE"
    INPUTS[f"input_int_register_{_i}"] = "INT32"
    INPUTS[f"input_double_register_{_i}"] = "DOUBLE"
for _i in range(64, 128):
    OUTPUTS[f"output_bit_register_{_i}"] = "BOOL"
    OUTPUTS[f"input_bit_register_{_i}"] = "BOOL"
    INPUTS[f"input_bit_register_{_i}"] = "BOOL"


def output_type(name: str) -> str:
    """RTDE type of output variable ``name``, or ``"NOT_FOUND"``."""
    return OUTPUTS.get(name, "NOT_FOUND")


def input_type(name: str) -> str:
    """RTDE type of input variable ``name``, or ``"NOT_FOUND"``."""
    return INPUTS.get(name, "NOT_FOUND")


@dataclass(frozen=True, slots=True)
class RtdePackage:
    """One RTDE package: its type byte and payload (header stripped)."""

    type: int
    payload: bytes

    @property
    def letter(self) -> str:
        """The type as its ASCII letter (``"U"``, ``"O"``...)."""
        return chr(self.type) if 32 <= self.type < 127 else f"\\x{self.type:02x}"


def encode(ptype: int, payload: bytes = b"") -> bytes:
    """Frame ``payload`` as a package of type ``ptype``.

    Raises
    ------
    FramingError
        If the package would exceed 65535 bytes.
    """
    size = 3 + len(payload)
    if size > MAX_PACKAGE:
        raise FramingError(f"RTDE package of {size} bytes exceeds {MAX_PACKAGE}")
    return struct.pack(">HB", size, ptype) + payload


class RtdeFramer:
    """Split a byte stream into :class:`RtdePackage`; a size below 3 raises FramingError."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        """Append received bytes."""
        self._buf += data

    def packages(self) -> Iterator[RtdePackage]:
        """Yield every complete package buffered so far."""
        while len(self._buf) >= 3:
            size, ptype = struct.unpack_from(">HB", self._buf)
            if size < 3:
                head = bytes(self._buf[:8])
                self._buf.clear()
                raise FramingError(f"RTDE package size {size} < 3", last_frames=[head])
            if len(self._buf) < size:
                return
            payload = bytes(self._buf[3:size])
            del self._buf[:size]
            yield RtdePackage(ptype, payload)


def parse_names(payload: bytes) -> list[str]:
    """Comma-separated variable names (or types) as a list; empty items (a trailing comma,
    as ur-rtde sends) are dropped, as the controller does."""
    text = payload.decode("ascii", errors="replace").strip("\x00")
    return [n.strip() for n in text.split(",") if n.strip()]


def _format(types: Sequence[str]) -> str:
    try:
        return ">" + "".join(_TYPE_FORMATS[t] for t in types)
    except KeyError as err:
        raise ProtocolError(f"unknown RTDE type {err.args[0]!r}") from None


def encode_values(types: Sequence[str], values: Sequence[Any]) -> bytes:
    """Pack one value per type (vectors as sequences) in recipe order."""
    flat: list[Any] = []
    for t, v in zip(types, values, strict=True):
        n = _VECTOR_LEN.get(t)
        if n is None:
            flat.append(v)
        else:
            items = list(v)
            if len(items) != n:
                raise ProtocolError(f"{t} needs {n} values, got {len(items)}")
            flat.extend(items)
    try:
        return struct.pack(_format(types), *flat)
    except struct.error as err:
        raise ProtocolError(f"cannot pack RTDE values: {err}") from err


def decode_values(types: Sequence[str], data: bytes) -> list[Any]:
    """Unpack the values of a data package (after the recipe id) in recipe order."""
    fmt = _format(types)
    if struct.calcsize(fmt) != len(data):
        raise ProtocolError(
            f"RTDE data of {len(data)} bytes does not match a recipe of "
            f"{struct.calcsize(fmt)} bytes", last_frames=[data[:64]],
        )
    flat = list(struct.unpack(fmt, data))
    out: list[Any] = []
    for t in types:
        n = _VECTOR_LEN.get(t)
        if n is None:
            out.append(flat.pop(0))
        else:
            out.append(tuple(flat[:n]))
            del flat[:n]
    return out


def data_package(recipe_id: int, types: Sequence[str], values: Sequence[Any]) -> bytes:
    """A whole ``U`` package."""
    return encode(DATA_PACKAGE, bytes([recipe_id]) + encode_values(types, values))


def text_message(text: str, source: str = "robocal", level: int = 0) -> bytes:
    """A whole ``M`` package (protocol version 2 layout)."""
    t = text.encode("utf-8")[:255]
    s = source.encode("utf-8")[:255]
    return encode(TEXT_MESSAGE, bytes([len(t)]) + t + bytes([len(s)]) + s + bytes([level]))


def parse_text_message(payload: bytes) -> tuple[str, str, int]:
    """``(text, source, warning level)`` of a version 2 ``M`` payload."""
    try:
        n = payload[0]
        text = payload[1:1 + n].decode("utf-8", errors="replace")
        m = payload[1 + n]
        source = payload[2 + n:2 + n + m].decode("utf-8", errors="replace")
        level = payload[2 + n + m]
    except IndexError as err:
        raise ProtocolError("truncated RTDE text message", last_frames=[payload]) from err
    return text, source, level


# --- request/reply helpers (both sides) ------------------------------------------------------
def request_protocol_version(version: int = PROTOCOL_VERSION) -> bytes:
    """``V`` request."""
    return encode(REQUEST_PROTOCOL_VERSION, struct.pack(">H", version))


def setup_outputs(names: Sequence[str], frequency_hz: float) -> bytes:
    """``O`` request (version 2: with the output frequency)."""
    return encode(SETUP_OUTPUTS, struct.pack(">d", frequency_hz) + ",".join(names).encode())


def setup_inputs(names: Sequence[str]) -> bytes:
    """``I`` request."""
    return encode(SETUP_INPUTS, ",".join(names).encode())


def parse_setup_outputs_request(payload: bytes) -> tuple[float, list[str]]:
    """``(frequency, names)`` of an ``O`` request."""
    if len(payload) < 8:
        raise ProtocolError("RTDE output setup without a frequency", last_frames=[payload])
    (freq,) = struct.unpack_from(">d", payload)
    return freq, parse_names(payload[8:])


def recipe_reply(ptype: int, recipe_id: int, types: Sequence[str]) -> bytes:
    """``O``/``I`` reply: recipe id and the comma-separated types."""
    return encode(ptype, bytes([recipe_id]) + ",".join(types).encode())


def parse_recipe_reply(payload: bytes) -> tuple[int, list[str]]:
    """``(recipe id, types)`` of an ``O``/``I`` reply."""
    if not payload:
        raise ProtocolError("empty RTDE recipe reply")
    return payload[0], parse_names(payload[1:])


def accepted(ptype: int, ok: bool) -> bytes:
    """A one-byte accepted/refused reply (``V``, ``S``, ``P``)."""
    return encode(ptype, bytes([1 if ok else 0]))


def controller_version(major: int, minor: int, bugfix: int, build: int) -> bytes:
    """``v`` reply."""
    return encode(GET_URCONTROL_VERSION, struct.pack(">IIII", major, minor, bugfix, build))


def parse_controller_version(payload: bytes) -> tuple[int, int, int, int]:
    """``(major, minor, bugfix, build)`` of a ``v`` reply."""
    if len(payload) != 16:
        raise ProtocolError("RTDE controller version reply is not 16 bytes",
                            last_frames=[payload])
    major, minor, bugfix, build = struct.unpack(">IIII", payload)
    return major, minor, bugfix, build


def values_by_name(names: Sequence[str], types: Sequence[str], data: bytes) -> dict[str, Any]:
    """Decode a data package's values into ``{name: value}``."""
    return dict(zip(names, decode_values(types, data), strict=True))


def ordered(names: Sequence[str], values: Mapping[str, Any]) -> list[Any]:
    """The values of ``names`` in recipe order."""
    return [values[n] for n in names]
