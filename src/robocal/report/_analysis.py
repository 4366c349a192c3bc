"""Turn a :class:`ReportInput` into every number and array the report shows."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robocal import __version__
from robocal._core.measurements import MeasurementSet
from robocal._core.threads import blas_threads
from robocal.kinematics import CalibratedModel, RobotDescription
from robocal.report._input import BASELINE, ModelEntry, ReportInput, model_entry
from robocal.report._metrics import (
    Described,
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

Array = NDArray[np.float64]
SETS = ("calibration", "validation")
_STORED_KEYS = {"calibration": ("calibration", "train", "training"),
                "validation": ("validation", "val", "holdout", "held_out")}


@dataclass
class SetResult:
    """One model on one pose set. ``norms`` (n,) m for every pose (outliers included),
    ``inlier`` (n,) mask; ``stats``/``described`` over inliers. ``source``: data or stored."""

    stats: ErrorStats | None
    described: Described | None = None
    norms: Array | None = None
    inlier: NDArray[np.bool_] | None = None
    source: str = "data"
    baseline_stats: ErrorStats | None = None


@dataclass
class ModelResult:
    """A model and its results per pose set."""

    entry: ModelEntry
    sets: dict[str, SetResult] = field(default_factory=dict)

    @property
    def name(self) -> str:
        """Model name."""
        return self.entry.name


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
    """A ``.baseline`` model some FitResult carries (identification's nominal fit)."""
    for v in inp.models.values():
        b = getattr(v, "baseline", None)
        if isinstance(b, CalibratedModel):
            return b
    return None


def _mask(data: MeasurementSet, outliers: set[str]) -> NDArray[np.bool_]:
    return np.array([pid not in outliers for pid in data.pose_id], dtype=bool)


def analyse(inp: ReportInput) -> Analysis:
    """Compute every figure of the report (see module docstring of ``robocal.report``)."""
    entries = inp.entries()
    selected = inp.selected_name()
    sel_entry = entries.get(selected) if selected else None
    sel_cm = sel_entry.calibrated if sel_entry else None
    robot = inp.robot or (sel_cm.robot if sel_cm is not None else None)
    if robot is None:
        robot = next((e.calibrated.robot for e in entries.values()
                      if e.calibrated is not None), None)
    data = {k: v for k, v in (("calibration", inp.calibration),
                              ("validation", inp.validation)) if v is not None}

    # the baseline: given, carried by a FitResult, or fitted here on the calibration poses
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

    outliers = tuple(sel_entry.outliers) if sel_entry else ()
    # held-out poses are not screened by the fit: flag gross glitches (beam breaks) with a
    # scale-free robust rule on the judged model's errors (|r| > factor x median |r|)
    val_glitches: tuple[str, ...] = ()
    factor = inp.acceptance.validation_outlier_factor
    if inp.validation is not None and sel_cm is not None and factor > 0:
        r = np.linalg.norm(inp.validation.p - sel_cm.predict(inp.validation.q), axis=1)
        med = float(np.median(r))
        if med > 0:
            val_glitches = tuple(inp.validation.pose_id[i]
                                 for i in np.flatnonzero(r > factor * med)
                                 if inp.validation.pose_id[i] not in set(outliers))
    outliers = outliers + val_glitches
    out_set = set(outliers)

    models: dict[str, ModelResult] = {}
    base_norms: dict[str, Array] = {}
    base_entry = entries.get(BASELINE)
    if base_entry is not None and base_entry.calibrated is not None:
        for which, ds in data.items():
            base_norms[which] = np.linalg.norm(ds.p - base_entry.calibrated.predict(ds.q), axis=1)
    for name, e in entries.items():
        mr = ModelResult(e)
        for which in SETS:
            d = data.get(which)
            if d is not None and e.calibrated is not None:
                norms = np.linalg.norm(d.p - e.calibrated.predict(d.q), axis=1)
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

    # no data and no nominal model: show the baseline figures the judged fit stored
    if BASELINE not in models and selected in models:
        stored_base = {w: SetResult(sr.baseline_stats, source="stored")
                       for w, sr in models[selected].sets.items()
                       if sr.source == "stored" and sr.baseline_stats is not None}
        if stored_base:
            models = {BASELINE: ModelResult(ModelEntry(BASELINE, None), stored_base), **models}

    ident = None
    work = None
    if sel_cm is not None:
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

    # what the verdict judges
    judged = None
    if selected and selected in models:
        mr = models[selected]
        on = "validation" if "validation" in mr.sets else "calibration"
        sr = mr.sets.get(on)
        if sr is not None:
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
            judged = Judged(selected, on, sr.stats, bstats, sr.described,
                            None if cal is None or cal.stats is None or on == "calibration"
                            else cal.stats.rms_m,
                            n_outliers=n_out, n_poses=n_poses, expected_ratio=expected,
                            status=sel_entry.status if sel_entry else "")
    v = verdict(judged, inp.acceptance)

    # per-joint error curves: the richest of selected / high-order / auto
    joint_model = None
    joints: list[JointCurves] = []
    for cand in (selected, "high-order", "auto"):
        ce = entries.get(cand) if cand else None
        if ce is None or ce.calibrated is None:
            continue
        cm = ce.calibrated
        if any(t.family not in ("const", "gravity") for t in cm.model.spec.terms):
            joint_model = cand
            pts = max(181, 4 * max(cm.model.spec.map_knots, default=0))
            joints = [joint_curves(cm, j, points=pts, removed=ce.removed)
                      for j in range(cm.robot.dof)]
            break

    series = list(inp.iso)
    if not series and inp.iso_measurements is not None and sel_cm is not None:
        base_cm = base_entry.calibrated if base_entry is not None else None
        series = iso_series_from_measurements(
            inp.iso_measurements, inp.iso_purposes, command=base_cm or sel_cm,
            predicted=sel_cm if base_cm is not None else None)
    iso = [iso9283(s) for s in series]

    hashes: dict[str, Any] = {"robocal": __version__}
    for which, d in data.items():
        hashes[f"{which}_sha256"] = d.digest()
        hashes[f"{which}_poses"] = len(d)
    hashes["models"] = {n: {"model_id": e.calibrated.model_id, "kind": e.calibrated.kind,
                            "created": e.calibrated.created,
                            "data": dict(e.calibrated.data or {})}
                        for n, e in entries.items() if e.calibrated is not None}
    return Analysis(inp, robot, models, selected, baseline_note, outliers, val_glitches,
                    judged, v,
                    joint_model, joints, ident, work, iso, hashes)
