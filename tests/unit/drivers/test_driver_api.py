"""Driver API: value types, capability protocols, the joint-target check."""

from __future__ import annotations

import dataclasses
import math

import pytest

from robocal.drivers import (
    CompensationSink,
    CompensationSlots,
    CompensationSnapshots,
    Connectable,
    JointMover,
    JointReader,
    JointReading,
    PointMeasurer,
    RobotDriver,
    TrackerDriver,
    TrackerReading,
    check_joint_target,
    require,
)
from robocal.drivers.fanuc_rmi import FanucRmiRobot
from robocal.drivers.ltp import LtpTracker
from robocal.drivers.mock import MockRobot, MockTracker
from robocal.drivers.modbus_plc import ModbusPlcRobot
from robocal.errors import DriverError, LimitViolation

LIMITS = [(-1.0, 1.0), (-2.0, 0.5)]


def test_check_joint_target_accepts_and_refuses():
    assert check_joint_target([0.0, -2.0], LIMITS) == (0.0, -2.0)
    assert check_joint_target((1, 0.5), LIMITS) == (1.0, 0.5)
    for bad in (
        [1.01, 0.0],
        [0.0, -2.1],
        [math.nan, 0.0],
        [0.0, math.inf],
        [0.0],
        [0, 0, 0],
        ["a", 0],
    ):
        with pytest.raises(LimitViolation):
            check_joint_target(bad, LIMITS, kind="x")


def test_limit_violation_message_is_in_degrees_and_names_joint():
    with pytest.raises(LimitViolation, match=r"J2 target -171\.8873 deg") as info:
        check_joint_target([0.0, -3.0], LIMITS, kind="fanuc_rmi")
    assert info.value.kind == "fanuc_rmi"
    assert isinstance(info.value, ValueError)


def test_value_types_are_frozen():
    j = JointReading((0.1, 0.2), 1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        j.q_rad = (0.0,)  # type: ignore[misc]
    t = TrackerReading((1.0, 2.0, 3.0), None, 1, None, 0.0)
    assert t.status == "ok" and t.weather == {} and t.point_id is None


@pytest.mark.parametrize(
    ("cls", "options"),
    [
        (MockRobot, {}),
        (FanucRmiRobot, {"joint_limits_deg": [(-170, 170)] * 6}),
        (ModbusPlcRobot, {"joint_limits_deg": [(-170, 170)] * 6}),
    ],
)
def test_robot_drivers_satisfy_protocols(cls, options):
    robot = cls(options)
    compensation = (CompensationSink, CompensationSlots, CompensationSnapshots)
    for proto in (Connectable, JointMover, JointReader, RobotDriver, *compensation):
        assert isinstance(robot, proto)
    assert not isinstance(robot, PointMeasurer)
    require(robot, RobotDriver, *compensation)


@pytest.mark.parametrize(
    ("cls", "options"), [(MockTracker, {}), (LtpTracker, {"url": "tcp://127.0.0.1:7710"})]
)
def test_tracker_drivers_satisfy_protocols(cls, options):
    tracker = cls(options)
    assert isinstance(tracker, TrackerDriver) and isinstance(tracker, PointMeasurer)
    assert not isinstance(tracker, JointMover)
    assert not isinstance(tracker, CompensationSlots | CompensationSnapshots)
    with pytest.raises(DriverError, match="JointMover"):
        require(tracker, JointMover)


def test_units_converted_at_boundary():
    robot = FanucRmiRobot({"joint_limits_deg": [(-180, 90)]})
    assert robot.dof == 1
    assert robot.joint_limits_rad == ((-math.pi, math.pi / 2),)
