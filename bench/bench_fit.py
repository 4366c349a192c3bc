"""Benchmark: identification run times (tables, not timed tests).

1. ``high-order`` fit on 250 virtual poses (acceptance: well under 1 s) and on 5,000 poses
   (a few seconds), LR Mate 200i ``paper`` scenario, whole ``fit`` call incl. baseline,
   constant model, identifiability, outlier rounds and metrics.
2. Cost of one Levenberg-Marquardt iteration (Jacobian + normal equations, 219 parameters)
   against the number of poses: linear.
3. ``auto`` with joint-angle maps on 1,386 real UR10 poses (series C, 50/50 split) incl. the
   cross-validated selection (acceptance: < 30 s); skipped when the data set is absent.
   A virtual ``fine-map`` run of the same size is timed as well.

Run from the repository root::

    /work/venv/bin/python bench/bench_fit.py [--quick]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from robocal._core.measurements import MeasurementSet
from robocal._core.threads import blas_threads
from robocal.identification import fit, load_ipa_series
from robocal.identification._models import high_order_spec
from robocal.identification._solver import Problem
from robocal.identification._weights import TrackerSigma, whitening
from robocal.kinematics import KinematicModel
from robocal.simulation import VirtualCell

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "ipa-ur10-lasertracker"


def _virtual(scenario: str, n: int, seed: int = 1, robot: str = "fanuc_lrmate200i"
             ) -> tuple[VirtualCell, MeasurementSet, MeasurementSet]:
    cell = VirtualCell.create(robot, scenario, seed=seed)
    rng = np.random.default_rng(seed)
    q, p, _, _ = cell.simulate(cell.random_joints(n, rng), rng)
    qv, pv, _, _ = cell.simulate(cell.random_joints(500, rng), rng)
    return cell, MeasurementSet(q, p), MeasurementSet(qv, pv)


def _row(label: str, n: int, secs: float, res=None) -> None:
    extra = ""
    if res is not None:
        v = res.validation
        extra = (f"  iters {res.iterations:2d}  params {res.n_free:4d}/{res.n_params:4d}  "
                 f"held-out {v.rms_m * 1e3:.4f} mm")
    print(f"{label:34s}{n:>7d}{secs:10.2f} s{extra}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the 5,000-pose and real-data runs")
    args = ap.parse_args()

    print("== whole fit() calls (virtual LR Mate 200i, 'paper' scenario)")
    print(f"{'model':34s}{'poses':>7s}{'time':>12s}")
    for n in (250,) if args.quick else (250, 5000):
        cell, tr, va = _virtual("paper", n)
        for model in ("constant", "high-order"):
            t = time.perf_counter()
            res = fit(cell.robot, tr, model, validation=va)
            _row(model, n, time.perf_counter() - t, res)

    print("\n== one LM iteration (Jacobian + whitened normal equations), high-order, 219 params")
    cell, tr, _ = _virtual("paper", 10000)
    model = KinematicModel(cell.robot, high_order_spec(cell.robot), cell.T_tracker_base)
    x = model.nominal_params()
    W = whitening(tr.p, TrackerSigma())
    prob = Problem(model, tr.q, tr.p, W)
    cols = np.arange(model.size)
    print(f"{'poses':>7s}{'time [s]':>11s}{'per 1000 poses [s]':>21s}")
    with blas_threads(1):
        for n in (1000, 2000, 5000, 10000):
            rows = np.arange(n)
            best = np.inf
            for _ in range(3):
                t = time.perf_counter()
                prob.normal_equations(x, rows, cols)
                best = min(best, time.perf_counter() - t)
            print(f"{n:7d}{best:11.3f}{best / n * 1000:21.4f}")

    print("\n== auto (CV selection of harmonics, gravity, joint-angle maps)")
    print(f"{'data':34s}{'poses':>7s}{'time':>12s}")
    cell, tr, va = _virtual("fine-map", 1386, robot="ur10")
    t = time.perf_counter()
    res = fit(cell.robot, tr, "auto", validation=va)
    _row("virtual UR10 fine-map", len(tr), time.perf_counter() - t, res)
    if not args.quick and (DATA / "Series_C").is_dir():
        data = load_ipa_series(DATA / "Series_C")
        train, val = data.split(0.5, seed=0)
        t = time.perf_counter()
        res = fit("ur10", train, "auto", validation=val)
        _row("real UR10 series C (50/50)", len(train), time.perf_counter() - t, res)
        sel = next(e for e in res.selection if e.get("action") == "final")
        print(f"  selection {sel['selection_s']:.2f} s, {sel['cv_evaluations']} CV evaluations; "
              f"terms: {', '.join(sel['groups'])}")
    elif not args.quick:
        print(f"(real data not found at {DATA})")


if __name__ == "__main__":
    main()
