"""Winding resistance drifting within a record (the winding warms or cools).

Family: R_s(t) = R_s + r_1 (t - t_mid) + r_2 ((t - t_mid)^2 - T^2/12), T the record's length: a ramp
and the curvature of a first-order warming (r_2 = -r_1 / (2 tau) for a thermal time constant tau),
both zero-mean over the record, so that the model's R_s stays the mid-record level and the
record's psi_m (fitted per record) keeps its own per-record level.

Degrees of freedom: r_1 = dR/dt at mid-record (ohm/s, +-0.5 R_s per s), r_2 (ohm/s^2, +-0.5 R_s per s^2).
Reported: dR_dt_ohm_per_s (headline), the change over the record and d2R_dt2_ohm_per_s2 = 2 r_2.
"""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current


def columns(sig):
    t = (np.arange(sig.n) - 0.5 * sig.n) * sig.ts  # s from mid-record
    span = sig.n * sig.ts
    i_dq = smooth_current(sig)[0]
    return np.stack((-t * i_dq, -(t ** 2 - span ** 2 / 12.0) * i_dq))  # V per (ohm/s), V per (ohm/s^2)


def report(v, ctx):
    return {"dR_dt_ohm_per_s": float(v[0]), "dR_over_record_ohm": float(v[0] * 2.0 * ctx["t_mid"]),
            "d2R_dt2_ohm_per_s2": float(2.0 * v[1])}


EFFECT = Effect(
    id="resistance_drift",
    physics="The stator resistance changes during a record, R_s(t) = R_s + (dR/dt)(t - t_mid) + r_2 ((t - t_mid)^2 "
            "- T^2/12), dR/dt in ohm/s (the winding warms by dR/dt / (R_s 0.0039/K) K/s), r_2 in ohm/s^2 (a "
            "first-order warming's curvature); the model's R_s is the mid-record value.",
    kind="voltage",
    params=(Param("dR_dt", "ohm/s", "rate of change of R_s at mid-record", 0.2, -0.5, 0.5, "Rs_q"),
            Param("r_2", "ohm/s^2", "curvature of R_s(t) (half its second derivative)", 0.2, -0.5, 0.5, "Rs_q")),
    columns=columns, report=report,
    signature="residual growing over time within each record (time-binned residual), mostly on q",
    reveals="records long enough for R_s to change by 1 % or more within them (a winding warming by 3 K: "
            "seconds to minutes), at 30 % load or more; the curvature needs records a good part of the "
            "winding's thermal time constant long",
)
