"""Records from a drive simulator the project does not own: motulator 0.5.0 (Aalto University).

Its PMSM, inverter, current-vector and speed control (one-sample computation delay, 1.5 T_s angle
advance), two-mass mechanics and ODE solver are independent of ``agent/simulator``. This module
only sets it up, samples it the way a DAQ beside the drive would, and writes CONTRACT records:

* ``t``, ``ia, ib, ic`` (the controller's own current measurement, after the sensor effects, plus
  white noise), ``va, vb, vc`` (phase-to-neutral) and, with ``encoder``, ``theta_e``/``omega_e``;
* voltages: ``measured`` is the converter's average voltage over each sampling interval (what a
  filtered terminal measurement gives); ``reference`` is the drive's voltage command for that
  interval (without the dead time it does not know of).

Hidden effects (``effects={id: value}``), and how each enters:

================  =========================================================================  ==========
effect            injection                                                                  value unit
================  =========================================================================  ==========
voltage_delay     the voltage channel recorded whole samples behind the current channel       samples
current_offset    offset on the sampled currents (a, -a/2, -a/2), seen by the controller      A
current_gain_     gain error of the phase-b current sensor, seen by the controller            -
mismatch
resistance_drift  the machine's R_s raised each sample, R_s (1 + r t)                         1/s
magnetic_         motulator's saturation hook i_s(psi_s): i_q = psi_q/L_q (1 + a (psi_q/      L_q drop at
saturation        psi_qr)^2)                                                                  rated
inverter_         average dead-time duty error -sign(i_x) U_dt/U_dc on the converter's        V
deadtime          duty ratios; visible only with ``voltage="reference"``
flux_harmonics    a subclass of motulator's machine: magnet flux psi_f + psi_6 cos(6 theta)   Wb
                  on d
speed_ripple      load-torque ripple T sin(omega_M t) through motulator's two-mass shaft      N m
================  =========================================================================  ==========

A record may carry a load step (``load_step_pct``: the load torque steps by that many %-points of
rated a quarter into the record, and stays), the transient that reveals a delay at constant speed.

Simulation speed: about 6 times slower than real time at 10 kHz without PWM (``pwm=True``: the
carrier comparison, several times slower again). :func:`cached` keeps records on disk.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

RATE_HZ = 10_000.0  #: sampling (and control) rate of this drive, Hz
N_P = 3
R_S, L_D, L_Q, PSI_F = 3.6, 0.036, 0.051, 0.545  #: motulator's 2.2 kW example machine (ohm, H, H, Wb)
U_DC = 540.0  #: V
TAU_RATED = 14.0  #: N m
W_RATED = 2 * np.pi * 75.0  #: electrical rad/s (1500 rpm)
J_M, J_L, K_S, C_S = 0.005, 0.005, 700.0, 0.01  #: two-mass shaft: kg m^2, N m/rad, N m s/rad
WARMUP_S = 0.25  #: s simulated and dropped before a record starts (speed and current loops settle)
PROFILE = Path(__file__).with_name("motulator_gear.toml")
CACHE = Path(__file__).resolve().parents[1] / "results" / "motulator_cache"


@dataclass(frozen=True)
class Run:
    """One record's settings; ``effects``: {effect id: value in the table's unit}."""

    load_pct: float = 80.0
    seconds: float = 1.0
    seed: int = 0
    effects: dict = field(default_factory=dict)
    voltage: str = "measured"  #: "measured" (interval average) or "reference" (the drive's command)
    encoder: bool = True
    pwm: bool = False
    speed_pct: float = 100.0
    noise_a: float = 0.01  #: current-sensor white noise, A rms
    noise_v: float = 0.5  #: voltage-channel white noise, V rms
    load_step_pct: float = 0.0  #: load change, %-points of rated, a quarter into the record (it stays)

    def key(self) -> str:
        fields = {k: v for k, v in self.__dict__.items() if k != "load_step_pct" or v}  # keys of records without a step stay
        fields.update({"step_at": 0.25} if self.load_step_pct else {})
        doc = json.dumps({**fields, "effects": sorted(self.effects.items()),
                          "v": 2 if "voltage_delay" in self.effects else 1}, sort_keys=True)
        return hashlib.sha1(doc.encode()).hexdigest()[:16]


def _machine(effects: dict):
    import motulator.drive.model as model
    from motulator.drive.utils import SynchronousMachinePars

    par = SynchronousMachinePars(n_p=N_P, R_s=R_S, L_d=L_D, L_q=L_Q, psi_f=PSI_F)
    if "magnetic_saturation" in effects:
        a, psi_qr = float(effects["magnetic_saturation"]), L_Q * 1.5 * 4.3 * np.sqrt(2)

        def i_s(psi_s):  # accepts arrays (motulator post-processing calls it with the whole solution)
            psi_s = np.asarray(psi_s)
            return (psi_s.real - PSI_F) / L_D + 1j * psi_s.imag / L_Q * (1 + a * (psi_s.imag / psi_qr) ** 2)

        return model.SynchronousMachine(par, i_s=i_s)
    if "flux_harmonics" in effects:
        psi6 = float(effects["flux_harmonics"])

        class Harmonic(model.SynchronousMachine):
            """The magnet flux on d carries a 6th harmonic of the electrical angle (5th/7th EMF)."""

            def _psi_f(self, exp_j):
                return PSI_F + psi6 * np.cos(6 * np.angle(exp_j))

            @property
            def i_s(self):
                s = self.state
                return (s.psi_s.real - self._psi_f(s.exp_j_theta_m)) / L_D + 1j * s.psi_s.imag / L_Q

            def post_process_states(self):
                super().post_process_states()
                d = self.data
                d.i_s = (d.psi_s.real - self._psi_f(d.exp_j_theta_m)) / L_D + 1j * d.psi_s.imag / L_Q
                d.i_ss = d.i_s * d.exp_j_theta_m

        return Harmonic(par)
    return model.SynchronousMachine(par)


def simulate(run: Run) -> dict:
    """Columns of one record (CONTRACT section 3) and its true values, from motulator."""
    import motulator.drive.control.sm as control
    import motulator.drive.model as model
    from motulator.common.utils import abc2complex, complex2abc
    from motulator.drive.utils import SynchronousMachinePars, TwoMassMechanicalSystemPars

    eff = dict(run.effects)
    rng = np.random.default_rng(run.seed)
    ts = 1.0 / RATE_HZ
    tau = run.load_pct / 100.0 * TAU_RATED * (1 + 0.002 * rng.standard_normal())
    w_ref = run.speed_pct / 100.0 * W_RATED
    ripple = float(eff.get("speed_ripple", 0.0))
    phase = rng.uniform(0, 2 * np.pi)

    step = run.load_step_pct / 100.0 * TAU_RATED
    t_step = WARMUP_S + 0.25 * run.seconds

    def tau_l(t):  # time only; arrays in post-processing
        t = np.asarray(t)
        return tau + ripple * np.sin(w_ref / N_P * t + phase) + step * (t >= t_step)

    machine = _machine(eff)
    mech = model.TwoMassMechanicalSystem(TwoMassMechanicalSystemPars(J_M=J_M, J_L=J_L, K_S=K_S, C_S=C_S),
                                         tau_L=tau_l)
    mech.state.w_M = mech.state.w_L = w_ref / N_P
    theta0 = rng.uniform(0, 2 * np.pi)  # mechanical rad; the state must not stay 0 (motulator pitfall)
    mech.state.exp_j_theta_M = complex(np.exp(1j * theta0))
    machine.state.exp_j_theta_m = complex(np.exp(1j * N_P * theta0))  # its own electrical angle state
    mech.state.theta_ML = tau / K_S
    mdl = model.Drive(model.VoltageSourceConverter(U_DC), machine, mech)
    if run.pwm:
        mdl.pwm = model.CarrierComparison()
    ctrl_par = SynchronousMachinePars(n_p=N_P, R_s=R_S, L_d=L_D, L_q=L_Q, psi_f=PSI_F)
    cfg = control.CurrentReferenceCfg(ctrl_par, max_i_s=1.5 * 4.3 * np.sqrt(2), nom_w_m=W_RATED)
    ctrl = control.CurrentVectorControl(ctrl_par, cfg, T_s=ts, J=J_M + J_L, sensorless=False)
    ctrl.ref.w_m = lambda t: w_ref
    sc = ctrl.speed_ctrl  # start the speed loop's integrator at the load (no 0.5 s speed transient)
    sc.u_i = tau + (sc.k_p - sc.k_t) * w_ref / N_P

    offset = float(eff.get("current_offset", 0.0)) * np.array([1.0, -0.5, -0.5])
    gain = np.array([1.0, 1.0 + float(eff.get("current_gain_mismatch", 0.0)), 1.0])
    true_meas = machine.meas_currents
    last = {}

    def meas_currents():  # the sensors: what the controller and the DAQ both see
        i = gain * true_meas() + offset + run.noise_a * rng.standard_normal(3)
        last["i"] = i
        return i

    machine.meas_currents = meas_currents
    u_dt = float(eff.get("inverter_deadtime", 0.0))
    if u_dt:
        delay = mdl.delay

        def dead_time(d_ref):  # average dead-time error on the duties the converter applies
            d = np.asarray(delay(d_ref), dtype=float)
            return np.clip(d - np.sign(complex2abc(machine.i_s * machine.state.exp_j_theta_m)) * u_dt / U_DC, 0, 1)

        mdl.delay = dead_time
    r_rate = float(eff.get("resistance_drift", 0.0))
    rows = []
    main = ctrl.main

    def sampled(m):
        t = m.t0
        if r_rate:
            machine.par.R_s = R_S * (1 + r_rate * max(t - WARMUP_S, 0.0))
        t_s, d = main(m)
        rows.append((t, *last["i"], np.angle(m.mechanics.state.exp_j_theta_M) * N_P,
                     m.mechanics.state.w_M.real * N_P, *np.asarray(d, dtype=float)))
        return t_s, d

    ctrl.main = sampled
    sim = model.Simulation(mdl, ctrl)
    sim.simulate(t_stop=WARMUP_S + run.seconds - 0.5 * ts)
    a = np.array(rows)
    if a[-1, 0] < WARMUP_S + run.seconds - 1.5 * ts:
        raise RuntimeError(f"motulator stopped at {a[-1, 0]:.4f} s (FloatingPointError): {run}")
    duty = a[:, 6:9]
    command = U_DC * (duty - duty.mean(axis=1, keepdims=True))  # computed at k for the interval k+1
    applied = np.vstack((command[:1], command[:-1]))  # motulator's one-sample computation delay
    if u_dt:
        i_true = a[:, 1:4] - offset  # the sign of the phase current (noise flips it only near zero)
        applied = applied - u_dt * (np.sign(i_true) - np.sign(i_true).mean(axis=1, keepdims=True))
    # the command of interval k is computed at k - 1; the reference channel records it for
    # interval k (the command does not know the dead time)
    v = np.vstack((command[:1], command[:-1])) if run.voltage == "reference" else applied
    lag = int(round(float(eff.get("voltage_delay", 0.0))))
    if lag:  # the voltage channel recorded ``lag`` samples behind the current channel
        v = np.vstack((np.repeat(v[:1], lag, axis=0), v[:-lag]))
    keep = a[:, 0] >= WARMUP_S - 1e-12
    a, v = a[keep], v[keep]
    v = v + run.noise_v * rng.standard_normal(v.shape)
    cols = {"t": a[:, 0] - a[0, 0], "ia": a[:, 1], "ib": a[:, 2], "ic": a[:, 3],
            "va": v[:, 0], "vb": v[:, 1], "vc": v[:, 2]}
    if run.encoder:
        cols["theta_e"] = np.unwrap(a[:, 4])
        cols["omega_e"] = a[:, 5]
    truth = {"R_s": R_S, "L_d": L_D, "L_q": L_Q, "psi_m": PSI_F, "load_pct": run.load_pct, **eff}
    return {"columns": cols, "truth": truth}


def cached(run: Run, folder: Path = CACHE) -> Path:
    """Path of the run's record (``.npz``, CONTRACT columns), simulated once and kept in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"motulator_{run.key()}.npz"
    if not path.exists():
        out = simulate(run)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **out["columns"], truth=json.dumps(out["truth"]))
        tmp.replace(path)
    return path


if __name__ == "__main__":  # python -m bench.thirdparty.motulator_drive: one record, timed
    import time

    t0 = time.perf_counter()
    res = simulate(Run(seconds=0.2))
    c = res["columns"]
    print(f"{c['t'].size} samples in {time.perf_counter() - t0:.1f} s; i_q rms "
          f"{np.sqrt(np.mean(c['ia'] ** 2)):.2f} A, omega_e {c['omega_e'].mean():.1f} rad/s")
