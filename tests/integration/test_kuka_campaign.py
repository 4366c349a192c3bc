"""KUKA over KUKAVARPROXY through the daemon: a 100-pose campaign with ~10 % injected faults
using deploy/config/kuka.toml, and an abort that halts the simulated robot within 0.2 s.

Faults: beam breaks and unstable readings at the tracker (retried by the daemon), slow KVP
replies and slow LTP replies on ~3 % of requests. The simulators run time-scaled.
"""

from __future__ import annotations

import math
import time
import tomllib
from pathlib import Path

import numpy as np
from tests.unit.daemon.conftest import ROBOT, random_plan
from tests.unit.daemon.test_motion_stop import HALT_BOUND_S, _halted_after, _mid_move

from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers.sim import FaultConfig, KukaSimOptions, LtpSimOptions, SimCell
from robocal.protocols import kuka_kvp as kvp

N_POSES = 100
DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "config" / "kuka.toml"


def _config(cell: SimCell, tmp_path: Path) -> dict:
    doc = tomllib.loads(DEPLOY.read_text())
    doc["data_dir"] = str(tmp_path / "state")
    doc["robot_description"] = ROBOT
    doc["robot"]["options"].update(cell.robot_options("kuka_kvp"))
    doc["tracker"]["options"] = cell.tracker_options("tcp")
    doc["api"] = {"socket": str(tmp_path / "api.sock")}
    doc["measurement"].update({"samples": 3, "settle_s": 0.0, "backoff_s": 0.001})
    doc["fit"] = {"models": ["constant"], "select": "constant", "executor": "thread",
                  "report": False, "cpa": False}
    doc["logging"] = {"level": "warning"}
    return doc


async def test_daemon_runs_a_kuka_campaign_with_injected_faults(tmp_path):
    faults = FaultConfig(beam_break_rate=0.05, unstable_rate=0.05, slow_rate=0.03,
                         slow_s=0.002, seed=8)
    cell = SimCell(robot=ROBOT, seed=6, fanuc=False, modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0), kuka=KukaSimOptions(time_scale=0.001),
                   faults=faults)
    async with cell:
        svc = CalibrationService(parse_config(_config(cell, tmp_path), source=str(DEPLOY)))
        await svc.start()
        try:
            st = await svc.create(random_plan(N_POSES, seed=3), actor="t")
            st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=120)
            assert st["state"] == "fitted", st.get("reason")
            rows = svc.store.measurements(st["id"])
            assert sorted(r.pose_idx for r in rows) == list(range(N_POSES))
            assert any(r.attempts > 1 for r in rows)  # injected faults were retried
            # every pose measured where the plan put the robot, read from $AXIS_ACT
            assert all(np.allclose(r.q_act_deg, r.q_cmd_deg, atol=0.01) for r in rows)
        finally:
            await svc.stop()
        sim = cell.kuka_sim
        assert sim is not None and sim.moves >= N_POSES
        counts = {**cell.ltp_sim.faults.counts} if cell.ltp_sim else {}
    injected = counts.get("beam_break", 0) + counts.get("unstable", 0)
    assert 5 <= injected <= 25, counts
    assert sim.faults.counts.get("slow", 0) > 0


async def test_abort_mid_move_halts_the_kuka_robot_within_bound(tmp_path):
    cell = SimCell(robot=ROBOT, seed=2, fanuc=False, modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0), kuka=KukaSimOptions(time_scale=0.1))
    async with cell:
        svc = CalibrationService(parse_config(_config(cell, tmp_path), source=str(DEPLOY)))
        await svc.start()
        try:
            world = cell.world
            st = await svc.create(random_plan(8, seed=5), actor="op", measure_only=True)
            cid = st["id"]
            await _mid_move(svc, world, cid, after_measured=1)
            t_request = time.monotonic()
            st = await svc.abort(cid, actor="op", reason="person in the cell")
            last_change = await _halted_after(world, t_request)
            halt_at = (world.last_halt_time or math.inf) - t_request
            assert st["state"] == "aborted"
            assert 0.0 <= halt_at < HALT_BOUND_S and last_change < HALT_BOUND_S
            stops = [a for a in svc.store.audit_log() if a["action"] == "motion.stop"]
            assert len(stops) == 1 and stops[0]["detail"]["outcome"] == "stopped"
            assert cell.kuka_sim is not None and cell.kuka_sim.stops == 1
            # the halt is the loop's stop interrupt: RC_STOP cleared, RC_STATUS stopped
            assert cell.kuka_sim.read("RC_STOP") == ("FALSE", True)
            assert cell.kuka_sim.read("RC_STATUS") == ("4", True)
        finally:
            await svc.stop()


async def test_push_writes_rc_comp_and_rollback_restores_what_was_there(tmp_path):
    """The daemon pushes corrected targets into the E6AXIS array, measures their effect and
    rolls back to what another program had left in RC_COMP."""
    from tests.unit.daemon.conftest import base_config
    from tests.unit.daemon.test_service import program_plan

    cell = SimCell(robot=ROBOT, seed=4, fanuc=False, modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0), kuka=KukaSimOptions(time_scale=0.0))
    async with cell:
        sim = cell.kuka_sim
        assert sim is not None
        for i in range(1, 41):
            sim.write(f"RC_COMP[{i}]", "{A1 " + str(i + 0.5) + ", A2 -1.25}")
        sim.write("RC_COMP_N", "40")
        original = [sim.read(f"RC_COMP[{i}]")[0] for i in range(1, 41)]
        cfg = base_config(tmp_path, limits={"max_joint_correction_deg": 5.0},
                          compensation={"verify_count": 3})
        cfg["robot"] = {"kind": "kuka_kvp", "options": cell.robot_options("kuka_kvp")}
        cfg["tracker"] = {"kind": "ltp", "options": {**cell.tracker_options("tcp"),
                                                     "stab_ms": 10}}
        svc = CalibrationService(parse_config(cfg, source="test"))
        await svc.start()
        try:
            st = await svc.create(program_plan(36, validation=8), actor="a")
            st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=120)
            assert st["state"] == "fitted", st["reason"]
            await svc.approve(st["id"], actor="a")
            st = await svc.push(st["id"], actor="a")
            v = await svc.wait_verification(st["push"]["key"], timeout=120)
            assert v is not None and v["state"] == "done", v
            assert v["after"]["rms_mm"] < 0.6 * v["before"]["rms_mm"]
            robot = await svc.hub.robot()
            table = await robot.read_compensation()
            assert table is not None and table.kind == "targets" and table.targets
            ok = [r for r in table.targets if r.status == "ok"]
            for r in ok:
                held = kvp.parse_e6axis(sim.read(f"RC_COMP[{r.index + 1}]")[0],
                                        components=len(r.q_deg))
                assert np.allclose(held, r.q_deg, atol=1e-4)
            # the checksum of the table as pushed (the re-read one differs in float32 digits)
            pushed = sim.read("RC_COMP_ID[]")[0].strip('"')
            assert len(pushed) == 64 and pushed in str(svc.compensation())

            await svc.rollback(actor="b")
            assert [sim.read(f"RC_COMP[{i}]")[0] for i in range(1, 41)] == original
            assert sim.read("RC_COMP_N") == ("40", True)
        finally:
            await svc.stop()
