"""Benchmark: identification run times (tables, not timed tests).

1. ``high-order`` fit on 250 virtual poses (acceptance: well under 1 s) and on 5,000 poses
   (a few seconds), LR Mate 200i ``paper`` scenario, whole ``fit`` call incl. baseline,
   constant model, identifiability, outlier rounds and metrics.
2. Cost of one Levenberg-Marquardt iteration (Jacobian + normal equations, 219 parameters)
   against the number of poses: linear.
3. ``auto`` with joint-angle maps on 1,386 real UR10 poses (series C, 50/50 split) incl. the
   cross-validated selection (acceptance: < 30 s); skipped when the data set is absent.
   A virtual ``fine-map`` run of the same size is timed as well.

4. ``--splits N``: spread of the ``auto`` model's held-out RMS over N random 50/50 splits of
   each real UR10 series (issue 14: worst split <= 1.3x the median; B <= 0.13 mm, C <= 0.12
   mm), and the ``--reuse`` workflow (maps from series A, constants from 50 poses of B / D).
5. ``--startup``: whole-process times of ``robocal --help`` and ``robocal fit`` (hyperfine if
   installed, else repeated subprocess runs).

Run from the repository root::

    .venv/bin/python bench/bench_fit.py [--quick] [--splits 20] [--series B,C] [--startup]
"""

from __future__ import annotations

import argparse
import math
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


def splits(n_splits: int, series: str, max_a: int) -> None:
    """Held-out RMS of ``auto`` over random 50/50 splits, per series."""
    from robocal.identification.datasets import ipa_series_path

    print(f"\n== auto on real UR10 data: {n_splits} random 50/50 splits per series "
          "(held-out RMS, screened gross outliers excluded)")
    print(f"{'series':8s}{'poses':>7s}{'median':>9s}{'worst':>9s}{'best':>9s}"
          f"{'worst/median':>14s}{'const median':>14s}{'s/fit':>8s}")
    for s in series.split(","):
        data = load_ipa_series(ipa_series_path(DATA, s), max_poses=max_a if s == "A" else None)
        rms, crms, secs = [], [], []
        for seed in range(n_splits):
            train, val = data.split(0.5, seed=seed)
            t = time.perf_counter()
            res = fit("ur10", train, "auto", validation=val)
            secs.append(time.perf_counter() - t)
            assert res.validation is not None and res.constant is not None
            rms.append(res.validation.rms_m * 1e3)
            e = np.linalg.norm(res.constant.predict(val.q) - val.p, axis=1)
            crms.append(float(np.sqrt(np.mean(e**2))) * 1e3)
            print(f"  {s} split {seed:2d}: {rms[-1]:.4f} mm", flush=True)
        med = float(np.median(rms))
        print(f"{s:8s}{len(data):7d}{med:9.4f}{max(rms):9.4f}{min(rms):9.4f}"
              f"{max(rms) / med:14.2f}{float(np.median(crms)):14.4f}{np.mean(secs):8.1f}")


def reuse(n_new: int = 50, repeats: int = 10) -> None:
    """Maps of an ``auto`` fit on series A, constants refitted on ``n_new`` poses of B and D.

    The source is the physically structured ``auto`` model (maps, gravity, pitch; no
    harmonics and no fine ripple, which belong to one session), as ``tests/integration``
    uses it. Three refits per draw: the default (map gaps filled, link constants held near
    the earlier values), the strict freeze of issue 14's first version (every map knot kept,
    all constants free), and a constant fit on the same ``n_new`` poses.
    """
    from robocal.identification import FitOptions, refit_frozen
    from robocal.identification.datasets import ipa_series_path

    print(f"\n== --reuse: maps from series A (auto, no harmonics/ripple), constants from {n_new} "
          f"poses of the new series, held-out = the rest; {repeats} random draws")
    t0 = time.perf_counter()
    src = fit("ur10", load_ipa_series(ipa_series_path(DATA, "A")), "auto",
              options=FitOptions(auto_max_order=0, auto_ripple_orders=()))
    print(f"source fit on all of A: {time.perf_counter() - t0:.0f} s")
    strict = FitOptions(reuse_fill_gaps=False, reuse_link_mm=math.inf,
                        reuse_link_deg=math.inf)
    print(f"{'series':8s}{'median':>9s}{'worst':>9s}{'best':>9s}{'strict median':>15s}"
          f"{'strict worst':>14s}{'constant median':>17s}{'s/refit':>9s}")
    for s in ("B", "D"):
        data = load_ipa_series(ipa_series_path(DATA, s))
        r, f, c, secs = [], [], [], []
        for seed in range(repeats):
            rng = np.random.default_rng(seed)
            pick = np.zeros(len(data), dtype=bool)
            pick[rng.choice(len(data), n_new, replace=False)] = True
            train, val = data.subset(pick), data.subset(~pick)
            t = time.perf_counter()
            res = refit_frozen(src.calibrated, train, validation=val)
            secs.append(time.perf_counter() - t)
            old = refit_frozen(src.calibrated, train, validation=val, options=strict)
            const = fit("ur10", train, "constant", validation=val)
            assert res.validation and old.validation and const.validation
            r.append(res.validation.rms_m * 1e3)
            f.append(old.validation.rms_m * 1e3)
            c.append(const.validation.rms_m * 1e3)
            print(f"  {s} draw {seed}: {r[-1]:.4f} mm (strict {f[-1]:.4f}, constant "
                  f"{c[-1]:.4f})", flush=True)
        print(f"{s:8s}{np.median(r):9.4f}{max(r):9.4f}{min(r):9.4f}{np.median(f):15.4f}"
              f"{max(f):14.4f}{np.median(c):17.4f}{np.mean(secs):9.1f}")


def startup() -> None:
    """Whole-process start-up and fit times of the console script."""
    import shutil
    import subprocess
    import sys
    import tempfile

    exe = str(Path(sys.executable).with_name("robocal"))
    with tempfile.TemporaryDirectory() as d:
        meas = Path(d) / "m.csv"
        subprocess.run([exe, "simulate", "--robot", "fanuc_lrmate200i", "--scenario", "paper",
                        "--poses", "250", "--validation", "0", "--out", str(meas)],
                       check=True, capture_output=True)
        cmds = {"robocal --help": [exe, "--help"]}
        for model in ("constant", "high-order"):
            cmds[f"robocal fit --model {model} (250 poses)"] = [
                exe, "fit", "--robot", "fanuc_lrmate200i", "--data", str(meas), "--model",
                model, "--out", str(Path(d) / f"{model}.json")]
        print("\n== whole-process times")
        if shutil.which("hyperfine"):
            for label, cmd in cmds.items():
                out = subprocess.run(["hyperfine", "-N", "-w", "3", "-r", "20", "--style",
                                      "basic", " ".join(cmd)], capture_output=True, text=True)
                lines = [ln.strip() for ln in out.stdout.splitlines() if "Time" in ln
                         or "Range" in ln]
                print(f"{label}: " + "; ".join(lines))
            return
        for label, cmd in cmds.items():
            best = []
            for _ in range(10):
                t = time.perf_counter()
                subprocess.run(cmd, check=True, capture_output=True)
                best.append(time.perf_counter() - t)
            print(f"{label:40s} min {min(best):.3f} s  median {np.median(best):.3f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the 5,000-pose and real-data runs")
    ap.add_argument("--splits", type=int, default=0, help="random 50/50 splits per UR10 series")
    ap.add_argument("--series", default="A,B,C,D", help="series for --splits")
    ap.add_argument("--max-a", type=int, default=3000, help="poses of series A for --splits")
    ap.add_argument("--reuse", action="store_true", help="time/accuracy of map re-use only")
    ap.add_argument("--startup", action="store_true", help="whole-process times only")
    args = ap.parse_args()
    if args.startup:
        startup()
        return
    if args.splits or args.reuse:
        if not (DATA / "Series_C").is_dir():
            print(f"(real data not found at {DATA})")
            return
        with blas_threads(1):
            if args.splits:
                splits(args.splits, args.series, args.max_a)
            if args.reuse:
                reuse()
        return

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
