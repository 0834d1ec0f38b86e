"""identify on 30 healthy 4 s records plus diagnose of one 4 s record at 25 kHz, one core.

    python -m bench.bench_identify

Targets (issue: foundation): identify < 5 s, diagnose < 0.2 s. Records are simulated beforehand
and held in memory, so the figures are the signal chain's, not the simulator's or the disk's.
"""

from __future__ import annotations

import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from agent.baseline import identify_baseline  # noqa: E402
from agent.decision import diagnose  # noqa: E402
from agent.profile import load_profile  # noqa: E402
from agent.simulator import simulate  # noqa: E402
from bench.acceptance import PROFILES  # noqa: E402


def run(n_records: int = 30, seconds: float = 4.0, repeat: int = 3) -> dict:
    profile = load_profile(PROFILES["gear"])
    records = [simulate(profile, "healthy", 80.0, seconds, seed=s) for s in range(n_records)]
    probe = simulate(profile, "gear_severe_wear", 80.0, seconds, seed=999)
    identify_baseline(records[:4], profile)  # compile numba kernels once
    t_id, t_dx = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        base = identify_baseline(records, profile)
        t_id.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        diagnose(base, probe)
        t_dx.append(time.perf_counter() - t0)
    return {"identify_s": min(t_id), "diagnose_s": min(t_dx), "records": n_records, "seconds_each": seconds,
            "identify_target_s": 5.0, "diagnose_target_s": 0.2}


if __name__ == "__main__":
    r = run()
    print(f"identify {r['records']} x {r['seconds_each']:.0f} s records: {r['identify_s']:.2f} s "
          f"(target < {r['identify_target_s']} s)")
    print(f"diagnose one record: {r['diagnose_s'] * 1e3:.0f} ms (target < {r['diagnose_target_s'] * 1e3:.0f} ms)")
