"""FDI decision (paper Table 4): residual-spectrum levels at the fault frequencies and the
parameter-cluster distance, combined into normal / caution / warning.

* spectrum: a fault line above TH3 is a warning, above TH2 a caution, in every window of the
  record (a stationary fault persists; a noise excursion does not). A transmission fault is a
  periodic torque disturbance that modulates the speed, so it raises *both* sidebands fe - k f and
  fe + k f; with ``rule="pair"`` (default) a sideband pair counts at the lower of its two levels,
  which keeps the false-alarm rate of 2-sigma thresholds at many lines low (docs/method.md has the
  measured rates). ``rule="line"`` is the paper's literal reading: the worst single line.
* cluster: outside the healthy region (Mahalanobis distance beyond the region's limit) is a warning.
* overall: the worse of the two.
* family verdict (``verdict``, and ``reason`` in words): the component most likely at fault, from
  all its sideband pairs together. A pair's evidence is its z, (magnitude - centre) / spread at the
  lower of its two lines, floored at 0; a family's score is the mean over its orders weighted 1/k
  (a defect's harmonics fall with order, so a line that is one family's low order is likelier
  that family's). Pairs on the same lines (at ratio 2 the driving gear's k=1 is the driven gear's
  k=2) count for both families and are listed once, under the higher-ranked family, with
  ``shared_with`` naming the others. Families are ranked by their level, then by the level of
  their *unshared* pairs (the lines only that component explains: a dry mesh's driven-gear ovality
  sits on the shared line, but its k=1 and k=3 are the driven gear's alone), then by score.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agent.baseline import Baseline, residual_spectra
from agent.evidence import K_MAX, STATES, AlarmConfig, feature_values, make_features
from agent.frequencies import fault_frequencies
from agent.identify import cluster_point, operating_point, record_signals
from agent.model import Signals
from agent.records import Record
from agent.sanity import not_running
from agent.spectrum import nearest_bin, peak_near

#: Relative distance of a record's operating point from the model's that earns a warning note.
FE_TOLERANCE, LOAD_TOLERANCE_PCT = 0.02, 5.0


def worst(*states: str) -> str:
    return max(states, key=STATES.index)


@dataclass
class Diagnosis:
    record: str
    state: str
    spectrum_state: str
    cluster_state: str
    peaks: list[dict]
    cluster: dict
    operating_point: dict
    notes: list[str] = field(default_factory=list)
    evidence: dict = field(default_factory=dict)  #: the alarm evidence of the record (agent.evidence)
    quality: str = "good"  #: "no_model" when the drive is not running (``reason`` says why)
    reason: str | None = None  #: why no diagnosis (quality not good), else the family verdict in words
    verdict: dict = field(default_factory=dict)  #: :func:`family_verdict` (the component most likely at fault)
    spectrum: tuple | None = field(default=None, repr=False)  #: (freqs Hz, amplitude per window) for plots

    def to_json(self) -> dict:
        return {"record": self.record, "state": self.state, "quality": self.quality, "reason": self.reason,
                "spectrum_state": self.spectrum_state, "cluster_state": self.cluster_state, "peaks": self.peaks,
                "cluster": self.cluster, "operating_point": self.operating_point, "notes": self.notes,
                "evidence": self.evidence, "verdict": self.verdict}


def _line_magnitudes(baseline: Baseline, freqs: np.ndarray, amp: np.ndarray, fe_hz: float):
    """Every fault line (family, k, Hz) within the spectrum, its magnitude in the window where it is
    lowest, the bin it was read at and its nearest bin; None when no line lies within it."""
    lines = [(family, line["k"], line["freq_hz"])
             for family, items in fault_frequencies(baseline.profile, fe_hz, K_MAX).items()
             for line in items if line["freq_hz"] <= freqs[-1]]
    if not lines:
        return None
    targets = np.array([f for _, _, f in lines])
    idx, _, mag = peak_near(freqs, np.atleast_2d(amp), targets, baseline.thresholds.search_bins)  # (windows, lines)
    weakest = np.argmin(mag, axis=0)  # the window where each line is lowest
    cols = np.arange(len(lines))
    return lines, mag[weakest, cols], idx[weakest, cols], nearest_bin(freqs, targets)


def spectrum_peaks(baseline: Baseline, freqs: np.ndarray, amp: np.ndarray, fe_hz: float) -> list[dict]:
    """Every fault line (family, k, both sidebands) with its magnitude, thresholds and level.

    ``amp`` is one spectrum (bins,) or one per window (n_windows, bins); with several windows a
    line's level is the one it held in *every* window (persistence) and its magnitude the smallest.
    A line's magnitude is the largest bin within ``search_bins`` of its frequency (``peak_near``).
    """
    return _peaks_of(baseline, freqs, _line_magnitudes(baseline, freqs, amp, fe_hz))


def _peaks_of(baseline: Baseline, freqs: np.ndarray, lines) -> list[dict]:
    """:func:`spectrum_peaks` from the lines :func:`_line_magnitudes` read."""
    if lines is None:
        return []
    lines, mag_min, bin_at, centre = lines
    th = baseline.thresholds
    th2, th3 = th.th2[centre], th.th3[centre]
    peaks = []
    for j, (family, k, f) in enumerate(lines):
        level = "warning" if mag_min[j] > th3[j] else "caution" if mag_min[j] > th2[j] else "normal"
        z = (mag_min[j] - th.centre[centre[j]]) / max(float(th.spread[centre[j]]), 1e-30)
        peaks.append({"freq_hz": round(float(freqs[bin_at[j]]), 4), "family": family, "k": k, "level": level,
                      "magnitude": float(mag_min[j]), "th2": float(th2[j]), "th3": float(th3[j]),
                      "target_hz": round(f, 4), "z": round(float(z), 3)})
    return peaks


def shared_pairs(profile, fe_hz: float, resolution_hz: float) -> dict[tuple[str, int], list[tuple[str, int]]]:
    """(family, k) -> the other (family, k) whose sideband pair lies on the same lines (within
    ``resolution_hz``, Hz), as the alarm features merge them (:func:`agent.evidence.make_features`)."""
    out: dict[tuple[str, int], list[tuple[str, int]]] = {}
    for feat in make_features(profile, fe_hz, resolution_hz, float("inf")):
        group = [(feat.family, feat.k), *feat.shared]
        for member in group:
            out[member] = [g for g in group if g != member]
    return out


def family_verdict(peaks: list[dict], shared: dict) -> dict:
    """The component most likely at fault from every line of :func:`spectrum_peaks` (module
    docstring; ``shared``: :func:`shared_pairs`): ``{"family": best or None, "families": [{"family",
    "score", "level", "pairs": [{"k", "z", "level", "shared_with"}]}] best first}``; ``family`` is
    None when no pair is above TH2."""
    pairs: dict[tuple[str, int], list[dict]] = {}
    for p in peaks:
        pairs.setdefault((p["family"], p["k"]), []).append(p)
    families = []
    for family in dict.fromkeys(f for f, _ in pairs):
        rows = []
        for k in sorted(k for f, k in pairs if f == family):
            lines = pairs[(family, k)]
            rows.append({"k": k, "z": round(max(min(p["z"] for p in lines), 0.0), 3),
                         "level": min((p["level"] for p in lines), key=STATES.index),
                         "shared_with": [f"{f} k={j}" for f, j in shared.get((family, k), [])]})
        weights = [1.0 / r["k"] for r in rows]
        score = sum(w * r["z"] for w, r in zip(weights, rows)) / sum(weights)
        families.append({"family": family, "score": round(score, 3),
                         "level": worst("normal", *(r["level"] for r in rows)),
                         "unshared_level": worst("normal", *(r["level"] for r in rows if not r["shared_with"])),
                         "pairs": rows})
    families.sort(key=lambda f: (f["level"] != "normal", STATES.index(f["unshared_level"]), f["score"]), reverse=True)
    best = families[0]["family"] if families and families[0]["level"] != "normal" else None
    return {"family": best, "families": families}


def verdict_text(verdict: dict) -> str:
    """The family verdict in one sentence (a diagnosis's ``reason``)."""
    fams = verdict["families"]
    if verdict["family"] is None:
        return "no fault family: no sideband pair above TH2"
    best, others = fams[0], fams[1:]
    raised = [f"k={r['k']}" for r in best["pairs"] if r["level"] != "normal"]
    shared = [f"k={r['k']} = {', '.join(r['shared_with'])}" for r in best["pairs"] if r["shared_with"]]
    return (f"{best['family']} most likely at fault (evidence {best['score']:.1f}, pairs {', '.join(raised)} "
            f"above TH2)" + "".join(f"; {f['family']} {f['score']:.1f}" for f in others)
            + (f"; shared lines: {'; '.join(shared)}" if shared else ""))


def _listed_once(flagged: list[dict], verdict: dict, shared: dict) -> list[dict]:
    """The flagged lines in the verdict's family order, a line shared by several families listed
    once (under the highest-ranked of them) with ``shared_with``."""
    rank = {f["family"]: j for j, f in enumerate(verdict["families"])}
    out = []
    for p in flagged:
        partners = shared.get((p["family"], p["k"]), [])
        if any(rank.get(f, 1 << 30) < rank.get(p["family"], 1 << 30) for f, _ in partners):
            continue  # listed under the family ranked above
        out.append({**p, "shared_with": [f"{f} k={j}" for f, j in partners]})
    return sorted(out, key=lambda p: (rank.get(p["family"], 1 << 30), p["k"], p["freq_hz"]))


def spectrum_decision(peaks: list[dict], rule: str = "pair") -> tuple[str, list[dict]]:
    """Spectrum state and the lines behind it (see the module docstring for ``rule``)."""
    if rule == "line":
        flagged = [p for p in peaks if p["level"] != "normal"]
        return worst("normal", *(p["level"] for p in flagged)), flagged
    if rule != "pair":
        raise ValueError(f"unknown spectrum rule {rule!r} (pair, line)")
    pairs: dict[tuple, list[dict]] = {}
    for p in peaks:
        pairs.setdefault((p["family"], p["k"]), []).append(p)
    state, flagged = "normal", []
    for lines in pairs.values():
        level = min((p["level"] for p in lines), key=STATES.index)
        if level != "normal":
            state = worst(state, level)
            flagged.extend(lines)
    return state, flagged


def diagnose(baseline: Baseline, record: Record) -> Diagnosis:
    """Table 4 decision for one record against a healthy baseline."""
    return assess(baseline, record_signals(record, baseline.profile), record.source)


def assess(baseline: Baseline, sig: Signals, source: str = "") -> Diagnosis:
    """Table 4 decision for dq signals (a record or a streamed span) against a baseline, in the
    agent's order: operating point (a drive that is not running is no diagnosis), residual
    spectra and cluster point, evidence, decision."""
    op = operating_point(sig, baseline.profile)
    idle = not_running(sig, baseline.profile)
    if idle is None and baseline.unusable is not None:
        idle = f"the model {baseline.unusable}"
    if idle is not None:
        return Diagnosis(source, "normal", "normal", "normal", [], {}, op, [], {}, "no_model", idle)
    m = baseline.model
    point = cluster_point(sig, baseline.profile, m.form, m.extra_q, baseline.settings.get("prefilter_hz"))
    freqs, amp = residual_spectra(m, sig, baseline.thresholds.window_s, baseline.thresholds.freqs_hz[-1])
    d = decide(baseline, freqs, amp, point, op, source)
    d.evidence = record_evidence(baseline, freqs, amp, point, op)
    d.spectrum = (freqs, amp)
    return d


def record_evidence(baseline: Baseline, freqs: np.ndarray, amp: np.ndarray, point, op: dict) -> dict:
    """The agent's alarm evidence of one record taken as one stretch: per feature (sideband pair)
    the stretch z, the largest single-window z and the one-window threshold at the default gross
    budget, the cluster z (docs/method.md, "Alarms")."""
    ev = baseline.evidence
    if ev is None:
        return {}
    y = feature_values(freqs, amp, baseline.profile, op["fe_hz"], ev.features, baseline.thresholds.search_bins)
    stretch, window = ev.stretch_z(y.mean(axis=0)), ev.window_z(y).max(axis=0)
    gross, _ = AlarmConfig().gross_thresholds(ev)
    out = {f.name: {"families": list(f.families), "stretch_z": round(float(a), 3), "window_z": round(float(b), 3),
                    "gross_threshold": round(float(g), 3)}
           for f, a, b, g in zip(ev.features, stretch, window, gross)}
    out["cluster"] = {"stretch_z": round(ev.cluster_z(point, op["input_power_pct"]), 3)}
    return out


def _resolution(freqs: np.ndarray) -> float:
    """The spectrum's bin spacing, Hz (0 for one bin)."""
    return float(freqs[1] - freqs[0]) if freqs.size > 1 else 0.0


def listed_peaks(baseline: Baseline, freqs: np.ndarray, amp: np.ndarray, fe_hz: float) -> list[dict]:
    """The flagged lines as :func:`decide` lists them (its ``peaks``), without the rest of its
    diagnosis: the family verdict that orders them is only worked out when a line is flagged (the
    streaming pipeline's display, every hop)."""
    lines = _line_magnitudes(baseline, freqs, amp, fe_hz)
    if lines is None or not np.any(lines[1] > baseline.thresholds.th2[lines[3]]):
        return []  # no line above its caution threshold: nothing flagged, by either rule
    peaks = _peaks_of(baseline, freqs, lines)
    flagged = spectrum_decision(peaks, baseline.settings.get("spectrum_rule", "pair"))[1]
    if not flagged:
        return []
    shared = shared_pairs(baseline.profile, fe_hz, _resolution(freqs))
    return _listed_once(flagged, family_verdict(peaks, shared), shared)


def decide(baseline: Baseline, freqs: np.ndarray, amp: np.ndarray, point: np.ndarray, op: dict,
           source: str = "") -> Diagnosis:
    """Table 4 from the residual spectra of the windows (n_windows, bins) and the cluster point."""
    peaks = spectrum_peaks(baseline, freqs, amp, op["fe_hz"])
    spectrum_state, flagged = spectrum_decision(peaks, baseline.settings.get("spectrum_rule", "pair"))
    shared = shared_pairs(baseline.profile, op["fe_hz"], _resolution(freqs))
    verdict = family_verdict(peaks, shared)
    d2 = baseline.cluster.distance2(point)
    cluster_state = "warning" if d2 > baseline.cluster.limit else "normal"
    return Diagnosis(
        record=source, state=worst(spectrum_state, cluster_state), spectrum_state=spectrum_state,
        cluster_state=cluster_state,
        peaks=_listed_once(flagged, verdict, shared),
        verdict=verdict, reason=verdict_text(verdict),
        cluster={"ts_over_lq": float(point[0]), "b_gt": float(point[1]), "distance2": d2,
                 "limit": baseline.cluster.limit, "confidence": baseline.cluster.confidence},
        operating_point=op, notes=operating_point_notes(baseline.operating_point, op))


def operating_point_notes(model_op: dict, op: dict) -> list[str]:
    """Warnings when a record's operating point is far from the one the baseline was learned at."""
    notes = []
    if abs(op["fe_hz"] - model_op["fe_hz"]) > FE_TOLERANCE * model_op["fe_hz"]:
        notes.append(f"operating point: fe {op['fe_hz']:.2f} Hz is far from the model's {model_op['fe_hz']:.2f} Hz")
    if abs(op["load_pct"] - model_op["load_pct"]) > LOAD_TOLERANCE_PCT:
        notes.append(f"operating point: load {op['load_pct']:.1f} % is far from the model's "
                     f"{model_op['load_pct']:.1f} %")
    return notes
