"""``pmsm-agent router`` and ``pmsm-agent fleet``: a plant of gateways on zenoh routers.

* ``router --listen tcp/IP:PORT [--connect EP] [--config zenoh.json5]`` runs a zenoh session in
  router mode (for plants without ``zenohd``): gateways, the historian and ``fleet`` connect to
  it as clients. Multicast scouting and gossip are off; a second router joins with
  ``--connect`` (redundant routers). It sends READY=1 to systemd and stops on SIGTERM.
* ``fleet status --connect EP`` prints one row per drive of the plant: its link (``live``, or
  ``LOST`` when the gateway's or the drive's liveliness token is gone), state, quality,
  evidence per family, last change, seq and gateway. Live gateways answer the query
  ``<root>/**/agent/*/fleet`` with all their drives at once; gateways and drives seen before
  come from the inventory file (``--inventory``), so a gateway that died is still listed, LOST.
* ``fleet command ACTION --connect EP --drive KEY --role ROLE --key-file F`` sends a signed
  ACK or RELEARN (:mod:`agent.runtime.commands`) to the drive whose key prefix is ``KEY``
  (``<root>/<site>/<gateway>/<drive>``, the ``key`` column of ``fleet status --json``).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path

from agent.errors import InputError

log = logging.getLogger("pmsm-agent.plant")
QUERY_TIMEOUT_S = 3.0  #: how long fleet waits for the gateways' answers, s
STATUS_PERIOD_S = 5.0  #: the router's sd_notify STATUS line is refreshed this often


def _session(connect: list[str], config: str | None = None, lease_ms: int | None = None):
    """A client session on the plant's routers (``InputError`` naming ``--connect`` when none answers)."""
    import zenoh

    from protocols.zenoh_sink import zenoh_config

    extra = {"transport/link/tx/lease": lease_ms} if lease_ms else {}
    try:
        cfg = zenoh_config("client", None, connect or None, extra, path=config)
    except ValueError as err:
        raise InputError(str(err)) from None
    try:
        return zenoh.open(cfg)
    except zenoh.ZError as err:
        raise InputError(f"--connect {' '.join(connect)}: no zenoh router answers ({' '.join(str(err).split())})") \
            from None


# --- router --------------------------------------------------------------------------------------

def cmd_router(args) -> None:
    import zenoh

    from agent.runtime import sdnotify
    from protocols.zenoh_sink import zenoh_config

    if not args.listen and not args.config:
        raise InputError("--listen: at least one endpoint, e.g. tcp/0.0.0.0:7447 (or a --config that lists "
                         "listen/endpoints)")
    try:
        cfg = zenoh_config("router", args.listen or None, args.connect or None, path=args.config)
    except ValueError as err:
        raise InputError(str(err), source=args.config) from None
    except Exception as err:  # zenoh.ZError from a bad JSON5 file
        raise InputError(f"not a valid zenoh config: {err}", source=args.config) from None
    listen = json.loads(cfg.get_json("listen/endpoints"))
    try:
        session = zenoh.open(cfg)
    except zenoh.ZError as err:
        raise InputError(f"--listen {' '.join(listen)}: {' '.join(str(err).split())}") from None
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    clients: set[str] = set()

    def on_transport(event):
        zid, kind = str(event.transport.zid), str(event.transport.whatami)
        if event.kind == zenoh.SampleKind.PUT:
            clients.add(zid)
            log.info("%s %s connected", kind, zid)
        else:
            clients.discard(zid)
            log.info("%s %s gone", kind, zid)

    listener = session.info.declare_transport_events_listener(on_transport, history=True)
    print(f"router {session.zid()} listening on {', '.join(listen)}", flush=True)
    sdnotify.ready(f"listening on {', '.join(listen)}")
    try:
        while not stop.wait(STATUS_PERIOD_S):
            sdnotify.status(f"listening on {', '.join(listen)}; {len(clients)} session(s) connected")
    finally:
        sdnotify.stopping("stopping")
        listener.undeclare()
        session.close()


# --- fleet status --------------------------------------------------------------------------------

def gather(session, root: str, timeout: float = QUERY_TIMEOUT_S) -> tuple[set[str], list[dict]]:
    """The live liveliness keys under ``root`` and the gateways' fleet answers."""
    tokens = {str(r.ok.key_expr) for r in session.liveliness().get(f"{root}/**/alive", timeout=timeout) if r.ok}
    answers = []
    for r in session.get(f"{root}/**/agent/*/fleet", timeout=timeout):
        if r.ok:
            try:
                answers.append(json.loads(r.ok.payload.to_string()))
            except ValueError:
                log.warning("a fleet answer on %s is not JSON", r.ok.key_expr)
    return tokens, answers


def plant_view(tokens: set[str], answers: list[dict], inventory: dict | None = None,
               now: float | None = None) -> dict:
    """Gateways and drives of the plant: the answers of live gateways, tokens that did not answer,
    and what ``inventory`` (a previous view) knew of gateways that are gone; returns the new view
    ``{"t", "gateways": {prefix: {...}}}`` where every gateway and drive has ``link`` live or LOST."""
    now = time.time() if now is None else now
    gateways: dict[str, dict] = {}
    for doc in answers:
        gateways[doc["prefix"]] = {"agent": doc["agent"], "site": doc.get("site", ""), "prefix": doc["prefix"],
                                   "boot_id": doc.get("boot_id"), "answered": True, "last_seen": now,
                                   "commands": doc.get("commands"), "drives": dict(doc.get("drives") or {})}
    for key in tokens:  # a gateway whose token is live but whose answer did not come
        head, sep, tail = key.rpartition("/agent/")
        if sep and tail.endswith("/alive") and tail.count("/") == 1 and head not in gateways:
            gateways[head] = {"agent": tail.split("/")[0], "site": "", "prefix": head, "answered": False,
                              "last_seen": now, "drives": {}}
    for prefix, old in ((inventory or {}).get("gateways") or {}).items():
        if prefix in gateways:
            if not gateways[prefix]["answered"]:  # live token, no answer: keep the drives we knew
                gateways[prefix].update(site=old.get("site", ""), drives=old.get("drives") or {})
        else:
            gateways[prefix] = {**old, "answered": False}
    for prefix, gw in gateways.items():
        gw["link"] = "live" if f"{prefix}/agent/{gw['agent']}/alive" in tokens else "LOST"
        if gw["link"] == "LOST":
            gw.setdefault("lost_since", now)
        else:
            gw.pop("lost_since", None)
        for name, d in gw["drives"].items():
            d["link"] = "live" if gw["link"] == "live" and f"{prefix}/{name}/alive" in tokens else "LOST"
    return {"t": now, "gateways": gateways}


def drive_rows(view: dict) -> list[dict]:
    """One row per drive, sorted by site, gateway, drive."""
    rows = []
    for prefix, gw in view["gateways"].items():
        for name, d in gw["drives"].items():
            rows.append({"site": gw.get("site", ""), "gateway": gw["agent"], "drive": name, "key": f"{prefix}/{name}",
                         "link": d["link"], "gateway_link": gw["link"], "state": d.get("state"),
                         "quality": d.get("quality"), "evidence": d.get("evidence") or {}, "since": d.get("since"),
                         "t": d.get("t"), "seq": d.get("seq")})
        if not gw["drives"]:
            rows.append({"site": gw.get("site", ""), "gateway": gw["agent"], "drive": None, "key": prefix,
                         "link": gw["link"], "gateway_link": gw["link"], "state": None, "quality": None,
                         "evidence": {}, "since": None, "t": None, "seq": None})
    return sorted(rows, key=lambda r: (r["site"], r["gateway"], r["drive"] or ""))


def _when(t: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t)) if t else "-"


def _evidence(ev: dict) -> str:
    if not ev:
        return "-"
    return " ".join(f"{k}={v:.2f}" if isinstance(v, (int, float)) else f"{k}={v}" for k, v in sorted(ev.items()))


def format_table(rows: list[dict]) -> str:
    """The plant table: one line per drive (a gateway without known drives gets one line)."""
    head = ("SITE", "GATEWAY", "DRIVE", "LINK", "STATE", "QUALITY", "EVIDENCE", "LAST CHANGE", "SEQ")
    lines = [head] + [(r["site"] or "-", r["gateway"], r["drive"] or "-", r["link"],
                       str(r["state"] or "-").upper() if r["state"] not in (None, "normal") else (r["state"] or "-"),
                       r["quality"] or "-", _evidence(r["evidence"]), _when(r["since"]),
                       "-" if r["seq"] is None else str(r["seq"])) for r in rows]
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(line, widths)).rstrip() for line in lines)


def _inventory_path(args) -> Path:
    if args.inventory:
        return Path(args.inventory)
    base = os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state"
    return Path(base) / "pmsm-agent" / f"fleet-{args.prefix.replace('/', '_')}.json"


def _read_inventory(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as err:
        raise InputError(f"not a fleet inventory ({err}); delete it to start afresh", source=str(path)) from None


def _write_inventory(path: Path, view: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(view, default=str))
    os.replace(tmp, path)


def _check_key(key: str, option: str) -> None:
    from protocols.zenoh_sink import check_key

    try:
        check_key(key, option)
    except ValueError as err:
        raise InputError(str(err)) from None


def cmd_fleet_status(args) -> None:
    _check_key(args.prefix, "--prefix")
    path = _inventory_path(args)
    inventory = _read_inventory(path)
    session = _session(args.connect, args.zenoh_config)
    try:
        tokens, answers = gather(session, args.prefix, args.timeout)
    finally:
        session.close()
    view = plant_view(tokens, answers, inventory)
    for prefix in args.forget or ():
        view["gateways"] = {p: g for p, g in view["gateways"].items() if prefix not in (p, g["agent"])}
    _write_inventory(path, view)
    rows = drive_rows(view)
    lost = [r for r in rows if r["link"] == "LOST"]
    gateways = sorted(view["gateways"].values(), key=lambda g: (g.get("site", ""), g["agent"]))
    if args.json:
        json.dump({"as_of": view["t"], "prefix": args.prefix, "inventory": str(path),
                   "gateways": [{k: g.get(k) for k in ("site", "agent", "prefix", "link", "boot_id", "last_seen",
                                                       "lost_since", "commands")} | {"drives": len(g["drives"])}
                                for g in gateways],
                   "drives": rows, "lost": len(lost)}, sys.stdout, default=str)
        sys.stdout.write("\n")
        return
    live = sum(g["link"] == "live" for g in gateways)
    print(f"plant {args.prefix}: {live}/{len(gateways)} gateway(s) live, {len(rows) - len(lost)}/{len(rows)} "
          f"drive(s) live, as of {_when(view['t'])}")
    print(format_table(rows))


# --- fleet command -------------------------------------------------------------------------------

def cmd_fleet_command(args) -> None:
    from agent.runtime.commands import load_keys, sign

    _check_key(args.drive, "--drive")
    keys = load_keys(args.key_file)
    if args.role not in keys:
        raise InputError(f"--role {args.role!r}: no key for it in {args.key_file}")
    doc = sign(args.action, args.drive, args.role, keys[args.role], by=args.by or os.environ.get("USER", ""))
    session = _session(args.connect, args.zenoh_config)
    try:
        replies = list(session.get(f"{args.drive}/command", payload=json.dumps(doc), timeout=args.timeout))
    finally:
        session.close()
    if not replies:
        raise InputError(f"--drive {args.drive}: no gateway answers on {args.drive}/command (is it live, and "
                         f"are commands enabled in its config?)")
    r = replies[0]
    answer = json.loads((r.ok or r.err).payload.to_string())
    if args.json:
        json.dump({"drive": args.drive, "command": args.action, "ok": bool(r.ok), **answer}, sys.stdout)
        sys.stdout.write("\n")
    elif r.ok:
        print(f"{args.drive}: {args.action} accepted (role {args.role})")
    if not r.ok:
        raise InputError(f"{args.drive}: {args.action} {answer.get('error', 'refused')}")


# --- parser --------------------------------------------------------------------------------------

def add_commands(sub, common) -> None:
    """Add ``router`` and ``fleet`` to the ``pmsm-agent`` subparsers."""
    s = sub.add_parser("router", parents=[common], help="run a zenoh router for the plant's gateways "
                       "(where zenohd is not installed)")
    s.add_argument("--listen", action="append", metavar="ENDPOINT", help="e.g. tcp/0.0.0.0:7447 (repeatable)")
    s.add_argument("--connect", action="append", metavar="ENDPOINT", help="another router (repeatable)")
    s.add_argument("--config", metavar="FILE", help="zenoh JSON5 config read first (TLS, access control, lease)")
    s.set_defaults(func=cmd_router)

    s = sub.add_parser("fleet", help="the plant's gateways and drives on the zenoh routers")
    fleet = s.add_subparsers(dest="fleet_command", required=True, metavar="ACTION")

    def connection(p):
        p.add_argument("--connect", action="append", required=True, metavar="ENDPOINT",
                       help="a zenoh router, e.g. tcp/router-1:7447 (repeatable)")
        p.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config read first (TLS, credentials)")
        p.add_argument("--timeout", type=float, default=QUERY_TIMEOUT_S, help="query timeout, s (default 3)")

    s = fleet.add_parser("status", parents=[common], help="one table of every drive in the plant")
    connection(s)
    s.add_argument("--prefix", default="pmsm", help="the plant's key-space root (default pmsm)")
    s.add_argument("--inventory", metavar="FILE", help="where the gateways seen so far are kept (default "
                   "$XDG_STATE_HOME/pmsm-agent/fleet-<prefix>.json)")
    s.add_argument("--forget", action="append", metavar="GATEWAY", help="drop a decommissioned gateway (its id "
                   "or prefix) from the inventory (repeatable)")
    s.set_defaults(func=cmd_fleet_status)

    s = fleet.add_parser("command", parents=[common], help="send a signed ACK or RELEARN to one drive")
    s.add_argument("action", choices=("acknowledge", "relearn"), help="acknowledge the alarm, or relearn the baseline")
    connection(s)
    s.add_argument("--drive", required=True, metavar="KEY", help="the drive's key prefix, e.g. pmsm/site-a/gw1/d1")
    s.add_argument("--role", required=True, help="the role to sign as (a key in --key-file)")
    s.add_argument("--key-file", required=True, metavar="FILE", help="TOML [keys] role = \"hex\"")
    s.add_argument("--by", help="who sends it (journalled; default $USER)")
    s.set_defaults(func=cmd_fleet_command)
