"""The hidden effects: each drawn from its whole physical family, its truth in the workbench's units,
and whether records can reveal it at all.

A draw is a JSON-able dict (:func:`draw_effect`); ``simulate(drive, {id: draw, ...}, ...)`` puts it
into the machine, the inverter, the sensors or the shaft. A drive with no effect drawn (a null
drive) has a linear machine with a sinusoidal magnet flux, an ideal inverter (no dead time, no
device drop), ideal sensor gains and zero offsets (white noise and ADC quantisation only), a
constant winding temperature and a smooth load -- but its own voltage path (hold, computation delay,
angle compensation, command logging or the measured voltage's averaging window), which is part
of the drive and which the base model must cope with.

Ranges (a size a good engineer would consider realistic and detectable):

======================  =============================================================================
effect                  draw
======================  =============================================================================
flux_harmonics          phase-a magnet flux psi_m cos(th) + sum psi_h cos(h th + phi_h): the 5th
                        alone, the 7th alone, 5th + 7th, or 5th + 7th + 11th + 13th; log-uniform
                        psi_5 0.5-3 %, psi_7 0.3-2 %, psi_11, psi_13 0.1-0.6 % of psi_m (back-EMF
                        harmonics h psi_h of 1-15 % of the fundamental); phases uniform
inverter_deadtime       switched inverter: dead time t_d 0.5-4 us (capped at 18 V of U_dc t_d f_sw)
                        and a device drop 0.7-2.5 V, each edge delayed by the phase current's sign
                        at that edge; averaged inverter: U_dt 2-20 V with a knee from the PWM ripple
                        (1-2 U_dc/(24 L_d f_sw), the knees the switched inverter shows; within
                        0.2-10 % of rated current)
voltage_delay           an extra voltage-channel delay of -1..+2 samples (|d| >= 0.25; fractional by
                        linear interpolation between samples), on top of the drive's own path
current_offset          per-phase sensor offsets, each 0.5-3 % of rated peak current with a random
                        sign (one phase without an offset in a third of the draws)
current_gain_mismatch   phase a's gain 1 +- 1 %, phases b and c 1-5 % off phase a (one of them
                        matched in a third of the draws)
resistance_drift        the winding warms in each record: R_s grows at 0.4-8 %/s at the record's
                        start (1-20 % over 2.5 s), a first-order thermal response (tau 20-200 s,
                        at most 150 K above the start); each record starts 0-(5-30) K warmer than
                        the drive's winding temperature
magnetic_saturation     the flux map of bench.family.machine: chord L_q drop at rated current 5-30 %
                        (self-saturation exponent n 1.5-4), cross-saturation lowering psi_d by 0-6 %
                        at rated i_q, L_d 0-12 % larger at -rated i_d
speed_ripple            a once-per-revolution load torque (coupling misalignment, unbalance)
                        2-15 % of rated torque
======================  =============================================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.optimize

from bench.family.drive import COPPER_PER_K, Drive
from bench.family.machine import flux_from_currents, flux_map, is_convex

SQRT3 = math.sqrt(3.0)
HARMONIC_MIXES = ((5,), (7,), (5, 7), (5, 7, 11, 13))
#: psi_h / psi_m per order: back-EMF harmonics h psi_h of 2.5-15 % (5th), 2-14 % (7th), 1-8 % (11th,
#: 13th) of the fundamental, from distributed to concentrated windings
HARMONIC_SHARE = {5: (0.005, 0.03), 7: (0.003, 0.02), 11: (0.001, 0.006), 13: (0.001, 0.006)}


@dataclass(frozen=True)
class EffectFamily:
    id: str
    draw: Callable[[Drive, np.random.Generator], dict]
    doc: str


def _draw_flux_harmonics(drive: Drive, rng) -> dict:
    orders = HARMONIC_MIXES[int(rng.integers(len(HARMONIC_MIXES)))]
    share = [math.exp(rng.uniform(*np.log(HARMONIC_SHARE[h]))) for h in orders]  # log-uniform
    return {"orders": list(orders), "psi_wb": [s * drive.psi_m_wb for s in share],
            "phase_rad": [float(p) for p in rng.uniform(0, 2 * np.pi, len(orders))]}


def _draw_deadtime(drive: Drive, rng) -> dict:
    if drive.inverter == "switched":
        t_dead = min(rng.uniform(0.5e-6, 4e-6), 18.0 / (drive.u_dc_v * drive.switching_hz))
        return {"t_dead_s": t_dead, "u_on_v": rng.uniform(0.7, 2.5)}
    ripple = drive.u_dc_v / (24.0 * drive.ld_h * drive.switching_hz)
    knee = float(np.clip(rng.uniform(1.0, 2.0) * ripple, 0.002 * drive.i_rated_peak, 0.1 * drive.i_rated_peak))
    return {"U_dt_v": rng.uniform(2.0, 20.0), "knee_a": knee}


def _draw_voltage_delay(drive: Drive, rng) -> dict:
    extra = rng.uniform(0.25, 2.0) if rng.random() < 0.6 else -rng.uniform(0.25, 1.0)
    return {"extra_samples": extra}


def _draw_offset(drive: Drive, rng) -> dict:
    size = rng.uniform(0.005, 0.03, 3) * rng.choice([-1.0, 1.0], 3) * drive.i_rated_peak
    if rng.random() < 1 / 3:
        size[int(rng.integers(3))] = 0.0
    return {"offset_a": [float(s) for s in size]}


def _draw_gain(drive: Drive, rng) -> dict:
    g_a = rng.uniform(-0.01, 0.01)
    rel = rng.uniform(0.01, 0.05, 2) * rng.choice([-1.0, 1.0], 2)
    if rng.random() < 1 / 3:
        rel[int(rng.integers(2))] = 0.0
    return {"gain_error": [float(g) for g in (g_a, (1 + g_a) * (1 + rel[0]) - 1, (1 + g_a) * (1 + rel[1]) - 1)]}


def _draw_drift(drive: Drive, rng) -> dict:
    rate = rng.uniform(0.004, 0.08)  # relative R_s growth per second at the record's start
    slope_k = rate / copper_coefficient_at(drive.winding_temp_c)  # K/s
    tau = min(rng.uniform(20.0, 200.0), 150.0 / slope_k)
    return {"initial_rate_per_s": rate, "tau_s": tau, "rise_k": slope_k * tau,
            "start_spread_k": rng.uniform(5.0, 30.0)}


def copper_coefficient_at(temp_c: float) -> float:
    """(dR/dT)/R of copper at ``temp_c``, 1/K."""
    return COPPER_PER_K / (1.0 + COPPER_PER_K * (temp_c - 20.0))


def saturation_map(drive: Drive, draw: dict) -> np.ndarray:
    """The drive's flux map with the saturation ``draw`` (see bench.family.machine)."""
    i_r = drive.i_rated_peak
    ld, lq, psi_m = drive.ld_h, drive.lq_h, drive.psi_m_wb
    beta = draw["ld_rise_at_rated"] / (ld * ld * i_r)
    c = draw["psi_d_drop_at_rated"] * psi_m / (ld * (lq * i_r) ** 2)
    return flux_map(ld, lq, psi_m, beta, draw["alpha"], draw["n"], lq * i_r, c)


def lq_drop_at_rated(drive: Drive, fm: np.ndarray) -> float:
    """1 - psi_q(i_d = 0, I_rated)/(L_q I_rated): the chord L_q drop at rated peak current."""
    i_r = drive.i_rated_peak
    return 1.0 - flux_from_currents(0.0, i_r, fm)[1] / (drive.lq_h * i_r)


def _draw_saturation(drive: Drive, rng) -> dict:
    target = rng.uniform(0.05, 0.30)
    draw = {"n": rng.uniform(1.5, 4.0), "psi_d_drop_at_rated": rng.uniform(0.0, 0.06),
            "ld_rise_at_rated": rng.uniform(0.0, 0.12), "alpha": 0.0}
    for _ in range(8):  # shrink the cross and d terms until the target is reachable and the energy is
        def drop(alpha):  # convex over 2.5 rated current
            return lq_drop_at_rated(drive, saturation_map(drive, {**draw, "alpha": alpha})) - target

        if drop(0.0) < 0.0 < drop(100.0):
            draw["alpha"] = scipy.optimize.brentq(drop, 0.0, 100.0)
            if is_convex(saturation_map(drive, draw), 2.5 * drive.i_rated_peak):
                return draw
        draw["psi_d_drop_at_rated"] *= 0.5
        draw["ld_rise_at_rated"] *= 0.5
    raise RuntimeError(f"no convex flux map for drive {drive.seed}")


def _draw_speed_ripple(drive: Drive, rng) -> dict:
    return {"torque_nm": rng.uniform(0.02, 0.15) * drive.rated_torque_nm, "phase_rad": rng.uniform(0, 2 * np.pi)}


EFFECTS: dict[str, EffectFamily] = {f.id: f for f in (
    EffectFamily("flux_harmonics", _draw_flux_harmonics, "magnet flux space harmonics 5, 7 (11, 13)"),
    EffectFamily("inverter_deadtime", _draw_deadtime, "dead time and device drop of the inverter"),
    EffectFamily("voltage_delay", _draw_voltage_delay, "an extra delay of the voltage channel"),
    EffectFamily("current_offset", _draw_offset, "DC offsets of the phase-current sensors"),
    EffectFamily("current_gain_mismatch", _draw_gain, "gain errors of the phase-current sensors"),
    EffectFamily("resistance_drift", _draw_drift, "the winding warming within and between records"),
    EffectFamily("magnetic_saturation", _draw_saturation, "self- and cross-saturation from one energy"),
    EffectFamily("speed_ripple", _draw_speed_ripple, "a once-per-revolution shaft torque"),
)}


def draw_effect(drive: Drive, effect_id: str, seed: int) -> dict:
    """A draw of ``effect_id`` for ``drive`` from ``seed`` (JSON-able; ranges in the module docstring)."""
    if effect_id not in EFFECTS:
        raise KeyError(f"unknown effect {effect_id!r} (known: {', '.join(EFFECTS)})")
    return EFFECTS[effect_id].draw(drive, np.random.default_rng([seed, drive.seed, list(EFFECTS).index(effect_id)]))


# ------------------------------------------------------------------------------------ truth


def voltage_path(drive: Drive, extra_samples: float = 0.0) -> tuple[float, float]:
    """(delay_samples, advance_samples) of the reported voltage against the applied one.

    With v(k) the phase-to-neutral voltage averaged over [t_k, t_k + T_s] and a dq value the
    Park transform of an abc value at the interval's mid angle theta(t_k + T_s/2):

        v_applied,dq(k - d) = exp(j (d + a) omega_e T_s) v_reported,dq(k)

    i.e. v_reported(k) = v_applied(k - d) in abc when a = 0 (d > 0: the report lags); a is any
    rotation of the applied voltage beyond that delay, in units of omega_e T_s.

    * measured voltage: d = the averaging window's lag, a = 0;
    * reported command, abc hold: d = -computation delay; a = 0 when the phase commands are logged
      (they are what the modulator applies), a = c when the dq command is logged at the sample's
      angle and the controller turns it forward by c omega_e T_s (c = delay + 0.5, or 0 without
      angle compensation);
    * reported command, dq hold (a continuous inverter holds the rotor-frame command over the
      interval): d = -computation delay, a = delay + 0.5 (the report is the command at the sample's
      angle, the applied voltage's interval average sits at the mid angle of its interval).

    ``extra_samples`` (the voltage_delay effect) adds to d."""
    if drive.voltage_source == "measured":
        return drive.voltage_filter_delay + extra_samples, 0.0
    delay = float(drive.computation_delay)
    if drive.voltage_hold == "dq":
        advance = delay + 0.5
    elif drive.command_logged_as == "dq" and drive.angle_compensation:
        advance = delay + 0.5
    else:
        advance = 0.0
    return -delay + extra_samples, advance


def truth(drive: Drive, effect_id: str, draw: dict, records) -> dict:
    """The true value of an effect in the workbench's units.

    * current_offset: ``offset_A`` = |(alpha, beta)| of the per-phase offsets (amplitude-invariant
      Clarke, alpha = (2 o_a - o_b - o_c)/3, beta = (o_b - o_c)/sqrt 3), ``offset_abc_A``, and
      ``offset_voltage_V`` = R_s offset_A, the stator-frame DC voltage that holds -o in the winding
      (the controller acts on the offset sensors);
    * current_gain_mismatch: ``gain_b``, ``gain_c`` = (1 + g_x)/(1 + g_a) - 1;
    * resistance_drift: ``dR_dt_ohm_per_s`` = dR_s/dt at each record's middle, mean over ``records``
      (their meta), and ``R_s_start_ohm`` (mean);
    * voltage_delay: ``delay_samples``, ``advance_samples`` (:func:`voltage_path`, extra delay included);
    * flux_harmonics: ``psi_<h>_Wb`` and ``phase_<h>_rad`` per phase-a order h (psi_h cos(h theta +
      phi_h)); ``psi_6d_Wb``, ``psi_6q_Wb``: the amplitudes of the 6th harmonic of the rotor-frame
      magnet flux on d (|psi_5 e^{j phi_5} + psi_7 e^{j phi_7}|) and q (|psi_7 e^{j phi_7} - psi_5 e^{j phi_5}|);
    * inverter_deadtime: ``U_dt_V`` = U_dc t_d f_sw + device drop (switched) or the drawn U_dt
      (averaged), the mean phase-voltage loss U_dt sign(i) away from zero current; ``knee_A``: the
      knee of the loss U_dt clip(i/knee) (common mode removed) over the interval's mean current:
      drawn for the averaged inverter; for the switched one fitted with U_dt (least squares) to the
      records' per-interval loss of the applied voltage against the command (records' meta, mean),
      with ``edge_ripple_A``, the mean |carrier ripple| of the phase current at its switching edges;
    * magnetic_saturation: ``lq_drop_at_rated`` = 1 - psi_q(0, I_rated)/(L_q I_rated) (I_rated peak),
      and ``psi_d_drop_at_rated`` = 1 - psi_d(0, I_rated)/psi_m;
    * speed_ripple: ``omega_e_ripple_rad_s``: the amplitude of the true omega_e at the shaft's
      rotation frequency (least squares on each record), mean over the records."""
    metas = [r.meta for r in records]
    if effect_id == "current_offset":
        o = np.asarray(draw["offset_a"])
        alpha, beta = (2 * o[0] - o[1] - o[2]) / 3.0, (o[1] - o[2]) / SQRT3
        return {"offset_A": float(math.hypot(alpha, beta)), "offset_abc_A": [float(x) for x in o],
                "offset_voltage_V": float(math.hypot(alpha, beta)) * drive.rs_ohm}
    if effect_id == "current_gain_mismatch":
        g = draw["gain_error"]
        return {"gain_b": (1 + g[1]) / (1 + g[0]) - 1, "gain_c": (1 + g[2]) / (1 + g[0]) - 1}
    if effect_id == "resistance_drift":
        return {"dR_dt_ohm_per_s": float(np.mean([m["dR_dt_mid_ohm_per_s"] for m in metas])),
                "R_s_start_ohm": float(np.mean([m["R_s_start_ohm"] for m in metas]))}
    if effect_id == "voltage_delay":
        d, a = voltage_path(drive, draw.get("extra_samples", 0.0))
        return {"delay_samples": d, "advance_samples": a}
    if effect_id == "flux_harmonics":
        out = {}
        phasor = {}
        for h, psi, phi in zip(draw["orders"], draw["psi_wb"], draw["phase_rad"]):
            out[f"psi_{h}_Wb"], out[f"phase_{h}_rad"] = psi, phi
            phasor[h] = psi * np.exp(1j * phi)
        out["psi_6d_Wb"] = float(abs(phasor.get(5, 0) + phasor.get(7, 0)))
        out["psi_6q_Wb"] = float(abs(phasor.get(7, 0) - phasor.get(5, 0)))
        return out
    if effect_id == "inverter_deadtime":
        if drive.inverter == "switched":
            return {"U_dt_V": drive.u_dc_v * draw["t_dead_s"] * drive.switching_hz + draw["u_on_v"],
                    "knee_A": float(np.mean([m["deadtime_knee_A"] for m in metas])) if metas else float("nan"),
                    "edge_ripple_A": float(np.mean([m["edge_ripple_A"] for m in metas])) if metas else float("nan")}
        return {"U_dt_V": draw["U_dt_v"], "knee_A": draw["knee_a"]}
    if effect_id == "magnetic_saturation":
        fm = saturation_map(drive, draw)
        i_r = drive.i_rated_peak
        return {"lq_drop_at_rated": lq_drop_at_rated(drive, fm),
                "psi_d_drop_at_rated": 1.0 - flux_from_currents(0.0, i_r, fm)[0] / drive.psi_m_wb}
    if effect_id == "speed_ripple":
        return {"omega_e_ripple_rad_s": float(np.mean([m["omega_e_ripple_rad_s"] for m in metas]))}
    raise KeyError(f"unknown effect {effect_id!r}")


def revealable(drive: Drive, effect_id: str, loads, excitation: str | None = None) -> tuple[bool, str]:
    """Whether records of ``drive`` at ``loads`` (% of rated torque) under ``excitation`` (None: the
    drive's own) can reveal ``effect_id`` at all, and why (physics, not the workbench's power)."""
    excitation = excitation or drive.excitation
    levels = len({round(float(x), 6) for x in loads})
    moves_current = levels >= 2 or excitation == "load_step" or (
        excitation == "speed_step" and drive.mechanics == "speed_loop")
    if effect_id == "inverter_deadtime":
        if drive.voltage_source == "measured":
            return False, "the measured terminal voltage already contains the dead-time loss"
        return True, "the voltage command lacks U_dt sign(i): 6k harmonics locked to the current's zero crossings"
    if effect_id == "voltage_delay":
        lag = drive.voltage_filter_delay
        if drive.inverter == "switched" and drive.voltage_source == "measured" and abs(lag - round(lag)) > 0.05:
            return False, ("the measured voltage's window straddles two PWM periods and cuts their pulses: its "
                           "effective delay follows the duty cycle, so a change of the path cannot be told from it")
        if levels >= 2 or excitation != "constant":
            return True, "the operating point changes: a delay is no longer one fixed rotation of the voltage"
        return False, "at one constant operating point a delay is one rotation omega_e d T_s of a constant voltage, absorbed by R_s, L and psi_m"
    if effect_id == "magnetic_saturation":
        if moves_current:
            return True, "the current takes two or more levels: the flux is not proportional to it"
        return False, "one current level: a saturated inductance is indistinguishable from a smaller constant one"
    if effect_id == "speed_ripple":
        if drive.encoder:
            return False, "the encoder's omega_e carries the ripple: the model is fed it"
        return True, "without an encoder the shaft-frequency speed ripple is missing from the model's speed"
    if effect_id == "current_gain_mismatch":
        if max(abs(float(x)) for x in loads) == 0.0:
            return False, "no current, no gain error"
        return True, "an unbalanced current measurement is a 2 f_e component in dq"
    if effect_id in ("current_offset", "flux_harmonics", "resistance_drift"):
        return True, {"current_offset": "an offset is an f_e component in dq at any speed",
                      "flux_harmonics": "the magnet's 5th/7th give a 6 f_e back-EMF in dq at any speed",
                      "resistance_drift": "R_s changes within each record while the current stays"}[effect_id]
    raise KeyError(f"unknown effect {effect_id!r}")
