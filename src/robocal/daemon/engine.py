"""The measuring executor: move, settle, read joints, measure, validate, persist — per pose.

With ``[warmup]`` configured, a new operator campaign first runs the warm-up routine: the
plan's poses cycled through the same checked moves (each cycle starts with the checked first
move), until the configured time has passed or the joint temperatures settled (``warmup``
events, ``campaign.warmup`` audit; ADR 0042).

Before the first move of every run (new campaign, resume, verification run) the robot's
actual joints are read and the run's first moves are checked from there (joint limits; swept
path in the daemon's cell, else the plan's): a fresh run of a plan with a home moves to home
first, then to pose 0; a resumed run moves straight to its next pose. The plan's declared home
is never taken as the start. An unsafe first move faults the campaign before anything moves,
naming the actual start pose.

For every pose not yet in the store, in plan order:

1. check the target against the joint limits shrunk by ``limits.joint_margin_deg``
   (a target outside is never sent; the campaign faults);
2. ``move_to`` (the driver waits until the robot is in position), then settle;
   (via-points, ``measure = false`` in the plan, are only moved through);
3. read the actual joints (they must be within ``max_joint_deviation_deg`` of the target)
   and, where the driver reads them, the joint temperatures;
4. measure, retrying a broken beam, an unstable target, a tracker timeout, a noisy reading
   (sample RMS) or a reading too far from the prediction, with exponential backoff;
5. persist the measurement in one SQLite transaction, *before* the next motion.

Between poses the executor re-reads the campaign state. Pause, abort and shutdown do not wait
for the pose in progress: the service cancels the executor and stops the robot at once (the
unfinished pose is redone on resume, nothing of it is stored). Any driver failure stops the
robot, then faults the campaign with a reason; the operator resumes. Every stop is logged and
audited (``motion.stop``: trigger, reason, when, how long the controller took to confirm).
"""

from __future__ import annotations

import asyncio
import math
import operator
import time
from collections.abc import Sequence
from typing import cast

import numpy as np
import structlog
from numpy.typing import NDArray

from robocal._core.clock import SYSTEM_CLOCK, Clock
from robocal.daemon._plan import check_first_legs, first_stops, stored_plan
from robocal.daemon._warmup import WarmupWatch
from robocal.daemon.campaign import CampaignState
from robocal.daemon.config import AppConfig
from robocal.daemon.events import EventBus
from robocal.daemon.hub import DriverHub
from robocal.daemon.schemas import Measurement
from robocal.daemon.store import PoseRow, Store, now_iso
from robocal.drivers import (
    RETRYABLE,
    JointTemperatureReader,
    TrackerReading,
    check_joint_target,
    with_retry,
)
from robocal.errors import (
    BeamLost,
    LimitViolation,
    MeasurementError,
    MeasurementRejected,
    MotionRejected,
    RobocalError,
    StorageError,
)
from robocal.kinematics import (
    CalibratedModel,
    ErrorModelSpec,
    KinematicModel,
    RobotDescription,
    kabsch,
)
from robocal.planning import load_cell

__all__ = [
    "CampaignRunner",
    "MeasurementRejected",
    "Predictor",
    "halt_motion",
    "limits_with_margin",
]

Array = NDArray[np.float64]
Vec = tuple[float, float, float]
_log = structlog.get_logger(__name__)


def _raise_if_cancelling(cause: BaseException | None = None) -> None:
    """Re-raise a cancellation that a library swallowed (Python 3.11's ``asyncio.wait_for``
    can lose one when its future completes at the same moment, as pymodbus's requests do)."""
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError from cause


async def halt_motion(hub: DriverHub, store: Store, *, campaign: str | None, actor: str,
                      trigger: str, reason: str, audit_idle: bool = False) -> bool:
    """Stop the robot now and record when and why (structlog and the ``motion.stop`` audit).

    ``trigger`` names the cause (``pause``, ``abort``, ``shutdown``, ``driver-fault``, ...).
    Returns True when the controller confirmed the halt or no robot is connected. Nothing is
    audited for an unconnected robot unless ``audit_idle``.
    """
    requested_at = now_iso()
    t0 = time.monotonic()
    outcome, detail = await hub.stop_motion(f"{trigger}: {reason}")
    seconds = round(time.monotonic() - t0, 4)
    emit = _log.info if outcome == "not-connected" else _log.warning
    emit("motion stop", campaign=campaign, trigger=trigger, reason=reason, outcome=outcome,
         detail=detail, stop_s=seconds)
    if outcome != "not-connected" or audit_idle:
        try:
            store.audit(actor=actor, action="motion.stop", campaign=campaign,
                        detail={"trigger": trigger, "reason": reason, "outcome": outcome,
                                "detail": detail, "requested_at": requested_at,
                                "stop_s": seconds})
        except Exception as err:  # the stop itself matters more than its record
            _log.error("motion stop not audited", error=repr(err))
    return outcome != "failed"


def limits_with_margin(robot: RobotDescription, margin_deg: float) -> tuple[tuple[float, float],
                                                                            ...]:
    """Joint limits (rad) shrunk by ``margin_deg`` on both sides."""
    m = math.radians(margin_deg)
    return tuple((j.q_min + m, j.q_max - m) for j in robot.joints)


class Predictor:
    """Where the reflector should be, from the nominal (or a previous) model.

    The model's frame is aligned to the tracker's by a rigid fit to the poses measured so
    far, so neither the tracker placement nor the previous model's base need be right;
    distances are available from ``min_poses`` measurements on.

    Parameters
    ----------
    robot : RobotDescription
        Nominal robot (used when ``model`` is None).
    model : CalibratedModel, optional
        A previously identified model of this robot.
    min_poses : int
        Measurements needed before :meth:`distance` answers.
    """

    #: Largest joint step (rad) from a primed pose answered by its first-order expansion
    #: (error <= ~|dq|^2 x reach: a few micrometres at 1e-3 rad); beyond, the model is called.
    LINEAR_STEP = 1e-3
    #: The alignment is refitted after each of the first ``REFIT_ALL`` poses, then after every
    #: ``REFIT_EVERY``-th: one more pose among dozens moves it by far less than the gate
    #: (``max_distance_mm``) can tell, and the refit was a fifth of the daemon's per-pose cost.
    REFIT_ALL = 32
    REFIT_EVERY = 8

    def __init__(self, robot: RobotDescription, model: CalibratedModel | None = None, *,
                 min_poses: int = 6) -> None:
        self.min_poses = min_poses
        if model is not None:
            self._predict = model.predict
        else:
            nominal = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
            x = nominal.nominal_params()

            def predict(q: Array) -> Array:
                return nominal.positions(np.atleast_2d(q), x)

            self._predict = predict
        # the measured poses' model and tracker points (m) as running moments about the first
        # of each (the alignment then costs a 3 x 3 SVD per refit, whatever the count); the
        # per-pose path is plain float arithmetic on 3- and 6-tuples (numpy's per-call cost on
        # such tiny arrays was most of the predictor's time)
        self._n = 0
        self._origin: tuple[Vec, Vec] | None = None
        self._sum_s = [0.0, 0.0, 0.0]               # Σ s
        self._sum_d = [0.0, 0.0, 0.0]               # Σ d
        self._ss = [[0.0] * 3 for _ in range(3)]    # Σ s sᵀ
        self._sd = [[0.0] * 3 for _ in range(3)]    # Σ s dᵀ
        self._T: tuple[tuple[Vec, Vec, Vec], Vec] | None = None  # rotation rows, translation
        self._last: tuple[tuple[float, ...], Vec] | None = None
        self._primed_q: Array | None = None
        self._rows_q: list[tuple[float, ...]] = []
        self._rows_p: list[Vec] = []
        self._rows_J: list[tuple[tuple[float, ...], ...]] = []
        self._next = 0  # the primed row the next reading most likely belongs to

    def prime(self, q_rad: Array) -> None:
        """Predict the planned joints ``q_rad`` (n, dof) at once, with the joint Jacobian
        (central differences, one batched call): a single-pose model call costs ~200 batched
        poses, and a reading's actual joints lie within the deviation limit of a planned pose.
        """
        q = np.atleast_2d(np.asarray(q_rad, dtype=float))
        if not q.size:
            return
        n, dof = q.shape
        h = 1e-6
        steps = np.concatenate([np.zeros((1, dof)), h * np.eye(dof), -h * np.eye(dof)])
        pts = np.asarray(self._predict((q[None, :, :] + steps[:, None, :]).reshape(-1, dof)))
        pts = pts.reshape(2 * dof + 1, n, 3)
        J = ((pts[1:dof + 1] - pts[dof + 1:]) / (2 * h)).transpose(1, 2, 0)  # (n, 3, dof)
        self._primed_q = q
        self._rows_q = [tuple(r) for r in q.tolist()]
        self._rows_p = [(r[0], r[1], r[2]) for r in pts[0].tolist()]
        self._rows_J = [tuple(tuple(row) for row in Ji) for Ji in J.tolist()]

    def _linear(self, i: int, q: tuple[float, ...]) -> Vec | None:
        """First-order prediction at ``q`` from primed row ``i``; None if ``q`` is too far."""
        dq = [a - b for a, b in zip(q, self._rows_q[i], strict=True)]
        if max(map(abs, dq)) > self.LINEAR_STEP:
            return None
        p, J = self._rows_p[i], self._rows_J[i]
        return (p[0] + sum(map(operator.mul, J[0], dq)), p[1] + sum(map(operator.mul, J[1], dq)),
                p[2] + sum(map(operator.mul, J[2], dq)))

    def _model_point(self, q_rad: Sequence[float] | Array) -> Vec:
        key = tuple(map(float, q_rad))
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        s = None
        rows = self._rows_q
        if rows and len(rows[0]) == len(key):
            # poses are measured in plan order: try the row after the last one matched
            # before searching them all (the search is most of a call's cost)
            i = self._next
            if i < len(rows):
                s = self._linear(i, key)
            if s is None:
                assert self._primed_q is not None
                i = int(np.argmin(np.abs(np.asarray(key) - self._primed_q).max(axis=1)))
                s = self._linear(i, key)
            if s is not None:
                self._next = i + 1
        if s is None:
            x, y, z = np.asarray(self._predict(np.asarray(key))[0], dtype=float).tolist()
            s = (x, y, z)
        self._last = (key, s)
        return s

    def add(self, q_rad: Sequence[float] | Array, p_m: Sequence[float] | Array) -> None:
        """Record one measured pose (actual joints, rad; point, m)."""
        src = self._model_point(q_rad)
        x, y, z = map(float, p_m)
        if self._origin is None:
            self._origin = (src, (x, y, z))
        o_s, o_d = self._origin
        s = (src[0] - o_s[0], src[1] - o_s[1], src[2] - o_s[2])
        d = (x - o_d[0], y - o_d[1], z - o_d[2])
        for j in range(3):
            self._sum_s[j] += s[j]
            self._sum_d[j] += d[j]
            ss, sd, sj = self._ss[j], self._sd[j], s[j]
            for k in range(3):
                ss[k] += sj * s[k]
                sd[k] += sj * d[k]
        self._n += 1
        if self._n <= self.REFIT_ALL or self._n % self.REFIT_EVERY == 0:
            self._T = None

    def __len__(self) -> int:
        return self._n

    def _refit(self) -> bool:
        """Align the model to the tracker from the moments; False while the poses are
        collinear or coincident (the rotation is ambiguous then: wait for more)."""
        assert self._origin is not None
        n = self._n
        cs, cd = np.array(self._sum_s) / n, np.array(self._sum_d) / n
        # the centred points' singular values are the square roots of their scatter's
        # eigenvalues
        scatter = np.array(self._ss) - n * np.outer(cs, cs)
        if np.count_nonzero(np.linalg.eigvalsh(scatter) > 1e-8) < 2:
            return False
        T = kabsch(np.array(self._sd) - n * np.outer(cs, cd), cs + np.array(self._origin[0]),
                   cd + np.array(self._origin[1]))
        R = T[:3, :3].tolist()
        t = T[:3, 3].tolist()
        self._T = ((R[0][0], R[0][1], R[0][2]), (R[1][0], R[1][1], R[1][2]),
                   (R[2][0], R[2][1], R[2][2])), (t[0], t[1], t[2])
        return True

    def distance(self, q_rad: Sequence[float], p_m: Sequence[float]) -> float | None:
        """Distance (m) of ``p_m`` from the aligned prediction at ``q_rad``; None if too early."""
        if self._n < self.min_poses:
            return None
        if self._T is None and not self._refit():
            return None
        assert self._T is not None
        (r0, r1, r2), t = self._T
        s = self._model_point(q_rad)
        x, y, z = map(float, p_m)
        return math.hypot(r0[0] * s[0] + r0[1] * s[1] + r0[2] * s[2] + t[0] - x,
                          r1[0] * s[0] + r1[1] * s[1] + r1[2] * s[2] + t[1] - y,
                          r2[0] * s[0] + r2[1] * s[1] + r2[2] * s[2] + t[2] - z)


class CampaignRunner:
    """Measure the remaining poses of one campaign.

    Parameters
    ----------
    store, hub, events, config, robot
        The daemon's store, drivers, event bus, configuration and robot description.
    reference : CalibratedModel, optional
        A previous model used to predict readings (default: the nominal robot).
    actor : str
        Recorded with the transitions the runner makes.
    """

    def __init__(self, *, store: Store, hub: DriverHub, events: EventBus, config: AppConfig,
                 robot: RobotDescription, reference: CalibratedModel | None = None,
                 actor: str = "daemon", clock: Clock = SYSTEM_CLOCK) -> None:
        self.store = store
        self.clock = clock      # settle time and retry backoff wait on it
        self.hub = hub
        self.events = events
        self.config = config
        self.robot = robot
        self.reference = reference
        self.actor = actor
        self.limits = limits_with_margin(robot, config.limits.joint_margin_deg)
        self.pose_times: list[float] = []
        self._temps_from: object = None
        self._reads_temps = False

    def _state(self, cid: str) -> CampaignState:
        return self.store.state(cid)

    def _transition(self, cid: str, to: CampaignState, reason: str = "") -> None:
        rec = self.store.transition(cid, to, actor=self.actor, reason=reason)
        self.events.emit("state", cid, state=rec.state.value, reason=reason,
                         poses_measured=rec.poses_measured, poses_total=rec.poses_total)

    async def run(self, cid: str) -> CampaignState:
        """Measure until done, paused, aborted or faulted; return the state reached."""
        log = _log.bind(campaign=cid)
        poses = self.store.poses(cid)
        predictor = Predictor(self.robot, self.reference,
                              min_poses=self.config.measurement.min_poses_for_distance)
        predictor.prime(np.radians([p.q_deg for p in poses if p.measure]).reshape(
            -1, self.robot.dof))
        for m in self.store.measurements(cid):
            predictor.add(np.radians(m.q_act_deg), np.asarray(m.p_mm) * 1e-3)
        done = self.store.measured_indices(cid)
        total = sum(1 for p in poses if p.measure)
        # Measurements form a prefix of the plan (poses run in order, a failure faults), so
        # resume right after the last measured pose, including the via-points after it.
        start = max(done) + 1 if done else 0
        todo = [p for p in poses if p.idx >= start and not (p.measure and p.idx in done)]
        log.info("measuring", remaining=sum(1 for p in todo if p.measure), total=total,
                 resume_at=start)
        try:
            async with self.hub.lock:
                if start == 0 and todo and self._wants_warmup(cid):
                    stopped = await self._warm_up(cid, poses)
                    if stopped is not None:
                        return stopped
                first = True
                for pose in todo:
                    _raise_if_cancelling()
                    state = self._state(cid)
                    if state != CampaignState.RUNNING:
                        log.info("stopped between poses", state=state.value)
                        return state
                    if first:
                        await self._checked_start(cid, pose, via_home=start == 0)
                        first = False
                    t0 = time.perf_counter()
                    if not pose.measure:
                        await self._move(pose)
                        continue
                    row, q_act, p_m = await self._measure_pose(cid, pose, predictor)
                    if self.store.add_measurement(cid, row):
                        predictor.add(q_act, p_m)  # the joints validated: its point is cached
                    else:  # cannot happen while one runner owns the campaign; never duplicate
                        log.warning("pose already measured; reading discarded", pose=pose.idx)
                    done.add(pose.idx)
                    self.pose_times.append(time.perf_counter() - t0)
                    self.events.emit(
                        "pose", cid, pose=pose.idx, purpose=pose.purpose,
                        poses_measured=len(done), poses_total=total, attempts=row.attempts,
                        distance_mm=row.distance_mm,
                    )
        except asyncio.CancelledError:
            log.info("measuring cancelled")
            raise
        except StorageError:
            raise  # the robot stands still between poses; the service pauses the campaign
        except (RobocalError, OSError) as err:
            reason = f"{type(err).__name__}: {err}"
            _raise_if_cancelling(err)  # stopped on purpose (pause, abort, shutdown): no fault
            log.warning("campaign faulted", error=reason)
            await halt_motion(self.hub, self.store, campaign=cid, actor=self.actor,
                              trigger="driver-fault", reason=reason)
            await self.hub.reset(reason)
            return self._fault(cid, reason)
        except Exception as err:  # a bug must fault the campaign, never kill the daemon
            reason = f"internal error: {type(err).__name__}: {err}"
            log.exception("campaign faulted by an internal error")
            await halt_motion(self.hub, self.store, campaign=cid, actor=self.actor,
                              trigger="internal-error", reason=reason)
            await self.hub.reset(reason)
            return self._fault(cid, reason)
        state = self._state(cid)
        if state == CampaignState.RUNNING and len(self.store.measured_indices(cid)) == total:
            self._transition(cid, CampaignState.MEASURED, "all poses measured")
            return CampaignState.MEASURED
        return state

    def _fault(self, cid: str, reason: str) -> CampaignState:
        state = self._state(cid)
        if state == CampaignState.RUNNING:
            self._transition(cid, CampaignState.FAULTED, reason)
            return CampaignState.FAULTED
        return state  # paused or aborted meanwhile: the pose in progress is simply redone

    async def _checked_start(self, cid: str, target: PoseRow, *, via_home: bool,
                             then: Sequence[tuple[str, tuple[float, ...]]] = ()) -> None:
        """Read where the robot stands, check the run's first moves from there (to home when
        ``via_home`` and the plan has one, then to ``target``, then through ``then``: label,
        joints deg) and move to home.

        Raises
        ------
        MotionRejected
            An unsafe first move (nothing was moved), or the robot did not reach home.
        """
        robot = await self.hub.robot()
        start_deg = [math.degrees(v) for v in (await robot.read_joints()).q_rad]
        plan = stored_plan(self.store.plan_json(cid), source=f"campaign {cid} plan")
        cell = load_cell(self.config.cell) if self.config.cell else plan.cell
        stops = [*first_stops(plan, target, via_home=via_home), *then]
        _log.info("first move checked from the actual joints", campaign=cid,
                  start_deg=[round(v, 4) for v in start_deg], via=[s[0] for s in stops],
                  cell=None if cell is None else cell.name)
        # the swept-path check takes milliseconds to a few tenths of a second: off the loop
        await asyncio.to_thread(check_first_legs, self.robot, cell, self.limits, start_deg,
                                stops)
        if len(stops) == 1 + len(then):
            return
        home = [math.radians(v) for v in stops[0][1]]
        await self._move_to(home, "home")
        # the next move was checked from home: make sure the robot is there
        q_act = (await robot.read_joints()).q_rad
        self._check_deviation("home", q_act, home)

    def _wants_warmup(self, cid: str) -> bool:
        """A warm-up is configured and ``cid`` is an operator's campaign (a verification
        run re-measures a few poses of a warm robot, right after the push)."""
        return self.config.warmup is not None and self.store.campaign(cid).verifies is None

    async def _joint_temperatures(self) -> tuple[tuple[float, ...], float | None]:
        """Joint temperatures (°C) and their controller time (s); ``((), None)`` when the
        robot's driver does not read them."""
        robot = await self.hub.robot()
        if self._temps_from is not robot:  # a Protocol isinstance costs ~10 us: once a driver
            self._temps_from, self._reads_temps = robot, isinstance(robot,
                                                                    JointTemperatureReader)
        if not self._reads_temps:
            return (), None
        reading = await cast("JointTemperatureReader", robot).read_joint_temperatures()
        return tuple(float(v) for v in reading.temps_c), float(reading.timestamp)

    async def _warm_up(self, cid: str, poses: Sequence[PoseRow]) -> CampaignState | None:
        """Run the warm-up routine; None when it ended, else the state that stopped it.

        Raises
        ------
        MotionRejected
            An unsafe first move of a cycle, or ``until_settled_c_per_min`` on a robot whose
            driver does not read joint temperatures (nothing moved then).
        """
        cfg = self.config.warmup
        assert cfg is not None
        cycle, closing = self._warmup_cycle(poses)
        watch = WarmupWatch(cfg)
        temps, t = await self._joint_temperatures()
        if cfg.until_settled_c_per_min is not None and t is None:
            raise MotionRejected("warm-up until the temperatures settle needs a robot driver "
                                 "that reads joint temperatures", kind="daemon")
        watch.add(self.clock.monotonic() if t is None else t, temps)
        self.events.emit("warmup", cid, phase="started", elapsed_s=0.0,
                         temps_c=list(temps) or None)
        _log.info("warm-up started", campaign=cid, temps_c=list(temps))
        reason = None
        cycles = 0
        while reason is None:
            for k, pose in enumerate(cycle):
                _raise_if_cancelling()
                if self._state(cid) != CampaignState.RUNNING:
                    return self._state(cid)
                if k == 0 and (not closing or cycles == 0):
                    await self._checked_start(cid, pose, via_home=True, then=closing)
                await self._move(pose)
                temps, t = await self._joint_temperatures()
                reason = watch.add(self.clock.monotonic() if t is None else t, temps)
                if reason is not None:
                    break
            cycles += 1
            self.events.emit("warmup", cid, phase="progress", elapsed_s=watch.elapsed_s,
                             temps_c=list(temps) or None, rate_c_per_min=watch.rate_c_per_min)
        detail = {"reason": reason, "elapsed_s": round(watch.elapsed_s, 3),
                  "temps_c": list(temps), "rate_c_per_min": watch.rate_c_per_min}
        self.store.audit(actor=self.actor, action="campaign.warmup", campaign=cid, detail=detail)
        self.events.emit("warmup", cid, phase="done", elapsed_s=watch.elapsed_s,
                         temps_c=list(temps) or None, rate_c_per_min=watch.rate_c_per_min,
                         reason=reason)
        _log.info("warm-up done", campaign=cid, **detail)
        return None

    def _warmup_cycle(self, poses: Sequence[PoseRow]
                      ) -> tuple[list[PoseRow], list[tuple[str, tuple[float, ...]]]]:
        """The poses one warm-up cycle visits and, for ``pattern = "poses"``, the rest of the
        cycle after its first pose (back to it) as first-move stops: that whole cycle is
        checked once, before anything moves. The plan's own cycle is checked from its first
        pose on every cycle, as a campaign's start is."""
        cfg = self.config.warmup
        assert cfg is not None
        if cfg.pattern == "plan":
            return list(poses), []
        cycle = [PoseRow(k, "warm-up", tuple(float(v) for v in q))
                 for k, q in enumerate(cfg.poses_deg)]
        for p in cycle:
            if len(p.q_deg) != self.robot.dof:
                raise MotionRejected(f"warm-up pose {p.idx} has {len(p.q_deg)} joints, the "
                                     f"robot {self.robot.dof}; nothing moved", kind="daemon")
        closing = [(f"pose {p.idx} (warm-up)", p.q_deg) for p in cycle[1:]]
        return cycle, [*closing, ("pose 0 (warm-up, closing the cycle)", cycle[0].q_deg)]

    def _check_deviation(self, what: str, q_act: Sequence[float],
                         q_cmd: Sequence[float]) -> None:
        dev = max(abs(a - b) for a, b in zip(q_act, q_cmd, strict=True))
        limit = self.config.measurement.max_joint_deviation_deg
        if math.degrees(dev) > limit:
            raise MotionRejected(
                f"{what}: robot stopped {math.degrees(dev):.3f} deg from the target "
                f"(limit {limit} deg)", kind="daemon")

    async def _move(self, pose: PoseRow) -> list[float]:
        """Check the target against the limits, then move; return the target (rad)."""
        q_cmd = [math.radians(v) for v in pose.q_deg]
        await self._move_to(q_cmd, f"pose {pose.idx}")
        return q_cmd

    async def _move_to(self, q_cmd: list[float], what: str) -> None:
        # Never send a target outside the limits (shrunk by the margin); the driver checks
        # its own limits again before anything goes on the wire.
        try:
            check_joint_target(q_cmd, self.limits, kind="daemon")
        except LimitViolation as err:
            raise LimitViolation(f"{what}: {err}", kind="daemon") from err
        robot = await self.hub.robot()
        await robot.move_to(q_cmd, speed_pct=self.config.limits.speed_pct,
                            timeout=self.config.measurement.move_timeout_s)

    async def _measure_pose(self, cid: str, pose: PoseRow, predictor: Predictor
                            ) -> tuple[Measurement, tuple[float, ...], tuple[float, ...]]:
        """Move to ``pose``, measure and validate; the row to store, the actual joints (rad)
        and the reading (m)."""
        cfg = self.config.measurement
        tracker = await self.hub.tracker()
        q_cmd = await self._move(pose)
        robot = await self.hub.robot()
        if cfg.settle_s > 0:
            await self.clock.sleep(cfg.settle_s)
        joints = await robot.read_joints()
        q_act = tuple(joints.q_rad)
        self._check_deviation(f"pose {pose.idx}", q_act, q_cmd)
        temps, _ = await self._joint_temperatures()
        attempts = 0
        beam_losses = 0

        async def attempt() -> tuple[TrackerReading, float | None]:
            nonlocal attempts
            attempts += 1
            reading = await tracker.measure(samples=cfg.samples, timeout=cfg.timeout_s,
                                            point_id=f"{cid}-{pose.idx}")
            return reading, self._validate(reading, q_act, predictor)

        def retried(n: int, err: Exception, delay: float) -> None:
            nonlocal beam_losses
            beam_losses += isinstance(err, BeamLost)
            problem = f"{type(err).__name__}: {err}"
            _log.info("reading retried", campaign=cid, pose=pose.idx, attempt=n,
                      problem=problem, delay_s=delay)
            self.events.emit("retry", cid, pose=pose.idx, attempt=n, problem=problem)

        retry_on: tuple[type[Exception], ...] = (*RETRYABLE, MeasurementRejected)
        try:
            reading, distance = await with_retry(
                attempt, attempts=cfg.retries + 1, backoff_s=cfg.backoff_s,
                backoff_factor=cfg.backoff_factor, max_backoff_s=cfg.max_backoff_s,
                retry_on=retry_on, on_retry=retried, clock=self.clock)
        except retry_on as err:
            raise MeasurementError(
                f"pose {pose.idx}: no valid reading after {attempts} attempts; last: "
                f"{type(err).__name__}: {err}") from err
        return (self._row(pose, q_cmd, q_act, reading, attempts, distance, beam_losses, temps),
                q_act, tuple(reading.position_m))

    def _validate(self, reading: TrackerReading, q_act: Sequence[float],
                  predictor: Predictor) -> float | None:
        cfg = self.config.measurement
        if reading.rms_m is not None and reading.rms_m * 1e3 > cfg.max_rms_mm:
            raise MeasurementRejected(
                f"sample RMS {reading.rms_m * 1e3:.4f} mm above {cfg.max_rms_mm} mm (unstable)")
        if not all(math.isfinite(v) for v in reading.position_m):
            raise MeasurementRejected("non-finite position")
        d = predictor.distance(q_act, reading.position_m)
        if d is not None and d * 1e3 > cfg.max_distance_mm:
            raise MeasurementRejected(
                f"reading {d * 1e3:.2f} mm from the prediction (limit {cfg.max_distance_mm} mm)")
        return None if d is None else d * 1e3

    @staticmethod
    def _row(pose: PoseRow, q_cmd: Sequence[float], q_act: Sequence[float],
             r: TrackerReading, attempts: int, distance_mm: float | None,
             beam_losses: int = 0, temps_c: tuple[float, ...] = ()) -> Measurement:
        return Measurement(
            pose_idx=pose.idx, purpose=pose.purpose,
            q_cmd_deg=tuple(map(math.degrees, q_cmd)),
            q_act_deg=tuple(map(math.degrees, q_act)),
            p_mm=(r.position_m[0] * 1e3, r.position_m[1] * 1e3, r.position_m[2] * 1e3),
            sigma_mm=None if r.std_m is None else (r.std_m[0] * 1e3, r.std_m[1] * 1e3,
                                                    r.std_m[2] * 1e3),
            rms_mm=None if r.rms_m is None else r.rms_m * 1e3,
            samples=r.n, attempts=attempts, distance_mm=distance_mm,
            weather={k: float(v) for k, v in r.weather.items()}, measured_at=now_iso(),
            beam_losses=beam_losses, temps_c=temps_c,
        )
