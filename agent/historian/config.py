"""The historian config (TOML): database, zenoh subscription, buffer, trend sampling, retention,
the fleet page.

Read and validated like the agent's config (:mod:`agent.runtime.config`, the same builder):
unknown keys are rejected and every error names the key path, e.g. ``retention.trend_days:
must be > 0, got 0`` (:class:`agent.errors.InputError`, with the file as its source). Relative
paths are relative to the config file; ``state_dir`` defaults to systemd's $STATE_DIRECTORY,
else ``state`` beside the config file. See ``config/historian.toml`` for an annotated example.
"""

from __future__ import annotations

import ipaddress
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

from agent.errors import InputError, read_toml
from agent.runtime.config import (_KeyError, _build, _default_agent_id, _default_state_dir, _endpoint, _key_chunk,
                                  _key_expr, _opt, _validate_zenoh)

SCHEMA_VERSION = 1
STATUS_FILENAME = "historian-status.json"
BUFFER_FILENAME = "historian-buffer.sqlite3"


def _subscription(v: str) -> str | None:
    """A zenoh key expression (wildcards allowed), outside the admin space ``@/...``."""
    import zenoh

    if v.startswith("@"):
        return "the admin space '@/...' is not drive state"
    try:
        zenoh.KeyExpr(v)
    except zenoh.ZError as err:
        return f"not a zenoh key expression: {err}"
    return None


@dataclass(frozen=True, kw_only=True)
class DatabaseCfg:
    """The PostgreSQL server (psycopg 3 / libpq)."""

    dsn: str = _opt()  #: libpq connection string or URI; a password is better kept in a passfile
    connect_timeout_s: float = _opt(5.0, ge=1, le=60)  #: per attempt; WatchdogSec must exceed it by 15 s
    retry_initial_s: float = _opt(1.0, gt=0, le=600)  #: first wait after a failed connect or write, s
    retry_max_s: float = _opt(30.0, gt=0, le=3600)  #: the wait doubles up to this, s


@dataclass(frozen=True, kw_only=True)
class SubscriptionCfg:
    """The zenoh session (client of routers, or peer of listed endpoints); never multicast."""

    enabled = True  # not a key: the historian always subscribes (read by the zenoh check it shares)
    mode: str = _opt("client", choices=("client", "peer"))
    connect: tuple[str, ...] = _opt((), check=_endpoint)  #: routers (client) or peers to connect to
    listen: tuple[str, ...] = _opt((), check=_endpoint)  #: peer mode only
    prefix: str = _opt("pmsm", check=_key_expr)  #: the plant's key space; identity chunks follow it
    key_expr: str = _opt("", check=lambda v: None if v == "" else _subscription(v))  #: default <prefix>/**/state
    config_file: Path | None = _opt(None)  #: JSON5 zenoh config read first
    inline: dict = _opt({})  #: extra zenoh keys, e.g. ``{"transport/link/tx/lease" = 3000}``
    retry_initial_s: float = _opt(1.0, gt=0, le=600)  #: first wait after a failed session open, s
    retry_max_s: float = _opt(30.0, gt=0, le=3600)


@dataclass(frozen=True, kw_only=True)
class RetentionCfg:
    """How long rows are kept (by their time ``t``); drives are never deleted."""

    trend_days: float = _opt(90.0, gt=0, le=36500)  #: evidence trend rows
    events_days: float = _opt(3650.0, gt=0, le=36500)  #: state, quality and reason changes (kept longer)
    interval_s: float = _opt(3600.0, ge=1, le=7 * 86400)  #: how often the deletes run, s


def _listen_host(v: str) -> str | None:
    """An address to listen on: an IP address or a host name (of this machine)."""
    try:
        ipaddress.ip_address(v)
        return None
    except ValueError:
        pass
    return None if re.fullmatch(r"[A-Za-z0-9]([A-Za-z0-9.\-]*[A-Za-z0-9])?", v) else \
        "an IP address or host name, e.g. '127.0.0.1' (the port is page.port)"


@dataclass(frozen=True, kw_only=True)
class PageCfg:
    """The fleet page (HTML at ``/``, the same data at ``/fleet.json``), served by the historian."""

    enabled: bool = _opt(False)
    host: str = _opt("127.0.0.1", check=_listen_host)  #: loopback, or this server's address on the plant network
    port: int = _opt(8470, ge=0, le=65535)  #: 0 picks a free port (the status shows the page's URL)
    refresh_s: float = _opt(30.0, ge=2, le=3600)  #: the page reloads itself this often, s
    window_h: float = _opt(24.0, gt=0, le=24 * 366)  #: the trend plots and the alarm list span this much, h
    trend_points: int = _opt(96, ge=2, le=2000)  #: points per drive and family (the last row of each slice)
    silent_after_s: float = _opt(300.0, gt=0, le=7 * 86400)  #: no sample for this long: the drive is marked silent


@dataclass(frozen=True, kw_only=True)
class HistorianConfig:
    schema_version: int = _opt()
    historian_id: str = _opt(None, check=_key_chunk)  #: default: the host name
    state_dir: Path | None = _opt(None)  #: the buffer and the status file live here
    batch_size: int = _opt(500, ge=1, le=100_000)  #: rows per PostgreSQL transaction
    trend_period_s: float = _opt(10.0, ge=0, le=86400)  #: at most one trend row per drive per period (plus changes), s
    database: DatabaseCfg = _opt()
    zenoh: SubscriptionCfg = SubscriptionCfg()
    retention: RetentionCfg = RetentionCfg()
    page: PageCfg = PageCfg()
    source: Path | None = field(default=None, metadata={"derived": True})  #: the config file

    @property
    def buffer_path(self) -> Path:
        return self.state_dir / BUFFER_FILENAME

    @property
    def status_path(self) -> Path:
        return self.state_dir / STATUS_FILENAME

    @property
    def health_key(self) -> str:
        """The zenoh queryable that answers the status JSON."""
        return f"{self.zenoh.prefix}/historian/{self.historian_id}/health"


def check_dsn(dsn: str) -> str | None:
    """``None`` when libpq can parse ``dsn``; else why not (the string itself is never echoed)."""
    from agent.historian.store import psycopg_module

    psycopg = psycopg_module()
    try:
        psycopg.conninfo.conninfo_to_dict(dsn)
    except psycopg.ProgrammingError as err:
        return f"not a libpq connection string or URI ({str(err).splitlines()[0]})"
    return None


def _validate(cfg: HistorianConfig) -> HistorianConfig:
    if cfg.schema_version != SCHEMA_VERSION:
        raise _KeyError("schema_version", f"this historian reads version {SCHEMA_VERSION}, got {cfg.schema_version}")
    if msg := check_dsn(cfg.database.dsn):
        raise _KeyError("database.dsn", msg)
    for table in ("database", "zenoh"):
        t = getattr(cfg, table)
        if t.retry_max_s < t.retry_initial_s:
            raise _KeyError(f"{table}.retry_max_s", f"must be >= {table}.retry_initial_s ({t.retry_initial_s}), "
                            f"got {t.retry_max_s}")
    z = cfg.zenoh
    if z.mode == "client" and not z.connect and z.config_file is None:
        raise _KeyError("zenoh.connect", "a client needs at least one router endpoint, e.g. ['tcp/router-1:7447']")
    if z.mode == "client" and z.listen:
        raise _KeyError("zenoh.listen", "only a peer listens (mode = 'peer'); a client connects to routers")
    if z.mode == "peer" and not (z.connect or z.listen) and z.config_file is None:
        raise _KeyError("zenoh.connect", "a peer needs endpoints to connect to or listen on (no multicast scouting)")
    _validate_zenoh(z)
    r = cfg.retention
    if r.events_days < r.trend_days:
        raise _KeyError("retention.events_days", f"state changes are kept at least as long as the trend "
                        f"(retention.trend_days = {r.trend_days:g}), got {r.events_days:g}")
    state_dir = cfg.state_dir or _default_state_dir(cfg.source)
    if state_dir.exists() and not state_dir.is_dir():
        raise _KeyError("state_dir", f"{state_dir} exists and is not a directory")
    return replace(cfg, state_dir=state_dir, historian_id=cfg.historian_id or _default_agent_id(),
                   zenoh=replace(z, key_expr=z.key_expr or f"{z.prefix}/**/state"))


def parse_historian_config(data: dict, source: str | os.PathLike = "<config>") -> HistorianConfig:
    """Build and validate a :class:`HistorianConfig` from a parsed TOML document."""
    base = Path(source).resolve().parent if str(source) != "<config>" else Path.cwd()
    try:
        cfg = _build(HistorianConfig, data, "", base)
        cfg = _validate(replace(cfg, source=Path(source).resolve()))
    except _KeyError as err:
        raise InputError(" ".join(str(err).split()), source=str(source)) from None
    return cfg


def load_historian_config(path: str | os.PathLike) -> HistorianConfig:
    """Read and validate the historian config file; ``InputError`` names the file and the key path."""
    return parse_historian_config(read_toml(path, "historian config"), path)
