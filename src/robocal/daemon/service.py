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
import json
import math
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from robocal import __version__
from robocal._core import read_joints_csv
from robocal._core.files import private_dir
from robocal.compensation import CompensationTable
from robocal.daemon import pushing
from robocal.daemon._plan import PlanDoc, parse_plan
from robocal.daemon.campaign import FINAL, CampaignState
from robocal.daemon.config import AppConfig, config_digest
from robocal.daemon.engine import CampaignRunner, limits_with_margin
from robocal.daemon.events import EventBus
from robocal.daemon.fitting import FitRunner, build_fit_job, fit_options
from robocal.daemon.hub import DriverHub
from robocal.daemon.store import CampaignRecord, MeasurementRow, Store
from robocal.drivers import check_joint_target
from robocal.errors import (
    ApprovalRequired,
    CampaignError,
    CompensationError,
    ConfigError,
    IdentificationError,
    InvalidTransition,
    LimitViolation,
    RobocalError,
)
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

    def __init__(self, config: AppConfig, *, robot: RobotDescription | None = None) -> None:
        self.config = config
        self.robot = robot or load_robot(config.robot_description)
        self.store = Store(config.db_path)
        self.events = EventBus()
        self.hub = DriverHub(config, self.robot)
        self.fitter = FitRunner(executor=config.fit.executor, timeout_s=config.fit.timeout_s)
        self._digest = config_digest(config)
        self._measure_task: tuple[str, asyncio.Task[None]] | None = None
        self._fit_tasks: dict[str, asyncio.Task[None]] = {}
        self._push_lock = asyncio.Lock()
        self._started = time.time()
        self.pose_times: list[float] = []

    # --- lifecycle -------------------------------------------------------------------------
    async def start(self, *, connect: bool = True) -> None:
        """Open the store, connect the drivers (failure is logged), resume campaigns."""
        private_dir(self.config.data_dir)
        self.store.open()
        self.hub.validate()
        fit_options(self.config.fit.options)
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

    async def stop(self) -> None:
        """Stop work (campaign states stay as they are, to resume on restart); close all."""
        tasks = [t for _, t in ([self._measure_task] if self._measure_task else [])]
        tasks += list(self._fit_tasks.values())
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        self.fitter.shutdown()
        await self.hub.close()
        self.events.close()
        self.store.close()

    # --- queries ---------------------------------------------------------------------------
    def health(self) -> dict[str, Any]:
        """Daemon status: version, uptime, drivers, active work."""
        return {
            "status": "ok",
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
        return out

    # below this method `list` names it inside the class: annotations use builtins.list
    def list(self) -> list[dict[str, Any]]:
        """Every campaign, oldest first."""
        return [r.to_json() for r in self.store.campaigns()]

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

    async def create(self, plan: Mapping[str, Any] | str | PlanDoc, *, actor: str,
                     name: str | None = None, start: bool = True,
                     measure_only: bool = False) -> dict[str, Any]:
        """Create a campaign from a plan (validated against limits) and, by default, start it.

        Raises
        ------
        ConfigError
            The plan is malformed, for another robot, or has a pose outside the limits.
        CampaignError
            ``start`` while another campaign is measuring.
        """
        doc = plan if isinstance(plan, PlanDoc) else parse_plan(plan)
        self._check_plan(doc)
        if start:
            self._ensure_idle()
        rec = self.store.create_campaign(
            name=name or f"campaign {time.strftime('%Y-%m-%d %H:%M')}", robot=self.robot.name,
            poses=doc.poses, plan_json=doc.text, plan_digest=doc.digest,
            config_digest=self._digest, actor=actor, measure_only=measure_only)
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
                raise CampaignError(f"campaign {other} is measuring; pause or abort it first")

    def _transition(self, cid: str, to: CampaignState, *, actor: str, reason: str = "",
                    only_from: Iterable[CampaignState] | None = None) -> CampaignRecord:
        rec = self.store.transition(cid, to, actor=actor, reason=reason,
                                    only_from=None if only_from is None else list(only_from))
        self.events.emit("state", cid, state=rec.state.value, reason=reason,
                         poses_measured=rec.poses_measured, poses_total=rec.poses_total)
        _log.info("campaign state", campaign=cid, state=rec.state.value, reason=reason,
                  actor=actor)
        return rec

    async def start_campaign(self, cid: str, *, actor: str) -> dict[str, Any]:
        """``created -> running``."""
        self._ensure_idle(cid)
        self._transition(cid, S.RUNNING, actor=actor, reason="started",
                         only_from=[S.CREATED])
        self._spawn_measure(cid)
        return self.status(cid)

    async def pause(self, cid: str, *, actor: str, reason: str = "") -> dict[str, Any]:
        """``running -> paused``; the pose in progress is finished and kept."""
        self._transition(cid, S.PAUSED, actor=actor, reason=reason or "paused by operator")
        return self.status(cid)

    async def resume(self, cid: str, *, actor: str) -> dict[str, Any]:
        """``paused | faulted -> running``: continue at the first unmeasured pose."""
        rec = self.store.campaign(cid)
        if rec.state not in (S.PAUSED, S.FAULTED):
            raise InvalidTransition(rec.state.value, S.RUNNING.value,
                                    "only paused or faulted campaigns resume")
        task = self._measure_task
        if task is not None and task[0] == cid and not task[1].done():
            # The pose in progress at the pause finishes first (bounded by the move timeout).
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(asyncio.shield(task[1]),
                                       self.config.measurement.move_timeout_s)
        self._ensure_idle(cid)
        self._transition(cid, S.RUNNING, actor=actor, reason="resumed by operator")
        self._spawn_measure(cid)
        return self.status(cid)

    async def abort(self, cid: str, *, actor: str, reason: str = "") -> dict[str, Any]:
        """Abort from any non-final state; motion and fitting for it stop."""
        self._transition(cid, S.ABORTED, actor=actor, reason=reason or "aborted by operator")
        task = self._measure_task
        if task is not None and task[0] == cid and not task[1].done():
            task[1].cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(task[1], 10.0)
            await self.hub.reset("campaign aborted")
        fit = self._fit_tasks.get(cid)
        if fit is not None:
            fit.cancel()
        self.store.audit(actor=actor, action="campaign.abort", campaign=cid,
                         detail={"reason": reason})
        return self.status(cid)

    async def approve(self, cid: str, *, actor: str, model: str | None = None
                      ) -> dict[str, Any]:
        """``fitted -> approved``, optionally choosing another fitted model to push."""
        rec = self.store.campaign(cid)
        chosen = model or rec.selected_model
        fits = self.store.fits(cid)
        if chosen is None or chosen not in fits or self.store.model_json(cid, chosen) is None:
            raise CampaignError(f"model {chosen!r} was not fitted in campaign {cid} "
                                f"(fitted: {', '.join(fits) or 'none'})")
        self._transition(cid, S.APPROVED, actor=actor, reason=f"model {chosen} approved")
        self.store.set_selected_model(cid, chosen)
        self.store.audit(actor=actor, action="campaign.approve", campaign=cid,
                         detail={"model": chosen, "model_id": fits[chosen].get("model_id")})
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
                    return CalibratedModel.from_dict(json.loads(text))
        return None

    def _spawn_measure(self, cid: str) -> None:
        task = asyncio.create_task(self._measure(cid), name=f"measure-{cid}")
        self._measure_task = (cid, task)

    async def _measure(self, cid: str) -> None:
        runner = CampaignRunner(store=self.store, hub=self.hub, events=self.events,
                                config=self.config, robot=self.robot,
                                reference=self._reference_model(cid))
        try:
            state = await runner.run(cid)
        except asyncio.CancelledError:
            raise
        except Exception:  # the runner faults campaigns itself; this is a last resort
            _log.exception("measuring task failed", campaign=cid)
            return
        finally:
            self.pose_times.extend(runner.pose_times)
            del self.pose_times[:-1000]
        if state == S.MEASURED and not self.store.campaign(cid).measure_only:
            self._spawn_fit(cid)

    def _spawn_fit(self, cid: str) -> None:
        if cid in self._fit_tasks and not self._fit_tasks[cid].done():
            return
        task = asyncio.create_task(self._fit(cid), name=f"fit-{cid}")
        self._fit_tasks[cid] = task
        task.add_done_callback(lambda _t: self._fit_tasks.pop(cid, None))

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
                            options=self.config.fit.options)
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
        self.store.save_fits(cid, fits)
        select = self.config.fit.select
        chosen = result.get("selected_hint") if select == "best" else select
        if chosen not in result["fits"] or result["fits"][chosen][1] is None:
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
    def _table(self, table_id: int) -> CompensationTable:
        return CompensationTable.model_validate_json(self.store.table(table_id)["table_json"])

    def _targets_q(self, cid: str) -> np.ndarray | None:
        path = self.config.compensation.targets_file
        if path is not None:
            return read_joints_csv(path, dof=self.robot.dof)
        rows = [p for p in self.store.poses(cid) if p.purpose == "validation"]
        if not rows:
            rows = self.store.poses(cid)
        return np.radians(np.array([p.q_deg for p in rows], dtype=float))

    async def push(self, cid: str, *, actor: str) -> dict[str, Any]:
        """Build, check, write, read back and activate the approved model's table.

        Raises
        ------
        ApprovalRequired
            If the campaign is not ``approved``.
        CompensationError
            If the table exceeds the bounds or the driver cannot store it (nothing written).
        VerificationMismatch
            If the read-back differs (the campaign stays ``approved``; see the audit log).
        """
        rec = self.store.campaign(cid)
        if rec.state != S.APPROVED:
            raise ApprovalRequired(f"campaign {cid} is {rec.state.value}; compensation is "
                                   "pushed only after an operator approves the fit")
        model = rec.selected_model or ""
        text = self.store.model_json(cid, model)
        if text is None:
            raise CompensationError(f"campaign {cid} has no fitted model {model!r}")
        cal = CalibratedModel.from_dict(json.loads(text), source=f"campaign {cid}")
        kind = self.config.compensation.kind
        targets = self._targets_q(cid) if kind == "targets" else None
        table = pushing.build_campaign_table(cal, kind, targets_q=targets)
        async with self._push_lock:
            self._ensure_idle()
            stack = self.store.table_stack()
            previous = self._table(stack[-1]) if stack else None
            pushing.check_bounds(
                table, self.config.limits, self.robot, previous=previous,
                seeds_q_deg=None if targets is None else np.degrees(targets).tolist())
            table_id = self.store.add_table(campaign=cid, origin="campaign", kind=table.kind,
                                            checksum=table.checksum,
                                            table_json=table.model_dump_json())
            try:
                async with self.hub.lock:
                    robot = await self.hub.robot()
                    if not stack:
                        await self._baseline(robot, actor)
                    await pushing.write_and_verify(robot, table)
            except (RobocalError, OSError) as err:
                self.store.audit(actor=actor, action="compensation.push-failed", campaign=cid,
                                 checksum=table.checksum,
                                 detail={"table_id": table_id, "error": str(err)})
                await self.hub.reset(f"push failed: {err}")
                raise
            self.store.record_push(action="push", table_id=table_id, campaign=cid, actor=actor,
                                   checksum=table.checksum,
                                   detail={"kind": table.kind, "model": model,
                                           "model_id": cal.model_id})
            self._transition(cid, S.PUSHED, actor=actor,
                             reason=f"{table.kind} table {table.checksum[:12]} pushed")
        self.events.emit("compensation", cid, action="push", checksum=table.checksum)
        return self.status(cid)

    async def _baseline(self, robot: object, actor: str) -> None:
        """Keep whatever the controller holds before the first push (to restore it later)."""
        read = getattr(robot, "read_compensation", None)
        if read is None:
            return
        current = await read()
        if current is None:
            return
        tid = self.store.add_table(campaign=None, origin="controller", kind=current.kind,
                                   checksum=current.checksum or current.compute_checksum(),
                                   table_json=current.model_dump_json())
        self.store.record_push(action="baseline", table_id=tid, campaign=None, actor=actor,
                               checksum=current.checksum, detail={"note": "read before push"})

    async def rollback(self, *, actor: str) -> dict[str, Any]:
        """Restore the table active before the current one (written, read back, verified).

        Raises
        ------
        CompensationError
            If there is no earlier table.
        """
        async with self._push_lock:
            self._ensure_idle()
            stack = self.store.table_stack()
            if len(stack) < 2:
                raise CompensationError("no earlier compensation table to restore")
            current_id, previous_id = stack[-1], stack[-2]
            table = self._table(previous_id)
            table.verify()
            try:
                async with self.hub.lock:
                    robot = await self.hub.robot()
                    await pushing.write_and_verify(robot, table)
            except (RobocalError, OSError) as err:
                self.store.audit(actor=actor, action="compensation.rollback-failed",
                                 checksum=table.checksum,
                                 detail={"table_id": previous_id, "error": str(err)})
                await self.hub.reset(f"rollback failed: {err}")
                raise
            self.store.record_push(action="rollback", table_id=current_id, campaign=None,
                                   actor=actor, checksum=table.checksum,
                                   detail={"restored_table_id": previous_id,
                                           "rolled_back_table_id": current_id})
        self.events.emit("compensation", None, action="rollback", checksum=table.checksum)
        return self.compensation()

    def compensation(self) -> dict[str, Any]:
        """The active table and the push history."""
        stack = self.store.table_stack()
        active = None
        if stack:
            t = self.store.table(stack[-1])
            active = {"table_id": t["id"], "kind": t["kind"], "checksum": t["checksum"],
                      "campaign": t["campaign"], "origin": t["origin"]}
        return {"active": active, "stack": stack, "history": self.store.pushes()}

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
        return CalibratedModel.from_dict(json.loads(text), source=f"campaign {cid}")
