"""The edge agent's signal chain for one drive at 25 kHz x 6 channels, parsing included.

    python -m bench.bench_pipeline [--hours H]

* throughput: serial-bridge frames (int16, 512 samples per frame) -> decoder -> blocks -> pipeline,
  in multiples of real time on one core (target >= 50 x);
* memory: resident set size over ``hours`` of accelerated streaming (target < 150 MB and
  < 1 MB growth after the first minute of signal);
* latency: from a transmission fault's onset in the signal to the first status that is not
  "normal" (target <= one span + 1 s of signal).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from agent.baseline import identify_baseline  # noqa: E402
from agent.library import ModelLibrary  # noqa: E402
from agent.pipeline import DriveMonitor, PipelineConfig  # noqa: E402
from agent.profile import load_profile  # noqa: E402
from agent.simulator import simulate  # noqa: E402
from bench.acceptance import PROFILES  # noqa: E402
from firmware_if import serial_frame  # noqa: E402
from protocols.base import Block  # noqa: E402

SAMPLES_PER_FRAME = 512  # ~20 ms of signal per frame, 6 kB: the bridge's recommended setting


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _library(profile, config: PipelineConfig) -> ModelLibrary:
    span_s = config.window_s * config.span_windows
    records = [simulate(profile, "healthy", 80.0, span_s, seed=7000 + j) for j in range(30)]
    lib = ModelLibrary(tempfile.mkdtemp(prefix="bench-lib-"))
    lib.add("gear80", identify_baseline(records, profile, window_s=config.window_s))
    return lib


def _frames(record) -> bytes:
    """The record as serial-bridge frames, as the drive would send them."""
    values = np.vstack((record.v_abc, record.i_abc))
    n = record.n - record.n % SAMPLES_PER_FRAME
    return b"".join(serial_frame.encode(j, values[:, k:k + SAMPLES_PER_FRAME])
                    for j, k in enumerate(range(0, n, SAMPLES_PER_FRAME)))


def _stream(monitor: DriveMonitor, payload: bytes, rate: float, first: int, chunk: int = 65536) -> tuple[int, list]:
    """Feed bytes through the decoder into the monitor; returns (next first sample, statuses)."""
    decoder = serial_frame.FrameDecoder()
    out = []
    for pos in range(0, len(payload), chunk):
        frames = decoder.feed(payload[pos:pos + chunk])
        if not frames:
            continue
        vals = np.concatenate([f.values() for f in frames], axis=1)
        first += vals.shape[1]
        out += [(first, status) for status in monitor.process(Block("d1", rate, vals[0:3], vals[3:6],
                                                                     first - vals.shape[1]))]
    return first, out


def run(hours: float = 0.25, throughput_s: float = 60.0) -> dict:
    profile = load_profile(PROFILES["gear"])
    rate = profile.sampling.rate_hz
    config = PipelineConfig()
    lib = _library(profile, config)
    monitor = DriveMonitor("d1", profile, lib, config)
    healthy = [_frames(simulate(profile, "healthy", 80.0, 20.0, seed=8000 + j)) for j in range(3)]

    # throughput, parsing included (the first pass warms up caches and the model library)
    first, _ = _stream(monitor, healthy[0], rate, 0)
    t0 = time.process_time()
    signal_s = 0.0
    while signal_s < throughput_s:
        for payload in healthy:
            first, _ = _stream(monitor, payload, rate, first)
            signal_s += 20.0
    cpu = time.process_time() - t0
    realtime = signal_s / cpu

    # memory over `hours` of accelerated streaming, in a process that holds only the agent's parts
    with tempfile.TemporaryDirectory() as tmp:
        files = []
        for j, payload in enumerate(healthy):
            files.append(os.path.join(tmp, f"frames{j}.bin"))
            with open(files[-1], "wb") as f:
                f.write(payload)
        proc = subprocess.run([sys.executable, "-m", "bench.memory_child", str(lib.directory), str(hours), *files], capture_output=True, text=True, check=True,
                              cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        rss = json.loads(proc.stdout.strip().splitlines()[-1])

    # latency: healthy, then a fault from sample `onset` on, no gap in between
    onset_s = 30.0
    monitor = DriveMonitor("d2", profile, lib, config)
    pre = simulate(profile, "healthy", 80.0, onset_s, seed=9001)
    post = simulate(profile, "gear_severe_wear", 80.0, 20.0, seed=9002)
    onset, _ = _stream(monitor, _frames(pre), rate, 0)
    alarms = [end for end, status in _stream(monitor, _frames(post), rate, onset)[1] if status.state != "normal"]
    latency = (alarms[0] - onset) / rate if alarms else None
    span_s = config.window_s * config.span_windows
    return {"realtime_x": realtime, "realtime_target_x": 50.0, "rss_mb_max": max(rss),
            "rss_growth_mb": max(rss) - rss[min(3, len(rss) - 1)], "hours_streamed": hours,
            "latency_s": latency, "latency_target_s": span_s + 1.0}


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--hours", type=float, default=1.0)
    r = run(hours=ap.parse_args().hours)
    print(f"throughput: {r['realtime_x']:.0f} x real time (target >= {r['realtime_target_x']:.0f} x)")
    print(f"memory: max RSS {r['rss_mb_max']:.0f} MB, growth {r['rss_growth_mb']:.2f} MB over "
          f"{r['hours_streamed']:.2f} h of signal (targets < 150 MB, < 1 MB)")
    print(f"latency: fault onset -> alarm {r['latency_s']} s of signal (target <= {r['latency_target_s']:.0f} s)")
