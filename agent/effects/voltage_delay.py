"""Voltage channel delayed against the current channel by d samples (DAQ filter group delays)."""

import numpy as np

from agent.effects.base import Effect, Param, mid_angle, phase_to_dq


def columns(sig):
    # true v(k) = v_meas(k + d) ~ v_meas(k) + d (v_meas(k+1) - v_meas(k))   (exact for 0 <= d <= 1)
    dv = np.zeros_like(sig.v_abc)
    dv[:, :-1] = np.diff(sig.v_abc, axis=1)
    return phase_to_dq(dv, mid_angle(sig))[None]


EFFECT = Effect(
    id="voltage_delay",
    physics="The voltage samples lag the current samples by d sampling periods (DAQ anti-alias "
            "filters of different group delay): v_meas(k) = v(k - d), d in samples (0..1).",
    kind="voltage",
    params=(Param("d", "samples", "voltage-channel delay behind the current channel", 1.0, lower=0.0, upper=2.0),),
    columns=columns,
    report=lambda v, ctx: {"delay_samples": float(v[0]), "delay_us": float(v[0] * ctx["ts"] * 1e6)},
    signature="residual correlated with the voltage increment v(k+1) - v(k) (cross-correlation with the "
              "input at lag +-1); at constant speed mostly a rotation of the voltage by omega_e d T_s",
    reveals="any record with the current loop's broadband voltage (the one-step regression reads the delay "
            "sample to sample); with a smooth voltage at one constant speed it is only a rotation "
            "omega_e d T_s, absorbed into the lumped parameters: speed or load steps of 10 % or more reveal it then",
)
