"""Healthy baseline (paper Algs. 2-4): model, residual-spectrum thresholds, parameter cluster.

* Alg. 2: identify each healthy record, average the parameters (median with ``robust=True``).
* Alg. 3: residual of phase a (measured minus free-run model current), windowed amplitude
  spectrum of every window (``window_s``) of every record, per-bin centre and spread; TH2 = centre + 2 spread,
  TH3 = centre + 3 spread. Centre/spread are mean/standard deviation, or median/1.4826 MAD with
  ``robust=True`` so that one outlier record cannot hide a fault.
* Alg. 4: per record the point (Ts/Lq, B_GT); the healthy region is an ellipse of Mahalanobis
  distance at ``confidence`` (default 95 %). ``region="prediction"`` (default) uses the Hotelling
  prediction ellipse, which accounts for estimating the centre and covariance from m records;
  ``region="chi2"`` uses the chi-square quantile as the paper's large-sample approximation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from agent.errors import InputError
from agent.evidence import EvidenceStats, Feature, feature_values, make_features
from agent.identify import (PREFILTER_HZ, FitResult, cluster_point, constrain, fit_record, operating_point,
                            record_signals, refine_output_error)
from agent.physical import Estimate, Observation, estimate, observe
from agent.voltage_path import corrected
from agent.model import DQModel, Signals
from agent.profile import DriveProfile
from agent.records import Record
from agent.sanity import not_running
from agent.spectrum import amplitude_spectrum, envelope

WINDOW_S = 2.0  #: residual-spectrum window, s (0.5 Hz resolution)
SEARCH_BINS = 1  #: a fault line is read as the largest bin within this many bins of it
F_MAX_HZ = 1000.0  #: highest frequency kept in the thresholds, Hz
MAD_SCALE = 1.4826  #: MAD -> standard deviation for normal data


def residual_phase_a(model: DQModel, sig: Signals) -> np.ndarray:
    """Phase-a residual current r_a = i_a - i_a_model (A), free-run model (Alg. 3 lines 4-6):
    the first row of the inverse Park and Clarke transforms, r_a = r_d cos(theta) - r_q sin(theta)."""
    r_d, r_q = sig.i_dq - model.simulate(sig)
    c, s = sig.cos_sin if sig.cos_sin is not None else (np.cos(sig.theta_e), np.sin(sig.theta_e))
    return r_d * c - r_q * s


def residual_spectra(model: DQModel, sig: Signals, window_s: float = WINDOW_S,
                     f_max_hz: float = F_MAX_HZ) -> tuple[np.ndarray, np.ndarray]:
    """Phase-a residual amplitude spectra (n_windows, bins) of consecutive windows of ``window_s``.

    The free-run simulation restarts from the measured current at each window's start, so a
    window's spectrum depends on that window only: a record and a stream cut into the same windows
    give the same spectra."""
    n_w = int(round(window_s / sig.ts))
    if sig.n < n_w:
        raise ValueError(f"{sig.n} samples are fewer than one window of {n_w}")
    parts = [residual_phase_a(model, sig.slice(j * n_w, (j + 1) * n_w)) for j in range(sig.n // n_w)]
    return window_spectra(np.concatenate(parts), 1.0 / sig.ts, window_s, f_max_hz)


def window_spectra(x: np.ndarray, rate_hz: float, window_s: float = WINDOW_S,
                   f_max_hz: float = F_MAX_HZ) -> tuple[np.ndarray, np.ndarray]:
    """Amplitude spectra (n_windows, bins) of ``x`` in consecutive windows of ``window_s`` s, up to ``f_max_hz``."""
    n_w = int(round(window_s * rate_hz))
    n_seg = x.size // n_w
    if n_seg < 1:
        raise ValueError(f"{x.size} samples are fewer than one window of {n_w}")
    freqs, amp = amplitude_spectrum(x[: n_seg * n_w].reshape(n_seg, n_w), rate_hz)
    keep = freqs <= f_max_hz
    return freqs[keep], amp[:, keep]


def centre_spread(values: np.ndarray, robust: bool, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and sample standard deviation, or median and scaled MAD, along ``axis``."""
    if robust:
        med = np.median(values, axis=axis)
        return med, MAD_SCALE * np.median(np.abs(values - np.expand_dims(med, axis)), axis=axis)
    return values.mean(axis=axis), values.std(axis=axis, ddof=1)


@dataclass
class Thresholds:
    """Per-bin residual-spectrum statistics (Alg. 3).

    The statistics are taken of each healthy spectrum's envelope (largest bin within
    ``search_bins``), the same statistic the decision reads at a fault line, so that searching
    a line between bins does not by itself raise the false-alarm rate."""

    freqs_hz: np.ndarray
    centre: np.ndarray
    spread: np.ndarray
    window_s: float = WINDOW_S
    robust: bool = False
    search_bins: int = SEARCH_BINS  #: statistics are of the spectrum's envelope over +-search_bins

    @property
    def th2(self) -> np.ndarray:
        return self.centre + 2.0 * self.spread

    @property
    def th3(self) -> np.ndarray:
        return self.centre + 3.0 * self.spread


@dataclass
class Cluster:
    """Healthy region of the (Ts/Lq, B_GT) parameter cluster (Alg. 4)."""

    points: np.ndarray  #: (m, 2) healthy points
    centre: np.ndarray
    cov: np.ndarray
    limit: float  #: squared Mahalanobis distance at the region's edge
    confidence: float = 0.95
    region: str = "prediction"

    def limit_at(self, confidence: float) -> float:
        """Squared Mahalanobis distance at the edge of this cluster's region at another ``confidence``."""
        return region_limit(self.region, confidence, *self.points.shape)

    def distance2(self, point) -> float:
        """Squared Mahalanobis distance of ``point`` from the healthy centre."""
        d = np.asarray(point, dtype=float) - self.centre
        return float(d @ np.linalg.solve(self.cov, d))

    @classmethod
    def fit(cls, points: np.ndarray, confidence: float = 0.95, region: str = "prediction",
            robust: bool = False) -> "Cluster":
        m, p = points.shape
        if m <= p + 1:
            raise ValueError(f"need at least {p + 2} records for the parameter cluster, got {m}")
        centre, cov = points.mean(axis=0), np.cov(points, rowvar=False)
        if robust:  # one reweighting step from median/MAD: drop points far outside, refit
            med, mad = centre_spread(points, robust=True)
            z2 = np.sum(((points - med) / np.where(mad > 0, mad, 1.0)) ** 2, axis=1)
            inliers = points[z2 <= chi2_quantile(0.975, p)]
            if len(inliers) > p + 1:
                centre, cov = inliers.mean(axis=0), np.cov(inliers, rowvar=False)
        cov = cov + np.eye(p) * 1e-12 * np.trace(cov)
        return cls(points, centre, cov, region_limit(region, confidence, m, p), confidence, region)


def region_limit(region: str, confidence: float, m: int, p: int) -> float:
    """Squared Mahalanobis distance at the edge of the healthy region of ``m`` points in ``p``
    dimensions: the Hotelling prediction ellipse (``"prediction"``) or the chi-square one."""
    if region == "chi2":
        return float(chi2_quantile(confidence, p))
    if region == "prediction":
        return float(p * (m - 1) * (m + 1) / (m * (m - p)) * f_quantile(confidence, p, m - p))
    raise ValueError(f"unknown cluster region {region!r} (prediction, chi2)")


def chi2_quantile(q: float, dof: int) -> float:
    """Chi-square quantile; closed form for 2 degrees of freedom (the cluster's), scipy otherwise."""
    if dof == 2:
        return -2.0 * np.log1p(-q)
    import scipy.stats  # noqa: PLC0415 (heavy; only for other dimensions)
    return float(scipy.stats.chi2.ppf(q, dof))


def f_quantile(q: float, dfn: int, dfd: int) -> float:
    """F-distribution quantile; closed form for dfn = 2: F = (dfd/2) ((1-q)^(-2/dfd) - 1)."""
    if dfn == 2:
        return dfd / 2.0 * ((1.0 - q) ** (-2.0 / dfd) - 1.0)
    import scipy.stats  # noqa: PLC0415
    return float(scipy.stats.f.ppf(q, dfn, dfd))


@dataclass
class TrainingRecord:
    """One record as a baseline saw it while learning (for :mod:`agent.training`'s checks)."""

    source: str
    operating_point: dict  #: fe_hz (Hz), load_pct (% of rated torque)
    #: dq signals, or a function that computes them again (to read the record with another baseline)
    signals: Signals | Callable[[], Signals] | None = field(default=None, repr=False)
    spectra: np.ndarray | None = field(default=None, repr=False)  #: residual amplitude spectra (windows, bins), A
    point: np.ndarray | None = None  #: cluster point (Ts/Lq, B_GT)


@dataclass
class Baseline:
    """Everything learned from healthy records at one operating point."""

    profile: DriveProfile
    model: DQModel
    thresholds: Thresholds
    cluster: Cluster
    operating_point: dict
    records: list[str] = field(default_factory=list)
    settings: dict = field(default_factory=dict)
    history: list[dict] = field(default_factory=list)
    evidence: EvidenceStats | None = None  #: healthy statistics of the alarm evidence (agent.evidence)
    physical: dict | None = None  #: physical parameters with intervals (agent.physical.Estimate.to_json)
    training: list[TrainingRecord] = field(default_factory=list, repr=False)  #: what it was learned from
    #: (records given to identify_baseline; this run only, not saved in the model file)

    @property
    def unusable(self) -> str | None:
        """Why this baseline cannot judge records, None when it can: thresholds and cluster kept from
        a parent model by ``model add-effect`` were learned with another residual (they misread
        healthy records), so it must be relearned before monitoring or diagnosis."""
        parent = self.settings.get("thresholds_of_parent")
        if parent:
            return (f"its thresholds and cluster are {parent}'s, learned with that model's residual, not this one's "
                    f"(model add-effect could not relearn them): relearn them with `pmsm-agent model add-effect` on "
                    f"at least 4 healthy records at its operating point, or `pmsm-agent learn`")
        return None


class BaselineBuilder:
    """Algs. 2-4 in two passes over healthy data, so records or streamed windows never need to be
    held in memory together: pass 1 ``add_fit`` (parameters, cluster points), then ``model()``,
    then pass 2 ``add_spectra`` (residual spectra of every window with that model), then ``build()``.
    """

    def __init__(self, profile: DriveProfile, *, form: str = "lumped", robust: bool = False,
                 window_s: float = WINDOW_S, confidence: float = 0.95, region: str = "prediction",
                 prefilter_hz: float | None = PREFILTER_HZ, spectrum_rule: str = "pair"):
        self.profile = profile
        self.settings = {"form": form, "robust": robust, "window_s": window_s, "prefilter_hz": prefilter_hz,
                         "confidence": confidence, "region": region, "spectrum_rule": spectrum_rule}
        self.fits: list[FitResult] = []
        self.observations: list[Observation] = []
        self.spectra: list[np.ndarray] = []
        self.freqs: np.ndarray | None = None
        self.sources: list[str] = []
        self._model: DQModel | None = None
        self._physical: Estimate | None = None
        self._features: list[Feature] | None = None
        # alarm evidence (agent.evidence): per stretch its windows' feature values, cluster point, load
        self.stretch_windows: list[np.ndarray] = []
        self.stretch_cluster: list[np.ndarray] = []
        self.stretch_load: list[float] = []  #: load %, torque over rated torque
        self.stretch_power: list[float] = []  #: input power %, what the cluster's B_GT moves with
        self.stretch_s = 0.0
        self.training: list[TrainingRecord] = []  #: per record of pass 2 (add_spectra)
        self.consecutive = False  #: stretches follow each other in one stream (streaming learning)

    def add_fit(self, sig: Signals, source: str = "", encoder: bool = False) -> FitResult:
        """Pass 1: identify one healthy record or window (Alg. 2 lines 4-8, Alg. 4 lines 6-10).
        With a model set beforehand (``set_model``), the fit carries its form and extra terms, as
        :func:`agent.decision.assess` does for the cluster point."""
        m = self._model
        extra = ((), ()) if m is None else (m.extra_d, m.extra_q)
        fit = fit_record(sig, self.profile, self.settings["form"] if m is None else m.form, extra,
                         prefilter_hz=self.settings["prefilter_hz"], plausible=False)
        self.fits.append(fit)
        sampling = self.profile.sampling
        self.observations.append(observe(corrected(sig, self.profile), encoder, samples=sampling.current_source,
                                         instruments=not sampling.current_window_samples))
        self.sources.append(source)
        return fit

    def physical(self) -> Estimate:
        """Physical parameters (R_s, L_d, L_q, psi_m) from the records so far and the nameplate."""
        if self._physical is None:
            self._physical = estimate(self.observations, self.profile)
        return self._physical

    def model(self) -> DQModel:
        """The baseline model (Alg. 2 line 10) from the fits so far."""
        if self._model is None:
            if len(self.fits) < 4:
                raise ValueError(f"need at least 4 healthy records, got {len(self.fits)}")
            self._model = average_model(self.fits, self.settings["robust"], self.physical().values["psi_m"])
        return self._model

    def set_model(self, model: DQModel) -> None:
        """Use ``model`` (e.g. refined, or with effects) for pass 2."""
        self._model = model

    def features(self) -> list[Feature]:
        """The alarm features (unique sideband pairs) at the fits' median electrical frequency."""
        if self._features is None:
            fe = float(np.median([f.operating_point["fe_hz"] for f in self.fits]))
            window_s = self.settings["window_s"]
            self._features = make_features(self.profile, fe, (SEARCH_BINS + 0.5) / window_s, F_MAX_HZ)
        return self._features

    def add_spectra(self, sig: Signals, source: str = "") -> None:
        """Pass 2: residual spectra of every window of one record (Alg. 3 lines 3-9); the record is
        also one stretch of the alarm evidence."""
        freqs, amp = residual_spectra(self.model(), sig, self.settings["window_s"])
        self.add_window_spectra(freqs, amp)
        m, op = self.model(), operating_point(sig, self.profile)
        point = cluster_point(sig, self.profile, m.form, m.extra_q, self.settings["prefilter_hz"])
        y = feature_values(freqs, amp, self.profile, op["fe_hz"], self.features(), SEARCH_BINS)
        self.add_stretch(y, point, op, sig.n * sig.ts)
        self.training.append(TrainingRecord(source, op, sig, amp, point))

    def add_stretch(self, window_y: np.ndarray, point, op: dict, seconds: float) -> None:
        """One stretch of healthy operation for the alarm evidence: its windows' feature values
        (m, F), its mean cluster point and operating point (``load_pct``, ``input_power_pct``), its
        length (s)."""
        self.stretch_windows.append(np.atleast_2d(window_y))
        self.stretch_cluster.append(np.asarray(point, dtype=float))
        self.stretch_load.append(float(op["load_pct"]))
        self.stretch_power.append(float(op["input_power_pct"]))
        self.stretch_s = seconds if not self.stretch_s else min(self.stretch_s, seconds)

    def add_window_spectra(self, freqs: np.ndarray, amp: np.ndarray) -> None:
        """Pass 2 with spectra (n_windows, bins) computed elsewhere (the streaming pipeline)."""
        self.freqs = freqs
        self.spectra.extend(amp)

    def build(self) -> Baseline:
        """Thresholds (Alg. 3 lines 10-13), cluster region (Alg. 4 line 12) and operating point."""
        st = self.settings
        centre, spread = centre_spread(envelope(np.array(self.spectra), SEARCH_BINS), st["robust"])
        op_all = np.array([[f.operating_point["fe_hz"], f.operating_point["load_pct"]] for f in self.fits])
        op = dict(zip(("fe_hz", "load_pct"), np.median(op_all, axis=0).tolist()))
        op.update(fe_spread_hz=float(np.ptp(op_all[:, 0])), load_spread_pct=float(np.ptp(op_all[:, 1])))
        return Baseline(
            profile=self.profile, model=self.model(),
            thresholds=Thresholds(self.freqs, centre, spread, st["window_s"], st["robust"]),
            cluster=Cluster.fit(np.array([f.cluster_point for f in self.fits]), st["confidence"], st["region"],
                                st["robust"]),
            operating_point=op, records=list(self.sources),
            settings={**st, "records": len(self.fits), "windows": len(self.spectra),
                      "implausible_records": sum(f.reason != "ok" for f in self.fits)},
            evidence=self.evidence(), physical=self.physical().to_json(), training=list(self.training))

    def evidence(self) -> EvidenceStats | None:
        """Healthy statistics of the alarm evidence, or None with fewer than 4 stretches."""
        if len(self.stretch_windows) < 4:
            return None
        return EvidenceStats.fit(self.features(), self.stretch_windows, np.array(self.stretch_cluster),
                                 np.array(self.stretch_power), self.stretch_s, self.profile, self.consecutive)


def identify_baseline(records: list[Record], profile: DriveProfile, *, refine: bool = False, progress=None,
                      model: DQModel | None = None, **settings) -> Baseline:
    """Algs. 2-4 on m healthy records (``settings``: see :class:`BaselineBuilder`); ``refine`` adds the
    output-error refinement of the model; ``progress(i, n, text)`` is called per step when given.
    ``model``: learn thresholds and cluster with this model (e.g. a workbench refit with effects)
    instead of the average of the per-record fits."""
    builder = BaselineBuilder(profile, **settings)
    if model is not None:
        builder.set_model(model)
    m = len(records)
    sigs = []
    for j, rec in enumerate(records):
        if progress:
            progress(j, 2 * m, f"identify {rec.source}")
        sigs.append(record_signals(rec, profile))
        idle = not_running(sigs[-1], profile)
        if idle is not None:
            raise InputError(f"{idle}: not a healthy record of a running drive", source=rec.source)
        builder.add_fit(sigs[-1], rec.source, encoder=rec.theta_e is not None)
    if refine:
        builder.set_model(refine_output_error(builder.model(), sigs))
    for j, (rec, sig) in enumerate(zip(records, sigs)):
        if progress:
            progress(m + j, 2 * m, f"residual spectrum {rec.source}")
        builder.add_spectra(sig, rec.source)
    base = builder.build()
    base.settings["refine"] = refine
    return base


def average_model(fits: list[FitResult], robust: bool = False, psi_m: float | None = None) -> DQModel:
    """Alg. 2 line 10, the baseline parameters from the per-record ones, kept plausible.

    The mean is information-weighted, (sum R_j)^-1 sum R_j theta_j, which is least squares over
    all records together: a record that barely excites a direction does not drag it. With
    ``robust`` the per-record median is used instead (one outlier record cannot move it). An
    implausible result is replaced by the nearest plausible one (:func:`agent.identify.constrain`).
    """
    first = fits[0].model
    info_d, info_q = sum(f.info_d for f in fits), sum(f.info_q for f in fits)
    if robust:
        theta_d = np.median([f.model.theta_d for f in fits], axis=0)
        theta_q = np.median([f.model.theta_q for f in fits], axis=0)
    else:
        theta_d = np.linalg.lstsq(info_d, sum(f.info_d @ f.model.theta_d for f in fits), rcond=None)[0]
        theta_q = np.linalg.lstsq(info_q, sum(f.info_q @ f.model.theta_q for f in fits), rcond=None)[0]
    fe = float(np.median([f.model.fe_hz for f in fits]))
    model = DQModel(first.form, first.ts, theta_d, theta_q, first.extra_d, first.extra_q, fe_hz=fe)
    ok, reason = model.is_plausible()
    if not ok:
        constrain(FitResult(model, np.zeros(2), info_d, info_q), psi_m)
        model.meta["constrained"] = reason
    return model
