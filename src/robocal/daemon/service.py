"""The daemon's service: a plain async facade over store, drivers, executor, fits and pushes.

The HTTP API is a thin shell over :class:`CalibrationService`; tests and ``robocal demo`` use it
in-process. Methods take an ``actor`` (who asked) that goes into the transitions and the audit
log. One campaign measures at a time (the robot is one); fits run in a worker
(:mod:`~robocal.daemon.fit_tasks`) while the next campaign measures; pushes, rollbacks and their
verification runs are the compensation component's (:mod:`~robocal.daemon.compensating`).
On :meth:`start`, campaigns left ``running`` resume at their first unmeasured pose.
"""

from __future__ import annotations

import asyncio
import builtins
import contextlib
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from robocal import __version__
from robocal._core.clock import SYSTEM_CLOCK, Clock
from robocal._core.files import private_dir
from robocal.compensation import CompensationTable
from robocal.daemon import _fingerprint, creating, pushing, storage_faults
from robocal.daemon._journal import PushJournal
from robocal.daemon._plan import CampaignPlan
from robocal.daemon._reports import ReportKeeper
from robocal.daemon.campaign import FINAL, CampaignState
from robocal.daemon.checking import CheckRuns
from robocal.daemon.compensating import CompensationManager
from robocal.daemon.config import AppConfig, config_digest
from robocal.daemon.engine import CampaignRunner, halt_motion
from robocal.daemon.events import EventBus
from robocal.daemon.fit_tasks import FitTasks
from robocal.daemon.fitting import FitRunner, fit_options
from robocal.daemon.hub import DriverHub
from robocal.daemon.schemas import CampaignSummary, JournalRow, Measurement
from robocal.daemon.store import Store
from robocal.errors import CampaignError, InvalidTransition, RobocalError, StorageError
from robocal.kinematics import CalibratedModel, RobotDescription, load_robot

__all__ = ["CalibrationService"]

S = CampaignState
_log = structlog.get_logger(__name__)


class CalibrationService:
    """Campaigns, fits and compensation for one robot cell.

    Parameters
    ----------
    config : AppConfig
        Validated configuration.
    robot : RobotDescription, optional
        Overrides ``config.robot_description``.
    """

    def __init__(self, config: AppConfig, *, robot: RobotDescription | None = None,
                 clock: Clock = SYSTEM_CLOCK) -> None:
        self.config = config
        self.clock = clock      # the campaign runner's settle time and retry backoff
        self.robot = robot or load_robot(config.robot_description)
        self.store = Store(config.db_path)
        self.events = EventBus()
        self.hub = DriverHub(config, self.robot)
        self.fitter = FitRunner(executor=config.fit.executor, timeout_s=config.fit.timeout_s)
        self._digest = config_digest(config)
        self._secret = config.read_site_secret()   # signs and checks stored MODEL.json
        self._measure_task: tuple[str, asyncio.Task[None]] | None = None
        self.fits = FitTasks(config=config, robot=self.robot, store=self.store,
                             events=self.events, fitter=self.fitter, secret=self._secret,
                             campaign_dir=self._campaign_dir, transition=self.transition)
        self._storage_task: asyncio.Task[None] | None = None
        self.journal = PushJournal(self.store)
        self.reports = ReportKeeper(self.report_records, self._campaign_dir, self.events)
        self.fits.on_report = self.reports.written   # a fresh report gets the current record
        self.compensator = CompensationManager(
            config=config, robot=self.robot, store=self.store, hub=self.hub,
            journal=self.journal, events=self.events, reports=self.reports, campaigns=self,
            secret=self._secret)
        self.checks = CheckRuns(  # drift checks and the reuse refits they recommend (ADR 0041)
            config=config, robot=self.robot, store=self.store, events=self.events,
            campaigns=self, reports=self.reports)
        self._started = time.time()
        self.pose_times: list[float] = []
        self._shutdown_stopped = False

    # --- lifecycle -------------------------------------------------------------------------
    async def start(self, *, connect: bool = True) -> None:
        """Open the store, connect the drivers (failure is logged), resume campaigns."""
        private_dir(self.config.data_dir)
        self.store.open()
        self.journal.ensure_schema()
        self.checks.ensure_schema()
        self.hub.validate()
        fit_options(self.config.fit.options)
        # after the checks above, so a start refused by them leaves no task behind
        self._storage_task = asyncio.create_task(storage_faults.watch(self.store),
                                                 name="storage-watch")
        if connect:
            try:
                await self.hub.connect()
            except (RobocalError, OSError) as err:
                _log.warning("drivers not connected at start-up", error=str(err))
                await self.hub.reset(f"{type(err).__name__}: {err}")
        for rec in self.store.campaigns(states=[S.RUNNING, S.MEASURED]):
            _log.info("resuming campaign after restart", campaign=rec.id, state=rec.state.value,
                      measured=rec.poses_measured, total=rec.poses_total)
            if rec.state == S.RUNNING:
                self.spawn_measure(rec.id)
            elif not rec.measure_only:
                self.fits.spawn(rec.id)
        await self.compensator.resume()
        self.checks.resume()
        self.reports.refresh()

    async def drain(self, timeout: float = 30.0) -> None:
        """Refuse new pushes and rollbacks; wait (at most ``timeout`` s) for the one in
        progress (:meth:`CompensationManager.drain
        <robocal.daemon.compensating.CompensationManager.drain>`)."""
        await self.compensator.drain(timeout)

    async def stop(self) -> None:
        """Stop work (campaign states stay as they are, to resume on restart); close all.

        Motion stops first, at once (the driver's ``stop()``), before anything else closes;
        then a push or rollback in progress finishes (:meth:`drain`).
        """
        self.compensator.closing = True  # verification runs cut from here on stay open
        task = self._measure_task
        if not self._shutdown_stopped or (task is not None and not task[1].done()):
            await self.stop_motion(trigger="shutdown", reason="daemon stopping")
        await self.drain()
        tasks = [t for _, t in ([self._measure_task] if self._measure_task else [])]
        tasks += [*self.fits.tasks(), *self.compensator.runs.unfinished(),
                  *self.checks.unfinished(),
                  *([self._storage_task] if self._storage_task is not None else [])]
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        with contextlib.suppress(TimeoutError):  # a report being rewritten gets finished
            await self.reports.settled(10.0)
        await self.reports.close()
        self.fitter.shutdown()
        await self.hub.close()
        self.events.close()
        self.store.close()

    # --- queries ---------------------------------------------------------------------------
    def health(self) -> dict[str, Any]:
        """Daemon status: version, uptime, drivers, active work."""
        return {
            "status": "ok" if self.store.fault is None else "degraded",
            "storage": self.store.fault or "ok",
            "unsaved_states": self.store.pending,
            "version": __version__,
            "uptime_s": round(time.time() - self._started, 3),
            "robot": self.robot.name,
            "drivers": self.hub.info(),
            "measuring": self.measuring(),
            "fitting": self.fits.running(),
            "config_digest": self._digest,
        }

    def status(self, cid: str) -> dict[str, Any]:
        """Campaign status with fits and state history."""
        rec = self.store.campaign(cid)
        out = rec.model_dump(mode="json", exclude_unset=True)
        out["fits"] = self.store.fits(cid)
        out["transitions"] = self.store.transitions(cid)
        out["pose_overhead_s"] = self._overhead()
        out["files"] = str(self._campaign_dir(cid))
        out.update(self.compensator.campaign_status(cid))
        started = self.fits.started(cid) if rec.state == S.MEASURED else None
        out["fitting"] = None if started is None else {
            "models": builtins.list(self.config.fit.models), "started": started[0],
            "elapsed_s": round(time.monotonic() - started[1], 1)}
        out["controller_calibration"] = _fingerprint.campaign_calibration(self.store, cid)
        out["report"] = self.fits.report_state(cid)
        return out

    # below this method `list` names it inside the class: annotations use builtins.list
    def list(self) -> list[dict[str, Any]]:
        """Every campaign, oldest first (a pushed one with its table's state now)."""
        pushed = self.compensator.pushed_campaigns()
        out = []
        for r in self.store.campaigns():
            d = r.model_dump(mode="json", exclude_unset=True)
            if r.id in pushed:
                d["push_key"], d["compensation_state"] = pushed[r.id]
            out.append(d)
        return out

    def measurements(self, cid: str) -> builtins.list[Measurement]:
        """Stored measurements of a campaign."""
        self.store.campaign(cid)
        return self.store.measurements(cid)

    def _overhead(self) -> float | None:
        if not self.pose_times:
            return None
        return round(float(np.median(self.pose_times)), 5)

    def _campaign_dir(self, cid: str) -> Path:
        return self.config.data_dir / "campaigns" / cid

    # --- campaign operations -----------------------------------------------------------------
    async def preflight(self) -> dict[str, str]:
        """Connect robot and tracker before anything is stored or moved
        (:func:`~robocal.daemon.creating.preflight`: ConnectFailed names the one that fails)."""
        return await creating.preflight(self.hub, self.config)

    async def create(self, plan: Mapping[str, Any] | str | CampaignPlan, *, actor: str,
                     name: str | None = None, start: bool = True,
                     measure_only: bool = False, parent: str | None = None
                     ) -> dict[str, Any]:
        """Create a campaign from a plan (validated against limits) and, by default, start it.

        Raises
        ------
        ConfigError
            The plan is malformed, for another robot, or has a pose outside the limits.
        CampaignError
            ``start`` while another campaign is measuring.
        """
        doc = await creating.checked_plan(plan, self.robot, self.config)
        if start:
            self.ensure_idle()
            await self.preflight()
        rec = self.store.create_campaign(
            name=name or f"campaign {time.strftime('%Y-%m-%d %H:%M')}", robot=self.robot.name,
            poses=doc.poses, plan_json=doc.text, plan_digest=doc.digest,
            config_digest=self._digest, actor=actor, measure_only=measure_only, parent=parent)
        self.events.emit("state", rec.id, state=rec.state.value, reason="created",
                         poses_measured=0, poses_total=rec.poses_total)
        _log.info("campaign created", campaign=rec.id, poses=rec.poses_total, actor=actor)
        if start:
            return await self.start_campaign(rec.id, actor=actor)
        return self.status(rec.id)

    def measuring(self) -> str | None:
        """The campaign measuring now, or None."""
        task = self._measure_task
        return task[0] if task is not None and not task[1].done() else None

    def ensure_idle(self, cid: str | None = None) -> None:
        """Raise CampaignError naming the campaign measuring now, unless none or ``cid``."""
        other = self.measuring()
        if other is not None and other != cid:
            parent = self.store.campaign(other).verifies
            if parent is not None:  # not a campaign the operator started: say what it is
                raise CampaignError(f"the robot is re-measuring the targets of push or "
                                    f"rollback {parent} (run {other}); wait for it, or "
                                    "roll back / push again, which stops it")
            raise CampaignError(f"campaign {other} is measuring; pause or abort it first")

    def transition(self, cid: str, to: CampaignState, *, actor: str, reason: str = "",
                   only_from: Iterable[CampaignState] | None = None,
                   selected_model: str | None = None,
                   audit: tuple[str, dict[str, Any]] | None = None) -> CampaignSummary:
        """Move ``cid`` to ``to`` in the store, announce it and log it."""
        rec = self.store.transition(cid, to, actor=actor, reason=reason,
                                    only_from=None if only_from is None else list(only_from),
                                    selected_model=selected_model, audit=audit)
        self.events.emit("state", cid, state=rec.state.value, reason=reason,
                         poses_measured=rec.poses_measured, poses_total=rec.poses_total)
        _log.info("campaign state", campaign=cid, state=rec.state.value, reason=reason,
                  actor=actor)
        return rec

    async def start_campaign(self, cid: str, *, actor: str) -> dict[str, Any]:
        """``created -> running``."""
        self.ensure_idle(cid)
        await _fingerprint.record_campaign_start(self.hub, self.store, cid, actor=actor)
        self.transition(cid, S.RUNNING, actor=actor, reason="started",
                        only_from=[S.CREATED])
        self.spawn_measure(cid)
        return self.status(cid)

    async def pause(self, cid: str, *, actor: str, reason: str = "") -> dict[str, Any]:
        """``running -> paused``, stopping the robot at once (not after the pose in progress).

        The unfinished pose keeps nothing; resume moves to it again and measures it.
        """
        why = reason or "paused by operator"
        self.transition(cid, S.PAUSED, actor=actor, reason=why)
        await self.stop_motion(trigger="pause", reason=why, actor=actor, cid=cid)
        return self.status(cid)

    async def stop_motion(self, *, trigger: str, reason: str, actor: str = "daemon",
                          cid: str | None = None) -> bool:
        """Halt the robot now: cancel the measuring task (of ``cid``, or whichever runs) and
        call the robot driver's ``stop()``; logged and audited as ``motion.stop``.

        Returns False when the controller could not confirm the halt.
        """
        if trigger == "shutdown":
            self._shutdown_stopped = True
        task = self._measure_task
        running = task is not None and not task[1].done() and (cid is None or task[0] == cid)
        if task is not None and running:
            task[1].cancel()
        campaign = task[0] if task is not None and running else cid
        ok = await halt_motion(self.hub, self.store, campaign=campaign, actor=actor,
                               trigger=trigger, reason=reason, audit_idle=running)
        if task is not None and running:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(task[1], 10.0)
        return ok

    async def resume(self, cid: str, *, actor: str) -> dict[str, Any]:
        """``paused | faulted -> running``: continue at the first unmeasured pose."""
        rec = self.store.campaign(cid)
        if rec.state not in (S.PAUSED, S.FAULTED):
            raise InvalidTransition(rec.state.value, S.RUNNING.value,
                                    "only paused or faulted campaigns resume")
        task = self._measure_task
        if task is not None and task[0] == cid and not task[1].done():
            # pause() cancelled the executor; let it finish unwinding (bounded).
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(asyncio.shield(task[1]),
                                       self.config.measurement.move_timeout_s)
        self.ensure_idle(cid)
        self.transition(cid, S.RUNNING, actor=actor, reason="resumed by operator")
        self.spawn_measure(cid)
        return self.status(cid)

    async def abort(self, cid: str, *, actor: str, reason: str = "") -> dict[str, Any]:
        """Abort from any non-final state (state and audit entry in one transaction); motion
        and fitting for it stop."""
        why = reason or "aborted by operator"
        task = self._measure_task
        if task is not None and task[0] == cid and not task[1].done():
            # Measuring: the robot stops at once. No push or rollback runs while a campaign
            # measures (both need the robot idle), so there is nothing to wait for.
            self.transition(cid, S.ABORTED, actor=actor, reason=why,
                            audit=("campaign.abort", {"reason": reason}))
            await self.stop_motion(trigger="abort", reason=why, actor=actor, cid=cid)
            await self.hub.reset("campaign aborted")
        else:
            # A push of this campaign may be writing: the abort waits until the table is
            # read back and journaled (or undone), then applies to what is true by then.
            async with self.compensator.lock:
                if self.store.campaign(cid).state == S.PUSHED:
                    raise InvalidTransition(
                        S.PUSHED.value, S.ABORTED.value,
                        "its table was pushed before the abort; robocal compensation "
                        "rollback removes it")
                self.transition(cid, S.ABORTED, actor=actor, reason=why,
                                audit=("campaign.abort", {"reason": reason}))
        self.fits.cancel(cid)
        return self.status(cid)

    async def approve(self, cid: str, *, actor: str, model: str | None = None
                      ) -> dict[str, Any]:
        """``fitted -> approved``, optionally choosing another fitted model to push.

        The state, the chosen model and the audit entry are one transaction.
        """
        rec = self.store.campaign(cid)
        if rec.state == S.MEASURED and cid in self.fits:
            raise CampaignError(f"the fit of campaign {cid} is still running; approve when it "
                                f"ends ('robocal campaign watch {cid}' waits for it)")
        chosen = model or rec.selected_model
        fits = self.store.fits(cid)
        if chosen is None or chosen not in fits or self.store.model_json(cid, chosen) is None:
            raise CampaignError(f"model {chosen!r} was not fitted in campaign {cid} "
                                f"(fitted: {', '.join(fits) or 'none'})")
        pushing.fault_point("approve:before-commit")
        self.transition(cid, S.APPROVED, actor=actor, reason=f"model {chosen} approved",
                        selected_model=chosen,
                        audit=("campaign.approve", {"model": chosen,
                                                    "model_id": fits[chosen].get("model_id")}))
        pushing.fault_point("approve:after-commit")
        self.reports.refresh()
        return self.status(cid)

    # --- measuring and fitting tasks -----------------------------------------------------------
    def spawn_measure(self, cid: str) -> None:
        """Start measuring ``cid`` (state ``running``) unless the store cannot write: then the
        campaign pauses with the reason before anything moves (start, resume, restart)."""
        fault = self.store.probe()
        if fault is not None:
            storage_faults.pause_campaign(
                self.store, self.transition, cid,
                StorageError(f"the store cannot write ({fault}); nothing moved"))
            return
        task = asyncio.create_task(self._measure(cid), name=f"measure-{cid}")
        self._measure_task = (cid, task)

    async def _measure(self, cid: str) -> None:
        runner = CampaignRunner(store=self.store, hub=self.hub, events=self.events,
                                config=self.config, robot=self.robot,
                                reference=self.fits.reference_model(cid), clock=self.clock)
        try:
            state = await runner.run(cid)
        except asyncio.CancelledError:
            raise
        except StorageError as err:
            storage_faults.pause_campaign(self.store, self.transition, cid, err)
            return
        except Exception:  # the runner faults campaigns itself; this is a last resort
            _log.exception("measuring task failed", campaign=cid)
            return
        finally:
            self.pose_times.extend(runner.pose_times)
            del self.pose_times[:-1000]
        if state == S.MEASURED and not self.store.campaign(cid).measure_only:
            self.fits.spawn(cid)

    async def wait(self, cid: str, states: Iterable[CampaignState | str], *,
                   timeout: float, report: bool = True) -> dict[str, Any]:
        """Wait until the campaign is in one of ``states`` (or a final state), and with
        ``report`` until the report of its fit is written too (it renders after the fit is
        stored); TimeoutError if it does not get there within ``timeout`` seconds."""
        wanted = {CampaignState(s) for s in states} | set(FINAL)
        # woken by state events only (not by every pose); the 0.5 s re-check bounds the rest
        async with asyncio.timeout(timeout), self.events.subscribe(("state",)) as q:
            while True:
                if self.store.state(cid) in wanted:
                    if report:
                        await self.fits.report_settled(cid, timeout)
                    return self.status(cid)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(0.5):
                        if await q.get() is None:
                            raise CampaignError("the service stopped")

    # --- compensation: the component beside the service (robocal.daemon.compensating) ----------
    def _entry(self, table_id: int) -> pushing.Entry:
        """A stored table or controller snapshot."""
        return self.compensator.entry(table_id)

    def _verifying(self) -> str | None:
        """The verification run measuring now (a child of a push), or None."""
        return self.compensator.runs.verifying()

    def build_push_table(self, cid: str) -> tuple[CompensationTable, dict[str, Any]]:
        """The table a push of ``cid`` would write, and its description (nothing written)."""
        return self.compensator.build_push_table(cid)

    async def push(self, cid: str, *, actor: str, force: bool = False, key: str | None = None,
                   reason: str = "") -> dict[str, Any]:
        """Build, check, journal, write and read back the approved model's table, then
        measure its targets again (:meth:`CompensationManager.push
        <robocal.daemon.compensating.CompensationManager.push>` says what it raises)."""
        return await self.compensator.push(cid, actor=actor, force=force, key=key,
                                           reason=reason)

    async def reconcile(self) -> builtins.list[JournalRow]:
        """Settle journal entries left ``intended`` by a crash, by reading the controller."""
        return await self.compensator.reconcile()

    async def rollback(self, *, actor: str, reason: str = "", key: str | None = None
                       ) -> dict[str, Any]:
        """Restore the table active before the current one (or the controller's original
        values), journaled like a push (:meth:`CompensationManager.rollback
        <robocal.daemon.compensating.CompensationManager.rollback>`)."""
        return await self.compensator.rollback(actor=actor, reason=reason, key=key)

    async def wait_verification(self, key: str, *, timeout: float) -> dict[str, Any] | None:
        """Wait (at most ``timeout`` s) for the verification run of ``key``; return it."""
        return await self.compensator.runs.wait(key, timeout=timeout)

    def report_records(self) -> dict[str, dict[str, Any]]:
        """Campaign id -> its report's Compensation section (approval, pushes, checks)."""
        return self.checks.report_records(self.compensator.report_records())

    def campaign_compensation(self, cid: str) -> builtins.list[dict[str, Any]]:
        """The pushes of ``cid``: journal state, table description, verification run."""
        return self.compensator.campaign_compensation(cid)

    def compensation(self) -> dict[str, Any]:
        """The active table (described) and the push history with verification runs."""
        return self.compensator.compensation()

    async def report_file(self, cid: str, name: str) -> Path | None:
        """The report file ``name`` (``report.html``, ``report.json``) once the fit's report
        is rendered (≤ 60 s) and a rewrite pending after an action ended (≤ 30 s), or None."""
        self.store.campaign(cid)
        with contextlib.suppress(TimeoutError):
            await self.fits.report_settled(cid, 60.0)   # rendered after the fit
            await self.reports.settled(30.0)
        path = self._campaign_dir(cid) / name
        return path if path.is_file() else None

    def audit(self, *, limit: int = 1000) -> builtins.list[dict[str, Any]]:
        """The audit log (most recent ``limit`` entries)."""
        return self.store.audit_log(limit=limit)

    def fitted_model(self, cid: str, model: str | None = None) -> CalibratedModel:
        """A fitted model of a campaign (default: the selected one); IdentificationError if
        that model was not fitted."""
        return self.fits.model(cid, model)
