"""Benchmark: choose 250 poses from 20,000 candidates (acceptance: <= 10 s on 2 cores).

Times the planner's stages on the LR Mate 200i in the demo cell:

* candidates: scrambled Sobol draws, the cheap screen (limits, range, facing) and the full
  capsule checks, until 20,000 are feasible;
* design space: the weighted, column-scaled identification Jacobian of all 20,000 and the
  rank-revealing QR that removes unidentifiable columns;
* selection: greedy D-optimal (rank-3 Woodbury updates) and Fedorov exchange passes, and
  the stratified design (k-means strata, exchange within strata);
* the whole ``plan_campaign(count=250, candidates=20000)`` call (with ordering, detours and
  via-points, no CPA/ISO), which is the figure the acceptance criterion refers to.

Run from the repository root::

    /work/venv/bin/python bench/bench_planning.py [--model constant|high-order] [--n 20000]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from robocal._core.threads import blas_threads
from robocal.identification import TrackerSigma, whitening
from robocal.kinematics import load_robot
from robocal.planning import (
    DesignSpace,
    FeasibilityChecker,
    draw_candidates,
    load_cell,
    model_spec,
    plan_campaign,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="constant", choices=("constant", "high-order"))
    ap.add_argument("--n", type=int, default=20000, help="feasible candidates")
    ap.add_argument("--count", type=int, default=250, help="poses to choose")
    ap.add_argument("--robot", default="fanuc_lrmate200i")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    print(f"cpus: {os.cpu_count()}, load average: {os.getloadavg()[0]:.2f}")
    robot = load_robot(args.robot)
    cell = load_cell("demo")
    checker = FeasibilityChecker(robot, cell)
    spec = model_spec(robot, args.model)

    with blas_threads(1):
        t0 = time.perf_counter()
        q, f, counts = draw_candidates(checker, target=args.n, seed=args.seed)
        t1 = time.perf_counter()
        print(f"candidates: {counts['drawn']} drawn, {counts['screened']} screened, "
              f"{len(q)} feasible in {t1 - t0:.2f} s")
        q, f = q[:args.n], f.subset(np.arange(min(args.n, len(q))))
        W = whitening(f.reflector, TrackerSigma(position=tuple(checker.tracker)))
        t1 = time.perf_counter()
        ds = DesignSpace(robot, spec, q, np.asarray(checker.tool_offset), weights=W)
        t2 = time.perf_counter()
        print(f"design space: {len(q)} x 3 x {len(ds.names)} Jacobian, {ds.identifiable} "
              f"identifiable, {t2 - t1:.2f} s")
        sel0 = ds.select(args.count, exchange_passes=0)
        t3 = time.perf_counter()
        sel = ds.select(args.count, exchange_passes=2)
        t4 = time.perf_counter()
        rnd = np.random.default_rng(1).choice(len(q), args.count, replace=False)
        o0, o, orand = (ds.observability(s) for s in (sel0, sel, rnd))
        print(f"greedy {args.count} of {len(q)}: {t3 - t2:.2f} s  O1 {o0.O1:.4f} "
              f"cond {o0.condition_number:.1f}")
        print(f"greedy + 2 exchange passes: {t4 - t3:.2f} s  O1 {o.O1:.4f} "
              f"cond {o.condition_number:.1f}   (random: O1 {orand.O1:.4f} "
              f"cond {orand.condition_number:.1f})")
        t4b = time.perf_counter()
        strat = ds.select_stratified(args.count)
        t4c = time.perf_counter()
        os_ = ds.observability(strat)
        print(f"stratified (the default design) {args.count} of {len(q)}: {t4c - t4b:.2f} s  "
              f"O1 {os_.O1:.4f} cond {os_.condition_number:.1f}")

    t5 = time.perf_counter()
    plan = plan_campaign(robot, cell, count=args.count, model=args.model, candidates=args.n,
                         iso=False, seed=args.seed)
    t6 = time.perf_counter()
    print(f"plan_campaign(count={args.count}, candidates={args.n}, model={args.model}): "
          f"{t6 - t5:.2f} s total; {len(plan.poses)} targets "
          f"({plan.count('via')} via), moves {plan.motion.move_time_s / 60:.1f} min, "
          f"O1 {plan.observability.calibration.O1:.4f}")


if __name__ == "__main__":
    main()
