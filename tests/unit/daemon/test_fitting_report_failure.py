"""A report that cannot be written is logged and skipped; the fit stands (structlog is
imported only on that path, see daemon.fitting)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from structlog.testing import capture_logs

from robocal._core.measurements import MeasurementSet
from robocal.daemon.fitting import _write_report
from robocal.kinematics import load_robot


def test_a_failed_report_is_logged_and_skipped(tmp_path: Path) -> None:
    robot = load_robot("fanuc_lrmate200i")
    train = MeasurementSet(np.zeros((3, robot.dof)), np.zeros((3, 3)))
    (tmp_path / "a-file").write_text("")  # the report directory cannot be made under it
    with capture_logs() as logs:
        out = _write_report({"campaign": "C1", "rows": []}, robot, {}, train, None,
                            tmp_path / "a-file" / "report")
    assert out["skipped"].startswith("report failed: ")
    assert [e["event"] for e in logs] == ["report failed"]
    assert logs[0]["log_level"] == "warning" and logs[0]["error"] == out["skipped"]
