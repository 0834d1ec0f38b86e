"""Rank the library's effects by the share of a model's error each explains on held-out data, and
refit a model with chosen effects (``model explain`` / ``model add-effect``).

Fair comparison: every candidate is the *control* (the model's own structure refitted on the same
fit segments, or the model itself where the refit is not better: this alone absorbs a change of
load or temperature) plus one effect, and never worse than the control on the fit segments (a
candidate refit that is, is the control with the effect at zero). The share it explains is
``(SSE(control) - SSE(candidate) - their noise floors' difference) / SSE(control)`` on the held-out
segments (the one error figure, :func:`agent.workbench.fitting.heldout`): a model is not credited
for responding less to the voltage channel's noise.

Significance (docs/workbench.md, "Claims"): the held-out error of one record is dominated by slow
components (a magnet-temperature or resistance mismatch is a constant over the record), so its
``BLOCK_S`` blocks are not independent samples; the records are. The test is a one-sided t-test of
the per-block share explained (as above, per block), whose sample size is the *effective* one, from the
blocks' autocorrelation within records (:func:`effective_size`), never more than the blocks and
never less than the records; Holm's step-down correction over the candidates keeps the
family-wise level ``ALPHA``; a practical floor ``MIN_EXPLAINED`` applies. An effect the records
cannot pin down (:attr:`agent.workbench.fitting.Refit.identifiable`) or whose fitted parameter sits
on its physical bound is never significant; the row says which, and which records would reveal it.
One that explains enough but misses the level says how many records like these would settle it
(:func:`records_needed`). An effect the records read directly (the sensors' gains off the phase
currents' sum) is tested on that reading where its refit's share clears zero (:func:`test_p`).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.optimize
import scipy.stats

from agent.decision import operating_point_notes
from agent.effects import EFFECTS
from agent.effects import get as get_effect
from agent.effects.voltage_delay import MOVES, REACH, move_toward
from agent.errors import InputError
from agent.evidence import effective_size
from agent.workbench.excitation import dynamics, no_dynamics_note, unfollowed_note
from agent.workbench.fitting import (CONFLICT_SD, L_MAX_H, NONLINEAR, UNSEEN, Prepared, Refit, fit_cost, heldout,
                                     frame_lowpass, hold_offset, hold_period, judge_figures, moved_path, one_step,
                                     onto_controller, onto_rotor, refit, with_prior)

ALPHA = 0.01  #: family-wise significance level of the test over records
MIN_RECORDS = 3  #: records needed for the test
MIN_EXPLAINED = 0.10  #: an effect must explain at least this share of the control's held-out error
CONTROL_NFEV = 100  #: iteration budget of the control refit (the candidates start from its result)
#: the refits' form: the speed form's rotation terms follow the recorded speed sample by sample (the
#: lumped form holds them at the operating point's, which a speed step of 15 % turns into a 4 % NRMSE)
REFIT_FORM = "speed"


def start_values(model) -> dict:
    """Physical starting point (Rs_q, Lq_x) of the free run from a dq model, where plausible."""
    p = model.physical()
    guess = {"Rs_q": p["Rs_q"], "Lq_x": p["Lq_from_d"]}
    fallback = {"Rs_q": 1.0, "Lq_x": 0.01}
    return {k: v if np.isfinite(v) and 1e-4 < v < 1e3 else fallback[k] for k, v in guess.items()}


def rated_current(motor, psi_m: float) -> float:
    """Rated current, A peak: the nameplate's, else the rated torque's at ``psi_m`` (Wb, i_d = 0)."""
    return motor.i_rated_peak or motor.rated_torque_nm / (1.5 * motor.pole_pairs * max(psi_m, 1e-3))


def context(ref, preps: list[Prepared], profile) -> dict:
    """What an effect's ``report`` needs: fitted base values, the rated current, the records' signals,
    the voltage path applied to them (:func:`agent.workbench.fitting.prepare`; voltage_delay reports totals)."""
    return {**ref.phys, "voltage_path": preps[0].meta.get("voltage_path") if preps else None,
            "i_rated": float(rated_current(profile.motor, ref.phys["psi_m"])), "ts": profile.ts,
            "t_mid": float(np.mean([0.5 * p.sig.n * p.sig.ts for p in preps])),
            "signals": [p.sig for p in preps]}


def operating_warnings(baseline, preps: list[Prepared]) -> list[str]:
    """One line per record whose operating point is far from the model's."""
    return [f"{p.source}: {n}" for p in preps for n in operating_point_notes(baseline.operating_point, p.op)]


def _fe(preps):
    return float(np.mean([p.op["fe_hz"] for p in preps]))


def drive_base(baseline) -> dict:
    """The drive's base values that effect parameters are bounded by
    (:meth:`agent.effects.base.Param.bounds`): rated current and phase voltage (peak), and R_s,
    L_q and psi_m from the baseline's physical estimate, else from its model, where physical."""
    m = baseline.profile.motor
    model_phys = baseline.model.physical()
    est = (baseline.physical or {}).get("values") or {}
    base = {"Rs_q": est.get("Rs") or model_phys["Rs_q"], "Lq": est.get("Lq") or model_phys["Lq"],
            "psi_m": est.get("psi_m") or model_phys["psi_m"]}
    base = {k: float(v) for k, v in base.items() if v is not None and np.isfinite(v) and v > 0}
    if m.i_rated_peak or "psi_m" in base:
        base["i_rated"] = rated_current(m, base.get("psi_m", 0.0))
    if m.rated_voltage_v:
        base["v_rated"] = m.rated_voltage_v * np.sqrt(2.0 / 3.0)
    return base


PRIOR_FLOOR = {"Ld": 0.05, "Lq": 0.05, "Rs": 0.2, "psi_m": 0.02}  #: relative sd at least: load, temperature move them


def physical_prior(baseline) -> dict:
    """{"Ld"|"Lq"|"Rs"|"psi_m": (value, relative sd)} from the baseline's physical estimate (identify, with
    the nameplate where the profile has one), for the refits' base values; identified values only.
    ``"instrumented"``: the inductances identify read by the instrumented regression (the drive's
    voltage answers the current's noise within the sample), which the refits' one-step reads so too."""
    est = baseline.physical or {}
    out = {}
    for key, floor in PRIOR_FLOOR.items():
        v, rel = (est.get("values") or {}).get(key), (est.get("rel_sd") or {}).get(key)
        if v is not None and rel is not None and np.isfinite(v) and v > 0 and np.isfinite(rel):
            out[key] = (float(v), max(float(rel), floor))
    if est.get("instrumented"):
        out["instrumented"] = tuple(est["instrumented"])
    return out


def rotor_frames(preps: list[Prepared], profile, prior: dict) -> list[Prepared]:
    """Records in the current vector's frame (no encoder) onto the rotor's, by the baseline's
    inductances: under MTPA by their active flux (:func:`agent.workbench.fitting.onto_rotor`; only
    where the profile says the current leads the rotor's q axis: a hidden effect that moves L_q with
    the load, saturation, reads as a current angle, and the rig's i_d = 0 records turned by up to 10
    degrees), else onto the frame in which the controller's own samples lie on q, where the records'
    current averages over the drive's hold (:func:`agent.workbench.fitting.onto_controller`)."""
    if all(p.encoder for p in preps) or "Lq" not in prior:
        return preps
    if profile.sampling.current_reference == "mtpa":
        return onto_rotor(preps, prior["Lq"][0], prior.get("Rs", (0.0,))[0])
    t_hold = hold_period(profile.sampling)
    if t_hold is None:
        return preps
    return onto_controller(preps, t_hold, hold_ld(preps, prior), prior["Lq"][0])


HOLD_LD_PRECISION = 0.3  #: the records' one-step L_d turns a frame onto the controller's where known to this share


def hold_ld(preps: list[Prepared], prior: dict) -> float:
    """H: the L_d that :func:`agent.workbench.fitting.hold_offset` reads the d offset through. Under
    i_d = 0 the baseline rarely pins it (its steady state has no d current), so the records' one-step
    reading with the baseline's where that is known to ``HOLD_LD_PRECISION`` (the d axis's response to
    the current loop's voltage), else the baseline's, else its L_q: L_d <= L_q, the smallest offset
    (constant references leave the d axis no dynamics to read: family drive 20649 read 10 H)."""
    step = one_step(preps)
    if np.isfinite(step.ld) and 0 < step.ld < L_MAX_H and step.rel_se.get("Ld", np.inf) <= HOLD_LD_PRECISION:
        return with_prior(step, prior)[0]
    return prior.get("Ld", prior["Lq"])[0]


def frame_warnings(profile, preps: list[Prepared], prior: dict) -> list[str]:
    """What explain says of records without an encoder angle: their frame is the current vector's,
    the rotor's only under i_d = 0 (:func:`agent.workbench.fitting.onto_rotor`)."""
    if all(p.encoder for p in preps):
        return []
    ref = profile.sampling.current_reference
    if ref is None:
        return ["records without an encoder angle are judged in the current vector's frame, the rotor's only "
                "under i_d = 0: a drive under MTPA states sampling.current_reference = \"mtpa\" in its profile, "
                "and explain turns its records onto the rotor's frame"]
    if ref == "mtpa" and "Lq" not in prior:
        return ["records without an encoder angle stay in the current vector's frame, which under MTPA leads the "
                "rotor's: turning them needs L_q, which identify did not pin (give nameplate.lq_h)"]
    s = profile.sampling
    if ref == "mtpa" or s.current_source != "independent" or s.voltage_hold != "abc":
        return []
    if hold_period(s) is not None:
        return [] if "Lq" in prior else [
            "records without an encoder angle stay in the current vector's frame, which leads or trails the rotor's "
            "by the drive's hold (the DAQ's current averages over it, the controller holds its own samples on q): "
            "turning them needs L_q, which identify did not pin (give nameplate.lq_h)"]
    if s.control_rate_hz:  # stated equal to the record's: a DAQ the drive triggers, at its own instants
        return []
    size = ""
    if "Lq" in prior:  # at an update rate equal to the record's, through L_q (L_d <= L_q: at least this)
        lq = prior["Lq"][0]
        turns = []
        for p in preps:
            if not p.encoder:
                i = frame_lowpass(p.sig.i_dq[0] + 1j * p.sig.i_dq[1], p.sig)
                off = hold_offset(p.sig, p.sig.ts, lq, lq)
                turns.append((float(np.mean(np.abs(off / np.maximum(np.abs(i), 1e-12)))),
                              p.sig.ts * float(np.mean(np.abs(p.sig.omega_e)))))
        turn, w_ts = max(turns)
        size = (f" (about {turn:.2g} rad, {turn / w_ts:.2g} samples of omega_e T_s, were the drive to update at the "
                f"record's rate; it grows with the square of its update period)")
    return ["records without an encoder angle from an independent DAQ are judged in the frame of its current vector, "
            "which averages over the drive's voltage hold, while the controller holds its own samples on q: that frame "
            f"leads or trails the rotor's{size}, and the voltage path's rotation may take it; state the drive's update "
            "rate (sampling.control_rate_hz) or give records with an encoder angle"]


def _as_refit(model, preps: list[Prepared]) -> Refit:
    """The model itself as a contender for the control: its own parameters, its fit-segment cost."""
    have = tuple(model.meta.get("effects", []))
    p = model.physical()
    phys = {"Rs_d": p["Rs_d"], "Rs_q": p["Rs_q"], "Ld": p["Ld"], "Lq": p["Lq"], "Lq_x": p["Lq_from_d"],
            "psi_m": p["psi_m"]}
    values = {e: get_effect(e).values_from_model(model) for e in have}
    return Refit(have, model, phys, values, fit_cost(model, preps), {e: (True, {"stage": "model"}) for e in have},
                 {e: False for e in have})


def _zero_effect(ctrl: Refit, eid: str, bound: bool = False) -> Refit:
    """``ctrl`` with effect ``eid`` added at zero: the same model, the floor of any candidate
    (``bound``: the refit it replaces held the effect at a physical bound)."""
    m = ctrl.model
    extra_d, extra_q = get_effect(eid).terms()
    n = len(get_effect(eid).params)
    model = type(m)(m.form, m.ts, np.concatenate((m.theta_d, np.zeros(n))), np.concatenate((m.theta_q, np.zeros(n))),
                    m.extra_d + extra_d, m.extra_q + extra_q, fe_hz=m.fe_hz, meta=dict(m.meta),
                    discretisation=m.discretisation)
    model.meta["effects"] = list(ctrl.effects) + [eid]
    return Refit(ctrl.effects + (eid,), model, dict(ctrl.phys), {**ctrl.values, eid: np.zeros(n)}, ctrl.cost,
                 {**ctrl.identifiable, eid: (False, {"stage": "no gain on the fit segments"})},
                 {**ctrl.at_bound, eid: bound})


def control(model, preps: list[Prepared], base: dict, max_nfev: int = CONTROL_NFEV, start: dict | None = None,
            prior: dict | None = None) -> Refit:
    """The better (lower fit-segment cost) of the model itself and its refit: never worse than it."""
    have = tuple(model.meta.get("effects", []))
    r = refit(preps, REFIT_FORM, _fe(preps), have, start or start_values(model), max_nfev=max_nfev, base=base,
              prior=prior)
    own = _as_refit(model, preps)
    return r if r.cost <= own.cost else own


def nested(ctrl: Refit, preps: list[Prepared], new: tuple, base: dict, prior: dict | None = None) -> Refit:
    """``ctrl`` refitted with the effects ``new`` added, from its base values; never worse than
    ``ctrl`` on the fit segments (else ``ctrl`` with the effects at zero). Where the one-step
    regression's reading of the new effects (:func:`refit` pins them by it where it is precise)
    leaves the free run worse than ``ctrl``, they are fitted again by the free run alone: on a family
    drive averaging its current over the interval with a hidden 5th harmonic of the magnet, the
    harmonics pinned by the one-step left the fit no better than the control (fit-segment cost 62.5:
    "no gain"); fitted by the free run, 0.076, the 5th within 15 %."""
    r = refit(preps, REFIT_FORM, _fe(preps), ctrl.effects + new, {k: ctrl.phys[k] for k in NONLINEAR}, base=base,
              prior=prior)
    if r.cost <= ctrl.cost:
        return r
    how = [r.identifiable[e][1] for e in new]
    if any(h.get("stage") == "one-step" or "one_step_pinned" in h for h in how):  # else the same fit again
        r = refit(preps, REFIT_FORM, _fe(preps), ctrl.effects + new, {k: ctrl.phys[k] for k in NONLINEAR}, base=base,
                  prior=prior, free=new)
        if r.cost <= ctrl.cost:
            return r
    out = ctrl
    for eid in new:
        out = _zero_effect(out, eid, r.at_bound.get(eid, False))
    return out


def keeps_inductances(moved: Refit, r: Refit, prior: dict) -> bool:
    """Whether a moved voltage path's refit keeps the base the unmoved one had: the current still
    responds to the voltage on each axis (the one-step regression below ``L_MAX_H``), and an
    inductance that agreed with the baseline's (within ``CONFLICT_SD`` of its relative sd) still
    does. A move that needs another base is not a path: on a no-encoder family drive a move
    lowered the fit cost with L_d at 10 H and raised the held-out error 8-fold; on a null drive
    whose baseline L_q the control kept, a move took it 40 % lower and was claimed."""
    for k in ("Ld", "Lq"):
        if moved.phys[k] >= L_MAX_H > r.phys[k]:
            return False
        if k in prior:
            value, rel = prior[k]
            far = [abs(np.log(x.phys[k] / value)) > CONFLICT_SD * rel for x in (moved, r)]
            if far[0] and not far[1]:
                return False
    return True


def moved_delay(ctrl: Refit, preps: list[Prepared], r: Refit, base: dict, prior: dict | None = None
                ) -> tuple[Refit, list[Prepared]]:
    """voltage_delay's refit ``r`` where its rotation is more than half a sample off the stated path
    (or its columns sit at their reach): refitted with the path moved by whole samples that way
    (:func:`moved_path`, within ``MOVES``) while each move lowers the fit segments' cost, its fit's
    whole delay change (the move and the columns') stays beyond ``REACH`` that way (else the
    columns alone hold it, and the gain is another base's: a null family drive whose control sat at
    R_s 2000 ohm went back to its stated path, -1 + 0.92 samples, with a base 100 times nearer) and
    it keeps the inductances (:func:`keeps_inductances`). No move is tried where the unmoved columns
    explain nothing (``r`` no better than ``ctrl``): a path further off still projects onto them,
    and on the drive family such moves, tried in 183 sets, were kept in 23; two were claims of the
    delay for a hidden flux harmonic and a saturation, one a true delay's. Returns the best refit
    and the records it was fitted on (``preps`` where no move helped)."""
    if r.cost >= ctrl.cost:  # the columns explain nothing: no sign of a path off the stated one
        return r, preps
    step = move_toward(r.values["voltage_delay"])
    best, best_preps = r, preps
    for direction in ([step] if step else [1, -1] if r.at_bound.get("voltage_delay") else []):
        n = 0
        while MOVES[0] <= n + direction <= MOVES[1]:
            n += direction
            moved = moved_path(preps, n)
            m = nested(ctrl, moved, ("voltage_delay",), base, prior)
            lag, lead, _ = path_change(m.values["voltage_delay"], preps, moved)
            if m.cost >= best.cost or direction * (lag - lead) <= REACH or not keeps_inductances(m, r, prior or {}):
                break
            best, best_preps = m, moved
            if move_toward(m.values["voltage_delay"]) != direction:
                break
        if best is not r:
            break
    return best, best_preps


def path_change(values, preps: list[Prepared], moved: list[Prepared]) -> np.ndarray:
    """A moved voltage_delay fit's ``values`` (d_lag, d_lead, advance) as the unmoved columns would
    hold its whole change from the stated path: the move's samples plus the columns' delay."""
    n = moved[0].meta["voltage_path"][0] - (preps[0].meta.get("voltage_path") or (0.0, 0.0))[0]
    change = n + float(values[0] - values[1])
    return np.array([max(change, 0.0), max(-change, 0.0), float(values[2])])


def negligible_as_pinned(eid: str, values, said: dict, ctx: dict) -> bool:
    """Whether the figures the records pin of effect ``eid`` (``said``: the row's ``params``, None
    where not pinned) are given as well by parameters within the physical range whose every floored
    one is below its negligible floor (:meth:`Effect.negligible`): what the records show of the fit is
    then no finding, however the fit split the rest. Where only a combination is pinned the split
    measures nothing: a voltage path fitted as a 0.6-sample lead and a 0.6-sample advance that
    cancel, where at one speed only their sum, the rotation, is seen and it did not change (family
    drive 20030, hidden flux harmonics). The figures' response is taken as linear (exact for the
    voltage path's totals); a feasibility LP. False for an effect without floors."""
    eff = get_effect(eid)
    values = np.asarray(values, float)
    floors = np.array([p.negligible for p in eff.params])
    keys = [k for k, v in said.items() if v is not None]
    if not np.any(floors > 0):
        return False
    if not keys:  # its response is pinned, no figure of it is: its parameters as fitted
        return eff.negligible(values)
    at = eff.report(np.zeros_like(values), ctx)
    jac = np.array([[eff.report(e, ctx)[k] - at[k] for e in np.eye(len(values))] for k in keys])
    if not (np.all(np.isfinite(jac)) and np.all(np.isfinite(values))):  # a diverged fit shows no size
        return False
    box = []  # the physical range, each floored parameter strictly within its floor
    for p, f in zip(eff.params, floors):
        lo, hi = p.bounds(ctx)
        if f > 0:
            lo, hi = max(lo, -f), min(hi, f)
            hi -= 1e-9 * (hi - lo)
        box.append((lo if np.isfinite(lo) else None, hi if np.isfinite(hi) else None))
    res = scipy.optimize.linprog(np.zeros(len(values)), A_eq=jac, b_eq=jac @ values, bounds=box, method="highs")
    return bool(res.status == 0)


def reported(eid: str, r: Refit, ctx: dict, prior: dict | None = None) -> dict:
    """Effect ``eid``'s parameters as refit ``r`` reports them: ``params``, each figure where the
    records pin it down and None where they cannot (as identify reports base values), and then
    ``unpinned_params``, the values the fit landed on for those, which measure nothing;
    ``params_bound``, how far each figure given may be from what the records show
    (:func:`agent.workbench.fitting.judge_figures`: the channels' noise and the model error the refit
    leaves), None where nothing bounds it. An identifiable effect whose records pin only some of its figures (a combination of its
    parameters) gets a ``note`` naming the others and the records that would separate them. Where
    the effect's size is read through a base value the records pin loosely
    (:attr:`agent.effects.base.Effect.read_through`, ``prior``: the baseline's), its figures are
    what that reading gives, and the note says why."""
    eff = get_effect(eid)
    values = eff.report(r.values[eid], ctx)
    if not r.identifiable[eid][0]:
        return _direct(eff, ctx, {"params": dict.fromkeys(values), "unpinned_params": values})
    judged = judge_figures(eff, r.values[eid], r.info.get(eid), ctx)
    pinned = {k: p for k, (p, _) in judged.items()}
    loose = [k for k in values if not pinned[k]]
    bounds = {k: None if k in loose else judged[k][1] for k in values}
    if not loose:
        said = {"params": values, "params_bound": bounds}
        return eff.read_through(r.values[eid], said, ctx, prior or {}) or said
    return _direct(eff, ctx, {
        "params": {k: None if k in loose else v for k, v in values.items()}, "params_bound": bounds,
        "unpinned_params": {k: values[k] for k in loose},
        "note": f"{', '.join(loose)} not separable from these records ("
                + (f"reported: {', '.join(k for k in values if pinned[k])}" if len(loose) < len(values) else
                   "its response is pinned, no figure of it is") + f"); revealed by {eff.reveals}"})


def _direct(eff, ctx: dict, said: dict) -> dict:
    """``said`` (a fit that leaves figures unpinned), with the records' own reading of them where
    they carry one (:attr:`agent.effects.base.Effect.direct`)."""
    read = eff.direct(ctx["signals"])
    if read is None:
        return said
    return {**said, "params": read["params"], "params_bound": read["params_bound"],
            "note": "; ".join(filter(None, [said.get("note"), f"{', '.join(read['params'])} {read['note']}"]))}


def params_floor(eid: str) -> str:
    """The sizes below which effect ``eid``'s parameters are no finding, as text."""
    return ", ".join(f"|{p.name}| < {p.negligible:g} {p.unit}" for p in get_effect(eid).params if p.negligible > 0)


def unidentified_note(eid: str, how: dict) -> str:
    """Why the records cannot pin effect ``eid`` down (``how``: :attr:`Refit.identifiable`'s
    judgement), and which records would."""
    if how["stage"] == UNSEEN:
        return f"not identifiable from these records: {how['why']}"
    why = ("the one-step regression pins it to no better than +-{:.0%} of a typical size".format(how["relative_se"])
           if how["stage"] == "one-step" else
           "it does not lower the error on the fit segments" if how["stage"].startswith("no gain") else
           "every combination of its parameters at a typical size would be absorbed into the base parameters")
    return f"not identifiable from these records: {why}; revealed by {get_effect(eid).reveals}"


def _block_shares(ctrl: dict, cand: dict) -> list[np.ndarray]:
    """Per record, per block: (SSE_control - SSE_candidate - (floor_control - floor_candidate)) / SSE_control."""
    return [(a - b - fa + fb) / np.maximum(a, 1e-300)
            for a, b, fa, fb in zip(ctrl["records"], cand["records"], ctrl["floor_records"], cand["floor_records"])]


def block_p(ctrl: dict, cand: dict) -> float:
    """One-sided p-value that the candidate lowers the held-out error: a t-test of the per-block
    share explained (:func:`_block_shares`) with the effective sample size of :func:`effective_size`
    (1 when fewer than ``MIN_RECORDS`` records or either free run is unstable)."""
    if not (ctrl["stable"] and cand["stable"]) or len(ctrl["records"]) < MIN_RECORDS:
        return 1.0
    return one_sided_p(*effective_size(_block_shares(ctrl, cand)))


def one_sided_p(mean: float, var: float, n_eff: float) -> float:
    """One-sided p of a mean above 0 from its samples' variance and effective size (t, n_eff - 1 dof)."""
    if mean <= 0:
        return 1.0
    if var == 0:
        return 0.0
    return float(scipy.stats.t.sf(mean / np.sqrt(var / n_eff), max(n_eff - 1.0, 1.0)))


def effect_size(ctrl: dict, cand: dict, nrmse_ctrl: float | None, nrmse_cand: float | None) -> dict | None:
    """A claim's size and its precision: the mean per-block share of the control's held-out error
    the candidate explains, its 95 % interval from the same t distribution and effective sample
    size as :func:`block_p` (the test rejects where the interval's lower end clears 0 at the
    level's confidence), ``n_eff``, the records, and the ``gain`` NRMSE_control / NRMSE_candidate.
    A large gain that differs from record to record has a wide interval: that, not the gain, is
    what the test weighs. None where a free run is unstable."""
    if not (ctrl["stable"] and cand["stable"]):
        return None
    mean, var, n_eff = effective_size(_block_shares(ctrl, cand))
    half = float(scipy.stats.t.ppf(0.975, max(n_eff - 1.0, 1.0)) * np.sqrt(var / n_eff))
    gain = None if not nrmse_cand else (nrmse_ctrl or 0.0) / nrmse_cand
    return {"share": mean, "share_ci95": [mean - half, mean + half], "n_eff": n_eff, "records": len(ctrl["records"]),
            "gain": gain}


def records_needed(ctrl: dict, cand: dict, alpha: float, most: int = 40) -> int | None:
    """How many records like these would bring :func:`block_p` below ``alpha`` if the candidate's
    share were as measured (its mean and spread kept, the effective sample size growing with the
    records); None beyond ``most`` or when it explains nothing."""
    if not (ctrl["stable"] and cand["stable"]):
        return None
    d = _block_shares(ctrl, cand)
    mean, var, n_eff = effective_size(d)
    if mean <= 0:
        return None
    per = n_eff / len(d)
    for n_rec in range(max(len(d), MIN_RECORDS), most + 1):
        n = n_rec * per
        if var == 0 or scipy.stats.t.sf(mean / np.sqrt(var / n), max(n - 1.0, 1.0)) < alpha:
            return n_rec
    return None


#: the words of :func:`too_few_note` that name the records that would settle a candidate
SETTLED_BY = "records like these would settle it"


def too_few_note(ctrl: dict, cand: dict, alpha: float, p: float, more: int | None) -> str:
    """Why a candidate that explains enough is not significant at ``alpha`` (its :func:`block_p`
    is ``p``), and how many records like these would make it so (``more``: :func:`records_needed`)."""
    shares = [float(np.mean(x)) for x in _block_shares(ctrl, cand)]
    return (f"not significant with these {len(shares)} records (p = {p:.2g}, Holm needs < "
            f"{alpha:.2g}): its share of the error is {min(shares):.0%} to {max(shares):.0%} between records; "
            + (f"about {more} {SETTLED_BY} if it is as large as measured (they would test its share of the error, "
               f"not that this effect is what leaves it)" if more else
               "more records like these would not settle it"))


#: a candidate whose effect the records read directly (:attr:`agent.effects.base.Effect.direct`'s
#: ``p``) is tested on that reading where its refit's share of the error clears zero at this
#: one-sided level (the lower end of its 95 % interval, ``effect_size``)
SHARE_CLEARS = 0.025


def test_p(row: dict, read: dict | None) -> float:
    """The p-value of ``row``'s test, which Holm's correction weighs: the records' direct reading of
    the effect (``read``: :attr:`agent.effects.base.Effect.direct`) where it has a test and the refit's
    share of the error clears zero (``SHARE_CLEARS``), else the refit's test over records
    (:func:`block_p`). A claim then says both: the effect is there (the direct reading: a sensor
    mismatch in the phase currents' sum, exact whatever the model) and adding it lowers the error
    (the refit). Sets ``p_value_direct`` and, where it is the test, ``test = "direct"``."""
    if read is None or read.get("p") is None:
        return row["p_value"]
    row["p_value_direct"] = read["p"]
    if row["p_value"] >= SHARE_CLEARS:
        return row["p_value"]
    row["test"] = "direct"
    return read["p"]


def tested_p(row: dict) -> float:
    """The p-value Holm's correction weighed for ``row`` (:func:`test_p`)."""
    return row["p_value_direct"] if row.get("test") == "direct" else row["p_value"]


def direct_note(row: dict) -> str:
    """How a claim that rests on the records' direct reading (:func:`test_p`) was tested."""
    return (f"tested on the records' direct reading (p = {row['p_value_direct']:.2g}: "
            f"{get_effect(row['effect']).direct_test}); its refit's share of the error clears zero "
            f"(p = {row['p_value']:.2g}, one-sided)")


def direct_short_note(row: dict, level: float) -> str:
    """Why a candidate tested on the records' direct reading (:func:`test_p`) is not significant."""
    return (f"not significant: the records' direct reading does not show it beyond their scatter (p = "
            f"{row['p_value_direct']:.2g}, Holm needs < {level:.2g}: {get_effect(row['effect']).direct_test}), "
            f"so what its refit takes ({row['explained_fraction']:.0%} of the error) is not shown to be this effect")


def holm(p_values: list[float], alpha: float) -> list[bool]:
    """Holm's step-down rejections at family-wise level ``alpha``."""
    order = np.argsort(p_values)
    reject = [False] * len(p_values)
    for rank, i in enumerate(order):
        if p_values[i] > alpha / (len(p_values) - rank):
            break
        reject[i] = True
    return reject


def _share(h_ctrl: dict, h: dict) -> float | None:
    if not (h_ctrl["stable"] and h["stable"]):
        return None
    raw = float(np.sum(np.concatenate(h_ctrl["records"])))
    return float(np.sum(h_ctrl["blocks"]) - np.sum(h["blocks"])) / max(raw, 1e-300)


def _total(h: dict):
    return None if h["nrmse"] is None else h["nrmse"]["total"]


def _dq(h: dict) -> dict | None:
    return None if h["nrmse"] is None else {"d": h["nrmse"]["d"], "q": h["nrmse"]["q"]}


RIVAL_RATIO = 0.8  #: a claim is withheld where an unclaimed candidate's held-out NRMSE is below this share of its own


def _better_unclaimed(rows: list[dict], first: dict | None) -> dict | None:
    """The candidate that fits the held-out records clearly better than the one to be claimed (NRMSE
    below ``RIVAL_RATIO`` of its), or explains a larger share of the control's held-out error (the
    measure the claim's own test weighs), but is not claimed itself (its parameters absorbed by the
    base, at a bound, or its test short of Holm's level), if any: where another effect explains as
    much, the records do not say which one they carry. (With the NRMSE alone, the family's 800
    drives kept two claims of another effect whose rival explained as much: 20017's gain mismatch
    for hidden harmonics, 93 % against 93 %, and 20036's delay for a hidden dead time. The NRMSE
    alone at 1.0 would weigh the records unlike the test: on 20009 a delay explaining 4 % of the
    error, with a 2 % lower NRMSE, withheld a speed ripple explaining 40 %.) Claiming the worse one would name a
    different effect than the records carry: a hidden dead time and the flux harmonics both put a 6 f_e line in dq, and where
    the dead time's fundamental is absorbed by the base, only the harmonic's freedom is left to
    tell them apart (a family drive: dead time fitted at 19.4 V for 19.0, 1.6x better than the
    flux harmonics, which were claimed). An effect the records' measurement cannot show (``UNSEEN``)
    is no such rival (unclaimable for the measurement, not for another effect), unless what it fits is
    the model's input itself (``Effect.unseen_is_input``): a voltage measured through a window that
    cuts the PWM pulses is no delayed copy of the applied one, and where a change of the path takes
    the control's error far better than the claim, the claim takes up part of that input's error (two
    family drives with such windows, one of them a null drive, where the path's refit left 0.2 % and
    0.3 % of the control's error and a gain mismatch or a saturation was claimed). A negligible fit
    is a rival too: where a change below what the base's own approximations leave fits clearly
    better than the claim, the claim's share may be such an approximation's as well (drive 20033, a
    hidden delay whose pinned figure came out within the floor: the saturation, 50 % against the
    path's 73 %, would have been claimed). So is a claimable one whose test fell short: a family
    drive's hidden saturation explained 95 % of the control's error at p = 0.0015 (Holm's level
    0.00125), the voltage path 74 % at p = 0.0011, and the path would have been claimed."""
    if first is None or first["nrmse_after"] is None:
        return None
    better = [r for r in rows if r is not first and r["nrmse_after"] is not None and not r.get("significant")
              and (r.get("identifiability", {}).get("stage") != UNSEEN or get_effect(r["effect"]).unseen_is_input)
              and (r["nrmse_after"] < RIVAL_RATIO * first["nrmse_after"]
                   or (r["explained_fraction"] or 0.0) > (first["explained_fraction"] or 0.0))
              and (r["explained_fraction"] or 0.0) > 0.0]
    return min(better, key=lambda r: r["nrmse_after"], default=None)


TWIN_SHARE = 0.9  #: a claim is withheld where another effect's form reproduces this share of its fitted contribution
TWIN_CHANCE = 0.05  #: the largest chance that a random contribution reaches TWIN_SHARE through a projected form
TWIN_ALPHA = ALPHA  #: the level at which a claim must beat its physical twin where the records cannot separate them
#: what separates two effects that the records at hand cannot tell apart (either order)
SEPARATES = {
    frozenset(("flux_harmonics", "inverter_deadtime")):
        "records at a second speed, 20 % or more apart (the back-EMF lines grow with the speed, the dead "
        "time's stay), or under MTPA at loads whose current angles differ (the dead time's lines turn with "
        "the current, the magnet's stay with the rotor)",
}


SPEED_SPREAD = 1.2  #: records whose mean speeds span this ratio separate speed-proportional lines from fixed ones
ANGLE_SPREAD = np.radians(5.0)  #: records whose current angles span this turn current-locked 6 f_e lines by 30 degrees


def spread(preps: list[Prepared]) -> tuple[float, float]:
    """The records' span of operating points: the ratio of their largest to smallest mean speed and
    the range of their current vectors' angles from the q axis (rad, either sign of torque)."""
    speeds = [float(np.mean(np.abs(p.sig.omega_e))) for p in preps]
    angles = [float(np.arctan2(-np.mean(p.sig.i_dq[0]), abs(np.mean(p.sig.i_dq[1])))) for p in preps]
    return max(speeds) / max(min(speeds), 1e-9), float(np.ptp(angles))


def separable(first: str, other: str, preps: list[Prepared]) -> bool:
    """Whether records ``preps`` can tell effect ``first`` from ``other`` by physics, where the two
    are known to share a signature (``SEPARATES``); True for any other pair. The magnet's 5th and
    7th and the dead time both put 6 f_e lines into dq: the magnet's grow with the speed and stay
    with the rotor, the dead time's keep their size and turn with the current vector. At one speed
    (mean speeds within ``SPEED_SPREAD``) and one current angle (within ``ANGLE_SPREAD``), a dead
    time modelled with a slightly wrong knee leaves exactly such lines for the harmonics to take."""
    if frozenset((first, other)) not in SEPARATES:
        return True
    speeds, angles = spread(preps)
    return speeds >= SPEED_SPREAD or angles >= ANGLE_SPREAD


def contribution(eid: str, values, preps: list[Prepared], moved_from: list[Prepared] | None = None
                 ) -> list[np.ndarray]:
    """Effect ``eid``'s contribution with parameters ``values`` on each record's fit segment, (2, N)
    each, less its mean per axis (what the base's per-record flux and resistance take); where
    ``preps`` are ``moved_from``'s with the voltage path moved (:func:`moved_delay`), the move's
    change of the voltage included."""
    out = []
    for j, p in enumerate(preps):
        t = np.tensordot(np.asarray(values, float), get_effect(eid).cols(p.sig)[:, :, p.fit_slice], 1)
        if moved_from is not None:
            t = t + (p.sig.v_dq - moved_from[j].sig.v_dq)[:, p.fit_slice]
        out.append(t - t.mean(axis=-1, keepdims=True))
    return out


def _design(eid: str, preps: list[Prepared]) -> np.ndarray:
    """Effect ``eid``'s columns on every record's fit segment, less their means per record and axis,
    stacked: (samples, parameters)."""
    design = []
    for p in preps:
        c = get_effect(eid).cols(p.sig)[:, :, p.fit_slice]
        design.append((c - c.mean(axis=-1, keepdims=True)).reshape(c.shape[0], -1))
    return np.hstack(design).T


def reproduced(target: list[np.ndarray], kind: str, other: str, preps: list[Prepared], through: str | None = None
               ) -> float:
    """The share of a ``kind`` effect's contribution ``target`` (:func:`contribution`) that effect
    ``other``'s columns reproduce by least squares with a free level per record and axis (both
    sides less their means: Frisch-Waugh). 1 means the records cannot tell the two apart: at one
    speed under i_d = 0 a dead time's 6 f_e lines are a 5th and a 7th harmonic in the ratio 49:25
    at the current's angle.

    ``through``: the target's own effect; ``other``'s columns are first projected onto its columns,
    so the share says whether the target is what ``other`` leaves in that effect's form (a dead time
    seen through the flux harmonics: its 5th and 7th in their ratio and phase, its 11th and 13th,
    which the harmonics cannot take, set aside), with ``other``'s parameters held to their physical
    signs (a dead time's pattern with a negative U_dt is no dead time). 0 where such a projection
    spans the target's whole form, or so much of it that a random contribution of that form would
    reach ``TWIN_SHARE`` with a chance above ``TWIN_CHANCE`` (the squared cosine of a random
    direction in p dimensions with a k-dimensional subspace is Beta(k/2, (p - k)/2))."""
    if get_effect(other).kind != kind:
        return 0.0
    y, x = np.concatenate([t.ravel() for t in target]), _design(other, preps)
    energy = float(y @ y)
    if not (energy > 0 and np.all(np.isfinite(x))):
        return 0.0
    if through is not None:
        own = _design(through, preps)
        if not np.all(np.isfinite(own)):
            return 0.0
        x = own @ np.linalg.lstsq(own, x, rcond=None)[0]
        k, p = np.linalg.matrix_rank(x), np.linalg.matrix_rank(own)
        if k == 0 or k >= p or scipy.stats.beta.sf(TWIN_SHARE, k / 2, (p - k) / 2) > TWIN_CHANCE:
            return 0.0
        signs = [(0.0 if q.lower >= 0 else -np.inf, 0.0 if q.upper <= 0 else np.inf) for q in get_effect(other).params]
        rest = y - x @ scipy.optimize.lsq_linear(x, y, bounds=tuple(zip(*signs))).x
        return float(max(0.0, 1.0 - (rest @ rest) / energy))
    rest = y - x @ np.linalg.lstsq(x, y, rcond=None)[0]
    return float(max(0.0, 1.0 - (rest @ rest) / energy))


def _twin(first: dict | None, rows: list[dict], fits: dict, preps: list[Prepared], own: dict, held: dict
          ) -> tuple[dict, float, str] | None:
    """The candidate these records cannot tell from the to-be-claimed ``first``, if any, with the
    share and its basis: one whose form reproduces at least ``TWIN_SHARE`` of ``first``'s fitted
    contribution (:func:`reproduced`, basis "reproduced"); its physical twin (``SEPARATES``, one the
    records' measurement can show) whose form, seen through ``first``'s, reproduces that share
    (basis "pattern": a dead time's 6 f_e lines taken by the flux harmonics, their 5th and 7th fitted
    in the dead time's 49:25 at its phase; on any records, for what the fit took shows whether they
    separated the two); or such a twin, on records that cannot separate the two (:func:`separable`),
    that ``first`` does not beat on the held-out records (:func:`block_p` of ``first`` against the
    twin's refit at ``TWIN_ALPHA``; basis "explains", the twin's share of the error as a fraction of
    ``first``'s): at one speed and one current angle a dead time and the magnet's harmonics leave
    the same lines, and which of the two fits a hair better is chance. ``own``: effect -> the records
    its refit was fitted on, where not ``preps``; ``held``: effect -> its refit's held-out errors (:func:`heldout`)."""
    if first is None:
        return None
    eid = first["effect"]
    target = contribution(eid, fits[eid].values[eid], own.get(eid, preps), preps if eid in own else None)
    kind = get_effect(eid).kind
    best = max(((r, reproduced(target, kind, r["effect"], preps)) for r in rows if r is not first),
               key=lambda t: t[1], default=None)
    if best is not None and best[1] >= TWIN_SHARE:
        return best[0], best[1], "reproduced"
    seen = max(((r, reproduced(target, kind, r["effect"], preps, through=eid)) for r in rows if r is not first
                and frozenset((eid, r["effect"])) in SEPARATES and r.get("identifiability", {}).get("stage") != UNSEEN),
               key=lambda t: t[1], default=None)
    if seen is not None and seen[1] >= TWIN_SHARE:
        return seen[0], seen[1], "pattern"
    pair = next((r for r in rows if r is not first and not r["at_bound"] and (r["explained_fraction"] or 0.0) > 0.0
                 and r.get("identifiability", {}).get("stage") != UNSEEN
                 and not separable(eid, r["effect"], own.get(eid, preps))
                 and block_p(held[r["effect"]], held[eid]) >= TWIN_ALPHA), None)
    if pair is None:
        return None
    return pair, pair["explained_fraction"] / max(first["explained_fraction"] or 0.0, 1e-12), "explains"


def twin_note(first: str, other: str, share: float, basis: str = "reproduced",
              preps: list[Prepared] | None = None) -> str:
    """Why ``first`` is not claimed beside its twin ``other``, and which records would separate them
    (``preps``: the records, whose span of speed and current angle a "pattern" note states)."""
    how = SEPARATES.get(frozenset((first, other)), f"records that reveal {other}: {get_effect(other).reveals}")
    span = ""
    if preps and basis == "pattern":
        speeds, angles = spread(preps)
        span = f"; these records span {speeds:.2f}x in speed and {np.degrees(angles):.1f} degrees of current angle"
    why = (f"{other}'s form reproduces {share:.0%} of {first}'s fitted contribution" if basis == "reproduced" else
           f"{first}'s fitted contribution is {share:.0%} what {other} leaves in {first}'s form{span}"
           if basis == "pattern" else
           f"one speed and one current angle, where {first} fits no better than {other}, which explains {share:.0%} "
           f"as much of the error")
    return f"not claimed: these records cannot tell {first} from {other} ({why}); {how} would separate them"


def _readable(row: dict) -> bool:
    """The records pin the candidate within its physical range, beyond the model's own approximations,
    and their direct reading of it does not contradict the fit (``contradicted``,
    :attr:`agent.effects.base.Effect.read_through`)."""
    return bool(row["identifiable"] and not row["at_bound"] and not row.get("negligible")
                and not row.get("contradicted"))


def _claimable(row: dict) -> bool:
    return _readable(row) and (row["explained_fraction"] or 0.0) >= MIN_EXPLAINED


def _too_small(row: dict) -> bool:
    """Claimable but for its share: it explains less than ``MIN_EXPLAINED`` of the control's error."""
    return _readable(row) and 0.0 < (row["explained_fraction"] or 0.0) < MIN_EXPLAINED


def floor_ratio(h_ctrl: dict) -> float | None:
    """The control's held-out error beyond the noise floor (its NRMSE, :func:`heldout`) over that
    floor, or None."""
    floor = (h_ctrl.get("noise_floor") or {}).get("total")
    total = _total(h_ctrl)
    return total / floor if floor and total is not None else None


def too_small_note(share: float, ratio: float | None, p: float | None = None, level: float | None = None) -> str:
    """Why a candidate the records pin is not claimed though it explains some of the error: its
    ``share`` of the control's held-out error is below ``MIN_EXPLAINED`` (a real but minor part
    where its test passes; where ``p`` is at or above Holm's ``level``, it does not pass either);
    ``ratio``: the control over its noise floor, :func:`floor_ratio`, where what is left is larger
    than any candidate explains."""
    left = (f"; the control's error beyond the noise is {ratio:.3g} times the noise floor, so a larger error that no "
            f"candidate explains is left" if ratio is not None and ratio > 2.0 else "")
    test = ("its test passes, but" if p is None or level is None or p < level else
            f"its test does not pass (p = {p:.2g}, Holm needs < {level:.2g}), and")
    return (f"not claimed: {test} it explains {share:.1%} of the control's held-out error, below the "
            f"{MIN_EXPLAINED:.0%} a claim needs{left}")


def _forward(rows: list[dict], fits: dict, preps: list[Prepared], base: dict, prior: dict, own: dict) -> None:
    """Forward selection after the ranking: with the significant effects accepted (their refit the
    new control), each remaining candidate that explained at least ``MIN_EXPLAINED`` on its own is
    refitted on top and tested again (Bonferroni over those still open, at ``ALPHA``). Two hidden
    effects: the second one's share is judged against a control that no longer carries the first,
    whose error differs from record to record (a delay's grows with the load) and hides it.
    Marks such rows significant with ``given``: the effects accepted before. ``own``: effect -> the
    records its refit was fitted on, where not ``preps`` (the first accepted's are used for all)."""
    accepted = [r["effect"] for r in rows if r["significant"]]
    if not accepted:
        return
    preps = own.get(accepted[0], preps)
    open_rows = [r for r in rows if not r["significant"] and _claimable(r)]
    for row in list(open_rows):  # an effect these records cannot tell from an accepted one is not added on top
        twin = next((a for a in accepted if not separable(row["effect"], a, preps)), None)
        if twin is not None:
            open_rows.remove(row)
            row["note"] = "; ".join(filter(None, [row.get("note"), (
                f"not claimed on top of {twin}: these records cannot tell them apart (one speed, one current "
                f"angle); {SEPARATES[frozenset((row['effect'], twin))]} would separate them")]))
    while open_rows and len(accepted) < 4:
        ctrl = fits[accepted[0]]
        for eid in accepted[1:]:
            ctrl = nested(ctrl, preps, (eid,), base, prior)
        h_ctrl = heldout(ctrl.model, preps)
        tried = []
        for row in list(open_rows):
            r = nested(ctrl, preps, (row["effect"],), base, prior)
            h = heldout(r.model, preps)
            share, p = _share(h_ctrl, h), block_p(h_ctrl, h)
            twin, pattern = on_top_pattern(row["effect"], r, accepted, preps)
            if twin is not None and (share or 0.0) * (1.0 - pattern) < MIN_EXPLAINED:
                open_rows.remove(row)  # what it takes on top is mostly the part of its twin that the twin's model leaves
                row["note"] = "; ".join(filter(None, [row.get("note"), (
                    f"not claimed on top of {twin}: {pattern:.0%} of what its refit takes on top is {twin}'s pattern "
                    f"(reproduced through its own form: the part of {twin} its model leaves), and the rest explains "
                    f"{(share or 0.0) * (1.0 - pattern):.0%} of the error, below the {MIN_EXPLAINED:.0%} a claim needs")]))
                continue
            ok = (r.identifiable[row["effect"]][0] and not r.at_bound.get(row["effect"], False)
                  and not get_effect(row["effect"]).negligible(r.values[row["effect"]])
                  and (share or 0.0) >= MIN_EXPLAINED)
            tried.append((p, row, ok, share))
        if not tried:
            return
        p, row, ok, share = min(tried, key=lambda t: t[0])
        if not (ok and p < ALPHA / len(open_rows)):  # Bonferroni over the rows still open
            return
        row.update(significant=True, given=list(accepted), explained_fraction_given=share, p_value_given=p)
        accepted.append(row["effect"])
        open_rows.remove(row)


def on_top_pattern(eid: str, r: Refit, accepted: list[str], preps: list[Prepared]) -> tuple[str | None, float]:
    """Among ``eid``'s accepted physical twins (``SEPARATES``), the one whose form, seen through
    ``eid``'s (:func:`reproduced`, ``through``), reproduces most of what ``eid``'s refit ``r`` on top
    of the accepted effects contributes, and that share; (None, 0.0) without such a twin. Records
    that span enough to separate the twins (:func:`separable`) still leave the part of an accepted
    effect that its model misses: on family drive 20038 (a hidden 5.5 V dead time, fitted at 3.5 V)
    the magnet's harmonics on top took the rest, 84 % of it in the dead time's 49:25, and were
    claimed as a second effect. :func:`_forward` weighs only what is beyond the pattern."""
    twins = [a for a in accepted if frozenset((eid, a)) in SEPARATES]
    if not twins:
        return None, 0.0
    target = contribution(eid, r.values[eid], preps)
    share, twin = max((reproduced(target, get_effect(eid).kind, a, preps, through=eid), a) for a in twins)
    return twin, share


def explain(baseline, preps: list[Prepared], candidates=None, progress=None) -> dict:
    """Rank ``candidates`` (default: every library effect the model lacks). Returns the CONTRACT
    document: ``nrmse_before`` (the model as it is), ``nrmse_control``, the control's ``noise_floor``
    and ``candidates`` best first; NRMSEs are None (with a ``note``) where a free run is unstable."""
    t0 = time.perf_counter()
    model = baseline.model
    have = tuple(model.meta.get("effects", []))
    candidates = [get_effect(e).id for e in (candidates or EFFECTS) if e not in have]
    base, prior = drive_base(baseline), physical_prior(baseline)
    before = heldout(model, preps)
    dyn = dynamics(preps, prior)
    if dyn["quiet"]:
        return _unranked(baseline, preps, before, None, dyn, no_dynamics_note(dyn), t0)
    preps = rotor_frames(preps, baseline.profile, prior)
    ctrl = control(model, preps, base, prior=prior)
    h_ctrl = heldout(ctrl.model, preps)
    if not h_ctrl["stable"]:
        return _unranked(baseline, preps, before, h_ctrl, dyn, f"the base model cannot be refitted stably on these "
                         f"records ({h_ctrl['note']}), so no effect is ranked against it", t0)
    fits = []
    for j, eid in enumerate(candidates):
        if progress:
            progress(j, len(candidates), f"refit with {eid}")
        fits.append(nested(ctrl, preps, (eid,), base, prior))
    # No candidate may be credited for finding better base values: refit the control from the
    # best candidate's base values and keep the better control (the candidates stay >= it).
    best = min(fits, key=lambda r: r.cost, default=None)
    if best is not None and best.cost < ctrl.cost and best.model is not ctrl.model:
        again = control(model, preps, base, start={k: best.phys[k] for k in NONLINEAR}, prior=prior)
        if again.cost < ctrl.cost:
            ctrl = again
            fits = [r if r.cost <= ctrl.cost else _zero_effect(ctrl, eid, r.at_bound.get(eid, False))
                    for eid, r in zip(candidates, fits)]
            h_ctrl = heldout(ctrl.model, preps)
    # A control beyond any machine of the rating is no base to rank against, unless an effect's refit
    # makes the base physical (a delay misreads L_q until it is modelled; the other effects of the
    # records are ranked as well then: a second hidden effect cannot fix what the delay breaks).
    fits = dict(zip(candidates, fits))
    wrong = implausible_base(ctrl.phys, base, baseline.profile.motor)
    own = {}  # effect -> the records its refit was fitted on, where not preps: a voltage path moved by whole samples
    if "voltage_delay" in fits and fits["voltage_delay"].identifiable["voltage_delay"][1]["stage"] != UNSEEN:
        r, moved = moved_delay(ctrl, preps, fits["voltage_delay"], base, prior)
        if moved is not preps:
            fits["voltage_delay"], own["voltage_delay"] = r, moved
    if wrong is not None and all(implausible_base(r.phys, base, baseline.profile.motor) for r in fits.values()):
        why = [wrong, "the baseline does not pin L_q either: give the nameplate (nameplate.lq_h) or records with an "
                      "encoder angle" if "Lq" not in prior else "",
               "R_s,q is pinned by records with a load step (the q current's time constant: each record's magnet "
               "flux takes any steady q voltage) or by the nameplate (nameplate.rs_ohm)"
               if "Rs_q" in wrong and "Rs" not in prior else "",
               unfollowed_note(dyn, baseline.profile.sampling.voltage_source)]
        return _unranked(baseline, preps, before, h_ctrl, dyn, "; ".join(filter(None, why)), t0)
    rows, p_values, held = [], [], []
    for eid, r in fits.items():
        h = heldout(r.model, own.get(eid, preps))
        held.append(h)
        identifiable, how = r.identifiable[eid]
        bound = r.at_bound.get(eid, False)
        row = {"effect": eid, "nrmse_after": _total(h), "explained_fraction": _share(h_ctrl, h),
               "significant": False, "p_value": block_p(h_ctrl, h), "identifiable": identifiable, "at_bound": bound,
               "nrmse_after_dq": _dq(h), "identifiability": how,
               "effect_size": effect_size(h_ctrl, h, _total(h_ctrl), _total(h)),
               **reported(eid, r, ctx := context(r, own.get(eid, preps), baseline.profile), prior)}
        p_values.append(test_p(row, get_effect(eid).direct(ctx["signals"])))
        refuted = (row["explained_fraction"] or 0.0) > 0.0 and get_effect(eid).refutes(ctx["signals"])
        if refuted:  # only where it explains something: a refutation of nothing says nothing
            row.update(contradicted=True, note="; ".join(filter(None, [row.get("note"), refuted])))
        if not identifiable:
            row["note"] = "; ".join(filter(None, [unidentified_note(eid, how), row.get("note")]))
        elif negligible_as_pinned(eid, path_change(r.values[eid], preps, own[eid]) if eid in own else r.values[eid],
                                  row["params"], ctx):
            row["negligible"] = True
            row["note"] = "; ".join(filter(None, [row.get("note"), (
                "negligible: its fitted size is below what the base model's own approximations leave "
                f"({params_floor(eid)}), so it is not claimed")]))
        if bound:
            row["note"] = "; ".join(filter(None, [get_effect(eid).at_bound or (
                "at bound: the fit wants it beyond its physical range, so it is not this effect"), row.get("note")]))
        if not h["stable"]:
            row["note"] = h["note"]
        rows.append(row)
    reject = holm(p_values, ALPHA)
    level = ALPHA / max(len(p_values) - sum(reject), 1)  # what the next in Holm's order needs
    for row, rej in zip(rows, reject):
        row["significant"] = bool(rej and _claimable(row))
    # Only the best of them is claimed on its own: a large effect is partly absorbed by every
    # candidate, so the others must be significant on top of it (_forward), not against the control.
    first = max((r for r in rows if r["significant"]), key=lambda r: r["explained_fraction"] or 0.0, default=None)
    leader = first  # the others are judged on top of it, whether or not it is claimed
    rival = _better_unclaimed(rows, first)
    if rival is not None:  # the records cannot tell them apart: no claim, and why
        short = _claimable(rival)  # claimable, its test short of the level
        first.update(significant=False, note="; ".join(filter(None, [first.get("note"), (
            f"not claimed: {rival['effect']} fits the held-out records as well or better (NRMSE "
            f"{100 * rival['nrmse_after']:.3g} % against {100 * first['nrmse_after']:.3g} %, "
            f"{100 * (rival['explained_fraction'] or 0.0):.3g} % of the control's error against "
            f"{100 * (first['explained_fraction'] or 0.0):.3g} %) but " + (
                f"its own test falls short of Holm's level (p = {tested_p(rival):.2g}), so these records cannot tell "
                f"which of the two they carry" if short else f"these records cannot pin it ({rival.get('note', '')})"))])))
        first = None
    twin = _twin(first, rows, fits, preps, own, dict(zip(fits, held)))
    if twin is not None:  # another effect's form makes the same contribution: no claim, and what separates them
        first.update(significant=False, twin={"effect": twin[0]["effect"], twin[2]: twin[1]}, note="; ".join(
            filter(None, [first.get("note"), twin_note(first["effect"], twin[0]["effect"], twin[1], twin[2], preps)])))
        first = None
    for row in rows:
        if row["significant"] and row is not first:
            row.update(significant=False, alone_significant=True)
    _forward(rows, fits, preps, base, prior, own)
    for row in rows:
        if row.pop("alone_significant", False) and not row["significant"]:
            row["note"] = "; ".join(filter(None, [row.get("note"), (
                f"significant against the control alone, not on top of {leader['effect']}: it takes up part of "
                f"that effect's error")]))
    for row, h in zip(rows, held):
        if row["significant"] and row.get("test") == "direct" and "given" not in row:
            row["note"] = "; ".join(filter(None, [row.get("note"), direct_note(row)]))
        if row["significant"] or row["p_value"] >= 1.0:
            continue
        if _claimable(row) and row.get("test") == "direct" and tested_p(row) >= level:
            why = direct_short_note(row, level)
        elif _claimable(row) and row["p_value"] >= level:  # below it, Holm passed it and its note says why it is not claimed
            row["records_needed"] = records_needed(h_ctrl, h, level)
            why = too_few_note(h_ctrl, h, level, row["p_value"], row["records_needed"])
        elif _too_small(row):
            why = too_small_note(row["explained_fraction"], floor_ratio(h_ctrl), row["p_value"], level)
        else:
            continue
        row["note"] = "; ".join(filter(None, [row.get("note"), why]))
    rows.sort(key=lambda r: (r["significant"], r["explained_fraction"] if r["explained_fraction"] is not None
                             else -np.inf), reverse=True)
    doc = _document(baseline, preps, before, h_ctrl, dyn, rows, t0)
    doc.update(control_params=ctrl.phys, control_is_model=ctrl.model is model)
    for key in dyn["unpinned"]:  # the voltage varies, the current does not follow it as the model expects
        doc["warnings"].append(f"{key[0]}_{key[1]} is pinned by neither these records (one-step relative sd "
                               f"{dyn['inductance_rel_se'][key]:.0%}, with a voltage spread of "
                               f"{dyn['voltage_spread_v']:.3g} V against noise {dyn['voltage_noise_v']:.3g} V) nor the "
                               f"baseline: the refits read it from the free run")
    doc["warnings"].extend(frame_warnings(baseline.profile, preps, prior))
    if len(preps) < MIN_RECORDS:
        doc["warnings"].append(f"{len(preps)} record(s): significance needs at least {MIN_RECORDS} "
                               f"(the test is over records); nothing is called significant")
    return doc


SENSOR_CLASS = 0.005  #: a phase sensor's gain off phase a's by more than this (and 3 standard errors) is said


def sensor_gains(preps: list[Prepared], rows: list) -> tuple[dict | None, str | None]:
    """The current sensors' gains against phase a as the records read them, off the phase currents'
    sum (current_gain_mismatch's :attr:`agent.effects.base.Effect.direct`): {"gain_b", "gain_c",
    "bound"} (None where phase c is computed or no record carries current), and a warning where a
    sensor is off beyond ``SENSOR_CLASS`` and its bound and no claim says so already. The sum reads
    the sensors whatever the model does: a mismatch the drive's controller acts on shows in the
    model only through its impedance, where the refits' R_s,q and L can take it, so no candidate may
    gain from it."""
    read = get_effect("current_gain_mismatch").direct([p.sig for p in preps])
    if read is None:
        return None, None
    g, bound = read["params"], read["params_bound"]
    said = any(r["effect"] == "current_gain_mismatch" and r["significant"] for r in rows)
    if said or not any(abs(g[k]) > max(SENSOR_CLASS, bound[k]) for k in g):
        return {**g, "bound": bound}, None
    return {**g, "bound": bound}, (
        f"the phase currents' sum shows the current sensors of phases b and c {100 * g['gain_b']:+.2f} % and "
        f"{100 * g['gain_c']:+.2f} % off phase a's gain (+-{100 * max(bound.values()):.2g} %): a three-wire winding's "
        f"currents sum to zero, so this is the sensors' mismatch, whatever the refits gain from current_gain_mismatch "
        f"(a mismatch the drive's controller acts on reaches the model only through its impedance)")


def _document(baseline, preps: list[Prepared], before: dict, h_ctrl: dict | None, dyn: dict, rows: list,
              t0: float) -> dict:
    """explain's CONTRACT document around its candidate ``rows``."""
    doc = {"nrmse_before": _total(before), "nrmse_control": None if h_ctrl is None else _total(h_ctrl),
           "noise_floor": None if h_ctrl is None or h_ctrl["noise_floor"] is None else h_ctrl["noise_floor"]["total"],
           "nrmse_before_dq": _dq(before), "candidates": rows, "control_params": None, "control_is_model": False,
           "dynamics": dyn, "records": [p.source for p in preps], "warnings": operating_warnings(baseline, preps)}
    doc["sensor_gains"], warning = sensor_gains(preps, rows)
    doc["warnings"].extend(filter(None, [warning]))
    doc["seconds"] = time.perf_counter() - t0
    if not before["stable"]:
        doc["note_before"] = before["note"]
    return doc


#: a refit's base values beyond any machine of the drive's rating: R_s i_rated above this share of
#: the rated voltage (copper losses of half the rated power), omega_rated L i_rated above this
#: multiple of it (industrial machines: 0.1-1 per unit)
R_MAX_PU, X_MAX_PU = 0.5, 3.0


def implausible_base(phys: dict, base: dict, motor) -> str | None:
    """What in a refit's q-axis values (``phys``: Rs_q ohm, Lq H) no machine of the drive's rating can
    have (per unit of the rated voltage and current, ``base``: drive_base), or None. Such a control
    is not a model of this drive but of what the records do not pin. (The d axis's R_s,d and L_d
    carry almost no current under i_d = 0 and may sit anywhere, L_d at the one-step regression's
    L_MAX_H where it sees no response, without harming the model.)"""
    i, w = base.get("i_rated"), 2 * np.pi * motor.rated_speed_rpm / 60.0 * motor.pole_pairs
    v = base.get("v_rated") or (base["psi_m"] * w if "psi_m" in base else None)
    if not (i and v and w):
        return None
    bad = [f"Rs_q {phys['Rs_q']:.3g} ohm"] if phys.get("Rs_q") and phys["Rs_q"] * i > R_MAX_PU * v else []
    bad += [f"Lq {phys['Lq']:.3g} H"] if phys.get("Lq") and w * phys["Lq"] * i > X_MAX_PU * v else []
    if not bad:
        return None
    return (f"the base model is not identified by these records: its refit lands on {', '.join(bad)}, beyond any "
            f"machine of this rating (rated impedance {v / i:.3g} ohm; R_s at most {R_MAX_PU:g}, omega L at most "
            f"{X_MAX_PU:g} times it), so no effect is ranked against it")


def _unranked(baseline, preps: list[Prepared], before: dict, h_ctrl: dict | None, dyn: dict, why: str,
              t0: float) -> dict:
    """explain's answer where no ranking would mean anything (``why``): no candidates, ``note``
    saying why and what would help."""
    doc = _document(baseline, preps, before, h_ctrl, dyn, [], t0)
    doc["note"] = why
    return doc


def add_effects(baseline, preps: list[Prepared], effect_ids) -> tuple[object, dict]:
    """Refit ``baseline.model`` with ``effect_ids`` added; returns (refit, figures). Figures:
    ``nrmse_before`` (the model as it is), ``nrmse_control`` (the control: the model refitted without
    the new effects, or the model itself if better) and ``nrmse_after``, all the held-out figure."""
    model = baseline.model
    have = tuple(model.meta.get("effects", []))
    new = tuple(get_effect(e).id for e in effect_ids)
    dup = [e for e in new if e in have]
    if dup:
        raise InputError(f"the model already has effect(s) {', '.join(dup)}")
    base, prior = drive_base(baseline), physical_prior(baseline)
    preps = rotor_frames(preps, baseline.profile, prior)
    ctrl = control(model, preps, base, prior=prior)
    r = nested(ctrl, preps, new, base, prior)
    ctx = context(r, preps, baseline.profile)
    h_before, h_ctrl, h_after = heldout(model, preps), heldout(ctrl.model, preps), heldout(r.model, preps)
    said = {e: reported(e, r, ctx, prior) for e in have + new}
    figures = {"nrmse_before": _total(h_before), "nrmse_control": _total(h_ctrl), "nrmse_after": _total(h_after),
               "params": {e: said[e]["params"] for e in have + new},
               "params_bound": {e: said[e].get("params_bound") for e in have + new},
               "at_bound": [e for e in new if r.at_bound.get(e)], "base": r.phys,
               "warnings": operating_warnings(baseline, preps)}
    for e in have + new:
        note = said[e].get("note")
        if r.identifiable[e][0] and note:
            figures["warnings"].append(f"{e}: {note}")
        if not r.identifiable[e][0]:
            figures["warnings"].append(f"{e}: {unidentified_note(e, r.identifiable[e][1])}; " + (
                f"its figures are the records' own reading ({note})" if any(v is not None for v in said[e]["params"].values())
                else "its parameters are not reported (the model keeps the fitted values as lumped terms)"))
    for e in figures["at_bound"]:
        figures["warnings"].append(f"{e}: at its physical bound; the data want it beyond physics, so it is not this effect")
    for h in (h_before, h_ctrl, h_after):
        if not h["stable"]:
            figures["warnings"].append(h["note"])
    r.model.meta["effect_params"] = figures["params"]
    return r, figures
