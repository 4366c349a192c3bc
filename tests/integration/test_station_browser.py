"""A whole campaign through the operator's station in a real browser, against the simulators.

Headless Chromium (Debian's, driven by Playwright with ``executable_path``) signs in with the
daemon's token, starts a campaign from a plan file, watches it measure and fit live, approves
the proposed model, pushes it, and rolls it back, asserting at each step on what the page
shows (and that the service agrees). Screenshots of each page at 1024 and 1920 px go to
``$ROBOCAL_STATION_SHOTS`` (or the test's tmp dir). Accessibility basics: labelled inputs,
the palette's contrast, the actions reachable with the keyboard.

Skipped, with the reason, when no Chromium is installed (CI installs Debian's ``chromium``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Any

import pytest
import structlog
from playwright.async_api import Dialog, Page, async_playwright
from tests.unit.daemon.conftest import ROBOT, base_config

from robocal.daemon import station
from robocal.daemon.api import ApiServer
from robocal.daemon.config import parse_config
from robocal.daemon.service import CalibrationService
from robocal.drivers.sim import FanucSimOptions, LtpSimOptions, SimCell

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
TOKEN = "station-e2e-token-0123456789"
VIEWER = "station-e2e-viewer-9876543210"
WAIT_MS = 60_000

# WCAG relative luminance and contrast ratio of every visible text against its background.
CONTRAST = """
(sel) => {
  const lum = (c) => {
    const v = c.match(/[\\d.]+/g).slice(0, 3).map(Number).map((x) => x / 255)
      .map((x) => x <= 0.03928 ? x / 12.92 : ((x + 0.055) / 1.055) ** 2.4);
    return 0.2126 * v[0] + 0.7152 * v[1] + 0.0722 * v[2];
  };
  const bg = (el) => {
    for (let e = el; e; e = e.parentElement) {
      const c = getComputedStyle(e).backgroundColor;
      if (c && !c.startsWith("rgba(0, 0, 0, 0)") && c !== "transparent") return c;
    }
    return "rgb(255, 255, 255)";
  };
  return Array.from(document.querySelectorAll(sel)).filter((e) => e.offsetParent !== null)
    .map((e) => {
      const a = lum(getComputedStyle(e).color), b = lum(bg(e));
      return [e.tagName + "." + e.className + ":" + e.textContent.trim().slice(0, 30),
              (Math.max(a, b) + 0.05) / (Math.min(a, b) + 0.05)];
    });
}
"""
UNLABELLED = """
() => Array.from(document.querySelectorAll("input:not([type=hidden]), select, textarea"))
  .filter((e) => !(e.labels && e.labels.length) && !e.getAttribute("aria-label"))
  .map((e) => e.name || e.id)
"""


def _browser() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


@pytest.fixture(scope="module")
def chromium() -> str:
    b = _browser()
    if b is None:
        pytest.skip("no Chromium/Chrome found (tried: " + ", ".join(BROWSERS) + "); install "
                    "Debian's 'chromium' package to run the station's browser test")
    return b


@pytest.fixture
def shots(tmp_path: Path) -> Path:
    d = Path(os.environ.get("ROBOCAL_STATION_SHOTS") or tmp_path / "screenshots")
    d.mkdir(parents=True, exist_ok=True)
    return d


@pytest.fixture
def plan_file(tmp_path: Path) -> Path:
    from robocal.planning import plan_campaign

    plan = plan_campaign(ROBOT, "demo", count=30, model="constant", validation=8, cpa=False,
                         iso=False, seed=3, candidates=256)
    path = tmp_path / "PLAN.json"
    path.write_text(plan.to_json())
    return path


async def _screens(page: Page, shots: Path, name: str) -> None:
    for width, height in ((1024, 768), (1920, 1080)):
        await page.set_viewport_size({"width": width, "height": height})
        # nothing sideways: the page fits the screen at both widths
        overflow = await page.evaluate(
            "() => document.documentElement.scrollWidth - window.innerWidth")
        assert overflow <= 0, f"{name} at {width} px is {overflow} px too wide"
        await page.screenshot(path=str(shots / f"{name}-{width}.png"), full_page=True)
    await page.set_viewport_size({"width": 1280, "height": 900})


async def _act(page: Page, button: str, expect_in_dialog: str) -> str:
    """Click an action, check its confirmation names what happens, accept it; wait for the
    page to come back."""
    seen: list[str] = []

    async def accept(d: Dialog) -> None:
        seen.append(d.message)
        await d.accept()

    page.once("dialog", accept)
    async with page.expect_navigation(timeout=WAIT_MS):
        await page.click(button)
    assert seen and expect_in_dialog in seen[0], seen
    return seen[0]


async def _state(page: Page, state: str) -> None:
    await page.wait_for_selector(f'#live-state[data-state="{state}"]', timeout=WAIT_MS)


async def test_a_campaign_from_sign_in_to_rollback_through_the_pages(
        chromium: str, tmp_path: Path, plan_file: Path, shots: Path,
        capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    # the station's log lines, whatever logging an earlier test in this worker configured
    # (structlog caches a logger on first use): a fresh logger writing to a capture
    cap = structlog.testing.LogCapture()
    structlog.configure(processors=[cap])
    monkeypatch.setattr(station, "_log", structlog.get_logger("robocal.daemon.station"))
    try:
        await _whole_campaign(tmp_path, plan_file, shots, chromium)
    finally:
        structlog.reset_defaults()
    logged = repr(cap.entries)
    out, err = capfd.readouterr()
    assert "station sign-in" in logged       # the daemon's log lines were captured ...
    for text in (logged, out + err):         # ... and none holds a token
        assert TOKEN not in text and VIEWER not in text


async def _whole_campaign(tmp_path: Path, plan_file: Path, shots: Path, chromium: str) -> None:
    cell = SimCell(robot=ROBOT, seed=4, fanuc=FanucSimOptions(time_scale=0.0), modbus=False,
                   ltp=LtpSimOptions(time_scale=0.0))
    tok = tmp_path / "token"
    tok.write_text(TOKEN + "\n")
    tok.chmod(0o600)
    vtok = tmp_path / "viewer-token"
    vtok.write_text(VIEWER + "\n")
    vtok.chmod(0o600)
    async with cell:
        cfg: dict[str, Any] = base_config(
            tmp_path, limits={"max_joint_correction_deg": 5.0},
            compensation={"verify_count": 4},
            fit={"report": True},
            api={"socket": None, "tcp_port": 0, "token_file": str(tok),
                 "viewer_token_file": str(vtok)})
        cfg["robot"] = {"kind": "fanuc_rmi", "options": cell.robot_options("fanuc_rmi")}
        cfg["tracker"] = {"kind": "ltp",
                          "options": {**cell.tracker_options("tcp"), "stab_ms": 10}}
        config = parse_config(cfg, source="test")
        svc = CalibrationService(config)
        await svc.start()
        api = ApiServer(svc, config)
        await api.start()
        url = f"http://127.0.0.1:{api.tcp_port}"
        try:
            async with async_playwright() as pw:
                browser = await pw.chromium.launch(executable_path=chromium,
                                                   args=["--no-sandbox", "--disable-gpu"])
                try:
                    page = await browser.new_page(viewport={"width": 1280, "height": 900})
                    cid = await _run(page, url, svc, plan_file, shots)
                    viewer = await browser.new_page(viewport={"width": 1024, "height": 768})
                    await _viewer(viewer, url, cid)
                finally:
                    await browser.close()
        finally:
            await api.stop()
            await svc.stop()


async def _viewer(page: Page, url: str, cid: str) -> None:
    """The viewer token signs in read only: the same page, no action."""
    await page.goto(f"{url}/station/campaigns/{cid}")
    assert page.url.endswith("/station/login")
    await page.fill("#token", VIEWER)
    await page.fill("#name", "vic")
    async with page.expect_navigation():
        await page.click("button[type=submit]")
    await page.goto(f"{url}/station/campaigns/{cid}")
    assert "vic · viewer" in await page.inner_text("header")
    assert "original values" in await page.inner_text("#controller")
    assert await page.locator("#actions form").count() == 0
    assert "read only" in await page.inner_text("#actions")


async def _run(page: Page, url: str, svc: CalibrationService, plan_file: Path,
               shots: Path) -> str:
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))

    # --- sign in ------------------------------------------------------------------------
    await page.goto(url + "/")
    assert page.url.endswith("/station/login")
    assert await page.evaluate(UNLABELLED) == []
    await _screens(page, shots, "login")
    await page.fill("#token", TOKEN)
    await page.fill("#name", "alice")
    async with page.expect_navigation():
        await page.click("button[type=submit]")
    assert page.url.endswith("/station/"), await page.content()
    assert "original values" in await page.inner_text("#controller")
    assert "alice · operator" in await page.inner_text("header")
    assert await page.evaluate(UNLABELLED) == []
    cookies = await page.context.cookies()
    session = next(c for c in cookies if c["name"] == "robocal_session")
    assert session["httpOnly"] and session["sameSite"] == "Strict"
    assert TOKEN not in await page.content()

    # --- start from a plan file -----------------------------------------------------------
    await page.fill("#plan", str(plan_file))
    await page.fill("#cname", "e2e")
    msg = await _act(page, "#start", "the robot will move through every pose")
    assert str(plan_file) in msg
    cid = page.url.rsplit("/", 1)[-1]
    assert re.fullmatch(r"[0-9a-f]+", cid), page.url
    # --- watch: the page updates itself (no reload) until the fit is done -------------
    await page.evaluate("() => { window.__noReload = 1; }")
    await page.wait_for_function("() => document.body.dataset.sse === 'open'",
                                 timeout=WAIT_MS)
    await _state(page, "fitted")
    assert await page.evaluate("() => window.__noReload") == 1
    st = svc.status(cid)
    assert st["state"] == "fitted", st["reason"]
    total = st["poses_total"]
    assert await page.inner_text("#measured") == f"{total} / {total}"
    assert "poses/min" in await page.inner_text("#rate")
    assert await page.inner_text("li.step.current") == "review"
    steps = await page.eval_on_selector_all("li.step", "els => els.map(e => e.textContent)")
    assert steps == ["plan", "measure", "fit", "review", "approve", "push", "verify"]
    # the plot has every pose and, once fitted, the residuals of nominal and fitted model
    await page.wait_for_function(
        f"() => document.getElementById('plot').dataset.n === '{total}' && "
        "document.getElementById('plot').dataset.models.includes('constant')",
        timeout=WAIT_MS)
    rms = st["fits"]["constant"]["validation"]["rms_mm"]
    assert f"{rms:.4f} mm" in await page.inner_text("#live")
    # the report renders after the fit is stored (ADR 0048): the page swaps it in
    await page.wait_for_selector("iframe.report", timeout=WAIT_MS)
    assert await page.is_visible("iframe.report")
    # the embedded report renders (sandboxed, its own inline styles and inline SVG figures)
    await page.frame_locator("iframe.report").locator("#verdict").wait_for(timeout=WAIT_MS)
    # with its figures drawn: inline SVG under the report's CSP, laid out at a readable size
    plots = page.frame_locator("iframe.report").locator("figure > svg")
    assert await plots.count() > 5
    box = await plots.first.bounding_box()
    assert box is not None and box["width"] > 200 and box["height"] > 100
    report = await page.request.get(f"{url}/campaigns/{cid}/report")
    assert report.status == 200 and "<html" in (await report.text()).lower()

    # accessibility: labels, contrast of every text shown, keyboard reaches the action
    assert await page.evaluate(UNLABELLED) == []
    ratios = await page.evaluate(CONTRAST, "h1, h2, p, dt, dd, td, th, label, button, a, "
                                           ".badge, li.step, #controller")
    low = [(what, round(r, 2)) for what, r in ratios if r < 4.5]
    assert not low, low
    reached = []
    await page.focus("body")
    for _ in range(60):
        await page.keyboard.press("Tab")
        reached.append(await page.evaluate("() => document.activeElement.id"))
        if reached[-1] == "act-approve":
            break
    assert reached[-1] == "act-approve", reached
    await _screens(page, shots, "campaign-fitted")

    # --- approve the chosen model -----------------------------------------------------------
    await page.select_option("#model", "constant")
    await _act(page, "#act-approve", "Approve model constant: nothing moves")
    await _state(page, "approved")
    assert svc.status(cid)["state"] == "approved"
    assert await page.inner_text("li.step.current") == "push"

    # --- push: the controller's table changes, the banner says so -------------------------
    await _act(page, "#act-push", "the controller's compensation is overwritten")
    await _state(page, "pushed")
    assert svc.compensation()["active"]["campaign"] == cid
    await page.wait_for_function(
        "() => document.getElementById('controller').textContent.includes('after')",
        timeout=WAIT_MS)
    banner = await page.inner_text("#controller")
    assert "model constant" in banner and cid in banner, banner
    push = svc.status(cid)["push"]
    assert f"{push['measured_after_rms_mm']:.4f} mm after" in banner
    assert push["measured_after_rms_mm"] < push["measured_before_rms_mm"]
    await _screens(page, shots, "campaign-pushed")

    # --- roll back --------------------------------------------------------------------------
    await _act(page, "#act-rollback", "returns to what it held before this push")
    await page.wait_for_selector("#rolled-back", timeout=WAIT_MS)
    assert "original values, rolled back at" in await page.inner_text("#controller")
    # the rollback is measured again, and the banner says how it came out
    await page.wait_for_function(
        "() => document.getElementById('controller').textContent.includes('after')",
        timeout=WAIT_MS)
    last = svc.compensation()["history"][-1]
    assert last["action"] == "rollback" and last["verification"]["state"] == "done"
    assert (f"{last['verification']['after']['rms_mm']:.4f} mm after"
            in await page.inner_text("#controller"))
    assert svc.compensation()["active"]["origin"] == "controller"
    assert "rolled back" in await page.eval_on_selector_all(
        "li.step", "els => els.map(e => e.textContent)")
    assert not await page.is_visible("#act-rollback")
    await _screens(page, shots, "campaign-rolled-back")

    # --- the list says the same -------------------------------------------------------------
    await page.goto(url + "/station/")
    row = await page.inner_text(f'tr[data-campaign="{cid}"]')
    assert "pushed" in row and "rolled back" in row and f"{rms:.4f} mm" in row
    await _screens(page, shots, "campaigns")
    # what the CLI does shows up on the open page within a second, without a reload
    await page.evaluate("() => { window.__noReload = 2; }")
    await page.wait_for_function("() => document.body.dataset.sse === 'open'",
                                 timeout=WAIT_MS)
    other = await svc.create(json.loads(plan_file.read_text()), actor="cli", name="from cli",
                             start=False)
    await page.wait_for_selector(f'tr[data-campaign="{other["id"]}"]', timeout=1000)
    assert await page.evaluate("() => window.__noReload") == 2
    # the audit log names the actor of every action
    actors = {a["action"]: a["actor"] for a in svc.audit()}
    for action in ("campaign.approve", "compensation.push", "compensation.rollback"):
        assert actors[action].startswith("alice (operator) via station"), actors
    # offline: nothing was fetched from anywhere but the daemon
    assert all(u.startswith(url) or u.startswith("data:") for u in requests), \
        sorted({u for u in requests if not u.startswith(url)})
    return cid
