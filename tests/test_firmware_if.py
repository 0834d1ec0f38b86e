"""firmware_if: serial frame, CAN FD frame, DBC export, C header (round trips, properties, gcc)."""

import shutil
import subprocess

import cantools
import numpy as np
import pytest
from crccheck.crc import Crc16Ibm3740, Crc16Xmodem
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from firmware_if import c_header as ch
from firmware_if import can_frame as cf
from firmware_if import serial_frame as sf

PROP = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
RNG = np.random.default_rng(7)


def crc16_reference(data: bytes, crc: int = 0xFFFF) -> int:
    """Bitwise CRC-16, poly 0x1021, MSB first (independent of binascii)."""
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def phase_values(n, n_ch=6, v=300.0, i=10.0, rng=RNG):
    x = np.vstack([rng.uniform(-v, v, (3, n)), rng.uniform(-i, i, (3, n))])
    if n_ch == 8:
        x = np.vstack([x, rng.uniform(0, 2 * np.pi, (1, n)), rng.uniform(-600, 600, (1, n))])
    return x


def expected(x, fmt, scales=None):
    scales = sf.DEFAULT_SCALES[fmt][: x.shape[0]] if scales is None else scales
    return sf.quantize(x, scales, fmt) * sf.wire_scales(scales, x.shape[0])[:, None]


def stream(n_frames, n_ch=6, fmt=sf.FMT_INT16, n=32, seq0=0):
    xs = [phase_values(n, n_ch) for _ in range(n_frames)]
    frames = [sf.encode(seq0 + k, x, fmt=fmt) for k, x in enumerate(xs)]
    return xs, frames


# ---------------------------------------------------------------------------------- CRC


def test_crc_catalogue_check_values():
    check = b"123456789"
    assert sf.crc16(check) == sf.CRC16_CHECK == 0x29B1  # CRC-16/IBM-3740 (CCITT-FALSE)
    assert sf.crc16(check, 0) == 0x31C3  # CRC-16/XMODEM: same poly, init 0
    assert Crc16Ibm3740.calc(check) == 0x29B1 and Crc16Xmodem.calc(check) == 0x31C3
    assert sf.crc16(b"") == 0xFFFF


@PROP
@given(st.binary(max_size=300), st.integers(0, 0xFFFF))
def test_crc_matches_bitwise_reference_and_crccheck(data, init):
    assert sf.crc16(data, init) == crc16_reference(data, init)
    assert sf.crc16(data) == Crc16Ibm3740.calc(data)
    # streaming: CRC of a concatenation continues from the first part's CRC
    k = len(data) // 2
    assert sf.crc16(data[k:], sf.crc16(data[:k])) == sf.crc16(data)


# ---------------------------------------------------------------------------------- int24


@PROP
@given(arrays(np.int32, st.integers(0, 50), elements=st.integers(-(2**23), 2**23 - 1)))
def test_int24_round_trip(q):
    b = sf.int32_to_int24(q)
    assert len(b) == 3 * q.size
    back = sf.int24_to_int32(np.frombuffer(b, np.uint8))
    np.testing.assert_array_equal(back, q)
    ref = [int.from_bytes(b[3 * k:3 * k + 3], "little", signed=True) for k in range(q.size)]
    assert back.tolist() == ref


# ---------------------------------------------------------------------------------- serial frame


def test_header_layout_is_12_bytes_and_sync_bytes():
    assert sf.HEADER_SIZE == 12 and ch.struct_size(sf.HEADER_FIELDS) == 12
    f = sf.encode(0x1234, phase_values(3), fmt=sf.FMT_INT24)
    assert f[:2] == b"\xa5\x5a" and f[2] == sf.VERSION and f[3] == sf.FMT_INT24
    assert f[4:6] == b"\x34\x12" and f[6] == 6 and f[8:10] == b"\x03\x00"
    assert len(f) == sf.frame_size(6, 3, sf.FMT_INT24) == 12 + 24 + 6 * 3 * 3 + 2
    assert crc16_reference(f[:10]) == int.from_bytes(f[10:12], "little")
    assert crc16_reference(f[:-2]) == int.from_bytes(f[-2:], "little")


@pytest.mark.parametrize("fmt", [sf.FMT_INT16, sf.FMT_INT24])
@pytest.mark.parametrize("n_ch", [6, 8])
def test_serial_round_trip_exact_to_quantisation(fmt, n_ch):
    x = phase_values(200, n_ch)
    frames = sf.FrameDecoder().feed(sf.encode(65535, x, fmt=fmt))
    assert len(frames) == 1
    f = frames[0]
    assert (f.seq, f.fmt, f.n_channels, f.n_samples) == (65535, fmt, n_ch, 200)
    np.testing.assert_array_equal(f.values(), expected(x, fmt))
    lsb = sf.wire_scales(sf.DEFAULT_SCALES[fmt][:n_ch], n_ch)
    assert np.all(np.abs(f.values() - x) <= lsb[:, None] / 2 * (1 + 1e-9))


def test_quantize_saturates_and_maps_nonfinite():
    s = sf.DEFAULT_SCALES[sf.FMT_INT16][:6]
    x = np.zeros((6, 4))
    x[0] = [1e9, -1e9, np.nan, np.inf]
    q = sf.quantize(x, s)
    assert q[0].tolist() == [32767, -32768, 0, 32767]


@PROP
@given(fmt=st.sampled_from([sf.FMT_INT16, sf.FMT_INT24]), n_ch=st.sampled_from([6, 8]),
       n=st.integers(1, 300), seq=st.integers(0, 0xFFFF), data=st.data())
def test_serial_round_trip_property(fmt, n_ch, n, seq, data):
    lo, hi = sf.FORMATS[fmt][2:]
    raw = data.draw(arrays(np.int32, (n_ch, n), elements=st.integers(lo, hi)))
    scales = data.draw(st.lists(st.floats(1e-6, 10.0), min_size=n_ch, max_size=n_ch))
    frames = sf.FrameDecoder().feed(sf.encode_raw(seq, raw, scales, fmt))
    assert len(frames) == 1
    np.testing.assert_array_equal(frames[0].raw, raw)
    np.testing.assert_array_equal(frames[0].scales, np.float32(scales).astype(np.float64))


def test_encode_rejects_bad_arguments():
    with pytest.raises(ValueError):
        sf.encode(0, np.zeros((5, 10)))
    with pytest.raises(ValueError):
        sf.encode(0, np.zeros((6, sf.MAX_SAMPLES + 1)))
    with pytest.raises(ValueError):
        sf.encode(0, np.zeros((6, 0)))
    with pytest.raises(ValueError):
        sf.encode_raw(0, np.full((6, 2), 40000), sf.DEFAULT_SCALES[1][:6])
    with pytest.raises(ValueError):
        sf.encode(0, np.zeros((6, 2)), scales=[0.0] * 6)


@PROP
@given(cuts=st.lists(st.integers(0, 10_000), max_size=12), fmt=st.sampled_from([1, 2]))
def test_decoder_split_feeds_equal_whole_feed(cuts, fmt):
    xs, frames = stream(8, 6 + 2 * (fmt == 2), fmt, n=40)
    data = b"".join(frames)
    cuts = sorted({c % (len(data) + 1) for c in cuts})
    d = sf.FrameDecoder()
    got = []
    for a, b in zip([0, *cuts], [*cuts, len(data)]):
        got += d.feed(data[a:b])
    assert [f.seq for f in got] == list(range(8))
    for f, x in zip(got, xs):
        np.testing.assert_array_equal(f.values(), expected(x, fmt))
    assert d.stats.errors == 0 and d.stats.resyncs == 0 and d.buffered == 0


@PROP
@given(garbage=st.binary(max_size=3000), chunk=st.integers(1, 700))
def test_decoder_survives_random_garbage(garbage, chunk):
    d = sf.FrameDecoder(max_samples=64)
    got = []
    for k in range(0, len(garbage), chunk):
        got += d.feed(garbage[k:k + chunk])
    assert got == []
    assert d.stats.internal_errors == 0
    assert d.buffered <= 1 or d.buffered < sf.frame_size(8, 64, 2)
    assert len(d._buf) == d.capacity


@PROP
@given(g=st.lists(st.binary(max_size=200), min_size=5, max_size=5), chunk=st.integers(1, 500))
def test_decoder_resyncs_after_garbage_between_frames(g, chunk):
    xs, frames = stream(4, n=20)
    data = g[0] + frames[0] + g[1] + frames[1] + g[2] + frames[2] + g[3] + frames[3] + g[4]
    d = sf.FrameDecoder()
    got = []
    for k in range(0, len(data), chunk):
        got += d.feed(data[k:k + chunk])
    assert [f.seq for f in got] == [0, 1, 2, 3]
    n_junk = sum(1 for x in g[:4] if x)
    assert d.stats.resyncs >= (1 if n_junk else 0)
    assert d.stats.internal_errors == 0


@PROP
@given(bit=st.integers(0, 10**9), fmt=st.sampled_from([1, 2]))
def test_decoder_single_bit_flip_loses_exactly_that_frame(bit, fmt):
    xs, frames = stream(5, 6, fmt, n=24)
    data = bytearray(b"".join(frames))
    bit %= 8 * len(data)
    data[bit // 8] ^= 1 << (bit % 8)
    hit = next(k for k in range(5) if bit // 8 < sum(map(len, frames[:k + 1])))
    d = sf.FrameDecoder()
    got = d.feed(bytes(data))
    assert [f.seq for f in got] == [k for k in range(5) if k != hit]
    assert d.stats.errors + d.stats.resyncs >= 1
    for f in got:
        np.testing.assert_array_equal(f.values(), expected(xs[f.seq], fmt))


@PROP
@given(cut=st.integers(0, 10**6))
def test_decoder_truncation_keeps_complete_frames(cut):
    _, frames = stream(4, n=30)
    data = b"".join(frames)
    cut %= len(data) + 1
    d = sf.FrameDecoder()
    got = d.feed(data[:cut])
    ends = np.cumsum([len(f) for f in frames])
    assert len(got) == int(np.sum(ends <= cut))
    assert d.stats.errors == 0
    # the truncated frame completes when the rest arrives
    assert len(got) + len(d.feed(data[cut:])) == 4


def _patched_header(frame: bytes, **fields) -> bytes:
    """Frame with header fields changed and the header CRC made valid again."""
    import struct
    vals = dict(zip([f.name for f in sf.HEADER_FIELDS], sf.HEADER.unpack_from(frame)))
    vals.update(fields)
    head = bytearray(sf.HEADER.pack(*vals.values()))
    struct.pack_into("<H", head, 10, sf.crc16(head[:10]))
    return bytes(head) + frame[12:]


def test_decoder_counts_each_error_kind():
    _, (good,) = stream(1, n=10)
    d = sf.FrameDecoder(max_samples=64)
    bad_crc = bytearray(good)
    bad_crc[20] ^= 0xFF
    bad_header = bytearray(good)
    bad_header[4] ^= 0x01
    cases = [bytes(bad_crc), bytes(bad_header), _patched_header(good, version=9), _patched_header(good, fmt=7),
             _patched_header(good, n_channels=5), _patched_header(good, n_samples=0),
             _patched_header(good, n_samples=65)]
    got = d.feed(b"".join(c + good for c in cases))
    s = d.stats
    assert len(got) == len(cases)
    assert (s.bad_crc, s.bad_header, s.unknown_format, s.bad_length) == (1, 1, 3, 2)
    assert s.errors == 7 and s.internal_errors == 0


def test_decoder_memory_bounded_under_endless_sync_words():
    d = sf.FrameDecoder(max_samples=128)
    fake = _patched_header(sf.encode(0, phase_values(128)), n_samples=128)[:12]  # valid header, no body
    junk = (fake + bytes(RNG.integers(0, 256, 700, dtype=np.uint8))) * 300
    for k in range(0, len(junk), 4096):
        assert d.feed(junk[k:k + 4096]) == []
        assert d.buffered <= d.capacity
    assert len(d._buf) == d.capacity
    assert d.stats.bad_crc >= 290 and d.stats.internal_errors == 0
    # the last fake header (valid header CRC) claims 1574 bytes: the frames that follow are found
    # once that many bytes have arrived (bounded resync latency), none is lost
    _, frames = stream(20, n=5)
    assert [f.seq for f in d.feed(b"".join(frames))] == list(range(20))


def test_decoder_never_raises_on_odd_input():
    d = sf.FrameDecoder()
    assert d.feed(b"") == []
    assert d.feed(memoryview(b"\xa5\x5a" * 10)) == []
    assert d.feed(np.arange(10, dtype=np.int32)) == []  # multi-byte buffer: cast to bytes
    assert d.stats.internal_errors == 0
    assert d.feed("not bytes") == [] and d.stats.internal_errors == 1


# ---------------------------------------------------------------------------------- CAN frame


def test_can_layout_sizes_and_ids():
    assert cf.PHASE_SIZE == 64 and cf.ENCODER_SIZE == 24
    lay = cf.CanLayout("d3", cf.drive_base_id(3))
    assert lay.base_id == cf.DEFAULT_BASE_ID + 48
    assert (lay.phase_id, lay.encoder_id) == (lay.base_id, lay.base_id + 1)
    assert lay.kind(lay.phase_id) == cf.PHASE and lay.kind(lay.encoder_id) == cf.ENCODER
    assert lay.kind(lay.base_id + 5) is None and lay.in_block(lay.base_id + 5)
    assert lay.kind(lay.phase_id, is_extended=False) is None
    assert not lay.in_block(lay.base_id + 16)
    for bad in (0x20000000, 0x100 + 3, -16):
        with pytest.raises(ValueError):
            cf.CanLayout(base_id=bad)
    with pytest.raises(ValueError):
        cf.CanLayout(v_lsb=0.0)


@PROP
@given(n5=st.integers(1, 40), first=st.integers(0, 2**32 - 1), data=st.data())
def test_can_phase_round_trip_property(n5, first, data):
    lay = cf.CanLayout()
    n = 5 * n5
    v = data.draw(arrays(float, (3, n), elements=st.floats(-1638, 1638)))
    i = data.draw(arrays(float, (3, n), elements=st.floats(-65, 65)))
    payloads = lay.encode_phase(first, v, i)
    assert len(payloads) == n5 and all(len(p) == 64 for p in payloads)
    idx, v2, i2 = lay.decode_phase(b"".join(payloads))
    assert idx.tolist() == [(first + 5 * k) % 2**32 for k in range(n5)]
    np.testing.assert_array_equal(v2, np.rint(v / lay.v_lsb) * lay.v_lsb)
    np.testing.assert_array_equal(i2, np.rint(i / lay.i_lsb) * lay.i_lsb)


def test_can_encoder_round_trip_and_saturation():
    lay = cf.CanLayout(omega_lsb=0.1)
    th = np.linspace(-7, 7, 20)
    om = np.linspace(-5000, 5000, 20)
    idx, th2, om2 = lay.decode_encoder(b"".join(lay.encode_encoder(10, th, om)))
    assert idx.tolist() == [10, 15, 20, 25]
    err = np.angle(np.exp(1j * (th2 - th)))
    assert np.all(np.abs(err) <= cf.THETA_LSB / 2 + 1e-12) and np.all((th2 >= 0) & (th2 < 2 * np.pi))
    np.testing.assert_array_equal(om2, np.clip(np.rint(om / 0.1), -32768, 32767) * 0.1)
    with pytest.raises(ValueError):
        lay.encode_phase(0, np.zeros((3, 7)), np.zeros((3, 7)))
    with pytest.raises(ValueError):
        lay.decode_phase(b"\x00" * 63)


def test_dbc_loads_in_cantools_and_decodes_like_us():
    lays = [cf.CanLayout("drive0"), cf.CanLayout("line-2", cf.drive_base_id(2), v_lsb=0.1, i_lsb=0.001)]
    db = cantools.database.load_string(cf.to_dbc(lays), database_format="dbc")
    assert len(db.messages) == 4
    for lay in lays:
        for can_id, size, nsig in ((lay.phase_id, 64, 31), (lay.encoder_id, 24, 11)):
            m = db.get_message_by_frame_id(can_id, force_extended_id=True)
            assert m.is_extended_frame and m.is_fd and m.length == size and len(m.signals) == nsig
        payload = bytes(RNG.integers(0, 256, 64, dtype=np.uint8))
        theirs = db.decode_message(lay.phase_id, payload, force_extended_id=True)
        idx, v, i = lay.decode_phase(payload)
        assert theirs["sample_index"] == idx[0]
        for k in range(5):
            for c, name in enumerate(cf.PHASE_CHANNELS):
                ours = (v if c < 3 else i)[c % 3, k]
                assert theirs[f"{name}_{k}"] == pytest.approx(ours, rel=1e-12, abs=1e-12)
        enc = bytes(RNG.integers(0, 256, 24, dtype=np.uint8))
        theirs = db.decode_message(lay.encoder_id, enc, force_extended_id=True)
        _, th, om = lay.decode_encoder(enc)
        for k in range(5):
            assert theirs[f"theta_e_{k}"] == pytest.approx(th[k], rel=1e-12)
            assert theirs[f"omega_e_{k}"] == pytest.approx(om[k], rel=1e-12, abs=1e-12)


@PROP
@given(payload=st.binary(min_size=64, max_size=64))
def test_dbc_decode_agrees_on_random_payloads(payload):
    lay = cf.CanLayout()
    db = _DB_DEFAULT
    theirs = db.decode_message(lay.phase_id, payload, force_extended_id=True, scaling=False)
    idx, v, i = lay.decode_phase(payload)
    raw = np.frombuffer(payload, cf.PHASE_DTYPE)["samples"][0]
    assert theirs["sample_index"] == idx[0]
    assert [theirs[f"{n}_{k}"] for k in range(5) for n in cf.PHASE_CHANNELS] == raw.reshape(-1).tolist()


_DB_DEFAULT = cantools.database.load_string(cf.to_dbc(cf.CanLayout()), database_format="dbc")


def test_dbc_low_extended_id_needs_force_extended():
    """cantools gotcha: an extended id <= 0x7FF is looked up as a standard id without the flag."""
    lay = cf.CanLayout("low", base_id=0x200)
    db = cantools.database.load_string(cf.to_dbc(lay), database_format="dbc")
    payload = lay.encode_phase(0, np.ones((3, 5)), np.ones((3, 5)))[0]
    with pytest.raises(KeyError):
        db.decode_message(0x200, payload)
    assert db.decode_message(0x200, payload, force_extended_id=True)["va_0"] == pytest.approx(1.0)


# ---------------------------------------------------------------------------------- C header


def test_registry_contributions_and_conflicts():
    try:
        ch.register_defines("test_extra", {"PMSM_TEST_A": 7, "PMSM_TEST_B": -1.5, "PMSM_TEST_S": 'a"b'})
        ch.register_defines("test_extra2", [("PMSM_TEST_C", 0x1F, "c")])
        text = ch.render_header()
        assert "#define PMSM_TEST_A 7u" in text and "#define PMSM_TEST_B (-1.5)" in text
        assert '#define PMSM_TEST_S "a\\"b"' in text and "/* c */" in text
        ch.register_defines("test_extra2", [("PMSM_TEST_A", 1)])
        with pytest.raises(ValueError, match="PMSM_TEST_A"):
            ch.render_header()
        with pytest.raises(ValueError):
            ch.register_defines("test_extra3", {"lower_case": 1})
        with pytest.raises(ValueError):
            ch.register_defines("test_extra3", {"NO_PREFIX": 1})
    finally:
        for s in ("test_extra", "test_extra2", "test_extra3"):
            ch.unregister_section(s)
    assert "PMSM_TEST_A" not in ch.render_header()


def test_header_has_our_sections_and_constants():
    text = ch.render_header()
    for needle in ("#define PMSM_SER_SYNC_WORD 0x5AA5u", "#define PMSM_CRC16_POLY 0x1021u",
                   "#define PMSM_CRC16_CHECK 0x29B1u", "pmsm_ser_header_t", "pmsm_can_phase_t",
                   f"#define PMSM_CAN_DEFAULT_BASE_ID 0x{cf.DEFAULT_BASE_ID:X}u", "#define PMSM_CAN_V_LSB 0.05"):
        assert needle in text


GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc not installed")


@needs_gcc
def test_header_compiles_warning_free(tmp_path):
    h = ch.write_header(tmp_path)
    for std in ("c11", "gnu17"):
        r = subprocess.run([GCC, f"-std={std}", "-fsyntax-only", "-Wall", "-Wextra", "-Werror", "-x", "c", str(h)],
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    gxx = shutil.which("g++")
    if gxx:
        r = subprocess.run([gxx, "-std=c++11", "-fsyntax-only", "-Wall", "-Werror", "-x", "c++", str(h)],
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr


C_ROUND_TRIP = r"""
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "pmsm_wire.h"

static uint8_t *slurp(const char *path, size_t *len)
{
    FILE *f = fopen(path, "rb");
    static uint8_t buf[PMSM_SER_MAX_FRAME_SIZE];
    if (!f) exit(2);
    *len = fread(buf, 1, sizeof buf, f);
    fclose(f);
    return buf;
}

static void spill(const char *path, const void *data, size_t len)
{
    FILE *f = fopen(path, "wb");
    if (!f || fwrite(data, 1, len, f) != len) exit(3);
    fclose(f);
}

int main(int argc, char **argv)
{
    static uint8_t out[PMSM_SER_MAX_FRAME_SIZE];
    static double value[PMSM_SER_MAX_SAMPLES][PMSM_SER_N_ENCODER];
    size_t len;
    if (argc != 5) return 1;
    /* ---- serial frame: parse, check, print, re-encode from the physical values ---- */
    const uint8_t *in = slurp(argv[1], &len);
    pmsm_ser_header_t h;
    memcpy(&h, in, sizeof h);
    if (h.sync != PMSM_SER_SYNC_WORD || in[0] != PMSM_SER_SYNC_BYTE0 || in[1] != PMSM_SER_SYNC_BYTE1) return 10;
    if (pmsm_crc16(in, PMSM_SER_HEADER_CRC_SPAN, PMSM_CRC16_INIT) != h.header_crc) return 11;
    unsigned bps = h.fmt == PMSM_SER_FMT_INT16 ? 2u : 3u;
    size_t size = PMSM_SER_FRAME_SIZE(h.n_channels, h.n_samples, bps);
    if (size != len) return 12;
    uint16_t crc;
    memcpy(&crc, in + size - PMSM_SER_CRC_SIZE, sizeof crc);
    if (pmsm_crc16(in, size - PMSM_SER_CRC_SIZE, PMSM_CRC16_INIT) != crc) return 13;
    float scale[PMSM_SER_N_ENCODER];
    memcpy(scale, in + PMSM_SER_SCALES_OFFSET, 4u * h.n_channels);
    printf("ser %u %u %u %u\n", h.seq, h.fmt, h.n_channels, h.n_samples);
    const uint8_t *s = in + PMSM_SER_SAMPLES_OFFSET(h.n_channels);
    for (unsigned k = 0; k < h.n_samples; ++k)
        for (unsigned c = 0; c < h.n_channels; ++c, s += bps) {
            int32_t raw = bps == 2u ? (int32_t)(int16_t)(uint16_t)(s[0] | (s[1] << 8)) : pmsm_int24_get(s);
            value[k][c] = raw * (double)scale[c];
            printf("%.17g\n", value[k][c]);
        }
    pmsm_ser_header_t o;
    memset(&o, 0, sizeof o);
    o.sync = PMSM_SER_SYNC_WORD; o.version = PMSM_SER_VERSION; o.fmt = h.fmt; o.seq = h.seq;
    o.n_channels = h.n_channels; o.n_samples = h.n_samples;
    memcpy(out, &o, sizeof o);
    o.header_crc = pmsm_crc16(out, PMSM_SER_HEADER_CRC_SPAN, PMSM_CRC16_INIT);
    memcpy(out, &o, sizeof o);
    memcpy(out + PMSM_SER_SCALES_OFFSET, scale, 4u * h.n_channels);
    uint8_t *d = out + PMSM_SER_SAMPLES_OFFSET(h.n_channels);
    for (unsigned k = 0; k < h.n_samples; ++k)
        for (unsigned c = 0; c < h.n_channels; ++c, d += bps) {
            int32_t raw = (int32_t)lrint(value[k][c] / (double)scale[c]);
            if (bps == 2u) { d[0] = (uint8_t)raw; d[1] = (uint8_t)((uint32_t)raw >> 8); }
            else pmsm_int24_put(d, raw);
        }
    crc = pmsm_crc16(out, size - PMSM_SER_CRC_SIZE, PMSM_CRC16_INIT);
    memcpy(out + size - PMSM_SER_CRC_SIZE, &crc, sizeof crc);
    spill(argv[2], out, size);
    /* ---- CAN FD PHASE payload ---- */
    in = slurp(argv[3], &len);
    if (len != sizeof(pmsm_can_phase_t)) return 20;
    pmsm_can_phase_t p, q;
    memcpy(&p, in, sizeof p);
    printf("can %u\n", (unsigned)p.sample_index);
    q.sample_index = p.sample_index;
    for (unsigned k = 0; k < PMSM_CAN_SAMPLES_PER_FRAME; ++k)
        for (unsigned c = 0; c < 6u; ++c) {
            double lsb = c < 3u ? PMSM_CAN_V_LSB : PMSM_CAN_I_LSB;
            double v = p.samples[k][c] * lsb;
            printf("%.17g\n", v);
            q.samples[k][c] = (int16_t)lrint(v / lsb);
        }
    spill(argv[4], &q, sizeof q);
    printf("check %u %u %u %u\n", (unsigned)pmsm_crc16((const uint8_t *)"123456789", 9, PMSM_CRC16_INIT),
           (unsigned)sizeof(pmsm_ser_header_t), (unsigned)sizeof(pmsm_can_phase_t),
           (unsigned)sizeof(pmsm_can_encoder_t));
    return 0;
}
"""


@needs_gcc
@pytest.mark.parametrize("fmt,n_ch", [(sf.FMT_INT16, 6), (sf.FMT_INT24, 8)])
def test_c_program_round_trips_python_frames(tmp_path, fmt, n_ch):
    ch.write_header(tmp_path)
    src = tmp_path / "rt.c"
    src.write_text(C_ROUND_TRIP)
    exe = tmp_path / "rt"
    r = subprocess.run([GCC, "-std=c11", "-Wall", "-Wextra", "-Werror", "-O1", f"-I{tmp_path}", str(src), "-o",
                        str(exe), "-lm"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    x = phase_values(17, n_ch)
    frame = sf.encode(4321, x, fmt=fmt)
    lay = cf.CanLayout()
    can_payload = lay.encode_phase(2**32 - 5, x[:3, :5], x[3:6, :5])[0]
    (tmp_path / "ser.bin").write_bytes(frame)
    (tmp_path / "can.bin").write_bytes(can_payload)
    r = subprocess.run([str(exe), *(str(tmp_path / n) for n in ("ser.bin", "ser_out.bin", "can.bin", "can_out.bin"))],
                       capture_output=True, text=True, timeout=20)
    assert r.returncode == 0, (r.returncode, r.stderr)
    lines = r.stdout.splitlines()
    assert lines[0] == f"ser 4321 {fmt} {n_ch} 17"
    c_vals = np.array([float(v) for v in lines[1:1 + 17 * n_ch]]).reshape(17, n_ch).T
    (py,) = sf.FrameDecoder().feed(frame)
    np.testing.assert_array_equal(c_vals, py.values())  # bit-exact
    assert (tmp_path / "ser_out.bin").read_bytes() == frame  # C re-encoding == Python encoding
    k = 1 + 17 * n_ch
    assert lines[k] == f"can {2**32 - 5}"
    c_can = np.array([float(v) for v in lines[k + 1:k + 31]]).reshape(5, 6).T
    _, v, i = lay.decode_phase(can_payload)
    np.testing.assert_array_equal(c_can, np.vstack([v, i]))
    assert (tmp_path / "can_out.bin").read_bytes() == can_payload
    assert lines[k + 31] == f"check {0x29B1} 12 64 24"


def test_command_line_exports(tmp_path):
    assert cf.main(["--drive", "left", "--drive", "right=0x200", "-o", str(tmp_path / "d.dbc")]) == 0
    db = cantools.database.load_file(str(tmp_path / "d.dbc"))
    assert {m.name: m.frame_id for m in db.messages} == {
        "PMSM_PHASE_left": cf.DEFAULT_BASE_ID, "PMSM_ENCODER_left": cf.DEFAULT_BASE_ID + 1,
        "PMSM_PHASE_right": 0x200, "PMSM_ENCODER_right": 0x201}
    assert ch.main(["-o", str(tmp_path)]) == 0
    assert (tmp_path / "pmsm_wire.h").read_text() == ch.render_header()


def test_put_drop_oldest_keeps_the_newest():
    import queue

    from protocols.streaming import put_drop_oldest

    q = queue.Queue(maxsize=3)
    dropped = sum(put_drop_oldest(q, i) for i in range(10))
    assert dropped == 7 and [q.get_nowait() for _ in range(3)] == [7, 8, 9]


def test_short_capture_header_reply_is_a_value_error_naming_the_lengths():
    from firmware_if import modbus_capture as cap

    with pytest.raises(ValueError, match=f"short header reply: 5 of {cap.HEADER_REGS} registers"):
        cap.CaptureHeader.from_registers([0] * 5)
