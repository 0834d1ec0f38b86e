"""The drive's Modbus capture buffer: the snapshot protocol, defined once.

The drive (Modbus server, default unit id 1) records a *snapshot*: ``N`` consecutive samples of
the six channels ``va vb vc ia ib ic`` as int16, ``physical = raw * scale[c]`` (V or A per
LSB, FLOAT32 per channel). The agent (Modbus client) runs this sequence:

1. write ``REQ_COUNT`` (HR0..1) and ``COMMAND`` = ``TRIGGER`` (HR2) in one FC16 request
   (HR0..2); the drive checks ``1 <= N <= CAPACITY`` (else ``STATUS=ERROR``,
   ``ERROR=BAD_COUNT``), resets ``WINDOW_START`` to 0 and goes ``CAPTURING`` (or ``ARMED``
   first for ``COMMAND=ARM``: capture at the drive's own trigger condition);
2. poll the 32-register header (IR0..31, one FC4 request) until ``STATUS=READY`` with a new
   ``SEQ`` (or ``ERROR``);
3. read the samples: the sample window IR1024.. shows ``WINDOW_SAMPLES`` samples starting at
   sample ``WINDOW_START``, **channel-interleaved**: sample ``WINDOW_START + k``, channel ``c``
   is at ``SAMPLE_BASE + 6*k + c``. Read in chunks of at most 125 registers (default 120 =
   20 whole samples); for ``N > WINDOW_SAMPLES`` write ``WINDOW_START`` (HR4..5, FC16) before
   each further window. Registers past ``COUNT`` read 0;
4. re-read the header: still ``READY`` with the same ``SEQ`` (else discard the snapshot);
5. write ``COMMAND=RELEASE``: the drive may overwrite the buffer, ``STATUS=IDLE``.

Why interleaved: the drive's ADC/DMA produces one 6-channel frame per sample, a chunk holds
whole samples, and a partial read is still time-aligned across channels.
Why a window: the Modbus address space (65536 registers) holds at most ~10 900 six-channel
samples, less than a second at 25 kS/s; the window pages through any ``CAPACITY``.

Writes outside ``REQ_COUNT``/``COMMAND``/``WINDOW_START`` get exception 2 (illegal address),
an unknown command or an out-of-range window exception 3 (illegal value).

``python -m firmware_if.modbus_capture --write docs/modbus_capture.md`` writes the
documentation generated from :data:`REGISTERS`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from firmware_if.modbus_map import (RegisterDef, check_layout, decode_block, encode_block, markdown_table,
                                    render_main)

LAYOUT_VERSION = 1
DEVICE_ID = 1  #: default unit id of the drive
CHANNELS = ("va", "vb", "vc", "ia", "ib", "ic")
N_CHANNELS = len(CHANNELS)
UNITS = ("V", "V", "V", "A", "A", "A")
MAX_READ_REGS = 125  #: Modbus limit for FC3/FC4
CHUNK_REGS = 120  #: default read size: 20 whole samples
HEADER_REGS = 32
HR_REGS = 16
SAMPLE_BASE = 1024
WINDOW_SAMPLES = 10_000
WINDOW_REGS = WINDOW_SAMPLES * N_CHANNELS


RATE_TOLERANCE = 1e-6  #: relative: a header's RATE (float32) against the profile's sampling.rate_hz

class Status(IntEnum):
    IDLE = 0
    ARMED = 1
    CAPTURING = 2
    READY = 3
    ERROR = 4


class Command(IntEnum):
    NONE = 0
    TRIGGER = 1  #: capture now
    ARM = 2  #: capture at the drive's own trigger condition
    RELEASE = 3  #: the agent has read the snapshot; back to IDLE
    RESET = 4  #: abort / clear ERROR; back to IDLE


class CaptureError(IntEnum):
    NONE = 0
    BAD_COUNT = 1  #: REQ_COUNT is 0 or above CAPACITY
    OVERRUN = 2  #: the drive could not keep up (samples lost)
    HARDWARE = 3  #: ADC / measurement fault
    ABORTED = 4  #: capture aborted by RESET or a drive event


_STATUS_TXT = ", ".join(f"{s.value} {s.name.lower()}" for s in Status)
_CMD_TXT = ", ".join(f"{c.value} {c.name.lower()}" for c in Command)
_ERR_TXT = ", ".join(f"{e.value} {e.name.lower()}" for e in CaptureError)

#: The capture buffer's register map (drive = Modbus server).
REGISTERS: tuple[RegisterDef, ...] = (
    # --- holding registers: written by the agent
    RegisterDef("REQ_COUNT", "HR", 0, "UINT32", unit="samples", access="RW",
                description="Samples per channel to capture, 1..CAPACITY."),
    RegisterDef("COMMAND", "HR", 2, access="RW",
                description=f"Command: {_CMD_TXT}. Reads 0 once the drive has taken it; "
                            "other values -> exception 3."),
    RegisterDef("WINDOW_START", "HR", 4, "UINT32", unit="samples", access="RW",
                description="Index of the sample shown at SAMPLE_BASE; set to 0 by trigger/arm; "
                            ">= CAPACITY -> exception 3."),
    # --- input registers: the header (one 32-register read)
    RegisterDef("LAYOUT_VERSION", "IR", 0, description=f"Capture map version ({LAYOUT_VERSION})."),
    RegisterDef("STATUS", "IR", 1, description=f"Capture state: {_STATUS_TXT}."),
    RegisterDef("ERROR", "IR", 2, description=f"Why STATUS is error: {_ERR_TXT}."),
    RegisterDef("SEQ", "IR", 3, description="Capture counter, +1 each time a capture becomes ready (wraps at 65535)."),
    RegisterDef("COUNT", "IR", 4, "UINT32", unit="samples",
                description="Samples per channel in the ready capture."),
    RegisterDef("RATE", "IR", 6, "FLOAT32", unit="Hz", description="Sample rate."),
    RegisterDef("FIRST_SAMPLE", "IR", 8, "UINT32", unit="samples",
                description="Drive sample counter at the capture's first sample (wraps at 2^32)."),
    RegisterDef("CAPACITY", "IR", 10, "UINT32", unit="samples", description="Largest REQ_COUNT."),
    RegisterDef("CHANNELS", "IR", 12, description=f"Channels per sample ({N_CHANNELS}: "
                                                  + " ".join(CHANNELS) + ")."),
    RegisterDef("WINDOW_SAMPLES", "IR", 13, unit="samples",
                description=f"Samples shown in the sample window ({WINDOW_SAMPLES})."),
    RegisterDef("WINDOW_START_ECHO", "IR", 14, "UINT32", unit="samples",
                description="WINDOW_START currently shown."),
    *(RegisterDef(f"SCALE_{c.upper()}", "IR", 16 + 2 * i, "FLOAT32", unit=f"{u}/LSB",
                  description=f"Scale of channel {c}: {c} = raw * scale.")
      for i, (c, u) in enumerate(zip(CHANNELS, UNITS))),
    # --- the sample window
    RegisterDef("SAMPLES", "IR", SAMPLE_BASE, "INT16", count=WINDOW_REGS, unit="LSB",
                description="Sample window, channel-interleaved: sample WINDOW_START+k, channel c "
                            "(0..5 = va vb vc ia ib ic) at SAMPLE_BASE + 6k + c. Read <= 125 per request."),
)
check_layout(REGISTERS)
BY_NAME = {d.name: d for d in REGISTERS}
HEADER_DEFS = tuple(d for d in REGISTERS if d.table == "IR" and d.end <= HEADER_REGS)
HR_DEFS = tuple(d for d in REGISTERS if d.table == "HR")
HR_WRITABLE = frozenset(a for d in HR_DEFS for a in range(d.address, d.end))  #: writable HR addresses


def address(name: str) -> int:
    """0-based wire address of a register by name."""
    return BY_NAME[name].address


@dataclass(frozen=True)
class CaptureHeader:
    """The decoded header IR0..31."""

    status: int = Status.IDLE
    error: int = CaptureError.NONE
    seq: int = 0
    count: int = 0
    rate_hz: float = 0.0
    first_sample: int = 0
    capacity: int = 0
    n_channels: int = N_CHANNELS
    window_samples: int = WINDOW_SAMPLES
    window_start: int = 0
    scales: tuple[float, ...] = (1.0,) * N_CHANNELS
    version: int = LAYOUT_VERSION

    def registers(self) -> list[int]:
        """The 32 header registers."""
        vals = {"LAYOUT_VERSION": self.version, "STATUS": int(self.status), "ERROR": int(self.error),
                "SEQ": self.seq & 0xFFFF, "COUNT": self.count, "RATE": self.rate_hz,
                "FIRST_SAMPLE": self.first_sample & 0xFFFFFFFF, "CAPACITY": self.capacity,
                "CHANNELS": self.n_channels, "WINDOW_SAMPLES": self.window_samples,
                "WINDOW_START_ECHO": self.window_start,
                **{f"SCALE_{c.upper()}": s for c, s in zip(CHANNELS, self.scales)}}
        return encode_block(HEADER_DEFS, vals, HEADER_REGS)

    def problem(self, count: int, rate_hz: float = 0.0) -> tuple[str, str] | None:
        """(register, why) a READY header cannot describe the snapshot of ``count`` samples that
        was asked for at ``rate_hz`` (the drive profile's; 0: not checked), or None when it can. A
        header is checked like any other frame: a NaN, negative or infinite scale would turn into
        NaN or sign-flipped phase samples."""
        bad_scale = next((c for c, x in zip(CHANNELS, self.scales) if not (math.isfinite(x) and x > 0)), None)
        checks = (
            ("LAYOUT_VERSION", self.version != LAYOUT_VERSION,
             f"unknown layout version {self.version} (this agent reads {LAYOUT_VERSION})"),
            ("CHANNELS", self.n_channels != N_CHANNELS, f"CHANNELS = {self.n_channels}, the layout has {N_CHANNELS}"),
            ("COUNT", self.count != count, f"COUNT = {self.count}, {count} were asked for"),
            ("CAPACITY", self.count > self.capacity, f"COUNT = {self.count} is beyond CAPACITY = {self.capacity}"),
            ("WINDOW_SAMPLES", self.window_samples < 1, f"WINDOW_SAMPLES = {self.window_samples}"),
            ("RATE", not (math.isfinite(self.rate_hz) and self.rate_hz > 0),
             f"RATE = {self.rate_hz:g} Hz is not a positive finite rate"),
            ("RATE", bool(rate_hz) and abs(self.rate_hz - rate_hz) > RATE_TOLERANCE * rate_hz,
             f"RATE = {self.rate_hz:.9g} Hz disagrees with the profile's sampling.rate_hz = {rate_hz:.9g} Hz"),
            (f"SCALE_{(bad_scale or '').upper()}", bad_scale is not None,
             f"SCALE_{(bad_scale or '').upper()} = {self.scales[CHANNELS.index(bad_scale)] if bad_scale else 0:g} "
             f"is not a positive finite scale"),
        )
        return next(((reg, why) for reg, bad, why in checks if bad), None)

    @classmethod
    def from_registers(cls, regs) -> CaptureHeader:
        """The header from its registers; ``ValueError`` for a reply shorter than the header."""
        if len(regs) < HEADER_REGS:
            raise ValueError(f"short header reply: {len(regs)} of {HEADER_REGS} registers")
        v = decode_block(HEADER_DEFS, regs)
        return cls(status=v["STATUS"], error=v["ERROR"], seq=v["SEQ"], count=v["COUNT"], rate_hz=v["RATE"],
                   first_sample=v["FIRST_SAMPLE"], capacity=v["CAPACITY"], n_channels=v["CHANNELS"],
                   window_samples=v["WINDOW_SAMPLES"], window_start=v["WINDOW_START_ECHO"],
                   scales=tuple(float(v[f"SCALE_{c.upper()}"]) for c in CHANNELS), version=v["LAYOUT_VERSION"])


def trigger_registers(count: int, command: Command = Command.TRIGGER) -> list[int]:
    """HR0..2 for the FC16 request that starts a capture of ``count`` samples."""
    return [(count >> 16) & 0xFFFF, count & 0xFFFF, int(command)]


def u32_registers(value: int) -> list[int]:
    """A UINT32 as two registers, high word first (for ``WINDOW_START``)."""
    return [(value >> 16) & 0xFFFF, value & 0xFFFF]


def float32_round(x) -> np.ndarray:
    """Values as the drive stores them in FLOAT32 registers, back in float64."""
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def quantize(x: np.ndarray, scales) -> np.ndarray:
    """Physical ``(6, N)`` -> int16 ``(6, N)``: round to nearest (ties to even), saturate."""
    s = float32_round(scales)[:, None]
    return np.clip(np.rint(np.asarray(x, dtype=np.float64) / s), -32768, 32767).astype(np.int16)


def to_physical(raw: np.ndarray, scales) -> np.ndarray:
    """int16 ``(6, N)`` -> float64 ``(6, N)`` in V / A: ``raw * float64(float32(scale))``."""
    return raw.astype(np.float64) * float32_round(scales)[:, None]


def interleave(raw: np.ndarray) -> np.ndarray:
    """int16 ``(6, N)`` -> the flat uint16 register image (sample-major, channel-minor)."""
    return np.ascontiguousarray(np.asarray(raw, dtype=np.int16).T).reshape(-1).view(np.uint16)


def deinterleave(regs, n: int) -> np.ndarray:
    """Flat register values (``6*n``) -> int16 ``(6, n)``."""
    a = np.asarray(regs, dtype=np.uint16)[:N_CHANNELS * n]
    return a.view(np.int16).reshape(n, N_CHANNELS).T.copy()


def read_plan(count: int, chunk_regs: int = CHUNK_REGS,
              window_samples: int = WINDOW_SAMPLES) -> list[tuple[int, list[tuple[int, int]]]]:
    """The requests that read a capture of ``count`` samples.

    A list of ``(window_start, [(address, n_registers), ...])``: for each window, the FC4
    reads (each <= ``chunk_regs`` <= 125 registers) after setting ``WINDOW_START``.
    """
    if not 1 <= chunk_regs <= MAX_READ_REGS:
        raise ValueError(f"chunk_regs must be 1..{MAX_READ_REGS}, got {chunk_regs}")
    plan = []
    for start in range(0, count, window_samples):
        nregs = N_CHANNELS * min(window_samples, count - start)
        plan.append((start, [(SAMPLE_BASE + o, min(chunk_regs, nregs - o)) for o in range(0, nregs, chunk_regs)]))
    return plan


# ---------------------------------------------------------------------------------- docs / C

def render_markdown() -> str:
    """The capture map as Markdown (generated; see ``docs/modbus_capture.md``)."""
    hr = [d for d in REGISTERS if d.table == "HR"]
    ir = [d for d in REGISTERS if d.table == "IR"]
    return "\n".join([
        "# Drive capture buffer (Modbus snapshot protocol)",
        "",
        "Generated from `firmware_if/modbus_capture.py` by",
        "`python -m firmware_if.modbus_capture --write docs/modbus_capture.md`; do not edit by hand.",
        "",
        f"The drive is the Modbus server (RTU or TCP, default unit id {DEVICE_ID}); the agent is the client.",
        f"Layout version {LAYOUT_VERSION}. Addresses are 0-based wire addresses; *legacy* is the 1-based",
        "30001/40001 notation (6-digit 300001/400001 above address 9998). 32-bit values: two",
        "registers, high word first, big-endian bytes (`ABCD`). `physical = raw * scale`.",
        "",
        "## Sequence",
        "",
        "1. FC16 HR0..2 = `REQ_COUNT` (N), `COMMAND=1` (trigger): the drive captures N samples.",
        "2. FC4 IR0..31 (header) until `STATUS=3` (ready) with a new `SEQ`, or `STATUS=4` (error).",
        f"3. FC4 reads of at most 125 registers (default {CHUNK_REGS} = {CHUNK_REGS // N_CHANNELS} samples) "
        f"from IR{SAMPLE_BASE};",
        f"   for N > {WINDOW_SAMPLES}, FC16 `WINDOW_START` (HR4..5) = {WINDOW_SAMPLES}, "
        f"{2 * WINDOW_SAMPLES}, ... before each further window.",
        "4. FC4 header again: still ready with the same `SEQ`, else the snapshot is discarded.",
        "5. FC6 `COMMAND=3` (release): `STATUS=0` (idle).",
        "",
        "Sample `WINDOW_START + k`, channel `c` (0..5 = va vb vc ia ib ic) is at wire address",
        f"`{SAMPLE_BASE} + 6k + c`: channel-interleaved, so every 120-register chunk holds 20 whole samples.",
        "",
        "## Holding registers (agent writes)",
        "",
        markdown_table(hr),
        "",
        f"HR0..{HR_REGS - 1} are readable; writes other than the rows above get exception 2.",
        "",
        "## Input registers (drive writes)",
        "",
        markdown_table(ir),
        "",
        f"IR{HEADER_REGS - 4}..{HEADER_REGS - 1} are reserved (read 0). IR{HEADER_REGS}..{SAMPLE_BASE - 1} "
        "are not mapped (exception 2).",
        "",
    ])


def c_defines() -> dict[str, int]:
    """C ``#define`` constants of the capture protocol (also registered with
    :mod:`firmware_if.c_header` as section ``modbus_capture``)."""
    out = {"PMSM_MBCAP_LAYOUT_VERSION": LAYOUT_VERSION, "PMSM_MBCAP_DEVICE_ID": DEVICE_ID,
           "PMSM_MBCAP_N_CHANNELS": N_CHANNELS, "PMSM_MBCAP_MAX_READ_REGS": MAX_READ_REGS,
           "PMSM_MBCAP_CHUNK_REGS": CHUNK_REGS, "PMSM_MBCAP_HEADER_REGS": HEADER_REGS,
           "PMSM_MBCAP_HR_REGS": HR_REGS, "PMSM_MBCAP_SAMPLE_BASE": SAMPLE_BASE,
           "PMSM_MBCAP_WINDOW_SAMPLES": WINDOW_SAMPLES, "PMSM_MBCAP_WINDOW_REGS": WINDOW_REGS}
    for d in REGISTERS:
        out[f"PMSM_MBCAP_{d.table}_{d.name}"] = d.address
    for i, c in enumerate(CHANNELS):
        out[f"PMSM_MBCAP_CH_{c.upper()}"] = i
    for enum in (Status, Command, CaptureError):
        prefix = {"Status": "STATUS", "Command": "CMD", "CaptureError": "ERR"}[enum.__name__]
        for m in enum:
            out[f"PMSM_MBCAP_{prefix}_{m.name}"] = int(m)
    return out


def _register_c_header() -> None:
    from firmware_if.c_header import Define, register_section
    comments = {f"PMSM_MBCAP_{d.table}_{d.name}": f"{d.table} {d.type}: {d.description}" for d in REGISTERS}
    register_section(
        "modbus_capture",
        comment="drive capture buffer over Modbus (0-based register addresses; 32-bit values ABCD)",
        defines=[Define(k, v, comments.get(k, "")) for k, v in c_defines().items()],
        code="/* wire address of sample k (in the window) of channel c */\n"
             "#define PMSM_MBCAP_SAMPLE_REG(k, c) "
             "(PMSM_MBCAP_SAMPLE_BASE + PMSM_MBCAP_N_CHANNELS * (uint32_t)(k) + (uint32_t)(c))",
        order=30)


_register_c_header()


def main(argv: list[str] | None = None) -> int:
    return render_main(render_markdown, argv, prog="python -m firmware_if.modbus_capture",
                       description="Render the drive capture-buffer register map to Markdown.")


if __name__ == "__main__":
    raise SystemExit(main())
