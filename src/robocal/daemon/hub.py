"""The daemon's drivers: built by entry-point name from the configuration, connected on demand.

After any fault the hub drops both drivers (closing them), so the next use reconnects from a
clean session (a lost RMI session, a tracker link in an unknown state). The daemon reaches
simulated devices only this way, through real drivers and their wire protocols.

The hub owns the :class:`~robocal.drivers.DriverContext` its drivers are built in, so drivers
that share state (the mock robot and mock tracker share one simulated world) share it within
one hub, across reconnects, and never with another hub.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable
from typing import Any, Literal, TypeVar

import structlog

from robocal.daemon.config import AppConfig, DriverConfig
from robocal.drivers import (
    DriverContext,
    RobotDriver,
    TrackerDriver,
    load_robot_driver,
    load_tracker_driver,
)
from robocal.errors import ConnectFailed, DriverError, ProtocolError
from robocal.kinematics import RobotDescription

__all__ = ["DriverHub"]

_log = structlog.get_logger(__name__)
_T = TypeVar("_T")


def robot_options(cfg: DriverConfig, robot: RobotDescription) -> dict[str, Any]:
    """Driver options with ``joint_limits_deg`` defaulted from the robot description."""
    opts = dict(cfg.options)
    if cfg.kind != "mock" and "joint_limits_deg" not in opts:
        opts["joint_limits_deg"] = [[math.degrees(j.q_min), math.degrees(j.q_max)]
                                    for j in robot.joints]
    return opts


class DriverHub:
    """Owns the robot and tracker drivers.

    Parameters
    ----------
    config : AppConfig
        ``robot`` and ``tracker`` sections name the drivers and their options.
    robot : RobotDescription
        Supplies default joint limits.

    Attributes
    ----------
    lock : asyncio.Lock
        Held by whoever moves the robot or pushes compensation (one user at a time).
    context : DriverContext
        The scope the drivers are built in (lives as long as the hub).
    """

    def __init__(self, config: AppConfig, robot: RobotDescription) -> None:
        self.config = config
        self.description = robot
        self.lock = asyncio.Lock()
        self.context = DriverContext()
        self._robot: RobotDriver | None = None
        self._tracker: TrackerDriver | None = None
        self.last_error: str = ""

    def validate(self) -> None:
        """Build (not connect) both drivers once, so bad kinds or options fail at start-up."""
        load_robot_driver(self.config.robot.kind,
                          robot_options(self.config.robot, self.description),
                          context=self.context)
        load_tracker_driver(self.config.tracker.kind, self.config.tracker.options,
                            context=self.context)

    async def robot(self) -> RobotDriver:
        """The connected robot driver (connecting it if needed)."""
        if self._robot is None:
            cfg = self.config.robot
            drv = load_robot_driver(cfg.kind, robot_options(cfg, self.description),
                                    context=self.context)
            await drv.connect(timeout=cfg.connect_timeout_s)
            self._robot = drv
            _log.info("robot connected", driver=cfg.kind)
            self._clear_error_when_connected()
        return self._robot

    async def read_robot(self, read: Callable[[RobotDriver], Awaitable[_T]], *, what: str,
                         short: str) -> _T:
        """One read from the robot under the hub's lock (connecting it if needed).

        Raises
        ------
        ConnectFailed
            The robot does not answer: the hub is reset (``<short> not read``) and the error
            says ``<what> could not be read``.
        """
        try:
            async with self.lock:
                return await read(await self.robot())
        except (DriverError, ProtocolError, OSError, TimeoutError) as err:
            await self.reset(f"{short} not read: {err}")
            raise ConnectFailed(f"{what} could not be read: {err}") from err

    async def tracker(self) -> TrackerDriver:
        """The connected tracker driver (connecting it if needed)."""
        if self._tracker is None:
            cfg = self.config.tracker
            drv = load_tracker_driver(cfg.kind, cfg.options, context=self.context)
            await drv.connect(timeout=cfg.connect_timeout_s)
            self._tracker = drv
            _log.info("tracker connected", driver=cfg.kind)
            self._clear_error_when_connected()
        return self._tracker

    def _clear_error_when_connected(self) -> None:
        """The last error is history once both drivers are connected again."""
        if self._robot is not None and self._tracker is not None and self.last_error:
            _log.info("drivers connected again", cleared_error=self.last_error)
            self.last_error = ""

    async def stop_motion(
        self, reason: str, *, timeout: float = 5.0
    ) -> tuple[Literal["stopped", "not-connected", "failed"], str]:
        """Halt the robot at once with the driver's ``stop()``; never waits for :attr:`lock`.

        Returns ``(outcome, detail)``: ``"stopped"`` (the controller confirmed the halt),
        ``"not-connected"`` (no robot driver, so nothing of ours can be moving) or
        ``"failed"`` with the error; never raises a driver error.
        """
        robot = self._robot
        if robot is None:
            return "not-connected", ""
        t0 = time.monotonic()
        try:
            async with asyncio.timeout(timeout):
                await robot.stop()
        except Exception as err:  # any failure to confirm a stop is reported, not raised
            what = f"{type(err).__name__}: {err}"
            _log.error("robot stop failed", reason=reason, error=what)
            return "failed", what
        seconds = time.monotonic() - t0
        _log.warning("robot stopped", reason=reason, stop_s=round(seconds, 4))
        return "stopped", f"confirmed in {seconds:.3f} s"

    async def connect(self) -> None:
        """Connect both drivers."""
        await self.robot()
        await self.tracker()

    async def reset(self, reason: str = "") -> None:
        """Close and forget both drivers; the next use reconnects."""
        self.last_error = reason
        robot, tracker = self._robot, self._tracker
        self._robot = self._tracker = None
        for drv in (robot, tracker):
            if drv is not None:
                await drv.close()
        if robot is not None or tracker is not None:
            _log.info("drivers reset", reason=reason)

    async def close(self) -> None:
        """Close both drivers (shutdown)."""
        await self.reset("shutdown")

    def info(self) -> dict[str, Any]:
        """Driver kinds and whether they are connected."""
        return {
            "robot": {"kind": self.config.robot.kind, "connected": self._robot is not None},
            "tracker": {"kind": self.config.tracker.kind,
                        "connected": self._tracker is not None},
            "last_error": self.last_error,
        }
