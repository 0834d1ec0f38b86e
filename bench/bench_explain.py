"""``model explain`` speed: four 4 s records at 25 kHz, every library effect as a candidate, one core.

    python -m bench.bench_explain [--seconds 4] [--records 4]

``run()`` returns a dict of figures (target: ``explain_s`` < 5 s). The records hold a hidden
flux harmonic at two loads; the baseline is identified at 80 % load on separate records.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run(seconds: float = 4.0, n_records: int = 4, effect: str = "flux_harmonics") -> dict:
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    from agent.baseline import identify_baseline
    from agent.profile import load_profile
    from agent.simulator import simulate
    from agent.workbench.explain import explain
    from agent.workbench.fitting import prepare

    profile = load_profile(ROOT / "config/profiles/rig_gear.toml")
    base = identify_baseline([simulate(profile, "healthy", 80.0, 1.0, seed=900 + j) for j in range(4)], profile,
                             window_s=0.5)
    recs = [simulate(profile, "healthy", (60.0, 100.0)[j % 2], seconds, seed=950 + j, effects={effect: None})
            for j in range(n_records)]
    explain(base, prepare(recs[:1], profile))  # compile the numba kernels outside the timing
    t0 = time.perf_counter()
    preps = prepare(recs, profile)
    doc = explain(base, preps)
    t = time.perf_counter() - t0
    top = doc["candidates"][0]
    return {"records": n_records, "seconds_per_record": seconds, "samples": sum(r.n for r in recs),
            "candidates": len(doc["candidates"]), "explain_s": t, "top": top["effect"],
            "top_explained": top["explained_fraction"], "nrmse_control": doc["nrmse_control"],
            "nrmse_top": top["nrmse_after"]}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=4.0)
    p.add_argument("--records", type=int, default=4)
    a = p.parse_args(argv)
    r = run(a.seconds, a.records)
    print(f"explain: {r['records']} x {r['seconds_per_record']:g} s records ({r['samples']} samples), "
          f"{r['candidates']} candidate effects: {r['explain_s']:.2f} s (target < 5 s)")
    print(f"  top: {r['top']} explains {100 * r['top_explained']:.1f} % "
          f"(NRMSE {100 * r['nrmse_control']:.3f} % -> {100 * r['nrmse_top']:.3f} %)")
    return r


if __name__ == "__main__":
    main()
