"""The local HTTP/JSON API: a thin aiohttp shell over :class:`CalibrationService`.

It listens on a Unix socket (file mode 0660 by default: the file permissions are the access
control) and, optionally, on TCP, where every request needs ``Authorization: Bearer
<token>`` (401 otherwise). ``GET /openapi.json`` describes every route. Errors are JSON
(``{"error": {"type", "message", "status"}}``) with a 4xx status for anything the client can
fix; a malformed request never takes the daemon down.

Routes::

    GET  /health                       daemon status
    GET  /openapi.json                 this API
    GET  /campaigns                    list
    POST /campaigns                    create (and start) from a plan
    GET  /campaigns/{id}               status (state, poses_total, poses_measured, fits)
    GET  /campaigns/{id}/measurements  stored measurements (mm, deg)
    GET  /campaigns/{id}/report.json   the report's summary, as it is after the last action
    GET  /campaigns/{id}/report.html   the report page, likewise
    POST /campaigns/{id}/{action}      start | pause | resume | abort | approve | push
    GET  /events                       Server-Sent Events (``?campaign=ID&after=SEQ``)
    GET  /events/poll                  long-poll: JSON list of events after ``after``
    GET  /compensation                 active table and push history
    POST /compensation/rollback        restore the previous table
    GET  /audit                        append-only audit log
    GET  /checks                       drift checks, oldest first (ADR 0041)
    POST /checks                       start a drift check of the active model
    GET  /checks/{id}                  one check (verdict, errors, recommendation)
    POST /checks/{id}/recalibrate      start the re-calibration with --reuse it recommends

The operator's station (HTML pages under ``/station/``, ``/campaigns/{id}/report``, sign-in,
sessions and CSRF) is :mod:`robocal.daemon.station`; on TCP a station session cookie may
read every route above but change nothing through them.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import pwd
import re
import resource
import socket
import sqlite3
import struct
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Literal

import structlog
from aiohttp import web
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from robocal import __version__
from robocal._core.clock import SYSTEM_CLOCK, Clock
from robocal._core.files import atomic_write_text
from robocal.daemon._gate import ConnectionGate, GatedTCPSite, GatedUnixSite
from robocal.daemon.config import AppConfig, config_warnings
from robocal.daemon.schemas import (
    AuditEntry,
    CampaignStatus,
    CampaignSummary,
    CheckRecord,
    CompensationState,
    ErrorBody,
    Event,
    EventPoll,
    Health,
    Measurement,
)
from robocal.daemon.service import CalibrationService
from robocal.daemon.station import SessionStore, auth_middleware, register
from robocal.daemon.store import UnknownCampaign, is_storage_fault
from robocal.errors import (
    CampaignError,
    CompensationError,
    ConfigError,
    DriverError,
    IdentificationError,
    ProtocolError,
    RobocalError,
    StorageError,
)

__all__ = ["ROUTES", "ApiServer", "Route", "make_app", "openapi_spec"]

_log = structlog.get_logger(__name__)
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
_SERVICE: web.AppKey[CalibrationService] = web.AppKey("service", CalibrationService)
_TOKEN_AUTH: web.AppKey[bool] = web.AppKey("token_auth", bool)
_BODY_TIMEOUT: web.AppKey[float] = web.AppKey("body_timeout", float)
_ACTOR_RE = re.compile(r"[^A-Za-z0-9_.@:-]")
_ACTIONS = ("start", "pause", "resume", "abort", "approve", "push")


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CreateCampaignRequest(_Request):
    """Body of ``POST /campaigns``."""

    plan: dict[str, Any] = Field(description="a PLAN.json document (robocal.plan/1)")
    name: str | None = Field(default=None, max_length=200)
    start: bool = Field(default=True, description="start measuring at once")
    measure_only: bool = Field(default=False, description="no fit (verification runs)")


class ActionRequest(_Request):
    """Optional body of ``POST /campaigns/{id}/{action}``."""

    reason: str = Field(default="", max_length=1000)
    model: str | None = Field(default=None, max_length=64,
                              description="approve: the fitted model to approve")
    force: bool = Field(default=False, description="push: push a table that does not clearly "
                                                   "improve on nominal, onto a controller "
                                                   "whose own calibration changed since the "
                                                   "campaign or with a vendor absolute-"
                                                   "accuracy option active (audited)")
    key: str | None = Field(default=None, min_length=8, max_length=64,
                            pattern=r"^[A-Za-z0-9_.:-]+$",
                            description="push: idempotency key (a retry with the same key "
                                        "never writes twice)")


class RollbackRequest(_Request):
    """Optional body of ``POST /compensation/rollback``."""

    reason: str = Field(default="", max_length=1000)
    key: str | None = Field(default=None, min_length=8, max_length=64,
                            pattern=r"^[A-Za-z0-9_.:-]+$", description="idempotency key")


class CheckRequest(_Request):
    """Optional body of ``POST /checks``."""

    plan: dict[str, Any] | None = Field(
        default=None, description="a PLAN.json (robocal.plan/1) whose measured poses the "
                                  "check measures (default: check.poses poses of the active "
                                  "model's own campaign)")


def _error(status: int, kind: str, message: str, **extra: Any) -> web.Response:
    body = {"error": {"type": kind, "message": message, "status": status, **extra}}
    return web.json_response(body, status=status)


def _status_for(err: RobocalError) -> int:
    if isinstance(err, UnknownCampaign):
        return 404
    if isinstance(err, StorageError):
        return 503
    if isinstance(err, ConfigError):
        return 422
    if isinstance(err, CompensationError):
        return 422
    if isinstance(err, CampaignError | IdentificationError):
        return 409
    if isinstance(err, DriverError | ProtocolError):
        return 502
    return 400


@web.middleware
async def _errors(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Turn every failure into a JSON error; only bugs give 500, and the daemon lives on."""
    try:
        return await handler(request)
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        resp = _error(exc.status, type(exc).__name__, exc.reason or exc.text or "")
        if exc.status in (408, 413):
            resp.force_close()  # the rest of that body is not worth waiting for
        return resp
    except RobocalError as err:
        return _error(_status_for(err), type(err).__name__, str(err))
    except asyncio.CancelledError:
        raise
    except sqlite3.Error as err:
        if is_storage_fault(err):  # a read hit the disk fault: not the client's doing
            return _error(503, "StorageError", f"the store cannot be read: {err}")
        _log.exception("request failed", path=request.path, method=request.method)
        return _error(500, "InternalError", f"{type(err).__name__}: {err}")
    except Exception as err:
        _log.exception("request failed", path=request.path, method=request.method)
        return _error(500, "InternalError", f"{type(err).__name__}: {err}")


def _peer(request: web.Request) -> str:
    """``uid=N(name)`` of a Unix-socket client (SO_PEERCRED), else ``token``/``unknown``."""
    if request.app[_TOKEN_AUTH]:
        return "token"
    sock = request.transport.get_extra_info("socket") if request.transport else None
    if sock is not None and getattr(sock, "family", None) == socket.AF_UNIX:
        with contextlib.suppress(OSError, struct.error):
            creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                    struct.calcsize("3i"))
            _pid, uid, _gid = struct.unpack("3i", creds)
            try:
                name = pwd.getpwuid(uid).pw_name
            except KeyError:
                name = "?"
            return f"uid={uid}({name})"
    return "unknown"


def _remote(request: web.Request) -> str:
    """The TCP client's address (the station's sessions record it with the actor)."""
    return request.remote or "unknown"


def _actor(request: web.Request) -> str:
    claimed = _ACTOR_RE.sub("", request.headers.get("X-Robocal-Actor", ""))[:64]
    peer = _peer(request)
    return f"{claimed} via {peer}" if claimed else peer


async def _body(request: web.Request, model: type[_Request], *, required: bool) -> Any:
    try:
        async with asyncio.timeout(request.app[_BODY_TIMEOUT]):
            raw = await request.read()
    except TimeoutError as err:
        raise web.HTTPRequestTimeout(reason="the request body did not arrive in time") from err
    if not raw.strip():
        if required:
            raise web.HTTPBadRequest(reason="a JSON body is required")
        return model()
    try:
        data = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise web.HTTPBadRequest(reason=f"body is not valid JSON: {err}") from err
    except RecursionError as err:
        raise web.HTTPBadRequest(reason="body is not valid JSON: nested too deeply") from err
    except ValueError as err:  # e.g. an integer of more than 4300 digits
        raise web.HTTPBadRequest(reason=f"body is not valid JSON: {err}") from err
    if not isinstance(data, dict):
        raise web.HTTPBadRequest(reason="body must be a JSON object")
    try:
        return model.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        loc = ".".join(str(p) for p in first["loc"]) or "<body>"
        raise web.HTTPUnprocessableEntity(reason=f"{loc}: {first['msg']}") from err


def _int_query(request: web.Request, name: str, default: int, lo: int, hi: int) -> int:
    raw = request.query.get(name)
    if raw is None:
        return default
    try:
        v = int(raw)
    except ValueError as err:
        raise web.HTTPBadRequest(reason=f"query parameter {name!r} must be an integer") from err
    if not lo <= v <= hi:
        raise web.HTTPBadRequest(reason=f"query parameter {name!r} must be in [{lo}, {hi}]")
    return v


@cache
def _adapter(shape: Any) -> TypeAdapter[Any]:
    return TypeAdapter(shape)


def _reply(shape: Any, data: Any, *, status: int = 200) -> web.Response:
    """``data`` validated against and serialised through the response model ``shape``.

    A service answer that no longer matches its model is a bug: a ValidationError here
    becomes a logged 500, and the tests that call the route fail.
    """
    adapter = _adapter(shape)
    # exclude_unset: the keys the service gave, no more (an absent optional is not null)
    body = adapter.dump_python(adapter.validate_python(data), mode="json", exclude_unset=True)
    return web.json_response(body, status=status)


# --- handlers ---------------------------------------------------------------------------------
async def health(request: web.Request) -> web.Response:
    return _reply(Health, request.app[_SERVICE].health())


async def openapi(request: web.Request) -> web.Response:
    return web.json_response(openapi_spec())


async def list_campaigns(request: web.Request) -> web.Response:
    return _reply(list[CampaignSummary], request.app[_SERVICE].list())


async def create_campaign(request: web.Request) -> web.Response:
    body = await _body(request, CreateCampaignRequest, required=True)
    status = await request.app[_SERVICE].create(
        body.plan, actor=_actor(request), name=body.name, start=body.start,
        measure_only=body.measure_only)
    return _reply(CampaignStatus, status, status=201)


async def get_campaign(request: web.Request) -> web.Response:
    return _reply(CampaignStatus, request.app[_SERVICE].status(request.match_info["cid"]))


async def get_measurements(request: web.Request) -> web.Response:
    rows = request.app[_SERVICE].measurements(request.match_info["cid"])
    return _reply(list[Measurement], rows)


async def _report(request: web.Request, name: str) -> web.Response:
    cid = request.match_info["cid"]
    path = await request.app[_SERVICE].report_file(cid, name)
    if path is None:
        raise web.HTTPNotFound(reason=f"campaign {cid} has no {name} (fitted with "
                                      "report = false, or not fitted yet)")
    text = await asyncio.to_thread(path.read_text, encoding="utf-8")
    if name == "report.json":
        return web.json_response(json.loads(text))
    return web.Response(text=text, content_type="text/html")


async def get_report_json(request: web.Request) -> web.Response:
    return await _report(request, "report.json")


async def get_report_html(request: web.Request) -> web.Response:
    return await _report(request, "report.html")


async def campaign_action(request: web.Request) -> web.Response:
    svc = request.app[_SERVICE]
    cid, action = request.match_info["cid"], request.match_info["action"]
    if action not in _ACTIONS:
        raise web.HTTPNotFound(reason=f"unknown action {action!r} (one of {', '.join(_ACTIONS)})")
    body = await _body(request, ActionRequest, required=False)
    actor = _actor(request)
    if action == "start":
        out = await svc.start_campaign(cid, actor=actor)
    elif action == "pause":
        out = await svc.pause(cid, actor=actor, reason=body.reason)
    elif action == "resume":
        out = await svc.resume(cid, actor=actor)
    elif action == "abort":
        out = await svc.abort(cid, actor=actor, reason=body.reason)
    elif action == "approve":
        out = await svc.approve(cid, actor=actor, model=body.model)
    else:
        out = await svc.push(cid, actor=actor, force=body.force, key=body.key,
                             reason=body.reason)
    return _reply(CampaignStatus, out)


async def compensation(request: web.Request) -> web.Response:
    return _reply(CompensationState, request.app[_SERVICE].compensation())


async def rollback(request: web.Request) -> web.Response:
    body = await _body(request, RollbackRequest, required=False)
    return _reply(CompensationState, await request.app[_SERVICE].rollback(
        actor=_actor(request), reason=body.reason, key=body.key))


async def audit(request: web.Request) -> web.Response:
    limit = _int_query(request, "limit", 1000, 1, 100_000)
    return _reply(list[AuditEntry], request.app[_SERVICE].audit(limit=limit))


async def events_poll(request: web.Request) -> web.Response:
    """Long-poll: events after ``after`` (waits up to ``timeout`` s for the first one)."""
    svc = request.app[_SERVICE]
    after = _int_query(request, "after", 0, 0, 2**62)
    timeout = _int_query(request, "timeout", 20, 0, 300)
    campaign = request.query.get("campaign") or None
    events = svc.events.history(after=after, campaign=campaign)
    if not events and timeout > 0:
        async with svc.events.subscribe() as q:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(timeout):
                    while True:
                        ev = await q.get()
                        if ev is None:
                            break
                        if ev["seq"] > after and (campaign is None or
                                                  ev["campaign"] == campaign):
                            events = [ev]
                            break
    return _reply(EventPoll, {"events": events, "last_seq": svc.events.last_seq})


async def events_sse(request: web.Request) -> web.StreamResponse:
    """Server-Sent Events: ``id: seq``, ``event: kind``, ``data: JSON``; keep-alive comments."""
    svc = request.app[_SERVICE]
    after = _int_query(request, "after", 0, 0, 2**62)
    last_id = request.headers.get("Last-Event-ID")
    if last_id:
        after = max(after, svc.events.after_event_id(last_id))
    campaign = request.query.get("campaign") or None
    resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                       "Cache-Control": "no-cache"})
    await resp.prepare(request)

    async def send(ev: dict[str, Any]) -> None:
        data = json.dumps(ev, default=str)
        await resp.write(f"id: {svc.events.event_id(ev)}\nevent: {ev['kind']}\n"
                         f"data: {data}\n\n".encode())

    try:
        async with svc.events.subscribe() as q:
            last = after
            for past in svc.events.history(after=after, campaign=campaign):
                await send(past)
                last = past["seq"]
            while True:
                try:
                    async with asyncio.timeout(15.0):
                        ev = await q.get()
                except TimeoutError:
                    await resp.write(b": keep-alive\n\n")
                    continue
                if ev is None:
                    break
                if ev["seq"] <= last or (campaign is not None and ev["campaign"] != campaign):
                    continue
                await send(ev)
                last = ev["seq"]
    except (ConnectionResetError, ConnectionError):
        pass
    return resp


def _check_id(request: web.Request) -> int:
    text = request.match_info["check"]
    if not text.isdigit() or len(text) > 18:
        raise web.HTTPNotFound(reason=f"no check {text!r}")
    return int(text)


async def list_checks(request: web.Request) -> web.Response:
    limit = _int_query(request, "limit", 1000, 1, 100_000)
    return _reply(list[CheckRecord], request.app[_SERVICE].checks.log.history(limit=limit))


async def start_check(request: web.Request) -> web.Response:
    body = await _body(request, CheckRequest, required=False)
    out = await request.app[_SERVICE].checks.start(actor=_actor(request), plan=body.plan)
    return _reply(CheckRecord, out, status=201)


async def get_check(request: web.Request) -> web.Response:
    return _reply(CheckRecord, request.app[_SERVICE].checks.log.get(_check_id(request)))


async def recalibrate(request: web.Request) -> web.Response:
    out = await request.app[_SERVICE].checks.recalibrate(actor=_actor(request),
                                                          check_id=_check_id(request))
    return _reply(CampaignStatus, out, status=201)


@dataclass(frozen=True)
class Route:
    """One route: what aiohttp serves and what ``openapi.json`` says about it.

    ``response`` is the model (or type) of the JSON answer, None for a non-JSON one (of
    type ``media``);
    ``query`` lists ``(name, JSON type)`` of the query parameters.
    """

    method: str
    path: str
    handler: Handler
    summary: str
    response: Any = None
    status: int = 200
    body: type[_Request] | None = None
    body_required: bool = False
    query: tuple[tuple[str, str], ...] = ()
    media: str = "text/event-stream"


#: Every route of the API; ``{action}`` is one of ``_ACTIONS`` (documented one path each).
ROUTES: tuple[Route, ...] = (
    Route("GET", "/health", health, "daemon status", Health),
    Route("GET", "/openapi.json", openapi, "this description", dict[str, Any]),
    Route("GET", "/campaigns", list_campaigns, "list campaigns, oldest first",
          list[CampaignSummary]),
    Route("POST", "/campaigns", create_campaign, "create (and start) a campaign from a plan",
          CampaignStatus, status=201, body=CreateCampaignRequest, body_required=True),
    Route("GET", "/campaigns/{cid}", get_campaign,
          "campaign status: state, poses, fits, transitions, pushes", CampaignStatus),
    Route("GET", "/campaigns/{cid}/measurements", get_measurements,
          "stored measurements (mm, deg)", list[Measurement]),
    Route("GET", "/campaigns/{cid}/report.json", get_report_json,
          "the report's JSON summary, once it shows the last approve, push or rollback",
          dict[str, Any]),
    Route("GET", "/campaigns/{cid}/report.html", get_report_html,
          "the report page, once it shows the last approve, push or rollback",
          media="text/html"),
    Route("POST", "/campaigns/{cid}/{action}", campaign_action, "{action} the campaign",
          CampaignStatus, body=ActionRequest),
    Route("GET", "/events", events_sse,
          "progress events as Server-Sent Events (id BOOT-SEQ, event kind, data an Event)",
          query=(("campaign", "string"), ("after", "integer"))),
    Route("GET", "/events/poll", events_poll, "long-poll for events after a sequence number",
          EventPoll, query=(("after", "integer"), ("timeout", "integer"),
                            ("campaign", "string"))),
    Route("GET", "/compensation", compensation, "active compensation table and push history",
          CompensationState),
    Route("POST", "/compensation/rollback", rollback, "restore the previous table (verified)",
          CompensationState, body=RollbackRequest),
    Route("GET", "/audit", audit, "append-only audit log", list[AuditEntry],
          query=(("limit", "integer"),)),
    Route("GET", "/checks", list_checks, "drift checks, oldest first", list[CheckRecord],
          query=(("limit", "integer"),)),
    Route("POST", "/checks", start_check, "start a drift check of the active model",
          CheckRecord, status=201, body=CheckRequest),
    Route("GET", "/checks/{check}", get_check, "one drift check", CheckRecord),
    Route("POST", "/checks/{check}/recalibrate", recalibrate,
          "start the re-calibration with --reuse of the checked model", CampaignStatus,
          status=201),
)


def make_app(service: CalibrationService, *, token: str | None = None,
             viewer_token: str | None = None, max_body_bytes: int = 512 * 1024,
             body_timeout_s: float = 60.0) -> web.Application:
    """The aiohttp application with the operator's station (:mod:`robocal.daemon.station`).

    With ``token`` (TCP), every request must carry it as a bearer, or a station session
    cookie obtained by signing in with it (or with ``viewer_token``: read only).
    """
    middlewares: list[Any] = [_errors]
    sessions = SessionStore()
    if token is not None:
        middlewares.append(auth_middleware(sessions, token=token, viewer_token=viewer_token))
    app = web.Application(middlewares=middlewares, client_max_size=max_body_bytes)
    app[_SERVICE] = service
    app[_TOKEN_AUTH] = token is not None
    app[_BODY_TIMEOUT] = body_timeout_s
    for route in ROUTES:
        app.router.add_route(route.method, route.path, route.handler)
    tokens = {} if token is None else {"operator": token}
    if token is not None and viewer_token is not None:
        tokens["viewer"] = viewer_token
    register(app, service, sessions, local=token is None, tokens=tokens,
             peer=_peer if token is None else _remote)
    return app


_REF = "#/components/schemas/{model}"


def _schema(shape: Any, mode: Literal["validation", "serialization"],
            components: dict[str, Any]) -> dict[str, Any]:
    """The JSON schema of ``shape``: its ``$defs`` moved into ``components`` and, for a
    model, a ``$ref`` to it."""
    schema = dict(_adapter(shape).json_schema(ref_template=_REF, mode=mode))
    defs = schema.pop("$defs", {})
    if isinstance(shape, type) and issubclass(shape, BaseModel):
        defs[shape.__name__] = schema
        schema = {"$ref": _REF.format(model=shape.__name__)}
    for name, d in defs.items():
        if components.setdefault(name, d) != d:
            raise RuntimeError(f"two different schemas are named {name!r}")
    return schema


def _operation(route: Route, path: str, components: dict[str, Any]) -> dict[str, Any]:
    summary = route.summary.replace("{action}", path.rsplit("/", 1)[-1])
    err = {"description": "error", "content": {"application/json": {
        "schema": {"$ref": _REF.format(model=ErrorBody.__name__)}}}}
    if route.response is None:
        ok: dict[str, Any] = {"description": route.media, "content": {
            route.media: {"schema": {"type": "string"}}}}
    else:
        ok = {"description": "OK", "content": {"application/json": {
            "schema": _schema(route.response, "serialization", components)}}}
    op: dict[str, Any] = {"summary": summary,
                          "responses": {str(route.status): ok, "4XX": err, "5XX": err}}
    params = [{"name": name, "in": "path", "required": True, "schema": {"type": "string"}}
              for name in re.findall(r"{(\w+)}", path)]
    params += [{"name": name, "in": "query", "required": False, "schema": {"type": kind}}
               for name, kind in route.query]
    if params:
        op["parameters"] = params
    if route.body is not None:
        op["requestBody"] = {"required": route.body_required, "content": {
            "application/json": {"schema": _schema(route.body, "validation", components)}}}
    return op


def openapi_spec() -> dict[str, Any]:
    """The OpenAPI 3.1 description of the API, generated from :data:`ROUTES` and the models
    in :mod:`robocal.daemon.schemas` (``{action}`` expands to one path per action)."""
    components: dict[str, Any] = {}
    _schema(ErrorBody, "serialization", components)
    components["Event"] = _schema(Event, "serialization", components)
    paths: dict[str, dict[str, Any]] = {}
    for route in ROUTES:
        expanded = ([route.path.replace("{action}", a) for a in _ACTIONS]
                    if "{action}" in route.path else [route.path])
        for path in expanded:
            paths.setdefault(path, {})[route.method.lower()] = _operation(route, path,
                                                                          components)
    return {
        "openapi": "3.1.0",
        "info": {"title": "robocal daemon API", "version": __version__,
                 "description": "Local API of the robocal calibration daemon. On TCP every "
                                "request needs 'Authorization: Bearer <token>'."},
        "paths": paths,
        "components": {"schemas": dict(sorted(components.items())), "securitySchemes": {
            "bearer": {"type": "http", "scheme": "bearer"}}},
    }


#: Unauthenticated TCP connections held at most, and file descriptors kept for everything else
#: (drivers, store, fit workers, the Unix socket's connections).
_POOL_MAX = 4096
_FD_RESERVE = 256


def unauthenticated_pool(max_connections: int) -> int:
    """Size of the TCP listener's pool of unauthenticated connections: as many as the file
    descriptors allow (``RLIMIT_NOFILE``, raised by the daemon at start), at most 4,096, at
    least ``max_connections``.

    A pool that holds a flood's half-open connections until their header deadline keeps the
    flood from cycling: a connection cut at once is reopened at once, and a flood that cycles
    keeps the kernel's accept queue full, so a real client's SYN is dropped and retried a
    second later (ADR 0025).
    """
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return _POOL_MAX
    room = soft - _FD_RESERVE - 2 * max_connections
    return max(max_connections, min(_POOL_MAX, room))


def _socket_in_use(path: Path) -> bool:
    """True if a daemon is listening on ``path`` (a stale socket file is not in use)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.settimeout(1.0)
        s.connect(str(path))
    except OSError:
        return False
    finally:
        s.close()
    return True


class ApiServer:
    """Serve the API on the configured Unix socket and/or TCP port.

    Parameters
    ----------
    service : CalibrationService
        What the API exposes.
    config : AppConfig
        ``api`` section: socket path and mode, TCP host/port and token file.
    clock : Clock, optional
        Time source of the listeners' header deadlines (default: the system clock).
    max_unauthenticated : int, optional
        Size of the TCP listener's pool of unauthenticated connections (default:
        :func:`unauthenticated_pool`).
    """

    def __init__(self, service: CalibrationService, config: AppConfig, *,
                 clock: Clock = SYSTEM_CLOCK, max_unauthenticated: int | None = None) -> None:
        self.service = service
        self.config = config
        self.clock = clock
        self.max_unauthenticated = max_unauthenticated
        self._runners: list[web.AppRunner] = []
        self.socket_path: Path | None = None
        self.tcp_port: int | None = None
        self.tcp_gate: ConnectionGate | None = None
        self.unix_gate: ConnectionGate | None = None

    async def start(self) -> None:
        """Bind and serve.

        Raises
        ------
        ConfigError
            If the socket is in use by a running daemon or the token file is unusable.
        """
        api = self.config.api
        try:
            sock = self.config.socket_path
            if sock is not None:
                await self._start_unix(sock, api.socket_mode)
            if api.tcp_port is not None:
                token = self.config.read_token()
                runner = self._runner(token)
                await runner.setup()
                self._runners.append(runner)
                # Token holders get max_connections slots of their own; everything else
                # shares one pool, counted over all addresses (ADR 0025).
                self.tcp_gate = ConnectionGate(
                    max_connections=api.max_connections,
                    max_per_client=api.max_connections_per_client,
                    header_timeout_s=api.header_timeout_s, token=token,
                    max_unauthenticated=self.max_unauthenticated
                    or unauthenticated_pool(api.max_connections),
                    clock=self.clock)
                site = GatedTCPSite(runner, api.tcp_host, api.tcp_port, gate=self.tcp_gate)
                await site.start()
                self.tcp_port = site.port
                _log.info("api listening", url=f"http://{api.tcp_host}:{self.tcp_port}")
                for warning in config_warnings(self.config):
                    _log.warning("insecure setting", warning=warning)
        except BaseException:
            await self.stop()
            raise
        self._write_endpoints()

    async def _start_unix(self, path: Path, mode: int) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists() or path.is_symlink():
            if _socket_in_use(path):
                raise ConfigError("another daemon is listening on this socket", source=str(path))
            path.unlink()  # stale, from a daemon that was killed
        api = self.config.api
        runner = self._runner(None)
        await runner.setup()
        self._runners.append(runner)
        # Local clients share one budget, separate from TCP's (a TCP flood cannot use it up).
        self.unix_gate = ConnectionGate(max_connections=api.max_connections, max_per_client=None,
                                        header_timeout_s=api.header_timeout_s,
                                        clock=self.clock)
        site = GatedUnixSite(runner, str(path), gate=self.unix_gate)
        # Create the socket with no more permission than asked, then set the mode exactly.
        old = os.umask(0o777 & ~mode)
        try:
            await site.start()
        finally:
            os.umask(old)
        os.chmod(path, mode)
        self.socket_path = path
        _log.info("api listening", socket=str(path), mode=oct(mode))

    def _runner(self, token: str | None) -> web.AppRunner:
        api = self.config.api
        viewer = None if token is None else self.config.read_viewer_token()
        app = make_app(self.service, token=token, viewer_token=viewer,
                       max_body_bytes=api.max_body_bytes, body_timeout_s=api.body_timeout_s)
        # lingering_time: after an error mid-body, read what is left for at most 1 s, not 10
        return web.AppRunner(app, access_log=None, shutdown_timeout=2.0,
                             keepalive_timeout=api.keepalive_timeout_s, lingering_time=1.0)

    def _write_endpoints(self) -> None:
        """Write ``api.json`` (socket and TCP URL) to ``data_dir`` for clients and tests."""
        d = {"socket": None if self.socket_path is None else str(self.socket_path),
             "url": None if self.tcp_port is None else
             f"http://{self.config.api.tcp_host}:{self.tcp_port}",
             "pid": os.getpid()}
        try:
            atomic_write_text(self.config.data_dir / "api.json", json.dumps(d) + "\n")
        except OSError as err:  # a full disk: keep serving (health says why), never exit
            _log.error("api.json not written", error=str(err))

    async def stop(self) -> None:
        """Stop serving; idempotent."""
        runners, self._runners = self._runners, []
        for runner in runners:
            with contextlib.suppress(Exception):
                await runner.cleanup()
        if self.socket_path is not None:
            with contextlib.suppress(OSError):
                self.socket_path.unlink()
            self.socket_path = None
