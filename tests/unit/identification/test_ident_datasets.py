"""The IPA UR10 CSV parser (``;`` separator, decimal comma): property tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.errors import DataError
from robocal.identification.datasets import (
    IPA_JOINT_COLUMNS,
    IPA_POINT_COLUMNS,
    IPA_STD_COLUMNS,
    parse_ipa_csv,
)

HEADER = ["Timestamp", "Goal x", *IPA_JOINT_COLUMNS, "measurement_temperature",
          "measurement_x", "measurement_std_x", "measurement_y", "measurement_std_y",
          "measurement_z", "measurement_std_z", "measurement_rx"]


def _fmt(v: float) -> str:
    return repr(float(v)).replace(".", ",")


def _render(rows: list[dict[str, float]], header: list[str] = HEADER) -> str:
    lines = [";".join(header)]
    for r in rows:
        lines.append(";".join(_fmt(r.get(h, 0.0)) if h != "Timestamp" else "2,02011E+13"
                              for h in header))
    return "\n".join(lines) + "\n"


finite = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False)
positive = st.floats(min_value=1e-6, max_value=1.0)
row = st.fixed_dictionaries({
    **{c: finite for c in IPA_JOINT_COLUMNS}, **{c: finite for c in IPA_POINT_COLUMNS},
    **{c: positive for c in IPA_STD_COLUMNS}, "Goal x": finite,
    "measurement_temperature": finite, "measurement_rx": finite})


@settings(max_examples=60, deadline=None)
@given(st.lists(row, min_size=1, max_size=12), st.booleans())
def test_round_trip_of_rendered_files(rows, with_sigma):
    data = parse_ipa_csv(_render(rows), with_sigma=with_sigma, prefix="B")
    assert len(data) == len(rows) and data.dof == 6
    q = np.array([[r[c] for c in IPA_JOINT_COLUMNS] for r in rows])
    p = np.array([[r[c] for c in IPA_POINT_COLUMNS] for r in rows]) * 1e-3
    np.testing.assert_array_equal(data.q, q)                 # rad, not wrapped
    np.testing.assert_allclose(data.p, p, rtol=1e-15, atol=0)
    if with_sigma:
        s = np.array([[r[c] for c in IPA_STD_COLUMNS] for r in rows]) * 1e-3
        np.testing.assert_allclose(data.sigma, s, rtol=1e-15)
    else:
        assert data.sigma is None
    assert data.pose_id[0] == "B00000" and len(set(data.pose_id)) == len(rows)


@settings(max_examples=40, deadline=None)
@given(st.lists(row, min_size=1, max_size=5), st.sampled_from(IPA_JOINT_COLUMNS +
                                                              IPA_POINT_COLUMNS))
def test_missing_required_column_names_it(rows, missing):
    header = [h for h in HEADER if h != missing]
    with pytest.raises(DataError) as err:
        parse_ipa_csv(_render(rows, header), source="x.csv")
    assert err.value.key == missing and "x.csv" in str(err.value)


@settings(max_examples=40, deadline=None)
@given(st.lists(row, min_size=1, max_size=6), st.data(),
       st.sampled_from(["nan", "NaN", "inf", "-inf", "abc", "", "1,2,3"]))
def test_bad_cell_names_row_and_column(rows, data, bad):
    i = data.draw(st.integers(0, len(rows) - 1))
    col = data.draw(st.sampled_from(IPA_JOINT_COLUMNS + IPA_POINT_COLUMNS))
    lines = _render(rows).splitlines()
    cells = lines[i + 1].split(";")
    cells[HEADER.index(col)] = bad
    lines[i + 1] = ";".join(cells)
    with pytest.raises(DataError) as err:
        parse_ipa_csv("\n".join(lines))
    assert err.value.key == col and f"row {i + 2}" in str(err.value)


@given(st.text(alphabet=";,\n -.0123456789eainf", max_size=300))
@settings(max_examples=80, deadline=None)
def test_arbitrary_body_never_crashes_with_anything_but_data_error(body):
    try:
        data = parse_ipa_csv(";".join(HEADER) + "\n" + body)
    except DataError:
        return
    assert np.isfinite(data.q).all() and np.isfinite(data.p).all()


def test_empty_and_short_files():
    with pytest.raises(DataError, match="empty"):
        parse_ipa_csv("")
    with pytest.raises(DataError, match="no data rows"):
        parse_ipa_csv(";".join(HEADER) + "\n")
    with pytest.raises(DataError, match="fields"):
        parse_ipa_csv(";".join(HEADER) + "\n1,0;2,0\n")


def test_non_positive_std_is_rejected_only_when_used():
    r = {c: 0.5 for c in HEADER if c != "Timestamp"}
    r["measurement_std_y"] = 0.0
    text = _render([r])
    assert parse_ipa_csv(text).sigma is None
    with pytest.raises(DataError, match="positive"):
        parse_ipa_csv(text, with_sigma=True)
    assert math.isclose(parse_ipa_csv(text).p[0, 0], 0.5e-3)
