"""What the sample sources share, written once.

* :class:`Backoff`: exponential backoff between attempts (``initial``, doubled after each
  failure up to ``maximum``, back to ``initial`` after a success).
* :class:`BlockAssembler`: decoded samples -> :class:`~protocols.base.Block`: the block counter
  (``Block.seq``), the stream index of the next sample (``Block.first_sample``), gap accounting
  (``stats.gaps``) and the delivery counters (``stats.blocks``, ``stats.samples``).
* :class:`LinkSource`: the :class:`~protocols.base.Source` contract for a transport that is
  read in a loop (the CAN bus, the serial port): ``open()`` connects once or raises
  ``ConnectionError``; ``read()`` never raises, reopens a failed link with :class:`Backoff`
  (``stats.reconnects``) and returns a block as soon as one is full, or what has arrived at
  its deadline.
* :class:`EmulatorThread`: the device side of such a transport: sends a record-like's
  samples frame by frame from a daemon thread, paced or unpaced, with injected messages and
  dropped frames.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Iterator
from typing import Any, Self

import numpy as np

from protocols.base import Block, OpenClose, SourceStats


def put_drop_oldest(q: queue.Queue, item) -> int:
    """Put ``item`` without blocking; when ``q`` is full drop the oldest entries to make room.
    Returns how many were dropped (producers count them; a slow consumer never blocks a producer)."""
    dropped = 0
    while True:
        try:
            q.put_nowait(item)
            return dropped
        except queue.Full:
            try:
                q.get_nowait()
                dropped += 1
            except queue.Empty:
                pass


class Backoff:
    """Exponential backoff: after a failure wait ``delay`` s (``next_try``), then double it."""

    def __init__(self, initial: float, maximum: float):
        self.initial = float(initial)
        self.maximum = float(maximum)
        self.delay = self.initial  #: the wait after the next failure, s
        self.next_try = 0.0  #: ``time.monotonic()`` of the next attempt

    def failed(self) -> float:
        """Schedule the next attempt ``delay`` s from now and double the delay (up to
        ``maximum``); returns the wait scheduled."""
        wait = self.delay
        self.next_try = time.monotonic() + wait
        self.delay = min(self.maximum, 2.0 * wait)
        return wait

    def reset(self) -> None:
        """A success: the next failure waits ``initial`` again."""
        self.delay = self.initial

    def due(self) -> bool:
        return time.monotonic() >= self.next_try


class BlockAssembler:
    """Samples of one drive -> :class:`Block` s, with the counters every source keeps.

    Frame streams (CAN, serial): the source buffers decoded frames and reports them with
    :meth:`add` (True: the block is full), checks each frame's counter with :meth:`check_counter`
    and, on a jump, flushes its buffer and calls :meth:`skip` with the lost samples; its flush
    hands the buffered samples to :meth:`emit`; :meth:`pop` delivers the oldest ready block.
    Sources that receive whole blocks (NI-DAQmx reads, Modbus snapshots) call :meth:`block`.
    """

    def __init__(self, drive: str, rate_hz: float, stats: SourceStats, block_samples: int = 1):
        self.drive = drive
        self.rate_hz = float(rate_hz)
        self.stats = stats
        self.block_samples = int(block_samples)
        self.next_sample = 0  #: stream index of the sample after the last one accepted
        self.pending = 0  #: samples accepted and not yet in a block
        self.seq = 0  #: ``seq`` of the next block
        self.ready: deque[Block] = deque()
        self._expected: int | None = None  # frame counter expected next

    # ---- frame streams

    def check_counter(self, counter: int, step: int, modulo: int) -> int:
        """How far a frame's ``counter`` jumped past the one expected (0: in order, or the first
        frame), modulo ``modulo``; the next frame is expected at ``counter + step``."""
        jump = 0 if self._expected is None else (counter - self._expected) % modulo
        self._expected = (counter + step) % modulo
        return jump

    def add(self, n: int) -> bool:
        """``n`` more samples buffered by the source; True when they fill a block."""
        self.pending += n
        self.next_sample += n
        return self.pending >= self.block_samples

    def skip(self, n: int) -> None:
        """A gap of ``n`` lost samples (call it after flushing the samples before the gap)."""
        self.stats.gaps += 1
        self.next_sample += n

    def emit(self, v_abc: np.ndarray, i_abc: np.ndarray, theta_e: np.ndarray | None = None,
             omega_e: np.ndarray | None = None) -> None:
        """The buffered samples, decoded by the source, as the next ready block."""
        self.ready.append(Block(drive=self.drive, rate_hz=self.rate_hz, v_abc=v_abc, i_abc=i_abc,
                                first_sample=self.next_sample - self.pending, seq=self.seq,
                                theta_e=theta_e, omega_e=omega_e))
        self.seq += 1
        self.pending = 0

    def pop(self) -> Block | None:
        """The oldest ready block, counted as delivered; ``None`` when there is none."""
        return self._delivered(self.ready.popleft()) if self.ready else None

    # ---- whole blocks

    def block(self, v_abc: np.ndarray, i_abc: np.ndarray, first_sample: int, *, rate_hz: float | None = None,
              theta_e: np.ndarray | None = None, omega_e: np.ndarray | None = None) -> Block:
        """A block received whole, delivered at once; a ``first_sample`` other than the end of
        the previous block counts a gap."""
        n = int(i_abc.shape[1])
        if first_sample != self.next_sample:
            self.stats.gaps += 1
        self.next_sample = first_sample + n
        blk = Block(drive=self.drive, rate_hz=self.rate_hz if rate_hz is None else float(rate_hz),
                    v_abc=v_abc, i_abc=i_abc, first_sample=first_sample, seq=self.seq,
                    theta_e=theta_e, omega_e=omega_e)
        self.seq += 1
        return self._delivered(blk)

    def _delivered(self, blk: Block) -> Block:
        self.stats.blocks += 1
        self.stats.samples += blk.n
        return blk


class LinkSource(OpenClose):
    """Base of the sources read from a link in a loop (see the module docstring).

    Subclasses set :attr:`_open_errors` / :attr:`_read_errors` (the exceptions meaning "the link
    failed") and implement :attr:`_where` (the link's name in messages), :meth:`_open_link`,
    :meth:`_close_link`, :meth:`_receive` (one poll: data or ``None``), :meth:`_consume` (decode
    into the assembler ``self._asm``) and :meth:`_flush` (hand buffered samples to
    ``self._asm.emit``); :meth:`_link_up` runs after each (re)connect.
    """

    _open_errors: tuple[type[BaseException], ...] = (OSError,)
    _read_errors: tuple[type[BaseException], ...] = (OSError,)
    _read_call = "read"  #: in ``stats.last_error``: "<read_call> failed: ..."

    def __init__(self, drive: str, rate_hz: float, block_samples: int, *, poll_s: float,
                 backoff_s: tuple[float, float], name: str):
        self.drive = drive
        self.rate_hz = float(rate_hz)
        self.poll_s = float(poll_s)
        self.backoff_min, self.backoff_max = (float(b) for b in backoff_s)
        self.name = name
        self.stats = SourceStats()
        self._backoff = Backoff(self.backoff_min, self.backoff_max)
        self._asm = BlockAssembler(drive, self.rate_hz, self.stats, block_samples)
        self._link: Any = None
        self._wanted = False
        self._lost = False  # the link failed since the last good connect
        self._log = logging.getLogger(type(self).__module__)

    # ---- hooks

    @property
    def _where(self) -> str:
        raise NotImplementedError

    def _open_link(self) -> Any:
        raise NotImplementedError

    def _close_link(self, link: Any) -> None:
        raise NotImplementedError

    def _receive(self, link: Any, timeout: float) -> Any:
        raise NotImplementedError

    def _consume(self, data: Any) -> None:
        raise NotImplementedError

    def _flush(self) -> None:
        raise NotImplementedError

    def _link_up(self) -> None:
        pass

    # ---- contract

    def open(self) -> None:
        self._wanted = True
        if self._link is None and not self._connect():
            raise ConnectionError(f"{self.name}: cannot open {self._where}: {self.stats.last_error}")

    def read(self, timeout: float) -> Block | None:
        deadline = time.monotonic() + max(0.0, float(timeout))
        try:
            while True:
                blk = self._asm.pop()
                if blk is not None:
                    return blk
                now = time.monotonic()
                if now >= deadline or not self._wanted:
                    self._flush()
                    return self._asm.pop()
                link = self._link
                if link is None:
                    if now >= self._backoff.next_try:
                        self._connect()
                    if self._link is None:
                        time.sleep(max(0.0, min(deadline, self._backoff.next_try) - now))
                    continue
                try:
                    data = self._receive(link, min(self.poll_s, deadline - now))
                except self._read_errors as err:
                    self._disconnect(f"{self._read_call} failed: {err}")
                    continue
                if data is not None:
                    self._consume(data)
        except Exception as err:  # noqa: BLE001 - a source never raises out of read
            self._log.exception("%s: unexpected error in read", self.name)
            self.stats.last_error = f"internal: {err!r}"
            return None

    def close(self) -> None:
        self._wanted = False
        link, self._link = self._link, None
        self._release(link)

    @property
    def connected(self) -> bool:
        return self._link is not None

    # ---- link

    def _connect(self) -> bool:
        try:
            link = self._open_link()
        except self._open_errors as err:
            self.stats.last_error = f"open {self._where}: {err}"
            self._backoff.failed()
            return False
        if not self._wanted:  # closed meanwhile
            self._release(link)
            return False
        self._link = link
        self._backoff.reset()
        self._link_up()
        if self._lost:
            self.stats.reconnects += 1
            self._lost = False
            self._log.info("%s: reconnected to %s", self.name, self._where)
        return True

    def _disconnect(self, why: str) -> None:
        self._log.warning("%s: %s; reconnecting", self.name, why)
        self.stats.last_error = why
        link, self._link = self._link, None
        self._release(link)
        self._lost = True
        self._flush()
        self._backoff.failed()

    def _release(self, link: Any) -> None:
        if link is not None:
            try:
                self._close_link(link)
            except Exception:  # noqa: BLE001
                pass


class EmulatorThread:
    """Base of the device-side emulators: sends a record-like's samples from a daemon thread.

    ``source``: a record-like (``v_abc``, ``i_abc`` ``(3, N)``, optional ``theta_e``/``omega_e``,
    ``rate_hz``) or an iterable of them (a generator of chunks; single pass), repeated while
    ``loop``. ``speed``: 1.0 real time, ``k`` k times faster, ``None`` unpaced.

    Subclasses implement :meth:`_send_record` (one record-like, frame by frame through
    :meth:`_emit`; False when stopped), :meth:`_send_frame`, :meth:`_send_injected` and
    :meth:`_release` (what :meth:`stop` closes).
    """

    _min_sleep_s = 0.0  #: paced waits shorter than this are skipped (frames go out in bursts)

    def __init__(self, source, *, rate_hz: float | None, speed: float | None, loop: bool, thread_name: str):
        self._source = source
        self.rate_hz = float(rate_hz if rate_hz is not None else getattr(source, "rate_hz", float("nan")))
        if speed is not None and not (self.rate_hz > 0):
            raise ValueError("rate_hz is needed for paced sending (speed is not None)")
        self.speed = speed
        self.loop = loop
        self._stop = threading.Event()
        self.done = threading.Event()
        self._lock = threading.Lock()
        self._inject: list = []
        self._finished = False  #: every frame sent: inject() sends at once
        self._drop = 0
        self._t0 = 0.0
        self.frames_sent = 0
        self.frames_dropped = 0
        self.samples_sent = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=thread_name, daemon=True)

    # ---- hooks

    def _send_record(self, rec) -> bool:
        raise NotImplementedError

    def _send_frame(self, frame) -> None:
        raise NotImplementedError

    def _send_injected(self, item) -> None:
        raise NotImplementedError

    def _release(self) -> None:
        pass

    # ---- control

    def start(self) -> Self:
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and close what the emulator opened (safe twice)."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        self._release()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until everything was sent (or the thread stopped); True if done."""
        return self.done.wait(timeout)

    def inject(self, item) -> None:
        """Send ``item`` before the next frame; once the last frame is out, at once (nothing
        injected is ever lost: an unpaced stream can end before the caller injects)."""
        with self._lock:
            if not self._finished:
                self._inject.append(item)
                return
        self._send_injected(item)

    def drop_frames(self, n: int) -> None:
        """Do not send the next ``n`` frames (their sample counters are used up: a gap)."""
        with self._lock:
            self._drop += int(n)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---- thread

    def _records(self) -> Iterator:
        src = self._source
        while True:
            if hasattr(src, "i_abc"):
                yield src
            else:
                yield from src  # an iterable of record-likes / a generator (single pass)
                return
            if not self.loop:
                return

    def _emit(self, n: int, frame) -> bool:
        """Send ``frame`` (``n`` samples) when it is due, after what was injected, or drop it
        as asked; False when stopped while waiting."""
        if self.speed is not None:
            target = self._t0 + (self.samples_sent + n) / (self.rate_hz * self.speed)
            delay = target - time.monotonic()
            if delay > self._min_sleep_s and self._stop.wait(delay):
                return False
        with self._lock:
            extra, self._inject = self._inject, []
            drop = self._drop > 0
            self._drop -= drop
        for item in extra:
            self._send_injected(item)
        if drop:
            self.frames_dropped += 1
        else:
            self._send_frame(frame)
            self.frames_sent += 1
        self.samples_sent += n
        return True

    def _run(self) -> None:
        self._t0 = time.monotonic()
        try:
            for rec in self._records():
                if not self._send_record(rec):
                    return
            with self._lock:  # what was injected after the last frame goes out now
                extra, self._inject, self._finished = self._inject, [], True
            for item in extra:
                self._send_injected(item)
        except Exception as err:  # noqa: BLE001 - e.g. EIO when the port is unplugged
            self.error = err
            logging.getLogger(type(self).__module__).info("%s stopped: %r", self._thread.name, err)
        finally:
            self.done.set()
