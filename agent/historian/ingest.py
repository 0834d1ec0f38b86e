"""From one drive-state sample to history rows: identity, change detection, trend sampling.

A sample is the JSON that :class:`protocols.zenoh_sink.ZenohSink` puts on ``.../<drive>/state``
on every change and every ``period_s``. Per drive (``site``, ``gateway``, ``drive``) the
historian keeps the last state, quality, alarm reason and trend time (:class:`Last`) and turns
each sample into rows:

* ``event`` rows: ``kind = "state"`` when the alarm state differs from the last one (or the
  drive is new), ``"quality"`` likewise for the data quality, ``"reason"`` when the state stays
  raised but the alarm's reason (its path and feature) changes;
* a ``trend`` row with the evidence per family when ``trend_period_s`` has passed since the
  drive's last trend row (by the sample's own time ``t``), on every event, and for a new drive.

Identity: the key's chunks after ``prefix`` and before ``state`` are ``[site...]/[gateway]/drive``
(``<prefix>/<drive>/state`` and ``<prefix>/<site>/<gateway>/<drive>/state`` alike); what the key
lacks comes from the payload: ``drive``, and ``agent`` for the gateway.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from protocols.base import QUALITY_CODES, STATE_CODES

Identity = tuple[str, str, str]  #: (site, gateway, drive)


@dataclass(frozen=True)
class Last:
    """What the historian last recorded of a drive."""

    state: int
    quality: int
    reason_key: str | None  #: identity of the alarm's reason while the state is raised
    trend_t: float | None  #: ``t`` of the last trend row, Unix s


def identity(key: str, doc: dict, prefix: str) -> Identity:
    """(site, gateway, drive) of a sample on ``key``; see the module docstring. ``ValueError``
    when ``doc`` is not a JSON object or no drive name is found."""
    if not isinstance(doc, dict):
        raise ValueError("not a JSON object")
    chunks, pre = key.split("/"), prefix.split("/")
    rest = chunks[len(pre):-1] if chunks[:len(pre)] == pre else chunks[:-1]
    drive = rest[-1] if rest else str(doc.get("drive") or "")
    gateway = rest[-2] if len(rest) >= 2 else str(doc.get("agent") or "")
    if not drive:
        raise ValueError("no drive name in the key or the payload")
    return "/".join(rest[:-2]), gateway, drive


def reason_key(reason) -> str | None:
    """What makes two alarm reasons the same one: path and feature (its numbers move every stretch)."""
    if isinstance(reason, dict):
        return json.dumps([reason.get("path"), reason.get("feature")])
    return None if reason in (None, "") else str(reason)


def _code(doc: dict, name: str, codes: dict) -> int:
    value = doc.get(name)
    code = codes.get(value) if isinstance(value, str) else doc.get(f"{name}_code")
    if not isinstance(code, int) or code not in codes.values():
        raise ValueError(f"'{name}' is {value!r}: one of {', '.join(codes)} expected")
    return code


def _number(x) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) else None


def _text(x) -> str:
    """A string PostgreSQL's text takes (no NUL characters)."""
    return str(x or "").replace("\x00", "")


def json_safe(x):
    """``x`` with non-finite numbers as ``None`` and NUL characters dropped (jsonb refuses both)."""
    if isinstance(x, dict):
        return {_text(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, float):
        return _number(x)
    return _text(x) if isinstance(x, str) else x


def sample_rows(ident: Identity, doc: dict, last: Last | None, *, trend_period_s: float,
                received_t: float) -> tuple[list[tuple[str, dict]], Last]:
    """``([(table, row), ...], new Last)`` for one sample of the drive ``ident`` (see :func:`identity`);
    ``ValueError`` if it is not a drive state. ``t`` is the sample's own time (Unix s), else ``received_t``."""
    state, quality = _code(doc, "state", STATE_CODES), _code(doc, "quality", QUALITY_CODES)
    t = _number(doc.get("t"))
    t = t if t and t > 0 else received_t
    reason = json_safe(doc.get("reason")) or None
    rkey = reason_key(reason) if state > 0 else None
    site, gateway, drive = ident
    base = {"site": site, "gateway": gateway, "drive": drive, "t": t, "state": state, "quality": quality,
            "fe_hz": _number(doc.get("fe_hz")), "load_pct": _number(doc.get("load_pct"))}
    event = {**base, "prev_state": last.state if last else None, "prev_quality": last.quality if last else None,
             "reason": reason, "model": _text(doc.get("model")),
             "spectrum_state": STATE_CODES.get(doc.get("spectrum_state")),
             "cluster_state": STATE_CODES.get(doc.get("cluster_state")),
             "agent": _text(doc.get("agent")), "boot_id": _text(doc.get("boot_id")),
             "seq": doc.get("seq") if isinstance(doc.get("seq"), int) else None}
    rows = []
    if last is None or state != last.state:
        rows.append(("event", {**event, "kind": "state"}))
    if last is None or quality != last.quality:
        rows.append(("event", {**event, "kind": "quality"}))
    if last is not None and state > 0 and state == last.state and rkey != last.reason_key:
        rows.append(("event", {**event, "kind": "reason"}))
    evidence = doc.get("evidence")
    trend_t = last.trend_t if last else None
    if isinstance(evidence, dict) and evidence and (
            rows or trend_t is None or t - trend_t >= trend_period_s or t < trend_t):
        rows.append(("trend", {**base, "evidence": {_text(k): _number(v) for k, v in evidence.items()}}))
        trend_t = t
    return rows, Last(state, quality, rkey, trend_t)
