"""Inverter dead time and device drop: the applied phase voltage misses U_dt sign(i_x), sign(i)
smoothed near the zero crossings by the current ripple.

Family: dv_x = -U_dt f(i_x) per phase, common mode removed (Clarke drops it), f a ramp that reaches
+-1 at the knee |i_x| = i_k (the PWM current ripple averages the sign over a switching period).
The knee is a linear mix of a sharp ramp (knee K_SHARP of the record's current amplitude |i|) and a
soft one (K_SOFT |i|): dv_x = -U_dt r_sharp(i_x) - U_soft (r_soft(i_x) - r_sharp(i_x)).

Degrees of freedom: U_dt (V, 0..0.1 v_rated, the plateau), U_soft (V, 0..0.1 v_rated, the part of it
that switches over the soft knee). Reported: U_dt_V (headline) and knee_A = (1 - s) i_sharp + s i_soft,
s = U_soft / U_dt (the area-equivalent knee of the mix, A). The knee is pinned where the records'
zero crossings are resolved (a current amplitude many times the knee); the plateau from the 6 fe
ripple and, across loads, the DC part.
"""

import numpy as np

from agent.effects.base import Effect, Param, mid_angle, phase_to_dq, smooth_current

K_SHARP, K_SOFT = 0.01, 0.15  #: knees of the two ramps, share of the record's current amplitude


def knees(i_dq: np.ndarray) -> tuple[float, float]:
    """(sharp, soft) knees, A, for a record's (2, N) smoothed dq current."""
    amp = max(float(np.mean(np.hypot(*i_dq))), 1e-9)
    return K_SHARP * amp, K_SOFT * amp


def columns(sig):
    i_dq, i_abc = smooth_current(sig)
    sharp, soft = (-np.clip(i_abc / k, -1.0, 1.0) for k in knees(i_dq))  # V per V; common mode dropped by Clarke
    mid = mid_angle(sig)
    return np.stack((phase_to_dq(sharp, mid), phase_to_dq(soft - sharp, mid)))


def report(v, ctx):
    sharp, soft = np.mean([knees(smooth_current(s)[0]) for s in ctx["signals"]], axis=0)
    share = float(v[1] / v[0]) if v[0] > 0 else 0.0
    return {"U_dt_V": float(v[0]), "knee_A": float(sharp + share * (soft - sharp))}


EFFECT = Effect(
    id="inverter_deadtime",
    physics="Dead time and switch drop make each phase voltage U_dt (V) short in the direction of its "
            "current, dv_x = -U_dt sign(i_x) (common mode removed), U_dt ~ U_dc t_dead f_sw + V_drop; the "
            "current ripple smooths sign(i) into a ramp up to the knee current (A).",
    kind="voltage",
    params=(Param("U_dt", "V", "voltage lost per phase at the dead time", 6.0, lower=0.0, upper=0.1,
                  scale="v_rated"),
            Param("U_soft", "V", "part of U_dt that switches over the soft knee instead of the sharp one", 3.0,
                  lower=0.0, upper=0.1, scale="v_rated", split=True)),
    columns=columns, report=report,
    signature="6k fe ripple in dq (5th, 7th, 11th, 13th in abc) locked to the current zero crossings; "
              "a DC part against the current vector that looks like extra resistance at one load",
    dq_orders=(6, 12), abc_orders=(5, 7, 11, 13),
    reveals="records whose voltage is the drive's command (sampling.voltage_source = \"reference\"): "
            "a measured terminal voltage already contains the dead time; at two or more loads (the dead-time "
            "voltage stays while R_s i grows)",
)
