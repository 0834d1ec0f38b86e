"""explain's significance test against two others, on the same fits over the drive family.

    python -m bench.compare_tests [--drives N] [--null N] [--jobs J] [--out FILE]

Runs the family's effect and null sets as ``bench.bench_family`` does (60 drives per effect, 300
null drives by default: about 45 min on two cores), keeps for every candidate the per-record
squared errors of the held-out segments in 0.01 s blocks (explain itself judges 0.1 s blocks, the
sums of ten), and judges each set three ways with explain's gates (identifiable, not at a bound,
not negligible, 10 % explained) and Holm's correction at 1 %:

* over records (explain's :func:`agent.workbench.explain.block_p`);
* every record on its own: each record's blocks tested alone (:func:`agent.evidence.effective_size`
  of that record: its autocorrelation within the record), the largest of the records' p
  (intersection-union);
* Fisher's combination of the records' own p.

Prints, per test, how many null drives claim, how often the hidden effect is first and
significant, and how often another effect is first. docs/workbench.md ("Claims") has the figures.
The twin, rival and forward-selection steps are not repeated here (the test over records gives
the same counts as explain's own verdicts to within one set).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
import traceback
from collections import Counter
from pathlib import Path

import numpy as np
import scipy.stats

from bench import bench_family as family

FINE_S = 0.01  #: s, the recorded blocks
COARSE = 10  #: fine blocks in one of explain's


def _coarse(h: dict) -> dict:
    out = dict(h)
    for key in ("records", "floor_records"):
        out[key] = [x[: x.size // COARSE * COARSE].reshape(-1, COARSE).sum(axis=1) for x in h[key]]
    return out


def _recording():
    """explain with its held-out blocks at FINE_S, judged at explain's own length; returns the list
    the (control, candidate) pairs of each block test are appended to."""
    import agent.workbench.explain as E
    import agent.workbench.fitting as F

    F.heldout.__defaults__ = (FINE_S,)
    seen = []
    block_p, effect_size, records_needed = E.block_p, E.effect_size, E.records_needed

    def recorded_p(ctrl, cand):
        seen.append((ctrl, cand))
        return block_p(_coarse(ctrl), _coarse(cand))

    E.block_p = recorded_p
    E.effect_size = lambda c, h, a, b: effect_size(_coarse(c), _coarse(h), a, b)
    E.records_needed = lambda c, h, alpha, most=40: records_needed(_coarse(c), _coarse(h), alpha, most)
    return seen


def run_drive(args: tuple) -> list[dict]:
    seed, with_effects = args
    from agent.effects import EFFECTS
    from agent.baseline import identify_baseline
    import agent.workbench.explain as E
    from agent.workbench.fitting import prepare
    from bench.family import draw_drive, draw_effect, profile, simulate

    seen = _recording()
    drive = draw_drive(seed)
    prof = profile(drive, nameplate=False, timing=True)
    out = []
    try:
        base = identify_baseline([simulate(drive, {}, family.BASE_LOAD, 1.0, seed=100 + j) for j in range(4)], prof,
                                 window_s=0.5)
        sets = [("null", {})] + ([(e, {e: draw_effect(drive, e, seed)}) for e in family.HEADLINE]
                                 if with_effects else [])
        for name, hidden in sets:
            recs = [simulate(drive, hidden, load, 1.0, seed=200 + j) for j, load in enumerate(family.TEST_LOADS)]
            seen.clear()
            doc = E.explain(base, prepare(recs, prof))
            rows = {c["effect"]: c for c in doc["candidates"]}
            order = [e for e in EFFECTS if e in rows]  # the order explain tests them in
            pairs = seen[: len(order)]
            rec = {"seed": seed, "set": name, "cands": []}
            if pairs:
                c0 = pairs[0][0]
                rec["ctrl"] = {"stable": c0["stable"], "a": [x.tolist() for x in c0["records"]],
                               "fa": [x.tolist() for x in c0["floor_records"]]}
            for eid, (_, h) in zip(order, pairs):
                rec["cands"].append({"effect": eid, "stable": h["stable"], "b": [x.tolist() for x in h["records"]],
                                     "fb": [x.tolist() for x in h["floor_records"]],
                                     "claimable": E._claimable(rows[eid]), "explained": rows[eid]["explained_fraction"]})
            out.append(rec)
    except Exception:
        out.append({"seed": seed, "error": traceback.format_exc()})
    return out


def records_p(ctrl: dict, cand: dict) -> list[float]:
    """Each record's own one-sided p that the candidate lowers its held-out error."""
    from agent.evidence import effective_size
    from agent.workbench.explain import one_sided_p

    ps = []
    for a, fa, b, fb in zip(ctrl["a"], ctrl["fa"], cand["b"], cand["fb"]):
        a, fa, b, fb = map(np.asarray, (a, fa, b, fb))
        ps.append(one_sided_p(*effective_size([(a - b - fa + fb) / max(float(np.mean(a)), 1e-300)])))  # one record
    return ps


def _held(r: dict, key: str, floor_key: str) -> dict:
    """A recorded set's blocks as :func:`agent.workbench.fitting.heldout` gives them, at explain's length."""
    return _coarse({"stable": True, "records": [np.asarray(x) for x in r[key]],
                    "floor_records": [np.asarray(x) for x in r[floor_key]]})


def over_records(ctrl: dict, cand: dict) -> float:
    from agent.workbench.explain import block_p

    return block_p(_held(ctrl, "a", "fa"), _held(cand, "b", "fb"))


TESTS = {"over records (explain's)": over_records,
         "every record on its own": lambda c, h: max(records_p(c, h)),
         "Fisher's combination": lambda c, h: float(scipy.stats.combine_pvalues(np.maximum(records_p(c, h), 1e-300))[1])}


def judge(lines: list[dict]) -> dict:
    from agent.workbench.explain import ALPHA, holm

    out = {name: Counter() for name in TESTS}
    for d in lines:
        if "error" in d or not d.get("cands") or not d["ctrl"]["stable"]:
            continue
        for name, test in TESTS.items():
            ps = [test(d["ctrl"], c) if c["stable"] else 1.0 for c in d["cands"]]
            sig = [c for c, r in zip(d["cands"], holm(ps, ALPHA)) if r and c["claimable"]]
            first = max(sig, key=lambda c: c["explained"] or 0.0, default=None)
            n = out[name]
            if d["set"] == "null":
                n["null sets"] += 1
                n["null drives claiming"] += first is not None
            else:
                n["effect sets"] += 1
                n["true first, significant"] += first is not None and first["effect"] == d["set"]
                n["a different effect first"] += first is not None and first["effect"] != d["set"]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--drives", type=int, default=60)
    p.add_argument("--null", type=int, default=300)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", default=str(family.RESULTS / "compare_tests.jsonl"))
    a = p.parse_args(argv)
    path = Path(a.out)
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        todo = [(family.FIRST_SEED + j, j < a.drives) for j in range(max(a.drives, a.null))]
        t0 = time.perf_counter()
        with open(path, "w") as f, multiprocessing.get_context("spawn").Pool(a.jobs) as pool:
            for k, recs in enumerate(pool.imap_unordered(run_drive, todo), 1):
                f.write("".join(json.dumps(r, default=float) + "\n" for r in recs))
                print(f"drive {k}/{len(todo)} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    for name, n in judge(lines).items():
        print(f"{name}: {dict(n)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
