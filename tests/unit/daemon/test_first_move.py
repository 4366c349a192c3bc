"""The first move of every run is checked from where the robot actually stands (issue 25).

The robot is put somewhere by the test (``SimWorld.move``, as a jog on the teach pendant
would) before the daemon starts or resumes a run; the daemon must read the joints from the
controller and refuse an unsafe first move before anything moves, naming that pose.
"""

from __future__ import annotations

import asyncio
import copy
import math

import numpy as np

from robocal.daemon._plan import parse_plan, plan_from_poses
from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers.mock import MockRobot
from robocal.drivers.sim import FanucSimOptions, LtpSimOptions, SimCell
from tests.unit.daemon.conftest import ROBOT

# an LR Mate pose beside the pedestal of the demo cell: safe where it stands, but the straight
# joint move from it to the demo plan's first pose takes the tool into the pedestal clearance
BESIDE_PEDESTAL = [136.0, 91.0, -140.0, -44.0, -12.0, -122.0]


async def robot_at(svc: CalibrationService, q_deg: list[float]) -> MockRobot:
    """Put the (mock) robot at ``q_deg`` as a jog would; return its driver."""
    robot = await svc.hub.robot()
    assert isinstance(robot, MockRobot)
    robot.world.move(np.radians(q_deg))
    return robot


def stands_at(robot: MockRobot) -> str:
    """The robot's actual joints as the refusal names them."""
    q = np.degrees(robot.world.q_actual_rad)
    return "stands at [" + ", ".join(f"{v:.2f}" for v in q) + "] deg"


async def test_false_home_is_refused_before_the_first_move(service, real_plan) -> None:
    # the plan declares its first pose as home: checked from there, every move is safe
    plan = copy.deepcopy(real_plan)
    plan["motion"]["home_deg"] = plan["poses"][0]["joints_deg"]
    svc = await service()
    robot = await robot_at(svc, BESIDE_PEDESTAL)
    moves, q_cmd = robot.world.moves, robot.world.q_cmd_rad.copy()
    st = await svc.create(plan, actor="test")          # the plan check accepts it
    st = await svc.wait(st["id"], ["faulted", "measured"], timeout=30.0)
    assert st["state"] == "faulted" and st["poses_measured"] == 0
    reason = st["reason"]
    assert "first move refused before any motion" in reason
    assert stands_at(robot) in reason                  # the actual start pose, in degrees
    assert "pedestal" in reason and "home (the plan's motion.home_deg)" in reason
    # no motion command reached the robot
    assert robot.world.moves == moves
    np.testing.assert_array_equal(robot.world.q_cmd_rad, q_cmd)

    # jogged back to a safe pose, the campaign resumes: home first, then the plan
    await robot_at(svc, [0.0] * 6)
    await svc.resume(st["id"], actor="test")
    st = await svc.wait(st["id"], ["measured", "fitted", "faulted"], timeout=60.0)
    assert st["state"] in ("measured", "fitted"), st["reason"]


async def test_a_fresh_run_moves_home_first(service, real_plan) -> None:
    svc = await service()
    # left at one of the plan's poses by an earlier run; home is all zeros
    robot = await robot_at(svc, real_plan["poses"][3]["joints_deg"])
    st = await svc.create(real_plan, actor="test", measure_only=True)
    st = await svc.wait(st["id"], ["measured", "faulted"], timeout=60.0)
    assert st["state"] == "measured", st["reason"]
    # the test's placement, one move to home, then one move per pose (via-points included)
    assert robot.world.moves == 1 + 1 + len(real_plan["poses"])


async def test_resume_checks_the_move_from_where_the_robot_stands(service, real_plan
                                                                  ) -> None:
    # a bare plan (no home) run in the daemon's cell: zeros, then the demo plan's first pose
    q0 = real_plan["poses"][0]["joints_deg"]
    doc = parse_plan(plan_from_poses([[0.0] * 6, q0, q0], robot=ROBOT), source="test",
                     strict=False)
    svc = await service(cell="demo", tracker={"options": {"measure_time_s": 0.5}})
    robot = await robot_at(svc, [0.0] * 6)
    async with svc.events.subscribe() as q, asyncio.timeout(30.0):
        cid = (await svc.create(doc, actor="test", measure_only=True))["id"]
        while (ev := await q.get()) is not None and ev["kind"] != "pose":
            pass
        await svc.pause(cid, actor="test")
    assert svc.store.measured_indices(cid) == {0}      # pose 1 was in progress: redone
    # jogged elsewhere while paused; the move from there to pose 1 crosses the pedestal
    await robot_at(svc, BESIDE_PEDESTAL)
    moves = robot.world.moves
    await svc.resume(cid, actor="test")
    st = await svc.wait(cid, ["faulted", "measured"], timeout=30.0)
    assert st["state"] == "faulted"
    assert stands_at(robot) in st["reason"] and "to pose 1 (calibration)" in st["reason"]
    assert "pedestal" in st["reason"] and robot.world.moves == moves


async def test_bare_plan_without_a_cell_checks_the_start_against_the_limits(service) -> None:
    svc = await service()
    hi = math.degrees(svc.robot.joints[0].q_max)
    # inside the robot's limits (the mock accepts it) but within the daemon's 1 deg margin
    robot = await robot_at(svc, [hi - 0.5, 0.0, 0.0, 0.0, 0.0, 0.0])
    moves = robot.world.moves
    doc = parse_plan(plan_from_poses([[10.0, 0.0, 0.0, 0.0, 0.0, 0.0]], robot=ROBOT),
                     source="verification", strict=False)
    st = await svc.create(doc, actor="test", measure_only=True)
    st = await svc.wait(st["id"], ["faulted", "measured"], timeout=30.0)
    assert st["state"] == "faulted" and robot.world.moves == moves
    assert stands_at(robot) in st["reason"]
    assert "outside the joint limits with margin: J1 at" in st["reason"]



async def test_false_home_is_refused_over_the_rmi_wire(tmp_path, real_plan) -> None:
    # the same refusal against the FANUC RMI and LTP/1 simulators over loopback TCP
    plan = copy.deepcopy(real_plan)
    plan["motion"]["home_deg"] = plan["poses"][0]["joints_deg"]
    cell = SimCell(robot=ROBOT, seed=1, fanuc=FanucSimOptions(time_scale=0.0), modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0))
    async with cell:
        cell.world.move(np.radians(BESIDE_PEDESTAL))
        moves, q_cmd = cell.world.moves, cell.world.q_cmd_rad.copy()
        cfg = parse_config({
            "data_dir": str(tmp_path / "state"), "robot_description": ROBOT,
            "robot": {"kind": "fanuc_rmi", "options": cell.robot_options("fanuc_rmi")},
            "tracker": {"kind": "ltp", "options": cell.tracker_options("tcp")},
            "measurement": {"settle_s": 0.0, "samples": 3},
            "fit": {"models": ["constant"], "select": "constant", "executor": "thread",
                    "report": False},
        }, source="test")
        svc = CalibrationService(cfg)
        await svc.start()
        try:
            st = await svc.create(plan, actor="test")
            st = await svc.wait(st["id"], ["faulted", "measured"], timeout=30.0)
            q = np.degrees(cell.world.q_actual_rad)
            assert st["state"] == "faulted"
            assert "stands at [" + ", ".join(f"{v:.2f}" for v in q) + "] deg" in st["reason"]
            assert "pedestal" in st["reason"]
            assert cell.world.moves == moves            # no motion command reached the robot
            np.testing.assert_array_equal(cell.world.q_cmd_rad, q_cmd)
        finally:
            await svc.stop()
