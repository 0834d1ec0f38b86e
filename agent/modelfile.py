"""Model files: a healthy baseline (model, thresholds, cluster, profile) as versioned JSON.

Written atomically (temporary file, fsync, rename) so a crash never leaves half a model behind.
A file that is not JSON, lacks a key, or has another format version is an ``InputError`` naming
the file.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import asdict
from pathlib import Path

import numpy as np

from agent.baseline import Baseline, Cluster, Thresholds
from agent.errors import InputError
from agent.evidence import EvidenceStats
from agent.model import DQModel
from agent.profile import parse_profile

FORMAT = "pmsm-agent-model"
VERSION = 1


def _arr(a) -> list:
    return np.asarray(a, dtype=float).tolist()


def baseline_to_json(b: Baseline) -> dict:
    m, th, cl = b.model, b.thresholds, b.cluster
    prof = asdict(b.profile)
    name = prof.pop("name")
    return {
        "format": FORMAT, "version": VERSION,
        "profile": {"name": name, **{k: {kk: vv for kk, vv in v.items() if vv is not None}
                                     for k, v in prof.items() if v is not None}},
        "operating_point": b.operating_point,
        "model": {"form": m.form, "ts": m.ts, "fe_hz": m.fe_hz, "discretisation": m.discretisation,
                  "theta_d": _arr(m.theta_d),
                  "theta_q": _arr(m.theta_q), "effects": m.meta.get("effects", []),
                  # the coefficients read as R, L, psi at the operating point: not physical values where
                  # the records cannot separate them (those, with intervals, are the top-level "physical")
                  "lumped_equivalent": m.physical(), "meta": {k: v for k, v in m.meta.items() if k != "effects"}},
        "thresholds": {"freqs_hz": _arr(th.freqs_hz), "centre": _arr(th.centre), "spread": _arr(th.spread),
                       "window_s": th.window_s, "robust": th.robust, "search_bins": th.search_bins},
        "cluster": {"points": _arr(cl.points), "centre": _arr(cl.centre), "cov": _arr(cl.cov),
                    "limit": cl.limit, "confidence": cl.confidence, "region": cl.region},
        "records": b.records, "settings": b.settings, "history": b.history,
        **({"evidence": b.evidence.to_json()} if b.evidence is not None else {}),
        **({"physical": b.physical} if b.physical is not None else {}),
    }


def baseline_from_json(doc: dict, source: str = "<model>") -> Baseline:
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"not a {FORMAT} file", source=source)
    if doc.get("version") != VERSION:
        raise InputError(f"unsupported model version {doc.get('version')!r} (this build reads {VERSION})",
                         source=source)
    try:
        m, th, cl = doc["model"], doc["thresholds"], doc["cluster"]
        extra_d, extra_q = effect_terms(m.get("effects", []), source)
        model = DQModel(m["form"], float(m["ts"]), np.array(m["theta_d"]), np.array(m["theta_q"]),
                        extra_d, extra_q, fe_hz=float(m["fe_hz"]), meta={**m.get("meta", {}), "effects": m.get("effects", [])},
                        discretisation=_discretisation(m.get("discretisation", "euler"), source))
        return Baseline(
            profile=parse_profile(doc["profile"], source=source), model=model,
            thresholds=Thresholds(np.array(th["freqs_hz"]), np.array(th["centre"]), np.array(th["spread"]),
                                  float(th["window_s"]), bool(th["robust"]), int(th["search_bins"])),
            cluster=Cluster(np.array(cl["points"]), np.array(cl["centre"]), np.array(cl["cov"]),
                            float(cl["limit"]), float(cl["confidence"]), cl["region"]),
            operating_point=doc["operating_point"], records=list(doc.get("records", [])),
            settings=dict(doc.get("settings", {})), history=list(doc.get("history", [])),
            evidence=EvidenceStats.from_json(doc["evidence"]) if "evidence" in doc else None,
            physical=doc.get("physical"))
    except InputError:
        raise
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"corrupt model file ({type(err).__name__}: {err})", source=source) from None


def _discretisation(name, source: str) -> str:
    if name not in ("euler", "zoh2"):
        raise InputError(f"model.discretisation {name!r} is not 'euler' or 'zoh2'", source=source)
    return name


def effect_terms(effects: list, source: str):
    """Regressor terms (d, q) of a model's named effects, from the workbench's effect library."""
    if not effects:
        return (), ()
    try:
        from agent.effects import model_terms
    except ImportError:
        raise InputError(f"model uses effects {effects} but this build has no effect library", source=source) from None
    try:
        return model_terms(effects)
    except InputError as err:
        raise InputError(str(err), source=source) from None


def save_baseline(b: Baseline, path: str | Path, replace: bool = True) -> Path:
    """Write ``b`` to ``path`` atomically; with ``replace`` False an existing file is an InputError."""
    return write_atomic(path, json.dumps(baseline_to_json(b), indent=1).encode(), replace)


def load_baseline(path: str | Path) -> Baseline:
    path = Path(path)
    try:
        doc = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise InputError("no such model file", source=str(path)) from None
    except (OSError, ValueError) as err:
        raise InputError(f"corrupt model file ({err})", source=str(path)) from None
    return baseline_from_json(doc, source=str(path))


def write_atomic(path: str | Path, data: bytes, replace: bool = True) -> Path:
    """Write ``data`` to ``path`` via a temporary file in the same folder, fsync and rename; a
    failure leaves any old file as it was and is an InputError naming ``path``. With ``replace``
    False the rename is a hard link, which fails if ``path`` exists, so a file that appeared while
    the caller worked is kept too."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if replace:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
            os.unlink(tmp)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except BaseException as err:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(err, FileExistsError):
            raise InputError("exists; a model version is never overwritten (choose a new file)",
                             source=str(path)) from None
        if isinstance(err, OSError):  # a folder there, no space, no permission (as save_record says it)
            raise InputError(f"cannot write model: {err.strerror or err}", source=str(path)) from err
        raise
    return path
