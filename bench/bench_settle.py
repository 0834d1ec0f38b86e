"""Are the records explain names the records that settle it? A check of its forecast on the drive family.

    python -m bench.bench_settle [--seconds S] [--most N] [--jobs J]

Where a candidate explains enough but misses Holm's level, explain says how many records like these
would settle it (``records_needed``, a forecast at the measured size). This takes every such set of
``bench.bench_family``'s results for the documented workflow (bench/results/family_<S>s.jsonl: the
drive's voltage path stated, no nameplate; effect and null sets; the largest count named in the set,
up to ``--most``), records that many records like the set's (its own four, then more at the same
loads in turn, fresh noise, the same hidden effect) and runs ``model explain`` on them against the
same baseline. Per set: whether the hidden effect is now significant, and what else is claimed; on
a null set every claim is a false one. Results are appended per set to
bench/results/settle_<S>s.jsonl (a rerun resumes, unless the family's results are newer); the
markdown table goes to stdout (docs/benchmarks.md, "Workbench on a family of random drives").
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
import traceback
from pathlib import Path

from bench import bench_family as family


def named_sets(results: list, most: int) -> list[tuple]:
    """(seed, set name, records named) for every set where explain named at most ``most`` records;
    the set name is the hidden effect or "null"."""
    out = []
    for r in results:
        sets = [("null", r.get("null", {}))] + [(row["effect"], row) for row in r["rows"]]
        for name, s in sets:
            named = [n for n in (s.get("records_named") or {}).values() if n is not None]
            if named and max(named) <= most:
                out.append((r["seed"], name, max(named)))
    return out


def run_set(args: tuple) -> dict:
    """One set again with ``n`` records like its own: explain's verdicts."""
    seed, name, n, seconds = args
    from agent.workbench.explain import explain
    from agent.workbench.fitting import prepare
    from bench.family import draw_drive, draw_effect, profile

    t0 = time.perf_counter()
    out = {"seed": seed, "set": name, "records": n}
    try:
        drive = draw_drive(seed)
        prof = profile(drive, nameplate=False, timing=True)
        hidden = {} if name == "null" else {name: draw_effect(drive, name, seed)}
        doc = explain(family.baseline(drive, prof, seconds), prepare(family.hidden_records(drive, hidden, seconds, n),
                                                                     prof))
        out["claims"] = [c["effect"] for c in doc["candidates"] if c["significant"]]
        out["answer"] = doc.get("note")
    except Exception as err:  # kept with its traceback, the run goes on
        out["error"] = f"{type(err).__name__}: {err}"
        out["traceback"] = traceback.format_exc()
    out["seconds"] = time.perf_counter() - t0
    return out


def table(named: list[tuple], done: dict, first: dict) -> str:
    """Per hidden effect (then the null sets): the sets where records were named (of them, where the
    hidden effect was first), the counts named, and with that many records: the hidden effect
    significant (of all, of the first-ranked) and another effect claimed (listed)."""
    lines = ["| set | records named: sets (hidden effect first) | records named (median, range) | with them: hidden "
             "effect significant (where first) | with them: another effect claimed |", "|---|---|---|---|---|"]
    by = {}
    for seed, name, n in named:
        by.setdefault(name, []).append((seed, n))
    for name in sorted(by, key=lambda k: (k == "null", k)):
        counts = sorted(n for _, n in by[name])
        ran = {seed: done[(seed, name)] for seed, _ in by[name] if "claims" in done.get((seed, name), {})}
        tops = {seed for seed, _ in by[name] if first.get((seed, name))} & set(ran)
        hit = {seed for seed, d in ran.items() if name in d["claims"]}
        other = [f"{seed}: {', '.join(c for c in d['claims'] if c != name)}" for seed, d in ran.items()
                 if any(c != name for c in d["claims"])]
        found = "-" if name == "null" else f"{len(hit)} of {len(ran)} ({len(hit & tops)} of {len(tops)})"
        lines.append(f"| {name} | {len(counts)} ({len(tops)}) | {counts[len(counts) // 2]} ({counts[0]}-{counts[-1]}) | "
                     f"{found} | {len(other)}{' (' + '; '.join(other) + ')' if other else ''} |")
    errors = [d for d in done.values() if "error" in d]
    if errors:
        lines.append(f"\nSets that ended in an error: {len(errors)} ({errors[0]['error']})")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=1.0, help="record length of the family run, s (default 1.0)")
    p.add_argument("--most", type=int, default=12, help="sets naming more records than this are left (default 12)")
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    a = p.parse_args(argv)
    if a.most < 1 or a.jobs < 1:
        p.error("--most and --jobs must be >= 1")
    seconds = a.seconds
    src = family.RESULTS / f"family_{seconds:g}s.jsonl"  # as bench_family names the documented workflow's
    if not src.exists():
        p.error(f"{src} does not exist (run python -m bench.bench_family --seconds {seconds:g} first)")
    results = [json.loads(line) for line in src.read_text().splitlines()]
    other = next((r["seed"] for r in results if not r.get("timing", True) or r.get("nameplate")), None)
    if other is not None:
        p.error(f"{src}: drive {other} was run with another profile (reported voltage or nameplate) than the "
                f"documented workflow this reruns")
    named = named_sets(results, a.most)
    first = {(r["seed"], row["effect"]): row["rank"] == 1 for r in results for row in r["rows"]}
    out = family.RESULTS / f"settle_{seconds:g}s.jsonl"
    done = {}
    if out.exists() and out.stat().st_mtime < src.stat().st_mtime:  # its sets may be another run's
        print(f"settle: {src.name} is newer than {out.name}: every set is run again", file=sys.stderr, flush=True)
        out.unlink()
    if out.exists():
        for line in out.read_text().splitlines():
            d = json.loads(line)
            done[(d["seed"], d["set"])] = d
    todo = [(seed, name, n, seconds) for seed, name, n in named if (seed, name) not in done]
    print(f"settle: {len(named)} sets name at most {a.most} records, {len(todo)} to run on {a.jobs} process(es)",
          file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    with open(out, "a") as f, multiprocessing.get_context("spawn").Pool(a.jobs) as pool:
        for k, d in enumerate(pool.imap_unordered(run_set, todo), start=1):
            f.write(json.dumps(d) + "\n")
            f.flush()
            done[(d["seed"], d["set"])] = d
            print(f"{d['seed']} {d['set']} with {d['records']} records: {d.get('error') or d['claims'] or 'no claim'} "
                  f"({d['seconds']:.0f} s; {k}/{len(todo)}, {time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    print(table(named, done, first))
    print(f"\n{len(named)} sets; {sum(d['seconds'] for d in done.values()):.0f} s of set work; results {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
