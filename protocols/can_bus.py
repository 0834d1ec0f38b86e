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

import can
import numpy as np

from firmware_if.can_frame import (DEFAULT_BASE_ID, DEFAULT_I_LSB, DEFAULT_OMEGA_LSB, DEFAULT_V_LSB, ENCODER,
                                   ENCODER_SIZE, INDEX_MODULO, PHASE_SIZE, SAMPLES_PER_FRAME, CanLayout)
from protocols.streaming import EmulatorThread, LinkSource

DEFAULT_BLOCK_SAMPLES = 2500
COUNTERS = ("unknown_id", "error_frame", "remote", "malformed")


class CanSource(LinkSource):
    """Phase samples of one drive from a CAN FD bus (see the module docstring)."""

    _open_errors = (can.CanError, OSError, ValueError, ImportError, NotImplementedError)
    _read_errors = (can.CanError, OSError, ValueError, AttributeError)
    _read_call = "recv"

    def __init__(self, interface: str, channel, drive: str, base_id: int = DEFAULT_BASE_ID, fd: bool = True, *,
                 rate_hz: float = 25_000.0, block_samples: int = DEFAULT_BLOCK_SAMPLES,
                 v_lsb: float = DEFAULT_V_LSB, i_lsb: float = DEFAULT_I_LSB, omega_lsb: float = DEFAULT_OMEGA_LSB,
                 filter_ids: bool = True, poll_s: float = 0.05, backoff_s: tuple[float, float] = (0.05, 5.0),
                 name: str | None = None, **bus_kwargs):
        if not fd:
            raise ValueError("the PHASE frame needs CAN FD (64-byte payload); classic CAN is not supported")
        if rate_hz <= 0 or block_samples < 1:
            raise ValueError("rate_hz and block_samples must be positive")
        # block assembly: preallocated payload buffers, one slot per PHASE frame
        self.block_frames = -(-int(block_samples) // SAMPLES_PER_FRAME)
        super().__init__(drive, rate_hz, self.block_frames * SAMPLES_PER_FRAME, poll_s=poll_s,
                         backoff_s=backoff_s, name=name or f"can:{drive}")
        self.interface = interface
        self.channel = channel
        self.layout = CanLayout(drive, base_id, v_lsb, i_lsb, omega_lsb)
        self.filter_ids = filter_ids
        self.bus_kwargs = bus_kwargs
        self.counters = dict.fromkeys(COUNTERS, 0)
        self._phase = bytearray(self.block_frames * PHASE_SIZE)
        self._enc = bytearray(self.block_frames * ENCODER_SIZE)
        self._enc_ok = np.zeros(self.block_frames, dtype=bool)
        self._k = 0  # PHASE frames in the buffer
        self._last_enc: tuple[int, bytes] | None = None

    @property
    def _bus(self) -> can.BusABC | None:
        return self._link

    # ------------------------------------------------------------------ link

    @property
    def _where(self) -> str:
        return f"{self.interface}:{self.channel}"

    def _open_link(self) -> can.BusABC:
        kw = dict(self.bus_kwargs)
        if self.filter_ids:
            kw.setdefault("can_filters", [self.layout.can_filter()])
        return can.Bus(interface=self.interface, channel=self.channel, fd=True, ignore_config=True, **kw)

    def _close_link(self, bus: can.BusABC) -> None:
        bus.shutdown()

    def _link_up(self) -> None:
        self._last_enc = None

    def _receive(self, bus: can.BusABC, timeout: float) -> can.Message | None:
        return bus.recv(timeout)

    # ------------------------------------------------------------------ messages -> blocks

    def _bad(self, what: str, msg: can.Message) -> None:
        self.counters[what] += 1
        self.stats.bad_frames += 1
        self.stats.last_error = f"{what}: id 0x{msg.arbitration_id:X} len {len(msg.data or b'')}"

    def _consume(self, msg: can.Message) -> None:
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
        jump = self._asm.check_counter(idx, SAMPLES_PER_FRAME, INDEX_MODULO)
        if jump:
            self._flush()
            self._asm.skip(jump if jump < INDEX_MODULO // 2 else SAMPLES_PER_FRAME)
        k = self._k
        self._phase[k * PHASE_SIZE:(k + 1) * PHASE_SIZE] = data
        enc = self._last_enc
        if enc is not None and enc[0] == idx:
            self._enc[k * ENCODER_SIZE:(k + 1) * ENCODER_SIZE] = enc[1]
            self._enc_ok[k] = True
        else:
            self._enc_ok[k] = False
        self._k = k + 1
        if self._asm.add(SAMPLES_PER_FRAME):
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
        self._asm.emit(v, i, theta, omega)
        self._k = 0


# ---------------------------------------------------------------------------------- emulator


class CanEmulator(EmulatorThread):
    """Device side: sends a record-like's samples as CAN FD frames from a thread.

    ``bus``: a ``can.BusABC`` (not shut down here) or a dict of ``can.Bus`` keyword arguments
    (created with ``ignore_config=True`` and shut down by :meth:`stop`). ``source``: a record-like
    (``v_abc``, ``i_abc`` ``(3, N)``, optional ``theta_e``/``omega_e``, ``rate_hz``) or an iterable
    of them. Each chunk's trailing ``N % 5`` samples are not sent (frames hold 5 samples).
    ``speed``: 1.0 real time, ``k`` faster, ``None`` unpaced. :meth:`inject` sends a
    ``can.Message`` before the next sample frame; :meth:`drop_frames` skips PHASE (and ENCODER)
    frames: a gap of ``5 n`` samples.
    """

    _min_sleep_s = 0.002  # batch sleeps of >= 2 ms

    def __init__(self, bus, source, base_id: int = DEFAULT_BASE_ID, *, layout: CanLayout | None = None,
                 rate_hz: float | None = None, speed: float | None = 1.0, start_index: int = 0,
                 encoder: bool | None = None, loop: bool = False, batch_frames: int = 500):
        super().__init__(source, rate_hz=rate_hz, speed=speed, loop=loop, thread_name="can-emulator")
        self.layout = layout or CanLayout(base_id=base_id)
        self._owned = None
        if isinstance(bus, dict):
            kw = {"fd": True, **bus}
            self._owned = bus = can.Bus(ignore_config=True, **kw)
        self.bus = bus
        self.index = int(start_index) % INDEX_MODULO  #: sample_index of the next frame
        self.encoder = encoder
        self.batch_frames = int(batch_frames)

    def _release(self) -> None:
        if self._owned is not None:
            self._owned.shutdown()
            self._owned = None

    def _msg(self, can_id: int, data: bytes) -> can.Message:
        return can.Message(arbitration_id=can_id, is_extended_id=True, is_fd=True, bitrate_switch=True,
                           data=data, check=False)

    def _send_injected(self, msg: can.Message) -> None:
        self.bus.send(msg)

    def _send_frame(self, frame: tuple[bytes, bytes | None]) -> None:
        phase, enc = frame
        if enc is not None:
            self.bus.send(self._msg(self.layout.encoder_id, enc))
        self.bus.send(self._msg(self.layout.phase_id, phase))

    def _send_record(self, rec) -> bool:
        lay = self.layout
        v, i = np.asarray(rec.v_abc, float), np.asarray(rec.i_abc, float)
        th, om = getattr(rec, "theta_e", None), getattr(rec, "omega_e", None)
        with_enc = (th is not None and om is not None) if self.encoder is None else self.encoder
        n_all = (v.shape[1] // SAMPLES_PER_FRAME) * SAMPLES_PER_FRAME
        step = self.batch_frames * SAMPLES_PER_FRAME
        for j in range(0, n_all, step):
            sl = slice(j, min(n_all, j + step))
            phase = lay.encode_phase(self.index, v[:, sl], i[:, sl])
            enc = lay.encode_encoder(self.index, th[sl], om[sl]) if with_enc else [None] * len(phase)
            for frame in zip(phase, enc):
                if self._stop.is_set() or not self._emit(SAMPLES_PER_FRAME, frame):
                    return False
                self.index = (self.index + SAMPLES_PER_FRAME) % INDEX_MODULO
        return True
