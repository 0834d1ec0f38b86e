"""A drawn drive: the machine from its rating, the inverter, the controller, the sensors, the shaft.

Every attribute is drawn per drive from one seed (:func:`draw_drive`). The machine is designed
from its rating, in per unit of the rated phase voltage and current (peak values):

* rated power 0.4-15 kW (log-uniform), rated speed 1000-3000 rpm, 2-6 pole pairs, DC link
  300-600 V; the rated line voltage is 0.78-0.92 of the inverter's linear limit U_dc/sqrt 2;
* R_s 0.02-0.08 pu, X_q = omega_rated L_q 0.2-0.8 pu, saliency L_q/L_d 1.0-2.5 (a third of the
  drives surface-mounted, 1.0-1.1);
* the back-EMF omega_rated psi_m is the one that puts the rated point (MTPA at rated current and
  speed) exactly on the rated voltage; the rated current then follows from the rated power as
  the air-gap power 1.5 V I (e i_q + (x_d - x_q) i_d i_q) (pu) -- so rating, R_s, L_d, L_q and
  psi_m agree the way a real machine's do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import scipy.optimize

from agent.profile import DriveProfile, parse_profile
from bench.family.machine import flux_from_currents_array, flux_map, inverse_inductance, torque_nm

COPPER_PER_K = 0.00393  #: copper's resistance temperature coefficient at 20 C, 1/K
EXCITATIONS = ("constant", "load_ripple", "load_step", "speed_step")
MAX_LOAD_PCT = 110.0  #: the heaviest load the operating speed is checked for (the voltage limit)


@dataclass(frozen=True)
class Drive:
    """One drawn drive (SI units; angles rad; 'pu' of the rated phase voltage and current).

    This is the null drive: a linear machine with a sinusoidal magnet flux, an ideal inverter,
    ideal current sensors (noise and ADC only), a constant winding temperature and a smooth shaft,
    with its own voltage path (hold, computation delay, angle compensation, command logging or the
    measured voltage's window: ``bench.family.effects.voltage_path``). The hidden effects
    (``bench.family.effects``) add to it.
    """

    seed: int
    # --- machine and rating
    pole_pairs: int
    rated_power_w: float
    rated_speed_rpm: float
    rated_torque_nm: float
    rated_voltage_v: float  #: line-to-line rms at the rated point
    rated_current_a: float  #: phase rms at the rated point
    u_dc_v: float
    rs_ohm: float  #: phase resistance at ``winding_temp_c``
    ld_h: float
    lq_h: float
    psi_m_wb: float  #: magnet flux linkage, peak per phase
    winding_temp_c: float  #: the winding's temperature in healthy records
    # --- timing and inverter
    rate_hz: float  #: the record's sampling rate
    control_rate_hz: float  #: the controller's rate (= rate_hz unless current_sampling is "async")
    updates_per_carrier: int  #: 1 (f_sw = control rate) or 2 (sampled at both carrier extremes)
    inverter: str  #: "switched" (PWM edges integrated) or "averaged" (interval-average voltage)
    voltage_hold: str  #: "abc" (PWM average, constant phase voltage) or "dq" (continuous inverter, constant rotor-frame voltage)
    computation_delay: int  #: intervals between a sample and the interval its command acts in (0 or 1)
    angle_compensation: bool  #: the command is turned forward by (delay + 0.5) omega_e T_c (abc hold only)
    # --- control and mechanics
    current_reference: str  #: "id0" or "mtpa"
    current_bandwidth_hz: float
    integral_time_s: float  #: current PI's integral time, 4-10 / (2 pi bandwidth), at most L_q/R_s
    ctrl_ld_h: float  #: the controller's estimates (commissioning errors up to 8 %): its decoupling, and
    ctrl_lq_h: float  #: the same relative error on its gain schedule (incremental L at the reference)
    ctrl_psi_m_wb: float
    mechanics: str  #: "load_machine" (a stiff speed-controlled load machine sets the speed; the drive follows a torque command) or "speed_loop" (the drive's speed PI against a load torque)
    speed_bandwidth_hz: float  #: the bandwidth of whichever speed loop holds the speed
    inertia_kgm2: float
    friction_nm_s: float  #: viscous friction torque per mechanical rad/s
    operating_speed_rpm: float
    excitation: str  #: one of EXCITATIONS: what changes in a record besides noise
    # --- measurement
    voltage_source: str  #: "reference" (the drive's command) or "measured" (terminal, interval average)
    command_logged_as: str  #: reference only: "phase" (the modulator's phase commands) or "dq" (the dq command at the sample's angle)
    voltage_filter_delay: float  #: measured only: the averaging window's lag, samples (window [t_k - d T_s, t_k + (1 - d) T_s])
    current_sampling: str  #: "centre" (at the carrier's centre), "average" (over the interval around the sample) or "async" (record clock not the PWM's)
    adc_bits: int
    current_full_scale_a: float  #: +- full scale of the current ADC
    voltage_adc_bits: int
    voltage_full_scale_v: float
    current_noise_a: float  #: rms, per phase
    voltage_noise_v: float  #: rms, per phase (measured voltage only)
    encoder: bool  #: records carry theta_e and omega_e
    # --- transmission (profile only)
    driving_teeth: int
    driven_teeth: int

    @property
    def i_rated_peak(self) -> float:
        return self.rated_current_a * math.sqrt(2.0)

    @property
    def v_rated_peak(self) -> float:
        """Rated phase voltage, peak (V)."""
        return self.rated_voltage_v * math.sqrt(2.0 / 3.0)

    @property
    def omega_m_rated(self) -> float:
        return self.rated_speed_rpm * math.pi / 30.0

    @property
    def omega_m_operating(self) -> float:
        return self.operating_speed_rpm * math.pi / 30.0

    @property
    def switching_hz(self) -> float:
        return self.control_rate_hz / self.updates_per_carrier

    @property
    def rs_20c_ohm(self) -> float:
        """R_s at 20 C (a DC measurement's reference)."""
        return self.rs_ohm / (1.0 + COPPER_PER_K * (self.winding_temp_c - 20.0))

    def linear_flux_map(self) -> np.ndarray:
        return flux_map(self.ld_h, self.lq_h, self.psi_m_wb)


class _Draw:
    """Draws in a fixed order from one generator; an override replaces a draw (the generator still
    advances, so the other attributes do not change)."""

    def __init__(self, seed: int, overrides: dict):
        self.rng = np.random.default_rng(seed)
        self.overrides = dict(overrides)
        known = {f.name for f in fields(Drive)}
        unknown = set(overrides) - known
        if unknown:
            raise TypeError(f"unknown Drive attribute(s): {', '.join(sorted(unknown))}")

    def __call__(self, name, value):
        value = value.item() if isinstance(value, np.generic) else value  # plain Python types: JSON-able
        return self.overrides.get(name, value)

    def uniform(self, name, lo, hi):
        return self(name, float(self.rng.uniform(lo, hi)))

    def choice(self, name, options, p=None):
        pick = options[int(self.rng.choice(len(options), p=p))]
        return self(name, pick)


def _mtpa_pu(e: float, x_d: float, x_q: float) -> tuple[float, float]:
    """(i_d, i_q) of unit current at maximum torque (pu), linear machine."""
    delta = x_q - x_d
    if delta < 1e-9:
        return 0.0, 1.0
    i_d = (e - math.sqrt(e * e + 8.0 * delta * delta)) / (4.0 * delta)
    return i_d, math.sqrt(1.0 - i_d * i_d)


def design_machine(r: float, x_q: float, saliency: float) -> tuple[float, float, float]:
    """Back-EMF e (pu) that puts the MTPA rated point on the rated voltage, and the rated point's
    (i_d, i_q) (pu)."""
    x_d = x_q / saliency

    def excess(e):
        i_d, i_q = _mtpa_pu(e, x_d, x_q)
        return math.hypot(r * i_d - x_q * i_q, r * i_q + x_d * i_d + e) - 1.0

    e = scipy.optimize.brentq(excess, 0.0, 2.0)
    return (e, *_mtpa_pu(e, x_d, x_q))


def steady_voltage(fm: np.ndarray, r_s: float, omega_e: float, i_d: float, i_q: float) -> tuple[float, float]:
    """(v_d, v_q) (V) at steady state: v_d = R i_d - w psi_q, v_q = R i_q + w psi_d."""
    from bench.family.machine import flux_from_currents

    psi_d, psi_q = flux_from_currents(i_d, i_q, fm)
    return r_s * i_d - omega_e * psi_q, r_s * i_q + omega_e * psi_d


def draw_drive(seed: int, **overrides) -> Drive:
    """A drive with every attribute drawn from ``seed``; ``overrides`` fix attributes by name (the
    derived ones, e.g. the rated current, follow the overridden rating)."""
    d = _Draw(seed, overrides)
    pole_pairs = d("pole_pairs", int(d.rng.integers(2, 7)))
    power = d("rated_power_w", float(math.exp(d.rng.uniform(math.log(400.0), math.log(15000.0)))))
    speed = d.uniform("rated_speed_rpm", 1000.0, 3000.0)
    u_dc = d.uniform("u_dc_v", 300.0, 600.0)
    v_ll = d("rated_voltage_v", d.rng.uniform(0.78, 0.92) * u_dc / math.sqrt(2.0))
    r_pu = d.rng.uniform(0.02, 0.08)
    x_q = d.rng.uniform(0.2, 0.8)
    saliency = d.rng.uniform(1.0, 1.1) if d.rng.random() < 1 / 3 else d.rng.uniform(1.1, 2.5)
    e, i_d_pu, i_q_pu = design_machine(r_pu, x_q, saliency)
    x_d = x_q / saliency
    v_peak = v_ll * math.sqrt(2.0 / 3.0)
    i_peak = power / (1.5 * v_peak * (e * i_q_pu + (x_d - x_q) * i_d_pu * i_q_pu))
    omega_e = speed * math.pi / 30.0 * pole_pairs
    z = v_peak / i_peak
    rated_current = d("rated_current_a", i_peak / math.sqrt(2.0))
    i_peak = rated_current * math.sqrt(2.0)
    lq = d("lq_h", x_q * z / omega_e)
    ld = d("ld_h", lq / saliency)
    psi_m = d("psi_m_wb", e * v_peak / omega_e)
    rs = d("rs_ohm", r_pu * z)
    torque = d("rated_torque_nm", power / (speed * math.pi / 30.0))
    winding = d.uniform("winding_temp_c", 30.0, 110.0)

    rate = d("rate_hz", float(round(d.rng.uniform(8000.0, 32000.0), -2)))
    sampling = d.choice("current_sampling", ("centre", "average", "async"), p=(0.5, 0.25, 0.25))
    ratio = d.rng.uniform(0.6, 0.95) if d.rng.random() < 0.5 else d.rng.uniform(1.05, 1.6)
    control_rate = d("control_rate_hz", rate * ratio if sampling == "async" else rate)
    updates = d("updates_per_carrier", int(d.rng.integers(1, 3)))
    inverter = d.choice("inverter", ("switched", "averaged"))
    hold = d.choice("voltage_hold", ("abc", "dq"), p=(0.6, 0.4))
    hold = d("voltage_hold", "abc" if inverter == "switched" else hold)
    delay = d("computation_delay", int(d.rng.random() < 0.7))
    compensation = d("angle_compensation", bool(d.rng.random() < 0.5) and hold == "abc")

    reference = d.choice("current_reference", ("id0", "mtpa"))
    bandwidth = d("current_bandwidth_hz", d.rng.uniform(0.04, 0.10) * control_rate if delay
                  else d.rng.uniform(0.05, 0.15) * control_rate)
    alpha_c = 2.0 * math.pi * bandwidth
    integral_time = d("integral_time_s", min(lq / rs, d.rng.uniform(4.0, 10.0) / alpha_c))
    err = d.rng.uniform(-0.08, 0.08, 3)
    ctrl_ld, ctrl_lq = d("ctrl_ld_h", ld * (1 + err[0])), d("ctrl_lq_h", lq * (1 + err[1]))
    ctrl_psi = d("ctrl_psi_m_wb", psi_m * (1 + err[2]))
    mechanics = d.choice("mechanics", ("load_machine", "speed_loop"))
    speed_bw = d("speed_bandwidth_hz", d.rng.uniform(10.0, 40.0) if mechanics == "load_machine"
                 else d.rng.uniform(3.0, 20.0))
    start_time = d.rng.uniform(0.02, 0.5)  # J omega_rated / T_rated, s
    inertia = d("inertia_kgm2", start_time * torque / (speed * math.pi / 30.0))
    friction = d("friction_nm_s", d.rng.uniform(0.003, 0.02) * torque / (speed * math.pi / 30.0))
    operating = d.rng.uniform(0.5, 1.0) * speed
    excitation = d.choice("excitation", EXCITATIONS, p=(0.4, 0.2, 0.2, 0.2))

    source = d.choice("voltage_source", ("reference", "measured"))
    source = d("voltage_source", "measured" if sampling == "async" else source)
    logged = d.choice("command_logged_as", ("phase", "dq"))
    filter_delay = float(d.rng.choice([0.0, 1.0, d.rng.uniform(0.0, 1.0)]))
    filter_delay = d("voltage_filter_delay", filter_delay if source == "measured" else 0.0)
    bits = d("adc_bits", int(d.rng.integers(12, 17)))
    current_fs = d("current_full_scale_a", d.rng.uniform(2.0, 3.0) * i_peak)
    v_bits = d("voltage_adc_bits", int(d.rng.integers(12, 17)))
    voltage_fs = d("voltage_full_scale_v", d.rng.uniform(0.7, 1.0) * u_dc)
    noise_i = d("current_noise_a", d.rng.uniform(0.0005, 0.005) * i_peak)
    noise_v = d("voltage_noise_v", d.rng.uniform(0.0005, 0.005) * v_peak if source == "measured" else 0.0)
    encoder = d("encoder", bool(d.rng.random() < 0.5))
    driving = d("driving_teeth", int(d.rng.integers(12, 31)))
    driven = d("driven_teeth", int(round(driving * d.rng.uniform(1.0, 5.0))))

    drive = Drive(seed=seed, pole_pairs=pole_pairs, rated_power_w=power, rated_speed_rpm=speed,
                  rated_torque_nm=torque, rated_voltage_v=v_ll, rated_current_a=rated_current, u_dc_v=u_dc,
                  rs_ohm=rs, ld_h=ld, lq_h=lq, psi_m_wb=psi_m, winding_temp_c=winding, rate_hz=rate,
                  control_rate_hz=control_rate, updates_per_carrier=updates, inverter=inverter,
                  voltage_hold=hold, computation_delay=delay, angle_compensation=compensation,
                  current_reference=reference, current_bandwidth_hz=bandwidth, integral_time_s=integral_time,
                  ctrl_ld_h=ctrl_ld, ctrl_lq_h=ctrl_lq, ctrl_psi_m_wb=ctrl_psi,
                  mechanics=mechanics, speed_bandwidth_hz=speed_bw, inertia_kgm2=inertia, friction_nm_s=friction,
                  operating_speed_rpm=speed, excitation=excitation, voltage_source=source,
                  command_logged_as=logged, voltage_filter_delay=filter_delay, current_sampling=sampling,
                  adc_bits=bits, current_full_scale_a=current_fs, voltage_adc_bits=v_bits,
                  voltage_full_scale_v=voltage_fs, current_noise_a=noise_i, voltage_noise_v=noise_v,
                  encoder=encoder, driving_teeth=driving, driven_teeth=driven)
    operating = d("operating_speed_rpm", min(operating, _fastest_speed_rpm(drive)))
    return _replace(drive, operating_speed_rpm=operating)


def _replace(drive: Drive, **changes) -> Drive:
    from dataclasses import replace

    return replace(drive, **changes)


def _fastest_speed_rpm(drive: Drive) -> float:
    """The speed at which the heaviest checked load needs 85 % of the inverter's linear voltage (the
    margin a drive keeps for transients and harmonics)."""
    fm = drive.linear_flux_map()
    table = reference_table(drive, fm)
    torque = MAX_LOAD_PCT / 100.0 * drive.rated_torque_nm
    i_d, i_q = np.interp(torque, *table[:2]), np.interp(torque, table[0], table[2])
    limit = 0.85 * drive.u_dc_v / math.sqrt(3.0)

    def excess(rpm):
        v_d, v_q = steady_voltage(fm, drive.rs_ohm, rpm * math.pi / 30.0 * drive.pole_pairs, i_d, i_q)
        return math.hypot(v_d, v_q) - limit

    top = 1.2 * drive.rated_speed_rpm
    return top if excess(top) < 0 else scipy.optimize.brentq(excess, 1.0, top)


def reference_table(drive: Drive, fm: np.ndarray, points: int = 161) -> tuple[np.ndarray, ...]:
    """(torque N m, i_d* A, i_q* A, L_d H, L_q H): the drive's torque-to-current table for its flux map
    ``fm`` (commissioned on the true machine), i_d = 0 or maximum torque per ampere, up to 2.5 rated
    current, with the incremental inductances there (the current controller's gain schedule)."""
    i_max = 2.5 * drive.i_rated_peak
    mags = np.linspace(0.0, i_max, points)
    if drive.current_reference == "id0":
        torque = torque_nm(np.zeros_like(mags), mags, fm, drive.pole_pairs)
        i_d, i_q = np.zeros_like(mags), mags
    else:
        angles = np.linspace(0.0, 0.45 * math.pi, 91)  # current angle ahead of q
        grid = torque_nm(-np.outer(mags, np.sin(angles)), np.outer(mags, np.cos(angles)), fm, drive.pole_pairs)
        best = np.argmax(grid, axis=1)
        torque = grid[np.arange(points), best]
        i_d, i_q = -mags * np.sin(angles[best]), mags * np.cos(angles[best])
    keep = np.concatenate(([True], np.diff(torque) > 0))
    torque, i_d, i_q = torque[keep], i_d[keep], i_q[keep]
    l_d, l_q = incremental_inductances(i_d, i_q, fm)
    # odd in torque: a negative torque reverses i_q (the map is even in psi_q)
    return (np.concatenate((-torque[:0:-1], torque)), np.concatenate((i_d[:0:-1], i_d)),
            np.concatenate((-i_q[:0:-1], i_q)), np.concatenate((l_d[:0:-1], l_d)), np.concatenate((l_q[:0:-1], l_q)))


def incremental_inductances(i_d, i_q, fm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal of the incremental inductance matrix d psi/d i (H) at the currents (A)."""
    psi_d, psi_q = flux_from_currents_array(np.asarray(i_d, float), np.asarray(i_q, float), fm)
    a_dd, a_dq, a_qq = (np.array(x) for x in zip(*(inverse_inductance(a, b, fm) for a, b in zip(psi_d, psi_q))))
    det = a_dd * a_qq - a_dq * a_dq
    return a_qq / det, a_dd / det


def profile(drive: Drive, nameplate: bool = False, timing: bool = False) -> DriveProfile:
    """The drive's profile (CONTRACT section 4); with ``nameplate``, R_s (a DC measurement at 20 C,
    with the records' winding temperature), psi_m, L_d and L_q, each within 5 % of the truth
    (a random error drawn from the drive's seed); with ``timing``, the voltage path the drive's
    documentation gives (computation delay, hold, logging, the DAQ filter's lag:
    :func:`bench.family.effects.voltage_path` of the healthy drive), the current ADC's window, whose
    current samples the records carry, the current reference (i_d = 0 or MTPA), the drive's update
    rate and its hold (abc or dq)."""
    doc = {
        "name": f"family_{drive.seed}",
        "motor": {"pole_pairs": drive.pole_pairs, "rated_power_w": drive.rated_power_w,
                  "rated_torque_nm": drive.rated_torque_nm, "rated_speed_rpm": drive.rated_speed_rpm,
                  "rated_voltage_v": drive.rated_voltage_v, "rated_current_a": drive.rated_current_a},
        "sampling": {"rate_hz": drive.rate_hz, "voltage_source": "reference" if drive.voltage_source == "reference"
                     else "measured", "inverter": "pwm" if drive.inverter == "switched" else "continuous"},
        "transmission": {"kind": "gear", "driving_teeth": drive.driving_teeth, "driven_teeth": drive.driven_teeth},
    }
    if nameplate:
        err = 1.0 + np.random.default_rng([drive.seed, 1]).uniform(-0.05, 0.05, 4)
        doc["nameplate"] = {"rs_ohm": drive.rs_20c_ohm * err[0], "rs_temp_c": 20.0,
                            "winding_temp_c": drive.winding_temp_c, "psi_m_wb": drive.psi_m_wb * err[1],
                            "ld_h": drive.ld_h * err[2], "lq_h": drive.lq_h * err[3]}
    if timing:
        from bench.family.effects import voltage_path

        delay, advance = voltage_path(drive)
        doc["sampling"].update(voltage_delay_samples=delay, voltage_advance_samples=advance)
        if drive.current_sampling == "average":  # the interval around each sample
            doc["sampling"]["current_window_samples"] = 1.0
        # the controller's own ADC samples at the carrier's centre; averaged and asynchronous records
        # come from the DAQ's own channels (bench.family.simulate)
        doc["sampling"]["current_source"] = "controller" if drive.current_sampling == "centre" else "independent"
        doc["sampling"]["current_reference"] = drive.current_reference
        # the drive's update rate and its hold (its documentation's PWM frequency and inverter)
        doc["sampling"].update(control_rate_hz=drive.control_rate_hz, voltage_hold=drive.voltage_hold)
    return parse_profile(doc, source=f"family_{drive.seed}")
