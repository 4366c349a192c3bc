"""The push journal: every controller write is *intended* before it happens, *completed* after.

A push or rollback is three transactions around the one controller write:

1. ``intend``: the table to write (and the controller's own values read just before, the
   *baseline* snapshot, when robocal has not written these slots yet), the journal row
   ``intended`` with its idempotency key and an audit entry;
2. the write, read back and verified (no transaction);
3. ``complete``: the push history rows, the audit entry, the campaign ``approved -> pushed``
   and the journal row ``completed``; or ``abandon`` with the reason.

A daemon killed between 1 and 3 leaves an ``intended`` row; on restart the service reads the
controller and completes or abandons it (:meth:`CalibrationService.reconcile`), so nothing
is ever written twice blindly and the history never misses a write. Verification runs
(the pushed targets measured with the tracker) are kept per journal key: ``pending`` from
the completing transaction on, then ``measuring`` (with the child campaign that measures
them), then ``done``, ``skipped`` or ``failed``.
"""

from __future__ import annotations

import json
import sqlite3
import uuid
from typing import Any

from robocal.daemon.campaign import CampaignState, check_transition
from robocal.daemon.schemas import JournalRow, PushDetail, RollbackDetail
from robocal.daemon.store import Store, now_iso
from robocal.errors import CampaignError

__all__ = ["PushJournal", "new_key"]


def new_key() -> str:
    """A fresh journal key: 12 hex digits (48 random bits), the one id a push or rollback is
    shown by everywhere (status, list, watch, report, API), in full."""
    return uuid.uuid4().hex[:12]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS push_journal(
    key TEXT PRIMARY KEY,
    action TEXT NOT NULL CHECK(action IN ('push', 'rollback')),
    state TEXT NOT NULL CHECK(state IN ('intended', 'completed', 'abandoned')),
    campaign TEXT,
    actor TEXT NOT NULL,
    table_id INTEGER NOT NULL REFERENCES tables(id),
    baseline_id INTEGER REFERENCES tables(id),
    rolled_back_id INTEGER REFERENCES tables(id),
    intended_at TEXT NOT NULL,
    finished_at TEXT,
    outcome TEXT NOT NULL DEFAULT '',
    detail TEXT NOT NULL DEFAULT '{}'
);
CREATE TABLE IF NOT EXISTS push_verifications(
    key TEXT PRIMARY KEY REFERENCES push_journal(key),
    campaign TEXT,
    state TEXT NOT NULL,
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    result TEXT NOT NULL DEFAULT '{}'
);
"""


def _entry(row: sqlite3.Row) -> JournalRow:
    return JournalRow.model_validate({**dict(row), "detail": json.loads(row["detail"])})


class PushJournal:
    """Journal rows and verification results in the daemon's store (same SQLite file)."""

    def __init__(self, store: Store) -> None:
        self.store = store

    def ensure_schema(self) -> None:
        """Create the journal tables if needed (the store must be open)."""
        self.store.db.executescript(_SCHEMA)

    # --- the three steps -------------------------------------------------------------------
    def intend(self, *, key: str, action: str, campaign: str | None, actor: str,
               table: tuple[str, str, str] | None = None, table_id: int | None = None,
               baseline: tuple[str, str] | None = None, rolled_back_id: int | None = None,
               detail: PushDetail | RollbackDetail) -> JournalRow:
        """Record the intent, with the table ``(kind, checksum, json)`` to write (or the id of
        a stored one) and the ``baseline`` snapshot ``(checksum, json)``; one transaction.

        Raises
        ------
        CampaignError
            If ``key`` was used before.
        """
        t = now_iso()
        facts = detail.model_dump(mode="json", exclude_unset=True)
        try:
            with self.store.transaction() as db:
                if table is not None:
                    kind, checksum, text = table
                    cur = db.execute(
                        "INSERT INTO tables(campaign, created, origin, kind, checksum, "
                        "table_json) VALUES(?,?,?,?,?,?)",
                        (campaign, t, "campaign", kind, checksum, text))
                    table_id = int(cur.lastrowid or 0)
                if table_id is None:
                    raise CampaignError("a journal entry needs a table")
                baseline_id = None
                if baseline is not None:
                    cur = db.execute(
                        "INSERT INTO tables(campaign, created, origin, kind, checksum, "
                        "table_json) VALUES(?,?,?,?,?,?)",
                        (None, t, "controller", "snapshot", baseline[0], baseline[1]))
                    baseline_id = int(cur.lastrowid or 0)
                db.execute(
                    "INSERT INTO push_journal(key, action, state, campaign, actor, table_id, "
                    "baseline_id, rolled_back_id, intended_at, detail) "
                    "VALUES(?,?,?,?,?,?,?,?,?,?)",
                    (key, action, "intended", campaign, actor, table_id, baseline_id,
                     rolled_back_id, t, json.dumps(facts)))
                checksum = db.execute("SELECT checksum FROM tables WHERE id=?",
                                      (table_id,)).fetchone()[0]
                Store._audit(db, actor, f"compensation.{action}-intended", campaign, checksum,
                             {"key": key, "table_id": table_id, "baseline_id": baseline_id,
                              **facts})
        except sqlite3.IntegrityError as err:
            raise CampaignError(f"idempotency key {key!r} was used before") from err
        return self.get(key)

    def complete(self, key: str, *, actor: str, outcome: str = "written, read back, verified",
                 extra: dict[str, Any] | None = None) -> JournalRow:
        """Finish an intended entry: history, audit, campaign ``pushed``; one transaction."""
        e = self.get(key)
        if e.state != "intended":
            raise CampaignError(f"journal entry {key} is already {e.state}")
        t = now_iso()
        with self.store.transaction() as db:
            checksum = db.execute("SELECT checksum FROM tables WHERE id=?",
                                  (e.table_id,)).fetchone()[0]
            detail = {"key": key, "table_id": e.table_id,
                      **e.detail.model_dump(mode="json", exclude_unset=True), **(extra or {})}
            if e.action == "push":
                if e.baseline_id is not None:
                    db.execute("INSERT INTO pushes(at, action, table_id, campaign, actor) "
                               "VALUES(?,?,?,?,?)", (t, "baseline", e.baseline_id, None, actor))
                db.execute("INSERT INTO pushes(at, action, table_id, campaign, actor) "
                           "VALUES(?,?,?,?,?)", (t, "push", e.table_id, e.campaign, actor))
                if e.campaign is not None:
                    kind = e.detail.kind if isinstance(e.detail, PushDetail) else "table"
                    note = self._to_pushed(db, e.campaign, actor,
                                           f"push {key} ({kind} table {checksum[:12]})")
                    if note:
                        outcome = f"{outcome}; {note}"
                        detail["campaign_note"] = note
            else:
                db.execute("INSERT INTO pushes(at, action, table_id, campaign, actor) "
                           "VALUES(?,?,?,?,?)", (t, "rollback", e.rolled_back_id, None, actor))
                detail["restored_table_id"] = e.table_id
                detail["rolled_back_table_id"] = e.rolled_back_id
            Store._audit(db, actor, f"compensation.{e.action}", e.campaign, checksum, detail)
            db.execute("UPDATE push_journal SET state='completed', finished_at=?, outcome=? "
                       "WHERE key=? AND state='intended'", (t, outcome, key))
            # The verification run is owed from this commit on: a daemon killed the instant
            # after it still finds the run to do on its next start.
            db.execute("INSERT OR IGNORE INTO push_verifications(key, campaign, state, "
                       "created, updated, result) VALUES(?,NULL,'pending',?,?,'{}')",
                       (key, t, t))
        return self.get(key)

    @staticmethod
    def _to_pushed(db: sqlite3.Connection, cid: str, actor: str, reason: str) -> str | None:
        """``approved -> pushed``; for a campaign no longer approved (aborted while its table
        was written, by a daemon without the push lock) the state stays and a note says so:
        the write happened and must be in the history, or nothing could roll it back."""
        row = db.execute("SELECT state FROM campaigns WHERE id=?", (cid,)).fetchone()
        if row is None:
            raise CampaignError(f"no campaign {cid!r}")
        src = CampaignState(row[0])
        if src == CampaignState.PUSHED:
            return None
        if src != CampaignState.APPROVED:
            return (f"campaign {cid} was {src.value} when its table was confirmed on the "
                    "controller; the table is active (roll back to remove it)")
        check_transition(src, CampaignState.PUSHED)
        t = now_iso()
        db.execute("UPDATE campaigns SET state=?, reason=?, updated=? WHERE id=?",
                   (CampaignState.PUSHED.value, reason, t, cid))
        db.execute("INSERT INTO transitions(campaign, at, from_state, to_state, reason, actor) "
                   "VALUES(?,?,?,?,?,?)", (cid, t, src.value, CampaignState.PUSHED.value,
                                           reason, actor))
        return None

    def abandon(self, key: str, *, actor: str, reason: str, what: str = "abandoned",
                extra: dict[str, Any] | None = None) -> JournalRow:
        """Close an intended entry without a history row (nothing, or the original, is on the
        controller); audit ``compensation.<action>-<what>`` with the reason."""
        e = self.get(key)
        if e.state != "intended":
            raise CampaignError(f"journal entry {key} is already {e.state}")
        with self.store.transaction() as db:
            checksum = db.execute("SELECT checksum FROM tables WHERE id=?",
                                  (e.table_id,)).fetchone()[0]
            Store._audit(db, actor, f"compensation.{e.action}-{what}", e.campaign, checksum,
                         {"key": key, "reason": reason, **(extra or {})})
            db.execute("UPDATE push_journal SET state='abandoned', finished_at=?, outcome=? "
                       "WHERE key=? AND state='intended'", (now_iso(), reason, key))
        return self.get(key)

    # --- queries ---------------------------------------------------------------------------
    def get(self, key: str) -> JournalRow:
        """One entry; raise CampaignError when unknown."""
        row = self.store.db.execute("SELECT * FROM push_journal WHERE key=?",
                                    (key,)).fetchone()
        if row is None:
            raise CampaignError(f"no journal entry {key!r}")
        return _entry(row)

    def find(self, key: str) -> JournalRow | None:
        """One entry or None."""
        row = self.store.db.execute("SELECT * FROM push_journal WHERE key=?",
                                    (key,)).fetchone()
        return None if row is None else _entry(row)

    def pending(self) -> list[JournalRow]:
        """Entries still ``intended`` (a write may or may not have happened), oldest first."""
        rows = self.store.db.execute(
            "SELECT * FROM push_journal WHERE state='intended' ORDER BY rowid").fetchall()
        return [_entry(r) for r in rows]

    def entries(self, *, campaign: str | None = None) -> list[JournalRow]:
        """Every entry (of one campaign), oldest first."""
        if campaign is None:
            rows = self.store.db.execute("SELECT * FROM push_journal ORDER BY rowid").fetchall()
        else:
            rows = self.store.db.execute(
                "SELECT * FROM push_journal WHERE campaign=? ORDER BY rowid",
                (campaign,)).fetchall()
        return [_entry(r) for r in rows]

    # --- verification runs -----------------------------------------------------------------
    def set_verification(self, key: str, *, state: str, campaign: str | None = None,
                         result: dict[str, Any] | None = None) -> None:
        """Create or update the verification run of journal entry ``key``."""
        t = now_iso()
        with self.store.transaction() as db:
            row = db.execute("SELECT campaign, result FROM push_verifications WHERE key=?",
                             (key,)).fetchone()
            if row is None:
                db.execute("INSERT INTO push_verifications(key, campaign, state, created, "
                           "updated, result) VALUES(?,?,?,?,?,?)",
                           (key, campaign, state, t, t, json.dumps(result or {})))
            else:
                merged = {**json.loads(row["result"]), **(result or {})}
                db.execute("UPDATE push_verifications SET state=?, campaign=?, updated=?, "
                           "result=? WHERE key=?",
                           (state, campaign or row["campaign"], t, json.dumps(merged), key))

    def verification(self, key: str) -> dict[str, Any] | None:
        """The verification run of ``key`` (state, campaign, result), or None."""
        row = self.store.db.execute("SELECT * FROM push_verifications WHERE key=?",
                                    (key,)).fetchone()
        if row is None:
            return None
        return {"state": row["state"], "campaign": row["campaign"], "updated": row["updated"],
                **json.loads(row["result"])}

    def open_verifications(self) -> list[tuple[str, str | None]]:
        """``(key, campaign)`` of verification runs not finished yet (``pending``: owed since
        the push completed, not started; ``measuring``), oldest first."""
        rows = self.store.db.execute(
            "SELECT key, campaign FROM push_verifications WHERE state IN ('pending', "
            "'measuring') ORDER BY rowid").fetchall()
        return [(str(r[0]), r[1]) for r in rows]
