"""Per-pose driver overhead: move + read joints + measure through real drivers and simulators.

Simulated motion, settling and sampling time are zero, so the figures are pure software
and loopback overhead: JSON/LTP/Modbus encoding, asyncio scheduling, sockets or the pty,
and the simulators' own work (the virtual robot's kinematics and tracker noise), all in
one process and one event loop.

Usage::

    python bench/bench_drivers.py [--poses 300] [--samples 1] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import statistics
import time
from typing import Any

import numpy as np
import structlog

from robocal.drivers import load_robot_driver, load_tracker_driver
from robocal.drivers.sim import FanucSimOptions, LtpSimOptions, ModbusSimOptions, SimCell

COMBOS = [
    ("mock", "mock"),
    ("fanuc_rmi", "tcp"),
    ("fanuc_rmi", "pty"),
    ("modbus_plc", "tcp"),
]


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q))


async def bench(robot_kind: str, tracker_via: str, poses: int, samples: int) -> dict[str, Any]:
    cell = SimCell(
        seed=1,
        fanuc=FanucSimOptions(time_scale=0.0),
        modbus=ModbusSimOptions(time_scale=0.0),
        ltp=LtpSimOptions(time_scale=0.0),
        ltp_pty=(tracker_via == "pty"),
    )
    async with cell:
        if robot_kind == "mock":
            from robocal.drivers.mock import MockRobot, MockTracker

            robot: Any = MockRobot(world=cell.world)
            tracker: Any = MockTracker(world=cell.world)
        else:
            robot = load_robot_driver(robot_kind, cell.robot_options(robot_kind))  # type: ignore[arg-type]
            tracker = load_tracker_driver("ltp", cell.tracker_options(tracker_via))  # type: ignore[arg-type]
        await robot.connect(timeout=10)
        await tracker.connect(timeout=10)
        rng = np.random.default_rng(0)
        lim = np.asarray(robot.joint_limits_rad)
        centre, half = lim.mean(axis=1), 0.4 * (lim[:, 1] - lim[:, 0])
        targets = rng.uniform(centre - half, centre + half, (poses + 20, robot.dof))
        move, read, meas, total = [], [], [], []
        try:
            for i, q in enumerate(targets):
                t0 = time.perf_counter()
                await robot.move_to(q, speed_pct=100, timeout=10)
                t1 = time.perf_counter()
                await robot.read_joints()
                t2 = time.perf_counter()
                await tracker.measure(samples=samples, timeout=10, point_id=f"P{i}")
                t3 = time.perf_counter()
                if i >= 20:  # warm-up
                    move.append(t1 - t0)
                    read.append(t2 - t1)
                    meas.append(t3 - t2)
                    total.append(t3 - t0)
        finally:
            await tracker.close()
            await robot.close()
    ms = 1e3
    return {
        "robot": robot_kind,
        "tracker": "mock" if robot_kind == "mock" else f"ltp/{tracker_via}",
        "poses": poses,
        "move_ms": statistics.median(move) * ms,
        "read_ms": statistics.median(read) * ms,
        "measure_ms": statistics.median(meas) * ms,
        "pose_median_ms": statistics.median(total) * ms,
        "pose_p95_ms": _pct(total, 95) * ms,
        "poses_per_s": 1.0 / statistics.mean(total),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--samples", type=int, default=1, help="tracker samples per MEAS")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(40))

    async def run() -> list[dict[str, Any]]:
        return [await bench(r, t, args.poses, args.samples) for r, t in COMBOS]

    rows = asyncio.run(run())
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(
        f"driver overhead per pose ({args.poses} poses, {args.samples} sample(s)/MEAS, zero "
        f"simulated time; Python {platform.python_version()}, {platform.machine()})"
    )
    head = (
        f"{'robot':<11} {'tracker':<9} {'move':>8} {'read':>8} {'measure':>8} "
        f"{'pose p50':>9} {'pose p95':>9} {'poses/s':>8}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        print(
            f"{r['robot']:<11} {r['tracker']:<9} {r['move_ms']:>6.3f}ms {r['read_ms']:>6.3f}ms "
            f"{r['measure_ms']:>6.3f}ms {r['pose_median_ms']:>7.3f}ms {r['pose_p95_ms']:>7.3f}ms "
            f"{r['poses_per_s']:>8.0f}"
        )


if __name__ == "__main__":
    main()
