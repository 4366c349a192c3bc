"""Benchmark: the calibration report of a 250-pose campaign (acceptance: <= 5 s on 2 cores).

Simulates the paper scenario on the virtual LR Mate 200i: 250 random poses (200 calibration,
50 validation, 2 % beam-break outliers), five ISO 9283 cube poses with 30 repeats each, and
fits nominal/constant/high-order/auto with ``robocal.identification.fit`` (CPA too when
``cpa_fit`` exists; the test helpers' small Gauss-Newton fit when identification is absent).
Then times :func:`robocal.report.write_report` (analysis + 12-13 figures + HTML + JSON).

Run from the repository root::

    /work/venv/bin/python bench/bench_report.py [--repeat 3] [--out DIR] [--poses 250]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robocal._core.measurements import MeasurementSet
from robocal.kinematics import ErrorModelSpec
from robocal.report import IsoPoseSeries, MeasurementLog, ReportInput, write_report
from robocal.simulation import VirtualCell


def _fits(cell: VirtualCell, cal: MeasurementSet, val: MeasurementSet,
          rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    try:
        from robocal import identification as ident

        fit = ident.fit
    except (ImportError, AttributeError):
        fit = None
    if fit is None:
        from tests.unit.report._fitting import gn_fit

        T = cell.truth_model.T_ref
        nom = gn_fit(cell.robot, ErrorModelSpec(6, ()), T, cal, kind="nominal")
        con = gn_fit(cell.robot, ErrorModelSpec.constant(6), T, cal, x0=nom.calibrated,
                     kind="constant")
        ho = gn_fit(cell.robot, ErrorModelSpec.build(6, fourier=2), T, cal, x0=con.calibrated,
                    kind="high-order")
        return {"nominal": nom.calibrated, "constant": con, "high-order": ho,
                "auto": ho}, "test-helper Gauss-Newton"
    out: dict[str, Any] = {}
    for name in ("constant", "high-order", "auto"):
        out[name] = fit(cell.robot, cal, name, validation=val)
    cpa_fit = getattr(ident, "cpa_fit", None)
    cpa_sweeps = getattr(ident, "cpa_sweeps", None)
    if cpa_fit is not None and cpa_sweeps is not None:
        try:
            sweeps = []
            for j, q in cpa_sweeps(cell.robot):
                qc, p, s, _ = cell.simulate(q, rng)
                sweeps.append((j, MeasurementSet(qc, p, s, tuple(f"C{j + 1}-{k}"
                                                                   for k in range(len(q))))))
            out["cpa"] = cpa_fit(cell.robot, sweeps, validation=val,
                                 baseline=getattr(out["auto"], "baseline", None))
        except Exception as err:  # the benchmark is about the report; report and go on
            print(f"(CPA skipped: {type(err).__name__}: {err})")
    return out, "robocal.identification.fit"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=250)
    ap.add_argument("--repeat", type=int, default=3, help="repetitions (best and median)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", help="directory for report.html/report.json (default: a tmp dir)")
    args = ap.parse_args()

    rng = np.random.default_rng(args.seed)
    cell = VirtualCell.create("fanuc_lrmate200i", "paper", seed=args.seed)
    q = cell.random_joints(args.poses, rng)
    qc, p, s, _ = cell.simulate(q, rng, outlier_fraction=0.02)
    cal, val = MeasurementSet(qc, p, s).split(0.8, seed=args.seed)
    t0 = time.perf_counter()
    models, how = _fits(cell, cal, val, rng)
    t_fit = time.perf_counter() - t0
    iso = []
    ref = models["auto"].calibrated
    base = getattr(models["auto"], "baseline", None) or models.get("nominal")
    for k in range(5):
        qi = cell.random_joints(1, rng)
        _, pi, _, _ = cell.simulate(np.repeat(qi, 30, axis=0), rng)
        iso.append(IsoPoseSeries(f"P{k + 1}", base.predict(qi)[0], pi,
                                 predicted=ref.predict(qi)[0]))
    log = MeasurementLog(planned=args.poses, measured=args.poses, retries=3, beam_losses=1,
                         weather=[{"temperature_c": 20.4, "pressure_hpa": 1011.0,
                                   "humidity_pct": 41.0}], tracker="virtual tracker")
    inp = ReportInput(models=models, calibration=cal, validation=val, iso=iso, log=log,
                      campaign_id="bench")
    out_dir = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="robocal-report-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    walls, cpus = [], []
    for _ in range(args.repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        html_path, json_path = write_report(inp, out_dir / "report.html")
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    import json

    summ = json.loads(json_path.read_text())
    print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; fits by {how} "
          f"({t_fit:.1f} s, not timed below)")
    print(f"poses: {len(cal)} calibration + {len(val)} validation, 5 ISO poses x 30; models: "
          f"{', '.join(models)}")
    print(f"write_report: best {min(walls):.2f} s wall ({min(cpus):.2f} s CPU), median "
          f"{float(np.median(walls)):.2f} s over {args.repeat} runs  [acceptance <= 5 s]")
    t = summ.get("timing_s", {})
    print(f"  last run: analysis {t.get('analysis')} s, figures {t.get('figures')} s; "
          f"{len(summ['figures'])} figures; page {html_path.stat().st_size / 1e6:.2f} MB")
    print(f"verdict: {summ['verdict']['headline']}")
    print(f"wrote {html_path} and {json_path}")
    return 0 if min(walls) <= 5.0 else 1


if __name__ == "__main__":
    sys.exit(main())
