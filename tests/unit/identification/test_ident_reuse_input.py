"""A reused MODEL.json's map support and map priors are checked before any fit (hand edits)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal._core.measurements import MeasurementSet
from robocal.cli.main import main
from robocal.errors import ConfigError
from robocal.identification._fit import _earlier_map_settings, _earlier_support
from robocal.identification._models import constant_spec
from robocal.kinematics import CalibratedModel, KinematicModel, load_robot
from robocal.kinematics._spec import Term
from robocal.simulation import VirtualCell

N_KNOTS = 48


def _model() -> CalibratedModel:
    rob = load_robot("fanuc_lrmate200i")
    spec = constant_spec(rob).with_terms([Term(1, "ez", "map", k) for k in range(N_KNOTS)],
                                         map_knots={1: N_KNOTS})
    m = KinematicModel(rob, spec)
    cm = CalibratedModel(model=m, params=m.nominal_params(), kind="auto")
    cm.data = {"map_support": {"j2": [10] * N_KNOTS}}
    cm.fit = {"map_priors": [{"joint": 2, "lambda_per_rad2": 1e3, "ridge_sigma_deg": 0.1}]}
    cm.model_id = cm.compute_id()
    return cm


def test_a_well_formed_file_parses():
    cm = _model()
    assert list(_earlier_support(cm)) == [1]
    assert _earlier_map_settings(cm) == {1: (1e3, pytest.approx(np.radians(0.1)))}
    cm.data = {}
    assert _earlier_support(cm) == {}            # files from before the counts: no gap filling


junk = st.recursive(st.none() | st.booleans() | st.integers(-5, 10**6) | st.floats()
                    | st.text(max_size=4),
                    lambda c: st.lists(c, max_size=60) | st.dictionaries(st.text(max_size=3), c,
                                                                          max_size=3),
                    max_leaves=80)


@settings(max_examples=150, deadline=None)
@given(support=junk, priors=junk)
def test_any_content_parses_or_raises_one_config_error(support, priors):
    cm = _model()
    cm.data = {"map_support": {"j2": support} if not isinstance(support, dict) else support}
    cm.fit = {"map_priors": priors}
    for parse in (_earlier_support, _earlier_map_settings):
        try:
            parse(cm)
        except ConfigError as err:
            assert "map_" in str(err)


def test_reuse_of_a_hand_edited_file_is_one_line_error(tmp_path, capsys):
    cm = _model()
    cm.data["map_support"]["j2"] = [10] * (N_KNOTS - 1) + ["x"]
    path = tmp_path / "edited.json"
    cm.save(path)
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=1)
    rng = np.random.default_rng(1)
    q, p, _, _ = cell.simulate(cell.random_joints(30, rng), rng)
    MeasurementSet(q, p).write_csv(tmp_path / "new.csv")
    out = tmp_path / "out.json"
    code = main(["fit", "--reuse", str(path), "--data", str(tmp_path / "new.csv"), "--out",
                 str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "data.map_support.j2" in err[0]
    assert not out.exists()
    json.loads(path.read_text())                 # the input is left as it was
