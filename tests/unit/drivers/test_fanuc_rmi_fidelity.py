"""The fanuc_rmi driver against controller behaviours seen on real equipment (issue 13, 1-7)."""

from __future__ import annotations

import contextlib
import math

import pytest

from robocal.compensation import CompensationTable, TargetRow
from robocal.drivers.fanuc_rmi import FanucRmiRobot
from robocal.drivers.sim import FanucRmiSimulator, FanucSimOptions
from robocal.drivers.sim.fanuc_rmi import normalise_wpr
from robocal.errors import ConnectFailed


@contextlib.asynccontextmanager
async def controller(world, **options):
    sim = FanucRmiSimulator(world, FanucSimOptions(time_scale=0.0, **options))
    await sim.start()
    try:
        yield sim
    finally:
        await sim.stop()


def robot_for(sim, world, **extra) -> FanucRmiRobot:
    return FanucRmiRobot(
        {
            "connect_port": sim.connect_port,
            "joint_limits_deg": extra.pop("joint_limits_deg", world.joint_limits_deg),
            "reply_timeout_s": 2.0,
            **extra,
        }
    )


async def test_numbers_without_a_leading_zero(world):
    """Item 1: ``-.0123`` used to be dropped as malformed, and read_joints timed out."""
    q = [math.radians(v) for v in (-0.0123, 0.0456, 0.5, -0.75, 0.001, -0.999)]
    world.move(q)
    async with controller(world, number_style="no_leading_zero") as sim:
        wire = sim.render({"Command": "FRC_ReadJointAngles", "ErrorID": 0, "A": -0.0123, "B": 0.5})
        assert wire == b'{"Command":"FRC_ReadJointAngles","ErrorID":0,"A":-.0123,"B": .5}'
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        reading = await robot.read_joints()
        assert reading.q_rad == pytest.approx(tuple(world.q_actual_rad), abs=1e-9)
        assert robot.bad_packets == 0
        await robot.close()


async def test_next_sequence_id_survives_initialize(world):
    """Item 2: a controller expecting ID 900 silently drops ID 1; the move used to time out."""
    async with controller(world, sequence_persists=True, initial_sequence_id=900) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        await robot.move_to([0.01] * world.dof, timeout=2)
        await robot.move_to([0.02] * world.dof, timeout=2)
        await robot.close()
        # A second session continues where the first left off.
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        await robot.move_to([0.03] * world.dof, timeout=2)
        await robot.close()
        seqs = [p["SequenceID"] for p in sim.received if "Instruction" in p]
        assert seqs == [900, 901, 902] and sim.dropped_stale == 0


async def test_plural_joint_angles_key(world):
    """Item 3: older firmware answers ``JointAngles``."""
    world.move([0.1] * world.dof)
    async with controller(world, joint_key="JointAngles") as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        reading = await robot.read_joints()
        assert reading.q_rad == pytest.approx(tuple(world.q_actual_rad), abs=1e-9)
        await robot.close()


async def test_resettable_alarm_at_connect(world):
    """Item 4: GetStatus, Reset, GetStatus, Initialize; the alarm used to give ConnectFailed."""
    async with controller(world, alarm_at_connect=True) as sim:
        assert sim.alarm_active
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        names = [next(iter(p.values())) for p in sim.received[:4]]
        assert names == ["FRC_GetStatus", "FRC_Reset", "FRC_GetStatus", "FRC_Initialize"]
        assert not sim.alarm_active
        await robot.move_to([0.01] * world.dof, timeout=2)
        await robot.close()


async def test_initialize_refusal_names_the_alarm(world):
    async with controller(world, servo_ready=False) as sim:
        with pytest.raises(ConnectFailed, match="RMIT-007 controller servo is off"):
            await robot_for(sim, world).connect(timeout=5)
    async with controller(world, tp_enabled=True) as sim:
        with pytest.raises(ConnectFailed, match="teach pendant is enabled"):
            await robot_for(sim, world).connect(timeout=5)


async def test_late_session_port_is_retried(world):
    """Item 5: the session port listens only a while after FRC_Connect."""
    async with controller(world, session_port_delay_s=0.15) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        await robot.move_to([0.01] * world.dof, timeout=2)
        await robot.close()
        late = robot_for(sim, world)
        with pytest.raises(ConnectFailed, match="not listening"):
            await late.connect(timeout=0.1)  # bounded: gives up within the connect timeout


def table(rows) -> CompensationTable:
    return CompensationTable(
        kind="targets",
        model_id="m1",
        robot="lrmate",
        valid_range_deg=[(-360.0, 360.0)] * 6,
        predicted_residual_mm=0.04,
        targets=rows,
    ).sealed()


def test_controller_keeps_wpr_canonical():
    """Why J4..J6 cannot live in W/P/R: those angles do not read back as written."""
    assert normalise_wpr(10.0, 20.0, 30.0) == pytest.approx((10.0, 20.0, 30.0))
    assert normalise_wpr(0.0, 0.0, 270.0) == pytest.approx((0.0, 0.0, -90.0))
    assert normalise_wpr(40.0, 100.0, 30.0) == pytest.approx((-140.0, 80.0, -150.0))


async def test_joint_targets_survive_the_position_registers(world):
    """Item 6: J5 = 100 and J6 = 270 degrees used to come back altered (W/P/R normalised)."""
    async with controller(world) as sim:
        limits = [(-360.0, 360.0)] * world.dof
        robot = robot_for(sim, world, joint_limits_deg=limits, pr_base=10, utool_number=3)
        await robot.connect(timeout=5)
        rows = [
            TargetRow(
                index=0, q_deg=[10, -20, 30, 200, 100, 270], status="ok", model_residual_mm=0
            ),
            TargetRow(
                index=2, q_deg=[-1, 2, -3, -190, -95, -300.5], status="ok", model_residual_mm=0
            ),
        ]
        t = table(rows)
        await robot.write_compensation(t)  # read back and compared inside
        assert await robot.read_compensation() == t
        assert sorted(sim.position_registers) == [10, 11, 14, 15]
        pr = sim.position_registers[11]
        assert pr["Position"] == {"X": 200.0, "Y": 100.0, "Z": 270.0, "W": 0.0, "P": 0.0, "R": 0.0}
        assert pr["Configuration"]["UToolNumber"] == 3 and pr["Configuration"]["UFrameNumber"] == 0
        await robot.close()
