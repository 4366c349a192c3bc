"""``robocal demo`` end to end, as a user runs it.

80 calibration poses keep it fast (the high-order model needs at least 64).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "robocal.cli.main", "demo", "--poses", "80", "--out", str(out),
         "--seed", "2"],
        capture_output=True, text=True, timeout=240, cwd=tmp_path)
    wall = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    text = proc.stdout
    for label in ("nominal", "constant", "high-order", "auto", "nominal (before)",
                  "auto compensated", "Report:"):
        assert label in text, text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["state"] == "pushed"
    assert summary["poses_measured"] == summary["poses_total"]
    fits = summary["fits"]
    val = {k: fits[k]["validation"]["rms_mm"] for k in ("nominal", "constant", "high-order")}
    assert val["high-order"] < val["constant"] < val["nominal"]
    comp = summary["compensation"]
    assert comp["auto"]["rms_mm"] < 0.25 * comp["before"]["rms_mm"]
    # what was pushed (the validation targets, compensated with the approved model) was
    # measured again by the daemon on the simulated robot after the push
    push = summary["push"]
    assert push["kind"] == "targets" and push["verification"] == "done"
    assert push["measured_n"] == comp["targets"]
    # as accurate as the approved model's held-out accuracy says (with 80 poses that is a
    # few hundredths of a mm; the default 250-pose demo measures about 0.011 mm, ADR 0013)
    held_out = fits["auto"]["validation"]["rms_mm"]
    assert push["model_accuracy_mm"] == pytest.approx(held_out, abs=1e-6)
    assert push["measured_after_rms_mm"] <= 1.5 * held_out + 0.005
    assert push["measured_before_rms_mm"] > 20 * push["measured_after_rms_mm"]
    assert push["predicted_rms_mm"] < 0.5 * push["nominal_rms_mm"]
    assert f"-> {push['measured_after_rms_mm']:.4f} mm RMS after" in text
    files = summary["files"]
    for key in ("report_html", "report_json"):
        assert key in files and (tmp_path / files[key]).exists()
    assert (out / "PLAN.json").exists() and (out / "state" / "robocal.sqlite3").exists()
    # ISO 9283: the plan cycles P1..P5 30 times, so the report states AP and RP per pose
    report = json.loads((tmp_path / files["report_json"]).read_text())
    rows = report["iso9283"]
    assert [r["pose"] for r in rows] == [f"P{k}" for k in range(1, 6)], rows
    for row in rows:
        assert row["n"] == 30 and row["RP_mm"] is not None and row["RP_mm"] > 0, row
    assert wall < 120
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
