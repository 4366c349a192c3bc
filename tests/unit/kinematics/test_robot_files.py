"""Robot description files: built-ins, round trip, and one clear error per bad file."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.errors import ConfigError
from robocal.kinematics import RobotDescription, builtin_robots, load_robot

GOOD = """
name = "Test arm"
[[joints]]
a_mm = 150.0
d_mm = 450.0
alpha_deg = -90.0
theta_offset_deg = 0.0
min_deg = -170.0
max_deg = 170.0
gear_ratio = 121.0
mass_kg = 12.0
com_mm = [0.0, 10.0, 100.0]
[[joints]]
a_mm = 600.0
d_mm = 0.0
alpha_deg = 0.0
min_deg = -90.0
max_deg = 150.0
"""


def test_builtins_load() -> None:
    names = builtin_robots()
    assert {"fanuc_lrmate200id", "ur10", "kuka_kr210_r3100", "fanuc_lrmate200i"} <= set(names)
    for n in names:
        r = load_robot(n)
        assert r.dof == 6
        assert np.all(r.joint_limits[:, 0] < r.joint_limits[:, 1])
    assert load_robot("ur10").has_masses


def test_file_units_and_round_trip(tmp_path: Path) -> None:
    f = tmp_path / "arm.toml"
    f.write_text(GOOD)
    r = load_robot(f)
    assert r.name == "Test arm" and r.dof == 2
    j = r.joints[0]
    assert j.a == pytest.approx(0.15) and j.d == pytest.approx(0.45)
    assert j.alpha == pytest.approx(-math.pi / 2) and j.gear_ratio == 121.0
    assert j.com == pytest.approx((0.0, 0.01, 0.1))
    assert RobotDescription.from_dict(r.to_dict()) == r


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (lambda s: s.replace('name = "Test arm"', ""), "name"),
        (lambda s: s.replace("a_mm = 150.0", 'a_mm = "long"'), "joints[1].a_mm"),
        (lambda s: s.replace("max_deg = 170.0", "max_deg = -180.0"), "joints[1].min_deg"),
        (lambda s: s.replace("gear_ratio = 121.0", "gear_ratio = -5"), "joints[1].gear_ratio"),
        (lambda s: s.replace("com_mm = [0.0, 10.0, 100.0]", ""), "joints[1].com_mm"),
        (lambda s: s.replace("d_mm = 450.0", "d_mm = 450.0\nlength = 3"), "joints[1].length"),
        (lambda s: s.replace("a_mm = 600.0\n", ""), "joints[2].a_mm"),
        (lambda s: "colour = 'red'\n" + s, "colour"),
    ],
)
def test_bad_file_names_file_and_key(tmp_path: Path, edit, key: str) -> None:  # type: ignore[no-untyped-def]
    f = tmp_path / "bad.toml"
    f.write_text(edit(GOOD))
    with pytest.raises(ConfigError) as info:
        load_robot(f)
    assert info.value.key == key
    assert str(f) in str(info.value)


def test_not_toml_and_missing(tmp_path: Path) -> None:
    f = tmp_path / "x.toml"
    f.write_text("name = [unclosed")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_robot(f)
    with pytest.raises(ConfigError, match="no such file"):
        load_robot(tmp_path / "missing.toml")


scalars = st.one_of(st.none(), st.booleans(), st.integers(-1000, 1000),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=5))
joint_tables = st.dictionaries(
    st.sampled_from(["a_mm", "d_mm", "alpha_deg", "min_deg", "max_deg", "gear_ratio", "mass_kg",
                     "com_mm", "sign", "coupled_to", "coupling", "bogus"]),
    st.one_of(scalars, st.lists(scalars, max_size=4)), max_size=8)


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.sampled_from(["name", "joints", "tool_mm", "gravity", "other"]),
                       st.one_of(scalars, st.lists(joint_tables, max_size=3)), max_size=4))
def test_arbitrary_content_gives_config_error_or_robot(data: dict) -> None:  # type: ignore[type-arg]
    try:
        r = RobotDescription.from_dict(data, source="fuzz.toml")
    except ConfigError as err:
        assert "fuzz.toml" in str(err)
    else:
        assert r.dof >= 1


@settings(max_examples=60, deadline=None)
@given(key=st.sampled_from(["a_mm", "d_mm", "alpha_deg", "theta_offset_deg"]),
       value=st.one_of(st.floats(allow_nan=False, allow_infinity=False),
                       st.integers(-10**400, 10**400)))
def test_a_number_of_any_size_is_a_robot_that_computes_or_a_config_error(
        key: str, value: float) -> None:
    """Property: a robot file with any number in a joint either loads and gives finite
    positions without numpy warnings, or is refused as a ConfigError (no overflow later)."""
    import warnings

    from robocal.kinematics import ErrorModelSpec, KinematicModel

    data = load_robot("fanuc_lrmate200i").to_dict()
    data["joints"][1][key] = value
    try:
        robot = RobotDescription.from_dict(data, source="big.toml")
    except ConfigError as err:
        assert "big.toml" in str(err) and key in str(err)
        return
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
        p = m.positions(np.zeros((2, robot.dof)), m.nominal_params())
    assert np.all(np.isfinite(p))
