"""Verification runs are children of their push (issue 32): not in the campaign list, and a
rollback (or a new push) while one measures stops it instead of refusing, naming a campaign
the operator never started."""

from __future__ import annotations

import asyncio

import pytest

from robocal.daemon.service import CalibrationService
from tests._waiting import eventually
from tests.unit.daemon.test_service import program_plan


@pytest.fixture
async def svc(make_config):
    s = CalibrationService(make_config(limits={"max_joint_correction_deg": 5.0},
                                       compensation={"verify_count": 8}))
    await s.start()
    yield s
    await s.stop()


async def test_rollback_while_the_push_is_remeasured_stops_the_run_and_rolls_back(svc):
    st = await svc.create(program_plan(36, validation=10), actor="a")
    cid = st["id"]
    await svc.wait(cid, ["fitted"], timeout=60)
    await svc.approve(cid, actor="a")
    robot = await svc.hub.robot()
    move = robot.move_to
    slow = asyncio.Event()

    async def slow_move(*args, **kwargs):  # type: ignore[no-untyped-def]
        if slow.is_set():  # the re-measurement takes a while, as on a real robot
            await asyncio.sleep(0.02)
        return await move(*args, **kwargs)

    robot.move_to = slow_move
    slow.set()
    key = (await svc.push(cid, actor="a"))["push"]["key"]
    v = await eventually(lambda: (svc.journal.verification(key) or {}).get("state")
                         == "measuring" and svc.journal.verification(key), 10)
    child = str(v["campaign"])
    await eventually(lambda: svc.health()["measuring"] == child, 10)
    # the child is the push's, not a campaign of the list
    assert [c["id"] for c in svc.list()] == [cid]
    assert svc.status(child)["verifies"] == key
    slow.clear()
    out = await svc.rollback(actor="a", reason="wrong model")
    assert out["active"]["kind"] == "snapshot"
    v = svc.journal.verification(key)
    assert v["state"] == "skipped" and "stopped before the end" in v["reason"]
    assert svc.status(child)["state"] == "aborted"
    rb = svc.journal.entries()[-1]
    assert rb.action == "rollback"
    done = await svc.wait_verification(rb.key, timeout=60)
    assert done is not None and done["state"] == "done", done
    assert [c["id"] for c in svc.list()] == [cid]


async def test_push_rollback_push_status_list_and_api_agree_at_every_step(make_config):
    """One truth of where each push's table is (issue 32): active, superseded or rolled back,
    the same in status, list, ``GET /compensation`` and the CLI's text."""
    from aiohttp.test_utils import TestClient, TestServer

    from robocal.cli._campaign import _describe
    from robocal.daemon.api import make_app
    from tests.unit.daemon.test_push_abort_race import _approved_copy, _fitted

    svc = CalibrationService(make_config(limits={"max_joint_correction_deg": 5.0},
                                         compensation={"verify_count": 0}))
    await svc.start()
    try:
        src = await _fitted(svc)
        doc = program_plan(36, validation=6)
        a, b, c = (_approved_copy(svc, src, doc) for _ in range(3))
        async with TestClient(TestServer(make_app(svc))) as http:

            async def agree(expected: dict[str, str | None]) -> None:
                listed = {x["id"]: x for x in await (await http.get("/campaigns")).json()}
                history = (await (await http.get("/compensation")).json())["history"]
                by_campaign = {h["campaign"]: h.get("compensation_state")
                               for h in history if h["action"] == "push"}
                for cid, want in expected.items():
                    st = await (await http.get(f"/campaigns/{cid}")).json()
                    assert st.get("compensation_state") == want, (cid, st)
                    assert listed[cid].get("compensation_state") == want
                    assert by_campaign.get(cid) == want
                    if want is not None:
                        assert st["push"]["compensation_state"] == want
                        shown = _describe(st).splitlines()[1]
                        assert f"pushed (push {st['push_key']}: {want})" in shown, shown

            async def post(path: str) -> None:
                r = await http.post(path, json={})
                assert r.status == 200, await r.text()

            await agree({a: None, b: None, c: None})
            await post(f"/campaigns/{a}/push")
            await agree({a: "active", b: None})
            await post(f"/campaigns/{b}/push")
            await agree({a: "superseded", b: "active"})
            await post("/compensation/rollback")
            await agree({a: "active", b: "rolled back"})
            await post("/compensation/rollback")
            await agree({a: "rolled back", b: "rolled back"})
            await post(f"/campaigns/{c}/push")
            await agree({a: "rolled back", b: "rolled back", c: "active"})
    finally:
        await svc.stop()


async def test_cli_push_and_rollback_end_with_the_measured_before_and_after(make_config,
                                                                             tmp_path, capsys):
    """``campaign push`` and ``compensation rollback`` return once their re-measurement
    ended, and print it (issue 32); ``--no-wait`` returns at once."""
    from robocal.cli.main import main
    from robocal.daemon.api import ApiServer

    sock = tmp_path / "api.sock"
    cfg = make_config(api={"socket": str(sock)}, robot={"options": {"move_time_s": 0.01}},
                      limits={"max_joint_correction_deg": 5.0},
                      compensation={"verify_count": 4})
    svc = CalibrationService(cfg)
    await svc.start()
    api = ApiServer(svc, cfg)
    await api.start()

    async def cli(*argv: str) -> tuple[int, str]:
        rc = await asyncio.wait_for(asyncio.to_thread(main, [*argv, "--socket", str(sock)]),
                                    60)
        return rc, capsys.readouterr().out

    try:
        st = await svc.create(program_plan(36, validation=10), actor="a")
        cid = st["id"]
        await svc.wait(cid, ["fitted"], timeout=60)
        await svc.approve(cid, actor="a")
        rc, out = await cli("campaign", "push", cid)
        assert rc == 0, out
        key = svc.journal.entries(campaign=cid)[-1].key
        assert svc.journal.verification(key)["state"] == "done"  # finished when it returned
        assert "mm before ->" in out and "mm after (RMS of 4 re-measured targets)" in out
        rc, out = await cli("compensation", "rollback", "--reason", "test")
        assert rc == 0, out
        rb = svc.journal.entries()[-1]
        assert rb.action == "rollback" and svc.journal.verification(rb.key)["state"] == "done"
        assert "mm before ->" in out
    finally:
        await api.stop()
        await svc.stop()


async def test_a_campaign_refused_during_a_remeasurement_says_what_measures(svc):
    from robocal.errors import CampaignError

    st = await svc.create(program_plan(36, validation=10), actor="a")
    cid = st["id"]
    await svc.wait(cid, ["fitted"], timeout=60)
    await svc.approve(cid, actor="a")
    robot = await svc.hub.robot()
    move = robot.move_to

    async def slow_move(*args, **kwargs):  # type: ignore[no-untyped-def]
        await asyncio.sleep(0.02)
        return await move(*args, **kwargs)

    robot.move_to = slow_move
    key = (await svc.push(cid, actor="a"))["push"]["key"]
    await eventually(lambda: svc._verifying() is not None, 10)
    with pytest.raises(CampaignError, match=f"re-measuring the targets of push or rollback "
                                            f"{key}"):
        await svc.create(program_plan(20, seed=4, validation=5), actor="a")
