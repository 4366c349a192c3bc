"""Sans-I/O codec for KUKAVARPROXY (KVP), the variable server run on KUKA KRC4/KRC5 controllers.

Wire layout (TCP, port 7000 by default, big-endian), described in docs/protocols/kuka-kvp.md::

    request   u16 msg_id | u16 length | u8 mode | u16 name_len | name
              [| u16 value_len | value]                                  (write only)
    reply     u16 msg_id | u16 length | u8 mode | u16 value_len | value | 00 01 <ok>

``length`` counts the bytes after the first four. ``mode`` 0 reads and 1 writes a KRL
variable named in KRL syntax (``$AXIS_ACT``, ``RC_COMP[3]``, ``$ROBNAME[]``); values travel
as KRL text (``{E6AXIS: A1 10.0, A2 -90.0, ...}``, ``TRUE``, ``42``, ``"text"``). A reply
echoes the request's ``msg_id`` and ``mode``, carries the variable's value (after a write:
its new value) and ends with three status bytes whose last is 1 on success and 0 on failure.

:class:`KvpFramer` splits a byte stream into messages; :func:`decode_request` and
:func:`decode_reply` parse one message each and raise :class:`~robocal.errors.FramingError`
for anything else. The ``parse_*`` and ``format_*`` helpers read and write KRL value text
(:class:`~robocal.errors.UnexpectedReply` for text of the wrong shape).
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from robocal.errors import FramingError, UnexpectedReply
from robocal.protocols.framing import StreamBuffer

__all__ = [
    "AXIS_NAMES",
    "DEFAULT_PORT",
    "MAX_BODY",
    "MODE_READ",
    "MODE_WRITE",
    "KvpFramer",
    "Reply",
    "Request",
    "decode_reply",
    "decode_request",
    "encode_reply",
    "encode_request",
    "format_bool",
    "format_e6axis",
    "format_int",
    "format_real",
    "format_string",
    "parse_bool",
    "parse_e6axis",
    "parse_int",
    "parse_real",
    "parse_string",
    "parse_struct",
]

DEFAULT_PORT = 7000
MODE_READ = 0
MODE_WRITE = 1
#: Largest ``length`` field accepted (u16); KRL values are far shorter.
MAX_BODY = 0xFFFF
#: E6AXIS components in KRL order: robot axes A1..A6, external axes E1..E6 (degrees or mm).
AXIS_NAMES: tuple[str, ...] = (*(f"A{i}" for i in range(1, 7)), *(f"E{i}" for i in range(1, 7)))

_HEAD = struct.Struct(">HHB")
_U16 = struct.Struct(">H")
_OK_TAIL = b"\x00\x01\x01"
_FAIL_TAIL = b"\x00\x01\x00"


@dataclass(frozen=True)
class Request:
    """A client's request: read (``value`` None) or write ``value`` to variable ``name``."""

    msg_id: int
    mode: int
    name: str
    value: str | None = None


@dataclass(frozen=True)
class Reply:
    """The proxy's answer: the variable's value as KRL text, and whether the access worked."""

    msg_id: int
    mode: int
    value: str
    ok: bool


def _text(data: bytes) -> str:
    # KRL text is ASCII; latin-1 keeps any other byte visible instead of failing.
    return data.decode("latin-1")


def _bytes(text: str, what: str) -> bytes:
    try:
        data = text.encode("ascii")
    except UnicodeEncodeError as err:
        raise FramingError(f"KVP {what} must be ASCII: {text[:40]!r}") from err
    if len(data) > 0xFFFF:
        raise FramingError(f"KVP {what} of {len(data)} bytes is too long")
    return data


def _check_id(msg_id: int) -> None:
    if not 0 <= msg_id <= 0xFFFF:
        raise FramingError(f"KVP message id {msg_id} outside 0..65535")


def encode_request(req: Request) -> bytes:
    """Serialise a read (``value`` None, mode 0) or write (mode 1) request.

    Raises
    ------
    FramingError
        For a message id outside u16, an empty or non-ASCII name, or a message too long.
    """
    _check_id(req.msg_id)
    name = _bytes(req.name, "variable name")
    if not name:
        raise FramingError("KVP variable name is empty")
    body = bytes([req.mode]) + _U16.pack(len(name)) + name
    if req.mode == MODE_WRITE:
        if req.value is None:
            raise FramingError("KVP write request without a value")
        value = _bytes(req.value, "value")
        body += _U16.pack(len(value)) + value
    elif req.mode != MODE_READ or req.value is not None:
        raise FramingError(f"KVP request mode {req.mode} with value {req.value!r} not supported")
    if len(body) > MAX_BODY:
        raise FramingError(f"KVP request of {len(body)} bytes is too long")
    return _U16.pack(req.msg_id) + _U16.pack(len(body)) + body


def encode_reply(reply: Reply) -> bytes:
    """Serialise a reply (status bytes ``00 01 01`` on success, ``00 01 00`` on failure)."""
    _check_id(reply.msg_id)
    value = _bytes(reply.value, "value")
    body = bytes([reply.mode]) + _U16.pack(len(value)) + value
    body += _OK_TAIL if reply.ok else _FAIL_TAIL
    if len(body) > MAX_BODY:
        raise FramingError(f"KVP reply of {len(body)} bytes is too long")
    return _U16.pack(reply.msg_id) + _U16.pack(len(body)) + body


def _field(msg: bytes, at: int, what: str) -> tuple[bytes, int]:
    """The u16-length-prefixed field at ``at``; and the offset after it."""
    if at + 2 > len(msg):
        raise FramingError(f"KVP message ends inside the {what} length", last_frames=[msg])
    (n,) = _U16.unpack_from(msg, at)
    end = at + 2 + n
    if end > len(msg):
        raise FramingError(f"KVP {what} of {n} bytes overruns the message", last_frames=[msg])
    return msg[at + 2 : end], end


def _head(msg: bytes) -> tuple[int, int]:
    if len(msg) < _HEAD.size:
        raise FramingError(f"KVP message of {len(msg)} bytes is too short", last_frames=[msg])
    msg_id, length, mode = _HEAD.unpack_from(msg)
    if length != len(msg) - 4:
        raise FramingError(
            f"KVP length field says {length} bytes, message has {len(msg) - 4}",
            last_frames=[msg],
        )
    return msg_id, mode


def decode_request(msg: bytes) -> Request:
    """Parse one whole request message (as :class:`KvpFramer` returns it).

    Raises
    ------
    FramingError
        If the fields do not fill the message exactly, the mode is neither read nor write, or
        the name is empty.
    """
    msg = bytes(msg)
    msg_id, mode = _head(msg)
    name, at = _field(msg, 5, "variable name")
    if not name:
        raise FramingError("KVP request names no variable", last_frames=[msg])
    value: str | None = None
    if mode == MODE_WRITE:
        raw, at = _field(msg, at, "value")
        value = _text(raw)
    elif mode != MODE_READ:
        raise FramingError(f"KVP request mode {mode} is not read (0) or write (1)",
                           last_frames=[msg])
    if at != len(msg):
        raise FramingError(f"KVP request has {len(msg) - at} trailing bytes", last_frames=[msg])
    return Request(msg_id, mode, _text(name), value)


def decode_reply(msg: bytes) -> Reply:
    """Parse one whole reply message.

    Raises
    ------
    FramingError
        If the value and the three status bytes do not fill the message exactly.
    """
    msg = bytes(msg)
    msg_id, mode = _head(msg)
    value, at = _field(msg, 5, "value")
    tail = msg[at:]
    if len(tail) != 3:
        raise FramingError(f"KVP reply ends with {len(tail)} status bytes, not 3",
                           last_frames=[msg])
    return Reply(msg_id, mode, _text(value), tail[-1] == 1)


class KvpFramer(StreamBuffer):
    """Split a byte stream into whole KVP messages (both directions share the framing).

    A ``length`` field below the smallest message (3 bytes) cannot be resynchronised from:
    :meth:`next_message` raises FramingError and the connection should be closed.
    """

    def next_message(self) -> bytes | None:
        """Return the next whole message (header included), or None if more bytes are needed.

        Raises
        ------
        FramingError
            If a length field is too small to hold a message.
        """
        if len(self._buf) < 4:
            return None
        (length,) = _U16.unpack_from(self._buf, 2)
        if length < 3:
            raise FramingError(f"KVP length field {length} is too small",
                               last_frames=[bytes(self._buf[:16])])
        if len(self._buf) < 4 + length:
            return None
        msg = bytes(self._buf[: 4 + length])
        del self._buf[: 4 + length]
        return msg


# --- KRL value text ------------------------------------------------------------------------------
def format_real(x: float, digits: int = 6) -> str:
    """A KRL REAL literal (at most ``digits`` decimals, trailing zeros dropped)."""
    if not math.isfinite(x):
        raise FramingError(f"KRL REAL must be finite, got {x!r}")
    text = f"{float(x):.{digits}f}".rstrip("0")
    text = text + "0" if text.endswith(".") else text
    return "0.0" if text in ("-0.0", "-0") else text


def format_int(n: int) -> str:
    """A KRL INT literal (32-bit signed)."""
    if not -(2**31) <= n < 2**31:
        raise FramingError(f"KRL INT {n} outside 32 bits")
    return str(int(n))


def format_bool(b: bool) -> str:
    """A KRL BOOL literal."""
    return "TRUE" if b else "FALSE"


def format_string(s: str) -> str:
    """A KRL CHAR array literal in double quotes (no quotes inside)."""
    if '"' in s or not s.isascii():
        raise FramingError(f"KRL string cannot hold {s[:40]!r}")
    return f'"{s}"'


def format_e6axis(values: Sequence[float] | Mapping[str, float], digits: int = 6) -> str:
    """An E6AXIS aggregate: a sequence fills A1, A2, ... in order (at most 12); a mapping
    names its components. Only the components given are written (KRL keeps the others)."""
    items = dict(values) if isinstance(values, Mapping) else dict(zip(AXIS_NAMES, values,
                                                                      strict=False))
    if not isinstance(values, Mapping) and len(values) > len(AXIS_NAMES):
        raise FramingError(f"E6AXIS has {len(AXIS_NAMES)} components, got {len(values)}")
    unknown = set(items) - set(AXIS_NAMES)
    if unknown:
        raise FramingError(f"E6AXIS has no component {sorted(unknown)[0]}")
    parts = [f"{k} {format_real(items[k], digits)}" for k in AXIS_NAMES if k in items]
    return "{E6AXIS: " + ", ".join(parts) + "}"


_INT = re.compile(r"[-+]?\d+")
_REAL = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_NAME = re.compile(r"[A-Za-z_$][A-Za-z0-9_$]*")


def parse_int(text: str) -> int:
    """Parse a KRL INT (decimal; ``'H..'`` hex and ``'B..'`` binary literals too)."""
    t = text.strip()
    if t[:2].upper() in ("'H", "'B") and t.endswith("'") and len(t) > 3:
        try:
            return int(t[2:-1], 16 if t[1] in "Hh" else 2)
        except ValueError:
            pass
    if not _INT.fullmatch(t):
        raise UnexpectedReply(f"not a KRL INT: {text[:40]!r}")
    return int(t)


def parse_real(text: str) -> float:
    """Parse a KRL REAL (an INT literal is a REAL too)."""
    t = text.strip()
    if not _REAL.fullmatch(t):
        raise UnexpectedReply(f"not a KRL REAL: {text[:40]!r}")
    value = float(t)
    if not math.isfinite(value):
        raise UnexpectedReply(f"KRL REAL out of range: {text[:40]!r}")
    return value


def parse_bool(text: str) -> bool:
    """Parse a KRL BOOL (``TRUE``/``FALSE``, any case)."""
    t = text.strip().upper()
    if t not in ("TRUE", "FALSE"):
        raise UnexpectedReply(f"not a KRL BOOL: {text[:40]!r}")
    return t == "TRUE"


def parse_string(text: str) -> str:
    """Parse a KRL CHAR array literal in double (or single) quotes."""
    t = text.strip()
    if len(t) < 2 or t[0] != t[-1] or t[0] not in "\"'" or t[0] in t[1:-1]:
        raise UnexpectedReply(f"not a KRL string: {text[:40]!r}")
    return t[1:-1]


def parse_struct(text: str) -> tuple[str | None, dict[str, str]]:
    """Parse a flat KRL aggregate ``{TYPE: K1 v1, K2 v2}`` (type optional).

    Returns the type name (upper case, or None) and the component texts by upper-case name.

    Raises
    ------
    UnexpectedReply
        If the text is not a flat aggregate, or names a component twice.
    """
    t = text.strip()
    if len(t) < 2 or t[0] != "{" or t[-1] != "}" or "{" in t[1:-1] or "}" in t[1:-1]:
        raise UnexpectedReply(f"not a flat KRL aggregate: {text[:60]!r}")
    inner = t[1:-1].strip()
    kind: str | None = None
    head, colon, rest = inner.partition(":")
    if colon:
        if not _NAME.fullmatch(head.strip()):
            raise UnexpectedReply(f"bad KRL aggregate type {head.strip()[:40]!r}")
        kind, inner = head.strip().upper(), rest
    fields: dict[str, str] = {}
    if inner.strip():
        for part in inner.split(","):
            key, _, value = part.strip().partition(" ")
            key, value = key.upper(), value.strip()
            if not _NAME.fullmatch(key) or not value or key in fields:
                raise UnexpectedReply(f"bad KRL aggregate component {part.strip()[:40]!r}")
            fields[key] = value
    return kind, fields


def parse_e6axis(text: str, *, components: int = 6) -> list[float]:
    """Return the first ``components`` values (A1.., then E1..) of an E6AXIS or AXIS text.

    Raises
    ------
    UnexpectedReply
        If the text is not such an aggregate or lacks one of those components.
    """
    kind, fields = parse_struct(text)
    if kind not in (None, "E6AXIS", "AXIS"):
        raise UnexpectedReply(f"expected an E6AXIS, got a {kind}")
    out = []
    for name in AXIS_NAMES[:components]:
        if name not in fields:
            raise UnexpectedReply(f"E6AXIS text lacks {name}: {text[:60]!r}")
        out.append(parse_real(fields[name]))
    return out
