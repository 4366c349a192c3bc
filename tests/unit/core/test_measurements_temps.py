"""Optional joint-temperature columns of the measurement CSV: temp1..tempN (degC, ADR 0042)."""

from __future__ import annotations

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


def test_temperature_columns_are_read_in_degc(tmp_path: Path) -> None:
    f = _write(tmp_path, f"{HEAD},temp1,temp2\nA,10,20,1,2,3,21.5,-3.25\nB,1,2,1,2,3,30,31\n")
    m = MeasurementSet.read_csv(f)
    assert m.temps == pytest.approx(np.array([[21.5, -3.25], [30.0, 31.0]]))
    assert m.subset([1]).temps == pytest.approx(np.array([[30.0, 31.0]]))
    assert m.concat(m).temps.shape == (4, 2)
    assert m.without_orientation().temps is not None
    plain = MeasurementSet.read_csv(_write(tmp_path, f"{HEAD}\nA,1,2,1,2,3\n"))
    assert plain.temps is None
    assert plain.digest() != MeasurementSet(plain.q, plain.p, temps=[[20.0, 20.0]]).digest()


@pytest.mark.parametrize(
    ("extra_head", "extra_row", "words"),
    [
        (",temp1", ",20", "key 'temp2': temp1..temp2 must be given together"),
        (",temp2", ",20", "key 'temp1': temp1..temp2 must be given together"),
        (",temp1,temp2", ",20,warm", "row 2: 'warm' is not a number"),
        (",temp1,temp2", ",20,nan", "must be finite"),
        (",temp1,temp2", ",20,5000", "not a plausible value"),
    ],
)
def test_bad_temperature_columns_give_one_clear_error(tmp_path: Path, extra_head: str,
                                                      extra_row: str, words: str) -> None:
    f = _write(tmp_path, f"{HEAD}{extra_head}\nA,1,2,1,2,3{extra_row}\n")
    with pytest.raises(DataError) as info:
        MeasurementSet.read_csv(f)
    assert words in str(info.value) and "m.csv" in str(info.value)


_TEMP = st.floats(-50.0, 200.0, allow_nan=False)


@settings(max_examples=50, deadline=None)
@given(st.integers(1, 7).flatmap(
    lambda dof: st.lists(st.lists(_TEMP, min_size=dof, max_size=dof), min_size=1,
                         max_size=5)))
def test_csv_round_trip_with_temperatures(rows: list[list[float]]) -> None:
    temps = np.array(rows)
    n, dof = temps.shape
    m = MeasurementSet(np.zeros((n, dof)), np.ones((n, 3)), temps=temps)
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "t.csv"
        m.write_csv(path)
        back = MeasurementSet.read_csv(path)
    assert back.temps is not None and back.temps.shape == (n, dof)
    assert np.abs(back.temps - temps).max() <= 5e-7           # 6 decimals of a degree


@settings(max_examples=50, deadline=None)
@given(st.text(alphabet="0123456789.-e+xn ", max_size=8))
def test_any_temperature_cell_parses_or_is_one_data_error(cell: str) -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "m.csv"
        f.write_text(f"{HEAD},temp1,temp2\nA,1,2,1,2,3,20,{cell}\n")
        try:
            m = MeasurementSet.read_csv(f)
        except DataError as err:
            assert "temp2" in str(err)
        else:
            assert m.temps is not None and np.isfinite(m.temps).all()
            assert m.temps[0, 1] == pytest.approx(float(cell))
