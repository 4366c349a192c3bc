"""``robocal fit`` warns about inputs that make its figures misleading."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from robocal.cli.main import main


@pytest.fixture(scope="module")
def meas(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--scenario", "constant", "--poses", "20", "--validation", "8",
                 "--seed", "3", "--out", str(d / "meas.csv")]) == 0
    return d / "meas.csv"


def _warnings(out: str) -> list[str]:
    return [ln for ln in out.splitlines() if ln.startswith("WARNING:")]


def test_validation_file_equal_to_the_training_file_is_warned(meas, tmp_path, capsys):
    copy = tmp_path / "copy.csv"
    shutil.copyfile(meas, copy)
    for val in (meas, copy):
        assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model",
                     "constant", "--validate", str(val), "--out", str(tmp_path / "M.json")]) == 0
        w = _warnings(capsys.readouterr().out)
        assert any("same data as --data" in x and "not held-out" in x for x in w), w
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model",
                 "constant", "--validate", str(meas.with_name("meas-val.csv")),
                 "--out", str(tmp_path / "M.json")]) == 0
    assert not any("same data" in x for x in _warnings(capsys.readouterr().out))


def test_auto_fit_on_too_few_poses_is_warned(meas, tmp_path, capsys):
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model", "auto",
                 "--out", str(tmp_path / "M.json")]) == 0
    w = _warnings(capsys.readouterr().out)
    assert any("20 poses are fewer than the" in x and "auto model needs" in x for x in w), w
    # the constant model is well determined by 20 poses: no such warning
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model",
                 "constant", "--out", str(tmp_path / "M.json")]) == 0
    assert not any("poses are fewer" in x for x in _warnings(capsys.readouterr().out))
