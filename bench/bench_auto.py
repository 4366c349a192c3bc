"""Benchmark: ``auto`` against ``high-order`` (CPU time) and the peak memory of ``auto``.

Issue 28's acceptance: ``auto`` <= 3x the high-order time on the UR10 series (1,386 poses of
series C, 50/50 split; real data from ../shared/datasets) and on the 250-pose ripple robot
(virtual LR Mate 200i, ``strain-wave`` scenario), with the same held-out RMS +-2 %; peak
memory of ``auto`` on 5,000 UR10 poses (series A) <= 500 MiB, measured in a fresh process
(``ru_maxrss``).

``ROBOCAL_SRC=/path/to/src`` runs another checkout's code (for before/after figures).

Run from the repository root::

    .venv/bin/python bench/bench_auto.py [--memory] [--repeat 1]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

if os.environ.get("ROBOCAL_SRC"):
    sys.path.insert(0, os.environ["ROBOCAL_SRC"])

import numpy as np
from _machine import header

from robocal._core.measurements import MeasurementSet
from robocal.identification import fit, load_ipa_series
from robocal.identification.datasets import ipa_series_path
from robocal.simulation import VirtualCell

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "ipa-ur10-lasertracker"


def _cases() -> list[tuple[str, str, MeasurementSet, MeasurementSet]]:
    out = []
    if DATA.exists():
        full = load_ipa_series(ipa_series_path(DATA, "C"))
        tr, va = full.split(0.5, seed=0)
        out.append(("UR10 series C", "ur10", tr, va))
    cell = VirtualCell.create("fanuc_lrmate200i", "strain-wave", seed=3)
    rng = np.random.default_rng(3)
    q, p, _, _ = cell.simulate(cell.random_joints(250, rng), rng)
    qv, pv, _, _ = cell.simulate(cell.random_joints(500, rng), rng)
    out.append(("ripple robot (strain-wave)", "fanuc_lrmate200i", MeasurementSet(q, p),
                MeasurementSet(qv, pv)))
    return out


def _timing(repeat: int) -> None:
    print(f"{'case':28s} {'model':10s} {'poses':>6s} {'cpu s':>7s} {'held-out mm':>12s}")
    for label, robot, tr, va in _cases():
        cpu: dict[str, float] = {}
        for model in ("constant", "high-order", "auto"):
            best = np.inf
            for _ in range(repeat):
                c0 = time.process_time()
                r = fit(robot, tr, model, validation=va)
                best = min(best, time.process_time() - c0)
            cpu[model] = best
            assert r.validation is not None
            print(f"{label:28s} {model:10s} {len(tr):6d} {best:7.2f} "
                  f"{r.validation.rms_m * 1e3:12.4f}", flush=True)
        print(f"{label:28s} auto / high-order = {cpu['auto'] / cpu['high-order']:.1f}")


def _memory_child() -> None:
    full = load_ipa_series(ipa_series_path(DATA, "A"), max_poses=5000)
    c0 = time.process_time()
    fit("ur10", full, "auto")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"auto on {len(full)} UR10 poses (series A): cpu {time.process_time() - c0:.1f} s, "
          f"peak RSS {rss:.0f} MiB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--memory", action="store_true", help="also the 5,000-pose peak memory")
    ap.add_argument("--memory-child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.memory_child:
        _memory_child()
        return
    print(header())
    _timing(a.repeat)
    if a.memory and DATA.exists():
        subprocess.run([sys.executable, __file__, "--memory-child"], check=True)


if __name__ == "__main__":
    main()
