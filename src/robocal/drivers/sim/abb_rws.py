"""An ABB IRC5 / OmniCore controller simulator speaking Robot Web Services
(docs/protocols/abb-rws.md): RWS 1.0 of RobotWare 6 or RWS 2.0 of RobotWare 7, chosen by
:attr:`AbbSimOptions.robotware`.

An aiohttp server on a real loopback socket. RobotWare 6: HTTP digest authentication (MD5,
qop auth), XHTML answers, JSON with ``?json=1``, actions as ``?action=``. RobotWare 7: basic
authentication (over plain HTTP here; a real OmniCore serves HTTPS only), HAL JSON
``application/hal+json;v=2.0`` answers, ``application/x-www-form-urlencoded;v=2.0`` bodies,
actions as path segments. Both hand out the ``-http-session-`` and ``ABBCX`` cookies after a
successful login, accept either the cookie or fresh credentials afterwards, and limit the
number of sessions (503 beyond).

Task ``T_ROB1`` holds the module ``RobocalServer`` whose source ships in
``deploy/abb/RobocalServer.mod``; the simulator runs its behaviour when execution is started:
``main`` sets ``rc_done := rc_seq`` (a fresh start drops a pending command), then loops: wait
until ``rc_seq <> rc_done``, ``MoveAbsJ rc_target`` at ``rc_speed`` percent, ``rc_done :=
rc_seq``. A stop (``stopmode=stop``) halts the robot where it is and leaves the program
pointer in the move (starting again finishes it; ``resetpp`` drops it). A target outside the
joint limits, or an injected alarm, stops execution with an event-log entry.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import secrets
import ssl
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from html import escape
from typing import Any, Literal

import numpy as np
import structlog
from aiohttp import web
from pydantic import BaseModel, ConfigDict, Field

from robocal.drivers.sim.faults import FaultConfig, FaultInjector
from robocal.drivers.sim.world import SimWorld
from robocal.errors import FramingError
from robocal.protocols import abb_rws as rws

__all__ = ["AbbRwsSimulator", "AbbSimOptions", "RapidSymbol"]

_log = structlog.get_logger(__name__)

#: Error codes the simulator answers with (RWS reports HRESULT-like negative numbers).
ERR_NOT_FOUND = -1073445860
ERR_MOTORS_OFF = -1073445853
ERR_NOT_AUTO = -1073445847
ERR_MASTERSHIP = -1073445851
ERR_BAD_VALUE = -1073445862
ERR_SESSIONS = -1073445876


class AbbSimOptions(BaseModel):
    """Behaviour of the simulated controller.

    ``time_scale`` multiplies motion times (0 = instantaneous, 1 = real time).
    ``max_joint_speed_deg_s`` is the joint speed at 100 % ``rc_speed`` and 100 % speed ratio.
    ``comp_size`` is the length of the ``rc_comp`` array (as declared in the module).
    ``max_sessions`` sessions are held at once (503 beyond); one unused for
    ``session_idle_s`` seconds ends. ``absolute_accuracy`` loads the robot calibration
    ``r1_calib`` (the Absolute Accuracy data) instead of ``r1_uncalib``; ``cal_offset_rad``
    are the motors' calibration offsets (``MOTOR_CALIB``), radians.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    robotware: Literal[6, 7] = 6
    time_scale: float = Field(default=0.001, ge=0.0)
    username: str | None = None
    password: str = "robotics"
    opmode: Literal["AUTO", "MANR", "MANF"] = "AUTO"
    motors_on: bool = False
    max_sessions: int = Field(default=70, ge=1)
    session_idle_s: float = Field(default=600.0, gt=0.0)
    max_joint_speed_deg_s: float = Field(default=180.0, gt=0.0)
    min_motion_s: float = Field(default=0.012, ge=0.0)
    comp_size: int = Field(default=500, ge=1, le=5000)
    task: str = "T_ROB1"
    module: str = "RobocalServer"
    absolute_accuracy: bool = False
    cal_offset_rad: tuple[float, ...] = (0.3175, 5.6023, 2.1234, 4.9871, 1.0296, 3.3389)

    @property
    def user(self) -> str:
        """The accepted user name (RobotWare 6 ``Default User``, 7 ``Admin``)."""
        if self.username is not None:
            return self.username
        return "Default User" if self.robotware == 6 else "Admin"


@dataclass
class RapidSymbol:
    """A RAPID data symbol: ``dattyp`` (``num``, ``string``, ``jointtarget``), ``dims``
    (array length, 0 for a scalar), storage ``symtyp`` (``per``/``var``) and its ``value``
    as the controller prints it."""

    module: str
    name: str
    dattyp: str
    value: str
    dims: int = 0
    symtyp: str = "per"

    def assign(self, text: str) -> None:
        """Parse ``text`` as this symbol's type and keep the controller's rendering of it.

        Raises
        ------
        FramingError
            ``text`` is not a value of the symbol's type (and length).
        """
        if self.dims:
            if self.dattyp != "jointtarget":
                raise FramingError(f"arrays of {self.dattyp} are not simulated")
            items = rws.parse_jointtarget_array(text)
            if len(items) != self.dims:
                raise FramingError(f"{self.name} has {self.dims} elements, got {len(items)}")
            self.value = rws.format_jointtarget_array(
                [rws.JointTarget(t.robax, t.extax) for t in items])
        elif self.dattyp == "num":
            self.value = rws.format_num(rws.parse_num(text))
        elif self.dattyp == "string":
            self.value = rws.format_string(rws.parse_string(text))
        elif self.dattyp == "jointtarget":
            t = rws.parse_jointtarget(text)
            self.value = rws.format_jointtarget(t.robax, t.extax)
        else:
            raise FramingError(f"type {self.dattyp} is not simulated")


def _server_symbols(module: str, comp_size: int) -> dict[str, RapidSymbol]:
    zero = rws.format_jointtarget([0.0] * 6)
    syms = [
        RapidSymbol(module, "rc_seq", "num", "0"),
        RapidSymbol(module, "rc_done", "num", "0"),
        RapidSymbol(module, "rc_speed", "num", "10"),
        RapidSymbol(module, "rc_target", "jointtarget", zero),
        RapidSymbol(module, "rc_comp", "jointtarget", "[" + ",".join([zero] * comp_size) + "]",
                    dims=comp_size),
        RapidSymbol(module, "rc_comp_n", "num", "0"),
        RapidSymbol(module, "rc_comp_kind", "string", '""'),
        RapidSymbol(module, "rc_comp_sum", "string", '""'),
    ]
    return {s.name.lower(): s for s in syms}


class _Fail(Exception):
    """An RWS error answer."""

    def __init__(self, status: int, code: int, msg: str) -> None:
        super().__init__(msg)
        self.status, self.code, self.msg = status, code, msg


@dataclass
class _Session:
    sid: str
    abbcx: str
    last_used: float = field(default_factory=time.monotonic)


@dataclass(frozen=True)
class ElogEntry:
    """An event-log message: ``code`` and ``title``."""

    seqnum: int
    code: int
    title: str


class AbbRwsSimulator:
    """The controller: panel, RAPID execution, the RobocalServer module, motion system.

    Attributes
    ----------
    requests : int
        Number of requests that reached a resource (after authentication).
    received : deque of (method, path and query)
        The last 1000 of them.
    symbols : dict
        RAPID data of the server module, by lower-case name.
    elog : list of ElogEntry
        Event-log messages (motion errors).
    """

    def __init__(self, world: SimWorld, options: AbbSimOptions | None = None,
                 faults: FaultConfig | None = None) -> None:
        self.world = world
        self.options = options or AbbSimOptions()
        self.faults = FaultInjector(faults)
        o = self.options
        self.dialect: rws.Dialect = "rws1" if o.robotware == 6 else "rws2"
        self.ctrlstate = "motoron" if o.motors_on else "motoroff"
        self.opmode: str = o.opmode
        self.execstate = "stopped"
        self.speedratio = 100
        self.symbols = _server_symbols(o.module, o.comp_size)
        #: the configuration database: domain -> type -> instance -> attribute -> value text
        self.cfg: dict[str, dict[str, dict[str, dict[str, str]]]] = {"MOC": {
            "ROBOT": {"ROB_1": {
                "name": "ROB_1", "use_robot_serial_number": "rob_1",
                "use_robot_type": "ROB1_SIM", "use_joint_0": "rob1_1",
                "use_robot_calib": "r1_calib" if o.absolute_accuracy else "r1_uncalib"}},
            "MOTOR_CALIB": {f"rob1_{i}": {
                "name": f"rob1_{i}", "cal_offset": f"{v:.6f}", "valid_cal_offset": "TRUE",
                "com_offset": "1.570796", "valid_com_offset": "TRUE"}
                for i, v in enumerate(o.cal_offset_rad, 1)}}}
        self.requests = 0
        self.received: deque[tuple[str, str]] = deque(maxlen=1000)
        self.elog: list[ElogEntry] = []
        self.port = 0
        self.host = "127.0.0.1"
        self.scheme = "http"
        # program pointer: "main" (start of main), "wait" (in the WaitUntil) or "move"
        self.pp: Literal["main", "wait", "move"] = "main"
        self._program: asyncio.Task[None] | None = None
        self._changed = asyncio.Event()
        self._sessions: dict[str, _Session] = {}
        self._nonces: dict[str, set[int]] = {}
        self._master: str | None = None
        self._runner: web.AppRunner | None = None
        self._abbcx = 0
        lim = np.asarray(world.joint_limits_rad)
        self._limits_deg = np.degrees(lim)

    # --- lifecycle -------------------------------------------------------------------------------
    async def start(self, host: str = "127.0.0.1", port: int = 0,
                    ssl_context: ssl.SSLContext | None = None) -> None:
        """Listen on ``host:port`` (0: a free port); HTTPS with ``ssl_context``."""
        app = web.Application(client_max_size=4 << 20)
        app.router.add_route("*", "/{tail:.*}", self._handle)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False,
                                     shutdown_timeout=0.5)
        await self._runner.setup()
        site = web.TCPSite(self._runner, host, port, ssl_context=ssl_context)
        self.scheme = "https" if ssl_context is not None else "http"
        await site.start()
        self.host = host
        self.port = int(self._runner.addresses[0][1])
        _log.info("abb rws sim listening", host=host, port=self.port,
                  robotware=self.options.robotware)

    async def stop(self) -> None:
        """Stop the program and the server; idempotent."""
        self._halt_now()
        await self._halt_program()
        if self._runner is not None:
            runner, self._runner = self._runner, None
            await runner.cleanup()

    @property
    def base_url(self) -> str:
        """``http(s)://host:port`` of the running server."""
        return f"{self.scheme}://{self.host}:{self.port}"

    # --- HTTP plumbing ---------------------------------------------------------------------------
    async def _handle(self, request: web.Request) -> web.StreamResponse:
        try:
            new_session = self._authenticate(request)
            self.requests += 1
            self.received.append((request.method, request.path_qs))
            if self.faults.fire("slow"):
                await asyncio.sleep(self.faults.config.slow_s)
            self._check_accept(request)
            form: Mapping[str, str] = {}
            if request.method == "POST":
                self._check_content_type(request)
                form = dict(await request.post())  # type: ignore[arg-type]
            result = await self._route(request, form)
        except _Fail as fail:
            return self._error(request, fail)
        response = self._render(request, result)
        if new_session is not None:
            response.set_cookie("-http-session-", new_session.sid, path="/", httponly=True)
            response.set_cookie("ABBCX", new_session.abbcx, path="/")
        return response

    def _check_accept(self, request: web.Request) -> None:
        accept = request.headers.get("Accept", "*/*").replace(" ", "")
        if self.dialect == "rws2" and "*/*" not in accept and "v=2.0" not in accept:
            raise _Fail(406, ERR_BAD_VALUE,
                        "RWS 2.0 answers application/hal+json;v=2.0 (or xhtml+xml;v=2.0) only")

    def _check_content_type(self, request: web.Request) -> None:
        if self.dialect == "rws2" and request.can_read_body:
            ctype = request.headers.get("Content-Type", "")
            if "v=2.0" not in ctype.replace(" ", ""):
                raise _Fail(415, ERR_BAD_VALUE,
                            "RWS 2.0 needs Content-Type application/x-www-form-urlencoded;v=2.0")

    def _authenticate(self, request: web.Request) -> _Session | None:
        """Accept a session cookie or credentials; a new session on good credentials."""
        now = time.monotonic()
        sid = request.cookies.get("-http-session-")
        if sid is not None and sid in self._sessions:
            self._sessions[sid].last_used = now
            return None
        header = request.headers.get("Authorization")
        if header is None:
            raise self._challenge()
        try:
            scheme, params = rws.parse_authorization(header)
        except FramingError as err:
            raise self._challenge() from err
        if not self._credentials_ok(request, scheme, params):
            raise self._challenge()
        idle = [k for k, v in self._sessions.items()
                if now - v.last_used > self.options.session_idle_s]
        for k in idle:
            self._sessions.pop(k)
            if self._master == k:
                self._master = None
        if len(self._sessions) >= self.options.max_sessions:
            raise _Fail(503, ERR_SESSIONS, "too many sessions")
        self._abbcx += 1
        session = _Session(secrets.token_hex(16), str(self._abbcx))
        self._sessions[session.sid] = session
        return session

    def _credentials_ok(self, request: web.Request, scheme: str, params: Mapping[str, str]) -> bool:
        o = self.options
        if self.dialect == "rws2":
            if scheme != "basic":
                return False
            try:
                user, password = rws.parse_basic(params["token"])
            except FramingError:
                return False
            return user == o.user and password == o.password
        if scheme != "digest":
            return False
        nonce = params.get("nonce", "")
        if nonce not in self._nonces or params.get("username") != o.user:
            return False
        if params.get("uri") != request.raw_path:
            return False
        qop = params.get("qop")
        try:
            nc = int(params.get("nc", "0"), 16)
        except ValueError:
            return False
        if qop is not None and (qop != "auth" or nc in self._nonces[nonce]):
            return False  # a replayed nonce count
        expected = rws.digest_response(
            username=o.user, password=o.password, realm=rws.REALM, nonce=nonce,
            method=request.method, uri=params.get("uri", ""), qop=qop, nc=params.get("nc", ""),
            cnonce=params.get("cnonce", ""))
        if not secrets.compare_digest(expected, params.get("response", "")):
            return False
        self._nonces[nonce].add(nc)
        return True

    def _challenge(self) -> _Fail:
        fail = _Fail(401, 0, "authentication required")
        if self.dialect == "rws2":
            fail.challenge = 'Basic realm="validusers@robapi.abb"'  # type: ignore[attr-defined]
        else:
            nonce = secrets.token_hex(16)
            if len(self._nonces) > 1000:
                self._nonces.clear()
            self._nonces[nonce] = set()
            fail.challenge = rws.DigestChallenge(  # type: ignore[attr-defined]
                rws.REALM, nonce, "auth", secrets.token_hex(8)).header()
        return fail

    def _json_wanted(self, request: web.Request) -> bool:
        return self.dialect == "rws2" or request.query.get("json") == "1"

    def _render(self, request: web.Request, result: tuple[str, list[dict[str, Any]]] | None
                ) -> web.Response:
        if result is None:
            return web.Response(status=204)
        base, items = result
        host = request.host
        if self.dialect == "rws2":
            doc = {"_links": {"base": {"href": f"http://{host}{base}"}}, "state": items}
            return web.Response(body=json.dumps(doc).encode(),
                                headers={"Content-Type": rws.JSON_RWS2})
        if request.query.get("json") == "1":
            doc = {"_links": {"base": {"href": f"http://{host}{base}"}},
                   "_embedded": {"_state": items}}
            # exactly "application/json": abb-robot-client compares the whole header value
            return web.Response(body=json.dumps(doc).encode(),
                                headers={"Content-Type": rws.JSON_RWS1})
        lis = [_xhtml_item(item) for item in items]
        page = ('<?xml version="1.0" encoding="utf-8"?><html xmlns="http://www.w3.org/1999/xhtml">'
                f'<head><base href="http://{escape(host)}{escape(base)}"/></head><body>'
                f'<div class="state"><ul>{"".join(lis)}</ul></div></body></html>')
        return web.Response(body=page.encode(), headers={"Content-Type": rws.XHTML})

    def _error(self, request: web.Request, fail: _Fail) -> web.Response:
        headers: dict[str, str] = {}
        challenge = getattr(fail, "challenge", None)
        if challenge:
            headers["WWW-Authenticate"] = challenge
        status = {"code": str(fail.code), "msg": fail.msg}
        if self.dialect == "rws2":
            body = json.dumps({"status": status}).encode()
            headers["Content-Type"] = rws.JSON_RWS2
        elif request.query.get("json") == "1":
            body = json.dumps({"_embedded": {"status": status}}).encode()
            headers["Content-Type"] = rws.JSON_RWS1
        else:
            body = (f'<html xmlns="http://www.w3.org/1999/xhtml"><body><div class="status">'
                    f'<span class="code">{fail.code}</span><span class="msg">'
                    f"{escape(fail.msg)}</span></div></body></html>").encode()
            headers["Content-Type"] = rws.XHTML
        return web.Response(status=fail.status, body=body, headers=headers)

    # --- routing ---------------------------------------------------------------------------------
    async def _route(self, request: web.Request, form: Mapping[str, str]
                     ) -> tuple[str, list[dict[str, Any]]] | None:
        path = request.path.rstrip("/")
        action = request.query.get("action")
        post = request.method == "POST"
        if path == "/logout":
            self._logout(request)
            return None
        if path.startswith("/rw/rapid/symbol/"):
            return self._symbol(path, post, action, form)
        if path.startswith("/rw/cfg/") and not post:
            return self._get_cfg(path)
        handler = self._routes().get((request.method, self._action_path(path, action)))
        if handler is None:
            raise _Fail(404, ERR_NOT_FOUND, f"no resource {request.method} {request.path}")
        result = handler(request, form)
        if asyncio.iscoroutine(result):
            return await result
        return result

    def _action_path(self, path: str, action: str | None) -> str:
        if self.dialect == "rws1":
            return f"{path}?{action}" if action else path
        return path

    def _routes(self) -> dict[tuple[str, str], Callable[..., Any]]:
        if self.dialect == "rws1":
            return {
                ("GET", "/rw/panel/ctrlstate"): self._get_ctrlstate,
                ("POST", "/rw/panel/ctrlstate?setctrlstate"): self._set_ctrlstate,
                ("GET", "/rw/panel/opmode"): self._get_opmode,
                ("GET", "/rw/panel/speedratio"): self._get_speedratio,
                ("POST", "/rw/panel/speedratio?setspeedratio"): self._set_speedratio,
                ("GET", "/rw/rapid/execution"): self._get_execution,
                ("POST", "/rw/rapid/execution?start"): self._start,
                ("POST", "/rw/rapid/execution?stop"): self._stop,
                ("POST", "/rw/rapid/execution?resetpp"): self._resetpp,
                ("GET", "/rw/rapid/tasks"): self._get_tasks,
                (
                    "POST", f"/rw/rapid/tasks/{self.options.task}?activate"
                ): self._noop,
                ("GET", f"/rw/rapid/tasks/{self.options.task}/modules"): self._get_modules,
                ("POST", "/rw/mastership?request"): self._mastership_request,
                ("POST", "/rw/mastership?release"): self._mastership_release,
                ("POST", "/rw/mastership/edit?request"): self._mastership_request,
                ("POST", "/rw/mastership/edit?release"): self._mastership_release,
                ("GET", "/rw/motionsystem/mechunits/ROB_1/jointtarget"): self._get_jointtarget,
                ("GET", "/rw/motionsystem/mechunits/ROB_1/robtarget"): self._get_robtarget,
                ("GET", "/rw/elog/0"): self._get_elog,
            }
        return {
            ("GET", "/rw/panel/ctrl-state"): self._get_ctrlstate,
            ("GET", "/rw/panel/ctrlstate"): self._get_ctrlstate,
            ("POST", "/rw/panel/ctrl-state"): self._set_ctrlstate,
            ("GET", "/rw/panel/opmode"): self._get_opmode,
            ("GET", "/rw/panel/speedratio"): self._get_speedratio,
            ("POST", "/rw/panel/speedratio"): self._set_speedratio,
            ("GET", "/rw/rapid/execution"): self._get_execution,
            ("POST", "/rw/rapid/execution/start"): self._start,
            ("POST", "/rw/rapid/execution/stop"): self._stop,
            ("POST", "/rw/rapid/execution/resetpp"): self._resetpp,
            ("GET", "/rw/rapid/tasks"): self._get_tasks,
            ("GET", f"/rw/rapid/tasks/{self.options.task}/modules"): self._get_modules,
            ("POST", "/rw/mastership/request"): self._mastership_request,
            ("POST", "/rw/mastership/release"): self._mastership_release,
            ("POST", "/rw/mastership/edit/request"): self._mastership_request,
            ("POST", "/rw/mastership/edit/release"): self._mastership_release,
            ("GET", "/rw/motionsystem/mechunits/ROB_1/jointtarget"): self._get_jointtarget,
            ("GET", "/rw/motionsystem/mechunits/ROB_1/robtarget"): self._get_robtarget,
            ("GET", "/rw/elog/0"): self._get_elog,
        }

    def _sid(self, request: web.Request) -> str | None:
        return request.cookies.get("-http-session-")

    def _logout(self, request: web.Request) -> None:
        sid = self._sid(request)
        if sid is not None:
            self._sessions.pop(sid, None)
            if self._master == sid:
                self._master = None

    def _noop(self, request: web.Request, form: Mapping[str, str]) -> None:
        return None

    # --- panel -----------------------------------------------------------------------------------
    def _get_ctrlstate(self, request: web.Request, form: Mapping[str, str]
                       ) -> tuple[str, list[dict[str, Any]]]:
        return "/rw/panel/", [{"_type": "pnl-ctrlstate", "_title": "ctrlstate",
                               "ctrlstate": self.ctrlstate}]

    async def _set_ctrlstate(self, request: web.Request, form: Mapping[str, str]) -> None:
        state = form.get("ctrl-state")
        if state not in ("motoron", "motoroff"):
            raise _Fail(400, ERR_BAD_VALUE, f"bad ctrl-state {state!r}")
        if self.opmode != "AUTO":
            raise _Fail(403, ERR_NOT_AUTO, "motors can be switched remotely in AUTO only")
        if state == "motoroff":
            self._halt_now()
            await self._halt_program()
        self.ctrlstate = state
        return None

    def _get_opmode(self, request: web.Request, form: Mapping[str, str]
                    ) -> tuple[str, list[dict[str, Any]]]:
        return "/rw/panel/", [{"_type": "pnl-opmode", "_title": "opmode", "opmode": self.opmode}]

    def _get_speedratio(self, request: web.Request, form: Mapping[str, str]
                        ) -> tuple[str, list[dict[str, Any]]]:
        return "/rw/panel/", [{"_type": "pnl-speedratio", "_title": "speedratio",
                               "speedratio": str(self.speedratio)}]

    def _set_speedratio(self, request: web.Request, form: Mapping[str, str]) -> None:
        try:
            ratio = int(float(form.get("speed-ratio", "")))
        except ValueError as err:
            raise _Fail(400, ERR_BAD_VALUE, "bad speed-ratio") from err
        if not 0 <= ratio <= 100:
            raise _Fail(400, ERR_BAD_VALUE, "speed-ratio outside 0..100")
        self.speedratio = ratio
        return None

    # --- mastership ------------------------------------------------------------------------------
    def _mastership_request(self, request: web.Request, form: Mapping[str, str]) -> None:
        sid = self._sid(request)
        if self._master is not None and self._master != sid:
            raise _Fail(409, ERR_MASTERSHIP, "mastership is held by another client")
        self._master = sid
        return None

    def _mastership_release(self, request: web.Request, form: Mapping[str, str]) -> None:
        if self._master == self._sid(request):
            self._master = None
        return None

    def _check_mastership(self, request: web.Request | None, *, explicit: bool) -> None:
        sid = None if request is None else self._sid(request)
        if self._master is not None and self._master != sid:
            raise _Fail(409, ERR_MASTERSHIP, "mastership is held by another client")
        implicit = request is not None and request.query.get("mastership") == "implicit"
        if explicit and self._master is None and not implicit:
            raise _Fail(403, ERR_MASTERSHIP, "this operation needs edit mastership")

    # --- RAPID execution -------------------------------------------------------------------------
    def _get_execution(self, request: web.Request, form: Mapping[str, str]
                       ) -> tuple[str, list[dict[str, Any]]]:
        return "/rw/rapid/", [{"_type": "rap-execution", "_title": "execution",
                               "ctrlexecstate": self.execstate, "cycle": "forever"}]

    def _start(self, request: web.Request, form: Mapping[str, str]) -> None:
        self._check_mastership(request, explicit=False)
        if self.opmode != "AUTO":
            raise _Fail(403, ERR_NOT_AUTO, "remote start needs AUTO mode")
        if self.ctrlstate != "motoron":
            raise _Fail(403, ERR_MOTORS_OFF, "motors are off")
        if self.execstate == "running":
            return None
        self.execstate = "running"
        self._program = asyncio.create_task(self._run_program(), name="abb-sim-program")
        return None

    async def _stop(self, request: web.Request, form: Mapping[str, str]) -> None:
        self._halt_now()
        await self._halt_program()
        return None

    def _resetpp(self, request: web.Request, form: Mapping[str, str]) -> None:
        # RobotWare 7 wants edit mastership (or mastership=implicit) for resetpp.
        self._check_mastership(request, explicit=self.dialect == "rws2")
        if self.execstate == "running":
            raise _Fail(409, ERR_BAD_VALUE, "cannot move the program pointer while running")
        self.pp = "main"
        return None

    def _halt_now(self) -> None:
        """Halt the robot at once (before any await), where it is."""
        self.world.halt()
        self.execstate = "stopped"

    async def _halt_program(self) -> None:
        task, self._program = self._program, None
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self.execstate = "stopped"

    def _num(self, name: str) -> float:
        return rws.parse_num(self.symbols[name].value)

    def _set_num(self, name: str, v: float) -> None:
        self.symbols[name].value = rws.format_num(v)
        self._changed.set()

    async def _run_program(self) -> None:
        """The RAPID module's ``main`` (deploy/abb/RobocalServer.mod) as the task runs it."""
        try:
            if self.pp == "main":
                self._set_num("rc_done", self._num("rc_seq"))
                self.pp = "wait"
            while True:
                if self.pp == "wait":
                    while self._num("rc_seq") == self._num("rc_done"):
                        self._changed.clear()
                        await self._changed.wait()
                    self.pp = "move"
                await self._move_abs_j()
                self._set_num("rc_done", self._num("rc_seq"))
                self.pp = "wait"
        except _MotionError as err:
            self._elog(err.code, err.title)
            self.world.halt()
            self.execstate = "stopped"
            self._program = None

    async def _move_abs_j(self) -> None:
        target = rws.parse_jointtarget(self.symbols["rc_target"].value).robax
        q_deg = np.asarray(target[: self.world.dof], dtype=float)
        lim = self._limits_deg
        if np.any(q_deg < lim[:, 0]) or np.any(q_deg > lim[:, 1]):
            raise _MotionError(50050, "Position outside reach")
        if self.faults.fire("alarm"):
            raise _MotionError(50056, "Joint collision")
        speed = max(0.01, min(100.0, self._num("rc_speed"))) * self.speedratio / 100.0
        rate = self.options.max_joint_speed_deg_s * speed / 100.0
        dist = float(np.max(np.abs(q_deg - np.degrees(self.world.q_actual_rad))))
        duration = max(dist / rate, self.options.min_motion_s) * self.options.time_scale
        motion = self.world.start_motion(np.radians(q_deg), duration)
        await asyncio.sleep(duration)
        self.world.finish_motion(motion)

    def _elog(self, code: int, title: str) -> None:
        self.elog.append(ElogEntry(len(self.elog) + 1, code, title))
        _log.info("abb rws sim: execution error", code=code, title=title)

    def _get_elog(self, request: web.Request, form: Mapping[str, str]
                  ) -> tuple[str, list[dict[str, Any]]]:
        return "/rw/elog/", [{"_type": "elog-message-li", "_title": f"/rw/elog/0/{e.seqnum}",
                              "msgtype": "3", "code": str(e.code), "title": e.title}
                             for e in reversed(self.elog)]

    def _get_tasks(self, request: web.Request, form: Mapping[str, str]
                   ) -> tuple[str, list[dict[str, Any]]]:
        return "/rw/rapid/", [{
            "_type": "rap-task-li", "_title": self.options.task, "name": self.options.task,
            "type": "normal", "taskstate": "started",
            "excstate": "started" if self.execstate == "running" else "stopped",
            "active": "On", "motiontask": "TRUE"}]

    def _get_modules(self, request: web.Request, form: Mapping[str, str]
                     ) -> tuple[str, list[dict[str, Any]]]:
        return "/rw/rapid/", [
            {"_type": "rap-module-info-li", "_title": m, "name": m, "type": t}
            for m, t in (("BASE", "SysMod"), ("user", "SysMod"),
                         (self.options.module, "ProgMod"))]

    # --- RAPID data ------------------------------------------------------------------------------
    def _symbol(self, path: str, post: bool, action: str | None, form: Mapping[str, str]
                ) -> tuple[str, list[dict[str, Any]]] | None:
        if self.dialect == "rws1":
            prefix, suffix = "/rw/rapid/symbol/data/RAPID/", ""
        else:
            prefix, suffix = "/rw/rapid/symbol/RAPID/", "/data"
        if not path.startswith(prefix) or not path.endswith(suffix):
            raise _Fail(404, ERR_NOT_FOUND, f"no resource {path}")
        parts = path[len(prefix): len(path) - len(suffix)].split("/")
        if len(parts) not in (2, 3) or parts[0] != self.options.task:
            raise _Fail(404, ERR_NOT_FOUND, f"no RAPID symbol {path}")
        if len(parts) == 3 and parts[1] != self.options.module:
            raise _Fail(404, ERR_NOT_FOUND, f"no module {parts[1]} in {parts[0]}")
        sym = self.symbols.get(parts[-1].lower())
        if sym is None:
            raise _Fail(404, ERR_NOT_FOUND, f"no RAPID symbol {parts[-1]}")
        if not post:
            return "/rw/rapid/symbol/", [{"_type": "rap-data", "_title": f"RAPID/{parts[0]}/"
                                          f"{sym.module}/{sym.name}", "value": sym.value}]
        if self.dialect == "rws1" and action != "set":
            raise _Fail(400, ERR_BAD_VALUE, "RWS 1.0 writes RAPID data with ?action=set")
        if "value" not in form:
            raise _Fail(400, ERR_BAD_VALUE, "no value")
        try:
            sym.assign(form["value"])
        except (FramingError, ValueError) as err:
            raise _Fail(400, ERR_BAD_VALUE, f"{sym.name}: {err}") from err
        self._changed.set()
        return None

    # --- motion system ---------------------------------------------------------------------------
    def _get_cfg(self, path: str) -> tuple[str, list[dict[str, Any]]]:
        """``/rw/cfg/{domain}/{type}/instances[/{name}]``, read only."""
        parts = path.split("/")[3:]
        if len(parts) not in (3, 4) or parts[2] != "instances":
            raise _Fail(404, ERR_NOT_FOUND, f"no configuration resource {path}")
        instances = self.cfg.get(parts[0], {}).get(parts[1])
        if instances is None or (len(parts) == 4 and parts[3] not in instances):
            raise _Fail(404, ERR_NOT_FOUND, f"no configuration {'/'.join(parts)}")
        names = [parts[3]] if len(parts) == 4 else list(instances)
        items = [{"_type": "cfg-dt-instance-li", "_title": n, "rdonly": "false",
                  "attrib": [{"_type": "cfg-ia-t-li", "_title": k, "value": v}
                             for k, v in instances[n].items()]} for n in names]
        return "/rw/cfg/", items

    def _get_jointtarget(self, request: web.Request, form: Mapping[str, str]
                         ) -> tuple[str, list[dict[str, Any]]]:
        q = np.degrees(self.world.q_actual_rad)
        item: dict[str, Any] = {"_type": "ms-jointtarget", "_title": "ROB_1"}
        for i in range(6):
            item[f"rax_{i + 1}"] = rws.format_num(float(q[i])) if i < len(q) else "0"
        for c in "abcdef":
            item[f"eax_{c}"] = "9E+09"
        return "/rw/motionsystem/", [item]

    def _get_robtarget(self, request: web.Request, form: Mapping[str, str]
                       ) -> tuple[str, list[dict[str, Any]]]:
        tool = request.query.get("tool", "tool0")
        wobj = request.query.get("wobj", "wobj0")
        coord = request.query.get("coordinate", "Base")
        if tool != "tool0" or wobj != "wobj0" or coord not in ("Base", "World", "Wobj"):
            raise _Fail(400, ERR_BAD_VALUE, "the simulator knows tool0, wobj0 and Base only")
        R, o = _flange_pose(self.world, self.world.q_actual_rad)
        w, x, y, z = _quaternion(R)
        item: dict[str, Any] = {"_type": "ms-robtargets", "_title": "ROB_1"}
        for k, v in zip(("x", "y", "z"), o * 1000.0, strict=True):
            item[k] = f"{v:.2f}"
        for k, v in zip(("q1", "q2", "q3", "q4"), (w, x, y, z), strict=True):
            item[k] = f"{v:.6f}"
        item.update(cf1="0", cf4="0", cf6="0", cfx="0")
        for c in "abcdef":
            item[f"eax{c}"] = "9E+09"
        return "/rw/motionsystem/", [item]


def _xhtml_item(item: dict[str, Any]) -> str:
    """One state item as ``<li class=type title=...>``: fields as spans, a list-valued field
    (a configuration instance's attributes) as a nested ``<ul>`` of items."""
    spans = "".join(f'<span class="{escape(k)}">{escape(str(v))}</span>'
                    for k, v in item.items() if not k.startswith("_") and not isinstance(v, list))
    nested = "".join("<ul>" + "".join(_xhtml_item(x) for x in v) + "</ul>"
                     for v in item.values() if isinstance(v, list))
    return (f'<li class="{escape(item.get("_type", ""))}" '
            f'title="{escape(item.get("_title", ""))}">{spans}{nested}</li>')


class _MotionError(Exception):
    def __init__(self, code: int, title: str) -> None:
        super().__init__(title)
        self.code, self.title = code, title


def _flange_pose(world: SimWorld, q_rad: Any) -> tuple[np.ndarray, np.ndarray]:
    """Nominal flange rotation (3, 3) and origin (3,) m in the robot base frame, as the
    controller's own kinematic model computes them."""
    from robocal.kinematics import ErrorModelSpec, KinematicModel

    robot = world.cell.robot
    model = KinematicModel(robot, ErrorModelSpec(robot.dof, ()), np.eye(4))
    x = model.nominal_params()
    _, R, o = model.flange_poses(np.atleast_2d(q_rad), x)
    return R[0], o[0]


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of rotation ``R`` with w >= 0."""
    tr = float(np.trace(R))
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = (0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s)
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = ((R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s)
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = ((R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s)
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = ((R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s)
    sign = -1.0 if q[0] < 0 else 1.0
    return tuple(float(sign * v) for v in q)  # type: ignore[return-value]

