"""Live progress events: an in-memory, sequence-numbered stream with fan-out to subscribers.

The store is the record; events are for watching (``GET /events`` as Server-Sent Events,
``robocal campaign watch``). Each event is a JSON object with ``seq`` (increasing within one
daemon run), ``time``, ``kind`` and ``campaign``; a subscriber that reconnects passes the last
``seq`` it saw (or, over SSE, the ``Last-Event-ID`` ``BOOT-SEQ``, which names the daemon run)
and gets what it missed from a bounded replay buffer.

Kinds: ``state`` (a transition), ``pose`` (a pose measured), ``retry`` (a reading retried),
``fit`` (fitting started/finished), ``compensation`` (push/rollback), ``report`` (a
campaign's report rewritten to show the compensation now), ``warmup`` (the warm-up
routine before a campaign's first measured pose), ``log``; each kind's
fields are the model in :mod:`robocal.daemon.schemas`, checked by :meth:`EventBus.emit`.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import secrets
import time
from collections.abc import AsyncIterator, Collection
from typing import Any

from robocal.daemon.schemas import EVENT_MODELS

__all__ = ["EventBus"]


class EventBus:
    """Publish events to any number of subscribers; slow subscribers lose old events.

    Parameters
    ----------
    replay : int
        Events kept for subscribers that (re)connect with ``after``.
    queue_size : int
        Per-subscriber queue; when full, the oldest queued event is dropped.
    """

    def __init__(self, *, replay: int = 2000, queue_size: int = 1000) -> None:
        #: Names this daemon run: sequence numbers restart with every run, so an event id
        #: (``BOOT-SEQ``) from an earlier run must not be read as "seen up to SEQ".
        self.boot_id = secrets.token_hex(4)
        self._seq = 0
        self._buffer: collections.deque[dict[str, Any]] = collections.deque(maxlen=replay)
        # each subscriber's queue and the kinds it takes (None: every kind)
        self._subscribers: dict[asyncio.Queue[dict[str, Any] | None],
                                frozenset[str] | None] = {}
        self._queue_size = queue_size
        self._closed = False

    @property
    def last_seq(self) -> int:
        """Sequence number of the latest event (0 before the first)."""
        return self._seq

    def emit(self, kind: str, campaign: str | None = None, **data: Any) -> dict[str, Any]:
        """Publish one event and return it.

        Raises
        ------
        ValueError
            If ``kind`` is unknown or ``data`` does not match the kind's model in
            :mod:`robocal.daemon.schemas` (a missing, extra or mistyped field: a bug, which
            the tests that emit it catch); nothing is published then.
        """
        model = EVENT_MODELS.get(kind)
        if model is None:
            raise ValueError(f"unknown event kind {kind!r} (one of {', '.join(EVENT_MODELS)})")
        event = {"seq": self._seq + 1, "time": time.time(), "kind": kind,
                 "campaign": campaign, **data}
        model.model_validate(event)  # pydantic's ValidationError is a ValueError
        self._seq += 1
        self._buffer.append(event)
        for q, kinds in list(self._subscribers.items()):
            if kinds is not None and kind not in kinds:
                continue  # not woken for what it does not watch (a pose event per pose)
            if q.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(event)
        return event

    def event_id(self, event: dict[str, Any]) -> str:
        """The SSE ``id`` of an event: ``BOOT-SEQ``."""
        return f"{self.boot_id}-{event['seq']}"

    def after_event_id(self, last_event_id: str) -> int:
        """The ``seq`` to replay after for a client's ``Last-Event-ID``.

        An id of this run gives its sequence number; one of an earlier run (or a bare number
        from a client of an older daemon) gives 0: everything buffered is news to that client.
        """
        boot, sep, seq = last_event_id.strip().rpartition("-")
        if sep and boot == self.boot_id and seq.isdigit():
            return min(int(seq), self._seq)
        return 0

    def history(self, *, after: int = 0, campaign: str | None = None) -> list[dict[str, Any]]:
        """Buffered events with ``seq > after`` (optionally of one campaign)."""
        return [e for e in self._buffer
                if e["seq"] > after and (campaign is None or e["campaign"] == campaign)]

    @contextlib.asynccontextmanager
    async def subscribe(self, kinds: Collection[str] | None = None
                        ) -> AsyncIterator[asyncio.Queue[dict[str, Any] | None]]:
        """A queue receiving every new event (only those of ``kinds`` if given); ``None``
        means the bus closed.

        Raises
        ------
        ValueError
            If ``kinds`` names an unknown kind.
        """
        wanted = None if kinds is None else frozenset(kinds)
        if wanted is not None and not wanted <= EVENT_MODELS.keys():
            raise ValueError(f"unknown event kinds {sorted(wanted - EVENT_MODELS.keys())}")
        q: asyncio.Queue[dict[str, Any] | None] = asyncio.Queue(self._queue_size)
        if self._closed:
            q.put_nowait(None)
        self._subscribers[q] = wanted
        try:
            yield q
        finally:
            self._subscribers.pop(q, None)

    def close(self) -> None:
        """Wake every subscriber with ``None`` (daemon shutdown)."""
        self._closed = True
        for q in list(self._subscribers):
            if q.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(None)
