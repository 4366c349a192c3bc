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
from robocal.compensation import CompensationTable, describe_table, improvement_refusal
from robocal.daemon import _fingerprint, pushing
from robocal.daemon._journal import JournalEntry, PushJournal, new_key
from robocal.daemon._plan import PlanDoc, parse_plan, plan_from_poses, unsafe_moves
from robocal.daemon._reports import ReportKeeper
from robocal.daemon.campaign import FINAL, CampaignState
from robocal.daemon.config import AppConfig, config_digest
from robocal.daemon.engine import CampaignRunner, halt_motion, limits_with_margin
from robocal.daemon.events import EventBus
from robocal.daemon.fitting import FitRunner, build_fit_job, fit_options, load_model, sign_fits
from robocal.daemon.hub import DriverHub
from robocal.daemon.store import CampaignRecord, MeasurementRow, Store, now_iso
from robocal.drivers import ControllerSnapshot, check_joint_target
from robocal.errors import (
    ApprovalRequired,
    CampaignError,
    CompensationError,
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
        self._push_lock = asyncio.Lock()
        self._storage_task: asyncio.Task[None] | None = None
        self.journal = PushJournal(self.store)
        self._verify_tasks: dict[str, asyncio.Task[None]] = {}
        self.reports = ReportKeeper(self.report_records, self._campaign_dir, self.events)
        self._started = time.time()
        self.pose_times: list[float] = []
        self._shutdown_stopped = False
        self._closing = False

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
                self._spawn_measure(rec.id)
            elif not rec.measure_only:
                self._spawn_fit(rec.id)
        if self.journal.pending():
            await self.reconcile()
        for key, _ in self.journal.open_verifications():
            self._spawn_verify(key)
        self.reports.refresh()

    async def drain(self, timeout: float = 30.0) -> None:
        """Refuse new pushes and rollbacks and wait (at most ``timeout`` s) for the one in
        progress to be read back and journaled, so shutdown never cuts a write in half.

        A write still running after ``timeout`` stays ``intended`` in the journal and is
        reconciled on the next start.
        """
        self._closing = True
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout), self._push_lock:
                pass

    async def stop(self) -> None:
        """Stop work (campaign states stay as they are, to resume on restart); close all.

        Motion stops first, at once (the driver's ``stop()``), before anything else closes;
        then a push or rollback in progress finishes (:meth:`drain`).
        """
        self._closing = True  # verification runs cut from here on stay open in the journal
        task = self._measure_task
        if not self._shutdown_stopped or (task is not None and not task[1].done()):
            await self.stop_motion(trigger="shutdown", reason="daemon stopping")
        await self.drain()
        tasks = [t for _, t in ([self._measure_task] if self._measure_task else [])]
        tasks += list(self._fit_tasks.values())
        tasks += [t for t in self._verify_tasks.values() if not t.done()]
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
            "measuring": (self._measure_task[0] if self._measure_task is not None
                          and not self._measure_task[1].done() else None),
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
        out["compensation"] = self.campaign_compensation(cid)
        out["push"] = self._push_summary(out["compensation"])
        if out["push"] is not None:
            out["push"].update(self.push_fates().get(out["push"]["key"], {}))
            out["compensation_state"] = out["push"].get("compensation_state")
            out["push_key"] = out["push"]["key"]
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
        states = self.push_states()
        by_campaign = {e.campaign: e.key for e in self.journal.entries() if e.key in states}
        out = []
        for r in self.store.campaigns():
            d = r.to_json()
            if r.id in by_campaign:
                d["push_key"] = by_campaign[r.id]
                d["compensation_state"] = states[d["push_key"]]
            out.append(d)
        return out

    def push_states(self) -> dict[str, str]:
        """Journal key of every completed push -> its table now: ``active`` (on the
        controller), ``superseded`` (a later push is on top; a rollback would bring it back)
        or ``rolled back``. The one source status, list, the API and the report read."""
        return {k: str(f["compensation_state"]) for k, f in self.push_fates().items()}

    def push_fates(self) -> dict[str, dict[str, str | None]]:
        """:meth:`push_states` with what made it so: ``superseded_by`` (key of the push on
        top of it), ``rolled_back_by`` (key of the rollback) and ``rolled_back_at``."""
        stack: builtins.list[str] = []
        out: dict[str, dict[str, str | None]] = {}
        for e in self.journal.entries():
            if e.state != "completed":
                continue
            if e.action == "push":
                stack.append(e.key)
            elif stack:  # a rollback takes the top push off (never the baseline below)
                out[stack.pop()] = {"compensation_state": "rolled back", "superseded_by": None,
                                    "rolled_back_by": e.key, "rolled_back_at": e.finished_at}
        for i, k in enumerate(stack):  # the top one is active, each below it superseded
            above = stack[i + 1] if i + 1 < len(stack) else None
            out[k] = {"compensation_state": "active" if above is None else "superseded",
                      "superseded_by": above, "rolled_back_by": None, "rolled_back_at": None}
        return out

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
            self._ensure_idle()
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

    def _ensure_idle(self, cid: str | None = None) -> None:
        if self._measure_task is not None and not self._measure_task[1].done():
            other = self._measure_task[0]
            if other != cid:
                parent = self.store.campaign(other).parent
                if parent is not None:  # not a campaign the operator started: say what it is
                    raise CampaignError(f"the robot is re-measuring the targets of push or "
                                        f"rollback {parent} (run {other}); wait for it, or "
                                        "roll back / push again, which stops it")
                raise CampaignError(f"campaign {other} is measuring; pause or abort it first")

    def _transition(self, cid: str, to: CampaignState, *, actor: str, reason: str = "",
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
        self._ensure_idle(cid)
        await _fingerprint.record_campaign_start(self.hub, self.store, cid, actor=actor)
        self._transition(cid, S.RUNNING, actor=actor, reason="started",
                         only_from=[S.CREATED])
        self._spawn_measure(cid)
        return self.status(cid)

    async def pause(self, cid: str, *, actor: str, reason: str = "") -> dict[str, Any]:
        """``running -> paused``, stopping the robot at once (not after the pose in progress).

        The unfinished pose keeps nothing; resume moves to it again and measures it.
        """
        why = reason or "paused by operator"
        self._transition(cid, S.PAUSED, actor=actor, reason=why)
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
        self._ensure_idle(cid)
        self._transition(cid, S.RUNNING, actor=actor, reason="resumed by operator")
        self._spawn_measure(cid)
        return self.status(cid)

    async def abort(self, cid: str, *, actor: str, reason: str = "") -> dict[str, Any]:
        """Abort from any non-final state (state and audit entry in one transaction); motion
        and fitting for it stop."""
        why = reason or "aborted by operator"
        task = self._measure_task
        if task is not None and task[0] == cid and not task[1].done():
            # Measuring: the robot stops at once. No push or rollback runs while a campaign
            # measures (both need the robot idle), so there is nothing to wait for.
            self._transition(cid, S.ABORTED, actor=actor, reason=why,
                             audit=("campaign.abort", {"reason": reason}))
            await self.stop_motion(trigger="abort", reason=why, actor=actor, cid=cid)
            await self.hub.reset("campaign aborted")
        else:
            # A push of this campaign may be writing: the abort waits until the table is
            # read back and journaled (or undone), then applies to what is true by then.
            async with self._push_lock:
                if self.store.campaign(cid).state == S.PUSHED:
                    raise InvalidTransition(
                        S.PUSHED.value, S.ABORTED.value,
                        "its table was pushed before the abort; robocal compensation "
                        "rollback removes it")
                self._transition(cid, S.ABORTED, actor=actor, reason=why,
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
        self._transition(cid, S.APPROVED, actor=actor, reason=f"model {chosen} approved",
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

    def _spawn_measure(self, cid: str) -> None:
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
                self._transition(cid, S.PAUSED, actor="daemon", reason=reason)
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
        self._transition(cid, S.FITTED, actor="daemon",
                         reason=f"fitted {', '.join(result['fits'])}; proposed {chosen}")
        summary = result["fits"][chosen][0].get("validation") or {}
        self.events.emit("fit", cid, phase="done", selected=chosen,
                         validation_rms_mm=summary.get("rms_mm"), report=report,
                         seconds=result.get("seconds"))
        log.info("fitted", selected=chosen, seconds=result.get("seconds"), report=report)

    def _fault_fit(self, cid: str, reason: str) -> None:
        if self.store.campaign(cid).state == S.MEASURED:
            self._transition(cid, S.FAULTED, actor="daemon", reason=reason)
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

    # --- compensation --------------------------------------------------------------------------
    def _entry(self, table_id: int) -> CompensationTable | ControllerSnapshot:
        """A stored table or controller snapshot."""
        row = self.store.table(table_id)
        return pushing.parse_entry(str(row["kind"]), str(row["table_json"]))

    def _table(self, table_id: int) -> CompensationTable:
        entry = self._entry(table_id)
        if not isinstance(entry, CompensationTable):
            raise CompensationError(f"stored entry {table_id} is a controller snapshot")
        return entry

    def _program(self, cid: str) -> pushing.Program:
        """The production targets: ``targets_file`` (JOINTS or TARGETS.csv), else the
        campaign's validation poses (else all measured poses)."""
        path = self.config.compensation.targets_file
        if path is not None:
            return pushing.read_program(path, dof=self.robot.dof)
        rows = [p for p in self.store.poses(cid) if p.purpose == "validation"]
        if not rows:
            rows = [p for p in self.store.poses(cid) if p.measure]
        return pushing.Program(np.radians(np.array([p.q_deg for p in rows], dtype=float)))

    def _covered_kinds(self, stack: builtins.list[int]) -> set[str]:
        kinds: set[str] = set()
        for tid in stack:
            entry = self._entry(tid)
            kinds.add(entry.covers if isinstance(entry, ControllerSnapshot) else entry.kind)
        return kinds

    def build_push_table(self, cid: str) -> tuple[CompensationTable, dict[str, Any]]:
        """The table a push of ``cid`` would write, and its description (nothing written).

        Raises
        ------
        CompensationError
            If the campaign has no approved model or the table cannot be built.
        """
        rec = self.store.campaign(cid)
        model = rec.selected_model or ""
        text = self.store.model_json(cid, model)
        if text is None:
            raise CompensationError(f"campaign {cid} has no fitted model {model!r}")
        cal = load_model(text, source=f"campaign {cid}", secret=self._secret,
                         nominal=self.robot)
        kind = self.config.compensation.kind
        program = self._program(cid)
        table = pushing.build_campaign_table(
            cal, kind, targets_q=program.q if kind == "targets" else None,
            targets_p=program.p, targets_R=program.R,
            max_change_deg=self.config.limits.max_joint_correction_deg)
        desc = describe_table(table)
        desc.update(model=model, model_id=cal.model_id,
                    program_q_deg=np.round(np.degrees(program.q), 9).tolist(),
                    target_p_mm=None if program.p is None
                    else np.round(program.p * 1e3, 6).tolist(),
                    coverage=pushing.outside_coverage(cal, program.q, table.kind))
        return table, desc

    async def push(self, cid: str, *, actor: str, force: bool = False, key: str | None = None,
                   reason: str = "") -> dict[str, Any]:
        """Build, check, journal, write and read back the approved model's table.

        The push is journaled as intended (idempotency ``key``, default a new one) before the
        controller is written and completed after the read-back, in one transaction with the
        history, the audit entry and ``approved -> pushed``. A ``key`` already completed
        returns the status without writing again. Then the pushed targets are measured
        again (:meth:`verification`).

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
        if key is not None and await self._retried(key, action="push", campaign=cid):
            return self.status(cid)
        rec = self.store.campaign(cid)
        if rec.state == S.PUSHED:
            raise CampaignError(f"campaign {cid} was already pushed; robocal compensation "
                                "list shows it (a new push needs a new campaign; rollback "
                                "restores the previous table)")
        if rec.state != S.APPROVED:
            raise ApprovalRequired(f"campaign {cid} is {rec.state.value}; compensation is "
                                   "pushed only after an operator approves the fit")
        table, desc = self.build_push_table(cid)
        refusal = improvement_refusal(table, self.config.compensation.max_residual_ratio)
        refusal = refusal or pushing.coverage_refusal(
            desc["coverage"], self.config.compensation.max_outside_coverage)
        summary = {k: desc[k] for k in ("kind", "purpose", "predicted_residual_mm",
                                         "nominal_residual_mm", "model_accuracy_mm", "ratio",
                                         "warnings", "model", "model_id", "coverage")}
        if refusal is not None and not force:
            self.store.audit(actor=actor, action="compensation.push-refused", campaign=cid,
                             checksum=table.checksum, detail={"refusal": refusal, **summary})
            raise CompensationError(f"push refused: {refusal}; an operator may force it "
                                    "(recorded in the audit log)")
        calibration = await _fingerprint.check_push(self.hub, self.store, cid, force=force,
                                                    actor=actor)
        async with self._push_lock:
            self._ensure_open()
            self._ensure_idle(self._verifying())
            await self._reconcile_locked()
            if self.journal.pending():
                raise CompensationError("an earlier push could not be reconciled with the "
                                        "controller yet (is it reachable?); nothing written")
            if self.store.campaign(cid).state != S.APPROVED:
                raise ApprovalRequired(f"campaign {cid} is no longer approved")
            stack = self.store.table_stack()
            previous = self._entry(stack[-1]) if stack else None
            pushing.check_bounds(
                table, self.config.limits, self.robot,
                previous=previous if isinstance(previous, CompensationTable) else None,
                seeds_q_deg=desc["program_q_deg"] if table.kind == "targets" else None)
            # checked and about to write: an earlier push's re-measurement ends here
            await self._stop_verification_run("a new push was asked for")
            key = key or new_key()
            detail = {**summary, "forced": refusal is not None or calibration["forced"],
                      "refusal": refusal, "reason": reason, "controller_calibration": calibration,
                      "program_q_deg": desc["program_q_deg"]}
            try:
                async with self.hub.lock:
                    robot = await self.hub.robot()
                    snap = None
                    if table.kind not in self._covered_kinds(stack):
                        snap = await pushing.take_snapshot(robot, table)
                    pushing.fault_point("push:after-snapshot")
                    self.journal.intend(
                        key=key, action="push", campaign=cid, actor=actor,
                        table=(table.kind, table.checksum, table.model_dump_json()),
                        baseline=None if snap is None else (snap.checksum(),
                                                            snap.model_dump_json()),
                        detail=detail)
                    pushing.fault_point("push:after-intent")
                    try:
                        await pushing.write_and_verify(robot, table)
                    except (RobocalError, OSError) as err:
                        await self._undo(robot, key, actor, f"write failed: {err}")
                        raise
                    pushing.fault_point("push:after-write")
                    self.journal.complete(key, actor=actor)
                    pushing.fault_point("push:after-complete")
            except (RobocalError, OSError) as err:
                await self.hub.reset(f"push failed: {err}")
                raise
        self.events.emit("compensation", cid, action="push", checksum=table.checksum, key=key)
        _log.info("compensation pushed", campaign=cid, key=key, **summary)
        self._spawn_verify(key)
        self.reports.refresh()
        return self.status(cid)

    def _ensure_open(self) -> None:
        if self._closing:
            raise CompensationError("the daemon is stopping; nothing written")

    async def _retried(self, key: str, *, action: str, campaign: str | None) -> bool:
        """True when ``key`` is a completed ``action`` (a retry: answer as the first time);
        False when the key is new.

        Raises
        ------
        CampaignError
            If the key belongs to another action or campaign.
        CompensationError
            If that action was abandoned (nothing of it is on the controller).
        """
        done = self.journal.find(key)
        if done is None:
            return False
        if done.campaign != campaign or done.action != action:
            raise CampaignError(f"idempotency key {key!r} belongs to another action")
        if done.state == "intended":
            await self.reconcile()
            done = self.journal.get(key)
        if done.state == "completed":
            return True
        raise CompensationError(f"{action} {key} was abandoned: {done.outcome}")

    async def _undo(self, robot: object, key: str, actor: str, reason: str,
                    what: str = "failed") -> None:
        """After a failed or unfinished write: put back what the slots held, abandon ``key``.

        Never writes the journaled table again; writes the previous values only when the
        controller holds something else.
        """
        e = self.journal.get(key)
        prior: CompensationTable | ControllerSnapshot | None = None
        if e.action == "push":
            if e.baseline_id is not None:
                prior = self._entry(e.baseline_id)
            else:
                stack = self.store.table_stack()
                prior = self._entry(stack[-1]) if stack else None
        elif e.rolled_back_id is not None:
            prior = self._entry(e.rolled_back_id)
        outcome = reason
        try:
            if prior is not None and not await pushing.holds(robot, prior):
                await pushing.restore(robot, prior)
                outcome += "; the previous values were written back and verified"
            else:
                outcome += "; the controller holds the previous values"
        except (RobocalError, OSError) as err:
            outcome += f"; restoring the previous values failed too: {err}"
        self.journal.abandon(key, actor=actor, reason=outcome, what=what)

    async def reconcile(self) -> builtins.list[dict[str, Any]]:
        """Settle journal entries left ``intended`` by a crash, by reading the controller."""
        async with self._push_lock:
            return await self._reconcile_locked()

    async def _reconcile_locked(self) -> builtins.list[dict[str, Any]]:
        out = []
        for e in self.journal.pending():
            target = self._entry(e.table_id)
            try:
                async with self.hub.lock:
                    robot = await self.hub.robot()
                    if await pushing.holds(robot, target):
                        done = self.journal.complete(
                            e.key, actor=e.actor,
                            outcome="reconciled after a restart: the controller holds it",
                            extra={"reconciled_by": "daemon"})
                        self._spawn_verify(e.key)
                    else:
                        await self._undo(robot, e.key, "daemon",
                                         "interrupted before the write was confirmed",
                                         what="abandoned")
                        done = self.journal.get(e.key)
            except (RobocalError, OSError) as err:
                _log.warning("push journal not reconciled", key=e.key, error=str(err))
                await self.hub.reset(f"reconcile failed: {err}")
                continue
            _log.info("push journal reconciled", key=e.key, state=done.state,
                      outcome=done.outcome)
            self.events.emit("compensation", e.campaign, action=f"{e.action}-reconciled",
                             key=e.key, state=done.state)
            out.append(done.to_json())
        if out:
            self.reports.refresh()
        return out

    async def rollback(self, *, actor: str, reason: str = "", key: str | None = None
                       ) -> dict[str, Any]:
        """Restore the table (or the controller's original values) active before the current
        one: journaled like a push, written, read back, verified, then measured again.

        Raises
        ------
        CompensationError
            If there is no earlier table.
        """
        if key is not None and await self._retried(key, action="rollback", campaign=None):
            return self.compensation()
        async with self._push_lock:
            self._ensure_open()
            await self._stop_verification_run("a rollback was asked for")
            self._ensure_idle()
            await self._reconcile_locked()
            if self.journal.pending():
                raise CompensationError("an earlier push could not be reconciled with the "
                                        "controller yet; nothing written")
            stack = self.store.table_stack()
            if len(stack) < 2:
                raise CompensationError("no earlier compensation table to restore")
            current_id, previous_id = stack[-1], stack[-2]
            entry = self._entry(previous_id)
            if isinstance(entry, CompensationTable):
                entry.verify()
            # Re-measured afterwards: the restored table's own targets, or (restoring the
            # controller's original) the rolled-back table's targets, now uncompensated.
            source_id = previous_id if isinstance(entry, CompensationTable) else current_id
            pushed = [j for j in self.journal.entries()
                      if j.action == "push" and j.table_id == source_id]
            program = pushed[-1].detail.get("program_q_deg") if pushed else None
            model_campaign = self.store.table(source_id)["campaign"]
            key = key or new_key()
            detail = {"reason": reason, "restored_table_id": previous_id,
                      "rolled_back_table_id": current_id, "program_q_deg": program,
                      "model_campaign": model_campaign,
                      "target_p_mm": pushed[-1].detail.get("target_p_mm") if pushed else None,
                      "restores": ("controller original" if isinstance(entry, ControllerSnapshot)
                                   else f"{entry.kind} table")}
            try:
                async with self.hub.lock:
                    robot = await self.hub.robot()
                    self.journal.intend(key=key, action="rollback", campaign=None, actor=actor,
                                        table_id=previous_id, rolled_back_id=current_id,
                                        detail=detail)
                    pushing.fault_point("rollback:after-intent")
                    try:
                        await pushing.restore(robot, entry)
                    except (RobocalError, OSError) as err:
                        await self._undo(robot, key, actor, f"restore failed: {err}")
                        raise
                    pushing.fault_point("rollback:after-write")
                    self.journal.complete(key, actor=actor)
                    pushing.fault_point("rollback:after-complete")
            except (RobocalError, OSError) as err:
                await self.hub.reset(f"rollback failed: {err}")
                raise
        checksum = self.store.table(previous_id)["checksum"]
        self.events.emit("compensation", None, action="rollback", checksum=checksum, key=key)
        self._spawn_verify(key)
        self.reports.refresh()
        return self.compensation()

    # --- verification runs: the pushed targets measured again ----------------------------------
    def _spawn_verify(self, key: str) -> None:
        if key in self._verify_tasks and not self._verify_tasks[key].done():
            return
        task = asyncio.create_task(self._verify(key), name=f"verify-{key}")
        self._verify_tasks[key] = task

    async def wait_verification(self, key: str, *, timeout: float) -> dict[str, Any] | None:
        """Wait (at most ``timeout`` s) for the verification run of ``key``; return it."""
        task = self._verify_tasks.get(key)
        if task is not None:
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(task), timeout)
        return self.journal.verification(key)

    async def _verify(self, key: str) -> None:
        try:
            v = self.journal.verification(key)
            if v is None or v["state"] == "pending":
                started = await self._start_verification(key)
                self.reports.refresh()
                if not started:
                    return
                v = self.journal.verification(key)
            if v is not None and v["state"] == "measuring":
                await self._finish_verification(key)
                self.reports.refresh()
        except asyncio.CancelledError:
            raise
        except Exception as err:  # a verification bug must not take the daemon down
            if self._closing:  # cut by shutdown: still open in the journal, resumed on start
                _log.info("verification interrupted by shutdown", key=key, error=str(err))
                return
            _log.exception("verification failed", key=key)
            with contextlib.suppress(Exception):
                self.journal.set_verification(key, state="failed",
                                              result={"reason": f"{type(err).__name__}: {err}"})
            self.reports.refresh()

    def _verifying(self) -> str | None:
        """The verification run measuring now (a child of a push), or None."""
        task = self._measure_task
        if task is None or task[1].done():
            return None
        return task[0] if self.store.campaign(task[0]).parent is not None else None

    async def _stop_verification_run(self, why: str) -> None:
        """Stop the verification run measuring now, if any (push lock held): a new push or a
        rollback supersedes what it measures, so it ends (``skipped``, saying why) instead of
        making the operator wait or refusing them."""
        task = self._measure_task
        if task is None or task[1].done():
            return
        rec = self.store.campaign(task[0])
        if rec.parent is None:
            return  # an operator's campaign: the caller refuses, naming it
        key = rec.parent
        verifying = self._verify_tasks.get(key)
        if verifying is not None:
            verifying.cancel()
        reason = f"verification stopped: {why}"
        self._transition(rec.id, S.ABORTED, actor="daemon", reason=reason)
        await self.stop_motion(trigger="abort", reason=reason, cid=rec.id)
        if verifying is not None:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(verifying, 10.0)
        self.journal.set_verification(key, state="skipped",
                                      result={"reason": f"stopped before the end: {why}"})
        _log.info("verification run stopped", key=key, campaign=rec.id, reason=why)

    async def _wait_idle(self) -> None:
        """Wait until no campaign measures (the robot is one)."""
        async with self.events.subscribe() as q:
            while self._measure_task is not None and not self._measure_task[1].done():
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(0.5):
                        if await q.get() is None:
                            raise CampaignError("the service stopped")

    async def _run_child(self, vcid: str) -> None:
        """Make a verification run measure: after a restart it is ``running`` without a task
        (never resumed as a campaign of its own) or still ``created``."""
        task = self._measure_task
        if task is not None and task[0] == vcid and not task[1].done():
            return
        state = self.store.campaign(vcid).state
        if state not in (S.CREATED, S.RUNNING):
            return
        await self._wait_idle()
        if self.store.campaign(vcid).state == S.CREATED:
            await self.preflight()
            await self.start_campaign(vcid, actor="daemon")
        elif self.store.campaign(vcid).state == S.RUNNING:
            _log.info("resuming verification run after restart", campaign=vcid)
            self._spawn_measure(vcid)

    async def _start_verification(self, key: str) -> bool:
        e = self.journal.get(key)
        count = self.config.compensation.verify_count
        program = e.detail.get("program_q_deg")
        entry = self._entry(e.table_id)
        skip = None
        if count <= 0:
            skip = "verification disabled (compensation.verify_count = 0)"
        elif not program:
            skip = "no program targets recorded for this push"
        elif isinstance(entry, CompensationTable) and entry.kind == "frames":
            skip = ("a frames table changes the frames Cartesian programs use; measuring "
                    "joint targets again would not test it")
        if skip is not None:
            self.journal.set_verification(key, state="skipped", result={"reason": skip})
            return False
        q_program = np.radians(np.asarray(program, dtype=float))
        q_cmd, compensated = pushing.commanded_joints(entry, q_program)
        rows = ([i for i in range(len(q_program)) if compensated[i]]
                if isinstance(entry, CompensationTable) else list(range(len(q_program))))
        idx = [rows[k] for k in pushing.verification_indices(len(rows), count)]
        q_deg: builtins.list[builtins.list[float]] = []
        purposes: builtins.list[str] = []
        for i in idx:
            q_deg += [np.degrees(q_program[i]).tolist(), np.degrees(q_cmd[i]).tolist()]
            purposes += ["verify-before", "verify-after"]
        doc = plan_from_poses(q_deg, purposes=purposes, robot=self.robot.name)
        model_campaign = e.campaign or e.detail.get("model_campaign")
        # a child created by a daemon that stopped before recording it is taken up again
        earlier = [r for r in self.store.campaigns(parent=key) if r.state not in FINAL]
        if earlier:
            vcid = earlier[-1].id
        else:
            await self._wait_idle()
            try:
                vst = await self.create(parse_plan(doc, source="verification", strict=False),
                                        actor="daemon", name=f"verify {e.action} {key}",
                                        measure_only=True, parent=key)
            except RobocalError as err:
                if self._closing:
                    raise
                self.journal.set_verification(key, state="skipped",
                                              result={"reason": f"not measured: {err}"})
                return False
            vcid = str(vst["id"])
        self.journal.set_verification(key, state="measuring", campaign=vcid,
                                      result={"indices": idx, "model_campaign": model_campaign,
                                              "action": e.action})
        return True

    async def _finish_verification(self, key: str) -> None:
        v = self.journal.verification(key)
        if v is None or not v.get("campaign"):
            return
        vcid = str(v["campaign"])
        await self._run_child(vcid)
        st = await self.wait(vcid, ["measured", "faulted"], timeout=24 * 3600.0)
        if st["state"] != "measured":
            self.journal.set_verification(
                key, state="failed",
                result={"reason": f"verification campaign {vcid} {st['state']}: "
                                  f"{st['reason']}"})
            return
        e = self.journal.get(key)
        cal = self.fitted_model(str(v["model_campaign"]))
        q_program = np.radians(np.asarray(e.detail["program_q_deg"], dtype=float))
        target_p = e.detail.get("target_p_mm")
        idx = [int(i) for i in v["indices"]]
        rows = {m.pose_idx: m for m in self.store.measurements(vcid)}
        p_before = np.array([rows[2 * k].p_mm for k in range(len(idx))]) * 1e-3
        p_after = np.array([rows[2 * k + 1].p_mm for k in range(len(idx))]) * 1e-3
        # TARGETS.csv positions where the program gives them, else where the error-free
        # robot would be at the program joints
        p_ideal = (np.asarray(target_p, dtype=float)[idx] * 1e-3 if target_p
                   else pushing.ideal_positions(cal, q_program[idx]))
        before = pushing.verification_errors(p_ideal, p_before)
        after = pushing.verification_errors(p_ideal, p_after)
        per_target = [{"index": i,
                       "before_mm": round(float(np.linalg.norm(p_before[k] - p_ideal[k]) * 1e3),
                                          5),
                       "after_mm": round(float(np.linalg.norm(p_after[k] - p_ideal[k]) * 1e3),
                                         5)}
                      for k, i in enumerate(idx)]
        result = {"before": before, "after": after, "per_target": per_target}
        self.journal.set_verification(key, state="done", result=result)
        self.store.audit(actor="daemon", action=f"compensation.{e.action}-verified",
                         campaign=e.campaign,
                         detail={"key": key, "verification_campaign": vcid,
                                 "before_rms_mm": before.get("rms_mm"),
                                 "after_rms_mm": after.get("rms_mm"), "n": after.get("n")})
        self.events.emit("compensation", e.campaign, action="verified", key=key,
                         before_rms_mm=before.get("rms_mm"), after_rms_mm=after.get("rms_mm"))
        _log.info("compensation verified", key=key, before_rms_mm=before.get("rms_mm"),
                  after_rms_mm=after.get("rms_mm"))

    async def report_file(self, cid: str, name: str) -> Path | None:
        """The campaign's report file ``name`` (``report.html``, ``report.json``) as it is
        once a rewrite pending after an action has ended (at most 30 s); None if absent."""
        self.store.campaign(cid)
        with contextlib.suppress(TimeoutError):
            await self.reports.settled(30.0)
        path = self._campaign_dir(cid) / name
        return path if path.is_file() else None

    def report_records(self) -> dict[str, dict[str, Any]]:
        """Campaign id -> what its report's Compensation section shows: its approval and its
        pushes, each with where its table is now (:meth:`push_fates`)."""
        fates = self.push_fates()
        pushed = {e.campaign for e in self.journal.entries() if e.campaign is not None}
        out: dict[str, dict[str, Any]] = {}
        for rec in self.store.campaigns():
            if rec.id not in pushed and rec.state not in (S.APPROVED, S.PUSHED):
                continue
            approved = [t for t in self.store.transitions(rec.id) if t["to_state"] == "approved"]
            approval = None if not approved else {
                "model": rec.selected_model, "actor": approved[-1]["actor"],
                "at": approved[-1]["at"]}
            entries = [{**e, **fates.get(e["key"], {})} if e["action"] == "push" else e
                       for e in self.campaign_compensation(rec.id)]
            out[rec.id] = {"approval": approval, "entries": entries}
        return out

    def campaign_compensation(self, cid: str) -> builtins.list[dict[str, Any]]:
        """The pushes of ``cid``: journal state, table description, verification run."""
        out = []
        for e in self.journal.entries(campaign=cid):
            row = self.store.table(e.table_id)
            d = {k: v for k, v in e.detail.items()
                 if k not in ("program_q_deg", "target_p_mm")}
            out.append({"key": e.key, "action": e.action, "state": e.state, "actor": e.actor,
                        "at": e.finished_at or e.intended_at, "outcome": e.outcome,
                        "checksum": row["checksum"], "table_id": e.table_id, **d,
                        "verification": self.journal.verification(e.key)})
        return out

    @staticmethod
    def _push_summary(entries: builtins.list[dict[str, Any]]) -> dict[str, Any] | None:
        """The campaign's last completed push in a few numbers (None if never pushed)."""
        done = [e for e in entries if e["action"] == "push" and e["state"] == "completed"]
        if not done:
            return None
        e = done[-1]
        v = e.get("verification") or {}
        return {"key": e["key"], "at": e["at"], "actor": e["actor"], "model": e.get("model"),
                "kind": e.get("kind"), "checksum": e["checksum"],
                "predicted_rms_mm": e.get("predicted_residual_mm"),
                "nominal_rms_mm": e.get("nominal_residual_mm"),
                "model_accuracy_mm": e.get("model_accuracy_mm"), "forced": e.get("forced"),
                "verification": v.get("state"),
                "measured_before_rms_mm": (v.get("before") or {}).get("rms_mm"),
                "measured_after_rms_mm": (v.get("after") or {}).get("rms_mm"),
                "measured_n": (v.get("after") or {}).get("n")}

    def compensation(self) -> dict[str, Any]:
        """The active table (described) and the push history with verification runs."""
        stack = self.store.table_stack()
        active = None
        if stack:
            t = self.store.table(stack[-1])
            active = {"table_id": t["id"], "kind": t["kind"], "checksum": t["checksum"],
                      "campaign": t["campaign"], "origin": t["origin"]}
            entry = self._entry(stack[-1])
            if isinstance(entry, CompensationTable):
                active.update({k: v for k, v in describe_table(entry).items()
                               if k not in ("kind", "checksum")})
            else:
                active["purpose"] = "the controller's own values from before robocal's first push"
        journal = self.journal.entries()
        fates = self.push_fates()
        by_table: dict[tuple[str, int | None], JournalEntry] = {}
        for j in journal:
            if j.state == "completed":
                by_table[(j.action, j.rolled_back_id if j.action == "rollback"
                          else j.table_id)] = j
        history = []
        for h in self.store.pushes():
            hj = by_table.get((str(h["action"]), int(h["table_id"])))
            if hj is not None:
                h = {**h, "key": hj.key,
                     **{k: hj.detail.get(k) for k in ("predicted_residual_mm",
                                                      "nominal_residual_mm", "forced",
                                                      "refusal", "reason")},
                     "verification": self.journal.verification(hj.key)}
                if hj.action == "push":
                    h.update(fates.get(hj.key, {}))
            history.append(h)
        return {"active": active, "stack": stack, "history": history,
                "journal": [{**j.to_json(), "detail": {k: v for k, v in j.detail.items()
                                                        if k not in ("program_q_deg",
                                                                     "target_p_mm")}}
                            for j in journal[-50:]]}

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
