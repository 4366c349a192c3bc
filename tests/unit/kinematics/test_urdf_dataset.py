"""A UR10 URDF from ur_description imports and fits the IPA UR10 data as the built-in does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robocal.identification import fit, load_ipa_series
from robocal.identification.datasets import ipa_series_path
from robocal.kinematics import load_robot

pytestmark = pytest.mark.dataset
FIXTURE = Path(__file__).parent / "fixtures" / "ur10_ur_description.urdf"


def test_ur_description_urdf_fits_series_c_like_the_builtin(dataset_dir: Path) -> None:
    data = load_ipa_series(ipa_series_path(dataset_dir, "C"), max_poses=800, seed=1)
    train, val = data.split(0.5, seed=0)
    builtin = fit("ur10", train, "constant", validation=val)
    imported = fit(load_robot(FIXTURE), train, "constant", validation=val)
    b, i = builtin.validation, imported.validation
    # same chain up to the base frame (absorbed by the fitted tracker <- base transform):
    # nominal and calibrated held-out accuracy agree
    assert abs(i.baseline_rms_m - b.baseline_rms_m) < 0.01e-3
    assert abs(i.rms_m - b.rms_m) < 0.01e-3
    assert 0.4e-3 < i.rms_m < 0.6e-3 < i.baseline_rms_m
    # and the fitted reflector point in the flange frame: 93 mm along the flange axis
    z = imported.calibrated.params[8]
    assert np.isclose(abs(z), 0.093, atol=0.003)
