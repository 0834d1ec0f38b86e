"""Serial ADC bridge source + emulator over real ptys: exact samples, garbage, gaps, unplug/replug."""

import time

import numpy as np
import pytest

from _transport_helpers import FS, assert_contiguous, joined, make_record, read_samples
from firmware_if import serial_frame as sf
from protocols.base import Source
from protocols.ptyutil import NullModem, PluggablePort, Pty
from protocols.serial_bridge import SerialBridgeEmulator, SerialBridgeSource, record_chunks

SPF = 64  # samples per frame


def quantised(rec, fmt=sf.FMT_INT16):
    x = np.vstack([rec.v_abc, rec.i_abc] + ([np.vstack([rec.theta_e, rec.omega_e])] if rec.theta_e is not None
                                              else []))
    s = sf.DEFAULT_SCALES[fmt][:x.shape[0]]
    return sf.quantize(x, s, fmt) * sf.wire_scales(s, x.shape[0])[:, None]


@pytest.fixture
def pty():
    p = Pty()
    yield p
    p.close()


@pytest.mark.parametrize("fmt,encoder", [(sf.FMT_INT16, False), (sf.FMT_INT24, True)])
def test_samples_arrive_exactly(pty, fmt, encoder):
    n = 10_000
    rec = make_record(n, encoder)
    src = SerialBridgeSource(pty.path, "d1", FS, block_samples=1000)
    assert isinstance(src, Source)
    src.open()
    with SerialBridgeEmulator(pty.master, rec, rate_hz=FS, speed=None, samples_per_frame=SPF, fmt=fmt) as emu:
        blocks = read_samples(src, n)
        assert emu.wait(2)
    src.close()
    want = quantised(rec, fmt)
    np.testing.assert_array_equal(joined(blocks, "v_abc"), want[:3])
    np.testing.assert_array_equal(joined(blocks, "i_abc"), want[3:6])
    if encoder:
        np.testing.assert_array_equal(joined(blocks, "theta_e"), want[6])
        np.testing.assert_array_equal(joined(blocks, "omega_e"), want[7])
    else:
        assert all(b.theta_e is None for b in blocks)
    assert_contiguous(blocks)
    assert [b.seq for b in blocks] == list(range(len(blocks)))
    assert all(b.drive == "d1" and b.rate_hz == FS for b in blocks)
    assert max(b.n for b in blocks) < 1000 + SPF  # bounded block size
    s = src.stats
    assert (s.samples, s.blocks, s.frames) == (n, len(blocks), -(-n // SPF))
    assert (s.bad_frames, s.gaps, s.resyncs, s.reconnects) == (0, 0, 0, 0)


def test_real_time_and_accelerated_pacing(pty):
    rec = make_record(2500)  # 0.1 s
    src = SerialBridgeSource(pty.path, "d1", FS, block_samples=500)
    src.open()
    for speed, lo, hi in ((1.0, 0.095, 2.0), (4.0, 0.024, 1.0)):  # upper bounds: loaded CI machines
        t0 = time.monotonic()
        with SerialBridgeEmulator(pty.master, rec, speed=speed) as emu:
            blocks = read_samples(src, 2500)
            assert emu.wait(2)
        elapsed = time.monotonic() - t0
        assert sum(b.n for b in blocks) == 2500
        assert lo <= elapsed <= hi, (speed, elapsed)
    src.close()


def test_garbage_mid_stream_is_survived_and_counted(pty):
    n = 12_800
    rec = make_record(n)
    src = SerialBridgeSource(pty.path, "d1", FS, block_samples=640)
    src.open()
    rng = np.random.default_rng(3)
    junk = [bytes(rng.integers(0, 256, 300, dtype=np.uint8)),
            sf.SYNC + bytes(rng.integers(0, 256, 40, dtype=np.uint8)),  # false sync word, bad header CRC
            sf.encode(999, np.zeros((6, 4)))[:-5]]  # truncated frame: header fine, CRC fails
    with SerialBridgeEmulator(pty.master, rec, speed=None, samples_per_frame=SPF) as emu:
        blocks = read_samples(src, 1000)
        assert not emu.done.is_set()  # the injection below really lands mid-stream
        for j in junk:
            emu.inject(j)
        blocks += read_samples(src, n - sum(b.n for b in blocks))
        assert emu.wait(2)
    src.close()
    want = quantised(rec)
    np.testing.assert_array_equal(joined(blocks, "i_abc"), want[3:6])
    assert_contiguous(blocks)
    s = src.stats
    assert s.resyncs >= 1 and s.bad_frames >= 2 and s.gaps == 0
    assert src.decoder.stats.bad_header >= 1 and src.decoder.stats.internal_errors == 0
    assert s.last_error.startswith("bad frames")


def test_dropped_frames_are_a_gap_with_exact_jump(pty):
    n = 6400
    rec = make_record(n)
    src = SerialBridgeSource(pty.path, "d1", FS, block_samples=100_000)
    src.open()

    def chunks():  # runs in the emulator thread: the drop lands exactly after frame 10
        parts = list(record_chunks(rec, 640))
        yield parts[0]
        emu.drop_frames(3)
        yield from parts[1:]

    emu = SerialBridgeEmulator(pty.master, chunks(), rate_hz=FS, speed=None, samples_per_frame=SPF,
                               start_seq=65530)  # seq wraps inside the stream
    emu.start()
    blocks = read_samples(src, n - 3 * SPF)
    assert emu.wait(2)
    emu.stop()
    src.close()
    assert src.stats.gaps == 1 and emu.frames_dropped == 3
    jumps = [(a, b) for a, b in zip(blocks, blocks[1:]) if b.first_sample != a.first_sample + a.n]
    assert len(jumps) == 1
    a, b = jumps[0]
    assert b.first_sample - (a.first_sample + a.n) == 3 * SPF
    want = quantised(rec)
    for blk in blocks:  # every block holds exactly the record's samples at its first_sample
        np.testing.assert_array_equal(blk.v_abc, want[:3, blk.first_sample:blk.first_sample + blk.n])


def test_unplug_and_replug_reconnects(tmp_path):
    port = PluggablePort(tmp_path / "ttyBRIDGE")
    rec = make_record(6400)
    src = SerialBridgeSource(port.path, "d1", FS, block_samples=640, backoff_s=(0.02, 0.1))
    src.open()
    try:
        with SerialBridgeEmulator(port.master, rec, speed=None) as emu1:
            blocks = read_samples(src, 6400)
            assert emu1.wait(2)
        assert sum(b.n for b in blocks) == 6400
        port.unplug()  # USB bridge gone: reads fail, the path vanishes
        t0 = time.monotonic()
        assert src.read(0.3) is None  # no exception, no block
        assert time.monotonic() - t0 < 1.0
        assert not src.connected and src.stats.last_error
        port.plug()
        t0 = time.monotonic()
        while not src.connected and time.monotonic() - t0 < 2:  # pyserial flushes input on open:
            assert src.read(0.02) is None  # start the device once the agent is back on the port
        assert src.connected
        # the device kept counting while unplugged: 5 frames never reached the agent
        with SerialBridgeEmulator(port.master, rec, speed=None, start_seq=emu1.seq + 5) as emu2:
            after = read_samples(src, 6400)
            assert emu2.wait(2)
        assert src.stats.reconnects == 1 and src.stats.gaps == 1
        assert after[0].first_sample == 6400 + 5 * SPF
        assert_contiguous(after, 6400 + 5 * SPF)
        np.testing.assert_array_equal(joined(after, "i_abc"), quantised(rec)[3:6])
    finally:
        src.close()
        port.close()


def test_null_modem_both_sides_open_paths():
    rec = make_record(5000, encoder=True)
    with NullModem() as cable:
        src = SerialBridgeSource(cable.path_a, "d2", FS, block_samples=2500)
        src.open()
        emu = SerialBridgeEmulator(cable.path_b, record_chunks(rec, 999), rate_hz=FS, speed=None,
                                   samples_per_frame=100, fmt=sf.FMT_INT24).start()
        blocks = read_samples(src, 5000)
        assert emu.wait(2) and emu.error is None
        emu.stop()
        src.close()
    want = quantised(rec, sf.FMT_INT24)
    np.testing.assert_array_equal(joined(blocks, "v_abc"), want[:3])
    np.testing.assert_array_equal(joined(blocks, "omega_e"), want[7])
    assert_contiguous(blocks)
    assert src.stats.gaps == 0 and src.stats.bad_frames == 0


def test_missing_port_never_raises_from_read(tmp_path):
    src = SerialBridgeSource(str(tmp_path / "nope"), "d1", FS, backoff_s=(0.01, 0.05))
    with pytest.raises(ConnectionError):
        src.open()
    t0 = time.monotonic()
    assert src.read(0.15) is None
    assert 0.1 <= time.monotonic() - t0 < 0.6
    assert "nope" in src.stats.last_error
    src.close()
    src.close()  # twice is fine
    assert src.read(1.0) is None  # closed: returns at once


def test_channel_count_change_starts_new_block(pty):
    a, b = make_record(640), make_record(640, encoder=True, seed=1)
    src = SerialBridgeSource(pty.path, "d1", FS, block_samples=10_000)
    src.open()
    emu = SerialBridgeEmulator(pty.master, iter([a, b]), rate_hz=FS, speed=None).start()
    blocks = read_samples(src, 1280)
    assert emu.wait(2)
    src.close()
    assert [(blk.n, blk.theta_e is not None) for blk in blocks] == [(640, False), (640, True)]
    assert_contiguous(blocks)
