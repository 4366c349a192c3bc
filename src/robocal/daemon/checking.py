"""Drift checks (``robocal check``, ADR 0041): is the active compensation's model still right?

A check is a short measure-only campaign (``check.poses``, default 20) at poses the active
model's own campaign measured (held-out poses first, spread over its joint space, so inside
the calibrated coverage, through the plan's home as verification runs go), or at the
measured poses of a plan the operator gives. Each measurement is compared with what the
model predicts at the joints read back: RMS, mean and max (mm). The verdict (pass, warn,
fail) comes from the cell's thresholds (:class:`~robocal.daemon.config.CheckConfig`),
including the growth of the RMS since the last check of the same model; a check that does
not pass recommends a re-calibration with ``--reuse`` (how many poses) or a full one
(:func:`recommend`). Checks are rows of the ``checks`` table (replicated to the fleet store);
a failed one is logged at error priority and announced as a ``check`` event.

:meth:`CheckRuns.recalibrate` starts the recommended reuse refit as a campaign: its fit
keeps the checked model's joint-dependent terms and refits the constant part
(:func:`robocal.identification.refit_frozen`; ``reuse_sources`` says which model).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sqlite3
from collections.abc import Mapping, Sequence
from typing import Any, Literal, Protocol

import numpy as np
import structlog
from numpy.typing import NDArray

from robocal.daemon._plan import CampaignPlan, parse_plan, plan_from_poses
from robocal.daemon._reports import ReportKeeper
from robocal.daemon.config import AppConfig, CheckConfig
from robocal.daemon.events import EventBus
from robocal.daemon.schemas import Measurement
from robocal.daemon.store import Store, now_iso
from robocal.daemon.verifying import CampaignSide, plan_home
from robocal.errors import CampaignError, UnknownCampaign
from robocal.kinematics import CalibratedModel, RobotDescription

__all__ = ["CheckLog", "CheckRuns", "Verdict", "constant_refit_rms_mm", "judge", "recommend",
           "reuse_source", "spread_indices"]

_log = structlog.get_logger(__name__)

Verdict = Literal["pass", "warn", "fail"]
_RANK = {"pass": 0, "warn": 1, "fail": 2}

_SCHEMA = """
CREATE TABLE IF NOT EXISTS checks(
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    campaign TEXT,
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    state TEXT NOT NULL,
    actor TEXT NOT NULL,
    model_campaign TEXT NOT NULL,
    model TEXT NOT NULL,
    verdict TEXT,
    rms_mm REAL,
    max_mm REAL,
    n INTEGER,
    recommendation TEXT,
    detail TEXT NOT NULL DEFAULT '{}'
);
CREATE TABLE IF NOT EXISTS reuse_sources(
    campaign TEXT PRIMARY KEY,
    model_campaign TEXT NOT NULL,
    model TEXT NOT NULL,
    check_id INTEGER
);
"""


# --- the judgement (pure) ----------------------------------------------------------------------
def rms_thresholds(cfg: CheckConfig, model_rms_mm: float | None
                   ) -> tuple[tuple[float, str], tuple[float, str]]:
    """(warn, fail) RMS thresholds (mm) with where each comes from: the absolute one, or
    ``*_rms_ratio`` times the model's held-out RMS when configured, known and lower."""
    out = []
    for level in ("warn", "fail"):
        limit, why = float(getattr(cfg, f"{level}_rms_mm")), ""
        ratio = getattr(cfg, f"{level}_rms_ratio")
        if ratio is not None and model_rms_mm is not None and model_rms_mm > 0 \
                and ratio * model_rms_mm < limit:
            limit = ratio * model_rms_mm
            why = f" ({ratio:g} x the model's held-out {model_rms_mm:.4f} mm)"
        out.append((limit, why))
    return out[0], out[1]


def judge(rms_mm: float, max_mm: float, growth_mm: float | None, cfg: CheckConfig,
          model_rms_mm: float | None = None) -> tuple[Verdict, list[str]]:
    """The verdict of a check and why (each threshold reached, worst first);
    ``model_rms_mm``, the model's held-out RMS, for the relative RMS thresholds."""
    verdict: Verdict = "pass"
    reasons: list[str] = []
    (warn_rms, warn_why), (fail_rms, fail_why) = rms_thresholds(cfg, model_rms_mm)
    values = (("RMS", rms_mm, min(warn_rms, fail_rms), fail_rms),
              ("max", max_mm, cfg.warn_max_mm, cfg.fail_max_mm),
              ("growth since the last check", growth_mm, cfg.warn_growth_mm,
               cfg.fail_growth_mm))
    for what, value, warn, fail in values:
        if value is None:
            continue
        level: Verdict | None = "fail" if value >= fail else "warn" if value >= warn else None
        if level is None:
            continue
        limit = fail if level == "fail" else warn
        why = (fail_why if level == "fail" else warn_why) if what == "RMS" else ""
        reasons.append(f"{what} {value:.4f} mm >= {level} threshold {limit:.4g} mm{why}")
        if _RANK[level] > _RANK[verdict]:
            verdict = level
    reasons.sort(key=lambda r: " fail " not in r)
    return verdict, reasons


def recommend(verdict: Verdict, rms_mm: float, constant_rms_mm: float | None,
              cfg: CheckConfig, *, model_rms_mm: float | None = None) -> dict[str, Any]:
    """What to do after a check.

    ``constant_rms_mm`` is the check's RMS once the joint offsets and the tracker placement
    are refitted to it (:func:`constant_refit_rms_mm`): what a ``--reuse`` re-calibration
    cannot correct; ``model_rms_mm`` the model's held-out RMS when it was fitted. ``none``
    when the check passed; ``reuse`` (with the poses to measure) when that remainder is under
    ``warn_rms_mm`` or within ``reuse_ratio`` of the model's own held-out RMS; ``full``
    otherwise, or from ``full_rms_mm`` on.
    """
    if verdict == "pass":
        return {"action": "none", "why": "every value is under its warn threshold"}
    if rms_mm >= cfg.full_rms_mm:
        return {"action": "full",
                "why": f"RMS {rms_mm:.4f} mm >= full_rms_mm {cfg.full_rms_mm:g} mm: more than "
                       "a drift of the constant part; calibrate in full"}
    bar = cfg.warn_rms_mm
    if model_rms_mm is not None:
        bar = max(bar, cfg.reuse_ratio * model_rms_mm)
    if constant_rms_mm is None or constant_rms_mm >= bar:
        left = "unknown" if constant_rms_mm is None else f"{constant_rms_mm:.4f} mm"
        return {"action": "full",
                "why": f"refitting the joint offsets and the tracker placement leaves {left} "
                       f"(>= {bar:.4f} mm): the joint-dependent errors changed; calibrate in "
                       "full"}
    return {"action": "reuse", "poses": cfg.reuse_poses,
            "validation_poses": cfg.reuse_validation_poses,
            "why": f"refitting the joint offsets and the tracker placement leaves "
                   f"{constant_rms_mm:.4f} mm (< {bar:.4f} mm): re-calibrate with --reuse on "
                   f"{cfg.reuse_poses} poses (+ {cfg.reuse_validation_poses} held out)"}


def constant_refit_rms_mm(cal: CalibratedModel, q: NDArray[np.float64],
                          p_m: NDArray[np.float64]) -> float | None:
    """RMS (mm) of ``p_m`` (n, 3) m minus the model's prediction at ``q`` (n, dof) rad after a
    linearised least-squares refit of the joint zero offsets and a small rigid motion of the
    tracker frame; None with too few poses (fewer equations than 2 x unknowns)."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n, dof = q.shape
    unknowns = dof + 6
    if 3 * n < 2 * unknowns:
        return None
    p0 = cal.predict(q)
    cols = []
    h = 1e-6
    for j in range(dof):
        dq = np.zeros(dof)
        dq[j] = h
        cols.append(((cal.predict(q + dq) - p0) / h).reshape(-1))
    for k in range(3):  # translation of the tracker frame
        t = np.zeros((n, 3))
        t[:, k] = 1.0
        cols.append(t.reshape(-1))
    for k in range(3):  # small rotation about the tracker's axes: omega x p
        axis = np.zeros(3)
        axis[k] = 1.0
        cols.append(np.cross(axis, p0).reshape(-1))
    A = np.stack(cols, axis=1)
    r = (np.asarray(p_m, dtype=float) - p0).reshape(-1)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    x, *_ = np.linalg.lstsq(A / scale, r, rcond=None)
    left = (r - (A / scale) @ x).reshape(n, 3)
    return float(np.sqrt(np.mean(np.sum(left**2, axis=1))) * 1e3)


def spread_indices(q: NDArray[np.float64], count: int, *, first: Sequence[int] = ()
                   ) -> list[int]:
    """``count`` rows of ``q`` (n, dof) spread over its joint space: farthest-point order,
    starting with the rows ``first`` (taken in their order while they last), deterministic."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n = len(q)
    if count >= n:
        return list(range(n))
    span = np.ptp(q, axis=0)
    span[span == 0] = 1.0
    z = q / span
    chosen: list[int] = list(first[:count]) or [0]
    dist = np.min(np.linalg.norm(z[:, None, :] - z[chosen][None, :, :], axis=2), axis=1)
    while len(chosen) < count:
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(z - z[k], axis=1))
    return chosen


def errors_mm(cal: CalibratedModel, rows: Sequence[Measurement]
              ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Joints (n, dof) rad read back, measured points (n, 3) m and the distances (n,) mm
    between them and the model's prediction."""
    q = np.radians(np.array([r.q_act_deg for r in rows], dtype=float))
    p = np.array([r.p_mm for r in rows], dtype=float) * 1e-3
    e = np.linalg.norm(p - cal.predict(q), axis=1) * 1e3
    return q, p, e


# --- the store: checks and the sources of reuse refits -------------------------------------------
class CheckLog:
    """The ``checks`` and ``reuse_sources`` tables in the daemon's store (same SQLite file)."""

    def __init__(self, store: Store) -> None:
        self.store = store

    def ensure_schema(self) -> None:
        """Create the tables if needed (the store must be open)."""
        self.store.db.executescript(_SCHEMA)

    def add(self, *, campaign: str, actor: str, model_campaign: str, model: str) -> int:
        """A new check, ``measuring``; its id."""
        t = now_iso()
        with self.store.transaction() as db:
            cur = db.execute(
                "INSERT INTO checks(campaign, created, updated, state, actor, model_campaign, "
                "model) VALUES(?,?,?,?,?,?,?)",
                (campaign, t, t, "measuring", actor, model_campaign, model))
            return int(cur.lastrowid or 0)

    def finish(self, check_id: int, *, state: str, verdict: str | None = None,
               rms_mm: float | None = None, max_mm: float | None = None, n: int | None = None,
               recommendation: str | None = None, detail: Mapping[str, Any] | None = None
               ) -> None:
        """Record the outcome of a check (``done`` or ``failed``)."""
        with self.store.transaction() as db:
            db.execute(
                "UPDATE checks SET state=?, updated=?, verdict=?, rms_mm=?, max_mm=?, n=?, "
                "recommendation=?, detail=? WHERE id=?",
                (state, now_iso(), verdict, rms_mm, max_mm, n, recommendation,
                 json.dumps(dict(detail or {}), default=str), check_id))

    def get(self, check_id: int) -> dict[str, Any]:
        """One check; UnknownCampaign (a LookupError: 404 on the API) when unknown."""
        row = self.store.db.execute("SELECT * FROM checks WHERE id=?", (check_id,)).fetchone()
        if row is None:
            raise UnknownCampaign(f"no check {check_id}")
        return _check(row)

    def history(self, *, limit: int = 1000) -> list[dict[str, Any]]:
        """The most recent ``limit`` checks, oldest first."""
        rows = self.store.db.execute(
            "SELECT * FROM (SELECT * FROM checks ORDER BY id DESC LIMIT ?) ORDER BY id",
            (limit,)).fetchall()
        return [_check(r) for r in rows]

    def add_reuse(self, *, campaign: str, model_campaign: str, model: str,
                  check_id: int | None) -> None:
        """Mark ``campaign`` as a reuse refit of ``model`` of ``model_campaign``."""
        with self.store.transaction() as db:
            db.execute("INSERT INTO reuse_sources(campaign, model_campaign, model, check_id) "
                       "VALUES(?,?,?,?)", (campaign, model_campaign, model, check_id))


def _check(row: sqlite3.Row) -> dict[str, Any]:
    out = dict(row)
    out["detail"] = json.loads(out["detail"] or "{}")
    return out


def reuse_source(store: Store, cid: str) -> tuple[str, str] | None:
    """(model campaign, model) whose joint-dependent terms campaign ``cid`` refits, or None
    for an ordinary campaign."""
    with contextlib.suppress(sqlite3.OperationalError):  # a store without the table
        row = store.db.execute("SELECT model_campaign, model FROM reuse_sources WHERE "
                               "campaign=?", (cid,)).fetchone()
        if row is not None:
            return str(row[0]), str(row[1])
    return None


# --- the runs ----------------------------------------------------------------------------------
class _Campaigns(CampaignSide, Protocol):
    async def create(self, plan: CampaignPlan, *, actor: str, name: str | None = None,
                     start: bool = True, measure_only: bool = False,
                     parent: str | None = None) -> dict[str, Any]:
        """Create (and by default start) a campaign."""
        ...


class CheckRuns:
    """Starts checks, judges them when measured, and starts recommended reuse refits.

    ``campaigns`` is the campaign service (creates, waits, loads fitted models).
    """

    def __init__(self, *, config: AppConfig, robot: RobotDescription, store: Store,
                 events: EventBus, campaigns: _Campaigns,
                 reports: ReportKeeper | None = None) -> None:
        self.config = config
        self.reports = reports
        self.robot = robot
        self.store = store
        self.events = events
        self.campaigns = campaigns
        self.log = CheckLog(store)
        self._tasks: dict[int, asyncio.Task[None]] = {}

    def ensure_schema(self) -> None:
        """Create the tables (at start, after the store opened)."""
        self.log.ensure_schema()

    def resume(self) -> None:
        """Judge the checks a stopped daemon left measuring (their campaigns resume)."""
        for c in self.log.history(limit=100):
            if c["state"] == "measuring":
                self._spawn(int(c["id"]))

    def unfinished(self) -> list[asyncio.Task[None]]:
        """Tasks still going (cancelled at shutdown; resumed on the next start)."""
        return [t for t in self._tasks.values() if not t.done()]

    def active_model(self) -> tuple[str, str]:
        """(campaign, model) of the compensation on the controller now.

        Raises
        ------
        CampaignError
            If no table of a calibration campaign is active (nothing pushed, or rolled back
            to the controller's own values).
        """
        stack = self.store.table_stack()
        campaign = self.store.table(stack[-1])["campaign"] if stack else None
        if campaign is None:
            raise CampaignError("nothing to check: no calibration's compensation is active on "
                                "the controller (push one first)")
        model = self.store.campaign(str(campaign)).selected_model
        if not model:
            raise CampaignError(f"campaign {campaign} has no selected model")
        return str(campaign), model

    def _home(self, cid: str) -> list[float] | None:
        """The home of ``cid``'s plan; a reuse refit's bare plan has none, so the home of the
        campaign it refits (and so on back to the planned calibration)."""
        seen: set[str] = set()
        while cid not in seen:
            seen.add(cid)
            home = plan_home(self.store, cid, self.robot.dof)
            source = reuse_source(self.store, cid)
            if home is not None or source is None:
                return home
            cid = source[0]
        return None

    def _poses_of(self, cid: str, count: int, *, validation: int = 0) -> CampaignPlan:
        """A bare plan of ``count`` poses the model campaign measured (held-out ones first),
        spread over its joints, each from the plan's home when it has one; the last
        ``validation`` of them held out."""
        rows = [r for r in self.store.measurements(cid) if r.purpose != "via"]
        if not rows:
            raise CampaignError(f"campaign {cid} has no measured poses to check at")
        q = np.array([r.q_cmd_deg for r in rows], dtype=float)
        held = [i for i, r in enumerate(rows) if r.purpose == "validation"]
        idx = spread_indices(q, count, first=held if not validation else ())
        home = self._home(cid)
        q_deg: list[list[float]] = []
        purposes: list[str] = []
        for k, i in enumerate(idx):
            if home is not None:
                q_deg.append(home)
                purposes.append("via")
            q_deg.append(q[i].tolist())
            purposes.append("validation" if not validation or k >= len(idx) - validation
                            else "calibration")
        doc = plan_from_poses(q_deg, purposes=purposes, robot=self.robot.name)
        return parse_plan(doc, source="check", strict=False)

    async def start(self, *, actor: str, plan: Mapping[str, Any] | None = None
                    ) -> dict[str, Any]:
        """Start a check of the active model (at ``plan``'s measured poses if given)."""
        mc, model = self.active_model()
        self.campaigns.fitted_model(mc, model)  # a model that does not load is refused now
        doc: Mapping[str, Any] | CampaignPlan = (plan if plan is not None
                                            else self._poses_of(mc, self.config.check.poses))
        n = len(self.log.history(limit=1_000_000)) + 1
        st = await self.campaigns.create(doc if isinstance(doc, CampaignPlan) else parse_plan(doc),
                                         actor=actor, name=f"check {n} of {mc}",
                                         measure_only=True)
        check_id = self.log.add(campaign=str(st["id"]), actor=actor, model_campaign=mc,
                                model=model)
        self.events.emit("check", str(st["id"]), check=check_id, state="measuring")
        _log.info("check started", check=check_id, campaign=st["id"], model_campaign=mc,
                  model=model, actor=actor)
        self._spawn(check_id)
        return self.log.get(check_id)

    async def wait(self, check_id: int, *, timeout: float) -> dict[str, Any]:
        """Wait (at most ``timeout`` s) for a check to be judged; return it as it is then."""
        task = self._tasks.get(check_id)
        if task is not None:
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(task), timeout)
        return self.log.get(check_id)

    def _spawn(self, check_id: int) -> None:
        if check_id in self._tasks and not self._tasks[check_id].done():
            return
        self._tasks[check_id] = asyncio.create_task(self._guarded(check_id),
                                                    name=f"check-{check_id}")

    async def _guarded(self, check_id: int) -> None:
        try:
            await self._finish(check_id)
        except asyncio.CancelledError:
            raise
        except Exception as err:  # a bug in judging must not take the daemon down
            _log.exception("check could not be judged", check=check_id)
            with contextlib.suppress(Exception):
                self._failed(check_id, f"{type(err).__name__}: {err}")

    def _failed(self, check_id: int, reason: str) -> None:
        c = self.log.get(check_id)
        self.log.finish(check_id, state="failed", verdict="fail", detail={"reason": reason})
        _log.error("drift check failed", check=check_id, reason=reason)
        self.events.emit("check", c["campaign"], check=check_id, state="failed",
                         verdict="fail", reason=reason)
        if self.reports is not None:
            self.reports.refresh()

    def _previous(self, check_id: int, model_campaign: str, model: str
                  ) -> dict[str, Any] | None:
        done = [c for c in self.log.history(limit=1_000_000)
                if c["id"] < check_id and c["state"] == "done"
                and (c["model_campaign"], c["model"]) == (model_campaign, model)]
        return done[-1] if done else None

    async def _finish(self, check_id: int) -> None:
        c = self.log.get(check_id)
        cid = str(c["campaign"])
        st = await self.campaigns.wait(cid, ["measured", "faulted"],
                                       timeout=self.config.check.timeout_s)
        if st["state"] != "measured":
            self._failed(check_id, f"check campaign {cid} {st['state']}: {st['reason']}")
            return
        cal = self.campaigns.fitted_model(c["model_campaign"], c["model"])
        rows = [r for r in self.store.measurements(cid) if r.purpose != "via"]
        fit = self.store.fits(c["model_campaign"]).get(c["model"], {})
        held = (fit.get("validation") or {}).get("rms_mm")
        detail = evaluate(cal, rows, self._previous(check_id, c["model_campaign"], c["model"]),
                          self.config.check,
                          model_rms_mm=float(held) if isinstance(held, int | float) else None)
        rec = detail["recommendation"]
        self.log.finish(check_id, state="done", verdict=detail["verdict"],
                        rms_mm=detail["rms_mm"], max_mm=detail["max_mm"], n=detail["n"],
                        recommendation=rec["action"], detail=detail)
        self.store.audit(actor="daemon", action="check.done", campaign=cid,
                         detail={"check": check_id, "verdict": detail["verdict"],
                                 "rms_mm": detail["rms_mm"], "recommendation": rec["action"]})
        self.events.emit("check", cid, check=check_id, state="done", verdict=detail["verdict"],
                         rms_mm=detail["rms_mm"], max_mm=detail["max_mm"],
                         recommendation=rec["action"])
        if self.reports is not None:
            self.reports.refresh()  # the model's report shows its checks
        say = {"pass": _log.info, "warn": _log.warning, "fail": _log.error}[detail["verdict"]]
        say("drift check " + {"pass": "passed", "warn": "warns",
                              "fail": "failed"}[detail["verdict"]],
            check=check_id, rms_mm=detail["rms_mm"], max_mm=detail["max_mm"],
            reasons=detail["reasons"], recommendation=rec["action"])

    def report_records(self, records: dict[str, dict[str, Any]]
                       ) -> dict[str, dict[str, Any]]:
        """``records`` (campaign id -> its report's compensation record) with the judged
        checks of each campaign's model added (``checks``, oldest first, and the
        ``check_thresholds``)."""
        by_model: dict[str, list[dict[str, Any]]] = {}
        for c in self.log.history(limit=1_000_000):
            if c["state"] == "measuring":
                continue
            d = c.get("detail") or {}
            by_model.setdefault(str(c["model_campaign"]), []).append(
                {"id": c["id"], "created": c["created"], "state": c["state"],
                 "verdict": c["verdict"], "rms_mm": c["rms_mm"], "max_mm": c["max_mm"],
                 "n": c["n"], "growth_mm": d.get("growth_mm"),
                 "recommendation": c["recommendation"]})
        thresholds = self.config.check.model_dump(include={"warn_rms_mm", "fail_rms_mm"})
        return {cid: ({**rec, "checks": by_model[cid], "check_thresholds": thresholds}
                      if cid in by_model else rec) for cid, rec in records.items()}

    async def recalibrate(self, *, actor: str, check_id: int | None = None) -> dict[str, Any]:
        """Start the re-calibration with ``--reuse`` of the active model (or of the model
        check ``check_id`` checked): ``reuse_poses`` + ``reuse_validation_poses`` of its
        campaign's measured poses, fitted by a refit of the constant part."""
        if check_id is not None:
            c = self.log.get(check_id)
            mc, model = str(c["model_campaign"]), str(c["model"])
        else:
            mc, model = self.active_model()
        cfg = self.config.check
        doc = self._poses_of(mc, cfg.reuse_poses + cfg.reuse_validation_poses,
                             validation=cfg.reuse_validation_poses)
        st = await self.campaigns.create(doc, actor=actor, start=False,
                                         name=f"reuse refit of {mc}")
        self.log.add_reuse(campaign=str(st["id"]), model_campaign=mc, model=model,
                           check_id=check_id)
        _log.info("reuse refit created", campaign=st["id"], model_campaign=mc, model=model)
        return await self.campaigns.start_campaign(str(st["id"]), actor=actor)


def evaluate(cal: CalibratedModel, rows: Sequence[Measurement],
             previous: Mapping[str, Any] | None, cfg: CheckConfig, *,
             model_rms_mm: float | None = None) -> dict[str, Any]:
    """A measured check judged: errors (mm), verdict, reasons and recommendation
    (``model_rms_mm``: the model's held-out RMS when fitted)."""
    if not rows:
        raise CampaignError("the check measured nothing")
    q, p, e = errors_mm(cal, rows)
    rms, mx = float(np.sqrt(np.mean(e**2))), float(np.max(e))
    prev = None if previous is None else previous.get("rms_mm")
    growth = None if prev is None else rms - float(prev)
    verdict, reasons = judge(rms, mx, growth, cfg, model_rms_mm)
    constant = constant_refit_rms_mm(cal, q, p)
    return {"n": len(rows), "rms_mm": round(rms, 5), "max_mm": round(mx, 5),
            "mean_mm": round(float(np.mean(e)), 5),
            "growth_mm": None if growth is None else round(growth, 5),
            "previous_check": None if previous is None else previous.get("id"),
            "constant_refit_rms_mm": None if constant is None else round(constant, 5),
            "verdict": verdict, "reasons": reasons,
            "model_held_out_rms_mm": model_rms_mm,
            "recommendation": recommend(verdict, rms, constant, cfg,
                                        model_rms_mm=model_rms_mm),
            "per_pose_mm": [round(float(v), 5) for v in e]}
