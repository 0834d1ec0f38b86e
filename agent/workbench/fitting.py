"""Output-error (free-run) refits of the dq model with named effects, and their hold-out evaluation.

Model (physical units): L di/dt = v - R_s i - omega_e J L i - omega_e psi_m e_q + sum_j p_j c_j(k)
for voltage effects, discretised exactly as :class:`agent.model.DQModel` does (its ``form``), and
y = x + sum_j p_j c_j(k) for output effects. The free-run output is linear in psi_m and in every
effect parameter p_j once (R_s, L_d, L_q) are fixed, so the fit is a *variable projection*: an outer
nonlinear least-squares over log(R_s, L_d, L_q) whose every evaluation solves the linear parameters
exactly from the simulated responses of their columns (one batched numba simulation per record).

Hold-out: each record is split in time; the fit uses its first ``FIT_FRACTION`` (at most
``max_fit_s`` seconds), the error is measured on the rest, from a free run over the whole record
(the free run forgets its start within a few L/R time constants, ~10 ms). Records whose angle comes
from the PLL lose their first ``SETTLE_S`` (the PLL's lock-in).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np
import scipy.optimize

from agent.effects import get as get_effect
from agent.identify import operating_point, record_signals
from agent.model import DQModel, Signals, lumped_params, nrmse
from agent.profile import DriveProfile
from agent.records import Record

SETTLE_S = 0.1  #: s dropped at the start of records whose angle comes from the PLL
FIT_FRACTION = 0.5  #: share of each record used for fitting; the rest is held out
BLOCK_S = 0.1  #: s, block length of the held-out significance test
DECIMATE = 4  #: the fit's error is read at every DECIMATE-th sample (the free run is simulated at all)
_SCALE = np.array([1.0, 1.0, 1e-2, 1e-2, 1e-2])  # R_s,d ohm, R_s,q ohm, L_d H, L_q H, L_qx H
NONLINEAR = ("Rs_d", "Rs_q", "Ld", "Lq", "Lq_x")


@dataclass
class Prepared:
    """One record ready for the workbench: dq signals, operating point, where the hold-out starts."""

    source: str
    sig: Signals
    op: dict
    split: int  #: first held-out sample
    meta: dict = field(default_factory=dict)

    @property
    def fit_slice(self) -> slice:
        return slice(0, self.split)

    @property
    def eval_slice(self) -> slice:
        return slice(self.split, self.sig.n)


def prepare(records: list[Record], profile: DriveProfile, max_fit_s: float = 0.5) -> list[Prepared]:
    out = []
    rate = profile.sampling.rate_hz
    for rec in records:
        sig = record_signals(rec, profile)
        if rec.theta_e is None:
            sig = sig.slice(int(SETTLE_S * rate), sig.n)
        split = min(int(FIT_FRACTION * sig.n), int(max_fit_s * rate))
        out.append(Prepared(rec.source, sig, operating_point(sig, profile), split, dict(rec.meta)))
    return out


@numba.njit(cache=True)
def _sim_batch(a0, a1, omega, u, x0):
    """Free runs x(k+1) = (A0 + omega(k) A1) x(k) + u[m](k) for every input m: (M, 2, N) from (M, 2)."""
    m_in, _, n = u.shape
    x = np.empty((m_in, 2, n))
    for m in range(m_in):
        d, q = x0[m, 0], x0[m, 1]
        x[m, 0, 0], x[m, 1, 0] = d, q
        for k in range(n - 1):
            w = omega[k]
            d, q = ((a0[0, 0] + w * a1[0, 0]) * d + (a0[0, 1] + w * a1[0, 1]) * q + u[m, 0, k],
                    (a0[1, 0] + w * a1[1, 0]) * d + (a0[1, 1] + w * a1[1, 1]) * q + u[m, 1, k])
            x[m, 0, k + 1], x[m, 1, k + 1] = d, q
    return x


def _thetas(form, ts, w, rs_d, rs_q, ld, lq, lq_x, psi_m):
    """Base coefficient vectors (d, q) of ``form``. Each axis has its own resistance and the d axis
    its own cross-coupling inductance ``lq_x``: the freedom of the paper's lumped coefficients."""
    return lumped_params(form, ts, rs_d, ld, lq_x, psi_m, w)[0], lumped_params(form, ts, rs_q, ld, lq, psi_m, w)[1]


def base_model(form: str, ts: float, fe_hz: float, phys: dict, effect_ids=(), values: dict | None = None) -> DQModel:
    """A :class:`DQModel` from physical values (``Rs_d, Rs_q, Ld, Lq, Lq_x, psi_m``) and effect parameters."""
    from agent.effects import model_terms

    w = 2 * np.pi * fe_hz
    th_d, th_q = _thetas(form, ts, w, *(phys[k] for k in (*NONLINEAR, "psi_m")))
    ld, lq = phys["Ld"], phys["Lq"]
    extra_d, extra_q = model_terms(effect_ids)
    for eid in effect_ids:
        eff, p = get_effect(eid), np.asarray((values or {})[eid], dtype=float)
        gain_d, gain_q = (1.0, 1.0) if eff.kind == "output" else (ts / ld, ts / lq)
        th_d, th_q = np.concatenate((th_d, p * gain_d)), np.concatenate((th_q, p * gain_q))
    model = DQModel(form, ts, th_d, th_q, extra_d, extra_q, fe_hz=fe_hz)
    model.meta["effects"] = list(effect_ids)
    return model


@dataclass
class Refit:
    """Result of one output-error refit."""

    effects: tuple[str, ...]
    model: DQModel
    phys: dict  #: Rs_d, Rs_q ohm, Ld H, Lq H, Lq_x H (the d axis's cross-coupling inductance), psi_m Wb
    values: dict  #: effect id -> parameter values (physical units)
    cost: float
    unique: dict  #: effect id -> share of its response that the base parameters cannot absorb


def refit(preps: list[Prepared], form: str, fe_hz: float, effect_ids=(), start: dict | None = None,
          max_nfev: int = 40) -> Refit:
    """Free-run refit of (R_s,d, R_s,q, L_d, L_q, L_qx, psi_m) and the effects' parameters on the fit
    segments. Like the paper's lumped coefficients, each axis has its own R_s (at one load R_s,q
    trades with psi_m) and L_qx is L_q as the d axis sees it in omega_e L_q i_q: it takes up a
    d-voltage bias (angle offset, chord against incremental L_q under saturation)."""
    ts = preps[0].sig.ts
    w_op = 2 * np.pi * fe_hz
    effs = [get_effect(e) for e in effect_ids]
    data = []
    for p in preps:
        cut = p.fit_slice
        s = p.sig
        cols = [e.cols(s)[:, :, cut] for e in effs]
        data.append((np.ascontiguousarray(s.omega_e[cut]), s.v_dq[:, cut], s.i_dq[:, cut], cols))
    kinds = [e.kind for e in effs for _ in e.params]
    n_lin = 1 + len(kinds)

    def responses(z):
        rs_d, rs_q, ld, lq, lq_x = np.exp(z) * _SCALE
        a0, a1 = DQModel(form, ts, *_thetas(form, ts, w_op, rs_d, rs_q, ld, lq, lq_x, 0.0)).state_matrices()
        b = np.array([ts / ld, ts / lq])[:, None]
        for omega, v, i, cols in data:
            n = omega.size
            u = np.zeros((1 + n_lin, 2, n))
            x0 = np.zeros((1 + n_lin, 2))
            u[0], x0[0] = b * v, i[:, 0]
            u[1, 1] = -ts / lq * omega
            j = 2
            for c, e in zip(cols, effs):
                for row in c:
                    if e.kind == "voltage":
                        u[j] = b * row
                    else:
                        x0[j] = -row[:, 0]
                    j += 1
            r = _sim_batch(a0, a1, omega, u, x0)
            j = 2
            for c, e in zip(cols, effs):
                if e.kind == "output":
                    r[j:j + len(c)] += c
                j += len(c)
            yield (i - r[0])[:, ::DECIMATE], r[1:, :, ::DECIMATE]

    def solve(z):
        g, h, parts = np.zeros((n_lin, n_lin)), np.zeros(n_lin), []
        with np.errstate(over="ignore", invalid="ignore"):
            for y, s in responses(z):
                s2 = s.reshape(n_lin, -1)
                g += s2 @ s2.T
                h += s2 @ y.ravel()
                parts.append((y, s))
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(h))):
            return None, parts  # a trial step made the free run diverge
        scale = np.sqrt(np.diag(g)) + 1e-30
        alpha = np.linalg.lstsq(g / np.outer(scale, scale), h / scale, rcond=1e-12)[0] / scale
        return alpha, parts

    n_res = sum(2 * len(range(0, d[0].size, DECIMATE)) for d in data)

    def residual(z):
        alpha, parts = solve(z)
        if alpha is None:
            return np.full(n_res, 1e3)
        res = np.concatenate([(y - np.tensordot(alpha, s, 1)).ravel() for y, s in parts])
        return np.nan_to_num(res, nan=1e3, posinf=1e3, neginf=-1e3)

    start = {**{"Rs_d": 1.0, "Rs_q": 1.0, "Ld": 0.01, "Lq": 0.01, "Lq_x": 0.01}, **(start or {})}
    z0 = np.log(np.array([start[k] for k in NONLINEAR]) / _SCALE)
    sol = scipy.optimize.least_squares(residual, z0, method="trf", max_nfev=max_nfev, diff_step=1e-4, verbose=0,
                                       ftol=1e-7, xtol=1e-7)
    alpha, parts = solve(sol.x)
    values, j = {}, 1
    for e in effs:
        values[e.id] = alpha[j:j + len(e.params)]
        j += len(e.params)
    phys = {**dict(zip(NONLINEAR, (np.exp(sol.x) * _SCALE).tolist())), "psi_m": float(alpha[0])}
    model = base_model(form, ts, fe_hz, phys, effect_ids, values)
    unique = {}
    if effs:  # sensitivities of the free-run output to the base parameters, effects' responses
        def output(z):
            return np.concatenate([(i0[:, ::DECIMATE] - y - np.tensordot(alpha, s, 1)).ravel()
                                   for (y, s), (_, _, i0, _) in zip(responses(z), data)])
        y0 = output(sol.x)
        base = [(output(sol.x + 1e-4 * e) - y0) / 1e-4 for e in np.eye(len(NONLINEAR))]
        s_all = np.concatenate([s.reshape(n_lin, -1) for _, s in parts], axis=1)
        i_norm = np.sqrt(sum(np.sum(d[2][:, ::DECIMATE] ** 2) for d in data))
        unique = _unique_share(np.column_stack(base + [s_all[0]]), s_all, effs, i_norm)
    return Refit(tuple(effect_ids), model, phys, values, float(2 * sol.cost), unique)


def _unique_share(base: np.ndarray, s_all: np.ndarray, effs, i_norm: float) -> dict:
    """Per effect: (share, visible): the share of its typical-size free-run response that the base
    parameters (``base``: output sensitivities to the base parameters) cannot absorb (0..1),
    and that unabsorbed part's norm over the measured current's (an NRMSE)."""
    q, _ = np.linalg.qr(base / np.maximum(np.linalg.norm(base, axis=0), 1e-300))
    out, j = {}, 1
    for e in effs:
        resp = s_all[j:j + len(e.params)].T @ np.array([p.typical for p in e.params])
        left = float(np.linalg.norm(resp - q @ (q.T @ resp)))
        out[e.id] = (left / max(np.linalg.norm(resp), 1e-300), left / i_norm)
        j += len(e.params)
    return out


def heldout(model: DQModel, preps: list[Prepared], block_s: float = BLOCK_S) -> dict:
    """Free-run error of ``model`` on the held-out segments: pooled NRMSE (agent.model.nrmse) and
    the per-block sums of squared error for the significance test."""
    meas, pred, blocks = [], [], []
    for p in preps:
        y = model.simulate(p.sig)[:, p.eval_slice]
        i = p.sig.i_dq[:, p.eval_slice]
        meas.append(i)
        pred.append(y)
        nb = max(int(block_s / p.sig.ts), 1)
        e2 = np.sum((i - y) ** 2, axis=0)
        k = e2.size // nb
        blocks.append(e2[: k * nb].reshape(k, nb).sum(axis=1) if k else e2.sum(keepdims=True))
    out = nrmse(np.hstack(meas), np.hstack(pred))
    out["blocks"] = np.concatenate(blocks)
    return out
