"""Analytic Jacobians against central finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from robocal.kinematics import ErrorModelSpec, KinematicModel, builtin_robots, load_robot


def _rich_model(name: str, gravity: bool) -> KinematicModel:
    robot = load_robot(name)
    spec = ErrorModelSpec.build(
        robot.dof, poly=2, fourier=2, strain_wave=(1, 2), gear_ratios=robot.gear_ratios,
        map_spacing_deg=15.0, gravity=gravity and robot.has_masses)
    return KinematicModel(robot, spec)


def _params(m: KinematicModel, rng: np.random.Generator) -> np.ndarray:
    x = m.nominal_params() + rng.normal(0.0, 2e-3, m.size)
    grav = [i for i, n in enumerate(m.names) if n.endswith("gravity")]
    x[grav] = 1e-5
    return x


@pytest.mark.parametrize("name", builtin_robots())
def test_parameter_jacobian(name: str, rng: np.random.Generator) -> None:
    m = _rich_model(name, gravity=True)
    x = _params(m, rng)
    lim = m.robot.joint_limits
    q = rng.uniform(lim[:, 0], lim[:, 1], (6, m.robot.dof))
    p, J = m.jacobian(q, x)
    np.testing.assert_allclose(p, m.positions(q, x), atol=1e-15)
    h = 1e-6
    for k in range(m.size):
        e = np.zeros(m.size)
        e[k] = h
        num = (m.positions(q, x + e) - m.positions(q, x - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], num, atol=5e-8, err_msg=m.names[k])


@pytest.mark.parametrize("name", builtin_robots())
def test_joint_jacobian(name: str, rng: np.random.Generator) -> None:
    m = _rich_model(name, gravity=False)
    x = _params(m, rng)
    lim = m.robot.joint_limits
    q = rng.uniform(lim[:, 0], lim[:, 1], (6, m.robot.dof))
    _, R, J = m.joint_jacobian(q, x)
    h = 1e-6
    for k in range(m.robot.dof):
        dq = np.zeros(m.robot.dof)
        dq[k] = h
        pp, Rp, _ = m.flange_poses(q + dq, x)
        pm, Rm, _ = m.flange_poses(q - dq, x)
        np.testing.assert_allclose(J[:, :3, k], (pp - pm) / (2 * h), atol=5e-8)
        W = ((Rp - Rm) / (2 * h)) @ np.transpose(R, (0, 2, 1))
        w = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=1)
        np.testing.assert_allclose(J[:, 3:, k], w, atol=5e-8)


def test_constant_model_has_45_parameters() -> None:
    robot = load_robot("fanuc_lrmate200i")
    m = KinematicModel(robot, ErrorModelSpec.constant(robot.dof))
    assert m.size == 45
    assert m.names[:9] == ("base.dx", "base.dy", "base.dz", "base.ex", "base.ey", "base.ez",
                           "tool.x", "tool.y", "tool.z")
    # rank of the position Jacobian at random poses: 4 per joint x 6 + 6 - 3 = 27
    rng = np.random.default_rng(0)
    lim = robot.joint_limits
    q = rng.uniform(lim[:, 0], lim[:, 1], (250, 6))
    _, J = m.jacobian(q, m.nominal_params())
    A = J.reshape(-1, m.size)
    A = A / np.linalg.norm(A, axis=0)
    s = np.linalg.svd(A, compute_uv=False)
    assert int(np.sum(s > 1e-6 * s[0])) == 27
