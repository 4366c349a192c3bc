"""Keeps each campaign's report showing what is true of its compensation now.

The daemon writes a campaign's report when it fits it; approval, push, re-measurement,
rollback and later pushes (which supersede it) come afterwards. After each of those the
service calls :meth:`ReportKeeper.refresh`: a background task asks the service for every
campaign's compensation record (approval, pushes with their state, measured before/after),
and rewrites the report's Compensation section of each campaign whose record differs from
what its report last showed. Rendering (a plot per push) runs in a worker thread, off the
event loop and off every request; a ``report`` event tells watchers (and tests) that a
campaign's report now shows the new state.

At start-up the first refresh compares each record with the ``compensation`` block of the
campaign's ``report.json`` (the HTML is written first, the JSON last), so a daemon stopped
between a push and the rewrite, or a push reconciled after a restart, gets its report
brought up to date without rewriting the reports that already agree.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog

from robocal.daemon.events import EventBus
from robocal.errors import RobocalError

__all__ = ["ReportKeeper"]

_log = structlog.get_logger(__name__)

#: campaign id -> the record its Compensation section shows (JSON-able)
Records = dict[str, dict[str, Any]]


def _write(out_dir: Path, record: dict[str, Any]) -> bool:
    from robocal.report import add_checks_section, add_compensation_section

    wrote = add_compensation_section(out_dir, record["entries"],
                                     approval=record.get("approval"))
    # the drift checks of the campaign's model (ADR 0041), when it was checked
    return add_checks_section(out_dir, record.get("checks") or [],
                              thresholds=record.get("check_thresholds")) or wrote


class ReportKeeper:
    """Rewrites reports' Compensation sections in the background when the truth changes.

    Parameters
    ----------
    records : callable
        Returns every campaign's current record (read on the event loop).
    campaign_dir : callable
        The directory of a campaign's report files.
    events : EventBus
        Gets a ``report`` event per rewritten report.
    """

    def __init__(self, records: Callable[[], Records], campaign_dir: Callable[[str], Path],
                 events: EventBus) -> None:
        self._records = records
        self._dir = campaign_dir
        self._events = events
        self._shown: dict[str, str] = {}  # what each report shows (canonical JSON)
        self._dirty = False
        self._task: asyncio.Task[None] | None = None

    def refresh(self) -> None:
        """Bring every report up to date soon (returns at once; coalesces calls)."""
        self._dirty = True
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._run(), name="report-refresh")

    def written(self, cid: str) -> None:
        """``cid``'s report was (re)written from its fit: give it the current record."""
        self._shown.pop(cid, None)
        self.refresh()

    async def settled(self, timeout: float) -> None:
        """Wait (at most ``timeout`` s) until no refresh is pending."""
        async with asyncio.timeout(timeout):
            while self._task is not None and not self._task.done():
                await asyncio.shield(self._task)

    async def close(self) -> None:
        """Stop (a rewrite cut here is done again at the next start)."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task

    async def _run(self) -> None:
        while self._dirty:
            self._dirty = False
            try:
                records = self._records()
            except (RobocalError, OSError, ValueError) as err:
                _log.warning("reports not updated", error=str(err))
                return
            for cid, record in records.items():
                # through JSON, so it compares equal to what report.json holds
                record = json.loads(json.dumps(record, default=str))
                text = json.dumps(record, sort_keys=True)
                if self._shown.get(cid) == text:
                    continue
                out_dir = self._dir(cid)
                try:
                    wrote = await asyncio.to_thread(_write, out_dir, record)
                except (ImportError, RobocalError, OSError, ValueError) as err:
                    _log.warning("report not updated with the compensation", campaign=cid,
                                 error=str(err))
                    continue
                self._shown[cid] = text
                if wrote:
                    self._events.emit("report", cid, section="compensation",
                                      html=str(out_dir / "report.html"))
