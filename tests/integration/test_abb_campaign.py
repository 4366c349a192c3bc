"""The daemon with the ABB driver (deploy/config/abb.toml) against the RWS simulator.

A 100-pose campaign with ~10 % injected tracker faults (and slow controller replies) on
RobotWare 6, fitted, approved and pushed into the PERS jointtarget array ``rc_comp``, measured
again, then rolled back to what the controller held before; and an abort mid-move on
RobotWare 7 that halts the simulated robot within 0.2 s.
"""

from __future__ import annotations

import math
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from tests._waiting import eventually
from tests.unit.daemon.conftest import ROBOT, random_plan
from tests.unit.daemon.test_service import program_plan

from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers.sim import AbbSimOptions, FaultConfig, LtpSimOptions, SimCell
from robocal.protocols import abb_rws as rws

N_POSES = 100
HALT_BOUND_S = 0.2
DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "config" / "abb.toml"


def _config(cell: SimCell, tmp_path: Path, **measurement: Any) -> Any:
    doc = tomllib.loads(DEPLOY.read_text())
    doc["data_dir"] = str(tmp_path / "state")
    doc["robot_description"] = ROBOT
    doc.pop("cell", None)  # random plans are not checked against a cell's obstacles
    doc["robot"]["options"].update(cell.robot_options("abb_rws"))
    # the simulated RobotWare's default user; plain HTTP on loopback
    for key in ("username", "ca_file"):
        doc["robot"]["options"].pop(key)
    doc["tracker"]["options"] = {**cell.tracker_options("tcp"), "stab_ms": 10}
    doc["api"] = {"socket": str(tmp_path / "api.sock")}
    doc["measurement"].update({"settle_s": 0.0, "backoff_s": 0.001, "samples": 4,
                               **measurement})
    doc["limits"]["max_joint_correction_deg"] = 5.0
    doc["compensation"]["verify_count"] = 3
    doc["fit"] = {"models": ["constant"], "select": "constant", "executor": "thread",
                  "report": False, "cpa": False}
    return parse_config(doc, source=str(DEPLOY))


async def test_campaign_push_and_rollback_through_the_daemon_on_robotware6(tmp_path):
    faults = FaultConfig(beam_break_rate=0.05, unstable_rate=0.05, slow_rate=0.02,
                         slow_s=0.01, seed=8)
    cell = SimCell(robot=ROBOT, seed=6, fanuc=False, modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0),
                   abb=AbbSimOptions(robotware=6, time_scale=0.0), faults=faults)
    async with cell:
        sim = cell.abb_sim
        assert sim is not None
        # what another tool left in the array before robocal's first push
        foreign = [rws.JointTarget((i, -i, 0.5 * i, 0, 45, 0))
                   for i in range(sim.options.comp_size)]
        sim.symbols["rc_comp"].assign(rws.format_jointtarget_array(foreign))
        original = {k: sim.symbols[k].value
                    for k in ("rc_comp", "rc_comp_n", "rc_comp_kind", "rc_comp_sum")}
        svc = CalibrationService(_config(cell, tmp_path))
        await svc.start()
        try:
            st = await svc.create(program_plan(N_POSES, validation=20), actor="t")
            st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=120)
            assert st["state"] == "fitted", st.get("reason")
            rows = svc.store.measurements(st["id"])
            assert sorted(r.pose_idx for r in rows) == list(range(N_POSES))
            assert any(r.attempts > 1 for r in rows)  # injected faults were retried
            assert all(np.allclose(r.q_act_deg, r.q_cmd_deg, atol=0.01) for r in rows)

            await svc.approve(st["id"], actor="t")
            st = await svc.push(st["id"], actor="t")
            v = await svc.wait_verification(st["push"]["key"], timeout=120)
            assert v is not None and v["state"] == "done", v
            assert v["after"]["rms_mm"] < 0.6 * v["before"]["rms_mm"]
            # the table is in rc_comp: kind, row count and checksum as pushed
            assert rws.parse_string(sim.symbols["rc_comp_kind"].value) == "targets"
            pushed = svc.compensation()["history"][-1]
            assert rws.parse_string(sim.symbols["rc_comp_sum"].value) == pushed["checksum"]

            await svc.rollback(actor="t")
            for k, value in original.items():
                assert sim.symbols[k].value == value, k
        finally:
            await svc.stop()
    counts = cell.ltp_sim.faults.counts if cell.ltp_sim else {}
    assert counts.get("beam_break", 0) + counts.get("unstable", 0) >= 5, counts
    assert sim.faults.counts.get("slow", 0) > 0


async def test_abort_mid_move_halts_within_bound_on_robotware7(tmp_path):
    cell = SimCell(robot=ROBOT, seed=2, fanuc=False, modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0),
                   abb=AbbSimOptions(robotware=7, time_scale=0.1))
    async with cell:
        world = cell.world
        svc = CalibrationService(_config(cell, tmp_path, samples=2))
        await svc.start()
        try:
            st = await svc.create(random_plan(8, seed=5), actor="op", measure_only=True)
            cid = st["id"]
            await eventually(lambda: svc.store.campaign(cid).poses_measured >= 1
                             and world.moving, 60, what="a move in progress")
            start = world.q_actual_rad
            await eventually(lambda: np.max(np.abs(world.q_actual_rad - start)) > 1e-3, 5,
                             what="joints moving")
            t_request = time.monotonic()
            st = await svc.abort(cid, actor="op", reason="person in the cell")
            halt_at = (world.last_halt_time or math.inf) - t_request
            assert st["state"] == "aborted"
            assert 0.0 <= halt_at < HALT_BOUND_S, halt_at
            q_halted = world.q_actual_rad
            # stays halted: the RAPID loop was restarted without the aborted command
            await eventually(lambda: cell.abb_sim is not None
                             and cell.abb_sim.execstate == "running", 5, what="restarted")
            assert not world.moving and np.array_equal(world.q_actual_rad, q_halted)
            stops = [a for a in svc.store.audit_log() if a["action"] == "motion.stop"]
            assert len(stops) == 1 and stops[0]["detail"]["outcome"] == "stopped"
            assert stops[0]["detail"]["stop_s"] < 2.0
        finally:
            await svc.stop()
