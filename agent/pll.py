"""Streaming synchronous-reference-frame PLL: theta_e and omega_e from a three-phase signal (Fig. 3).

The input ``x_abc`` ``(3, N)`` (normally the phase currents, any unit) goes through the
amplitude-invariant Clarke transform and the Park rotation of :mod:`agent.frames`. The loop locks
the input vector onto the **+q axis** (d driven to zero, q positive), so for a positive-sequence
input ``x_a = X cos(phi)`` the estimate is ``theta_e = phi - pi/2``: under ``id = 0`` current
control the current vector lies on the rotor q axis, and ``theta_e`` is the rotor d-axis angle.
``theta_e`` is wrapped to ``[-pi, pi)``; it is the angle used for sample ``k`` (predicted from the
samples before it). ``omega_e`` (electrical rad/s) is the loop-filter integrator, which is free
of the proportional path's ripple.

Loop. Phase detector ``e = atan2(-d, q)`` (rad): the exact phase error, independent of the input
amplitude, so the loop gain does not depend on the current level (the C loop, :func:`agent.kernels.pll_run`,
evaluates it by the atan series near lock and rotates the angle's cos/sin phasor by each step: the
same values to an ulp or two, without libm's cos, sin, hypot and atan2 every sample). PI loop filter, damping
``1/sqrt(2)``: ``Kp = 2 zeta wn``, ``Ki = wn**2``; closed-loop phase transfer
``H(s) = (Kp s + Ki) / (s**2 + Kp s + Ki)`` whose -3 dB bandwidth is ``2.058 fn``; from the true
speed to ``omega_e`` it is ``Ki / (s**2 + Kp s + Ki)`` (-40 dB/decade).

Gear shifting. The loop acquires with the wide ``lock_bandwidth_hz``. A lock detector low-passes
``e`` (``LOCK_FILTER_HZ``, which removes the 6th-harmonic ripple) and declares lock once
``|e| < lock_threshold_rad`` has held for ``lock_time_s``; the bandwidth then tapers geometrically
(time constant ``shift_time_s``) to the narrow ``bandwidth_hz``, so no frequency bias is frozen in
by a sudden gear change. Lock is lost when the filtered error exceeds ``UNLOCK_FACTOR`` times the
threshold, and the wide bandwidth is restored at once.

Tracking bandwidth. Transmission faults modulate the speed at ``f_gl``/``f_ch`` = 8.5..12.5 Hz on
the paper's rig and show as sidebands ``fe +/- f``; the PLL must not follow that modulation or it
would remove it from ``i_dq``. Keep ``bandwidth_hz`` well below 8 Hz: the default 3 Hz gives
``|H(8.5 Hz)| = 0.24`` for the angle and 0.03 for ``omega_e``. The price is a steady lag during
speed ramps of ``alpha`` rad/s**2: angle ``-alpha / wn**2``, speed ``-2 zeta alpha / wn`` (with the
defaults 4.3 deg and 0.97 rad/s per Hz/s); beyond about 2.7 Hz/s the lag crosses the unlock threshold
and the loop cycles between gears (angle error bounded near 12 deg).

Samples that carry no phase (non-finite, or amplitude ``<= min_amplitude``; an all-zero input)
leave the frequency held: the angle free-runs at ``omega_e`` and the lock detector is frozen.
A noise-only input (drive stopped) makes the frequency wander unless ``min_amplitude`` is set.
"""

from __future__ import annotations

import math

import numpy as np

from agent.frames import CLARKE
from agent.kernels import block_rows, pll_run

#: Damping of the loop.
ZETA = 1.0 / math.sqrt(2.0)
#: -3 dB bandwidth of ``H(s)`` over the natural frequency ``fn`` at ``ZETA``.
BW_PER_FN = math.sqrt(1.0 + 2.0 * ZETA**2 + math.sqrt((1.0 + 2.0 * ZETA**2) ** 2 + 1.0))
#: Cut-off of the lock detector's phase-error low-pass, Hz.
LOCK_FILTER_HZ = 50.0
#: Lock is lost when the filtered phase error exceeds this multiple of ``lock_threshold_rad``.
UNLOCK_FACTOR = 4.0
#: Fewest samples from which :func:`input_start` reads where an input starts.
MIN_START_SAMPLES = 8


class PLL:
    """Streaming SRF-PLL with gear shifting; see the module docstring for the loop.

    ``rate_hz``: sample rate, Hz. ``f_nominal_hz``: initial frequency, Hz (electrical).
    ``bandwidth_hz``: closed-loop -3 dB bandwidth once locked, Hz (keep well below 8 Hz).
    ``lock_bandwidth_hz``: -3 dB bandwidth while acquiring, Hz. ``lock_threshold_rad``: filtered
    phase error below which the loop counts as locked, rad, after ``lock_time_s`` s.
    ``shift_time_s``: time constant of the bandwidth taper after lock, s. ``min_amplitude``:
    input amplitude (units of ``x_abc``) at or below which a sample is ignored.
    ``theta0``: initial angle, rad.
    """

    def __init__(self, rate_hz: float, f_nominal_hz: float, *, bandwidth_hz: float = 3.0,
                 lock_bandwidth_hz: float = 100.0, lock_threshold_rad: float = 0.05,
                 lock_time_s: float = 0.01, shift_time_s: float = 0.02,
                 min_amplitude: float = 0.0, theta0: float = 0.0):
        if not 0.0 < bandwidth_hz <= lock_bandwidth_hz < rate_hz / 10.0:
            raise ValueError("need 0 < bandwidth_hz <= lock_bandwidth_hz < rate_hz / 10")
        ts = 1.0 / rate_hz
        self.rate_hz, self.f_nominal_hz, self.theta0 = float(rate_hz), float(f_nominal_hz), theta0
        self._wn_acq = 2.0 * math.pi * lock_bandwidth_hz / BW_PER_FN
        # the loop runs in C (agent.kernels.pll_run), which documents this vector and the state's
        self._par = np.array([
            ts, 2.0 * math.pi * bandwidth_hz / BW_PER_FN, self._wn_acq,
            math.exp(-ts / shift_time_s), -math.expm1(-2.0 * math.pi * LOCK_FILTER_HZ * ts),
            lock_threshold_rad, UNLOCK_FACTOR * lock_threshold_rad,
            max(1.0, round(lock_time_s * rate_hz)), min_amplitude, ZETA,
        ])
        self._clarke = np.ascontiguousarray(CLARKE[:2])
        self.reset()

    def reset(self, x_abc=None) -> None:
        """Return to the initial state (unlocked, wide band): at ``f_nominal_hz`` and ``theta0``, or,
        given the input about to be processed, where it starts (:func:`input_start`) if it can tell."""
        start = None if x_abc is None else input_start(x_abc, self.rate_hz)
        f0, th0 = start or (self.f_nominal_hz, self.theta0)
        th0 = (th0 + math.pi) % (2.0 * math.pi) - math.pi
        self._state = np.array([th0, 2.0 * math.pi * f0, 0.0, 0.0, 0.0, self._wn_acq, 1.0, 0.0, 0.0])

    @property
    def locked(self) -> bool:
        """True once the lock detector has declared lock (and until it is lost)."""
        return bool(self._state[4])

    def process(self, x_abc, cos_sin: bool = False):
        """Track a block ``(3, N)``; returns ``theta_e`` (rad, in ``[-pi, pi)``), ``omega_e`` (rad/s),
        and with ``cos_sin`` also ``(4, N)``: cos and sin of ``theta_e`` and of the mid angle
        ``theta_e + omega_e T_s / 2`` (the Park rotations of currents and held voltages)."""
        x = np.ascontiguousarray(x_abc, dtype=float)
        if x.ndim != 2 or x.shape[0] != 3:
            raise ValueError(f"x_abc must be shaped (3, N), got {x.shape}")
        theta, omega, self._state, cs = pll_run(x, self._clarke, self._par, self._state, cos_sin=True)
        return (theta, omega, cs) if cos_sin else (theta, omega)

    def process_rows(self, i_abc, v_abc, limits, theta_last: float, rows: np.ndarray,
                     unwrapped: np.ndarray | None = None, sums: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
        """Track a block of currents ``i_abc`` ``(3, N)`` (non-finite samples taken as
        :func:`numpy.nan_to_num` makes them) and write, in the same pass, the streaming pipeline's
        signal rows from it and ``v_abc`` (:func:`agent.kernels.block_rows`: ``rows`` ``(11, N)``;
        ``limits`` = max |i|, |v|). Returns ``theta_e`` unwrapped from ``theta_last`` (rad; written
        into ``unwrapped`` when given) and whether a sample is NaN or saturated; adds to the hop
        sums ``sums`` when given."""
        theta, bad, self._state = block_rows(i_abc, v_abc, self._clarke, limits, theta_last, rows,
                                             pll=(self._par, self._state), unwrapped=unwrapped, sums=sums)
        return theta, bad


def input_start(x_abc, rate_hz: float, span_s: float = 0.02) -> tuple[float, float] | None:
    """Where a recorded input starts: (frequency in Hz, angle in rad in the PLL's convention, the
    input on +q), from a line through its vector's unwrapped angle over the first ``span_s``; None
    where the input carries no phase there, has fewer than ``MIN_START_SAMPLES`` samples or does
    not turn forwards. A PLL started there has no
    acquisition transient: started at ``f_nominal_hz`` and angle 0 instead, the first 30-40 ms of a
    record carry angle errors up to 0.8 rad, which a regression over the record reads as a model."""
    x = np.asarray(x_abc, dtype=float)[:, : max(int(span_s * rate_hz), MIN_START_SAMPLES)]
    ab = CLARKE[:2] @ x
    if x.shape[1] < MIN_START_SAMPLES or not (np.all(np.isfinite(ab)) and np.all(np.hypot(ab[0], ab[1]) > 0)):
        return None
    phi = np.unwrap(np.arctan2(ab[1], ab[0]))
    slope, phi0 = np.polyfit(np.arange(phi.size), phi, 1)
    f = slope * rate_hz / (2.0 * math.pi)
    return (f, phi0 - 0.5 * math.pi) if 0.0 < f < rate_hz / 20.0 else None


def track(x_abc, rate_hz: float, f_nominal_hz: float, **kw) -> tuple[np.ndarray, np.ndarray]:
    """A :class:`PLL` over a whole record ``(3, N)``, started where the record starts
    (:meth:`PLL.reset`): ``theta_e`` (rad), ``omega_e`` (rad/s)."""
    pll = PLL(rate_hz, f_nominal_hz, **kw)
    pll.reset(x_abc)
    return pll.process(x_abc)
