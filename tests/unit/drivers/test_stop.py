"""Stopping motion: the world's halt, the simulators' FRC_Abort / ABORT, and every driver's stop().

The acceptance bound of the safe-motion issue: an abort during a move halts the simulated
robot within 0.2 s of the request, on both the FANUC RMI and the Modbus PLC simulator.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import time
from collections.abc import AsyncIterator, Sequence
from typing import Any

import numpy as np
import pytest

from robocal.drivers import Stoppable, _registry, load_robot_driver, require
from robocal.drivers._modbus_client import ModbusClient
from robocal.drivers.mock import MockRobot
from robocal.drivers.sim import (
    FanucRmiSimulator,
    FanucSimOptions,
    ModbusPlcSimulator,
    ModbusSimOptions,
    SimWorld,
)
from robocal.errors import DriverImportError, MotionStopped
from robocal.protocols import modbus as mb
from tests._waiting import eventually

HALT_BOUND_S = 0.2  # acceptance: halt within 0.2 s of the stop request


def _max_diff(a: Sequence[float], b: Sequence[float]) -> float:
    return float(np.max(np.abs(np.asarray(a, dtype=float) - np.asarray(b, dtype=float))))


async def _watch_halt(world: SimWorld, t_request: float, watch_s: float = 0.3) -> float:
    """Sample the world's joints every few ms for ``watch_s``; return when they last changed.

    The result is seconds after ``t_request`` of the last sample that differed from the
    one before it (0 when nothing changed after the request).
    """
    last = world.q_actual_rad
    last_change = t_request
    end = time.monotonic() + watch_s
    while time.monotonic() < end:
        await asyncio.sleep(0.002)
        q = world.q_actual_rad
        if _max_diff(q, last) > 0.0:
            last_change = time.monotonic()
            last = q
    return last_change - t_request


# --- the world ---------------------------------------------------------------------------------
def test_world_motion_sweeps_and_halt_freezes(world):
    start = world.q_actual_rad
    target = start + 0.5
    motion = world.start_motion(target, 10.0)
    assert world.moving
    t = time.monotonic()
    while time.monotonic() - t < 0.03:
        pass
    mid = world.q_actual_rad
    assert 0.0 < _max_diff(mid, start) < 0.5
    halted = world.halt()
    assert not world.moving and world.halts == 1 and world.last_halt_time is not None
    assert _max_diff(world.q_actual_rad, halted) == 0.0
    assert np.allclose(world.q_cmd_rad, halted)
    # the halted motion can no longer complete; a second halt changes nothing
    assert world.finish_motion(motion) is False
    assert _max_diff(world.q_actual_rad, halted) == 0.0
    world.halt()
    assert world.halts == 1
    # a later motion starts from the halted position and settles at its target
    m2 = world.start_motion(start, 0.0)
    assert world.finish_motion(m2) is True
    assert _max_diff(world.q_actual_rad, start) < 1e-3


# --- Modbus PLC simulator at the register level (issue 13 item 14) -----------------------------
@contextlib.asynccontextmanager
async def _plc(world: SimWorld, **options: Any) -> AsyncIterator[ModbusPlcSimulator]:
    sim = ModbusPlcSimulator(world, ModbusSimOptions(**options))
    await sim.start()
    try:
        yield sim
    finally:
        await sim.stop()


async def test_modbus_sim_abort_halts_the_move_and_keeps_ack_seq_monotonic(world):
    """J1 12 deg -> 32 deg, ABORT midway: J1 stays where it was, ACK_SEQ ends on the ABORT's."""
    q0 = [0.0] * world.dof
    q0[0] = math.radians(12.0)
    world.move(q0)
    async with _plc(world, time_scale=1.0, max_joint_speed_deg_s=40.0) as sim:
        m = sim.map
        client = ModbusClient("127.0.0.1", sim.port, device_id=m.device_id, timeout=2.0)
        await client.connect(timeout=5.0)
        s0, s1 = m.status_span()
        fields = m.status_fields()

        async def status() -> tuple[int, int, float]:
            words = await client.read_input(s0, s1 - s0)

            def field(name: str) -> list[int]:
                a, b = fields[name]
                return words[a + m.status_offset - s0 : b + m.status_offset - s0]

            j1 = mb.decode_f32(field("actual")[:2], m.word_order)[0]
            return field("ack_seq")[0], field("status")[0], j1

        try:
            target = [math.degrees(v) for v in q0] + [0.0] * (m.joints - world.dof)
            target[0] = 32.0
            await client.write_registers(m.target, mb.encode_f32(target, m.word_order))
            await client.write_registers(m.speed, [100])
            await client.write_registers(m.cmd, [int(mb.Cmd.MOVE_JOINT), 1])
            t_move = time.monotonic()  # 20 deg at 40 deg/s: 0.5 s of motion
            await eventually(lambda: math.degrees(world.q_actual_rad[0]) > 14.0)
            _, busy, j1_live = await status()
            assert busy == mb.Status.BUSY and 12.0 < j1_live < 32.0  # live joints while moving
            t_request = time.monotonic()
            await client.write_registers(m.cmd, [int(mb.Cmd.ABORT), 2])
            acks: list[int] = []
            j1s: list[float] = []
            # watch until well past the time the move would have ended
            while time.monotonic() < t_move + 0.8:
                ack, st, j1 = await status()
                acks.append(ack)
                if ack == 2:
                    assert st == mb.Status.DONE
                    j1s.append(j1)
                await asyncio.sleep(0.01)
        finally:
            await client.close()
        halt_after = (world.last_halt_time or math.inf) - t_request
        assert 0.0 <= halt_after < HALT_BOUND_S
        assert acks[-1] == 2 and 1 not in acks  # the aborted move is never acknowledged
        assert all(a <= b for a, b in itertools.pairwise(acks))  # never falls back
        assert sim.acks == [2]
        assert j1s and max(j1s) - min(j1s) < 1e-4  # halted: J1 no longer changes
        assert 14.0 < j1s[-1] < 30.0  # where it was, not the aborted 32 deg target
        assert math.degrees(world.q_actual_rad[0]) == pytest.approx(j1s[-1], abs=1e-4)


async def test_modbus_sim_abort_when_idle_and_while_latched_is_done(world):
    async with _plc(world, time_scale=0.0, client_heartbeat_timeout_s=0.05) as sim:
        m = sim.map
        client = ModbusClient("127.0.0.1", sim.port, device_id=m.device_id, timeout=2.0)
        await client.connect(timeout=5.0)
        try:
            await client.write_register(m.client_heartbeat, 7)  # then let it go stale
            await eventually(lambda: sim.latched)
            before = world.q_actual_rad
            await client.write_registers(m.cmd, [int(mb.Cmd.ABORT), 1])
            await eventually(lambda: sim.acks == [1])
            s0, s1 = m.status_span()
            words = await client.read_input(s0, s1 - s0)
            a, _ = m.status_fields()["status"]
            # ABORT is honoured even with HEARTBEAT_LOST latched
            assert words[a + m.status_offset - s0] == mb.Status.DONE
            assert _max_diff(world.q_actual_rad, before) == 0.0
        finally:
            await client.close()


# --- every driver's stop() against its simulator -----------------------------------------------
@contextlib.asynccontextmanager
async def _robot(kind: str, world: SimWorld) -> AsyncIterator[tuple[Any, Any]]:
    """A connected driver of ``kind`` whose moves run in real time, and its simulator."""
    if kind == "mock":
        robot = MockRobot({"move_time_s": 2.0}, world=world)
        await robot.connect(timeout=5)
        try:
            yield robot, None
        finally:
            await robot.close()
        return
    sim: FanucRmiSimulator | ModbusPlcSimulator
    if kind == "fanuc_rmi":
        sim = FanucRmiSimulator(world, FanucSimOptions(time_scale=1.0))
        await sim.start()
        options: dict[str, Any] = {"connect_port": sim.connect_port, "reply_timeout_s": 2.0}
    else:
        sim = ModbusPlcSimulator(world, ModbusSimOptions(time_scale=1.0))
        await sim.start()
        options = {"port": sim.port, "poll_interval_s": 0.002}
    robot = load_robot_driver(kind, {"joint_limits_deg": world.joint_limits_deg, **options})
    try:
        await robot.connect(timeout=5)
        yield robot, sim
    finally:
        await robot.close()
        await sim.stop()


KINDS = ["fanuc_rmi", "modbus_plc", "mock"]


@pytest.mark.parametrize("kind", KINDS)
async def test_stop_mid_move_halts_within_bound_and_next_move_works(kind, world):
    async with _robot(kind, world) as (robot, sim):
        require(robot, Stoppable)
        start = world.q_actual_rad
        far = [lo + 0.8 * (hi - lo) for lo, hi in world.joint_limits_rad]
        move = asyncio.create_task(robot.move_to(far, speed_pct=10, timeout=30))
        await eventually(lambda: _max_diff(world.q_actual_rad, start) > 0.01)
        t_request = time.monotonic()
        await robot.stop()
        t_confirmed = time.monotonic() - t_request
        with pytest.raises(MotionStopped):
            async with asyncio.timeout(5):
                await move
        last_change = await _watch_halt(world, t_request)
        halt_after = (world.last_halt_time or math.inf) - t_request
        assert 0.0 <= halt_after < HALT_BOUND_S
        assert last_change < HALT_BOUND_S  # observed from outside: nothing moves after
        assert t_confirmed < HALT_BOUND_S  # and stop() returned within the bound too
        halted = world.q_actual_rad
        assert _max_diff(halted, far) > 0.05  # short of the target
        reading = await robot.read_joints()
        assert _max_diff(reading.q_rad, halted) < 1e-5  # the driver reports the halt position
        # a later move works and reaches its target
        back = [lo + 0.45 * (hi - lo) for lo, hi in world.joint_limits_rad]
        if sim is not None:
            sim.options = sim.options.model_copy(update={"time_scale": 0.0})
        else:
            robot = MockRobot(world=world)
            await robot.connect(timeout=5)
        r = await robot.move_to(back, speed_pct=50, timeout=10)
        assert _max_diff(r.q_rad, back) < 1e-3
        if kind == "modbus_plc":
            assert isinstance(sim, ModbusPlcSimulator)
            seqs = [s for _, s in sim.commands]
            assert [c for c, _ in sim.commands] == [
                mb.Cmd.MOVE_JOINT,
                mb.Cmd.ABORT,
                mb.Cmd.READ_ACTUAL,
                mb.Cmd.MOVE_JOINT,
            ]
            assert seqs == sorted(seqs) and sim.acks == seqs[1:]  # the aborted move: no ACK
        if kind == "fanuc_rmi":
            assert isinstance(sim, FanucRmiSimulator)
            names = [
                p.get("Command") or p.get("Instruction") or p.get("Communication")
                for p in sim.received
            ]
            i = names.index("FRC_Abort")
            assert names[i : i + 3] == ["FRC_Abort", "FRC_Initialize", "FRC_GetStatus"]
            seqs = [p["SequenceID"] for p in sim.received if "Instruction" in p]
            assert seqs == [1, 1]  # RMI restarts at 1 after the re-initialisation


@pytest.mark.parametrize("kind", KINDS)
async def test_stop_is_idempotent_when_idle_and_a_no_op_when_not_connected(kind, world):
    async with _robot(kind, world) as (robot, _):
        before = world.q_actual_rad
        for _ in range(3):
            await robot.stop()
        assert _max_diff(world.q_actual_rad, before) == 0.0
        await robot.close()
        await robot.stop()  # after close: nothing to do, no error


async def test_fanuc_stop_cancels_a_move_not_yet_sent(world):
    """A move_to still waiting for the sequence lock when stop() runs is never sent."""
    async with _robot("fanuc_rmi", world) as (robot, sim):
        far = [lo + 0.8 * (hi - lo) for lo, hi in world.joint_limits_rad]
        async with robot._seq_lock:  # hold instructions back, as a running stop() does
            move = asyncio.create_task(robot.move_to(far, speed_pct=10, timeout=10))
            async with asyncio.timeout(5):  # until the move waits for the lock (no fixed sleep)
                while not robot._seq_lock._waiters:
                    await asyncio.sleep(0)
            robot._stop_gen += 1  # what stop() does under the lock
        with pytest.raises(MotionStopped):
            async with asyncio.timeout(5):
                await move
        assert not [p for p in sim.received if "Instruction" in p]


def test_a_robot_driver_without_stop_is_refused_by_name(monkeypatch):
    class NoStop(MockRobot):
        stop = None  # type: ignore[assignment]

    monkeypatch.setattr(_registry, "driver_class", lambda kind, role: NoStop)
    with pytest.raises(DriverImportError, match=r"missing: Stoppable"):
        load_robot_driver("no_stop", {})


async def test_fanuc_stop_continues_the_sequence_ids_a_controller_keeps(world):
    """Controllers that keep NextSequenceID across FRC_Initialize: the move after a stop
    carries the next ID (a restart at 1 would be dropped as stale)."""
    sim = FanucRmiSimulator(world, FanucSimOptions(time_scale=1.0, sequence_persists=True))
    await sim.start()
    robot = load_robot_driver(
        "fanuc_rmi",
        {"joint_limits_deg": world.joint_limits_deg, "connect_port": sim.connect_port},
    )
    try:
        await robot.connect(timeout=5)
        start = world.q_actual_rad
        far = [lo + 0.8 * (hi - lo) for lo, hi in world.joint_limits_rad]
        move = asyncio.create_task(robot.move_to(far, speed_pct=10, timeout=30))
        await eventually(lambda: _max_diff(world.q_actual_rad, start) > 0.01)
        await robot.stop()
        with pytest.raises(MotionStopped):
            await move
        sim.options = sim.options.model_copy(update={"time_scale": 0.0})
        back = [lo + 0.45 * (hi - lo) for lo, hi in world.joint_limits_rad]
        r = await robot.move_to(back, speed_pct=50, timeout=10)
        assert _max_diff(r.q_rad, back) < 1e-3
        seqs = [p["SequenceID"] for p in sim.received if "Instruction" in p]
        assert seqs[-2:] == [seqs[-2], seqs[-2] + 1]  # continued, not restarted at 1
    finally:
        await robot.close()
        await sim.stop()


async def test_modbus_close_during_a_move_sends_abort(world):
    """A PLC robot is never left moving on its own: close() with a move in flight (its
    move_to cancelled) writes ABORT, as RMI's disconnect aborts."""
    async with _robot("modbus_plc", world) as (robot, sim):
        start = world.q_actual_rad
        far = [lo + 0.8 * (hi - lo) for lo, hi in world.joint_limits_rad]
        move = asyncio.create_task(robot.move_to(far, speed_pct=10, timeout=30))
        await eventually(lambda: _max_diff(world.q_actual_rad, start) > 0.01)
        move.cancel()
        with pytest.raises(asyncio.CancelledError):
            await move
        assert world.moving  # the PLC moves on after the client gave up waiting
        await robot.close()
        assert not world.moving and world.halts == 1
        assert [c for c, _ in sim.commands] == [mb.Cmd.MOVE_JOINT, mb.Cmd.ABORT]
        # an idle close sends nothing
        await robot.connect(timeout=5)
        await robot.close()
        assert [c for c, _ in sim.commands] == [mb.Cmd.MOVE_JOINT, mb.Cmd.ABORT]


@pytest.mark.parametrize("kind", ["fanuc_rmi", "modbus_plc"])
async def test_a_stop_that_fails_on_close_is_logged_as_an_error(kind, world):
    """close() with a move in flight stops the robot; when the controller does not answer
    the stop in time, closing goes on but says so loudly (structlog error)."""
    from structlog.testing import capture_logs

    from robocal.drivers.sim.faults import FaultConfig

    sim: FanucRmiSimulator | ModbusPlcSimulator
    if kind == "fanuc_rmi":
        sim = FanucRmiSimulator(world, FanucSimOptions(time_scale=1.0))
        await sim.start()
        options: dict[str, Any] = {"connect_port": sim.connect_port, "reply_timeout_s": 2.0}
    else:
        sim = ModbusPlcSimulator(world, ModbusSimOptions(time_scale=1.0))
        await sim.start()
        options = {"port": sim.port, "poll_interval_s": 0.002, "request_timeout_s": 0.2}
    robot = load_robot_driver(kind, {"joint_limits_deg": world.joint_limits_deg, **options})
    try:
        await robot.connect(timeout=5)
        start = world.q_actual_rad
        far = [lo + 0.8 * (hi - lo) for lo, hi in world.joint_limits_rad]
        move = asyncio.create_task(robot.move_to(far, speed_pct=10, timeout=30))
        await eventually(lambda: _max_diff(world.q_actual_rad, start) > 0.01)
        move.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await move
        sim.faults.config = FaultConfig(slow_rate=1.0, slow_s=2.0)
        with capture_logs() as logs:
            async with asyncio.timeout(5):
                await robot.close()
        errors = [e for e in logs if e["log_level"] == "error"]
        assert errors and "may still be moving" in errors[0]["event"], logs
    finally:
        await robot.close()
        await sim.stop()
