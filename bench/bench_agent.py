"""The real agent process (``pmsm-agent run``, all its threads: reader, DSP, journal, Modbus
server, zenoh), measured from outside through /proc:

    python -m bench.bench_agent [--drives N] [--seconds S]

* throughput: N drives replaying S s of recorded signal each at speedup 0 (lossless): signal
  seconds per CPU second of the whole process, and per wall second;
* real time: the same drives at speedup 1 for 20 s: percent of one core;
* idle: the process after its sources finished (nothing to do: must not spin);
* memory: the largest resident set (VmHWM) of each run.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "config" / "profiles" / "rig_gear.toml"
TICK = os.sysconf("SC_CLK_TCK")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK  # utime + stime


def _hwm_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _config(tmp: Path, files: list[str], drives: int, speedup: float) -> Path:
    text = f'schema_version = 1\nagent_id = "bench"\nstate_dir = "{tmp / "state"}"\n'
    for j in range(drives):
        text += (f'[[drives]]\nname = "d{j}"\nprofile = "{PROFILE}"\n[drives.source]\nkind = "replay"\n'
                 f"files = {json.dumps(files)}\nspeedup = {speedup}\n")
    text += (f"[pipeline]\nauto_learn = false\n[modbus_server]\nport = {_free_port()}\n"
             f'[zenoh]\nlisten = ["tcp/127.0.0.1:{_free_port()}"]\nprefix = "bench/pmsm"\n')
    path = tmp / f"agent_{speedup:g}.toml"
    path.write_text(text)
    return path


def _run(cfg: Path, until_idle: bool, seconds: float) -> dict:
    proc = subprocess.Popen([str(ROOT / ".venv" / "bin" / "pmsm-agent"), "run", "--config", str(cfg)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        t0, c0 = time.monotonic(), _cpu_s(proc.pid)
        samples = [(t0, c0)]
        while True:
            time.sleep(0.5)
            if proc.poll() is not None:
                raise RuntimeError(f"agent exited: {proc.stderr.read()[-500:]}")
            samples.append((time.monotonic(), _cpu_s(proc.pid)))
            if not until_idle and samples[-1][0] - t0 >= seconds:
                break
            if until_idle and len(samples) > 8:
                (ta, ca), (tb, cb) = samples[-5], samples[-1]
                if (cb - ca) / (tb - ta) < 0.1 and tb - t0 > 5:  # sources done, pipeline drained
                    break
        hwm = _hwm_mb(proc.pid)
        t_end, c_end = samples[-1]
        busy_end = samples[-5] if until_idle else samples[-1]
        idle = None
        if until_idle:  # 5 s of idling after the work
            time.sleep(5.0)
            idle = (_cpu_s(proc.pid) - c_end) / (time.monotonic() - t_end)
        return {"cpu_s": busy_end[1] - c0, "wall_s": busy_end[0] - t0, "rss_max_mb": hwm, "idle_core": idle}
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)


def run(drives: int = 1, seconds: float = 120.0) -> dict:
    from agent.baseline import identify_baseline
    from agent.modelfile import save_baseline
    from agent.profile import load_profile
    from agent.records import save_record
    from agent.simulator import simulate

    profile = load_profile(PROFILE)
    with tempfile.TemporaryDirectory(prefix="bench-agent-") as tmp:
        tmp = Path(tmp)
        lib = tmp / "state" / "library"
        lib.mkdir(parents=True)
        base = identify_baseline([simulate(profile, "healthy", 80.0, 4.0, seed=7000 + j) for j in range(12)], profile)
        save_baseline(base, lib / "b80.json")
        n = max(1, int(round(seconds / 20.0)))
        files = [str(save_record(simulate(profile, "healthy", 80.0, 20.0, seed=8000 + j), tmp / f"h{j}.npz"))
                 for j in range(n)]
        signal_s = 20.0 * n * drives
        fast = _run(_config(tmp, files, drives, 0.0), until_idle=True, seconds=0)
        real = _run(_config(tmp, files, drives, 1.0), until_idle=False, seconds=20.0)
    return {"drives": drives, "signal_s": signal_s,
            "realtime_x_cpu": round(signal_s / fast["cpu_s"], 1), "realtime_x_wall": round(signal_s / fast["wall_s"], 1),
            "rss_max_mb_replay_fast": round(fast["rss_max_mb"], 1), "idle_core_pct": round(100 * fast["idle_core"], 2),
            "realtime_core_pct": round(100 * real["cpu_s"] / real["wall_s"], 2),
            "rss_max_mb_realtime": round(real["rss_max_mb"], 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.bench_agent", description=__doc__.split("\n\n")[0])
    ap.add_argument("--drives", type=int, default=1, help="drives in the agent (default 1)")
    ap.add_argument("--seconds", type=float, default=120.0, help="recorded signal per drive, s (default 120)")
    args = ap.parse_args(argv)
    if not (1 <= args.drives <= 64 and 20 <= args.seconds <= 86400):
        print("bench_agent: --drives 1..64 and --seconds 20..86400", file=sys.stderr)
        return 2
    print(json.dumps(run(args.drives, args.seconds)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
