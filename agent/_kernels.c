/* Per-sample recursions of the agent's runtime path (loaded by agent/kernels.py through ctypes).
 *
 * Plain C on float64 arrays, no Python API: the agent runs them without importing numba/LLVM
 * (about 120 MB of resident memory). Every array is C-contiguous; the Python wrappers in
 * agent/kernels.py check the shapes. It is built with -ffp-contract=off so that no multiply-add
 * is fused on targets with FMA: the results are the same on every target. The free-run simulation
 * follows its Python reference operation by operation (same order, no reassociation) and matches
 * it bit for bit; the PLL replaces libm's per-sample cos, sin, hypot and atan2 by a rotating phasor
 * and series, within 1e-12 rad of the libm loop (tests/test_kernels.py).
 */

#include <math.h>
#include <stddef.h>

#define PI 3.14159265358979323846 /* the double nearest pi, as math.pi */

/* The interface's version (agent/kernels.py refuses a library built from another one). 2: the
 * PLL's state of 9 and its cos/sin output. */
int kernels_abi(void) { return 2; }

/* cos and sin of a small angle x (|x| <= SMALL_ANGLE) by their Taylor series, short where |x| <=
 * 1/16 (to x^8 / x^9) and to x^14 / x^13 above: the first term left out is below 1e-19 there,
 * far under an ulp of the result. Estrin's scheme (pairs of terms, powers of x^2 in parallel):
 * the loop's latency runs through here every sample. */
#define SMALL_ANGLE 0.4
static inline void small_cos_sin(double x, double *c, double *s)
{
    const double x2 = x * x, x4 = x2 * x2, x8 = x4 * x4;
    if (fabs(x) <= 0.0625) {
        *c = (1.0 - x2 * (1.0 / 2)) + x4 * ((1.0 / 24 - x2 * (1.0 / 720)) + x4 * (1.0 / 40320));
        *s = x * ((1.0 - x2 * (1.0 / 6)) + x4 * ((1.0 / 120 - x2 * (1.0 / 5040)) + x4 * (1.0 / 362880)));
        return;
    }
    *c = ((1.0 - x2 * (1.0 / 2)) + x4 * (1.0 / 24 - x2 * (1.0 / 720)))
         + x8 * ((1.0 / 40320 - x2 * (1.0 / 3628800)) + x4 * (1.0 / 479001600 - x2 * (1.0 / 87178291200.0)));
    *s = x * (((1.0 - x2 * (1.0 / 6)) + x4 * (1.0 / 120 - x2 * (1.0 / 5040)))
              + x8 * ((1.0 / 362880 - x2 * (1.0 / 39916800)) + x4 * (1.0 / 6227020800.0)));
}

/* The phase error atan2(-d, q). Near lock (q > 0, |d| <= q / 8, |e| < 0.125) by the odd series of
 * atan(t), t = -d / q: to t^9 where |t| <= 1/64, to t^15 above; the first term left out is under
 * an ulp of e (Estrin's scheme, as above). Else libm's atan2. */
static inline double phase_error(double d, double q)
{
    if (q > 0.0 && fabs(d) <= 0.125 * q) {
        const double t = -d / q, t2 = t * t, t4 = t2 * t2, t8 = t4 * t4;
        if (fabs(t) <= 0.015625)
            return t * ((1.0 - t2 * (1.0 / 3)) + t4 * ((1.0 / 5 - t2 * (1.0 / 7)) + t4 * (1.0 / 9)));
        return t * (((1.0 - t2 * (1.0 / 3)) + t4 * (1.0 / 5 - t2 * (1.0 / 7)))
                    + t8 * ((1.0 / 9 - t2 * (1.0 / 11)) + t4 * (1.0 / 13 - t2 * (1.0 / 15))));
    }
    return atan2(-d, q);
}

/* The phasor (cos, sin) of the angle is exact (libm) every RESYNC samples and rotated by the
 * angle's step in between; the rotation's rounding (a few ulps a step) never accumulates over
 * more than RESYNC steps. */
#define RESYNC 64

/* SRF-PLL with gear shifting (agent/pll.py) over n samples of x_abc (3, n).
 *
 * clarke (2, 3): the first two rows of the amplitude-invariant Clarke matrix.
 * par (10,): Ts, wn_track, wn_acq, taper per sample, lock-filter coefficient, lock threshold,
 *            unlock threshold, lock samples, min amplitude, damping zeta.
 * state (9,), read and updated in place: angle, integrator omega, filtered error,
 *            samples below threshold, locked 0/1, natural frequency wn, the angle's phasor
 *            (cos, sin) and the steps it has been rotated since it was exact (0: take it from the
 *            angle; a new state has 0), so that a stream cut into blocks gives the same output.
 * theta, omega (n,), written: the angle used for sample k and the integrator after it.
 * cs (4, n), written: cos and sin of theta(k) and of theta(k) + Ts omega(k) / 2 (the mid angle of
 *            the sample's interval, at which a zero-order-held voltage is rotated).
 *
 * Per sample the loop needs the angle's cos and sin and the phase error; instead of libm's cos,
 * sin, hypot and atan2 (about 100 ns a sample) it rotates a phasor by the angle's step (a small
 * angle: its cos and sin by series), compares the squared amplitude and takes the error by the
 * atan series near lock. Every one of these equals the libm expression to an ulp or two; the
 * output stays within 1e-12 rad of the per-sample libm loop (tests/test_kernels.py).
 */
void pll_run(const double *x_abc, ptrdiff_t n, const double *clarke, const double *par,
             double *state, double *theta, double *omega, double *cs)
{
    const double ts = par[0], wn_trk = par[1], wn_acq = par[2], taper = par[3], a_ef = par[4];
    const double thr = par[5], thr_off = par[6], n_lock = par[7], amin = par[8], zeta = par[9];
    double th = state[0], om = state[1], ef = state[2], cnt = state[3], lck = state[4], wn = state[5];
    /* locals, so the stores to theta/omega (which might alias) force no reloads */
    const double c_aa = clarke[0], c_ab = clarke[1], c_ac = clarke[2];
    const double c_ba = clarke[3], c_bb = clarke[4], c_bc = clarke[5];
    const double two_pi = 2.0 * PI;
    const double amin2 = amin > 0.0 ? amin * amin : 0.0;
    const double *xa = x_abc, *xb = x_abc + n, *xc = x_abc + 2 * n;
    double *cos_th = cs, *sin_th = cs + n, *cos_v = cs + 2 * n, *sin_v = cs + 3 * n;
    double steps = state[8], c = state[6], s = state[7];
    if (steps == 0.0) {
        c = cos(th);
        s = sin(th);
    }

    for (ptrdiff_t k = 0; k < n; ++k) {
        const double al = c_aa * xa[k] + c_ab * xb[k] + c_ac * xc[k];
        const double be = c_ba * xa[k] + c_bb * xb[k] + c_bc * xc[k];
        const double d = al * c + be * s;
        const double q = -al * s + be * c;
        double e = 0.0;
        if (isfinite(d) && isfinite(q) && d * d + q * q > amin2) {
            e = phase_error(d, q); /* exact phase error of the +q alignment, amplitude-free */
            ef += a_ef * (e - ef);
            if (lck == 0.0) {
                cnt = fabs(ef) < thr ? cnt + 1.0 : 0.0;
                lck = cnt >= n_lock ? 1.0 : 0.0;
            } else if (fabs(ef) > thr_off) {
                lck = 0.0;
                cnt = 0.0;
                wn = wn_acq;
            }
        }
        if (lck != 0.0 && wn > wn_trk) {
            const double tapered = wn * taper;
            wn = wn_trk > tapered ? wn_trk : tapered; /* Python's max(tapered, wn_trk) */
        }
        om += wn * wn * ts * e;
        theta[k] = th;
        omega[k] = om;
        cos_th[k] = c;
        sin_th[k] = s;
        const double half = 0.5 * ts * om;
        double ch, sh;
        if (fabs(half) <= SMALL_ANGLE) {
            small_cos_sin(half, &ch, &sh);
            cos_v[k] = c * ch - s * sh;
            sin_v[k] = s * ch + c * sh;
        } else {
            cos_v[k] = cos(th + half);
            sin_v[k] = sin(th + half);
        }
        const double step = ts * (om + 2.0 * zeta * wn * e);
        th += step;
        const double turns = (th + PI) / two_pi;
        if (turns < 0.0 || turns >= 1.0) /* floor(turns) is 0 in between: no libm call */
            th -= two_pi * floor(turns);
        steps += 1.0;
        if (steps >= RESYNC || !(fabs(step) <= SMALL_ANGLE)) {
            steps = 0.0;
            c = cos(th);
            s = sin(th);
        } else {
            double cr, sr;
            small_cos_sin(step, &cr, &sr);
            const double c_next = c * cr - s * sr;
            s = s * cr + c * sr;
            c = c_next;
        }
    }
    state[0] = th;
    state[1] = om;
    state[2] = ef;
    state[3] = cnt;
    state[4] = lck;
    state[5] = wn;
    state[6] = c;
    state[7] = s;
    state[8] = steps;
}

/* Free-run simulation x(k+1) = (A0 + omega(k) A1) x(k) + u(k) (agent/model.py), x(0) = x0.
 *
 * a0, a1 (2, 2); omega (n,); u (2, n); x0 (2,); x (2, n), written.
 */
void simulate_ltv(const double *a0, const double *a1, const double *omega, const double *u,
                  const double *x0, ptrdiff_t n, double *x)
{
    /* locals, so the stores to x (which might alias) force no reloads */
    const double a0_dd = a0[0], a0_dq = a0[1], a0_qd = a0[2], a0_qq = a0[3];
    const double a1_dd = a1[0], a1_dq = a1[1], a1_qd = a1[2], a1_qq = a1[3];
    const double *ud = u, *uq = u + n;
    double *xd = x, *xq = x + n;

    if (n <= 0)
        return;
    double d = x0[0], q = x0[1];
    xd[0] = d;
    xq[0] = q;
    for (ptrdiff_t k = 0; k < n - 1; ++k) {
        const double w = omega[k];
        const double d_next = (a0_dd + w * a1_dd) * d + (a0_dq + w * a1_dq) * q + ud[k];
        const double q_next = (a0_qd + w * a1_qd) * d + (a0_qq + w * a1_qq) * q + uq[k];
        d = d_next;
        q = q_next;
        xd[k + 1] = d;
        xq[k + 1] = q;
    }
}
