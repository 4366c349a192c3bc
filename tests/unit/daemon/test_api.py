"""The HTTP API: routes, OpenAPI, JSON errors, bearer token on TCP, socket mode, fuzzing."""

from __future__ import annotations

import json
import os
import stat

import aiohttp
import pytest
from aiohttp.test_utils import TestClient, TestServer
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robocal.daemon.api import ApiServer, make_app, openapi_spec
from robocal.daemon.client import ApiError, DaemonClient
from robocal.daemon.service import CalibrationService

TOKEN = "s3cret-token-0123456789"


@pytest.fixture
async def client(svc):
    async with TestClient(TestServer(make_app(svc))) as c:
        yield c


async def test_openapi_lists_every_route(client):
    r = await client.get("/openapi.json")
    spec = await r.json()
    assert r.status == 200 and spec["openapi"].startswith("3.")
    for path in ("/campaigns", "/campaigns/{cid}", "/campaigns/{cid}/push", "/events",
                 "/compensation/rollback", "/audit", "/health"):
        assert path in spec["paths"]
    assert "CreateCampaignRequest" in spec["components"]["schemas"]
    assert openapi_spec() == spec


async def test_campaign_over_http(client, svc, real_plan):
    r = await client.post("/campaigns", json={"plan": real_plan, "name": "http"},
                          headers={"X-Robocal-Actor": "alice"})
    body = await r.json()
    assert r.status == 201, body
    cid = body["id"]
    assert body["state"] == "running" and body["poses_total"] == 25
    st = await svc.wait(cid, ["fitted"], timeout=60)
    assert st["state"] == "fitted"
    r = await client.get(f"/campaigns/{cid}")
    body = await r.json()
    assert body["state"] == "fitted" and body["poses_measured"] == 25
    r = await client.get(f"/campaigns/{cid}/measurements")
    assert len(await r.json()) == 25
    r = await client.post(f"/campaigns/{cid}/push")
    assert r.status == 409 and (await r.json())["error"]["type"] == "ApprovalRequired"
    r = await client.post(f"/campaigns/{cid}/approve", json={"model": "constant"})
    assert r.status == 200
    r = await client.post(f"/campaigns/{cid}/push")
    assert r.status == 200 and (await r.json())["state"] == "pushed"
    r = await client.get("/audit")
    actors: dict[str, str] = {}
    for a in await r.json():  # the first of each (the push's verification run comes later)
        actors.setdefault(a["action"], a["actor"])
    assert actors["campaign.create"].startswith("alice")
    r = await client.get("/events/poll", params={"campaign": cid, "timeout": "0"})
    kinds = {e["kind"] for e in (await r.json())["events"]}
    assert {"state", "pose", "fit", "compensation"} <= kinds


async def test_sse_stream(client, svc):
    svc.events.emit("log", "abc", text="hello")
    async with client.get("/events", params={"after": "0"}) as r:
        assert r.headers["Content-Type"].startswith("text/event-stream")
        lines = []
        async for raw in r.content:
            lines.append(raw.decode().rstrip("\n"))
            if lines[-1] == "" and len(lines) > 2:
                break
    assert lines[0].startswith("id: ") and lines[1] == "event: log"
    assert json.loads(lines[2][len("data: "):])["text"] == "hello"


async def _first_event(client, last_event_id: str) -> dict:
    async with client.get("/events", headers={"Last-Event-ID": last_event_id}) as r:
        async for raw in r.content:
            line = raw.decode().rstrip("\n")
            if line.startswith("data: "):
                return json.loads(line[len("data: "):])
    raise AssertionError("no event")


async def test_sse_ids_name_the_daemon_run(client, svc):
    """A client reconnecting with an id from an earlier daemon run is not starved."""
    first = svc.events.emit("log", None, text="one")
    svc.events.emit("log", None, text="two")
    own = svc.events.event_id(first)
    assert own == f"{svc.events.boot_id}-{first['seq']}"
    assert (await _first_event(client, own))["text"] == "two"        # this run: after it
    stale = f"0000dead-{first['seq'] + 500}"                          # an earlier run, later seq
    assert (await _first_event(client, stale))["text"] == "one"       # replayed from the start
    assert (await _first_event(client, "17"))["text"] == "one"        # an old-style bare number


@pytest.mark.parametrize(("method", "path", "body", "status"), [
    ("POST", "/campaigns", b"{not json", 400),
    ("POST", "/campaigns", b"[1, 2]", 400),
    ("POST", "/campaigns", b"", 400),
    ("POST", "/campaigns", b'{"plan": 3}', 422),
    ("POST", "/campaigns", b'{"plan": {}, "extra": 1}', 422),
    ("POST", "/campaigns", b'{"plan": {"poses": []}}', 422),
    ("POST", "/campaigns", b'{"plan": {"format": "robocal.plan/1", "poses": [1]}}', 422),
    ("GET", "/campaigns/nope", None, 404),
    ("POST", "/campaigns/nope/resume", None, 404),
    ("POST", "/campaigns/nope/fly", None, 404),
    ("GET", "/nowhere", None, 404),
    ("DELETE", "/campaigns", None, 405),
    ("GET", "/audit?limit=x", None, 400),
    ("GET", "/events/poll?after=-1", None, 400),
    ("POST", "/compensation/rollback", None, 422),
])
async def test_malformed_requests_get_json_4xx(client, method, path, body, status):
    r = await client.request(method, path, data=body,
                             headers={"Content-Type": "application/json"})
    assert r.status == status
    err = (await r.json())["error"]
    assert err["status"] == status and err["message"] is not None


async def test_oversized_body_is_413(svc):
    async with TestClient(TestServer(make_app(svc, max_body_bytes=2048))) as c:
        r = await c.post("/campaigns", data=b"x" * 5000)
        assert r.status == 413 and "error" in await r.json()


async def test_tcp_needs_the_bearer_token(svc):
    async with TestClient(TestServer(make_app(svc, token=TOKEN))) as c:
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": TOKEN}):
            r = await c.get("/campaigns", headers=headers)
            assert r.status == 401
            assert r.headers["WWW-Authenticate"].startswith("Bearer")
        r = await c.post("/campaigns", data=b"{}")
        assert r.status == 401
        r = await c.get("/campaigns", headers={"Authorization": f"Bearer {TOKEN}"})
        assert r.status == 200 and await r.json() == []


async def test_unix_socket_mode_and_client(make_config, tmp_path):
    tok = tmp_path / "token"
    tok.write_text(TOKEN + "\n")
    tok.chmod(0o600)
    cfg = make_config(api={"socket": str(tmp_path / "run" / "api.sock"), "tcp_port": 0,
                           "token_file": str(tok)})
    svc = CalibrationService(cfg)
    await svc.start()
    api = ApiServer(svc, cfg)
    await api.start()
    try:
        path = tmp_path / "run" / "api.sock"
        assert stat.S_ISSOCK(os.stat(path).st_mode)
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o660
        conn = aiohttp.UnixConnector(path=str(path))
        async with aiohttp.ClientSession(connector=conn) as s, \
                s.get("http://daemon/health") as r:
            assert r.status == 200 and (await r.json())["status"] == "ok"
        async with aiohttp.ClientSession() as s, \
                s.get(f"http://127.0.0.1:{api.tcp_port}/health") as r:
            assert r.status == 401
        endpoints = json.loads((cfg.data_dir / "api.json").read_text())
        assert endpoints["socket"] == str(path) and endpoints["url"].endswith(str(api.tcp_port))
    finally:
        await api.stop()
        await svc.stop()
    assert not path.exists()


async def test_stale_socket_is_replaced(make_config, tmp_path):
    import socket

    path = tmp_path / "api.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.close()  # a socket file nobody listens on: what a kill -9 leaves behind
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    with pytest.raises(ConnectionRefusedError):
        probe.connect(str(path))
    probe.close()
    cfg = make_config(api={"socket": str(path)})
    svc = CalibrationService(cfg)
    await svc.start(connect=False)
    api = ApiServer(svc, cfg)
    await api.start()
    try:
        assert api.socket_path == path and stat.S_ISSOCK(os.stat(path).st_mode)
        conn = aiohttp.UnixConnector(path=str(path))  # refused above, served now
        async with aiohttp.ClientSession(connector=conn) as session, \
                session.get("http://daemon/health") as r:
            assert r.status == 200 and (await r.json())["status"] == "ok"
    finally:
        await api.stop()
        await svc.stop()
    assert not path.exists()


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.sampled_from(["plan", "name", "start", "poses", "q_deg", "purpose",
                                       "reason", "model", "format", "x"]), children, max_size=4),
    max_leaves=20,
)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(body=_json, path=st.sampled_from(["/campaigns", "/campaigns/abc/pause",
                                         "/campaigns/abc/approve", "/compensation/rollback"]))
async def test_fuzzed_bodies_never_crash(client, body, path):
    r = await client.post(path, data=json.dumps(body).encode())
    assert 400 <= r.status < 500, await r.text()
    assert "error" in await r.json()
    r = await client.get("/health")
    assert r.status == 200


async def test_client_reports_api_errors(make_config, tmp_path):
    cfg = make_config(api={"socket": str(tmp_path / "c.sock")})
    svc = CalibrationService(cfg)
    await svc.start(connect=False)
    api = ApiServer(svc, cfg)
    await api.start()
    try:
        import asyncio

        c = DaemonClient(socket_path=tmp_path / "c.sock")
        out = await asyncio.to_thread(c.request, "GET", "/campaigns")
        assert out == []
        with pytest.raises(ApiError) as info:
            await asyncio.to_thread(c.request, "GET", "/campaigns/nope")
        assert info.value.status == 404
    finally:
        await api.stop()
        await svc.stop()
