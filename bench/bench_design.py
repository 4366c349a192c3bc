"""Benchmark: what the pose-selection design is worth, on virtual robots (issue 18, ADR 0004).

For each seed a virtual LR Mate 200i with planted errors stands in the demo cell (tracker
where the cell says). From the same feasible candidates, ``N`` poses are chosen at random,
D-optimally and stratified (one per k-means stratum, D-optimal within strata), each for the
model named by ``--design-model``; the poses are measured (simulated noise) and fitted with
``--fit``; the fit is compared with the truth on 800 other random feasible poses. Prints the
median held-out RMS over seeds and the median ratio to random poses.

Run from the repository root (about 1 min per 3 seeds and N)::

    .venv/bin/python bench/bench_design.py --scenario paper --fit constant --n 60,120,250
    .venv/bin/python bench/bench_design.py --scenario paper --fit high-order --n 100
    .venv/bin/python bench/bench_design.py --scenario constant --fit constant --n 60
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform

import numpy as np

from robocal._core.measurements import MeasurementSet
from robocal.identification import fit
from robocal.planning import (
    FeasibilityChecker,
    cell_design_space,
    draw_candidates,
    load_cell,
    model_spec,
)
from robocal.planning._cell import Cell
from robocal.simulation import VirtualCell


def _cell_at(tracker_mm: list[float]) -> Cell:
    d = load_cell("demo").to_dict()
    d["tracker"] = {**d["tracker"], "position_mm": tracker_mm}
    return Cell.from_dict(d)


def held_out(vc: VirtualCell, q_fit: np.ndarray, q_val: np.ndarray, model: str,
             seed: int) -> float:
    """RMS (m) of the fitted model against the truth on ``q_val``."""
    q, p, s, _ = vc.simulate(q_fit, np.random.default_rng(seed))
    res = fit(vc.robot, MeasurementSet(q, p, s), model)
    e = np.linalg.norm(res.calibrated.predict(q_val) - vc.reflector_position(q_val), axis=1)
    return float(np.sqrt(np.mean(e**2)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper", help="planted errors (simulation scenario)")
    ap.add_argument("--fit", default="constant", help="model fitted to the chosen poses")
    ap.add_argument("--design-model", default=None,
                    help="model the designs are optimised for (default: the fitted model)")
    ap.add_argument("--n", default="60,120,250", help="pose counts, comma-separated")
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args()
    design_model = args.design_model or args.fit
    counts = [int(v) for v in args.n.split(",")]
    print(f"{datetime.date.today()} {platform.node()} cpus {os.cpu_count()} load "
          f"{os.getloadavg()[0]:.2f}; scenario {args.scenario}, fit {args.fit}, designs for "
          f"{design_model}, {args.seeds} seeds")
    out: dict[tuple[int, str], list[float]] = {}
    for seed in range(args.seeds):
        vc = VirtualCell.create("fanuc_lrmate200i", args.scenario, seed)
        cell = _cell_at([float(v) for v in vc.tracker_in_base * 1e3])
        checker = FeasibilityChecker(vc.robot, cell)
        q, f, _ = draw_candidates(checker, target=2048, seed=seed)
        q_val, _, _ = draw_candidates(checker, target=800, seed=seed + 1000)
        ds = cell_design_space(checker, model_spec(vc.robot, design_model), q, f)
        rng = np.random.default_rng(seed + 7)
        for n in counts:
            designs = {"random": rng.choice(len(q), n, replace=False),
                       "d-optimal": ds.select(n), "stratified": ds.select_stratified(n)}
            for name, idx in designs.items():
                out.setdefault((n, name), []).append(
                    held_out(vc, q[idx], q_val, args.fit, seed * 31 + n))
    for n in counts:
        r = np.array(out[(n, "random")])
        for name in ("random", "d-optimal", "stratified"):
            v = np.array(out[(n, name)])
            print(f"N={n:4d} {name:10s} held-out RMS median {np.median(v) * 1e6:7.1f} um, "
                  f"ratio to random: median {np.median(v / r):.3f}, "
                  f"worst seed {np.max(v / r):.3f}")


if __name__ == "__main__":
    main()
