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


@pytest.mark.parametrize("unit", ["radians", "metres"])
def test_report_data_in_the_wrong_unit_is_refused_like_fit(meas, model, tmp_path, capsys, unit):
    """Joints written in radians or positions in metres: report refuses as fit does."""
    import numpy as np

    from robocal._core.measurements import MeasurementSet

    ms = MeasurementSet.read_csv(meas, dof=6)
    # the file's numbers are degrees of q and mm of p: write radians / metres in their place
    wrong = (MeasurementSet(np.radians(ms.q), ms.p, ms.sigma, ms.pose_id) if unit == "radians"
             else MeasurementSet(ms.q, ms.p / 1000.0, ms.sigma, ms.pose_id))
    bad = tmp_path / "bad.csv"
    wrong.write_csv(bad)
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(bad), "--model",
                 "constant", "--out", str(tmp_path / "M.json")]) == 2
    _one_line_error(capsys, unit)
    out = tmp_path / "r.html"
    assert main(["report", "--model", str(model), "--data", str(bad), "--out", str(out)]) == 2
    _one_line_error(capsys, "bad.csv", unit)
    assert not out.exists()
    assert main(["report", "--model", str(model), "--data", str(bad), "--no-sanity",
                 "--out", str(out)]) in (0, 1)
    assert out.exists()


def test_report_takes_the_model_as_an_option_or_positional(meas, model, tmp_path, capsys):
    assert main(["report", "--model", str(model), "--data", str(meas),
                 "--out", str(tmp_path / "a.html")]) in (0, 1)
    assert main(["report", str(model), "--out", str(tmp_path / "b.html")]) in (0, 1)
    capsys.readouterr()
    assert main(["report", str(model), "--model", str(model),
                 "--out", str(tmp_path / "c.html")]) == 2
    _one_line_error(capsys, "one source")


def test_a_robot_or_cell_with_absurd_lengths_is_refused_before_any_arithmetic(tmp_path, capsys):
    """a_mm = 1e300 or a tracker 1e300 mm away: the one-line error, no numpy warning first."""
    from robocal.kinematics import load_robot, robot_to_toml

    robot = tmp_path / "big.toml"
    robot.write_text(robot_to_toml(load_robot("fanuc_lrmate200i")).replace(
        "a_mm = 250.0", "a_mm = 1e300", 1))
    assert "1e300" in robot.read_text()
    assert main(["simulate", "--robot", str(robot), "--poses", "20",
                 "--out", str(tmp_path / "m.csv")]) == 2
    _one_line_error(capsys, "big.toml", "a_mm")
    cell = tmp_path / "cell.toml"
    cell.write_text('name = "big"\n[tracker]\nposition_mm = [1e300, 0.0, 500.0]\n')
    assert main(["plan", "--robot", "fanuc_lrmate200i", "--cell", str(cell), "--count", "30",
                 "--out", str(tmp_path / "p.json")]) == 2
    _one_line_error(capsys, "cell.toml", "position_mm")
    assert not (tmp_path / "m.csv").exists() and not (tmp_path / "p.json").exists()
