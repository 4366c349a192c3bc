"""Turn a :class:`ReportInput` into every number and array the report shows."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal import __version__
from robocal._core.measurements import MeasurementSet
from robocal._core.threads import blas_threads
from robocal.identification import FitResult, extrapolation, thermal_shift
from robocal.kinematics import CalibratedModel, RobotDescription
from robocal.report._coverage import Coverage, coverage
from robocal.report._cpa import CpaComparison, compare, with_classical
from robocal.report._input import BASELINE, ModelEntry, ReportInput, model_entry
from robocal.report._metrics import (
    ErrorStats,
    Identifiability,
    IsoResult,
    JointCurves,
    Judged,
    Verdict,
    Workspace,
    described,
    fit_nominal_baseline,
    identifiability,
    iso9283,
    iso_series_from_measurements,
    joint_curves,
    stats_from_stored,
    verdict,
    workspace,
)
from robocal.report._results import ModelResult, SetResult

Array = NDArray[np.float64]
SETS = ("calibration", "validation")
_STORED_KEYS = {"calibration": ("calibration", "train", "training"),
                "validation": ("validation", "val", "holdout", "held_out")}


@dataclass
class Analysis:
    """Everything computed for one report."""

    inp: ReportInput
    robot: RobotDescription | None
    models: dict[str, ModelResult]
    selected: str | None
    baseline_note: str
    outliers: tuple[str, ...]
    validation_glitches: tuple[str, ...]
    judged: Judged | None
    verdict: Verdict
    joint_model: str | None
    joints: list[JointCurves]
    ident: Identifiability | None
    work: Workspace | None
    iso: list[IsoResult]
    hashes: dict[str, Any]
    iso_frame: str = "tracker"
    cpa: CpaComparison | None = None
    coverage: Coverage | None = None

    @property
    def data(self) -> dict[str, MeasurementSet]:
        """The pose sets that were given."""
        out = {}
        if self.inp.calibration is not None:
            out["calibration"] = self.inp.calibration
        if self.inp.validation is not None:
            out["validation"] = self.inp.validation
        return out


def _stored_for(entry: ModelEntry, which: str) -> dict[str, Any] | None:
    for k in _STORED_KEYS[which]:
        v = entry.stored.get(k)
        if isinstance(v, dict):
            return v
    return None


def _baseline_from_fits(inp: ReportInput) -> CalibratedModel | None:
    """The ``baseline`` model a :class:`FitResult` carries (identification's nominal fit)."""
    return next((v.baseline for v in inp.models.values() if isinstance(v, FitResult)), None)


def _mask(data: MeasurementSet, outliers: set[str]) -> NDArray[np.bool_]:
    return np.array([pid not in outliers for pid in data.pose_id], dtype=bool)


def analyse(inp: ReportInput) -> Analysis:
    """Compute every figure of the report (see module docstring of ``robocal.report``)."""
    entries = with_classical(inp.models, inp.entries())
    selected = inp.selected_name()
    sel_entry = entries.get(selected) if selected else None
    sel_cm = sel_entry.calibrated if sel_entry else None
    robot = _robot_of(inp, entries, sel_cm)
    if robot is not None:  # the default RMS limit grows with the robot's reach
        reach_m = sum(abs(j.a) + abs(j.d) for j in robot.joints)
        inp = replace(inp, acceptance=inp.acceptance.for_reach(reach_m))
    data = {k: v for k, v in (("calibration", inp.calibration),
                              ("validation", inp.validation)) if v is not None}
    entries, baseline_note = _with_baseline(inp, entries, sel_cm)
    outliers = tuple(sel_entry.outliers) if sel_entry else ()
    val_glitches = _validation_glitches(inp, sel_cm, outliers)
    outliers = outliers + val_glitches
    out_set = set(outliers)
    models = _stored_baseline(_model_results(entries, data, out_set), selected)
    ident, work = _identifiability_and_workspace(inp, sel_entry, sel_cm, out_set)
    judged = _judged(inp, models, selected, sel_entry, ident, outliers, out_set)
    v = verdict(judged, inp.acceptance)
    joint_model, joints = _joint_curves(entries, selected)
    iso = _iso(inp, entries.get(BASELINE), sel_cm)
    cover = None if robot is None else coverage(
        robot, sel_cm, None if inp.calibration is None else inp.calibration.q, inp.targets)
    return Analysis(inp, robot, models, selected, baseline_note, outliers, val_glitches,
                    judged, v,
                    joint_model, joints, ident, work, iso, _hashes(data, entries),
                    cpa=compare(models), coverage=cover)


def _robot_of(inp: ReportInput, entries: dict[str, ModelEntry],
              sel_cm: CalibratedModel | None) -> RobotDescription | None:
    """The robot given, else the judged model's, else the first model's."""
    robot = inp.robot or (sel_cm.robot if sel_cm is not None else None)
    if robot is None:
        robot = next((e.calibrated.robot for e in entries.values()
                      if e.calibrated is not None), None)
    return robot


def _with_baseline(inp: ReportInput, entries: dict[str, ModelEntry],
                   sel_cm: CalibratedModel | None) -> tuple[dict[str, ModelEntry], str]:
    """Entries with the baseline first (given, carried by a FitResult, or fitted here on the
    calibration poses) and the sentence describing it."""
    baseline_note = "nominal kinematics with only the tracker←base transform and the " \
                    "reflector offset fitted on the calibration poses"
    if BASELINE not in entries:
        b = _baseline_from_fits(inp)
        ref = sel_cm or next((e.calibrated for e in entries.values()
                              if e.calibrated is not None), None)
        if b is None and ref is not None and inp.calibration is not None:
            b = fit_nominal_baseline(ref, inp.calibration)
            baseline_note += " (fitted by the report: no nominal fit was given)"
        if b is not None:
            entries = {BASELINE: model_entry(BASELINE, b), **entries}
    return entries, baseline_note


def _validation_glitches(inp: ReportInput, sel_cm: CalibratedModel | None,
                         outliers: tuple[str, ...]) -> tuple[str, ...]:
    """Held-out poses that are gross glitches under the judged model."""
    # held-out poses are not screened by the fit: flag gross glitches (beam breaks) with a
    # scale-free robust rule on the judged model's errors (|r| > factor x median |r|)
    factor = inp.acceptance.validation_outlier_factor
    if inp.validation is None or sel_cm is None or factor <= 0:
        return ()
    r = np.linalg.norm(inp.validation.p - sel_cm.predict(inp.validation.q), axis=1)
    med = float(np.median(r))
    if not med > 0:
        return ()
    return tuple(inp.validation.pose_id[i] for i in np.flatnonzero(r > factor * med)
                 if inp.validation.pose_id[i] not in set(outliers))


def _predict(cm: CalibratedModel, data: MeasurementSet) -> Array:
    """``cm``'s prediction of ``data``'s poses, with its thermal term at their joint
    temperatures when it has one and they are known (ADR 0042)."""
    p = cm.predict(data.q)
    if data.temps is not None and cm.fit.get("thermal"):
        p = p + thermal_shift(cm, data.q, data.temps)
    return p


def _model_results(entries: dict[str, ModelEntry], data: dict[str, MeasurementSet],
                   out_set: set[str]) -> dict[str, ModelResult]:
    """Errors of every model on every pose set, from the data or else from stored figures."""
    models: dict[str, ModelResult] = {}
    base_norms: dict[str, Array] = {}
    base_entry = entries.get(BASELINE)
    if base_entry is not None and base_entry.calibrated is not None:
        for which, ds in data.items():
            base_norms[which] = np.linalg.norm(ds.p - _predict(base_entry.calibrated, ds), axis=1)
    for name, e in entries.items():
        mr = ModelResult(e)
        for which in SETS:
            d = data.get(which)
            if d is not None and e.calibrated is not None:
                norms = np.linalg.norm(d.p - _predict(e.calibrated, d), axis=1)
                m = _mask(d, out_set)
                desc = None
                bstats = None
                if which in base_norms:
                    desc = described(base_norms[which][m], norms[m])
                    bstats = ErrorStats.of(base_norms[which][m])
                mr.sets[which] = SetResult(ErrorStats.of(norms[m]), desc, norms, m, "data",
                                           bstats)
            else:
                st, desc, bst = stats_from_stored(_stored_for(e, which))
                if st is not None:
                    mr.sets[which] = SetResult(st, desc, source="stored", baseline_stats=bst)
        models[name] = mr
    return models


def _stored_baseline(models: dict[str, ModelResult], selected: str | None
                     ) -> dict[str, ModelResult]:
    """With no data and no nominal model: the baseline figures the judged fit stored."""
    if BASELINE not in models and selected in models:
        stored_base = {w: SetResult(sr.baseline_stats, source="stored")
                       for w, sr in models[selected].sets.items()
                       if sr.source == "stored" and sr.baseline_stats is not None}
        if stored_base:
            models = {BASELINE: ModelResult(ModelEntry(BASELINE, None), stored_base), **models}
    return models


def _identifiability_and_workspace(inp: ReportInput, sel_entry: ModelEntry | None,
                                   sel_cm: CalibratedModel | None, out_set: set[str]
                                   ) -> tuple[Identifiability | None, Workspace | None]:
    """Identifiability at the calibration inliers and workspace coverage of the judged model."""
    if sel_cm is None:
        return None, None
    q = inp.calibration.q if inp.calibration is not None else None
    if q is not None and out_set:
        q = q[_mask(inp.calibration, out_set)]  # type: ignore[arg-type]
    removed = sel_entry.removed if sel_entry else ()
    have_sv = bool(sel_entry and sel_entry.fit_info.get("singular_values"))
    with blas_threads(1):
        ident = identifiability(sel_cm, q, removed, svd=not have_sv)
        if sel_entry is not None:
            ident.use_fit(sel_entry.fit_info)
        work = workspace(sel_cm, inp.workspace_samples, inp.seed)
    return ident, work


def _judged(inp: ReportInput, models: dict[str, ModelResult], selected: str | None,
            sel_entry: ModelEntry | None, ident: Identifiability | None,
            outliers: tuple[str, ...], out_set: set[str]) -> Judged | None:
    """What the verdict judges: the selected model on validation, else on calibration."""
    if not (selected and selected in models):
        return None
    mr = models[selected]
    on = "validation" if "validation" in mr.sets else "calibration"
    sr = mr.sets.get(on)
    if sr is None:
        return None
    base = models.get(BASELINE)
    bstats = (base.sets[on].stats if base is not None and on in base.sets
              else sr.baseline_stats)
    cal = mr.sets.get("calibration")
    n_out = len(outliers)
    expected = 1.0
    if ident is not None and cal is not None and cal.stats is not None:
        m_coords = 3 * cal.stats.n
        # effective parameter count (smoothness priors make it < n_free) if known
        p_eff = float(sel_entry.fit_info.get("dof_effective") or ident.n_free
                      if sel_entry else ident.n_free)
        if 0 < p_eff < m_coords:
            expected = math.sqrt(m_coords / (m_coords - p_eff))
    if inp.calibration is not None:
        n_poses = len(inp.calibration)
        n_out = int(np.sum(~_mask(inp.calibration, out_set)))
    else:
        n_poses = cal.stats.n + n_out if cal is not None and cal.stats else 0
    if inp.validation is not None:
        n_poses += len(inp.validation)
        n_out += int(np.sum(~_mask(inp.validation, out_set)))
    return Judged(selected, on, sr.stats, bstats, sr.described,
                  None if cal is None or cal.stats is None or on == "calibration"
                  else cal.stats.rms_m,
                  n_outliers=n_out, n_poses=n_poses, expected_ratio=expected,
                  status=sel_entry.status if sel_entry else "",
                  extrapolation=_extrapolation(inp, sel_entry, out_set))


def _extrapolation(inp: ReportInput, sel_entry: ModelEntry | None, out_set: set[str]) -> str:
    """The verdict's note on validation poses the calibration poses leave nearly free."""
    cm = None if sel_entry is None else sel_entry.calibrated
    if cm is None or inp.calibration is None or inp.validation is None:
        return ""
    train = inp.calibration.q[_mask(inp.calibration, out_set)]
    ex = extrapolation(cm, train, inp.validation.q)
    if ex is None or not ex.n:
        return ""
    return f"{ex.n} of {len(ex.sigma_m)} validation poses {ex.message()}"


def _joint_curves(entries: dict[str, ModelEntry], selected: str | None
                  ) -> tuple[str | None, list[JointCurves]]:
    """Per-joint error curves of the richest of selected / high-order / auto."""
    for cand in (selected, "high-order", "auto"):
        ce = entries.get(cand) if cand else None
        if ce is None or ce.calibrated is None:
            continue
        cm = ce.calibrated
        if any(t.family not in ("const", "gravity") for t in cm.model.spec.terms):
            pts = max(181, 4 * max(cm.model.spec.map_knots, default=0))
            return cand, [joint_curves(cm, j, points=pts, removed=ce.removed)
                          for j in range(cm.robot.dof)]
    return None, []


def _iso(inp: ReportInput, base_entry: ModelEntry | None, sel_cm: CalibratedModel | None
         ) -> list[IsoResult]:
    """ISO 9283 results of the given series, or of series built from ISO measurements."""
    series = list(inp.iso)
    if not series and inp.iso_measurements is not None and sel_cm is not None:
        base_cm = base_entry.calibrated if base_entry is not None else None
        series = iso_series_from_measurements(
            inp.iso_measurements, inp.iso_purposes, command=base_cm or sel_cm,
            predicted=sel_cm if base_cm is not None else None)
    return [iso9283(s) for s in series]


def _hashes(data: dict[str, MeasurementSet], entries: dict[str, ModelEntry]) -> dict[str, Any]:
    """Version, data digests and model identities that make the report traceable."""
    hashes: dict[str, Any] = {"robocal": __version__}
    for which, d in data.items():
        hashes[f"{which}_sha256"] = d.digest()
        hashes[f"{which}_poses"] = len(d)
    hashes["models"] = {n: {"model_id": e.calibrated.model_id, "kind": e.calibrated.kind,
                            "created": e.calibrated.created,
                            "data": dict(e.calibrated.data or {})}
                        for n, e in entries.items() if e.calibrated is not None}
    return hashes
