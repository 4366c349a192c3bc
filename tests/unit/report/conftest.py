"""A simulated 250-pose campaign with fitted models, shared by the report tests."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.kinematics import ErrorModelSpec
from robocal.report import IsoPoseSeries, ModelEntry
from robocal.simulation import VirtualCell
from tests.unit.report._fitting import gn_fit


@dataclass
class Campaign:
    cell: VirtualCell
    cal: MeasurementSet
    val: MeasurementSet
    outliers: tuple[str, ...]
    fits: dict[str, ModelEntry]
    iso: list[IsoPoseSeries]


def make_campaign(n: int = 250, seed: int = 7) -> Campaign:
    rng = np.random.default_rng(seed)
    cell = VirtualCell.create("fanuc_lrmate200i", "paper", seed=seed)
    q = cell.random_joints(n, rng)
    qc, p, s, _ = cell.simulate(q, rng)
    ms = MeasurementSet(qc, p, s)
    cal, val = ms.split(0.8, seed=seed)
    # three beam-break glitches in the calibration poses
    bad = np.array([5, 60, 120]) * len(cal) // 200
    pc = cal.p.copy()
    pc[bad] = cell.outlier(pc[bad], rng)
    cal = MeasurementSet(cal.q, pc, cal.sigma, cal.pose_id)
    out = tuple(cal.pose_id[i] for i in bad)
    T = cell.truth_model.T_ref
    nom = gn_fit(cell.robot, ErrorModelSpec(6, (), label="nominal"), T, cal, kind="nominal",
                 exclude=out)
    con = gn_fit(cell.robot, ErrorModelSpec.constant(6), T, cal, x0=nom.calibrated,
                 kind="constant", exclude=out)
    spec = ErrorModelSpec.build(6, fourier=2, fourier_components=("dx", "dy", "dz", "ex", "ey",
                                                                  "ez"), label="high-order")
    ho = gn_fit(cell.robot, spec, T, cal, x0=con.calibrated, kind="high-order", exclude=out)
    iso = []
    for k in range(5):
        qi = cell.random_joints(1, rng)
        _, pi, _, _ = cell.simulate(np.repeat(qi, 10, axis=0), rng)
        iso.append(IsoPoseSeries(f"P{k + 1}", nom.calibrated.predict(qi)[0], pi,
                                 predicted=ho.calibrated.predict(qi)[0]))
    return Campaign(cell, cal, val, out, {"nominal": nom, "constant": con, "high-order": ho},
                    iso)


@pytest.fixture(scope="session")
def campaign() -> Campaign:
    """The shared simulated campaign (fits done once per session)."""
    return make_campaign()
