"""MODEL.json is verified on load: its content must hash to its ``model_id``, every number
must be finite and plausible, every section well formed; the commands that read a model
(predict, compensate, table, report) answer a bad one with one line and exit 2."""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from robocal._core.measurements import write_joints_csv
from robocal.cli.main import main
from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel
from robocal.simulation import VirtualCell

Doc = dict[str, Any]


@pytest.fixture(scope="module")
def good() -> Doc:
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=1)
    const = KinematicModel(cell.robot, ErrorModelSpec.constant(cell.robot.dof),
                           cell.truth_model.T_ref)
    fb = CalibratedModel(const, cell.truth_model.transfer(cell.truth_params, const))
    cm = CalibratedModel(cell.truth_model, cell.truth_params, coverage=np.tile(
        [[-1.5, 1.5]], (cell.robot.dof, 1)), fallback=fb,
        covariance=np.eye(cell.truth_model.size) * 1e-12)
    return cm.to_dict()


def _param(d: Doc, unit: str) -> Doc:
    return next(p for p in d["parameters"] if p["unit"] == unit)


def _nudge_half_mm(d: Doc) -> None:
    _param(d, "mm")["value"] += 0.5


def _huge(d: Doc) -> None:
    _param(d, "mm")["value"] = 1e308


CORRUPTIONS: dict[str, tuple[Callable[[Doc], None], str]] = {
    "parameter +0.5 mm": (_nudge_half_mm, "model_id"),
    "parameter 1e308": (_huge, "plausible"),
    "parameter NaN": (lambda d: _param(d, "deg").__setitem__("value", math.nan), "finite"),
    "coverage a string": (lambda d: d.__setitem__("coverage_deg", "[[-90, 90]]"),
                          "coverage_deg"),
    "coverage wrong shape": (lambda d: d.__setitem__("coverage_deg", [[-90, 90]]),
                             "coverage_deg"),
    "coverage reversed": (lambda d: d["coverage_deg"][0].reverse(), "coverage_deg"),
    "coverage of nulls": (lambda d: d.__setitem__("coverage_deg", [[None, None]] * 6),
                          "coverage_deg"),
    "terms not a list": (lambda d: d["error_model"].__setitem__("terms", 7), "error"),
    "terms of junk": (lambda d: d["error_model"].__setitem__("terms", [{"kind": 3}, "x"]),
                      "error"),
    "T not rigid": (lambda d: d["T_tracker_base_ref_mm"][0].__setitem__(0, 2.0),
                    "rigid"),
    "T far away": (lambda d: d["T_tracker_base_ref_mm"][0].__setitem__(3, 1e9), "80000"),
    "metrics a list": (lambda d: d.__setitem__("metrics", [1, 2]), "metrics"),
    "fallback edited": (lambda d: _nudge_half_mm(d["fallback"]), "model_id"),
    "parameters not a list": (lambda d: d.__setitem__("parameters", 5), "parameter"),
    "model_id missing": (lambda d: d.pop("model_id"), "model_id"),
}


def test_an_untouched_file_loads_with_its_id(good: Doc, tmp_path: Path) -> None:
    p = tmp_path / "MODEL.json"
    p.write_text(json.dumps(good))
    back = CalibratedModel.load(p)
    assert back.model_id == good["model_id"] == back.compute_id()
    assert back.fallback is not None and back.fallback.model_id == good["fallback"]["model_id"]
    # and a model saved again keeps verifying (the id is of the values as stored)
    back.save(tmp_path / "again.json")
    assert CalibratedModel.load(tmp_path / "again.json").model_id == back.model_id


@pytest.mark.parametrize("name", sorted(CORRUPTIONS))
def test_corrupted_model_is_one_config_error(good: Doc, tmp_path: Path, name: str) -> None:
    change, needle = CORRUPTIONS[name]
    d = copy.deepcopy(good)
    change(d)
    p = tmp_path / "MODEL.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ConfigError) as info:
        CalibratedModel.load(p)
    assert needle in str(info.value) and str(p) in str(info.value)


def test_an_edited_file_can_still_be_read_on_purpose(good: Doc, tmp_path: Path) -> None:
    d = copy.deepcopy(good)
    _nudge_half_mm(d)
    p = tmp_path / "MODEL.json"
    p.write_text(json.dumps(d))
    assert CalibratedModel.load(p, verify=False).model_id == good["model_id"]


@pytest.mark.parametrize("text", ["[" * 100_000 + "]" * 100_000,
                                  '{"format": ' + "9" * 5000 + "}"])
def test_pathological_json_is_one_config_error(tmp_path: Path, text: str) -> None:
    p = tmp_path / "MODEL.json"
    p.write_text(text)
    with pytest.raises(ConfigError, match="not valid JSON"):
        CalibratedModel.load(p)


def _inputs(tmp: Path, d: Doc) -> dict[str, list[str]]:
    q = np.radians([[10.0, 20.0, -10.0, 5.0, 30.0, 15.0], [0.0, 10.0, 5.0, -5.0, 20.0, 0.0]])
    write_joints_csv(tmp / "joints.csv", q)
    (tmp / "targets.csv").write_text(
        "q1,q2,q3,q4,q5,q6,x,y,z\n10,20,-10,5,30,15,1500,200,300\n")
    model = str(tmp / "MODEL.json")
    return {
        "predict": ["predict", "--model", model, "--joints", str(tmp / "joints.csv"),
                    "--out", str(tmp / "pred.csv")],
        "compensate": ["compensate", "--model", model, "--targets", str(tmp / "targets.csv"),
                       "--out", str(tmp / "comp.csv")],
        "table": ["table", "--model", model, "--kind", "frames", "--out",
                  str(tmp / "table.json")],
        "report": ["report", model, "--out", str(tmp / "r.html")],
    }


@pytest.mark.parametrize("command", ["predict", "compensate", "table", "report"])
@pytest.mark.parametrize("name", ["parameter +0.5 mm", "parameter 1e308", "coverage a string",
                                  "terms of junk", "nested"])
def test_commands_refuse_a_bad_model_in_one_line(good: Doc, tmp_path: Path, command: str,
                                                 name: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "MODEL.json"
    if name == "nested":
        p.write_text('{"metrics": ' + "[" * 100_000 + "]" * 100_000 + "}")
    else:
        d = copy.deepcopy(good)
        CORRUPTIONS[name][0](d)
        p.write_text(json.dumps(d))
    argv = _inputs(tmp_path, good)[command]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and str(p) in err


def _with_thermal(good: Doc) -> Doc:
    """``good`` refitted with a thermal term: the term is in ``fit.thermal``, and the id and
    seal are those a fit writes (scheme 3)."""
    cm = CalibratedModel.from_dict(copy.deepcopy(good))
    cm.fit["thermal"] = {"components": ["dz"], "coefficients_mm_per_c": [0.004] * 6,
                         "t_ref_c": 21.5}
    cm.model_id = cm.compute_id()
    return cm.to_dict()


def test_the_thermal_term_is_covered_by_the_hash(good: Doc, tmp_path: Path) -> None:
    d = _with_thermal(good)
    assert d["integrity"]["scheme"] == "robocal.model-hash/3"
    assert "fit.thermal" in d["integrity"]["covers"] and d["model_id"] != good["model_id"]
    p = tmp_path / "MODEL.json"
    p.write_text(json.dumps(d))
    assert CalibratedModel.load(p).model_id == d["model_id"]
    d["fit"]["thermal"]["coefficients_mm_per_c"][2] = 0.04  # ten times the growth of J3
    p.write_text(json.dumps(d))
    with pytest.raises(ConfigError, match="does not match its model_id"):
        CalibratedModel.load(p)
    # the rest of ``fit`` stays free-form: a note does not change the id
    d = _with_thermal(good)
    d["fit"]["note"] = "checked by the night shift"
    p.write_text(json.dumps(d))
    assert CalibratedModel.load(p).model_id == d["model_id"]


def test_a_scheme_2_file_loads_unless_it_carries_a_thermal_term(good: Doc,
                                                                tmp_path: Path) -> None:
    """Files written before scheme 3 verify as they were written; one with a thermal term,
    which its hash did not cover, is refused with the key named."""
    from robocal.kinematics._integrity import digests

    d = copy.deepcopy(good)
    d["integrity"] = {"scheme": "robocal.model-hash/2", "covers": [],
                      "sha256": digests(d, scheme="robocal.model-hash/2")[0]}
    d["model_id"] = d["integrity"]["sha256"][:16]
    p = tmp_path / "MODEL.json"
    p.write_text(json.dumps(d))
    assert CalibratedModel.load(p).model_id == d["model_id"]
    d["fit"] = {"thermal": {"components": ["dz"], "coefficients_mm_per_c": [0.0] * 6}}
    p.write_text(json.dumps(d))
    with pytest.raises(ConfigError, match=r"fit\.thermal"):
        CalibratedModel.load(p)
