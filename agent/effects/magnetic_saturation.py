"""Magnetic saturation of the q axis, self and cross, from one co-energy.

Family (x = current / I_REF): the co-energy's lowest nonlinear terms
W' = c I_REF i_d x_q^2 - lambda_q I_REF^2 x_q^4 / 4 (+ kappa_d I_REF^2 x_d^3 / 3 for the d self term)
give reciprocal flux changes (d psi_d / d i_q = d psi_q / d i_d)
  Delta psi_q = 2 c i_d i_q / I_REF - lambda_q i_q^3 / I_REF^2   (cross; q self)
  Delta psi_d = c i_q^2 / I_REF (+ kappa_d i_d^2 / I_REF)          (cross; d self)
and the model misses d Delta psi/dt + j omega_e Delta psi (V), computed from the current's 2 Hz level.

A d-flux change is a back-EMF change, and the refit fits psi_m per record: at each record's load it
takes Delta psi_d whole. What is left of it within a record (the 2 Hz level's slow wander times
omega_e) acts on q like a resistance on that wander, and with the resistance held (a nameplate R_s)
it took the R_s mismatch instead (c went to its bound on the rig). So the columns carry the q-flux
change only: c through 2 c i_d i_q (pinned where i_d changes with the load: MTPA, field weakening),
lambda_q through its cube; kappa_d, a pure d-flux change, is left to psi_m and is not a parameter.

Degrees of freedom: lambda_q (H, 0..0.5 L_q (I_REF/I_rated)^2: the q chord inductance dropping by up
to 50 % at rated current), c (H, +-0.1 psi_m I_REF / I_rated^2: the d flux changing by up to 10 % of
psi_m at rated current). Reported: lq_drop_at_rated = 1 - psi_q(0, I_rated) / (L_q I_rated)
(headline), cross_dpsi_d_at_rated_Wb = c I_rated^2 / I_REF, lambda_H. The L_q there is the refit's
L_qx, the chord the d axis sees in omega_e L_q i_q, not its L_q: that is read sample to sample, the
incremental inductance d psi_q / d i_q at the records' currents, which saturation lowers more than
the chord (on a family drive 0.53 of the truth against L_qx's 1.02, and the drop read against it 2.3
times the truth).
"""

import numpy as np

from agent.effects.base import Effect, Param, smooth_current

I_REF = 10.0  #: A, current scale of the columns (keeps the parameters near 1e-3 H)


def columns(sig):
    i_d, i_q = smooth_current(sig)[0]
    w = sig.omega_e
    # q-flux changes (Wb) per H of lambda_q and c; the d-flux change is each record's psi_m's
    flux_q = np.stack((-i_q ** 3 / I_REF ** 2, 2 * i_d * i_q / I_REF))
    rate_q = np.gradient(flux_q, sig.ts, axis=1) if sig.n > 1 else np.zeros_like(flux_q)
    # the effect's voltage is minus what the model misses: d: -(0 - w psi_q), q: -(d psi_q/dt + 0)
    return np.stack((w * flux_q, -rate_q), axis=1)


def report(v, ctx):
    lam, c = (float(x) for x in v)
    i_r = ctx["i_rated"]
    # against psi_q / i_q at low current: L_q as the d axis takes it in omega_e L_q i_q
    return {"lq_drop_at_rated": lam / ctx["Lq_x"] * (i_r / I_REF) ** 2, "cross_dpsi_d_at_rated_Wb": c * i_r ** 2 / I_REF,
            "lambda_H": lam}


def _d_flux_bound(b):
    return b["psi_m"] * I_REF / b["i_rated"] ** 2


EFFECT = Effect(
    id="magnetic_saturation",
    physics="The iron saturates: psi_q = L_q i_q - lambda_q i_q^3 / I_REF^2 + 2 c i_d i_q / I_REF and "
            "psi_d = psi_m + L_d i_d + c i_q^2 / I_REF (one co-energy, reciprocal cross terms, I_REF = 10 A; "
            "the d-flux change is each record's psi_m's); the chord inductance psi_q/i_q drops by the fraction "
            "s at rated current (dimensionless).",
    kind="voltage",
    params=(Param("lambda", "H", "lambda_q = L_q s (I_REF/I_rated)^2, the cubic q-flux coefficient", 5e-3,
                  0.0, 0.5, lambda b: b["Lq"] * (I_REF / b["i_rated"]) ** 2),
            Param("c_cross", "H", "cross-saturation coefficient c (d flux per i_q^2 / I_REF)", 1e-3,
                  -0.1, 0.1, _d_flux_bound)),
    columns=columns, report=report,
    signature="d-axis residual that grows with the cube of the q current: visible across loads, "
              "absorbed into L_q at any single load; a d flux change with the load is a back-EMF change",
    reveals="records at several loads, at least three spanning 40 % of rated current or more (e.g. 50, 80, "
            "110 %); at one load it is absorbed into L_q; where i_d changes "
            "with the load (MTPA) also the winding resistance (nameplate.rs_ohm), which R_s i_d otherwise "
            "trades with it; the cross term needs records whose d current differs (MTPA, field weakening)",
)
