"""Rotor-flux space harmonics, the 5th and the 7th, each with its own amplitude and phase.

Family: phase-a magnet flux psi_a(theta) = psi_m cos(theta) + psi_5 cos(5 theta + phi_5)
+ psi_7 cos(7 theta + phi_7) (phases b, c at theta -+ 2 pi/3). In alpha-beta (amplitude-invariant)
the 5th is psi_5 e^{-j(5 theta + phi_5)} (negative sequence), the 7th psi_7 e^{+j(7 theta + phi_7)};
in the rotor frame a5 e^{-j 6 theta} and a7 e^{+j 6 theta} with a5 = psi_5 e^{-j phi_5},
a7 = psi_7 e^{+j phi_7}. The back-EMF the model lacks, d Psi/dt + j omega_e Psi, is
-j 5 omega_e a5 e^{-j 6 theta} + j 7 omega_e a7 e^{+j 6 theta} (V).

Degrees of freedom: 4 linear, (psi_5 cos phi_5, psi_5 sin phi_5, psi_7 cos phi_7, psi_7 sin phi_7)
in Wb. Bounds: each within +-0.1 psi_m. A 6th harmonic of the d-axis flux alone (the 5th and 7th
equal, phi_5 = phi_7 = 0) is psi_5 = psi_7 = psi_6 / 2.
"""

import numpy as np

from agent.effects.base import Effect, Param, amplitude, mid_angle


def columns(sig):
    th6 = 6.0 * mid_angle(sig)
    c, s, w = np.cos(th6), np.sin(th6), sig.omega_e
    # the effect's voltage is minus the missing back-EMF (V per Wb), (d, q) per parameter:
    # 5th: j5w e^{-j6th} (a5 real part), 5w e^{-j6th} (a5 = c5 - j s5: the sine part)
    # 7th: -j7w e^{+j6th} (a7 real part), 7w e^{+j6th} (a7 = c7 + j s7)
    return np.stack((np.stack((5 * w * s, 5 * w * c)), np.stack((5 * w * c, -5 * w * s)),
                     np.stack((7 * w * s, -7 * w * c)), np.stack((7 * w * c, 7 * w * s))))


def report(v, ctx):
    return {"psi_5_Wb": amplitude(v[:2]), "phase_5_rad": float(np.arctan2(v[1], v[0])),
            "psi_7_Wb": amplitude(v[2:]), "phase_7_rad": float(np.arctan2(v[3], v[2]))}


_BOUND = dict(lower=-0.1, upper=0.1, scale="psi_m")

EFFECT = Effect(
    id="flux_harmonics",
    physics="The magnet flux carries 5th and 7th space harmonics, psi_a = psi_m cos(theta) + "
            "psi_5 cos(5 theta + phi_5) + psi_7 cos(7 theta + phi_7) (Wb); in the rotor frame they are "
            "6th harmonics turning backwards (the 5th) and forwards (the 7th), and the model misses their "
            "back-EMF -j 5 omega_e a5 e^{-j 6 theta} + j 7 omega_e a7 e^{+j 6 theta} (V).",
    kind="voltage",
    params=(Param("psi_5c", "Wb", "5th harmonic flux, psi_5 cos(phi_5)", 0.005, **_BOUND),
            Param("psi_5s", "Wb", "5th harmonic flux, psi_5 sin(phi_5)", 0.005, **_BOUND),
            Param("psi_7c", "Wb", "7th harmonic flux, psi_7 cos(phi_7)", 0.005, **_BOUND),
            Param("psi_7s", "Wb", "7th harmonic flux, psi_7 sin(phi_7)", 0.005, **_BOUND)),
    columns=columns, report=report,
    signature="6 fe in dq (the 5th and the 7th in abc: negative and positive sequence), locked to the "
              "rotor angle, amplitude growing with speed",
    dq_orders=(6,), abc_orders=(5, 7),
    reveals="any steady record at speed (the 6 fe line; the 5th and the 7th turn in opposite directions, "
            "so one record separates them); stronger at higher speed",
)
