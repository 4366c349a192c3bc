"""Push and rollback through the real controller drivers against their simulators.

Before robocal's first push the controller holds its own values (a table block another tool
wrote into the PLC, the robot program's position registers); rolling back the first push
must put exactly those back, and the rollback is measured again like a push.
"""

from __future__ import annotations

import pytest

from robocal.compensation import CompensationTable, Frame, FramesPayload
from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers import load_robot_driver
from robocal.drivers.sim import FanucSimOptions, LtpSimOptions, SimCell
from tests.unit.daemon.conftest import ROBOT, base_config
from tests.unit.daemon.test_service import program_plan


def _foreign_table() -> CompensationTable:
    """A frames table some earlier tool left in the PLC."""
    f = Frame(x=1.5, y=-2.0, z=0.25, w=0.01, p=-0.02, r=0.03)
    return CompensationTable(kind="frames", model_id="other-tool", robot="x",
                             valid_range_deg=[], predicted_residual_mm=0.0,
                             frames=FramesPayload(base=f, tool=f)).sealed()


@pytest.mark.parametrize("kind", ["modbus_plc", "fanuc_rmi"])
async def test_rollback_after_the_first_push_restores_the_controllers_original(tmp_path, kind):
    cell = SimCell(robot=ROBOT, seed=4, fanuc=FanucSimOptions(time_scale=0.0),
                   modbus=kind == "modbus_plc", ltp=LtpSimOptions(time_scale=0.0))
    async with cell:
        original_pr: dict[int, dict[str, object]] = {}
        if kind == "modbus_plc":
            plc = load_robot_driver(kind, cell.robot_options(kind))
            await plc.connect(timeout=10)
            await plc.write_compensation(_foreign_table())
            await plc.close()
        else:
            sim = cell.fanuc_sim
            assert sim is not None
            for n in range(1, 41):
                sim.position_registers[n] = {
                    "Configuration": {"UToolNumber": 1, "UFrameNumber": 0, "Front": 1,
                                      "Up": 1, "Left": 0, "Flip": 0, "Turn4": 0, "Turn5": 0,
                                      "Turn6": 0},
                    "Position": {"X": n + 0.5, "Y": -n, "Z": 3.0 * n, "W": 0.0, "P": 0.0,
                                 "R": 0.0}}
            original_pr = {n: dict(v) for n, v in sim.position_registers.items()}
        cfg = base_config(tmp_path, limits={"max_joint_correction_deg": 5.0},
                          compensation={"verify_count": 3})
        cfg["robot"] = {"kind": kind, "options": cell.robot_options(kind)}
        cfg["tracker"] = {"kind": "ltp",
                          "options": {**cell.tracker_options("tcp"), "stab_ms": 10}}
        svc = CalibrationService(parse_config(cfg, source="test"))
        await svc.start()
        try:
            st = await svc.create(program_plan(36, validation=8), actor="a")
            st = await svc.wait(st["id"], ["fitted", "faulted"], timeout=120)
            assert st["state"] == "fitted", st["reason"]
            await svc.approve(st["id"], actor="a")
            st = await svc.push(st["id"], actor="a")
            v = await svc.wait_verification(st["push"]["key"], timeout=120)
            assert v is not None and v["state"] == "done", v
            assert v["after"]["rms_mm"] < 0.6 * v["before"]["rms_mm"]
            comp = svc.compensation()
            assert [h["action"] for h in comp["history"]] == ["baseline", "push"]

            out = await svc.rollback(actor="b")
            assert out["active"]["origin"] == "controller"
            robot = await svc.hub.robot()
            if kind == "modbus_plc":
                back = await robot.read_compensation()
                assert back is not None and back.checksum == _foreign_table().checksum
            else:
                sim = cell.fanuc_sim
                assert sim is not None
                for n, value in original_pr.items():
                    assert sim.position_registers[n] == value, n
            rb = [a for a in svc.audit() if a["action"] == "compensation.rollback"][-1]
            v = await svc.wait_verification(rb["detail"]["key"], timeout=120)
            # the original values mean the uncompensated targets: as inaccurate as before
            assert v is not None and v["state"] == "done"
            assert v["after"]["rms_mm"] == pytest.approx(v["before"]["rms_mm"], rel=0.1)
        finally:
            await svc.stop()
