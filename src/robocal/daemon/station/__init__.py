"""The operator's station: web pages served by the daemon on its API listeners.

Pages (HTML, assets from this package, no CDN)::

    GET  /                                  redirect to /station/
    GET  /station/                          campaigns list (+ start form for operators)
    GET  /station/campaigns/{cid}           campaign page (?fragment=live: JSON of its
                                            live parts, fetched by station.js on events)
    GET  /station/campaigns/{cid}/points    per-pose residuals for the plot (JSON)
    GET  /campaigns/{cid}/report            the campaign's HTML report (sandboxed)
    GET  /station/login, POST /station/login, POST /station/logout
    POST /station/campaigns                 start a campaign from a plan file on this PC
    POST /station/campaigns/{cid}/{action}  start|pause|resume|abort|approve|push|rollback
    GET  /station/static/{name}             station.css, station.js

Live updates come from the JSON API's ``GET /events`` (SSE), which a signed-in browser may
read with its session cookie. Authentication, roles and CSRF: :mod:`._auth` and ADR 0031.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import secrets
import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
import structlog
from aiohttp import web

from robocal.daemon.service import CalibrationService
from robocal.daemon.station import _facts, _pages
from robocal.daemon.station._auth import (
    COOKIE,
    Session,
    SessionStore,
    auth_middleware,
    check_same_origin,
)
from robocal.errors import RobocalError

__all__ = ["SessionStore", "auth_middleware", "next_url", "register"]

_log = structlog.get_logger(__name__)
#: The station's pages, registered on the API's application by :func:`register`.
_PAGES = web.RouteTableDef()
_SERVICE: web.AppKey[CalibrationService] = web.AppKey("station_service", CalibrationService)
_SESSIONS: web.AppKey[SessionStore] = web.AppKey("station_sessions", SessionStore)
_LOCAL: web.AppKey[bool] = web.AppKey("station_local", bool)
_TOKENS: web.AppKey[dict[str, str]] = web.AppKey("station_tokens", dict)
_PEER: web.AppKey[Callable[[web.Request], str]] = web.AppKey("station_peer")
_RESIDUALS: web.AppKey[dict[tuple[str, str], list[list[float]]]] = web.AppKey(
    "station_residuals", dict)
_LOGIN_COOKIE = "robocal_login"
_BEFORE_FIT = ("created", "running", "paused", "measured")
_STATIC = {"station.css": "text/css", "station.js": "text/javascript"}
_ACTIONS = ("start", "pause", "resume", "abort", "approve", "push", "rollback")
_MAX_PLAN_BYTES = 8 * 1024 * 1024
_PAGE_CSP = ("default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
             "connect-src 'self'; frame-src 'self'; frame-ancestors 'none'; "
             "form-action 'self'; base-uri 'none'; object-src 'none'")
# The report is our own HTML with inline styles, scripts and data: images; sandboxed so it
# runs with no origin (it cannot use the session) and may only be framed by the station.
_REPORT_CSP = ("sandbox allow-scripts; default-src 'none'; img-src data:; "
               "style-src 'unsafe-inline'; script-src 'unsafe-inline'; frame-ancestors 'self'")


def _headers(resp: web.StreamResponse, csp: str = _PAGE_CSP) -> web.StreamResponse:
    resp.headers["Content-Security-Policy"] = csp
    resp.headers["X-Content-Type-Options"] = "nosniff"
    # same-origin, not no-referrer: with no-referrer a form POST says "Origin: null"
    resp.headers["Referrer-Policy"] = "same-origin"
    resp.headers["Cache-Control"] = "no-store"
    return resp


def _redirect(url: str) -> web.Response:
    """A 303 See Other as a response (not raised), so that cookies set on it are kept."""
    return web.Response(status=303, headers={"Location": url})


def _html(text: str, status: int = 200) -> web.StreamResponse:
    return _headers(web.Response(text=text, status=status, content_type="text/html"))


def _set_cookie(resp: web.StreamResponse, name: str, value: str, *, max_age: int | None
                ) -> None:
    resp.set_cookie(name, value, httponly=True, samesite="Strict", path="/", max_age=max_age)


def _session(request: web.Request) -> tuple[Session | None, bool]:
    """The request's session; on the Unix socket one is made (operator) when missing.

    Returns (session, new): ``new`` means the response must set the cookie.
    """
    store = request.app[_SESSIONS]
    s = store.get(request.cookies.get(COOKIE))
    if s is not None:
        return s, False
    if request.app[_LOCAL]:
        return store.new("operator", name="local", peer=request.app[_PEER](request)), True
    return None, False


def _require(request: web.Request) -> tuple[Session, bool]:
    s, new = _session(request)
    if s is None:
        raise web.HTTPSeeOther("/station/login")
    return s, new


def _finish(resp: web.StreamResponse, session: Session, new: bool) -> web.StreamResponse:
    if new:
        _set_cookie(resp, COOKIE, session.id, max_age=None)
    return resp


async def _post(request: web.Request, *, operator: bool = True) -> tuple[Session, Any]:
    """A station POST: same origin, a session, its CSRF token, and (``operator``) the role.

    Raises
    ------
    web.HTTPForbidden
        Cross-site, bad or missing CSRF token, or a viewer asking for an operator action.
    web.HTTPUnauthorized
        No session.
    """
    check_same_origin(request)
    s, _new = _session(request)
    if s is None or _new:
        raise web.HTTPUnauthorized(reason="sign in first")
    form = await request.post()
    got = request.headers.get("X-CSRF-Token") or form.get("csrf")
    if not isinstance(got, str) or not s.check_csrf(got):
        raise web.HTTPForbidden(reason="missing or wrong CSRF token; reload the page")
    if operator and s.role != "operator":
        _log.warning("station action refused", actor=s.actor, path=request.path,
                     why="viewer")
        raise web.HTTPForbidden(reason="viewers can only read; sign in with the operator token")
    return s, form


def _fields(form: Any, name: str, limit: int = 1000) -> str:
    v = form.get(name, "")
    return v[:limit].strip() if isinstance(v, str) else ""


# --- views --------------------------------------------------------------------------------
def _banner(svc: CalibrationService, comp: dict[str, Any] | None = None) -> str:
    comp = svc.compensation() if comp is None else comp
    active = comp.get("active") or {}
    push_of: dict[str, dict[str, Any] | None] = {}
    cid = active.get("campaign")
    if cid:
        with contextlib.suppress(RobocalError):
            push_of[cid] = svc.status(cid).get("push")
    return _pages.banner(_facts.controller_banner(comp, push_of))


def _list_rows(svc: CalibrationService, comp: dict[str, Any]) -> list[dict[str, Any]]:
    active = (comp.get("active") or {}).get("campaign")
    origin = (comp.get("active") or {}).get("origin")
    rows = []
    for c in svc.list():
        # only what the row shows: a full status per campaign would make a long list slow
        unfitted = c["state"] in _BEFORE_FIT
        st = {**c, "fits": {} if unfitted else svc.store.fits(c["id"]),
              "compensation": ([] if unfitted or c["state"] == "fitted"
                               else svc.campaign_compensation(c["id"]))}
        rows.append({"id": c["id"], "name": c["name"], "state": c["state"],
                     "robot": c["robot"], "created": c["created"],
                     "measured": c["poses_measured"], "total": c["poses_total"],
                     "rms": _facts.heldout_rms(st),
                     "active": c["id"] == active and origin != "controller",
                     "rolled_back": _facts.rolled_back_at(st, comp)})
    return rows


@_PAGES.get("/", name="station.index")
@_PAGES.get("/station", name="station.redirect")
async def index(request: web.Request) -> web.StreamResponse:
    raise web.HTTPSeeOther("/station/")


@_PAGES.get("/station/", name="station.list_view")
async def list_view(request: web.Request) -> web.StreamResponse:
    s, new = _require(request)
    svc = request.app[_SERVICE]
    comp = svc.compensation()
    rows = _list_rows(svc, comp)
    if request.query.get("fragment") == "live":
        resp: web.StreamResponse = web.json_response(
            {"live": _pages.list_rows(rows), "banner": _banner(svc, comp)})
        return _finish(_headers(resp), s, new)
    page = _pages.list_page(rows, session=s, banner_html=_banner(svc, comp),
                            checks_html=_pages.checks_box(svc.checks.log.history(limit=10),
                                                          session=s))
    return _finish(_html(page.replace("data-live=", f'data-seq="{svc.events.last_seq}" '
                                                    "data-live=", 1)), s, new)


def _report_path(st: dict[str, Any]) -> Path:
    return Path(st["files"]) / "report.html"


def _report_box(st: dict[str, Any]) -> str:
    rendering = (st.get("report") or {}).get("state") == "rendering"
    return _pages.report_box(st["id"], _report_path(st).is_file() and not rendering,
                             rendering=rendering)


def _campaign_live(svc: CalibrationService, st: dict[str, Any], s: Session,
                   comp: dict[str, Any]) -> str:
    rows = svc.store.measurement_columns(st["id"], ("attempts", "beam_losses", "measured_at"))
    rolled = _facts.rolled_back_at(st, comp)
    active = comp.get("active") or {}
    active_here = active.get("campaign") == st["id"] and active.get("origin") != "controller"
    fitting = st["id"] in svc.health()["fitting"]
    since = next((t["at"] for t in reversed(st.get("transitions") or ())
                  if t["to_state"] == "measured"), None)
    models = [m for m, f in (st.get("fits") or {}).items()
              if m != "nominal" and not f.get("error")]
    return _pages.campaign_live(
        st, session=s, steps=_facts.steps(st, rolled_back=rolled is not None),
        prog=_facts.progress(st, rows), fitting=fitting, fit_since=since,
        active_here=active_here, rolled_back=rolled,
        verify_count=svc.config.compensation.verify_count, models=models,
        has_report=_report_path(st).is_file())


@_PAGES.get("/station/campaigns/{cid}", name="station.campaign_view")
async def campaign_view(request: web.Request) -> web.StreamResponse:
    s, new = _require(request)
    svc = request.app[_SERVICE]
    st = svc.status(request.match_info["cid"])
    comp = svc.compensation()
    live = _campaign_live(svc, st, s, comp)
    if request.query.get("fragment") == "live":
        resp: web.StreamResponse = web.json_response({
            "live": live, "banner": _banner(svc, comp),
            "report": _report_box(st)})
        return _finish(_headers(resp), s, new)
    page = _pages.campaign_page(st, live, session=s, banner_html=_banner(svc, comp),
                                has_report=_report_path(st).is_file())
    return _finish(_html(page.replace("data-live=", f'data-seq="{svc.events.last_seq}" '
                                                    "data-live=", 1)), s, new)


def _distances(model: Any, rows: list[tuple[Any, ...]]) -> list[list[float]]:
    """``[pose, |measured - predicted| mm]`` from ``(pose, q_act_deg JSON, x, y, z)`` rows."""
    q = np.radians(np.array([json.loads(r[1]) for r in rows], dtype=float))
    p = np.array([r[2:5] for r in rows], dtype=float)
    d = np.linalg.norm(p - 1000.0 * model.predict(q), axis=1)
    return [[r[0], round(float(x), 5)] for r, x in zip(rows, d, strict=True)]


async def _residuals(request: web.Request, cid: str, model: str) -> list[list[float]] | None:
    """|measured - predicted| (mm) per pose for a fitted model; cached (a fit never changes).

    The store is read on the loop (its connection belongs to this thread); the decoding and
    the kinematics of 10,000 poses run in a thread, so live updates keep flowing meanwhile.
    """
    cache = request.app[_RESIDUALS]
    key = (cid, model)
    if key not in cache:
        svc = request.app[_SERVICE]
        try:
            m = svc.fitted_model(cid, model)
        except RobocalError:
            return None
        rows = svc.store.measurement_columns(cid, ("pose_idx", "q_act_deg", "x_mm", "y_mm",
                                                   "z_mm"))
        cache[key] = await asyncio.to_thread(_distances, m, rows)
    return cache[key]


@_PAGES.get("/station/campaigns/{cid}/points", name="station.points")
async def points(request: web.Request) -> web.StreamResponse:
    """Plot data: per pose ``[index, reading spread mm, held out?]``, and per fitted model
    ``[index, |residual| mm]``."""
    s, new = _require(request)
    svc = request.app[_SERVICE]
    cid = request.match_info["cid"]
    st = svc.status(cid)
    rows = svc.store.measurement_columns(cid, ("pose_idx", "rms_mm", "purpose"))
    spread = [[i, None if r is None else round(r, 5), 0 if p == "calibration" else 1]
              for i, r, p in rows]
    models: dict[str, list[list[float]]] = {}
    if st["state"] not in _BEFORE_FIT and rows:
        names = ["nominal", st.get("selected_model")]
        for name in dict.fromkeys(n for n in names if n and n in (st.get("fits") or {})):
            res = await _residuals(request, cid, name)
            if res is not None:
                models[name] = res
    resp = web.json_response({"spread": spread, "models": models,
                              "selected": st.get("selected_model")})
    return _finish(_headers(resp), s, new)


@_PAGES.get("/campaigns/{cid}/report", name="station.report")
async def report(request: web.Request) -> web.StreamResponse:
    _require(request)
    st = request.app[_SERVICE].status(request.match_info["cid"])
    path = _report_path(st)
    if not path.is_file():
        return _html("<!doctype html><html lang=\"en\"><title>no report</title><p>No report "
                     "yet: it is written when the fit ends (unless fit.report is off).</p>",
                     status=404)
    resp = web.Response(body=path.read_bytes(), content_type="text/html", charset="utf-8")
    return _headers(resp, _REPORT_CSP)


@_PAGES.get("/station/static/{name}", name="station.static")
async def static(request: web.Request) -> web.StreamResponse:
    name = request.match_info["name"]
    if name not in _STATIC:
        raise web.HTTPNotFound(reason="no such asset")
    data = resources.files(__package__).joinpath("static", name).read_bytes()
    resp = web.Response(body=data, content_type=_STATIC[name], charset="utf-8")
    resp.headers["Cache-Control"] = "max-age=300"
    resp.headers["X-Content-Type-Options"] = "nosniff"
    return resp


# --- sign-in ------------------------------------------------------------------------------
def next_url(url: str) -> str:
    """Where to go after signing in: a path on this daemon, never another site (browsers
    read ``/\\host`` as ``//host``; control characters are dropped by them)."""
    parts = urlsplit(url)
    if (parts.scheme or parts.netloc or not url.startswith("/") or url.startswith("//")
            or "\\" in url or any(ord(c) < 0x21 or c == "\x7f" for c in url)):
        return "/station/"
    return url


@_PAGES.get("/station/login", name="station.login_form")
async def login_form(request: web.Request) -> web.StreamResponse:
    s, _new = _session(request)
    if s is not None and not _new:
        raise web.HTTPSeeOther("/station/")
    if request.app[_LOCAL]:
        raise web.HTTPSeeOther("/station/")  # the socket's permissions already let you in
    nonce = secrets.token_urlsafe(24)
    resp = _html(_pages.login_page(login_csrf=nonce,
                                   next_url=next_url(request.query.get("next", "/station/"))))
    _set_cookie(resp, _LOGIN_COOKIE, nonce, max_age=3600)
    return resp


@_PAGES.post("/station/login", name="station.login")
async def login(request: web.Request) -> web.StreamResponse:
    check_same_origin(request)
    store = request.app[_SESSIONS]
    peer = request.app[_PEER](request)
    form = await request.post()
    nonce = request.cookies.get(_LOGIN_COOKIE, "")
    got = form.get("csrf")
    if not nonce or not isinstance(got, str) or not hmac.compare_digest(got.encode(),
                                                                        nonce.encode()):
        raise web.HTTPForbidden(reason="sign-in form expired or cross-site; reload it")
    if store.locked_out(peer):
        raise web.HTTPTooManyRequests(reason="too many failed sign-ins; wait a minute")
    token = form.get("token")
    name = _fields(form, "name", 40)
    role: Any = None
    if isinstance(token, str):
        for r, secret in request.app[_TOKENS].items():
            if hmac.compare_digest(token.strip().encode(), secret.encode()):
                role = r
    if role is None:
        n = store.failed(peer)
        _log.warning("station sign-in failed", peer=peer, failures_last_minute=n)
        resp = _html(_pages.login_page(login_csrf=nonce, error="That token is not valid.",
                                       next_url=next_url(_fields(form, "next"))), status=401)
        return resp
    s = store.new(role, name=name, peer=peer)
    _log.info("station sign-in", actor=s.actor, role=role)
    resp = _redirect(next_url(_fields(form, "next") or "/station/"))
    _set_cookie(resp, COOKIE, s.id, max_age=None)
    resp.del_cookie(_LOGIN_COOKIE, path="/")
    return resp


@_PAGES.post("/station/logout", name="station.logout")
async def logout(request: web.Request) -> web.StreamResponse:
    s, _form = await _post(request, operator=False)
    request.app[_SESSIONS].drop(s.id)
    _log.info("station sign-out", actor=s.actor)
    resp = _redirect("/station/login")
    resp.del_cookie(COOKIE, path="/")
    return resp


# --- actions ------------------------------------------------------------------------------
@_PAGES.post("/station/campaigns", name="station.start_plan")
async def start_from_plan(request: web.Request) -> web.StreamResponse:
    s, form = await _post(request)
    svc = request.app[_SERVICE]
    raw = _fields(form, "plan", 4096)
    name = _fields(form, "name", 200) or None
    try:
        path = Path(raw).expanduser()
        if not raw or not path.is_absolute():
            raise ValueError("give the plan file's full path on this PC (starting with /)")
        if not path.is_file():
            raise ValueError(f"no plan file at {path}")
        if path.stat().st_size > _MAX_PLAN_BYTES:
            raise ValueError(f"{path} is larger than {_MAX_PLAN_BYTES // 2**20} MiB")
        doc = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(doc, dict):
            raise ValueError(f"{path} is not a plan (a JSON object)")
        st = await svc.create(doc, actor=s.actor, name=name, start=True)
    except (OSError, UnicodeDecodeError, ValueError, RobocalError) as err:
        s.flash.append(("error", f"Not started: {err}"))
        return _redirect("/station/")
    s.flash.append(("ok", f"Campaign {st['id']} started from {path}."))
    return _redirect(f"/station/campaigns/{st['id']}")


@_PAGES.post("/station/campaigns/{cid}/{action}", name="station.action")
async def action(request: web.Request) -> web.StreamResponse:
    s, form = await _post(request)
    svc = request.app[_SERVICE]
    cid, act = request.match_info["cid"], request.match_info["action"]
    if act not in _ACTIONS:
        raise web.HTTPNotFound(reason=f"unknown action {act!r}")
    svc.status(cid)  # 404 for an unknown campaign
    reason = _fields(form, "reason")
    t0 = time.monotonic()
    try:
        if act == "start":
            await svc.start_campaign(cid, actor=s.actor)
        elif act == "pause":
            await svc.pause(cid, actor=s.actor, reason=reason)
        elif act == "resume":
            await svc.resume(cid, actor=s.actor)
        elif act == "abort":
            await svc.abort(cid, actor=s.actor, reason=reason)
        elif act == "approve":
            await svc.approve(cid, actor=s.actor, model=_fields(form, "model", 64) or None)
        elif act == "push":
            await svc.push(cid, actor=s.actor, reason=reason)
        else:
            await svc.rollback(actor=s.actor, reason=reason)
    except RobocalError as err:
        s.flash.append(("error", f"{act} refused: {err}"))
    else:
        s.flash.append(("ok", f"{act}: done in {time.monotonic() - t0:.1f} s."))
    return _redirect(f"/station/campaigns/{cid}")


@_PAGES.post("/station/checks/{what:(run|recalibrate)}", name="station.check")
async def check_action(request: web.Request) -> web.StreamResponse:
    """Run a drift check now, or (``recalibrate``) start the reuse refit a check recommends."""
    s, form = await _post(request)
    svc = request.app[_SERVICE]
    try:
        if request.match_info["what"] == "recalibrate":
            check = _fields(form, "check", 18)
            st = await svc.checks.recalibrate(actor=s.actor,
                                              check_id=int(check) if check.isdigit() else None)
            s.flash.append(("ok", f"Re-calibration with --reuse started: campaign {st['id']}."))
            return _redirect(f"/station/campaigns/{st['id']}")
        c = await svc.checks.start(actor=s.actor)
    except RobocalError as err:
        s.flash.append(("error", f"Not started: {err}"))
        return _redirect("/station/")
    s.flash.append(("ok", f"Drift check {c['id']} started (campaign {c['campaign']})."))
    return _redirect(f"/station/campaigns/{c['campaign']}")


def register(app: web.Application, service: CalibrationService, sessions: SessionStore, *,
             local: bool, tokens: dict[str, str], peer: Callable[[web.Request], str]) -> None:
    """Add the station's routes to the API's ``app``.

    ``local``: the Unix-socket listener (no sign-in; operator sessions on first visit).
    ``tokens``: role -> secret accepted by the sign-in form (TCP).
    """
    app[_SERVICE] = service
    app[_SESSIONS] = sessions
    app[_LOCAL] = local
    app[_TOKENS] = tokens
    app[_PEER] = peer
    app[_RESIDUALS] = {}
    app.router.add_routes(_PAGES)

