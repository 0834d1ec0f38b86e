"""Records: three-phase voltage and current samples, measured or simulated (CONTRACT section 3).

A record is read from CSV, NPZ or TDMS into a :class:`Record`; every problem a user can fix
(missing column, non-uniform time, NaN, sample rate that disagrees with the profile, too few
samples) raises :class:`agent.errors.InputError` naming the file and the problem.

Formats (channel names ``t, va, vb, vc, ia, ib, ic`` and optional ``theta_e, omega_e``):

* ``.csv``: header row, column order free, unknown columns ignored; as spreadsheets export it:
  the separator (comma, semicolon, tab or bar) read off the header, a decimal comma where the
  separator is not a comma, names in any case with a stated unit (``ia [A]``, ``IA (mA)``,
  ``t_ms``) converted to the record's (:data:`UNIT_FACTORS`), a unit of another quantity refused.
* ``.npz``: one 1-D array per channel; ``meta`` as a JSON string under ``__meta__``.
* ``.tdms``: one channel per name in one group (the only group, the group named by the root
  property ``record_group``, or the only group holding the required channels); time from the
  channels' ``wf_increment`` / ``wf_start_offset`` (a ``t`` channel is used only when they are
  missing); ``meta`` as group properties.
"""

from __future__ import annotations

import csv
import json
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path

import numpy as np

from agent.errors import InputError

#: Required channels, in the order of ``Record`` arrays.
VOLTAGES = ("va", "vb", "vc")
CURRENTS = ("ia", "ib", "ic")
OPTIONAL = ("theta_e", "omega_e")
REQUIRED = ("t", *VOLTAGES, *CURRENTS)
#: Relative tolerance on the uniformity of the time column.
TIME_TOLERANCE = 1e-6
#: Relative tolerance between the record's sample rate and the profile's ``sampling.rate_hz``.
RATE_TOLERANCE = 1e-6
FORMATS = (".csv", ".npz", ".tdms")
UNITS = {"t": "s", **dict.fromkeys(VOLTAGES, "V"), **dict.fromkeys(CURRENTS, "A"),
         "theta_e": "rad", "omega_e": "rad/s"}
META_KEY = "__meta__"  #: NPZ key of the JSON-encoded ``meta``
GROUP_PROPERTY = "record_group"  #: TDMS root property naming the record's group
TDMS_GROUP = "record"  #: group name used when writing TDMS


@dataclass
class Record:
    """One record.

    ``v_abc`` and ``i_abc`` are ``(3, N)`` arrays in V and A (phase-to-neutral); ``theta_e``
    (rad) and ``omega_e`` (rad/s) are the electrical rotor angle and speed when the drive
    provides them, else ``None``. ``meta`` holds free-form string/number annotations
    (simulator condition, load, seed...) that round-trip through NPZ and TDMS.
    """

    t: np.ndarray
    v_abc: np.ndarray
    i_abc: np.ndarray
    theta_e: np.ndarray | None = None
    omega_e: np.ndarray | None = None
    source: str = "<memory>"
    meta: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.t.size)

    @property
    def rate_hz(self) -> float:
        """Sample rate from the time column, Hz."""
        return (self.n - 1) / float(self.t[-1] - self.t[0]) if self.n > 1 else float("nan")

    @property
    def duration_s(self) -> float:
        return self.n / self.rate_hz

    def channels(self) -> dict[str, np.ndarray]:
        """Name -> ``(N,)`` array for ``t``, the six phase channels and the optional ones present."""
        out = {"t": self.t, **dict(zip(VOLTAGES, self.v_abc)), **dict(zip(CURRENTS, self.i_abc))}
        out.update({k: getattr(self, k) for k in OPTIONAL if getattr(self, k) is not None})
        return out


# ---------------------------------------------------------------------------------- public API


def load_record(path: str | Path, profile=None, min_samples: int = 0) -> Record:
    """Read and validate a ``.csv``, ``.npz`` or ``.tdms`` record (see :func:`validate_record`)."""
    path = Path(path)
    src = str(path)
    reader = _READERS[_suffix(path)]
    _check_file(path)
    columns, meta, found = reader(path, src)
    return validate_record(_from_columns(columns, src, meta, found), profile, min_samples)


def stream_record(path: str | Path, profile=None, chunk_samples: int = 25_000) -> Iterator[Record]:
    """Read a record in consecutive chunks of ``chunk_samples`` (the last one shorter), each
    validated as :func:`validate_record` validates a whole record, plus the time step across chunk
    boundaries; memory stays at one chunk whatever the file's length. Same formats and errors as
    :func:`load_record` (an error in a later chunk is raised when that chunk is reached)."""
    path = Path(path)
    src = str(path)
    opener = _STREAMERS[_suffix(path)]
    _check_file(path)
    last_t, step = None, None
    for columns, meta, found in opener(path, src, max(2, int(chunk_samples))):
        chunk = validate_record(_from_columns(columns, src, meta, found), profile)
        if last_t is not None:
            gap = float(chunk.t[0] - last_t)
            if abs(gap - step) > TIME_TOLERANCE * step:
                raise InputError(f"non-uniform time: step {gap:.9g} s before t = {float(chunk.t[0]):.9g} s, expected {step:.9g} s",
                                 source=src)
        step = (float(chunk.t[-1] - chunk.t[0]) / (chunk.n - 1)) if step is None else step
        last_t = float(chunk.t[-1])
        yield chunk


def save_record(record: Record, path: str | Path) -> Path:
    """Write ``record`` as ``.csv`` (no meta), ``.npz`` or ``.tdms``; returns the path."""
    path = Path(path)
    writer = _WRITERS[_suffix(path)]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        writer(record, path)
    except OSError as err:
        raise InputError(f"cannot write record: {err.strerror or err}", source=str(path)) from err
    return path


def validate_record(record: Record, profile=None, min_samples: int = 0) -> Record:
    """Check at least 2 samples, finite values, uniform increasing time, the sample rate against
    ``profile.sampling.rate_hz`` and then at least ``min_samples`` samples (a record at another
    rate is refused for its rate, whatever its length).

    Raises :class:`InputError` naming ``record.source``; returns ``record`` unchanged.
    """
    src, n = record.source, record.n
    if n == 0:
        raise InputError("no samples: the file has no data rows", source=src)
    if n < 2:
        raise InputError(f"need at least 2 samples to define a sample rate, got {n}", source=src)
    for name, x in record.channels().items():
        bad = ~np.isfinite(x)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"{'NaN' if np.isnan(x[i]) else 'inf'} in column '{name}' at sample {i}", source=src)
    step = _uniform_step(record.t, src)
    if profile is not None:
        rate, want = 1.0 / step, float(profile.sampling.rate_hz)
        if abs(rate - want) > RATE_TOLERANCE * want:
            raise InputError(f"sample rate {rate:.9g} Hz disagrees with the profile's "
                             f"sampling.rate_hz = {want:.9g} Hz", source=src)
    if n < min_samples:  # after the rate: a record at another rate is that, not a short one
        raise InputError(f"too short for the window: {n} samples, need {min_samples}", source=src)
    return record


# ---------------------------------------------------------------------------------- helpers


def _check_file(path: Path) -> None:
    if path.is_dir():
        raise InputError("is a folder, not a record file", source=str(path))
    if not path.is_file():
        raise InputError("no such record file", source=str(path))
    if path.suffix.lower() == ".npz":
        import zipfile

        if not zipfile.is_zipfile(path):
            raise InputError("cannot read NPZ: not an NPZ archive (not a zip file)", source=str(path))


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise InputError(f"unknown record format '{path.suffix}' (expected {', '.join(FORMATS)})",
                         source=str(path))
    return suffix


def _uniform_step(t: np.ndarray, src: str) -> float:
    """Mean time step (s) of an increasing time column whose steps all lie within
    ``TIME_TOLERANCE`` (relative) of the median step."""
    dt = np.diff(t)
    bad = dt <= 0
    if bad.any():
        i = int(np.argmax(bad)) + 1
        raise InputError(f"time is not increasing at sample {i} (t = {float(t[i]):.9g} s after {float(t[i - 1]):.9g} s)", source=src)
    ref = float(np.median(dt))
    bad = np.abs(dt - ref) > TIME_TOLERANCE * ref
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"non-uniform time: step {dt[i]:.9g} s at sample {i + 1}, expected {ref:.9g} s "
                         f"(relative tolerance {TIME_TOLERANCE:g})", source=src)
    return float(t[-1] - t[0]) / (t.size - 1)


def _from_columns(cols: dict, src: str, meta: dict, found) -> Record:
    """Build a :class:`Record` from name -> array (``found``: all names in the file), checking
    presence, type, shape and lengths."""
    missing = [k for k in REQUIRED if k not in cols]
    if missing:
        s = "s" if len(missing) > 1 else ""
        raise InputError(f"missing required column{s} {', '.join(map(repr, missing))} "
                         f"(found: {', '.join(found) or 'none'})", source=src)
    out = {}
    for name, a in cols.items():
        a = np.asarray(a)
        if a.dtype.kind not in "iuf":
            raise InputError(f"column '{name}' is not numeric (dtype {a.dtype})", source=src)
        if a.ndim != 1:
            raise InputError(f"column '{name}' must be 1-D, has shape {a.shape}", source=src)
        if a.size != cols["t"].size:
            raise InputError(f"column '{name}' has {a.size} samples, 't' has {cols['t'].size}", source=src)
        out[name] = np.ascontiguousarray(a, dtype=np.float64)
    return Record(t=out["t"], v_abc=np.stack([out[k] for k in VOLTAGES]), i_abc=np.stack([out[k] for k in CURRENTS]),
                  theta_e=out.get("theta_e"), omega_e=out.get("omega_e"), source=src, meta=meta)


def _plain(value):
    """A meta value as plain JSON-able Python: numpy scalars and arrays converted, others -> str."""
    if isinstance(value, (np.ndarray, np.generic)) and not isinstance(value, np.datetime64):
        return value.tolist()
    return value if isinstance(value, (str, int, float, bool, list, dict, type(None))) else str(value)


# CSV ------------------------------------------------------------------------------------------

_CONVERT = re.compile(r"could not convert string '(.*)' to \w+ at row (\d+), column (\d+)")
_RAGGED = re.compile(r"at row (\d+) with (\d+) columns")
SEPARATORS = (",", ";", "\t", "|")  #: CSV field separators recognised from the header row
#: units a column may state in its header, per quantity: factor to the record's unit
UNIT_FACTORS = {"s": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "min": 60.0},
                "V": {"V": 1.0, "mV": 1e-3, "kV": 1e3},
                "A": {"A": 1.0, "mA": 1e-3, "kA": 1e3},
                "rad": {"rad": 1.0, "deg": np.pi / 180.0, "°": np.pi / 180.0},
                "rad/s": {"rad/s": 1.0, "1/s": 1.0, "deg/s": np.pi / 180.0}}
SPELLINGS = {**{k: k for k in UNITS}, "time": "t"}  #: header names (lower case) of each channel
_UNIT = re.compile(r"^\s*(?:\[(?P<b>[^\]]*)\]|\((?P<p>[^)]*)\)|[_/ ](?P<s>\S+))\s*$")


@dataclass(frozen=True)
class CsvLayout:
    """How a CSV file is written: its separator, whether numbers use a decimal comma, its header
    fields, and per known channel the column index and the factor to the record's unit."""

    sep: str
    decimal_comma: bool
    header: list
    columns: dict  #: channel name -> (column index, factor)

    def lines(self, lines):
        """Data lines as numpy reads them (a decimal comma turned into a point)."""
        return (line.replace(",", ".") for line in lines) if self.decimal_comma else lines


def _unit_factor(unit: str, quantity: str) -> float | None:
    """Factor from ``unit`` to the record's unit of ``quantity``; None if it is not one of its units
    (case aside: ``ma`` is mA)."""
    factors = UNIT_FACTORS[quantity]
    if unit in factors:
        return factors[unit]
    return {k.lower(): v for k, v in factors.items()}.get(unit.lower())


def _channel(field: str, src: str) -> tuple[str, float] | None:
    """(channel, factor) a header field names, in any case and with a stated unit (``ia [A]``,
    ``ia (mA)``, ``ia_A``, ``IA``), or None for a column the record does not use. A bracketed unit
    that is not one of the channel's quantity is refused naming it, as is a suffixed one that is a
    unit of another quantity (``ia_V``); any other suffix is another column (``t_motor``)."""
    low = field.strip().lower()
    for spelled, name in sorted(SPELLINGS.items(), key=lambda kv: len(kv[0]), reverse=True):  # theta_e before t
        if not low.startswith(spelled):
            continue
        rest = field.strip()[len(spelled):]
        if not rest:
            return name, 1.0
        m = _UNIT.match(rest)
        if not m:
            continue
        unit = next(u for u in m.groups() if u is not None).strip()
        factor = _unit_factor(unit, UNITS[name])
        if factor is not None:
            return name, factor
        if m.group("s") is not None and not any(_unit_factor(unit, q) is not None for q in UNIT_FACTORS):
            continue
        raise InputError(f"column '{field.strip()}': unit '{unit}' is not one of {UNITS[name]}'s "
                         f"({', '.join(UNIT_FACTORS[UNITS[name]])})", source=src)
    return None


def _csv_layout(f, src: str) -> CsvLayout:
    """The layout of an open CSV file from its header row and first data row; the file is left
    after the header."""
    head = f.readline()
    pos = f.tell()
    first = f.readline()
    f.seek(pos)
    sep = max(SEPARATORS, key=lambda c: (head.count(c), c == ","))
    header = [h.strip() for h in next(csv.reader([head], delimiter=sep), [])]
    # a decimal comma: a separator other than the comma, and commas inside the data row's numbers
    decimal_comma = sep != "," and bool(re.search(r"\d,\d", first))
    columns, seen = {}, {}
    for j, field in enumerate(header):
        hit = _channel(field, src)
        if hit is None:
            continue
        name, factor = hit
        if name in seen:
            raise InputError(f"duplicate column '{name}' ('{seen[name]}' and '{field}')", source=src)
        seen[name] = field
        columns[name] = (j, factor)
    return CsvLayout(sep, decimal_comma, header, columns)


def _csv_rows(lines, layout: CsvLayout, src: str, first_row: int = 0) -> dict:
    """CSV data rows (an open file or a list of lines) -> channel name -> array in the record's
    units; errors name the sample."""
    names = list(layout.columns)
    header = layout.header
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            data = np.loadtxt(layout.lines(lines), delimiter=layout.sep, usecols=[layout.columns[k][0] for k in names],
                              ndmin=2)
    except ValueError as err:
        msg = str(err)
        if m := _CONVERT.search(msg):
            value, row, col = m.group(1), int(m.group(2)), int(m.group(3))
            raise InputError(f"non-numeric value {value!r} in column '{header[col - 1]}' at sample "
                             f"{first_row + row}", source=src) from err
        if m := _RAGGED.search(msg):  # numpy counts this row from 1, the one above from 0
            raise InputError(f"sample {first_row + int(m.group(1)) - 1} has only {m.group(2)} fields, header has "
                             f"{len(header)}", source=src) from err
        raise InputError(f"cannot parse CSV: {msg}", source=src) from err
    if data.shape[1] != len(names):  # no data rows
        data = np.empty((0, len(names)))
    return {k: data[:, j] * layout.columns[k][1] for j, k in enumerate(names)}


def _csv_errors(err: Exception, src: str) -> InputError:
    if isinstance(err, UnicodeDecodeError):
        return InputError(f"cannot read CSV: not UTF-8 text ({err.reason} at byte {err.start})", source=src)
    return InputError(f"cannot read CSV: {err.strerror or err}", source=src)


def _read_csv(path: Path, src: str):
    return next(_stream_csv(path, src, None))


def _stream_csv(path: Path, src: str, chunk: int | None):
    """Chunks of ``chunk`` rows (None: the whole file at once) as (columns, meta, header)."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            layout = _csv_layout(f, src)
            if not layout.columns:
                yield {}, {}, layout.header
                return
            if chunk is None:
                yield _csv_rows(f, layout, src), {}, layout.header
                return
            row = 0
            while lines := list(islice(f, chunk)):
                yield _csv_rows(lines, layout, src, row), {}, layout.header
                row += len(lines)
    except (UnicodeDecodeError, OSError) as err:
        raise _csv_errors(err, src) from err


def _write_csv(record: Record, path: Path) -> None:
    cols = record.channels()
    np.savetxt(path, np.column_stack(list(cols.values())), delimiter=",", header=",".join(cols), comments="",
               fmt=["%.17g" if k == "t" else "%.10g" for k in cols])  # t exact: the step tolerance is 1e-6


# NPZ ------------------------------------------------------------------------------------------


def _read_npz(path: Path, src: str):
    key = None
    try:  # any failure of the archive reader means a corrupt file
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise TypeError("not an NPZ archive (a single .npy array?)")
        with z:
            found = [k for k in z.files if k != META_KEY]
            cols = {}
            for key in (k for k in (*UNITS, META_KEY) if k in z.files):
                cols[key] = z[key]
    except Exception as err:  # noqa: BLE001
        where = f" (array '{key}')" if key else ""
        raise InputError(f"cannot read NPZ{where}: {err}", source=src) from err
    meta = _npz_meta(cols.pop(META_KEY), src) if META_KEY in cols else {}
    return cols, meta, found


def _stream_npz(path: Path, src: str, chunk: int):
    """NPZ members read ``chunk`` values at a time straight from the archive (each member is an
    .npy file: header, then the raw array)."""
    import zipfile

    key = None
    try:
        with zipfile.ZipFile(path) as z:
            members = {n[:-4]: n for n in z.namelist() if n.endswith(".npy")}
            found = [k for k in members if k != META_KEY]
            meta = {}
            if META_KEY in members:
                with z.open(members[META_KEY]) as f:
                    meta = _npz_meta(np.lib.format.read_array(f, allow_pickle=False), src)
            streams, total = {}, None
            for key in (k for k in UNITS if k in members):
                f = z.open(members[key])
                version = np.lib.format.read_magic(f)
                shape, fortran, dtype = (np.lib.format.read_array_header_1_0(f) if version == (1, 0)
                                         else np.lib.format.read_array_header_2_0(f))
                if len(shape) != 1 or dtype.kind not in "iuf":
                    raise InputError(f"column '{key}' must be a 1-D numeric array, has shape {shape}, dtype {dtype}",
                                     source=src)
                streams[key] = (f, dtype)
                total = shape[0] if total is None else total
            if not streams:
                yield {}, meta, found
                return
            done = 0
            while done < total or done == 0:
                n = min(chunk, total - done)
                cols = {}
                for key, (f, dtype) in streams.items():
                    raw = f.read(n * dtype.itemsize)
                    cols[key] = np.frombuffer(raw, dtype=dtype)
                done += n
                yield cols, meta, found
                if n == 0:
                    return
    except InputError:
        raise
    except Exception as err:  # noqa: BLE001 - any failure of the archive reader means a corrupt file
        where = f" (array '{key}')" if key else ""
        raise InputError(f"cannot read NPZ{where}: {err}", source=src) from err


def _npz_meta(value, src: str) -> dict:
    try:
        meta = json.loads(str(np.asarray(value).reshape(-1)[0]))
    except (ValueError, IndexError) as err:
        raise InputError(f"'{META_KEY}' is not a JSON string: {err}", source=src) from err
    if not isinstance(meta, dict):
        raise InputError(f"'{META_KEY}' must be a JSON object", source=src)
    return meta


def _write_npz(record: Record, path: Path) -> None:
    meta = np.array(json.dumps(record.meta, default=_plain))
    with open(path, "wb") as f:  # a file object: np.savez would otherwise append ".npz" to odd names
        np.savez(f, **record.channels(), **{META_KEY: meta})


# TDMS -----------------------------------------------------------------------------------------


def _tdms_group(tf, src: str):
    """The record's group of a TDMS file (the only one, the named one, or the only complete one)."""
    groups = {g.name: g for g in tf.groups()}
    named = tf.properties.get(GROUP_PROPERTY)
    if named is not None:
        if named not in groups:
            raise InputError(f"group '{named}' named by root property '{GROUP_PROPERTY}' not found "
                             f"(groups: {', '.join(groups) or 'none'})", source=src)
        return groups[named]
    fits = [g for g in groups.values() if all(k in g for k in REQUIRED[1:])]
    if len(groups) == 1 or len(fits) == 1:
        return fits[0] if len(fits) == 1 else next(iter(groups.values()))
    raise InputError(f"cannot tell which of {len(groups)} groups holds the record "
                     f"({', '.join(groups) or 'none'}); name it with the root property "
                     f"'{GROUP_PROPERTY}'", source=src)


def _tdms_time(chans: dict, src: str) -> tuple[float, float] | None:
    """(t0, step) from the channels' waveform properties; None when a ``t`` channel must be used."""
    signals = [k for k in chans if k != "t"]
    if not signals:
        return None
    ref = signals[0]
    inc = [chans[k].properties.get("wf_increment") for k in signals]
    if all(v is not None for v in inc):
        d0 = float(inc[0])
        for k, d in zip(signals, inc):
            if abs(float(d) - d0) > TIME_TOLERANCE * abs(d0):
                raise InputError(f"channel '{k}' has wf_increment {float(d):.9g} s, '{ref}' has {d0:.9g} s",
                                 source=src)
        return float(chans[ref].properties.get("wf_start_offset", 0.0)), d0
    if "t" not in chans:
        k = signals[inc.index(None)]
        raise InputError(f"channel '{k}' has no wf_increment property and there is no 't' channel", source=src)
    return None


def _tdms_chunks(tf, src: str, chunk: int | None):
    group = _tdms_group(tf, src)
    chans = {k: group[k] for k in UNITS if k in group}
    timing = _tdms_time(chans, src)
    meta = {k: _plain(v) for k, v in group.properties.items()}
    found = [c.name for c in group.channels()]
    n = max((len(c) for c in chans.values()), default=0)
    step = n if chunk is None else chunk
    for start in range(0, max(n, 1), max(step, 1)):
        cols = {k: c[start:start + step] for k, c in chans.items()}
        if timing is not None:
            size = cols[next(k for k in chans if k != "t")].size
            cols["t"] = timing[0] + timing[1] * np.arange(start, start + size)
        yield cols, meta, found


def _read_tdms(path: Path, src: str):
    from nptdms import TdmsFile

    try:
        tf = TdmsFile.read(path)
    except Exception as err:  # noqa: BLE001 - npTDMS raises many types on corrupt files
        raise InputError(f"cannot read TDMS: {err}", source=src) from err
    return next(_tdms_chunks(tf, src, None))


def _stream_tdms(path: Path, src: str, chunk: int):
    from nptdms import TdmsFile

    try:
        tf = TdmsFile.open(path)  # lazy: slices read from disk
    except Exception as err:  # noqa: BLE001
        raise InputError(f"cannot read TDMS: {err}", source=src) from err
    with tf:
        yield from _tdms_chunks(tf, src, chunk)


def _tdms_value(value):
    """A meta value as a TDMS property: scalars as they are, anything else as JSON text."""
    value = _plain(value)
    return value if isinstance(value, (str, int, float, bool)) else json.dumps(value, default=_plain)


def _write_tdms(record: Record, path: Path) -> None:
    from nptdms import ChannelObject, GroupObject, RootObject, TdmsWriter

    step = _uniform_step(record.t, record.source)
    meta = {k: _tdms_value(v) for k, v in record.meta.items()}
    objects = [RootObject({GROUP_PROPERTY: TDMS_GROUP}), GroupObject(TDMS_GROUP, meta)]
    for name, x in record.channels().items():
        if name != "t":
            props = {"wf_increment": step, "wf_start_offset": float(record.t[0]), "wf_samples": x.size,
                     "unit_string": UNITS[name]}
            objects.append(ChannelObject(TDMS_GROUP, name, np.asarray(x, dtype=np.float64), properties=props))
    with TdmsWriter(path) as writer:
        writer.write_segment(objects)


_READERS = {".csv": _read_csv, ".npz": _read_npz, ".tdms": _read_tdms}
_STREAMERS = {".csv": _stream_csv, ".npz": _stream_npz, ".tdms": _stream_tdms}
_WRITERS = {".csv": _write_csv, ".npz": _write_npz, ".tdms": _write_tdms}
