"""The virtual robot's planted warm-up drift and the joint temperatures drivers read from it
(the mock in process, the Universal Robots driver over the real RTDE wire)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robocal.drivers import JointTemperatureReader, load_robot_driver
from robocal.drivers.mock import MockRobot
from robocal.drivers.sim import SimCell, SimWorld, UrSimOptions
from robocal.drivers.sim.world import COLD_C
from robocal.simulation import VirtualCell, WarmUpDrift

pytestmark = pytest.mark.timeout(30)


def test_planted_drift_grows_links_by_the_planted_amount_over_30_min():
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=3)
    drift = WarmUpDrift.planted(cell.robot, drift_m=1e-4)
    drift.advance(1800.0, moving=True)
    assert float(np.abs(drift.growth_m(drift.temps_c)).sum()) == pytest.approx(1e-4, rel=1e-9)
    # first order: after one time constant 63 % of the rise is there
    fresh = WarmUpDrift.planted(cell.robot)
    fresh.advance(fresh.tau_s, moving=True)
    assert fresh.temps_c - fresh.ambient_c == pytest.approx(fresh.rise_c * (1 - math.exp(-1)))
    # at ambient the drift model reproduces the planted kinematics exactly
    q = cell.random_joints(5, np.random.default_rng(0))
    cold = fresh.positions(cell, q, np.full(cell.robot.dof, fresh.ambient_c))
    assert np.allclose(cold, cell.reflector_position(q), atol=1e-12)
    warm = fresh.positions(cell, q, drift.temps_c)
    shift = np.linalg.norm(warm - cold, axis=1)
    assert np.all(shift > 1e-5) and np.all(shift < 1e-4 + 1e-9)


def test_world_heats_with_moves_and_the_mock_reads_it():
    world = SimWorld.create("fanuc_lrmate200i", "constant", seed=2, warmup_drift_mm=0.1)
    robot = MockRobot(world=world)
    assert isinstance(robot, JointTemperatureReader)
    temps0, t0 = world.joint_temperatures()
    assert temps0 == (20.0,) * world.dof and t0 == 0.0
    for k in range(200):
        world.move([0.4 * (-1) ** k] * world.dof)
    temps, t = world.joint_temperatures()
    assert t > 200.0 and all(a > b + 1.0 for a, b in zip(temps, temps0, strict=True))
    idle = SimWorld.create("fanuc_lrmate200i", "constant", seed=2)
    idle.move([0.4] * idle.dof)
    assert idle.joint_temperatures() == ((COLD_C,) * idle.dof, 0.0)


async def test_ur_driver_reads_joint_temperatures_over_rtde():
    world = SimWorld.create("ur10", "constant", seed=4, warmup_drift_mm=0.1)
    for k in range(100):  # warm the simulated arm before the driver connects
        world.move([0.3 * (-1) ** k] * world.dof)
    expected, _ = world.joint_temperatures()
    cell = SimCell(world=world, fanuc=False, modbus=False, ltp=False,
                   ur=UrSimOptions(time_scale=0.0, start_powered=True))
    async with cell:
        driver = load_robot_driver("universal_robots", cell.robot_options("universal_robots"))
        assert isinstance(driver, JointTemperatureReader)
        try:
            await driver.connect(timeout=5)  # type: ignore[attr-defined]
            reading = await driver.read_joint_temperatures()
        finally:
            await driver.close()  # type: ignore[attr-defined]
    assert reading.temps_c == pytest.approx(expected)
    assert min(reading.temps_c) > 21.0
    assert reading.timestamp >= 0.0
