"""Run benchmarks and print their figures: ``python -m bench.run [NAME ...]`` (``make bench``).

Figures are also written to ``bench/results/results.json`` (git-ignored) so they can be compared
between versions. The long ones have commands of their own: ``python -m bench.bench_alarms``
(``make bench-alarms``, about an hour) and ``python -m bench.acceptance``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import sys
import time
from pathlib import Path

BENCHES = ("bench_rls", "bench_identify", "bench_pipeline", "bench_agent", "bench_explain", "bench_transports", "bench_modbus",
           "bench_zenoh")
RESULTS = Path(__file__).resolve().parent / "results" / "results.json"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.run", description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", metavar="NAME", help=f"benchmarks to run (default all: {', '.join(BENCHES)})")
    ap.add_argument("--out", default=str(RESULTS), help=f"results file (default {RESULTS.relative_to(RESULTS.parents[2])})")
    args = ap.parse_args(argv)
    unknown = [n for n in args.names if n not in BENCHES]
    if unknown:
        print(f"python -m bench.run: error: unknown benchmark {unknown[0]!r} (known: {', '.join(BENCHES)})",
              file=sys.stderr)
        return 2
    results = {"machine": platform.processor() or platform.machine(), "python": platform.python_version(),
               "date": time.strftime("%Y-%m-%d")}
    for name in args.names or BENCHES:
        module = importlib.import_module(f"bench.{name}")
        t0 = time.perf_counter()
        results[name] = module.run()
        print(f"{name} ({time.perf_counter() - t0:.0f} s): {json.dumps(results[name], default=str)}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
