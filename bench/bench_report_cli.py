"""Benchmark: ``robocal report`` on the demo's campaign (issue 28: report <= 2 s CPU).

Runs ``robocal demo`` once (or reuses ``--demo-dir``), then times ``robocal report
CAMPAIGN_ID --config CFG`` as a fresh process, ``--repeat`` times: CPU (user + system of the
child, imports included) and wall time, median and best. The campaign's store holds the
demo's fits, 594 measurements and its ISO poses, so this is the report an operator waits for.

Run from the repository root::

    .venv/bin/python bench/bench_report_cli.py [--repeat 5] [--demo-dir DIR]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _demo(out: Path) -> None:
    subprocess.run([sys.executable, "-m", "robocal.cli.main", "demo", "--quiet", "--out",
                    str(out)], check=True, stdout=subprocess.DEVNULL)


def _child_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--demo-dir", help="output of an earlier 'robocal demo' (default: run one)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="robocal-bench-report-") as tmp:
        demo = Path(args.demo_dir) if args.demo_dir else Path(tmp) / "demo"
        if not args.demo_dir:
            _demo(demo)
        state = demo / "state"
        (cid,) = [p.name for p in (state / "campaigns").iterdir()]
        cfg = Path(tmp) / "config.toml"
        cfg.write_text(f'data_dir = "{state}"\nrobot_description = "fanuc_lrmate200i"\n'
                       '[robot]\nkind = "fanuc_rmi"\n[tracker]\nkind = "ltp"\n')
        cpus, walls = [], []
        for _ in range(args.repeat):
            c0, w0 = _child_cpu(), time.perf_counter()
            subprocess.run([sys.executable, "-m", "robocal.cli.main", "report", cid, "--config",
                            str(cfg), "--out", str(Path(tmp) / "report.html")],
                           check=True, stdout=subprocess.DEVNULL)
            walls.append(time.perf_counter() - w0)
            cpus.append(_child_cpu() - c0)
    print(f"machine: {platform.machine()} {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load {os.getloadavg()[0]:.2f}")
    print(f"robocal report (demo campaign, fresh process): CPU median "
          f"{float(np.median(cpus)):.2f} s, best {min(cpus):.2f} s; wall median "
          f"{float(np.median(walls)):.2f} s over {args.repeat} runs  [acceptance <= 2 s CPU]")
    return 0 if float(np.median(cpus)) <= 2.0 else 1


if __name__ == "__main__":
    sys.exit(main())
