"""write_report end to end: the numbers in the page and the JSON come from the data, the plots
exist and decode, the page is self-contained, and the verdict goes both ways."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel
from robocal.report import Acceptance, MeasurementLog, ReportInput, write_report
from tests.unit.report.conftest import Campaign
from tests.unit.report.svgdoc import NS, figures, texts, title


@dataclass
class Written:
    html: str
    summary: dict[str, Any]
    html_path: Path
    json_path: Path


@pytest.fixture(scope="module")
def full(campaign: Campaign, tmp_path_factory: pytest.TempPathFactory) -> Written:
    fits = campaign.fits
    inp = ReportInput(
        models={"nominal": fits["nominal"].calibrated, "constant": fits["constant"],
                "high-order": fits["high-order"], "auto": fits["high-order"]},
        calibration=campaign.cal, validation=campaign.val, iso=campaign.iso,
        log=MeasurementLog(planned=250, measured=250, retries=4, beam_losses=2,
                           weather=[{"temperature_c": 20.5, "pressure_hpa": 1010.0},
                                    {"temperature_c": 21.5, "pressure_hpa": 1012.0}],
                           tracker="virtual tracker"),
        campaign_id="C-42", workspace_samples=300)
    h, j = write_report(inp, tmp_path_factory.mktemp("rep") / "report.html")
    return Written(h.read_text(encoding="utf-8"), json.loads(j.read_text()), h, j)


def _norms(cm: CalibratedModel, data: Any, drop: tuple[str, ...]) -> np.ndarray:
    keep = np.array([p not in set(drop) for p in data.pose_id])
    return np.linalg.norm(data.p[keep] - cm.predict(data.q[keep]), axis=1)


def test_files_and_verdict(full: Written) -> None:
    assert full.html_path.name == "report.html" and full.json_path.name == "report.json"
    s = full.summary
    assert s["format"] == "robocal.report/1"
    assert s["verdict"]["outcome"] == "succeeded" and s["judged_on"] == "validation"
    assert s["selected_model"] == "auto" and s["campaign_id"] == "C-42"
    assert 'class="verdict succeeded"' in full.html
    assert "Calibration succeeded" in full.html
    assert s["robot"]["name"] in full.html and s["model_id"] in full.html


def test_numbers_come_from_the_data(campaign: Campaign, full: Written) -> None:
    s = full.summary
    out = campaign.outliers
    assert sorted(s["outliers"]) == sorted(out)
    base = campaign.fits["nominal"].calibrated
    for name, fit_name in (("constant", "constant"), ("auto", "high-order")):
        cm = campaign.fits[fit_name].calibrated
        for which, data in (("calibration", campaign.cal), ("validation", campaign.val)):
            r = _norms(cm, data, out)
            e = _norms(base, data, out)
            got = s["accuracy"][name][which]
            assert got["n"] == len(r)
            rms = float(np.sqrt(np.mean(r**2))) * 1e3
            assert got["rms_mm"] == pytest.approx(rms, rel=1e-12)
            assert got["max_mm"] == pytest.approx(r.max() * 1e3, rel=1e-12)
            pr = 100 * (1 - np.sqrt(np.sum(r**2) / np.sum(e**2)))
            pm = 100 * (1 - r.mean() / e.mean())
            assert got["percent_described_rms"] == pytest.approx(pr, rel=1e-12)
            assert got["percent_described_mean"] == pytest.approx(pm, rel=1e-12)
            # and the page shows them, mm with 3 decimals, % with 1
            assert f"{rms:.3f}" in full.html and f"{pr:.1f} %" in full.html
    assert s["accuracy"]["auto"]["calibration"]["n"] == len(campaign.cal) - len(out)
    # the outliers appear in the log, the rejected-outlier check counts them
    for pid in out:
        assert pid in full.html
    n_all = len(campaign.cal) + len(campaign.val)
    assert f"{len(out)} of {n_all} poses rejected as outliers" in full.html
    assert full.summary["validation_glitches"] == []


def test_iso_and_workspace_and_log(campaign: Campaign, full: Written) -> None:
    s = full.summary
    assert [r["pose"] for r in s["iso9283"]] == ["P1", "P2", "P3", "P4", "P5"]
    for series, r in zip(campaign.iso, s["iso9283"], strict=True):
        bary = series.attained.mean(axis=0)
        assert r["AP_mm"] == pytest.approx(np.linalg.norm(bary - series.command) * 1e3)
        assert f"{r['AP_mm']:.3f}" in full.html and f"{r['RP_mm']:.3f}" in full.html
    w = s["workspace"]
    assert w["samples"] == 300 and 0 < w["sigma_mm"]["median"] < w["sigma_mm"]["max"] < 1
    assert "20.5–21.5 °C" in full.html and "beam losses" in full.html
    assert s["provenance"]["calibration_sha256"] == campaign.cal.digest()
    assert campaign.cal.digest() in full.html
    ident = s["identifiability"]
    assert ident["n_free"] + len(ident["removed"]) == ident["n_parameters"]
    assert ident["condition_number"] > 1
    joints = s["joint_errors"]
    assert joints["model"] == "auto" and len(joints["joints"]) == 6
    assert all(c["max_2sigma"] is not None for j in joints["joints"]
               for c in j["components"].values())


def test_plots_are_inline_svg(full: Written) -> None:
    svgs = figures(full.html)  # every figure is well-formed XML
    assert full.html.count("<figure>") == len(svgs) and "<img" not in full.html
    keys = full.summary["figures"]
    assert set(keys) == {"summary", "histograms", "per_pose", "singular_values", "workspace",
                         "iso", "coverage", *(f"joint{j}" for j in range(1, 7))}
    assert len(svgs) == len(keys)
    for svg in svgs:
        w, h = int(svg.get("width", 0)), int(svg.get("height", 0))
        assert svg.get("viewBox") == f"0 0 {w} {h}" and w > 300 and h > 150
        assert svg.get("role") == "img" and svg.get("aria-label") == title(svg) != ""
        assert len(list(svg.iter(f"{NS}path"))) >= 4 and len(texts(svg)) > 5  # not blank
    ids = re.findall(r' id="([^"]+)"', full.html)
    assert len(ids) == len(set(ids))  # the figures' ids do not collide on the page
    by_alt = {title(s): s for s in svgs}
    per_pose = by_alt["Position error per pose for every model"]
    assert {"nominal", "constant", "high-order", "auto"} <= set(texts(per_pose))
    assert "error (mm, log)" in texts(per_pose)
    joint1 = next(s for a, s in by_alt.items() if a.startswith("Joint 1:"))
    assert {"residuals vs joint angle", "joint 1 (deg)", "constant, val."} <= set(texts(joint1))
    assert any(t.startswith("δx (") for t in texts(joint1))


def test_page_is_self_contained(full: Written) -> None:
    # the figures name their SVG namespace and refer to their own clip paths and patterns
    low = full.html.lower().replace('xmlns="http://www.w3.org/2000/svg"', "")
    low = re.sub(r'url\(#f-[a-z0-9_-]+\)', "", low)
    for bad in ("http://", "https://", "<script", "<link", "url(", "src=\"/", "@import"):
        assert bad not in low, bad
    assert low.startswith("<!doctype html>") and low.rstrip().endswith("</html>")


def test_verdict_failed_end_to_end(campaign: Campaign, tmp_path: Path) -> None:
    nom = campaign.fits["nominal"].calibrated
    # a "calibration" that moved the reflector 0.8 mm: worse than the nominal model
    x = nom.params.copy()
    x[6] += 8e-4
    bad = CalibratedModel(nom.model, x, kind="constant")
    inp = ReportInput(models={"nominal": nom, "auto": bad}, calibration=campaign.cal,
                      validation=campaign.val, workspace_samples=0)
    h, j = write_report(inp, tmp_path / "bad.html")
    s = json.loads(j.read_text())
    page = h.read_text(encoding="utf-8")
    assert s["verdict"]["outcome"] == "failed"
    assert 'class="verdict failed"' in page and "Calibration failed" in page
    assert "does not improve accuracy" in page
    assert s["accuracy"]["auto"]["validation"]["percent_described_rms"] < 0


def test_marginal_on_absolute_limit_and_without_validation(campaign: Campaign,
                                                           tmp_path: Path) -> None:
    fits = campaign.fits
    inp = ReportInput(models={"constant": fits["constant"]}, calibration=campaign.cal,
                      acceptance=Acceptance(min_percent_described=90.0), workspace_samples=0)
    h, j = write_report(inp, tmp_path)           # a directory: report.html inside
    assert h == tmp_path / "report.html" and j == tmp_path / "report.json"
    s = json.loads(j.read_text())
    assert s["verdict"]["outcome"] == "marginal" and s["judged_on"] == "calibration"
    # no nominal given: the report fitted base + reflector itself
    assert "fitted by the report" in s["baseline"]
    assert "nominal" in s["accuracy"]
    checks = {c["check"]: c["status"] for c in s["verdict"]["checks"]}
    assert checks["improvement"] == "warn" and checks["held-out poses"] == "warn"


def test_model_file_alone_uses_stored_metrics(campaign: Campaign, tmp_path: Path) -> None:
    ho = campaign.fits["high-order"].calibrated
    cm = CalibratedModel(ho.model, ho.params, ho.covariance, coverage=ho.coverage,
                         kind="high-order",
                         metrics={"train": {"rms_mm": 0.021, "max_mm": 0.06, "n": 197},
                                  "validation": {"rms_mm": 0.024, "mean_mm": 0.02,
                                                 "max_mm": 0.07, "n": 50,
                                                 "percent_described_rms": 98.0,
                                                 "baseline_rms_mm": 1.2}},
                         fit={"removed": ["j6.ex.cos1"], "outliers": ["P0001"]})
    cm.save(tmp_path / "m.json")
    loaded = CalibratedModel.load(tmp_path / "m.json")
    h, j = write_report(ReportInput(models={"high-order": loaded}, workspace_samples=50),
                        tmp_path / "r.html")
    s = json.loads(j.read_text())
    page = h.read_text(encoding="utf-8")
    assert s["accuracy"]["high-order"]["validation"]["source"] == "stored"
    assert s["accuracy"]["high-order"]["validation"]["rms_mm"] == pytest.approx(0.024)
    assert s["verdict"]["outcome"] == "succeeded"
    assert "0.024 mm" in page and "1.200 mm" in page and "98.0 %" in page
    assert s["identifiability"]["removed"] == ["j6.ex.cos1"]
    assert "histograms" not in s["figures"] and "joint1" in s["figures"]
    assert "No measurements were given" in page


def test_bare_model_is_judged_on_the_data(campaign: Campaign, tmp_path: Path) -> None:
    inp = ReportInput(models={"auto": campaign.fits["constant"].calibrated},
                      validation=campaign.val, workspace_samples=0)
    _, j = write_report(inp, tmp_path / "r.html")
    s = json.loads(j.read_text())
    assert s["selected_model"] == "auto"
    assert s["accuracy"]["auto"]["validation"]["n"] == len(campaign.val)
    assert s["judged_on"] == "validation"


def test_refuses_objects_that_are_no_fit_result(campaign: Campaign, tmp_path: Path) -> None:
    @dataclass
    class LooksLikeAFit:
        calibrated: CalibratedModel

    fake = LooksLikeAFit(campaign.fits["constant"].calibrated)
    inp = ReportInput(models={"auto": fake},  # type: ignore[dict-item]
                      validation=campaign.val, workspace_samples=0)
    with pytest.raises(ConfigError, match="'auto': a LooksLikeAFit is not a FitResult"):
        write_report(inp, tmp_path / "r.html")
    assert not (tmp_path / "r.html").exists()


def test_entries_take_the_name_they_are_given(campaign: Campaign) -> None:
    entry = campaign.fits["high-order"]
    got = ReportInput(models={"auto": entry}).entries()["auto"]
    assert got.name == "auto" and got.label == "Auto-selected model"
    assert got.calibrated is entry.calibrated and got.removed == entry.removed


def test_validation_glitch_is_flagged_not_hidden(campaign: Campaign, tmp_path: Path) -> None:
    from robocal._core.measurements import MeasurementSet

    val = campaign.val
    p = val.p.copy()
    p[7] += np.array([2e-3, -1e-3, 1e-3])           # a 2.4 mm beam-break reading
    glitchy = MeasurementSet(val.q, p, val.sigma, val.pose_id)
    fits = campaign.fits
    # the constant model keeps this test quick (no joint-dependent plots)
    inp = ReportInput(models={"nominal": fits["nominal"].calibrated, "auto": fits["constant"]},
                      calibration=campaign.cal, validation=glitchy, workspace_samples=0)
    h, j = write_report(inp, tmp_path / "r.html")
    s = json.loads(j.read_text())
    assert s["validation_glitches"] == [val.pose_id[7]]
    assert val.pose_id[7] in s["outliers"]
    got = s["accuracy"]["auto"]["validation"]
    assert got["n"] == len(val) - 1
    assert s["verdict"]["outcome"] == "succeeded"
    page = h.read_text(encoding="utf-8")
    assert "validation glitches" in page and val.pose_id[7] in page
    # switched off, the glitch stays in and the held-out RMS shows it
    inp.acceptance = Acceptance(validation_outlier_factor=0)
    _, j2 = write_report(inp, tmp_path / "r2.html")
    s2 = json.loads(j2.read_text())
    assert s2["validation_glitches"] == []
    assert s2["accuracy"]["auto"]["validation"]["rms_mm"] > 1.5 * got["rms_mm"]


def test_nothing_to_judge_still_renders(tmp_path: Path) -> None:
    for models in ({}, {"auto": None}):  # None: a fit that produced no model
        h, j = write_report(ReportInput(models=models), tmp_path / "r.html")
        s = json.loads(j.read_text())
        assert s["verdict"]["outcome"] == "failed" and s["figures"] == []
        assert "no calibrated model" in h.read_text(encoding="utf-8")
