"""The report's Drift checks section: the checks of the campaign's model over time (ADR 0041).

The daemon rewrites it after each check of a model (``robocal check``): the campaign's
``report.html`` gets (or has replaced) a ``<section id="checks">`` with the latest verdict
and recommendation, a table of the checks and a plot of their RMS and max error over time
against the thresholds; ``report.json`` gets a ``checks`` list.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from robocal._core.files import atomic_write_text
from robocal.report._figures import Plot, grid, new_figure, render
from robocal.report._html import _fig, _table, esc, nice_date, put_section

__all__ = ["add_checks_section", "checks_html"]

_SECTION = re.compile(r'<section id="checks">.*?</section>', re.DOTALL)
_ADVICE = {"none": "nothing to do", "reuse": "re-calibrate with --reuse",
           "full": "full calibration"}


def _mm(v: Any) -> str:
    return f"{float(v):.4f}" if isinstance(v, int | float) else "–"


def _plot(checks: Sequence[Mapping[str, Any]], thresholds: Mapping[str, Any]) -> Plot | None:
    """RMS and max error (mm) of each check, in order, with the warn and fail RMS lines."""
    done = [c for c in checks if isinstance(c.get("rms_mm"), int | float)]
    if len(done) < 2:
        return None
    fig = new_figure(7.0, 2.6)
    (ax,) = grid(fig, 1, 1, (0.65, 0.1, 0.45, 0.3))
    x = list(range(len(done)))
    ax.line(x, [c["rms_mm"] for c in done], "#1f77b4", marker="o", size=3.5, label="RMS")
    ax.line(x, [float(c.get("max_mm") or math.nan) for c in done], "#9e9e9e", marker=".",
            size=2.0, label="max")
    for key, colour in (("warn_rms_mm", "#ff7f0e"), ("fail_rms_mm", "#d62728")):
        if isinstance(thresholds.get(key), int | float):
            ax.hline(thresholds[key], colour, dash="--", width=1.0,
                     label=key.replace("_mm", "").replace("_", " "))
    step = max(1, -(-len(done) // 12))
    ax.set_xticks(x[::step], [str(c["id"]) for c in done][::step])
    ax.xlabel = "check"
    ax.ylabel = "error vs model, mm"
    ax.legend("above", ncol=4)
    return render("checks", fig, "RMS and max error of each drift check, in order")


def checks_html(checks: Sequence[Mapping[str, Any]],
                thresholds: Mapping[str, Any] | None = None) -> str:
    """The ``<section id="checks">`` for the model's checks (oldest first)."""
    out = ['<section id="checks"><h2>Drift checks</h2>']
    if not checks:
        out.append("<p>No check of this model yet.</p></section>")
        return "".join(out)
    last = checks[-1]
    verdict = last.get("verdict") or last.get("state")
    out.append(f'<p class="now">Latest: check {esc(last.get("id"))} at '
               f'{esc(nice_date(str(last.get("created", ""))))}, <b>{esc(verdict)}</b>, RMS '
               f'{_mm(last.get("rms_mm"))} mm; recommendation: '
               f'<b>{esc(_ADVICE.get(str(last.get("recommendation")), "–"))}</b>.</p>')
    rows = [[esc(c.get("id")), esc(nice_date(str(c.get("created", "")))),
             esc(c.get("verdict") or c.get("state")), _mm(c.get("rms_mm")),
             _mm(c.get("max_mm")), _mm(c.get("growth_mm")), esc(c.get("n")),
             esc(_ADVICE.get(str(c.get("recommendation")), "–"))] for c in checks]
    out.append(_table(["check", "time", "verdict", "RMS mm", "max mm", "growth mm", "poses",
                       "recommendation"], rows, raw=True))
    out.append("<p>Each check measured poses of this campaign again and compared them with "
               "what the model predicts at the joints read back; growth is the change of the "
               "RMS since the previous check of this model.</p>")
    out.append(_fig(_plot(checks, thresholds or {}), "Trend of the drift checks"))
    out.append("</section>")
    return "".join(out)


def add_checks_section(out_dir: str | Path, checks: Sequence[Mapping[str, Any]], *,
                       thresholds: Mapping[str, Any] | None = None) -> bool:
    """Add (or replace) the Drift checks section of ``out_dir``'s report files; return False
    when there is nothing to rewrite (no report files, or a ``report.json`` showing
    ``checks`` already, or no checks to show). The HTML is written first, the JSON last."""
    out_dir = Path(out_dir)
    data = [dict(c) for c in checks]
    jpath, hpath = out_dir / "report.json", out_dir / "report.html"
    doc = json.loads(jpath.read_text(encoding="utf-8")) if jpath.exists() else None
    if (doc is not None and doc.get("checks", []) == data) or (doc is None and not data):
        return False
    wrote = False
    if hpath.exists():
        page = put_section(hpath.read_text(encoding="utf-8"), _SECTION,
                           checks_html(data, thresholds))
        atomic_write_text(hpath, page)
        wrote = True
    if doc is not None:
        doc["checks"] = data
        atomic_write_text(jpath, json.dumps(doc, indent=1, default=str))
        wrote = True
    return wrote
