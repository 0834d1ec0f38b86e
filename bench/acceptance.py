"""Acceptance experiments on the rig simulator: the paper's Table 4 and Table 5 patterns.

    python -m bench.acceptance            # full form: 30 healthy + 30 faulty per condition, 4 s records
    python -m bench.acceptance --quick    # the short form that `make test` runs

Table 4: per transmission, a baseline from healthy records at 80 % load, then every fault
condition diagnosed; the majority spectrum and cluster states must follow the paper's pattern,
and fresh healthy records must read "normal" in at least 95 % of cases.
Table 5: models identified at 58, 73 and 80 % load, each evaluated (free-run NRMSE) on held-out
records of every load; the diagonal must be the lowest of each row.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from agent.baseline import identify_baseline
from agent.decision import diagnose
from agent.identify import record_signals
from agent.model import nrmse
from agent.profile import load_profile
from agent.simulator import simulate

ROOT = Path(__file__).resolve().parent.parent
PROFILES = {"gear": ROOT / "config/profiles/rig_gear.toml", "chain": ROOT / "config/profiles/rig_chain.toml"}

#: The paper's Table 4: condition -> (residual-spectrum state, parameter-cluster state).
TABLE4 = {
    "gear": {"gear_slight_wear": ("caution", "normal"), "gear_severe_wear": ("warning", "warning"),
             "gear_no_lubricant": ("warning", "warning")},
    "chain": {"chain_offset": ("warning", "warning"), "chain_slight_wear": ("normal", "warning"),
              "chain_missing_tooth": ("warning", "warning")},
}
TABLE5_LOADS = (58.0, 73.0, 80.0)


def _batch(profile, condition, load, seconds, n, seed0):
    return [simulate(profile, condition, load, seconds, seed=seed0 + j) for j in range(n)]


def table4(kind: str, n_healthy=30, n_faulty=30, n_fresh=40, seconds=4.0, window_s=2.0, say=print) -> dict:
    """Baseline at 80 % load, then diagnose every fault condition and fresh healthy records."""
    profile = load_profile(PROFILES[kind])
    t0 = time.perf_counter()
    base = identify_baseline(_batch(profile, "healthy", 80.0, seconds, n_healthy, 10_000), profile,
                             window_s=window_s)
    t_identify = time.perf_counter() - t0
    out = {"identify_s": t_identify, "conditions": {}}
    fresh = [diagnose(base, r) for r in _batch(profile, "healthy", 80.0, seconds, n_fresh, 20_000)]
    out["fresh_normal_fraction"] = sum(d.state == "normal" for d in fresh) / n_fresh
    out["fresh_states"] = dict(Counter(d.state for d in fresh))
    for j, (cond, expected) in enumerate(TABLE4[kind].items()):
        ds = [diagnose(base, r) for r in _batch(profile, cond, 80.0, seconds, n_faulty, 30_000 + 1000 * j)]
        spec = Counter(d.spectrum_state for d in ds)
        clus = Counter(d.cluster_state for d in ds)
        got = (spec.most_common(1)[0][0], clus.most_common(1)[0][0])
        out["conditions"][cond] = {"expected": expected, "majority": got, "spectrum": dict(spec),
                                   "cluster": dict(clus), "match": got == expected}
        say(f"{kind:5} {cond:20} expected {expected[0]:7}/{expected[1]:7}  got {got[0]:7}/{got[1]:7}  "
            f"spectrum {dict(spec)} cluster {dict(clus)}")
    say(f"{kind:5} fresh healthy records normal: {out['fresh_normal_fraction']:.1%} {out['fresh_states']}")
    return out


def table5(n_train=8, n_test=4, seconds=2.0, say=print) -> dict:
    """Cross-evaluation of models identified at three loads (rows: measured load, columns: model load)."""
    profile = load_profile(PROFILES["gear"])
    models = {}
    for load in TABLE5_LOADS:
        base = identify_baseline(_batch(profile, "healthy", load, seconds, n_train, 40_000 + int(load) * 100),
                                 profile, window_s=seconds / 2)
        models[load] = base.model
    matrix = np.zeros((len(TABLE5_LOADS), len(TABLE5_LOADS)))
    for r, load in enumerate(TABLE5_LOADS):
        sigs = [record_signals(rec, profile)
                for rec in _batch(profile, "healthy", load, seconds, n_test, 50_000 + int(load) * 100)]
        for c, mload in enumerate(TABLE5_LOADS):
            matrix[r, c] = np.mean([nrmse(s.i_dq, models[mload].simulate(s))["total"] for s in sigs])
    say("Table 5 (free-run NRMSE %, rows = measured load, columns = model load)")
    say("         " + "".join(f"{m:>9.0f}%" for m in TABLE5_LOADS))
    for r, load in enumerate(TABLE5_LOADS):
        say(f"{load:7.0f}% " + "".join(f"{100 * v:9.2f}%" for v in matrix[r]))
    diagonal_lowest = all(np.argmin(matrix[r]) == r for r in range(len(TABLE5_LOADS)))
    return {"loads": TABLE5_LOADS, "nrmse": matrix.tolist(), "diagonal_lowest": diagonal_lowest}


def run(quick: bool = False, say=print) -> dict:
    n = dict(n_healthy=12, n_faulty=8, n_fresh=30, seconds=2.0, window_s=1.0) if quick else {}
    t0 = time.perf_counter()
    result = {kind: table4(kind, say=say, **n) for kind in ("gear", "chain")}
    result["table5"] = table5(**(dict(n_train=6, n_test=3) if quick else {}), say=say)
    result["seconds"] = time.perf_counter() - t0
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the short form run by `make test`")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    result = run(quick=args.quick)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=str))
    ok = all(c["match"] for k in ("gear", "chain") for c in result[k]["conditions"].values())
    ok &= all(result[k]["fresh_normal_fraction"] >= 0.95 for k in ("gear", "chain"))
    ok &= result["table5"]["diagonal_lowest"]
    print(f"acceptance {'PASSED' if ok else 'FAILED'} in {result['seconds']:.0f} s")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
