"""Accuracy metrics and the "% of measured error described" definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.identification import BASELINE_DESCRIPTION, accuracy


def _set(errors: np.ndarray) -> tuple[MeasurementSet, np.ndarray]:
    """Poses whose 'measurement' sits at a known offset from a reference predictor."""
    n = len(errors)
    q = np.zeros((n, 6))
    q[:, 0] = np.arange(n)
    ref = np.column_stack([np.arange(n), np.zeros(n), np.ones(n)])
    return MeasurementSet(q, ref + errors), ref


def test_rms_mean_max_and_percent_described():
    rng = np.random.default_rng(0)
    base_err = rng.normal(0, 1e-3, (50, 3))
    res_err = 0.2 * base_err + rng.normal(0, 1e-5, (50, 3))
    data, ref = _set(base_err)

    def baseline(q):
        return ref[q[:, 0].astype(int)]

    def model(q):
        i = q[:, 0].astype(int)
        return ref[i] + (base_err - res_err)[i]

    acc = accuracy(model, data, baseline=baseline)
    r = np.linalg.norm(res_err, axis=1)
    e = np.linalg.norm(base_err, axis=1)
    assert acc.n == 50
    assert acc.rms_m == pytest.approx(math.sqrt(np.mean(r**2)))
    assert acc.mean_m == pytest.approx(np.mean(r))
    assert acc.max_m == pytest.approx(np.max(r))
    assert acc.percent_described_rms == pytest.approx(
        100 * (1 - math.sqrt(np.mean(r**2)) / math.sqrt(np.mean(e**2))))
    assert acc.percent_described_mean == pytest.approx(100 * (1 - np.mean(r) / np.mean(e)))
    assert acc.percent_described_r2 == pytest.approx(100 * (1 - np.sum(r**2) / np.sum(e**2)))
    d = acc.to_dict()
    assert d["rms_mm"] == pytest.approx(acc.rms_m * 1e3)
    assert d["baseline"] == BASELINE_DESCRIPTION


def test_without_baseline_no_percentages_and_exclusion():
    data, ref = _set(np.tile([[1e-3, 0, 0]], (10, 1)) * np.arange(1, 11)[:, None])

    def model(q):
        return ref[q[:, 0].astype(int)]

    acc = accuracy(model, data)
    assert acc.percent_described_rms is None and acc.max_m == pytest.approx(10e-3)
    acc2 = accuracy(model, data, exclude=[data.pose_id[9]])
    assert acc2.n == 9 and acc2.max_m == pytest.approx(9e-3)
    assert acc2.excluded == (data.pose_id[9],)
