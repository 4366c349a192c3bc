"""``robocal campaign ...``: drive campaigns on a running daemon.

Contract for scripts::

    robocal campaign start --plan PLAN.json [--json]   # prints the campaign id (or JSON)
    robocal campaign status ID --json                  # state, poses_total, poses_measured, ...
    robocal campaign pause|resume|abort|approve ID [--json]
    robocal campaign push ID [--json] [--no-wait]      # waits for the re-measurement
    robocal campaign list --json
    robocal campaign watch ID [--json]                 # progress bar, or JSON lines

The daemon is found with ``--config FILE``, ``--socket PATH`` or ``--url URL``
(+ ``--token-file`` or ``$ROBOCAL_TOKEN``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from robocal.cli._command import command
from robocal.cli._remeasure import add_wait_options, remeasured_text, wait_remeasured


def add_client_options(p: argparse.ArgumentParser) -> None:
    """Options locating the daemon."""
    g = p.add_argument_group("daemon")
    g.add_argument("--config", type=Path, help="the daemon's configuration file")
    g.add_argument("--socket", type=Path, help="the daemon's Unix socket")
    g.add_argument("--url", help="the daemon's TCP API, http://host:port")
    g.add_argument("--token-file", type=Path, help="file holding the TCP bearer token "
                                                   "(or set ROBOCAL_TOKEN)")
    g.add_argument("--timeout", type=float, default=60.0, help="request timeout, seconds")
    g.add_argument("--wait-for-daemon", type=float, default=0.0, metavar="SECONDS",
                   help="keep trying this long while the daemon is not listening yet (a "
                        "daemon just started)")


def client(args: argparse.Namespace) -> Any:
    """A :class:`~robocal.daemon.client.DaemonClient` from the parsed options."""
    from robocal.daemon.client import DaemonClient

    c = DaemonClient.from_args(config=args.config, socket_path=args.socket, url=args.url,
                               token_file=args.token_file, timeout=args.timeout)
    c.wait_s = max(0.0, float(getattr(args, "wait_for_daemon", 0.0) or 0.0))
    return c


def emit(obj: Any) -> None:
    """Write JSON to stdout."""
    sys.stdout.write(json.dumps(obj, indent=1, default=str) + "\n")


def answer(args: argparse.Namespace, obj: Any, lines: Iterable[str]) -> int:
    """``obj`` as JSON with ``--json``, else the (lazily made) ``lines``; exit code 0."""
    if args.json:
        emit(obj)
    else:
        sys.stdout.writelines(f"{line}\n" for line in lines)
    return 0


def register(sub: Any) -> None:
    """Add the ``campaign`` subcommand and its verbs."""
    p = command(sub, "campaign", None)
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)

    s = command(verbs, "start", start, parent="campaign")
    s.add_argument("--plan", required=True, type=Path, help="PLAN.json")
    s.add_argument("--name", help="a label for the campaign")
    s.add_argument("--json", action="store_true", help="print the status as JSON")
    _on_one(verbs, "status", status, "print the status as JSON")
    command(verbs, "list", list_, parent="campaign").add_argument(
        "--json", action="store_true", help="print the list as JSON")
    for verb in ("pause", "resume", "abort", "approve", "push"):
        a = _on_one(verbs, verb, action, "print the campaign's status afterwards as JSON",
                    action=verb)
        if verb in ("pause", "abort"):
            a.add_argument("--reason", default="",
                           help="why (kept in the campaign history and the audit log)")
        if verb == "approve":
            a.add_argument("--model", help="approve this fitted model instead of the proposed")
        if verb == "push":
            a.add_argument("--force", action="store_true",
                           help="push even if the table does not clearly improve on the "
                                "nominal residual, the controller's own calibration changed "
                                "since the campaign, or a vendor absolute-accuracy option is "
                                "active (recorded in the audit log)")
            a.add_argument("--reason", default="", help="why (kept in the audit log)")
            a.add_argument("--key", help="idempotency key: a retry with the same key never "
                                         "writes the controller twice")
            add_wait_options(a)
    _on_one(verbs, "events", events, "print the entries as JSON")
    w = _on_one(verbs, "watch", watch, "JSON lines instead of a progress bar")
    w.add_argument("--exit-on-pause", action="store_true",
                   help="exit 3 when the campaign is (or becomes) paused instead of waiting "
                        "for the resume")
    for parser in verbs.choices.values():  # last: the daemon group after the verb's own
        add_client_options(parser)


def _on_one(verbs: Any, name: str, run: Any, json_help: str, **defaults: Any
            ) -> argparse.ArgumentParser:
    """A verb acting on one campaign: its ``id`` and a ``--json`` flag."""
    a = command(verbs, name, run, parent="campaign", **defaults)
    a.add_argument("id", help="campaign id (see campaign list)")
    a.add_argument("--json", action="store_true", help=json_help)
    return a


def _read_plan(path: Path) -> Any:
    from robocal._core.files import read_text
    from robocal.errors import ConfigError

    try:
        return json.loads(read_text(path))
    except json.JSONDecodeError as err:
        raise ConfigError(f"not valid JSON: {err}", source=str(path)) from err


def start(args: argparse.Namespace) -> int:
    """Create and start; print the id (or the status as JSON)."""
    body: dict[str, Any] = {"plan": _read_plan(args.plan)}
    if args.name:
        body["name"] = args.name
    out = client(args).request("POST", "/campaigns", body)
    if args.json:
        emit(out)
    else:
        sys.stdout.write(f"{out['id']}\n")
    return 0


def _state_text(s: dict[str, Any]) -> str:
    """The campaign's state; a pushed one with its push's key (the one id of a push) and
    where its table is now (the daemon's ``compensation_state``: active, superseded, rolled
    back)."""
    where, key = s.get("compensation_state"), s.get("push_key")
    return f"{s['state']} (push {key}: {where})" if where and key else str(s["state"])


def _now_text(p: dict[str, Any]) -> str:
    """Where a push's table is now, with what made it so (a campaign status's ``push``)."""
    where = p.get("compensation_state")
    if where == "superseded":
        return f"superseded by push {p.get('superseded_by')} (a rollback brings it back)"
    if where == "rolled back":
        return f"rolled back at {p.get('rolled_back_at')} by rollback {p.get('rolled_back_by')}"
    return "active on the controller" if where == "active" else str(where)


def _describe(s: dict[str, Any]) -> str:
    lines = [f"campaign {s['id']}  {s.get('name', '')}",
             f"  state     {_state_text(s)}" + (f"  ({s['reason']})" if s.get("reason") else ""),
             f"  poses     {s['poses_measured']}/{s['poses_total']} measured",
             *_fitting_line(s),
             f"  robot     {s.get('robot', '')}",
             f"  created   {s.get('created', '')} by {s.get('created_by', '')}"]
    cal = s.get("controller_calibration")
    if cal:
        lines.append(_describe_calibration(cal))
    fits = s.get("fits") or {}
    if fits:
        lines.append("  fits      model        held-out RMS   % described")
        for name, f in fits.items():
            v = f.get("validation") or f.get("train") or {}
            rms = v.get("rms_mm")
            pct = v.get("percent_described_rms")
            err = f.get("error")
            mark = " *" if name == s.get("selected_model") else ""
            if err:
                lines.append(f"            {name:12s} failed: {err}")
            else:
                r = f"{rms:.4f} mm" if isinstance(rms, int | float) else "-"
                pc = f"{pct:.1f} %" if isinstance(pct, int | float) else "-"
                lines.append(f"            {name:12s} {r:>13s} {pc:>11s}{mark}")
    report = _report_path(s)
    if (s.get("report") or {}).get("state") == "rendering":
        lines.append("  report    rendering (after the fit)")
    elif report is not None:
        lines.append(f"  report    {report}")
    p = s.get("push") or {}
    if p:
        lines.append(f"  push      {p.get('key')}  model {p.get('model')}, {p.get('kind')} "
                     f"table {str(p.get('checksum', ''))[:12]}, at {p.get('at', '')} by "
                     f"{p.get('actor', '')}" + ("  (forced)" if p.get("forced") else ""))
        lines.append(f"  now       {_now_text(p)}")
        before, after = p.get("measured_before_rms_mm"), p.get("measured_after_rms_mm")
        if isinstance(before, int | float) and isinstance(after, int | float):
            lines.append(f"  measured  {before:.4f} mm before -> {after:.4f} mm after "
                         f"({p.get('measured_n')} pushed targets re-measured)")
        elif p.get("verification"):
            lines.append(f"  measured  verification {p['verification']}")
    return "\n".join(lines) + "\n"


def _fitting_line(s: dict[str, Any]) -> list[str]:
    """``fitting   constant, high-order ... (running 12 s)`` while the daemon fits."""
    f = s.get("fitting")
    if not isinstance(f, dict):
        return []
    return [f"  fitting   {', '.join(str(m) for m in f.get('models', []))} (running "
            f"{_clock(float(f.get('elapsed_s') or 0.0))}, since {f.get('started', '')}); "
            "approve when it ends"]


def _describe_calibration(cal: dict[str, Any]) -> str:
    """The controller's own calibration recorded at campaign start, in one line."""
    if cal.get("state") != "read":
        return f"  controller calibration unavailable ({cal.get('reason', '')})"
    aa = {True: "vendor absolute accuracy ON", False: "no vendor absolute accuracy",
          None: "absolute accuracy not shown"}[cal.get("absolute_accuracy")]
    return f"  controller calibration {cal.get('fingerprint')} ({cal.get('source')}; {aa})"


def _report_path(s: dict[str, Any]) -> Path | None:
    """The campaign's HTML report, when the daemon has written one (same machine)."""
    if not s.get("files"):
        return None
    path = Path(str(s["files"])) / "report.html"
    return path if path.exists() else None


def _held_out_rms(s: dict[str, Any], model: str | None) -> str:
    f = (s.get("fits") or {}).get(model or "") or {}
    v = f.get("validation") or f.get("train") or {}
    rms = v.get("rms_mm")
    return f"{rms:.4f} mm" if isinstance(rms, int | float) else "-"


def status(args: argparse.Namespace) -> int:
    """Print one campaign."""
    out = client(args).request("GET", f"/campaigns/{args.id}")
    if args.json:
        emit(out)
    else:
        sys.stdout.write(_describe(out))
    return 0


def events(args: argparse.Namespace) -> int:
    """Print a campaign's state changes and audit entries, oldest first."""
    c = client(args)
    s = c.request("GET", f"/campaigns/{args.id}")
    entries: list[dict[str, Any]] = [
        {"at": t["at"], "kind": "state", "actor": t["actor"],
         "what": f"{t.get('from_state') or '-'} -> {t['to_state']}", "detail": t["reason"]}
        for t in s.get("transitions", [])]
    for a in c.request("GET", "/audit", query={"limit": 100_000}):
        if a.get("campaign") == args.id:
            detail = a.get("detail") or {}
            text = ", ".join(f"{k} {v}" for k, v in detail.items()
                             if isinstance(v, str | int | float) and not isinstance(v, bool))
            entries.append({"at": a["at"], "kind": "audit", "actor": a["actor"],
                            "what": a["action"], "detail": text})
    entries.sort(key=lambda e: str(e["at"]))
    return answer(args, entries, (f"{e['at']}  {e['kind']:5s} {e['what']:28s} "
                                  f"{e['actor']:16s} {e['detail']}" for e in entries))


def list_(args: argparse.Namespace) -> int:
    """Print every campaign."""
    out = client(args).request("GET", "/campaigns")
    width = max([9, *(len(_state_text(c)) for c in out)])
    return answer(args, out, (f"{c['id']}  {_state_text(c):{width}s} {c['poses_measured']:5d}/"
                              f"{c['poses_total']:<5d} {c['created']}  {c['name']}"
                              for c in out))


def action(args: argparse.Namespace) -> int:
    """pause / resume / abort / approve / push."""
    body: dict[str, Any] = {}
    if getattr(args, "reason", ""):
        body["reason"] = args.reason
    if getattr(args, "model", None):
        body["model"] = args.model
    if getattr(args, "force", False):
        body["force"] = True
    if getattr(args, "key", None):
        body["key"] = args.key
    cli = client(args)
    out = cli.request("POST", f"/campaigns/{args.id}/{args.action}", body or None)
    measured = None
    if args.action == "push" and not args.no_wait and out.get("push"):
        v = wait_remeasured(cli, out["push"]["key"], timeout=args.wait_timeout)
        measured = remeasured_text(v)
        out = cli.request("GET", f"/campaigns/{args.id}")
    if args.json:
        emit(out)
        return 0
    text = f"{out['id']}: {out['state']}"
    if args.action == "approve":
        model = out.get("selected_model")
        text += f"; approved model {model} (held-out RMS {_held_out_rms(out, model)})"
    elif args.action == "push":
        text += _push_text(out)
        if measured is not None:
            text += "\n" + measured
    sys.stdout.write(text + "\n")
    return 0


def _push_text(s: dict[str, Any]) -> str:
    """What was pushed, from the campaign status after a push."""
    p = s.get("push") or {}
    if not p:
        return f"; model {s.get('selected_model')} pushed"
    parts = [f"as push {p.get('key')}", f"model {p.get('model', s.get('selected_model'))}",
             f"kind {p.get('kind')}"]
    if p.get("checksum"):
        parts.append(f"table checksum {str(p['checksum'])[:12]}")
    for key, label in (("predicted_rms_mm", "solved to"),
                       ("model_accuracy_mm", "model held-out RMS"),
                       ("nominal_rms_mm", "uncompensated (predicted)"),
                       ("measured_before_rms_mm", "measured before"),
                       ("measured_after_rms_mm", "measured after")):
        v = p.get(key)
        if isinstance(v, int | float):
            parts.append(f"{label} {v:.4f} mm")
    if isinstance(p.get("verification"), str) and p.get("measured_after_rms_mm") is None:
        parts.append(f"verification {p['verification']} (robocal campaign status shows the "
                     "measured result)")
    return "; pushed " + ", ".join(parts)


#: Exit codes of ``campaign watch``: goal reached, failed (fault/abort), waiting (paused).
WATCH_DONE, WATCH_FAILED, WATCH_PAUSED = 0, 1, 3


def _epoch(iso: str) -> float | None:
    """Seconds since the epoch of an ISO 8601 time, None when unreadable."""
    from datetime import datetime

    try:
        return datetime.fromisoformat(iso).timestamp()
    except (TypeError, ValueError):
        return None


class _Progress:
    """What ``campaign watch`` shows: counts, timing, retries, the fitting phase.

    Times come from the campaign's state history, so a watch started after a pause or a
    daemon restart shows the campaign's elapsed time (since it first ran) and a rate over
    the time spent measuring only (not paused, not fitting).
    """

    def __init__(self, status: dict[str, Any], *, now: float | None = None) -> None:
        now = time.time() if now is None else now
        self.measured = int(status["poses_measured"])
        self.total = int(status["poses_total"])
        self.state = str(status["state"])
        self.retries = 0
        self.beam_losses = 0
        self.phase = ""
        self.started: float | None = None        # first time it ran (epoch s)
        self.measuring_s = 0.0                   # closed running intervals
        self.running_since: float | None = None  # open running interval
        for t in status.get("transitions") or []:
            at = _epoch(str(t.get("at", "")))
            if at is None:
                continue
            self._leave_running(at)
            if t.get("to_state") == "running":
                self.started = at if self.started is None else self.started
                self.running_since = at
        self.fit_since: float | None = None
        fitting = status.get("fitting")
        if isinstance(fitting, dict):
            self.fit_since = now - float(fitting.get("elapsed_s") or 0.0)
            self.phase = "fitting " + ", ".join(str(m) for m in fitting.get("models", []))

    def _leave_running(self, at: float) -> None:
        if self.running_since is not None:
            self.measuring_s += max(0.0, at - self.running_since)
            self.running_since = None

    def update(self, ev: dict[str, Any], *, now: float | None = None) -> None:
        """Fold one event into the display state."""
        now = time.time() if now is None else now
        kind = ev.get("kind")
        if "poses_measured" in ev:
            self.measured = int(ev["poses_measured"])
            self.total = int(ev.get("poses_total", self.total))
        if kind == "state":
            self.state = str(ev.get("state"))
            self._leave_running(now)
            if self.fit_since is not None and self.state != "measured":
                # the state event can come before the fit's own "done" event
                self.phase = f"fit took {_clock(now - self.fit_since)}"
                self.fit_since = None
            if self.state == "running":
                self.started = now if self.started is None else self.started
                self.running_since = now
        elif kind == "retry":
            self.retries += 1
            if str(ev.get("problem", "")).startswith("BeamLost"):
                self.beam_losses += 1
        elif kind == "warmup":
            rate = ev.get("rate_c_per_min")
            self.phase = ("warmed up" if ev.get("phase") == "done" else "warming up") + (
                f" {_clock(float(ev.get('elapsed_s') or 0.0))}"
                + ("" if rate is None else f", {float(rate):.3f} degC/min"))
        elif kind == "fit":
            phase = ev.get("phase")
            if phase == "started":
                self.phase = "fitting " + ", ".join(str(m) for m in ev.get("models", []))
                self.fit_since = now
            elif phase == "done":
                self.phase = f"fitted; proposed {ev.get('selected')}"
                self.fit_since = None
            elif phase == "failed":
                self.phase = "fit failed"
                self.fit_since = None

    def line(self, width: int = 30, *, now: float | None = None) -> str:
        """One progress line: bar, counts, elapsed, rate, ETA (while running), retries, beam
        losses, the fit."""
        now = time.time() if now is None else now
        frac = self.measured / self.total if self.total else 0.0
        filled = round(frac * width)
        elapsed = now - self.started if self.started is not None else 0.0
        measuring = self.measuring_s + (now - self.running_since
                                        if self.running_since is not None else 0.0)
        rate = self.measured / measuring if measuring > 0 and self.measured > 0 else 0.0
        left = self.total - self.measured
        text = (f"[{'#' * filled}{'.' * (width - filled)}] {self.measured}/{self.total} "
                f"{self.state} {_clock(elapsed)} elapsed, {rate * 60:.1f} poses/min")
        if self.state == "running":
            text += f", ETA {_clock(left / rate) if rate > 0 and left > 0 else '--:--'}"
        text += f", {self.retries} retries, {self.beam_losses} beam losses"
        if self.phase.startswith("warming") and self.state == "running":
            text += f" | {self.phase}"
        elif self.phase and self.state in ("measured", "faulted", "fitted"):
            text += f" | {self.phase}"
            if self.fit_since is not None:
                text += f" {_clock(now - self.fit_since)}"
        return text


def _terminal_line(prog: _Progress) -> str:
    """The progress line for a terminal: overwritten in place, never wider than it."""
    import shutil

    columns = shutil.get_terminal_size((80, 24)).columns
    text = prog.line(width=12)
    if len(text) > columns - 1:
        text = text[:max(1, columns - 2)] + "~"
    return "\r\033[K" + text


_MAX_RECONNECTS = 100


def _clock(seconds: float) -> str:
    s = round(seconds)
    if s >= 3600:
        return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
    return f"{s // 60}:{s % 60:02d}"


def _following(state: str, measure_only: bool, exit_on_pause: bool = True) -> bool:
    """True while the watch keeps following: the daemon works on the campaign by itself,
    or it is paused and the watch waits for the resume (unless ``exit_on_pause``)."""
    from robocal.daemon.campaign import ACTIVE, CampaignState

    if state == CampaignState.MEASURED and measure_only:
        return False
    if state == CampaignState.PAUSED:
        return not exit_on_pause
    return state == CampaignState.CREATED or state in ACTIVE


def _exit_code(state: str, measure_only: bool) -> int:
    from robocal.daemon.campaign import CampaignState as S

    if state in (S.FAULTED, S.ABORTED):
        return WATCH_FAILED
    if state == S.PAUSED:
        return WATCH_PAUSED
    if state in (S.FITTED, S.APPROVED, S.PUSHED) or (state == S.MEASURED and measure_only):
        return WATCH_DONE
    return WATCH_PAUSED


def _summary(s: dict[str, Any], config: Path | None) -> str:
    """The closing lines: the state with its reason, RMS per model, report, next command."""
    state, cid = s["state"], s["id"]
    lines = [f"{cid}: {_state_text(s)}" + (f": {s['reason']}" if s.get("reason") else "")]
    fits = s.get("fits") or {}
    parts = []
    for name, f in fits.items():
        v = f.get("validation") or f.get("train") or {}
        rms = v.get("rms_mm")
        if isinstance(rms, int | float):
            parts.append(f"{name} {rms:.4f} mm")
    if parts:
        lines.append("held-out RMS: " + ", ".join(parts)
                     + (f"; proposed: {s['selected_model']}" if s.get("selected_model") else ""))
    report = _report_path(s)
    if (s.get("report") or {}).get("state") == "rendering":
        lines.append("report: rendering (after the fit)")
    elif report is not None:
        lines.append(f"report: {report}")
    cfg = f" --config {config}" if config else ""
    nxt = {"fitted": f"robocal campaign approve{cfg} {cid}   (after reading the report)",
           "approved": f"robocal campaign push{cfg} {cid}",
           "paused": f"robocal campaign resume{cfg} {cid}",
           "faulted": f"robocal campaign resume{cfg} {cid}   (once the cause is fixed)"}
    if state in nxt:
        lines.append("next: " + nxt[state])
    return "\n".join(lines) + "\n"


#: Longest a watch that reached ``fitted`` waits for the fit's report (it renders after the fit
#: is stored, ADR 0048), so that its summary names the report the operator reads next.
REPORT_WAIT_S = 120.0


def _with_report(c: Any, cid: str, after: int) -> dict[str, Any]:
    """The campaign's status, once the report of its fit is no longer rendering (or after
    :data:`REPORT_WAIT_S`): waits on ``report`` events by long-polling from ``after``."""
    deadline = time.monotonic() + REPORT_WAIT_S
    s: dict[str, Any] = c.request("GET", f"/campaigns/{cid}")
    while (s.get("report") or {}).get("state") == "rendering" and time.monotonic() < deadline:
        left = max(1, min(10, int(deadline - time.monotonic())))
        got = c.request("GET", f"/events/poll?after={after}&timeout={left}&campaign={cid}")
        after = max([after, *(int(ev.get("seq", after)) for ev in got["events"])])
        s = c.request("GET", f"/campaigns/{cid}")
    return s


def watch(args: argparse.Namespace) -> int:
    """Follow the campaign's current run until the daemon needs the operator.

    Exit code 0 when the campaign got where it was going (fitted, approved, pushed, or a
    measure-only run measured), 1 when it faulted or was aborted (the reason is printed), 3
    when it is paused and ``--exit-on-pause`` was given (else it waits for the resume).
    """
    from robocal.daemon.client import DaemonUnavailable

    c = client(args)
    # Only events after this point belong to the run being watched: older ones (a fault before
    # a resume, say) are history and must not end the watch.
    after = int(c.request("GET", f"/events/poll?after={2**62}&timeout=0")["last_seq"])
    s = c.request("GET", f"/campaigns/{args.id}")
    measure_only = bool(s.get("measure_only"))
    exit_on_pause = bool(getattr(args, "exit_on_pause", False))
    prog = _Progress(s)
    tty = sys.stdout.isatty()

    def show() -> None:
        sys.stdout.write(_terminal_line(prog) if tty else prog.line() + "\n")

    if args.json:
        first = {"kind": "status", "campaign": args.id,
                 **{k: s.get(k) for k in ("state", "reason", "poses_total", "poses_measured")}}
        sys.stdout.write(json.dumps(first) + "\n")
    else:
        show()
        if prog.state == "paused" and not exit_on_pause:
            sys.stdout.write(("\n" if tty else "") + f"paused ({s.get('reason') or 'no reason'}"
                             f"); waiting for 'robocal campaign resume {args.id}' (Ctrl-C or "
                             "--exit-on-pause to stop watching)\n")
    sys.stdout.flush()
    reconnects = 0
    while _following(prog.state, measure_only, exit_on_pause):
        for ev in c.events(campaign=args.id, after=after):
            after = max(after, int(ev.get("seq", after)))
            prog.update(ev)
            if args.json:
                sys.stdout.write(json.dumps(ev, default=str) + "\n")
            elif tty or ev.get("kind") in ("state", "fit"):
                show()
            sys.stdout.flush()
            if ev.get("kind") == "state" and not _following(prog.state, measure_only,
                                                            exit_on_pause):
                break
        else:
            # The stream ended with the campaign still under way (a proxy, a daemon restart):
            # look again and follow on from the last event seen.
            reconnects += 1
            if reconnects > _MAX_RECONNECTS:
                raise DaemonUnavailable("the daemon's event stream keeps ending; "
                                        f"see robocal campaign status {args.id}")
            time.sleep(0.5)
            now = c.request("GET", f"/campaigns/{args.id}")
            # the history is the truth after a gap in the stream; the counts carry on
            counts = (prog.retries, prog.beam_losses)
            prog = _Progress(now)
            prog.retries, prog.beam_losses = counts
            last = int(c.request("GET", f"/events/poll?after={2**62}&timeout=0")["last_seq"])
            if last < after:  # the daemon restarted: its sequence numbers did too
                after = 0
    final = _with_report(c, args.id, after)
    code = _exit_code(str(final["state"]), measure_only)
    if args.json:
        sys.stdout.write(json.dumps({"kind": "summary", "campaign": args.id,
                                     "state": final["state"], "reason": final.get("reason"),
                                     "exit_code": code}) + "\n")
    else:
        sys.stdout.write(("\n" if tty else "") + _summary(final, getattr(args, "config", None)))
    return code
