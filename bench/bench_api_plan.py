"""Event-loop stalls while the daemon's API receives a large plan (issue 15).

A ticker task records the longest gap between its 1 ms wake-ups while a client POSTs
``/campaigns`` with plans of growing size (``start: false``, so nothing moves), over the mock
drivers with the demo cell's checks. The app admits 2 MiB here (the daemon's default is
512 KiB), so the last size shows the refusal.

Run: ``.venv/bin/python bench/bench_api_plan.py``
"""

from __future__ import annotations

import asyncio
import json
import tempfile
import time
from pathlib import Path

from aiohttp.test_utils import TestClient, TestServer

from robocal.daemon.api import make_app
from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.planning import plan_campaign

ROBOT = "fanuc_lrmate200i"


def _config(tmp: Path) -> dict[str, object]:
    return {"data_dir": str(tmp / "state"), "robot_description": ROBOT,
            "robot": {"kind": "mock", "options": {"robot": ROBOT}},
            "tracker": {"kind": "mock", "options": {"robot": ROBOT}},
            "fit": {"models": ["constant"], "select": "constant", "executor": "thread"}}


async def _max_gap(stop: asyncio.Event, out: list[float]) -> None:
    last = time.perf_counter()
    while not stop.is_set():
        await asyncio.sleep(0.001)
        now = time.perf_counter()
        out.append(now - last)
        last = now


async def main() -> None:
    base = json.loads(plan_campaign(ROBOT, "demo", count=20, model="constant", validation=5,
                                    cpa=False, iso=False, seed=3, candidates=256).to_json())
    per_pose = len(json.dumps(base["poses"][0]))
    with tempfile.TemporaryDirectory() as d:
        svc = CalibrationService(parse_config(_config(Path(d))))
        await svc.start()
        try:
            app = make_app(svc, max_body_bytes=2 * 1024 * 1024)
            async with TestClient(TestServer(app)) as http:
                print("| body | poses | status | request | longest loop stall |")
                print("|---|---|---|---|---|")
                for size in (100_000, 500_000, 1_000_000, 7_500_000):
                    n = size // per_pose
                    plan = dict(base, poses=[dict(base["poses"][i % len(base["poses"])],
                                                  index=i) for i in range(n)])
                    body = json.dumps({"plan": plan, "start": False}).encode()
                    gaps: list[float] = []
                    stop = asyncio.Event()
                    ticker = asyncio.create_task(_max_gap(stop, gaps))
                    t0 = time.perf_counter()
                    r = await http.post("/campaigns", data=body,
                                        headers={"Content-Type": "application/json"})
                    await r.read()
                    dt = time.perf_counter() - t0
                    stop.set()
                    await ticker
                    print(f"| {len(body) / 1e6:.2f} MB | {n} | {r.status} | {dt:.2f} s | "
                          f"{max(gaps) * 1e3:.0f} ms |")
        finally:
            await svc.stop()


if __name__ == "__main__":
    asyncio.run(main())
