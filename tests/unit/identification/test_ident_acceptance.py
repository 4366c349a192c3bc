"""Acceptance on the virtual robot: planted truth, 250 training poses, separate held-out poses.

"% described" is relative to the nominal model with base and reflector fitted; "truth
structure" is a fit with the planted error-model structure (``truth_spec``), which bounds what
any model can reach with these poses and this noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from robocal.identification import FitOptions, fit, refit_frozen
from robocal.kinematics import KinematicModel
from robocal.simulation import VirtualCell, truth_spec

from .conftest import make_data

NO_OUTLIERS = FitOptions(detect_outliers=False)


def _truth_fit(d, *, clean_only: bool = False):
    train = d.train
    if clean_only:
        planted = set(d.planted)
        train = train.subset(np.array([p not in planted for p in train.pose_id]))
    return fit(d.cell.robot, train, truth_spec(d.cell.robot, d.cell.scenario),
               validation=d.val, options=NO_OUTLIERS)


def test_paper_constant_describes_about_80_percent():
    # The planted magnitudes are random per seed: over 20 seeds the constant model describes
    # 56-87 % (mean 77 %) of the held-out error. Average a few seeds rather than pick one.
    rms, mean = [], []
    for seed in range(100, 106):
        d = make_data("fanuc_lrmate200i", "paper", seed=seed, n_val=200)
        res = fit(d.cell.robot, d.train, "constant", validation=d.val)
        assert res.rank == 27
        rms.append(res.validation.percent_described_rms)
        mean.append(res.validation.percent_described_mean)
    assert 75.0 <= np.mean(rms) <= 85.0
    assert 75.0 <= np.mean(mean) <= 85.0
    assert min(rms) >= 50.0 and max(rms) <= 92.0


def test_paper_high_order_describes_97_percent_close_to_truth_structure(paper_data):
    ho = fit(paper_data.cell.robot, paper_data.train, "high-order", validation=paper_data.val)
    ref = _truth_fit(paper_data)
    assert ho.validation.percent_described_rms >= 97.0
    assert ho.validation.rms_m <= 1.3 * ref.validation.rms_m
    assert ho.outliers == []


@pytest.fixture(scope="module")
def strain_wave():
    return make_data("fanuc_lrmate200i", "strain-wave", seed=12)


def test_strain_wave_auto_within_1_5_of_truth_structure(strain_wave):
    d = strain_wave
    auto = fit(d.cell.robot, d.train, "auto", validation=d.val)
    ref = _truth_fit(d)
    assert auto.validation.rms_m <= 1.5 * ref.validation.rms_m
    groups = [g for e in auto.selection if e.get("action") == "final" for g in e["groups"]]
    assert any("strain-wave" in g for g in groups)       # the gear-ratio ripple was found
    assert auto.calibrated.kind == "auto"


def test_auto_with_3_percent_outliers_within_1_5_of_truth_structure():
    d = make_data("fanuc_lrmate200i", "strain-wave", seed=13, outlier_fraction=0.03)
    assert len(d.planted) == 8
    auto = fit(d.cell.robot, d.train, "auto", validation=d.val)
    assert sorted(auto.outliers) == sorted(d.planted)
    ref = _truth_fit(d, clean_only=True)                  # oracle: knows structure and glitches
    assert auto.validation.rms_m <= 1.5 * ref.validation.rms_m


def test_auto_is_not_worse_than_constant_without_joint_dependent_errors():
    d = make_data("fanuc_lrmate200i", "constant", seed=14)
    const = fit(d.cell.robot, d.train, "constant", validation=d.val)
    auto = fit(d.cell.robot, d.train, "auto", validation=d.val)
    assert auto.validation.rms_m <= 1.03 * const.validation.rms_m
    groups = [g for e in auto.selection if e.get("action") == "final" for g in e["groups"]]
    assert len(groups) <= 2


@pytest.fixture(scope="module")
def fine_map():
    d = make_data("fanuc_lrmate200i", "fine-map", seed=15, n_train=600)
    res = fit(d.cell.robot, d.train, "auto", validation=d.val,
              options=FitOptions(map_spacing_deg=2.5))
    return d, res


def test_auto_finds_fine_grained_joint_angle_errors(fine_map):
    d, auto = fine_map
    const = fit(d.cell.robot, d.train, "constant", validation=d.val)
    assert auto.validation.rms_m <= 0.35 * const.validation.rms_m
    cal, tm = auto.calibrated, d.cell.truth_model
    # joints whose rotation got fine joint-dependent terms (maps or ripple harmonics)
    fine = sorted({t.joint for t in cal.model.spec.terms if t.component == "ez"
                   and (t.family == "map" or (t.family in ("cos", "sin") and t.index > 3))})
    assert len(fine) >= 4
    # each fitted error follows the planted fine-grained error (3, 5, 17, 34 cycles/rev) over
    # the joint range the data cover
    from robocal.kinematics import evaluate_basis

    corr = []
    for j in fine:
        q = np.zeros((720, 6))
        q[:, j] = np.linspace(d.train.q[:, j].min(), d.train.q[:, j].max(), 720)
        B, _ = evaluate_basis(cal.model.spec, cal.robot, q)
        cols = np.array([k for k, t in enumerate(cal.model.spec.terms)
                         if t.joint == j and t.component == "ez" and t.family != "const"])
        fitted = B[:, cols] @ cal.params[9 + cols]
        Bt, _ = evaluate_basis(tm.spec, cal.robot, q)
        tcols = np.array([k for k, t in enumerate(tm.spec.terms)
                          if t.joint == j and t.component == "ez" and t.family in ("cos", "sin")])
        true = Bt[:, tcols] @ d.cell.truth_params[9 + tcols]
        corr.append(np.corrcoef(fitted, true)[0, 1])
    assert min(corr) > 0.85 and np.median(corr) > 0.95


def test_refit_with_frozen_maps_transfers_to_a_new_session(fine_map):
    d, auto = fine_map
    c1 = d.cell
    # session 2: tracker moved, reflector re-mounted, constant geometry drifted a little
    rng = np.random.default_rng(99)
    T2 = c1.truth_model.T_ref.copy()
    T2[:3, 3] += [0.3, -0.4, 0.1]
    x2 = c1.truth_params.copy()
    x2[6:9] += rng.normal(0, 2e-3, 3)
    const_idx = [9 + k for k, t in enumerate(c1.truth_model.spec.terms) if t.family == "const"]
    x2[const_idx] += rng.normal(0, 3e-5, len(const_idx))
    c2 = VirtualCell(robot=c1.robot, scenario=c1.scenario,
                     truth_model=KinematicModel(c1.robot, c1.truth_model.spec, T2),
                     truth_params=x2, seed=99)
    q, p, _, _ = c2.simulate(c2.random_joints(120, rng), rng)
    qv, pv, _, _ = c2.simulate(c2.random_joints(300, rng), rng)
    from robocal._core.measurements import MeasurementSet

    train2, val2 = MeasurementSet(q, p), MeasurementSet(qv, pv)
    frozen = refit_frozen(auto.calibrated, train2, validation=val2)
    const2 = fit(c1.robot, train2, "constant", validation=val2)
    assert frozen.validation.rms_m <= 0.35 * const2.validation.rms_m
    assert frozen.validation.rms_m <= 1.5 * auto.validation.rms_m
    # random poses leave no gap of 10 deg or more in the first session's maps: every
    # joint-dependent term is kept exactly, constant kinematics were refitted
    assert frozen.calibrated.fit["refreshed_map_knots"] == {}
    names = auto.calibrated.model.names
    m_idx = [i for i, n in enumerate(names) if not (n.startswith(("base.", "tool."))
                                                    or n.endswith(".const"))]
    np.testing.assert_array_equal(frozen.calibrated.params[m_idx],
                                  auto.calibrated.params[m_idx])
    assert frozen.calibrated.kind == "refit:auto"
    # trusted where the maps were learnt and where the refit met data (else: fallback)
    cov, prev = frozen.calibrated.coverage, auto.calibrated.coverage
    assert cov is not None and prev is not None
    assert np.all(cov[:, 0] <= np.minimum(prev[:, 0], q.min(axis=0)) + 1e-12)
    assert np.all(cov[:, 1] >= np.maximum(prev[:, 1], q.max(axis=0)) - 1e-12)
    assert frozen.calibrated.fit["frozen_from"] == auto.calibrated.model_id


def test_auto_resolves_fine_ripple_like_a_fit_that_knows_the_structure(fine_map):
    """Fine joint-angle ripple (17 and 34 cycles/rev, like the UR10's): auto within 10 %."""
    d, auto = fine_map
    ref = _truth_fit(d)
    assert auto.validation.rms_m <= 1.10 * ref.validation.rms_m
    ripple = {t.index for t in auto.calibrated.model.spec.terms
              if t.family in ("cos", "sin") and t.index > 3}
    assert {17, 34} <= ripple


def test_glitches_of_a_few_mm_are_screened_and_auto_does_not_suffer():
    """10 % beam-break glitches of 1-5 mm: all caught, and auto is as good as high-order."""
    d = make_data("fanuc_lrmate200i", "strain-wave", seed=21, outlier_fraction=0.10)
    assert len(d.planted) == 25
    ref = _truth_fit(d, clean_only=True)
    results = {m: fit(d.cell.robot, d.train, m, validation=d.val)
               for m in ("high-order", "auto")}
    for res in results.values():
        assert sorted(res.outliers) == sorted(d.planted)
    assert results["auto"].validation.rms_m <= 1.10 * results["high-order"].validation.rms_m
    assert results["auto"].validation.rms_m <= 1.10 * ref.validation.rms_m
    screen = results["auto"].selection[0]
    assert screen["action"] == "screen" and screen["excluded"] == 25


def test_reuse_fills_the_gaps_of_the_earlier_maps(tmp_path):
    """Knots the first session never reached are refitted from the new data; the rest hold."""
    from robocal._core.measurements import MeasurementSet
    from robocal.kinematics import CalibratedModel

    cell = VirtualCell.create("fanuc_lrmate200i", "fine-map", seed=15)
    rng = np.random.default_rng(1015)
    q = cell.random_joints(900, rng)
    lo, hi = np.quantile(q[:, 1], [0.35, 0.6])       # a 25 % gap in J2 in session 1
    gap = (q[:, 1] > lo) & (q[:, 1] < hi)
    q1, p1, _, _ = cell.simulate(q[~gap][:600], rng)
    src = fit(cell.robot, MeasurementSet(q1, p1), "auto",
              options=FitOptions(map_spacing_deg=2.5))
    assert any(t.joint == 1 and t.family == "map" for t in src.calibrated.model.spec.terms)
    path = tmp_path / "first.json"
    src.calibrated.save(path)
    first = CalibratedModel.load(path)
    support = first.data["map_support"]["j2"]
    assert len(support) == first.model.spec.map_knots[1] and sum(support) > 0
    # session 2: 60 poses anywhere in the workspace; held out: 600 more
    q2, p2, _, _ = cell.simulate(cell.random_joints(60, rng), rng)
    qv, pv, _, _ = cell.simulate(cell.random_joints(600, rng), rng)
    new, val = MeasurementSet(q2, p2), MeasurementSet(qv, pv)
    in_gap = (qv[:, 1] > lo) & (qv[:, 1] < hi)

    def gap_rms(res):
        e = np.linalg.norm(res.calibrated.predict(qv) - pv, axis=1)
        return float(np.sqrt(np.mean(e[in_gap] ** 2)))

    filled = refit_frozen(first, new, validation=val)
    frozen = refit_frozen(first, new, validation=val,
                          options=FitOptions(reuse_fill_gaps=False))
    # measured: in the gap 0.024 mm filled vs 0.039 mm frozen; all held out 0.023 vs 0.032
    assert gap_rms(filled) < 0.75 * gap_rms(frozen)
    assert filled.validation.rms_m < frozen.validation.rms_m
    assert filled.calibrated.fit["refreshed_map_knots"]["j2"] > 0
    assert frozen.calibrated.fit["refreshed_map_knots"] == {}
    # the refit's support adds the new poses to the earlier counts; the maps' own smoothness
    # settings carry over unchanged (a chain of reuses does not compound the reuse factor)
    assert sum(filled.calibrated.data["map_support"]["j2"]) > sum(support)
    assert filled.calibrated.fit["map_priors"] == first.fit["map_priors"]
    assert any(d["joint"] == 2 and d["anchored_knots"] > 0
               for d in filled.calibrated.fit["reuse_priors"])
