"""HTML of the station's pages: server-rendered, escaped, no inline script or style.

Every page is a header, the controller banner, flash messages and a ``<main>``; the campaign
page's live parts sit in ``#live`` so ``station.js`` can swap them for a fresh rendering.
"""

from __future__ import annotations

import html
from typing import Any

from robocal.daemon.station._auth import Session
from robocal.daemon.station._facts import Progress, Step

__all__ = ["campaign_live", "campaign_page", "checks_box", "layout", "list_page", "list_rows",
           "login_page", "report_box"]


def e(x: object) -> str:
    """Escaped text."""
    return html.escape("" if x is None else str(x), quote=True)


def _mm(v: float | None, digits: int = 4) -> str:
    return "–" if v is None else f"{v:.{digits}f} mm"


def _when(iso: str | None) -> str:
    if not iso:
        return "–"
    return e(str(iso).replace("T", " ")[:19] + " UTC")


def _duration(s: float | None) -> str:
    if s is None:
        return "–"
    s = round(s)
    if s >= 3600:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    if s >= 60:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s} s"


def _measured(b: dict[str, Any]) -> str:
    """``; measured X mm before → Y mm after`` of the last write's verification run."""
    if b.get("before_mm") is not None and b.get("after_mm") is not None:
        return f"; measured {b['before_mm']:.4f} mm before → {b['after_mm']:.4f} mm after"
    if b.get("verification"):
        return f"; verification {e(b['verification'])}"
    return ""


def banner(b: dict[str, Any]) -> str:
    """The controller banner (``role="status"``: screen readers announce changes)."""
    if b["kind"] == "original":
        text = "Controller holds its <strong>original values</strong>"
        if b.get("rolled_back_at"):
            text += f", rolled back at {_when(b['rolled_back_at'])} by {e(b.get('by'))}"
            text += _measured(b)
        else:
            text += " (robocal has not changed them)"
        cls = "banner original"
    else:
        model = e(b.get("model") or "?")
        text = (f"Controller holds <strong>model {model}</strong> of campaign "
                f"<a href=\"/station/campaigns/{e(b['campaign'])}\">{e(b['campaign'])}</a>"
                f" ({e(b.get('table'))} table {e(str(b.get('checksum'))[:12])}), "
                f"{'pushed' if b.get('action') != 'rollback' else 'restored'} at "
                f"{_when(b.get('at'))} by {e(b.get('by'))}")
        text += _measured(b)
        cls = "banner pushed"
    return f'<div id="controller" class="{cls}" role="status">{text}</div>'


def layout(title: str, body: str, *, session: Session | None, banner_html: str = "",
           page: str = "", live: str = "") -> str:
    """A whole page."""
    who = ""
    if session is not None:
        who = (f'<span class="who">{e(session.name or "unnamed")} · {e(session.role)}</span>'
               f'<form method="post" action="/station/logout" class="inline">'
               f'<input type="hidden" name="csrf" value="{e(session.csrf)}">'
               f'<button type="submit" class="link">Sign out</button></form>')
    flash = ""
    if session is not None and session.flash:
        items = "".join(f'<p class="flash {e(kind)}" role="alert">{e(msg)}</p>'
                        for kind, msg in session.flash)
        session.flash.clear()
        flash = f'<div id="flash">{items}</div>'
    csrf = e(session.csrf) if session is not None else ""
    return (
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<meta name=\"csrf-token\" content=\"{csrf}\">"
        f"<title>{e(title)} · robocal station</title>"
        "<link rel=\"stylesheet\" href=\"/station/static/station.css\">"
        "<script src=\"/station/static/station.js\" defer></script></head>"
        f"<body data-page=\"{e(page)}\" data-live=\"{e(live)}\">"
        "<header class=\"top\"><a class=\"brand\" href=\"/station/\">robocal station</a>"
        f"<nav aria-label=\"main\"><a href=\"/station/\">Campaigns</a></nav>{who}</header>"
        f"<div id=\"bannerbox\">{banner_html}</div>{flash}"
        f"<main>{body}</main></body></html>\n")


def login_page(*, login_csrf: str, error: str = "", next_url: str = "/station/") -> str:
    """The sign-in form."""
    err = f'<p class="flash error" role="alert">{e(error)}</p>' if error else ""
    body = (
        "<h1>Sign in</h1>"
        "<p>Use the daemon's API token (operator: start, pause, approve, push, roll back) "
        "or the viewer token (read only). Ask whoever set up the cell PC; it is in the "
        "daemon's token file.</p>" + err +
        "<form method=\"post\" action=\"/station/login\" class=\"card narrow\">"
        f"<input type=\"hidden\" name=\"csrf\" value=\"{e(login_csrf)}\">"
        f"<input type=\"hidden\" name=\"next\" value=\"{e(next_url)}\">"
        "<label for=\"token\">Access token</label>"
        "<input id=\"token\" name=\"token\" type=\"password\" autocomplete=\"off\" required>"
        "<label for=\"name\">Your name (recorded in the audit log)</label>"
        "<input id=\"name\" name=\"name\" type=\"text\" maxlength=\"40\" "
        "autocomplete=\"username\">"
        "<button type=\"submit\">Sign in</button></form>")
    return layout("Sign in", body, session=None, page="login")


_BADGE = {"running": "run", "paused": "warn", "faulted": "bad", "aborted": "bad",
          "pushed": "ok", "approved": "ok", "fitted": "info", "measured": "info",
          "created": "info"}


def badge(state: str) -> str:
    return f'<span class="badge {_BADGE.get(state, "info")}">{e(state)}</span>'


def list_rows(rows: list[dict[str, Any]]) -> str:
    """The campaigns table body (``rows``: id, name, state, robot, created, measured, total,
    rms, active, rolled_back)."""
    if not rows:
        return '<tr><td colspan="7">No campaigns yet.</td></tr>'
    out = []
    for r in reversed(rows):
        comp = ('<span class="badge ok">active on controller</span>' if r["active"] else
                f"rolled back {_when(r['rolled_back'])}" if r["rolled_back"] else "–")
        out.append(
            f"<tr data-campaign=\"{e(r['id'])}\">"
            f"<td><a href=\"/station/campaigns/{e(r['id'])}\">{e(r['name'] or r['id'])}</a>"
            f"<br><small>{e(r['id'])}</small></td>"
            f"<td class=\"state\">{badge(r['state'])}</td><td>{e(r['robot'])}</td>"
            f"<td>{_when(r['created'])}</td>"
            f"<td class=\"num\">{r['measured']} / {r['total']}</td>"
            f"<td class=\"num rms\">{_mm(r['rms'])}</td><td class=\"comp\">{comp}</td></tr>")
    return "".join(out)


_VERDICT = {"pass": "ok", "warn": "warn", "fail": "bad"}
_ADVICE = {"none": "nothing to do", "reuse": "re-calibrate with --reuse",
           "full": "full calibration"}


def _check_forms(checks: list[dict[str, Any]], session: Session | None) -> str:
    """For an operator: run a check now; start the reuse refit the latest one recommends."""
    if session is None or session.role != "operator":
        return ""
    out = _form(session, "/station/checks/run", "Run a drift check now",
                "Run a drift check: the robot will move through the check's poses (from its "
                "home) and the tracker will measure each one.", button_id="run-check")
    last = checks[-1] if checks else {}
    if last.get("recommendation") == "reuse":
        out += _form(session, "/station/checks/recalibrate",
                     f"Re-calibrate with --reuse (check {last['id']})",
                     "Start the re-calibration with --reuse: the robot will move through the "
                     "poses of the checked model's campaign; approve and push its result as "
                     "any campaign's.",
                     inputs=f'<input type="hidden" name="check" value="{e(last["id"])}">',
                     button_id="recalibrate")
    return f'<div class="actions">{out}</div>'


def checks_box(checks: list[dict[str, Any]], *, session: Session | None = None) -> str:
    """The drift checks (ADR 0041): the latest with its verdict and recommendation, and the
    trend of the RMS over the last checks (oldest first in ``checks``); an operator's
    ``session`` gets the buttons of :func:`_check_forms`."""
    if not checks:
        return ("<section class=\"card\" id=\"checks\" aria-labelledby=\"checks-h\">"
                "<h2 id=\"checks-h\">Drift checks</h2><p>No check yet (<code>robocal check"
                "</code>, or the robocal-check.timer).</p>"
                f"{_check_forms(checks, session)}</section>")
    last = checks[-1]
    verdict = str(last.get("verdict") or last["state"])
    rec = (last.get("detail") or {}).get("recommendation") or {}
    advice = _ADVICE.get(str(last.get("recommendation")), "–")
    if rec.get("action") == "reuse":
        advice += f" ({rec.get('poses')} poses + {rec.get('validation_poses')} held out)"
    reasons = "; ".join((last.get("detail") or {}).get("reasons") or []) or \
        (last.get("detail") or {}).get("reason") or ""
    rows = "".join(
        f"<tr><td>{c['id']}</td><td>{_when(c['created'])}</td>"
        f"<td><span class=\"badge {_VERDICT.get(str(c.get('verdict')), 'info')}\">"
        f"{e(c.get('verdict') or c['state'])}</span></td>"
        f"<td class=\"num\">{_mm(c.get('rms_mm'))}</td><td class=\"num\">"
        f"{_mm(c.get('max_mm'))}</td><td>{e(c['model_campaign'])}</td></tr>"
        for c in reversed(checks[-10:]))
    return (
        "<section class=\"card\" id=\"checks\" aria-labelledby=\"checks-h\">"
        "<h2 id=\"checks-h\">Drift checks</h2>"
        f"<p class=\"latest\">Latest check {last['id']} ({_when(last['created'])}): "
        f"<span class=\"badge {_VERDICT.get(verdict, 'info')}\">{e(verdict)}</span> RMS "
        f"{_mm(last.get('rms_mm'))}, max {_mm(last.get('max_mm'))}; "
        f"recommendation: <strong>{e(advice)}</strong>"
        f"{'. ' + e(reasons) if reasons else ''}</p>"
        "<p class=\"trend\">Trend (RMS, oldest first): "
        + " → ".join(_mm(c.get("rms_mm")) for c in checks[-10:]) + "</p>"
        "<table class=\"checks\"><thead><tr><th scope=\"col\">Check</th>"
        "<th scope=\"col\">When</th><th scope=\"col\">Verdict</th><th scope=\"col\">RMS"
        "</th><th scope=\"col\">Max</th><th scope=\"col\">Model of campaign</th></tr>"
        f"</thead><tbody>{rows}</tbody></table>{_check_forms(checks, session)}</section>")


def list_page(rows: list[dict[str, Any]], *, session: Session, banner_html: str,
              checks_html: str = "") -> str:
    """The campaigns list with, for an operator, the form that starts a campaign, and the
    drift checks (``checks_html``, :func:`checks_box`)."""
    start = ""
    if session.role == "operator":
        start = (
            "<section class=\"card\" aria-labelledby=\"new-h\"><h2 id=\"new-h\">"
            "Start a campaign</h2>"
            "<form method=\"post\" action=\"/station/campaigns\" data-confirm=\"Start the "
            "campaign: the robot will move through every pose of the plan file {plan} and "
            "the tracker will measure each one.\">"
            f"<input type=\"hidden\" name=\"csrf\" value=\"{e(session.csrf)}\">"
            "<label for=\"plan\">Plan file on this cell PC (PLAN.json)</label>"
            "<input id=\"plan\" name=\"plan\" type=\"text\" required "
            "placeholder=\"full path, e.g. /srv/robocal/plans/PLAN.json\">"
            "<label for=\"cname\">Campaign name (optional)</label>"
            "<input id=\"cname\" name=\"name\" type=\"text\" maxlength=\"200\">"
            "<button type=\"submit\" id=\"start\">Start campaign</button></form></section>")
    else:
        start = '<p class="note">Signed in as viewer: read only.</p>'
    body = (
        "<h1>Campaigns</h1>" + start + checks_html +
        "<section aria-labelledby=\"list-h\"><h2 id=\"list-h\">All campaigns</h2>"
        "<table class=\"campaigns\"><thead><tr><th scope=\"col\">Campaign</th>"
        "<th scope=\"col\">State</th><th scope=\"col\">Robot</th><th scope=\"col\">Created</th>"
        "<th scope=\"col\">Poses</th><th scope=\"col\">Held-out RMS</th>"
        "<th scope=\"col\">Compensation</th></tr></thead>"
        f"<tbody id=\"live\">{list_rows(rows)}</tbody></table></section>")
    return layout("Campaigns", body, session=session, banner_html=banner_html, page="list",
                  live="/station/?fragment=live")


def _form(session: Session, action: str, label: str, confirm: str, *, inputs: str = "",
          danger: bool = False, button_id: str = "") -> str:
    cls = ' class="danger"' if danger else ""
    bid = f' id="{e(button_id)}"' if button_id else ""
    return (f"<form method=\"post\" action=\"{e(action)}\" data-confirm=\"{e(confirm)}\">"
            f"<input type=\"hidden\" name=\"csrf\" value=\"{e(session.csrf)}\">{inputs}"
            f"<button type=\"submit\"{cls}{bid}>{e(label)}</button></form>")


def actions(st: dict[str, Any], session: Session, *, active_here: bool, verify_count: int,
            models: list[str]) -> str:
    """The buttons that fit the campaign's state, each confirming what the robot will do."""
    if session.role != "operator":
        return '<p class="note">Signed in as viewer: read only.</p>'
    cid, state = st["id"], st["state"]
    base = f"/station/campaigns/{cid}"
    left = st["poses_total"] - st["poses_measured"]
    out = []
    if state == "created":
        out.append(_form(session, f"{base}/start", "Start measuring",
                         f"Start: the robot will move through {st['poses_total']} poses and "
                         "the tracker will measure each.", button_id="act-start"))
    if state == "running":
        out.append(_form(session, f"{base}/pause", "Pause",
                         "Pause: the robot stops after the pose it is measuring and waits.",
                         inputs="<label for=\"pause-reason\">Reason for pausing</label>"
                                "<input id=\"pause-reason\" name=\"reason\" type=\"text\" "
                                "maxlength=\"1000\">", button_id="act-pause"))
    if state == "paused":
        out.append(_form(session, f"{base}/resume", "Resume",
                         f"Resume: the robot will move again and measure the {left} poses "
                         "left.", button_id="act-resume"))
    if state in ("created", "running", "paused", "measured", "fitted"):
        out.append(_form(session, f"{base}/abort", "Abort",
                         "Abort: the robot stops now and this campaign ends for good "
                         "(its measurements are kept).",
                         inputs="<label for=\"abort-reason\">Reason for aborting</label>"
                                "<input id=\"abort-reason\" name=\"reason\" type=\"text\" "
                                "maxlength=\"1000\">", danger=True, button_id="act-abort"))
    if state == "fitted" and models:
        chosen = st.get("selected_model")
        opts = "".join(f"<option value=\"{e(m)}\"{' selected' if m == chosen else ''}>"
                       f"{e(m)}</option>" for m in models)
        out.append(_form(session, f"{base}/approve", "Approve model",
                         "Approve model {model}: nothing moves and the controller is not "
                         "changed; it allows pushing this model to the controller.",
                         inputs=f"<label for=\"model\">Model to approve</label>"
                                f"<select id=\"model\" name=\"model\">{opts}</select>",
                         button_id="act-approve"))
    if state == "approved":
        out.append(_form(session, f"{base}/push", "Push to controller",
                         f"Push model {st.get('selected_model')}: the controller's "
                         "compensation is overwritten with this campaign's table, then the "
                         f"robot moves to {verify_count} verification poses to measure the "
                         "result.", button_id="act-push"))
    if active_here:
        out.append(_form(session, f"{base}/rollback", "Roll back",
                         "Roll back: the controller's compensation returns to what it held "
                         "before this push, then the robot moves to the verification poses "
                         "to measure the result.",
                         inputs="<label for=\"rb-reason\">Reason for rolling back</label>"
                                "<input id=\"rb-reason\" name=\"reason\" type=\"text\" "
                                "maxlength=\"1000\">", danger=True, button_id="act-rollback"))
    if not out:
        return '<p class="note">No action fits this state.</p>'
    return "".join(f'<div class="action">{f}</div>' for f in out)


def _fits(st: dict[str, Any]) -> str:
    fits = st.get("fits") or {}
    if not fits:
        return ""
    rows = []
    for name, f in fits.items():
        train = (f.get("train") or {}).get("rms_mm") if isinstance(f.get("train"), dict) \
            else None
        val = (f.get("validation") or {}).get("rms_mm") \
            if isinstance(f.get("validation"), dict) else None
        sel = " (proposed)" if name == st.get("selected_model") else ""
        rows.append(f"<tr><th scope=\"row\">{e(name)}{sel}</th>"
                    f"<td class=\"num\">{_mm(train)}</td><td class=\"num\">{_mm(val)}</td>"
                    f"<td>{e(f.get('error') or '')}</td></tr>")
    return ("<section class=\"card\" aria-labelledby=\"fits-h\"><h2 id=\"fits-h\">Models</h2>"
            "<table><thead><tr><th scope=\"col\">Model</th><th scope=\"col\">Training RMS</th>"
            "<th scope=\"col\">Held-out RMS</th><th scope=\"col\">Note</th></tr></thead>"
            f"<tbody>{''.join(rows)}</tbody></table></section>")


def campaign_live(st: dict[str, Any], *, session: Session, steps: list[Step], prog: Progress,
                  fitting: bool, fit_since: str | None, active_here: bool,
                  rolled_back: str | None, verify_count: int, models: list[str],
                  has_report: bool) -> str:
    """The parts of the campaign page that change: steps, progress, fits, actions."""
    current = ' aria-current="step"'
    bar = "".join(
        f"<li class=\"step {s.status}\"{current if s.status == 'current' else ''}>"
        f"{e(s.name)}</li>" for s in steps)
    state = st["state"]
    reason = st.get("reason") or ""
    if state == "paused":
        why = (f"<p class=\"paused\" id=\"pause-reason-text\">Paused: "
               f"{e(reason or 'no reason given')}</p>")
    elif state in ("faulted", "aborted"):
        why = f"<p class=\"flash error\">{e(state.capitalize())}: {e(reason)}</p>"
    else:
        why = ""
    fit = ""
    if fitting:
        fit = (f"<p id=\"fitting\" class=\"note\">Fitting the models since {_when(fit_since)}"
               " (this takes up to a minute).</p>")
    push = st.get("push") or {}
    pushed = ""
    if push:
        v = push.get("verification") or "not measured"
        before, after = push.get("measured_before_rms_mm"), push.get("measured_after_rms_mm")
        measured = (f"measured {before:.4f} mm before → {after:.4f} mm after "
                    f"({push.get('measured_n')} poses)" if before is not None and after is not None
                    else f"verification: {e(v)}")
        temps = push.get("temperatures_c")
        warm = (f"; compensated for joint temperatures "
                f"{e(', '.join(f'{t:.1f}' for t in temps))} °C" if temps else "")
        pushed = (f"<p id=\"push-summary\">Pushed model {e(push.get('model'))} at "
                  f"{_when(push.get('at'))} by {e(push.get('actor'))}{warm}; {measured}.</p>")
    if rolled_back:
        pushed += f"<p id=\"rolled-back\">Rolled back at {_when(rolled_back)}.</p>"
    report = ""
    if _rendering(st):
        report = "<p id=\"report-rendering\">Report rendering…</p>"
    elif has_report:
        report = (f"<p><a href=\"/campaigns/{e(st['id'])}/report\" target=\"_blank\" "
                  "rel=\"noopener\">Open the report in a new tab</a></p>")
    pct = 0 if not st["poses_total"] else round(100 * prog.measured / prog.total)
    return (
        f"<div id=\"live-state\" data-state=\"{e(state)}\" data-measured=\"{prog.measured}\">"
        f"<ol class=\"steps\" aria-label=\"campaign steps\">{bar}</ol>{why}"
        "<section class=\"card\" aria-labelledby=\"prog-h\"><h2 id=\"prog-h\">Progress</h2>"
        f"<progress id=\"bar\" max=\"{max(prog.total, 1)}\" value=\"{prog.measured}\" "
        f"aria-label=\"poses measured\">{pct} %</progress>"
        "<dl class=\"facts\">"
        f"<dt>State</dt><dd id=\"state\">{badge(state)}</dd>"
        f"<dt>Poses measured</dt><dd id=\"measured\">{prog.measured} / {prog.total}</dd>"
        f"<dt>Rate</dt><dd id=\"rate\">"
        f"{'–' if prog.rate_per_min is None else f'{prog.rate_per_min:.1f} poses/min'}</dd>"
        f"<dt>Time left</dt><dd id=\"eta\">{_duration(prog.eta_s)}</dd>"
        f"<dt>Retries</dt><dd id=\"retries\">{prog.retries}</dd>"
        f"<dt>Beam losses</dt><dd id=\"losses\">{prog.beam_losses}</dd></dl>"
        f"{fit}{pushed}{report}</section>{_fits(st)}"
        "<section class=\"card\" aria-labelledby=\"act-h\"><h2 id=\"act-h\">Actions</h2>"
        f"<div id=\"actions\" data-key=\"{e(state)}-{int(active_here)}\">"
        f"{actions(st, session, active_here=active_here, verify_count=verify_count, models=models)}"
        "</div></section></div>")


def _rendering(st: dict[str, Any]) -> bool:
    """Whether the campaign's report is being rendered after its fit."""
    return (st.get("report") or {}).get("state") == "rendering"


def report_box(cid: str, has_report: bool, *, rendering: bool = False) -> str:
    """The embedded report (a note while it renders after the fit, empty before)."""
    if rendering:
        return ("<section class=\"card\" data-rendering=\"1\" aria-labelledby=\"rep-h\">"
                "<h2 id=\"rep-h\">Report</h2><p class=\"muted\">Report rendering: the fit is "
                "stored; the report appears here when its figures are drawn.</p></section>")
    if not has_report:
        return ""
    return ("<section class=\"card\" aria-labelledby=\"rep-h\"><h2 id=\"rep-h\">Report"
            "</h2><iframe class=\"report\" title=\"calibration report\" "
            f"src=\"/campaigns/{e(cid)}/report\"></iframe></section>")


def campaign_page(st: dict[str, Any], live_html: str, *, session: Session, banner_html: str,
                  has_report: bool) -> str:
    """The campaign page: head, ``#live`` (steps, progress, fits, actions), plot, report."""
    cid = st["id"]
    report = (f"<div id=\"reportbox\">"
              f"{report_box(cid, has_report, rendering=_rendering(st))}</div>")
    body = (
        f"<h1>{e(st.get('name') or cid)} <small>{e(cid)} · {e(st['robot'])}</small></h1>"
        f"<div id=\"live\">{live_html}</div>"
        "<section class=\"card\" aria-labelledby=\"plot-h\"><h2 id=\"plot-h\">Residual per "
        "measured pose</h2><p class=\"note\" id=\"plot-note\">While measuring: the spread "
        "of the tracker's samples at each pose; once fitted: the distance between measured "
        "and predicted position, per model.</p>"
        f"<div id=\"plot\" data-points=\"/station/campaigns/{e(cid)}/points\" role=\"img\" "
        "aria-labelledby=\"plot-h\"></div></section>" + report)
    return layout(st.get("name") or cid, body, session=session, banner_html=banner_html,
                  page="campaign", live=f"/station/campaigns/{cid}?fragment=live")
