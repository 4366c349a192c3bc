"""Identifiability analysis at the actual poses (position-only, one reflector)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robocal.errors import NotIdentifiable
from robocal.identification import FitOptions, fit, identifiability
from robocal.kinematics import ErrorModelSpec, KinematicModel, Term, load_robot

from .conftest import make_data


def _random_q(robot, n, seed):
    lim = robot.joint_limits
    return np.random.default_rng(seed).uniform(lim[:, 0], lim[:, 1], (n, robot.dof))


def test_6r_constant_model_has_27_identifiable_parameters():
    robot = load_robot("fanuc_lrmate200i")
    model = KinematicModel(robot, ErrorModelSpec.constant(6))
    assert model.size == 45                       # 36 joint constants + 6 base + 3 tool
    q = _random_q(robot, 250, 0)
    rank, cond, removed, sv = identifiability(model, q, model.nominal_params())
    assert rank == 27
    assert len(removed) == 45 - 27
    assert all(n.endswith(".const") for n in removed)  # base and tool are all kept
    assert np.all(np.diff(sv) <= 1e-12)               # descending
    assert cond == pytest.approx(sv[0] / sv[rank - 1])
    # the kept columns are independent, every removed column lies in their span
    _, J = model.jacobian(q, model.nominal_params())
    J = J.reshape(-1, model.size)
    J = J / np.linalg.norm(J, axis=0)
    kept = [i for i, n in enumerate(model.names) if n not in removed]
    assert np.linalg.matrix_rank(J[:, kept], tol=1e-8) == 27
    for name in removed:
        col = J[:, model.names.index(name)]
        coef = np.linalg.lstsq(J[:, kept], col, rcond=None)[0]
        assert np.linalg.norm(J[:, kept] @ coef - col) < 1e-8


def test_first_harmonics_add_8_per_joint_and_2_for_the_last():
    robot = load_robot("fanuc_lrmate200i")
    model = KinematicModel(robot, ErrorModelSpec.build(6, fourier=1))
    rank, _, removed, _ = identifiability(model, _random_q(robot, 250, 1), model.nominal_params())
    assert rank == 27 + 5 * 8 + 2
    # lower orders are kept first: no constant term is removed in favour of a harmonic
    const_removed = {n for n in removed if n.endswith(".const")}
    assert len(const_removed) == 18


def test_reflector_on_the_last_axis_loses_two_parameters():
    robot = dataclasses.replace(load_robot("fanuc_lrmate200i"), tool=(0.0, 0.0, 0.06))
    model = KinematicModel(robot, ErrorModelSpec.constant(6))
    rank, _, removed, _ = identifiability(model, _random_q(robot, 250, 2), model.nominal_params())
    assert rank == 25
    assert "j6.ex.const" in removed and "j6.ey.const" in removed


def test_restricted_to_named_parameters():
    robot = load_robot("fanuc_lrmate200i")
    model = KinematicModel(robot, ErrorModelSpec.constant(6))
    names = [*model.names[:9], "j2.ez.const"]
    rank, _, removed, _ = identifiability(model, _random_q(robot, 50, 3), model.nominal_params(),
                                          params=names)
    assert rank == 10 and removed == []


def test_single_pose_cannot_identify_a_base():
    robot = load_robot("fanuc_lrmate200i")
    model = KinematicModel(robot, ErrorModelSpec(6, ()))
    rank, _, removed, _ = identifiability(model, _random_q(robot, 1, 4), model.nominal_params())
    assert rank == 3 and len(removed) == 6


def test_fit_reports_removed_parameters_by_name(paper_data):
    res = fit(paper_data.cell.robot, paper_data.train, "constant")
    assert res.rank == 27
    assert len(res.removed) == 18
    assert res.calibrated.fit["identifiability"]["removed"] == res.removed
    # held at zero, with zero variance
    idx = [res.calibrated.model.names.index(n) for n in res.removed]
    assert np.all(res.calibrated.params[idx] == 0.0)
    assert np.all(np.diag(res.calibrated.covariance)[idx] == 0.0)


def test_too_few_poses_for_the_model_is_a_clear_error(paper_data):
    few = paper_data.train.subset(np.arange(9))
    with pytest.raises(NotIdentifiable, match="too few poses"):
        fit(paper_data.cell.robot, few, "constant")
    with pytest.raises(NotIdentifiable, match="too few poses"):
        fit(paper_data.cell.robot, paper_data.train.subset(np.arange(40)), "high-order")


def test_near_redundant_parallel_axis_offsets_are_held():
    # UR10: joints 2-4 are parallel; offsets along them are identifiable only through tiny
    # second-order effects. Structurally 27, numerically (default threshold) fewer.
    robot = load_robot("ur10")
    model = KinematicModel(robot, ErrorModelSpec.constant(6))
    lim = np.radians([[-300, -190], [-185, -90], [5, 130], [-250, 300], [5, 145], [-300, 150]])
    q = np.random.default_rng(5).uniform(lim[:, 0], lim[:, 1], (300, 6))
    strict = identifiability(model, q, model.nominal_params(), tol=1e-9)
    default = identifiability(model, q, model.nominal_params())
    assert strict.rank == 27
    assert default.rank < 27
    assert default.rank == int(np.sum(strict.singular_values / strict.singular_values[0]
                                      > FitOptions().rank_tol))


def test_gravity_term_is_identifiable_with_masses():
    robot = load_robot("ur10")
    spec = ErrorModelSpec.constant(6).with_terms([Term(1, "ez", "gravity")])
    model = KinematicModel(robot, spec)
    q = _random_q(robot, 200, 6)
    rank, _, removed, _ = identifiability(model, q, model.nominal_params())
    assert "j2.ez.gravity" not in removed
    base = identifiability(KinematicModel(robot, ErrorModelSpec.constant(6)), q,
                           np.r_[model.nominal_params()[:-1]])
    assert rank == base.rank + 1


def test_make_data_helper_is_deterministic():
    a = make_data("fanuc_lrmate200i", "constant", seed=3, n_train=20, n_val=5)
    b = make_data("fanuc_lrmate200i", "constant", seed=3, n_train=20, n_val=5)
    assert a.train.digest() == b.train.digest()
