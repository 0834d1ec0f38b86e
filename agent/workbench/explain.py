"""Rank the library's effects by the share of a model's error each explains on held-out data, and
refit a model with chosen effects (``model explain`` / ``model add-effect``).

Fair comparison: every candidate is the *control* refit (the model's own structure, refitted on the
same fit segments: this alone absorbs a change of load or temperature) plus one effect; the share
it explains is ``1 - SSE(candidate) / SSE(control)`` on the held-out segments. Significance: a
one-sided t-test over ``BLOCK_S`` blocks of the held-out error (control minus candidate),
Bonferroni-corrected over the candidates, plus a practical floor ``MIN_EXPLAINED``. An effect
the records cannot pin down (:attr:`agent.workbench.fitting.Refit.identifiable`) is reported as not
identifiable from these records, with the data that would reveal it.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.stats

from agent.decision import operating_point_notes
from agent.effects import EFFECTS
from agent.effects import get as get_effect
from agent.errors import InputError
from agent.workbench.fitting import NONLINEAR, Prepared, heldout, refit

ALPHA = 0.01  #: family-wise significance level of the block test
MIN_EXPLAINED = 0.10  #: an effect must explain at least this share of the control's held-out error
CONTROL_NFEV = 100  #: iteration budget of the control refit (the candidates start from its result)


def start_values(model) -> dict:
    """Physical starting point (Rs_q, Lq_x) of the free run from a dq model, where plausible."""
    p = model.physical()
    guess = {"Rs_q": p["Rs_q"], "Lq_x": p["Lq_from_d"]}
    fallback = {"Rs_q": 1.0, "Lq_x": 0.01}
    return {k: v if np.isfinite(v) and 1e-4 < v < 1e3 else fallback[k] for k, v in guess.items()}


def context(ref, preps: list[Prepared], profile) -> dict:
    """What an effect's ``report`` needs: fitted base values, the rated current, the records' signals."""
    m = profile.motor
    i_rated = (m.rated_current_a * np.sqrt(2) if m.rated_current_a
               else m.rated_torque_nm / (1.5 * m.pole_pairs * max(ref.phys["psi_m"], 1e-3)))
    return {**ref.phys, "i_rated": float(i_rated), "ts": profile.ts,
            "t_mid": float(np.mean([0.5 * p.sig.n * p.sig.ts for p in preps])),
            "signals": [p.sig for p in preps]}


def operating_warnings(baseline, preps: list[Prepared]) -> list[str]:
    """One line per record whose operating point is far from the model's."""
    return [f"{p.source}: {n}" for p in preps for n in operating_point_notes(baseline.operating_point, p.op)]


def _fe(preps):
    return float(np.mean([p.op["fe_hz"] for p in preps]))


def _block_p(ctrl_blocks: np.ndarray, cand_blocks: np.ndarray) -> float:
    """One-sided p-value that the candidate lowers the held-out error (paired t-test over blocks)."""
    d = ctrl_blocks - cand_blocks
    if d.size < 3 or not np.any(d):
        return 1.0
    t = d.mean() / (d.std(ddof=1) / np.sqrt(d.size) + 1e-300)
    return float(scipy.stats.t.sf(t, d.size - 1))


def explain(baseline, preps: list[Prepared], candidates=None, progress=None) -> dict:
    """Rank ``candidates`` (default: every library effect the model lacks). Returns the CONTRACT
    document: ``nrmse_before`` (the model as it is), ``nrmse_control`` and ``candidates`` best first."""
    t0 = time.perf_counter()
    model = baseline.model
    have = tuple(model.meta.get("effects", []))
    candidates = [get_effect(e).id for e in (candidates or EFFECTS) if e not in have]
    before = heldout(model, preps)
    fe = _fe(preps)
    ctrl = refit(preps, model.form, fe, have, start_values(model), max_nfev=CONTROL_NFEV)
    start = {k: ctrl.phys[k] for k in NONLINEAR}
    fits = []
    for j, eid in enumerate(candidates):
        if progress:
            progress(j, len(candidates), f"refit with {eid}")
        fits.append(refit(preps, model.form, fe, have + (eid,), start))
    # No candidate may be credited for finding better base values: refit the control from the
    # best candidate's base values and keep the better control.
    best = min(fits, key=lambda r: r.cost, default=None)
    if best is not None and best.cost < ctrl.cost:
        again = refit(preps, model.form, fe, have, {k: best.phys[k] for k in NONLINEAR}, max_nfev=CONTROL_NFEV)
        ctrl = again if again.cost < ctrl.cost else ctrl
    h_ctrl = heldout(ctrl.model, preps)
    rows = []
    for eid, r in zip(candidates, fits):
        h = heldout(r.model, preps)
        identifiable, how = r.identifiable[eid]
        explained = 1.0 - float(np.sum(h["blocks"]) / max(np.sum(h_ctrl["blocks"]), 1e-300))
        p_value = _block_p(h_ctrl["blocks"], h["blocks"])
        eff = EFFECTS[eid]
        row = {"effect": eid, "nrmse_after": h["total"], "explained_fraction": explained,
               "significant": bool(identifiable and explained >= MIN_EXPLAINED
                                   and p_value < ALPHA / len(candidates)),
               "p_value": p_value, "identifiable": identifiable,
               "params": eff.report(r.values[eid], context(r, preps, baseline.profile)),
               "nrmse_after_dq": {"d": h["d"], "q": h["q"]}, "identifiability": how}
        if not identifiable:
            why = ("the one-step regression pins it to no better than +-{:.0%} of a typical size".format(
                how["relative_se"]) if how["stage"] == "one-step" else
                "a typical one would be absorbed into the base parameters")
            row["note"] = f"not identifiable from these records: {why}; revealed by {eff.reveals}"
        rows.append(row)
    rows.sort(key=lambda r: (r["significant"], r["explained_fraction"]), reverse=True)
    return {"nrmse_before": before["total"], "nrmse_control": h_ctrl["total"],
            "nrmse_before_dq": {"d": before["d"], "q": before["q"]}, "candidates": rows,
            "control_params": ctrl.phys, "records": [p.source for p in preps],
            "warnings": operating_warnings(baseline, preps), "seconds": time.perf_counter() - t0}


def add_effects(baseline, preps: list[Prepared], effect_ids) -> tuple[object, dict]:
    """Refit ``baseline.model`` with ``effect_ids`` added; returns (refit, figures). Figures:
    ``nrmse_before`` (the model as it is), ``nrmse_control`` (refit without the new effects) and
    ``nrmse_after``, all free-run on the held-out segments."""
    model = baseline.model
    have = tuple(model.meta.get("effects", []))
    new = tuple(get_effect(e).id for e in effect_ids)
    dup = [e for e in new if e in have]
    if dup:
        raise InputError(f"the model already has effect(s) {', '.join(dup)}")
    fe = _fe(preps)
    ctrl = refit(preps, model.form, fe, have, start_values(model))
    r = refit(preps, model.form, fe, have + new, {k: ctrl.phys[k] for k in NONLINEAR})
    ctx = context(r, preps, baseline.profile)
    figures = {"nrmse_before": heldout(model, preps)["total"], "nrmse_control": heldout(ctrl.model, preps)["total"],
               "nrmse_after": heldout(r.model, preps)["total"],
               "params": {e: get_effect(e).report(r.values[e], ctx) for e in have + new},
               "base": r.phys, "warnings": operating_warnings(baseline, preps)}
    r.model.meta["effect_params"] = figures["params"]
    return r, figures
