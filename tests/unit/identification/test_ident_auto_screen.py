"""``auto``: the score-test pre-screen of the ripple family and the restricted fold factors.

Small virtual-robot data (a few hundred poses, no joint-angle maps) keeps each fit fast.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.errors import ConfigError
from robocal.identification import FitOptions, fit
from robocal.identification._auto import _CV
from robocal.kinematics import KinematicModel, Term
from robocal.simulation import VirtualCell

# maps off: the ripple family then meets only parametric terms, and a fit takes < 1 s
FAST = FitOptions(auto_maps=False)


def _cell_with_ripple(seed: int, joint: int, order: int, amp_rad: float) -> VirtualCell:
    """The ``constant`` virtual cell plus a planted ripple ``amp cos/sin(order q)`` on the
    rotation about ``joint``'s axis."""
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=seed)
    spec = cell.truth_model.spec.with_terms(
        [Term(joint, "ez", "cos", order), Term(joint, "ez", "sin", order)], label="truth:ripple")
    model = KinematicModel(cell.robot, spec, cell.truth_model.T_ref)
    x = np.concatenate([cell.truth_params, [0.8 * amp_rad, -0.6 * amp_rad]])
    return dataclasses.replace(cell, truth_model=model, truth_params=x)


def _data(cell: VirtualCell, n: int, seed: int) -> MeasurementSet:
    rng = np.random.default_rng(seed)
    q, p, _, _ = cell.simulate(cell.random_joints(n, rng), rng)
    return MeasurementSet(q, p)


def _chosen(res) -> list[str]:
    return next(e["groups"] for e in res.selection if e.get("action") == "final")


def test_a_planted_ripple_ranks_first_and_is_chosen_with_a_screen_of_one():
    """Only the best-ranked ripple candidate is cross-validated per round; the planted
    J2 ripple of order 23 (60 µrad) is still found, and nothing else of the family."""
    cell = _cell_with_ripple(seed=31, joint=1, order=23, amp_rad=6e-5)
    train, val = _data(cell, 300, 1031), _data(cell, 300, 2031)
    res = fit(cell.robot, train, "auto", validation=val,
              options=dataclasses.replace(FAST, auto_ripple_screen=1))
    chosen = _chosen(res)
    assert "j2:ripple23" in chosen
    assert not [g for g in chosen if ":ripple" in g and g != "j2:ripple23"]
    # as good as a fit that knows the planted structure
    truth = fit(cell.robot, train, cell.truth_model.spec, validation=val)
    assert res.validation.rms_m <= 1.05 * truth.validation.rms_m


def test_no_ripple_is_chosen_on_data_without_ripple():
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=32)
    train, val = _data(cell, 250, 1032), _data(cell, 250, 2032)
    res = fit(cell.robot, train, "auto", validation=val, options=FAST)
    assert not [g for g in _chosen(res) if ":ripple" in g]


def test_the_screen_does_not_change_the_choice_when_it_keeps_everything():
    """Screening the family down to a few leaves the selection as with all of it tried."""
    cell = _cell_with_ripple(seed=33, joint=2, order=17, amp_rad=5e-5)
    train = _data(cell, 250, 1033)
    screened = fit(cell.robot, train, "auto", options=FAST)
    everything = fit(cell.robot, train, "auto",
                     options=dataclasses.replace(FAST, auto_ripple_screen=10_000))
    assert _chosen(screened) == _chosen(everything)
    assert "j3:ripple17" in _chosen(screened)
    assert (screened.selection[-1]["cv_evaluations"]
            < everything.selection[-1]["cv_evaluations"])


def test_screen_size_must_be_positive():
    with pytest.raises(ConfigError):
        FitOptions(auto_ripple_screen=0)


def _random_cv(rng: np.random.Generator, K: int = 3, P: int = 24, n: int = 90) -> _CV:
    G_f = np.zeros((K, P, P))
    b_f = np.zeros((K, P))
    c_f = np.zeros(K)
    for f in range(K):
        J = rng.normal(size=(n, P))
        r = rng.normal(size=n)
        G_f[f], b_f[f], c_f[f] = J.T @ J, J.T @ r, r @ r
    return _CV(G_f, b_f, c_f)


def test_fold_factors_over_active_columns_match_a_fresh_factorisation():
    """Extending the base and dropping columns from the active set (the forward selection's
    updates) gives the factors a fresh computation gives; new columns are recomputed."""
    cv = _random_cv(np.random.default_rng(5))
    base = np.arange(4)
    cv.fold_bases(base, np.zeros((4, 4)), np.arange(4, 16))
    base2 = np.r_[base, [9, 7, 8]]
    pen2 = np.zeros((7, 7))
    pen2[4:, 4:] = 0.5 * np.eye(3)
    for act in (np.r_[4:7, 10:16], np.r_[4:7, 10:20]):     # a subset; then new columns
        updated = [dataclasses.replace(fb) for fb in cv.fold_bases(base2, pen2, act)]
        cv._cache = None
        fresh = cv.fold_bases(base2, pen2, act)
        for u, f in zip(updated, fresh, strict=True):
            assert u.X.shape == (7, len(act))
            np.testing.assert_allclose(u.Ainv, f.Ainv, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(u.X, f.X, rtol=1e-9, atol=1e-12)


def test_train_gains_are_the_drop_of_the_training_sum_of_squares():
    """The score-test gain of a group equals the first fold's training SSE drop when the
    group is added (checked against two direct least-squares solves)."""
    cv = _random_cv(np.random.default_rng(6))
    base = np.arange(5)
    C = np.array([[6, 7], [10, 11], [20, 3 + 20]])
    pens = np.stack([0.3 * np.eye(2)] * 3)
    gains = cv.train_gains(base, np.zeros((5, 5)), C, pens, np.unique(C))
    Gt = cv.G - cv.G_f[0]
    bt = cv.b - cv.b_f[0]

    def sse_drop(cols: np.ndarray, pen: np.ndarray) -> float:
        # SSE(d) = c - 2 d.b + d.G d (+ d.pen d); at the optimum it is c - b.A^-1 b
        return float(bt[cols] @ np.linalg.solve(Gt[np.ix_(cols, cols)] + pen, bt[cols]))

    for g, (cols, pen) in enumerate(zip(C, pens, strict=True)):
        allc = np.r_[base, cols]
        P = np.zeros((7, 7))
        P[5:, 5:] = pen
        want = sse_drop(allc, P) - sse_drop(base, np.zeros((5, 5)))
        assert gains[g] == pytest.approx(want, rel=1e-9)


def test_a_group_almost_in_the_span_of_the_base_makes_the_factors_be_recomputed():
    """Adding columns the base nearly reproduces (a fine map after its joint's harmonics)
    would leave the updated factors a few digits; they are recomputed instead, and the
    scores equal those of a fresh factorisation (B series split 13: 0.130 -> 0.097 mm)."""
    rng = np.random.default_rng(7)
    K, P, n = 3, 12, 120
    J = rng.normal(size=(K * n, P))
    J[:, 8:10] = J[:, :2] @ rng.normal(size=(2, 2)) + 1e-6 * rng.normal(size=(K * n, 2))
    r = J[:, :3] @ rng.normal(size=3) + rng.normal(size=K * n)
    G_f = np.stack([J[f::K].T @ J[f::K] for f in range(K)])
    b_f = np.stack([J[f::K].T @ r[f::K] for f in range(K)])
    c_f = np.array([r[f::K] @ r[f::K] for f in range(K)])
    cv = _CV(G_f, b_f, c_f)
    base = np.arange(4)
    cv.fold_bases(base, np.zeros((4, 4)), np.arange(4, 12))
    base2 = np.r_[base, [8, 9]]
    pen2 = np.zeros((6, 6))
    pen2[4:, 4:] = 1e-9 * np.eye(2)                 # a weak ridge, as on a map
    options = [(np.array([c]), [np.zeros((1, 1))]) for c in (4, 5, 6, 7, 10, 11)]
    updated = cv.scores_added(base2, pen2, options)
    assert cv.refactorisations == 1
    cv._cache = None
    fresh = cv.scores_added(base2, pen2, options)
    np.testing.assert_allclose(updated, fresh, rtol=1e-12)


def _direct_scores(cv: _CV, base: np.ndarray, options) -> list[list[float]]:
    """``base + group`` scored one model at a time (``_CV.score``, one solve per fold)."""
    k = len(base)
    out = []
    for cols, pens in options:
        row = []
        for pen in pens:
            P = np.zeros((k + len(cols), k + len(cols)))
            P[k:, k:] = pen
            row.append(cv.score(np.r_[base, cols], P))
        out.append(row)
    return out


@pytest.mark.parametrize("seed", range(4))
def test_fold_stacked_scores_equal_one_model_at_a_time(seed: int):
    """All folds' systems solved in one stacked call, groups of different sizes stacked
    padded, and a smoothness family's definiteness proven by its least definite member,
    give the scores of direct per-model solves."""
    rng = np.random.default_rng(100 + seed)
    cv = _random_cv(rng, K=4, P=30, n=120)
    base = np.sort(rng.choice(30, size=6, replace=False))
    rest = np.setdiff1d(np.arange(30), base)
    D = np.diff(np.eye(5), 2, axis=0)
    D2 = D.T @ D
    options = [(rest[[0]], [np.zeros((1, 1))]), (rest[[1]], [np.zeros((1, 1))]),
               (rest[2:4], [np.zeros((2, 2))]), (rest[4:6], [0.1 * np.eye(2)]),
               # map-like groups: a ridge plus a smoothness grid (unsorted on purpose)
               (rest[6:11], [lam * D2 + 1e-3 * np.eye(5) for lam in (10.0, 0.01, 1.0)]),
               (rest[11:16], [lam * D2 + 1e-3 * np.eye(5) for lam in (0.1, 100.0)])]
    stacked = cv.scores_added(base, np.zeros((6, 6)), options)
    direct = _direct_scores(cv, base, options)
    for s_row, d_row in zip(stacked, direct, strict=True):
        np.testing.assert_allclose(s_row, d_row, rtol=1e-10)


def test_a_family_with_a_singular_member_falls_back_for_every_system():
    """When the least definite system of a family is singular (no prior, dependent
    columns) the stack is solved system by system (least squares where singular), as
    direct solves are."""
    rng = np.random.default_rng(11)
    K, P, n = 3, 10, 60
    J = rng.normal(size=(K * n, P))
    J[:, 9] = J[:, 8]                                 # columns 8 and 9 are identical
    r = rng.normal(size=K * n)
    cv = _CV(np.stack([J[f::K].T @ J[f::K] for f in range(K)]),
             np.stack([J[f::K].T @ r[f::K] for f in range(K)]),
             np.array([r[f::K] @ r[f::K] for f in range(K)]))
    base = np.arange(4)
    options = [(np.array([8, 9]), [np.zeros((2, 2)), np.eye(2)]),
               (np.array([5, 6]), [np.zeros((2, 2))])]
    stacked = cv.scores_added(base, np.zeros((4, 4)), options)
    assert np.all(np.isfinite(stacked[0]))
    np.testing.assert_allclose(stacked[1], _direct_scores(cv, base, options[1:])[0],
                               rtol=1e-10)
    np.testing.assert_allclose(stacked[0][1], _direct_scores(cv, base, options[:1])[0][1],
                               rtol=1e-10)


def test_varied_scores_equal_direct_scores_across_a_changed_model():
    """Block drops and prior changes (backward pass, smoothness refinement) score as direct
    fits, before and after a variant is adopted (the held-out blocks kept for the model's
    columns are renewed when its columns change)."""
    rng = np.random.default_rng(21)
    cv = _random_cv(rng, K=3, P=20, n=100)
    cols = np.array([0, 1, 2, 3, 7, 8, 9, 12, 13])
    pen = np.zeros((9, 9))
    pen[4:7, 4:7] = 0.2 * np.eye(3)
    drop, blk = np.array([7, 8]), np.array([4, 5, 6])
    dpen = 0.5 * np.eye(3)
    for _ in range(2):
        dropped, repen = cv.scores_varied(cols, pen, [drop], [(blk, dpen)])
        keep = np.setdiff1d(np.arange(len(cols)), drop)
        assert dropped[0] == pytest.approx(cv.score(cols[keep], pen[np.ix_(keep, keep)]),
                                           rel=1e-10)
        pen2 = pen.copy()
        pen2[np.ix_(blk, blk)] += dpen
        assert repen[0] == pytest.approx(cv.score(cols, pen2), rel=1e-10)
        # adopt the drop: the next round scores the smaller model
        cv.adopt_variant(cols, pen, cols[keep], pen[np.ix_(keep, keep)], drop=drop)
        cols, pen = cols[keep], pen[np.ix_(keep, keep)]
        drop = np.array([len(cols) - 1])
