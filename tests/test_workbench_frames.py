"""The workbench on drives of the family (bench.family, an independent simulator) where its frame
or its regression were wrong: the refits follow the recorded speed (speed steps), a record without
an encoder is turned from the current vector's frame onto the rotor's (MTPA) before anything is
fitted, and a controller that acts within the sample is read by the instrumented regression. The
simulator's own rotor angle and effect values are the reference."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from agent.baseline import identify_baseline
from agent.model import Signals
from agent.workbench.explain import explain
from agent.workbench.fitting import hold_offset, hold_period, onto_controller, onto_rotor, prepare
from bench.family import draw_drive, draw_effect, profile, simulate, simulate_detail, truth

pytestmark = pytest.mark.timeout(300)

ID0_NO_ENCODER = 20019  #: i_d = 0, no encoder: the current vector's frame is the rotor's
MTPA_NO_ENCODER = 20001  #: saliency 2.0, MTPA, no encoder: the current leads the rotor's q axis by 7-15 degrees
SPEED_STEP = 20006  #: encoder, a 15 % speed step in every record
ROUND_MTPA_STEP = 20522  #: saliency 1.02, MTPA, no encoder, a load step in every record, averaged current
DEAD_TIME = 20011  #: i_d = 0, encoder, switched inverter reporting its command: a dead time is revealable
LOADS = (40.0, 60.0, 90.0, 100.0)


def _offset_deg(sig, true_theta) -> float:
    n0 = true_theta.size - sig.n  # prepare drops the PLL's lock-in at the start
    return float(np.degrees(np.mean(np.angle(np.exp(1j * (sig.theta_e - np.unwrap(true_theta)[n0:]))))))


@pytest.mark.parametrize("load", [40.0, 100.0])
def test_a_current_frame_is_turned_onto_the_rotor(load):
    """The current vector's frame leads the rotor's by the MTPA current angle; turned by its active
    flux with an L_q 3 % off (identify's typical error), it is within half a degree of the rotor's."""
    drive = draw_drive(MTPA_NO_ENCODER)
    rec = simulate_detail(dataclasses.replace(drive, encoder=True), {}, load, 1.0, seed=200)[0]
    prep = prepare([dataclasses.replace(rec, theta_e=None, omega_e=None)], profile(drive, timing=True))
    before = _offset_deg(prep[0].sig, rec.theta_e)
    after = _offset_deg(onto_rotor(prep, 1.03 * drive.lq_h)[0].sig, rec.theta_e)
    assert before > 5.0, before
    assert abs(after) < 0.5, (before, after)


def test_an_id0_current_frame_is_kept(monkeypatch):
    """Under i_d = 0 the current's frame is the rotor's (within 0.05 degrees); turning it by the
    active flux with R_s unknown would add 0.4-0.8 degrees: explain turns only the records of a
    drive whose profile states MTPA."""
    import agent.workbench.explain as E

    drive = draw_drive(ID0_NO_ENCODER)
    rec = simulate_detail(dataclasses.replace(drive, encoder=True), {}, 60.0, 1.0, seed=201)[0]
    prof = profile(drive, timing=True)
    assert prof.sampling.current_reference == "id0"
    prep = prepare([dataclasses.replace(rec, theta_e=None, omega_e=None)], prof)
    assert abs(_offset_deg(prep[0].sig, rec.theta_e)) < 0.05

    class Reached(Exception):
        """explain got to this step (the frames are settled before the control's refit)."""

    def stop_at(step):
        def raise_(*a, **kw):
            raise Reached(step)
        return raise_

    monkeypatch.setattr(E, "onto_rotor", stop_at("turned"))
    monkeypatch.setattr(E, "control", stop_at("refitted"))
    for seed, first in ((ID0_NO_ENCODER, "refitted"), (MTPA_NO_ENCODER, "turned")):  # MTPA: turned
        with pytest.raises(Reached) as reached:
            _explained(seed, None)
        assert reached.value.args == (first,), seed


SPEED_STEP_NO_ENCODER = 20183  #: i_d = 0, no encoder, a load machine stepping the speed by 9 % in every record


def test_without_an_encoder_the_speed_follows_a_speed_step():
    """Through a speed step the followed current angle's speed (its rate less the shaft line) is
    0.24 % rms and at most 2.3 % off the simulator's rotor speed; that angle's speed low-passed below
    half the shaft frequency, which it replaced, 0.41 % rms (a ramp's corners smoothed over tens of
    ms); the agent's narrow PLL 1.4 % rms and 14 % at the step's edge."""
    from agent.workbench.fitting import SETTLE_S, follow_current, record_signals, shaft_lowpass

    drive = draw_drive(SPEED_STEP_NO_ENCODER)
    assert drive.excitation == "speed_step" and not drive.encoder
    prof = profile(drive, timing=True)
    rec = simulate_detail(dataclasses.replace(drive, encoder=True), {}, 60.0, 1.0, seed=200)[0]
    blind = dataclasses.replace(rec, theta_e=None, omega_e=None)
    pll = record_signals(blind, prof)
    n0 = int(SETTLE_S * prof.sampling.rate_hz)
    true = rec.omega_e[n0:]
    rms = lambda w: float(np.sqrt(np.mean((w[n0:] - true) ** 2)) / np.mean(true))  # noqa: E731
    assert np.ptp(true) > 0.05 * np.mean(true)  # the step is there
    peak = lambda w: float(np.max(np.abs(w[n0:] - true)) / np.mean(true))  # noqa: E731
    followed = follow_current(pll, blind)
    k = np.arange(followed.n)
    slope, offset = np.polyfit(k, followed.theta_e, 1)
    smoothed = (slope + np.gradient(shaft_lowpass(followed.theta_e - (slope * k + offset), followed))) / followed.ts
    assert rms(followed.omega_e) < 0.003 and peak(followed.omega_e) < 0.03
    assert rms(followed.omega_e) < 0.7 * rms(smoothed)
    assert rms(pll.omega_e) > 3 * rms(followed.omega_e) and peak(pll.omega_e) > 0.1


MTPA_LOAD_STEP = 20055  #: saliency 1.8, MTPA, no encoder, a load step in every record


@pytest.mark.parametrize("load", [40.0, 100.0])
def test_a_turned_frame_and_its_speed_follow_the_rotor_through_a_load_step_and_to_the_ends(load):
    """Through the load step (the current angle and the speed both move) and to the records' ends
    the turned frame stays within 0.01 rad of the simulator's rotor angle (before: 0.19 rad at the
    ends, where the low-pass was pinned to the last raw sample, and 0.06 at the step) and its speed
    within 0.05 % rms of the rotor's.""" 
    drive = draw_drive(MTPA_LOAD_STEP)
    rec = simulate_detail(dataclasses.replace(drive, encoder=True), {}, load, 1.0, seed=200)[0]
    prep = prepare([dataclasses.replace(rec, theta_e=None, omega_e=None)], profile(drive, timing=True))
    sig = onto_rotor(prep, drive.lq_h, drive.rs_ohm)[0].sig
    n0 = rec.theta_e.size - sig.n
    err = np.angle(np.exp(1j * (sig.theta_e - np.unwrap(rec.theta_e)[n0:])))
    assert np.max(np.abs(err - np.mean(err))) < 0.01
    assert abs(np.mean(err)) < 0.005
    speed = rec.omega_e[n0:]
    assert np.sqrt(np.mean((sig.omega_e - speed) ** 2)) < 5e-4 * np.mean(speed)


@functools.lru_cache(maxsize=None)
def _baseline(seed: int):
    drive = draw_drive(seed)
    prof = profile(drive, timing=True)
    return drive, prof, identify_baseline([simulate(drive, {}, 80.0, 1.0, seed=100 + j) for j in range(4)], prof,
                                          window_s=0.5)


def _explained(seed: int, effect: str | None):
    drive, prof, base = _baseline(seed)
    hidden = {effect: draw_effect(drive, effect, seed)} if effect else {}
    recs = [simulate(drive, hidden, load, 1.0, seed=200 + j) for j, load in enumerate(LOADS)]
    return drive, hidden, explain(base, prepare(recs, prof))


@pytest.mark.parametrize("seed", [SPEED_STEP, MTPA_NO_ENCODER, ROUND_MTPA_STEP])
def test_null_records_refit_near_their_noise_floor(seed):
    """Speed steps (the refit's rotation terms follow the recorded speed), a current frame (turned
    onto the rotor) and a nearly round machine's under MTPA through load steps (its current angle
    0.5-2 degrees, turned as well): the null control's held-out error is within 1.5x its noise
    floor, and nothing is claimed. Before: 1.6x, 5.3x, and 2.1x with a voltage delay claimed
    (the round machine's frame left in the current's)."""
    _, _, doc = _explained(seed, None)
    assert doc["nrmse_control"] < 1.5 * doc["noise_floor"], (doc["nrmse_control"], doc["noise_floor"])
    assert not [c["effect"] for c in doc["candidates"] if c["significant"]]


@pytest.mark.parametrize("seed", [SPEED_STEP, MTPA_NO_ENCODER])
def test_flux_harmonics_found_through_a_speed_step_and_without_an_encoder(seed):
    """A 5th space harmonic alone: first, significant, at least 2x the best wrong effect, psi_5 within
    20 %. Before: not found on either drive."""
    drive, hidden, doc = _explained(seed, "flux_harmonics")
    top = doc["candidates"][0]
    assert top["effect"] == "flux_harmonics" and top["significant"], top
    wrong = min(c["nrmse_after"] for c in doc["candidates"][1:] if c["nrmse_after"] is not None)
    assert wrong >= 2.0 * top["nrmse_after"], (wrong, top["nrmse_after"])
    draw = hidden["flux_harmonics"]
    for order, psi in zip(draw["orders"], draw["psi_wb"]):
        if psi >= 0.2 * max(draw["psi_wb"]):
            assert top["params"][f"psi_{order}_Wb"] == pytest.approx(psi, rel=0.2), (order, top["params"])


def test_a_hidden_offset_found_on_a_drive_whose_controller_acts_within_the_sample():
    """No computation delay: identify reads L_d, L_q by the instrumented regression, and the refits'
    one-step does so too (a missing offset's error would hide the difference there). The hidden
    sensor offsets (0.42 A) are found first, significant, and the voltage R_s o that holds them
    (the controller acts on these sensors) within 20 %. Before: 0.05 A, not significant (the
    one-step's L_q at 0.58x had taken the base apart)."""
    drive, hidden, doc = _explained(20000, "current_offset")
    assert drive.computation_delay == 0
    top = doc["candidates"][0]
    assert top["effect"] == "current_offset" and top["significant"], top
    o = np.asarray(hidden["current_offset"]["offset_a"])
    true = np.hypot((2 * o[0] - o[1] - o[2]) / 3.0, (o[1] - o[2]) / np.sqrt(3.0))
    assert top["params"]["offset_voltage_V"] == pytest.approx(true * drive.rs_ohm, rel=0.2)


def test_records_without_an_encoder_say_which_frame_they_are_judged_in():
    """No encoder and no stated current reference: explain says the frame is the current's and names
    the key that turns it; MTPA stated without an identified L_q: it says what is missing; i_d = 0 or
    an encoder: nothing to say."""
    from types import SimpleNamespace

    from agent.workbench.explain import frame_warnings

    def prof(ref, source="controller", rate=None):
        return SimpleNamespace(sampling=SimpleNamespace(
            current_reference=ref, current_source=source, voltage_hold="abc", control_rate_hz=rate,
            current_window_samples=None, rate_hz=10e3))

    pll, enc = [SimpleNamespace(encoder=False)], [SimpleNamespace(encoder=True)]
    assert "sampling.current_reference" in frame_warnings(prof(None), pll, {})[0]
    assert "nameplate.lq_h" in frame_warnings(prof("mtpa"), pll, {})[0]
    assert frame_warnings(prof("mtpa"), pll, {"Lq": (0.01, 0.05)}) == []
    assert frame_warnings(prof("id0"), pll, {}) == [] == frame_warnings(prof(None), enc, {})
    # an independent DAQ's current averages over the drive's hold: its update rate turns the frame
    assert "sampling.control_rate_hz" in frame_warnings(prof("id0", "independent"), pll, {})[0]
    assert "nameplate.lq_h" in frame_warnings(prof("id0", "independent", 8e3), pll, {})[0]
    assert frame_warnings(prof("id0", "independent", 8e3), pll, {"Lq": (0.01, 0.05)}) == []
    # point samples at the drive's own rate are the drive's instants (the rig's triggered DAQ): no turn
    assert frame_warnings(prof("id0", "independent", 10e3), pll, {}) == []
    assert hold_period(prof("id0", "independent", 10e3).sampling) is None
    assert hold_period(prof("id0", "independent", 8e3).sampling) == pytest.approx(1 / 8e3)
    assert hold_period(prof("id0", "controller", 8e3).sampling) is None


def test_a_dead_time_whose_fundamental_the_records_flux_takes_is_read_by_its_6fe_lines():
    """A family drive (i_d = 0, encoder, one speed) with a hidden 19.8 V dead time: its fundamental
    lies along the current, which each record's magnet flux takes, and only its 6 f_e lines are
    left (3-5 % of its response). They pin it: identifiable, first, significant, U_dt within 10 %
    of the simulator's value (with the old 10 % share floor it was "not identifiable")."""
    drive, hidden, doc = _explained(DEAD_TIME, "inverter_deadtime")
    top = doc["candidates"][0]
    assert top["effect"] == "inverter_deadtime" and top["significant"], doc["candidates"][:2]
    assert top["identifiability"]["unabsorbed_share"] < 0.1
    true = truth(drive, "inverter_deadtime", hidden["inverter_deadtime"], [])["U_dt_V"]
    assert top["params"]["U_dt_V"] == pytest.approx(true, rel=0.1)


@pytest.mark.parametrize("direction", [1.0, -1.0])
@pytest.mark.parametrize("ripple", [0.0, 0.6])
def test_the_frame_speed_loses_a_shaft_line_only_where_there_is_one(ripple, direction):
    """A followed frame's speed through a speed ramp (9 %, 40 ms), with white noise on the rate and
    a shaft-frequency ripple of ``ripple`` rad/s: ``frame_speed`` takes out that line within 15 % of
    its amplitude (the ramp leaks up to 0.08 rad/s into it over the 1 s record, adding or taking
    away with the ripple's phase) and keeps the ramp; without a ripple it takes out nothing (a ramp's corners and the
    noise project onto any frequency, and taken out as a line they left an error that speed_ripple
    claimed on two family null sets). The same in reverse rotation (``direction`` -1)."""
    from agent.workbench.fitting import frame_speed

    rng = np.random.default_rng(3)
    ts, n, p, w0 = 1 / 16000, 16000, 3, direction * 2 * np.pi * 60.0
    t = np.arange(n) * ts
    ramp = 0.09 * w0 * np.clip((t - 0.45) / 0.04, 0.0, 1.0)
    theta = np.cumsum(w0 + ramp) * ts
    line = ripple * np.cos(theta / p + 0.4)
    rate = w0 + ramp + line + rng.normal(0.0, 0.3, n)
    theta = np.cumsum(rate) * ts
    sig = Signals(np.zeros((2, n)), np.zeros((2, n)), theta, rate, ts, pole_pairs=p)
    taken = np.gradient(theta) / ts - frame_speed(theta, sig)
    if ripple == 0.0:
        assert np.all(taken == 0.0)
        return
    amp = np.sqrt(2.0) * np.std(taken)
    assert amp == pytest.approx(ripple, rel=0.15)
    assert np.corrcoef(taken, line)[0, 1] > 0.95


HOLD_DAQ = 20703  #: i_d = 0, no encoder, 6 pole pairs at 834 rad/s, a 5.1 kHz drive behind an asynchronous 8.3 kHz DAQ


@pytest.mark.parametrize("load", [40.0, 100.0])
def test_the_hold_offset_is_the_daq_current_less_the_controllers_samples(load):
    """Over each period the drive holds its voltage in abc, the DAQ's current (asynchronous: all
    phases of the period alike) averages j omega_e T^2 / 12 L^-1 v away from the controller's own
    samples, which the controller holds at i_d = 0. The simulator's true current at the DAQ's
    instants against its controller's samples: the d offset within 10 %."""
    drive = draw_drive(HOLD_DAQ)
    enc = dataclasses.replace(drive, encoder=True)
    rec, det = simulate_detail(enc, {}, load, 1.0, seed=200)
    sig = prepare([rec], profile(enc, timing=True))[0].sig
    n0 = rec.t.size - sig.n
    true = Signals.from_abc(rec.v_abc, det["i_true"], det["theta_e"], det["omega_e"], sig.ts, sig.pole_pairs)
    simulated = float(np.mean(true.i_dq[0][n0:]) - np.mean(det["i_d"]))  # the controller's: i_d = 0
    said = float(np.mean(hold_offset(sig, 1.0 / drive.control_rate_hz, drive.ld_h, drive.lq_h).real))
    assert abs(np.mean(det["i_d"])) < 0.05 * abs(simulated)
    assert said == pytest.approx(simulated, rel=0.1), (said, simulated)


def test_a_daq_current_frame_is_turned_onto_the_controllers():
    """The DAQ's current vector leads the rotor by the hold offset's angle (0.7-1.4 degrees at
    40-100 % load); turned onto the frame in which the controller's samples lie on q, with the
    inductances 5 % off, the frame is within a fifth of that of the rotor's."""
    drive = draw_drive(HOLD_DAQ)
    prof = profile(drive, timing=True)
    for load in (40.0, 100.0):
        rec = simulate_detail(dataclasses.replace(drive, encoder=True), {}, load, 1.0, seed=201)[0]
        prep = prepare([dataclasses.replace(rec, theta_e=None, omega_e=None)], prof)
        before = _offset_deg(prep[0].sig, rec.theta_e)
        turned = onto_controller(prep, 1.0 / prof.sampling.control_rate_hz, 1.05 * drive.ld_h, 0.95 * drive.lq_h)
        after = _offset_deg(turned[0].sig, rec.theta_e)
        assert before > 0.5, (load, before)
        assert abs(after) < 0.2 * before, (load, before, after)
    # an offset as large as the current (a drive updating 30x slower) carries no frame: left as it is
    assert onto_controller(prep, 30.0 / prof.sampling.control_rate_hz, drive.ld_h, drive.lq_h)[0] is prep[0]


def test_a_daq_behind_the_drives_hold_claims_no_voltage_path_once_the_update_rate_is_known():
    """Null records of the hold DAQ drive: with the drive's update rate stated, the control fits
    within 1.5x its noise floor and nothing is claimed. Before (the frame the DAQ's current's):
    4.5x, and a 0.33-sample advance of the voltage claimed at 86 % of the control's error."""
    _, _, doc = _explained(HOLD_DAQ, None)
    assert doc["nrmse_control"] < 1.5 * doc["noise_floor"], (doc["nrmse_control"], doc["noise_floor"])
    assert not [c["effect"] for c in doc["candidates"] if c["significant"]]


def test_the_rigs_triggered_daq_and_motulators_own_samples_are_not_turned():
    """The rig's DAQ point-samples at its drive's updates (control_rate_hz = rate_hz), motulator's
    records are its controller's samples: neither has a hold offset to turn by."""
    from pathlib import Path

    from agent.profile import load_profile

    root = Path(__file__).resolve().parent.parent
    for path in (root / "config/profiles/rig_gear.toml", root / "config/profiles/rig_chain.toml",
                 root / "bench/thirdparty/motulator_gear.toml"):
        assert hold_period(load_profile(path).sampling) is None, path


def _shaft_signals(amplitudes, p=3, omega_e=600.0, ts=1e-4, n=9000, kept=()):
    """Frames whose angle carries a shaft-frequency speed ripple of ``amplitudes`` (rad/s), one per
    record, that their speed leaves out (as :func:`agent.workbench.fitting.frame_speed` does), but
    for the records in ``kept``, whose speed keeps it (a line the frame's gate missed)."""
    from types import SimpleNamespace

    t = np.arange(n) * ts
    w_r = omega_e / p
    return [SimpleNamespace(theta_e=omega_e * t + a / w_r * np.sin(w_r * t + 0.3), ts=ts, pole_pairs=p, n=n,
                            omega_e=omega_e + (a * np.cos(w_r * t + 0.3) if j in kept else np.zeros(n)))
            for j, a in enumerate(amplitudes)]


def test_a_shaft_line_in_a_few_records_only_contradicts_a_once_per_revolution_ripple():
    """A once-per-revolution torque ripples every record at one speed alike: lines of 0.5-0.6 rad/s
    in all four stand (None: the fit's figures); one record's line and none in the others, or two of
    four, is no such ripple (explain marks the row ``contradicted``; the note counts the records)."""
    from agent.effects.speed_ripple import in_some_records_only

    assert in_some_records_only(_shaft_signals([0.5, 0.55, 0.6, 0.5])) is None
    assert in_some_records_only(_shaft_signals([0.0, 0.0, 0.0, 0.0])) is None  # no line anywhere: nothing refuted
    # a true ripple whose line one record's speed kept (family drive 20022, a speed step) is in every record
    assert in_some_records_only(_shaft_signals([0.5, 0.55, 0.6, 0.5], kept=(3,))) is None
    for amps, seen in (([0.0, 0.0, 0.0, 0.6], 1), ([0.01, 0.02, 0.5, 0.6], 2)):
        assert f"in {seen} of 4 records only" in in_some_records_only(_shaft_signals(amps)), amps


LOAD_RIPPLE_AT_SHAFT = 20110  #: MTPA, no encoder, a load ripple 0.06 Hz off the shaft frequency in one record of four


def test_a_load_ripple_near_the_shaft_frequency_in_one_record_is_not_claimed_as_a_speed_ripple():
    """Null drive 20110: one record's load ripple lies 0.06 Hz off f_r (0.64 rad/s of true shaft-line
    speed ripple in it, under 0.05 in the others). Before, speed_ripple was claimed (21 % of the
    control's error, p = 0.00076); now it is contradicted and nothing is claimed."""
    _, _, doc = _explained(LOAD_RIPPLE_AT_SHAFT, None)
    row = next(c for c in doc["candidates"] if c["effect"] == "speed_ripple")
    assert row["contradicted"] and "1 of 4 records only" in row["note"], row
    assert not [c["effect"] for c in doc["candidates"] if c["significant"]]
