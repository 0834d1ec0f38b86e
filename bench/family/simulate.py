"""Records of a drawn drive: set up the kernel from the drive and its hidden effects, warm up at the
operating point, then sample the record the way the drive (or a DAQ beside it) does.

Channels (CONTRACT section 3), by the drive's configuration:

* ``ia, ib, ic``: the current sensors (gain, offset: the hidden effects) plus white noise, through
  the ADC (``adc_bits`` over +- ``current_full_scale_a``): the controller's own samples at the
  carrier's centre ("centre"), the average over [t_k - T_s/2, t_k + T_s/2] ("average"), or
  instantaneous samples of a record clock that is not the PWM's ("async", carrier ripple visible);
* ``va, vb, vc`` (phase-to-neutral): the command the controller computed at t_k ("reference",
  as its phase commands or as its dq command at the sample's angle), or the applied voltage
  averaged over [t_k - d T_s, t_k + (1 - d) T_s] (d = ``voltage_filter_delay``) plus noise through
  the voltage ADC ("measured"); the voltage_delay effect shifts this channel further;
* ``theta_e`` (continuous, rad) and ``omega_e`` (rad/s), the true rotor's, when the drive has an
  encoder.
"""

from __future__ import annotations

import json
import math

import numpy as np
import scipy.optimize

from agent.records import Record
from bench.family import kernel as K
from bench.family.drive import COPPER_PER_K, Drive, reference_table, steady_voltage
from bench.family.effects import EFFECTS, saturation_map, voltage_path
from bench.family.machine import flux_from_currents, harmonic_terms

MARGIN = 4  #: record samples simulated after the record (the voltage channel's extra delay reads ahead)
ACCEL_TORQUE = 0.3  #: per unit of rated torque: the speed reference's ramp accelerates the inertia with it
TORQUE_LIMIT = 2.0  #: per unit of rated torque: the speed loop's output limit


def _warmup_s(drive: Drive) -> float:
    """Time simulated and dropped before the record: the loops settle from the computed steady state."""
    return min(0.4, 0.1 + 4.0 / (2 * math.pi * drive.speed_bandwidth_hz))


def _quantise(x: np.ndarray, bits: int, full_scale: float) -> np.ndarray:
    step = 2.0 * full_scale / 2 ** bits
    return np.clip(step * np.round(x / step), -full_scale, full_scale)


def _inv_park(d, q, theta):
    alpha = d * np.cos(theta) - q * np.sin(theta)
    beta = d * np.sin(theta) + q * np.cos(theta)
    return np.stack((alpha, -0.5 * alpha + 0.5 * K.SQRT3 * beta, -0.5 * alpha - 0.5 * K.SQRT3 * beta))


def _shift(x: np.ndarray, samples: float) -> np.ndarray:
    """x(k - samples) along the last axis by linear interpolation (holds the ends)."""
    if samples == 0.0:
        return x
    k = np.arange(x.shape[-1], dtype=float)
    return np.stack([np.interp(k - samples, k, row) for row in x])


def _shaft_ripple(t: np.ndarray, omega_e: np.ndarray, pole_pairs: int) -> float:
    """Amplitude (rad/s) of omega_e at the shaft's rotation frequency (least squares, with a trend)."""
    w_m = float(np.mean(omega_e)) / pole_pairs
    basis = np.column_stack((np.ones_like(t), t, np.cos(w_m * t), np.sin(w_m * t)))
    coef = np.linalg.lstsq(basis, omega_e, rcond=None)[0]
    return float(math.hypot(coef[2], coef[3]))


def _deadtime_knee(drive: Drive, ctrl: np.ndarray, t_rel: np.ndarray, seconds: float) -> float:
    """The knee (A) of U_dt clip(i/knee) fitted with U_dt to the record's loss of the applied phase
    voltage against the command acting in each control interval, over the interval's mean true
    current: the averaged inverter's drawn knee, or the switched inverter's (its carrier ripple)."""
    if drive.inverter == "averaged":
        return float("nan")
    tc = 1.0 / drive.control_rate_hz
    inside = np.flatnonzero((t_rel >= 0.0) & (t_rel < seconds))[:-1]
    applied = (ctrl[inside + 1, K.C_INT_VA:K.C_INT_VC + 1] - ctrl[inside, K.C_INT_VA:K.C_INT_VC + 1]).T / tc
    source = inside - drive.computation_delay
    loss = applied - ctrl[source, K.C_VA:K.C_VC + 1].T
    current = [_inv_park(ctrl[j, K.C_ID], ctrl[j, K.C_IQ], ctrl[j, K.C_THETA]) for j in (inside, inside + 1)]
    current = 0.5 * (current[0] + current[1])
    loss -= loss.mean(axis=0)

    def residual(p):
        shape = np.clip(current / p[1], -1.0, 1.0)
        return (loss + p[0] * (shape - shape.mean(axis=0))).ravel()

    guess = (float(np.median(np.abs(loss))) * 1.5, 0.01 * drive.i_rated_peak)
    fit = scipy.optimize.least_squares(residual, guess, bounds=([0.0, 1e-6], [np.inf, np.inf]), x_scale="jac")
    return float(fit.x[1])


def simulate(drive: Drive, effects: dict | None, load_pct: float, seconds: float, seed: int,
             excitation: str | None = None) -> Record:
    """One record (CONTRACT section 3) of ``drive`` at ``load_pct`` (shaft torque, % of rated) for
    ``seconds``, with the hidden ``effects`` ({effect id: draw from draw_effect}); ``excitation``
    (None: the drive's own) is one of bench.family.drive.EXCITATIONS. ``seed`` draws the noise, the
    rotor's angle, the steps' times and sizes, the record's winding temperature."""
    return simulate_detail(drive, effects, load_pct, seconds, seed, excitation)[0]


def simulate_detail(drive: Drive, effects: dict | None, load_pct: float, seconds: float, seed: int,
                    excitation: str | None = None) -> tuple[Record, dict]:
    """:func:`simulate` and the internals at the record's samples: ``v_applied`` (3, N) the applied
    phase-to-neutral voltage averaged over [t_k, t_k + T_s] (V), ``i_true`` (3, N) the phase currents
    at t_k (A), ``theta_e``, ``omega_e`` (true), ``r_s`` (ohm); and per control interval (same
    samples when the record is synchronous): ``torque`` (N m), ``psi_d``, ``psi_q`` (Wb, with the
    harmonics), ``i_d``, ``i_q`` (A, true)."""
    effects = dict(effects or {})
    for key in effects:
        if key not in EFFECTS:
            raise KeyError(f"unknown effect {key!r} (known: {', '.join(EFFECTS)})")
    excitation = excitation or drive.excitation
    rng = np.random.default_rng([seed, drive.seed, 7])
    p = drive.pole_pairs
    tc, ts = 1.0 / drive.control_rate_hz, 1.0 / drive.rate_hz
    fm = saturation_map(drive, effects["magnetic_saturation"]) if "magnetic_saturation" in effects \
        else drive.linear_flux_map()
    harm = effects.get("flux_harmonics")
    hs, hm, ha, hp = harmonic_terms(*(harm[k] for k in ("orders", "psi_wb", "phase_rad"))) if harm \
        else (np.zeros(0),) * 4

    warmup = _warmup_s(drive)
    m_start = int(math.ceil(warmup / ts))
    n_keep = int(round(seconds * drive.rate_hz))
    n_rec = m_start + n_keep + MARGIN
    n_ctrl = int(math.ceil((n_rec + 1) * ts / tc)) + 1
    t_rel = np.arange(n_ctrl) * tc - m_start * ts  # control instants from the record's start, s

    # winding temperature: constant, or warming from each record's own start temperature
    drift = effects.get("resistance_drift")
    r20 = drive.rs_20c_ohm
    if drift:
        t_start_c = drive.winding_temp_c + rng.uniform(0.0, drift["start_spread_k"])
        rise = drift["rise_k"] * (1.0 - np.exp(-np.clip(t_rel, 0.0, None) / drift["tau_s"]))
        r_s = r20 * (1.0 + COPPER_PER_K * (t_start_c + rise - 20.0))
        slope_mid = r20 * COPPER_PER_K * drift["rise_k"] / drift["tau_s"] * math.exp(-0.5 * seconds / drift["tau_s"])
    else:
        r_s = np.full(n_ctrl, drive.rs_ohm)
        slope_mid = 0.0

    # operating point and excitation
    omega_op = drive.omega_m_operating
    t_load = load_pct / 100.0 * drive.rated_torque_nm
    step_at = rng.uniform(0.2, 0.7) * seconds
    after = t_rel >= step_at
    load = np.full(n_ctrl, t_load)
    omega_ref = np.full(n_ctrl, omega_op)
    step = 0.0
    if excitation == "load_step":
        step = rng.uniform(10.0, 30.0) * (1.0 if load_pct < 60.0 else -1.0)  # % of rated
        load += after * step / 100.0 * drive.rated_torque_nm
    elif excitation == "speed_step":  # through the drive's ramp: the acceleration takes ACCEL_TORQUE
        step = rng.uniform(5.0, 15.0) * (1.0 if drive.operating_speed_rpm < 0.7 * drive.rated_speed_rpm else -1.0)
        ramp_s = max(drive.inertia_kgm2 * abs(step) / 100.0 * omega_op / (ACCEL_TORQUE * drive.rated_torque_nm), 5e-3)
        omega_ref += np.clip((t_rel - step_at) / ramp_s, 0.0, 1.0) * step / 100.0 * omega_op
    elif excitation != "constant" and excitation != "load_ripple":
        raise ValueError(f"unknown excitation {excitation!r}")
    ripple_t = rng.uniform(0.02, 0.10) * drive.rated_torque_nm if excitation == "load_ripple" else 0.0
    ripple_w = 2 * math.pi * rng.uniform(2.0, 30.0)
    speed_loop = drive.mechanics == "speed_loop"
    torque_cmd = load if speed_loop else load + drive.friction_nm_s * omega_ref

    # the steady state the record starts from
    table = reference_table(drive, fm)
    torque0 = t_load + drive.friction_nm_s * omega_op
    i_d0, i_q0 = float(np.interp(torque0, table[0], table[1])), float(np.interp(torque0, table[0], table[2]))
    psi_d0, psi_q0 = flux_from_currents(i_d0, i_q0, fm)
    w0 = p * omega_op
    theta0 = rng.uniform(0.0, 2 * math.pi)
    v_d0, v_q0 = steady_voltage(fm, r_s[0], w0, i_d0, i_q0)
    comp = (drive.computation_delay + 0.5) * w0 * tc if drive.angle_compensation else 0.0
    pend_abc = _inv_park(np.array(v_d0), np.array(v_q0), np.array(theta0 - w0 * tc + comp))
    integrators = np.array([v_d0 + w0 * drive.ctrl_lq_h * i_q0,
                            v_q0 - w0 * (drive.ctrl_ld_h * i_d0 + drive.ctrl_psi_m_wb),
                            torque0, t_load, v_d0, v_q0, *pend_abc])
    y0 = np.zeros(K.N_STATE)
    y0[K.S_PSI_D], y0[K.S_PSI_Q], y0[K.S_OMEGA_M], y0[K.S_THETA] = psi_d0, psi_q0, omega_op, theta0

    par = _kernel_parameters(drive, effects, ripple_t, ripple_w, rng)
    noise = rng.normal(0.0, drive.current_noise_a, (n_ctrl, 3))
    ctrl, rec, edge = K.run_drive(par, fm, hs, hm, ha, hp, r_s, noise, torque_cmd, omega_ref,
                                  *table, y0, integrators, n_rec)

    # the record's channels
    keep = slice(m_start, m_start + n_keep)
    sensor_gain = 1.0 + np.asarray(effects.get("current_gain_mismatch", {}).get("gain_error", [0.0] * 3))[:, None]
    sensor_offset = np.asarray(effects.get("current_offset", {}).get("offset_a", [0.0] * 3))[:, None]
    if drive.current_sampling == "centre":
        i_rec = ctrl[:n_rec, K.C_IA:K.C_IC + 1].T  # the controller's own samples (same ADC)
    else:
        if drive.current_sampling == "average":
            half = rec[:, K.R_INT_I_HALF_A:K.R_INT_I_HALF_C + 1].T
            seen = np.diff(half, axis=1, prepend=half[:, :1]) / ts  # window [t_m - T_s/2, t_m + T_s/2]
        else:
            seen = rec[:, K.R_IA:K.R_IC + 1].T
        i_rec = _quantise(sensor_gain * seen + sensor_offset + rng.normal(0.0, drive.current_noise_a, seen.shape),
                          drive.adc_bits, drive.current_full_scale_a)
    int_v = rec[:, K.R_INT_VA:K.R_INT_VC + 1].T
    v_applied = np.diff(int_v, axis=1, append=int_v[:, -1:]) / ts
    if drive.voltage_source == "reference":
        if drive.command_logged_as == "dq" or drive.voltage_hold == "dq":
            v_rec = _inv_park(ctrl[:n_rec, K.C_VD], ctrl[:n_rec, K.C_VQ], ctrl[:n_rec, K.C_THETA])
        else:
            v_rec = ctrl[:n_rec, K.C_VA:K.C_VC + 1].T.copy()
    else:
        lag = int(math.ceil(drive.voltage_filter_delay - 1e-12))
        win = rec[:, K.R_INT_V_WIN_A:K.R_INT_V_WIN_C + 1].T
        window = np.diff(win, axis=1, append=win[:, -1:]) / ts  # window starting at (m + phase) T_s
        v_rec = np.roll(window, lag, axis=1)
        v_rec = _quantise(v_rec + rng.normal(0.0, drive.voltage_noise_v, v_rec.shape),
                          drive.voltage_adc_bits, drive.voltage_full_scale_v)
    extra = float(effects.get("voltage_delay", {}).get("extra_samples", 0.0))
    v_rec = _shift(v_rec, extra)
    t = np.arange(n_keep) * ts
    theta, omega = rec[keep, K.R_THETA], rec[keep, K.R_OMEGA]
    delay, advance = voltage_path(drive, extra)
    meta = {"generator": "bench.family", "drive_seed": drive.seed, "seed": seed, "load_pct": float(load_pct),
            "seconds": float(seconds), "excitation": excitation, "effects": json.dumps(effects, sort_keys=True),
            "step_time_s": float(step_at) if excitation in ("load_step", "speed_step") else -1.0,
            "step_pct": float(step), "R_s_start_ohm": float(r_s[np.searchsorted(t_rel, 0.0)]),
            "dR_dt_mid_ohm_per_s": float(slope_mid),
            "omega_e_ripple_rad_s": _shaft_ripple(t, omega, p),
            "edge_ripple_A": float(edge[0] / edge[1]) if edge[1] else 0.0,
            "deadtime_knee_A": _deadtime_knee(drive, ctrl, t_rel, seconds) if "inverter_deadtime" in effects else 0.0,
            "delay_samples": delay, "advance_samples": advance}
    record = Record(t=t, v_abc=v_rec[:, keep], i_abc=i_rec[:, keep],
                    theta_e=theta.copy() if drive.encoder else None, omega_e=omega.copy() if drive.encoder else None,
                    source=f"family drive {drive.seed}, load {load_pct:g} %, seed {seed}, "
                           f"effects {','.join(sorted(effects)) or 'none'}", meta=meta)
    ctrl_keep = slice(m_start, m_start + n_keep) if drive.current_sampling != "async" else slice(None)
    detail = {"v_applied": v_applied[:, keep], "i_true": rec[keep, K.R_IA:K.R_IC + 1].T, "theta_e": theta,
              "omega_e": omega, "r_s": np.interp(t, t_rel, r_s),
              "torque": ctrl[ctrl_keep, K.C_TORQUE], "psi_d": ctrl[ctrl_keep, K.C_PSI_D],
              "psi_q": ctrl[ctrl_keep, K.C_PSI_Q], "i_d": ctrl[ctrl_keep, K.C_ID], "i_q": ctrl[ctrl_keep, K.C_IQ],
              "omega_ctrl": ctrl[ctrl_keep, K.C_OMEGA]}
    return record, detail


def _kernel_parameters(drive: Drive, effects: dict, ripple_t: float, ripple_w: float, rng) -> np.ndarray:
    par = np.zeros(K.N_PAR)
    alpha_c = 2 * math.pi * drive.current_bandwidth_hz
    alpha_w = 2 * math.pi * drive.speed_bandwidth_hz
    j = drive.inertia_kgm2
    dead = effects.get("inverter_deadtime", {})
    rev = effects.get("speed_ripple", {})
    gain = effects.get("current_gain_mismatch", {}).get("gain_error", [0.0] * 3)
    offset = effects.get("current_offset", {}).get("offset_a", [0.0] * 3)
    lag = int(math.ceil(drive.voltage_filter_delay - 1e-12))
    values = {
        K.P_POLE_PAIRS: drive.pole_pairs, K.P_J: j, K.P_B: drive.friction_nm_s, K.P_UDC: drive.u_dc_v,
        K.P_TC: 1.0 / drive.control_rate_hz, K.P_TS: 1.0 / drive.rate_hz,
        K.P_T_DEAD: dead.get("t_dead_s", 0.0), K.P_U_ON: dead.get("u_on_v", 0.0),
        K.P_U_DT: dead.get("U_dt_v", 0.0), K.P_KNEE: dead.get("knee_a", 1.0),
        K.P_SWITCHED: drive.inverter == "switched", K.P_UPDATES: drive.updates_per_carrier,
        K.P_HOLD_DQ: drive.voltage_hold == "dq", K.P_DELAY: drive.computation_delay,
        K.P_COMP: drive.angle_compensation,
        K.P_KP_D: alpha_c * drive.ctrl_ld_h / drive.ld_h, K.P_KP_Q: alpha_c * drive.ctrl_lq_h / drive.lq_h,
        K.P_KI_D: alpha_c * drive.ctrl_ld_h / drive.ld_h / drive.integral_time_s,
        K.P_KI_Q: alpha_c * drive.ctrl_lq_h / drive.lq_h / drive.integral_time_s,
        K.P_LD_HAT: drive.ctrl_ld_h, K.P_LQ_HAT: drive.ctrl_lq_h, K.P_PSI_HAT: drive.ctrl_psi_m_wb,
        K.P_U_MAX: 0.99 * drive.u_dc_v / K.SQRT3, K.P_SPEED_LOOP: drive.mechanics == "speed_loop",
        K.P_KP_W: alpha_w * j, K.P_KI_W: alpha_w ** 2 * j / 4.0,
        K.P_KP_LOAD: alpha_w * j, K.P_KI_LOAD: alpha_w ** 2 * j / 4.0,
        K.P_REV_T: rev.get("torque_nm", 0.0), K.P_REV_PHASE: rev.get("phase_rad", 0.0),
        K.P_RIPPLE_T: ripple_t, K.P_RIPPLE_W: ripple_w, K.P_RIPPLE_PHASE: rng.uniform(0, 2 * math.pi),
        K.P_OFFSET_A: offset[0], K.P_OFFSET_B: offset[1], K.P_OFFSET_C: offset[2],
        K.P_GAIN_A: 1.0 + gain[0], K.P_GAIN_B: 1.0 + gain[1], K.P_GAIN_C: 1.0 + gain[2],
        K.P_ADC_STEP: 2.0 * drive.current_full_scale_a / 2 ** drive.adc_bits, K.P_ADC_FS: drive.current_full_scale_a,
        K.P_WINDOW_PHASE: lag - drive.voltage_filter_delay, K.P_T_MAX: TORQUE_LIMIT * drive.rated_torque_nm,
    }
    for index, value in values.items():
        par[index] = float(value)
    return par
