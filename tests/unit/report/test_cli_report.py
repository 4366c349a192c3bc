"""``robocal report``: from a MODEL.json alone, with measurement files, and from a campaign in
the daemon's store."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from robocal.cli.main import main
from tests.unit.report.conftest import Campaign


def _save(campaign: Campaign, tmp: Path) -> dict[str, Path]:
    paths = {}
    for name in ("nominal", "constant", "high-order"):
        f = campaign.fits[name]
        cm = dataclasses.replace(f.calibrated, fit={"outliers": list(f.outliers),
                                                    "removed": list(f.removed)})
        paths[name] = tmp / f"MODEL-{name}.json"
        cm.save(paths[name])
    campaign.cal.write_csv(tmp / "cal.csv")
    campaign.val.write_csv(tmp / "val.csv")
    return paths


def test_model_file_with_data(campaign: Campaign, tmp_path: Path,
                              capsys: pytest.CaptureFixture[str]) -> None:
    m = _save(campaign, tmp_path)
    out = tmp_path / "out" / "report.html"
    rc = main(["report", str(m["high-order"]), "--out", str(out), "--data",
               str(tmp_path / "cal.csv"), "--validate", str(tmp_path / "val.csv"),
               "--compare", f"nominal={m['nominal']}", "--compare",
               f"constant={m['constant']}", "--max-rms-mm", "0.5"])
    assert rc == 0
    text = capsys.readouterr().out
    assert text.startswith("Calibration succeeded") and "report.json" in text
    s = json.loads((tmp_path / "out" / "report.json").read_text())
    assert s["selected_model"] == "high-order"
    assert set(s["accuracy"]) == {"nominal", "constant", "high-order"}
    assert s["acceptance"]["max_rms_mm"] == 0.5
    assert sorted(s["outliers"]) == sorted(campaign.outliers)   # from the model file
    r = np.linalg.norm(campaign.val.p - campaign.fits["high-order"].calibrated.predict(
        campaign.val.q), axis=1)
    assert s["accuracy"]["high-order"]["validation"]["rms_mm"] == pytest.approx(
        np.sqrt(np.mean(r**2)) * 1e3, rel=1e-6)   # CSV round trip: µm-level digits


def test_model_file_alone(campaign: Campaign, tmp_path: Path,
                          capsys: pytest.CaptureFixture[str]) -> None:
    m = _save(campaign, tmp_path)
    rc = main(["report", str(m["constant"]), "--out", str(tmp_path / "r.html"), "--json"])
    assert rc == 1  # the page is written, and a failed verdict fails the command
    got = json.loads(capsys.readouterr().out)
    assert got["html"].endswith("r.html") and got["json"].endswith("r.json")
    # no stored metrics and no data: nothing to judge, and the page says so
    assert got["verdict"]["outcome"] == "failed"
    page = (tmp_path / "r.html").read_text(encoding="utf-8")
    assert "No measurements were given" in page


def test_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(tmp_path / "missing.json"), "--out",
                 str(tmp_path / "r.html")]) == 2
    assert "file not found" in capsys.readouterr().err
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'data_dir = "{tmp_path}"\nrobot_description = "fanuc_lrmate200i"\n'
                   '[robot]\nkind = "mock"\n[tracker]\nkind = "mock"\n')
    assert main(["report", "abc123", "--config", str(cfg), "--out",
                 str(tmp_path / "r.html")]) == 2
    assert "store does not exist" in capsys.readouterr().err


def test_campaign_from_the_store(campaign: Campaign, tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    from robocal.daemon.schemas import Measurement
    from robocal.daemon.store import PoseRow, Store

    cfg = tmp_path / "c.toml"
    prog = tmp_path / "JOINTS.csv"
    prog.write_text("q1,q2,q3,q4,q5,q6\n0,10,0,0,30,45\n5,20,-10,0,-30,90\n")
    cfg.write_text(f'data_dir = "{tmp_path}"\nrobot_description = "fanuc_lrmate200i"\n'
                   '[robot]\nkind = "mock"\n[tracker]\nkind = "mock"\n'
                   f'[compensation]\ntargets_file = "{prog}"\n')
    store = Store(tmp_path / "robocal.sqlite3").open()
    rows: list[tuple[str, np.ndarray, np.ndarray]] = []
    # a slice of the campaign keeps the per-measurement fsyncs of the store cheap
    cal, val = campaign.cal.subset(np.arange(70)), campaign.val.subset(np.arange(20))
    for purpose, data in (("calibration", cal), ("validation", val)):
        rows += [(purpose, data.q[i], data.p[i]) for i in range(len(data))]
    iso = campaign.iso[0]
    q_iso = np.zeros(6)
    rows += [("iso-P1", q_iso, iso.attained[k]) for k in range(len(iso.attained))]
    poses = [PoseRow(i, pur, tuple(np.degrees(q))) for i, (pur, q, _) in enumerate(rows)]
    rec = store.create_campaign(name="test", robot="fanuc_lrmate200i", poses=poses,
                                plan_json="{}", plan_digest="p" * 16, config_digest="c" * 16,
                                actor="test")
    for i, (pur, q, p) in enumerate(rows):
        qd = tuple(float(v) for v in np.degrees(q))
        store.add_measurement(rec.id, Measurement(
            pose_idx=i, purpose=pur, q_cmd_deg=qd, q_act_deg=qd,
            p_mm=tuple(float(v) for v in p * 1e3), sigma_mm=None, rms_mm=0.001, samples=5,
            attempts=2 if i == 3 else 1, distance_mm=None,
            weather={"temperature_c": 20.0 + 0.01 * i}, measured_at="2026-01-01T00:00:00"))
    # the daemon names poses P<index in the plan>
    out_ids = [f"P{i:04d}" for i in range(len(cal)) if cal.pose_id[i] in set(campaign.outliers)]
    fits = {}
    for name in ("nominal", "constant", "high-order"):
        summ = {"model": name, "outliers": out_ids, "status": "converged"}
        f = campaign.fits[name]
        fits[name] = (summ, json.dumps(f.calibrated.to_dict()))
    store.save_fits(rec.id, fits)
    store.set_selected_model(rec.id, "high-order")
    store.close()
    out = tmp_path / "campaign.html"
    rc = main(["report", rec.id, "--config", str(cfg), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    s = json.loads(out.with_suffix(".json").read_text())
    assert s["campaign_id"] == rec.id and s["selected_model"] == "high-order"
    assert s["verdict"]["outcome"] == "succeeded"
    assert s["accuracy"]["high-order"]["validation"]["n"] == len(val)
    assert s["accuracy"]["high-order"]["calibration"]["n"] == len(cal) - len(out_ids)
    assert sorted(s["outliers"]) == out_ids
    assert s["measurement_log"]["retries"] == 1
    assert [r["pose"] for r in s["iso9283"]] == ["P1"] and s["iso9283"][0]["n"] == 10
    # the program the daemon pushes is overlaid on the coverage (ADR 0026)
    assert s["coverage"]["targets"] == 2
    assert s["coverage"]["joints"][5]["targets_deg"] == [45.0, 90.0]
    page = out.read_text(encoding="utf-8")
    assert rec.id in page and "20.0–" in page
