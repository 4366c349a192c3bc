"""Real data: the Fraunhofer IPA UR10 / laser-tracker data set (skipped when absent).

Subsets keep the run short (<= 1,500 poses per series); full-series figures are in the
identification report / docs/benchmarks.md.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from robocal.identification import FitOptions, fit, load_ipa_series, refit_frozen
from robocal.identification.datasets import ipa_series_path

pytestmark = pytest.mark.dataset


@pytest.fixture(scope="module")
def series(dataset_dir):
    return {s: load_ipa_series(ipa_series_path(dataset_dir, s), max_poses=1500)
            for s in "ABCD"}


def test_loader_reads_every_series(dataset_dir):
    counts = {"A": 11911, "B": 1495, "C": 2773, "D": 632}
    for s, n in counts.items():
        d = load_ipa_series(ipa_series_path(dataset_dir, s), with_sigma=(s != "A"))
        assert len(d) == n and d.dof == 6
        assert d.pose_id[0] == f"{s}00000"
        dist = np.linalg.norm(d.p, axis=1)
        assert dist.min() > 1.0 and dist.max() < 5.0            # metres from the tracker
        assert np.abs(d.q).max() < 2 * np.pi + 1e-6              # rad, not wrapped
        if s != "A":
            assert 0.003e-3 < np.median(d.sigma) < 0.03e-3       # tracker std ~0.01 mm


def test_series_c_baseline_constant_and_auto(series):
    train, val = series["C"].split(0.5, seed=0)
    const = fit("ur10", train, "constant", validation=val)
    auto = fit("ur10", train, "auto", validation=val)
    assert 0.85e-3 < const.validation.baseline_rms_m < 1.15e-3     # nominal + base + reflector
    assert 0.42e-3 < const.validation.rms_m < 0.58e-3
    assert auto.validation.rms_m <= 0.15e-3
    assert auto.validation.percent_described_rms > 85.0
    assert auto.calibrated.fit["map_priors"]                      # joint-angle maps were chosen


def test_series_a_auto(series):
    train, val = series["A"].split(0.5, seed=0)
    auto = fit("ur10", train, "auto", validation=val)
    assert auto.validation.rms_m <= 0.15e-3


def test_series_b_auto_detects_the_gross_outliers(series):
    full = series["B"]
    # independent evidence of the glitches: near-repeated configurations whose measurements
    # disagree by far more than the repeatability (~0.02-0.05 mm)
    pairs = cKDTree(full.q).query_pairs(1e-3, p=np.inf, output_type="ndarray")
    gap = np.linalg.norm(full.p[pairs[:, 0]] - full.p[pairs[:, 1]], axis=1)
    bad_pairs = pairs[gap > 0.3e-3]
    assert len(bad_pairs) == 4
    forced = np.unique(bad_pairs)
    rng = np.random.default_rng(0)
    rest = np.setdiff1d(np.arange(len(full)), forced)
    pick = np.sort(np.concatenate([forced, rng.choice(rest, 740, replace=False)]))
    train = full.subset(pick)
    val = full.subset(np.setdiff1d(np.arange(len(full)), pick))
    auto = fit("ur10", train, "auto", validation=val)
    flagged = set(auto.outliers)
    for a, b in bad_pairs:
        # exactly one of each disagreeing pair is a glitch, and it is the one flagged
        assert (full.pose_id[a] in flagged) != (full.pose_id[b] in flagged)
    assert len(flagged) <= 4 + 3
    assert auto.validation.rms_m <= 0.15e-3


@pytest.fixture(scope="module")
def source_a(series):
    # the physically structured auto model (maps + gravity + pitch, no harmonics and no fine
    # ripple terms, which belong to one session) transfers
    return fit("ur10", series["A"], "auto",
               options=FitOptions(auto_max_order=0, auto_ripple_orders=()))


@pytest.mark.parametrize("target", ["D", "B"])
def test_cross_session_maps_with_refitted_constants(series, source_a, target):
    train, val = series[target].split(0.5, seed=0)
    frozen = refit_frozen(source_a.calibrated, train, validation=val)
    const = fit("ur10", train, "constant", validation=val)
    # measured (1,500-pose subset of A): A->D 0.164 mm, A->B 0.116 mm with the gaps of A's
    # maps filled and the links held (ADR 0022); strictly frozen 0.307 / 0.24 mm
    assert frozen.validation.rms_m <= 0.20e-3
    assert frozen.validation.rms_m < 0.5 * const.validation.rms_m
    assert frozen.calibrated.fit["frozen_from"] == source_a.calibrated.model_id
    assert frozen.calibrated.fit["refreshed_map_knots"]


@pytest.mark.parametrize("target", ["D", "B"])
def test_reuse_from_fifty_new_poses(series, source_a, target):
    """Issue 14's workflow: maps from A, constants from 50 poses of B or D.

    The acceptance figure (maps from all of A: B 0.177 mm, D 0.188 mm, median of 10 draws) is
    in docs/benchmarks.md; this source is A's first 1,500 poses, a corner of its grid, so
    more of B's and D's poses fall in gaps the 50 new poses must fill.
    """
    full = series[target]
    r, c = [], []
    for draw in range(3):
        rng = np.random.default_rng(draw)
        pick = np.zeros(len(full), dtype=bool)
        pick[rng.choice(len(full), 50, replace=False)] = True
        train, val = full.subset(pick), full.subset(~pick)
        res = refit_frozen(source_a.calibrated, train, validation=val)
        const = fit("ur10", train, "constant", validation=val)
        assert res.validation is not None and const.validation is not None
        r.append(res.validation.rms_m)
        c.append(const.validation.rms_m)
        if res.validation.rms_m > 1e-3:
            # D draw 1: no training pose with J6 = 90 deg, and D's 27 such poses also have
            # J4 beyond A's subset: predicted from nothing, and said so
            assert any("leave the model nearly free" in w for w in res.warnings)
    # measured: B 0.200 / 0.233 / 0.265 mm (constant 0.46 / 0.53 / 0.60 mm), D 0.208 / 9.6 /
    # 0.222 mm (constant 0.44 / 6.4 / 0.46 mm)
    assert np.median(r) <= 0.25e-3
    assert np.median(r) <= 0.6 * np.median(c)


@pytest.mark.parametrize("seed", [8])
def test_series_b_auto_holds_on_splits_that_used_to_fail(dataset_dir, seed):
    # this random 50/50 split gave 0.17 mm (seed 10: 0.14 mm) before maps bridged thin data
    # (issue 14); the 20-split spread is in docs/benchmarks.md (bench/bench_fit.py --splits
    # 20), which keeps the suite from fitting every split
    full = load_ipa_series(ipa_series_path(dataset_dir, "B"))
    train, val = full.split(0.5, seed=seed)
    auto = fit("ur10", train, "auto", validation=val)
    assert auto.validation.rms_m <= 0.13e-3


@pytest.mark.parametrize("draw", [1, 3, 4])
def test_constant_fit_on_fifty_poses_of_series_d_converges(series, draw):
    # these draws crept along a nearly flat valley (scaled condition number ~2e7) and hit the
    # former 100-iteration limit; they converge within the present 300
    train, val = series["D"].split(0.5, seed=0)
    rng = np.random.default_rng(draw)
    sub = train.subset(np.sort(rng.choice(len(train), 50, replace=False)))
    const = fit("ur10", sub, "constant", validation=val)
    assert const.status == "converged"
    assert const.validation.rms_m < 0.5e-3


def test_constant_fit_that_creeps_past_the_iteration_limit_is_kept_not_raised(series):
    # 50 poses of B (draw 3) crawl along a curved valley for more than 300 iterations; the
    # Gauss-Newton step then predicts less than 0.1 % further decrease, so the result is kept
    # and reported as not converged instead of raising NotConverged
    data = series["B"]
    rng = np.random.default_rng(3)
    pick = np.zeros(len(data), dtype=bool)
    pick[rng.choice(len(data), 50, replace=False)] = True
    const = fit("ur10", data.subset(pick), "constant", validation=data.subset(~pick))
    assert const.status == "max-iterations"
    assert const.validation.rms_m < 0.55e-3


def test_series_d_auto_holds_on_the_split_that_used_to_fail(series):
    # split 17 of D gave 0.59 mm: a first harmonic of J6 (three angles only in D) coupled
    # with the wrist constants put one upright validation pose 10 mm off
    train, val = series["D"].split(0.5, seed=17)
    auto = fit("ur10", train, "auto", validation=val)
    assert auto.validation.rms_m <= 0.20e-3
    assert not any(g.startswith("j6:") for g in auto.calibrated.fit["selection"][-1]["groups"])


def test_series_b_split_9_keeps_the_better_of_two_selections(dataset_dir):
    """On this split the first selection's model rejects a pose it was selected with; the
    selection without it ends with a higher CV score per coordinate (its greedy path went
    astray: 0.118 mm held-out), so the first model, already solved without the pose, is
    kept."""
    full = load_ipa_series(ipa_series_path(dataset_dir, "B"))
    train, val = full.split(0.5, seed=9)
    auto = fit("ur10", train, "auto", validation=val)
    screen = auto.selection[0]
    assert screen["action"] == "screen" and "not kept" in screen["by"]
    final = auto.selection[-1]
    assert screen["second_selection_cv_rms_whitened"] > final["cv_rms_whitened"]
    assert auto.validation.rms_m <= 0.105e-3          # measured 0.1032 mm
