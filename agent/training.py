"""Training data is checked before it becomes a baseline (``identify``, ``learn``, ``model add-effect``).

A baseline says what healthy looks like at one operating point; records that are not that make
every later decision quietly wrong (thresholds and cluster widened until a fault reads normal).
:func:`check_training` refuses, with one line naming the files:

* **spread**: operating points that spread beyond the operating-point tolerance the agent uses to
  schedule a baseline (:class:`agent.library.Schedule`: +-2 Hz fe, +-5 %-points load): the records
  belong to several baselines;
* **fault evidence**: a record that reads as faulty (the diagnosis's rule at stricter levels: a
  sideband pair above centre + :data:`GUARD_SIGMA` spread in every window, where TH3 is + 3, or a
  cluster point beyond the :data:`GUARD_CONFIDENCE` region)

  - against the baseline being replaced, when the record is at that baseline's operating point;
    and the set as a whole when at least half of its records (and 2) read a spectrum warning at the
    diagnosis's own level (TH3) against it: one healthy record in many does, most of a set do not;
  - against the thresholds and cluster learned from the *other* records (leave one out, with the
    new model), when there are at least :data:`LOO_MIN_RECORDS` records.

  The levels are stricter than the diagnosis's (a healthy record lies outside a 95 % region one
  time in twenty) because every record of a set is read and healthy sets must pass almost always (docs/method.md, "Training data is checked", has the measured rate).

``accept_fault_evidence`` learns from records with fault evidence anyway; the caller records it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from agent.baseline import Baseline, Cluster, Thresholds, TrainingRecord, centre_spread, residual_spectra
from agent.errors import InputError
from agent.identify import cluster_point, operating_point
from agent.library import Schedule
from agent.model import Signals
from agent.spectrum import envelope

#: a sideband pair reads as a fault when both lines stand above centre + GUARD_SIGMA spread in every
#: window (the diagnosis's warning, TH3, is centre + 3 spread)
GUARD_SIGMA = 5.0
#: confidence of the cluster region that the checks read a record against (the diagnosis uses 95 %)
GUARD_CONFIDENCE = 0.9999
#: the set as a whole: when at least this share of the records (and 2) read a spectrum warning at the
#: diagnosis's own level (TH3, SET_SIGMA) against the baseline they replace, they are refused
SET_SHARE, SET_SIGMA = 0.5, 3.0
#: the leave-one-out check needs this many records (the cluster of the others needs 4 points)
LOO_MIN_RECORDS = 5
#: the others' spectrum statistics are median / MAD: faulty records among the others must not hide one
#: another (the cluster's stay mean / covariance: the robust fit's trimmed covariance refused healthy
#: records when two faulty ones were among the others)
LOO_ROBUST = True
ACCEPT_FLAG = "--accept-fault-evidence"


def check_training(records: list[TrainingRecord], schedule: Schedule = Schedule(), *,
                   baseline: Baseline | None = None, replaced: Baseline | None = None, replaced_name: str = "",
                   accept_fault_evidence: bool = False) -> list[str]:
    """Refuse (``InputError``, one line naming the files) training ``records`` whose operating
    points spread beyond ``schedule``'s tolerance, or with fault evidence (module docstring):
    read by ``replaced`` (the baseline they replace, named ``replaced_name``) and, when
    ``baseline`` (the one learned from them) is given, by leave-one-out. With
    ``accept_fault_evidence`` the fault evidence is returned (one text per record) instead."""
    check_spread(records, schedule)
    name = replaced_name or "the baseline it replaces"
    seen = [_seen_by(replaced, rec, schedule) for rec in records]
    why: dict[str, list[str]] = {rec.source: [] for rec in records}
    for rec, by_replaced in zip(records, seen):
        why[rec.source] += [f"{name} reads {r}" for r in fault_reading(replaced, by_replaced)] if by_replaced else []
        why[rec.source] += [f"the other records' baseline reads {r}" for r in _left_out_reading(baseline, records, rec)]
    # the set as a whole: most records at the diagnosis's own warning level against the replaced baseline
    warned = {r.source: fault_reading(replaced, s, SET_SIGMA, None) for r, s in zip(records, seen) if s is not None}
    warned = {k: v for k, v in warned.items() if v}
    if len(warned) >= max(2, math.ceil(SET_SHARE * len(records))):
        for source, reasons in warned.items():
            why[source] += [f"{name} reads {r} (as it reads {len(warned)} of {len(records)} records)"
                            for r in reasons if not why[source]]
    findings = [f"{source} ({'; '.join(w)})" for source, w in why.items() if w]
    if findings and not accept_fault_evidence:
        raise InputError(f"fault evidence in the training records: {', '.join(findings)}: learn from healthy "
                         f"records (or {ACCEPT_FLAG} to learn from them anyway, recorded)")
    return findings


def check_spread(records: list[TrainingRecord], schedule: Schedule = Schedule()) -> None:
    """Refuse records whose loads or electrical frequencies spread beyond ``schedule``'s tolerance,
    naming them grouped by operating point (a new group where a record lies beyond the tolerance
    of its group's first)."""
    fe = np.array([r.operating_point["fe_hz"] for r in records])
    load = np.array([r.operating_point["load_pct"] for r in records])
    load_wide, fe_wide = np.ptp(load) > schedule.load_tol_pct, np.ptp(fe) > schedule.fe_tol_hz
    if not (load_wide or fe_wide):
        return
    what = ([f"load {load.min():.1f}-{load.max():.1f} % (tolerance {schedule.load_tol_pct:g} %-points)"]
            * bool(load_wide) + [f"fe {fe.min():.2f}-{fe.max():.2f} Hz (tolerance {schedule.fe_tol_hz:g} Hz)"]
            * bool(fe_wide))
    groups: list[list[int]] = []
    for j in np.lexsort((load, fe) if fe_wide else (fe, load)):
        first = groups[-1][0] if groups else None
        if (first is None or abs(load[j] - load[first]) > schedule.load_tol_pct
                or abs(fe[j] - fe[first]) > schedule.fe_tol_hz):
            groups.append([])
        groups[-1].append(int(j))

    def span(x, unit, digits):
        lo, hi = f"{x.min():.{digits}f}", f"{x.max():.{digits}f}"
        return f"{lo} {unit}" if lo == hi else f"{lo}-{hi} {unit}"

    each = "; ".join(f"load {span(load[g], '%', 1)}" + (f" fe {span(fe[g], 'Hz', 2)}" if fe_wide else "") + ": "
                     + ", ".join(records[j].source for j in g) for g in groups)
    raise InputError(f"the training records spread over {' and '.join(what)}, beyond one operating point: "
                     f"{each}; split them by operating point (one baseline each)")


def at_operating_point(baseline: Baseline, op: dict, schedule: Schedule = Schedule()) -> bool:
    """Whether ``op`` lies within ``schedule``'s tolerance of ``baseline``'s operating point."""
    bop = baseline.operating_point
    return (abs(op["fe_hz"] - bop["fe_hz"]) <= schedule.fe_tol_hz
            and abs(op["load_pct"] - bop["load_pct"]) <= schedule.load_tol_pct)


def training_record(baseline: Baseline, sig: Signals, source: str) -> TrainingRecord:
    """A record as ``baseline`` sees it: operating point, residual spectra (None when the record is
    shorter than one of its windows), cluster point."""
    m, th = baseline.model, baseline.thresholds
    amp = (residual_spectra(m, sig, th.window_s, th.freqs_hz[-1])[1]
           if sig.n >= int(round(th.window_s / sig.ts)) else None)
    point = cluster_point(sig, baseline.profile, m.form, m.extra_q, baseline.settings.get("prefilter_hz"))
    return TrainingRecord(source, operating_point(sig, baseline.profile), sig, amp, point)


def fault_reading(baseline: Baseline, rec: TrainingRecord, sigma: float = GUARD_SIGMA,
                  confidence: float | None = GUARD_CONFIDENCE) -> list[str]:
    """What reads as a fault in ``rec`` (its spectra and cluster point under ``baseline``'s model):
    a sideband pair above centre + ``sigma`` spread in every window, a cluster point beyond the
    ``confidence`` region (None: the cluster is not read). The diagnosis's own rule
    (:func:`agent.decision.decide`) at those levels."""
    from agent.decision import decide

    th, cl = baseline.thresholds, baseline.cluster
    guard = dataclasses.replace(  # TH3 = centre + 3 (sigma / 3) spread
        baseline, thresholds=dataclasses.replace(th, spread=th.spread * sigma / 3.0),
        cluster=dataclasses.replace(cl, limit=cl.limit_at(confidence) if confidence else np.inf))
    d = decide(guard, th.freqs_hz, rec.spectra, rec.point, rec.operating_point, rec.source)
    out = []
    if d.spectrum_state == "warning":
        lines = sorted({(p["family"], p["k"]) for p in d.peaks if p["level"] == "warning"})
        out.append(f"sidebands above {sigma:g} sigma at " + ", ".join(f"{f} k={k}" for f, k in lines))
    if d.cluster_state == "warning":
        out.append(f"its cluster point outside the {100 * confidence:g} % region (distance^2 "
                   f"{d.cluster['distance2']:.1f} > {d.cluster['limit']:.1f})")
    return out


def _seen_by(replaced: Baseline | None, rec: TrainingRecord, schedule: Schedule) -> TrainingRecord | None:
    """``rec`` as the baseline it replaces sees it, when that baseline covers its operating point
    and can read it (same sample rate, at least one window)."""
    if (replaced is None or replaced.unusable or rec.signals is None
            or not at_operating_point(replaced, rec.operating_point, schedule)):
        return None
    sig = rec.signals() if callable(rec.signals) else rec.signals
    if abs(replaced.model.ts - sig.ts) > 1e-9 * sig.ts:  # a model of another sample rate cannot read it
        return None
    seen = training_record(replaced, sig, rec.source)
    return None if seen.spectra is None else dataclasses.replace(seen, signals=None)


def _left_out_reading(baseline: Baseline | None, records: list[TrainingRecord], rec: TrainingRecord) -> list[str]:
    """``rec`` against thresholds and cluster learned from the other records with ``baseline``'s model."""
    if baseline is None or len(records) < LOO_MIN_RECORDS or rec.spectra is None:
        return []
    th, cl = baseline.thresholds, baseline.cluster
    others = [r for r in records if r is not rec and r.spectra is not None]
    if len(others) < LOO_MIN_RECORDS - 1:
        return []
    centre, spread = centre_spread(envelope(np.concatenate([r.spectra for r in others]), th.search_bins), LOO_ROBUST)
    rest = dataclasses.replace(
        baseline, thresholds=Thresholds(th.freqs_hz, centre, spread, th.window_s, LOO_ROBUST, th.search_bins),
        cluster=Cluster.fit(np.array([r.point for r in others]), cl.confidence, cl.region))
    return fault_reading(rest, rec)
