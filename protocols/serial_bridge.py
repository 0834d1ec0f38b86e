"""Serial ADC bridge transport: phase samples framed by :mod:`firmware_if.serial_frame` over a
UART / USB-serial link (pyserial, any ``serial_for_url`` URL: ``/dev/ttyUSB0``,
``/dev/serial/by-id/...``, ``rfc2217://host:port``, ``socket://host:port``).

:class:`SerialBridgeSource` (agent side, the :class:`protocols.base.Source` contract):

* ``open()`` opens the port once and raises ``ConnectionError`` if it cannot (the runtime retries);
  after that ``read()`` never raises: when the port fails or disappears (USB unplugged) it is
  closed and reopened with exponential backoff (``backoff_s = (min, max)``), counted in
  ``stats.reconnects``; ``read`` returns ``None`` while the link is down.
* Frames are decoded by :class:`~firmware_if.serial_frame.FrameDecoder` (bounded buffer, resync on
  garbage: ``stats.bad_frames``, ``stats.resyncs``) and assembled into :class:`Block` s of up to
  ``block_samples`` samples. A block is returned as soon as it is full, or at the ``read``
  deadline with what has arrived. Blocks hold consecutive samples only: a jump in the frame
  ``seq`` ends the block, counts ``stats.gaps`` and advances ``first_sample`` by the lost frames
  times the frame length (seq is 16-bit: a gap of more than 65535 frames is not measurable).
  A change of channel count (encoder channels appearing) also ends the block.
* 8-channel frames fill ``Block.theta_e`` / ``omega_e``.

:class:`SerialBridgeEmulator` (device side, for tests and the demo) streams a record's samples as
frames from a thread, real time (``speed=1``), accelerated (``speed=k``) or as fast as the
reader takes them (``speed=None``), writing in small chunks (a pty holds about 4 KiB).
It can inject garbage and drop frames to exercise the source.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator

import numpy as np
import serial

from firmware_if.serial_frame import (DEFAULT_SCALES, FMT_INT16, MAX_SAMPLES, N_ENCODER, N_PHASE, DecoderStats,
                                      FrameDecoder, SerialFrame, encode_raw, quantize)
from protocols.base import Block, SourceStats
from protocols.ptyutil import write_all

log = logging.getLogger(__name__)

#: Link budget: 25 kS/s x 6 channels int16 in 64-sample frames is 806 bytes per 64 samples,
#: 315 kB/s, i.e. 3.15 Mbit/s on an 8N1 UART. The default suits FT232H/FT2232H-class bridges;
#: USB CDC-ACM bridges ignore the baud rate; 921600 baud carries only about 7 kS/s.
DEFAULT_BAUD = 4_000_000
#: A block of ``block_samples`` at 25 kS/s = 0.1 s.
DEFAULT_BLOCK_SAMPLES = 2500
SEQ_MODULO = 1 << 16


class SerialBridgeSource:
    """Phase samples of one drive from a serial ADC bridge (see the module docstring)."""

    def __init__(self, port_url: str, drive: str, rate_hz: float, baud: int = DEFAULT_BAUD, *,
                 block_samples: int = DEFAULT_BLOCK_SAMPLES, max_samples: int = MAX_SAMPLES,
                 read_size: int = 4096, poll_s: float = 0.02, backoff_s: tuple[float, float] = (0.05, 5.0),
                 name: str | None = None, **serial_kwargs):
        if rate_hz <= 0 or block_samples < 1 or read_size < 1:
            raise ValueError("rate_hz, block_samples and read_size must be positive")
        self.port_url = port_url
        self.drive = drive
        self.rate_hz = float(rate_hz)
        self.baud = int(baud)
        self.block_samples = int(block_samples)
        self.read_size = int(read_size)
        self.poll_s = float(poll_s)
        self.backoff_min, self.backoff_max = (float(b) for b in backoff_s)
        self.serial_kwargs = serial_kwargs
        self.name = name or f"serial:{drive}"
        self.stats = SourceStats()
        self.decoder = FrameDecoder(max_samples)
        self._seen = DecoderStats()
        self._ser: serial.SerialBase | None = None
        self._wanted = False
        self._backoff = self.backoff_min
        self._next_try = 0.0
        self._lost = False  # the link failed since the last good connect
        # block assembly
        self._pending: list[SerialFrame] = []
        self._pending_n = 0
        self._ready: deque[Block] = deque()
        self._next_sample = 0  # index of the sample after the last one accepted
        self._expected_seq: int | None = None
        self._frame_len = 0
        self._block_seq = 0

    # ------------------------------------------------------------------ contract

    def open(self) -> None:
        self._wanted = True
        if self._ser is None and not self._connect():
            raise ConnectionError(f"{self.name}: cannot open {self.port_url}: {self.stats.last_error}")

    def read(self, timeout: float) -> Block | None:
        deadline = time.monotonic() + max(0.0, float(timeout))
        try:
            while True:
                if self._ready:
                    return self._deliver(self._ready.popleft())
                now = time.monotonic()
                if now >= deadline or not self._wanted:
                    self._flush()
                    return self._deliver(self._ready.popleft()) if self._ready else None
                if self._ser is None:
                    if now >= self._next_try:
                        self._connect()
                    if self._ser is None:
                        time.sleep(max(0.0, min(deadline, self._next_try) - now))
                    continue
                try:
                    ser = self._ser
                    n = ser.in_waiting
                    data = ser.read(min(max(1, n), self.read_size))
                except (serial.SerialException, OSError, TypeError, AttributeError) as err:
                    # TypeError/AttributeError: pyserial after a concurrent close()
                    self._disconnect(f"read failed: {err}")
                    continue
                if data:
                    self._ingest(data)
        except Exception as err:  # noqa: BLE001 - a source never raises out of read
            log.exception("%s: unexpected error in read", self.name)
            self.stats.last_error = f"internal: {err!r}"
            return None

    def close(self) -> None:
        self._wanted = False
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001
                pass

    def __enter__(self) -> SerialBridgeSource:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        return self._ser is not None

    # ------------------------------------------------------------------ link

    def _connect(self) -> bool:
        try:
            ser = serial.serial_for_url(self.port_url, baudrate=self.baud, timeout=self.poll_s,
                                        **self.serial_kwargs)
        except (serial.SerialException, OSError, ValueError) as err:
            self.stats.last_error = f"open {self.port_url}: {err}"
            self._next_try = time.monotonic() + self._backoff
            self._backoff = min(self.backoff_max, 2.0 * self._backoff)
            return False
        if not self._wanted:  # closed meanwhile
            ser.close()
            return False
        self._ser = ser
        self.decoder.reset()
        self._backoff = self.backoff_min
        if self._lost:
            self.stats.reconnects += 1
            self._lost = False
            log.info("%s: reconnected to %s", self.name, self.port_url)
        return True

    def _disconnect(self, why: str) -> None:
        log.warning("%s: %s; reconnecting", self.name, why)
        self.stats.last_error = why
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001
                pass
        self._lost = True
        self._flush()
        self._next_try = time.monotonic() + self._backoff
        self._backoff = min(self.backoff_max, 2.0 * self._backoff)

    # ------------------------------------------------------------------ frames -> blocks

    def _ingest(self, data: bytes) -> None:
        frames = self.decoder.feed(data)
        d, seen, st = self.decoder.stats, self._seen, self.stats
        st.frames += d.frames - seen.frames
        st.bad_frames += d.errors - seen.errors
        st.resyncs += d.resyncs - seen.resyncs
        if d.errors != seen.errors:
            st.last_error = (f"bad frames: header {d.bad_header}, crc {d.bad_crc}, length {d.bad_length}, "
                             f"format {d.unknown_format}")
        self._seen = DecoderStats(**d.__dict__)
        for f in frames:
            n = f.n_samples
            if self._expected_seq is not None and f.seq != self._expected_seq:
                lost = (f.seq - self._expected_seq) % SEQ_MODULO
                self._flush()
                st.gaps += 1
                self._next_sample += lost * (self._frame_len or n)
            elif self._pending and f.n_channels != self._pending[0].n_channels:
                self._flush()
            self._pending.append(f)
            self._pending_n += n
            self._next_sample += n
            self._expected_seq = (f.seq + 1) % SEQ_MODULO
            self._frame_len = n
            if self._pending_n >= self.block_samples:
                self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        x = np.concatenate([f.values() for f in self._pending], axis=1)
        enc = x.shape[0] == N_ENCODER
        blk = Block(drive=self.drive, rate_hz=self.rate_hz, v_abc=x[0:3], i_abc=x[3:6],
                    first_sample=self._next_sample - self._pending_n, seq=self._block_seq,
                    theta_e=x[6] if enc else None, omega_e=x[7] if enc else None)
        self._block_seq += 1
        self._pending, self._pending_n = [], 0
        self._ready.append(blk)

    def _deliver(self, blk: Block) -> Block:
        self.stats.blocks += 1
        self.stats.samples += blk.n
        return blk


# ---------------------------------------------------------------------------------- emulator


def _channels(rec) -> np.ndarray:
    """``(6|8, N)`` from a record-like (``v_abc``, ``i_abc``, optional ``theta_e``, ``omega_e``)."""
    rows = [np.asarray(rec.v_abc, float), np.asarray(rec.i_abc, float)]
    th, om = getattr(rec, "theta_e", None), getattr(rec, "omega_e", None)
    if th is not None and om is not None:
        rows.append(np.vstack([np.asarray(th, float), np.asarray(om, float)]))
    return np.vstack(rows)


class SerialBridgeEmulator:
    """Device side: streams record samples as serial frames from a thread.

    ``port``: an ``int`` fd (e.g. :attr:`protocols.ptyutil.Pty.master`; set non-blocking), a
    pyserial URL (opened here, closed by :meth:`stop`), or an object with ``fileno()`` or ``write()``.
    ``source``: a record-like (``v_abc``, ``i_abc`` ``(3, N)``, optional ``theta_e``/``omega_e``,
    ``rate_hz``), e.g. :class:`agent.records.Record`, or an iterable of them (a generator of
    chunks). ``encoder``: send 8 channels (``None``: when the record has theta_e and omega_e).
    ``speed``: 1.0 real time, ``k`` k times faster, ``None`` no pacing (back-pressure only).
    """

    def __init__(self, port, source, *, rate_hz: float | None = None, samples_per_frame: int = 64,
                 fmt: int = FMT_INT16, scales=None, speed: float | None = 1.0, start_seq: int = 0,
                 loop: bool = False, chunk_size: int = 256, baud: int = DEFAULT_BAUD, encoder: bool | None = None):
        if not 1 <= samples_per_frame <= MAX_SAMPLES:
            raise ValueError(f"samples_per_frame must be 1..{MAX_SAMPLES}")
        self.samples_per_frame = int(samples_per_frame)
        self.fmt = fmt
        self.scales = scales
        self.speed = speed
        self.seq = int(start_seq) % SEQ_MODULO  #: seq of the next frame
        self.loop = loop
        self.chunk_size = int(chunk_size)
        self.encoder = encoder
        self._source = source
        self.rate_hz = float(rate_hz if rate_hz is not None else getattr(source, "rate_hz", float("nan")))
        if speed is not None and not (self.rate_hz > 0):
            raise ValueError("rate_hz is needed for paced streaming (speed is not None)")
        self._owned = None
        self._write = None
        self._fd: int | None = None
        if isinstance(port, int):
            self._fd = port
        elif isinstance(port, str):
            self._owned = serial.serial_for_url(port, baudrate=baud, timeout=0.1)
            self._fd = self._owned.fileno()
        elif hasattr(port, "fileno"):
            self._fd = port.fileno()
        else:
            self._write = port.write
        if self._fd is not None:
            os.set_blocking(self._fd, False)
        self._stop = threading.Event()
        self.done = threading.Event()
        self._lock = threading.Lock()
        self._inject: list[bytes] = []
        self._drop = 0
        self.frames_sent = 0
        self.frames_dropped = 0
        self.samples_sent = 0
        self.bytes_sent = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="serial-bridge-emulator", daemon=True)

    # ------------------------------------------------------------------ control

    def start(self) -> SerialBridgeEmulator:
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and close a port opened here (safe twice)."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        if self._owned is not None:
            self._owned.close()
            self._owned = None

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until everything was sent (or the thread stopped); True if done."""
        return self.done.wait(timeout)

    def inject(self, data: bytes) -> None:
        """Write ``data`` (garbage) before the next frame."""
        with self._lock:
            self._inject.append(bytes(data))

    def drop_frames(self, n: int) -> None:
        """Do not send the next ``n`` frames (their seq numbers are used up: a gap)."""
        with self._lock:
            self._drop += int(n)

    def __enter__(self) -> SerialBridgeEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ thread

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

    def _send(self, data: bytes) -> None:
        if self._fd is not None:
            self.bytes_sent += write_all(self._fd, data, self._stop, self.chunk_size)
        else:
            for k in range(0, len(data), self.chunk_size):
                self._write(data[k:k + self.chunk_size])
            self.bytes_sent += len(data)

    def _run(self) -> None:
        spf = self.samples_per_frame
        t0 = time.monotonic()
        try:
            for rec in self._records():
                x = _channels(rec)
                if self.encoder is False:
                    x = x[:N_PHASE]
                elif self.encoder and x.shape[0] != N_ENCODER:
                    raise ValueError("encoder=True needs theta_e and omega_e in the record")
                scales = DEFAULT_SCALES[self.fmt][:x.shape[0]] if self.scales is None else self.scales
                q = quantize(x, scales, self.fmt)  # whole chunk at once
                for j in range(0, x.shape[1], spf):
                    if self._stop.is_set():
                        return
                    seg = q[:, j:j + spf]
                    frame = encode_raw(self.seq, seg, scales, self.fmt)
                    self.seq = (self.seq + 1) % SEQ_MODULO
                    if self.speed is not None:
                        target = t0 + (self.samples_sent + seg.shape[1]) / (self.rate_hz * self.speed)
                        delay = target - time.monotonic()
                        if delay > 0 and self._stop.wait(delay):
                            return
                    with self._lock:
                        garbage, self._inject = self._inject, []
                        drop = self._drop > 0
                        self._drop -= drop
                    for g in garbage:
                        self._send(g)
                    if drop:
                        self.frames_dropped += 1
                    else:
                        self._send(frame)
                        self.frames_sent += 1
                    self.samples_sent += seg.shape[1]
        except Exception as err:  # noqa: BLE001 - e.g. EIO when the port is unplugged
            self.error = err
            log.info("serial emulator stopped: %r", err)
        finally:
            self.done.set()


def record_chunks(rec, n: int) -> Iterable:
    """Split a record-like into record-likes of ``n`` samples (a generator source for the emulator)."""
    from types import SimpleNamespace
    th, om = getattr(rec, "theta_e", None), getattr(rec, "omega_e", None)
    for k in range(0, rec.i_abc.shape[1], n):
        sl = slice(k, k + n)
        yield SimpleNamespace(v_abc=rec.v_abc[:, sl], i_abc=rec.i_abc[:, sl],
                              theta_e=None if th is None else th[sl], omega_e=None if om is None else om[sl])
