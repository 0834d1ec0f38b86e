"""Current-sensor offsets: of the acquisition alone, or of the drive's own sensors that the records share.

Family: constant offsets o_a, o_b, o_c (A) on the measured phase currents; their common part has
no alpha-beta image (Clarke drops it), their differential part is a fixed alpha-beta vector
o = (o_alpha, o_beta), which the dq frame sees turning at -omega_e. Where only the acquisition
carries them, the residual is o itself: the records' current has a stator-frame DC. Where the
drive's controller acts on the same sensors, it holds the measured current at its reference, so
the winding carries -o, the records' current has no stator-frame DC, and the offset shows only as
the voltage R_s o that holds -o (DC in the stator frame: no inductive drop). The model, driven by
that voltage, reads o R_s / R_s,q through its own R_s,q, which also takes the voltage errors the
model lacks and is pinned loosely (each record's psi_m takes R_s i_q's steady state): on the drive
family R_s,q was up to 4 times the winding's, and the offset came out at 0.22-1.0 of the truth,
R_s / R_s,q each time. What such records pin is the voltage, R_s,q |o|; o itself needs the
winding's R_s (:func:`through_resistance`).

Degrees of freedom: o_alpha, o_beta (A, each within 5 % of the rated peak current: a sensor class).
Reported: offset_A = |o| (headline) and the per-phase offsets ia_A, ib_A, ic_A (zero-sum part); where
the controller acts on the sensors, offset_voltage_V = R_s,q |o| (V) first, and offset_A through the
baseline's R_s, or not at all.
"""

import numpy as np

from agent.effects.base import Effect, Param, amplitude, mid_angle, smooth

_S3 = np.sqrt(3.0) / 2.0


def columns(sig):
    c, s = np.cos(sig.theta_e), np.sin(sig.theta_e)
    return np.stack((np.stack((c, -s)), np.stack((s, c))))  # Park of a fixed alpha / beta vector (A per A)


def report(v, ctx):
    a, b = v
    return {"offset_A": amplitude(v), "ia_A": float(a), "ib_A": float(-0.5 * a + _S3 * b),
            "ic_A": float(-0.5 * a - _S3 * b)}


DIRECT = 0.5  #: the current's own stator-frame DC at least this share of the fitted offset: the offset is read directly


def stator_dc(signals, voltage: bool = False) -> complex:
    """The records' stator-frame DC (alpha + j beta) of the measured current (A) or, with ``voltage``,
    of the voltage (V): its dq component turning at -omega_e, e^{-j theta} (least squares on the
    quantity less its slow part, ``agent.effects.base.SMOOTH_HZ``; the voltage at the interval's
    mid angle, where it acts)."""
    num = den = 0.0
    for sig in signals:
        x, theta = (sig.v_dq, mid_angle(sig)) if voltage else (sig.i_dq, sig.theta_e)
        slow = smooth(x, sig.ts)
        num = num + np.sum(((x[0] - slow[0]) + 1j * (x[1] - slow[1])) * np.exp(1j * theta))
        den += sig.n
    return complex(num / max(den, 1))


AGREE = 0.5  #: the fit's and the records' readings of the holding voltage within this share of the larger: pinned


def through_resistance(values, said: dict, ctx: dict, prior: dict) -> dict | None:
    """Where the offset is not in the current the records carry (its stator-frame DC below
    ``DIRECT`` of the fit's, :func:`stator_dc`), the drive's controller acts on the same sensors:
    it holds the measured current at its reference, the winding carries -o and only the voltage
    R_s o that holds it shows, which the model reads as o R_s / R_s,q through its own R_s,q (module
    docstring). The records then pin that voltage, not o: ``offset_voltage_V`` = R_s,q |o| (V), its
    bound widened to the records' own stator-frame DC voltage, and not given where the two differ
    by more than ``AGREE`` of the larger (the voltage holds more than the offset, or the model reads
    it through more than R_s). offset_A and the per-phase figures are given through the baseline's
    or the nameplate's R_s (``prior["Rs"]``, their bound widened by twice its relative sd), or not at
    all. ``said``: the figures and bounds as fitted (``params``, ``params_bound``). Returns them so
    read, with a ``note`` (and ``unpinned_params`` where not given), or None where the offset is read
    directly."""
    o = complex(values[0], values[1])
    rs = ctx.get("Rs_q")
    if abs(o) == 0.0 or rs is None or not np.isfinite(rs) or rs <= 0:
        return None
    seen = stator_dc(ctx["signals"])
    if abs(seen) >= DIRECT * abs(o):
        return None
    figures, bounds = said["params"], said["params_bound"]
    volt, v_dc = rs * abs(o), abs(stator_dc(ctx["signals"], voltage=True))
    volt_bound = max(abs(volt - v_dc), rs * (bounds.get("offset_A") or 0.0))
    agree = abs(volt - v_dc) <= AGREE * max(volt, v_dc)
    note = (f"the records' current carries no offset of its own (its stator-frame DC is {abs(seen):.2g} A against "
            f"the fit's {abs(o):.2g} A): the drive's controller acts on these sensors, holds the measured current at "
            f"its reference, and the offset shows only as the voltage R_s o that holds -o in the winding, which the "
            f"model reads as {volt:.3g} V (offset_voltage_V) through its R_s,q of {rs:.3g} ohm, which also takes the "
            f"voltage errors the model lacks; the records' stator-frame DC voltage is {v_dc:.3g} V")
    unpinned = {"offset_voltage_V": volt, **figures}
    if not agree:
        return {"params": dict.fromkeys(unpinned), "params_bound": dict.fromkeys(unpinned),
                "unpinned_params": unpinned,
                "note": note + "; the two differ by more than half, so neither the voltage nor the offset is "
                               "given: record with the inverter's pulses off, which shows the offsets directly"}
    if "Rs" in prior:
        r_s, rel = prior["Rs"]
        scale = rs / r_s
        return {"params": {**{k: v * scale for k, v in figures.items()}, "offset_voltage_V": volt},
                "params_bound": {**{k: max(2.0 * rel * abs(v * scale), (bounds.get(k) or 0.0) * scale)
                                    for k, v in figures.items()}, "offset_voltage_V": volt_bound},
                "note": note + f"; offset_A is read through the baseline's R_s ({r_s:.3g} ohm, +-{rel:.0%})"}
    return {"params": {"offset_voltage_V": volt, **dict.fromkeys(figures)},
            "params_bound": {"offset_voltage_V": volt_bound, **dict.fromkeys(figures)},
            "unpinned_params": figures,
            "note": note + "; offset_A is not pinned without the winding's R_s: give the nameplate R_s "
                           "(nameplate.rs_ohm), record a load step (which pins R_s), or record with the inverter's "
                           "pulses off, which shows the offsets directly"}


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
