"""The agent's detection on a drive nobody here wrote: motulator 0.5.0's 2.2 kW drive behind a
17/51 gear stage (bench/thirdparty/motulator_drive.py).

    python -m bench.bench_thirdparty_detection [--healthy 12] [--fresh 20] [--faulty 4] [--seconds 2]

A baseline identified (``identify_baseline``, window 1 s) from healthy records at 80 % load; then
``diagnose`` on fresh healthy records (false alarms) and on records whose load torque ripples at
the driving shaft's rotation frequency (25 Hz at rated speed), the first sign of a worn or
eccentric gear, at amplitudes from 0.005 % to 0.5 % of the rated 14 N m (detections). motulator has
no gear-mesh model: the ripple enters through its two-mass shaft, and its own speed controller
answers it. Nothing in the agent knows of this simulator. Records are cached
(bench/results/motulator_cache).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from bench.bench_workbench import RESULTS

AMPLITUDES_NM = (0.0007, 0.002, 0.007, 0.07)  #: load-torque ripple, N m (0.005, 0.014, 0.05, 0.5 % of rated)


def _records(n: int, first_seed: int, seconds: float, effects: dict, profile) -> list:
    from agent.records import load_record
    from bench.thirdparty.motulator_drive import Run, cached

    return [load_record(cached(Run(load_pct=80.0, seconds=seconds, seed=first_seed + j, effects=effects)), profile)
            for j in range(n)]


def upper95(k: int, n: int) -> float:
    """One-sided 95 % Clopper-Pearson upper bound of a rate seen k times in n independent trials."""
    import scipy.stats

    return 1.0 if k >= n else float(scipy.stats.beta.ppf(0.95, k + 1, n - k))


def run(n_healthy: int = 12, n_fresh: int = 20, n_faulty: int = 4, seconds: float = 2.0, say=print,
        amplitudes=AMPLITUDES_NM) -> dict:
    from agent.baseline import identify_baseline
    from agent.decision import diagnose
    from agent.profile import load_profile
    from bench.thirdparty.motulator_drive import PROFILE

    profile = load_profile(PROFILE)
    t0 = time.perf_counter()
    base = identify_baseline(_records(n_healthy, 0, seconds, {}, profile), profile, window_s=1.0)
    fresh = [diagnose(base, r) for r in _records(n_fresh, 100, seconds, {}, profile)]
    out = {"seconds": seconds, "healthy": n_healthy,
           "fresh": {"records": n_fresh, "states": [d.state for d in fresh],
                     "spectrum": [d.spectrum_state for d in fresh], "cluster": [d.cluster_state for d in fresh],
                     "alarms": sum(d.state != "normal" for d in fresh)}}
    out["fresh"]["alarm_rate_upper95"] = upper95(out["fresh"]["alarms"], n_fresh)
    say(f"healthy: {out['fresh']['alarms']} of {n_fresh} fresh records not normal "
        f"(95 % upper {out['fresh']['alarm_rate_upper95']:.1%}) ({time.perf_counter() - t0:.0f} s)")
    out["faulty"] = []
    for amp in amplitudes:
        ds = [diagnose(base, r) for r in _records(n_faulty, 200, seconds, {"speed_ripple": amp}, profile)]
        row = {"ripple_nm": amp, "records": n_faulty, "states": [d.state for d in ds],
               "spectrum": [d.spectrum_state for d in ds], "cluster": [d.cluster_state for d in ds],
               "families": sorted({p["family"] for d in ds for p in d.peaks})}
        out["faulty"].append(row)
        say(f"ripple {amp:g} N m: states {row['states']}, spectrum {row['spectrum']}, cluster {row['cluster']}, "
            f"families {row['families']} ({time.perf_counter() - t0:.0f} s)")
    return out


def table(res: dict) -> str:
    f = res["fresh"]
    by = {k: sum(s != "normal" for s in f[k]) for k in ("spectrum", "cluster")}
    lines = [f"Fresh healthy records ({res['seconds']:g} s, 80 % load): {f['alarms']} of {f['records']} not normal "
             f"(spectrum {by['spectrum']}, cluster {by['cluster']}; one-sided 95 % upper bound "
             f"{f['alarm_rate_upper95']:.1%} per record).", "",
             "| load-torque ripple at 25 Hz | % of rated | records: warning / caution / normal | by the spectrum | "
             "by the cluster | families named |", "|---|---|---|---|---|---|"]
    for r in res["faulty"]:
        n = {s: r["states"].count(s) for s in ("warning", "caution", "normal")}
        lines.append(f"| {r['ripple_nm']:g} N m | {100 * r['ripple_nm'] / 14.0:.2g} % | {n['warning']} / {n['caution']} / "
                     f"{n['normal']} | {sum(s != 'normal' for s in r['spectrum'])} | "
                     f"{sum(s != 'normal' for s in r['cluster'])} | {', '.join(r['families']) or '-'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--healthy", type=int, default=12, help="baseline records (default 12)")
    p.add_argument("--fresh", type=int, default=20, help="fresh healthy records (default 20)")
    p.add_argument("--faulty", type=int, default=4, help="records per ripple amplitude (default 4)")
    p.add_argument("--seconds", type=float, default=2.0, help="record length, s (default 2)")
    a = p.parse_args(argv)
    try:
        import motulator  # noqa: F401
    except ImportError:
        p.error("motulator is not installed (make setup-test installs it)")
    if a.healthy < 4:
        p.error(f"--healthy: {a.healthy} is under 4 (the parameter cluster's region)")
    if min(a.fresh, a.faulty) < 1:
        p.error("--fresh and --faulty need at least 1 record")
    if not 1.0 <= a.seconds <= 10:
        p.error(f"--seconds: {a.seconds:g} is outside 1..10 s (one 1 s window at least)")
    res = run(a.healthy, a.fresh, a.faulty, a.seconds, say=lambda s: print(s, file=sys.stderr, flush=True))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "thirdparty_detection.json").write_text(json.dumps(res, indent=1))
    print(table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
