"""The drive's voltage path (agent.voltage_path): stated in the profile, applied by the
workbench before it fits, checked against the independent reference bench.family.effects.voltage_path."""

import numpy as np
import pytest

from agent.baseline import identify_baseline
from agent.errors import InputError
from agent.frames import CLARKE
from agent.model import Signals
from agent.modelfile import baseline_from_json, baseline_to_json
from agent.profile import parse_profile
from agent.workbench.explain import explain
from agent.workbench.fitting import prepare
from agent.voltage_path import apply_path, cuts_pulses, stated_path
from bench.family import draw_drive, profile, simulate
from bench.family.simulate import simulate_detail
from bench.family.effects import voltage_path

SEED = 20005  #: reference voltage, abc hold, one computation period: the path is (-1, 0)
LOADS = (40.0, 60.0, 90.0, 100.0)


def test_apply_path_shifts_and_turns_the_stationary_voltage():
    n, ts, w = 400, 1e-4, 300.0
    k = np.arange(n)
    theta = w * ts * k
    v = np.stack([np.cos(theta - j * 2 * np.pi / 3) + 0.01 * np.sin(0.7 * k + j) for j in range(3)])
    sig = Signals.from_abc(v, np.zeros_like(v), theta, np.full(n, w), ts, 2)
    out = apply_path(sig, 1.0, 0.5)
    ab, ab_out = CLARKE[:2] @ v, CLARKE[:2] @ out.v_abc
    want = (ab[0, 1:] + 1j * ab[1, 1:]) * np.exp(0.5j * w * ts)  # v_applied(m) = e^(j a w Ts) v_reported(m + d)
    np.testing.assert_allclose(ab_out[0, :-1] + 1j * ab_out[1, :-1], want, atol=1e-12)
    assert apply_path(sig, 0.0, 0.0) is sig


def test_a_fractional_shift_is_cubic_exact_on_whole_samples_and_holds_the_ends():
    """shifted against the analytic x(k + d): a voltage near a quarter of the sampling rate is
    reproduced within 2e-4 of its amplitude (the linear interpolation's error there is 1e-2); a
    whole-sample shift moves the samples exactly and holds the last one."""
    from agent.voltage_path import shifted

    k = np.arange(400.0)
    for d in (0.648, -0.3, 1.5):
        want = np.stack([np.sin(0.05 * (k + d)), np.cos(0.3 * (k + d))])
        got = shifted(np.stack([np.sin(0.05 * k), np.cos(0.3 * k)]), d)
        assert np.abs(got - want)[:, 5:-5].max() < 2e-4, d
        linear = np.interp(k + d, k, np.cos(0.3 * k))
        assert np.abs(linear - want[1])[5:-5].max() > 5e-3
    x = np.arange(10.0)[None]
    np.testing.assert_array_equal(shifted(x, 2.0), [[2, 3, 4, 5, 6, 7, 8, 9, 9, 9]])
    np.testing.assert_array_equal(shifted(x, -1.0), [[0, 0, 1, 2, 3, 4, 5, 6, 7, 8]])


#: a continuous inverter holding its voltage in dq on a clock asynchronous to the record's, measured
#: through a window 0.648 sample late
FRACTIONAL = 20686


def test_a_window_lagging_by_a_fraction_of_a_sample_gives_the_applied_interval_average():
    """The stated path read from the family drive's window (its voltage noise off; the current
    loop's broadband answer to the current's noise kept) against the simulator's own applied voltage
    averaged over each interval [t_k, t_k + T_s], its error weighted as the current answers it
    (1/f above 20 Hz): below 0.4 of what a linear interpolation of the windows leaves (0.28 here)."""
    drive = draw_drive(FRACTIONAL, voltage_noise_v=0.0, voltage_adc_bits=24)
    rec, detail = simulate_detail(drive, {}, 60.0, 0.3, seed=1)
    sig = Signals.from_abc(rec.v_abc, rec.i_abc, rec.theta_e, rec.omega_e, 1.0 / drive.rate_hz, drive.pole_pairs)
    applied = detail["v_applied"][:, 50:-50]

    def weighted(v):
        spectrum = np.fft.rfft(v[:, 50:-50] - applied, axis=1)
        f = np.fft.rfftfreq(applied.shape[1], 1.0 / drive.rate_hz)
        return np.sqrt(np.sum(np.abs(spectrum[:, f > 20.0] / f[f > 20.0]) ** 2))

    k = np.arange(rec.v_abc.shape[1], dtype=float)
    linear = np.stack([np.interp(k + drive.voltage_filter_delay, k, x) for x in rec.v_abc])
    assert weighted(apply_path(sig, *voltage_path(drive)).v_abc) < 0.4 * weighted(linear)


def test_a_null_drive_with_a_fractional_window_lag_claims_nothing():
    """Drive 20686's null records claimed a voltage delay (0.47 sample of rotation, p = 2e-5) while its
    windows were interpolated linearly: the control sat at 1.3 times its noise floor; with the window
    at 0 or 1 sample, at 0.3 times."""
    drive = draw_drive(FRACTIONAL)
    prof = profile(drive, timing=True)
    base = identify_baseline([simulate(drive, {}, 80.0, 1.0, seed=100 + j) for j in range(4)], prof, window_s=0.5)
    doc = explain(base, prepare([simulate(drive, {}, load, 1.0, seed=200 + j) for j, load in enumerate(LOADS)], prof))
    assert not [c["effect"] for c in doc["candidates"] if c["significant"]]
    assert doc["nrmse_control"] < doc["noise_floor"]


def _doc(**sampling):
    return {"motor": {"pole_pairs": 4, "rated_power_w": 2200.0, "rated_torque_nm": 14.0, "rated_speed_rpm": 1500.0},
            "sampling": {"rate_hz": 25000.0, "voltage_source": "reference", **sampling},
            "transmission": {"kind": "gear", "driving_teeth": 20, "driven_teeth": 40}}


def test_the_profile_states_a_signed_path_within_its_physical_range():
    assert stated_path(parse_profile(_doc())) is None
    assert stated_path(parse_profile(_doc(voltage_delay_samples=-1))) == (-1.0, 0.0)
    assert stated_path(parse_profile(_doc(voltage_delay_samples=-1, voltage_advance_samples=1.5))) == (-1.0, 1.5)
    for key, value in (("voltage_delay_samples", -3.0), ("voltage_advance_samples", 2.5)):
        with pytest.raises(InputError, match=f"sampling.{key}' = {value:g} is outside its physical range"):
            parse_profile(_doc(**{key: value}), source="p.toml")


@pytest.fixture(scope="module")
def drive_and_base():
    drive = draw_drive(SEED)
    assert voltage_path(drive) == (-1.0, 0.0)
    prof = profile(drive, timing=True)
    base = identify_baseline([simulate(drive, {}, 80.0, 1.0, seed=100 + j) for j in range(4)], prof, window_s=0.5)
    return drive, base


def test_the_model_file_keeps_the_stated_path(drive_and_base):
    base = drive_and_base[1]
    assert stated_path(baseline_from_json(baseline_to_json(base)).profile) == (-1.0, 0.0)


def test_with_the_drives_path_stated_the_null_records_fit_better_and_claim_nothing(drive_and_base):
    """Side by side on the same records: the profile without the path (the voltage as reported) and
    with the drive's path."""
    drive, base = drive_and_base
    recs = [simulate(drive, {}, load, 1.0, seed=200 + j) for j, load in enumerate(LOADS)]
    raw = explain(base, prepare(recs, profile(drive)))
    moved = explain(base, prepare(recs, profile(drive, timing=True)))
    assert not [c["effect"] for c in moved["candidates"] if c["significant"]]
    ratio = lambda doc: doc["nrmse_control"] / doc["noise_floor"]  # noqa: E731
    assert ratio(moved) < 0.5 * ratio(raw), (ratio(moved), ratio(raw))


def test_an_extra_delay_is_named_and_reported_as_the_total_path(drive_and_base):
    """A DAQ lag of one sample on top of the drive's own path: voltage_delay first, significant, its
    delay the total (the stated -1 plus the extra +1) within a quarter sample."""
    drive, base = drive_and_base
    hidden = {"voltage_delay": {"extra_samples": 1.0}}
    recs = [simulate(drive, hidden, load, 1.0, seed=300 + j) for j, load in enumerate(LOADS)]
    doc = explain(base, prepare(recs, profile(drive, timing=True)))
    top = doc["candidates"][0]
    assert top["effect"] == "voltage_delay" and top["significant"], [(c["effect"], c["significant"]) for c in doc["candidates"]]
    want = voltage_path(drive, 1.0)[0]
    assert abs(top["params"]["delay_samples"] - want) <= 0.25, (top["params"], want)


def _rl_averaged(window: float, n: int = 6000, seed: int = 0):
    """An R-L branch driven by a voltage constant over each interval (a current loop's broadband
    answer to noise), its current averaged over ``window`` samples centred on each sample instant,
    integrated at 64 sub-steps per interval (exact exponential steps): the independent reference."""
    r, l, ts, sub = 2.0, 0.01, 1e-4, 64
    rng = np.random.default_rng(seed)
    v = 20.0 * rng.standard_normal(n) + 5.0 * np.sin(2 * np.pi * 7.0 * ts * np.arange(n))
    h = ts / sub
    a, b = np.exp(-r * h / l), (1.0 - np.exp(-r * h / l)) / r
    fine = np.zeros(n * sub + 1)
    for k in range(n):  # sub-steps of interval [t_k, t_k+1], the voltage v(k) throughout
        x = fine[k * sub]
        steps = a ** np.arange(1, sub + 1)
        fine[k * sub + 1:(k + 1) * sub + 1] = steps * x + (1.0 - steps) * v[k] * b / (1.0 - a)
    half = int(round(window * sub / 2))
    y = np.array([fine[k * sub - half:k * sub + half + 1].mean() if half else fine[k * sub] for k in range(1, n - 1)])
    return r, l, ts, v[1:n - 1], y


@pytest.mark.parametrize("window", [0.5, 1.0])
def test_a_current_averaged_over_its_interval_obeys_the_model_with_the_window_equivalent_voltage(window):
    """y(k+1) = a y(k) + b v_f(k): the least squares reads 1/b = L/T_s within 0.5 % from the
    filtered voltage, and 20 % or more off from the voltage as applied."""
    from agent.voltage_path import window_equivalent

    r, l, ts, v, y = _rl_averaged(window)
    v3 = np.stack([v, -0.5 * v, -0.5 * v])  # phase a's branch, balanced; only the filter matters here
    sig = Signals.from_abc(v3, np.zeros_like(v3), np.zeros(v.size), np.zeros(v.size), ts, 2)
    v_f = window_equivalent(sig, window).v_abc[0]
    want = np.exp(-r * ts / l), (1.0 - np.exp(-r * ts / l)) / r
    for volt, close in ((v_f, True), (v, False)):
        (a_hat, b_hat), *_ = np.linalg.lstsq(np.column_stack([y[:-1], volt[:-1]]), y[1:], rcond=None)
        err = b_hat / want[1] - 1.0
        assert (abs(err) < 0.005) if close else (abs(err) > 0.1 * window), (window, close, err)


def test_identify_reads_the_inductances_through_the_stated_path_and_window():
    """Family drives whose timing moves identify's L_d by 20-145 % (a DAQ filter's lag behind a dq
    hold; a current averaged over its interval): with the profile's timing within 5 %; without it
    more than 15 % off, or not reported (20024's profile then does not say whose current samples the
    records carry, and its readings differ as the controller's and as a DAQ's)."""
    for seed in (20043, 20046, 20024):
        drive = draw_drive(seed)
        recs = [simulate(drive, {}, 80.0, 1.0, seed=100 + j) for j in range(4)]
        for timing in (False, True):
            ld = identify_baseline(recs, profile(drive, timing=timing), window_s=0.5).physical["values"]["Ld"]
            if timing:
                assert ld == pytest.approx(drive.ld_h, rel=0.05), (seed, ld, drive.ld_h)
            else:
                assert ld is None or abs(ld / drive.ld_h - 1.0) > 0.15, (seed, ld, drive.ld_h)


def test_the_profile_states_the_current_window_reference_and_source_or_names_the_key():
    prof = parse_profile(_doc(current_window_samples=1.0, current_reference="mtpa", current_source="controller"))
    assert (prof.sampling.current_window_samples, prof.sampling.current_reference,
            prof.sampling.current_source) == (1.0, "mtpa", "controller")
    assert parse_profile(_doc()).sampling.current_source is None
    for key, value, says in (("current_window_samples", 1.5, "outside its physical range 0..1"),
                             ("current_window_samples", "x", "wrong type"),
                             ("current_reference", "MTPA", 'must be "id0" or "mtpa"'),
                             ("current_reference", 5, "wrong type"),
                             ("current_source", "drive", 'must be "controller" or "independent"')):
        with pytest.raises(InputError, match=f"sampling.{key}' .*{says}|sampling.{key}' {says}"):
            parse_profile(_doc(**{key: value}), source="p.toml")


def test_a_measured_voltage_window_off_the_sampling_on_a_pwm_inverter_is_said_to_cut_pulses():
    """cuts_pulses: only a measured voltage, on a PWM inverter (the default), whose stated window
    lag is more than 0.05 sample from a whole sample; the profile's inverter key names itself."""
    for source, inverter, lag, cuts in (("measured", None, 0.29, True), ("measured", "pwm", 0.5, True),
                                        ("measured", "pwm", -0.3, True), ("measured", "pwm", 0.97, False),
                                        ("measured", "pwm", 1.0, False), ("measured", "pwm", 0.0, False),
                                        ("measured", "pwm", None, False), ("measured", "continuous", 0.29, False),
                                        ("reference", "pwm", 0.29, False)):
        keys = {"voltage_source": source, **({"inverter": inverter} if inverter else {}),
                **({"voltage_delay_samples": lag} if lag is not None else {})}
        assert (cuts_pulses(parse_profile(_doc(**keys))) == lag) if cuts else cuts_pulses(parse_profile(_doc(**keys))) is None
    with pytest.raises(InputError, match='sampling.inverter\' must be "pwm" or "continuous"'):
        parse_profile(_doc(inverter="PWM"), source="p.toml")


def test_a_delay_behind_a_window_that_cuts_pwm_pulses_is_not_claimed_and_the_answer_says_why():
    """A family null drive (20165: a switched inverter, its voltage measured through a window 0.29
    sample late) on which the delay was claimed (0.38 samples, rotation 0.09 for 0.29 stated); the
    same drive with the window at 0 or 0.5, or with an averaged inverter, claimed nothing. The
    window's own duty-dependent delay cannot be told from a change of the path: no claim, and the
    note names the window and the records that would tell."""
    drive = draw_drive(20165)
    prof = profile(drive, timing=True)
    base = identify_baseline([simulate(drive, {}, 80.0, 1.0, seed=100 + j) for j in range(4)], prof, window_s=0.5)
    doc = explain(base, prepare([simulate(drive, {}, load, 1.0, seed=200 + j)
                                 for j, load in enumerate((40.0, 60.0, 90.0, 100.0))], prof))
    delay = next(c for c in doc["candidates"] if c["effect"] == "voltage_delay")
    assert not any(c["significant"] for c in doc["candidates"])
    assert delay["identifiability"]["stage"] == "unseen" and all(v is None for v in delay["params"].values())
    assert f"lagging by {drive.voltage_filter_delay:g} samples" in delay["note"] and "cuts the PWM pulses" in delay["note"]
