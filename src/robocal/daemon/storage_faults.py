"""The campaign service's answer to a store that cannot write (full disk, read-only file).

A measuring campaign whose data cannot be written pauses (:func:`pause_campaign`), the new
state held in memory and shown until the store can write again; :func:`watch` writes such
held states as soon as it can.
"""

from __future__ import annotations

import asyncio
import sqlite3
from collections.abc import Callable

import structlog

from robocal.daemon.campaign import CampaignState
from robocal.daemon.store import Store
from robocal.errors import RobocalError, StorageError

__all__ = ["pause_campaign", "watch"]

_log = structlog.get_logger(__name__)


def pause_campaign(store: Store, transition: Callable[..., object], cid: str,
                   err: StorageError) -> None:
    """Pause ``cid`` if it is ``running`` (``transition`` is the service's), saying why; an
    error reading its state is logged, never raised."""
    reason = f"storage fault: {err}"
    _log.error("campaign paused: the store cannot write", campaign=cid, error=str(err))
    try:
        if store.campaign(cid).state == CampaignState.RUNNING:
            transition(cid, CampaignState.PAUSED, actor="daemon", reason=reason)
    except (RobocalError, sqlite3.Error) as again:
        _log.error("storage fault: campaign state unknown", campaign=cid, error=str(again))


async def watch(store: Store, period_s: float = 1.0) -> None:
    """Write states held in memory by a storage fault as soon as the store can (forever)."""
    while True:
        await asyncio.sleep(period_s)
        if store.pending and store.flush_pending():
            _log.info("storage recovered: held campaign states saved")
