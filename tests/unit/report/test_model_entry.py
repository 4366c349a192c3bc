"""The report reads identification's own results by their types: FitResult and CPAResult."""

from __future__ import annotations

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.identification import CPAResult, FitResult, cpa_fit, fit
from robocal.identification._cpa import cpa_sweeps
from robocal.report import ReportInput, analyse, model_entry
from robocal.simulation import VirtualCell
from tests._designs import thin_j6_design


@pytest.fixture(scope="module")
def cell() -> VirtualCell:
    return VirtualCell.create("fanuc_lrmate200i", "constant", seed=5)


@pytest.fixture(scope="module")
def data(cell: VirtualCell) -> tuple[MeasurementSet, MeasurementSet]:
    rng = np.random.default_rng(5)
    q, p, _, _ = cell.simulate(cell.random_joints(80, rng), rng)
    qv, pv, _, _ = cell.simulate(cell.random_joints(30, rng), rng)
    return MeasurementSet(q, p), MeasurementSet(qv, pv)


@pytest.fixture(scope="module")
def constant(cell: VirtualCell, data: tuple[MeasurementSet, MeasurementSet]) -> FitResult:
    train, val = data
    return fit(cell.robot, train, "constant", validation=val)


def test_fit_result_entry(constant: FitResult) -> None:
    e = model_entry("constant", constant)
    assert e.name == "constant" and e.calibrated is constant.calibrated
    assert e.stored["train"] == constant.train.to_dict()
    assert constant.validation is not None
    assert e.stored["validation"] == constant.validation.to_dict()
    assert e.status == constant.status and e.outliers == tuple(constant.outliers)
    assert e.summary == constant.summary()
    assert e.fit_info["converged"] is constant.converged
    assert e.fit_info["rank"] == constant.identifiability.rank
    assert e.fit_info["n_free"] == constant.n_free
    assert len(e.fit_info["singular_values"]) == len(constant.identifiability.singular_values)


def test_fit_result_carries_the_baseline(constant: FitResult,
                                         data: tuple[MeasurementSet, MeasurementSet]) -> None:
    train, val = data
    an = analyse(ReportInput(models={"constant": constant}, calibration=train, validation=val,
                             workspace_samples=0))
    assert "nominal" in an.models and "fitted by the report" not in an.baseline_note
    assert an.models["nominal"].entry.calibrated is constant.baseline


def test_cpa_result_entry(cell: VirtualCell, constant: FitResult,
                          data: tuple[MeasurementSet, MeasurementSet]) -> None:
    rng = np.random.default_rng(6)
    sweeps = []
    for j, q in cpa_sweeps(cell.robot, n_points=12):
        qs, ps, _, _ = cell.simulate(q, rng)
        sweeps.append((j, MeasurementSet(qs, ps)))
    res = cpa_fit(cell.robot, sweeps, validation=data[1], baseline=constant.baseline)
    assert isinstance(res, CPAResult) and res.validation is not None
    e = model_entry("cpa", res)
    assert e.calibrated is res.calibrated and e.label == "Circle Point Analysis"
    assert e.stored == {"validation": res.validation.to_dict()}
    assert e.summary == res.summary() and e.outliers == ()


def test_verdict_warns_about_extrapolated_validation_poses() -> None:
    """Calibration poses with J6 at 0 and 2 deg only: the report names the poses it guesses."""
    cell, rng, train = thin_j6_design()
    qv, pv, _, _ = cell.simulate(cell.random_joints(40, rng), rng)
    val = MeasurementSet(qv, pv)
    res = fit(cell.robot, train, "constant", validation=val)
    an = analyse(ReportInput(models={"constant": res}, calibration=train, validation=val,
                             workspace_samples=0))
    checks = {c.name: c for c in an.verdict.checks}
    assert checks["extrapolation"].status == "warn"
    assert "with J6 angles the training poses lack" in checks["extrapolation"].message
    assert an.verdict.outcome != "succeeded"
    # a random design of the same size: no such check
    q2, p2, _, _ = cell.simulate(cell.random_joints(60, rng), rng)
    train2 = MeasurementSet(q2, p2)
    ok = analyse(ReportInput(models={"constant": fit(cell.robot, train2, "constant",
                                                     validation=val)},
                             calibration=train2, validation=val, workspace_samples=0))
    assert "extrapolation" not in {c.name for c in ok.verdict.checks}
