"""The KUKA simulator keeps KVP's and robocal_loop's rules (raw KVP client, no driver)."""

from __future__ import annotations

import asyncio
import contextlib
import math

import numpy as np

from robocal.drivers.sim import FaultConfig, KukaKvpSimulator, KukaSimOptions
from robocal.protocols import kuka_kvp as kvp
from tests._waiting import eventually


class Raw:
    """A bare KVP client."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer, self.msg_id = reader, writer, 100

    @classmethod
    async def open(cls, port: int) -> Raw:
        return cls(*await asyncio.open_connection("127.0.0.1", port))

    async def ask(self, name: str, value: str | None = None) -> kvp.Reply:
        self.msg_id += 1
        mode = kvp.MODE_READ if value is None else kvp.MODE_WRITE
        self.writer.write(kvp.encode_request(kvp.Request(self.msg_id, mode, name, value)))
        head = await asyncio.wait_for(self.reader.readexactly(4), 2)
        body = await asyncio.wait_for(self.reader.readexactly(int.from_bytes(head[2:], "big")), 2)
        reply = kvp.decode_reply(head + body)
        assert reply.msg_id == self.msg_id and reply.mode == mode
        return reply

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(Exception):
            await self.writer.wait_closed()


@contextlib.asynccontextmanager
async def served(world, faults=None, **options):
    sim = KukaKvpSimulator(world, KukaSimOptions(**options), faults)
    await sim.start()
    client = await Raw.open(sim.port)
    try:
        yield sim, client
    finally:
        await client.close()
        await sim.stop()


async def test_values_types_and_refusals(world):
    async with served(world, time_scale=0.0) as (_sim, c):
        r = await c.ask("RC_TARGET", "{A1 0.1, A3 -7}")  # partial: the others are kept
        assert r.ok and r.value.startswith("{E6AXIS: A1 0.1, A2 0.0, A3 -7.0,")
        assert (await c.ask("rc_target")).value == r.value  # KRL names ignore case
        # REALs are 32-bit: 170.1234567 reads back as the float32 nearest to it
        r = await c.ask("RC_TARGET", "{A2 170.1234567}")
        assert "A2 170.123459," in r.value
        assert not (await c.ask("RC_SPEED", "12.5")).ok  # not an INT
        assert (await c.ask("RC_SPEED")).value == "10"
        assert not (await c.ask("RC_TARGET", "{E6POS: X 1.0}")).ok
        assert not (await c.ask("RC_COMP[101]")).ok and not (await c.ask("RC_COMP")).ok
        assert not (await c.ask("$AXIS_ACT", "{A1 0.0}")).ok  # system variables: read-only
        assert not (await c.ask("RC_COMP_ID[]", '"' + "x" * 65 + '"')).ok
        assert not (await c.ask("NO_SUCH_VAR")).ok
        assert (await c.ask("$OV_PRO", "55")).value == "55"


async def test_a_bad_length_field_closes_the_connection(world):
    async with served(world) as (sim, c):
        c.writer.write(b"\x00\x01\x00\x01\x00")
        assert await asyncio.wait_for(c.reader.read(), 2) == b""
        assert sim.requests == []


async def test_command_written_right_after_a_stop_is_executed_not_swallowed(world):
    """The stop interrupt acknowledges what was commanded; a command written after it but
    before the loop resumed is still executed (robocal_loop keeps RC_RUN_SEQ for that)."""
    async with served(world, time_scale=1.0) as (sim, c):
        far = [lo + 0.2 * (hi - lo) for lo, hi in world.joint_limits_deg]
        await c.ask("RC_TARGET", kvp.format_e6axis(far))
        await c.ask("RC_SPEED", "1")
        await c.ask("RC_CMD_SEQ", "1")
        await eventually(lambda: world.moving, 2)
        assert sim.write("RC_STOP", "TRUE")[1]
        await asyncio.sleep(0)  # the interrupt runs; the loop has not resumed yet
        assert sim.read("RC_ACK_SEQ") == ("1", True) and sim.read("RC_STATUS") == ("4", True)
        near = [math.degrees(v) + 0.5 for v in world.q_actual_rad]
        sim.write("RC_TARGET", kvp.format_e6axis(near))
        sim.write("RC_SPEED", "100")
        sim.write("RC_CMD_SEQ", "2")
        await eventually(lambda: sim.read("RC_ACK_SEQ")[0] == "2", 5)
        assert sim.read("RC_STATUS") == ("2", True) and sim.moves == 2
        assert np.allclose(np.degrees(world.q_cmd_rad), near, atol=1e-4)


async def test_stop_right_after_a_command_halts_at_the_start(world):
    async with served(world, time_scale=1.0) as (sim, _c):
        start = world.q_actual_rad
        sim.write("RC_TARGET", kvp.format_e6axis([50.0] * world.dof))
        sim.write("RC_CMD_SEQ", "1")
        sim.write("RC_STOP", "TRUE")  # in the same turn as the command
        await eventually(lambda: sim.read("RC_STOP")[0] == "FALSE", 2)
        await asyncio.sleep(0)
        assert sim.read("RC_ACK_SEQ") == ("1", True) and sim.read("RC_STATUS") == ("4", True)
        assert not world.moving and np.max(np.abs(world.q_actual_rad - start)) < 1e-3


async def test_injected_drop_closes_the_connection(world):
    async with served(world, faults=FaultConfig(drop_rate=1.0)) as (sim, c):
        c.writer.write(kvp.encode_request(kvp.Request(1, kvp.MODE_READ, "$OV_PRO")))
        assert await asyncio.wait_for(c.reader.read(), 2) == b""
        assert sim.faults.counts["drop"] == 1
