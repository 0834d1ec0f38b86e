"""The PLC's view of the agent: a Modbus TCP server (a :class:`protocols.base.Sink`).

Register map: :mod:`firmware_if.plc_registers` (``docs/registers.md``). The server runs on its
own asyncio loop thread (pymodbus 3.16 ``SimDevice``; the live registers are updated only with
``server.async_setValues`` on that loop):

* ``publish(status)`` is the thread-safe, non-blocking entry point for the DSP thread: it
  encodes the drive's 16 input registers in the caller's thread, leaves them in a per-drive
  slot (a newer update for the same drive replaces one not yet applied) and wakes the loop
  with ``call_soon_threadsafe``. The loop writes each drive block with **one**
  ``async_setValues`` call (one slice assignment: a PLC reading the block never sees half an
  update), then the global block (summary). Nothing in ``publish`` waits for the loop or a
  client, so a dead or slow PLC connection cannot stall the pipeline.
* A heartbeat task owned by the server increments IR1 every ``heartbeat_period_s`` (default
  0.5 s) and refreshes each drive's ``DATA_AGE``.
* Commands: the PLC writes 1 to ``ACK`` / ``RELEARN`` (HR ``16 + 16*i`` + 0/1). The device
  action validates every client write (other addresses: exception 2; values other than 0/1:
  exception 3), then the server queues a :class:`PlcCommand` for ``commands()`` or calls
  ``on_command`` (on the server's loop thread: keep it short). ``ACK`` is handled by the
  server itself (``ALARM_ACKED`` = 1 until the state rises or returns to normal) and its
  register returns to 0 at once; ``RELEARN`` stays 1 until the agent has taken it.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from firmware_if import plc_registers as reg
from protocols._aio import LoopThread
from protocols.base import QUALITY_CODES, STATE_CODES, DriveStatus, OpenClose

log = logging.getLogger(__name__)

WRITE_FCS = frozenset({5, 6, 15, 16, 22, 23})
BIT_FCS = frozenset({1, 2, 5, 15})
_OFF = {d.name: d.address for d in reg.DRIVE_IR}


@dataclass(frozen=True)
class PlcCommand:
    """A command from the PLC. ``kind``: ``"acknowledge"`` or ``"relearn"``; ``t``: Unix time."""

    drive: str
    index: int
    kind: str
    t: float


@dataclass
class PlcServerStats:
    published: int = 0  #: publish() calls accepted
    applied: int = 0  #: drive-block writes to the register memory
    coalesced: int = 0  #: updates replaced by a newer one before being applied
    dropped: int = 0  #: updates not applied (server not open, encoding error)
    unknown_drive: int = 0
    commands: int = 0
    rejected_writes: int = 0  #: client writes refused by the map (addresses past the map are refused by pymodbus, uncounted)
    heartbeats: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def status_values(status: DriveStatus) -> dict:
    """DriveStatus -> ``{register row: physical value}`` of a drive block (without
    ``ALARM_ACKED``, ``DATA_AGE`` and ``UPDATE_COUNT``, which the server owns)."""
    ratio, freq = 0.0, 0.0
    for p in status.peaks or ():
        try:
            th2, mag = float(p.get("th2", math.nan)), float(p.get("magnitude", math.nan))
        except (TypeError, ValueError):
            continue
        if th2 > 0 and mag == mag and mag / th2 > ratio:
            ratio, freq = mag / th2, float(p.get("freq_hz", 0.0) or 0.0)
    t = status.t if isinstance(status.t, (int, float)) and math.isfinite(status.t) and status.t > 0 else 0
    return {"STATE": STATE_CODES[status.state], "QUALITY": QUALITY_CODES[status.quality],
            "SPECTRUM_STATE": STATE_CODES[status.spectrum_state], "CLUSTER_STATE": STATE_CODES[status.cluster_state],
            "FE": status.fe_hz, "LOAD": status.load_pct, "UPDATE_TIME": int(t),
            "WINDOW": int(status.window) & 0xFFFFFFFF, "PEAK_FREQ": freq, "PEAK_RATIO": ratio,
            "MODEL_ID": reg.model_id(status.model or "")}


def evidence_values(status: DriveStatus) -> dict:
    """DriveStatus -> ``{register row: physical value}`` of its evidence block (map version 2)."""
    extra = status.extra or {}
    reason = extra.get("reason") if isinstance(extra.get("reason"), dict) else {}
    evidence = extra.get("evidence") or {}
    values = {"LEARN_PROGRESS": float(extra.get("learn_progress_pct") or 0.0) if status.quality == "learning" else 0.0,
              "ALARM_PATH": reg.PATH_CODES.get(reason.get("path", "none"), 0) if status.state != "normal" else 0,
              "SETTLING": 1 if extra.get("settling") else 0,
              "REASON_FREQ": float((reason.get("freqs_hz") or [0.0])[0]) if status.state != "normal" else 0.0,
              "REASON_SCORE": 0.0}
    if status.state != "normal" and reason:
        values["REASON_SCORE"] = float(reason["z"]) if "z" in reason else \
            float(reason.get("evidence", 0.0)) / max(float(reason.get("threshold", 1.0)), 1e-9)
    for row, family in reg.EVIDENCE_FAMILIES.items():
        values[row] = float(evidence.get(family, 0.0))
    return values


class PlcModbusServer(OpenClose):
    """Modbus TCP server for the PLC, unit id 1, one register block per drive.

    ``drives``: drive names in block order (drive ``i`` at IR ``16 + 16*i``). ``port=0`` binds
    an ephemeral port (see ``address`` after ``open()``). ``on_command``: called on the server
    thread for each command instead of queueing it for :meth:`commands`.
    """

    name = "modbus-plc"

    def __init__(self, drives: Sequence[str], *, host: str = "127.0.0.1", port: int = 5020,
                 device_id: int = reg.DEVICE_ID, heartbeat_period_s: float = 0.5,
                 on_command: Callable[[PlcCommand], None] | None = None, start_timeout_s: float = 5.0):
        drives = list(drives)
        if not 1 <= len(drives) <= reg.MAX_DRIVES:
            raise ValueError(f"modbus plc: drives: 1..{reg.MAX_DRIVES} names expected, got {len(drives)}")
        if len(set(drives)) != len(drives):
            raise ValueError("modbus plc: drives: names must be unique")
        if not 0.01 <= heartbeat_period_s <= 1.0:
            raise ValueError("modbus plc: heartbeat_period_s must be 0.01..1.0 (contract: >= 1 advance per second)")
        self.drives = drives
        self.host, self._port, self.device_id = host, port, device_id
        self.heartbeat_period_s = heartbeat_period_s
        self.on_command = on_command
        self.start_timeout_s = start_timeout_s
        self.stats = PlcServerStats()
        self._index = {d: i for i, d in enumerate(drives)}
        self._n = len(drives)
        self._size = reg.table_size(self._n)
        self._cmd_addr = reg.command_addresses(self._n)
        self._loop = LoopThread("plc-modbus")
        self._lock = threading.Lock()
        self._pending: dict[int, tuple[list[int], float]] = {}
        self._wake_scheduled = False
        self._open = False
        self._update_count = [0] * self._n
        self._commands: deque[PlcCommand] = deque()
        self._unknown_logged: set[str] = set()
        # loop-thread state
        self._server: ModbusTcpServer | None = None
        self._current: list[tuple[list[int], float] | None] = [None] * self._n
        self._ack_level = [0] * self._n
        self._heartbeat = 0
        self._t_start = time.monotonic()
        self._tasks: set = set()

    # ---- Sink contract

    def open(self) -> None:
        """Bind and start serving; raises ``OSError`` when the address cannot be bound."""
        if self._open:
            return
        self._loop.start(self.start_timeout_s)
        quiet = logging.getLogger("pymodbus.logging")  # its bind warning would repeat our one line
        level = quiet.level
        quiet.setLevel(logging.ERROR)
        try:
            self._loop.run(self._start(), self.start_timeout_s + 1.0)
        except BaseException:
            self._loop.stop()
            raise
        finally:
            quiet.setLevel(level)
        with self._lock:
            self._open = True
        log.info("PLC Modbus server on %s:%d, unit %d, %d drive(s)", self.host, self._port, self.device_id, self._n)

    def publish(self, status: DriveStatus) -> None:
        """Hand over one drive's status; returns at once (thread-safe, never raises)."""
        idx = self._index.get(status.drive)
        if idx is None:
            self.stats.unknown_drive += 1
            if status.drive not in self._unknown_logged:
                self._unknown_logged.add(status.drive)
                log.error("PLC server: status for unknown drive %r dropped (known: %s)", status.drive, self.drives)
            return
        try:
            regs = reg.encode_drive(status_values(status)) + reg.encode_evidence(evidence_values(status))
        except Exception as err:  # noqa: BLE001 - a bad status must not stop the pipeline
            self.stats.dropped += 1
            log.error("PLC server: cannot encode status of %r: %s", status.drive, err)
            return
        with self._lock:
            if not self._open:
                self.stats.dropped += 1
                return
            self._update_count[idx] = (self._update_count[idx] + 1) & 0xFFFF
            regs[_OFF["UPDATE_COUNT"]] = self._update_count[idx]
            if idx in self._pending:
                self.stats.coalesced += 1
            self._pending[idx] = (regs, time.monotonic())
            self.stats.published += 1
            wake = not self._wake_scheduled
            self._wake_scheduled = True
        if wake and not self._loop.call_soon(self._on_pending):
            with self._lock:
                self._wake_scheduled = False

    def close(self) -> None:
        """Stop serving and the loop thread; safe twice."""
        with self._lock:
            was_open, self._open = self._open, False
        if was_open and self._loop.running:
            try:
                self._loop.run(self._stop(), 3.0)
            except (TimeoutError, RuntimeError) as err:
                log.warning("PLC server: shutdown: %s", err)
        self._loop.stop()

    # ---- agent-side API

    @property
    def address(self) -> tuple[str, int]:
        """``(host, bound port)``."""
        return self.host, self._port

    def commands(self) -> list[PlcCommand]:
        """Commands received since the last call (oldest first). Taking a ``relearn`` clears
        its register to 0 (the PLC sees that the agent has it)."""
        out = []
        while self._commands:
            out.append(self._commands.popleft())
        for c in out:
            if c.kind == "relearn":
                self._loop.call_soon(self._clear_command, reg.address("RELEARN", c.index))
        return out

    def acknowledge(self, drive: str) -> None:
        """Acknowledge ``drive``'s current alarm as the PLC's ACK does (a command from elsewhere,
        e.g. a signed zenoh command); ``KeyError`` for an unknown drive. Thread-safe."""
        i = self._index[drive]

        def ack():
            cur = self._current[i]
            self._ack_level[i] = cur[0][_OFF["STATE"]] if cur is not None else 0
            self._spawn(self._write_drive(i))
        self._loop.call_soon(ack)

    def flush(self, timeout: float = 1.0) -> bool:
        """Wait until every update published so far is in the registers (tests, shutdown)."""
        if not self._loop.running:
            return False
        try:
            self._loop.run(self._apply_pending(), timeout)
            return True
        except (TimeoutError, RuntimeError):
            return False

    # ---- loop side

    async def _start(self) -> None:
        dev = SimDevice(id=self.device_id, action=self._action, simdata=(
            [SimData(0, count=16, values=False, datatype=DataType.BITS)],
            [SimData(0, count=16, values=False, datatype=DataType.BITS)],
            [SimData(0, count=self._size, values=0, datatype=DataType.REGISTERS)],
            [SimData(0, count=self._size, values=0, datatype=DataType.REGISTERS),
             SimData(reg.EVIDENCE_BASE, count=reg.DRIVE_STRIDE * self._n, values=0, datatype=DataType.REGISTERS)]))
        server = ModbusTcpServer(dev, address=(self.host, self._port))
        try:
            await asyncio.wait_for(server.serve_forever(background=True), self.start_timeout_s)
        except RuntimeError as err:  # pymodbus: "Could not start listen"
            raise OSError(f"cannot listen on {self.host}:{self._port} (in use, or not an address of this machine)") from err
        self._port = server.transport.sockets[0].getsockname()[1]
        self._server = server
        self._t_start = time.monotonic()
        for i in range(self._n):
            await self._write_drive(i)
        await self._write_global()
        self._spawn(self._heartbeat_task())

    async def _stop(self) -> None:
        for t in list(self._tasks):
            t.cancel()
        server, self._server = self._server, None
        if server is not None:
            await asyncio.wait_for(server.shutdown(), 2.0)

    def _spawn(self, coro) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("PLC server task failed: %r", task.exception())

    def _clear_command(self, addr: int) -> None:
        self._spawn(self._set(3, addr, [0]))

    def _on_pending(self) -> None:
        self._spawn(self._apply_pending())

    async def _apply_pending(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, {}
            self._wake_scheduled = False
        if not pending:
            return
        for idx, item in pending.items():
            self._current[idx] = item
            await self._write_drive(idx)
        await self._write_global()

    async def _set(self, fc: int, addr: int, values: list[int]) -> None:
        if self._server is not None:
            await self._server.async_setValues(self.device_id, fc, addr, values)

    def _drive_registers(self, i: int, now: float) -> list[int]:
        cur = self._current[i]
        if cur is None:  # never updated: quality stale, n/a values, age saturated
            regs = reg.encode_drive({"STATE": 0, "QUALITY": QUALITY_CODES["stale"], "SPECTRUM_STATE": 0,
                                     "CLUSTER_STATE": 0, "FE": math.nan, "LOAD": math.nan, "DATA_AGE": 65535})
            return regs
        regs, t_pub = cur
        regs = list(regs[:reg.DRIVE_STRIDE])
        state = regs[_OFF["STATE"]]
        if state == 0:
            self._ack_level[i] = 0
        regs[_OFF["ALARM_ACKED"]] = 1 if 0 < state <= self._ack_level[i] else 0
        regs[_OFF["DATA_AGE"]] = min(65535, int((now - t_pub) * 1000.0))
        return regs

    async def _write_drive(self, i: int) -> None:
        await self._set(4, reg.drive_base(i), self._drive_registers(i, time.monotonic()))
        cur = self._current[i]
        if cur is not None:
            await self._set(4, reg.evidence_base(i), list(cur[0][reg.DRIVE_STRIDE:]))
        self.stats.applied += 1

    async def _write_global(self) -> None:
        states = [c[0][_OFF["STATE"]] for c in self._current if c is not None]
        not_good = sum(1 for c in self._current if c is None or c[0][_OFF["QUALITY"]] != 0)
        regs = reg.encode_global({"MAP_VERSION": reg.MAP_VERSION, "HEARTBEAT": self._heartbeat,
                                  "DRIVE_COUNT": self._n, "SUMMARY_STATE": max(states, default=0),
                                  "DRIVES_NOT_GOOD": not_good, "AGENT_TIME": int(time.time()) & 0xFFFFFFFF,
                                  "UPTIME": int(time.monotonic() - self._t_start),
                                  "HEARTBEAT_PERIOD": round(self.heartbeat_period_s * 1000)})
        await self._set(4, 0, regs)

    async def _heartbeat_task(self) -> None:
        while True:
            await asyncio.sleep(self.heartbeat_period_s)
            try:
                self._heartbeat = (self._heartbeat + 1) & 0xFFFF
                self.stats.heartbeats += 1
                for i in range(self._n):
                    if self._current[i] is not None:
                        await self._write_drive(i)
                await self._write_global()
            except asyncio.CancelledError:
                raise
            except Exception:  # the heartbeat must outlive any single failure
                log.exception("PLC server: heartbeat update failed")

    async def _action(self, fc, start, address, count, regs, values):
        """Access check for every request (pymodbus device action, on the loop)."""
        if fc in BIT_FCS:  # no coils / discrete inputs in this map
            if fc in WRITE_FCS:
                self.stats.rejected_writes += 1
            return ExcCodes.ILLEGAL_ADDRESS
        if values is None or fc not in WRITE_FCS:
            return None  # reads (and FC6/FC22 read-back), and our own writes with fc 3/4
        for k in range(count):
            if address + k not in self._cmd_addr:
                self.stats.rejected_writes += 1
                return ExcCodes.ILLEGAL_ADDRESS
        if any(v not in (reg.CMD_IDLE, reg.CMD_REQUEST) for v in values):
            self.stats.rejected_writes += 1
            return ExcCodes.ILLEGAL_VALUE
        for k, v in enumerate(values):
            if v == reg.CMD_REQUEST:
                self._command(address + k)
        return None

    def _command(self, addr: int) -> None:
        i, kind = self._cmd_addr[addr]
        cmd = PlcCommand(self.drives[i], i, kind, time.time())
        self.stats.commands += 1
        log.info("PLC command %s for drive %r", kind, cmd.drive)
        if kind == "acknowledge":
            cur = self._current[i]
            self._ack_level[i] = cur[0][_OFF["STATE"]] if cur is not None else 0
            self._spawn(self._write_drive(i))
        clear_now = kind == "acknowledge"
        if self.on_command is not None:
            try:
                self.on_command(cmd)
            except Exception:  # noqa: BLE001
                log.exception("PLC server: on_command callback failed")
            clear_now = True
        else:
            self._commands.append(cmd)
        if clear_now:  # the task runs after pymodbus has stored the written 1
            self._clear_command(addr)
