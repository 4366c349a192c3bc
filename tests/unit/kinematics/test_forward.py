"""Forward kinematics against hand-computed poses and an independent 4x4 implementation."""

from __future__ import annotations

import numpy as np
import pytest

from robocal.kinematics import ErrorModelSpec, KinematicModel, builtin_robots, load_robot

from .reference import chain


def _nominal(name: str) -> tuple[KinematicModel, np.ndarray]:
    robot = load_robot(name)
    m = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    x = m.nominal_params()
    x[6:9] = 0.0
    return m, x


def test_lrmate200i_zero_pose_by_hand() -> None:
    # upper arm vertical (350 + 250 + 75 above the floor), forearm horizontal: 150 + 290 + 80
    m, x = _nominal("fanuc_lrmate200i")
    _, R, o = m.flange_poses(np.zeros((1, 6)), x)
    np.testing.assert_allclose(o[0], [0.520, 0.0, 0.675], atol=1e-12)
    # flange z axis points forward (+x) at the zero pose
    np.testing.assert_allclose(R[0][:, 2], [1.0, 0.0, 0.0], atol=1e-12)


def test_lrmate200i_j1_quarter_turn_and_j2_coupling() -> None:
    m, x = _nominal("fanuc_lrmate200i")
    q = np.zeros((1, 6))
    q[0, 0] = np.pi / 2
    np.testing.assert_allclose(m.flange_poses(q, x)[2][0], [0.0, 0.520, 0.675], atol=1e-12)
    # FANUC J3 is measured from horizontal: tilting J2 alone keeps the forearm horizontal
    q = np.zeros((1, 6))
    q[0, 1] = np.radians(30.0)
    o = m.flange_poses(q, x)[2][0]
    expect = [0.150 + 0.250 * np.sin(np.radians(30)) + 0.290 + 0.080,
              0.0, 0.350 + 0.250 * np.cos(np.radians(30)) + 0.075]
    np.testing.assert_allclose(o, expect, atol=1e-12)


def test_ur10_zero_pose_by_hand() -> None:
    m, x = _nominal("ur10")
    o = m.flange_poses(np.zeros((1, 6)), x)[2][0]
    np.testing.assert_allclose(o, [-1.1843, -0.256141, 0.0116], atol=1e-9)


@pytest.mark.parametrize("name", builtin_robots())
def test_matches_reference_chain(name: str, rng: np.random.Generator) -> None:
    m, x = _nominal(name)
    x[6:9] = [0.01, -0.02, 0.07]
    q = rng.uniform(m.robot.joint_limits[:, 0], m.robot.joint_limits[:, 1], (20, m.robot.dof))
    p, R, _ = m.flange_poses(q, x)
    for i in range(len(q)):
        pr, T = chain(m.robot, q[i], tool=x[6:9])
        np.testing.assert_allclose(p[i], pr, atol=1e-12)
        np.testing.assert_allclose(R[i], T[:3, :3], atol=1e-12)


def test_base_reference_and_correction(rng: np.random.Generator) -> None:
    robot = load_robot("fanuc_lrmate200id")
    T_ref = np.eye(4)
    T_ref[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    T_ref[:3, 3] = [1.5, 0.2, -0.3]
    m = KinematicModel(robot, ErrorModelSpec(robot.dof, ()), T_ref)
    x = m.nominal_params()
    x[:6] = [0.001, -0.002, 0.003, 0.001, 0.002, -0.003]
    q = rng.uniform(-1, 1, (5, 6))
    Tb = m.base_transform(x)
    for i in range(5):
        pr, _ = chain(robot, q[i], base=Tb, tool=x[6:9])
        np.testing.assert_allclose(m.positions(q[i:i + 1], x)[0], pr, atol=1e-12)
    m2, x2 = m.rebased(x)
    np.testing.assert_allclose(m2.positions(q, x2), m.positions(q, x), atol=1e-12)
