"""Benchmark: how per-point tracker sigmas (``sx, sy, sz``) should weight a fit (ADR 0032).

On the real UR10 series that carry the T-Mac's per-point standard deviations (B, C, D), fit
on a random half and report the held-out RMS of the other half for several weightings:

* ``none``: the tracker model (``use_point_sigma=False``);
* ``raw``: the reported sigmas as they are (diagonal covariance);
* ``estimated`` (the default): ``hypot(s, tau)`` with tau the model-error variance
  component estimated from the constant model's residuals;
* ``floor F``: ``hypot(s, F)`` per axis, F in micrometres (``point_sigma_floor_m``).

Run from the repository root::

    .venv/bin/python bench/bench_sigma.py [--models high-order,auto] [--seeds 0,1]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from _machine import header

from robocal._core.measurements import MeasurementSet
from robocal._core.threads import blas_threads
from robocal.identification import FitOptions, fit, load_ipa_series
from robocal.identification.datasets import ipa_series_path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "ipa-ur10-lasertracker"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--models", default="high-order")
    ap.add_argument("--series", default="B,C,D")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--floors-um", default="0,20")
    ap.add_argument("--max-poses", type=int, default=1500)
    a = ap.parse_args()
    floors = [float(f) for f in a.floors_um.split(",")]
    print(header())
    print(f"{'series':6s} {'model':10s} {'seed':>4s} {'weights':>10s} {'held-out mm':>12s}"
          f" {'all mm':>10s} {'cpu s':>6s}")
    for s in a.series.split(","):
        full = load_ipa_series(ipa_series_path(DATA, s), with_sigma=True,
                               max_poses=a.max_poses)
        assert full.sigma is not None
        print(f"# series {s}: {len(full)} poses, reported sigma median "
              f"{np.median(full.sigma) * 1e3:.4f} mm, 5-95 % "
              f"{np.percentile(full.sigma, 5) * 1e3:.4f}-"
              f"{np.percentile(full.sigma, 95) * 1e3:.4f} mm")
        for model in a.models.split(","):
            for seed in (int(x) for x in a.seeds.split(",")):
                train, val = full.split(0.5, seed=seed)
                runs: list[tuple[str, FitOptions, MeasurementSet, MeasurementSet]] = [
                    ("none", FitOptions(use_point_sigma=False), train, val),
                    ("estimated", FitOptions(), train, val)]
                for f in floors:
                    label = "raw" if f == 0 else f"floor {f:g}"
                    runs.append((label, FitOptions(point_sigma_floor_m=f * 1e-6), train, val))
                for label, opts, tr, va in runs:
                    t0 = time.process_time()
                    with blas_threads(1):
                        r = fit("ur10", tr, model, options=opts, validation=va)
                    dt = time.process_time() - t0
                    assert r.validation is not None and r.validation_all is not None
                    print(f"{s:6s} {model:10s} {seed:4d} {label:>10s} "
                          f"{r.validation.rms_m * 1e3:12.4f} "
                          f"{r.validation_all.rms_m * 1e3:10.4f} {dt:6.1f}", flush=True)


if __name__ == "__main__":
    main()
