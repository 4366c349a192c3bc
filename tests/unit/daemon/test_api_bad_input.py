"""Pathological JSON bodies get a 4xx JSON error, never a 500, and the daemon lives on."""

from __future__ import annotations

import pytest
from aiohttp.test_utils import TestClient, TestServer

from robocal.daemon.api import make_app
from robocal.daemon.service import CalibrationService

DEEP = b"[" * 100_000 + b"]" * 100_000
HUGE_INT = b'{"plan": {"format": "robocal.plan/1", "poses": [{"index": ' + b"9" * 5000 + b"}]}}"


@pytest.fixture
async def client(make_config):
    svc = CalibrationService(make_config())
    await svc.start()
    async with TestClient(TestServer(make_app(svc, max_body_bytes=1024 * 1024))) as c:
        yield c
    await svc.stop()


@pytest.mark.parametrize("path", ["/campaigns", "/campaigns/abc/pause",
                                  "/compensation/rollback"])
@pytest.mark.parametrize("body", [DEEP, b'{"plan": ' + DEEP + b"}", HUGE_INT,
                                  b'{"reason": ' + b"1" * 5000 + b"}", b"\xff\xfe{}"])
async def test_pathological_json_is_400(client, path, body):
    r = await client.post(path, data=body, headers={"Content-Type": "application/json"})
    err = (await r.json())["error"]
    assert r.status == 400, err
    assert "not valid JSON" in err["message"]
    assert (await client.get("/health")).status == 200

