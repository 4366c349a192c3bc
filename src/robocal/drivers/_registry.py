"""Driver registry: names resolved lazily through ``importlib.metadata`` entry points.

Groups ``robocal.robots`` and ``robocal.trackers``; a third-party package adds a driver with::

    [project.entry-points."robocal.trackers"]
    leica-emscon = "mypkg.leica:LeicaTracker"

A driver class is built as ``cls(options)``. One whose constructor also takes a ``context``
keyword is built as ``cls(options, context=...)`` when the caller passes a
:class:`~robocal.drivers.DriverContext`, the scope in which drivers built together share
state (the mock drivers share their simulated world there).
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Literal

from robocal.drivers._base import validate_options
from robocal.drivers._context import DriverContext
from robocal.drivers.api import (
    Connectable,
    JointMover,
    JointReader,
    PointMeasurer,
    RobotDriver,
    Stoppable,
    TrackerDriver,
)
from robocal.errors import ConfigError, DriverImportError, DriverNotFound

__all__ = [
    "ROBOT_GROUP",
    "TRACKER_GROUP",
    "available",
    "driver_class",
    "load_robot_driver",
    "load_tracker_driver",
]

ROBOT_GROUP = "robocal.robots"
TRACKER_GROUP = "robocal.trackers"
Role = Literal["robot", "tracker"]
_GROUPS: dict[Role, str] = {"robot": ROBOT_GROUP, "tracker": TRACKER_GROUP}


def _entry_points(group: str) -> dict[str, EntryPoint]:
    return {ep.name: ep for ep in entry_points(group=group)}


def available() -> dict[str, list[str]]:
    """Return the installed driver names: ``{"robots": [...], "trackers": [...]}``.

    Nothing is imported; this only reads package metadata.
    """
    return {
        "robots": sorted(_entry_points(ROBOT_GROUP)),
        "trackers": sorted(_entry_points(TRACKER_GROUP)),
    }


def driver_class(kind: str, *, role: Role) -> type[Any]:
    """Import and return the driver class registered as ``kind``.

    Raises
    ------
    DriverNotFound
        If no entry point of that name exists in the role's group.
    DriverImportError
        If importing the module or class fails, or the object is not a driver class.
    """
    group = _GROUPS[role]
    eps = _entry_points(group)
    ep = eps.get(kind)
    if ep is None:
        known = ", ".join(sorted(eps)) or "none"
        raise DriverNotFound(f"no {role} driver named {kind!r} (installed: {known})", kind=kind)
    try:
        cls = ep.load()
    except Exception as err:
        raise DriverImportError(
            f"cannot import {ep.value} for {role} driver {kind!r}: {type(err).__name__}: {err}",
            kind=kind,
        ) from err
    options = getattr(cls, "Options", None)
    if not isinstance(cls, type) or options is None or not hasattr(options, "model_validate"):
        raise DriverImportError(
            f"{ep.value} is not a driver class with a pydantic Options model", kind=kind
        )
    return cls


def _takes_context(cls: type[Any]) -> bool:
    """True if ``cls(options, context=...)`` is how ``cls`` wants to be built."""
    try:
        param = inspect.signature(cls).parameters.get("context")
    except (TypeError, ValueError):
        return False
    return param is not None and param.kind in (param.KEYWORD_ONLY,
                                                param.POSITIONAL_OR_KEYWORD)


def _load(kind: str, options: Mapping[str, Any] | None, role: Role,
          context: DriverContext | None) -> Any:
    cls = driver_class(kind, role=role)
    opts = validate_options(cls.Options, options, kind=kind)
    try:
        if context is not None and _takes_context(cls):
            driver = cls(opts, context=context)
        else:
            driver = cls(opts)
    except ConfigError:
        raise
    except Exception as err:
        raise DriverImportError(
            f"{cls.__qualname__}(options) failed: {type(err).__name__}: {err}", kind=kind
        ) from err
    expected = RobotDriver if role == "robot" else TrackerDriver
    if not isinstance(driver, expected):
        parts: tuple[type, ...] = (
            (Connectable, JointMover, JointReader, Stoppable)
            if role == "robot"
            else (Connectable, PointMeasurer)
        )
        missing = ", ".join(p.__name__ for p in parts if not isinstance(driver, p))
        raise DriverImportError(
            f"{cls.__qualname__} does not implement the {role} driver protocols "
            f"(missing: {missing})",
            kind=kind,
        )
    return driver


def load_robot_driver(kind: str, options: Mapping[str, Any] | None = None, *,
                      context: DriverContext | None = None) -> RobotDriver:
    """Build (not connect) the robot driver ``kind`` with validated ``options``.

    ``context`` is handed to a driver that takes one (see the module docstring); without
    it, a driver shares nothing with the others (a mock robot gets a world of its own).

    Raises
    ------
    DriverNotFound, DriverImportError
        See :func:`driver_class`.
    ConfigError
        If ``options`` do not validate against the driver's ``Options`` (the key is named).
    """
    return _load(kind, options, "robot", context)


def load_tracker_driver(kind: str, options: Mapping[str, Any] | None = None, *,
                        context: DriverContext | None = None) -> TrackerDriver:
    """Build (not connect) the tracker driver ``kind`` with validated ``options``.

    ``context`` as in :func:`load_robot_driver`.

    Raises
    ------
    DriverNotFound, DriverImportError, ConfigError
        As :func:`load_robot_driver`.
    """
    return _load(kind, options, "tracker", context)
