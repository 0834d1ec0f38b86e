"""CAN FD frames carrying phase samples, per drive, on 29-bit (extended) identifiers.

Each drive owns a block of :data:`ID_BLOCK` (16) identifiers starting at ``base_id`` (aligned to
16; :func:`drive_base_id` gives drive ``k`` the block ``DEFAULT_BASE_ID + 16 k``). Assigned ids:

=============  ==========  ========  ===================================================================
message        id          payload   layout (little-endian, packed)
=============  ==========  ========  ===================================================================
``PHASE``      base + 0    64 bytes  u32 sample_index; i16 samples[5][6] (va vb vc ia ib ic per sample)
``ENCODER``    base + 1    24 bytes  u32 sample_index; u16 theta_e[5]; i16 omega_e[5]
=============  ==========  ========  ===================================================================

``sample_index`` is the index of the frame's first sample since the drive started streaming
(wraps at 2**32, 47 h at 25 kS/s); frames of one drive advance it by :data:`SAMPLES_PER_FRAME`,
so a jump is a gap of exactly that many samples. The optional ``ENCODER`` frame carries the
encoder angle/speed of the same five samples and is sent **before** the ``PHASE`` frame with the
same ``sample_index``. Other ids in the block are reserved: a receiver counts them as unknown.

Scaling (physical = raw * LSB): voltages :data:`DEFAULT_V_LSB` V, currents :data:`DEFAULT_I_LSB` A,
theta_e ``2 pi / 65536`` rad (unsigned, wrapped to [0, 2 pi)), omega_e :data:`DEFAULT_OMEGA_LSB`
rad/s. Voltage/current LSB are per-layout settings (:class:`CanLayout`) and go into the DBC.

Bandwidth: 25 kS/s x 6 channels is 5000 PHASE frames/s; at 500 kbit/s arbitration and 5 Mbit/s
data phase a 64-byte FD frame with a 29-bit id takes about 0.17 ms, i.e. about 85 % bus load for
one drive. Use a 8 Mbit/s data phase, or a lower sample rate, for more than one drive per bus.
Classic CAN (8-byte frames) cannot carry this stream and is not supported.

:func:`to_dbc` exports the layouts as a DBC (CAN FD, extended ids) for CANalyzer/SavvyCAN/cantools.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from firmware_if import c_header as ch
from firmware_if.c_header import Define, Field

DEFAULT_BASE_ID = 0x0A500000
ID_BLOCK = 16
ID_MASK = 0x1FFFFFFF & ~(ID_BLOCK - 1)
MAX_EXTENDED_ID = 0x1FFFFFFF
PHASE_OFFSET = 0
ENCODER_OFFSET = 1
SAMPLES_PER_FRAME = 5
N_PHASE = 6
PHASE_CHANNELS = ("va", "vb", "vc", "ia", "ib", "ic")
INDEX_MODULO = 2**32

DEFAULT_V_LSB = 0.05  #: V per LSB (+-1638 V)
DEFAULT_I_LSB = 0.002  #: A per LSB (+-65.5 A)
THETA_LSB = 2.0 * np.pi / 65536  #: rad per LSB, unsigned
DEFAULT_OMEGA_LSB = 0.05  #: rad/s per LSB (+-1638 rad/s)

PHASE_FIELDS = (
    Field("sample_index", "u32", comment="index of samples[0] since start, wraps"),
    Field("samples", "i16", (SAMPLES_PER_FRAME, N_PHASE), comment="[sample][va vb vc ia ib ic]"),
)
ENCODER_FIELDS = (
    Field("sample_index", "u32", comment="same as the PHASE frame it belongs to"),
    Field("theta_e", "u16", (SAMPLES_PER_FRAME,), comment="rad, PMSM_CAN_THETA_LSB, [0, 2pi)"),
    Field("omega_e", "i16", (SAMPLES_PER_FRAME,), comment="rad/s, PMSM_CAN_OMEGA_LSB"),
)
PHASE_DTYPE = ch.numpy_dtype(PHASE_FIELDS)
ENCODER_DTYPE = ch.numpy_dtype(ENCODER_FIELDS)
PHASE_SIZE = PHASE_DTYPE.itemsize  # 64
ENCODER_SIZE = ENCODER_DTYPE.itemsize  # 24
#: CAN FD payload lengths (DLC 0..15).
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
assert PHASE_SIZE in FD_LENGTHS and ENCODER_SIZE in FD_LENGTHS

PHASE = "phase"
ENCODER = "encoder"
_I16 = (-(2**15), 2**15 - 1)


def drive_base_id(index: int, base: int = DEFAULT_BASE_ID) -> int:
    """Base id of drive number ``index`` (0-based) in the default allocation."""
    return base + ID_BLOCK * int(index)


def _q16(x: np.ndarray, lsb: float) -> np.ndarray:
    q = np.nan_to_num(np.rint(np.asarray(x, dtype=np.float64) / lsb), nan=0.0, posinf=_I16[1], neginf=_I16[0])
    return np.clip(q, *_I16).astype("<i2")


@dataclass(frozen=True)
class CanLayout:
    """Identifiers and scaling of one drive's CAN FD stream."""

    drive: str = "drive0"
    base_id: int = DEFAULT_BASE_ID
    v_lsb: float = DEFAULT_V_LSB
    i_lsb: float = DEFAULT_I_LSB
    omega_lsb: float = DEFAULT_OMEGA_LSB

    def __post_init__(self):
        if not 0 <= self.base_id <= MAX_EXTENDED_ID - (ID_BLOCK - 1) or self.base_id % ID_BLOCK:
            raise ValueError(f"base_id 0x{self.base_id:X} must be a 29-bit id aligned to {ID_BLOCK}")
        for k in ("v_lsb", "i_lsb", "omega_lsb"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{k} must be finite and positive, got {v}")

    @property
    def phase_id(self) -> int:
        return self.base_id + PHASE_OFFSET

    @property
    def encoder_id(self) -> int:
        return self.base_id + ENCODER_OFFSET

    @property
    def scales(self) -> np.ndarray:
        """LSB of the six phase channels, ``(6,)``."""
        return np.array([self.v_lsb] * 3 + [self.i_lsb] * 3)

    def kind(self, arbitration_id: int, is_extended: bool = True) -> str | None:
        """``"phase"``, ``"encoder"`` or ``None`` (not ours, or reserved in our block)."""
        if not is_extended:
            return None
        if arbitration_id == self.phase_id:
            return PHASE
        if arbitration_id == self.encoder_id:
            return ENCODER
        return None

    def in_block(self, arbitration_id: int, is_extended: bool = True) -> bool:
        return bool(is_extended) and (arbitration_id & ID_MASK) == self.base_id

    def can_filter(self) -> dict:
        """python-can filter passing this drive's id block."""
        return {"can_id": self.base_id, "can_mask": ID_MASK, "extended": True}

    # ------------------------------------------------------------------ phase frames

    def encode_phase(self, first_index: int, v_abc: np.ndarray, i_abc: np.ndarray) -> list[bytes]:
        """PHASE payloads for ``N`` samples (``N`` a multiple of 5), quantised and saturated."""
        v_abc, i_abc = np.asarray(v_abc, float), np.asarray(i_abc, float)
        n = v_abc.shape[1]
        if v_abc.shape != (3, n) or i_abc.shape != (3, n) or n % SAMPLES_PER_FRAME:
            raise ValueError(f"v_abc, i_abc must be (3, N) with N a multiple of {SAMPLES_PER_FRAME}")
        k = n // SAMPLES_PER_FRAME
        arr = np.zeros(k, PHASE_DTYPE)
        arr["sample_index"] = (int(first_index) + SAMPLES_PER_FRAME * np.arange(k, dtype=np.int64)) % INDEX_MODULO
        q = np.concatenate([_q16(v_abc, self.v_lsb), _q16(i_abc, self.i_lsb)])  # (6, N)
        arr["samples"] = q.T.reshape(k, SAMPLES_PER_FRAME, N_PHASE)
        raw = arr.tobytes()
        return [raw[j * PHASE_SIZE:(j + 1) * PHASE_SIZE] for j in range(k)]

    def decode_phase(self, payloads) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Concatenated PHASE payloads (``64 K`` bytes) -> ``(sample_index (K,) int64,
        v_abc (3, 5K), i_abc (3, 5K))``. Raises ``ValueError`` on a length that is not ``64 K``."""
        arr = np.frombuffer(payloads, PHASE_DTYPE)
        x = arr["samples"].reshape(-1, N_PHASE).T * self.scales[:, None]
        return arr["sample_index"].astype(np.int64), x[:3], x[3:]

    # ------------------------------------------------------------------ encoder frames

    def encode_encoder(self, first_index: int, theta_e: np.ndarray, omega_e: np.ndarray) -> list[bytes]:
        """ENCODER payloads for ``N`` samples (``N`` a multiple of 5)."""
        theta_e, omega_e = np.asarray(theta_e, float).reshape(-1), np.asarray(omega_e, float).reshape(-1)
        n = theta_e.size
        if omega_e.size != n or n % SAMPLES_PER_FRAME:
            raise ValueError(f"theta_e, omega_e must be (N,) with N a multiple of {SAMPLES_PER_FRAME}")
        k = n // SAMPLES_PER_FRAME
        arr = np.zeros(k, ENCODER_DTYPE)
        arr["sample_index"] = (int(first_index) + SAMPLES_PER_FRAME * np.arange(k, dtype=np.int64)) % INDEX_MODULO
        th = np.nan_to_num(np.rint(np.mod(theta_e, 2 * np.pi) / THETA_LSB))
        arr["theta_e"] = (th.astype(np.int64) % 65536).reshape(k, SAMPLES_PER_FRAME)
        arr["omega_e"] = _q16(omega_e, self.omega_lsb).reshape(k, SAMPLES_PER_FRAME)
        raw = arr.tobytes()
        return [raw[j * ENCODER_SIZE:(j + 1) * ENCODER_SIZE] for j in range(k)]

    def decode_encoder(self, payloads) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Concatenated ENCODER payloads -> ``(sample_index (K,), theta_e (5K,), omega_e (5K,))``."""
        arr = np.frombuffer(payloads, ENCODER_DTYPE)
        return (arr["sample_index"].astype(np.int64), arr["theta_e"].reshape(-1) * THETA_LSB,
                arr["omega_e"].reshape(-1) * self.omega_lsb)


# ---------------------------------------------------------------------------------- DBC

_DBC_HEAD = '''VERSION ""


NS_ :
\tNS_DESC_
\tCM_
\tBA_DEF_
\tBA_
\tVAL_
\tBA_DEF_DEF_
\tSIG_VALTYPE_

BS_:

BU_: {nodes}
'''

_DBC_ATTRS = '''BA_DEF_ BO_ "VFrameFormat" ENUM "StandardCAN","ExtendedCAN","reserved","J1939PG","reserved","reserved",\
"reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","StandardCAN_FD",\
"ExtendedCAN_FD";
BA_DEF_ BO_ "CANFD_BRS" ENUM "0","1";
BA_DEF_ "BusType" STRING ;
BA_DEF_DEF_ "VFrameFormat" "StandardCAN";
BA_DEF_DEF_ "CANFD_BRS" "1";
BA_DEF_DEF_ "BusType" "CAN FD";
BA_ "BusType" "CAN FD";
'''
_EXTENDED_CAN_FD = 15
_AGENT_NODE = "PMSM_AGENT"


def _ident(text: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_]", "_", text)
    return s if re.match(r"[A-Za-z_]", s) else "_" + s


def _g(x: float, exact: bool = True) -> str:
    """Number for the DBC: exact shortest repr for factors, 12 digits for the [min|max] range."""
    x = float(x)
    if x == int(x) and abs(x) < 2**53:
        return str(int(x))
    return repr(x) if exact else format(x, ".12g")


def _signal(name: str, start: int, length: int, signed: bool, lsb: float, unit: str, receiver: str) -> str:
    if signed:
        lo, hi = -(2 ** (length - 1)), 2 ** (length - 1) - 1
    else:
        lo, hi = 0, 2**length - 1
    return (f' SG_ {name} : {start}|{length}@1{"-" if signed else "+"} ({_g(lsb)},0) '
            f'[{_g(lo * lsb, False)}|{_g(hi * lsb, False)}] "{unit}" {receiver}')


def to_dbc(layouts: CanLayout | Iterable[CanLayout] = (CanLayout(),)) -> str:
    """DBC text describing the PHASE and ENCODER messages of each layout (CAN FD, extended ids).

    Message names ``PMSM_PHASE_<drive>`` / ``PMSM_ENCODER_<drive>``; sender node
    ``DRIVE_<drive>``; signals ``sample_index``, ``<ch>_<k>`` (k = sample in the frame, 0..4) and
    ``theta_e_<k>``, ``omega_e_<k>``. Load with ``cantools.database.load_string(s, database_format="dbc")``
    and decode with ``force_extended_id=True``.
    """
    if isinstance(layouts, CanLayout):
        layouts = [layouts]
    layouts = list(layouts)
    ids = [lay.base_id for lay in layouts]
    if len(set(ids)) != len(ids):
        raise ValueError("two layouts share a base_id")
    nodes = [_AGENT_NODE] + [f"DRIVE_{_ident(lay.drive)}" for lay in layouts]
    out = [_DBC_HEAD.format(nodes=" ".join(nodes))]
    attrs, comments = [], []
    for lay, node in zip(layouts, nodes[1:]):
        d = _ident(lay.drive)
        for name, can_id, size, sigs, text in (
            (f"PMSM_PHASE_{d}", lay.phase_id, PHASE_SIZE, _phase_signals(lay),
             f"Phase samples of drive {lay.drive}: 5 samples x (va vb vc ia ib ic)"),
            (f"PMSM_ENCODER_{d}", lay.encoder_id, ENCODER_SIZE, _encoder_signals(lay),
             f"Encoder angle/speed of drive {lay.drive}, sent before the PHASE frame with the same sample_index"),
        ):
            dbc_id = can_id | 0x80000000
            out.append(f"BO_ {dbc_id} {name}: {size} {node}")
            out.extend(sigs)
            out.append("")
            attrs.append(f'BA_ "VFrameFormat" BO_ {dbc_id} {_EXTENDED_CAN_FD};')
            comments.append(f'CM_ BO_ {dbc_id} "{text}";')
    out.append("")
    out.extend(comments)
    out.append(_DBC_ATTRS.rstrip("\n"))
    out.extend(attrs)
    return "\n".join(out) + "\n"


def _phase_signals(lay: CanLayout) -> list[str]:
    sigs = [_signal("sample_index", 0, 32, False, 1, "", _AGENT_NODE)]
    for k in range(SAMPLES_PER_FRAME):
        for c, chan in enumerate(PHASE_CHANNELS):
            lsb, unit = (lay.v_lsb, "V") if c < 3 else (lay.i_lsb, "A")
            sigs.append(_signal(f"{chan}_{k}", 32 + 16 * (k * N_PHASE + c), 16, True, lsb, unit, _AGENT_NODE))
    return sigs


def _encoder_signals(lay: CanLayout) -> list[str]:
    sigs = [_signal("sample_index", 0, 32, False, 1, "", _AGENT_NODE)]
    sigs += [_signal(f"theta_e_{k}", 32 + 16 * k, 16, False, THETA_LSB, "rad", _AGENT_NODE)
             for k in range(SAMPLES_PER_FRAME)]
    sigs += [_signal(f"omega_e_{k}", 32 + 16 * (SAMPLES_PER_FRAME + k), 16, True, lay.omega_lsb, "rad/s",
                     _AGENT_NODE) for k in range(SAMPLES_PER_FRAME)]
    return sigs


# ---------------------------------------------------------------------------------- C header

_C_CODE = f"""\
{ch.c_struct("pmsm_can_phase_t", PHASE_FIELDS, "CAN FD PHASE payload, id = base + PMSM_CAN_PHASE_OFFSET")}

{ch.c_struct("pmsm_can_encoder_t", ENCODER_FIELDS, "CAN FD ENCODER payload, id = base + PMSM_CAN_ENCODER_OFFSET")}

#define PMSM_CAN_DRIVE_BASE_ID(index) (PMSM_CAN_DEFAULT_BASE_ID + PMSM_CAN_ID_BLOCK * (uint32_t)(index))
#define PMSM_CAN_PHASE_ID(base_id) ((uint32_t)(base_id) + PMSM_CAN_PHASE_OFFSET)
#define PMSM_CAN_ENCODER_ID(base_id) ((uint32_t)(base_id) + PMSM_CAN_ENCODER_OFFSET)"""


def _register_c() -> None:
    ch.register_section("can_frame", order=20, comment="CAN FD phase frames (firmware_if/can_frame.py)", defines=[
        Define("PMSM_CAN_DEFAULT_BASE_ID", DEFAULT_BASE_ID, "29-bit extended id of drive 0", hex=True),
        Define("PMSM_CAN_ID_BLOCK", ID_BLOCK, "ids per drive; base ids are aligned to it"),
        Define("PMSM_CAN_ID_MASK", ID_MASK, "acceptance mask for one drive's block", hex=True),
        Define("PMSM_CAN_PHASE_OFFSET", PHASE_OFFSET),
        Define("PMSM_CAN_ENCODER_OFFSET", ENCODER_OFFSET),
        Define("PMSM_CAN_SAMPLES_PER_FRAME", SAMPLES_PER_FRAME),
        Define("PMSM_CAN_PHASE_SIZE", PHASE_SIZE, "payload bytes, FD DLC 15"),
        Define("PMSM_CAN_ENCODER_SIZE", ENCODER_SIZE, "payload bytes, FD DLC 12"),
        Define("PMSM_CAN_V_LSB", DEFAULT_V_LSB, "V per LSB (default layout)"),
        Define("PMSM_CAN_I_LSB", DEFAULT_I_LSB, "A per LSB (default layout)"),
        Define("PMSM_CAN_THETA_LSB", THETA_LSB, "rad per LSB, unsigned"),
        Define("PMSM_CAN_OMEGA_LSB", DEFAULT_OMEGA_LSB, "rad/s per LSB (default layout)"),
    ], code=_C_CODE)


_register_c()


def main(argv: list[str] | None = None) -> int:
    """``python -m firmware_if.can_frame [--drive NAME[=BASE_ID]]... [-o FILE]``: write the DBC."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="python -m firmware_if.can_frame", description="Export the CAN FD DBC.")
    ap.add_argument("--drive", action="append", default=[],
                    help="NAME or NAME=BASE_ID (hex ok); default: drive0 at the default base id; "
                         "without BASE_ID the k-th drive gets drive_base_id(k)")
    ap.add_argument("-o", "--out", default="-", help="output file ('-' = stdout)")
    args = ap.parse_args(argv)
    layouts = []
    for k, spec in enumerate(args.drive or ["drive0"]):
        name, _, base = spec.partition("=")
        layouts.append(CanLayout(name, int(base, 0) if base else drive_base_id(k)))
    text = to_dbc(layouts)
    if args.out == "-":
        sys.stdout.write(text)
    else:
        with open(args.out, "w") as f:
            f.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
