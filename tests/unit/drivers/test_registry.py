"""Driver registry over entry points."""

from __future__ import annotations

from importlib.metadata import EntryPoint
from typing import Any

import pytest

from robocal.drivers import (
    DriverContext,
    _registry,
    available,
    driver_class,
    load_robot_driver,
    load_tracker_driver,
)
from robocal.drivers.fanuc_rmi import FanucRmiRobot
from robocal.drivers.ltp import LtpTracker
from robocal.drivers.mock import MockRobot, MockTracker
from robocal.drivers.modbus_plc import ModbusPlcRobot
from robocal.drivers.universal_robots import UniversalRobotsRobot
from robocal.errors import ConfigError, DriverImportError, DriverNotFound


def test_available_lists_declared_entry_points():
    assert available() == {
        "robots": ["abb_rws", "fanuc_rmi", "kuka_kvp", "mock", "modbus_plc", "universal_robots"],
        "trackers": ["emscon", "ltp", "mock"],
    }


def test_driver_classes_resolve():
    assert driver_class("fanuc_rmi", role="robot") is FanucRmiRobot
    assert driver_class("modbus_plc", role="robot") is ModbusPlcRobot
    assert driver_class("universal_robots", role="robot") is UniversalRobotsRobot
    assert driver_class("mock", role="robot") is MockRobot
    assert driver_class("mock", role="tracker") is MockTracker
    assert driver_class("ltp", role="tracker") is LtpTracker


def test_load_validates_options():
    robot = load_robot_driver("fanuc_rmi",
                              {"host": "10.0.0.5", "joint_limits_deg": [[-170, 170]] * 6})
    assert isinstance(robot, FanucRmiRobot)
    assert robot.options.host == "10.0.0.5" and robot.options.connect_port == 16001
    tracker = load_tracker_driver("ltp", {"url": "serial:///dev/ttyUSB0?baudrate=115200"})
    assert isinstance(tracker, LtpTracker)


def test_unknown_kind():
    with pytest.raises(DriverNotFound, match=r"no robot driver named 'kuka'.*fanuc_rmi") as info:
        load_robot_driver("kuka", {})
    assert info.value.kind == "kuka"
    assert isinstance(info.value, LookupError)
    with pytest.raises(DriverNotFound):
        load_tracker_driver("fanuc_rmi", {})


def test_bad_options_name_kind_and_key():
    with pytest.raises(ConfigError) as info:
        load_robot_driver("fanuc_rmi", {"joint_limits_deg": [[-1, 1]], "hots": "x"})
    assert info.value.key == "hots" and "fanuc_rmi" in str(info.value)
    with pytest.raises(ConfigError) as info:
        load_robot_driver("fanuc_rmi", {"joint_limits_deg": [[1, -1]]})
    assert info.value.key == "joint_limits_deg"
    with pytest.raises(ConfigError, match="url"):
        load_tracker_driver("ltp", {})
    with pytest.raises(ConfigError, match="mapping"):
        load_tracker_driver("ltp", ["url"])  # type: ignore[arg-type]


def test_options_are_frozen():
    robot = load_robot_driver("mock", {})
    with pytest.raises(Exception, match="frozen"):
        robot.options.seed = 3  # type: ignore[misc]


def fake_eps(monkeypatch, **values):
    eps = [EntryPoint(name=k, value=v, group=_registry.ROBOT_GROUP) for k, v in values.items()]
    monkeypatch.setattr(
        _registry, "entry_points", lambda group: eps if group == _registry.ROBOT_GROUP else []
    )


def test_import_failure_is_wrapped(monkeypatch):
    fake_eps(monkeypatch, broken="robocal_no_such_module:Robot")
    with pytest.raises(DriverImportError, match="robocal_no_such_module") as info:
        load_robot_driver("broken", {})
    assert info.value.kind == "broken"
    assert isinstance(info.value.__cause__, ModuleNotFoundError)


def test_object_without_options_is_refused(monkeypatch):
    fake_eps(monkeypatch, notadriver="robocal.errors:RobocalError")
    with pytest.raises(DriverImportError, match="Options"):
        load_robot_driver("notadriver", {})


def test_class_lacking_capabilities_is_refused(monkeypatch):
    fake_eps(monkeypatch, tracker_as_robot="robocal.drivers.mock:MockTracker")
    with pytest.raises(DriverImportError, match="robot driver protocols"):
        load_robot_driver("tracker_as_robot", {})


class _NoContextRobot(MockRobot):
    """A plugin-style driver whose constructor takes the options only."""

    def __init__(self, options=None) -> None:
        super().__init__(options)


def test_a_driver_without_a_context_parameter_is_built_without_it(monkeypatch):
    monkeypatch.setattr(_registry, "driver_class", lambda kind, role: _NoContextRobot)
    robot = load_robot_driver("plugin", {"seed": 2}, context=DriverContext())
    assert isinstance(robot, _NoContextRobot)


def test_a_driver_taking_a_context_gets_the_callers():
    context = DriverContext()
    robot: Any = load_robot_driver("mock", {}, context=context)
    tracker: Any = load_tracker_driver("mock", {}, context=context)
    assert robot._context is context
    assert robot.world is tracker.world
    assert len(context) == 1
