"""The campaign service's fits: one task per measured campaign, off the event loop.

:class:`FitTasks` starts a fit when a campaign is ``measured`` (or was when the daemon
stopped), runs it in the :class:`~robocal.daemon.fitting.FitRunner`, signs and stores the
models and moves the campaign to ``fitted`` (or ``faulted``, saying why). It belongs to the
campaign service, which constructs it and reaches its tasks through it.
"""

from __future__ import annotations

import asyncio
import contextlib
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog

from robocal.daemon import _fingerprint, checking
from robocal.daemon.campaign import CampaignState
from robocal.daemon.config import AppConfig
from robocal.daemon.events import EventBus
from robocal.daemon.fitting import (
    LATER,
    FitRunner,
    build_fit_job,
    load_model,
    sign_fits,
    temperature_log,
)
from robocal.daemon.schemas import Measurement
from robocal.daemon.store import Store, now_iso
from robocal.errors import IdentificationError, RobocalError, StorageError
from robocal.kinematics import CalibratedModel, RobotDescription

__all__ = ["FitTasks"]

S = CampaignState
_log = structlog.get_logger(__name__)


@dataclass(kw_only=True, eq=False)
class FitTasks:
    """Fit tasks by campaign id.

    ``campaign_dir`` names a campaign's files; ``transition`` moves a campaign to a state
    (stored, announced and logged: the service's own).
    """

    config: AppConfig
    robot: RobotDescription
    store: Store
    events: EventBus
    fitter: FitRunner
    secret: bytes | None
    campaign_dir: Callable[[str], Path]
    transition: Callable[..., object]
    _tasks: dict[str, asyncio.Task[None]] = field(default_factory=dict, init=False)
    _started: dict[str, tuple[str, float]] = field(  # ISO time, monotonic s
        default_factory=dict, init=False)
    # reports rendered after the fit was stored: campaign -> its render task, and the
    # state of each render this daemon started ("rendering", "ready", "failed")
    _renders: dict[str, asyncio.Task[None]] = field(default_factory=dict, init=False)
    _report_state: dict[str, dict[str, Any]] = field(default_factory=dict, init=False)
    #: called with the campaign id when its report has been written
    on_report: Callable[[str], object] = field(default=lambda _cid: None, init=False)

    def __contains__(self, cid: str) -> bool:
        return cid in self._tasks

    def running(self) -> list[str]:
        """Campaigns fitting now, sorted."""
        return sorted(self._tasks)

    def tasks(self) -> list[asyncio.Task[None]]:
        """The fit and report tasks (to cancel at shutdown)."""
        return [*self._tasks.values(), *self._renders.values()]

    def report_state(self, cid: str) -> dict[str, Any] | None:
        """``{"state": "rendering" | "ready" | "failed", ...}`` of the report this daemon
        renders or rendered for ``cid`` after its fit, or None."""
        st = self._report_state.get(cid)
        return None if st is None else dict(st)

    async def report_settled(self, cid: str, timeout: float) -> None:
        """Wait (at most ``timeout`` s; TimeoutError) until ``cid``'s report is not being
        rendered."""
        task = self._renders.get(cid)
        if task is not None and not task.done():
            async with asyncio.timeout(timeout):
                await asyncio.shield(task)

    def _render_later(self, cid: str, report: Any) -> None:
        """Render the report the fit left pending, in the fit worker, after the fit is
        stored and announced (the operator does not wait for the figures)."""
        if not isinstance(report, dict) or "pending" not in report:
            return
        self._report_state[cid] = {"state": "rendering"}
        self.events.emit("report", cid, section="campaign", state="rendering")
        task = asyncio.create_task(self._render(cid, str(report["pending"])),
                                   name=f"report-{cid}")
        self._renders[cid] = task
        task.add_done_callback(lambda t: self._renders.pop(cid, None)
                               if self._renders.get(cid) is t else None)

    async def _render(self, cid: str, token: str) -> None:
        try:
            out = await self.fitter.render(token)
        except (RobocalError, OSError, ValueError) as err:
            out = {"skipped": f"report failed: {type(err).__name__}: {err}"}
        paths = out.get("paths")
        if paths:
            self._report_state[cid] = {"state": "ready", "html": paths["html"]}
            self.on_report(cid)
            self.events.emit("report", cid, section="campaign", state="ready",
                             html=paths["html"])
        else:
            reason = str(out.get("skipped") or "report not written")
            self._report_state[cid] = {"state": "failed", "reason": reason}
            self.events.emit("report", cid, section="campaign", state="failed",
                             reason=reason)
        _log.info("report", campaign=cid, **self._report_state[cid])

    def started(self, cid: str) -> tuple[str, float] | None:
        """When the fit of ``cid`` started (ISO time, monotonic s), if it runs."""
        return self._started.get(cid) if cid in self._tasks else None

    def cancel(self, cid: str) -> None:
        """Stop the fit of ``cid``, if any."""
        fit = self._tasks.get(cid)
        if fit is not None:
            fit.cancel()

    def spawn(self, cid: str) -> None:
        """Fit ``cid`` unless its fit runs already."""
        if cid in self._tasks and not self._tasks[cid].done():
            return
        task = asyncio.create_task(self._fit_guarded(cid), name=f"fit-{cid}")
        self._tasks[cid] = task
        self._started[cid] = (now_iso(), time.monotonic())
        task.add_done_callback(lambda _t: (self._tasks.pop(cid, None),
                                           self._started.pop(cid, None)))

    async def _fit_guarded(self, cid: str) -> None:
        try:
            await self._fit(cid)
        except StorageError as err:
            # Never stuck in "measured": faulted (held in memory until saved); resume fits again.
            _log.error("fit not saved: the store cannot write", campaign=cid, error=str(err))
            with contextlib.suppress(RobocalError, sqlite3.Error):
                self._fault(cid, f"storage fault while saving the fit: {err}")

    def measurement_log(self, cid: str, rows: list[Measurement]) -> dict[str, Any]:
        """What the report says of the measuring: poses planned and measured, retries, beam
        losses, devices, the last weather reading and the joint temperatures."""
        retries = sum(max(0, r.attempts - 1) for r in rows)
        weather = [r.weather for r in rows if r.weather][-1:]
        planned = sum(1 for p in self.store.poses(cid) if p.measure)
        return {"planned": planned, "measured": len(rows), "retries": retries,
                "beam_losses": sum(r.beam_losses for r in rows),
                "tracker": self.config.tracker.kind, "controller": self.config.robot.kind,
                "weather": weather[0] if weather else {}, **temperature_log(rows)}

    async def _run(self, cid: str, rows: list[Measurement]) -> dict[str, Any] | None:
        """The fit job's result, or None when it failed (the campaign faulted)."""
        log = _log.bind(campaign=cid)
        job = build_fit_job(campaign=cid, robot=self.robot, rows=rows,
                            models=self.config.fit.models, cpa=self.config.fit.cpa,
                            out_dir=self.campaign_dir(cid),
                            report=LATER if self.config.fit.report else False,
                            log=self.measurement_log(cid, rows),
                            options=self.config.fit.options,
                            acceptance=self.config.fit.acceptance,
                            model_data=_fingerprint.model_data(self.store, cid))
        if self.config.fit.select != "best":
            job["selected"] = self.config.fit.select
        reuse = checking.reuse_source(self.store, cid)
        if reuse is not None:  # a re-calibration with --reuse of that model (ADR 0041)
            job["reuse"] = self.model(*reuse).to_dict()
        self.events.emit("fit", cid, phase="started", models=list(self.config.fit.models))
        log.info("fitting", models=list(self.config.fit.models), poses=len(rows))
        try:
            return await self.fitter.run(job)
        except asyncio.CancelledError:
            raise
        except (RobocalError, OSError, ValueError, TypeError) as err:
            reason = f"fit failed: {type(err).__name__}: {err}"
            log.warning("fit failed", error=reason)
            self._fault(cid, reason)
        except Exception as err:  # never let a fit bug kill the daemon
            log.exception("fit crashed")
            self._fault(cid, f"fit crashed: {type(err).__name__}: {err}")
        return None

    async def _fit(self, cid: str) -> None:
        result = await self._run(cid, self.store.measurements(cid))
        if result is None:
            return
        fits = {name: (summ, mj) for name, (summ, mj) in result["fits"].items()}
        for name, msg in result["errors"].items():
            fits.setdefault(name, ({"model": name, "error": msg}, None))
        fits = sign_fits(fits, self.secret, self.robot)
        self.store.save_fits(cid, fits)
        report = result.get("report")
        try:
            self._announce_fit(cid, result, fits, report)
        finally:
            self._render_later(cid, report)   # the worker holds the results until then

    def _announce_fit(self, cid: str, result: dict[str, Any],
                      fits: dict[str, tuple[dict[str, Any], str | None]],
                      report: Any) -> None:
        """Select the model and move the campaign to fitted (or faulted), announced."""
        select = self.config.fit.select
        chosen = result.get("selected_hint") if select == "best" or result.get("reused") \
            else select
        if chosen not in result["fits"] or fits[str(chosen)][1] is None:
            errors = "; ".join(f"{k}: {v}" for k, v in result["errors"].items())
            self._fault(cid, f"model {chosen!r} could not be fitted ({errors or 'no model'})")
            return
        self.store.set_selected_model(cid, chosen)
        if self.store.campaign(cid).state != S.MEASURED:
            return  # aborted while fitting
        self.transition(cid, S.FITTED, actor="daemon",
                         reason=f"fitted {', '.join(result['fits'])}; proposed {chosen}")
        summary = result["fits"][chosen][0].get("validation") or {}
        self.events.emit("fit", cid, phase="done", selected=chosen,
                         validation_rms_mm=summary.get("rms_mm"),
                         report=None if "pending" in (report or {}) else report,
                         seconds=result.get("seconds"))
        _log.info("fitted", campaign=cid, selected=chosen, seconds=result.get("seconds"),
                  report=report)

    def model(self, cid: str, model: str | None = None) -> CalibratedModel:
        """A fitted model of a campaign (default: the selected one), its signature checked.

        Raises
        ------
        IdentificationError
            If that model was not fitted.
        """
        rec = self.store.campaign(cid)
        name = model or rec.selected_model or ""
        text = self.store.model_json(cid, name)
        if text is None:
            raise IdentificationError(f"campaign {cid} has no fitted model {name!r}")
        return load_model(text, source=f"campaign {cid}", secret=self.secret,
                          nominal=self.robot)

    def reference_model(self, exclude: str) -> CalibratedModel | None:
        """The model of the last pushed campaign (not ``exclude``), used to predict readings."""
        for rec in reversed(self.store.campaigns(states=[S.PUSHED])):
            if rec.id == exclude or not rec.selected_model:
                continue
            text = self.store.model_json(rec.id, rec.selected_model)
            if text:
                with contextlib.suppress(RobocalError, ValueError, KeyError):
                    return load_model(text, source=f"campaign {rec.id}",
                                      secret=self.secret, nominal=self.robot)
        return None

    def _fault(self, cid: str, reason: str) -> None:
        if self.store.campaign(cid).state == S.MEASURED:
            self.transition(cid, S.FAULTED, actor="daemon", reason=reason)
        self.events.emit("fit", cid, phase="failed", reason=reason)
