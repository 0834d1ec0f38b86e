"""Inverter dead time and device drop: the applied phase voltage misses U_dt sign(i_x), sign(i)
smoothed near the zero crossings by the current ripple.

Family: dv_x = -U_dt f(i_x) per phase, common mode removed (Clarke drops it), f a ramp that reaches
+-1 at the knee |i_x| = i_k: the ripple about the operating current averages the sign over the
crossing. The knee is derived, not fitted: i_k is the record's own measured ripple, the rms of the
phase currents about their operating level (:func:`ripple`, A).

Degrees of freedom: U_dt (V, 0..0.1 v_rated). Reported: U_dt_V (headline) and ripple_A, the
records' mean sampled ripple, to which the model's knee is set. That is a setting of the model, not
a measurement of the loss's knee: the ripple the samples do not show (the PWM carrier's, under
synchronous sampling) is not in it, and the knee of the true loss (bench.family's least-squares
ramp) was 0.8-3.4 times the sampled ripple on six switched family drives. A fitted knee (a mix of
this ramp and one at 15 % of the current amplitude) was tried: its soft part is a voltage
proportional to the current near the crossings, which trades with R_s, and on the rig it took 3.7 V
of a 10 V dead time and raised the plateau to 12 V; the measured ripple gives 9.4 V before the
refit's inductance correction.
"""

import numpy as np

from agent.effects.base import Effect, Param, mid_angle, phase_to_dq, smooth_current

KNEE_MIN = 1e-3  #: A, the knee at least (a record of noise alone keeps a finite one)


def ripple(sig) -> float:
    """The knee, A: the rms of the measured phase currents about their operating level (the
    current ripple the samples show), at least ``KNEE_MIN``."""
    return max(float(np.sqrt(np.mean((sig.i_abc - smooth_current(sig)[1]) ** 2))), KNEE_MIN)


def columns(sig):
    dv_abc = -np.clip(smooth_current(sig)[1] / ripple(sig), -1.0, 1.0)  # V per V; common mode dropped by Clarke
    return phase_to_dq(dv_abc, mid_angle(sig))[None]


def report(v, ctx):
    return {"U_dt_V": float(v[0]), "ripple_A": float(np.mean([ripple(s) for s in ctx["signals"]]))}


REVEALS = ("records whose voltage is the drive's command (sampling.voltage_source = \"reference\"): a measured "
           "terminal voltage already contains the dead time; at two or more loads (the dead-time voltage stays while "
           "R_s i grows)")


def behind_measured_voltage(meta: dict) -> str | None:
    """Why records whose voltage is measured at the terminals cannot show a dead time (the
    terminal voltage holds its loss: what a dead time fits there is another effect's), or None."""
    if meta.get("voltage_source") != "measured":
        return None
    return ("their voltage is measured at the terminals (sampling.voltage_source = \"measured\"), so what a dead "
            f"time would fit here is another effect's; revealed by {REVEALS}")


EFFECT = Effect(
    id="inverter_deadtime",
    physics="Dead time and switch drop make each phase voltage U_dt (V) short in the direction of its "
            "current, dv_x = -U_dt sign(i_x) (common mode removed), U_dt ~ U_dc t_dead f_sw + V_drop; the "
            "current ripple smooths sign(i) into a ramp up to the knee, the measured ripple (A).",
    kind="voltage",
    params=(Param("U_dt", "V", "voltage lost per phase at the dead time", 6.0, lower=0.0, upper=0.1,
                  scale="v_rated"),),
    columns=columns, report=report,
    signature="6k fe ripple in dq (5th, 7th, 11th, 13th in abc) locked to the current zero crossings; "
              "a DC part against the current vector that looks like extra resistance at one load",
    dq_orders=(6, 12), abc_orders=(5, 7, 11, 13),
    reveals=REVEALS,
    unseen=behind_measured_voltage,
)
