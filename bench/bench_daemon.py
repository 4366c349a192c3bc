"""Benchmark: the daemon's per-pose overhead and the demo's wall time.

Runs the same poses twice against the in-process FANUC RMI and LTP/1 simulators (instant
simulated motion, no faults): once with bare driver calls (move, read joints, measure), once
through the daemon's campaign engine (limit check, validation against the aligned nominal
prediction, one SQLite transaction per pose (``synchronous=NORMAL`` since ADR 0036),
events). The difference is the daemon's overhead per pose. Also times the store's commits
alone, and optionally
``robocal demo``.

Run from the repository root::

    .venv/bin/python bench/bench_daemon.py [--poses 200] [--rounds 5] [--demo]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from robocal.daemon._plan import parse_plan, plan_from_poses
from robocal.daemon.config import parse_config
from robocal.daemon.logging import configure_logging
from robocal.daemon.schemas import Measurement
from robocal.daemon.service import CalibrationService
from robocal.daemon.store import PoseRow, Store, now_iso
from robocal.drivers import load_robot_driver, load_tracker_driver
from robocal.drivers.sim import FanucSimOptions, LtpSimOptions, SimCell
from robocal.kinematics import load_robot as load_description

ROBOT = "fanuc_lrmate200i"


def _poses(n: int, seed: int = 0) -> np.ndarray:
    robot = load_description(ROBOT)
    lim = robot.joint_limits
    return np.random.default_rng(seed).uniform(lim[:, 0] + 0.2, lim[:, 1] - 0.2, (n, robot.dof))


async def _bare(cell: SimCell, q: np.ndarray, samples: int) -> tuple[float, float]:
    """Median wall and CPU seconds per pose (CPU: this process, simulators included)."""
    robot = load_robot_driver("fanuc_rmi", cell.robot_options("fanuc_rmi"))
    tracker = load_tracker_driver("ltp", {**cell.tracker_options("tcp"), "stab_ms": 100})
    await robot.connect(timeout=10)
    await tracker.connect(timeout=10)
    try:
        times, cpu = [], []
        for row in q:
            t0, c0 = time.perf_counter(), time.process_time()
            await robot.move_to(list(row), speed_pct=100.0, timeout=30)
            await robot.read_joints()
            await tracker.measure(samples=samples, timeout=10)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    finally:
        await robot.close()
        await tracker.close()
    return float(np.median(times)), float(np.median(cpu))


async def _daemon(cell: SimCell, q: np.ndarray, samples: int, data_dir: Path
                  ) -> tuple[float, float]:
    """Median wall and CPU seconds per pose (CPU between consecutive "pose" events)."""
    cfg = parse_config({
        "data_dir": str(data_dir), "robot_description": ROBOT,
        "robot": {"kind": "fanuc_rmi", "options": cell.robot_options("fanuc_rmi")},
        "tracker": {"kind": "ltp", "options": {**cell.tracker_options("tcp"), "stab_ms": 100}},
        "limits": {"joint_margin_deg": 0.5, "speed_pct": 100.0},
        "measurement": {"samples": samples, "settle_s": 0.0},
        "fit": {"executor": "thread", "models": ["constant"], "select": "constant",
                "report": False},
    }, source="bench")
    svc = CalibrationService(cfg)
    marks: list[float] = []
    emit = svc.events.emit

    def marking(kind: str, campaign: str | None = None, **data: Any) -> dict[str, Any]:
        if kind == "pose":
            marks.append(time.process_time())
        return emit(kind, campaign, **data)

    svc.events.emit = marking  # type: ignore[method-assign]
    await svc.start()
    try:
        doc = plan_from_poses(np.degrees(q).tolist(), robot=ROBOT)
        st = await svc.create(parse_plan(doc, strict=False), actor="bench", measure_only=True)
        await svc.wait(st["id"], ["measured", "faulted"], timeout=600)
        return float(np.median(svc.pose_times)), float(np.median(np.diff(marks)))
    finally:
        await svc.stop()


def _store_commit(data_dir: Path, n: int = 300) -> tuple[float, float]:
    """Seconds per measurement commit (NORMAL) and per durable audit commit (FULL)."""
    store = Store(data_dir / "commit.sqlite3").open()
    try:
        rec = store.create_campaign(
            name="b", robot="r", poses=[PoseRow(i, "calibration", (0.0,) * 6) for i in range(n)],
            plan_json="{}", plan_digest="d", config_digest="c", actor="bench")
        t0 = time.perf_counter()
        for i in range(n):
            store.add_measurement(rec.id, Measurement(
                pose_idx=i, purpose="calibration", q_cmd_deg=(0.0,) * 6, q_act_deg=(0.0,) * 6,
                p_mm=(1.0, 2.0, 3.0), sigma_mm=(0.01,) * 3, rms_mm=0.001, samples=5,
                attempts=1, distance_mm=None, weather={}, measured_at=now_iso()))
        t1 = time.perf_counter()
        for i in range(n):
            store.audit(actor="bench", action="bench", campaign=rec.id, detail={"i": i})
        return (t1 - t0) / n, (time.perf_counter() - t1) / n
    finally:
        store.close()


async def _main(args: argparse.Namespace) -> None:
    q = _poses(args.poses)
    cell = SimCell(robot=ROBOT, seed=1, fanuc=FanucSimOptions(time_scale=0.0), modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0))
    bare, daemon = [], []
    with tempfile.TemporaryDirectory() as tmp:
        async with cell:
            # bare and daemon alternate, so a change of machine load hits both alike
            for r in range(args.rounds):
                bare.append(await _bare(cell, q, args.samples))
                daemon.append(await _daemon(cell, q, args.samples, Path(tmp) / f"state{r}"))
            await asyncio.sleep(0.1)
        commit = _store_commit(Path(tmp))
    b, d = np.array(bare), np.array(daemon)  # (rounds, 2): wall, CPU s per pose
    ratio = d / b
    print(f"poses: {args.poses}, samples per reading: {args.samples}, rounds: {args.rounds} "
          "(bare and daemon alternating; per round the median per pose)")
    print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    for r in range(args.rounds):
        print(f"  round {r + 1}: bare {b[r, 0] * 1e3:.2f} / {b[r, 1] * 1e3:.2f} ms, daemon "
              f"{d[r, 0] * 1e3:.2f} / {d[r, 1] * 1e3:.2f} ms (wall / CPU), ratio "
              f"{ratio[r, 0]:.2f} / {ratio[r, 1]:.2f}")
    mb, md, mr = np.median(b, axis=0), np.median(d, axis=0), np.median(ratio, axis=0)
    print(f"bare drivers          {mb[0] * 1e3:8.2f} ms wall, {mb[1] * 1e3:6.2f} ms CPU per "
          "pose (median of rounds)")
    print(f"daemon engine         {md[0] * 1e3:8.2f} ms wall, {md[1] * 1e3:6.2f} ms CPU "
          "per pose (median of rounds)")
    print(f"daemon / bare         {mr[0]:8.2f} x wall, {mr[1]:6.2f} x CPU (median of the "
          "rounds' ratios)  [acceptance <= 1.3 x]")
    print(f"store commit (NORMAL) {commit[0] * 1e3:8.2f} ms per measurement")
    print(f"store commit (FULL)   {commit[1] * 1e3:8.2f} ms per audit record")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--poses", type=int, default=200)
    p.add_argument("--samples", type=int, default=5)
    p.add_argument("--rounds", type=int, default=5, help="bare/daemon pairs (default 5)")
    p.add_argument("--demo", action="store_true", help="also time 'robocal demo'")
    args = p.parse_args()
    configure_logging("warning", "console")
    asyncio.run(_main(args))
    if args.demo:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "robocal.cli.main", "demo", "--quiet",
                            "--out", str(Path(tmp) / "demo")], check=True,
                           stdout=subprocess.DEVNULL)
            print(f"robocal demo (250 poses) {time.perf_counter() - t0:8.1f} s wall")


if __name__ == "__main__":
    main()
