"""Streaming pipeline of one drive: blocks -> angle -> window -> model -> residual spectrum and
parameter cluster -> decision -> alarm state, with fixed memory.

Every ``hop_s`` the last ``window_s`` of samples (a ring buffer) is assessed against the baseline
scheduled for the window's operating point (:mod:`agent.library`), exactly as ``diagnose`` assesses
a record. Around the per-window decision:

* persistence: a level is raised only when ``persist_windows`` consecutive windows reach it;
* hold: a raised level is kept until lower windows have lasted ``alarm_hold_s`` (no chattering);
* quality: ``no_model`` outside every baseline (no alarm), ``learning`` while a baseline is being
  learned, ``bad_input`` for a window with NaN or saturated samples, ``stale`` when input stops
  (:meth:`DriveMonitor.tick`), else ``good``. The last values are kept in every case.

Learning (commissioning) runs the baseline's two passes on streamed windows
(:class:`agent.baseline.BaselineBuilder`): ``learn_windows`` windows for the parameters, then as
many for the residual-spectrum thresholds, then the baseline is written to the library.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from agent.baseline import BaselineBuilder
from agent.decision import STATES, assess
from agent.identify import operating_point
from agent.library import ModelLibrary
from agent.model import Signals
from agent.pll import PLL
from agent.profile import DriveProfile
from protocols.base import Block, DriveStatus

log = logging.getLogger(__name__)


#: rows of the window buffer: phase voltages and currents, angle (wrapped), speed, dq signals, power
_ROWS = ("va", "vb", "vc", "ia", "ib", "ic", "theta_e", "omega_e", "i_d", "i_q", "v_d", "v_q", "p_in")


@dataclass(frozen=True)
class PipelineConfig:
    window_s: float = 2.0  #: analysis window, s (a baseline's thresholds are learned on this window)
    hop_s: float = 0.5  #: a decision every hop, s
    persist_windows: int = 2  #: consecutive windows needed to raise a level
    alarm_hold_s: float = 10.0  #: a raised level drops only after this long below it, s
    stale_after_s: float = 3.0  #: no input for this long -> quality "stale", s
    learn_windows: int = 30  #: windows per learning pass (two passes)
    max_current_a: float = float("inf")  #: |i| at or above this is saturation -> bad input
    max_voltage_v: float = float("inf")


class DriveMonitor:
    """The pipeline of one drive; ``process(block)`` returns a status per completed hop."""

    def __init__(self, drive: str, profile: DriveProfile, library: ModelLibrary, config: PipelineConfig = PipelineConfig(),
                 on_event=None):
        self.drive, self.profile, self.library, self.config = drive, profile, library, config
        self.rate = profile.sampling.rate_hz
        self.n_win = int(round(config.window_s * self.rate))
        self.n_hop = int(round(config.hop_s * self.rate))
        self.on_event = on_event or (lambda kind, detail: None)
        # circular buffer, one row per signal (see _ROWS); each sample is transformed once, on arrival
        self._buf = np.zeros((len(_ROWS), self.n_win))
        self._write = 0
        self.pll = PLL(self.rate, profile.rated_fe_hz)
        self.status = DriveStatus(drive)
        self._raw_history: list[str] = []
        self._below_since: float | None = None
        self._builder: BaselineBuilder | None = None
        self._learn_name = ""
        self.reset_stream()

    # -- stream ---------------------------------------------------------------------------------
    def reset_stream(self) -> None:
        """Forget buffered samples (start, gap in the stream)."""
        self._filled = 0
        self._since_hop = 0
        self._next_sample: int | None = None
        self.pll.reset()
        self.last_input = time.monotonic()

    def process(self, block: Block) -> list[DriveStatus]:
        """Append a block; every ``hop_s`` of new samples assess the last window."""
        if self._next_sample is not None and block.first_sample != self._next_sample:
            self.on_event("gap", {"expected": self._next_sample, "got": block.first_sample})
            self.reset_stream()
        self._next_sample = block.first_sample + block.n
        self.last_input = time.monotonic()
        if block.theta_e is not None:
            theta = block.theta_e
            omega = block.omega_e if block.omega_e is not None else np.gradient(np.unwrap(theta)) * self.rate
        else:
            theta, omega = self.pll.process(np.nan_to_num(block.i_abc))
        sig = Signals.from_abc(block.v_abc, block.i_abc, theta, omega, 1.0 / self.rate)
        data = np.vstack((block.v_abc, block.i_abc, np.mod(theta, 2 * np.pi)[None, :], omega[None, :],
                          sig.i_dq, sig.v_dq, sig.p_in[None, :]))
        out, pos = [], 0
        while pos < block.n:
            take = min(block.n - pos, self.n_hop - self._since_hop)
            self._push(data[:, pos:pos + take])
            pos += take
            self._since_hop += take
            if self._since_hop == self.n_hop:
                self._since_hop = 0
                if self._filled >= self.n_win:
                    out.append(self._assess_window())
        return out

    def _push(self, chunk: np.ndarray) -> None:
        n = chunk.shape[1]  # <= n_hop <= n_win
        end = self._write + n
        if end <= self.n_win:
            self._buf[:, self._write:end] = chunk
        else:
            split = self.n_win - self._write
            self._buf[:, self._write:] = chunk[:, :split]
            self._buf[:, :n - split] = chunk[:, split:]
        self._write = end % self.n_win
        self._filled = min(self.n_win, self._filled + n)

    def tick(self, now: float | None = None) -> DriveStatus | None:
        """Call periodically: after ``stale_after_s`` without input the quality becomes ``stale``."""
        now = time.monotonic() if now is None else now
        if now - self.last_input > self.config.stale_after_s and self.status.quality != "stale":
            return self._set(quality="stale")
        return None

    # -- decisions ------------------------------------------------------------------------------
    def _window_signals(self) -> Signals | None:
        """The last window, oldest sample first; None if it holds NaN or saturated samples."""
        b = np.roll(self._buf, -self._write, axis=1) if self._write else self._buf
        if not np.isfinite(b).all() or np.abs(b[3:6]).max() >= self.config.max_current_a \
                or np.abs(b[0:3]).max() >= self.config.max_voltage_v:
            return None
        return Signals(b[8:10], b[10:12], np.unwrap(b[6]), b[7], 1.0 / self.rate, b[3:6], b[0:3],
                       self.profile.motor.pole_pairs, b[12])

    def _assess_window(self) -> DriveStatus:
        sig = self._window_signals()
        if sig is None:
            return self._set(quality="bad_input")
        op = operating_point(sig, self.profile)
        if self._builder is not None:
            return self._learn(sig, op)
        name = self.library.select(op["fe_hz"], op["load_pct"], self.status.model or None)
        if name is None:
            self._raw_history.clear()
            return self._set(quality="no_model", model="", state="normal", spectrum_state="normal",
                             cluster_state="normal", fe_hz=op["fe_hz"], load_pct=op["load_pct"], peaks=[])
        d = assess(self.library.baselines[name], sig, self.drive)
        state = self._filter(d.state)
        return self._set(quality="good", model=name, state=state, spectrum_state=d.spectrum_state,
                         cluster_state=d.cluster_state, fe_hz=op["fe_hz"], load_pct=op["load_pct"],
                         peaks=d.peaks, cluster_distance2=d.cluster["distance2"])

    def _filter(self, raw: str) -> str:
        """Persistence to raise a level, hold time to lower it."""
        cfg = self.config
        self._raw_history = (self._raw_history + [raw])[-cfg.persist_windows:]
        held = self.status.state if self.status.quality == "good" else "normal"
        reached = min(self._raw_history, key=STATES.index) if len(self._raw_history) == cfg.persist_windows else "normal"
        if STATES.index(reached) > STATES.index(held):
            self._below_since = None
            return reached
        if STATES.index(raw) < STATES.index(held):
            now = self._stream_time()
            self._below_since = self._below_since if self._below_since is not None else now
            if now - self._below_since >= cfg.alarm_hold_s:
                self._below_since = None
                return max(raw, reached, key=STATES.index)
            return held
        self._below_since = None
        return held

    def _stream_time(self) -> float:
        return (self._next_sample or 0) / self.rate

    def _set(self, **changes) -> DriveStatus:
        old = self.status
        new = DriveStatus(**{**old.__dict__, **changes, "t": time.time(), "window": old.window + 1})
        for key in ("state", "quality"):
            if getattr(new, key) != getattr(old, key):
                self.on_event(key, {"from": getattr(old, key), "to": getattr(new, key), "model": new.model,
                                    "fe_hz": new.fe_hz, "load_pct": new.load_pct, "peaks": new.peaks[:6]})
        self.status = new
        return new

    # -- learning -------------------------------------------------------------------------------
    def start_learning(self, name: str, **settings) -> None:
        """Learn a baseline named ``name`` from the next 2 x ``learn_windows`` healthy windows."""
        self._builder = BaselineBuilder(self.profile, window_s=self.config.window_s, **settings)
        self._learn_name = name
        self._learn_skip = 0
        self.on_event("learning", {"name": name, "phase": "parameters"})

    @property
    def learning(self) -> bool:
        return self._builder is not None

    def _learn(self, sig: Signals, op: dict) -> DriveStatus:
        b, n = self._builder, self.config.learn_windows
        stride = max(1, self.n_win // self.n_hop)  # non-overlapping windows for the statistics
        self._learn_skip = (self._learn_skip + 1) % stride
        if self._learn_skip == 0:
            if len(b.fits) < n:
                b.add_fit(sig, f"{self.drive}@window{self.status.window}")
                if len(b.fits) == n:
                    self.on_event("learning", {"name": self._learn_name, "phase": "thresholds"})
            else:
                b.add_spectra(sig)
                if len(b.spectra) >= n:
                    baseline = b.build()
                    path = self.library.add(self._learn_name, baseline)
                    self._builder = None
                    self.on_event("learned", {"name": self._learn_name, "path": str(path),
                                              "operating_point": baseline.operating_point})
        return self._set(quality="learning" if self._builder else "good", state="normal",
                         spectrum_state="normal", cluster_state="normal", fe_hz=op["fe_hz"],
                         load_pct=op["load_pct"], peaks=[])
