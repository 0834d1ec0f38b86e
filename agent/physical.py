"""Physical motor parameters (R_s, L_d, L_q, psi_m) with confidence intervals, from records and
the nameplate (maximum a posteriori, numpy only: the gateway learns baselines too).

What records say, robustly and independently of any simulator or controller:

* **steady state** (each record's means; eq. 5 with d/dt = 0):
  v_d = R_s i_d - omega_e L_q i_q and v_q = R_s i_q + omega_e L_d i_d + omega_e psi_m.
  Their standard errors come from 50 ms block means (the ripple is correlated, samples are not
  independent) plus the voltage channel's accuracy (``V_ACCURACY`` of the reading). The d equation
  holds in the rotor's frame: an encoder's. A PLL's frame puts the current on +q, which is the
  rotor's q axis only if the drive holds i_d = 0; under MTPA or field weakening the current leads
  it by beta and the PLL frame's steady d voltage is -omega_e (L_q cos^2 beta + L_d sin^2 beta) |i|
  + omega_e psi_m sin beta (motulator's MTPA drive at 80 % load: beta = 7 deg, and the d equation
  reads L_q = 0.036 H for 0.051 H). The records cannot show beta, so PLL-frame records give L_q
  through the dynamics alone unless the profile says the drive holds i_d = 0
  (``sampling.current_reference = "id0"``);
* **dynamics**: T_s/L_x from the current's sample-to-sample response to the voltage (eq. 6 in the
  ``speed`` form with one intercept per record), least squares compensated for the white noise
  of the channels (levels read off the zero sequences, :func:`zero_sequence_sigma`); its standard
  error is inflated for the residual's lag-1 correlation.

At one steady operating point with i_d ~ 0 these leave R_s and psi_m collinear (both only in
R_s i_q + omega_e psi_m) and L_d unseen in steady state. The nameplate (profile ``[nameplate]``)
supplies log-normal priors; the estimate minimises the data's and the priors' normalised squared
residuals over log(R_s, L_d, L_q, psi_m) (Levenberg-Marquardt), and the posterior covariance is
the inverse Gauss-Newton Hessian there. A parameter the data alone determine to worse than
``IDENTIFIABLE_REL`` is *not identifiable* from these records: reported by name with the reason,
and its value comes from the prior (or is withheld when there is none).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agent.identify import levenberg_marquardt
from agent.model import Signals
from agent.profile import DriveProfile

NAMES = ("Rs", "Ld", "Lq", "psi_m")
UNITS = {"Rs": "ohm", "Ld": "H", "Lq": "H", "psi_m": "Wb"}
BLOCK_S = 0.05  #: s, blocks whose means give the steady-state standard errors
V_ACCURACY = 0.005  #: relative accuracy of the voltage channel (0.5 % of reading) ...
V_FLOOR = 0.2  #: ... plus this many volts
IDENTIFIABLE_REL = 0.10  #: the data alone must pin a parameter to this relative sd (1 sigma)
VAGUE_SD = 1.0  #: log-sd (a factor e) of the vague prior where the nameplate says nothing
COLLINEAR = 0.8  #: |correlation| of two unidentifiable parameters reported as one collinear group
CONFLICT_Z = 4.0  #: the records pull a parameter this many nameplate sds away: they disagree
ENDOGENOUS_Z = 3.0  #: the compensated dynamics regression is rejected this many sds from the instrumented one
ENDOGENOUS_REL = 0.1  #: ... and by more than this share of it
IV_LAG = 2  #: samples between a regression's instruments and its regressors (one more than white noise needs)
Z95 = 1.959964


@dataclass
class Observation:
    """What one record says about the parameters (a few numbers; records need not stay in memory)."""

    means: np.ndarray  #: [i_d, i_q, v_d, v_q, omega_e] means (A, V, rad/s)
    se: np.ndarray  #: standard errors of the v_d, v_q equations (V)
    gram: list  #: per axis (G, h, M): noise-compensated normal equations of the dynamics, and the
    #: meat X^T diag(e^2) X of their sandwich covariance
    ts: float
    encoder: bool = True  #: the frame is the encoder's (else a PLL's, whose d axis carries the speed ripple)
    iv: list = field(default_factory=list)  #: per axis (Z^T X, Z^T y, Z^T diag(e^2) Z): the same regression
    #: with the previous sample's regressors as instruments (:func:`_dynamics`)
    own: list | None = None  #: per axis (G, h, M) compensated also for the controller's immediate answer to
    #: this sample's noise (:func:`immediate_answer`), as if the record's current were the controller's
    #: own samples; None where the profile says it is not
    samples: str | None = None  #: the profile's ``sampling.current_source`` ("controller", "independent")


def iv_moments(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Z^T X, Z^T y) of the regression y = X theta with the regressors ``IV_LAG`` samples back as
    instruments Z (rows of ``x``, ``y`` are consecutive samples)."""
    z = x[:-IV_LAG]
    return z.T @ x[IV_LAG:], z.T @ y[IV_LAG:]


def iv_meat(x: np.ndarray, y: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Z^T diag(e^2) Z of that regression at ``theta``: the meat of its sandwich covariance."""
    ze = x[:-IV_LAG] * (y[IV_LAG:] - x[IV_LAG:] @ theta)[:, None]
    return ze.T @ ze


def zero_sequence_sigma(x_abc: np.ndarray) -> float:
    """Per-phase rms of the channels' white noise, from the zero sequence (x_a + x_b + x_c)/3 of a
    three-wire machine, which carries only the channels' own noise (variance sigma^2/3). The median
    of its periodogram (ln 2 sigma0^2 for white noise) ignores lines (a third-harmonic EMF)."""
    x0 = x_abc.sum(axis=0) / 3.0
    per = np.abs(np.fft.rfft(x0 - x0.mean())[1:]) ** 2 / x0.size
    return float(np.sqrt(3.0 * np.median(per) / np.log(2.0)))


def _dq_noise_var(sigma: float) -> float:
    """Variance of one dq component of white per-phase noise sigma (amplitude-invariant Park): 2/3 sigma^2."""
    return 2.0 / 3.0 * sigma**2


def immediate_answer(sig: Signals) -> np.ndarray:
    """K (2 x 2, V/A): the dq voltage's answer within the sample to this sample's dq current,
    v_a(k) = sum_b K[a, b] i_b(k) + (what the samples before say), read by regressing v(k) on i(k),
    i(k-1), i(k-2), v(k-1), v(k-2), omega_e(k) and 1: a PI current loop with decoupling in
    incremental form, acting on the sample it has just taken (K ~ -(K_p + K_i T_s) on the diagonal,
    the decoupling -omega_e L off it) or a sample later (K ~ 0). Where the record's current is the
    controller's own samples, K is the controller's: on 64 such family drives (both axes) within 0.73-1.10
    of the loop's K_p without computation delay (16 drives), and |K| < 0.42 K_p with one (48). Where
    it is an independent DAQ's, the regression reads other things (-0.08 to 8.4 K_p on 56 family
    drives): the voltage then does not answer this sample's noise, whatever K reads."""
    y, v, n = sig.i_dq, sig.v_dq, sig.n
    lagged = [y[:, 2 - j:n - j] for j in range(3)] + [v[:, 2 - j:n - j] for j in (1, 2)]
    x = np.column_stack([row for block in lagged for row in block] + [sig.omega_e[2:], np.ones(n - 2)])
    coef = np.linalg.lstsq(x, v[:, 2:].T, rcond=None)[0]  # (columns, 2)
    return coef[:2].T


def observe(sig: Signals, encoder: bool = True, instruments: bool = True, samples: str | None = None
            ) -> Observation:
    """Steady-state means and the dynamics' normal equations of one record; ``encoder``: whether
    its angle is an encoder's (a narrow PLL's frame wobbles with the shaft's speed ripple, which the
    d axis's sample-to-sample regression reads as inductance: 0.0285 H for 0.015 H on the rig);
    ``samples``: the profile's ``sampling.current_source`` (None: not stated).

    The noise compensation removes the regressors' own noise: E[U^T U] = diag(s_i, s_v, omega^2 s_i)
    per sample (s the dq noise variances). Where the current is the controller's own samples and the
    controller acts on the sample it has just taken, the voltage it applies carries K n(k), which the
    one-step equation's error (-a n(k)) meets: E[X0^T U] adds K s_i in the voltage's row (not its
    column: an asymmetric correction). ``own`` keeps that reading beside the plain one; :func:`_dynamics`
    compares them."""
    i_d, i_q = sig.i_dq
    v_d, v_q = sig.v_dq
    w = sig.omega_e
    means = np.array([i_d.mean(), i_q.mean(), v_d.mean(), v_q.mean(), w.mean()])
    nb = max(int(BLOCK_S / sig.ts), 1)
    k = sig.n // nb
    se = []
    for v, i_a, i_b, sgn in ((v_d, i_d, i_q, -1.0), (v_q, i_q, i_d, 1.0)):
        # the equation's residual per block: v - R i_a - sgn w L i_b varies with R, L; the blocks'
        # spread of v itself (less its slow trend with the current) bounds it
        blocks = v[: k * nb].reshape(k, nb).mean(axis=1) if k >= 4 else v
        spread = float(np.std(blocks, ddof=1) / np.sqrt(blocks.size)) if blocks.size > 1 else abs(v.mean())
        se.append(np.hypot(spread, V_ACCURACY * abs(v.mean()) + V_FLOOR))
    sv = zero_sequence_sigma(sig.v_abc) if sig.v_abc is not None else 0.0
    si = zero_sequence_sigma(sig.i_abc) if sig.i_abc is not None else 0.0
    answer = None if samples == "independent" else immediate_answer(sig)
    gram, iv, own = [], [], (None if answer is None else [])
    for axis in (0, 1):
        other = 1 - axis
        cols = [sig.i_dq[axis, :-1], sig.v_dq[axis, :-1], w[:-1] * sig.i_dq[other, :-1]]
        if axis == 1:
            cols.append(w[:-1])
        x = np.column_stack(cols + [np.ones(sig.n - 1)])
        y = sig.i_dq[axis, 1:]
        g = x.T @ x
        # white channel noise in the regressors (errors in variables): remove its expected share
        noise = np.zeros(x.shape[1])
        noise[0] = _dq_noise_var(si)
        noise[1] = _dq_noise_var(sv)
        noise[2] = float(np.mean(w**2)) * _dq_noise_var(si)
        g -= np.diag(noise) * (sig.n - 1)
        h = x.T @ y
        theta = np.linalg.lstsq(g, h, rcond=None)[0]
        e = y - x @ theta
        xe = x * e[:, None]
        gram.append((g, h, xe.T @ xe))
        if own is not None:  # the voltage's row meets K n(k): E[v n_a] = K_aa s_i, E[v omega n_b] = K_ab omega s_i
            g_own = g.copy()
            g_own[1, 0] -= answer[axis, axis] * _dq_noise_var(si) * (sig.n - 1)
            g_own[1, 2] -= answer[axis, other] * float(np.mean(w)) * _dq_noise_var(si) * (sig.n - 1)
            own.append((g_own, h, xe.T @ xe))
        if instruments:
            zx, zy = iv_moments(x, y)
            iv.append((zx, zy, iv_meat(x, y, np.linalg.lstsq(zx, zy, rcond=None)[0])))
    return Observation(means, np.array(se), gram, sig.ts, encoder, iv, own, samples)


@dataclass
class Prior:
    """Log-normal prior of one parameter: centre (SI unit) and relative sd, and where it comes from."""

    value: float
    rel_sd: float
    source: str


COPPER_T0_C = 234.5  #: C, copper's inferred zero-resistance temperature: R(T) ~ T + 234.5 (alpha_20 = 0.00393/K)


def nameplate_priors(profile: DriveProfile) -> dict[str, Prior]:
    """Priors from the profile's ``[nameplate]`` (see :class:`agent.profile.Nameplate`)."""
    n = profile.nameplate
    if n is None:
        return {}
    out = {}
    if n.rs_ohm is not None:
        t_op = n.rs_temp_c if n.winding_temp_c is None else n.winding_temp_c
        out["Rs"] = Prior(n.rs_ohm * (COPPER_T0_C + t_op) / (COPPER_T0_C + n.rs_temp_c), n.rs_tol_pct / 100,
                          f"nameplate.rs_ohm ({n.rs_ohm:g} ohm at {n.rs_temp_c:g} C, winding at {t_op:g} C)")
    psi = n.psi_m(profile.motor.pole_pairs)
    if psi is not None:
        out["psi_m"] = Prior(psi, n.psi_m_tol_pct / 100,
                             "nameplate.psi_m_wb" if n.psi_m_wb is not None else "nameplate.ke_vrms_per_krpm")
    for name, key in (("Ld", "ld_h"), ("Lq", "lq_h")):
        if getattr(n, key) is not None:
            out[name] = Prior(getattr(n, key), n.l_tol_pct / 100, f"nameplate.{key}")
    return out


@dataclass
class Estimate:
    """Physical parameters with 95 % intervals; which the records could not determine, and why."""

    values: dict  #: name -> value (SI), None when neither data nor nameplate determine it
    ci95: dict  #: name -> (low, high)
    rel_sd: dict  #: name -> posterior relative sd
    data_rel_sd: dict  #: name -> relative sd from the records alone (inf: not identifiable)
    determined_by: dict  #: name -> "records", "nameplate" or "records+nameplate"
    unidentifiable: list = field(default_factory=list)  #: [{"parameters": [...], "reason": str}]
    problems: list = field(default_factory=list)  #: reasons to refuse the estimate (nonphysical)
    priors: dict = field(default_factory=dict)
    conflicts: dict = field(default_factory=dict)  #: name -> warning: a nameplate value the records contradict (dropped)
    instrumented: list = field(default_factory=list)  #: "Ld", "Lq": read by the instrumented regression
    #: (the drive's voltage answers the current's noise within the sample: :func:`_dynamics`)

    def to_json(self) -> dict:
        return {"values": self.values, "ci95": {k: list(v) if v else None for k, v in self.ci95.items()},
                "rel_sd": self.rel_sd, "data_rel_sd": {k: (None if not np.isfinite(v) else v)
                                                        for k, v in self.data_rel_sd.items()},
                "determined_by": self.determined_by, "unidentifiable": self.unidentifiable,
                "problems": self.problems, "conflicts": self.conflicts, "instrumented": self.instrumented,
                "priors": {k: {"value": p.value, "rel_sd": p.rel_sd, "source": p.source} for k, p in self.priors.items()}}


def _data_residual(obs: list[Observation], dyn: list[tuple[float, float]], current_on_q: bool = False):
    """Residual function of log-parameters z: steady-state rows of every record, dynamic rows. The
    steady d row only where the frame's d axis is the rotor's: an encoder's frame, or a PLL's on the
    current where ``current_on_q`` (the profile says the drive holds i_d = 0). There the current's
    d component is the frame's error (a PLL lagging a speed step), not the rotor's i_d: the row is
    v_d = -omega_e L_q i_q (with R_s i_d it pulled R_s to wherever the lag put i_d, and psi_m,
    collinear with R_s, lost its identification on 7 of 200 family drives)."""
    m = np.array([o.means for o in obs])
    se = np.array([o.se for o in obs])
    i_d, i_q, v_d, v_q, w = m.T
    log_l = np.array([np.log(d[0]) if np.isfinite(d[0]) and d[0] > 0 else np.nan for d in dyn])
    s_l = np.array([d[1] for d in dyn])
    rotor_d = np.array([float(o.encoder or current_on_q) for o in obs])  # the steady d row: the rotor's frame only
    i_d_rotor = np.array([o.means[0] if o.encoder else 0.0 for o in obs])

    def residual(z):
        rs, ld, lq, psi = np.exp(z)
        rows = [rotor_d * (v_d - (rs * i_d_rotor - w * lq * i_q)) / se[:, 0],
                (v_q - (rs * i_q + w * ld * i_d + w * psi)) / se[:, 1]]
        dyn_rows = np.where(np.isfinite(log_l) & np.isfinite(s_l), (z[1:3] - np.nan_to_num(log_l)) / s_l, 0.0)
        return np.concatenate(rows + [dyn_rows])

    return residual


def scaled_pinv(a: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of a normal-equation matrix ``a`` whose columns differ by orders of magnitude
    (A, V, rad/s): equilibrated by sqrt|diag| on both sides first, so that rcond judges the
    columns' correlation, not their units."""
    scale = np.sqrt(np.abs(np.diag(a))) + 1e-300
    return np.linalg.pinv(a / np.outer(scale, scale), rcond=1e-12) / np.outer(scale, scale)


def _pooled(parts: list, p: int):
    """(A, c, M) of per-record normal equations (A_j, c_j, M_j) with ``p`` shared columns and one
    intercept per record (the last column of each)."""
    size = p + len(parts)
    a, c, meat = np.zeros((size, size)), np.zeros(size), np.zeros((size, size))
    for j, (aj, cj, mj) in enumerate(parts):
        idx = list(range(p)) + [p + j]
        a[np.ix_(idx, idx)] += aj
        meat[np.ix_(idx, idx)] += mj
        c[idx] += cj
    return a, c, meat


def endogenous(b: float, b_iv: float, var_iv: float) -> bool:
    """Whether the compensated regression's T_s/L ``b`` is rejected for the instrumented one's
    ``b_iv`` (variance ``var_iv``): beyond ``ENDOGENOUS_Z`` of its standard error and by more than
    ``ENDOGENOUS_REL`` of it. The second bound keeps the compensated reading where the difference
    is real but small: a current window's filter reaches the next sample's voltage, which answers
    this sample's noise (a 1/8 share; 0.4 % on a family drive) while the weaker instrumented reading
    left L_d unidentified."""
    return bool(np.isfinite(b_iv) and np.isfinite(var_iv)
                and abs(b - b_iv) > max(ENDOGENOUS_Z * np.sqrt(max(var_iv, 0.0)), ENDOGENOUS_REL * abs(b_iv)))


#: why :func:`_dynamics` asked for the instrumented reading, as the reason of an inductance it left unidentified
ASKED_WHY = {
    "answers": "the drive's voltage answers the current's noise within the sample (a controller without computation "
               "delay acting on the samples recorded), so the current loop's broadband voltage does not read the "
               "inductance",
    "unstated": "these records read it differently as the controller's own current samples and as an independent "
                "DAQ's (a controller without computation delay answers its own samples' noise within the sample): "
                "state sampling.current_source (\"controller\" or \"independent\") in the profile",
    "instruments": "the compensated and the instrumented readings of the current's response disagree beyond the "
                   "instrumented one's standard error, so something in these records answers the current's noise "
                   "that the model lacks (a filter the profile does not state, the PWM ripple in samples off the "
                   "carrier's centre)",
}


def _dynamics(obs: list[Observation]) -> list[tuple[float, float, str | None]]:
    """Per axis (L_x in H, sd of log L_x, why the instrumented regression was asked: None, ``"answers"``,
    ``"unstated"`` or ``"instruments"``) from the pooled, noise-compensated dynamics regressions (shared slopes, one
    intercept per record); (nan, inf) when the voltage does not excite the current's response. The
    covariance is the sandwich G^-1 M G^-1: the compensated estimator's residual carries the
    regressors' own noise, which the textbook s^2 G^-1 would leave out.

    The plain compensation assumes the voltage does not answer the current's noise within the sample.
    A controller that acts on the sample it has just taken (no computation delay) puts K n(k) into
    v(k) where the record's current is its own samples, and the regression reads T_s/L biased (L_d
    3.5x high, L_q 0.6x on a family drive; on the 44 such axes of 200 family drives 62 % off at the
    median and all 44 more than 20 % off, against 17 of 109 with a computation delay, with a claimed
    sd of 1-4 %). Two checks ask for the instrumented regression (the previous samples' regressors as
    instruments: its noise is white, so nothing there correlates with it, but it is weaker):

    * **answers**: the reading compensated for the controller's own immediate answer
      (:attr:`Observation.own`) differs from the plain one by more than ``ENDOGENOUS_REL``: the
      reading hangs on whether the voltage answers this sample's noise. Where the profile says the
      current is the controller's own samples, it does (``"answers"``); where it says nothing, the
      records cannot tell (``"unstated"``: an independent DAQ's current makes the immediate-answer
      regression read spurious gains); where it says an independent DAQ's, the check is not made. The
      own reading itself is not used: under constant references it leans on the noise variances and
      K to within a few per cent (of the 44 axes above it left 17 more than 20 % off, median 6 %);
    * the Hausman-type check: the two readings differ by more than ``ENDOGENOUS_Z`` of the
      instrumented one's standard error (:func:`endogenous`): ``"answers"``, or ``"instruments"``
      where the profile says the current is an independent DAQ's (then no controller answers its
      noise, and the cause is something else the model lacks: an unstated filter, the PWM ripple).

    The instrumented reading then stands with its own, wider uncertainty (on a drive without the
    loop's broadband excitation, so wide that L_x is reported as not identifiable). Encoder frames
    only: a frame that follows the current carries the current's own errors two samples on, and the
    instrumented reading there was worse than the compensated one (L_q 49 % low for 7 % on a family
    drive), so there an asked-for axis is not identifiable. Point samples only (:func:`observe`'s
    ``instruments``): behind a current window the model is a straight-line approximation whose error
    the instruments carry (L_d 70 % low on a family drive, 28 % high by the compensated reading)."""
    out = []
    for axis in (0, 1):
        use = [o for o in obs if o.encoder or axis == 1]  # L_d: encoder frames only
        if not use:
            out.append((np.nan, np.inf, None))
            continue
        p = use[0].gram[axis][0].shape[0] - 1
        g, h, meat = _pooled([o.gram[axis] for o in use], p)
        gi = scaled_pinv(g)
        b = (gi @ h)[1]  # T_s / L_x
        var_b = (gi @ meat @ gi)[1, 1]
        asked = None
        if all(o.own is not None for o in use):
            g_own, h_own, _ = _pooled([o.own[axis] for o in use], p)
            b_own = (scaled_pinv(g_own) @ h_own)[1]
            if not (np.isfinite(b_own) and abs(b_own - b) <= ENDOGENOUS_REL * abs(b)):
                asked = "answers" if all(o.samples == "controller" for o in use) else "unstated"
        if all(o.iv and o.encoder for o in use):  # a PLL's frame follows the current: its errors are no instruments
            zx, zy, zmeat = _pooled([o.iv[axis] for o in use], p)
            with np.errstate(all="ignore"):
                zi = scaled_pinv(zx)
                b_iv, var_iv = (zi @ zy)[1], (zi @ zmeat @ zi.T)[1, 1]
            if asked is None and endogenous(b, b_iv, var_iv):
                asked = "instruments" if all(o.samples == "independent" for o in use) else "answers"
            if asked is not None:
                b, var_b = b_iv, var_iv
        elif asked is not None:
            out.append((np.nan, np.inf, asked))
            continue
        if not (np.isfinite(b) and b > 0 and np.isfinite(var_b)):
            out.append((np.nan, np.inf, asked))
            continue
        out.append((obs[0].ts / b, float(np.sqrt(max(var_b, 0.0)) / b), asked))
    return out


def _collinear_reason(names: list[str], means: np.ndarray, encoder: bool = True) -> str:
    fe_spread = np.ptp(means[:, 4]) / max(abs(means[:, 4]).mean(), 1e-9)
    iq_spread = np.ptp(means[:, 1]) / max(abs(means[:, 1]).mean(), 1e-9)
    one_point = fe_spread < 0.05 and iq_spread < 0.2
    s = set(names)
    if {"Rs", "psi_m"} <= s:
        where = "at one operating point" if one_point else "over these operating points"
        return (f"R_s and psi_m are collinear {where} (both only in R_s i_q + omega_e psi_m); records at a "
                f"second load (i_q at least 30 % apart) or a speed step separate them, or give "
                f"nameplate.rs_ohm or nameplate.psi_m_wb")
    if s == {"Ld"}:
        if not encoder:
            return ("L_d: with i_d ~ 0 it is absent from the steady state, and its sample-to-sample response is "
                    "read only in an encoder's frame (a PLL's d axis carries the shaft's speed ripple); records "
                    "with an encoder angle, or with i_d varying (field weakening, MTPA), reveal it, or give "
                    "nameplate.ld_h")
        return ("L_d: with i_d ~ 0 it is absent from the steady state, and the voltage barely excites the d "
                "current; a d-current step, field weakening or PWM ripple in the records reveals it, or give "
                "nameplate.ld_h")
    if s == {"Lq"}:
        if not encoder:
            return ("L_q: too little voltage response on q, and without an encoder the steady d voltage does not "
                    "read it (the current may lead the q axis: MTPA, field weakening); records with an encoder "
                    "angle reveal it, or give nameplate.lq_h")
        return ("L_q: too little voltage response on q and too little q current; records under load reveal it, "
                "or give nameplate.lq_h")
    if s == {"Rs"}:
        return "R_s: its voltage drop is too small against the voltage channel's accuracy; give nameplate.rs_ohm"
    if s == {"psi_m"}:
        return "psi_m: the back-EMF is not separated from the other terms; give nameplate.psi_m_wb"
    return " and ".join(names) + " are not separated by these records; records at other loads and speeds help"


def estimate(obs: list[Observation], profile: DriveProfile, priors: dict[str, Prior] | None = None) -> Estimate:
    """MAP estimate of (R_s, L_d, L_q, psi_m) from records' observations and nameplate priors.

    A nameplate value the records contradict (they pull the estimate more than ``CONFLICT_Z`` of
    its tolerances away) is left out (its spread widened to the vague prior's) and the estimate made
    again: a warning in
    ``conflicts`` names the field and the size of the disagreement, and the records' value is the
    one reported (a compromise between two values that disagree would be neither)."""
    priors = nameplate_priors(profile) if priors is None else priors
    dyn = _dynamics(obs)
    est = _estimate(obs, profile, priors, dyn)
    contradicted = [k for k in est.conflicts if k in priors]
    if not contradicted:
        return est
    # the contradicted value widened to the vague prior's spread: the records set it, the rest stays
    kept = {k: Prior(p.value, VAGUE_SD, f"{p.source} (contradicted by the records: not used)")
            if k in contradicted else p for k, p in priors.items()}
    again = _estimate(obs, profile, kept, dyn)
    again.conflicts = {**est.conflicts, **again.conflicts}
    return again


def _estimate(obs: list[Observation], profile: DriveProfile, priors: dict[str, Prior], dyn: list) -> Estimate:
    """The MAP fit; where a sample-to-sample reading of L_x and the rest of the records disagree
    (:func:`_dynamics_conflicts`), the fit again without it, and a warning naming both values."""
    est = _fit(obs, profile, priors, dyn)
    dropped = _dynamics_conflicts(est, dyn)
    if not dropped:
        return est
    again = _fit(obs, profile, priors, [(np.nan, np.inf, d[2]) if name in dropped else d
                                         for name, d in zip(("Ld", "Lq"), dyn)])
    for name, (value, sd, apart) in dropped.items():
        kept = again.values[name]
        again.conflicts[f"{name}_dynamics"] = (
            f"the current's sample-to-sample response reads {name} = {value:.4g} H +- {100 * sd:.0f} %, "
            f"{apart:.0f} of its sds from what the rest of the records say: a cause outside the one-step model "
            f"(a frame that follows the current through steps, a current sampled away from the carrier's centre); "
            + (f"{kept:.4g} H from the rest is used" if kept is not None else
               f"not used, and the rest do not pin {name}"))
    return again


def _dynamics_conflicts(est: Estimate, dyn: list) -> dict[str, tuple[float, float, float]]:
    """Inductances whose sample-to-sample reading (``dyn``) lies more than ``CONFLICT_Z`` of its sds
    from what the fit made of all the records (the steady d voltage reads L_q in the rotor's frame):
    name -> (the reading H, its sd, how many sds apart). The two read one L_q through different
    physics, and a reading that misses by many of its own sds has a cause outside its model: a frame
    that follows the current through steps and load ripple (read so, L_q 22 % to 3x high on seven
    family drives without an encoder under i_d = 0, with a claimed sd of 1-2 %; without that reading
    six of them within 2.2 %), a current sampled away from the carrier's centre."""
    out = {}
    for name, (value, sd, _) in zip(("Ld", "Lq"), dyn):
        fitted = est.values.get(name)
        if fitted and np.isfinite(value) and value > 0 and np.isfinite(sd) and sd > 0:
            apart = abs(np.log(value / fitted)) / sd
            if apart > CONFLICT_Z:
                out[name] = (float(value), float(sd), float(apart))
    return out


def _fit(obs: list[Observation], profile: DriveProfile, priors: dict[str, Prior], dyn: list) -> Estimate:
    data_res = _data_residual(obs, dyn, profile.sampling.current_reference == "id0")
    means = np.array([o.means for o in obs])
    # where the nameplate says nothing: a vague prior (log-sd VAGUE_SD) around a plausible point from
    # the steady state: R_s at a 5 % voltage drop, psi_m from v_q, L_q from v_d, L_d from the dynamics
    w = float(np.mean(means[:, 4]))
    i_q = float(np.mean(means[:, 1]))
    v_abs = float(np.mean(np.hypot(means[:, 2], means[:, 3])))
    i_abs = float(np.mean(np.hypot(means[:, 0], means[:, 1])))
    guess = {"Rs": 0.05 * v_abs / max(i_abs, 1e-6), "Ld": dyn[0][0],
             "Lq": -np.mean(means[:, 2]) / (w * i_q) if abs(w * i_q) > 0 else np.nan,
             "psi_m": np.mean(means[:, 3]) / w if w else np.nan}
    guess = {k: v if np.isfinite(v) and v > 0 else (dyn[1][0] if k == "Ld" and np.isfinite(dyn[1][0]) else 0.01)
             for k, v in guess.items()}
    centre = np.array([priors[k].value if k in priors else guess[k] for k in NAMES])
    sd = np.array([priors[k].rel_sd if k in priors else VAGUE_SD for k in NAMES])
    z0 = np.log(centre)

    def residual(z):
        return np.concatenate((data_res(z), (z - z0) / sd))

    z = levenberg_marquardt(residual, z0)
    jac = _jacobian(residual, z)
    post = np.sqrt(np.clip(np.diag(np.linalg.pinv(jac.T @ jac)), 0, None))
    # what the records alone say: the marginal sds under the vague prior on every parameter
    jd = _jacobian(data_res, z)
    cov_v = np.linalg.inv(jd.T @ jd + np.eye(4) / VAGUE_SD**2)
    data_sd = np.sqrt(np.clip(np.diag(cov_v), 0, None))
    corr = cov_v / np.outer(data_sd, data_sd)
    weak = data_sd > IDENTIFIABLE_REL
    groups = []
    for j in np.flatnonzero(weak):
        close = [k for k in range(4) if k == j or abs(corr[j, k]) > COLLINEAR]
        names = [NAMES[k] for k in close if weak[k]]
        if names in [g["parameters"] for g in groups]:
            continue
        reason = _collinear_reason([NAMES[k] for k in close], means, any(o.encoder for o in obs))
        asked = {n: dyn[("Ld", "Lq").index(n)][2] for n in names if n in ("Ld", "Lq")}
        inductances = [n for n, why in asked.items() if why]
        if inductances:
            keys = " and ".join(f"nameplate.{n.lower()}_h" for n in inductances)
            why = "; ".join(ASKED_WHY[w] for w in dict.fromkeys(asked[n] for n in inductances))
            reason = (f"{' and '.join(inductances)}: {why}; records with current-reference steps, or {keys}; "
                      + reason)
        groups.append({"parameters": names, "reason": reason,
                       "correlated": {NAMES[k]: float(data_sd[k]) for k in close if not weak[k]},
                       "from_nameplate": all(n in priors for n in names)})
    data_sd = np.where(weak, np.inf, data_sd)
    values, ci, rel, by = {}, {}, {}, {}
    for j, name in enumerate(NAMES):
        seen = np.isfinite(data_sd[j])
        has_prior = name in priors
        by[name] = "records+nameplate" if seen and has_prior else "records" if seen else "nameplate" if has_prior else None
        if by[name] is None:
            values[name], ci[name], rel[name] = None, None, None
            continue
        values[name] = float(np.exp(z[j]))
        ci[name] = (float(np.exp(z[j] - Z95 * post[j])), float(np.exp(z[j] + Z95 * post[j])))
        rel[name] = float(post[j])
    return Estimate(values, ci, rel, {n: float(data_sd[j]) for j, n in enumerate(NAMES)}, by, groups,
                    _problems(z, means, profile), dict(priors), _conflicts(z, z0, sd, priors),
                    [n for n, d in zip(("Ld", "Lq"), dyn) if d[2]])


def _jacobian(fun, z: np.ndarray, h: float = 1e-6) -> np.ndarray:
    r0 = fun(z)
    return np.column_stack([(fun(z + h * e) - r0) / h for e in np.eye(z.size)])


def _conflicts(z, z0, sd, priors) -> dict[str, str]:
    """Nameplate values the records contradict: the records pull the estimate more than
    ``CONFLICT_Z`` tolerances away; name -> the warning, naming the field and the disagreement."""
    out = {}
    for j, name in enumerate(NAMES):
        p = priors.get(name)
        if p is not None and abs(z[j] - z0[j]) > CONFLICT_Z * sd[j]:
            out[name] = (f"{p.source.split(' ')[0]} disagrees with the records: it says {p.value:.4g} {UNITS[name]} "
                         f"+- {100 * p.rel_sd:.0f} %, the records pull {name} to {np.exp(z[j]):.4g} {UNITS[name]} "
                         f"even against it ({np.exp(z[j] - z0[j]) - 1:+.0%}, {abs(z[j] - z0[j]) / sd[j]:.1f} "
                         f"tolerances); the records' value is used")
    return out


def _problems(z, means, profile) -> list[str]:
    """Reasons the estimate is not physical: values outside physical ranges."""
    out = []
    rs, ld, lq, psi = np.exp(z)  # the estimate itself, whether or not the records pin each value
    w = float(np.mean(np.abs(means[:, 4])))
    v = float(np.mean(np.hypot(means[:, 2], means[:, 3])))
    for name, l in (("Ld", ld), ("Lq", lq)):
        if not 1e-4 <= l / rs <= 2.0:
            out.append(f"{name}/Rs = {l / rs:.3g} s is outside 0.1 ms .. 2 s (no motor has that time constant)")
    if w > 0 and psi * w < 0.05 * v:
        out.append(f"psi_m = {psi:.3g} Wb gives a back-EMF of {psi * w:.3g} V, under 5 % of the {v:.3g} V applied "
                   "while current flows: a PMSM's magnet flux cannot be that small")
    if v > 0:
        i = float(np.mean(np.hypot(means[:, 0], means[:, 1])))
        if rs * i > 0.5 * v:
            out.append(f"Rs = {rs:.3g} ohm would drop {rs * i:.3g} V of the {v:.3g} V applied")
    z_base = profile.motor.z_base_ohm
    if z_base:
        if not 1e-3 * z_base <= rs <= 0.5 * z_base:
            out.append(f"Rs = {rs:.3g} ohm is outside 0.001..0.5 of the nameplate impedance ({z_base:.3g} ohm)")
    return out
