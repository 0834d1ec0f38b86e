"""``simulate``: one record of the paper's rig (closed-loop IPMSM drive + transmission + DAQ).

Sampling convention: ``i_abc[:, k]`` is the current at t_k, ``v_abc[:, k]`` the inverter's average
voltage over [t_k, t_k + T_s) (zero-order hold, the assumption behind eq. 6); both DAQ channels have
the same filter delay, which is not modelled (their difference is the ``voltage_delay`` effect).
With ``sampling.voltage_source = "reference"`` the voltage columns hold the drive's command for
that interval (before dead time, no DAQ noise). The record starts at steady state: states are
initialised at the operating point and ``RigParams.t_warmup`` is simulated and discarded.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from agent.errors import InputError
from agent.frames import CLARKE_INV
from agent.frequencies import base_frequencies
from agent.profile import DriveProfile, load_profile
from agent.records import Record
from agent.simulator import plant as P
from agent.simulator.conditions import (FAMILIES, HEALTHY_RIPPLE, Harmonics, Pulse, check_condition,
                                        _MAX_LEAD, check_effects)
from agent.simulator.rig import RigParams, operating_point, psi_q_of_i_q, saturation, speed_pi_gains

_TAPS_HALF = 16  # fractional-delay interpolator: 2 x 16 taps
_KAISER_BETA = 8.0


def _family_angle(profile: DriveProfile, family: str) -> tuple[int, float]:
    """(use theta_2, gain): the family's revolution angle is gain * theta (theta motor-side, rad)."""
    tr = profile.transmission
    if family == "gm":
        return 0, 1.0
    if family == "gl":
        return 1, 1.0 / tr.ratio
    return 0, math.pi * tr.driving_pitch_diameter_mm / tr.chain_length_mm  # 2 pi r_m / l_ch


def _terms(profile, cond, severity, rng_draws, sr_amp) -> np.ndarray:
    """Disturbance-term table for the kernel (rows: node, theta2, gain, phase, amp, width, mean)."""
    amp_f, ph, phi0 = rng_draws
    kind = profile.transmission.kind
    rows = []
    for fi, fam in enumerate(FAMILIES):
        if fam not in HEALTHY_RIPPLE[kind]:
            continue
        use2, gain = _family_angle(profile, fam)
        for k, a in enumerate(HEALTHY_RIPPLE[kind][fam]):
            rows.append((1, use2, (k + 1) * gain, ph[fi, k], a * amp_f[fi, k], 0.0, 0.0))
    for term in cond.ripple:
        fi = FAMILIES.index(term.family)
        use2, gain = _family_angle(profile, term.family)
        if isinstance(term, Pulse):
            sig = term.width_rad
            mean = sig * math.sqrt(2 * math.pi) * math.erf(math.pi / (math.sqrt(2) * sig)) / (2 * math.pi)
            rows.append((1, use2, gain, phi0[fi], severity * term.peak_nm, sig, mean))
        elif isinstance(term, Harmonics):
            for k, a in enumerate(term.amp_nm):
                rows.append((1, use2, (k + 1) * gain, (k + 1) * phi0[fi], severity * a, 0.0, 0.0))
    if sr_amp:
        rows.append((0, 0, 1.0, phi0[3], sr_amp, 0.0, 0.0))
    return np.array(rows, dtype=float).reshape(-1, P.N_TM)


def flux_harmonic_coefficients(value) -> tuple[float, float, float, float]:
    """(h_dc, h_ds, h_qc, h_qs), Wb: the rotor-frame magnet flux's 6th harmonic (:mod:`agent.simulator.plant`)
    of the 5th and 7th space harmonics psi_a = psi_m cos(theta) + psi_5 cos(5 theta + phi_5) +
    psi_7 cos(7 theta + phi_7). ``value``: {"psi_5", "phase_5", "psi_7", "phase_7"} (Wb, rad), or a
    number psi_6: the 5th and the 7th equal, psi_6 / 2 each at phase 0 (psi_pm,d = psi_m + psi_6 cos 6 theta)."""
    if not isinstance(value, dict):
        value = {"psi_5": 0.5 * value, "psi_7": 0.5 * value}
    p5, f5, p7, f7 = (float(value.get(k, 0.0)) for k in ("psi_5", "phase_5", "psi_7", "phase_7"))
    # rotor frame: psi_5 e^{-j(6 theta + phi_5)} + psi_7 e^{+j(6 theta + phi_7)}
    return (p5 * math.cos(f5) + p7 * math.cos(f7), -(p5 * math.sin(f5) + p7 * math.sin(f7)),
            p7 * math.sin(f7) - p5 * math.sin(f5), p7 * math.cos(f7) - p5 * math.cos(f5))


def _delay(x: np.ndarray, d: float, start: int, n: int) -> np.ndarray:
    """``x`` (3, M) delayed by ``d`` samples, samples ``start .. start+n-1`` (windowed sinc); a negative
    ``d`` advances it (the record leads: the samples after it are simulated)."""
    n0 = int(math.floor(d))
    mu = d - n0
    if mu < 1e-12:
        return x[:, start - n0:start - n0 + n].copy()
    m = np.arange(n0 - _TAPS_HALF + 1, n0 + _TAPS_HALF + 1)
    u = m - d
    h = np.sinc(u) * np.i0(_KAISER_BETA * np.sqrt(1.0 - (u / _TAPS_HALF) ** 2)) / np.i0(_KAISER_BETA)
    h /= h.sum()
    y = np.zeros((x.shape[0], n))
    for hm, mm in zip(h, m):
        y += hm * x[:, start - mm:start - mm + n]
    return y


def _check_args(load_pct, seconds, severity, seed):
    # above ~130 % load the i_d = 0 drive runs into its voltage limit at rated speed (no field weakening)
    for name, value, lo, hi in (("load_pct", load_pct, 0.0, 130.0), ("seconds", seconds, 1e-3, 120.0),
                                ("severity", severity, 0.0, 100.0)):
        if not isinstance(value, (int, float)) or not lo <= value <= hi:
            raise InputError(f"{name} must be a number within {lo:g}..{hi:g}, got {value!r}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")


def simulate(profile, condition: str = "healthy", load_pct: float = 80.0, seconds: float = 4.0,
             seed: int = 0, effects=None, encoder: bool = False, severity: float = 1.0,
             rig: RigParams | None = None, load_step: tuple[float, float] | None = None) -> Record:
    """Simulate one steady-state record of the rig at the profile's rated speed.

    ``profile``: DriveProfile or path; ``condition``: a :data:`CONDITIONS` name valid for the
    profile's transmission; ``load_pct``: the torque the motor delivers at its shaft (the generator's load and the
    transmission's friction), % of rated;
    ``effects``: ``{id: magnitude or None (default)}`` or a list of ids (:data:`EFFECTS`);
    ``encoder``: also return the true electrical angle (rad, wrapped to [0, 2 pi)) and speed (rad/s);
    ``severity`` scales the fault ripple and friction increase; ``load_step`` = (t_s, load_pct): the
    load torque steps to ``load_pct`` at ``t_s`` s into the record (the drive's speed loop answers
    it; temperatures stay). Raises InputError on bad names/values.
    """
    if isinstance(profile, (str, Path)):
        profile = load_profile(profile)
    rig = rig or RigParams()
    kind = profile.transmission.kind
    cond = check_condition(condition, kind)
    eff = check_effects(effects)
    _check_args(load_pct, seconds, severity, seed)
    if load_step is not None:
        t_step, load_after = load_step
        _check_args(load_after, seconds, severity, seed)
        if not 0.0 <= t_step <= seconds:
            raise InputError(f"load_step: the step time must be within the record (0..{seconds:g} s), got {t_step!r}")
    if 1.0 + eff.get("resistance_drift", 0.0) * seconds < 0.1:
        raise InputError("effect 'resistance_drift': R_s would fall below 10 % of its value in this record")

    mot = profile.motor
    n_p, T_s, T_rated = mot.pole_pairs, profile.ts, mot.rated_torque_nm
    w_ref = 2.0 * math.pi * mot.rated_speed_rpm / 60.0  # rad/s, mechanical
    w_e = n_p * w_ref
    n_rec = int(round(seconds / T_s))
    n_warm = max(int(round(rig.t_warmup / T_s)), 128)  # >= history of the delay interpolator
    n_tot = n_warm + n_rec + _TAPS_HALF + int(_MAX_LEAD)  # the interpolator reads past the record, a lead further

    # record-level random draws (fixed order and count: same seed -> same ripple/noise for any condition)
    # The rig's geometry (where the defect sits on each part, the phases of the manufacturing ripple)
    # belongs to the machine, not to the record: drawn from rig.geometry_seed.
    geo = np.random.default_rng(rig.geometry_seed)
    phi0 = geo.uniform(0.0, 2.0 * math.pi, 4)  # defect positions on gm, gl, ch, speed-ripple source
    ph = geo.uniform(0.0, 2.0 * math.pi, (3, 3))  # healthy ripple phases per family and k
    rng = np.random.default_rng(seed)
    th1_0 = rng.uniform(0.0, 2.0 * math.pi)
    z_load, z_Tw, z_Tm = rng.standard_normal(3)
    amp_f = rng.uniform(*rig.ripple_spread, (3, 3))
    noise_drive = rng.standard_normal((2, n_tot)) * (rig.sigma_i_drive * math.sqrt(2.0 / 3.0))
    noise_i = rng.standard_normal((3, n_rec)) * rig.sigma_i
    noise_v = rng.standard_normal((3, n_rec)) * rig.sigma_v

    op = operating_point(rig, w_ref, T_rated, load_pct, z_load, z_Tw, z_Tm)
    B_2 = rig.B_2 * (1.0 + severity * (cond.friction - 1.0))
    I_rated = (mot.rated_current_a * math.sqrt(2.0) if mot.rated_current_a
               else T_rated / (1.5 * n_p * rig.psi_m))
    sat = eff.get("magnetic_saturation", 0.0)
    sat_a, psi_qr = saturation(rig.L_q, I_rated, sat) if sat else (0.0, 1.0)
    h6 = flux_harmonic_coefficients(eff.get("flux_harmonics", 0.0))

    # steady state (i_d = 0, mean ripple = 0)
    T_e0 = op.T_L + (rig.B_1 + B_2) * w_ref
    iq0 = T_e0 / (1.5 * n_p * op.psi_m)
    psi_q0 = psi_q_of_i_q(iq0, rig.L_q, sat_a, psi_qr)
    th_e0 = n_p * th1_0
    c6, s6 = math.cos(6.0 * th_e0), math.sin(6.0 * th_e0)
    x0 = np.array([op.psi_m + h6[0] * c6 + h6[1] * s6, psi_q0 + h6[2] * c6 + h6[3] * s6, w_ref, w_ref,
                   th1_0, th1_0 - (op.T_L + B_2 * w_ref) / rig.K_s])
    v_d0, v_q0 = -w_e * psi_q0, op.R_s * iq0 + w_e * op.psi_m
    th_v = th_e0 + 0.5 * w_e * T_s
    c0 = np.array([v_d0 + w_e * rig.L_q * iq0, v_q0 - w_e * rig.psi_m, 1.5 * n_p * rig.psi_m * iq0,
                   v_d0 * math.cos(th_v) - v_q0 * math.sin(th_v), v_d0 * math.sin(th_v) + v_q0 * math.cos(th_v)])

    a_i = 2.0 * math.pi * rig.f_bw_i
    kp_w, ki_w = speed_pi_gains(rig)
    par = np.zeros(P.N_PAR)
    for idx, val in ((P.T_S, T_s), (P.N_SUB, rig.n_sub), (P.N_P, n_p), (P.R_S, op.R_s),
                     (P.R_DRIFT, eff.get("resistance_drift", 0.0)), (P.K_REC, n_warm),
                     (P.L_D, rig.L_d), (P.L_Q0, rig.L_q), (P.PSI_M, op.psi_m), (P.H_DC, h6[0]),
                     (P.H_DS, h6[1]), (P.H_QC, h6[2]), (P.H_QS, h6[3]),
                     (P.SAT_A, sat_a), (P.PSI_QR, psi_qr), (P.J_1, rig.J_1), (P.J_2, rig.J_2),
                     (P.K_S, rig.K_s), (P.C_S, rig.C_s), (P.B_1, rig.B_1), (P.B_2, B_2),
                     (P.T_L0, op.T_L), (P.K_LOAD, rig.k_load), (P.W_REF, w_ref),
                     (P.U_DT, eff.get("inverter_deadtime", 0.0)), (P.U_MAX, rig.u_max),
                     (P.LD_HAT, rig.L_d), (P.LQ_HAT, rig.L_q), (P.PSIM_HAT, rig.psi_m),
                     (P.KP_D, a_i * rig.L_d), (P.KP_Q, a_i * rig.L_q), (P.KI_D, a_i * rig.R_s),
                     (P.KI_Q, a_i * rig.R_s), (P.KP_W, kp_w), (P.KI_W, ki_w), (P.T_MAX, rig.T_max_rel * T_rated),
                     (P.K_STEP, math.inf if load_step is None else n_warm + round(load_step[0] / T_s)),
                     (P.DT_STEP, 0.0 if load_step is None else (load_step[1] - load_pct) / 100.0 * T_rated)):
        par[idx] = val
    terms = _terms(profile, cond, severity, (amp_f, ph, phi0), eff.get("speed_ripple", 0.0))

    i_ab, v_ab, vref_ab = (np.empty((2, n_tot)) for _ in range(3))
    theta, omega = np.empty(n_tot), np.empty(n_tot)
    P.run(np.array(P.derived(par)), x0, c0, terms, noise_drive, i_ab, v_ab, vref_ab, theta, omega)

    # data acquisition
    rec = slice(n_warm, n_warm + n_rec)
    to_abc = CLARKE_INV[:, :2]
    i_abc = to_abc @ i_ab[:, rec]
    a_off = eff.get("current_offset", 0.0)
    i_abc += np.array([a_off, -0.5 * a_off, -0.5 * a_off])[:, None]
    i_abc[1] *= 1.0 + eff.get("current_gain_mismatch", 0.0)
    i_abc += noise_i
    reference = profile.sampling.voltage_source == "reference"
    v_full = to_abc @ (vref_ab if reference else v_ab)
    v_abc = _delay(v_full, eff.get("voltage_delay", 0.0), n_warm, n_rec)
    if not reference:
        v_abc += noise_v

    meta = _meta(profile, condition, load_pct, seconds, seed, severity, eff, rig, op, B_2, T_e0, iq0, psi_q0,
                 sat_a, psi_qr, w_ref)
    if load_step is not None:
        meta.update(load_step_s=float(load_step[0]), load_pct_after=float(load_step[1]))
    if "speed_ripple" in eff:  # omega_e ripple at f_gm: least-squares fit on the shaft angle
        th1 = theta[rec] / n_p + phi0[3]
        A = np.column_stack((np.ones(n_rec), np.sin(th1), np.cos(th1)))
        coef = np.linalg.lstsq(A, omega[rec], rcond=None)[0]
        meta["speed_ripple_omega_e"] = float(np.hypot(coef[1], coef[2]))
    return Record(t=np.arange(n_rec) * T_s, v_abc=v_abc, i_abc=i_abc,
                  theta_e=np.mod(theta[rec], 2.0 * math.pi) if encoder else None,
                  omega_e=omega[rec].copy() if encoder else None,
                  source=f"<simulator {profile.name} {condition} seed={seed}>", meta=meta)


def _meta(profile, condition, load_pct, seconds, seed, severity, eff, rig, op, B_2, T_e0, iq0, psi_q0,
          sat_a, psi_qr, w_ref) -> dict:
    """Flat str/float/int annotations: inputs and the true parameters in effect (SI units)."""
    L_q = psi_q0 / iq0 if iq0 else rig.L_q
    L_q_incr = rig.L_q / (1.0 + 3.0 * sat_a * (psi_q0 / psi_qr) ** 2)
    meta = {
        "simulator": "agent.simulator", "profile": profile.name, "condition": condition,
        "load_pct": float(load_pct), "seconds": float(seconds), "seed": int(seed), "severity": float(severity),
        "voltage_source": profile.sampling.voltage_source, "effects": ",".join(eff),
        "R_s": op.R_s, "R_s_end": op.R_s * (1.0 + eff.get("resistance_drift", 0.0) * seconds),
        "L_d": rig.L_d, "L_q": L_q, "L_q_incr": L_q_incr, "L_q0": rig.L_q, "psi_m": op.psi_m,
        "T_winding_c": op.T_w, "T_magnet_c": op.T_m,
        "J_1": rig.J_1, "J_2": rig.J_2, "K_s": rig.K_s, "B_1": rig.B_1, "B_2": B_2,
        "B_GT": rig.B_1 + B_2, "T_load": op.T_L, "T_e": T_e0, "B_GT_equiv": T_e0 / w_ref,
        "i_q": iq0, "P_in": T_e0 * w_ref + 1.5 * op.R_s * iq0 ** 2, "omega_m": w_ref,
    }
    meta["fe_hz"] = profile.rated_fe_hz
    meta.update({f"f_{k}_hz": v for k, v in base_frequencies(profile).items()})
    for name, value in eff.items():
        if isinstance(value, dict):
            meta.update({f"effect.{name}.{k}": v for k, v in value.items()})
        else:
            meta[f"effect.{name}"] = value
    return {k: float(v) if isinstance(v, (float, np.floating)) else v for k, v in meta.items()}
