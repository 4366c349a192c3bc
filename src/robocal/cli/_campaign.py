"""``robocal campaign ...``: drive campaigns on a running daemon.

Contract for scripts::

    robocal campaign start --plan PLAN.json [--json]   # prints the campaign id (or JSON)
    robocal campaign status ID --json                  # state, poses_total, poses_measured, ...
    robocal campaign pause|resume|abort|approve|push ID [--json]
    robocal campaign list --json
    robocal campaign watch ID [--json]                 # progress bar, or JSON lines

The daemon is found with ``--config FILE``, ``--socket PATH`` or ``--url URL``
(+ ``--token-file`` or ``$ROBOCAL_TOKEN``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

_FINISHED = {"fitted", "pushed", "aborted", "faulted", "paused", "approved"}


def add_client_options(p: argparse.ArgumentParser) -> None:
    """Options locating the daemon."""
    g = p.add_argument_group("daemon")
    g.add_argument("--config", type=Path, help="the daemon's configuration file")
    g.add_argument("--socket", type=Path, help="the daemon's Unix socket")
    g.add_argument("--url", help="the daemon's TCP API, http://host:port")
    g.add_argument("--token-file", type=Path, help="file holding the TCP bearer token "
                                                   "(or set ROBOCAL_TOKEN)")
    g.add_argument("--timeout", type=float, default=60.0, help="request timeout, seconds")


def client(args: argparse.Namespace) -> Any:
    """A :class:`~robocal.daemon.client.DaemonClient` from the parsed options."""
    from robocal.daemon.client import DaemonClient

    return DaemonClient.from_args(config=args.config, socket_path=args.socket, url=args.url,
                                  token_file=args.token_file, timeout=args.timeout)


def emit(obj: Any) -> None:
    """Write JSON to stdout."""
    sys.stdout.write(json.dumps(obj, indent=1, default=str) + "\n")


def register(sub: Any) -> None:
    """Add the ``campaign`` subcommand and its verbs."""
    p = sub.add_parser("campaign", help="start, watch and control campaigns on the daemon",
                       description="Control calibration campaigns on a running daemon.")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)

    s = verbs.add_parser("start", help="create a campaign from a plan and start it")
    s.add_argument("--plan", required=True, type=Path, help="PLAN.json")
    s.add_argument("--name", help="a label for the campaign")
    s.add_argument("--json", action="store_true", help="print the status as JSON")
    add_client_options(s)
    s.set_defaults(handler=start)

    st = verbs.add_parser("status", help="show a campaign")
    st.add_argument("id")
    st.add_argument("--json", action="store_true")
    add_client_options(st)
    st.set_defaults(handler=status)

    ls = verbs.add_parser("list", help="list campaigns")
    ls.add_argument("--json", action="store_true")
    add_client_options(ls)
    ls.set_defaults(handler=list_)

    for verb, text in (("pause", "pause after the pose in progress"),
                       ("resume", "resume a paused or faulted campaign"),
                       ("abort", "abort a campaign"),
                       ("approve", "approve the fit (required before push)"),
                       ("push", "push the approved compensation to the robot")):
        a = verbs.add_parser(verb, help=text)
        a.add_argument("id")
        a.add_argument("--json", action="store_true")
        if verb in ("pause", "abort"):
            a.add_argument("--reason", default="")
        if verb == "approve":
            a.add_argument("--model", help="approve this fitted model instead of the proposed")
        add_client_options(a)
        a.set_defaults(handler=action, action=verb)

    w = verbs.add_parser("watch", help="follow a campaign's progress")
    w.add_argument("id")
    w.add_argument("--json", action="store_true", help="JSON lines instead of a progress bar")
    add_client_options(w)
    w.set_defaults(handler=watch)


def _read_plan(path: Path) -> Any:
    from robocal.errors import ConfigError

    try:
        return json.loads(path.read_text())
    except FileNotFoundError as err:
        raise ConfigError("file not found", source=str(path)) from err
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read: {err}", source=str(path)) from err
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


def _describe(s: dict[str, Any]) -> str:
    lines = [f"campaign {s['id']}  {s.get('name', '')}",
             f"  state     {s['state']}" + (f"  ({s['reason']})" if s.get("reason") else ""),
             f"  poses     {s['poses_measured']}/{s['poses_total']} measured",
             f"  robot     {s.get('robot', '')}",
             f"  created   {s.get('created', '')} by {s.get('created_by', '')}"]
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
    return "\n".join(lines) + "\n"


def status(args: argparse.Namespace) -> int:
    """Print one campaign."""
    out = client(args).request("GET", f"/campaigns/{args.id}")
    if args.json:
        emit(out)
    else:
        sys.stdout.write(_describe(out))
    return 0


def list_(args: argparse.Namespace) -> int:
    """Print every campaign."""
    out = client(args).request("GET", "/campaigns")
    if args.json:
        emit(out)
        return 0
    for c in out:
        sys.stdout.write(f"{c['id']}  {c['state']:9s} {c['poses_measured']:5d}/"
                         f"{c['poses_total']:<5d} {c['created']}  {c['name']}\n")
    return 0


def action(args: argparse.Namespace) -> int:
    """pause / resume / abort / approve / push."""
    body: dict[str, Any] = {}
    if getattr(args, "reason", ""):
        body["reason"] = args.reason
    if getattr(args, "model", None):
        body["model"] = args.model
    out = client(args).request("POST", f"/campaigns/{args.id}/{args.action}", body or None)
    if args.json:
        emit(out)
    else:
        sys.stdout.write(f"{out['id']}: {out['state']}\n")
    return 0


def _bar(measured: int, total: int, state: str, width: int = 30) -> str:
    frac = measured / total if total else 0.0
    filled = round(frac * width)
    return f"\r[{'#' * filled}{'.' * (width - filled)}] {measured}/{total} {state:9s}"


def watch(args: argparse.Namespace) -> int:
    """Follow the event stream until the campaign stops needing the daemon's attention."""
    c = client(args)
    s = c.request("GET", f"/campaigns/{args.id}")
    measured, total, state = s["poses_measured"], s["poses_total"], s["state"]
    tty = sys.stdout.isatty()
    if args.json:
        first = {"kind": "status", "campaign": args.id,
                 **{k: s[k] for k in ("state", "reason", "poses_total", "poses_measured")}}
        sys.stdout.write(json.dumps(first) + "\n")
        sys.stdout.flush()
    else:
        sys.stdout.write(_bar(measured, total, state) + ("" if tty else "\n"))
    if state in _FINISHED or (state == "measured" and s.get("measure_only")):
        if not args.json:
            sys.stdout.write("\n")
        return 0
    for ev in c.events(campaign=args.id):
        if args.json:
            sys.stdout.write(json.dumps(ev, default=str) + "\n")
            sys.stdout.flush()
        if "poses_measured" in ev:
            measured = int(ev["poses_measured"])
            total = int(ev.get("poses_total", total))
        if ev.get("kind") == "state":
            state = str(ev.get("state"))
        if not args.json and (tty or ev.get("kind") == "state"):
            sys.stdout.write(_bar(measured, total, state) + ("" if tty else "\n"))
            sys.stdout.flush()
        if ev.get("kind") == "state" and (state in _FINISHED or (
                state == "measured" and c.request("GET", f"/campaigns/{args.id}")
                .get("measure_only"))):
            break
    if not args.json:
        sys.stdout.write("\n")
        final = c.request("GET", f"/campaigns/{args.id}")
        if final.get("reason"):
            sys.stdout.write(f"{final['state']}: {final['reason']}\n")
    return 0
