"""Rotor-flux harmonics: psi_pm,d = psi_m + psi_6c cos(6 theta_e) + psi_6s sin(6 theta_e)."""

import numpy as np

from agent.effects.base import Effect, Param, amplitude, mid_angle


def columns(sig):
    th6 = 6.0 * mid_angle(sig)
    c, s, w = np.cos(th6), np.sin(th6), sig.omega_e
    # d: -d psi_pm/dt = 6 w (psi_c sin - psi_s cos); q: -w (psi_c cos + psi_s sin)   (V per Wb)
    return np.stack((np.stack((6 * w * s, -w * c)), np.stack((-6 * w * c, -w * s))))


EFFECT = Effect(
    id="flux_harmonics",
    physics="The magnet flux seen by the d axis carries a 6th harmonic of the electrical angle "
            "(5th and 7th space harmonics), psi_pm,d = psi_m + psi_6 cos(6 theta_e + phi) (Wb), "
            "which adds 6 omega_e psi_6 on d and omega_e psi_6 on q (V).",
    kind="voltage",
    params=(Param("psi_6c", "Wb", "6th-harmonic flux, cosine part", 0.005, -0.1, 0.1, "psi_m"),
            Param("psi_6s", "Wb", "6th-harmonic flux, sine part", 0.005, -0.1, 0.1, "psi_m")),
    columns=columns,
    report=lambda v, ctx: {"psi_6_Wb": amplitude(v), "phase_rad": float(np.arctan2(v[1], v[0]))},
    signature="6 fe in dq (5th and 7th in abc), locked to the rotor angle, amplitude growing with speed",
    dq_orders=(6,), abc_orders=(5, 7),
    reveals="any steady record at speed (the 6 fe line); stronger at higher speed",
)
