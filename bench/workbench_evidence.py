"""Model-workbench evidence on the rig simulator (docs/workbench.md, "Measured figures").

    python -m bench.workbench_evidence [--seconds 1.2]

For every effect of the library, records in which the simulator has the effect while the baseline
(identified at 80 % load on records without it) lacks it. ``model explain`` must rank it first and
significant; the refit with it must have at most half the held-out free-run NRMSE of the refit
without it and of every refit with a wrong effect; its headline parameter must be within 20 % of
the simulator's value. Plus a null set (no hidden effect: nothing significant). The tests
(tests/test_workbench.py) run the same scenarios.
"""

from __future__ import annotations

import argparse
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from agent.baseline import identify_baseline
from agent.profile import load_profile, parse_profile
from agent.simulator import simulate

ROOT = Path(__file__).resolve().parent.parent
GEAR_PATH = ROOT / "config/profiles/rig_gear.toml"
GEAR = load_profile(GEAR_PATH)
_doc = tomllib.loads(GEAR_PATH.read_text())
_doc["sampling"]["voltage_source"] = "reference"
#: the rig with the drive's voltage command recorded instead of the terminal voltage (dead time shows)
GEAR_REF = parse_profile(_doc, source="rig_gear_reference")


def _mean_dr_dt(recs) -> float:
    """The records' mean dR_s/dt, ohm/s."""
    return float(np.mean([(r.meta["R_s_end"] - r.meta["R_s"]) / r.meta["seconds"] for r in recs]))


#: effect -> (simulator value, loads %, profile, headline key, the headline's true value from the records)
SCENARIOS = {
    "current_offset": (0.1, (80.0,), GEAR, "offset_A", lambda recs: 0.1),
    "current_gain_mismatch": (0.03, (80.0,), GEAR, "gain_b", lambda recs: 0.03),
    "resistance_drift": (0.2, (60.0, 100.0), GEAR, "dR_dt_ohm_per_s", _mean_dr_dt),
    "voltage_delay": (1.0, (60.0, 100.0), GEAR, "delay_samples", lambda recs: 1.0),
    "flux_harmonics": (0.005, (80.0,), GEAR, "psi_5_Wb", lambda recs: 0.0025),  # psi_6 = 0.005: 5th = 7th = 0.0025
    "magnetic_saturation": (0.15, (50.0, 80.0, 110.0), GEAR, "lq_drop_at_rated", lambda recs: 0.15),
    # 10 V ~ 540 V x 2 us x 8 kHz + 1.5 V device drop
    "inverter_deadtime": (10.0, (50.0, 80.0, 110.0), GEAR_REF, "U_dt_V", lambda recs: 10.0),
    "speed_ripple": (1.0, (80.0,), GEAR, "omega_e_ripple_rad_s",
                     lambda recs: float(np.mean([r.meta["speed_ripple_omega_e"] for r in recs]))),
}

#: further figures judged like the headline (the same true value)
MORE = {"flux_harmonics": ("psi_7_Wb",)}
#: the figure judged where the records leave the headline null (the simulator holds its voltage in abc: advance 0)
ALT = {"voltage_delay": "rotation_samples"}


def baseline(profile, seed: int = 700):
    """The model under test: four healthy 1 s records at 80 % load."""
    return identify_baseline([simulate(profile, "healthy", 80.0, 1.0, seed=seed + j) for j in range(4)], profile,
                             window_s=0.5)


def scenario_records(effect: str | None, seconds: float, seed: int = 100) -> list:
    """At least four records with ``effect`` at its scenario's value, cycling through its loads
    (``None``: the null set, four healthy records at 80 %)."""
    if effect is None:
        return [simulate(GEAR, "healthy", 80.0, seconds, seed=seed + j) for j in range(4)]
    value, loads, prof, _, _ = SCENARIOS[effect]
    return [simulate(prof, "healthy", loads[j % len(loads)], seconds, seed=seed + j, effects={effect: value})
            for j in range(max(4, len(loads)))]


def judge(effect: str, recs: list, doc: dict) -> dict:
    """The brief's figures of one scenario from its ``explain`` document (:func:`bench.bench_workbench.judge`)."""
    from bench.bench_workbench import judge as judge_doc

    _, _, _, key, truth = SCENARIOS[effect]
    return judge_doc(doc, effect, key, truth(recs), MORE.get(effect, ()), ALT.get(effect, ""))


def run(seconds: float = 1.2, say=print) -> dict:
    from agent.workbench.explain import explain
    from agent.workbench.fitting import prepare

    bases = {p.name: baseline(p) for p in (GEAR, GEAR_REF)}
    rows = []
    for effect, (_, _, prof, _, _) in SCENARIOS.items():
        t0 = time.perf_counter()
        recs = scenario_records(effect, seconds)
        rows.append(judge(effect, recs, explain(bases[prof.name], prepare(recs, prof))))
        say(f"{effect}: {time.perf_counter() - t0:.1f} s")
    null = explain(bases[GEAR.name], prepare(scenario_records(None, seconds), GEAR))
    return {"seconds": seconds, "rows": rows,
            "null_significant": [c["effect"] for c in null["candidates"] if c["significant"]],
            "null_max_explained": max(c["explained_fraction"] for c in null["candidates"])}


def table(result: dict) -> str:
    """The markdown table of docs/workbench.md."""
    lines = ["| hidden effect | loads | rank, significant | NRMSE control -> with it (best wrong) | fitted (true) |",
             "|---|---|---|---|---|"]
    for r in result["rows"]:
        value, loads, _, _, _ = SCENARIOS[r["effect"]]
        lines.append(f"| {r['effect']} {value:g} | {', '.join(f'{x:g}' for x in loads)} % | {r['rank']}, "
                     f"{'yes' if r['significant'] else 'no'} | {100 * r['nrmse_control']:.2f} % -> "
                     f"{100 * r['nrmse_after']:.2f} % ({100 * r['nrmse_best_wrong']:.2f} %) | {r['key']} "
                     f"{r['fitted']:.4g} ({r['true']:.4g}, {100 * r['error']:+.0f} %) |")
    lines.append(f"| none (null set) | 80 % | significant: {', '.join(result['null_significant']) or 'none'} | "
                 f"largest explained share {100 * result['null_max_explained']:.1f} % | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=1.2, help="record length, s (default 1.2, as `make test`)")
    a = p.parse_args(argv)
    print(table(run(a.seconds, say=lambda s: print(s, file=sys.stderr))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
