"""Inverter dead time and device drop: the applied phase voltage misses U_dt sign(i_x)."""

import numpy as np

from agent.effects.base import Effect, Param, mid_angle, phase_to_dq, smooth_current

I_KNEE = 0.05  #: A, below this |i| the error grows linearly (current ripple smooths sign(i))


def columns(sig):
    dv_abc = -np.clip(smooth_current(sig)[1] / I_KNEE, -1.0, 1.0)  # V per V of U_dt; common mode dropped by Clarke
    return phase_to_dq(dv_abc, mid_angle(sig))[None]


EFFECT = Effect(
    id="inverter_deadtime",
    physics="Dead time and switch drop make each phase voltage U_dt (V) short in the direction of its "
            "current, dv_x = -U_dt sign(i_x) (common mode removed), U_dt ~ U_dc t_dead f_sw + V_drop.",
    kind="voltage",
    params=(Param("U_dt", "V", "voltage lost per phase at the dead time", 6.0, lower=0.0, upper=0.1,
                  scale="v_rated"),),
    columns=columns,
    report=lambda v, ctx: {"U_dt_V": float(v[0])},
    signature="6k fe ripple in dq (5th, 7th, 11th, 13th in abc) locked to the current zero crossings; "
              "a DC part against the current vector that looks like extra resistance at one load",
    dq_orders=(6, 12), abc_orders=(5, 7, 11, 13),
    reveals="records whose voltage is the drive's command (sampling.voltage_source = \"reference\"): "
            "a measured terminal voltage already contains the dead time; at two or more loads (the dead-time "
            "voltage stays while R_s i grows)",
)
