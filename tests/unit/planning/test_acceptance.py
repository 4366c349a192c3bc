"""Acceptance on the virtual robot: D-optimal poses against random poses, held-out accuracy.

Issue 5 asks that 60 D-optimal poses give a constant-model fit at least as accurate on
held-out poses as 120 random poses. On this robot and cell that is not reachable by any choice
of 60 poses when the fit error comes from measurement noise (which it does for the constant
scenario): with A the mean information of one candidate, every 60-pose set has expected
held-out variance tr(A M^-1) >= L^2 / tr(A^-1 M) (harmonic vs arithmetic mean of the
eigenvalues of A^-1/2 M A^-1/2), and tr(A^-1 M) is at most the sum of the 60 largest
per-pose leverages h_i = tr(A^-1 J_i^T J_i), whose mean over candidates is L. The test below
computes that bound for the actual candidate pool and shows it is above what 120 random poses
achieve (L / 120), then checks what the planner does deliver: D-optimal 60 beats random 60
and comes within 50 % of random 120 (1.28x over 12 seeds, 1.09x on the three seeds here; 60
D-optimal poses are worth about 78 random ones).
"""

from __future__ import annotations

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.identification import fit
from robocal.planning import (
    FeasibilityChecker,
    cell_design_space,
    draw_candidates,
    load_cell,
    model_spec,
    plan_campaign,
)
from robocal.simulation import VirtualCell

from .helpers import cell_with

SEEDS = (0, 1, 2)


def _held_out_rms(vc: VirtualCell, q_train: np.ndarray, q_val: np.ndarray,
                  val: MeasurementSet, rng: np.random.Generator) -> float:
    """RMS distance (m) between the fitted constant model and the truth on held-out poses."""
    q, p, s, _ = vc.simulate(q_train, rng)
    res = fit(vc.robot, MeasurementSet(q, p, s), "constant", validation=val)
    assert res.validation is not None and np.isfinite(res.validation.rms_m)
    e = np.linalg.norm(res.calibrated.predict(q_val) - vc.reflector_position(q_val), axis=1)
    return float(np.sqrt(np.mean(e**2)))


@pytest.mark.slow
def test_d_optimal_poses_against_random_poses_on_the_virtual_robot() -> None:
    dopt, rand60, rand120 = [], [], []
    for seed in SEEDS:
        vc = VirtualCell.create("fanuc_lrmate200i", "constant", seed)
        # the tracker position is known to ~0.1 m only
        guess = vc.tracker_in_base * 1e3 + np.array([60.0, -60.0, 40.0])
        cell = cell_with(load_cell("demo"), tracker={"position_mm": [float(v) for v in guess]})
        plan = plan_campaign(vc.robot, cell, count=60, validation=150, iso=False, seed=seed,
                             candidates=1024)
        q_cal = plan.joint_targets("calibration")
        q_val = plan.joint_targets("validation")
        # the same candidate pool the planner chose from (same seed, same target)
        checker = FeasibilityChecker(vc.robot, cell)
        pool, _, _ = draw_candidates(checker, target=1024, seed=seed)
        used = np.vstack([q_cal, q_val])
        dist = np.abs(pool[:, None, :] - used[None, :, :]).max(axis=2).min(axis=1)
        free = pool[dist > 1e-6]
        assert len(free) == len(pool) - len(used)
        rng = np.random.default_rng(1000 + seed)
        q_rand = free[rng.choice(len(free), 120, replace=False)]
        qv, pv, sv, _ = vc.simulate(q_val, rng)
        val = MeasurementSet(qv, pv, sv)
        dopt.append(_held_out_rms(vc, q_cal, q_val, val, rng))
        rand120.append(_held_out_rms(vc, q_rand, q_val, val, rng))
        rand60.append(_held_out_rms(vc, q_rand[:60], q_val, val, rng))
        assert (plan.observability.calibration.O1
                > plan.observability.random_baseline.O1)  # type: ignore[union-attr]
    d, r60, r120 = np.mean(dopt), np.mean(rand60), np.mean(rand120)
    print(f"held-out RMS vs truth (um): D-opt 60 {d * 1e6:.2f}, random 60 {r60 * 1e6:.2f}, "
          f"random 120 {r120 * 1e6:.2f}")
    assert d < r60
    assert d < 1.5 * r120


def test_sixty_poses_cannot_match_a_hundred_and_twenty_random_ones() -> None:
    """The bound that makes '60 D-optimal >= 120 random' unreachable (see the module doc)."""
    vc = VirtualCell.create("fanuc_lrmate200i", "constant", 0)
    cell = cell_with(load_cell("demo"), tracker={
        "position_mm": [float(v) for v in vc.tracker_in_base * 1e3]})
    checker = FeasibilityChecker(vc.robot, cell)
    q, f, _ = draw_candidates(checker, target=1024, seed=0)
    ds = cell_design_space(checker, model_spec(vc.robot, "constant"), q, f)
    J = ds.J
    L = J.shape[2]
    A = np.einsum("nai,naj->ij", J, J) / len(J)
    h = np.einsum("nai,ij,naj->n", J, np.linalg.inv(A), J)
    assert np.mean(h) == pytest.approx(L)
    best60 = np.sort(h)[::-1][:60].sum()
    lower_bound_60 = L**2 / best60      # any 60 poses, expected held-out variance (units of A)
    random_120 = L / 120                # 120 random poses, expected variance (Jensen: >=)
    assert lower_bound_60 > 1.1 * random_120
    # and the planner's 60 poses sit between that bound and random 60
    sel = ds.select(60)
    M = J[sel].reshape(-1, L).T @ J[sel].reshape(-1, L)
    v_dopt = float(np.trace(np.linalg.solve(M, A)))
    assert lower_bound_60 <= v_dopt < L / 60


def _design_trial(scenario: str, fit_model: str, n: int, seed: int) -> dict[str, float]:
    """Held-out RMS (m, against the truth) of ``fit_model`` on n random / stratified poses."""
    vc = VirtualCell.create("fanuc_lrmate200i", scenario, seed)
    cell = cell_with(load_cell("demo"), tracker={
        "position_mm": [float(v) for v in vc.tracker_in_base * 1e3]})
    checker = FeasibilityChecker(vc.robot, cell)
    q, f, _ = draw_candidates(checker, target=1024, seed=seed)
    q_val, _, _ = draw_candidates(checker, target=400, seed=seed + 1000)
    ds = cell_design_space(checker, model_spec(vc.robot, fit_model), q, f)
    designs = {"random": np.random.default_rng(seed + 7).choice(len(q), n, replace=False),
               "stratified": ds.select_stratified(n)}
    out = {}
    for name, idx in designs.items():
        qq, p, s, _ = vc.simulate(q[idx], np.random.default_rng(seed * 31 + n))
        res = fit(vc.robot, MeasurementSet(qq, p, s), fit_model)
        e = np.linalg.norm(res.calibrated.predict(q_val) - vc.reflector_position(q_val), axis=1)
        out[name] = float(np.sqrt(np.mean(e**2)))
    return out


@pytest.mark.slow
def test_stratified_design_serves_high_order_fits_and_does_not_bias_constant_ones() -> None:
    """Issue 18 on a virtual robot with joint-dependent errors (10-seed figures:
    bench/bench_design.py, docs/benchmarks.md)."""
    ho = [_design_trial("paper", "high-order", 100, s) for s in SEEDS]
    ratio = np.median([t["stratified"] / t["random"] for t in ho])
    assert ratio <= 0.85                       # measured 0.35 over 10 seeds
    const = [_design_trial("paper", "constant", 120, s) for s in SEEDS]
    strat = np.median([t["stratified"] for t in const])
    rand = np.median([t["random"] for t in const])
    assert strat <= rand * 1.01                # constant fit: bias-dominated, no worse



def test_stratified_design_beats_random_on_a_robot_with_constant_errors() -> None:
    """Without unmodelled errors the held-out error is the fit's variance: its expectation,
    tr(A M^-1) with A the mean information of a held-out pose, decides (one simulated
    realisation per seed varies by tens of percent; bench/bench_design.py measures 0.78x
    random over 10 seeds)."""
    ratios = []
    for seed in SEEDS:
        vc = VirtualCell.create("fanuc_lrmate200i", "constant", seed)
        cell = cell_with(load_cell("demo"), tracker={
            "position_mm": [float(v) for v in vc.tracker_in_base * 1e3]})
        checker = FeasibilityChecker(vc.robot, cell)
        q, f, _ = draw_candidates(checker, target=1024, seed=seed)
        ds = cell_design_space(checker, model_spec(vc.robot, "constant"), q, f)
        J, L = ds.J, ds.identifiable
        A = np.einsum("nai,naj->ij", J, J) / len(J)

        def variance(idx: np.ndarray, J: np.ndarray = J, L: int = L,
                     A: np.ndarray = A) -> float:
            Ji = J[idx].reshape(-1, L)
            return float(np.trace(np.linalg.solve(Ji.T @ Ji, A)))

        rng = np.random.default_rng(seed)
        rand = np.median([variance(rng.choice(len(q), 60, replace=False)) for _ in range(20)])
        ratios.append(variance(ds.select_stratified(60)) / rand)
    print("variance ratio stratified/random", ratios)
    assert max(ratios) < 0.9
