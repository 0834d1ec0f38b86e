"""False alarms per drive-day and detection delays, through the real streaming pipeline.

    python -m bench.bench_alarms [--hours 24] [--reps 5] [--kinds gear chain] [--out DIR]

Per drive configuration (gear, chain), in a process of its own:

1. commissioning with the agent's own learning and its default amounts (40 stretches of 30 s over
   at least 20 min, from a cold start) at each load setpoint of the plant (bench/alarm_scenarios.py);
2. ``hours`` of healthy operation with thermal drift, load wander, setpoint changes, session-to-
   session mesh ripple and sensor noise: alarm onsets (a good-quality hop that leaves "normal");
3. detection: each fault class ``reps`` times, injected at a random moment (1-10 min into
   operation, inside a session: no jump in the signal), delay to caution and to warning (capped
   at 45 min of fault).

Figures (docs/benchmarks.md, "Alarms"):

* onsets per drive-day with the exact Poisson 95 % upper bound (no onset in T days: 3.0 / T);
* the month extrapolation and its model: every CUSUM's in-control ARL (Siegmund) from the healthy
  stretch z statistics measured in the run (mean, sd, lag-1 correlation, each at its 95 % bound),
  summed over the tests; the gross path's per-window tail from the healthy window z (normal fit);
* detection delays per fault class (median and max over the repetitions).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from multiprocessing import Pool
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from agent.evidence import MONTH_S, cusum_arl, effective_size  # noqa: E402
from agent.library import ModelLibrary  # noqa: E402
from agent.pipeline import DriveMonitor, PipelineConfig  # noqa: E402
from agent.profile import load_profile  # noqa: E402
from bench.alarm_scenarios import Operation, Plant, commission, stream  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FAULTS = {"gear": ("gear_slight_wear", "gear_severe_wear", "gear_no_lubricant"),
          "chain": ("chain_offset", "chain_slight_wear", "chain_missing_tooth")}
MAX_FAULT_S = 2700.0


def poisson_upper(n: int, exposure: float, q: float = 0.95) -> float:
    """Exact (Garwood) upper confidence bound of a Poisson rate: n events in ``exposure``."""
    from scipy.stats import chi2

    return float(chi2.ppf(q, 2 * (n + 1)) / 2.0 / exposure)


def month_model(z_rows: np.ndarray, names: list[str], h: float, k: float, stretch_s: float,
                window_excess: np.ndarray) -> dict:
    """Expected false alarms per month (point and 95 % upper bound) from the healthy statistics."""
    from scipy.stats import chi2

    per_month = MONTH_S / stretch_s
    point, upper, detail = 0.0, 0.0, {}
    for j, name in enumerate(names):
        z = z_rows[:, j]
        n = z.size
        mu, sd = float(z.mean()), float(z.std(ddof=1))
        c = z - mu
        rho = float(np.clip(np.sum(c[1:] * c[:-1]) / max(np.sum(c * c), 1e-30), 0.0, 0.95))
        sd_eff = sd * math.sqrt((1 + rho) / (1 - rho))
        n_eff = n * (1 - rho) / (1 + rho)
        mu_up = mu + 1.645 * sd_eff / math.sqrt(n_eff)
        sd_up = sd_eff * math.sqrt((n_eff - 1) / chi2.ppf(0.05, max(n_eff - 1, 1)))
        arl = cusum_arl(h / sd_eff, k / sd_eff, mu / sd_eff)
        arl_up = cusum_arl(h / sd_up, k / sd_up, mu_up / sd_up)
        point += per_month / arl
        upper += per_month / arl_up
        detail[name] = {"mean": round(mu, 3), "sd": round(sd, 3), "rho": round(rho, 3), "n": n,
                        "arl_stretches": arl, "arl_stretches_upper": arl_up}
    # gross path: per feature, the healthy window z minus its threshold (one per 1 s hop), a normal
    # tail fitted to it; the hops are autocorrelated, so a month holds as many trials as independent
    # windows (effective_size, as the threshold's design counts them); mean and sd at their 95 % bounds
    from scipy.stats import norm

    g_point = g_upper = 0.0
    gross_detail = {}
    for j in range(window_excess.shape[1]):
        w = window_excess[:, j]
        _, _, n_eff = effective_size([w])
        mu, sd = float(w.mean()), float(w.std(ddof=1))
        trials = MONTH_S * n_eff / w.size  # one window per 1 s hop
        mu_up = mu + 1.645 * sd / math.sqrt(n_eff)
        sd_up = sd * math.sqrt((n_eff - 1) / chi2.ppf(0.05, max(n_eff - 1, 1)))
        g_point += trials * norm.sf(0.0, mu, sd)
        g_upper += trials * norm.sf(0.0, mu_up, sd_up)
        gross_detail[j] = {"n_eff": round(n_eff, 1), "max_excess": round(float(w.max()), 2),
                           "mean": round(mu, 3), "sd": round(sd, 3)}
    return {"cusum_per_month": point, "cusum_per_month_upper": upper, "gross_per_month": g_point,
            "gross_per_month_upper": g_upper, "tests": detail, "gross": gross_detail,
            "max_window_excess": [round(float(x), 2) for x in window_excess.max(axis=0)]}


def run_kind(kind: str, hours: float, reps: int, seed: int = 1, log=print) -> dict:
    profile = load_profile(ROOT / "config" / "profiles" / f"rig_{kind}.toml")
    plant, cfg = Plant(), PipelineConfig()
    lib = ModelLibrary(tempfile.mkdtemp(prefix=f"bench-alarms-{kind}-"))
    t0 = time.process_time()
    commissioning = {}
    for sp in plant.setpoints:
        r = commission(profile, lib, plant, sp, seed=seed * 1000 + int(sp), config=cfg)
        commissioning[r["name"]] = round(r["seconds"], 1)
        log(f"{kind}: commissioned {r['name']} in {r['seconds'] / 60:.1f} min of operation")

    # healthy operation
    mon = DriveMonitor("d1", profile, lib, cfg)
    onsets, z_rows, window_excess, prev = [], [], [], {"state": "normal"}
    gross_th = {}  #: baseline name -> its features' gross thresholds (they change only with the baseline)
    names: list[str] = []

    steps = set()

    def watch(t, st, seg):
        if seg.step is not None:
            steps.add(seg.index)
        if st.quality != "good":
            return
        if st.state != "normal" and prev["state"] == "normal":
            onsets.append({"t_s": round(t, 1), "state": st.state, "reason": st.extra.get("reason")})
            log(f"{kind}: onset at {t:.1f} s: {onsets[-1]}")
        prev["state"] = st.state
        base = lib.baselines[st.model].evidence
        if st.extra.get("settling"):
            return
        if mon.alarms.last_z and mon.alarms.last_z is not watch.last:
            watch.last = mon.alarms.last_z
            if not names:
                names.extend(mon.alarms.last_z)
            z_rows.append([mon.alarms.last_z.get(n, np.nan) for n in names])
        if st.model not in gross_th:
            gross_th[st.model] = cfg.alarm.gross_thresholds(base)[0]
        window_excess.append(base.window_z(watch.window_y) - gross_th[st.model])

    watch.last = None
    step = mon.alarms.step

    def spy(stats, prof, window_y, *a, **kw):  # the newest window's features, for the gross tail
        watch.window_y = window_y
        return step(stats, prof, window_y, *a, **kw)

    mon.alarms.step = spy
    op = Operation(plant, seed)
    hour = 0
    t_healthy = time.process_time()
    while op.t < hours * 3600 - 1e-6:
        stream(mon, op, profile, min(hours * 3600, (hour + 1) * 3600.0), watch)
        hour += 1
        log(f"{kind}: {hour} h of healthy operation, {len(onsets)} onsets, "
            f"{(time.process_time() - t_healthy) / hour:.0f} s CPU per hour")
    cpu_healthy = time.process_time() - t_healthy
    h = cfg.alarm.threshold(len(names), max(cfg.alarm.stretch_s, 30.0))
    z = np.array(z_rows, dtype=float)
    model = month_model(z[~np.isnan(z).any(axis=1)], names, h, cfg.alarm.cusum_k, cfg.alarm.stretch_s,
                        np.array(window_excess))
    gross = {name: np.round(np.append(*cfg.alarm.gross_thresholds(b.evidence)), 2).tolist()
             for name, b in lib.baselines.items()}
    days = hours / 24.0

    # detection
    rng = np.random.default_rng(seed + 17)
    detection = {}
    for fault in FAULTS[kind]:
        delays = []
        for rep in range(reps):
            onset = float(rng.uniform(60.0, 600.0))
            m = DriveMonitor("d1", profile, lib, cfg)
            first = {}

            def seen(t, st, seg, onset=onset, first=first):
                if st.quality == "good" and t >= onset and st.state != "normal" and st.state not in first:
                    first[st.state] = round(t - onset, 1)
                    if st.state == "warning":
                        first.setdefault("caution", round(t - onset, 1))
                    first.setdefault("path", (st.extra.get("reason") or {}).get("path"))
            o = Operation(plant, seed * 7919 + rep, fault=fault, fault_at_s=onset)
            stream(m, o, profile, onset + MAX_FAULT_S, seen, until=lambda first=first: "warning" in first)
            delays.append(first)
        detection[fault] = {
            "caution_s": [d.get("caution") for d in delays], "warning_s": [d.get("warning") for d in delays],
            "path": [d.get("path") for d in delays]}
        log(f"{kind}: {fault}: {detection[fault]}")
    return {"kind": kind, "hours": hours, "onsets": onsets, "onsets_per_day": len(onsets) / days,
            "onsets_per_day_upper95": poisson_upper(len(onsets), days),
            "month_model": model, "window_excess": np.array(window_excess), "threshold_h": h, "gross_thresholds": gross,
            "commissioning_s": commissioning, "load_steps_in_stream": len(steps),
            "detection": detection,
            "cpu_s": round(time.process_time() - t0, 1),
            "realtime_x": round(hours * 3600 / cpu_healthy, 1)}


def _job(args):
    kind, hours, reps = args
    return run_kind(kind, hours, reps, log=lambda s: print(s, file=sys.stderr, flush=True))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.bench_alarms", description=__doc__.split("\n\n")[0])
    ap.add_argument("--hours", type=float, default=24.0, help="healthy operation per configuration (default 24)")
    ap.add_argument("--reps", type=int, default=5, help="injections per fault class (default 5)")
    ap.add_argument("--kinds", nargs="+", default=["gear", "chain"], choices=["gear", "chain"])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results"), help="folder for alarms_<kind>.json")
    args = ap.parse_args(argv)
    if not (args.hours > 0 and args.reps >= 1):
        print("bench_alarms: --hours must be > 0 and --reps >= 1", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with Pool(min(2, len(args.kinds))) as pool:
        results = pool.map(_job, [(k, args.hours, args.reps) for k in args.kinds])
    for r in results:
        np.save(out / f"alarms_{r['kind']}_window_excess.npy", np.asarray(r.pop("window_excess"), dtype=np.float32))
        (out / f"alarms_{r['kind']}.json").write_text(json.dumps(r, indent=1, default=float))
        m = r["month_model"]
        print(f"{r['kind']}: {len(r['onsets'])} onsets in {r['hours']:g} h of healthy operation "
              f"({r['onsets_per_day']:.2f}/drive-day, 95 % upper bound {r['onsets_per_day_upper95']:.2f}); "
              f"model: {m['cusum_per_month']:.2g} (upper {m['cusum_per_month_upper']:.2g}) slow-path and "
              f"{m['gross_per_month']:.2g} (upper {m['gross_per_month_upper']:.2g}) gross false alarms per month; "
              f"{r['load_steps_in_stream']} setpoint steps in the stream; {r['realtime_x']:g} x real time")
        for fault, d in r["detection"].items():
            print(f"  {fault}: caution after {d['caution_s']} s, warning after {d['warning_s']} s ({d['path']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
