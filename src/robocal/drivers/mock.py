"""In-process mock robot and tracker backed by the virtual robot (no I/O at all).

A :class:`MockRobot` and a :class:`MockTracker` built in one
:class:`~robocal.drivers.DriverContext` with the same ``robot``, ``scenario``, ``seed`` and
``world`` options share one :class:`~robocal.drivers.sim.world.SimWorld`, so the tracker
measures where the robot actually is. Built without a context (and without ``world=``), each
mock driver has a world of its own. They double as test doubles: faults can be injected
through their options.
"""

from __future__ import annotations

import asyncio
import math
import random
import time
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from pydantic import Field

from robocal.compensation import CompensationTable, Frame, FramesPayload
from robocal.drivers._base import DriverBase, DriverOptions, RobotDriverBase
from robocal.drivers._compensation import ControllerSnapshot, snapshot_diff, table_diff
from robocal.drivers._context import DriverContext
from robocal.drivers.api import (
    CompensationSink,
    CompensationSlots,
    CompensationSnapshots,
    JointReading,
    JointTemperatures,
    TrackerReading,
)
from robocal.drivers.sim.world import DEFAULT_ROBOT, SimWorld
from robocal.errors import (
    BeamLost,
    ConfigError,
    DriverTimeout,
    MotionStopped,
    Unstable,
)

__all__ = ["MockRobot", "MockRobotOptions", "MockTracker", "MockTrackerOptions"]


class _WorldOptions(DriverOptions):
    robot: str = DEFAULT_ROBOT
    scenario: str = "paper"
    seed: int = 1
    world: str = Field(default="default",
                       description="name of the world within the driver context")
    warmup_drift_mm: float = Field(default=0.0, ge=0.0, description=(
        "planted warm-up drift: link growth over 30 min of motion from cold, mm"))


def _world_for(o: _WorldOptions, context: DriverContext | None) -> SimWorld:
    """The world ``o`` names in ``context`` (created there once), or a new one without it."""
    def create() -> SimWorld:
        return SimWorld.create(o.robot, o.scenario, o.seed, warmup_drift_mm=o.warmup_drift_mm)

    if context is None:
        return create()
    return context.shared((__name__, o.robot, o.scenario, o.seed, o.world, o.warmup_drift_mm),
                          create)


class MockRobotOptions(_WorldOptions):
    """Options of :class:`MockRobot`.

    ``joint_limits_deg`` defaults to the virtual robot's limits; ``move_time_s`` is the
    simulated time per move (the joints sweep there, and :meth:`MockRobot.stop` halts them
    midway); ``corrupt_readback`` makes the stored compensation table differ
    from what was written (to exercise verification).
    """

    joint_limits_deg: tuple[tuple[float, float], ...] | None = None
    default_speed_pct: float = Field(default=10.0, gt=0.0, le=100.0)
    move_time_s: float = Field(default=0.0, ge=0.0)
    corrupt_readback: bool = False


class MockTrackerOptions(_WorldOptions):
    """Options of :class:`MockTracker`: fault rates per measurement and a fault seed."""

    beam_break_rate: float = Field(default=0.0, ge=0.0, le=1.0)
    unstable_rate: float = Field(default=0.0, ge=0.0, le=1.0)
    fault_seed: int = 0
    measure_time_s: float = Field(default=0.0, ge=0.0)


_ZERO_FRAME = Frame(x=0.0, y=0.0, z=0.0, w=0.0, p=0.0, r=0.0)
_EMPTY_FRAMES = CompensationTable(kind="frames", model_id="snapshot", robot="",
                                  valid_range_deg=[], predicted_residual_mm=0.0,
                                  frames=FramesPayload(base=_ZERO_FRAME, tool=_ZERO_FRAME))


class _OnWorld:
    """The virtual robot a mock driver acts on: given, shared through a context, or its own.

    Parameters
    ----------
    world : SimWorld, optional
        Use this world (the options' ``robot``, ``scenario``, ``seed`` and ``world`` are
        then ignored).
    context : DriverContext, optional
        Share the world named by the options with the other drivers of this context;
        without one (and without ``world``) the driver makes a world of its own.
    """

    options: _WorldOptions

    def __init__(self, *, world: SimWorld | None, context: DriverContext | None) -> None:
        self._world = world
        self._context = context

    @property
    def world(self) -> SimWorld:
        """The simulated world (created on first use; pure computation, no I/O)."""
        if self._world is None:
            self._world = _world_for(self.options, self._context)
        return self._world


class MockRobot(_OnWorld, RobotDriverBase, CompensationSink, CompensationSlots,
                CompensationSnapshots):
    """In-process robot: moves the virtual robot instantly (or over ``move_time_s``).

    Parameters
    ----------
    options : MockRobotOptions or mapping
        Validated options.
    world, context
        The virtual robot to act on, as for every mock driver (see ``_OnWorld``).
    """

    kind: ClassVar[str] = "mock"
    Options: ClassVar[type[DriverOptions]] = MockRobotOptions
    options: MockRobotOptions  # type: ignore[assignment]
    supported_compensation: ClassVar[frozenset[str]] = frozenset({"targets", "joint", "frames"})

    def __init__(
        self,
        options: MockRobotOptions | Mapping[str, Any] | None = None,
        *,
        world: SimWorld | None = None,
        context: DriverContext | None = None,
    ) -> None:
        RobotDriverBase.__init__(self, options)
        _OnWorld.__init__(self, world=world, context=context)
        self._stored: str | None = None
        self._stop_event = asyncio.Event()

    @property
    def dof(self) -> int:
        """Number of joints."""
        return len(self.joint_limits_rad)

    @property
    def joint_limits_rad(self) -> tuple[tuple[float, float], ...]:
        """Configured limits, or the virtual robot's, radians."""
        lim = self.options.joint_limits_deg
        if lim is None:
            return self.world.joint_limits_rad
        return tuple((math.radians(lo), math.radians(hi)) for lo, hi in lim)

    async def _connect_impl(self, timeout: float) -> None:
        if self.dof != self.world.dof:
            raise ConfigError(
                f"{len(self.joint_limits_rad)} joint limits for a {self.world.dof}-joint robot",
                source="mock options",
                key="joint_limits_deg",
            )

    async def _close_impl(self) -> None:
        return None

    async def move_to(
        self, q_rad: Sequence[float], *, speed_pct: float | None = None, timeout: float = 60.0
    ) -> JointReading:
        """Move the virtual robot to ``q_rad`` (radians) and return the actual joints."""
        q = self._check_target(q_rad)
        self._ensure_connected()
        duration = self.options.move_time_s
        if duration <= 0:
            self.world.move(q)
            return await self.read_joints()
        stopped = self._stop_event
        # Like a controller, the motion runs on if this call is cancelled; only stop() halts it.
        motion = self.world.start_motion(q, duration)
        try:
            async with asyncio.timeout(min(duration, timeout)):
                await stopped.wait()
        except TimeoutError:
            if duration > timeout:
                self.world.halt()
                raise DriverTimeout(
                    f"move not finished within {timeout:.3g} s; halted", kind=self.kind
                ) from None
        if not self.world.finish_motion(motion):
            if stopped.is_set():
                raise MotionStopped("motion stopped by request", kind=self.kind)
            raise MotionStopped("motion superseded by another move", kind=self.kind)
        return await self.read_joints()

    async def stop(self) -> None:
        """Halt the virtual robot where it is; a waiting ``move_to`` raises MotionStopped."""
        if self.state != "connected":
            return
        self.world.halt()
        self._stop_event.set()
        self._stop_event = asyncio.Event()
        await asyncio.sleep(0)
        self.log.info("stopped", q_rad=[round(float(v), 6) for v in self.world.q_actual_rad])

    async def read_joints(self) -> JointReading:
        """Return the virtual robot's actual joints (radians)."""
        self._ensure_connected()
        await asyncio.sleep(0)
        return JointReading(tuple(float(v) for v in self.world.q_actual_rad), time.time())

    async def read_joint_temperatures(self) -> JointTemperatures:
        """The virtual robot's joint temperatures (°C) on the world's simulated clock."""
        self._ensure_connected()
        await asyncio.sleep(0)
        temps, t = self.world.joint_temperatures()
        return JointTemperatures(temps, t)

    async def write_compensation(self, table: CompensationTable) -> None:
        """Store ``table`` (as JSON), read it back and verify content and checksum."""
        self._ensure_connected()
        sealed = table if table.checksum else table.sealed()
        stored = sealed
        if self.options.corrupt_readback:
            stored = sealed.model_copy(update={"predicted_residual_mm": 1e9})
        self._stored = stored.model_dump_json()
        back = await self.read_compensation()
        diff = table_diff(sealed, back)
        if back is not None and back.checksum != sealed.checksum:
            diff.append("checksum differs")
        self._check_read_back(diff, "compensation read back differs")

    async def read_compensation(self) -> CompensationTable | None:
        """Return the stored table, or None."""
        self._ensure_connected()
        if self._stored is None:
            return None
        return CompensationTable.model_validate_json(self._stored)

    async def read_compensation_like(self, table: CompensationTable) -> CompensationTable | None:
        """The stored table (the mock keeps whole tables, so the slots are the table)."""
        return await self.read_compensation()

    async def snapshot_compensation(self, table: CompensationTable) -> ControllerSnapshot:
        """What the mock holds before a write (``None`` when it holds no table)."""
        self._ensure_connected()
        return ControllerSnapshot(driver=self.kind, covers=table.kind,
                                  items={"table": self._stored})

    async def restore_snapshot(self, snapshot: ControllerSnapshot) -> None:
        """Put a snapshot back and verify it."""
        self._ensure_connected()
        stored = snapshot.items.get("table")
        self._stored = stored if isinstance(stored, str) else None
        back = await self.snapshot_compensation(
            CompensationTable.model_validate_json(stored) if isinstance(stored, str)
            else _EMPTY_FRAMES)
        diff = snapshot_diff(snapshot.model_copy(update={"covers": back.covers}), back)
        self._check_read_back(diff, "restored table differs")


class MockTracker(_OnWorld, DriverBase):
    """In-process tracker measuring the virtual robot's reflector with noise.

    ``options`` (MockTrackerOptions or a mapping) are validated; ``world`` and ``context``
    choose the virtual robot as for every mock driver (see ``_OnWorld``).
    """

    kind: ClassVar[str] = "mock"
    Options: ClassVar[type[DriverOptions]] = MockTrackerOptions
    options: MockTrackerOptions

    def __init__(
        self,
        options: MockTrackerOptions | Mapping[str, Any] | None = None,
        *,
        world: SimWorld | None = None,
        context: DriverContext | None = None,
    ) -> None:
        DriverBase.__init__(self, options)
        _OnWorld.__init__(self, world=world, context=context)
        self._faults = random.Random(self.options.fault_seed)

    async def _connect_impl(self, timeout: float) -> None:
        _ = self.world

    async def _close_impl(self) -> None:
        return None

    async def measure(
        self, *, samples: int = 10, timeout: float = 10.0, point_id: str | None = None
    ) -> TrackerReading:
        """Measure the reflector of the virtual robot (metres, tracker frame)."""
        self._ensure_connected()
        if samples < 1:
            raise ConfigError("samples must be at least 1", source="measure", key="samples")
        if self.options.measure_time_s > 0:
            await asyncio.sleep(min(self.options.measure_time_s, timeout))
        else:
            await asyncio.sleep(0)
        if self._faults.random() < self.options.beam_break_rate:
            raise BeamLost("beam broken (injected)", kind=self.kind)
        if self._faults.random() < self.options.unstable_rate:
            raise Unstable("target not stable (injected)", kind=self.kind)
        m = self.world.measure(samples)
        return TrackerReading(
            position_m=m.mean_m,
            std_m=m.std_m,
            n=m.n,
            rms_m=m.rms_m,
            timestamp=time.time(),
            status="ok",
            weather={"temp_c": 20.0, "press_hpa": 1013.25, "hum_pct": 45.0},
            point_id=point_id,
        )
