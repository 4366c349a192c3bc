"""The third-party ``ur-rtde`` client drives the UR simulator through a realistic session.

ur-rtde reaches RTDE on port 30004 only (no port argument), and RTDEControlInterface sends
its control program to 30003, so the simulator listens on a loopback address of its own
(127.0.0.N, N chosen at random among those whose ports 29999 and 30001-30004 are free) with
the real port numbers. The client runs in a child
process: its calls block holding the GIL.
"""

from __future__ import annotations

import asyncio
import json
import random
import sys
from pathlib import Path

import pytest

from robocal.drivers.sim import SimCell, SimWorld, UrSimOptions

pytest.importorskip("rtde_receive", reason="ur-rtde has no wheel for this platform")

SESSION = Path(__file__).with_name("_ur_rtde_session.py")
REAL_PORTS = {"ur_dashboard": 29999, "ur_primary": 30001, "ur_secondary": 30002,
              "ur_realtime": 30003, "ur_rtde": 30004}


async def _start_on_free_loopback(world: SimWorld) -> SimCell:
    """A UR simulator on the real ports of the first free 127.0.0.N tried."""
    candidates = random.Random().sample(range(2, 255), 20)
    for n in candidates:
        cell = SimCell(world=world, fanuc=False, modbus=False, ltp=False,
                       ur=UrSimOptions(time_scale=0.01), ur_host=f"127.0.0.{n}",
                       ports=REAL_PORTS)
        try:
            return await cell.start()
        except OSError:
            continue  # a port is taken on that address (start() cleaned up)
    pytest.skip("no loopback address with ports 29999 and 30001-30004 free")


async def test_ur_rtde_session_passes_every_step():
    world = SimWorld.create("ur10", seed=3)
    q0 = [0.1, -1.2, 1.1, -0.4, 0.3, 0.2]
    world.move(q0)
    cell = await _start_on_free_loopback(world)
    try:
        sim = cell.ur_sim
        assert sim is not None
        sim.int_out[12] = 4242
        sim.double_out[12] = 2.5
        expected_q = [float(v) for v in world.q_actual_rad]
        proc = await asyncio.create_subprocess_exec(
            sys.executable, str(SESSION), cell.ur_host, json.dumps(expected_q),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        try:
            async with asyncio.timeout(60):
                out, err = await proc.communicate()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        steps = [json.loads(line) for line in out.decode().splitlines() if line.startswith("{")]
        passed = [s for s in steps if s["ok"]]
        print(f"ur-rtde session: {len(passed)}/{len(steps)} steps passed")
        failed = [f"{s['step']}: {s['detail']}" for s in steps if not s["ok"]]
        assert proc.returncode == 0, err.decode()[-2000:]
        assert not failed, failed
        assert len(steps) == 75
        # What the client set arrived in the controller.
        assert sim.int_in[18] == 42
        assert sim.double_in[19] == 1.25
        assert sim.speed_slider == 0.5
        assert sim.digital_out & (1 << 3) == 0
        assert sim.robot_mode == 3  # powered off at the end
        # ur-rtde's control program ran three times (uploaded, then again after the error and
        # after the protective stop); the payload it set arrived
        assert sum(p.startswith("def rtde_control():") for p in sim.scripts) == 3
        assert sim.payload == (1.5, [0.0, 0.0, 0.05]) and sim.tcp == [0.0] * 6
        assert any("outside the joint limits" in e for e in sim.runtime_errors)
    finally:
        await cell.stop()
