"""The report's Compensation section: what was pushed, predicted, and measured after the push.

The daemon rewrites it whenever what is true of the campaign's compensation changes
(approval, push, re-measurement, rollback, a later push that supersedes it; also after a
restart): the campaign's ``report.html`` gets (or has replaced) a ``<section
id="compensation">`` and ``report.json`` a ``compensation`` list and an ``approval``. The
section opens with one sentence of what is true now (approved model, ``push KEY`` with its
time, measured before -> after, and whether its table is active, superseded by a later push
or rolled back, when and by which rollback); then each push (named by its journal key, the
one id status, list, watch and the API use; the table checksum is a detail) with its kind
and purpose, the predicted residual against the nominal one and the model's accuracy, and
the measured before/after of its verification run with a per-target plot.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from robocal._core.files import atomic_write_text
from robocal.report._figures import Plot, grid, new_figure, render
from robocal.report._html import _fig, _table, esc, nice_date, put_section

__all__ = ["add_compensation_section", "compensation_html"]

_SECTION = re.compile(r'<section id="compensation">.*?</section>', re.DOTALL)
_SUMMARY = re.compile(r'<div id="push-result"[^>]*>.*?</div>', re.DOTALL)


def _plot(entry: Mapping[str, Any]) -> Plot | None:
    """Per-target error (mm) measured before and after the push, one pair of bars each."""
    v = entry.get("verification") or {}
    rows = v.get("per_target") or []
    if not rows:
        return None
    fig = new_figure(7.0, 2.6)
    (ax,) = grid(fig, 1, 1, (0.65, 0.1, 0.45, 0.3))
    x = np.arange(len(rows), dtype=float)
    ax.bar(x - 0.2, [r["before_mm"] for r in rows], 0.4, "#9e9e9e",
           label="before (program targets)")
    ax.bar(x + 0.2, [r["after_mm"] for r in rows], 0.4, "#1f77b4",
           label="after (pushed values)")
    ax.yscale = "log"
    step = max(1, -(-len(rows) // 16))  # at most 16 labels, so they never overlap
    ax.set_xticks(x[::step], [str(r["index"]) for r in rows][::step])
    ax.xlim = (-0.5, len(rows) - 0.5)
    ax.xlabel = "target (row of the pushed table)"
    ax.ylabel = "position error, mm"
    ax.legend("above", ncol=2)
    return render(f"compensation-{entry.get('key', '')}", fig,
                  "position error of each verified target before and after the push")


def _mm(v: Any, digits: int = 4) -> str:
    """A length already in mm (``–`` when missing)."""
    return f"{float(v):.{digits}f}" if isinstance(v, int | float) else "–"


def _rms(block: Mapping[str, Any] | None) -> float | None:
    if not block:
        return None
    v = block.get("rms_mm")
    return float(v) if isinstance(v, int | float) else None


def _now(e: Mapping[str, Any]) -> str:
    """Where the push's table is now (the daemon's one truth), or why it never got there."""
    state = e.get("compensation_state")
    if e.get("state") != "completed" or state is None:
        return str(e.get("state", "-"))
    if state == "superseded":
        return f"superseded by push {e.get('superseded_by')}"
    if state == "rolled back":
        return (f"rolled back at {nice_date(str(e.get('rolled_back_at', '')))} by rollback "
                f"{e.get('rolled_back_by')}")
    return "active on the controller"


def _measured(e: Mapping[str, Any]) -> str:
    v = e.get("verification") or {}
    before, after = _rms(v.get("before")), _rms(v.get("after"))
    if before is not None and after is not None:
        return (f"measured {_mm(before)} mm before -> {_mm(after)} mm after "
                f"({(v.get('after') or {}).get('n')} targets)")
    return f"re-measurement {v.get('state', 'not recorded')}"


def _headline(pushes: Sequence[Mapping[str, Any]], approval: Mapping[str, Any] | None) -> str:
    """One sentence of what is true now: approval, push, measurement, where the table is."""
    parts = []
    if approval:
        parts.append(f"Model {esc(approval.get('model'))} approved by "
                     f"{esc(approval.get('actor'))} at {esc(nice_date(str(approval.get('at'))))}.")
    done = [e for e in pushes if e.get("state") == "completed"]
    if not done:
        parts.append("Not pushed to the controller" + (" yet." if approval else "."))
    for e in done:
        parts.append(f"Pushed as <b>push {esc(e.get('key'))}</b> by {esc(e.get('actor'))} "
                     f"at {esc(nice_date(str(e.get('at'))))}; {esc(_measured(e))}. "
                     f"Now: <b>{esc(_now(e))}</b>.")
    return f'<p class="now">{" ".join(parts)}</p>'


def compensation_html(entries: Sequence[Mapping[str, Any]],
                      approval: Mapping[str, Any] | None = None) -> str:
    """The ``<section id="compensation">`` for the campaign's push journal ``entries`` (each
    push with ``compensation_state`` and what made it so) and its ``approval``."""
    out = ['<section id="compensation"><h2>Compensation</h2>']
    pushes = [e for e in entries if e.get("action") == "push"]
    out.append(_headline(pushes, approval))
    if not pushes:
        out.append("</section>")
        return "".join(out)
    rows = []
    for e in pushes:
        v = e.get("verification") or {}
        rows.append([
            esc(e.get("key")), esc(_now(e)), esc(nice_date(e["at"])), esc(e.get("actor")),
            esc(e.get("kind")), _mm(e.get("predicted_residual_mm")),
            _mm(e.get("nominal_residual_mm")), _mm(e.get("model_accuracy_mm")),
            _mm(_rms(v.get("before"))), _mm(_rms(v.get("after"))),
            esc((v.get("after") or {}).get("n", v.get("state", "-"))),
            esc(str(e.get("checksum", ""))[:16])])
    out.append(_table(["push", "now", "time", "by", "kind", "predicted mm", "nominal mm",
                       "model mm", "measured before mm", "measured after mm", "targets",
                       "table checksum"], rows, raw=True))
    out.append("<p>Predicted: the model's residual with the table applied, against the "
               "nominal (uncompensated) residual on the same targets. Measured: the daemon "
               "moved the robot to a subset of the pushed targets, first as programmed "
               "(before) then to the pushed values (after), and measured each with the "
               "tracker; errors are distances to where the error-free robot would be.</p>")
    for e in pushes:
        if e.get("purpose"):
            out.append(f"<p><b>{esc(e.get('kind'))}</b>: {esc(e['purpose'])}.</p>")
        for w in e.get("warnings") or []:
            out.append(f'<p class="warn">{esc(w)}</p>')
        if e.get("forced"):
            out.append(f'<p class="warn">Pushed by force: {esc(e.get("refusal"))}</p>')
        v = e.get("verification") or {}
        if v.get("state") in ("skipped", "failed"):
            out.append(f"<p>Not measured after the push: {esc(v.get('reason'))}</p>")
        out.append(_fig(_plot(e), f"Verification of push {esc(e.get('key', ''))}: "
                                  "error of each measured target before and after"))
    out.append("</section>")
    return "".join(out)


def push_summary_html(entries: Sequence[Mapping[str, Any]]) -> str:
    """One line under the verdict: the latest push and its measured before -> after."""
    pushes = [e for e in entries if e.get("action") == "push"]
    if not pushes:
        return ""
    e = pushes[-1]
    v = e.get("verification") or {}
    before, after = _rms(v.get("before")), _rms(v.get("after"))
    if before is not None and after is not None:
        n = (v.get("after") or {}).get("n")
        what = (f"measured {before:.4f} mm before &rarr; {after:.4f} mm after on "
                f"{esc(n)} re-measured targets")
    else:
        what = f"not measured after the push ({esc(v.get('reason') or v.get('state') or '-')})"
    active = e.get("state") == "completed" and e.get("compensation_state") in (None, "active")
    return (f'<div id="push-result" class="flag {"ok" if active else "info"}"><b>Pushed</b> as '
            f'push {esc(e.get("key"))} ({esc(e.get("kind"))} table '
            f'{esc(str(e.get("checksum", ""))[:12])}; '
            f'{esc(nice_date(str(e.get("at", ""))))} by {esc(e.get("actor"))}): {what}. '
            f'Now: {esc(_now(e))}. <a href="#compensation">Details</a></div>')


def _put_summary(page: str, summary: str) -> str:
    """``page`` with the push summary right under the verdict (replacing an earlier one)."""
    page = _SUMMARY.sub("", page, count=1)
    start = page.find('<section id="verdict"')
    end = page.find("</section>", start) if start >= 0 else -1
    if not summary or end < 0:
        return page
    end += len("</section>")
    return page[:end] + summary + page[end:]


def add_compensation_section(out_dir: str | Path, entries: Sequence[Mapping[str, Any]], *,
                             approval: Mapping[str, Any] | None = None) -> bool:
    """Add (or replace) the Compensation section of ``out_dir``'s report files; return
    False when there is nothing to rewrite: no report files, or a ``report.json`` that
    already shows ``entries`` and ``approval``.

    Missing report files are left missing (a campaign fitted with ``report = false``). The
    HTML is written first, the JSON last: a JSON that shows the record vouches for both.
    """
    out_dir = Path(out_dir)
    data = [dict(e) for e in entries]
    jpath, hpath = out_dir / "report.json", out_dir / "report.html"
    doc = json.loads(jpath.read_text(encoding="utf-8")) if jpath.exists() else None
    if doc is not None and doc.get("compensation") == data and doc.get("approval") == approval:
        return False
    wrote = False
    if hpath.exists():
        page = hpath.read_text(encoding="utf-8")
        page = put_section(page, _SECTION, compensation_html(data, approval))
        atomic_write_text(hpath, _put_summary(page, push_summary_html(data)))
        wrote = True
    if doc is not None:
        doc["compensation"] = data
        doc["approval"] = None if approval is None else dict(approval)
        atomic_write_text(jpath, json.dumps(doc, indent=1, default=str))
        wrote = True
    return wrote
