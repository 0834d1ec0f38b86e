"""The agent's Modbus register map for the PLC, generated from one table (:data:`REGISTERS`).

The agent is a Modbus TCP server, unit id 1. CONTRACT section 6 fixes IR0 (map version), IR1
(heartbeat), IR2 (number of drives) and, for drive ``i`` (0-based), the block at
``16 + 16*i`` whose IR+0 is the alarm state and IR+1 the data quality. Everything else here is
this module's choice and is documented in ``docs/registers.md``, which is generated from
:data:`REGISTERS` by ``python -m firmware_if.plc_registers --write docs/registers.md``
(a test checks that the committed file is current).

Layout: IR0..15 global, IR 16+16*i .. 31+16*i drive ``i``; the holding registers mirror that
layout, with commands at HR 16+16*i + 0/1. Every register from 0 up to the end of the last
drive block is readable in both tables (reserved ones read 0) so a PLC can read any span in one
request; only the command registers accept writes, any other write gets exception 2.
Map version 2 adds, without moving anything of version 1, an *evidence block* per drive at IR
``EVIDENCE_BASE + 16*i`` (4112 + 16*i): learning progress, the alarm's path and reason, and the
alarm evidence of each family as a trend (docs/method.md, "Alarms").
"""

from __future__ import annotations

from firmware_if.modbus_map import (RegisterDef, check_layout, decode_block, encode_block, legacy,
                                    markdown_table, render_main)

MAP_VERSION = 2
DEVICE_ID = 1
GLOBAL_REGS = 16
DRIVE_BASE = 16
DRIVE_STRIDE = 16
MAX_DRIVES = 256
EVIDENCE_BASE = DRIVE_BASE + DRIVE_STRIDE * MAX_DRIVES  #: 4112: evidence block of drive 0 (input registers)
#: ALARM_PATH codes: what raised the current caution/warning
PATH_CODES = {"none": 0, "gross": 1, "cusum": 2}
#: EVIDENCE_* rows: the family each reports (CUSUM / threshold of its strongest feature)
EVIDENCE_FAMILIES = {"EVIDENCE_GEAR_DRIVING": "gear_driving", "EVIDENCE_GEAR_DRIVEN": "gear_driven",
                     "EVIDENCE_CHAIN": "chain", "EVIDENCE_CLUSTER": "cluster"}

#: Alarm and quality codes (CONTRACT section 6; equal to ``protocols.base`` STATE_CODES/QUALITY_CODES).
STATE_CODES = {"normal": 0, "caution": 1, "warning": 2}
QUALITY_CODES = {"good": 0, "no_model": 1, "learning": 2, "stale": 3, "bad_input": 4}
#: Command register values.
CMD_IDLE = 0
CMD_REQUEST = 1

_STATES = ", ".join(f"{v} {k}" for k, v in STATE_CODES.items())
_QUALITIES = ", ".join(f"{v} {k}" for k, v in QUALITY_CODES.items())
_NA16 = 0xFFFF
_NA_I16 = -0x8000

#: The one table. Rows with ``block="drive"`` give the offset inside drive i's block at
#: ``DRIVE_BASE + DRIVE_STRIDE*i``; the others are absolute.
REGISTERS: tuple[RegisterDef, ...] = (
    # ---- global input registers
    RegisterDef("MAP_VERSION", "IR", 0, description=f"Register-map version ({MAP_VERSION})."),
    RegisterDef("HEARTBEAT", "IR", 1,
                description="+1 at least once a second while the agent lives; wraps 65535 -> 0."),
    RegisterDef("DRIVE_COUNT", "IR", 2, description="Number of drives (blocks at 16 + 16*i)."),
    RegisterDef("SUMMARY_STATE", "IR", 3, description=f"Worst alarm state over all drives: {_STATES}."),
    RegisterDef("DRIVES_NOT_GOOD", "IR", 4, description="Number of drives whose quality is not good."),
    RegisterDef("AGENT_TIME", "IR", 6, "UINT32", unit="s", description="Agent clock, Unix time (updated with the heartbeat)."),
    RegisterDef("UPTIME", "IR", 8, "UINT32", unit="s", description="Seconds since the Modbus server started."),
    RegisterDef("HEARTBEAT_PERIOD", "IR", 10, unit="ms", description="Heartbeat period."),
    # ---- per-drive input registers (offsets in the drive block)
    RegisterDef("STATE", "IR", 0, block="drive", description=f"Alarm state: {_STATES}."),
    RegisterDef("QUALITY", "IR", 1, block="drive", description=f"Data quality: {_QUALITIES}."),
    RegisterDef("SPECTRUM_STATE", "IR", 2, block="drive", description=f"Residual-spectrum verdict: {_STATES}."),
    RegisterDef("CLUSTER_STATE", "IR", 3, block="drive", description=f"Parameter-cluster verdict: {_STATES}."),
    RegisterDef("ALARM_ACKED", "IR", 4, block="drive",
                description="1 when the current caution/warning has been acknowledged (HR ACK); "
                            "0 when normal or when the state rose since the acknowledgement."),
    RegisterDef("FE", "IR", 5, "UINT16", scale=0.01, unit="Hz", block="drive", na=_NA16,
                description="Electrical frequency of the window."),
    RegisterDef("LOAD", "IR", 6, "INT16", scale=0.1, unit="%", block="drive", na=_NA_I16,
                description="Load, percent of rated torque."),
    RegisterDef("DATA_AGE", "IR", 7, unit="ms", block="drive",
                description="Time since this drive's last update, refreshed with the heartbeat; "
                            "saturates at 65535 (also: never updated)."),
    RegisterDef("UPDATE_TIME", "IR", 8, "UINT32", unit="s", block="drive",
                description="Unix time of the analysed window's end."),
    RegisterDef("WINDOW", "IR", 10, "UINT32", block="drive", description="Windows analysed (wraps at 2^32)."),
    RegisterDef("PEAK_FREQ", "IR", 12, "UINT16", scale=0.1, unit="Hz", block="drive",
                description="Frequency of the worst fault line (largest magnitude/caution threshold); 0 = none."),
    RegisterDef("PEAK_RATIO", "IR", 13, "UINT16", scale=0.01, block="drive",
                description="Worst fault line's magnitude / its caution threshold (>= 1 flagged); 0 = none."),
    RegisterDef("MODEL_ID", "IR", 14, block="drive",
                description="Scheduled baseline model: CRC-16/MODBUS of its id string; 0 = none."),
    RegisterDef("UPDATE_COUNT", "IR", 15, block="drive", description="+1 per status update of this drive (wraps)."),
    # ---- per-drive evidence block (input registers at EVIDENCE_BASE + 16*i)
    RegisterDef("LEARN_PROGRESS", "IR", 0, scale=0.1, unit="%", block="evidence",
                description="Progress of the baseline being learned (quality 2); 0 when not learning."),
    RegisterDef("ALARM_PATH", "IR", 1, block="evidence",
                description="What raised the alarm: 0 none, 1 gross fault (one window), 2 slow wear (accumulated evidence)."),
    RegisterDef("SETTLING", "IR", 2, block="evidence",
                description="1 while an operating-point change holds the decision (settling guard), else 0."),
    *(RegisterDef(name, "IR", 3 + j, scale=0.001, block="evidence",
                  description=f"Evidence of the {fam.replace('_', ' ')}: accumulated evidence / caution threshold "
                              "(1.000 = caution); a trend to plot, 0 when none.")
      for j, (name, fam) in enumerate(EVIDENCE_FAMILIES.items())),
    RegisterDef("REASON_FREQ", "IR", 7, scale=0.1, unit="Hz", block="evidence",
                description="Lower line of the feature behind the alarm; 0 = none (or the parameter cluster)."),
    RegisterDef("REASON_SCORE", "IR", 8, "INT16", scale=0.01, block="evidence",
                description="Gross path: the window's z (threshold 8); slow path: evidence / threshold; 0 = none."),
    # ---- per-drive command holding registers
    RegisterDef("ACK", "HR", 0, access="RW", block="drive",
                description="Write 1: acknowledge the drive's current alarm (see ALARM_ACKED). "
                            "The agent sets it back to 0 when taken."),
    RegisterDef("RELEARN", "HR", 1, access="RW", block="drive",
                description="Write 1: relearn the drive's present operating point (the new baseline replaces "
                            "the one that covers it; QUALITY reads 2 while learning). Stays 1 until the agent has "
                            "taken the request, then 0. Refused while the drive reads as faulty (a fault would be "
                            "learned as healthy): QUALITY stays 0, the journal has the reason; relearn after a "
                            "repair with `pmsm-agent learn --replace`."),
)
check_layout(REGISTERS)
BY_NAME = {d.name: d for d in REGISTERS}
GLOBAL_IR = tuple(d for d in REGISTERS if d.block == "" and d.table == "IR")
DRIVE_IR = tuple(d for d in REGISTERS if d.block == "drive" and d.table == "IR")
DRIVE_HR = tuple(d for d in REGISTERS if d.block == "drive" and d.table == "HR")
EVIDENCE_IR = tuple(d for d in REGISTERS if d.block == "evidence")
COMMANDS = {"ACK": "acknowledge", "RELEARN": "relearn"}  #: command register -> command kind


def drive_base(i: int) -> int:
    """First register of drive ``i``'s block (both tables)."""
    if not 0 <= i < MAX_DRIVES:
        raise ValueError(f"drive index {i} outside 0..{MAX_DRIVES - 1}")
    return DRIVE_BASE + DRIVE_STRIDE * i


def evidence_base(i: int) -> int:
    """First input register of drive ``i``'s evidence block."""
    return drive_base(i) - DRIVE_BASE + EVIDENCE_BASE


def address(name: str, drive: int | None = None) -> int:
    """0-based wire address of ``name`` (``drive`` required for per-drive rows)."""
    d = BY_NAME[name]
    if d.block:
        if drive is None:
            raise ValueError(f"{name} is a per-drive register: give drive=")
        return (drive_base(drive) if d.block == "drive" else evidence_base(drive)) + d.address
    return d.address


def table_size(n_drives: int) -> int:
    """Registers 0 .. table_size-1 exist in both IR and HR."""
    return DRIVE_BASE + DRIVE_STRIDE * n_drives


def command_addresses(n_drives: int) -> dict[int, tuple[int, str]]:
    """Writable HR address -> (drive index, command kind)."""
    return {drive_base(i) + d.address: (i, COMMANDS[d.name]) for i in range(n_drives) for d in DRIVE_HR}


def encode_global(values: dict) -> list[int]:
    """IR0..15 from ``{row name: physical value}`` (missing rows 0)."""
    return encode_block(GLOBAL_IR, values, GLOBAL_REGS)


def encode_drive(values: dict) -> list[int]:
    """The 16 input registers of one drive block from ``{row name: physical value}``."""
    return encode_block(DRIVE_IR, values, DRIVE_STRIDE)


def encode_evidence(values: dict) -> list[int]:
    """The 16 input registers of one evidence block from ``{row name: physical value}``."""
    return encode_block(EVIDENCE_IR, values, DRIVE_STRIDE)


def decode_evidence(regs) -> dict:
    return decode_block(EVIDENCE_IR, regs)


def decode_global(regs) -> dict:
    return decode_block(GLOBAL_IR, regs)


def decode_drive(regs) -> dict:
    """16 registers of a drive block -> ``{row name: physical value}`` (NaN for n/a)."""
    return decode_block(DRIVE_IR, regs)


def crc16_modbus(data: bytes) -> int:
    """CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF)."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def model_id(model: str) -> int:
    """MODEL_ID register value of a model id string (0 for none; never 0 otherwise)."""
    if not model:
        return 0
    return crc16_modbus(model.encode()) or 1


# ---------------------------------------------------------------------------------- docs / C

def render_markdown() -> str:
    """``docs/registers.md``: the PLC map with wire and legacy addresses."""
    example = "\n".join(
        f"| {i} | {drive_base(i)}..{drive_base(i) + DRIVE_STRIDE - 1} | "
        f"{legacy('IR', drive_base(i))}..{legacy('IR', drive_base(i) + DRIVE_STRIDE - 1)} | "
        f"{legacy('HR', drive_base(i))}..{legacy('HR', drive_base(i) + DRIVE_STRIDE - 1)} |"
        for i in range(3))
    return "\n".join([
        "# PLC register map",
        "",
        "Generated from `firmware_if/plc_registers.py` by",
        "`python -m firmware_if.plc_registers --write docs/registers.md`; do not edit by hand",
        "(`tests/test_registers.py` fails when this file is stale).",
        "",
        f"The agent is a Modbus TCP server, unit id {DEVICE_ID}. Map version {MAP_VERSION}.",
        "",
        "* **address** is the 0-based wire address (the PDU address); **legacy** is the 1-based",
        "  notation 30001 + address (input registers) / 40001 + address (holding registers).",
        "* 32-bit values take two registers, high word first, big-endian bytes (`ABCD`), on even addresses.",
        "* `physical = raw * scale`. Scaled values are rounded and saturate at the type's limits;",
        "  an unavailable value (NaN) reads as the row's n/a raw value.",
        "* Alarm states: " + _STATES + ". Data quality (separate from the alarm): " + _QUALITIES + ".",
        f"* Registers 0 .. {DRIVE_BASE - 1} + {DRIVE_STRIDE}·(number of drives) exist in both tables; reserved",
        "  ones read 0, addresses past the last drive block give exception 2 (illegal data address),",
        f"  except the input registers of the evidence blocks from {EVIDENCE_BASE}.",
        "* Only the command holding registers (ACK, RELEARN) accept writes; any other write gets exception 2.",
        "  A command register accepts 0 or 1 (other values: exception 3).",
        "* One request at a time per connection: the server (pymodbus 3.16) answers only the first of",
        "  several requests sent without waiting for the replies (pipelined). A PLC must wait for each",
        "  reply (the usual Modbus TCP client behaviour), or open one connection per concurrent request.",
        "* Heartbeat: IR1 advances at least once a second while the agent runs, also when a drive's",
        "  data is stale (then QUALITY = 3 and DATA_AGE grows). A PLC watchdog should alarm when",
        "  IR1 has not changed for a few seconds.",
        "",
        "## Global input registers",
        "",
        markdown_table(GLOBAL_IR),
        "",
        f"IR5 and IR11..{GLOBAL_REGS - 1} are reserved (read 0). HR0..{GLOBAL_REGS - 1} are reserved "
        "(read 0, writes give exception 2).",
        "",
        "## Drive block",
        "",
        "Drive i (0-based, in the order of the agent's configuration) has the registers",
        f"{DRIVE_BASE} + {DRIVE_STRIDE}·i + offset in both tables:",
        "",
        "| drive | wire addresses | legacy IR | legacy HR |",
        "|---|---|---|---|",
        example,
        "",
        "The address columns give drive 0's registers; add 16·i for drive i.",
        "",
        markdown_table(DRIVE_IR + DRIVE_HR, base=drive_base(0), offset_column=True),
        "",
        "Holding-register offsets +2..+15 are reserved (read 0, writes give exception 2).",
        "",
        "## Evidence block (map version 2)",
        "",
        f"Drive i has input registers {EVIDENCE_BASE} + {DRIVE_STRIDE}·i + offset "
        f"({legacy('IR', EVIDENCE_BASE)} + 16·i in the legacy notation) that say why the drive is in",
        "alarm and how close each family is to one. The EVIDENCE_* rows are trends for SCADA: 1.000",
        "is the caution threshold of the slow-wear evidence (docs/method.md, \"Alarms\").",
        "Offsets +9..+15 are reserved (read 0). The block is written together with the drive block.",
        "",
        markdown_table(EVIDENCE_IR, base=EVIDENCE_BASE, offset_column=True),
        "",
        "Each drive block is written in one piece per update, so a PLC that reads the 16 input",
        "registers of a block in one request always sees one consistent status. Before the agent's",
        "first update of a drive its block reads STATE 0, QUALITY 3 (stale), FE and LOAD n/a and",
        "DATA_AGE 65535. Unit ids other than 1 are not served (pymodbus 3.16 answers exception 4).",
        "",
    ])


def c_defines() -> dict[str, int]:
    """C ``#define`` constants of the PLC map (also registered with :mod:`firmware_if.c_header`
    as section ``plc_registers``). Per-drive rows are offsets in the drive block."""
    out = {"PMSM_PLC_MAP_VERSION": MAP_VERSION, "PMSM_PLC_DEVICE_ID": DEVICE_ID,
           "PMSM_PLC_GLOBAL_REGS": GLOBAL_REGS, "PMSM_PLC_DRIVE_BASE": DRIVE_BASE,
           "PMSM_PLC_DRIVE_STRIDE": DRIVE_STRIDE, "PMSM_PLC_MAX_DRIVES": MAX_DRIVES,
           "PMSM_PLC_CMD_IDLE": CMD_IDLE, "PMSM_PLC_CMD_REQUEST": CMD_REQUEST}
    out["PMSM_PLC_EVIDENCE_BASE"] = EVIDENCE_BASE
    for d in REGISTERS:
        kind = {"drive": "DRV_", "evidence": "EVD_"}.get(d.block, "")
        out[f"PMSM_PLC_{kind}{d.table}_{d.name}"] = d.address
    for k, v in STATE_CODES.items():
        out[f"PMSM_PLC_STATE_{k.upper()}"] = v
    for k, v in QUALITY_CODES.items():
        out[f"PMSM_PLC_QUALITY_{k.upper()}"] = v
    return out


def _register_c_header() -> None:
    from firmware_if.c_header import Define, register_section
    comments = {f"PMSM_PLC_{ {'drive': 'DRV_', 'evidence': 'EVD_'}.get(d.block, '')}{d.table}_{d.name}":
                f"{d.table}{' +offset' if d.block else ''} {d.type}"
                f"{' x' + format(d.scale, 'g') if d.scale != 1 else ''}"
                f"{' ' + d.unit if d.unit else ''}: {d.description}" for d in REGISTERS}
    register_section(
        "plc_registers",
        comment="agent -> PLC Modbus TCP map (0-based addresses; drive i block at "
                "PMSM_PLC_DRIVE_BASE + PMSM_PLC_DRIVE_STRIDE*i; 32-bit values ABCD)",
        defines=[Define(k, v, comments.get(k, "")) for k, v in c_defines().items()],
        code="#define PMSM_PLC_DRIVE_REG(i, offset) "
             "(PMSM_PLC_DRIVE_BASE + PMSM_PLC_DRIVE_STRIDE * (uint32_t)(i) + (uint32_t)(offset))",
        order=40)


_register_c_header()


def main(argv: list[str] | None = None) -> int:
    return render_main(render_markdown, argv, prog="python -m firmware_if.plc_registers",
                       description="Render the PLC register map to Markdown (docs/registers.md).")


if __name__ == "__main__":
    raise SystemExit(main())
