"""q-axis magnetic saturation: the q flux grows less than linearly with the current."""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current

I_REF = 10.0  #: A, current scale of the column (keeps the parameter near 1e-3 H)


def columns(sig):
    # psi_q = L_q i_q (1 - s (i_q/I_r)^2): the d voltage equation's omega_e psi_q misses
    # -omega_e L_q s i_q^3 / I_r^2 = -omega_e i_q^3/I_REF^2 * lam,  lam = L_q s (I_REF/I_r)^2 (H)
    iq = smooth_current(sig)[0][1]
    col = np.zeros((1, 2, sig.n))
    col[0, 0] = -sig.omega_e * iq**3 / I_REF**2
    return col


def report(v, ctx):
    drop = v[0] / ctx["Lq"] * (ctx["i_rated"] / I_REF) ** 2
    return {"lq_drop_at_rated": float(drop), "lambda_H": float(v[0])}


EFFECT = Effect(
    id="magnetic_saturation",
    physics="The q-axis flux saturates, psi_q = L_q i_q (1 - s (i_q/I_rated)^2): the chord inductance "
            "psi_q/i_q drops by the fraction s at rated current (dimensionless).",
    kind="voltage",
    params=(Param("lambda", "H", "L_q s (I_REF/I_rated)^2, the cubic flux coefficient", 5e-3,
                  0.0, 0.5, lambda b: b["Lq"] * (I_REF / b["i_rated"]) ** 2),),
    columns=columns, report=report,
    signature="d-axis residual that grows with the cube of the q current: visible across loads, "
              "absorbed into L_q at any single load",
    reveals="records at several loads, at least three spanning 40 % of rated current or more (e.g. 50, 80, "
            "110 %); at one load it is absorbed into L_q; where i_d changes "
            "with the load (MTPA) also the winding resistance (nameplate.rs_ohm), which R_s i_d otherwise "
            "trades with it",
)
