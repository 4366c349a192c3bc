"""Storage faults: a full disk or an I/O error pauses the campaign with a reason that is shown
at once and saved once the store can write again; resume then completes it, nothing lost.

Two ways to fill the disk: SQLite's own ``max_page_count`` (a genuine ``SQLITE_FULL`` from the
engine, no mount needed) and the store's fault seam (an ``OperationalError`` at every write).
"""

from __future__ import annotations

import asyncio
import json
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from aiohttp.test_utils import TestClient, TestServer

from robocal.daemon.api import make_app
from robocal.daemon.service import CalibrationService
from robocal.daemon.store import Store, is_storage_fault
from robocal.errors import StorageError
from tests._waiting import eventually
from tests.unit.daemon.conftest import random_plan

DISK_FULL = "database or disk is full"


def _disk_full(where: str) -> None:
    raise sqlite3.OperationalError(DISK_FULL)


def _state_on_disk(svc: CalibrationService, cid: str) -> tuple[str, str]:
    with sqlite3.connect(svc.config.db_path) as db:
        row = db.execute("SELECT state, reason FROM campaigns WHERE id=?", (cid,)).fetchone()
    return str(row[0]), str(row[1])


def _measured_once(svc: CalibrationService, cid: str) -> list[int]:
    idx = [r.pose_idx for r in svc.store.measurements(cid)]
    assert len(idx) == len(set(idx))
    return idx


def test_storage_fault_classification():
    assert is_storage_fault(sqlite3.OperationalError(DISK_FULL))
    assert is_storage_fault(sqlite3.OperationalError("disk I/O error"))
    assert not is_storage_fault(sqlite3.OperationalError("no such table: x"))
    assert not is_storage_fault(sqlite3.IntegrityError("UNIQUE constraint failed"))


def test_store_stays_usable_after_a_real_sqlite_full(tmp_path):
    store = Store(tmp_path / "s.sqlite3").open()
    try:
        n = store.db.execute("PRAGMA page_count").fetchone()[0]
        store.db.execute(f"PRAGMA max_page_count={n}")
        with pytest.raises(StorageError, match="disk is full"):
            for i in range(10_000):
                store.audit(actor="t", action="fill", detail={"pad": "x" * 2000, "i": i})
        assert store.fault is not None and not store.db.in_transaction
        store.db.execute("PRAGMA max_page_count=1000000")
        store.audit(actor="t", action="after")
        assert store.fault is None and store.audit_log(limit=1)[0]["action"] == "after"
    finally:
        store.close()


async def test_real_disk_full_while_measuring_pauses_then_resume_completes(svc):
    cid = (await svc.create(random_plan(24, validation=4), actor="op"))["id"]
    async with TestClient(TestServer(make_app(svc))) as http:
        await eventually(lambda: len(svc.store.measured_indices(cid)) >= 5, 30)
        n = svc.store.db.execute("PRAGMA page_count").fetchone()[0]
        svc.store.db.execute(f"PRAGMA max_page_count={n}")  # the disk is full from now on
        await eventually(lambda: svc.store.campaign(cid).state == "paused", 30)
        st = await (await http.get(f"/campaigns/{cid}")).json()
        assert st["state"] == "paused" and DISK_FULL in st["reason"]
        kept = _measured_once(svc, cid)
        # the pause itself may or may not fit in the full file; every action answers (no 500)
        r = await http.post(f"/campaigns/{cid}/pause")
        assert r.status == 409
        assert (await http.get("/health")).status == 200
        # space is back: the held pause is saved by itself, then resume finishes the campaign
        svc.store.db.execute("PRAGMA max_page_count=1073741823")
        await eventually(lambda: not svc.store.pending, 10)
        state, reason = _state_on_disk(svc, cid)
        assert state == "paused" and DISK_FULL in reason
        r = await http.post(f"/campaigns/{cid}/resume")
        assert r.status == 200, await r.text()
        st = await svc.wait(cid, ["fitted"], timeout=60)
        assert st["state"] == "fitted", st["reason"]
        idx = _measured_once(svc, cid)
        assert set(kept) <= set(idx) and len(idx) == 24
        history = [t["to_state"] for t in svc.store.transitions(cid)]
        assert history == ["created", "running", "paused", "running", "measured", "fitted"]


async def test_pause_during_a_storage_fault_answers_and_is_kept(svc):
    def fail_for_operators(where: str) -> None:
        task = asyncio.current_task()
        if task is None or not task.get_name().startswith("measure-"):
            _disk_full(where)

    st = await svc.create(random_plan(30), actor="op")
    cid = st["id"]
    await eventually(lambda: len(svc.store.measured_indices(cid)) >= 3, 30)
    async with TestClient(TestServer(make_app(svc))) as http:
        svc.store.fault_hook = fail_for_operators  # the operator's write hits the full disk
        r = await http.post(f"/campaigns/{cid}/pause", json={"reason": "lunch"})
        body = await r.json()
        assert r.status == 200, body
        assert body["state"] == "paused" and "lunch" in body["reason"]
        # the robot is not driven: the runner's state check sees the pause held in memory
        await eventually(lambda: svc.health()["measuring"] is None, 30)
        assert svc.store.pending and svc.store.state(cid).value == "paused"
        assert svc.store.campaign(cid).state == svc.store.state(cid)
        svc.store.fault_hook = _disk_full  # now every write fails
        r = await http.post(f"/campaigns/{cid}/resume")
        body = await r.json()
        assert r.status == 503 and DISK_FULL in body["error"]["message"]
        health = svc.health()
        assert health["status"] == "degraded" and DISK_FULL in health["storage"]
        assert (await (await http.get(f"/campaigns/{cid}")).json())["state"] == "paused"
        kept = _measured_once(svc, cid)
        svc.store.fault_hook = None
        await eventually(lambda: not svc.store.pending, 10)
        assert _state_on_disk(svc, cid) == ("paused", "lunch")
        r = await http.post(f"/campaigns/{cid}/resume")
        assert r.status == 200
    st = await svc.wait(cid, ["fitted"], timeout=60)
    assert st["state"] == "fitted" and set(kept) <= set(_measured_once(svc, cid))
    assert st["poses_measured"] == 30


async def test_fit_that_cannot_be_saved_faults_and_resume_fits_again(svc):
    def fail_in_fits(where: str) -> None:
        task = asyncio.current_task()
        if task is not None and task.get_name().startswith("fit-"):
            _disk_full(where)

    svc.store.fault_hook = fail_in_fits
    st = await svc.create(random_plan(20), actor="op")
    cid = st["id"]
    await eventually(lambda: svc.store.campaign(cid).state == "faulted", 30)
    rec = svc.store.campaign(cid)
    assert "storage fault while saving the fit" in rec.reason and DISK_FULL in rec.reason
    assert _state_on_disk(svc, cid)[0] == "measured" and svc.store.fits(cid) == {}
    svc.store.fault_hook = None
    await eventually(lambda: not svc.store.pending, 10)
    assert _state_on_disk(svc, cid)[0] == "faulted"
    await svc.resume(cid, actor="op")
    st = await svc.wait(cid, ["fitted"], timeout=60)
    assert st["state"] == "fitted" and "constant" in st["fits"]
    assert len(_measured_once(svc, cid)) == 20


def test_a_real_full_filesystem(tmp_path):
    """A 4 MiB tmpfs (in a private mount namespace) filled while measuring."""
    repo = Path(__file__).resolve().parents[3]
    if shutil.which("unshare") is None:
        pytest.skip("unshare(1) is not installed")
    probe = subprocess.run(["unshare", "-rm", "sh", "-c",
                            f"mount -t tmpfs -o size=1m tmpfs {tmp_path}"],
                           capture_output=True, timeout=30)
    if probe.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {probe.stderr.decode().strip()}")
    run = subprocess.run(["unshare", "-rm", sys.executable, "-m",
                          "tests.unit.daemon._tmpfs_full"], cwd=repo, capture_output=True,
                         text=True, timeout=300)
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("SUMMARY ")]
    assert run.returncode == 0 and lines, run.stderr[-3000:]
    s = json.loads(lines[-1][len("SUMMARY "):])
    assert DISK_FULL in s["paused_reason"] and s["health"] == "degraded"
    assert s["state_on_disk"] == "paused"
    assert s["final_state"] == "fitted" and s["measured"] == s["distinct"] == 30
    assert set(s["measured_at_pause"]) <= set(range(30)) and s["integrity"] == "ok"


async def test_a_pause_held_by_a_full_disk_survives_a_restart_after_the_disk_is_freed(
        make_config):
    """Held in memory on the full disk, kept in place in the preallocated held-states file:
    the next daemon, on a disk with room again, finds the campaign paused, not running."""
    cfg = make_config(robot={"options": {"move_time_s": 0.005}})
    svc = CalibrationService(cfg)
    await svc.start()
    cid = (await svc.create(random_plan(60), actor="op"))["id"]
    await eventually(lambda: len(svc.store.measured_indices(cid)) >= 2, 30)
    svc.store.fault_hook = _disk_full
    await eventually(lambda: svc.store.campaign(cid).state == "paused", 30)
    assert _state_on_disk(svc, cid)[0] == "running"
    await svc.stop()  # still full: the pause is not in the database
    assert _state_on_disk(svc, cid)[0] == "running"
    again = CalibrationService(cfg)  # the disk was freed meanwhile
    await again.start()
    try:
        st = again.status(cid)
        assert st["state"] == "paused" and DISK_FULL in st["reason"], st
        assert again.health()["measuring"] is None
        await eventually(lambda: _state_on_disk(again, cid)[0] == "paused", 10)
    finally:
        await again.stop()
