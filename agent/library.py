"""Model library: healthy baselines at several operating points, scheduled by (fe, load).

The paper's outlook (section 6): "a set of the healthy state-space model and the residual current
spectrum threshold will be identified ... for each combination of the operating frequency and
load ... similar to gain scheduling". A library is a directory of model files (one baseline
each); the nearest *valid* baseline is scheduled, with hysteresis so that an operating point
between two baselines does not flip between them every window. Outside every baseline's range
there is no model (the agent reports quality ``no_model`` and raises no alarm).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from agent.baseline import Baseline
from agent.errors import InputError
from agent.evidence import FULL_EVIDENCE_STRETCHES
from agent.modelfile import load_baseline, save_baseline

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Schedule:
    """Validity range around a baseline's operating point and the switching hysteresis."""

    fe_tol_hz: float = 2.0  #: valid within +-2 Hz of the baseline's electrical frequency
    load_tol_pct: float = 5.0  #: valid within +-5 %-points of its load (the paper's Table 5: models do not
    #: transfer between 73 and 80 % load)
    hysteresis: float = 0.2  #: a new baseline must be this much closer (normalised distance) to take over


class ModelLibrary:
    """Baselines in ``directory`` (``*.json``); corrupt files are skipped with a log line."""

    def __init__(self, directory: str | Path, schedule: Schedule = Schedule()):
        self.directory = Path(directory)
        self.schedule = schedule
        self.baselines: dict[str, Baseline] = {}
        self.errors: dict[str, str] = {}
        self.reload()

    def reload(self) -> None:
        """(Re)read every model file; a bad file never replaces a good one already loaded."""
        found, errors = {}, {}
        for path in sorted(self.directory.glob("*.json")) if self.directory.is_dir() else []:
            try:
                found[path.stem] = load_baseline(path)
                if path.stem not in self.baselines:
                    _note_thin_evidence(path.stem, found[path.stem])
            except InputError as err:
                errors[path.stem] = str(err)
                if path.stem in self.baselines:
                    found[path.stem] = self.baselines[path.stem]
                log.warning("model library: %s", err)
        self.baselines, self.errors = found, errors

    def add(self, name: str, baseline: Baseline) -> Path:
        """Write a new baseline atomically and make it schedulable."""
        _note_thin_evidence(name, baseline)
        path = save_baseline(baseline, self.directory / f"{name}.json")
        self.baselines[name] = baseline
        return path

    def remove(self, name: str) -> None:
        """Take a baseline out of the library and delete its file (``learn --replace``)."""
        (self.directory / f"{name}.json").unlink(missing_ok=True)
        self.baselines.pop(name, None)

    def distance(self, name: str, fe_hz: float, load_pct: float) -> float:
        """Normalised distance of an operating point from a baseline's; <= 1 means within range."""
        op = self.baselines[name].operating_point
        s = self.schedule
        return max(abs(fe_hz - op["fe_hz"]) / s.fe_tol_hz, abs(load_pct - op["load_pct"]) / s.load_tol_pct)

    def select(self, fe_hz: float, load_pct: float, current: str | None = None) -> str | None:
        """Name of the baseline to use at (fe, load), keeping ``current`` unless another is clearly closer."""
        if not self.baselines or fe_hz != fe_hz or load_pct != load_pct:
            return None
        dist = {name: self.distance(name, fe_hz, load_pct) for name in self.baselines}
        best = min(dist, key=dist.get)
        if dist[best] > 1.0:
            return None
        if current in dist and dist[current] <= 1.0 and dist[current] <= dist[best] + self.schedule.hysteresis:
            return current
        return best


def _note_thin_evidence(name: str, baseline: Baseline) -> None:
    """A log line when a baseline holds less healthy evidence than the default commissioning: its
    alarm thresholds are wider (docs/method.md, "Alarms"), so faults need to be larger."""
    n = baseline.evidence.n if baseline.evidence is not None else 0
    if n < FULL_EVIDENCE_STRETCHES:
        log.warning("model library: %s holds %d stretches of healthy evidence (commissioning learns %d): its "
                    "alarm thresholds are wider; `pmsm-agent learn` gives the promised false-alarm rate",
                    name, n, FULL_EVIDENCE_STRETCHES)
