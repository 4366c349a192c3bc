"""FANUC RMI driver against the RMI simulator and against scripted misbehaving controllers."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math

import pytest

from robocal.compensation import CompensationTable, Frame, FramesPayload, TargetRow
from robocal.drivers.fanuc_rmi import FanucRmiRobot
from robocal.drivers.sim import FanucRmiSimulator, FanucSimOptions, FaultConfig
from robocal.errors import (
    CompensationError,
    ConnectFailed,
    DriverTimeout,
    LimitViolation,
    MotionRejected,
    OperationError,
    VerificationMismatch,
)
from robocal.protocols import fanuc_rmi as rmi
from tests._waiting import eventually


@contextlib.asynccontextmanager
async def rmi_sim(world, options=None, faults=None):
    sim = FanucRmiSimulator(world, options or FanucSimOptions(time_scale=0.0), faults)
    await sim.start()
    try:
        yield sim
    finally:
        await sim.stop()


def robot_for(sim, world, **extra) -> FanucRmiRobot:
    limits = extra.pop("joint_limits_deg", world.joint_limits_deg)
    return FanucRmiRobot(
        {
            "connect_port": sim.connect_port,
            "joint_limits_deg": limits,
            "reply_timeout_s": 2.0,
            **extra,
        }
    )


def instructions(sim):
    return [p for p in sim.received if "Instruction" in p]


async def test_session_setup_and_consecutive_sequence_ids(world):
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        assert robot.controller_version == (7, 0) and robot.session_port == sim.main_port
        assert [next(iter(p.values())) for p in sim.received[:5]] == [
            "FRC_GetStatus",
            "FRC_Reset",
            "FRC_GetStatus",
            "FRC_Initialize",
            "FRC_GetStatus",
        ]
        for i in range(12):
            q = [0.01 * i] * world.dof
            reading = await robot.move_to(q, speed_pct=50, timeout=5)
            assert max(abs(a - b) for a, b in zip(reading.q_rad, q, strict=True)) < 1e-4
            assert reading.q_rad == pytest.approx(tuple(world.q_actual_rad), abs=1e-12)
        seqs = [p["SequenceID"] for p in instructions(sim)]
        assert seqs == list(range(1, 13))
        motion = instructions(sim)[0]
        assert (
            motion["TermType"] == "FINE"
            and motion["SpeedType"] == "Percent"
            and motion["Speed"] == 50
        )
        assert motion["JointAngle"]["J1"] == 0.0
        await robot.close()
        await robot.close()
        names = [next(iter(p.values())) for p in sim.received[-2:]]
        assert names == ["FRC_Abort", "FRC_Disconnect"]


async def test_refuses_major_version_below_6(world):
    async with rmi_sim(world, FanucSimOptions(major_version=5, time_scale=0.0)) as sim:
        robot = robot_for(sim, world)
        with pytest.raises(ConnectFailed, match=r"MajorVersion 5.*actual") as info:
            await robot.connect(timeout=5)
        assert info.value.kind == "fanuc_rmi"
        assert sim.sessions == 0  # never went on to the session port
        assert robot.state == "closed"
        with pytest.raises(Exception, match="greater than or equal to 6"):
            FanucRmiRobot({"joint_limits_deg": [(-1, 1)], "min_major_version": 5})


async def test_rmi_move_selected_gives_a_hint(world):
    async with rmi_sim(world, FanucSimOptions(rmi_move_selected=True, time_scale=0.0)) as sim:
        with pytest.raises(ConnectFailed, match="RMI_MOVE"):
            await robot_for(sim, world).connect(timeout=5)


async def test_connection_refused(world):
    async with rmi_sim(world) as sim:
        port = sim.connect_port
    robot = FanucRmiRobot({"connect_port": port, "joint_limits_deg": world.joint_limits_deg})
    with pytest.raises(ConnectFailed, match="cannot connect"):
        await robot.connect(timeout=2)
    await robot.close()


async def test_limit_violation_sends_nothing(world):
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        before = len(sim.received)
        with pytest.raises(LimitViolation):
            await robot.move_to([math.radians(500)] + [0.0] * (world.dof - 1), timeout=5)
        assert len(sim.received) == before
        await robot.close()


async def test_at_most_eight_in_flight(world):
    async with rmi_sim(world, FanucSimOptions(time_scale=0.3, min_motion_s=0.1)) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        targets = [[0.001 * i] * world.dof for i in range(12)]
        await asyncio.gather(*(robot.move_to(q, timeout=10) for q in targets))
        assert sim.max_in_flight == 8
        assert [p["SequenceID"] for p in instructions(sim)] == list(range(1, 13))
        await robot.close()


async def test_sequence_gap_hold_is_recovered(world):
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        await robot.move_to([0.1] * world.dof, timeout=5)
        robot._next_seq = 7  # simulate a lost instruction: the controller expects 2
        reading = await robot.move_to([0.2] * world.dof, timeout=5)
        assert reading.q_rad[0] == pytest.approx(0.2, abs=1e-4)
        sent = [p["SequenceID"] for p in instructions(sim)]
        assert sent == [1, 7, 2]
        names = [next(iter(p.values())) for p in sim.received]
        assert "FRC_Reset" in names and not sim.hold
        await robot.close()


async def test_system_fault_then_recovery(world):
    # The driver's limits are wider than the controller's: the controller faults.
    wide = [(lo - 20, hi + 20) for lo, hi in world.joint_limits_deg]
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world, joint_limits_deg=wide)
        await robot.connect(timeout=5)
        beyond = [math.radians(world.joint_limits_deg[0][1] + 10)] + [0.0] * (world.dof - 1)
        with pytest.raises(MotionRejected, match="system fault") as info:
            await robot.move_to(beyond, timeout=5)
        assert info.value.code == "FRC_SystemFault"
        assert sim.hold
        assert "Limit error" in await robot.read_error()
        reading = await robot.move_to([0.05] * world.dof, timeout=5)
        assert reading.q_rad[0] == pytest.approx(0.05, abs=1e-4)
        await robot.close()


async def test_injected_alarm_is_motion_rejected(world):
    async with rmi_sim(world, faults=FaultConfig(alarm_rate=1.0)) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        with pytest.raises(MotionRejected):
            await robot.move_to([0.1] * world.dof, timeout=5)
        await robot.close()


async def test_garbage_lines_are_skipped(world):
    async with rmi_sim(world, faults=FaultConfig(garbage_rate=0.5, seed=2)) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        for i in range(20):
            await robot.move_to([0.01 * i] * world.dof, timeout=5)
        assert robot.bad_packets > 0
        assert sim.faults.counts["garbage"] == robot.bad_packets
        await robot.close()


async def test_dropped_connection_raises_connect_failed_and_reconnect_works(world):
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        sim.faults.config = FaultConfig(drop_rate=1.0)
        with pytest.raises(ConnectFailed, match="lost"):
            await robot.move_to([0.1] * world.dof, timeout=5)
        with pytest.raises(ConnectFailed):
            await robot.read_joints()
        await robot.close()
        sim.faults.config = FaultConfig()
        await robot.connect(timeout=5)
        await robot.move_to([0.1] * world.dof, timeout=5)
        await robot.close()


async def test_slow_reply_times_out(world):
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world, reply_timeout_s=0.1)
        await robot.connect(timeout=5)
        sim.faults.config = FaultConfig(slow_rate=1.0, slow_s=0.3)
        with pytest.raises(DriverTimeout):
            await robot.read_joints()
        await robot.close()


async def test_motion_timeout(world):
    async with rmi_sim(world, FanucSimOptions(time_scale=1.0, min_motion_s=5.0)) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        with pytest.raises(DriverTimeout, match="SequenceID 1"):
            await robot.move_to([0.1] * world.dof, timeout=0.1)
        await robot.close()


async def test_idle_terminate(world):
    async with rmi_sim(world, FanucSimOptions(time_scale=0.0, idle_timeout_s=0.25)) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        # the controller ends a session idle for 0.25 s with FRC_Terminate
        await eventually(lambda: robot._lost is not None, what="FRC_Terminate received")
        with pytest.raises(ConnectFailed, match="terminated"):
            await robot.read_joints()
        await robot.close()


def frames_table() -> CompensationTable:
    return CompensationTable(
        kind="frames",
        model_id="m1",
        robot="lrmate",
        valid_range_deg=[(-170.0, 170.0)] * 6,
        predicted_residual_mm=0.04,
        frames=FramesPayload(
            base=Frame(x=1500.125, y=-20.5, z=-400.25, w=0.01, p=-0.02, r=178.5),
            tool=Frame(x=0.25, y=0.5, z=120.75, w=0.0, p=0.0, r=0.0),
        ),
    ).sealed()


def targets_table(rows) -> CompensationTable:
    return CompensationTable(
        kind="targets",
        model_id="m1",
        robot="lrmate",
        valid_range_deg=[(-170.0, 170.0)] * 6,
        predicted_residual_mm=0.04,
        targets=rows,
    ).sealed()


async def test_compensation_frames_and_targets(world):
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world, uframe_number=3, utool_number=2, pr_base=50)
        await robot.connect(timeout=5)
        assert await robot.read_compensation() is None
        table = frames_table()
        await robot.write_compensation(table)
        assert sim.uframes[3] == {
            "X": 1500.125,
            "Y": -20.5,
            "Z": -400.25,
            "W": 0.01,
            "P": -0.02,
            "R": 178.5,
        }
        assert sim.utools[2]["Z"] == 120.75
        assert await robot.read_compensation() == table
        rows = [
            TargetRow(index=0, q_deg=[1, 2, 3, 4, 5, 6], status="ok", model_residual_mm=0.01),
            TargetRow(
                index=4, q_deg=[0, 0, 0, 0, 0, 0], status="unreachable", model_residual_mm=9.0
            ),
            TargetRow(
                index=7, q_deg=[-10, 20, -30, 40, -50, 60.125], status="ok", model_residual_mm=0.02
            ),
        ]
        table = targets_table(rows)
        await robot.write_compensation(table)
        assert sorted(sim.position_registers) == [50, 51, 64, 65]
        assert sim.position_registers[65]["Position"]["Z"] == 60.125
        back = await robot.read_compensation()
        assert back == table
        await robot.close()


async def test_compensation_refusals(world):
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world, pr_count=5)
        await robot.connect(timeout=5)
        before = len(sim.received)
        bad_limits = targets_table(
            [
                TargetRow(index=0, q_deg=[0, 0, 0, 0, 0, 0], status="ok", model_residual_mm=0.0),
                TargetRow(index=1, q_deg=[400, 0, 0, 0, 0, 0], status="ok", model_residual_mm=0.0),
            ]
        )
        with pytest.raises(LimitViolation):
            await robot.write_compensation(bad_limits)
        too_far = targets_table(
            [TargetRow(index=5, q_deg=[0] * 6, status="ok", model_residual_mm=0.0)]
        )
        with pytest.raises(CompensationError, match="PR"):
            await robot.write_compensation(too_far)
        assert len(sim.received) == before  # nothing written
        joint = CompensationTable(
            kind="joint",
            model_id="m",
            robot="r",
            valid_range_deg=[],
            predicted_residual_mm=0,
            joints=[],
        )
        with pytest.raises(CompensationError, match="frames"):
            await robot.write_compensation(joint)
        await robot.close()


async def test_verification_mismatch(world, monkeypatch):
    async with rmi_sim(world) as sim:
        robot = robot_for(sim, world)
        await robot.connect(timeout=5)
        real = sim._frame_cmd

        def lossy(req, key, store, bad, count):
            reply = real(req, key, store, bad, count)
            if key == "ToolNumber" and "Frame" in reply:
                reply["Frame"] = {**reply["Frame"], "Z": reply["Frame"]["Z"] + 0.5}
            return reply

        monkeypatch.setattr(sim, "_frame_cmd", lossy)
        with pytest.raises(VerificationMismatch) as info:
            await robot.write_compensation(frames_table())
        assert any("tool" in d for d in info.value.diff)
        await robot.close()


# --- scripted, misbehaving controllers ------------------------------------------------------------
@contextlib.asynccontextmanager
async def scripted_controller(script):
    """A fake controller: a proper connect port, then ``script(reader, writer)`` on the session."""
    tasks = []

    async def session(reader, writer):
        tasks.append(asyncio.current_task())
        try:
            await script(reader, writer)
        finally:
            writer.close()

    main = await asyncio.start_server(session, "127.0.0.1", 0)
    main_port = main.sockets[0].getsockname()[1]

    async def connect(reader, writer):
        await reader.readline()
        reply = {
            "Communication": "FRC_Connect",
            "ErrorID": 0,
            "PortNumber": main_port,
            "MajorVersion": 6,
        }
        writer.write(json.dumps(reply).encode() + b"\r\n")
        await writer.drain()
        writer.close()

    conn = await asyncio.start_server(connect, "127.0.0.1", 0)
    try:
        yield conn.sockets[0].getsockname()[1]
    finally:
        for server in (main, conn):
            server.close()
        for t in tasks:
            t.cancel()
        for server in (main, conn):
            await server.wait_closed()


def reply_for(line: bytes, **extra) -> bytes:
    packet = json.loads(line)
    category = next(iter(packet))
    out = {category: packet[category], "ErrorID": 0, **extra}
    if "SequenceID" in packet:
        out["SequenceID"] = packet["SequenceID"]
    return json.dumps(out).encode() + b"\r\n"


async def answer_rest(reader, writer):
    """Answer every further packet with ErrorID 0 (so close() is quick)."""
    while line := await reader.readline():
        with contextlib.suppress(ValueError):
            writer.write(reply_for(line))
            await writer.drain()


async def good_setup(reader, writer):
    """Answer the setup (GetStatus, Reset, GetStatus, Initialize, GetStatus) properly."""
    for _ in range(5):
        writer.write(reply_for(await reader.readline()))
    await writer.drain()


async def test_malformed_replies_are_skipped_not_fatal():
    async def script(reader, writer):
        await good_setup(reader, writer)
        line = await reader.readline()  # the motion
        for junk in (
            b"{not json\r\n",
            b'{"ErrorID":0}\r\n',
            b"\xff\xfe\x00\r\n",
            b"x" * 9000 + b"\r\n",
            b'{"Instruction":"FRC_JointMotionJRep","ErrorID":0,"SequenceID":99}\r\n',
            b'{"Command":"FRC_Bogus","ErrorID":0}\r\n',
        ):
            writer.write(junk)
        writer.write(reply_for(line))
        angles = {f"J{i}": 1.0 for i in range(1, 10)}
        writer.write(reply_for(await reader.readline(), JointAngle=angles))
        await writer.drain()
        await answer_rest(reader, writer)

    async with scripted_controller(script) as port:
        robot = FanucRmiRobot(
            {"connect_port": port, "joint_limits_deg": [(-10, 10)] * 6, "reply_timeout_s": 2}
        )
        await robot.connect(timeout=5)
        reading = await robot.move_to([0.0] * 6, timeout=5)
        assert reading.q_rad == pytest.approx((math.radians(1.0),) * 6)
        assert robot.bad_packets == 4
        await robot.close()


async def test_wrong_sequence_id_reply_leads_to_timeout_not_crash():
    async def script(reader, writer):
        await good_setup(reader, writer)
        line = json.loads(await reader.readline())
        writer.write(
            json.dumps({"Instruction": line["Instruction"], "ErrorID": 0, "SequenceID": 5}).encode()
            + b"\r\n"
        )
        await writer.drain()
        await answer_rest(reader, writer)

    async with scripted_controller(script) as port:
        robot = FanucRmiRobot({"connect_port": port, "joint_limits_deg": [(-10, 10)] * 6})
        await robot.connect(timeout=5)
        with pytest.raises(DriverTimeout):
            await robot.move_to([0.0] * 6, timeout=0.3)
        await robot.close()


async def test_garbled_joint_angles_raise_protocol_error():
    async def script(reader, writer):
        await good_setup(reader, writer)
        writer.write(reply_for(await reader.readline(), JointAngle={"J1": "x"}))
        await writer.drain()
        await answer_rest(reader, writer)

    async with scripted_controller(script) as port:
        robot = FanucRmiRobot({"connect_port": port, "joint_limits_deg": [(-10, 10)] * 6})
        await robot.connect(timeout=5)
        from robocal.errors import UnexpectedReply

        with pytest.raises(UnexpectedReply):
            await robot.read_joints()
        await robot.close()


async def test_unknown_command_reply_is_an_operation_error():
    async def script(reader, writer):
        await good_setup(reader, writer)
        await reader.readline()
        writer.write(b'{"Command":"Unknown","ErrorID":2556950}\r\n')
        await writer.drain()
        await answer_rest(reader, writer)

    async with scripted_controller(script) as port:
        robot = FanucRmiRobot({"connect_port": port, "joint_limits_deg": [(-10, 10)] * 6})
        await robot.connect(timeout=5)
        with pytest.raises(OperationError, match="RMIT-022"):
            await robot.read_joints()
        await robot.close()


async def test_connect_reply_without_port_or_garbage_only():
    async def connect_script(reader, writer):
        await reader.readline()
        writer.write(
            b"garbage\r\n"
            + json.dumps({"Communication": "FRC_Connect", "ErrorID": rmi.rmit(26)}).encode()
            + b"\r\n"
        )
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(connect_script, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        robot = FanucRmiRobot({"connect_port": port, "joint_limits_deg": [(-10, 10)] * 6})
        with pytest.raises(ConnectFailed, match="RMIT-026"):
            await robot.connect(timeout=3)
    finally:
        server.close()
        await server.wait_closed()
