"""``auto``'s linear thermal term (ADR 0042): it recovers a planted link growth per °C when
temperatures vary, and is never taken when they do not (or when they vary without effect)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

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


def test_model_at_temperatures_predicts_with_the_term_folded_in():
    """``at_temperatures`` (compensation at production temperatures): plain kinematics that
    predict what the model plus its thermal term predicts, and the warm robot."""
    from robocal.errors import ConfigError
    from robocal.identification import at_temperatures

    n = 250
    temps = np.random.default_rng(7).uniform(20.0, 30.0, (n, 6))
    cell, drift, data = _data(n, temps, planted=True)
    cal = fit(cell.robot, data, "auto", options=FAST).calibrated
    assert cal.fit["thermal"]["selected"]
    hot = np.array([28.0, 27.0, 29.0, 26.0, 25.0, 24.0])
    warm = at_temperatures(cal, hot)
    q = cell.random_joints(40, np.random.default_rng(3), margin_rad=0.3)
    expected = cal.predict(q) + thermal_shift(cal, q, np.tile(hot, (40, 1)))
    np.testing.assert_allclose(warm.predict(q), expected, atol=1e-12)
    truth = drift.positions(cell, q, np.tile(hot, (40, 1)))
    assert (np.linalg.norm(warm.predict(q) - truth, axis=1).max()
            < 0.5 * np.linalg.norm(cal.predict(q) - truth, axis=1).max())
    # folded in once: no thermal term left to apply again; the reference temperatures give
    # the model's own predictions
    assert "thermal" not in warm.fit and warm.fit["thermal_applied"]["temps_c"] == hot.tolist()
    assert not thermal_shift(warm, q, np.tile(hot, (40, 1))).any()
    at_ref = at_temperatures(cal, cal.fit["thermal"]["t_ref_c"])
    np.testing.assert_allclose(at_ref.predict(q), cal.predict(q), atol=1e-12)
    assert at_ref.model_id != cal.model_id != warm.model_id
    # the covariance follows the parameters it belongs to
    names = list(warm.model.names)
    for i, name in enumerate(cal.model.names):
        assert warm.covariance[names.index(name), names.index(name)] == cal.covariance[i, i]
    with pytest.raises(ConfigError, match="6 finite numbers"):
        at_temperatures(cal, [20.0] * 5)
    with pytest.raises(ConfigError, match="6 finite numbers"):
        at_temperatures(cal, [20.0] * 5 + [float("nan")])
    import dataclasses

    bad = dataclasses.replace(cal, fit={**cal.fit, "thermal": {**cal.fit["thermal"],
                                                               "t_ref_c": [20.0] * 4}})
    with pytest.raises(ConfigError, match="thermal term is malformed"):
        at_temperatures(bad, hot)
    # a model without a thermal term is returned as it is
    const = fit(cell.robot, data, "constant").calibrated
    assert at_temperatures(const, hot) is const


def test_compensate_cli_at_production_temperatures(tmp_path, capsys):
    """``robocal compensate --temps``: the warm robot, commanded with the joints solved at its
    temperatures, reaches the targets better than with the joints solved at the reference."""
    from robocal.cli.main import main
    from robocal.compensation import CompensationTable, TargetSet

    n = 250
    temps = np.random.default_rng(7).uniform(20.0, 30.0, (n, 6))
    cell, drift, data = _data(n, temps, planted=True)
    cal = fit(cell.robot, data, "auto", options=FAST).calibrated
    cal.save(tmp_path / "model.json")
    q = cell.random_joints(10, np.random.default_rng(11), margin_rad=0.4)
    hot = [29.0, 28.0, 30.0, 27.0, 26.0, 25.0]
    TargetSet(p=cell.reflector_position(q), q_seed=q).write_csv(tmp_path / "targets.csv")

    def solve(*extra: str) -> np.ndarray:
        out = tmp_path / "joints.csv"
        assert main(["compensate", "--model", str(tmp_path / "model.json"), "--targets",
                     str(tmp_path / "targets.csv"), "--out", str(out), *extra]) == 0
        rows = out.read_text().splitlines()[1:]
        return np.radians([[float(v) for v in r.split(",")[1:7]] for r in rows])

    q_ref = solve()
    q_hot = solve("--temps", ",".join(map(str, hot)), "--table", str(tmp_path / "t.json"))
    assert "at 29, 28, 30, 27, 26, 25 degC" in capsys.readouterr().out
    target = cell.reflector_position(q)
    reach = {k: np.linalg.norm(drift.positions(cell, qq, np.tile(hot, (10, 1))) - target,
                               axis=1).max() for k, qq in (("ref", q_ref), ("hot", q_hot))}
    assert reach["hot"] < 0.5 * reach["ref"], reach
    table = CompensationTable.read(tmp_path / "t.json")
    assert [table.stats[f"temp{j}_c"] for j in range(1, 7)] == hot
    table.verify()
    # wrong input: one clear error, exit 2
    assert main(["compensate", "--model", str(tmp_path / "model.json"), "--targets",
                 str(tmp_path / "targets.csv"), "--out", str(tmp_path / "j2.csv"),
                 "--temps", "30,30"]) == 2
    assert "--temps must be 6 temperatures" in capsys.readouterr().err
    assert not (tmp_path / "j2.csv").exists()


@settings(max_examples=200, deadline=None)
@given(hs.one_of(hs.text(max_size=60),
                 hs.lists(hs.floats(allow_nan=True, allow_infinity=True), max_size=8).map(
                     lambda v: ",".join(map(str, v)))))
def test_temps_argument_is_six_temperatures_or_one_error(text):
    """``compensate --temps``: any text is either one temperature per joint in range, or a
    ConfigError naming the option (never another exception)."""
    from types import SimpleNamespace

    from robocal.cli._solve_targets import _temperatures
    from robocal.errors import ConfigError

    cal = SimpleNamespace(robot=SimpleNamespace(dof=6),
                          fit={"thermal": {"selected": True}})
    try:
        temps = _temperatures(text, cal)
    except ConfigError as err:
        assert "--temps" in str(err)
    else:
        assert temps is not None and len(temps) == 6
        assert all(-40.0 <= t <= 150.0 for t in temps)
