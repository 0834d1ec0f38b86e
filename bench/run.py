"""Run every benchmark and print its figures: ``python -m bench.run [NAME ...]`` (``make bench``).

Figures are also written to ``bench/results.json`` so they can be compared between versions.
"""

from __future__ import annotations

import importlib
import json
import platform
import sys
import time
from pathlib import Path

BENCHES = ("bench_rls", "bench_identify", "bench_pipeline", "bench_explain", "bench_transports", "bench_modbus",
           "bench_zenoh")


def main(argv: list[str]) -> int:
    names = argv or BENCHES
    results = {"machine": platform.processor() or platform.machine(), "python": platform.python_version(),
               "date": time.strftime("%Y-%m-%d")}
    for name in names:
        try:
            module = importlib.import_module(f"bench.{name}")
        except ModuleNotFoundError:
            print(f"{name}: not available")
            continue
        t0 = time.perf_counter()
        results[name] = module.run()
        print(f"{name} ({time.perf_counter() - t0:.0f} s): {json.dumps(results[name], default=str)}")
    Path(__file__).with_name("results.json").write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
