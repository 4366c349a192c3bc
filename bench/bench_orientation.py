"""Benefit of 6-DoF (T-Mac) orientation readings on the IPA UR10 series C (not a timing bench).

Held-out position RMS of the constant model versus the number of calibration poses, with and
without the orientation residuals, and the fewest poses reaching a target RMS.

    .venv/bin/python bench/bench_orientation.py [--draws 20] [--series C]

The 1000 held-out poses are drawn once (seed 0); each training set of n poses is a random
draw (seeds 100..) from the remaining poses; the same draws are used with and without
orientation. Targets: the position-only plateau (mean RMS at the largest n) times 1.05 and
1.10.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from robocal.errors import RobocalError
from robocal.identification import fit, load_ipa_series
from robocal.identification.datasets import ipa_series_path

ROOT = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "ipa-ur10-lasertracker"
GRID = (12, 16, 20, 25, 30, 40, 50, 60, 80, 100, 150, 200, 300)


def sweep(series: str = "C", draws: int = 20, grid: tuple[int, ...] = GRID,
          n_val: int = 1000) -> dict[str, dict[int, float]]:
    """Mean held-out position RMS (mm) per pose count, keys "position" and "orientation"
    (fits that fail are left out of the mean and counted under "position-failed" etc.)."""
    data = load_ipa_series(ipa_series_path(ROOT, series), with_orientation=True)
    perm = np.random.default_rng(0).permutation(len(data))
    val = data.subset(np.sort(perm[:n_val])).without_orientation()
    pool = perm[n_val:]
    out: dict[str, dict[int, float]] = {"position": {}, "orientation": {},
                                        "position-failed": {}, "orientation-failed": {}}
    for n in grid:
        rms: dict[str, list[float]] = {"position": [], "orientation": []}
        for s in range(draws):
            tr = data.subset(np.sort(np.random.default_rng(100 + s).choice(pool, n,
                                                                           replace=False)))
            for key, d in (("position", tr.without_orientation()), ("orientation", tr)):
                try:
                    r = fit("ur10", d, "constant", validation=val).validation
                    rms[key].append(r.rms_m * 1e3)
                except RobocalError:
                    rms[key].append(math.nan)
        for key in ("position", "orientation"):
            out[key][n] = float(np.nanmean(rms[key]))
            out[f"{key}-failed"][n] = float(np.isnan(rms[key]).sum())
    return out


def needed(curve: dict[int, float], target: float) -> int | None:
    """Fewest poses on the grid whose mean RMS is at or below ``target`` (mm)."""
    return next((n for n in sorted(curve) if curve[n] <= target), None)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--series", default="C")
    args = ap.parse_args()
    res = sweep(args.series, args.draws)
    print(f"series {args.series}, {args.draws} draws, constant model, held-out position RMS mm")
    print("  poses  position-only  with-orientation  (failed fits)")
    for n in GRID:
        print(f"  {n:5d}  {res['position'][n]:13.4f}  {res['orientation'][n]:16.4f}"
              f"  ({res['position-failed'][n]:.0f}, {res['orientation-failed'][n]:.0f})")
    plateau = res["position"][max(GRID)]
    for f in (1.05, 1.10):
        a, b = needed(res["position"], f * plateau), needed(res["orientation"], f * plateau)
        ratio = "-" if a is None or b is None else f"{b / a:.0%}"
        print(f"  target {f:.2f} x plateau = {f * plateau:.4f} mm: position-only {a} poses, "
              f"with orientation {b} poses ({ratio})")
    assert math.isfinite(plateau)


if __name__ == "__main__":
    main()
