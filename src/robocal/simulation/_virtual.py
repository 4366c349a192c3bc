"""Virtual robot with planted constant and joint-dependent errors, and a virtual tracker.

Scenarios (the planted "truth"):

``nominal``      no kinematic error, only base and reflector placement
``constant``     constant 6-DoF errors per joint (~0.3 mm, ~0.5 mrad), the traditional model
``paper``        constant errors plus joint-dependent harmonics (orders 1-3; bearing runout and
                 wobble, rotating-centre offsets), pitch error (linear in q) on every joint
``strain-wave``  ``paper`` plus strain-wave ripple cos/sin(m N q), m = 1, 2, where the robot
                 file gives gear ratios
``fine-map``     constant errors plus a fine-grained repeatable joint-angle error per joint
                 (strongest near 17 cycles/rev, ~0.2-0.4 mrad, as seen on real UR10 data) and
                 gravity torsion where the robot file gives masses

The tracker sits at the origin of its frame; noise is anisotropic (radial 5 µm + 0.5 µm/m,
transverse 7.5 µm + 3 µm/m, 1 sigma), joints repeat to ~5 µrad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from robocal.errors import ConfigError
from robocal.kinematics import (
    ErrorModelSpec,
    KinematicModel,
    ParameterLayout,
    RobotDescription,
    Term,
    euler_xyz_to_matrix,
    load_robot,
)

Array = NDArray[np.float64]
SCENARIOS = ("nominal", "constant", "paper", "strain-wave", "fine-map")


@dataclass(frozen=True)
class TrackerNoise:
    """Laser-tracker noise model (1 sigma, metres), range-dependent."""

    radial_m: float = 5e-6
    radial_per_m: float = 0.5e-6
    transverse_m: float = 7.5e-6
    transverse_per_m: float = 3e-6

    def sigmas(self, p: Array) -> tuple[Array, Array]:
        """Radial and transverse sigma (n,) for points ``p`` (n, 3) in the tracker frame."""
        rho = np.linalg.norm(p, axis=1)
        return (self.radial_m + self.radial_per_m * rho,
                self.transverse_m + self.transverse_per_m * rho)

    def covariances(self, p: Array) -> Array:
        """Per-point covariance (n, 3, 3), m^2."""
        sr, st = self.sigmas(p)
        u = p / np.linalg.norm(p, axis=1, keepdims=True)
        uu = u[:, :, None] * u[:, None, :]
        return (sr**2)[:, None, None] * uu + (st**2)[:, None, None] * (np.eye(3) - uu)

    def sample(self, p: Array, rng: np.random.Generator) -> Array:
        """Noise vectors (n, 3) drawn from the covariance at ``p``."""
        sr, st = self.sigmas(p)
        u = p / np.linalg.norm(p, axis=1, keepdims=True)
        g = rng.standard_normal(p.shape)
        radial = np.einsum("ni,ni->n", g, u)
        transverse = g - radial[:, None] * u
        return sr[:, None] * radial[:, None] * u + st[:, None] * transverse

    def axis_sigmas(self, p: Array) -> Array:
        """Per-axis standard deviations (n, 3): square roots of the covariance diagonal."""
        return np.sqrt(np.einsum("nii->ni", self.covariances(p)))


def truth_spec(robot: RobotDescription, scenario: str) -> ErrorModelSpec:
    """The error-model structure a scenario plants (a fit that "knows the truth" uses it)."""
    dof = robot.dof
    if scenario not in SCENARIOS:
        raise ConfigError(f"unknown scenario {scenario!r} (choose from {', '.join(SCENARIOS)})")
    if scenario == "nominal":
        return ErrorModelSpec(dof, (), label="truth:nominal")
    spec = ErrorModelSpec.constant(dof)
    extra: list[Term] = []
    if scenario in ("paper", "strain-wave"):
        for j in range(dof):
            for c in ("dx", "dy", "dz", "ex", "ey", "ez"):
                for k in (1, 2):
                    extra += [Term(j, c, "cos", k), Term(j, c, "sin", k)]
            extra.append(Term(j, "ez", "poly", 1))  # pitch error r*q
        if scenario == "strain-wave":
            for j, jt in enumerate(robot.joints):
                if jt.gear_ratio:
                    for m in (1, 2):
                        extra += [Term(j, "ez", "swcos", m), Term(j, "ez", "swsin", m)]
    if scenario == "fine-map":
        for j in range(dof):
            for k in (3, 5, 17, 34):
                extra += [Term(j, "ez", "cos", k), Term(j, "ez", "sin", k)]
            if robot.has_masses and j in (1, 2):
                extra.append(Term(j, "ez", "gravity"))
    return spec.with_terms(extra, label=f"truth:{scenario}")


def _plant(model: KinematicModel, scenario: str, rng: np.random.Generator) -> Array:
    """Draw planted parameter values with realistic magnitudes."""
    x = model.nominal_params()
    for k, term in enumerate(model.spec.terms):
        i = ParameterLayout.OFFSET + k
        trans = term.component.startswith("d")
        if term.family == "const":
            x[i] = rng.normal(0.0, 3e-4 if trans else 5e-4)
        elif term.family in ("cos", "sin"):
            if scenario == "fine-map":
                amp = {3: 6e-5, 5: 8e-5, 17: 3e-4, 34: 1e-4}[term.index]
                x[i] = rng.normal(0.0, amp / math.sqrt(2))
            else:
                # bearing runout / wobble: tens of µm and µrad, decaying with order
                scale = (6e-5 if trans else 9e-5) / term.index
                x[i] = rng.normal(0.0, scale)
        elif term.family == "poly":
            x[i] = rng.normal(0.0, 2e-4)  # pitch error: Legendre P1 over the range
        elif term.family in ("swcos", "swsin"):
            x[i] = rng.normal(0.0, 4e-5 / term.index)
        elif term.family == "gravity":
            x[i] = abs(rng.normal(0.0, 1.5e-6)) + 5e-7  # rad/(N m): 50-300 µrad at full load
    return x


@dataclass
class VirtualCell:
    """A robot with planted errors, measured by a laser tracker.

    The true reflector position for joint values q is ``truth_model.positions(q, truth_params)``.
    """

    robot: RobotDescription
    scenario: str
    truth_model: KinematicModel
    truth_params: Array
    noise: TrackerNoise = field(default_factory=TrackerNoise)
    joint_noise_rad: float = 5e-6
    seed: int = 0
    #: Planted drift (issue 31): joint zero offsets growing by these rates (deg/day, one
    #: per joint; empty: none) over the simulated clock ``sim_days``, which tests advance.
    drift_deg_per_day: tuple[float, ...] = ()
    sim_days: float = 0.0

    @classmethod
    def create(cls, robot: str | RobotDescription = "fanuc_lrmate200i", scenario: str = "paper",
               seed: int = 0, *, tracker_distance_m: float | None = None,
               noise: TrackerNoise | None = None, joint_noise_rad: float = 5e-6) -> VirtualCell:
        """Build a cell with a seeded planted truth.

        The robot base stands ``tracker_distance_m`` (default: about 1.5 x reach) from the
        tracker, turned so that the tracker looks at the robot's front (+x of the base).
        """
        rob = load_robot(robot) if isinstance(robot, str) else robot
        rng = np.random.default_rng(seed)
        reach = sum(abs(j.a) + abs(j.d) for j in rob.joints)
        dist = tracker_distance_m if tracker_distance_m is not None else max(1.2, 1.5 * reach)
        yaw = math.pi + rng.uniform(-0.2, 0.2)
        T = np.eye(4)
        T[:3, :3] = euler_xyz_to_matrix(rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), yaw)
        T[:3, 3] = [dist, rng.uniform(-0.2, 0.2), rng.uniform(-0.5, -0.2)]
        spec = truth_spec(rob, scenario)
        model = KinematicModel(rob, spec, T)
        x = _plant(model, scenario, rng)
        x[ParameterLayout.TOOL] = np.asarray(rob.tool) + rng.normal(0.0, 2e-3, 3)
        return cls(robot=rob, scenario=scenario, truth_model=model, truth_params=x,
                   noise=noise or TrackerNoise(), joint_noise_rad=joint_noise_rad, seed=seed)

    @property
    def T_tracker_base(self) -> Array:
        """True pose of the robot base in the tracker frame (4, 4), m."""
        return self.truth_model.base_transform(self.truth_params)

    @property
    def tracker_in_base(self) -> Array:
        """Tracker position in the robot base frame (3,), m."""
        T = self.T_tracker_base
        return -T[:3, :3].T @ T[:3, 3]

    def actual_joints(self, q_cmd: Array, rng: np.random.Generator) -> Array:
        """Where the joints really are when commanded to ``q_cmd`` (n, dof): repeatability noise."""
        q_cmd = np.atleast_2d(np.asarray(q_cmd, dtype=float))
        return q_cmd + rng.normal(0.0, self.joint_noise_rad, q_cmd.shape)

    def joint_drift_rad(self) -> Array:
        """The planted joint zero drift now (dof,) rad: ``drift_deg_per_day * sim_days``.

        The joints read back stay the commanded ones (an encoder does not see its own zero
        move); only where the arm really is changes.
        """
        rate = np.zeros(self.robot.dof)
        rate[:len(self.drift_deg_per_day)] = self.drift_deg_per_day
        return np.radians(rate * self.sim_days)

    def reflector_position(self, q_actual: Array) -> Array:
        """True reflector positions (n, 3) m in the tracker frame."""
        q = np.atleast_2d(q_actual)
        if self.drift_deg_per_day:
            q = q + self.joint_drift_rad()
        return self.truth_model.positions(q, self.truth_params)

    def nominal_position(self, q: Array) -> Array:
        """Where the nominal robot (true base and reflector) puts the reflector (n, 3) m,
        tracker frame: where a program written with nominal kinematics expects it."""
        nominal = KinematicModel(self.robot, ErrorModelSpec(self.robot.dof, ()),
                                 self.T_tracker_base)
        x = nominal.nominal_params()
        x[ParameterLayout.TOOL] = self.truth_params[ParameterLayout.TOOL]
        return nominal.positions(np.atleast_2d(q), x)

    def nominal_error(self, q: Array) -> Array:
        """Distance (n,) between truth and the nominal model with true base and reflector."""
        return np.linalg.norm(self.reflector_position(q) - self.nominal_position(q), axis=1)

    def measure(self, q_actual: Array, rng: np.random.Generator) -> tuple[Array, Array]:
        """Noisy tracker readings (n, 3) m and their per-axis sigmas (n, 3) m."""
        p = self.reflector_position(q_actual)
        return p + self.noise.sample(p, rng), self.noise.axis_sigmas(p)

    def outlier(self, points: Array, rng: np.random.Generator) -> Array:
        """Add a beam-break glitch of 1-5 mm in a random direction to each point."""
        points = np.atleast_2d(points)
        d = rng.standard_normal(points.shape)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return points + d * rng.uniform(1e-3, 5e-3, (points.shape[0], 1))

    def random_joints(self, n: int, rng: np.random.Generator, margin_rad: float = 0.05,
                      ranges: Array | None = None) -> Array:
        """Uniform random joint values (n, dof) within the limits (or ``ranges`` (dof, 2))."""
        lim = self.robot.joint_limits if ranges is None else np.asarray(ranges, dtype=float)
        lo = lim[:, 0] + margin_rad
        hi = lim[:, 1] - margin_rad
        return rng.uniform(lo, hi, (n, self.robot.dof))

    def simulate(self, q_cmd: Array, rng: np.random.Generator, *,
                 outlier_fraction: float = 0.0
                 ) -> tuple[Array, Array, Array, NDArray[np.intp]]:
        """Command, move and measure.

        Returns (q reported by the controller (= commanded), measured points (n, 3),
        per-axis sigmas (n, 3), indices of planted outliers).
        """
        q_cmd = np.atleast_2d(np.asarray(q_cmd, dtype=float))
        q_act = self.actual_joints(q_cmd, rng)
        p, s = self.measure(q_act, rng)
        idx = np.array([], dtype=np.intp)
        if outlier_fraction > 0:
            k = max(1, round(outlier_fraction * len(q_cmd)))
            idx = np.sort(rng.choice(len(q_cmd), size=k, replace=False))
            p[idx] = self.outlier(p[idx], rng)
        return q_cmd, p, s, idx
