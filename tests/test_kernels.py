"""agent.kernels (the C kernels through ctypes) against literal Python transcriptions written here.

The pipeline's per-block pass (block_rows) and the hop sums it adds up are compared with the numpy
expressions they replace (np.unwrap, the Clarke matrix and numpy's Park rotation, einsum, sums and
dot products over float64 copies), to float32 rounding where the rows are float32.

The free-run simulation's reference repeats the C recursion operation by operation in Python
floats, so that comparison is exact. The PLL's reference is the loop as it was first written,
libm's cos, sin, hypot and atan2 every sample; the C loop rotates a phasor and takes the phase
error by series near lock (each within an ulp or two of libm), so the two agree to 1e-12 rad over
long streams, not bit for bit. The agent's behaviour itself is tested through agent.pll and
agent.model (tests/test_pll.py, tests/test_model.py).
"""

from __future__ import annotations

import importlib.machinery
import math
import subprocess
import sys

import numpy as np
import pytest

from agent import kernels
from agent.frames import CLARKE, park
from agent.kernels import block_rows, ltv_residuals, new_sums, pll_run, simulate_ltv
from agent.pipeline import HopSums, hop_sums
from agent.pll import PLL

FS = 25_000.0


def pll_reference(x_abc, clarke, par, zi):
    ts, wn_trk, wn_acq, taper, a_ef, thr, thr_off, n_lock, amin, zeta = (float(v) for v in par)
    th, om, ef, cnt, lck, wn = (float(v) for v in zi)
    theta, omega = [], []
    for xa, xb, xc in zip(*(map(float, row) for row in x_abc)):
        al = clarke[0, 0] * xa + clarke[0, 1] * xb + clarke[0, 2] * xc
        be = clarke[1, 0] * xa + clarke[1, 1] * xb + clarke[1, 2] * xc
        c, s = math.cos(th), math.sin(th)
        d, q = al * c + be * s, -al * s + be * c
        e = 0.0
        if math.isfinite(d) and math.isfinite(q) and math.hypot(d, q) > amin:
            e = math.atan2(-d, q)
            ef += a_ef * (e - ef)
            if lck == 0.0:
                cnt = cnt + 1.0 if abs(ef) < thr else 0.0
                lck = 1.0 if cnt >= n_lock else 0.0
            elif abs(ef) > thr_off:
                lck, cnt, wn = 0.0, 0.0, wn_acq
        if lck != 0.0 and wn > wn_trk:
            wn = max(wn * taper, wn_trk)
        om += wn * wn * ts * e
        theta.append(th)
        omega.append(om)
        th += ts * (om + 2.0 * zeta * wn * e)
        th -= 2.0 * math.pi * math.floor((th + math.pi) / (2.0 * math.pi))
    return np.array(theta), np.array(omega), np.array([th, om, ef, cnt, lck, wn])


def ltv_reference(a0, a1, omega, u, x0):
    x = np.empty((2, omega.size))
    x[:, 0] = x0
    for k in range(omega.size - 1):
        a = [[a0[i, j] + omega[k] * a1[i, j] for j in range(2)] for i in range(2)]
        x[0, k + 1] = a[0][0] * x[0, k] + a[0][1] * x[1, k] + u[0, k]
        x[1, k + 1] = a[1][0] * x[0, k] + a[1][1] * x[1, k] + u[1, k]
    return x


def three_phase(n, f_hz, amp, seed):
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0.0, 2.0 * np.pi) + 2.0 * np.pi * f_hz * np.arange(n) / FS
    x = amp * np.cos(phi + np.array([0.0, -2.0 * np.pi / 3.0, 2.0 * np.pi / 3.0])[:, None])
    return x + 0.05 * amp * rng.standard_normal(x.shape)


def assert_pll_matches(got, want, tol_rad=1e-12):
    """The C loop's (theta, omega, state, cos_sin) against the libm loop's (theta, omega, state)."""
    theta, omega, zf, cs = got
    dtheta = np.angle(np.exp(1j * (theta - want[0])))  # the angle wraps at +-pi
    assert np.abs(dtheta).max() < tol_rad
    np.testing.assert_allclose(omega, want[1], rtol=0, atol=tol_rad * FS)  # rad/s: an angle error a sample
    np.testing.assert_array_equal(zf[3:5], want[2][3:5])  # the lock detector took the same decisions
    np.testing.assert_allclose(zf[[1, 2, 5]], want[2][[1, 2, 5]], rtol=1e-9, atol=1e-12)
    mid = theta + 0.5 * omega / FS
    for row, exact in zip(cs, (np.cos(theta), np.sin(theta), np.cos(mid), np.sin(mid))):
        np.testing.assert_allclose(row, exact, rtol=0, atol=1e-13)


def test_the_pll_series_are_libm_to_an_ulp_in_every_range():
    """Each series the loop takes instead of libm (cos and sin of a turn, atan of the phase error),
    on points spread over every range it is taken in, within 3 ulps of numpy's libm values (the
    phase error's division rounds too): a wrong coefficient in a short range moves the loop's output by far less than the
    stream tests' 1e-12 rad, so it is held here."""
    rng = np.random.default_rng(11)
    x = np.concatenate([np.geomspace(1e-9, 0.4, 4000), -rng.uniform(0, 0.4, 1000), [0.0]])
    t = np.concatenate([np.geomspace(1e-9, 0.125, 4000), -rng.uniform(0, 0.125, 1000), [0.0]])
    q = rng.uniform(0.5, 20.0, t.size)
    cos_x, sin_x, error, took = kernels.pll_series(x, -t * q, q)
    ulp = lambda v: np.spacing(np.abs(v))  # noqa: E731
    assert np.all(np.abs(cos_x - np.cos(x)) <= 2 * ulp(np.cos(x)))
    assert np.all(np.abs(sin_x - np.sin(x)) <= 2 * ulp(np.sin(x)) + 1e-300)
    want = np.arctan2(t * q, q)
    assert took.all()
    assert np.all(np.abs(error - want) <= 3 * ulp(want) + 1e-300)


@pytest.mark.parametrize("seed", range(4))
def test_pll_matches_the_libm_loop_through_lock_gaps_and_nan(seed):
    x = three_phase(3000, 95.0 + 5.0 * seed, amp=10.0 ** (seed - 1), seed=seed)
    x[:, 1200:1400] = 0.0  # no phase: the angle free-runs
    x[seed % 3, 1700:1710] = np.nan
    pll = PLL(FS, 100.0, lock_time_s=0.002, shift_time_s=0.005, min_amplitude=0.01 * seed)
    pll._state[0] = seed - 1.5  # start away from the input's phase
    got = pll_run(x, pll._clarke, pll._par, pll._state, cos_sin=True)
    assert_pll_matches(got, pll_reference(x, pll._clarke, pll._par, pll._state[:6]))
    assert got[2][4] == 1.0  # the run went through lock


def test_pll_matches_the_libm_loop_over_a_long_stream():
    """10 s (250 000 samples) of a speed-modulated input in 0.1 s blocks, through an acquisition
    from the wrong phase and speed, a phase jump (re-acquisition at atan2's full range) and a
    speed ramp: the phasor never drifts from the angle (it is exact every 64 samples) and the
    loop stays within 1e-12 rad of the per-sample libm loop."""
    n = int(10 * FS)
    t = np.arange(n) / FS
    f = 100.0 + 20.0 * np.clip(t - 6.0, 0.0, 2.0)  # 10 Hz/s for 2 s
    phi = 2 * np.pi * np.cumsum(f) / FS + 0.05 * np.sin(2 * np.pi * 9.5 * t) + np.where(t > 3.0, 2.0, 0.0)
    x = 5.0 * np.cos(phi + np.array([0.0, -2.0 * np.pi / 3.0, 2.0 * np.pi / 3.0])[:, None])
    x += 0.1 * np.random.default_rng(11).standard_normal(x.shape)
    pll = PLL(FS, 90.0, theta0=2.5)
    zi = pll._state.copy()
    parts = [pll.process(x[:, k:k + 2500], cos_sin=True) for k in range(0, n, 2500)]
    got = tuple(np.concatenate(p, axis=-1) for p in zip(*parts))
    assert_pll_matches((got[0], got[1], pll._state, got[2]), pll_reference(x, pll._clarke, pll._par, zi[:6]))


def test_pll_state_in_and_out():
    x = three_phase(2000, 100.0, 1.0, seed=7)
    pll = PLL(FS, 100.0)
    zi = pll._state.copy()
    theta, omega, zf = pll_run(x, pll._clarke, pll._par, zi)
    np.testing.assert_array_equal(zi, pll._state)  # the input state is not modified
    t1, o1, z1 = pll_run(x[:, :777], pll._clarke, pll._par, zi)
    t2, o2, z2 = pll_run(x[:, 777:], pll._clarke, pll._par, z1)
    np.testing.assert_array_equal(np.concatenate((t1, t2)), theta)
    np.testing.assert_array_equal(np.concatenate((o1, o2)), omega)
    np.testing.assert_array_equal(z2, zf)
    t0, o0, z0 = pll_run(np.empty((3, 0)), pll._clarke, pll._par, zi)
    assert t0.shape == o0.shape == (0,)
    np.testing.assert_array_equal(z0, zi)


def test_simulate_ltv_equals_reference_and_takes_views():
    rng = np.random.default_rng(3)
    n = 2000
    a0, a1 = 0.5 * rng.standard_normal((2, 2)), 1e-4 * rng.standard_normal((2, 2))
    omega, u = rng.uniform(0.0, 700.0, n), rng.standard_normal((2, n))
    x0 = rng.standard_normal((2, 5))[:, 2]  # a strided view, as sig.i_dq[:, 0]
    np.testing.assert_array_equal(simulate_ltv(a0, a1, omega, u, x0), ltv_reference(a0, a1, omega, u, x0))
    np.testing.assert_array_equal(simulate_ltv(a0, a1, omega[:1], u[:, :1], x0), x0[:, None])
    assert simulate_ltv(a0, a1, omega[:0], u[:, :0], x0).shape == (2, 0)


def rows_reference(i_abc, v_abc, theta, omega, cs, theta_last):
    """The pipeline's rows in numpy as they were computed before the C pass, float64; the angle
    unwrapped by np.unwrap from theta_last."""
    with np.errstate(invalid="ignore"):  # inf * 0 in the matrix product: NaN, as in C
        rows = np.vstack((v_abc, i_abc, omega, park(CLARKE[:2] @ i_abc, cs[0], cs[1]),
                          park(CLARKE[:2] @ v_abc, cs[2], cs[3])))
    return rows, np.unwrap(np.concatenate(([theta_last], theta)))[1:]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_block_rows_at_a_given_angle_equals_numpy(dtype):
    rng = np.random.default_rng(5)
    n = 3000
    i_abc, v_abc = three_phase(n, 97.0, 20.0, seed=1), three_phase(n, 97.0, 300.0, seed=2)
    omega = 2 * np.pi * 97.0 + rng.standard_normal(n)
    theta = np.angle(np.exp(1j * (np.cumsum(omega) / FS + 0.3)))  # wrapped to (-pi, pi]
    mid = theta + 0.5 * omega / FS
    cs = np.vstack((np.cos(theta), np.sin(theta), np.cos(mid), np.sin(mid)))
    want, unwrapped = rows_reference(i_abc, v_abc, theta, omega, cs, 1000.0)
    rows = np.full((11, n), np.nan, dtype=dtype)
    got, bad, zf = block_rows(i_abc, v_abc, CLARKE[:2], [np.inf, np.inf], 1000.0, rows,
                              angle=np.vstack((theta, omega, cs)))
    assert not bad and zf is None
    np.testing.assert_allclose(got, unwrapped, rtol=0, atol=1e-9)
    assert abs(got[0] - 1000.0) < np.pi and np.abs(np.diff(got)).max() < 0.1  # continuous
    if dtype == np.float64:
        np.testing.assert_allclose(rows, want, rtol=1e-12, atol=1e-9)
    else:  # the same value rounded to float32: at most an ulp apart (a last-bit tie in float64)
        np.testing.assert_array_max_ulp(rows, want.astype(np.float32), maxulp=1)


def test_block_rows_flags_nan_and_saturated_samples():
    n = 500
    i_abc, v_abc = three_phase(n, 100.0, 10.0, seed=3), three_phase(n, 100.0, 200.0, seed=4)
    angle = np.vstack((np.zeros(n), np.zeros(n), np.ones(n), np.zeros(n), np.ones(n), np.zeros(n)))
    lim = [np.abs(i_abc).max() * 1.001, np.abs(v_abc).max() * 1.001]
    run = lambda i, v, limits=lim: block_rows(i, v, CLARKE[:2], limits, 0.0, np.empty((11, n)), angle=angle)[1]  # noqa: E731
    assert not run(i_abc, v_abc)
    assert run(i_abc, v_abc, [lim[0], np.abs(v_abc).max()])  # at the limit: saturated
    assert run(i_abc, v_abc, [np.abs(i_abc).max(), lim[1]])
    for row, which in ((2, "i"), (0, "v")):
        x = (i_abc if which == "i" else v_abc).copy()
        x[row, 321] = np.nan
        assert run(x, v_abc) if which == "i" else run(i_abc, x)


@pytest.mark.parametrize("with_nan", [False, True])
def test_block_rows_through_the_pll_equals_pll_run_then_numpy(with_nan):
    """The PLL inside the pass: the same loop as pll_run (its state, and the rows at pll_run's
    angle), on the input as nan_to_num makes it; the rows keep the NaN."""
    n = 5000
    i_abc, v_abc = three_phase(n, 103.0, 15.0, seed=6), three_phase(n, 103.0, 250.0, seed=8)
    if with_nan:
        i_abc[1, 2000:2003] = np.nan
        i_abc[0, 2500] = np.inf
    pll = PLL(FS, 100.0)
    pll.reset(i_abc[:, :1000])
    theta, omega, zf, cs = pll_run(np.nan_to_num(i_abc), pll._clarke, pll._par, pll._state, cos_sin=True)
    want, unwrapped = rows_reference(i_abc, v_abc, theta, omega, cs, -5.0)
    rows = np.empty((11, n))
    got, bad, zf_got = block_rows(i_abc, v_abc, CLARKE[:2], [1e9, 1e9], -5.0, rows, pll=(pll._par, pll._state))
    assert bad == with_nan
    np.testing.assert_array_equal(zf_got, zf)
    np.testing.assert_allclose(got, unwrapped, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rows, want, rtol=1e-12, atol=1e-9)  # NaN where numpy has NaN
    pll2 = PLL(FS, 100.0)
    pll2._state = pll._state.copy()
    ring = np.full((11, n + 7), -1.0)  # written in place, block by block, into a wider array's columns
    for k in range(0, n, 1234):  # in blocks (views of the record): the same stream
        part, _ = pll2.process_rows(i_abc[:, k:k + 1234], v_abc[:, k:k + 1234], [1e9, 1e9],
                                    got[k - 1] if k else -5.0, ring[:, k:min(k + 1234, n)])
        np.testing.assert_allclose(part, got[k:k + 1234], rtol=1e-15, atol=0)  # turns added per block
    np.testing.assert_array_equal(pll2._state, zf)
    np.testing.assert_array_equal(ring[:, :n], rows)
    assert np.all(ring[:, n:] == -1.0)


def sums_reference(rows, theta):
    """A hop's sums in numpy over float64 rows (as pipeline.HopSums holds them, the angle's moments
    about its mean); the input power from the phases."""
    i, w = rows[7:9], rows[6]
    p = np.einsum("ij,ij->j", rows[0:3], rows[3:6])
    mean = float(np.mean(theta))
    dth = theta - mean
    return np.array([p.sum(), w.sum(), i[1].sum(), i[0] @ i[1], np.einsum("ij,ij->", i, i), *i.min(axis=1),
                     *i.max(axis=1), mean, dth @ dth, dth @ w, dth @ p, w @ w, w @ p])


def flat(h: HopSums) -> np.ndarray:
    return np.array([h.power, h.omega, h.i_q, h.i_dq, h.i_sq, *h.i_min, *h.i_max, h.theta_mean, h.theta_sq,
                     h.theta_omega, h.theta_power, h.omega_sq, h.omega_power])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_block_rows_hop_sums_equal_numpy_however_the_stream_is_cut(dtype):
    """The hop's sums block_rows adds up as it writes the rows (from the samples as they came, not
    as stored): numpy's over the same samples, and the same however the stream is cut."""
    rng = np.random.default_rng(9)
    n = 3000
    i_abc, v_abc = three_phase(n, 97.0, 20.0, seed=1), three_phase(n, 97.0, 300.0, seed=2)
    omega = 2 * np.pi * 97.0 + rng.standard_normal(n)
    theta = np.angle(np.exp(1j * (np.cumsum(omega) / FS + 0.3)))
    mid = theta + 0.5 * omega / FS
    angle = np.vstack((theta, omega, np.cos(theta), np.sin(theta), np.cos(mid), np.sin(mid)))
    want_rows, unwrapped = rows_reference(i_abc, v_abc, theta, omega, angle[2:], 3e5)
    sums = new_sums(3e5 - 1.0)
    block_rows(i_abc, v_abc, CLARKE[:2], [np.inf, np.inf], 3e5, np.empty((11, n), dtype), angle=angle, sums=sums)
    got, want = flat(hop_sums(sums, n)), sums_reference(want_rows, unwrapped)
    np.testing.assert_allclose(got[:11], want[:11], rtol=1e-11, atol=1e-9)
    np.testing.assert_allclose(got[13:], want[13:], rtol=1e-11)
    # the angle's moments with speed and power, small sums of large terms: to 1e-12 of their scale
    p = np.einsum("ij,ij->j", want_rows[0:3], want_rows[3:6])
    for j, x in ((11, want_rows[6]), (12, p)):
        assert abs(got[j] - want[j]) <= 1e-12 * math.sqrt(want[10] * (x @ x)), j
    cut = new_sums(3e5 - 1.0)
    last = 3e5
    for k in range(0, n, 777):
        got, _, _ = block_rows(i_abc[:, k:k + 777], v_abc[:, k:k + 777], CLARKE[:2], [np.inf, np.inf], last,
                               np.empty((11, min(777, n - k)), dtype), angle=angle[:, k:k + 777], sums=cut)
        last = got[-1]
    np.testing.assert_array_equal(cut[:10], sums[:10])  # the same bits, but for the angle's sums
    np.testing.assert_allclose(cut[10:], sums[10:], rtol=1e-11)  # (each block unwraps its own turns)
    i_abc[1, 321] = np.nan  # a NaN phase: i_d and i_q NaN there, so their minima, maxima and sums
    nan = new_sums(3e5)
    block_rows(i_abc, v_abc, CLARKE[:2], [np.inf, np.inf], 3e5, np.empty((11, n), dtype), angle=angle, sums=nan)
    got = flat(hop_sums(nan, n))
    assert np.isnan(got[[0, 2, 3, 4, 5, 6, 7, 8]]).all() and np.isfinite(got[[1, 9, 13]]).all()
    with pytest.raises(ValueError, match="sums"):
        block_rows(i_abc, v_abc, CLARKE[:2], [np.inf, np.inf], 3e5, np.empty((11, n)), angle=angle, sums=np.zeros(16))


def test_ltv_residuals_equal_simulate_ltv_and_numpy_across_cuts():
    """Three runs from their own states over one stream: the same free run as simulate_ltv (bit
    for bit), the residual rotated at libm's cos and sin of the angle, and cut into blocks (the
    states carried) the same again."""
    rng = np.random.default_rng(12)
    n = 5000
    a0 = np.array([[0.98, 0.02], [-0.02, 0.98]]) + 1e-3 * rng.standard_normal((2, 2))
    a1 = 1e-5 * rng.standard_normal((2, 2))
    omega, u, i_dq = rng.uniform(500.0, 700.0, n), rng.standard_normal((2, n)), rng.standard_normal((2, n))
    theta = 7e5 + np.cumsum(omega) / FS
    theta[3000:] += 1.0  # a jump beyond the phasor's small angle: exact again there
    x0 = rng.standard_normal((2, 3))
    r, x = ltv_residuals(a0, a1, omega, u, i_dq, theta, x0)
    for j in range(3):
        sim = simulate_ltv(a0, a1, np.append(omega, 0.0), np.append(u, np.zeros((2, 1)), axis=1), x0[:, j])
        np.testing.assert_array_equal(x[:, j], sim[:, -1])  # the state after the last sample
        want = (i_dq[0] - sim[0, :-1]) * np.cos(theta) - (i_dq[1] - sim[1, :-1]) * np.sin(theta)
        np.testing.assert_allclose(r[j], want, rtol=0, atol=1e-12 * np.abs(want).max())
    r1, x1 = ltv_residuals(a0, a1, omega[:1234], u[:, :1234], i_dq[:, :1234], theta[:1234], x0)
    r2, x2 = ltv_residuals(a0, a1, omega[1234:], u[:, 1234:], i_dq[:, 1234:], theta[1234:], x1)
    np.testing.assert_array_equal(x2, x)
    np.testing.assert_allclose(np.hstack((r1, r2)), r, rtol=0, atol=1e-12 * np.abs(r).max())
    with pytest.raises(ValueError, match="at most"):
        ltv_residuals(a0, a1, omega, u, i_dq, theta, np.zeros((2, kernels.LTV_RUNS + 1)))


@pytest.mark.parametrize("bad", ["x_abc", "u", "par"])
def test_wrong_shapes_raise(bad):
    pll = PLL(FS, 100.0)
    with pytest.raises(ValueError, match=bad):
        if bad == "x_abc":
            pll_run(np.zeros((2, 10)), pll._clarke, pll._par, pll._state)
        elif bad == "par":
            pll_run(np.zeros((3, 10)), pll._clarke, pll._par[:9], pll._state)
        else:
            simulate_ltv(np.eye(2), np.zeros((2, 2)), np.zeros(10), np.zeros((2, 9)), np.zeros(2))


def test_missing_library_says_how_to_build(monkeypatch):
    monkeypatch.setattr(importlib.machinery, "EXTENSION_SUFFIXES", [".not-built.so"])
    with pytest.raises(ImportError, match="make setup"):
        kernels._load()


def test_the_agent_pipeline_does_not_import_numba():
    code = ("import sys, numpy as np, agent.pipeline; from agent.model import DQModel, Signals; "
            "from agent.pll import track; w = np.full(100, 600.0); "
            "track(np.cos(np.arange(100) / 40 + np.array([[0], [-2.1], [2.1]])), 25e3, 100.0); "
            "sig = Signals(np.ones((2, 100)), np.ones((2, 100)), w, w, 4e-5); "
            "DQModel('speed', 4e-5, np.ones(3), np.ones(4)).simulate(sig); "
            "print(sorted(m for m in ('numba', 'llvmlite') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
