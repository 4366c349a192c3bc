"""One reader of campaign data by purpose, for the daemon's fits and the CLI's reports.

A plan with no ``calibration`` marks calibrates on its unmarked rows only: validation, ISO
9283 and CPA rows are held out by both the fit job and ``robocal report --campaign``.
"""

from __future__ import annotations

import math

import numpy as np

from robocal.daemon.fitting import build_fit_job, rows_by_purpose, run_fit_job
from robocal.daemon.schemas import Measurement
from robocal.simulation import VirtualCell


def _rows(purposes: list[str], *, seed: int = 5,
          offset_mm: dict[str, float]) -> list[Measurement]:
    rng = np.random.default_rng(seed)
    cell = VirtualCell.create("fanuc_lrmate200i", "paper", seed=seed)
    q = cell.random_joints(len(purposes), rng)
    qc, p, _, _ = cell.simulate(q, rng)
    rows = []
    for i, purpose in enumerate(purposes):
        p_mm = p[i] * 1e3 + offset_mm.get(purpose, 0.0)
        q_deg = tuple(float(v) for v in np.degrees(qc[i]))
        rows.append(Measurement(
            pose_idx=i, purpose=purpose, q_cmd_deg=q_deg, q_act_deg=q_deg,
            p_mm=(float(p_mm[0]), float(p_mm[1]), float(p_mm[2])), sigma_mm=None, rms_mm=None,
            samples=1, attempts=1, distance_mm=None, weather={}, measured_at="2026-01-01"))
    return rows


def test_rows_by_purpose_holds_out_validation_iso_and_cpa_when_nothing_is_marked():
    purposes = ["", "via", "validation", "ISO-P1", "iso-P2", "cpa-j1", "cpa-j3", ""]
    split = rows_by_purpose(_rows(purposes, offset_mm={}))
    assert [r.purpose for r in split.calibration] == ["", "via", ""]
    assert [r.purpose for r in split.validation] == ["validation"]
    assert [r.purpose for r in split.iso] == ["ISO-P1", "iso-P2"]
    assert {j: [r.purpose for r in rs] for j, rs in split.cpa.items()} == {
        1: ["cpa-j1"], 3: ["cpa-j3"]}
    marked = rows_by_purpose(_rows(["calibration", "", "validation"], offset_mm={}))
    assert [r.purpose for r in marked.calibration] == ["calibration"]


def test_the_fit_job_does_not_train_on_validation_or_iso_rows():
    """Validation and ISO rows 40 mm off (a different frame, say) never reach the training
    set: the constant model fits the 40 unmarked poses to the noise level."""
    purposes = [""] * 40 + ["validation"] * 6 + ["iso-P1"] * 6
    rows = _rows(purposes, offset_mm={"validation": 40.0, "iso-P1": 40.0})
    from robocal.kinematics import load_robot

    job = build_fit_job(campaign="c1", robot=load_robot("fanuc_lrmate200i"), rows=rows,
                        models=["constant"], cpa=False, out_dir=None, report=False)
    out = run_fit_job(job)
    assert not out["errors"], out["errors"]
    train = out["fits"]["constant"][0]["train"]
    assert train["n"] == 40
    assert math.isfinite(train["rms_mm"]) and train["rms_mm"] < 1.0
