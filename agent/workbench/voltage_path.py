"""The drive's voltage path, learned from healthy records, and its correction of every record.

The reported voltage is the applied one shifted and turned (:mod:`agent.effects.voltage_delay`):
in the stationary alpha-beta frame v_applied(m) = exp(j a omega_e T_s) v_reported(m + d), d the
delay in samples (signed: -1 for a drive that reports its command and applies it one computation
period later, > 0 for a measured voltage through a filter), a the advance in samples of omega_e T_s
(0.5 for a voltage held constant in dq). It belongs to the healthy drive and its measurement chain,
so the baseline carries it (``model.meta["voltage_path"]``) and the workbench applies it to every
record's voltage before it fits (:func:`agent.workbench.fitting.prepare`); the voltage_delay effect
then measures the change from it.

Estimate (:func:`estimate_path`): the path under which the base model, refitted on the healthy
records (:func:`agent.workbench.fitting.refit`, the workbench's control), predicts their held-out
current best: a scan of d, then of a. Why not the one-step regression alone: the current loop's
broadband voltage is its answer to the current's measurement noise, and the sample of the reported
voltage that carries the controller's reaction to i(k+1) explains i(k+1) as well as the plant's
input does (the controller's equation), so a regression over voltage lags reads the controller
where the path's lag is. The free run of the whole record does not: it must follow the current
over the machine's time constants. The path is pinned when the error at every candidate at least
half a sample away is ``RISE`` times the best's and the best is inside the physical range; else none is given and the workbench uses the
voltage as reported.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from agent.frames import CLARKE
from agent.model import Signals

D_RANGE = (-1.5, 2.0)  #: samples, the delay's physical range
A_RANGE = (-1.0, 2.0)  #: samples of omega_e T_s, the advance's (a dq hold after one computation period: 1.5)
STEP = 0.25  #: samples, the scan's grid (refined to half of it around the best)
RISE = 1.5  #: the path is pinned when every candidate >= 0.5 sample away has this times the best's error
FLOOR_SHARE = 0.3  #: share of the noise floor (rms) counted in a candidate's error
SCAN_NFEV = 40  #: iteration budget of each candidate's refit
NOT_PINNED = ("the records do not pin the voltage path (the base model's held-out error varies by less than "
              "{rise:g}x over the {what} candidates): the workbench uses the voltage as reported; a healthy record "
              "with the current loop's broadband voltage at a load or speed step pins it")


def apply_path(sig: Signals, delay: float, advance: float) -> Signals:
    """``sig`` with the voltage the machine saw: v_applied(m) = exp(j a omega_e(m) T_s) v_reported(m + d)
    in alpha-beta (``delay`` d and ``advance`` a in samples; a fractional d interpolates linearly
    between samples, the ends hold the first and last sample). The zero sequence is shifted alike,
    the current, angle and speed are kept."""
    if delay == 0.0 and advance == 0.0:
        return sig
    n = sig.n
    k = np.arange(n, dtype=float)
    v = np.stack([np.interp(k + delay, k, x) for x in sig.v_abc])  # V, v_reported(m + d)
    ab = CLARKE[:2] @ v
    z = (ab[0] + 1j * ab[1]) * np.exp(1j * advance * sig.omega_e * sig.ts)
    zero = v.mean(axis=0)
    s3 = np.sqrt(3.0) / 2.0
    v_abc = np.stack((z.real, -0.5 * z.real + s3 * z.imag, -0.5 * z.real - s3 * z.imag)) + zero
    return Signals.from_abc(v_abc, sig.i_abc, sig.theta_e, sig.omega_e, sig.ts, sig.pole_pairs)


def path_of(meta: dict | None) -> tuple[float, float] | None:
    """(delay, advance) samples of a model's ``meta["voltage_path"]``, or None where it has none."""
    p = (meta or {}).get("voltage_path")
    if not p or p.get("delay_samples") is None:
        return None
    return float(p["delay_samples"]), float(p["advance_samples"])


def _error(preps, d: float, a: float, fit) -> float:
    """Held-out mean squared current error beyond the noise floor plus ``FLOOR_SHARE`` of the floor
    (a model within the noise is not better than one at a tenth of it), over the mean squared current, of
    the base model refitted (``fit(preps) -> Refit``) on ``preps`` with the path (d, a) applied."""
    from agent.workbench.fitting import heldout  # noqa: PLC0415

    moved = [replace(p, sig=apply_path(p.sig, d, a)) for p in preps]
    h = heldout(fit(moved).model, moved)
    if h["nrmse"] is None:
        return np.inf
    return float(h["nrmse"]["total"] ** 2 + (FLOOR_SHARE * h["noise_floor"]["total"]) ** 2)


def _scan(err, lo: float, hi: float) -> tuple[float, bool, dict]:
    """(best, pinned, {candidate: error}) of a 1-D scan of ``err`` over [lo, hi] at ``STEP``, refined
    at STEP/2 on both sides of the best and by a parabola through the best and its neighbours."""
    seen = {float(x): err(float(x)) for x in np.arange(lo, hi + 1e-9, STEP)}
    best = min(seen, key=seen.get)
    for x in (best - STEP / 2, best + STEP / 2):
        if lo <= x <= hi:
            seen[x] = err(x)
    best = min(seen, key=seen.get)
    far = [e for x, e in seen.items() if abs(x - best) >= 0.5 - 1e-9]
    inside = lo < best < hi  # a best on the range's edge wants the path beyond physics: not this path
    pinned = bool(inside and np.isfinite(seen[best]) and far and min(far) >= RISE * seen[best])
    left, right = best - STEP / 2, best + STEP / 2
    if left in seen and right in seen and all(np.isfinite([seen[left], seen[best], seen[right]])):
        curv = seen[left] - 2 * seen[best] + seen[right]
        if curv > 0:
            best += float(np.clip(0.5 * (seen[left] - seen[right]) / curv, -0.5, 0.5)) * STEP / 2
    return float(best), pinned, seen


def estimate_path(preps, fit) -> dict:
    """The voltage path of healthy records (``preps``: :class:`agent.workbench.fitting.Prepared`;
    ``fit(preps) -> Refit``: the base model's refit, as explain's control). Returns
    {"delay_samples", "advance_samples", "source": "records"} where the records pin the delay
    (the advance is 0 with ``"advance_pinned": False`` where they do not pin it), else
    {"delay_samples": None, "advance_samples": None, "note"} saying what record would pin it."""
    d, d_pinned, _ = _scan(lambda x: _error(preps, x, 0.0, fit), *D_RANGE)
    if not d_pinned:
        return {"delay_samples": None, "advance_samples": None,
                "note": NOT_PINNED.format(rise=RISE, what="delay")}
    a, a_pinned, _ = _scan(lambda x: _error(preps, d, x, fit), *A_RANGE)
    return {"delay_samples": d, "advance_samples": a if a_pinned else 0.0, "advance_pinned": a_pinned,
            "source": "records"}


def learn_path(baseline, records) -> dict:
    """:func:`estimate_path` of a baseline's healthy ``records`` with its base model refitted as
    explain's control is (the same prior, bounds and start), for ``model.meta["voltage_path"]``."""
    from agent.workbench.explain import _fe, drive_base, physical_prior, start_values  # noqa: PLC0415
    from agent.workbench.fitting import prepare, refit  # noqa: PLC0415

    model = baseline.model
    base, prior, start = drive_base(baseline), physical_prior(baseline), start_values(model)
    have = tuple(model.meta.get("effects", []))

    def fit(preps):
        return refit(preps, model.form, _fe(preps), have, start, max_nfev=SCAN_NFEV, base=base, prior=prior)

    return estimate_path(prepare(records, baseline.profile), fit)
