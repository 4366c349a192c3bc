"""The daemon drives the UR simulator with deploy/config/ur.toml: a 100-pose campaign with
~10 % injected tracker faults, and an abort that halts the arm within 0.2 s."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
import tomllib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
from tests._waiting import eventually

from robocal.daemon import parse_plan, plan_from_poses
from robocal.daemon.config import config_errors, load_config, parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers.sim import FaultConfig, LtpSimOptions, SimCell, SimWorld, UrSimOptions
from robocal.kinematics import load_robot

ROBOT = "ur10"
DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "config" / "ur.toml"
HALT_BOUND_S = 0.2


def ur_plan(n: int, seed: int, validation: int = 0) -> Any:
    """``n`` random UR10 poses, ``+-150`` degrees per joint, the wrist at least 20 degrees
    from its singularity (the last ``validation`` held out: they are the pushed targets)."""
    robot = load_robot(ROBOT)
    q = np.random.default_rng(seed).uniform(-150.0, 150.0, (4 * n, robot.dof))
    q = q[np.abs(np.sin(np.radians(q[:, 4]))) >= math.sin(math.radians(20.0))][:n]
    purposes = ["calibration" if i < n - validation else "validation" for i in range(n)]
    return parse_plan(plan_from_poses(q.tolist(), robot=ROBOT, purposes=purposes),
                      source="test", strict=False)


@contextlib.asynccontextmanager
async def service(tmp_path: Path, *, time_scale: float, faults: FaultConfig | None = None,
                  models: tuple[str, ...] = ("constant",)
                  ) -> AsyncIterator[tuple[CalibrationService, SimCell]]:
    doc = tomllib.loads(DEPLOY.read_text())
    cell = SimCell(robot=ROBOT, seed=8, fanuc=False, modbus=False,
                   ur=UrSimOptions(time_scale=time_scale), ltp=LtpSimOptions(time_scale=0.0),
                   faults=faults)
    async with cell:
        doc["data_dir"] = str(tmp_path / "state")
        doc["robot"]["options"].update(cell.robot_options("universal_robots"))
        doc["robot"]["options"]["max_joint_speed_rad_s"] = math.pi
        doc["tracker"]["options"] = cell.tracker_options("tcp")
        doc["api"] = {"socket": str(tmp_path / "api.sock")}
        doc["limits"]["speed_pct"] = 100.0
        doc["measurement"].update({"settle_s": 0.0, "backoff_s": 0.001, "samples": 2,
                                   "retries": 8})
        doc["fit"] = {"models": list(models), "select": models[-1], "executor": "thread",
                      "report": False, "cpa": False}
        doc["compensation"]["verify_count"] = 4
        doc["limits"]["max_joint_correction_deg"] = 5.0
        svc = CalibrationService(parse_config(doc, source=str(DEPLOY)))
        await svc.start()
        try:
            yield svc, cell
        finally:
            await svc.stop()


async def test_daemon_runs_100_poses_with_faults_through_the_ur_driver(tmp_path):
    faults = FaultConfig(beam_break_rate=0.05, unstable_rate=0.05, seed=12)
    async with service(tmp_path, time_scale=0.0, faults=faults) as (svc, cell):
        st = await svc.create(ur_plan(100, seed=1), actor="t")
        st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=120)
        assert st["state"] == "fitted", st.get("reason")
        rows = svc.store.measurements(st["id"])
        assert sorted(r.pose_idx for r in rows) == list(range(100))
        retried = sum(1 for r in rows if r.attempts > 1)
        # every commanded pose was reached by movej on the simulated arm
        assert all(np.allclose(r.q_act_deg, r.q_cmd_deg, atol=0.05) for r in rows)
        sim = cell.ur_sim
        assert sim is not None and sim.script_runs >= 100
    counts = cell.ltp_sim.faults.counts if cell.ltp_sim is not None else {}
    failures = counts.get("beam_break", 0) + counts.get("unstable", 0)
    assert 4 <= failures <= 25 and retried > 0, counts


async def _halted_after(world: SimWorld, t_request: float, watch_s: float = 0.25) -> float:
    """Watch the joints for ``watch_s``; seconds after ``t_request`` of the last change."""
    last, last_change = world.q_actual_rad, t_request
    end = time.monotonic() + watch_s
    while time.monotonic() < end:
        await asyncio.sleep(0.002)
        q = world.q_actual_rad
        if np.any(q != last):
            last, last_change = q, time.monotonic()
    return last_change - t_request


async def test_abort_mid_move_halts_the_ur_arm_within_bound(tmp_path):
    async with service(tmp_path, time_scale=0.1) as (svc, cell):
        world = cell.world
        st = await svc.create(ur_plan(8, seed=2), actor="op", measure_only=True)
        cid = st["id"]
        await eventually(lambda: svc.store.campaign(cid).poses_measured >= 1 and world.moving,
                         30, what="a move in progress")
        start = world.q_actual_rad
        await eventually(lambda: np.max(np.abs(world.q_actual_rad - start)) > 1e-3, 5,
                         what="joints moving")
        t_request = time.monotonic()
        st = await svc.abort(cid, actor="op", reason="person in the cell")
        last_change = await _halted_after(world, t_request)
        halt_at = (world.last_halt_time or math.inf) - t_request
        assert st["state"] == "aborted"
        assert 0.0 <= halt_at < HALT_BOUND_S and last_change < HALT_BOUND_S
        stops = [a for a in svc.store.audit_log() if a["action"] == "motion.stop"]
        assert len(stops) == 1 and stops[0]["detail"]["outcome"] == "stopped"
        assert any("  stopj(" in s for s in cell.ur_sim.scripts)  # type: ignore[union-attr]


def test_the_deploy_config_validates():
    assert config_errors(DEPLOY) == []
    cfg = load_config(DEPLOY)
    assert cfg.robot.kind == "universal_robots"


async def test_push_writes_waypoint_variables_and_rollback_restores_the_sites(tmp_path):
    async with service(tmp_path, time_scale=0.0) as (svc, cell):
        sim = cell.ur_sim
        assert sim is not None
        site = {f"rc_wp_{i}": [0.1 * i, -1.0, 1.0, -0.5, 1.2, 0.0] for i in range(40)}
        sim.variables.update({k: list(v) for k, v in site.items()})
        st = await svc.create(ur_plan(40, seed=3, validation=8), actor="a")
        st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=120)
        assert st["state"] == "fitted", st.get("reason")
        await svc.approve(st["id"], actor="a")
        st = await svc.push(st["id"], actor="a")
        v = await svc.wait_verification(st["push"]["key"], timeout=120)
        assert v is not None and v["state"] == "done", v
        assert v["after"]["rms_mm"] < 0.6 * v["before"]["rms_mm"]
        pushed = [k for k in site if sim.variables[k] != site[k]]
        assert len(pushed) == 8  # one corrected waypoint per validation target
        await svc.rollback(actor="b")
        assert {k: sim.variables[k] for k in site} == site
