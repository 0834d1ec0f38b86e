"""Zenoh state latency on loopback: ZenohSink.publish() -> subscriber callback, vs a bare put.

    python -m bench.bench_zenoh [--n 1000]

Two peer sessions on tcp/127.0.0.1 (multicast off). ``run()`` returns a dict of figures.
"""

from __future__ import annotations

import argparse
import socket
import statistics
import threading
import time

import zenoh

from protocols.base import DriveStatus
from protocols.zenoh_sink import ZenohSink, zenoh_config


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stats(xs: list[float]) -> dict:
    q = statistics.quantiles(xs, n=100)
    return {"median_us": statistics.median(xs) * 1e6, "p99_us": q[98] * 1e6, "max_us": max(xs) * 1e6}


def run(n: int = 1000) -> dict:
    """Time ``n`` state changes one at a time (each waits for its delivery)."""
    port, fast = _free_port(), {"scouting/delay": 0}
    scada = zenoh.open(zenoh_config("peer", [f"tcp/127.0.0.1:{port}"], [], fast))
    arrived, cond = [], threading.Condition()

    def on_sample(_s):
        with cond:
            arrived.append(time.perf_counter())
            cond.notify()

    sub = scada.declare_subscriber("bench/pmsm/**", on_sample)
    sink = ZenohSink(zenoh_config("peer", [], [f"tcp/127.0.0.1:{port}"], fast), "bench/pmsm", "bench",
                     drives=["d1"], period_s=3600.0, diagnostics_period_s=3600.0)
    sink.open()
    raw = sink._session.declare_publisher("bench/pmsm/raw", congestion_control=zenoh.CongestionControl.BLOCK,
                                          priority=zenoh.Priority.REAL_TIME, express=True)
    time.sleep(0.3)

    def one(send) -> tuple[float, float]:
        with cond:
            k = len(arrived)
        t0 = time.perf_counter()
        send()
        t_call = time.perf_counter() - t0
        with cond:
            if not cond.wait_for(lambda: len(arrived) > k, 2.0):
                raise RuntimeError("sample lost on loopback")
            return arrived[k] - t0, t_call

    sink_lat, sink_call, raw_lat = [], [], []
    try:
        for i in range(n):
            st = DriveStatus("d1", state=("normal", "caution")[i % 2], quality="good", fe_hz=100.0, load_pct=80.0,
                             t=time.time())
            lat, call = one(lambda: sink.publish(st))
            sink_lat.append(lat), sink_call.append(call)
            raw_lat.append(one(lambda: raw.put('{"state":"normal"}'))[0])
    finally:
        raw.undeclare()
        sink.close()
        sub.undeclare()
        scada.close()
    return {"n": n, "sink_publish_to_subscriber": _stats(sink_lat), "sink_publish_call": _stats(sink_call),
            "bare_put_to_subscriber": _stats(raw_lat)}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1000)
    r = run(p.parse_args(argv).n)
    print(f"zenoh loopback, {r['n']} state changes (tcp/127.0.0.1, peer-to-peer, BLOCK + express)")
    for key in ("sink_publish_to_subscriber", "sink_publish_call", "bare_put_to_subscriber"):
        s = r[key]
        print(f"  {key:<28}: median {s['median_us']:7.0f} us   p99 {s['p99_us']:7.0f} us   max {s['max_us']:7.0f} us")
    return r


if __name__ == "__main__":
    main()
