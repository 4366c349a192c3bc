"""Benchmark: a campaign after the warm-up routine against one without, on a robot with a
planted warm-up drift (ADR 0042).

The virtual FANUC LR Mate 200i carries constant kinematic errors and a warm-up drift: joint
temperatures rise with motion on a first-order lag (time constant 10 min) and the links grow
with them, 0.1 mm in all after 30 min of motion from cold. Both campaigns measure the same
planned poses through the daemon's engine and the mock drivers (simulated time: the 30 min
run in seconds) and fit the constant model. The truth they are judged against is the robot
in production: warm, at the temperatures a long run of the campaign's own cycle of moves and
stops reaches. The figure is the RMS distance between the fitted model's prediction and that
truth over 500 random poses in the calibrated joint ranges.

Run from the repository root::

    .venv/bin/python bench/bench_thermal.py [--poses 60] [--seed 5]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from robocal.compensation import compensate
from robocal.daemon.config import parse_config
from robocal.daemon.fitting import measurement_set
from robocal.daemon.logging import configure_logging
from robocal.daemon.schemas import Measurement
from robocal.daemon.service import CalibrationService
from robocal.drivers.sim import SimWorld
from robocal.identification import FitOptions, at_temperatures, fit, thermal_shift
from robocal.kinematics import CalibratedModel
from robocal.planning import plan_campaign

sys.path.insert(0, str(Path(__file__).parent))
from _machine import header

ROBOT = "fanuc_lrmate200i"
DRIFT_MM = 0.1


def _config(data_dir: Path, seed: int, warmup: dict[str, Any] | None) -> Any:
    opts = {"robot": ROBOT, "scenario": "constant", "seed": seed, "warmup_drift_mm": DRIFT_MM}
    cfg: dict[str, Any] = {
        "data_dir": str(data_dir), "robot_description": ROBOT,
        "robot": {"kind": "mock", "options": opts},
        "tracker": {"kind": "mock", "options": opts},
        "measurement": {"settle_s": 0.0},
        "fit": {"models": ["constant"], "select": "constant", "executor": "thread",
                "report": False, "cpa": False},
    }
    if warmup is not None:
        cfg["warmup"] = warmup
    return parse_config(cfg, source="bench")


async def _campaign(plan: dict[str, Any], data_dir: Path, seed: int,
                    warmup: dict[str, Any] | None
                    ) -> tuple[CalibratedModel, list[Measurement], dict[str, Any]]:
    """Run one campaign; return the fitted model, the measurements and what the run saw."""
    svc = CalibrationService(_config(data_dir, seed, warmup))
    await svc.start()
    try:
        t0 = time.perf_counter()
        st = await svc.create(plan, actor="bench")
        st = await svc.wait(st["id"], ["fitted"], timeout=600)
        wall = time.perf_counter() - t0
        if st["state"] != "fitted":
            raise SystemExit(f"campaign ended {st['state']}: {st['reason']}")
        text = svc.store.model_json(st["id"], "constant")
        assert text is not None
        model = CalibratedModel.from_dict(json.loads(text), verify=False)
        rows = svc.store.measurements(st["id"])
        done = [e for e in svc.events._buffer if e["kind"] == "warmup" and e["phase"] == "done"]
    finally:
        await svc.stop()
    temps = np.array([r.temps_c for r in rows])
    return model, rows, {"wall_s": wall, "warmup_s": done[0]["elapsed_s"] if done else 0.0,
                   "temps_first": temps[0], "temps_last": temps[-1]}


def _production_temps(world: SimWorld, q_plan: np.ndarray, hours: float = 3.0) -> np.ndarray:
    """Joint temperatures after ``hours`` of the campaign's cycle (move, measure) of
    ``world`` (a world of its own: this heats it)."""
    w = world
    assert w.thermal is not None
    while w.thermal.time_s < hours * 3600.0:
        for q in q_plan:
            w.move(q)
            w.measure(1)
    return np.asarray(w.thermal.temps_c, dtype=float)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=60)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--settled", type=float, default=0.02,
                    help="warm-up ends below this many degC per minute")
    args = ap.parse_args()
    configure_logging(level="error", fmt="console")
    print(header())
    plan = json.loads(plan_campaign(ROBOT, "demo", count=args.poses, model="constant",
                                    validation=0, cpa=False, iso=False, seed=args.seed,
                                    candidates=512).to_json())
    q_plan = np.radians([p["joints_deg"] for p in plan["poses"]])
    world = SimWorld.create(ROBOT, "constant", args.seed, warmup_drift_mm=DRIFT_MM)
    assert world.thermal is not None
    hot = _production_temps(world, q_plan)
    rng = np.random.default_rng(args.seed + 100)
    lo, hi = q_plan.min(axis=0), q_plan.max(axis=0)
    q_test = rng.uniform(lo, hi, (500, world.dof))
    truth = world.thermal.positions(world.cell, q_test, hot)
    cold = world.thermal.positions(world.cell, q_test, np.full(world.dof, 20.0))
    print(f"planted: {DRIFT_MM} mm link growth over 30 min of motion; production temperatures "
          f"{np.round(hot, 1).tolist()} degC; cold-to-production shift at the test poses "
          f"{np.sqrt(np.mean(np.sum((truth - cold) ** 2, axis=1))) * 1e3:.4f} mm RMS")
    results = {}
    cold_rows: list[Measurement] = []
    for name, warm in (("without warm-up", None),
                       ("after warm-up", {"until_settled_c_per_min": args.settled,
                                          "max_s": 7200.0})):
        with tempfile.TemporaryDirectory() as tmp:
            model, rows, seen = asyncio.run(_campaign(plan, Path(tmp), args.seed, warm))
        cold_rows = cold_rows or rows
        err = np.linalg.norm(model.predict(q_test) - truth, axis=1) * 1e3
        results[name] = float(np.sqrt(np.mean(err**2)))
        print(f"{name:16s}: fit vs production truth {results[name]:.4f} mm RMS "
              f"({np.max(err):.4f} max) over 500 poses; {args.poses} poses measured; "
              f"warm-up {seen['warmup_s'] / 60:.1f} min simulated; joint temperatures "
              f"{np.round(seen['temps_first'], 1).tolist()} -> "
              f"{np.round(seen['temps_last'], 1).tolist()} degC; {seen['wall_s']:.1f} s wall")
    ratio = results["without warm-up"] / results["after warm-up"]
    print(f"after warm-up the fit is {ratio:.1f}x closer to the truth (acceptance: >= 2x)")
    low = FitOptions(auto_maps=False, auto_max_order=1, auto_ripple_orders=(),
                     auto_strain_wave=False, auto_gravity=False)
    res = fit(ROBOT, measurement_set(cold_rows), "auto", options=low)
    hot_q = np.broadcast_to(hot, (len(q_test), world.dof))
    pred = res.calibrated.predict(q_test) + thermal_shift(res.calibrated, q_test, hot_q)
    err = np.linalg.norm(pred - truth, axis=1) * 1e3
    note = next(e for e in res.selection if e["action"] == "thermal")
    print(f"without warm-up, auto + thermal term at the production temperatures: "
          f"{np.sqrt(np.mean(err**2)):.4f} mm RMS ({np.max(err):.4f} max); thermal term "
          f"{'taken' if note.get('selected') else 'not taken'} (CV gain "
          f"{note.get('gain_percent', 0.0):.1f} %)")
    # compensation (ADR 0054): the warm robot commanded with joints solved under the model at
    # its reference temperatures (the campaign's mean) or at the production temperatures
    q_t = q_test[:100]
    targets = truth[:100]
    reach = {}
    for name, cal in (("reference", res.calibrated),
                      ("production", at_temperatures(res.calibrated, hot))):
        sol = compensate(cal, targets, q_t)
        ok = sol.status == "ok"
        got = world.thermal.positions(world.cell, sol.q[ok], hot)
        reach[name] = np.linalg.norm(got - targets[ok], axis=1) * 1e3
    print("compensating 100 targets for the warm robot with that model: "
          + "; ".join(f"at the {k} temperatures {np.sqrt(np.mean(v**2)):.4f} mm RMS "
                      f"({np.max(v):.4f} max, {len(v)} solved)" for k, v in reach.items()))


if __name__ == "__main__":
    main()
