"""``pmsm-agent demo``: the embedded default (CONTRACT section 6), within 60 s of wall time.

The shipped ``config/agent.toml`` with a simulated gear drive, accelerated: healthy first (the
agent learns a baseline for the operating point, then monitors), then a slightly and a severely
worn driven-gear tooth. Modbus TCP on 127.0.0.1:5020, zenoh peer on tcp/127.0.0.1:7447 with prefix
``pmsm/demo``; loopback only, no multicast. Every state and quality transition is printed as it
happens. A fresh state directory is used, so every demo learns from scratch.
"""

from __future__ import annotations

import dataclasses
import signal
import tempfile
import threading
import time
from pathlib import Path

from agent.errors import InputError

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "config" / "agent.toml"
SPEEDUP = 12.0  #: simulated seconds per wall second
#: A demonstration commissioning, far shorter than a plant's (40 stretches of 30 s over >= 20 min,
#: the amounts behind the false-alarm figures): 16 spans for the parameters, then 16 stretches of 8 s.
DEMO_LEARNING = {"learn_windows": 16, "learn_stretches": 16, "learn_min_s": 0.0, "stretch_s": 8.0}
#: (condition, simulated seconds): the demo's learning takes about 220 s of healthy signal
SCRIPT = (("healthy", 360.0), ("gear_slight_wear", 120.0), ("gear_severe_wear", 120.0))
WALL_LIMIT_S = 60.0


def demo_config(state_dir: Path):
    """The embedded default config, with the demo's schedule, speed and a private state dir."""
    from agent.runtime.config import LibraryCfg, Phase, check_config

    if not DEFAULT_CONFIG.is_file():
        raise InputError("the embedded default config is missing (run from the project checkout)",
                         source=str(DEFAULT_CONFIG))
    cfg = check_config(DEFAULT_CONFIG)
    drive = cfg.drives[0]
    source = dataclasses.replace(drive.source, speedup=SPEEDUP, loop=False,
                                 schedule=tuple(Phase(condition=c, seconds=s) for c, s in SCRIPT))
    return dataclasses.replace(cfg, state_dir=state_dir, library=LibraryCfg(path=state_dir / "library"),
                               pipeline=dataclasses.replace(cfg.pipeline, **DEMO_LEARNING),
                               drives=(dataclasses.replace(drive, source=source),))


def run_demo(seconds: float = WALL_LIMIT_S, say=print, until_learned: bool = False) -> list[dict]:
    """Run the demo for at most ``min(seconds, 60)`` s (``until_learned``: only until its baseline is
    learned); returns the transitions."""
    from agent.runtime.service import Service

    transitions: list[dict] = []
    t0 = time.monotonic()

    def on_transition(drive: str, kind: str, detail: dict) -> None:
        t = round(time.monotonic() - t0, 2)
        if kind in ("state", "quality"):
            item = {"t": t, "drive": drive, "kind": kind, "from": detail.get("from"), "to": detail.get("to"),
                    "fe_hz": detail.get("fe_hz"), "load_pct": detail.get("load_pct"),
                    "peaks": sorted({round(p["freq_hz"], 1) for p in detail.get("peaks", [])})}
            transitions.append(item)
            peaks = ", ".join(f"{f:.1f}" for f in item["peaks"][:4])
            say(f"[{t:6.2f} s] {drive}: {kind} {item['from']} -> {item['to'].upper()}"
                + (f" (residual lines at {peaks} Hz)" if peaks else ""))
        elif kind == "learning":
            what = detail.get("phase") or (f"{detail.get('progress_pct', 0):.0f} %, about "
                                           f"{detail.get('remaining_s', 0):.0f} s of operation more")
            say(f"[{t:6.2f} s] {drive}: learning a baseline ({what})")
        elif kind == "learning_refused":
            say(f"[{t:6.2f} s] {drive}: learning refused: {detail.get('reason')}")
        elif kind == "learned":
            op = detail.get("operating_point", {})
            say(f"[{t:6.2f} s] {drive}: baseline learned at fe {op.get('fe_hz', 0):.1f} Hz, "
                f"load {op.get('load_pct', 0):.0f} % -> {detail.get('path')}")
            if until_learned:
                service.stop_event.set()

    import logging

    # the demo prints every transition itself: the service's journald lines would repeat them
    logging.getLogger("pmsm-agent.transitions").setLevel(logging.ERROR)
    with tempfile.TemporaryDirectory(prefix="pmsm-demo-") as state:
        cfg = demo_config(Path(state))
        say(f"demo: simulated gear drive at {SPEEDUP:g}x real time; Modbus TCP on "
            f"{cfg.modbus_server.host}:{cfg.modbus_server.port}, zenoh {', '.join(cfg.zenoh.listen)} prefix "
            f"{cfg.zenoh.prefix}; script: " + ", ".join(f"{c} {s:g} s" for c, s in SCRIPT))
        service = Service(cfg, on_transition)
        if threading.current_thread() is threading.main_thread():  # SIGTERM/SIGINT end the demo, its temp dir removed
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: service.stop_event.set())
        # the whole demo, start-up and shut-down included, stays within the limit
        service.run(max_seconds=max(1.0, min(seconds, WALL_LIMIT_S) - (time.monotonic() - t0) - 3.0))
    say(f"demo: done after {time.monotonic() - t0:.1f} s, {len(transitions)} transitions")
    return transitions
