"""What a report is made from: :class:`ReportInput` and its parts.

Everything here is SI (m, rad) like the rest of robocal; the report converts to mm and deg on
screen. Fitted models are given as identification results (:class:`FitResult`,
:class:`CPAResult`), as bare :class:`~robocal.kinematics.CalibratedModel` objects (a MODEL.json
file) or as a ready :class:`ModelEntry`; :func:`model_entry` normalises each and refuses
anything else.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, TypeAlias

import numpy as np
from numpy.typing import NDArray

from robocal._core.measurements import MeasurementSet
from robocal._core.model_names import CPA, CPA_CLASSICAL, MODELS, NOMINAL
from robocal.errors import ConfigError
from robocal.identification import Accuracy, CPAResult, FitResult
from robocal.kinematics import CalibratedModel, RobotDescription

Array = NDArray[np.float64]

_LABELS: dict[str, str] = {
    "constant": "Constant error model",
    "high-order": "High-order joint-dependent model",
    "auto": "Auto-selected model",
}
#: Display order and labels of the well-known model names (robocal._core.model_names).
KNOWN_MODELS: dict[str, str] = {
    NOMINAL: "Nominal (base + reflector fitted)",
    CPA: "Circle Point Analysis",
    CPA_CLASSICAL: "Circle Point Analysis, classical (not polished)",
    **{name: _LABELS[name] for name in MODELS},
}
#: Which model is judged when ``ReportInput.selected`` is not given (first present wins):
#: the richest fitted model, CPA last.
SELECTION_ORDER = (*reversed(MODELS), CPA)
BASELINE = NOMINAL


#: The reach up to which the default RMS limit applies unscaled, m.
REACH_REF_M = 2.0


@dataclass(frozen=True)
class Acceptance:
    """Thresholds of the verdict, applied to the held-out (validation) poses.

    ``min_percent_described``: RMS-based share of the nominal error the model must describe for
    "succeeded" (below it: "marginal"; zero or less: "failed"). ``max_rms_mm`` (default
    0.5 mm, the accuracy a calibrated industrial arm of up to ~2 m reach is expected to reach,
    scaled in proportion for a longer reach unless given: see :meth:`for_reach`; set it per
    cell, ``None`` switches it off) and ``max_error_mm`` (optional): absolute
    limits (exceeded: "failed"). A held-out RMS above ``implausible_rms_mm`` fails in any
    case: no calibrated robot is that far off, so the data or the robot description are
    wrong (joints in radians, positions in metres, another robot variant). Outlier fractions above
    ``max_outlier_fraction`` make the result marginal, above ``fail_outlier_fraction`` failed.
    A validation RMS above ``max_overfit_ratio`` times the calibration RMS (and more than
    ``overfit_floor_mm`` above it) flags over-fitting (marginal); the ratio is first divided
    by ``sqrt(m / (m - p))``, what fitting p free parameters to m coordinates alone gives.
    Validation poses whose error under the judged model exceeds ``validation_outlier_factor``
    times the median error are treated as measurement glitches (beam breaks): listed, marked
    and left out of the statistics, and counted as outliers (0 disables this). Validation
    poses whose predicted position is far less certain than the calibration poses' (the
    calibration poses leave the model nearly free there; see
    :func:`robocal.identification.extrapolation`) make the result marginal.
    """

    min_percent_described: float = 50.0
    max_rms_mm: float | None = 0.5
    max_error_mm: float | None = None
    implausible_rms_mm: float = 25.0
    max_outlier_fraction: float = 0.05
    fail_outlier_fraction: float = 0.20
    max_overfit_ratio: float = 1.5
    overfit_floor_mm: float = 0.005
    validation_outlier_factor: float = 5.0
    #: The default RMS limit grows with the robot: ``max_rms_mm`` per 2 m of reach (never
    #: below it). False once a limit is given (CLI ``--max-rms-mm``, config ``max_rms_mm``).
    scale_with_reach: bool = True

    def for_reach(self, reach_m: float) -> Acceptance:
        """This acceptance with the RMS limit scaled to a robot of ``reach_m`` (m) reach."""
        if not self.scale_with_reach or self.max_rms_mm is None or not reach_m > REACH_REF_M:
            return self
        return replace(self, max_rms_mm=self.max_rms_mm * reach_m / REACH_REF_M,
                       scale_with_reach=False)

    def __post_init__(self) -> None:
        for name in ("min_percent_described", "max_outlier_fraction", "fail_outlier_fraction",
                     "max_overfit_ratio", "overfit_floor_mm", "validation_outlier_factor",
                     "implausible_rms_mm"):
            if not math.isfinite(float(getattr(self, name))):
                raise ConfigError("must be a finite number", key=f"acceptance.{name}")
        for name in ("max_rms_mm", "max_error_mm"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ConfigError("must be a positive number", key=f"acceptance.{name}")

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any] | None) -> Acceptance:
        """Build from a config table; unknown keys raise :class:`ConfigError`."""
        if not d:
            return cls()
        allowed = set(cls.__dataclass_fields__)
        bad = sorted(set(d) - allowed)
        if bad:
            raise ConfigError(f"unknown key (allowed: {', '.join(sorted(allowed))})",
                              key=f"acceptance.{bad[0]}")
        # None is meant for the optional limits; __post_init__ checks the rest
        kwargs: dict[str, Any] = {k: (None if v is None else float(v)) for k, v in d.items()
                                  if k != "scale_with_reach"}
        kwargs["scale_with_reach"] = bool(d.get("scale_with_reach", "max_rms_mm" not in d))
        return cls(**kwargs)


@dataclass(frozen=True)
class IsoPoseSeries:
    """Repeated measurements of one ISO 9283 pose (P1..P5).

    ``command``: the commanded position (3,) m, i.e. where the controller believes it sends
    the robot; ``attained``: the measured positions (n, 3) m, same frame (tracker frame unless
    stated in ``frame``). ``predicted`` (optional, (3,) m): where the calibrated model says
    the commanded joints put the reflector; AP against it is the accuracy left after
    compensating with that model.
    """

    name: str
    command: Array
    attained: Array
    predicted: Array | None = None
    frame: str = "tracker"

    def __post_init__(self) -> None:
        c = np.asarray(self.command, dtype=float).reshape(3)
        a = np.atleast_2d(np.asarray(self.attained, dtype=float))
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 1:
            raise ConfigError(f"ISO pose {self.name}: attained positions must be (n, 3)")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a))):
            raise ConfigError(f"ISO pose {self.name}: positions must be finite")
        object.__setattr__(self, "command", c)
        object.__setattr__(self, "attained", a)
        if self.predicted is not None:
            object.__setattr__(self, "predicted",
                               np.asarray(self.predicted, dtype=float).reshape(3))


@dataclass(frozen=True)
class MeasurementLog:
    """What happened while measuring (all optional).

    ``weather``: samples such as ``{"temperature_c": 21.3, "pressure_hpa": 1012,
    "humidity_pct": 40}``. ``joint_temps``: the joint temperatures (°C per joint) of every
    measurement in order, ``joint_temps_t_s`` when each was taken (s since the first).
    ``extra``: anything else worth showing (str -> JSON value).
    """

    planned: int | None = None
    measured: int | None = None
    retries: int = 0
    failed: int = 0
    beam_losses: int = 0
    duration_s: float | None = None
    weather: Sequence[Mapping[str, float]] = ()
    tracker: str = ""
    controller: str = ""
    notes: Sequence[str] = ()
    extra: Mapping[str, Any] = field(default_factory=dict)
    joint_temps: Sequence[Sequence[float]] = ()
    joint_temps_t_s: Sequence[float] = ()

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any] | None) -> MeasurementLog:
        """Build from a loose mapping (e.g. a daemon's campaign statistics); unknown keys go to
        ``extra``."""
        if not d:
            return cls()
        known = set(cls.__dataclass_fields__)
        kw: dict[str, Any] = {k: v for k, v in d.items() if k in known and k != "extra"}
        extra = {k: v for k, v in d.items() if k not in known}
        extra.update(dict(d.get("extra") or {}))
        w = kw.get("weather")
        if isinstance(w, Mapping):
            kw["weather"] = (w,)
        return cls(**kw, extra=extra)


@dataclass(frozen=True)
class ModelEntry:
    """One fitted model, normalised from a ``FitResult`` or a ``CalibratedModel``.

    ``fit_info``: what the fit said about itself, when known: ``converged`` (bool),
    ``n_free``, ``dof_effective``, ``rank``, ``condition_number``, ``singular_values``.
    """

    name: str
    calibrated: CalibratedModel | None
    outliers: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()
    status: str = ""
    stored: Mapping[str, Any] = field(default_factory=dict)
    summary: Mapping[str, Any] = field(default_factory=dict)
    fit_info: Mapping[str, Any] = field(default_factory=dict)

    @property
    def label(self) -> str:
        """Human-readable name."""
        return KNOWN_MODELS.get(self.name, self.name)


def _as_names(v: Any) -> tuple[str, ...]:
    """Pose or parameter names from a list, or from a mapping's ``pose_ids``/``names``."""
    if v is None:
        return ()
    if isinstance(v, str):
        return (v,)
    if isinstance(v, Mapping):
        for k in ("pose_ids", "names", "ids"):
            if k in v:
                return _as_names(v[k])
        return ()
    try:
        return tuple(str(x) for x in v)
    except TypeError:
        return ()


def _acc_to_dict(acc: Accuracy | None) -> dict[str, Any] | None:
    """An :class:`Accuracy` as identification stores it (mm, %), None when absent."""
    return None if acc is None else acc.to_dict()


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def _info_from_fit_dict(fit: Mapping[str, Any]) -> dict[str, Any]:
    """``fit_info`` from the ``fit`` section identification writes into MODEL.json."""
    info: dict[str, Any] = {}
    solver = fit.get("solver")
    if isinstance(solver, Mapping) and isinstance(solver.get("converged"), bool):
        info["converged"] = solver["converged"]
    elif isinstance(fit.get("converged"), bool):
        info["converged"] = fit["converged"]
    for k in ("n_free", "dof_effective"):
        if _num(fit.get(k)) is not None:
            info[k] = _num(fit.get(k))
    ident = fit.get("identifiability")
    if isinstance(ident, Mapping):
        if _num(ident.get("rank")) is not None:
            info["rank"] = int(ident["rank"])
        if _num(ident.get("condition_number")) is not None:
            info["condition_number"] = _num(ident["condition_number"])
        sv = ident.get("singular_values")
        if isinstance(sv, list | tuple) and sv:
            info["singular_values"] = [float(x) for x in sv]
        if ident.get("note"):
            info["note"] = str(ident["note"])
    return info


def _status(info: Mapping[str, Any], explicit: Any = None) -> str:
    if isinstance(explicit, str) and explicit:
        return explicit
    conv = info.get("converged")
    if conv is True:
        return "converged"
    if conv is False:
        return "not converged"
    return ""


#: What :attr:`ReportInput.models` maps a name to (None: a fit that produced no model).
ModelSource: TypeAlias = FitResult | CPAResult | CalibratedModel | ModelEntry | None


def _model_file_entry(name: str, cm: CalibratedModel) -> ModelEntry:
    """What a MODEL.json says about its own fit (``fit`` and ``metrics`` sections)."""
    fit_d: Mapping[str, Any] = cm.fit or {}
    info = _info_from_fit_dict(fit_d)
    ident = fit_d.get("identifiability")
    removed = _as_names(fit_d.get("removed"))
    if not removed and isinstance(ident, Mapping):
        removed = _as_names(ident.get("removed"))
    outliers = _as_names(fit_d.get("outliers")) or _as_names(cm.data.get("outliers"))
    return ModelEntry(name, cm, outliers, removed, _status(info, fit_d.get("status")),
                      dict(cm.metrics or {}), {}, info)


def _stored(**parts: Accuracy | None) -> dict[str, Any]:
    """The accuracies a result carries, as stored dicts, leaving out those it lacks."""
    return {k: d for k, acc in parts.items() if (d := _acc_to_dict(acc))}


def _fit_entry(name: str, res: FitResult) -> ModelEntry:
    """An identification :class:`FitResult`: its own figures over its model file's."""
    base = _model_file_entry(name, res.calibrated)
    info = dict(base.fit_info)
    info["converged"] = bool(res.converged)
    for k, v in (("n_free", res.n_free), ("dof_effective", res.dof_effective)):
        if (num := _num(v)) is not None:
            info[k] = num
    ident = res.identifiability
    if _num(ident.rank) is not None:
        info["rank"] = int(ident.rank)
    if (cond := _num(ident.cond)) is not None:
        info["condition_number"] = cond
    if len(ident.singular_values):
        info["singular_values"] = [float(x) for x in np.asarray(ident.singular_values).ravel()]
    stored = _stored(train=res.train, validation=res.validation)
    return ModelEntry(name, res.calibrated, tuple(res.outliers) or base.outliers,
                      tuple(res.removed) or base.removed,
                      _status(info, res.status) or base.status,
                      stored or dict(base.stored), dict(res.summary()), info)


def _cpa_entry(name: str, res: CPAResult) -> ModelEntry:
    """A :class:`CPAResult`: held-out accuracy and summary over its model file's."""
    base = _model_file_entry(name, res.calibrated)
    stored = _stored(validation=res.validation)
    return replace(base, status=_status(base.fit_info) or base.status,
                   stored=stored or dict(base.stored), summary=dict(res.summary()))


def model_entry(name: str, obj: ModelSource) -> ModelEntry:
    """Normalise one of :data:`ModelSource` under ``name``.

    Raises
    ------
    ConfigError
        For anything else (the report does not guess what an object means).
    """
    if obj is None:
        return ModelEntry(name, None)
    if isinstance(obj, ModelEntry):
        return obj if obj.name == name else replace(obj, name=name)
    if isinstance(obj, CalibratedModel):
        return _model_file_entry(name, obj)
    if isinstance(obj, FitResult):
        return _fit_entry(name, obj)
    if isinstance(obj, CPAResult):
        return _cpa_entry(name, obj)
    raise ConfigError(f"model {name!r}: a {type(obj).__name__} is not a FitResult, CPAResult, "
                      "CalibratedModel or ModelEntry")


@dataclass
class ReportInput:
    """Everything a calibration report shows.

    Parameters
    ----------
    models
        Name -> :data:`ModelSource` (``FitResult``, ``CPAResult``, ``CalibratedModel``,
        ``ModelEntry`` or None for a fit without a model). Well-known names: ``nominal`` (base and
        reflector fitted; the baseline of "% described"), ``cpa``, ``constant``,
        ``high-order``, ``auto``. When ``nominal`` is missing and calibration data is given,
        the report fits base and reflector itself.
    calibration, validation
        Calibration and held-out poses (SI). Without data the report uses the metrics stored
        in the models.
    robot
        Defaults to the robot of the judged model.
    selected
        Name of the model the verdict is about; default: the first of ``auto``,
        ``high-order``, ``constant``, ``cpa`` present.
    iso
        Repeated measurements at ISO 9283 cube poses P1..P5, grouped.
    iso_measurements, iso_purposes
        Alternatively the raw ISO measurements (joints = the commanded ones) and each pose's
        purpose (``iso-P1`` .. ``iso-P5``); the report groups them, takes the command from the
        nominal model (what the controller believes) and "AP after calibration" from the
        judged model.
    log
        Measurement statistics (retries, beam losses, weather...).
    targets
        The production program's joint values (n, dof) rad, overlaid on the per-joint
        coverage (ADR 0026).
    acceptance
        Verdict thresholds.
    """

    models: Mapping[str, ModelSource] = field(default_factory=dict)
    calibration: MeasurementSet | None = None
    validation: MeasurementSet | None = None
    robot: RobotDescription | None = None
    selected: str | None = None
    iso: Sequence[IsoPoseSeries] = ()
    iso_measurements: MeasurementSet | None = None
    iso_purposes: Sequence[str] = ()
    log: MeasurementLog | None = None
    acceptance: Acceptance = field(default_factory=Acceptance)
    title: str = "Robot calibration report"
    campaign_id: str = ""
    created: str = ""
    notes: Sequence[str] = ()
    workspace_samples: int = 1000
    seed: int = 0
    targets: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        if not self.created:
            self.created = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        if self.workspace_samples < 0:
            raise ConfigError("workspace_samples must not be negative")
        if self.iso_measurements is not None and len(self.iso_purposes) != len(
                self.iso_measurements):
            raise ConfigError("iso_purposes needs one entry per ISO measurement")

    def entries(self) -> dict[str, ModelEntry]:
        """Models normalised and ordered: well-known names first, then the rest."""
        raw = {str(k): model_entry(str(k), v) for k, v in self.models.items()}
        order = [k for k in KNOWN_MODELS if k in raw] + [k for k in raw if k not in KNOWN_MODELS]
        return {k: raw[k] for k in order}

    def selected_name(self) -> str | None:
        """The judged model's name (see ``selected``)."""
        names = [k for k, e in self.entries().items() if e.calibrated is not None or e.stored]
        if self.selected:
            if self.selected not in self.models:
                raise ConfigError(f"selected model {self.selected!r} is not among the models "
                                  f"({', '.join(self.models) or 'none'})")
            return self.selected
        for k in SELECTION_ORDER:
            if k in names:
                return k
        others = [k for k in names if k != BASELINE]
        return others[0] if others else None
