"""What the daemon tells the operator: approve during the fit, the fit in the status."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest

from robocal.daemon import fitting
from robocal.daemon.service import CalibrationService
from robocal.errors import CampaignError
from tests._waiting import eventually
from tests.unit.daemon.conftest import random_plan


async def test_approve_while_the_fit_runs_says_so_and_status_shows_the_fit(
        make_config: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    release = threading.Event()
    real = fitting.run_fit_job

    def held_fit(job: Any) -> dict[str, Any]:
        release.wait(30)  # the fit starts only when the test has looked at it
        return real(job)

    monkeypatch.setattr(fitting, "run_fit_job", held_fit)
    svc = CalibrationService(make_config())
    await svc.start()
    try:
        cid = (await svc.create(random_plan(16, validation=3), actor="op"))["id"]
        await eventually(lambda: svc.status(cid)["fitting"] is not None, 30,
                         what="the fit to start")
        st = svc.status(cid)
        assert st["state"] == "measured"
        assert st["fitting"]["models"] == ["constant"] and st["fitting"]["elapsed_s"] >= 0
        with pytest.raises(CampaignError, match=r"fit .* is still running; approve when it ends"):
            await svc.approve(cid, actor="op")
        from robocal.cli._campaign import _describe

        assert "fitting   constant (running" in _describe(st)
        release.set()
        st = await svc.wait(cid, ["fitted", "faulted"], timeout=60)
        assert st["state"] == "fitted", st["reason"]
        assert st["state"] == "fitted" and st["fitting"] is None
        assert "fitting" not in _describe(st)
        assert (await svc.approve(cid, actor="op"))["state"] == "approved"
    finally:
        release.set()
        await asyncio.wait_for(svc.stop(), 30)


async def test_health_forgets_the_last_error_once_both_drivers_are_back(make_config: Any) -> None:
    svc = CalibrationService(make_config())
    await svc.start()
    try:
        await svc.hub.connect()
        await svc.hub.reset("DriverTimeout: tracker did not answer")
        drivers = svc.health()["drivers"]
        assert drivers["last_error"].startswith("DriverTimeout")
        await svc.hub.robot()  # one driver back: the error still explains the other
        assert svc.health()["drivers"]["last_error"]
        await svc.hub.tracker()
        drivers = svc.health()["drivers"]
        assert drivers["robot"]["connected"] and drivers["tracker"]["connected"]
        assert drivers["last_error"] == ""
    finally:
        await asyncio.wait_for(svc.stop(), 30)
