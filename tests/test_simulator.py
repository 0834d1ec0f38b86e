"""Simulator physics against analytic references: speed, torque, energy, eq. 5 steady state,
fault sidebands (eqs. 19-21), the eight workbench effects, determinism and input errors."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from agent.errors import InputError
from agent.frames import abc_to_ab0, abc_to_dq
from agent.profile import load_profile
from agent.simulator import CONDITIONS, EFFECTS, RigParams, simulate

ROOT = Path(__file__).resolve().parents[1]
GEAR = load_profile(ROOT / "config/profiles/rig_gear.toml")
CHAIN = load_profile(ROOT / "config/profiles/rig_chain.toml")
REF = dataclasses.replace(GEAR, sampling=dataclasses.replace(GEAR.sampling, voltage_source="reference"))
RIG = RigParams()
FS, TS, FE, NP = 25_000.0, 4e-5, 100.0, 4
W_M = 2 * math.pi * 1500 / 60  # rad/s
W_E = NP * W_M


def spectrum(x):
    """Hann-windowed amplitude spectrum (amplitude of a sinusoid = its peak value)."""
    w = np.hanning(x.size)
    return np.fft.rfftfreq(x.size, 1 / FS), np.abs(np.fft.rfft((x - x.mean()) * w)) * 2 / w.sum()


def line(x, f0, half=0.6):
    f, a = spectrum(x)
    return a[(f > f0 - half) & (f < f0 + half)].max()


def sidebands(rec, f_fault, k_max=3):
    return sum(line(rec.i_abc[0], FE + s * k * f_fault) for k in range(1, k_max + 1) for s in (-1, 1))


def dq(rec):
    """i_dq at theta_e(t_k); v_dq at the mid-interval angle (the voltage is held over [t_k, t_k+T_s))."""
    i_dq, _ = abc_to_dq(rec.i_abc, rec.theta_e)
    v_dq, _ = abc_to_dq(rec.v_abc, rec.theta_e + 0.5 * rec.omega_e * TS)
    return i_dq, v_dq


@pytest.fixture(scope="module")
def healthy():
    return simulate(GEAR, seconds=2.0, seed=1, encoder=True)


def test_record_shape_and_meta(healthy):
    rec = healthy
    assert rec.t[0] == 0.0 and rec.n == 50_000 and rec.v_abc.shape == rec.i_abc.shape == (3, 50_000)
    assert rec.rate_hz == pytest.approx(FS, rel=1e-9)
    assert 0.0 <= rec.theta_e.min() and rec.theta_e.max() < 2 * math.pi
    for key in ("condition", "load_pct", "seed", "profile", "R_s", "L_d", "L_q", "psi_m", "B_GT", "B_GT_equiv"):
        assert key in rec.meta
    assert all(isinstance(v, (str, int, float)) for v in rec.meta.values())
    assert simulate(GEAR, seconds=0.1).theta_e is None


def test_steady_speed_100hz(healthy):
    assert healthy.omega_e.mean() / (2 * math.pi) == pytest.approx(FE, rel=5e-4)
    # independently of the encoder: the phase of the current vector advances at f_e
    ab = abc_to_ab0(healthy.i_abc)
    phase = np.unwrap(np.angle(ab[0] + 1j * ab[1]))
    assert np.polyfit(healthy.t, phase, 1)[0] / (2 * math.pi) == pytest.approx(FE, rel=5e-4)


def test_starts_at_steady_state(healthy):
    i_dq, _ = dq(healthy)
    first, last = i_dq[1, :2500].mean(), i_dq[1, -2500:].mean()
    assert first == pytest.approx(last, rel=0.01)


def test_torque_matches_load(healthy):
    i_dq, _ = dq(healthy)
    T_e = 0.8 * 14.0  # the load is the motor's shaft torque (the generator's load and the friction), N m
    assert i_dq[1].mean() == pytest.approx(T_e / (1.5 * NP * healthy.meta["psi_m"]), rel=0.012)
    assert abs(i_dq[0].mean()) < 0.01  # i_d = 0 control


def test_encoder_angle_aligned_with_current(healthy):
    ab = abc_to_ab0(healthy.i_abc)
    err = np.angle(np.exp(1j * (np.angle(ab[0] + 1j * ab[1]) - healthy.theta_e - math.pi / 2)))
    assert abs(err.mean()) < 5e-4 and err.std() < 5e-3  # current on the q axis


def test_energy_balance(healthy):
    i_mid = 0.5 * (healthy.i_abc[:, :-1] + healthy.i_abc[:, 1:])  # mean current over each ZOH interval
    p_in = np.mean(np.sum(healthy.v_abc[:, :-1] * i_mid, axis=0))
    i_dq, _ = dq(healthy)
    copper = 1.5 * healthy.meta["R_s"] * np.mean(np.sum(i_dq ** 2, axis=0))
    p_fric = (RIG.B_1 + RIG.B_2) * W_M ** 2
    assert p_in == pytest.approx(0.8 * 14.0 * W_M + copper, rel=0.02)  # nominal load: the shaft torque, friction included
    assert p_in == pytest.approx(healthy.meta["T_load"] * W_M + p_fric + copper, rel=1e-3)


def test_voltage_eq5_steady_state(healthy):
    i_dq, v_dq = dq(healthy)
    m, iq = healthy.meta, i_dq[1].mean()
    assert v_dq[0].mean() == pytest.approx(-W_E * RIG.L_q * iq, rel=1e-3)
    assert v_dq[1].mean() == pytest.approx(m["R_s"] * iq + W_E * m["psi_m"], rel=1e-3)


def test_thermal_operating_point():
    lo, hi = (simulate(GEAR, load_pct=p, seconds=0.05, seed=3).meta for p in (40.0, 100.0))
    assert lo["R_s"] < hi["R_s"] and lo["psi_m"] > hi["psi_m"]
    assert hi["R_s"] == pytest.approx(RIG.R_s * (1 + 0.00393 * 60), rel=0.02)


def test_determinism():
    a, b = (simulate(GEAR, "gear_severe_wear", seconds=0.2, seed=5, encoder=True) for _ in range(2))
    c = simulate(GEAR, "gear_severe_wear", seconds=0.2, seed=6, encoder=True)
    for x in ("v_abc", "i_abc", "theta_e", "omega_e"):
        np.testing.assert_array_equal(getattr(a, x), getattr(b, x))
    assert not np.allclose(a.i_abc, c.i_abc)
    assert a.meta == b.meta


@pytest.mark.parametrize("seed", [2, 7])
def test_gear_faults_raise_sidebands(seed):
    f_gl = 12.5  # eq. 20: 100 / (2 * 4)
    recs = {c: simulate(GEAR, c, seconds=2.0, seed=seed)
            for c in ("healthy", "gear_slight_wear", "gear_severe_wear", "gear_no_lubricant")}
    s = {c: sidebands(r, f_gl) for c, r in recs.items()}
    # the fault adds to the healthy ripple at the rig's fixed geometry phase, so a slight fault is a
    # modest rise in the raw current; the residual spectrum (tests/test_acceptance.py) is the real check
    assert s["gear_slight_wear"] > 1.15 * s["healthy"]
    assert s["gear_severe_wear"] > 2.5 * s["healthy"] and s["gear_severe_wear"] > 1.5 * s["gear_slight_wear"]
    k2 = {c: line(r.i_abc[0], FE - 2 * f_gl) + line(r.i_abc[0], FE + 2 * f_gl) for c, r in recs.items()}
    assert k2["gear_no_lubricant"] > 2.0 * k2["healthy"]


def test_chain_faults_raise_sidebands():
    f_ch = 2 * math.pi * 0.045810 / 2 * 25.0 / 0.423  # eq. 21, 8.5 Hz
    recs = {c: simulate(CHAIN, c, seconds=2.0, seed=4)
            for c in ("healthy", "chain_offset", "chain_missing_tooth")}
    s = {c: sidebands(r, f_ch, 2) for c, r in recs.items()}
    assert s["chain_offset"] > 1.3 * s["healthy"] and s["chain_missing_tooth"] > 2.5 * s["healthy"]
    s_gl = {c: sidebands(r, 12.5, 1) for c, r in recs.items()}
    assert s_gl["chain_missing_tooth"] > 3 * s_gl["healthy"]


def p_in(rec):
    return float(np.mean(np.sum(rec.v_abc * rec.i_abc, axis=0)))


def test_friction_raises_input_power():
    base = simulate(GEAR, seconds=1.0, seed=3)
    dry = simulate(GEAR, "gear_no_lubricant", seconds=1.0, seed=3)
    dT = (2.5 - 1.0) * RIG.B_2 * W_M  # extra friction torque, N m
    m = base.meta
    iq, d_iq = m["i_q"], dT / (1.5 * NP * m["psi_m"])
    expected = dT * W_M + 1.5 * m["R_s"] * ((iq + d_iq) ** 2 - iq ** 2)  # friction + extra copper loss, W
    assert p_in(dry) - p_in(base) == pytest.approx(expected, rel=0.05)
    assert dry.meta["B_GT"] > base.meta["B_GT"]
    chain = [p_in(simulate(CHAIN, c, seconds=1.0, seed=3)) for c in ("healthy", "chain_slight_wear")]
    assert chain[1] - chain[0] > 15.0


def test_effect_deadtime_reference_voltage():
    base = simulate(REF, seconds=1.0, seed=2)
    dt_ref = simulate(REF, seconds=1.0, seed=2, effects={"inverter_deadtime": None})
    dt_meas = simulate(GEAR, seconds=1.0, seed=2, effects={"inverter_deadtime": None})
    for h in (5, 7):
        assert line(dt_ref.i_abc[0], h * FE) > 5 * line(base.i_abc[0], h * FE)
    np.testing.assert_array_equal(dt_ref.i_abc, dt_meas.i_abc)  # same plant, only the voltage column differs
    # the measured terminal voltage holds the dead-time error the reference lacks: fundamental 4 U_dt / pi
    err = dt_meas.v_abc[0] - dt_ref.v_abc[0]
    assert line(err, FE) == pytest.approx(4 * EFFECTS["inverter_deadtime"].default / math.pi, rel=0.03)
    assert np.allclose(base.v_abc, simulate(REF, seconds=1.0, seed=2).v_abc)


def test_effect_flux_harmonics_6th_in_dq():
    base = simulate(GEAR, seconds=1.0, seed=2, encoder=True)
    fh = simulate(GEAR, seconds=1.0, seed=2, encoder=True, effects={"flux_harmonics": None})
    assert line(dq(fh)[0][1], 6 * FE) > 10 * line(dq(base)[0][1], 6 * FE)
    assert line(dq(fh)[0][0], 6 * FE) > 10 * line(dq(base)[0][0], 6 * FE)


def test_effect_voltage_lead_is_the_next_sample():
    """voltage_delay -1: the voltage channel records the interval after the current's (a drive
    reporting its command before it applies it); the plant is the same."""
    lead = simulate(REF, seconds=0.2, seed=2, effects={"voltage_delay": -1.0})
    plain = simulate(REF, seconds=0.2, seed=2)
    np.testing.assert_array_equal(lead.i_abc, plain.i_abc)
    np.testing.assert_allclose(lead.v_abc[:, :-1], plain.v_abc[:, 1:], atol=1e-9)  # the command: no channel noise


def test_effect_current_offset_fe_in_dq():
    base = simulate(GEAR, seconds=1.0, seed=2, encoder=True)
    off = simulate(GEAR, seconds=1.0, seed=2, encoder=True, effects={"current_offset": 0.05})
    assert line(dq(off)[0][0], FE) == pytest.approx(0.05, rel=0.1)
    assert line(dq(base)[0][0], FE) < 0.005


def test_effect_gain_mismatch_2fe_in_dq():
    base = simulate(GEAR, seconds=1.0, seed=2, encoder=True)
    gm = simulate(GEAR, seconds=1.0, seed=2, encoder=True, effects={"current_gain_mismatch": 0.03})
    amp = np.hypot(*dq(base)[0].mean(axis=1))
    assert line(dq(gm)[0][1], 2 * FE) == pytest.approx(0.03 * amp / 3, rel=0.1)  # negative sequence g I / 3
    assert line(dq(base)[0][1], 2 * FE) < 0.1 * 0.03 * amp / 3


def test_effect_voltage_delay_shifts_voltage():
    quiet = RigParams(sigma_v=0.0)
    base = simulate(GEAR, seconds=0.5, seed=2, rig=quiet)
    d3 = simulate(GEAR, seconds=0.5, seed=2, rig=quiet, effects={"voltage_delay": 3})
    np.testing.assert_allclose(d3.v_abc[:, 3:], base.v_abc[:, :-3], atol=1e-9)
    np.testing.assert_array_equal(d3.i_abc, base.i_abc)
    half = simulate(GEAR, seconds=0.5, seed=2, rig=quiet, effects={"voltage_delay": 0.5})
    k = np.exp(-2j * math.pi * FE * base.t)
    lag = np.angle(np.sum(half.v_abc[0] * k) / np.sum(base.v_abc[0] * k))
    assert lag == pytest.approx(-2 * math.pi * FE * 0.5 * TS, rel=0.02)


def test_effect_saturation_lowers_lq():
    def lq(rec):
        i_dq, v_dq = dq(rec)
        return -v_dq[0].mean() / (W_E * i_dq[1].mean())
    base = simulate(GEAR, seconds=1.0, seed=2, encoder=True)
    sat = simulate(GEAR, seconds=1.0, seed=2, encoder=True, effects={"magnetic_saturation": 0.15})
    assert lq(base) == pytest.approx(RIG.L_q, rel=5e-3)
    assert lq(sat) == pytest.approx(sat.meta["L_q"], rel=5e-3) and lq(sat) < 0.93 * RIG.L_q


def test_effect_resistance_drift_raises_vq():
    base = simulate(GEAR, seconds=1.0, seed=2, encoder=True)
    drift = simulate(GEAR, seconds=1.0, seed=2, encoder=True, effects={"resistance_drift": 0.05})
    dv = dq(drift)[1][1] - dq(base)[1][1]
    slope = np.polyfit(base.t, dv, 1)[0]
    assert slope == pytest.approx(base.meta["R_s"] * 0.05 * dq(base)[0][1].mean(), rel=0.1)  # V/s
    assert drift.meta["R_s_end"] == pytest.approx(drift.meta["R_s"] * 1.05)


def test_effect_speed_ripple_at_fgm():
    base = simulate(GEAR, seconds=1.0, seed=2, encoder=True)
    sr = simulate(GEAR, seconds=1.0, seed=2, encoder=True, effects=["speed_ripple"])
    ripple = line(sr.omega_e, FE / NP)
    assert ripple > 5 * line(base.omega_e, FE / NP)
    assert ripple == pytest.approx(sr.meta["speed_ripple_omega_e"], rel=0.1)


def test_null_record_has_no_effect_keys():
    rec = simulate(GEAR, seconds=0.05, seed=0)
    assert rec.meta["effects"] == "" and not any(k.startswith("effect.") for k in rec.meta)
    assert set(EFFECTS) == {"inverter_deadtime", "flux_harmonics", "voltage_delay", "current_offset",
                            "current_gain_mismatch", "resistance_drift", "magnetic_saturation", "speed_ripple"}


def test_bad_names_raise_input_error():
    with pytest.raises(InputError, match="gear_severe_wear"):
        simulate(GEAR, "broken", seconds=0.01)
    with pytest.raises(InputError, match="speed_ripple"):
        simulate(GEAR, seconds=0.01, effects={"warp_drive": 1.0})
    with pytest.raises(InputError, match="chain_missing_tooth"):
        simulate(CHAIN, "gear_no_lubricant", seconds=0.01)
    with pytest.raises(InputError):  # a lead (negative delay) of at most 4 samples
        simulate(GEAR, seconds=0.01, effects={"voltage_delay": -5.0})
    with pytest.raises(InputError, match="psi_5"):
        simulate(GEAR, seconds=0.01, effects={"flux_harmonics": {"psi_6": 0.01}})
    with pytest.raises(InputError, match="amplitudes"):
        simulate(GEAR, seconds=0.01, effects={"flux_harmonics": {"psi_5": -0.01}})
    with pytest.raises(InputError):
        simulate(GEAR, load_pct=-5.0, seconds=0.01)
    assert set(CONDITIONS) == {"healthy", "gear_slight_wear", "gear_severe_wear", "gear_no_lubricant", "gear_driving_wear",
                               "chain_offset", "chain_slight_wear", "chain_missing_tooth"}


def test_load_step_within_a_record():
    """A load step at t = 0.4 s: the record is the same as without it before the step, the speed
    loop answers it (speed overshoot, back within 0.3 % in 0.3 s) and the torque-producing current
    settles at the new load's, i_q = T / (1.5 p psi_m) within 2 %."""
    kw = dict(condition="healthy", load_pct=80.0, seconds=1.0, seed=4, encoder=True)
    plain = simulate(GEAR, **kw)
    rec = simulate(GEAR, **kw, load_step=(0.4, 50.0))
    k = int(0.4 / GEAR.ts)
    np.testing.assert_array_equal(rec.i_abc[:, :k], plain.i_abc[:, :k])
    i_dq, _ = abc_to_dq(rec.i_abc, rec.theta_e)
    w_ref = rec.omega_e[:k].mean()
    assert rec.omega_e[k:k + int(0.1 / GEAR.ts)].max() > 1.005 * w_ref
    after = slice(int(0.7 / GEAR.ts), None)
    assert abs(rec.omega_e[after].mean() / w_ref - 1.0) < 3e-3
    m = rec.meta
    t_after = m["T_load"] + (50.0 - 80.0) / 100.0 * GEAR.motor.rated_torque_nm + m["B_GT"] * m["omega_m"]
    assert i_dq[1, after].mean() == pytest.approx(t_after / (1.5 * GEAR.motor.pole_pairs * m["psi_m"]), rel=0.02)
    assert m["load_step_s"] == 0.4 and m["load_pct_after"] == 50.0
    with pytest.raises(InputError, match="load_step"):
        simulate(GEAR, **kw, load_step=(2.0, 50.0))
