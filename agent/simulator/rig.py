"""Physical parameters of the paper's test rig (Tables 2-3, Fig. 2, Fig. 4) and its operating point.

All values are SI and referred to the motor shaft unless a name says otherwise. The defaults
describe the driving 2.2 kW / 1500 rpm / 14 N m / 4-pole-pair interior PMSM with its drive, a
two-mass transmission (eqs. 7-9) and the NI-9239 / NI-9244 acquisition at 25 kHz.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RigParams:
    """Rig parameters (units in the comments). Electrical values are at 20 C."""

    # --- interior PMSM, eq. 5 (paper Table 2, driving motor) ---
    R_s: float = 2.0  #: ohm, stator resistance per phase at 20 C
    L_d: float = 15e-3  #: H, d-axis inductance
    L_q: float = 28e-3  #: H, q-axis inductance (unsaturated)
    #: Wb, PM flux linkage (peak) at 20 C: 0.25 Wb at the magnet's rated-load temperature (60 C), so
    #: that rated current (6.6 A rms, i_q = 9.33 A) gives rated torque (14 N m) hot, as a nameplate rates it
    psi_m: float = 0.2626
    alpha_cu: float = 0.00393  #: 1/K, copper temperature coefficient of R_s
    alpha_pm: float = -0.0012  #: 1/K, NdFeB remanence temperature coefficient of psi_m
    # --- thermal operating point (constant within a record) ---
    T_amb: float = 20.0  #: C, ambient = reference temperature of R_s, psi_m
    dT_w_rated: float = 60.0  #: K, winding temperature rise at 100 % load (scales with load^2)
    dT_m_rated: float = 40.0  #: K, magnet temperature rise at 100 % load (scales with load^2)
    sigma_T: float = 1.5  #: K, record-to-record spread of both temperatures (std)
    # --- inverter (average-value model, no PWM ripple) ---
    U_dc: float = 540.0  #: V, DC link; voltage vector limit U_dc/sqrt(3)
    # --- two-mass transmission, eqs. 7-9, referred to the motor shaft ---
    J_1: float = 3.0e-3  #: kg m^2, motor rotor + driving gear/sprocket
    J_2: float = 3.0e-3  #: kg m^2, driven gear + generator rotor, referred (x 1/g_r^2)
    K_s: float = 5000.0  #: N m/rad, mesh + shaft + coupling torsional stiffness (resonance ~290 Hz)
    C_s: float = 0.3  #: N m s/rad, torsional damping (damping ratio ~0.05)
    B_1: float = 9.0e-4  #: N m s/rad, motor-side viscous friction (0.14 N m = 1 % rated at 1500 rpm)
    B_2: float = 1.8e-3  #: N m s/rad, transmission + load-side friction (0.28 N m = 2 % rated)
    k_load: float = 1.0  #: -, d ln T_L / d ln omega of the generator load (1: generator into a resistor)
    sigma_load: float = 0.003  #: -, record-to-record relative spread of the load torque (std)
    # --- drive control (field oriented, i_d_ref = 0) ---
    f_bw_i: float = 600.0  #: Hz, current-loop bandwidth (IMC PI + decoupling)
    f_bw_w: float = 10.0  #: Hz, speed-loop bandwidth (PI, double closed-loop pole)
    T_max_rel: float = 2.0  #: -, torque-reference limit / rated torque
    sigma_i_drive: float = 0.05  #: A rms, drive's own phase-current sensing noise (12-bit ADC, PWM
    #: sampling); the current PI turns it into the broadband voltage excitation that makes eq. 6 identifiable
    # --- data acquisition ---
    sigma_i: float = 5e-3  #: A rms, NI-9239 current channel noise
    sigma_v: float = 0.5  #: V rms, NI-9244 voltage channel noise (measured voltage only)
    # --- numerics ---
    n_sub: int = 4  #: RK4 sub-steps per sample
    t_warmup: float = 0.2  #: s, simulated before t = 0 and discarded
    # --- healthy mesh ripple: amplitude factor per record uniform in ripple_spread (temperature,
    # lubricant film, load); phases and defect positions fixed by the machine's geometry ---
    ripple_spread: tuple[float, float] = (0.8, 1.2)
    geometry_seed: int = 7

    @property
    def u_max(self) -> float:
        """Largest voltage-vector magnitude of the inverter (linear modulation), V."""
        return self.U_dc / math.sqrt(3.0)


@dataclass(frozen=True)
class OperatingPoint:
    """Values constant within one record (load, temperatures and the parameters they set)."""

    omega_m: float  #: rad/s, mechanical speed reference
    T_L: float  #: N m, generator load torque at omega_m (motor side): the motor's torque less the friction
    T_w: float  #: C, winding temperature
    T_m: float  #: C, magnet temperature
    R_s: float  #: ohm
    psi_m: float  #: Wb


def operating_point(rig: RigParams, omega_m: float, T_rated: float, load_pct: float,
                    z_load: float, z_Tw: float, z_Tm: float) -> OperatingPoint:
    """Load torque and temperatures from the load, the torque the motor delivers at its shaft in
    steady state (% of rated: what a drive shows as its load): the generator takes it less the
    transmission's friction at ``omega_m``. ``z_*`` are standard-normal record draws."""
    x = load_pct / 100.0
    T_L = max(x * T_rated - (rig.B_1 + rig.B_2) * omega_m, 0.0) * (1.0 + rig.sigma_load * z_load)
    T_w = rig.T_amb + rig.dT_w_rated * x**2 + rig.sigma_T * z_Tw
    T_m = rig.T_amb + rig.dT_m_rated * x**2 + rig.sigma_T * z_Tm
    R_s = rig.R_s * (1.0 + rig.alpha_cu * (T_w - rig.T_amb))
    psi_m = rig.psi_m * (1.0 + rig.alpha_pm * (T_m - rig.T_amb))
    return OperatingPoint(omega_m, T_L, T_w, T_m, R_s, psi_m)


def saturation(L_q0: float, I_rated: float, drop: float) -> tuple[float, float]:
    """q-axis saturation model ``i_q = psi_q/L_q0 * (1 + a (psi_q/psi_qr)^2)`` (flux -> current).

    ``drop`` is the fractional drop of the chord inductance psi_q/i_q at i_q = I_rated (A peak).
    Returns ``(a, psi_qr)``: ``a = drop/(1-drop)``, ``psi_qr = (1-drop) L_q0 I_rated`` (Wb).
    The map is monotonic for every ``a >= 0``, so the current is explicit in the flux.
    """
    return drop / (1.0 - drop), (1.0 - drop) * L_q0 * I_rated


def psi_q_of_i_q(i_q: float, L_q0: float, a: float, psi_qr: float) -> float:
    """Invert the saturation map for the flux at a given current (Newton, Wb)."""
    psi = L_q0 * i_q
    for _ in range(50):
        f = psi / L_q0 * (1.0 + a * (psi / psi_qr) ** 2) - i_q
        psi -= f / ((1.0 + 3.0 * a * (psi / psi_qr) ** 2) / L_q0)
        if abs(f) < 1e-13:
            break
    return psi


def speed_pi_gains(rig: RigParams) -> tuple[float, float]:
    """Speed PI ``(k_p [N m s/rad], k_i [N m/rad])`` placing both closed-loop poles at -2 pi f_bw_w."""
    a = 2.0 * np.pi * rig.f_bw_w
    J = rig.J_1 + rig.J_2
    return 2.0 * a * J, a * a * J
