"""The historian's on-disk buffer: every row is here (fsync'd) before it goes to PostgreSQL.

SQLite in the state directory, WAL with ``synchronous=FULL`` (as the agent's journal): when
:meth:`Buffer.append` returns, the rows survive a killed process and a power cut. Rows leave
only through :meth:`Buffer.delete_through`, which the writer calls after PostgreSQL committed
them, or through :meth:`Buffer.set_aside` when PostgreSQL refuses a row itself (kept, with the
error, in the ``set_aside`` table). Ids grow and are never reused (AUTOINCREMENT), and each
buffer file has its own random ``buffer_id``: PostgreSQL keeps the highest id written per
buffer, so a batch committed but not yet deleted here (the process died in between) is skipped
when it is sent again.

The last recorded state of each drive (:class:`agent.historian.ingest.Last`) is stored in the
same transaction as the rows it produced, so a restart neither repeats nor misses a change.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
import time
import uuid
from pathlib import Path

from agent.historian.ingest import Identity, Last

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS pending (
    id    INTEGER PRIMARY KEY AUTOINCREMENT,
    tbl   TEXT NOT NULL,
    row   TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS set_aside (
    id     INTEGER PRIMARY KEY,
    tbl    TEXT NOT NULL,
    row    TEXT NOT NULL,
    error  TEXT NOT NULL,
    t      REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS drive_last (
    site TEXT NOT NULL, gateway TEXT NOT NULL, drive TEXT NOT NULL,
    state INTEGER NOT NULL, quality INTEGER NOT NULL, reason_key TEXT, trend_t REAL,
    PRIMARY KEY (site, gateway, drive)
);
"""


class Buffer:
    """Durable FIFO of rows for PostgreSQL plus each drive's :class:`Last`; thread-safe."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute("PRAGMA busy_timeout=2000")
        self._db.executescript(_SCHEMA)
        self._db.execute("INSERT OR IGNORE INTO meta VALUES ('buffer_id', ?)", (uuid.uuid4().hex,))
        self.buffer_id: str = self._db.execute("SELECT value FROM meta WHERE key='buffer_id'").fetchone()[0]

    def load_last(self) -> dict[Identity, Last]:
        with self._lock:
            rows = self._db.execute("SELECT site, gateway, drive, state, quality, reason_key, trend_t "
                                    "FROM drive_last").fetchall()
        return {(s, g, d): Last(*rest) for s, g, d, *rest in rows}

    def append(self, rows: list[tuple[str, dict]], ident: Identity, last: Last) -> None:
        """Store ``rows`` (``(table, row)``) and the drive's new ``last`` in one fsync'd transaction."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.executemany("INSERT INTO pending(tbl, row) VALUES (?, ?)",
                                     [(tbl, json.dumps(row, default=str)) for tbl, row in rows])
                self._db.execute("INSERT OR REPLACE INTO drive_last VALUES (?,?,?,?,?,?,?)",
                                 (*ident, last.state, last.quality, last.reason_key, last.trend_t))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

    def oldest(self, limit: int) -> list[tuple[int, str, dict]]:
        """Up to ``limit`` rows, oldest first: ``(id, table, row)``."""
        with self._lock:
            rows = self._db.execute("SELECT id, tbl, row FROM pending ORDER BY id LIMIT ?", (int(limit),)).fetchall()
        return [(i, tbl, json.loads(row)) for i, tbl, row in rows]

    def delete_through(self, last_id: int) -> None:
        """Forget every row with ``id <= last_id`` (PostgreSQL has committed them)."""
        with self._lock:
            self._db.execute("DELETE FROM pending WHERE id <= ?", (int(last_id),))

    def set_aside(self, row_id: int, error: str) -> None:
        """Move a row that PostgreSQL refuses (bad data, not an outage) out of the queue into
        ``set_aside``, with the error, so that it no longer blocks the rows behind it."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            self._db.execute("INSERT INTO set_aside(id, tbl, row, error, t) SELECT id, tbl, row, ?, ? "
                             "FROM pending WHERE id = ?", (error, time.time(), int(row_id)))
            self._db.execute("DELETE FROM pending WHERE id = ?", (int(row_id),))
            self._db.execute("COMMIT")

    @property
    def is_open(self) -> bool:
        return self._db is not None

    def count(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM pending").fetchone()[0])

    def close(self) -> None:
        """Checkpoint and close; safe twice."""
        with self._lock:
            if self._db is None:
                return
            try:
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            except sqlite3.Error:
                pass
            self._db.close()
            self._db = None
