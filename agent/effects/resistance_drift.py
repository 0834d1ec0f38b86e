"""Winding resistance drifting within a record (the winding warms or cools).

Family: R_s(t) = R_s + (dR/dt)(t - t_mid): a ramp, zero-mean over the record, so that the model's
R_s stays the mid-record level and the record's psi_m (fitted per record) keeps its own per-record
level. The curvature of a first-order warming (r_2 ((t - t_mid)^2 - T^2/12), the family's second
term) is left out: the refit reads half of each record, where the parabola is nearly the ramp (on
the rig the pair's kept responses were 97 % correlated, and neither figure was pinned), and beyond
it the parabola would be extrapolated into the held-out half.

Degrees of freedom: dR/dt (ohm/s, +-0.5 R_s per s). Reported: dR_dt_ohm_per_s at mid-record
(headline) and the change over the record.
"""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current


def columns(sig):
    t = (np.arange(sig.n) - 0.5 * sig.n) * sig.ts  # s from mid-record
    return (-t * smooth_current(sig)[0])[None]  # V per (ohm/s): -(t - t_mid) i


def report(v, ctx):
    return {"dR_dt_ohm_per_s": float(v[0]), "dR_over_record_ohm": float(v[0] * 2.0 * ctx["t_mid"])}


EFFECT = Effect(
    id="resistance_drift",
    physics="The stator resistance changes linearly during a record, R_s(t) = R_s + (dR/dt)(t - t_mid), "
            "dR/dt in ohm/s (the winding warms by dR/dt / (R_s 0.0039/K) K/s); the model's R_s is the "
            "mid-record value.",
    kind="voltage",
    params=(Param("dR_dt", "ohm/s", "rate of change of R_s", 0.2, -0.5, 0.5, "Rs_q"),),
    columns=columns, report=report,
    signature="residual growing over time within each record (time-binned residual), mostly on q",
    reveals="records long enough for R_s to change by 1 % or more within them (a winding warming by 3 K: "
            "seconds to minutes), at 30 % load or more",
)
