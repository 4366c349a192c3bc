"""The report renders in a real browser: headless Chromium loads the page offline, every
inline SVG plot is laid out with its text inside the figure, and the first screen shows
the verdict.

Skipped, with the reason, when no Chromium is installed (CI installs Debian's ``chromium``).
"""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from robocal.report import MeasurementLog, ReportInput, write_report

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
CHECK = """
<script>
window.addEventListener("load", () => {
  const figs = Array.from(document.querySelectorAll("figure > svg"));
  // a text outside its figure's canvas would be cut off (rotated labels: see their anchor)
  const outside = s => Array.from(s.querySelectorAll("text:not([transform])")).filter(t => {
    const b = t.getBBox(), v = s.viewBox.baseVal;
    return b.x < -1 || b.y < -1 || b.x + b.width > v.width + 1 || b.y + b.height > v.height + 1;
  }).map(t => t.textContent);
  const out = {
    n: figs.length,
    bad: figs.filter(s => !(s.getBoundingClientRect().height > 0
                            && s.querySelectorAll("text").length > 0))
             .map(s => s.getAttribute("aria-label")),
    cut: figs.flatMap(outside),
    shown: figs.map(s => Math.round(s.getBoundingClientRect().width)),
    badge: (document.querySelector("#verdict .badge") || {}).textContent || "",
    verdictTop: Math.round(document.querySelector("#verdict").getBoundingClientRect().top),
    requests: performance.getEntriesByType("resource").map(e => e.name)
                .filter(u => !u.startsWith("data:")),
  };
  const pre = document.createElement("pre");
  pre.id = "robocal-check";
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script>
"""


def _browser() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


def _run(browser: str, profile: Path, *args: str) -> subprocess.CompletedProcess[str]:
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           "--no-first-run", "--hide-scrollbars", f"--user-data-dir={profile}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=90, check=False)


@pytest.fixture(scope="module")
def browser() -> str:
    b = _browser()
    if b is None:
        pytest.skip("no Chromium/Chrome found (tried: " + ", ".join(BROWSERS) + "); install "
                    "Debian's 'chromium' package to run the browser check")
    return b


def test_report_renders_in_headless_chromium(browser: str, tmp_path: Path) -> None:
    from tests.unit.report.conftest import make_campaign

    c = make_campaign(n=250, seed=11)
    inp = ReportInput(models={"nominal": c.fits["nominal"].calibrated,
                              "constant": c.fits["constant"], "auto": c.fits["high-order"]},
                      calibration=c.cal, validation=c.val, iso=c.iso,
                      log=MeasurementLog(retries=1, weather=[{"temperature_c": 20.0}]),
                      workspace_samples=200)
    page, summary = write_report(inp, tmp_path / "report.html")
    n_figures = len(json.loads(summary.read_text())["figures"])
    probe = tmp_path / "probe.html"
    probe.write_text(page.read_text(encoding="utf-8").replace("</body>", CHECK + "</body>"),
                     encoding="utf-8")
    res = _run(browser, tmp_path / "profile", "--virtual-time-budget=10000",
               "--window-size=1280,900", "--dump-dom", probe.as_uri())
    m = re.search(r'<pre id="robocal-check">(.*?)</pre>', res.stdout, re.S)
    assert m, f"no check output (exit {res.returncode}): {res.stderr[-2000:]}"
    got = json.loads(html.unescape(m.group(1)))
    assert got["n"] == n_figures > 8
    assert got["bad"] == []                      # every plot is drawn, with its text
    assert got["cut"] == []                      # no label runs off its figure
    assert min(got["shown"]) > 200               # and is laid out at a readable size
    assert got["requests"] == []                 # nothing fetched from anywhere
    assert "Calibration succeeded" in got["badge"]
    assert got["verdictTop"] < 200               # the verdict is on the first screen

    # the unmodified page as a user sees it: the first screen is not blank
    shot = tmp_path / "first-screen.png"
    res = _run(browser, tmp_path / "profile2", "--window-size=1280,800",
               f"--screenshot={shot}", page.as_uri())
    assert shot.exists(), res.stderr[-2000:]
    from PIL import Image

    im = np.asarray(Image.open(shot).convert("RGB"))
    assert im.shape[:2] == (800, 1280)
    # the green verdict colour (#1e8e3e) is on screen
    green = np.all(np.abs(im.astype(int) - [30, 142, 62]) < 12, axis=2)
    assert green.sum() > 500
