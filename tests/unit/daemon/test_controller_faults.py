"""Controller alarms and lost links against the in-process RMI and LTP/1 simulators."""

from __future__ import annotations

import asyncio

import pytest

from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers.sim import FanucSimOptions, FaultConfig, LtpSimOptions, SimCell
from robocal.errors import ConnectFailed
from tests.unit.daemon.conftest import ROBOT, random_plan


async def test_alarms_fault_the_campaign_and_the_operator_resumes(tmp_path):
    faults = FaultConfig(alarm_rate=0.1, seed=3)
    cell = SimCell(robot=ROBOT, seed=2, fanuc=FanucSimOptions(time_scale=0.0), modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0), faults=faults)
    async with cell:
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
            st = await svc.create(random_plan(20), actor="t")
            cid = st["id"]
            reasons = []
            for _ in range(20):
                st = await svc.wait(cid, ["fitted", "faulted"], timeout=60)
                if st["state"] != "faulted":
                    break
                reasons.append(st["reason"])
                await svc.resume(cid, actor="operator")
            assert st["state"] == "fitted", st["reason"]
            assert reasons and all("MotionRejected" in r for r in reasons)
            rows = svc.store.measurements(cid)
            assert sorted(r.pose_idx for r in rows) == list(range(20))
            history = [t["to_state"] for t in svc.store.transitions(cid)]
            assert history.count("faulted") == len(reasons)
        finally:
            await svc.stop()
            await asyncio.sleep(0.05)


async def test_unreachable_devices_refuse_a_start_and_the_daemon_serves_on(tmp_path):
    cfg = parse_config({
        "data_dir": str(tmp_path / "state"), "robot_description": ROBOT,
        "robot": {"kind": "fanuc_rmi", "options": {"host": "127.0.0.1", "connect_port": 9,
                                                   "reply_timeout_s": 0.5},
                  "connect_timeout_s": 0.5},
        "tracker": {"kind": "ltp", "options": {"url": "tcp://127.0.0.1:9"},
                    "connect_timeout_s": 0.5},
        "fit": {"executor": "thread"},
    }, source="test")
    svc = CalibrationService(cfg)
    await svc.start()  # logs the failure, serves anyway
    try:
        assert svc.health()["drivers"]["last_error"]
        # pre-flight: nothing is created for a cell whose devices do not answer
        with pytest.raises(ConnectFailed, match=r"the robot \(fanuc_rmi\) does not answer"):
            await svc.create(random_plan(5), actor="t")
        assert svc.list() == [] and svc.health()["status"] == "ok"
    finally:
        await svc.stop()
