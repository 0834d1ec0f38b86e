"""NidaqSource against a stand-in of the nidaqmx task API (no NI driver, no nidaqmx package).

:func:`fake_nidaqmx` builds a module object with what the source uses: ``Task`` (ai_channels,
timing with delta-sigma rate coercion, in_stream, every-N and done events, start/stop/close),
``constants.AcquisitionType`` / ``TerminalConfiguration``, ``stream_readers.AnalogMultiChannelReader``
and ``errors.Error`` / ``DaqError`` / ``DaqReadError`` / ``DaqNotFoundError``. A fake task is a small
model of the hardware: a DAQmx buffer of ``samps_per_chan`` that the "hardware" fills with a
deterministic 3-phase set and the reader drains; the every-N callback fires each N samples, either
from a thread at the sample rate (``FakeHardware(realtime=True)``) or by hand (:meth:`FakeTask.acquire`).
Reading after the hardware got more than a buffer ahead raises -200279, as DAQmx does.
"""

from __future__ import annotations

import re
import sys
import threading
import time
import tomllib
import types
from enum import Enum
from pathlib import Path

import numpy as np
import pytest

import protocols.nidaq as nidaq_mod
from protocols.base import Source
from protocols.nidaq import NidaqNotInstalled, NidaqSource, load_nidaqmx

ROOT = Path(__file__).resolve().parent.parent
FE = 50.0  # Hz
V_PEAK = 325.0  # V, line-to-neutral peak
I_PEAK = (12.0, 11.0, 10.0)  # A per phase: distinct, so a channel mix-up shows
SCALE = (10.0, 20.0, 40.0)  # A/V per current channel
V_CH, I_CH = "cDAQ1Mod1/ai0:2", "cDAQ1Mod2/ai0:2"


# ---------------------------------------------------------------------------------- the stand-in

class Error(Exception):
    pass


class DaqError(Error):
    def __init__(self, message, error_code, task_name=""):
        super().__init__(f"{message}\n\nTask Name: {task_name}" if task_name else message)
        self._error_code = int(error_code)

    @property
    def error_code(self):
        return self._error_code


class DaqReadError(DaqError):
    def __init__(self, message, error_code, samps_per_chan_read, task_name=""):
        super().__init__(message, error_code, task_name)
        self.samps_per_chan_read = samps_per_chan_read


class DaqNotFoundError(Error):
    pass


class AcquisitionType(Enum):
    FINITE = 10178
    CONTINUOUS = 10123


class TerminalConfiguration(Enum):
    DEFAULT = -1
    RSE = 10083
    DIFF = 10106


def signal(row: int, k: np.ndarray, rate: float) -> np.ndarray:
    """What the module sees on channel ``row`` (add order) at sample indices ``k``."""
    phase = 2 * np.pi * FE * k / rate - 2 * np.pi * (row % 3) / 3
    if row < 3:
        return V_PEAK * np.cos(phase)
    return I_PEAK[row - 3] / SCALE[row - 3] * np.cos(phase)  # transducer volts


def expanded(physical: str) -> list[str]:
    m = re.fullmatch(r"(.+/ai)(\d+)(?::(\d+))?", physical)
    a, b = int(m[2]), int(m[3] if m[3] is not None else m[2])
    return [f"{m[1]}{i}" for i in range(a, b + 1)]


class FakeTask:
    def __init__(self, hw: FakeHardware, new_task_name=""):
        if hw.not_found:
            raise DaqNotFoundError("Could not find an installation of NI-DAQmx.")
        if hw.create_failures:
            hw.create_failures -= 1
            raise DaqError("Device cannot be accessed.", -201003, new_task_name)
        self.hw, self.name = hw, new_task_name
        self.log: list[str] = []
        self.channels: list[tuple[str, float, float]] = []
        self.rate = self.buffer = None
        self.every_n = self.every_n_cb = self.done_cb = None
        self.running = self.closed = False
        self.starts = self.stops = self.closes = 0
        self.acquired = self.read_pos = 0
        self.lock = threading.Lock()
        self.thread = None
        task = self

        class Chans:
            def add_ai_voltage_chan(self, physical_channel, name_to_assign_to_channel="",
                                    terminal_config=TerminalConfiguration.DEFAULT, min_val=-5.0, max_val=5.0):
                assert isinstance(terminal_config, TerminalConfiguration)
                task.log.append(f"add {physical_channel}")
                task.channels += [(p, min_val, max_val) for p in expanded(physical_channel)]

        class Timing:
            def cfg_samp_clk_timing(self, rate, source="", active_edge=None,
                                    sample_mode=AcquisitionType.FINITE, samps_per_chan=1000):
                assert sample_mode is AcquisitionType.CONTINUOUS
                task.log.append("timing")
                # NI-9244/9239: fs = 12.8 MHz / 256 / n, coerced to the next rate at or above
                ok = [12.8e6 / 256 / n for n in range(31, 0, -1)]
                task.rate = next((f for f in ok if f >= rate * (1 - 1e-12)), ok[-1])
                task.buffer = int(samps_per_chan)

            @property
            def samp_clk_rate(self):
                return task.rate

        class InStream:
            @property
            def total_samp_per_chan_acquired(self):
                return task.acquired

        self.ai_channels, self.timing, self.in_stream = Chans(), Timing(), InStream()

    @property
    def number_of_channels(self):
        return len(self.channels)

    def register_every_n_samples_acquired_into_buffer_event(self, sample_interval, callback_method):
        if self.running:  # DAQmx refuses to (un)register events on a running task
            raise DaqError("Events cannot be registered while the task is running.", -200986, self.name)
        if self.every_n_cb is not None:
            raise DaqError("Every N Samples Acquired into Buffer event is already registered.", -200960, self.name)
        self.log.append("register every_n")
        self.every_n, self.every_n_cb = int(sample_interval), callback_method

    def register_done_event(self, callback_method):
        if self.running:
            raise DaqError("Events cannot be registered while the task is running.", -200986, self.name)
        if self.done_cb is not None:
            raise DaqError("Done event is already registered.", -200961, self.name)
        self.log.append("register done")
        self.done_cb = callback_method

    def start(self):
        if self.hw.start_failures:
            self.hw.start_failures -= 1
            raise DaqError("Start failed.", -50103, self.name)
        self.log.append("start")
        self.starts += 1
        with self.lock:
            self.acquired = self.read_pos = 0  # a (re)started task begins with an empty buffer
            self.running = True
        if self.hw.realtime:
            self.thread = threading.Thread(target=self._realtime, daemon=True)
            self.thread.start()

    def stop(self):
        self.log.append("stop")
        self.stops += 1
        self.running = False
        if self.thread is not None and self.thread is not threading.current_thread():
            self.thread.join(2.0)
        self.thread = None

    def close(self):
        self.log.append("close")
        self.closes += 1
        self.running = False
        self.closed = True

    def is_task_done(self):
        if self.hw.done_error is not None:
            raise DaqError("The device stopped.", self.hw.done_error, self.name)
        return not self.running

    # --- the hardware side

    def acquire(self, n_blocks: int = 1, callbacks: bool = True) -> None:
        """The module acquires ``n_blocks`` x N samples; the every-N callback fires after each N."""
        for _ in range(n_blocks):
            if not self.running:
                return
            with self.lock:
                self.acquired += self.every_n
            if callbacks:
                assert self.every_n_cb(id(self), 1, self.every_n, None) == 0  # must return an int

    def fire_done(self, status: int) -> None:
        self.running = False
        assert self.done_cb(id(self), status, None) == 0

    def _realtime(self):
        period = self.every_n / self.rate / self.hw.speed
        t_next = time.monotonic() + period
        while self.running:
            time.sleep(max(0.0, t_next - time.monotonic()))
            t_next += period
            if self.running:
                self.acquire(1)


class FakeReader:
    def __init__(self, hw: FakeHardware, in_stream):
        self.task = next(t for t in hw.tasks if t.in_stream is in_stream)

    def read_many_sample(self, data, number_of_samples_per_channel=-1, timeout=10.0):
        t, n = self.task, number_of_samples_per_channel
        assert data.shape == (len(t.channels), n) and data.dtype == np.float64 and data.flags.c_contiguous
        if t.hw.read_error is not None:
            code, t.hw.read_error = t.hw.read_error, None
            raise DaqReadError("Injected read error.", code, 0, t.name)
        with t.lock:
            if t.acquired - t.read_pos > t.buffer:
                raise DaqReadError("Attempted to read samples that are no longer available. The requested "
                                   "sample was previously available, but has since been overwritten.",
                                   -200279, 0, t.name)
            if t.acquired - t.read_pos < n:
                raise DaqReadError("Some or all of the samples requested have not yet been acquired.",
                                   -200284, 0, t.name)
            k = t.read_pos + np.arange(n)
            t.read_pos += n
        for row in range(data.shape[0]):
            data[row] = signal(row, k, t.rate)
        return n


class FakeHardware:
    """The test's handle on the fake driver: tasks created, faults to inject."""

    def __init__(self, realtime=False, speed=1.0):
        self.realtime, self.speed = realtime, speed
        self.tasks: list[FakeTask] = []
        self.not_found = False
        self.create_failures = self.start_failures = 0
        self.read_error: int | None = None
        self.done_error: int | None = None

    @property
    def task(self) -> FakeTask:
        return self.tasks[-1]

    def module(self):
        hw = self

        def Task(new_task_name=""):
            t = FakeTask(hw, new_task_name)
            hw.tasks.append(t)
            return t

        return types.SimpleNamespace(
            Task=Task,
            constants=types.SimpleNamespace(AcquisitionType=AcquisitionType,
                                            TerminalConfiguration=TerminalConfiguration),
            stream_readers=types.SimpleNamespace(AnalogMultiChannelReader=lambda s: FakeReader(hw, s)),
            errors=types.SimpleNamespace(Error=Error, DaqError=DaqError, DaqReadError=DaqReadError,
                                         DaqNotFoundError=DaqNotFoundError))


def make(hw, rate=25_000.0, **kw) -> NidaqSource:
    args = dict(block_samples=250, current_scale_a_per_v=SCALE, backoff_s=(0.01, 0.05), nidaqmx_module=hw.module())
    args.update(kw)
    return NidaqSource(V_CH, I_CH, "d1", rate, **args)


def check_block(blk, rate=25_000.0, k0=None):
    """The block holds the fake's signal at stream samples ``k0...`` (default: its first_sample)."""
    k = (blk.first_sample if k0 is None else k0) + np.arange(blk.n)
    want_v = np.vstack([signal(r, k, rate) for r in range(3)])
    want_i = np.vstack([I_PEAK[p] * np.cos(2 * np.pi * FE * k / rate - 2 * np.pi * p / 3) for p in range(3)])
    np.testing.assert_allclose(blk.v_abc, want_v, atol=1e-9)
    np.testing.assert_allclose(blk.i_abc, want_i, atol=1e-9)


@pytest.fixture
def hw():
    return FakeHardware()


# ---------------------------------------------------------------------------------- tests

def test_task_setup_order_and_ranges(hw):
    src = make(hw, voltage_range_v=997.5, current_range_v=10.0)
    assert isinstance(src, Source)
    src.open()
    t = hw.task
    assert t.name == "pmsm-agent-d1"
    assert t.log[:2] == [f"add {V_CH}", f"add {I_CH}"]  # voltages first: rows va vb vc ia ib ic
    assert t.log.index("register every_n") < t.log.index("start")
    assert t.log.index("register done") < t.log.index("start")
    assert t.every_n == 250 and t.rate == 25_000.0
    assert t.buffer % (2 * 250) == 0 and t.buffer >= 2.0 * 25_000  # even multiple of N, ~2 s
    assert [c[1:] for c in t.channels] == [(-997.5, 997.5)] * 3 + [(-10.0, 10.0)] * 3
    assert src.rate_hz == 25_000.0 and src.rate_warning == ""
    src.close()


def test_blocks_scaled_in_channel_order(hw):
    src = make(hw)
    src.open()
    hw.task.acquire(3)
    blocks = [src.read(0.1) for _ in range(3)]
    assert src.read(0.01) is None  # nothing more acquired
    for j, blk in enumerate(blocks):
        assert (blk.drive, blk.rate_hz, blk.n, blk.first_sample, blk.seq) == ("d1", 25_000.0, 250, 250 * j, j)
        assert blk.v_abc.shape == blk.i_abc.shape == (3, 250) and blk.theta_e is None
        check_block(blk)
    # per-channel A/V: each phase comes out at its own peak
    np.testing.assert_allclose(np.abs(np.hstack([b.i_abc for b in blocks])).max(axis=1), I_PEAK, rtol=1e-3)
    s = src.stats
    assert (s.blocks, s.samples, s.frames, s.gaps) == (3, 750, 3, 0)
    src.close()


def test_realtime_thread_at_25ks():
    hw = FakeHardware(realtime=True)
    src = make(hw, block_samples=2500)  # 0.1 s blocks at 25 kS/s from the fake's thread
    src.open()
    t0 = time.monotonic()
    blocks = [src.read(1.0) for _ in range(4)]
    elapsed = time.monotonic() - t0
    src.close()
    assert all(b is not None for b in blocks)
    assert [b.first_sample for b in blocks] == [0, 2500, 5000, 7500]
    assert 0.3 < elapsed < 1.5  # paced by the sample clock
    for b in blocks:
        check_block(b)
    assert src.stats.gaps == 0 and src.counters["queue_overruns"] == 0
    assert hw.task.thread is None and hw.task.closes == 1


def test_coerced_rate_is_read_back_and_warned(hw, caplog):
    src = make(hw, rate=20_000.0)  # not 12.8 MHz / 256 / n: DAQmx coerces it (to 25 kS/s here)
    with caplog.at_level("WARNING", logger="protocols.nidaq"):
        src.open()
    assert hw.task.rate == 25_000.0 and src.rate_hz == 25_000.0
    assert "coerced" in src.rate_warning and "profile" in src.rate_warning
    assert any("20000" in r.getMessage() and "25000" in r.getMessage() for r in caplog.records)
    hw.task.acquire(1)
    blk = src.read(0.1)
    assert blk.rate_hz == 25_000.0
    check_block(blk, 25_000.0)
    src.close()


def test_coerced_to_the_profile_rate_only_notes_the_coercion(hw):
    src = make(hw, rate=24_000.0, profile_rate_hz=25_000.0)
    src.open()
    assert src.rate_hz == 25_000.0
    assert "coerced" in src.rate_warning and "profile" not in src.rate_warning
    src.close()


def test_buffer_overrun_restarts_task_and_makes_a_gap(hw):
    src = make(hw)
    src.open()
    t = hw.task
    t.acquire(2)
    b0, b1 = src.read(0.1), src.read(0.1)
    # the callback thread falls behind: the hardware runs a whole buffer ahead without events
    t.acquire(t.buffer // t.every_n + 1, callbacks=False)
    t.acquire(1)  # this callback's read raises -200279
    assert src.read(0.05) is None  # handled inside read(): no exception, the task restarted
    assert src.counters["buffer_overruns"] == 1 and src.counters["restarts"] == 1
    assert src.counters["daq_errors"] == 0 and "-200279" in src.stats.last_error
    assert len(hw.tasks) == 1 and t.starts == 2 and t.stops == 1 and t.closes == 0  # same task
    t.acquire(2)
    b2, b3 = src.read(0.1), src.read(0.1)
    lost = b2.first_sample - (b1.first_sample + b1.n)
    assert lost >= t.buffer  # at least the samples acquired but never read
    assert b3.first_sample == b2.first_sample + b2.n
    assert src.stats.gaps == 1 and src.stats.reconnects == 0
    assert [b.seq for b in (b0, b1, b2, b3)] == [0, 1, 2, 3]
    src.close()


def test_other_daq_errors_are_counted_and_the_task_recreated(hw):
    src = make(hw)
    src.open()
    hw.task.acquire(1)
    assert src.read(0.1).first_sample == 0
    hw.read_error = -200088  # e.g. a module removed from the chassis
    hw.create_failures = 2  # ... and it takes three tries to get the task back
    hw.task.acquire(1)
    deadline = time.monotonic() + 2.0
    while src.stats.reconnects == 0 and time.monotonic() < deadline:
        assert src.read(0.02) is None  # never raises
    assert src.stats.reconnects == 1
    assert src.counters["daq_errors"] == 3  # the read error + two failed creations
    assert src.counters["buffer_overruns"] == 0
    assert len(hw.tasks) == 2 and hw.tasks[0].closes == 1 and hw.tasks[0].stops == 1
    new = hw.task
    assert new.log.index("register every_n") < new.log.index("start")
    new.acquire(1)
    blk = src.read(0.1)
    assert blk.first_sample > 250 and src.stats.gaps == 1  # a new stream: first_sample jumps
    check_block(blk, k0=0)  # the new task's data, from its own sample 0
    src.close()


def test_done_event_error_and_start_failure_recover(hw):
    src = make(hw)
    src.open()
    hw.start_failures = 1
    hw.task.fire_done(-201003)
    deadline = time.monotonic() + 2.0
    while src.stats.reconnects == 0 and time.monotonic() < deadline:
        src.read(0.02)
    assert src.stats.reconnects == 1 and src.counters["daq_errors"] == 2  # done event + failed start
    assert [t.closes for t in hw.tasks] == [1, 1, 0]  # the task whose start failed is closed too
    hw.task.acquire(1)
    assert src.read(0.1) is not None
    src.close()


def test_stall_is_detected_and_recovered(hw):
    src = make(hw, stall_s=0.1)
    src.open()
    hw.done_error = -200474  # the driver reports why the task stopped when asked
    t0 = time.monotonic()
    while src.stats.reconnects == 0 and time.monotonic() - t0 < 2.0:
        src.read(0.02)
    assert src.counters["stalls"] >= 1 and src.counters["daq_errors"] >= 1
    assert "-200474" in src.stats.last_error
    assert len(hw.tasks) >= 2 and hw.tasks[0].closed
    src.close()


def test_slow_consumer_drops_oldest_counted_and_bounded(hw):
    src = make(hw, max_queue_blocks=8)
    src.open()
    hw.task.acquire(50)  # the consumer reads nothing meanwhile
    assert src.queued == 8 and src.counters["queue_overruns"] == 42
    got = []
    while (b := src.read(0.01)) is not None:
        got.append(b)
    assert [b.first_sample for b in got] == [250 * k for k in range(42, 50)]  # the newest survive
    assert src.stats.gaps == 1 and src.counters["buffer_overruns"] == 0
    for b in got:
        check_block(b)
    src.close()


def test_slow_consumer_realtime_memory_bounded():
    hw = FakeHardware(realtime=True, speed=20.0)  # 20x real time: 200 blocks/s of 250 samples
    src = make(hw, max_queue_blocks=5)
    src.open()
    peak = 0
    for _ in range(10):
        time.sleep(0.03)
        peak = max(peak, src.queued)
        src.read(0.0)
    src.close()
    assert peak <= 5 and src.counters["queue_overruns"] > 0 and src.stats.gaps > 0
    assert src.counters["buffer_overruns"] == 0  # the callback kept up; only the consumer was slow


def test_close_twice_is_safe(hw):
    src = make(hw)
    src.open()
    hw.task.acquire(2)
    src.close()
    src.close()
    t = hw.task
    assert (t.stops, t.closes) == (1, 1) and not src.connected
    assert src.read(0.01) is None and src.queued == 0
    t.acquire(1)  # a late callback after close is ignored
    assert src.read(0.01) is None
    with make(FakeHardware()) as s2:  # context manager
        assert s2.connected
    assert not s2.connected


def test_missing_package_gives_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "nidaqmx", None)  # import nidaqmx -> ImportError
    monkeypatch.setattr(nidaq_mod, "nidaqmx", None)
    src = NidaqSource(V_CH, I_CH, "d1")  # constructing never imports it
    with pytest.raises(NidaqNotInstalled, match=r"pmsm-agent\[nidaqmx\]") as ei:
        src.open()
    assert isinstance(ei.value, ImportError)
    with pytest.raises(ImportError, match="nidaqmx"):
        load_nidaqmx()


def test_module_attribute_injection_and_missing_driver(monkeypatch):
    hw = FakeHardware()
    hw.not_found = True
    monkeypatch.setattr(nidaq_mod, "nidaqmx", hw.module())
    src = NidaqSource(V_CH, I_CH, "d1")
    with pytest.raises(ConnectionError, match="driver is not installed"):
        src.open()
    hw.not_found = False
    src.open()  # the runtime retries open()
    assert src.connected
    src.close()


def test_wrong_channel_count_is_a_config_error(hw):
    src = NidaqSource("cDAQ1Mod1/ai0:3", I_CH, "d1", nidaqmx_module=hw.module())
    with pytest.raises(ValueError, match="3 channels each"):
        src.open()
    assert hw.task.closed and not src.connected


def test_from_config_and_docs_example(tmp_path):
    from agent.runtime.config import NidaqCfg, parse_config

    text = (ROOT / "docs" / "hardware.md").read_text()
    toml = re.search(r"```toml\n(.*?)```", text, re.S)[1]
    data = tomllib.loads(toml.replace('"profiles/rig_gear.toml"',
                                      f'"{ROOT / "config" / "profiles" / "rig_gear.toml"}"'))
    data.update(schema_version=1, state_dir=str(tmp_path), zenoh={"enabled": False})
    cfg = parse_config(data)
    (d,) = cfg.drives
    assert isinstance(d.source, NidaqCfg)
    hw = FakeHardware()
    src = NidaqSource.from_config(d.source, d.name, d.drive_profile.sampling.rate_hz, nidaqmx_module=hw.module())
    s = d.source
    assert (src.voltage_channels, src.current_channels) == (s.voltage_channels, s.current_channels)
    assert src.requested_rate_hz == src.profile_rate_hz == 25_000.0 and src.block_samples == s.block_samples
    np.testing.assert_allclose(src.current_scale.ravel(), [s.current_scale_a_per_v] * 3)
    src.open()
    assert [c[2] for c in hw.task.channels] == [s.voltage_range_v] * 3 + [s.current_range_v] * 3
    src.close()
    explicit = NidaqSource.from_config(NidaqCfg(voltage_channels=V_CH, current_channels=I_CH, rate_hz=12_800.0),
                                       "d2", 25_000.0)
    assert explicit.requested_rate_hz == 12_800.0 and explicit.profile_rate_hz == 25_000.0
