"""The drive's voltage path, as its profile states it, and its correction of every record.

The reported voltage is the applied one shifted and turned (:mod:`agent.effects.voltage_delay`):
in the stationary alpha-beta frame v_applied(m) = exp(j a omega_e T_s) v_reported(m + d), d the
delay in samples (signed: -1 for a drive that reports its command and applies it one computation
period later, > 0 for a measured voltage through a filter), a the advance in samples of omega_e T_s
(docs/workbench.md, "The voltage path", says which drives do what). It belongs to the healthy drive
and its measurement chain, so the profile states it (``sampling.voltage_delay_samples``,
``sampling.voltage_advance_samples``) and the workbench applies it to every record's voltage before
it fits (:func:`agent.workbench.fitting.prepare`); the voltage_delay effect then measures the change
from it and reports totals.

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
    in alpha-beta (``delay`` d and ``advance`` a in samples; a fractional d interpolates linearly
    between samples, the ends hold the first and last sample). The zero sequence is shifted alike,
    the current, angle and speed are kept."""
    if delay == 0.0 and advance == 0.0:
        return sig
    n = sig.n
    k = np.arange(n, dtype=float)
    ab0 = abc_to_ab0([np.interp(k + delay, k, x) for x in sig.v_abc])  # V, v_reported(m + d)
    z = (ab0[0] + 1j * ab0[1]) * np.exp(1j * advance * sig.omega_e * sig.ts)
    v_abc = ab0_to_abc(np.stack((z.real, z.imag, ab0[2])))
    return Signals.from_abc(v_abc, sig.i_abc, sig.theta_e, sig.omega_e, sig.ts, sig.pole_pairs)


def stated_path(profile) -> tuple[float, float] | None:
    """(delay, advance) samples the profile states (``sampling.voltage_delay_samples``, the advance
    0 where only the delay is stated), or None where it states neither."""
    d, a = profile.sampling.voltage_delay_samples, profile.sampling.voltage_advance_samples
    if d is None and a is None:
        return None
    return float(d or 0.0), float(a or 0.0)
