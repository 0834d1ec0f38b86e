"""The drive's capture header is checked like any other frame: an unknown layout, a count beyond
capacity, a non-finite or non-positive scale or rate, or a rate that disagrees with the profile is
refused and counted with its reason; 10^5 mutated headers let none through that breaks the layout."""

import time

import numpy as np
import pytest

from firmware_if import modbus_capture as cap
from tests.test_modbus_drive import FS, generator, tcp_source

pytestmark = pytest.mark.timeout(120)
COUNT = 1000
GOOD = cap.CaptureHeader(status=cap.Status.READY, seq=7, count=COUNT, rate_hz=FS, first_sample=123, capacity=100_000,
                         scales=(0.02, 0.02, 0.02, 0.001, 0.001, 0.001))


def _layout_holds(h: cap.CaptureHeader) -> bool:
    """The layout an accepted header promises, checked through what the source does with it: the
    read plan covers exactly the samples asked for inside the capacity, full-scale raw values turn
    into finite phase samples of the raw value's sign, at the profile's rate."""
    plan = cap.read_plan(h.count, cap.CHUNK_REGS, max(h.window_samples, 1))
    regs = sum(n for _, chunks in plan for _, n in chunks)
    raw = np.array([[32767, -32768]] * cap.N_CHANNELS, dtype=np.int16)
    phys = cap.to_physical(raw, h.scales)
    return (h.version == cap.LAYOUT_VERSION and h.n_channels == cap.N_CHANNELS and regs == cap.N_CHANNELS * COUNT
            and h.count <= h.capacity and np.all(np.isfinite(phys)) and np.all(phys[:, 0] > 0)
            and np.all(phys[:, 1] < 0) and abs(h.rate_hz - FS) <= 1e-6 * FS)


def test_the_good_header_is_accepted():
    assert GOOD.problem(COUNT, FS) is None and _layout_holds(GOOD)


def test_ten_to_the_five_mutated_headers_accept_none_that_breaks_the_layout():
    rng = np.random.default_rng(1)
    good = np.array(GOOD.registers(), dtype=np.int64)
    refused, accepted_ok = {}, 0
    special = [0x7FC0, 0xFF80, 0x7F80, 0x8000, 0xBF80, 0x0000, 0xFFFF]  # float32 high words: NaN, -inf, inf, -0, -1
    for _ in range(100_000):
        regs = good.copy()
        for j in rng.choice(cap.HEADER_REGS, size=rng.integers(1, 4), replace=False):
            regs[j] = special[rng.integers(len(special))] if rng.random() < 0.3 else rng.integers(0, 65536)
        h = cap.CaptureHeader.from_registers(regs.tolist())
        why = h.problem(COUNT, FS)
        if why is None:
            assert _layout_holds(h), h
            accepted_ok += 1
        else:
            refused[why[0]] = refused.get(why[0], 0) + 1
    # every kind of damage occurred and was refused; harmless mutations (status, seq, ...) pass
    assert {"LAYOUT_VERSION", "CHANNELS", "COUNT", "CAPACITY", "RATE", "SCALE_VA", "SCALE_IC"} <= set(refused)
    assert accepted_ok > 1000


@pytest.mark.parametrize("scales, source_kw, register, text", [
    ((0.02, 0.02, 0.02, 0.001, -0.001, 0.001), {}, "SCALE_IB", "SCALE_IB = -0.001 is not a positive finite scale"),
    ((0.02, float("nan"), 0.02, 0.001, 0.001, 0.001), {}, "SCALE_VB", "SCALE_VB = nan is not a positive"),
    (None, {"rate_hz": 2 * FS}, "RATE", "RATE = 25000 Hz disagrees with the profile's sampling.rate_hz = 50000 Hz"),
])
@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # the drive quantises with its broken scale
def test_the_source_refuses_a_bad_header_and_counts_why(scales, source_kw, register, text):
    from protocols.modbus_drive import DriveModbusEmulator

    with DriveModbusEmulator(generator, rate_hz=FS, capture_time_s=0.0) as emu:
        if scales is not None:  # a drive that writes a broken scale (the emulator itself refuses one)
            emu.scales = tuple(float(x) for x in cap.float32_round(scales))
        with tcp_source(emu, samples=COUNT, **source_kw) as src:
            t_end = time.monotonic() + 5.0
            while time.monotonic() < t_end and not src.stats.bad_headers:
                assert src.read(0.2) is None  # never a block from a header that breaks the layout
            assert src.stats.bad_headers[register] >= 1 and src.stats.bad_frames >= 1
            assert text in src.stats.last_error and src.stats.blocks == 0
