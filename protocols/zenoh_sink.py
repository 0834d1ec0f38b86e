"""Zenoh sink: drive state, diagnostics, agent health, liveliness token and queryables.

Key space under ``prefix`` (e.g. ``pmsm/demo``; CONTRACT section 6):

=====================================  =======================================================
``<prefix>/<drive>/state``             JSON on change (BLOCK, express, REAL_TIME) and every
                                       ``period_s`` (DROP); ``DriveStatus.to_json()`` plus
                                       ``schema`` (:data:`SCHEMA_VERSION`), ``state_code``,
                                       ``quality_code``, ``agent``, ``boot_id``, ``seq``
``<prefix>/<drive>/diagnostics``       JSON every ``diagnostics_period_s`` (DROP)
``<prefix>/agent/<agent_id>/health``   JSON every ``diagnostics_period_s`` (DROP); also a queryable
``<prefix>/agent/<agent_id>/alive``    liveliness token (DELETE when the agent stops or dies)
``<prefix>/<drive>/model`` ...         queryables ``model``, ``spectrum``, ``thresholds``, ``events``
                                       answered by :class:`Providers`; selector parameters are
                                       passed on, e.g. ``pmsm/demo/d1/events?limit=20;kind=state``
=====================================  =======================================================

Threading: :meth:`ZenohSink.publish` only compares with the last status and enqueues a JSON
snapshot (a few tens of microseconds); one sender thread does every zenoh put, so a congested
or half-open link (BLOCK waits up to the lease, 10 s) never stalls the pipeline. When the
queue of changes is full the oldest is dropped and counted.

Reconnect is zenoh's own: a peer whose ``connect`` endpoint is down returns from ``open``
(after ``scouting/delay``, 500 ms by default) and keeps retrying in the background; publications
made while nobody is connected go nowhere (routing has no subscriber), and delivery resumes
within about 0.1 s once the other side is back. Liveliness of a vanished agent is noticed at
once on a TCP reset, else at lease expiry (``transport/link/tx/lease``, 10 s by default).
Multicast scouting and gossip are always off (:func:`zenoh_config`).

An open session whose Python callbacks are still declared makes interpreter exit hang (zenoh's
callback threads are non-daemon and Python joins them before ``atexit``), so
:meth:`ZenohSink.open` registers :meth:`ZenohSink.close` to run at the start of shutdown.
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import queue
import re
import threading
import time
import uuid
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import zenoh

from protocols.base import QUALITY_CODES, STATE_CODES, DriveStatus, OpenClose
from protocols.streaming import put_drop_oldest

#: Version of the JSON payloads (the ``schema`` field). 2: adds ``reason``, ``evidence``, ``settling``
#: and ``learn_progress_pct`` (the alarm logic, docs/method.md "Alarms") and the field itself;
#: a payload without ``schema`` is version 1.
SCHEMA_VERSION = 2
log = logging.getLogger(__name__)

QUERY_TOPICS = ("model", "spectrum", "thresholds", "events")
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")
_STOP = object()


def check_key(key: str, what: str = "key") -> str:
    """A concrete zenoh key: ``/``-separated non-empty chunks without ``* $ ? #``."""
    if not key or not all(_CHUNK.match(c) for c in key.split("/")):
        raise ValueError(f"{what} {key!r}: use '/'-separated chunks of letters, digits, '_', '.', '-'")
    return key


def zenoh_config(mode: str | None = "peer", listen: Sequence[str] | None = None,
                 connect: Sequence[str] | None = None, extra: Mapping[str, object] | None = None,
                 *, path: str | os.PathLike | None = None) -> zenoh.Config:
    """A ``zenoh.Config`` with multicast scouting and gossip always off.

    ``path``: optional JSON5 file read first. ``listen``/``connect``: endpoint lists; ``None``
    keeps the file's value, or sets ``[]`` without a file (a peer would otherwise listen on all
    interfaces). ``extra``: ``{"a/b/c": value}`` inserted as JSON. Raises ``ValueError`` naming
    the key for unknown keys or bad values.
    """
    cfg = zenoh.Config.from_file(str(path)) if path else zenoh.Config()

    def put(key, value):
        try:
            cfg.insert_json5(key, json.dumps(value))
        except zenoh.ZError as err:
            raise ValueError(f"zenoh config key '{key}' = {value!r}: {err}") from err

    if mode is not None:
        put("mode", mode)
    for key, eps in (("listen/endpoints", listen), ("connect/endpoints", connect)):
        if eps is not None or not path:
            put(key, list(eps or ()))
    for key, value in (extra or {}).items():
        put(key, value)
    for key in ("scouting/multicast/enabled", "scouting/gossip/enabled"):
        if (path or key in (extra or {})) and json.loads(cfg.get_json(key)) is not False:
            log.log(logging.WARNING if key in (extra or {}) else logging.INFO,
                    "zenoh: %s forced to false (this agent never uses multicast or gossip)", key)
        put(key, False)
    return cfg


def _at_shutdown(fn) -> None:
    """Run ``fn`` when the interpreter exits, *before* it joins non-daemon threads: zenoh's
    callback threads end only when the session closes, so a plain ``atexit`` would never run."""
    register = getattr(threading, "_register_atexit", None)  # CPython >= 3.9 (concurrent.futures uses it)
    if register is None:
        atexit.register(fn)
        return
    try:
        register(fn)
    except RuntimeError:  # already shutting down
        pass


QueryFn = Callable[[str, dict], dict]


@dataclass
class Providers:
    """Callbacks of the runtime that answer queries; each returns a JSON-able dict.

    ``model``/``spectrum``/``thresholds``/``events``: ``fn(drive, params) -> dict`` where
    ``params`` are the selector parameters as ``{str: str}``; raise ``KeyError`` for an unknown
    drive or item. ``diagnostics``: ``fn(drive) -> dict`` merged into each drive's
    diagnostics; ``health``: ``fn() -> dict`` merged into the agent health. Callbacks run on
    zenoh or sender threads and must be thread-safe and quick.
    """

    model: QueryFn | None = None
    spectrum: QueryFn | None = None
    thresholds: QueryFn | None = None
    events: QueryFn | None = None
    diagnostics: Callable[[str], dict] | None = None
    health: Callable[[], dict] | None = None


@dataclass
class ZenohStats:
    """Counters of the sink (in diagnostics and health)."""

    changes: int = 0  #: on-change state puts
    periodic: int = 0  #: periodic state puts
    diagnostics: int = 0
    dropped: int = 0  #: changes dropped because the queue was full
    queries: int = 0
    errors: int = 0
    last_error: str = ""

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def _change_key(doc: dict) -> tuple:
    return tuple(doc.get(k) for k in ("state", "quality", "spectrum_state", "cluster_state", "model"))


@dataclass
class _Drive:
    doc: dict  #: last status JSON (with codes)
    key: tuple
    seq: int = 0
    mono: float = 0.0  #: monotonic time of the last publish() call
    pub: object = None
    queryables: list = field(default_factory=list)


class ZenohSink(OpenClose):
    """Publishes :class:`DriveStatus` on zenoh (the :class:`protocols.base.Sink` contract)."""

    name = "zenoh"

    def __init__(self, config: zenoh.Config, prefix: str, agent_id: str, *, drives: Sequence[str] = (),
                 providers: Providers | None = None, period_s: float = 1.0, diagnostics_period_s: float = 5.0,
                 queue_size: int = 256):
        self.config, self.prefix = config, check_key(prefix, "prefix")
        self.agent_id = check_key(agent_id, "agent_id")
        if "/" in agent_id:
            raise ValueError(f"agent_id {agent_id!r}: one key chunk, no '/'")
        self.providers = providers or Providers()
        self.period_s, self.diagnostics_period_s = float(period_s), float(diagnostics_period_s)
        self.boot_id = uuid.uuid4().hex[:16]
        self.stats = ZenohStats()
        self._names = list(drives)
        self._drives: dict[str, _Drive] = {}
        self._lock = threading.Lock()
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._session = self._token = self._thread = None
        self._agent_qbl = None
        self._t0 = time.monotonic()

    # --- lifecycle --------------------------------------------------------------------------

    def open(self) -> None:
        """Open the session, declare token, health queryable and known drives; start the sender."""
        if self._session is not None:
            return
        try:
            self._session = zenoh.open(self.config)
        except zenoh.ZError as err:
            raise ConnectionError(f"zenoh open failed: {err}") from err
        close = weakref.WeakMethod(self.close)
        _at_shutdown(lambda: (m := close()) and m())
        base = f"{self.prefix}/agent/{self.agent_id}"
        self._token = self._session.liveliness().declare_token(f"{base}/alive")
        self._agent_qbl = self._session.declare_queryable(f"{base}/health", self._on_health_query)
        for name in self._names:
            self._declare_drive(name)
        self._q = queue.Queue(maxsize=self._q.maxsize)
        self._thread = threading.Thread(target=self._run, name="zenoh-sink", daemon=True)
        self._thread.start()
        log.info("zenoh sink open: prefix %s, agent %s", self.prefix, self.agent_id)

    def close(self) -> None:
        """Flush pending changes (at most ~3 s on a stuck link), remove the token, close the session; safe twice."""
        session, self._session = self._session, None
        if session is None:
            return
        if self._thread is not None:
            try:
                self._q.put(_STOP, timeout=1.0)
            except queue.Full:
                pass
            self._thread.join(timeout=2.0)
            self._thread = None
        try:
            self._token.undeclare()
            session.close()
        except zenoh.ZError as err:  # already closed underneath us
            log.warning("zenoh close: %s", err)
        self._drives.clear()

    # --- the Sink contract ------------------------------------------------------------------

    def publish(self, status: DriveStatus) -> None:
        """Record ``status``; on a change enqueue it for an immediate put. Never blocks."""
        doc = status.to_json()
        doc["state_code"] = STATE_CODES.get(status.state)
        doc["quality_code"] = QUALITY_CODES.get(status.quality)
        key = _change_key(doc)
        with self._lock:
            d = self._drives.get(status.drive)
            changed = d is None or d.key != key
            if d is None:
                d = self._drives[status.drive] = _Drive(doc, key)
            d.doc, d.key, d.mono = doc, key, time.monotonic()
        if changed and self._session is not None:
            self._enqueue((status.drive, doc))  # a snapshot: a later change does not overwrite it

    def _enqueue(self, item: tuple) -> None:
        self.stats.dropped += put_drop_oldest(self._q, item)

    # --- sender thread ----------------------------------------------------------------------

    def _run(self) -> None:
        now = time.monotonic()
        next_state, next_diag = now + self.period_s, now + min(self.diagnostics_period_s, 0.2)
        while True:
            try:
                item = self._q.get(timeout=max(0.0, min(next_state, next_diag) - time.monotonic()))
            except queue.Empty:
                item = None
            if item is _STOP:
                self._drain()
                return
            if item is not None:
                self._put_state(*item, change=True)
            now = time.monotonic()
            if now >= next_state:
                next_state = now + self.period_s
                with self._lock:
                    latest = [(n, d.doc) for n, d in self._drives.items() if d.doc]
                for name, doc in latest:
                    self._put_state(name, doc, change=False)
            if now >= next_diag:
                next_diag = now + self.diagnostics_period_s
                self._put_diagnostics()

    def _drain(self) -> None:
        while True:
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                return
            if item is not _STOP:
                self._put_state(*item, change=True)

    def _guard(self, what: str, fn, *args, **kw) -> bool:
        try:
            fn(*args, **kw)
            return True
        except Exception as err:  # transport trouble is counted, never raised
            self.stats.errors += 1
            self.stats.last_error = f"{what}: {err}"
            log.warning("zenoh %s: %s", what, err)
            return False

    def _put_state(self, drive: str, doc: dict, change: bool) -> None:
        session = self._session
        if session is None:
            return
        d = self._drives.get(drive)
        if d is None:
            return
        if d.pub is None and not self._guard("declare", self._declare_drive, drive):
            return
        d.seq += 1
        payload = json.dumps({"schema": SCHEMA_VERSION, **doc, "agent": self.agent_id, "boot_id": self.boot_id,
                              "seq": d.seq}, default=str)
        if change:
            ok = self._guard("put state", d.pub.put, payload)
            self.stats.changes += ok
        else:
            ok = self._guard("put state", session.put, f"{self.prefix}/{drive}/state", payload,
                             encoding=zenoh.Encoding.APPLICATION_JSON,
                             congestion_control=zenoh.CongestionControl.DROP)
            self.stats.periodic += ok

    def _put_diagnostics(self) -> None:
        session = self._session
        if session is None:
            return
        now, mono = time.time(), time.monotonic()
        with self._lock:
            drives = list(self._drives.items())
        for name, d in drives:
            doc = {"drive": name, "agent": self.agent_id, "boot_id": self.boot_id, "t": now,
                   "status_age_s": round(mono - d.mono, 3) if d.mono else None, "seq": d.seq,
                   "zenoh": self.stats.as_dict()}
            if self.providers.diagnostics is not None:
                self._guard("diagnostics provider", lambda: doc.update(self.providers.diagnostics(name)))
            self._guard("put diagnostics", session.put, f"{self.prefix}/{name}/diagnostics",
                        json.dumps(doc, default=str), encoding=zenoh.Encoding.APPLICATION_JSON,
                        congestion_control=zenoh.CongestionControl.DROP)
        self.stats.diagnostics += 1
        self._guard("put health", session.put, f"{self.prefix}/agent/{self.agent_id}/health",
                    json.dumps(self.health(), default=str), encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.DROP)

    def health(self) -> dict:
        """The agent health document (also answered by the ``.../health`` queryable)."""
        mono = time.monotonic()
        with self._lock:
            drives = {n: {"state": d.doc.get("state"), "quality": d.doc.get("quality"),
                          "status_age_s": round(mono - d.mono, 3) if d.mono else None}
                      for n, d in self._drives.items()}
        doc = {"agent": self.agent_id, "boot_id": self.boot_id, "pid": os.getpid(), "t": time.time(),
               "uptime_s": round(mono - self._t0, 3), "drives": drives, "zenoh": self.stats.as_dict()}
        if self.providers.health is not None:
            doc.update(self.providers.health())
        return doc

    # --- queryables -------------------------------------------------------------------------

    def _declare_drive(self, drive: str) -> None:
        check_key(drive, "drive name")
        session = self._session
        with self._lock:
            d = self._drives.setdefault(drive, _Drive({}, ()))
        if d.pub is not None:
            return
        d.pub = session.declare_publisher(
            f"{self.prefix}/{drive}/state", encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME, express=True)
        for topic in QUERY_TOPICS:
            d.queryables.append(session.declare_queryable(
                f"{self.prefix}/{drive}/{topic}", lambda q, drive=drive, topic=topic: self._on_query(q, drive, topic)))

    def _reply(self, q: zenoh.Query, key: str, fn) -> None:
        self.stats.queries += 1
        try:  # reply on our own concrete key, not the query's (which may hold wildcards)
            doc = fn()
            q.reply(key, json.dumps(doc, default=str), encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception as err:  # answer with an error reply instead of silence
            msg = f"{type(err).__name__}: {err}" if not isinstance(err, KeyError) else f"not found: {err}"
            try:
                q.reply_err(json.dumps({"error": msg}), encoding=zenoh.Encoding.APPLICATION_JSON)
            except zenoh.ZError:
                pass

    def _on_query(self, q: zenoh.Query, drive: str, topic: str) -> None:
        fn = getattr(self.providers, topic)

        def answer():
            if fn is None:
                raise LookupError(f"'{topic}' is not provided by this agent")
            return fn(drive, dict(q.parameters))
        self._reply(q, f"{self.prefix}/{drive}/{topic}", answer)

    def _on_health_query(self, q: zenoh.Query) -> None:
        self._reply(q, f"{self.prefix}/agent/{self.agent_id}/health", self.health)


def sink_from_config(zcfg, agent_id: str, drives: Sequence[str] = (), providers: Providers | None = None) -> ZenohSink:
    """Build a :class:`ZenohSink` from the agent config's ``[zenoh]`` table (``agent.runtime.config.ZenohCfg``)."""
    cfg = zenoh_config(zcfg.mode, zcfg.listen, zcfg.connect, dict(zcfg.inline), path=zcfg.config_file)
    return ZenohSink(cfg, zcfg.prefix, agent_id, drives=drives, providers=providers, period_s=zcfg.period_s,
                     diagnostics_period_s=zcfg.diagnostics_period_s)
