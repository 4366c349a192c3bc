"""Third-party Robot Web Services clients from PyPI drive the ABB simulator through realistic
sessions: ``abb-robot-client`` (RWS 1.0, RobotWare 6, digest auth) and ``rwswrap``
(RWS 2.0, RobotWare 7, basic auth). Each prints its count of steps passed/tried; all must pass.

The clients are synchronous (requests); they run in a worker thread while the simulator serves
on the test's event loop. requests sets no timeout, so the socket default bounds every call.
"""

from __future__ import annotations

import asyncio
import importlib
import json
import math
import socket
from collections.abc import Callable, Iterator
from typing import Any

import abb_robot_client.rws as rws_client
import numpy as np
import pytest
from tests._waiting import eventually_sync

from robocal.drivers.sim import AbbSimOptions, SimCell, SimWorld
from robocal.kinematics import ErrorModelSpec, KinematicModel

rwswrap_module = importlib.import_module("rwswrap.RWS")  # module and class are both RWS
MODULE = "RobocalServer"


@pytest.fixture(autouse=True)
def bounded_sockets() -> Iterator[None]:
    old = socket.getdefaulttimeout()
    socket.setdefaulttimeout(10.0)
    try:
        yield
    finally:
        socket.setdefaulttimeout(old)


class Steps:
    """Named session steps: each runs, counts as passed or failed, and the session goes on."""

    def __init__(self, client: str) -> None:
        self.client = client
        self.passed: list[str] = []
        self.failed: list[tuple[str, str]] = []

    def run(self, name: str, step: Callable[[], Any]) -> Any:
        try:
            result = step()
        except Exception as err:
            self.failed.append((name, f"{type(err).__name__}: {err}"))
            return None
        self.passed.append(name)
        return result

    def report(self) -> None:
        tried = len(self.passed) + len(self.failed)
        print(f"{self.client}: {len(self.passed)}/{tried} session steps passed")
        for name, why in self.failed:
            print(f"  FAILED {name}: {why}")


def _check(cond: bool, what: str) -> None:
    if not cond:
        raise AssertionError(what)


def _nominal_flange_mm(world: SimWorld) -> np.ndarray:
    robot = world.cell.robot
    model = KinematicModel(robot, ErrorModelSpec(robot.dof, ()), np.eye(4))
    _, _, o = model.flange_poses(np.atleast_2d(world.q_actual_rad), model.nominal_params())
    return o[0] * 1000.0


def _target_deg(world: SimWorld, frac: float) -> list[float]:
    return [lo + frac * (hi - lo) for lo, hi in world.joint_limits_deg]


def abb_robot_client_session(url: str, world: SimWorld) -> Steps:
    """A RobotWare 6 session as abb-robot-client's RWS class runs it."""
    s = Steps("abb-robot-client (RWS 1.0)")
    c = rws_client.RWS(url)  # Default User / robotics, digest
    s.run("get_operation_mode is AUTO",
          lambda: _check(c.get_operation_mode() == "AUTO", "not AUTO"))
    s.run("get_controller_state is motoroff",
          lambda: _check(c.get_controller_state() == "motoroff", "motors on at start"))
    s.run("set_controller_state motoron", lambda: c.set_controller_state("motoron"))
    s.run("get_controller_state is motoron",
          lambda: _check(c.get_controller_state() == "motoron", "motors still off"))
    s.run("get_tasks lists T_ROB1 as an active motion task", lambda: _check(
        c.get_tasks()["T_ROB1"].motiontask and c.get_tasks()["T_ROB1"].active, "no T_ROB1"))
    s.run("get_execution_state is stopped",
          lambda: _check(c.get_execution_state().ctrlexecstate == "stopped", "running"))
    s.run("resetpp", c.resetpp)
    s.run("start T_ROB1", lambda: c.start(cycle="forever", tasks=["T_ROB1"]))
    s.run("get_execution_state is running",
          lambda: _check(c.get_execution_state().ctrlexecstate == "running", "not running"))
    s.run("get_speedratio is 100", lambda: _check(c.get_speedratio() == 100.0, "speed ratio"))
    s.run("set_speedratio 100", lambda: c.set_speedratio(100))
    done = s.run("get_rapid_variable_num rc_done",
                 lambda: c.get_rapid_variable_num("rc_done", "T_ROB1"))
    target = _target_deg(world, 0.6)

    def command_move() -> None:
        jt = rws_client.JointTarget(np.deg2rad(np.asarray(target)),
                                    np.deg2rad(np.full(6, 9e9)))
        c.set_rapid_variable_jointtarget("rc_target", jt, "T_ROB1")
        c.set_rapid_variable_num("rc_speed", 80, "T_ROB1")
        c.set_rapid_variable_num("rc_seq", (done or 0.0) + 1, "T_ROB1")

    s.run("set rc_target (jointtarget), rc_speed, rc_seq", command_move)
    s.run("read back rc_target", lambda: _check(np.allclose(
        np.rad2deg(c.get_rapid_variable_jointtarget("rc_target", "T_ROB1").robax), target,
        atol=1e-3), "rc_target differs"))
    s.run("rc_done follows rc_seq (the RAPID loop moved)", lambda: eventually_sync(
        lambda: c.get_rapid_variable_num("rc_done", "T_ROB1") == (done or 0.0) + 1, 10))
    s.run("get_jointtarget is the target", lambda: _check(np.allclose(
        c.get_jointtarget().robax, target, atol=0.01), "joints"))

    def robtarget() -> None:
        rt = c.get_robtarget()
        _check(abs(float(np.linalg.norm(rt.rot)) - 1.0) < 1e-4, "quaternion not unit")
        _check(np.allclose(rt.trans, _nominal_flange_mm(world), atol=0.05), "position")

    s.run("get_robtarget is the flange pose (mm, unit quaternion)", robtarget)

    def comp_array() -> None:
        arr = c.get_rapid_variable_jointtarget_array("rc_comp", "T_ROB1")
        new = [rws_client.JointTarget(np.deg2rad([i, 1.5, -2.25, 0, 90, -45]), t.extax)
               for i, t in enumerate(arr)]
        c.set_rapid_variable_jointtarget_array("rc_comp", new, "T_ROB1")
        back = c.get_rapid_variable_jointtarget_array("rc_comp", "T_ROB1")
        _check(len(back) == len(arr) and np.allclose(np.rad2deg(back[7].robax),
                                                     [7, 1.5, -2.25, 0, 90, -45]), "array")

    s.run("write and read back the PERS jointtarget array rc_comp", comp_array)

    def unknown_variable() -> None:
        try:
            c.get_rapid_variable("no_such_var", "T_ROB1")
        except rws_client.ABBException as err:
            _check(err.code < 0, "error code")
            return
        raise AssertionError("no error for an unknown variable")

    s.run("unknown variable raises ABBException with the controller's code", unknown_variable)
    s.run("stop", c.stop)
    s.run("get_execution_state is stopped after stop",
          lambda: _check(c.get_execution_state().ctrlexecstate == "stopped", "running"))
    s.run("close (logout)", c.close)
    return s


def rwswrap_session(url: str, world: SimWorld) -> Steps:
    """A RobotWare 7 session as rwswrap's RWS class runs it."""
    s = Steps("rwswrap (RWS 2.0)")
    c = rwswrap_module.RWS(url, username="Admin", password="robotics", module=MODULE)
    s.run("toggle_motors on", lambda: _check(c.toggle_motors(1).status_code == 204, "motors"))
    s.run("get_modules lists RobocalServer", lambda: _check(MODULE in c.get_modules(), "module"))
    s.run("get_exec_state is stopped", lambda: _check(c.get_exec_state() == "stopped", "run"))
    s.run("start_RAPID (resetpp under mastership, start)",
          lambda: _check(c.start_RAPID().status_code == 204, "start"))
    s.run("is_running", lambda: _check(c.is_running(), "not running"))
    s.run("get_rapid_variable rc_speed",
          lambda: _check(float(c.get_rapid_variable("rc_speed", module=MODULE)) > 0, "speed"))
    done = float(c.get_rapid_variable("rc_done", module=MODULE))
    target = _target_deg(world, 0.35)
    value = "[[" + ",".join(f"{v:.4f}" for v in target) + "],[9E9,9E9,9E9,9E9,9E9,9E9]]"
    s.run("set_rapid_variable rc_target", lambda: _check(
        c.set_rapid_variable("rc_target", value, module=MODULE).status_code == 204, "target"))
    s.run("set_rapid_variable rc_speed", lambda: _check(
        c.set_rapid_variable("rc_speed", 80, module=MODULE).status_code == 204, "speed"))
    s.run("set_rapid_variable rc_seq", lambda: _check(
        c.set_rapid_variable("rc_seq", done + 1, module=MODULE).status_code == 204, "seq"))
    s.run("rc_done follows rc_seq (the RAPID loop moved)", lambda: eventually_sync(
        lambda: float(c.get_rapid_variable("rc_done", module=MODULE)) == done + 1, 10))

    def joints() -> None:
        # rwswrap has no joint read: its authenticated session asks the resource directly.
        r = c.session.get(f"{url}/rw/motionsystem/mechunits/ROB_1/jointtarget",
                          headers=c.headers_json, verify=c.verify)
        _check(r.status_code == 200 and r.headers["Content-Type"].startswith(
            "application/hal+json"), f"HTTP {r.status_code}")
        state = json.loads(r.text)["state"][0]
        q = [float(state[f"rax_{i + 1}"]) for i in range(world.dof)]
        _check(np.allclose(q, target, atol=0.01), f"joints {q}")

    s.run("jointtarget through the client's session", joints)

    def robtarget() -> None:
        r = c.session.get(f"{url}/rw/motionsystem/mechunits/ROB_1/robtarget",
                          headers=c.headers_json, verify=c.verify)
        state = json.loads(r.text)["state"][0]
        q = [float(state[k]) for k in ("q1", "q2", "q3", "q4")]
        _check(abs(math.hypot(*q) - 1.0) < 1e-4, "quaternion not unit")
        xyz = [float(state[k]) for k in "xyz"]
        _check(np.allclose(xyz, _nominal_flange_mm(world), atol=0.05), "position")

    s.run("robtarget through the client's session", robtarget)
    s.run("stop_RAPID", lambda: _check(c.stop_RAPID().status_code == 204, "stop"))
    s.run("get_exec_state is stopped after stop",
          lambda: _check(c.get_exec_state() == "stopped", "running"))
    s.run("toggle_motors off", lambda: _check(c.toggle_motors(0).status_code == 204, "off"))
    return s


@pytest.mark.parametrize(("robotware", "session"), [(6, abb_robot_client_session),
                                                    (7, rwswrap_session)],
                         ids=["abb-robot-client", "rwswrap"])
async def test_third_party_client_session(robotware, session):
    world = SimWorld.create(seed=3)
    cell = SimCell(world=world, fanuc=False, modbus=False, ltp=False,
                   abb=AbbSimOptions(robotware=robotware, time_scale=0.01))
    async with cell:
        sim = cell.abb_sim
        assert sim is not None
        url = f"http://127.0.0.1:{sim.port}"
        steps = await asyncio.wait_for(asyncio.to_thread(session, url, world), 60)
    steps.report()
    assert not steps.failed, steps.failed
    assert len(steps.passed) >= 15
    assert world.moves >= 1  # the RAPID loop really moved the robot
