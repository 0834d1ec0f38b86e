"""Resident memory of the agent's signal chain alone (run by bench.bench_pipeline).

    python -m bench.memory_child LIBRARY_DIR HOURS FRAMES_FILE...

Streams serial-bridge frame files in a loop through one drive's pipeline for HOURS of signal,
reading 64 kB at a time as a serial port would deliver them, and prints the resident set size
(MB) after each file as a JSON list. Imports only what the running agent imports.
"""

import json
import sys
from pathlib import Path

import numpy as np

from agent.library import ModelLibrary
from agent.pipeline import DriveMonitor, PipelineConfig
from agent.profile import load_profile
from firmware_if import serial_frame
from protocols.base import Block

PROFILE = Path(__file__).resolve().parent.parent / "config/profiles/rig_gear.toml"


def rss_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def main(library: str, hours: float, files: list[str]) -> None:
    profile = load_profile(PROFILE)
    rate = profile.sampling.rate_hz
    monitor = DriveMonitor("d1", profile, ModelLibrary(library), PipelineConfig())
    decoder = serial_frame.FrameDecoder()
    rss, first = [], 0
    while first < hours * 3600 * rate:
        for path in files:
            with open(path, "rb") as f:
                while chunk := f.read(65536):
                    frames = decoder.feed(chunk)
                    if frames:
                        vals = np.concatenate([fr.values() for fr in frames], axis=1)
                        monitor.process(Block("d1", rate, vals[0:3], vals[3:6], first))
                        first += vals.shape[1]
            rss.append(rss_mb())
    print(json.dumps(rss))


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), sys.argv[3:])
