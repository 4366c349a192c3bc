"""Issue 31 acceptance: scheduled drift checks on the simulated cell (the daemon's service
driving the FANUC RMI and LTP tracker simulators over their wire protocols).

A joint zero offset of the virtual robot grows over simulated days. Daily checks of the
active compensation's model pass while the drift is small, then reach the configured
threshold; the check recommends a re-calibration with ``--reuse``, which (refit, approved,
pushed) restores the accuracy: the held-out error against the truth before and after, and a
check that passes again.
"""

from __future__ import annotations

import numpy as np
from tests.unit.daemon.conftest import ROBOT, base_config
from tests.unit.daemon.test_service import program_plan

from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers.sim import FanucSimOptions, LtpSimOptions, SimCell

#: the planted drift: J2's zero moves 0.004 deg a day (~0.017 mm a day at the reflector)
DRIFT_DEG_PER_DAY = (0.0, 0.004)
WARN_RMS_MM = 0.05


def _truth_rms_mm(svc: CalibrationService, world, cid: str, q: np.ndarray) -> float:
    """Held-out RMS (mm) of the model pushed from ``cid`` against the virtual robot's truth
    (drift as of now) at joints ``q`` (n, dof) rad."""
    cal = svc.fitted_model(cid)
    err = cal.predict(q) - world.cell.reflector_position(q)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))) * 1e3)


async def test_a_growing_joint_drift_is_detected_and_a_reuse_refit_restores_accuracy(tmp_path):
    sims = SimCell(robot=ROBOT, scenario="constant", seed=3, modbus=False,
                   fanuc=FanucSimOptions(time_scale=0.0), ltp=LtpSimOptions(time_scale=0.0))
    async with sims:
        cfg = base_config(
            tmp_path, limits={"max_joint_correction_deg": 5.0},
            compensation={"verify_count": 0},
            check={"poses": 20, "warn_rms_mm": WARN_RMS_MM, "fail_rms_mm": 0.1,
                   "warn_growth_mm": 0.04, "fail_growth_mm": 0.1, "reuse_poses": 24,
                   "reuse_validation_poses": 8})
        cfg["robot"] = {"kind": "fanuc_rmi", "options": sims.robot_options("fanuc_rmi")}
        cfg["tracker"] = {"kind": "ltp", "options": {**sims.tracker_options("tcp"),
                                                     "stab_ms": 10}}
        svc = CalibrationService(parse_config(cfg, source="test"))
        await svc.start()
        try:
            await _drift_detected_and_corrected(svc, sims.world)
        finally:
            await svc.stop()


async def _drift_detected_and_corrected(svc: CalibrationService, world) -> None:
    st = await svc.create(program_plan(60, validation=12), actor="t")
    cal_cid = st["id"]
    st = await svc.wait(cal_cid, ["fitted", "faulted"], timeout=60)
    assert st["state"] == "fitted", st["reason"]
    await svc.approve(cal_cid, actor="t")
    await svc.push(cal_cid, actor="t")
    world.cell.drift_deg_per_day = DRIFT_DEG_PER_DAY
    held_out = np.radians(np.array(
        [p.q_deg for p in svc.store.poses(cal_cid) if p.purpose == "validation"]))
    trend = []
    for day in range(15):
        world.cell.sim_days = float(day)  # the simulated clock: one check a day
        started = await svc.checks.start(actor="timer")
        c = await svc.checks.wait(started["id"], timeout=60)
        assert c["state"] == "done", c
        trend.append((day, c["rms_mm"], c["verdict"],
                      _truth_rms_mm(svc, world, cal_cid, held_out)))
        if c["verdict"] != "pass":
            break
    # detected at the threshold: the day the check's RMS first reached it, and the truth
    # agrees (held-out error against the virtual robot within 0.01 mm of the check's)
    assert [t[2] for t in trend[:-1]] == ["pass"] * (len(trend) - 1), trend
    assert c["verdict"] == "warn" and c["rms_mm"] >= WARN_RMS_MM, trend
    assert all(t[1] < WARN_RMS_MM for t in trend[:-1]), trend
    assert 2 <= trend[-1][0] <= 6, trend
    assert abs(trend[-1][3] - c["rms_mm"]) < 0.01, trend
    assert [t[1] for t in trend] == sorted(t[1] for t in trend), trend
    rec = c["detail"]["recommendation"]
    assert c["recommendation"] == rec["action"] == "reuse", c["detail"]
    assert rec["poses"] == 24 and rec["validation_poses"] == 8

    # the recommended re-calibration: a reuse refit of the checked model, pushed
    st = await svc.checks.recalibrate(actor="t", check_id=c["id"])
    refit = st["id"]
    st = await svc.wait(refit, ["fitted"], timeout=60)
    assert st["state"] == "fitted", st
    assert st["selected_model"] == "reuse"
    assert svc.store.poses(refit)[-1].purpose == "validation"
    assert sum(p.measure for p in svc.store.poses(refit)) == 32
    await svc.approve(refit, actor="t")
    await svc.push(refit, actor="t")
    before = _truth_rms_mm(svc, world, cal_cid, held_out)
    after = _truth_rms_mm(svc, world, refit, held_out)
    again = await svc.checks.wait((await svc.checks.start(actor="timer"))["id"], timeout=60)
    print(f"held-out RMS against the truth on day {trend[-1][0]}: {before:.4f} mm before, "
          f"{after:.4f} mm after the reuse refit; checks {[t[1] for t in trend]} -> "
          f"{again['rms_mm']}")
    assert before >= WARN_RMS_MM and after < 0.4 * WARN_RMS_MM, (before, after)
    assert again["verdict"] == "pass" and again["model_campaign"] == refit, again
    assert again["rms_mm"] < 0.4 * WARN_RMS_MM
    assert again["detail"]["growth_mm"] is None  # a new model: no growth to compare
    history = svc.checks.log.history()
    assert [h["verdict"] for h in history] == [t[2] for t in trend] + ["pass"]
