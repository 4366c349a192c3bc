"""Solver status, degenerate data, pose-count agreement with the planner (issue 14)."""

from __future__ import annotations

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.errors import RobocalError
from robocal.identification import _solver as solver
from robocal.identification import fit, min_poses
from robocal.identification._models import high_order_spec
from robocal.identification._weights import TrackerSigma, whitening
from robocal.kinematics import KinematicModel, load_robot
from robocal.simulation import VirtualCell
from tests._designs import thin_j6_design


def test_min_poses_meets_the_redundancy_rule() -> None:
    for rank in (0, 1, 27, 60, 183, 400):
        n = min_poses(rank)
        assert 3 * n - rank >= max(6, int(np.ceil(0.3 * n)))
        assert n == 1 or 3 * (n - 1) - rank < max(6, int(np.ceil(0.3 * (n - 1))))


@pytest.mark.parametrize("model", ["constant", "high-order"])
def test_a_plan_of_min_poses_always_fits(model: str) -> None:
    from robocal.planning import plan_campaign

    robot = "fanuc_lrmate200i"
    probe = plan_campaign(robot, "demo", count=80, model=model, iso=False, seed=1,
                          candidates=1024)
    n = probe.observability.calibration.min_poses
    assert n == min_poses(probe.observability.calibration.identifiable)
    plan = plan_campaign(robot, "demo", count=n, model=model, iso=False, seed=1,
                         candidates=1024)
    q = plan.joint_targets("calibration")          # rad
    assert len(q) == n
    cell = VirtualCell.create(robot, "paper", seed=2)
    qm, p, s, _ = cell.simulate(q, np.random.default_rng(3))
    res = fit(robot, MeasurementSet(qm, p, s), model)
    assert res.train.n == n and res.converged
    assert min_poses(res.rank) <= n           # the planner never counts fewer than the fit


def _problem(n: int = 60) -> tuple[solver.Problem, np.ndarray]:
    cell = VirtualCell.create("fanuc_lrmate200i", "paper", seed=4)
    rng = np.random.default_rng(5)
    q, p, _, _ = cell.simulate(cell.random_joints(n, rng), rng)
    robot = load_robot("fanuc_lrmate200i")
    m = KinematicModel(robot, high_order_spec(robot, order=1), cell.T_tracker_base)
    prob = solver.Problem(m, q, p, whitening(p, TrackerSigma()))
    x0 = m.nominal_params()
    x0[6:9] = robot.tool
    return prob, x0


def test_status_is_converged_only_on_success() -> None:
    prob, x0 = _problem()
    rows = np.arange(prob.n)
    free = np.arange(prob.model.size)[:9]
    ok = solver.levenberg_marquardt(prob, x0, free, rows, max_iter=100)
    assert ok.status == solver.CONVERGED and ok.converged
    short = solver.levenberg_marquardt(prob, x0, free, rows, max_iter=1)
    assert short.status == solver.MAX_ITERATIONS and not short.converged
    bad = x0.copy()
    bad[0] = np.nan
    nf = solver.levenberg_marquardt(prob, bad, free, rows)
    assert nf.status == solver.NON_FINITE and not nf.converged


def test_non_finite_trial_steps_are_not_converged(monkeypatch: pytest.MonkeyPatch) -> None:
    prob, x0 = _problem()
    rows = np.arange(prob.n)
    free = np.arange(9)
    start = prob.cost(x0, rows)
    real_cost = prob.cost

    def cost(x: np.ndarray, r: np.ndarray) -> float:
        # the model blows up everywhere except at the start point
        return start if np.array_equal(x, x0) else float("inf")

    monkeypatch.setattr(prob, "cost", cost)
    info = solver.levenberg_marquardt(prob, x0, free, rows)
    assert info.status == solver.NON_FINITE and not info.converged
    monkeypatch.setattr(prob, "cost", lambda x, r: real_cost(x, r) + 1e-3 * start
                        * float(not np.array_equal(x, x0)))
    info = solver.levenberg_marquardt(prob, x0, free, rows)
    assert info.status == solver.NO_PROGRESS and not info.converged


def test_degenerate_data_gives_a_robocal_error_not_linalgerror() -> None:
    robot = load_robot("fanuc_lrmate200i")
    rng = np.random.default_rng(0)
    # every pose the same configuration: nothing to register or identify
    q = np.tile(np.radians([10.0, 20, -30, 40, -50, 60]), (80, 1))
    p = rng.normal(0.0, 1e-5, (80, 3)) + np.array([1.5, 0.2, 0.3])
    for model in ("constant", "high-order", "auto"):
        with pytest.raises(RobocalError):
            fit(robot, MeasurementSet(q, p), model)
    # absurd magnitudes (overflow in the kinematics): one clear error
    q2 = rng.uniform(-1.0, 1.0, (80, 6)) * 1e200
    p2 = rng.uniform(-1.0, 1.0, (80, 3)) * 1e200
    with pytest.raises(RobocalError):
        fit(robot, MeasurementSet(q2, p2), "high-order")
    # only two joints move: most parameters unobservable; either a fit or a robocal error
    q3 = np.tile(np.radians([10.0, 20, -30, 40, -50, 60]), (80, 1))
    q3[:, :2] += rng.uniform(-0.5, 0.5, (80, 2))
    p3 = VirtualCell.create("fanuc_lrmate200i", "paper", seed=1).simulate(q3, rng)[1]
    for model in ("high-order", "auto"):
        try:
            res = fit(robot, MeasurementSet(q3, p3), model)
        except RobocalError:
            continue
        assert res.status in (solver.CONVERGED, solver.MAX_ITERATIONS)
        assert len(res.removed) > 0


def test_a_run_stopped_by_max_iter_reports_how_far_from_the_minimum_it_is() -> None:
    prob, x0 = _problem()
    rows = np.arange(prob.n)
    free = np.arange(prob.model.size)[:30]
    stopped = solver.levenberg_marquardt(prob, x0, free, rows, max_iter=1)
    full = solver.levenberg_marquardt(prob, x0, free, rows, max_iter=200)
    assert stopped.status == solver.MAX_ITERATIONS and full.converged
    assert np.isnan(full.remaining)
    # the Gauss-Newton prediction of what is left is close to what the full run still gained
    left = (stopped.cost - full.cost) / stopped.cost
    assert stopped.remaining > 0 and 0.2 * left < stopped.remaining < 5 * left


def test_gauss_newton_stop_ends_at_the_same_minimum_in_fewer_steps() -> None:
    prob, x0 = _problem()
    rows = np.arange(prob.n)
    cols = np.arange(prob.model.size)
    _, keep, _ = solver.analyse_jacobian(prob, x0, rows, cols, tol=3e-4)
    free = cols[keep]
    strict = solver.levenberg_marquardt(prob, x0, free, rows, max_iter=300, gtol=0.0)
    early = solver.levenberg_marquardt(prob, x0, free, rows, max_iter=300)
    assert early.converged and strict.converged
    assert early.iterations <= strict.iterations
    assert early.cost <= strict.cost * (1 + 1e-6)


def test_fit_warns_about_extrapolated_validation_poses_and_many_screened_ones():
    """Training J6 at 0 and 2 deg only: the reflector's direction about J6 is nearly free."""
    cell, rng, train = thin_j6_design()
    qv = cell.random_joints(200, rng)
    qv[:100, 5] = np.radians(rng.choice([0.0, 2.0], 100))
    qv, pv, _, _ = cell.simulate(qv, rng)
    val = MeasurementSet(qv, pv)
    weak = fit(cell.robot, train, "constant", validation=val)
    assert len(weak.warnings) == 1
    w = weak.warnings[0]
    assert "validation poses lie where the training poses leave the model nearly free" in w
    assert "with J6 angles the training poses lack" in w
    n_far = int(w.split(" of ")[0])
    assert 60 <= n_far <= 100                 # only poses with J6 elsewhere are flagged
    # the flagged uncertainty is real: those poses are ~10x worse than the others
    e = np.linalg.norm(weak.calibrated.predict(qv) - pv, axis=1)
    assert np.sqrt(np.mean(e[100:] ** 2)) > 5 * np.sqrt(np.mean(e[:100] ** 2))
    assert weak.calibrated.fit["warnings"] == weak.warnings
    assert weak.summary()["warnings"] == weak.warnings
    # the same number of random poses: no warning
    q2, p2, _, _ = cell.simulate(cell.random_joints(60, rng), rng)
    healthy = fit(cell.robot, MeasurementSet(q2, p2), "constant", validation=val)
    assert healthy.warnings == []
    # 10 % of the validation poses 5 mm off: screened, and said so with the unscreened RMS
    pv_bad = pv.copy()
    pv_bad[:20] += 0.005
    glitchy = fit(cell.robot, MeasurementSet(q2, p2), "constant",
                  validation=MeasurementSet(qv, pv_bad))
    assert len(glitchy.validation_outliers) == 20
    assert glitchy.warnings == [w for w in glitchy.warnings if "20 of 200 validation" in w]
    assert len(glitchy.warnings) == 1


def test_an_outlier_round_starts_from_the_last_normal_equations_updated() -> None:
    """The next round's normal equations: the last run's, minus the poses that left the fit
    and plus those that joined, equal a fresh pass over the new set; and a run started from
    them gives the same solution as one that computes them."""
    from robocal.identification._engine import _moved_normals
    from robocal.identification._models import constant_spec

    base, x0 = _problem(80)
    # data a constant model describes (its LM runs converge), started a little off
    rng = np.random.default_rng(6)
    m = base.model.with_spec(constant_spec(base.model.robot))
    x0 = x0[: m.size]
    x_true = x0.copy()
    x_true[9:] = 1e-4 * rng.standard_normal(m.size - 9)
    y = m.positions(base.q, x_true) + 2e-5 * rng.standard_normal((base.n, 3))
    prob = solver.Problem(m, base.q, y, whitening(y, TrackerSigma()))
    x0 = x_true + 1e-5 * rng.standard_normal(m.size)
    cand = np.arange(prob.model.size)
    _, keep, _ = solver.analyse_jacobian(prob, x0, np.arange(prob.n), cand)
    free = cand[keep]                                 # the identifiable parameters
    before = np.ones(prob.n, dtype=bool)
    before[[3, 40]] = False
    info = solver.levenberg_marquardt(prob, x0, free, np.flatnonzero(before))
    after = before.copy()
    after[[3, 11, 57]] = [True, False, False]
    start = _moved_normals(prob, info, free, before, after)
    assert start is not None
    A, g, c = prob.normal_equations(info.x, np.flatnonzero(after), free)
    scale = np.abs(A).max()
    assert np.max(np.abs(start[0] - A)) <= 1e-12 * scale
    assert np.max(np.abs(start[1] - g)) <= 1e-12 * np.abs(g).max()
    assert start[2] == pytest.approx(c, rel=1e-12)
    fresh = solver.levenberg_marquardt(prob, info.x, free, np.flatnonzero(after))
    warm = solver.levenberg_marquardt(prob, info.x, free, np.flatnonzero(after), start=start)
    assert info.converged and fresh.converged and warm.converged
    assert np.allclose(warm.x, fresh.x, rtol=0, atol=1e-12)
    # a quarter of the poses or more changed: computed afresh
    many = np.zeros(prob.n, dtype=bool)
    many[: prob.n // 2] = True
    assert _moved_normals(prob, info, free, before, many) is None
