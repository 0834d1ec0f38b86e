"""CAN FD transport: phase samples in the frames of :mod:`firmware_if.can_frame`, over any
python-can interface (``socketcan`` on the target, ``virtual`` in tests, pcan/kvaser/... by name).

:class:`CanSource` (agent side, the :class:`protocols.base.Source` contract):

* ``open()`` creates ``can.Bus(interface=..., channel=..., fd=True, ignore_config=True, **bus_kwargs)``
  (``ignore_config``: no ``~/can.conf`` / ``CAN_*`` environment leaking into the service) with a
  filter passing the drive's id block (``filter_ids=False`` passes everything). It raises
  ``ConnectionError`` if the bus cannot be created (the runtime retries). The bus bit rates of
  SocketCAN are set outside the process (``ip link`` / systemd-networkd).
* ``read()`` never raises: a failing bus (``CanError``/``OSError`` from ``recv``) is shut down and
  recreated with exponential backoff (``stats.reconnects``).
* Counted, never fatal (``stats.bad_frames``, detail in :attr:`CanSource.counters`): ids in the
  drive's block that are not assigned or frames of other senders when unfiltered (``unknown_id``),
  error frames (``error_frame``; SocketCAN delivers them whatever the id filter, interfaces that
  filter in software such as ``virtual`` drop them unless ``filter_ids=False``), remote frames
  (``remote``), a payload length other than 64 (PHASE) / 24 (ENCODER) bytes (``malformed``).
* PHASE payloads are copied into a preallocated buffer and decoded per block with one numpy
  structured-dtype view (no per-sample Python). A jump of ``sample_index`` ends the block and
  counts a gap; ``first_sample`` advances by the lost samples (a backwards jump, i.e. the drive
  restarted, advances it by one frame). ENCODER frames (sent before the PHASE frame of the same
  ``sample_index``) fill ``theta_e``/``omega_e`` when every frame of the block had one.

:class:`CanEmulator` (device side) sends a record as ENCODER/PHASE frames from a thread, paced in
real time, accelerated, or unpaced; it can drop frames and inject arbitrary messages.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Iterator

import can
import numpy as np

from firmware_if.can_frame import (DEFAULT_BASE_ID, DEFAULT_I_LSB, DEFAULT_OMEGA_LSB, DEFAULT_V_LSB, ENCODER,
                                   ENCODER_SIZE, INDEX_MODULO, PHASE_SIZE, SAMPLES_PER_FRAME, CanLayout)
from protocols.base import Block, SourceStats

log = logging.getLogger(__name__)

DEFAULT_BLOCK_SAMPLES = 2500
COUNTERS = ("unknown_id", "error_frame", "remote", "malformed")


class CanSource:
    """Phase samples of one drive from a CAN FD bus (see the module docstring)."""

    def __init__(self, interface: str, channel, drive: str, base_id: int = DEFAULT_BASE_ID, fd: bool = True, *,
                 rate_hz: float = 25_000.0, block_samples: int = DEFAULT_BLOCK_SAMPLES,
                 v_lsb: float = DEFAULT_V_LSB, i_lsb: float = DEFAULT_I_LSB, omega_lsb: float = DEFAULT_OMEGA_LSB,
                 filter_ids: bool = True, poll_s: float = 0.05, backoff_s: tuple[float, float] = (0.05, 5.0),
                 name: str | None = None, **bus_kwargs):
        if not fd:
            raise ValueError("the PHASE frame needs CAN FD (64-byte payload); classic CAN is not supported")
        if rate_hz <= 0 or block_samples < 1:
            raise ValueError("rate_hz and block_samples must be positive")
        self.interface = interface
        self.channel = channel
        self.drive = drive
        self.layout = CanLayout(drive, base_id, v_lsb, i_lsb, omega_lsb)
        self.rate_hz = float(rate_hz)
        self.filter_ids = filter_ids
        self.poll_s = float(poll_s)
        self.backoff_min, self.backoff_max = (float(b) for b in backoff_s)
        self.bus_kwargs = bus_kwargs
        self.name = name or f"can:{drive}"
        self.stats = SourceStats()
        self.counters = dict.fromkeys(COUNTERS, 0)
        self._bus: can.BusABC | None = None
        self._wanted = False
        self._lost = False
        self._backoff = self.backoff_min
        self._next_try = 0.0
        # block assembly: preallocated payload buffers, one slot per PHASE frame
        self.block_frames = -(-int(block_samples) // SAMPLES_PER_FRAME)
        self._phase = bytearray(self.block_frames * PHASE_SIZE)
        self._enc = bytearray(self.block_frames * ENCODER_SIZE)
        self._enc_ok = np.zeros(self.block_frames, dtype=bool)
        self._k = 0  # PHASE frames in the buffer
        self._last_enc: tuple[int, bytes] | None = None
        self._expected: int | None = None
        self._next_sample = 0
        self._block_seq = 0
        self._ready: deque[Block] = deque()

    # ------------------------------------------------------------------ contract

    def open(self) -> None:
        self._wanted = True
        if self._bus is None and not self._connect():
            raise ConnectionError(f"{self.name}: cannot open {self.interface}:{self.channel}: {self.stats.last_error}")

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
                if self._bus is None:
                    if now >= self._next_try:
                        self._connect()
                    if self._bus is None:
                        time.sleep(max(0.0, min(deadline, self._next_try) - now))
                    continue
                try:
                    msg = self._bus.recv(min(self.poll_s, deadline - now))
                except (can.CanError, OSError, ValueError, AttributeError) as err:
                    self._disconnect(f"recv failed: {err}")
                    continue
                if msg is not None:
                    self._on_message(msg)
        except Exception as err:  # noqa: BLE001 - a source never raises out of read
            log.exception("%s: unexpected error in read", self.name)
            self.stats.last_error = f"internal: {err!r}"
            return None

    def close(self) -> None:
        self._wanted = False
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001
                pass

    def __enter__(self) -> CanSource:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        return self._bus is not None

    # ------------------------------------------------------------------ link

    def _connect(self) -> bool:
        kw = dict(self.bus_kwargs)
        if self.filter_ids:
            kw.setdefault("can_filters", [self.layout.can_filter()])
        try:
            bus = can.Bus(interface=self.interface, channel=self.channel, fd=True, ignore_config=True, **kw)
        except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as err:
            self.stats.last_error = f"open {self.interface}:{self.channel}: {err}"
            self._next_try = time.monotonic() + self._backoff
            self._backoff = min(self.backoff_max, 2.0 * self._backoff)
            return False
        if not self._wanted:
            bus.shutdown()
            return False
        self._bus = bus
        self._backoff = self.backoff_min
        self._last_enc = None
        if self._lost:
            self.stats.reconnects += 1
            self._lost = False
            log.info("%s: bus %s:%s reopened", self.name, self.interface, self.channel)
        return True

    def _disconnect(self, why: str) -> None:
        log.warning("%s: %s; reopening the bus", self.name, why)
        self.stats.last_error = why
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001
                pass
        self._lost = True
        self._flush()
        self._next_try = time.monotonic() + self._backoff
        self._backoff = min(self.backoff_max, 2.0 * self._backoff)

    # ------------------------------------------------------------------ messages -> blocks

    def _bad(self, what: str, msg: can.Message) -> None:
        self.counters[what] += 1
        self.stats.bad_frames += 1
        self.stats.last_error = f"{what}: id 0x{msg.arbitration_id:X} len {len(msg.data or b'')}"

    def _on_message(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            return self._bad("error_frame", msg)
        if msg.is_remote_frame:
            return self._bad("remote", msg)
        kind = self.layout.kind(msg.arbitration_id, msg.is_extended_id)
        if kind is None:
            return self._bad("unknown_id", msg)
        data = msg.data
        if kind == ENCODER:
            if len(data) != ENCODER_SIZE:
                return self._bad("malformed", msg)
            self._last_enc = (int.from_bytes(data[:4], "little"), bytes(data))
            return None
        if len(data) != PHASE_SIZE:
            return self._bad("malformed", msg)
        self.stats.frames += 1
        idx = int.from_bytes(data[:4], "little")
        if self._expected is not None and idx != self._expected:
            self._flush()
            self.stats.gaps += 1
            lost = (idx - self._expected) % INDEX_MODULO
            self._next_sample += lost if lost < INDEX_MODULO // 2 else SAMPLES_PER_FRAME
        k = self._k
        self._phase[k * PHASE_SIZE:(k + 1) * PHASE_SIZE] = data
        enc = self._last_enc
        if enc is not None and enc[0] == idx:
            self._enc[k * ENCODER_SIZE:(k + 1) * ENCODER_SIZE] = enc[1]
            self._enc_ok[k] = True
        else:
            self._enc_ok[k] = False
        self._k = k + 1
        self._next_sample += SAMPLES_PER_FRAME
        self._expected = (idx + SAMPLES_PER_FRAME) % INDEX_MODULO
        if self._k == self.block_frames:
            self._flush()
        return None

    def _flush(self) -> None:
        k = self._k
        if not k:
            return
        _, v, i = self.layout.decode_phase(memoryview(self._phase)[:k * PHASE_SIZE])
        theta = omega = None
        if self._enc_ok[:k].all():
            _, theta, omega = self.layout.decode_encoder(memoryview(self._enc)[:k * ENCODER_SIZE])
        n = k * SAMPLES_PER_FRAME
        self._ready.append(Block(drive=self.drive, rate_hz=self.rate_hz, v_abc=v, i_abc=i,
                                 first_sample=self._next_sample - n, seq=self._block_seq,
                                 theta_e=theta, omega_e=omega))
        self._block_seq += 1
        self._k = 0

    def _deliver(self, blk: Block) -> Block:
        self.stats.blocks += 1
        self.stats.samples += blk.n
        return blk


# ---------------------------------------------------------------------------------- emulator


class CanEmulator:
    """Device side: sends a record-like's samples as CAN FD frames from a thread.

    ``bus``: a ``can.BusABC`` (not shut down here) or a dict of ``can.Bus`` keyword arguments
    (created with ``ignore_config=True`` and shut down by :meth:`stop`). ``source``: a record-like
    (``v_abc``, ``i_abc`` ``(3, N)``, optional ``theta_e``/``omega_e``, ``rate_hz``) or an iterable
    of them. Each chunk's trailing ``N % 5`` samples are not sent (frames hold 5 samples).
    ``speed``: 1.0 real time, ``k`` faster, ``None`` unpaced.
    """

    def __init__(self, bus, source, base_id: int = DEFAULT_BASE_ID, *, layout: CanLayout | None = None,
                 rate_hz: float | None = None, speed: float | None = 1.0, start_index: int = 0,
                 encoder: bool | None = None, loop: bool = False, batch_frames: int = 500):
        self.layout = layout or CanLayout(base_id=base_id)
        self._owned = None
        if isinstance(bus, dict):
            kw = {"fd": True, **bus}
            self._owned = bus = can.Bus(ignore_config=True, **kw)
        self.bus = bus
        self._source = source
        self.rate_hz = float(rate_hz if rate_hz is not None else getattr(source, "rate_hz", float("nan")))
        if speed is not None and not (self.rate_hz > 0):
            raise ValueError("rate_hz is needed for paced sending (speed is not None)")
        self.speed = speed
        self.index = int(start_index) % INDEX_MODULO  #: sample_index of the next frame
        self.encoder = encoder
        self.loop = loop
        self.batch_frames = int(batch_frames)
        self._stop = threading.Event()
        self.done = threading.Event()
        self._lock = threading.Lock()
        self._inject: list[can.Message] = []
        self._drop = 0
        self.frames_sent = 0
        self.frames_dropped = 0
        self.samples_sent = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="can-emulator", daemon=True)

    def start(self) -> CanEmulator:
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        if self._owned is not None:
            self._owned.shutdown()
            self._owned = None

    def wait(self, timeout: float | None = None) -> bool:
        return self.done.wait(timeout)

    def inject(self, msg: can.Message) -> None:
        """Send ``msg`` before the next sample frame."""
        with self._lock:
            self._inject.append(msg)

    def drop_frames(self, n: int) -> None:
        """Skip the next ``n`` PHASE (and ENCODER) frames: a gap of ``5 n`` samples."""
        with self._lock:
            self._drop += int(n)

    def __enter__(self) -> CanEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _records(self) -> Iterator:
        src = self._source
        while True:
            if hasattr(src, "i_abc"):
                yield src
            else:
                yield from src
                return
            if not self.loop:
                return

    def _msg(self, can_id: int, data: bytes) -> can.Message:
        return can.Message(arbitration_id=can_id, is_extended_id=True, is_fd=True, bitrate_switch=True,
                           data=data, check=False)

    def _run(self) -> None:
        lay, t0 = self.layout, time.monotonic()
        try:
            for rec in self._records():
                v, i = np.asarray(rec.v_abc, float), np.asarray(rec.i_abc, float)
                th, om = getattr(rec, "theta_e", None), getattr(rec, "omega_e", None)
                with_enc = (th is not None and om is not None) if self.encoder is None else self.encoder
                n_all = (v.shape[1] // SAMPLES_PER_FRAME) * SAMPLES_PER_FRAME
                step = self.batch_frames * SAMPLES_PER_FRAME
                for j in range(0, n_all, step):
                    sl = slice(j, min(n_all, j + step))
                    phase = lay.encode_phase(self.index, v[:, sl], i[:, sl])
                    enc = lay.encode_encoder(self.index, th[sl], om[sl]) if with_enc else [None] * len(phase)
                    for p, e in zip(phase, enc):
                        if self._stop.is_set():
                            return
                        if self.speed is not None:
                            target = t0 + (self.samples_sent + SAMPLES_PER_FRAME) / (self.rate_hz * self.speed)
                            delay = target - time.monotonic()
                            if delay > 0.002 and self._stop.wait(delay):  # batch sleeps of >= 2 ms
                                return
                        with self._lock:
                            extra, self._inject = self._inject, []
                            drop = self._drop > 0
                            self._drop -= drop
                        for m in extra:
                            self.bus.send(m)
                        if drop:
                            self.frames_dropped += 1
                        else:
                            if e is not None:
                                self.bus.send(self._msg(lay.encoder_id, e))
                            self.bus.send(self._msg(lay.phase_id, p))
                            self.frames_sent += 1
                        self.index = (self.index + SAMPLES_PER_FRAME) % INDEX_MODULO
                        self.samples_sent += SAMPLES_PER_FRAME
        except Exception as err:  # noqa: BLE001
            self.error = err
            log.info("CAN emulator stopped: %r", err)
        finally:
            self.done.set()
