"""``pmsm-agent learn``: commission a baseline for one drive at one operating point.

The same learning code as the running agent (:meth:`agent.pipeline.DriveMonitor.start_learning`),
fed from recorded files (``REC...``, each a separate stream, in the order given) or, without
files, from the drive's configured live source. The baseline is written into the drive's library
only when learning completes and every check passes; otherwise the command exits 2 with the
reason and the library is unchanged:

* not enough healthy evidence (``pipeline.learn_stretches`` stretches over ``pipeline.learn_min_s``):
  the refusal says how many more minutes of steady operation, at which load, the pipeline's own
  rule needs (:attr:`agent.pipeline.DriveMonitor.learn_remaining_s`);
* speed or load spread beyond the operating-point tolerance (``pipeline.schedule_*_tol``);
* too many unusable spans (NaN, saturation) or a drive that is not running;
* a valid baseline already covers the operating point, checked before any learning (from files: their
  operating point; live: the first span); ``--replace`` replaces the baseline that covers it, whatever
  its name (a different ``--name`` writes the new one and deletes the old); a ``--name`` that belongs
  to a baseline at another point is refused;
* from files, the training-data checks of :func:`agent.training.check_training` (one line naming the
  files): their operating points spread beyond the tolerance, or a file reads as faulty against the
  baseline it replaces (before learning) or against the others (after learning, before the write).
  ``--accept-fault-evidence`` learns anyway and writes a ``learning`` event saying so into the
  journal of the agent's ``state_dir``;
* live with ``--replace``, a drive that reads as faulty against the baseline it replaces (the
  training guard's rule on the first ``pipeline.persist_hops`` spans, before any learning): learning would make the fault the new
  normal (:meth:`agent.pipeline.DriveMonitor.relearn`, as for the PLC's relearn);
  ``--accept-fault-evidence`` learns anyway.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time

import numpy as np

from agent.errors import InputError

log = logging.getLogger("pmsm-agent.learn")


def _drive(cfg, name: str):
    for d in cfg.drives:
        if d.name == name:
            return d
    raise InputError(f"--drive {name!r}: no such drive in {cfg.source} (drives: {', '.join(d.name for d in cfg.drives)})")


def _file_records(files: list[str], profile) -> list:
    """Each file as a training record: its operating point, and its signals computed again when
    needed (a file set is never held in memory at once)."""
    from agent.baseline import TrainingRecord
    from agent.identify import operating_point, record_signals
    from agent.records import load_record

    def signals(path):
        return lambda: record_signals(load_record(path, profile), profile)

    return [TrainingRecord(path, operating_point(signals(path)(), profile), signals(path)) for path in files]


def learn(cfg, drive_name: str, files: list[str], name: str | None = None, replace: bool = False,
          progress=None, max_seconds: float | None = None, accept_fault_evidence: bool = False) -> dict:
    """Learn a baseline for ``drive_name``; returns what was learned, raises InputError with the
    reason when learning refuses or the data runs out (``progress(pct, text)`` as it goes)."""
    from dataclasses import replace as replace_field

    from agent.cli import distinct_records
    from agent.library import ModelLibrary, Schedule
    from agent.pipeline import DriveMonitor, covered_text
    from agent.runtime.service import build_source, pipeline_config
    from agent.training import check_spread, check_training, training_record

    drive = _drive(cfg, drive_name)
    distinct_records(files)
    p = cfg.pipeline
    library = ModelLibrary(cfg.library.path, Schedule(p.schedule_fe_tol_hz, p.schedule_load_tol_pct,
                                                      p.schedule_hysteresis))
    findings: list[str] = []
    vet = None
    if files:  # before any learning: spread, the baseline that covers the point, its reading of the files
        training = _file_records(files, drive.drive_profile)
        check_spread(training, library.schedule)
        op = {k: float(np.median([r.operating_point[k] for r in training])) for k in ("fe_hz", "load_pct")}
        covering = library.select(op["fe_hz"], op["load_pct"])
        if covering is not None and not replace:
            raise InputError(f"learning refused for drive {drive.name}: {covered_text(covering, op)}; the library "
                             f"is unchanged")
        _check_name(library, name, covering)
        replaced = library.baselines[covering] if covering is not None else None
        findings += check_training(training, library.schedule, replaced=replaced, replaced_name=f"baseline {covering}",
                                   accept_fault_evidence=accept_fault_evidence)

        def vet(baseline):  # then each file against the others, with the learned model, before the write
            seen = [replace_field(training_record(baseline, r.signals(), r.source), signals=r.signals)
                    for r in training]
            findings.extend(f for f in check_training(seen, library.schedule, baseline=baseline,
                                                      accept_fault_evidence=accept_fault_evidence)
                            if f not in findings)
            baseline.model.meta.update({"accepted_fault_evidence": findings} if findings else {})
    events: list[tuple[str, dict]] = []

    def on_event(kind, detail):
        events.append((kind, detail))
        if kind == "learning" and progress is not None:
            progress(detail.get("progress_pct", 0.0), detail.get("phase", ""), detail.get("remaining_s", 0.0))

    if not files:
        _check_name(library, name, None)
    pcfg = pipeline_config(cfg)
    lengths: list[float] = []  #: s, the files learned from
    seen: list = []  #: every status of the learning (why it made no progress)
    monitor = DriveMonitor(drive.name, drive.drive_profile, library, pcfg, on_event=on_event)
    #: a live relearn first reads the drive with the baseline it replaces (persist_hops decisions): one that
    #: reads warning is refused (DriveMonitor.relearn), a fault is not learned as healthy
    reads = 0 if replace and not files else None
    if reads is None:
        monitor.start_learning(name, replace=replace, vet=vet)
    if files:
        from agent.records import load_record
        from protocols.base import Block

        rate, first = drive.drive_profile.sampling.rate_hz, 0
        block = max(1, int(round(0.1 * rate)))
        for path in files:
            rec = load_record(path, drive.drive_profile)
            lengths.append(rec.n / rate)
            for start in range(0, rec.n - block + 1, block):
                cut = slice(start, start + block)
                seen += monitor.process(Block(drive.name, rate, rec.v_abc[:, cut], rec.i_abc[:, cut], first + start, 0,
                                      None if rec.theta_e is None else rec.theta_e[cut],
                                      None if rec.omega_e is None else rec.omega_e[cut]))
                if not monitor.learning:
                    break
            first += rec.n + block  # each file is a stream of its own
            if not monitor.learning:
                break
    else:
        source = build_source(drive, drive.drive_profile.sampling.rate_hz, pcfg.window_s * pcfg.span_windows)
        t_end = None if max_seconds is None else time.monotonic() + max_seconds
        try:
            source.open()
        except Exception as err:  # a link that is not there: the user's to connect or configure
            raise InputError(f"drive {drive.name}: cannot open its {drive.source.kind} source: {err}",
                             source=str(cfg.source)) from err
        try:
            while (monitor.learning or reads is not None) and (t_end is None or time.monotonic() < t_end):
                blk = source.read(timeout=0.5)
                if blk is None:
                    if getattr(source, "finished", False):
                        break
                    continue
                for st in monitor.process(blk):
                    seen.append(st)
                    if reads is None or st.quality not in ("good", "no_model"):
                        continue
                    reads = reads + 1 if st.quality == "good" else pcfg.persist_hops  # no_model: nothing to replace
                    if reads >= pcfg.persist_hops:
                        reads, reading = None, monitor.fault_evidence()
                        if monitor.relearn(name, accept_fault_evidence) is not None:
                            break
                        findings += [f"live data ({reading})"] if reading else []
                if reads is None and not monitor.learning:
                    break
        finally:
            source.close()
    if reads is not None:  # a live relearn that never got to read the drive with the baseline it replaces
        last = f"; its last status: {seen[-1].quality}, {seen[-1].extra.get('reason')}" if seen else ""
        raise InputError(f"learning not started for drive {drive.name}: no usable span to read the drive with the "
                         f"baseline it replaces within --max-seconds{last}; the library is unchanged")
    refused = [d["reason"] for k, d in events if k == "learning_refused"]
    if refused:
        raise InputError(f"learning refused for drive {drive.name}: {refused[-1]}; the library is unchanged")
    learned = [d for k, d in events if k == "learned"]
    idle = [st.extra["reason"] for st in seen if str(st.extra.get("reason") or "").startswith("not running")]
    if not learned and seen and len(idle) == len(seen):
        raise InputError(f"nothing to learn for drive {drive.name}: the drive was not running in any span "
                         f"({idle[-1]}); the library is unchanged")
    if not learned:
        span_s = pcfg.window_s * pcfg.span_windows
        usable = float(np.mean(lengths)) - (span_s - pcfg.hop_s) if lengths else 0.0
        per_file = "" if not files else (
            f"; each file gives at most its length less {span_s - pcfg.hop_s:g} s (its first span fills the "
            f"buffer)" + (f": about {_count(math.ceil(monitor.learn_remaining_s / usable - 1e-9), 'more file')} "
                          f"of {np.mean(lengths):.0f} s" if usable > 0 else "")
            + f", and a load or speed move holds {pcfg.alarm.settle_s:g} s more")
        short = [f for f, n in zip(files, lengths) if n < span_s]
        per_file += f"; shorter than one span ({span_s:g} s), so nothing learned from: {', '.join(short)}" if short else ""
        stopped = f"; the drive was not running in {len(idle)} of {len(seen)} spans" if idle else ""
        raise InputError(f"not enough healthy data for drive {drive.name}: "
                         f"{monitor.learn_needs_text(monitor.learning_point)}{stopped} (the rule: {p.learn_windows} spans of "
                         f"{span_s:g} s for the parameters, then {p.learn_stretches} stretches of {p.stretch_s:g} s "
                         f"over at least {p.learn_min_s / 60:g} min of steady operation, {_minutes(pcfg.learn_total_s)} "
                         f"in all{per_file}); the library is unchanged")
    doc = {"drive": drive.name, **learned[-1], "accepted_fault_evidence": findings}
    if findings:
        from agent.runtime.journal import Journal

        with Journal.from_config(cfg) as journal:
            journal.record("learning", drive.name, detail={
                "event": "fault_evidence_accepted", "name": doc["name"], "path": doc["path"],
                "msg": f"learned {doc['name']} from records with fault evidence (--accept-fault-evidence)",
                "records": findings})
    return doc


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds >= 90 else f"{seconds:g} s"


def _check_name(library, name: str | None, covering: str | None) -> None:
    """``--name`` must not be a baseline at another operating point (it would be overwritten)."""
    if name is not None and name in library.baselines and name != covering:
        op = library.baselines[name].operating_point
        raise InputError(f"--name {name}: a baseline of that name covers another operating point (fe "
                         f"{op['fe_hz']:.2f} Hz, load {op['load_pct']:.1f} %); choose another name; the library is "
                         f"unchanged")


def cmd_learn(args) -> None:
    from agent.cli import warn_fault_evidence
    from agent.runtime.config import check_config

    cfg = check_config(args.config)

    def progress(pct, phase, remaining_s):
        log.info("learning %s: %.0f %%%s, about %s more of steady operation", args.drive, pct,
                 f" ({phase})" if phase else "", _minutes(remaining_s))

    doc = learn(cfg, args.drive, args.data, name=args.name, replace=args.replace, progress=progress,
                max_seconds=args.max_seconds, accept_fault_evidence=args.accept_fault_evidence)
    warn_fault_evidence("learn", doc["accepted_fault_evidence"])
    if args.json:
        json.dump(doc, sys.stdout)
        sys.stdout.write("\n")
    else:
        op = doc["operating_point"]
        print(f"learned {doc['name']} for drive {doc['drive']} -> {doc['path']} (fe {op['fe_hz']:.2f} Hz, "
              f"load {op['load_pct']:.1f} %, {doc['stretches']} stretches)")


def add_commands(sub, common) -> None:
    """Add ``learn`` to the ``pmsm-agent`` subparsers."""
    from agent.cli import accept_fault_evidence_flag
    from agent.cliargs import number

    s = sub.add_parser("learn", parents=[common], help="commission a baseline for one drive (from files or the live source)")
    s.add_argument("--config", required=True, metavar="FILE", help="agent config TOML (the drive, its library)")
    s.add_argument("--drive", required=True, help="the drive's name in the config")
    s.add_argument("--name", help="baseline name (default: <drive>_<fe>hz_<load>pct)")
    s.add_argument("--replace", action="store_true",
                   help="replace the baseline of this --name if it covers the operating point (never implicit)")
    s.add_argument("--max-seconds", type=number(0, None, low_open=True, unit="s"), default=None,
                   help="live source only: give up after this many seconds of wall time")
    accept_fault_evidence_flag(s)
    s.add_argument("data", nargs="*", metavar="REC", help="recorded files (CSV/NPZ/TDMS); none: the live source")
    s.set_defaults(func=cmd_learn)
