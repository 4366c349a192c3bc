"""The virtual robot and tracker: determinism, noise model, planted magnitudes."""

from __future__ import annotations

import numpy as np
import pytest

from robocal.errors import ConfigError
from robocal.simulation import SCENARIOS, TrackerNoise, VirtualCell


def test_seeded_and_deterministic(rng: np.random.Generator) -> None:
    a = VirtualCell.create("fanuc_lrmate200i", "paper", seed=4)
    b = VirtualCell.create("fanuc_lrmate200i", "paper", seed=4)
    np.testing.assert_array_equal(a.truth_params, b.truth_params)
    c = VirtualCell.create("fanuc_lrmate200i", "paper", seed=5)
    assert not np.array_equal(a.truth_params, c.truth_params)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_nominal_error_magnitude(scenario: str, rng: np.random.Generator) -> None:
    cell = VirtualCell.create("fanuc_lrmate200i", scenario, seed=2)
    e = cell.nominal_error(cell.random_joints(300, rng))
    rms = float(np.sqrt(np.mean(e**2)))
    if scenario == "nominal":
        assert rms < 1e-12
    else:
        assert 0.3e-3 < rms < 3e-3  # robots are accurate to 0.5-2 mm


def test_tracker_noise_is_anisotropic(rng: np.random.Generator) -> None:
    noise = TrackerNoise()
    p = np.tile([[3.0, 0.0, 0.0]], (20000, 1))
    e = noise.sample(p, rng)
    sr, st = noise.sigmas(p[:1])
    assert np.std(e[:, 0]) == pytest.approx(sr[0], rel=0.05)   # along the beam
    assert np.std(e[:, 1]) == pytest.approx(st[0], rel=0.05)   # across it
    assert sr[0] == pytest.approx(5e-6 + 1.5e-6) and st[0] == pytest.approx(7.5e-6 + 9e-6)


def test_outliers_are_millimetres(rng: np.random.Generator) -> None:
    cell = VirtualCell.create("ur10", "constant", seed=1)
    q = cell.random_joints(100, rng)
    _, p, _, idx = cell.simulate(q, rng, outlier_fraction=0.05)
    clean = cell.reflector_position(q)
    d = np.linalg.norm(p - clean, axis=1)
    assert len(idx) == 5
    assert np.all(d[idx] > 0.9e-3) and np.all(np.delete(d, idx) < 2e-4)


def test_unknown_scenario() -> None:
    with pytest.raises(ConfigError, match="unknown scenario"):
        VirtualCell.create("ur10", "wobbly")


def test_planted_joint_drift_moves_the_arm_not_the_joints_read_back():
    import numpy as np

    from robocal.simulation import VirtualCell

    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=1)
    q = np.radians([[10.0, 20.0, -30.0, 40.0, -50.0, 60.0]])
    p0 = cell.reflector_position(q)
    cell.drift_deg_per_day = (0.0, 0.01)
    assert np.allclose(cell.reflector_position(q), p0)  # day 0: no drift yet
    cell.sim_days = 5.0
    expected = cell.truth_model.positions(q + np.radians([0, 0.05, 0, 0, 0, 0]),
                                          cell.truth_params)
    assert np.allclose(cell.reflector_position(q), expected)
    assert 1e-4 < np.linalg.norm(cell.reflector_position(q) - p0) < 2e-3
    rng = np.random.default_rng(0)
    assert np.allclose(cell.actual_joints(q, rng), q, atol=1e-4)
