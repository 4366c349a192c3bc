"""TARGETS.csv parser (hypothesis) and JOINTS.csv writer."""

from __future__ import annotations

import csv
import io
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal.compensation import (
    CompensationResult,
    TargetSet,
    compensated_joints_csv_text,
    read_targets_csv,
    write_compensated_joints_csv,
)
from robocal.errors import DataError
from robocal.kinematics import matrix_to_wpr, wpr_to_matrix

coord = st.floats(-5000.0, 5000.0, allow_nan=False)
angle = st.floats(-360.0, 360.0, allow_nan=False)


@st.composite
def target_rows(draw: Any) -> dict[str, Any]:
    n = draw(st.integers(1, 8))
    dof = draw(st.integers(1, 7))
    return {
        "xyz": draw(st.lists(st.lists(coord, min_size=3, max_size=3), min_size=n, max_size=n)),
        "q": draw(st.lists(st.lists(angle, min_size=dof, max_size=dof), min_size=n,
                           max_size=n)),
        "wpr": draw(st.none() | st.lists(
            st.tuples(st.floats(-179.0, 179.0), st.floats(-89.0, 89.0), st.floats(-179.0, 179.0)),
            min_size=n, max_size=n)),
        "ids": draw(st.booleans()),
        "extra": draw(st.booleans()),
        "order": draw(st.randoms(use_true_random=False)),
        "european": draw(st.booleans()),
    }


def _render(spec: dict[str, Any]) -> str:
    n, dof = len(spec["xyz"]), len(spec["q"][0])
    cols: dict[str, list[str]] = {}
    for k, c in enumerate("xyz"):
        cols[c] = [repr(r[k]) for r in spec["xyz"]]
    for j in range(dof):
        cols[f"q{j + 1}"] = [repr(r[j]) for r in spec["q"]]
    if spec["wpr"] is not None:
        for k, c in enumerate("wpr"):
            cols[c] = [repr(r[k]) for r in spec["wpr"]]
    if spec["ids"]:
        cols["target_id"] = [f"P{i}" for i in range(n)]
    if spec["extra"]:
        cols["comment"] = ["ignored"] * n
    names = list(cols)
    spec["order"].shuffle(names)                          # column order does not matter
    delim = ";" if spec["european"] else ","
    lines = [delim.join(names)]
    for i in range(n):
        cells = [cols[c][i] for c in names]
        if spec["european"]:
            cells = [c.replace(".", ",") for c in cells]
        lines.append(delim.join(cells))
    return "\n".join(lines) + "\n"


@settings(max_examples=80, deadline=None)
@given(target_rows())
def test_parser_reads_what_was_written(spec: dict[str, Any]) -> None:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "targets.csv"
        path.write_text(_render(spec))
        ts = read_targets_csv(path, dof=len(spec["q"][0]))
    np.testing.assert_allclose(ts.p, np.array(spec["xyz"]) * 1e-3, rtol=1e-15, atol=0)
    np.testing.assert_allclose(ts.q_seed, np.radians(spec["q"]), rtol=1e-15, atol=0)
    if spec["wpr"] is None:
        assert ts.R is None
    else:
        assert ts.R is not None
        want = np.stack([wpr_to_matrix(*np.radians(r)) for r in spec["wpr"]])
        np.testing.assert_allclose(ts.R, want, atol=1e-14)
    if spec["ids"]:
        assert ts.labels == tuple(f"P{i}" for i in range(len(ts)))


@settings(max_examples=60, deadline=None)
@given(target_rows(), st.data())
def test_parser_names_the_bad_cell(spec: dict[str, Any], data: st.DataObject) -> None:
    text = _render({**spec, "european": False, "extra": False})
    lines = text.splitlines()
    header = lines[0].split(",")
    numeric = [c for c in header if c != "target_id"]
    col = data.draw(st.sampled_from(numeric))
    row = data.draw(st.integers(1, len(lines) - 1))
    bad = data.draw(st.sampled_from(["abc", "nan", "inf", ""]))
    cells = lines[row].split(",")
    cells[header.index(col)] = bad
    lines[row] = ",".join(cells)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "t.csv"
        path.write_text("\n".join(lines) + "\n")
        with pytest.raises(DataError) as info:
            read_targets_csv(path)
    msg = str(info.value)
    assert f"'{col}'" in msg and f"row {row + 1}" in msg


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 6), st.integers(1, 7), st.booleans(), st.integers(0, 2**31))
def test_target_set_csv_round_trip(n: int, dof: int, with_r: bool, seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = None
    if with_r:
        R = np.stack([wpr_to_matrix(*rng.uniform(-3, 3, 3)) for _ in range(n)])
        R = np.stack([wpr_to_matrix(*matrix_to_wpr(r)) for r in R])
    ts = TargetSet(p=rng.uniform(-3, 3, (n, 3)), q_seed=rng.uniform(-6, 6, (n, dof)), R=R)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "t.csv"
        ts.write_csv(path)
        back = read_targets_csv(path, dof=dof)
    np.testing.assert_allclose(back.p, ts.p, rtol=1e-15)
    np.testing.assert_allclose(back.q_seed, ts.q_seed, rtol=1e-15)
    assert back.labels == ts.labels
    if R is not None:
        assert back.R is not None
        np.testing.assert_allclose(back.R, R, atol=1e-13)


@pytest.mark.parametrize(("text", "match"), [
    ("x,y,q1\n1,2,3\n", "'z'"),
    ("x,y,z\n1,2,3\n", "no joint columns"),
    ("x,y,z,q1,q2\n1,2,3,4,5\n", "robot has 6 joints"),
    ("x,y,z,q1,q2,q3,q4,q5,q6,w,p\n" + "1," * 10 + "1\n", "'r'"),
    ("x,y,z,q1,q2,q3,q4,q5,q6,x\n" + "1," * 9 + "1\n", "twice"),
    ("x,y,z,q1,q2,q3,q4,q5,q6\n", "no data rows"),
    ("", "empty"),
    ("x,y,z,q1,q2,q3,q4,q5,q6\n1,2,3\n", "row 2 has 3 fields"),
])
def test_parser_errors(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "t.csv"
    path.write_text(text)
    with pytest.raises(DataError, match=match):
        read_targets_csv(path, dof=6)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="file not found"):
        read_targets_csv(tmp_path / "none.csv")


def test_joints_csv_leaves_failed_rows_empty(tmp_path: Path) -> None:
    q = np.radians([[10.0, 20.0], [np.nan, np.nan]])
    res = CompensationResult(
        q=q, status=np.array(["ok", "unreachable"]), residual_m=np.array([1e-8, 0.25]),
        rotation_residual_rad=np.zeros(2), iterations=np.array([2, 20]),
        q_last=np.nan_to_num(q), q_start=np.zeros((2, 2)),
        orientation_relaxed=np.zeros(2, dtype=bool), in_coverage=np.ones(2, dtype=bool))
    rows = list(csv.reader(io.StringIO(compensated_joints_csv_text(res))))
    assert rows[0] == ["q1", "q2", "status", "model_residual_mm"]
    assert [float(v) for v in rows[1][:2]] == pytest.approx([10.0, 20.0], abs=1e-9)
    assert rows[1][2:] == ["ok", "0.000010"]
    assert rows[2] == ["", "", "unreachable", "250.000000"]
    write_compensated_joints_csv(tmp_path / "j.csv", res)
    assert (tmp_path / "j.csv").read_text() == compensated_joints_csv_text(res)
    assert [p.name for p in tmp_path.iterdir()] == ["j.csv"]
    assert math.isclose(float(rows[1][0]), 10.0, abs_tol=1e-9)
