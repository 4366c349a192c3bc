"""MODEL.json round trip, coverage fallback and prediction uncertainty."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel
from robocal.simulation import VirtualCell


def test_round_trip_and_fallback(tmp_path: Path, rng: np.random.Generator) -> None:
    cell = VirtualCell.create("ur10", "fine-map", seed=3)
    const = KinematicModel(cell.robot, ErrorModelSpec.constant(6), cell.truth_model.T_ref)
    fb = CalibratedModel(const, cell.truth_model.transfer(cell.truth_params, const))
    cover = np.tile([[-1.0, 1.0]], (6, 1))
    cm = CalibratedModel(cell.truth_model, cell.truth_params,
                         covariance=np.eye(cell.truth_model.size) * 1e-12,
                         coverage=cover, fallback=fb, kind="auto")
    cm.save(tmp_path / "m.json")
    back = CalibratedModel.load(tmp_path / "m.json")
    assert back.model_id == cm.model_id and back.kind == "auto"
    q_in = rng.uniform(-0.9, 0.9, (5, 6))
    q_out = q_in.copy()
    q_out[:, 0] = 2.0
    np.testing.assert_allclose(back.predict(q_in), cell.reflector_position(q_in), atol=1e-12)
    # outside the covered range the low-order fallback predicts, not the map
    np.testing.assert_allclose(back.predict(q_out), fb.predict(q_out), atol=1e-12)
    assert not np.allclose(back.predict(q_out), cell.reflector_position(q_out), atol=1e-6)
    s = back.prediction_sigma(q_in)
    assert s.shape == (5, 3) and np.all(s > 0)


def test_bad_model_files(tmp_path: Path, rng: np.random.Generator) -> None:
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=1)
    cm = CalibratedModel(cell.truth_model, cell.truth_params)
    cm.save(tmp_path / "m.json")
    d = json.loads((tmp_path / "m.json").read_text())
    d["parameters"] = d["parameters"][:-1]
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(ConfigError, match="parameter missing"):
        CalibratedModel.load(tmp_path / "bad.json")
    (tmp_path / "bad2.json").write_text("{")
    with pytest.raises(ConfigError, match="not valid JSON"):
        CalibratedModel.load(tmp_path / "bad2.json")
    d = json.loads((tmp_path / "m.json").read_text())
    d["format"] = "other/9"
    (tmp_path / "bad3.json").write_text(json.dumps(d))
    with pytest.raises(ConfigError, match="format"):
        CalibratedModel.load(tmp_path / "bad3.json")
