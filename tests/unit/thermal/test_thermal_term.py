"""``auto``'s linear thermal term (ADR 0042): it recovers a planted link growth per °C when
temperatures vary, and is never taken when they do not (or when they vary without effect)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.identification import FitOptions, accuracy, fit, thermal_shift
from robocal.identification._thermal import MIN_VARIATION_C
from robocal.simulation import VirtualCell, WarmUpDrift

pytestmark = pytest.mark.timeout(120)

FAST = FitOptions(auto_maps=False, auto_max_order=1, auto_ripple_orders=(),
                  auto_strain_wave=False, auto_gravity=False)


def _data(n: int, temps: np.ndarray, *, planted: bool, seed: int = 0
          ) -> tuple[VirtualCell, WarmUpDrift, MeasurementSet]:
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=seed)
    drift = WarmUpDrift.planted(cell.robot, drift_m=1e-4)
    rng = np.random.default_rng(seed + 1)
    q = cell.random_joints(n, rng, margin_rad=0.3)
    p = drift.positions(cell, q, temps) if planted else cell.reflector_position(q)
    p = p + cell.noise.sample(p, rng)
    return cell, drift, MeasurementSet(q, p, temps=temps)


def _warming(n: int, rng: np.random.Generator) -> np.ndarray:
    """Joint temperatures of a campaign on a cold robot: rising 0..8 degC over the poses."""
    return 20.0 + np.linspace(0.0, 8.0, n)[:, None] * np.linspace(1.0, 0.5, 6)[None, :] \
        + rng.normal(0.0, 0.05, (n, 6))


def test_thermal_term_recovers_the_planted_growth_per_degree():
    """Joints warmed independently of each other (a campaign's joints warm together, which
    leaves only combinations of the coefficients identifiable)."""
    n = 250
    temps = np.random.default_rng(7).uniform(20.0, 30.0, (n, 6))
    cell, drift, data = _data(n, temps, planted=True)
    res = fit(cell.robot, data, "auto", options=FAST)
    term = res.calibrated.fit.get("thermal")
    assert term is not None and term["selected"], res.selection
    coef = np.asarray(term["coef_mm_per_c"]) * 1e-3
    sigma = np.asarray(term["sigma_mm_per_c"]) * 1e-3
    truth = drift.growth_m_per_c
    # within 4 of the reported standard deviations, which are a tenth of the largest
    assert np.all(np.abs(coef - truth) < 4.0 * sigma), (coef, truth, sigma)
    assert np.all(sigma < 0.15 * np.max(truth))
    assert np.allclose(term["t_ref_c"], temps.mean(axis=0))
    # the model with its thermal term predicts the warm robot; without it, it cannot
    q = cell.random_joints(50, np.random.default_rng(3), margin_rad=0.3)
    hot = np.full((50, 6), 28.0)
    truth_hot = drift.positions(cell, q, hot)
    with_term = res.calibrated.predict(q) + thermal_shift(res.calibrated, q, hot)
    err_with = np.linalg.norm(with_term - truth_hot, axis=1).max()
    err_without = np.linalg.norm(res.calibrated.predict(q) - truth_hot, axis=1).max()
    assert err_with < 0.5 * err_without
    thermal = next(e for e in res.selection if e["action"] == "thermal")
    assert thermal["selected"] and res.selection[-1]["thermal"]
    # the reported accuracy applies the term at each pose's temperatures
    assert res.train.rms_m == pytest.approx(accuracy(res.calibrated, data).rms_m)
    assert res.train.rms_m < 0.9 * accuracy(res.calibrated, MeasurementSet(data.q, data.p)).rms_m


def test_no_thermal_term_without_temperature_variation():
    n = 150
    temps = np.full((n, 6), 24.0) + np.random.default_rng(2).normal(0.0, 0.05, (n, 6))
    cell, _, data = _data(n, temps, planted=True)
    res = fit(cell.robot, data, "auto", options=FAST)
    note = next(e for e in res.selection if e["action"] == "thermal")
    assert note["action"] == "thermal" and note["considered"] is False
    assert str(MIN_VARIATION_C) in note["reason"]
    assert "thermal" not in res.calibrated.fit


def test_varying_temperatures_without_effect_are_not_taken():
    """Temperatures that vary a lot but move nothing: CV finds no gain, nothing is taken."""
    n = 200
    temps = _warming(n, np.random.default_rng(5))
    cell, _, data = _data(n, temps, planted=False, seed=4)
    res = fit(cell.robot, data, "auto", options=FAST)
    note = next(e for e in res.selection if e["action"] == "thermal")
    assert note["considered"] is True and note["selected"] is False, note
    assert "thermal" not in res.calibrated.fit


def test_fit_cli_reads_temperature_columns_and_names_the_term(tmp_path, capsys):
    from robocal.cli.main import main

    n = 120
    temps = np.random.default_rng(4).uniform(20.0, 30.0, (n, 6))
    _, _, data = _data(n, temps, planted=True, seed=1)
    data.write_csv(tmp_path / "meas.csv")
    assert "temp6" in (tmp_path / "meas.csv").read_text().splitlines()[0]
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(tmp_path / "meas.csv"),
                 "--out", str(tmp_path / "model.json")]) == 0
    out = capsys.readouterr().out
    assert "thermal term: taken, +0.00" in out and "mm/degC per link" in out
    model = json.loads((tmp_path / "model.json").read_text())
    assert model["fit"]["thermal"]["selected"] is True
