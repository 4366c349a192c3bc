"""``robocal check``: a drift check of the active compensation's model on the daemon (ADR
0041), its history and trend, and the re-calibration it recommends."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from robocal.cli._campaign import add_client_options, client, emit
from robocal.cli._command import command

#: Exit codes of a check (documented in ``--help``); 2 stays robocal's error exit.
EXIT = {"pass": 0, "warn": 3, "fail": 4}

_EPILOG = """exit codes:
  0  the check passed (or --history / --recalibrate / --no-wait)
  3  the check warns: a threshold's warn value is reached
  4  the check failed: a fail value is reached, or the check could not be measured
  2  error: no daemon, nothing to check (no compensation pushed), a campaign is measuring
"""


def register(sub: Any) -> None:
    """Add the ``check`` subcommand."""
    p = command(sub, "check", run)
    p.epilog, p.formatter_class = _EPILOG, argparse.RawDescriptionHelpFormatter
    g = p.add_mutually_exclusive_group()
    g.add_argument("--history", action="store_true",
                   help="list the checks and the trend of their RMS instead of checking")
    g.add_argument("--recalibrate", type=int, metavar="CHECK",
                   help="start the re-calibration with --reuse of the model CHECK checked "
                        "(a campaign of check.reuse_poses poses; approve and push it as any)")
    g.add_argument("--plan", type=Path,
                   help="PLAN.json whose measured poses the check measures (default: poses "
                        "of the active model's own campaign)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--limit", type=int, default=50, help="--history: the last N checks")
    p.add_argument("--no-wait", action="store_true",
                   help="return once the check started (exit 0; its id is printed)")
    p.add_argument("--wait-timeout", type=float, default=3600.0, metavar="S",
                   help="longest wait for the check to be measured and judged, seconds")
    p.add_argument("--wait-idle", type=float, default=0.0, metavar="S",
                   help="while another campaign measures, wait up to S seconds for the robot "
                        "to be free, then check (default 0: refuse at once)")
    add_client_options(p)


def _mm(v: Any, sign: bool = False) -> str:
    if not isinstance(v, int | float):
        return "-"
    return f"{v:+.4f}" if sign else f"{v:.4f}"


def advice(c: dict[str, Any]) -> str:
    """The recommendation of check ``c`` as a sentence with the command that follows it."""
    rec = (c.get("detail") or {}).get("recommendation") or {}
    action = rec.get("action") or c.get("recommendation")
    if action == "none":
        return "nothing to do"
    if action == "reuse":
        return (f"re-calibrate with --reuse on {rec.get('poses')} poses (+ "
                f"{rec.get('validation_poses')} held out): robocal check --recalibrate "
                f"{c['id']}")
    if action == "full":
        return "full calibration (robocal plan, then robocal campaign start)"
    return "-"


def check_text(c: dict[str, Any]) -> str:
    """One judged (or failed) check, a few lines."""
    d = c.get("detail") or {}
    head = (f"check {c['id']} of model {c['model']} (campaign {c['model_campaign']}): "
            f"{str(c.get('verdict') or c['state']).upper()}")
    if c["state"] == "failed":
        return f"{head}\n  not measured: {d.get('reason', '-')}\n"
    if c["state"] != "done":
        return f"{head}\n  measuring (campaign {c['campaign']})\n"
    growth = ("" if d.get("growth_mm") is None else
              f"; {_mm(d['growth_mm'], sign=True)} mm since check {d.get('previous_check')}")
    lines = [head,
             f"  RMS {_mm(c['rms_mm'])} mm, max {_mm(c['max_mm'])} mm over {c['n']} poses"
             f"{growth}; the model's held-out RMS when fitted "
             f"{_mm(d.get('model_held_out_rms_mm'))} mm",
             *(f"  {r}" for r in d.get("reasons") or []),
             f"  recommendation: {advice(c)}"]
    return "\n".join(lines) + "\n"


def history_text(checks: list[dict[str, Any]]) -> str:
    """The checks as a table, oldest first, and the trend of their RMS."""
    if not checks:
        return "no checks yet (robocal check runs one)\n"
    lines = [f"{'check':>5}  {'when (UTC)':19}  {'verdict':7}  {'RMS mm':>7}  {'max mm':>7}  "
             f"{'model campaign':14}  recommendation"]
    for c in checks:
        lines.append(f"{c['id']:>5}  {str(c['created']).replace('T', ' ')[:19]:19}  "
                     f"{c.get('verdict') or c['state']!s:7}  {_mm(c.get('rms_mm')):>7}  "
                     f"{_mm(c.get('max_mm')):>7}  {c['model_campaign']:14}  "
                     f"{c.get('recommendation') or '-'}")
    lines.append("trend (RMS mm, oldest first): "
                 + " -> ".join(_mm(c.get("rms_mm")) for c in checks))
    return "\n".join(lines) + "\n"


def _start(cli: Any, body: dict[str, Any], wait_idle: float) -> dict[str, Any]:
    """Start the check; while another campaign measures (the daemon refuses with 409 and its
    health names the campaign), wait up to ``wait_idle`` s for the robot to be free."""
    from robocal.errors import ApiError

    deadline = time.monotonic() + max(0.0, wait_idle)
    told = ""
    while True:
        try:
            return dict(cli.request("POST", "/checks", body))
        except ApiError as err:
            busy = err.status == 409 and cli.request("GET", "/health").get("measuring")
            left = deadline - time.monotonic()
            if not busy or left <= 0:
                raise
            if busy != told:
                sys.stderr.write(f"robocal check: campaign {busy} is measuring; waiting up to "
                                 f"{left:.0f} s for the robot to be free\n")
                told = busy
            time.sleep(min(1.0, left))


def _wait(cli: Any, check: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Follow the check until it is judged (or ``timeout`` s); progress on stderr."""
    deadline = time.monotonic() + timeout
    shown = ""
    while check["state"] == "measuring" and time.monotonic() < deadline:
        st = cli.request("GET", f"/campaigns/{check['campaign']}")
        text = f"check {check['id']}: {st['poses_measured']}/{st['poses_total']} poses"
        if text != shown:
            sys.stderr.write(text + "\n")
            shown = text
        time.sleep(0.25)
        check = cli.request("GET", f"/checks/{check['id']}")
    return check


def _loud(c: dict[str, Any]) -> None:
    """A check that does not pass, on stderr; under systemd with a journald priority
    (``<3>`` error, ``<4>`` warning: journald reads the prefix)."""
    verdict = str(c.get("verdict") or "fail")
    prefix = ({"fail": "<3>", "warn": "<4>"}.get(verdict, "")
              if os.environ.get("JOURNAL_STREAM") else "")
    sys.stderr.write(f"{prefix}robocal check: drift check {c['id']} "
                     f"{'FAILED' if verdict == 'fail' else 'warns'}: RMS {_mm(c.get('rms_mm'))}"
                     f" mm; recommendation: {advice(c)}\n")


def run(args: argparse.Namespace) -> int:
    """Run, list or act on checks; the exit code is the verdict's (see ``--help``)."""
    cli = client(args)
    if args.history:
        checks = cli.request("GET", "/checks", query={"limit": max(1, args.limit)})
        if args.json:
            emit(checks)
        else:
            sys.stdout.write(history_text(checks))
        return 0
    if args.recalibrate is not None:
        st = cli.request("POST", f"/checks/{args.recalibrate}/recalibrate", {})
        if args.json:
            emit(st)
        else:
            sys.stdout.write(f"{st['id']}\nreuse refit campaign {st['id']} started "
                             f"({st['poses_total']} poses); watch it with robocal campaign "
                             f"watch {st['id']}, then approve and push it\n")
        return 0
    body: dict[str, Any] = {}
    if args.plan is not None:
        from robocal.errors import ConfigError

        try:
            body["plan"] = json.loads(args.plan.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            raise ConfigError(f"cannot read the plan: {err}", source=str(args.plan)) from err
    check = _start(cli, body, args.wait_idle)
    if args.no_wait:
        sys.stdout.write(f"{check['id']}\n")
        return 0
    check = _wait(cli, check, args.wait_timeout)
    if args.json:
        emit(check)
    else:
        sys.stdout.write(check_text(check))
    if check["state"] == "measuring":
        sys.stderr.write(f"robocal check: check {check['id']} still measuring after "
                         f"{args.wait_timeout:g} s\n")
        return 2
    verdict = "fail" if check["state"] == "failed" else str(check["verdict"])
    if verdict != "pass":
        _loud(check)
    return EXIT[verdict]
