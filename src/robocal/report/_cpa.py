"""Circle Point Analysis in the report: classical and polished CPA against the nominal model.

A ``cpa`` model written by ``identification.cpa_fit`` carries classical CPA inside its fit
record (``fit["classical"]["model"]``, ADR 0021). :func:`with_classical` adds it as an entry
of its own (``cpa-classical``), so every table and plot shows both. :func:`compare` sets each
CPA model's held-out RMS against the nominal baseline and, when one is worse, names the
reasons its circle fits recorded: short arcs, small radii, circle residuals far above the
tracker noise (joint-dependent errors, which CPA cannot describe).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from robocal.errors import ConfigError
from robocal.identification import CPAResult
from robocal.kinematics import CalibratedModel
from robocal.report._input import BASELINE, ModelEntry, model_entry
from robocal.report._results import ModelResult

#: Model kinds identification gives CPA models.
KINDS = ("cpa", "cpa-classical")
_ISSUES = ("short arc", "small radius", "joint-dependent errors")


def classical_name(name: str) -> str:
    """Entry name of the classical CPA carried by the polished model ``name``."""
    return f"{name}-classical"


def _classical_of(obj: Any, cm: CalibratedModel, name: str) -> CalibratedModel | None:
    """Classical CPA of a polished CPA model: the result's ``.classical`` or the copy in its
    fit record; None when there is none (not polished, older file) or it does not load."""
    if isinstance(obj, CPAResult):
        return obj.classical
    rec = cm.fit.get("classical")
    d = rec.get("model") if isinstance(rec, Mapping) else None
    if not isinstance(d, dict):
        return None
    try:
        return CalibratedModel.from_dict(d, source=f"model {name!r}: classical CPA")
    except ConfigError:
        return None


def with_classical(models: Mapping[str, Any], entries: dict[str, ModelEntry]
                   ) -> dict[str, ModelEntry]:
    """``entries`` with each polished CPA model followed by its classical CPA (unless given)."""
    out: dict[str, ModelEntry] = {}
    for name, e in entries.items():
        out[name] = e
        cm = e.calibrated
        key = classical_name(name)
        if cm is None or cm.kind != "cpa" or not cm.fit.get("polish") or key in entries:
            continue
        classical = _classical_of(models.get(name), cm, name)
        if classical is not None:
            out[key] = model_entry(key, classical)
    return out


@dataclass(frozen=True)
class CpaRow:
    """One CPA model on one pose set against the nominal model (m)."""

    name: str
    variant: str          # "classical", "polished" or "classical (not polished)"
    on: str               # "validation" or "calibration"
    n: int
    rms_m: float
    nominal_rms_m: float

    @property
    def diff_m(self) -> float:
        """RMS minus the nominal RMS, m (negative: CPA is better)."""
        return self.rms_m - self.nominal_rms_m

    @property
    def diff_percent(self) -> float:
        """``diff_m`` in % of the nominal RMS."""
        return 100.0 * self.diff_m / self.nominal_rms_m if self.nominal_rms_m > 0 else math.nan

    @property
    def better(self) -> bool:
        """Is CPA's RMS below the nominal model's?"""
        return self.rms_m < self.nominal_rms_m

    def sentence(self) -> str:
        """One sentence (mm, %) saying whether and by how much CPA beats the nominal model."""
        where = ("held-out" if self.on == "validation"
                 else "calibration (not used by CPA either)")
        how = "better" if self.better else "worse"
        return (f"{self.variant.capitalize()} CPA is {how} than the nominal model by "
                f"{abs(self.diff_m) * 1e3:.3f} mm ({abs(self.diff_percent):.0f} %): "
                f"{self.rms_m * 1e3:.3f} mm against {self.nominal_rms_m * 1e3:.3f} mm RMS on "
                f"{self.n} {where} poses.")

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (mm, %)."""
        return {"model": self.name, "variant": self.variant, "poses": self.on, "n": self.n,
                "rms_mm": self.rms_m * 1e3, "nominal_rms_mm": self.nominal_rms_m * 1e3,
                "difference_mm": self.diff_m * 1e3, "difference_percent": self.diff_percent,
                "better_than_nominal": self.better, "text": self.sentence()}


@dataclass(frozen=True)
class CpaComparison:
    """CPA models against nominal, with the circle fits and their recorded weaknesses."""

    rows: list[CpaRow]
    circles: list[dict[str, Any]] = field(default_factory=list)
    diagnosis: list[dict[str, Any]] = field(default_factory=list)
    polish: Mapping[str, Any] | None = None

    @property
    def worse(self) -> list[CpaRow]:
        """CPA models whose RMS is above the nominal model's."""
        return [r for r in self.rows if not r.better]

    def reasons(self) -> list[str]:
        """Why CPA falls short, one sentence per kind of weakness (joints named)."""
        out = []
        for issue in _ISSUES:
            items = [d for d in self.diagnosis if d.get("issue") == issue]
            if not items:
                continue
            limit = items[0].get("limit")
            if issue == "short arc":
                joints = ", ".join(f"J{d['joint']} {d['value']:.0f}°" for d in items)
                out.append(f"short arcs ({joints}; < {limit:g}°): the circles' centres and "
                           "axes are poorly determined")
            elif issue == "small radius":
                joints = ", ".join(f"J{d['joint']} {d['value']:.0f} mm" for d in items)
                out.append(f"small circle radii ({joints}; < {limit:g} mm): the axis "
                           "directions are poorly determined")
            else:
                joints = ", ".join(f"J{d['joint']} {d['value']:.1f}×" for d in items)
                out.append(f"circle residuals far above the tracker noise ({joints}; > "
                           f"{limit:g}×): CPA cannot describe joint-dependent errors")
        if not out:
            out.append("the circle fits record no short arc, small radius or excess residual"
                       + ("" if self.circles else " (the model file has no CPA diagnosis)"))
        return out

    @property
    def flag(self) -> str | None:
        """The warning when a CPA model is worse than nominal (amounts and reasons), else None."""
        if not self.worse:
            return None
        return (" ".join(r.sentence() for r in self.worse) + " Reasons: "
                + "; ".join(self.reasons()) + ".")

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (mm, deg, %)."""
        return {"models": [r.to_dict() for r in self.rows],
                "worse_than_nominal": [r.name for r in self.worse],
                "flag": self.flag, "reasons": self.reasons() if self.worse else [],
                "diagnosis": list(self.diagnosis), "circles": list(self.circles),
                "polish": None if self.polish is None else dict(self.polish)}


def _variant(cm: CalibratedModel) -> str:
    if cm.kind == "cpa-classical":
        return "classical"
    return "polished" if cm.fit.get("polish") else "classical (not polished)"


def compare(models: Mapping[str, ModelResult]) -> CpaComparison | None:
    """Each CPA model's RMS against nominal on the validation poses (else calibration poses),
    with the circles and diagnosis the CPA fit recorded; None without a CPA model."""
    base = models.get(BASELINE)
    rows: list[CpaRow] = []
    circles: list[dict[str, Any]] = []
    diagnosis: list[dict[str, Any]] = []
    polish = None
    for name, m in models.items():
        cm = m.entry.calibrated
        if cm is None or cm.kind not in KINDS:
            continue
        fit = cm.fit or {}
        if not circles and isinstance(fit.get("circles"), list):
            circles = [dict(c) for c in fit["circles"] if isinstance(c, Mapping)]
        if not diagnosis and isinstance(fit.get("diagnosis"), list):
            diagnosis = [dict(d) for d in fit["diagnosis"] if isinstance(d, Mapping)
                         and d.get("issue") in _ISSUES and isinstance(d.get("joint"), int)
                         and isinstance(d.get("value"), int | float)]
        if polish is None and isinstance(fit.get("polish"), Mapping):
            polish = fit["polish"]
        on = "validation" if "validation" in m.sets else "calibration"
        sr = m.sets.get(on)
        if sr is None or sr.stats is None:
            continue
        bst = (base.sets[on].stats if base is not None and on in base.sets
               else sr.baseline_stats)
        if bst is None or not math.isfinite(bst.rms_m):
            continue
        rows.append(CpaRow(name, _variant(cm), on, sr.stats.n, sr.stats.rms_m, bst.rms_m))
    if not rows and not circles:
        return None
    rows.sort(key=lambda r: r.variant != "classical")      # before the polish, then after
    return CpaComparison(rows, circles, diagnosis, polish)
