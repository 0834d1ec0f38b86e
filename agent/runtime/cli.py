"""``pmsm-agent events`` and ``pmsm-agent run`` (CONTRACT section 2).

``run --check-config FILE`` validates the agent config and exits 0, or 2 with one line naming
the file and key path. ``run --config FILE`` hands the validated config to
``agent.runtime.service.run_service`` (imported only then), which opens sources and sinks,
sends ``READY=1`` to systemd once they are open, pings the watchdog from the processing loop,
reloads the model library on SIGHUP and stops on SIGTERM.
"""

from __future__ import annotations

import importlib
import json
import os
import sys
import time
from pathlib import Path

from agent.errors import InputError


def _state_dir(args) -> Path:
    if args.state_dir:
        return Path(args.state_dir)
    if args.config:
        from agent.runtime.config import check_config

        return check_config(args.config).state_dir
    env = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    return Path(env or "state")


def cmd_events(args) -> None:
    from agent.runtime.journal import Journal, journal_path

    if args.limit < 0:
        raise InputError(f"--limit must be >= 0, got {args.limit}")
    if args.config and args.drive:
        from agent.runtime.config import check_config

        drives = [d.name for d in check_config(args.config).drives]
        if args.drive not in drives:
            raise InputError(f"--drive {args.drive!r}: no such drive in {args.config} (drives: {', '.join(drives)})")
    path = journal_path(_state_dir(args))
    kinds = [k for item in args.kind or () for k in item.split(",") if k]
    with Journal(path, readonly=True) as j:
        events = j.recent(args.drive, kinds=kinds, limit=args.limit)
    events = events[::-1]  # the newest --limit, oldest first (newest last), like a log: text and JSON alike
    if args.json:
        json.dump({"journal": str(path), "order": "oldest first", "events": events}, sys.stdout)
        sys.stdout.write("\n")
        return
    for e in events:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(e["t"])) + f".{int(e['t'] % 1 * 1000):03d}"
        codes = " ".join(f"{k}={e[k]}({e[k + '_code']})" for k in ("state", "quality") if e[k + "_code"] is not None)
        detail = json.dumps(e["detail"], separators=(",", ":")) if e["detail"] else ""
        print(f"{e['id']:>7}  {when}  {e['drive'] or '-':<10} {e['kind']:<9} {codes:<30} {detail}")
    if not events:
        print(f"no events in {path}", file=sys.stderr)


def cmd_status(args) -> None:
    """Each drive's current state and quality, from the journal (the last change), and whether the
    agent that wrote it is running (its last start/stop event)."""
    from agent.runtime.config import check_config
    from agent.runtime.journal import Journal, journal_path

    cfg = check_config(args.config)
    path = journal_path(cfg.state_dir)
    if not path.is_file():
        raise InputError(f"no journal at {path}: the agent has not run with this config yet", source=str(args.config))
    with Journal(path, readonly=True) as j:
        life = j.recent(None, kinds=["start", "stop"], limit=1)
        stopped = bool(life) and life[0]["kind"] == "stop"
        now = life[0]["t"] if stopped else time.time()  # a stopped agent's states hold as of its stop
        drives = []
        for d in cfg.drives:
            last = j.recent(d.name, kinds=["state", "quality"], limit=1)
            e = last[0] if last else None
            reason = (e["detail"] or {}).get("reason") if e else None
            drives.append({"drive": d.name, "state": e["state"] if e else None, "quality": e["quality"] if e else None,
                           "since": e["t"] if e else None, "age_s": round(now - e["t"], 1) if e else None,
                           "reason": reason})
    agent = "never started" if not life else ("stopped" if stopped else "running")
    if args.json:
        json.dump({"journal": str(path), "agent": agent, "agent_since": life[0]["t"] if life else None,
                   "as_of": now, "drives": drives}, sys.stdout)
        sys.stdout.write("\n")
        return
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(life[0]["t"])) if life else ""
    print(f"agent {agent}" + (f" since {when}" if when else "") + f" (journal {path})"
          + ("; the states below are as of the stop" if stopped else ""))
    for d in drives:
        if d["state"] is None:
            print(f"{d['drive']}: no state recorded yet")
            continue
        why = d["reason"]
        why = why if isinstance(why, str) else " ".join(f"{k}={v}" for k, v in (why or {}).items()
                                                       if k in ("path", "feature", "z", "evidence", "threshold"))
        print(f"{d['drive']}: {str(d['state']).upper()} (quality {d['quality']}) for {_age(d['age_s'])}"
              + (f"; {why}" if why else ""))


def _age(seconds: float) -> str:
    for unit, size in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= size:
            return f"{seconds / size:.1f} {unit}"
    return f"{seconds:.0f} s"


def cmd_run(args) -> None:
    from agent.runtime.config import check_config

    if args.check_config:
        cfg = check_config(args.check_config)
        names = ", ".join(f"{d.name} ({d.source.kind})" for d in cfg.drives)
        from agent.runtime.config import MEMORY_LIMIT_MB, memory_estimate

        mem = memory_estimate(cfg)
        if args.json:
            json.dump({"config": str(cfg.source), "ok": True, "drives": [d.name for d in cfg.drives],
                       "state_dir": str(cfg.state_dir), "memory_mb": round(mem["total_mb"], 1),
                       "memory_per_drive_mb": round(mem["per_drive_mb"], 2), "memory_limit_mb": MEMORY_LIMIT_MB,
                       "workers": mem["workers"]}, sys.stdout)
            sys.stdout.write("\n")
        else:
            print(f"{args.check_config}: OK: {len(cfg.drives)} drive(s): {names}; state_dir {cfg.state_dir}; "
                  f"memory about {mem['total_mb']:.0f} MB ({mem['per_drive_mb']:.1f} MB per drive, "
                  f"{mem['workers']} DSP process(es); limit {MEMORY_LIMIT_MB:g} MB)")
        return
    cfg = check_config(args.config)
    try:
        service = importlib.import_module("agent.runtime.service")
    except ModuleNotFoundError as err:
        if err.name != "agent.runtime.service":
            raise
        raise RuntimeError("agent.runtime.service is not part of this build; `run` is unavailable") from err
    rc = service.run_service(cfg)
    if rc:
        raise SystemExit(int(rc))


def add_commands(sub, common) -> None:
    """Add ``events`` and ``run`` to the ``pmsm-agent`` subparsers."""
    s = sub.add_parser("events", parents=[common], help="list the agent's event journal (newest last)")
    s.add_argument("--state-dir", help="the agent's state directory (default: $STATE_DIRECTORY, else ./state)")
    s.add_argument("--config", help="take the state directory from this agent config")
    s.add_argument("--drive", help="only this drive")
    s.add_argument("--kind", action="append", help="only these kinds (state, quality, learning, error, ...; "
                   "repeatable or comma-separated)")
    s.add_argument("--limit", type=int, default=50, help="newest N events (default 50)")
    s.set_defaults(func=cmd_events)

    s = sub.add_parser("status", parents=[common], help="each drive's current state, from the agent's journal")
    s.add_argument("--config", required=True, metavar="FILE", help="the agent's config TOML")
    s.set_defaults(func=cmd_status)

    s = sub.add_parser("run", parents=[common], help="run the agent service (or only check its config)")
    g = s.add_mutually_exclusive_group(required=True)
    g.add_argument("--config", metavar="FILE", help="agent config TOML (e.g. /etc/pmsm-agent/agent.toml)")
    g.add_argument("--check-config", metavar="FILE", help="validate FILE and exit: 0 if valid, 2 with the key path")
    s.set_defaults(func=cmd_run)
