"""Two daemon processes replicate to one PostgreSQL (ADR 0035); one is killed with SIGKILL
while it measures and replicates, restarted, and finishes: the fleet database then holds
exactly the rows of both stores, none lost and none twice."""

from __future__ import annotations

import json
import sqlite3
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import psycopg
import pytest
from tests._postgres import PostgresServer
from tests.integration.test_daemon_processes import Daemon, small_plan, wait_for
from tests.integration.test_fleet_store import assert_replicated

pytestmark = pytest.mark.timeout(120)


def _config(tmp: Path, url: str, serial: str) -> Path:
    text = f"""
data_dir = "{tmp / "state"}"
robot_description = "fanuc_lrmate200i"

[robot]
kind = "mock"
options = {{ robot = "fanuc_lrmate200i", move_time_s = 0.05 }}

[tracker]
kind = "mock"
options = {{ robot = "fanuc_lrmate200i" }}

[api]
socket = "{tmp / "api.sock"}"

[measurement]
samples = 2
settle_s = 0.0

[fit]
models = ["constant"]
select = "constant"
cpa = false
report = false
executor = "thread"

[logging]
format = "json"

[fleet]
url = "{url}"
robot_serial = "{serial}"
cell_name = "{tmp.name}"
batch_rows = 4
poll_s = 0.02
backoff_s = 0.05
max_backoff_s = 0.5
"""
    path = tmp / "robocal.toml"
    path.write_text(text)
    return path


def _local(tmp: Path, sql: str, *args: Any) -> Any:
    db = sqlite3.connect(f"file:{tmp / 'state' / 'robocal.sqlite3'}?mode=ro", uri=True)
    try:
        return db.execute(sql, args).fetchone()[0]
    finally:
        db.close()


def _cell_id(tmp: Path) -> str:
    return str(_local(tmp, "SELECT value FROM meta WHERE key='fleet_cell_id'"))


def test_two_daemons_one_killed_mid_replication(tmp_path: Path,
                                                postgres: PostgresServer) -> None:
    url = postgres.new_database()
    cells = []
    for name, serial in (("cell-a", "SN-A"), ("cell-b", "SN-B")):
        tmp = tmp_path / name
        tmp.mkdir()
        cells.append((tmp, Daemon(tmp, _config(tmp, url, serial))))
    try:
        with ThreadPoolExecutor(2) as pool:  # the daemons start while the plan is made
            started = [pool.submit(d.start) for _, d in cells]
            plan = json.loads(small_plan(tmp_path, count=12, validation=4).read_text())
            for f in started:
                f.result(timeout=90)
        ids = [d.client.request("POST", "/campaigns", {"plan": plan})["id"] for _, d in cells]
        (tmp_a, a), (_, b) = cells

        def measured_and_replicated() -> bool:
            state = _local(tmp_a, "SELECT state || ' ' || reason FROM campaigns")
            assert state.startswith("running"), state
            n = _local(tmp_a, "SELECT COUNT(*) FROM measurements")
            with psycopg.connect(url, connect_timeout=5) as conn:
                got = conn.execute("SELECT COUNT(*) FROM robocal_measurements WHERE "
                                   "cell_id=%s", (_cell_id(tmp_a),)).fetchone()
            return n >= 4 and got is not None and got[0] >= 2

        wait_for(measured_and_replicated, 60, "cell A measuring and replicating")
        a.kill9()
        state = _local(tmp_a, "SELECT state FROM campaigns")
        assert state == "running", "killed after the campaign: not mid-campaign"
        a.start()
        for (tmp, d), cid in zip(cells, ids, strict=True):
            wait_for(lambda d=d, cid=cid: d.status(cid)["state"] == "fitted", 60,
                     f"campaign {cid} fitted")
            wait_for(lambda tmp=tmp: _local(tmp, "SELECT COUNT(*) FROM fleet_outbox") == 0, 30,
                     "outbox drained")
        for tmp, _ in cells:
            assert_replicated(url, tmp / "state" / "robocal.sqlite3", _cell_id(tmp))
        with psycopg.connect(url, connect_timeout=5) as conn:
            rows = conn.execute("SELECT c.robot_serial, COUNT(*) FROM robocal_measurements m "
                                "JOIN robocal_cells c USING (cell_id) GROUP BY 1 ORDER BY 1"
                                ).fetchall()
        planned = sum(1 for p in plan["poses"] if p.get("measure", True))
        assert rows == [("SN-A", planned), ("SN-B", planned)]
        b.stop()
    finally:
        for _, d in cells:
            d.stop()
