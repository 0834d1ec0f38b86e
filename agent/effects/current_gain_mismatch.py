"""Relative gain errors of the acquisition's phase-b and phase-c current sensors (against phase a).

Family: i_x,meas = (1 + g_x) i_x for x = b, c; a gain error common to all three is a scale of the
current the motor parameters take, so phase a is the reference.

Degrees of freedom: g_b, g_c (dimensionless, each within +-0.1: a sensor class). Reported: gain_b
(headline), gain_c.
"""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current
from agent.frames import CLARKE, ab_to_dq


def columns(sig):
    # measured i_x = (1 + g_x) i_x: error g_x i_x along phase x's Clarke direction (A per unit gain)
    i_abc = smooth_current(sig)[1]
    return np.stack([ab_to_dq(CLARKE[:2, x:x + 1] * i_abc[x], sig.theta_e) for x in (1, 2)])


EFFECT = Effect(
    id="current_gain_mismatch",
    physics="A current sensor's gain differs from phase a's by g (dimensionless): i_x,meas = (1 + g_x) i_x "
            "for x = b, c (a common gain error is indistinguishable from the motor parameters).",
    kind="output",
    params=(Param("g_b", "-", "relative gain error of phase b", 0.03, -0.1, 0.1),
            Param("g_c", "-", "relative gain error of phase c", 0.03, -0.1, 0.1)),
    columns=columns,
    report=lambda v, ctx: {"gain_b": float(v[0]), "gain_c": float(v[1])},
    signature="2 fe ripple and a DC shift in dq; a negative-sequence fe line in the phase residual",
    dq_orders=(0, 2), abc_orders=(1,),
    reveals="any record with current",
)
