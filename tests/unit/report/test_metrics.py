"""The report's numbers: % described, ISO 9283, joint-error bands, verdict, stored metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel, Term, load_robot
from robocal.report import (
    Acceptance,
    Described,
    ErrorStats,
    IsoPoseSeries,
    Judged,
    described,
    fit_nominal_baseline,
    iso9283,
    iso_series_from_measurements,
    joint_curves,
    verdict,
)
from robocal.report._metrics import identifiability, stats_from_stored
from robocal.simulation import VirtualCell


def test_described_matches_the_paper_definitions() -> None:
    e = np.array([1.0, 2.0, 2.0])      # baseline error norms
    r = np.array([0.1, 0.2, 0.5])      # model residual norms
    d = described(e, r)
    assert d.rms == pytest.approx(100 * (1 - math.sqrt(0.30 / 9.0)))
    assert d.mean == pytest.approx(100 * (1 - (0.8 / 3) / (5 / 3)))
    assert d.r2 == pytest.approx(100 * (1 - 0.30 / 9.0))
    assert described(e, e).rms == pytest.approx(0.0)
    assert described(np.zeros(3), r) == Described(None, None, None)
    with pytest.raises(ConfigError):
        described(e, r[:2])


def test_error_stats() -> None:
    s = ErrorStats.of(np.array([3e-3, 4e-3]))
    assert s.n == 2 and s.rms_m == pytest.approx(math.sqrt(12.5) * 1e-3)
    assert s.mean_m == pytest.approx(3.5e-3) and s.max_m == pytest.approx(4e-3)
    assert s.to_dict()["rms_mm"] == pytest.approx(math.sqrt(12.5))
    assert ErrorStats.of(np.array([])).n == 0


def test_iso9283_by_hand() -> None:
    # four attained points on a square of side 2 µm around (1, 2, 3) mm; command 10 µm off in x
    bary = np.array([1e-3, 2e-3, 3e-3])
    pts = bary + 1e-6 * np.array([[1, 1, 0], [1, -1, 0], [-1, 1, 0], [-1, -1, 0.0]])
    s = IsoPoseSeries("P1", bary - np.array([10e-6, 0, 0]), pts,
                      predicted=bary + np.array([0, 3e-6, 4e-6]))
    r = iso9283(s)
    assert r.n == 4
    assert r.ap_m == pytest.approx(10e-6)
    assert r.ap_xyz_m == pytest.approx((10e-6, 0.0, 0.0), abs=1e-15)
    # all distances to the barycentre are sqrt(2) µm, so S_l = 0 and RP = l̄
    assert r.rp_m == pytest.approx(math.sqrt(2) * 1e-6)
    assert r.ap_model_m == pytest.approx(5e-6)
    # a spread in distances adds 3 S_l
    pts2 = np.array([[0, 0, 0], [2e-6, 0, 0], [-2e-6, 0, 0], [0, 4e-6, 0]])
    pts2 = pts2 - pts2.mean(axis=0)
    r2 = iso9283(IsoPoseSeries("P2", np.zeros(3), pts2))
    lj = np.linalg.norm(pts2, axis=1)
    assert r2.rp_m == pytest.approx(lj.mean() + 3 * lj.std(ddof=1))
    assert r2.ap_m == pytest.approx(0.0, abs=1e-18)
    # one cycle: AP is defined, RP (a spread) is not
    one = iso9283(IsoPoseSeries("P4", np.zeros(3), np.array([[1e-3, 0, 0]])))
    assert one.ap_m == pytest.approx(1e-3) and one.rp_m is None
    assert one.to_dict()["RP_mm"] is None
    with pytest.raises(ConfigError):
        IsoPoseSeries("P3", np.zeros(3), np.zeros((2, 2)))


def test_iso_series_grouping() -> None:
    q = np.zeros((6, 2))
    p = np.arange(18, dtype=float).reshape(6, 3)
    data = MeasurementSet(q, p)
    series = iso_series_from_measurements(
        data, ["iso-P1", "iso-P2", "iso-P1", "calibration", "P2", "iso-p1"],
        command=np.ones((6, 3)))
    assert [s.name for s in series] == ["P1", "P2"]
    np.testing.assert_array_equal(series[0].attained, p[[0, 2, 5]])
    np.testing.assert_array_equal(series[1].attained, p[[1, 4]])
    assert series[0].predicted is None
    with pytest.raises(ConfigError):
        iso_series_from_measurements(data, ["iso-P1"], command=np.ones((6, 3)))


def _single_term_model(value: float, sigma: float) -> CalibratedModel:
    robot = load_robot("fanuc_lrmate200i")
    spec = ErrorModelSpec(6, (Term(0, "ez", "const"), Term(0, "ez", "cos", 2),
                              Term(1, "dx", "sin", 1)))
    m = KinematicModel(robot, spec)
    x = m.nominal_params()
    x[10] = value   # j1.ez.cos2
    x[11] = 2e-5    # j2.dx.sin1
    cov = np.zeros((m.size, m.size))
    cov[10, 10] = sigma**2
    cov[11, 11] = (1e-6) ** 2
    return CalibratedModel(m, x, cov)


def test_joint_curve_value_and_band() -> None:
    cm = _single_term_model(1e-4, 2e-5)
    jc = joint_curves(cm, 0, points=91)
    assert [c.component for c in jc.curves] == ["ez"]   # the constant term is not a curve
    b = np.cos(2 * jc.angle)
    b = b - b.mean()                                      # centred over the covered range
    np.testing.assert_allclose(jc.curves[0].value, 1e-4 * b, atol=1e-15)
    np.testing.assert_allclose(jc.curves[0].sigma, 2e-5 * np.abs(b), atol=1e-15)
    jc2 = joint_curves(cm, 1, points=91)
    assert [c.component for c in jc2.curves] == ["dx"]
    assert joint_curves(cm, 2).curves == ()
    # a removed term is not drawn
    assert joint_curves(cm, 1, removed=["j2.dx.sin1"]).curves == ()


def _judged(rms_mm: float, base_mm: float = 1.0, *, on: str = "validation",
            cal_mm: float | None = None, outliers: int = 0, status: str = "") -> Judged:
    st = ErrorStats(50, rms_mm * 1e-3, rms_mm * 0.9e-3, rms_mm * 2e-3)
    b = ErrorStats(50, base_mm * 1e-3, base_mm * 0.9e-3, base_mm * 2e-3)
    d = Described(100 * (1 - rms_mm / base_mm), None, None)
    return Judged("auto", on, st, b, d, None if cal_mm is None else cal_mm * 1e-3,
                  n_outliers=outliers, n_poses=200, status=status)


def test_verdict_succeeds() -> None:
    v = verdict(_judged(0.05, 1.0, cal_mm=0.045), Acceptance())
    assert v.outcome == "succeeded"
    assert "0.050 mm" in v.headline and "95.0 %" in v.headline
    assert {c.name for c in v.checks} == {"improvement", "RMS limit", "over-fitting",
                                          "outliers"}
    assert all(c.status == "pass" for c in v.checks)


@pytest.mark.parametrize(("judged", "acc", "outcome", "phrase"), [
    (_judged(1.2, 1.0), Acceptance(), "failed", "does not improve"),
    (_judged(0.05, 1.0), Acceptance(max_rms_mm=0.04), "failed", "limit 0.040 mm"),
    (_judged(0.05, 1.0), Acceptance(max_error_mm=0.08), "failed", "max error"),
    (_judged(0.05, 1.0, outliers=50), Acceptance(), "failed", "50 of 200"),
    (_judged(0.05, 1.0, status="not converged"), Acceptance(), "failed", "status"),
    (_judged(0.7, 1.0), Acceptance(max_rms_mm=None), "marginal", "only 30.0 %"),
    # the default absolute limit: describing 65 % of a 2 mm error still leaves 0.7 mm
    (_judged(0.7, 2.0), Acceptance(), "failed", "limit 0.500 mm"),
    # joints read as radians: never "marginal", whatever the limits
    (_judged(411.0, 1500.0), Acceptance(max_rms_mm=None), "failed", "implausible"),
    (_judged(0.05, 1.0, on="calibration"), Acceptance(), "marginal", "no validation poses"),
    (_judged(0.05, 1.0, outliers=20), Acceptance(), "marginal", "20 of 200"),
    (_judged(0.05, 1.0, cal_mm=0.02), Acceptance(), "marginal", "ratio 2.50"),
])
def test_verdict_fails_or_is_marginal(judged: Judged, acc: Acceptance, outcome: str,
                                      phrase: str) -> None:
    v = verdict(judged, acc)
    assert v.outcome == outcome
    assert phrase.lower() in v.reason.lower() and phrase in v.headline
    assert v.headline.startswith("Calibration failed" if outcome == "failed"
                                 else "Calibration is marginal")


def test_verdict_without_anything() -> None:
    assert verdict(None, Acceptance()).outcome == "failed"


def test_overfit_floor_keeps_noise_level_ratios_quiet() -> None:
    # 8 µm vs 4 µm is a ratio of 2 but only 4 µm apart: below the 5 µm floor
    v = verdict(_judged(0.008, 1.0, cal_mm=0.004), Acceptance())
    assert v.outcome == "succeeded"


def test_acceptance_from_mapping() -> None:
    a = Acceptance.from_mapping({"max_rms_mm": 0.1, "min_percent_described": 80})
    assert a.max_rms_mm == 0.1 and a.min_percent_described == 80
    with pytest.raises(ConfigError, match=r"acceptance\.max_rms"):
        Acceptance.from_mapping({"max_rms": 0.1})
    with pytest.raises(ConfigError):
        Acceptance(max_rms_mm=-1.0)


def test_stats_from_stored_reads_mm_and_m() -> None:
    st, d, b = stats_from_stored({"rms_mm": 0.02, "mean_mm": 0.018, "max_mm": 0.05, "n": 50,
                                  "percent_described_rms": 97.0, "baseline_rms_mm": 1.1})
    assert st is not None and st.rms_m == pytest.approx(2e-5) and st.n == 50
    assert d is not None and d.rms == 97.0 and d.mean is None
    assert b is not None and b.rms_m == pytest.approx(1.1e-3)
    st, d, b = stats_from_stored({"rms_m": 2e-5})
    assert st is not None and st.rms_m == 2e-5 and d is None and b is None
    assert stats_from_stored({}) == (None, None, None)


def test_nominal_baseline_registers_base_and_reflector(rng: np.random.Generator) -> None:
    cell = VirtualCell.create("fanuc_lrmate200i", "nominal", seed=3)
    q = cell.random_joints(40, rng)
    qc, p, s, _ = cell.simulate(q, rng)
    data = MeasurementSet(qc, p, s)
    start = KinematicModel(cell.robot, ErrorModelSpec.constant(6), cell.truth_model.T_ref)
    b = fit_nominal_baseline(CalibratedModel(start, start.nominal_params()), data)
    err = np.linalg.norm(data.p - b.predict(data.q), axis=1)
    assert np.sqrt(np.mean(err**2)) < 3e-5          # tracker noise level, not millimetres
    assert b.kind == "nominal" and len(b.model.spec) == 0


def test_identifiability_of_a_fit(campaign: object) -> None:
    ho = campaign.fits["high-order"]  # type: ignore[attr-defined]
    cm = ho.calibrated
    idt = identifiability(cm, campaign.cal.q, ho.removed)  # type: ignore[attr-defined]
    assert idt.n_params == cm.model.size
    assert idt.n_free == cm.model.size - len(ho.removed)
    assert idt.rank == idt.n_free and 1 < idt.condition < 1e6
    assert len(idt.correlations) == 12
    assert all(abs(r) <= 1 + 1e-9 for _, _, r in idt.correlations)
    rho = [abs(r) for _, _, r in idt.correlations]
    assert rho == sorted(rho, reverse=True)
    removed = {p["name"] for p in idt.parameters if p["removed"]}
    assert removed == set(ho.removed)


def test_weather_ranges_accept_driver_spellings() -> None:
    from robocal.report._html import weather_ranges

    got = weather_ranges([{"temp_c": 20.4, "press_hpa": 1012.6, "hum_pct": 41.0, "co2": 400},
                          {"temperature_c": 21.0}])
    assert got == [("air temperature", "°C", [20.4, 21.0]),
                   ("air pressure", "hPa", [1012.6]), ("humidity", "%", [41.0]),
                   ("weather: co2", "", [400.0])]
