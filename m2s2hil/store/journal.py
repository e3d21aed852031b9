"""The session journal: one SQLite database per session (WAL, synchronous=FULL).

Tables:

- ``meta``: schema version.
- ``session``: one row: id, satellite, build, sweep JSON, rig JSON, rig digest, software
  version, state, created/updated (epoch seconds).
- ``events``: an append-only log (kind, payload JSON, time) of everything that happened.
- ``frames``: one row per committed frame (``event_id`` UNIQUE), its files (relative
  path, sha256, size) and its metadata JSON.
- ``darks``: one row per master dark (``dark_id`` UNIQUE) with its file.
- ``skips``: captures given up, with the reason and the fault class.

Every write is one transaction (``BEGIN IMMEDIATE`` … ``COMMIT``). A full disk inside
SQLite rolls the transaction back and raises :class:`DiskFull`. The connection is shared
between the engine's threads behind a lock.

A journal opened ``read_only`` uses SQLite's ``mode=ro`` (and ``immutable`` when no
``-wal`` file exists): it can never change the file nor add any beside it.
A damaged database (SQLite's "malformed" or "not a database") raises
:class:`JournalDamaged` wherever it is met; :meth:`Journal.check` runs ``PRAGMA
quick_check`` so an owner finds the damage before it writes anything.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from m2s2hil.atomic import DiskFull
from m2s2hil.errors import M2S2Error
from m2s2hil.store.frame_files import dumps

SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE session (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    session_id TEXT NOT NULL,
    satellite TEXT NOT NULL,
    build TEXT NOT NULL,
    sweep_json TEXT NOT NULL,
    rig_json TEXT NOT NULL,
    rig_digest TEXT NOT NULL,
    software_version TEXT NOT NULL,
    state TEXT NOT NULL,
    created REAL NOT NULL,
    updated REAL NOT NULL
);
CREATE TABLE events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    time REAL NOT NULL,
    kind TEXT NOT NULL,
    payload TEXT NOT NULL
);
CREATE TABLE frames (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    event_id TEXT NOT NULL UNIQUE,
    idx INTEGER NOT NULL,
    time REAL NOT NULL,
    dark_id TEXT,
    files TEXT NOT NULL,
    meta TEXT NOT NULL
);
CREATE TABLE darks (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    dark_id TEXT NOT NULL UNIQUE,
    exposure_s REAL NOT NULL,
    gain REAL NOT NULL,
    n_frames INTEGER NOT NULL,
    reduce TEXT NOT NULL,
    time REAL NOT NULL,
    files TEXT NOT NULL,
    meta TEXT NOT NULL
);
CREATE TABLE skips (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    event_id TEXT NOT NULL,
    idx INTEGER NOT NULL,
    time REAL NOT NULL,
    reason TEXT NOT NULL,
    fault_class TEXT NOT NULL
);
CREATE INDEX skips_event ON skips(event_id);
"""


class JournalError(M2S2Error):
    """The journal cannot be opened or read (missing, not a database, wrong schema)."""


class JournalDamaged(JournalError):
    """The journal's database is damaged (``quick_check`` fails, or SQLite says malformed);
    ``detail`` is what SQLite said."""

    def __init__(self, message: str, detail: str | None = None) -> None:
        super().__init__(message)
        self.detail = message if detail is None else detail


_DAMAGE_CODES = {11, 26}  # SQLITE_CORRUPT, SQLITE_NOTADB


def _is_damage(exc: sqlite3.Error) -> bool:
    code = getattr(exc, "sqlite_errorcode", None)
    if code is not None:
        return code & 0xFF in _DAMAGE_CODES
    text = str(exc)
    return "malformed" in text or "not a database" in text


class JournalClosed(JournalError):
    """The journal was closed (its session retired from memory); open the session again."""


class DuplicateEvent(M2S2Error):
    """An event that is already committed (or being written) was written again."""

    fault_class = "other"

    def __init__(self, event_id: str) -> None:
        self.event_id = event_id
        super().__init__(f"event {event_id!r} is already in the session; captures are never duplicated")


def _is_full(exc: sqlite3.Error) -> bool:
    code = getattr(exc, "sqlite_errorcode", None)
    return code == getattr(sqlite3, "SQLITE_FULL", 13) or "disk is full" in str(exc)


class Journal:
    def __init__(self, path: Path, *, create: bool = False, read_only: bool = False) -> None:
        self.path = Path(path)
        self.read_only = read_only and not create
        if not create and not self.path.is_file():
            raise JournalError(f"{self.path}: no journal")
        self._lock = threading.RLock()
        immutable = False
        try:
            if self.read_only:
                # No -wal file: everything is in the main file, read it as immutable so that no
                # -wal/-shm appear either. A -wal file (a live or a killed writer's) is read too.
                # An archived session in a folder we cannot write is immutable as well: WAL would
                # need to create its -shm file there (and no writer can change such a folder).
                immutable = (not Path(f"{self.path}-wal").exists()
                             or not os.access(self.path.parent, os.W_OK))
                uri = f"{self.path.resolve().as_uri()}?mode=ro" + ("&immutable=1" if immutable else "")
                self._db = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False,
                                           timeout=30)
            else:
                self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False,
                                           timeout=30)
            self._db.row_factory = sqlite3.Row
            if self.read_only:  # a read-only connection can only report the mode
                mode = self._db.execute("PRAGMA journal_mode").fetchone()[0]
            else:
                mode = self._db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
                self._db.execute("PRAGMA synchronous=FULL")
            if create:
                self._db.executescript(_SCHEMA)
                self._db.execute("INSERT INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
            row = self._db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        except sqlite3.DatabaseError as exc:
            self.close()
            if _is_damage(exc):
                raise JournalDamaged(f"{self.path}: journal damaged ({exc})", str(exc)) from None
            raise JournalError(f"{self.path}: not a readable session journal ({exc})") from None
        if mode.lower() != "wal" and not (self.read_only and immutable):  # immutable reports "delete"
            self.close()
            raise JournalError(f"{self.path}: cannot switch the journal to WAL mode (got {mode})")
        if row is None or row[0] != str(SCHEMA_VERSION):
            self.close()
            raise JournalError(f"{self.path}: journal schema {row[0] if row else '?'} is not "
                               f"{SCHEMA_VERSION}")

    # -------------------------------------------------------------- plumbing
    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            db = self._open_db()
            try:
                db.execute("BEGIN IMMEDIATE")
            except sqlite3.OperationalError as exc:
                if _is_full(exc):
                    raise DiskFull(self.path.parent, detail=str(exc)) from exc
                raise
            try:
                yield db
                db.execute("COMMIT")
            except BaseException as exc:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                if isinstance(exc, sqlite3.OperationalError) and _is_full(exc):
                    raise DiskFull(self.path.parent, detail=str(exc)) from exc
                if isinstance(exc, sqlite3.DatabaseError) and _is_damage(exc):
                    raise JournalDamaged(f"{self.path}: journal damaged ({exc})", str(exc)) from None
                raise

    def query(self, sql: str, args: tuple = ()) -> list[sqlite3.Row]:
        with self._lock:
            try:
                return self._open_db().execute(sql, args).fetchall()
            except sqlite3.DatabaseError as exc:
                if _is_damage(exc):
                    raise JournalDamaged(f"{self.path}: journal damaged ({exc})", str(exc)) from None
                raise

    def pragma(self, name: str) -> Any:
        with self._lock:
            return self._open_db().execute(f"PRAGMA {name}").fetchone()[0]

    def check(self) -> str | None:
        """``PRAGMA quick_check``: None when the database is sound, else what is wrong
        (first lines). Catches the damage a query of the session row would not touch."""
        with self._lock:
            try:
                rows = [r[0] for r in self._open_db().execute("PRAGMA quick_check(5)").fetchall()]
            except sqlite3.DatabaseError as exc:
                return str(exc)
        return None if rows == ["ok"] else "; ".join(str(r) for r in rows)

    def _open_db(self) -> sqlite3.Connection:
        """The connection (the caller holds the lock); :class:`JournalClosed` once closed."""
        db = self._db
        if db is None:
            raise JournalClosed(f"{self.path}: journal closed")
        return db

    def reopen_read_only(self) -> None:
        """Swap the connection for a read-only one in place: a reader holding this journal
        keeps reading (swapping the object left one querying a closed connection)."""
        fresh = Journal(self.path, read_only=True)
        with self._lock:
            old, self._db = self._db, fresh._db
            fresh._db = None  # type: ignore[assignment]
            self.read_only = True
            if old is not None:
                old.close()

    def close(self) -> None:
        lock = getattr(self, "_lock", None)
        if lock is None:  # failed before the lock existed
            return
        with lock:
            db = getattr(self, "_db", None)
            self._db = None  # type: ignore[assignment]
            if db is not None:
                db.close()

    # -------------------------------------------------------------- session row
    def init_session(self, *, session_id: str, satellite: str, build: str, sweep_json: str, rig_json: str,
                     rig_digest: str, software_version: str, state: str, now: float) -> None:
        with self.transaction() as db:
            db.execute(
                "INSERT INTO session VALUES (1, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (session_id, satellite, build, sweep_json, rig_json, rig_digest, software_version, state,
                 now, now),
            )
            db.execute("INSERT INTO events (time, kind, payload) VALUES (?, 'created', ?)",
                       (now, dumps({"session_id": session_id, "state": state})))

    def session(self) -> sqlite3.Row:
        rows = self.query("SELECT * FROM session WHERE id = 1")
        if not rows:
            raise JournalError(f"{self.path}: journal has no session row")
        return rows[0]

    def set_state(self, state: str, now: float) -> None:
        with self.transaction() as db:
            db.execute("UPDATE session SET state = ?, updated = ? WHERE id = 1", (state, now))
            db.execute("INSERT INTO events (time, kind, payload) VALUES (?, 'state', ?)",
                       (now, dumps({"state": state})))

    # -------------------------------------------------------------- records
    def add_event(self, kind: str, payload: dict, now: float) -> int:
        with self.transaction() as db:
            cur = db.execute("INSERT INTO events (time, kind, payload) VALUES (?, ?, ?)",
                             (now, kind, dumps(payload)))
            db.execute("UPDATE session SET updated = ? WHERE id = 1", (now,))
            return int(cur.lastrowid)

    def add_frame(self, *, event_id: str, idx: int, dark_id: str | None, files: dict, meta: dict,
                  now: float) -> None:
        try:
            with self.transaction() as db:
                db.execute(
                    "INSERT INTO frames (event_id, idx, time, dark_id, files, meta) "
                    "VALUES (?, ?, ?, ?, ?, ?)",
                    (event_id, idx, now, dark_id, dumps(files), dumps(meta)),
                )
                db.execute("INSERT INTO events (time, kind, payload) VALUES (?, 'frame', ?)",
                           (now, dumps({"event_id": event_id, "index": idx})))
                db.execute("UPDATE session SET updated = ? WHERE id = 1", (now,))
        except sqlite3.IntegrityError:
            raise DuplicateEvent(event_id) from None

    def add_dark(self, *, dark_id: str, exposure_s: float, gain: float, n_frames: int, reduce: str,
                 files: dict, meta: dict, now: float) -> None:
        try:
            with self.transaction() as db:
                db.execute(
                    "INSERT INTO darks (dark_id, exposure_s, gain, n_frames, reduce, time, files, meta) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    (dark_id, exposure_s, gain, n_frames, reduce, now, dumps(files), dumps(meta)),
                )
                db.execute("INSERT INTO events (time, kind, payload) VALUES (?, 'dark', ?)",
                           (now, dumps({"dark_id": dark_id})))
                db.execute("UPDATE session SET updated = ? WHERE id = 1", (now,))
        except sqlite3.IntegrityError:
            raise DuplicateEvent(dark_id) from None

    def add_skip(self, *, event_id: str, idx: int, reason: str, fault_class: str, now: float) -> None:
        with self.transaction() as db:
            db.execute("INSERT INTO skips (event_id, idx, time, reason, fault_class) VALUES (?, ?, ?, ?, ?)",
                       (event_id, idx, now, reason, fault_class))
            db.execute("INSERT INTO events (time, kind, payload) VALUES (?, 'skip', ?)",
                       (now, dumps({"event_id": event_id, "reason": reason, "fault_class": fault_class})))
            db.execute("UPDATE session SET updated = ? WHERE id = 1", (now,))

    def remove_record(self, event_id: str, *, reason: str, now: float) -> dict | None:
        """Take a frame's or a dark's row out (its files failed verification), keeping the
        whole row in a ``quarantined`` event; the event is then pending again."""
        with self.transaction() as db:
            for table, key in (("frames", "event_id"), ("darks", "dark_id")):
                row = db.execute(f"SELECT * FROM {table} WHERE {key} = ?", (event_id,)).fetchone()
                if row is None:
                    continue
                kept = dict(zip(row.keys(), tuple(row), strict=True))
                db.execute(f"DELETE FROM {table} WHERE {key} = ?", (event_id,))
                db.execute("INSERT INTO events (time, kind, payload) VALUES (?, 'quarantined', ?)",
                           (now, dumps({"event_id": event_id, "table": table, "reason": reason,
                                        "row": kept})))
                db.execute("UPDATE session SET updated = ? WHERE id = 1", (now,))
                return kept
        return None

    def is_completed(self, event_id: str) -> bool:
        return bool(self.query("SELECT 1 FROM frames WHERE event_id = ? UNION ALL "
                               "SELECT 1 FROM darks WHERE dark_id = ?", (event_id, event_id)))

    def completed_ids(self) -> set[str]:
        rows = self.query("SELECT event_id AS id FROM frames UNION SELECT dark_id AS id FROM darks")
        return {r["id"] for r in rows}

    def events(self, since: int = 0) -> list[dict]:
        rows = self.query("SELECT * FROM events WHERE seq > ? ORDER BY seq", (since,))
        return [dict(seq=r["seq"], time=r["time"], kind=r["kind"], payload=json.loads(r["payload"]))
                for r in rows]
