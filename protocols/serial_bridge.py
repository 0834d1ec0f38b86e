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

import os
from collections.abc import Iterable

import numpy as np
import serial

from firmware_if.serial_frame import (DEFAULT_SCALES, FMT_INT16, MAX_SAMPLES, N_ENCODER, N_PHASE, DecoderStats,
                                      FrameDecoder, SerialFrame, encode_raw, quantize)
from protocols.ptyutil import write_all
from protocols.streaming import EmulatorThread, LinkSource

#: Link budget: 25 kS/s x 6 channels int16 in 64-sample frames is 806 bytes per 64 samples,
#: 315 kB/s, i.e. 3.15 Mbit/s on an 8N1 UART. The default suits FT232H/FT2232H-class bridges;
#: USB CDC-ACM bridges ignore the baud rate; 921600 baud carries only about 7 kS/s.
DEFAULT_BAUD = 4_000_000
#: A block of ``block_samples`` at 25 kS/s = 0.1 s.
DEFAULT_BLOCK_SAMPLES = 2500
SEQ_MODULO = 1 << 16


class SerialBridgeSource(LinkSource):
    """Phase samples of one drive from a serial ADC bridge (see the module docstring)."""

    _open_errors = (serial.SerialException, OSError, ValueError)
    # TypeError/AttributeError: pyserial after a concurrent close()
    _read_errors = (serial.SerialException, OSError, TypeError, AttributeError)

    def __init__(self, port_url: str, drive: str, rate_hz: float, baud: int = DEFAULT_BAUD, *,
                 block_samples: int = DEFAULT_BLOCK_SAMPLES, max_samples: int = MAX_SAMPLES,
                 read_size: int = 4096, poll_s: float = 0.02, backoff_s: tuple[float, float] = (0.05, 5.0),
                 name: str | None = None, **serial_kwargs):
        if rate_hz <= 0 or block_samples < 1 or read_size < 1:
            raise ValueError("rate_hz, block_samples and read_size must be positive")
        super().__init__(drive, rate_hz, block_samples, poll_s=poll_s, backoff_s=backoff_s,
                         name=name or f"serial:{drive}")
        self.port_url = port_url
        self.baud = int(baud)
        self.block_samples = int(block_samples)
        self.read_size = int(read_size)
        self.serial_kwargs = serial_kwargs
        self.decoder = FrameDecoder(max_samples)
        self._seen = DecoderStats()
        self._pending: list[SerialFrame] = []  # frames of the block under way
        self._frame_len = 0

    @property
    def _ser(self) -> serial.SerialBase | None:
        return self._link

    # ------------------------------------------------------------------ link

    @property
    def _where(self) -> str:
        return self.port_url

    def _open_link(self) -> serial.SerialBase:
        return serial.serial_for_url(self.port_url, baudrate=self.baud, timeout=self.poll_s, **self.serial_kwargs)

    def _close_link(self, ser: serial.SerialBase) -> None:
        ser.close()

    def _link_up(self) -> None:
        self.decoder.reset()

    def _receive(self, ser: serial.SerialBase, timeout: float) -> bytes | None:
        return ser.read(min(max(1, ser.in_waiting), self.read_size)) or None

    # ------------------------------------------------------------------ frames -> blocks

    def _consume(self, data: bytes) -> None:
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
            lost = self._asm.check_counter(f.seq, 1, SEQ_MODULO)
            if lost:
                self._flush()
                self._asm.skip(lost * (self._frame_len or n))
            elif self._pending and f.n_channels != self._pending[0].n_channels:
                self._flush()
            self._pending.append(f)
            self._frame_len = n
            if self._asm.add(n):
                self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        x = np.concatenate([f.values() for f in self._pending], axis=1)
        self._pending = []
        enc = x.shape[0] == N_ENCODER
        self._asm.emit(x[0:3], x[3:6], x[6] if enc else None, x[7] if enc else None)


# ---------------------------------------------------------------------------------- emulator


def _channels(rec) -> np.ndarray:
    """``(6|8, N)`` from a record-like (``v_abc``, ``i_abc``, optional ``theta_e``, ``omega_e``)."""
    rows = [np.asarray(rec.v_abc, float), np.asarray(rec.i_abc, float)]
    th, om = getattr(rec, "theta_e", None), getattr(rec, "omega_e", None)
    if th is not None and om is not None:
        rows.append(np.vstack([np.asarray(th, float), np.asarray(om, float)]))
    return np.vstack(rows)


class SerialBridgeEmulator(EmulatorThread):
    """Device side: streams record samples as serial frames from a thread.

    ``port``: an ``int`` fd (e.g. :attr:`protocols.ptyutil.Pty.master`; set non-blocking), a
    pyserial URL (opened here, closed by :meth:`stop`), or an object with ``fileno()`` or ``write()``.
    ``source``: a record-like (``v_abc``, ``i_abc`` ``(3, N)``, optional ``theta_e``/``omega_e``,
    ``rate_hz``), e.g. :class:`agent.records.Record`, or an iterable of them (a generator of
    chunks). ``encoder``: send 8 channels (``None``: when the record has theta_e and omega_e).
    ``speed``: 1.0 real time, ``k`` k times faster, ``None`` no pacing (back-pressure only).
    :meth:`inject` writes bytes (garbage) before the next frame; :meth:`drop_frames` skips
    frames (their seq numbers are used up: a gap).
    """

    def __init__(self, port, source, *, rate_hz: float | None = None, samples_per_frame: int = 64,
                 fmt: int = FMT_INT16, scales=None, speed: float | None = 1.0, start_seq: int = 0,
                 loop: bool = False, chunk_size: int = 256, baud: int = DEFAULT_BAUD, encoder: bool | None = None):
        if not 1 <= samples_per_frame <= MAX_SAMPLES:
            raise ValueError(f"samples_per_frame must be 1..{MAX_SAMPLES}")
        super().__init__(source, rate_hz=rate_hz, speed=speed, loop=loop, thread_name="serial-bridge-emulator")
        self.samples_per_frame = int(samples_per_frame)
        self.fmt = fmt
        self.scales = scales
        self.seq = int(start_seq) % SEQ_MODULO  #: seq of the next frame
        self.chunk_size = int(chunk_size)
        self.encoder = encoder
        self.bytes_sent = 0
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

    def inject(self, data: bytes) -> None:
        """Write ``data`` (garbage) before the next frame."""
        super().inject(bytes(data))

    def _release(self) -> None:
        if self._owned is not None:
            self._owned.close()
            self._owned = None

    def _send(self, data: bytes) -> None:
        if self._fd is not None:
            self.bytes_sent += write_all(self._fd, data, self._stop, self.chunk_size)
        else:
            for k in range(0, len(data), self.chunk_size):
                self._write(data[k:k + self.chunk_size])
            self.bytes_sent += len(data)

    _send_frame = _send_injected = _send

    def _send_record(self, rec) -> bool:
        spf = self.samples_per_frame
        x = _channels(rec)
        if self.encoder is False:
            x = x[:N_PHASE]
        elif self.encoder and x.shape[0] != N_ENCODER:
            raise ValueError("encoder=True needs theta_e and omega_e in the record")
        scales = DEFAULT_SCALES[self.fmt][:x.shape[0]] if self.scales is None else self.scales
        q = quantize(x, scales, self.fmt)  # whole chunk at once
        for j in range(0, x.shape[1], spf):
            if self._stop.is_set():
                return False
            seg = q[:, j:j + spf]
            frame = encode_raw(self.seq, seg, scales, self.fmt)
            self.seq = (self.seq + 1) % SEQ_MODULO
            if not self._emit(seg.shape[1], frame):
                return False
        return True


def record_chunks(rec, n: int) -> Iterable:
    """Split a record-like into record-likes of ``n`` samples (a generator source for the emulator)."""
    from types import SimpleNamespace
    th, om = getattr(rec, "theta_e", None), getattr(rec, "omega_e", None)
    for k in range(0, rec.i_abc.shape[1], n):
        sl = slice(k, k + n)
        yield SimpleNamespace(v_abc=rec.v_abc[:, sl], i_abc=rec.i_abc[:, sl],
                              theta_e=None if th is None else th[sl], omega_e=None if om is None else om[sl])
