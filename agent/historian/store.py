"""The history in PostgreSQL (psycopg 3): schema migrations, batch writes, retention, queries.

Tables (docs/historian.md has the full description):

* ``schema_version(version, description, applied_at)``: one row per applied migration;
* ``drive(drive_id, site, gateway, drive, first_seen)``: every drive ever heard of;
* ``drive_event(event_id, drive_id, t, kind, state, quality, prev_state, prev_quality, reason, ...)``:
  state, quality and alarm-reason changes (``kind`` ``state`` / ``quality`` / ``reason``);
* ``evidence_trend(drive_id, t, state, quality, evidence, fe_hz, load_pct)``: the sampled trend,
  ``evidence`` a JSON object ``{family: CUSUM / caution threshold}`` (1 = the caution threshold);
* ``historian_buffer(buffer_id, historian_id, written_up_to, updated_at)``: the highest buffer
  row id committed per on-disk buffer, updated in the same transaction as the rows, so a batch
  sent twice is written once.

Codes: ``state`` 0/1/2 = normal/caution/warning, ``quality`` 0..4 = good/no_model/learning/
stale/bad_input (CONTRACT section 6). Times are ``timestamptz``.
"""

from __future__ import annotations

import importlib

from agent.errors import InputError
from protocols.base import QUALITY_CODES, STATE_CODES

#: the migrations, applied in order, each once (``schema_version`` records them)
MIGRATIONS: tuple[tuple[int, str, str], ...] = (
    (1, "drives, drive events, evidence trend, buffer high-water marks", """
CREATE TABLE drive (
    drive_id    integer GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    site        text NOT NULL,
    gateway     text NOT NULL,
    drive       text NOT NULL,
    first_seen  timestamptz NOT NULL DEFAULT now(),
    UNIQUE (site, gateway, drive)
);
CREATE TABLE drive_event (
    event_id        bigint GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    drive_id        integer NOT NULL REFERENCES drive,
    t               timestamptz NOT NULL,
    kind            text NOT NULL CHECK (kind IN ('state', 'quality', 'reason')),
    state           smallint NOT NULL CHECK (state BETWEEN 0 AND 2),
    quality         smallint NOT NULL CHECK (quality BETWEEN 0 AND 4),
    prev_state      smallint,
    prev_quality    smallint,
    reason          jsonb,
    spectrum_state  smallint,
    cluster_state   smallint,
    model           text NOT NULL DEFAULT '',
    fe_hz           double precision,
    load_pct        double precision,
    agent           text NOT NULL DEFAULT '',
    boot_id         text NOT NULL DEFAULT '',
    seq             bigint
);
CREATE INDEX drive_event_drive_t ON drive_event (drive_id, t);
CREATE INDEX drive_event_t ON drive_event (t);
CREATE TABLE evidence_trend (
    drive_id  integer NOT NULL REFERENCES drive,
    t         timestamptz NOT NULL,
    state     smallint NOT NULL CHECK (state BETWEEN 0 AND 2),
    quality   smallint NOT NULL CHECK (quality BETWEEN 0 AND 4),
    evidence  jsonb NOT NULL,
    fe_hz     double precision,
    load_pct  double precision
);
CREATE INDEX evidence_trend_drive_t ON evidence_trend (drive_id, t);
CREATE INDEX evidence_trend_t ON evidence_trend (t);
CREATE TABLE historian_buffer (
    buffer_id      text PRIMARY KEY,
    historian_id   text NOT NULL,
    written_up_to  bigint NOT NULL,
    updated_at     timestamptz NOT NULL DEFAULT now()
);
"""),
)
SCHEMA_VERSION = MIGRATIONS[-1][0]
_MIGRATION_LOCK = 0x706D736D  #: pg_advisory_xact_lock key: concurrent historians migrate one at a time
RETENTION_CHUNK = 10_000  #: rows per DELETE, so retention never holds a long lock

_EVENT_COLUMNS = ("drive_id", "t", "kind", "state", "quality", "prev_state", "prev_quality", "reason",
                  "spectrum_state", "cluster_state", "model", "fe_hz", "load_pct", "agent", "boot_id", "seq")
_TREND_COLUMNS = ("drive_id", "t", "state", "quality", "evidence", "fe_hz", "load_pct")
STATE_NAMES = {v: k for k, v in STATE_CODES.items()}
QUALITY_NAMES = {v: k for k, v in QUALITY_CODES.items()}


def psycopg_module():
    """``psycopg``, or an ``InputError`` saying how to install it (the gateway install leaves it out)."""
    try:
        return importlib.import_module("psycopg")
    except ImportError as err:
        raise InputError(f"the historian needs psycopg ({err}): pip install 'pmsm-agent[historian]' "
                         f"(in the checkout: make setup-test, or pip install -r requirements-historian.lock)") from None


def connect(dsn: str, timeout_s: float):
    """An autocommit connection (each write is an explicit transaction). TCP keepalives and a
    user timeout of 30 s make a vanished server an error instead of a write that hangs."""
    psycopg = psycopg_module()
    return psycopg.connect(dsn, autocommit=True, connect_timeout=max(1, round(timeout_s)),
                           application_name="pmsm-historian", keepalives=1, keepalives_idle=10,
                           keepalives_interval=5, keepalives_count=3, tcp_user_timeout=30_000)


def migrate(conn) -> int:
    """Apply the missing migrations in order (idempotent); returns the schema version.

    ``RuntimeError`` if the database was migrated by a newer historian."""
    with conn.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(%s)", (_MIGRATION_LOCK,))
        conn.execute("CREATE TABLE IF NOT EXISTS schema_version (version integer PRIMARY KEY, "
                     "description text NOT NULL, applied_at timestamptz NOT NULL DEFAULT now())")
        applied = {v for (v,) in conn.execute("SELECT version FROM schema_version")}
        if applied and max(applied) > SCHEMA_VERSION:
            raise RuntimeError(f"the database's schema version is {max(applied)}, newer than this historian's "
                               f"({SCHEMA_VERSION}): update the historian")
        for version, description, sql in MIGRATIONS:
            if version not in applied:
                conn.execute(sql)
                conn.execute("INSERT INTO schema_version(version, description) VALUES (%s, %s)",
                             (version, description))
    return SCHEMA_VERSION


class Writer:
    """Writes buffer batches into PostgreSQL, each batch once (see ``historian_buffer``)."""

    def __init__(self, conn, buffer_id: str, historian_id: str):
        self.conn, self.buffer_id, self.historian_id = conn, buffer_id, historian_id
        self._drive_ids: dict[tuple[str, str, str], int] = {}

    def write(self, batch: list[tuple[int, str, dict]]) -> int:
        """Commit ``batch`` (``(buffer id, table, row)``, ids ascending) in one transaction;
        returns the rows written (those at or below this buffer's high-water mark are skipped)."""
        from psycopg.types.json import Jsonb

        if not batch:
            return 0
        new_ids: dict[tuple[str, str, str], int] = {}
        with self.conn.transaction():
            row = self.conn.execute("SELECT written_up_to FROM historian_buffer WHERE buffer_id = %s FOR UPDATE",
                                    (self.buffer_id,)).fetchone()
            mark = row[0] if row else 0
            todo = [(tbl, r) for i, tbl, r in batch if i > mark]
            events, trends = [], []
            for tbl, r in todo:
                ident = (r["site"], r["gateway"], r["drive"])
                drive_id = self._drive_ids.get(ident) or new_ids.get(ident)
                if drive_id is None:
                    drive_id = new_ids[ident] = self._drive_id(ident)
                values = {**r, "drive_id": drive_id}
                for key in ("reason", "evidence"):
                    if values.get(key) is not None:
                        values[key] = Jsonb(values[key])
                if tbl == "event":
                    events.append(tuple(values.get(c) for c in _EVENT_COLUMNS))
                else:
                    trends.append(tuple(values.get(c) for c in _TREND_COLUMNS))
            with self.conn.cursor() as cur:
                for table, columns, rows in (("drive_event", _EVENT_COLUMNS, events),
                                             ("evidence_trend", _TREND_COLUMNS, trends)):
                    if rows:
                        marks = ", ".join("to_timestamp(%s)" if c == "t" else "%s" for c in columns)
                        cur.executemany(f"INSERT INTO {table} ({', '.join(columns)}) VALUES ({marks})", rows)
            self.conn.execute(
                "INSERT INTO historian_buffer(buffer_id, historian_id, written_up_to) VALUES (%s, %s, %s) "
                "ON CONFLICT (buffer_id) DO UPDATE SET written_up_to = EXCLUDED.written_up_to, updated_at = now()",
                (self.buffer_id, self.historian_id, max(mark, batch[-1][0])))
        self._drive_ids.update(new_ids)  # only once committed: a rolled-back drive row does not exist
        return len(todo)

    def _drive_id(self, ident: tuple[str, str, str]) -> int:
        return self.conn.execute(
            "INSERT INTO drive(site, gateway, drive) VALUES (%s, %s, %s) ON CONFLICT (site, gateway, drive) "
            "DO UPDATE SET drive = EXCLUDED.drive RETURNING drive_id", ident).fetchone()[0]


def apply_retention(conn, trend_days: float, events_days: float) -> dict:
    """Delete trend rows older than ``trend_days`` and events older than ``events_days`` (by their
    ``t``), in chunks of :data:`RETENTION_CHUNK`; returns the counts deleted."""
    deleted = {}
    for table, days in (("evidence_trend", trend_days), ("drive_event", events_days)):
        total = 0
        while True:
            cur = conn.execute(f"DELETE FROM {table} WHERE ctid IN (SELECT ctid FROM {table} "
                               f"WHERE t < now() - make_interval(secs => %s) LIMIT %s)",
                               (float(days) * 86400.0, RETENTION_CHUNK))
            total += cur.rowcount
            if cur.rowcount < RETENTION_CHUNK:
                break
        deleted[table] = total
    return deleted


# --- queries ------------------------------------------------------------------------------------

def _event(row) -> dict:
    t, site, gateway, drive, kind, state, quality, prev_state, prev_quality, reason, model = row
    return {"t": t.timestamp(), "site": site, "gateway": gateway, "drive": drive, "kind": kind,
            "state": STATE_NAMES.get(state), "state_code": state, "quality": QUALITY_NAMES.get(quality),
            "quality_code": quality, "from": (STATE_NAMES if kind != "quality" else QUALITY_NAMES).get(
                prev_state if kind != "quality" else prev_quality), "reason": reason, "model": model}


def reason_text(reason) -> str:
    """One line for an alarm reason: its path, feature and numbers (and the first lines, Hz)."""
    if isinstance(reason, dict):
        parts = [f"{k}={reason[k]}" for k in ("path", "feature", "z", "evidence", "threshold") if k in reason]
        if reason.get("freqs_hz"):
            parts.append("lines_hz=" + ",".join(f"{f:g}" for f in reason["freqs_hz"][:2]))
        return " ".join(parts)
    return "" if reason is None else str(reason)


_EVENT_SELECT = ("SELECT e.t, d.site, d.gateway, d.drive, e.kind, e.state, e.quality, e.prev_state, "
                 "e.prev_quality, e.reason, e.model FROM drive_event e JOIN drive d USING (drive_id)")


def drive_history(conn, drive: str, since: float, until: float) -> list[dict]:
    """State, quality and reason changes of ``drive`` in [since, until] (Unix s), oldest first.

    ``drive`` is a drive name, or ``gateway/drive`` or ``site/gateway/drive`` when names repeat."""
    *head, name = drive.split("/")
    gateway = head[-1] if head else None
    site = "/".join(head[:-1]) if len(head) > 1 else None
    rows = conn.execute(
        _EVENT_SELECT + " WHERE d.drive = %s AND (%s::text IS NULL OR d.gateway = %s) "
        "AND (%s::text IS NULL OR d.site = %s) AND e.t BETWEEN to_timestamp(%s) AND to_timestamp(%s) "
        "ORDER BY e.t, e.event_id", (name, gateway, gateway, site, site, since, until)).fetchall()
    return [_event(r) for r in rows]


def plant_alarms(conn, since: float, until: float) -> list[dict]:
    """The plant's alarm episodes overlapping [since, until] (Unix s), by start time.

    An episode runs from a state change to caution/warning up to the next change back to normal
    (``end`` ``None`` while it lasts); it lists its highest state and its reasons in order (the
    first is what raised it). An alarm already raised at ``since`` starts at its real start."""
    rows = conn.execute(
        "WITH before AS (SELECT DISTINCT ON (drive_id) drive_id, event_id FROM drive_event "
        "  WHERE kind = 'state' AND t < to_timestamp(%s) ORDER BY drive_id, t DESC, event_id DESC) "
        + _EVENT_SELECT + " WHERE e.kind IN ('state', 'reason') AND (e.event_id IN (SELECT event_id FROM before) "
        "OR e.t BETWEEN to_timestamp(%s) AND to_timestamp(%s)) ORDER BY d.drive_id, e.t, e.event_id",
        (since, since, until)).fetchall()
    episodes, open_ = [], {}
    for e in map(_event, rows):
        ident = (e["site"], e["gateway"], e["drive"])
        ep = open_.get(ident)
        if e["kind"] == "state" and e["state_code"] == 0:
            if ep is not None:
                ep["end"] = e["t"]
                del open_[ident]
            continue
        if ep is None:
            if e["kind"] != "state":
                continue
            ep = open_[ident] = {"site": ident[0], "gateway": ident[1], "drive": ident[2], "start": e["t"],
                                 "end": None, "state": e["state"], "reasons": []}
            episodes.append(ep)
        if e["state_code"] > STATE_CODES[ep["state"]]:
            ep["state"] = e["state"]
        if e["reason"] is not None and e["reason"] not in ep["reasons"]:
            ep["reasons"].append(e["reason"])
    kept = [ep for ep in episodes if ep["end"] is None or ep["end"] >= since]
    for ep in kept:
        ep["duration_s"] = None if ep["end"] is None else round(ep["end"] - ep["start"], 3)
    return sorted(kept, key=lambda ep: (ep["start"], ep["site"], ep["gateway"], ep["drive"]))


def fleet_now(conn) -> list[dict]:
    """Every drive with its latest event (state, quality, reason, model), the time of its latest
    state change and its latest trend row (evidence, fe, load); one query (index lookups per drive)."""
    rows = conn.execute(
        "SELECT d.site, d.gateway, d.drive, extract(epoch FROM e.t)::float8, e.state, e.quality, e.reason, e.model, "
        "extract(epoch FROM s.t)::float8, extract(epoch FROM r.t)::float8, r.evidence, r.fe_hz, r.load_pct "
        "FROM drive d "
        "LEFT JOIN LATERAL (SELECT t, state, quality, reason, model FROM drive_event WHERE drive_id = d.drive_id "
        "  ORDER BY t DESC, event_id DESC LIMIT 1) e ON true "
        "LEFT JOIN LATERAL (SELECT t FROM drive_event WHERE drive_id = d.drive_id AND kind = 'state' "
        "  ORDER BY t DESC, event_id DESC LIMIT 1) s ON true "
        "LEFT JOIN LATERAL (SELECT t, evidence, fe_hz, load_pct FROM evidence_trend WHERE drive_id = d.drive_id "
        "  ORDER BY t DESC LIMIT 1) r ON true").fetchall()
    drives = []
    for site, gateway, drive, event_t, state, quality, reason, model, state_t, trend_t, evidence, fe, load in rows:
        heard = [t for t in (event_t, trend_t) if t is not None]
        drives.append({"site": site, "gateway": gateway, "drive": drive,
                       "state": STATE_NAMES.get(state, "unknown"), "state_code": state,
                       "quality": QUALITY_NAMES.get(quality, "unknown"), "quality_code": quality,
                       "state_since": state_t, "last_t": max(heard) if heard else None,
                       "reason": reason if state else None, "model": model or "",
                       "fe_hz": fe, "load_pct": load, "evidence": evidence or {}})
    return drives


def trend_samples(conn, since: float, until: float, points: int) -> dict[tuple[str, str, str], list]:
    """The evidence trend of every drive in [since, until] (Unix s), at most ``points`` rows per
    drive: the last row in each of ``points`` equal slices of the period. One query, one index
    lookup per drive and slice, so its cost does not grow with the trend's density.

    Returns ``{(site, gateway, drive): [(t, {family: evidence}), ...]}``, oldest first."""
    rows = conn.execute(
        "SELECT d.site, d.gateway, d.drive, extract(epoch FROM p.t)::float8, p.evidence "
        "FROM drive d CROSS JOIN generate_series(1, %(points)s) AS k "
        "CROSS JOIN LATERAL (SELECT t, evidence FROM evidence_trend WHERE drive_id = d.drive_id "
        "  AND t > to_timestamp(%(since)s + (k - 1) * %(step)s) AND t <= to_timestamp(%(since)s + k * %(step)s) "
        "  ORDER BY t DESC LIMIT 1) p ORDER BY d.drive_id, p.t",
        {"since": since, "step": (until - since) / points, "points": points}).fetchall()
    trends: dict[tuple[str, str, str], list] = {}
    for site, gateway, drive, t, evidence in rows:
        trends.setdefault((site, gateway, drive), []).append((t, evidence))
    return trends
