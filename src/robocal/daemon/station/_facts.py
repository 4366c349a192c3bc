"""What the station shows, computed from the service's public answers (plain dicts).

Nothing here changes state; every figure comes from ``CalibrationService.status``, ``list``,
``compensation``, ``health`` and ``measurements``, so the page says what the CLI says.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

__all__ = [
    "STEPS",
    "Progress",
    "controller_banner",
    "heldout_rms",
    "progress",
    "rolled_back_at",
    "steps",
]

#: The step bar, in order.
STEPS = ("plan", "measure", "fit", "review", "approve", "push", "verify")

# The step a campaign in each state is at (its earlier steps are done).
_CURRENT = {"created": "plan", "running": "measure", "paused": "measure", "measured": "fit",
            "fitted": "review", "approved": "push", "pushed": "verify"}


def _dig(d: Any, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return d


def heldout_rms(status: dict[str, Any]) -> float | None:
    """Held-out (validation) RMS (mm) of the campaign's selected model, if fitted."""
    name = status.get("selected_model")
    fits = status.get("fits") or {}
    if name is None or name not in fits:
        return None
    v = _dig(fits[name], "validation", "rms_mm")
    return float(v) if isinstance(v, int | float) else None


def rolled_back_at(status: dict[str, Any], compensation: dict[str, Any]) -> str | None:
    """When the campaign's pushed table was rolled back (None if it was not)."""
    tables = {e["table_id"] for e in status.get("compensation") or ()
              if e.get("action") == "push" and e.get("state") == "completed"}
    if not tables:
        return None
    for j in reversed(compensation.get("journal") or ()):
        if (j.get("action") == "rollback" and j.get("state") == "completed"
                and j.get("rolled_back_id") in tables):
            return str(j.get("finished_at") or j.get("intended_at"))
    return None


@dataclass(frozen=True)
class Step:
    """One box of the step bar."""

    name: str
    status: str  # "done" | "current" | "todo" | "failed"


def steps(status: dict[str, Any], *, rolled_back: bool) -> list[Step]:
    """The step bar of a campaign: done steps, the current one, the rest to do."""
    state = status["state"]
    current = _CURRENT.get(state)
    if state in ("faulted", "aborted"):
        # stuck where it stopped: the last step it was in, from its transitions
        prev = [t["from_state"] for t in status.get("transitions") or () if t["from_state"]]
        current = _CURRENT.get(prev[-1] if prev else "created", "plan")
    verify = (status.get("push") or {}).get("verification")
    out = []
    reached = False
    for name in STEPS:
        if name == current:
            reached = True
            if state in ("faulted", "aborted"):
                out.append(Step(name, "failed"))
            elif name == "verify" and verify == "done":
                out.append(Step(name, "done"))
            else:
                out.append(Step(name, "current"))
        else:
            out.append(Step(name, "todo" if reached else "done"))
    if rolled_back:
        out.append(Step("rolled back", "current"))
    return out


@dataclass(frozen=True)
class Progress:
    """Measuring progress in operator's units."""

    measured: int
    total: int
    rate_per_min: float | None
    eta_s: float | None
    retries: int
    beam_losses: int
    elapsed_s: float | None


def _t(iso: str) -> float:
    return datetime.fromisoformat(iso).timestamp()


def progress(status: dict[str, Any], rows: list[tuple[int, int, str]], *, window: int = 20
             ) -> Progress:
    """Poses measured, rate over the last ``window`` poses, ETA while running, retries and
    beam losses, from ``(attempts, beam_losses, measured_at)`` per stored measurement."""
    n, total = int(status["poses_measured"]), int(status["poses_total"])
    retries = sum(max(0, r[0] - 1) for r in rows)
    losses = sum(r[1] for r in rows)
    rate = eta = elapsed = None
    if len(rows) >= 2:
        stamps = sorted(r[2] for r in rows)  # ISO 8601 UTC strings sort by time
        recent = [_t(x) for x in stamps[-window:]]
        span = recent[-1] - recent[0]
        if span > 0:
            rate = 60.0 * (len(recent) - 1) / span
        elapsed = recent[-1] - _t(stamps[0])
    if rate and status["state"] == "running":
        eta = max(0.0, (total - n) / rate * 60.0)
    return Progress(n, total, rate, eta, retries, losses, elapsed)


def controller_banner(compensation: dict[str, Any],
                      push_of: dict[str, dict[str, Any] | None]) -> dict[str, Any]:
    """What the controller holds now, for the banner.

    ``push_of`` maps a campaign id to its status' ``push`` summary (model, time, measured
    before/after). Returns ``{"kind": "pushed"|"original"|"unknown", ...}``.
    """
    active = compensation.get("active")
    history = compensation.get("history") or []
    last = history[-1] if history else None
    if active is None or active.get("origin") == "controller" or not active.get("campaign"):
        out: dict[str, Any] = {"kind": "original"}
        if last is not None and last.get("action") == "rollback":
            v = last.get("verification") or {}
            out.update(rolled_back_at=last.get("at"), by=last.get("actor"),
                       verification=v.get("state"),
                       before_mm=_dig(v, "before", "rms_mm"), after_mm=_dig(v, "after", "rms_mm"))
        return out
    cid = str(active["campaign"])
    push = push_of.get(cid) or {}
    entry: dict[str, Any] = next((h for h in reversed(history)
                  if h.get("table_id") == active.get("table_id")), {})
    verification = entry.get("verification") or {}
    before = _dig(verification, "before", "rms_mm")
    after = _dig(verification, "after", "rms_mm")
    return {"kind": "pushed", "campaign": cid, "model": push.get("model"),
            "table": active.get("kind"), "checksum": active.get("checksum"),
            "at": entry.get("at") or push.get("at"), "action": entry.get("action"),
            "by": entry.get("actor") or push.get("actor"),
            "verification": verification.get("state"),
            "before_mm": before if before is not None else push.get("measured_before_rms_mm"),
            "after_mm": after if after is not None else push.get("measured_after_rms_mm")}
