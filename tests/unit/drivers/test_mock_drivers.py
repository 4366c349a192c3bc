"""Mock robot and tracker over a virtual world shared through a driver context."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robocal.compensation import CompensationTable, Frame, FramesPayload
from robocal.drivers import DriverContext, load_robot_driver, load_tracker_driver
from robocal.drivers.mock import MockRobot, MockTracker
from robocal.drivers.sim.world import SimWorld
from robocal.errors import BeamLost, ConfigError, ConnectFailed, Unstable, VerificationMismatch


def frames_table() -> CompensationTable:
    return CompensationTable(
        kind="frames",
        model_id="m",
        robot="r",
        valid_range_deg=[(-1.0, 1.0)],
        predicted_residual_mm=0.1,
        frames=FramesPayload(
            base=Frame(x=1, y=2, z=3, w=0, p=0, r=90), tool=Frame(x=0, y=0, z=100, w=0, p=0, r=0)
        ),
    ).sealed()


async def test_tracker_measures_where_the_robot_is():
    context = DriverContext()
    robot = load_robot_driver("mock", {"seed": 4}, context=context)
    tracker = load_tracker_driver("mock", {"seed": 4}, context=context)
    await robot.connect(timeout=1)
    await tracker.connect(timeout=1)
    world = robot.world
    assert tracker.world is world
    rng = np.random.default_rng(0)
    lim = np.array(robot.joint_limits_rad)
    for _ in range(5):
        q = rng.uniform(lim[:, 0] * 0.8, lim[:, 1] * 0.8)
        reading = await robot.move_to(q, speed_pct=10, timeout=1)
        assert np.allclose(reading.q_rad, q, atol=1e-4)
        m = await tracker.measure(samples=20, timeout=1, point_id="x")
        truth = world.true_reflector_position()
        sigma = np.asarray(world.measure(1).sigma_m)
        assert np.all(np.abs(np.asarray(m.position_m) - truth) < 5 * sigma)
        assert m.point_id == "x" and m.n == 20
    await robot.close()
    await tracker.close()


async def test_separate_world_names_do_not_share():
    context = DriverContext()
    a = MockRobot({"world": "a"}, context=context)
    b = MockTracker({"world": "b"}, context=context)
    assert a.world is not b.world
    assert MockTracker({"world": "a"}, context=context).world is a.world


async def test_worlds_are_shared_only_within_one_context():
    one, other = DriverContext(), DriverContext()
    robot = load_robot_driver("mock", {}, context=one)
    assert load_tracker_driver("mock", {}, context=one).world is robot.world
    assert load_tracker_driver("mock", {}, context=other).world is not robot.world
    # Without a context every mock driver has a world of its own.
    assert MockTracker().world is not MockRobot().world
    assert load_tracker_driver("mock", {}).world is not load_robot_driver("mock", {}).world


async def test_explicit_world_and_limits_override():
    world = SimWorld.create(seed=9)
    robot = MockRobot({"joint_limits_deg": [(-10, 10)] * world.dof}, world=world)
    assert robot.joint_limits_rad[0] == pytest.approx((-math.radians(10), math.radians(10)))
    await robot.connect(timeout=1)
    with pytest.raises(Exception, match="outside"):
        await robot.move_to([math.radians(11)] + [0.0] * (world.dof - 1), speed_pct=10, timeout=1)
    await robot.close()
    wrong = MockRobot({"joint_limits_deg": [(-10, 10)]}, world=world)
    with pytest.raises(ConfigError):
        await wrong.connect(timeout=1)
    assert wrong.state == "closed"


async def test_fault_injection_and_sample_check():
    tracker = MockTracker({"beam_break_rate": 1.0})
    await tracker.connect(timeout=1)
    with pytest.raises(BeamLost):
        await tracker.measure(samples=1, timeout=1)
    await tracker.close()
    tracker = MockTracker({"unstable_rate": 1.0})
    await tracker.connect(timeout=1)
    with pytest.raises(Unstable):
        await tracker.measure(samples=1, timeout=1)
    with pytest.raises(ConfigError):
        await tracker.measure(samples=0, timeout=1)
    await tracker.close()
    with pytest.raises(ConnectFailed):
        await tracker.measure(samples=1, timeout=1)


async def test_compensation_round_trip_and_verification():
    robot = MockRobot()
    await robot.connect(timeout=1)
    assert await robot.read_compensation() is None
    table = frames_table()
    await robot.write_compensation(table)
    assert await robot.read_compensation() == table
    await robot.close()
    bad = MockRobot({"corrupt_readback": True})
    await bad.connect(timeout=1)
    with pytest.raises(VerificationMismatch) as info:
        await bad.write_compensation(table)
    assert any("predicted_residual_mm" in d for d in info.value.diff)
    await bad.close()
