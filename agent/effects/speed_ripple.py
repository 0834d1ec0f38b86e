"""Rotor speed ripple at the shaft frequency that the model's speed signal does not carry.

Family: the rotor's speed ripples at f_r = fe/p by delta omega_e (rad/s); the model, turning its
flux at a speed without that line (the PLL's narrow-band one, or the workbench frame's speed less its
shaft line: :func:`agent.workbench.fitting.frame_speed`), misses -j delta omega_e psi_s, and a frame that follows the current
vector also turns against the rotor by a share s of its angle ripple.

Degrees of freedom: k_w (0..3, the model's gain on the measured speed error's column; 1 where its
response is exact), frame_share s (-1..1). Reported: omega_e_ripple_rad_s = (1 - s) times the
measured speed error's line (headline), frame_angle_share, measured_speed_error_rad_s, k_w. A
line in some records only is not this effect (:func:`in_some_records_only`).
"""

import numpy as np

from agent.effects.base import Effect, Param


def _lines(sig) -> tuple[np.ndarray, np.ndarray]:
    """The shaft-frequency (f_r = fe/p) line of the speed error d theta_e/dt - omega_e (rad/s) and
    of its integral, the frame's angle ripple (rad), (N,) each, by least squares over the signals."""
    p = sig.pole_pairs or 1
    th = sig.theta_e / p
    err = np.gradient(sig.theta_e) / sig.ts - sig.omega_e
    c, s = np.cos(th), np.sin(th)
    a, b = np.linalg.lstsq(np.column_stack((c, s, np.ones_like(c))), err, rcond=None)[0][:2]
    w_m = float(np.mean(sig.omega_e)) / p
    return a * c + b * s, (a * s - b * c) / w_m if w_m else np.zeros_like(c)


def speed_error_line(sig) -> np.ndarray:
    """(N,) rad/s: the shaft-frequency (f_r = fe/p) component of the speed error
    d theta_e/dt - omega_e, by least squares over the signals.

    Under an angle that follows the rotor (the workbench's frame,
    :func:`agent.workbench.fitting.follow_current`, or an encoder) and a speed without the shaft
    line (the PLL's, or the frame's: :func:`agent.workbench.fitting.frame_speed`), the rotor's speed
    ripple is in this difference; the phase is read off the signals
    themselves, since theta_e / p fixes the shaft angle only up to a multiple of 2 pi / p. In the
    PLL's own frame angle and speed agree up to the loop's proportional path (about a tenth of the
    ripple at 25 Hz with the 3 Hz loop), so the line nearly vanishes there."""
    return _lines(sig)[0]


def columns(sig):
    # The model turns its flux at omega_e where the frame turns at omega_e + dw: it misses
    # -j dw psi_s (V), whatever the frame. psi_s's direction in the frame is that of the mean
    # voltage, psi_s ~ v_bar / (j omega_e) (the resistive drop R_s i, a few % of v at speed, left
    # out), so the column is -(dw / omega_e) v_bar. A frame that follows the current vector also
    # turns against the rotor (under MTPA the current's angle moves with i_q): by delta beta =
    # s theta_w, a share s of its angle ripple. Then the rotor's speed ripple is (1 - s) dw and its
    # flux psi_m, on the frame's d axis, misses s (omega_e theta_w - j dw) psi_m besides.
    dw, theta_w = _lines(sig)
    w = float(np.mean(sig.omega_e))
    v_d, v_q = float(np.mean(sig.v_dq[0])), float(np.mean(sig.v_dq[1]))
    if not w:
        return np.zeros((2, 2, sig.n))
    speed = -np.stack((dw * v_d, dw * v_q)) / w
    psi_d = v_q / w  # the stator flux's d component, the rotor's flux where L_d i_d is small
    angle = -np.stack((w * theta_w * psi_d, -dw * psi_d))
    # less its projection on the speed column: s keeps its meaning, the pair is better conditioned
    angle = angle - speed * (np.sum(angle * speed) / max(float(np.sum(speed * speed)), 1e-300))
    return np.stack((speed, angle))


def report(v, ctx):
    # the rotor's ripple (1 - s) dw, s the fitted share of the frame's angle ripple
    dw = float(np.mean([np.sqrt(2.0) * np.std(speed_error_line(s)) for s in ctx["signals"]]))
    return {"omega_e_ripple_rad_s": dw * (1.0 - float(v[1])), "frame_angle_share": float(v[1]),
            "measured_speed_error_rad_s": dw, "k_w": float(v[0])}


SPREAD = 3.0  #: a once-per-revolution line more than this many times a record's own is not one


def in_some_records_only(signals) -> str | None:
    """Why the records refute a once-per-revolution ripple, or None. A shaft torque ripples the speed
    in every record of the drive (the same speed, the same loop) by about the same amount (within
    1.9x on the 16 family drives where it was claimed). Where the largest record's shaft line is more
    than ``SPREAD`` times another record's, the line is in some records only: a load ripple whose
    frequency lies near the shaft's in those (null drive 20110: 0.64 rad/s of speed ripple 0.06 Hz
    off f_r in one record of four, under 0.05 in the others). The line is read off each record's frame
    rate whether or not its speed left it out (:func:`agent.workbench.fitting.shaft_ripple`): through a
    speed step the frame's speed may keep a true ripple's line in one record (family drive 20022), which
    no more refutes it there than elsewhere."""
    from agent.workbench.fitting import shaft_ripple

    amps = [shaft_ripple(s) for s in signals]
    if len(amps) < 2 or max(amps) <= SPREAD * min(amps):
        return None
    return (f"the shaft-frequency line of the records' speed is {', '.join(f'{a:.2g}' for a in amps)} rad/s: in "
            f"{sum(a * SPREAD >= max(amps) for a in amps)} of {len(amps)} records only (the others below 1/{SPREAD:g} "
            f"of the largest), where a once-per-revolution torque would ripple every record alike, so it is not "
            f"claimed; a load ripple near the shaft frequency in those records does this; revealed by records at "
            f"another speed (the shaft's line moves with it, a load's does not)")


EFFECT = Effect(
    id="speed_ripple",
    physics="The rotor speed ripples at the shaft frequency f_r = fe/p (a coupling, load or unbalance "
            "torque once per revolution) by delta omega_e (rad/s), which the model's narrow-band speed "
            "signal does not carry: it misses -j delta omega_e psi_s (V), the ripple times the stator "
            "flux linkage, in any frame.",
    kind="voltage",
    params=(Param("k_w", "-", "gain on -j dw psi_s, dw the speed error the records' angle shows (1 where the "
                  "model's response to it is exact; it does not scale the reported ripple)", 1.0, 0.0, 3.0),
            Param("frame_share", "-", "share s of the frame's angle ripple that is the frame turning against the "
                  "rotor (0 when the angle follows the rotor; a current-vector frame under MTPA): the rotor's "
                  "ripple is (1 - s) dw", 0.1, -1.0, 1.0)),
    columns=columns, report=report, refutes=in_some_records_only,
    signature="f_r = fe/p in dq (fe +- f_r in the phase residual, the driving-gear line k = 1), in "
              "phase with the ripple of the angle's rotation",
    reveals="records without an encoder speed, whose angle follows the rotor (the workbench's) while the "
            "speed leaves the shaft line out where the records show one; in the agent's own PLL frame angle and speed nearly "
            "agree, the columns nearly vanish and the ripple stays in its residual",
)
