"""Drive profile: motor nameplate, sampling and transmission geometry (CONTRACT section 4).

A profile is a small TOML file; every key is checked, unknown keys are an error that names the
key path, and the values land in frozen dataclasses.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, fields
from pathlib import Path

from agent.errors import InputError, read_toml


@dataclass(frozen=True)
class Motor:
    """Nameplate of the driving PMSM (paper Table 2)."""

    pole_pairs: int
    rated_power_w: float
    rated_torque_nm: float
    rated_speed_rpm: float
    rated_voltage_v: float | None = None  #: line-to-line rms, optional
    rated_current_a: float | None = None  #: phase rms, optional

    @property
    def i_rated_peak(self) -> float | None:
        """Rated phase current, A peak (the dq current vector's magnitude at rating)."""
        return None if self.rated_current_a is None else self.rated_current_a * math.sqrt(2.0)

    @property
    def z_base_ohm(self) -> float | None:
        """Rated impedance V_phase / I_phase (rms), ohm."""
        if self.rated_voltage_v is None or self.rated_current_a is None:
            return None
        return self.rated_voltage_v / math.sqrt(3.0) / self.rated_current_a

    @property
    def psi_m_from_rating(self) -> float | None:
        """Magnet flux linkage the rated torque needs at the rated current with i_d = 0, Wb
        (T = 1.5 p psi_m i_q): reluctance torque only lowers it."""
        i = self.i_rated_peak
        return None if i is None else self.rated_torque_nm / (1.5 * self.pole_pairs * i)


@dataclass(frozen=True)
class Sampling:
    rate_hz: float
    voltage_source: str = "measured"  #: "measured" or "reference" (drive's voltage command)
    #: the voltage path where the drive's timing is known (agent.voltage_path): the reported
    #: voltage is the applied one delayed by this many samples (signed: -1 for a drive reporting its
    #: command one computation period before applying it; a filter's lag > 0) ...
    voltage_delay_samples: float | None = None
    #: ... and turned back by this many samples of omega_e T_s (1.5 for a voltage held in dq, or an
    #: angle compensation, after one computation period)
    voltage_advance_samples: float | None = None
    #: the current ADC's averaging window, samples, centred on the sample instant (0: a point sample
    #: at the carrier's centre; 1: a sigma-delta or oversampling ADC averaging the whole interval)
    current_window_samples: float | None = None
    #: the drive's current reference where known: "id0" (i_d = 0: the current vector on the rotor's q
    #: axis) or "mtpa" (it leads q by the current angle, which grows with the load); without an
    #: encoder the workbench turns the current's frame onto the rotor's only for "mtpa"
    current_reference: str | None = None
    #: whose current samples the records carry: "controller" (the drive's own, which its current loop
    #: acts on: a drive trace) or "independent" (a separate DAQ's sensors or channels); a controller
    #: without computation delay answers its own samples' noise within the sample, which identify
    #: must know to read the inductances (agent.physical._dynamics)
    current_source: str | None = None
    #: the inverter: "pwm" (it switches the DC link: what a measured terminal voltage averages) or
    #: "continuous" (a linear amplifier, or a simulation's averaged inverter); not stated: PWM
    inverter: str = "pwm"
    #: the drive's voltage update rate, Hz (its current loop's: PWM updates the duty cycles once or twice
    #: per carrier). Only needed where the records' current is not the controller's own samples
    #: (current_source = "independent") and has no encoder angle: averaged over the drive's hold (a
    #: clock not the drive's, or a window over the interval), that current leads or trails the
    #: controller's samples (agent.workbench.fitting.hold_offset); equal to rate_hz, a DAQ that point-
    #: samples at the drive's own instants. Not stated: the record's rate where the current ADC's window
    #: is stated (a DAQ synchronous with the drive)
    control_rate_hz: float | None = None
    #: how the drive holds its voltage over each update: "abc" (PWM, which fixes the phases' duty cycles)
    #: or "dq" (a continuous inverter holding the rotor-frame command); not stated: "abc"
    voltage_hold: str = "abc"


@dataclass(frozen=True)
class Transmission:
    """Gear pair or sprocket-chain drive (paper Table 3)."""

    kind: str  #: "gear" or "chain"
    driving_teeth: int
    driven_teeth: int
    driving_pitch_diameter_mm: float | None = None  #: chain only
    driven_pitch_diameter_mm: float | None = None  #: chain only, informative
    chain_length_mm: float | None = None  #: chain only

    @property
    def ratio(self) -> float:
        """Gear ratio g_r = driven / driving teeth (eq. 20)."""
        return self.driven_teeth / self.driving_teeth


@dataclass(frozen=True)
class Nameplate:
    """Datasheet and nameplate values with their tolerances: identify's priors (agent.physical).

    Phase values of the star equivalent. The back-EMF constant is the line-to-line rms voltage per
    1000 rpm; with ``psi_m_wb`` as well, the two must agree within their tolerances."""

    rs_ohm: float | None = None  #: phase resistance, DC measurement
    rs_temp_c: float = 20.0  #: winding temperature of that measurement, C
    winding_temp_c: float | None = None  #: winding temperature in the records, C (default: rs_temp_c)
    rs_tol_pct: float = 5.0
    psi_m_wb: float | None = None  #: magnet flux linkage (peak, per phase)
    ke_vrms_per_krpm: float | None = None  #: back-EMF constant, line-to-line V rms per 1000 rpm
    psi_m_tol_pct: float = 5.0
    ld_h: float | None = None
    lq_h: float | None = None
    l_tol_pct: float = 15.0

    def psi_m(self, pole_pairs: int) -> float | None:
        """psi_m (Wb) from ``psi_m_wb`` or from the back-EMF constant: E_ll,rms = sqrt(3/2) omega_e psi_m."""
        if self.psi_m_wb is not None:
            return self.psi_m_wb
        if self.ke_vrms_per_krpm is not None:
            return ke_to_psi_m(self.ke_vrms_per_krpm, pole_pairs)
        return None


def ke_to_psi_m(ke_vrms_per_krpm: float, pole_pairs: int) -> float:
    """Magnet flux linkage (Wb, peak phase) of a back-EMF constant (V rms line-to-line per 1000 rpm)."""
    omega_e = 1000.0 / 60.0 * 2.0 * math.pi * pole_pairs
    return ke_vrms_per_krpm * math.sqrt(2.0 / 3.0) / omega_e


@dataclass(frozen=True)
class DriveProfile:
    motor: Motor
    sampling: Sampling
    transmission: Transmission
    name: str = "drive"
    nameplate: Nameplate | None = None  #: optional priors for identify

    @property
    def rated_fe_hz(self) -> float:
        """Electrical frequency at rated speed, Hz."""
        return self.motor.rated_speed_rpm / 60.0 * self.motor.pole_pairs

    @property
    def ts(self) -> float:
        """Sampling period T_s, s."""
        return 1.0 / self.sampling.rate_hz

    @property
    def torque_per_watt(self) -> float:
        """T_rated / P_rated of eq. 10, N m / W."""
        return self.motor.rated_torque_nm / self.motor.rated_power_w


_SECTIONS = {"motor": Motor, "sampling": Sampling, "transmission": Transmission}


def _build(cls, table: dict, section: str, source: str):
    known = {f.name: f for f in fields(cls)}
    for key in table:
        if key not in known:
            raise InputError(f"unknown key '{section}.{key}' (known: {', '.join(known)})", source=source)
    values = {}
    for name, f in known.items():
        if name not in table:
            if f.default is MISSING:
                raise InputError(f"missing key '{section}.{name}'", source=source)
            continue
        value = table[name]
        want = str(f.type)
        if "int" in want and "float" not in want:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif "float" in want:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            value = float(value) if ok else value
        else:
            ok = isinstance(value, str)
        if not ok:
            raise InputError(f"key '{section}.{name}' has the wrong type ({type(value).__name__})", source=source)
        if isinstance(value, (int, float)) and not math.isfinite(value):
            raise InputError(f"key '{section}.{name}' must be finite, got {value}", source=source)
        if isinstance(value, (int, float)) and value <= 0 and not name.endswith(("_temp_c", "_samples")):
            raise InputError(f"key '{section}.{name}' must be positive, got {value}", source=source)
        values[name] = value
    return cls(**values)


#: samples: the physical ranges of the stated measurement timing (a DAQ filter lags up to 2 samples, a
#: drive's command leads by its computation period; a dq hold after one period advances by 1.5; a
#: current ADC averages at most the interval it samples)
VOLTAGE_PATH_RANGES = {"voltage_delay_samples": (-1.5, 2.0), "voltage_advance_samples": (-1.0, 2.0),
                       "current_window_samples": (0.0, 1.0)}


def parse_profile(data: dict, source: str = "<profile>") -> DriveProfile:
    """Build a profile from a parsed TOML document; errors name ``source`` and the key path."""
    for key in data:
        if key not in _SECTIONS and key not in ("name", "nameplate"):
            raise InputError(f"unknown key '{key}' (known: name, {', '.join(_SECTIONS)}, nameplate)", source=source)
    parts = {}
    for section, cls in _SECTIONS.items():
        table = data.get(section)
        if not isinstance(table, dict):
            raise InputError(f"missing table [{section}]", source=source)
        parts[section] = _build(cls, table, section, source)
    if parts["sampling"].voltage_source not in ("measured", "reference"):
        raise InputError("key 'sampling.voltage_source' must be \"measured\" or \"reference\"", source=source)
    if parts["sampling"].current_source not in (None, "controller", "independent"):
        raise InputError("key 'sampling.current_source' must be \"controller\" or \"independent\"", source=source)
    if parts["sampling"].inverter not in ("pwm", "continuous"):
        raise InputError("key 'sampling.inverter' must be \"pwm\" or \"continuous\"", source=source)
    if parts["sampling"].voltage_hold not in ("abc", "dq"):
        raise InputError("key 'sampling.voltage_hold' must be \"abc\" or \"dq\"", source=source)
    if parts["sampling"].voltage_hold == "dq" and parts["sampling"].inverter == "pwm":
        raise InputError("key 'sampling.voltage_hold' = \"dq\" needs sampling.inverter = \"continuous\": PWM fixes the "
                         "phases' duty cycles over each update, which holds the voltage in abc", source=source)
    if parts["sampling"].current_reference not in (None, "id0", "mtpa"):
        raise InputError("key 'sampling.current_reference' must be \"id0\" or \"mtpa\"", source=source)
    for key, (lo, hi) in VOLTAGE_PATH_RANGES.items():
        value = getattr(parts["sampling"], key)
        if value is not None and not lo <= value <= hi:
            raise InputError(f"key 'sampling.{key}' = {value:g} is outside its physical range {lo:g}..{hi:g} samples",
                             source=source)
    tr = parts["transmission"]
    if tr.kind not in ("gear", "chain"):
        raise InputError("key 'transmission.kind' must be \"gear\" or \"chain\"", source=source)
    if tr.kind == "chain":
        for key in ("driving_pitch_diameter_mm", "chain_length_mm"):
            if getattr(tr, key) is None:
                raise InputError(f"missing key 'transmission.{key}' (required for a chain)", source=source)
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise InputError("key 'name' must be a string", source=source)
    plate = None
    if "nameplate" in data:
        if not isinstance(data["nameplate"], dict):
            raise InputError("key 'nameplate' must be a table", source=source)
        plate = _build(Nameplate, data["nameplate"], "nameplate", source)
        _check_nameplate(plate, parts["motor"], source)
    return DriveProfile(name=name, nameplate=plate, **parts)


WINDING_TEMP_C = (-60.0, 250.0)  #: C, the range of winding temperatures a nameplate may state


def _check_nameplate(n: Nameplate, motor: Motor, source: str) -> None:
    """Nameplate values that contradict each other are an error naming the field."""
    if n.psi_m_wb is not None and n.ke_vrms_per_krpm is not None:
        from_ke = ke_to_psi_m(n.ke_vrms_per_krpm, motor.pole_pairs)
        if abs(math.log(n.psi_m_wb / from_ke)) > 2 * n.psi_m_tol_pct / 100:
            raise InputError(f"key 'nameplate.psi_m_wb' = {n.psi_m_wb:g} Wb does not match nameplate.ke_vrms_per_krpm "
                             f"= {n.ke_vrms_per_krpm:g} V with {motor.pole_pairs} pole pairs ({from_ke:.4g} Wb)",
                             source=source)
    psi = n.psi_m(motor.pole_pairs)
    need = motor.psi_m_from_rating
    if psi is not None and need is not None:
        if not 0.3 * need <= psi <= 3.0 * need:
            key = "psi_m_wb" if n.psi_m_wb is not None else "ke_vrms_per_krpm"
            raise InputError(f"key 'nameplate.{key}' gives psi_m = {psi:.4g} Wb, but the rated torque and current "
                             f"need about {need:.4g} Wb", source=source)
    for key in ("rs_temp_c", "winding_temp_c"):  # copper's temperature coefficient holds over this range
        t = getattr(n, key)
        if t is not None and not WINDING_TEMP_C[0] <= t <= WINDING_TEMP_C[1]:
            raise InputError(f"key 'nameplate.{key}' = {t:g} C is outside a winding's {WINDING_TEMP_C[0]:g}.."
                             f"{WINDING_TEMP_C[1]:g} C", source=source)
    for key in ("rs_tol_pct", "psi_m_tol_pct", "l_tol_pct"):
        if not 0 < getattr(n, key) <= 100:
            raise InputError(f"key 'nameplate.{key}' must be within 0..100 %", source=source)
    z_base = motor.z_base_ohm
    if n.rs_ohm is not None and z_base is not None:
        if not 1e-3 * z_base <= n.rs_ohm <= 0.5 * z_base:
            raise InputError(f"key 'nameplate.rs_ohm' = {n.rs_ohm:g} ohm is outside 0.001..0.5 of the rated "
                             f"impedance ({z_base:.3g} ohm)", source=source)


def load_profile(path: str | Path) -> DriveProfile:
    """Read and validate a drive profile TOML file."""
    data = read_toml(path, "profile")
    return parse_profile(data, source=str(path))
