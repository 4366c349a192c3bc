"""``robocal sim``: the simulators as a process, and its argument handling."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import sys

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as hs

from robocal.drivers import load_robot_driver, load_tracker_driver
from robocal.drivers.sim import main


def test_bad_arguments():
    with pytest.raises(SystemExit) as info:
        main(["nonsense"])
    assert info.value.code == 2
    assert main(["all", "--fault-rate", "2"]) == 2
    assert main(["all", "--warmup-drift-mm", "-1"]) == 2


async def test_all_in_one_process_shares_one_world(tmp_path):
    ports_file = tmp_path / "ports.json"
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "robocal.drivers.sim",
        "all",
        "--pty",
        "--seed",
        "4",
        "--time-scale",
        "0",
        "--ports-file",
        str(ports_file),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    try:
        line = await asyncio.wait_for(proc.stdout.readline(), 30)
        ports = json.loads(line)
        assert json.loads(ports_file.read_text()) == ports
        assert set(ports) == {
            "host", "robot", "fanuc_rmi", "modbus_plc", "ltp_tracker", "emscon_tracker",
            "kuka_kvp",
            "abb_rws",
            "universal_robots",
        }
        pty = ports["ltp_tracker"]["pty"]
        assert pty.startswith("/dev/")
        limits = [(-90.0, 90.0)] * 6
        robot = load_robot_driver(
            "fanuc_rmi",
            {"connect_port": ports["fanuc_rmi"]["connect_port"], "joint_limits_deg": limits},
        )
        plc = load_robot_driver(
            "modbus_plc", {"port": ports["modbus_plc"]["port"], "joint_limits_deg": limits}
        )
        tcp = load_tracker_driver("ltp", {"url": f"tcp://127.0.0.1:{ports['ltp_tracker']['port']}"})
        serial = load_tracker_driver("ltp", {"url": f"serial://{pty}?baudrate=115200"})
        for d in (robot, plc, tcp, serial):
            await d.connect(timeout=10)
        try:
            await robot.move_to([0.3] * 6, timeout=10)
            a = await tcp.measure(samples=10, timeout=5)
            b = await serial.measure(samples=10, timeout=5)
            assert np.linalg.norm(np.subtract(a.position_m, b.position_m)) < 1e-4
            # The PLC moves the same robot: the tracker sees the new pose.
            await plc.move_to([-0.3] * 6, timeout=10)
            assert (await robot.read_joints()).q_rad[0] == pytest.approx(-0.3, abs=1e-4)
            c = await tcp.measure(samples=10, timeout=5)
            assert np.linalg.norm(np.subtract(a.position_m, c.position_m)) > 0.05
            # and so does the KUKA loop behind KUKAVARPROXY
            kuka = load_robot_driver(
                "kuka_kvp", {"port": ports["kuka_kvp"]["port"], "joint_limits_deg": limits})
            async with kuka:
                await kuka.move_to([0.1] * 6, timeout=10)
            assert (await robot.read_joints()).q_rad[0] == pytest.approx(0.1, abs=1e-4)
        finally:
            for d in (robot, plc, tcp, serial):
                await d.close()
        proc.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(proc.wait(), 20) == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        with contextlib.suppress(Exception):
            await proc.communicate()


async def test_sim_ur_serves_the_ur_interfaces(tmp_path):
    """``robocal sim ur --robot ur10``: dashboard, primary and RTDE at the real spacing."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "robocal.drivers.sim", "ur", "--robot", "ur10", "--time-scale",
        "0", "--warmup-drift-mm", "0.1", stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    try:
        line = await asyncio.wait_for(proc.stdout.readline(), 30)
        ports = json.loads(line)
        assert set(ports) == {"host", "robot", "universal_robots"}
        ur = ports["universal_robots"]
        robot = load_robot_driver("universal_robots", {
            "host": ur["host"], "dashboard_port": ur["dashboard"],
            "primary_port": ur["primary"], "rtde_port": ur["rtde"],
            "joint_limits_deg": [(-360.0, 360.0)] * 6})
        await robot.connect(timeout=10)
        try:
            cold = await robot.read_joint_temperatures()
            reached = await robot.move_to([0.3] * 6, timeout=10)
            assert reached.q_rad[0] == pytest.approx(0.3, abs=1e-4)
            await robot._next_state(5.0)  # a package sent after the move
            warm = await robot.read_joint_temperatures()
            # the planted warm-up drift heats the joints while they move (ADR 0042)
            assert cold.temps_c == (20.0,) * 6
            assert all(w > c for w, c in zip(warm.temps_c, cold.temps_c, strict=True))
        finally:
            await robot.close()
        proc.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(proc.wait(), 20) == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        with contextlib.suppress(Exception):
            await proc.communicate()


def test_ur_ports_keep_the_real_spacing():
    from robocal.drivers.sim import _fixed_ports

    assert _fixed_ports("ur", 29999) == {"ur_dashboard": 29999, "ur_primary": 30001,
                                         "ur_secondary": 30002, "ur_realtime": 30003,
                                         "ur_rtde": 30004}
    ports = _fixed_ports("all", 17001)
    assert ports["ur_rtde"] == 17011 and ports["ur_realtime"] == 17012
    assert len(set(ports.values())) == len(ports)            # no two simulators share one


def test_drift_rates_are_checked():
    with pytest.raises(SystemExit) as info:
        main(["all", "--drift-deg-per-day", "0,x"])
    assert info.value.code == 2
    with pytest.raises(SystemExit):
        main(["all", "--drift-deg-per-day", "0,nan"])


async def test_the_drift_clock_advances_the_planted_drift():
    from robocal.drivers.sim import drift_clock
    from robocal.drivers.sim.world import SimWorld
    from tests._waiting import eventually

    world = SimWorld.create("fanuc_lrmate200i", "constant", seed=2)
    world.cell.drift_deg_per_day = (0.0, 0.5)
    q = np.zeros(6)
    world.move(q)
    before = world.true_reflector_position()
    task = asyncio.create_task(drift_clock(world, 6000.0, period_s=0.005))  # 100 days/s
    try:
        await eventually(lambda: world.cell.sim_days > 0.1, 5)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    days = world.cell.sim_days
    assert np.allclose(world.cell.joint_drift_rad(), np.radians([0, 0.5 * days, 0, 0, 0, 0]))
    moved = np.linalg.norm(world.true_reflector_position() - before)
    assert moved > 1e-4  # the arm is elsewhere ...
    assert np.allclose(world.q_actual_rad, q, atol=1e-4)  # ... the joints read the same


@given(hs.lists(hs.floats(allow_nan=False, allow_infinity=False), min_size=1, max_size=7))
def test_drift_rates_parse_back_what_was_written(rates):
    from robocal.drivers.sim import _rates

    assert _rates(",".join(repr(r) for r in rates)) == tuple(rates)


@given(hs.text(max_size=20))
def test_drift_rates_refuse_anything_else_with_an_argparse_error(text):
    import argparse

    from robocal.drivers.sim import _rates

    try:
        out = _rates(text)
    except argparse.ArgumentTypeError:
        return
    assert all(np.isfinite(out)) and len(out) == text.count(",") + 1
