"""The service in-process over mock drivers: campaigns, faults, restart, approval, push."""

from __future__ import annotations

import asyncio
import math

import pytest

from robocal.daemon.service import CalibrationService
from robocal.errors import (
    ApprovalRequired,
    CampaignError,
    CompensationError,
    ConfigError,
    InvalidTransition,
    VerificationMismatch,
)
from tests.unit.daemon.conftest import ROBOT, random_plan


@pytest.fixture
async def service(make_config):
    services: list[CalibrationService] = []

    async def make(**sections):
        svc = CalibrationService(make_config(**sections))
        await svc.start()
        services.append(svc)
        return svc

    yield make
    for svc in services:
        await svc.stop()


def _unique(svc, cid):
    rows = svc.store.measurements(cid)
    idx = [r.pose_idx for r in rows]
    assert len(idx) == len(set(idx))
    return idx


async def test_campaign_runs_fits_and_pushes_after_approval(service):
    svc = await service()
    st = await svc.create(random_plan(24, validation=4, via_every=5), actor="alice")
    cid = st["id"]
    assert st["state"] == "running" and st["poses_total"] == 24
    st = await svc.wait(cid, ["fitted"], timeout=60)
    assert st["state"] == "fitted", st["reason"]
    assert st["poses_measured"] == 24 and len(_unique(svc, cid)) == 24
    fit = st["fits"]["constant"]
    assert fit["validation"]["n"] == 4 and fit["validation"]["rms_mm"] < 1.0
    assert "nominal" in st["fits"]
    with pytest.raises(ApprovalRequired):
        await svc.push(cid, actor="alice")
    await svc.approve(cid, actor="bob")
    st = await svc.push(cid, actor="bob")
    assert st["state"] == "pushed"
    comp = svc.compensation()
    assert comp["active"]["kind"] == "frames" and comp["active"]["campaign"] == cid
    robot = await svc.hub.robot()
    stored = await robot.read_compensation()
    assert stored is not None and stored.checksum == comp["active"]["checksum"]
    actions = [(a["action"], a["actor"]) for a in svc.audit()]
    assert ("campaign.approve", "bob") in actions and ("compensation.push", "bob") in actions
    states = [t["to_state"] for t in svc.store.transitions(cid)]
    assert states == ["created", "running", "measured", "fitted", "approved", "pushed"]


async def test_rollback_restores_the_previous_table(service):
    svc = await service()
    checksums = []
    for seed in (1, 2):
        st = await svc.create(random_plan(20, seed=seed), actor="alice")
        st = await svc.wait(st["id"], ["fitted"], timeout=60)
        await svc.approve(st["id"], actor="alice")
        await svc.push(st["id"], actor="alice")
        checksums.append(svc.compensation()["active"]["checksum"])
    assert checksums[0] != checksums[1]
    out = await svc.rollback(actor="carol")
    assert out["active"]["checksum"] == checksums[0]
    stored = await (await svc.hub.robot()).read_compensation()
    assert stored.checksum == checksums[0]
    with pytest.raises(CompensationError, match="no earlier"):
        await svc.rollback(actor="carol")
    last = svc.audit()[-1]
    assert last["action"] == "compensation.rollback" and last["actor"] == "carol"
    assert last["checksum"] == checksums[0]


async def test_pause_and_resume_keep_every_measurement_once(service):
    svc = await service(robot={"options": {"move_time_s": 0.01}})
    st = await svc.create(random_plan(30), actor="a")
    cid = st["id"]
    while svc.store.campaign(cid).poses_measured < 5:
        await asyncio.sleep(0.01)
    await svc.pause(cid, actor="a")
    await asyncio.sleep(0.1)
    rec = svc.store.campaign(cid)
    assert rec.state.value == "paused" and 5 <= rec.poses_measured < 30
    await asyncio.sleep(0.1)
    assert svc.store.campaign(cid).poses_measured == rec.poses_measured
    await svc.resume(cid, actor="a")
    st = await svc.wait(cid, ["fitted"], timeout=60)
    assert st["state"] == "fitted" and _unique(svc, cid) == list(range(30))


async def test_tracker_faults_fault_the_campaign_then_resume(service, make_config):
    svc = await service(tracker={"options": {"beam_break_rate": 1.0}},
                        measurement={"retries": 2})
    st = await svc.create(random_plan(16), actor="a")
    st = await svc.wait(st["id"], ["faulted"], timeout=30)
    assert st["state"] == "faulted"
    assert "no valid reading after 3 attempts" in st["reason"] and "BeamLost" in st["reason"]
    assert st["poses_measured"] == 0
    # The operator fixes the beam and resumes.
    svc.hub.config = make_config()
    await svc.resume(st["id"], actor="operator")
    st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=60)
    assert st["state"] == "fitted" and st["poses_measured"] == 16


async def test_occasional_faults_are_retried(service):
    svc = await service(tracker={"options": {"beam_break_rate": 0.1, "unstable_rate": 0.1}})
    st = await svc.create(random_plan(30), actor="a")
    st = await svc.wait(st["id"], ["fitted"], timeout=60)
    rows = svc.store.measurements(st["id"])
    assert st["state"] == "fitted" and len(rows) == 30
    retries = sum(r.attempts - 1 for r in rows)
    beam = sum(r.beam_losses for r in rows)
    assert retries > 0 and 0 < beam <= retries
    # the report's measurement log counts from the store, not from fixed numbers
    log = svc._measurement_log(st["id"], rows)
    assert (log["planned"], log["measured"], log["retries"], log["beam_losses"]) == \
        (30, 30, retries, beam)


async def test_restart_resumes_at_the_first_unmeasured_pose(service, make_config):
    svc = await service(robot={"options": {"move_time_s": 0.01}})
    st = await svc.create(random_plan(25), actor="a")
    cid = st["id"]
    while svc.store.campaign(cid).poses_measured < 8:
        await asyncio.sleep(0.005)
    await svc.stop()  # as a crash would: the state stays "running"
    assert svc.store._db is None
    svc2 = await service(robot={"options": {"move_time_s": 0.001}})
    st = await svc2.wait(cid, ["fitted"], timeout=60)
    assert st["state"] == "fitted" and _unique(svc2, cid) == list(range(25))


async def test_abort_stops_motion(service):
    svc = await service(robot={"options": {"move_time_s": 0.02}})
    st = await svc.create(random_plan(30), actor="a")
    await asyncio.sleep(0.1)
    st = await svc.abort(st["id"], actor="a", reason="test")
    assert st["state"] == "aborted"
    n = st["poses_measured"]
    await asyncio.sleep(0.1)
    assert svc.store.campaign(st["id"]).poses_measured == n < 30
    with pytest.raises(InvalidTransition):
        await svc.resume(st["id"], actor="a")


async def test_one_campaign_measures_at_a_time(service):
    svc = await service(robot={"options": {"move_time_s": 0.01}})
    first = await svc.create(random_plan(20), actor="a")
    with pytest.raises(CampaignError, match="is measuring"):
        await svc.create(random_plan(5), actor="a")
    await svc.abort(first["id"], actor="a")


async def test_targets_outside_the_limits_are_refused_before_anything_moves(service):
    svc = await service(limits={"joint_margin_deg": 5.0})
    plan = random_plan(5)
    hi = math.degrees(svc.robot.joints[0].q_max)
    bad = plan.poses[2].__class__(2, "calibration", (hi - 1.0, *plan.poses[2].q_deg[1:]))
    poses = (*plan.poses[:2], bad, *plan.poses[3:])
    with pytest.raises(ConfigError, match=r"poses\[2\].*J1"):
        await svc.create(plan.__class__(ROBOT, poses, plan.document, plan.digest), actor="a")
    assert svc.list() == []


async def test_plan_for_another_robot_is_refused(service):
    svc = await service()
    plan = random_plan(5)
    with pytest.raises(ConfigError, match="robot"):
        await svc.create(plan.__class__("ur10", plan.poses, plan.document, plan.digest),
                         actor="a")


async def test_out_of_bounds_compensation_is_refused(service):
    svc = await service(limits={"max_frame_translation_mm": 0.001})
    st = await svc.create(random_plan(20), actor="a")
    st = await svc.wait(st["id"], ["fitted"], timeout=60)
    await svc.approve(st["id"], actor="a")
    with pytest.raises(CompensationError, match="tool frame changes"):
        await svc.push(st["id"], actor="a")
    assert svc.store.campaign(st["id"]).state.value == "approved"
    assert await (await svc.hub.robot()).read_compensation() is None


async def test_read_back_mismatch_is_reported_and_audited(service):
    svc = await service(robot={"options": {"corrupt_readback": True}})
    st = await svc.create(random_plan(20), actor="a")
    st = await svc.wait(st["id"], ["fitted"], timeout=60)
    await svc.approve(st["id"], actor="a")
    with pytest.raises(VerificationMismatch):
        await svc.push(st["id"], actor="a")
    assert svc.store.campaign(st["id"]).state.value == "approved"
    assert svc.audit()[-1]["action"] == "compensation.push-failed"
    assert svc.compensation()["active"] is None


@pytest.mark.parametrize("kind", ["targets", "joint"])
async def test_other_table_kinds_push(service, kind):
    svc = await service(compensation={"kind": kind},
                        limits={"max_joint_correction_deg": 10.0})
    st = await svc.create(random_plan(24, validation=4), actor="a")
    st = await svc.wait(st["id"], ["fitted"], timeout=60)
    await svc.approve(st["id"], actor="a")
    st = await svc.push(st["id"], actor="a")
    assert st["state"] == "pushed"
    table = await (await svc.hub.robot()).read_compensation()
    assert table.kind == kind
    if kind == "targets":
        assert len(table.targets) == 4 and all(r.status == "ok" for r in table.targets)
