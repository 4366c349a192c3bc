"""Batch compensation on the identified model, and the acceptance criterion of issue 4."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from robocal.compensation import compensate, rotation_error
from robocal.errors import ConfigError
from robocal.kinematics import (
    CalibratedModel,
    ErrorModelSpec,
    KinematicModel,
    RobotDescription,
    euler_xyz_to_matrix,
)
from robocal.simulation import VirtualCell

Fit = tuple[VirtualCell, CalibratedModel]


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2)))


def _program(cell: VirtualCell, cal: CalibratedModel, n: int, rng: np.random.Generator
             ) -> tuple[np.ndarray, np.ndarray]:
    """Program joints inside the calibrated range and the targets a nominal controller with
    perfectly registered frames believes they reach (tracker frame)."""
    assert cal.coverage is not None
    cov = cal.coverage
    q = rng.uniform(cov[:, 0] + 0.05, cov[:, 1] - 0.05, (n, cell.robot.dof))
    nom = KinematicModel(cell.robot, ErrorModelSpec(cell.robot.dof, ()), cell.T_tracker_base)
    x = nom.nominal_params()
    x[6:9] = cell.truth_params[6:9]
    return q, nom.positions(q, x)


def test_acceptance_virtual_lrmate(paper_fit: Fit) -> None:
    """Compensated targets executed on the true robot land within 1.5x the model's own
    prediction error + 3 um (RMS); the uncompensated program is reported beside it."""
    cell, cal = paper_fit
    rng = np.random.default_rng(2)
    q_prog, p_target = _program(cell, cal, 400, rng)
    res = compensate(cal, p_target, q_prog)
    ok = res.ok
    assert ok.mean() > 0.98, res.counts()
    assert res.residual_m[ok].max() < 1e-6                  # below 1 um under the model
    assert np.median(res.iterations) <= 3
    q_c = res.q[ok]
    landed = cell.reflector_position(cell.actual_joints(q_c, rng))   # with repeatability
    err = _rms(np.linalg.norm(landed - p_target[ok], axis=1))
    model_err = _rms(np.linalg.norm(cal.predict(q_c) - cell.reflector_position(q_c), axis=1))
    uncomp = _rms(np.linalg.norm(
        cell.reflector_position(cell.actual_joints(q_prog, rng)) - p_target, axis=1))
    print(f"\nacceptance: compensated RMS {err * 1e6:.2f} um, model prediction error "
          f"{model_err * 1e6:.2f} um, uncompensated {uncomp * 1e6:.1f} um "
          f"({int(ok.sum())}/{len(ok)} ok, {int(res.orientation_relaxed.sum())} relaxed)")
    assert err <= 1.5 * model_err + 3e-6
    assert uncomp > 20 * err


def test_model_pose_matches_target_and_seed_orientation(paper_fit: Fit) -> None:
    cell, cal = paper_fit
    rng = np.random.default_rng(3)
    q_prog, p_target = _program(cell, cal, 200, rng)
    res = compensate(cal, p_target, q_prog)
    ok = res.ok
    np.testing.assert_allclose(cal.predict(res.q[ok]), p_target[ok], atol=1e-7)
    keep = ok & ~res.orientation_relaxed
    assert keep.mean() > 0.9
    _, R_c, _ = cal.model.flange_poses(res.q[keep], cal.params)
    _, R_s, _ = cal.model.flange_poses(q_prog[keep], cal.params)
    assert np.linalg.norm(rotation_error(R_s, R_c), axis=1).max() < 1e-6
    assert res.rotation_residual_rad[keep].max() < 1e-6
    lim = cell.robot.joint_limits
    assert np.all((res.q[ok] >= lim[:, 0]) & (res.q[ok] <= lim[:, 1]))


def test_orientation_targets_are_met(paper_fit: Fit) -> None:
    _, cal = paper_fit
    rng = np.random.default_rng(4)
    assert cal.coverage is not None
    cov = cal.coverage
    q_true = rng.uniform(cov[:, 0] + 0.1, cov[:, 1] - 0.1, (100, 6))
    p, R, _ = cal.model.flange_poses(q_true, cal.params)
    res = compensate(cal, p, q_true + rng.normal(0, 0.02, q_true.shape), R_targets=R)
    ok = res.ok
    assert ok.mean() > 0.95 and not res.orientation_relaxed.any()
    assert res.rotation_residual_rad[ok].max() < 1e-6
    # a full pose has one solution per branch: the seed's branch gives back q_true
    near = np.abs(res.q[ok] - q_true[ok]).max(axis=1) < 1e-4
    assert near.mean() > 0.95


def test_batch_equals_one_by_one(paper_fit: Fit) -> None:
    cell, cal = paper_fit
    q_prog, p_target = _program(cell, cal, 6, np.random.default_rng(5))
    batch = compensate(cal, p_target, q_prog)
    for i in range(6):
        one = compensate(cal, p_target[i], q_prog[i])
        assert one.status[0] == batch.status[i]
        np.testing.assert_allclose(one.q_last[0], batch.q_last[i], atol=1e-9)


def test_failures_are_reported_not_returned(paper_fit: Fit) -> None:
    cell, cal = paper_fit
    q_prog, p_target = _program(cell, cal, 3, np.random.default_rng(6))
    p_target[1] = [5.0, 5.0, 5.0]                          # far outside the workspace
    res = compensate(cal, p_target, q_prog)
    assert list(res.status) == ["ok", "unreachable", "ok"]
    assert np.isnan(res.q[1]).all() and np.isfinite(res.q_last[1]).all()
    assert res.residual_m[1] > 1.0
    assert res.counts() == {"ok": 2, "not-converged": 0, "out-of-limits": 0, "unreachable": 1}


def test_joint_limits_are_respected(paper_fit: Fit) -> None:
    """A target that needs J1 beyond a (narrowed) limit is reported, not clipped silently."""
    _, cal = paper_fit
    joints = list(cal.robot.joints)
    joints[0] = dataclasses.replace(joints[0], q_min=-math.radians(135),
                                    q_max=math.radians(135))
    robot = RobotDescription(name="narrow", joints=tuple(joints))
    narrow = CalibratedModel(KinematicModel(robot, cal.model.spec, cal.model.T_ref),
                             cal.params)
    q_true = np.array([[math.radians(155), 0.6, 0.1, 0.3, -0.8, 0.4]])
    p = cal.model.positions(q_true, cal.params)
    seed = q_true.copy()
    seed[0, 0] = math.radians(134)
    res = compensate(narrow, p, seed)
    assert res.status[0] == "out-of-limits"
    assert np.isnan(res.q[0]).all()
    assert res.q_last[0, 0] <= math.radians(135) + 1e-12


def test_outside_coverage_uses_the_fallback(paper_fit: Fit) -> None:
    cell, cal = paper_fit
    assert cal.fallback is not None
    cover = cell.robot.joint_limits.copy()
    cover[0] = [-1.0, 1.0]                                  # J1 calibrated over +-57 deg only
    cm = CalibratedModel(cal.model, cal.params, coverage=cover, fallback=cal.fallback)
    q = np.array([[1.4, 0.5, 0.2, 0.4, -0.6, 0.3], [0.2, 0.5, 0.2, 0.4, -0.6, 0.3]])
    p = cm.predict(q) + 2e-4
    res = compensate(cm, p, q)
    assert res.ok.all()
    assert list(res.in_coverage) == [False, True]
    np.testing.assert_allclose(cm.predict(res.q), p, atol=1e-7)
    # the fallback really differs from the high-order model there
    assert np.linalg.norm(cal.model.positions(res.q[:1], cal.params) - p[:1]) > 1e-6


def test_ur10_starts_from_the_seed(rng: np.random.Generator) -> None:
    cell = VirtualCell.create("ur10", "constant", seed=2)
    cal = CalibratedModel(cell.truth_model, cell.truth_params)
    q = cell.random_joints(100, rng, margin_rad=0.2)
    p = cal.predict(q) + rng.normal(0, 5e-4, (100, 3))
    res = compensate(cal, p, q)
    assert res.ok.mean() > 0.95
    np.testing.assert_allclose(cal.predict(res.q[res.ok]), p[res.ok], atol=1e-7)
    np.testing.assert_array_equal(res.q_start, q)
    far = compensate(cal, np.array([[10.0, 0.0, 0.0]]), q[:1])
    assert far.status[0] == "unreachable"


@pytest.mark.parametrize("start", ["seed", "nominal"])
def test_other_starts(paper_fit: Fit, start: str) -> None:
    cell, cal = paper_fit
    q_prog, p_target = _program(cell, cal, 50, np.random.default_rng(8))
    res = compensate(cal, p_target, q_prog, start=start)
    assert res.ok.mean() > 0.95
    assert res.residual_m[res.ok].max() < 1e-7


def test_rotation_error_inverts_exp(rng: np.random.Generator) -> None:
    def exp(w: np.ndarray) -> np.ndarray:
        a = np.linalg.norm(w)
        k = w / a
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K

    R = np.stack([euler_xyz_to_matrix(*rng.uniform(-3, 3, 3)) for _ in range(40)])
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(1e-9, 3.0, 30), np.full(10, math.pi - 1e-5)])
    W = axes * angles[:, None]
    R_t = np.stack([exp(w) @ r for w, r in zip(W, R, strict=True)])
    np.testing.assert_allclose(rotation_error(R_t, R), W, atol=1e-6)
    assert np.abs(rotation_error(R, R)).max() < 1e-12


def test_bad_inputs(paper_fit: Fit) -> None:
    _, cal = paper_fit
    with pytest.raises(ConfigError, match="shape"):
        compensate(cal, np.zeros((2, 2)), np.zeros((2, 6)))
    with pytest.raises(ConfigError, match="seed"):
        compensate(cal, np.zeros((2, 3)), np.zeros((2, 5)))
    with pytest.raises(ConfigError, match="finite"):
        compensate(cal, np.full((1, 3), np.nan), np.zeros((1, 6)))
    with pytest.raises(ConfigError, match="rotation"):
        compensate(cal, np.zeros((1, 3)), np.zeros((1, 6)), R_targets=2 * np.eye(3))
    with pytest.raises(ConfigError, match="start"):
        compensate(cal, np.zeros((1, 3)), np.zeros((1, 6)), start="guess")
    empty = compensate(cal, np.zeros((0, 3)), np.zeros((0, 6)))
    assert len(empty) == 0 and empty.counts()["ok"] == 0


def test_targets_near_the_wrist_singularity_keep_small_corrections(paper_fit: Fit) -> None:
    """Holding the seed's orientation at J5 ~ 0 turns J4/J6 a long way; with
    ``max_change_deg`` such targets are solved for position alone, with small corrections,
    and still land on the target on the true robot."""
    cell, cal = paper_fit
    rng = np.random.default_rng(8)
    q_prog, p_target = _program(cell, cal, 60, rng)
    q_prog[:, 4] = rng.uniform(-0.002, 0.002, len(q_prog))  # wrist straight
    nom = KinematicModel(cell.robot, ErrorModelSpec(cell.robot.dof, ()), cell.T_tracker_base)
    x = nom.nominal_params()
    x[6:9] = cell.truth_params[6:9]
    p_target = nom.positions(q_prog, x)
    full = compensate(cal, p_target, q_prog)
    bounded = compensate(cal, p_target, q_prog, max_change_deg=3.0)
    change = np.degrees(np.abs(full.q - q_prog).max(axis=1))
    assert np.nanmax(change) > 10.0          # the 6-D answer swings the wrist
    ok = bounded.ok
    assert ok.all()
    assert np.degrees(np.abs(bounded.q - q_prog).max()) <= 3.0
    relaxed = bounded.orientation_relaxed
    assert relaxed[change > 3.0].all() and relaxed.sum() < len(relaxed)
    np.testing.assert_allclose(cal.predict(bounded.q[ok]), p_target[ok], atol=1e-7)
    landed = cell.reflector_position(bounded.q[ok])
    err = _rms(np.linalg.norm(landed - p_target[ok], axis=1))
    model_err = _rms(np.linalg.norm(cal.predict(bounded.q[ok])
                                    - cell.reflector_position(bounded.q[ok]), axis=1))
    assert err <= 1.5 * model_err + 3e-6
