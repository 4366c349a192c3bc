"""A push counts and names program targets outside the calibrated coverage (ADR 0026)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robocal.daemon import pushing
from robocal.daemon._plan import parse_plan, plan_from_poses
from robocal.errors import CompensationError
from robocal.kinematics import load_robot
from tests.unit.daemon.conftest import ROBOT


def _plan(n: int, j6_deg: float) -> object:
    """Random poses with |J6| <= ``j6_deg`` and the wrist away from its singularity."""
    robot = load_robot(ROBOT)
    rng = np.random.default_rng(5)
    lim = np.degrees(robot.joint_limits)
    lim[5] = [-j6_deg, j6_deg]
    q = rng.uniform(lim[:, 0] + 10, lim[:, 1] - 10, (4 * n, robot.dof))
    q = q[np.abs(q[:, 4]) >= 20.0][:n]
    purposes = ["calibration"] * (n - 6) + ["validation"] * 6
    return parse_plan(plan_from_poses(q.tolist(), robot=ROBOT, purposes=purposes),
                      source="test", strict=False)


def _program(path: Path, j6: list[float]) -> Path:
    rows = [f"10,40,-20,30,{40 if i % 2 else -40},{v}" for i, v in enumerate(j6)]
    path.write_text("q1,q2,q3,q4,q5,q6\n" + "\n".join(rows) + "\n")
    return path


async def test_push_refuses_a_program_mostly_outside_coverage_unless_forced(service, tmp_path):
    # 4 of 10 targets at J6 = 250 deg, the campaign measured |J6| <= 90 deg only
    prog = _program(tmp_path / "JOINTS.csv", [250.0] * 4 + [30.0] * 6)
    svc = await service(limits={"max_joint_correction_deg": 5.0},
                        compensation={"verify_count": 0, "targets_file": str(prog)},
                        fit={"models": ["high-order"], "select": "high-order"})
    st = await svc.create(_plan(80, 90.0), actor="a")
    cid = st["id"]
    st = await svc.wait(cid, ["fitted"], timeout=60)
    assert st["state"] == "fitted", st["reason"]
    await svc.approve(cid, actor="a")
    _, desc = svc.build_push_table(cid)
    assert desc["coverage"]["outside"] == 4 and desc["coverage"]["share"] == 0.4
    assert desc["coverage"]["names"][0].startswith("target 0: J6 250.0 deg outside")
    with pytest.raises(CompensationError, match=r"4 of 10 targets \(40%\) lie outside"):
        await svc.push(cid, actor="a")
    assert await (await svc.hub.robot()).read_compensation() is None
    refused = svc.audit()[-1]
    assert refused["action"] == "compensation.push-refused"
    assert refused["detail"]["coverage"]["outside"] == 4
    st = await svc.push(cid, actor="a", force=True, reason="J6 beyond coverage, known")
    assert st["state"] == "pushed" and st["push"]["forced"] is True


def test_coverage_share_limit() -> None:
    cov = {"targets": 10, "outside": 1, "share": 0.1, "names": ["target 3: J6 ..."]}
    assert pushing.coverage_refusal(cov, 0.10) is None
    msg = pushing.coverage_refusal(cov, 0.05)
    assert msg is not None and "1 of 10 targets (10%)" in msg and "target 3" in msg
    many = {"targets": 40, "outside": 20, "share": 0.5, "names": [f"t{i}" for i in range(10)]}
    assert "and 10 more" in str(pushing.coverage_refusal(many, 0.1))
