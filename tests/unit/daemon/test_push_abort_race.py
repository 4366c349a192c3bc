"""Abort racing a push (issue 25 item 2): the controller's table and the store agree every
time, the journal never keeps an entry it cannot settle, and rollback works afterwards.

The service runs in-process over the mock controller; random delays are injected at the
driver (write and read-back of the table), and the abort is fired at a random moment of the
push, so it lands before, inside and after the write.
"""

from __future__ import annotations

import asyncio
import random

import pytest

from robocal.compensation import CompensationTable
from robocal.daemon import pushing
from robocal.daemon.campaign import CampaignState as S
from robocal.daemon.service import CalibrationService
from robocal.errors import ApprovalRequired, InvalidTransition
from tests.unit.daemon.test_service import program_plan

TRIES = 100


async def _fitted(svc: CalibrationService) -> str:
    st = await svc.create(program_plan(36, validation=6), actor="a")
    st = await svc.wait(st["id"], ["fitted"], timeout=60)
    assert st["state"] == "fitted", st["reason"]
    return str(st["id"])


def _approved_copy(svc: CalibrationService, src: str, doc) -> str:  # type: ignore[no-untyped-def]
    """A new campaign with ``src``'s plan and fitted model, moved to ``approved`` through the
    store's own transitions (measuring and fitting 100 campaigns would only cost time)."""
    st = svc.store
    rec = st.create_campaign(name="copy", robot=svc.robot.name, poses=doc.poses,
                             plan_json=doc.text, plan_digest=doc.digest, config_digest="t",
                             actor="a")
    model = st.campaign(src).selected_model
    assert model is not None
    st.save_fits(rec.id, {model: (st.fits(src)[model], st.model_json(src, model))})
    st.set_selected_model(rec.id, model)
    for to in (S.RUNNING, S.MEASURED, S.FITTED, S.APPROVED):
        st.transition(rec.id, to, actor="a", reason="test copy")
    return rec.id


async def _controller_agrees(svc: CalibrationService) -> None:
    """What the controller holds is the store's active table (or its original snapshot)."""
    robot = await svc.hub.robot()
    stack = svc.store.table_stack()
    held = await robot.read_compensation()
    if not stack:
        assert held is None
        return
    active = svc._entry(stack[-1])
    if isinstance(active, CompensationTable):
        assert held is not None and held.checksum == active.checksum
    else:  # the controller's own values, restored by a rollback of the first push
        assert await pushing.holds(robot, active)


@pytest.fixture
async def svc(make_config):
    s = CalibrationService(make_config(limits={"max_joint_correction_deg": 5.0},
                                       compensation={"verify_count": 0}))
    await s.start()
    yield s
    await s.stop()


async def test_abort_racing_a_push_leaves_controller_and_store_in_agreement(svc):
    src = await _fitted(svc)
    doc = program_plan(36, validation=6)
    rng = random.Random(25)
    robot = await svc.hub.robot()
    write, read = robot.write_compensation, robot.read_compensation

    async def slow_write(table):  # type: ignore[no-untyped-def]
        await asyncio.sleep(rng.uniform(0.0, 0.004))
        await write(table)
        await asyncio.sleep(rng.uniform(0.0, 0.004))

    async def slow_read():  # type: ignore[no-untyped-def]
        await asyncio.sleep(rng.uniform(0.0, 0.004))
        return await read()

    robot.write_compensation = slow_write
    robot.read_compensation = slow_read
    outcomes = {"pushed": 0, "aborted": 0}
    for _ in range(TRIES):
        cid = _approved_copy(svc, src, doc)
        # a third of the aborts start first; the others at a random moment of the push
        first = rng.random() < 0.3
        delay = 0.0 if first else rng.uniform(0.0, 0.012)

        async def abort(cid: str = cid, delay: float = delay) -> None:
            if delay:
                await asyncio.sleep(delay)
            await svc.abort(cid, actor="op2", reason="race")

        if first:
            a = asyncio.create_task(abort())
            p = asyncio.create_task(svc.push(cid, actor="op"))
        else:
            p = asyncio.create_task(svc.push(cid, actor="op"))
            a = asyncio.create_task(abort())
        got = await asyncio.gather(p, a, return_exceptions=True)
        state = svc.store.campaign(cid).state
        if state == S.PUSHED:
            # the push won: the abort was refused, naming the rollback
            assert got[0]["state"] == "pushed"
            assert isinstance(got[1], InvalidTransition) and "rollback" in str(got[1])
            outcomes["pushed"] += 1
        else:
            assert state == S.ABORTED, state
            assert isinstance(got[0], ApprovalRequired), got[0]
            assert got[1] is None
            outcomes["aborted"] += 1
        assert not svc.journal.pending()
        await _controller_agrees(svc)
        if state == S.PUSHED and rng.random() < 0.5:
            await svc.rollback(actor="op", reason="after the race")
            await _controller_agrees(svc)
    # both orders really happened
    assert outcomes["pushed"] >= 10 and outcomes["aborted"] >= 10, outcomes
    # and rollback still works at the end, back to the controller's original values
    while len(svc.store.table_stack()) >= 2:
        await svc.rollback(actor="op")
        await _controller_agrees(svc)
    assert await robot.read_compensation() is None


async def test_a_push_confirmed_after_an_unlocked_abort_is_journaled_and_rolled_back(svc):
    """A store where the campaign was aborted while its table was written (as a daemon
    without the push lock did): completing the journal never fails, the table is in the
    history and active, and rollback removes it."""
    src = await _fitted(svc)
    cid = _approved_copy(svc, src, program_plan(36, validation=6))
    robot = await svc.hub.robot()
    write = robot.write_compensation

    async def write_then_abort(table):  # type: ignore[no-untyped-def]
        await write(table)
        svc.store.transition(cid, S.ABORTED, actor="op", reason="aborted mid-write")

    robot.write_compensation = write_then_abort
    await svc.push(cid, actor="op")
    robot.write_compensation = write
    assert svc.store.campaign(cid).state == S.ABORTED
    e = svc.journal.entries(campaign=cid)[-1]
    assert e.state == "completed" and "aborted" in e.outcome
    assert [h["action"] for h in svc.compensation()["history"]] == ["baseline", "push"]
    await _controller_agrees(svc)
    await svc.rollback(actor="op")
    assert await robot.read_compensation() is None


async def test_shutdown_during_a_push_lets_the_write_finish_and_be_journaled(make_config):
    """Shutdown is ordered with a push too: the table being written is read back and
    journaled before drivers and store close; a push asked for after that is refused."""
    from robocal.daemon.store import Store
    from robocal.errors import CompensationError

    cfg = make_config(limits={"max_joint_correction_deg": 5.0},
                      compensation={"verify_count": 0})
    svc = CalibrationService(cfg)
    await svc.start()
    src = await _fitted(svc)
    doc = program_plan(36, validation=6)
    cid, later = _approved_copy(svc, src, doc), _approved_copy(svc, src, doc)
    robot = await svc.hub.robot()
    write = robot.write_compensation
    writing = asyncio.Event()

    async def slow_write(table):  # type: ignore[no-untyped-def]
        writing.set()
        await asyncio.sleep(0.2)
        await write(table)

    robot.write_compensation = slow_write
    push = asyncio.create_task(svc.push(cid, actor="op"))
    async with asyncio.timeout(10):
        await writing.wait()
    stopping = asyncio.create_task(svc.stop())
    await asyncio.sleep(0)  # stop() has begun: from here on nothing new is written
    second = asyncio.create_task(svc.push(later, actor="op"))
    st = await asyncio.wait_for(push, 10)
    assert st["state"] == "pushed"
    with pytest.raises(CompensationError, match="stopping"):
        await asyncio.wait_for(second, 10)
    await asyncio.wait_for(stopping, 30)
    store = Store(cfg.db_path).open()
    try:
        rows = store.db.execute("SELECT state FROM push_journal").fetchall()
        assert [r[0] for r in rows] == ["completed"]
    finally:
        store.close()
