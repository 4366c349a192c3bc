"""Optional 6-DoF columns of the measurement CSV: rx, ry, rz (deg) and srx, sry, srz (deg)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robocal._core.measurements import MeasurementSet
from robocal.errors import DataError

HEAD = "pose_id,q1,q2,x,y,z"


def _write(tmp_path: Path, text: str) -> Path:
    f = tmp_path / "m.csv"
    f.write_text(text)
    return f


def test_orientation_columns_are_read_in_radians(tmp_path: Path) -> None:
    f = _write(tmp_path, f"{HEAD},rx,ry,rz,srx,sry,srz\nA,10,20,1,2,3,-90,45,180,0.01,0.02,0.03\n")
    m = MeasurementSet.read_csv(f)
    assert m.rot == pytest.approx(np.radians([[-90.0, 45.0, 180.0]]))
    assert m.rot_sigma == pytest.approx(np.radians([[0.01, 0.02, 0.03]]))
    assert m.subset([0]).rot is not None and m.concat(m).rot.shape == (2, 3)
    assert MeasurementSet.read_csv(_write(tmp_path, f"{HEAD}\nA,1,2,1,2,3\n")).rot is None


@pytest.mark.parametrize(
    ("extra_head", "extra_row", "words"),
    [
        (",rx,ry", ",1,2", "key 'rz': rx, ry, rz must be given together"),
        (",srx,sry,srz", ",1,1,1", "key 'rx': srx, sry, srz need rx, ry, rz"),
        (",rx,ry,rz,srx,sry,srz", ",1,2,3,0,1,1", "row 2: standard deviations must be positive"),
        (",rx,ry,rz", ",1,abc,3", "row 2: 'abc' is not a number"),
    ],
)
def test_bad_orientation_columns_give_one_clear_error(tmp_path: Path, extra_head: str,
                                                      extra_row: str, words: str) -> None:
    f = _write(tmp_path, f"{HEAD}{extra_head}\nA,1,2,1,2,3{extra_row}\n")
    with pytest.raises(DataError) as info:
        MeasurementSet.read_csv(f)
    assert words in str(info.value) and "m.csv" in str(info.value)


_ANG = st.floats(-180.0, 180.0, allow_nan=False)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(_ANG, _ANG, _ANG), min_size=1, max_size=5), st.booleans())
def test_csv_round_trip_with_orientation(rows: list[tuple[float, float, float]],
                                         with_sigma: bool) -> None:
    n = len(rows)
    rot = np.radians(np.array(rows))
    m = MeasurementSet(np.zeros((n, 2)), np.ones((n, 3)), rot=rot,
                       rot_sigma=np.full((n, 3), math.radians(0.01)) if with_sigma else None)
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "r.csv"
        m.write_csv(path)
        back = MeasurementSet.read_csv(path)
    assert back.rot is not None
    assert np.abs(back.rot - rot).max() < 1e-10           # 9 decimals of a degree
    assert (back.rot_sigma is not None) == with_sigma
