"""Register-map machinery shared by the Modbus maps of :mod:`firmware_if`.

A map is a tuple of :class:`RegisterDef` rows (name, table, 0-based address, type, word order,
scale, unit, access, description). The same rows drive encoding/decoding of register blocks,
the Markdown documentation and the C ``#define`` constants, so code, docs and firmware cannot
drift.

Conventions (Modbus application protocol v1.1b3 and common PLC practice):

* Addresses are the 0-based *wire* addresses of the PDU. The legacy notation adds 30001 (input
  registers) or 40001 (holding registers); addresses above 9998 use the 6-digit form
  300001/400001 + address.
* 32-bit values occupy two registers, high word first and big-endian bytes in each word
  (``ABCD``), and start on an even address.
* ``physical = raw * scale``; encoding rounds to the nearest integer and saturates to the
  type's range (the n/a sentinel excluded). A NaN physical value is written as the row's
  ``na`` sentinel when it has one.
"""

from __future__ import annotations

import argparse
import math
import struct
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

TABLES = ("IR", "HR")  #: input registers, holding registers (also the documentation order)
#: type -> (registers, struct code, min raw, max raw)
TYPES = {
    "UINT16": (1, "H", 0, 0xFFFF),
    "INT16": (1, "h", -0x8000, 0x7FFF),
    "UINT32": (2, "I", 0, 0xFFFFFFFF),
    "FLOAT32": (2, "f", None, None),
}
LEGACY_BASE = {"IR": 30001, "HR": 40001}
LEGACY_BASE_6 = {"IR": 300001, "HR": 400001}


@dataclass(frozen=True)
class RegisterDef:
    """One row of a register map.

    ``address`` is the 0-based wire address, or the offset inside a repeated block when
    ``block`` names one (the PLC map's per-drive block). ``count`` > 1 makes an array of
    ``count`` consecutive values of ``type`` (the capture buffer's sample window).
    ``na``: raw value written for NaN (None: NaN is an error). ``access``: ``R`` or ``RW``
    as seen by the Modbus client.
    """

    name: str
    table: str
    address: int
    type: str = "UINT16"
    scale: float = 1.0
    unit: str = ""
    access: str = "R"
    description: str = ""
    block: str = ""
    count: int = 1
    na: int | None = None

    def __post_init__(self):
        if self.table not in TABLES:
            raise ValueError(f"{self.name}: table must be one of {TABLES}")
        if self.type not in TYPES:
            raise ValueError(f"{self.name}: type must be one of {tuple(TYPES)}")
        if self.access not in ("R", "RW"):
            raise ValueError(f"{self.name}: access must be R or RW")
        if self.words == 2 and self.address % 2:
            raise ValueError(f"{self.name}: 32-bit value on odd address {self.address}")
        if not (self.scale > 0 and math.isfinite(self.scale)):
            raise ValueError(f"{self.name}: scale must be positive")

    @property
    def words(self) -> int:
        """Registers per value."""
        return TYPES[self.type][0]

    @property
    def size(self) -> int:
        """Registers of the whole row."""
        return self.words * self.count

    @property
    def word_order(self) -> str:
        return "ABCD" if self.words == 2 else "-"

    @property
    def end(self) -> int:
        """One past the last register."""
        return self.address + self.size


def legacy(table: str, address: int, six_digit: bool | None = None) -> str:
    """Legacy 1-based notation of a 0-based wire address (30001/40001; the 6-digit form
    300001/400001 above address 9998 or when ``six_digit``)."""
    if not six_digit and address <= 9998:
        return str(LEGACY_BASE[table] + address)
    return str(LEGACY_BASE_6[table] + address)


def encode_value(d: RegisterDef, value: float | int) -> list[int]:
    """Physical ``value`` -> the row's registers (one value, ``d.words`` registers)."""
    nwords, code, lo, hi = TYPES[d.type]
    if d.type == "FLOAT32":
        raw = struct.unpack(">I", struct.pack(">f", float(value) / d.scale))[0]
        return [raw >> 16, raw & 0xFFFF]
    v = float(value)
    if v != v:
        if d.na is None:
            raise ValueError(f"{d.name}: NaN has no encoding")
        raw = d.na
    else:
        if d.na is not None:  # keep the sentinel out of the value range
            if d.na == hi:
                hi -= 1
            elif d.na == lo:
                lo += 1
        r = v / d.scale
        raw = int(min(max(round(r), lo), hi)) if math.isfinite(r) else (hi if r > 0 else lo)
    raw &= (1 << (16 * nwords)) - 1  # two's complement for INT16
    if nwords == 2:
        return [raw >> 16, raw & 0xFFFF]
    return [raw]


def decode_value(d: RegisterDef, regs: Sequence[int]) -> float | int:
    """Registers of one value -> physical value (NaN for the n/a sentinel); ints stay ints
    when ``scale`` is 1."""
    nwords, code, _, _ = TYPES[d.type]
    raw_u = int(regs[0]) if nwords == 1 else (int(regs[0]) << 16) | int(regs[1])
    if d.type == "FLOAT32":
        return struct.unpack(">f", struct.pack(">I", raw_u))[0] * d.scale
    raw = struct.unpack(">" + code, struct.pack(">I" if nwords == 2 else ">H", raw_u))[0]
    if d.na is not None and raw == d.na:
        return float("nan")
    return raw if d.scale == 1.0 else raw * d.scale


def encode_block(defs: Iterable[RegisterDef], values: Mapping[str, float | int], length: int,
                 base: int = 0) -> list[int]:
    """Registers ``base .. base+length`` with ``values`` (by row name) encoded; rows without a
    value and reserved registers are 0. Array rows are skipped."""
    regs = [0] * length
    for d in defs:
        if d.name in values and d.count == 1:
            o = d.address - base
            regs[o:o + d.words] = encode_value(d, values[d.name])
    return regs


def decode_block(defs: Iterable[RegisterDef], regs: Sequence[int], base: int = 0) -> dict:
    """Name -> physical value for every scalar row inside ``regs`` (which start at ``base``)."""
    out = {}
    for d in defs:
        o = d.address - base
        if d.count == 1 and 0 <= o and o + d.words <= len(regs):
            out[d.name] = decode_value(d, regs[o:o + d.words])
    return out


def check_layout(defs: Sequence[RegisterDef]) -> None:
    """Raise ``ValueError`` on overlapping rows or duplicate names (per table and block)."""
    names = [d.name for d in defs]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ValueError(f"duplicate register names {sorted(dup)}")
    groups: dict[tuple[str, str], list[RegisterDef]] = {}
    for d in defs:
        groups.setdefault((d.table, d.block), []).append(d)
    for rows in groups.values():
        rows = sorted(rows, key=lambda d: d.address)
        for a, b in zip(rows, rows[1:]):
            if b.address < a.end:
                raise ValueError(f"{a.name} and {b.name} overlap")


def _fmt_scale(d: RegisterDef) -> str:
    if d.type == "FLOAT32" or d.scale == 1.0:
        return "1"
    return f"{d.scale:g}"


def markdown_table(defs: Iterable[RegisterDef], *, base: int = 0, offset_column: bool = False) -> str:
    """A Markdown table of ``defs``.

    Columns: name, table, 0-based wire address (``base + address``), legacy notation, type,
    word order, scale, unit, access, description. With ``offset_column`` a first column gives
    the row's offset inside its block.
    """
    head = ["name", "table", "address", "legacy", "type", "word order", "scale", "unit", "access", "description"]
    if offset_column:
        head.insert(0, "offset")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for d in sorted(defs, key=lambda d: (TABLES.index(d.table), d.address)):
        a = base + d.address
        addr = str(a) if d.size == 1 else f"{a}..{a + d.size - 1}"
        last = a + d.size - 1
        six = last > 9998
        leg = legacy(d.table, a) if d.size == 1 else f"{legacy(d.table, a, six)}..{legacy(d.table, last, six)}"
        typ = d.type if d.count == 1 else f"{d.type}[{d.count}]"
        desc = d.description
        if d.na is not None:
            desc += f" Raw {d.na} = n/a."
        row = [f"`{d.name}`", d.table, addr, leg, typ, d.word_order, _fmt_scale(d), d.unit or "-", d.access,
               desc.replace("|", "\\|")]
        if offset_column:
            row.insert(0, f"+{d.address}")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def render_main(render: Callable[[], str], argv: list[str] | None, *, prog: str, description: str) -> int:
    """The command line of a map module: print ``render()``, ``--write PATH`` it, or ``--check PATH``
    (exit 1 when the file differs from the generated text)."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument("--write", metavar="PATH", help="write the Markdown to PATH (default: stdout)")
    ap.add_argument("--check", metavar="PATH", help="exit 1 when PATH differs from the generated text")
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        ok = Path(args.check).is_file() and Path(args.check).read_text() == text
        print(f"{args.check}: {'up to date' if ok else 'STALE, regenerate with --write'}", file=sys.stderr)
        return 0 if ok else 1
    if args.write:
        Path(args.write).write_text(text)
        print(args.write)
    else:
        sys.stdout.write(text)
    return 0
