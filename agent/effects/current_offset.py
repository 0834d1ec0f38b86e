"""Current-sensor offsets: of the acquisition alone, or of the drive's own sensors that the records share.

Family: constant offsets o_a, o_b, o_c (A) on the measured phase currents; their common part has
no alpha-beta image (Clarke drops it), their differential part is a fixed alpha-beta vector
o = (o_alpha, o_beta), which the dq frame sees turning at -omega_e. Where only the acquisition
carries them, the residual is o itself. Where the records are the drive's own current measurement,
its controller holds the measured current at its reference, so the winding carries -o and the
offset shows only as the voltage R_s o that holds it (DC in the stator frame: no inductive drop):
the model, driven by that voltage, reads o R_s / R_s,q through its own R_s,q, which also takes the
voltage errors the model lacks and is pinned loosely (each record's psi_m takes R_s i_q's steady
state). On two family drives R_s,q was 2.5 and 3.7 times the winding's, and the offset came out at
0.41 and 0.22 of the truth; on one whose R_s,q was the winding's, at 0.99 (:func:`through_resistance`
says so with each claim).

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


def through_resistance(phys: dict, prior: dict) -> str | None:
    """Why offset_A rests on the refit's R_s,q (module docstring), and what would check it; None
    where the baseline's or the nameplate's R_s agrees with R_s,q (within twice its relative sd)."""
    rs = phys.get("Rs_q")
    if rs is None or not np.isfinite(rs) or rs <= 0:
        return None
    text = (f"offset_A is read through the refit's R_s,q ({rs:.3g} ohm) where the records are the drive's own "
            "current measurement: its controller holds that current at the reference, so the offset o shows only "
            "as the voltage R_s o that holds -o in the winding, and offset_A = o R_s / R_s,q, while R_s,q also takes "
            "the voltage errors the model lacks")
    if "Rs" in prior:
        p, rel = prior["Rs"]
        if abs(np.log(rs / p)) <= 2.0 * rel:
            return None
        text += f"; the baseline's R_s is {p:.3g} ohm, so the offset may be {rs / p:.2g} times the figure"
    else:
        text += "; give the nameplate R_s (nameplate.rs_ohm) to check R_s,q"
    return text + ", or record with the inverter's pulses off, which shows the offsets directly"


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
    read_through=through_resistance,
)
