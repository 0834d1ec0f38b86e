"""The historian process: zenoh drive states -> on-disk buffer -> PostgreSQL.

Threads: zenoh's callback thread turns each sample into rows (:mod:`agent.historian.ingest`)
and appends them to the buffer (fsync'd) before it returns; one writer thread sends the
buffer's oldest rows to PostgreSQL in batches of ``batch_size``, deletes them from the buffer
only after the commit, and runs retention every ``retention.interval_s``; the main thread opens
the zenoh session (retrying with backoff while no router answers), writes the status file every
second, answers ``<prefix>/historian/<id>/health`` and talks to systemd.

Nothing is lost while PostgreSQL is down: rows wait in the buffer and the writer reconnects
with backoff (``database.retry_initial_s`` doubling up to ``retry_max_s``), saying "waiting for
the database" on stderr and in the status; when the server is back it migrates (a no-op when
current) and catches up, oldest first. A start with PostgreSQL or the routers down is not a
failure: ``READY=1`` goes out once the buffer is open, and STATUS says what is awaited.
SIGTERM/SIGINT stop cleanly (the buffer keeps what was not written).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sqlite3
import threading
import time

import zenoh

from agent.errors import InputError
from agent.historian import ingest, store
from agent.historian.buffer import Buffer
from agent.historian.config import HistorianConfig
from agent.historian.page import FleetPage
from agent.runtime import sdnotify
from protocols.streaming import Backoff
from protocols.zenoh_sink import _at_shutdown, zenoh_config

log = logging.getLogger("pmsm-agent.historian")
log.setLevel(logging.INFO)  # its lifecycle lines (waiting, connected, caught up) reach journald whatever -v says
STATUS_PERIOD_S = 1.0  #: the status file and systemd STATUS are refreshed this often
WRITER_STALL_S = 15.0  #: a writer pass longer than this (beyond a connect timeout) stops the watchdog pings, s
WAITING_FOR_DATABASE = "waiting for the database"
WAITING_FOR_ROUTER = "waiting for a zenoh router"
PAGE_RETRY_MAX_S = 60.0  #: a fleet page that cannot listen is retried, the wait doubling from 1 s up to this


class RefusedBatch(Exception):
    """PostgreSQL refused a batch for the data of one of its rows (up to buffer id ``last_id``)."""

    def __init__(self, message: str, last_id: int):
        super().__init__(message)
        self.last_id = last_id


class Historian:
    """One historian: :meth:`start` the threads, :meth:`stop` them; :meth:`status` is the health JSON."""

    def __init__(self, cfg: HistorianConfig):
        self.cfg = cfg
        self.buffer = Buffer(cfg.buffer_path)
        self.stop_event = threading.Event()
        self._wake = threading.Event()  # new rows for the writer
        self._lock = threading.Lock()  # ingest: per-drive Last and buffer order
        self._last = self.buffer.load_last()
        self._session = self._subscriber = self._queryable = None
        self._writer_thread: threading.Thread | None = None
        self.heartbeat = time.monotonic()  #: the writer's last pass (the watchdog's proof of progress)
        self.counters = {"samples": 0, "rejected": 0, "rows_buffered": 0, "rows_written": 0, "batches": 0,
                         "rows_set_aside": 0, "buffer_errors": 0}
        self.database = {"state": "connecting", "error": "", "schema_version": None, "since": time.time()}
        self.zenoh_state = {"state": "connecting", "error": ""}
        self.retention: dict = {"last_run": None, "deleted": {}}
        self.last_error = ""
        self._rejected_keys: set[str] = set()
        #: when each drive's last state sample arrived (a drive without evidence may write no row for hours)
        self.heard: dict[ingest.Identity, float] = {}
        self.page = FleetPage(cfg, self.status, self.heard.copy) if cfg.page.enabled else None  #: the fleet page
        self.page_error = ""  #: why the page is not served (its address cannot be used)

    # --- lifecycle --------------------------------------------------------------------------

    def start(self) -> None:
        """Start the writer thread, and serve the fleet page if enabled."""
        self.open_page()
        self._writer_thread = threading.Thread(target=self._write_loop, name="historian-writer", daemon=True)
        self._writer_thread.start()

    def stop(self) -> int:
        """Close the subscription, let the writer finish its batch, close the buffer; safe twice.
        Returns the rows left in the buffer (written at the next start)."""
        self.stop_event.set()
        self._wake.set()
        if self.page is not None:
            self.page.stop()
        session, self._session = self._session, None
        if session is not None:
            try:
                session.close()
            except zenoh.ZError as err:
                log.warning("zenoh close: %s", err)
        if self._writer_thread is not None:
            self._writer_thread.join(timeout=10.0)
            self._writer_thread = None
        left = self.buffer.count() if self.buffer.is_open else 0
        self.buffer.close()
        return left

    def open_zenoh(self) -> bool:
        """Try once to open the session and subscribe; ``True`` when subscribed."""
        z = self.cfg.zenoh
        try:
            session = zenoh.open(zenoh_config(z.mode, z.listen, z.connect, dict(z.inline), path=z.config_file))
        except zenoh.ZError as err:
            self.zenoh_state = {"state": WAITING_FOR_ROUTER, "error": str(err).split(" at ")[0]}
            return False
        self._session = session
        _at_shutdown(lambda: self._session and self._session.close())
        self._subscriber = session.declare_subscriber(z.key_expr, self._on_sample)
        self._queryable = session.declare_queryable(self.cfg.health_key, self._on_health_query)
        self.zenoh_state = {"state": "subscribed", "error": ""}
        log.info("subscribed to %s (%s of %s)", z.key_expr, z.mode, ", ".join(z.connect or z.listen) or "config file")
        return True

    def open_page(self) -> bool:
        """Try once to serve the fleet page; ``True`` when it is served or not enabled. An address
        that cannot be used is logged once and shown in the status (naming page.host and
        page.port); the historian records without the page meanwhile."""
        if self.page is None or self.page.url:
            return True
        try:
            self.page.start()
        except InputError as err:
            if str(err) != self.page_error:
                log.error("%s; recording goes on without the page, which is retried", err)
            self.page_error = str(err)
            return False
        self.page_error = ""
        return True

    # --- ingest (zenoh thread) --------------------------------------------------------------

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        key = str(sample.key_expr)
        try:
            self.ingest(key, json.loads(sample.payload.to_bytes()))
        except (ValueError, TypeError) as err:  # not a drive state: counted, logged once per key, never raised
            self.counters["rejected"] += 1
            self.last_error = f"{key}: {err}"
            if key not in self._rejected_keys:
                self._rejected_keys.add(key)
                log.warning("ignored a sample on %s (not a drive state; further ones are only counted): %s", key, err)
        except sqlite3.Error as err:  # the buffer's disk is full or broken: this sample's rows are lost
            self.counters["buffer_errors"] += 1
            self.last_error = f"buffer: {err}"
            log.error("cannot buffer a sample on %s (%s): its rows are lost", key, err)

    def ingest(self, key: str, doc: dict, received_t: float | None = None) -> int:
        """Turn one state sample into rows and buffer them (fsync'd); returns the rows buffered.
        ``received_t`` is the time of receipt (default now)."""
        received_t = time.time() if received_t is None else received_t
        with self._lock:
            self.counters["samples"] += 1
            ident = ingest.identity(key, doc, self.cfg.zenoh.prefix)
            rows, last = ingest.sample_rows(ident, doc, self._last.get(ident), trend_period_s=self.cfg.trend_period_s,
                                            received_t=received_t)
            if rows:
                self.buffer.append(rows, ident, last)
                self.counters["rows_buffered"] += len(rows)
            self._last[ident] = last
            self.heard[ident] = received_t
        if rows:
            self._wake.set()
        return len(rows)

    # --- writer thread ----------------------------------------------------------------------

    def _write_loop(self) -> None:
        db = self.cfg.database
        backoff = Backoff(db.retry_initial_s, db.retry_max_s)
        conn = writer = None
        next_retention = time.monotonic()
        one_by_one_through = None  # after a refused batch: rows up to this id go one at a time
        while not self.stop_event.is_set():
            self.heartbeat = time.monotonic()
            try:
                if conn is None:
                    if not backoff.due():
                        self.stop_event.wait(min(0.5, max(0.0, backoff.next_try - time.monotonic())))
                        continue
                    conn = store.connect(db.dsn, db.connect_timeout_s)
                    version = store.migrate(conn)
                    writer = store.Writer(conn, self.buffer.buffer_id, self.cfg.historian_id)
                    backoff.reset()
                    was = self.database["state"]
                    self.database = {"state": "connected", "error": "", "schema_version": version, "since": time.time()}
                    log.info("database connected (schema version %d)%s; %d row(s) buffered", version,
                             " after an outage" if was == WAITING_FOR_DATABASE else "", self.buffer.count())
                self._wake.clear()  # before the read: rows appended after it wake the wait below
                batch = self.buffer.oldest(1 if one_by_one_through else self.cfg.batch_size)
                if batch:
                    self._write(writer, batch)
                    if one_by_one_through is not None and batch[-1][0] >= one_by_one_through:
                        one_by_one_through = None
                    continue  # the next batch at once: catching up
                if time.monotonic() >= next_retention:
                    self._run_retention(conn)
                    next_retention = time.monotonic() + self.cfg.retention.interval_s
                self._wake.wait(0.5)
            except RefusedBatch as refused:  # bad data in a row, not an outage: find it, set it aside
                one_by_one_through = refused.last_id
                log.warning("PostgreSQL refused a batch (%s); writing its rows one by one", refused)
            except Exception as err:  # the server went away, refused us, or a write failed: retry later
                if conn is not None:
                    try:
                        conn.close()
                    except Exception:
                        pass
                conn = writer = None
                wait = backoff.failed()
                message = " ".join(str(err).split()) or type(err).__name__
                if not isinstance(err, store.psycopg_module().OperationalError):
                    message = f"{type(err).__name__}: {message}"
                if self.database["state"] != WAITING_FOR_DATABASE:
                    self.database = {**self.database, "since": time.time()}
                self.database.update(state=WAITING_FOR_DATABASE, error=message)
                log.warning("%s (%s); retrying in %.1f s; %d row(s) buffered", WAITING_FOR_DATABASE, message, wait,
                            self.buffer.count())
        if conn is not None:
            conn.close()

    def _write(self, writer: store.Writer, batch: list) -> None:
        """Commit ``batch``, then delete it from the buffer. A single row that PostgreSQL refuses
        for its data is set aside (``RefusedBatch`` for a larger batch)."""
        psycopg = store.psycopg_module()
        try:
            self.counters["rows_written"] += writer.write(batch)
        except (psycopg.DataError, psycopg.IntegrityError) as err:
            message = " ".join(str(err).split())
            if len(batch) > 1:
                raise RefusedBatch(message, batch[-1][0]) from err
            self.buffer.set_aside(batch[0][0], message)
            self.counters["rows_set_aside"] += 1
            self.last_error = f"row set aside: {message}"
            log.error("PostgreSQL refused a row; set aside in %s (table set_aside): %s", self.buffer.path, message)
            return
        self.counters["batches"] += 1
        self.buffer.delete_through(batch[-1][0])

    def _run_retention(self, conn) -> None:
        r = self.cfg.retention
        deleted = store.apply_retention(conn, r.trend_days, r.events_days)
        self.retention = {"last_run": time.time(), "deleted": deleted}
        if any(deleted.values()):
            log.info("retention: deleted %s", ", ".join(f"{n} from {t}" for t, n in deleted.items()))

    # --- health -----------------------------------------------------------------------------

    def status(self) -> dict:
        """The health JSON (status file and zenoh queryable)."""
        return {"historian": self.cfg.historian_id, "pid": os.getpid(), "t": time.time(),
                "database": dict(self.database), "zenoh": self._zenoh_status(),
                "buffered": self.buffer.count(), **self.counters, "last_error": self.last_error,
                "retention": self.retention, "buffer": str(self.cfg.buffer_path),
                "page": None if self.page is None else {"url": self.page.url or None, "error": self.page_error}}

    def _zenoh_status(self) -> dict:
        """The session's state with the routers and peers it is connected to now: a client whose
        routers all went away is waiting again while zenoh reconnects it."""
        doc = {**self.zenoh_state, "key_expr": self.cfg.zenoh.key_expr}
        session = self._session
        if session is None:
            return doc
        try:
            doc["routers"] = len(list(session.info.routers_zid()))
            doc["peers"] = len(list(session.info.peers_zid()))
        except zenoh.ZError:  # closing
            return doc
        if self.cfg.zenoh.mode == "client" and doc["routers"] == 0:
            doc.update(state=WAITING_FOR_ROUTER, error="no router connected (zenoh reconnects by itself)")
        return doc

    def status_line(self) -> str:
        """One line for systemd's STATUS and the log."""
        waiting = [s["state"] for s in (self.database, self._zenoh_status()) if s["state"].startswith("waiting")]
        waiting += ["the fleet page is not served (page.host, page.port)"] if self.page_error else []
        return "; ".join(waiting + [f"{self.counters['rows_written']} row(s) written, "
                                    f"{self.buffer.count()} buffered"])

    def write_status(self) -> None:
        path = self.cfg.status_path
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.status(), default=str))
        os.replace(tmp, path)

    def _on_health_query(self, q: zenoh.Query) -> None:
        try:
            q.reply(self.cfg.health_key, json.dumps(self.status(), default=str),
                    encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception as err:
            log.warning("health query: %s", err)

    # --- the process ------------------------------------------------------------------------

    def run(self, max_seconds: float | None = None) -> int:
        """Run until SIGTERM/SIGINT (or ``max_seconds``); returns the exit status."""
        z = self.cfg.zenoh
        zenoh_backoff = Backoff(z.retry_initial_s, z.retry_max_s)
        page_backoff = Backoff(1.0, PAGE_RETRY_MAX_S)
        watchdog = sdnotify.Watchdog()
        self.start()
        sdnotify.ready(self.status_line())
        deadline = None if max_seconds is None else time.monotonic() + max_seconds
        try:
            while not self.stop_event.is_set() and (deadline is None or time.monotonic() < deadline):
                if self._session is None and zenoh_backoff.due() and not self.open_zenoh():
                    wait = zenoh_backoff.failed()
                    log.warning("%s (%s); retrying in %.1f s", WAITING_FOR_ROUTER, self.zenoh_state["error"], wait)
                if page_backoff.due() and not self.open_page():
                    page_backoff.failed()
                self.write_status()
                sdnotify.status(self.status_line())
                if time.monotonic() - self.heartbeat < self.cfg.database.connect_timeout_s + WRITER_STALL_S:
                    watchdog.ping()  # the writer loop advances (a connect attempt may take its timeout)
                self.stop_event.wait(STATUS_PERIOD_S)
        finally:
            sdnotify.stopping("stopping")
            left = self.stop()
            log.info("stopped: %d row(s) written, %d left in the buffer", self.counters["rows_written"], left)
        return 0

    def install_signal_handlers(self) -> None:
        signal.signal(signal.SIGTERM, lambda *_: self.stop_event.set())
        signal.signal(signal.SIGINT, lambda *_: self.stop_event.set())


def run_historian(cfg: HistorianConfig, max_seconds: float | None = None) -> int:
    """The ``pmsm-agent historian`` process."""
    try:
        historian = Historian(cfg)
    except (OSError, sqlite3.Error) as err:
        raise InputError(f"state_dir: cannot open the buffer {cfg.buffer_path}: {err}",
                         source=str(cfg.source)) from None
    historian.install_signal_handlers()
    return historian.run(max_seconds)
