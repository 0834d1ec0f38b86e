"""Decode throughput of the serial and CAN transports, in samples/s (one sample = all 6 channels).

    python -m bench.bench_transports [--samples 200000]

* ``serial_decode_*``: :class:`FrameDecoder` alone, 4 KiB feeds, 64-sample frames.
* ``serial_pty``: :class:`SerialBridgeSource` reading a pty, the emulator in a child process
  (unpaced): decoder + pyserial + pty, no GIL sharing with the device side. Wall-clock rate
  (limited by the Python emulator) and rate per CPU-second of the reading process.
* ``can_decode``: :class:`CanSource` message handling + block decode, messages pre-built (no bus).
* ``can_virtual``: :class:`CanSource` receiving from python-can's ``virtual`` bus (frames queued
  by the emulator beforehand): includes python-can's per-message cost.

``run()`` returns the figures for ``bench/run.py``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
import uuid
from types import SimpleNamespace

import can
import numpy as np

from firmware_if import can_frame as cf
from firmware_if import serial_frame as sf


def _record(n: int, fs: float = 25_000.0):
    t = np.arange(n) / fs
    ph = 2 * np.pi * 50 * t - 2 * np.pi / 3 * np.arange(3)[:, None]
    return SimpleNamespace(v_abc=300 * np.cos(ph), i_abc=8 * np.sin(ph), rate_hz=fs)


def _serial_decode(n: int, fmt: int, spf: int = 64) -> float:
    x = np.vstack([_record(spf).v_abc, _record(spf).i_abc])
    data = b"".join(sf.encode(k, x, fmt=fmt) for k in range(n // spf))
    d = sf.FrameDecoder()
    t0 = time.perf_counter()
    for k in range(0, len(data), 4096):
        d.feed(data[k:k + 4096])
    dt = time.perf_counter() - t0
    assert d.stats.frames == n // spf
    return d.stats.frames * spf / dt


def _emulate(fd: int, n: int) -> None:
    from protocols.serial_bridge import SerialBridgeEmulator
    SerialBridgeEmulator(fd, _record(n), speed=None).start().wait()


def _serial_pty(n: int) -> tuple[float, float]:
    from protocols.ptyutil import Pty
    from protocols.serial_bridge import SerialBridgeSource
    with Pty() as p:
        src = SerialBridgeSource(p.path, "bench", 25_000.0, block_samples=2500)
        src.open()
        child = mp.get_context("fork").Process(target=_emulate, args=(p.master, n))
        t0, c0 = time.perf_counter(), time.process_time()
        child.start()
        got = 0
        while got < n and time.perf_counter() - t0 < 60:
            b = src.read(0.5)
            got += b.n if b is not None else 0
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        child.join(5)
        src.close()
    return got / dt, got / cpu


def _can(n: int) -> tuple[float, float]:
    from protocols.can_bus import CanEmulator, CanSource
    lay = cf.CanLayout()
    rec = _record(n)
    msgs = [can.Message(arbitration_id=lay.phase_id, is_extended_id=True, is_fd=True, data=p)
            for p in lay.encode_phase(0, rec.v_abc, rec.i_abc)]
    src = CanSource("virtual", "unused", "bench", block_samples=2500)
    t0 = time.perf_counter()
    for m in msgs:
        src._consume(m)
    src._flush()
    decode = n / (time.perf_counter() - t0)
    assert sum(b.n for b in src._asm.ready) == n
    channel = f"bench-{uuid.uuid4().hex[:6]}"
    src = CanSource("virtual", channel, "bench", block_samples=2500)
    src.open()
    with CanEmulator({"interface": "virtual", "channel": channel}, rec, speed=None) as emu:
        emu.wait()
    t0 = time.perf_counter()
    got = 0
    while got < n:
        b = src.read(0.5)
        if b is None:
            break
        got += b.n
    virtual = got / (time.perf_counter() - t0)
    src.close()
    return decode, virtual


def run(n_samples: int = 200_000) -> dict:
    can_decode, can_virtual = _can(n_samples)
    pty_wall, pty_cpu = _serial_pty(n_samples)
    return {
        "serial_decode_int16_sps": round(_serial_decode(n_samples, sf.FMT_INT16)),
        "serial_decode_int24_sps": round(_serial_decode(n_samples, sf.FMT_INT24)),
        "serial_pty_sps": round(pty_wall),  # bound by the (Python) device emulator
        "serial_pty_reader_cpu_sps": round(pty_cpu),  # samples per CPU-second of the agent side
        "can_decode_sps": round(can_decode),
        "can_virtual_sps": round(can_virtual),
    }


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=200_000)
    for k, v in run(ap.parse_args().samples).items():
        print(f"{k:28s} {v:>12,d}")
