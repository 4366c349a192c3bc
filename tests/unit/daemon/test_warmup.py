"""The warm-up routine before a campaign's first measured pose (ADR 0042): it runs the plan's
moves through the checked path until the joint temperatures settle, and every measurement
keeps the joint temperatures."""

from __future__ import annotations

import pytest

from robocal.daemon._warmup import WarmupWatch
from robocal.daemon.config import WarmupConfig
from robocal.daemon.fitting import temperature_log
from robocal.daemon.service import CalibrationService
from tests.unit.daemon.conftest import ROBOT, random_plan

pytestmark = pytest.mark.timeout(60)


def _warm_config(make_config, **warmup):
    opts = {"robot": ROBOT, "scenario": "constant", "warmup_drift_mm": 0.1}
    return make_config(robot={"options": opts}, tracker={"options": opts}, warmup=warmup)


async def test_warmup_runs_until_the_temperatures_settle_then_measures(make_config):
    cfg = _warm_config(make_config, until_settled_c_per_min=0.05, max_s=20000.0)
    svc = CalibrationService(cfg)
    await svc.start()
    try:
        events = []
        st = await svc.create(random_plan(8, seed=2), actor="t")
        st = await svc.wait(st["id"], ["measured", "fitted"], timeout=45)
        events = [e for e in svc.events._buffer if e["kind"] == "warmup"]
        rows = svc.store.measurements(st["id"])
        audit = [a for a in svc.store.audit_log() if a["action"] == "campaign.warmup"]
        robot = await svc.hub.robot()
        world = robot.world  # type: ignore[attr-defined]
    finally:
        await svc.stop()
    assert events[0]["phase"] == "started"
    assert events[-1]["phase"] == "done" and "settled" in events[-1]["reason"]
    assert events[-1]["rate_c_per_min"] <= 0.05
    # the routine ran long enough for a first-order lag of 10 min to settle
    assert events[-1]["elapsed_s"] > 1200.0
    assert len(audit) == 1 and "settled" in audit[0]["detail"]["reason"]
    # every measurement keeps the joint temperatures, warm from the first one on
    assert len(rows) == 8 and all(len(r.temps_c) == 6 for r in rows)
    cold = world.thermal.ambient_c
    assert min(rows[0].temps_c) > cold + 2.0
    # the warm-up moves went through the driver like plan moves (many more than the plan)
    assert world.moves > 8 * 10
    # what the report plots: every measurement's temperatures against its time
    series = temperature_log(rows)
    assert series["joint_temps"] == [list(r.temps_c) for r in rows]
    assert series["joint_temps_t_s"][0] == 0.0
    assert series["joint_temps_t_s"] == sorted(series["joint_temps_t_s"])
    assert temperature_log([r.model_copy(update={"temps_c": ()}) for r in rows]) == {}


async def test_without_warmup_the_first_measurement_is_cold(make_config):
    cfg = _warm_config(make_config, duration_s=1.0)
    cfg = cfg.model_copy(update={"warmup": None})
    svc = CalibrationService(cfg)
    await svc.start()
    try:
        st = await svc.create(random_plan(4, seed=2), actor="t")
        st = await svc.wait(st["id"], ["measured", "fitted"], timeout=30)
        rows = svc.store.measurements(st["id"])
        warm = [e for e in svc.events._buffer if e["kind"] == "warmup"]
    finally:
        await svc.stop()
    assert warm == []
    assert max(rows[0].temps_c) < 20.0 + 1.0


def test_watch_duration_settling_and_cap():
    by_time = WarmupWatch(WarmupConfig(duration_s=100.0))
    assert by_time.add(0.0, ()) is None and by_time.add(99.0, ()) is None
    assert "duration_s" in (by_time.add(100.0, ()) or "")
    settle = WarmupWatch(WarmupConfig(until_settled_c_per_min=0.1, settle_window_s=60.0,
                                      duration_s=30.0, max_s=1000.0))
    temps = 20.0
    reasons = []
    for t in range(0, 1000, 10):
        temps += 0.5 if t < 300 else 0.001   # 3 degC/min, then 0.006 degC/min
        reasons.append((t, settle.add(float(t), (temps, temps - 1.0))))
    first = next((t, r) for t, r in reasons if r is not None)
    assert first[0] == 350 and "settled" in first[1]  # a whole window after the rise ended
    assert all(r is None for t, r in reasons if t < 350)
    capped = WarmupWatch(WarmupConfig(until_settled_c_per_min=0.1, max_s=50.0))
    assert capped.add(0.0, (20.0,)) is None
    assert "max_s" in (capped.add(60.0, (40.0,)) or "")
    with pytest.raises(ValueError, match="duration_s or until_settled"):
        WarmupConfig()


def test_watch_line_shows_the_warmup_while_running():
    from robocal.cli._campaign import _Progress

    prog = _Progress({"poses_measured": 0, "poses_total": 8, "state": "running",
                      "transitions": []}, now=0.0)
    prog.update({"kind": "warmup", "phase": "progress", "elapsed_s": 754.0,
                 "rate_c_per_min": 0.21}, now=1.0)
    assert "| warming up 12:34, 0.210 degC/min" in prog.line(now=1.0)
    prog.update({"kind": "warmup", "phase": "done", "elapsed_s": 2520.0,
                 "rate_c_per_min": 0.02}, now=2.0)
    assert "warm" not in prog.line(now=2.0)  # measuring now: the line is about the poses


async def test_a_poses_pattern_is_cycled_for_its_duration(make_config):
    poses = [[10.0, 20.0, -10.0, 0.0, 30.0, 0.0], [-20.0, 40.0, 10.0, 30.0, -30.0, 90.0]]
    cfg = _warm_config(make_config, pattern="poses", poses_deg=poses, duration_s=600.0)
    svc = CalibrationService(cfg)
    await svc.start()
    try:
        st = await svc.create(random_plan(4, seed=2), actor="t")
        st = await svc.wait(st["id"], ["measured", "fitted"], timeout=30)
        done = [e for e in svc.events._buffer if e["kind"] == "warmup"][-1]
        world = (await svc.hub.robot()).world  # type: ignore[attr-defined]
    finally:
        await svc.stop()
    assert done["phase"] == "done" and "duration_s" in done["reason"]
    assert 600.0 <= done["elapsed_s"] < 700.0
    # about 5 s of simulated time per warm-up move (step / 0.5 rad/s + 1 s), 4 measured poses
    assert world.moves > 600.0 / 10.0 + 4


async def test_an_unsafe_warmup_pose_faults_before_anything_moves(make_config):
    poses = [[10.0, 20.0, -10.0, 0.0, 30.0, 0.0], [400.0, 0.0, 0.0, 0.0, 0.0, 0.0]]
    cfg = _warm_config(make_config, pattern="poses", poses_deg=poses, duration_s=60.0)
    svc = CalibrationService(cfg)
    await svc.start()
    try:
        st = await svc.create(random_plan(4, seed=2), actor="t")
        st = await svc.wait(st["id"], ["faulted"], timeout=30)
        world = (await svc.hub.robot()).world  # type: ignore[attr-defined]
    finally:
        await svc.stop()
    assert "first move refused" in st["reason"] and "pose 1 (warm-up)" in st["reason"]
    assert world.moves == 0 and st["poses_measured"] == 0


def test_poses_pattern_needs_poses():
    with pytest.raises(ValueError, match="poses_deg"):
        WarmupConfig(pattern="poses", duration_s=60.0)
    with pytest.raises(ValueError, match="poses_deg"):
        WarmupConfig(poses_deg=((0.0,) * 6, (1.0,) * 6), duration_s=60.0)
