"""Circle Point Analysis in the report: classical and polished rows, and the flag (with its
reasons and amounts) when CPA is worse than the nominal model."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.identification import CPAResult, cpa_fit
from robocal.identification._cpa import cpa_sweeps
from robocal.kinematics import CalibratedModel
from robocal.report import ReportInput, analyse, write_report
from robocal.report._cpa import CpaComparison, CpaRow
from tests.unit.report.conftest import Campaign


def _cpa(c: Campaign, short: tuple[int, ...], short_deg: float) -> CPAResult:
    """CPA on the campaign's cell; joints in ``short`` sweep only ``short_deg``."""
    rng = np.random.default_rng(3)
    full = dict(cpa_sweeps(c.cell.robot, n_points=20))
    part = dict(cpa_sweeps(c.cell.robot, n_points=20, span_deg=short_deg))
    sweeps = []
    for j in range(6):
        q, p, s, _ = c.cell.simulate(part[j] if j in short else full[j], rng)
        sweeps.append((j, MeasurementSet(q, p, s)))
    return cpa_fit(c.cell.robot, sweeps, validation=c.val,
                   baseline=c.fits["nominal"].calibrated)


@pytest.fixture(scope="module")
def short_cpa(campaign: Campaign) -> CPAResult:
    """Every arc 60°: polished CPA is worse than nominal on this cell, classical a little
    better."""
    return _cpa(campaign, tuple(range(6)), 60.0)


@pytest.fixture(scope="module")
def good_cpa(campaign: Campaign) -> CPAResult:
    """J1 and J5 on 50°, the rest full: both CPA models beat nominal."""
    return _cpa(campaign, (0, 4), 50.0)


def _input(c: Campaign, cpa: object) -> ReportInput:
    return ReportInput(models={"nominal": c.fits["nominal"].calibrated,
                               "constant": c.fits["constant"], "cpa": cpa},
                       calibration=c.cal, validation=c.val, workspace_samples=50)


def test_flag_when_cpa_is_worse_than_nominal(campaign: Campaign, short_cpa: CPAResult,
                                             tmp_path: Path) -> None:
    assert short_cpa.validation.percent_described_rms < 0               # the premise
    assert short_cpa.classical_validation.percent_described_rms > 0
    h, j = write_report(_input(campaign, short_cpa), tmp_path / "r.html")
    page = h.read_text(encoding="utf-8")
    summ = json.loads(j.read_text())
    cpa = summ["cpa"]
    assert cpa["worse_than_nominal"] == ["cpa"]
    rows = {r["model"]: r for r in cpa["models"]}
    assert rows["cpa"]["variant"] == "polished" and rows["cpa-classical"]["variant"] == "classical"
    nominal = summ["accuracy"]["nominal"]["validation"]["rms_mm"]
    for name, acc in (("cpa", short_cpa.validation),
                      ("cpa-classical", short_cpa.classical_validation)):
        r = rows[name]
        assert r["rms_mm"] == pytest.approx(acc.rms_m * 1e3, rel=1e-9)
        assert r["nominal_rms_mm"] == pytest.approx(nominal, rel=1e-9)
        assert r["difference_mm"] == pytest.approx(r["rms_mm"] - nominal, rel=1e-9)
        assert r["difference_percent"] == pytest.approx(100 * (r["rms_mm"] / nominal - 1))
        assert r["better_than_nominal"] == (name == "cpa-classical")
        # the page says by how much, in mm and %, either way
        how = "better" if r["better_than_nominal"] else "worse"
        assert (f"{r['variant'].capitalize()} CPA is {how} than the nominal model by "
                f"{abs(r['difference_mm']):.3f} mm ({abs(r['difference_percent']):.0f} %)"
                in page)
    # the reasons name the joints, from the circle fits
    reasons = " ".join(cpa["reasons"])
    assert "short arcs (J1 60°, J2 60°, J3 60°, J4 60°, J5 60°, J6 60°; < 90°)" in reasons
    small = [f"J{c.joint + 1}" for c in short_cpa.circles if c.radius < 0.1]
    assert small and all(k in reasons.split("small circle radii")[1] for k in small)
    assert cpa["flag"].startswith("Polished CPA is worse than the nominal model by")
    # visible: on the first screen and in the CPA section, which the contents link to
    assert page.count('data-flag="cpa-worse-than-nominal"') == 2
    assert page.index('data-flag="cpa-worse-than-nominal"') < page.index('id="accuracy"')
    assert '<section id="cpa">' in page and 'href="#cpa"' in page
    assert "short arcs (J1 60°" in page
    # both CPA models are in the accuracy tables and the JSON accuracy
    assert {"cpa", "cpa-classical"} <= set(summ["accuracy"])
    assert "Circle Point Analysis, classical (not polished)" in page


def test_no_flag_and_the_gain_when_cpa_beats_nominal(campaign: Campaign,
                                                      good_cpa: CPAResult) -> None:
    an = analyse(_input(campaign, good_cpa))
    assert an.cpa is not None and an.cpa.flag is None and not an.cpa.worse
    rows = {r.name: r for r in an.cpa.rows}
    assert set(rows) == {"cpa", "cpa-classical"}
    pol = rows["cpa"]
    assert pol.better and pol.rms_m == pytest.approx(good_cpa.validation.rms_m)
    assert pol.diff_percent == pytest.approx(good_cpa.validation.percent_described_rms * -1)
    assert pol.sentence().startswith("Polished CPA is better than the nominal model by "
                                     f"{-pol.diff_m * 1e3:.3f} mm")
    # the circle table shows the weaknesses even when CPA wins
    assert {i["issue"] for i in an.cpa.diagnosis} >= {"short arc", "small radius"}


def test_classical_cpa_comes_back_from_the_model_file(campaign: Campaign,
                                                      good_cpa: CPAResult) -> None:
    # a report made from MODEL-cpa.json alone still shows classical and polished CPA
    loaded = CalibratedModel.from_dict(json.loads(json.dumps(good_cpa.calibrated.to_dict())))
    an = analyse(_input(campaign, loaded))
    assert {"cpa", "cpa-classical"} <= set(an.models)
    cls = an.models["cpa-classical"].sets["validation"].stats
    assert cls.rms_m == pytest.approx(good_cpa.classical_validation.rms_m, rel=1e-9)
    assert an.cpa is not None and an.cpa.polish is not None
    assert an.cpa.polish["sweep_points"] == 120


def test_reasons_include_joint_dependent_errors() -> None:
    diag = [{"joint": 2, "issue": "joint-dependent errors", "value": 6.4, "limit": 2.0},
            {"joint": 1, "issue": "short arc", "value": 54.0, "limit": 90.0},
            {"joint": 6, "issue": "small radius", "value": 39.0, "limit": 100.0},
            {"joint": 4, "issue": "small radius", "value": 28.2, "limit": 100.0}]
    c = CpaComparison([CpaRow("cpa-classical", "classical", "validation", 50, 2.036e-3,
                              0.958e-3),
                       CpaRow("cpa", "polished", "validation", 50, 0.361e-3, 0.958e-3)],
                      diagnosis=diag)
    assert [r.name for r in c.worse] == ["cpa-classical"]
    assert c.reasons() == [
        "short arcs (J1 54°; < 90°): the circles' centres and axes are poorly determined",
        "small circle radii (J6 39 mm, J4 28 mm; < 100 mm): the axis directions are poorly "
        "determined",
        "circle residuals far above the tracker noise (J2 6.4×; > 2×): CPA cannot describe "
        "joint-dependent errors"]
    assert c.flag is not None and c.flag.startswith(
        "Classical CPA is worse than the nominal model by 1.078 mm (113 %)")
    assert "Polished" not in c.flag
    d = c.to_dict()
    assert d["worse_than_nominal"] == ["cpa-classical"] and len(d["reasons"]) == 3
    none = CpaComparison([CpaRow("cpa", "polished", "validation", 5, 2e-3, 1e-3)])
    assert "no short arc, small radius or excess residual" in none.reasons()[0]


def test_cpa_worse_than_nominal_under_another_models_verdict_is_a_reference_not_an_alarm(
        campaign: Campaign, short_cpa: CPAResult, tmp_path: Path) -> None:
    """No red CPA alarm right under the verdict about another model: a grey note that says
    CPA is a reference and not applicable here; red only when the verdict is about CPA."""
    inp = _input(campaign, short_cpa)
    inp.selected = "constant"
    h, _ = write_report(inp, tmp_path / "r.html")
    page = h.read_text(encoding="utf-8")
    first = page[:page.index('id="accuracy"')]
    assert '<div class="flag info" data-flag="cpa-worse-than-nominal">' in first
    assert '<div class="flag" data-flag="cpa-worse-than-nominal">' not in page
    assert "for reference only (not applicable here; the verdict above is about constant)" \
        in first
    assert "worse: not applicable" in page and "more than doubles the error" in page
    inp = _input(campaign, short_cpa)
    inp.selected = "cpa"
    h, _ = write_report(inp, tmp_path / "c.html")
    page = h.read_text(encoding="utf-8")
    assert page.count('<div class="flag" data-flag="cpa-worse-than-nominal">') == 2


def test_the_default_rms_limit_grows_with_the_robots_reach() -> None:
    from robocal.report import Acceptance

    acc = Acceptance()
    assert acc.for_reach(1.2).max_rms_mm == 0.5          # an LR Mate keeps 0.5 mm
    assert acc.for_reach(4.056).max_rms_mm == pytest.approx(1.014)  # a KR 210 R3100
    given = Acceptance.from_mapping({"max_rms_mm": 0.3})
    assert given.for_reach(4.056).max_rms_mm == 0.3      # a limit given is kept
    assert Acceptance.from_mapping({"min_percent_described": 60}).scale_with_reach


def test_the_overview_uses_a_log_axis_when_bars_span_decades(campaign: Campaign) -> None:
    """0.009 mm next to 2.5 mm: the overview switches to a log axis (both bars visible)."""
    from robocal.report._figures import needs_log_axis, summary_plot
    from tests.unit.report.svgdoc import figures, texts

    assert needs_log_axis(np.array([2.5, 1.08, 0.009, np.nan]))
    assert not needs_log_axis(np.array([0.5, 0.1, 0.05]))
    an = analyse(ReportInput(models={"nominal": campaign.fits["nominal"].calibrated,
                                     "high-order": campaign.fits["high-order"]},
                             calibration=campaign.cal, validation=campaign.val,
                             workspace_samples=50))
    rms = [st.rms_m for m in an.models.values() for s in m.sets.values()
           if (st := s.stats) is not None]
    assert max(rms) / min(rms) > 20  # the premise: nominal vs high-order
    p = summary_plot(an)
    assert p is not None
    (svg,) = figures(p.svg)
    words = texts(svg)
    assert "RMS position error (mm, log scale)" in words
    assert {"0.01", "0.1", "1"} <= set(words)  # decades on the axis
    assert {"calibration", "validation", "nominal", "high-order"} <= set(words)
