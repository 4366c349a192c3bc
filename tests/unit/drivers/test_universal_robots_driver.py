"""The Universal Robots driver against the UR simulator: power-up, refusals, faults,
compensation as installation variables, and the kinematics fingerprint."""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator

import pytest

from robocal.compensation import CompensationTable, TargetRow
from robocal.drivers import load_robot_driver, table_diff
from robocal.drivers.sim import FaultConfig, SimCell, SimWorld, UrSimOptions, UrSimulator
from robocal.drivers.universal_robots import UniversalRobotsRobot
from robocal.errors import CompensationError, ConnectFailed, MotionRejected
from tests._waiting import eventually

pytestmark = pytest.mark.timeout(30)


@contextlib.asynccontextmanager
async def ur_cell(**options: object) -> AsyncIterator[tuple[SimCell, UrSimulator]]:
    opts = UrSimOptions(**{"time_scale": 0.0, **options})  # type: ignore[arg-type]
    cell = SimCell(world=SimWorld.create("ur10", seed=4), fanuc=False, modbus=False, ltp=False,
                   ur=opts)
    async with cell:
        assert cell.ur_sim is not None
        yield cell, cell.ur_sim


def robot(cell: SimCell, **extra: object) -> UniversalRobotsRobot:
    driver = load_robot_driver("universal_robots",
                               {**cell.robot_options("universal_robots"), **extra})
    assert isinstance(driver, UniversalRobotsRobot)
    return driver


def _targets(rows: list[list[float]]) -> CompensationTable:
    return CompensationTable(
        kind="targets", model_id="m1", robot="UR10", valid_range_deg=[(-360.0, 360.0)] * 6,
        predicted_residual_mm=0.02,
        targets=[TargetRow(index=i, q_deg=q, status="ok", model_residual_mm=0.01)
                 for i, q in enumerate(rows)],
    ).sealed()


async def test_connect_powers_on_and_releases_the_brakes():
    async with ur_cell(time_scale=0.001) as (cell, sim):
        assert sim.robot_mode == 3  # POWER_OFF
        r = robot(cell)
        try:
            await r.connect(timeout=5)
            assert sim.robot_mode == 7  # RUNNING
            log = sim.dashboard_log
            assert log.index("power on") < log.index("brake release")
            assert r.controller_version == (5, 12, 2, 1101534)
        finally:
            await r.close()


async def test_connect_refuses_local_mode_and_powered_off_without_power_on():
    async with ur_cell(remote_control=False) as (cell, _):
        r = robot(cell)
        with pytest.raises(ConnectFailed, match="local mode"):
            await r.connect(timeout=5)
        await r.close()
    async with ur_cell() as (cell, sim):
        r = robot(cell, power_on=False)
        with pytest.raises(ConnectFailed, match="POWER_OFF"):
            await r.connect(timeout=5)
        await r.close()
        assert "power on" not in sim.dashboard_log


async def test_protective_stop_rejects_the_move_and_the_next_until_unlocked():
    async with ur_cell(start_powered=True) as (cell, sim):
        r = robot(cell)
        await r.connect(timeout=5)
        try:
            sim.faults.config = FaultConfig(alarm_rate=1.0)
            with pytest.raises(MotionRejected, match="PROTECTIVE_STOP"):
                await r.move_to([0.1] * 6, speed_pct=20, timeout=5)
            assert sim.runtime_errors == []  # the controller just stopped the program
            await r.stop()  # allowed after a motion fault: the arm is halted already
            sim.faults.config = FaultConfig()
            await r._next_state(1.0)
            with pytest.raises(MotionRejected, match="PROTECTIVE_STOP"):
                await r.move_to([0.1] * 6, speed_pct=20, timeout=5)
            assert (await r.dashboard("unlock protective stop")).startswith("Protective stop")
            await r._next_state(1.0)
            await r._next_state(1.0)
            reached = await r.move_to([0.1] * 6, speed_pct=20, timeout=5)
            assert max(abs(a - 0.1) for a in reached.q_rad) < 1e-3
        finally:
            await r.close()


async def test_targets_are_installation_variables_read_back_and_restored():
    async with ur_cell(start_powered=True) as (cell, sim):
        r = robot(cell)
        await r.connect(timeout=5)
        try:
            table = _targets([[10.0, -80.0, 70.0, -20.0, 90.0, 0.5],
                              [12.5, -85.0, 72.0, -21.0, 91.0, 1.5]])
            before = await r.snapshot_compensation(table)
            assert before.items["var:rc_wp_1"] == [0.0] * 6
            await r.write_compensation(table)
            assert sim.variables["rc_wp_1"] == pytest.approx(
                [math.radians(v) for v in table.targets[1].q_deg], abs=1e-15)  # type: ignore[index]
            back = await r.read_compensation()
            assert table_diff(table, back, tol=1e-9) == []
            await r.restore_snapshot(before)
            assert sim.variables["rc_wp_1"] == [0.0] * 6
            assert await r.read_compensation() is None
        finally:
            await r.close()


async def test_undeclared_variables_fail_with_a_clear_error():
    async with ur_cell(start_powered=True, declared_waypoints=1) as (cell, _):
        r = robot(cell)
        await r.connect(timeout=5)
        try:
            table = _targets([[0.0] * 6, [1.0] * 6])
            with pytest.raises(CompensationError, match="declared"):
                await r.snapshot_compensation(table)
        finally:
            await r.close()


async def test_kinematics_fingerprint_follows_the_controller_calibration():
    async with ur_cell(start_powered=True) as (cell, sim):
        r = robot(cell)
        await r.connect(timeout=5)
        try:
            first = await r.controller_calibration()
            k = sim.kinematics()
            assert first.facts["dh_a_m"] == list(k.dh_a)
            assert first.facts["checksums"] == k.fingerprint()
            assert first.absolute_accuracy is False
            sim.set_kinematics(k.dh_theta, [a + 1e-4 for a in k.dh_a], k.dh_d, k.dh_alpha)
            # read again in the same session: the next kinematics info shows the change
            second = await r.controller_calibration()
        finally:
            await r.close()
        assert second.fingerprint != first.fingerprint
        assert second.facts["checksums"] == sim.kinematics().fingerprint()


async def test_a_program_stopped_from_the_dashboard_fails_the_move():
    async with ur_cell(start_powered=True, time_scale=1.0) as (cell, sim):
        r = robot(cell)
        await r.connect(timeout=5)
        try:
            move = asyncio.create_task(r.move_to([2.0] * 6, speed_pct=5, timeout=20))
            await eventually(lambda: cell.world.moving, 5, what="moving")
            await r._next_state(1.0)  # the driver has seen the program playing
            assert await r.dashboard("stop") == "Stopped"
            with pytest.raises(MotionRejected, match="stopped before it finished"):
                async with asyncio.timeout(5):
                    await move
            assert not cell.world.moving
            assert sim.runtime_errors == []
        finally:
            await r.close()
