"""Whether records carry the dynamics that a refit of the dq model needs.

The workbench reads L_d and L_q from the current's sample-to-sample response to the voltage
(:func:`agent.workbench.fitting.one_step`). At one load with constant references a drive's
voltage varies only by the channel's noise and the current loop's small corrections: the records
then pin neither inductance, every effect's refit trades with them, and a ranking would be a
list of accidents. Where the baseline's physical estimate (identify, with a nameplate) holds the
inductance, the refits take it from there instead (:func:`agent.workbench.fitting.with_prior`).
"""

from __future__ import annotations

import numpy as np

from agent.physical import IDENTIFIABLE_REL
from agent.workbench.fitting import Prepared, one_step

SPREAD_MIN = 3.0  #: records whose voltage varies less than this many times its channel's noise carry almost no dynamics


def dynamics(preps: list[Prepared], prior: dict) -> dict:
    """What the records' fit segments say about the inductances.

    Returns ``voltage_spread_v`` (rms of the dq voltage about each record's mean, V),
    ``voltage_noise_v`` (the voltage channel's white noise per dq axis, sqrt(2/3) sigma, V),
    ``inductance_rel_se`` (the one-step regression's relative standard errors of L_d, L_q) and
    ``unpinned``: those of L_d, L_q that neither the records (relative sd above
    ``IDENTIFIABLE_REL``) nor ``prior`` (:func:`agent.workbench.explain.physical_prior`) carry, and
    ``quiet``: whether that is for want of excitation (the voltage varies less than ``SPREAD_MIN``
    times its noise). A voltage that varies while the current does not follow it as the model
    expects (a voltage path the model lacks) leaves inductances unpinned too, but that is an
    effect to rank, not a lack of data."""
    step = one_step(preps)
    spread = np.sqrt(np.mean([np.mean(np.var(p.sig.v_dq[:, p.fit_slice], axis=1)) for p in preps]))
    noise = np.sqrt(np.mean([p.noise_var[0] for p in preps]))
    rel = {k: float(step.rel_se[k]) for k in ("Ld", "Lq")}
    unpinned = [k for k, v in rel.items() if not (v <= IDENTIFIABLE_REL) and k not in prior]
    return {"voltage_spread_v": float(spread), "voltage_noise_v": float(noise), "inductance_rel_se": rel,
            "unpinned": unpinned, "quiet": bool(unpinned) and bool(spread < SPREAD_MIN * noise)}


#: what reveals each inductance, and the nameplate key that gives it instead
REVEALED_BY = {"Lq": ("a load or speed step", "nameplate.lq_h"),
               "Ld": ("a change of the d current (MTPA across loads, field weakening)", "nameplate.ld_h")}


def no_dynamics_note(dyn: dict) -> str:
    """The answer to records that carry no dynamics, with the figures and the records that would."""
    keys = [k for k in REVEALED_BY if k in dyn["unpinned"]]
    return (f"these records carry almost no dynamics (voltage spread {dyn['voltage_spread_v']:.3g} V against noise "
            f"{dyn['voltage_noise_v']:.3g} V): record {' and '.join(REVEALED_BY[k][0] for k in keys)}, or give the "
            f"nameplate ({', '.join(REVEALED_BY[k][1] for k in keys)})")


def unfollowed_note(dyn: dict, voltage_source: str) -> str:
    """Why the records pin no inductance although their voltage varies (spread at least ``SPREAD_MIN``
    times its noise): the current does not follow that voltage as a winding would. Empty where the
    voltage is quiet (:func:`no_dynamics_note` answers then) or the inductances are pinned."""
    if not dyn["unpinned"] or dyn["voltage_spread_v"] < SPREAD_MIN * dyn["voltage_noise_v"]:
        return ""
    key = max(dyn["unpinned"], key=lambda k: dyn["inductance_rel_se"][k])
    cause = ("a measured voltage that is not the mean the winding integrates over each sample (switching pulses "
             "taken at an instant, a filter the profile does not state): a voltage channel averaged over each "
             "sampling interval, or the drive's voltage command (sampling.voltage_source = \"reference\"), would "
             "carry it" if voltage_source == "measured" else
             "a voltage path the model lacks (state it: sampling.voltage_delay_samples, voltage_advance_samples)")
    return (f"the voltage varies ({dyn['voltage_spread_v']:.3g} V against noise {dyn['voltage_noise_v']:.3g} V) but the "
            f"current does not follow it as a winding would ({key[0]}_{key[1]}'s one-step relative sd "
            f"{dyn['inductance_rel_se'][key]:.0%}); the likely cause: {cause}")
