"""What a compensation table does, in one place: kind, checksum, predicted and nominal residual.

Every table robocal prints, stores or pushes is described by :func:`describe_table`, so a
table that does not compensate is never shown as if it did:

``targets``  the program's targets, compensated: the only kind that carries the whole model;
``joint``    per-joint corrections, bounded by what a separable joint table can express;
``frames``   base/tool alignment, *not* compensation: the joint-dependent and link errors stay.

:func:`improvement_refusal` is the push gate: a table whose predicted residual is not below
``max_ratio`` times the nominal residual (the uncompensated robot, same poses, same model) is
refused unless the operator forces it.
"""

from __future__ import annotations

import math
from typing import Any

from robocal.compensation._table import CompensationTable

__all__ = ["PURPOSE", "describe_table", "improvement_refusal"]

PURPOSE: dict[str, str] = {
    "targets": "compensated program targets (the whole model, per target)",
    "joint": "per-joint corrections (a separable approximation of the model)",
    "frames": "base/tool alignment, not compensation (joint-dependent and link errors stay)",
}

#: A ``joint`` table whose predicted residual exceeds this multiple of the model's accuracy
#: is flagged: the table, not the model, limits the accuracy.
JOINT_WARN_FACTOR = 2.0


def _finite(v: Any) -> float | None:
    if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(float(v)):
        return float(v)
    return None


def describe_table(table: CompensationTable) -> dict[str, Any]:
    """Kind, purpose, checksum, predicted and nominal residual (mm), model accuracy (mm),
    improvement ratio and warnings of ``table`` (JSON-ready)."""
    predicted = float(table.predicted_residual_mm)
    nominal = _finite(table.stats.get("nominal_residual_mm"))
    model = _finite(table.stats.get("model_validation_rms_mm"))
    warnings: list[str] = []
    if table.kind == "frames":
        warnings.append("a frames table aligns base and tool only; it does not compensate "
                        "the robot's joint-dependent or link errors")
    if table.kind == "joint":
        tol = _finite(table.stats.get("interpolation_tol_deg"))
        bound = f" (interpolation bound {tol:g} deg)" if tol is not None else ""
        if model is not None and predicted > JOINT_WARN_FACTOR * model:
            warnings.append(f"joint table predicts {predicted:.4f} mm{bound}, far worse than "
                            f"the model's {model:.4f} mm: use a targets table for the full "
                            "accuracy")
    ratio = None if not nominal else predicted / nominal
    if ratio is not None and ratio >= 1.0:
        warnings.append(f"predicted residual {predicted:.4f} mm is not better than the "
                        f"uncompensated robot's {nominal:.4f} mm")
    n_ok = _finite(table.stats.get("n_ok"))
    n = _finite(table.stats.get("n_targets"))
    if table.kind == "targets" and n_ok is not None and n is not None and n_ok < n:
        warnings.append(f"{int(n - n_ok)} of {int(n)} targets could not be compensated")
    temps = table.temperatures_c
    purpose = PURPOSE[table.kind]
    if temps:
        purpose += (", for joint temperatures "
                    + ", ".join(f"{t:.1f}" for t in temps) + " degC")
    return {
        "kind": table.kind,
        "purpose": purpose,
        "checksum": table.checksum or table.compute_checksum(),
        "predicted_residual_mm": round(predicted, 6),
        "nominal_residual_mm": None if nominal is None else round(nominal, 6),
        "model_accuracy_mm": None if model is None else round(model, 6),
        "ratio": None if ratio is None else round(ratio, 4),
        "warnings": warnings,
    }


def improvement_refusal(table: CompensationTable, max_ratio: float) -> str | None:
    """Why ``table`` must not be pushed without force, or None when it clearly improves.

    The predicted residual must be below ``max_ratio`` times the nominal residual.
    """
    d = describe_table(table)
    nominal, predicted = d["nominal_residual_mm"], d["predicted_residual_mm"]
    if nominal is None:
        return (f"{table.kind} table states no nominal residual to compare its predicted "
                f"{predicted:.4f} mm with")
    if predicted >= max_ratio * nominal:
        what = " (base/tool alignment, not compensation)" if table.kind == "frames" else ""
        return (f"{table.kind} table{what} predicts {predicted:.4f} mm against "
                f"{nominal:.4f} mm uncompensated: not below {max_ratio:.0%} of it")
    return None


def summary_line(table: CompensationTable) -> str:
    """One line: kind, checksum, predicted vs nominal residual, model accuracy."""
    d = describe_table(table)
    nominal = d["nominal_residual_mm"]
    model = d["model_accuracy_mm"]
    parts = [f"{d['kind']} table {d['checksum'][:16]}: {d['purpose']}",
             f"predicted residual {d['predicted_residual_mm']:.4f} mm",
             "nominal residual " + ("unknown" if nominal is None else f"{nominal:.4f} mm")]
    if model is not None:
        parts.append(f"model accuracy {model:.4f} mm")
    return "; ".join(parts)
