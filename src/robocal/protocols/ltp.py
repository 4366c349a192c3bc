r"""Sans-I/O codec for LTP/1, the tracker line protocol; normative description in
``docs/protocols/ltp1.md`` (grammar, verbs, error codes, framing, examples).

Wire layout (7-bit ASCII, one message per CR LF line, at most 512 bytes)::

    request  :=  TAG SP VERB *(SP key=value)                      TAG = 1..8 alphanumerics
    reply    :=  TAG SP "OK" *(SP key=value)
              |  TAG SP "ERR" SP CODE SP NAME [SP msg="..."]
    event    :=  "*" SP "EVT" SP NAME *(SP key=value)             unsolicited, any time
    value    :=  bare (printable, no space, no ``"``)  |  ``"`` any printable but ``"`` ``"``

    > 3 MEAS id=P0007 n=20 stab_mm=0.010 stab_ms=500 timeout_ms=8000
    < * EVT BEAM state=LOCKED t=2026-01-05T10:11:12.345Z
    < 3 OK id=P0007 x=1523.40712 y=-210.11930 z=887.00241 sx=0.0021 ... smr=RRR15
    > 4 MEAS id=P0008 timeout_ms=3000
    < 4 ERR 10 BEAM_BROKEN msg="C:\bridge\log.txt: beam interrupted"

Inside quotes there are no escapes: a backslash is an ordinary character, and a value ends
at the next double quote. ``msg`` of an ERR reply is always quoted. Requests are parsed
strictly (single spaces); replies and events leniently (runs of spaces, and an ERR whose
``msg`` is malformed still yields its code). Parsers raise only
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
    "message_text",
    "parse_message",
    "parse_request",
    "readable_tag",
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
_READABLE_TAG = re.compile(r"([A-Za-z0-9]{1,8})(?: |$)")
_ERR_LINE = re.compile(
    r' *(\S+) +ERR +([0-9]{1,6}) +([A-Z][A-Z0-9_]*)(?: +msg=(?:"(.*)"|([!#-~]+)))? *'
)


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


def _tokens(text: str, *, strict: bool) -> list[str]:
    """Split a line into tokens on spaces; a quoted value stays inside its ``key="..."`` token.

    A double quote may only open a value (right after the token's first ``=``); the value
    then runs to the next double quote, which must end the token. Backslash is an ordinary
    character. ``strict`` refuses leading, trailing and doubled spaces (the grammar's single
    SP); the driver's side is lenient about them.
    """
    if strict and (text.startswith(" ") or text.endswith(" ")):
        raise FramingError("tokens must be separated by single spaces")
    tokens: list[str] = []
    i, n = 0, len(text)
    while i < n:
        if text[i] == " ":  # between tokens (spaces inside quotes are consumed below)
            if strict and i + 1 < n and text[i + 1] == " ":
                raise FramingError("tokens must be separated by single spaces")
            i += 1
            continue
        j = i
        while j < n and text[j] != " ":
            if text[j] == '"':
                eq = text.find("=", i, j + 1)
                if eq != j - 1:
                    raise FramingError(f"stray double quote in {text[i : j + 1][:80]!r}")
                close = text.find('"', j + 1)
                if close < 0:
                    raise FramingError(f"unterminated quoted value in {text[i:][:80]!r}")
                j = close + 1
                if j < n and text[j] != " ":
                    raise FramingError(f"a quoted value must end its token: {text[i:][:80]!r}")
                break
            j += 1
        tokens.append(text[i:j])
        i = j
    return tokens


def _unquote(raw: str, token: str) -> str:
    if raw.startswith('"'):
        # _tokens guarantees the closing quote is the token's last character.
        return raw[1:-1]
    if not _BARE.fullmatch(raw):
        raise FramingError(f"bad value in {token[:80]!r}")
    return raw


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


def _quote(value: str, *, force: bool = False) -> str:
    if value and not force and _BARE.fullmatch(value):
        return value
    if '"' in value:
        raise FramingError(
            f"value {value[:40]!r} contains a double quote, which LTP/1 cannot carry"
        )
    if any(not (" " <= c <= "~") for c in value):
        raise FramingError(f"value {value[:40]!r} is not printable ASCII")
    return '"' + value + '"'


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


def message_text(text: str) -> str:
    """Return ``text`` made fit for a quoted ``msg``: ``"`` becomes ``'``, others ``?``."""
    return "".join("'" if c == '"' else c if " " <= c <= "~" else "?" for c in str(text))


# --- requests (client -> bridge) ---------------------------------------------------------------
def format_request(req: Request) -> str:
    """Return the request line (without CR LF)."""
    if not _TAG.fullmatch(req.tag):
        raise FramingError(f"bad tag {req.tag!r}: 1..8 alphanumerics")
    if not _VERB.fullmatch(req.verb):
        raise FramingError(f"bad verb {req.verb!r}")
    return _check_len(f"{req.tag} {req.verb}{_format_pairs(req.args)}")


def parse_request(line: bytes | str) -> Request:
    """Parse a request line (the bridge's side), strictly: single spaces only.

    Raises
    ------
    FramingError
        If the line is not a well-formed request.
    """
    tokens = _tokens(_text(line), strict=True)
    if len(tokens) < 2:
        raise FramingError("LTP request needs a tag and a verb")
    tag, verb = tokens[0], tokens[1]
    if not _TAG.fullmatch(tag):
        raise FramingError(f"bad tag {tag[:20]!r}")
    if not _VERB.fullmatch(verb):
        raise FramingError(f"bad verb {verb[:20]!r}")
    return Request(tag, verb, _pairs(tokens[2:]))


def readable_tag(line: bytes | str) -> str | None:
    """Return the tag of a (possibly malformed or over-long) request line, if one is readable.

    A tag is readable when the line starts with 1..8 alphanumerics followed by a space or
    the end of the line; a bridge answers such a line with a tagged ``ERR 1 SYNTAX``.
    """
    head = line[:10] if isinstance(line, str) else bytes(line[:10]).decode("ascii", "replace")
    m = _READABLE_TAG.match(head)
    return m.group(1) if m else None


# --- replies and events (bridge -> client) ----------------------------------------------------
def format_ok(tag: str, values: Mapping[str, object] | None = None) -> str:
    """Return an ``OK`` reply line."""
    if not _TAG.fullmatch(tag):
        raise FramingError(f"bad tag {tag!r}")
    return _check_len(f"{tag} OK{_format_pairs(values or {})}")


def format_err(tag: str, code: int, name: str | None = None, msg: str | None = None) -> str:
    """Return an ``ERR`` reply line; ``name`` defaults to the table name of ``code``.

    ``msg`` is always sent quoted, as the grammar requires; characters a quoted value cannot
    carry are replaced (see :func:`message_text`) and an over-long text is shortened.
    """
    if not _TAG.fullmatch(tag):
        raise FramingError(f"bad tag {tag!r}")
    if name is None:
        try:
            name = ErrorCode(code).name
        except ValueError:
            name = "INTERNAL"
    if not _NAME.fullmatch(name) or not 0 <= code <= 999_999:
        raise FramingError(f"bad error {code} {name!r}")
    head = f"{tag} ERR {code} {name}"
    if msg is None:
        return head
    room = MAX_LINE - len(head) - len(' msg=""')
    return f'{head} msg="{message_text(msg)[:room]}"'


def format_event(name: str, values: Mapping[str, object] | None = None) -> str:
    """Return an event line ``* EVT NAME ...``."""
    if not _NAME.fullmatch(name):
        raise FramingError(f"bad event name {name!r}")
    return _check_len(f"* EVT {name}{_format_pairs(values or {})}")


def parse_message(line: bytes | str) -> Message:
    """Parse a reply or event line (the client's side), leniently about spacing.

    An ``ERR`` reply is recognised from its code and name even when its ``msg`` is not
    well formed (taken verbatim up to the line's last double quote), so a bridge's error is
    never lost as garbage.

    Raises
    ------
    FramingError
        If the line is not a well-formed reply or event.
    """
    text = _text(line)
    m = _ERR_LINE.fullmatch(text)
    if m is not None:
        tag, code, name, quoted, bare = m.groups()
        if not _TAG.fullmatch(tag):
            raise FramingError(f"bad tag {tag[:20]!r}")
        return Err(tag, int(code), name, quoted if quoted is not None else bare)
    tokens = _tokens(text, strict=False)
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
        raise FramingError('malformed LTP ERR reply: expected ERR <code> <NAME> [msg="..."]')
    raise FramingError(f"expected OK, ERR or * EVT, got {kind[:20]!r}")
