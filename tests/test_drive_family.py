"""bench.family against independent references: the dq steady state, the torque at the requested
load, Faraday's law on the magnet's harmonics, the dead-time loss, the voltage path's delay and
advance regressed from the applied voltage, the ADC step, seeds, and the drawn ranges."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from bench.drive_family import EFFECTS, draw_drive, draw_effect, profile, revealable, simulate, simulate_detail, truth
from bench.family.drive import COPPER_PER_K
from bench.family.effects import HARMONIC_SHARE, saturation_map
from bench.family.machine import currents_from_flux, flux_from_currents

SQRT3 = math.sqrt(3.0)
QUIET = dict(excitation="constant", current_sampling="centre", encoder=True)


def clarke(x):
    return (2 * x[0] - x[1] - x[2]) / 3.0, (x[1] - x[2]) / SQRT3


def to_dq(x_abc, theta):
    """Complex d + j q of a (3, N) phase quantity at the angles ``theta`` (amplitude invariant)."""
    alpha, beta = clarke(x_abc)
    return (alpha + 1j * beta) * np.exp(-1j * theta)


def mid_angle(detail, rate_hz):
    return detail["theta_e"] + 0.5 * detail["omega_e"] / rate_hz


def sign_free(x):
    """Without the common mode (the star point's)."""
    return x - x.mean(axis=0)


# ------------------------------------------------------------------------- draws (no simulation)


@pytest.fixture(scope="module")
def drives():
    return [draw_drive(seed) for seed in range(200)]


def test_every_attribute_is_drawn_over_its_range(drives):
    values = {f.name: [getattr(d, f.name) for d in drives] for f in dataclasses.fields(drives[0])}
    assert set(values["pole_pairs"]) == {2, 3, 4, 5, 6}
    for name, lo, hi in (("rated_power_w", 400, 15000), ("rated_speed_rpm", 1000, 3000), ("u_dc_v", 300, 600),
                         ("rate_hz", 8000, 32000), ("winding_temp_c", 30, 110)):
        x = np.array(values[name])
        assert lo <= x.min() < lo + 0.15 * (hi - lo) and hi - 0.15 * (hi - lo) < x.max() <= hi, name
    for name in ("updates_per_carrier", "inverter", "voltage_hold", "computation_delay", "angle_compensation",
                 "current_reference", "mechanics", "excitation", "voltage_source", "command_logged_as",
                 "current_sampling", "encoder", "adc_bits"):
        assert len(set(values[name])) >= 2, name
    assert set(values["adc_bits"]) == set(range(12, 17))
    assert set(values["excitation"]) == {"constant", "load_ripple", "load_step", "speed_step"}
    assert set(values["current_sampling"]) == {"centre", "average", "async"}
    z = np.array([d.v_rated_peak / d.i_rated_peak for d in drives])
    w = np.array([d.rated_speed_rpm * math.pi / 30 * d.pole_pairs for d in drives])
    r_pu = np.array(values["rs_ohm"]) / z
    x_q = w * np.array(values["lq_h"]) / z
    saliency = np.array(values["lq_h"]) / np.array(values["ld_h"])
    for x, lo, hi in ((r_pu, 0.02, 0.08), (x_q, 0.2, 0.8), (saliency, 1.0, 2.5)):
        assert lo <= x.min() < lo + 0.1 * (hi - lo) and hi - 0.1 * (hi - lo) < x.max() <= hi
    fraction = np.array([d.current_bandwidth_hz / d.control_rate_hz for d in drives])
    assert 0.04 <= fraction.min() < 0.05 and 0.13 < fraction.max() <= 0.15
    full_scale = np.array([d.current_full_scale_a / d.i_rated_peak for d in drives])
    assert 2.0 <= full_scale.min() < 2.1 and 2.9 < full_scale.max() <= 3.0
    rated_w = np.array([d.omega_m_rated for d in drives])
    torque = np.array(values["rated_torque_nm"])
    for x, lo, hi in ((np.array(values["inertia_kgm2"]) * rated_w / torque, 0.02, 0.5),  # start time, s
                      (np.array(values["friction_nm_s"]) * rated_w / torque, 0.003, 0.02),
                      (np.array(values["current_noise_a"]) / np.array([d.i_rated_peak for d in drives]), 0.0005, 0.005),
                      (np.array(values["voltage_full_scale_v"]) / np.array(values["u_dc_v"]), 0.7, 1.0),
                      (np.array(values["driven_teeth"]) / np.array(values["driving_teeth"]), 1.0, 5.0),
                      (np.array(values["rated_voltage_v"]) * math.sqrt(2) / np.array(values["u_dc_v"]), 0.78, 0.92)):
        assert lo - 1e-9 <= x.min() < lo + 0.15 * (hi - lo) and hi - 0.15 * (hi - lo) < x.max() <= hi + 0.03 * hi
    for name, rel in (("ctrl_ld_h", "ld_h"), ("ctrl_lq_h", "lq_h"), ("ctrl_psi_m_wb", "psi_m_wb")):
        err = np.array(values[name]) / np.array(values[rel]) - 1
        assert -0.08 <= err.min() < -0.06 and 0.06 < err.max() <= 0.08, name
    for mech, lo, hi in (("speed_loop", 3, 20), ("load_machine", 10, 40)):
        bw = np.array([d.speed_bandwidth_hz for d in drives if d.mechanics == mech])
        assert lo <= bw.min() < lo + 0.2 * (hi - lo) and hi - 0.2 * (hi - lo) < bw.max() <= hi
    integral = np.array([d.integral_time_s * 2 * math.pi * d.current_bandwidth_hz for d in drives])
    assert 4 <= integral.min() < 4.5 and 9.5 < integral.max() <= 10  # alpha_c T_i (L_q/R_s is longer)
    delays = np.array([d.voltage_filter_delay for d in drives if d.voltage_source == "measured"])
    assert {0.0, 1.0} <= set(delays) and ((delays > 0) & (delays < 1)).any()
    for d in drives:
        if d.current_sampling == "async":
            assert d.voltage_source == "measured" and abs(d.control_rate_hz / d.rate_hz - 1) >= 0.05
        else:
            assert d.control_rate_hz == d.rate_hz
        assert d.voltage_hold == "abc" or d.inverter == "averaged"
        assert not (d.angle_compensation and d.voltage_hold == "dq")
        assert 0.2 * d.rated_speed_rpm < d.operating_speed_rpm <= d.rated_speed_rpm


def test_rating_is_consistent_with_the_machine(drives):
    """P = T omega; the rated point (maximum torque per ampere at rated current and speed) needs the
    rated voltage and gives the rated torque: an independent minimisation over the current angle."""
    for d in drives[:40]:
        assert d.rated_torque_nm * d.rated_speed_rpm * math.pi / 30 == pytest.approx(d.rated_power_w, rel=1e-9)
        gamma = np.linspace(0, 0.49 * math.pi, 4001)
        i_d, i_q = -d.i_rated_peak * np.sin(gamma), d.i_rated_peak * np.cos(gamma)
        torque = 1.5 * d.pole_pairs * (d.psi_m_wb * i_q + (d.ld_h - d.lq_h) * i_d * i_q)
        k = int(np.argmax(torque))
        w = d.rated_speed_rpm * math.pi / 30 * d.pole_pairs
        v = math.hypot(d.rs_ohm * i_d[k] - w * d.lq_h * i_q[k], d.rs_ohm * i_q[k] + w * (d.psi_m_wb + d.ld_h * i_d[k]))
        assert torque[k] == pytest.approx(d.rated_torque_nm, rel=1e-4)
        assert v == pytest.approx(d.v_rated_peak, rel=1e-4)
        assert d.v_rated_peak < d.u_dc_v / SQRT3


def test_seeds_reproducible_and_overrides_change_only_their_attribute():
    assert draw_drive(11) == draw_drive(11)
    assert draw_drive(11) != draw_drive(12)
    base, moved = draw_drive(11), draw_drive(11, encoder=not draw_drive(11).encoder)
    diff = {f.name for f in dataclasses.fields(base) if getattr(base, f.name) != getattr(moved, f.name)}
    assert diff == {"encoder"}
    json.dumps(dataclasses.asdict(base))
    with pytest.raises(TypeError, match="no_such"):
        draw_drive(1, no_such=3)
    d = draw_drive(3, **QUIET)
    eff = {"current_offset": draw_effect(d, "current_offset", 4)}
    a, b, c = (simulate(d, eff, 70, 0.05, seed) for seed in (5, 5, 6))
    assert np.array_equal(a.i_abc, b.i_abc) and np.array_equal(a.v_abc, b.v_abc)
    assert not np.array_equal(a.i_abc, c.i_abc)
    assert draw_effect(d, "magnetic_saturation", 2) == draw_effect(d, "magnetic_saturation", 2)


def test_effect_draws_cover_their_families():
    d = draw_drive(21)
    draws = {k: [draw_effect(d, k, s) for s in range(150)] for k in EFFECTS}
    mixes = {tuple(x["orders"]) for x in draws["flux_harmonics"]}
    assert mixes == {(5,), (7,), (5, 7), (5, 7, 11, 13)}
    for x in draws["flux_harmonics"]:
        for h, psi in zip(x["orders"], x["psi_wb"]):
            lo, hi = HARMONIC_SHARE[h]
            assert lo * d.psi_m_wb <= psi <= hi * d.psi_m_wb
    offsets = np.abs(np.array([x["offset_a"] for x in draws["current_offset"]])) / d.i_rated_peak
    assert offsets.max() <= 0.03 and (offsets == 0).any() and offsets[offsets > 0].min() >= 0.005
    gains = [truth(d, "current_gain_mismatch", x, []) for x in draws["current_gain_mismatch"]]
    g = np.abs([[t["gain_b"], t["gain_c"]] for t in gains])
    assert g.max() <= 0.05 + 1e-12 and ((g >= 0.01 - 1e-12) | (g < 1e-12)).all() and (g.max(axis=1) >= 0.01).all()
    drops = [truth(d, "magnetic_saturation", x, [])["lq_drop_at_rated"] for x in draws["magnetic_saturation"][:30]]
    assert 0.05 <= min(drops) and max(drops) <= 0.30
    extra = [x["extra_samples"] for x in draws["voltage_delay"]]
    assert -1 <= min(extra) < -0.5 and 1.5 < max(extra) <= 2 and min(abs(e) for e in extra) >= 0.25


def test_flux_map_is_reciprocal_and_its_truth_is_the_chord_drop():
    """One energy function: d psi_d/d i_q = d psi_q/d i_d everywhere (finite differences of the
    inverted map); the truth is the chord L_q drop at rated current."""
    d = draw_drive(8)
    draw = draw_effect(d, "magnetic_saturation", 3)
    fm = saturation_map(d, draw)
    rng = np.random.default_rng(0)
    h = 1e-4 * d.i_rated_peak
    for i_d, i_q in rng.uniform(-1.5, 1.5, (20, 2)) * d.i_rated_peak:
        dpsi_d_diq = (flux_from_currents(i_d, i_q + h, fm)[0] - flux_from_currents(i_d, i_q - h, fm)[0]) / (2 * h)
        dpsi_q_did = (flux_from_currents(i_d + h, i_q, fm)[1] - flux_from_currents(i_d - h, i_q, fm)[1]) / (2 * h)
        assert dpsi_d_diq == pytest.approx(dpsi_q_did, rel=1e-5, abs=1e-9)
        assert np.allclose(currents_from_flux(*flux_from_currents(i_d, i_q, fm), fm), (i_d, i_q), atol=1e-9)
    psi_q = flux_from_currents(0.0, d.i_rated_peak, fm)[1]
    assert truth(d, "magnetic_saturation", draw, [])["lq_drop_at_rated"] == pytest.approx(
        1 - psi_q / (d.lq_h * d.i_rated_peak), rel=1e-12)
    assert flux_from_currents(0.0, d.i_rated_peak, fm)[0] < d.psi_m_wb  # cross-saturation lowers psi_d


def test_profile_and_nameplate():
    d = draw_drive(5, voltage_source="reference", current_sampling="centre")
    plain, plate = profile(d), profile(d, nameplate=True)
    assert plain.nameplate is None and plain.sampling.voltage_source == "reference"
    assert plain.motor.rated_torque_nm == d.rated_torque_nm and plain.sampling.rate_hz == d.rate_hz
    n = plate.nameplate
    for got, true in ((n.rs_ohm, d.rs_20c_ohm), (n.psi_m_wb, d.psi_m_wb), (n.ld_h, d.ld_h), (n.lq_h, d.lq_h)):
        assert abs(got / true - 1) <= 0.05 and got != true
    assert n.rs_ohm * (1 + COPPER_PER_K * (n.winding_temp_c - 20)) == pytest.approx(d.rs_ohm, rel=0.06)
    assert profile(draw_drive(5, voltage_source="measured")).sampling.voltage_source == "measured"


def test_revealable_follows_the_physics():
    d = draw_drive(9, voltage_source="measured", encoder=True)
    assert not revealable(d, "inverter_deadtime", (40, 60))[0]
    assert revealable(dataclasses.replace(d, voltage_source="reference"), "inverter_deadtime", (40, 60))[0]
    assert not revealable(d, "magnetic_saturation", (80, 80), "constant")[0]
    assert revealable(d, "magnetic_saturation", (40, 100), "constant")[0]
    assert revealable(d, "magnetic_saturation", (80,), "load_step")[0]
    assert not revealable(d, "voltage_delay", (80,), "constant")[0]
    assert not revealable(d, "speed_ripple", (80,))[0]
    assert revealable(dataclasses.replace(d, encoder=False), "speed_ripple", (80,))[0]
    assert all(revealable(d, k, (40, 100), "load_step")[1] for k in EFFECTS)


# ------------------------------------------------------------------------------- simulations


@pytest.mark.parametrize("inverter", ["averaged", "switched"])
def test_steady_state_matches_the_dq_equations(inverter):
    """Record means (measured voltage over [t_k, t_k + T_s], currents at t_k, encoder angle) against
    v_d = R i_d - w psi_q, v_q = R i_q + w psi_d with the drive's own R_s, L_d, L_q, psi_m."""
    d = draw_drive(2, inverter=inverter, voltage_source="measured", voltage_filter_delay=0.0, **QUIET)
    rec = simulate(d, {}, 80, 0.3, 1)
    theta = rec.theta_e + 0.5 * rec.omega_e / d.rate_hz
    v = to_dq(rec.v_abc, theta)
    i = to_dq(rec.i_abc, rec.theta_e)
    w = rec.omega_e.mean()
    i_d, i_q = i.real.mean(), i.imag.mean()
    psi_d, psi_q = d.psi_m_wb + d.ld_h * i_d, d.lq_h * i_q
    noise = 3 * d.voltage_noise_v / math.sqrt(rec.n) + 0.002 * d.v_rated_peak
    assert v.real.mean() == pytest.approx(d.rs_ohm * i_d - w * psi_q, abs=noise)
    assert v.imag.mean() == pytest.approx(d.rs_ohm * i_q + w * psi_d, abs=noise)
    assert w == pytest.approx(d.omega_m_operating * d.pole_pairs, rel=1e-3)


@pytest.mark.parametrize("mechanics", ["load_machine", "speed_loop"])
def test_torque_is_the_requested_load(mechanics):
    """With a saturated MTPA machine: the mean of 1.5 p (psi_d i_q - psi_q i_d) (independent of the
    kernel's torque) less the friction is the requested shaft torque."""
    d = draw_drive(4, mechanics=mechanics, current_reference="mtpa", **QUIET)
    sat = {"magnetic_saturation": draw_effect(d, "magnetic_saturation", 1)}
    _, det = simulate_detail(d, sat, 65, 0.3, 2)
    torque = 1.5 * d.pole_pairs * (det["psi_d"] * det["i_q"] - det["psi_q"] * det["i_d"])
    assert np.allclose(torque, det["torque"], rtol=1e-9, atol=1e-9)
    fm = saturation_map(d, sat["magnetic_saturation"])
    psi = [flux_from_currents(a, b, fm) for a, b in zip(det["i_d"][::97], det["i_q"][::97])]
    assert np.allclose(np.array(psi).T, [det["psi_d"][::97], det["psi_q"][::97]], atol=1e-9)
    shaft = torque.mean() - d.friction_nm_s * det["omega_e"].mean() / d.pole_pairs
    assert shaft == pytest.approx(0.65 * d.rated_torque_nm, rel=2e-3)


def test_back_emf_harmonics_follow_faraday():
    """At no load (i ~ 0) the phase-a back-EMF e = v - R i - L di/dt (a surface-mounted machine)
    carries h w psi_h at h f_e, with the phase of -d/dt psi_h cos(h theta + phi_h)."""
    d = draw_drive(6, ld_h=draw_drive(6).lq_h, inverter="averaged", voltage_hold="abc", mechanics="load_machine",
                   **QUIET)
    draw = {"orders": [5, 7, 11], "psi_wb": [0.02 * d.psi_m_wb, 0.01 * d.psi_m_wb, 0.004 * d.psi_m_wb],
            "phase_rad": [0.3, 2.0, -1.0]}
    rec, det = simulate_detail(d, {"flux_harmonics": draw}, 0, 0.2, 3)
    i = det["i_true"]
    ts = 1 / d.rate_hz
    v = det["v_applied"][:, :-1]
    e = v - d.rs_ohm * 0.5 * (i[:, 1:] + i[:, :-1]) - d.lq_h * np.diff(i, axis=1) / ts
    e = sign_free(e)[0]
    theta = mid_angle(det, d.rate_hz)[:-1]
    w = det["omega_e"].mean()
    orders = [1, *draw["orders"]]
    basis = np.column_stack([f(h * theta) for h in orders for f in (np.cos, np.sin)])
    coef = np.linalg.lstsq(basis, e, rcond=None)[0].reshape(-1, 2)
    for (a, b), h, psi, phi in zip(coef[1:], draw["orders"], draw["psi_wb"], draw["phase_rad"]):
        expected = h * w * psi * np.sinc(h * w * ts / (2 * np.pi))  # -h w psi sin(h th + phi), interval average
        assert math.hypot(a, b) == pytest.approx(expected, rel=0.03)
        assert np.angle((a - 1j * b) / (expected * np.exp(1j * (phi + np.pi / 2)))) == pytest.approx(0, abs=0.05)


@pytest.mark.parametrize("inverter", ["switched", "averaged"])
def test_deadtime_loss_is_u_dt_sign_i(inverter):
    """Applied minus commanded phase voltage (common mode removed) against -U_dt sign(i_x), where every
    phase current is beyond its knee (the switched inverter: the per-edge dead time and device drop)."""
    d = draw_drive(12, inverter=inverter, voltage_hold="abc", voltage_source="reference",
                   command_logged_as="phase", **QUIET)
    draw = draw_effect(d, "inverter_deadtime", 0)
    rec, det = simulate_detail(d, {"inverter_deadtime": draw}, 90, 0.2, 4)
    u_dt = truth(d, "inverter_deadtime", draw, [rec])["U_dt_V"]
    k = d.computation_delay
    applied = det["v_applied"][:, k:-1] if k else det["v_applied"][:, :-1]
    command = rec.v_abc[:, : applied.shape[1]]
    loss = sign_free(applied - command)
    i = det["i_true"][:, k: k + applied.shape[1]]
    knee = 4 * truth(d, "inverter_deadtime", draw, [rec])["knee_A"] + 0.05 * d.i_rated_peak
    away = (np.abs(i) > knee).all(axis=0) & (np.abs(np.roll(i, -1, axis=1)) > knee).all(axis=0)
    assert away.mean() > 0.3
    expected = -u_dt * sign_free(np.sign(i))
    slope = np.sum(loss[:, away] * expected[:, away]) / np.sum(expected[:, away] ** 2)
    assert slope == pytest.approx(1.0, abs=0.04)
    assert 2.0 <= u_dt <= 21.0


CONFIGS = [
    dict(voltage_source="measured", voltage_filter_delay=0.0, inverter="switched"),
    dict(voltage_source="measured", voltage_filter_delay=0.4, inverter="averaged", voltage_hold="abc"),
    dict(voltage_source="measured", voltage_filter_delay=1.0, inverter="averaged", voltage_hold="dq"),
    dict(voltage_source="reference", inverter="switched", computation_delay=1, angle_compensation=True,
         command_logged_as="phase"),
    dict(voltage_source="reference", inverter="averaged", voltage_hold="abc", computation_delay=1,
         angle_compensation=True, command_logged_as="dq"),
    dict(voltage_source="reference", inverter="averaged", voltage_hold="abc", computation_delay=0,
         angle_compensation=False, command_logged_as="dq"),
    dict(voltage_source="reference", inverter="averaged", voltage_hold="dq", computation_delay=0,
         angle_compensation=False),
    dict(voltage_source="reference", inverter="averaged", voltage_hold="dq", computation_delay=1,
         angle_compensation=False),
]


@pytest.mark.parametrize("extra", [0.0, 0.6])
@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: "-".join(str(v) for v in c.values()))
def test_delay_and_advance_truth_from_the_applied_voltage(config, extra):
    """The regression of the applied dq voltage (its interval average at the mid angle) on the
    reported one finds the shift d (least residual over a fine grid of shifts) and the rotation
    (d + a) omega_e T_s of the truth; the load step and the loop's noise make the shift sharp.
    Converting both at the same angles keeps the regression independent of the truth's convention."""
    d = draw_drive(14, **{**QUIET, "excitation": "load_step", **config})
    effects = {"voltage_delay": {"extra_samples": extra}} if extra else {}
    rec, det = simulate_detail(d, effects, 60, 0.25, 5)
    want = truth(d, "voltage_delay", effects.get("voltage_delay", {}), [rec])
    theta = mid_angle(det, d.rate_hz)
    smooth = np.hanning(11) / np.hanning(11).sum()  # the same low-pass on both: a fractional delay is a
    applied = np.convolve(to_dq(det["v_applied"], theta), smooth, "same")  # delay below the Nyquist band
    reported = np.convolve(to_dq(rec.v_abc, theta), smooth, "same")
    k = np.arange(rec.n, dtype=float)
    inner = slice(16, rec.n - 16)
    best = None
    for shift in np.arange(-2.0, 3.0001, 0.05):
        moved = np.interp(k - shift, k, applied.real) + 1j * np.interp(k - shift, k, applied.imag)
        gain = np.vdot(reported[inner], moved[inner]) / np.vdot(reported[inner], reported[inner])
        resid = np.sum(np.abs(moved[inner] - gain * reported[inner]) ** 2)
        if best is None or resid < best[0]:
            best = (resid, shift, gain)
    _, shift, gain = best
    wts = det["omega_e"].mean() / d.rate_hz
    assert shift == pytest.approx(want["delay_samples"], abs=0.051)
    assert np.angle(gain) / wts - want["delay_samples"] == pytest.approx(want["advance_samples"], abs=0.06)
    assert abs(gain) == pytest.approx(1.0, abs=0.01)


def test_quantisation_step_and_noise():
    d = draw_drive(15, adc_bits=12, voltage_adc_bits=12, voltage_source="measured", **QUIET)
    rec = simulate(d, {}, 50, 0.1, 6)
    step_i = 2 * d.current_full_scale_a / 2 ** 12
    step_v = 2 * d.voltage_full_scale_v / 2 ** 12
    assert np.allclose(rec.i_abc / step_i, np.round(rec.i_abc / step_i), atol=1e-6)
    assert np.allclose(rec.v_abc / step_v, np.round(rec.v_abc / step_v), atol=1e-6)
    assert np.min(np.diff(np.unique(rec.i_abc[0]))) == pytest.approx(step_i, rel=1e-6)


def test_sensor_offsets_gains_and_their_truth():
    """The recorded currents are (1 + g_x) i_x + o_x of the true currents (interval-averaged
    sampling: the true interval average), and the truth's definitions."""
    d = draw_drive(16, **{**QUIET, "current_sampling": "average", "current_noise_a": 1e-9, "adc_bits": 16})
    eff = {"current_offset": {"offset_a": [0.01 * d.i_rated_peak, -0.02 * d.i_rated_peak, 0.0]},
           "current_gain_mismatch": {"gain_error": [0.01, 0.04, -0.02]}}
    rec, det = simulate_detail(d, eff, 80, 0.1, 7)
    x = det["i_true"]
    for ph in range(3):
        a, b = np.polyfit(x[ph], rec.i_abc[ph], 1)
        assert a == pytest.approx(1 + eff["current_gain_mismatch"]["gain_error"][ph], abs=0.01)
        assert b == pytest.approx(eff["current_offset"]["offset_a"][ph], abs=0.01 * d.i_rated_peak)
    o = truth(d, "current_offset", eff["current_offset"], [rec])["offset_A"]
    assert o == pytest.approx(math.hypot(0.04 / 3, 0.02 / SQRT3) * d.i_rated_peak, rel=1e-9)  # alpha, beta
    g = truth(d, "current_gain_mismatch", eff["current_gain_mismatch"], [rec])
    assert g["gain_b"] == pytest.approx(1.04 / 1.01 - 1) and g["gain_c"] == pytest.approx(0.98 / 1.01 - 1)


def test_resistance_drift_and_speed_ripple_truths():
    d = draw_drive(17, **{**QUIET, "encoder": False, "mechanics": "speed_loop"})
    drift = draw_effect(d, "resistance_drift", 1)
    ripple = draw_effect(d, "speed_ripple", 1)
    recs, dets = zip(*(simulate_detail(d, {"resistance_drift": drift, "speed_ripple": ripple}, load, 0.5, s)
                       for s, load in enumerate((60, 100))))
    slopes = [np.gradient(det["r_s"], rec.t)[rec.n // 2] for rec, det in zip(recs, dets)]
    assert truth(d, "resistance_drift", drift, recs)["dR_dt_ohm_per_s"] == pytest.approx(np.mean(slopes), rel=1e-3)
    rise = [det["r_s"][-1] / det["r_s"][0] - 1 for det in dets]
    assert all(0.5 * drift["initial_rate_per_s"] * 0.5 < r < 1.5 * drift["initial_rate_per_s"] * 0.5 for r in rise)
    assert recs[0].meta["R_s_start_ohm"] != recs[1].meta["R_s_start_ohm"]  # a different level per record
    amp = truth(d, "speed_ripple", ripple, recs)["omega_e_ripple_rad_s"]
    quiet = simulate(d, {}, 60, 0.5, 0).meta["omega_e_ripple_rad_s"]
    assert amp > 20 * quiet and recs[0].theta_e is None


def test_records_are_valid_contract_records(tmp_path):
    """Each sampling mode's record passes the project's validation against the drive's profile and
    survives the NPZ round trip with its meta."""
    from agent.records import load_record, save_record

    for sampling in ("centre", "average", "async"):
        d = draw_drive(18, current_sampling=sampling, encoder=sampling != "async")
        rec = simulate(d, {"current_offset": draw_effect(d, "current_offset", 1)}, 80, 0.05, 1)
        back = load_record(save_record(rec, tmp_path / f"{sampling}.npz"), profile(d), min_samples=rec.n)
        assert np.array_equal(back.i_abc, rec.i_abc) and back.meta["drive_seed"] == 18
        assert (back.theta_e is None) == (sampling == "async")
        assert json.loads(back.meta["effects"])["current_offset"]["offset_a"]


def test_every_effect_draws_on_many_drives():
    """Each effect's draw succeeds on 60 drawn drives (the saturation draw once asked brentq for a
    target its cross term alone already exceeded)."""
    from bench.family import EFFECTS, draw_drive, draw_effect

    for seed in range(20000, 20060):
        drive = draw_drive(seed)
        for effect in EFFECTS:
            assert draw_effect(drive, effect, seed), (seed, effect)


def test_load_of_a_salient_mtpa_drive_counts_its_reluctance_torque():
    """agent.identify.operating_point on a family drive (saliency 2, MTPA, i_d < 0) with its exact
    nameplate: load_pct is the electromagnetic torque 1.5 p (psi_m i_q + (L_d - L_q) i_d i_q) over the
    rated torque, within 1 %-point of the requested shaft torque plus the friction's; without L_d and
    L_q on the nameplate the magnet torque alone reads low by the reluctance share."""
    from agent.identify import operating_point, record_signals
    from agent.profile import Nameplate

    d = draw_drive(20001, current_reference="mtpa", **QUIET)
    assert d.lq_h / d.ld_h > 1.5
    rec, det = simulate_detail(d, {}, 80, 0.3, 1)
    friction_pct = 100 * d.friction_nm_s * det["omega_e"].mean() / d.pole_pairs / d.rated_torque_nm
    exact = Nameplate(psi_m_wb=d.psi_m_wb, ld_h=d.ld_h, lq_h=d.lq_h)
    prof = dataclasses.replace(profile(d), nameplate=exact)
    load = operating_point(record_signals(rec, prof), prof)["load_pct"]
    assert load == pytest.approx(80 + friction_pct, abs=1.0)
    magnet = dataclasses.replace(prof, nameplate=Nameplate(psi_m_wb=d.psi_m_wb))
    reluctance = 100 * 1.5 * d.pole_pairs * (d.ld_h - d.lq_h) * np.mean(det["i_d"] * det["i_q"]) / d.rated_torque_nm
    assert reluctance > 2.0
    assert operating_point(record_signals(rec, magnet), magnet)["load_pct"] == pytest.approx(load - reluctance, abs=0.5)


def test_an_event_a_rounding_apart_from_the_next_is_integrated_not_divided_by_zero():
    """Drive 20432 (a record clock asynchronous to its carrier): at 90 % load two event times fell
    a rounding apart, the integrator's step count came out 0 and the family run ended that drive in
    a ZeroDivisionError. Such a span is one RK4 step."""
    rec = simulate(draw_drive(20432), {}, 90.0, 1.0, seed=202)
    assert np.all(np.isfinite(rec.i_abc)) and np.all(np.isfinite(rec.v_abc))
