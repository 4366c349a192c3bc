"""Sans-I/O codec for ABB Robot Web Services: RWS 1.0 (RobotWare 6) and RWS 2.0 (RobotWare 7).

What robocal speaks is described in ``docs/protocols/abb-rws.md``. This module builds
requests (method, path, query, form body, headers) and parses answers; the HTTP itself is
done elsewhere (the driver with aiohttp's client, the simulator with aiohttp's server).

Dialects
--------
``rws1`` (RobotWare 6)
    HTTP digest authentication (MD5, ``qop=auth``), then a session cookie (``-http-session-``
    and ``ABBCX``). Answers are XHTML, or JSON with ``?json=1`` (``Content-Type:
    application/json``; the items sit in ``_embedded._state``). Actions are query
    parameters: ``POST /rw/rapid/execution?action=start``. RAPID data:
    ``/rw/rapid/symbol/data/RAPID/<task>/<module>/<name>``.
``rws2`` (RobotWare 7)
    HTTP basic authentication over HTTPS (plain HTTP only in the simulator), then the same
    cookies. Requests carry ``Accept: application/hal+json;v=2.0`` and form bodies
    ``application/x-www-form-urlencoded;v=2.0``; answers list the items under ``state``.
    Actions are path segments: ``POST /rw/rapid/execution/start``. RAPID data:
    ``/rw/rapid/symbol/RAPID/<task>/<module>/<name>/data``.

RAPID values travel as RAPID literals: ``num`` ``12.5``, ``bool`` ``TRUE``, ``string``
``"text"`` and the record ``jointtarget`` ``[[j1,...,j6],[e1,...,e6]]`` (degrees / mm,
``9E+09`` for an unused external axis); arrays are ``[v1,v2,...]``. RAPID ``num`` is a
32-bit float: :func:`format_num` writes the shortest text that reads back as the same
single-precision value.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import html.parser
import json
import math
import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal
from urllib.parse import quote

from robocal.errors import FramingError, UnexpectedReply

__all__ = [
    "EXTAX_UNUSED",
    "FORM_RWS2",
    "JSON_RWS1",
    "JSON_RWS2",
    "REALM",
    "XHTML",
    "Dialect",
    "DigestChallenge",
    "JointTarget",
    "Request",
    "RobTarget",
    "RwsError",
    "basic_authorization",
    "cfg_instances",
    "ctrlstate",
    "digest_authorization",
    "digest_response",
    "elog",
    "execution",
    "format_jointtarget",
    "format_jointtarget_array",
    "format_num",
    "format_string",
    "jointtarget",
    "logout",
    "mastership",
    "motors_on",
    "opmode",
    "parse_authorization",
    "parse_basic",
    "parse_cfg_instances",
    "parse_challenge",
    "parse_error",
    "parse_jointtarget",
    "parse_jointtarget_array",
    "parse_jointtarget_state",
    "parse_num",
    "parse_robtarget_state",
    "parse_states",
    "parse_string",
    "read_symbol",
    "reset_pp",
    "robtarget",
    "single",
    "single_precision",
    "start_execution",
    "stop_execution",
    "symbol_path",
    "write_symbol",
]

Dialect = Literal["rws1", "rws2"]

JSON_RWS1 = "application/json"
JSON_RWS2 = "application/hal+json;v=2.0"
FORM_RWS2 = "application/x-www-form-urlencoded;v=2.0"
XHTML = "application/xhtml+xml"
#: Digest realm of RobotWare 6 controllers.
REALM = "validusers@robapi.abb"
#: RAPID's value for an external axis that does not exist.
EXTAX_UNUSED = 9e9
#: Longest RAPID value text accepted by the parsers (a 500-element jointtarget array is ~60 kB).
MAX_VALUE = 1 << 20


# --- requests ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Request:
    """One RWS request: ``method`` ``path`` (already percent-encoded) with ``query`` and a form
    body ``form`` (both ``(key, value)`` pairs), plus ``headers``."""

    method: Literal["GET", "POST"]
    path: str
    query: tuple[tuple[str, str], ...] = ()
    form: tuple[tuple[str, str], ...] = ()
    headers: tuple[tuple[str, str], ...] = ()

    @property
    def target(self) -> str:
        """Path and query as sent on the request line (and hashed by digest auth)."""
        if not self.query:
            return self.path
        return self.path + "?" + "&".join(f"{quote(k)}={quote(v)}" for k, v in self.query)


def _request(dialect: Dialect, method: Literal["GET", "POST"], path: str,
             query: Sequence[tuple[str, str]] = (),
             form: Sequence[tuple[str, str]] = ()) -> Request:
    if dialect == "rws1":
        return Request(method, path, (*query, ("json", "1")), tuple(form))
    headers: list[tuple[str, str]] = [("Accept", JSON_RWS2)]
    if method == "POST":
        headers.append(("Content-Type", FORM_RWS2))
    return Request(method, path, tuple(query), tuple(form), tuple(headers))


_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}$")


def _rapid_name(name: str, what: str) -> str:
    if not _NAME.match(name):
        raise ValueError(f"{what} {name!r} is not a RAPID name")
    return name


def symbol_path(dialect: Dialect, task: str, module: str | None, name: str) -> str:
    """Path of RAPID data ``name`` in ``task`` (and ``module``; None: looked up in the task)."""
    parts = [_rapid_name(task, "task")]
    if module is not None:
        parts.append(_rapid_name(module, "module"))
    parts.append(_rapid_name(name, "symbol"))
    if dialect == "rws1":
        return "/rw/rapid/symbol/data/RAPID/" + "/".join(parts)
    return "/rw/rapid/symbol/RAPID/" + "/".join(parts) + "/data"


def read_symbol(dialect: Dialect, task: str, module: str | None, name: str) -> Request:
    """GET the value of RAPID data (answer item field ``value``)."""
    return _request(dialect, "GET", symbol_path(dialect, task, module, name))


def write_symbol(dialect: Dialect, task: str, module: str | None, name: str,
                 value: str) -> Request:
    """POST a new value (RAPID literal text) to RAPID data; answer 204."""
    path = symbol_path(dialect, task, module, name)
    if dialect == "rws1":
        return _request(dialect, "POST", path, [("action", "set")], [("value", value)])
    return _request(dialect, "POST", path, form=[("value", value)])


def ctrlstate(dialect: Dialect) -> Request:
    """GET the controller state (field ``ctrlstate``: ``motoron``, ``motoroff``, ...); RWS 2.0
    names the resource ``ctrl-state``."""
    path = "/rw/panel/ctrlstate" if dialect == "rws1" else "/rw/panel/ctrl-state"
    return _request(dialect, "GET", path)


def motors_on(dialect: Dialect, on: bool = True) -> Request:
    """POST motors on (or off); needs the controller in AUTO."""
    state = "motoron" if on else "motoroff"
    if dialect == "rws1":
        return _request(dialect, "POST", "/rw/panel/ctrlstate", [("action", "setctrlstate")],
                        [("ctrl-state", state)])
    return _request(dialect, "POST", "/rw/panel/ctrl-state", form=[("ctrl-state", state)])


def opmode(dialect: Dialect) -> Request:
    """GET the operating mode (field ``opmode``: ``AUTO``, ``MANR``, ``MANF``, ...)."""
    return _request(dialect, "GET", "/rw/panel/opmode")


def execution(dialect: Dialect) -> Request:
    """GET the RAPID execution state (fields ``ctrlexecstate``: ``running``/``stopped``,
    ``cycle``)."""
    return _request(dialect, "GET", "/rw/rapid/execution")


def _exec_action(dialect: Dialect, action: str, form: Sequence[tuple[str, str]]) -> Request:
    if dialect == "rws1":
        return _request(dialect, "POST", "/rw/rapid/execution", [("action", action)], form)
    return _request(dialect, "POST", f"/rw/rapid/execution/{action}", form=form)


def start_execution(dialect: Dialect) -> Request:
    """POST start of the normal RAPID tasks from the program pointer (cycle ``forever``)."""
    return _exec_action(dialect, "start", [
        ("regain", "continue"), ("execmode", "continue"), ("cycle", "forever"),
        ("condition", "none"), ("stopatbp", "disabled"), ("alltaskbytsp", "false"),
    ])


def stop_execution(dialect: Dialect) -> Request:
    """POST stop of RAPID execution (``stopmode=stop``: the robot halts on its path)."""
    return _exec_action(dialect, "stop", [("stopmode", "stop"), ("usetsp", "normal")])


def reset_pp(dialect: Dialect) -> Request:
    """POST program pointer to main."""
    return _exec_action(dialect, "resetpp", [])


def mastership(dialect: Dialect, action: Literal["request", "release"]) -> Request:
    """POST a request for (or release of) RAPID edit mastership."""
    if dialect == "rws1":
        return _request(dialect, "POST", "/rw/mastership/edit", [("action", action)])
    return _request(dialect, "POST", f"/rw/mastership/edit/{action}")


def jointtarget(dialect: Dialect, mechunit: str = "ROB_1") -> Request:
    """GET the mechanical unit's actual joints (``rax_1``..``rax_6``, degrees)."""
    return _request(dialect, "GET",
                    f"/rw/motionsystem/mechunits/{_rapid_name(mechunit, 'mechunit')}/jointtarget")


def robtarget(dialect: Dialect, mechunit: str = "ROB_1", *, tool: str = "tool0",
              wobj: str = "wobj0", coordinate: str = "Base") -> Request:
    """GET the TCP pose (``x y z`` mm, quaternion ``q1..q4``, configuration ``cf1 cf4 cf6
    cfx``)."""
    return _request(
        dialect, "GET",
        f"/rw/motionsystem/mechunits/{_rapid_name(mechunit, 'mechunit')}/robtarget",
        [("tool", tool), ("wobj", wobj), ("coordinate", coordinate)])


def elog(dialect: Dialect, domain: int = 0) -> Request:
    """GET the event-log messages of ``domain`` (newest first; fields ``code``, ``title``)."""
    return _request(dialect, "GET", f"/rw/elog/{int(domain)}", [("lang", "en")])


_CFG_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,63}$")


def cfg_instances(dialect: Dialect, domain: str, cfg_type: str,
                  instance: str | None = None) -> Request:
    """GET the instances of configuration type ``cfg_type`` in ``domain`` (``MOC``, ``SYS``,
    ...), or the one named ``instance``: items ``cfg-dt-instance-li`` titled with the
    instance's name, its attributes in ``attrib`` (:func:`parse_cfg_instances`)."""
    names = [domain, cfg_type] + ([] if instance is None else [instance])
    for n in names:
        if not _CFG_NAME.match(n):
            raise ValueError(f"{n!r} is not a configuration name")
    path = f"/rw/cfg/{domain}/{cfg_type}/instances"
    return _request(dialect, "GET", path if instance is None else f"{path}/{instance}")


def parse_cfg_instances(items: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, str]]:
    """Instance name -> attribute name -> value text, from :func:`cfg_instances` items.

    Raises
    ------
    UnexpectedReply
        An instance item without a name or with malformed attributes.
    """
    out: dict[str, dict[str, str]] = {}
    for item in items:
        if item.get("_type") != "cfg-dt-instance-li":
            continue
        name, attrib = item.get("_title"), item.get("attrib", [])
        if not isinstance(name, str) or not isinstance(attrib, list):
            raise UnexpectedReply(f"malformed configuration instance: {dict(item)!r}"[:300])
        attrs: dict[str, str] = {}
        for a in attrib:
            if not isinstance(a, dict) or not isinstance(a.get("_title"), str):
                raise UnexpectedReply(f"malformed configuration attribute: {a!r}"[:300])
            attrs[a["_title"]] = str(a.get("value", ""))
        out[name] = attrs
    return out


def logout(dialect: Dialect) -> Request:
    """GET ``/logout``: ends the session (frees one of the controller's session slots)."""
    return _request(dialect, "GET", "/logout")


# --- answers -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class RwsError:
    """An error answer: HTTP ``status``, controller ``code`` (negative, 0 if absent), text."""

    status: int
    code: int
    message: str


class _XhtmlItems(html.parser.HTMLParser):
    """Collects ``<li class=T title=N>`` items and their ``<span class=K>V</span>`` fields."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.items: list[dict[str, str]] = []
        self._span: str | None = None
        self._text: list[str] = []
        self._depth = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if tag == "li" and "class" in a:
            self.items.append({"_type": a["class"], "_title": a.get("title", "")})
        elif tag == "span" and "class" in a and self.items:
            self._span, self._text = a["class"], []

    def handle_endtag(self, tag: str) -> None:
        if tag == "span" and self._span is not None:
            self.items[-1][self._span] = "".join(self._text)
            self._span = None

    def handle_data(self, data: str) -> None:
        if self._span is not None:
            self._text.append(data)


def _strings(item: Mapping[str, Any]) -> dict[str, Any]:
    return {str(k): (v if isinstance(v, list | dict) else str(v)) for k, v in item.items()
            if not str(k).startswith("_links")}


def parse_states(body: bytes, content_type: str) -> list[dict[str, Any]]:
    """Return the state items of an answer (each a dict of strings, with ``_type``).

    RWS 1.0 JSON lists them in ``_embedded._state``, RWS 2.0 in ``state``; XHTML answers
    as ``<li class=type>`` items of ``<span class=field>`` values.

    Raises
    ------
    FramingError
        The body is not JSON/XHTML of that shape.
    """
    ctype = content_type.split(";", 1)[0].strip().lower()
    if len(body) > MAX_VALUE * 2:
        raise FramingError(f"RWS answer of {len(body)} bytes is too long")
    if ctype in ("application/xhtml+xml", "text/html"):
        parser = _XhtmlItems()
        try:
            parser.feed(body.decode("utf-8"))
            parser.close()
        except (UnicodeDecodeError, AssertionError) as err:
            raise FramingError(f"RWS XHTML answer is not parseable: {err}") from err
        return parser.items
    try:
        doc = json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise FramingError(f"RWS answer is not JSON: {err}") from err
    if not isinstance(doc, dict):
        raise FramingError("RWS answer is not a JSON object")
    embedded = doc.get("_embedded")
    if isinstance(embedded, dict) and "_state" in embedded:
        items = embedded["_state"]
    elif "state" in doc:
        items = doc["state"]
    else:
        raise FramingError("RWS answer has neither _embedded._state nor state")
    if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
        raise FramingError("RWS answer's state is not a list of objects")
    return [_strings(i) for i in items]


def single(items: Sequence[Mapping[str, Any]], field: str) -> str:
    """Return ``field`` of the first item.

    Raises
    ------
    UnexpectedReply
        No item, or the field is missing or not text.
    """
    if not items:
        raise UnexpectedReply(f"RWS answer has no item (wanted {field!r})")
    value = items[0].get(field)
    if not isinstance(value, str):
        raise UnexpectedReply(f"RWS answer item lacks {field!r}: {dict(items[0])!r}"[:300])
    return value


def parse_error(status: int, body: bytes, content_type: str) -> RwsError:
    """Read the controller's error code and message from an error answer (best effort)."""
    code, message = 0, ""
    ctype = content_type.split(";", 1)[0].strip().lower()
    try:
        if ctype in ("application/xhtml+xml", "text/html"):
            parser = _XhtmlItems()
            parser.feed(body.decode("utf-8", "replace"))
            for item in parser.items:
                if "code" in item:
                    code = int(item["code"])
                    message = item.get("msg", "")
                    break
        else:
            doc = json.loads(body) if body else {}
            st = doc.get("_embedded", {}).get("status") or doc.get("status") or {}
            code = int(st.get("code", 0))
            message = str(st.get("msg", ""))
    except (ValueError, AttributeError, TypeError):
        pass
    return RwsError(status, code, message or f"HTTP {status}")


# --- motion-system answers -----------------------------------------------------------------------
@dataclass(frozen=True)
class JointTarget:
    """Robot axes ``robax`` (6, degrees) and external axes ``extax`` (6; ``9E+09`` unused)."""

    robax: tuple[float, ...]
    extax: tuple[float, ...] = (EXTAX_UNUSED,) * 6


@dataclass(frozen=True)
class RobTarget:
    """TCP position ``trans`` (mm), orientation quaternion ``rot`` (``q1`` = w first) and the
    configuration ``robconf`` (``cf1 cf4 cf6 cfx``)."""

    trans: tuple[float, float, float]
    rot: tuple[float, float, float, float]
    robconf: tuple[int, int, int, int] = (0, 0, 0, 0)
    extax: tuple[float, ...] = field(default=(EXTAX_UNUSED,) * 6)


def _float(item: Mapping[str, Any], key: str) -> float:
    try:
        v = float(item[key])
    except (KeyError, TypeError, ValueError) as err:
        raise UnexpectedReply(f"RWS item lacks a number {key!r}") from err
    if not math.isfinite(v):
        raise UnexpectedReply(f"RWS item's {key!r} is not finite")
    return v


def parse_jointtarget_state(items: Sequence[Mapping[str, Any]], dof: int = 6) -> tuple[float, ...]:
    """Joint angles (degrees, ``dof`` of them) of a ``ms-jointtarget`` answer."""
    if not items:
        raise UnexpectedReply("jointtarget answer has no item")
    item = items[0]
    if item.get("_type") != "ms-jointtarget":
        raise UnexpectedReply(f"expected ms-jointtarget, got {item.get('_type')!r}")
    return tuple(_float(item, f"rax_{i + 1}") for i in range(dof))


def parse_robtarget_state(items: Sequence[Mapping[str, Any]]) -> RobTarget:
    """The pose of a ``ms-robtargets`` answer."""
    if not items:
        raise UnexpectedReply("robtarget answer has no item")
    item = items[0]
    if item.get("_type") != "ms-robtargets":
        raise UnexpectedReply(f"expected ms-robtargets, got {item.get('_type')!r}")
    x, y, z = (_float(item, k) for k in "xyz")
    q = tuple(_float(item, f"q{i}") for i in range(1, 5))
    cf = tuple(int(_float(item, k)) for k in ("cf1", "cf4", "cf6", "cfx"))
    return RobTarget((x, y, z), q, cf)  # type: ignore[arg-type]


# --- RAPID literals ------------------------------------------------------------------------------
def single_precision(v: float) -> float:
    """``v`` rounded to IEEE single precision (what a RAPID ``num`` holds)."""
    try:
        f = float(struct.unpack("<f", struct.pack("<f", v))[0])
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise ValueError(f"{v!r} is not a RAPID num")
    return f


def format_num(v: float) -> str:
    """RAPID text of ``v`` as a ``num``: the shortest that reads back as the same single."""
    f = single_precision(v)
    if f == 0.0:
        return "0"
    for digits in range(1, 10):
        text = f"{f:.{digits}G}"
        with contextlib.suppress(ValueError):  # rounded up beyond the largest single
            if single_precision(float(text)) == f:
                break
    mant, _, exp = text.partition("E")
    if exp:
        return f"{mant}E{int(exp):+03d}"
    return mant


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUM_RE = re.compile(rf"^\s*({_NUM})\s*$")


def parse_num(text: str) -> float:
    """A RAPID ``num`` literal as float; raise FramingError otherwise."""
    m = _NUM_RE.match(text)
    if not m:
        raise FramingError(f"not a RAPID num: {text[:40]!r}")
    return float(m.group(1))


def format_string(text: str) -> str:
    """RAPID ``string`` literal (quotes and backslashes doubled; at most 80 characters)."""
    if len(text) > 80 or any(ord(c) < 32 or ord(c) > 126 for c in text):
        raise ValueError("a RAPID string holds at most 80 printable ASCII characters")
    return '"' + text.replace("\\", "\\\\").replace('"', '""') + '"'


def parse_string(text: str) -> str:
    """The text of a RAPID ``string`` literal."""
    t = text.strip()
    if len(t) < 2 or t[0] != '"' or t[-1] != '"':
        raise FramingError(f"not a RAPID string: {text[:40]!r}")
    inner = t[1:-1]
    if re.search(r'(?<!")"(?!")', inner.replace('""', "")):
        raise FramingError(f"unescaped quote in RAPID string: {text[:40]!r}")
    return inner.replace('""', '"').replace("\\\\", "\\")


def format_jointtarget(robax: Sequence[float],
                       extax: Sequence[float] = (EXTAX_UNUSED,) * 6) -> str:
    """RAPID ``jointtarget`` literal; ``robax`` (up to 6, degrees) padded with zeros."""
    if len(robax) > 6 or len(extax) != 6:
        raise ValueError("a jointtarget has 6 robot and 6 external axes")
    rob = [*robax, *([0.0] * (6 - len(robax)))]
    return ("[[" + ",".join(format_num(v) for v in rob) + "],["
            + ",".join(format_num(v) for v in extax) + "]]")


_SIX = rf"((?:\s*{_NUM}\s*,){{5}}\s*{_NUM}\s*)"
_JT = rf"\[\s*\[{_SIX}\]\s*,\s*\[{_SIX}\]\s*\]"
_JT_RE = re.compile(rf"^\s*{_JT}\s*$")
_JT_ITEM = re.compile(rf"\s*{_JT}\s*(,|$)")


def _six(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(","))


def parse_jointtarget(text: str) -> JointTarget:
    """A RAPID ``jointtarget`` literal; raise FramingError otherwise."""
    m = _JT_RE.match(text)
    if not m:
        raise FramingError(f"not a RAPID jointtarget: {text[:60]!r}")
    return JointTarget(_six(m.group(1)), _six(m.group(2)))


def format_jointtarget_array(items: Sequence[JointTarget]) -> str:
    """RAPID array literal of jointtargets."""
    return "[" + ",".join(format_jointtarget(t.robax, t.extax) for t in items) + "]"


def parse_jointtarget_array(text: str) -> list[JointTarget]:
    """A RAPID array of ``jointtarget`` literals; raise FramingError otherwise."""
    if len(text) > MAX_VALUE:
        raise FramingError("RAPID value too long")
    t = text.strip()
    if len(t) < 2 or t[0] != "[" or t[-1] != "]":
        raise FramingError(f"not a RAPID array: {text[:60]!r}")
    inner, pos = t[1:-1], 0
    out: list[JointTarget] = []
    if not inner.strip():
        return out
    while pos < len(inner):
        m = _JT_ITEM.match(inner, pos)
        if not m:
            raise FramingError(f"bad jointtarget array element at {pos}: {inner[pos:pos + 60]!r}")
        out.append(JointTarget(_six(m.group(1)), _six(m.group(2))))
        pos = m.end()
        if m.group(3) == "" and pos < len(inner):
            raise FramingError("jointtarget array element without a separator")
    return out


# --- authentication ------------------------------------------------------------------------------
@dataclass(frozen=True)
class DigestChallenge:
    """A ``WWW-Authenticate: Digest`` challenge (RFC 7616; RobotWare uses MD5, qop auth)."""

    realm: str
    nonce: str
    qop: str | None = "auth"
    opaque: str | None = None
    algorithm: str = "MD5"

    def header(self) -> str:
        """The ``WWW-Authenticate`` header value."""
        parts = [f'realm="{self.realm}"', f'nonce="{self.nonce}"']
        if self.qop:
            parts.append(f'qop="{self.qop}"')
        if self.opaque is not None:
            parts.append(f'opaque="{self.opaque}"')
        parts.append(f"algorithm={self.algorithm}")
        return "Digest " + ", ".join(parts)


_PARAM = re.compile(r'\s*([A-Za-z0-9_-]+)\s*=\s*(?:"((?:[^"\\]|\\.)*)"|([^\s,]+))\s*,?')


def _params(text: str) -> dict[str, str]:
    out: dict[str, str] = {}
    pos = 0
    while pos < len(text):
        m = _PARAM.match(text, pos)
        if not m:
            raise FramingError(f"bad auth parameter list at {pos}: {text[pos:pos + 40]!r}")
        value = m.group(2) if m.group(2) is not None else m.group(3)
        out[m.group(1).lower()] = re.sub(r"\\(.)", r"\1", value)
        pos = m.end()
    return out


def parse_challenge(header: str) -> DigestChallenge:
    """Parse a ``WWW-Authenticate: Digest ...`` value; FramingError if it is not one."""
    scheme, _, rest = header.strip().partition(" ")
    if scheme.lower() != "digest":
        raise FramingError(f"not a digest challenge: {header[:40]!r}")
    p = _params(rest)
    if "realm" not in p or "nonce" not in p:
        raise FramingError("digest challenge lacks realm or nonce")
    algorithm = p.get("algorithm", "MD5")
    if algorithm.upper() != "MD5":
        raise FramingError(f"digest algorithm {algorithm!r} is not supported (MD5 only)")
    qops = [q.strip() for q in p.get("qop", "").split(",") if q.strip()]
    if qops and "auth" not in qops:
        raise FramingError(f"digest qop {p['qop']!r} offers no 'auth'")
    return DigestChallenge(p["realm"], p["nonce"], "auth" if qops else None, p.get("opaque"),
                           algorithm)


def _md5(text: str) -> str:
    return hashlib.md5(text.encode("utf-8"), usedforsecurity=False).hexdigest()


def digest_response(*, username: str, password: str, realm: str, nonce: str, method: str,
                    uri: str, qop: str | None, nc: str = "", cnonce: str = "") -> str:
    """The 32-hex-digit ``response`` of RFC 2617/7616 (MD5)."""
    ha1 = _md5(f"{username}:{realm}:{password}")
    ha2 = _md5(f"{method}:{uri}")
    if qop:
        return _md5(f"{ha1}:{nonce}:{nc}:{cnonce}:{qop}:{ha2}")
    return _md5(f"{ha1}:{nonce}:{ha2}")


def digest_authorization(challenge: DigestChallenge, *, username: str, password: str,
                         method: str, uri: str, nc: int, cnonce: str) -> str:
    """The ``Authorization`` header answering ``challenge`` for request ``method uri``."""
    nc_text = f"{nc:08x}"
    resp = digest_response(username=username, password=password, realm=challenge.realm,
                           nonce=challenge.nonce, method=method, uri=uri, qop=challenge.qop,
                           nc=nc_text, cnonce=cnonce)
    parts = [f'username="{username}"', f'realm="{challenge.realm}"',
             f'nonce="{challenge.nonce}"', f'uri="{uri}"', f'response="{resp}"',
             f"algorithm={challenge.algorithm}"]
    if challenge.qop:
        parts += [f"qop={challenge.qop}", f"nc={nc_text}", f'cnonce="{cnonce}"']
    if challenge.opaque is not None:
        parts.append(f'opaque="{challenge.opaque}"')
    return "Digest " + ", ".join(parts)


def parse_authorization(header: str) -> tuple[str, dict[str, str]]:
    """Split an ``Authorization`` value into its scheme (lower case) and parameters.

    For ``Basic`` the single parameter ``token`` holds the base64 text.
    """
    scheme, _, rest = header.strip().partition(" ")
    scheme = scheme.lower()
    if scheme == "basic":
        return scheme, {"token": rest.strip()}
    if scheme == "digest":
        return scheme, _params(rest)
    raise FramingError(f"unsupported authorization scheme {scheme!r}")


def basic_authorization(username: str, password: str) -> str:
    """``Authorization: Basic`` value (RWS 2.0)."""
    token = base64.b64encode(f"{username}:{password}".encode()).decode("ascii")
    return "Basic " + token


def parse_basic(token: str) -> tuple[str, str]:
    """User and password of a basic token; FramingError if malformed."""
    try:
        user, sep, password = base64.b64decode(token, validate=True).decode("utf-8").partition(":")
    except (ValueError, UnicodeDecodeError) as err:
        raise FramingError("malformed basic credentials") from err
    if not sep:
        raise FramingError("basic credentials without ':'")
    return user, password
