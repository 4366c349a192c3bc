"""Modbus PLC driver against the pymodbus-based PLC simulator."""

from __future__ import annotations

import asyncio
import contextlib
import math

import pytest

from robocal._core.clock import SYSTEM_CLOCK
from robocal.compensation import CompensationTable, Frame, FramesPayload, JointCorrection, TargetRow
from robocal.drivers.modbus_plc import ModbusPlcRobot
from robocal.drivers.sim import FaultConfig, ModbusPlcSimulator, ModbusSimOptions
from robocal.errors import (
    CompensationError,
    ConnectFailed,
    DriverTimeout,
    LimitViolation,
    MotionRejected,
    OperationError,
    ProtocolError,
    VerificationMismatch,
)
from robocal.protocols import modbus as mb
from tests._clock import ManualClock
from tests._waiting import eventually


@contextlib.asynccontextmanager
async def plc(world, options=None, faults=None, clock=None):
    sim = ModbusPlcSimulator(
        world, options or ModbusSimOptions(time_scale=0.0), faults, clock=clock or SYSTEM_CLOCK
    )
    await sim.start()
    try:
        yield sim
    finally:
        await sim.stop()


def robot_for(sim, world, clock=None, **extra) -> ModbusPlcRobot:
    opts = {
        "port": sim.port,
        "joint_limits_deg": world.joint_limits_deg,
        "register_map": sim.map.model_dump(),
        "poll_interval_s": 0.001,
        **extra,
    }
    return ModbusPlcRobot(opts, clock=clock or SYSTEM_CLOCK)


@pytest.mark.parametrize(
    "register_map",
    [
        mb.RegisterMap(),
        mb.RegisterMap(word_order="little", status_area="holding", status_offset=5000),
    ],
    ids=["default", "hr-only-little-endian"],
)
async def test_handshake_moves_and_reads(world, register_map):
    async with plc(world, ModbusSimOptions(time_scale=0.0, register_map=register_map)) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        for i in range(1, 6):
            q = [0.02 * i] * world.dof
            reading = await robot.move_to(q, speed_pct=30, timeout=5)
            # FLOAT32 on the wire: a few micro-radians of rounding at most.
            assert reading.q_rad == pytest.approx(tuple(world.q_actual_rad), abs=1e-6)
        assert [c for c, _ in sim.commands] == [mb.Cmd.MOVE_JOINT] * 5
        assert [s for _, s in sim.commands] == [1, 2, 3, 4, 5]
        # CMD and CMD_SEQ arrive together in one FC16 write of two registers at CMD.
        cmd_writes = [w for w in sim.writes if w[1] == register_map.cmd]
        assert cmd_writes and all(w == (16, register_map.cmd, 2) for w in cmd_writes)
        assert robot.last_status.status == mb.Status.DONE
        again = await robot.read_joints()
        assert again.q_rad == pytest.approx(reading.q_rad, abs=1e-12)
        await robot.close()


async def test_sequence_continues_after_plc_ack_and_wraps(world):
    async with plc(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        robot._seq = 0xFFFE
        await robot.read_joints()
        await robot.read_joints()
        assert [s for _, s in sim.commands][-2:] == [0xFFFF, 1]
        await robot.close()
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        await robot.read_joints()
        assert sim.commands[-1][1] == 2  # continued from the PLC's ACK_SEQ
        await robot.close()


async def test_limits_checked_by_driver_and_by_plc(world):
    async with plc(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        n = len(sim.writes)
        with pytest.raises(LimitViolation):
            await robot.move_to([10.0] * world.dof, timeout=5)
        assert len(sim.writes) == n
        await robot.close()
        wide = [(lo - 30, hi + 30) for lo, hi in world.joint_limits_deg]
        robot = robot_for(sim, world, joint_limits_deg=wide)
        await robot.connect(timeout=5)
        with pytest.raises(LimitViolation, match="ERROR_CODE 10"):
            await robot.move_to(
                [math.radians(world.joint_limits_deg[0][1] + 10)] + [0.0] * (world.dof - 1),
                timeout=5,
            )
        await robot.close()


async def test_alarm_and_timeout(world):
    async with plc(world, faults=FaultConfig(alarm_rate=1.0)) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        with pytest.raises(MotionRejected) as info:
            await robot.move_to([0.1] * world.dof, timeout=5)
        assert info.value.code == mb.PlcError.MOTION_FAULT
        await robot.close()
    async with plc(world, ModbusSimOptions(time_scale=1.0, min_motion_s=2.0)) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        with pytest.raises(DriverTimeout, match="ACK_SEQ"):
            await robot.move_to([0.1] * world.dof, timeout=0.1)
        await robot.close()


def heartbeat_writes(sim):
    return [w for w in sim.writes if w[1] == sim.map.client_heartbeat]


async def test_client_heartbeat_written(world):
    clock = ManualClock()
    async with plc(world) as sim:
        robot = robot_for(sim, world, clock, heartbeat_period_s=0.02, heartbeat_timeout_s=1.0)
        await robot.connect(timeout=5)
        for n in range(1, 5):
            # One write per period: the n-th, then the heartbeat sleeps until time moves on.
            await eventually(
                lambda n=n: clock.sleepers == 1 and len(heartbeat_writes(sim)) == n,
                what=f"write {n}",
            )
            clock.advance(0.02)
        await eventually(lambda: len(heartbeat_writes(sim)) == 5)
        assert all(w[0] == 6 for w in heartbeat_writes(sim))
        await robot.close()
        assert robot._heartbeat_task is None and clock.sleepers == 0


async def test_close_ends_heartbeat_even_when_its_cancellation_is_lost(world):
    """Python 3.11's wait_for (inside pymodbus) drops a cancel that meets the reply."""
    async with plc(world) as sim:
        robot = robot_for(sim, world, heartbeat_period_s=0.0005, heartbeat_timeout_s=1.0)
        await robot.connect(timeout=5)
        for i in range(200):
            task = robot._heartbeat_task
            await asyncio.sleep(0.0001 * (i % 5))
            await robot._stop_heartbeat()
            assert task.done()
            robot._heartbeat_stop = asyncio.Event()
            robot._heartbeat_task = asyncio.create_task(robot._heartbeat())
        await robot.close()
        assert robot._heartbeat_task is None and task.done()


async def test_stale_plc_heartbeat_faults_driver(world):
    clock = ManualClock()
    async with plc(world, ModbusSimOptions(time_scale=0.0, heartbeat_stalled=True)) as sim:
        robot = robot_for(sim, world, clock, heartbeat_period_s=0.02, heartbeat_timeout_s=0.1)
        await robot.connect(timeout=5)
        await eventually(lambda: clock.sleepers == 1)
        clock.advance(0.09)
        await robot.read_joints()  # unchanged for less than the timeout: fine
        clock.advance(0.02)
        with pytest.raises(OperationError, match="heartbeat"):
            await robot.read_joints()
        await robot.close()


async def test_plc_latches_when_client_heartbeat_stops(world):
    plc_clock, robot_clock = ManualClock(), ManualClock()
    opts = ModbusSimOptions(time_scale=0.0, plc_heartbeat_hz=50, client_heartbeat_timeout_s=0.3)
    async with plc(world, opts, clock=plc_clock) as sim:
        robot = robot_for(
            sim, world, robot_clock, heartbeat_period_s=0.02, heartbeat_timeout_s=1.0
        )
        await robot.connect(timeout=5)
        await eventually(lambda: len(heartbeat_writes(sim)) == 1 and robot_clock.sleepers == 1)
        plc_clock.advance(0.25)  # within the timeout
        await eventually(lambda: plc_clock.sleepers == 1)
        assert not sim.latched
        await robot.read_joints()
        await robot._stop_heartbeat()  # the client "hangs"
        plc_clock.advance(0.1)  # 0.35 s since the last client heartbeat
        await eventually(lambda: sim.latched)
        with pytest.raises(OperationError, match="HEARTBEAT_LOST"):
            await robot.read_joints()
        await robot.reset()
        await robot.read_joints()
        await robot.close()


async def test_connection_lost(world):
    sim = ModbusPlcSimulator(world, ModbusSimOptions(time_scale=0.0))
    await sim.start()
    robot = robot_for(sim, world, request_timeout_s=0.5)
    await robot.connect(timeout=5)
    await sim.stop()
    with pytest.raises((ConnectFailed, DriverTimeout)):
        await robot.read_joints()
    await robot.close()
    with pytest.raises(ConnectFailed):
        await robot.connect(timeout=1)


async def test_map_version_checked(world):
    async with plc(world) as sim:
        robot = robot_for(sim, world, map_version=2)
        with pytest.raises(ConnectFailed, match="MAP_VERSION 1"):
            await robot.connect(timeout=5)


def tables():
    common = dict(
        model_id="m", robot="r", valid_range_deg=[(-90.0, 90.0)] * 6, predicted_residual_mm=0.05
    )
    yield CompensationTable(
        kind="joint",
        joints=[
            JointCorrection(
                joint=j + 1,
                q_deg=[-90.0, -30.0, 30.0, 90.0],
                dq_deg=[0.1 / 3, -0.002 * j, 0.0, 1e-5],
                interpolation_error_bound_deg=0.0001,
            )
            for j in range(6)
        ],
        **common,
    ).sealed()
    yield CompensationTable(
        kind="targets",
        targets=[
            TargetRow(
                index=i,
                q_deg=[i * 1.1, -2.2, 3.3, 0.0, 45.0, -90.0],
                status="ok",
                model_residual_mm=0.01,
            )
            for i in range(40)
        ]
        + [TargetRow(index=40, q_deg=[999.0] * 6, status="out-of-limits", model_residual_mm=5.0)],
        **common,
    ).sealed()
    yield CompensationTable(
        kind="frames",
        frames=FramesPayload(
            base=Frame(x=1500.1, y=2, z=3, w=0.1, p=0.2, r=179.9),
            tool=Frame(x=0, y=0, z=100.3, w=0, p=0, r=0),
        ),
        **common,
    ).sealed()


@pytest.mark.parametrize("table", list(tables()), ids=lambda t: t.kind)
async def test_compensation_round_trip(world, table):
    async with plc(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        assert await robot.read_compensation() is None
        await robot.write_compensation(table)
        assert sim.applied_table is not None
        back = await robot.read_compensation()
        assert back == table
        back.verify()
        await robot.close()


async def test_float32_tables(world):
    table = next(tables())
    async with plc(world) as sim:
        robot = robot_for(sim, world, table_dtype="float32")
        await robot.connect(timeout=5)
        await robot.write_compensation(table)
        back = await robot.read_compensation()
        assert back.joints[0].dq_deg[0] == pytest.approx(0.1 / 3, rel=1e-7)
        assert back.joints[0].dq_deg[0] != 0.1 / 3
        back.verify()  # resealed as stored
        await robot.close()


async def test_compensation_refusals(world):
    async with plc(world) as sim:
        small = {**sim.map.model_dump(), "table_words": 64}
        robot = robot_for(sim, world, register_map=small)
        await robot.connect(timeout=5)
        with pytest.raises(CompensationError, match="reserves 64"):
            await robot.write_compensation(next(tables()))
        await robot.close()

        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        bad_row = CompensationTable(
            kind="targets",
            model_id="m",
            robot="r",
            valid_range_deg=[],
            predicted_residual_mm=0.0,
            targets=[
                TargetRow(index=0, q_deg=[400.0] + [0.0] * 5, status="ok", model_residual_mm=0.0)
            ],
        )
        n = len(sim.writes)
        with pytest.raises(LimitViolation):
            await robot.write_compensation(bad_row)
        assert len(sim.writes) == n
        await robot.close()


def flip_table_word(sim, offset):
    sim._hr[sim.map.table + offset - sim._hr_start] ^= 1


async def test_corruption_in_plc_memory_is_caught_by_crc(world, monkeypatch):
    async with plc(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        real = sim._apply_table

        def corrupt_then_apply(seq):
            flip_table_word(sim, 30)
            real(seq)

        monkeypatch.setattr(sim, "_apply_table", corrupt_then_apply)
        with pytest.raises(VerificationMismatch, match="TABLE_CRC"):
            await robot.write_compensation(next(tables()))
        assert sim.applied_table is None
        await robot.close()


async def test_corruption_after_apply_is_caught_by_read_back(world, monkeypatch):
    async with plc(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        real = sim._apply_table

        def apply_then_corrupt(seq):
            real(seq)
            flip_table_word(sim, 20)

        monkeypatch.setattr(sim, "_apply_table", apply_then_corrupt)
        with pytest.raises(VerificationMismatch) as info:
            await robot.write_compensation(next(tables()))
        assert info.value.diff[0].startswith(f"register {sim.map.table + 20}")
        with pytest.raises(ProtocolError, match="CRC"):
            await robot.read_compensation()
        await robot.close()
