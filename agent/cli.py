"""The ``pmsm-agent`` command line (CONTRACT section 2).

Every subcommand takes ``--json`` (exactly one JSON object on stdout; logs on stderr). Exit
status: 0 success, 2 bad usage or bad input (one line naming the file/key/column), 1 internal
failure.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from agent.cliargs import Parser, UsageError, fraction, number, quiet_broken_pipe
from agent.errors import InputError
from agent.evidence import FULL_EVIDENCE_STRETCHES, AlarmConfig

log = logging.getLogger("pmsm-agent")

#: Modules that add subcommands: each has ``add_commands(subparsers, common_parent)`` whose
#: handlers take the parsed args and raise ``InputError`` for user errors.
#: what the gateway install leaves out (pyproject's ``workbench`` extra)
WORKBENCH_MODULES = ("scipy", "numba", "matplotlib", "llvmlite")
EXTENSIONS: tuple[str, ...] = ("agent.runtime.cli", "agent.runtime.commissioning", "agent.workbench.cli",
                               "agent.historian.cli", "agent.runtime.plant")


# --- helpers --------------------------------------------------------------------------------

def _emit(args, doc: dict, human: str) -> None:
    if args.json:
        json.dump(doc, sys.stdout, default=_json_default)
        sys.stdout.write("\n")
    else:
        print(human)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _progress(i: int, n: int, text: str) -> None:
    log.info("[%d/%d] %s", i + 1, n, text)


def _load_records(paths, profile, min_samples: int = 0):
    from agent.records import load_record

    return [load_record(p, profile, min_samples=min_samples) for p in paths]


def distinct_records(paths: list[str]) -> list[str]:
    """Training records, each once: a record given twice would count as two healthy records and
    narrow the learned spread (``identify``, ``learn``, ``add-effect``)."""
    seen: dict[Path, str] = {}
    for p in paths:
        key = Path(p).resolve()
        if key in seen:
            raise InputError(f"{p}: given twice (as {seen[key]}): a record counted twice narrows the healthy spread")
        seen[key] = p
    return paths


def _parse_effects(items: list[str] | None) -> dict[str, float | None]:
    effects: dict[str, float | None] = {}
    for item in items or []:
        name, _, value = item.partition("=")
        try:
            effects[name.strip()] = float(value) if value else None
        except ValueError:
            raise InputError(f"--effect {item!r}: the value after '=' must be a number") from None
    return effects


# --- subcommands -----------------------------------------------------------------------------

def cmd_simulate(args) -> None:
    from agent.profile import load_profile
    from agent.records import save_record
    from agent.simulator import simulate

    profile = load_profile(args.profile)
    if args.seconds <= 0:
        raise InputError(f"--seconds must be positive, got {args.seconds}")
    if not 0 <= args.load <= 150:
        raise InputError(f"--load must be within 0..150 %, got {args.load}")
    out = Path(args.out)
    written, samples = [], 0
    for j in range(args.count):
        seed = args.seed + j
        rec = simulate(profile, condition=args.condition, load_pct=args.load, seconds=args.seconds, seed=seed,
                       effects=_parse_effects(args.effect), encoder=args.encoder, severity=args.severity)
        path = out if args.count == 1 else out.with_name(f"{out.stem}_{seed:04d}{out.suffix}")
        save_record(rec, path)
        written.append(str(path))
        samples = rec.n
    doc = {"out": written[0] if args.count == 1 else written, "samples": samples,
           "condition": args.condition, "load_pct": args.load, "seed": args.seed}
    _emit(args, doc, "\n".join(f"wrote {p} ({samples} samples)" for p in written))


def cmd_frequencies(args) -> None:
    from agent.frequencies import base_frequencies, fault_frequencies
    from agent.profile import load_profile

    profile = load_profile(args.profile)
    fe = profile.rated_fe_hz if args.fe is None else args.fe
    fam = fault_frequencies(profile, fe, args.k)
    doc = {"profile": profile.name, "fe_hz": fe, "base_hz": base_frequencies(profile, fe), "families": fam}
    lines = [f"fe = {fe:g} Hz"]
    for name, items in fam.items():
        lines.append(f"{name:>13}: " + ", ".join(f"{p['freq_hz']:.2f}" for p in items) + " Hz")
    _emit(args, doc, "\n".join(lines))


def _existing_model(path: str):
    """The baseline in the model file ``path``, or None when there is none this version reads."""
    from agent.modelfile import load_baseline

    try:
        return load_baseline(path)
    except InputError:  # no model there, or not one this version reads
        return None


def accept_fault_evidence_flag(parser) -> None:
    """``--accept-fault-evidence`` (identify, learn, model add-effect): :mod:`agent.training`."""
    parser.add_argument("--accept-fault-evidence", action="store_true",
                        help="learn from training records that read as faulty (against the baseline they replace, "
                             "or against the other records) anyway; the model file or journal records it")


def warn_fault_evidence(command: str, findings: list[str]) -> None:
    """The warning line when training records with fault evidence were learned from (on stderr)."""
    if findings:
        print(f"pmsm-agent {command}: warning: learned from records with fault evidence "
              f"(--accept-fault-evidence): {', '.join(findings)}", file=sys.stderr)


def cmd_identify(args) -> None:
    from agent.baseline import identify_baseline
    from agent.modelfile import save_baseline
    from agent.profile import load_profile
    from agent.training import check_training

    profile = load_profile(args.profile)
    replaced = _existing_model(args.out)
    if not args.replace and replaced is not None and replaced.history:
        raise InputError(f"--out {args.out}: a model with workbench versions (model history); it is kept "
                         f"(choose a new file, or --replace)")
    if len(args.data) < 4:
        raise InputError(f"identify needs at least 4 healthy records (the parameter cluster's region), got "
                         f"{len(args.data)}")
    recs = _load_records(distinct_records(args.data), profile,
                         min_samples=int(round(args.window * profile.sampling.rate_hz)))
    t0 = time.perf_counter()
    base = identify_baseline(recs, profile, form=args.form, robust=args.robust, window_s=args.window,
                             confidence=args.confidence, region=args.region, spectrum_rule=args.spectrum_rule,
                             prefilter_hz=args.prefilter, progress=_progress)
    findings = check_training(base.training, baseline=base, replaced=replaced, replaced_name=f"--out {args.out}",
                              accept_fault_evidence=args.accept_fault_evidence)
    if findings:
        base.model.meta["accepted_fault_evidence"] = findings
    phys = base.physical
    radius = base.model.spectral_radius(2 * np.pi * base.operating_point["fe_hz"])
    if not radius < 1.0:  # a model whose free run diverges describes no machine, however well it predicts one step
        phys["problems"].append(f"the identified model's free run is unstable at fe {base.operating_point['fe_hz']:.2f} Hz "
                                f"(largest eigenvalue {radius:.6f}): its inductances and resistance are not the "
                                f"machine's; records with a load step, or nameplate.ld_h and nameplate.lq_h, pin them")
    if phys["problems"] and not args.force:
        raise InputError(f"nonphysical parameters, model not written: {'; '.join(phys['problems'])} "
                         f"(check the records and the profile's [nameplate]; --force writes it anyway, marked)")
    if phys["problems"]:
        base.model.meta["forced"] = phys["problems"]
    save_baseline(base, args.out)
    warn_fault_evidence("identify", findings)
    m = base.model
    names_d, names_q = (tuple(t.name for t in ts) for ts in m.terms)
    params = {"d": dict(zip(names_d, m.theta_d.tolist())), "q": dict(zip(names_q, m.theta_q.tolist())),
              "physical": phys["values"], "ci95": phys["ci95"], "determined_by": phys["determined_by"],
              "unidentifiable": phys["unidentifiable"], "ts_over_lq": float(m.theta_q[2]),
              "b_gt": float(base.cluster.centre[1]), "constrained": base.model.meta.get("constrained", False),
              "forced": phys["problems"], "accepted_fault_evidence": findings}
    doc = {"model": str(args.out), "records": len(recs), "params": params,
           "operating_point": {k: base.operating_point[k] for k in ("fe_hz", "load_pct")},
           "cluster": {"centre": base.cluster.centre, "limit": base.cluster.limit, "region": base.cluster.region},
           "seconds": round(time.perf_counter() - t0, 3), "alarm": _alarm_evidence(base),
           "warnings": list(phys.get("conflicts", {}).values())}
    for w in doc["warnings"]:  # a nameplate value, or a sample-to-sample inductance, the records contradict: dropped
        log.warning("%s", w)
    for g in phys["unidentifiable"]:
        if g["from_nameplate"]:
            log.info("%s taken from the nameplate: %s", ", ".join(g["parameters"]), g["reason"])
        else:
            log.warning("not identifiable from these records: %s", g["reason"])
    units = {"Rs": ("ohm", 1.0), "Ld": ("mH", 1e3), "Lq": ("mH", 1e3), "psi_m": ("Wb", 1.0)}
    lines = []
    for k, (unit, f) in units.items():
        v, ci, by = phys["values"][k], phys["ci95"][k], phys["determined_by"][k]
        lines.append(f"  {k:6s} not identifiable (no nameplate value)" if v is None else
                     f"  {k:6s} {v * f:.4g} {unit}  (95 % {ci[0] * f:.4g} .. {ci[1] * f:.4g}; from {by})")
    _emit(args, doc, (
        f"baseline from {len(recs)} records -> {args.out}" + (" (FORCED: nonphysical)" if phys["problems"] else "") + "\n"
        f"operating point: fe {doc['operating_point']['fe_hz']:.2f} Hz, load {doc['operating_point']['load_pct']:.1f} %\n"
        "physical parameters:\n" + "\n".join(lines) + "\n"
        + (f"lumped model pulled back to the nearest plausible values ({params['constrained']})\n"
           if params["constrained"] else "") +
        f"cluster centre: Ts/Lq {base.cluster.centre[0]:.4e}, B_GT {base.cluster.centre[1]:.5f} N m s/rad\n"
        f"alarm evidence: {doc['alarm']['stretches']} independent stretches; one-window (gross) alarms above "
        f"window z {_span(*doc['alarm']['gross_threshold_z'])}"
        + ("" if doc["alarm"]["stretches"] >= FULL_EVIDENCE_STRETCHES else
           f" (few stretches widen it: the agent's commissioning, {FULL_EVIDENCE_STRETCHES} stretches of 30 s, "
           "gives about 6)")))


def _span(lo: float, hi: float) -> str:
    """'lo-hi', or one figure when both print alike."""
    a, b = f"{lo:.1f}", f"{hi:.1f}"
    return a if a == b else f"{a}-{b}"


def _alarm_evidence(base) -> dict:
    """The baseline's healthy evidence for the agent's alarms and its one-window threshold range
    at the default gross budget (docs/method.md, "Alarms")."""
    g, _ = AlarmConfig().gross_thresholds(base.evidence)
    return {"stretches": base.evidence.n, "gross_threshold_z": [round(float(g.min()), 2), round(float(g.max()), 2)]}


def cmd_diagnose(args) -> None:
    from agent.decision import diagnose
    from agent.modelfile import load_baseline

    if args.report:  # before the work: a folder that cannot be written is found at once
        try:
            from agent.workbench.report import report_folder, write_diagnosis_report
        except ImportError as err:
            raise InputError(f"--report needs the workbench install (make setup): {err}") from None
        report_folder(args.report)
    base = load_baseline(args.model)
    recs = _load_records(args.data, base.profile,
                         min_samples=int(round(base.thresholds.window_s * base.profile.sampling.rate_hz)))
    diagnoses = [diagnose(base, r) for r in recs]
    results = [d.to_json() for d in diagnoses]
    report = None
    if args.report:

        report = str(write_diagnosis_report(args.report, base, diagnoses, str(args.model)))
    lines = []
    for r in results:
        if r["quality"] != "good":
            lines.append(f"{r['record']}: no diagnosis ({r['quality']}): {r['reason']}")
            continue
        peaks = ", ".join(f"{p['freq_hz']:.1f} Hz {p['family']} k={p['k']} {p['level']}"
                          + (f" (shared with {', '.join(p['shared_with'])})" if p["shared_with"] else "")
                          for p in r["peaks"])
        lines.append(f"{r['record']}: {r['state'].upper()} (spectrum {r['spectrum_state']}, cluster "
                     f"{r['cluster_state']}, d2 {r['cluster']['distance2']:.1f}/{r['cluster']['limit']:.1f})"
                     + (f"\n    verdict: {r['reason']}" if r["verdict"]["family"] else "")
                     + (f"\n    peaks: {peaks}" if peaks else "")
                     + "".join(f"\n    note: {n}" for n in r["notes"]))
    lines += [f"report: {report}"] if report else []
    _emit(args, {"model": str(args.model), "results": results, **({"report": report} if report else {})},
          "\n".join(lines))


def cmd_demo(args) -> None:
    from agent.demo import run_demo

    transitions = run_demo(seconds=args.seconds,
                           say=lambda s: print(s, file=sys.stderr if args.json else sys.stdout, flush=True))
    if args.json:
        json.dump({"transitions": transitions}, sys.stdout, default=_json_default)
        sys.stdout.write("\n")


# --- parser ----------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    common.add_argument("-v", "--verbose", action="store_true", help="log progress to stderr")

    p = Parser(prog="pmsm-agent", description="Model-based transmission-fault detection for "
                                "PMSM drives: simulate, identify, diagnose, the model workbench and the agent service.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("simulate", parents=[common], help="write a record from the rig simulator")
    s.add_argument("--profile", required=True, help="drive profile TOML")
    s.add_argument("--condition", default="healthy", help="healthy or a fault condition of the profile's transmission")
    s.add_argument("--effect", action="append", metavar="ID[=VALUE]",
                   help="add a physical effect (repeatable), e.g. inverter_deadtime=8")
    s.add_argument("--load", type=number(0, 130, unit="%"), default=80.0, help="load, %% of rated torque (default 80)")
    s.add_argument("--seconds", type=number(0, 120, low_open=True, unit="s"), default=4.0,
                   help="record length, s (default 4)")
    s.add_argument("--seed", type=number(0, 2**63 - 1, integer=True), default=0, help="random seed (default 0)")
    s.add_argument("--count", type=number(1, 10_000, integer=True), default=1,
                   help="write COUNT records with seeds SEED.. (suffix _SEED)")
    s.add_argument("--severity", type=number(0, 100), default=1.0, help="scale of the fault (default 1)")
    s.add_argument("--encoder", action="store_true", help="include theta_e/omega_e columns (drive encoder)")
    s.add_argument("--out", required=True, help="output record (.csv, .npz or .tdms)")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("frequencies", parents=[common], help="fault characteristic frequencies (eqs. 19-22)")
    s.add_argument("--profile", required=True, help="drive profile TOML")
    s.add_argument("--fe", type=number(0, 1e5, low_open=True, unit="Hz"),
                   help="electrical frequency, Hz (default: rated speed)")
    s.add_argument("--k", type=number(1, 100, integer=True), default=3, help="sideband orders 1..K (default 3)")
    s.set_defaults(func=cmd_frequencies)

    s = sub.add_parser("identify", parents=[common], help="learn a healthy baseline from records (Algs. 2-4)")
    s.add_argument("--profile", required=True, help="drive profile TOML")
    s.add_argument("--out", required=True, help="model file to write (JSON); one with workbench versions is kept "
                   "unless --replace")
    s.add_argument("--replace", action="store_true", help="overwrite --out even if it holds workbench versions")
    s.add_argument("--form", choices=("lumped", "speed"), default="lumped",
                   help="regression form: paper eqs. 13-14 (lumped) or omega_e as a regressor (speed)")
    s.add_argument("--robust", action="store_true", help="median/MAD instead of mean/std")
    s.add_argument("--window", type=number(0.1, 60, unit="s"), default=2.0,
                   help="residual-spectrum window, s (default 2)")
    s.add_argument("--confidence", type=fraction, default=0.95,
                   help="parameter-cluster region, a fraction (default 0.95)")
    s.add_argument("--region", choices=("prediction", "chi2"), default="prediction",
                   help="cluster region: Hotelling prediction ellipse (default) or chi-square")
    s.add_argument("--prefilter", type=number(0, 1e5, low_open=True, unit="Hz"), metavar="HZ",
                   help="low-pass both sides of the regressions at HZ (removes current-sensor noise bias)")
    s.add_argument("--spectrum-rule", choices=("pair", "line"), default="pair",
                   help="a fault needs both sidebands fe -+ k f above threshold (pair, default) or one line (line)")
    s.add_argument("--force", action="store_true",
                   help="write the model even when its physical parameters are refused (the model is marked)")
    accept_fault_evidence_flag(s)
    s.add_argument("data", nargs="+", help="healthy records at one operating point")
    s.set_defaults(func=cmd_identify)

    s = sub.add_parser("diagnose", parents=[common], help="normal / caution / warning for each record")
    s.add_argument("--model", required=True, help="baseline model file (JSON, from identify or learn)")
    s.add_argument("--report", metavar="DIR", help="write an HTML page: decision table, parameter cluster, each "
                   "record's residual spectrum with TH1-TH3 and the fault sidebands (needs the workbench install)")
    s.add_argument("data", nargs="+", help="records to diagnose (CSV, NPZ, TDMS)")
    s.set_defaults(func=cmd_diagnose)

    for module in EXTENSIONS:  # command groups that live with their subsystem
        importlib.import_module(module).add_commands(sub, common)

    s = sub.add_parser("demo", parents=[common], help="the embedded demo (simulated drive, healthy then faulty)")
    s.add_argument("--seconds", type=number(0, 60, low_open=True, unit="s"), default=60.0,
                   help="wall-time limit, s (default and at most 60)")
    s.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except BrokenPipeError:
        return quiet_broken_pipe()


def _main(argv: list[str] | None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except UsageError as err:  # one line on stderr already; with --json also the error object
        if "--json" in (sys.argv[1:] if argv is None else argv):
            json.dump({"error": err.message, "exit": 2}, sys.stdout)
            sys.stdout.write("\n")
        raise
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        args.func(args)
    except InputError as err:
        return _error(args, str(err), 2)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        raise
    except ModuleNotFoundError as err:
        if err.name not in WORKBENCH_MODULES:
            raise
        return _error(args, f"this needs the workbench install ({err.name} is missing): pip install "
                            f"'pmsm-agent[workbench]' (in the checkout: make setup)", 2)
    except Exception as err:  # a bug: say so, with the traceback, and exit 1
        log.exception("internal error")
        return _error(args, f"internal error: {type(err).__name__}: {err}", 1, quiet=True)
    return 0


def _error(args, message: str, code: int, quiet: bool = False) -> int:
    """Exit status ``code`` for an error: one line on stderr (unless ``quiet``: already logged) and,
    with ``--json``, one object ``{"error": message, "exit": code}`` on stdout."""
    if not quiet:
        print(f"pmsm-agent {args.command}: error: {message}", file=sys.stderr)
    if getattr(args, "json", False):
        json.dump({"error": message, "exit": code}, sys.stdout)
        sys.stdout.write("\n")
    return code


if __name__ == "__main__":
    sys.exit(main())
