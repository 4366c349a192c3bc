"""Fleet store: the cell's SQLite store replicated to a shared PostgreSQL (ADR 0035).

SQLite stays the cell's source of truth. Triggers in the SQLite file append the key of every
inserted, updated or deleted row of the replicated tables to ``fleet_outbox`` in the same
transaction as the change, so a change and its outbox entry are on disk together or not at
all. A background task of the daemon reads the outbox in order, reads the rows' current
contents and writes them to PostgreSQL in one transaction per batch, together with the
highest outbox sequence number applied (``robocal_cells.applied_seq``); only then are the
entries deleted from the outbox. A kill -9 or a lost connection at any point leaves either
the batch applied with its sequence number (its entries are skipped next time) or nothing;
rows are upserted by ``(cell_id, local_id)``, so applying one twice changes nothing.

PostgreSQL layout: ``robocal_cells`` (one row per cell: id, name, robot serial, applied
sequence) and one table ``robocal_<table>`` per replicated SQLite table with ``cell_id``,
``local_id`` (the SQLite primary key as text, ``/``-joined when composite), ``campaign`` and
``data`` (the whole row as JSONB; JSON text columns decoded). ``psycopg`` is imported only
when the fleet store is configured.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import socket
import sqlite3
import stat
import uuid
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from robocal.daemon.config import AppConfig, FleetConfig
from robocal.errors import ConfigError

if TYPE_CHECKING:
    import psycopg

__all__ = ["REPLICATED", "FleetReplicator", "detach", "fleet_report", "install",
           "read_password", "start_fleet"]

_log = structlog.get_logger(__name__)

#: SQLite tables replicated, in the order a first copy enqueues them: table -> (primary key
#: columns, mutable). Mutable tables are upserted; the others are append-only. ``checks``
#: is replicated once a store has it.
REPLICATED: dict[str, tuple[tuple[str, ...], bool]] = {
    "campaigns": (("id",), True),
    "transitions": (("id",), False),
    "measurements": (("id",), False),
    "fits": (("campaign", "model"), True),
    "tables": (("id",), False),
    "pushes": (("id",), False),
    "checks": (("id",), True),
    "audit": (("id",), False),
}

#: Campaign columns whose change is replicated (``updated`` alone changes with every
#: measurement; the campaign's plan is not sent again for each one).
_CAMPAIGN_COLUMNS = "state, reason, selected_model, name, parent"

_OUTBOX = ("CREATE TABLE IF NOT EXISTS fleet_outbox(seq INTEGER PRIMARY KEY AUTOINCREMENT, "
           "tbl TEXT NOT NULL, key TEXT NOT NULL)")

_CELL_ID_KEY = "fleet_cell_id"

#: libpq TCP keepalives (unless the URL sets them): a peer gone without a reset (a cable
#: pulled, a firewall dropping the session) is noticed within about 25 s.
_KEEPALIVE = {"keepalives": "1", "keepalives_idle": "10", "keepalives_interval": "5",
              "keepalives_count": "3"}

_PG_CELLS = """
CREATE TABLE IF NOT EXISTS robocal_cells(
    cell_id text PRIMARY KEY,
    cell_name text NOT NULL,
    robot_serial text NOT NULL,
    robot text NOT NULL,
    applied_seq bigint NOT NULL DEFAULT 0,
    first_seen timestamptz NOT NULL DEFAULT now(),
    last_seen timestamptz NOT NULL DEFAULT now()
)"""

_PG_TABLE = """
CREATE TABLE IF NOT EXISTS robocal_{tbl}(
    cell_id text NOT NULL REFERENCES robocal_cells(cell_id),
    local_id text NOT NULL,
    campaign text,
    data jsonb NOT NULL,
    replicated_at timestamptz NOT NULL DEFAULT now(),
    PRIMARY KEY(cell_id, local_id)
)"""


# --- the SQLite side -------------------------------------------------------------------------
def _connect(db_path: Path) -> sqlite3.Connection:
    db = sqlite3.connect(db_path, isolation_level=None, timeout=10.0)
    db.row_factory = sqlite3.Row
    db.execute("PRAGMA synchronous=FULL")
    return db


@contextlib.contextmanager
def _immediate(db: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    """``BEGIN IMMEDIATE`` ... ``COMMIT``, rolled back on any error."""
    db.execute("BEGIN IMMEDIATE")
    try:
        yield db
        db.execute("COMMIT")
    except BaseException:
        with contextlib.suppress(sqlite3.Error):  # a failed COMMIT may have ended it
            db.execute("ROLLBACK")
        raise


def _tables(db: sqlite3.Connection) -> list[str]:
    have = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    return [t for t in REPLICATED if t in have]


def _key_sql(row: str, cols: Sequence[str]) -> str:
    return "json_array(" + ", ".join(f"{row}.{c}" for c in cols) + ")"


def _trigger_sql(tbl: str) -> list[str]:
    cols, mutable = REPLICATED[tbl]
    out = [f"CREATE TRIGGER IF NOT EXISTS fleet_{tbl}_ins AFTER INSERT ON {tbl} BEGIN "
           f"INSERT INTO fleet_outbox(tbl, key) VALUES('{tbl}', {_key_sql('NEW', cols)}); END"]
    if mutable:
        of = f" OF {_CAMPAIGN_COLUMNS}" if tbl == "campaigns" else ""
        out.append(f"CREATE TRIGGER IF NOT EXISTS fleet_{tbl}_upd AFTER UPDATE{of} ON {tbl} "
                   f"BEGIN INSERT INTO fleet_outbox(tbl, key) "
                   f"VALUES('{tbl}', {_key_sql('NEW', cols)}); END")
        out.append(f"CREATE TRIGGER IF NOT EXISTS fleet_{tbl}_del AFTER DELETE ON {tbl} "
                   f"BEGIN INSERT INTO fleet_outbox(tbl, key) "
                   f"VALUES('{tbl}', {_key_sql('OLD', cols)}); END")
    return out


def _enqueue_all(db: sqlite3.Connection, tbl: str) -> None:
    cols = REPLICATED[tbl][0]
    db.execute(f"INSERT INTO fleet_outbox(tbl, key) SELECT '{tbl}', {_key_sql(tbl, cols)} "
               f"FROM {tbl} ORDER BY rowid")


def install(db_path: Path) -> str:
    """Create the outbox and its triggers in the store at ``db_path`` (idempotent); return
    the cell id kept in the store.

    A table that gets its triggers here has all its rows enqueued in the same transaction,
    so a store that existed before the fleet was configured (or a table added by a later
    schema) is copied whole, and nothing written meanwhile is missed.
    """
    db = _connect(db_path)
    try:
        with _immediate(db):
            db.execute(_OUTBOX)
            have = {r[0] for r in db.execute(
                "SELECT name FROM sqlite_master WHERE type='trigger'")}
            for tbl in _tables(db):
                if f"fleet_{tbl}_ins" not in have:
                    for sql in _trigger_sql(tbl):
                        db.execute(sql)
                    _enqueue_all(db, tbl)
            row = db.execute("SELECT value FROM meta WHERE key=?", (_CELL_ID_KEY,)).fetchone()
            if row is None:
                cell_id = str(uuid.uuid4())
                db.execute("INSERT INTO meta(key, value) VALUES(?, ?)", (_CELL_ID_KEY, cell_id))
            else:
                cell_id = str(row[0])
    finally:
        db.close()
    return cell_id


def detach(db_path: Path) -> bool:
    """Remove the triggers and empty the outbox (the fleet store is off); True if there were
    any. The outbox keeps its sequence, so a later :func:`install` numbers on from there."""
    db = _connect(db_path)
    try:
        names = [r[0] for r in db.execute(
            "SELECT name FROM sqlite_master WHERE type='trigger' AND name LIKE 'fleet\\_%' "
            "ESCAPE '\\'")]
        if not names:
            return False
        with _immediate(db):
            for name in names:
                db.execute(f'DROP TRIGGER IF EXISTS "{name}"')
            db.execute("DELETE FROM fleet_outbox")
        return True
    finally:
        db.close()


def _finite(value: Any) -> Any:
    """``value`` as JSONB takes it: NaN and infinities made None, NUL characters replaced."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, str):
        return value.replace("\x00", "\ufffd")
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def _row_json(row: sqlite3.Row) -> dict[str, Any]:
    """A SQLite row as a JSON object; text columns holding JSON (``*_json``, joint lists,
    weather, joint temperatures, summaries, details) are decoded."""
    out: dict[str, Any] = {}
    for k in row.keys():  # noqa: SIM118 - sqlite3.Row is not a mapping
        v = row[k]
        if isinstance(v, bytes):
            v = v.hex()
        elif isinstance(v, str) and v[:1] in "[{" and (
                k.endswith("_json") or k.startswith("q_") or k in _JSON_COLUMNS):
            with contextlib.suppress(ValueError):
                v = json.loads(v)
        out[k] = _finite(v)
    return out


_JSON_COLUMNS = frozenset({"weather", "temps", "summary", "detail"})


@dataclass(frozen=True)
class _Change:
    seq: int
    tbl: str
    local_id: str
    campaign: str | None
    data: dict[str, Any] | None  # None: the row is gone


def _read_batch(db: sqlite3.Connection, limit: int) -> list[_Change]:
    """The oldest ``limit`` outbox entries, in order, each with its row's current contents
    (one snapshot; ``data`` None when the row is gone)."""
    db.execute("BEGIN")
    try:
        entries = db.execute("SELECT seq, tbl, key FROM fleet_outbox ORDER BY seq LIMIT ?",
                             (limit,)).fetchall()
        rows: dict[tuple[str, str], tuple[str, str | None, dict[str, Any] | None]] = {}
        out: list[_Change] = []
        for seq, tbl, key in entries:
            if tbl not in REPLICATED:
                out.append(_Change(int(seq), "", "", None, None))  # a later robocal's table
                continue
            if (tbl, key) not in rows:
                cols = REPLICATED[tbl][0]
                values = json.loads(key)
                where = " AND ".join(f"{c}=?" for c in cols)
                row = db.execute(f"SELECT * FROM {tbl} WHERE {where}", values).fetchone()
                data = None if row is None else _row_json(row)
                campaign = None if data is None else data.get(
                    "id" if tbl == "campaigns" else "campaign")
                rows[tbl, key] = ("/".join(str(v) for v in values),
                                  None if campaign is None else str(campaign), data)
            local_id, campaign, data = rows[tbl, key]
            out.append(_Change(int(seq), tbl, local_id, campaign, data))
        return out
    finally:
        db.execute("COMMIT")


def _unique(changes: Iterable[_Change]) -> list[_Change]:
    """The first change of each row (all carry the row's newest contents)."""
    seen: set[tuple[str, str]] = set()
    out = []
    for c in changes:
        if c.tbl and (c.tbl, c.local_id) not in seen:
            seen.add((c.tbl, c.local_id))
            out.append(c)
    return out


# --- the PostgreSQL side ---------------------------------------------------------------------
def _pg() -> Any:
    try:
        import psycopg
    except ImportError as err:  # pragma: no cover - a dependency of robocal
        raise ConfigError("the fleet store needs psycopg (pip install 'psycopg[binary]')",
                          source="fleet.url") from err
    return psycopg


def read_password(path: Path) -> str:
    """The database password in ``path`` (stripped); the file must be its owner's alone.

    The mode is checked on the descriptor the password is read from, so the file cannot be
    swapped between the check and the read.

    Raises
    ------
    ConfigError
        If the file cannot be read or group or others may read or write it.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError as err:
        raise ConfigError(f"cannot read password file: {err}", source=str(path)) from err
    with os.fdopen(fd, "rb") as f:
        mode = stat.S_IMODE(os.fstat(fd).st_mode)
        if mode & 0o077:
            raise ConfigError(f"password file has mode {mode:04o}: group or others may read "
                              "or change it; chmod 600 (owned by the daemon's user)",
                              source=str(path))
        try:
            return f.read(65536).decode("utf-8").strip()
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"cannot read password file: {err}", source=str(path)) from err


def _password(cfg: FleetConfig) -> str | None:
    return None if cfg.password_file is None else read_password(cfg.password_file)


def _params(psycopg: Any, cfg: FleetConfig, application: str) -> dict[str, Any]:
    """Connection parameters: the URL's, then defaults (keepalives, connect timeout, the
    application name PostgreSQL shows), the password from its file."""
    params: dict[str, Any] = {**_KEEPALIVE, "connect_timeout": str(max(1, round(
        cfg.connect_timeout_s))), "application_name": application,
        **psycopg.conninfo.conninfo_to_dict(cfg.url)}
    password = _password(cfg)
    if password is not None:
        params["password"] = password
    return params


async def _ensure_schema(conn: psycopg.AsyncConnection[Any]) -> None:
    async with conn.transaction():
        # one creator at a time: CREATE TABLE IF NOT EXISTS races between sessions
        await conn.execute("SELECT pg_advisory_xact_lock(3503500)")
        await conn.execute(_PG_CELLS)
        for tbl in REPLICATED:
            await conn.execute(_PG_TABLE.format(tbl=tbl))


class FleetReplicator:
    """Copies one store's outbox to PostgreSQL, in order, until stopped.

    Parameters
    ----------
    db_path : Path
        The SQLite store (the daemon's ``robocal.sqlite3``).
    config : FleetConfig
        With ``url`` and ``robot_serial`` set.
    robot : str
        The robot description's name (shown in the fleet report).
    """

    def __init__(self, db_path: Path, config: FleetConfig, *, robot: str) -> None:
        if config.url is None or not config.robot_serial:
            raise ConfigError("the fleet store needs fleet.url and fleet.robot_serial")
        self.db_path = Path(db_path)
        self.config = config
        self.robot = robot
        self.cell_name = config.cell_name or socket.gethostname()
        self.cell_id = ""
        #: The last connection or replication error (None after a successful batch).
        self.last_error: str | None = None
        #: Outbox entries applied by this replicator, and sessions it opened (for tests).
        self.applied = 0
        self.sessions = 0
        self._stop = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    # --- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        """Install the outbox and start the background task. A store that cannot take the
        outbox now (a full disk) does not stop the daemon: the task tries again."""
        try:
            self.cell_id = install(self.db_path)
        except sqlite3.Error as err:
            self.last_error = f"{type(err).__name__}: {err}"
            _log.warning("fleet outbox not installed yet", error=self.last_error)
        self._task = asyncio.create_task(self.run(), name="fleet-replication")

    async def stop(self) -> None:
        """Stop the task; a batch in flight is abandoned (applied later, never twice)."""
        self._stop.set()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
            self._task = None

    def pending(self) -> int:
        """Outbox entries not yet replicated (0 before :meth:`start`)."""
        db = _connect(self.db_path)
        try:
            return int(db.execute("SELECT COUNT(*) FROM fleet_outbox").fetchone()[0])
        except sqlite3.OperationalError:
            return 0
        finally:
            db.close()

    async def run(self) -> None:
        """Connect, replicate, and on any database or network error wait and start again
        (``backoff_s`` doubling up to ``max_backoff_s``)."""
        psycopg = _pg()
        delay = self.config.backoff_s
        while not self._stop.is_set():
            try:
                if not self.cell_id:
                    self.cell_id = install(self.db_path)
                await self._session(psycopg)
            except (psycopg.Error, OSError, sqlite3.Error, ConfigError) as err:
                self.last_error = f"{type(err).__name__}: {err}".strip()
                _log.warning("fleet replication interrupted", error=self.last_error,
                             retry_in_s=delay)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(delay):
                        await self._stop.wait()
                delay = min(2 * delay, self.config.max_backoff_s)
            else:
                delay = self.config.backoff_s

    async def _session(self, psycopg: Any) -> None:
        cfg = self.config
        conn = await psycopg.AsyncConnection.connect(**_params(psycopg, cfg, "robocal-fleet"))
        db = _connect(self.db_path)
        try:
            self.sessions += 1
            await _ensure_schema(conn)
            await self._register(conn, db)
            _log.info("fleet replication connected", cell_id=self.cell_id,
                      pending=self.pending())
            while not self._stop.is_set():
                # a connection that went silent (no reset) is given up after this long
                async with asyncio.timeout(max(30.0, 3 * cfg.connect_timeout_s)):
                    done = await self.replicate_once(conn, db)
                if done:
                    continue
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(cfg.poll_s):
                        await self._stop.wait()
        finally:
            db.close()
            with contextlib.suppress(Exception):
                await conn.close()

    async def _register(self, conn: psycopg.AsyncConnection[Any], db: sqlite3.Connection
                        ) -> None:
        """Create or update this cell's row.

        If the fleet has applied more of this cell's outbox than the store ever numbered,
        the store is an older copy (restored from a backup) whose new rows would reuse local
        ids the fleet already holds: it becomes a new cell (a new id, the same serial) and
        is copied whole; the old cell's rows stay in the fleet as history.
        """
        applied = await self._upsert_cell(conn)
        local = db.execute("SELECT seq FROM sqlite_sequence WHERE name='fleet_outbox'"
                           ).fetchone()
        if applied <= (int(local[0]) if local else 0):
            return
        old, self.cell_id = self.cell_id, str(uuid.uuid4())
        _log.warning("the fleet holds more of this cell than its store (restored from a "
                     "backup?): replicating it as a new cell", old_cell_id=old,
                     cell_id=self.cell_id, applied_seq=applied)
        with _immediate(db):
            db.execute("DELETE FROM fleet_outbox")
            db.execute("UPDATE meta SET value=? WHERE key=?", (self.cell_id, _CELL_ID_KEY))
            for tbl in _tables(db):
                _enqueue_all(db, tbl)
        await self._upsert_cell(conn)

    async def _upsert_cell(self, conn: psycopg.AsyncConnection[Any]) -> int:
        """Insert or refresh this cell's row; return its applied sequence number."""
        async with conn.transaction():
            cur = await conn.execute(
                "INSERT INTO robocal_cells(cell_id, cell_name, robot_serial, robot) "
                "VALUES(%s, %s, %s, %s) ON CONFLICT (cell_id) DO UPDATE SET "
                "cell_name=EXCLUDED.cell_name, robot_serial=EXCLUDED.robot_serial, "
                "robot=EXCLUDED.robot, last_seen=now() RETURNING applied_seq",
                (self.cell_id, self.cell_name, self.config.robot_serial, self.robot))
            row = await cur.fetchone()
        return int(row[0]) if row else 0

    async def replicate_once(self, conn: psycopg.AsyncConnection[Any],
                             db: sqlite3.Connection) -> int:
        """Apply one batch of the outbox; return the number of entries it covered."""
        batch = _read_batch(db, self.config.batch_rows)
        if not batch:
            return 0
        last = batch[-1].seq
        async with conn.transaction():
            cur = await conn.execute(
                "SELECT applied_seq FROM robocal_cells WHERE cell_id=%s FOR UPDATE",
                (self.cell_id,))
            row = await cur.fetchone()
            applied = int(row[0]) if row else 0
            await self._apply(conn, _unique(c for c in batch if c.seq > applied))
            if last > applied:
                await conn.execute(
                    "UPDATE robocal_cells SET applied_seq=%s, last_seen=now() "
                    "WHERE cell_id=%s", (last, self.cell_id))
        # after the commit; a crash here leaves entries the next batch skips by sequence
        db.execute("DELETE FROM fleet_outbox WHERE seq <= ?", (last,))
        self.applied += len(batch)
        self.last_error = None
        return len(batch)

    async def _apply(self, conn: psycopg.AsyncConnection[Any], todo: Iterable[_Change]
                     ) -> None:
        by_table: dict[str, list[_Change]] = {}
        for c in todo:
            by_table.setdefault(c.tbl, []).append(c)
        async with conn.cursor() as cur:
            for tbl, changes in by_table.items():
                mutable = REPLICATED[tbl][1]
                gone = [(self.cell_id, c.local_id) for c in changes if c.data is None]
                rows = [(self.cell_id, c.local_id, c.campaign, json.dumps(c.data))
                        for c in changes if c.data is not None]
                if rows:
                    conflict = ("DO UPDATE SET campaign=EXCLUDED.campaign, data=EXCLUDED.data, "
                                "replicated_at=now()" if mutable else "DO NOTHING")
                    await cur.executemany(
                        f"INSERT INTO robocal_{tbl}(cell_id, local_id, campaign, data) "
                        f"VALUES(%s, %s, %s, %s::jsonb) ON CONFLICT (cell_id, local_id) "
                        f"{conflict}", rows)
                if gone:
                    await cur.executemany(
                        f"DELETE FROM robocal_{tbl} WHERE cell_id=%s AND local_id=%s", gone)


def start_fleet(config: AppConfig, *, robot: str) -> FleetReplicator | None:
    """The daemon's hook: start replicating when ``fleet.url`` is set (call inside the event
    loop, after the store is open); otherwise remove the outbox triggers of an earlier
    configuration and return None."""
    if config.fleet.url is None:
        try:
            if config.db_path.exists() and detach(config.db_path):
                _log.info("fleet store off: outbox triggers removed")
        except sqlite3.Error as err:  # a full disk: the next start tries again
            _log.warning("fleet outbox triggers not removed", error=str(err))
        return None
    rep = FleetReplicator(config.db_path, config.fleet, robot=robot)
    rep.start()
    return rep


# --- the fleet report --------------------------------------------------------------------------
def _pick(data: Mapping[str, Any], *names: str) -> Any:
    for n in names:
        if data.get(n) is not None:
            return data[n]
    return None


def _held_out_rms(summary: Any) -> float | None:
    if not isinstance(summary, dict):
        return None
    part = summary.get("validation") or summary.get("train") or {}
    v = part.get("rms_mm") if isinstance(part, dict) else None
    return float(v) if isinstance(v, int | float) else None


def _active(pushes: Sequence[Mapping[str, Any]]) -> int | None:
    """The table id on the controller after ``pushes`` (oldest first)."""
    stack: list[int] = []
    for p in pushes:
        if p.get("action") == "rollback":
            if stack:
                stack.pop()
        else:
            stack.append(int(p["table_id"]))
    return stack[-1] if stack else None


def _robot_entry(cells: list[dict[str, Any]], rows: Mapping[str, list[dict[str, Any]]]
                 ) -> dict[str, Any]:
    """One robot's fleet summary from its cells' replicated rows."""
    campaigns = sorted(rows["campaigns"], key=lambda d: str(d.get("created") or ""))
    fits = {(d["_cell"], d.get("campaign"), d.get("model")): d for d in rows["fits"]}
    calib = None
    for c in reversed(campaigns):
        if (c.get("parent") is None and not c.get("measure_only")
                and c.get("state") in ("fitted", "approved", "pushed")):
            model = c.get("selected_model")
            fit = fits.get((c["_cell"], c.get("id"), model), {})
            calib = {"campaign": c.get("id"), "name": c.get("name"), "at": c.get("created"),
                     "state": c.get("state"), "model": model,
                     "held_out_rms_mm": _held_out_rms(fit.get("summary")),
                     "cell_id": c.get("_cell")}
            break
    # checks still measuring have no result yet (robocal check, ADR 0041)
    checks = sorted((d for d in rows["checks"] if d.get("state") != "measuring"),
                    key=lambda d: str(_pick(d, "created", "at") or ""))
    trend = [{"at": _pick(d, "created", "at"),
              "rms_mm": _pick(d, "rms_mm", "held_out_rms_mm"),
              "verdict": _pick(d, "verdict", "result", "status"),
              "recommendation": d.get("recommendation")} for d in checks]
    active = None
    for cell in cells:  # the cell seen most recently holds the robot now
        pushes = sorted((p for p in rows["pushes"] if p["_cell"] == cell["cell_id"]),
                        key=lambda p: int(p["id"]))
        tid = _active(pushes)
        if tid is not None:
            table = next((t for t in rows["tables"] if t["_cell"] == cell["cell_id"]
                          and int(t["id"]) == tid), {})
            active = {"table_id": tid, "kind": table.get("kind"),
                      "checksum": table.get("checksum"), "campaign": table.get("campaign"),
                      "origin": table.get("origin"), "since": pushes[-1].get("at"),
                      "cell_id": cell["cell_id"]}
        break
    return {
        "robot_serial": cells[0]["robot_serial"],
        "robot": cells[0]["robot"],
        "cells": [{k: (v.isoformat() if hasattr(v, "isoformat") else v) for k, v in c.items()}
                  for c in cells],
        "campaigns": len(campaigns),
        "last_calibration": calib,
        "last_check": trend[-1] if trend else None,
        "drift_trend": trend,
        "active_compensation": active,
    }


def fleet_report(url: str, *, password_file: Path | None = None) -> list[dict[str, Any]]:
    """Every robot in the fleet database by serial: last calibration, last check, the
    checks' trend and the active compensation (see ``robocal fleet report``)."""
    psycopg = _pg()
    cfg = FleetConfig(url=url, robot_serial="-", password_file=password_file)
    with psycopg.connect(**_params(psycopg, cfg, "robocal-fleet-report")) as conn:
        have = {r[0] for r in conn.execute(
            "SELECT table_name FROM information_schema.tables WHERE table_schema = "
            "current_schema() AND table_name LIKE 'robocal\\_%'")}
        if "robocal_cells" not in have:
            return []
        cur = conn.execute("SELECT cell_id, cell_name, robot_serial, robot, first_seen, "
                           "last_seen FROM robocal_cells ORDER BY robot_serial, last_seen DESC")
        names = [d.name for d in cur.description or []]
        cells = [dict(zip(names, r, strict=True)) for r in cur.fetchall()]
        by_serial: dict[str, list[dict[str, Any]]] = {}
        for c in cells:
            by_serial.setdefault(c["robot_serial"], []).append(c)
        out = []
        for serial_cells in by_serial.values():
            ids = [c["cell_id"] for c in serial_cells]
            rows: dict[str, list[dict[str, Any]]] = {}
            for tbl in ("campaigns", "fits", "checks", "pushes", "tables"):
                if f"robocal_{tbl}" not in have:
                    rows[tbl] = []
                    continue
                data = {"tables": "data - 'table_json'", "fits": "data - 'model_json'",
                        "campaigns": "data - 'plan_json'"}.get(tbl, "data")
                got = conn.execute(f"SELECT cell_id, {data} FROM robocal_{tbl} "
                                   "WHERE cell_id = ANY(%s)", (ids,)).fetchall()
                rows[tbl] = [{**d, "_cell": cid} for cid, d in got]
            out.append(_robot_entry(serial_cells, rows))
        return out
