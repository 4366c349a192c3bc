"""The report's per-joint coverage with the program targets overlaid (ADR 0026)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from robocal.cli.main import main
from tests.unit.report.conftest import Campaign
from tests.unit.report.svgdoc import figures, texts, title


def test_report_shows_coverage_and_counts_targets_outside(
        campaign: Campaign, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = campaign.fits["high-order"]
    lim = campaign.cell.robot.joint_limits
    cover = lim.copy()
    cover[5] = np.radians([-90.0, 90.0])
    # another coverage is another model: model_id="" makes it hash its own content
    cm = dataclasses.replace(f.calibrated, coverage=cover, model_id="",
                             fit={"outliers": list(f.outliers), "removed": list(f.removed)})
    cm.save(tmp_path / "MODEL.json")
    campaign.cal.write_csv(tmp_path / "cal.csv")
    prog = tmp_path / "JOINTS.csv"
    prog.write_text("q1,q2,q3,q4,q5,q6\n0,10,0,0,30,250\n5,20,-10,0,-30,45\n"
                    "10,30,0,20,40,-120\n")
    out = tmp_path / "report.html"
    rc = main(["report", str(tmp_path / "MODEL.json"), "--data", str(tmp_path / "cal.csv"),
               "--targets", str(prog), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc in (0, 1), err
    summary = json.loads((tmp_path / "report.json").read_text())
    cov = summary["coverage"]
    assert cov["targets"] == 3 and cov["targets_outside"] == 2
    j6 = cov["joints"][5]
    assert j6["calibrated_deg"] == [-90.0, 90.0] and j6["targets_deg"] == [-120.0, 250.0]
    assert j6["targets_outside"] == 2 and cov["joints"][0]["targets_outside"] == 0
    q = np.degrees(campaign.cal.q[:, 5])
    assert j6["measured_deg"] == pytest.approx([q.min(), q.max()], abs=1e-3)
    assert cov["outside_names"][0].startswith("target 0: J6 250.0 deg outside")
    html = out.read_text()
    assert '<section id="coverage">' in html and 'href="#coverage"' in html
    assert "2 of 3 program targets lie outside" in html
    (plot,) = [s for s in figures(html) if title(s) == "Per-joint coverage with the program "
                                                         "targets"]
    assert ("grey: limits, blue: calibrated range, black: measured, ticks: 3 program targets "
            "(2 outside, red)") in texts(plot)
    assert {"J1", "J6", "joint value (deg)"} <= set(texts(plot))


def test_report_without_targets_still_shows_the_ranges(
        campaign: Campaign, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = campaign.fits["constant"]
    f.calibrated.save(tmp_path / "MODEL.json")
    main(["report", str(tmp_path / "MODEL.json"), "--out", str(tmp_path / "r.html")])
    capsys.readouterr()
    cov = json.loads((tmp_path / "r.json").read_text())["coverage"]
    assert cov["targets"] == 0 and len(cov["joints"]) == 6
    assert cov["joints"][0]["targets_deg"] is None
