"""Benchmark: robustness of ``auto`` to the training/validation split (issue 28).

``auto`` is fitted on random 50/50 splits of the UR10 series B and C (real data,
../shared/datasets) and scored on the other half (held-out RMS after screening, mm).
Acceptance: the worst of 20 splits <= 1.2x their median, per series. Prints each split's
figure, the chosen groups, and median / worst / ratio.

``ROBOCAL_SRC=/path/to/src`` runs another checkout's code (for before/after figures).

Run from the repository root::

    .venv/bin/python bench/bench_auto_splits.py [--series B C] [--splits 20]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

if os.environ.get("ROBOCAL_SRC"):
    sys.path.insert(0, os.environ["ROBOCAL_SRC"])

import numpy as np
from _machine import header

from robocal.identification import fit, load_ipa_series
from robocal.identification.datasets import ipa_series_path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "ipa-ur10-lasertracker"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--series", nargs="+", default=["B", "C"])
    ap.add_argument("--splits", type=int, default=20)
    ap.add_argument("--model", default="auto")
    a = ap.parse_args()
    print(header())
    if not DATA.exists():
        print(f"no data at {DATA}")
        return
    for series in a.series:
        full = load_ipa_series(ipa_series_path(DATA, series))
        rms = []
        c0 = time.process_time()
        for seed in range(a.splits):
            tr, va = full.split(0.5, seed=seed)
            r = fit("ur10", tr, a.model, validation=va)
            assert r.validation is not None
            rms.append(r.validation.rms_m * 1e3)
            groups = next((e.get("groups") for e in r.selection or []
                           if e.get("action") == "final"), None)
            print(f"{series} seed {seed:2d}: {rms[-1]:.4f} mm  {groups}", flush=True)
        med = float(np.median(rms))
        print(f"series {series}: {a.model} on {len(tr)} poses, {a.splits} splits: median "
              f"{med:.4f} mm, worst {max(rms):.4f} mm (seed {int(np.argmax(rms))}), "
              f"worst / median {max(rms) / med:.3f}; cpu {time.process_time() - c0:.0f} s",
              flush=True)


if __name__ == "__main__":
    main()
