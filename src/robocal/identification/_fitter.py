"""Fit options and the fitter one fit runs on (engine, base registration, baseline, constant).

Apart from :mod:`robocal.identification._fit` so that :mod:`robocal.identification._auto`
(which :func:`~robocal.identification.fit` calls) can use :class:`Fitter` without importing
the module that imports it (ADR 0038).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal._core.measurements import MeasurementSet
from robocal.errors import ConfigError, DataError
from robocal.identification._engine import Engine, EngineSettings, Solution, model_error_sigma
from robocal.identification._linalg import median
from robocal.identification._models import constant_spec, high_order_spec
from robocal.kinematics import (
    ErrorModelSpec,
    KinematicModel,
    ParameterLayout,
    RobotDescription,
    rigid_fit,
)

__all__ = ["FitOptions", "Fitter", "initial_base"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FitOptions(EngineSettings):
    """Options of :func:`fit` (SI units).

    Measurement model
        ``noise``: tracker sigma model (whitening, ML weights). ``use_point_sigma``: use the
        data's per-point ``sx, sy, sz`` where given (diagonal covariance), each combined in
        quadrature with the model error they leave out: ``point_sigma_floor_m`` (m), or when
        None, a variance component estimated from the constant model's residuals
        (``max(0, r'r/(m - p) - mean(s^2)``, zero when the sigmas explain the residuals).
    Start
        ``tool_m``: flange -> reflector offset to start from (default: the robot file's).
    Solver
        ``rank_tol``: relative singular-value threshold of the column-scaled identification
        Jacobian below which parameter combinations count as unidentifiable (held fixed).
        ``max_iter``, ``ftol``: Levenberg-Marquardt limits; ``creep_ftol``,
        ``creep_remaining``: a run that hits ``max_iter`` with a last relative decrease below
        ``creep_ftol``, or whose undamped Gauss-Newton step predicts a relative decrease below
        ``creep_remaining`` (it stopped that close to the minimum), is kept (status
        ``max-iterations``, reported as not converged), otherwise it is an error.
        ``chunk``: poses per Jacobian block.
    Outliers
        ``detect_outliers``; ``outlier_alpha``: family-wise false-alarm rate of the normalised
        residual test (Bonferroni over poses); ``outlier_sigma_min``: never flag below this
        many robust sigmas (real residuals are heavy-tailed model error; only gross errors such
        as beam-break glitches are outliers); ``outlier_sigma``: fixed threshold in robust
        sigmas instead of both; ``outlier_max_rounds``, ``outlier_max_fraction``. The same
        test screens validation poses (reported, and left out of ``validation``).
    ``high-order``
        ``order`` of the Fourier harmonics, ``pitch`` (linear term on the joint rotation),
        ``strain_wave`` multiples of the gear ratio.
    ``auto``
        ``cv_folds``; ``cv_group_tol_deg`` (poses this close in every joint share a fold);
        ``auto_max_order``; ``auto_ripple_orders`` (harmonics cos/sin(k q) of the rotation
        about each joint axis tried one at a time: fine gear/encoder ripple);
        ``auto_ripple_screen`` (how many of them, ranked by their score-test gain at the
        current model, are cross-validated in each round); ``auto_maps``
        and ``map_spacing_deg`` (the finest knot spacing of joint-angle maps; sparser data
        widen it until a knot's support holds ``map_min_points`` poses on average); ``map_lambdas``
        (relative smoothness weights tried by CV);
        ``map_ridge_deg`` (prior sigma of map values); knots with fewer than
        ``map_min_points`` poses in their support are tied to their neighbours (prior sigma
        ``map_tie_deg`` per knot step) and shrunk to zero (prior sigma ``map_weak_deg``), so
        thin data and gaps are bridged smoothly and left to the parametric terms;
        ``auto_gravity``;
        ``auto_strain_wave``; ``auto_min_improvement`` (relative CV gain needed to add a term
        group); ``seed`` of the CV folds.
    Sanity
        ``sanity``: refuse data whose joints look like radians or positions like metres, and
        data the nominal robot cannot explain: median pose error above
        ``sanity_baseline_mm`` after fitting only base and reflector (wrong robot or variant).
    Reuse (:func:`refit_frozen`)
        ``reuse_fill_gaps``: refit the map knots the earlier data did not support (runs of
        knots at least ``reuse_min_gap_deg`` wide with fewer than ``map_min_points`` earlier
        poses each) where the new data reach them; the other knots keep their values within
        ``reuse_anchor_deg``, and the change is smoothed with the earlier
        smoothness weight times ``reuse_smoothing``. ``reuse_link_mm`` / ``reuse_link_deg``:
        prior sigmas of the constant link errors around their earlier values (the joint
        offsets, base and reflector are free; ``inf`` frees the links too).
    Output
        ``fallback``: store a constant-model fallback for poses outside the covered joint range
        (the training range of each joint widened by ``coverage_margin_deg``; the full joint
        range where the joint has no joint-dependent terms, or only periodic ones and the data
        cover a full turn).
    """

    # the solver and outlier settings are inherited from EngineSettings
    tool_m: tuple[float, float, float] | None = None
    order: int = 2
    pitch: bool = True
    strain_wave: tuple[int, ...] = (1, 2)
    cv_folds: int = 5
    cv_group_tol_deg: float = 0.5
    auto_max_order: int = 3
    auto_ripple_orders: tuple[int, ...] = tuple(range(4, 41))
    auto_ripple_screen: int = 8
    auto_maps: bool = True
    map_spacing_deg: float = 1.25
    map_lambdas: tuple[float, ...] = (1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0, 1e3, 1e4)
    map_ridge_deg: float = 0.1
    map_min_points: int = 8
    map_tie_deg: float = 5e-4
    map_weak_deg: float = 2e-3
    reuse_fill_gaps: bool = True
    reuse_min_gap_deg: float = 10.0
    reuse_anchor_deg: float = 1e-3
    reuse_smoothing: float = 30.0
    reuse_link_mm: float = 0.05
    reuse_link_deg: float = 0.005
    auto_gravity: bool = True
    auto_strain_wave: bool = True
    auto_min_improvement: float = 0.01
    seed: int = 0
    sanity: bool = True
    sanity_baseline_mm: float = 10.0
    fallback: bool = True
    coverage_margin_deg: float = 5.0

    def __post_init__(self) -> None:
        if not 0 < self.rank_tol < 1:
            raise ConfigError("rank_tol must be in (0, 1)")
        if self.max_iter < 1 or self.chunk < 1:
            raise ConfigError("max_iter and chunk must be positive")
        if self.order < 0 or self.auto_max_order < 0:
            raise ConfigError("orders must not be negative")
        if self.cv_folds < 2:
            raise ConfigError("cv_folds must be at least 2")
        if self.auto_ripple_screen < 1:
            raise ConfigError("auto_ripple_screen must be at least 1")
        if self.map_min_points < 1:
            raise ConfigError("map_min_points must be at least 1")
        if self.seed < 0:
            raise ConfigError("seed must not be negative (it seeds the CV folds)")
        if self.point_sigma_floor_m is not None and not 0 <= self.point_sigma_floor_m < 1e-2:
            raise ConfigError("point_sigma_floor_m must be in [0, 0.01) m")
        for f in fields(self):   # NaN passes every comparison below; it is never a setting
            v = getattr(self, f.name)
            if isinstance(v, float) and v != v:
                raise ConfigError(f"{f.name} must be a number, not NaN")
        for name in ("map_spacing_deg", "map_ridge_deg", "map_tie_deg", "map_weak_deg"):
            if not 0 < getattr(self, name) < float("inf"):
                raise ConfigError(f"{name} must be a positive finite number")

    def engine_settings(self) -> EngineSettings:
        """The subset the engine needs."""
        return EngineSettings(**{f.name: getattr(self, f.name) for f in fields(EngineSettings)})

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (SI)."""
        d = asdict(self)
        d["noise"] = asdict(self.noise)
        return d


def initial_base(robot: RobotDescription, data: MeasurementSet, tool: Array) -> Array:
    """Tracker <- base by rigid registration of the nominal FK to the measurements."""
    m0 = KinematicModel(robot, ErrorModelSpec(robot.dof, ()))
    x0 = m0.nominal_params()
    x0[ParameterLayout.TOOL] = tool
    src = m0.positions(data.q, x0)
    if np.linalg.matrix_rank(src - src.mean(axis=0), tol=1e-6) < 2:
        raise DataError("the poses do not span a plane; cannot register the robot base")
    T = rigid_fit(src, data.p)
    # one trimmed re-registration against gross outliers
    d = np.linalg.norm(data.p - (src @ T[:3, :3].T + T[:3, 3]), axis=1)
    good = d <= max(3.0 * median(d), 1e-3)
    if good.sum() >= 3 and not good.all():
        T = rigid_fit(src[good], data.p[good])
    return T


class Fitter:
    """One fit: engine, baseline, constant, and the requested model."""

    def __init__(self, robot: RobotDescription, data: MeasurementSet, opts: FitOptions) -> None:
        self.robot = robot
        self.data = data
        self.opts = opts
        self.engine = Engine(robot, data, opts.engine_settings())
        self.tool0 = np.asarray(opts.tool_m if opts.tool_m is not None else robot.tool, float)
        self.T = initial_base(robot, data, self.tool0)
        self._baselines: dict[tuple[bool, bytes], Solution] = {}

    def model(self, spec: ErrorModelSpec) -> KinematicModel:
        return KinematicModel(self.robot, spec, self.T)

    def baseline(self, inliers: NDArray[np.bool_] | None = None, robust: bool = False
                 ) -> Solution:
        """The nominal model with base and reflector fitted (the same poses: fitted once)."""
        n = len(self.data.q)
        key = (robust, (np.ones(n, dtype=bool) if inliers is None else inliers).tobytes())
        if key not in self._baselines:
            m = self.model(ErrorModelSpec(self.robot.dof, ()))
            x0 = m.nominal_params()
            x0[ParameterLayout.TOOL] = self.tool0
            self._baselines[key] = self.engine.solve(m, x0, inliers=inliers, robust=robust,
                                                     what="nominal (base + reflector) model")
        return self._baselines[key]

    def constant(self, start: Solution) -> Solution:
        m = self.model(constant_spec(self.robot))
        sol = self.engine.solve(m, start.model.transfer(start.x, m), what="constant model")
        if self.opts.point_sigma_floor_m is None and self.opts.use_point_sigma:
            # per-point sigmas plus the model error they leave out, estimated from the
            # constant model's residuals (a variance component), then solved again
            tau = model_error_sigma(self.data, sol)
            if tau > 0:
                self.engine.reweight(tau)
                self._baselines.clear()
                sol = self.engine.solve(m, sol.x, what="constant model")
        return sol

    def high_order(self, start: Solution) -> Solution:
        spec = high_order_spec(self.robot, order=self.opts.order, pitch=self.opts.pitch,
                               strain_wave=self.opts.strain_wave)
        m = self.model(spec)
        return self.engine.solve(m, start.model.transfer(start.x, m), what="high-order model",
                                 inliers=start.inliers)
