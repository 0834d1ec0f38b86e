"""Magnetic saturation of the d and q axes, self and cross, from one co-energy.

Family (x = current / I_REF): the co-energy's lowest nonlinear terms
W' = c I_REF i_d x_q^2 - lambda_q I_REF^2 x_q^4 / 4 + kappa_d I_REF^2 x_d^3 / 3 give the flux changes
  Delta psi_d = c i_q^2 / I_REF + kappa_d i_d^2 / I_REF      (cross, d self)
  Delta psi_q = 2 c i_d i_q / I_REF - lambda_q i_q^3 / I_REF^2  (cross, reciprocal; q self)
so that the cross terms are reciprocal (d psi_d / d i_q = d psi_q / d i_d). The model misses
d Delta psi/dt + j omega_e Delta psi (V), computed from the current's operating level.

Degrees of freedom: lambda_q (H, 0..0.5 L_q (I_REF/I_rated)^2, the q chord inductance dropping by up
to 50 % at rated current), c and kappa_d (H, +-0.1 psi_m I_REF / I_rated^2: the d flux changing by up
to 10 % of psi_m at rated current). Reported: lq_drop_at_rated = 1 - psi_q(0, I_rated) / (L_q I_rated)
(headline), the d-flux changes at rated current of the cross and the d self term (Wb), lambda_H.

What records pin: lambda_q needs several loads (at one it is L_q); a pure psi_d change (c at i_d = 0,
kappa_d) is a back-EMF change, which each record's own psi_m takes (the columns leave its level
within a record to it, so that the pair cannot carry psi_m beyond its range): c is pinned only where
i_d varies with the load (MTPA, field weakening: 2 c i_d i_q on d) or by a load step within a
record, and kappa_d only by records whose d current moves.
"""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current

I_REF = 10.0  #: A, current scale of the columns (keeps the parameters near 1e-3 H)


def columns(sig):
    i_d, i_q = smooth_current(sig)[0]
    w = sig.omega_e
    # flux changes (Wb) per H of lambda_q, c, kappa_d: (Delta psi_d, Delta psi_q)
    flux = np.stack((np.stack((0 * i_q, -i_q ** 3 / I_REF ** 2)),
                     np.stack((i_q ** 2 / I_REF, 2 * i_d * i_q / I_REF)),
                     np.stack((i_d ** 2 / I_REF, 0 * i_d))))
    # a d-flux change's level within a record is a back-EMF change the record's own psi_m takes (the
    # refit fits one per record, within its physical range): the columns keep what varies within it
    flux[1:, 0] -= flux[1:, 0].mean(axis=1, keepdims=True)
    rate = np.gradient(flux, sig.ts, axis=2) if sig.n > 1 else np.zeros_like(flux)
    # the effect's voltage is minus what the model misses: -(d psi_d/dt - w psi_q, d psi_q/dt + w psi_d)
    return -np.stack((rate[:, 0] - w * flux[:, 1], rate[:, 1] + w * flux[:, 0]), axis=1)


def report(v, ctx):
    lam, c, kappa = (float(x) for x in v)
    i_r = ctx["i_rated"]
    return {"lq_drop_at_rated": lam / ctx["Lq"] * (i_r / I_REF) ** 2,
            "cross_dpsi_d_at_rated_Wb": c * i_r ** 2 / I_REF, "d_self_dpsi_d_at_rated_Wb": kappa * i_r ** 2 / I_REF,
            "lambda_H": lam}


def _d_flux_bound(b):
    return b["psi_m"] * I_REF / b["i_rated"] ** 2


EFFECT = Effect(
    id="magnetic_saturation",
    physics="The iron saturates: psi_q = L_q i_q - lambda_q i_q^3 / I_REF^2 + 2 c i_d i_q / I_REF and "
            "psi_d = psi_m + L_d i_d + c i_q^2 / I_REF + kappa_d i_d^2 / I_REF (one co-energy, reciprocal "
            "cross terms, I_REF = 10 A); the chord inductance psi_q/i_q drops by the fraction s at rated "
            "current (dimensionless).",
    kind="voltage",
    params=(Param("lambda", "H", "lambda_q = L_q s (I_REF/I_rated)^2, the cubic q-flux coefficient", 5e-3,
                  0.0, 0.5, lambda b: b["Lq"] * (I_REF / b["i_rated"]) ** 2),
            Param("c_cross", "H", "cross-saturation coefficient c (d flux per i_q^2 / I_REF)", 1e-3,
                  -0.1, 0.1, _d_flux_bound),
            Param("kappa_d", "H", "d self-saturation coefficient (d flux per i_d^2 / I_REF)", 1e-3,
                  -0.1, 0.1, _d_flux_bound)),
    columns=columns, report=report,
    signature="d-axis residual that grows with the cube of the q current: visible across loads, "
              "absorbed into L_q at any single load; a d flux change with the load is a back-EMF change",
    reveals="records at several loads, at least three spanning 40 % of rated current or more (e.g. 50, 80, "
            "110 %); at one load it is absorbed into L_q; where i_d changes "
            "with the load (MTPA) also the winding resistance (nameplate.rs_ohm), which R_s i_d otherwise "
            "trades with it; the d-flux terms need records whose d current differs (MTPA, field weakening)",
)
