"""Closed-loop drive kernel: IPMSM (eqs. 3-5, flux state), FOC drive, two-mass transmission (eqs. 7-9).

One call simulates ``n`` samples at ``T_s``. Per sample k (time t_k):

1. the DAQ-side quantities are recorded: current i(t_k) (instantaneous), the inverter's average
   output voltage over [t_k, t_k + T_s) (zero-order hold, what eq. 6 assumes) and the drive's command
   for that interval, the electrical angle and speed;
2. the drive computes the command for [t_{k+1}, t_{k+2}) (one-sample computation delay) from its
   own (noisy) current sensors and the encoder: speed PI -> i_q reference (i_d_ref = 0) -> current PI
   in rotor coordinates with decoupling feed-forward, voltage limit and back-calculation anti-windup,
   angle advance 1.5 omega_e T_s for the inverse Park transform;
3. the plant is integrated over [t_k, t_k + T_s) with ``n_sub`` RK4 steps; the inverter holds the
   alpha-beta voltage (command + dead-time error), disturbance torques are held per sample.

Plant (rotor frame, flux state; reduces exactly to eq. 5 when the harmonics are 0 and a = 0):
    d psi_d/dt = v_d - R_s i_d + omega_e psi_q,   i_d = (psi_d - psi_pm,d) / L_d
    d psi_q/dt = v_q - R_s i_q - omega_e psi_d,   i_q = psi_i / L_q0 (1 + a (psi_i/psi_qr)^2), psi_i = psi_q - psi_pm,q
    T_e = 1.5 n_p (psi_d i_q - psi_q i_d + i_d d psi_pm,d/d theta_e + i_q d psi_pm,q/d theta_e)
with the magnet flux in the rotor frame psi_pm,d = psi_m + h_dc cos 6 theta_e + h_ds sin 6 theta_e,
psi_pm,q = h_qc cos 6 theta_e + h_qs sin 6 theta_e (the 5th and 7th space harmonics, see
``simulation.flux_harmonic_coefficients``).
    J_1 d omega_1/dt = T_e - B_1 omega_1 - T_sh - T_dist,1,   T_sh = K_s (theta_1 - theta_2) + C_s (omega_1 - omega_2)
    J_2 d omega_2/dt = T_sh - B_2 omega_2 - T_L0 (1 + k_load (omega_2/omega_ref - 1)) - T_dist,2

A load step adds ``DT_STEP`` (N m) to the driven side's torque from sample ``K_STEP`` on.
"""

from __future__ import annotations

import math

from numba import njit

# indices into the parameter vector ``par`` (see simulation.py for how each is set)
(T_S, N_SUB, N_P, R_S, R_DRIFT, K_REC, L_D, L_Q0, PSI_M, H_DC, H_DS, H_QC, H_QS, SAT_A, PSI_QR,
 J_1, J_2, K_S, C_S, B_1, B_2, T_L0, K_LOAD, W_REF, U_DT, U_MAX,
 LD_HAT, LQ_HAT, PSIM_HAT, KP_D, KP_Q, KI_D, KI_Q, KP_W, KI_W, T_MAX, K_STEP, DT_STEP, N_PAR) = range(39)
# derived entries (reciprocals: divisions dominate the RK stages), filled by ``derived(par)``
(INV_LD, INV_LQ0, INV_PSIQR, INV_J1, INV_J2, TL_SLOPE, N_PAR_ALL) = range(N_PAR, N_PAR + 7)

# columns of the disturbance-term table ``terms`` (one row per torque term)
(TM_NODE, TM_THETA2, TM_GAIN, TM_PHASE, TM_AMP, TM_WIDTH, TM_MEAN, N_TM) = range(8)

_I_DT = 0.05  # A, dead-time error grows linearly for |i| below this (current ripple smooths sign(i))
_SQRT3 = math.sqrt(3.0)


def derived(par):
    """Append the derived entries to a parameter vector of length ``N_PAR``."""
    extra = [1.0 / par[L_D], 1.0 / par[L_Q0], 1.0 / par[PSI_QR], 1.0 / par[J_1], 1.0 / par[J_2],
             par[T_L0] * par[K_LOAD] / par[W_REF]]
    return list(par[:N_PAR]) + extra


@njit(cache=True, nogil=True)
def _magnet(th_e, par):
    """Magnet flux in the rotor frame (Wb) and its derivatives by theta_e: (d, q, d', q')."""
    if par[H_DC] == 0.0 and par[H_DS] == 0.0 and par[H_QC] == 0.0 and par[H_QS] == 0.0:
        return par[PSI_M], 0.0, 0.0, 0.0
    c6, s6 = math.cos(6.0 * th_e), math.sin(6.0 * th_e)
    return (par[PSI_M] + par[H_DC] * c6 + par[H_DS] * s6, par[H_QC] * c6 + par[H_QS] * s6,
            6.0 * (par[H_DS] * c6 - par[H_DC] * s6), 6.0 * (par[H_QS] * c6 - par[H_QC] * s6))


@njit(cache=True, nogil=True)
def _currents(psi_d, psi_q, th_e, par):
    """Currents (A) from flux linkages (Wb) at electrical angle ``th_e`` (rad)."""
    pm_d, pm_q, _, _ = _magnet(th_e, par)
    psi_i = psi_q - pm_q
    r = psi_i * par[INV_PSIQR]
    return (psi_d - pm_d) * par[INV_LD], psi_i * par[INV_LQ0] * (1.0 + par[SAT_A] * r * r)


@njit(cache=True, nogil=True)
def _cos_sin(th_e, th_k, c_k, s_k):
    """cos, sin of ``th_e`` from cos, sin of a nearby angle ``th_k`` (rad).

    Angle addition with a Taylor series of the small increment (error < 1e-15 for |d| < 0.1 rad,
    i.e. up to f_e ~ 400 Hz at 25 kHz), much cheaper than cos and sin at every RK stage.
    """
    d = th_e - th_k
    if abs(d) > 0.2:
        return math.cos(th_e), math.sin(th_e)
    d2 = d * d
    cd = 1.0 - 0.5 * d2 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0 * (1.0 - d2 / 56.0)))
    sd = d * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0 * (1.0 - d2 / 72.0))))
    return c_k * cd - s_k * sd, s_k * cd + c_k * sd


@njit(cache=True, nogil=True)
def _deriv(psi_d, psi_q, w1, w2, th1, th2, v_a, v_b, R_s, T_1, T_2, par, th_k, c_k, s_k):
    """Time derivatives of (psi_d, psi_q, omega_1, omega_2, theta_1, theta_2).

    ``th_k, c_k, s_k``: electrical angle at the start of the sample and its cos, sin.
    """
    n_p = par[N_P]
    th_e = n_p * th1
    c, s = _cos_sin(th_e, th_k, c_k, s_k)
    v_d = v_a * c + v_b * s
    v_q = -v_a * s + v_b * c
    i_d, i_q = _currents(psi_d, psi_q, th_e, par)
    _, _, dpm_d, dpm_q = _magnet(th_e, par)
    w_e = n_p * w1
    T_e = 1.5 * n_p * (psi_d * i_q - psi_q * i_d + i_d * dpm_d + i_q * dpm_q)
    T_sh = par[K_S] * (th1 - th2) + par[C_S] * (w1 - w2)
    T_L = par[T_L0] + par[TL_SLOPE] * (w2 - par[W_REF])  # = T_L0 (1 + k_load (w2/w_ref - 1))
    return (v_d - R_s * i_d + w_e * psi_q,
            v_q - R_s * i_q - w_e * psi_d,
            (T_e - par[B_1] * w1 - T_sh - T_1) * par[INV_J1],
            (T_sh - par[B_2] * w2 - T_L - T_2) * par[INV_J2],
            w1, w2)


@njit(cache=True, nogil=True)
def _dist(terms, th1, th2):
    """Disturbance torques (N m) on the motor side (node 0) and the driven side (node 1)."""
    T_1, T_2 = 0.0, 0.0
    for j in range(terms.shape[0]):
        th = th2 if terms[j, TM_THETA2] != 0.0 else th1
        phi = terms[j, TM_GAIN] * th + terms[j, TM_PHASE]
        width = terms[j, TM_WIDTH]
        if width == 0.0:
            val = math.sin(phi)
        else:
            w = phi + math.pi
            w = w - 2.0 * math.pi * math.floor(w / (2.0 * math.pi)) - math.pi
            val = math.exp(-0.5 * (w / width) ** 2) - terms[j, TM_MEAN]
        if terms[j, TM_NODE] == 0.0:
            T_1 += terms[j, TM_AMP] * val
        else:
            T_2 += terms[j, TM_AMP] * val
    return T_1, T_2


@njit(cache=True, nogil=True)
def run(par, x0, c0, terms, noise_drive, i_ab, v_ab, vref_ab, theta_e, omega_e):
    """Simulate ``i_ab.shape[1]`` samples; fills the output arrays in place.

    ``x0`` = (psi_d, psi_q, omega_1, omega_2, theta_1, theta_2) [Wb, Wb, rad/s, rad/s, rad, rad];
    ``c0`` = (xi_d, xi_q, xi_w, v_a, v_b): current/speed PI integrators [V, V, N m] and the
    alpha-beta command for the first interval [V]; ``noise_drive`` (2, n) alpha-beta noise of the
    drive's current sensors [A]. Outputs: ``i_ab``, ``v_ab`` (applied), ``vref_ab`` (command)
    (2, n); ``theta_e`` (unwrapped, rad), ``omega_e`` (rad/s) (n,).
    """
    n = i_ab.shape[1]
    T_s, n_p = par[T_S], par[N_P]
    n_sub = int(par[N_SUB])
    h = T_s / n_sub
    psi_d, psi_q, w1, w2, th1, th2 = x0[0], x0[1], x0[2], x0[3], x0[4], x0[5]
    xi_d, xi_q, xi_w, v_a, v_b = c0[0], c0[1], c0[2], c0[3], c0[4]
    for k in range(n):
        # 1. sample at t_k
        th_e = n_p * th1
        c, s = math.cos(th_e), math.sin(th_e)
        i_d, i_q = _currents(psi_d, psi_q, th_e, par)
        i_a, i_b = i_d * c - i_q * s, i_d * s + i_q * c
        i_ab[0, k], i_ab[1, k] = i_a, i_b
        theta_e[k], omega_e[k] = th_e, n_p * w1
        vref_ab[0, k], vref_ab[1, k] = v_a, v_b
        va_app, vb_app = v_a, v_b
        if par[U_DT] != 0.0:  # dead time: dv_x = -U_dt sign(i_x); common mode has no alpha-beta part
            ia_, ib_, ic_ = i_a, -0.5 * i_a + 0.5 * _SQRT3 * i_b, -0.5 * i_a - 0.5 * _SQRT3 * i_b
            da = -par[U_DT] * min(max(ia_ / _I_DT, -1.0), 1.0)
            db = -par[U_DT] * min(max(ib_ / _I_DT, -1.0), 1.0)
            dc = -par[U_DT] * min(max(ic_ / _I_DT, -1.0), 1.0)
            va_app += (2.0 / 3.0) * (da - 0.5 * (db + dc))
            vb_app += (db - dc) / _SQRT3
        v_ab[0, k], v_ab[1, k] = va_app, vb_app

        # 2. drive: command for [t_{k+1}, t_{k+2})
        ia_m, ib_m = i_a + noise_drive[0, k], i_b + noise_drive[1, k]
        id_m, iq_m = ia_m * c + ib_m * s, -ia_m * s + ib_m * c
        w_e = n_p * w1
        e_w = par[W_REF] - w1
        T_u = par[KP_W] * e_w + xi_w
        T_ref = min(max(T_u, -par[T_MAX]), par[T_MAX])
        xi_w += T_s * par[KI_W] * (e_w + (T_ref - T_u) / par[KP_W])
        iq_ref = T_ref / (1.5 * n_p * par[PSIM_HAT])
        e_d, e_q = -id_m, iq_ref - iq_m
        u_d = par[KP_D] * e_d + xi_d - w_e * par[LQ_HAT] * iq_ref
        u_q = par[KP_Q] * e_q + xi_q + w_e * par[PSIM_HAT]
        mag = math.sqrt(u_d * u_d + u_q * u_q)
        scale = par[U_MAX] / mag if mag > par[U_MAX] else 1.0
        xi_d += T_s * par[KI_D] * (e_d + (scale - 1.0) * u_d / par[KP_D])
        xi_q += T_s * par[KI_Q] * (e_q + (scale - 1.0) * u_q / par[KP_Q])
        u_d, u_q = scale * u_d, scale * u_q
        cc, sc = _cos_sin(th_e + 1.5 * w_e * T_s, th_e, c, s)
        v_a_next, v_b_next = u_d * cc - u_q * sc, u_d * sc + u_q * cc

        # 3. plant over [t_k, t_k + T_s)
        T_1, T_2 = _dist(terms, th1, th2)
        if k >= par[K_STEP]:  # a load step: the load torque changes by DT_STEP from sample K_STEP on
            T_2 += par[DT_STEP]
        R_s = par[R_S]
        if par[R_DRIFT] != 0.0 and k > par[K_REC]:
            R_s *= 1.0 + par[R_DRIFT] * (k - par[K_REC]) * T_s
        for _ in range(n_sub):
            k1 = _deriv(psi_d, psi_q, w1, w2, th1, th2, va_app, vb_app, R_s, T_1, T_2, par, th_e, c, s)
            k2 = _deriv(psi_d + 0.5 * h * k1[0], psi_q + 0.5 * h * k1[1], w1 + 0.5 * h * k1[2],
                        w2 + 0.5 * h * k1[3], th1 + 0.5 * h * k1[4], th2 + 0.5 * h * k1[5],
                        va_app, vb_app, R_s, T_1, T_2, par, th_e, c, s)
            k3 = _deriv(psi_d + 0.5 * h * k2[0], psi_q + 0.5 * h * k2[1], w1 + 0.5 * h * k2[2],
                        w2 + 0.5 * h * k2[3], th1 + 0.5 * h * k2[4], th2 + 0.5 * h * k2[5],
                        va_app, vb_app, R_s, T_1, T_2, par, th_e, c, s)
            k4 = _deriv(psi_d + h * k3[0], psi_q + h * k3[1], w1 + h * k3[2],
                        w2 + h * k3[3], th1 + h * k3[4], th2 + h * k3[5],
                        va_app, vb_app, R_s, T_1, T_2, par, th_e, c, s)
            g = h / 6.0
            psi_d += g * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0])
            psi_q += g * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1])
            w1 += g * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2])
            w2 += g * (k1[3] + 2.0 * k2[3] + 2.0 * k3[3] + k4[3])
            th1 += g * (k1[4] + 2.0 * k2[4] + 2.0 * k3[4] + k4[4])
            th2 += g * (k1[5] + 2.0 * k2[5] + 2.0 * k3[5] + k4[5])
        v_a, v_b = v_a_next, v_b_next
