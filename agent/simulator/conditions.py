"""Transmission conditions (paper section 4.2, Figs. 5-6) and effects for the model workbench (CONTRACT 5).

Transmission faults are modelled as two physical changes, tabulated in :data:`CONDITIONS` so the
Table 4 pattern can be tuned in one place:

* a mesh torque ripple (transmission error), N m referred to the motor shaft, acting on the driven
  side of the mesh and periodic in the angle of the rotating part that carries the defect
  (family ``gm``: motor shaft / driving gear, f_gm = f_e/n_p, eq. 19; ``gl``: driven gear or
  sprocket, f_gl = f_gm/g_r, eq. 20; ``ch``: chain loop, f_ch = 2 pi r_m f_gm / l_ch, eq. 21).
  A damaged tooth is a zero-mean Gaussian pulse once per revolution (:class:`Pulse`, harmonic k
  has amplitude ``peak * width * sqrt(2/pi) * exp(-(k width)^2/2)``), a distributed defect a set of
  sinusoidal harmonics (:class:`Harmonics`);
* a friction change: ``friction`` multiplies B_2 (transmission + load-side viscous friction),
  which raises the shaft torque, the input power and the paper's B_GT.

A healthy transmission also has a mesh ripple (manufacturing tolerance, :data:`HEALTHY_RIPPLE`)
whose amplitudes vary from record to record (uniform in ``RigParams.ripple_spread`` x base); its
phases and the defect positions are the machine's geometry (``RigParams.geometry_seed``). ``severity`` scales the fault ripple amplitudes and the friction increase ``friction - 1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent.errors import InputError


@dataclass(frozen=True)
class Pulse:
    """Zero-mean Gaussian torque pulse once per revolution of ``family`` (a damaged tooth)."""

    family: str  #: "gm", "gl" or "ch"
    peak_nm: float  #: N m, pulse height (motor side)
    width_rad: float  #: rad of the part's revolution, standard deviation of the pulse


@dataclass(frozen=True)
class Harmonics:
    """Sinusoidal torque harmonics k = 1, 2, ... of the rotation of ``family``."""

    family: str  #: "gm", "gl" or "ch"
    amp_nm: tuple[float, ...]  #: N m (motor side), amplitude of harmonic k = 1, 2, ...


@dataclass(frozen=True)
class Condition:
    kind: str | None  #: "gear", "chain" or None (any transmission)
    friction: float  #: multiplier on B_2
    ripple: tuple  #: Pulse / Harmonics terms added to the healthy ripple
    note: str = ""


#: Healthy mesh ripple base amplitudes, N m (motor side) for k = 1, 2, 3, per transmission kind and family.
#: Rated torque is 14 N m, so 0.05 N m is 0.36 % of rated.
HEALTHY_RIPPLE = {
    "gear": {"gm": (0.03, 0.015, 0.01), "gl": (0.05, 0.035, 0.025)},
    "chain": {"gm": (0.03, 0.015, 0.01), "gl": (0.04, 0.03, 0.02), "ch": (0.05, 0.035, 0.025)},
}
FAMILIES = ("gm", "gl", "ch")

#: The tunable fault table (amplitudes in N m at the motor shaft, severity = 1).
CONDITIONS: dict[str, Condition] = {
    "healthy": Condition(None, 1.0, (), "manufacturing-tolerance ripple only"),
    # one worn driven-gear tooth: a wide, shallow pulse per driven revolution, k = 1..3 ~ 0.074, 0.009,
    # 0.0002 N m (the paper's Fig. 8a shows only the k = 1 sidebands 87.5 / 112.5 Hz)
    "gear_slight_wear": Condition("gear", 1.0, (Pulse("gl", 0.16, 1.2),),
                                  "worn spot on one driven-gear tooth"),
    # wear along a whole tooth: larger, narrower pulse (k = 1..3 ~ 0.25, 0.17, 0.09 N m), more mesh loss
    "gear_severe_wear": Condition("gear", 1.5, (Pulse("gl", 0.71, 0.5),),
                                  "tooth worn along its face, extra sliding loss"),
    # the same wear on one tooth of the driving gear (on the motor shaft): a pulse per motor revolution,
    # k = 1..3 ~ 0.25, 0.17, 0.09 N m at f_gm (not one of the paper's conditions: the family verdict's test)
    "gear_driving_wear": Condition("gear", 1.5, (Pulse("gm", 0.71, 0.5),),
                                   "tooth of the driving gear worn along its face"),
    # dry mesh: friction x2.5; the friction amplifies the gear's ovality (twice per driven revolution)
    "gear_no_lubricant": Condition("gear", 2.5, (Harmonics("gl", (0.03, 0.15, 0.03)),),
                                   "no lubricant on either gear"),
    # misaligned sprockets: driven-sprocket wobble once per revolution, chain side plates rubbing the
    # sprocket flanks (k = 2 of the chain loop dominant, shaped on the paper's Fig. 10a)
    "chain_offset": Condition("chain", 1.6, (Harmonics("gl", (0.2,)), Harmonics("ch", (0.05, 0.15, 0.03))),
                              "chain offset from driving to driven sprocket"),
    # incipient sprocket-tooth wear: mostly friction, tiny ripple (k = 1 ~ 0.04 N m)
    "chain_slight_wear": Condition("chain", 1.5, (Pulse("gl", 0.08, 0.8),),
                                   "slightly worn driven-sprocket tooth"),
    # missing tooth: the chain jumps once per driven revolution (k = 1..3 ~ 0.29, 0.23, 0.16 N m) and
    # the slack it leaves travels with the chain loop (k = 1..3 ~ 0.24, 0.19, 0.12 N m)
    "chain_missing_tooth": Condition("chain", 1.8, (Pulse("gl", 1.0, 0.4), Pulse("ch", 0.8, 0.4)),
                                     "one missing tooth on the driven sprocket"),
}


@dataclass(frozen=True)
class EffectSpec:
    default: float
    unit: str
    doc: str


#: Physical effects the baseline model (eq. 6) lacks; ``simulate(effects={id: magnitude})``.
EFFECTS: dict[str, EffectSpec] = {
    "inverter_deadtime": EffectSpec(
        6.0, "V", "dead-time + device drop: dv_x = -U_dt sign(i_x) per phase, common mode removed "
        "(U_dt ~ U_dc t_dead f_sw); only visible as a model error with voltage_source='reference', "
        "a measured terminal voltage already contains it"),
    "flux_harmonics": EffectSpec(
        0.005, "Wb", "5th/7th rotor-flux space harmonics: psi_a = psi_m cos(theta) + psi_5 cos(5 theta + phi_5) + "
        "psi_7 cos(7 theta + phi_7); a number psi_6 means psi_5 = psi_7 = psi_6/2 at phase 0 (psi_pm,d = psi_m + "
        "psi_6 cos(6 theta_e)), a dict {psi_5, phase_5, psi_7, phase_7} (Wb, rad) sets each"),
    "voltage_delay": EffectSpec(
        1.0, "samples", "voltage channel lags the current channel by d samples (DAQ filter delays), "
        "fractional delays by a Kaiser-windowed sinc interpolator (32 taps)"),
    "current_offset": EffectSpec(
        0.05, "A", "DAQ current-sensor offsets (a, -a/2, -a/2) on phases a, b, c (a DC alpha-axis "
        "vector of magnitude a; drive control unaffected)"),
    "current_gain_mismatch": EffectSpec(
        0.03, "-", "relative gain error of the DAQ phase-b current sensor (i_b x (1 + g))"),
    "resistance_drift": EffectSpec(
        0.05, "1/s", "warming winding: R_s(t) = R_s (1 + r t) during the record, t from 0"),
    "magnetic_saturation": EffectSpec(
        0.15, "-", "q-axis saturation, i_q = psi_q/L_q0 (1 + a (psi_q/psi_qr)^2): fractional drop of "
        "L_q = psi_q/i_q at rated current"),
    "speed_ripple": EffectSpec(
        0.5, "N m", "load-torque oscillation T sin(theta_m + phi) on the motor shaft (f_gm, e.g. "
        "coupling misalignment); the resulting omega_e ripple is in meta['speed_ripple_omega_e']"),
}

_MAX_DELAY = 64.0  # samples
_MAX_LEAD = 4.0  # samples a voltage may lead (the simulation runs past the record by the interpolator's half length)
_HARMONIC_KEYS = ("psi_5", "phase_5", "psi_7", "phase_7")


def _check_harmonics(value: dict) -> dict[str, float]:
    """A flux_harmonics dict {psi_5, phase_5, psi_7, phase_7} (Wb, rad; missing: 0) validated."""
    bad = [k for k in value if k not in _HARMONIC_KEYS]
    if bad:
        raise InputError(f"effect 'flux_harmonics': unknown key {bad[0]!r} (known: {', '.join(_HARMONIC_KEYS)})")
    try:
        out = {k: float(value.get(k, 0.0)) for k in _HARMONIC_KEYS}
    except (TypeError, ValueError):
        raise InputError(f"effect 'flux_harmonics': values must be numbers, got {value!r}") from None
    if not all(np.isfinite(list(out.values()))) or out["psi_5"] < 0 or out["psi_7"] < 0:
        raise InputError("effect 'flux_harmonics': amplitudes must be finite and >= 0, phases finite")
    return out


def conditions_for(kind: str) -> list[str]:
    """Condition names valid for a transmission kind."""
    return [n for n, c in CONDITIONS.items() if c.kind in (None, kind)]


def check_condition(name: str, kind: str) -> Condition:
    if name not in CONDITIONS:
        raise InputError(f"unknown condition '{name}' (known: {', '.join(CONDITIONS)})")
    cond = CONDITIONS[name]
    if cond.kind not in (None, kind):
        raise InputError(f"condition '{name}' needs a {cond.kind} transmission, the profile has a {kind} "
                         f"(valid: {', '.join(conditions_for(kind))})")
    return cond


def check_effects(effects) -> dict[str, float]:
    """``None`` / ``{id: magnitude or None}`` / iterable of ids -> ``{id: magnitude}`` (validated)."""
    if effects is None:
        return {}
    if isinstance(effects, str):
        effects = [effects]
    items = effects.items() if isinstance(effects, dict) else ((e, None) for e in effects)
    out = {}
    for name, value in items:
        if name not in EFFECTS:
            raise InputError(f"unknown effect '{name}' (known: {', '.join(EFFECTS)})")
        value = EFFECTS[name].default if value is None else value
        if name == "flux_harmonics" and isinstance(value, dict):
            out[name] = _check_harmonics(value)
            continue
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise InputError(f"effect '{name}': magnitude must be a number, got {value!r}") from None
        if value != value or abs(value) == float("inf"):
            raise InputError(f"effect '{name}': magnitude must be finite")
        if name == "voltage_delay" and not -_MAX_LEAD <= value <= _MAX_DELAY:
            raise InputError(f"effect 'voltage_delay': delay must be within -{_MAX_LEAD:g}..{_MAX_DELAY:g} samples")
        if name == "magnetic_saturation" and not 0.0 <= value < 0.9:
            raise InputError("effect 'magnetic_saturation': L_q drop must be within 0..0.9")
        if name in ("inverter_deadtime", "flux_harmonics", "speed_ripple") and value < 0:
            raise InputError(f"effect '{name}': magnitude must be >= 0")
        out[name] = value
    return out
