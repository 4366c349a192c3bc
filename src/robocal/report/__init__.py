"""The calibration report: one self-contained HTML page plus a JSON summary.

``write_report(ReportInput(...), "report.html")`` writes ``report.html`` (plots as inline
SVG drawn by robocal itself, ADR 0049; inline CSS, no scripts, readable offline) and
``report.json`` beside it. The first screen gives the verdict (succeeded / marginal /
failed, with the reason) against :class:`Acceptance`; below: error before/after per model
with the "% described" table, joint-dependent errors with ±2σ bands, identifiability,
ISO 9283 AP/RP, predicted accuracy over the workspace, the measurement log and provenance.
"""

from typing import TYPE_CHECKING

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
    from robocal.report._checks import add_checks_section
    from robocal.report._compensation import add_compensation_section
    from robocal.report._write import REPORT_FORMAT, summary, write_report

# Lazy attributes, kept on purpose: the daemon's configuration check imports this package for
# Acceptance alone, and the figures and page templates are needed only to write a report.
def __getattr__(name: str) -> object:
    found: dict[str, object]
    if name in ("REPORT_FORMAT", "summary", "write_report"):
        from robocal.report._write import REPORT_FORMAT, summary, write_report

        found = {"REPORT_FORMAT": REPORT_FORMAT, "summary": summary, "write_report": write_report}
    elif name == "add_compensation_section":
        from robocal.report._compensation import add_compensation_section

        found = {name: add_compensation_section}
    elif name == "add_checks_section":
        from robocal.report._checks import add_checks_section

        found = {name: add_checks_section}
    else:
        raise AttributeError(f"module 'robocal.report' has no attribute {name!r}")
    globals().update(found)  # each module is looked up once
    return found[name]


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
    "add_checks_section",
    "add_compensation_section",
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
