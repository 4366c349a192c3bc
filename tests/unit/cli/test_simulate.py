"""``robocal simulate`` writes measurement files that ``robocal fit`` accepts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robocal._core.measurements import MeasurementSet
from robocal.cli.main import main


def test_simulate_then_fit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    meas = tmp_path / "meas.csv"
    assert main(["simulate", "--scenario", "constant", "--poses", "120", "--validation", "30",
                 "--outliers", "0.05", "--out", str(meas)]) == 0
    out = capsys.readouterr().out
    assert "120 poses, 6 with planted glitches" in out
    cal = MeasurementSet.read_csv(meas, dof=6)
    val = MeasurementSet.read_csv(tmp_path / "meas-val.csv", dof=6)
    assert len(cal) == 120 and len(val) == 30 and cal.sigma is not None
    assert np.all(np.linalg.norm(cal.p, axis=1) > 0.5)  # metres from the tracker
    model = tmp_path / "model.json"
    assert main(["fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model",
                 "constant", "--out", str(model),
                 "--validate", str(tmp_path / "meas-val.csv")]) == 0
    assert model.exists()


def test_simulate_rejects_bad_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "--poses", "0", "--out", str(tmp_path / "m.csv")]) == 2
    assert "--poses" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "wobbly", "--out", str(tmp_path / "m.csv")]) == 2
    assert "unknown scenario" in capsys.readouterr().err
    assert not (tmp_path / "m.csv").exists()
