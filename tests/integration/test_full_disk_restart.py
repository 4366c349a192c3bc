"""Restart while the disk is still full (issue 25 item 3): no motion command reaches the
controller, the campaign shows the pause and its reason, and the daemon stays up serving
health and status (no exit, so no restart loop under ``Restart=on-failure``).

A campaign is killed (kill -9) while it measures; its state directory is copied onto a small
tmpfs in a private mount namespace (``unshare -rm``) that is then filled to the last byte,
and the daemon restarts there. The FANUC simulator runs in this process and records every
command the controller receives.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from tests.integration.test_daemon_processes import (
    PY,
    Daemon,
    _env,
    small_plan,
    wait_for,
    write_config,
)
from tests.integration.test_push_crash import SimThread

from robocal.daemon.client import ApiError


@pytest.fixture
def sims() -> Iterator[SimThread]:
    with SimThread() as s:
        yield s


def _recording(sims: SimThread) -> list[list[float]]:
    """Joint targets (rad) of every motion the simulated controller starts from now on."""
    sim = sims.cell.fanuc_sim
    assert sim is not None
    moves: list[list[float]] = []
    original = sim.world.start_motion

    def record(q: list[float], duration: float) -> Any:
        moves.append(list(q))
        return original(q, duration)

    sim.world.start_motion = record  # type: ignore[method-assign]
    return moves


def _can_mount_tmpfs(where: Path) -> str | None:
    if shutil.which("unshare") is None:
        return "unshare(1) is not installed"
    probe = subprocess.run(["unshare", "-rm", "sh", "-c",
                            f"mount -t tmpfs -o size=1m tmpfs {where}"],
                           capture_output=True, timeout=30)
    return None if probe.returncode == 0 else probe.stderr.decode().strip()


def _start_on_full_disk(daemon: Daemon, state: Path, snapshot: Path, out: Path) -> None:
    """The daemon in a mount namespace where ``state`` is a full 4 MiB tmpfs holding a copy
    of ``snapshot``; when it has exited (SIGTERM is passed on), the tmpfs is copied to
    ``out`` without the filler."""
    script = (f"mount -t tmpfs -o size=4m tmpfs '{state}' && cp -a '{snapshot}/.' '{state}/' "
              f"&& {{ cat /dev/zero > '{state}/filler' 2>/dev/null; true; }} "
              f"&& {{ '{PY}' -m robocal.daemon --config '{daemon.config}' & pid=$!; "
              f"trap 'kill -TERM $pid' TERM; wait $pid; wait $pid; rc=$?; "
              f"rm -f '{state}/filler'; cp -a '{state}/.' '{out}/'; exit $rc; }}")
    daemon.starts += 1
    log = (daemon.tmp / f"daemon-{daemon.starts}.log").open("wb")
    daemon.proc = subprocess.Popen(["unshare", "-rm", "sh", "-c", script], stdout=log,
                                   stderr=subprocess.STDOUT, env=_env())
    log.close()


@pytest.mark.slow
def test_restart_on_a_full_disk_moves_nothing_shows_the_pause_and_stays_up(tmp_path, sims):
    why = _can_mount_tmpfs(tmp_path)
    if why is not None:
        pytest.skip(f"cannot mount a tmpfs here: {why}")
    config = write_config(tmp_path, sims.ports)
    plan = small_plan(tmp_path, count=60, validation=8)
    daemon = Daemon(tmp_path, config)
    daemon.start()
    sock = str(tmp_path / "api.sock")
    try:
        cid = daemon.cli("campaign", "start", "--socket", sock, "--plan", str(plan)).stdout.strip()
        wait_for(lambda: daemon.status(cid)["poses_measured"] >= 2, 60, "two poses measured")
        daemon.kill9()
        state = tmp_path / "state"
        snapshot = tmp_path / "snapshot"
        shutil.copytree(state, snapshot)
        moves = _recording(sims)  # motions started

        out = tmp_path / "after-full-disk"
        out.mkdir()
        _start_on_full_disk(daemon, state, snapshot, out)
        health = wait_for(lambda: daemon._healthy() and daemon.client.request("GET", "/health"),
                          60, "the daemon on the full disk to answer")
        st = daemon.status(cid)
        assert st["state"] == "paused", (st["state"], st["reason"], daemon.log_tail())
        assert "storage fault" in st["reason"] and "nothing moved" in st["reason"]
        assert "No space left" in st["reason"] or "full" in st["reason"], st["reason"]
        assert health["status"] == "degraded" and health["storage"] != "ok"
        assert health["measuring"] is None
        # the pause happened before anything could move: the controller got no motion
        assert moves == [], moves
        # an operator's resume is refused while the disk is full; still nothing moves
        with pytest.raises(ApiError) as err:
            daemon.client.request("POST", f"/campaigns/{cid}/resume")
        assert err.value.status == 503
        assert daemon.status(cid)["state"] == "paused"
        assert moves == [], moves
        # still up: serving, never exited
        assert daemon.proc is not None and daemon.proc.poll() is None
        daemon.proc.send_signal(signal.SIGTERM)
        assert daemon.proc.wait(30) == 0, daemon.log_tail()

        # the disk is freed while the daemon is down: the pause is still a pause (kept in
        # place on the full disk), not a campaign resumed on start without an operator
        shutil.rmtree(state)
        shutil.copytree(out, state)
        daemon.start()
        st = daemon.status(cid)
        assert st["state"] == "paused" and "storage fault" in st["reason"], st["reason"]
        assert moves == [], moves
        wait_for(lambda: daemon.client.request("GET", "/health")["unsaved_states"] == {}, 30,
                 "the held pause written to the store")
        daemon.client.request("POST", f"/campaigns/{cid}/resume")  # the operator's call
        wait_for(lambda: moves, 30, "the robot moving again")
    finally:
        daemon.stop()
