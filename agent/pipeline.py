"""Streaming pipeline of one drive: blocks -> angle -> window -> model -> residual spectrum and
parameter cluster -> evidence -> decision -> alarm state, with fixed memory.

Every ``hop_s`` the last *span* of ``span_windows`` x ``window_s`` samples (a ring buffer) is
assessed in one flow, the same as offline ``diagnose``: signals, operating point (a drive that is
not running is quality ``no_model``, :mod:`agent.sanity`), the baseline scheduled for it
(:mod:`agent.library`), the residual spectra of its windows (each computed once, when the window
completes, and reused by later spans), the cluster point, and the alarm evidence
(:mod:`agent.evidence`): the newest window for the gross path, stretches of ``alarm.stretch_s``
for the slow-wear CUSUMs, a settling guard after operating-point changes. The paper's per-span
rule still gives the ``peaks`` shown with a status.

Around the decision:

* persistence: a level is raised when ``persist_hops`` consecutive decisions reach it;
* hold: a raised level is kept until lower decisions have lasted ``alarm_hold_s`` (no chattering);
* quality: ``no_model`` outside every baseline or when the drive is not running (no alarm),
  ``learning`` while a baseline is being learned, ``bad_input`` for a span with NaN or saturated
  samples, ``stale`` when input stops (:meth:`DriveMonitor.tick`), else ``good``; every status
  carries its ``reason``, the evidence per family and the learning progress in ``extra``.

Latency: a gross fault that starts at t0 fills a window by t0 + window and is raised at the next
hop (window + hop, after a settling period if the operating point just changed); slow wear is
raised when its CUSUM crosses its threshold (minutes: docs/benchmarks.md).

Learning (commissioning) runs the baseline's two passes on the stream
(:class:`agent.baseline.BaselineBuilder`): ``learn_windows`` non-overlapping spans for the
parameters, then at least ``learn_stretches`` stretches over ``learn_min_s`` for the thresholds
(non-overlapping windows) and the alarm statistics; it refuses, with the reason, a load or speed
spread beyond the schedule's tolerance, too many unusable spans, a change of the lines' level
within the learning, and an operating point that a baseline already covers (unless told to
replace it). The baseline is then written to the library (atomically) and scheduled.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np

from agent.baseline import SEARCH_BINS, BaselineBuilder, TrainingRecord, residual_spectra
from agent.decision import STATES, listed_peaks
from agent.evidence import FULL_EVIDENCE_STRETCHES, AlarmConfig, AlarmLogic, feature_values, learning_shift
from agent.frames import CLARKE, cos_sin32
from agent.identify import cluster_point, operating_point_of_means, solve_torque
from agent.sanity import not_running_of
from agent.library import ModelLibrary
from agent.model import BASE_TERMS, Signals
from agent.pll import PLL
from agent.kernels import ROWS, block_rows, ltv_residuals, new_sums
from agent.spectrum import amplitude_spectrum
from agent.training import ACCEPT_FLAG, fault_reading
from agent.profile import DriveProfile
from protocols.base import Block, DriveStatus

log = logging.getLogger(__name__)


_THETA_LIMIT = 2.0**20  #: rad; the buffered angle is kept within +- this (either sense of rotation)
#: |t| of a feature's change within the learning stretches above which learning refuses (a fault
#: starting while learning): with 40 stretches P(|t_38| > 6) = 5e-7 per split and feature
LEARNING_SHIFT_T = 6.0
LEARNING_SHIFT_MIN = 20  #: stretches from which the check is made (fewer: too little to tell)
#: rows of the signal ring (agent.kernels.block_rows writes them): phase voltages and currents,
#: speed, dq signals (the input power is the phases' product, summed per hop); stored as float32
#: (24-bit mantissa, above any ADC's resolution). The
#: angle has a float64 ring of its own: unwrapped up to _THETA_LIMIT, float32 would resolve it to 0.06 rad.
RING_DTYPE = np.float32


#: The newest window's residual is simulated hop by hop (:meth:`DriveMonitor._hop_residuals`) up to
#: this many hops a window; beyond, the open windows' residuals would outweigh the gain.
MAX_HOPS_PER_WINDOW = 4


def residual_bytes(rate_hz: float, window_s: float, hop_s: float) -> int:
    """Bytes of the open windows' residuals kept between hops (float32): with m hops a window,
    m - 1 windows are open holding 1 .. m - 1 hops each (one hop at the default m = 2)."""
    m = int(round(window_s / hop_s))
    n_hop = int(round(hop_s * rate_hz))
    return n_hop * m * (m - 1) // 2 * 4 if m <= MAX_HOPS_PER_WINDOW else 0


def ring_bytes(rate_hz: float, span_s: float, window_s: float | None = None, hop_s: float | None = None) -> int:
    """Bytes of one drive's signal ring: a span of the float32 rows and the float64 angle; given
    ``window_s`` and ``hop_s``, also the open windows' residuals (:func:`residual_bytes`)."""
    extra = residual_bytes(rate_hz, window_s, hop_s) if window_s and hop_s else 0
    return int(round(span_s * rate_hz)) * (len(ROWS) * np.dtype(RING_DTYPE).itemsize + 8) + extra


@dataclass(frozen=True)
class HopSums:
    """Sums over one hop of the ring, from which a span's operating point, running check and torque
    regression follow without the span's samples (each sample summed once, on its hop). The angle
    enters as its deviation from the hop's mean ``theta_mean`` (rad), so the sums stay exact where
    the angle is large."""

    n: int
    power: float  #: sum of P_in, W
    omega: float  #: sum of omega_e, rad/s
    i_q: float
    i_dq: float  #: sum of i_d i_q, A^2 (the reluctance torque)
    i_sq: float  #: sum of i_d^2 + i_q^2, A^2
    i_min: tuple[float, float]  #: (i_d, i_q) minima and maxima, A (NaN when a sample is not finite)
    i_max: tuple[float, float]
    theta_mean: float
    theta_sq: float  #: sum of (theta - theta_mean)^2
    theta_omega: float
    theta_power: float
    omega_sq: float
    omega_power: float


def hop_sums(sums: np.ndarray, n: int) -> HopSums:
    """The :class:`HopSums` of a hop of ``n`` samples from the sums :func:`agent.kernels.block_rows`
    carried over it (:data:`agent.kernels.SUMS`, about their angle ``ref``): the angle's mean, and
    its moments about it (sum of (theta - mean)^2 = sum dth^2 - (sum dth)^2 / n, and alike)."""
    ref, power, omega, i_q, i_dq, i_sq, d_lo, q_lo, d_hi, q_hi, dth, dth_sq, dth_omega, dth_power, omega_sq, \
        omega_power, _ = sums.tolist()
    shift = dth / n  # the mean less ref
    return HopSums(n, power, omega, i_q, i_dq, i_sq, (d_lo, q_lo), (d_hi, q_hi), ref + shift,
                   dth_sq - shift * dth, dth_omega - shift * omega, dth_power - shift * power, omega_sq, omega_power)


class _OpenWindows:
    """The windows of one baseline's model whose phase-a residual is simulated hop by hop: per open
    window [start sample, residual parts (one a hop), state at the next hop's first sample]; the
    stream sample ``upto`` they reach; ``done``: the last completed window's residual by end sample."""

    def __init__(self, model: str, upto: int):
        self.model, self.upto = model, upto
        self.windows: list[list] = []
        self.done: dict[int, np.ndarray] = {}


def _gram(x) -> np.ndarray:
    """x x^T of a few long rows ``x`` (m rows of N), by their dot products (BLAS's matrix product
    is about twice as slow at this shape)."""
    m = len(x)
    g = np.empty((m, m))
    for i in range(m):
        for j in range(i, m):
            g[i, j] = g[j, i] = x[i] @ x[j]
    return g


def _per_sample(model) -> bool:
    """True when the model's free run is a per-sample recursion of per-sample inputs, so that a
    window's simulation can be split at hop boundaries (Euler, no effect terms)."""
    return model.discretisation == "euler" and not model.extra_d and not model.extra_q


@dataclass(frozen=True)
class PipelineConfig:
    window_s: float = 2.0  #: residual-spectrum window, s (a baseline's thresholds are learned on it)
    span_windows: int = 2  #: windows per assessment (a record of this length offline)
    hop_s: float = 1.0  #: an assessment every hop, s (divides window_s)
    persist_hops: int = 1  #: consecutive decisions needed to raise a level
    alarm_hold_s: float = 10.0  #: a raised level drops only after this long below it, s
    stale_after_s: float = 3.0  #: no input for this long -> quality "stale", s
    learn_windows: int = 30  #: spans to learn the baseline's parameters (pass 1)
    learn_stretches: int = FULL_EVIDENCE_STRETCHES  #: stretches for the thresholds and alarm statistics (pass 2)
    learn_min_s: float = 1200.0  #: s of operation pass 2 covers at least (cold to hot: thermal drift)
    max_current_a: float = float("inf")  #: |i| at or above this is saturation -> bad input
    max_voltage_v: float = float("inf")
    alarm: AlarmConfig = AlarmConfig()  #: the alarm logic (agent.evidence)
    ring_dtype: str = np.dtype(RING_DTYPE).name  #: storage of the signal ring (float64: the reference in tests)

    @property
    def learn_total_s(self) -> float:
        """Seconds of steady operation a commissioning needs in one uninterrupted stream: the pass-1
        spans, then whole stretches until ``learn_stretches`` and ``learn_min_s``
        (:attr:`DriveMonitor.learn_remaining_s` at the start)."""
        stretches = max(self.learn_stretches, math.ceil(self.learn_min_s / self.alarm.stretch_s - 1e-9))
        return self.learn_windows * self.window_s * self.span_windows + stretches * self.alarm.stretch_s

    def __post_init__(self):
        ratio = self.window_s / self.hop_s
        if self.hop_s <= 0 or abs(ratio - round(ratio)) > 1e-9 or self.span_windows < 1:
            raise ValueError("pipeline: hop_s must divide window_s, span_windows >= 1")


def covered_text(covering: str, op: dict) -> str:
    """Why learning at ``op`` is refused without ``replace``."""
    return (f"baseline {covering} already covers fe {op['fe_hz']:.2f} Hz, load {op['load_pct']:.1f} % "
            f"(--replace replaces it)")


def _learn_stretch() -> dict:
    """An empty commissioning stretch: per hop the features, cluster point and load, and its length, s."""
    return {"y": [], "points": [], "ops": [], "seconds": 0.0}


class DriveMonitor:
    """The pipeline of one drive; ``process(block)`` returns a status per completed hop."""

    def __init__(self, drive: str, profile: DriveProfile, library: ModelLibrary,
                 config: PipelineConfig = PipelineConfig(), on_event=None):
        self.drive, self.profile, self.library, self.config = drive, profile, library, config
        self.rate = profile.sampling.rate_hz
        self._limits = np.array([config.max_current_a, config.max_voltage_v])  #: saturation, A and V
        self.n_win = int(round(config.window_s * self.rate))
        self.n_hop = int(round(config.hop_s * self.rate))
        self.n_span = self.n_win * config.span_windows
        self.on_event = on_event or (lambda kind, detail: None)
        self._judge: str | None = None  #: the baseline that judged last (an event when it changes)
        # circular buffer of one span, one row per signal (ROWS) and the angle: each sample is
        # transformed once, on arrival; a stretch is read out as float64 (:meth:`_signals`)
        self._ring = np.zeros((len(ROWS), self.n_span), dtype=config.ring_dtype)
        self._theta = np.zeros(self.n_span)
        self.pll = PLL(self.rate, profile.rated_fe_hz)
        self.status = DriveStatus(drive)
        self._below_since: float | None = None
        # persistence and hold outlive gaps: a snapshot source (one span per stream) must still be
        # able to raise a level, and a segmented stream to drop it after alarm_hold_s
        self._recent: list[str] = []
        self._clock = 0  # samples since the monitor started (all streams): the hold's time base
        self._builder: BaselineBuilder | None = None
        self._learn_name = ""
        self._learn_vet = None
        self._reading: tuple[str, TrainingRecord] | None = None  #: the last assessed span (fault_evidence)
        self.alarms = AlarmLogic(config.alarm)
        self.reset_stream()

    # -- stream ---------------------------------------------------------------------------------
    def reset_stream(self) -> None:
        """Forget buffered samples (start, gap in the stream)."""
        self._write = 0
        self._filled = 0
        self._since_hop = 0
        self._samples = 0  # samples since the stream (re)started
        self._learn_mark = -(1 << 62)  # learning takes non-overlapping spans/windows from here on
        self._next_sample: int | None = None
        self._encoder = False  #: the last block carried an encoder angle
        self._theta_last = 0.0
        self._bad_until = 0  # stream sample until which spans contain NaN or saturated samples
        self._spectra: dict[tuple[str, int], np.ndarray] = {}  # (model, window end sample) -> spectrum
        self._open: _OpenWindows | None = None  # the windows whose residual is being simulated hop by hop
        self._q_info: dict[int, tuple] = {}  # hop end sample -> (model, q-axis X^T X, X^T y)
        self._newest: tuple[int, Signals] | None = None  # (end sample, signals) of the newest hop (_hop_signals)
        self._hop_sums: dict[int, HopSums] = {}  # hop end sample -> its sums (the span's hops)
        self._sums = new_sums(0.0)  # the open hop's, as block_rows adds to them
        self.pll.reset()
        self.last_input = time.monotonic()
        self.alarms.new_stream()

    def process(self, block: Block) -> list[DriveStatus]:
        """Append a block; every ``hop_s`` of new samples assess the last span."""
        if block.n == 0:  # nothing to add (an empty block must not take the DSP thread down)
            return []
        if self._next_sample is not None and block.first_sample != self._next_sample:
            self.on_event("gap", {"expected": self._next_sample, "got": block.first_sample})
            self.reset_stream()
        self._next_sample = block.first_sample + block.n
        self.last_input = time.monotonic()
        self._encoder = block.theta_e is not None
        # one C pass per stretch of the block up to the next hop's end or the ring's end: the ring's
        # rows (Clarke, Park) written in place, the saturation check, the angle unwrapped across
        # blocks (Signals wants it so) and the hop's sums; the angle is kept within +-2^20 rad by
        # shifting the whole buffer by whole turns, which changes no cosine and no difference. A
        # hop is assessed before the next overwrites the span's oldest samples.
        if block.theta_e is not None:
            angle = block.theta_e
            omega = block.omega_e if block.omega_e is not None else np.gradient(np.unwrap(angle)) * self.rate
            angle = np.concatenate(([angle], [omega], cos_sin32(angle), cos_sin32(angle + 0.5 * omega / self.rate)))
        elif self._samples == 0:  # a new stream: the PLL starts where it starts, as offline (record_signals)
            self.pll.reset(block.i_abc)
        out, pos = [], 0
        while pos < block.n:
            w = self._write
            take = min(block.n - pos, self.n_hop - self._since_hop, self.n_span - w)
            part = slice(pos, pos + take)
            rows, theta = self._ring[:, w:w + take], self._theta[w:w + take]
            if block.theta_e is not None:
                _, bad, _ = block_rows(block.i_abc[:, part], block.v_abc[:, part], CLARKE[:2], self._limits,
                                       self._theta_last, rows, angle=angle[:, part], unwrapped=theta, sums=self._sums)
            else:  # the PLL's loop writes the rows (its angle's cos and sin and the voltages' mid angle's at hand)
                _, bad = self.pll.process_rows(block.i_abc[:, part], block.v_abc[:, part], self._limits,
                                               self._theta_last, rows, theta, self._sums)
            if bad:
                self._bad_until = self._samples + take + self.n_span  # spans containing these samples are bad
            if abs(theta[-1]) > _THETA_LIMIT:  # either sense of rotation
                turns = 2 * np.pi * np.floor(theta[0] / (2 * np.pi))
                self._theta -= turns
                self._sums[0] -= turns
                self._hop_sums = {k: replace(h, theta_mean=h.theta_mean - turns) for k, h in self._hop_sums.items()}
            self._theta_last = theta[-1]
            self._advance(take)
            pos += take
            self._since_hop += take
            if self._since_hop == self.n_hop:
                self._since_hop = 0
                self._hop_sums[self._samples] = hop_sums(self._sums, self.n_hop)
                self._sums = new_sums(self._theta_last)
                for old in [k for k in self._hop_sums if k <= self._samples - self.n_span]:
                    del self._hop_sums[old]
                status = self._hop()
                self._newest = None  # the hop's float64 read-out lives while it is judged (1.2 MB a drive)
                if status is not None:
                    out.append(status)
        return out

    def _advance(self, n: int) -> None:
        """Count ``n`` samples written into the ring at its write position."""
        self._write = (self._write + n) % self.n_span
        self._filled = min(self.n_span, self._filled + n)
        self._samples += n
        self._clock += n

    def tick(self, now: float | None = None) -> DriveStatus | None:
        """Call periodically: after ``stale_after_s`` without input the quality becomes ``stale``."""
        now = time.monotonic() if now is None else now
        if now - self.last_input > self.config.stale_after_s and self.status.quality != "stale":
            return self._set(quality="stale")
        return None

    # -- decisions ------------------------------------------------------------------------------
    def _clean(self, n: int) -> bool:
        """True when the last ``n`` samples hold no NaN nor saturated sample."""
        return self._samples >= self._bad_until - self.n_span + n

    def _signals(self, n: int, back: int = 0, checked: bool = True, phases: bool = True) -> Signals | None:
        """``n`` samples ending ``back`` samples before the newest, oldest first, as float64
        copies; None (when ``checked``) if the last ``n + back`` hold NaN or saturated samples.
        Without ``phases`` only the dq signals, speed and angle (what a model without effects needs)."""
        if checked and not self._clean(n + back):
            return None
        start = (self._write - back - n) % self.n_span
        first = min(n, self.n_span - start)
        lo, hi = (0, len(ROWS)) if phases else (ROWS.index("omega_e"), ROWS.index("v_q") + 1)
        rows, theta, ring = np.empty((hi - lo, n)), np.empty(n), self._ring[lo:hi]
        rows[:, :first], theta[:first] = ring[:, start:start + first], self._theta[start:start + first]
        rows[:, first:], theta[first:] = ring[:, :n - first], self._theta[:n - first]
        r = lambda name: rows[ROWS.index(name) - lo]  # noqa: E731
        dq = rows[ROWS.index("i_d") - lo:ROWS.index("v_q") - lo + 1]
        if not phases:
            return Signals(dq[:2], dq[2:], theta, r("omega_e"), 1.0 / self.rate, pole_pairs=self.profile.motor.pole_pairs)
        return Signals(dq[:2], dq[2:], theta, r("omega_e"), 1.0 / self.rate, rows[3:6], rows[0:3],
                       self.profile.motor.pole_pairs)

    def _hop_signals(self, end: int, phases: bool = False) -> Signals:
        """The hop ending at stream sample ``end`` and the sample before it where the ring still holds
        it, as float64 copies (:meth:`_signals`, unchecked); the newest hop's dq signals are read out
        once (the residual simulation and the q-axis regression both read them)."""
        if not phases and self._newest is not None and self._newest[0] == end == self._samples:
            return self._newest[1]
        back = self._samples - end
        part = self._signals(self.n_hop + int(back + self.n_hop + 1 <= self._filled), back, checked=False,
                             phases=phases)
        if back == 0 and not phases:
            self._newest = (end, part)
        return part

    def _span_sums(self) -> HopSums:
        """The sums of the span's hops combined (the angle about the span's mean)."""
        hops = [self._hop_sums[e] for e in range(self._samples - self.n_span + self.n_hop, self._samples + 1, self.n_hop)]
        n = sum(h.n for h in hops)
        mean = sum(h.n * h.theta_mean for h in hops) / n
        total = lambda f: sum(getattr(h, f) for h in hops)  # noqa: E731
        shift = [h.theta_mean - mean for h in hops]
        return HopSums(n, total("power"), total("omega"), total("i_q"), total("i_dq"), total("i_sq"),
                       tuple(np.min([h.i_min for h in hops], axis=0).tolist()),
                       tuple(np.max([h.i_max for h in hops], axis=0).tolist()), mean,
                       sum(h.theta_sq + h.n * d * d for h, d in zip(hops, shift)),
                       sum(h.theta_omega + d * h.omega for h, d in zip(hops, shift)),
                       sum(h.theta_power + d * h.power for h, d in zip(hops, shift)),
                       total("omega_sq"), total("omega_power"))

    def _operating_point(self, sums: HopSums) -> dict:
        return operating_point_of_means(sums.power / sums.n, sums.i_q / sums.n, sums.omega / sums.n, self.profile,
                                        sums.i_dq / sums.n)

    def _not_running(self, sums: HopSums) -> str | None:
        lo, hi = np.array(sums.i_min), np.array(sums.i_max)
        constant = not np.all(np.isfinite(hi - lo)) or bool(np.all(hi == lo))
        return not_running_of(constant, sums.omega / sums.n, float(np.sqrt(sums.i_sq / sums.n)), self.profile)

    def _torque(self, sums: HopSums) -> np.ndarray:
        """[K_GT, B_GT] of the span (:func:`agent.identify.fit_torque` from the sums)."""
        p, k = self.profile.motor.pole_pairs, self.profile.torque_per_watt
        return solve_torque(sums.theta_sq / p**2, sums.theta_omega / p**2, sums.omega_sq / p**2,
                            k * sums.theta_power / p, k * sums.omega_power / p)

    def _window_spectrum(self, name: str, end: int) -> np.ndarray | None:
        """Residual spectrum of the window ending at stream sample ``end`` (cached). The newest
        window's residual comes hop by hop (:meth:`_hop_residuals`) where the model allows it."""
        key = (name, end)
        if key not in self._spectra:
            back = self._samples - end
            if back + self.n_win > self._filled:
                return None
            base = self.library.baselines[name]
            if (back == 0 and _per_sample(base.model) and self.n_win <= MAX_HOPS_PER_WINDOW * self.n_hop
                    and round(base.thresholds.window_s * self.rate) == self.n_win):
                self._hop_residuals(name)
                if not self._clean(self.n_win):
                    return None
                self._spectra[key] = amplitude_spectrum(self._open.done.pop(end), self.rate,
                                                        bins=base.thresholds.freqs_hz.size)[1]
            else:
                part = self._signals(self.n_win, back, phases=bool(base.model.extra_d or base.model.extra_q))
                if part is None:
                    return None
                part = replace(part, cos_sin=cos_sin32(part.theta_e))
                self._spectra[key] = residual_spectra(base.model, part, base.thresholds.window_s,
                                                      base.thresholds.freqs_hz[-1])[1][0]
            for old in [k for k in self._spectra if k[1] <= self._samples - self.n_span]:
                del self._spectra[old]
        return self._spectra[key]

    def _hop_residuals(self, name: str) -> None:
        """Bring the open windows' residuals up to the newest sample: each hop since the last call
        is read out once and simulated from the state each open window reached (and from the
        measured current for the window that starts on it; :func:`agent.kernels.ltv_residuals`,
        every open window in one call), which continues every window's free run exactly where a
        simulation of the whole window would be (the same C recursion, split, the state carried in
        float64); the residual of a hop is kept in float32 until its
        window completes (:func:`residual_bytes`); a window that completes leaves its phase-a
        residual in ``done``."""
        ow, model = self._open, self.library.baselines[name].model
        if ow is None or ow.model != name or ow.upto < self._samples - self.n_win:
            ow = self._open = _OpenWindows(name, self._samples - self.n_win)  # start afresh from the ring
        a0, a1 = model.state_matrices()
        for hop_end in range(ow.upto + self.n_hop, self._samples + 1, self.n_hop):
            part = self._hop_signals(hop_end)
            part = part.slice(part.n - self.n_hop, part.n)
            ow.windows.append([hop_end - self.n_hop, [], part.i_dq[:, 0]])
            r, x = ltv_residuals(a0, a1, part.omega_e, model.exogenous(part), part.i_dq, part.theta_e,
                                 np.column_stack([win[2] for win in ow.windows]))
            for j, win in enumerate(ow.windows):
                win[1].append(r[j])
                win[2] = x[:, j]
            for win in [v for v in ow.windows if len(v[1]) * self.n_hop == self.n_win]:
                ow.windows.remove(win)
                ow.done = {hop_end: np.concatenate(win[1])}
            for win in ow.windows:  # kept until the next hop: float32, as the ring
                win[1][-1] = win[1][-1].astype(np.float32)
            ow.upto = hop_end

    def _hop(self) -> DriveStatus | None:
        """One assessment: samples -> signals -> operating point -> baseline -> residual -> evidence -> decision."""
        if self._filled < self.n_span:
            return None
        clean = self._clean(self.n_span)
        if self._builder is not None:
            self._learn_hops += 1
            if not clean:
                self._learn_bad += 1
                if self._learn_bad > max(10, 0.2 * self._learn_hops):
                    return self._refuse(f"{self._learn_bad} of {self._learn_hops} spans had NaN or saturated "
                                        "samples: the data is not good enough to learn from",
                                        {"fe_hz": self.status.fe_hz, "load_pct": self.status.load_pct})
        if not clean:
            return self._set(quality="bad_input", reason="NaN or saturated samples in the span")
        sums = self._span_sums()
        op = self._operating_point(sums)
        self.alarms.observe((op["fe_hz"], op["load_pct"]), self.config.hop_s, self._span_ends(),
                            acquiring=self._samples <= self.n_span and not self._encoder)
        idle = self._not_running(sums)
        if idle is not None:
            return self._set(quality="no_model", model="", state="normal", spectrum_state="normal",
                             cluster_state="normal", fe_hz=op["fe_hz"], load_pct=op["load_pct"], peaks=[],
                             reason=idle)
        if self._builder is not None:
            return self._learn(self._signals(self.n_span), op)
        name = self.library.select(op["fe_hz"], op["load_pct"], self.status.model or None)
        if name is None:
            return self._set(quality="no_model", model="", state="normal", spectrum_state="normal",
                             cluster_state="normal", fe_hz=op["fe_hz"], load_pct=op["load_pct"], peaks=[],
                             reason="no baseline for this operating point")
        base = self.library.baselines[name]
        unusable = "has no alarm statistics: learn it again" if base.evidence is None else base.unusable
        if unusable is not None:
            return self._set(quality="no_model", model=name, state="normal", spectrum_state="normal",
                             cluster_state="normal", fe_hz=op["fe_hz"], load_pct=op["load_pct"], peaks=[],
                             reason=f"baseline {name} {unusable}")
        ends = [self._samples - j * self.n_win for j in range(self.config.span_windows - 1, -1, -1)]
        spectra = [self._window_spectrum(name, e) for e in ends]
        if any(s is None for s in spectra):
            return self._set(quality="bad_input", reason="NaN or saturated samples in a window")
        spectra = np.array(spectra)
        point = np.array([self._ts_over_lq(name), self._torque(sums)[1]])
        freqs = base.thresholds.freqs_hz
        y = feature_values(freqs, spectra, self.profile, op["fe_hz"], base.evidence.features, SEARCH_BINS)
        v = self.alarms.step(base.evidence, self.profile, y[-1], point, op["input_power_pct"], op["fe_hz"],
                             self.config.hop_s)
        self._reading = (name, TrainingRecord(f"{self.drive} (live)", op, None, spectra, point))
        return self._set(quality="good", model=name, state=self._hold(v.state), spectrum_state=v.spectrum_state,
                         cluster_state=v.cluster_state, fe_hz=op["fe_hz"], load_pct=op["load_pct"],
                         peaks=listed_peaks(base, freqs, spectra, op["fe_hz"]),  # the paper's rule, for display
                         cluster_distance2=base.cluster.distance2(point), reason=v.reason,
                         evidence=v.evidence, settling=v.settling)

    def _span_ends(self):
        """On a stream's first hop, the readings of the span's first and last hop and the hops per
        span (:meth:`AlarmLogic.observe`); None after that."""
        if not self.alarms.fresh:
            return None
        ends = [self._operating_point(self._hop_sums[e]) for e in (self._samples - self.n_span + self.n_hop, self._samples)]
        return (ends[0]["fe_hz"], ends[0]["load_pct"]), (ends[1]["fe_hz"], ends[1]["load_pct"]), self.n_span // self.n_hop

    def last_spectrum(self) -> tuple[str, np.ndarray, np.ndarray] | None:
        """(model, freqs_hz, amplitude) of the newest window's residual spectrum, for queries."""
        if not self._spectra:
            return None
        name, end = max(self._spectra, key=lambda k: k[1])
        return name, self.library.baselines[name].thresholds.freqs_hz, self._spectra[(name, end)]

    def _ts_over_lq(self, name: str) -> float:
        """Ts/Lq of the q-axis regression (eq. 14) over the span, from per-hop information blocks:
        each sample enters the least squares once, on its hop (streaming RLS in information form).
        The span's rows are those of a record of the span plus the row that links it to the sample
        before it, where the ring still holds that sample (not on a stream's first span, nor when a
        change of baseline recomputes the span's oldest hop)."""
        m = self.library.baselines[name].model
        if m.form not in ("lumped", "speed") or self.library.baselines[name].settings.get("prefilter_hz"):
            return cluster_point(self._signals(self.n_span), self.profile, m.form, m.extra_q,
                                 self.library.baselines[name].settings.get("prefilter_hz"))[0]
        terms = BASE_TERMS[m.form][1] + tuple(m.extra_q)
        ends = range(self._samples - self.n_span + self.n_hop, self._samples + 1, self.n_hop)
        for end in ends:
            if self._q_info.get(end, (None,))[0] != name:
                part = self._hop_signals(end, phases=bool(m.extra_q))  # a clean span (_hop judges no other)
                x = [np.asarray(t.column(part))[:-1] for t in terms]  # regressors()'s columns, no stacked copy
                y = part.i_dq[1, 1:]
                self._q_info[end] = (name, _gram(x), np.array([col @ y for col in x]))
        for old in [k for k in self._q_info if k not in ends]:
            del self._q_info[old]
        info = sum(self._q_info[e][1] for e in ends) + np.eye(len(terms)) * 1e-6
        theta = np.linalg.solve(info, sum(self._q_info[e][2] for e in ends))
        return float(theta[2])

    def _hold(self, raw: str) -> str:
        """Raise to the level held by the last ``persist_hops`` decisions; lower only after
        ``alarm_hold_s`` of lower decisions (stream time)."""
        self._recent = (self._recent + [raw])[-self.config.persist_hops:]
        sustained = min(self._recent, key=STATES.index) if len(self._recent) == self.config.persist_hops else "normal"
        held = self.status.state if self.status.quality == "good" else "normal"
        if STATES.index(sustained) > STATES.index(held):
            self._below_since = None
            return sustained
        if STATES.index(raw) >= STATES.index(held):
            self._below_since = None
            return held
        now = self._clock / self.rate
        self._below_since = now if self._below_since is None else self._below_since
        if now - self._below_since >= self.config.alarm_hold_s:
            self._below_since = None
            return raw
        return held

    def _set(self, reason=None, evidence=None, settling=False, learn_progress_pct=None, **changes) -> DriveStatus:
        """The new status; ``extra`` carries why (``reason``), the evidence trend per family
        (CUSUM / threshold), whether a settling guard holds the decision, learning progress."""
        old = self.status
        extra = {"reason": reason, "evidence": evidence if evidence is not None else old.extra.get("evidence", {}),
                 "settling": settling}
        if learn_progress_pct is not None:
            extra["learn_progress_pct"] = learn_progress_pct
        new = DriveStatus(**{**old.__dict__, **changes, "t": time.time(), "window": old.window + 1, "extra": extra})
        for key in ("state", "quality"):
            if getattr(new, key) != getattr(old, key):
                self.on_event(key, {"from": getattr(old, key), "to": getattr(new, key), "model": new.model,
                                    "fe_hz": new.fe_hz, "load_pct": new.load_pct, "peaks": new.peaks[:6],
                                    "reason": reason, "evidence": extra["evidence"]})
        if new.model and new.model != self._judge:  # which baseline judges from here on, whatever the state
            self.on_event("baseline", {"from": self._judge, "to": new.model, "fe_hz": new.fe_hz,
                                       "load_pct": new.load_pct})
            self._judge = new.model
        self.status = new
        return new

    # -- learning -------------------------------------------------------------------------------
    def start_learning(self, name: str | None = None, replace: bool = False, vet=None, **settings) -> None:
        """Learn a baseline named ``name`` (default ``<drive>_<fe>hz_<load>pct``, from the learned
        operating point) from the stream; ``replace`` lets it replace the baseline that covers the
        operating point, whatever its name (never implicit; without it a covered point is refused
        at the first span). ``vet(baseline)``, when given, is
        called with the learned baseline before it is written (it raises to keep it out)."""
        self._builder = BaselineBuilder(self.profile, window_s=self.config.window_s, **settings)
        self._learn_vet = vet
        self._builder.consecutive = True
        self._learn_name = name
        self._learn_replace = replace
        self._learn_mark = -(1 << 62)
        self._learn_stretch = _learn_stretch()
        self._learn_seconds = 0.0
        self._learn_reported = -1
        self._learn_hops = self._learn_bad = 0
        self._learn_op: dict | None = None  #: the operating point of the first span learned from
        self.on_event("learning", {"name": name, "phase": "parameters", "progress_pct": 0.0,
                                   "remaining_s": self.learn_remaining_s})

    def fault_evidence(self) -> str | None:
        """What the last assessed span reads as a fault against the baseline that covers it: the
        training guard's rule (:func:`agent.training.fault_reading`, a sideband pair above centre + 5
        spread in both windows or a cluster point beyond the 99.99 % region), or a warning of the
        alarm logic; None when neither."""
        st = self.status
        if st.quality != "good" or self._reading is None or self._reading[0] != st.model:
            return None
        name, reading = self._reading
        found = fault_reading(self.library.baselines[name], reading)
        if st.state == "warning":
            found.append(f"the alarm logic's warning ({(st.extra.get('reason') or {}).get('path', 'slow')} path)")
        return f"{self.drive} reads as faulty against {name}: {'; '.join(found)}" if found else None

    def relearn(self, name: str | None = None, accept_fault_evidence: bool = False) -> str | None:
        """Learn the present operating point again, replacing the baseline that covers it (the PLC's or
        an authorised zenoh relearn command, ``pmsm-agent learn --replace`` live). Refused while the
        drive reads as faulty against that baseline (:meth:`fault_evidence`): learning then would make
        the fault the new normal. Returns the refusal (also journalled as ``learning_refused``) or
        None when learning started."""
        reading = self.fault_evidence()
        if reading is not None and not accept_fault_evidence:
            why = (f"relearn refused: {reading}; learning now would learn the fault as healthy. Inspect the "
                   f"transmission; after a repair that changed what healthy looks like, relearn with "
                   f"`pmsm-agent learn --drive {self.drive} --replace {ACCEPT_FLAG}` (journalled)")
            self.on_event("learning_refused", {"name": name, "reason": why})
            log.warning("%s: %s", self.drive, why)
            return why
        self.start_learning(name, replace=True)
        return None

    @property
    def learning(self) -> bool:
        return self._builder is not None

    @property
    def learning_point(self) -> dict | None:
        """The operating point being learned (the pass-1 spans' median; the first span's before)."""
        if self._builder is None:
            return None
        fits = [f.operating_point for f in self._builder.fits]
        if not fits:
            return self._learn_op
        return {k: float(np.median([op[k] for op in fits])) for k in ("fe_hz", "load_pct")}

    @property
    def learn_remaining_s(self) -> float:
        """Seconds of steady operation the learning still needs, by its own rule: the pass-1 spans
        left (``span_windows`` x ``window_s`` each), then the pass-2 time until ``learn_stretches``
        stretches of ``alarm.stretch_s`` are complete and at least ``learn_min_s`` has been seen,
        rounded up to the end of a stretch (the rule is checked there). Settling hops, a stream's
        first span and a stretch cut by an operating-point move or a gap are not counted: they add
        to it (:meth:`learn_needs_text`)."""
        if self._builder is None:
            return 0.0
        c, b = self.config, self._builder
        stretch_s = c.alarm.stretch_s
        partial = self._learn_stretch["seconds"]
        for_stretches = max(c.learn_stretches - len(b.stretch_windows), 0) * stretch_s - partial
        for_minimum = c.learn_min_s - self._learn_seconds
        if for_minimum > for_stretches:  # more stretches, to the end of the one that passes learn_min_s
            for_stretches = math.ceil((partial + for_minimum) / stretch_s - 1e-9) * stretch_s - partial
        pass_1 = max(c.learn_windows - len(b.fits), 0) * self.n_span / self.rate
        return pass_1 + max(for_stretches, 0.0)

    def learn_needs_text(self, op: dict | None = None) -> str:
        """'learning reached 84 %: about 5 more minutes of steady operation at 92 % load (fe 100.0 Hz)'."""
        rest = self.learn_remaining_s
        more = f"{math.ceil(rest / 60 - 1e-9)} more minutes" if rest >= 90 else f"{math.ceil(rest - 1e-9)} more seconds"
        at = f" at {op['load_pct']:.0f} % load (fe {op['fe_hz']:.1f} Hz)" if op else ""
        return f"learning reached {self.learn_progress_pct:.0f} %: about {more} of steady operation{at}"

    @property
    def learn_progress_pct(self) -> float:
        """Share of the learning done: pass 1 spans and pass 2 stretches and seconds, by time needed."""
        if self._builder is None:
            return 100.0
        c, b = self.config, self._builder
        span_s = self.n_span / self.rate
        need_1 = c.learn_windows * span_s
        stretch_s = max(c.alarm.stretch_s, 0.0)
        need_2 = max(c.learn_stretches * stretch_s, c.learn_min_s)
        done_2 = min(len(b.stretch_windows) * stretch_s, self._learn_seconds) if c.learn_stretches else 0.0
        return round(100.0 * (min(len(b.fits), c.learn_windows) * span_s + done_2) / (need_1 + need_2), 1)

    def _refuse(self, why: str, op: dict) -> DriveStatus:
        self._builder = None
        self.on_event("learning_refused", {"name": self._learn_name, "reason": why})
        log.warning("%s: learning refused: %s", self.drive, why)
        return self._set(quality="no_model", state="normal", spectrum_state="normal", cluster_state="normal",
                         fe_hz=op["fe_hz"], load_pct=op["load_pct"], peaks=[], reason=f"learning refused: {why}")

    def _learn(self, sig: Signals, op: dict) -> DriveStatus:
        """Pass 1: ``learn_windows`` non-overlapping spans fit the parameters. Pass 2: stretches of
        ``alarm.stretch_s`` (a settling guard after operating-point changes) give the thresholds
        (non-overlapping windows) and the alarm statistics, until ``learn_stretches`` stretches
        and ``learn_min_s`` seconds; then the checks and the write."""
        b, c = self._builder, self.config
        hop_s = c.hop_s
        if self._learn_op is None:  # the first span learned from: is the point already covered?
            self._learn_op = op
            covering = self.library.select(op["fe_hz"], op["load_pct"])
            if covering is not None and not self._learn_replace:
                return self._refuse(covered_text(covering, op), op)
        if len(b.fits) < c.learn_windows:
            if self._samples - self._learn_mark >= self.n_span:  # non-overlapping spans
                self._learn_mark = self._samples
                b.add_fit(sig, f"{self.drive}@{self._samples}", encoder=self._encoder)
                if len(b.fits) == c.learn_windows:
                    self._learn_mark = -(1 << 62)
                    self.on_event("learning", {"name": self._learn_name, "phase": "thresholds",
                                               "progress_pct": self.learn_progress_pct,
                                               "remaining_s": self.learn_remaining_s})
            return self._learning_status(op)
        if self.alarms.new_stretch:  # the guard saw this hop's reading (AlarmLogic.observe)
            self._learn_stretch = _learn_stretch()  # never mixes operating points
        if self.alarms.settling:
            return self._learning_status(op)
        model = b.model()
        last = sig.slice(self.n_span - self.n_win, self.n_span)
        freqs, amp = residual_spectra(model, last, c.window_s)
        if self._samples - self._learn_mark >= self.n_win:  # thresholds: non-overlapping windows
            self._learn_mark = self._samples
            b.add_window_spectra(freqs, amp)
        st = self._learn_stretch
        st["y"].append(feature_values(freqs, amp, self.profile, op["fe_hz"], b.features(), SEARCH_BINS)[0])
        st["points"].append(cluster_point(sig, self.profile, model.form, model.extra_q,
                                          b.settings["prefilter_hz"]))
        st["ops"].append(op)
        st["seconds"] += hop_s
        self._learn_seconds += hop_s
        if st["seconds"] >= c.alarm.stretch_s - 1e-9:
            b.add_stretch(np.array(st["y"]), np.mean(st["points"], axis=0),
                          {k: float(np.mean([o[k] for o in st["ops"]])) for k in ("load_pct", "input_power_pct")},
                          st["seconds"])
            self._learn_stretch = _learn_stretch()
            loads = np.array(b.stretch_load)
            fes = np.array([f.operating_point["fe_hz"] for f in b.fits])
            spread = float(np.ptp(loads))
            if spread > self.library.schedule.load_tol_pct:
                return self._refuse(f"load spread {spread:.1f} %-points over the stretches exceeds the "
                                    f"operating-point tolerance {self.library.schedule.load_tol_pct:g}", op)
            if abs(op["fe_hz"] - float(np.median(fes))) > self.library.schedule.fe_tol_hz:
                return self._refuse(f"speed moved: fe {op['fe_hz']:.2f} Hz against {np.median(fes):.2f} Hz in "
                                    f"pass 1 (tolerance {self.library.schedule.fe_tol_hz:g} Hz)", op)
            if len(b.stretch_windows) >= c.learn_stretches and self._learn_seconds >= c.learn_min_s:
                return self._finish_learning(op)
        return self._learning_status(op)

    def _learning_status(self, op: dict) -> DriveStatus:
        pct = self.learn_progress_pct
        if int(pct // 10) != self._learn_reported:  # journal every 10 %
            self._learn_reported = int(pct // 10)
            self.on_event("learning", {"name": self._learn_name, "progress_pct": pct,
                                       "remaining_s": self.learn_remaining_s})
        return self._set(quality="learning", state="normal", spectrum_state="normal", cluster_state="normal",
                         fe_hz=op["fe_hz"], load_pct=op["load_pct"], peaks=[], learn_progress_pct=pct,
                         reason=self.learn_needs_text(op) + (f" for {self._learn_name}" if self._learn_name else ""))

    def _finish_learning(self, op: dict) -> DriveStatus:
        b = self._builder
        j, t = learning_shift(np.array([w.mean(axis=0) for w in b.stretch_windows]))
        if len(b.stretch_windows) >= LEARNING_SHIFT_MIN and abs(t) > LEARNING_SHIFT_T:
            return self._refuse(f"{b.features()[j].name} changed during learning (t = {t:.1f} between the stretches "
                                "before and after a change): the data does not look healthy and steady", op)
        baseline = b.build()
        bop = baseline.operating_point
        if self._learn_name is None:
            self._learn_name = f"{self.drive}_{bop['fe_hz']:.0f}hz_{bop['load_pct']:.0f}pct"
        covering = self.library.select(bop["fe_hz"], bop["load_pct"])
        if covering is not None and not self._learn_replace:
            return self._refuse(covered_text(covering, bop), op)
        if self._learn_vet is not None:
            self._learn_vet(baseline)
        path = self.library.add(self._learn_name, baseline)
        replaced = covering if covering not in (None, self._learn_name) else None
        if replaced is not None:  # replaced under another name: the old one leaves the library
            self.library.remove(replaced)
        self._builder = None
        self.on_event("learned", {"name": self._learn_name, "path": str(path), "operating_point": bop,
                                  "stretches": baseline.evidence.n if baseline.evidence else 0,
                                  "replaced": covering if self._learn_replace else None})
        return self._set(quality="good", state="normal", spectrum_state="normal", cluster_state="normal",
                         fe_hz=op["fe_hz"], load_pct=op["load_pct"], peaks=[], learn_progress_pct=100.0,
                         reason=f"learned {self._learn_name}")
