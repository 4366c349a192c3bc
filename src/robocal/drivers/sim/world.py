"""The simulated world shared by every simulator and mock driver of one cell.

One :class:`SimWorld` holds one virtual robot (a :class:`robocal.simulation.VirtualCell`) and
its current pose, so the tracker simulator measures where the robot simulator actually put
the reflector: commanded joints plus joint repeatability noise, through the true (planted)
kinematics, plus tracker noise.

Motion takes time: :meth:`SimWorld.start_motion` sweeps the joints linearly (all joints
arriving together, as a joint move does) from where they are to the target over the motion's
duration; :attr:`SimWorld.q_actual_rad` is the interpolated position while it runs.
:meth:`SimWorld.halt` freezes the robot where it is, the way a controller's abort does, and
:meth:`SimWorld.finish_motion` settles a motion that ran to its end (adding the repeatability
noise). :meth:`SimWorld.move` is the instantaneous form.

A world may carry a planted warm-up drift (:class:`robocal.simulation.WarmUpDrift`): every
settled move heats the joints for the move's simulated duration (largest joint step at
``THERMAL_SPEED_RAD_S`` plus ``THERMAL_MOVE_S``), every measurement lets them cool for
``THERMAL_DWELL_S``, and the reflector is where the links, grown by their temperatures, put
it. :meth:`SimWorld.joint_temperatures` reads them (a constant ``COLD_C`` without a drift).

There is no process-wide registry of worlds: whoever builds the simulators or mock drivers of
one cell hands them the same world, directly (``world=``, :class:`~robocal.drivers.sim.SimCell`)
or through the :class:`~robocal.drivers.DriverContext` the drivers are loaded in.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "DEFAULT_ROBOT",
    "SimMotion",
    "SimWorld",
    "WorldMeasurement",
]

DEFAULT_ROBOT = "fanuc_lrmate200id"
#: Simulated time a move heats the joints: largest joint step / speed + a fixed part, s.
THERMAL_SPEED_RAD_S = 0.5
THERMAL_MOVE_S = 1.0
#: Simulated standing time of one measurement (settle, samples), s.
THERMAL_DWELL_S = 3.0
#: Joint temperature a world without a warm-up drift reports, °C.
COLD_C = 25.0
Array = NDArray[np.float64]


@dataclass(frozen=True)
class WorldMeasurement:
    """An averaged simulated tracker measurement, tracker frame, metres.

    ``std_m`` is the standard uncertainty of the mean (per-sample sigma / sqrt(n));
    ``sigma_m`` the per-sample sigma of the noise model; ``rms_m`` the RMS distance of the
    samples from their mean.
    """

    mean_m: tuple[float, float, float]
    std_m: tuple[float, float, float]
    sigma_m: tuple[float, float, float]
    rms_m: float
    n: int


@dataclass(frozen=True)
class SimMotion:
    """One joint motion in progress: a linear sweep from ``q_from_rad`` to ``q_to_rad``.

    ``t0`` is its ``time.monotonic()`` start, ``duration_s`` its length in seconds.
    """

    q_from_rad: Array
    q_to_rad: Array
    t0: float
    duration_s: float

    def position(self, now: float) -> Array:
        """Joint angles (radians, shape ``(dof,)``) at monotonic time ``now``."""
        if self.duration_s <= 0.0:
            return self.q_to_rad.copy()
        s = min(1.0, max(0.0, (now - self.t0) / self.duration_s))
        return np.asarray(self.q_from_rad + s * (self.q_to_rad - self.q_from_rad), dtype=float)


class SimWorld:
    """A virtual robot and its current pose.

    Parameters
    ----------
    cell : VirtualCell
        The virtual robot and tracker (``robocal.simulation.VirtualCell``).
    seed : int
        Seed of the world's noise generator (joint repeatability, tracker noise).
    """

    def __init__(self, cell: Any, *, seed: int = 0, thermal: Any = None) -> None:
        self.cell = cell
        #: planted warm-up drift (``robocal.simulation.WarmUpDrift``) or None
        self.thermal = thermal
        self.rng = np.random.default_rng(seed)
        robot = cell.robot
        self.dof: int = int(robot.dof)
        self.robot_name: str = str(getattr(robot, "name", "robot"))
        limits = getattr(robot, "joint_limits_rad", None)
        if limits is None:
            limits = robot.joint_limits
        lim = np.asarray(limits, dtype=float).reshape(self.dof, 2)
        self.joint_limits_rad: tuple[tuple[float, float], ...] = tuple(
            (float(lo), float(hi)) for lo, hi in lim
        )
        q0 = np.clip(np.zeros(self.dof), lim[:, 0], lim[:, 1])
        self.q_cmd_rad: Array = q0.copy()
        self._q_actual: Array = q0.copy()
        self.moves = 0
        self.motion: SimMotion | None = None
        self.halts = 0
        self.last_halt_time: float | None = None
        # Simulators of one world may run in different threads only via to_thread; keep it safe.
        self._lock = threading.Lock()

    @classmethod
    def create(cls, robot: str = DEFAULT_ROBOT, scenario: str = "paper", seed: int = 1, *,
               warmup_drift_mm: float = 0.0) -> SimWorld:
        """Build a world around ``VirtualCell.create(robot, scenario, seed)``; with a planted
        warm-up drift of ``warmup_drift_mm`` over 30 min of motion when positive."""
        from robocal.simulation import VirtualCell, WarmUpDrift

        cell = VirtualCell.create(robot=robot, scenario=scenario, seed=seed)
        thermal = None
        if warmup_drift_mm > 0:
            thermal = WarmUpDrift.planted(cell.robot, drift_m=warmup_drift_mm * 1e-3)
        return cls(cell, seed=seed + 1, thermal=thermal)

    @property
    def joint_limits_deg(self) -> tuple[tuple[float, float], ...]:
        """Joint limits in degrees (the form driver options take)."""
        return tuple((math.degrees(lo), math.degrees(hi)) for lo, hi in self.joint_limits_rad)

    def within_limits(self, q_rad: Any) -> bool:
        """Return True if every joint of ``q_rad`` is inside the limits."""
        q = np.asarray(q_rad, dtype=float)
        lim = np.asarray(self.joint_limits_rad)
        return bool(
            q.shape == (self.dof,)
            and np.all(np.isfinite(q))
            and np.all(q >= lim[:, 0])
            and np.all(q <= lim[:, 1])
        )

    @property
    def q_actual_rad(self) -> Array:
        """Actual joint angles now, radians, shape ``(dof,)`` (interpolated while moving)."""
        with self._lock:
            return self._position_locked(time.monotonic())

    def _position_locked(self, now: float) -> Array:
        if self.motion is not None:
            return self.motion.position(now)
        return self._q_actual.copy()

    @property
    def moving(self) -> bool:
        """True while a motion started by :meth:`start_motion` is neither finished nor halted."""
        return self.motion is not None

    def move(self, q_cmd_rad: Any) -> Array:
        """Put the robot at ``q_cmd_rad`` (radians) at once; return the actual joints reached.

        Ends any motion in progress.
        """
        q = np.asarray(q_cmd_rad, dtype=float).reshape(self.dof)
        with self._lock:
            self.motion = None
            return self._settle_locked(q)

    def _settle_locked(self, q: Array) -> Array:
        if self.thermal is not None:
            step = float(np.max(np.abs(q - self._q_actual)))
            self.thermal.advance(step / THERMAL_SPEED_RAD_S + THERMAL_MOVE_S, moving=True)
        actual = np.asarray(self.cell.actual_joints(q[None, :], self.rng), dtype=float)[0]
        self.q_cmd_rad = q.copy()
        self._q_actual = actual
        self.moves += 1
        return actual.copy()

    def start_motion(self, q_cmd_rad: Any, duration_s: float) -> SimMotion:
        """Start sweeping from the current position to ``q_cmd_rad`` over ``duration_s`` s.

        A motion already in progress is replaced from the point it has reached. Returns the
        motion; pass it to :meth:`finish_motion` when its time is up.
        """
        q = np.asarray(q_cmd_rad, dtype=float).reshape(self.dof)
        with self._lock:
            now = time.monotonic()
            start = self._position_locked(now)
            self.motion = SimMotion(start, q.copy(), now, max(0.0, float(duration_s)))
            self.q_cmd_rad = q.copy()
            return self.motion

    def finish_motion(self, motion: SimMotion) -> bool:
        """Settle ``motion`` at its target (with repeatability noise); False if it was halted.

        Returns False, changing nothing, when ``motion`` is no longer the current motion
        (halted or replaced).
        """
        with self._lock:
            if self.motion is not motion:
                return False
            self.motion = None
            self._settle_locked(motion.q_to_rad)
            return True

    def halt(self) -> Array:
        """Stop any motion where it is now; return the joints (radians). Idempotent.

        The commanded position becomes the halted one, so a later move starts from there.
        """
        with self._lock:
            now = time.monotonic()
            q = self._position_locked(now)
            if self.motion is not None:
                self.motion = None
                self._q_actual = q.copy()
                self.q_cmd_rad = q.copy()
                self.halts += 1
                self.last_halt_time = now
            return q

    def joint_temperatures(self) -> tuple[tuple[float, ...], float]:
        """Joint temperatures (°C, one per joint) and the simulated time (s) they hold at."""
        with self._lock:
            if self.thermal is None:
                return (COLD_C,) * self.dof, 0.0
            return tuple(float(v) for v in self.thermal.temps_c), float(self.thermal.time_s)

    def true_reflector_position(self) -> Array:
        """Return the true reflector centre (3,) for the actual joints, tracker frame, metres."""
        q = self.q_actual_rad
        return np.asarray(self.cell.reflector_position(q[None, :]), dtype=float)[0]

    def measure(self, n: int, *, glitch: bool = False) -> WorldMeasurement:
        """Simulate ``n`` tracker samples of the reflector and average them.

        ``glitch`` adds a beam-break glitch (a few mm) to the mean, as a real tracker that
        re-locked on a wrong return would report.
        """
        n = max(1, int(n))
        with self._lock:
            q = np.repeat(self._position_locked(time.monotonic())[None, :], n, axis=0)
            points, sigma = self.cell.measure(q, self.rng)
            if self.thermal is not None:
                self.thermal.advance(THERMAL_DWELL_S, moving=False)
                shift = (self.thermal.positions(self.cell, q[:1], self.thermal.temps_c)
                         - self.cell.reflector_position(q[:1]))
                points = np.asarray(points, dtype=float) + shift
            points = np.asarray(points, dtype=float)
            sigma = np.asarray(sigma, dtype=float)
            mean = points.mean(axis=0)
            if glitch:
                mean = np.asarray(self.cell.outlier(mean[None, :], self.rng), dtype=float)[0]
        rms = float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))
        s = sigma[0]
        std = s / math.sqrt(n)
        return WorldMeasurement(
            mean_m=(float(mean[0]), float(mean[1]), float(mean[2])),
            std_m=(float(std[0]), float(std[1]), float(std[2])),
            sigma_m=(float(s[0]), float(s[1]), float(s[2])),
            rms_m=rms,
            n=n,
        )
