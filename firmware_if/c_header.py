"""C header ``pmsm_wire.h`` generated from the Python wire definitions.

The drive firmware includes this header, the agent imports the Python modules: one definition,
two languages. Every wire module of :mod:`firmware_if` contributes a *section* at import time:

* ``#define`` constants (:func:`register_defines`), e.g. sync word, ids, scale factors;
* packed structs generated from a :class:`Field` list (:func:`c_struct`), with a static assert on
  the size. The same field list builds the module's ``struct.Struct`` / numpy dtype
  (:func:`struct_format`, :func:`numpy_dtype`), so C and Python layouts cannot drift;
* free C code (inline helpers) through ``register_section(..., code=...)``.

:func:`render_header` imports :data:`WIRE_MODULES` (missing ones are skipped, so a module that
another engineer has not written yet does not break the header) and emits the sections in
``order`` then name order. Regenerate with ``python -m firmware_if.c_header -o pmsm_wire.h``.

Registry API for other wire modules (stable)::

    from firmware_if.c_header import register_defines, register_section, Define
    register_defines("modbus_capture", {"PMSM_MBCAP_BLOCK_REGS": 120, ...}, comment="...")
    register_defines("plc_registers", [Define("PMSM_PLC_IR_VERSION", 0, "IR0: map version")])

Names must be upper-case C identifiers starting with ``PMSM_`` and unique across sections
(:func:`render_header` raises ``ValueError`` on a conflict). Registering a section again replaces
it (module reloads are harmless). Values: ``bool``/``int`` (unsigned ints get a ``u`` suffix,
``hex=True`` prints hex), ``float`` (shortest repr, exact as a C ``double``), ``str`` (a C string
literal), or :class:`CExpr` (emitted verbatim in parentheses).

Assumptions stated in the header: little-endian target (checked with ``__BYTE_ORDER__`` where
the compiler defines it), packed structs (``PMSM_PACKED``, GCC/Clang attribute by default;
predefine it for other compilers), C11 ``_Static_assert`` or C++11 ``static_assert``.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: Modules whose import registers their sections (missing modules are skipped).
WIRE_MODULES = (
    "firmware_if.serial_frame",
    "firmware_if.can_frame",
    "firmware_if.modbus_capture",
    "firmware_if.plc_registers",
)
HEADER_NAME = "pmsm_wire.h"
GUARD = "PMSM_WIRE_H"
PREFIX = "PMSM_"

_NAME = re.compile(r"^[A-Z][A-Z0-9_]*$")
_CIDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class CExpr:
    """A C expression emitted verbatim (in parentheses), e.g. ``CExpr("PMSM_A * 2u")``."""

    text: str


@dataclass(frozen=True)
class Define:
    """One ``#define NAME value /* comment */``."""

    name: str
    value: int | float | str | bool | CExpr
    comment: str = ""
    hex: bool = False

    def render(self) -> str:
        v = self.value
        if isinstance(v, CExpr):
            text = f"({v.text})"
        elif isinstance(v, bool):
            text = "1" if v else "0"
        elif isinstance(v, (int, np.integer)):
            v = int(v)
            if v < 0:
                text = f"({v})"
            else:
                suffix = "u" if v <= 0xFFFFFFFF else "ull"
                text = f"0x{v:X}{suffix}" if self.hex else f"{v}{suffix}"
        elif isinstance(v, (float, np.floating)):
            v = float(v)
            if v != v or v in (float("inf"), float("-inf")):
                raise ValueError(f"{self.name}: non-finite float {v}")
            text = repr(v)
            text = f"({text})" if v < 0 else text
        elif isinstance(v, str):
            text = '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        else:
            raise TypeError(f"{self.name}: unsupported value type {type(v).__name__}")
        line = f"#define {self.name} {text}"
        if self.comment:
            line = f"{line:<56} /* {_comment(self.comment)} */"
        return line


@dataclass(frozen=True)
class Field:
    """One field of a packed little-endian wire struct.

    ``ctype``: ``u8 u16 u32 i8 i16 i32 f32``; ``shape``: array dimensions (``()`` for a scalar).
    """

    name: str
    ctype: str
    shape: tuple[int, ...] = ()
    comment: str = ""

    @property
    def size(self) -> int:
        return _TYPES[self.ctype][2] * int(np.prod(self.shape, dtype=np.int64))


#: ctype -> (C type, struct char, size, numpy dtype)
_TYPES = {
    "u8": ("uint8_t", "B", 1, "u1"), "i8": ("int8_t", "b", 1, "i1"),
    "u16": ("uint16_t", "H", 2, "<u2"), "i16": ("int16_t", "h", 2, "<i2"),
    "u32": ("uint32_t", "I", 4, "<u4"), "i32": ("int32_t", "i", 4, "<i4"),
    "f32": ("float", "f", 4, "<f4"),
}


@dataclass
class Section:
    name: str
    comment: str = ""
    defines: list[Define] = field(default_factory=list)
    code: str = ""
    order: int = 100


_SECTIONS: dict[str, Section] = {}


# ---------------------------------------------------------------------------------- registry


def register_section(name: str, *, comment: str = "", defines: Iterable[Define] = (), code: str = "",
                     order: int = 100) -> None:
    """Register (or replace) a section of the header: its ``#define`` lines then ``code``."""
    if not _CIDENT.match(name):
        raise ValueError(f"section name {name!r} is not an identifier")
    defs = list(defines)
    for d in defs:
        _check_name(d.name)
    _SECTIONS[name] = Section(name, comment, defs, code.strip("\n"), order)


def register_defines(section: str, defines: Mapping[str, object] | Iterable[Define | tuple],
                     *, comment: str = "", order: int = 100) -> None:
    """Register ``#define`` constants for ``section``.

    ``defines``: a mapping ``NAME -> value``, or an iterable of :class:`Define` or
    ``(name, value[, comment])`` tuples. Keeps any code already registered for the section.
    """
    if isinstance(defines, Mapping):
        defs = [Define(k, v) for k, v in defines.items()]
    else:
        defs = [d if isinstance(d, Define) else Define(*d) for d in defines]
    old = _SECTIONS.get(section)
    register_section(section, comment=comment or (old.comment if old else ""), defines=defs,
                     code=old.code if old else "", order=order if old is None else old.order)


def unregister_section(name: str) -> None:
    """Remove a section (tests; no error if absent)."""
    _SECTIONS.pop(name, None)


def sections() -> list[Section]:
    """Registered sections in output order."""
    return sorted(_SECTIONS.values(), key=lambda s: (s.order, s.name))


def _check_name(name: str) -> None:
    if not _NAME.match(name) or not name.startswith(PREFIX):
        raise ValueError(f"#define name {name!r} must be an upper-case C identifier starting with {PREFIX}")


def _comment(text: str) -> str:
    return text.replace("*/", "* /").replace("\n", " ")


# ---------------------------------------------------------------------------------- layouts


def struct_size(fields: Iterable[Field]) -> int:
    return sum(f.size for f in fields)


def struct_format(fields: Iterable[Field]) -> str:
    """``struct`` module format (little-endian, no padding); arrays are flattened."""
    out = "<"
    for f in fields:
        n = int(np.prod(f.shape, dtype=np.int64))
        out += (str(n) if n != 1 else "") + _TYPES[f.ctype][1]
    return out


def numpy_dtype(fields: Iterable[Field]) -> np.dtype:
    """Packed structured numpy dtype of the fields (``itemsize == struct_size``)."""
    return np.dtype([(f.name, _TYPES[f.ctype][3], f.shape) if f.shape else (f.name, _TYPES[f.ctype][3])
                     for f in fields])


def c_struct(typename: str, fields: Iterable[Field], comment: str = "") -> str:
    """``typedef struct PMSM_PACKED {...} typename;`` plus a static assert on its size."""
    fields = list(fields)
    lines = [f"/* {_comment(comment)} */"] if comment else []
    lines.append("typedef struct PMSM_PACKED {")
    for f in fields:
        dims = "".join(f"[{d}]" for d in f.shape)
        decl = f"    {_TYPES[f.ctype][0]} {f.name}{dims};"
        lines.append(f"{decl:<40} /* {_comment(f.comment)} */" if f.comment else decl)
    lines.append(f"}} {typename};")
    size = struct_size(fields)
    lines.append(f'PMSM_STATIC_ASSERT(sizeof({typename}) == {size}u, "{typename} must be {size} bytes");')
    return "\n".join(lines)


# ---------------------------------------------------------------------------------- output

_PREAMBLE = """\
/* {name}: wire definitions shared by the PMSM drive firmware and the edge agent.
 * GENERATED by `python -m firmware_if.c_header` from the Python package firmware_if.
 * Do not edit: change the Python definitions and regenerate.
 * All multi-byte fields are little-endian; structs are packed (no padding).
 */
#ifndef {guard}
#define {guard}

#include <stddef.h>
#include <stdint.h>

#if defined(__BYTE_ORDER__) && defined(__ORDER_LITTLE_ENDIAN__) && (__BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__)
#error "pmsm_wire.h: the packed structs assume a little-endian target"
#endif

#ifndef PMSM_PACKED
#define PMSM_PACKED __attribute__((packed))
#endif

#ifdef __cplusplus
#define PMSM_STATIC_ASSERT(cond, msg) static_assert(cond, msg)
extern "C" {{
#else
#define PMSM_STATIC_ASSERT(cond, msg) _Static_assert(cond, msg)
#endif
"""

_POSTAMBLE = """
#ifdef __cplusplus
}}
#endif

#endif /* {guard} */
"""


def render_header(modules: Iterable[str] = WIRE_MODULES) -> str:
    """The complete header text after importing ``modules`` (missing ones skipped)."""
    for mod in modules:
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as err:
            if err.name != mod:  # the module exists but one of its imports is missing: real error
                raise
    seen: dict[str, str] = {}
    parts = [_PREAMBLE.format(name=HEADER_NAME, guard=GUARD)]
    for sec in sections():
        parts.append("")
        parts.append(f"/* ---- {sec.name}" + (f": {_comment(sec.comment)}" if sec.comment else "") + " ---- */")
        for d in sec.defines:
            if d.name in seen and seen[d.name] != sec.name:
                raise ValueError(f"#define {d.name} registered by both {seen[d.name]!r} and {sec.name!r}")
            if d.name in seen:
                raise ValueError(f"#define {d.name} registered twice in section {sec.name!r}")
            seen[d.name] = sec.name
            parts.append(d.render())
        if sec.code:
            parts.append("")
            parts.append(sec.code)
    parts.append(_POSTAMBLE.format(guard=GUARD))
    return "\n".join(parts)


def write_header(path: str | Path, modules: Iterable[str] = WIRE_MODULES) -> Path:
    """Write :func:`render_header` to ``path`` (a directory gets ``pmsm_wire.h``); returns the file."""
    path = Path(path)
    if path.is_dir():
        path = path / HEADER_NAME
    path.write_text(render_header(modules))
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m firmware_if.c_header",
                                 description="Generate the C header pmsm_wire.h from firmware_if.")
    ap.add_argument("-o", "--out", default="-", help="output file or directory ('-' = stdout)")
    args = ap.parse_args(argv)
    if args.out == "-":
        sys.stdout.write(render_header())
    else:
        print(write_header(args.out))
    return 0


if __name__ == "__main__":
    # Run the package's instance of this module: the wire modules register into *that* one,
    # not into ``__main__``.
    from firmware_if import c_header as _registry
    raise SystemExit(_registry.main())
