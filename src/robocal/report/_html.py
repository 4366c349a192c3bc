"""The self-contained HTML page: inline CSS, plots as inline SVG, no scripts, no links out."""

from __future__ import annotations

import datetime as _dt
import html
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from robocal.report._analysis import SETS, Analysis
from robocal.report._figures import COMP_LABEL, Plot, color
from robocal.report._metrics import FAIL, MARGINAL, PASS, SUCCEEDED, WARN

_CSS = """
*{box-sizing:border-box}
body{margin:0;font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,"DejaVu Sans",sans-serif;
color:#1d2330;background:#f4f6f9}
main{max-width:1240px;margin:0 auto;padding:0 18px 40px}
header.top{background:#1d2330;color:#fff;padding:10px 18px}
header.top .in{max-width:1240px;margin:0 auto;display:flex;flex-wrap:wrap;gap:6px 22px;
align-items:baseline}
header.top b{font-size:17px}
header.top span{color:#c9d1e0;font-size:13px}
.verdict{margin:14px 0 12px;padding:14px 18px;border-radius:8px;border-left:10px solid;
background:#fff;box-shadow:0 1px 3px rgba(0,0,0,.08)}
.verdict .badge{font-size:24px;font-weight:700;letter-spacing:.02em}
.verdict p{margin:6px 0 0;font-size:15px}
.verdict p.plain{color:#414b5e;font-size:14px}
.succeeded{border-color:#1e8e3e}.succeeded .badge{color:#1e8e3e}
.marginal{border-color:#e37400}.marginal .badge{color:#b35c00}
.failed{border-color:#d93025}.failed .badge{color:#c5221f}
.first{display:grid;grid-template-columns:minmax(0,1.25fr) minmax(0,1fr);gap:14px}
.cards{display:grid;grid-template-columns:repeat(3,1fr);gap:10px}
.card{background:#fff;border-radius:8px;padding:9px 12px;box-shadow:0 1px 3px rgba(0,0,0,.08)}
.card .v{font-size:22px;font-weight:700}
.card .k{font-size:12px;color:#5a6375}
.panel{background:#fff;border-radius:8px;padding:10px 14px;box-shadow:0 1px 3px rgba(0,0,0,.08)}
.checks{margin-top:10px}
.checks table{width:100%}
.st{font-weight:700;white-space:nowrap}
.st.pass{color:#1e8e3e}.st.warn{color:#b35c00}.st.fail{color:#c5221f}.st.info{color:#5a6375}
h2{margin:30px 0 8px;padding-bottom:4px;border-bottom:2px solid #d5dbe5;font-size:20px}
h3{margin:18px 0 6px;font-size:16px}
table{border-collapse:collapse;background:#fff;font-size:13px}
th,td{padding:4px 9px;border-bottom:1px solid #e3e7ee;text-align:right;vertical-align:top}
th:first-child,td:first-child,td.l,th.l{text-align:left}
thead th{background:#eef1f6;font-weight:600}
.note{color:#5a6375;font-size:12.5px;margin:4px 0}
.note.warn{color:#b35c00}
figure{margin:10px 0;background:#fff;border-radius:8px;padding:6px;
box-shadow:0 1px 3px rgba(0,0,0,.08)}
figure svg{max-width:100%;height:auto;display:block}
figcaption{font-size:12.5px;color:#5a6375;padding:2px 6px}
nav.toc{margin:16px 0 0;font-size:13px}
nav.toc a{margin-right:14px;color:#1a57b5;text-decoration:none}
.swatch{display:inline-block;width:10px;height:10px;border-radius:2px;margin-right:5px}
details{margin:8px 0}summary{cursor:pointer;color:#1a57b5}
code{font-size:12.5px}
.two{display:grid;grid-template-columns:minmax(0,1fr) minmax(0,1fr);gap:14px;
align-items:start}
.checks th,.checks td{text-align:left}
.flag{margin:10px 0;padding:9px 14px;border-radius:6px;border-left:7px solid #d93025;
background:#fdecea;color:#5c1a14}
.flag.ok{border-color:#1e8e3e;background:#e6f4ea;color:#14371f}
.flag.info{border-color:#8a94a6;background:#f1f3f6;color:#2b3240}
.flag b{font-weight:700}
@media print{figure{break-inside:avoid;box-shadow:none}}
@media (max-width:900px){.first,.two{grid-template-columns:1fr}
.cards{grid-template-columns:repeat(2,1fr)}}
"""

_BADGE = {SUCCEEDED: "✔ Calibration succeeded", MARGINAL: "⚠ Calibration marginal",
          "failed": "✖ Calibration failed"}
_ICON = {PASS: "✔ pass", WARN: "⚠ warn", FAIL: "✖ fail", "info": "ℹ info"}


def esc(v: Any) -> str:
    """HTML-escape anything."""
    return html.escape(str(v), quote=True)


def mm(v: float | None, digits: int = 3) -> str:
    """A length in m shown in mm (``–`` when missing)."""
    if v is None or not math.isfinite(v):
        return "–"
    return f"{v * 1e3:.{digits}f}"


def pct(v: float | None, digits: int = 1) -> str:
    """A percentage (``–`` when missing)."""
    if v is None or not math.isfinite(v):
        return "–"
    return f"{v:.{digits}f} %"


def nice_date(iso: str) -> str:
    """``2026-11-21T06:06:46+00:00`` -> ``2026-11-21 06:06 UTC`` (as given if unparsable)."""
    try:
        d = _dt.datetime.fromisoformat(iso)
    except ValueError:
        return iso
    if d.tzinfo is not None:
        d = d.astimezone(_dt.UTC)
        return d.strftime("%Y-%m-%d %H:%M UTC")
    return d.strftime("%Y-%m-%d %H:%M")


def _table(head: Sequence[str], rows: Iterable[Sequence[Any]], *, raw: bool = False,
           cls: str = "") -> str:
    h = "".join(f"<th>{esc(x)}</th>" for x in head)
    body = "".join("<tr>" + "".join(f"<td>{x if raw else esc(x)}</td>" for x in r) + "</tr>"
                   for r in rows)
    c = f' class="{cls}"' if cls else ""
    return f"<table{c}><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>"


def put_section(page: str, pattern: re.Pattern[str], section: str) -> str:
    """``page`` with ``section`` in place of the one ``pattern`` finds, else at the end of
    ``<main>`` (or of ``<body>``): how the daemon adds sections to a written report."""
    if pattern.search(page):
        return pattern.sub(lambda _m: section, page, count=1)
    if "</main>" in page:
        return page.replace("</main>", section + "</main>", 1)
    return page.replace("</body>", section + "</body>", 1)


def _fig(p: Plot | None, caption: str) -> str:
    if p is None:
        return ""
    # the markup carries role="img", the alt text as aria-label and <title> (ADR 0049)
    return f"<figure>{p.svg}<figcaption>{caption}</figcaption></figure>"


def _swatch(name: str, i: int = 0) -> str:
    return f'<span class="swatch" style="background:{color(name, i)}"></span>{esc(name)}'


def render(an: Analysis, plots: Mapping[str, Plot], summary: Mapping[str, Any]) -> str:
    """The whole page."""
    parts = [_head(an), "<main>", _first_screen(an, plots, summary), _toc(an),
             _accuracy(an, plots), _cpa(an), _joints(an, plots), _ident(an, plots),
             _iso(an, plots), _coverage(an, plots),
             _workspace(an, plots), _log(an, plots), "</main>", _footer(an), "</body></html>"]
    return "\n".join(p for p in parts if p)


def _head(an: Analysis) -> str:
    inp = an.inp
    robot = an.robot.name if an.robot else "unknown robot"
    sel = an.models.get(an.selected) if an.selected else None
    cm = sel.entry.calibrated if sel else None
    model = f"{an.selected} · {cm.model_id}" if cm else (an.selected or "no model")
    items = [f"<b>{esc(inp.title)}</b>", f"<span>Robot: <b>{esc(robot)}</b></span>",
             f"<span>Model: <b>{esc(model)}</b></span>",
             f"<span>Date: {esc(nice_date(inp.created))}</span>"]
    if inp.campaign_id:
        items.append(f"<span>Campaign: {esc(inp.campaign_id)}</span>")
    return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
            f'<meta name="viewport" content="width=device-width,initial-scale=1">'
            f"<title>{esc(inp.title)} – {esc(robot)}</title><style>{_CSS}</style></head>"
            f'<body><header class="top"><div class="in">{"".join(items)}</div></header>')


def _card(value: str, key: str) -> str:
    return f'<div class="card"><div class="v">{value}</div><div class="k">{key}</div></div>'


def _first_screen(an: Analysis, plots: Mapping[str, Plot], summary: Mapping[str, Any]) -> str:
    v = an.verdict
    j = an.judged
    cards = []
    if j is not None and j.stats is not None:
        on = "held-out" if j.on == "validation" else "calibration"
        cards.append(_card(f"{mm(j.stats.rms_m)} mm",
                           f"RMS error after calibration ({on} poses, {esc(j.model)})"))
        cards.append(_card(f"{mm(j.baseline.rms_m) if j.baseline else '–'} mm",
                           f"RMS error of the nominal model ({on} poses)"))
        cards.append(_card(pct(j.described.rms if j.described else None),
                           "of the measured error described (RMS-based)"))
        cards.append(_card(f"{mm(j.stats.max_m)} mm", f"largest error after ({on})"))
    n_cal = len(an.inp.calibration) if an.inp.calibration is not None else None
    n_val = len(an.inp.validation) if an.inp.validation is not None else None
    sel = an.models.get(an.selected) if an.selected else None
    if sel is not None:  # without data: the pose counts the fit stored
        for which in ("calibration", "validation"):
            st = sel.sets[which].stats if which in sel.sets else None
            if st is not None and st.n and (n_cal if which == "calibration" else n_val) is None:
                if which == "calibration":
                    n_cal = st.n
                else:
                    n_val = st.n
    cards.append(_card(f"{n_cal if n_cal is not None else '–'} / "
                       f"{n_val if n_val is not None else '–'}",
                       "calibration / validation poses"))
    cards.append(_card(str(len(an.outliers)), "outliers rejected"))
    checks = _table(["check", "result", "detail"],
                    [(esc(c.name), f'<span class="st {c.status}">{_ICON[c.status]}</span>',
                      f'<span style="text-align:left;display:block">{esc(c.message)}</span>')
                     for c in v.checks], raw=True)
    acc = an.inp.acceptance
    thr = ["held-out RMS below the nominal model's (else failed)",
           f"≥ {acc.min_percent_described:.0f} % of the error described (else marginal)",
           f"≤ {100 * acc.max_outlier_fraction:.0f} % outliers (marginal up to "
           f"{100 * acc.fail_outlier_fraction:.0f} %)",
           f"validation/calibration RMS ≤ {acc.max_overfit_ratio:.2f} × what the parameter "
           "count alone explains"]
    if acc.max_rms_mm is not None:
        thr.append(f"held-out RMS ≤ {acc.max_rms_mm:.3f} mm")
    if acc.max_error_mm is not None:
        thr.append(f"held-out max error ≤ {acc.max_error_mm:.3f} mm")
    cpa_flag = ""
    if an.cpa is not None and an.cpa.flag:
        if _judges_cpa(an):  # the verdict is about CPA itself: an alarm
            cpa_flag = (f'<div class="flag" data-flag="cpa-worse-than-nominal"><b>⚠ Circle '
                        f"Point Analysis:</b> {esc(an.cpa.flag)} "
                        '<a href="#cpa">Details</a></div>')
        else:  # a reference method that does not apply here, under another model's verdict
            cpa_flag = (f'<div class="flag info" data-flag="cpa-worse-than-nominal"><b>ℹ '
                        "Circle Point Analysis, for reference only (not applicable here; the "
                        f"verdict above is about {esc(an.selected or 'the selected model')}):"
                        f"</b> {esc(an.cpa.flag)} <a href=\"#cpa\">Details</a></div>")
    left = (f'<div class="cards">{"".join(cards)}</div>'
            f'<div class="panel checks">{checks}<p class="note">Acceptance: '
            f'{esc("; ".join(thr))}.</p></div>{cpa_flag}')
    right = _fig(plots.get("summary"), "RMS position error per model: hatched = calibration "
                 "poses, solid = held-out validation poses. <i>nominal</i> = nominal kinematics "
                 "with only base and reflector fitted.")
    if not right:
        right = '<div class="panel note">No accuracy figures available.</div>'
    plain = ""
    if j is not None and j.stats is not None:
        where = (f"{j.stats.n} poses not used for fitting" if j.on == "validation"
                 else f"the {j.stats.n} calibration poses (no held-out poses were measured)")
        plain = (f"On {where}, the calibrated model predicts where the robot really goes "
                 f"within {mm(j.stats.rms_m)} mm RMS (largest error {mm(j.stats.max_m)} mm)")
        plain += (f"; the nominal model is off by {mm(j.baseline.rms_m)} mm RMS."
                  if j.baseline is not None else ".")
        plain = f'<p class="plain">{esc(plain)}</p>'
    return (f'<section id="verdict" class="verdict {v.outcome}" data-outcome="{v.outcome}">'
            f'<div class="badge">{_BADGE[v.outcome]}</div><p class="headline">'
            f"{esc(v.reason or v.headline)}</p>{plain}</section>"
            f'<div class="first"><div>{left}</div><div>{right}</div></div>')


def _judges_cpa(an: Analysis) -> bool:
    """Is the verdict about a CPA model (then CPA's shortfalls are alarms, else references)?"""
    return bool(an.selected) and str(an.selected).startswith("cpa")


def _toc(an: Analysis) -> str:
    links = [("accuracy", "Position error"),
             *([("cpa", "Circle Point Analysis")] if an.cpa is not None else []),
             ("joints", "Joint-dependent errors"),
             ("identifiability", "Identifiability"), ("iso", "ISO 9283"),
             *([("coverage", "Joint coverage")] if an.coverage is not None else []),
             ("workspace", "Predicted accuracy"), ("log", "Measurements & provenance")]
    return '<nav class="toc">' + "".join(f'<a href="#{a}">{esc(t)}</a>' for a, t in links) \
        + "</nav>"


def _accuracy(an: Analysis, plots: Mapping[str, Plot]) -> str:
    out = ['<section id="accuracy"><h2>Position error before and after calibration</h2>']
    rows = []
    for i, (name, m) in enumerate(an.models.items()):
        cells: list[str] = [_swatch(name, i) + f' <span class="note">{esc(m.entry.label)}'
                            f"</span>"]
        for which in SETS:
            s = m.sets.get(which)
            d = s.described if s else None
            cells += [pct(d.rms if d else None), pct(d.mean if d else None),
                      pct(d.r2 if d else None, 2)]
        rows.append(cells)
    out.append("<h3>% of measured error described</h3>")
    out.append(_table(["model", "cal. RMS-based", "cal. mean-based", "cal. R²",
                       "val. RMS-based", "val. mean-based", "val. R²"], rows, raw=True))
    worse = [m.entry.label for m in an.models.values()
             if any(s.described is not None and s.described.rms is not None
                    and s.described.rms < 0 for s in m.sets.values())]
    if worse:
        out.append('<p class="note warn">A negative percentage means the model predicts the '
                   "robot <em>worse</em> than the nominal baseline does: "
                   f"{esc(', '.join(worse))}. Such a model must not be used for compensation."
                   " For Circle Point Analysis the usual causes are short arcs (the reflector "
                   "is visible over only part of a joint's range), small circle radii and "
                   "joint-dependent errors, which CPA cannot average out.</p>")
    n_out = len(an.outliers)
    n_gl = len(an.validation_glitches)
    gl = (f" ({n_gl} of them validation poses with an error above "
          f"{an.inp.acceptance.validation_outlier_factor:g} × the median: measurement glitches)"
          if n_gl else "")
    out.append(f'<p class="note">Baseline ("measured error"): {esc(an.baseline_note)}. '
               "RMS-based = 1 − RMS|r| / RMS|e|; mean-based = 1 − mean|r| / mean|e|; "
               "R² = 1 − Σ|r|² / Σ|e|², with e the baseline's and r the model's error at the "
               f"same poses. {n_out} outlier pose{'s' if n_out != 1 else ''} excluded{gl}, "
               "the same for every model.</p>")
    rows = []
    for i, (name, m) in enumerate(an.models.items()):
        for which in SETS:
            s = m.sets.get(which)
            if s is None or s.stats is None:
                continue
            st = s.stats
            rows.append([_swatch(name, i), which, str(st.n) if st.n else "–", mm(st.rms_m),
                         mm(st.mean_m), mm(st.p95_m), mm(st.max_m), esc(s.source)])
    out.append("<h3>Error statistics (mm)</h3>")
    if rows:
        out.append(_table(["model", "poses", "n", "RMS", "mean", "95 %", "max", "from"], rows,
                          raw=True))
        out.append('<p class="note">Error = |measured − predicted| reflector position. '
                   '"from": <i>data</i> = computed here from the measurements, <i>stored</i> = '
                   "read from the model file.</p>")
    else:
        out.append('<p class="note">No accuracy figures: neither measurements nor stored '
                   "metrics.</p>")
    out.append(_fig(plots.get("histograms"), "Distribution of the position error per model "
                    "(log scale; the further left, the better)."))
    out.append(_fig(plots.get("per_pose"), "Position error at each pose. Red crosses: poses "
                    "rejected as outliers (by the fit, or validation glitches)."))
    if not an.data:
        out.append('<p class="note">No measurements were given (report made from a model file '
                   "alone): histograms and per-pose plots need <code>--data</code> / "
                   "<code>--validate</code>.</p>")
    out.append("</section>")
    return "\n".join(out)


def _cpa(an: Analysis) -> str:
    """Classical and polished CPA against nominal, the flag when worse, the circle fits."""
    c = an.cpa
    if c is None:
        return ""
    out = ['<section id="cpa"><h2>Circle Point Analysis (CPA)</h2>']
    alarm = _judges_cpa(an)
    if c.flag:
        out.append(f'<div class="flag{"" if alarm else " info"}" '
                   f'data-flag="cpa-worse-than-nominal"><b>{"⚠" if alarm else "ℹ"}</b> '
                   f"{esc(' '.join(r.sentence() for r in c.worse))}"
                   "<br><b>Reasons:</b> " + esc("; ".join(c.reasons())) + "."
                   + ("" if alarm else "<br>CPA is shown as a reference method: a CPA model "
                      "worse than the nominal one (a difference above +100 % means it more "
                      "than doubles the error) is not applicable to this robot and has no "
                      "bearing on the verdict, which is about "
                      + esc(an.selected or "the selected model") + ".") + "</div>")
    better = [r for r in c.rows if r.better]
    if better:
        out.append(f'<div class="flag ok">✔ {esc(" ".join(r.sentence() for r in better))}'
                   "</div>")
    rows = [[_swatch(r.name, i), esc(r.variant), esc(r.on), str(r.n), mm(r.rms_m),
             mm(r.nominal_rms_m), f"{r.diff_m * 1e3:+.3f}", f"{r.diff_percent:+.1f} %",
             '<span class="st pass">better</span>' if r.better
             else ('<span class="st fail">worse</span>' if alarm
                   else '<span class="st info">worse: not applicable</span>')]
            for i, r in enumerate(c.rows)]
    if rows:
        out.append(_table(["model", "CPA", "poses", "n", "RMS (mm)", "nominal RMS (mm)",
                           "difference (mm)", "difference (% of nominal)", "against nominal"],
                          rows, raw=True))
    note = ("<i>Classical</i> CPA fits a plane and a circle to each joint's sweep on its own "
            "and builds the model from the six axes. <i>Polished</i> CPA re-fits that model "
            "(constant errors) by robust maximum likelihood on all the sweep points at once, "
            "started from the classical one: no circle is then fitted alone, so short arcs "
            "and small radii cost less.")
    p = c.polish
    if p:
        sw = p.get("sweep_rms_mm") or {}
        if isinstance(sw.get("classical"), int | float) and isinstance(sw.get("polished"),
                                                                          int | float):
            note += (f" On the {esc(p.get('sweep_points', '?'))} sweep points the RMS error "
                     f"went from {sw['classical']:.3f} mm (classical) to "
                     f"{sw['polished']:.3f} mm (polished)")
            n_out = len(p.get("outliers") or ())
            note += f", {n_out} outlier{'s' if n_out != 1 else ''} rejected." if n_out else "."
    out.append(f'<p class="note">{note} Neither uses the calibration or validation poses; '
               "both describe constant errors only.</p>")
    if c.circles:
        crow = []
        for ci in c.circles:
            def num(key: str, fmt: str, ci: Mapping[str, Any] = ci) -> str:
                v = ci.get(key)
                return format(v, fmt) if isinstance(v, int | float) else "–"
            crow.append([f"J{esc(ci.get('joint', '?'))}", esc(ci.get("n", "–")),
                         num("arc_deg", ".0f"), num("radius_mm", ".1f"),
                         num("circle_rms_mm", ".4f"), num("noise_rms_mm", ".4f"),
                         num("noise_ratio", ".1f"),
                         esc(", ".join(str(x) for x in ci.get("issues") or ()) or "–")])
        out.append("<h3>Circle fits</h3>")
        out.append(_table(["joint", "points", "arc (deg)", "radius (mm)", "circle RMS (mm)",
                           "noise (mm)", "RMS / noise", "weakness"], crow))
        out.append('<p class="note">Per joint sweep: the chain-angle arc covered, the circle '
                   "radius (the reflector's distance from the axis), the RMS distance of the "
                   "points from the fitted circle, and what the tracker noise alone would "
                   "leave. Weak: arcs under 90°, radii under 100 mm (centre and axis poorly "
                   "determined), circle residuals above twice the noise (joint-dependent "
                   "errors, which CPA cannot describe).</p>")
    out.append("</section>")
    return "\n".join(out)


def _noted(sid: str, title: str, note: str) -> str:
    """A section that only says why it has nothing to show (``note`` is HTML)."""
    return f'<section id="{sid}"><h2>{title}</h2>\n<p class="note">{note}</p></section>'


def _joints(an: Analysis, plots: Mapping[str, Plot]) -> str:
    if not an.joints:
        return _noted("joints", "Joint-dependent errors", "The model has no joint-dependent "
                      "terms (constant errors only).")
    out = ['<section id="joints"><h2>Joint-dependent errors</h2>']
    out.append(f'<p class="note">Model <b>{esc(an.joint_model)}</b>. For each joint, the '
               "identified error of each component as a function of the joint angle "
               "(all terms except the constant one and gravity torsion), drawn about its mean over "
               "the covered range (the constant part cannot be told apart from the constant "
               "errors), with a ±2σ band "
               "propagated from the parameter covariance (gradient = the basis functions of "
               "that component). δ = translation (mm), ε = rotation (deg) of the joint's error "
               "transform. Grey background: outside the joint range the data covered. Right: "
               "residual magnitude at each measured pose against the joint angle.</p>")
    comps = ("dx", "dy", "dz", "ex", "ey", "ez")
    rows = []
    for jc in an.joints:
        by = {c.component: c for c in jc.curves}
        cells = [f"J{jc.joint + 1}"]
        for comp in comps:
            c = by.get(comp)
            if c is None:
                cells.append("–")
                continue
            f = 1e3 if comp.startswith("d") else 180 / math.pi
            s2 = "" if c.sigma is None else f" ± {2 * float(np.max(c.sigma)) * f:.4f}"
            cells.append(f"{float(np.ptp(c.value)) * f:.4f}{s2}")
        rows.append(cells)
    out.append(_table(["joint", *(f"{COMP_LABEL[c]} ({'mm' if c[0] == 'd' else 'deg'})"
                                  for c in comps)], rows))
    out.append('<p class="note">Peak-to-peak of each joint-dependent error component over the '
               "joint range, ± the largest 2σ along the curve. – = no joint-dependent term.</p>")
    for jc in an.joints:
        n = jc.joint + 1
        out.append(f'<h3 id="joint{n}">Joint {n}</h3>')
        out.append(_fig(plots.get(f"joint{n}"), f"Joint {n}: identified joint-dependent errors "
                        "(±2σ) and residuals against the joint angle (red crosses: outliers)."))
    out.append("</section>")
    return "\n".join(out)


def _ident(an: Analysis, plots: Mapping[str, Plot]) -> str:
    if an.ident is None:
        return _noted("identifiability", "Identifiability", "No calibrated model.")
    idt = an.ident
    out = ['<section id="identifiability"><h2>Identifiability</h2>']
    cond = "–" if idt.condition is None else f"{idt.condition:.3g}"
    rank = "–" if idt.rank is None else str(idt.rank)
    out.append(_table(["parameters", "free", "removed (unidentifiable)", "rank", "condition"],
                      [[str(idt.n_params), str(idt.n_free), str(len(idt.removed)), rank, cond]]))
    out.append(f'<p class="note">Rank, condition number and singular values: {esc(idt.source)}'
               ". Removed parameters were fixed by the fit because these poses cannot "
               "distinguish them from other parameters. σ and correlations come from the "
               "parameter covariance.</p>")
    left = _fig(plots.get("singular_values"), "Singular values, normalised by the largest. "
                "A steep drop at the end means weakly determined combinations.")
    right = ""
    if idt.correlations:
        right = "<h3>Strongest correlations</h3>" + _table(
            ["parameter", "parameter", "ρ"],
            [[f"<code>{esc(a)}</code>", f"<code>{esc(b)}</code>", f"{r:+.3f}"]
             for a, b, r in idt.correlations], raw=True)
    if left or right:
        out.append(f'<div class="two"><div>{left}</div><div>{right}</div></div>')
    if idt.removed:
        out.append(f"<details><summary>{len(idt.removed)} removed parameters</summary><p>"
                   + ", ".join(f"<code>{esc(n)}</code>" for n in idt.removed)
                   + "</p></details>")
    rows = []
    for p in idt.parameters:
        s = p["sigma"]
        ratio = "–" if not s else f"{abs(p['value']) / s:.1f}"
        rows.append([f"<code>{esc(p['name'])}</code>", f"{p['value']:.5g}",
                     "–" if s is None else f"{s:.3g}", esc(p["unit"]), ratio,
                     "removed" if p["removed"] else ""])
    out.append(f"<details><summary>All {len(rows)} parameters: value and σ</summary>"
               + _table(["parameter", "value", "σ", "unit", "|value|/σ", ""], rows, raw=True)
               + "</details>")
    out.append("</section>")
    return "\n".join(out)


def _iso(an: Analysis, plots: Mapping[str, Plot]) -> str:
    title = "ISO 9283 pose accuracy and repeatability"
    if not an.iso:
        return _noted("iso", title, "The ISO 9283 cube poses P1–P5 were not measured with "
                      "repeats in this campaign.")
    out = [f'<section id="iso"><h2>{title}</h2>']
    has_model = any(r.ap_model_m is not None for r in an.iso)
    rows = [[r.name, str(r.n), mm(r.ap_m), *(mm(v) for v in r.ap_xyz_m), mm(r.rp_m)]
            + ([mm(r.ap_model_m)] if has_model else []) for r in an.iso]
    frame = an.inp.iso[0].frame if an.inp.iso else an.iso_frame
    head = ["pose", "cycles", "AP", "APx", "APy", "APz", "RP"]
    if has_model:
        head.append("AP after calibration")
    left = (_table(head, rows)
            + '<p class="note">mm. AP = distance between the barycentre of the attained '
            "positions and the commanded position; APx/y/z its components "
            f"({esc(frame)} frame). RP = l̄ + 3·S_l, with l_j the distance of each attained "
            "position to the barycentre and S_l their standard deviation (ISO 9283 §7.2.1, "
            "§7.2.2)."
            + (" AP after calibration: AP against the calibrated model's prediction for the "
               "commanded joints, the accuracy left once the robot is compensated with it."
               if has_model else "") + "</p>")
    if any(r.n < 2 for r in an.iso):
        left += ('<p class="note">Poses measured once have no RP: repeatability needs '
                 "repeated cycles (ISO 9283 uses 30).</p>")
    out.append(f'<div class="two"><div>{left}</div><div>'
               f'{_fig(plots.get("iso"), "AP and RP per ISO pose.")}</div></div>')
    out.append("</section>")
    return "\n".join(out)


def _workspace(an: Analysis, plots: Mapping[str, Plot]) -> str:
    title = "Predicted accuracy over the workspace"
    w = an.work
    if w is None:
        return _noted("workspace", title, "Not available: the model has no parameter "
                      "covariance.")
    out = [f'<section id="workspace"><h2>{title}</h2>']
    s = w.sigma
    out.append(_table(["configurations", "median 1σ", "95 % 1σ", "max 1σ"],
                      [[str(s.size), f"{mm(float(np.median(s)), 4)} mm",
                        f"{mm(float(np.percentile(s, 95)), 4)} mm",
                        f"{mm(float(np.max(s)), 4)} mm"]]))
    out.append('<p class="note">1σ uncertainty (3-D) of the position the calibrated model '
               f"predicts, from the parameter covariance, at random joint configurations "
               f"inside the {esc(w.within)}. It covers the parameter uncertainty only, not "
               "unmodelled errors or tracker noise.</p>")
    out.append(_fig(plots.get("workspace"), "Predicted 1σ position uncertainty: histogram "
                    "and maps in the robot base frame."))
    out.append("</section>")
    return "\n".join(out)


def _coverage(an: Analysis, plots: Mapping[str, Plot]) -> str:
    """Per-joint coverage: limits, calibrated and measured ranges, the program's targets."""
    cov = an.coverage
    if cov is None:
        return ""

    def rng(v: tuple[float, float] | None) -> str:
        return "–" if v is None else f"{v[0]:.1f} … {v[1]:.1f}"

    has_t = cov.targets is not None
    head = ["joint", "limits (deg)", "calibrated (deg)", "measured (deg)"]
    if has_t:
        head += ["targets (deg)", "targets outside"]
    rows = []
    for r in cov.rows:
        row = [f"J{r.joint}", rng(r.limits_deg), rng(r.calibrated_deg), rng(r.measured_deg)]
        if has_t:
            row += [rng(r.targets_deg), str(r.targets_outside)]
        rows.append(row)
    out = ['<section id="coverage"><h2>Joint coverage</h2>', _table(head, rows)]
    note = ("Calibrated: the joint ranges inside which the model's corrections are trusted "
            "(its coverage); outside them the joint-dependent terms are not used. Measured: "
            "the range the calibration poses spanned.")
    if has_t and cov.targets is not None:
        note += (f" {cov.outside} of {len(cov.targets)} program targets lie outside the "
                 "calibrated range" + (": " + "; ".join(cov.names) if cov.names else "") + ".")
    out.append(f'<p class="note">{esc(note)}</p>')
    out.append(_fig(plots.get("coverage"), "Per-joint coverage: limits, calibrated range, "
                    "measured range and program targets."))
    out.append("</section>")
    return "\n".join(out)


def _kv(rows: Sequence[tuple[str, Any]]) -> str:
    return "<table>" + "".join(f'<tr><td class="l">{esc(k)}</td><td class="l">{v}</td></tr>'
                               for k, v in rows) + "</table>"


_WEATHER = (("air temperature", "°C", ("temperature_c", "temp_c", "temperature")),
            ("air pressure", "hPa", ("pressure_hpa", "press_hpa", "pressure")),
            ("humidity", "%", ("humidity_pct", "hum_pct", "humidity")))


def weather_ranges(samples: Sequence[Mapping[str, Any]]
                   ) -> list[tuple[str, str, list[float]]]:
    """(label, unit, values) per weather quantity found in the samples; unknown numeric keys
    are listed under their own name."""
    out = []
    known: set[str] = set()
    for label, unit, keys in _WEATHER:
        known.update(keys)
        vals = [float(w[k]) for w in samples for k in keys
                if isinstance(w.get(k), int | float) and not isinstance(w.get(k), bool)]
        if vals:
            out.append((label, unit, vals))
    extra = sorted({k for w in samples for k in w if k not in known})
    for k in extra:
        vals = [float(w[k]) for w in samples
                if isinstance(w.get(k), int | float) and not isinstance(w.get(k), bool)]
        if vals:
            out.append((f"weather: {k}", "", vals))
    return out


def _thermal(an: Analysis, plots: Mapping[str, Plot]) -> str:
    """The joint temperatures and the thermal term of the selected model (ADR 0042)."""
    parts = [_fig(plots.get("temperatures"), "Joint temperatures while measuring. A campaign "
                  "measured while they still rise calibrates a robot that is not yet the "
                  "one in production (configure <code>[warmup]</code>)."),
             _fig(plots.get("residual_temperature"), "Position error of the selected model "
                  "per pose against the pose's mean joint temperature: a trend is a thermal "
                  "error the model does not describe.")]
    sel = an.models.get(an.selected) if an.selected else None
    cm = sel.entry.calibrated if sel else None
    term = cm.fit.get("thermal") if cm is not None else None
    if isinstance(term, Mapping) and term.get("selected"):
        rows = [(f"J{j + 1} ({c})", f"{v * 1e3:+.3f}", f"{s_ * 1e3:.3f}", f"{t:.1f}")
                for j, (c, v, s_, t) in enumerate(zip(
                    term["components"], term["coef_mm_per_c"], term["sigma_mm_per_c"],
                    term["t_ref_c"], strict=True))]
        parts.append("<p>The fit took a linear thermal term: each link's length change per "
                     "°C of its joint. The model predicts at the reference temperatures.</p>"
                     + _table(["link (component)", "µm/°C", "σ µm/°C", "reference °C"],
                              rows))
    body = "".join(p for p in parts if p)
    return f"<h3>Thermal state</h3>{body}" if body else ""


def _log(an: Analysis, plots: Mapping[str, Plot]) -> str:
    out = ['<section id="log"><h2>Measurements and provenance</h2>', _thermal(an, plots)]
    lg = an.inp.log
    rows: list[tuple[str, Any]] = []
    if lg is not None:
        for k, v in (("poses planned", lg.planned), ("poses measured", lg.measured),
                     ("retries", lg.retries), ("poses failed", lg.failed),
                     ("beam losses", lg.beam_losses)):
            if v is not None:
                rows.append((k, esc(v)))
        if lg.duration_s is not None:
            rows.append(("duration", esc(f"{lg.duration_s / 60:.1f} min")))
        if lg.tracker:
            rows.append(("tracker", esc(lg.tracker)))
        if lg.controller:
            rows.append(("controller", esc(lg.controller)))
        for label, unit, vals in weather_ranges(lg.weather):
            rng = (f"{min(vals):.1f}–{max(vals):.1f} {unit}" if len(vals) > 1
                   else f"{vals[0]:.1f} {unit}")
            rows.append((label, esc(rng).strip()))
        for k, v in lg.extra.items():
            rows.append((str(k), esc(v)))
        for n in lg.notes:
            rows.append(("note", esc(n)))
    fit_out = [o for o in an.outliers if o not in set(an.validation_glitches)]
    rows.append(("outliers rejected by the fit", esc(", ".join(fit_out) or "none")))
    if an.inp.validation is not None:
        rows.append((f"validation glitches (error > "
                     f"{an.inp.acceptance.validation_outlier_factor:g} × median)",
                     esc(", ".join(an.validation_glitches) or "none")))
    out.append("<h3>Measurement log</h3>" + _kv(rows))
    prov: list[tuple[str, Any]] = []
    for k, v in an.hashes.items():
        if k == "models":
            continue
        prov.append((k, f"<code>{esc(v)}</code>"))
    for name, d in an.hashes.get("models", {}).items():
        extra = ", ".join(f"{k}={v}" for k, v in d.get("data", {}).items()
                          if isinstance(v, str | int | float))
        prov.append((f"model {name}", f"<code>{esc(d['model_id'])}</code> ({esc(d['kind'])}, "
                     f"{esc(d['created'])}){' · ' + esc(extra) if extra else ''}"))
    for n in an.inp.notes:
        prov.append(("note", esc(n)))
    out.append("<h3>Provenance</h3>" + _kv(prov))
    out.append("</section>")
    return "\n".join(out)


def _footer(an: Analysis) -> str:
    return (f'<footer class="note" style="text-align:center;padding:16px">Generated by robocal '
            f"{esc(an.hashes.get('robocal', ''))} · units: mm and degrees · machine-readable "
            "summary in the .json file beside this page</footer>")
