"""The event journal: state and quality changes, learning events and errors in SQLite.

One table ``events(id, t, drive, kind, state, quality, detail)``: ``t`` Unix time (s), ``kind``
one of :data:`KINDS`, ``state`` the alarm code 0/1/2 and ``quality`` the data-quality code
0..4 (CONTRACT section 6; NULL when the event has none), ``detail`` a JSON object.

Durability: WAL with ``synchronous=FULL`` by default. In WAL mode every commit is in the WAL
file before ``record`` returns, so a killed process (kill -9, OOM, watchdog SIGABRT) never loses a
committed event with either NORMAL or FULL; FULL additionally fsyncs the WAL on each commit,
so a power cut (the usual way a cabinet PC stops) cannot lose the last alarm transitions
either, which are the ones an audit needs. Events are rare (changes, not samples), so one fsync
per event costs nothing that matters; set ``synchronous="NORMAL"`` on flash that must be spared.

Repeated errors are rate-limited (``error_holdoff_s``). Size is bounded: rows beyond ``max_events`` or older than ``max_age_s`` are deleted in batches
of at most ``prune_batch`` rows every ``prune_every`` inserts (never one long delete), pages are
given back with ``incremental_vacuum`` and the WAL is capped by ``journal_size_limit``.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import sqlite3
import threading
import time
from collections.abc import Iterable
from pathlib import Path

from agent.errors import InputError
from protocols.base import QUALITY_CODES, STATE_CODES

log = logging.getLogger(__name__)

#: event kinds (free-form kinds are accepted too; these are the ones the runtime writes)
KINDS = ("state", "quality", "learning", "baseline", "model", "error", "start", "stop", "reload", "worker")
FILENAME = "journal.sqlite3"
SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS events (
    id      INTEGER PRIMARY KEY AUTOINCREMENT,
    t       REAL    NOT NULL,
    drive   TEXT    NOT NULL DEFAULT '',
    kind    TEXT    NOT NULL,
    state   INTEGER,
    quality INTEGER,
    detail  TEXT    NOT NULL DEFAULT '{}'
);
CREATE INDEX IF NOT EXISTS events_drive ON events(drive, id);
CREATE INDEX IF NOT EXISTS events_t ON events(t);
"""
_STATE_NAMES = {v: k for k, v in STATE_CODES.items()}
_QUALITY_NAMES = {v: k for k, v in QUALITY_CODES.items()}


def journal_path(state_dir: str | os.PathLike) -> Path:
    return Path(state_dir) / FILENAME


def _row(r: tuple) -> dict:
    id_, t, drive, kind, state, quality, detail = r
    return {"id": id_, "t": t, "drive": drive, "kind": kind, "state_code": state, "quality_code": quality,
            "state": _STATE_NAMES.get(state), "quality": _QUALITY_NAMES.get(quality), "detail": json.loads(detail)}


class Journal:
    """Append-only event log with bounded size; thread-safe (one connection behind a lock)."""

    def __init__(self, path: str | os.PathLike, *, max_events: int = 100_000, max_age_s: float = 365 * 86400.0,
                 synchronous: str = "FULL", prune_every: int = 64, prune_batch: int = 500,
                 error_holdoff_s: float = 60.0, readonly: bool = False):
        if synchronous.upper() not in ("NORMAL", "FULL"):
            raise ValueError(f"synchronous must be NORMAL or FULL, got {synchronous!r}")
        if prune_batch < prune_every:
            raise ValueError(f"prune_batch ({prune_batch}) must be >= prune_every ({prune_every}) to bound the size")
        self.path = Path(path)
        self.max_events, self.max_age_s = int(max_events), float(max_age_s)
        self.prune_every, self.prune_batch = int(prune_every), int(prune_batch)
        self.readonly, self.error_holdoff_s = readonly, float(error_holdoff_s)
        self._errors: dict[tuple[str, str], tuple[float, int]] = {}
        self._lock = threading.Lock()
        self._inserts = 0
        if readonly:
            if not self.path.is_file():
                raise InputError("no journal here (has the agent run with this state directory?)", source=str(path))
            self._db = sqlite3.connect(f"{self.path.resolve().as_uri()}?mode=ro", uri=True, check_same_thread=False)
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA auto_vacuum=INCREMENTAL")  # only effective on a new file
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute(f"PRAGMA synchronous={synchronous.upper()}")
            self._db.execute("PRAGMA journal_size_limit=4194304")
            self._db.executescript(_SCHEMA)
            self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        self._db.execute("PRAGMA busy_timeout=2000")
        self._last: dict[str, tuple[int | None, int | None]] = self._load_last() if not readonly else {}

    @classmethod
    def from_config(cls, cfg) -> Journal:
        """Open ``<state_dir>/journal.sqlite3`` with the ``[journal]`` settings of an agent ``Config``."""
        j = cfg.journal
        return cls(journal_path(cfg.state_dir), max_events=j.max_events, max_age_s=j.max_age_days * 86400.0,
                   synchronous=j.synchronous, error_holdoff_s=j.error_holdoff_s)

    def _load_last(self) -> dict:
        """Last known (state, quality) per drive, so a restart does not log a spurious change."""
        last = {}
        for kind, col in (("state", 0), ("quality", 1)):
            for drive, code in self._db.execute(
                    f"SELECT drive, {kind} FROM events WHERE id IN "
                    f"(SELECT MAX(id) FROM events WHERE kind=? GROUP BY drive)", (kind,)):
                pair = list(last.get(drive, (None, None)))
                pair[col] = code
                last[drive] = tuple(pair)
        return last

    # --- writing ----------------------------------------------------------------------------

    def record(self, kind: str, drive: str = "", *, state: str | int | None = None,
               quality: str | int | None = None, detail: dict | None = None, t: float | None = None) -> int | None:
        """Append one event (committed when this returns); returns its id.

        A repeat of an ``error`` (same drive and ``detail["event"]`` or ``detail["msg"]``) within
        ``error_holdoff_s`` is only counted (returns ``None``); the next one written carries
        ``"suppressed": n``, so a flapping input cannot flush the history out of retention."""
        detail = dict(detail or {})
        if kind == "error" and self.error_holdoff_s > 0:
            key = (drive, str(detail.get("event") or detail.get("msg") or ""))
            now = time.monotonic()
            last, n = self._errors.get(key, (float("-inf"), 0))
            if now - last < self.error_holdoff_s:
                self._errors[key] = (last, n + 1)
                return None
            self._errors[key] = (now, 0)
            if n:
                detail["suppressed"] = n
        s = STATE_CODES[state] if isinstance(state, str) else state
        q = QUALITY_CODES[quality] if isinstance(quality, str) else quality
        row = (time.time() if t is None else float(t), drive, kind, s, q, json.dumps(detail, default=str))
        with self._lock:
            cur = self._db.execute(
                "INSERT INTO events(t, drive, kind, state, quality, detail) VALUES (?,?,?,?,?,?)", row)
            self._inserts += 1
            if self._inserts % self.prune_every == 0:
                self._prune_locked()
            return int(cur.lastrowid)

    def record_status(self, status) -> list[int | None]:
        """Log the state and/or quality change of a ``DriveStatus`` against the last logged one."""
        s, q = STATE_CODES.get(status.state), QUALITY_CODES.get(status.quality)
        old_s, old_q = self._last.get(status.drive, (None, None))
        ids = []
        if s != old_s:
            ids.append(self.record("state", status.drive, state=s, quality=q, t=status.t or None, detail={
                "from": _STATE_NAMES.get(old_s), "spectrum_state": status.spectrum_state,
                "cluster_state": status.cluster_state, "fe_hz": _num(status.fe_hz),
                "load_pct": _num(status.load_pct), "model": status.model, "peaks": status.peaks[:8],
                **getattr(status, "extra", {})}))  # why: the path, feature, z or evidence; evidence per family
        if q != old_q:
            reason = getattr(status, "extra", {}).get("reason")
            ids.append(self.record("quality", status.drive, state=s, quality=q, t=status.t or None,
                                   detail={"from": _QUALITY_NAMES.get(old_q), "model": status.model,
                                           **({"reason": reason} if reason else {})}))
        self._last[status.drive] = (s, q)
        return ids

    def prune(self) -> int:
        """Delete one batch of expired rows; returns how many."""
        with self._lock:
            return self._prune_locked()

    def _prune_locked(self) -> int:
        if self.readonly:
            return 0
        cutoff = time.time() - self.max_age_s
        cur = self._db.execute(
            "DELETE FROM events WHERE id IN (SELECT id FROM events WHERE t < ? "
            "OR id <= (SELECT MAX(id) FROM events) - ? ORDER BY id LIMIT ?)",
            (cutoff, self.max_events, self.prune_batch))
        if cur.rowcount:
            self._db.execute(f"PRAGMA incremental_vacuum({max(8, cur.rowcount // 16)})")
        return cur.rowcount

    # --- reading ----------------------------------------------------------------------------

    def recent(self, drive: str | None = None, *, kinds: Iterable[str] | None = None, limit: int = 100,
               since: float | None = None, before_id: int | None = None) -> list[dict]:
        """The newest ``limit`` events, newest first; filters are ANDed. ``before_id`` pages back."""
        kinds = list(kinds or ())
        clauses = [("drive = ?", [drive] if drive else None),
                   (f"kind IN ({','.join('?' * len(kinds))})", kinds or None),
                   ("t >= ?", None if since is None else [float(since)]),
                   ("id < ?", None if before_id is None else [int(before_id)])]
        where = [c for c, a in clauses if a is not None]
        args = [x for _, a in clauses if a is not None for x in a]
        sql = ("SELECT id, t, drive, kind, state, quality, detail FROM events"
               + (" WHERE " + " AND ".join(where) if where else "") + " ORDER BY id DESC LIMIT ?")
        with self._lock:
            rows = self._db.execute(sql, (*args, max(0, int(limit)))).fetchall()
        return [_row(r) for r in rows]

    def count(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM events").fetchone()[0])

    def provider(self, default_limit: int = 50, max_limit: int = 1000):
        """``fn(drive, params) -> {"events": [...]}`` for the zenoh ``events`` queryable.

        Parameters (all optional): ``limit``, ``kind`` (comma-separated), ``since`` (Unix s)."""
        def events(drive: str, params: dict) -> dict:
            try:
                limit = min(int(params.get("limit", default_limit)), max_limit)
                since = float(params["since"]) if "since" in params else None
            except ValueError as err:
                raise ValueError(f"bad query parameter: {err}") from None
            kinds = [k for k in params.get("kind", "").split(",") if k]
            return {"drive": drive, "events": self.recent(drive, kinds=kinds, limit=limit, since=since)}
        return events

    def close(self) -> None:
        """Checkpoint and close; safe twice."""
        with self._lock:
            if self._db is None:
                return
            if not self.readonly:
                try:
                    self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                except sqlite3.Error:
                    pass
            self._db.close()
            self._db = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _num(x):
    return None if x is None or x != x else float(x)


class JournalSink:
    """A :class:`protocols.base.Sink` that journals state and quality changes from a writer thread.

    ``publish`` compares with the last status in memory and hands only changes to the thread,
    so a slow fsync never delays the pipeline."""

    name = "journal"

    def __init__(self, journal: Journal, queue_size: int = 1024):
        self.journal, self.dropped, self.errors = journal, 0, 0
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._last: dict[str, tuple[str, str]] = {}
        self._thread: threading.Thread | None = None

    def open(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="journal-sink", daemon=True)
            self._thread.start()

    def publish(self, status) -> None:
        key = (status.state, status.quality)
        if self._last.get(status.drive) == key:
            return
        self._last[status.drive] = key
        try:
            self._q.put_nowait(_Snapshot(status))
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        while (item := self._q.get()) is not None:
            try:
                self.journal.record_status(item)
            except sqlite3.Error as err:
                self.errors += 1
                log.error("journal write failed: %s", err)

    def close(self) -> None:
        """Write what is queued, stop the thread (the journal itself stays open)."""
        if self._thread is not None:
            self._q.put(None)
            self._thread.join(timeout=5.0)
            self._thread = None


class _Snapshot:
    """The fields of a DriveStatus the journal needs, copied at publish time."""

    __slots__ = ("drive", "state", "quality", "spectrum_state", "cluster_state", "fe_hz", "load_pct", "t",
                 "model", "peaks", "extra")

    def __init__(self, s):
        for k in self.__slots__:
            setattr(self, k, getattr(s, k))
        self.peaks = list(s.peaks[:8])
        self.extra = {k: s.extra[k] for k in ("reason", "evidence") if s.extra.get(k)}
