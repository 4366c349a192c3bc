"""The daemon's service: a plain async facade over store, drivers, executor, fits and pushes.

The HTTP API is a thin shell over :class:`CalibrationService`; tests and ``robocal demo`` use it
in-process. Methods take an ``actor`` (who asked) that goes into the transitions and the audit
log. One campaign measures at a time (the robot is one); fits run in a worker while the next
campaign measures.

On :meth:`start`, campaigns left ``running`` by a crash resume at their first unmeasured pose,
and ``measured`` ones are fitted again.
"""

from __future__ import annotations

import asyncio
import builtins
import contextlib
import math
import sqlite3
import time
from collections.abc import Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from robocal import __version__
from robocal._core.clock import SYSTEM_CLOCK, Clock
from robocal._core.files import private_dir
from robocal.compensation import CompensationTable
from robocal.daemon import _fingerprint, pushing
from robocal.daemon._journal import PushJournal
from robocal.daemon._plan import PlanDoc, parse_plan, unsafe_moves
from robocal.daemon._reports import ReportKeeper
from robocal.daemon.campaign import FINAL, CampaignState
from robocal.daemon.compensating import CompensationManager
from robocal.daemon.config import AppConfig, config_digest
from robocal.daemon.engine import CampaignRunner, halt_motion, limits_with_margin
from robocal.daemon.events import EventBus
from robocal.daemon.fitting import FitRunner, build_fit_job, fit_options, load_model, sign_fits
from robocal.daemon.hub import DriverHub
from robocal.daemon.store import CampaignRecord, MeasurementRow, Store, now_iso
from robocal.drivers import ControllerSnapshot, check_joint_target
from robocal.errors import (
    CampaignError,
    ConfigError,
    ConnectFailed,
    DriverError,
    IdentificationError,
    InvalidTransition,
    LimitViolation,
    ProtocolError,
    RobocalError,
    StorageError,
)
from robocal.kinematics import CalibratedModel, RobotDescription, load_robot
from robocal.planning import load_cell

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
        self._fit_tasks: dict[str, asyncio.Task[None]] = {}
        self._fit_started: dict[str, tuple[str, float]] = {}  # ISO time, monotonic s
        self._storage_task: asyncio.Task[None] | None = None
        self.journal = PushJournal(self.store)
        self.reports = ReportKeeper(self.report_records, self._campaign_dir, self.events)
        self.compensator = CompensationManager(
            config=config, robot=self.robot, store=self.store, hub=self.hub,
            journal=self.journal, events=self.events, reports=self.reports, campaigns=self,
            secret=self._secret)
        self._started = time.time()
        self.pose_times: list[float] = []
        self._shutdown_stopped = False

    # --- lifecycle -------------------------------------------------------------------------
    async def start(self, *, connect: bool = True) -> None:
        """Open the store, connect the drivers (failure is logged), resume campaigns."""
        private_dir(self.config.data_dir)
        self.store.open()
        self.journal.ensure_schema()
        self.hub.validate()
        fit_options(self.config.fit.options)
        # after the checks above, so a start refused by them leaves no task behind
        self._storage_task = asyncio.create_task(self._storage_watch(), name="storage-watch")
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
                self._spawn_fit(rec.id)
        await self.compensator.resume()
        self.reports.refresh()

    async def drain(self, timeout: float = 30.0) -> None:
        """Refuse new pushes and rollbacks and wait (at most ``timeout`` s) for the one in
        progress to be read back and journaled, so shutdown never cuts a write in half.

        A write still running after ``timeout`` stays ``intended`` in the journal and is
        reconciled on the next start.
        """
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
        tasks += list(self._fit_tasks.values())
        tasks += self.compensator.runs.unfinished()
        if self._storage_task is not None:
            tasks.append(self._storage_task)
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
            "fitting": sorted(self._fit_tasks),
            "config_digest": self._digest,
        }

    def status(self, cid: str) -> dict[str, Any]:
        """Campaign status with fits and state history."""
        rec = self.store.campaign(cid)
        out = rec.to_json()
        out["fits"] = self.store.fits(cid)
        out["transitions"] = self.store.transitions(cid)
        out["pose_overhead_s"] = self._overhead()
        out["files"] = str(self._campaign_dir(cid))
        out.update(self.compensator.campaign_status(cid))
        started = (self._fit_started.get(cid)
                   if cid in self._fit_tasks and rec.state == S.MEASURED else None)
        out["fitting"] = None if started is None else {
            "models": builtins.list(self.config.fit.models), "started": started[0],
            "elapsed_s": round(time.monotonic() - started[1], 1)}
        out["controller_calibration"] = _fingerprint.campaign_calibration(self.store, cid)
        return out

    # below this method `list` names it inside the class: annotations use builtins.list
    def list(self) -> list[dict[str, Any]]:
        """Every campaign, oldest first (a pushed one with its table's state now)."""
        pushed = self.compensator.pushed_campaigns()
        out = []
        for r in self.store.campaigns():
            d = r.to_json()
            if r.id in pushed:
                d["push_key"], d["compensation_state"] = pushed[r.id]
            out.append(d)
        return out

    def push_states(self) -> dict[str, str]:
        """Journal key of every completed push -> its table now: ``active`` (on the
        controller), ``superseded`` (a later push is on top; a rollback would bring it back)
        or ``rolled back``. The one source status, list, the API and the report read."""
        return self.compensator.push_states()

    def push_fates(self) -> dict[str, dict[str, str | None]]:
        """:meth:`push_states` with what made it so: ``superseded_by`` (key of the push on
        top of it), ``rolled_back_by`` (key of the rollback) and ``rolled_back_at``."""
        return self.compensator.push_fates()

    def measurements(self, cid: str) -> builtins.list[MeasurementRow]:
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
    def _check_plan(self, plan: PlanDoc) -> None:
        if plan.robot and plan.robot not in (self.robot.name, self.config.robot_description):
            names = {self.robot.name, Path(self.config.robot_description).stem}
            if plan.robot not in names:
                raise ConfigError(f"plan is for robot {plan.robot!r}, the daemon drives "
                                  f"{self.robot.name!r}", source="plan", key="robot")
        limits = limits_with_margin(self.robot, self.config.limits.joint_margin_deg)
        for p in plan.poses:
            try:
                check_joint_target([math.radians(v) for v in p.q_deg], limits, kind="plan")
            except LimitViolation as err:
                raise ConfigError(f"pose {p.idx}: {err} (joint margin "
                                  f"{self.config.limits.joint_margin_deg} deg)",
                                  source="plan", key=f"poses[{p.idx}]") from err
        # Motion safety is recomputed for every move (swept path: floor, keep-out boxes,
        # self-collision) in the daemon's cell, else the plan's; the plan's flags are ignored.
        cell = load_cell(self.config.cell) if self.config.cell else plan.cell
        if cell is None:
            return
        unsafe = unsafe_moves(plan, self.robot, cell, limits)
        if unsafe:
            _log.warning("plan refused: unsafe moves", count=len(unsafe), cell=cell.name,
                         poses=[u.index for u in unsafe])
            raise ConfigError(
                f"{len(unsafe)} unsafe move(s) in cell {cell.name!r}, nothing started: "
                + "; ".join(u.describe() for u in unsafe), source="plan",
                key=f"poses[{unsafe[0].index}]")

    async def preflight(self) -> dict[str, str]:
        """Connect to the robot and the tracker before anything is stored or moved.

        Raises
        ------
        ConnectFailed
            Naming the device that does not answer and why; nothing was created.
        """
        out: dict[str, str] = {}
        for what, cfg, connect in (("robot", self.config.robot, self.hub.robot),
                                   ("tracker", self.config.tracker, self.hub.tracker)):
            try:
                await connect()
            except (DriverError, ProtocolError, OSError, TimeoutError) as err:
                await self.hub.reset(f"pre-flight: {what} unreachable")
                raise ConnectFailed(
                    f"the {what} ({cfg.kind}) does not answer: {err}. Nothing was started; "
                    f"check that it is on and reachable, then try again") from err
            out[what] = cfg.kind
        return out

    async def create(self, plan: Mapping[str, Any] | str | PlanDoc, *, actor: str,
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
        # Validation is pure computation: off the event loop, which keeps serving meanwhile.
        doc = plan if isinstance(plan, PlanDoc) else await asyncio.to_thread(parse_plan, plan)
        # the swept-path check takes a while on long plans: off the event loop, in a thread
        # that ends with it
        with ThreadPoolExecutor(1, thread_name_prefix="plan-check") as pool:
            await asyncio.get_running_loop().run_in_executor(pool, self._check_plan, doc)
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
        """Refuse while a campaign other than ``cid`` measures (the robot is one).

        Raises
        ------
        CampaignError
            Naming it (and, for a verification run, the push it re-measures).
        """
        if self._measure_task is not None and not self._measure_task[1].done():
            other = self._measure_task[0]
            if other != cid:
                parent = self.store.campaign(other).parent
                if parent is not None:  # not a campaign the operator started: say what it is
                    raise CampaignError(f"the robot is re-measuring the targets of push or "
                                        f"rollback {parent} (run {other}); wait for it, or "
                                        "roll back / push again, which stops it")
                raise CampaignError(f"campaign {other} is measuring; pause or abort it first")

    def transition(self, cid: str, to: CampaignState, *, actor: str, reason: str = "",
                    only_from: Iterable[CampaignState] | None = None,
                    selected_model: str | None = None,
                    audit: tuple[str, dict[str, Any]] | None = None) -> CampaignRecord:
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
        fit = self._fit_tasks.get(cid)
        if fit is not None:
            fit.cancel()
        return self.status(cid)

    async def approve(self, cid: str, *, actor: str, model: str | None = None
                      ) -> dict[str, Any]:
        """``fitted -> approved``, optionally choosing another fitted model to push.

        The state, the chosen model and the audit entry are one transaction.
        """
        rec = self.store.campaign(cid)
        if rec.state == S.MEASURED and cid in self._fit_tasks:
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
    def _reference_model(self, exclude: str) -> CalibratedModel | None:
        """The model of the last pushed campaign, used to predict readings."""
        for rec in reversed(self.store.campaigns(states=[S.PUSHED])):
            if rec.id == exclude or not rec.selected_model:
                continue
            text = self.store.model_json(rec.id, rec.selected_model)
            if text:
                with contextlib.suppress(RobocalError, ValueError, KeyError):
                    return load_model(text, source=f"campaign {rec.id}",
                                      secret=self._secret, nominal=self.robot)
        return None

    def spawn_measure(self, cid: str) -> None:
        """Start measuring ``cid`` (state ``running``) unless the store cannot write: then the
        campaign pauses with the reason before anything moves (start, resume, restart)."""
        fault = self.store.probe()
        if fault is not None:
            self._storage_pause(cid, StorageError(f"the store cannot write ({fault}); "
                                                  "nothing moved"))
            return
        task = asyncio.create_task(self._measure(cid), name=f"measure-{cid}")
        self._measure_task = (cid, task)

    async def _measure(self, cid: str) -> None:
        runner = CampaignRunner(store=self.store, hub=self.hub, events=self.events,
                                config=self.config, robot=self.robot,
                                reference=self._reference_model(cid), clock=self.clock)
        try:
            state = await runner.run(cid)
        except asyncio.CancelledError:
            raise
        except StorageError as err:
            self._storage_pause(cid, err)
            return
        except Exception:  # the runner faults campaigns itself; this is a last resort
            _log.exception("measuring task failed", campaign=cid)
            return
        finally:
            self.pose_times.extend(runner.pose_times)
            del self.pose_times[:-1000]
        if state == S.MEASURED and not self.store.campaign(cid).measure_only:
            self._spawn_fit(cid)

    def _storage_pause(self, cid: str, err: StorageError) -> None:
        """Pause a measuring campaign whose data cannot be written; held in memory (and
        shown) until the store can write again, then persisted by :meth:`_storage_watch`."""
        reason = f"storage fault: {err}"
        _log.error("campaign paused: the store cannot write", campaign=cid, error=str(err))
        try:
            if self.store.campaign(cid).state == S.RUNNING:
                self.transition(cid, S.PAUSED, actor="daemon", reason=reason)
        except (RobocalError, sqlite3.Error) as again:
            _log.error("storage fault: campaign state unknown", campaign=cid, error=str(again))

    async def _fit_guarded(self, cid: str) -> None:
        try:
            await self._fit(cid)
        except StorageError as err:
            # Never stuck in "measured": faulted (held in memory until saved); resume fits again.
            _log.error("fit not saved: the store cannot write", campaign=cid, error=str(err))
            with contextlib.suppress(RobocalError, sqlite3.Error):
                self._fault_fit(cid, f"storage fault while saving the fit: {err}")

    async def _storage_watch(self, period_s: float = 1.0) -> None:
        """Write states held in memory by a storage fault as soon as the store can."""
        while True:
            await asyncio.sleep(period_s)
            if self.store.pending and self.store.flush_pending():
                _log.info("storage recovered: held campaign states saved")

    def _spawn_fit(self, cid: str) -> None:
        if cid in self._fit_tasks and not self._fit_tasks[cid].done():
            return
        task = asyncio.create_task(self._fit_guarded(cid), name=f"fit-{cid}")
        self._fit_tasks[cid] = task
        self._fit_started[cid] = (now_iso(), time.monotonic())
        task.add_done_callback(lambda _t: (self._fit_tasks.pop(cid, None),
                                           self._fit_started.pop(cid, None)))

    def _measurement_log(self, cid: str, rows: builtins.list[MeasurementRow]
                         ) -> dict[str, Any]:
        retries = sum(max(0, r.attempts - 1) for r in rows)
        weather = [r.weather for r in rows if r.weather][-1:]
        planned = sum(1 for p in self.store.poses(cid) if p.measure)
        return {"planned": planned, "measured": len(rows), "retries": retries,
                "beam_losses": sum(r.beam_losses for r in rows),
                "tracker": self.config.tracker.kind, "controller": self.config.robot.kind,
                "weather": weather[0] if weather else {}}

    async def _fit(self, cid: str) -> None:
        log = _log.bind(campaign=cid)
        rows = self.store.measurements(cid)
        out_dir = self._campaign_dir(cid)
        job = build_fit_job(campaign=cid, robot=self.robot, rows=rows,
                            models=self.config.fit.models, cpa=self.config.fit.cpa,
                            out_dir=out_dir, report=self.config.fit.report,
                            log=self._measurement_log(cid, rows),
                            options=self.config.fit.options,
                            acceptance=self.config.fit.acceptance,
                            model_data=_fingerprint.model_data(self.store, cid))
        if self.config.fit.select != "best":
            job["selected"] = self.config.fit.select
        self.events.emit("fit", cid, phase="started", models=list(self.config.fit.models))
        log.info("fitting", models=list(self.config.fit.models), poses=len(rows))
        try:
            result = await self.fitter.run(job)
        except asyncio.CancelledError:
            raise
        except (RobocalError, OSError, ValueError, TypeError) as err:
            reason = f"fit failed: {type(err).__name__}: {err}"
            log.warning("fit failed", error=reason)
            self._fault_fit(cid, reason)
            return
        except Exception as err:  # never let a fit bug kill the daemon
            log.exception("fit crashed")
            self._fault_fit(cid, f"fit crashed: {type(err).__name__}: {err}")
            return
        fits = {name: (summ, mj) for name, (summ, mj) in result["fits"].items()}
        for name, msg in result["errors"].items():
            fits.setdefault(name, ({"model": name, "error": msg}, None))
        fits = sign_fits(fits, self._secret, self.robot)
        self.store.save_fits(cid, fits)
        select = self.config.fit.select
        chosen = result.get("selected_hint") if select == "best" else select
        if chosen not in result["fits"] or fits[str(chosen)][1] is None:
            errors = "; ".join(f"{k}: {v}" for k, v in result["errors"].items())
            self._fault_fit(cid, f"model {chosen!r} could not be fitted ({errors or 'no model'})")
            return
        self.store.set_selected_model(cid, chosen)
        report = result.get("report")
        if self.store.campaign(cid).state != S.MEASURED:
            return  # aborted while fitting
        self.transition(cid, S.FITTED, actor="daemon",
                         reason=f"fitted {', '.join(result['fits'])}; proposed {chosen}")
        summary = result["fits"][chosen][0].get("validation") or {}
        self.events.emit("fit", cid, phase="done", selected=chosen,
                         validation_rms_mm=summary.get("rms_mm"), report=report,
                         seconds=result.get("seconds"))
        log.info("fitted", selected=chosen, seconds=result.get("seconds"), report=report)

    def _fault_fit(self, cid: str, reason: str) -> None:
        if self.store.campaign(cid).state == S.MEASURED:
            self.transition(cid, S.FAULTED, actor="daemon", reason=reason)
        self.events.emit("fit", cid, phase="failed", reason=reason)

    async def wait(self, cid: str, states: Iterable[CampaignState | str], *,
                   timeout: float) -> dict[str, Any]:
        """Wait until the campaign is in one of ``states`` (or a final state).

        Raises
        ------
        TimeoutError
            If it does not get there within ``timeout`` seconds.
        """
        wanted = {CampaignState(s) for s in states} | set(FINAL)
        async with asyncio.timeout(timeout), self.events.subscribe() as q:
            while True:
                if self.store.campaign(cid).state in wanted:
                    return self.status(cid)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(0.5):
                        if await q.get() is None:
                            raise CampaignError("the service stopped")

    # --- compensation: the component beside the service (robocal.daemon.compensating) ----------
    def _entry(self, table_id: int) -> CompensationTable | ControllerSnapshot:
        """A stored table or controller snapshot."""
        return self.compensator.entry(table_id)

    def _verifying(self) -> str | None:
        """The verification run measuring now (a child of a push), or None."""
        return self.compensator.runs.verifying()

    def build_push_table(self, cid: str) -> tuple[CompensationTable, dict[str, Any]]:
        """The table a push of ``cid`` would write, and its description (nothing written).

        Raises
        ------
        CompensationError
            If the campaign has no approved model or the table cannot be built.
        """
        return self.compensator.build_push_table(cid)

    async def push(self, cid: str, *, actor: str, force: bool = False, key: str | None = None,
                   reason: str = "") -> dict[str, Any]:
        """Build, check, journal, write and read back the approved model's table.

        The push is journaled as intended (idempotency ``key``, default a new one) before the
        controller is written and completed after the read-back, in one transaction with the
        history, the audit entry and ``approved -> pushed``. A ``key`` already completed
        returns the status without writing again. Then the pushed targets are measured
        again (:meth:`wait_verification`).

        Raises
        ------
        ApprovalRequired
            If the campaign is not ``approved``.
        CompensationError
            If the table exceeds the bounds, does not clearly improve on the nominal
            residual (unless ``force``), or the driver cannot store it (nothing written).
        VerificationMismatch
            If the read-back differs (the previous values are put back; the campaign stays
            ``approved``; see the audit log).
        """
        return await self.compensator.push(cid, actor=actor, force=force, key=key,
                                           reason=reason)

    async def reconcile(self) -> builtins.list[dict[str, Any]]:
        """Settle journal entries left ``intended`` by a crash, by reading the controller."""
        return await self.compensator.reconcile()

    async def rollback(self, *, actor: str, reason: str = "", key: str | None = None
                       ) -> dict[str, Any]:
        """Restore the table (or the controller's original values) active before the current
        one: journaled like a push, written, read back, verified, then measured again.

        Raises
        ------
        CompensationError
            If there is no earlier table.
        """
        return await self.compensator.rollback(actor=actor, reason=reason, key=key)

    async def wait_verification(self, key: str, *, timeout: float) -> dict[str, Any] | None:
        """Wait (at most ``timeout`` s) for the verification run of ``key``; return it."""
        return await self.compensator.runs.wait(key, timeout=timeout)

    def report_records(self) -> dict[str, dict[str, Any]]:
        """Campaign id -> what its report's Compensation section shows: its approval and its
        pushes, each with where its table is now (:meth:`push_fates`)."""
        return self.compensator.report_records()

    def campaign_compensation(self, cid: str) -> builtins.list[dict[str, Any]]:
        """The pushes of ``cid``: journal state, table description, verification run."""
        return self.compensator.campaign_compensation(cid)

    def compensation(self) -> dict[str, Any]:
        """The active table (described) and the push history with verification runs."""
        return self.compensator.compensation()

    async def report_file(self, cid: str, name: str) -> Path | None:
        """The campaign's report file ``name`` (``report.html``, ``report.json``) as it is
        once a rewrite pending after an action has ended (at most 30 s); None if absent."""
        self.store.campaign(cid)
        with contextlib.suppress(TimeoutError):
            await self.reports.settled(30.0)
        path = self._campaign_dir(cid) / name
        return path if path.is_file() else None

    def audit(self, *, limit: int = 1000) -> builtins.list[dict[str, Any]]:
        """The audit log (most recent ``limit`` entries)."""
        return self.store.audit_log(limit=limit)

    def fitted_model(self, cid: str, model: str | None = None) -> CalibratedModel:
        """A fitted model of a campaign (default: the selected one).

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
        return load_model(text, source=f"campaign {cid}", secret=self._secret,
                          nominal=self.robot)
