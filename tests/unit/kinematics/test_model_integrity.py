"""MODEL.json's hash covers the robot description (and every section that changes a
prediction), a site secret signs it, and the robot geometry must be the nominal robot's
(issue 25 item 4)."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel, load_robot
from robocal.kinematics._integrity import digests

Doc = dict[str, Any]
SECRET = b"0123456789abcdef-site"


@pytest.fixture(scope="module")
def cal() -> CalibratedModel:
    robot = load_robot("fanuc_lrmate200i")
    T = np.eye(4)
    T[:3, 3] = [1.8, 0.2, -0.4]
    model = KinematicModel(robot, ErrorModelSpec.constant(robot.dof), T)
    x = model.nominal_params() + np.random.default_rng(0).normal(0.0, 1e-4, model.size)
    const = CalibratedModel(model, x)
    return CalibratedModel(model, x, covariance=np.eye(model.size) * 1e-12,
                           coverage=np.tile([[-1.5, 1.5]], (robot.dof, 1)), fallback=const)


@pytest.fixture
def doc(cal: CalibratedModel) -> Doc:
    return json.loads(json.dumps(cal.to_dict()))


def rehash(d: Doc) -> Doc:
    """What an attacker who knows the (unkeyed) scheme does after editing: recompute it."""
    sha, _ = digests(d)
    d["model_id"], d["integrity"]["sha256"] = sha[:16], sha
    return d


def joint(n: int, key: str, delta: float) -> Callable[[Doc], None]:
    def change(d: Doc) -> None:
        d["robot"]["joints"][n - 1][key] += delta
    return change


def widen_j1(d: Doc) -> None:
    d["robot"]["joints"][0].update(min_deg=-720.0, max_deg=720.0)


def rename(d: Doc) -> None:
    d["robot"]["name"] = "another robot"


def base_offset(d: Doc) -> None:
    d["robot"]["base_xyz_mm"] = [90_000.0, 0.0, 0.0]
    d["robot"]["base_rpy_deg"] = [0.0, 0.0, 0.0]


def base_rotation(d: Doc) -> None:
    d["robot"]["base_xyz_mm"] = [0.0, 0.0, 0.0]
    d["robot"]["base_rpy_deg"] = [0.0, 0.0, 3000.0]


def param(name: str, value: float) -> Callable[[Doc], None]:
    def change(d: Doc) -> None:
        next(p for p in d["parameters"] if p["name"] == name)["value"] = value
    return change


def reference_far(d: Doc) -> None:
    d["T_tracker_base_ref_mm"][0][3] = 90_000.0


ROBOT_EDITS: dict[str, Callable[[Doc], None]] = {
    "J2 a_mm +500 mm": joint(2, "a_mm", 500.0),
    "J1 limits +-720 deg": widen_j1,
    "robot renamed": rename,
    "base offset +90 m": base_offset,
    "base rotation +3000 deg": base_rotation,
    "J3 alpha +10 deg": joint(3, "alpha_deg", 10.0),
}


@pytest.mark.parametrize("name", sorted(ROBOT_EDITS))
def test_robot_section_edits_change_the_hash(doc: Doc, name: str) -> None:
    d = copy.deepcopy(doc)
    ROBOT_EDITS[name](d)
    assert digests(d)[0] != doc["integrity"]["sha256"]


@pytest.mark.parametrize("edit", [joint(2, "a_mm", 5.0), joint(6, "max_deg", -1.0),
                                  joint(4, "theta_offset_deg", 0.5)])
def test_small_robot_edits_are_refused_by_the_hash(doc: Doc, edit: Callable[[Doc], None]
                                                   ) -> None:
    # within the plausibility tolerance: only the hash can tell
    d = copy.deepcopy(doc)
    edit(d)
    with pytest.raises(ConfigError, match="does not match its model_id"):
        CalibratedModel.from_dict(d, source="m.json")


IMPLAUSIBLE: dict[str, tuple[Callable[[Doc], None], str]] = {
    **{k: (v, "not a plausible description of this robot") for k, v in ROBOT_EDITS.items()},
    "base.ez parameter +3000 deg": (param("base.ez", 3000.0), "base.ez"),
    "base.dx parameter +90 m": (param("base.dx", 90_000.0), "base.dx"),
    "tracker <- base 90 m away": (reference_far, "80000 mm"),
}


@pytest.mark.parametrize("name", sorted(IMPLAUSIBLE))
def test_implausible_geometry_is_refused_even_with_a_recomputed_hash(doc: Doc, name: str
                                                                     ) -> None:
    change, needle = IMPLAUSIBLE[name]
    d = copy.deepcopy(doc)
    change(d)
    rehash(d)
    with pytest.raises(ConfigError) as info:
        CalibratedModel.from_dict(d, source="m.json")
    assert needle in str(info.value)


def test_nominal_of_the_daemon_wins_and_narrower_limits_pass(doc: Doc) -> None:
    d = copy.deepcopy(doc)
    d["robot"]["joints"][0].update(min_deg=-150.0, max_deg=150.0)   # narrower: fine
    CalibratedModel.from_dict(rehash(d), source="m.json")
    other = load_robot("fanuc_lrmate200id")
    with pytest.raises(ConfigError, match="nominal description is 'FANUC LR Mate 200iD'"):
        CalibratedModel.from_dict(copy.deepcopy(doc), source="m.json", nominal=other)


def test_prediction_sections_are_all_covered(doc: Doc) -> None:
    for edit in (lambda d: d["coverage_deg"][0].__setitem__(0, -10.0),
                 lambda d: d["robot"]["joints"][5].__setitem__("d_mm", 80.5),
                 lambda d: d["robot"].__setitem__("tool_mm", [30.0, 20.0, 61.0]),
                 lambda d: d["fallback"]["parameters"][0].__setitem__("sigma", 1.0)):
        d = copy.deepcopy(doc)
        edit(d)
        with pytest.raises(ConfigError, match=r"model_id|fallback"):
            CalibratedModel.from_dict(d, source="m.json")


def test_site_secret_signs_and_is_checked(cal: CalibratedModel) -> None:
    signed = json.loads(json.dumps(cal.to_dict(secret=SECRET)))
    back = CalibratedModel.from_dict(signed, source="m.json", secret=SECRET)
    assert back.model_id == cal.model_id          # the id is the same with or without a secret
    with pytest.raises(ConfigError, match="not signed"):
        CalibratedModel.from_dict(cal.to_dict(), source="m.json", secret=SECRET)
    with pytest.raises(ConfigError, match="does not match this site's secret"):
        CalibratedModel.from_dict(signed, source="m.json", secret=b"another-site-secret!")
    # an edit with a recomputed public hash does not carry a valid signature
    d = copy.deepcopy(signed)
    d["parameters"][0]["value"] += 0.5
    with pytest.raises(ConfigError, match="site's secret"):
        CalibratedModel.from_dict(rehash(d), source="m.json", secret=SECRET)


def test_earlier_files_get_a_clear_message_to_refit(doc: Doc) -> None:
    d = copy.deepcopy(doc)
    del d["integrity"]
    with pytest.raises(ConfigError, match=r"earlier robocal.*refit"):
        CalibratedModel.from_dict(d, source="m.json")
    assert CalibratedModel.from_dict(d, source="m.json", verify=False).model_id == d["model_id"]


def test_loaded_model_saves_and_loads_again(cal: CalibratedModel, tmp_path) -> None:
    cal.save(tmp_path / "a.json", secret=SECRET)
    back = CalibratedModel.load(tmp_path / "a.json", secret=SECRET)
    back.save(tmp_path / "b.json", secret=SECRET)
    again = CalibratedModel.load(tmp_path / "b.json", secret=SECRET)
    assert again.model_id == back.model_id == cal.model_id
    np.testing.assert_array_equal(again.params, back.params)
