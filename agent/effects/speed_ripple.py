"""Speed ripple at the shaft frequency that the model's speed signal does not follow."""

import numpy as np

from agent.effects.base import Effect, Param


def columns(sig):
    # The shaft angle is theta_e / p up to a multiple of 2 pi / p that differs from record to record,
    # so the ripple's phase is referred to the record's own d-voltage line at the shaft frequency.
    th = sig.theta_e / (sig.pole_pairs or 1)
    ref = np.angle(np.sum(sig.v_dq[0] * np.exp(-1j * th)))
    c, s = np.cos(th - ref), np.sin(th - ref)
    z = np.zeros_like(c)
    return np.stack((np.stack((c, z)), np.stack((s, z)), np.stack((z, c)), np.stack((z, s))))


def report(v, ctx):
    # frame wobble eps = a/v_q rotates the dq frame; delta omega_e = eps * omega_r
    amp_d = float(np.hypot(v[0], v[1]))
    return {"ripple_V": amp_d, "omega_e_ripple_rad_s": amp_d / ctx["v_q"] * ctx["omega_r"],
            "q_ripple_V": float(np.hypot(v[2], v[3]))}


EFFECT = Effect(
    id="speed_ripple",
    physics="The rotor speed oscillates at the shaft frequency f_r = fe/p (a load or coupling torque "
            "ripple), delta omega_e in rad/s, which the speed and angle used by the model do not follow "
            "(PLL bandwidth, lumped speed): a voltage ripple at f_r on d (frame wobble, L_q i_q delta "
            "omega_e) and q (psi_m delta omega_e).",
    kind="voltage",
    params=(Param("d_in", "V", "d ripple in phase with the record's d-voltage line", 2.0),
            Param("d_quad", "V", "d ripple in quadrature", 2.0),
            Param("q_in", "V", "q ripple in phase", 0.5),
            Param("q_quad", "V", "q ripple in quadrature", 0.5)),
    columns=columns, report=report,
    signature="fe +- f_r sidebands in the phase residual (f_r = fe/p, the driving-gear line k = 1), "
              "f_r in dq; residual binned over the shaft angle",
    reveals="any record at speed whose speed signal does not carry the ripple (PLL angle, lumped form)",
)
