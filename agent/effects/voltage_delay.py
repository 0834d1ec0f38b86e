"""The voltage path: a signed delay between the reported and the applied voltage, and the hold.

Family: v_reported(k) = v_applied(k - d), d in samples, signed: d > 0 the report lags the applied
voltage (a DAQ anti-alias filter), d < 0 it leads (a drive reporting its command, which it applies
one computation period later: d = -1). Besides, the applied voltage may be held constant in the
rotor's dq frame over the interval (a continuous inverter, or the uncompensated part of a drive's
angle compensation) instead of in abc (PWM, what the model's mid-angle conversion assumes): the
applied dq voltage is then the reported one turned by a omega_e T_s, a = +0.5 for a dq hold.

Degrees of freedom (linear, exact for zero-order-held signals with |d| <= 1; a path further off is
reached by moving the records' voltage by whole samples, ``MOVES``, and the columns' fraction on top:
:func:`agent.workbench.fitting.moved_path`):
  d_lag >= 0 (samples, <= 2): the forward difference v(k+1) - v(k);
  d_lead >= 0 (samples, <= 1.5): minus the backward difference v(k) - v(k-1);
  advance a (samples, -1..1): j omega_e T_s v(k), the rotation.
Reported: delay_samples = d_lag - d_lead (headline), advance_samples = a, and their sum
rotation_samples, the angle by which the applied voltage leads the reported one in units of
omega_e T_s. Where the profile states the drive's own path (:mod:`agent.voltage_path`)
the records' voltage is corrected with it before the fit, the parameters measure the change from it,
and the report gives the totals (the stated path plus the change). At constant speed with a smooth
voltage all three columns are nearly j omega_e T_s v: only the sum is pinned then, and delay and
advance are reported null.

A change below ``NEGLIGIBLE`` (0.1 sample) in each of them is no finding: the free run's d axis
turns a rotation of the back-EMF by 0.001 rad into an i_d error of omega_e psi_m 0.001 / R_s (0.6 A
on a family drive), so the base model's own timing approximations (a fractional lag interpolated
between samples, zoh2 at the record's mean speed, a current window taken as straight lines) already buy a
measurable gain with 0.02-0.06 sample (null drives of bench.family, whose path is stated exactly).
"""

import numpy as np

from agent.effects.base import Effect, Param, mid_angle, phase_to_dq


NEGLIGIBLE = 0.1  #: samples: a smaller change of the path is within the models' own timing approximations
REACH = 0.5  #: samples: a fitted change of the rotation beyond this is refitted with the path moved by a whole sample
MOVES = (-1, 2)  #: whole samples the path may be moved (a command reported a sample early .. a DAQ filter two samples late)


def move_toward(values) -> int:
    """+1 or -1: the whole sample by which a fit (d_lag, d_lead, advance) wants the path moved, the
    sign of its rotation change d_lag - d_lead + a where that exceeds ``REACH``; 0 within reach.
    The rotation, not the delay alone: at one speed with a smooth voltage the fit splits it freely
    between delay and advance (a 1.8-sample delay fitted as 0.3 of delay and the advance at +1)."""
    turn = float(values[0] - values[1] + values[2])
    return int(np.sign(turn)) if abs(turn) > REACH else 0


def columns(sig):
    # v_applied(k) = v_reported(k + d): d > 0 interpolates forward, d < 0 backward   (V per sample)
    forward, backward = np.zeros_like(sig.v_abc), np.zeros_like(sig.v_abc)
    forward[:, :-1] = np.diff(sig.v_abc, axis=1)
    backward[:, 1:] = -np.diff(sig.v_abc, axis=1)
    mid = mid_angle(sig)
    turn = sig.omega_e * sig.ts * np.stack((-sig.v_dq[1], sig.v_dq[0]))  # j omega_e T_s v (V per sample)
    return np.stack((phase_to_dq(forward, mid), phase_to_dq(backward, mid), turn))


def report(v, ctx):
    # totals: the stated voltage path (ctx "voltage_path", applied to the records before the fit) plus the change fitted
    d0, a0 = ctx.get("voltage_path") or (0.0, 0.0)
    delay, advance = d0 + float(v[0] - v[1]), a0 + float(v[2])
    return {"delay_samples": delay, "advance_samples": advance, "rotation_samples": delay + advance,
            "delay_us": delay * ctx["ts"] * 1e6}


def behind_pulse_window(meta: dict) -> str | None:
    """Why records whose measured voltage comes through a window that cuts PWM pulses cannot show
    a change of the path (:func:`agent.voltage_path.cuts_pulses`: the window's effective delay
    follows the duty cycle), or None."""
    window = meta.get("pulse_window")
    if window is None:
        return None
    return (f"their voltage is measured through a window (or filter) lagging by {window:g} samples "
            f"(sampling.voltage_delay_samples), which straddles two sampling intervals and cuts the PWM pulses of "
            f"both, so its effective delay follows the duty cycle and a change of the path cannot be told from it; "
            f"revealed by records whose voltage window is aligned with the sampling (a whole sample late), or by "
            f"the drive's voltage command with its timing stated (sampling.voltage_source = \"reference\"); for a "
            f"continuous inverter, state sampling.inverter = \"continuous\"")


EFFECT = Effect(
    id="voltage_delay",
    physics="The reported voltage is the applied one delayed by d samples, v_rep(k) = v_app(k - d), d signed "
            "(> 0: a DAQ filter; < 0: a drive reporting its command before it applies it), and an applied "
            "voltage held constant in dq rather than in abc turns by a omega_e T_s against the report "
            "(a = 0.5 for a dq hold); d and a in samples.",
    kind="voltage",
    params=(Param("d_lag", "samples", "delay of the reported voltage behind the applied one", 1.0, 0.0, 2.0,
                  split=True, negligible=NEGLIGIBLE),
            Param("d_lead", "samples", "lead of the reported voltage before the applied one", 1.0, 0.0, 1.5,
                  split=True, negligible=NEGLIGIBLE),
            Param("advance", "samples", "rotation of the applied dq voltage against the reported, in omega_e T_s",
                  1.0, -1.0, 1.0, negligible=NEGLIGIBLE)),
    columns=columns, report=report,
    signature="residual correlated with the voltage increments v(k+1) - v(k) and v(k) - v(k-1) "
              "(cross-correlation with the input at lag +-1); at constant speed mostly a rotation of the "
              "voltage by omega_e (d + a) T_s",
    reveals="any record with the current loop's broadband voltage (the one-step regression reads the delay "
            "sample to sample and tells it from the hold); with a smooth voltage at one constant speed only "
            "the rotation omega_e (d + a) T_s is seen, partly absorbed into the lumped parameters: speed or "
            "load steps of 10 % or more reveal it then",
    raw=True, turns_voltage=True, unseen=behind_pulse_window, unseen_is_input=True,
    at_bound="at the columns' reach: the fit wants the voltage path further from the stated one than its columns "
             "follow (they interpolate within one sample of the stated path or of that path moved by whole samples, "
             "-1 to +2, and turn by one omega_e T_s at most); the path may be "
             "that far off, or another error of the model pulls it there, so no figure of it is given; where the "
             "drive's path is not known within a sample, state it (sampling.voltage_delay_samples, "
             "voltage_advance_samples) and explain again",
)
