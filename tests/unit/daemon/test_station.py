"""The operator's station over HTTP (no browser): sign-in, roles, CSRF, what pages show.

The browser end-to-end run is tests/integration/test_station_browser.py.
"""

from __future__ import annotations

import logging
import re
from urllib.parse import urlsplit

import pytest
import structlog
from aiohttp.test_utils import TestClient, TestServer
from hypothesis import given
from hypothesis import strategies as hs

from robocal.daemon import station
from robocal.daemon.api import make_app
from robocal.daemon.service import CalibrationService
from robocal.daemon.station import next_url
from tests.unit.daemon.conftest import random_plan

TOKEN = "operator-token-0123456789abcdef"
VIEWER = "viewer-token-fedcba9876543210"


@pytest.fixture
async def client(svc):
    async with TestClient(TestServer(make_app(svc, token=TOKEN, viewer_token=VIEWER))) as c:
        yield c


def _csrf(page: str) -> str:
    m = re.search(r'name="csrf" value="([^"]+)"', page)
    assert m, page
    return m.group(1)


async def _sign_in(c: TestClient, token: str, name: str = "alice") -> str:
    """Sign in through the form; returns the campaigns page."""
    r = await c.get("/station/login")
    assert r.status == 200
    form = await r.text()
    r = await c.post("/station/login", data={"csrf": _csrf(form), "token": token,
                                             "name": name, "next": "/station/"})
    assert r.status == 200 and r.url.path == "/station/", await r.text()
    return await r.text()


async def _fitted(svc: CalibrationService) -> str:
    st = await svc.create(random_plan(16, validation=4), actor="t")
    st = await svc.wait(st["id"], ["fitted"], timeout=60)
    assert st["state"] == "fitted", st["reason"]
    return str(st["id"])


async def test_pages_need_sign_in_and_api_stays_bearer_only(client):
    for path in ("/", "/station/", "/campaigns/x/report"):
        r = await client.get(path, allow_redirects=False)
        assert r.status == 303 and r.headers["Location"] == "/station/login"
    r = await client.get("/station/", allow_redirects=False)
    assert r.status == 303 and r.headers["Location"] == "/station/login"
    for path in ("/campaigns", "/health", "/events/poll?timeout=0"):
        assert (await client.get(path)).status == 401
    # an unauthenticated POST is refused, to the API and to the station
    assert (await client.post("/campaigns", data=b"{}")).status == 401
    r = await client.post("/station/campaigns/x/push", data={"csrf": "x"})
    assert r.status == 401


async def test_sign_in_sets_a_strict_httponly_cookie_and_never_shows_the_token(client, svc,
                                                                             monkeypatch):
    cap = structlog.testing.LogCapture()
    structlog.configure(processors=[cap])
    # a fresh logger: structlog caches one on first use, under an earlier test's configuration
    monkeypatch.setattr(station, "_log", structlog.get_logger("robocal.daemon.station"))
    try:
        r = await client.get("/station/login")
        form = await r.text()
        bad = await client.post("/station/login", data={"csrf": _csrf(form), "token": "nope"})
        assert bad.status == 401 and "not valid" in await bad.text()
        r = await client.post("/station/login", data={"csrf": _csrf(form), "token": TOKEN,
                                                      "name": "alice"},
                              allow_redirects=False)
        assert r.status == 303
        cookie = r.headers.getall("Set-Cookie")
        session = next(c for c in cookie if c.startswith("robocal_session="))
        assert "HttpOnly" in session and "SameSite=Strict" in session
        assert TOKEN not in session
        page = await (await client.get("/station/")).text()
        assert "Campaigns" in page and "alice" in page and "operator" in page
        assert TOKEN not in page and VIEWER not in page
    finally:
        structlog.reset_defaults()
    logged = repr(cap.entries)
    assert "station sign-in" in logged and "station sign-in failed" in logged
    assert TOKEN not in logged


async def test_cross_site_and_csrf_less_posts_are_refused(client, svc):
    cid = await _fitted(svc)
    page = await _sign_in(client, TOKEN)
    csrf = _csrf(page)
    url = f"/station/campaigns/{cid}/approve"
    assert (await client.post(url, data={"model": "constant"})).status == 403
    assert (await client.post(url, data={"csrf": "forged", "model": "constant"})).status == 403
    for origin in ("http://evil.example", "null", f"http://{client.host}:1"):
        r = await client.post(url, data={"csrf": csrf}, headers={"Origin": origin})
        assert r.status == 403, origin
    r = await client.post(url, data={"csrf": csrf}, headers={"Sec-Fetch-Site": "cross-site"})
    assert r.status == 403
    # the session cookie never writes through the JSON API
    assert (await client.post(f"/campaigns/{cid}/approve", data=b"{}")).status == 401
    assert svc.status(cid)["state"] == "fitted"
    r = await client.post(url, data={"csrf": csrf, "model": "constant"})
    assert r.status == 200 and svc.status(cid)["state"] == "approved"
    approve = [a for a in svc.audit() if a["action"] == "campaign.approve"][-1]
    assert approve["actor"].startswith("alice (operator) via station")


async def test_a_viewer_reads_but_cannot_approve_or_push(client, svc):
    cid = await _fitted(svc)
    page = await _sign_in(client, VIEWER, name="vic")
    assert "read only" in page and 'id="start"' not in page
    page = await (await client.get(f"/station/campaigns/{cid}")).text()
    assert "act-approve" not in page and "read only" in page
    csrf = _csrf(page)  # the sign-out form's: a valid token, still not enough
    for act in ("approve", "push", "rollback", "abort"):
        r = await client.post(f"/station/campaigns/{cid}/{act}", data={"csrf": csrf})
        assert r.status == 403, act
    assert svc.status(cid)["state"] == "fitted"
    # the viewer token as a bearer reads the API but cannot write
    h = {"Authorization": f"Bearer {VIEWER}"}
    assert (await client.get("/campaigns", headers=h)).status == 200
    r = await client.post(f"/campaigns/{cid}/approve", headers=h, data=b"{}")
    assert r.status == 403 and svc.status(cid)["state"] == "fitted"


async def test_campaign_page_shows_fits_steps_and_plot_data(client, svc):
    cid = await _fitted(svc)
    await _sign_in(client, TOKEN)
    page = await (await client.get(f"/station/campaigns/{cid}")).text()
    assert '<li class="step current" aria-current="step">review</li>' in page
    assert "Held-out RMS" in page and "act-approve" in page
    live = await (await client.get(f"/station/campaigns/{cid}?fragment=live")).json()
    assert "original values" in live["banner"] and 'data-state="fitted"' in live["live"]
    pts = await (await client.get(f"/station/campaigns/{cid}/points")).json()
    assert len(pts["spread"]) == 16 and set(pts["models"]) == {"nominal", "constant"}
    # the fitted model explains the measurements far better than the nominal one
    med = sorted(v for _, v in pts["models"]["constant"])[8]
    assert med < 0.2 * sorted(v for _, v in pts["models"]["nominal"])[8]
    r = await client.get(f"/campaigns/{cid}/report")
    assert r.status == 404  # the test configuration writes no report


@pytest.fixture(autouse=True)
def _quiet_aiohttp() -> None:
    logging.getLogger("aiohttp.access").setLevel(logging.WARNING)


async def test_on_the_unix_socket_no_token_but_csrf_still_checked(svc):
    async with TestClient(TestServer(make_app(svc))) as c:
        st = await svc.create(random_plan(2000, validation=100), actor="t")
        cid = st["id"]
        url = f"/station/campaigns/{cid}"
        page = await (await c.get(url)).text()
        assert "local · operator" in page and "act-pause" in page
        r = await c.post(f"{url}/pause", data={"reason": "x"})
        assert r.status == 403 and svc.status(cid)["state"] == "running"
        r = await c.post(f"{url}/pause", data={"csrf": _csrf(page), "reason": "fixture bump"})
        assert r.status == 200
        page = await r.text()
        assert "Paused: fixture bump" in page and "act-resume" in page
        assert svc.status(cid)["state"] == "paused"
        r = await c.post(f"{url}/abort", data={"csrf": _csrf(page), "reason": "done"})
        assert r.status == 200 and svc.status(cid)["state"] == "aborted"
        abort = [a for a in svc.audit() if a["action"] == "campaign.abort"][-1]
        assert abort["actor"].startswith("local (operator) via station")
        pause = [t for t in svc.store.transitions(cid) if t["to_state"] == "paused"][-1]
        assert pause["actor"] == abort["actor"] and pause["reason"] == "fixture bump"


async def test_repeated_failed_sign_ins_are_refused_for_a_while(client):
    form = await (await client.get("/station/login")).text()
    for _ in range(10):
        r = await client.post("/station/login", data={"csrf": _csrf(form), "token": "bad"})
        assert r.status == 401
    r = await client.post("/station/login", data={"csrf": _csrf(form), "token": TOKEN})
    assert r.status == 429


def test_viewer_token_file_needs_the_operator_token_and_must_differ(make_config, tmp_path):
    from robocal.errors import ConfigError

    with pytest.raises(ValueError, match="viewer_token_file needs token_file"):
        make_config(api={"viewer_token_file": str(tmp_path / "v")})
    same = tmp_path / "same"
    same.write_text(TOKEN)
    same.chmod(0o600)
    cfg = make_config(api={"tcp_port": 0, "token_file": str(same),
                           "viewer_token_file": str(same)})
    with pytest.raises(ConfigError, match="must differ"):
        cfg.read_viewer_token()


async def test_light_measurement_columns_refuse_anything_else(svc):
    cid = await _fitted(svc)
    rows = svc.store.measurement_columns(cid, ("pose_idx", "attempts"))
    assert [r[0] for r in rows] == [m.pose_idx for m in svc.measurements(cid)]
    for bad in (("pose_idx", "campaign; DROP TABLE measurements"), ("weather",), ()):
        with pytest.raises(ValueError, match="not readable"):
            svc.store.measurement_columns(cid, bad)


@given(hs.text(max_size=60) | hs.sampled_from(["//evil", "/\\evil", "http://evil/", "/ok",
                                               "/\t/evil", "https:evil", "/station/x?y=1"]))
def test_after_sign_in_the_browser_stays_on_this_daemon(url):
    out = next_url(url)
    assert out == "/station/" or out == url
    parts = urlsplit(out)
    assert not parts.scheme and not parts.netloc and out.startswith("/")
    assert not out.startswith("//") and "\\" not in out
    assert all(ord(c) >= 0x21 and c != "\x7f" for c in out)


async def test_signing_out_ends_the_session(client):
    page = await _sign_in(client, TOKEN)
    r = await client.post("/station/logout", data={"csrf": _csrf(page)})
    assert r.status == 200 and r.url.path == "/station/login"
    r = await client.get("/station/", allow_redirects=False)
    assert r.status == 303 and r.headers["Location"] == "/station/login"
