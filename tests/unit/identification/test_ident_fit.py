"""Maximum-likelihood fit: initialisation, weights, variance factor, covariance, file, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.errors import ConfigError, DataError, NotConverged
from robocal.identification import FitOptions, fit
from robocal.kinematics import CalibratedModel
from robocal.simulation import VirtualCell

from .conftest import make_data


@pytest.fixture(scope="module")
def const_data():
    return make_data("fanuc_lrmate200i", "constant", seed=21, with_sigma=True)


@pytest.fixture(scope="module")
def const_fit(const_data):
    return fit(const_data.cell.robot, const_data.train, "constant",
               validation=const_data.val, options=FitOptions(use_point_sigma=False))


def test_baseline_recovers_base_and_reflector_without_a_guess():
    d = make_data("fanuc_lrmate200i", "nominal", seed=22)
    res = fit(d.cell.robot, d.train, "constant", options=FitOptions(tool_m=(0.0, 0.0, 0.1)))
    base = res.baseline
    T = base.model.base_transform(base.params)
    T_true = d.cell.T_tracker_base
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 5e-5
    ang = np.arccos(np.clip((np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2, -1, 1))
    assert ang < 3e-5
    assert np.linalg.norm(base.params[6:9] - d.cell.truth_params[6:9]) < 5e-5


def test_constant_model_reaches_noise_level_and_unit_variance_factor(const_data, const_fit):
    res = const_fit
    truth = const_data.cell.reflector_position(const_data.val.q)
    err = np.linalg.norm(res.calibrated.predict(const_data.val.q) - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.010e-3          # model error far below tracker noise
    assert 0.8 < res.variance_factor < 1.4
    assert res.validation.percent_described_rms > 95.0
    assert res.converged and res.iterations <= 10


def test_prediction_sigma_matches_actual_prediction_error(const_data, const_fit):
    cal = const_fit.calibrated
    q = const_data.val.q
    z = (cal.predict(q) - const_data.cell.reflector_position(q)) / cal.prediction_sigma(q)
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.6


def test_per_point_sigmas_weight_the_fit(const_data):
    d = const_data
    doubled = MeasurementSet(d.train.q, d.train.p, d.train.sigma * 2.0, d.train.pose_id)
    res = fit(d.cell.robot, doubled, "constant")
    assert 0.15 < res.variance_factor < 0.45          # residuals are half the stated sigma
    assert res.calibrated.data["sigma_source"] == "per-point sx,sy,sz"


def test_tracker_sigma_option_scales_variance_factor(const_data, const_fit):
    from robocal.identification import TrackerSigma

    loose = TrackerSigma(radial_m=10e-6, radial_per_m=1e-6, transverse_m=15e-6,
                         transverse_per_m=6e-6)
    res = fit(const_data.cell.robot, const_data.train, "constant",
              options=FitOptions(noise=loose, use_point_sigma=False))
    assert res.variance_factor == pytest.approx(const_fit.variance_factor / 4, rel=0.1)


def test_model_file_round_trip_is_self_describing(tmp_path, const_data, const_fit):
    cal = const_fit.calibrated
    path = tmp_path / "MODEL.json"
    cal.save(path)
    raw = json.loads(path.read_text())
    assert raw["kind"] == "constant"
    assert raw["data"]["digest"] == const_data.train.digest()
    assert raw["data"]["validation_digest"] == const_data.val.digest()
    ident = raw["fit"]["identifiability"]
    assert ident["rank"] == 27 and len(ident["removed"]) == 18
    assert len(ident["singular_values"]) >= 27 and ident["condition_number"] > 1
    assert raw["fit"]["solver"]["converged"] is True
    assert "Levenberg-Marquardt" in raw["fit"]["solver"]["method"]
    assert raw["fit"]["options"]["rank_tol"] == FitOptions().rank_tol
    assert raw["fit"]["variance_factor"] == pytest.approx(const_fit.variance_factor)
    assert raw["metrics"]["train"]["rms_mm"] == pytest.approx(const_fit.train.rms_m * 1e3,
                                                              rel=1e-5)
    assert "reflector" in raw["metrics"]["baseline"]
    assert len(raw["data"]["coverage_deg"]) == 6
    back = CalibratedModel.load(path)
    q = const_data.val.q[:20]
    np.testing.assert_allclose(back.predict(q), cal.predict(q), atol=1e-12)
    np.testing.assert_allclose(back.prediction_sigma(q), cal.prediction_sigma(q), rtol=1e-6)


def test_summary_is_json_in_mm(const_fit):
    s = json.loads(json.dumps(const_fit.summary()))
    assert s["train"]["rms_mm"] == pytest.approx(const_fit.train.rms_m * 1e3, rel=1e-5)
    assert s["model"] == "constant" and "baseline" in s and s["rank"] == 27


def test_outside_coverage_uses_the_constant_fallback(paper_data):
    res = fit(paper_data.cell.robot, paper_data.train, "high-order")
    cal = res.calibrated
    assert cal.fallback is not None and cal.fallback.kind == "constant"
    q_in = paper_data.val.q[:5]
    q_out = q_in.copy()
    q_out[:, 1] = cal.coverage[1, 1] + 0.05            # beyond the covered range of joint 2
    assert cal.inside_coverage(q_in).all() and not cal.inside_coverage(q_out).any()
    np.testing.assert_allclose(cal.predict(q_out), cal.fallback.predict(q_out))
    np.testing.assert_allclose(cal.predict(q_in), cal.model.positions(q_in, cal.params))


def test_wrong_joint_count_and_nan_are_data_errors(paper_data):
    robot = paper_data.cell.robot
    bad = MeasurementSet(paper_data.train.q[:, :5], paper_data.train.p)
    with pytest.raises(DataError, match="5 joint columns"):
        fit(robot, bad, "constant")
    p = paper_data.train.p.copy()
    p[3, 1] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        fit(robot, MeasurementSet(paper_data.train.q, p), "constant")
    with pytest.raises(DataError, match="validation"):
        fit(robot, paper_data.train, "constant",
            validation=MeasurementSet(paper_data.val.q[:, :4], paper_data.val.p))


def test_unknown_model_and_bad_options_are_config_errors(paper_data):
    with pytest.raises(ConfigError, match="unknown model"):
        fit(paper_data.cell.robot, paper_data.train, "quadratic")
    with pytest.raises(ConfigError):
        FitOptions(rank_tol=2.0)
    with pytest.raises(ConfigError):
        FitOptions(cv_folds=1)
    # it sets how far sparse data widen the map knots: zero would divide by zero there
    with pytest.raises(ConfigError, match="map_min_points"):
        FitOptions(map_min_points=0)
    # robocal fit --map-spacing-deg nan|inf reached the knot count and raised a ValueError
    for bad in (float("nan"), float("inf"), 0.0, -2.0):
        with pytest.raises(ConfigError, match="map_spacing_deg"):
            FitOptions(map_spacing_deg=bad)
    with pytest.raises(ConfigError, match="seed"):        # numpy refused it with a traceback
        FitOptions(seed=-1)
    with pytest.raises(ConfigError, match="auto_min_improvement must be a number"):
        FitOptions(auto_min_improvement=float("nan"))


def test_non_convergence_raises(paper_data):
    with pytest.raises(NotConverged, match="did not converge"):
        fit(paper_data.cell.robot, paper_data.train, "constant",
            options=FitOptions(max_iter=1, tool_m=(0.0, 0.0, 0.0)))


def test_custom_structure_can_be_fitted(paper_data):
    from robocal.simulation import truth_spec

    res = fit(paper_data.cell.robot, paper_data.train, truth_spec(paper_data.cell.robot, "paper"),
              validation=paper_data.val)
    assert res.model == "truth:paper" and res.calibrated.kind == "truth:paper"
    assert res.validation.rms_m < 0.03e-3


def test_auto_offers_no_harmonic_a_joint_with_too_few_angles_can_tell_apart():
    # J6 at three angles only (as in the UR10's ISO-cube series): const + cos + sin of order 1
    # interpolate three values exactly, so order 1 and above are no candidates for J6
    from robocal.identification._auto import candidate_groups
    from robocal.identification._fitter import Fitter

    d = make_data("fanuc_lrmate200i", "paper", seed=3, n_train=120, n_val=10)
    q = d.train.q.copy()
    q[:, 5] = np.radians(np.array([-90.0, 0.0, 90.0]))[np.arange(len(q)) % 3]
    f = Fitter(d.cell.robot, MeasurementSet(q, d.train.p), FitOptions())
    keys = {g.key for g in candidate_groups(f, q)}
    assert not any(k.startswith("j6:fourier") or k.startswith("j6:ripple") for k in keys)
    assert {"j5:fourier1", "j5:fourier3"} <= keys and "j5:ripple40" in keys


def test_map_knots_widen_where_the_data_are_too_sparse_for_the_finest_spacing():
    # 1.25 deg knots on 250 poses put less than one pose in a knot's support; the spacing
    # widens until a support holds map_min_points poses on average; dense data keep 1.25 deg
    from robocal.identification._auto import candidate_groups
    from robocal.identification._fitter import Fitter

    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=4)
    rng = np.random.default_rng(4)
    for n, widened in ((250, True), (4000, False)):
        q = cell.random_joints(n, rng)
        f = Fitter(cell.robot, MeasurementSet(q, np.zeros((n, 3))), FitOptions())
        maps = [g for g in candidate_groups(f, q) if g.is_map]
        assert len(maps) == 6
        for g in maps:
            arc_deg = len(g.knots) * 360.0 / g.n_knots
            per_support = n * 4 * (360.0 / g.n_knots) / arc_deg
            if widened:
                assert g.n_knots < 288 and per_support >= 0.95 * f.opts.map_min_points
            else:
                assert g.n_knots == 288


def test_coverage_extends_linear_terms_by_half_the_span():
    from robocal.identification._fit import _model_coverage
    from robocal.kinematics import ErrorModelSpec, Term, load_robot

    robot = load_robot("fanuc_lrmate200i")
    lim = np.asarray(robot.joint_limits)
    rng = np.random.default_rng(0)
    q = rng.uniform(lim[:, 0] * 0.5, lim[:, 1] * 0.5, (200, 6))
    q[:, 5] = rng.uniform(-np.pi, np.pi, 200)            # joint 6: a full turn
    harm = [Term(j, "ez", f, 1) for j in (2, 5) for f in ("cos", "sin")]
    pitch = [Term(j, "ez", "poly", 1) for j in (0, 2, 5)]
    terms = (*harm, *pitch, Term(3, "ez", "poly", 2))
    spec = ErrorModelSpec(6, terms, (0,) * 6, label="t")
    cov = _model_coverage(spec, robot, q, 5.0)
    lo, hi, span = q.min(axis=0), q.max(axis=0), np.ptp(q, axis=0)
    m = np.radians(5.0)
    # joint 1, pitch alone: half the span beyond the data on each side, inside the limits
    np.testing.assert_allclose(cov[0], [max(lim[0, 0], lo[0] - span[0] / 2),
                                        min(lim[0, 1], hi[0] + span[0] / 2)])
    assert cov[0, 1] - cov[0, 0] > span[0] + 2 * m
    # joint 2, no dependent term: the whole range
    np.testing.assert_allclose(cov[1], lim[1])
    # joint 3, a harmonic over part of a turn next to the pitch: the data and the margin only
    np.testing.assert_allclose(cov[2], [lo[2] - m, hi[2] + m])
    # joint 4, a quadratic: the data and the margin only
    np.testing.assert_allclose(cov[3], [lo[3] - m, hi[3] + m])
    # joint 6, a harmonic over a full turn and the pitch: widened to the limits
    np.testing.assert_allclose(cov[5], [max(lim[5, 0], lo[5] - span[5] / 2),
                                        min(lim[5, 1], hi[5] + span[5] / 2)])
