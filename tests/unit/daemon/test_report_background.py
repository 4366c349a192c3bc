"""The report of a fit renders after the fit is stored and announced (issue 28, ADR 0048):
the campaign is ``fitted`` and its status says "rendering" while the fit worker draws the
figures; the files are those a synchronous render writes."""

from __future__ import annotations

import asyncio
import json
import re
import threading
from pathlib import Path
from typing import Any

from robocal.daemon.fitting import build_fit_job, run_fit_job
from robocal.daemon.service import CalibrationService
from robocal.daemon.station import _pages

from .conftest import random_plan


def _same_report(a: Path, b: Path) -> None:
    """Equal report files but for the time they were written and how long it took."""
    def norm(text: str) -> str:
        return re.sub(r"\d{4}-\d\d-\d\d[ T]\d\d:\d\d(:\d\d(\.\d+)?)?(\+00:00|Z| UTC)?", "T",
                      text)

    ja = json.loads(norm((a / "report.json").read_text(encoding="utf-8")))
    jb = json.loads(norm((b / "report.json").read_text(encoding="utf-8")))
    ja.pop("timing_s")
    jb.pop("timing_s")
    assert ja == jb
    assert norm((a / "report.html").read_text(encoding="utf-8")) == norm(
        (b / "report.html").read_text(encoding="utf-8"))


async def test_fitted_before_the_report_renders_and_the_report_is_the_same(
        make_config: Any, tmp_path: Path) -> None:
    svc = CalibrationService(make_config(fit={"report": True}))
    await svc.start()
    gate = threading.Event()
    try:
        async with svc.events.subscribe() as q:
            st = await svc.create(random_plan(30, validation=6), actor="a")
            cid = st["id"]
            seen: list[dict[str, Any]] = []
            async with asyncio.timeout(120):
                while True:
                    ev = await q.get()
                    assert ev is not None
                    if ev["campaign"] != cid:
                        continue
                    seen.append(ev)
                    if ev["kind"] == "fit" and ev["phase"] == "started":
                        # the fit worker (one) takes this after the fit: the render queues
                        # behind it, so the fitted campaign is seen while the report waits
                        svc.fitter._executor().submit(gate.wait, 60.0)
                    if ev["kind"] == "report" and ev.get("state") == "rendering":
                        break
            st = svc.status(cid)
            assert st["state"] == "fitted" and st["fits"]["constant"]["validation"]
            assert st["report"] == {"state": "rendering"}
            assert "Report rendering" in _pages.report_box(cid, False, rendering=True)
            assert not (Path(st["files"]) / "report.json").exists()
            order = [(e["kind"], e.get("to_state") or e.get("phase") or e.get("state"))
                     for e in seen]
            assert order.index(("fit", "done")) < order.index(("report", "rendering"))
            gate.set()
            async with asyncio.timeout(120):
                while True:
                    ev = await q.get()
                    assert ev is not None
                    if ev["campaign"] == cid and ev["kind"] == "report":
                        break
            assert ev["state"] == "ready", ev
        st = await svc.wait(cid, ["fitted"], timeout=60)
        assert st["report"]["state"] == "ready"
        html = Path(st["report"]["html"])
        assert html == Path(st["files"]) / "report.html" and html.is_file()
        # the same job with the report written at once, as before
        rows = svc.store.measurements(cid)
        job = build_fit_job(campaign=cid, robot=svc.robot, rows=rows,
                            models=svc.config.fit.models, cpa=svc.config.fit.cpa,
                            out_dir=tmp_path / "sync", report=True,
                            log=svc.fits.measurement_log(cid, rows),
                            options=svc.config.fit.options,
                            acceptance=svc.config.fit.acceptance)
        job["selected"] = svc.config.fit.select
        out = await asyncio.to_thread(run_fit_job, job)
        assert out["report"]["paths"]
        _same_report(Path(st["files"]), tmp_path / "sync")
    finally:
        gate.set()
        await svc.stop()


async def test_wait_and_the_api_file_wait_for_the_report(make_config: Any) -> None:
    """Callers that read the files after ``fitted`` (the CLI, the API) get them written."""
    svc = CalibrationService(make_config(fit={"report": True}))
    await svc.start()
    try:
        st = await svc.create(random_plan(24, validation=4), actor="a")
        st = await svc.wait(st["id"], ["fitted"], timeout=120)
        assert st["state"] == "fitted" and st["report"]["state"] == "ready"
        assert (Path(st["files"]) / "report.json").is_file()
        path = await svc.report_file(st["id"], "report.html")
        assert path is not None and path.is_file()
    finally:
        await svc.stop()
