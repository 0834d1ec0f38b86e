"""Register maps defined once in code: the PLC map (CONTRACT section 6) and the drive's capture
buffer; generated docs are current; encoders agree with an independent reference."""

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_if import c_header, modbus_capture as cap, plc_registers as plc
from firmware_if.modbus_map import RegisterDef, decode_value, encode_value, legacy
from protocols.base import QUALITY_CODES, STATE_CODES

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------- docs


def test_committed_registers_md_is_generated_text():
    assert (ROOT / "docs/registers.md").read_text() == plc.render_markdown(), \
        "docs/registers.md is stale: python -m firmware_if.plc_registers --write docs/registers.md"


def test_committed_capture_md_is_generated_text():
    assert (ROOT / "docs/modbus_capture.md").read_text() == cap.render_markdown(), \
        "docs/modbus_capture.md is stale: python -m firmware_if.modbus_capture --write docs/modbus_capture.md"


def test_check_command(tmp_path, capsys):
    assert plc.main(["--check", str(ROOT / "docs/registers.md")]) == 0
    stale = tmp_path / "r.md"
    stale.write_text("old")
    assert plc.main(["--check", str(stale)]) == 1
    out = tmp_path / "new.md"
    assert plc.main(["--write", str(out)]) == 0 and out.read_text() == plc.render_markdown()


def test_docs_show_wire_and_legacy_addresses():
    md = plc.render_markdown()
    assert "| `HEARTBEAT` | IR | 1 | 30002 |" in md
    assert "| +0 | `STATE` | IR | 16 | 30017 |" in md
    assert "| +1 | `RELEARN` | HR | 17 | 40018 |" in md
    assert "| 1 | 32..47 | 30033..30048 | 40033..40048 |" in md


# ---------------------------------------------------------------------------------- contract anchors


def test_contract_anchors():
    assert plc.address("MAP_VERSION") == 0
    assert plc.address("HEARTBEAT") == 1
    assert plc.address("DRIVE_COUNT") == 2
    for i in (0, 1, 7, 255):
        assert plc.address("STATE", i) == 16 + 16 * i
        assert plc.address("QUALITY", i) == 16 + 16 * i + 1
    assert plc.DEVICE_ID == 1
    assert plc.STATE_CODES == STATE_CODES == {"normal": 0, "caution": 1, "warning": 2}
    assert plc.QUALITY_CODES == QUALITY_CODES == {"good": 0, "no_model": 1, "learning": 2, "stale": 3,
                                                  "bad_input": 4}


def test_plc_layout():
    for d in plc.REGISTERS:
        assert d.end <= (plc.GLOBAL_REGS if not d.block else plc.DRIVE_STRIDE), d.name
        if d.words == 2:
            assert (plc.drive_base(3) + d.address if d.block else d.address) % 2 == 0
    assert {d.name for d in plc.DRIVE_HR} == set(plc.COMMANDS)
    assert all(d.access == "RW" for d in plc.DRIVE_HR)
    assert all(d.access == "R" for d in plc.REGISTERS if d.table == "IR")
    assert plc.command_addresses(2) == {16: (0, "acknowledge"), 17: (0, "relearn"),
                                        32: (1, "acknowledge"), 33: (1, "relearn")}
    with pytest.raises(ValueError):
        plc.address("STATE")
    with pytest.raises(ValueError):
        plc.drive_base(plc.MAX_DRIVES)


def test_capture_layout():
    assert cap.SAMPLE_BASE + cap.WINDOW_REGS <= 65536
    assert cap.CHUNK_REGS % cap.N_CHANNELS == 0 and cap.CHUNK_REGS <= cap.MAX_READ_REGS
    assert max(d.end for d in cap.HEADER_DEFS) <= cap.HEADER_REGS
    assert cap.HR_WRITABLE == {0, 1, 2, 4, 5}
    assert cap.CHANNELS == ("va", "vb", "vc", "ia", "ib", "ic")


def test_register_def_rejects_bad_rows():
    with pytest.raises(ValueError):
        RegisterDef("X", "IR", 3, "UINT32")  # odd address
    with pytest.raises(ValueError):
        RegisterDef("X", "CO", 0)
    with pytest.raises(ValueError):
        RegisterDef("X", "IR", 0, "INT64")


def test_legacy_notation():
    assert legacy("IR", 0) == "30001" and legacy("HR", 0) == "40001"
    assert legacy("IR", 9998) == "39999"
    assert legacy("IR", 9999) == "310000"  # 6-digit form above 9998
    assert legacy("HR", 1024, six_digit=True) == "401025"


# ---------------------------------------------------------------------------------- encoding


def ref_encode(kind, raw):
    """Independent reference: big-endian bytes -> 16-bit words."""
    code = {"UINT16": ">H", "INT16": ">h", "UINT32": ">I", "FLOAT32": ">f"}[kind]
    b = struct.pack(code, raw)
    return [int.from_bytes(b[k:k + 2], "big") for k in range(0, len(b), 2)]


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 0xFFFF))
def test_uint16_roundtrip(raw):
    d = RegisterDef("X", "IR", 0, "UINT16")
    assert encode_value(d, raw) == ref_encode("UINT16", raw)
    assert decode_value(d, encode_value(d, raw)) == raw


@settings(max_examples=200, deadline=None)
@given(st.integers(-0x7FFF, 0x7FFF))
def test_int16_scaled_roundtrip(raw):
    d = RegisterDef("LOAD", "IR", 0, "INT16", scale=0.1, na=-0x8000)
    regs = encode_value(d, raw * 0.1)
    assert regs == ref_encode("INT16", raw)
    assert decode_value(d, regs) == pytest.approx(raw * 0.1)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 0xFFFFFFFF))
def test_uint32_word_order_abcd(raw):
    d = RegisterDef("X", "IR", 0, "UINT32")
    assert encode_value(d, raw) == ref_encode("UINT32", raw) == [raw >> 16, raw & 0xFFFF]
    assert decode_value(d, encode_value(d, raw)) == raw


@settings(max_examples=200, deadline=None)
@given(st.floats(width=32, allow_nan=False, allow_infinity=False))
def test_float32_roundtrip(x):
    d = RegisterDef("X", "IR", 0, "FLOAT32")
    assert encode_value(d, x) == ref_encode("FLOAT32", x)
    assert decode_value(d, encode_value(d, x)) == x


def test_saturation_and_na():
    fe = plc.BY_NAME["FE"]
    assert encode_value(fe, 50.0) == [5000]
    assert encode_value(fe, 1e9) == [0xFFFE]  # saturates below the n/a sentinel
    assert encode_value(fe, -3.0) == [0]
    assert encode_value(fe, math.nan) == [0xFFFF] and math.isnan(decode_value(fe, [0xFFFF]))
    load = plc.BY_NAME["LOAD"]
    assert encode_value(load, -12.3) == [(-123) & 0xFFFF]
    assert encode_value(load, -1e9) == [(-0x7FFF) & 0xFFFF]
    assert encode_value(load, math.nan) == [0x8000]
    with pytest.raises(ValueError):
        encode_value(plc.BY_NAME["STATE"], math.nan)


def test_drive_block_encode_decode():
    vals = {"STATE": 2, "QUALITY": 0, "FE": 49.99, "LOAD": -5.5, "UPDATE_TIME": 1_700_000_123,
            "WINDOW": 70_000, "PEAK_FREQ": 123.4, "PEAK_RATIO": 2.5, "MODEL_ID": 0xBEEF}
    regs = plc.encode_drive(vals)
    assert len(regs) == 16
    assert regs[0] == 2 and regs[5] == 4999 and regs[6] == (-55) & 0xFFFF
    assert regs[8:10] == [1_700_000_123 >> 16, 1_700_000_123 & 0xFFFF]
    assert regs[10:12] == [1, 70_000 - 65536] and regs[12] == 1234 and regs[13] == 250
    back = plc.decode_drive(regs)
    assert back["FE"] == pytest.approx(49.99) and back["WINDOW"] == 70_000


def test_model_id_crc16_modbus():
    assert plc.crc16_modbus(b"123456789") == 0x4B37  # the CRC catalogue's check value
    assert plc.model_id("") == 0 and plc.model_id("gear80") != 0


# ---------------------------------------------------------------------------------- capture helpers


@settings(max_examples=50, deadline=None)
@given(st.integers(1, 300), st.integers(0, 2**31 - 1))
def test_interleave_roundtrip(n, seed):
    raw = np.random.default_rng(seed).integers(-32768, 32768, size=(6, n)).astype(np.int16)
    flat = cap.interleave(raw)
    assert flat.dtype == np.uint16 and flat.size == 6 * n
    k, c = n // 2, 4
    assert flat[6 * k + c] == np.uint16(raw[c, k].astype(np.int64) & 0xFFFF)
    assert np.array_equal(cap.deinterleave(flat.tolist(), n), raw)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 3 * cap.WINDOW_SAMPLES), st.integers(20, 125))
def test_read_plan_covers_capture(count, chunk):
    plan = cap.read_plan(count, chunk)
    nxt = 0  # next register of the capture's flat image
    for start, chunks in plan:
        assert start % cap.WINDOW_SAMPLES == 0
        for addr, n in chunks:
            assert 1 <= n <= chunk <= 125
            assert cap.SAMPLE_BASE <= addr and addr + n <= cap.SAMPLE_BASE + cap.WINDOW_REGS
            assert 6 * start + addr - cap.SAMPLE_BASE == nxt
            nxt += n
    assert nxt == 6 * count


def test_read_plan_small_chunks_and_limits():
    plan = cap.read_plan(25, 1)
    assert plan[0][1][:2] == [(cap.SAMPLE_BASE, 1), (cap.SAMPLE_BASE + 1, 1)] and len(plan[0][1]) == 150
    with pytest.raises(ValueError):
        cap.read_plan(10, 126)


def test_header_roundtrip():
    h = cap.CaptureHeader(status=cap.Status.READY, error=0, seq=65535, count=123_456, rate_hz=25_000.0,
                          first_sample=2**32 - 5, capacity=1_000_000, window_start=20_000,
                          scales=(0.05, 0.05, 0.05, 0.001, 0.001, 0.001))
    regs = h.registers()
    assert len(regs) == cap.HEADER_REGS and regs[1] == 3 and regs[4:6] == [1, 123_456 - 65536]
    back = cap.CaptureHeader.from_registers(regs)
    assert back.scales == tuple(float(np.float32(s)) for s in h.scales)
    assert (back.count, back.first_sample, back.rate_hz, back.seq) == (123_456, 2**32 - 5, 25_000.0, 65535)


def test_quantize_and_scale():
    # scales exact in float32, so the expected raw values are exact too
    x = np.array([[0.0, 0.25, 0.75, 1e6, -1e6]] * 3 + [[0.0, 0.125, -0.375, 1.0, -1.0]] * 3)
    s = (0.5,) * 3 + (0.25,) * 3
    raw = cap.quantize(x, s)
    assert raw.dtype == np.int16
    assert raw[0].tolist() == [0, 0, 2, 32767, -32768]  # ties to even, saturation
    assert raw[3].tolist() == [0, 0, -2, 4, -4]
    s2 = (0.05,) * 3 + (0.001,) * 3  # not exact in float32: the drive's FLOAT32 value is used
    phys = cap.to_physical(raw, s2)
    assert np.array_equal(phys[0], raw[0] * np.float64(np.float32(0.05)))
    assert np.array_equal(phys[5], raw[5] * np.float64(np.float32(0.001)))


# ---------------------------------------------------------------------------------- C header


def test_c_header_registration():
    text = c_header.render_header()
    assert "#define PMSM_PLC_DRV_IR_STATE 0u" in text
    assert "#define PMSM_PLC_DRIVE_BASE 16u" in text
    assert "#define PMSM_MBCAP_SAMPLE_BASE 1024u" in text
    assert "PMSM_MBCAP_SAMPLE_REG(k, c)" in text
    assert plc.c_defines()["PMSM_PLC_DRV_IR_QUALITY"] == 1
    assert cap.c_defines()["PMSM_MBCAP_STATUS_READY"] == 3
