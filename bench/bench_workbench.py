"""The workbench on two simulators: the project's rig and motulator 0.5.0 (a drive nobody here wrote).

    python -m bench.bench_workbench [--short] [--null N] [--seconds S] [--sims rig,motulator]

The workflow a user runs: a model identified at 80 % load from four healthy records, then records
with one hidden effect (or two, or none) at other loads, ``model explain`` on them. Per simulator
and effect: the true effect's rank, whether it is called significant, the gain of the refit with
it over the best refit with a wrong effect (held-out free-run NRMSE beyond the noise floor, ratio,
target >= 2) and its
headline parameter's error (target <= 20 %). Null sets (no hidden effect, four records at 40, 60,
90 and 100 % load) measure the false-claim rate at the explain's family-wise level. The same
values are injected in both simulators in the same units; nothing is tuned to either.

Writes the markdown of docs/benchmarks.md ("Workbench on two simulators") to stdout and the
figures to bench/results/workbench.json (workbench_<S>s.json for another --seconds). motulator records are cached (bench/results).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from agent.profile import load_profile, parse_profile

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
NULL_LOADS = (40.0, 60.0, 90.0, 100.0)
BASE_LOAD = 80.0
STEP_PCT = 10.0  #: the load step, %-points, of the step scenario and the null sets with steps
ALPHA_FW = 0.01  #: the explain's family-wise level (agent.workbench.explain.ALPHA)


def _variants(path: Path, rs_ohm: float) -> dict:
    """The profile at ``path`` keyed by (reference, nameplate): with the drive's voltage command
    recorded (dead time shows) and with a nameplate R_s (a DC measurement at 20 C, 5 %)."""
    out = {}
    for reference in (False, True):
        for nameplate in (False, True):
            doc = tomllib.loads(path.read_text())
            if reference:
                doc["sampling"]["voltage_source"] = "reference"
            if nameplate:
                doc["nameplate"] = {"rs_ohm": rs_ohm, "rs_temp_c": 20.0}
            out[reference, nameplate] = parse_profile(doc, source=f"{doc['name']}_{int(reference)}{int(nameplate)}")
    return out


@dataclass(frozen=True)
class Scenario:
    """One hidden effect: its value (the effect's own unit), the loads of its records, whether the
    records carry the voltage command, the explain's headline key and its true value."""

    value: float
    loads: tuple[float, ...]
    reference: bool
    key: str
    truth: Callable[[list, float], float]
    encoder: bool = True  #: motulator's records carry its encoder angle (the rig's never: PLL, as the agent runs)
    nameplate: bool = False  #: the profile carries the nameplate R_s
    effect: str = ""  #: the hidden effect when the scenario's key is not its id
    step_pct: float = 0.0  #: each record's load steps up by this many %-points a quarter into it
    more: tuple[str, ...] = ()  #: further figures with the same true value, judged alike (the worst error counts)
    alt: str = ""  #: the figure judged where the records leave the headline null (the same true value)
    alt_truth: Callable[[list, float], float] | None = None  #: its own true value, where it is another quantity


def _const(recs, value):
    return value


def _delay_truth(recs, value):
    return value


def _half(recs, value):
    """The 5th and the 7th flux harmonics of a simulator's psi_6 (Wb): half of it each."""
    return 0.5 * value


class Rig:
    """agent.simulator, the project's own rig (PLL angle, as the agent runs)."""

    name = "rig"
    path = ROOT / "config/profiles/rig_gear.toml"
    encoder = False  #: its records carry no encoder angle

    def __init__(self):
        self.profiles = _variants(self.path, 2.0)  # agent.simulator.rig.RigParams.R_s at 20 C

    def records(self, effects: dict, loads, seconds: float, seed: int, reference=False, encoder=True, step_pct=0.0):
        from agent.simulator import simulate

        prof = self.profiles[reference, False]
        return [simulate(prof, "healthy", load, seconds, seed=seed + j, effects=effects or None,
                         load_step=(0.25 * seconds, load + step_pct) if step_pct else None)
                for j, load in enumerate(loads)]

    @staticmethod
    def drift_truth(recs, value):
        return float(np.mean([(r.meta["R_s_end"] - r.meta["R_s"]) / r.meta["seconds"] for r in recs]))

    @staticmethod
    def ripple_truth(recs, value):
        return float(np.mean([r.meta["speed_ripple_omega_e"] for r in recs]))

    @staticmethod
    def saturation_truth(recs, value):
        return value

    @staticmethod
    def offset_voltage_truth(recs, value):
        """R_s o: the stator-frame DC voltage that holds an offset o (A) off the winding, V."""
        return value * float(np.mean([r.meta["R_s"] for r in recs]))


class Motulator:
    """bench.thirdparty.motulator_drive (encoder angle; its own controller, inverter and solver)."""

    name = "motulator"
    encoder = True  #: its records carry the encoder angle (the null sets also run without it)

    def __init__(self):
        from bench.thirdparty.motulator_drive import PROFILE

        from bench.thirdparty.motulator_drive import R_S

        self.path = PROFILE
        self.profiles = _variants(PROFILE, R_S)

    def records(self, effects: dict, loads, seconds: float, seed: int, reference=False, encoder=True, step_pct=0.0):
        from agent.records import load_record
        from bench.thirdparty.motulator_drive import Run, cached

        prof = self.profiles[reference, False]
        out = []
        for j, load in enumerate(loads):
            run = Run(load_pct=load, seconds=seconds, seed=seed + j, effects=dict(effects or {}),
                      voltage="reference" if reference else "measured", load_step_pct=step_pct)
            rec = load_record(cached(run), prof)
            if not encoder:  # the same record as a drive without an encoder gives it (the truth kept aside)
                rec = dataclasses.replace(rec, theta_e=None, omega_e=None,
                                          meta={**rec.meta, "true_omega_e": rec.omega_e})
            out.append(rec)
        return out

    @staticmethod
    def drift_truth(recs, value):
        from bench.thirdparty.motulator_drive import R_S

        return R_S * value  # R_s (1 + r t): ohm/s

    @staticmethod
    def ripple_truth(recs, value):
        """The omega_e ripple at the shaft's rotation frequency, read off the encoder's speed."""
        amps = []
        for r in recs:
            w = np.asarray(r.omega_e if r.omega_e is not None else r.meta["true_omega_e"])
            t = r.t - r.t[0]
            wm = np.mean(w) / 3.0  # mechanical rad/s (3 pole pairs)
            x = np.column_stack((np.ones_like(t), np.cos(wm * t), np.sin(wm * t)))
            c = np.linalg.lstsq(x, w, rcond=None)[0]
            amps.append(np.hypot(c[1], c[2]))
        return float(np.mean(amps))

    @staticmethod
    def offset_voltage_truth(recs, value):
        """R_s o: the stator-frame DC voltage that holds an offset o (A) off the winding, V."""
        from bench.thirdparty.motulator_drive import R_S

        return value * R_S

    @staticmethod
    def saturation_truth(recs, value):
        """Chord L_q drop at rated current of motulator's i_q = psi_q/L_q (1 + a (psi_q/psi_qr)^2)."""
        import scipy.optimize

        from bench.thirdparty.motulator_drive import L_Q

        i_r = 4.3 * np.sqrt(2)
        psi_qr = L_Q * 1.5 * i_r
        psi = scipy.optimize.brentq(lambda p: p / L_Q * (1 + value * (p / psi_qr) ** 2) - i_r, 0, L_Q * i_r)
        return 1.0 - psi / (L_Q * i_r)


def scenarios(sim) -> dict[str, Scenario]:
    """The same injected values in both simulators (magnetic_saturation: each simulator's own law,
    its true chord drop at rated current computed from it)."""
    sat = 0.15 if sim.name == "rig" else 0.35  # motulator's a: a chord drop of about 0.14
    return {
        # an offset the drive's controller acts on shows as the voltage R_s o that holds it
        "current_offset": Scenario(0.1, (80.0,), False, "offset_A", _const, alt="offset_voltage_V",
                                   alt_truth=sim.offset_voltage_truth),
        "current_gain_mismatch": Scenario(0.03, (80.0,), False, "gain_b", _const),
        "resistance_drift": Scenario(0.2, (60.0, 100.0), False, "dR_dt_ohm_per_s", sim.drift_truth),
        # the simulators hold the voltage in abc (advance 0): the pinned sum delay + advance is the delay too
        "voltage_delay": Scenario(1.0, (60.0, 100.0), False, "delay_samples", _delay_truth, alt="rotation_samples"),
        "flux_harmonics": Scenario(0.005, (80.0,), False, "psi_5_Wb", _half, more=("psi_7_Wb",)),
        "magnetic_saturation": Scenario(sat, (50.0, 80.0, 110.0), False, "lq_drop_at_rated", sim.saturation_truth),
        # the same with the nameplate R_s an engineer measures: under MTPA it separates R_s i_d from saturation
        "magnetic_saturation+nameplate": Scenario(sat, (50.0, 80.0, 110.0), False, "lq_drop_at_rated",
                                                       sim.saturation_truth, nameplate=True,
                                                       effect="magnetic_saturation"),
        # the same at constant speed with a load step in each record, which explain names as what reveals it
        "voltage_delay+load_step": Scenario(1.0, (60.0, 90.0), False, "delay_samples", _delay_truth,
                                            effect="voltage_delay", step_pct=STEP_PCT, alt="rotation_samples"),
        "inverter_deadtime": Scenario(10.0, (50.0, 80.0, 110.0), True, "U_dt_V", _const),
        # the effect is the ripple a narrow-band speed signal misses: records without an encoder
        "speed_ripple": Scenario(1.0 if sim.name == "rig" else 1.5, (80.0,), False, "omega_e_ripple_rad_s",
                                 sim.ripple_truth, encoder=False),
    }


PAIR = ("current_offset", "voltage_delay")  #: two hidden effects at once


class Bench:
    def __init__(self, sim, seconds: float, say=print):
        self.sim, self.seconds, self.say = sim, seconds, say
        self._bases = {}

    def baseline(self, reference: bool, nameplate: bool = False):
        from agent.baseline import identify_baseline

        if (reference, nameplate) not in self._bases:
            recs = self.sim.records({}, (BASE_LOAD,) * 4, 1.0, 700, reference)
            self._bases[reference, nameplate] = identify_baseline(recs, self.sim.profiles[reference, nameplate],
                                                                  window_s=0.5)
        return self._bases[reference, nameplate]

    def explain(self, recs, reference=False, nameplate=False) -> dict:
        from agent.workbench.explain import explain
        from agent.workbench.fitting import prepare

        return explain(self.baseline(reference, nameplate), prepare(recs, self.sim.profiles[reference, nameplate]))

    def scenario(self, name: str, sc: Scenario) -> dict:
        t0 = time.perf_counter()
        effect = sc.effect or name
        loads = sc.loads * (4 // len(sc.loads)) + sc.loads[: 4 % len(sc.loads)]
        recs = self.sim.records({effect: sc.value}, loads, self.seconds, 100, sc.reference, sc.encoder, sc.step_pct)
        doc = self.explain(recs, sc.reference, sc.nameplate)
        row = judge(doc, effect, sc.key, sc.truth(recs, sc.value), sc.more, sc.alt,
                    sc.alt_truth(recs, sc.value) if sc.alt_truth else None)
        row["scenario"] = name
        self.say(f"{self.sim.name} {name}: rank {row['rank']}, significant {row['significant']}, "
                 f"gain {row['gain']:.2f}, error {row['error']:+.0%} ({time.perf_counter() - t0:.0f} s)")
        return row

    def pair(self) -> dict:
        effects = {e: scenarios(self.sim)[e].value for e in PAIR}
        recs = self.sim.records(effects, (60.0, 100.0, 60.0, 100.0), self.seconds, 300)
        doc = self.explain(recs)
        sig = [c["effect"] for c in doc["candidates"] if c["significant"]]
        top2 = [c["effect"] for c in doc["candidates"][:2]]
        self.say(f"{self.sim.name} pair {PAIR}: top two {top2}, significant {sig}")
        return {"effects": list(PAIR), "top2": top2, "significant": sig}

    def null(self, n_sets: int, first_seed: int = 5000, step_pct: float = 0.0, encoder: bool = True) -> dict:
        claims = []
        for j in range(n_sets):
            recs = self.sim.records({}, NULL_LOADS, self.seconds, first_seed + 10 * j, encoder=encoder,
                                    step_pct=step_pct)
            doc = self.explain(recs)
            sig = [c["effect"] for c in doc["candidates"] if c["significant"]]
            claims.append(sig)
            self.say(f"{self.sim.name} null set {j + 1}/{n_sets}{' (load steps)' if step_pct else ''}"
                     f"{'' if encoder else ' (no encoder)'}: claims {sig or 'nothing'}")
        return {"sets": n_sets, "claiming": sum(bool(c) for c in claims), "claims": claims}


def judge(doc: dict, effect: str, key: str, true: float, more: tuple[str, ...] = (), alt: str = "",
          alt_true: float | None = None) -> dict:
    """The brief's figures of one scenario from its explain document; ``more``: further figures with
    the same true value (the worst error is the row's); ``alt``: the figure judged instead where the
    records leave ``key`` null and pin it (against ``alt_true`` where given). A figure the records do
    not pin is reported null by explain: its fitted value is then read from ``unpinned_params`` and
    the row says so."""
    names = [c["effect"] for c in doc["candidates"]]
    row = doc["candidates"][names.index(effect)]
    if alt and row["params"].get(key) is None and row["params"].get(alt) is not None:
        key, true = alt, true if alt_true is None else alt_true
    wrong = min(c["nrmse_after"] for c in doc["candidates"] if c["effect"] != effect)

    def fitted(k):
        value = row["params"].get(k)
        return (value, True) if value is not None else (row.get("unpinned_params", {}).get(k, float("nan")), False)

    figures = {k: fitted(k) for k in (key, *more)}
    error = max((v / true - 1.0 for v, _ in figures.values()), key=abs)
    return {"effect": effect, "rank": names.index(effect) + 1, "top": names[0], "significant": row["significant"],
            "nrmse_before": doc["nrmse_before"], "nrmse_control": doc["nrmse_control"],
            "nrmse_after": row["nrmse_after"], "nrmse_best_wrong": wrong, "noise_floor": doc.get("noise_floor"),
            "p_value": row["p_value"],
            "gain": wrong / max(row["nrmse_after"], 1e-300), "key": key, "fitted": figures[key][0], "true": true,
            "more": {k: v for k, (v, _) in figures.items() if k != key},
            "error": error, "bound": row.get("at_bound", False),
            "plus_minus": (row.get("params_bound") or {}).get(key),
            "identifiable": bool(row["identifiable"] and all(p for _, p in figures.values())),
            "note": row.get("note", "")}


def run(sims=("rig", "motulator"), seconds: float = 1.0, n_null: int = 25, effects=None, pair=True,
        say=print, n_null_step: int = 10, n_null_pll: int = 10) -> dict:
    out = {"seconds": seconds, "sims": {}}
    for name in sims:
        sim = Rig() if name == "rig" else Motulator()
        b = Bench(sim, seconds, say)
        scs = scenarios(sim)
        res = {"rows": [b.scenario(e, scs[e]) for e in (effects or scs)]}
        if pair:
            res["pair"] = b.pair()
        res["null"] = b.null(n_null)
        res["null_step"] = b.null(n_null_step, first_seed=8000, step_pct=STEP_PCT)
        if sim.encoder:  # and as a drive without one gives them: the PLL's frame (under MTPA, not the rotor's)
            res["null_pll"] = b.null(n_null_pll, first_seed=9000, encoder=False)
        out["sims"][name] = res
    return out


def _fmt(x: float) -> str:
    return "diverged" if not np.isfinite(x) else f"{100 * x:.2f} %"


def table(result: dict) -> str:
    lines = ["| simulator | hidden effect | top of explain | significant (p) | NRMSE control -> true (best wrong); "
             "noise floor | gain | parameter: fitted +- its bound (true), error |", "|---|---|---|---|---|---|---|"]
    for name, res in result["sims"].items():
        for r in res["rows"]:
            lines.append(f"| {name} | {r.get('scenario', r['effect'])} | {r['top']} (rank {r['rank']}) | "
                         f"{'yes' if r['significant'] else 'no'} ({r['p_value']:.2g}) | {_fmt(r['nrmse_control'])} -> "
                         f"{_fmt(r['nrmse_after'])} ({_fmt(r['nrmse_best_wrong'])}); {'n/a' if r['noise_floor'] is None else _fmt(r['noise_floor'])} | "
                         f"{r['gain']:.3g}x | "
                         + (f"{r['key']} {r['fitted']:.4g}"
                            + ("" if r.get("plus_minus") is None else f" +-{r['plus_minus']:.2g}")
                            + "".join(f", {k} {v:.4g}" for k, v in r.get("more", {}).items())
                            + f" ({r['true']:.4g}), {100 * r['error']:+.0f} %" if r['identifiable']
                            else f"{r['key']} not identifiable, not reported (the fit's value {r['fitted']:.4g}, "
                                 f"{100 * r['error']:+.0f} %)") + " |")
        if "pair" in res:
            p = res["pair"]
            lines.append(f"| {name} | {' + '.join(p['effects'])} | {', '.join(p['top2'])} | "
                         f"{', '.join(p['significant']) or 'none'} | | | |")
    lines.append("")

    def claims(kind: str) -> str:
        runs = {n: r[kind] for n, r in result["sims"].items() if kind in r}
        per = "; ".join(f"{n}: {r['claiming']} of {r['sets']}" for n, r in runs.items())
        return f"{sum(r['claiming'] for r in runs.values())} of {sum(r['sets'] for r in runs.values())} claim an effect ({per})"

    lines.append(f"Null sets (no hidden effect, records at {', '.join(f'{x:g}' for x in NULL_LOADS)} % load against "
                 f"a model at {BASE_LOAD:g} %): {claims('null')}; family-wise level {ALPHA_FW:g} per set.")
    if all("null_step" in r for r in result["sims"].values()):
        lines.append(f"Null sets with a {STEP_PCT:g} %-point load step a quarter into each record: {claims('null_step')}.")
    if any("null_pll" in r for r in result["sims"].values()):
        lines.append(f"Null sets without the encoder angle (the PLL's frame, which motulator's MTPA drive turns "
                     f"off the rotor's; the rig's records have no encoder anyway): {claims('null_pll')}.")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sims", default="rig,motulator", help="comma-separated: rig, motulator")
    p.add_argument("--seconds", type=float, default=1.0, help="record length, s (default 1.0)")
    p.add_argument("--null", type=int, default=25, help="null record sets per simulator (default 25)")
    p.add_argument("--effects", default="", help="comma-separated scenarios: effect ids, "
                   "magnetic_saturation+nameplate or voltage_delay+load_step (default: all)")
    p.add_argument("--null-steps", type=int, default=10, help="null record sets with load steps per simulator "
                   "(default 10)")
    p.add_argument("--null-pll", type=int, default=10, help="null record sets without the encoder angle, per "
                   "simulator whose records have one (default 10)")
    p.add_argument("--no-pair", action="store_true", help="skip the two-effect scenario")
    p.add_argument("--short", action="store_true", help="`make test`'s form: 0.6 s records, 2 null sets")
    a = p.parse_args(argv)
    sims = [s for s in a.sims.split(",") if s]
    bad = [s for s in sims if s not in ("rig", "motulator")]
    if bad:
        p.error(f"--sims: unknown simulator {bad[0]!r} (rig, motulator)")
    if "motulator" in sims:
        try:
            import motulator  # noqa: F401
        except ImportError:
            p.error("--sims motulator: motulator is not installed (make setup-test installs it)")
    if not 0.4 <= a.seconds <= 10:
        p.error(f"--seconds: {a.seconds:g} is outside 0.4..10 s (the hold-out needs half of each record)")
    for flag, n in (("--null", a.null), ("--null-steps", a.null_steps), ("--null-pll", a.null_pll)):
        if n < 0:
            p.error(f"{flag}: {n} is negative")
    known = scenarios(Rig())
    unknown = [e for e in a.effects.split(",") if e and e not in known]
    if unknown:
        p.error(f"--effects: unknown scenario {unknown[0]!r} (known: {', '.join(known)})")
    seconds, n_null, n_step, n_pll = (0.6, 2, 1, 1) if a.short else (a.seconds, a.null, a.null_steps, a.null_pll)
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    res = run(sims, seconds, n_null, [e for e in a.effects.split(",") if e] or None, not a.no_pair, say, n_step, n_pll)
    RESULTS.mkdir(parents=True, exist_ok=True)
    name = "workbench" if seconds == 1.0 else f"workbench_{seconds:g}s"
    (RESULTS / f"{name}.json").write_text(json.dumps(res, indent=1, default=str))
    print(table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
