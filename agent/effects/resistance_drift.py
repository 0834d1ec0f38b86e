"""Winding resistance drifting within a record (the winding warms or cools): R_s(t) = R_s + dR/dt (t - t_mid)."""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current


def columns(sig):
    t = np.arange(sig.n) * sig.ts
    return (-(t - 0.5 * sig.n * sig.ts) * smooth_current(sig)[0])[None]  # V per (ohm/s): -(t - t_mid) i


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
