"""Physical sanity of an input: is the drive running at all? (stopped, idling, constant samples)."""

from __future__ import annotations

import numpy as np

MIN_FE_FRACTION = 0.05  #: below 5 % of the rated electrical frequency the drive is not running
MIN_CURRENT_FRACTION = 0.03  #: rms phase current below 3 % of rated (or of rated torque's) is idling


def not_running(sig, profile) -> str | None:
    """Why ``sig`` (agent.model.Signals) is not a running drive, or None: constant samples, speed
    below ``MIN_FE_FRACTION`` of rated, current below ``MIN_CURRENT_FRACTION`` of rated."""
    i = np.asarray(sig.i_dq)
    constant = not np.all(np.isfinite(i)) or np.ptp(i[1]) == 0.0 and np.ptp(i[0]) == 0.0
    return not_running_of(constant, float(np.mean(sig.omega_e)), float(np.sqrt(np.mean(i[0] ** 2 + i[1] ** 2))),
                          profile)


def not_running_of(constant: bool, omega_e: float, i_rms: float, profile) -> str | None:
    """:func:`not_running` from whether the dq currents are constant (or not finite), the mean
    speed (rad/s) and the rms current-vector magnitude (A)."""
    if constant:
        return "not running: constant current samples"
    fe = abs(omega_e) / (2 * np.pi)
    if fe < MIN_FE_FRACTION * profile.rated_fe_hz:
        return f"not running: fe {fe:.2f} Hz is below {MIN_FE_FRACTION:.0%} of rated {profile.rated_fe_hz:.1f} Hz"
    i_rated = profile.motor.i_rated_peak
    if i_rated and i_rms < MIN_CURRENT_FRACTION * i_rated:
        return f"not running: current {i_rms:.3f} A is below {MIN_CURRENT_FRACTION:.0%} of rated {i_rated:.2f} A"
    return None
