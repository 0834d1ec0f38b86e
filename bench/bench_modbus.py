"""Snapshot read time over Modbus: ModbusSnapshotSource against DriveModbusEmulator on loopback
TCP and on RTU over a pty null-modem (no baud-rate limit), plus PlcModbusServer.publish cost.

    python -m bench.bench_modbus        (or: python -m bench.run bench_modbus)

``run()`` returns a dict of figures for ``bench/run.py``. Times are best of ``repeats``:
``*_ms`` from the trigger to the verified snapshot (the source first waits N/fs, the capture
time of a real drive), ``*_transfer_ms`` the sample reads alone (ceil(6N/120) FC4 requests plus
a window write per 10 000 samples). Real RTU is bound by the line: 6N registers * 2 bytes * 10 bits / baud.
"""

from __future__ import annotations

import json
import time

import numpy as np

from protocols.base import DriveStatus
from protocols.modbus_drive import DriveModbusEmulator, ModbusSnapshotSource, SnapshotSourceConfig
from protocols.modbus_plc import PlcModbusServer
from protocols.ptyutil import PtyNullModem

FS = 25_000.0


def _gen(first, n):
    k = first + np.arange(n)
    return np.vstack([np.sin(2 * np.pi * k / 500 + c) * (300 if c < 3 else 5) for c in range(6)])


def _time_snapshots(src: ModbusSnapshotSource, repeats: int) -> tuple[float, float]:
    """Best total time per snapshot (includes waiting N/fs for the drive to capture) and best
    transfer time (the sample reads alone), s."""
    best, transfer = np.inf, np.inf
    while src.read(10.0) is None:  # warm-up: the source learns the sample rate from the header
        pass
    for _ in range(repeats):
        t0 = time.perf_counter()
        b = None
        while b is None:
            b = src.read(10.0)
        best = min(best, time.perf_counter() - t0)
        transfer = min(transfer, src.stats.last_transfer_s)
    return best, transfer


def run(sizes=(1000, 2500, 10_000, 25_000), rtu_sizes=(1000, 2500), repeats: int = 3) -> dict:
    out: dict = {"tcp_ms": {}, "tcp_transfer_ms": {}, "rtu_pty_ms": {}, "rtu_pty_transfer_ms": {}}
    with DriveModbusEmulator(_gen, rate_hz=FS, capture_time_s=0.0) as emu:
        for n in sizes:
            src = ModbusSnapshotSource(SnapshotSourceConfig(port=emu.address[1], samples=n))
            best, transfer = _time_snapshots(src, repeats)
            src.close()
            out["tcp_ms"][n], out["tcp_transfer_ms"][n] = round(best * 1e3, 1), round(transfer * 1e3, 1)
    with PtyNullModem() as modem, DriveModbusEmulator(_gen, rate_hz=FS, transport="rtu", serial_port=modem.port_a,
                                                      capture_time_s=0.0):
        for n in rtu_sizes:
            src = ModbusSnapshotSource(SnapshotSourceConfig(transport="rtu", serial_port=modem.port_b, samples=n))
            best, transfer = _time_snapshots(src, repeats)
            src.close()
            out["rtu_pty_ms"][n], out["rtu_pty_transfer_ms"][n] = round(best * 1e3, 1), round(transfer * 1e3, 1)
    with PlcModbusServer([f"d{i}" for i in range(8)], port=0) as srv:
        st = DriveStatus("d3", state="warning", quality="good", fe_hz=50.0, load_pct=80.0, t=time.time())
        t0 = time.perf_counter()
        for _ in range(10_000):
            srv.publish(st)
        out["plc_publish_us"] = round((time.perf_counter() - t0) / 10_000 * 1e6, 1)
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=1))
