"""Benchmark: /health over TCP for a client with the token while 2,000 half-open connections
from 250 loopback addresses flood the daemon (issue 25, item 6).

Three processes: the daemon (mock drivers, TCP API with a token, the shipped connection
limits), an attacker and this one, which measures. The attacker binds each socket to one of
127.0.0.2..127.0.0.251 (all of 127/8 is loopback on Linux), sends part of a request head
(``GET /campaigns HTTP/1.1`` and an unfinished header) and opens a new one as soon as the
daemon cuts one, so 2,000 are always open or opening. The measuring client opens a fresh
connection for every request (the worst case: each request passes admission) and sends
``GET /health`` with the token, every 50 ms, so 300 requests span one 10 s header deadline
(when the daemon cuts the whole flood at once and it reconnects); a request that gets no
answer within 5 s counts as lost.

Run from the repository root::

    .venv/bin/python bench/bench_api_flood.py [--requests 300] [--connections 2000]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TOKEN = "bench-flood-token-0123456789abcdef"
ROBOT = "fanuc_lrmate200i"
HEAD = b"GET /campaigns HTTP/1.1\r\nHost: robocal\r\nX-Slow: "


def _raise_fd_limit() -> int:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


# --- attacker (a child process) ------------------------------------------------------------------
async def _hold(port: int, source: str, counts: dict[str, int]) -> None:
    while True:
        try:
            r, w = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))
        except OSError:
            counts["failed"] += 1
            await asyncio.sleep(0.05)
            continue
        counts["opened"] += 1
        try:
            w.write(HEAD)
            await r.read()  # returns (or raises) when the daemon cuts the connection
        except OSError:
            pass
        finally:
            w.close()
        counts["cut"] += 1


async def _attack(port: int, connections: int, addresses: int) -> None:
    counts = {"opened": 0, "cut": 0, "failed": 0}
    sources = [f"127.0.0.{2 + i % addresses}" for i in range(connections)]
    tasks = [asyncio.create_task(_hold(port, s, counts)) for s in sources]
    while counts["opened"] < connections:
        await asyncio.sleep(0.05)
    print(json.dumps({"ready": True, **counts}), flush=True)
    t0, before = time.monotonic(), dict(counts)
    while True:  # report the churn once a second until killed
        await asyncio.sleep(1.0)
        now = time.monotonic()
        rate = {k: (counts[k] - before[k]) / (now - t0) for k in counts}
        print(json.dumps({"rate": rate}), flush=True)
        t0, before = now, dict(counts)
    del tasks  # pragma: no cover


# --- measuring client ----------------------------------------------------------------------------
def _health(port: int, timeout: float = 5.0) -> float | None:
    """Seconds for one authenticated /health on a fresh connection; None if not answered."""
    t0 = time.perf_counter()
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
            s.sendall(f"GET /health HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n"
                      "Connection: close\r\n\r\n".encode())
            data = b""
            while b"\r\n" not in data:
                chunk = s.recv(4096)
                if not chunk:
                    return None
                data += chunk
    except OSError:
        return None
    if not data.startswith(b"HTTP/1.1 200"):
        return None
    return time.perf_counter() - t0


def _series(port: int, n: int, interval: float) -> tuple[list[float], int]:
    times: list[float] = []
    lost = 0
    for _ in range(n):
        t = _health(port)
        if t is None:
            lost += 1
        else:
            times.append(t)
        time.sleep(interval)
    return times, lost


def _pct(times: list[float], q: float) -> float:
    ordered = sorted(times)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] * 1e3


def _summary(name: str, times: list[float], lost: int) -> str:
    if not times:
        return f"{name}: all {lost} requests lost"
    return (f"{name}: {len(times)} served, {lost} lost; median {statistics.median(times) * 1e3:.1f}"
            f" ms, p99 {_pct(times, 0.99):.1f} ms, max {max(times) * 1e3:.1f} ms, "
            f"{sum(t > 0.1 for t in times)} over 100 ms")


def _config(tmp: Path) -> Path:
    (tmp / "token").write_text(TOKEN + "\n")
    (tmp / "token").chmod(0o600)
    path = tmp / "robocal.toml"
    path.write_text(f"""
data_dir = "{tmp / "state"}"
robot_description = "{ROBOT}"

[robot]
kind = "mock"
options = {{ robot = "{ROBOT}" }}

[tracker]
kind = "mock"
options = {{ robot = "{ROBOT}" }}

[api]
socket = "{tmp / "api.sock"}"
tcp_port = 0
token_file = "{tmp / "token"}"

[logging]
level = "warning"
""")
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=300)
    ap.add_argument("--connections", type=int, default=2000)
    ap.add_argument("--addresses", type=int, default=250)
    ap.add_argument("--interval", type=float, default=0.05,
                    help="pause between requests, s (the default spans a header deadline)")
    ap.add_argument("--attacker", type=int, metavar="PORT", help=argparse.SUPPRESS)
    args = ap.parse_args()
    limit = _raise_fd_limit()
    if args.attacker is not None:
        asyncio.run(_attack(args.attacker, args.connections, args.addresses))
        return
    if limit < args.connections + 100:
        sys.exit(f"RLIMIT_NOFILE {limit} is too small for {args.connections} connections")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("NOTIFY_SOCKET", None)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        log = (tmp / "daemon.log").open("wb")
        daemon = subprocess.Popen([sys.executable, "-m", "robocal.daemon", "--config",
                                   str(_config(tmp))], stdout=log, stderr=subprocess.STDOUT,
                                  env=env)
        attacker = None
        try:
            api = tmp / "state" / "api.json"
            deadline = time.monotonic() + 60
            while not api.exists():
                if daemon.poll() is not None or time.monotonic() > deadline:
                    sys.exit("the daemon did not start: " + (tmp / "daemon.log").read_text())
                time.sleep(0.05)
            port = int(json.loads(api.read_text())["url"].rsplit(":", 1)[1])
            quiet, quiet_lost = _series(port, args.requests, args.interval)
            print(_summary("no flood", quiet, quiet_lost))
            attacker = subprocess.Popen(
                [sys.executable, __file__, "--attacker", str(port), "--connections",
                 str(args.connections), "--addresses", str(args.addresses)],
                stdout=subprocess.PIPE, env=env, text=True)
            assert attacker.stdout is not None
            ready = json.loads(attacker.stdout.readline())
            print(f"flood: {args.connections} half-open connections from {args.addresses} "
                  f"addresses opened ({ready})")
            flood, flood_lost = _series(port, args.requests, args.interval)
            rate = json.loads(attacker.stdout.readline())["rate"]
            print(_summary("flood", flood, flood_lost))
            print(f"attacker churn (first second of the flood): {rate['opened']:.0f} "
                  f"connections opened/s, {rate['cut']:.0f} cut/s")
        finally:
            if attacker is not None:
                attacker.kill()
                attacker.wait(10)
            daemon.terminate()
            daemon.wait(20)
            log.close()


if __name__ == "__main__":
    main()
