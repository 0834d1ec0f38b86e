"""DSP worker processes: the drives split into groups, each group's sources and pipelines run by
a process of its own, so that the drives' signal processing spreads over the cores.

A worker is :class:`agent.runtime.service.Service` on its group's drives with the pipe to the
agent's process in place of the sinks and the journal: statuses, journal records and transitions
go up the pipe; PLC commands, library reloads and queries come down it. The agent's process (the
supervisor) keeps the journal, the PLC's Modbus server, the zenoh session and the systemd
watchdog, which it pings only while every worker beats (at least every ``BEAT_S``). A worker that
dies, or stops beating for ``STALL_S``, is killed and started again after a backoff; the other
workers' drives never wait for it. Workers are spawned (never forked from a process that runs
zenoh's and the Modbus server's threads) and carry no systemd notify socket.
"""

from __future__ import annotations

import itertools
import logging
import math
import multiprocessing
import os
import signal
import threading
import time
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection, wait

from agent.runtime.config import Config
from agent.runtime.service import Service, bound_heap

log = logging.getLogger("pmsm-agent.workers")

BEAT_S = 1.0  #: a worker reports its drives' diagnostics this often (its liveness)
STALL_S = 20.0  #: a worker silent this long is stuck: it is killed and started again
RESTART_BACKOFF_S = (1.0, 30.0)  #: first and longest wait before a worker is started again
QUERY_TIMEOUT_S = 2.0  #: a query to a worker (a drive's spectrum) waits at most this long
DRIVES_IN_PROCESS = 4  #: up to this many drives the agent's process runs them itself (``workers = 0``)


def worker_count(cfg: Config) -> int:
    """DSP processes for ``cfg``: its ``workers``, or with 0 one per core (at most one per
    ``DRIVES_IN_PROCESS`` drives); 1 means the agent's own process, no worker."""
    if cfg.workers:
        return min(cfg.workers, len(cfg.drives))
    if len(cfg.drives) <= DRIVES_IN_PROCESS:
        return 1
    return max(1, min(os.cpu_count() or 1, math.ceil(len(cfg.drives) / DRIVES_IN_PROCESS)))


def drive_groups(cfg: Config, workers: int) -> list[tuple[str, ...]]:
    """The drives dealt round-robin to ``workers`` groups (config order within a group)."""
    names = [d.name for d in cfg.drives]
    return [tuple(names[k::workers]) for k in range(workers)]


# --- the worker's side ---------------------------------------------------------------------------

class _PipeJournal:
    """The journal as a worker sees it: records go up the pipe (the worker's own start and stop
    are the supervisor's to journal, as ``worker`` events)."""

    def __init__(self, send):
        self._send = send

    def record(self, kind: str, drive: str = "", detail: dict | None = None) -> None:
        if kind not in ("start", "stop"):
            self._send(("journal", kind, drive, detail))

    def close(self) -> None:
        pass


class _PipeSink:
    """Every status up the pipe (the supervisor's sinks filter and publish)."""

    name = "worker-pipe"

    def __init__(self, send):
        self._send = send

    def open(self) -> None:
        pass

    def publish(self, status) -> None:
        self._send(("status", status))

    def close(self) -> None:
        pass


class WorkerService(Service):
    """A group's drives in a worker process: the service's readers and DSP loop, with the pipe
    to the supervisor as its only sink and journal."""

    def __init__(self, cfg: Config, conn: Connection):
        self.conn = conn
        self._send_lock = threading.Lock()
        self._next_beat = 0.0
        super().__init__(cfg, on_transition=lambda drive, kind, detail: self._send(("transition", drive, kind, detail)))
        self.sinks = [_PipeSink(self._send)]

    def _open_journal(self, cfg: Config):
        return _PipeJournal(self._send)

    def _send(self, message) -> None:
        with self._send_lock:
            try:
                self.conn.send(message)
            except (BrokenPipeError, EOFError, OSError):  # the supervisor is gone: stop
                self.stop_event.set()

    def _commands(self) -> None:
        """Between DSP passes: the supervisor's messages, and a beat every ``BEAT_S``."""
        try:
            while self.conn.poll():
                self._handle(self.conn.recv())
        except (EOFError, OSError):
            self.stop_event.set()
            return
        now = time.monotonic()
        if now >= self._next_beat:
            self._next_beat = now + BEAT_S
            self._send(("beat", {name: {**self._diagnostics(name), "opened": d.first_open.is_set(),
                                        "learn_progress_pct": d.monitor.learn_progress_pct}
                                 for name, d in self.drives.items()}))

    def _handle(self, message) -> None:
        kind = message[0]
        if kind == "stop":
            self.stop_event.set()
        elif kind == "reload":
            self._reload.set()
        elif kind == "relearn":
            self.relearn(message[1])
        elif kind == "query":
            _, ident, what, drive, params = message
            try:
                reply = {"spectrum": self._q_spectrum}[what](drive, params)
                self._send(("reply", ident, reply, None))
            except Exception as err:  # the asker gets the error, the worker keeps running
                self._send(("reply", ident, None, f"{type(err).__name__}: {err}"))


def _worker_main(cfg: Config, conn: Connection) -> None:
    """A worker process: its group's service until the supervisor stops it or goes away."""
    for key in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):  # systemd talks to the supervisor only
        os.environ.pop(key, None)
    bound_heap()
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C: the supervisor stops the workers
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    service = WorkerService(cfg, conn)
    signal.signal(signal.SIGTERM, lambda *_: service.stop_event.set())
    service.run()


# --- the supervisor's side -----------------------------------------------------------------------

@dataclass
class _Worker:
    index: int
    drives: tuple[str, ...]
    process: multiprocessing.process.BaseProcess | None = None
    conn: Connection | None = None
    last_beat: float = 0.0
    started: float = 0.0
    restart_at: float | None = None
    restarts: int = 0
    diagnostics: dict = field(default_factory=dict)


class WorkerPool:
    """The supervisor's workers: started, read, restarted, stopped. ``deliver(message)`` takes
    each worker's ``status`` / ``journal`` / ``transition`` message in the supervisor's loop, and
    ``("lost", drives, why)`` when a worker is lost (its drives are stale until it is back)."""

    def __init__(self, cfg: Config, deliver, workers: int):
        self.cfg, self.deliver = cfg, deliver
        self._ctx = multiprocessing.get_context("spawn")
        self.workers = [_Worker(k, group) for k, group in enumerate(drive_groups(cfg, workers))]
        self._of_drive = {name: w for w in self.workers for name in w.drives}
        self._send_lock = threading.Lock()
        self._ids = itertools.count()
        self._replies: dict[int, list] = {}
        self._replied = threading.Condition()

    def _group_config(self, w: _Worker) -> Config:
        return replace(self.cfg, drives=tuple(d for d in self.cfg.drives if d.name in w.drives),
                       modbus_server=replace(self.cfg.modbus_server, enabled=False),
                       zenoh=replace(self.cfg.zenoh, enabled=False), workers=1)

    def _start(self, w: _Worker) -> None:
        ours, theirs = self._ctx.Pipe()
        w.process = self._ctx.Process(target=_worker_main, args=(self._group_config(w), theirs),
                                      name=f"pmsm-dsp-{w.index}", daemon=True)
        w.process.start()
        theirs.close()
        w.conn, w.started, w.last_beat, w.restart_at, w.diagnostics = ours, time.monotonic(), time.monotonic(), None, {}

    def start(self) -> None:
        for w in self.workers:
            self._start(w)

    def wait_open(self, timeout: float) -> None:
        """Until every worker has opened (or tried) each of its sources, at most ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not all(
                w.diagnostics and all(d.get("opened") for d in w.diagnostics.values()) for w in self.workers):
            self.pump(0.05)

    def pump(self, timeout: float) -> bool:
        """Handle what the workers sent (waiting at most ``timeout`` s for it), restart the dead
        and the stuck; returns True if any message came."""
        now = time.monotonic()
        for w in self.workers:
            if w.restart_at is not None and now >= w.restart_at:
                self._start(w)
                self.deliver(("journal", "worker", "", {"event": "restarted", "worker": w.index,
                                                          "drives": list(w.drives), "restarts": w.restarts}))
            elif w.conn is not None and now - w.last_beat > STALL_S:
                self._lost(w, f"no beat for {now - w.last_beat:.0f} s")
        live = {w.conn: w for w in self.workers if w.conn is not None}
        busy = False
        for conn in wait(list(live), timeout):
            w = live[conn]
            try:
                while conn.poll():
                    self._receive(w, conn.recv())
                    busy = True
            except (EOFError, OSError):
                w.process.join(1.0)
                self._lost(w, f"exit code {w.process.exitcode}")
        return busy

    def _receive(self, w: _Worker, message) -> None:
        kind = message[0]
        if kind == "beat":
            w.last_beat, w.diagnostics = time.monotonic(), message[1]
        elif kind == "reply":
            with self._replied:
                self._replies[message[1]] = list(message[2:])
                self._replied.notify_all()
        else:
            self.deliver(message)

    def _lost(self, w: _Worker, why: str) -> None:
        """A worker died or stalled: kill what is left of it and schedule its restart."""
        if w.process is not None and w.process.is_alive():
            w.process.kill()
            w.process.join(2.0)
        if w.conn is not None:
            w.conn.close()
        w.conn = None
        first, longest = RESTART_BACKOFF_S
        uptime = time.monotonic() - w.started
        w.restarts = 0 if uptime > 10 * longest else w.restarts + 1  # a long healthy run forgets old failures
        w.restart_at = time.monotonic() + min(longest, first * 2 ** max(0, w.restarts - 1))
        log.error("DSP worker %d (%s) lost: %s; restarting", w.index, ", ".join(w.drives), why)
        self.deliver(("journal", "error", "", {"event": "worker", "worker": w.index, "drives": list(w.drives),
                                                 "error": why}))
        self.deliver(("lost", w.drives, why))

    def healthy(self) -> bool:
        """Every worker beats (or is being restarted): the supervisor may ping the watchdog."""
        now = time.monotonic()
        return all(w.conn is None or now - w.last_beat <= STALL_S for w in self.workers)

    def send(self, drive: str | None, message) -> None:
        """``message`` to the worker of ``drive`` (None: to every worker)."""
        targets = self.workers if drive is None else [self._of_drive[drive]]
        with self._send_lock:
            for w in targets:
                if w.conn is not None:
                    try:
                        w.conn.send(message)
                    except (BrokenPipeError, OSError):
                        pass  # the loop sees the worker gone

    def query(self, drive: str, what: str, params: dict):
        """Ask the worker of ``drive`` (from any thread); raises KeyError when it cannot answer."""
        ident = next(self._ids)
        self.send(drive, ("query", ident, what, drive, params))
        with self._replied:
            if not self._replied.wait_for(lambda: ident in self._replies, QUERY_TIMEOUT_S):
                raise KeyError(f"{drive}: its DSP worker did not answer")
            reply, error = self._replies.pop(ident)
        if error is not None:
            raise KeyError(error)
        return reply

    def diagnostics(self, drive: str) -> dict:
        """The drive's last reported diagnostics (empty while its worker starts)."""
        return dict(self._of_drive[drive].diagnostics.get(drive, {}))

    def pids(self) -> list[int]:
        return [w.process.pid for w in self.workers if w.process is not None and w.process.is_alive()]

    def stop(self, timeout: float = 10.0) -> None:
        """Stop every worker (SIGTERM-like: its sources close), then kill what remains."""
        self.send(None, ("stop",))
        deadline = time.monotonic() + timeout
        for w in self.workers:
            if w.process is not None:
                w.process.join(max(0.1, deadline - time.monotonic()))
                if w.process.is_alive():
                    w.process.kill()
                    w.process.join(2.0)
            if w.conn is not None:
                w.conn.close()
                w.conn = None
