"""``pmsm-agent model compare | explain | add-effect | history`` (the model workbench).

Each handler takes the parsed args, prints one JSON object with ``--json`` and raises
:class:`agent.errors.InputError` for user errors (exit 2)."""

from __future__ import annotations

import logging
import sys
import textwrap
from datetime import datetime, timezone
from pathlib import Path

from agent.errors import InputError

NOTE_SHARE = 0.01  #: explain's text shows the note of a candidate that explains at least this share
#: what a figure's +- means in the text (``params_bound``, :func:`agent.workbench.fitting.judge_figures`)
BOUND_LEGEND = ("+-: how far a figure may be from what the records show (the channels' noise, or the error the "
                "refit leaves lying all along the figure's weakest direction): a worst case, not a confidence interval")

log = logging.getLogger("pmsm-agent.model")


#: what a history entry's NRMSE figures mean (entries without it hold the raw free-run figure)
NRMSE_BASIS = "beyond_noise_floor"


def _load(args, model_path):
    from agent.cli import _load_records
    from agent.modelfile import load_baseline
    from agent.workbench.fitting import prepare

    if getattr(args, "report", None):  # before the work: a folder that cannot be written is found at once
        from agent.workbench.report import report_folder

        report_folder(args.report)

    base = load_baseline(model_path)
    recs = _load_records(args.data, base.profile, min_samples=int(0.2 * base.profile.sampling.rate_hz))
    return base, recs, prepare(recs, base.profile)


def _pct(v) -> str:
    """The one error figure as text: a percentage, or "unstable" (free run diverged)."""
    return "unstable" if v is None else f"{100 * v:.3f} %"


def _warn(doc: dict) -> None:
    for w in doc.get("warnings", []):
        log.warning("%s", w)


def _emit(args, doc, human):
    from agent.cli import _emit as emit

    emit(args, doc, human)


def cmd_compare(args) -> None:
    from agent.modelfile import load_baseline
    from agent.workbench.compare import compare
    from agent.workbench.explain import explain, operating_warnings

    twice = next((m for j, m in enumerate(args.model) if m in args.model[:j]), None)
    if twice is not None:
        raise InputError(f"--model {twice}: given twice")
    base, _, preps = _load(args, args.model[0])
    others = {m: load_baseline(m) for m in args.model[1:]}
    doc, data = compare(base, preps, one_step=args.one_step, others=others, name=args.model[0])
    doc["model"] = args.model[0]
    doc["warnings"] = operating_warnings(base, preps)
    _warn(doc)
    ranking = explain(base, preps) if args.report and args.rank else None
    if args.report:
        from agent.workbench.report import write_report

        doc["report"] = str(write_report(args.report, f"Model {args.model[0]} against {len(preps)} record(s)",
                                         doc, data, ranking))
    n = doc["nrmse"]
    cov = doc["coverage"]
    lines = ([f"{doc['mode']} NRMSE (held-out): d {100 * n['d']:.3f} %, q {100 * n['q']:.3f} %, "
              f"total {100 * n['total']:.3f} %", "fit %: " + ", ".join(f"{k} {v:.1f}" for k, v in doc["fit_pct"].items())]
             if n else [doc["note"]])
    if n and doc["noise_floor"]:
        lines.append(f"noise floor (the channels' noise, left out of the free-run figure): total "
                     f"{100 * doc['noise_floor']['total']:.3f} %")
    lines.append(f"records cover load {cov['load_pct_range'][0]:.0f}-{cov['load_pct_range'][1]:.0f} %, fe "
                 f"{cov['fe_hz_range'][0]:.1f}-{cov['fe_hz_range'][1]:.1f} Hz; the model's operating point: load "
                 f"{cov['model']['load_pct']:.0f} %, fe {cov['model']['fe_hz']:.1f} Hz")
    if len(doc["models"]) > 1:
        lines += ["whole record set, held-out free-run NRMSE:"] + [f"  {k}: {_pct(v)}" for k, v in doc["models"].items()]
    lines += [f"  fe {r['fe_hz']:.1f} Hz load {r['load_pct']:.0f} %: "
              + ", ".join(f"{k} {_pct(v)}" for k, v in r["nrmse"].items()) for r in doc["table"]]
    lines += ["where: " + (w.get("summary") or f"{w['freq_hz']:.1f} Hz {w['label']}") for w in doc["where"]]
    lines += [f"report: {doc['report']}"] if args.report else []
    _emit(args, doc, "\n".join(lines))


def cmd_explain(args) -> None:
    from agent.effects import get, params_text
    from agent.workbench.explain import explain

    candidates = [get(e).id for e in args.effect] if args.effect else None
    base, _, preps = _load(args, args.model)
    doc = explain(base, preps, candidates)
    doc["model"] = args.model
    _warn(doc)
    if args.report:
        from agent.workbench.compare import compare
        from agent.workbench.report import write_report

        cdoc, data = compare(base, preps)
        cdoc["warnings"] = doc["warnings"]
        doc["report"] = str(write_report(args.report, f"Effects missing from {args.model}", cdoc, data, doc))
    lines = [f"NRMSE (held-out, free run, beyond the noise floor): model {_pct(doc['nrmse_before'])}"
             + ("" if doc["nrmse_control"] is None and "note" in doc else
                f", control {_pct(doc['nrmse_control'])}" + (" (the model itself)" if doc["control_is_model"] else
                                                            " (the model refitted without new effects)"))
             + (f"; the control's noise floor {_pct(doc['noise_floor'])}" if doc.get("noise_floor") is not None else "")]
    lines += [doc["note_before"]] if doc.get("note_before") else []
    lines += textwrap.wrap(f"no effect ranked: {doc['note']}", 100, subsequent_indent="  ") if "note" in doc else []
    for r in doc["candidates"]:
        mark = ("SIGNIFICANT" if r["significant"] else "not identifiable" if not r["identifiable"]
                else "at bound" if r["at_bound"] else "")
        share = "   n/a" if r["explained_fraction"] is None else f"{100 * r['explained_fraction']:6.1f}"
        size = r.get("effect_size")
        ci = ("" if not size or (r["explained_fraction"] or 0.0) < NOTE_SHARE else
              " (per block {:.0f} %, 95 % {:.0f}..{:.0f} %, {:.3g} effective samples)".format(
                  100 * size["share"], *(100 * x for x in size["share_ci95"]), size["n_eff"]))
        lines.append(f"  {r['effect']:22s} explains {share} %{ci}  NRMSE {_pct(r['nrmse_after'])}  {mark:16s} "
                     + ("" if mark == "not identifiable" else params_text(r["params"], bounds=r.get("params_bound"))))
        if r.get("note") and (r["explained_fraction"] or 0.0) >= NOTE_SHARE:  # what the records cannot tell, and what would
            lines += textwrap.wrap(r["note"], 100, initial_indent=" " * 4, subsequent_indent=" " * 6)
    if any(b is not None for r in doc["candidates"] for b in (r.get("params_bound") or {}).values()):
        lines += textwrap.wrap(BOUND_LEGEND, 100, subsequent_indent="  ")
    _emit(args, doc, "\n".join(lines))


def cmd_add_effect(args) -> None:
    from agent.cli import distinct_records, warn_fault_evidence
    from agent.effects import get, params_text
    from agent.modelfile import save_baseline
    from agent.workbench.explain import add_effects

    effects = [get(e).id for e in args.effect]
    distinct_records(args.data)
    if Path(args.out).exists():
        raise InputError(f"--out {args.out}: exists; a model version is never overwritten (choose a new file)")
    base, recs, preps = _load(args, args.model)
    ref, fig = add_effects(base, preps, effects)
    _warn(fig)
    new, thresholds, findings = _relearn_thresholds(base, ref.model, recs, args.model, args.accept_fault_evidence)
    entry = {"version": len(base.history) + 1, "parent": str(args.model), "added": effects,
             "effects": list(ref.model.meta["effects"]), "nrmse_before": fig["nrmse_before"],
             "nrmse_control": fig["nrmse_control"], "nrmse_after": fig["nrmse_after"], "params": fig["params"],
             "nrmse_basis": NRMSE_BASIS, "thresholds": thresholds,
             **({"accepted_fault_evidence": findings} if findings else {}),
             "records": [r.source for r in recs], "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    new.history = list(base.history) + [entry]
    save_baseline(new, args.out, replace=False)
    warn_fault_evidence("model add-effect", findings)
    doc = {"model": str(args.out), "effect": effects[0] if len(effects) == 1 else effects,
           "nrmse_before": fig["nrmse_before"], "nrmse_after": fig["nrmse_after"],
           "nrmse_control": fig["nrmse_control"], "params": fig["params"], "params_bound": fig["params_bound"],
           "base": fig["base"],
           "version": entry["version"], "parent": str(args.model), "warnings": fig["warnings"],
           "thresholds": thresholds, "accepted_fault_evidence": findings,
           "th3_change": float((new.thresholds.th3.mean() / base.thresholds.th3.mean()) - 1)
           if new.thresholds.th3.size == base.thresholds.th3.size else None}
    _emit(args, doc, (f"wrote {args.out} (version {entry['version']}, effects {', '.join(entry['effects'])})\n"
                      f"held-out free-run NRMSE beyond the noise floor: before {_pct(fig['nrmse_before'])}, control "
                      f"{_pct(fig['nrmse_control'])}, with {'+'.join(effects)} {_pct(fig['nrmse_after'])}\n"
                      + "\n".join(f"  {e}: {params_text(p, bounds=fig['params_bound'].get(e))}"
                                  for e, p in fig["params"].items())
                      + (f"\n{BOUND_LEGEND}" if any(v is not None for b in fig["params_bound"].values()
                                                   for v in (b or {}).values()) else "")
                      + f"\nthresholds and cluster: {thresholds['action']} ({thresholds['reason']})"
                      + (f"; {thresholds['note']}" if "note" in thresholds else "")))


def _relearn_thresholds(parent, model, recs, parent_path: str, accept_fault_evidence: bool):
    """The new version's baseline with ``model``: thresholds, cluster and alarm statistics relearned
    on ``recs`` when they are healthy records at the parent's operating point (the checks of
    :func:`agent.training.check_training`, the parent reading them as the baseline they replace),
    else the parent's kept. Returns (baseline, {"action": "relearned"/"kept", "reason"}, the fault
    evidence accepted). Fault evidence at the operating point is refused (InputError) unless
    ``accept_fault_evidence``."""
    from dataclasses import replace

    from agent.baseline import identify_baseline
    from agent.training import at_operating_point, check_spread, check_training

    keep = ("form", "robust", "window_s", "prefilter_hz", "confidence", "region", "spectrum_rule")
    settings = {k: v for k, v in parent.settings.items() if k in keep}
    window_s = settings.get("window_s", 2.0)
    short = [r.source for r in recs if r.duration_s < window_s]

    def kept(reason):
        op = parent.operating_point
        note = (f"they were learned with the parent's model, whose residual differs from this one's, so this "
                f"version judges no record (diagnose and the agent say no_model) until they are relearned on at "
                f"least 4 healthy records at load {op['load_pct']:.1f} %, fe {op['fe_hz']:.2f} Hz")
        marked = {**parent.settings,
                  "thresholds_of_parent": parent.settings.get("thresholds_of_parent") or f"the parent model {parent_path}"}
        return (replace(parent, model=model, training=[], settings=marked),
                {"action": "kept", "reason": reason, "note": note}, [])

    if len(recs) < 4 or short:
        return kept(f"relearning needs at least 4 healthy records of at least {window_s:g} s at the model's "
                    f"operating point, got {len(recs)}" + (f", too short: {', '.join(short)}" if short else ""))
    new = identify_baseline(recs, parent.profile, model=model, **settings)
    try:
        check_spread(new.training)
    except InputError as err:
        return kept(str(err))
    far = [f"{r.source} load {r.operating_point['load_pct']:.1f} % fe {r.operating_point['fe_hz']:.2f} Hz"
           for r in new.training if not at_operating_point(parent, r.operating_point)]
    if far:
        op = parent.operating_point
        return kept(f"records away from the model's operating point (load {op['load_pct']:.1f} %, fe "
                    f"{op['fe_hz']:.2f} Hz): {', '.join(far)}")
    findings = check_training(new.training, baseline=new, replaced=parent, replaced_name=f"--model {parent_path}",
                              accept_fault_evidence=accept_fault_evidence)
    return new, {"action": "relearned", "reason": f"{len(recs)} healthy records at the model's operating point"
                 + (" (fault evidence accepted)" if findings else "")}, findings


def cmd_history(args) -> None:
    from agent.modelfile import load_baseline

    given = {m for m in (args.model, args.model_flag) if m}
    if len(given) != 1:
        raise InputError("model history: give one model file (--model M)" if not given else
                         f"model history: two model files given ({', '.join(sorted(given))}); give one")
    args.model = given.pop()
    base = load_baseline(args.model)
    versions = [{"version": 0, "effects": [], "note": "baseline (identify)"}] + list(base.history)
    doc = {"model": str(args.model), "effects": list(base.model.meta.get("effects", [])), "versions": versions}
    lines = [f"{args.model}: effects {', '.join(doc['effects']) or '(none)'}"]
    for v in versions:
        lines.append(f"  v{v['version']}: " + (v.get("note") or
                     f"+{'+'.join(v['added'])} from {v['parent']} at {v['timestamp']}: held-out NRMSE "
                     f"{_pct(v['nrmse_before'])} -> {_pct(v['nrmse_after'])}"
                     + ("" if v.get("nrmse_basis") == NRMSE_BASIS else " (raw figures: written before the "
                                                                      "figure left out the noise floor)")))
    _emit(args, doc, "\n".join(lines))


def add_commands(sub, common) -> None:
    p = sub.add_parser("model", help="model workbench: compare, explain, add-effect, history")
    msub = p.add_subparsers(dest="model_command", required=True, metavar="ACTION")
    s = msub.add_parser("compare", parents=[common], help="fit of a model on records, and where it fails")
    s.add_argument("--model", required=True, action="append", help="model file (repeat to compare several)")
    s.add_argument("--report", metavar="DIR", help="write an HTML report with plots into DIR")
    s.add_argument("--one-step", action="store_true", help="report one-step prediction instead of free run")
    s.add_argument("--no-rank", dest="rank", action="store_false", help="leave the effect ranking out of the report")
    s.add_argument("data", nargs="+", help="records (CSV, NPZ, TDMS)")
    s.set_defaults(func=cmd_compare)
    s = msub.add_parser("explain", parents=[common], help="rank the physical effects the model lacks")
    s.add_argument("--model", required=True, help="model file (JSON)")
    s.add_argument("--effect", action="append", metavar="ID", help="only these candidates (repeatable)")
    s.add_argument("--report", metavar="DIR", help="write an HTML report with plots into DIR")
    s.add_argument("data", nargs="+", help="records (CSV, NPZ, TDMS)")
    s.set_defaults(func=cmd_explain)
    s = msub.add_parser("add-effect", parents=[common], help="refit with an effect, write a new model version")
    s.add_argument("--model", required=True, help="model file to refit (JSON; it is never overwritten)")
    s.add_argument("--effect", required=True, action="append", metavar="ID", help="effect id (repeatable)")
    s.add_argument("--out", required=True, help="new model file")
    from agent.cli import accept_fault_evidence_flag

    accept_fault_evidence_flag(s)
    s.add_argument("data", nargs="+", help="records; the thresholds and cluster are relearned on them when they are "
                   "at least 4 healthy records at the model's operating point, else the model's are kept")
    s.set_defaults(func=cmd_add_effect)
    s = msub.add_parser("history", parents=[common], help="versions of a model file")
    s.add_argument("model", nargs="?", help="model file")
    s.add_argument("--model", dest="model_flag", metavar="MODEL", help="model file, as the other actions take it")
    s.set_defaults(func=cmd_history)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use: pmsm-agent model ...")
