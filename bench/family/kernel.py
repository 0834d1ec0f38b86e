"""The per-sample loop: one numba kernel that runs the drive's controller at each control instant and
integrates the continuous machine, inverter and shaft in between.

Time is cut at every event of a control interval (switching edges, shifted by the dead time by the
sign of the phase current at that edge; the record's sampling instants and averaging windows) and
each piece is integrated by classical Runge-Kutta steps of at most ``T_c / SUBSTEPS``.

States: the flux linkages without the magnet harmonics (psi_sd, psi_sq, Wb), the shaft speed
omega_m (rad/s) and the electrical angle theta_e (rad), and the running integrals of the applied
phase-to-neutral voltages (V s) and of the phase currents (A s), from which the record's interval
averages are differenced.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from bench.family.machine import currents_from_flux, flux_from_currents, harmonic_flux

SUBSTEPS = 4  #: Runge-Kutta steps per control interval at least (plus one per event)
N_STATE = 10
S_PSI_D, S_PSI_Q, S_OMEGA_M, S_THETA, S_INT_V, S_INT_I = 0, 1, 2, 3, 4, 7

# scalar parameters, indices into ``par``
(P_POLE_PAIRS, P_J, P_B, P_UDC, P_TC, P_TS, P_T_DEAD, P_U_ON, P_U_DT, P_KNEE, P_SWITCHED, P_UPDATES,
 P_HOLD_DQ, P_DELAY, P_COMP, P_KP_D, P_KP_Q, P_KI_D, P_KI_Q, P_LD_HAT, P_LQ_HAT, P_PSI_HAT, P_U_MAX,
 P_SPEED_LOOP, P_KP_W, P_KI_W, P_KP_LOAD, P_KI_LOAD, P_REV_T, P_REV_PHASE, P_RIPPLE_T, P_RIPPLE_W,
 P_RIPPLE_PHASE, P_OFFSET_A, P_OFFSET_B, P_OFFSET_C, P_GAIN_A, P_GAIN_B, P_GAIN_C, P_ADC_STEP, P_ADC_FS,
 P_WINDOW_PHASE, P_T_MAX, N_PAR) = range(44)

# per control interval outputs
(C_IA, C_IB, C_IC, C_THETA, C_OMEGA, C_VD, C_VQ, C_VA, C_VB, C_VC, C_TORQUE, C_PSI_D, C_PSI_Q, C_ID, C_IQ,
 C_INT_VA, C_INT_VB, C_INT_VC, N_CTRL_OUT) = range(19)
# per record sample outputs
(R_IA, R_IB, R_IC, R_THETA, R_OMEGA, R_INT_VA, R_INT_VB, R_INT_VC, R_INT_I_HALF_A, R_INT_I_HALF_B,
 R_INT_I_HALF_C, R_INT_V_WIN_A, R_INT_V_WIN_B, R_INT_V_WIN_C, N_REC_OUT) = range(15)

SQRT3 = math.sqrt(3.0)


@njit(cache=True, inline="always")
def _clarke_park(a, b, c, cos_t, sin_t):
    alpha = (2.0 * a - b - c) / 3.0
    beta = (b - c) / SQRT3
    return alpha * cos_t + beta * sin_t, -alpha * sin_t + beta * cos_t


@njit(cache=True, inline="always")
def _inv_park_clarke(d, q, cos_t, sin_t):
    alpha = d * cos_t - q * sin_t
    beta = d * sin_t + q * cos_t
    return alpha, -0.5 * alpha + 0.5 * SQRT3 * beta, -0.5 * alpha - 0.5 * SQRT3 * beta


@njit(cache=True)
def _rhs(y, t, par, fm, hs, hm, ha, hp, r_s, t_load, switch, v_hold, dy, out_i):
    """Time derivative of the state ``y`` into ``dy``; the phase currents into ``out_i``; returns T_e (N m)."""
    p = par[P_POLE_PAIRS]
    theta = y[S_THETA]
    cos_t, sin_t = math.cos(theta), math.sin(theta)
    h_d, h_q, dh_d, dh_q = harmonic_flux(theta, hs, hm, ha, hp)
    i_d, i_q = currents_from_flux(y[S_PSI_D], y[S_PSI_Q], fm)
    ia, ib, ic = _inv_park_clarke(i_d, i_q, cos_t, sin_t)
    out_i[0], out_i[1], out_i[2] = ia, ib, ic
    if par[P_SWITCHED] > 0.5:
        u_on = par[P_U_ON]
        va = par[P_UDC] * switch[0] - u_on * np.sign(ia)
        vb = par[P_UDC] * switch[1] - u_on * np.sign(ib)
        vc = par[P_UDC] * switch[2] - u_on * np.sign(ic)
    else:
        if par[P_HOLD_DQ] > 0.5:
            va, vb, vc = _inv_park_clarke(v_hold[0], v_hold[1], cos_t, sin_t)
        else:
            va, vb, vc = v_hold[0], v_hold[1], v_hold[2]
        if par[P_U_DT] > 0.0:
            k = par[P_KNEE]
            va -= par[P_U_DT] * min(1.0, max(-1.0, ia / k))
            vb -= par[P_U_DT] * min(1.0, max(-1.0, ib / k))
            vc -= par[P_U_DT] * min(1.0, max(-1.0, ic / k))
    common = (va + vb + vc) / 3.0
    va -= common
    vb -= common
    vc -= common
    v_d, v_q = _clarke_park(va, vb, vc, cos_t, sin_t)
    omega_m = y[S_OMEGA_M]
    w = p * omega_m
    psi_d = y[S_PSI_D] + h_d
    psi_q = y[S_PSI_Q] + h_q
    dy[S_PSI_D] = v_d - r_s * i_d + w * psi_q - w * dh_d
    dy[S_PSI_Q] = v_q - r_s * i_q - w * psi_d - w * dh_q
    torque = 1.5 * p * (psi_d * i_q - psi_q * i_d + i_d * dh_d + i_q * dh_q)
    load = (t_load + par[P_RIPPLE_T] * math.sin(par[P_RIPPLE_W] * t + par[P_RIPPLE_PHASE])
            + par[P_REV_T] * math.cos(theta / p + par[P_REV_PHASE]))
    dy[S_OMEGA_M] = (torque - load - par[P_B] * omega_m) / par[P_J]
    dy[S_THETA] = w
    dy[S_INT_V], dy[S_INT_V + 1], dy[S_INT_V + 2] = va, vb, vc
    dy[S_INT_I], dy[S_INT_I + 1], dy[S_INT_I + 2] = ia, ib, ic
    return torque


@njit(cache=True)
def _integrate(y, t0, t1, h_max, par, fm, hs, hm, ha, hp, r_s, t_load, switch, v_hold, work, cur):
    """Runge-Kutta 4 from ``t0`` to ``t1`` in equal steps of at most ``h_max`` (in place)."""
    span = t1 - t0
    if span <= 0.0:
        return
    n = max(int(math.ceil(span / h_max - 1e-9)), 1)  # a span below 1e-9 h_max (event times a rounding apart): one step
    h = span / n
    k1, k2, k3, k4, tmp = work[0], work[1], work[2], work[3], work[4]
    t = t0
    for _ in range(n):
        _rhs(y, t, par, fm, hs, hm, ha, hp, r_s, t_load, switch, v_hold, k1, cur)
        for j in range(N_STATE):
            tmp[j] = y[j] + 0.5 * h * k1[j]
        _rhs(tmp, t + 0.5 * h, par, fm, hs, hm, ha, hp, r_s, t_load, switch, v_hold, k2, cur)
        for j in range(N_STATE):
            tmp[j] = y[j] + 0.5 * h * k2[j]
        _rhs(tmp, t + 0.5 * h, par, fm, hs, hm, ha, hp, r_s, t_load, switch, v_hold, k3, cur)
        for j in range(N_STATE):
            tmp[j] = y[j] + h * k3[j]
        _rhs(tmp, t + h, par, fm, hs, hm, ha, hp, r_s, t_load, switch, v_hold, k4, cur)
        for j in range(N_STATE):
            y[j] += h / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
        t += h


@njit(cache=True)
def _quantise(x, step, full_scale):
    return min(full_scale, max(-full_scale, step * np.round(x / step))) if step > 0.0 else x




@njit(cache=True)
def run_drive(par, fm, hs, hm, ha, hp, r_s, noise_ctrl, torque_cmd, omega_ref, tq_grid, id_tab, iq_tab,
              ld_tab, lq_tab, y0, integrators0, n_rec):
    """Simulate ``r_s.size`` control intervals of length ``par[P_TC]`` from the state ``y0``.

    Per control interval k: ``r_s[k]`` (ohm), ``noise_ctrl[k]`` (A, the current sensors' noise),
    ``torque_cmd[k]`` (N m: the PMSM's torque command when the load machine imposes the speed, else
    the load torque), ``omega_ref[k]`` (mechanical rad/s: the speed loop's reference, the load
    machine's or the drive's). ``integrators0``: PI integrators (u_d, u_q in V, speed loop N m, load
    machine N m) and the pending command (u_d, u_q, u_a, u_b, u_c). The table (``tq_grid`` N m ->
    i_d*, i_q* A, incremental L_d, L_q H) sets the current references and schedules the PI gains,
    ``par[P_KP_D]`` being the bandwidth times the controller's relative L_d estimate (1/s), and so on.
    Returns (per-interval outputs, per-record-sample outputs, [sum |carrier ripple at edges| (A),
    number of edges])."""
    n_ctrl = r_s.size
    tc = par[P_TC]
    ts = par[P_TS]
    p = par[P_POLE_PAIRS]
    udc = par[P_UDC]
    h_max = tc / SUBSTEPS
    y = y0.copy()
    ctrl = np.zeros((n_ctrl, N_CTRL_OUT))
    rec = np.zeros((n_rec, N_REC_OUT))
    work = np.zeros((5, N_STATE))
    cur = np.zeros(3)
    dy = np.zeros(N_STATE)
    switch = np.ones(3)  # every phase high at the first carrier centre (centred pulses)
    v_hold = np.zeros(3)
    int_d, int_q, int_w, int_load = integrators0[0], integrators0[1], integrators0[2], integrators0[3]
    pend_d, pend_q = integrators0[4], integrators0[5]
    pend_abc = integrators0[6:9].copy()
    pending_edge = np.full(3, -1.0)  # absolute time of a dead-time-delayed edge
    pending_level = np.zeros(3)
    edge_t = np.zeros(6)
    edge_i = np.zeros(6)
    edge_phase = np.zeros(6, dtype=np.int64)
    ripple = np.zeros(2)
    meas = np.zeros(3)
    m0, m_half, m_win = 0, 0, 0  # next record instants (phase 0, 0.5 and the voltage window's phase)
    w_phase = par[P_WINDOW_PHASE]
    offs = (par[P_OFFSET_A], par[P_OFFSET_B], par[P_OFFSET_C])
    gains = (par[P_GAIN_A], par[P_GAIN_B], par[P_GAIN_C])
    for k in range(n_ctrl):
        t0 = k * tc
        t_end = (k + 1) * tc
        # --- the controller's sample at the carrier's centre
        cos_t, sin_t = math.cos(y[S_THETA]), math.sin(y[S_THETA])
        i_d_true, i_q_true = currents_from_flux(y[S_PSI_D], y[S_PSI_Q], fm)
        ia, ib, ic = _inv_park_clarke(i_d_true, i_q_true, cos_t, sin_t)
        true_abc = (ia, ib, ic)
        for x in range(3):
            meas[x] = _quantise(gains[x] * true_abc[x] + offs[x] + noise_ctrl[k, x], par[P_ADC_STEP], par[P_ADC_FS])
        theta = y[S_THETA]
        omega_m = y[S_OMEGA_M]
        w = p * omega_m
        i_d, i_q = _clarke_park(meas[0], meas[1], meas[2], cos_t, sin_t)
        # --- speed: the drive's speed loop, or the load machine holding the speed
        if par[P_SPEED_LOOP] > 0.5:
            err_w = omega_ref[k] - omega_m
            torque_ref = par[P_KP_W] * err_w + int_w
            if abs(torque_ref) > par[P_T_MAX]:  # the torque limit, integration stopped
                torque_ref = math.copysign(par[P_T_MAX], torque_ref)
            else:
                int_w += par[P_KI_W] * tc * err_w
            t_load = torque_cmd[k]
        else:
            torque_ref = torque_cmd[k]
            err_w = omega_ref[k] - omega_m
            t_load = int_load - par[P_KP_LOAD] * err_w
            int_load -= par[P_KI_LOAD] * tc * err_w
        i_d_ref, i_q_ref = np.interp(torque_ref, tq_grid, id_tab), np.interp(torque_ref, tq_grid, iq_tab)
        l_d, l_q = np.interp(torque_ref, tq_grid, ld_tab), np.interp(torque_ref, tq_grid, lq_tab)
        # --- current PI in dq with decoupling, the voltage limited to the inverter's linear range
        e_d = i_d_ref - i_d
        e_q = i_q_ref - i_q
        dec_d = -w * par[P_LQ_HAT] * i_q
        dec_q = w * (par[P_LD_HAT] * i_d + par[P_PSI_HAT])
        u_d = par[P_KP_D] * l_d * e_d + int_d + dec_d
        u_q = par[P_KP_Q] * l_q * e_q + int_q + dec_q
        mag = math.hypot(u_d, u_q)
        if mag > par[P_U_MAX]:
            u_d *= par[P_U_MAX] / mag
            u_q *= par[P_U_MAX] / mag
        else:
            int_d += par[P_KI_D] * l_d * tc * e_d
            int_q += par[P_KI_Q] * l_q * tc * e_q
        comp = (par[P_DELAY] + 0.5) * w * tc if par[P_COMP] > 0.5 else 0.0
        ua, ub, uc = _inv_park_clarke(u_d, u_q, math.cos(theta + comp), math.sin(theta + comp))
        row = ctrl[k]
        row[C_IA], row[C_IB], row[C_IC] = meas[0], meas[1], meas[2]
        row[C_THETA], row[C_OMEGA] = theta, w
        row[C_VD], row[C_VQ] = u_d, u_q
        row[C_VA], row[C_VB], row[C_VC] = ua, ub, uc
        row[C_TORQUE] = _rhs(y, t0, par, fm, hs, hm, ha, hp, r_s[k], t_load, switch, v_hold, dy, cur)
        h_d, h_q, _, _ = harmonic_flux(theta, hs, hm, ha, hp)
        row[C_PSI_D], row[C_PSI_Q] = y[S_PSI_D] + h_d, y[S_PSI_Q] + h_q
        row[C_ID], row[C_IQ] = i_d_true, i_q_true
        row[C_INT_VA], row[C_INT_VB], row[C_INT_VC] = y[S_INT_V], y[S_INT_V + 1], y[S_INT_V + 2]
        # --- the command acting in this interval (computed now, or one interval ago)
        if par[P_DELAY] > 0.5:
            act_d, act_q, act_a, act_b, act_c = pend_d, pend_q, pend_abc[0], pend_abc[1], pend_abc[2]
            pend_d, pend_q = u_d, u_q
            pend_abc[0], pend_abc[1], pend_abc[2] = ua, ub, uc
        else:
            act_d, act_q, act_a, act_b, act_c = u_d, u_q, ua, ub, uc
        if par[P_HOLD_DQ] > 0.5:
            v_hold[0], v_hold[1], v_hold[2] = act_d, act_q, 0.0
        else:
            v_hold[0], v_hold[1], v_hold[2] = act_a, act_b, act_c
        # --- switching edges of this interval (centred PWM with min-max zero sequence)
        n_edges = 0
        if par[P_SWITCHED] > 0.5:
            zero = -0.5 * (max(act_a, act_b, act_c) + min(act_a, act_b, act_c))
            act = (act_a, act_b, act_c)
            rising_half = par[P_UPDATES] > 1.5 and k % 2 == 1
            for x in range(3):
                duty = min(1.0, max(0.0, 0.5 + (act[x] + zero) / udc))
                if par[P_UPDATES] > 1.5:  # carrier half period per interval: one edge
                    edge_t[n_edges] = t0 + ((1.0 - duty) * tc if rising_half else duty * tc)
                    edge_phase[n_edges] = x + (3 if rising_half else 0)
                    n_edges += 1
                else:  # a whole carrier period per interval: high around the interval's ends
                    edge_t[n_edges] = t0 + 0.5 * duty * tc
                    edge_phase[n_edges] = x
                    edge_t[n_edges + 1] = t0 + (1.0 - 0.5 * duty) * tc
                    edge_phase[n_edges + 1] = x + 3
                    n_edges += 2
        done = np.zeros(6, dtype=np.bool_)
        i_start = (ia, ib, ic)
        # --- integrate through the interval's events
        now = (0.0, 0.0, 0.0)
        t = t0
        while True:
            t_next = t_end
            kind = 0  # 0 end, 1 record sample, 2 half-window, 3 voltage window, 4 commanded edge, 5 delayed edge
            which = -1
            tm = m0 * ts
            if m0 < n_rec and tm < t_next - 1e-12 * ts:
                t_next, kind = tm, 1
            tm = (m_half + 0.5) * ts
            if m_half < n_rec and tm < t_next - 1e-12 * ts:
                t_next, kind = tm, 2
            tm = (m_win + w_phase) * ts
            if m_win < n_rec and tm < t_next - 1e-12 * ts:
                t_next, kind = tm, 3
            for e in range(n_edges):
                if not done[e] and edge_t[e] <= t_next:
                    t_next, kind, which = edge_t[e], 4, e
            for x in range(3):
                if pending_edge[x] >= 0.0 and pending_edge[x] <= t_next:
                    t_next, kind, which = pending_edge[x], 5, x
            t_next = max(t_next, t)
            _integrate(y, t, t_next, h_max, par, fm, hs, hm, ha, hp, r_s[k], t_load, switch, v_hold, work, cur)
            t = t_next
            if kind == 0:
                break
            if kind == 1 or kind == 2 or kind == 3 or kind == 4:
                c_t, s_t = math.cos(y[S_THETA]), math.sin(y[S_THETA])
                i_d_now, i_q_now = currents_from_flux(y[S_PSI_D], y[S_PSI_Q], fm)
                now = _inv_park_clarke(i_d_now, i_q_now, c_t, s_t)
            if kind == 1:
                r = rec[m0]
                r[R_IA], r[R_IB], r[R_IC] = now[0], now[1], now[2]
                r[R_THETA], r[R_OMEGA] = y[S_THETA], p * y[S_OMEGA_M]
                r[R_INT_VA], r[R_INT_VB], r[R_INT_VC] = y[S_INT_V], y[S_INT_V + 1], y[S_INT_V + 2]
                m0 += 1
            elif kind == 2:
                r = rec[m_half]
                r[R_INT_I_HALF_A], r[R_INT_I_HALF_B], r[R_INT_I_HALF_C] = y[S_INT_I], y[S_INT_I + 1], y[S_INT_I + 2]
                m_half += 1
            elif kind == 3:
                r = rec[m_win]
                r[R_INT_V_WIN_A], r[R_INT_V_WIN_B], r[R_INT_V_WIN_C] = y[S_INT_V], y[S_INT_V + 1], y[S_INT_V + 2]
                m_win += 1
            elif kind == 4:
                done[which] = True
                x = edge_phase[which] % 3
                rising = edge_phase[which] >= 3
                edge_i[which] = now[x]
                if pending_edge[x] >= 0.0:  # a narrow pulse: the earlier delayed edge happens first
                    switch[x] = pending_level[x]
                    pending_edge[x] = -1.0
                level = 1.0 if rising else 0.0
                # during the dead time the free-wheeling diode sets the phase by the current's sign
                delayed = (rising and now[x] > 0.0) or ((not rising) and now[x] < 0.0)
                if delayed and par[P_T_DEAD] > 0.0:
                    pending_edge[x] = t + par[P_T_DEAD]
                    pending_level[x] = level
                else:
                    switch[x] = level
            else:
                switch[which] = pending_level[which]
                pending_edge[which] = -1.0
        # carrier ripple at the edges: deviation from the line between the centre samples
        if n_edges > 0:
            d_end, q_end = currents_from_flux(y[S_PSI_D], y[S_PSI_Q], fm)
            i_end = _inv_park_clarke(d_end, q_end, math.cos(y[S_THETA]), math.sin(y[S_THETA]))
            for e in range(n_edges):
                x = edge_phase[e] % 3
                frac = (edge_t[e] - t0) / tc
                ripple[0] += abs(edge_i[e] - (i_start[x] + frac * (i_end[x] - i_start[x])))
                ripple[1] += 1.0
    return ctrl, rec, ripple
