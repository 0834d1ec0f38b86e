"""CAN FD source + emulator on python-can's in-process ``virtual`` interface."""

import uuid

import can
import cantools
import numpy as np
import pytest

from _transport_helpers import FS, assert_contiguous, joined, make_record, read_samples
from agent.records import Record
from firmware_if import can_frame as cf
from protocols.base import Source
from protocols.can_bus import CanEmulator, CanSource

BASE = cf.drive_base_id(2)


def q(x, lsb):
    return np.rint(np.asarray(x) / lsb) * lsb


@pytest.fixture
def channel():
    return f"test-{uuid.uuid4().hex[:8]}"  # a private virtual bus per test


def bus_cfg(channel):
    return {"interface": "virtual", "channel": channel}


@pytest.mark.parametrize("encoder", [False, True])
def test_samples_arrive_exactly(channel, encoder):
    n = 10_000
    rec = make_record(n, encoder)
    src = CanSource("virtual", channel, "d2", BASE, rate_hz=FS, block_samples=1000)
    assert isinstance(src, Source)
    src.open()
    with CanEmulator(bus_cfg(channel), rec, BASE, speed=None, start_index=2**32 - 500) as emu:  # index wraps
        blocks = read_samples(src, n)
        assert emu.wait(2) and emu.error is None
    src.close()
    lay = cf.CanLayout()
    np.testing.assert_array_equal(joined(blocks, "v_abc"), q(rec.v_abc, lay.v_lsb))
    np.testing.assert_array_equal(joined(blocks, "i_abc"), q(rec.i_abc, lay.i_lsb))
    if encoder:
        th = joined(blocks, "theta_e")
        assert np.all(np.abs(np.angle(np.exp(1j * (th - rec.theta_e)))) <= cf.THETA_LSB / 2 + 1e-12)
        np.testing.assert_array_equal(joined(blocks, "omega_e"), q(rec.omega_e, lay.omega_lsb))
    else:
        assert all(b.theta_e is None for b in blocks)
    assert_contiguous(blocks)
    # full blocks of 1000, or fewer samples when a read's deadline came first (a loaded machine)
    assert all(0 < b.n <= 1000 and b.n % 5 == 0 for b in blocks)
    assert [b.seq for b in blocks] == list(range(len(blocks)))
    s = src.stats
    assert (s.samples, s.blocks, s.frames, s.gaps, s.bad_frames) == (n, len(blocks), n // 5, 0, 0)


def test_unknown_ids_error_frames_and_malformed_payloads_are_counted(channel):
    n = 5000
    rec = make_record(n)
    src = CanSource("virtual", channel, "d2", BASE, rate_hz=FS, block_samples=500, filter_ids=False)
    src.open()
    junk = [
        can.Message(arbitration_id=BASE + 7, is_extended_id=True, is_fd=True, data=bytes(64)),  # reserved id
        can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"),  # another node
        can.Message(arbitration_id=BASE, is_extended_id=False, data=bytes(8)),  # same number, 11-bit
        can.Message(arbitration_id=0x40, is_error_frame=True),  # bus-off error frame
        can.Message(arbitration_id=BASE, is_extended_id=True, is_remote_frame=True, dlc=8),
        can.Message(arbitration_id=BASE, is_extended_id=True, is_fd=True, data=bytes(48)),  # short PHASE
        can.Message(arbitration_id=BASE + 1, is_extended_id=True, is_fd=True, data=bytes(8)),  # short ENCODER
    ]
    emu = CanEmulator(bus_cfg(channel), rec, BASE, speed=None)
    for m in junk:
        emu.inject(m)  # sent before the first frame ...
    emu.start()
    blocks = read_samples(src, 1000)
    for m in junk:
        emu.inject(m)  # ... and again mid-stream
    blocks += read_samples(src, n - sum(b.n for b in blocks))
    assert emu.wait(2)
    # the second batch may follow the last frame (an unpaced emulator can finish before it is
    # injected): read until the bus is quiet, then count
    while src.read(timeout=0.2) is not None:
        pass
    emu.stop()
    src.close()
    assert src.counters == {"unknown_id": 6, "error_frame": 2, "remote": 2, "malformed": 4}
    assert src.stats.bad_frames == 14 and src.stats.gaps == 0
    np.testing.assert_array_equal(joined(blocks, "i_abc"), q(rec.i_abc, cf.DEFAULT_I_LSB))
    assert_contiguous(blocks)


def test_id_filter_keeps_foreign_traffic_out(channel):
    rec = make_record(1000)
    src = CanSource("virtual", channel, "d2", BASE, rate_hz=FS, block_samples=1000)
    src.open()
    emu = CanEmulator(bus_cfg(channel), rec, BASE, speed=None)
    emu.inject(can.Message(arbitration_id=BASE + 16, is_extended_id=True, data=b"x"))  # next drive's block
    emu.inject(can.Message(arbitration_id=BASE + 3, is_extended_id=True, data=b"x"))  # ours, reserved
    emu.start()
    blocks = read_samples(src, 1000)
    emu.stop()
    src.close()
    assert sum(b.n for b in blocks) == 1000
    assert src.counters["unknown_id"] == 1


def test_dropped_frames_are_a_gap_with_exact_jump(channel):
    n = 4000
    rec = make_record(n)
    src = CanSource("virtual", channel, "d2", BASE, rate_hz=FS, block_samples=100_000)
    src.open()

    def chunks():  # runs in the emulator thread: the drop lands exactly after sample 1000
        yield Record(t=rec.t[:1000], v_abc=rec.v_abc[:, :1000], i_abc=rec.i_abc[:, :1000])
        emu.drop_frames(7)
        yield Record(t=rec.t[1000:], v_abc=rec.v_abc[:, 1000:], i_abc=rec.i_abc[:, 1000:])

    emu = CanEmulator(bus_cfg(channel), chunks(), BASE, rate_hz=FS, speed=None)  # bound before the thread runs
    emu.start()
    blocks = read_samples(src, n - 35)
    assert emu.wait(2)
    emu.stop()
    src.close()
    assert src.stats.gaps == 1 and sum(b.n for b in blocks) == n - 35
    jumps = [(a.first_sample + a.n, b.first_sample) for a, b in zip(blocks, blocks[1:])
             if b.first_sample != a.first_sample + a.n]
    assert jumps == [(1000, 1035)]
    for b in blocks:
        np.testing.assert_array_equal(b.v_abc, q(rec.v_abc[:, b.first_sample:b.first_sample + b.n], cf.DEFAULT_V_LSB))


def test_missing_encoder_frames_leave_theta_none(channel):
    rec = make_record(1000, encoder=True)
    src = CanSource("virtual", channel, "d2", BASE, rate_hz=FS, block_samples=500)
    src.open()
    with CanEmulator(bus_cfg(channel), rec, BASE, speed=None, encoder=False):
        blocks = read_samples(src, 1000)
    src.close()
    assert sum(b.n for b in blocks) == 1000 and all(b.theta_e is None and b.omega_e is None for b in blocks)


def test_bus_failure_reconnects_and_never_raises(channel):
    rec = make_record(12_500)  # 0.5 s, sent 2x faster than real time
    src = CanSource("virtual", channel, "d2", BASE, rate_hz=FS, block_samples=500, backoff_s=(0.01, 0.05))
    src.open()
    with CanEmulator(bus_cfg(channel), rec, BASE, speed=2.0) as emu:
        blocks = read_samples(src, 2000)

        def boom(timeout=None):
            raise can.CanOperationError("bus-off")

        src._bus.recv = boom
        while not emu.done.is_set() or blocks[-1] is not None:  # drain until the device is done
            blocks.append(src.read(0.2))
        blocks = [b for b in blocks if b is not None]
    src.close()
    s = src.stats
    assert s.reconnects == 1 and "bus-off" in s.last_error and s.gaps <= 1
    assert 10_000 < sum(b.n for b in blocks) <= 12_500
    assert blocks[-1].first_sample + blocks[-1].n == 12_500
    for b in blocks:
        np.testing.assert_array_equal(b.i_abc, q(rec.i_abc[:, b.first_sample:b.first_sample + b.n], cf.DEFAULT_I_LSB))


def test_open_failure_and_classic_can():
    src = CanSource("no_such_interface", "x", "d2", rate_hz=FS, backoff_s=(0.01, 0.02))
    with pytest.raises(ConnectionError):
        src.open()
    assert src.read(0.05) is None and "no_such_interface" in src.stats.last_error
    src.close()
    src.close()
    with pytest.raises(ValueError):
        CanSource("virtual", "x", "d2", fd=False)


def test_frames_on_the_wire_decode_with_the_exported_dbc(channel):
    rec = make_record(50, encoder=True)
    lay = cf.CanLayout("d2", BASE)
    db = cantools.database.load_string(cf.to_dbc(lay), database_format="dbc")
    with can.Bus(interface="virtual", channel=channel, fd=True, ignore_config=True) as sniffer:
        with CanEmulator(bus_cfg(channel), rec, layout=lay, speed=None) as emu:
            assert emu.wait(2)
        msgs = [sniffer.recv(1.0) for _ in range(20)]
    assert all(m is not None and m.is_fd and m.is_extended_id for m in msgs)
    assert [m.arbitration_id for m in msgs[:2]] == [lay.encoder_id, lay.phase_id]  # ENCODER first
    phase = [m for m in msgs if m.arbitration_id == lay.phase_id]
    for k, m in enumerate(phase):
        sig = db.decode_message(m.arbitration_id, m.data, force_extended_id=m.is_extended_id)
        assert sig["sample_index"] == 5 * k
        for j in range(5):
            assert sig[f"vb_{j}"] == pytest.approx(q(rec.v_abc[1, 5 * k + j], lay.v_lsb), abs=1e-9)
            assert sig[f"ic_{j}"] == pytest.approx(q(rec.i_abc[2, 5 * k + j], lay.i_lsb), abs=1e-9)
