"""Robot and tracker drivers: capability protocols, registry, retry helper.

Drivers are found by name through the entry-point groups ``robocal.robots`` and
``robocal.trackers`` and imported lazily; this package imports none of them (nor the
simulators in :mod:`robocal.drivers.sim`).

>>> from robocal.drivers import available
>>> "mock" in available()["robots"]
True
"""

from robocal.drivers._base import DriverBase, DriverOptions, RobotDriverBase, RobotOptions
from robocal.drivers._compensation import ControllerSnapshot, snapshot_diff, table_diff
from robocal.drivers._context import DriverContext
from robocal.drivers._registry import (
    ROBOT_GROUP,
    TRACKER_GROUP,
    available,
    driver_class,
    load_robot_driver,
    load_tracker_driver,
)
from robocal.drivers._retry import RETRYABLE, measure_with_retry, with_retry
from robocal.drivers.api import (
    CompensationSink,
    CompensationSlots,
    CompensationSnapshots,
    Connectable,
    ControllerCalibration,
    ControllerCalibrationReadable,
    JointMover,
    JointReader,
    JointReading,
    JointTemperatureReader,
    JointTemperatures,
    PointMeasurer,
    RobotDriver,
    Stoppable,
    TrackerDriver,
    TrackerReading,
    check_joint_target,
    require,
)

__all__ = [
    "RETRYABLE",
    "ROBOT_GROUP",
    "TRACKER_GROUP",
    "CompensationSink",
    "CompensationSlots",
    "CompensationSnapshots",
    "Connectable",
    "ControllerCalibration",
    "ControllerCalibrationReadable",
    "ControllerSnapshot",
    "DriverBase",
    "DriverContext",
    "DriverOptions",
    "JointMover",
    "JointReader",
    "JointReading",
    "JointTemperatureReader",
    "JointTemperatures",
    "PointMeasurer",
    "RobotDriver",
    "RobotDriverBase",
    "RobotOptions",
    "Stoppable",
    "TrackerDriver",
    "TrackerReading",
    "available",
    "check_joint_target",
    "driver_class",
    "load_robot_driver",
    "load_tracker_driver",
    "measure_with_retry",
    "require",
    "snapshot_diff",
    "table_diff",
    "with_retry",
]
