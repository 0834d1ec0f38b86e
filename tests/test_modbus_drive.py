"""Snapshot source against the drive emulator over real TCP (127.0.0.1, ephemeral ports) and
RTU on a pty null-modem: bit-exact snapshots, exceptions, failed captures, disconnects."""

import socket
import time

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.constants import ExcCodes

from agent.records import Record
from firmware_if import modbus_capture as cap
from protocols.base import Block, Source
from protocols.modbus_drive import DriveModbusEmulator, ModbusSnapshotSource, SnapshotSourceConfig
from protocols.ptyutil import PtyNullModem

pytestmark = pytest.mark.timeout(60)
FS = 25_000.0


def make_record(n=20_000, fs=FS):
    t = np.arange(n) / fs
    ph = 2 * np.pi * 50.0 * t - 2 * np.pi / 3 * np.arange(3)[:, None]
    rng = np.random.default_rng(0)
    return Record(t=t, v_abc=310 * np.cos(ph) + rng.normal(0, 2, (3, n)),
                  i_abc=8 * np.sin(ph) + rng.normal(0, 0.05, (3, n)))


def generator(first, n):
    k = first + np.arange(n)
    return np.vstack([300 * np.sin(2 * np.pi * (k / 500 + c / 3)) for c in range(3)]
                     + [5 * np.cos(2 * np.pi * (k / 500 + c / 3)) for c in range(3)])


def expected_from_record(rec, first, n, scales):
    """Independent reference: the record's samples at the drive counter, int16-quantised with
    the drive's FLOAT32 scales, scaled back in float64."""
    x = np.vstack([rec.v_abc, rec.i_abc])[:, (first + np.arange(n)) % rec.n]
    s = np.array(scales, dtype=np.float32).astype(np.float64)[:, None]
    raw = np.clip(np.rint(x / s), -32768, 32767)
    return raw * s


def tcp_source(emu, **kw):
    kw.setdefault("samples", 1000)
    kw.setdefault("request_timeout_s", 0.5)
    kw.setdefault("backoff_initial_s", 0.02)
    kw.setdefault("backoff_max_s", 0.2)
    return ModbusSnapshotSource(SnapshotSourceConfig(drive="d0", host="127.0.0.1", port=emu.address[1], **kw))


def read_block(src, within=10.0):
    t_end = time.monotonic() + within
    while time.monotonic() < t_end:
        b = src.read(0.5)
        if b is not None:
            return b
    raise AssertionError(f"no block within {within} s: {src.stats.as_dict()}")


@pytest.fixture
def emulator():
    emu = DriveModbusEmulator(generator, rate_hz=FS, capture_time_s=0.0).start()
    yield emu
    emu.close()


def test_source_contract(emulator):
    src = tcp_source(emulator)
    assert isinstance(src, Source)
    src.close()
    src.close()  # safe twice


def test_snapshot_tcp_bit_exact_from_record():
    rec = make_record()
    with DriveModbusEmulator(rec, capture_time_s=0.01) as emu:
        src = tcp_source(emu, samples=3000)
        src.open()
        blocks = [read_block(src), read_block(src)]
        src.close()
        captures = list(emu.stats.history)
    for b, c in zip(blocks, captures[-2:]):
        assert isinstance(b, Block) and b.drive == "d0" and b.n == 3000
        assert b.v_abc.shape == (3, 3000) and b.i_abc.dtype == np.float64
        assert b.rate_hz == float(np.float32(rec.rate_hz))
        exp = expected_from_record(rec, c.first_sample, 3000, emu.scales)
        assert np.array_equal(b.v_abc, exp[:3]) and np.array_equal(b.i_abc, exp[3:])
        err = np.abs(b.v_abc - rec.v_abc[:, (c.first_sample + np.arange(3000)) % rec.n])
        assert np.all(err <= 0.5 * np.array(emu.scales[:3])[:, None] * (1 + 1e-9))  # half an LSB per channel
    assert [b.seq for b in blocks] == [0, 1]
    assert blocks[0].first_sample == 0
    assert blocks[1].first_sample == captures[-1].first_sample - captures[-2].first_sample > 0
    assert src.stats.blocks == 2 and src.stats.samples == 6000 and src.stats.exceptions == 0


def test_snapshot_spanning_windows(emulator):
    n = cap.WINDOW_SAMPLES + 1234
    src = tcp_source(emulator, samples=n, chunk_registers=125)  # chunks not sample-aligned
    b = read_block(src)
    src.close()
    c = emulator.last_capture
    assert b.n == n
    assert np.array_equal(np.vstack([b.v_abc, b.i_abc]), cap.to_physical(c.raw, emulator.scales))
    assert src.stats.frames == 1 + 1 + 1 + int(np.ceil(6 * cap.WINDOW_SAMPLES / 125)) + \
        int(np.ceil(6 * 1234 / 125)) + 2  # trigger, status, window write, reads, verify, release


def test_snapshot_rtu_over_pty():
    with PtyNullModem() as modem, \
            DriveModbusEmulator(generator, rate_hz=FS, transport="rtu", serial_port=modem.port_a,
                                capture_time_s=0.0) as emu:
        src = ModbusSnapshotSource(SnapshotSourceConfig(drive="rtu0", transport="rtu", serial_port=modem.port_b,
                                                        samples=600, request_timeout_s=0.5,
                                                        backoff_initial_s=0.02, backoff_max_s=0.2))
        b = read_block(src)
        c = emu.last_capture
        assert np.array_equal(np.vstack([b.v_abc, b.i_abc]), cap.to_physical(c.raw, emu.scales))
        # a cut cable: timeouts counted, nothing raised, recovery after re-plugging
        modem.unplug()
        assert src.read(0.8) is None
        assert src.stats.timeouts >= 1
        modem.plug()
        b2 = read_block(src)
        assert b2.n == 600 and b2.seq == 1
        assert np.array_equal(np.vstack([b2.v_abc, b2.i_abc]), cap.to_physical(emu.last_capture.raw, emu.scales))
        src.close()


def test_exceptions_are_counted_and_survived(emulator):
    src = tcp_source(emulator, samples=500, max_retries=3)
    emulator.inject_exceptions(ExcCodes.DEVICE_BUSY, count=1, function_codes={16})  # the trigger
    emulator.inject_exceptions(ExcCodes.DEVICE_FAILURE, count=3, function_codes={4})  # status / samples
    b = read_block(src)
    assert src.stats.exceptions == 4 and src.stats.last_exception_code in (4, 6)
    assert np.array_equal(np.vstack([b.v_abc, b.i_abc]), cap.to_physical(emulator.last_capture.raw, emulator.scales))
    # more consecutive exceptions than max_retries: the capture restarts, still no raise
    emulator.inject_exceptions(ExcCodes.DEVICE_BUSY, count=5, function_codes={4})
    b = read_block(src)
    assert src.stats.exceptions == 9 and src.stats.blocks == 2 and b.seq == 1
    assert emulator.stats.triggers >= 3
    src.close()


def test_failed_capture_is_counted(emulator):
    src = tcp_source(emulator, samples=200)
    emulator.fail_next_capture()
    b = read_block(src)
    src.close()
    assert b.n == 200 and src.stats.capture_errors == 1
    assert "hardware" in src.stats.last_error


def test_bad_count_is_a_capture_error():
    with DriveModbusEmulator(generator, rate_hz=FS, capture_time_s=0.0, capacity=100) as emu:
        src = tcp_source(emu, samples=101)
        assert src.read(0.3) is None
        assert src.stats.capture_errors >= 1 and "bad_count" in src.stats.last_error
        src.close()


def test_disconnect_and_reconnect(emulator):
    src = tcp_source(emulator, samples=300)
    read_block(src)
    emulator.stop()
    t0 = time.monotonic()
    assert src.read(0.4) is None  # never raises, returns within the timeout
    assert time.monotonic() - t0 < 1.0
    assert src.stats.timeouts >= 1 and src.stats.reconnects == 0
    emulator.start()  # same port
    b = read_block(src)
    assert b.seq == 1 and src.stats.reconnects == 1
    src.close()


def test_drive_absent_at_start_then_appears():
    with socket.socket() as s:  # a free port nobody listens on (yet)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    src = ModbusSnapshotSource(SnapshotSourceConfig(port=port, samples=100, backoff_initial_s=0.02,
                                                    backoff_max_s=0.1, request_timeout_s=0.5))
    src.open()  # does not raise
    assert src.read(0.2) is None and "connect" in src.stats.last_error
    with DriveModbusEmulator(generator, rate_hz=FS, capture_time_s=0.0, port=port) as emu:
        assert emu.address[1] == port
        assert read_block(src).n == 100
    src.close()


def test_short_read_timeouts_resume_the_capture():
    with DriveModbusEmulator(generator, rate_hz=FS, capture_time_s=0.15) as emu:
        src = tcp_source(emu, samples=2000)
        nones = 0
        t0 = time.monotonic()
        while True:
            t = time.monotonic()
            b = src.read(0.02)
            assert time.monotonic() - t < 0.2
            if b is not None:
                break
            nones += 1
            assert time.monotonic() - t0 < 5
        assert nones >= 3 and emu.stats.triggers == 1  # resumed, not restarted
        assert np.array_equal(np.vstack([b.v_abc, b.i_abc]), cap.to_physical(emu.last_capture.raw, emu.scales))
        src.close()


def test_counter_wrap_keeps_first_sample_increasing():
    with DriveModbusEmulator(generator, rate_hz=FS, capture_time_s=0.0, counter_offset=2**32 - 3000) as emu:
        src = tcp_source(emu, samples=500)
        firsts = []
        for _ in range(3):
            firsts.append(read_block(src).first_sample)
            time.sleep(0.08)  # 2000 samples at 25 kS/s: the drive counter wraps by the third
        src.close()
        raw_firsts = [c.first_sample for c in list(emu.stats.history)[-3:]]
    assert raw_firsts[-1] >= 2**32  # the drive's counter did wrap (register shows it mod 2^32)
    assert firsts[0] == 0 and firsts[1] > 0 and firsts[2] > firsts[1]
    assert [f - firsts[0] for f in firsts] == [r - raw_firsts[0] for r in raw_firsts]
    assert src.stats.gaps == 2  # snapshots are not contiguous


def test_emulator_write_guard(emulator):
    c = ModbusTcpClient("127.0.0.1", port=emulator.address[1], timeout=1, retries=0)
    assert c.connect()
    try:
        assert c.write_register(3, 1, device_id=1).exception_code == 2  # reserved
        assert c.write_register(cap.address("COMMAND"), 99, device_id=1).exception_code == 3
        assert c.write_registers(cap.address("WINDOW_START"), cap.u32_registers(10**9), device_id=1).exception_code == 3
        assert c.read_input_registers(40, count=2, device_id=1).exception_code == 2  # unmapped gap
        assert c.write_coil(0, True, device_id=1).exception_code == 2
        assert not c.write_registers(0, cap.trigger_registers(10), device_id=1).isError()
        h = cap.CaptureHeader.from_registers(c.read_input_registers(0, count=32, device_id=1).registers)
        assert h.status == cap.Status.READY and h.count == 10 and h.n_channels == 6
        assert c.read_holding_registers(cap.address("COMMAND"), count=1, device_id=1).registers == [0]
    finally:
        c.close()


def test_config_validation():
    with pytest.raises(ValueError, match="chunk_registers"):
        SnapshotSourceConfig(chunk_registers=126)
    with pytest.raises(ValueError, match="serial_port"):
        SnapshotSourceConfig(transport="rtu")
    with pytest.raises(ValueError, match="transport"):
        SnapshotSourceConfig(transport="udp")


def test_snapshot_read_time_tcp(emulator):
    """Figure for the report: one 10 000-sample snapshot (500 FC4 requests) over loopback TCP."""
    src = tcp_source(emulator, samples=10_000)
    t0 = time.perf_counter()
    b = read_block(src)
    dt = time.perf_counter() - t0
    src.close()
    print(f"\nsnapshot 10000 x 6 over TCP: {dt * 1e3:.0f} ms total, transfer "
          f"{src.stats.last_transfer_s * 1e3:.0f} ms, {src.stats.frames} requests")
    assert b.n == 10_000 and dt < 5.0
