"""Rotor speed ripple at the shaft frequency that the model's speed signal does not carry."""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current


def speed_error_line(sig) -> np.ndarray:
    """(N,) rad/s: the shaft-frequency (f_r = fe/p) component of the speed error
    d theta_e/dt - omega_e, by least squares over the signals.

    Under an angle that follows the rotor (the workbench's frame,
    :func:`agent.workbench.fitting.follow_current`, or an encoder) and a narrow-band speed (the
    PLL's), the rotor's speed ripple is in this difference; the phase is read off the signals
    themselves, since theta_e / p fixes the shaft angle only up to a multiple of 2 pi / p. In the
    PLL's own frame angle and speed agree up to the loop's proportional path (about a tenth of the
    ripple at 25 Hz with the 3 Hz loop), so the line nearly vanishes there."""
    th = sig.theta_e / (sig.pole_pairs or 1)
    err = np.gradient(sig.theta_e) / sig.ts - sig.omega_e
    c, s = np.cos(th), np.sin(th)
    a, b = np.linalg.lstsq(np.column_stack((c, s, np.ones_like(c))), err, rcond=None)[0][:2]
    return a * c + b * s


def columns(sig):
    # the model uses omega_e where the rotor turns at omega_e + dw: it misses j dw psi, i.e.
    # d: + dw L_q i_q (V per H), q: - dw psi_m (V per Wb)
    dw = speed_error_line(sig)
    iq = smooth_current(sig)[0][1]
    zero = np.zeros_like(dw)
    return np.stack((np.stack((iq * dw, zero)), np.stack((zero, -dw))))


def report(v, ctx):
    # the measured line times the share of it the fit confirms; headline from d against L_qx, the
    # inductance the d axis's cross term omega_e L_qx i_q carries (L_q in the rotor's frame; less in
    # a frame that follows the current vector under MTPA); psi_m is known only together with R_s
    dw = float(np.mean([np.sqrt(2.0) * np.std(speed_error_line(s)) for s in ctx["signals"]]))
    return {"omega_e_ripple_rad_s": dw * float(v[0]) / ctx["Lq_x"],
            "omega_e_ripple_from_q_rad_s": dw * float(v[1]) / ctx["psi_m"],
            "measured_speed_error_rad_s": dw}


EFFECT = Effect(
    id="speed_ripple",
    physics="The rotor speed ripples at the shaft frequency f_r = fe/p (a coupling, load or unbalance "
            "torque once per revolution) by delta omega_e (rad/s), which the model's narrow-band speed "
            "signal does not carry: it misses the back-EMF ripple psi_m delta omega_e on q (V) and "
            "L_q i_q delta omega_e on d.",
    kind="voltage",
    params=(Param("L_w", "H", "L_q as the speed ripple's d-axis term sees it (= L_qx when the ripple is real)", 0.03,
                  0.0, 2.0, "Lq"),
            Param("psi_w", "Wb", "psi_m as the speed ripple's q-axis term sees it (= psi_m)", 0.25, 0.0, 2.0, "psi_m")),
    columns=columns, report=report,
    signature="f_r = fe/p in dq (fe +- f_r in the phase residual, the driving-gear line k = 1), in "
              "phase with the ripple of the angle's rotation",
    reveals="records without an encoder speed, whose angle follows the rotor (the workbench's) while the "
            "speed is the PLL's narrow-band one; in the agent's own PLL frame angle and speed nearly "
            "agree, the columns nearly vanish and the ripple stays in its residual",
)
