"""The RMI simulator enforces the controller's rules (raw JSON client, no driver)."""

from __future__ import annotations

import asyncio
import contextlib
import json

from robocal.drivers.sim import FanucRmiSimulator, FanucSimOptions
from robocal.protocols import fanuc_rmi as rmi


class Raw:
    def __init__(self, reader, writer):
        self.reader, self.writer = reader, writer

    @classmethod
    async def open(cls, port):
        return cls(*await asyncio.open_connection("127.0.0.1", port))

    async def send(self, packet):
        self.writer.write(json.dumps(packet).encode() + b"\r\n")
        await self.writer.drain()

    async def recv(self, timeout=2.0):
        line = await asyncio.wait_for(self.reader.readline(), timeout)
        return json.loads(line) if line else None

    async def close(self):
        self.writer.close()
        with contextlib.suppress(Exception):
            await self.writer.wait_closed()


@contextlib.asynccontextmanager
async def session(world, **opts):
    sim = FanucRmiSimulator(world, FanucSimOptions(**opts))
    await sim.start()
    clients = []
    try:
        c = await Raw.open(sim.connect_port)
        await c.send({"Communication": "FRC_Connect"})
        reply = await c.recv()
        assert reply["PortNumber"] == sim.main_port and reply["MajorVersion"] == 7
        assert await c.recv() is None  # the controller closed the connect-port connection
        await c.close()
        main = await Raw.open(reply["PortNumber"])
        clients.append(main)
        yield sim, main
    finally:
        for c in clients:
            await c.close()
        await sim.stop()


def motion(seq, q=0.0):
    return rmi.joint_motion_jrep(seq, [q] * 6, speed_pct=100)


async def test_instructions_need_initialize_and_sequence_ids(world):
    async with session(world, time_scale=0.0) as (_sim, c):
        await c.send(motion(1))
        assert (await c.recv())["ErrorID"] == rmi.rmit(9)
        await c.send({"Command": "FRC_Initialize"})
        assert (await c.recv()) == {"Command": "FRC_Initialize", "ErrorID": 0, "GroupMask": 1}
        await c.send(motion(1))
        assert (await c.recv()) == {
            "Instruction": "FRC_JointMotionJRep",
            "ErrorID": 0,
            "SequenceID": 1,
        }
        await c.send(motion(3))  # gap
        assert (await c.recv())["ErrorID"] == rmi.rmit(29)
        await c.send(motion(2))  # HOLD until reset
        assert (await c.recv())["ErrorID"] == rmi.rmit(24)
        await c.send({"Command": "FRC_GetStatus"})
        status = await c.recv()
        assert status["NextSequenceID"] == 2 and status["RMIMotionStatus"] == 1
        await c.send({"Command": "FRC_Reset"})
        assert (await c.recv())["ErrorID"] == 0
        await c.send(motion(2))
        assert (await c.recv())["ErrorID"] == 0


async def test_ninth_instruction_in_flight_is_refused(world):
    async with session(world, time_scale=1.0, min_motion_s=0.2) as (sim, c):
        await c.send({"Command": "FRC_Initialize"})
        await c.recv()
        for seq in range(1, 10):
            await c.send(motion(seq, 0.001 * seq))
        first = await c.recv()
        assert first == {
            "Instruction": "FRC_JointMotionJRep",
            "ErrorID": rmi.rmit(28),
            "SequenceID": 9,
        }
        assert sim.max_in_flight == 8
        await c.send({"Command": "FRC_Abort"})


async def test_replies_on_completion_and_unknown_packets(world):
    async with session(world, time_scale=1.0, min_motion_s=0.05) as (_sim, c):
        await c.send({"Command": "FRC_Initialize"})
        await c.recv()
        await c.send(motion(1, 1.0))
        await c.send({"Command": "FRC_GetStatus"})
        assert (await c.recv())[
            "Command"
        ] == "FRC_GetStatus"  # command answered before the motion ends
        assert (await c.recv())["SequenceID"] == 1
        c.writer.write(b"{broken\r\n")
        await c.send({"ErrorID": 0, "Command": "FRC_GetStatus"})
        assert await c.recv() == {"Command": "Unknown", "ErrorID": rmi.rmit(22)}
        assert await c.recv() == {"Command": "Unknown", "ErrorID": rmi.rmit(22)}
        await c.send({"Command": "FRC_Nonsense"})
        assert (await c.recv())["ErrorID"] == rmi.rmit(13)
        await c.send({"Command": "FRC_SetOverRide", "Value": 150})
        assert (await c.recv())["ErrorID"] == rmi.rmit(5)


async def test_second_client_refused_and_session_port_needs_handshake(world):
    async with session(world, time_scale=0.0) as (sim, c):
        other = await Raw.open(sim.connect_port)
        await other.send({"Communication": "FRC_Connect"})
        assert (await other.recv())["ErrorID"] == rmi.rmit(26)
        await other.close()
        sneaky = await Raw.open(sim.main_port)
        assert await sneaky.recv() is None  # closed: no handshake pending
        await sneaky.close()
        await c.send({"Communication": "FRC_Connect"})
        assert (await c.recv())["ErrorID"] == rmi.rmit(26)
        await c.send({"Communication": "FRC_Disconnect"})
        assert await c.recv() == {"Communication": "FRC_Disconnect", "ErrorID": 0}


async def test_frames_and_registers_storage(world):
    async with session(world, time_scale=0.0) as (_sim, c):
        frame = rmi.frame_fields(1, 2, 3, 4, 5, 6)
        await c.send({"Command": "FRC_WriteUFrameData", "FrameNumber": 2, "Frame": frame})
        assert (await c.recv())["ErrorID"] == 0
        await c.send({"Command": "FRC_ReadUFrameData", "FrameNumber": 2})
        assert (await c.recv())["Frame"] == frame
        await c.send({"Command": "FRC_WriteUToolData", "ToolNumber": 11, "Frame": frame})
        assert (await c.recv())["ErrorID"] == rmi.rmit(2)
        await c.send(
            {"Command": "FRC_WritePositionRegister", "RegisterNumber": 5, "Position": frame}
        )
        assert (await c.recv())["ErrorID"] == rmi.rmit(23)  # no Configuration
        await c.send({"Command": "FRC_ReadPositionRegister", "RegisterNumber": 0})
        assert (await c.recv())["ErrorID"] == rmi.rmit(4)


async def test_cartesian_read_linear_moves_and_io(world):
    async with session(world, time_scale=0.0) as (sim, c):
        await c.send({"Command": "FRC_Initialize"})
        await c.recv()
        await c.send(motion(1, 10.0))
        assert (await c.recv())["ErrorID"] == 0
        await c.send({"Command": "FRC_ReadCartesianPosition", "Group": 1})
        reply = await c.recv()
        assert reply["ErrorID"] == 0 and reply["Configuration"]["UToolNumber"] == 1
        here = reply["Position"]
        assert here == sim.tcp_position(world.q_actual_rad, 0, 1)
        config = rmi.Configuration(utool_number=1)
        target = dict(here, Z=here["Z"] - 20.0)
        await c.send(rmi.linear_motion(2, target, config, speed_mm_s=100))
        assert (await c.recv()) == {"Instruction": "FRC_LinearMotion", "ErrorID": 0,
                                    "SequenceID": 2}
        reached = sim.tcp_position(world.q_cmd_rad, 0, 1)
        assert all(abs(reached[k] - target[k]) < 1e-6 for k in "XYZ")
        # SpeedType Percent belongs to joint motions
        await c.send({**rmi.linear_motion(3, target, config, speed_mm_s=100),
                      "SpeedType": "Percent"})
        assert (await c.recv())["ErrorID"] == rmi.rmit(30)
        # an unreachable point is a system fault (MOTN-018) and HOLD, not a reply
        far = dict(here, X=here["X"] + 5000.0)
        await c.send(rmi.linear_motion(4, far, config, speed_mm_s=100))
        assert (await c.recv()) == {"Communication": "FRC_SystemFault", "SequenceID": 4}
        assert sim.hold and "MOTN-018" in sim.last_alarm
        await c.send({"Command": "FRC_WriteDOUT", "PortNumber": 0, "PortValue": "ON"})
        assert (await c.recv())["ErrorID"] == rmi.rmit(38)
        await c.send({"Command": "FRC_WriteDOUT", "PortNumber": 2, "PortValue": "MAYBE"})
        assert (await c.recv())["ErrorID"] == rmi.rmit(21)
        await c.send({"Command": "FRC_ReadDIN", "PortNumber": 2})
        assert (await c.recv()) == {"Command": "FRC_ReadDIN", "ErrorID": 0, "PortNumber": 2,
                                    "PortValue": "OFF"}
