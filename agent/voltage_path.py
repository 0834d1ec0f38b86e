"""The drive's voltage path, as its profile states it, and its correction of every record.

The reported voltage is the applied one shifted and turned (:mod:`agent.effects.voltage_delay`):
in the stationary alpha-beta frame v_applied(m) = exp(j a omega_e T_s) v_reported(m + d), d the
delay in samples (signed: -1 for a drive that reports its command and applies it one computation
period later, > 0 for a measured voltage through a filter), a the advance in samples of omega_e T_s
(docs/workbench.md, "The voltage path", says which drives do what). It belongs to the healthy drive
and its measurement chain, so the profile states it (``sampling.voltage_delay_samples``,
``sampling.voltage_advance_samples``); identify's physical estimate (:meth:`agent.baseline.
BaselineBuilder.add_fit`) and the workbench (:func:`agent.workbench.fitting.prepare`) read every
record's voltage through it (:func:`corrected`); the voltage_delay effect then measures the change
from it and reports totals. The lumped model the agent streams with keeps the voltage as reported:
its coefficients absorb the path at the operating point, as they absorb everything else.

Why the profile and not the records: healthy records in closed loop do not pin it. The current
loop's broadband voltage is its answer to the current's measurement noise, so a regression over
voltage lags reads the controller's equation where the path's lag is; and at one operating point
the base model's lumped parameters absorb the path (a scan of the held-out error over candidate
paths pinned a measured voltage's 0.92-sample filter lag near 0 on a family drive). Where the
profile is silent the workbench uses the voltage as reported, and a drive's own path may then be
named as voltage_delay (which it physically is).
"""

from __future__ import annotations

import numpy as np

from agent.frames import ab0_to_abc, abc_to_ab0
from agent.model import Signals


def apply_path(sig: Signals, delay: float, advance: float) -> Signals:
    """``sig`` with the voltage the machine saw: v_applied(m) = exp(j a omega_e(m) T_s) v_reported(m + d)
    in alpha-beta (``delay`` d and ``advance`` a in samples; a fractional d by :func:`shifted`). The
    zero sequence is shifted alike, the current, angle and speed are kept."""
    if delay == 0.0 and advance == 0.0:
        return sig
    ab0 = abc_to_ab0(shifted(sig.v_abc, delay))  # V, v_reported(m + d)
    z = (ab0[0] + 1j * ab0[1]) * np.exp(1j * advance * sig.omega_e * sig.ts)
    v_abc = ab0_to_abc(np.stack((z.real, z.imag, ab0[2])))
    return Signals.from_abc(v_abc, sig.i_abc, sig.theta_e, sig.omega_e, sig.ts, sig.pole_pairs)


def shifted(x: np.ndarray, d: float) -> np.ndarray:
    """Each row of ``x`` at sample k + ``d`` (d in samples, signed): four-point (cubic) Lagrange
    interpolation for a fractional d, exact for a whole one; the ends hold the first and last sample.

    A measured voltage's window lagging by a fractional d gives interval averages on a grid offset
    from the model's; interpolating them linearly averages two neighbours, a low-pass that at the
    Nyquist frequency keeps only |1 - 2 d| of the voltage. On the drive family's continuous inverters
    with such windows (64 drives, their voltage noise off, the applied interval average as the
    reference, the error weighted by 1/f above 20 Hz as the current answers it), the cubic one left
    a median 0.63 of the linear one's error with an abc hold synchronous to the samples, 0.64 with a
    dq hold, 0.70 and 0.44 on a clock asynchronous to the record's (at worst 0.94); what is left is
    the content near the Nyquist frequency that no interpolation of the windows recovers. On null
    drive 20686 (dq hold, asynchronous, 0.648 sample) the delay was claimed with the linear one.
    """
    i = int(np.floor(d))
    f = d - i
    taps = (-1, 0, 1, 2)
    weights = [np.prod([(f - u) / (t - u) for u in taps if u != t]) for t in taps]
    pad = abs(i) + 2
    xp = np.pad(np.asarray(x, float), ((0, 0), (pad, pad)), mode="edge")
    n = xp.shape[1] - 2 * pad
    return sum(w * xp[:, pad + i + t:pad + i + t + n] for t, w in zip(taps, weights) if w != 0.0)


def stated_path(profile) -> tuple[float, float] | None:
    """(delay, advance) samples the profile states (``sampling.voltage_delay_samples``, the advance
    0 where only the delay is stated), or None where it states neither."""
    d, a = profile.sampling.voltage_delay_samples, profile.sampling.voltage_advance_samples
    if d is None and a is None:
        return None
    return float(d or 0.0), float(a or 0.0)


PULSE_CUT = 0.05  #: samples: a measured voltage's window further than this from a whole sample cuts PWM pulses


def cuts_pulses(profile) -> float | None:
    """The stated window lag (samples) of a measured voltage on a PWM inverter that straddles two
    sampling intervals, more than ``PULSE_CUT`` from a whole sample; None where the window is
    aligned, the voltage is the command or the inverter is continuous.

    Such a window averages part of one interval's switching pulses and part of the next's: what it
    takes of each depends on where the pulses sit, so on the duty cycles (for a centre-aligned
    carrier: the whole of one pulse, the nearer interval's, while the duties keep the pulse edges
    inside the window, and half of each where they cross it). Its effective delay thus follows the
    operating point, between the whole samples around the stated lag; it is no delayed copy of the
    applied voltage, and a fitted change of the path cannot be told from it. On the drive family's
    null drives with a switched inverter and a measured voltage, the delay was claimed on 6 of 28
    with such a window, and on 1 of 73 with a window within 0.05 of a whole sample; on one of the
    six (drive 20165, a 0.29-sample lag) the same drive with its window at 0 or at 0.5, or with an
    averaged inverter, claimed nothing (a centre-aligned single-update carrier: at half a sample
    the window cuts both pulses at their centres, an exact half-sample delay; elsewhere not)."""
    d = profile.sampling.voltage_delay_samples
    if profile.sampling.voltage_source != "measured" or profile.sampling.inverter != "pwm" or d is None:
        return None
    return float(d) if abs(d - round(d)) > PULSE_CUT else None


def window_equivalent(sig: Signals, window: float) -> Signals:
    """``sig`` with its voltage filtered by [w/8, 1 - w/4, w/8] (w = ``window``, samples): what a
    current averaged over w T_s centred on each sample makes of the model's input.

    Between samples the current is a straight line (T_s << L/R), so its average over the window is
    y(k) = x(k) + w/8 (x(k+1) - 2 x(k) + x(k-1)), the same three-tap filter of the point samples x.
    The model x(k+1) = A x(k) + B v(k) + c commutes with it (A, B constant over three samples), so the
    averaged current obeys the model exactly with the filtered voltage: y(k+1) = A y(k) + B v_f(k) + c.
    Read with the unfiltered voltage, a one-step regression takes the filter's -w/4 v(k) for a
    smaller B (L_d 16-55 % high on family drives with w = 1)."""
    if window == 0.0:
        return sig
    v = np.pad(sig.v_abc, ((0, 0), (1, 1)), mode="edge")
    v_f = window / 8.0 * (v[:, :-2] + v[:, 2:]) + (1.0 - window / 4.0) * v[:, 1:-1]
    return Signals.from_abc(v_f, sig.i_abc, sig.theta_e, sig.omega_e, sig.ts, sig.pole_pairs)


def corrected(sig: Signals, profile) -> Signals:
    """``sig`` with the voltage the machine saw by the path ``profile`` states, as its current
    sensor's window sees it (:func:`window_equivalent`); unchanged where the profile states neither."""
    path, window = stated_path(profile), profile.sampling.current_window_samples
    sig = sig if path is None else apply_path(sig, *path)
    return sig if not window else window_equivalent(sig, float(window))
