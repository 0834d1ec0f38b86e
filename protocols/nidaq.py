"""NI-DAQmx transport: phase voltages and currents of one drive from a CompactDAQ chassis, e.g.
an NI-9244 (3 phase voltages against N) and an NI-9239 (3 current-transducer voltages) in ONE
hardware-timed task, so both modules share the chassis timebase (docs/hardware.md).

:class:`NidaqSource` (the :class:`protocols.base.Source` contract):

* ``nidaqmx`` is an optional extra (``pip install 'pmsm-agent[nidaqmx]'``), imported in
  :meth:`~NidaqSource.open`, never at module import; a missing package raises
  :class:`NidaqNotInstalled` (an ``ImportError``) naming the extra. The module can be injected
  (``NidaqSource(..., nidaqmx_module=m)`` or the module attribute :data:`nidaqmx`) for tests.
* The task: voltage channels then current channels (rows ``va vb vc ia ib ic`` in that order),
  continuous sampling at the requested rate with a DAQmx buffer of ``buffer_s`` (an even multiple
  of the block), an every-N-samples-acquired-into-buffer event of ``block_samples`` and a done
  event, both registered BEFORE ``start()``. The rate is read back from
  ``task.timing.samp_clk_rate`` (delta-sigma modules coerce it to 12.8 MHz / 256 / n) and used for
  ``Block.rate_hz``; a coerced rate, or one that differs from the profile's ``sampling.rate_hz``,
  is logged as a warning and kept in :attr:`NidaqSource.rate_warning` (the pipeline works at the
  profile's rate).
* The every-N callback (a DAQmx thread) reads with ``AnalogMultiChannelReader.read_many_sample``
  into a preallocated ``(6, block_samples)`` buffer and appends a copy to a bounded queue of
  ``max_queue_blocks``; when the consumer is slow the OLDEST block is dropped
  (``counters["queue_overruns"]``), so memory stays bounded and the next delivered block's
  ``first_sample`` jumps. The callback never raises and never touches the task: errors are
  handed to the consumer thread.
* :meth:`~NidaqSource.read` never raises. It returns a :class:`Block` (``v_abc`` in V,
  ``i_abc`` = shunt/transducer volts x ``current_scale_a_per_v`` in A), or ``None`` at the timeout
  or while the task is down. In the consumer thread it handles what the callback reported:

  - DAQmx error -200279 (``SAMPLES_NO_LONGER_AVAILABLE``: the DAQmx buffer overran): stop and
    start the same task (``counters["buffer_overruns"]``, ``counters["restarts"]``); the next
    block's ``first_sample`` jumps by the estimated number of lost samples;
  - any other DAQmx error, a done event with an error status, or no samples for ``stall_s``
    (``counters["stalls"]``): the task is closed and recreated with exponential backoff
    (``counters["daq_errors"]`` per failure, ``stats.reconnects`` per recovery).

  ``stats.gaps`` counts the discontinuities in the delivered stream (a ``first_sample`` other
  than the end of the previous block, whatever the cause); ``stats.frames`` counts DAQmx reads.
  ``first_sample`` is exact within one run of the task and an estimate across restarts
  (from ``in_stream.total_samp_per_chan_acquired`` and wall-clock time); it always moves forward.
* :meth:`~NidaqSource.open` raises ``ConnectionError`` if the first task cannot be created
  (no driver, device absent or reserved; the runtime retries) and ``ValueError`` if the channel
  strings do not name 3 + 3 channels. :meth:`~NidaqSource.close` stops and closes the task and
  is safe to call twice.

:meth:`NidaqSource.from_config` maps ``[drives.source] kind = "nidaq"``
(:class:`agent.runtime.config.NidaqCfg`) onto the constructor.
"""

from __future__ import annotations

import importlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from protocols.base import Block, OpenClose, SourceStats
from protocols.streaming import Backoff, BlockAssembler

log = logging.getLogger(__name__)

#: Injected ``nidaqmx`` module (tests); ``None``: import the real package in ``open()``.
nidaqmx: Any = None

#: DAQmx error: samples no longer available (the input buffer overran, the app fell behind).
SAMPLES_NO_LONGER_AVAILABLE = -200279
#: Both modules sample at 12.8 MHz / 256 / n; 25 kS/s is n = 2.
DEFAULT_RATE_HZ = 25_000.0
DEFAULT_BLOCK_SAMPLES = 2500
N_CHANNELS = 6
COUNTERS = ("daq_errors", "buffer_overruns", "queue_overruns", "restarts", "stalls")
EXTRA_HINT = "pip install 'pmsm-agent[nidaqmx]'"


class NidaqNotInstalled(ImportError):
    """The optional ``nidaqmx`` package is missing."""


def load_nidaqmx(injected: Any = None) -> Any:
    """The ``nidaqmx`` module: ``injected``, else the module attribute :data:`nidaqmx`, else the
    real package with its ``constants``, ``errors`` and ``stream_readers`` submodules."""
    if injected is not None:
        return injected
    if nidaqmx is not None:
        return nidaqmx
    try:
        mod = importlib.import_module("nidaqmx")
        for sub in ("constants", "errors", "stream_readers"):
            importlib.import_module(f"nidaqmx.{sub}")
    except ImportError as err:
        raise NidaqNotInstalled(
            f"the nidaq source needs the optional 'nidaqmx' package ({err}); install it with "
            f"`{EXTRA_HINT}` (the NI-DAQmx driver itself comes from NI's installer, "
            "see docs/hardware.md)") from err
    return mod


class _Run:
    """One started run of the task: what the callback writes into, and its bookkeeping."""

    __slots__ = ("buf", "reader", "active", "read", "t_last")

    def __init__(self, reader, n_samples: int):
        self.buf = np.zeros((N_CHANNELS, n_samples))  # preallocated, reused by every callback
        self.reader = reader
        self.active = True  # False once stopped, replaced or faulted: late callbacks are dropped
        self.read = 0  # samples per channel read in this run
        self.t_last = time.monotonic()  # wall time of the last read (or of the start)


class NidaqSource(OpenClose):
    """Phase voltages and currents of one drive from an NI-DAQmx task (see the module docstring)."""

    def __init__(self, voltage_channels: str, current_channels: str, drive: str,
                 rate_hz: float = DEFAULT_RATE_HZ, *, profile_rate_hz: float | None = None,
                 voltage_range_v: float = 800.0, current_range_v: float = 10.0,
                 current_scale_a_per_v: float | Sequence[float] = 1.0,
                 block_samples: int = DEFAULT_BLOCK_SAMPLES, max_queue_blocks: int = 20,
                 buffer_s: float = 2.0, stall_s: float | None = None,
                 backoff_s: tuple[float, float] = (0.5, 10.0), task_name: str | None = None,
                 name: str | None = None, nidaqmx_module: Any = None):
        if not voltage_channels or not current_channels:
            raise ValueError("voltage_channels and current_channels must name physical channels")
        if not (rate_hz > 0 and block_samples >= 1 and max_queue_blocks >= 1 and buffer_s > 0):
            raise ValueError("rate_hz, block_samples, max_queue_blocks and buffer_s must be positive")
        if not (voltage_range_v > 0 and current_range_v > 0):
            raise ValueError("voltage_range_v and current_range_v must be positive")
        scale = np.broadcast_to(np.asarray(current_scale_a_per_v, dtype=float), (3,)).copy()
        if not (np.isfinite(scale).all() and (scale != 0).all()):
            raise ValueError(f"current_scale_a_per_v must be finite and non-zero, got {current_scale_a_per_v!r}")
        self.voltage_channels = voltage_channels
        self.current_channels = current_channels
        self.drive = drive
        self.requested_rate_hz = float(rate_hz)
        self.profile_rate_hz = float(profile_rate_hz) if profile_rate_hz is not None else float(rate_hz)
        self.rate_hz = self.requested_rate_hz  #: the task's actual rate once open
        self.rate_warning = ""  #: why the actual rate is suspicious ("" if it is not)
        self.voltage_range_v = float(voltage_range_v)
        self.current_range_v = float(current_range_v)
        self.current_scale = scale[:, None]  # (3, 1) A/V
        self.block_samples = int(block_samples)
        self.max_queue_blocks = int(max_queue_blocks)
        per = max(4, math.ceil(buffer_s * rate_hz / self.block_samples))
        self.buffer_samples = self.block_samples * (per + per % 2)  # an even multiple of the event interval
        self.stall_s = float(stall_s) if stall_s is not None else max(2.0, 10.0 * self.block_samples / rate_hz)
        self.backoff_min, self.backoff_max = (float(b) for b in backoff_s)
        self.task_name = task_name or f"pmsm-agent-{drive}"
        self.name = name or f"nidaq:{drive}"
        self.stats = SourceStats()
        self.counters = dict.fromkeys(COUNTERS, 0)
        self._injected = nidaqmx_module
        self._mod: Any = None
        self._io = threading.RLock()  # task lifecycle (consumer side); never taken by callbacks
        self._cond = threading.Condition()  # queue, counters shared with the callback thread
        self._queue: deque[tuple[int, np.ndarray]] = deque()
        self._task: Any = None
        self._run: _Run | None = None
        self._pending: tuple[int | None, str] | None = None  # a fault reported by a callback
        self._wanted = False
        self._next_sample = 0  # stream index of the next sample the callback will read
        self._asm = BlockAssembler(drive, self.rate_hz, self.stats)  # delivered blocks: seq, gaps, counters
        self._backoff = Backoff(self.backoff_min, self.backoff_max)
        self._t_data = 0.0  # wall time of the last data of the previous run (reconnect estimate)

    @classmethod
    def from_config(cls, cfg, drive: str, profile_rate_hz: float, **kwargs) -> NidaqSource:
        """From ``[drives.source] kind = "nidaq"`` (:class:`agent.runtime.config.NidaqCfg`);
        the rate defaults to the profile's ``sampling.rate_hz``."""
        rate = cfg.rate_hz if cfg.rate_hz is not None else profile_rate_hz
        return cls(cfg.voltage_channels, cfg.current_channels, drive, rate, profile_rate_hz=profile_rate_hz,
                   voltage_range_v=cfg.voltage_range_v, current_range_v=cfg.current_range_v,
                   current_scale_a_per_v=cfg.current_scale_a_per_v, block_samples=cfg.block_samples, **kwargs)

    # ------------------------------------------------------------------ contract

    def open(self) -> None:
        with self._io:
            self._mod = load_nidaqmx(self._injected)
            self._wanted = True
            if self._task is not None:
                return
            try:
                self._connect(jump=0)
            except ValueError:
                self._wanted = False
                raise
            except Exception as err:  # noqa: BLE001 - DaqError, DaqNotFoundError, OSError, ...
                self._note_error(err)
                self._backoff.failed()
                raise ConnectionError(f"{self.name}: cannot start the DAQmx task: {self.stats.last_error}"
                                      f"{_driver_hint(err)}") from err

    def read(self, timeout: float) -> Block | None:
        deadline = time.monotonic() + max(0.0, float(timeout))
        try:
            while True:
                self._service()
                with self._cond:
                    if self._queue:
                        first, raw = self._queue.popleft()
                        break
                    left = deadline - time.monotonic()
                    if left <= 0 or not self._wanted:
                        return None
                    if self._pending is None:
                        down = self._task is None
                        wait = max(0.0, self._backoff.next_try - time.monotonic()) if down else self.stall_s / 4
                        self._cond.wait(min(left, max(wait, 0.001)))
            return self._deliver(first, raw)
        except Exception as err:  # noqa: BLE001 - a source never raises out of read
            log.exception("%s: unexpected error in read", self.name)
            self.stats.last_error = f"internal: {err!r}"
            return None

    def close(self) -> None:
        with self._io:
            self._wanted = False
            self._teardown()
            with self._cond:
                self._queue.clear()
                self._pending = None
                self._cond.notify_all()

    @property
    def connected(self) -> bool:
        return self._task is not None

    @property
    def queued(self) -> int:
        """Blocks waiting in the queue (at most ``max_queue_blocks``)."""
        return len(self._queue)

    # ------------------------------------------------------------------ DAQmx callbacks (DAQmx thread)

    def _on_samples(self, task_handle, every_n_samples_event_type, number_of_samples, callback_data) -> int:
        run = self._run
        if run is None or not run.active:
            return 0
        try:
            got = run.reader.read_many_sample(run.buf, number_of_samples_per_channel=self.block_samples,
                                              timeout=0.0)
            got = self.block_samples if got is None else int(got)
            x = run.buf[:, :got].copy()
        except Exception as err:  # noqa: BLE001 - never raise into DAQmx; the consumer handles it
            self._fault(run, getattr(err, "error_code", None), _err_text(err))
            return 0
        with self._cond:
            if run is not self._run or not run.active or got <= 0:
                return 0
            if len(self._queue) >= self.max_queue_blocks:
                self._queue.popleft()  # drop the oldest: the consumer sees a jump of first_sample
                self.counters["queue_overruns"] += 1
            self._queue.append((self._next_sample, x))
            self._next_sample += got
            run.read += got
            run.t_last = time.monotonic()
            self.stats.frames += 1
            self._cond.notify_all()
        return 0

    def _on_done(self, task_handle, status, callback_data) -> int:
        run = self._run
        if run is not None and status is not None and int(status) < 0:
            self._fault(run, int(status), f"DAQmx error {int(status)}: the task stopped (done event)")
        return 0

    def _fault(self, run: _Run, code: int | None, text: str) -> None:
        with self._cond:
            if run is not self._run or not run.active:
                return  # a late report of a run already handled
            run.active = False
            self._pending = (code, text)
            self._cond.notify_all()

    # ------------------------------------------------------------------ consumer side

    def _service(self) -> None:
        """Handle a reported fault, a stall, or a due reconnect (consumer thread)."""
        with self._io:
            if not self._wanted:
                return
            with self._cond:
                fault, self._pending = self._pending, None
            if fault is not None:
                self._handle_fault(*fault)
            elif self._task is None:
                if self._backoff.due():
                    self._reconnect()
            else:
                run = self._run
                if run is not None and run.active and time.monotonic() - run.t_last > self.stall_s:
                    self._stalled(run)

    def _handle_fault(self, code: int | None, text: str) -> None:
        if self._task is None:
            return  # already down
        self.stats.last_error = text
        if code == SAMPLES_NO_LONGER_AVAILABLE:
            self.counters["buffer_overruns"] += 1
            log.warning("%s: DAQmx buffer overrun (-200279); restarting the task, data gap", self.name)
            try:
                self._restart()
                return
            except Exception as err:  # noqa: BLE001 - fall back to a full reconnect
                text = self._note_error(err)
        self.counters["daq_errors"] += 1
        log.warning("%s: %s; recreating the task in %.2f s", self.name, text, self._backoff.delay)
        self._down()

    def _stalled(self, run: _Run) -> None:
        with self._cond:
            run.active = False
        self.counters["stalls"] += 1
        try:
            self._task.is_task_done()  # reports the error that stopped the task, if any
            text = f"no samples for {self.stall_s:g} s"
        except Exception as err:  # noqa: BLE001
            text = _err_text(err)
            self.counters["daq_errors"] += 1
        self.stats.last_error = text
        log.warning("%s: %s; recreating the task", self.name, text)
        self._down()

    def _down(self) -> None:
        self._teardown()
        self._backoff.failed()

    def _reconnect(self) -> None:
        jump = max(1, round((time.monotonic() - self._t_data) * self.rate_hz))
        try:
            self._connect(jump)
        except Exception as err:  # noqa: BLE001
            self.counters["daq_errors"] += 1
            self._note_error(err)
            wait = self._backoff.failed()
            log.warning("%s: cannot recreate the task: %s (next try in %.2f s)", self.name,
                        self.stats.last_error, wait)
            return
        self.stats.reconnects += 1
        log.info("%s: DAQmx task running again", self.name)

    def _connect(self, jump: int) -> None:
        """Create, configure and start the task (the event is registered before ``start``)."""
        m = self._mod
        AcquisitionType = m.constants.AcquisitionType
        TerminalConfiguration = m.constants.TerminalConfiguration
        task = m.Task(self.task_name)
        try:
            chans = task.ai_channels
            chans.add_ai_voltage_chan(self.voltage_channels, min_val=-self.voltage_range_v,
                                      max_val=self.voltage_range_v, terminal_config=TerminalConfiguration.DEFAULT)
            n_v = int(task.number_of_channels)
            chans.add_ai_voltage_chan(self.current_channels, min_val=-self.current_range_v,
                                      max_val=self.current_range_v, terminal_config=TerminalConfiguration.DEFAULT)
            n_all = int(task.number_of_channels)
            if (n_v, n_all - n_v) != (3, 3):
                raise ValueError(f"{self.name}: voltage_channels {self.voltage_channels!r} and current_channels "
                                 f"{self.current_channels!r} must name 3 channels each (phases a, b, c), "
                                 f"got {n_v} and {n_all - n_v}")
            task.timing.cfg_samp_clk_timing(self.requested_rate_hz, sample_mode=AcquisitionType.CONTINUOUS,
                                            samps_per_chan=self.buffer_samples)
            self._check_rate(float(task.timing.samp_clk_rate))
            reader = m.stream_readers.AnalogMultiChannelReader(task.in_stream)
            task.register_every_n_samples_acquired_into_buffer_event(self.block_samples, self._on_samples)
            task.register_done_event(self._on_done)
            self._task = task
            self._install(_Run(reader, self.block_samples), jump)
            task.start()
        except BaseException:
            self._task = None
            with self._cond:
                self._run = None
            _quiet(task.close)
            raise
        self._backoff.reset()

    def _restart(self) -> None:
        """Stop and start the same task after a buffer overrun; advance the stream index."""
        task = self._task
        with self._cond:
            run, self._run = self._run, None
        try:
            lost = int(task.in_stream.total_samp_per_chan_acquired) - run.read
        except Exception:  # noqa: BLE001 - not every driver state answers
            lost = -1
        t0 = time.monotonic()
        if lost < 0:
            lost = round((t0 - run.t_last) * self.rate_hz)
        try:
            task.stop()
        except Exception as err:  # noqa: BLE001 - stopping may report the overrun once more
            if getattr(err, "error_code", None) != SAMPLES_NO_LONGER_AVAILABLE:
                raise
        dead = round((time.monotonic() - t0) * self.rate_hz)  # stopped: nothing is acquired
        self._install(_Run(run.reader, self.block_samples), max(1, lost + dead))
        task.start()
        self.counters["restarts"] += 1

    def _install(self, run: _Run, jump: int) -> None:
        with self._cond:
            self._next_sample += jump
            self._run = run

    def _teardown(self) -> None:
        with self._cond:
            run, self._run = self._run, None
            if run is not None:
                run.active = False
            task, self._task = self._task, None
        if run is not None:
            self._t_data = run.t_last
        if task is not None:
            _quiet(task.stop)
            _quiet(task.close)

    def _check_rate(self, actual: float) -> None:
        msgs = []
        if not math.isclose(actual, self.requested_rate_hz, rel_tol=1e-9):
            msgs.append(f"the DAQmx sample clock is {actual:g} Hz, {self.requested_rate_hz:g} Hz was requested "
                        "(coerced: delta-sigma modules run at 12.8 MHz / 256 / n)")
        if not math.isclose(actual, self.profile_rate_hz, rel_tol=1e-9):
            msgs.append(f"the drive profile's sampling.rate_hz is {self.profile_rate_hz:g} Hz; blocks carry "
                        f"rate_hz = {actual:g}, fix the profile or the source's rate_hz")
        self.rate_hz = actual
        self.rate_warning = "; ".join(msgs)
        if msgs:
            log.warning("%s: %s", self.name, self.rate_warning)

    def _deliver(self, first: int, raw: np.ndarray) -> Block:
        expected = self._asm.next_sample
        if first != expected:
            log.info("%s: gap of %d samples before sample %d", self.name, first - expected, first)
        return self._asm.block(raw[0:3], raw[3:6] * self.current_scale, first, rate_hz=self.rate_hz)

    def _note_error(self, err: BaseException) -> str:
        self.stats.last_error = _err_text(err)
        return self.stats.last_error


def _err_text(err: BaseException) -> str:
    code = getattr(err, "error_code", None)
    first = (str(err).strip().splitlines() or [""])[0]
    prefix = f"DAQmx error {code}" if code is not None else type(err).__name__
    return f"{prefix}: {first}" if first else prefix


def _driver_hint(err: BaseException) -> str:
    if type(err).__name__ == "DaqNotFoundError":
        return (" (the NI-DAQmx driver is not installed: use NI's installer or `python -m nidaqmx installdriver`, "
                "see docs/hardware.md)")
    return ""


def _quiet(fn) -> None:
    try:
        fn()
    except Exception as err:  # noqa: BLE001 - cleanup of a task that may be in error
        log.debug("ignored during cleanup: %r", err)
