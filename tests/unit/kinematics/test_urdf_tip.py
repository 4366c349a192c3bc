"""``--tip`` cuts a URDF chain before a movable gripper; ``predict --robot`` without a model."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from robocal.cli.main import main
from robocal.errors import ConfigError
from robocal.kinematics import ErrorModelSpec, KinematicModel, load_urdf, urdf_to_robot

_ARM = """<robot name="desk_arm">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="l3"/>
  <link name="gripper_base"/><link name="jaw"/><link name="finger"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 0 1"/><limit lower="-2" upper="2"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.05"/><axis xyz="0 1 0"/><limit lower="-2" upper="2"/></joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.2 0 0"/><axis xyz="0 1 0"/><limit lower="-2" upper="2"/></joint>
  <joint name="to_gripper" type="fixed"><parent link="l3"/><child link="gripper_base"/>
    <origin xyz="0.15 0 0" rpy="0 0.3 0"/></joint>
  <joint name="jaw" type="revolute"><parent link="gripper_base"/><child link="jaw"/>
    <origin xyz="0.03 0 0"/><axis xyz="1 0 0"/><limit lower="0" upper="1"/></joint>
  <joint name="slide" type="prismatic"><parent link="gripper_base"/><child link="finger"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.02"/></joint>
</robot>"""


def _tip_position(q: np.ndarray) -> np.ndarray:
    """Reference: gripper_base origin by composing the URDF's own transforms (no DH)."""
    def rot(axis: str, t: float) -> np.ndarray:
        c, s = np.cos(t), np.sin(t)
        return {"z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]),
                "y": np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])}[axis]
    out = []
    for a, b, c in q:
        R, o = np.eye(3), np.zeros(3)
        for off, ax, t in (((0, 0, 0.1), "z", a), ((0, 0, 0.05), "y", b),
                           ((0.2, 0, 0), "y", c)):
            o = o + R @ np.array(off)
            R = R @ rot(ax, t)
        out.append(o + R @ np.array([0.15, 0, 0]))
    return np.array(out)


def test_tip_before_a_movable_gripper_cuts_it_off() -> None:
    with pytest.raises(ConfigError, match="prismatic"):
        urdf_to_robot(_ARM)                             # the sliding finger is not a robot joint
    robot = urdf_to_robot(_ARM, tip="gripper_base")
    assert [j.name for j in robot.joints] == ["j1", "j2", "j3"]
    q = np.random.default_rng(0).uniform(-1.5, 1.5, (30, 3))
    m = KinematicModel(robot, ErrorModelSpec(3, ()))
    p = m.positions(q, np.zeros(m.size))               # tool (0,0,0): the tip link's origin
    assert np.abs(p - _tip_position(q)).max() < 1e-12
    # everything below the tip goes, the arm's own joints too
    assert [j.name for j in urdf_to_robot(_ARM, tip="l2").joints] == ["j1", "j2"]
    with pytest.raises(ConfigError, match="no link named"):
        urdf_to_robot(_ARM, tip="hand")


def test_predict_with_a_nominal_robot(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                      ) -> None:
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(_ARM)
    qdeg = np.array([[0.0, 10.0, -20.0], [30.0, -45.0, 60.0]])
    joints = tmp_path / "joints.csv"
    joints.write_text("pose_id,q1,q2,q3\n" + "".join(
        f"P{i},{a},{b},{c}\n" for i, (a, b, c) in enumerate(qdeg)))
    out = tmp_path / "pred.csv"
    assert main(["predict", "--robot", str(urdf), "--tip", "gripper_base", "--joints",
                 str(joints), "--out", str(out), "--tool", "0", "0", "0", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["kind"] == "nominal" and summary["n"] == 2
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["pose_id"] for r in rows] == ["P0", "P1"]
    got = np.array([[float(r[k]) for k in "xyz"] for r in rows]) * 1e-3
    assert np.abs(got - _tip_position(np.radians(qdeg))).max() < 1e-9
    # a built-in robot by name, with its own reflector offset
    assert main(["predict", "--robot", "ur10", "--joints", str(_six(tmp_path)), "--out",
                 str(out)]) == 0
    assert "nominal" in capsys.readouterr().out
    assert main(["predict", "--robot", "ur10", "--tip", "x", "--joints", str(joints),
                 "--out", str(out)]) == 2
    assert "--tip" in capsys.readouterr().err
    assert load_urdf(urdf, tip="gripper_base").dof == 3


def _six(tmp: Path) -> Path:
    path = tmp / "six.csv"
    path.write_text("q1,q2,q3,q4,q5,q6\n0,-90,90,0,90,0\n10,-80,70,5,60,30\n")
    return path
