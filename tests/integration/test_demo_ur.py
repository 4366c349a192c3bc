"""``robocal demo --robot ur10``: measure, fit, push and re-measure through the UR simulator
(Dashboard, RTDE and primary interface, with the universal_robots driver)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


@pytest.mark.slow
def test_demo_ur10_pushes_installation_variables_and_measures_again(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "robocal.cli.main", "demo", "--robot", "ur10", "--poses", "80",
         "--out", str(out), "--seed", "3", "--quiet"],
        capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["robot"] == "ur10" and summary["state"] == "pushed"
    assert summary["poses_measured"] == summary["poses_total"]
    push = summary["push"]
    assert push["kind"] == "targets" and push["verification"] == "done"
    # before/after on the robot: the pushed waypoints land far closer to their targets
    assert push["measured_before_rms_mm"] > 20 * push["measured_after_rms_mm"]
    assert f"-> {push['measured_after_rms_mm']:.4f} mm RMS after" in proc.stdout
    # the daemon talked to the UR simulator, not the FANUC one
    log = (out / "daemon.log").read_text()
    assert "universal_robots" in log and "fanuc_rmi" not in log
