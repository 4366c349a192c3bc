"""The daemon as a real process against the protocol simulators in another process.

* kill -9 at five random points of one campaign (four while measuring, one while fitting),
  restarting each time: the campaign completes with exactly the planned measurements, none
  duplicated;
* tracker faults on 10 % of readings are survived; the TCP API refuses requests without the
  bearer token (401); malformed requests get 4xx and the daemon lives on; the CLI contract
  (``campaign start/status/list/approve/push --json``, ``compensation list``).
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from tests._waiting import eventually_sync

from robocal.daemon.client import ApiError, DaemonClient, DaemonUnavailable

PY = sys.executable
ROBOT = "fanuc_lrmate200i"


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("NOTIFY_SOCKET", None)
    env.pop("WATCHDOG_USEC", None)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def wait_for(pred: Any, timeout: float, what: str, interval: float = 0.02) -> Any:
    """Poll ``pred()`` until it returns something truthy (a daemon not answering yet counts
    as not yet); fail after ``timeout`` seconds."""

    def answered() -> Any:
        with contextlib.suppress(DaemonUnavailable, OSError, ValueError):
            return pred()
        return None

    return eventually_sync(answered, timeout, what=what, interval=interval)


def stop_process(proc: subprocess.Popen[bytes], timeout: float = 10.0) -> None:
    """SIGTERM, wait, then SIGKILL; never leaves the process behind."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)


@contextlib.contextmanager
def simulators(tmp: Path, *, fault_rate: float = 0.0, seed: int = 5,
               time_scale: float | None = None) -> Iterator[dict[str, Any]]:
    """``python -m robocal.drivers.sim all`` on free loopback ports; yields the ports JSON."""
    ports = tmp / "ports.json"
    log = (tmp / "sim.log").open("wb")
    scale = [] if time_scale is None else ["--time-scale", str(time_scale)]
    proc = subprocess.Popen(
        [PY, "-m", "robocal.drivers.sim", "all", "--robot", ROBOT, "--seed", str(seed),
         "--fault-rate", str(fault_rate), "--ports-file", str(ports), *scale],
        stdout=log, stderr=subprocess.STDOUT, env=_env())
    try:
        data = wait_for(lambda: ports.exists() and json.loads(ports.read_text()), 60,
                        "the simulators' ports file")
        yield data
    finally:
        stop_process(proc)
        log.close()


def write_config(tmp: Path, ports: dict[str, Any], *, token: str | None = None,
                 extra: str = "") -> Path:
    """A daemon configuration against the simulators (Unix socket; TCP when ``token``)."""
    api = f'socket = "{tmp / "api.sock"}"\n'
    if token is not None:
        (tmp / "token").write_text(token + "\n")
        (tmp / "token").chmod(0o600)
        api += f'tcp_port = 0\ntoken_file = "{tmp / "token"}"\n'
    text = f"""
data_dir = "{tmp / "state"}"
robot_description = "{ROBOT}"

[robot]
kind = "fanuc_rmi"
options = {{ host = "127.0.0.1", connect_port = {ports["fanuc_rmi"]["connect_port"]} }}

[tracker]
kind = "ltp"
options = {{ url = "tcp://127.0.0.1:{ports["ltp_tracker"]["port"]}", stab_ms = 50 }}

[api]
{api}
[measurement]
samples = 4
settle_s = 0.02
backoff_s = 0.01
max_backoff_s = 0.05
retries = 8

[fit]
models = ["constant"]
select = "constant"
cpa = false
report = false

[logging]
level = "info"
format = "json"
{extra}
"""
    path = tmp / "robocal.toml"
    path.write_text(text)
    return path


class Daemon:
    """One daemon process (restartable) and a client for its Unix socket."""

    def __init__(self, tmp: Path, config: Path) -> None:
        self.tmp = tmp
        self.config = config
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0
        self.client = DaemonClient(socket_path=tmp / "api.sock", timeout=10.0)

    def start(self) -> None:
        self.starts += 1
        log = (self.tmp / f"daemon-{self.starts}.log").open("wb")
        self.proc = subprocess.Popen(
            [PY, "-m", "robocal.daemon", "--config", str(self.config)],
            stdout=log, stderr=subprocess.STDOUT, env=_env())
        log.close()
        wait_for(self._healthy, 60, "the daemon to answer")

    def _healthy(self) -> bool:
        assert self.proc is not None
        if self.proc.poll() is not None:
            raise AssertionError(f"daemon exited with {self.proc.returncode}: "
                                 + self.log_tail())
        return bool(self.client.request("GET", "/health"))

    def log_tail(self, n: int = 4000) -> str:
        logs = sorted(self.tmp.glob("daemon-*.log"))
        return logs[-1].read_text(errors="replace")[-n:] if logs else ""

    def kill9(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None:
            stop_process(self.proc)

    def status(self, cid: str) -> dict[str, Any]:
        return self.client.request("GET", f"/campaigns/{cid}")

    def cli(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        out = subprocess.run([PY, "-m", "robocal.cli.main", *args], capture_output=True,
                             text=True, timeout=60, env=_env())
        if check and out.returncode != 0:
            raise AssertionError(f"robocal {' '.join(args)} -> {out.returncode}: {out.stderr}")
        return out


def small_plan(tmp: Path, *, count: int, validation: int, seed: int = 4) -> Path:
    """A real PLAN.json from the planner (demo cell, constant model)."""
    from robocal.planning import plan_campaign

    plan = plan_campaign(ROBOT, "demo", count=count, model="constant", validation=validation,
                         cpa=False, iso=False, seed=seed, candidates=256)
    path = tmp / "PLAN.json"
    plan.save(path)
    return path


def _db_counts(tmp: Path, cid: str) -> tuple[int, int]:
    """(measurements, distinct poses) read straight from the store, read-only."""
    db = sqlite3.connect(f"file:{tmp / 'state' / 'robocal.sqlite3'}?mode=ro", uri=True)
    try:
        n, distinct = db.execute(
            "SELECT COUNT(*), COUNT(DISTINCT pose_idx) FROM measurements WHERE campaign=?",
            (cid,)).fetchone()
    finally:
        db.close()
    return int(n), int(distinct)


@pytest.mark.slow
def test_kill9_at_five_random_points_loses_and_duplicates_nothing(tmp_path):
    rng = random.Random(20261121)
    with simulators(tmp_path) as ports:
        plan = small_plan(tmp_path, count=40, validation=8)
        daemon = Daemon(tmp_path, write_config(tmp_path, ports))
        daemon.start()
        try:
            out = daemon.cli("campaign", "start", "--socket", str(tmp_path / "api.sock"),
                             "--plan", str(plan))
            cid = out.stdout.strip()
            total = daemon.status(cid)["poses_total"]
            # every measured pose of the plan (the planner may drop a target it cannot reach
            # safely, so the count comes from the file, not from 40 + 8)
            doc = json.loads(plan.read_text())
            assert total == sum(1 for p in doc["poses"] if p.get("measure", True)) >= 40
            targets = sorted(rng.sample(range(2, total - 2), 4))
            kills: list[tuple[str, int]] = []
            for target in [*targets, total]:
                def reached(t: int = target) -> dict[str, Any] | None:
                    s = daemon.status(cid)
                    return s if s["poses_measured"] >= t or s["state"] != "running" else None

                s = wait_for(reached, 120, f"pose {target} of {cid}", interval=0.005)
                if target < total:
                    time.sleep(rng.uniform(0.0, 0.03))  # land somewhere inside a pose
                daemon.kill9()
                n, distinct = _db_counts(tmp_path, cid)
                assert n == distinct, "a measurement was duplicated"
                kills.append((s["state"], n))
                daemon.start()
            final = wait_for(
                lambda: (s := daemon.status(cid))["state"] in ("fitted", "faulted") and s,
                120, "the fit")
            assert final["state"] == "fitted", final["reason"] + daemon.log_tail()
            assert final["poses_measured"] == total
            assert _db_counts(tmp_path, cid) == (total, total)
            rows = daemon.client.request("GET", f"/campaigns/{cid}/measurements")
            assert sorted(r["pose_idx"] for r in rows) == sorted({r["pose_idx"] for r in rows})
            history = [t["to_state"] for t in final["transitions"]]
            assert history[-2:] == ["measured", "fitted"]
            assert len(kills) == 5 and daemon.starts == 6
            assert any(state == "running" for state, _ in kills)
        finally:
            daemon.stop()
    # no fit worker outlives its daemon, whether that was killed or stopped
    wait_for(lambda: not _processes_writing_to(tmp_path), 10, "fit workers to exit")


@pytest.mark.slow
def test_sigterm_mid_move_stops_the_robot_before_the_daemon_exits(tmp_path):
    """SIGTERM while the robot moves (simulated in real time): the daemon stops it first
    (FRC_Abort), audits ``motion.stop`` with trigger ``shutdown``, exits 0, and the
    campaign stays ``running`` to resume at the next start."""
    with simulators(tmp_path, time_scale=0.5) as ports:
        plan = small_plan(tmp_path, count=12, validation=2)
        daemon = Daemon(tmp_path, write_config(tmp_path, ports))
        daemon.start()
        try:
            out = daemon.cli("campaign", "start", "--socket", str(tmp_path / "api.sock"),
                             "--plan", str(plan))
            cid = out.stdout.strip()
            wait_for(lambda: daemon.status(cid)["poses_measured"] >= 1, 120, "a measured pose")
            time.sleep(0.03)  # the next move has started (moves take about a second here)
            assert daemon.proc is not None
            daemon.proc.send_signal(signal.SIGTERM)
            assert daemon.proc.wait(30) == 0, daemon.log_tail()
        finally:
            daemon.stop()
        db = sqlite3.connect(f"file:{tmp_path / 'state' / 'robocal.sqlite3'}?mode=ro", uri=True)
        try:
            stops = [json.loads(d) for (d,) in db.execute(
                "SELECT detail FROM audit WHERE action='motion.stop' AND campaign=?", (cid,))]
            (state,) = db.execute("SELECT state FROM campaigns WHERE id=?", (cid,)).fetchone()
        finally:
            db.close()
        assert [(s["trigger"], s["outcome"]) for s in stops] == [("shutdown", "stopped")]
        assert state == "running"
        logged = [json.loads(line) for line in daemon.log_tail(200_000).splitlines()
                  if line.startswith("{")]
        events = [e.get("event") for e in logged]
        assert "robot stopped" in events and "daemon stopped" in events
        assert events.index("robot stopped") < events.index("drivers reset")
    sim_log = (tmp_path / "sim.log").read_text(errors="replace")
    assert "rmi sim: abort" in sim_log


def _processes_writing_to(directory: Path) -> list[int]:
    """Pids whose stdout is a file under ``directory`` (the daemons' logs)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            target = os.readlink(proc / "fd" / "1")
        except OSError:
            continue
        if target.startswith(str(directory)):
            pids.append(int(proc.name))
    return pids


TOKEN = "integration-token-0123456789abcdef"


@pytest.fixture(scope="module")
def faulty_cell(tmp_path_factory):
    """Simulators with tracker faults on ~10 % of readings, and a daemon with TCP + token."""
    tmp = tmp_path_factory.mktemp("faults")
    with simulators(tmp, fault_rate=0.1, seed=9) as ports:
        daemon = Daemon(tmp, write_config(tmp, ports, token=TOKEN))
        daemon.start()
        try:
            yield daemon
        finally:
            daemon.stop()


def _url(daemon: Daemon) -> str:
    return json.loads((daemon.tmp / "state" / "api.json").read_text())["url"]


@pytest.mark.slow
def test_faults_on_ten_percent_of_readings_are_survived(faulty_cell):
    d = faulty_cell
    tmp = d.tmp
    plan = small_plan(tmp, count=40, validation=10, seed=8)
    url = _url(d)
    tcp = ["--url", url, "--token-file", str(tmp / "token")]
    out = json.loads(d.cli("campaign", "start", "--plan", str(plan), "--json", *tcp).stdout)
    cid = out["id"]
    assert out["state"] == "running" and out["poses_total"] == 50
    wait_for(lambda: d.status(cid)["state"] in ("fitted", "faulted"), 180, "the campaign")
    st = json.loads(d.cli("campaign", "status", cid, "--json", *tcp).stdout)
    assert st["state"] == "fitted", st["reason"]
    assert st["poses_total"] == st["poses_measured"] == 50
    rows = d.client.request("GET", f"/campaigns/{cid}/measurements")
    assert len(rows) == 50 == len({r["pose_idx"] for r in rows})
    assert sum(r["attempts"] - 1 for r in rows) >= 1, "no fault was injected"
    listed = json.loads(d.cli("campaign", "list", "--json", *tcp).stdout)
    assert [c["id"] for c in listed] == [cid]
    sock = ["--socket", str(tmp / "api.sock")]
    watch = d.cli("campaign", "watch", cid, "--json", *sock).stdout.splitlines()
    assert json.loads(watch[0])["state"] == "fitted"
    push = d.cli("campaign", "push", cid, *sock, check=False)
    assert push.returncode == 2 and "approve" in push.stderr
    assert json.loads(d.cli("campaign", "approve", cid, "--json", *sock).stdout)["state"] == \
        "approved"
    assert json.loads(d.cli("campaign", "push", cid, "--json", *sock).stdout)["state"] == \
        "pushed"
    comp = json.loads(d.cli("compensation", "list", "--json", *sock).stdout)
    assert comp["active"]["campaign"] == cid and comp["history"][-1]["action"] == "push"


@pytest.mark.slow
def test_tcp_api_refuses_requests_without_the_token(faulty_cell):
    import http.client
    from urllib.parse import urlsplit

    u = urlsplit(_url(faulty_cell))
    for headers in ({}, {"Authorization": "Bearer nope"}):
        conn = http.client.HTTPConnection(u.hostname, u.port, timeout=10)
        conn.request("POST", "/campaigns", body=b"{}", headers=headers)
        resp = conn.getresponse()
        body = json.loads(resp.read())
        conn.close()
        assert resp.status == 401 and body["error"]["type"] == "Unauthorized"
    bad = DaemonClient(url=_url(faulty_cell), token="wrong-token-wrong-token")
    with pytest.raises(ApiError) as info:
        bad.request("GET", "/campaigns")
    assert info.value.status == 401


@pytest.mark.slow
def test_malformed_requests_never_crash_the_daemon(faulty_cell):
    import http.client
    from urllib.parse import urlsplit

    u = urlsplit(_url(faulty_cell))
    auth = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
    cases = [("POST", "/campaigns", b"{bad json"), ("POST", "/campaigns", b'{"plan": []}'),
             ("POST", "/campaigns", b"\xff\xfe\x00"), ("POST", "/campaigns/x/approve", b"{}"),
             ("GET", "/campaigns/../../etc/passwd", None), ("PUT", "/campaigns", b"{}"),
             # malformed whatever the state (a valid "{}" succeeds once a verification
             # run has finished, which is a matter of timing)
             ("POST", "/compensation/rollback", b'{"reason": 5}'),
             ("GET", "/audit?limit=0", None),
             ("POST", "/campaigns", b'{"plan": {"format": "robocal.plan/1"}, "start": "x"}')]
    for method, path, body in cases:
        conn = http.client.HTTPConnection(u.hostname, u.port, timeout=10)
        conn.request(method, path, body=body, headers=auth)
        resp = conn.getresponse()
        payload = resp.read()
        conn.close()
        assert 400 <= resp.status < 500, (method, path, resp.status, payload[:200])
        assert "error" in json.loads(payload)
    assert faulty_cell.proc is not None and faulty_cell.proc.poll() is None
    assert faulty_cell.client.request("GET", "/health")["status"] == "ok"
