"""The declarative robot and MODEL.json tables (ADR 0045): one ConfigError naming the key for
any bad value, round trips, and a MODEL.json written before them still loads with its id."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.errors import ConfigError
from robocal.kinematics import CalibratedModel, RobotDescription

FIXTURES = Path(__file__).parent / "fixtures"

finite = st.floats(-1e5, 1e5, allow_nan=False, allow_infinity=False)
joint_tables = st.fixed_dictionaries(
    {"a_mm": finite, "d_mm": finite, "alpha_deg": finite, "min_deg": st.floats(-360, -1),
     "max_deg": st.floats(1, 360)},
    optional={"theta_offset_deg": finite, "gear_ratio": st.floats(0.5, 200),
              "sign": st.sampled_from([1, -1]), "name": st.text(max_size=4),
              "max_speed_deg_s": st.floats(1, 720)})
robots = st.fixed_dictionaries(
    {"name": st.text(min_size=1, max_size=8).filter(str.strip),
     "joints": st.lists(joint_tables, min_size=1, max_size=7)},
    optional={"tool_mm": st.lists(finite, min_size=3, max_size=3),
              "manufacturer": st.text(max_size=5),
              "convention": st.sampled_from(["standard", "modified"])})
not_numbers = st.one_of(st.text(max_size=3), st.booleans(), st.none(),
                        st.sampled_from([math.nan, math.inf, -math.inf, 1e7, -1e300, 10**400]),
                        st.lists(finite, max_size=2), st.dictionaries(st.text(max_size=2),
                                                                      finite, max_size=2))


@settings(max_examples=80, deadline=None)
@given(robots)
def test_a_valid_robot_table_loads_in_si_and_round_trips(data: dict[str, Any]) -> None:
    r = RobotDescription.from_dict(data, source="gen.toml")
    assert r.name == data["name"].strip() and r.dof == len(data["joints"])
    for j, jd in zip(r.joints, data["joints"], strict=True):
        assert j.q_min == math.radians(jd["min_deg"]) and j.q_max == math.radians(jd["max_deg"])
        assert j.sign == jd.get("sign", 1) and j.name == jd.get("name", "")
    if data.get("convention", "standard") == "standard":
        assert [j.d for j in r.joints] == [jd["d_mm"] * 1e-3 for jd in data["joints"]]
    back = RobotDescription.from_dict(r.to_dict(), source="again.toml")  # mm <-> m: rounding
    for j, k in zip(r.joints, back.joints, strict=True):
        assert (k.a, k.d, k.alpha, k.q_min, k.sign) == pytest.approx((j.a, j.d, j.alpha, j.q_min,
                                                                      j.sign), rel=1e-12)


@settings(max_examples=100, deadline=None)
@given(data=robots, where=st.integers(0, 6),
       field=st.sampled_from(["a_mm", "d_mm", "alpha_deg", "theta_offset_deg", "min_deg",
                              "gear_ratio", "mass_kg", "coupling", "max_speed_deg_s"]),
       value=not_numbers)
def test_any_bad_number_is_one_error_naming_the_joint_key(data: dict[str, Any], where: int,
                                                          field: str, value: Any) -> None:
    i = where % len(data["joints"])
    data["joints"][i][field] = value
    if field == "mass_kg":
        data["joints"][i]["com_mm"] = [0.0, 0.0, 10.0]
    with pytest.raises(ConfigError) as info:
        RobotDescription.from_dict(data, source="bad.toml")
    assert info.value.key == f"joints[{i + 1}].{field}"
    assert str(info.value).startswith(f"bad.toml: key 'joints[{i + 1}].{field}': must be a "
                                      "finite number within +-1e+06, got ")


@settings(max_examples=50, deadline=None)
@given(data=robots, extra=st.text(min_size=1, max_size=6), nested=st.booleans())
def test_an_unknown_key_is_named_with_the_keys_allowed_there(data: dict[str, Any], extra: str,
                                                             nested: bool) -> None:
    table = data["joints"][0] if nested else data
    extra = f"x_{extra}"  # never a key of the format
    table[extra] = 1.0
    with pytest.raises(ConfigError, match=r"unknown key \(allowed: ") as info:
        RobotDescription.from_dict(data, source="x.toml")
    assert info.value.key == (f"joints[1].{extra}" if nested else extra)


@pytest.fixture(scope="module")
def before() -> dict[str, Any]:
    return dict(json.loads((FIXTURES / "model_written_before_0045.json").read_text()))


def test_a_model_file_written_before_the_tables_loads_with_its_id(tmp_path: Path) -> None:
    path = FIXTURES / "model_written_before_0045.json"
    cal = CalibratedModel.load(path)
    assert cal.model_id == cal.compute_id() == "a0ad0b644c8f058b"
    assert cal.fallback is not None and cal.coverage is not None
    assert cal.covariance is not None and cal.metrics == {"rms_mm": 0.1}
    cal.save(tmp_path / "again.json")
    assert CalibratedModel.load(tmp_path / "again.json").model_id == cal.model_id
    p = cal.predict(np.zeros((1, 6)))
    assert np.all(np.isfinite(p))


json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10, 10), st.floats(), st.text(max_size=3)),
    lambda inner: st.one_of(st.lists(inner, max_size=3),
                            st.dictionaries(st.text(max_size=3), inner, max_size=3)),
    max_leaves=8)


@settings(max_examples=60, deadline=None)
@given(section=st.sampled_from(["robot", "error_model", "T_tracker_base_ref_mm", "parameters",
                                "coverage_deg", "covariance", "metrics", "fit", "data",
                                "kind", "fallback", "unknown_section"]),
       value=json_values)
def test_any_section_value_loads_or_is_one_config_error(before: dict[str, Any], section: str,
                                                        value: Any) -> None:
    d = copy.deepcopy(before)
    d[section] = value
    try:
        CalibratedModel.from_dict(d, source="M.json")
    except ConfigError as err:
        assert str(err).startswith("M.json")
        if section == "unknown_section":
            assert err.key == "unknown_section" and "allowed: T_tracker_base_ref_mm" in str(err)
