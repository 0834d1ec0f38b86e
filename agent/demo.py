"""The embedded demo, offline form: a simulated gear drive learns a healthy baseline, is
monitored while healthy, then develops a transmission fault; each state transition is printed."""

from __future__ import annotations

import time
from pathlib import Path

from agent.baseline import identify_baseline
from agent.decision import diagnose
from agent.profile import load_profile
from agent.simulator import simulate

PROFILE = Path(__file__).resolve().parent.parent / "config" / "profiles" / "rig_gear.toml"
#: (condition, number of monitoring windows) after learning
SCRIPT = (("healthy", 4), ("gear_slight_wear", 3), ("gear_severe_wear", 3))


def run_offline_demo(seconds: float = 60.0, say=print, n_learn: int = 12, record_s: float = 2.0) -> list[dict]:
    """Run the story within ``seconds`` of wall time; returns the state transitions."""
    t0 = time.monotonic()
    profile = load_profile(PROFILE)
    say(f"demo: learning a healthy baseline from {n_learn} simulated records at 80 % load ...")
    healthy = [simulate(profile, "healthy", 80.0, record_s, seed=1000 + j) for j in range(n_learn)]
    base = identify_baseline(healthy, profile, window_s=record_s / 2)
    op = base.operating_point
    say(f"demo: baseline ready (fe {op['fe_hz']:.2f} Hz, load {op['load_pct']:.1f} %); monitoring")
    transitions, state, seed = [], None, 5000
    for condition, count in SCRIPT:
        for _ in range(count):
            if time.monotonic() - t0 > seconds:
                say("demo: time limit reached")
                return transitions
            seed += 1
            d = diagnose(base, simulate(profile, condition, 80.0, record_s, seed=seed))
            if d.state != state:
                t = round(time.monotonic() - t0, 2)
                transitions.append({"t": t, "condition": condition, "state": d.state,
                                    "spectrum_state": d.spectrum_state, "cluster_state": d.cluster_state})
                peaks = ", ".join(f"{p['freq_hz']:.1f} Hz ({p['family']})" for p in d.peaks[:4])
                say(f"[{t:6.2f} s] drive condition {condition}: state {state or '-'} -> {d.state.upper()} "
                    f"(spectrum {d.spectrum_state}, cluster {d.cluster_state})" + (f"; peaks {peaks}" if peaks else ""))
                state = d.state
    say("demo: done")
    return transitions
