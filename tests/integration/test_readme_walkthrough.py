"""The README's command blocks, run verbatim: the offline walkthrough, then the daemon one.

The two set-up commands are what CI runs itself (``.ci/run`` and ``test_demo``); the
activation line is replaced by putting this interpreter's ``bin`` first on ``PATH``. Every
other ``sh`` block under "Using it" runs exactly as written, in order, in one bash process per
block, inside a scratch directory that holds a link to the checkout's ``deploy/``.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ACTIVATE = ". .venv/bin/activate"
# sim all --port 17001: ..., UR 17006/08/09/11/12, KUKA 17007, ABB 17010
SIM_PORTS = range(17001, 17013)


def _using_blocks() -> list[str]:
    text = (REPO / "README.md").read_text()
    using = text.split("## Using it", 1)[1].split("\n## ", 1)[0]
    return [b.strip() for b in re.findall(r"```sh\n(.*?)```", using, flags=re.S)]


def _port_free(port: int) -> bool:
    with socket.socket() as s:  # as the simulators bind: TIME_WAIT leftovers do not count
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _run(block: str, cwd: Path, env: dict[str, str], timeout: float
         ) -> subprocess.CompletedProcess[str]:
    proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", block], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        raise AssertionError(f"README block timed out after {timeout} s:\n{block}\n{out}"
                             ) from None
    finally:  # nothing the block started in the background outlives it
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
    return subprocess.CompletedProcess(block, proc.returncode, out, "")


def test_readme_blocks_are_activation_offline_and_daemon() -> None:
    blocks = _using_blocks()
    assert blocks[0] == ACTIVATE
    assert len(blocks) == 3
    assert "robocal fit" in blocks[1] and "robocal daemon" in blocks[2]


@pytest.mark.slow
def test_readme_walkthroughs_run_verbatim(tmp_path: Path) -> None:
    busy = [p for p in SIM_PORTS if not _port_free(p)]
    if busy:
        pytest.fail(f"the README's simulator ports {busy} are taken on this machine")
    (tmp_path / "deploy").symlink_to(REPO / "deploy")
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("ROBOCAL_CONFIG", None)
    # sim.toml keeps the cell's state (and the API socket) under ~: a short home, since a
    # Unix socket path may not exceed 107 bytes and pytest's tmp_path under xdist comes close
    home = Path(tempfile.mkdtemp(prefix="rc-home-", dir="/tmp"))
    env["HOME"] = str(home)
    _, offline, daemon = _using_blocks()

    out = _run(offline, tmp_path, env, timeout=600)
    assert out.returncode == 0, out.stdout[-4000:]
    try_dir = tmp_path / "try"
    for name in ("plan.json", "meas.csv", "meas-val.csv", "meas-targets.csv", "model.json",
                 "pred.csv", "joints.csv", "targets-table.json", "report.html", "report.json"):
        assert (try_dir / name).is_file(), name
    assert "Calibration succeeded" in out.stdout
    # a visible compensation: the nominal targets are about a millimetre from where the robot
    # goes, the compensated joints close that gap; joints.csv keeps the targets' pose_id
    nominal = re.search(r"; nominal (\d+\.\d+) mm", out.stdout)
    assert nominal is not None and float(nominal.group(1)) > 0.2, out.stdout[-3000:]
    joints = (try_dir / "joints.csv").read_text().splitlines()
    assert joints[0].startswith("pose_id,q1,") and joints[1].startswith("V0000,")

    out = _run(daemon, tmp_path, env, timeout=900)
    log = (tmp_path / "cell" / "daemon.log")
    assert out.returncode == 0, out.stdout[-4000:] + (
        log.read_text()[-3000:] if log.exists() else "")
    text = out.stdout
    assert re.search(r"held-out RMS: .*auto \d+\.\d+ mm", text), text[-3000:]
    pushed = re.search(r"pushed as push ([\w.:-]+), model auto, kind targets", text)
    assert "approved model auto" in text and pushed, text[-3000:]
    key = pushed.group(1)  # one id for the push: status, then `compensation list` after rollback
    assert f"state     pushed (push {key}: active)" in text, text[-3000:]
    assert re.search(rf"push +{key} +rolled back ", text), text[-2000:]
    report = re.search(r"  report    (\S+report\.html)", text)
    assert report, text[-3000:]
    page = Path(report.group(1)).read_text(encoding="utf-8")  # rewritten before the daemon ended
    assert f"Pushed as <b>push {key}</b>" in page and "Now: <b>rolled back " in page
    # the daemon stopped first: its shutdown stop reached the simulated controller
    assert not [ln for ln in log.read_text().splitlines()
                if "motion stop" in ln and '"failed"' in ln]
    assert (home / ".local" / "state" / "robocal-sim").is_dir()
    for port in SIM_PORTS:  # the block's own `kill` stopped the simulators and the daemon
        assert _port_free(port), f"port {port} still in use after the walkthrough"
    shutil.rmtree(home, ignore_errors=True)
