"""Benchmark: swept-path samples evaluated and CPU time of ``plan_campaign`` (issue 28).

Counts the poses the motion checker evaluates (every call of ``MotionChecker.margins``)
while planning ``robocal plan --robot R --cell demo --count 250`` (auto, validation 50, ISO)
for the LR Mate 200i and the UR10 (a third of whose candidates no straight move from home
reaches, ADR 0057), and the CPU and wall time of the call in this process. Compare commits by
running it with ``PYTHONPATH`` pointing at another checkout's ``src``. Whole-process wall
time: ``/usr/bin/time -v .venv/bin/robocal plan ...``.

Run from the repository root::

    .venv/bin/python bench/bench_plan_checks.py [--count 250] [--robot fanuc_lrmate200i ur10]
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

import numpy as np

from robocal.planning import MotionChecker, plan_campaign


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=250)
    ap.add_argument("--validation", type=int, default=50)
    ap.add_argument("--robot", nargs="+", default=["fanuc_lrmate200i", "ur10"])
    ap.add_argument("--model", default="auto")
    args = ap.parse_args()
    print(f"cpus: {os.cpu_count()}, load average: {os.getloadavg()[0]:.2f}")
    evaluated = [0]
    margins = MotionChecker.margins

    def counted(self: MotionChecker, q: Any) -> Any:
        evaluated[0] += len(np.atleast_2d(q))
        return margins(self, q)

    MotionChecker.margins = counted  # type: ignore[method-assign]
    for robot in args.robot:
        evaluated[0] = 0
        t0, w0 = time.process_time(), time.perf_counter()
        plan = plan_campaign(robot, "demo", count=args.count, validation=args.validation,
                             model=args.model)
        cpu, wall = time.process_time() - t0, time.perf_counter() - w0
        print(f"{robot}, {args.count} + {args.validation} poses ({len(plan.poses)} in the "
              f"plan, {len(plan.dropped)} dropped): {evaluated[0]:,} poses checked by the "
              f"motion checker, {cpu:.2f} s CPU, {wall:.2f} s wall", flush=True)

if __name__ == "__main__":
    main()
