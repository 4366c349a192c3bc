"""Contract checks every robot and tracker driver must pass, fake or real.

Public so third-party driver packages can run them (like scikit-learn's
``parametrize_with_checks``). Describe the driver under test with :class:`RobotUnderTest` or
:class:`TrackerUnderTest`, then run one check per test::

    @pytest.mark.parametrize("check", robot_checks(), ids=lambda c: c.__name__)
    async def test_my_robot(check, my_sim):
        await check(RobotUnderTest("my_robot", make=lambda: MyRobot(my_sim.options)))

or everything at once with :func:`check_robot` / :func:`check_tracker`. Every check builds
its own driver with ``make()`` and closes it, whatever happens.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel

from robocal.compensation import (
    CompensationTable,
    Frame,
    FramesPayload,
    JointCorrection,
    TargetRow,
)
from robocal.drivers._compensation import table_diff
from robocal.drivers.api import (
    CompensationSink,
    ControllerCalibration,
    ControllerCalibrationReadable,
    JointReading,
    RobotDriver,
    Stoppable,
    TrackerDriver,
    TrackerReading,
)
from robocal.errors import (
    ConnectFailed,
    DriverError,
    LimitViolation,
    MotionStopped,
    RobocalError,
)

__all__ = [
    "ContractError",
    "RobotUnderTest",
    "TrackerUnderTest",
    "check_robot",
    "check_tracker",
    "robot_checks",
    "tracker_checks",
]


class ContractError(AssertionError):
    """A driver broke the driver contract."""


def _expect(cond: bool, message: str) -> None:
    if not cond:
        raise ContractError(message)


@dataclass(frozen=True)
class _DriverUnderTest:
    """A driver to check.

    Attributes
    ----------
    name : str
        Label used in messages.
    make : callable
        Returns a new, unconnected driver each call.
    """

    name: str
    make: Callable[[], Any]


@dataclass(frozen=True)
class RobotUnderTest(_DriverUnderTest):
    """A robot driver to check (``name`` and ``make`` as for every driver under test).

    Attributes
    ----------
    actual_joints : callable, optional
        The device's true joint angles (radians), if the test can observe them.
    messages_received : callable, optional
        Number of messages the device has received so far (for "nothing was sent").
    connect_timeout, move_timeout : float
        Seconds.
    joint_tol_rad : float
        Agreement expected between a target and the joints reported after the move.
    slow_moves : callable, optional
        Returns a context manager inside which the device's moves take long enough (about a
        second or more across the joint range at 10 % speed) for the stop checks to stop one
        midway; None when the device always moves that slowly.
    """

    actual_joints: Callable[[], Sequence[float]] | None = None
    messages_received: Callable[[], int] | None = None
    connect_timeout: float = 5.0
    move_timeout: float = 10.0
    joint_tol_rad: float = 1e-3
    slow_moves: Callable[[], contextlib.AbstractContextManager[Any]] | None = None


@dataclass(frozen=True)
class TrackerUnderTest(_DriverUnderTest):
    """A tracker driver to check (``name`` and ``make`` as for every driver under test).

    Attributes
    ----------
    true_position : callable, optional
        The reflector's true position (metres, tracker frame), if observable.
    position_tol_m : float
        Agreement expected with ``true_position``.
    """

    true_position: Callable[[], Sequence[float]] | None = None
    position_tol_m: float = 2e-4
    connect_timeout: float = 5.0
    measure_timeout: float = 5.0


@contextlib.asynccontextmanager
async def _connected(make: Callable[[], Any], timeout: float) -> AsyncIterator[Any]:
    driver = make()
    try:
        await driver.connect(timeout=timeout)
        yield driver
    finally:
        await driver.close()


# --- checks shared by both kinds -------------------------------------------------------------
def _check_declaration(driver: Any, name: str) -> None:
    cls = type(driver)
    _expect(isinstance(getattr(cls, "kind", None), str), f"{name}: class lacks a str `kind`")
    options = getattr(cls, "Options", None)
    _expect(
        isinstance(options, type) and issubclass(options, BaseModel),
        f"{name}: class lacks a pydantic `Options` model",
    )
    assert isinstance(options, type) and issubclass(options, BaseModel)  # _expect raised if not
    config = options.model_config
    _expect(config.get("extra") == "forbid", f"{name}: Options must forbid unknown keys")
    _expect(bool(config.get("frozen")), f"{name}: Options must be frozen")


async def _check_lifecycle(make: Callable[[], Any], name: str, timeout: float) -> None:
    driver = make()
    try:
        await driver.close()  # close before connect: a no-op
        await driver.close()
        await driver.connect(timeout=timeout)
        await driver.close()
        await driver.close()  # idempotent
        await driver.connect(timeout=timeout)  # reconnect after close
    except RobocalError as err:
        raise ContractError(f"{name}: lifecycle failed: {err!r}") from err
    finally:
        await driver.close()


# --- robot checks ----------------------------------------------------------------------------
async def check_robot_declaration(rut: RobotUnderTest) -> None:
    """Driver class declares ``kind`` and a frozen, strict ``Options``; satisfies RobotDriver."""
    driver = rut.make()
    try:
        _check_declaration(driver, rut.name)
        _expect(isinstance(driver, RobotDriver), f"{rut.name}: not a RobotDriver")
        _expect(driver.dof == len(driver.joint_limits_rad), f"{rut.name}: dof != len(limits)")
    finally:
        await driver.close()


async def check_robot_no_io_before_connect(rut: RobotUnderTest) -> None:
    """Check building a driver sends nothing and operations before ``connect`` fail."""
    before = rut.messages_received() if rut.messages_received else None
    driver = rut.make()
    try:
        if before is not None and rut.messages_received is not None:
            _expect(rut.messages_received() == before, f"{rut.name}: __init__ talked to device")
        mid = [0.5 * (lo + hi) for lo, hi in driver.joint_limits_rad]
        for call in (driver.read_joints, lambda: driver.move_to(mid, speed_pct=10, timeout=1.0)):
            try:
                await call()
            except ConnectFailed:
                continue
            raise ContractError(f"{rut.name}: operation before connect did not raise")
    finally:
        await driver.close()


async def check_robot_lifecycle(rut: RobotUnderTest) -> None:
    """``close`` is idempotent and safe before ``connect``; reconnecting works."""
    await _check_lifecycle(rut.make, rut.name, rut.connect_timeout)


def _check_joint_reading(
    r: Any, dof: int, limits: Sequence[tuple[float, float]], name: str
) -> None:
    _expect(isinstance(r, JointReading), f"{name}: expected JointReading, got {type(r)}")
    _expect(len(r.q_rad) == dof, f"{name}: {len(r.q_rad)} joints, dof is {dof}")
    _expect(all(isinstance(v, float) and math.isfinite(v) for v in r.q_rad), f"{name}: bad q")
    for v, (lo, hi) in zip(r.q_rad, limits, strict=True):
        # Radians, not degrees: a reading must lie (nearly) within the limits.
        _expect(lo - 0.01 <= v <= hi + 0.01, f"{name}: joint {v} outside limits (units?)")
    _expect(abs(r.timestamp - time.time()) < 60.0, f"{name}: timestamp not time.time()")


async def check_robot_read_joints(rut: RobotUnderTest) -> None:
    """``read_joints`` returns ``dof`` finite radians within limits, stamped with time.time()."""
    async with _connected(rut.make, rut.connect_timeout) as robot:
        r = await robot.read_joints()
        _check_joint_reading(r, robot.dof, robot.joint_limits_rad, rut.name)


def _target(limits: Sequence[tuple[float, float]], frac: float) -> list[float]:
    return [lo + frac * (hi - lo) for lo, hi in limits]


async def check_robot_move_to(rut: RobotUnderTest) -> None:
    """``move_to`` reaches the target, waits in position and reports the actual joints."""
    async with _connected(rut.make, rut.connect_timeout) as robot:
        for frac in (0.45, 0.6):
            target = _target(robot.joint_limits_rad, frac)
            r = await robot.move_to(target, speed_pct=20, timeout=rut.move_timeout)
            _check_joint_reading(r, robot.dof, robot.joint_limits_rad, rut.name)
            err = max(abs(a - b) for a, b in zip(r.q_rad, target, strict=True))
            _expect(err < rut.joint_tol_rad, f"{rut.name}: reached {r.q_rad}, target {target}")
            again = await robot.read_joints()
            err = max(abs(a - b) for a, b in zip(again.q_rad, r.q_rad, strict=True))
            _expect(err < 1e-6, f"{rut.name}: read_joints disagrees with move_to's result")
            if rut.actual_joints is not None:
                true = rut.actual_joints()
                err = max(abs(a - b) for a, b in zip(r.q_rad, true, strict=True))
                _expect(err < 1e-6, f"{rut.name}: reported joints are not the device's actual")


async def check_robot_refuses_out_of_limits(rut: RobotUnderTest) -> None:
    """Targets outside limits, non-finite or of the wrong length raise LimitViolation; none sent."""
    async with _connected(rut.make, rut.connect_timeout) as robot:
        before = await robot.read_joints()
        sent = rut.messages_received() if rut.messages_received else None
        limits = robot.joint_limits_rad
        mid = _target(limits, 0.5)
        bad_targets = []
        for j in range(robot.dof):
            high = list(mid)
            high[j] = limits[j][1] + 0.05
            low = list(mid)
            low[j] = limits[j][0] - 0.05
            bad_targets += [high, low]
        bad_targets += [[*mid[:-1], math.nan], mid[:-1], [*mid, 0.0]]
        for bad in bad_targets:
            try:
                await robot.move_to(bad, speed_pct=10, timeout=rut.move_timeout)
            except LimitViolation:
                continue
            raise ContractError(f"{rut.name}: target {bad} was not refused")
        if sent is not None and rut.messages_received is not None:
            _expect(rut.messages_received() == sent, f"{rut.name}: a refused target was sent")
        after = await robot.read_joints()
        moved = max(abs(a - b) for a, b in zip(after.q_rad, before.q_rad, strict=True))
        _expect(moved < 1e-9, f"{rut.name}: robot moved on a refused target")


def _max_diff(a: Sequence[float], b: Sequence[float]) -> float:
    return max(abs(x - y) for x, y in zip(a, b, strict=True))


async def _settled(robot: Any, name: str, *, polls: int = 4, gap_s: float = 0.02) -> JointReading:
    """Read the joints ``polls`` times ``gap_s`` apart; they must not change (halted)."""
    first = await robot.read_joints()
    for _ in range(polls):
        await asyncio.sleep(gap_s)
        again = await robot.read_joints()
        moved = _max_diff(again.q_rad, first.q_rad)
        _expect(moved < 1e-6, f"{name}: joints still change after stop ({moved:.3g} rad)")
    return first


async def check_robot_stop_idle(rut: RobotUnderTest) -> None:
    """``stop`` is declared, a no-op before connect and after close, idempotent when idle,
    leaves the robot where it is, and a move after it works."""
    driver = rut.make()
    try:
        _expect(isinstance(driver, Stoppable), f"{rut.name}: no stop() (not Stoppable)")
        await driver.stop()  # before connect: allowed, nothing to do
        await driver.connect(timeout=rut.connect_timeout)
        before = await driver.read_joints()
        await driver.stop()
        await driver.stop()  # idempotent
        after = await _settled(driver, rut.name)
        _expect(
            _max_diff(after.q_rad, before.q_rad) < 1e-6, f"{rut.name}: stop while idle moved it"
        )
        target = _target(driver.joint_limits_rad, 0.55)
        r = await driver.move_to(target, speed_pct=20, timeout=rut.move_timeout)
        err = _max_diff(r.q_rad, target)
        _expect(err < rut.joint_tol_rad, f"{rut.name}: move after stop missed by {err:.3g} rad")
        await driver.stop()  # after a completed move
        await driver.close()
        await driver.stop()  # after close: allowed, nothing to do
    except RobocalError as err:
        raise ContractError(f"{rut.name}: stop failed: {err!r}") from err
    finally:
        await driver.close()


async def check_robot_stop_mid_move(rut: RobotUnderTest) -> None:
    """``stop`` during a move halts the robot short of the target where it is (joints stop
    changing), the waiting ``move_to`` raises MotionStopped, a second stop is harmless and
    the next move reaches its target."""
    async with _connected(rut.make, rut.connect_timeout) as robot:
        limits = robot.joint_limits_rad
        start_target = _target(limits, 0.7)
        await robot.move_to(start_target, speed_pct=50, timeout=rut.move_timeout)
        start = (await robot.read_joints()).q_rad
        far = _target(limits, 0.3)
        slow = rut.slow_moves() if rut.slow_moves is not None else contextlib.nullcontext()
        with slow:
            move = asyncio.create_task(robot.move_to(far, speed_pct=10, timeout=rut.move_timeout))
            try:
                deadline = time.monotonic() + rut.move_timeout
                while not move.done() and time.monotonic() < deadline:
                    await asyncio.sleep(0.01)
                    if rut.actual_joints is None:
                        break  # cannot watch the device: stop it shortly after the start
                    if _max_diff(rut.actual_joints(), start) > 1e-3:
                        break
                _expect(not move.done(), f"{rut.name}: move ended before stop; too fast to test")
                await robot.stop()
                try:
                    async with asyncio.timeout(rut.move_timeout):
                        await move
                except MotionStopped:
                    pass
                else:
                    raise ContractError(f"{rut.name}: move_to did not raise MotionStopped")
            finally:
                if not move.done():
                    move.cancel()
                    with contextlib.suppress(BaseException):
                        await move
            halted = await _settled(robot, rut.name)
            _expect(
                _max_diff(halted.q_rad, far) > rut.joint_tol_rad,
                f"{rut.name}: the robot reached the target despite stop",
            )
            for j, (q, a, b) in enumerate(zip(halted.q_rad, start, far, strict=True)):
                lo, hi = min(a, b) - rut.joint_tol_rad, max(a, b) + rut.joint_tol_rad
                _expect(lo <= q <= hi, f"{rut.name}: J{j + 1} halted off the path at {q}")
            if rut.actual_joints is not None:
                true = rut.actual_joints()
                _expect(
                    _max_diff(halted.q_rad, true) < 1e-6,
                    f"{rut.name}: reported halt position is not the device's",
                )
            await robot.stop()
        target = _target(limits, 0.5)
        r = await robot.move_to(target, speed_pct=50, timeout=rut.move_timeout)
        err = _max_diff(r.q_rad, target)
        _expect(err < rut.joint_tol_rad, f"{rut.name}: move after stop missed by {err:.3g} rad")


def _sample_table(kind: str, dof: int,
                  limits: Sequence[tuple[float, float]] = ()) -> CompensationTable:
    common: dict[str, Any] = {
        "model_id": "contract",
        "robot": "contract-robot",
        "valid_range_deg": [(-90.0, 90.0)] * dof,
        "predicted_residual_mm": 0.05,
        "created": "2026-01-01T00:00:00Z",
    }
    if kind == "frames":
        return CompensationTable(
            kind="frames",
            frames=FramesPayload(
                base=Frame(x=1523.25, y=-210.5, z=-880.125, w=0.015, p=-0.02, r=179.5),
                tool=Frame(x=0.5, y=-0.25, z=105.75, w=0.0, p=0.0, r=0.0),
            ),
            **common,
        ).sealed()
    if kind == "targets":
        # rows inside the limits, with gaps in the indices (slots that are not consecutive)
        rows = [
            TargetRow(index=i, q_deg=[math.degrees(lo + f * (hi - lo)) for lo, hi in limits],
                      status="ok", model_residual_mm=0.01 * i)
            for i, f in ((0, 0.41), (1, 0.5), (4, 0.5625))
        ]
        return CompensationTable(kind="targets", targets=rows, **common).sealed()
    return CompensationTable(
        kind="joint",
        joints=[
            JointCorrection(
                joint=j + 1,
                q_deg=[-90.0, 0.0, 90.0],
                dq_deg=[0.01 * j, -0.005, 0.0125],
                interpolation_error_bound_deg=0.001,
            )
            for j in range(dof)
        ],
        **common,
    ).sealed()


async def check_robot_compensation(rut: RobotUnderTest) -> None:
    """Check a CompensationSink stores a table and reads the same content back."""
    robot: RobotDriver
    async with _connected(rut.make, rut.connect_timeout) as robot:
        if not isinstance(robot, CompensationSink):
            return
        supported = getattr(robot, "supported_compensation", frozenset({"frames"}))
        kind = next(k for k in ("frames", "joint", "targets") if k in supported)
        table = _sample_table(kind, robot.dof, robot.joint_limits_rad)
        await robot.write_compensation(table)
        back = await robot.read_compensation()
        _expect(isinstance(back, CompensationTable), f"{rut.name}: nothing read back")
        diff = table_diff(table, back, tol=1e-3)
        _expect(not diff, f"{rut.name}: table read back differs: {diff[:3]}")


async def check_robot_controller_calibration(rut: RobotUnderTest) -> None:
    """Check a ControllerCalibrationReadable reads the same fingerprint twice, a hash of JSON
    facts, and says True/False/None about absolute accuracy."""
    robot: RobotDriver
    async with _connected(rut.make, rut.connect_timeout) as robot:
        if not isinstance(robot, ControllerCalibrationReadable):
            return
        first = await robot.controller_calibration()
        second = await robot.controller_calibration()
        _expect(isinstance(first, ControllerCalibration),
                f"{rut.name}: expected ControllerCalibration, got {type(first)}")
        _expect(first.fingerprint == second.fingerprint,
                f"{rut.name}: fingerprint differs between two reads of an unchanged controller")
        again = ControllerCalibration(first.source, first.to_json()["facts"],
                                      first.absolute_accuracy)
        _expect(again.fingerprint == first.fingerprint,
                f"{rut.name}: facts are not plain JSON (the fingerprint does not survive)")
        _expect(first.absolute_accuracy in (True, False, None),
                f"{rut.name}: absolute_accuracy must be True, False or None")


# --- tracker checks --------------------------------------------------------------------------
async def check_tracker_declaration(tut: TrackerUnderTest) -> None:
    """Driver class declares ``kind`` and a frozen, strict ``Options``; satisfies TrackerDriver."""
    driver = tut.make()
    try:
        _check_declaration(driver, tut.name)
        _expect(isinstance(driver, TrackerDriver), f"{tut.name}: not a TrackerDriver")
    finally:
        await driver.close()


async def check_tracker_no_io_before_connect(tut: TrackerUnderTest) -> None:
    """``measure`` before ``connect`` raises ConnectFailed."""
    driver = tut.make()
    try:
        await driver.measure(samples=1, timeout=1.0)
    except ConnectFailed:
        return
    finally:
        await driver.close()
    raise ContractError(f"{tut.name}: measure before connect did not raise")


async def check_tracker_lifecycle(tut: TrackerUnderTest) -> None:
    """``close`` is idempotent and safe before ``connect``; reconnecting works."""
    await _check_lifecycle(tut.make, tut.name, tut.connect_timeout)


async def check_tracker_measure(tut: TrackerUnderTest) -> None:
    """``measure`` returns an SI TrackerReading with ``n`` samples and the point id echoed."""
    async with _connected(tut.make, tut.connect_timeout) as tracker:
        for samples, pid in ((1, None), (7, "P0001")):
            r = await tracker.measure(samples=samples, timeout=tut.measure_timeout, point_id=pid)
            _expect(isinstance(r, TrackerReading), f"{tut.name}: expected TrackerReading")
            _expect(len(r.position_m) == 3, f"{tut.name}: position is not 3-D")
            _expect(all(math.isfinite(v) for v in r.position_m), f"{tut.name}: non-finite")
            # Metres: a tracker works from ~1 m to ~80 m; mm would show up as 1000s.
            dist = math.dist(r.position_m, (0.0, 0.0, 0.0))
            _expect(0.05 < dist < 100.0, f"{tut.name}: |p| = {dist}, not metres?")
            if r.std_m is not None:
                _expect(all(0.0 <= s < 1e-3 for s in r.std_m), f"{tut.name}: std_m not metres")
            _expect(r.n == samples, f"{tut.name}: n = {r.n}, asked {samples}")
            _expect(r.status == "ok", f"{tut.name}: status {r.status}")
            _expect(r.point_id == pid, f"{tut.name}: point_id {r.point_id!r}, asked {pid!r}")
            _expect(abs(r.timestamp - time.time()) < 60.0, f"{tut.name}: timestamp scale")
            if tut.true_position is not None:
                err = math.dist(r.position_m, tuple(tut.true_position()))
                _expect(err < tut.position_tol_m, f"{tut.name}: {err * 1e3:.3f} mm from truth")


async def check_tracker_rejects_bad_samples(tut: TrackerUnderTest) -> None:
    """Check ``samples < 1`` raises a ValueError-like robocal error before any exchange."""
    async with _connected(tut.make, tut.connect_timeout) as tracker:
        try:
            await tracker.measure(samples=0, timeout=tut.measure_timeout)
        except (ValueError, DriverError) as err:
            _expect(isinstance(err, RobocalError), f"{tut.name}: {type(err)} not a robocal error")
            return
        raise ContractError(f"{tut.name}: samples=0 accepted")


RobotCheck = Callable[[RobotUnderTest], Awaitable[None]]
TrackerCheck = Callable[[TrackerUnderTest], Awaitable[None]]


def robot_checks() -> list[RobotCheck]:
    """Return every robot contract check (each an ``async def check(rut)``)."""
    return [
        check_robot_declaration,
        check_robot_no_io_before_connect,
        check_robot_lifecycle,
        check_robot_read_joints,
        check_robot_move_to,
        check_robot_refuses_out_of_limits,
        check_robot_stop_idle,
        check_robot_stop_mid_move,
        check_robot_compensation,
        check_robot_controller_calibration,
    ]


def tracker_checks() -> list[TrackerCheck]:
    """Return every tracker contract check (each an ``async def check(tut)``)."""
    return [
        check_tracker_declaration,
        check_tracker_no_io_before_connect,
        check_tracker_lifecycle,
        check_tracker_measure,
        check_tracker_rejects_bad_samples,
    ]


async def check_robot(rut: RobotUnderTest) -> None:
    """Run every robot check; raise ContractError on the first broken rule."""
    for check in robot_checks():
        await check(rut)


async def check_tracker(tut: TrackerUnderTest) -> None:
    """Run every tracker check; raise ContractError on the first broken rule."""
    for check in tracker_checks():
        await check(tut)
