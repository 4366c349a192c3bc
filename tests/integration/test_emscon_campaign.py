"""100 poses through fanuc_rmi + emscon against the simulators, with ~10 % tracker faults:
driver level (with ``measure_with_retry``) and through the daemon with the deploy config.

Beam breaks are re-acquired inside the emscon driver (GoPosition + FindReflector), an
unstable target is retried by the caller (``measure_with_retry``), busy replies and split,
merged or foreign packets are absorbed by the driver. Every pose must end up measured, within
a few reported sigmas of the virtual robot's true reflector position.
"""

from __future__ import annotations

import asyncio
import tomllib
from pathlib import Path

import numpy as np
from tests.unit.daemon.conftest import ROBOT, random_plan

from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers import load_robot_driver, load_tracker_driver, measure_with_retry
from robocal.drivers.sim import EmsconSimOptions, FanucSimOptions, FaultConfig, SimCell
from robocal.drivers.sim.emscon import EmsconFaults

N_POSES = 100
SAMPLES = 10


async def test_fanuc_rmi_and_emscon_campaign_with_faults():
    faults = FaultConfig(beam_break_rate=0.05, unstable_rate=0.05, seed=21)
    wire = EmsconFaults(busy_rate=0.02, split_rate=0.05, merge_rate=0.05,
                        unknown_type_rate=0.03, error_packet_rate=0.02)
    cell = SimCell(
        seed=17,
        fanuc=FanucSimOptions(time_scale=0.001),
        modbus=False,
        ltp=False,
        emscon=EmsconSimOptions(time_scale=0.001, faults=wire),
        faults=faults,
    )
    async with cell:
        world = cell.world
        robot = load_robot_driver("fanuc_rmi", cell.robot_options("fanuc_rmi"))
        tracker = load_tracker_driver("emscon", {**cell.emscon_options(), "abort_drain_s": 0.02,
                                          "busy_backoff_s": 0.001})
        await robot.connect(timeout=10)
        await tracker.connect(timeout=10)
        try:
            rng = np.random.default_rng(7)
            lim = np.asarray(robot.joint_limits_rad)
            centre, half = lim.mean(axis=1), 0.4 * (lim[:, 1] - lim[:, 0])
            poses = rng.uniform(centre - half, centre + half, (N_POSES, robot.dof))
            z_scores, measured = [], 0
            for i, q in enumerate(poses):
                await robot.move_to(q, speed_pct=50, timeout=10)
                reading = await measure_with_retry(tracker, samples=SAMPLES, timeout=2.0,
                                                   point_id=f"P{i:04d}", attempts=6,
                                                   backoff_s=0.001)
                measured += 1
                assert reading.point_id == f"P{i:04d}" and reading.n == SAMPLES
                truth = world.true_reflector_position()
                z = (np.asarray(reading.position_m) - truth) / np.asarray(reading.std_m)
                assert np.all(np.abs(z) < 5.0), f"pose {i}: {z} sigmas from the truth"
                z_scores.append(z)
        finally:
            await tracker.close()
            await robot.close()
        sim = cell.emscon_sim
        assert sim is not None
        shared, wire_counts = sim.faults.counts, sim.emscon_faults.counts
        commands = [c.name for c in sim.commands]
    assert measured == N_POSES
    # The faults really happened: ~10 % of the first attempts failed.
    assert 5 <= shared.get("beam_break", 0) + shared.get("unstable", 0) <= 25, shared
    assert commands.count("FindReflector") >= shared.get("beam_break", 0) > 0
    assert min(wire_counts.get(k, 0) for k in ("busy", "split", "merge", "unknown_type")) > 0
    assert "ExitApplication" not in commands
    # The reported uncertainty is honest: normalised errors have unit variance (3 x 100).
    var = float(np.mean(np.square(z_scores)))
    assert 0.7 < var < 1.4, var


async def test_daemon_campaign_with_the_documented_emscon_config(tmp_path):
    """The daemon runs a 100-pose campaign with deploy/config/emscon.toml's tracker options."""
    deploy = Path(__file__).resolve().parents[2] / "deploy" / "config" / "emscon.toml"
    doc = tomllib.loads(deploy.read_text())
    cell = SimCell(robot=ROBOT, seed=4, fanuc=FanucSimOptions(time_scale=0.0), modbus=False,
                   ltp=False, emscon=EmsconSimOptions(time_scale=0.001),
                   faults=FaultConfig(beam_break_rate=0.05, unstable_rate=0.05, seed=5))
    async with cell:
        doc["data_dir"] = str(tmp_path / "state")
        doc["robot_description"] = ROBOT
        # The random plan is not checked against a cell's obstacles (the planner's job).
        doc.pop("cell", None)
        doc["robot"]["options"] = cell.robot_options("fanuc_rmi")
        doc["tracker"]["options"].update(cell.emscon_options())
        doc["api"] = {"socket": str(tmp_path / "api.sock")}
        doc["measurement"].update({"settle_s": 0.0, "backoff_s": 0.001})
        doc["fit"] = {"models": ["constant"], "select": "constant", "executor": "thread",
                      "report": False}
        svc = CalibrationService(parse_config(doc, source=str(deploy)))
        await svc.start()
        try:
            st = await svc.create(random_plan(N_POSES), actor="t")
            st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=120)
            assert st["state"] == "fitted", st.get("reason")
            rows = svc.store.measurements(st["id"])
            assert sorted(r.pose_idx for r in rows) == list(range(N_POSES))
            assert all(r.samples == doc["measurement"]["samples"] for r in rows)
            assert any(r.attempts > 1 for r in rows)  # injected faults were retried
        finally:
            await svc.stop()
            await asyncio.sleep(0.05)
    sim = cell.emscon_sim
    assert sim is not None and sim.faults.counts.get("unstable", 0) > 0
