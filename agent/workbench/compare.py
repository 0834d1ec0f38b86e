"""``model compare``: how well a model reproduces records, and where and why it fails.

The fit figure is the workbench's one error figure (:func:`agent.workbench.fitting.heldout`,
docs/workbench.md "One error figure"): NRMSE on the held-out second part of each record, free run
beyond the channels' noise floor (or raw one-step with ``--one-step``), per axis (d, q), total and
per phase, and fit % = 100 (1 - NRMSE);
the same model on the same records gives the same figure here, in ``explain``, ``add-effect``,
``history`` and the report. An unstable free run has no figure, only a note. With several models
and operating points: a Table-5-like matrix. "Where": the phase-residual spectrum's largest peaks
labelled by harmonic order of fe (abc and dq), fault families and the effects with that signature;
the residual binned over electrical angle, phase current and time; the phase residuals' DC with its
batch-means t (an offset); whiteness and input cross-correlation of the one-step residual with a 99 %
band (MATLAB ``resid``), and its correlation with the voltage's sample-to-sample change (a delay).
A peak at a fault line or a harmonic of fe is reported at that line's exact frequency (``freq_hz``,
from :mod:`agent.frequencies`; ``bin_hz`` is the FFT bin it was found in). Each finding's
``effects`` are the ones its own evidence points to (none when the evidence is absent).
"""

from __future__ import annotations

import numpy as np

from agent.baseline import residual_spectra
from agent.decision import operating_point_notes
from agent.effects import EFFECTS
from agent.frames import dq_to_abc
from agent.frequencies import fault_frequencies
from agent.workbench.fitting import Prepared, fit_pct, flux_adapted, heldout

MAX_LAG = 40  #: samples, correlation lags
Z99 = 2.576  #: two-sided 99 % normal quantile
BATCHES, T99_BATCHES = 20, 2.861  #: batch means of a phase residual's DC, and the two-sided 99 % t quantile (19 dof)
#: |correlation| of the q residual with the voltage's sample-to-sample change (lags -1..1) that
#: reads as a voltage delay. On the rig simulator: delay 1 sample 0.83, 0.3 samples 0.30; none
#: (healthy, severe wear, current offset 0.02-0.1 A, dead time, flux harmonics, gain mismatch) 0.024 at most
DELAY_R = 0.05
N_PEAKS = 6
ANGLE_BINS, CURRENT_BINS, TIME_BINS = 36, 24, 10


def figures(model, preps: list[Prepared]) -> dict:
    """{"free_run": {nrmse, fit_pct, noise_floor}, "one_step": {nrmse, fit_pct}, "stable", "note"?}: the one
    figure (the free run's beyond the channels' noise floor, which it also gives)."""
    h = heldout(model, preps)
    out = {"free_run": {"nrmse": h["nrmse"], "fit_pct": fit_pct(h["nrmse"]), "noise_floor": h["noise_floor"]},
           "one_step": {"nrmse": h["one_step"], "fit_pct": fit_pct(h["one_step"])}, "stable": h["stable"]}
    if not h["stable"]:
        out["note"] = h["note"]
    return out


def _total(model, preps):
    n = heldout(model, preps)["nrmse"]
    return None if n is None else n["total"]


def coverage(baseline, preps: list[Prepared]) -> dict:
    """Which operating points the records cover, and how far they are from the model's."""
    op = baseline.operating_point
    points = [{"record": p.source, "fe_hz": p.op["fe_hz"], "load_pct": p.op["load_pct"],
               "notes": operating_point_notes(op, p.op)} for p in preps]
    loads = [p.op["load_pct"] for p in preps]
    fes = [p.op["fe_hz"] for p in preps]
    return {"model": {"fe_hz": op.get("fe_hz"), "load_pct": op.get("load_pct")}, "records": points,
            "load_pct_range": [min(loads), max(loads)], "fe_hz_range": [min(fes), max(fes)],
            "far": [p["record"] for p in points if p["notes"]]}


def table(models: dict, preps: list[Prepared]) -> list[dict]:
    """Rows: records grouped by operating point (fe 0.5 Hz, load 5 %); the held-out free-run NRMSE
    per model (None: unstable)."""
    groups: dict[tuple, list[Prepared]] = {}
    for p in preps:
        groups.setdefault((round(p.op["fe_hz"] * 2) / 2, 5 * round(p.op["load_pct"] / 5)), []).append(p)
    return [{"fe_hz": fe, "load_pct": load, "records": len(ps),
             "nrmse": {name: _total(b.model, ps) for name, b in models.items()}}
            for (fe, load), ps in sorted(groups.items())]


def _label(f: float, fe: float, df: float, families: dict) -> tuple[str, list[str], float | None]:
    """Likely origin of a residual line in the bin at ``f`` Hz: harmonic of fe (abc and dq), fault
    family; and the exact frequency (Hz) of what it was matched to (a fault line from
    :mod:`agent.frequencies` before a harmonic; None: neither)."""
    labels, effects, exact = [], [], None
    k = int(round(f / fe))
    if abs(f - k * fe) <= 1.5 * df:
        labels.append("DC" if k == 0 else f"{k} fe in abc (dq: {abs(k - 1)} fe)")
        effects += [e.id for e in EFFECTS.values() if k in e.abc_orders or abs(k - 1) in e.dq_orders]
        exact = k * fe
    lines = sorted(((abs(f - line["freq_hz"]), fam, line) for fam, items in families.items() for line in items
                    if abs(f - line["freq_hz"]) <= 1.5 * df), key=lambda x: x[0])
    for _, fam, line in lines:
        labels.append(f"{fam} k={line['k']} sideband")
        effects += ["speed_ripple"] if fam == "gear_driving" and line["k"] == 1 else []
    if lines:
        exact = lines[0][2]["freq_hz"]
    return "; ".join(labels) or f"{f / fe:.2f} fe (no harmonic or fault line)", sorted(set(effects)), exact


def _batch_t(x: np.ndarray, batches: int = BATCHES) -> float:
    """t statistic of the mean of ``x`` by batch means (robust to the samples' autocorrelation)."""
    means = np.array([b.mean() for b in np.array_split(x, batches)])
    return float(means.mean() / max(means.std(ddof=1) / np.sqrt(batches), 1e-300))


def _corr(x: np.ndarray, y: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation r_xy(lag) = E[x(k) y(k - lag)] / (sigma_x sigma_y)."""
    x, y = x - x.mean(), y - y.mean()
    n, s = x.size, np.sqrt(np.sum(x**2) * np.sum(y**2)) + 1e-300
    return np.array([np.sum(x[max(lag, 0):n + min(lag, 0)] * y[max(-lag, 0):n - max(lag, 0)]) for lag in lags]) / s


def where(baseline, preps: list[Prepared], preds: list[np.ndarray]) -> tuple[list[dict], dict]:
    """Findings (JSON) and the arrays behind them (for the report's plots)."""
    model, prof, th = baseline.model, baseline.profile, baseline.thresholds
    fe = float(np.mean([p.op["fe_hz"] for p in preps]))
    res = [p.sig.i_dq - y for p, y in zip(preps, preds)]
    found, data = [], {"fe_hz": fe}
    # 1. residual spectrum of phase a, windows as the thresholds' when the records allow
    n_min = min(p.sig.n for p in preps) * preps[0].sig.ts
    window = th.window_s if n_min >= th.window_s else n_min
    with np.errstate(all="ignore"):  # an unstable model's windows diverge: their lines are left out
        spec = [residual_spectra(model, p.sig, window, th.freqs_hz[-1]) for p in preps]
        freqs, amp = spec[0][0], np.nan_to_num(np.vstack([a for _, a in spec]).mean(axis=0), nan=0.0, posinf=0.0)
    same_grid = freqs.size == th.freqs_hz.size
    data.update(freqs=freqs, amp=amp, th2=th.th2 if same_grid else None, th3=th.th3 if same_grid else None)
    df = freqs[1] - freqs[0]
    floor = np.median(amp)
    is_peak = (amp[1:-1] >= amp[:-2]) & (amp[1:-1] >= amp[2:]) & (amp[1:-1] > 4 * floor)
    idx = 1 + np.flatnonzero(is_peak)
    idx = idx[np.argsort(amp[idx])[::-1][:N_PEAKS]]
    families = fault_frequencies(prof, fe, 3)
    peaks = []
    for i in sorted(idx, key=lambda i: -amp[i]):
        label, effects, exact = _label(freqs[i], fe, df, families)
        over = "above TH3" if same_grid and amp[i] > th.th3[i] else "above TH2" if same_grid and amp[i] > th.th2[i] else ""
        peaks.append({"freq_hz": float(freqs[i] if exact is None else exact), "bin_hz": float(freqs[i]),
                      "amplitude_a": float(amp[i]), "label": label, "effects": effects, "threshold": over})
    data["peaks"] = peaks
    found += [{"kind": "spectrum_peak", **pk} for pk in peaks]
    # 2. binned residual: over electrical angle, phase-a current, time
    theta = np.concatenate([np.mod(p.sig.theta_e, 2 * np.pi) for p in preps])
    r = np.hstack(res)
    rms = float(np.sqrt(np.mean(np.sum(r**2, axis=0))))
    ang = np.minimum((theta / (2 * np.pi) * ANGLE_BINS).astype(int), ANGLE_BINS - 1)
    by_angle = np.array([[np.bincount(ang, r[ax], ANGLE_BINS)[b] for b in range(ANGLE_BINS)] for ax in (0, 1)])
    by_angle /= np.maximum(np.bincount(ang, minlength=ANGLE_BINS), 1)
    r_abc = np.hstack([dq_to_abc(x, p.sig.theta_e) for x, p in zip(res, preps)])
    ra = r_abc[0]
    ia = np.concatenate([p.sig.i_abc[0] for p in preps])
    dc = r_abc.mean(axis=1)
    dc_t = np.array([_batch_t(x) for x in r_abc])
    offset = bool(np.any(np.abs(dc_t) > T99_BATCHES))
    edges = np.linspace(ia.min(), ia.max(), CURRENT_BINS + 1)
    cb = np.clip(np.digitize(ia, edges) - 1, 0, CURRENT_BINS - 1)
    by_current = np.bincount(cb, ra, CURRENT_BINS) / np.maximum(np.bincount(cb, minlength=CURRENT_BINS), 1)
    step = float(np.mean(ra[ia > 0]) - np.mean(ra[ia < 0]))
    slope = float(np.polyfit(ia, ra, 1)[0])
    by_time = np.array([[np.sqrt(np.mean(np.sum(c**2, axis=0))) for c in np.array_split(x, TIME_BINS, axis=1)]
                        for x in res])
    trend = float(np.polyfit(np.arange(TIME_BINS), by_time.mean(axis=0), 1)[0] * (TIME_BINS - 1))
    data.update(angle_bins=by_angle, current_edges=edges, current_bins=by_current, time_bins=by_time)
    found += [
        {"kind": "angle", "summary": f"mean d/q residual varies over the electrical angle by "
         f"{np.ptp(by_angle[0]):.4f} / {np.ptp(by_angle[1]):.4f} A (residual RMS {rms:.4f} A)",
         "ptp_a": [float(np.ptp(by_angle[0])), float(np.ptp(by_angle[1]))],
         "effects": ["current_offset", "flux_harmonics", "inverter_deadtime"]},
        {"kind": "current", "summary": f"phase-a residual: step {step:+.4f} A across the current's sign "
         f"(dead time), slope {slope:+.5f} A/A (gain), mean {np.mean(ra):+.4f} A (offset)",
         "sign_step_a": step, "slope": slope, "mean_a": float(np.mean(ra)),
         "effects": ["inverter_deadtime", "current_gain_mismatch"]},
        {"kind": "offset", "summary": "phase residual DC a/b/c " + "/".join(f"{x:+.4f}" for x in dc) + " A (t "
         + "/".join(f"{x:.1f}" for x in dc_t) + f" over {BATCHES} batches): "
         + ("a current-sensor offset" if offset else f"none (|t| <= {T99_BATCHES})"),
         "dc_a": dc.tolist(), "t": dc_t.tolist(), "effects": ["current_offset"] if offset else []},
        {"kind": "time", "summary": f"residual RMS changes by {trend:+.4f} A from the first to the last tenth "
         f"of the records", "trend_a": trend, "effects": ["resistance_drift"]},
    ]
    # 3. whiteness of the one-step residual and its cross-correlation with the inputs (MATLAB resid)
    e1 = np.hstack([p.sig.i_dq - model.one_step(p.sig) for p in preps])[:, 1:]
    v = np.hstack([p.sig.v_dq for p in preps])[:, :-1]
    lags = np.arange(-MAX_LAG, MAX_LAG + 1)
    band = Z99 / np.sqrt(e1.shape[1])
    auto = np.array([_corr(e1[ax], e1[ax], lags[MAX_LAG + 1:]) for ax in (0, 1)])
    cross = np.array([_corr(e1[1], v[ax], lags) for ax in (0, 1)])
    # a delay makes the residual follow the voltage's sample-to-sample change, which carries no slow
    # component: an offset (or a fault's ripple) correlates with v at every lag alike, never with dv
    dv = np.hstack([np.zeros((2, 1)), np.diff(v, axis=1)])
    delay_r = float(np.max(np.abs(_corr(e1[1], dv[1], np.arange(-1, 2)))))
    delay = delay_r > DELAY_R
    slow = not delay and np.max(np.abs(cross)) > band
    data.update(lags=lags, auto=auto, cross=cross, band=band)
    found += [
        {"kind": "whiteness", "summary": f"one-step residual autocorrelation outside the 99 % band at "
         f"{np.mean(np.abs(auto[0]) > band):.0%} (d) / {np.mean(np.abs(auto[1]) > band):.0%} (q) of lags 1..{MAX_LAG}",
         "band": band, "outside": [float(np.mean(np.abs(a) > band)) for a in auto],
         "max_abs": [float(np.max(np.abs(a))) for a in auto]},
        {"kind": "cross_correlation", "summary": f"q residual vs v_d / v_q: max |r| {np.max(np.abs(cross[0])):.3f} / "
         f"{np.max(np.abs(cross[1])):.3f} (band {band:.3f}); vs the sample-to-sample change of v_q at lags -1..1: "
         f"{delay_r:.3f} ({'a voltage delay' if delay else f'no delay: <= {DELAY_R}'})"
         + ("; the correlation is slow, alike at every lag: " + ("the phase residual's DC (current offset)" if offset
            else "a slow component common to residual and voltage, not a delay") if slow else ""),
         "max_abs": [float(np.max(np.abs(c))) for c in cross], "delay_r": delay_r,
         "effects": (["voltage_delay"] if delay else []) + (["current_offset"] if slow and offset else [])},
    ]
    return found, data


def compare(baseline, preps: list[Prepared], one_step: bool = False, others: dict | None = None,
            name: str = "model") -> tuple[dict, dict]:
    """The CONTRACT document of ``model compare`` (free-run unless ``one_step``) and plot data;
    ``others`` ({name: baseline}) are compared on the same records under their names, ``name``
    being the first model's: ``models`` holds each one's held-out free-run NRMSE (total) over the
    whole record set, ``table`` per operating point."""
    model = baseline.model
    figs = figures(model, preps)
    mode = "one_step" if one_step else "free_run"
    with np.errstate(all="ignore"):
        free = [flux_adapted(model, p) for p in preps]
    shown = free if figs["stable"] else [model.one_step(p.sig) for p in preps]
    with np.errstate(all="ignore"):
        found, data = where(baseline, preps, [np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0) for y in shown])
    doc = {"nrmse": figs[mode]["nrmse"], "fit_pct": figs[mode]["fit_pct"], "mode": mode,
           "noise_floor": figs["free_run"]["noise_floor"],
           "modes": {k: figs[k] for k in ("free_run", "one_step")}, "stable": figs["stable"], "where": found,
           "table": table({name: baseline, **(others or {})}, preps), "coverage": coverage(baseline, preps),
           "records": [p.source for p in preps]}
    free_total = figs["free_run"]["nrmse"]
    doc["models"] = {name: None if free_total is None else free_total["total"],
                     **{n: _total(b.model, preps) for n, b in (others or {}).items()}}
    if not figs["stable"]:
        doc["note"] = figs["note"]
    data["traces"] = [(preps[0].sig, shown[0], name)]
    for other, b in (others or {}).items():
        with np.errstate(all="ignore"):
            data["traces"].append((preps[0].sig, flux_adapted(b.model, preps[0]), other))
    data["split"] = preps[0].split
    return doc, data
