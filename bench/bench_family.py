"""The workbench over a randomised family of drives (bench.family): the customer's drive, not ours.

    python -m bench.bench_family [--drives N] [--null N] [--seconds S] [--jobs J] [--short]

Per drive (every attribute drawn, ``bench.family.draw_drive``): a baseline identified from four
healthy records at 80 % load, as a user starts; then, for each library effect drawn from its whole
family (``bench.family.draw_effect``), four records at 40/60/90/100 % load with it hidden, and
``model explain`` on them; and four such records with nothing hidden (the null drive). The drive's
own voltage path (its hold, computation delay and reporting) is in every record: it is the drive,
not a hidden effect. Per effect:

* top-1: the true effect first, of all drives and of those whose records can reveal it (where they
  cannot, the effect leaves nothing in the records to rank);
* significant: of the drives whose records can reveal it (``bench.family.revealable``: physics,
  not the workbench's power); where they cannot, whether explain said so;
* gain: NRMSE of the best refit with a wrong effect over the true effect's (target >= 2);
* the headline parameter's error (target <= 20 %; a delay against max(|d|, 1 sample));
* a different effect claimed significant: counted and listed, never acceptable.

Null drives: how many claim anything, with the 95 % upper bound (Clopper-Pearson) of the rate.
Misses are grouped by the drive attribute that concentrates them. Results are appended per drive to
bench/results/family_<S>s.jsonl and a rerun skips drives already there (nothing is lost when a run
is cut short); the markdown table goes to stdout (docs/benchmarks.md, "Workbench on a family of
drives") and the power plot (detected fraction against the hidden effect's size beyond the noise)
to docs/img/family_power.png.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import re
import sys
import time
import traceback
from collections import Counter, defaultdict
from dataclasses import asdict
from pathlib import Path

import numpy as np
import scipy.stats

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
BASE_LOAD, TEST_LOADS = 80.0, (40.0, 60.0, 90.0, 100.0)
FIRST_SEED = 20_000
#: the headline figure of each effect: the report keys compared with bench.family.truth's
HEADLINE = {"current_offset": ("offset_A",), "current_gain_mismatch": ("gain_b", "gain_c"),
            "resistance_drift": ("dR_dt_ohm_per_s",), "voltage_delay": ("delay_samples",),
            "flux_harmonics": ("psi_5_Wb", "psi_7_Wb"), "inverter_deadtime": ("U_dt_V",),
            "magnetic_saturation": ("lq_drop_at_rated",), "speed_ripple": ("omega_e_ripple_rad_s",)}
#: the figure compared where the headline is not said because the records pin only it (a shared
#: sensor's offset: the voltage R_s o that holds it, agent.effects.current_offset.through_resistance)
PINNED_INSTEAD = {"current_offset": ("offset_voltage_V",)}
#: categorical drive attributes misses are grouped by (numeric ones are split at their median)
ATTRIBUTES = ("inverter", "voltage_hold", "computation_delay", "angle_compensation", "current_reference",
              "mechanics", "excitation", "voltage_source", "command_logged_as", "current_sampling", "encoder",
              "updates_per_carrier", "pole_pairs", "rate_hz", "saliency", "rated_power_w")
GAIN_MIN, ERROR_MAX = 2.0, 0.20


PHASE_MAX = 0.2  #: rad: a harmonic's phase said further off than this is wrong, as a magnitude 20 % off
HARMONIC_KEY = re.compile(r"^(psi|phase)_(\d+)_(Wb|rad)$")


def figure_errors(said: dict, true: dict, bound: dict | None = None) -> dict:
    """Every figure explain said (not None) that the truth has, key -> (error, outside): its error
    (wrong above ``ERROR_MAX``), relative for a magnitude, a delay's
    (and its sum with the advance, ``rotation_samples``) against max(|d|, 1 sample), a harmonic's
    phase as a share of ``PHASE_MAX`` times ``ERROR_MAX`` (a harmonic's figures only where it is at
    least a fifth of the largest: a smaller one's phase measures nothing); and whether the truth lies
    outside the bound explain gave (``bound``: its ``params_bound``; None where it gave none)."""
    out = {}
    bound = bound or {}
    amps = [v for k, v in true.items() if (m := HARMONIC_KEY.match(k)) and m[1] == "psi"]
    for key, value in said.items():
        if value is None:
            continue
        if key in ("delay_samples", "advance_samples", "rotation_samples"):
            t = (true.get("delay_samples", 0.0) + true.get("advance_samples", 0.0) if key == "rotation_samples"
                 else true.get(key))
            if t is None:
                continue
            off, err = abs(value - t), abs(value - t) / max(abs(t), 1.0)
        elif m := HARMONIC_KEY.match(key):
            if key not in true or true.get(f"psi_{m[2]}_Wb", 0.0) < 0.2 * max(amps, default=0.0):
                continue
            off = abs(float(np.angle(np.exp(1j * (value - true[key]))))) if m[1] == "phase" else abs(value - true[key])
            err = off / PHASE_MAX * ERROR_MAX if m[1] == "phase" else off / abs(true[key])
        elif isinstance(true.get(key), float) and true[key] != 0.0:
            off = abs(value - true[key])
            err = off / abs(true[key])
        else:
            continue
        out[key] = (err, None if bound.get(key) is None else bool(off > bound[key]))
    return out


def parameter_error(effect: str, fitted: dict, true: dict) -> float | None:
    """The headline error: the largest of :func:`figure_errors` over the effect's headline keys (a
    mix of harmonics: each one at least a fifth of the largest; a delay against max(|d|, 1 sample)).
    None where the effect reports no value (not identifiable)."""
    keys = HEADLINE[effect]
    if any(fitted.get(k) is None for k in keys):
        keys = PINNED_INSTEAD.get(effect, ())
    if not keys or any(fitted.get(k) is None for k in keys):
        return None
    return max((e for e, _ in figure_errors({k: fitted[k] for k in keys}, true).values()), default=None)


def judge(doc: dict, effect: str, true: dict, revealable: tuple[bool, str]) -> dict:
    """One drive's figures for one hidden effect from explain's document."""
    rows = doc["candidates"]
    names = [c["effect"] for c in rows]
    sig = [c["effect"] for c in rows if c["significant"]]
    out = {"effect": effect, "truth": true, "revealable": revealable[0], "why": revealable[1],
           "answer": doc.get("note"), "significant_effects": sig, "wrong_claims": [e for e in sig if e != effect],
           "nrmse_control": doc["nrmse_control"], "noise_floor": doc["noise_floor"], "seconds": doc["seconds"],
           "records_named": records_named(doc), "candidates": candidates(doc)}
    if effect not in names:  # no ranking (the records carry no dynamics, or the control is unstable)
        return {**out, "rank": None, "top": None, "significant": False, "gain": None, "error": None, "fitted": None}
    row = rows[names.index(effect)]
    wrong = [c["nrmse_after"] for c in rows if c["effect"] != effect and c["nrmse_after"] is not None]
    fitted = {**(row.get("unpinned_params") or {}), **{k: v for k, v in row["params"].items() if v is not None}}
    gain = (min(wrong) / max(row["nrmse_after"], 1e-12)) if wrong and row["nrmse_after"] is not None else None
    return {**out, "rank": names.index(effect) + 1, "top": names[0], "significant": bool(row["significant"]),
            "p_value": row["p_value"], "gain": gain, "fitted": fitted, "said": dict(row["params"]),
            "bound": row.get("params_bound"),
            "error": parameter_error(effect, {k: v for k, v in row["params"].items()}, true),
            "identifiable": bool(row["identifiable"]), "note": row.get("note", "")}


def records_named(doc: dict) -> dict:
    """Effect -> how many records like these explain said would settle it (its ``records_needed``),
    for every candidate that explained enough but missed Holm's level."""
    return {c["effect"]: c["records_needed"] for c in doc["candidates"] if "records_needed" in c}


def candidates(doc: dict) -> list[dict]:
    """Every candidate of a set in explain's order, in brief: share explained, p, and its gates."""
    keys = ("effect", "explained_fraction", "p_value", "p_value_direct", "test", "significant", "identifiable",
            "at_bound", "negligible", "contradicted")
    return [{k: c.get(k) for k in keys} for c in doc["candidates"]]


def baseline(drive, prof, seconds: float):
    """The user's first step: a baseline identified from four healthy records at ``BASE_LOAD``."""
    from agent.baseline import identify_baseline
    from bench.family import simulate

    return identify_baseline([simulate(drive, {}, BASE_LOAD, seconds, seed=100 + j) for j in range(4)], prof,
                             window_s=min(0.5, seconds / 2))


def hidden_records(drive, hidden: dict, seconds: float, n: int = len(TEST_LOADS)) -> list:
    """``n`` records with ``hidden`` effects at ``TEST_LOADS`` in turn (the first four are the set's own)."""
    from bench.family import simulate

    return [simulate(drive, hidden, TEST_LOADS[j % len(TEST_LOADS)], seconds, seed=200 + j) for j in range(n)]


def run_drive(args: tuple) -> dict:
    """Everything for one drive: its baseline, the null set and (``with_effects``) one set per effect."""
    seed, seconds, with_effects, effects, timing, nameplate = args
    from agent.workbench.explain import explain
    from agent.workbench.fitting import prepare
    from bench.family import draw_drive, draw_effect, profile, revealable, truth

    t0 = time.perf_counter()
    drive = draw_drive(seed)
    prof = profile(drive, nameplate=nameplate, timing=timing)
    out = {"seed": seed, "timing": timing, "nameplate": nameplate,
           "drive": {k: v for k, v in asdict(drive).items() if k in ATTRIBUTES},
           "saliency": drive.lq_h / drive.ld_h, "rows": []}
    out["drive"]["saliency"] = out["saliency"]
    try:
        base = baseline(drive, prof, seconds)
        sets = [("null", {})] + ([(e, {e: draw_effect(drive, e, seed)}) for e in effects] if with_effects else [])
        for name, hidden in sets:
            recs = hidden_records(drive, hidden, seconds)
            doc = explain(base, prepare(recs, prof))
            if name == "null":
                out["null"] = {"claims": [c["effect"] for c in doc["candidates"] if c["significant"]],
                               "answer": doc.get("note"), "nrmse_control": doc["nrmse_control"],
                               "noise_floor": doc["noise_floor"], "records_named": records_named(doc),
                               "candidates": candidates(doc)}
            else:
                out["rows"].append(judge(doc, name, truth(drive, name, hidden[name], recs),
                                         revealable(drive, name, TEST_LOADS)))
    except Exception as err:  # a crash is a finding of its own: kept with its traceback, the run goes on
        out["error"] = f"{type(err).__name__}: {err}"
        out["traceback"] = traceback.format_exc()
    out["seconds"] = time.perf_counter() - t0
    return out


def run(n_drives: int, n_null: int, seconds: float, jobs: int, effects, say=print, path: Path | None = None,
        timing: bool = True, nameplate: bool = False) -> list:
    """Run (or resume) the family: drives FIRST_SEED.. with effects for the first ``n_drives``,
    null sets for the first max(n_null, n_drives); results appended to ``path`` (JSON lines).
    ``timing``: each profile states the drive's voltage path (as the drive's documentation gives it),
    else the workbench takes the voltage as reported; ``nameplate``: each profile has the nameplate
    (R_s, psi_m, L_d, L_q within 5 %)."""
    path = path or RESULTS / f"family_{seconds:g}s{'' if timing else '_reported'}{'_nameplate' if nameplate else ''}.jsonl"
    path.parent.mkdir(parents=True, exist_ok=True)
    done = {}
    if path.exists():
        for line in path.read_text().splitlines():
            r = json.loads(line)
            done[r["seed"]] = r
    total = max(n_null, n_drives)
    todo = [(FIRST_SEED + j, seconds, j < n_drives, tuple(effects), timing, nameplate) for j in range(total)
            if FIRST_SEED + j not in done or (j < n_drives and not done[FIRST_SEED + j]["rows"]
                                               and "error" not in done[FIRST_SEED + j])]
    say(f"family: {total} drives ({n_drives} with {len(effects)} effects each), {len(done)} done before, "
        f"{len(todo)} to run on {jobs} process(es)")
    t0 = time.perf_counter()
    with open(path, "a") as f, multiprocessing.get_context("spawn").Pool(jobs) as pool:
        for k, r in enumerate(pool.imap_unordered(run_drive, todo), start=1):
            f.write(json.dumps(r, default=float) + "\n")
            f.flush()
            done[r["seed"]] = r
            left = (time.perf_counter() - t0) / k * (len(todo) - k)
            say(f"drive {r['seed']}: {'ERROR ' + r['error'] if 'error' in r else summary(r)} "
                f"({r['seconds']:.0f} s; {k}/{len(todo)}, about {left / 60:.0f} min left)")
    return [done[FIRST_SEED + j] for j in range(total) if FIRST_SEED + j in done]


def summary(r: dict) -> str:
    null = r.get("null", {})
    parts = [f"null claims {null.get('claims') or 'nothing'}"]
    for row in r["rows"]:
        ok = "ok" if row["rank"] == 1 and (row["significant"] or not row["revealable"]) else "MISS"
        parts.append(f"{row['effect']} {ok} (rank {row['rank']}, sig {row['significant']}, "
                     f"gain {row['gain'] or 0:.2g}, err {'n/a' if row['error'] is None else format(row['error'], '+.0%')})")
    return "; ".join(parts)


def upper95(k: int, n: int) -> float:
    """Clopper-Pearson one-sided 95 % upper bound of a rate seen k times in n."""
    return 1.0 if k >= n else float(scipy.stats.beta.ppf(0.95, k + 1, n - k))


def _attr_value(drive: dict, key: str, medians: dict):
    v = drive.get(key)
    if key in medians:
        return f"{'<' if v < medians[key] else '>='} {medians[key]:.3g}"
    return v


def misses_by_attribute(rows: list[tuple[dict, dict]], alpha: float = 0.05) -> list[str]:
    """The attribute values that concentrate the misses, as "attribute=value: misses/drives against
    misses/drives elsewhere (p)": each value's misses against the other drives' by Fisher's exact
    test (two-sided; one drive, one set: independent), kept where p < ``alpha`` and the value's
    miss rate is the higher, most significant first; marked "(holds over all N values)" where p
    stays below ``alpha`` / N, N the attribute values tested (Bonferroni): the others are leads, not
    findings. Numeric attributes are split at their median."""
    if not rows:
        return []
    medians = {k: float(np.median([d[k] for d, _ in rows])) for k in ATTRIBUTES
               if all(isinstance(d.get(k), float) for d, _ in rows)}  # numeric attributes split at their median
    misses, total = sum(m for _, m in rows), len(rows)
    tested = []
    for key in ATTRIBUTES:
        groups = defaultdict(lambda: [0, 0])
        for d, miss in rows:
            g = groups[_attr_value(d, key, medians)]
            g[0] += miss
            g[1] += 1
        for value, (m, n) in groups.items():
            if 0 < n < total:
                rest_m, rest_n = misses - m, total - n
                p = float(scipy.stats.fisher_exact([[m, n - m], [rest_m, rest_n - rest_m]])[1])
                tested.append((p, m / n > rest_m / rest_n, f"{key}={value}: {m}/{n} against {rest_m}/{rest_n}"))
    level = alpha / max(len(tested), 1)
    return [f"{text} (p = {p:.2g}{f', holds over all {len(tested)} values' if p < level else ''})"
            for p, higher, text in sorted(tested) if higher and p < alpha]


def is_miss(row: dict) -> bool:
    if row["rank"] is None:
        return row["revealable"]  # no ranking: a miss only where the records could reveal it
    return (row["rank"] != 1 or (row["revealable"] and not row["significant"])
            or (row["gain"] is not None and row["gain"] < GAIN_MIN)
            or (row["error"] is not None and row["error"] > ERROR_MAX) or bool(row["wrong_claims"]))


def _more_records_named(row: dict) -> bool:
    """Ranked first but not significant, and explain said how many records like these would settle
    it (its ``records_needed``: the test's power, not the fit, is short)."""
    return row["rank"] == 1 and not row["significant"] and (row.get("records_named") or {}).get(row["effect"]) is not None


def table(results: list, effects) -> str:
    lines = ["| effect | drives | top-1 (of revealable) | significant (revealable) | first, not significant: records named | "
             "not revealable: said so | gain >= 2 (median) | parameter within 20 % (median error) | "
             "figures said in claims: off > 20 % (outside their bound) | other effect claimed | misses concentrate at (Fisher) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    wrong_all, unsure = [], []
    for eff in effects:
        rows = [({**r["drive"], "seed": r["seed"]}, row) for r in results for row in r["rows"] if row["effect"] == eff]
        if not rows:
            continue
        n = len(rows)
        top = sum(row["rank"] == 1 for _, row in rows)
        rev = [row for _, row in rows if row["revealable"]]
        sig = sum(row["significant"] for row in rev)
        top_rev = sum(row["rank"] == 1 for row in rev)
        named = sum(_more_records_named(row) for row in rev)
        hidden = [row for _, row in rows if not row["revealable"]]
        told = sum(bool(row["answer"]) or (row["rank"] is not None and not row["significant"]) for row in hidden)
        gains = [row["gain"] for _, row in rows if row["gain"] is not None]
        errs = [row["error"] for _, row in rows if row["error"] is not None]
        wrong = [(d, row) for d, row in rows if row["wrong_claims"]]
        wrong_all += [(eff, row["wrong_claims"], d["seed"]) for d, row in wrong]
        where = misses_by_attribute([(d, is_miss(row)) for d, row in rows])
        said = [e for _, row in rows if row["significant"] and "said" in row
                for e in figure_errors(row["said"], row["truth"], row.get("bound")).values()]
        off = (f"{sum(e > ERROR_MAX for e, _ in said)} of {len(said)} "
               f"({sum(bool(out) for e, out in said if e > ERROR_MAX)} outside their bound)" if said else "-")
        quiet = misses_by_attribute([(d, not row["significant"]) for d, row in rows if row["revealable"]])
        if quiet:
            unsure.append(f"{eff}: {'; '.join(quiet[:2])}")
        tops = f"{top / n:.0%} ({top_rev}/{len(rev)} = {top_rev / max(len(rev), 1):.0%})"
        lines.append(f"| {eff} | {n} | {tops} | {sig}/{len(rev)} = {sig / max(len(rev), 1):.0%} | {named} | "
                     f"{told}/{len(hidden)} | {np.mean(np.array(gains) >= GAIN_MIN):.0%} ({np.median(gains):.3g}x) | "
                     f"{np.mean(np.array(errs) <= ERROR_MAX):.0%} of {len(errs)} ({np.median(errs):.0%}) | {off} | "
                     f"{len(wrong)} | {'; '.join(where[:2]) or '-'} |" if gains and errs else
                     f"| {eff} | {n} | {tops} | {sig}/{len(rev)} | {named} | {told}/{len(hidden)} | - | - | {off} | {len(wrong)} | "
                     f"{'; '.join(where[:2]) or '-'} |")
    if unsure:
        lines += ["", "Not significant where the records can reveal it, concentrated at (Fisher's exact test, "
                  "one set per drive): " + " | ".join(unsure)]
    nulls = [r["null"] for r in results if "null" in r]
    claiming = [n["claims"] for n in nulls if n["claims"]]
    quiet = sum(bool(n["answer"]) for n in nulls)
    lines += ["", f"Null drives (nothing hidden): {len(claiming)} of {len(nulls)} claim an effect "
              f"(95 % upper bound {upper95(len(claiming), len(nulls)):.1%} per drive); {quiet} answered that the "
              "records carry no dynamics."]
    if claiming:
        lines.append("Claims on null drives: " + ", ".join(f"{k} x{v}" for k, v in
                                                           Counter(e for c in claiming for e in c).most_common()))
    lines.append("A different effect claimed significant: " + (", ".join(f"{w} for hidden {e} ({seed})" for e, ws, seed
                                                                          in wrong_all for w in ws) or "never") + ".")
    errors = [r for r in results if "error" in r]
    if errors:
        lines.append(f"Drives that ended in an error: {len(errors)} ({'; '.join(r['error'] for r in errors[:3])})")
    return "\n".join(lines)


def effect_size(r: dict, row: dict) -> float | None:
    """A hidden effect's own size on its drive: the part of the control's held-out NRMSE beyond what
    the same drive's null set leaves (sqrt(ctrl^2 - ctrl_null^2), the base model's own misses taken
    out), over the noise floor; None where either is missing."""
    null = r.get("null", {})
    c, c0, f = row["nrmse_control"], null.get("nrmse_control"), row["noise_floor"]
    if c is None or c0 is None or not f:
        return None
    return float(np.sqrt(max(c * c - c0 * c0, 0.0))) / f


def power_plot(results: list, effects, path: Path) -> Path:
    """Detected (significant) fraction against the hidden effect's own size (:func:`effect_size`),
    binned; one line per effect, each point labelled with its drives."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    edges = np.array([0, 0.5, 1, 2, 4, 8, 16, 32, np.inf])
    centres = np.array([0.35, 0.7, 1.4, 2.8, 5.6, 11, 22, 45])
    for eff in effects:
        pts = [(size, row["significant"]) for r in results for row in r["rows"]
               if row["effect"] == eff and row["revealable"] and (size := effect_size(r, row)) is not None]
        if not pts:
            continue
        x, y = np.array(pts, dtype=float).T
        idx = np.digitize(x, edges) - 1
        frac = [(centres[b], y[idx == b].mean(), (idx == b).sum()) for b in range(len(centres)) if (idx == b).any()]
        line, = ax.plot([f[0] for f in frac], [f[1] for f in frac], "o-", label=eff)
        for xc, yc, n in frac:
            ax.annotate(str(n), (xc, yc), textcoords="offset points", xytext=(3, 3), fontsize=6, color=line.get_color())
    ax.set_xscale("log")
    ax.set_xlabel("hidden effect's own size: its share of the control's NRMSE / noise floor (labels: drives)")
    ax.set_ylabel("detected (significant) fraction")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("explain's power over the drive family")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    from agent.effects import EFFECTS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--drives", type=int, default=60, help="drives with each hidden effect (default 60)")
    p.add_argument("--null", type=int, default=800,
                   help="null drives, the effect drives among them (default 800; a one-sided 95 %% bound of 1 %% on "
                        "the null rate takes 0 claims in 300 drives, 2 in 630, 3 in 775)")
    p.add_argument("--seconds", type=float, default=1.0, help="record length, s (default 1.0)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: the cores)")
    p.add_argument("--effects", default="", help="comma-separated effect ids (default: the library's)")
    p.add_argument("--reported-voltage", action="store_true",
                   help="profiles without the drive's voltage path: the voltage taken as reported")
    p.add_argument("--nameplate", action="store_true", help="profiles with the nameplate (R_s, psi_m, L_d, L_q within 5 %%)")
    p.add_argument("--short", action="store_true", help="`make test`'s form: 2 drives per effect, 0.6 s records")
    p.add_argument("--plot", default=str(ROOT / "docs" / "img" / "family_power.png"), help="power plot file")
    a = p.parse_args(argv)
    effects = [e for e in a.effects.split(",") if e] or list(EFFECTS)
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        p.error(f"--effects: unknown effect {unknown[0]!r} (known: {', '.join(EFFECTS)})")
    if a.drives < 0 or a.null < 0 or a.jobs < 1:
        p.error("--drives, --null must be >= 0 and --jobs >= 1")
    if not 0.4 <= a.seconds <= 10:
        p.error(f"--seconds: {a.seconds:g} is outside 0.4..10 s (the hold-out needs half of each record)")
    n_drives, n_null, seconds = (2, 2, 0.6) if a.short else (a.drives, a.null, a.seconds)
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    path = RESULTS / (f"family_short.jsonl" if a.short else
                      f"family_{seconds:g}s{'_reported' if a.reported_voltage else ''}"
                      f"{'_nameplate' if a.nameplate else ''}.jsonl")
    if a.short and path.exists():
        path.unlink()
    t0 = time.perf_counter()
    results = run(n_drives, n_null, seconds, a.jobs, effects, say, path, timing=not a.reported_voltage,
                  nameplate=a.nameplate)
    print(table(results, effects))
    print(f"\n{len(results)} drives, {time.perf_counter() - t0:.0f} s wall on {a.jobs} process(es), "
          f"{sum(r['seconds'] for r in results):.0f} s of drive work; results {path}")
    if not (a.short or a.nameplate or a.reported_voltage):  # the plot is of the documented workflow
        print(f"power plot: {power_plot(results, effects, Path(a.plot))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
