"""Serial ADC bridge frame: phase samples from the drive's ADC bridge over a UART / USB-serial link.

Wire layout (all little-endian, no padding)::

    offset          size            field
    0               2   u16         sync        SYNC_WORD 0x5AA5 (bytes A5 5A)
    2               1   u8          version     VERSION (1)
    3               1   u8          fmt         FMT_INT16 (1) | FMT_INT24 (2)
    4               2   u16         seq         frame counter, +1 per frame, wraps at 65536
    6               1   u8          n_channels  6 (va vb vc ia ib ic) or 8 (+ theta_e omega_e)
    7               1   u8          flags       reserved, sender writes 0, receiver ignores
    8               2   u16         n_samples   samples per channel, 1..MAX_SAMPLES
    10              2   u16         header_crc  CRC-16 over bytes 0..9
    12              4*C f32[C]      scale       SI unit per LSB per channel (V, A, rad, rad/s)
    12+4C           S*C*B           samples     int16 (B=2) or int24 (B=3), interleaved:
                                                s0.ch0 s0.ch1 .. s0.chC-1 s1.ch0 ..
    12+4C+S*C*B     2   u16         crc         CRC-16 over bytes 0 .. end-2 (header included)

CRC: **CRC-16/IBM-3740** (a.k.a. CRC-16/CCITT-FALSE in older catalogues): width 16, poly 0x1021,
init 0xFFFF, refin/refout false, xorout 0, check("123456789") = 0x29B1 (reveng CRC catalogue).
Python computes it with ``binascii.crc_hqx`` (C speed); the C header carries a bitwise version.
The separate header CRC lets the decoder reject a false sync word in the data (or a corrupt
length) at once instead of waiting for a bogus frame length of bytes.

Physical value = ``int * float32(scale)``. The scale travels in every frame, so the agent needs no
calibration table; firmware owns calibration. Default scales (:data:`DEFAULT_SCALES`) are what the
emulator and the C header use.

:class:`FrameDecoder` is a streaming parser with a fixed-size buffer: ``feed(bytes)`` returns the
complete frames found; garbage, truncated and corrupt frames are skipped by searching the next
sync word from one byte after the rejected one, and counted in :class:`DecoderStats`. ``feed``
never raises for any input bytes.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

import numpy as np

from firmware_if import c_header as ch
from firmware_if.c_header import CExpr, Define, Field

SYNC_WORD = 0x5AA5
SYNC = struct.pack("<H", SYNC_WORD)  # b"\xa5\x5a"
VERSION = 1
FMT_INT16 = 1
FMT_INT24 = 2
#: fmt code -> (name, bytes per sample, min, max)
FORMATS = {FMT_INT16: ("int16", 2, -(2**15), 2**15 - 1), FMT_INT24: ("int24", 3, -(2**23), 2**23 - 1)}
FORMAT_CODES = {"int16": FMT_INT16, "int24": FMT_INT24}
#: Channel order on the wire.
CHANNELS = ("va", "vb", "vc", "ia", "ib", "ic", "theta_e", "omega_e")
UNITS = ("V", "V", "V", "A", "A", "A", "rad", "rad/s")
N_PHASE = 6  #: channel count without encoder
N_ENCODER = 8  #: channel count with theta_e, omega_e
CHANNEL_COUNTS = (N_PHASE, N_ENCODER)
MAX_SAMPLES = 1024  #: samples per channel per frame

HEADER_FIELDS = (
    Field("sync", "u16", comment="PMSM_SER_SYNC_WORD (bytes A5 5A)"),
    Field("version", "u8", comment="PMSM_SER_VERSION"),
    Field("fmt", "u8", comment="PMSM_SER_FMT_INT16 | PMSM_SER_FMT_INT24"),
    Field("seq", "u16", comment="frame counter, +1 per frame, wraps"),
    Field("n_channels", "u8", comment="6 or 8 (PMSM_CH_* order)"),
    Field("flags", "u8", comment="reserved, 0"),
    Field("n_samples", "u16", comment="samples per channel, 1..PMSM_SER_MAX_SAMPLES"),
    Field("header_crc", "u16", comment="CRC-16 over the 10 bytes before it"),
)
HEADER = struct.Struct(ch.struct_format(HEADER_FIELDS))
HEADER_SIZE = HEADER.size  # 12
HEADER_CRC_SPAN = HEADER_SIZE - 2
CRC_SIZE = 2

#: CRC-16/IBM-3740 (CCITT-FALSE) parameters, reveng catalogue.
CRC16_NAME = "CRC-16/IBM-3740"
CRC16_POLY = 0x1021
CRC16_INIT = 0xFFFF
CRC16_XOROUT = 0x0000
CRC16_REFIN = False
CRC16_REFOUT = False
CRC16_CHECK = 0x29B1  #: CRC of b"123456789"

_TWO_PI = 2.0 * np.pi
#: Default SI-per-LSB scale per format, channel order :data:`CHANNELS`.
DEFAULT_SCALES = {
    # +-1638 V, +-65.5 A, +-2pi rad, +-1638 rad/s
    FMT_INT16: (0.05, 0.05, 0.05, 0.002, 0.002, 0.002, _TWO_PI / 2**15, 0.05),
    # +-839 V, +-83.9 A, +-2pi rad, +-1678 rad/s
    FMT_INT24: (1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5, _TWO_PI / 2**23, 2e-4),
}


def crc16(data, crc: int = CRC16_INIT) -> int:
    """CRC-16/IBM-3740 of ``data`` (bytes-like), continuing from ``crc``."""
    return binascii.crc_hqx(data, crc)


def frame_size(n_channels: int, n_samples: int, fmt: int) -> int:
    """Bytes of a frame with ``n_channels`` x ``n_samples`` samples in format ``fmt``."""
    return HEADER_SIZE + 4 * n_channels + n_channels * n_samples * FORMATS[fmt][1] + CRC_SIZE


MAX_FRAME_SIZE = frame_size(N_ENCODER, MAX_SAMPLES, FMT_INT24)


@dataclass
class SerialFrame:
    """One decoded frame: ``raw`` ``(n_channels, n_samples)`` int32, ``scales`` ``(n_channels,)``
    float64 (the float32 on the wire, widened exactly)."""

    seq: int
    fmt: int
    scales: np.ndarray
    raw: np.ndarray

    @property
    def n_channels(self) -> int:
        return int(self.raw.shape[0])

    @property
    def n_samples(self) -> int:
        return int(self.raw.shape[1])

    def values(self) -> np.ndarray:
        """Physical values ``(n_channels, n_samples)`` float64 (V, A, rad, rad/s)."""
        return self.raw * self.scales[:, None]


# ---------------------------------------------------------------------------------- int24


def int24_to_int32(b: np.ndarray) -> np.ndarray:
    """Little-endian int24 bytes ``(3*m,)`` uint8 -> ``(m,)`` int32, sign-extended, vectorised.

    Each 3-byte group goes into the upper three bytes of a little-endian int32 (value << 8);
    an arithmetic shift right by 8 sign-extends.
    """
    b = np.asarray(b, dtype=np.uint8).reshape(-1, 3)
    w = np.zeros((b.shape[0], 4), dtype=np.uint8)
    w[:, 1:] = b
    return w.view("<i4").reshape(-1) >> 8


def int32_to_int24(q: np.ndarray) -> bytes:
    """``(m,)`` integers in int24 range -> little-endian int24 bytes (low three bytes of each)."""
    return np.ascontiguousarray(q, dtype="<i4").view(np.uint8).reshape(-1, 4)[:, :3].tobytes()


# ---------------------------------------------------------------------------------- encode


def wire_scales(scales, n_channels: int) -> np.ndarray:
    """Scales as sent (float32), widened to float64: what the receiver multiplies by."""
    s = np.asarray(scales, dtype=np.float64).reshape(-1)
    if s.size != n_channels:
        raise ValueError(f"need {n_channels} scales, got {s.size}")
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError("scales must be finite and positive")
    return s.astype(np.float32).astype(np.float64)


def quantize(values: np.ndarray, scales, fmt: int = FMT_INT16) -> np.ndarray:
    """Physical ``(n_channels, n)`` -> int32 counts: ``rint(x / float32(scale))``, saturated to
    the format's range (non-finite values become 0)."""
    values = np.asarray(values, dtype=np.float64)
    s = wire_scales(scales, values.shape[0])
    _, _, lo, hi = FORMATS[fmt]
    q = np.rint(values / s[:, None])
    q = np.nan_to_num(q, nan=0.0, posinf=hi, neginf=lo)
    return np.clip(q, lo, hi).astype(np.int32)


def encode_raw(seq: int, raw: np.ndarray, scales, fmt: int = FMT_INT16) -> bytes:
    """One frame from integer counts ``raw`` ``(n_channels, n_samples)`` (must fit ``fmt``)."""
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise ValueError("raw must be (n_channels, n_samples)")
    n_ch, n = raw.shape
    if n_ch not in CHANNEL_COUNTS:
        raise ValueError(f"n_channels must be one of {CHANNEL_COUNTS}, got {n_ch}")
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"n_samples must be 1..{MAX_SAMPLES}, got {n}")
    if fmt not in FORMATS:
        raise ValueError(f"unknown sample format {fmt}")
    _, _, lo, hi = FORMATS[fmt]
    if raw.size and (raw.min() < lo or raw.max() > hi):
        raise ValueError(f"raw counts out of {FORMATS[fmt][0]} range")
    s = wire_scales(scales, n_ch).astype("<f4")
    interleaved = np.ascontiguousarray(raw.T)
    body = interleaved.astype("<i2").tobytes() if fmt == FMT_INT16 else int32_to_int24(interleaved.reshape(-1))
    head = bytearray(HEADER.pack(SYNC_WORD, VERSION, fmt, seq & 0xFFFF, n_ch, 0, n, 0))
    struct.pack_into("<H", head, HEADER_CRC_SPAN, crc16(head[:HEADER_CRC_SPAN]))
    frame = bytes(head) + s.tobytes() + body
    return frame + struct.pack("<H", crc16(frame))


def encode(seq: int, values: np.ndarray, scales=None, fmt: int = FMT_INT16) -> bytes:
    """One frame from physical values ``(n_channels, n_samples)`` (rows in :data:`CHANNELS` order),
    quantised with :func:`quantize`; ``scales`` default to :data:`DEFAULT_SCALES`."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise ValueError("values must be (n_channels, n_samples)")
    if scales is None:
        scales = DEFAULT_SCALES[fmt][: values.shape[0]]
    return encode_raw(seq, quantize(values, scales, fmt), scales, fmt)


# ---------------------------------------------------------------------------------- decode


@dataclass
class DecoderStats:
    frames: int = 0
    bytes: int = 0
    bad_header: int = 0  #: header CRC mismatch (false sync word or corrupt header)
    bad_crc: int = 0  #: frame CRC mismatch
    bad_length: int = 0  #: n_samples 0 or above the decoder's limit
    unknown_format: int = 0  #: version, fmt or n_channels not understood
    resyncs: int = 0  #: runs of skipped bytes before a sync word
    skipped_bytes: int = 0
    internal_errors: int = 0  #: bugs caught so that feed() never raises (should stay 0)

    @property
    def errors(self) -> int:
        """Frames rejected: bad header, bad CRC, bad length, unknown format."""
        return self.bad_header + self.bad_crc + self.bad_length + self.unknown_format


class FrameDecoder:
    """Streaming decoder with a fixed buffer of ``2 * frame_size(8, max_samples, int24)`` bytes.

    ``feed(data)`` appends bytes and returns the complete frames now available, in order. Bytes
    are consumed only by a decoded frame or when no sync word can start at them, so a rejected
    frame's bytes are searched again for the next sync word (resync) and no good frame that
    follows garbage is lost. Memory is bounded whatever the input.
    """

    def __init__(self, max_samples: int = MAX_SAMPLES):
        if not 1 <= max_samples <= MAX_SAMPLES:
            raise ValueError(f"max_samples must be 1..{MAX_SAMPLES}")
        self.max_samples = int(max_samples)
        self.capacity = 2 * frame_size(N_ENCODER, self.max_samples, FMT_INT24)
        self._buf = bytearray(self.capacity)
        self._mv = memoryview(self._buf)  # the exported view also pins the bytearray's size
        self._start = 0
        self._end = 0
        self._hunting = False
        self.stats = DecoderStats()

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return self._end - self._start

    def reset(self) -> None:
        """Drop buffered bytes (e.g. after a reconnect); counters are kept."""
        self._start = self._end = 0
        self._hunting = False

    def feed(self, data) -> list[SerialFrame]:
        out: list[SerialFrame] = []
        try:
            mv = memoryview(data).cast("B")
        except (TypeError, ValueError):
            self.stats.internal_errors += 1
            return out
        pos, total = 0, len(mv)
        self.stats.bytes += total
        while pos < total:
            try:
                if self._start:
                    n_keep = self._end - self._start
                    self._buf[:n_keep] = self._mv[self._start:self._end]
                    self._start, self._end = 0, n_keep
                n = min(total - pos, self.capacity - self._end)
                self._buf[self._end:self._end + n] = mv[pos:pos + n]
                self._end += n
                pos += n
                self._parse(out)
            except Exception:  # noqa: BLE001 - a reader never raises; counted, buffer dropped
                self.stats.internal_errors += 1
                self.reset()
        return out

    # ------------------------------------------------------------------ internals

    def _skip(self, n: int) -> None:
        if n <= 0:
            return
        self.stats.skipped_bytes += n
        if not self._hunting:
            self.stats.resyncs += 1
            self._hunting = True
        self._start += n

    def _reject(self, i: int) -> None:
        self._start = i
        self._skip(1)

    def _parse(self, out: list[SerialFrame]) -> None:
        buf, mv, st = self._buf, self._mv, self.stats
        while self._end - self._start >= 2:
            i = buf.find(SYNC, self._start, self._end)
            if i < 0:
                keep = 1 if buf[self._end - 1] == SYNC[0] else 0
                self._skip(self._end - keep - self._start)
                return
            self._skip(i - self._start)
            if self._end - i < HEADER_SIZE:
                return
            _, version, fmt, seq, n_ch, _, n_samp, hcrc = HEADER.unpack_from(buf, i)
            if crc16(mv[i:i + HEADER_CRC_SPAN]) != hcrc:
                st.bad_header += 1
                self._reject(i)
                continue
            if version != VERSION or fmt not in FORMATS or n_ch not in CHANNEL_COUNTS:
                st.unknown_format += 1
                self._reject(i)
                continue
            if not 1 <= n_samp <= self.max_samples:
                st.bad_length += 1
                self._reject(i)
                continue
            size = frame_size(n_ch, n_samp, fmt)
            if self._end - i < size:
                return
            crc_at = i + size - CRC_SIZE
            if crc16(mv[i:crc_at]) != buf[crc_at] | (buf[crc_at + 1] << 8):
                st.bad_crc += 1
                self._reject(i)
                continue
            out.append(self._decode(i, seq, fmt, n_ch, n_samp))
            st.frames += 1
            self._start = i + size
            self._hunting = False

    def _decode(self, i: int, seq: int, fmt: int, n_ch: int, n_samp: int) -> SerialFrame:
        off = i + HEADER_SIZE
        scales = np.frombuffer(self._buf, "<f4", count=n_ch, offset=off).astype(np.float64)
        off += 4 * n_ch
        count = n_ch * n_samp
        if fmt == FMT_INT16:
            raw = np.frombuffer(self._buf, "<i2", count=count, offset=off).astype(np.int32)
        else:
            raw = int24_to_int32(np.frombuffer(self._buf, np.uint8, count=3 * count, offset=off))
        return SerialFrame(seq=seq, fmt=fmt, scales=scales, raw=raw.reshape(n_samp, n_ch).T.copy())


# ---------------------------------------------------------------------------------- C header

_HEADER_STRUCT = ch.c_struct("pmsm_ser_header_t", HEADER_FIELDS,
                             "serial ADC bridge frame header; then f32 scale[n_channels], samples, u16 crc")
_C_CODE = f"""\
{_HEADER_STRUCT}

/* Total frame size for n_channels x n_samples samples of bytes_per_sample (2 or 3) bytes. */
#define PMSM_SER_FRAME_SIZE(n_channels, n_samples, bytes_per_sample) \\
    (PMSM_SER_HEADER_SIZE + 4u * (n_channels) + (n_channels) * (n_samples) * (bytes_per_sample) + PMSM_SER_CRC_SIZE)
/* Offsets inside a frame. */
#define PMSM_SER_SCALES_OFFSET PMSM_SER_HEADER_SIZE
#define PMSM_SER_SAMPLES_OFFSET(n_channels) (PMSM_SER_HEADER_SIZE + 4u * (n_channels))

/* {CRC16_NAME}: poly 0x1021, init 0xFFFF, no reflection, xorout 0, check 0x29B1.
 * Start with crc = PMSM_CRC16_INIT; header_crc covers bytes 0..9, crc covers bytes 0..end-2. */
static inline uint16_t pmsm_crc16(const uint8_t *data, size_t len, uint16_t crc)
{{
    for (size_t i = 0; i < len; ++i) {{
        crc = (uint16_t)(crc ^ (uint16_t)((uint16_t)data[i] << 8));
        for (int bit = 0; bit < 8; ++bit)
            crc = (crc & 0x8000u) ? (uint16_t)((uint16_t)(crc << 1) ^ PMSM_CRC16_POLY) : (uint16_t)(crc << 1);
    }}
    return crc;
}}

/* Sign-extend a little-endian int24 sample. */
static inline int32_t pmsm_int24_get(const uint8_t *p)
{{
    uint32_t u = (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16);
    return (u & 0x800000u) ? (int32_t)(u | 0xFF000000u) : (int32_t)u;
}}

static inline void pmsm_int24_put(uint8_t *p, int32_t v)
{{
    uint32_t u = (uint32_t)v;
    p[0] = (uint8_t)u; p[1] = (uint8_t)(u >> 8); p[2] = (uint8_t)(u >> 16);
}}"""


def _register_c() -> None:
    ch.register_section("serial_frame", order=10, comment="serial ADC bridge frame (firmware_if/serial_frame.py)",
                        defines=[
        Define("PMSM_SER_SYNC_WORD", SYNC_WORD, "u16 LE, bytes A5 5A", hex=True),
        Define("PMSM_SER_SYNC_BYTE0", SYNC[0], hex=True),
        Define("PMSM_SER_SYNC_BYTE1", SYNC[1], hex=True),
        Define("PMSM_SER_VERSION", VERSION),
        Define("PMSM_SER_FMT_INT16", FMT_INT16, "2 bytes per sample"),
        Define("PMSM_SER_FMT_INT24", FMT_INT24, "3 bytes per sample, little-endian"),
        Define("PMSM_SER_HEADER_SIZE", HEADER_SIZE),
        Define("PMSM_SER_CRC_SIZE", CRC_SIZE),
        Define("PMSM_SER_MAX_SAMPLES", MAX_SAMPLES, "samples per channel per frame"),
        Define("PMSM_SER_N_PHASE", N_PHASE, "channels va..ic"),
        Define("PMSM_SER_N_ENCODER", N_ENCODER, "channels va..ic, theta_e, omega_e"),
        Define("PMSM_SER_MAX_FRAME_SIZE", MAX_FRAME_SIZE),
        *[Define(f"PMSM_CH_{name.upper()}", k, f"channel index, {unit}") for k, (name, unit)
          in enumerate(zip(CHANNELS, UNITS))],
        *[Define(f"PMSM_SER_{FORMATS[fmt][0].upper()}_LSB_{name.upper()}", s, f"default {unit} per LSB")
          for fmt, scales in DEFAULT_SCALES.items() for name, unit, s in zip(CHANNELS, UNITS, scales)],
        Define("PMSM_CRC16_NAME", CRC16_NAME),
        Define("PMSM_CRC16_POLY", CRC16_POLY, hex=True),
        Define("PMSM_CRC16_INIT", CRC16_INIT, hex=True),
        Define("PMSM_CRC16_XOROUT", CRC16_XOROUT, hex=True),
        Define("PMSM_CRC16_REFIN", CRC16_REFIN),
        Define("PMSM_CRC16_REFOUT", CRC16_REFOUT),
        Define("PMSM_CRC16_CHECK", CRC16_CHECK, 'CRC of "123456789"', hex=True),
        Define("PMSM_SER_HEADER_CRC_SPAN", CExpr("PMSM_SER_HEADER_SIZE - 2u"), "bytes covered by header_crc"),
    ], code=_C_CODE)


_register_c()
