/* Per-sample recursions of the agent's runtime path (loaded by agent/kernels.py through ctypes).
 *
 * Plain C on float64 arrays, no Python API: the agent runs them without importing numba/LLVM
 * (about 120 MB of resident memory). Every array is C-contiguous; the Python wrappers in
 * agent/kernels.py check the shapes. The arithmetic follows the Python reference expressions
 * operation by operation (same order, no reassociation); it is built with -ffp-contract=off so
 * that no multiply-add is fused on targets with FMA, and the results match the former numba
 * kernels bit for bit.
 */

#include <math.h>
#include <stddef.h>

#define PI 3.14159265358979323846 /* the double nearest pi, as math.pi */

/* SRF-PLL with gear shifting (agent/pll.py) over n samples of x_abc (3, n).
 *
 * clarke (2, 3): the first two rows of the amplitude-invariant Clarke matrix.
 * par (10,): Ts, wn_track, wn_acq, taper per sample, lock-filter coefficient, lock threshold,
 *            unlock threshold, lock samples, min amplitude, damping zeta.
 * state (6,), read and updated in place: angle, integrator omega, filtered error,
 *            samples below threshold, locked 0/1, natural frequency wn.
 * theta, omega (n,), written: the angle used for sample k and the integrator after it.
 */
void pll_run(const double *x_abc, ptrdiff_t n, const double *clarke, const double *par,
             double *state, double *theta, double *omega)
{
    const double ts = par[0], wn_trk = par[1], wn_acq = par[2], taper = par[3], a_ef = par[4];
    const double thr = par[5], thr_off = par[6], n_lock = par[7], amin = par[8], zeta = par[9];
    double th = state[0], om = state[1], ef = state[2], cnt = state[3], lck = state[4], wn = state[5];
    /* locals, so the stores to theta/omega (which might alias) force no reloads */
    const double c_aa = clarke[0], c_ab = clarke[1], c_ac = clarke[2];
    const double c_ba = clarke[3], c_bb = clarke[4], c_bc = clarke[5];
    const double two_pi = 2.0 * PI;
    const double *xa = x_abc, *xb = x_abc + n, *xc = x_abc + 2 * n;

    for (ptrdiff_t k = 0; k < n; ++k) {
        const double al = c_aa * xa[k] + c_ab * xb[k] + c_ac * xc[k];
        const double be = c_ba * xa[k] + c_bb * xb[k] + c_bc * xc[k];
        const double c = cos(th), s = sin(th);
        const double d = al * c + be * s;
        const double q = -al * s + be * c;
        double e = 0.0;
        if (isfinite(d) && isfinite(q) && hypot(d, q) > amin) {
            e = atan2(-d, q); /* exact phase error of the +q alignment, amplitude-free */
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
        th += ts * (om + 2.0 * zeta * wn * e);
        th -= two_pi * floor((th + PI) / two_pi);
    }
    state[0] = th;
    state[1] = om;
    state[2] = ef;
    state[3] = cnt;
    state[4] = lck;
    state[5] = wn;
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
