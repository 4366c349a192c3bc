"""Verification runs: the targets of a push or rollback measured again with the tracker.

After a push or rollback completes, :class:`VerificationRuns` creates a measure-only child
campaign (``parent`` = the journal key) at the program targets, as the controller runs them
without and with the table, and journals the errors before and after (``pending ->
measuring -> done | skipped | failed``). The runs belong to the compensation component
(:mod:`robocal.daemon.compensating`); they reach the campaign service only through
:class:`CampaignSide`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import structlog

from robocal.compensation import CompensationTable
from robocal.daemon import pushing
from robocal.daemon._journal import PushJournal
from robocal.daemon._plan import CampaignPlan, parse_plan, plan_from_poses
from robocal.daemon._reports import ReportKeeper
from robocal.daemon.campaign import FINAL, CampaignState
from robocal.daemon.config import AppConfig
from robocal.daemon.events import EventBus
from robocal.daemon.schemas import CampaignSummary
from robocal.daemon.store import Store
from robocal.errors import CampaignError, RobocalError
from robocal.kinematics import CalibratedModel, RobotDescription

__all__ = ["CampaignSide", "VerificationRuns", "plan_home"]

S = CampaignState
_log = structlog.get_logger(__name__)


class CampaignSide(Protocol):
    """What the compensation component uses of the campaign service (which is one)."""

    def measuring(self) -> str | None:
        """The campaign measuring now, or None."""
        ...

    def ensure_idle(self, cid: str | None = None) -> None:
        """Refuse (CampaignError) while a campaign other than ``cid`` measures."""
        ...

    def status(self, cid: str) -> dict[str, Any]:
        """Campaign status."""
        ...

    def transition(self, cid: str, to: CampaignState, *, actor: str,
                   reason: str = "") -> CampaignSummary:
        """Move a campaign to ``to`` (stored, announced, logged)."""
        ...

    def spawn_measure(self, cid: str) -> None:
        """Start measuring a ``running`` campaign."""
        ...

    async def stop_motion(self, *, trigger: str, reason: str, actor: str = "daemon",
                          cid: str | None = None) -> bool:
        """Halt the robot now."""
        ...

    async def preflight(self) -> dict[str, str]:
        """Connect robot and tracker."""
        ...

    async def create(self, plan: CampaignPlan, *, actor: str, name: str | None = None,
                     measure_only: bool = False, parent: str | None = None
                     ) -> dict[str, Any]:
        """Create and start a campaign."""
        ...

    async def start_campaign(self, cid: str, *, actor: str) -> dict[str, Any]:
        """``created -> running``."""
        ...

    async def wait(self, cid: str, states: Iterable[CampaignState | str], *,
                   timeout: float) -> dict[str, Any]:
        """Wait for one of ``states``."""
        ...

    def fitted_model(self, cid: str, model: str | None = None) -> CalibratedModel:
        """A fitted model of a campaign."""
        ...


def plan_home(store: Store, cid: object, dof: int) -> list[float] | None:
    """The home (deg) of the plan campaign ``cid`` was created from, if it declares one for
    ``dof`` joints (runs that measure a campaign's poses again visit each from there)."""
    if not isinstance(cid, str):
        return None
    try:
        home = json.loads(store.plan_json(cid))["motion"]["home_deg"]
    except (RobocalError, ValueError, KeyError, TypeError):
        return None
    if not isinstance(home, list) or len(home) != dof:
        return None
    return [float(v) for v in home]


@dataclass(kw_only=True, eq=False)
class VerificationRuns:
    """The verification runs of pushes and rollbacks, one task per journal key.

    ``entry`` reads a stored table or snapshot by id; ``closing`` says whether the daemon is
    stopping (a run cut then stays open in the journal and is resumed on the next start).
    """

    config: AppConfig
    robot: RobotDescription
    store: Store
    journal: PushJournal
    events: EventBus
    reports: ReportKeeper
    campaigns: CampaignSide
    entry: Callable[[int], pushing.Entry]
    closing: Callable[[], bool]
    _tasks: dict[str, asyncio.Task[None]] = field(default_factory=dict, init=False)

    def spawn(self, key: str) -> None:
        """Start (or resume) the run of ``key`` unless it is under way."""
        if key in self._tasks and not self._tasks[key].done():
            return
        task = asyncio.create_task(self._verify(key), name=f"verify-{key}")
        self._tasks[key] = task

    def unfinished(self) -> list[asyncio.Task[None]]:
        """The run tasks still going (to cancel at shutdown)."""
        return [t for t in self._tasks.values() if not t.done()]

    async def wait(self, key: str, *, timeout: float) -> dict[str, Any] | None:
        """Wait (at most ``timeout`` s) for the verification run of ``key``; return it."""
        task = self._tasks.get(key)
        if task is not None:
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(task), timeout)
        return self.journal.verification(key)

    async def _verify(self, key: str) -> None:
        try:
            v = self.journal.verification(key)
            if v is None or v["state"] == "pending":
                started = await self._start(key)
                self.reports.refresh()
                if not started:
                    return
                v = self.journal.verification(key)
            if v is not None and v["state"] == "measuring":
                await self._finish(key)
                self.reports.refresh()
        except asyncio.CancelledError:
            raise
        except Exception as err:  # a verification bug must not take the daemon down
            if self.closing():  # cut by shutdown: still open in the journal, resumed on start
                _log.info("verification interrupted by shutdown", key=key, error=str(err))
                return
            _log.exception("verification failed", key=key)
            with contextlib.suppress(Exception):
                self.journal.set_verification(key, state="failed",
                                              result={"reason": f"{type(err).__name__}: {err}"})
            self.reports.refresh()

    def verifying(self) -> str | None:
        """The verification run measuring now (a child of a push), or None."""
        cid = self.campaigns.measuring()
        if cid is None:
            return None
        return cid if self.store.campaign(cid).verifies is not None else None

    async def stop_run(self, why: str) -> None:
        """Stop the verification run measuring now, if any (push lock held): a new push or a
        rollback supersedes what it measures, so it ends (``skipped``, saying why) instead of
        making the operator wait or refusing them."""
        cid = self.campaigns.measuring()
        if cid is None:
            return
        rec = self.store.campaign(cid)
        if rec.verifies is None:
            return  # an operator's campaign: the caller refuses, naming it
        key = rec.verifies
        verifying = self._tasks.get(key)
        if verifying is not None:
            verifying.cancel()
        reason = f"verification stopped: {why}"
        self.campaigns.transition(rec.id, S.ABORTED, actor="daemon", reason=reason)
        await self.campaigns.stop_motion(trigger="abort", reason=reason, cid=rec.id)
        if verifying is not None:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(verifying, 10.0)
        self.journal.set_verification(key, state="skipped",
                                      result={"reason": f"stopped before the end: {why}"})
        _log.info("verification run stopped", key=key, campaign=rec.id, reason=why)

    async def _wait_idle(self) -> None:
        """Wait until no campaign measures (the robot is one)."""
        async with self.events.subscribe(("state",)) as q:
            while self.campaigns.measuring() is not None:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(0.5):
                        if await q.get() is None:
                            raise CampaignError("the service stopped")

    async def _run_child(self, vcid: str) -> None:
        """Make a verification run measure: after a restart it is ``running`` without a task
        (never resumed as a campaign of its own) or still ``created``."""
        if self.campaigns.measuring() == vcid:
            return
        state = self.store.campaign(vcid).state
        if state not in (S.CREATED, S.RUNNING):
            return
        await self._wait_idle()
        if self.store.campaign(vcid).state == S.CREATED:
            await self.campaigns.preflight()
            await self.campaigns.start_campaign(vcid, actor="daemon")
        elif self.store.campaign(vcid).state == S.RUNNING:
            _log.info("resuming verification run after restart", campaign=vcid)
            self.campaigns.spawn_measure(vcid)

    def _skip_reason(self, program: object,
                     entry: pushing.Entry) -> str | None:
        """Why the targets of a push are not measured again, or None."""
        if self.config.compensation.verify_count <= 0:
            return "verification disabled (compensation.verify_count = 0)"
        if not program:
            return "no program targets recorded for this push"
        if isinstance(entry, CompensationTable) and entry.kind == "frames":
            return ("a frames table changes the frames Cartesian programs use; measuring "
                    "joint targets again would not test it")
        return None

    def _home_deg(self, cid: object) -> list[float] | None:
        """The home (deg) of the plan campaign ``cid`` was created from, if it declares one."""
        return plan_home(self.store, cid, self.robot.dof)

    async def _start(self, key: str) -> bool:
        e = self.journal.get(key)
        program = e.detail.program_q_deg
        entry = self.entry(e.table_id)
        skip = self._skip_reason(program, entry)
        if skip is not None:
            self.journal.set_verification(key, state="skipped", result={"reason": skip})
            return False
        q_program = np.radians(np.asarray(program, dtype=float))
        q_cmd, compensated = pushing.commanded_joints(entry, q_program)
        rows = ([i for i in range(len(q_program)) if compensated[i]]
                if isinstance(entry, CompensationTable) else list(range(len(q_program))))
        idx = [rows[k] for k in pushing.verification_indices(
            len(rows), self.config.compensation.verify_count)]
        model_campaign = e.model_campaign()
        home = self._home_deg(model_campaign)
        q_deg: list[list[float]] = []
        purposes: list[str] = []
        for i in idx:
            # each target from the plan's home when it has one: the planner chose its poses
            # reachable from home, while a straight move between two targets may not be safe
            if home is not None:
                q_deg.append(home)
                purposes.append("via")
            q_deg += [np.degrees(q_program[i]).tolist(), np.degrees(q_cmd[i]).tolist()]
            purposes += ["verify-before", "verify-after"]
        doc = plan_from_poses(q_deg, purposes=purposes, robot=self.robot.name)
        # a child created by a daemon that stopped before recording it is taken up again
        earlier = [r for r in self.store.campaigns(parent=key) if r.state not in FINAL]
        if earlier:
            vcid = earlier[-1].id
        else:
            await self._wait_idle()
            try:
                vst = await self.campaigns.create(
                    parse_plan(doc, source="verification", strict=False), actor="daemon",
                    name=f"verify {e.action} {key}", measure_only=True, parent=key)
            except RobocalError as err:
                if self.closing():
                    raise
                self.journal.set_verification(key, state="skipped",
                                              result={"reason": f"not measured: {err}"})
                return False
            vcid = str(vst["id"])
        self.journal.set_verification(key, state="measuring", campaign=vcid,
                                      result={"indices": idx, "model_campaign": model_campaign,
                                              "action": e.action})
        return True

    async def _finish(self, key: str) -> None:
        v = self.journal.verification(key)
        if v is None or not v.get("campaign"):
            return
        vcid = str(v["campaign"])
        await self._run_child(vcid)
        st = await self.campaigns.wait(vcid, ["measured", "faulted"], timeout=24 * 3600.0)
        if st["state"] != "measured":
            self.journal.set_verification(
                key, state="failed",
                result={"reason": f"verification campaign {vcid} {st['state']}: "
                                  f"{st['reason']}"})
            return
        e = self.journal.get(key)
        cal = self.campaigns.fitted_model(str(v["model_campaign"]))
        q_program = np.radians(np.asarray(e.detail.program_q_deg, dtype=float))
        target_p = e.detail.target_p_mm
        idx = [int(i) for i in v["indices"]]
        # the k-th verify-before and verify-after poses in plan order (via poses between
        # targets are moved through, not measured)
        rows = sorted(self.store.measurements(vcid), key=lambda m: m.pose_idx)
        p_before = np.array([m.p_mm for m in rows if m.purpose == "verify-before"]) * 1e-3
        p_after = np.array([m.p_mm for m in rows if m.purpose == "verify-after"]) * 1e-3
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
