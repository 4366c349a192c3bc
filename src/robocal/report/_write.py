"""``write_report``: analysis, plots, the HTML page and the JSON summary beside it."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from robocal._core.files import atomic_write_text
from robocal.report._analysis import SETS, Analysis, analyse
from robocal.report._figures import render_all
from robocal.report._html import render
from robocal.report._input import ReportInput

REPORT_FORMAT = "robocal.report/1"


def _clean(v: Any) -> Any:
    """JSON-safe: numpy scalars to Python, NaN/inf to None."""
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(x) for x in v]
    if isinstance(v, np.ndarray):
        return _clean(v.tolist())
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def summary(an: Analysis) -> dict[str, Any]:
    """The machine-readable summary (mm, deg, %)."""
    inp = an.inp
    robot = an.robot
    sel = an.models.get(an.selected) if an.selected else None
    cm = sel.entry.calibrated if sel else None
    accuracy: dict[str, Any] = {}
    for name, m in an.models.items():
        accuracy[name] = {}
        for which in SETS:
            s = m.sets.get(which)
            if s is None or s.stats is None:
                continue
            d = s.stats.to_dict()
            d.update({"percent_described_rms": None, "percent_described_mean": None,
                      "percent_described_r2": None, "source": s.source})
            if s.described is not None:
                d.update({"percent_described_rms": s.described.rms,
                          "percent_described_mean": s.described.mean,
                          "percent_described_r2": s.described.r2})
            accuracy[name][which] = d
    joints = []
    for jc in an.joints:
        comps = {}
        for c in jc.curves:
            f, u = (1e3, "mm") if c.component.startswith("d") else (180 / math.pi, "deg")
            comps[c.component] = {
                "unit": u, "terms": c.n_terms,
                "peak_to_peak": float(np.ptp(c.value)) * f,
                "max_abs": float(np.max(np.abs(c.value))) * f,
                "max_2sigma": None if c.sigma is None else 2 * float(np.max(c.sigma)) * f}
        joints.append({"joint": jc.joint + 1, "components": comps})
    log = None
    if inp.log is not None:
        log = dataclasses.asdict(inp.log)
    out = {
        "format": REPORT_FORMAT,
        "title": inp.title,
        "created": inp.created,
        "campaign_id": inp.campaign_id or None,
        "robot": None if robot is None else {"name": robot.name,
                                             "manufacturer": robot.manufacturer,
                                             "dof": robot.dof},
        "selected_model": an.selected,
        "model_id": None if cm is None else cm.model_id,
        "verdict": an.verdict.to_dict(),
        "judged_on": None if an.judged is None else an.judged.on,
        "acceptance": dataclasses.asdict(inp.acceptance),
        "baseline": an.baseline_note,
        "accuracy": accuracy,
        "outliers": list(an.outliers),
        "validation_glitches": list(an.validation_glitches),
        "joint_errors": {"model": an.joint_model, "joints": joints},
        "identifiability": None if an.ident is None else an.ident.to_dict(),
        "cpa": None if an.cpa is None else an.cpa.to_dict(),
        "iso9283": [r.to_dict() for r in an.iso],
        "workspace": None if an.work is None else an.work.to_dict(),
        "coverage": None if an.coverage is None else an.coverage.to_dict(),
        "measurement_log": log,
        "provenance": an.hashes,
        "notes": list(inp.notes),
    }
    return _clean(out)


def write_report(inp: ReportInput, out_html: str | Path, *,
                 json_path: str | Path | None = None) -> tuple[Path, Path]:
    """Write the self-contained HTML report and its JSON summary; return both paths.

    The JSON goes to ``json_path`` or beside the page with the suffix ``.json``
    (``report.html`` -> ``report.json``). When ``out_html`` is an existing directory the page
    is ``report.html`` inside it. Both files are written atomically.
    """
    t0 = time.perf_counter()
    out_html = Path(out_html)
    if out_html.is_dir():
        out_html = out_html / "report.html"
    jpath = Path(json_path) if json_path is not None else out_html.with_suffix(".json")
    an = analyse(inp)
    t1 = time.perf_counter()
    plots = render_all(an)
    t2 = time.perf_counter()
    summ = summary(an)
    summ["figures"] = sorted(plots)
    page = render(an, plots, summ)
    summ["timing_s"] = {"analysis": round(t1 - t0, 3), "figures": round(t2 - t1, 3),
                        "total": round(time.perf_counter() - t0, 3)}
    out_html.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_html, page)
    atomic_write_text(jpath, json.dumps(summ, indent=1, ensure_ascii=False))
    return out_html, jpath
