"""The agent config (TOML): drives and their sources, pipeline, Modbus server, zenoh, library, journal.

Read with ``tomllib`` into frozen dataclasses and validated once, at load: unknown keys are
rejected and every error names the key path, e.g. ``drives[0].source.port: must be a string``
(:class:`agent.errors.InputError`, with the file as its source). Every relative path is relative
to the config file, and so is the default ``state_dir``: systemd's $STATE_DIRECTORY, else
``state`` beside the config file. See ``config/agent.toml`` for an annotated example.
"""

from __future__ import annotations

import math
import os
import re
import socket
import typing
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from agent.errors import InputError, read_toml
from agent.evidence import FULL_EVIDENCE_STRETCHES

SCHEMA_VERSION = 1
DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "config" / "agent.toml"
SOURCE_KINDS = ("simulated", "replay", "serial", "can", "modbus", "nidaq")
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")


class _KeyError(Exception):
    """A config error at a key path (turned into ``InputError`` with the file name)."""

    def __init__(self, path: str, message: str):
        super().__init__(f"{path}: {message}" if path else message)


def _opt(default=MISSING, *, gt=None, ge=None, le=None, choices=None, check=None):
    """A dataclass field with validation metadata (bounds, choices, ``check(v) -> message or None``)."""
    meta = {"gt": gt, "ge": ge, "le": le, "choices": choices, "check": check}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda d=default: type(d)(d), metadata=meta)
    return field(default=default, metadata=meta)


def _key_chunk(v: str) -> str | None:
    return None if _CHUNK.match(v) else "use letters, digits, '_', '.', '-' only (one zenoh key chunk)"


def _key_expr(v: str) -> str | None:
    return None if v and all(_CHUNK.match(c) for c in v.split("/")) else \
        "'/'-separated chunks of letters, digits, '_', '.', '-' (no wildcards, no empty chunks)"


def _endpoint(v: str) -> str | None:
    return None if re.match(r"^[a-z0-9]+/\S+$", v) else "a zenoh endpoint like 'tcp/127.0.0.1:7447'"


# --- sources -------------------------------------------------------------------------------------

@dataclass(frozen=True, kw_only=True)
class Phase:
    """One step of a simulated drive's condition schedule."""

    condition: str
    seconds: float = _opt(gt=0, le=30 * 86400)  #: simulated time spent in this condition, s
    load_pct: float | None = _opt(None, ge=0, le=150)  #: overrides the source's ``load_pct``
    severity: float = _opt(1.0, ge=0, le=100)


@dataclass(frozen=True, kw_only=True)
class SimulatedCfg:
    """The project's rig simulator as a live source."""

    kind: str = "simulated"
    schedule: tuple[Phase, ...] = (Phase(condition="healthy", seconds=3600.0),)
    load_pct: float = _opt(80.0, ge=0, le=150)
    speedup: float = _opt(1.0, gt=0, le=10_000)  #: simulated seconds per wall second
    seed: int = _opt(0, ge=0)
    block_s: float = _opt(0.1, gt=0, le=2.0)  #: block length handed to the pipeline, s
    loop: bool = True  #: repeat the schedule; else the source goes stale at its end


@dataclass(frozen=True, kw_only=True)
class ReplayCfg:
    """Recorded files (CSV/NPZ/TDMS, CONTRACT section 3) played back as a live source."""

    kind: str = "replay"
    files: tuple[Path, ...] = _opt()
    speedup: float = _opt(1.0, ge=0, le=10_000)  #: 1 = real time, 0 = as fast as the pipeline takes it
    loop: bool = False
    block_s: float = _opt(0.1, gt=0, le=2.0)


@dataclass(frozen=True, kw_only=True)
class SerialCfg:
    """ADC bridge on a serial port (``protocols.serial_bridge``)."""

    kind: str = "serial"
    port: str = _opt()  #: e.g. /dev/ttyUSB0 or a pyserial URL
    baud: int = _opt(921_600, gt=0, le=20_000_000)
    read_timeout_s: float = _opt(0.2, gt=0, le=60)


@dataclass(frozen=True, kw_only=True)
class CanCfg:
    """Sample frames on CAN / CAN FD (``protocols.can_bus``)."""

    kind: str = "can"
    interface: str = "socketcan"  #: python-can interface name (socketcan, virtual, pcan, ...)
    channel: str = _opt()  #: e.g. can0
    base_id: int = _opt(0x0A500000, ge=0, le=0x1FFFFFFF)  #: first id of the drive's block (firmware_if.can_frame)
    fd: bool = True
    extended: bool = True  #: the sample frames use 29-bit ids
    bitrate: int | None = _opt(None, gt=0, le=10_000_000)  #: only for interfaces that set it (SocketCAN ignores it)
    data_bitrate: int | None = _opt(None, gt=0, le=20_000_000)


@dataclass(frozen=True, kw_only=True)
class ModbusCfg:
    """A drive polled over Modbus TCP (``host``) or RTU (``serial_port``); exactly one of the two."""

    kind: str = "modbus"
    host: str | None = None
    port: int = _opt(502, ge=1, le=65535)
    serial_port: str | None = None
    baud: int = _opt(19_200, gt=0, le=20_000_000)
    unit_id: int = _opt(1, ge=0, le=247)
    address: int = _opt(0, ge=0, le=65535)  #: first register of the drive's sample block
    poll_interval_s: float = _opt(0.1, gt=0, le=3600)
    timeout_s: float = _opt(1.0, gt=0, le=600)


@dataclass(frozen=True, kw_only=True)
class NidaqCfg:
    """NI-DAQmx acquisition (e.g. NI-9244 voltages + NI-9239 shunt voltages in one cDAQ task)."""

    kind: str = "nidaq"
    voltage_channels: str = _opt()  #: e.g. cDAQ1Mod1/ai0:2 (phases a, b, c)
    current_channels: str = _opt()  #: e.g. cDAQ1Mod2/ai0:2
    voltage_range_v: float = _opt(800.0, gt=0, le=2000)
    current_range_v: float = _opt(10.0, gt=0, le=100)
    current_scale_a_per_v: float = _opt(1.0, gt=0, le=1e6)
    rate_hz: float | None = _opt(None, gt=0, le=1e7)  #: default: the profile's sampling.rate_hz
    block_samples: int = _opt(2500, gt=0, le=1_000_000)


SourceCfg = SimulatedCfg | ReplayCfg | SerialCfg | CanCfg | ModbusCfg | NidaqCfg
_SOURCES = dict(zip(SOURCE_KINDS, (SimulatedCfg, ReplayCfg, SerialCfg, CanCfg, ModbusCfg, NidaqCfg)))


@dataclass(frozen=True, kw_only=True)
class DriveCfg:
    name: str = _opt(check=_key_chunk)
    profile: Path = _opt()  #: drive profile TOML (CONTRACT section 4)
    source: SourceCfg = _opt()
    drive_profile: Any = field(default=None, metadata={"derived": True})  #: the loaded ``DriveProfile``


# --- the rest ------------------------------------------------------------------------------------

@dataclass(frozen=True, kw_only=True)
class PipelineCfg:
    window_s: float = _opt(2.0, ge=0.1, le=60)  #: analysis window, s
    hop_s: float = _opt(1.0, ge=0.01, le=60)  #: assessment period, s (divides window_s)
    persist_hops: int = _opt(1, ge=1, le=1000)  #: consecutive assessments needed to raise an alarm level
    alarm_hold_s: float = _opt(10.0, ge=0, le=86400)  #: a raised state is held this long before it may fall
    stale_after_s: float = _opt(3.0, gt=0, le=3600)  #: no input for this long -> quality "stale"
    learn_windows: int = _opt(30, ge=4, le=10000)  #: spans fitting a new baseline's parameters (pass 1)
    learn_stretches: int = _opt(FULL_EVIDENCE_STRETCHES, ge=4, le=100000)  #: stretches of its alarm statistics (pass 2)
    learn_min_s: float = _opt(1200.0, ge=0, le=30 * 86400)  #: s of operation pass 2 covers at least
    stretch_s: float = _opt(30.0, gt=0, le=3600)  #: s of operation per step of the slow-wear evidence
    settle_s: float = _opt(3.0, ge=0, le=3600)  #: s of held decision after the operating-point reading last moved
    false_alarms_per_month: float = _opt(0.1, gt=0, le=100)  #: design budget of the slow-wear path per drive
    gross_false_alarms_per_month: float = _opt(0.1, gt=0, le=100)  #: design budget of the gross path per drive
    auto_learn: bool = True  #: first commissioning: learn once when the drive has no baseline at all
    schedule_fe_tol_hz: float = _opt(2.0, gt=0, le=1000)  #: a baseline applies within this fe distance
    schedule_load_tol_pct: float = _opt(5.0, gt=0, le=100)  #: ... and this load distance (input power, % of rated)
    schedule_hysteresis: float = _opt(0.2, ge=0, le=1)  #: extra fraction of the tolerance to leave a baseline


@dataclass(frozen=True, kw_only=True)
class ModbusServerCfg:
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = _opt(5020, ge=1, le=65535)


@dataclass(frozen=True, kw_only=True)
class ZenohCfg:
    """Zenoh session; multicast scouting and gossip are always off.

    Key space: without ``site``, ``prefix`` is the agent's own prefix (default ``pmsm/<host name>``)
    and each drive publishes on ``<prefix>/<drive>/state``. On a plant's router network set
    ``site``: ``prefix`` is then the plant's root (default ``pmsm``) and the agent's own prefix
    becomes ``<prefix>/<site>/<agent_id>``, so its drives publish on
    ``<root>/<site>/<agent_id>/<drive>/state`` (docs/architecture.md "Plant"). After loading,
    ``prefix`` always holds the agent's own prefix and ``plant_prefix`` the root.
    """

    enabled: bool = True
    mode: str = _opt("peer", choices=("peer", "client", "router"))
    listen: tuple[str, ...] = _opt((), check=_endpoint)
    connect: tuple[str, ...] = _opt((), check=_endpoint)
    prefix: str = _opt("", check=lambda v: None if v == "" else _key_expr(v))  #: see the class docstring
    site: str = _opt("", check=lambda v: None if v == "" else _key_chunk(v))  #: the plant site (one key chunk)
    config_file: Path | None = _opt(None)  #: JSON5 zenoh config read first
    inline: dict = _opt({})  #: extra zenoh keys, ``{"transport/link/tx/lease" = 3000}``
    period_s: float = _opt(1.0, gt=0, le=3600)  #: state republish period, s
    diagnostics_period_s: float = _opt(5.0, gt=0, le=86400)
    retry_initial_s: float = _opt(0.5, gt=0, le=600)  #: client mode, no router answers: first wait, s
    retry_max_s: float = _opt(10.0, gt=0, le=3600)  #: ... doubling up to this, s
    plant_prefix: str = field(default="", metadata={"derived": True})  #: the plant's root (see above)


@dataclass(frozen=True, kw_only=True)
class CommandsCfg:
    """Commands (ACK, RELEARN) over zenoh, signed per role (:mod:`agent.runtime.commands`).

    Off unless enabled; ``key_file`` is a TOML file ``[keys] <role> = "<hex secret>"`` (not
    world-readable). ``acknowledge``/``relearn``: the roles allowed to send each command.
    """

    enabled: bool = False
    key_file: Path | None = _opt(None)
    acknowledge: tuple[str, ...] = _opt(("operator", "engineer"), check=_key_chunk)
    relearn: tuple[str, ...] = _opt(("engineer",), check=_key_chunk)
    max_skew_s: float = _opt(30.0, gt=0, le=3600)  #: a command's time ``t`` may differ this much from ours, s


@dataclass(frozen=True, kw_only=True)
class LibraryCfg:
    path: Path | None = _opt(None)  #: model library directory (default <state_dir>/library)


@dataclass(frozen=True, kw_only=True)
class JournalCfg:
    max_events: int = _opt(100_000, ge=100)
    max_age_days: float = _opt(365.0, gt=0)
    synchronous: str = _opt("FULL", choices=("FULL", "NORMAL"))
    error_holdoff_s: float = _opt(60.0, ge=0)  #: repeats of the same error within this are only counted


#: Resident memory, measured with bench.bench_scale (docs/benchmarks.md, "The agent at plant
#: scale"): the agent's process without drives (zenoh, Modbus server, journal), a DSP worker
#: without drives, and what a drive takes beyond its signal ring and its block queue (source
#: buffers, pipeline state, Python objects).
AGENT_PROCESS_MB = 80.0
WORKER_PROCESS_MB = 50.0
DRIVE_OVERHEAD_MB = 1.5
#: The largest estimate `run --check-config` accepts: config/pmsm-agent.service's MemoryHigh
#: (its MemoryMax is this plus a quarter, the room for the allocator and a leak's first hour).
MEMORY_LIMIT_MB = 1152.0


def memory_estimate(cfg) -> dict:
    """The agent's resident memory for ``cfg``, MB: its process, the DSP workers
    (agent.runtime.workers) and per drive the signal ring and the open windows' residuals (agent.pipeline.ring_bytes), a full
    block queue (float32) and the measured overhead. Returns total_mb, per_drive_mb (the largest)
    and workers."""
    from agent.pipeline import PipelineConfig, ring_bytes
    from agent.runtime.service import QUEUE_BLOCKS
    from agent.runtime.workers import worker_count

    drives = []
    for d in cfg.drives:
        rate = d.drive_profile.sampling.rate_hz
        block = getattr(d.source, "block_s", 0.1) * rate
        ring = ring_bytes(rate, cfg.pipeline.window_s * PipelineConfig().span_windows, cfg.pipeline.window_s,
                          cfg.pipeline.hop_s)
        drives.append((ring + QUEUE_BLOCKS * 6 * block * 4) / 1e6 + DRIVE_OVERHEAD_MB)
    workers = worker_count(cfg)
    total = AGENT_PROCESS_MB + (workers * WORKER_PROCESS_MB if workers > 1 else 0.0) + sum(drives)
    return {"total_mb": total, "per_drive_mb": max(drives, default=0.0), "workers": workers}


def _default_agent_id() -> str:
    return re.sub(r"[^a-z0-9_.\-]+", "-", socket.gethostname().lower()).strip("-.") or "agent"


def _default_state_dir(config_file: Path | None) -> Path:
    """systemd's $STATE_DIRECTORY, else ``state`` beside the config file (else in the working directory)."""
    env = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    if env:
        return Path(env)
    return (config_file.parent if config_file else Path.cwd()).resolve() / "state"


@dataclass(frozen=True, kw_only=True)
class Config:
    schema_version: int = _opt()
    drives: tuple[DriveCfg, ...] = _opt()
    agent_id: str = _opt(None, check=_key_chunk)  #: default: the host name
    state_dir: Path | None = _opt(None)  #: default: $STATE_DIRECTORY, else ``state`` beside the config file
    pipeline: PipelineCfg = PipelineCfg()
    modbus_server: ModbusServerCfg = ModbusServerCfg()
    zenoh: ZenohCfg = ZenohCfg()
    commands: CommandsCfg = CommandsCfg()
    library: LibraryCfg = LibraryCfg()
    journal: JournalCfg = JournalCfg()
    #: DSP processes (agent.runtime.workers): 0 = one per core for more than a few drives,
    #: 1 = the agent's own process; a worker that fails is restarted without the others
    workers: int = _opt(0, ge=0, le=64)
    source: Path | None = field(default=None, metadata={"derived": True})  #: the config file

    def drive(self, name: str) -> DriveCfg:
        for d in self.drives:
            if d.name == name:
                return d
        raise KeyError(name)


# --- the generic builder ------------------------------------------------------------------------

def _type_name(v) -> str:
    return {bool: "boolean", int: "integer", float: "number", str: "string", list: "array",
            dict: "table"}.get(type(v), type(v).__name__)


def _scalar(tp, v, kp: str, base: Path):
    if tp is bool:
        ok = isinstance(v, bool)
    elif tp is int:
        ok = isinstance(v, int) and not isinstance(v, bool)
    elif tp is float:
        ok = isinstance(v, (int, float)) and not isinstance(v, bool)
        if ok:
            v = float(v)
            if not math.isfinite(v):
                raise _KeyError(kp, f"must be finite, got {v}")
    elif tp is str or tp is Path:
        ok = isinstance(v, str) and (tp is str or v != "")
        if ok and tp is Path:
            v = (base / Path(v).expanduser()).resolve()
    elif tp is dict:
        ok = isinstance(v, dict)
    else:
        return _build(tp, v, kp, base)
    if not ok:
        want = {bool: "a boolean", int: "an integer", float: "a number", str: "a string", Path: "a path string",
                dict: "a table"}[tp]
        raise _KeyError(kp, f"must be {want}, got {_type_name(v)} {v!r}")
    return v


def _check(meta, v, kp: str):
    items = [(f"{kp}[{i}]", x) for i, x in enumerate(v)] if isinstance(v, tuple) else [(kp, v)]
    for kp, x in items:
        if meta.get("gt") is not None and not x > meta["gt"]:
            raise _KeyError(kp, f"must be > {meta['gt']}, got {x}")
        if meta.get("ge") is not None and not x >= meta["ge"]:
            raise _KeyError(kp, f"must be >= {meta['ge']}, got {x}")
        if meta.get("le") is not None and not x <= meta["le"]:
            raise _KeyError(kp, f"must be <= {meta['le']}, got {x}")
        if meta.get("choices") and x not in meta["choices"]:
            raise _KeyError(kp, f"must be one of {', '.join(map(repr, meta['choices']))}, got {x!r}")
        if meta.get("check") and (msg := meta["check"](x)):
            raise _KeyError(kp, f"{x!r}: {msg}")


def _value(tp, v, kp: str, base: Path):
    if typing.get_origin(tp) in (typing.Union, type(int | None)):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) > 1:  # the source union: discriminated by "kind"
            return _source(v, kp, base)
        tp = args[0]
    if typing.get_origin(tp) is tuple:
        if not isinstance(v, list):
            raise _KeyError(kp, f"must be an array, got {_type_name(v)} {v!r}")
        return tuple(_scalar(typing.get_args(tp)[0], x, f"{kp}[{i}]", base) for i, x in enumerate(v))
    return _scalar(tp, v, kp, base)


def _source(v, kp: str, base: Path):
    if not isinstance(v, dict):
        raise _KeyError(kp, f"must be a table, got {_type_name(v)}")
    kind = v.get("kind")
    if kind not in _SOURCES:
        raise _KeyError(f"{kp}.kind", f"must be one of {', '.join(SOURCE_KINDS)}, got {kind!r}"
                        if kind is not None else f"missing (one of {', '.join(SOURCE_KINDS)})")
    return _build(_SOURCES[kind], v, kp, base)


def _build(cls, table, kp: str, base: Path):
    """``table`` -> ``cls`` with every key checked; ``kp`` is the key path of ``table``."""
    if not isinstance(table, dict):
        raise _KeyError(kp, f"must be a table, got {_type_name(table)} {table!r}")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in fields(cls) if not f.metadata.get("derived")}
    dot = f"{kp}." if kp else ""
    for key in table:
        if key not in known:
            raise _KeyError(f"{dot}{key}", f"unknown key (known here: {', '.join(known)})")
    values = {}
    for name, f in known.items():
        if name not in table:
            if f.default is MISSING and f.default_factory is MISSING:
                raise _KeyError(f"{dot}{name}", "missing")
            continue
        v = _value(hints[name], table[name], f"{dot}{name}", base)
        if v is not None:
            _check(f.metadata, v, f"{dot}{name}")
        values[name] = v
    return cls(**values)


# --- cross-key checks ---------------------------------------------------------------------------

def _validate(cfg: Config) -> Config:
    if cfg.schema_version != SCHEMA_VERSION:
        raise _KeyError("schema_version", f"this agent reads version {SCHEMA_VERSION}, got {cfg.schema_version}")
    if not cfg.drives:
        raise _KeyError("drives", "at least one [[drives]] table is needed")
    seen, drives = set(), []
    for i, d in enumerate(cfg.drives):
        kp = f"drives[{i}]"
        if d.name in seen:
            raise _KeyError(f"{kp}.name", f"duplicate drive name {d.name!r}")
        if d.name == "agent":
            raise _KeyError(f"{kp}.name", "'agent' is reserved (zenoh key <prefix>/agent/...)")
        seen.add(d.name)
        drives.append(replace(d, drive_profile=_load_profile(d, kp)))
        _validate_source(drives[-1], f"{kp}.source")
    p = cfg.pipeline
    if p.hop_s > p.window_s:
        raise _KeyError("pipeline.hop_s", f"must be <= pipeline.window_s ({p.window_s}), got {p.hop_s}")
    _validate_zenoh(cfg.zenoh)
    _validate_commands(cfg.commands)
    mb = memory_estimate(replace(cfg, drives=tuple(drives)))["total_mb"]
    if mb > MEMORY_LIMIT_MB:
        raise _KeyError("drives", f"{len(drives)} drive(s) would take about {mb:.0f} MB of memory (at most "
                        f"{MEMORY_LIMIT_MB:g} MB, the unit's MemoryHigh): shorten pipeline.window_s or split the drives")
    state_dir = cfg.state_dir or _default_state_dir(cfg.source)
    if state_dir.exists() and not state_dir.is_dir():
        raise _KeyError("state_dir", f"{state_dir} exists and is not a directory")
    library = replace(cfg.library, path=cfg.library.path or state_dir / "library")
    agent_id = cfg.agent_id or _default_agent_id()
    z = cfg.zenoh
    if z.site:  # a plant: the prefix names the root, the agent's own prefix is <root>/<site>/<agent_id>
        root = z.prefix or "pmsm"
        z = replace(z, plant_prefix=root, prefix=f"{root}/{z.site}/{agent_id}")
    else:
        z = replace(z, prefix=z.prefix or f"pmsm/{_default_agent_id()}")
        z = replace(z, plant_prefix=z.prefix)
    return replace(cfg, drives=tuple(drives), state_dir=state_dir, library=library, agent_id=agent_id, zenoh=z)


def _load_profile(d: DriveCfg, kp: str):
    from agent.profile import load_profile

    try:
        return load_profile(d.profile)
    except InputError as err:
        raise _KeyError(f"{kp}.profile", str(err)) from None


def _validate_source(d: DriveCfg, kp: str) -> None:
    s = d.source
    if isinstance(s, SimulatedCfg):
        from agent.simulator.conditions import check_condition

        if not s.schedule:
            raise _KeyError(f"{kp}.schedule", "needs at least one {condition=..., seconds=...}")
        for i, ph in enumerate(s.schedule):
            try:
                check_condition(ph.condition, d.drive_profile.transmission.kind)
            except InputError as err:
                raise _KeyError(f"{kp}.schedule[{i}].condition", str(err)) from None
    elif isinstance(s, ReplayCfg):
        if not s.files:
            raise _KeyError(f"{kp}.files", "needs at least one record file")
        for i, f in enumerate(s.files):
            if not f.is_file():
                raise _KeyError(f"{kp}.files[{i}]", f"no such file: {f}")
            if f.suffix.lower() not in (".csv", ".npz", ".tdms"):
                raise _KeyError(f"{kp}.files[{i}]", f"must be .csv, .npz or .tdms, got {f.name}")
    elif isinstance(s, ModbusCfg):
        if (s.host is None) == (s.serial_port is None):
            raise _KeyError(f"{kp}.host", "set exactly one of host (Modbus TCP) or serial_port (Modbus RTU)")
    elif isinstance(s, CanCfg) and not s.extended and s.base_id > 0x7FF:
        raise _KeyError(f"{kp}.base_id", f"{s.base_id:#x} needs extended = true (standard ids are <= 0x7ff)")


def _validate_zenoh(z: ZenohCfg) -> None:
    for key, value in z.inline.items():
        if key.strip("/") in ("scouting/multicast/enabled", "scouting/gossip/enabled") and value is not False:
            raise _KeyError(f"zenoh.inline.{key}", "multicast scouting and gossip are never used by this agent")
    if z.config_file is not None and not z.config_file.is_file():
        raise _KeyError("zenoh.config_file", f"no such file: {z.config_file}")
    if not z.enabled:
        return
    if z.mode == "client" and not z.connect and z.config_file is None:
        raise _KeyError("zenoh.connect", "a client needs at least one router endpoint, e.g. ['tcp/router-1:7447']")
    if z.mode == "client" and z.listen:
        raise _KeyError("zenoh.listen", "only a peer or router listens; a client connects to routers")
    if z.retry_max_s < z.retry_initial_s:
        raise _KeyError("zenoh.retry_max_s", f"must be >= zenoh.retry_initial_s ({z.retry_initial_s}), "
                        f"got {z.retry_max_s}")
    from protocols.zenoh_sink import zenoh_config  # builds the real zenoh.Config: bad keys fail here

    try:
        zenoh_config(z.mode, z.listen, z.connect, z.inline, path=z.config_file)
    except ValueError as err:
        raise _KeyError("zenoh.inline", str(err)) from None
    except Exception as err:  # zenoh.ZError from a bad JSON5 file
        raise _KeyError("zenoh.config_file", f"not a valid zenoh config: {err}") from None


def _validate_commands(c: CommandsCfg) -> None:
    if not c.enabled:
        return
    if c.key_file is None:
        raise _KeyError("commands.key_file", "missing: signed commands need a key file ([keys] role = \"hex\")")
    from agent.runtime.commands import load_keys

    try:
        keys = load_keys(c.key_file)
    except InputError as err:
        raise _KeyError("commands.key_file", str(err)) from None
    for command in ("acknowledge", "relearn"):
        for i, role in enumerate(getattr(c, command)):
            if role not in keys:
                raise _KeyError(f"commands.{command}[{i}]", f"role {role!r} has no key in {c.key_file}")


# --- entry points -------------------------------------------------------------------------------

def parse_config(data: dict, source: str | os.PathLike = "<config>") -> Config:
    """Build and validate a :class:`Config` from a parsed TOML document."""
    base = Path(source).resolve().parent if str(source) != "<config>" else Path.cwd()
    try:
        cfg = _build(Config, data, "", base)
        cfg = _validate(replace(cfg, source=Path(source).resolve()))
    except _KeyError as err:
        raise InputError(" ".join(str(err).split()), source=str(source)) from None  # one line
    return cfg


def check_config(path: str | os.PathLike) -> Config:
    """Read and validate the agent config file; ``InputError`` names the file and the key path."""
    path = Path(path)
    data = read_toml(path, "config")
    return parse_config(data, path)


load_config = check_config
