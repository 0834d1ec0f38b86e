"""Relative gain errors of the acquisition's phase-b and phase-c current sensors (against phase a).

Family: i_x,meas = (1 + g_x) i_x for x = b, c; a gain error common to all three is a scale of the
current the motor parameters take, so phase a is the reference. In the dq frame the mismatch is a
negative sequence, eps i*, with 3 eps = g_b a^2 + g_c a (a = e^{j 2 pi / 3}). Where the drive's
controller acts on the same sensors, it holds the measured current at its reference, the winding
carries -eps i* and the mismatch shows only as the voltage that drives it, which the model reads
through its own impedance R_s,q - j omega_e L: on the drive family R_s,q was 2-4 times the
winding's, and eps came out rotated by up to 41 degrees, which put per-phase figures up to 161 %
off. The phase currents' sum reads the sensors directly (:func:`sensor_sum`): a three-wire
winding's currents sum to zero, so the measured sum is g_b i_b + g_c i_c relative to phase a,
whatever the controller does.

Degrees of freedom: g_b, g_c (dimensionless, each within +-0.1: a sensor class). Reported: gain_b
(headline), gain_c; read off the phase currents' sum where the records carry three sensors.
"""

import numpy as np
import scipy.stats

from agent.effects.base import ByIdentity, Effect, Param, smooth_current
from agent.frames import CLARKE, ab_to_dq
from agent.physical import zero_sequence_sigma


def columns(sig):
    # measured i_x = (1 + g_x) i_x: error g_x i_x along phase x's Clarke direction (A per unit gain)
    i_abc = smooth_current(sig)[1]
    return np.stack([ab_to_dq(CLARKE[:2, x:x + 1] * i_abc[x], sig.theta_e) for x in (1, 2)])


COMPUTED = 1e-6  #: the phase currents' sum below this share of their rms on every record: one phase is computed
SIGNAL = 100.0  #: a record's current read only where its Gram matrix exceeds the noise's this many times (20x in amplitude)


def _record_sum(sig):
    """One record's share of :func:`sensor_sum`: (Gram matrix less the regressors' noise, X^T y,
    residual sum of squares, its own u), None where its current is not well above the noise
    (``SIGNAL``), or a reason (str) where the record cannot be read at all."""
    m = sig.i_abc
    if m is None:
        return "no phase currents"
    z = m.sum(axis=0)
    if np.sqrt(np.mean((z - z.mean()) ** 2)) < COMPUTED * np.sqrt(np.mean(m ** 2)):
        return "one phase computed"
    x, y = (m[1:] - m[1:].mean(axis=1, keepdims=True)).T, -(m[0] - m[0].mean())
    gram, noise = x.T @ x, sig.n * zero_sequence_sigma(m) ** 2
    if np.linalg.eigvalsh(gram)[0] <= max(SIGNAL * noise, 1e-9 * np.trace(gram)):
        return None
    gram = gram - noise * np.eye(2)  # less the regressors' own noise
    u_k = np.linalg.solve(gram, x.T @ y)
    return gram, x.T @ y, float(np.sum((y - x @ u_k) ** 2)), u_k


#: per record, :func:`_record_sum` (explain reads the sum for the figures, the test and the warning)
_RECORDS = ByIdentity(16)


def sensor_sum(signals) -> tuple[np.ndarray, np.ndarray, int] | None:
    """(g_b, g_c), their standard errors and the records read, off the phase currents' sum, or None where it is
    zero sample by sample (two sensors, the third phase computed from them), not recorded, or where
    no record carries a current well above its noise (``SIGNAL``: at standstill, with the pulses off).

    A three-wire winding's currents sum to zero, so the measured ones m_x = (1 + g_a)(1 + g_x) i_x
    (g_x relative to phase a) obey -m_a = u_b m_b + u_c m_c with u_x = 1/(1 + g_x), exactly: least
    squares over the records with a constant per record (the offsets), the regressors' own noise
    (:func:`agent.physical.zero_sequence_sigma`) taken out of their Gram matrix, then
    g_x = 1/u_x - 1. Standard errors: the residual's, or the records' scatter where larger."""
    xtx, xty, rss, n, k, each = np.zeros((2, 2)), np.zeros(2), 0.0, 0, 0, []
    for sig in signals:
        one = _RECORDS.get(sig, _record_sum)
        if isinstance(one, str):  # not recorded, or one phase computed
            return None
        if one is None:
            continue  # too little current beyond the noise to read a gain from
        gram, x_y, r, u_k = one
        xtx, xty, rss, n, k = xtx + gram, xty + x_y, rss + r, n + sig.n, k + 1
        each.append(u_k)
    if k == 0:
        return None
    u = np.linalg.solve(xtx, xty)
    se_u = np.sqrt(np.diag(np.linalg.inv(xtx)) * rss / max(n - 3 * k, 1))
    if k > 1:  # the samples' residual is not white (quantisation, ripple): the records' own scatter counts too
        se_u = np.maximum(se_u, np.std(each, axis=0, ddof=1) / np.sqrt(k))
    return 1.0 / u - 1.0, se_u / u ** 2, k


def negative_sequence(g) -> complex:
    """eps (dimensionless) of relative gains (g_b, g_c): the measured dq current's eps i*."""
    a = np.exp(2j * np.pi / 3)
    return complex((g[0] * a * a + g[1] * a) / 3.0)


#: the sum's mismatch below this share of the fit's: what the fit takes is mostly not the sensors' (the
#: impedance reading put the fit at 0.15-2.5 times the sum on the family's hidden mismatches)
AGREE = 0.25


SUM_NOTE = ("read off the phase currents' sum (a three-wire winding's currents sum to zero, so the sum is the "
            "sensors' mismatch)")


def sum_p(g, se, k: int) -> float | None:
    """Two-sided p that the sensors' gains are equal, from the sum's figures ``g`` and standard errors
    ``se`` over ``k`` records: a t-test of each gain with k - 1 degrees of freedom (the records, not
    the samples, are independent: the standard error already counts their scatter), Bonferroni over
    the two. None with fewer than two records."""
    if k < 2:
        return None
    t = np.abs(np.asarray(g)) / np.maximum(np.asarray(se), 1e-300)
    return float(min(1.0, 2.0 * np.min(2.0 * scipy.stats.t.sf(t, k - 1))))


def read_sum(signals) -> dict | None:
    """The records' own reading of the figures, whatever a fit pins (:attr:`Effect.direct`):
    ``gain_b``, ``gain_c`` off the phase currents' sum (:func:`sensor_sum`), bounds 3 standard errors,
    and the test that the sensors differ (:func:`sum_p`); None where one phase is computed."""
    read = sensor_sum(signals)
    if read is None:
        return None
    (g_b, g_c), (s_b, s_c), k = read
    return {"params": {"gain_b": float(g_b), "gain_c": float(g_c)},
            "params_bound": {"gain_b": float(3.0 * s_b), "gain_c": float(3.0 * s_c)}, "note": SUM_NOTE,
            "p": sum_p((g_b, g_c), (s_b, s_c), k)}


def through_sum(values, said: dict, ctx: dict, prior: dict) -> dict | None:
    """Where the fit pins the figures: the sum's (:func:`read_sum`) instead, the fit reading the
    mismatch through the model's impedance where the controller acts on the sensors (module
    docstring). Where the sum shows less than ``AGREE`` of the fit's mismatch (beyond its noise),
    what the fit takes is another 2 f_e pattern: ``contradicted``, no figures. None where one phase
    is computed (the fit's figures stand)."""
    read = read_sum(ctx["signals"])
    if read is None:
        return None
    g, bound = list(read["params"].values()), list(read["params_bound"].values())
    eps_fit, eps_sum = negative_sequence(values), negative_sequence(g)
    se_eps = float(np.hypot(*bound)) / 3.0 / 3.0  # the bounds are 3 se of g; eps = (g_b a^2 + g_c a) / 3
    names = list(said["params"])
    if abs(eps_sum) + 3.0 * se_eps < AGREE * abs(eps_fit):
        return {"params": dict.fromkeys(names), "params_bound": dict.fromkeys(names),
                "unpinned_params": dict(zip(names, map(float, values))), "contradicted": True,
                "note": f"the phase currents' sum shows a mismatch of {abs(eps_sum):.2g} (negative sequence, "
                        f"+-{se_eps:.1g}) against the fit's {abs(eps_fit):.2g}: the sensors differ by less than a "
                        f"quarter of what the fit takes, which is another pattern at 2 f_e in dq, so it is not claimed"}
    turn = np.degrees(np.angle(eps_fit / eps_sum)) if abs(eps_fit) > 0 and abs(eps_sum) > 0 else 0.0
    return {**read, "note": f"{SUM_NOTE}; the fit reads it through the model's impedance, rotated by {turn:+.0f} "
                            f"degrees and {abs(eps_fit) / max(abs(eps_sum), 1e-12):.2f} times its size"}


EFFECT = Effect(
    id="current_gain_mismatch",
    physics="A current sensor's gain differs from phase a's by g (dimensionless): i_x,meas = (1 + g_x) i_x "
            "for x = b, c (a common gain error is indistinguishable from the motor parameters).",
    kind="output",
    params=(Param("g_b", "-", "relative gain error of phase b", 0.03, -0.1, 0.1),
            Param("g_c", "-", "relative gain error of phase c", 0.03, -0.1, 0.1)),
    columns=columns,
    report=lambda v, ctx: {"gain_b": float(v[0]), "gain_c": float(v[1])},
    signature="2 fe ripple and a DC shift in dq; a negative-sequence fe line in the phase residual; "
              "a fe line in the phase currents' sum",
    dq_orders=(0, 2), abc_orders=(1,),
    reveals="any record with current",
    read_through=through_sum,
    direct=read_sum,
    direct_test="the phase currents' sum, a t-test of each sensor's gain against phase a's over the records, "
                "Bonferroni over the two",
)
