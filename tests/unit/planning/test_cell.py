"""Cell description files: defaults, SI accessors, clear errors, parser fuzzing."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robocal.errors import ConfigError
from robocal.planning import Cell, builtin_cells, load_cell

from .helpers import to_toml


def test_demo_cell_loads_with_defaults_and_si_accessors() -> None:
    assert "demo" in builtin_cells()
    c = load_cell("demo")
    assert c.name == "demo"
    np.testing.assert_allclose(c.tracker_position_m, [1.78, 0.16, 0.42])
    assert c.reflector.offset_mm is None  # follows the robot file
    np.testing.assert_allclose(c.nest_direction, [0, 0, 1])
    assert c.acceptance_rad == pytest.approx(math.radians(30.0))
    assert c.floor_z_m == pytest.approx(-0.6)
    lo, hi, beam = c.boxes_m()
    assert lo.shape == (2, 3) and np.all(lo < hi) and beam.tolist() == [True, False]


def test_minimal_cell_defaults() -> None:
    c = Cell.from_dict({"tracker": {"position_mm": [2000, 0, 500]}})
    assert c.tracker.position_tolerance_mm == 100.0
    assert c.reflector.acceptance_deg == 30.0
    assert c.floor.z_mm == 0.0 and c.keep_out == []
    assert c.motion.max_joint_step_deg == 90.0
    lo, _hi, beam = c.boxes_m()
    assert lo.shape == (0, 3) and beam.shape == (0,)


def test_file_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"no such file.*built-in: demo"):
        load_cell(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[tracker\nposition_mm = 1")
    with pytest.raises(ConfigError, match=r"bad\.toml: not valid TOML"):
        load_cell(bad)


@pytest.mark.parametrize(("text", "key", "allowed"), [
    ('colour = "red"\n[tracker]\nposition_mm = [1, 2, 3]\n', "colour", "keep_out"),
    ("[tracker]\nposition_mm = [1, 2, 3]\nheight_mm = 3\n", "tracker.height_mm",
     "position_tolerance_mm"),
    ("[tracker]\nposition_mm = [1, 2, 3]\n[[keep_out]]\nmin_mm = [0, 0, 0]\nmax_mm = [1, 1, 1]\n"
     "[[keep_out]]\nmin_mm = [0, 0, 0]\nmax_mm = [1, 1, 1]\nshape = 'ball'\n",
     "keep_out[2].shape", "blocks_beam"),
])
def test_unknown_keys_are_rejected_naming_file_and_key(tmp_path: Path, text: str, key: str,
                                                       allowed: str) -> None:
    f = tmp_path / "cell.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_cell(f)
    msg = str(info.value)
    assert str(f) in msg and f"key {key!r}" in msg and "unknown key" in msg and allowed in msg
    assert info.value.key == key and info.value.source == str(f)


@pytest.mark.parametrize(("data", "key"), [
    ({}, "tracker"),
    ({"tracker": {"position_mm": [1, 2]}}, "tracker.position_mm"),
    ({"tracker": {"position_mm": [1, 2, 3], "min_range_mm": 5000, "max_range_mm": 1000}},
     "tracker"),
    ({"tracker": {"position_mm": [1, 2, 3]}, "reflector": {"acceptance_deg": 0}},
     "reflector.acceptance_deg"),
    ({"tracker": {"position_mm": [1, 2, 3]}, "reflector": {"direction": [0, 0, 0]}},
     "reflector.direction"),
    ({"tracker": {"position_mm": [1, 2, 3]}, "floor": {"z_mm": "low"}}, "floor.z_mm"),
    ({"tracker": {"position_mm": [1, 2, 3]}, "floor": {"z_mm": True}}, "floor.z_mm"),
    ({"tracker": {"position_mm": [1, 2, 3]}, "floor": {"z_mm": math.nan}}, "floor.z_mm"),
    ({"tracker": {"position_mm": [1, 2, 3]},
      "keep_out": [{"min_mm": [0, 0, 0], "max_mm": [1, 1, 0]}]}, "keep_out[1]"),
    ({"tracker": {"position_mm": [1, 2, 3]}, "robot": {"link_radii_mm": [10, -1]}},
     "robot.link_radii_mm"),
    ({"tracker": {"position_mm": [1, 2, 3]}, "robot": {"joint_ranges_deg": [[0, 1], [3, 1]]}},
     "robot.joint_ranges_deg"),
    ({"tracker": {"position_mm": [1, 2, 3]}, "motion": {"speed_fraction": 2.0}},
     "motion.speed_fraction"),
])
def test_invalid_values_are_one_clear_error(data: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        Cell.from_dict(data, source="c.toml")
    assert info.value.key == key
    assert str(info.value).startswith(f"c.toml: key {key!r}: ")
    assert "\n" not in str(info.value)


# -- hypothesis: round trips and fuzzing ---------------------------------------------------------
finite = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False)
pos = st.floats(min_value=1.0, max_value=500.0)
vec3 = st.lists(finite, min_size=3, max_size=3)
text = st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=12)


@st.composite
def boxes(draw: st.DrawFn) -> dict[str, Any]:
    lo = draw(vec3)
    size = draw(st.lists(pos, min_size=3, max_size=3))
    hi = [a + s for a, s in zip(lo, size, strict=True)]
    return {"name": draw(text), "min_mm": lo, "max_mm": hi, "blocks_beam": draw(st.booleans())}


@st.composite
def cells(draw: st.DrawFn) -> dict[str, Any]:
    rmin = draw(st.floats(min_value=0.0, max_value=5000.0))
    tracker = draw(vec3)
    d: dict[str, Any] = {
        "name": draw(text),
        "tracker": {"position_mm": tracker, "min_range_mm": rmin,
                    "max_range_mm": rmin + draw(pos),
                    "position_tolerance_mm": draw(st.floats(0.0, 2000.0))},
        "reflector": {"direction": draw(st.lists(st.floats(0.1, 1.0), min_size=3, max_size=3)),
                      "acceptance_deg": draw(st.floats(1.0, 90.0))},
        "floor": {"z_mm": tracker[2] - draw(pos)},
        "keep_out": draw(st.lists(boxes(), max_size=3)),
        "motion": {"max_joint_step_deg": draw(st.floats(1.0, 720.0)),
                   "speed_fraction": draw(st.floats(0.01, 1.0))},
    }
    if draw(st.booleans()):
        d["reflector"]["offset_mm"] = draw(vec3)
    if draw(st.booleans()):
        d["robot"] = {"link_radii_mm": draw(st.lists(pos, min_size=6, max_size=6)),
                      "clearance_mm": draw(st.floats(0.0, 50.0))}
    return d


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cells())
def test_valid_cells_round_trip_through_toml(tmp_path: Path, data: dict[str, Any]) -> None:
    c = Cell.from_dict(data)
    f = tmp_path / "c.toml"
    f.write_text(to_toml(c.to_dict()))
    back = load_cell(f)
    assert back == c
    assert Cell.from_dict(back.to_dict()) == c


@settings(max_examples=60, deadline=None)
@given(cells(), st.sampled_from(["", "tracker", "reflector", "floor", "motion", "keep_out"]),
       st.from_regex(r"[a-z][a-z_]{0,10}", fullmatch=True))
def test_an_extra_key_anywhere_is_named(data: dict[str, Any], where: str, extra: str) -> None:
    if where == "":
        known = set(Cell.model_fields)
        target = data
    elif where == "keep_out":
        if not data["keep_out"]:
            data["keep_out"] = [{"min_mm": [0, 0, 0], "max_mm": [1, 1, 1]}]
        target = data["keep_out"][-1]
        known = {"name", "min_mm", "max_mm", "blocks_beam"}
    else:
        target = data[where]
        known = set(type(getattr(Cell.from_dict(data), where)).model_fields)
    if extra in known:
        return
    target[extra] = 1
    with pytest.raises(ConfigError) as info:
        Cell.from_dict(data, source="x.toml")
    assert info.value.key is not None and info.value.key.endswith(extra)
    assert "unknown key" in str(info.value) and str(info.value).startswith("x.toml: ")


json_like = st.recursive(
    st.none() | st.booleans() | st.integers(-10, 10) | st.floats(allow_nan=True) | text,
    lambda children: st.lists(children, max_size=4) | st.dictionaries(text, children, max_size=4),
    max_leaves=20)


@settings(max_examples=150, deadline=None)
@given(st.dictionaries(st.sampled_from(["name", "tracker", "reflector", "robot", "floor",
                                        "keep_out", "motion", "junk"]), json_like, max_size=6))
def test_garbage_gives_config_error_or_a_cell(data: dict[str, Any]) -> None:
    try:
        c = Cell.from_dict(data, source="g.toml")
    except ConfigError as err:
        assert str(err).startswith("g.toml")
    else:
        assert isinstance(c, Cell)
