"""Records: CSV / NPZ / TDMS round trips and every validation error (CONTRACT section 3)."""

import time
from pathlib import Path

import numpy as np
import pytest
from nptdms import ChannelObject, GroupObject, RootObject, TdmsWriter

from agent.errors import InputError
from agent.profile import load_profile
from agent.records import (CURRENTS, META_KEY, TIME_TOLERANCE, VOLTAGES, Record, load_record, save_record,
                           validate_record)

PROFILE = load_profile(Path(__file__).resolve().parents[1] / "config/profiles/rig_gear.toml")
FS = 25_000.0
FORMATS = ("csv", "npz", "tdms")


def make_record(n=500, fs=FS, optional=True, t0=0.0):
    rng = np.random.default_rng(0)
    t = t0 + np.arange(n) / fs
    theta = 2 * np.pi * 100.0 * t
    ph = theta - 2 * np.pi / 3 * np.arange(3)[:, None]
    return Record(t=t, v_abc=300 * np.cos(ph) + rng.normal(0, 1, (3, n)), i_abc=5 * np.sin(ph),
                  theta_e=np.mod(theta, 2 * np.pi) if optional else None,
                  omega_e=np.full(n, 2 * np.pi * 100.0) if optional else None,
                  meta={"condition": "healthy", "load_pct": 80.0, "seed": 3} if optional else {})


def write_csv(path, cols: dict):
    names = list(cols)
    rows = zip(*[np.atleast_1d(cols[k]) for k in names])
    path.write_text(",".join(names) + "\n" + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    return path


def columns(rec):
    return {k: v.copy() for k, v in rec.channels().items()}


def write_npz(path, cols: dict):
    np.savez(path, **cols)
    return path


def write_tdms(path, groups: dict, root=None, props=None):
    """groups: name -> {channel: data}; props: channel properties (default wf timing at FS)."""
    objs = [RootObject(root or {})]
    for g, chans in groups.items():
        objs.append(GroupObject(g, {}))
        for k, x in chans.items():
            p = {"wf_increment": 1 / FS, "wf_start_offset": 0.0} if props is None else props.get(k, {})
            objs.append(ChannelObject(g, k, np.asarray(x), properties=p))
    with TdmsWriter(path) as w:
        w.write_segment(objs)
    return path


def signals(rec):
    return {k: v for k, v in columns(rec).items() if k != "t"}


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("optional", [True, False])
def test_round_trip(tmp_path, fmt, optional):
    rec = make_record(optional=optional, t0=1.5)
    back = load_record(save_record(rec, tmp_path / f"r.{fmt}"), PROFILE, min_samples=rec.n)
    assert back.source == str(tmp_path / f"r.{fmt}")
    for k, x in rec.channels().items():
        np.testing.assert_allclose(back.channels()[k], x, rtol=1e-9, atol=1e-9 * np.abs(x).max(), err_msg=k)
    assert set(back.channels()) == set(rec.channels())
    assert back.v_abc.shape == back.i_abc.shape == (3, rec.n)
    assert back.rate_hz == pytest.approx(FS, rel=1e-9)
    assert back.meta == (rec.meta if fmt != "csv" else {})


def test_csv_column_order_free_and_unknown_columns_ignored(tmp_path):
    rec = make_record(n=20, optional=False)
    cols = columns(rec)
    order = ["ic", "note", "va", "t", "extra", "ib", "vc", "ia", "vb"]
    cols.update(note=["x"] * 20, extra=np.arange(20))
    back = load_record(write_csv(tmp_path / "r.csv", {k: cols[k] for k in order}))
    np.testing.assert_array_equal(back.i_abc, rec.i_abc)
    np.testing.assert_array_equal(back.t, rec.t)
    assert back.theta_e is None and back.omega_e is None


def test_csv_utf8_bom_and_spaces_in_header(tmp_path):
    rec = make_record(n=10, optional=False)
    path = save_record(rec, tmp_path / "r.csv")
    text = path.read_text().splitlines()
    path.write_text("\ufeff" + " , ".join(text[0].split(",")) + "\n" + "\n".join(text[1:]) + "\n", encoding="utf-8")
    np.testing.assert_allclose(load_record(path).v_abc, rec.v_abc, rtol=1e-9)


def test_csv_loads_100k_rows_fast(tmp_path):
    rec = make_record(n=100_000)
    path = save_record(rec, tmp_path / "big.csv")
    start = time.perf_counter()
    back = load_record(path, PROFILE)
    assert time.perf_counter() - start < 1.0
    assert back.n == 100_000


def test_tdms_group_selection(tmp_path):
    chans = signals(make_record(n=50))
    other = {"x": np.zeros(3)}
    # named by the root property
    path = write_tdms(tmp_path / "a.tdms", {"junk": other, "data": chans, "copy": chans}, root={"record_group": "data"})
    assert load_record(path).n == 50
    # the only group holding the required channels
    assert load_record(write_tdms(tmp_path / "b.tdms", {"junk": other, "data": chans})).n == 50
    with pytest.raises(InputError, match="cannot tell which of 2 groups.*record_group"):
        load_record(write_tdms(tmp_path / "c.tdms", {"d1": chans, "d2": chans}))
    with pytest.raises(InputError, match="group 'nope' named by root property"):
        load_record(write_tdms(tmp_path / "d.tdms", {"data": chans}, root={"record_group": "nope"}))


def test_tdms_time_from_wf_properties_or_t_channel(tmp_path):
    chans = signals(make_record(n=50))
    props = {k: {"wf_increment": 1 / FS, "wf_start_offset": 2.0} for k in chans}
    back = load_record(write_tdms(tmp_path / "a.tdms", {"g": chans}, props=props), PROFILE)
    np.testing.assert_allclose(back.t, 2.0 + np.arange(50) / FS)
    t = 1.0 + np.arange(50) / FS  # no wf_* properties: fall back to a 't' channel
    back = load_record(write_tdms(tmp_path / "b.tdms", {"g": {"t": t, **chans}}, props={}), PROFILE)
    np.testing.assert_array_equal(back.t, t)


# ------------------------------------------------------------------------------ errors


def raises(match):
    return pytest.raises(InputError, match=match)


@pytest.mark.parametrize("op", ["load", "save"])
def test_unknown_extension(tmp_path, op):
    path = tmp_path / "r.xlsx"
    path.write_text("t,va\n")
    with raises(r"r\.xlsx: unknown record format '\.xlsx' \(expected \.csv, \.npz, \.tdms\)"):
        load_record(path) if op == "load" else save_record(make_record(), path)


@pytest.mark.parametrize("fmt", FORMATS)
def test_missing_file(tmp_path, fmt):
    with raises(f"nope.{fmt}: no such record file"):
        load_record(tmp_path / f"nope.{fmt}")


def test_save_creates_folders_and_reports_unwritable_ones(tmp_path):
    assert load_record(save_record(make_record(), tmp_path / "new/dir/r.npz")).n == 500
    (tmp_path / "file").write_text("")
    with raises("file/dir/r.npz: cannot write record"):  # a file where a folder should be
        save_record(make_record(), tmp_path / "file/dir/r.npz")


@pytest.mark.parametrize("fmt, content, match", [
    ("csv", b"t,va\xff\xfe\n1,2\n", "cannot read CSV: not UTF-8"),
    ("npz", b"PK\x03\x04 this is not a zip archive", "cannot read NPZ"),
    ("npz", b"\x00" * 100, "cannot read NPZ"),
    ("tdms", b"garbage " * 20, "cannot read TDMS"),
])
def test_corrupt_file(tmp_path, fmt, content, match):
    path = tmp_path / f"r.{fmt}"
    path.write_bytes(content)
    with raises(match):
        load_record(path)


def test_truncated_npz(tmp_path):
    path = save_record(make_record(), tmp_path / "r.npz")
    path.write_bytes(path.read_bytes()[:2000])
    with raises("cannot read NPZ"):
        load_record(path)


def test_npz_bad_meta(tmp_path):
    cols = columns(make_record(n=10))
    with raises(f"'{META_KEY}' is not a JSON string"):
        load_record(write_npz(tmp_path / "r.npz", {**cols, META_KEY: np.array("{oops")}))


@pytest.mark.parametrize("fmt", FORMATS)
def test_missing_required_column(tmp_path, fmt):
    cols = columns(make_record(n=10, optional=False))
    del cols["ib"]
    path = tmp_path / f"r.{fmt}"
    if fmt == "csv":
        write_csv(path, cols)
    elif fmt == "npz":
        write_npz(path, cols)
    else:
        write_tdms(path, {"g": {k: v for k, v in cols.items() if k != "t"}})
    with raises(r"missing required column 'ib' \(found: "):
        load_record(path)


def test_missing_several_columns_and_empty_csv(tmp_path):
    with raises(r"missing required columns 't', 'va', 'vb', 'vc', 'ia', 'ib', 'ic' \(found: U1, I1\)"):
        load_record(write_csv(tmp_path / "r.csv", {"U1": [1.0], "I1": [2.0]}))
    with raises(r"missing required columns 't', 'vb', 'vc', 'ib', 'ic' \(found: Va, Ia\)"):  # any case
        load_record(write_csv(tmp_path / "r.csv", {"Va": [1.0], "Ia": [2.0]}))
    (tmp_path / "e.csv").write_text("")
    with raises(r"missing required columns .*\(found: none\)"):
        load_record(tmp_path / "e.csv")


def test_duplicate_csv_column(tmp_path):
    (tmp_path / "r.csv").write_text("t,va,va\n0,1,2\n")
    with raises("duplicate column 'va'"):
        load_record(tmp_path / "r.csv")


def test_non_numeric_csv_value(tmp_path):
    cols = columns(make_record(n=10))
    cols["vb"] = cols["vb"].astype(object)
    cols["vb"][7] = "1.2V"
    with raises(r"non-numeric value '1\.2V' in column 'vb' at sample 7"):
        load_record(write_csv(tmp_path / "r.csv", cols))
    cols["vb"][7] = ""
    with raises(r"non-numeric value '' in column 'vb' at sample 7"):
        load_record(write_csv(tmp_path / "r.csv", cols))


def test_ragged_csv_row(tmp_path):
    path = save_record(make_record(n=10), tmp_path / "r.csv")
    lines = path.read_text().splitlines()
    lines[4] = ",".join(lines[4].split(",")[:3])
    path.write_text("\n".join(lines) + "\n")
    with raises("sample 3 has only 3 fields, header has 9"):
        load_record(path)


@pytest.mark.parametrize("fmt", ["npz", "tdms"])
def test_non_numeric_channel(tmp_path, fmt):
    cols = columns(make_record(n=3, optional=False))
    cols["ic"] = np.array(["a", "b", "c"])
    path = tmp_path / f"r.{fmt}"
    write_npz(path, cols) if fmt == "npz" else write_tdms(path, {"g": {k: v for k, v in cols.items() if k != "t"}})
    with raises("column 'ic' is not numeric"):
        load_record(path)


def test_npz_channel_not_1d(tmp_path):
    cols = columns(make_record(n=10))
    cols["va"] = np.zeros((2, 5))
    with raises(r"column 'va' must be 1-D, has shape \(2, 5\)"):
        load_record(write_npz(tmp_path / "r.npz", cols))


@pytest.mark.parametrize("fmt", ["csv", "npz"])
@pytest.mark.parametrize("bad, word", [(np.nan, "NaN"), (np.inf, "inf"), (-np.inf, "inf")])
def test_nan_inf(tmp_path, fmt, bad, word):
    rec = make_record(n=30)
    rec.i_abc[2, 11] = bad
    rec.i_abc[2, 20] = bad
    path = save_record(rec, tmp_path / f"r.{fmt}")
    with raises(f"{word} in column 'ic' at sample 11"):
        load_record(path)


def test_nan_in_optional_channel_tdms(tmp_path):
    rec = make_record(n=30)
    rec.omega_e[5] = np.nan
    with raises("NaN in column 'omega_e' at sample 5"):
        load_record(save_record(rec, tmp_path / "r.tdms"))


@pytest.mark.parametrize("fmt", ["csv", "npz"])
def test_non_uniform_time(tmp_path, fmt):
    rec = make_record(n=100)
    rec.t[40:] += 0.01 / FS  # one step 1 % longer
    with raises(r"non-uniform time: step 4\.04e-05 s at sample 40, expected .* \(relative tolerance 1e-06\)"):
        load_record(save_record(rec, tmp_path / f"r.{fmt}"))


def test_time_jitter_within_tolerance_is_accepted():
    rec = make_record(n=100)
    rec.t[50] += 0.2 * TIME_TOLERANCE / FS
    validate_record(rec, PROFILE)


@pytest.mark.parametrize("fmt", ["csv", "npz"])
def test_non_increasing_time(tmp_path, fmt):
    rec = make_record(n=100)
    rec.t[60] = rec.t[59]
    with raises(r"time is not increasing at sample 60 \(t = [0-9.e-]+ s after [0-9.e-]+ s\)"):  # plain numbers
        load_record(save_record(rec, tmp_path / f"r.{fmt}"))
    rec.t[::-1] = rec.t.copy()
    with raises("time is not increasing at sample 1"):
        load_record(save_record(rec, tmp_path / f"r.{fmt}"))


@pytest.mark.parametrize("fmt", FORMATS)
def test_sample_rate_disagrees_with_profile(tmp_path, fmt):
    path = save_record(make_record(fs=20_000.0), tmp_path / f"r.{fmt}")
    load_record(path)  # no profile: no check
    with raises(r"sample rate 20000 Hz disagrees with the profile's sampling\.rate_hz = 25000 Hz"):
        load_record(path, PROFILE)


def test_sample_rate_tolerance():
    validate_record(make_record(fs=FS * (1 + 0.5e-6)), PROFILE)
    with raises("disagrees"):
        validate_record(make_record(fs=FS * (1 + 2e-6)), PROFILE)


@pytest.mark.parametrize("fmt", FORMATS)
def test_too_short(tmp_path, fmt):
    path = save_record(make_record(n=300), tmp_path / f"r.{fmt}")
    assert load_record(path, min_samples=300).n == 300
    with raises(f"r.{fmt}: too short for the window: 300 samples, need 1000"):
        load_record(path, min_samples=1000)


@pytest.mark.parametrize("n, match", [(0, "no samples: the file has no data rows"),
                                      (1, "need at least 2 samples to define a sample rate, got 1")])
def test_fewer_than_two_samples(tmp_path, n, match):
    path = tmp_path / "r.csv"
    path.write_text("t,va,vb,vc,ia,ib,ic\n" + "0,1,2,3,4,5,6\n" * n)
    with raises(match):
        load_record(path)


def test_mismatched_lengths_npz(tmp_path):
    cols = columns(make_record(n=10))
    cols["theta_e"] = cols["theta_e"][:9]
    with raises("column 'theta_e' has 9 samples, 't' has 10"):
        load_record(write_npz(tmp_path / "r.npz", cols))


def test_mismatched_lengths_tdms(tmp_path):
    chans = signals(make_record(n=10))
    chans["ia"] = chans["ia"][:7]
    with raises("column 'ia' has 7 samples, 't' has 10"):
        load_record(write_tdms(tmp_path / "r.tdms", {"g": chans}))


def test_tdms_missing_or_inconsistent_wf_increment(tmp_path):
    chans = signals(make_record(n=10, optional=False))
    props = {k: {"wf_increment": 1 / FS} for k in chans}
    del props["vc"]["wf_increment"]
    with raises("channel 'vc' has no wf_increment property and there is no 't' channel"):
        load_record(write_tdms(tmp_path / "a.tdms", {"g": chans}, props=props))
    props["vc"]["wf_increment"] = 1.01 / FS
    with raises("channel 'vc' has wf_increment 4.04e-05 s, 'va' has 4e-05 s"):
        load_record(write_tdms(tmp_path / "b.tdms", {"g": chans}, props=props))


def test_save_tdms_needs_uniform_time(tmp_path):
    rec = make_record(n=20)
    rec.t[10:] += 0.5 / FS
    with raises("non-uniform time"):
        save_record(rec, tmp_path / "r.tdms")


def test_record_properties():
    rec = make_record(n=2500)
    assert rec.n == 2500 and rec.rate_hz == pytest.approx(FS) and rec.duration_s == pytest.approx(0.1)
    assert list(rec.channels()) == ["t", *VOLTAGES, *CURRENTS, "theta_e", "omega_e"]


# --- streaming -------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", [".csv", ".npz", ".tdms"])
@pytest.mark.parametrize("optional", [True, False])
def test_streamed_chunks_equal_the_whole_record(tmp_path, fmt, optional):
    from agent.records import stream_record

    rec = make_record(n=1003, optional=optional)
    path = save_record(rec, tmp_path / f"r{fmt}")
    whole = load_record(path)
    chunks = list(stream_record(path, chunk_samples=100))
    assert [c.n for c in chunks] == [100] * 10 + [3]
    for name, x in whole.channels().items():
        np.testing.assert_array_equal(np.concatenate([c.channels()[name] for c in chunks]), x)
    assert all(c.meta == whole.meta for c in chunks)


@pytest.mark.parametrize("fmt", [".csv", ".npz"])
def test_stream_raises_when_the_bad_chunk_is_reached(tmp_path, fmt):
    from agent.records import stream_record

    rec = make_record(n=1000)
    rec.i_abc[1, 750] = np.nan
    cols = columns(rec)
    path = tmp_path / f"r{fmt}"
    (write_csv if fmt == ".csv" else write_npz)(path, cols)
    chunks = stream_record(path, chunk_samples=250)
    assert [next(chunks).n for _ in range(3)] == [250, 250, 250]  # read before the bad sample
    with raises("NaN in column 'ib' at sample 0"):  # sample 750 is the 4th chunk's first
        next(chunks)


def test_stream_checks_the_step_across_chunks(tmp_path):
    from agent.records import stream_record

    rec = make_record(n=400)
    cols = columns(rec)
    cols["t"] = cols["t"].copy()
    cols["t"][200:] += 0.5 / FS  # a jump exactly at a chunk boundary
    path = tmp_path / "r.csv"
    write_csv(path, cols)
    with raises("non-uniform time"):
        list(stream_record(path, chunk_samples=200))
