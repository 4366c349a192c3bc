"""Modified (Craig) DH in the robot TOML: exact conversion to and from standard DH."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.errors import ConfigError
from robocal.kinematics import (
    CalibratedModel,
    ErrorModelSpec,
    KinematicModel,
    RobotDescription,
    builtin_robots,
    load_robot,
    robot_to_toml,
)

from .reference import rx, rz, tr

CRAIG = """
name = "Craig arm"
convention = "modified"
tool_mm = [10.0, 0.0, 80.0]
[[joints]]
a_mm = 25.0
alpha_deg = 30.0
d_mm = 400.0
theta_offset_deg = 5.0
min_deg = -170.0
max_deg = 170.0
[[joints]]
a_mm = 150.0
alpha_deg = -90.0
d_mm = 0.0
theta_offset_deg = -90.0
min_deg = -100.0
max_deg = 140.0
[[joints]]
a_mm = 600.0
alpha_deg = 0.0
d_mm = 20.0
min_deg = -160.0
max_deg = 160.0
[[joints]]
a_mm = 120.0
alpha_deg = -90.0
d_mm = 640.0
min_deg = -190.0
max_deg = 190.0
"""


def _craig_fk(data: dict, q: np.ndarray) -> np.ndarray:
    """Test-side Craig chain: Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i), then the tool."""
    T = np.eye(4)
    for j, qi in zip(data["joints"], q, strict=True):
        T = (T @ rx(math.radians(j["alpha_deg"])) @ tr(x=j["a_mm"] * 1e-3)
             @ rz(qi + math.radians(j.get("theta_offset_deg", 0.0))) @ tr(z=j["d_mm"] * 1e-3))
    return (T @ np.array([*(np.array(data["tool_mm"]) * 1e-3), 1.0]))[:3]


def _positions(robot: RobotDescription, q: np.ndarray) -> np.ndarray:
    m = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    return m.positions(q, m.nominal_params())


def test_modified_table_gives_craigs_forward_kinematics() -> None:
    data = tomllib.loads(CRAIG)
    robot = RobotDescription.from_dict(data, source="craig.toml")
    q = np.random.default_rng(2).uniform(-1.5, 1.5, (25, 4))
    p = _positions(robot, q)
    for k in range(len(q)):
        assert np.abs(p[k] - _craig_fk(data, q[k])).max() < 1e-12
    # standard DH: joint i carries the modified table's a, alpha of joint i+1
    assert robot.joints[0].a == pytest.approx(0.15) and robot.joints[-1].a == 0.0
    assert robot.has_base and not robot.has_flange


@pytest.mark.parametrize("name", builtin_robots())
def test_standard_to_modified_and_back_keeps_fk(name: str) -> None:
    robot = load_robot(name)
    mod = robot.to_modified_dict()
    assert mod["convention"] == "modified" and mod["joints"][0]["a_mm"] == 0.0
    back = RobotDescription.from_dict(mod, source="mod")
    q = np.random.default_rng(4).uniform(-2, 2, (30, robot.dof))
    assert np.abs(_positions(back, q) - _positions(robot, q)).max() < 1e-12
    # the modified table itself, evaluated by Craig's formula (uncoupled robots: q = theta)
    if all(j.sign == 1 and j.coupled_to is None for j in robot.joints):
        m = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
        _, R, o = m.flange_poses(q, m.nominal_params())
        # the flange point (tool 0) sits at Craig's frame n, then the flange transform
        flange = np.array(mod.get("flange_xyz_mm", [0.0, 0.0, 0.0])) * 1e-3
        plain = dict(mod, tool_mm=[0.0, 0.0, 0.0])
        for k in range(5):
            o_n = _craig_fk(plain, q[k])
            R_n = R[k] @ np.linalg.inv(back.T_dhn_flange[:3, :3])
            assert np.abs(o_n + R_n @ flange - o[k]).max() < 1e-12
    # and through the TOML text
    text = robot_to_toml(back)
    again = RobotDescription.from_dict(tomllib.loads(text))
    assert np.abs(_positions(again, q) - _positions(robot, q)).max() < 1e-12


def test_bad_convention_is_one_clear_error() -> None:
    data = tomllib.loads(CRAIG)
    data["convention"] = "craig"
    with pytest.raises(ConfigError, match=r"convention.*standard.*modified"):
        RobotDescription.from_dict(data, source="c.toml")


_LEN = st.floats(-800.0, 800.0)
_ANG = st.floats(-180.0, 180.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(_LEN, _ANG, _LEN, _ANG), min_size=1, max_size=7),
       st.integers(0, 2**31))
def test_random_modified_tables_match_craig(rows: list[tuple[float, float, float, float]],
                                            seed: int) -> None:
    data = {"name": "random", "convention": "modified", "tool_mm": [5.0, -3.0, 40.0],
            "joints": [{"a_mm": a, "alpha_deg": al, "d_mm": d, "theta_offset_deg": th,
                        "min_deg": -180.0, "max_deg": 180.0} for a, al, d, th in rows]}
    robot = RobotDescription.from_dict(data, source="random.toml")
    q = np.random.default_rng(seed).uniform(-3, 3, (3, len(rows)))
    p = _positions(robot, q)
    for k in range(len(q)):
        assert np.abs(p[k] - _craig_fk(data, q[k])).max() < 1e-12
    back = RobotDescription.from_dict(robot.to_modified_dict())
    assert np.abs(_positions(back, q) - p).max() < 1e-12


def test_model_file_keeps_base_and_flange_transforms(tmp_path) -> None:
    robot = RobotDescription.from_dict(tomllib.loads(CRAIG), source="craig.toml")
    robot = RobotDescription.from_dict(dict(robot.to_dict(), flange_xyz_mm=[1.0, 2.0, 3.0],
                                            flange_rpy_deg=[10.0, -20.0, 30.0]))
    assert robot.has_base and robot.has_flange
    model = KinematicModel(robot, ErrorModelSpec.constant(robot.dof))
    x = model.nominal_params()
    x[9:] = np.random.default_rng(0).normal(0, 1e-3, model.size - 9)
    path = tmp_path / "model.json"
    CalibratedModel(model=model, params=x).save(path)
    back = CalibratedModel.load(path)
    q = np.random.default_rng(1).uniform(-1, 1, (10, robot.dof))
    assert np.abs(back.predict(q) - model.positions(q, x)).max() < 1e-12
