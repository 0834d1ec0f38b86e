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
    path = journal_path(_state_dir(args))
    kinds = [k for item in args.kind or () for k in item.split(",") if k]
    with Journal(path, readonly=True) as j:
        events = j.recent(args.drive, kinds=kinds, limit=args.limit)
    if args.json:
        json.dump({"journal": str(path), "events": events}, sys.stdout)
        sys.stdout.write("\n")
        return
    for e in reversed(events):  # oldest first, like a log
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(e["t"])) + f".{int(e['t'] % 1 * 1000):03d}"
        codes = " ".join(f"{k}={e[k]}({e[k + '_code']})" for k in ("state", "quality") if e[k + "_code"] is not None)
        detail = json.dumps(e["detail"], separators=(",", ":")) if e["detail"] else ""
        print(f"{e['id']:>7}  {when}  {e['drive'] or '-':<10} {e['kind']:<9} {codes:<30} {detail}")
    if not events:
        print(f"no events in {path}", file=sys.stderr)


def cmd_run(args) -> None:
    from agent.runtime.config import check_config

    if args.check_config:
        cfg = check_config(args.check_config)
        names = ", ".join(f"{d.name} ({d.source.kind})" for d in cfg.drives)
        if args.json:
            json.dump({"config": str(cfg.source), "ok": True, "drives": [d.name for d in cfg.drives],
                       "state_dir": str(cfg.state_dir)}, sys.stdout)
            sys.stdout.write("\n")
        else:
            print(f"{args.check_config}: OK: {len(cfg.drives)} drive(s): {names}; state_dir {cfg.state_dir}")
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

    s = sub.add_parser("run", parents=[common], help="run the agent service (or only check its config)")
    g = s.add_mutually_exclusive_group(required=True)
    g.add_argument("--config", metavar="FILE", help="agent config TOML (e.g. /etc/pmsm-agent/agent.toml)")
    g.add_argument("--check-config", metavar="FILE", help="validate FILE and exit: 0 if valid, 2 with the key path")
    s.set_defaults(func=cmd_run)
