"""A small synchronous client of the daemon's API (stdlib ``http.client``; no event loop).

Used by ``robocal campaign ...`` and ``robocal compensation ...``. The daemon is found through
``--socket PATH`` (Unix socket), ``--url http://host:port`` with a token, or ``--config FILE``
(the daemon's own configuration: its socket, or its TCP port and token file).
"""

from __future__ import annotations

import getpass
import http.client
import json
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlencode, urlsplit

from robocal.daemon.config import load_config
from robocal.errors import ApiError, ConfigError, DaemonUnavailable

__all__ = ["ApiError", "DaemonClient", "DaemonUnavailable"]


_START_HINT = ("is the daemon running? start it with `robocal daemon --config FILE` "
               "(or `systemctl start robocal` on the cell PC)")


class _UnixConnection(http.client.HTTPConnection):
    def __init__(self, path: str, timeout: float) -> None:
        super().__init__("localhost", timeout=timeout)
        self._path = path

    def connect(self) -> None:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(self.timeout)
        try:
            s.connect(self._path)
        except OSError:
            s.close()
            raise
        self.sock = s


class DaemonClient:
    """Talk to the daemon.

    Parameters
    ----------
    socket_path : str or Path, optional
        Unix socket of the API.
    url : str, optional
        ``http://host:port`` of the TCP API (then ``token`` is needed).
    token : str, optional
        Bearer token for TCP.
    timeout : float
        Per-request timeout, seconds.
    """

    def __init__(self, *, socket_path: str | Path | None = None, url: str | None = None,
                 token: str | None = None, timeout: float = 60.0) -> None:
        if (socket_path is None) == (url is None):
            raise ConfigError("give exactly one of a socket path and a URL")
        self.socket_path = None if socket_path is None else str(socket_path)
        self.url = url
        self.token = token
        self.timeout = timeout
        #: Seconds to keep trying while nothing listens yet (a daemon that is starting).
        self.wait_s = 0.0
        try:
            self.actor = getpass.getuser()
        except (KeyError, OSError):
            self.actor = ""

    @classmethod
    def from_args(cls, *, config: str | Path | None = None, socket_path: str | Path | None = None,
                  url: str | None = None, token: str | None = None,
                  token_file: str | Path | None = None, timeout: float = 60.0) -> DaemonClient:
        """Resolve the daemon's address from CLI options (see the module docstring).

        Without any option, ``$ROBOCAL_SOCKET``, ``$ROBOCAL_URL`` (+ ``$ROBOCAL_TOKEN``) and
        ``$ROBOCAL_CONFIG`` are tried, then ``/etc/robocal/config.toml``.
        """
        if token is None and token_file is not None:
            try:
                token = Path(token_file).read_text().strip()
            except OSError as err:
                raise ConfigError(f"cannot read token file: {err}", source=str(token_file)) \
                    from err
        token = token or os.environ.get("ROBOCAL_TOKEN") or None
        if socket_path is not None:
            return cls(socket_path=socket_path, timeout=timeout)
        if url is not None:
            return cls(url=url, token=token, timeout=timeout)
        if config is None:
            if os.environ.get("ROBOCAL_SOCKET"):
                return cls(socket_path=os.environ["ROBOCAL_SOCKET"], timeout=timeout)
            if os.environ.get("ROBOCAL_URL"):
                return cls(url=os.environ["ROBOCAL_URL"], token=token, timeout=timeout)
            config = os.environ.get("ROBOCAL_CONFIG")
            if config is None:
                config = "/etc/robocal/config.toml"
                if not Path(config).exists():
                    raise ConfigError("where is the daemon? give --config FILE, --socket PATH "
                                      f"or --url URL (and {config} does not exist)")
        cfg = load_config(config)
        if cfg.socket_path is not None:
            return cls(socket_path=cfg.socket_path, timeout=timeout)
        endpoints = cfg.data_dir / "api.json"
        port = cfg.api.tcp_port
        if port == 0 and endpoints.exists():
            with_url = json.loads(endpoints.read_text()).get("url")
            return cls(url=with_url, token=token or cfg.read_token(), timeout=timeout)
        return cls(url=f"http://{cfg.api.tcp_host}:{port}", token=token or cfg.read_token(),
                   timeout=timeout)

    def _connection(self, timeout: float | None = None) -> http.client.HTTPConnection:
        t = self.timeout if timeout is None else timeout
        if self.socket_path is not None:
            return _UnixConnection(self.socket_path, t)
        parts = urlsplit(self.url or "")
        if parts.scheme != "http" or not parts.hostname:
            raise ConfigError(f"unsupported URL {self.url!r} (use http://host:port)")
        return http.client.HTTPConnection(parts.hostname, parts.port or 80, timeout=t)

    def _headers(self, body: bool) -> dict[str, str]:
        h = {"Accept": "application/json"}
        if body:
            h["Content-Type"] = "application/json"
        if self.token:
            h["Authorization"] = f"Bearer {self.token}"
        if self.actor:
            h["X-Robocal-Actor"] = self.actor
        return h

    def _where(self) -> str:
        return self.socket_path or self.url or "?"

    def request(self, method: str, path: str, body: Any = None, *,
                query: dict[str, Any] | None = None) -> Any:
        """Send one request and return the decoded JSON.

        Raises
        ------
        ApiError
            For an error response (the daemon's message is kept).
        DaemonUnavailable
            If the daemon cannot be reached.
        """
        if query:
            path = f"{path}?{urlencode(query)}"
        data = None if body is None else json.dumps(body).encode()
        conn = self._connection()
        deadline = time.monotonic() + self.wait_s
        while True:
            try:
                conn.connect()
                break
            except OSError as err:  # not listening (yet): wait for a starting daemon if asked
                conn.close()
                if time.monotonic() >= deadline:
                    raise DaemonUnavailable(f"cannot reach the daemon at {self._where()} "
                                            f"({err}); {_START_HINT}") from err
                time.sleep(0.2)
                conn = self._connection()
        try:
            conn.request(method, path, body=data, headers=self._headers(data is not None))
            resp = conn.getresponse()
            raw = resp.read()
        except (OSError, http.client.HTTPException) as err:
            raise DaemonUnavailable(f"cannot reach the daemon at {self._where()} ({err}); "
                                    f"{_START_HINT}") from err
        finally:
            conn.close()
        try:
            payload = json.loads(raw) if raw else None
        except json.JSONDecodeError:
            payload = None
        if resp.status >= 400:
            e = (payload or {}).get("error", {}) if isinstance(payload, dict) else {}
            raise ApiError(resp.status, str(e.get("type", resp.reason)),
                           str(e.get("message", raw[:200].decode(errors="replace"))))
        return payload

    def events(self, *, campaign: str | None = None, after: int = 0,
               timeout: float = 3600.0) -> Iterator[dict[str, Any]]:
        """Yield events from the Server-Sent Events stream until it ends or ``timeout``."""
        query: dict[str, Any] = {"after": after}
        if campaign:
            query["campaign"] = campaign
        conn = self._connection(timeout)
        try:
            conn.request("GET", f"/events?{urlencode(query)}",
                         headers={**self._headers(False), "Accept": "text/event-stream"})
            resp = conn.getresponse()
            if resp.status >= 400:
                raw = resp.read()
                try:
                    e = json.loads(raw).get("error", {})
                except (json.JSONDecodeError, AttributeError):
                    e = {}
                raise ApiError(resp.status, str(e.get("type", resp.reason)),
                               str(e.get("message", "")))
            data: list[str] = []
            while True:
                line = resp.readline()
                if not line:
                    return
                text = line.decode(errors="replace").rstrip("\r\n")
                if text.startswith("data:"):
                    data.append(text[5:].lstrip())
                elif not text and data:
                    yield json.loads("\n".join(data))
                    data = []
        except (OSError, http.client.HTTPException) as err:
            raise DaemonUnavailable(f"event stream from {self._where()} broke: {err}") from err
        finally:
            conn.close()
