r"""Sans-I/O codec for LTP/1, the tracker line protocol (docs/protocols.md section 2.5).

Wire layout (7-bit ASCII, one message per CR LF line, at most 512 bytes)::

    request  :=  TAG SP VERB *(SP key=value)                      TAG = 1..8 alphanumerics
    reply    :=  TAG SP "OK" *(SP key=value)
              |  TAG SP "ERR" SP CODE SP NAME [SP msg="..."]
    event    :=  "*" SP "EVT" SP NAME *(SP key=value)             unsolicited, any time

    > 3 MEAS id=P0007 n=20 stab_mm=0.010 stab_ms=500 timeout_ms=8000
    < * EVT BEAM state=LOCKED t=2026-01-05T10:11:12.345Z
    < 3 OK id=P0007 x=1523.40712 y=-210.11930 z=887.00241 sx=0.0021 ... smr=RRR15
    > 4 MEAS id=P0008 timeout_ms=3000
    < 4 ERR 10 BEAM_BROKEN msg="beam interrupted while settling"

Values contain no spaces unless double-quoted; inside quotes ``\\"`` and ``\\\\`` escape.
Parsers accept runs of spaces between tokens and raise only
:class:`~robocal.errors.FramingError` for anything malformed. Line framing itself is
:class:`~robocal.protocols.framing.LineFramer`'s job; these functions see one line.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from types import MappingProxyType

from robocal.errors import FramingError

__all__ = [
    "MAX_LINE",
    "PROTO",
    "Err",
    "ErrorCode",
    "Event",
    "Message",
    "Ok",
    "Request",
    "format_err",
    "format_event",
    "format_ok",
    "format_request",
    "parse_message",
    "parse_request",
]

PROTO = "LTP/1"
MAX_LINE = 512


class ErrorCode(IntEnum):
    """LTP/1 error codes (``ERR <code> <NAME>``)."""

    SYNTAX = 1
    UNKNOWN_VERB = 2
    BAD_ARG = 3
    BEAM_BROKEN = 10
    NO_TARGET = 11
    UNSTABLE = 12
    SMR_MISMATCH = 13
    BUSY = 14
    TIMEOUT = 15
    ABORTED = 16
    NOT_INITIALIZED = 20
    NOT_LEVELED = 21
    ENV_OUT_OF_RANGE = 30
    DEVICE_FAULT = 50
    INTERNAL = 99


_TAG = re.compile(r"[A-Za-z0-9]{1,8}")
_VERB = re.compile(r"[A-Z][A-Z0-9_]*\??")
_NAME = re.compile(r"[A-Z][A-Z0-9_]*")
_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_BARE = re.compile(r"[!#-~]+")  # printable, no space, no double quote


def _frozen(d: Mapping[str, str] | None) -> Mapping[str, str]:
    return MappingProxyType(dict(d or {}))


@dataclass(frozen=True)
class Request:
    """A client request: ``tag`` echoed in the reply, ``verb`` such as ``MEAS``, ``args``."""

    tag: str
    verb: str
    args: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "args", _frozen(self.args))


@dataclass(frozen=True)
class Ok:
    """A successful reply with its ``key=value`` pairs."""

    tag: str
    values: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", _frozen(self.values))


@dataclass(frozen=True)
class Err:
    """An error reply: numeric ``code``, symbolic ``name`` and an optional message."""

    tag: str
    code: int
    name: str
    msg: str | None = None


@dataclass(frozen=True)
class Event:
    """An unsolicited event ``* EVT NAME key=value ...``."""

    name: str
    values: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", _frozen(self.values))


Message = Ok | Err | Event


# --- tokenising --------------------------------------------------------------------------------
def _text(line: bytes | str) -> str:
    if isinstance(line, bytes | bytearray):
        try:
            text = bytes(line).decode("ascii")
        except UnicodeDecodeError as err:
            raise FramingError("LTP line is not 7-bit ASCII", last_frames=[bytes(line)]) from err
    else:
        text = line
    if len(text) > MAX_LINE:
        raise FramingError(f"LTP line longer than {MAX_LINE} bytes")
    if any(not (" " <= c <= "~") for c in text):
        raise FramingError(
            "LTP line contains control or non-ASCII characters",
            last_frames=[text.encode("ascii", "backslashreplace")],
        )
    return text


def _tokens(text: str) -> list[str]:
    """Split on spaces, keeping double-quoted runs (with escapes) inside one token."""
    tokens: list[str] = []
    cur: list[str] = []
    in_quotes = False
    i = 0
    while i < len(text):
        c = text[i]
        if in_quotes:
            if c == "\\" and i + 1 < len(text) and text[i + 1] in '"\\':
                cur.append(c + text[i + 1])
                i += 2
                continue
            if c == '"':
                in_quotes = False
            cur.append(c)
        elif c == " ":
            if cur:
                tokens.append("".join(cur))
                cur = []
        else:
            if c == '"':
                in_quotes = True
            cur.append(c)
        i += 1
    if in_quotes:
        raise FramingError(f"unterminated quoted value in {text[:80]!r}")
    if cur:
        tokens.append("".join(cur))
    return tokens


def _unquote(raw: str, token: str) -> str:
    if not raw.startswith('"'):
        if not _BARE.fullmatch(raw):
            raise FramingError(f"bad value in {token!r}")
        return raw
    if len(raw) < 2 or not raw.endswith('"'):
        raise FramingError(f"bad quoted value in {token!r}")
    out: list[str] = []
    body = raw[1:-1]
    i = 0
    while i < len(body):
        c = body[i]
        if c == "\\":
            if i + 1 >= len(body) or body[i + 1] not in '"\\':
                raise FramingError(f"bad escape in {token!r}")
            out.append(body[i + 1])
            i += 2
            continue
        if c == '"':
            raise FramingError(f"stray quote in {token!r}")
        out.append(c)
        i += 1
    return "".join(out)


def _pairs(tokens: list[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for token in tokens:
        key, sep, raw = token.partition("=")
        if not sep or not _KEY.fullmatch(key):
            raise FramingError(f"expected key=value, got {token[:80]!r}")
        if key in out:
            raise FramingError(f"duplicate key {key!r}")
        out[key] = _unquote(raw, token)
    return out


def _quote(value: str) -> str:
    if value and _BARE.fullmatch(value):
        return value
    if any(not (" " <= c <= "~") for c in value):
        raise FramingError(f"value {value[:40]!r} is not printable ASCII")
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _format_pairs(values: Mapping[str, object]) -> str:
    parts = []
    for key, value in values.items():
        if not _KEY.fullmatch(key):
            raise FramingError(f"bad key {key!r}")
        parts.append(f"{key}={_quote(str(value))}")
    return "".join(" " + p for p in parts)


def _check_len(line: str) -> str:
    if len(line) > MAX_LINE:
        raise FramingError(f"LTP line would be {len(line)} bytes, more than {MAX_LINE}")
    return line


# --- requests (client -> bridge) ---------------------------------------------------------------
def format_request(req: Request) -> str:
    """Return the request line (without CR LF)."""
    if not _TAG.fullmatch(req.tag):
        raise FramingError(f"bad tag {req.tag!r}: 1..8 alphanumerics")
    if not _VERB.fullmatch(req.verb):
        raise FramingError(f"bad verb {req.verb!r}")
    return _check_len(f"{req.tag} {req.verb}{_format_pairs(req.args)}")


def parse_request(line: bytes | str) -> Request:
    """Parse a request line (the simulator's side).

    Raises
    ------
    FramingError
        If the line is not a well-formed request.
    """
    tokens = _tokens(_text(line))
    if len(tokens) < 2:
        raise FramingError("LTP request needs a tag and a verb")
    tag, verb = tokens[0], tokens[1]
    if not _TAG.fullmatch(tag):
        raise FramingError(f"bad tag {tag[:20]!r}")
    if not _VERB.fullmatch(verb):
        raise FramingError(f"bad verb {verb[:20]!r}")
    return Request(tag, verb, _pairs(tokens[2:]))


# --- replies and events (bridge -> client) ----------------------------------------------------
def format_ok(tag: str, values: Mapping[str, object] | None = None) -> str:
    """Return an ``OK`` reply line."""
    if not _TAG.fullmatch(tag):
        raise FramingError(f"bad tag {tag!r}")
    return _check_len(f"{tag} OK{_format_pairs(values or {})}")


def format_err(tag: str, code: int, name: str | None = None, msg: str | None = None) -> str:
    """Return an ``ERR`` reply line; ``name`` defaults to the table name of ``code``."""
    if not _TAG.fullmatch(tag):
        raise FramingError(f"bad tag {tag!r}")
    if name is None:
        try:
            name = ErrorCode(code).name
        except ValueError:
            name = "INTERNAL"
    if not _NAME.fullmatch(name) or code < 0:
        raise FramingError(f"bad error {code} {name!r}")
    tail = _format_pairs({"msg": msg}) if msg is not None else ""
    return _check_len(f"{tag} ERR {code} {name}{tail}")


def format_event(name: str, values: Mapping[str, object] | None = None) -> str:
    """Return an event line ``* EVT NAME ...``."""
    if not _NAME.fullmatch(name):
        raise FramingError(f"bad event name {name!r}")
    return _check_len(f"* EVT {name}{_format_pairs(values or {})}")


def parse_message(line: bytes | str) -> Message:
    """Parse a reply or event line (the driver's side).

    Raises
    ------
    FramingError
        If the line is not a well-formed reply or event.
    """
    tokens = _tokens(_text(line))
    if len(tokens) < 2:
        raise FramingError("LTP reply needs a tag and a status")
    head, kind = tokens[0], tokens[1]
    if head == "*":
        if kind != "EVT" or len(tokens) < 3 or not _NAME.fullmatch(tokens[2]):
            raise FramingError("malformed LTP event")
        return Event(tokens[2], _pairs(tokens[3:]))
    if not _TAG.fullmatch(head):
        raise FramingError(f"bad tag {head[:20]!r}")
    if kind == "OK":
        return Ok(head, _pairs(tokens[2:]))
    if kind == "ERR":
        if len(tokens) < 4 or not tokens[2].isdigit() or len(tokens[2]) > 6:
            raise FramingError("malformed LTP ERR reply: expected ERR <code> <NAME>")
        if not _NAME.fullmatch(tokens[3]):
            raise FramingError(f"bad error name {tokens[3][:20]!r}")
        extra = _pairs(tokens[4:])
        unknown = set(extra) - {"msg"}
        if unknown:
            raise FramingError(f"unexpected keys in ERR reply: {sorted(unknown)}")
        return Err(head, int(tokens[2]), tokens[3], extra.get("msg"))
    raise FramingError(f"expected OK, ERR or * EVT, got {kind[:20]!r}")
