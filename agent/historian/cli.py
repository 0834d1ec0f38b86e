"""``pmsm-agent historian`` (the process) and ``pmsm-agent history`` (queries), docs/historian.md.

``historian --config F`` runs the historian; ``historian --check-config F`` validates F and
exits 0, or 2 with one line naming the file and key path. ``history`` reads PostgreSQL with the
connection of a historian config (``--config``) or ``--dsn``:

* ``history --drive D --since 24h`` lists the state, quality and alarm-reason changes of drive D;
* ``history --alarms --since 7d [--until ...]`` lists the plant's alarm episodes: which drives
  alarmed, from when to when, how high and why.

Times are ``30s``/``15min``/``24h``/``7d``/``2w`` before now, or ISO 8601 (local time when the
zone is not given).
"""

from __future__ import annotations

import json
import re
import sys
import time
from datetime import datetime

from agent.errors import InputError

_AGO = re.compile(r"^(\d+(?:\.\d+)?)\s*(s|min|h|d|w)$")
_UNIT_S = {"s": 1.0, "min": 60.0, "h": 3600.0, "d": 86400.0, "w": 7 * 86400.0}


def parse_time(text: str, flag: str, now: float | None = None) -> float:
    """Unix time (s) of ``24h``-style ages before ``now`` or of an ISO 8601 time."""
    now = time.time() if now is None else now
    if m := _AGO.match(text.strip()):
        return now - float(m.group(1)) * _UNIT_S[m.group(2)]
    try:
        return datetime.fromisoformat(text.strip()).timestamp()
    except ValueError:
        raise InputError(f"{flag} {text!r}: give an age like 30s, 15min, 24h, 7d, 2w or an ISO 8601 time "
                         f"like 2026-11-20T06:00") from None


def _when(t: float | None) -> str:
    return "-" if t is None else datetime.fromtimestamp(t).astimezone().isoformat(sep=" ", timespec="seconds")


def cmd_historian(args) -> None:
    from agent.historian.config import load_historian_config

    cfg = load_historian_config(args.check_config or args.config)
    if args.check_config:
        doc = {"config": str(cfg.source), "ok": True, "historian_id": cfg.historian_id,
               "state_dir": str(cfg.state_dir), "key_expr": cfg.zenoh.key_expr}
        if args.json:
            json.dump(doc, sys.stdout)
            sys.stdout.write("\n")
        else:
            print(f"{args.check_config}: OK: historian {cfg.historian_id} subscribes to {cfg.zenoh.key_expr} "
                  f"({cfg.zenoh.mode}); state_dir {cfg.state_dir}")
        return
    from agent.historian.service import run_historian

    rc = run_historian(cfg, max_seconds=args.seconds)
    if rc:
        raise SystemExit(int(rc))


def _connection(args):
    from agent.historian import store

    if args.dsn:
        dsn, origin, timeout_s = args.dsn, "--dsn", 5.0
    else:
        from agent.historian.config import load_historian_config

        cfg = load_historian_config(args.config)
        dsn, origin, timeout_s = cfg.database.dsn, f"{args.config}: database.dsn", cfg.database.connect_timeout_s
    psycopg = store.psycopg_module()
    try:
        return store.connect(dsn, timeout_s)
    except psycopg.Error as err:
        raise InputError(f"cannot reach the database ({origin}): {' '.join(str(err).split())}") from None


def cmd_history(args) -> None:
    from agent.historian import store

    now = time.time()
    since = parse_time(args.since, "--since", now)
    until = parse_time(args.until, "--until", now) if args.until else now
    if until < since:
        raise InputError(f"--until ({_when(until)}) is before --since ({_when(since)})")
    psycopg = store.psycopg_module()
    with _connection(args) as conn:
        try:
            if args.alarms:
                alarms = store.plant_alarms(conn, since, until)
            else:
                events = store.drive_history(conn, args.drive, since, until)
        except psycopg.errors.UndefinedTable:
            raise InputError("no history tables in this database (has a historian written to it?)") from None
    period = {"since": since, "until": until}
    if args.alarms:
        drives = sorted({(a["site"], a["gateway"], a["drive"]) for a in alarms})
        if args.json:
            json.dump({**period, "drives_alarmed": ["/".join(x for x in d if x) for d in drives], "alarms": alarms},
                      sys.stdout)
            sys.stdout.write("\n")
            return
        print(f"{len(alarms)} alarm(s) on {len(drives)} drive(s) from {_when(since)} to {_when(until)}")
        for a in alarms:
            name = "/".join(x for x in (a["site"], a["gateway"], a["drive"]) if x)
            why = "; ".join(store.reason_text(r) for r in a["reasons"][:3])
            print(f"{name:<24} {a['state'].upper():<8} {_when(a['start'])} .. "
                  f"{_when(a['end']) if a['end'] is not None else 'ongoing'}" + (f"  {why}" if why else ""))
        return
    if args.json:
        json.dump({"drive": args.drive, **period, "order": "oldest first", "events": events}, sys.stdout)
        sys.stdout.write("\n")
        return
    for e in events:
        name = "/".join(x for x in (e["site"], e["gateway"], e["drive"]) if x)
        value = e["quality"] if e["kind"] == "quality" else e["state"]
        change = f"{e['from']} -> {value}" if e["from"] is not None else str(value)
        why = store.reason_text(e["reason"])
        print(f"{_when(e['t'])}  {name:<20} {e['kind']:<8} {change:<22}" + (f" {why}" if why else ""))
    if not events:
        print(f"no history of drive {args.drive} from {_when(since)} to {_when(until)}", file=sys.stderr)


def add_commands(sub, common) -> None:
    """Add ``historian`` and ``history`` to the ``pmsm-agent`` subparsers."""
    from agent.cliargs import number

    s = sub.add_parser("historian", parents=[common], help="write the plant's drive states from zenoh into PostgreSQL")
    g = s.add_mutually_exclusive_group(required=True)
    g.add_argument("--config", metavar="FILE", help="historian config TOML (e.g. /etc/pmsm-historian/historian.toml)")
    g.add_argument("--check-config", metavar="FILE", help="validate FILE and exit: 0 if valid, 2 with the key path")
    s.add_argument("--seconds", type=number(0, None, low_open=True, unit="s"), help="stop after this long, s")
    s.set_defaults(func=cmd_historian)

    s = sub.add_parser("history", parents=[common], help="a drive's state changes, or the plant's alarms, "
                       "from the historian's database")
    what = s.add_mutually_exclusive_group(required=True)
    what.add_argument("--drive", metavar="D", help="this drive's changes (name, or gateway/name, site/gateway/name)")
    what.add_argument("--alarms", action="store_true", help="the plant's alarm episodes: which drives, when, why")
    s.add_argument("--since", default="24h", help="start: 24h, 7d, ... before now, or ISO 8601 (default 24h)")
    s.add_argument("--until", help="end: as --since (default now)")
    db = s.add_mutually_exclusive_group(required=True)
    db.add_argument("--config", metavar="FILE", help="the historian config (its database.dsn)")
    db.add_argument("--dsn", help="libpq connection string or URI")
    s.set_defaults(func=cmd_history)
