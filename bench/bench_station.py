"""Load times of the operator's station with 10,000 measurements in a campaign (issue 29).

A campaign of N poses (default 10,000) runs to ``fitted`` over the mock drivers (this takes
a minute or two), then:

1. the server side: each page and JSON the station serves, timed over HTTP (best and worst
   of 5; the first ``points`` request fits no model but computes the per-pose residuals of
   two models, so it is reported cold and warm);
2. the browser side, if Chromium is installed: Playwright opens the campaign page and waits
   until the residual plot has drawn all N poses (median of 3 loads, page + assets + plot
   data + SVG).

Run: ``.venv/bin/python bench/bench_station.py [--poses N]``
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from aiohttp.test_utils import TestClient, TestServer

from robocal.daemon._plan import parse_plan, plan_from_poses
from robocal.daemon.api import ApiServer, make_app
from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.kinematics import load_robot

ROBOT = "fanuc_lrmate200i"
TOKEN = "bench-station-token-0123456789"


def _config(tmp: Path, token: Path) -> dict[str, object]:
    return {"data_dir": str(tmp / "state"), "robot_description": ROBOT,
            "robot": {"kind": "mock", "options": {"robot": ROBOT}},
            "tracker": {"kind": "mock", "options": {"robot": ROBOT}},
            "measurement": {"settle_s": 0.0, "backoff_s": 0.001, "max_backoff_s": 0.01},
            "fit": {"models": ["constant"], "select": "constant", "executor": "thread",
                    "report": False, "cpa": False},
            "api": {"socket": None, "tcp_port": 0, "token_file": str(token)}}


def _plan(n: int) -> object:
    robot = load_robot(ROBOT)
    rng = np.random.default_rng(0)
    lim = np.degrees(robot.joint_limits)
    q = rng.uniform(lim[:, 0] + 10, lim[:, 1] - 10, (n, robot.dof))
    purposes = ["calibration" if i < n - n // 5 else "validation" for i in range(n)]
    return parse_plan(plan_from_poses(q.tolist(), robot=ROBOT, purposes=purposes),
                      source="bench", strict=False)


async def _timed(client: TestClient, path: str, reps: int = 5, expect: str = "") -> list[float]:
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        r = await client.get(path, allow_redirects=False)
        body = await r.text()
        assert r.status == 200 and expect in body, (path, r.status)
        out.append(time.perf_counter() - t)
    return out


async def _browser(url: str, cid: str, n: int) -> tuple[list[float], list[float]] | None:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        return None
    from playwright.async_api import async_playwright

    loaded, plotted = [], []
    async with async_playwright() as pw:
        browser = await pw.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
        page = await browser.new_page(viewport={"width": 1920, "height": 1080})
        await page.goto(url + "/station/login")
        await page.fill("#token", TOKEN)
        async with page.expect_navigation():
            await page.click("button[type=submit]")
        for _ in range(3):
            t = time.perf_counter()
            await page.goto(f"{url}/station/campaigns/{cid}")  # until the load event
            loaded.append(time.perf_counter() - t)
            await page.wait_for_function(
                f"() => document.getElementById('plot').dataset.n === '{n}'", timeout=30_000)
            plotted.append(time.perf_counter() - t)
        await browser.close()
    return loaded, plotted


async def main(n: int) -> None:
    with tempfile.TemporaryDirectory() as d:
        token = Path(d) / "token"
        token.write_text(TOKEN)
        token.chmod(0o600)
        config = parse_config(_config(Path(d), token), source="bench")
        svc = CalibrationService(config)
        await svc.start()
        t = time.perf_counter()
        st = await svc.create(_plan(n), actor="bench")  # type: ignore[arg-type]
        cid = st["id"]
        st = await svc.wait(cid, ["fitted", "faulted"], timeout=3600)
        assert st["state"] == "fitted", st["reason"]
        print(f"campaign of {n} poses measured and fitted in {time.perf_counter() - t:.0f} s",
              file=sys.stderr)
        async with TestClient(TestServer(make_app(svc))) as c:  # Unix-socket rules: no token
            print(f"| request ({n} measurements) | best | worst of 5 |")
            print("|---|---|---|")
            cold = await _timed(c, f"/station/campaigns/{cid}/points", reps=1)
            print(f"| points JSON, first (residuals of 2 models computed) | {cold[0]:.3f} s | |")
            for label, path, expect in (
                    ("campaigns list", "/station/", cid),
                    ("campaign page", f"/station/campaigns/{cid}", f"{n} / {n}"),
                    ("live fragment (per event)", f"/station/campaigns/{cid}?fragment=live",
                     f"{n} / {n}"),
                    ("points JSON (cached residuals)", f"/station/campaigns/{cid}/points",
                     "constant"),
                    ("station.js", "/station/static/station.js", "EventSource")):
                ts = await _timed(c, path, expect=expect)
                print(f"| {label} | {min(ts):.3f} s | {max(ts):.3f} s |")
        api = ApiServer(svc, config)
        await api.start()
        try:
            loads = await _browser(f"http://127.0.0.1:{api.tcp_port}", cid, n)
        finally:
            await api.stop()
        if loads is None:
            print("browser: no Chromium, skipped")
        else:
            for label, ts in (("browser: campaign page, load event (page, CSS, JS)", loads[0]),
                              (f"browser: campaign page until the plot shows {n} poses",
                               loads[1])):
                print(f"| {label} | {min(ts):.3f} s | {max(ts):.3f} s (median "
                      f"{statistics.median(ts):.3f} s of 3) |")
        await svc.stop()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=10_000)
    asyncio.run(main(ap.parse_args().poses))
