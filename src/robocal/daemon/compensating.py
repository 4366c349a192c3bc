"""The compensation component: push, rollback, reconcile, and what the push journal says.

:class:`CompensationManager` sits beside the campaign service, which constructs it and keeps
thin methods of the same names. Every controller write, push or rollback, goes through one
journaled write (:meth:`CompensationManager._journaled_write`): journal the intent, write and
read back, complete the journal; or put the previous values back and abandon the key. Writes
hold :attr:`CompensationManager.lock` (the push lock), so an abort and the drain at shutdown
wait for the one in progress. The targets are measured again afterwards by
:class:`~robocal.daemon.verifying.VerificationRuns`.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog

from robocal.compensation import CompensationTable, describe_table, improvement_refusal
from robocal.daemon import _fingerprint, pushing
from robocal.daemon._journal import PushJournal, new_key
from robocal.daemon._reports import ReportKeeper
from robocal.daemon.campaign import CampaignState
from robocal.daemon.config import AppConfig
from robocal.daemon.events import EventBus
from robocal.daemon.fitting import load_model
from robocal.daemon.hub import DriverHub
from robocal.daemon.pushing import Entry
from robocal.daemon.schemas import BULKY_DETAIL, JournalRow, PushDetail, RollbackDetail
from robocal.daemon.store import Store
from robocal.daemon.verifying import CampaignSide, VerificationRuns
from robocal.drivers import JointTemperatureReader, RobotDriver
from robocal.errors import (
    ApprovalRequired,
    CampaignError,
    CompensationError,
    RobocalError,
)
from robocal.identification import at_temperatures, thermal_term
from robocal.kinematics import CalibratedModel, RobotDescription

__all__ = ["CompensationManager"]

S = CampaignState
_log = structlog.get_logger(__name__)


@dataclass(kw_only=True, eq=False)
class CompensationManager:
    """Pushes, rollbacks and the journal's view of them for one robot cell.

    The references are the service's own (one store, hub, journal, event bus, report keeper);
    ``campaigns`` is the service itself, seen as :class:`CampaignSide`.
    """

    config: AppConfig
    robot: RobotDescription
    store: Store
    hub: DriverHub
    journal: PushJournal
    events: EventBus
    reports: ReportKeeper
    campaigns: CampaignSide
    secret: bytes | None
    #: the push lock: one write at a time, drained at shutdown
    lock: asyncio.Lock = field(default_factory=asyncio.Lock, init=False)
    #: set when the daemon stops: nothing new is written
    closing: bool = field(default=False, init=False)
    runs: VerificationRuns = field(init=False)

    def __post_init__(self) -> None:
        self.runs = VerificationRuns(
            config=self.config, robot=self.robot, store=self.store, journal=self.journal,
            events=self.events, reports=self.reports, campaigns=self.campaigns,
            entry=self.entry, closing=lambda: self.closing)

    async def resume(self) -> None:
        """At start: settle the journal with the controller, resume open verification runs."""
        if self.journal.pending():
            await self.reconcile()
        for key, _ in self.journal.open_verifications():
            self.runs.spawn(key)

    async def drain(self, timeout: float = 30.0) -> None:
        """Refuse new pushes and rollbacks and wait (at most ``timeout`` s) for the one in
        progress to be read back and journaled, so shutdown never cuts a write in half.

        A write still running after ``timeout`` stays ``intended`` in the journal and is
        reconciled on the next start.
        """
        self.closing = True
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout), self.lock:
                pass

    # --- stored tables and the program ---------------------------------------------------------
    def entry(self, table_id: int) -> Entry:
        """A stored table or controller snapshot."""
        row = self.store.table(table_id)
        return pushing.parse_entry(str(row["kind"]), str(row["table_json"]))

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

    def _covered_kinds(self, stack: list[int]) -> set[str]:
        kinds: set[str] = set()
        for tid in stack:
            entry = self.entry(tid)
            kinds.add(entry.covers if isinstance(entry, pushing.Baseline) else entry.kind)
        return kinds

    def build_push_table(self, cid: str, *, current_c: tuple[float, ...] | None = None,
                         pushing_now: bool = False
                         ) -> tuple[CompensationTable, dict[str, Any]]:
        """The table a push of ``cid`` would write, and its description (nothing written).

        ``current_c``: the robot's joint temperatures (°C) read for this push, used when
        ``compensation.temperatures`` is ``current`` and the model has a thermal term; a
        preview (``pushing_now`` false) without them takes the campaign's last measured ones.

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
        cal = load_model(text, source=f"campaign {cid}", secret=self.secret,
                         nominal=self.robot)
        cal, temperatures = self._at_temperatures(cid, cal, current_c, pushing_now)
        kind = self.config.compensation.kind
        program = self._program(cid)
        table = pushing.build_campaign_table(
            cal, kind, targets_q=program.q if kind == "targets" else None,
            targets_p=program.p, targets_R=program.R,
            max_change_deg=self.config.limits.max_joint_correction_deg)
        if temperatures["applied"]:
            table = table.with_temperatures(temperatures["temps_c"])
        desc = describe_table(table)
        desc.update(model=model, model_id=cal.model_id, temperatures=temperatures,
                    program_q_deg=np.round(np.degrees(program.q), 9).tolist(),
                    target_p_mm=None if program.p is None
                    else np.round(program.p * 1e3, 6).tolist(),
                    coverage=pushing.outside_coverage(cal, program.q, table.kind))
        return table, desc

    def _at_temperatures(self, cid: str, cal: CalibratedModel,
                         current_c: tuple[float, ...] | None, pushing_now: bool
                         ) -> tuple[CalibratedModel, dict[str, Any]]:
        """The model at the temperatures the table compensates for (ADR 0054), and what the
        description says of them. ``model_id`` stays the approved model's."""
        mode = self.config.compensation.temperatures
        term = thermal_term(cal)
        name = mode if isinstance(mode, str) else "configured"
        if term is None:
            return cal, {"mode": name, "applied": False,
                         "note": "the model has no thermal term"}
        ref = [float(v) for v in term["t_ref_c"]]
        if mode == "reference":
            return cal, {"mode": name, "applied": False, "temps_c": ref, "reference_c": ref}
        if isinstance(mode, list):
            temps, source = tuple(mode), "compensation.temperatures"
        elif current_c:
            temps, source = current_c, "read from the robot"
        elif pushing_now:
            raise CompensationError(
                "compensation.temperatures = \"current\" but the robot's joint temperatures "
                f"cannot be read (the {self.config.robot.kind} driver does not read them): "
                "configure the production temperatures, or \"reference\"; nothing written")
        else:
            last = [m.temps_c for m in self.store.measurements(cid) if m.temps_c]
            if not last:
                raise CompensationError(
                    "compensation.temperatures = \"current\": campaign "
                    f"{cid} has no joint temperatures to preview the table with")
            temps, source = last[-1], f"the last measurement of campaign {cid} (preview)"
        if len(temps) != self.robot.dof:
            raise CompensationError(
                f"compensation.temperatures has {len(temps)} values; {self.robot.name} has "
                f"{self.robot.dof} joints")
        try:
            warm = at_temperatures(cal, temps)
        except RobocalError as err:
            raise CompensationError(f"compensation at {list(temps)} degC: {err}") from err
        warm.model_id = cal.model_id
        return warm, {"mode": name, "applied": True, "temps_c": [float(v) for v in temps],
                      "reference_c": ref, "source": source}

    async def _read_temperatures(self) -> tuple[float, ...] | None:
        """The robot's joint temperatures (°C) now; None when its driver does not read them.

        Raises
        ------
        ConnectFailed
            The robot does not answer (the hub is reset); nothing written.
        """
        async def read(robot: object) -> tuple[float, ...] | None:
            if not isinstance(robot, JointTemperatureReader):
                return None
            return tuple(float(v) for v in (await robot.read_joint_temperatures()).temps_c)

        return await self.hub.read_robot(read, what="the robot's joint temperatures",
                                         short="joint temperatures")

    # --- the one journaled write ---------------------------------------------------------------
    async def _journaled_write(self, action: str, key: str, actor: str, *,
                               intend: Callable[[RobotDriver], Awaitable[None]],
                               write: Callable[[RobotDriver], Awaitable[object]],
                               what: str) -> None:
        """Under the hub's lock: ``intend`` journals the intent (after reading what it needs
        from the robot), ``write`` writes and reads back, then the journal row completes. A
        failed write puts the previous values back and abandons ``key`` (:meth:`_undo`, the
        outcome says ``<what> failed``); any failure resets the drivers and is raised.

        The crash tests' fault points ``<action>:after-intent|write|complete`` are here.
        """
        try:
            async with self.hub.lock:
                robot = await self.hub.robot()
                await intend(robot)
                pushing.fault_point(f"{action}:after-intent")
                try:
                    await write(robot)
                except (RobocalError, OSError) as err:
                    await self._undo(robot, key, actor, f"{what} failed: {err}")
                    raise
                pushing.fault_point(f"{action}:after-write")
                self.journal.complete(key, actor=actor)
                pushing.fault_point(f"{action}:after-complete")
        except (RobocalError, OSError) as err:
            await self.hub.reset(f"{action} failed: {err}")
            raise

    async def _undo(self, robot: RobotDriver, key: str, actor: str, reason: str,
                    what: str = "failed") -> None:
        """After a failed or unfinished write: put back what the slots held, abandon ``key``.

        Never writes the journaled table again; writes the previous values only when the
        controller holds something else.
        """
        e = self.journal.get(key)
        prior: Entry | None = None
        if e.action == "push":
            if e.baseline_id is not None:
                prior = self.entry(e.baseline_id)
            else:
                stack = self.store.table_stack()
                prior = self.entry(stack[-1]) if stack else None
        elif e.rolled_back_id is not None:
            prior = self.entry(e.rolled_back_id)
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

    def _ensure_open(self) -> None:
        if self.closing:
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

    # --- push ----------------------------------------------------------------------------------
    async def _push_checks(self, cid: str, *, actor: str, force: bool
                           ) -> tuple[CompensationTable, dict[str, Any], dict[str, Any],
                                      dict[str, Any]]:
        """Before the lock: the campaign approved, its table built and clearly better than
        nothing (or forced), the controller's calibration as at measuring (or forced).
        Returns the table, its description, its summary and what was forced."""
        rec = self.store.campaign(cid)
        if rec.state == S.PUSHED:
            raise CampaignError(f"campaign {cid} was already pushed; robocal compensation "
                                "list shows it (a new push needs a new campaign; rollback "
                                "restores the previous table)")
        if rec.state != S.APPROVED:
            raise ApprovalRequired(f"campaign {cid} is {rec.state.value}; compensation is "
                                   "pushed only after an operator approves the fit")
        current = (await self._read_temperatures()
                   if self.config.compensation.temperatures == "current" else None)
        table, desc = self.build_push_table(cid, current_c=current, pushing_now=True)
        refusal = improvement_refusal(table, self.config.compensation.max_residual_ratio)
        refusal = refusal or pushing.coverage_refusal(
            desc["coverage"], self.config.compensation.max_outside_coverage)
        summary = {k: desc[k] for k in ("kind", "purpose", "predicted_residual_mm",
                                         "nominal_residual_mm", "model_accuracy_mm", "ratio",
                                         "warnings", "model", "model_id", "coverage",
                                         "temperatures")}
        if refusal is not None and not force:
            self.store.audit(actor=actor, action="compensation.push-refused", campaign=cid,
                             checksum=table.checksum, detail={"refusal": refusal, **summary})
            raise CompensationError(f"push refused: {refusal}; an operator may force it "
                                    "(recorded in the audit log)")
        calibration = await _fingerprint.check_push(self.hub, self.store, cid, force=force,
                                                    actor=actor)
        return table, desc, summary, {"forced": refusal is not None or calibration["forced"],
                                      "refusal": refusal, "controller_calibration": calibration}

    async def push(self, cid: str, *, actor: str, force: bool = False, key: str | None = None,
                   reason: str = "") -> dict[str, Any]:
        """Build, check, journal, write and read back the approved model's table.

        The push is journaled as intended (idempotency ``key``, default a new one) before the
        controller is written and completed after the read-back, in one transaction with the
        history, the audit entry and ``approved -> pushed``. A ``key`` already completed
        returns the status without writing again. Then the pushed targets are measured
        again (:class:`~robocal.daemon.verifying.VerificationRuns`).

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
            return self.campaigns.status(cid)
        table, desc, summary, forced = await self._push_checks(cid, actor=actor, force=force)
        async with self.lock:
            self._ensure_open()
            self.campaigns.ensure_idle(self.runs.verifying())
            await self._reconcile_locked()
            if self.journal.pending():
                raise CompensationError("an earlier push could not be reconciled with the "
                                        "controller yet (is it reachable?); nothing written")
            if self.store.campaign(cid).state != S.APPROVED:
                raise ApprovalRequired(f"campaign {cid} is no longer approved")
            stack = self.store.table_stack()
            previous = self.entry(stack[-1]) if stack else None
            pushing.check_bounds(
                table, self.config.limits, self.robot,
                previous=previous if isinstance(previous, CompensationTable) else None,
                seeds_q_deg=desc["program_q_deg"] if table.kind == "targets" else None)
            # checked and about to write: an earlier push's re-measurement ends here
            await self.runs.stop_run("a new push was asked for")
            push_key = key or new_key()
            detail = PushDetail.model_validate({
                **summary, "forced": forced["forced"], "refusal": forced["refusal"],
                "reason": reason, "controller_calibration": forced["controller_calibration"],
                "program_q_deg": desc["program_q_deg"]})

            async def intend(robot: RobotDriver) -> None:
                snap = None
                if table.kind not in self._covered_kinds(stack):
                    snap = await pushing.take_snapshot(robot, table)
                pushing.fault_point("push:after-snapshot")
                self.journal.intend(
                    key=push_key, action="push", campaign=cid, actor=actor,
                    table=(table.kind, table.checksum, table.model_dump_json()),
                    baseline=None if snap is None else (snap.stored().checksum(),
                                                        snap.stored().model_dump_json()),
                    detail=detail)

            await self._journaled_write(
                "push", push_key, actor, intend=intend, what="write",
                write=lambda robot: pushing.write_and_verify(robot, table))
        self.events.emit("compensation", cid, action="push", checksum=table.checksum,
                         key=push_key)
        _log.info("compensation pushed", campaign=cid, key=push_key, **summary)
        self.runs.spawn(push_key)
        self.reports.refresh()
        return self.campaigns.status(cid)

    # --- reconcile -----------------------------------------------------------------------------
    async def reconcile(self) -> list[JournalRow]:
        """Settle journal entries left ``intended`` by a crash, by reading the controller."""
        async with self.lock:
            return await self._reconcile_locked()

    async def _reconcile_locked(self) -> list[JournalRow]:
        out = []
        for e in self.journal.pending():
            target = self.entry(e.table_id)
            try:
                async with self.hub.lock:
                    robot = await self.hub.robot()
                    if await pushing.holds(robot, target):
                        done = self.journal.complete(
                            e.key, actor=e.actor,
                            outcome="reconciled after a restart: the controller holds it",
                            extra={"reconciled_by": "daemon"})
                        self.runs.spawn(e.key)
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
            out.append(done)
        if out:
            self.reports.refresh()
        return out

    # --- rollback ------------------------------------------------------------------------------
    def _rollback_detail(self, reason: str, entry: Entry, previous_id: int,
                         current_id: int) -> RollbackDetail:
        """The journal detail of a rollback from ``current_id`` to ``previous_id``: what is
        measured again afterwards, the restored table's own targets, or (restoring the
        controller's original) the rolled-back table's targets, now uncompensated."""
        source_id = previous_id if isinstance(entry, CompensationTable) else current_id
        pushed = [j for j in self.journal.entries()
                  if j.action == "push" and j.table_id == source_id]
        return RollbackDetail(
            reason=reason, restored_table_id=previous_id, rolled_back_table_id=current_id,
            program_q_deg=pushed[-1].detail.program_q_deg if pushed else None,
            model_campaign=self.store.table(source_id)["campaign"],
            target_p_mm=pushed[-1].detail.target_p_mm if pushed else None,
            restores=("controller original" if isinstance(entry, pushing.Baseline)
                      else f"{entry.kind} table"))

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
        async with self.lock:
            self._ensure_open()
            await self.runs.stop_run("a rollback was asked for")
            self.campaigns.ensure_idle()
            await self._reconcile_locked()
            if self.journal.pending():
                raise CompensationError("an earlier push could not be reconciled with the "
                                        "controller yet; nothing written")
            stack = self.store.table_stack()
            if len(stack) < 2:
                raise CompensationError("no earlier compensation table to restore")
            current_id, previous_id = stack[-1], stack[-2]
            entry = self.entry(previous_id)
            if isinstance(entry, CompensationTable):
                entry.verify()
            detail = self._rollback_detail(reason, entry, previous_id, current_id)
            rb_key = key or new_key()

            async def intend(robot: RobotDriver) -> None:
                self.journal.intend(key=rb_key, action="rollback", campaign=None, actor=actor,
                                    table_id=previous_id, rolled_back_id=current_id,
                                    detail=detail)

            await self._journaled_write("rollback", rb_key, actor, intend=intend,
                                        what="restore",
                                        write=lambda robot: pushing.restore(robot, entry))
        checksum = self.store.table(previous_id)["checksum"]
        self.events.emit("compensation", None, action="rollback", checksum=checksum,
                         key=rb_key)
        self.runs.spawn(rb_key)
        self.reports.refresh()
        return self.compensation()

    # --- what the journal says -----------------------------------------------------------------
    def push_states(self) -> dict[str, str]:
        """Journal key of every completed push -> its table now: ``active`` (on the
        controller), ``superseded`` (a later push is on top; a rollback would bring it back)
        or ``rolled back``. The one source status, list, the API and the report read."""
        return {k: str(f["compensation_state"]) for k, f in self.push_fates().items()}

    def push_fates(self) -> dict[str, dict[str, str | None]]:
        """:meth:`push_states` with what made it so: ``superseded_by`` (key of the push on
        top of it), ``rolled_back_by`` (key of the rollback) and ``rolled_back_at``."""
        stack: list[str] = []
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

    def pushed_campaigns(self) -> dict[str, tuple[str, str]]:
        """Campaign id -> (key, state now) of its completed push (the last one)."""
        states = self.push_states()
        return {e.campaign: (e.key, states[e.key]) for e in self.journal.entries()
                if e.key in states and e.campaign is not None}

    def campaign_compensation(self, cid: str) -> list[dict[str, Any]]:
        """The pushes of ``cid``: journal state, table description, verification run."""
        out = []
        for e in self.journal.entries(campaign=cid):
            row = self.store.table(e.table_id)
            d = e.detail.model_dump(exclude=set(BULKY_DETAIL), exclude_unset=True)
            out.append({"key": e.key, "action": e.action, "state": e.state, "actor": e.actor,
                        "at": e.finished_at or e.intended_at, "outcome": e.outcome,
                        "checksum": row["checksum"], "table_id": e.table_id, **d,
                        "verification": self.journal.verification(e.key)})
        return out

    def campaign_status(self, cid: str) -> dict[str, Any]:
        """The status keys of ``cid`` about its pushes: ``compensation`` (all of them),
        ``push`` (the last completed one with its fate), ``compensation_state``, ``push_key``."""
        out: dict[str, Any] = {"compensation": self.campaign_compensation(cid)}
        out["push"] = _push_summary(out["compensation"])
        if out["push"] is not None:
            out["push"].update(self.push_fates().get(out["push"]["key"], {}))
            out["compensation_state"] = out["push"].get("compensation_state")
            out["push_key"] = out["push"]["key"]
        return out

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

    def _active(self, stack: list[int]) -> dict[str, Any] | None:
        """The active table of ``stack``, described (None: nothing pushed)."""
        if not stack:
            return None
        t = self.store.table(stack[-1])
        active = {"table_id": t["id"], "kind": t["kind"], "checksum": t["checksum"],
                  "campaign": t["campaign"], "origin": t["origin"]}
        entry = self.entry(stack[-1])
        if isinstance(entry, CompensationTable):
            active.update({k: v for k, v in describe_table(entry).items()
                           if k not in ("kind", "checksum")})
        else:
            active["purpose"] = "the controller's own values from before robocal's first push"
        return active

    def compensation(self) -> dict[str, Any]:
        """The active table (described) and the push history with verification runs."""
        stack = self.store.table_stack()
        active = self._active(stack)
        journal = self.journal.entries()
        fates = self.push_fates()
        by_table: dict[tuple[str, int | None], JournalRow] = {}
        for j in journal:
            if j.state == "completed":
                by_table[(j.action, j.rolled_back_id if j.action == "rollback"
                          else j.table_id)] = j
        history = []
        for h in self.store.pushes():
            hj = by_table.get((str(h["action"]), int(h["table_id"])))
            if hj is not None:
                h = {**h, "key": hj.key,
                     **{k: getattr(hj.detail, k, None) for k in (
                         "predicted_residual_mm", "nominal_residual_mm", "forced", "refusal",
                         "reason")},
                     "verification": self.journal.verification(hj.key)}
                if hj.action == "push":
                    h.update(fates.get(hj.key, {}))
            history.append(h)
        return {"active": active, "stack": stack, "history": history,
                "journal": [j.shown() for j in journal[-50:]]}


def _push_summary(entries: list[dict[str, Any]]) -> dict[str, Any] | None:
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
            "measured_n": (v.get("after") or {}).get("n"),
            "temperatures_c": _applied_temperatures(e.get("temperatures"))}


def _applied_temperatures(t: Any) -> list[float] | None:
    """The joint temperatures (°C) a pushed table compensates for, None at the model's
    reference (ADR 0054)."""
    if isinstance(t, dict) and t.get("applied"):
        return [float(v) for v in t.get("temps_c") or []]
    return None
