"""Bad inputs to the offline commands: one line on stderr, exit 2, no traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from robocal.cli.main import main


@pytest.fixture(scope="module")
def meas(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--robot", "fanuc_lrmate200i", "--scenario", "constant",
                 "--poses", "40", "--seed", "2", "--out", str(d / "meas.csv")]) == 0
    return d / "meas.csv"


@pytest.fixture(scope="module")
def model(meas: Path) -> Path:
    out = meas.parent / "MODEL.json"
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model",
                 "constant", "--out", str(out)]) == 0
    return out


def _poison(src: Path, dst: Path, column: str, value: str) -> Path:
    lines = src.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[3].split(",")
    cells[header.index(column)] = value
    lines[3] = ",".join(cells)
    dst.write_text("\n".join(lines) + "\n")
    return dst


def _one_line_error(capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in err, err


@pytest.mark.parametrize(("column", "value"), [("q2", "1e300"), ("x", "1e300"),
                                               ("q1", "-4000"), ("z", "2e5")])
def test_absurd_values_in_fit_data(meas, tmp_path, capsys, column, value):
    bad = _poison(meas, tmp_path / "bad.csv", column, value)
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(bad), "--model",
                 "constant", "--out", str(tmp_path / "M.json")]) == 2
    _one_line_error(capsys, "bad.csv", "not a plausible value", f"'{column}'")


def test_absurd_values_in_report_data(meas, model, tmp_path, capsys):
    bad = _poison(meas, tmp_path / "bad.csv", "x", "1e300")
    assert main(["report", str(model), "--data", str(bad), "--out",
                 str(tmp_path / "r.html")]) == 2
    _one_line_error(capsys, "bad.csv", "plausible")


def test_fit_out_naming_a_directory(meas, tmp_path, capsys):
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model",
                 "constant", "--out", str(tmp_path)]) == 2
    _one_line_error(capsys, "is a directory")


def test_table_targets_with_absurd_coordinates(model, tmp_path, capsys):
    t = tmp_path / "targets.csv"
    t.write_text("q1,q2,q3,q4,q5,q6,x,y,z\n10,20,-10,5,30,15,1e300,200,300\n")
    assert main(["table", "--model", str(model), "--kind", "targets", "--targets", str(t),
                 "--out", str(tmp_path / "table.json")]) == 2
    _one_line_error(capsys, "targets.csv", "plausible")


def test_predict_with_absurd_joints(model, tmp_path, capsys):
    j = tmp_path / "joints.csv"
    j.write_text("q1,q2,q3,q4,q5,q6\n1e300,0,0,0,0,0\n")
    assert main(["predict", "--model", str(model), "--joints", str(j), "--out",
                 str(tmp_path / "p.csv")]) == 2
    _one_line_error(capsys, "joints.csv", "plausible")
