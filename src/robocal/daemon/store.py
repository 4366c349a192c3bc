"""The daemon's embedded store: one SQLite file in ``data_dir``, WAL mode.

Every write is one ``BEGIN IMMEDIATE ... COMMIT`` transaction. A committed transaction is in
the WAL file when COMMIT returns, so a kill -9 at any moment loses at most the pose in
progress. Commits are ``synchronous=FULL`` (the WAL fsynced: durable against a power cut)
except a measurement's, which is ``synchronous=NORMAL`` (no fsync): a power cut may roll back
the last measurements, never a state change, push or audit record, because the WAL is
append-only and the next FULL commit syncs every frame before it (ADR 0036).
``UNIQUE(campaign, pose_idx)`` makes a duplicated measurement impossible. The
``audit`` and ``pushes`` tables are append-only (triggers refuse UPDATE and DELETE).

Units in the store are those of robocal's files: millimetres and degrees.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import math
import os
import sqlite3
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robocal._core.files import private_file
from robocal.daemon.campaign import CampaignState, check_transition
from robocal.daemon.schemas import CampaignSummary, Measurement
from robocal.errors import (
    CampaignError,
    ConfigError,
    InvalidTransition,
    StorageError,
    UnknownCampaign,
)

__all__ = ["PoseRow", "Store", "is_storage_fault", "now_iso"]

SCHEMA_VERSION = 2

#: Size of the file that keeps states held by a storage fault across a restart; written in
#: place, so a full disk still takes it (room for a few hundred held campaigns).
HELD_BYTES = 65536

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS campaigns(
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    state TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    robot TEXT NOT NULL,
    poses_total INTEGER NOT NULL,
    measure_only INTEGER NOT NULL DEFAULT 0,
    plan_json TEXT NOT NULL,
    plan_digest TEXT NOT NULL,
    config_digest TEXT NOT NULL,
    selected_model TEXT,
    created_by TEXT NOT NULL,
    parent TEXT
);
CREATE TABLE IF NOT EXISTS poses(
    campaign TEXT NOT NULL REFERENCES campaigns(id),
    idx INTEGER NOT NULL,
    purpose TEXT NOT NULL,
    measure INTEGER NOT NULL DEFAULT 1,
    q_deg TEXT NOT NULL,
    PRIMARY KEY(campaign, idx)
);
CREATE TABLE IF NOT EXISTS measurements(
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    campaign TEXT NOT NULL REFERENCES campaigns(id),
    pose_idx INTEGER NOT NULL,
    purpose TEXT NOT NULL,
    q_cmd_deg TEXT NOT NULL,
    q_act_deg TEXT NOT NULL,
    x_mm REAL NOT NULL, y_mm REAL NOT NULL, z_mm REAL NOT NULL,
    sx_mm REAL, sy_mm REAL, sz_mm REAL,
    rms_mm REAL,
    samples INTEGER NOT NULL,
    attempts INTEGER NOT NULL,
    beam_losses INTEGER NOT NULL DEFAULT 0,
    distance_mm REAL,
    weather TEXT NOT NULL DEFAULT '{}',
    temps TEXT NOT NULL DEFAULT '[]',
    measured_at TEXT NOT NULL,
    UNIQUE(campaign, pose_idx)
);
CREATE TABLE IF NOT EXISTS transitions(
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    campaign TEXT NOT NULL REFERENCES campaigns(id),
    at TEXT NOT NULL,
    from_state TEXT,
    to_state TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    actor TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS fits(
    campaign TEXT NOT NULL REFERENCES campaigns(id),
    model TEXT NOT NULL,
    created TEXT NOT NULL,
    summary TEXT NOT NULL,
    model_json TEXT,
    PRIMARY KEY(campaign, model)
);
CREATE TABLE IF NOT EXISTS tables(
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    campaign TEXT,
    created TEXT NOT NULL,
    origin TEXT NOT NULL,
    kind TEXT NOT NULL,
    checksum TEXT NOT NULL,
    table_json TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS pushes(
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    at TEXT NOT NULL,
    action TEXT NOT NULL CHECK(action IN ('push', 'rollback', 'baseline')),
    table_id INTEGER NOT NULL REFERENCES tables(id),
    campaign TEXT,
    actor TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS audit(
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    at TEXT NOT NULL,
    actor TEXT NOT NULL,
    action TEXT NOT NULL,
    campaign TEXT,
    checksum TEXT,
    detail TEXT NOT NULL DEFAULT '{}'
);
CREATE TRIGGER IF NOT EXISTS audit_no_update BEFORE UPDATE ON audit
    BEGIN SELECT RAISE(ABORT, 'the audit log is append-only'); END;
CREATE TRIGGER IF NOT EXISTS audit_no_delete BEFORE DELETE ON audit
    BEGIN SELECT RAISE(ABORT, 'the audit log is append-only'); END;
CREATE TRIGGER IF NOT EXISTS pushes_no_update BEFORE UPDATE ON pushes
    BEGIN SELECT RAISE(ABORT, 'the push history is append-only'); END;
CREATE TRIGGER IF NOT EXISTS pushes_no_delete BEFORE DELETE ON pushes
    BEGIN SELECT RAISE(ABORT, 'the push history is append-only'); END;
CREATE INDEX IF NOT EXISTS transitions_by_campaign ON transitions(campaign, id);
"""


_STORAGE_FAULTS = (10, 13)  # SQLITE_IOERR, SQLITE_FULL (primary result codes)


def is_storage_fault(err: BaseException) -> bool:
    """True for SQLite errors caused by the disk (full, I/O error), not by the request."""
    code = getattr(err, "sqlite_errorcode", None)
    if isinstance(code, int):
        return code & 0xFF in _STORAGE_FAULTS
    text = str(err).lower()
    return isinstance(err, sqlite3.OperationalError) and (
        "disk is full" in text or "disk i/o error" in text)


def _migrate_1_to_2(db: sqlite3.Connection) -> None:
    """Schema 2 adds the joint temperatures of every measurement (``[]``: not read)."""
    with db:  # one transaction: both or neither
        db.execute("BEGIN IMMEDIATE")
        if "temps" not in {r[1] for r in db.execute("PRAGMA table_info(measurements)")}:
            db.execute("ALTER TABLE measurements ADD COLUMN temps TEXT NOT NULL DEFAULT '[]'")
        db.execute("UPDATE meta SET value='2' WHERE key='schema'")


def now_iso() -> str:
    """Current UTC time, ISO 8601 with milliseconds."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class PoseRow:
    """A planned pose: index in the plan, purpose, joint target (degrees), measured or not.

    Via-points (``measure=False``) are moved through, never measured.
    """

    idx: int
    purpose: str
    q_deg: tuple[float, ...]
    measure: bool = True


def _floats_json(values: Sequence[float]) -> str:
    """``json.dumps(list(values))`` for floats, without the encoder's per-call set-up (a
    measurement row has three such lists, written once per pose)."""
    vals = list(map(float, values))
    if all(map(math.isfinite, vals)):
        return str(vals)  # a list's str is its floats' reprs, ", "-separated, as json writes
    return json.dumps(vals)


class Store:
    """SQLite store of campaigns, measurements, fits, compensation tables and the audit log.

    Parameters
    ----------
    path : Path
        Database file; its directory must exist.

    Notes
    -----
    Not thread-safe: the daemon uses it from the event-loop thread only. Each call is short
    (a durable commit costs one fsync; a measurement's none).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._db: sqlite3.Connection | None = None
        #: Last storage fault (text) or None once a write succeeded again.
        self.fault: str | None = None
        #: Test seam: called with "begin" / "commit" in every write transaction; raising
        #: ``sqlite3.OperationalError("database or disk is full")`` there is a full disk.
        self.fault_hook: Callable[[str], None] | None = None
        # cid -> (state on disk, state held in memory, reason, actor, time)
        self._pending: dict[str, tuple[CampaignState, CampaignState, str, str, str]] = {}
        self._sync = "FULL"

    # --- lifecycle -------------------------------------------------------------------------
    def open(self) -> Store:
        """Open (creating the schema if needed); WAL journal, full fsync on commit.

        The database and its WAL files are made 0600 (SQLite gives the WAL files the
        database's mode), whoever starts the daemon and whatever the umask.
        """
        try:
            private_file(self.path)
            for extra in ("-wal", "-shm", "-journal"):
                with contextlib.suppress(FileNotFoundError):
                    os.chmod(f"{self.path}{extra}", 0o600)
            db = sqlite3.connect(self.path, isolation_level=None, timeout=10.0)
        except (sqlite3.Error, OSError) as err:
            raise ConfigError(f"cannot open the store: {err}", source=str(self.path)) from err
        db.row_factory = sqlite3.Row
        mode = db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise ConfigError(f"cannot enable WAL (got {mode})", source=str(self.path))
        db.execute("PRAGMA synchronous=FULL")
        self._sync = "FULL"
        db.execute("PRAGMA foreign_keys=ON")
        db.executescript(_SCHEMA)
        columns = {r[1] for r in db.execute("PRAGMA table_info(measurements)")}
        if "beam_losses" not in columns:  # stores written before beam losses were counted
            db.execute("ALTER TABLE measurements ADD COLUMN beam_losses INTEGER NOT NULL "
                       "DEFAULT 0")
        if "parent" not in {r[1] for r in db.execute("PRAGMA table_info(campaigns)")}:
            db.execute("ALTER TABLE campaigns ADD COLUMN parent TEXT")  # before child runs
        row = db.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
        if row is None:
            db.execute("INSERT INTO meta(key, value) VALUES('schema', ?)", (str(SCHEMA_VERSION),))
        elif int(row[0]) == 1:
            _migrate_1_to_2(db)
        elif int(row[0]) != SCHEMA_VERSION:
            raise ConfigError(
                f"store schema {row[0]} is not supported (expected {SCHEMA_VERSION})",
                source=str(self.path),
            )
        self._db = db
        self._load_held()
        self._prepare_held()
        return self

    # --- states held by a storage fault, kept across a restart ----------------------------
    @property
    def held_path(self) -> Path:
        """The file that keeps held states (next to the database)."""
        return self.path.with_name(self.path.name + ".held")

    def _prepare_held(self) -> None:
        """Allocate the held-states file while the disk takes data (best effort)."""
        with contextlib.suppress(OSError):
            if not self.held_path.exists() or self.held_path.stat().st_size < HELD_BYTES:
                fd = os.open(self.held_path, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o600)
                try:
                    os.pwrite(fd, self._held_bytes(), 0)
                    os.fsync(fd)
                finally:
                    os.close(fd)

    def _held_bytes(self) -> bytes:
        data = {cid: [p[0].value, p[1].value, p[2], p[3], p[4]]
                for cid, p in self._pending.items()}
        raw = json.dumps(data).encode()
        while len(raw) > HELD_BYTES and data:  # never happens in practice; keep it valid
            data.pop(next(iter(data)))
            raw = json.dumps(data).encode()
        return raw.ljust(HELD_BYTES)

    def _write_held(self) -> None:
        """Rewrite the held-states file in place (no new blocks: it works on a full disk)."""
        try:
            fd = os.open(self.held_path, os.O_WRONLY | os.O_CLOEXEC)
        except OSError:
            return
        try:
            os.pwrite(fd, self._held_bytes(), 0)
            os.fsync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)

    def _load_held(self) -> None:
        """Hold again the states a daemon held when it stopped, where the database still has
        the state they were held over (a pause on a full disk stays a pause after a restart,
        even if the disk was freed meanwhile)."""
        try:
            data = json.loads(self.held_path.read_bytes().strip() or b"{}")
        except (OSError, ValueError):
            return
        if not isinstance(data, dict):
            return
        for cid, item in data.items():
            try:
                src, to = CampaignState(item[0]), CampaignState(item[1])
                row = self.db.execute("SELECT state FROM campaigns WHERE id=?",
                                      (cid,)).fetchone()
            except (ValueError, TypeError, IndexError, KeyError):
                continue
            if row is not None and row[0] == src.value:
                self._pending[str(cid)] = (src, to, str(item[2]), str(item[3]), str(item[4]))

    def close(self) -> None:
        """Close the connection; idempotent."""
        if self._db is not None:
            self._db.close()
            self._db = None

    @property
    def db(self) -> sqlite3.Connection:
        """The open connection."""
        if self._db is None:
            raise CampaignError("the store is not open")
        return self._db

    @contextlib.contextmanager
    def transaction(self, *, durable: bool = True) -> Iterator[sqlite3.Connection]:
        """``BEGIN IMMEDIATE`` ... ``COMMIT`` (``ROLLBACK`` on error).

        ``durable``: fsync the WAL on commit (``synchronous=FULL``); otherwise the commit
        survives a crash of the process but a power cut may roll it back (``NORMAL``).
        Transitions held in memory by a storage fault (see :meth:`transition`) are written
        first, in the same transaction, and always durably. A full disk or an I/O error
        raises :class:`StorageError`; the connection is left usable (rolled back).
        """
        db = self.db
        sync = "FULL" if durable or self._pending else "NORMAL"
        if sync != self._sync and not db.in_transaction:  # applies to the next transaction
            db.execute(f"PRAGMA synchronous={sync}")
            self._sync = sync
        try:
            if self.fault_hook is not None:
                self.fault_hook("begin")
            db.execute("BEGIN IMMEDIATE")
            try:
                flushed = self._write_pending(db)
                yield db
                if self.fault_hook is not None:
                    self.fault_hook("commit")
                db.execute("COMMIT")
            except BaseException:
                # SQLite may already have rolled back by itself (SQLITE_FULL, SQLITE_IOERR).
                if db.in_transaction:
                    with contextlib.suppress(sqlite3.Error):
                        db.execute("ROLLBACK")
                raise
        except sqlite3.Error as err:
            if not is_storage_fault(err):
                raise
            self.fault = f"{type(err).__name__}: {err}"
            raise StorageError(f"the store cannot write ({err}); free space or fix the disk, "
                               "then resume") from err
        for cid in flushed:
            self._pending.pop(cid, None)
        if flushed:
            self._write_held()
        self.fault = None

    # --- storage faults --------------------------------------------------------------------
    def _write_pending(self, db: sqlite3.Connection) -> list[str]:
        done = []
        for cid, (src, to, reason, actor, at) in list(self._pending.items()):
            row = db.execute("SELECT state FROM campaigns WHERE id=?", (cid,)).fetchone()
            if row is not None and row[0] == src.value:
                db.execute("UPDATE campaigns SET state=?, reason=?, updated=? WHERE id=?",
                           (to.value, reason, at, cid))
                db.execute(
                    "INSERT INTO transitions(campaign, at, from_state, to_state, reason, actor) "
                    "VALUES(?,?,?,?,?,?)", (cid, at, src.value, to.value, reason, actor))
            done.append(cid)
        return done

    @property
    def pending(self) -> dict[str, CampaignState]:
        """Campaign states known only in memory (their write hit a storage fault)."""
        return {cid: p[1] for cid, p in self._pending.items()}

    def probe(self) -> str | None:
        """Whether the store can write now: a synced page in a file next to the database and
        a row in it. Return None when both succeeded, else the fault (also :attr:`fault`).

        Called before any motion: a run whose measurements cannot be saved must not move the
        robot (a committed WAL page can be reused; the page file tells whether the disk
        itself still takes data).
        """
        page = b"\0" * 4096
        try:
            fd = os.open(self.path.parent / ".write-probe",
                         os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
            try:
                if os.write(fd, page) != len(page):
                    raise OSError(28, "No space left on device (short write)")
                os.fsync(fd)
            finally:
                os.close(fd)
            with self.transaction() as db:
                db.execute("INSERT OR REPLACE INTO meta(key, value) VALUES('write_probe', ?)",
                           (now_iso(),))
        except OSError as err:
            self.fault = f"{type(err).__name__}: {err}"
            return self.fault
        except StorageError:
            return self.fault
        return None

    def flush_pending(self) -> bool:
        """Try to write the transitions held in memory; True when none is left."""
        if self._pending:
            with contextlib.suppress(StorageError), self.transaction():
                pass
        return not self._pending

    # --- campaigns -------------------------------------------------------------------------
    def create_campaign(
        self,
        *,
        name: str,
        robot: str,
        poses: Sequence[PoseRow],
        plan_json: str,
        plan_digest: str,
        config_digest: str,
        actor: str,
        measure_only: bool = False,
        parent: str | None = None,
    ) -> CampaignSummary:
        """Insert a campaign in state ``created`` with its poses; return it.

        ``poses_total`` counts the poses to measure (via-points excluded). ``parent``: the
        journal key of the push or rollback whose verification run this is.
        """
        cid = uuid.uuid4().hex[:12]
        t = now_iso()
        with self.transaction() as db:
            db.execute(
                "INSERT INTO campaigns(id, name, created, updated, state, robot, poses_total, "
                "measure_only, plan_json, plan_digest, config_digest, created_by, parent) "
                "VALUES(?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (cid, name, t, t, CampaignState.CREATED.value, robot,
                 sum(1 for p in poses if p.measure),
                 int(measure_only), plan_json, plan_digest, config_digest, actor, parent),
            )
            db.executemany(
                "INSERT INTO poses(campaign, idx, purpose, measure, q_deg) VALUES(?,?,?,?,?)",
                [(cid, p.idx, p.purpose, int(p.measure), json.dumps(list(p.q_deg)))
                 for p in poses],
            )
            db.execute(
                "INSERT INTO transitions(campaign, at, from_state, to_state, reason, actor) "
                "VALUES(?,?,NULL,?,?,?)",
                (cid, t, CampaignState.CREATED.value, "created", actor),
            )
            self._audit(db, actor, "campaign.create", cid, None,
                        {"name": name, "poses": len(poses), "plan_digest": plan_digest})
        return self.campaign(cid)

    def _record(self, row: sqlite3.Row) -> CampaignSummary:
        n = self.db.execute(
            "SELECT COUNT(*) FROM measurements WHERE campaign=?", (row["id"],)
        ).fetchone()[0]
        # A measurement does not touch its campaign's row (one page less per pose): the last
        # one counts as the campaign's update here. Measurements are a prefix of the plan,
        # taken in order, so the last is the highest pose (found in the unique index; a
        # MAX(measured_at) reads every row: 2 ms at 10,000 measurements).
        last = self.db.execute(
            "SELECT measured_at FROM measurements WHERE campaign=? ORDER BY pose_idx DESC "
            "LIMIT 1", (row["id"],)).fetchone()
        state, reason = CampaignState(row["state"]), row["reason"]
        held = self._pending.get(row["id"])
        if held is not None:
            state, reason = held[1], f"{held[2]} (not yet saved: {self.fault or 'held'})"
        return CampaignSummary(
            id=row["id"], name=row["name"], created=row["created"],
            updated=max(row["updated"], last[0] if last else ""), state=state, reason=reason,
            robot=row["robot"],
            poses_total=int(row["poses_total"]), poses_measured=int(n),
            measure_only=bool(row["measure_only"]), plan_digest=row["plan_digest"],
            config_digest=row["config_digest"], selected_model=row["selected_model"],
            created_by=row["created_by"], verifies=row["parent"],
        )

    def campaign(self, cid: str) -> CampaignSummary:
        """Return one campaign; raise CampaignError (a LookupError too) when unknown."""
        row = self.db.execute("SELECT * FROM campaigns WHERE id=?", (cid,)).fetchone()
        if row is None:
            raise UnknownCampaign(f"no campaign {cid!r}")
        return self._record(row)

    def campaigns(self, *, states: Sequence[CampaignState] | None = None,
                  parent: str | None = None, children: bool = False) -> list[CampaignSummary]:
        """Return the operators' campaigns, oldest first, optionally only those in ``states``;
        with ``parent``, the verification runs of that journal key instead; with
        ``children``, both."""
        if children:
            rows = self.db.execute("SELECT * FROM campaigns ORDER BY created, rowid").fetchall()
        elif parent is None:
            rows = self.db.execute("SELECT * FROM campaigns WHERE parent IS NULL "
                                   "ORDER BY created, rowid").fetchall()
        else:
            rows = self.db.execute("SELECT * FROM campaigns WHERE parent=? "
                                   "ORDER BY created, rowid", (parent,)).fetchall()
        recs = [self._record(r) for r in rows]
        if states is not None:
            recs = [r for r in recs if r.state in states]
        return recs

    def plan_json(self, cid: str) -> str:
        """The plan document the campaign was created from."""
        row = self.db.execute("SELECT plan_json FROM campaigns WHERE id=?", (cid,)).fetchone()
        if row is None:
            raise UnknownCampaign(f"no campaign {cid!r}")
        return str(row[0])

    def transition(
        self,
        cid: str,
        to: CampaignState,
        *,
        actor: str,
        reason: str = "",
        only_from: Sequence[CampaignState] | None = None,
        selected_model: str | None = None,
        audit: tuple[str, dict[str, Any]] | None = None,
    ) -> CampaignSummary:
        """Move ``cid`` to state ``to`` atomically, checking the transition table.

        ``selected_model`` (when given) and the ``audit`` entry ``(action, detail)`` are
        stored in the same transaction, so an operator action is all there or not at all.

        A move to ``paused`` or ``faulted`` that hits a storage fault is held in memory
        (reads show it, the reason says it is not saved) and written with the next
        successful transaction; other transitions raise :class:`StorageError`.

        Raises
        ------
        InvalidTransition
            If the table (or ``only_from``) does not allow it from the current state.
        StorageError
            If the store cannot write and ``to`` is not a state that stops work.
        """
        try:
            return self._transition(cid, to, actor=actor, reason=reason, only_from=only_from,
                                    selected_model=selected_model, audit=audit)
        except StorageError:
            if to not in (CampaignState.PAUSED, CampaignState.FAULTED):
                raise
            current = self.campaign(cid).state
            check_transition(current, to)
            if only_from is not None and current not in only_from:
                raise InvalidTransition(current.value, to.value,
                                        "not from this state here") from None
            held = self._pending.get(cid)
            on_disk = held[0] if held is not None else current
            self._pending[cid] = (on_disk, to, reason, actor, now_iso())
            self._write_held()
            return self.campaign(cid)

    def _transition(self, cid: str, to: CampaignState, *, actor: str, reason: str,
                    only_from: Sequence[CampaignState] | None, selected_model: str | None,
                    audit: tuple[str, dict[str, Any]] | None) -> CampaignSummary:
        with self.transaction() as db:
            row = db.execute("SELECT state FROM campaigns WHERE id=?", (cid,)).fetchone()
            if row is None:
                raise UnknownCampaign(f"no campaign {cid!r}")
            src = CampaignState(row[0])
            check_transition(src, to)
            if only_from is not None and src not in only_from:
                raise InvalidTransition(src.value, to.value, "not from this state here")
            t = now_iso()
            db.execute(
                "UPDATE campaigns SET state=?, reason=?, updated=? WHERE id=?",
                (to.value, reason, t, cid),
            )
            db.execute(
                "INSERT INTO transitions(campaign, at, from_state, to_state, reason, actor) "
                "VALUES(?,?,?,?,?,?)",
                (cid, t, src.value, to.value, reason, actor),
            )
            if selected_model is not None:
                db.execute("UPDATE campaigns SET selected_model=? WHERE id=?",
                           (selected_model, cid))
            if audit is not None:
                self._audit(db, actor, audit[0], cid, None, audit[1])
        return self.campaign(cid)

    def transitions(self, cid: str) -> list[dict[str, Any]]:
        """The campaign's state history, oldest first."""
        rows = self.db.execute(
            "SELECT at, from_state, to_state, reason, actor FROM transitions WHERE campaign=? "
            "ORDER BY id", (cid,)).fetchall()
        return [dict(r) for r in rows]

    def set_selected_model(self, cid: str, model: str | None) -> None:
        """Record which fitted model is proposed for approval."""
        with self.transaction() as db:
            db.execute("UPDATE campaigns SET selected_model=?, updated=? WHERE id=?",
                       (model, now_iso(), cid))

    # --- poses and measurements ------------------------------------------------------------
    def poses(self, cid: str) -> list[PoseRow]:
        """The planned poses in order."""
        rows = self.db.execute(
            "SELECT idx, purpose, q_deg, measure FROM poses WHERE campaign=? ORDER BY idx",
            (cid,)).fetchall()
        return [PoseRow(int(r[0]), str(r[1]), tuple(json.loads(r[2])), bool(r[3]))
                for r in rows]

    def state(self, cid: str) -> CampaignState:
        """The campaign's state alone, as :meth:`campaign` reports it (a transition held in
        memory by a storage fault included), without counting its measurements: the runner
        asks before every pose."""
        held = self._pending.get(cid)
        if held is not None:
            return held[1]
        row = self.db.execute("SELECT state FROM campaigns WHERE id=?", (cid,)).fetchone()
        if row is None:
            raise UnknownCampaign(f"no campaign {cid!r}")
        return CampaignState(row[0])

    def measured_indices(self, cid: str) -> set[int]:
        """Indices of the poses already measured."""
        rows = self.db.execute(
            "SELECT pose_idx FROM measurements WHERE campaign=?", (cid,)).fetchall()
        return {int(r[0]) for r in rows}

    def add_measurement(self, cid: str, m: Measurement) -> bool:
        """Persist one measurement in its own transaction; False if the pose already has one.

        Not fsynced (see the module's docstring): a measurement lost to a power cut is
        measured again on resume, as the pose in progress at a kill -9 is.
        """
        try:
            with self.transaction(durable=False) as db:
                db.execute(
                    "INSERT INTO measurements(campaign, pose_idx, purpose, q_cmd_deg, q_act_deg, "
                    "x_mm, y_mm, z_mm, sx_mm, sy_mm, sz_mm, rms_mm, samples, attempts, "
                    "distance_mm, weather, measured_at, beam_losses, temps) "
                    "VALUES(?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                    (cid, m.pose_idx, m.purpose, _floats_json(m.q_cmd_deg),
                     _floats_json(m.q_act_deg), *m.p_mm,
                     *(m.sigma_mm if m.sigma_mm is not None else (None, None, None)),
                     m.rms_mm, m.samples, m.attempts, m.distance_mm, json.dumps(m.weather),
                     m.measured_at, m.beam_losses, _floats_json(m.temps_c)),
                )
        except sqlite3.IntegrityError:
            return False
        return True

    def measurements(self, cid: str) -> list[Measurement]:
        """Every measurement of the campaign, by pose index."""
        rows = self.db.execute(
            "SELECT * FROM measurements WHERE campaign=? ORDER BY pose_idx", (cid,)
        ).fetchall()
        out = []
        for r in rows:
            sig = None
            if r["sx_mm"] is not None:
                sig = (float(r["sx_mm"]), float(r["sy_mm"]), float(r["sz_mm"]))
            out.append(Measurement(
                pose_idx=int(r["pose_idx"]), purpose=r["purpose"],
                q_cmd_deg=tuple(json.loads(r["q_cmd_deg"])),
                q_act_deg=tuple(json.loads(r["q_act_deg"])),
                p_mm=(float(r["x_mm"]), float(r["y_mm"]), float(r["z_mm"])), sigma_mm=sig,
                rms_mm=r["rms_mm"], samples=int(r["samples"]), attempts=int(r["attempts"]),
                distance_mm=r["distance_mm"], weather=json.loads(r["weather"]),
                measured_at=r["measured_at"], beam_losses=int(r["beam_losses"]),
                temps_c=tuple(float(v) for v in json.loads(r["temps"])),
            ))
        return out

    #: Columns :meth:`measurement_columns` may read (SQL names of the measurements table).
    LIGHT_COLUMNS = frozenset({"pose_idx", "purpose", "rms_mm", "attempts", "beam_losses",
                               "measured_at", "q_act_deg", "x_mm", "y_mm", "z_mm"})

    def measurement_columns(self, cid: str, columns: Sequence[str]) -> list[tuple[Any, ...]]:
        """A few columns of every measurement, by pose index, undecoded (``q_act_deg`` stays
        JSON text): for displays that must stay fast with 10,000 measurements, where
        :meth:`measurements` decodes every field (about 50 µs a row).

        Raises
        ------
        ValueError
            If a column is not one of :attr:`LIGHT_COLUMNS`.
        """
        bad = set(columns) - self.LIGHT_COLUMNS
        if bad or not columns:
            raise ValueError(f"columns not readable here: {sorted(bad) or 'none given'}")
        rows = self.db.execute(
            f"SELECT {', '.join(columns)} FROM measurements WHERE campaign=? ORDER BY pose_idx",
            (cid,)).fetchall()
        return [tuple(r) for r in rows]

    # --- fits ------------------------------------------------------------------------------
    def save_fits(self, cid: str, fits: dict[str, tuple[dict[str, Any], str | None]]) -> None:
        """Store fit summaries and MODEL.json texts (replacing earlier ones), one transaction."""
        t = now_iso()
        with self.transaction() as db:
            for model, (summary, model_json) in fits.items():
                db.execute(
                    "INSERT OR REPLACE INTO fits(campaign, model, created, summary, model_json) "
                    "VALUES(?,?,?,?,?)", (cid, model, t, json.dumps(summary), model_json))

    def fits(self, cid: str) -> dict[str, dict[str, Any]]:
        """Fit summaries by model name."""
        rows = self.db.execute(
            "SELECT model, summary FROM fits WHERE campaign=? ORDER BY rowid", (cid,)).fetchall()
        return {str(r[0]): json.loads(r[1]) for r in rows}

    def model_json(self, cid: str, model: str) -> str | None:
        """The MODEL.json text of one fitted model, or None."""
        row = self.db.execute(
            "SELECT model_json FROM fits WHERE campaign=? AND model=?", (cid, model)).fetchone()
        return None if row is None else row[0]

    # --- compensation tables and the push history --------------------------------------------
    def add_table(self, *, campaign: str | None, origin: str, kind: str, checksum: str,
                  table_json: str) -> int:
        """Keep a table (every table ever pushed or read from the controller); return its id."""
        with self.transaction() as db:
            cur = db.execute(
                "INSERT INTO tables(campaign, created, origin, kind, checksum, table_json) "
                "VALUES(?,?,?,?,?,?)", (campaign, now_iso(), origin, kind, checksum, table_json))
            return int(cur.lastrowid or 0)

    def table(self, table_id: int) -> dict[str, Any]:
        """One stored table with its metadata (``table`` holds the JSON text)."""
        row = self.db.execute("SELECT * FROM tables WHERE id=?", (table_id,)).fetchone()
        if row is None:
            raise CampaignError(f"no compensation table {table_id}")
        return dict(row)

    def record_push(self, *, action: str, table_id: int, campaign: str | None, actor: str,
                    checksum: str, detail: dict[str, Any]) -> None:
        """Append to the push history and the audit log in one transaction."""
        with self.transaction() as db:
            db.execute(
                "INSERT INTO pushes(at, action, table_id, campaign, actor) VALUES(?,?,?,?,?)",
                (now_iso(), action, table_id, campaign, actor))
            self._audit(db, actor, f"compensation.{action}", campaign, checksum,
                        {"table_id": table_id, **detail})

    def table_stack(self) -> list[int]:
        """Table ids active on the controller over time; the last one is active now.

        ``push`` and ``baseline`` append; ``rollback`` removes the top (the table rolled back).
        """
        stack: list[int] = []
        for action, tid in self.db.execute("SELECT action, table_id FROM pushes ORDER BY id"):
            if action == "rollback":
                if stack:
                    stack.pop()
            else:
                stack.append(int(tid))
        return stack

    def pushes(self) -> list[dict[str, Any]]:
        """The push history, oldest first, with each table's kind and checksum."""
        rows = self.db.execute(
            "SELECT p.id, p.at, p.action, p.table_id, p.campaign, p.actor, t.kind, t.checksum, "
            "t.origin FROM pushes p JOIN tables t ON t.id = p.table_id ORDER BY p.id").fetchall()
        return [dict(r) for r in rows]

    # --- audit -----------------------------------------------------------------------------
    @staticmethod
    def _audit(db: sqlite3.Connection, actor: str, action: str, campaign: str | None,
               checksum: str | None, detail: dict[str, Any]) -> None:
        db.execute(
            "INSERT INTO audit(at, actor, action, campaign, checksum, detail) VALUES(?,?,?,?,?,?)",
            (now_iso(), actor, action, campaign, checksum, json.dumps(detail, default=str)))

    def audit(self, *, actor: str, action: str, campaign: str | None = None,
              checksum: str | None = None, detail: dict[str, Any] | None = None) -> None:
        """Append one audit entry (who, when, what, checksum) in its own transaction."""
        with self.transaction() as db:
            self._audit(db, actor, action, campaign, checksum, detail or {})

    def audit_log(self, *, limit: int = 1000) -> list[dict[str, Any]]:
        """The most recent audit entries, oldest first."""
        rows = self.db.execute(
            "SELECT * FROM (SELECT * FROM audit ORDER BY id DESC LIMIT ?) ORDER BY id",
            (limit,)).fetchall()
        out = []
        for r in rows:
            d = dict(r)
            d["detail"] = json.loads(d["detail"])
            out.append(d)
        return out
