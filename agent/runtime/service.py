"""The agent service: sources -> pipelines -> sinks, with lifecycle, health and signals.

Threads: one reader per source (``Source.read`` with a timeout, blocks into a bounded per-drive
queue; the oldest block is dropped and counted when the pipeline falls behind, except for a
``lossless`` source, a file played as fast as the pipeline takes it, whose reader waits; a
``finished`` source's reader idles until the service stops), and one DSP
thread that runs every drive's :class:`agent.pipeline.DriveMonitor`, hands each status to the
sinks (Modbus server for the PLC, zenoh, journal; ``publish`` never blocks), applies PLC
commands and pings the systemd watchdog from the place that proves progress.

Order (as in Telegraf): sinks open before sources, sources close before sinks; ``READY=1`` is
sent only when the sinks are open and every source has been opened (a source whose link is
not there yet has been tried once and keeps being retried; STATUS names it). SIGTERM/SIGINT
stop cleanly (journal flushed), SIGHUP reloads the model library.
"""

from __future__ import annotations

import ctypes
import logging
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from agent.errors import InputError
from agent.evidence import AlarmConfig
from agent.library import ModelLibrary, Schedule
from agent.pipeline import DriveMonitor, PipelineConfig
from agent.runtime import sdnotify
from agent.runtime.config import Config
from agent.runtime.journal import Journal, JournalSink
from protocols.base import Block, DriveStatus, Sink, Source
from protocols.streaming import put_drop_oldest

log = logging.getLogger("pmsm-agent.service")
#: one line per state or quality change on stderr, whatever the log level (journald keeps it)
transitions_log = logging.getLogger("pmsm-agent.transitions")
transitions_log.setLevel(logging.INFO)
STATUS_PERIOD_S = 5.0  #: the sd_notify STATUS line is refreshed this often


def transition_line(drive: str, kind: str, detail: dict) -> str:
    """One structured line for a state or quality change: ``key=value`` pairs, the reason last."""
    parts = [f"drive={drive}", f"{kind}={detail.get('from')}->{detail.get('to')}"]
    for key in ("model", "fe_hz", "load_pct"):
        value = detail.get(key)
        if value not in (None, "") and value == value:
            parts.append(f"{key}={value:.2f}" if isinstance(value, float) else f"{key}={value}")
    reason = detail.get("reason")
    if isinstance(reason, dict):
        parts += [f"path={reason.get('path')}", f"feature={str(reason.get('feature', '')).replace(' ', '_')}"]
        if "z" in reason:
            parts.append(f"z={reason['z']}/{reason.get('threshold')}")
        if "evidence" in reason:
            parts.append(f"evidence={reason['evidence']}/{reason.get('threshold')}")
        if reason.get("freqs_hz"):
            parts.append("lines_hz=" + ",".join(f"{f:g}" for f in reason["freqs_hz"][:2]))
    elif reason:
        parts.append(f'reason="{reason}"')
    return " ".join(parts)

QUEUE_BLOCKS = 16  #: per drive, 1.6 s of 0.1 s blocks, held as float32 (:func:`compact`)
OPEN_WAIT_S = 10.0  #: READY waits at most this long for each source's first open
WORKER_START_S = 30.0  #: ... plus this long for DSP workers to start (imports, library)


def compact(block: Block) -> Block:
    """The block as it waits in a queue: samples as float32 (as the signal ring stores them)."""
    return replace(block, v_abc=block.v_abc.astype(np.float32), i_abc=block.i_abc.astype(np.float32))


def build_source(drive, rate_hz: float, span_s: float | None = None) -> Source:
    """The transport of one ``[[drives]]`` entry; ``span_s``: the pipeline's span (window_s x
    span_windows), the length of a Modbus snapshot (default: the default pipeline's)."""
    s, name, profile = drive.source, drive.name, drive.drive_profile
    if s.kind == "simulated":
        from agent.playback import simulated_source

        schedule = [(p.condition, p.seconds, p.load_pct or s.load_pct, p.severity) for p in s.schedule]
        return simulated_source(profile, schedule, name, seed=s.seed, block_s=s.block_s, speedup=s.speedup,
                                loop=s.loop)
    if s.kind == "replay":
        from agent.playback import replay_source

        return replay_source([str(f) for f in s.files], name, profile, block_s=s.block_s, speedup=s.speedup,
                             loop=s.loop)
    if s.kind == "serial":
        from protocols.serial_bridge import SerialBridgeSource

        return SerialBridgeSource(s.port, name, rate_hz, s.baud)
    if s.kind == "can":
        from protocols.can_bus import CanSource

        extra = {k: v for k, v in (("bitrate", s.bitrate), ("data_bitrate", s.data_bitrate)) if v}
        return CanSource(s.interface, s.channel, name, s.base_id, s.fd, rate_hz=rate_hz, **extra)
    if s.kind == "modbus":
        from protocols.modbus_drive import ModbusSnapshotSource, SnapshotSourceConfig

        if span_s is None:
            span_s = PipelineConfig().window_s * PipelineConfig().span_windows
        return ModbusSnapshotSource(SnapshotSourceConfig(  # a snapshot must hold a whole span
            drive=name, transport="rtu" if s.serial_port else "tcp", host=s.host or "127.0.0.1", port=s.port,
            serial_port=s.serial_port or "", baudrate=s.baud, device_id=s.unit_id,
            samples=int(round(span_s * rate_hz)), request_timeout_s=s.timeout_s, poll_interval_s=s.poll_interval_s,
            rate_hz=rate_hz))
    if s.kind == "nidaq":
        from protocols.nidaq import NidaqSource

        return NidaqSource.from_config(s, name, rate_hz)
    raise ValueError(f"unknown source kind {s.kind!r}")


def _agent_id_in_use(err: Exception) -> bool:
    """Did the zenoh sink refuse because another gateway with this agent_id is live?"""
    from protocols.zenoh_sink import AgentIdInUse

    return isinstance(err, AgentIdInUse)


def pipeline_config(cfg: Config) -> PipelineConfig:
    p = cfg.pipeline
    alarm = AlarmConfig(stretch_s=p.stretch_s, settle_s=p.settle_s, false_alarms_per_month=p.false_alarms_per_month,
                        gross_false_alarms_per_month=p.gross_false_alarms_per_month)
    return PipelineConfig(window_s=p.window_s, hop_s=p.hop_s, persist_hops=p.persist_hops,
                          alarm_hold_s=p.alarm_hold_s, stale_after_s=p.stale_after_s, learn_windows=p.learn_windows,
                          learn_stretches=p.learn_stretches, learn_min_s=p.learn_min_s, alarm=alarm)


@dataclass
class DriveRuntime:
    name: str
    source: Source
    monitor: DriveMonitor
    blocks: queue.Queue = field(default_factory=lambda: queue.Queue(maxsize=QUEUE_BLOCKS))
    dropped: int = 0
    gaps: int = 0
    first_open: threading.Event = field(default_factory=threading.Event)
    auto_learned: bool = False
    reader: threading.Thread | None = None


class Service:
    """The running agent; :func:`run_service` is the entry point."""

    def __init__(self, cfg: Config, on_transition: Callable[[str, str, dict], None] | None = None):
        self.cfg = cfg
        self.on_transition = on_transition or (lambda drive, kind, detail: None)
        self.stop_event = threading.Event()
        self._reload = threading.Event()
        state_dir = Path(cfg.state_dir)
        state_dir.mkdir(parents=True, exist_ok=True)
        self.journal = self._open_journal(cfg)
        p = cfg.pipeline
        self.library = ModelLibrary(cfg.library.path or state_dir / "library",
                                    Schedule(p.schedule_fe_tol_hz, p.schedule_load_tol_pct, p.schedule_hysteresis))
        pcfg = pipeline_config(cfg)
        self.names = [d.name for d in cfg.drives]
        self.last: dict[str, DriveStatus] = {}  #: each drive's newest status
        self._windows_seen: dict[str, int] = {}  #: status.window at the last STATUS line
        self.drives = {}  #: the drives this process runs (none when DSP workers run them)
        self.pool = None
        span_s = pcfg.window_s * pcfg.span_windows
        from agent.runtime.workers import WorkerPool, worker_count

        workers = worker_count(cfg)
        if workers > 1:
            self.pool = WorkerPool(cfg, self._worker_message, workers)
        for d in cfg.drives if self.pool is None else ():
            # a snapshot source (Modbus) delivers one span every capture (span_s) + transfer: quiet
            # that long between snapshots is normal, so "stale" waits for two missed snapshots
            dcfg = replace(pcfg, stale_after_s=pcfg.stale_after_s + 2 * span_s) if d.source.kind == "modbus" else pcfg
            monitor = DriveMonitor(d.name, d.drive_profile, self.library, dcfg,
                                   on_event=lambda kind, detail, name=d.name: self._event(name, kind, detail))
            source = build_source(d, d.drive_profile.sampling.rate_hz, span_s)
            self.drives[d.name] = DriveRuntime(d.name, source, monitor)
        self.sinks: list[Sink] = [JournalSink(self.journal)]
        self.plc = None
        if cfg.modbus_server.enabled:
            from protocols.modbus_plc import PlcModbusServer

            self.plc = PlcModbusServer(self.names, host=cfg.modbus_server.host, port=cfg.modbus_server.port)
            self.sinks.append(self.plc)
        self.gate = None  #: checks signed zenoh commands (agent.runtime.commands)
        self.remote_commands: deque = deque()  #: accepted zenoh commands, applied by the DSP thread
        self.command_counts = {"accepted": 0, "refused": 0, "refused_by_reason": {}}
        self._command_lock = threading.Lock()  #: command_counts and _refusal_journaled (zenoh threads)
        self._refusal_journaled: dict[str, tuple[float, int]] = {}  #: reason -> (last journal time, suppressed)
        if cfg.zenoh.enabled:
            from protocols.zenoh_sink import Providers, sink_from_config

            if cfg.commands.enabled:
                from agent.runtime.commands import CommandGate

                self.gate = CommandGate.from_config(cfg.commands)
            providers = Providers(model=self._q_model, thresholds=self._q_thresholds, spectrum=self._q_spectrum,
                                  events=self.journal.provider(), diagnostics=self._diagnostics,
                                  health=self._health, link=self._zenoh_link,
                                  command=self._zenoh_command if self.gate is not None else None)
            self.sinks.append(sink_from_config(cfg.zenoh, cfg.agent_id, self.names, providers))

    def _open_journal(self, cfg: Config):
        return Journal.from_config(cfg)

    def _worker_message(self, message) -> None:
        """A DSP worker's status, journal record or transition (agent.runtime.workers)."""
        kind = message[0]
        if kind == "status":
            self._publish(message[1])
        elif kind == "journal":
            _, what, drive, detail = message
            self.journal.record(what, drive, detail=detail)
            if what == "learning" and (detail or {}).get("event") == "learned":
                self.library.reload()  # the worker wrote it: queries see it too
        elif kind == "transition":
            self.on_transition(*message[1:])
        elif kind == "lost":  # the worker is restarting: its drives' last statuses are stale
            for name in message[1]:
                old = self.last.get(name, DriveStatus(name))
                self._publish(replace(old, quality="stale", t=time.time(),
                                      extra={**old.extra, "reason": f"DSP worker lost ({message[2]}), restarting"}))

    # -- events and queries ---------------------------------------------------------------------
    def _event(self, drive: str, kind: str, detail: dict) -> None:
        if kind in ("state", "quality"):
            transitions_log.log(logging.WARNING if detail.get("to") in ("caution", "warning") else logging.INFO,
                                "%s", transition_line(drive, kind, detail))
        if kind in ("learning", "learned", "learning_refused"):
            self.journal.record("learning", drive, detail={"event": kind, **detail})
        elif kind == "baseline":  # a switch between baselines leaves no state change: journal which one judges
            self.journal.record("baseline", drive, detail=detail)
        elif kind == "gap":  # counted, not journalled: snapshot sources make one per snapshot
            self.drives[drive].gaps += 1
        if kind in ("state", "quality", "learning", "learned", "learning_refused"):
            self.on_transition(drive, kind, detail)

    def _baseline(self, drive: str):
        name = self.last[drive].model if drive in self.last else ""
        if not name:
            raise KeyError(f"{drive}: no model scheduled")
        return name, self.library.baselines[name]

    def _q_model(self, drive: str, params: dict) -> dict:
        from agent.modelfile import baseline_to_json

        name, base = self._baseline(drive)
        doc = baseline_to_json(base)
        return {"drive": drive, "name": name, "model": doc["model"], "operating_point": doc["operating_point"],
                "cluster": {k: doc["cluster"][k] for k in ("centre", "cov", "limit", "confidence", "region")}}

    def _q_thresholds(self, drive: str, params: dict) -> dict:
        name, base = self._baseline(drive)
        th = base.thresholds
        return {"drive": drive, "name": name, "freqs_hz": th.freqs_hz.tolist(), "th2": th.th2.tolist(),
                "th3": th.th3.tolist(), "window_s": th.window_s}

    def _q_spectrum(self, drive: str, params: dict) -> dict:
        if self.pool is not None:
            return self.pool.query(drive, "spectrum", params)
        mon = self.drives[drive].monitor
        spectrum = mon.last_spectrum()
        if spectrum is None:
            raise KeyError(f"{drive}: no spectrum yet")
        name, freqs, amp = spectrum
        return {"drive": drive, "model": name, "freqs_hz": freqs.tolist(), "amplitude": amp.tolist()}

    def _health(self) -> dict:
        with self._command_lock:
            commands = {**self.command_counts, "refused_by_reason": dict(self.command_counts["refused_by_reason"])}
        return {"site": self.cfg.zenoh.site, "commands": commands}

    def _zenoh_link(self, event: str, detail: dict) -> None:
        """The zenoh sink's link events (client mode): journalled as kind ``zenoh``."""
        self.journal.record("zenoh", detail={"event": event, **detail})

    def _zenoh_command(self, drive: str, target: str, payload: str) -> dict:
        """A signed command from a zenoh query (a zenoh thread): checked, queued for the DSP
        thread, journalled; a refusal is counted, journalled (the same reason at most once per
        ``journal.error_holdoff_s``, with the number held back) and raised to the sender."""
        from agent.runtime.commands import CommandRefused

        try:
            cmd = self.gate.check(drive, target, payload)
        except CommandRefused as err:
            now = time.monotonic()
            with self._command_lock:
                counts = self.command_counts
                counts["refused"] += 1
                counts["refused_by_reason"][err.reason] = counts["refused_by_reason"].get(err.reason, 0) + 1
                last, held = self._refusal_journaled.get(err.reason, (-1e18, 0))
                journal = now - last >= self.cfg.journal.error_holdoff_s
                self._refusal_journaled[err.reason] = (now, 0) if journal else (last, held + 1)
            if journal:
                self.journal.record("command", drive, detail={"accepted": False, "reason": err.reason,
                                                              "error": str(err), "held_back": held})
                log.warning("%s: zenoh command refused: %s", drive, err)
            raise
        with self._command_lock:
            self.command_counts["accepted"] += 1
        self.journal.record("command", drive, detail={"accepted": True, "command": cmd.kind, "role": cmd.role,
                                                      "by": cmd.by, "t": cmd.t})
        self.remote_commands.append(cmd)
        return {"accepted": True, "command": cmd.kind, "drive": drive, "role": cmd.role}

    def _diagnostics(self, drive: str) -> dict:
        if self.pool is not None:
            diag = self.pool.diagnostics(drive)
            diag.pop("opened", None)
            diag.pop("learn_progress_pct", None)
            return {**diag, "library": sorted(self.library.baselines)}
        d = self.drives[drive]
        return {"source": d.source.stats.as_dict(), "queue": d.blocks.qsize(), "dropped_blocks": d.dropped, "stream_gaps": d.gaps,
                "learning": d.monitor.learning, "library": sorted(self.library.baselines)}

    # -- threads --------------------------------------------------------------------------------
    def _reader(self, d: DriveRuntime) -> None:
        backoff = 0.5
        while not self.stop_event.is_set():
            try:
                d.source.open()
                d.source.stats.opened_at = time.time()
                d.first_open.set()
                break
            except Exception as err:  # a transport that is not there yet: retry with backoff
                d.source.stats.last_error = str(err)
                d.first_open.set()  # tried once: READY may go out, the link keeps being retried
                log.warning("%s: cannot open source (%s); retrying in %.1f s", d.name, err, backoff)
                self.stop_event.wait(backoff)
                backoff = min(2 * backoff, 30.0)
        lossless = getattr(d.source, "lossless", False)
        while not self.stop_event.is_set():
            if getattr(d.source, "finished", False):  # a played-out file: idle, never spin
                log.info("%s: source finished", d.name)
                self.stop_event.wait()
                break
            block = d.source.read(timeout=0.2)
            if block is None:
                continue
            block = compact(block)
            if not lossless:  # a live link: a slow pipeline loses the oldest blocks, never the link
                d.dropped += put_drop_oldest(d.blocks, block)
                continue
            while not self.stop_event.is_set():  # a file played as fast as the pipeline takes it
                try:
                    d.blocks.put(block, timeout=0.2)
                    break
                except queue.Full:
                    continue

    def _publish(self, status: DriveStatus) -> None:
        self.last[status.drive] = status
        for sink in self.sinks:
            try:
                sink.publish(status)
            except Exception:  # a sink must never take the pipeline down
                log.exception("sink %s failed", getattr(sink, "name", sink))

    def _dsp_step(self) -> bool:
        """One pass over the drives; returns True if any block was processed."""
        busy = False
        for d in self.drives.values():
            try:
                block: Block = d.blocks.get_nowait()
            except queue.Empty:
                status = d.monitor.tick()
                if status is not None:
                    self._publish(status)
                continue
            busy = True
            try:
                statuses = d.monitor.process(block)
            except Exception as err:  # a bug must not stop the other drives: journal it, restart the stream
                log.exception("%s: pipeline failed on a block", d.name)
                self.journal.record("error", d.name, detail={"event": "pipeline", "error": repr(err)})
                d.monitor.reset_stream()
                continue
            for status in statuses:
                self._publish(status)
                if self._auto_learn_due(d, status):
                    d.auto_learned = True
                    d.monitor.start_learning()  # named by the learned operating point
        return busy

    def status_line(self, period_s: float) -> str:
        """What ``systemctl status`` shows: per drive its state, quality and learning progress,
        and the windows assessed per second over the last ``period_s``."""
        items = []
        for name in self.names:
            st = self.last.get(name, DriveStatus(name))
            if self.pool is None:
                learning = self.drives[name].monitor.learn_progress_pct if self.drives[name].monitor.learning else None
            else:
                learning = self.pool.diagnostics(name).get("learn_progress_pct") if self.pool.diagnostics(name).get("learning") else None
            text = f"{name} {st.state}/{st.quality}" + (f" learning {learning:.0f}%" if learning is not None else "")
            rate = max(0, st.window - self._windows_seen.get(name, 0)) / max(period_s, 1e-3)
            self._windows_seen[name] = st.window
            items.append(f"{text} {rate:.1f} win/s")
        return "; ".join(items)

    def _auto_learn_due(self, d: "DriveRuntime", status: DriveStatus) -> bool:
        """First commissioning only: with ``auto_learn``, a running drive with no baseline of its own
        in the library starts learning once per run. It never learns again by itself (a second
        operating point, a relearn after refusal: ``pmsm-agent learn`` or the PLC's command), so it
        cannot learn from a fault that develops later."""
        if not self.cfg.pipeline.auto_learn or d.auto_learned or d.monitor.learning or status.quality != "no_model":
            return False
        if str(status.extra.get("reason") or "").startswith("not running"):
            return False
        return not any(name.startswith(f"{d.name}_") for name in self.library.baselines)

    def _commands(self) -> None:
        """Apply the PLC's commands and the accepted zenoh commands (ACK of a zenoh command goes
        to the PLC server, which keeps ALARM_ACKED, as the PLC's own ACK does)."""
        for cmd in self.plc.commands() if self.plc is not None else ():
            if cmd.kind == "relearn" and cmd.drive in self.names:
                self._relearn(cmd.drive, "relearn requested by the PLC")
        while self.remote_commands:
            cmd = self.remote_commands.popleft()
            if cmd.kind == "relearn" and cmd.drive in self.names:
                self._relearn(cmd.drive, f"relearn requested over zenoh by {cmd.by or cmd.role} ({cmd.role})")
            elif cmd.kind == "acknowledge" and self.plc is not None:
                self.plc.acknowledge(cmd.drive)

    def _relearn(self, drive: str, why: str) -> None:
        """Relearn ``drive`` (in its DSP worker where there are workers) and journal ``why``."""
        if self.pool is not None:
            self.pool.send(drive, ("relearn", drive))
        else:
            self.relearn(drive)
        self.journal.record("learning", drive, detail={"event": why})

    def relearn(self, drive: str) -> None:
        """Learn the drive's current operating point again: the new baseline replaces the one that
        covers it (the PLC's or an authorised zenoh relearn command); refused while the drive reads
        warning (:meth:`agent.pipeline.DriveMonitor.relearn`)."""
        self.drives[drive].monitor.relearn()

    def run(self, max_seconds: float | None = None) -> int:
        """Open everything, run until stopped (or ``max_seconds``), close everything."""
        t_end = None if max_seconds is None else time.monotonic() + max_seconds
        self.journal.record("start", detail={"drives": list(self.drives), "library": sorted(self.library.baselines)})
        opened = []
        try:
            for sink in self.sinks:
                try:
                    sink.open()
                except Exception as err:  # a busy port, an endpoint zenoh cannot listen on: the config's to fix
                    if getattr(sink, "name", "") == "zenoh" and _agent_id_in_use(err):
                        self.journal.record("error", detail={"event": "agent_id in use", "error": str(err)})
                        raise InputError(str(err), source=str(self.cfg.source)) from err
                    key = {"modbus-plc": "modbus_server.port", "zenoh": "zenoh.listen"}.get(getattr(sink, "name", ""))
                    if key is None:
                        raise
                    raise InputError(f"{key}: {err}", source=str(self.cfg.source)) from err
                opened.append(sink)
            for d in self.drives.values():
                d.reader = threading.Thread(target=self._reader, args=(d,), name=f"source-{d.name}", daemon=True)
                d.reader.start()
            if self.pool is not None:
                self.pool.start()
            watchdog = sdnotify.Watchdog()
            for d in self.drives.values():  # READY once every source has been opened (or tried)
                d.first_open.wait(timeout=OPEN_WAIT_S)
            if self.pool is not None:
                self.pool.wait_open(WORKER_START_S + OPEN_WAIT_S)
            down = [name for name in self.names if self._diagnostics(name).get("source", {}).get("last_error")]
            sdnotify.ready(f"monitoring {len(self.drives)} drive(s)" + (f"; not connected: {', '.join(down)}" if down else ""))
            last_status = time.monotonic()
            next_status = last_status + 1.0  # the first live line soon after READY
            while not self.stop_event.is_set():
                if t_end is not None and time.monotonic() > t_end:
                    break
                if self._reload.is_set():
                    self._reload.clear()
                    self.library.reload()
                    if self.pool is not None:
                        self.pool.send(None, ("reload",))
                    self.journal.record("reload", detail={"library": sorted(self.library.baselines)})
                    sdnotify.notify("READY=1", "STATUS=library reloaded")
                busy = self._dsp_step() if self.pool is None else self.pool.pump(0.01)
                if time.monotonic() >= next_status:
                    sdnotify.status(self.status_line(time.monotonic() - last_status))
                    last_status, next_status = time.monotonic(), time.monotonic() + STATUS_PERIOD_S
                self._commands()
                if self.pool is None or self.pool.healthy():
                    watchdog.ping()
                if not busy and self.pool is None:
                    time.sleep(0.01)
            return 0
        finally:
            sdnotify.stopping("stopping")
            self.stop_event.set()
            if self.pool is not None:
                self.pool.stop()
            for d in self.drives.values():
                if d.reader is not None:
                    d.reader.join(timeout=2.0)
                d.source.close()
            for sink in reversed(opened):
                try:
                    sink.close()
                except Exception:
                    log.exception("closing %s", getattr(sink, "name", sink))
            self.journal.record("stop")
            self.journal.close()

    def install_signal_handlers(self) -> None:
        signal.signal(signal.SIGTERM, lambda *_: self.stop_event.set())
        signal.signal(signal.SIGINT, lambda *_: self.stop_event.set())
        signal.signal(signal.SIGHUP, lambda *_: (sdnotify.reloading("reloading the model library"), self._reload.set()))


def bound_heap() -> None:
    """At most two glibc malloc arenas: by default every reader thread that allocates a block
    while another does gets an arena of its own (up to 8 per core), and the freed blocks of each
    stay resident; measured about 3 MB per drive (docs/benchmarks.md). Not glibc: nothing to do."""
    try:
        ctypes.CDLL("libc.so.6").mallopt(-8, 2)  # M_ARENA_MAX
    except (OSError, AttributeError):
        pass


def run_service(cfg: Config, max_seconds: float | None = None, on_transition=None) -> int:
    """``pmsm-agent run``: the service until SIGTERM (or ``max_seconds``)."""
    bound_heap()
    service = Service(cfg, on_transition)
    if threading.current_thread() is threading.main_thread():
        service.install_signal_handlers()
    return service.run(max_seconds)
