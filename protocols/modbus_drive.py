"""Snapshots of the drive's phase signals over Modbus (TCP or RTU), and a drive emulator.

:class:`ModbusSnapshotSource` is the agent side (a :class:`protocols.base.Source`): it runs the
capture-buffer protocol of :mod:`firmware_if.modbus_capture` (trigger, poll the header, read the
interleaved int16 samples in chunks of <= 125 registers, verify, release) with a synchronous
pymodbus client, and returns each snapshot as one :class:`Block`. ``read(timeout)`` is a
resumable state machine: one Modbus transaction per step, progress kept across calls, so a
short ``timeout`` returns ``None`` without losing the capture under way.

Trouble never raises out of ``read``: a Modbus exception response is counted
(``stats.exceptions``), logged (rate-limited) and the request is retried up to ``max_retries``
times before the capture is restarted after a backoff; a timeout or lost link closes the
client and reconnects with exponential backoff (``stats.reconnects`` counts successful
reconnections).

:class:`DriveModbusEmulator` is the drive side: a pymodbus server (``SimDevice`` whose action
computes the input registers on each read) serving snapshots of an
:class:`agent.records.Record` (played back at the drive's sample counter) or of a generator
``f(first_sample, n) -> (6, n)`` array in V/A. Over TCP (``port=0``: ephemeral, see
``address``) or RTU on a serial port (``serial_port=``, e.g. a :class:`PtyNullModem` end).
It can inject exception responses and failed captures for tests.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from firmware_if import modbus_capture as cap
from firmware_if.modbus_capture import CaptureError, CaptureHeader, Command, Status
from protocols._aio import LoopThread
from protocols.base import Block, OpenClose, SourceStats
from protocols.streaming import Backoff, BlockAssembler

log = logging.getLogger(__name__)

WRITE_FCS = frozenset({5, 6, 15, 16, 22, 23})
BIT_FCS = frozenset({1, 2, 5, 15})
TRANSPORTS = ("tcp", "rtu")
IDLE_GRACE_S = 0.5  #: after a trigger, IDLE (or the previous READY) is tolerated this long


# ---------------------------------------------------------------------------------- source


@dataclass(frozen=True)
class SnapshotSourceConfig:
    """Where the drive is and how to read it. Durations in seconds.

    ``samples``: samples per channel per snapshot. ``chunk_registers`` <= 125 (default 120 =
    20 whole samples). ``max_retries``: retries of one request after exception responses
    before the capture restarts. ``arm``: use ``COMMAND=ARM`` (drive-side trigger condition)
    instead of an immediate ``TRIGGER``.
    """

    drive: str = "drive0"
    transport: str = "tcp"
    host: str = "127.0.0.1"
    port: int = 502
    serial_port: str = ""
    baudrate: int = 115200
    parity: str = "N"
    stopbits: int = 1
    device_id: int = cap.DEVICE_ID
    samples: int = 2500
    chunk_registers: int = cap.CHUNK_REGS
    request_timeout_s: float = 1.0
    poll_interval_s: float = 0.01
    capture_timeout_s: float = 5.0
    backoff_initial_s: float = 0.1
    backoff_max_s: float = 5.0
    max_retries: int = 3
    arm: bool = False
    rate_hz: float = 0.0  #: the drive profile's sampling rate a snapshot's RATE must agree with (0: not checked)

    def __post_init__(self):
        def bad(key, why):
            raise ValueError(f"modbus source {self.drive!r}: {key}: {why}")
        if self.transport not in TRANSPORTS:
            bad("transport", f"must be one of {TRANSPORTS}, got {self.transport!r}")
        if self.transport == "rtu" and not self.serial_port:
            bad("serial_port", "required for transport 'rtu'")
        if not 0 <= self.port <= 65535:
            bad("port", "must be 0..65535")
        if not 0 <= self.device_id <= 247:
            bad("device_id", "must be 0..247")
        if not 1 <= self.samples <= 0xFFFFFFFF:
            bad("samples", "must be >= 1")
        if not 1 <= self.chunk_registers <= cap.MAX_READ_REGS:
            bad("chunk_registers", f"must be 1..{cap.MAX_READ_REGS}")
        for key in ("request_timeout_s", "poll_interval_s", "capture_timeout_s", "backoff_initial_s",
                    "backoff_max_s"):
            if not getattr(self, key) > 0:
                bad(key, "must be > 0")
        if self.backoff_max_s < self.backoff_initial_s:
            bad("backoff_max_s", "must be >= backoff_initial_s")
        if self.max_retries < 0:
            bad("max_retries", "must be >= 0")


@dataclass
class ModbusSourceStats(SourceStats):
    """:class:`SourceStats` plus Modbus counters. ``frames``: good responses;
    ``exceptions``: exception responses from the drive; ``timeouts``: requests without an
    answer or on a broken link; ``capture_errors``: STATUS=error or no capture within the
    timeout; ``discarded``: snapshots dropped because the verify step failed."""

    exceptions: int = 0
    last_exception_code: int = 0
    timeouts: int = 0
    capture_errors: int = 0
    discarded: int = 0
    requests: int = 0
    bad_headers: Counter = field(default_factory=Counter)  #: refused READY headers by what was wrong (the register)
    last_snapshot_s: float = float("nan")  #: trigger -> verified, s
    last_transfer_s: float = float("nan")  #: sample reads only, s


class _Throttle:
    """Log at most once per ``period`` s per key."""

    def __init__(self, period: float = 5.0):
        self.period = period
        self._last: dict[str, float] = {}

    def __call__(self, key: str) -> bool:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= self.period:
            self._last[key] = now
            return True
        return False


class ModbusSnapshotSource(OpenClose):
    """A :class:`protocols.base.Source` reading snapshots from the drive's capture buffer."""

    def __init__(self, config: SnapshotSourceConfig):
        self.config = config
        self.name = config.drive
        self.stats = ModbusSourceStats()
        self._client: ModbusTcpClient | ModbusSerialClient | None = None
        self._ever_connected = False
        # link: connect / timeouts (reset by a good response); capture restarts (reset by a good snapshot)
        self._backoff = Backoff(config.backoff_initial_s, config.backoff_max_s)
        self._capture_backoff = Backoff(config.backoff_initial_s, config.backoff_max_s)
        self._asm = BlockAssembler(config.drive, 0.0, self.stats)
        self._not_before = 0.0  # earliest time of the next step (poll interval, retry backoff)
        self._retries = 0
        self._throttle = _Throttle()
        self._counter_last: int | None = None  # drive sample counter (raw UINT32) of the last snapshot
        self._counter_abs = 0
        self._hdr_rate = 0.0  # sample rate from the last header (expected capture time)
        self._last_seq: int | None = None  # SEQ of the last snapshot returned
        self._restart()

    # ---- Source contract

    def open(self) -> None:
        """Create the client and try to connect once (failure is retried by ``read``)."""
        if self._client is None:
            self._client = self._make_client()
        self._connect(time.monotonic() + self.config.request_timeout_s)

    def read(self, timeout: float) -> Block | None:
        """The next snapshot, or ``None`` when it is not complete within ``timeout`` s (or the
        link is down). A request already on the wire is not abandoned, so a call may overrun
        ``timeout`` by up to ``request_timeout_s``."""
        if self._client is None:
            self._client = self._make_client()
        deadline = time.monotonic() + max(0.0, timeout)
        while True:
            now = time.monotonic()
            if now < self._not_before:
                if self._not_before >= deadline:
                    time.sleep(max(0.0, deadline - now))
                    return None
                time.sleep(self._not_before - now)
            if not self._connect(deadline):
                return None
            try:
                block = self._step()
            except Exception as err:  # a bug or an unexpected library error: never raise out of read
                self._link_failed(f"{type(err).__name__}: {err}")
                log.exception("%s: unexpected error in the capture sequence", self.name)
                block = None
            if block is not None:
                return block
            if time.monotonic() >= deadline:
                return None

    def close(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            except Exception:  # noqa: BLE001 - closing must not raise
                pass
            self._client = None
        self._restart()

    # ---- connection

    def _make_client(self):
        c = self.config
        if c.transport == "tcp":
            return ModbusTcpClient(c.host, port=c.port, timeout=c.request_timeout_s, retries=0,
                                   name=f"{c.drive}-tcp")
        return ModbusSerialClient(c.serial_port, framer=FramerType.RTU, baudrate=c.baudrate, parity=c.parity,
                                  stopbits=c.stopbits, timeout=c.request_timeout_s, retries=0,
                                  name=f"{c.drive}-rtu")

    def _connect(self, deadline: float) -> bool:
        client = self._client
        if client.connected:
            return True
        now, next_try = time.monotonic(), self._backoff.next_try
        if now < next_try:
            time.sleep(max(0.0, min(next_try, deadline) - now))
            if time.monotonic() < next_try:
                return False
        ok, why = False, "connect failed"
        try:
            ok = bool(client.connect())
        except Exception as err:  # noqa: BLE001 - pyserial raises assorted errors
            why = f"connect: {err}"
        if ok:
            if self._ever_connected:
                self.stats.reconnects += 1
                log.info("%s: reconnected to the drive", self.name)
            self._ever_connected = True
            self._restart()  # the backoff is reset by the first good response, not by connect
            return True
        self.stats.last_error = why
        wait = self._backoff.failed()
        if self._throttle("connect"):
            log.warning("%s: cannot connect to the drive (%s); retry in %.2f s", self.name, self._where(), wait)
        return False

    def _where(self) -> str:
        c = self.config
        return f"{c.host}:{c.port}" if c.transport == "tcp" else c.serial_port

    def _link_failed(self, why: str) -> None:
        self.stats.timeouts += 1
        self.stats.last_error = why
        if self._throttle("link"):
            log.warning("%s: link to the drive failed: %s; reconnecting", self.name, why)
        if self._client is not None:
            try:
                self._client.close()
            except Exception:  # noqa: BLE001
                pass
        self._backoff.failed()
        self._restart()

    # ---- one Modbus transaction

    def _call(self, what: str, fn, *args, **kw):
        """Run one request; the response, or ``None`` after counting/logging the trouble."""
        self.stats.requests += 1
        try:
            rr = fn(*args, device_id=self.config.device_id, **kw)
        except (ModbusException, OSError) as err:
            self._link_failed(f"{what}: {err}")
            return None
        if rr is None or rr.isError():
            code = int(getattr(rr, "exception_code", 0) or 0)
            self.stats.exceptions += 1
            self.stats.last_exception_code = code
            self.stats.last_error = f"{what}: exception {code}"
            if self._throttle(f"exc{code}"):
                log.warning("%s: drive answered %s with Modbus exception %d", self.name, what, code)
            self._retries += 1
            if self._retries > self.config.max_retries:
                self._restart_later()
            else:
                self._not_before = time.monotonic() + self.config.poll_interval_s
            return None
        self._retries = 0
        self._backoff.reset()
        self.stats.frames += 1
        return rr

    # ---- the capture state machine

    def _restart(self) -> None:
        self._phase = "trigger"
        self._retries = 0
        self._hdr: CaptureHeader | None = None
        self._buf: np.ndarray | None = None
        self._plan: list = []
        self._win = self._chunk = 0
        self._window_now = 0

    def _step(self) -> Block | None:
        c = self.config
        client = self._client
        if self._phase == "trigger":
            cmd = Command.ARM if c.arm else Command.TRIGGER
            if self._call("trigger", client.write_registers, cap.address("REQ_COUNT"),
                          cap.trigger_registers(c.samples, cmd)) is None:
                return None
            self._t_trigger = time.monotonic()
            expect = c.samples / self._hdr_rate if self._hdr_rate > 0 else 0.0
            self._wait_until = self._t_trigger + expect + c.capture_timeout_s
            self._not_before = self._t_trigger + (expect if expect > 0 else c.poll_interval_s)
            self._phase = "wait"
            return None
        if self._phase == "wait":
            rr = self._call("status", client.read_input_registers, 0, count=cap.HEADER_REGS)
            hdr = None if rr is None else self._decode_header(rr.registers)
            if hdr is None:
                return None
            now = time.monotonic()
            # a drive that has not yet taken the trigger may still show IDLE, or READY with the
            # snapshot this source read last: keep polling for IDLE_GRACE_S
            early = now - self._t_trigger < IDLE_GRACE_S
            if hdr.status == Status.READY and not (early and hdr.seq == self._last_seq):
                return self._start_reading(hdr)
            if hdr.status == Status.ERROR:
                name = (CaptureError(hdr.error).name.lower() if hdr.error in CaptureError._value2member_map_
                        else str(hdr.error))
                self._capture_failed(f"error {name}")
                return None
            if now > self._wait_until or (hdr.status in (Status.IDLE, Status.READY) and not early):
                self._capture_failed("timeout" if now > self._wait_until else "trigger not taken")
                return None
            self._not_before = now + c.poll_interval_s
            return None
        if self._phase == "read":
            win_start, chunks = self._plan[self._win]
            if win_start != self._window_now:
                if self._call("window", client.write_registers, cap.address("WINDOW_START"),
                              cap.u32_registers(win_start)) is None:
                    return None
                self._window_now = win_start
            addr, n = chunks[self._chunk]
            rr = self._call("samples", client.read_input_registers, addr, count=n)
            if rr is None:
                return None
            regs = rr.registers
            if len(regs) != n:
                self._link_failed(f"samples: {len(regs)} registers instead of {n}")
                return None
            o = cap.N_CHANNELS * win_start + (addr - cap.SAMPLE_BASE)
            self._buf[o:o + n] = regs
            self._chunk += 1
            if self._chunk == len(chunks):
                self._chunk = 0
                self._win += 1
                if self._win == len(self._plan):
                    self._t_transfer = time.monotonic() - self._t_transfer0
                    self._phase = "verify"
            return None
        if self._phase == "verify":
            rr = self._call("verify", client.read_input_registers, 0, count=cap.HEADER_REGS)
            hdr = None if rr is None else self._decode_header(rr.registers)
            if hdr is None:
                return None
            if hdr.status != Status.READY or hdr.seq != self._hdr.seq:
                self.stats.discarded += 1
                self.stats.last_error = "snapshot replaced while reading"
                if self._throttle("discard"):
                    log.warning("%s: snapshot %d changed while reading (status %d, seq %d); discarded",
                                self.name, self._hdr.seq, hdr.status, hdr.seq)
                self._restart()
                return None
            block = self._make_block()
            # release: a courtesy (the next TRIGGER overwrites anyway); trouble is only counted
            self._call("release", client.write_register, cap.address("COMMAND"), int(Command.RELEASE))
            self._retries = 0
            self._not_before = 0.0
            self._restart()
            return block
        raise AssertionError(self._phase)

    def _decode_header(self, regs) -> CaptureHeader | None:
        """The capture header, or None (counted as a bad frame, logged) for a malformed reply."""
        try:
            return CaptureHeader.from_registers(regs)
        except ValueError as err:
            self.stats.bad_frames += 1
            self.stats.last_error = str(err)
            if self._throttle("header"):
                log.warning("%s: %s; polling again", self.name, err)
            return None

    def _start_reading(self, hdr: CaptureHeader) -> None:
        c = self.config
        problem = hdr.problem(c.samples, c.rate_hz)
        if problem:
            self.stats.bad_frames += 1
            self.stats.bad_headers[problem[0]] += 1
            self._capture_failed(f"bad header: {problem[1]}")
            return None
        self._hdr = hdr
        self._hdr_rate = hdr.rate_hz
        self._buf = np.zeros(cap.N_CHANNELS * hdr.count, dtype=np.uint16)
        self._plan = cap.read_plan(hdr.count, c.chunk_registers, hdr.window_samples)
        self._win = self._chunk = 0
        self._window_now = 0  # TRIGGER/ARM reset WINDOW_START to 0
        self._t_transfer0 = time.monotonic()
        self._phase = "read"
        return None

    def _capture_failed(self, why: str) -> None:
        self.stats.capture_errors += 1
        self.stats.last_error = f"capture: {why}"
        if self._throttle("capture"):
            log.warning("%s: capture failed (%s); resetting the drive's capture buffer", self.name, why)
        self._call("reset", self._client.write_register, cap.address("COMMAND"), int(Command.RESET))
        self._restart_later()

    def _restart_later(self) -> None:
        """Restart the capture sequence after the capture backoff."""
        self._restart()
        self._capture_backoff.failed()
        self._not_before = self._capture_backoff.next_try

    def _make_block(self) -> Block:
        hdr = self._hdr
        n = hdr.count
        raw = cap.deinterleave(self._buf, n)
        phys = cap.to_physical(raw, hdr.scales)
        if self._counter_last is None:
            self._counter_abs = 0
        else:
            self._counter_abs += (hdr.first_sample - self._counter_last) & 0xFFFFFFFF
        self._counter_last = hdr.first_sample
        self._last_seq = hdr.seq
        block = self._asm.block(phys[:3], phys[3:], self._counter_abs, rate_hz=hdr.rate_hz)
        self.stats.last_snapshot_s = time.monotonic() - self._t_trigger
        self.stats.last_transfer_s = self._t_transfer
        self._capture_backoff.reset()
        return block


# ---------------------------------------------------------------------------------- emulator


SnapshotGenerator = Callable[[int, int], np.ndarray]
DEFAULT_SCALES = (0.05, 0.05, 0.05, 0.005, 0.005, 0.005)  #: V/LSB and A/LSB for generators


@dataclass
class _Capture:
    seq: int
    first_sample: int
    raw: np.ndarray  #: int16 (6, N)


@dataclass
class EmulatorStats:
    requests: int = 0
    exceptions_sent: int = 0
    captures: int = 0
    triggers: int = 0
    rejected_writes: int = 0
    history: deque = field(default_factory=lambda: deque(maxlen=8))


class DriveModbusEmulator:
    """The drive's capture buffer as a pymodbus server (TCP or RTU) on its own loop thread.

    ``signal``: an :class:`agent.records.Record` (snapshots are taken at the drive's sample
    counter, wrapping around the record) or ``f(first_sample, n) -> (6, n)`` physical values
    (needs ``rate_hz``). ``scales`` (V/LSB, A/LSB per channel) default to full scale for a
    record and :data:`DEFAULT_SCALES` for a generator. ``capture_time_s``: time from trigger to
    ready (default ``N / rate_hz``, as a real drive). ``counter_offset``: initial value of the
    drive's sample counter (test the UINT32 wrap).

    ``start()`` / ``stop()`` the server (restartable on the same port: a disconnect),
    ``close()`` the loop. ``stats.history`` keeps the last captures (``seq``, ``first_sample``,
    ``raw``) for bit-exact checks.
    """

    def __init__(self, signal, *, rate_hz: float | None = None, scales=None, transport: str = "tcp",
                 host: str = "127.0.0.1", port: int = 0, serial_port: str = "", baudrate: int = 115200,
                 device_id: int = cap.DEVICE_ID, capacity: int = 1_000_000, capture_time_s: float | None = None,
                 arm_delay_s: float = 0.0, counter_offset: int = 0):
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}")
        if transport == "rtu" and not serial_port:
            raise ValueError("serial_port is required for transport 'rtu'")
        if callable(signal):
            if not rate_hz or rate_hz <= 0:
                raise ValueError("rate_hz is required with a generator")
            self._gen: SnapshotGenerator = signal
            self.rate_hz = float(rate_hz)
            scales = DEFAULT_SCALES if scales is None else scales
        else:  # a Record (duck-typed: v_abc, i_abc, rate_hz)
            x = np.vstack([np.asarray(signal.v_abc, float), np.asarray(signal.i_abc, float)])
            n_rec = x.shape[1]
            self.rate_hz = float(rate_hz or signal.rate_hz)
            if scales is None:
                peak = np.max(np.abs(x), axis=1)
                scales = np.where(peak > 0, peak * 1.0001 / 32767.0, 1.0)
            self._gen = lambda first, n: x[:, (first + np.arange(n)) % n_rec]
        self.scales = tuple(float(s) for s in cap.float32_round(scales))
        if len(self.scales) != cap.N_CHANNELS or min(self.scales) <= 0:
            raise ValueError("scales: six positive values expected")
        self.transport, self.host, self.serial_port, self.baudrate = transport, host, serial_port, baudrate
        self.device_id, self.capacity = device_id, int(capacity)
        self.capture_time_s, self.arm_delay_s = capture_time_s, arm_delay_s
        self.counter_offset = int(counter_offset)
        self.stats = EmulatorStats()
        self._port = port
        self._lock = threading.Lock()
        self._inject: list = []  # [code, remaining, fcs]
        self._fail_next: CaptureError | None = None
        self._loop = LoopThread(f"drive-emulator-{transport}")
        self._server = None
        self._tasks: set = set()
        self._t0 = time.monotonic()
        # drive state (loop thread only)
        self._status = Status.IDLE
        self._error = CaptureError.NONE
        self._seq = 0
        self._count = 0
        self._first = 0
        self._window_start = 0
        self._flat = np.zeros(0, dtype=np.uint16)
        self._t_armed = self._t_capture = self._t_ready = 0.0
        self._pending: _Capture | None = None
        self._req_count = 0

    # ---- control (any thread)

    @property
    def address(self) -> tuple[str, int]:
        """``(host, bound port)`` for TCP."""
        return self.host, self._port

    @property
    def sample_counter(self) -> int:
        """The drive's free-running sample counter (not wrapped)."""
        return self.counter_offset + int((time.monotonic() - self._t0) * self.rate_hz)

    def start(self, timeout: float = 5.0) -> DriveModbusEmulator:
        self._loop.start(timeout)
        if self._server is None:
            self._loop.run(self._start_server(timeout), timeout + 1.0)
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop serving (clients see the link drop); ``start()`` again to come back."""
        if self._server is not None and self._loop.running:
            self._loop.run(self._stop_server(timeout), timeout + 1.0)
        self._server = None

    def close(self) -> None:
        """Stop the server and the loop; safe twice."""
        try:
            self.stop()
        finally:
            self._loop.stop()

    def __enter__(self) -> DriveModbusEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def inject_exceptions(self, code: int = ExcCodes.DEVICE_BUSY, count: int = 1,
                          function_codes: set[int] | None = None) -> None:
        """Answer the next ``count`` client requests (of ``function_codes``, default any) with
        Modbus exception ``code``."""
        with self._lock:
            self._inject.append([ExcCodes(code), int(count), frozenset(function_codes or ())])

    def fail_next_capture(self, error: CaptureError = CaptureError.HARDWARE) -> None:
        """The next capture ends in ``STATUS=ERROR`` with ``error``."""
        with self._lock:
            self._fail_next = CaptureError(error)

    @property
    def last_capture(self) -> _Capture | None:
        return self.stats.history[-1] if self.stats.history else None

    # ---- server (loop thread)

    async def _start_server(self, timeout: float) -> None:
        dev = SimDevice(id=self.device_id, action=self._action, simdata=(
            [SimData(0, count=16, values=False, datatype=DataType.BITS)],
            [SimData(0, count=16, values=False, datatype=DataType.BITS)],
            [SimData(0, count=cap.HR_REGS, values=0, datatype=DataType.REGISTERS)],
            [SimData(0, count=cap.HEADER_REGS, values=0, datatype=DataType.REGISTERS),
             SimData(cap.SAMPLE_BASE, count=cap.WINDOW_REGS, values=0, datatype=DataType.REGISTERS)]))
        if self.transport == "tcp":
            server = ModbusTcpServer(dev, address=(self.host, self._port))
        else:
            server = ModbusSerialServer(dev, port=self.serial_port, framer=FramerType.RTU, baudrate=self.baudrate,
                                        timeout=1.0, reconnect_delay=0.1)
        await asyncio.wait_for(server.serve_forever(background=True), timeout)
        if self.transport == "tcp":
            self._port = server.transport.sockets[0].getsockname()[1]
        self._server = server

    async def _stop_server(self, timeout: float) -> None:
        server, self._server = self._server, None
        if server is not None:
            await asyncio.wait_for(server.shutdown(), timeout)

    def _spawn(self, coro) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _set_hr(self, addr: int, values: list[int]) -> None:
        if self._server is not None:
            await self._server.async_setValues(self.device_id, 3, addr, values)

    async def _action(self, fc, start, address, count, regs, values):
        if fc in (3, 4) and values is not None:  # our own writes (async_setValues)
            return None
        if fc in WRITE_FCS and values is None:  # FC6/FC22 read the register back after writing it
            return None
        self.stats.requests += 1
        with self._lock:
            for item in self._inject:
                code, left, fcs = item
                if left > 0 and (not fcs or fc in fcs):
                    item[1] -= 1
                    self.stats.exceptions_sent += 1
                    self._inject = [i for i in self._inject if i[1] > 0]
                    return code
        if fc in BIT_FCS:
            return ExcCodes.ILLEGAL_ADDRESS
        if fc in WRITE_FCS:
            return self._client_write(address, count, regs, values)
        if fc == 4:
            self._advance(time.monotonic())
            if address < cap.HEADER_REGS:
                off = -start
                regs[off:off + cap.HEADER_REGS] = self._header().registers()
            else:
                lo = cap.N_CHANNELS * self._window_start + (address - cap.SAMPLE_BASE)
                seg = self._flat[lo:lo + count].tolist()
                seg += [0] * (count - len(seg))
                off = address - start
                regs[off:off + count] = seg
        return None

    def _client_write(self, address, count, regs, values):
        if any(a not in cap.HR_WRITABLE for a in range(address, address + count)):
            self.stats.rejected_writes += 1
            return ExcCodes.ILLEGAL_ADDRESS
        new = list(regs[0:cap.HR_REGS])
        new[address:address + count] = list(values)
        touched = set(range(address, address + count))
        a_cmd, a_win, a_req = cap.address("COMMAND"), cap.address("WINDOW_START"), cap.address("REQ_COUNT")
        if a_cmd in touched and new[a_cmd] not in Command._value2member_map_:
            self.stats.rejected_writes += 1
            return ExcCodes.ILLEGAL_VALUE
        if touched & {a_win, a_win + 1}:
            ws = (new[a_win] << 16) | new[a_win + 1]
            if ws >= self.capacity:
                self.stats.rejected_writes += 1
                return ExcCodes.ILLEGAL_VALUE
            self._window_start = ws
        if a_cmd in touched and new[a_cmd] != Command.NONE:
            self._command(Command(new[a_cmd]), (new[a_req] << 16) | new[a_req + 1])
            clear = [0]
            if new[a_cmd] in (Command.TRIGGER, Command.ARM):
                self._window_start = 0
                self._spawn(self._set_hr(a_win, [0, 0]))
            self._spawn(self._set_hr(a_cmd, clear))  # the command register reads 0 once taken
        return None

    def _command(self, cmd: Command, req_count: int) -> None:
        now = time.monotonic()
        if cmd in (Command.TRIGGER, Command.ARM):
            self.stats.triggers += 1
            if not 1 <= req_count <= self.capacity:
                self._status, self._error = Status.ERROR, CaptureError.BAD_COUNT
                return
            self._req_count = req_count
            self._error = CaptureError.NONE
            if cmd == Command.ARM:
                self._status, self._t_armed = Status.ARMED, now
            else:
                self._begin_capture(now)
        elif cmd in (Command.RELEASE, Command.RESET):
            if cmd == Command.RESET and self._status in (Status.ARMED, Status.CAPTURING):
                self._pending = None
            self._status, self._error = Status.IDLE, CaptureError.NONE

    def _begin_capture(self, now: float) -> None:
        n = self._req_count
        first = self.sample_counter
        x = np.asarray(self._gen(first, n), dtype=float)
        raw = cap.quantize(x, self.scales)
        self._pending = _Capture(0, first, raw)
        self._status = Status.CAPTURING
        self._t_capture = now
        dur = self.capture_time_s if self.capture_time_s is not None else n / self.rate_hz
        self._t_ready = now + dur

    def _advance(self, now: float) -> None:
        if self._status == Status.ARMED and now >= self._t_armed + self.arm_delay_s:
            self._begin_capture(now)
        if self._status == Status.CAPTURING and now >= self._t_ready and self._pending is not None:
            with self._lock:
                fail, self._fail_next = self._fail_next, None
            if fail is not None:
                self._status, self._error = Status.ERROR, fail
                self._pending = None
                return
            c = self._pending
            self._pending = None
            self._seq = (self._seq + 1) & 0xFFFF
            c.seq = self._seq
            self._flat = cap.interleave(c.raw)
            self._count = c.raw.shape[1]
            self._first = c.first_sample
            self._status = Status.READY
            self.stats.captures += 1
            self.stats.history.append(c)

    def _header(self) -> CaptureHeader:
        return CaptureHeader(status=self._status, error=self._error, seq=self._seq, count=self._count,
                             rate_hz=self.rate_hz, first_sample=self._first & 0xFFFFFFFF,
                             capacity=self.capacity, window_start=self._window_start, scales=self.scales)
