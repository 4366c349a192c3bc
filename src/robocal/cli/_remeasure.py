"""Waiting for the re-measurement of a push or rollback (its verification run, a child of
it in the daemon) so that ``campaign push`` and ``compensation rollback`` end with the
measured before -> after instead of returning while the robot still moves."""

from __future__ import annotations

import argparse
import sys
import time
import uuid
from typing import Any

__all__ = ["add_wait_options", "new_key", "remeasured_text", "wait_remeasured"]

_FINISHED = ("done", "skipped", "failed")


def add_wait_options(p: argparse.ArgumentParser) -> None:
    """``--no-wait`` and ``--wait-timeout`` for push and rollback."""
    p.add_argument("--no-wait", action="store_true",
                   help="return once the table is written and read back; the re-measurement "
                        "of the targets goes on in the daemon")
    p.add_argument("--wait-timeout", type=float, default=3600.0, metavar="S",
                   help="longest wait for the re-measurement, seconds (default: %(default)s)")


def new_key() -> str:
    """A fresh idempotency key (the CLI names its push or rollback, so it can follow it):
    12 hex digits, as the daemon's own (the id shown for it everywhere)."""
    return uuid.uuid4().hex[:12]


def _verification(cli: Any, key: str) -> dict[str, Any] | None:
    for h in cli.request("GET", "/compensation")["history"]:
        if h.get("key") == key:
            v = h.get("verification")
            return v if isinstance(v, dict) else None
    return None


def wait_remeasured(cli: Any, key: str, *, timeout: float, period_s: float = 0.25
                    ) -> dict[str, Any] | None:
    """Follow the verification run of journal key ``key`` until it ends (or ``timeout`` s);
    show progress on stderr (one line, rewritten on a terminal); return the run's record."""
    deadline = time.monotonic() + timeout
    tty = sys.stderr.isatty()
    shown = ""
    while True:
        v = _verification(cli, key)
        state = (v or {}).get("state")
        if state in _FINISHED or time.monotonic() >= deadline:
            if shown and tty:
                sys.stderr.write("\n")
            return v
        text = "re-measurement waiting for the robot"
        child = (v or {}).get("campaign")
        if state == "measuring" and child:
            st = cli.request("GET", f"/campaigns/{child}")
            text = (f"re-measuring the targets: {st['poses_measured']}/{st['poses_total']} "
                    f"poses ({st['state']})")
        if text != shown:
            sys.stderr.write(("\r" + text.ljust(len(shown))) if tty else text + "\n")
            sys.stderr.flush()
            shown = text
        time.sleep(period_s)


def remeasured_text(v: dict[str, Any] | None) -> str:
    """One line: the measured before -> after, or why there is none."""
    if v is None:
        return "re-measurement: none recorded"
    if v.get("state") != "done":
        why = f": {v['reason']}" if v.get("reason") else ""
        return f"re-measurement {v.get('state')}{why}"
    before, after = v.get("before") or {}, v.get("after") or {}
    return (f"measured {before.get('rms_mm', float('nan')):.4f} mm before -> "
            f"{after.get('rms_mm', float('nan')):.4f} mm after (RMS of {after.get('n')} "
            "re-measured targets)")
