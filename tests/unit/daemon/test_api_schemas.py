"""The typed API: OpenAPI generated from the routes and models, checked against real answers.

A campaign runs over the mock drivers through HTTP (create, start/pause/resume/abort,
approve, push, rollback); every JSON answer is validated with ``jsonschema`` against the
schema ``openapi.json`` documents for its route and status, independently of pydantic.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from aiohttp.test_utils import TestClient, TestServer

from robocal.daemon.api import _ACTIONS, make_app, openapi_spec
from robocal.daemon.events import EventBus
from robocal.daemon.service import CalibrationService
from tests.unit.daemon.conftest import random_plan

SPEC = openapi_spec()


def _validator(schema: dict[str, Any]) -> jsonschema.Draft202012Validator:
    # "#/components/schemas/X" resolves against the root: carry the components along
    return jsonschema.Draft202012Validator({**schema, "components": SPEC["components"]})


class Checker:
    """Validates answers against the spec and remembers which operations were exercised."""

    def __init__(self, client: TestClient) -> None:
        self.client = client
        self.seen: set[tuple[str, str, str]] = set()

    async def call(self, method: str, path: str, doc_path: str | None = None,
                   **kwargs: Any) -> tuple[int, Any]:
        r = await self.client.request(method, path, **kwargs)
        body = await r.json()
        doc_path = doc_path or path
        op = SPEC["paths"][doc_path][method.lower()]
        key = str(r.status) if str(r.status) in op["responses"] else f"{str(r.status)[0]}XX"
        assert key in op["responses"], (method, doc_path, r.status, body)
        schema = op["responses"][key]["content"]["application/json"]["schema"]
        errors = [e.message for e in _validator(schema).iter_errors(body)]
        assert not errors, (method, doc_path, r.status, errors[:3])
        self.seen.add((doc_path, method.lower(), key))
        return r.status, body


@pytest.fixture
async def svc(make_config):
    s = CalibrationService(make_config(limits={"max_joint_correction_deg": 5.0},
                                       compensation={"verify_count": 3}))
    await s.start()
    yield s
    await s.stop()


@pytest.fixture
async def checker(svc):
    async with TestClient(TestServer(make_app(svc))) as c:
        yield Checker(c)


async def test_every_registered_route_is_documented_with_its_methods(svc):
    app = make_app(svc)
    registered: dict[str, set[str]] = {}
    for route in app.router.routes():
        if route.method == "HEAD":  # aiohttp adds HEAD to every GET
            continue
        if (route.name or "").startswith("station."):  # HTML pages, not the JSON API
            continue
        path = route.resource.canonical if route.resource is not None else ""
        paths = ([path.replace("{action}", a) for a in _ACTIONS] if "{action}" in path
                 else [path])
        for p in paths:
            registered.setdefault(p, set()).add(route.method.lower())
    documented = {p: set(ops) for p, ops in SPEC["paths"].items()}
    assert registered == documented
    assert len(documented) == 21


async def test_spec_components_are_the_models_and_served_as_generated(checker):
    schemas = SPEC["components"]["schemas"]
    for name in ("CampaignStatus", "CampaignSummary", "Health", "CompensationState",
                 "AuditEntry", "Measurement", "ErrorBody", "Event", "StateEvent",
                 "CreateCampaignRequest", "ActionRequest", "RollbackRequest"):
        assert name in schemas, name
    refs = set()

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            if "$ref" in node:
                refs.add(node["$ref"].rsplit("/", 1)[-1])
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(SPEC)
    assert refs <= set(schemas), refs - set(schemas)  # no dangling reference
    assert not any("$defs" in json.dumps(s) for s in schemas.values())
    jsonschema.Draft202012Validator.check_schema({"components": SPEC["components"]})
    status, body = await checker.call("GET", "/openapi.json")
    assert status == 200 and body == SPEC


async def test_every_documented_answer_validates_a_real_one(checker, svc, real_plan):
    c = checker
    plan = real_plan
    assert (await c.call("GET", "/health"))[0] == 200
    assert (await c.call("GET", "/openapi.json"))[0] == 200
    status, st = await c.call("POST", "/campaigns", json={"plan": plan, "name": "typed"})
    assert status == 201 and st["state"] == "running"
    cid = st["id"]
    assert (await svc.wait(cid, ["fitted"], timeout=60))["state"] == "fitted"
    doc = "/campaigns/{cid}"
    status, st = await c.call("GET", f"/campaigns/{cid}", doc)
    assert status == 200 and st["fits"]["constant"]["model"] == "constant"
    status, rows = await c.call("GET", f"/campaigns/{cid}/measurements", doc + "/measurements")
    assert status == 200 and len(rows) == st["poses_total"] == 25
    status, err = await c.call("POST", f"/campaigns/{cid}/push", doc + "/push")
    assert status == 409 and err["error"]["type"] == "ApprovalRequired"
    status, st = await c.call("POST", f"/campaigns/{cid}/approve", doc + "/approve",
                              json={"model": "constant"})
    assert status == 200 and st["state"] == "approved"
    status, st = await c.call("POST", f"/campaigns/{cid}/push", doc + "/push")
    assert status == 200 and st["state"] == "pushed" and st["push"] is not None
    v = await svc.wait_verification(st["push"]["key"], timeout=60)
    assert v is not None and v["state"] == "done"
    # the push's verification run filled in the campaign's compensation record
    status, st = await c.call("GET", f"/campaigns/{cid}", doc)
    assert st["compensation"][0]["verification"]["state"] == "done"
    # a drift check of the model now active, and the reuse refit it would start
    status, chk = await c.call("POST", "/checks", json={})
    assert status == 201 and chk["state"] == "measuring"
    await svc.checks.wait(chk["id"], timeout=60)
    status, one = await c.call("GET", f"/checks/{chk['id']}", "/checks/{check}")
    assert status == 200 and one["state"] == "done" and one["n"] == 20
    assert (await c.call("GET", "/checks"))[1][-1]["id"] == chk["id"]
    status, refit = await c.call("POST", f"/checks/{chk['id']}/recalibrate",
                                 "/checks/{check}/recalibrate")
    assert status == 201 and refit["state"] == "running"
    await svc.abort(refit["id"], actor="t")
    status, comp = await c.call("GET", "/compensation")
    assert status == 200 and comp["active"]["campaign"] == cid
    status, comp = await c.call("POST", "/compensation/rollback", json={"reason": "typed"})
    assert status == 200 and comp["active"]["kind"] == "snapshot"
    rb_key = [j for j in comp["journal"] if j["action"] == "rollback"][-1]["key"]
    assert (await svc.wait_verification(rb_key, timeout=60)) is not None
    # the report as the API serves it: none written with report = false (404) until one is
    report = doc + "/report.json"
    assert (await c.call("GET", f"/campaigns/{cid}/report.json", report))[0] == 404
    files = Path(svc.status(cid)["files"])
    files.mkdir(parents=True, exist_ok=True)
    (files / "report.json").write_text(json.dumps({"format": "robocal.report/1"}))
    status, body = await c.call("GET", f"/campaigns/{cid}/report.json", report)
    assert status == 200 and body["format"] == "robocal.report/1"

    # the other actions, on a campaign long enough to be paused while measuring (a bare
    # plan, which only the service takes: the API wants a complete one)
    st = await svc.create(random_plan(60, seed=5), actor="t", start=False)
    assert st["state"] == "created"
    cid2 = st["id"]
    for action, state in (("start", "running"), ("pause", "paused"), ("resume", "running"),
                          ("abort", "aborted")):
        status, st = await c.call("POST", f"/campaigns/{cid2}/{action}", doc + f"/{action}")
        assert status == 200 and st["state"] == state, (action, st)

    # serialised through the models, the answers are exactly what the service returns
    for path, doc_path, direct in (
            (f"/campaigns/{cid}", doc, lambda: svc.status(cid)),
            ("/compensation", "/compensation", svc.compensation),
            ("/health", "/health", svc.health)):
        body = (await c.call("GET", path, doc_path))[1]
        expected = json.loads(json.dumps(direct()))
        if path == "/health":
            body.pop("uptime_s"), expected.pop("uptime_s")
        assert body == expected, path
    status, camps = await c.call("GET", "/campaigns")
    assert status == 200 and {cid, cid2} <= {x["id"] for x in camps}
    status, log = await c.call("GET", "/audit", params={"limit": "500"})
    assert status == 200 and "compensation.rollback" in {a["action"] for a in log}
    status, polled = await c.call("GET", "/events/poll", params={"timeout": "0"})
    kinds = {e["kind"] for e in polled["events"]}
    assert {"state", "pose", "fit", "compensation"} <= kinds
    # errors: unknown campaign, bad query, bad body
    assert (await c.call("GET", "/campaigns/nope", doc))[0] == 404
    assert (await c.call("GET", "/audit", params={"limit": "x"}))[0] == 400
    assert (await c.call("POST", "/campaigns", json={"plan": plan, "bogus": 1}))[0] == 422

    documented = {(p, m, code) for p, ops in SPEC["paths"].items() for m, op in ops.items()
                  for code in op["responses"] if not code.endswith("XX")
                  and "application/json" in op["responses"][code]["content"]}
    assert documented - c.seen == set()


async def test_events_match_the_documented_event_schema(checker, svc, real_plan):
    status, st = await checker.call("POST", "/campaigns", json={"plan": real_plan})
    assert status == 201
    await svc.wait(st["id"], ["fitted"], timeout=60)
    events = svc.events.history()
    validator = _validator({"$ref": "#/components/schemas/Event"})
    for ev in events:
        assert not list(validator.iter_errors(json.loads(json.dumps(ev)))), ev
    assert {"state", "pose", "fit"} <= {e["kind"] for e in events}
    # a different kind's fields under a kind's name do not validate
    wrong = {**events[0], "kind": "pose"}
    assert list(validator.iter_errors(json.loads(json.dumps(wrong))))


def _state(**over: Any) -> dict[str, Any]:
    return {"state": "running", "reason": "", "poses_measured": 0, "poses_total": 3, **over}


@pytest.mark.parametrize("kind, data", [
    ("state", _state(extra_field=1)),                         # a field no model names
    ("state", {k: v for k, v in _state().items() if k != "reason"}),  # a missing field
    ("state", _state(state="sleeping")),                      # not a campaign state
    ("pose", {"pose": "three", "purpose": "x", "poses_measured": 1, "poses_total": 2,
              "attempts": 1, "distance_mm": None}),           # mistyped
    ("compensation", {"action": "pushed", "key": "k"}),       # unknown action
    ("telemetry", {"text": "hello"}),                         # unknown kind
])
def test_emit_refuses_a_wrong_event_and_publishes_nothing(kind, data):
    bus = EventBus()
    with pytest.raises(ValueError):
        bus.emit(kind, "c1", **data)
    assert bus.last_seq == 0 and bus.history() == []
    ev = bus.emit("state", "c1", **_state())
    assert ev["seq"] == 1 and bus.history() == [ev]


async def test_a_service_answer_off_its_model_is_a_json_500(checker, svc, monkeypatch):
    good = svc.health()
    monkeypatch.setattr(svc, "health", lambda: {**good, "renamed_key": 1})
    status, body = await checker.call("GET", "/health")
    assert status == 500 and body["error"]["type"] == "InternalError"
    assert "renamed_key" in body["error"]["message"]
