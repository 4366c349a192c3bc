"""The third-party PyPI client ``fanuc-rmi`` drives the RMI simulator through a whole session.

Someone else's client is the check that the simulator speaks RMI as controllers do. Where the
client departs from the manual (docs/protocols/fanuc-rmi.md, "Clients' quirks") the test
works around it on the client's side, never in the simulator: the session port is passed in
(the client looks for a ``Port`` key; controllers answer ``PortNumber``) and every
instruction gets the next SequenceID (the client's default is 1 for every instruction).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import fanuc_rmi  # a test dependency: missing, the test errors rather than skips
import numpy as np
from tests._peer import run_steps, session_in_thread

from robocal.drivers.sim import FanucRmiSimulator, FanucSimOptions, SimWorld

TOOL = {"X": 0.0, "Y": 0.0, "Z": 120.0, "W": 0.0, "P": 0.0, "R": 0.0}
UFRAME = {"X": 300.0, "Y": -50.0, "Z": 10.0, "W": 0.0, "P": 0.0, "R": 30.0}
Q0 = [10.0, 20.0, -10.0, 15.0, -40.0, 30.0]


def _close(a: dict[str, float], b: dict[str, float], tol: float) -> bool:
    return all(abs(float(a[k]) - float(b[k])) < tol for k in "XYZ") and all(
        abs((float(a[k]) - float(b[k]) + 180.0) % 360.0 - 180.0) < tol for k in "WPR")


def _session(sim: FanucRmiSimulator, world: SimWorld, out: Path) -> tuple[int, int, list[str]]:
    """Run the client's session (blocking sockets, in a thread); return passed, tried, failures."""
    client = fanuc_rmi.RobotClient(
        host="127.0.0.1", startup_port=sim.connect_port, main_port=sim.main_port,
        connect_timeout=5.0, socket_timeout=5.0, reader_timeout=5.0, startup_pause=0.0)
    seq = iter(range(1, 1000))
    state: dict[str, Any] = {}

    def q_cmd_deg() -> list[float]:
        return [math.degrees(v) for v in world.q_cmd_rad]

    def joint_absolute() -> bool:
        client.joint_absolute({f"J{i + 1}": v for i, v in enumerate(Q0)}, 50, next(seq))
        return np.allclose(q_cmd_deg(), Q0, atol=1e-6)

    def joint_relative() -> bool:
        client.joint_relative({"J1": 5.0, "J2": 0.0, "J3": 0.0, "J4": 0.0, "J5": -5.0,
                               "J6": 0.0}, 50, next(seq))
        return np.allclose(q_cmd_deg(), [15.0, 20.0, -10.0, 15.0, -45.0, 30.0], atol=1e-6)

    def read_cartesian() -> bool:
        reply = client.read_cartesian_coordinates(str(out / "cart.jsonl"))
        state["pose"] = reply["Position"]
        expected = sim.tcp_position(world.q_actual_rad, 0, 1)
        return reply["ErrorID"] == 0 and _close(reply["Position"], expected, 1e-3)

    def linear_absolute() -> bool:
        target = dict(state["pose"], X=state["pose"]["X"] + 40.0, Z=state["pose"]["Z"] - 30.0)
        client.linear_absolute(target, 200.0, next(seq), uframe=0, utool=1)
        state["target"] = target
        return _close(sim.tcp_position(world.q_cmd_rad, 0, 1), target, 1e-3)

    def linear_relative() -> bool:
        delta = {"X": 0.0, "Y": 25.0, "Z": 10.0, "W": 0.0, "P": 0.0, "R": 0.0}
        client.linear_relative(delta, 100.0, next(seq), uframe=0, utool=1)
        t = state["target"]
        want = dict(t, Y=t["Y"] + 25.0, Z=t["Z"] + 10.0)
        return _close(sim.tcp_position(world.q_cmd_rad, 0, 1), want, 1e-3)

    def linear_in_user_frame() -> bool:
        here = sim.tcp_position(world.q_cmd_rad, 1, 1)
        target = dict(here, X=here["X"] - 20.0)
        client.linear_absolute(target, 150.0, next(seq), uframe=1, utool=1)
        return _close(sim.tcp_position(world.q_cmd_rad, 1, 1), target, 1e-3)

    def write_dout() -> bool:
        client.write_dout(7, True)
        on = sim.digital_outputs.get(7) is True
        client.write_dout(7, "OFF")
        return on and sim.digital_outputs.get(7) is False

    def read_din() -> bool:
        sim.digital_inputs[3] = True
        on, off = client.read_din(3), client.read_din(4)
        return on["PortValue"] == "ON" and off["PortValue"] == "OFF" and on["ErrorID"] == 0

    steps: list[tuple[str, Callable[[], Any]]] = [
        ("connect", lambda: client.connect() or True),
        ("initialize", lambda: client.initialize(uframe=0, utool=1) or sim.initialized),
        ("get_uframe_utool", lambda: client.get_uframe_utool()
         == {"UFrameNumber": 0, "UToolNumber": 1}),
        ("speed_override", lambda: client.speed_override(80) or sim.override == 80),
        ("write_utool_data", lambda: client.write_utool_data(1, TOOL)["ErrorID"] == 0),
        ("read_utool_data", lambda: _close(client.read_utool_data(1), TOOL, 1e-6)),
        ("write_uframe_data", lambda: client.write_uframe_data(1, UFRAME)["ErrorID"] == 0),
        ("read_uframe_data", lambda: _close(client.read_uframe_data(1), UFRAME, 1e-6)),
        ("joint_absolute", joint_absolute),
        ("read_joint_coordinates", lambda: np.allclose(
            [client.read_joint_coordinates(str(out / "joints.jsonl"))["JointAngle"][f"J{i}"]
             for i in range(1, 7)], np.degrees(world.q_actual_rad), atol=1e-6)),
        ("joint_relative", joint_relative),
        ("read_cartesian_coordinates", read_cartesian),
        ("linear_absolute", linear_absolute),
        ("linear_relative", linear_relative),
        ("linear_absolute_in_uframe_1", linear_in_user_frame),
        ("wait_time", lambda: client.wait_time(0.5, next(seq)) or not sim.hold),
        ("set_uframe", lambda: client.set_uframe(0, next(seq))["ErrorID"] == 0),
        ("set_utool", lambda: client.set_utool(1, next(seq))["ErrorID"] == 0),
        ("write_dout", write_dout),
        ("read_din", read_din),
        ("abort", lambda: client.abort()["ErrorID"] == 0 and not sim.initialized),
        ("close", lambda: client.close() or True),
    ]
    return run_steps(steps)


async def test_fanuc_rmi_client_session_passes_every_step(tmp_path, capsys):
    world = SimWorld.create(seed=12)
    sim = FanucRmiSimulator(world, FanucSimOptions(time_scale=0.001))
    await sim.start()
    passed, tried, failures = await session_in_thread(sim, "fanuc-rmi", capsys, _session, sim,
                                                      world, tmp_path)
    assert not failures, failures
    assert passed == tried == 22
    # nothing the client sent made the controller HOLD or fault
    names = [p.get("Instruction") or p.get("Command") for p in sim.received]
    assert {"FRC_ReadCartesianPosition", "FRC_JointRelativeJRep", "FRC_LinearMotion",
            "FRC_LinearRelative", "FRC_ReadDIN", "FRC_WriteDOUT"} <= set(names)
