"""Sans-I/O codec for FANUC RMI (Remote Motion Interface, option R912).

Wire layout: one JSON object per CR LF line over TCP. The **first key** names the packet
category and its value the packet name::

    {"Communication":"FRC_Connect"}                                   client -> :16001
    {"Communication":"FRC_Connect","ErrorID":0,"PortNumber":16002,"MajorVersion":7,...}
    {"Command":"FRC_Initialize","GroupMask":1}                        one reply each
    {"Instruction":"FRC_JointMotionJRep","SequenceID":7,"JointAngle":{"J1":10.0,...},
     "SpeedType":"Percent","Speed":10,"TermType":"FINE","TermValue":0}
    {"Instruction":"FRC_JointMotionJRep","ErrorID":0,"SequenceID":7}  sent on completion
    {"Communication":"FRC_SystemFault","SequenceID":7}                unsolicited

Angles are degrees and lengths millimetres on the wire. ``SID`` is accepted for
``SequenceID``, ``JointAngles`` for ``JointAngle``, and number forms strict JSON refuses
(``-.0123``, ``1.``, ``+2``) are normalised before decoding. What robocal speaks is described
in ``docs/protocols/fanuc-rmi.md``. :func:`decode` raises
:class:`~robocal.errors.FramingError` for anything that is not such a packet;
:class:`~robocal.errors.UnexpectedReply` for well-formed packets whose fields have the wrong
types.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from robocal.errors import FramingError, UnexpectedReply

__all__ = [
    "CATEGORIES",
    "DEFAULT_CONNECT_PORT",
    "ERROR_TEXT",
    "JOINT_KEYS",
    "LINEAR_SPEED_TYPES",
    "MAX_IN_FLIGHT",
    "MAX_LINE",
    "MAX_SEQUENCE_ID",
    "RMIT_BASE",
    "Configuration",
    "Packet",
    "decode",
    "describe_error",
    "encode",
    "frame_fields",
    "joint_angles",
    "joint_motion_jrep",
    "linear_motion",
    "next_sequence_id",
    "normalise_numbers",
    "parse_frame",
    "port_value",
    "rmit",
]

Category = Literal["Communication", "Command", "Instruction"]
CATEGORIES: tuple[Category, ...] = ("Communication", "Command", "Instruction")
DEFAULT_CONNECT_PORT = 16001
MAX_IN_FLIGHT = 8
MAX_SEQUENCE_ID = 2**31 - 1
MAX_LINE = 4096
RMIT_BASE = 2556928


def rmit(n: int) -> int:
    """Return the ErrorID of alarm RMIT-``n``."""
    return RMIT_BASE + n


#: RMIT-nnn alarm texts (ErrorID = 2556928 + nnn), in our words, after the operator's manual
#: B-84184EN and the tables public RMI clients carry (see docs/protocols/fanuc-rmi.md).
_RMIT_TEXT: dict[int, str] = {
    1: "internal system error",
    2: "invalid UTool number",
    3: "invalid UFrame number",
    4: "invalid position register",
    5: "invalid speed override",
    6: "cannot execute TP program",
    7: "controller servo is off",
    8: "teach pendant is enabled",
    9: "RMI is not running",
    10: "TP program is not paused",
    11: "cannot resume TP program",
    12: "cannot reset controller",
    13: "invalid RMI command",
    14: "RMI command failed",
    15: "invalid controller state",
    16: "cycle power (hot start is disabled while RMI runs)",
    17: "invalid payload schedule",
    18: "invalid motion option",
    19: "invalid vision register",
    20: "invalid RMI instruction",
    21: "invalid value",
    22: "invalid text string",
    23: "invalid position data",
    24: "RMI is in HOLD state",
    25: "remote device disconnected",
    26: "robot is already connected",
    27: "wait for command done",
    28: "wait for instruction done (more than 8 in flight)",
    29: "invalid sequence ID number",
    30: "invalid speed type",
    31: "invalid speed value",
    32: "invalid term type",
    33: "invalid term value",
    34: "invalid LCB port type",
    35: "invalid ACC value",
    36: "invalid destination position",
    37: "invalid VIA position",
    38: "invalid port number",
    39: "invalid group number",
    40: "invalid group mask",
    41: "joint motion with COORD",
    42: "incremental motion with COORD",
    43: "robot in single step mode",
    44: "invalid position data type",
    45: "not ready for ASCII packet",
    46: "ASCII conversion failed",
    47: "invalid ASCII instruction",
    48: "invalid number of groups",
    49: "invalid instruction packet",
    50: "invalid ASCII packet",
    51: "invalid ASCII string size",
    52: "invalid application tool",
    53: "invalid call program name",
    54: "joint motion with ALIM",
    55: "ALIM option is not loaded",
    56: "need to finish S-motion",
    57: "spline option is not loaded",
}

#: ErrorID -> meaning: every RMIT alarm above plus the MEMO codes FRC_Initialize returns.
ERROR_TEXT: dict[int, str] = {
    **{rmit(n): f"RMIT-{n:03d} {text}" for n, text in _RMIT_TEXT.items()},
    7004: "MEMO-004 specified program is in use (RMI_MOVE selected on the pendant)",
    7015: "MEMO-015 program already exists (RMI_MOVE selected on the pendant)",
}


def describe_error(error_id: int) -> str:
    """Return a readable text for a controller ErrorID (``"RMIT-029 invalid sequence ID"``).

    A code outside the table says so explicitly, naming the RMIT number when it lies in the
    RMIT range, so an operator can look it up in the controller's alarm manual.
    """
    if error_id in ERROR_TEXT:
        return ERROR_TEXT[error_id]
    if RMIT_BASE < error_id < RMIT_BASE + 1000:
        return f"RMIT-{error_id - RMIT_BASE:03d} (not in robocal's RMIT table; ErrorID {error_id})"
    return f"unknown ErrorID {error_id} (not an RMIT alarm; see the controller's alarm history)"


def next_sequence_id(seq: int) -> int:
    """Return the SequenceID following ``seq`` (wraps to 1 after 2**31 - 1)."""
    return 1 if seq >= MAX_SEQUENCE_ID else seq + 1


@dataclass(frozen=True)
class Packet:
    """One decoded RMI packet: ``category`` and ``name`` from the first key, ``body`` all keys."""

    category: Category
    name: str
    body: Mapping[str, Any]

    @property
    def error_id(self) -> int | None:
        """The ``ErrorID``, or None when the packet carries none."""
        return _int_field(self.body, "ErrorID")

    @property
    def sequence_id(self) -> int | None:
        """The ``SequenceID`` (or abbreviated ``SID``), or None."""
        if "SequenceID" in self.body:
            return _int_field(self.body, "SequenceID")
        return _int_field(self.body, "SID")

    def get_int(self, key: str) -> int:
        """Return integer field ``key``; raise UnexpectedReply if absent or not an integer."""
        value = _int_field(self.body, key)
        if value is None:
            raise UnexpectedReply(f"{self.name}: missing integer field {key!r}")
        return value


def _int_field(body: Mapping[str, Any], key: str) -> int | None:
    value = body.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int):
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise UnexpectedReply(f"field {key!r} is not an integer: {value!r}"[:200])
    return value


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name}")


def _pairs_hook(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"duplicate key {key!r}")
        out[key] = value
    # json gives no other way to see the key order of the outer object.
    out["\x00order"] = [k for k, _ in pairs]
    return out


def _strip_order(obj: Any) -> Any:
    if isinstance(obj, dict):
        obj.pop("\x00order", None)
        for v in obj.values():
            _strip_order(v)
    elif isinstance(obj, list):
        for v in obj:
            _strip_order(v)
    return obj


# A JSON string (kept as is) or a number as controllers write it: optional sign, digits with
# an optional point, or a point and digits, optional exponent.
_STRING_OR_NUMBER = re.compile(
    r'"(?:[^"\\]|\\.)*"|(?<![A-Za-z0-9_.])[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?'
)


def _json_number(m: re.Match[str]) -> str:
    token = m.group(0)
    if token.startswith('"'):
        return token
    sign = "-" if token[0] == "-" else ""
    body = token.lstrip("+-")
    mantissa, e, exponent = body.partition("e") if "e" in body else body.partition("E")
    whole, point, frac = mantissa.partition(".")
    whole = whole.lstrip("0") or "0"
    out = sign + whole + ("." + (frac or "0") if point else "")
    return out + (e.lower() + exponent if e else "")


def normalise_numbers(text: str) -> str:
    """Rewrite the number forms controllers send into strict JSON, leaving strings alone.

    Some controllers write numbers without a leading zero (``-.0123``, `` .0456``), with a
    trailing point (``1.``), a plus sign or leading zeros; ``json`` refuses all of these.
    """
    return _STRING_OR_NUMBER.sub(_json_number, text)


def encode(packet: Mapping[str, Any]) -> bytes:
    """Serialise one packet (without CR LF); the first key must be a category.

    Raises
    ------
    FramingError
        If the first key is not a category, a value is not JSON-serialisable or not finite,
        or the line is longer than :data:`MAX_LINE`.
    """
    keys = list(packet)
    if not keys or keys[0] not in CATEGORIES or not isinstance(packet[keys[0]], str):
        raise FramingError(f"RMI packet must start with one of {CATEGORIES}")
    try:
        data = json.dumps(dict(packet), separators=(",", ":"), allow_nan=False).encode("ascii")
    except (TypeError, ValueError) as err:
        raise FramingError(f"RMI packet cannot be encoded: {err}") from err
    if len(data) > MAX_LINE:
        raise FramingError(f"RMI packet of {len(data)} bytes exceeds {MAX_LINE}")
    return data


def decode(line: bytes | str) -> Packet:
    """Parse one line into a :class:`Packet`.

    Raises
    ------
    FramingError
        If the line is not a JSON object whose first key is a category with a string value.
    UnexpectedReply
        If ``ErrorID`` or ``SequenceID`` is present but not an integer.
    """
    raw = line.encode("utf-8", "surrogateescape") if isinstance(line, str) else bytes(line)
    if len(raw) > MAX_LINE:
        raise FramingError(f"RMI line of {len(raw)} bytes exceeds {MAX_LINE}")
    try:
        text = normalise_numbers(raw.decode("utf-8"))
        obj = json.loads(text, object_pairs_hook=_pairs_hook, parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as err:
        raise FramingError(f"RMI line is not valid JSON: {err}"[:200], last_frames=[raw]) from err
    if not isinstance(obj, dict):
        raise FramingError("RMI line is not a JSON object", last_frames=[raw])
    order = obj.pop("\x00order")
    _strip_order(obj)
    if not order or order[0] not in CATEGORIES:
        raise FramingError(f"RMI packet's first key must be one of {CATEGORIES}", last_frames=[raw])
    category = order[0]
    name = obj[category]
    if not isinstance(name, str):
        raise FramingError(f"RMI {category} name is not a string", last_frames=[raw])
    packet = Packet(category, name, obj)
    # Validate the routing fields now so the caller's dispatch cannot trip over them.
    _ = packet.error_id, packet.sequence_id
    return packet


# --- builders and field helpers ---------------------------------------------------------------
def _num(x: float, digits: int) -> float:
    if not math.isfinite(x):
        raise FramingError(f"non-finite value {x!r}")
    return round(float(x), digits)


def joint_motion_jrep(
    sequence_id: int,
    q_deg: Sequence[float],
    *,
    speed_pct: float,
    term_type: Literal["FINE", "CNT", "CR"] = "FINE",
    term_value: int = 0,
    relative: bool = False,
) -> dict[str, Any]:
    """Return an ``FRC_JointMotionJRep`` instruction to joint angles ``q_deg`` (degrees), or
    with ``relative`` an ``FRC_JointRelativeJRep`` moving each joint by ``q_deg``."""
    if not 1 <= len(q_deg) <= 9:
        raise FramingError("RMI joint motion takes 1..9 joints")
    return {
        "Instruction": "FRC_JointRelativeJRep" if relative else "FRC_JointMotionJRep",
        "SequenceID": sequence_id,
        "JointAngle": {f"J{i + 1}": _num(q, 6) for i, q in enumerate(q_deg)},
        "SpeedType": "Percent",
        "Speed": max(1, min(100, round(speed_pct))),
        "TermType": term_type,
        "TermValue": term_value,
    }


#: SpeedType values of linear motions and their factor to mm/s (``Time``/``mSec`` give the
#: motion's duration instead and are not used by robocal).
LINEAR_SPEED_TYPES: dict[str, float] = {"mmSec": 1.0, "InchMin": 25.4 / 60.0}


def linear_motion(
    sequence_id: int,
    position: Mapping[str, float],
    configuration: Configuration,
    *,
    speed_mm_s: float,
    term_type: Literal["FINE", "CNT", "CR"] = "FINE",
    term_value: int = 0,
    relative: bool = False,
) -> dict[str, Any]:
    """Return an ``FRC_LinearMotion`` instruction to ``position`` (X..R, mm and degrees, in
    the configuration's user frame with its tool), or with ``relative`` an
    ``FRC_LinearRelative`` displacing the tool centre by ``position``."""
    if not math.isfinite(speed_mm_s) or speed_mm_s <= 0:
        raise FramingError(f"linear speed must be positive, got {speed_mm_s!r}")
    return {
        "Instruction": "FRC_LinearRelative" if relative else "FRC_LinearMotion",
        "SequenceID": sequence_id,
        "Configuration": configuration.fields(),
        "Position": frame_fields(*(float(position[k]) for k in _FRAME_KEYS)),
        "SpeedType": "mmSec",
        "Speed": _num(speed_mm_s, 3),
        "TermType": term_type,
        "TermValue": term_value,
    }


def port_value(body: Mapping[str, Any]) -> bool:
    """Return the ``PortValue`` of an ``FRC_ReadDIN`` reply or ``FRC_WriteDOUT`` command.

    Controllers write ``"ON"``/``"OFF"``; 1/0 is accepted too.

    Raises
    ------
    UnexpectedReply
        If the field is missing or neither form.
    """
    value = body.get("PortValue")
    if isinstance(value, str) and value.upper() in ("ON", "OFF"):
        return value.upper() == "ON"
    if not isinstance(value, bool) and value in (0, 1):
        return bool(value)
    raise UnexpectedReply(f"PortValue is not ON or OFF: {value!r}"[:200])


#: Keys a joint-angle object comes under: newer firmware answers ``JointAngle``, older
#: firmware ``JointAngles``.
JOINT_KEYS = ("JointAngle", "JointAngles")


def joint_angles(body: Mapping[str, Any], dof: int, *, key: str | None = None) -> list[float]:
    """Return ``J1..J<dof>`` (degrees) from a ``JointAngle`` (or ``JointAngles``) mapping.

    Raises
    ------
    UnexpectedReply
        If the mapping or a joint is missing or not a finite number.
    """
    if key is None:
        key = next((k for k in JOINT_KEYS if k in body), JOINT_KEYS[0])
    angles = body.get(key)
    if not isinstance(angles, Mapping):
        raise UnexpectedReply(f"reply has no {key} object")
    out = []
    for i in range(1, dof + 1):
        v = angles.get(f"J{i}")
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise UnexpectedReply(f"{key}.J{i} missing or not a number: {v!r}"[:200])
        out.append(float(v))
    return out


_FRAME_KEYS = ("X", "Y", "Z", "W", "P", "R")


def frame_fields(x: float, y: float, z: float, w: float, p: float, r: float) -> dict[str, float]:
    """Return an RMI ``Frame``/``Position`` object (mm, degrees)."""
    return {k: _num(v, 6) for k, v in zip(_FRAME_KEYS, (x, y, z, w, p, r), strict=True)}


def parse_frame(body: Mapping[str, Any], key: str = "Frame") -> tuple[float, ...]:
    """Return ``(X, Y, Z, W, P, R)`` from a frame object.

    Raises
    ------
    UnexpectedReply
        If the object or one of its six fields is missing or not a finite number.
    """
    frame = body.get(key)
    if not isinstance(frame, Mapping):
        raise UnexpectedReply(f"reply has no {key} object")
    out = []
    for k in _FRAME_KEYS:
        v = frame.get(k)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise UnexpectedReply(f"{key}.{k} missing or not a number: {v!r}"[:200])
        out.append(float(v))
    return tuple(out)


@dataclass(frozen=True)
class Configuration:
    """The ``Configuration`` object of a Cartesian position (a position register's).

    The tool and user frame numbers, the arm configuration flags (``Front``, ``Up``, ``Left``,
    ``Flip``: 1 or 0) and the turn numbers of joints 4 to 6. The defaults are what a controller
    reports for a register never written: front, up, no left, no flip, no turns, frames 0.
    """

    utool_number: int = 0
    uframe_number: int = 0
    front: int = 1
    up: int = 1
    left: int = 0
    flip: int = 0
    turn4: int = 0
    turn5: int = 0
    turn6: int = 0

    def fields(self) -> dict[str, int]:
        """Return the wire object, keys in the order controllers write them."""
        return {
            "UToolNumber": self.utool_number,
            "UFrameNumber": self.uframe_number,
            "Front": self.front,
            "Up": self.up,
            "Left": self.left,
            "Flip": self.flip,
            "Turn4": self.turn4,
            "Turn5": self.turn5,
            "Turn6": self.turn6,
        }
