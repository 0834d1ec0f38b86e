"""The :class:`Effect` contract shared by every module of the effect library."""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.signal import butter, sosfiltfilt

from agent.frames import CLARKE, ab_to_dq, dq_to_abc
from agent.model import Signals, Term


class ByIdentity:
    """The last ``size`` results of ``make(obj)``, keyed by the object's identity (Signals hold
    arrays: neither hashable nor changed once built). Only weak references to the objects are kept,
    and a result goes with its object: a cache never keeps a record's signals alive (the streaming
    agent builds new ones every hop)."""

    def __init__(self, size: int):
        self.size, self.items = size, []

    def get(self, obj, make):
        for k, (ref, value) in enumerate(self.items):
            if ref() is obj:
                self.items.append(self.items.pop(k))
                return value
        value = make(obj)
        self.items.append((weakref.ref(obj, self._drop), value))
        del self.items[:-self.size]
        return value

    def _drop(self, ref) -> None:
        self.items[:] = [item for item in self.items if item[0] is not ref]


@dataclass(frozen=True)
class Param:
    """One linear parameter of an effect: its name, unit, meaning, a typical magnitude (used to
    judge whether records can reveal the effect at a realistic size) and its physical range
    [``lower``, ``upper``], in the parameter's unit or, with ``scale``, in multiples of that base
    value of the drive (``i_rated`` A peak, ``Rs_q`` ohm, ``Lq`` H, ``psi_m`` Wb, ``v_rated`` V peak) or
    of a function of them."""

    name: str
    unit: str
    meaning: str
    typical: float
    lower: float = -np.inf  #: physical lower bound (e.g. 0: the effect has a sign)
    upper: float = np.inf  #: physical upper bound
    scale: str | Callable[[dict], float] = ""  #: base value (key or function of them) the bounds multiply
    split: bool = False  #: one signed part of a signed quantity (lower bound 0): sitting at 0 is no physical limit
    negligible: float = 0.0  #: a size (parameter's unit) below which it is no finding (0: none; :meth:`Effect.negligible`)

    def bounds(self, base: dict) -> tuple[float, float]:
        """(lower, upper) in the parameter's unit for the drive's ``base`` values (unbounded where
        the base value is unknown)."""
        if not self.scale:
            return self.lower, self.upper
        try:
            b = self.scale(base) if callable(self.scale) else base.get(self.scale)
        except (KeyError, TypeError, ZeroDivisionError):
            b = None
        if b is None or not np.isfinite(b) or b <= 0:
            return (self.lower if self.lower in (0.0, -np.inf) else -np.inf), np.inf
        return self.lower * b if np.isfinite(self.lower) else -np.inf, self.upper * b


@dataclass(frozen=True)
class Effect:
    """A named physical effect.

    ``columns(sig) -> (m, 2, N)``: one d/q column pair per parameter, row k acting over the interval
    [t_k, t_k + T_s). ``kind="voltage"``: V per parameter unit, added to the voltage equation
    L di/dt = v - R i - ... (the dq model's column is scaled by T_s/L_d and T_s/L_q);
    ``kind="output"``: A per parameter unit, added to the measured current.
    ``report(values, ctx) -> dict`` turns the fitted parameter values into physical quantities
    (``ctx``: the fitted base values ``Rs_d``/``Rs_q`` ohm, ``Ld``/``Lq``/``Lq_x`` H, ``psi_m`` Wb,
    ``i_rated`` A peak, ``ts`` and ``t_mid`` s, ``signals``: the records' Signals); its first key is
    the headline figure, named with its unit.
    """

    id: str
    physics: str
    kind: str
    params: tuple[Param, ...]
    columns: Callable[[Signals], np.ndarray]
    report: Callable[[np.ndarray, dict], dict]
    signature: str
    dq_orders: tuple[int, ...] = ()  #: harmonics of fe the effect puts in the dq residual
    abc_orders: tuple[int, ...] = ()  #: harmonics of fe in the phase residual (0 = DC)
    reveals: str = ""  #: which records make it identifiable
    torque: str = "none"  #: what it adds to the torque regression (eq. 15)
    raw: bool = False  #: its columns carry the measured samples' white noise (not only the smoothed current)
    turns_voltage: bool = False  #: a column turns the voltage (the one-step regression then uses zoh2 columns)
    at_bound: str = ""  #: what a fit on a bound means for this effect, where it is not "beyond physics"
    #: why records prepared with this meta (:attr:`agent.workbench.fitting.Prepared.meta`) cannot show
    #: the effect at all, their measurement being what it is (and which records would), or None
    unseen: Callable[[dict], str | None] = lambda meta: None
    #: where unseen, what a refit of it fits is an error of the model's input itself (the voltage path
    #: behind a pulse-cutting window), so a claim it fits clearly better than is withheld all the same
    unseen_is_input: bool = False
    #: where its size rests on a base value the records pin loosely: its figures read so
    #: ``(values, said, ctx, prior) -> {"params", "params_bound", "note"[, "unpinned_params", "contradicted"]}``
    #: (``contradicted``: the records' direct reading of the effect refutes the fit, no claim; ``said``:
    #: the figures and bounds as fitted; ``prior``: the baseline's and the nameplate's base values,
    #: {key: (value, relative sd)}), or None where the fit's figures stand
    read_through: Callable[[np.ndarray, dict, dict, dict], dict | None] = lambda values, said, ctx, prior: None
    #: the records' own reading of its figures, whatever a fit pins: ``signals -> {"params", "params_bound",
    #: "note", "p"}``, or None where they carry none (the sensors' gains off the phase currents' sum); where a
    #: fit leaves the figures unpinned, these are reported; ``p``: the reading's own test that the effect
    #: is present, over records (None where too few), which explain's claim rests on (docs/workbench.md, "Claims")
    direct: Callable[[list], dict | None] = lambda signals: None
    #: what ``direct``'s test is, in words
    direct_test: str = ""
    #: the records' own reading that refutes the effect whatever a fit makes of it: ``signals -> why``
    #: (the row is then ``contradicted``, not claimed, and the note says why), or None
    refutes: Callable[[list], str | None] = lambda signals: None
    _cache: ByIdentity = field(default_factory=lambda: ByIdentity(8), compare=False, repr=False)

    def __post_init__(self):
        if self.kind not in ("voltage", "output"):
            raise ValueError(f"effect {self.id}: kind must be 'voltage' or 'output'")

    def negligible(self, values) -> bool:
        """Whether fitted ``values`` are too small to be this effect: every parameter with a
        ``negligible`` size is below it (False where none has one). Such a fit only takes up what the
        base model's own approximations leave, and a claim would name an effect the drive lacks."""
        floors = np.array([p.negligible for p in self.params])
        if not np.any(floors > 0):
            return False
        return bool(np.all(np.abs(np.asarray(values, float))[floors > 0] < floors[floors > 0]))

    def cols(self, sig: Signals) -> np.ndarray:
        """``columns(sig)``, cached for the last 8 Signals objects (each term asks for its own row,
        and a fit visits its records in turn)."""
        return self._cache.get(sig, lambda s: np.asarray(self.columns(s), dtype=float))

    def terms(self) -> tuple[tuple[Term, ...], tuple[Term, ...]]:
        """dq-model terms: one d and one q column per parameter (``output`` terms for output effects).
        A voltage parameter p has coefficients p T_s/L_d (d) and p T_s/L_q (q); an output one p."""
        out = self.kind == "output"
        return tuple(tuple(Term(f"{self.id}.{p.name}", exo=lambda s, j=j, ax=ax: self.cols(s)[j, ax], output=out)
                           for j, p in enumerate(self.params)) for ax in (0, 1))

    def values_from_model(self, model) -> np.ndarray:
        """The effect's parameter values stored in a dq model's coefficients (physical units)."""
        names = [f"{self.id}.{p.name}" for p in self.params]
        d_names = [t.name for t in model.terms[0]]
        theta = np.array([model.theta_d[d_names.index(n)] for n in names])
        return theta if self.kind == "output" else theta / model.theta_d[2]  # theta_d[2] = T_s/L_d


# --- helpers shared by the effect modules -------------------------------------------------------

def mid_angle(sig: Signals) -> np.ndarray:
    """Electrical angle at the middle of each sampling interval, rad (where held voltages act)."""
    return sig.theta_e + 0.5 * sig.omega_e * sig.ts


def phase_to_dq(x_abc: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(3, N) phase quantities -> (2, N) dq at ``theta`` (zero sequence dropped)."""
    return ab_to_dq(CLARKE[:2] @ x_abc, theta)


def amplitude(values) -> float:
    """Magnitude of a (cos, sin) or (alpha, beta) parameter pair."""
    return float(np.hypot(values[0], values[1]))


SMOOTH_HZ = 2.0  #: Hz, cut-off of the current used inside effect columns (its operating level)


_SMOOTHED = ByIdentity(16)


def smooth_current(sig: Signals) -> tuple[np.ndarray, np.ndarray]:
    """The current's slow part: dq (2, N) low-passed at ``SMOOTH_HZ`` (zero phase) and its phases (3, N).

    Effect columns built from the measured current would feed the measurement (its noise and the
    ripple the model should predict) back into a free-run prediction; the operating current
    (level, fundamental, zero crossings) is what the effects depend on. Cached per Signals object
    (several effects ask for it)."""
    return _SMOOTHED.get(sig, _smooth)


def smooth(x: np.ndarray, ts: float) -> np.ndarray:
    """(m, N) ``x`` low-passed at ``SMOOTH_HZ`` (zero phase; as it is for fewer than 31 samples)."""
    return sosfiltfilt(butter(2, SMOOTH_HZ, fs=1.0 / ts, output="sos"), x, axis=1) if x.shape[1] > 30 else x


def _smooth(sig: Signals) -> tuple[np.ndarray, np.ndarray]:
    i_dq = smooth(sig.i_dq, sig.ts)
    return i_dq, dq_to_abc(i_dq, sig.theta_e)
