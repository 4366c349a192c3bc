"""Fleet store (ADR 0035): stores replicated to a real PostgreSQL server (tests/_postgres.py).

Every check counts and compares the rows in PostgreSQL against the SQLite sources: nothing
lost, nothing twice, the newest contents of rows that change.
"""

from __future__ import annotations

import asyncio
import io
import json
import os
import signal
import sqlite3
import subprocess
import sys
from contextlib import redirect_stdout
from pathlib import Path
from typing import Any

import psycopg
import pytest
from tests._postgres import PostgresServer
from tests._waiting import eventually, eventually_sync

from robocal.cli.main import main as cli_main
from robocal.daemon.campaign import CampaignState as S
from robocal.daemon.checking import CheckLog
from robocal.daemon.config import FleetConfig
from robocal.daemon.fleet import REPLICATED, FleetReplicator, detach, install
from robocal.daemon.schemas import Measurement
from robocal.daemon.store import PoseRow, Store, now_iso

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parents[2]


def _store(path: Path) -> Store:
    path.mkdir(parents=True, exist_ok=True)
    return Store(path / "robocal.sqlite3").open()


def _campaign(store: Store, poses: int, *, push: bool = False) -> str:
    """A campaign measured, fitted and (with ``push``) approved and pushed."""
    rec = store.create_campaign(
        name="cal", robot="fanuc_lrmate200i",
        poses=[PoseRow(i, "calibration" if i % 5 else "validation", (float(i),) * 6)
               for i in range(poses)],
        plan_json=json.dumps({"poses": poses}), plan_digest="p", config_digest="c", actor="t")
    store.transition(rec.id, S.RUNNING, actor="t")
    for i in range(poses):
        store.add_measurement(rec.id, Measurement(
            pose_idx=i, purpose="calibration", q_cmd_deg=(float(i),) * 6,
            q_act_deg=(float(i),) * 6, p_mm=(1000.0 + i, 2.0, 3.0), sigma_mm=(0.01,) * 3,
            rms_mm=0.005, samples=10, attempts=1, distance_mm=None,
            weather={"temperature_C": 20.5}, measured_at=now_iso(),
            temps_c=(30.0 + 0.25 * i,) * 6))
    store.transition(rec.id, S.MEASURED, actor="t")
    store.save_fits(rec.id, {"auto": ({"validation": {"rms_mm": 0.042}}, '{"m": 1}')})
    store.transition(rec.id, S.FITTED, actor="t", selected_model="auto")
    if push:
        store.transition(rec.id, S.APPROVED, actor="op", audit=("campaign.approve", {}))
        tid = store.add_table(campaign=rec.id, origin="fit", kind="targets", checksum="c0ffee",
                              table_json="{}")
        store.record_push(action="push", table_id=tid, campaign=rec.id, actor="op",
                          checksum="c0ffee", detail={})
        store.transition(rec.id, S.PUSHED, actor="op")
    return rec.id


def _source(db_path: Path) -> dict[str, dict[str, Any]]:
    """SQLite rows of every replicated table by local id (as PostgreSQL keys them)."""
    db = sqlite3.connect(db_path)
    db.row_factory = sqlite3.Row
    out: dict[str, dict[str, Any]] = {}
    have = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    for tbl, (cols, _) in REPLICATED.items():
        if tbl in have:
            out[tbl] = {"/".join(str(r[c]) for c in cols): dict(r)
                        for r in db.execute(f"SELECT * FROM {tbl}")}
    db.close()
    return out


def _mirror(url: str, cell_id: str) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    with psycopg.connect(url, connect_timeout=10) as conn:
        for tbl in REPLICATED:
            rows = conn.execute(f"SELECT local_id, data FROM robocal_{tbl} WHERE cell_id=%s",
                                (cell_id,)).fetchall()
            assert len(rows) == len({r[0] for r in rows})
            out[tbl] = {r[0]: r[1] for r in rows}
    return out


def assert_replicated(url: str, db_path: Path, cell_id: str) -> None:
    """Same rows in PostgreSQL as in SQLite, table by table, with the same contents."""
    src, dst = _source(db_path), _mirror(url, cell_id)
    for tbl, rows in src.items():
        assert set(dst[tbl]) == set(rows), tbl
        for key, row in rows.items():
            for col in ("state", "selected_model", "action", "pose_idx", "x_mm", "to_state"):
                if col in row:
                    assert dst[tbl][key][col] == row[col], (tbl, key, col)
            if "temps" in row:  # joint temperatures (store schema 2), decoded as JSON
                assert dst[tbl][key]["temps"] == json.loads(row["temps"]), (tbl, key)


def _config(**kw: Any) -> FleetConfig:
    base = {"url": "postgresql://x@127.0.0.1/x", "robot_serial": "R-1", "backoff_s": 0.05,
            "max_backoff_s": 0.2, "poll_s": 0.02, "connect_timeout_s": 5}
    return FleetConfig(**{**base, **kw})


def _pending(rep: FleetReplicator) -> int:
    return rep.pending()


@pytest.fixture
def fleet_url(postgres: PostgresServer) -> str:
    return postgres.new_database()


async def test_two_cells_replicate_to_one_database(tmp_path: Path, fleet_url: str) -> None:
    a, b = _store(tmp_path / "a"), _store(tmp_path / "b")
    _campaign(a, 30, push=True)
    _campaign(b, 20)
    reps = [FleetReplicator(s.path, _config(url=fleet_url, robot_serial=serial,
                                            cell_name=name), robot="fanuc_lrmate200i")
            for s, serial, name in ((a, "R-A", "cell-a"), (b, "R-B", "cell-b"))]
    for rep in reps:
        rep.start()
    try:
        # written while replicating: rows the triggers add behind the first copy
        cid = _campaign(b, 10, push=True)
        a.audit(actor="op", action="note", detail={"x": 1})
        for rep in reps:
            await eventually(lambda rep=rep: _pending(rep) == 0, 20, what="outbox drained")
        await eventually(lambda: all(r.applied and r.last_error is None for r in reps), 5)
        for rep, s in zip(reps, (a, b), strict=True):
            assert_replicated(fleet_url, s.path, rep.cell_id)
        with psycopg.connect(fleet_url) as conn:
            cells = conn.execute("SELECT robot_serial, cell_name, applied_seq FROM "
                                 "robocal_cells ORDER BY robot_serial").fetchall()
            assert [c[:2] for c in cells] == [("R-A", "cell-a"), ("R-B", "cell-b")]
            state = conn.execute("SELECT data->>'state' FROM robocal_campaigns WHERE "
                                 "local_id=%s", (cid,)).fetchone()
            assert state == ("pushed",)
            total = conn.execute("SELECT COUNT(*) FROM robocal_measurements").fetchone()
            assert total == (60,)
    finally:
        for rep in reps:
            await rep.stop()
        a.close()
        b.close()


_CHILD = """
import asyncio, sys
from pathlib import Path
from robocal.daemon.config import FleetConfig
from robocal.daemon.fleet import FleetReplicator
cfg = FleetConfig(url=sys.argv[2], robot_serial="R-K", batch_rows=3, poll_s=0.02,
                  backoff_s=0.05, max_backoff_s=0.2)
asyncio.run(FleetReplicator(Path(sys.argv[1]), cfg, robot="ur10").run())
"""


def _applied(url: str) -> int:
    with psycopg.connect(url, connect_timeout=5) as conn, conn.cursor() as cur:
        have = cur.execute("SELECT to_regclass('robocal_cells')").fetchone()
        if have is None or have[0] is None:
            return 0
        row = cur.execute("SELECT max(applied_seq) FROM robocal_cells").fetchone()
    return int(row[0] or 0) if row else 0


async def test_kill_9_mid_replication_loses_and_duplicates_nothing(
        tmp_path: Path, fleet_url: str) -> None:
    store = _store(tmp_path / "k")
    _campaign(store, 80, push=True)
    cell_id = install(store.path)
    total = FleetReplicator(store.path, _config(url=fleet_url), robot="ur10").pending()
    assert total > 90
    kills = 0
    for threshold in (10, 40):  # two kills at different points of the copy
        child = subprocess.Popen([sys.executable, "-c", _CHILD, str(store.path), fleet_url],
                                 cwd=REPO, stderr=subprocess.DEVNULL,
                                 stdout=subprocess.DEVNULL)
        try:
            eventually_sync(lambda t=threshold: _applied(fleet_url) >= t, 20,
                            what=f"replicated {threshold} entries")
            os.kill(child.pid, signal.SIGKILL)
            kills += 1
        finally:
            child.kill()
            child.wait(timeout=10)
        store.audit(actor="op", action="between kills")  # a write while nobody replicates
    applied = _applied(fleet_url)
    assert kills == 2 and applied < total, "killed after the whole copy: not mid-replication"
    rep = FleetReplicator(store.path, _config(url=fleet_url, robot_serial="R-K"), robot="ur10")
    rep.start()
    try:
        await eventually(lambda: rep.pending() == 0, 20, what="outbox drained")
        assert rep.cell_id == cell_id
        assert_replicated(fleet_url, store.path, cell_id)
    finally:
        await rep.stop()
        store.close()


def _terminate(url: str, kill: bool = False) -> int:
    """End the replicator's server process (SIGTERM, or SIGKILL with ``kill``)."""
    with psycopg.connect(url, connect_timeout=5, autocommit=True) as conn:
        pids = [r[0] for r in conn.execute("SELECT pid FROM pg_stat_activity WHERE "
                                           "application_name='robocal-fleet'")]
        for pid in pids:
            if kill:
                os.kill(pid, signal.SIGKILL)
            else:
                conn.execute("SELECT pg_terminate_backend(%s)", (pid,))
    return len(pids)


async def test_connection_cut_killed_and_server_restart(tmp_path: Path, postgres: PostgresServer,
                                                 fleet_url: str) -> None:
    store = _store(tmp_path / "n")
    _campaign(store, 40)
    rep = FleetReplicator(store.path, _config(url=fleet_url, batch_rows=4), robot="ur10")
    rep.start()
    try:
        await eventually(lambda: _applied(fleet_url) > 0, 20, what="replication started")
        for cut in range(3):  # rows are waiting each time the server drops the connection
            _campaign(store, 3)
            # the backend terminated, then killed with SIGKILL (the server resets every
            # connection and recovers), then terminated again
            assert await asyncio.to_thread(_terminate, fleet_url, cut == 1) == 1
            await eventually(lambda cut=cut: rep.sessions >= cut + 2, 10, what="reconnected")
        await asyncio.to_thread(postgres.stop, "immediate")  # the server goes away entirely
        cid = _campaign(store, 5)  # the cell keeps working meanwhile
        await eventually(lambda: rep.last_error is not None, 10, what="error noticed")
        await asyncio.to_thread(postgres.start)
        await eventually(lambda: rep.pending() == 0 and rep.last_error is None, 20,
                         what="replication resumed")
        assert_replicated(fleet_url, store.path, rep.cell_id)
        assert cid in _mirror(fleet_url, rep.cell_id)["campaigns"]
    finally:
        await rep.stop()
        store.close()
        if not postgres.running:  # the next tests share the server
            await asyncio.to_thread(postgres.start)


async def test_report_lists_robots_by_serial(tmp_path: Path, fleet_url: str) -> None:
    a, b = _store(tmp_path / "a"), _store(tmp_path / "b")
    pushed = _campaign(a, 10, push=True)
    _campaign(b, 10)
    # a store with drift checks (robocal check): two judged, one still measuring
    checks = CheckLog(b)
    checks.ensure_schema()
    for rms, verdict, rec in ((0.04, "pass", "none"), (0.09, "warn", "reuse"), (None, "", "")):
        k = checks.add(campaign="c", actor="timer", model_campaign="m", model="auto")
        if verdict:
            checks.finish(k, state="done", verdict=verdict, rms_mm=rms, max_mm=rms, n=20,
                          recommendation=rec, detail={"reasons": []})
    reps = [FleetReplicator(s.path, _config(url=fleet_url, robot_serial=sn), robot="ur10")
            for s, sn in ((a, "SN-100"), (b, "SN-200"))]
    for rep in reps:
        rep.start()
    try:
        for rep in reps:
            await eventually(lambda rep=rep: rep.pending() == 0, 20, what="drained")
        out = io.StringIO()
        with redirect_stdout(out):
            code = await asyncio.to_thread(cli_main, ["fleet", "report", "--url", fleet_url])
        text = out.getvalue()
        assert code == 0, text
        first, second = text.index("SN-100"), text.index("SN-200")
        section_a, section_b = text[first:second], text[second:]
        assert pushed in section_a and "0.0420" in section_a
        assert "no checks yet" in section_a and "table 1 (targets" in section_a
        assert "warn" in section_b and "recommendation: reuse" in section_b
        assert "drift trend (RMS mm, oldest first): 0.0400 -> 0.0900\n" in section_b
        assert "active compensation: none" in section_b
        out = io.StringIO()
        with redirect_stdout(out):
            await asyncio.to_thread(cli_main, ["fleet", "report", "--url", fleet_url,
                                               "--json"])
        robots = json.loads(out.getvalue())
        assert [r["robot_serial"] for r in robots] == ["SN-100", "SN-200"]
        assert robots[0]["last_calibration"]["campaign"] == pushed
    finally:
        for rep in reps:
            await rep.stop()
        a.close()
        b.close()


def test_off_removes_the_triggers(tmp_path: Path) -> None:
    store = _store(tmp_path / "o")
    install(store.path)
    _campaign(store, 3)
    assert detach(store.path)
    db = sqlite3.connect(store.path)
    assert db.execute("SELECT COUNT(*) FROM fleet_outbox").fetchone() == (0,)
    seq = db.execute("SELECT seq FROM sqlite_sequence WHERE name='fleet_outbox'").fetchone()
    db.close()
    _campaign(store, 3)  # no trigger: nothing enqueued
    db = sqlite3.connect(store.path)
    assert db.execute("SELECT COUNT(*) FROM fleet_outbox").fetchone() == (0,)
    db.close()
    install(store.path)  # on again: everything is enqueued, numbered after the old entries
    db = sqlite3.connect(store.path)
    first = db.execute("SELECT MIN(seq), COUNT(*) FROM fleet_outbox").fetchone()
    db.close()
    assert first[0] > seq[0]
    assert first[1] == sum(len(rows) for rows in _source(store.path).values())
    store.close()


async def test_a_crash_after_the_commit_skips_only_what_was_applied(
        tmp_path: Path, fleet_url: str) -> None:
    """The state a kill -9 leaves between the PostgreSQL commit and the outbox delete (a
    copy of the store taken before the copy to PostgreSQL): the applied entries are skipped,
    a newer change of the same row is not."""
    store = _store(tmp_path / "c")
    rec = store.create_campaign(name="c", robot="ur10", poses=[PoseRow(0, "calibration",
                                (0.0,) * 6)], plan_json="{}", plan_digest="p",
                                config_digest="c", actor="t")
    install(store.path)
    crashed = tmp_path / "crashed.sqlite3"
    with sqlite3.connect(crashed) as dst:
        store.db.backup(dst)
    dst.close()
    rep = FleetReplicator(store.path, _config(url=fleet_url), robot="ur10")
    rep.start()
    try:
        await eventually(lambda: rep.pending() == 0, 20, what="outbox drained")
    finally:
        await rep.stop()
        store.close()
    after = Store(crashed).open()  # the crashed cell restarts; the campaign moves on
    after.transition(rec.id, S.RUNNING, actor="t")
    after.close()
    rep = FleetReplicator(crashed, _config(url=fleet_url), robot="ur10")
    rep.start()
    try:
        await eventually(lambda: rep.pending() == 0, 20, what="outbox drained")
        assert_replicated(fleet_url, crashed, rep.cell_id)
        assert _mirror(fleet_url, rep.cell_id)["campaigns"][rec.id]["state"] == "running"
    finally:
        await rep.stop()


async def test_a_store_restored_from_an_older_copy_becomes_a_new_cell(
        tmp_path: Path, fleet_url: str) -> None:
    """Rows a restored store writes reuse local ids the fleet holds from the lost store: the
    restored store is replicated whole under a new cell id, the old cell stays as it was."""
    store = _store(tmp_path / "r")
    old_id = install(store.path)
    backup = tmp_path / "backup.sqlite3"
    with sqlite3.connect(backup) as dst:
        store.db.backup(dst)
    dst.close()
    _campaign(store, 20)  # written after the backup, replicated, then the disk dies
    rep = FleetReplicator(store.path, _config(url=fleet_url), robot="ur10")
    rep.start()
    try:
        await eventually(lambda: rep.pending() == 0, 20, what="outbox drained")
    finally:
        await rep.stop()
        store.close()
    lost = _mirror(fleet_url, old_id)
    restored = Store(backup).open()
    _campaign(restored, 3)  # measurement ids 1..3 again, other contents
    restored.close()
    rep = FleetReplicator(backup, _config(url=fleet_url), robot="ur10")
    rep.start()
    try:
        await eventually(lambda: rep.pending() == 0 and rep.cell_id != old_id, 20,
                         what="restored store replicated")
        assert_replicated(fleet_url, backup, rep.cell_id)
        assert _mirror(fleet_url, old_id) == lost
    finally:
        await rep.stop()
