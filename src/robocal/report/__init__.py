"""The calibration report: one self-contained HTML page plus a JSON summary.

``write_report(ReportInput(...), "report.html")`` writes ``report.html`` (plots embedded as
PNG data URIs, inline CSS, no scripts, readable offline) and ``report.json`` beside it. The
first screen gives the verdict (succeeded / marginal / failed, with the reason) against
:class:`Acceptance`; below: error before/after per model with the "% described" table,
joint-dependent errors with ±2σ bands, identifiability, ISO 9283 AP/RP, predicted accuracy
over the workspace, the measurement log and provenance.
"""

from typing import TYPE_CHECKING, Any

from robocal.report._analysis import Analysis, analyse
from robocal.report._input import (
    BASELINE,
    KNOWN_MODELS,
    Acceptance,
    IsoPoseSeries,
    MeasurementLog,
    ModelEntry,
    ReportInput,
    model_entry,
)
from robocal.report._metrics import (
    Check,
    Described,
    ErrorStats,
    IsoResult,
    Judged,
    Verdict,
    described,
    fit_nominal_baseline,
    iso9283,
    iso_series_from_measurements,
    joint_curves,
    verdict,
)

if TYPE_CHECKING:
    from robocal.report._write import REPORT_FORMAT, summary, write_report

# Writing needs matplotlib (about a second to import): loaded on first use, so that reading
# acceptance thresholds or analysing costs nothing of it.
_LAZY = {"REPORT_FORMAT", "summary", "write_report"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from robocal.report import _write

        return getattr(_write, name)
    if name == "add_compensation_section":
        from robocal.report import _compensation

        return _compensation.add_compensation_section
    raise AttributeError(f"module 'robocal.report' has no attribute {name!r}")

__all__ = [
    "BASELINE",
    "KNOWN_MODELS",
    "REPORT_FORMAT",
    "Acceptance",
    "Analysis",
    "Check",
    "Described",
    "ErrorStats",
    "IsoPoseSeries",
    "IsoResult",
    "Judged",
    "MeasurementLog",
    "ModelEntry",
    "ReportInput",
    "Verdict",
    "analyse",
    "described",
    "fit_nominal_baseline",
    "iso9283",
    "iso_series_from_measurements",
    "joint_curves",
    "model_entry",
    "summary",
    "verdict",
    "write_report",
]
