"""The report's thermal state (ADR 0042): joint temperature against time, the error against
temperature and the fitted thermal term, shown only when the data has temperatures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.identification import FitOptions, fit
from robocal.report import MeasurementLog, ReportInput, write_report
from robocal.simulation import VirtualCell, WarmUpDrift
from tests.unit.report.svgdoc import figures, texts, title

pytestmark = pytest.mark.timeout(120)

FAST = FitOptions(auto_maps=False, auto_max_order=1, auto_ripple_orders=(),
                  auto_strain_wave=False, auto_gravity=False)


def _campaign(n: int = 160) -> tuple[MeasurementSet, np.ndarray]:
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=1)
    drift = WarmUpDrift.planted(cell.robot, drift_m=1e-4)
    rng = np.random.default_rng(4)
    q = cell.random_joints(n, rng, margin_rad=0.3)
    temps = rng.uniform(20.0, 30.0, (n, cell.robot.dof))
    p = drift.positions(cell, q, temps)
    return MeasurementSet(q, p + cell.noise.sample(p, rng), temps=temps), temps


def test_report_shows_temperatures_and_the_thermal_term(tmp_path: Path):
    data, temps = _campaign()
    res = fit("fanuc_lrmate200i", data, "auto", options=FAST)
    assert res.calibrated.fit["thermal"]["selected"]
    log = MeasurementLog(measured=len(data), joint_temps=temps.tolist(),
                         joint_temps_t_s=(np.arange(len(data)) * 7.0).tolist())
    html, _ = write_report(ReportInput(models={"auto": res}, calibration=data, log=log),
                           tmp_path / "r.html")
    page = Path(html).read_text()
    assert "<h3>Thermal state</h3>" in page
    plots = {title(svg): texts(svg) for svg in figures(page)}
    assert {"J1", "J6", "joint temperature (°C)"} <= set(plots["Joint temperatures against time"])
    assert "auto error (mm)" in plots["Position error of the selected model against temperature"]
    assert "µm/°C" in page and "linear thermal term" in page


def test_report_without_temperatures_has_no_thermal_state(tmp_path: Path):
    data, _ = _campaign(80)
    plain = MeasurementSet(data.q, data.p)
    res = fit("fanuc_lrmate200i", plain, "constant", options=FAST)
    html, _ = write_report(ReportInput(models={"constant": res}, calibration=plain),
                           tmp_path / "r.html")
    assert "Thermal state" not in Path(html).read_text()
