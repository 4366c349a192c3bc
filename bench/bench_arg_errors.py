"""Whole-process time until a wrong argument is reported (issue 32, item 11).

``robocal plan --robot nosuch`` and ``robocal daemon --config nosuch.toml`` must answer in
0.3 s or less: the arguments are checked before numpy, the planner or the daemon are
imported. Runs each command ``--runs`` times (default 20) and prints the median and the
maximum wall time and the median CPU time (user + system) of the child.

    .venv/bin/python bench/bench_arg_errors.py [--runs 20]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

COMMANDS = {
    "plan --robot nosuch": ["plan", "--robot", "nosuch", "--cell", "demo", "--count", "30",
                            "--out", "plan.json"],
    "daemon --config nosuch.toml": ["daemon", "--config", "nosuch.toml"],
}


def _run(argv: list[str], cwd: str) -> tuple[float, float]:
    """(wall s, child CPU s) of one run; the command must fail with exit code 2."""
    before = os.times()
    t0 = time.perf_counter()
    out = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = os.times()
    if out.returncode != 2 or out.stderr.count("\n") != 1:
        raise SystemExit(f"unexpected result of {argv}: {out.returncode} {out.stderr!r}")
    cpu = (after.children_user - before.children_user
           + after.children_system - before.children_system)
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=20)
    args = ap.parse_args()
    exe = str(Path(sys.executable).with_name("robocal"))
    with tempfile.TemporaryDirectory() as d:
        print(f"{'command':32s} {'median':>8s} {'max':>8s} {'CPU':>8s}   (s, {args.runs} runs)")
        for name, argv in COMMANDS.items():
            _run([exe, *argv], d)  # warm the file cache
            runs = [_run([exe, *argv], d) for _ in range(args.runs)]
            walls = [w for w, _ in runs]
            cpus = [c for _, c in runs]
            print(f"{name:32s} {statistics.median(walls):8.3f} {max(walls):8.3f} "
                  f"{statistics.median(cpus):8.3f}")


if __name__ == "__main__":
    main()
