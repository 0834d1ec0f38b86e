"""Rotor speed ripple at the shaft frequency that the model's speed signal does not carry."""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current


def shaft_line(sig) -> np.ndarray:
    """Unit sinusoid (N,) at the shaft frequency f_r = fe/p in phase with the speed error
    d theta_e/dt - omega_e: the ripple of the frame's rotation that the speed signal lacks.

    A narrow-band speed (the PLL's) under an angle that follows the rotor (the workbench's frame,
    :func:`agent.workbench.fitting.follow_current`) leaves the rotor's speed ripple in this
    difference; the phase is read from the record itself, since theta_e / p fixes the shaft angle
    only up to a multiple of 2 pi / p."""
    th = sig.theta_e / (sig.pole_pairs or 1)
    err = np.gradient(sig.theta_e) / sig.ts - sig.omega_e
    line = np.sum((err - err.mean()) * np.exp(-1j * th))
    return np.cos(th + np.angle(line)) if line else np.cos(th)  # line ~ e^{-j phase}


def columns(sig):
    # the model uses omega_e where the rotor turns at omega_e + dw: it misses j dw psi, i.e.
    # d: + dw L_q i_q, q: - dw psi_m.  With dw = W u(t): d column i_q u (V per ohm), q column -u (V per V)
    u = shaft_line(sig)
    iq = smooth_current(sig)[0][1]
    return np.stack((np.stack((iq * u, np.zeros_like(u))), np.stack((np.zeros_like(u), -u))))


def report(v, ctx):
    # headline from d: L_q is measured within 1-2 %, psi_m only together with R_s at one load
    return {"omega_e_ripple_rad_s": float(v[0] / ctx["Lq"]), "omega_e_ripple_from_q_rad_s": float(v[1] / ctx["psi_m"]),
            "q_emf_ripple_V": float(v[1])}


EFFECT = Effect(
    id="speed_ripple",
    physics="The rotor speed ripples at the shaft frequency f_r = fe/p (a coupling, load or unbalance "
            "torque once per revolution) by delta omega_e (rad/s), which the model's narrow-band speed "
            "signal does not carry: it misses the back-EMF ripple psi_m delta omega_e on q (V) and "
            "L_q i_q delta omega_e on d.",
    kind="voltage",
    params=(Param("L_dw", "ohm", "L_q delta omega_e: d-axis ripple per ampere of i_q", 0.1),
            Param("psi_dw", "V", "psi_m delta omega_e: q-axis back-EMF ripple", 0.9)),
    columns=columns, report=report,
    signature="f_r = fe/p in dq (fe +- f_r in the phase residual, the driving-gear line k = 1), in "
              "phase with the ripple of the angle's rotation",
    dq_orders=(), abc_orders=(),
    reveals="records without an encoder speed, whose angle follows the rotor (the workbench refines the "
            "PLL's) while the speed is the PLL's narrow-band one; the agent's own PLL frame carries the "
            "ripple as an angle error instead, which stays in its residual",
)
