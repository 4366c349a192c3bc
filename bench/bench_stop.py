"""Stop latency: from a driver's ``stop()`` request to the simulated robot's halt.

For each robot driver against its simulator, moving in real time, a far move is started and
stopped once the joints have begun to move. Two times are taken from the request: when the
simulator froze the virtual robot (``SimWorld.last_halt_time``), and when ``stop()`` returned
(the controller confirmed the halt and is ready for the next move). Everything runs in one
process and one event loop on loopback, so the figures are software and protocol overhead;
a real controller adds its braking time.

Usage::

    python bench/bench_stop.py [--trials 30] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import platform
import time
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import structlog

from robocal.drivers import load_robot_driver
from robocal.drivers.mock import MockRobot
from robocal.drivers.sim import (
    AbbSimOptions,
    FanucSimOptions,
    ModbusSimOptions,
    SimCell,
    SimWorld,
)

KINDS = ("fanuc_rmi", "modbus_plc", "mock", "abb_rws6", "abb_rws7")


@contextlib.asynccontextmanager
async def _robot(kind: str, world: SimWorld) -> AsyncIterator[Any]:
    if kind == "mock":
        robot: Any = MockRobot({"move_time_s": 5.0}, world=world)
        await robot.connect(timeout=5)
        try:
            yield robot
        finally:
            await robot.close()
        return
    abb = kind.startswith("abb_rws")
    cell = SimCell(
        world=world,
        fanuc=FanucSimOptions(time_scale=1.0) if kind == "fanuc_rmi" else False,
        modbus=ModbusSimOptions(time_scale=1.0) if kind == "modbus_plc" else False,
        ltp=False,
        abb=AbbSimOptions(time_scale=1.0, robotware=int(kind[-1])) if abb else False,  # type: ignore[arg-type]
    )
    async with cell:
        driver = "abb_rws" if abb else kind
        robot = load_robot_driver(driver, cell.robot_options(driver))  # type: ignore[arg-type]
        await robot.connect(timeout=5)
        try:
            yield robot
        finally:
            await robot.close()


async def _trial(kind: str, seed: int) -> tuple[float, float]:
    world = SimWorld.create(seed=seed)
    async with _robot(kind, world) as robot:
        start = world.q_actual_rad
        far = [lo + 0.8 * (hi - lo) for lo, hi in world.joint_limits_rad]
        move = asyncio.create_task(robot.move_to(far, speed_pct=10, timeout=60))
        deadline = time.monotonic() + 10
        while np.max(np.abs(world.q_actual_rad - start)) < 0.01:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{kind}: the robot did not start moving")
            await asyncio.sleep(0.002)
        t0 = time.monotonic()
        await robot.stop()
        confirmed = time.monotonic() - t0
        with contextlib.suppress(Exception):
            await move
        if world.last_halt_time is None:
            raise RuntimeError(f"{kind}: stop() did not halt the simulated robot")
        return world.last_halt_time - t0, confirmed


async def run(trials: int, kinds: list[str] | tuple[str, ...] = KINDS) -> dict[str, Any]:
    """Return per-driver latency statistics in milliseconds."""
    out: dict[str, Any] = {}
    for kind in kinds:
        halts, confirms = [], []
        for i in range(trials):
            h, c = await _trial(kind, seed=i)
            halts.append(h * 1e3)
            confirms.append(c * 1e3)
        out[kind] = {
            "trials": trials,
            "halt_ms": {
                "median": float(np.median(halts)),
                "p95": float(np.percentile(halts, 95)),
                "max": float(np.max(halts)),
            },
            "stop_returned_ms": {
                "median": float(np.median(confirms)),
                "p95": float(np.percentile(confirms, 95)),
                "max": float(np.max(confirms)),
            },
        }
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=30)
    p.add_argument("--json", action="store_true")
    p.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
    args = p.parse_args()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(40))
    result = asyncio.run(run(args.trials, args.kinds))
    result["machine"] = {"python": platform.python_version(), "cpu": platform.processor()}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(f"{'driver':<12} {'halt median/p95/max ms':>26} {'stop() returned median/p95/max':>32}")
    for kind in args.kinds:
        h, c = result[kind]["halt_ms"], result[kind]["stop_returned_ms"]
        print(
            f"{kind:<12} {h['median']:8.2f} {h['p95']:8.2f} {h['max']:8.2f}"
            f"   {c['median']:8.2f} {c['p95']:8.2f} {c['max']:8.2f}"
        )


if __name__ == "__main__":
    main()
