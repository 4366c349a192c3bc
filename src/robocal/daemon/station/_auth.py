"""Sign-in, sessions, roles and CSRF checks of the operator's station.

Two secrets may open the station: the daemon's API token (role ``operator``) and an optional
viewer token (role ``viewer``, read only). Signing in trades the token for a random session id
kept in an HttpOnly, SameSite=Strict cookie; the token itself is never stored in a page, a
cookie or a log line. Every state-changing station request carries the session's CSRF token
(a form field or ``X-CSRF-Token``) and, when the browser says where it comes from (``Origin``,
``Sec-Fetch-Site``), must come from this origin.

On the Unix socket the file permissions are the access control (as for the JSON API): a
client there gets an operator session without a token, but CSRF is checked all the same.
"""

from __future__ import annotations

import hmac
import re
import secrets
import time
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Literal
from urllib.parse import urlsplit

import structlog
from aiohttp import web

__all__ = [
    "COOKIE",
    "Session",
    "SessionStore",
    "auth_middleware",
    "check_same_origin",
    "is_page_path",
]

_log = structlog.get_logger(__name__)
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
Role = Literal["operator", "viewer"]

COOKIE = "robocal_session"
_NAME_RE = re.compile(r"[^A-Za-z0-9_.@-]")
_READ_METHODS = ("GET", "HEAD")


@dataclass
class Session:
    """One signed-in browser: role, who (as they typed it), CSRF token, pending messages."""

    id: str
    role: Role
    name: str
    peer: str
    csrf: str = field(default_factory=lambda: secrets.token_urlsafe(24))
    created: float = field(default_factory=time.monotonic)
    seen: float = field(default_factory=time.monotonic)
    flash: list[tuple[str, str]] = field(default_factory=list)

    @property
    def actor(self) -> str:
        """What the audit log records: ``NAME (ROLE) via station PEER``."""
        return f"{self.name or 'unnamed'} ({self.role}) via station {self.peer}"

    def check_csrf(self, got: str | None) -> bool:
        return got is not None and hmac.compare_digest(got.encode(), self.csrf.encode())


class SessionStore:
    """In-memory sessions (a daemon restart signs everyone out), bounded and expiring.

    Parameters
    ----------
    idle_s : float
        A session unused this long is gone.
    max_age_s : float
        Any session older than this is gone.
    max_sessions : int
        The oldest session is dropped beyond this many.
    """

    def __init__(self, *, idle_s: float = 8 * 3600.0, max_age_s: float = 24 * 3600.0,
                 max_sessions: int = 256) -> None:
        self.idle_s = idle_s
        self.max_age_s = max_age_s
        self.max_sessions = max_sessions
        self._sessions: OrderedDict[str, Session] = OrderedDict()
        self._failures: dict[str, deque[float]] = {}

    def new(self, role: Role, *, name: str, peer: str) -> Session:
        name = _NAME_RE.sub("", name)[:40]
        s = Session(id=secrets.token_urlsafe(32), role=role, name=name, peer=peer)
        self._sessions[s.id] = s
        while len(self._sessions) > self.max_sessions:
            self._sessions.popitem(last=False)
        return s

    def get(self, sid: str | None) -> Session | None:
        if not sid:
            return None
        s = self._sessions.get(sid)
        if s is None:
            return None
        now = time.monotonic()
        if now - s.seen > self.idle_s or now - s.created > self.max_age_s:
            del self._sessions[sid]
            return None
        s.seen = now
        return s

    def drop(self, sid: str) -> None:
        self._sessions.pop(sid, None)

    def failed(self, peer: str, *, window_s: float = 60.0) -> int:
        """Record a failed sign-in from ``peer``; returns failures within ``window_s``."""
        q = self._failures.setdefault(peer, deque(maxlen=64))
        now = time.monotonic()
        q.append(now)
        return sum(1 for t in q if now - t < window_s)

    def locked_out(self, peer: str, *, limit: int = 10, window_s: float = 60.0) -> bool:
        now = time.monotonic()
        return sum(1 for t in self._failures.get(peer, ()) if now - t < window_s) >= limit


def is_page_path(path: str) -> bool:
    """A browser page (sign-in redirect when unauthenticated) rather than a JSON route."""
    return path == "/" or path.startswith("/station") or (
        path.startswith("/campaigns/") and path.endswith("/report"))


def _public(path: str) -> bool:
    return path in ("/station/login", "/favicon.ico") or path.startswith("/station/static/")


def check_same_origin(request: web.Request) -> None:
    """Refuse (403) a request a browser marks as coming from another site.

    Raises
    ------
    web.HTTPForbidden
        If ``Origin`` names another origin or ``Sec-Fetch-Site`` says cross-site.
    """
    origin = request.headers.get("Origin")
    # host:port only: behind a TLS proxy the browser says https while the daemon sees http
    if origin is not None and urlsplit(origin).netloc != request.host:
        raise web.HTTPForbidden(reason="cross-site request refused (Origin)")
    site = request.headers.get("Sec-Fetch-Site")
    if site is not None and site not in ("same-origin", "none"):
        raise web.HTTPForbidden(reason="cross-site request refused (Sec-Fetch-Site)")


def auth_middleware(sessions: SessionStore, *, token: str, viewer_token: str | None = None
                    ) -> Callable[[web.Request, Handler], Awaitable[web.StreamResponse]]:
    """Authentication of the TCP listener.

    ``Authorization: Bearer <token>`` gives the operator role on every route (the JSON API as
    before); the viewer token as a bearer may only read. A station session cookie may read
    everything and post to the station's own routes (which check its CSRF token); it never
    writes through the JSON API. Anything else: 401, or for a page a redirect to sign-in.
    """
    operator = f"Bearer {token}".encode()
    viewer = None if viewer_token is None else f"Bearer {viewer_token}".encode()

    @web.middleware
    async def middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
        got = request.headers.get("Authorization", "").encode()
        if got:
            if hmac.compare_digest(got, operator):
                return await handler(request)
            if viewer is not None and hmac.compare_digest(got, viewer):
                if request.method not in _READ_METHODS:
                    raise web.HTTPForbidden(reason="the viewer token can only read")
                return await handler(request)
        else:
            session = sessions.get(request.cookies.get(COOKIE))
            if session is not None and (request.method in _READ_METHODS
                                        or request.path.startswith("/station/")):
                return await handler(request)
            if _public(request.path):
                return await handler(request)
            if request.method in _READ_METHODS and is_page_path(request.path):
                raise web.HTTPSeeOther("/station/login")
        body = {"error": {"type": "Unauthorized", "status": 401,
                          "message": "a valid bearer token is required"}}
        resp = web.json_response(body, status=401)
        resp.headers["WWW-Authenticate"] = 'Bearer realm="robocal"'
        return resp

    return middleware
