"""StreamingRLS (agent/rls.py) against independent references written here and padasip.

Tolerances. Both the block information form and the per-sample covariance recursion are
backward stable, so they differ by ~ eps * kappa, kappa the condition number of the Jacobi-
scaled information matrix: ~1 for the random regressors, ~1e5 for the PMSM q-axis regressors
(i_q ~ 9 A, v_q ~ 176 V, omega_e = 628 rad/s constant, small ripple). Observed differences are
<= ~3e-11 (PMSM) and ~1e-14 (random); the 1e-9 relative (norm-wise) tolerance leaves > 30x
margin. P0 is chosen "scaled", P0 = c * diag(1 / mean(x_j^2)): with P0 = 1e3 I the first PMSM
sample gives x^T P0 x ~ 4e8 and the covariance update P - K x^T P cancels ~8.5 digits, so the
*reference* itself is only good to ~1e-8 and the comparison would be meaningless.
The reference is written literally as Algorithm 1, ``P - K (x^T P)``; the tempting shortcut
``P - K (P x)^T`` (assuming P symmetric) is unstable for lam < 1 (asymmetry grows as lam^-k).
"""

from __future__ import annotations

import functools
import io

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from agent.rls import StreamingRLS

LAMS = (1.0, 0.999, 0.99)
N_REF = 1500
W_REF = 2.0


# ---------------------------------------------------------------------------- data & references
def pmsm_q_axis(N, seed, noise=1e-3):
    """Regressors of eq. 14, x = [i_q(k), i_d(k), v_q(k), omega_e]; y = x theta + noise (A)."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * 1e-4  # Ts = 100 us
    i_q = 9.0 + 0.2 * np.sin(2 * np.pi * 50 * t) + 0.05 * rng.standard_normal(N)
    i_d = 0.1 * np.sin(2 * np.pi * 70 * t + 1.0) + 0.05 * rng.standard_normal(N)
    v_q = 176.0 + 2.0 * np.sin(2 * np.pi * 30 * t) + 0.5 * rng.standard_normal(N)
    X = np.column_stack([i_q, i_d, v_q, np.full(N, 628.0)])
    Rs, Ld, Lq, psi, Ts, we = 0.4, 2.6e-3, 3.2e-3, 0.12, 1e-4, 628.0
    theta = np.array([1 - Rs * Ts / Lq, -we * Ld * Ts / Lq, Ts / Lq, -psi * Ts / Lq])
    return X, X @ theta + noise * rng.standard_normal(N), theta


def random_problem(N, seed):
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((N, 4))
    theta = np.array([1.0, 2.0, -1.0, 0.5])
    return X, X @ theta + 0.1 * rng.standard_normal(N), theta


def scaled_p0(X, c=10.0):
    return np.diag(c / np.mean(X**2, axis=0))


def algorithm1(X, y, lam, W, theta0, P0):
    """Per-sample covariance-form RLS (Alg. 1 / eqs. 16-18 with forgetting); theta, P after each sample."""
    th, P = np.array(theta0, float), np.array(P0, float)
    ths, Ps = [th.copy()], [P.copy()]
    for x, yk in zip(X, y):
        K = P @ x / (lam / W + x @ P @ x)
        th = th + K * (yk - x @ th)
        P = (P - np.outer(K, x @ P)) / lam
        ths.append(th)
        Ps.append(P)
    return np.array(ths), np.array(Ps)


def stabilized_info_form(X, y, lam, W, theta0, P0):
    """Per-sample stabilised forgetting in information form; theta, P after each sample.

    Accumulated in extended precision: in float64 the per-sample rounding of ``lam * R`` alone
    limits this reference to ~2e-9 on the prior-dominated PMSM case (lam = 0.999).
    """
    L = np.longdouble
    R0 = np.linalg.inv(P0).astype(L)
    r0 = R0 @ np.asarray(theta0, L)
    R, r, lam_, W_ = R0.copy(), r0.copy(), L(lam), L(W)
    ths, Ps = [np.array(theta0, float)], [np.array(P0, float)]
    for x, yk in zip(X.astype(L), y.astype(L)):
        R = lam_ * R + (1 - lam_) * R0 + W_ * np.outer(x, x)
        r = lam_ * r + (1 - lam_) * r0 + W_ * x * yk
        Rf, rf = R.astype(float), r.astype(float)
        d = 1 / np.sqrt(np.diag(Rf))  # equilibrate: plain LU on R (entries 1e-3 .. 1e9) loses digits
        ths.append(d * np.linalg.solve(Rf * np.outer(d, d), d * rf))
        Ps.append(np.outer(d, d) * np.linalg.inv(Rf * np.outer(d, d)))
    return np.array(ths), np.array(Ps)


@functools.lru_cache(maxsize=None)
def reference(kind, lam, stabilized):
    X, y, _ = (pmsm_q_axis if kind == "pmsm" else random_problem)(N_REF, seed=7)
    theta0 = np.linspace(-0.1, 0.1, 4)
    P0 = scaled_p0(X)
    ref = (stabilized_info_form if stabilized else algorithm1)(X, y, lam, W_REF, theta0, P0)
    return X, y, theta0, P0, ref


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def run_blocks(est, X, y, cuts):
    """Feed X, y split at ``cuts``; yield (boundary index, estimator) after each block."""
    bounds = [0, *sorted(set(cuts)), len(y)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        est.update(X[a:b], y[a:b])  # empty blocks (a == b) are legal no-ops
        yield b, est


splits = st.lists(st.integers(0, N_REF), min_size=0, max_size=8)


# ---------------------------------------------------------------------------- exactness
@pytest.mark.parametrize("kind", ["random", "pmsm"])
@pytest.mark.parametrize("lam", LAMS)
@settings(max_examples=15, deadline=None)
@given(cuts=splits)
def test_blocks_equal_algorithm1_at_every_boundary(kind, lam, cuts):
    X, y, theta0, P0, (ths, Ps) = reference(kind, lam, False)
    est = StreamingRLS(4, lam=lam, weight=W_REF, theta0=theta0, p0=P0, stabilize=False)
    for k, e in run_blocks(est, X, y, cuts):
        assert rel(e.theta, ths[k]) < 1e-9, (k, e.theta, ths[k])
        assert rel(e.covariance, Ps[k]) < 1e-9
        assert e.samples_seen == k


@pytest.mark.parametrize("kind", ["random", "pmsm"])
@pytest.mark.parametrize("lam", (0.999, 0.99))
@settings(max_examples=10, deadline=None)
@given(cuts=splits)
def test_stabilized_blocks_equal_per_sample_info_form(kind, lam, cuts):
    X, y, theta0, P0, (ths, Ps) = reference(kind, lam, True)
    # where longdouble is plain double (e.g. Windows, macOS arm64) the PMSM reference is ~2e-9
    tol = 1e-9 if kind == "random" or np.finfo(np.longdouble).eps < 1e-18 else 1e-8
    est = StreamingRLS(4, lam=lam, weight=W_REF, theta0=theta0, p0=P0, stabilize=True)
    for k, e in run_blocks(est, X, y, cuts):
        assert rel(e.theta, ths[k]) < tol, (k, e.theta, ths[k])
        assert rel(e.covariance, Ps[k]) < tol


def test_stabilize_is_noop_without_forgetting():
    X, y, _ = random_problem(500, seed=3)
    a = StreamingRLS(4, lam=1.0, stabilize=True)
    b = StreamingRLS(4, lam=1.0, stabilize=False)
    a.update(X, y)
    b.update(X, y)
    np.testing.assert_array_equal(a.theta, b.theta)


@pytest.mark.parametrize("lam", (1.0, 0.999))
def test_equals_batch_weighted_least_squares_with_prior(lam):
    X, y, _ = pmsm_q_axis(3000, seed=11)
    W, theta0, P0 = 4.0, np.array([1.0, 0.0, 0.0, 0.0]), scaled_p0(X, c=1.0)
    N = len(y)
    # min  sum_i W lam^(N-1-i) (y_i - x_i theta)^2 + lam^N (theta - theta0)^T P0^-1 (theta - theta0)
    L0 = np.linalg.cholesky(np.linalg.inv(P0))  # R0 = L0 L0^T
    sw = np.sqrt(W * lam ** np.arange(N - 1, -1, -1))
    A = np.vstack([sw[:, None] * X, np.sqrt(lam**N) * L0.T])
    b = np.concatenate([sw * y, np.sqrt(lam**N) * L0.T @ theta0])
    theta_ls = np.linalg.lstsq(A, b, rcond=None)[0]
    est = StreamingRLS(4, lam=lam, weight=W, theta0=theta0, p0=P0, stabilize=False)
    for blk in np.array_split(np.arange(N), 7):
        est.update(X[blk], y[blk])
    assert rel(est.theta, theta_ls) < 1e-9
    assert rel(est.covariance, np.linalg.inv(A.T @ A)) < 1e-9


@pytest.mark.parametrize("lam", LAMS)
def test_matches_padasip_filter_rls(lam):
    pa = pytest.importorskip("padasip")
    X, y, _ = random_problem(3000, seed=5)
    theta0 = np.array([0.3, -0.2, 0.1, 0.0])
    # padasip FilterRLS: P0 = I/eps, mu = lam, W = 1; w is the initial weight vector;
    # R <- (R - R x x^T R / (mu + x^T R x)) / mu,  w <- w + R x e  (== Alg. 1 with forgetting)
    f = pa.filters.FilterRLS(n=4, mu=lam, eps=0.1, w=theta0.copy())
    f.run(y, X)
    est = StreamingRLS(4, lam=lam, weight=1.0, theta0=theta0, p0=10.0, stabilize=False)
    for blk in np.array_split(np.arange(len(y)), 5):
        est.update(X[blk], y[blk])
    assert rel(est.theta, f.w) < 1e-12
    assert rel(est.covariance, f.R) < 1e-10


# ---------------------------------------------------------------------------- no excitation
def _zeros_run(est, n_total, block=20_000):
    Z, z = np.zeros((block, est.n_params)), np.zeros(block)
    for _ in range(n_total // block):
        est.update(Z, z)
        yield est


def test_stabilized_survives_a_million_zero_regressors():
    X, y, theta_true = random_problem(2000, seed=1)
    theta0 = np.zeros(4)
    P0 = 10.0 * np.eye(4)
    est = StreamingRLS(4, lam=0.99, theta0=theta0, p0=P0, stabilize=True)
    est.update(X, y)
    assert rel(est.theta, theta_true) < 0.05
    for e in _zeros_run(est, 1_000_000):
        th, P = e.theta, e.covariance
        assert np.isfinite(th).all() and np.isfinite(P).all()
        assert np.trace(P) <= np.trace(P0) * (1 + 1e-12)
        assert np.all(np.linalg.eigvalsh(P0 - P) >= -1e-12 * np.trace(P0))  # P <= P0
    np.testing.assert_allclose(est.theta, theta0, atol=1e-12)  # relaxed to the prior
    np.testing.assert_allclose(est.covariance, P0, rtol=1e-12)
    est.update(X[:300], y[:300])  # excitation returns: estimate recovers
    assert rel(est.theta, theta_true) < 0.05


def test_plain_forgetting_zero_regressors_no_nan_theta_kept():
    X, y, theta_true = random_problem(2000, seed=2)
    est = StreamingRLS(4, lam=0.99, p0=10.0, stabilize=False)
    est.update(X, y)
    theta_before, P_before = est.theta, est.covariance
    est.update(np.zeros((10_000, 4)), np.zeros(10_000))  # P grows as lam^-k (here ~4e43)
    np.testing.assert_allclose(est.theta, theta_before, rtol=1e-13)
    np.testing.assert_allclose(est.covariance, P_before * 0.99**-10_000, rtol=1e-9)
    for e in _zeros_run(est, 1_000_000):
        assert not np.isnan(e.theta).any() and not np.isnan(e.covariance).any()
    np.testing.assert_allclose(est.theta, theta_before, rtol=1e-13)
    assert np.isposinf(np.diag(est.covariance)).all()  # saturated, documented
    est.update(X[:300], y[:300])  # old information is gone; new data rule
    assert rel(est.theta, theta_true) < 0.05 and np.isfinite(est.covariance).all()


@pytest.mark.parametrize("stabilize", (True, False))
def test_long_excited_run_keeps_p_bounded(stabilize):
    rng = np.random.default_rng(9)
    theta = np.array([1.0, 2.0, -1.0, 0.5])
    est = StreamingRLS(4, lam=0.99, p0=10.0, stabilize=stabilize)
    traces = []
    for _ in range(100):  # 10^6 samples
        X = rng.standard_normal((10_000, 4))
        est.update(X, X @ theta + 0.1 * rng.standard_normal(10_000))
        traces.append(np.trace(est.covariance))
    # steady state P ~ (1 - lam) / W * inv(E[x x^T]) -> trace ~ 0.04
    assert np.isfinite(traces).all() and max(traces[1:]) < 0.1 and min(traces) > 0.01
    assert rel(est.theta, theta) < 0.05


# ---------------------------------------------------------------------------- estimation, API
def test_recovers_pmsm_parameters_with_calibrated_covariance():
    sigma = 5e-3  # A, current-measurement noise
    X, y, theta_true = pmsm_q_axis(40_000, seed=21, noise=sigma)
    est = StreamingRLS(4, lam=1.0, weight=1 / sigma**2, theta0=np.zeros(4), p0=scaled_p0(X, 1e3))
    for blk in np.array_split(np.arange(len(y)), 16):
        est.update(X[blk], y[blk])
    std = np.sqrt(np.diag(est.covariance))  # W = 1/sigma^2 -> P is the estimate covariance
    assert np.all(np.abs(est.theta - theta_true) < 5 * std)
    assert abs(est.theta[2] / theta_true[2] - 1) < 0.01  # Ts/Lq, the clustering parameter
    resid = y - est.predict(X)
    assert abs(resid.std() / sigma - 1) < 0.05


def test_reset_equals_fresh_instance():
    X, y, _ = random_problem(1000, seed=4)
    kw = dict(lam=0.995, weight=3.0, theta0=[0.1, 0.2, 0.3, 0.4], p0=[1.0, 2.0, 3.0, 4.0])
    used, fresh = StreamingRLS(4, **kw), StreamingRLS(4, **kw)
    used.update(X[:600], y[:600])
    used.theta
    used.reset()
    for a, b in zip(used.state().values(), fresh.state().values()):
        np.testing.assert_array_equal(a, b)
    used.update(X, y)
    fresh.update(X, y)
    np.testing.assert_array_equal(used.theta, fresh.theta)
    np.testing.assert_array_equal(used.covariance, fresh.covariance)


@pytest.mark.parametrize("stabilize", (True, False))
def test_state_round_trip_through_npz(stabilize):
    X, y, _ = random_problem(1000, seed=6)
    est = StreamingRLS(4, lam=0.99, weight=2.0, p0=5.0, stabilize=stabilize)
    est.update(X[:500], y[:500])
    est.update(np.zeros((3000, 4)), np.zeros(3000))  # non-trivial scale exponent
    buf = io.BytesIO()
    np.savez(buf, **est.state())
    buf.seek(0)
    back = StreamingRLS.from_state(np.load(buf))
    assert back.samples_seen == est.samples_seen and back.n_params == 4
    np.testing.assert_array_equal(back.theta, est.theta)
    np.testing.assert_array_equal(back.covariance, est.covariance)
    est.update(X[500:], y[500:])
    back.update(X[500:], y[500:])
    np.testing.assert_array_equal(back.theta, est.theta)


def test_api_edges():
    est = StreamingRLS(3, theta0=[1.0, 2.0, 3.0])
    np.testing.assert_allclose(est.theta, [1.0, 2.0, 3.0], rtol=1e-15)
    np.testing.assert_allclose(est.covariance, 1e3 * np.eye(3))
    est.update(np.empty((0, 3)), np.empty(0))
    assert est.samples_seen == 0
    est.update([1.0, 0.0, 0.0], [5.0])  # a single sample as (n,) regressor
    assert est.samples_seen == 1 and est.theta[0] > 4.99
    assert est.predict([[1.0, 0.0, 0.0]]).shape == (1,)
    before = est.state()
    with pytest.raises(ValueError):
        est.update(np.array([[np.nan, 0.0, 0.0]]), [1.0])
    with pytest.raises(ValueError):
        est.update(np.ones((2, 2)), np.ones(2))
    for a, b in zip(before.values(), est.state().values()):
        np.testing.assert_array_equal(a, b)  # rejected blocks leave the state unchanged
    for bad in (dict(lam=0.0), dict(lam=1.01), dict(weight=0.0), dict(p0=-1.0), dict(p0=np.inf), dict(theta0=[1.0])):
        with pytest.raises(ValueError):
            StreamingRLS(3, **bad)


def test_underdetermined_falls_back_to_closest_to_prior():
    est = StreamingRLS(2, theta0=[1.0, 1.0], p0=1e300)  # essentially no prior information
    est.update([[1.0, 1.0], [2.0, 2.0]], [4.0, 8.0])  # only theta_0 + theta_1 = 4 is observed
    np.testing.assert_allclose(est.theta, [2.0, 2.0], rtol=1e-9)
    assert np.isposinf(est.covariance).all()  # not identifiable: unbounded, not a made-up number


def test_plain_forgetting_resume_underdetermined_after_information_loss():
    X, y, theta_true = random_problem(100, seed=8)
    theta0 = np.array([0.5, 0.5, 0.5, 0.5])
    est = StreamingRLS(4, lam=0.99, theta0=theta0, p0=1.0, stabilize=False)
    est.update(X, y)
    est.update(np.zeros((1_000_000, 4)), np.zeros(1_000_000))  # one huge block: lam^N underflows
    est.update(X[:2], y[:2])  # 2 samples, 4 unknowns; old information is below float range
    th = est.theta
    assert np.isfinite(th).all()
    np.testing.assert_allclose(X[:2] @ th, y[:2], rtol=1e-9)  # fits the new data ...
    w = np.array([0.99, 1.0])  # forgetting weights of the two samples
    d = np.sqrt(np.diag((X[:2].T * w) @ X[:2]))  # ... and the closest such point to theta0
    null = np.linalg.svd(X[:2] * (1 / d))[2][2:]  # (scaled) null-space directions
    np.testing.assert_allclose(null @ (d * (th - theta0)), 0.0, atol=1e-9)
