/* Per-sample recursions of the agent's runtime path (loaded by agent/kernels.py through ctypes).
 *
 * Plain C on float64 arrays, no Python API: the agent runs them without importing numba/LLVM
 * (about 120 MB of resident memory). Every array is C-contiguous; the Python wrappers in
 * agent/kernels.py check the shapes. It is built with -ffp-contract=off so that no multiply-add
 * is fused on targets with FMA: the results are the same on every target. The free-run simulation
 * follows its Python reference operation by operation (same order, no reassociation) and matches
 * it bit for bit (ltv_residuals runs the same recursion); block_rows replaces numpy expressions, its
 * hop sums included (tests/test_kernels.py compares them); the PLL replaces libm's per-sample cos,
 * sin, hypot and atan2 by a rotating phasor and series, within 1e-12 rad of the libm loop
 * (tests/test_kernels.py).
 */

#include <float.h>
#include <math.h>
#include <stddef.h>

#define PI 3.14159265358979323846 /* the double nearest pi, as math.pi */

/* The interface's version (agent/kernels.py refuses a library built from another one). 2: the
 * PLL's state of 9 and its cos/sin output; 3: block_rows, ring_sums and ltv_residuals; 4: the
 * rows without the input power (ring_sums takes it from the phases); 5: block_rows's row strides;
 * 6: pll_series, ltv_residuals's current row stride, block_rows's hop sums in place of ring_sums. */
int kernels_abi(void) { return 6; }

/* cos and sin of a small angle x (|x| <= SMALL_ANGLE) by their Taylor series: to x^4 / x^5 where
 * |x| <= 2^-10 (the loop's turn by its phase error, in lock), to x^6 / x^7 where |x| <= 1/32, to
 * x^8 / x^9 where |x| <= 1/16, to x^14 / x^13 above: the first term left out is below 1e-19 there,
 * far under an ulp of the result (tests/test_kernels.py holds each range to libm through
 * pll_series). Estrin's scheme (pairs of terms, powers of x^2 in parallel): the loop's latency
 * runs through here every sample. */
#define SMALL_ANGLE 0.4
static inline __attribute__((always_inline)) void small_cos_sin(double x, double *c, double *s)
{
    const double x2 = x * x, x4 = x2 * x2, x8 = x4 * x4;
    if (fabs(x) <= 0x1p-10) {
        *c = (1.0 - x2 * (1.0 / 2)) + x4 * (1.0 / 24);
        *s = x * ((1.0 - x2 * (1.0 / 6)) + x4 * (1.0 / 120));
        return;
    }
    if (fabs(x) <= 0.03125) {
        *c = (1.0 - x2 * (1.0 / 2)) + x4 * (1.0 / 24 - x2 * (1.0 / 720));
        *s = x * ((1.0 - x2 * (1.0 / 6)) + x4 * (1.0 / 120 - x2 * (1.0 / 5040)));
        return;
    }
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
 * atan(t), t = -d / q: to t^5 where |t| <= 2^-10, to t^9 where |t| <= 1/64, to t^15 above; the
 * first term left out is under an ulp of e (Estrin's scheme, as above). Else libm's atan2. */
static inline double phase_error(double d, double q)
{
    if (q > 0.0 && fabs(d) <= 0.125 * q) {
        const double t = -d / q, t2 = t * t, t4 = t2 * t2, t8 = t4 * t4;
        if (fabs(t) <= 0x1p-10)
            return t * ((1.0 - t2 * (1.0 / 3)) + t4 * (1.0 / 5));
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

/* SRF-PLL with gear shifting (agent/pll.py): parameters and state, in locals while a loop runs.
 *
 * par (10,): Ts, wn_track, wn_acq, taper per sample, lock-filter coefficient, lock threshold,
 *            unlock threshold, lock samples, min amplitude, damping zeta.
 * state (9,): angle, integrator omega, filtered error, samples below threshold, locked 0/1,
 *            natural frequency wn, the angle's phasor (cos, sin) and the steps it has been rotated
 *            since it was exact (0: take it from the angle; a new state has 0), so that a stream
 *            cut into blocks gives the same output.
 *
 * Per sample the loop needs the angle's cos and sin and the phase error; instead of libm's cos,
 * sin, hypot and atan2 (about 100 ns a sample) it rotates a phasor by the angle's step (a small
 * angle: its cos and sin by series), compares the squared amplitude and takes the error by the
 * atan series near lock. Every one of these equals the libm expression to an ulp or two; the
 * output stays within 1e-12 rad of the per-sample libm loop (tests/test_kernels.py).
 */
struct pll {
    double ts, wn_trk, wn_acq, taper, a_ef, thr, thr_off, n_lock, amin2, zeta, c_aa, c_ab, c_ac, c_ba, c_bb, c_bc;
    double th, om, ef, cnt, lck, wn, c, s, steps;
    double ch, sh; /* cos and sin of the last sample's half turn Ts omega / 2, when half_ok */
    int half_ok;
};

/* The half turn Ts omega / 2 of the integrator: its cos and sin in ch, sh where it is small. */
static inline __attribute__((always_inline)) void half_turn(struct pll *p)
{
    const double half = 0.5 * p->ts * p->om;
    p->half_ok = fabs(half) <= SMALL_ANGLE;
    if (p->half_ok)
        small_cos_sin(half, &p->ch, &p->sh);
}

static struct pll pll_load(const double *clarke, const double *par, const double *state)
{
    struct pll p = {par[0], par[1], par[2], par[3], par[4], par[5], par[6], par[7],
                    par[8] > 0.0 ? par[8] * par[8] : 0.0, par[9],
                    clarke[0], clarke[1], clarke[2], clarke[3], clarke[4], clarke[5],
                    state[0], state[1], state[2], state[3], state[4], state[5], state[6], state[7], state[8],
                    0.0, 0.0, 0}; /* the half turn: from the integrator, below */
    if (p.steps == 0.0) {
        p.c = cos(p.th);
        p.s = sin(p.th);
    }
    half_turn(&p); /* as the sample before worked it out: a stream cut into blocks continues exactly */
    return p;
}

static void pll_save(const struct pll *p, double *state)
{
    const double st[9] = {p->th, p->om, p->ef, p->cnt, p->lck, p->wn, p->c, p->s, p->steps};
    for (int j = 0; j < 9; ++j)
        state[j] = st[j];
}

/* One sample through the loop, its Clarke components (al, be) (the phases' alpha and beta, struct
 * pll's Clarke rows): out (6,) = the angle used for it, the integrator after it, cos and sin of the
 * angle and of the mid angle angle + Ts omega / 2 (at which a zero-order-held voltage is rotated).
 * Inlined into the loops, p stays in registers. */
static inline __attribute__((always_inline)) void pll_step(struct pll *p, double al, double be, double *out)
{
    const double c = p->c, s = p->s, d = al * c + be * s, q = -al * s + be * c;
    double e = 0.0;
    if (isfinite(d) && isfinite(q) && d * d + q * q > p->amin2) {
        e = phase_error(d, q); /* exact phase error of the +q alignment, amplitude-free */
        p->ef += p->a_ef * (e - p->ef);
        if (p->lck == 0.0) {
            p->cnt = fabs(p->ef) < p->thr ? p->cnt + 1.0 : 0.0;
            p->lck = p->cnt >= p->n_lock ? 1.0 : 0.0;
        } else if (fabs(p->ef) > p->thr_off) {
            p->lck = 0.0;
            p->cnt = 0.0;
            p->wn = p->wn_acq;
        }
    }
    if (p->lck != 0.0 && p->wn > p->wn_trk) {
        const double tapered = p->wn * p->taper;
        p->wn = p->wn_trk > tapered ? p->wn_trk : tapered; /* Python's max(tapered, wn_trk) */
    }
    /* The phasor's next value is (c, s) turned by step = Ts (omega + 2 zeta wn e), omega after this
     * sample's update: by the part known before e, Ts omega_before (twice the last sample's half
     * turn: its double angle; turned while e is worked out), then by the part e adds,
     * Ts (wn^2 Ts + 2 zeta wn) e; the loop's latency runs through the second turn only. */
    const double by_e = p->ts * (p->wn * p->wn * p->ts + 2.0 * p->zeta * p->wn) * e;
    const int ahead_ok = p->half_ok;
    const double ca = p->ch * p->ch - p->sh * p->sh, sa = 2.0 * p->ch * p->sh;
    const double c_ahead = c * ca - s * sa, s_ahead = s * ca + c * sa;
    p->om += p->wn * p->wn * p->ts * e;
    out[0] = p->th;
    out[1] = p->om;
    out[2] = c;
    out[3] = s;
    half_turn(p);
    if (p->half_ok) {
        out[4] = c * p->ch - s * p->sh;
        out[5] = s * p->ch + c * p->sh;
    } else {
        out[4] = cos(p->th + 0.5 * p->ts * p->om);
        out[5] = sin(p->th + 0.5 * p->ts * p->om);
    }
    const double step = p->ts * (p->om + 2.0 * p->zeta * p->wn * e);
    p->th += step;
    const double turns = (p->th + PI) / (2.0 * PI);
    if (turns < 0.0 || turns >= 1.0) /* floor(turns) is 0 in between: no libm call */
        p->th -= 2.0 * PI * floor(turns);
    p->steps += 1.0;
    if (p->steps >= RESYNC || !(ahead_ok && fabs(by_e) <= SMALL_ANGLE)) {
        p->steps = 0.0;
        p->c = cos(p->th);
        p->s = sin(p->th);
    } else {
        double cr, sr;
        small_cos_sin(by_e, &cr, &sr);
        p->c = c_ahead * cr - s_ahead * sr;
        p->s = s_ahead * cr + c_ahead * sr;
    }
}

/* The PLL over n samples of x_abc (3, n).
 *
 * clarke (2, 3): the first two rows of the amplitude-invariant Clarke matrix. par, state: struct
 * pll's (state read and updated in place).
 * theta, omega (n,), written: the angle used for sample k and the integrator after it.
 * cs (4, n), written: cos and sin of theta(k) and of theta(k) + Ts omega(k) / 2.
 */
void pll_run(const double *x_abc, ptrdiff_t n, const double *clarke, const double *par,
             double *state, double *theta, double *omega, double *cs)
{
    struct pll p = pll_load(clarke, par, state);
    for (ptrdiff_t k = 0; k < n; ++k) {
        double out[6];
        const double xa = x_abc[k], xb = x_abc[n + k], xc = x_abc[2 * n + k];
        pll_step(&p, p.c_aa * xa + p.c_ab * xb + p.c_ac * xc, p.c_ba * xa + p.c_bb * xb + p.c_bc * xc, out);
        theta[k] = out[0];
        omega[k] = out[1];
        for (int j = 0; j < 4; ++j)
            cs[j * n + k] = out[2 + j];
    }
    pll_save(&p, state);
}

/* The PLL's series at n points (tests/test_kernels.py holds them to libm): out (4, n) = cos and sin
 * of x by small_cos_sin (|x| <= SMALL_ANGLE), phase_error(d, q), and 1 where phase_error took its
 * series, else 0. */
void pll_series(const double *x, const double *d, const double *q, ptrdiff_t n, double *out)
{
    for (ptrdiff_t k = 0; k < n; ++k) {
        small_cos_sin(x[k], &out[k], &out[n + k]);
        out[2 * n + k] = phase_error(d[k], q[k]);
        out[3 * n + k] = q[k] > 0.0 && fabs(d[k]) <= 0.125 * q[k];
    }
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


/* The largest of |a|, |b|, |c| (for finite values: a NaN may go unseen). */
static inline double largest_abs(double a, double b, double c)
{
    a = fabs(a), b = fabs(b), c = fabs(c);
    a = a > b ? a : b;
    return a > c ? a : c;
}

/* nan_to_num's value of x: NaN -> 0, +-inf -> +-DBL_MAX (the PLL's input, whatever the samples). */
static inline double finite_or_max(double x)
{
    return isfinite(x) ? x : isnan(x) ? 0.0 : copysign(DBL_MAX, x);
}

/* One block of the streaming pipeline's signal rows (agent/pipeline.py), in one pass.
 *
 * i_abc, v_abc (3, n): phase currents, A, and voltages, V, their rows i_stride and v_stride elements
 * apart (views of longer records need no copy). clarke (2, 3): the Clarke rows giving
 * alpha, beta. limits (2,): |i| and |v| at or above which a sample is saturated.
 * theta_last: the unwrapped angle of the sample before the block, rad.
 * The angle: either angle (6, n): the angle (rad, wrapped or not), speed (rad/s), cos and sin of the
 *            angle and of the voltages' mid angle angle + Ts omega / 2; or, when angle is NULL, the
 *            PLL's over the currents (with non-finite samples as nan_to_num makes them): pll_par,
 *            pll_state as pll_run's (the state updated in place).
 * unwrapped (n,), written: the angle unwrapped continuing theta_last (np.unwrap's result: a step
 *            of pi or more is taken back by whole turns).
 * rows (11, n), written (float when f32, else double), its rows rows_stride elements apart (a span
 *            of the pipeline's ring): va vb vc ia ib ic omega i_d i_q v_d v_q
 *            (kernels.ROWS): the phases, the Park rotations of the currents at the angle and
 *            of the voltages at the mid angle (the input power v.i is summed from the phases).
 * sums (17,), read and updated in place when not NULL: a hop's sums carried across blocks, added to
 *            in sample order (the same however the stream is cut, the angle's to the rounding of
 *            its unwrapping, which each block does from theta_last), for the operating point,
 *            the running check and the torque regression (pipeline.HopSums): ref (the angle they
 *            are taken about, rad, not changed), then the sums of the input power v.i (W, from the
 *            phases), omega, i_q, i_d i_q, i_d^2 + i_q^2; the minima of i_d, i_q and their maxima
 *            (NaN once a sample is NaN); the sums of dth = angle - ref, dth^2, dth omega,
 *            dth power, omega^2, omega power; the sum of i_d.
 * Returns 1 when a sample is NaN or saturated, else 0.
 */
#define N_SUMS 17
/* block_rows's loop; inlined with its switches constant (the PLL's or a given angle, float rows,
 * sums), each case is compiled without the others' tests. */
static inline __attribute__((always_inline)) int rows_loop(
    const double *i_abc, ptrdiff_t i_stride, const double *v_abc, ptrdiff_t v_stride, ptrdiff_t n,
    const double *clarke, const double *limits, double theta_last, const double *angle, const double *pll_par,
    double *pll_state, double *unwrapped, void *rows, ptrdiff_t rows_stride, const int f32, double *sums,
    const int with_pll, const int with_sums)
{
    const double c_aa = clarke[0], c_ab = clarke[1], c_ac = clarke[2];
    const double c_ba = clarke[3], c_bb = clarke[4], c_bc = clarke[5];
    const double i_lim = limits[0], v_lim = limits[1], two_pi = 2.0 * PI;
    struct pll p = {0};
    if (with_pll)
        p = pll_load(clarke, pll_par, pll_state);
    float *r32 = (float *)rows;
    double *r64 = (double *)rows;
    const ptrdiff_t rs = rows_stride;
    double prev = theta_last, turns = 0.0;
    int bad = 0;
    double sm[N_SUMS] = {0.0};
    if (with_sums)
        for (int j = 0; j < N_SUMS; ++j)
            sm[j] = sums[j];

    for (ptrdiff_t k = 0; k < n; ++k) {
        const double ia = i_abc[k], ib = i_abc[i_stride + k], ic = i_abc[2 * i_stride + k];
        const double va = v_abc[k], vb = v_abc[v_stride + k], vc = v_abc[2 * v_stride + k];
        const double i_al = c_aa * ia + c_ab * ib + c_ac * ic, i_be = c_ba * ia + c_bb * ib + c_bc * ic;
        const int finite = isfinite(ia + ib + ic) && isfinite(va + vb + vc); /* each is (none is beyond 1e308) */
        double a[6]; /* angle, omega, cos, sin, cos and sin of the mid angle */
        if (with_pll && finite)
            pll_step(&p, i_al, i_be, a);
        else if (with_pll) {
            const double xa = finite_or_max(ia), xb = finite_or_max(ib), xc = finite_or_max(ic);
            pll_step(&p, c_aa * xa + c_ab * xb + c_ac * xc, c_ba * xa + c_bb * xb + c_bc * xc, a);
        } else
            for (int j = 0; j < 6; ++j)
                a[j] = angle[j * n + k];
        const double step = a[0] - prev;
        if (!(fabs(step) < PI))
            turns += -two_pi * rint(step / two_pi);
        prev = a[0];
        const double th = a[0] + turns;
        unwrapped[k] = th;
        const double i_max = largest_abs(ia, ib, ic), v_max = largest_abs(va, vb, vc);
        if (!(finite && i_max < i_lim && v_max < v_lim)) /* NaN, infinite or saturated */
            bad = 1;
        const double v_al = c_aa * va + c_ab * vb + c_ac * vc, v_be = c_ba * va + c_bb * vb + c_bc * vc;
        const double i_d = i_al * a[2] + i_be * a[3], i_q = -i_al * a[3] + i_be * a[2];
        const double v_d = v_al * a[4] + v_be * a[5], v_q = -v_al * a[5] + v_be * a[4];
#define STORE_ROWS(r)                                                                                  \
    (r[k] = va, r[rs + k] = vb, r[2 * rs + k] = vc, r[3 * rs + k] = ia, r[4 * rs + k] = ib,                \
     r[5 * rs + k] = ic, r[6 * rs + k] = a[1], r[7 * rs + k] = i_d, r[8 * rs + k] = i_q, r[9 * rs + k] = v_d, \
     r[10 * rs + k] = v_q)
        if (with_sums) { /* in the loop's spare cycles: its latency runs through the PLL */
            const double pw = va * ia + vb * ib + vc * ic, om = a[1], dth = th - sm[0];
            sm[1] += pw;
            sm[2] += om;
            sm[3] += i_q;
            sm[4] += i_d * i_q;
            sm[5] += i_d * i_d + i_q * i_q;
            sm[6] = i_d < sm[6] ? i_d : sm[6]; /* a NaN sample is skipped here, and marked below */
            sm[7] = i_q < sm[7] ? i_q : sm[7];
            sm[8] = i_d > sm[8] ? i_d : sm[8];
            sm[9] = i_q > sm[9] ? i_q : sm[9];
            sm[16] += i_d;
            sm[10] += dth;
            sm[11] += dth * dth;
            sm[12] += dth * om;
            sm[13] += dth * pw;
            sm[14] += om * om;
            sm[15] += om * pw;
        }
        if (f32)
            STORE_ROWS(r32); /* rounded to float */
        else
            STORE_ROWS(r64);
#undef STORE_ROWS
    }
    if (with_pll)
        pll_save(&p, pll_state);
    if (with_sums) {
        if (isnan(sm[16])) /* a NaN i_d (or +-inf both ways) */
            sm[6] = sm[8] = NAN;
        if (isnan(sm[3]))
            sm[7] = sm[9] = NAN;
        for (int j = 1; j < N_SUMS; ++j)
            sums[j] = sm[j];
    }
    return bad;
}

int block_rows(const double *i_abc, ptrdiff_t i_stride, const double *v_abc, ptrdiff_t v_stride, ptrdiff_t n,
               const double *clarke, const double *limits, double theta_last, const double *angle,
               const double *pll_par, double *pll_state, double *unwrapped, void *rows, ptrdiff_t rows_stride,
               int f32, double *sums)
{
    if (angle == NULL && f32 && sums != NULL) /* the pipeline's case without an encoder */
        return rows_loop(i_abc, i_stride, v_abc, v_stride, n, clarke, limits, theta_last, angle, pll_par, pll_state,
                         unwrapped, rows, rows_stride, 1, sums, 1, 1);
    return rows_loop(i_abc, i_stride, v_abc, v_stride, n, clarke, limits, theta_last, angle, pll_par, pll_state,
                     unwrapped, rows, rows_stride, f32, sums, angle == NULL, sums != NULL);
}

#define LTV_RUNS 8 /* the most runs ltv_residuals takes at once */

/* The phase-a residuals of m free runs of x(k+1) = (A0 + omega(k) A1) x(k) + u(k) over the same n
 * samples (agent/pipeline.py's open windows), each from its own state:
 * r_j(k) = (i_d(k) - x_d(k)) cos theta(k) - (i_q(k) - x_q(k)) sin theta(k).
 *
 * a0, a1 (2, 2); omega (n,); u (2, n); i_dq (2, n): the measured currents, their rows i_stride elements
 * apart (a span of a longer read-out needs no copy); theta (n,): the angle
 * (rad, unwrapped). x (2, m), read and updated in place: each run's state at the first sample, then
 * after the last (the step from sample n - 1), so that a stream cut into blocks continues exactly.
 * r (m, n), written. m <= LTV_RUNS. The recursion is simulate_ltv's, operation by operation (the same x); cos
 * and sin of theta come from a phasor rotated by the angle's steps (exact every RESYNC samples),
 * within 1e-14 of libm's.
 */
/* ltv_residuals's loop; inlined with m a constant (1, 2: the pipeline's open windows) its runs'
 * states stay in registers. */
static inline __attribute__((always_inline)) void ltv_loop(const double *a0, const double *a1, const double *omega,
                                                           const double *u, const double *i_dq, ptrdiff_t i_stride,
                                                           const double *theta, ptrdiff_t n, const ptrdiff_t m,
                                                           double *x, double *r)
{
    const double a0_dd = a0[0], a0_dq = a0[1], a0_qd = a0[2], a0_qq = a0[3];
    const double a1_dd = a1[0], a1_dq = a1[1], a1_qd = a1[2], a1_qq = a1[3];
    const double *ud = u, *uq = u + n, *id = i_dq, *iq = i_dq + i_stride;
    double d[LTV_RUNS], q[LTV_RUNS], c = 0.0, s = 0.0;
    for (ptrdiff_t j = 0; j < m; ++j) {
        d[j] = x[j];
        q[j] = x[m + j];
    }
    for (ptrdiff_t k = 0; k < n; ++k) {
        const double step = k > 0 ? theta[k] - theta[k - 1] : 0.0;
        if (k % RESYNC == 0 || !(fabs(step) <= SMALL_ANGLE)) {
            c = cos(theta[k]);
            s = sin(theta[k]);
        } else {
            double cr, sr;
            small_cos_sin(step, &cr, &sr);
            const double c_next = c * cr - s * sr;
            s = s * cr + c * sr;
            c = c_next;
        }
        const double w = omega[k], b_dd = a0_dd + w * a1_dd, b_dq = a0_dq + w * a1_dq;
        const double b_qd = a0_qd + w * a1_qd, b_qq = a0_qq + w * a1_qq;
        for (ptrdiff_t j = 0; j < m; ++j) {
            r[j * n + k] = (id[k] - d[j]) * c - (iq[k] - q[j]) * s;
            const double d_next = b_dd * d[j] + b_dq * q[j] + ud[k];
            q[j] = b_qd * d[j] + b_qq * q[j] + uq[k];
            d[j] = d_next;
        }
    }
    for (ptrdiff_t j = 0; j < m; ++j) {
        x[j] = d[j];
        x[m + j] = q[j];
    }
}

void ltv_residuals(const double *a0, const double *a1, const double *omega, const double *u, const double *i_dq,
                   ptrdiff_t i_stride, const double *theta, ptrdiff_t n, ptrdiff_t m, double *x, double *r)
{
    if (m == 1)
        ltv_loop(a0, a1, omega, u, i_dq, i_stride, theta, n, 1, x, r);
    else if (m == 2)
        ltv_loop(a0, a1, omega, u, i_dq, i_stride, theta, n, 2, x, r);
    else if (m <= LTV_RUNS) /* the wrapper refuses more */
        ltv_loop(a0, a1, omega, u, i_dq, i_stride, theta, n, m, x, r);
}
