"""Measurement CSV files: round trip, European format, and clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal._core.measurements import MeasurementSet, read_joints_csv, write_joints_csv
from robocal.errors import DataError


def _set(rng: np.random.Generator, n: int = 7, sigma: bool = True) -> MeasurementSet:
    return MeasurementSet(q=rng.uniform(-3, 3, (n, 6)), p=rng.uniform(-2, 2, (n, 3)),
                          sigma=rng.uniform(1e-6, 1e-4, (n, 3)) if sigma else None)


def test_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    ms = _set(rng)
    ms.write_csv(tmp_path / "m.csv")
    back = MeasurementSet.read_csv(tmp_path / "m.csv", dof=6)
    np.testing.assert_allclose(back.q, ms.q, atol=1e-10)
    np.testing.assert_allclose(back.p, ms.p, atol=1e-9)
    assert back.sigma is not None and back.pose_id == ms.pose_id


def test_semicolon_decimal_comma(tmp_path: Path) -> None:
    f = tmp_path / "eu.csv"
    f.write_text("q1;q2;x;y;z;note\n1,5;-2;1000,25;0;-3,5;hello\n")
    ms = MeasurementSet.read_csv(f)
    assert ms.dof == 2
    np.testing.assert_allclose(ms.p[0], [1.00025, 0.0, -0.0035])
    np.testing.assert_allclose(np.degrees(ms.q[0]), [1.5, -2.0])


@pytest.mark.parametrize(
    ("text", "key", "match"),
    [
        ("q1,q2,x,y\n1,2,3,4\n", "z", "missing"),
        ("q1,q2,x,y,z\n1,2,3,4,nan\n", "z", "finite"),
        ("q1,q2,x,y,z\n1,abc,3,4,5\n", "q2", "not a number"),
        ("a,b\n1,2\n", "q1", "no joint columns"),
        ("q1,q2,x,y,z,sx\n1,2,3,4,5,0.1\n", "sy", "together"),
        ("q1,q2,x,y,z,sx,sy,sz\n1,2,3,4,5,0.1,0,0.1\n", "sx", "positive"),
        ("q1,q2,x,y,z,X\n1,2,3,4,5,6\n", "x", "twice"),
    ],
)
def test_bad_files(tmp_path: Path, text: str, key: str, match: str) -> None:
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(DataError, match=match) as info:
        MeasurementSet.read_csv(f)
    assert info.value.key == key and str(f) in str(info.value)


def test_wrong_joint_count_and_empty(tmp_path: Path) -> None:
    f = tmp_path / "m.csv"
    f.write_text("q1,q2,q3,x,y,z\n1,2,3,4,5,6\n")
    with pytest.raises(DataError, match="robot has 6 joints"):
        MeasurementSet.read_csv(f, dof=6)
    f.write_text("q1,q2,x,y,z\n")
    with pytest.raises(DataError, match="no data rows"):
        MeasurementSet.read_csv(f)
    with pytest.raises(DataError, match="not found"):
        MeasurementSet.read_csv(tmp_path / "none.csv")


def test_joints_csv(tmp_path: Path, rng: np.random.Generator) -> None:
    q = rng.uniform(-3, 3, (4, 6))
    write_joints_csv(tmp_path / "j.csv", q, {"status": ["ok"] * 4})
    np.testing.assert_allclose(read_joints_csv(tmp_path / "j.csv", dof=6), q, atol=1e-10)


@settings(max_examples=150, deadline=None)
@given(st.text(alphabet=st.sampled_from(list("q1234xyzs,;.-e\n 0123456789abn")), max_size=200))
def test_arbitrary_text_gives_data_error_or_set(tmp_path_factory, text: str) -> None:  # type: ignore[no-untyped-def]
    f = tmp_path_factory.mktemp("fuzz") / "f.csv"
    f.write_text(text)
    try:
        ms = MeasurementSet.read_csv(f)
    except DataError:
        return
    assert np.all(np.isfinite(ms.q)) and np.all(np.isfinite(ms.p)) and len(ms) >= 1


def test_semicolon_file_with_many_decimal_commas(tmp_path: Path) -> None:
    f = tmp_path / "eu2.csv"
    f.write_text("q1;q2;x;y;z\n1,5;2,5;1,25;2,5;3,75\n")
    ms = MeasurementSet.read_csv(f)
    np.testing.assert_allclose(ms.p[0], [0.00125, 0.0025, 0.00375])


def test_spreadsheet_habits_are_accepted(tmp_path):
    """Upper-case headers, Excel's leading ``sep=;`` line and decimal commas."""
    path = tmp_path / "m.csv"
    path.write_text("sep=;\nPOSE_ID;Q1;Q2;X;Y;Z\nA;1,5;-2;100,25;0;3\n")
    m = MeasurementSet.read_csv(path)
    assert m.pose_id == ("A",)
    np.testing.assert_allclose(np.degrees(m.q), [[1.5, -2.0]])
    np.testing.assert_allclose(m.p * 1e3, [[100.25, 0.0, 3.0]])


def test_missing_column_lists_the_columns_found(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("q1,q2,x,y,height\n1,2,3,4,5\n")
    with pytest.raises(DataError) as info:
        MeasurementSet.read_csv(path)
    assert "columns found: q1, q2, x, y, height" in str(info.value) and "z" in str(info.value)


def test_bad_cell_is_quoted_as_written(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("q1;x;y;z\n1,5;2,0mm;3;4\n")
    with pytest.raises(DataError) as info:
        MeasurementSet.read_csv(path)
    assert "'2,0mm'" in str(info.value) and "row 2" in str(info.value)


def test_atomic_write_leaves_no_temporary_and_keeps_umask_permissions(tmp_path):
    import os
    import stat

    from robocal._core.files import atomic_write_text

    old = os.umask(0o027)
    try:
        target = tmp_path / "out.txt"
        atomic_write_text(target, "one")
        atomic_write_text(target, "two")
    finally:
        os.umask(old)
    assert target.read_text() == "two"
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
