"""Alarm evidence: from a stream of strongly correlated spectra to few decisions an operator trusts.

The paper's thresholds (TH2/TH3 per record, Table 4) are the evidence; this module is the alarm
logic the running agent puts on top of it (docs/method.md, "Alarms"). Measured on healthy data,
the magnitude at a fault line varies little between the windows of one stretch of operation
(log-magnitude sd ~0.02 at the main gear lines) and much more between stretches (~0.12: mesh
ripple, temperature, lubricant film), so windows are not independent tests.

* **Features.** One piece of evidence per sideband *pair* fe -/+ k f of a family: the mean of
  the two lines' log-magnitudes. Pairs that land on the same lines (gear_driven k=2 and
  gear_driving k=1 at ratio 2, a chain order on a sprocket line) are one feature, reported under
  every family that reaches it. Per family one more: the mean of its pairs ("all k"), for faults
  that spread over several orders (no lubrication); it is standardised on its own learned
  spread, so the correlation between its pairs is accounted for as measured.
* **Standardisation** over independent healthy *stretches* (``stretch_s`` of operation each, or
  one record each when learned offline), widened for what few stretches can tell: the mean is
  taken at its one-sided 95 % upper bound, the sd at its 95 % upper bound (chi-square), and
  inflated by sqrt((1 + rho) / (1 - rho)) for the lag-1 correlation rho of consecutive stretches.
* **Slow wear path:** one-sided CUSUM per feature over stretches, S = max(0, S + min(z, z_cap) - k),
  caution at S >= h; a second CUSUM with reference ``warn_k`` (a shift beyond the paper's TH3)
  gives warning. The cap bounds what one stretch can add (z_cap - k), so no single outlier trips
  it. h is set from the false-alarm budget with Siegmund's ARL approximation
  (:func:`cusum_threshold`).
* **Gross path:** a feature whose newest window is so far above the healthy mean (in prediction
  sds of single windows) that healthy operation reaches it less than the gross budget allows
  (:meth:`AlarmConfig.gross_thresholds`, ~6 after commissioning) is a warning in the current hop:
  within one window plus one hop of a gross fault's onset. The cluster's gross test reads whole
  stretches (a 4 s span's cluster point is too noisy: measured, docs/method.md).
* **Parameter cluster** (Ts/Lq, B_GT), Alg. 4, made load-invariant: B_GT is the mean shaft torque
  over speed, so it moves with load; it is compared after removing the load's physical share,
  dB_GT/dload = P_rated / (100 omega_m^2) per %-point. A friction increase that shows up only as
  more input power is then indistinguishable from load (documented limitation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from statistics import NormalDist

import numpy as np

from agent.frequencies import base_frequencies
from agent.spectrum import peak_near

K_MAX = 3  #: sideband orders per family
_NORMAL = NormalDist()
MONTH_S = 30 * 86400.0
STATES = ("normal", "caution", "warning")  #: codes 0 / 1 / 2
#: stretches of healthy evidence the default commissioning learns: behind the promised false-alarm rate
FULL_EVIDENCE_STRETCHES = 40


# --- features ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Feature:
    """One sideband pair fe -/+ k f of ``family`` (``shared``: other (family, k) reaching the same
    lines), or, with ``members``, a family's combination: the mean of its pairs (indices into the
    feature list), which a fault spread over several orders raises more than any one pair."""

    family: str
    k: int  #: 0 for a family's combination
    shared: tuple[tuple[str, int], ...] = ()
    members: tuple[int, ...] = ()

    @property
    def name(self) -> str:
        return f"{self.family} all k" if self.members else f"{self.family} k={self.k}"

    @property
    def families(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys((self.family,) + tuple(f for f, _ in self.shared)))

    def freqs_hz(self, profile, fe_hz: float) -> tuple[float, ...]:
        """The lines read (Hz): the pair, or every pair of the family's combination."""
        f = base_frequencies(profile, fe_hz)[self.family]
        ks = [self.k] if not self.members else range(1, K_MAX + 1)
        return tuple(x for k in ks for x in (fe_hz - k * f, fe_hz + k * f))


def make_features(profile, fe_hz: float, resolution_hz: float, f_max_hz: float) -> list[Feature]:
    """The unique sideband pairs at ``fe_hz``: pairs whose lines both lie within ``resolution_hz``
    of another pair's are merged into it (one piece of evidence)."""
    out: list[tuple[Feature, tuple[float, float]]] = []
    for family, f in base_frequencies(profile, fe_hz).items():
        for k in range(1, K_MAX + 1):
            lo, hi = fe_hz - k * f, fe_hz + k * f
            if lo <= 0 or hi > f_max_hz:
                continue
            for j, (feat, (flo, fhi)) in enumerate(out):
                if abs(flo - lo) <= resolution_hz and abs(fhi - hi) <= resolution_hz:
                    out[j] = (Feature(feat.family, feat.k, feat.shared + ((family, k),)), (flo, fhi))
                    break
            else:
                out.append((Feature(family, k), (lo, hi)))
    pairs = [feat for feat, _ in out]
    combos = []
    for family in base_frequencies(profile, fe_hz):
        members = tuple(j for j, f in enumerate(pairs) if family in f.families)
        if len(members) >= 2:
            combos.append(Feature(family, 0, members=members))
    return pairs + combos


def feature_values(freqs: np.ndarray, amp: np.ndarray, profile, fe_hz: float, features: list[Feature],
                   search_bins: int = 1) -> np.ndarray:
    """(n_windows, n_features): per window, the mean log-magnitude (ln A) of each pair's two lines,
    each read as the largest bin within ``search_bins`` of it (as the paper's thresholds are)."""
    amp = np.atleast_2d(amp)
    pairs = [feat for feat in features if not feat.members]
    targets = np.array([f for feat in pairs for f in feat.freqs_hz(profile, fe_hz)])
    _, _, mag = peak_near(freqs, amp, targets, search_bins)
    logs = np.log(np.maximum(np.asarray(mag, dtype=float), 1e-15)).reshape(amp.shape[0], len(pairs), 2)
    y = logs.mean(axis=2)
    combos = [y[:, list(feat.members)].mean(axis=1) for feat in features if feat.members]
    return np.column_stack([y, *combos]) if combos else y


# --- statistics ----------------------------------------------------------------------------------

def chi2_lower(q: float, dof: int) -> float:
    """Chi-square quantile (Wilson-Hilferty; within 1 % for dof >= 5)."""
    z = _NORMAL.inv_cdf(q)
    return dof * (1.0 - 2.0 / (9 * dof) + z * math.sqrt(2.0 / (9 * dof))) ** 3


def _beta_cf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    f = d
    for m in range(1, 500):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            f *= c * d
        if abs(c * d - 1.0) < 1e-15:
            break
    return f


def student_t_sf(t: float, dof: float) -> float:
    """P(T > t) of Student's t with ``dof`` degrees of freedom, t >= 0 (incomplete beta). Here, not
    scipy's: the agent's runtime path does not import scipy (docs/benchmarks.md, memory)."""
    x = dof / (dof + t * t)
    a, b = 0.5 * dof, 0.5
    log_front = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)
    if x < (a + 1.0) / (a + b + 2.0):
        ib = math.exp(log_front) * _beta_cf(a, b, x) / a
    else:
        ib = 1.0 - math.exp(log_front) * _beta_cf(b, a, 1.0 - x) / b
    return 0.5 * ib


@lru_cache(maxsize=256)
def student_t_isf(p: float, dof: float) -> float:
    """t with P(T > t) = p (0 < p < 0.5), by bisection on :func:`student_t_sf`; inf for p <= 1e-300."""
    if p <= 1e-300:
        return math.inf
    lo, hi = 0.0, 1.0
    while student_t_sf(hi, dof) > p:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if student_t_sf(mid, dof) > p else (lo, mid)
        if hi - lo < 1e-9 * hi:
            break
    return hi


def cusum_arl(h: float, k: float, shift: float = 0.0) -> float:
    """Siegmund's approximation of the average run length (stretches) of a one-sided CUSUM with
    unit-variance normal increments of mean ``shift``, reference ``k`` and threshold ``h``."""
    d, b = shift - k, h + 1.166
    if abs(d) < 1e-9:
        return b * b
    if -2.0 * d * b > 700.0:  # beyond any horizon (and beyond a float's exp)
        return math.inf
    return (math.exp(-2.0 * d * b) + 2.0 * d * b - 1.0) / (2.0 * d * d)


@lru_cache(maxsize=64)
def cusum_threshold(arl: float, k: float) -> float:
    """Smallest h whose in-control ARL (:func:`cusum_arl` with no shift) reaches ``arl`` (bisection)."""
    lo, hi = 0.0, 100.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cusum_arl(mid, k) < arl else (lo, mid)
    return hi


def effective_size(d: list[np.ndarray]) -> tuple[float, float, float]:
    """(mean, variance, effective sample size) of a block statistic given per record: the blocks of
    one record are autocorrelated, the records independent. n_eff = N / (1 + 2 sum rho_k), rho_k
    pooled over the records about the grand mean (so a record-to-record spread reads as
    correlation), summed while positive (Geyer's initial positive sequence) and floored at the
    number of records."""
    n = sum(x.size for x in d)
    mean = float(np.mean(np.concatenate(d)))
    dev = [x - mean for x in d]
    g0 = sum(float(x @ x) for x in dev) / n
    if g0 <= 0:
        return mean, 0.0, float(len(d))
    s = 0.0
    for k in range(1, max(x.size for x in d)):
        rho = sum(float(x[k:] @ x[:-k]) for x in dev if x.size > k) / n / g0
        if rho <= 0:
            break
        s += rho
    return mean, g0, float(np.clip(n / (1.0 + 2.0 * s), len(d), n))


def learning_shift(stretch_y: np.ndarray) -> tuple[int, float]:
    """Largest change of a feature's level within the learning stretches: the pooled two-sample
    t between the stretches before and after each split (each side at least a quarter of them),
    deflated by sqrt((1 + rho) / (1 - rho)) for the lag-1 correlation rho of the stretches about
    their side's mean, maximised over splits; returns (feature index, t). A fault that starts, or
    grows, while a baseline is learned shows here; a healthy drive's thermal drift does not
    (benchmark). Meaningful from about 20 stretches on."""
    n = stretch_y.shape[0]
    edge = max(2, n // 4)
    best_j, best_t = 0, 0.0
    for m in range(edge, n - edge + 1):
        a, b = stretch_y[:m], stretch_y[m:]
        r = np.concatenate((a - a.mean(axis=0), b - b.mean(axis=0)))
        ss = np.maximum(np.sum(r * r, axis=0), 1e-24)
        rho = np.clip(np.sum(r[1:] * r[:-1], axis=0) / ss, 0.0, 0.9)
        se = np.sqrt(ss / (n - 2) * (1 / m + 1 / (n - m)) * (1 + rho) / (1 - rho))
        t = (b.mean(axis=0) - a.mean(axis=0)) / se
        j = int(np.argmax(np.abs(t)))
        if abs(t[j]) > abs(best_t):
            best_j, best_t = j, float(t[j])
    return best_j, best_t


@dataclass
class EvidenceStats:
    """Healthy statistics of the features and the cluster, learned over independent stretches."""

    features: list[Feature]
    mean: np.ndarray  #: (F,) stretch mean of each feature (ln A)
    sd: np.ndarray  #: (F,) sd between stretches
    window_sd: np.ndarray  #: (F,) sd of single windows about the mean (gross path; Bessel-corrected with n_eff)
    rho: float  #: lag-1 correlation of consecutive stretches (0 when stretches are separate records)
    n: int  #: independent stretches
    stretch_s: float  #: s of operation per stretch
    load_pct: float  #: input power at which the cluster is centred, % of rated (JSON key kept: ``load_pct``)
    b_gt_per_pct: float  #: physical slope dB_GT/dload, N m s/rad per %-point
    cluster_mean: np.ndarray  #: (2,) load-adjusted (Ts/Lq, B_GT)
    cluster_cov: np.ndarray  #: (2, 2) between stretches
    window_n_eff: np.ndarray | None = None  #: (F,) independent windows among the learned ones (None: n)

    @classmethod
    def fit(cls, features: list[Feature], windows: list[np.ndarray], stretch_cluster: np.ndarray,
            stretch_power: np.ndarray, stretch_s: float, profile, consecutive: bool) -> "EvidenceStats":
        """From the windows' feature values of each stretch (a list of (m_i, F), in time order), the
        cluster points (n, 2) and input powers (n,, % of rated: B_GT is the input power's torque over
        speed, copper loss included, so its load share is removed on that measure, not on the
        torque reading) of the stretches; ``consecutive``: the stretches follow each other in one
        stream (their lag-1 correlation is estimated)."""
        n = len(windows)
        if n < 4:
            raise ValueError(f"need at least 4 independent stretches, got {n}")
        windows = [np.atleast_2d(w) for w in windows]
        stretch_y = np.array([w.mean(axis=0) for w in windows])
        window_y = np.concatenate(windows)
        mean, sd = stretch_y.mean(axis=0), stretch_y.std(axis=0, ddof=1)
        n_eff = np.array([effective_size([w[:, j] for w in windows])[2] for j in range(window_y.shape[1])])
        window_sd = np.sqrt(np.mean((window_y - mean) ** 2, axis=0) * n_eff / np.maximum(n_eff - 1.0, 1.0))
        rho = 0.0
        if consecutive and n >= 8:
            c = stretch_y - mean
            rho = float(np.clip(np.mean(np.sum(c[1:] * c[:-1], 0) / np.maximum(np.sum(c * c, 0), 1e-30)), 0.0, 0.9))
        omega_m = 2 * math.pi * profile.motor.rated_speed_rpm / 60.0
        slope = profile.motor.rated_power_w / 100.0 / omega_m ** 2
        load0 = float(np.median(stretch_power))

        sc = np.array(stretch_cluster, dtype=float).copy()
        sc[:, 1] -= slope * (np.asarray(stretch_power) - load0)
        c_mean = sc.mean(axis=0)
        c_cov = np.cov(sc, rowvar=False) + np.eye(2) * 1e-12 * (1.0 + c_mean ** 2)
        return cls(features, mean, np.maximum(sd, 1e-6), np.maximum(window_sd, 1e-6), rho, n, float(stretch_s),
                   load0, slope, c_mean, c_cov, n_eff)

    # -- standardisation ------------------------------------------------------------------------
    @property
    def scale(self) -> np.ndarray:
        """Conservative sd for the CUSUM: upper 95 % bound of sd, inflated for lag-1 correlation."""
        c_sigma = math.sqrt((self.n - 1) / chi2_lower(0.05, self.n - 1))
        return self.sd * c_sigma * math.sqrt((1 + self.rho) / (1 - self.rho))

    def stretch_z(self, y: np.ndarray) -> np.ndarray:
        """z of stretch means: shift above the mean's one-sided 95 % upper bound, in :attr:`scale`."""
        upper = self.mean + 1.645 * self.sd / math.sqrt(self.n)
        return (np.asarray(y) - upper) / self.scale

    def window_z(self, y: np.ndarray) -> np.ndarray:
        """z of a single window: in prediction sds of single windows, sd sqrt(1 + 1/n) wider."""
        return (np.asarray(y) - self.mean) / (self.window_sd * math.sqrt(1 + 1 / self.n))

    def cluster_z(self, point, power_pct: float) -> float:
        """Normal score of the load-adjusted cluster point's squared Mahalanobis distance
        (chi-square, 2 dof, widened by 1 + 1/n for the estimated centre); ``power_pct``: the input
        power, % of rated (``operating_point``'s ``input_power_pct``)."""
        p = np.asarray(point, dtype=float).copy()
        p[1] -= self.b_gt_per_pct * (power_pct - self.load_pct)
        d = p - self.cluster_mean
        d2 = float(d @ np.linalg.solve(self.cluster_cov, d)) / (1 + 1 / self.n)
        tail = math.exp(-0.5 * min(d2, 1400.0))
        return 40.0 if tail <= 0.0 else -_NORMAL.inv_cdf(min(max(tail, 1e-300), 1 - 1e-16))

    # -- model file -----------------------------------------------------------------------------
    def to_json(self) -> dict:
        return {"features": [{"family": f.family, "k": f.k, "shared": [list(s) for s in f.shared],
                              "members": list(f.members)} for f in self.features],
                "mean": self.mean.tolist(), "sd": self.sd.tolist(), "window_sd": self.window_sd.tolist(),
                "rho": self.rho, "n": self.n, "stretch_s": self.stretch_s, "load_pct": self.load_pct,
                "b_gt_per_pct": self.b_gt_per_pct, "cluster_mean": self.cluster_mean.tolist(),
                "cluster_cov": self.cluster_cov.tolist(),
                "window_n_eff": None if self.window_n_eff is None else self.window_n_eff.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> "EvidenceStats":
        feats = [Feature(f["family"], int(f["k"]), tuple((s[0], int(s[1])) for s in f["shared"]),
                         tuple(int(j) for j in f.get("members", ()))) for f in d["features"]]
        arr = lambda key: np.array(d[key], dtype=float)  # noqa: E731
        n_eff = None if d.get("window_n_eff") is None else arr("window_n_eff")
        if n_eff is not None and (n_eff.shape != (len(feats),) or not np.all(np.isfinite(n_eff) & (n_eff >= 1))):
            raise ValueError("evidence.window_n_eff must hold one count >= 1 per feature")
        if int(d["n"]) < 4 or not float(d["stretch_s"]) > 0:
            raise ValueError("evidence needs n >= 4 stretches of stretch_s > 0 s")
        return cls(feats, arr("mean"), arr("sd"), arr("window_sd"), float(d["rho"]), int(d["n"]),
                   float(d["stretch_s"]), float(d["load_pct"]), float(d["b_gt_per_pct"]), arr("cluster_mean"),
                   arr("cluster_cov"), n_eff)


# --- the streaming decision ------------------------------------------------------------------------

@dataclass(frozen=True)
class AlarmConfig:
    """Tuning of the streaming alarm logic (docs/method.md explains each value and its evidence)."""

    stretch_s: float = 30.0  #: s; at least this much operation per CUSUM step (longer if the baseline's is)
    cusum_k: float = 0.5  #: reference shift, scaled sds: caution path
    warn_k: float = 3.0  #: reference shift of the warning path (beyond the paper's TH3)
    z_cap: float = 4.0  #: a stretch adds at most z_cap - k to a CUSUM (one outlier cannot trip it)
    false_alarms_per_month: float = 0.1  #: design budget of the slow path per drive (Siegmund ARL)
    gross_false_alarms_per_month: float = 0.1  #: design budget of the gross path per drive (:meth:`gross_thresholds`)
    settle_s: float = 3.0  #: s of held decision after the operating-point reading last moved (docs/method.md)
    settle_load_pct: float = 1.0  #: load change between hops (%-points) that starts settling
    settle_fe_hz: float = 0.2  #: fe change between hops (Hz) that starts settling

    def threshold(self, n_tests: int, stretch_s: float) -> float:
        """CUSUM threshold h: in-control ARL of every test together >= one month / budget."""
        arl = MONTH_S / stretch_s * n_tests / self.false_alarms_per_month
        return cusum_threshold(arl, self.cusum_k)

    def gross_thresholds(self, stats: "EvidenceStats") -> tuple[np.ndarray, float]:
        """Gross-path thresholds: per feature in window z (F,), and the cluster's in stretch z.

        The features and the cluster share :attr:`gross_false_alarms_per_month` equally. A feature's
        trials are its independent windows: learning saw ``window_n_eff`` of them in n stretches of
        ``stretch_s`` (:func:`effective_size`: one session's windows are nearly one value), so a
        month holds MONTH_S n_eff / (n stretch_s); the cluster's trials are stretches. Per trial the
        healthy value is Student t with (independent values learned - 1) dof: the mean and spread
        are estimates, and few of them widen the threshold.
        """
        stretch_s = max(self.stretch_s, stats.stretch_s)
        tests = len(stats.features) + 1
        n_eff = np.full(len(stats.features), float(stats.n)) if stats.window_n_eff is None else stats.window_n_eff
        trials = MONTH_S * n_eff / (stats.n * stats.stretch_s)
        p = self.gross_false_alarms_per_month / tests
        feat = np.array([student_t_isf(p / t, max(ne - 1.0, 1.0)) for t, ne in zip(trials, n_eff)])
        return feat, student_t_isf(p / (MONTH_S / stretch_s), max(stats.n - 1.0, 1.0))


@dataclass
class Verdict:
    """One hop's decision and why."""

    state: str
    spectrum_state: str
    cluster_state: str
    evidence: dict  #: family -> max CUSUM / h over its features (>= 1: caution)
    reason: dict | None = None  #: what drives the state (path, feature, family, z, threshold, evidence)
    settling: bool = False
    stretch_closed: bool = False


class _Stretch:
    """Running sums over the hops of the current stretch (fixed memory). The cluster point of a span
    that holds the angle's acquisition is kept apart: a stretch uses it only if it has no other
    (a snapshot source, whose every span starts a stream, and whose baseline learned them so)."""

    def __init__(self):
        self.y, self.hops, self.seconds = 0.0, 0, 0.0
        self.cluster = np.zeros((2, 4))  #: rows clean, acquiring: sum of Ts/Lq, B_GT, input power %; count

    def add(self, y, point, power_pct: float, hop_s: float, clean: bool = True) -> None:
        self.y = self.y + np.asarray(y, dtype=float)
        self.cluster[0 if clean else 1] += (*point, power_pct, 1.0)
        self.hops += 1
        self.seconds += hop_s

    def cluster_mean(self) -> tuple[np.ndarray, float]:
        """(mean cluster point, mean input power %) of the clean spans, else of the acquiring ones."""
        row = self.cluster[0] if self.cluster[0, 3] else self.cluster[1]
        return row[:2] / row[3], row[2] / row[3]


class AlarmLogic:
    """Per drive: accumulates stretches, keeps the CUSUMs, returns a :class:`Verdict` per hop.
    CUSUM state is kept per feature name across baselines (the transmission does not change when
    the scheduled model does)."""

    def __init__(self, config: AlarmConfig = AlarmConfig()):
        self.config = config
        self.s_caution: dict[str, float] = {}
        self.s_warning: dict[str, float] = {}
        self._stretch = _Stretch()
        self._settle_left = 0.0
        self._last_op: tuple[float, float] | None = None  #: the hop before's reading (None: a stream's first)
        self._before_gap: tuple[float, float] | None = None  #: the last reading before the stream restarted
        self.new_stretch = False  #: the last reading started a new stretch (a move, or a gap with one)
        self._settling = False
        self._acquiring = False
        self._last: Verdict = Verdict("normal", "normal", "normal", {})
        self.last_z: dict[str, float] = {}  #: the last stretch's z per test (diagnostics, benchmark)
        self._cluster_gross: dict | None = None
        self._gross_for: EvidenceStats | None = None
        self._gross_th: tuple[np.ndarray, float] = (np.zeros(0), math.inf)

    def reset(self) -> None:
        """Forget accumulated evidence (e.g. after maintenance or an acknowledged repair)."""
        self.__init__(self.config)

    def _moved(self, a: tuple[float, float], b: tuple[float, float], hops: float = 1.0) -> bool:
        """(fe Hz, load %) readings ``a`` and ``b`` differ by more than ``hops`` hops' settling rule."""
        return (abs(a[0] - b[0]) > hops * self.config.settle_fe_hz
                or abs(a[1] - b[1]) > hops * self.config.settle_load_pct)

    @property
    def fresh(self) -> bool:
        """No reading since the stream (re)started."""
        return self._last_op is None

    @property
    def settling(self) -> bool:
        """The last reading :meth:`observe` saw is within the settling hold after a move."""
        return self._settling

    def new_stream(self) -> None:
        """A gap in the stream: the next reading has no predecessor (see :meth:`observe`)."""
        self._before_gap = self._last_op or self._before_gap
        self._last_op = None

    def observe(self, op: tuple[float, float], hop_s: float, span_ends=None, acquiring: bool = False) -> None:
        """Every hop's operating-point reading ``op`` (fe Hz, load %), assessed or not (no baseline,
        idle, learning): settling starts when it moved since the hop before, and the hold counts
        down. On a stream's first hop there is no hop before: ``span_ends`` = (first hop's reading,
        last hop's reading, hops per span) judges a step inside the span, whose size a step in the
        stream spreads over the span's hops; a stretch continues across the gap only at the reading
        before it (:attr:`new_stretch` says when one restarts; commissioning's stretches follow it
        too). ``acquiring``: the span holds the angle's acquisition (a PLL locking after
        the stream started), which biases its Ts/Lq: :meth:`step` keeps its cluster point apart
        (:class:`_Stretch`). While settling, :meth:`step` holds its decision."""
        if self._last_op is not None:
            moved = broke = self._moved(self._last_op, op)
        else:
            moved = span_ends is not None and self._moved(span_ends[0], span_ends[1], span_ends[2])
            broke = moved or (self._before_gap is not None and self._moved(self._before_gap, op))
        if moved:
            self._settle_left = self.config.settle_s
        if broke:
            self._stretch = _Stretch()  # a stretch never mixes operating points
        self.new_stretch = broke
        self._acquiring = acquiring
        self._last_op = op
        self._settling = self._settle_left > 0
        if self._settling:
            self._settle_left -= hop_s

    def _tests(self, stats: EvidenceStats) -> tuple[list[str], float]:
        names = [f.name for f in stats.features] + ["cluster"]
        stretch_s = max(self.config.stretch_s, stats.stretch_s)
        return names, self.config.threshold(len(names), stretch_s)

    def _gross(self, stats: EvidenceStats) -> tuple[np.ndarray, float]:
        if self._gross_for is not stats:
            self._gross_for, self._gross_th = stats, self.config.gross_thresholds(stats)
        return self._gross_th

    def step(self, stats: EvidenceStats, profile, window_y: np.ndarray, cluster_point, power_pct: float,
             fe_hz: float, hop_s: float) -> Verdict:
        """One assessed hop, after :meth:`observe` saw its reading: ``window_y`` (F,) the newest
        window's feature values, the span's cluster point, its input power (% of rated, for the
        cluster's load share) and fe (``profile``: the drive's, for the lines' frequencies in the
        reason)."""
        cfg = self.config
        if self._settling:
            return Verdict(self._last.state, self._last.spectrum_state, self._last.cluster_state,
                           self._last.evidence, self._last.reason, settling=True)
        names, h = self._tests(stats)
        stretch_s = max(cfg.stretch_s, stats.stretch_s)

        # gross path: the newest window alone
        gross = None
        g_feat, g_cluster = self._gross(stats)
        over = stats.window_z(window_y) - g_feat
        j = int(np.argmax(over))
        if over[j] >= 0.0:
            feat = stats.features[j]
            gross = {"path": "gross", "feature": feat.name, "families": list(feat.families),
                     "freqs_hz": [round(x, 2) for x in feat.freqs_hz(profile, fe_hz)],
                     "z": round(float(over[j] + g_feat[j]), 2), "threshold": round(float(g_feat[j]), 2)}

        # slow path: a CUSUM step per completed stretch
        st = self._stretch
        st.add(window_y, cluster_point, power_pct, hop_s, clean=not self._acquiring)
        closed = st.seconds >= stretch_s - 1e-9
        if closed:
            z = np.append(stats.stretch_z(st.y / st.hops), stats.cluster_z(*st.cluster_mean()))
            self.last_z = dict(zip(names, np.round(z, 3).tolist()))
            # the cluster's gross test reads a whole stretch, and its verdict stands until the next
            self._cluster_gross = None if z[-1] < g_cluster else {
                "path": "gross", "feature": "cluster", "families": ["cluster"], "z": round(float(z[-1]), 2),
                "threshold": round(g_cluster, 2)}
            for name, zi in zip(names, z):
                self.s_caution[name] = min(2 * h, max(0.0, self.s_caution.get(name, 0.0) + min(zi, cfg.z_cap) - cfg.cusum_k))
                self.s_warning[name] = min(2 * h, max(0.0, self.s_warning.get(name, 0.0)
                                                      + min(zi, cfg.warn_k + cfg.z_cap) - cfg.warn_k))
            self._stretch = _Stretch()
        gross = gross or self._cluster_gross

        # levels per source (spectrum features / cluster) and the reason
        def level(name):
            return 2 if self.s_warning.get(name, 0.0) >= h else 1 if self.s_caution.get(name, 0.0) >= h else 0
        spec_levels = {f.name: level(f.name) for f in stats.features}
        spec = max(spec_levels.values(), default=0)
        clus = level("cluster")
        if gross is not None:
            if gross["feature"] == "cluster":
                clus = 2
            else:
                spec = 2
        evidence = {}
        for f in stats.features:
            for fam in f.families:
                evidence[fam] = round(max(evidence.get(fam, 0.0), self.s_caution.get(f.name, 0.0) / h), 3)
        evidence["cluster"] = round(self.s_caution.get("cluster", 0.0) / h, 3)
        reason = gross
        if reason is None and max(spec, clus) > 0:
            name = max(names, key=lambda n: (level(n), self.s_caution.get(n, 0.0)))
            feat = next((f for f in stats.features if f.name == name), None)
            reason = {"path": "cusum", "feature": name, "families": list(feat.families) if feat else ["cluster"],
                      "evidence": round(self.s_caution[name], 2), "threshold": round(h, 2),
                      "warning_evidence": round(self.s_warning.get(name, 0.0), 2)}
            if feat is not None:
                reason["freqs_hz"] = [round(x, 2) for x in feat.freqs_hz(profile, fe_hz)]
        self._last = Verdict(STATES[max(spec, clus)], STATES[spec], STATES[clus], evidence, reason,
                             stretch_closed=closed)
        return self._last
