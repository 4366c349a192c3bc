"""Sans-I/O codec for FANUC RMI (Remote Motion Interface, option R912), protocols.md 1.1.

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
``SequenceID``. :func:`decode` raises :class:`~robocal.errors.FramingError` for anything that
is not such a packet; :class:`~robocal.errors.UnexpectedReply` for well-formed packets whose
fields have the wrong types.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from robocal.errors import FramingError, UnexpectedReply

__all__ = [
    "CATEGORIES",
    "DEFAULT_CONNECT_PORT",
    "ERROR_TEXT",
    "MAX_IN_FLIGHT",
    "MAX_LINE",
    "MAX_SEQUENCE_ID",
    "RMIT_BASE",
    "Packet",
    "decode",
    "describe_error",
    "encode",
    "frame_fields",
    "joint_angles",
    "joint_motion_jrep",
    "next_sequence_id",
    "parse_frame",
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


#: ErrorID -> meaning, from the operator's manual (RMIT-nnn = 2556928 + nnn) plus MEMO codes.
ERROR_TEXT: dict[int, str] = {
    rmit(1): "RMIT-001 internal system error",
    rmit(2): "RMIT-002 invalid UTool number",
    rmit(3): "RMIT-003 invalid UFrame number",
    rmit(4): "RMIT-004 invalid position register",
    rmit(5): "RMIT-005 invalid speed override",
    rmit(6): "RMIT-006 cannot execute TP program",
    rmit(7): "RMIT-007 controller servo is off",
    rmit(8): "RMIT-008 teach pendant is enabled",
    rmit(9): "RMIT-009 RMI is not running",
    rmit(13): "RMIT-013 invalid RMI command",
    rmit(15): "RMIT-015 invalid controller state",
    rmit(16): "RMIT-016 hot start is disabled while RMI runs",
    rmit(21): "RMIT-021 invalid value",
    rmit(22): "RMIT-022 invalid text string",
    rmit(23): "RMIT-023 invalid position data",
    rmit(24): "RMIT-024 RMI is in HOLD state",
    rmit(25): "RMIT-025 remote device disconnected",
    rmit(26): "RMIT-026 robot is already connected",
    rmit(27): "RMIT-027 wait for command done",
    rmit(28): "RMIT-028 wait for instruction done (more than 8 in flight)",
    rmit(29): "RMIT-029 invalid sequence ID number",
    rmit(30): "RMIT-030 invalid speed type",
    rmit(31): "RMIT-031 invalid speed value",
    rmit(32): "RMIT-032 invalid term type",
    rmit(33): "RMIT-033 invalid term value",
    rmit(38): "RMIT-038 invalid port number",
    rmit(39): "RMIT-039 invalid group number",
    rmit(40): "RMIT-040 invalid group mask",
    7004: "MEMO-004 specified program is in use (RMI_MOVE selected on the pendant)",
    7015: "MEMO-015 program already exists (RMI_MOVE selected on the pendant)",
}


def describe_error(error_id: int) -> str:
    """Return a readable text for a controller ErrorID (``"RMIT-029 invalid sequence ID"``)."""
    if error_id in ERROR_TEXT:
        return ERROR_TEXT[error_id]
    if RMIT_BASE < error_id < RMIT_BASE + 1000:
        return f"RMIT-{error_id - RMIT_BASE:03d}"
    return f"ErrorID {error_id}"


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
        text = raw.decode("utf-8")
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
) -> dict[str, Any]:
    """Return an ``FRC_JointMotionJRep`` instruction to joint angles ``q_deg`` (degrees)."""
    if not 1 <= len(q_deg) <= 9:
        raise FramingError("RMI joint motion takes 1..9 joints")
    return {
        "Instruction": "FRC_JointMotionJRep",
        "SequenceID": sequence_id,
        "JointAngle": {f"J{i + 1}": _num(q, 6) for i, q in enumerate(q_deg)},
        "SpeedType": "Percent",
        "Speed": max(1, min(100, round(speed_pct))),
        "TermType": term_type,
        "TermValue": term_value,
    }


def joint_angles(body: Mapping[str, Any], dof: int, *, key: str = "JointAngle") -> list[float]:
    """Return ``J1..J<dof>`` (degrees) from a ``JointAngle`` mapping.

    Raises
    ------
    UnexpectedReply
        If the mapping or a joint is missing or not a finite number.
    """
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
