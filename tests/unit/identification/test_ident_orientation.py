"""6-DoF measurements: orientation residuals weighted by their own sigmas (virtual cell)."""

from __future__ import annotations

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.identification import fit
from robocal.identification._solver import rotation_vectors
from robocal.identification._weights import euler_xyz_matrices, orientation_whitening
from robocal.kinematics import euler_xyz_to_matrix, matrix_to_euler_xyz
from robocal.simulation import VirtualCell

SIGMA_ROT = np.radians(0.005)


def _six_dof(cell: VirtualCell, n: int, rng: np.random.Generator,
             R_tool: np.ndarray) -> MeasurementSet:
    """Positions as the virtual tracker measures them plus probe orientations (noisy)."""
    q, p, _, _ = cell.simulate(cell.random_joints(n, rng), rng)
    _, R, _ = cell.truth_model.flange_poses(q, cell.truth_params)
    rot = []
    for k in range(n):
        noise = euler_xyz_to_matrix(*rng.normal(0.0, SIGMA_ROT, 3))
        rot.append(matrix_to_euler_xyz(noise @ R[k] @ R_tool))
    return MeasurementSet(q, p, rot=np.array(rot), rot_sigma=np.full((n, 3), SIGMA_ROT))


def test_orientation_lets_fewer_poses_reach_the_accuracy() -> None:
    R_tool = euler_xyz_to_matrix(1.2, -0.4, 2.0)       # probe turned arbitrarily on the flange
    gains = []
    for seed in range(3):
        cell = VirtualCell.create("ur10", "constant", seed=seed)
        rng = np.random.default_rng(50 + seed)
        train = _six_dof(cell, 14, rng, R_tool)
        val = _six_dof(cell, 300, rng, R_tool).without_orientation()
        pos = fit(cell.robot, train.without_orientation(), "constant", validation=val)
        six = fit(cell.robot, train, "constant", validation=val)
        assert six.validation.rms_m < pos.validation.rms_m
        gains.append(six.validation.rms_m / pos.validation.rms_m)
    assert float(np.mean(gains)) < 0.95          # measured: 0.78, 0.98, 0.93


def test_orientation_residuals_reach_the_noise_level() -> None:
    cell = VirtualCell.create("ur10", "constant", seed=4)
    rng = np.random.default_rng(4)
    R_tool = euler_xyz_to_matrix(0.3, 0.2, -1.0)
    train = _six_dof(cell, 120, rng, R_tool)
    res = fit(cell.robot, train, "constant")
    cal = res.calibrated
    _, R, _ = cal.model.flange_poses(train.q, cal.params)
    R_meas = euler_xyz_matrices(train.rot)
    # the fitted flange orientation explains the measured one up to one constant rotation
    M = np.einsum("nji,njk->ik", R, R_meas)
    U, _, Vt = np.linalg.svd(M)
    R_fit = U @ Vt
    d = rotation_vectors(R_meas, R @ R_fit)
    rms = float(np.sqrt(np.mean(np.sum(d * d, axis=1)) / 3))
    assert rms < 2.0 * SIGMA_ROT
    # without orientation the rotation about the last axis is not observable at all
    pos = fit(cell.robot, train.without_orientation(), "constant").calibrated
    _, R_pos, _ = pos.model.flange_poses(train.q, pos.params)
    U, _, Vt = np.linalg.svd(np.einsum("nji,njk->ik", R_pos, R_meas))
    d_pos = rotation_vectors(R_meas, R_pos @ (U @ Vt))
    assert float(np.sqrt(np.mean(np.sum(d_pos * d_pos, axis=1)) / 3)) > 5.0 * rms


def test_orientation_whitening_matches_the_angle_covariance() -> None:
    rng = np.random.default_rng(0)
    rot = rng.uniform(-1.2, 1.2, (4, 3))
    sig = rng.uniform(1e-5, 1e-4, (4, 3))
    W = orientation_whitening(rot, sig)
    # Monte Carlo: whitened rotation-vector perturbations of noisy angles have unit covariance
    for k in range(4):
        da = rng.normal(0.0, 1.0, (20000, 3)) * sig[k]
        R0 = euler_xyz_matrices(rot[k][None])
        R = euler_xyz_matrices(rot[k] + da)
        w = rotation_vectors(R, np.broadcast_to(R0, R.shape)) @ W[k].T
        assert np.allclose(np.cov(w.T), np.eye(3), atol=0.05)
    iso = orientation_whitening(rot, None, default_sigma=2e-4)
    assert np.allclose(iso, np.eye(3) / 2e-4)


def test_rot_sigma_without_rot_is_refused() -> None:
    from robocal.errors import DataError

    with pytest.raises(DataError, match="rot_sigma given without rot"):
        MeasurementSet(np.zeros((2, 6)), np.zeros((2, 3)), rot_sigma=np.ones((2, 3)))
