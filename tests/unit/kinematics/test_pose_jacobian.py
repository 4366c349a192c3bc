"""pose_jacobian (position + flange angular rows) and Jacobians of robots with base/flange
transforms, against central differences."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robocal.kinematics import ErrorModelSpec, KinematicModel, load_robot

FIXTURE = Path(__file__).parent / "fixtures" / "ur10_ur_description.urdf"


@pytest.mark.parametrize("robot", ["ur10", str(FIXTURE), "fanuc_lrmate200i"])
def test_pose_jacobian_matches_finite_differences(robot: str) -> None:
    rob = load_robot(robot)
    model = KinematicModel(rob, ErrorModelSpec.build(rob.dof, poly=1, fourier=1))
    rng = np.random.default_rng(3)
    x = model.nominal_params()
    x[:6] = rng.normal(0, 1e-2, 6)
    x[9:] = rng.normal(0, 1e-3, model.size - 9)
    q = rng.uniform(-2, 2, (4, rob.dof))
    p, R, J = model.pose_jacobian(q, x)
    p2, J2 = model.jacobian(q, x)
    assert np.array_equal(p, p2) and np.allclose(J[:, :3], J2, rtol=0, atol=1e-15)
    h = 1e-6
    for k in range(model.size):
        dx = np.zeros(model.size)
        dx[k] = h
        pa, Ra, _ = model.flange_poses(q, x + dx)
        pb, Rb, _ = model.flange_poses(q, x - dx)
        assert np.abs((pa - pb) / (2 * h) - J[:, :3, k]).max() < 1e-7
        S = np.einsum("nij,nkj->nik", (Ra - Rb) / (2 * h), R)     # skew(omega)
        omega = np.stack([S[:, 2, 1], S[:, 0, 2], S[:, 1, 0]], axis=1)
        assert np.abs(omega - J[:, 3:, k]).max() < 1e-7
