"""Every driver through the public contract suite: mocks, and real drivers against simulators."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Callable, Iterator

import pytest

from robocal.drivers import contracts, load_robot_driver, load_tracker_driver
from robocal.drivers.mock import MockRobot, MockTracker
from robocal.drivers.sim import (
    AbbSimOptions,
    EmsconSimOptions,
    FanucRmiSimulator,
    FanucSimOptions,
    FaultConfig,
    KukaKvpSimulator,
    KukaSimOptions,
    LtpSimOptions,
    ModbusPlcSimulator,
    ModbusSimOptions,
    SimCell,
    SimWorld,
    UrSimOptions,
    UrSimulator,
)
from robocal.drivers.sim.emscon import EmsconFaults


@contextlib.asynccontextmanager
async def robot_case(name: str) -> AsyncIterator[contracts.RobotUnderTest]:
    world = SimWorld.create("ur10" if name == "universal_robots" else "fanuc_lrmate200id", seed=5)
    if name == "mock":
        yield contracts.RobotUnderTest(
            "mock",
            # Moves that take time, so the stop checks can stop one midway.
            make=lambda: MockRobot({"move_time_s": 0.3}, world=world),
            actual_joints=lambda: world.q_actual_rad,
        )
        return
    if name.startswith("abb_rws"):
        async with abb_case(world, int(name[-1])) as rut:
            yield rut
        return
    cell = SimCell(
        world=world,
        fanuc=FanucSimOptions(time_scale=0.0) if name == "fanuc_rmi" else False,
        modbus=ModbusSimOptions(time_scale=0.0) if name == "modbus_plc" else False,
        ltp=False,
        kuka=KukaSimOptions(time_scale=0.0) if name == "kuka_kvp" else False,
        ur=UrSimOptions(time_scale=0.0) if name == "universal_robots" else False,
    )
    async with cell:
        options = cell.robot_options(name)  # type: ignore[arg-type]
        sim: FanucRmiSimulator | ModbusPlcSimulator | KukaKvpSimulator | UrSimulator
        if name == "fanuc_rmi":
            rmi_sim = sim = cell.fanuc_sim
            received: Callable[[], int] = lambda: len(rmi_sim.received)  # noqa: E731
        elif name == "kuka_kvp":
            kvp_sim = sim = cell.kuka_sim
            received = lambda: len(kvp_sim.requests)  # noqa: E731
        elif name == "universal_robots":
            ur_sim = sim = cell.ur_sim
            received = lambda: len(ur_sim.scripts)  # noqa: E731
        else:
            plc_sim = sim = cell.modbus_sim
            received = lambda: len(plc_sim.commands)  # noqa: E731

        @contextlib.contextmanager
        def real_time() -> Iterator[None]:
            fast = sim.options
            sim.options = fast.model_copy(update={"time_scale": 1.0})  # type: ignore[assignment]
            try:
                yield
            finally:
                sim.options = fast  # type: ignore[assignment]

        yield contracts.RobotUnderTest(
            name,
            make=lambda: load_robot_driver(name, options),
            actual_joints=lambda: world.q_actual_rad,
            messages_received=received,
            slow_moves=real_time,
        )


@contextlib.asynccontextmanager
async def abb_case(world: SimWorld, robotware: int) -> AsyncIterator[contracts.RobotUnderTest]:
    """The ABB driver against the RWS simulator of RobotWare ``robotware`` (6 or 7)."""
    cell = SimCell(world=world, fanuc=False, modbus=False, ltp=False,
                   abb=AbbSimOptions(robotware=robotware, time_scale=0.0))  # type: ignore[arg-type]
    async with cell:
        sim = cell.abb_sim
        assert sim is not None
        options = cell.robot_options("abb_rws")

        @contextlib.contextmanager
        def real_time() -> Iterator[None]:
            fast = sim.options
            sim.options = fast.model_copy(update={"time_scale": 1.0})
            try:
                yield
            finally:
                sim.options = fast

        yield contracts.RobotUnderTest(
            f"abb_rws{robotware}",
            make=lambda: load_robot_driver("abb_rws", options),
            actual_joints=lambda: world.q_actual_rad,
            messages_received=lambda: sim.requests,
            slow_moves=real_time,
        )


@contextlib.asynccontextmanager
async def tracker_case(name: str) -> AsyncIterator[contracts.TrackerUnderTest]:
    world = SimWorld.create(seed=6)
    world.move([0.2] * world.dof)
    sigma = max(world.measure(1).sigma_m)
    if name == "mock":
        yield contracts.TrackerUnderTest(
            "mock",
            make=lambda: MockTracker(world=world),
            true_position=world.true_reflector_position,
            position_tol_m=10 * sigma,
        )
        return
    if name.startswith("emscon"):
        async with emscon_cell(world, faulty=name == "emscon-faults") as cell:
            options = cell.emscon_options()
            yield contracts.TrackerUnderTest(
                name,
                make=lambda: load_tracker_driver("emscon", options),
                true_position=world.true_reflector_position,
                position_tol_m=10 * sigma,
            )
        return
    via = name.split("-", 1)[1]
    async with SimCell(
        world=world,
        fanuc=False,
        modbus=False,
        ltp=LtpSimOptions(time_scale=0.0),
        ltp_pty=(via == "pty"),
    ) as cell:
        options = cell.tracker_options(via)  # type: ignore[arg-type]
        yield contracts.TrackerUnderTest(
            name,
            make=lambda: load_tracker_driver("ltp", options),
            true_position=world.true_reflector_position,
            position_tol_m=10 * sigma,
        )


def emscon_cell(world: SimWorld, *, faulty: bool) -> SimCell:
    """The emScon simulator; ``faulty``: 10 % of measurements hit a broken beam or a busy
    server, and packets are split, merged or preceded by unknown types (the driver must
    recover from all of these by itself)."""
    if not faulty:
        return SimCell(world=world, fanuc=False, modbus=False, ltp=False,
                       emscon=EmsconSimOptions(time_scale=0.0))
    rates = EmsconFaults(busy_rate=0.05, split_rate=0.1, merge_rate=0.1,
                         unknown_type_rate=0.1, error_packet_rate=0.05)
    return SimCell(world=world, fanuc=False, modbus=False, ltp=False,
                   emscon=EmsconSimOptions(time_scale=0.0, faults=rates),
                   faults=FaultConfig(beam_break_rate=0.05, seed=9))


ROBOTS = ["mock", "fanuc_rmi", "modbus_plc", "universal_robots", "kuka_kvp", "abb_rws6",
          "abb_rws7"]
TRACKERS = ["mock", "ltp-tcp", "ltp-socket", "ltp-pty", "emscon", "emscon-faults"]


@pytest.mark.parametrize("check", contracts.robot_checks(), ids=lambda c: c.__name__)
@pytest.mark.parametrize("name", ROBOTS)
async def test_robot_contract(name, check):
    async with robot_case(name) as rut:
        await check(rut)


@pytest.mark.parametrize("check", contracts.tracker_checks(), ids=lambda c: c.__name__)
@pytest.mark.parametrize("name", TRACKERS)
async def test_tracker_contract(name, check):
    async with tracker_case(name) as tut:
        await check(tut)


async def test_contract_catches_a_broken_driver():
    """The suite is not vacuous: a driver that ignores its limits fails it."""
    world = SimWorld.create(seed=5)

    class Careless(MockRobot):
        def _check_target(self, q_rad):
            return tuple(q_rad)

    rut = contracts.RobotUnderTest("careless", make=lambda: Careless(world=world))
    with pytest.raises(contracts.ContractError, match="not refused"):
        await contracts.check_robot_refuses_out_of_limits(rut)


async def test_contract_catches_millimetres():
    world = SimWorld.create(seed=5)

    class Millimetres(MockTracker):
        async def measure(self, *, samples=10, timeout=10.0, point_id=None):
            r = await super().measure(samples=samples, timeout=timeout, point_id=point_id)
            import dataclasses

            return dataclasses.replace(r, position_m=tuple(v * 1000 for v in r.position_m))

    tut = contracts.TrackerUnderTest("mm", make=lambda: Millimetres(world=world))
    with pytest.raises(contracts.ContractError, match="not metres"):
        await contracts.check_tracker_measure(tut)


async def test_contract_catches_a_robot_that_does_not_halt():
    """A stop() that does not halt the motion fails the mid-move stop check."""
    world = SimWorld.create(seed=5)

    class Unstoppable(MockRobot):
        async def stop(self):
            return None

    rut = contracts.RobotUnderTest(
        "unstoppable",
        make=lambda: Unstoppable({"move_time_s": 0.3}, world=world),
        actual_joints=lambda: world.q_actual_rad,
    )
    with pytest.raises(contracts.ContractError, match="MotionStopped"):
        await contracts.check_robot_stop_mid_move(rut)


async def test_whole_suite_helpers():
    world = SimWorld.create(seed=5)
    await contracts.check_robot(
        contracts.RobotUnderTest("mock", make=lambda: MockRobot({"move_time_s": 0.3}, world=world))
    )
    await contracts.check_tracker(
        contracts.TrackerUnderTest("mock", make=lambda: MockTracker(world=world))
    )
