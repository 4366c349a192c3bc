"""50 poses through fanuc_rmi + ltp against the simulators, with faults on ~10 % of readings.

The driver-user code retries recoverable tracker failures with backoff
(``measure_with_retry``). Every pose must end up measured, and every measurement must lie
within a few tracker sigmas of the virtual robot's true reflector position.
"""

from __future__ import annotations

import time

import numpy as np

from robocal.drivers import load_robot_driver, load_tracker_driver, measure_with_retry
from robocal.drivers.sim import FanucSimOptions, FaultConfig, LtpSimOptions, SimCell

N_POSES = 50
SAMPLES = 16


async def test_campaign_with_injected_tracker_faults():
    faults = FaultConfig(beam_break_rate=0.05, unstable_rate=0.05, garbage_rate=0.02, seed=2)
    cell = SimCell(
        seed=11,
        fanuc=FanucSimOptions(time_scale=0.001),
        modbus=False,
        ltp=LtpSimOptions(time_scale=0.001, event_rate=0.1),
        faults=faults,
    )
    started = time.perf_counter()
    async with cell:
        world = cell.world
        robot = load_robot_driver("fanuc_rmi", cell.robot_options("fanuc_rmi"))
        tracker = load_tracker_driver("ltp", cell.tracker_options("tcp"))
        await robot.connect(timeout=10)
        await tracker.connect(timeout=10)
        try:
            rng = np.random.default_rng(2024)
            lim = np.asarray(robot.joint_limits_rad)
            centre, half = lim.mean(axis=1), 0.4 * (lim[:, 1] - lim[:, 0])
            poses = rng.uniform(centre - half, centre + half, (N_POSES, robot.dof))
            z_scores, measured = [], 0
            for i, q in enumerate(poses):
                joints = await robot.move_to(q, speed_pct=50, timeout=10)
                assert np.allclose(joints.q_rad, world.q_actual_rad, atol=1e-9)
                assert np.allclose(joints.q_rad, q, atol=1e-4)
                reading = await measure_with_retry(
                    tracker,
                    samples=SAMPLES,
                    timeout=2.0,
                    point_id=f"P{i:04d}",
                    attempts=8,
                    backoff_s=0.001,
                )
                measured += 1
                assert reading.point_id == f"P{i:04d}" and reading.n == SAMPLES
                truth = world.true_reflector_position()
                z = (np.asarray(reading.position_m) - truth) / np.asarray(reading.std_m)
                assert np.all(np.abs(z) < 5.0), f"pose {i}: {z} sigmas from the truth"
                z_scores.append(z)
        finally:
            await tracker.close()
            await robot.close()
        injected = cell.ltp_sim.faults.counts
    assert measured == N_POSES
    # About 10 % of readings failed at first and were retried: the faults really happened.
    failures = injected.get("beam_break", 0) + injected.get("unstable", 0)
    assert 3 <= failures <= 15, injected
    # The reported uncertainty is honest: normalised errors have unit variance (3 x 50 values).
    var = float(np.mean(np.square(z_scores)))
    assert 0.6 < var < 1.5, var
    assert time.perf_counter() - started < 30.0
