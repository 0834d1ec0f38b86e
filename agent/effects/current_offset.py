"""Current-sensor offsets of the acquisition (the drive's own sensors are not affected).

Family: constant offsets o_a, o_b, o_c (A) on the measured phase currents; their common part has
no alpha-beta image (Clarke drops it), their differential part is a fixed alpha-beta vector
o = (o_alpha, o_beta), which the dq frame sees turning at -omega_e.

Degrees of freedom: o_alpha, o_beta (A, each within 5 % of the rated peak current: a sensor class).
Reported: offset_A = |o| (headline) and the per-phase offsets ia_A, ib_A, ic_A (zero-sum part).
"""

import numpy as np

from agent.effects.base import Effect, Param, amplitude

_S3 = np.sqrt(3.0) / 2.0


def columns(sig):
    c, s = np.cos(sig.theta_e), np.sin(sig.theta_e)
    return np.stack((np.stack((c, -s)), np.stack((s, c))))  # Park of a fixed alpha / beta vector (A per A)


def report(v, ctx):
    a, b = v
    return {"offset_A": amplitude(v), "ia_A": float(a), "ib_A": float(-0.5 * a + _S3 * b),
            "ic_A": float(-0.5 * a - _S3 * b)}


EFFECT = Effect(
    id="current_offset",
    physics="The measured phase currents carry constant offsets (A); their differential part is a fixed "
            "alpha-beta vector o = (o_alpha, o_beta) added to the measurement, |o| in A.",
    kind="output",
    params=(Param("o_alpha", "A", "offset vector, alpha component", 0.05, -0.05, 0.05, "i_rated"),
            Param("o_beta", "A", "offset vector, beta component", 0.05, -0.05, 0.05, "i_rated")),
    columns=columns, report=report,
    signature="DC in the phase residual, 1 fe in dq (rotating at -fe), same in every record",
    dq_orders=(1,), abc_orders=(0,),
    reveals="any record",
)
