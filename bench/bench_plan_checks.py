"""Benchmark: swept-path samples evaluated and CPU time of ``plan_campaign`` (issue 28).

Counts the poses the motion checker evaluates (every call of ``MotionChecker.margins``)
while planning ``robocal plan --robot fanuc_lrmate200i --cell demo --count 250`` (auto,
validation 50, ISO), and the CPU time of the call in this process. Compare commits by
running it with ``PYTHONPATH`` pointing at another checkout's ``src``. Whole-process wall
time: ``/usr/bin/time -v .venv/bin/robocal plan ...``.

Run from the repository root::

    .venv/bin/python bench/bench_plan_checks.py [--count 250] [--robot fanuc_lrmate200i]
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
    ap.add_argument("--robot", default="fanuc_lrmate200i")
    ap.add_argument("--model", default="auto")
    args = ap.parse_args()
    print(f"cpus: {os.cpu_count()}, load average: {os.getloadavg()[0]:.2f}")
    evaluated = [0]
    margins = MotionChecker.margins

    def counted(self: MotionChecker, q: Any) -> Any:
        evaluated[0] += len(np.atleast_2d(q))
        return margins(self, q)

    MotionChecker.margins = counted  # type: ignore[method-assign]
    t0 = time.process_time()
    plan = plan_campaign(args.robot, "demo", count=args.count, validation=args.validation,
                         model=args.model)
    cpu = time.process_time() - t0
    print(f"{args.robot}, {args.count} + {args.validation} poses ({len(plan.poses)} in the "
          f"plan): {evaluated[0]:,} poses checked by the motion checker, {cpu:.2f} s CPU")


if __name__ == "__main__":
    main()
