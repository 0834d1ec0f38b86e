"""Zenoh sink: drive state, diagnostics, agent health, liveliness tokens, queryables, commands.

Key space under ``prefix`` (e.g. ``pmsm/demo``, or ``pmsm/<site>/<gateway>`` on a plant's
router network: docs/architecture.md "Plant"; CONTRACT section 6):

=====================================  =======================================================
``<prefix>/<drive>/state``             JSON on change (BLOCK, express, REAL_TIME) and every
                                       ``period_s`` (DROP); ``DriveStatus.to_json()`` plus
                                       ``schema`` (:data:`SCHEMA_VERSION`), ``state_code``,
                                       ``quality_code``, ``agent``, ``boot_id``, ``seq``
``<prefix>/<drive>/diagnostics``       JSON every ``diagnostics_period_s`` (DROP)
``<prefix>/<drive>/alive``             liveliness token while the drive's input is live (it goes
                                       when the quality turns ``stale`` and when the agent dies)
``<prefix>/<drive>/model`` ...         queryables ``model``, ``spectrum``, ``thresholds``, ``events``
                                       answered by :class:`Providers`; selector parameters are
                                       passed on, e.g. ``pmsm/demo/d1/events?limit=20;kind=state``
``<prefix>/<drive>/command``           queryable taking a signed command (ACK, RELEARN) as the
                                       query's payload (:mod:`agent.runtime.commands`); only
                                       declared when ``Providers.command`` is set
``<prefix>/agent/<agent_id>/health``   JSON every ``diagnostics_period_s`` (DROP); also a queryable
``<prefix>/agent/<agent_id>/fleet``    queryable: every drive of this agent at once (state,
                                       quality, evidence, last change, seq, token) for
                                       ``pmsm-agent fleet status``
``<prefix>/agent/<agent_id>/alive``    liveliness token (DELETE when the agent stops or dies)
=====================================  =======================================================

Threading: :meth:`ZenohSink.publish` only compares with the last status and enqueues a JSON
snapshot (a few tens of microseconds); one sender thread does every zenoh put, so a congested
or half-open link (BLOCK waits up to the lease, 10 s) never stalls the pipeline. When the
queue of changes is full the oldest is dropped and counted.

Reconnect. A peer whose ``connect`` endpoint is down returns from ``open`` (after
``scouting/delay``, 500 ms by default) and zenoh keeps retrying in the background. A client
(``mode = "client"``, a gateway on a plant's routers) cannot open while no router answers: the
sender thread then retries ``zenoh.open`` itself, after ``retry_initial_s`` doubling up to
``retry_max_s``, while the agent keeps monitoring. Once open, zenoh reconnects a client to its
routers by itself and declares its tokens and queryables again; ``Providers.link`` hears of
each loss and return (the service journals them). Publications made while nobody is connected
go nowhere, and delivery resumes within about 0.1 s once the other side is back. Liveliness of a
vanished agent is noticed at once on a TCP reset, else at lease expiry
(``transport/link/tx/lease``, 10 s by default). Multicast scouting and gossip are always off
(:func:`zenoh_config`).

One agent per id: before it declares its token, the sink asks the network whether
``<prefix>/agent/<agent_id>/alive`` is already live; if it still is one lease later (a dead
predecessor's token is gone by then) the sink refuses with :class:`AgentIdInUse`.

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
#: a payload without ``schema`` is version 1. 3: ``load_pct`` is the shaft torque over the rated
#: torque, as a drive shows its load (it was the input power over the rated power; docs/method.md,
#: "Load is torque over rated torque").
SCHEMA_VERSION = 3
log = logging.getLogger(__name__)

QUERY_TOPICS = ("model", "spectrum", "thresholds", "events")
LIVE_CHECK_TIMEOUT_S = 2.0  #: how long the start-up query for a same-id agent waits for answers, s
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


class AgentIdInUse(ConnectionError):
    """Another live session holds ``<prefix>/agent/<agent_id>/alive``: a second agent with this id."""

    def __init__(self, agent_id: str, key: str):
        super().__init__(f"agent_id {agent_id!r} is already live on the zenoh network ({key}): "
                         f"another gateway runs with this id")
        self.agent_id, self.key = agent_id, key


@dataclass
class Providers:
    """Callbacks of the runtime; each query callback returns a JSON-able dict.

    ``model``/``spectrum``/``thresholds``/``events``: ``fn(drive, params) -> dict`` where
    ``params`` are the selector parameters as ``{str: str}``; raise ``KeyError`` for an unknown
    drive or item. ``command``: ``fn(drive, target, payload_text) -> dict`` for a query on
    ``<prefix>/<drive>/command`` (``target`` is ``<prefix>/<drive>``); raise ``PermissionError``
    to refuse it. ``diagnostics``: ``fn(drive) -> dict`` merged into each drive's diagnostics;
    ``health``: ``fn() -> dict`` merged into the agent health and the fleet answer. ``link``:
    ``fn(event, detail)`` hears ``"connected"``, ``"lost"``, ``"unreachable"`` and ``"refused"``
    (client mode). Callbacks run on zenoh or sender threads and must be thread-safe and quick.
    """

    model: QueryFn | None = None
    spectrum: QueryFn | None = None
    thresholds: QueryFn | None = None
    events: QueryFn | None = None
    command: Callable[[str, str, str], dict] | None = None
    diagnostics: Callable[[str], dict] | None = None
    health: Callable[[], dict] | None = None
    link: Callable[[str, dict], None] | None = None


@dataclass
class ZenohStats:
    """Counters of the sink (in diagnostics and health)."""

    changes: int = 0  #: on-change state puts
    periodic: int = 0  #: periodic state puts
    diagnostics: int = 0
    dropped: int = 0  #: changes dropped because the queue was full
    queries: int = 0
    errors: int = 0
    opens: int = 0  #: successful zenoh.open calls
    open_failures: int = 0  #: zenoh.open calls that found no router (client mode)
    link_losses: int = 0  #: times the last router went away (client mode)
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
    since: float | None = None  #: Unix time of the last state or quality change, s
    pub: object = None
    token: object = None  #: the drive's liveliness token while its input is live
    queryables: list = field(default_factory=list)


class ZenohSink(OpenClose):
    """Publishes :class:`DriveStatus` on zenoh (the :class:`protocols.base.Sink` contract).

    ``site``: the plant site named in the fleet answer (``""`` outside a plant). ``retry_initial_s``
    / ``retry_max_s``: the back-off of ``zenoh.open`` in client mode while no router answers, s.
    """

    name = "zenoh"

    def __init__(self, config: zenoh.Config, prefix: str, agent_id: str, *, drives: Sequence[str] = (),
                 providers: Providers | None = None, period_s: float = 1.0, diagnostics_period_s: float = 5.0,
                 queue_size: int = 256, site: str = "", retry_initial_s: float = 0.5, retry_max_s: float = 10.0):
        self.config, self.prefix = config, check_key(prefix, "prefix")
        self.agent_id = check_key(agent_id, "agent_id")
        if "/" in agent_id:
            raise ValueError(f"agent_id {agent_id!r}: one key chunk, no '/'")
        self.site = site
        self.mode = json.loads(config.get_json("mode") or '"peer"') or "peer"
        self.lease_s = (json.loads(config.get_json("transport/link/tx/lease") or "null") or 10_000) / 1000.0
        self.retry_initial_s, self.retry_max_s = float(retry_initial_s), float(retry_max_s)
        self.providers = providers or Providers()
        self.period_s, self.diagnostics_period_s = float(period_s), float(diagnostics_period_s)
        self.boot_id = uuid.uuid4().hex[:16]
        self.stats = ZenohStats()
        self._names = list(drives)
        self._drives: dict[str, _Drive] = {}
        self._lock = threading.Lock()
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._session = self._token = self._thread = None
        self._agent_qbls: list = []
        self._listener = None
        self._routers: set[str] = set()
        self._refused: AgentIdInUse | None = None
        self._t0 = time.monotonic()

    @property
    def agent_key(self) -> str:
        return f"{self.prefix}/agent/{self.agent_id}"

    @property
    def connected(self) -> bool:
        """An open session (in client mode: with at least one router reachable)."""
        return self._session is not None and (self.mode != "client" or bool(self._routers))

    # --- lifecycle --------------------------------------------------------------------------

    def open(self) -> None:
        """Open the session, declare tokens and queryables, start the sender thread.

        Raises :class:`AgentIdInUse` when another agent with this id is live, ``ConnectionError``
        when zenoh cannot open (in client mode only for a bad config: an unreachable router is
        retried in the background)."""
        if self._thread is not None:
            return
        self._refused = None
        self._q = queue.Queue(maxsize=self._q.maxsize)
        try:
            self._connect()
        except AgentIdInUse:
            raise
        except ConnectionError as err:
            if self.mode != "client":
                raise
            self._link("unreachable", {"error": str(err), "retry_s": self.retry_initial_s})
        self._thread = threading.Thread(target=self._run, name="zenoh-sink", daemon=True)
        self._thread.start()

    def _connect(self) -> None:
        """``zenoh.open``, the same-id check, then every declaration. Raises ``ConnectionError``."""
        try:
            session = zenoh.open(self.config)
        except zenoh.ZError as err:
            self.stats.open_failures += 1
            raise ConnectionError(f"zenoh open failed: {err}") from err
        try:
            self._check_unique(session)
        except BaseException:
            session.close()
            raise
        self.stats.opens += 1
        close = weakref.WeakMethod(self.close)
        _at_shutdown(lambda: (m := close()) and m())
        if self.mode == "client":
            self._routers = {str(z) for z in session.info.routers_zid()}
            self._listener = session.info.declare_transport_events_listener(self._on_transport)
        self._session = session
        self._token = session.liveliness().declare_token(f"{self.agent_key}/alive")
        self._agent_qbls = [session.declare_queryable(f"{self.agent_key}/health", self._on_health_query),
                            session.declare_queryable(f"{self.agent_key}/fleet", self._on_fleet_query)]
        for name in self._names:
            self._declare_drive(name)
        with self._lock:
            known = [n for n in self._drives if n not in self._names]
        for name in known:  # drives that published before the session opened
            self._declare_drive(name)
        log.info("zenoh sink open (%s): prefix %s, agent %s", self.mode, self.prefix, self.agent_id)
        if self.mode == "client":
            self._link("connected", {"routers": sorted(self._routers)})

    def _check_unique(self, session) -> None:
        """Refuse when ``<agent_key>/alive`` stays live for one lease (a dead predecessor's goes)."""
        key = f"{self.agent_key}/alive"
        deadline = time.monotonic() + self.lease_s + 0.5
        while True:
            live = [r for r in session.liveliness().get(key, timeout=LIVE_CHECK_TIMEOUT_S) if r.ok]
            if not live:
                return
            if time.monotonic() > deadline:
                raise AgentIdInUse(self.agent_id, key)
            time.sleep(0.25)

    def close(self) -> None:
        """Flush pending changes (at most ~3 s on a stuck link), remove the tokens, close the session; safe twice."""
        thread, self._thread = self._thread, None
        if thread is not None:
            try:
                self._q.put(_STOP, timeout=1.0)
            except queue.Full:
                pass
            thread.join(timeout=2.0)
        session, self._session = self._session, None
        if session is None:
            return
        try:
            self._token.undeclare()
            session.close()
        except zenoh.ZError as err:  # already closed underneath us
            log.warning("zenoh close: %s", err)
        with self._lock:
            for d in self._drives.values():
                d.pub = d.token = None
                d.queryables = []

    def _link(self, event: str, detail: dict) -> None:
        if self.providers.link is not None:
            self._guard("link provider", self.providers.link, event, detail)

    def _on_transport(self, event) -> None:
        """Client mode: notice when the last router goes away and when one is back."""
        if event.transport.whatami != zenoh.WhatAmI.ROUTER:
            return
        zid = str(event.transport.zid)
        before = bool(self._routers)
        if event.kind == zenoh.SampleKind.PUT:
            self._routers.add(zid)
        else:
            self._routers.discard(zid)
        if before and not self._routers:
            self.stats.link_losses += 1
            log.warning("zenoh: lost the last router (%s); zenoh reconnects by itself", zid)
            self._link("lost", {"router": zid})
        elif not before and self._routers:
            log.warning("zenoh: router %s connected again", zid)
            self._link("connected", {"routers": sorted(self._routers)})

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
            if d.since is None or (d.doc.get("state"), d.doc.get("quality")) != (status.state, status.quality):
                d.since = time.time()
            d.doc, d.key, d.mono = doc, key, time.monotonic()
        if changed and self._session is not None:
            self._enqueue((status.drive, doc))  # a snapshot: a later change does not overwrite it

    def _enqueue(self, item: tuple) -> None:
        self.stats.dropped += put_drop_oldest(self._q, item)

    # --- sender thread ----------------------------------------------------------------------

    def _run(self) -> None:
        now = time.monotonic()
        next_state, next_diag = now + self.period_s, now + min(self.diagnostics_period_s, 0.2)
        retry_s, next_open = self.retry_initial_s, now + self.retry_initial_s
        while True:
            wake = min(next_state, next_diag) if self._session is not None or self._refused else next_open
            try:
                item = self._q.get(timeout=max(0.0, wake - time.monotonic()))
            except queue.Empty:
                item = None
            if item is _STOP:
                self._drain()
                return
            now = time.monotonic()
            if self._session is None:
                if self._refused is None and now >= next_open:
                    retry_s, next_open = self._retry_open(retry_s)
                    next_state = now  # the latest states go out at once
                if self._session is None:
                    continue
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

    def _retry_open(self, retry_s: float) -> tuple[float, float]:
        """One more ``zenoh.open`` (client mode); returns the next back-off and when to try again."""
        try:
            self._connect()
        except AgentIdInUse as err:
            self._refused = err
            log.error("zenoh: %s; zenoh stays closed (the PLC registers are served)", err)
            self._link("refused", {"error": str(err), "key": err.key})
        except ConnectionError as err:
            retry_s = min(2 * retry_s, self.retry_max_s)
            log.info("zenoh: still no router (%s); next try in %.1f s", err, retry_s)
        return retry_s, time.monotonic() + retry_s

    def _drain(self) -> None:
        while True:
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                return
            if item is not _STOP and self._session is not None:
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
            self._guard("drive token", self._sync_token, drive, d)
        else:
            ok = self._guard("put state", session.put, f"{self.prefix}/{drive}/state", payload,
                             encoding=zenoh.Encoding.APPLICATION_JSON,
                             congestion_control=zenoh.CongestionControl.DROP)
            self.stats.periodic += ok

    def _sync_token(self, drive: str, d: _Drive) -> None:
        """The drive's token is live while its last status has input (quality not ``stale``)."""
        live = bool(d.doc) and d.doc.get("quality") != "stale"
        if live and d.token is None and self._session is not None:
            d.token = self._session.liveliness().declare_token(f"{self.prefix}/{drive}/alive")
        elif not live and d.token is not None:
            token, d.token = d.token, None
            token.undeclare()

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
        self._guard("put health", session.put, f"{self.agent_key}/health",
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

    def fleet(self) -> dict:
        """Every drive of this agent at once (the ``.../fleet`` queryable): per drive its state,
        quality, evidence per family, ``since`` (Unix s of the last state or quality change),
        ``t`` of the status, ``seq`` of the last put and whether its token is live."""
        with self._lock:
            drives = {n: {"state": d.doc.get("state"), "quality": d.doc.get("quality"),
                          "state_code": d.doc.get("state_code"), "quality_code": d.doc.get("quality_code"),
                          "evidence": d.doc.get("evidence") or {}, "fe_hz": d.doc.get("fe_hz"),
                          "load_pct": d.doc.get("load_pct"), "since": d.since, "t": d.doc.get("t"),
                          "seq": d.seq, "alive": d.token is not None}
                      for n, d in self._drives.items()}
        for name in self._names:
            drives.setdefault(name, {"state": None, "quality": None, "evidence": {}, "since": None, "t": None,
                                     "seq": 0, "alive": False})
        doc = {"agent": self.agent_id, "site": self.site, "prefix": self.prefix, "boot_id": self.boot_id,
               "t": time.time(), "uptime_s": round(time.monotonic() - self._t0, 3), "drives": drives}
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
        if self.providers.command is not None:
            d.queryables.append(session.declare_queryable(
                f"{self.prefix}/{drive}/command", lambda q, drive=drive: self._on_command(q, drive)))
        self._sync_token(drive, d)

    def _reply(self, q: zenoh.Query, key: str, fn) -> None:
        self.stats.queries += 1
        try:  # reply on our own concrete key, not the query's (which may hold wildcards)
            doc = fn()
            q.reply(key, json.dumps(doc, default=str), encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception as err:  # answer with an error reply instead of silence
            if isinstance(err, KeyError):
                msg = f"not found: {err}"
            elif isinstance(err, PermissionError):
                msg = f"refused: {err}"
            else:
                msg = f"{type(err).__name__}: {err}"
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

    def _on_command(self, q: zenoh.Query, drive: str) -> None:
        target = f"{self.prefix}/{drive}"
        payload = q.payload.to_string() if q.payload is not None else ""
        self._reply(q, f"{target}/command", lambda: self.providers.command(drive, target, payload))

    def _on_health_query(self, q: zenoh.Query) -> None:
        self._reply(q, f"{self.agent_key}/health", self.health)

    def _on_fleet_query(self, q: zenoh.Query) -> None:
        self._reply(q, f"{self.agent_key}/fleet", self.fleet)


def sink_from_config(zcfg, agent_id: str, drives: Sequence[str] = (), providers: Providers | None = None) -> ZenohSink:
    """Build a :class:`ZenohSink` from the agent config's ``[zenoh]`` table (``agent.runtime.config.ZenohCfg``)."""
    cfg = zenoh_config(zcfg.mode, zcfg.listen, zcfg.connect, dict(zcfg.inline), path=zcfg.config_file)
    return ZenohSink(cfg, zcfg.prefix, agent_id, drives=drives, providers=providers, period_s=zcfg.period_s,
                     diagnostics_period_s=zcfg.diagnostics_period_s, site=zcfg.site,
                     retry_initial_s=zcfg.retry_initial_s, retry_max_s=zcfg.retry_max_s)
