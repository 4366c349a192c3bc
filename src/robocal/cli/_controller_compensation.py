"""``robocal compensation list|rollback``: the compensation tables pushed by the daemon, each
with its predicted and nominal residual and the measured before/after of its verification run."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from robocal.cli._campaign import add_client_options, answer, client, emit
from robocal.cli._command import command
from robocal.cli._remeasure import add_wait_options, new_key, remeasured_text, wait_remeasured


def register(sub: Any) -> None:
    """Add the ``compensation`` subcommand."""
    p = command(sub, "compensation", None)
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    ls = command(verbs, "list", list_, parent="compensation")
    ls.add_argument("--json", action="store_true", help="print the tables and pushes as JSON")
    rb = command(verbs, "rollback", rollback, parent="compensation")
    rb.add_argument("--reason", default="", help="why (kept in the audit log)")
    rb.add_argument("--json", action="store_true", help="print the result as JSON")
    rb.add_argument("--key", help="idempotency key: a retry with the same key answers like "
                                  "the first rollback and writes nothing (default: a new one)")
    add_wait_options(rb)
    au = command(verbs, "audit", audit, parent="compensation")
    au.add_argument("--limit", type=int, default=50, help="newest entries to show")
    au.add_argument("--json", action="store_true", help="print the entries as JSON")
    for parser in verbs.choices.values():  # last: the daemon group after the verb's own
        add_client_options(parser)


def _mm(v: Any) -> str:
    return f"{v:.4f}" if isinstance(v, int | float) else "-"


def _print_state(out: dict[str, Any]) -> None:
    history = out.get("history", [])
    active = out.get("active")
    if active:
        on_top = [h for h in history if h.get("compensation_state") == "active"]
        what = (f"push {on_top[-1]['key']} (table {active['table_id']}"
                if on_top else f"table {active['table_id']} (")
        sys.stdout.write(f"active: {what}, {active['kind']}, {active['checksum'][:16]}, from "
                         f"{active['campaign'] or 'controller'})\n")
        if active.get("purpose"):
            sys.stdout.write(f"  {active['purpose']}\n")
        for w in active.get("warnings") or []:
            sys.stdout.write(f"  warning: {w}\n")
    else:
        sys.stdout.write("active: none pushed by robocal\n")
    if history:
        sys.stdout.write(f"  {'at':29s} {'action':8s} {'key':12s} {'now':11s} {'table':5s} "
                         f"{'kind':8s} {'predicted':>9s} {'nominal':>9s} "
                         f"{'meas.before':>11s} {'meas.after':>10s}  by\n")
    for h in history:
        v = h.get("verification") or {}
        before = (v.get("before") or {}).get("rms_mm")
        after = (v.get("after") or {}).get("rms_mm")
        forced = "  (forced)" if h.get("forced") else ""
        sys.stdout.write(f"  {h['at']:29s} {h['action']:8s} {h.get('key') or '-':12s} "
                         f"{h.get('compensation_state') or '':11s} {h['table_id']:<5d} "
                         f"{h['kind']:8s} {_mm(h.get('predicted_residual_mm')):>9s} "
                         f"{_mm(h.get('nominal_residual_mm')):>9s} {_mm(before):>11s} "
                         f"{_mm(after):>10s}  {h['actor']}{forced}\n")
    if history:
        sys.stdout.write("  mm RMS; measured: the pushed targets re-measured with the tracker "
                         "after the push or rollback\n")


def list_(args: argparse.Namespace) -> int:
    """Print the active table and the history."""
    out = client(args).request("GET", "/compensation")
    if args.json:
        emit(out)
    else:
        _print_state(out)
    return 0


def rollback(args: argparse.Namespace) -> int:
    """Restore the previous table."""
    key = args.key or new_key()
    body: dict[str, Any] = {"key": key, **({"reason": args.reason} if args.reason else {})}
    cli = client(args)
    out = cli.request("POST", "/compensation/rollback", body)
    measured = None
    if not args.no_wait:
        measured = remeasured_text(wait_remeasured(cli, key, timeout=args.wait_timeout))
        out = cli.request("GET", "/compensation")
    if args.json:
        emit(out)
    else:
        _print_state(out)
        if measured is not None:
            sys.stdout.write(measured + "\n")
    return 0


def audit(args: argparse.Namespace) -> int:
    """Print the audit log."""
    out = client(args).request("GET", "/audit", query={"limit": args.limit})
    return answer(args, out, (f"{a['at']}  {a['action']:28s} {a['actor']:24s} "
                              f"{a['campaign'] or '-':12s} {(a['checksum'] or '')[:16]}"
                              for a in out))
