"""Robot and tracker drivers: capability protocols, registry, retry helper.

Drivers are found by name through the entry-point groups ``robocal.robots`` and
``robocal.trackers`` and imported lazily; this package imports none of them (nor the
simulators in :mod:`robocal.drivers.sim`).

>>> from robocal.drivers import available
>>> "mock" in available()["robots"]
True
"""

from robocal.drivers import api
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
from robocal.drivers.api import *  # noqa: F403 (its __all__ is re-exported below)

__all__ = [
    "RETRYABLE",
    "ROBOT_GROUP",
    "TRACKER_GROUP",
    "ControllerSnapshot",
    "DriverBase",
    "DriverContext",
    "DriverOptions",
    "RobotDriverBase",
    "RobotOptions",
    "available",
    "driver_class",
    "load_robot_driver",
    "load_tracker_driver",
    "measure_with_retry",
    "snapshot_diff",
    "table_diff",
    "with_retry",
]
__all__ += api.__all__
