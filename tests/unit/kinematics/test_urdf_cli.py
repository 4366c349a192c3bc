"""The command line around URDF: robots --from-urdf, --robot FILE.urdf, export --format urdf."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from robocal.cli.main import main
from robocal.kinematics import (
    CalibratedModel,
    ErrorModelSpec,
    KinematicModel,
    constant_part,
    load_robot,
    robot_to_urdf,
)

from .urdf_reference import movable_joints, urdf_fk

FIXTURE = Path(__file__).parent / "fixtures" / "ur10_ur_description.urdf"


def _flange(robot, q):
    m = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    return m.flange_poses(q, m.nominal_params())[1:]


def test_robots_from_urdf_writes_a_robot_toml(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ur10.toml"
    assert main(["robots", "--from-urdf", str(FIXTURE), "--out", str(out)]) == 0
    assert "6 joints" in capsys.readouterr().err
    data = tomllib.loads(out.read_text())
    assert [j["name"] for j in data["joints"]][:2] == ["shoulder_pan_joint",
                                                     "shoulder_lift_joint"]
    q = np.random.default_rng(0).uniform(-3, 3, (20, 6))
    R0, o0 = _flange(load_robot(FIXTURE), q)
    R1, o1 = _flange(load_robot(out), q)
    assert np.abs(o0 - o1).max() < 1e-12 and np.abs(R0 - R1).max() < 1e-12
    assert main(["robots", str(FIXTURE)]) == 0                       # shows a URDF like a TOML
    assert "shoulder" not in capsys.readouterr().err
    assert main(["robots", "--from-urdf", str(tmp_path / "none.urdf")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "none.urdf" in err and "file not found" in err
    bad = tmp_path / "bad.urdf"
    bad.write_text('<robot name="x"><link name="a"/><link name="b"/><joint name="slide" '
                   'type="prismatic"><parent link="a"/><child link="b"/></joint></robot>')
    assert main(["robots", "--from-urdf", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "slide" in err and "prismatic" in err


def test_fit_takes_a_urdf_and_export_writes_urdf_and_side_table(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    urdf = tmp_path / "ur10.urdf"
    urdf.write_text(robot_to_urdf(load_robot("ur10")))
    meas = tmp_path / "m.csv"
    assert main(["simulate", "--robot", "ur10", "--scenario", "constant", "--poses", "60",
                 "--out", str(meas)]) == 0
    model_path = tmp_path / "model.json"
    assert main(["fit", "--robot", str(urdf), "--data", str(meas), "--model", "constant",
                 "--out", str(model_path)]) == 0
    capsys.readouterr()
    out = tmp_path / "calibrated.urdf"
    assert main(["export", "--model", str(model_path), "--format", "urdf", "--out",
                 str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    side = json.loads((tmp_path / "calibrated.joint_dependent.json").read_text())
    assert summary["side_table"].endswith("calibrated.joint_dependent.json")
    assert side["urdf"] == "calibrated.urdf" and side["format"] == "robocal.urdf-side/1"
    cal = CalibratedModel.load(model_path)
    x_const, _ = constant_part(cal)
    text = out.read_text()
    names = movable_joints(text)
    q = np.random.default_rng(3).uniform(-2, 2, (10, 6))
    p = cal.model.positions(q, x_const)
    for k in range(len(q)):
        T = urdf_fk(text, dict(zip(names, q[k], strict=True)), "tcp")
        assert np.abs(T[:3, 3] - p[k]).max() < 1e-12
    assert main(["export", "--model", str(tmp_path / "none.json"), "--out", str(out)]) == 2
    assert "none.json" in capsys.readouterr().err
