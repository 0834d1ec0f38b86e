"""Each effect of the workbench's library is its physical family (docs/workbench.md, "The effect
library"): the 5th and the 7th flux harmonics apart, a signed voltage delay and the dq hold, the
dead time's knee, saturation's self and cross terms, the drift's curvature; figures the records
cannot pin are reported null."""

import numpy as np
import pytest
import scipy.linalg

from agent.effects import EFFECTS, get
from agent.frames import dq_to_abc
from agent.model import Signals
from agent.records import Record
from agent.simulator import simulate
from agent.workbench.explain import add_effects, explain
from agent.workbench.fitting import heldout, judge_figures, prepare
from bench.workbench_evidence import GEAR, baseline

SECONDS = 1.0


@pytest.fixture(scope="module")
def base80():
    return baseline(GEAR)


def _top(doc):
    return doc["candidates"][0]


# --- the columns against the machine equations --------------------------------------------------------

def test_flux_harmonic_columns_are_the_missing_back_emf_of_the_5th_and_the_7th():
    """Phase fluxes psi_m cos(theta) + psi_5 cos(5 theta + phi_5) + psi_7 cos(7 theta + phi_7) (b, c at
    -+ 2 pi/3): their back-EMF, Clarke- and Park-transformed numerically, less the model's j w psi_m,
    is minus the effect's columns times (psi_5 cos, psi_5 sin, psi_7 cos, psi_7 sin)."""
    from agent.frames import abc_to_dq

    ts, w, n = 4e-5, 2 * np.pi * 100, 5000
    psi_m, (p5, f5, p7, f7) = 0.25, (0.004, 0.7, 0.003, -1.2)
    t = np.arange(n + 1) * ts
    th = w * t
    shift = np.array([0.0, -2 * np.pi / 3, 2 * np.pi / 3])[:, None]
    flux = lambda x: (psi_m * np.cos(x) + p5 * np.cos(5 * x + f5) + p7 * np.cos(7 * x + f7))  # noqa: E731
    # the mean back-EMF over each interval, held like a voltage sample, in the mid-angle frame
    e_abc = (flux(th[None, 1:] + shift) - flux(th[None, :-1] + shift)) / ts
    e_dq = abc_to_dq(e_abc, th[:-1] + 0.5 * w * ts)[0]
    missing = e_dq - np.vstack((np.zeros(n), np.full(n, w * psi_m)))
    sig = Signals(np.zeros((2, n)), np.zeros((2, n)), th[:-1], np.full(n, w), ts)
    cols = get("flux_harmonics").columns(sig)
    v = np.array([p5 * np.cos(f5), p5 * np.sin(f5), p7 * np.cos(f7), p7 * np.sin(f7)])
    np.testing.assert_allclose(np.tensordot(v, cols, 1), -missing, atol=2e-3 * np.abs(missing).max())
    rep = get("flux_harmonics").report(v, {})
    assert rep["psi_5_Wb"] == pytest.approx(p5) and rep["phase_5_rad"] == pytest.approx(f5)
    assert rep["psi_7_Wb"] == pytest.approx(p7) and rep["phase_7_rad"] == pytest.approx(f7)


def test_simulator_harmonics_scalar_is_equal_5th_and_7th():
    """The simulator's flux_harmonics: a number psi_6 is the 5th and the 7th at psi_6 / 2 each."""
    one = simulate(GEAR, "healthy", 80.0, 0.2, seed=3, effects={"flux_harmonics": 0.005})
    two = simulate(GEAR, "healthy", 80.0, 0.2, seed=3, effects={"flux_harmonics": {"psi_5": 0.0025, "psi_7": 0.0025}})
    np.testing.assert_array_equal(one.i_abc, two.i_abc)


def test_every_module_names_its_family_dofs_and_bounds():
    import importlib

    for eid in EFFECTS:
        doc = importlib.import_module(f"agent.effects.{eid}").__doc__ or ""
        assert "Family" in doc and "Degrees of freedom" in doc, eid


def test_delay_columns_split_a_signed_delay_and_report_it():
    """A delay d in (-1, 1) of a broadband (zero-order-held) voltage is exact in the lag/lead basis:
    v_applied(k) = v_reported(k + d)."""
    rng = np.random.default_rng(1)
    ts, w, n = 4e-5, 2 * np.pi * 100, 3000
    th = w * np.arange(n) * ts
    v_abc = rng.normal(0, 10, (3, n))
    v_abc -= v_abc.mean(axis=0)
    sig = Signals.from_abc(v_abc, np.zeros((3, n)), th, np.full(n, w), ts)
    eff = get("voltage_delay")
    cols = eff.columns(sig)
    for d in (0.6, -0.4):
        applied = v_abc + d * (np.roll(v_abc, -1, axis=1) - v_abc) if d > 0 else v_abc - d * (np.roll(v_abc, 1, axis=1)
                                                                                             - v_abc)
        want = Signals.from_abc(applied, np.zeros((3, n)), th, np.full(n, w), ts).v_dq - sig.v_dq
        p = np.array([max(d, 0.0), max(-d, 0.0), 0.0])
        np.testing.assert_allclose(np.tensordot(p, cols, 1)[:, 1:-1], want[:, 1:-1], atol=1e-9)
        assert eff.report(p, {"ts": ts})["delay_samples"] == pytest.approx(d)


def test_figures_the_records_cannot_separate_are_not_pinned():
    """judge_figures: three collinear columns pin only their sum (the delay's rotation at constant
    speed), not the delay and the advance apart; an independent set pins each."""
    eff = get("voltage_delay")
    typ = np.array([p.typical for p in eff.params])
    # per sample of each parameter the same response (the lead column minus the lag one), per typical step
    resp = np.array([1.0, -1.0, 1.0]) * typ * 0.1
    gram = np.outer(resp, resp) + 1e-12 * np.eye(3)
    info = {"kept": gram, "whole": gram, "i_norm": 1.0}
    got = {k: p for k, (p, _) in judge_figures(eff, np.array([0.5, 0.0, 0.2]), info, {"ts": 4e-5}).items()}
    assert got["rotation_samples"] and not got["delay_samples"] and not got["advance_samples"]
    free = {"kept": np.diag(typ ** 0 * 1e-2), "whole": np.diag(typ ** 0 * 1e-2), "i_norm": 1.0}
    assert all(p for p, _ in judge_figures(eff, np.array([0.5, 0.0, 0.2]), free, {"ts": 4e-5}).values())


def test_a_figures_bound_is_the_larger_of_two_standard_errors_and_what_the_error_left_could_move():
    """judge_figures' bound: U_dt's typical step (6 V) moves the free run's output by sqrt(kept) / i_norm;
    an error of the model as large as what is left (an NRMSE), lying all along it, moves U_dt by
    6 V x left / that. The one-step's two standard errors stand where larger; nothing bounds a
    figure of the model's own effect or a setting read off the records (the sampled ripple)."""
    eff = get("inverter_deadtime")
    values = np.array([12.0])
    seen = {"kept": np.array([[4e-6]]), "whole": np.array([[1e-5]]), "i_norm": 1.0, "left": 2e-3}
    n = 2000
    ctx = {"signals": [Signals.from_abc(np.ones((3, n)), np.sin(np.arange(3 * n).reshape(3, n)), np.zeros(n),
                                       np.full(n, 100.0), 1e-4, 2)], "ts": 1e-4}

    def bound(info):
        return {k: b for k, (_, b) in judge_figures(eff, values, info, ctx).items()}

    got = bound(seen)
    assert got["U_dt_V"] == pytest.approx(6.0 * 2e-3 / 2e-3) and got["ripple_A"] is None
    assert bound({**seen, "cov": np.array([[25.0]])})["U_dt_V"] == pytest.approx(10.0)
    assert bound({**seen, "left": 0.0})["U_dt_V"] == pytest.approx(6.0 * 5e-4 / 2e-3)
    assert all(v is None for v in bound(None).values())
    # a one-step figure is bounded by the free run with it held ("run")
    assert bound({"cov": np.array([[0.01]]), "run": seen})["U_dt_V"] == pytest.approx(6.0)


# --- flux harmonics: the 5th, the 7th and both ------------------------------------------------------

HARMONICS = {
    "5th": {"psi_5": 0.004, "phase_5": 0.7},
    "7th": {"psi_7": 0.003, "phase_7": -1.2},
    "mix": {"psi_5": 0.003, "phase_5": 2.0, "psi_7": 0.002, "phase_7": 0.4},
}


@pytest.mark.parametrize("case", list(HARMONICS))
def test_5th_and_7th_harmonics_are_named_measured_and_removed(base80, case):
    """Each on its own and both: flux_harmonics first and significant, psi_5 and psi_7 within 20 %
    (a missing one within 20 % of the other's size), and add-effect brings the held-out error
    beyond the noise floor within twice the floor (the rig's transmission ripple stays in it), and
    at least 6x below the control's (the pure 7th: 0.25 % against 2.3 %, floor 0.17 %)."""
    h = HARMONICS[case]
    recs = [simulate(GEAR, "healthy", 80.0, SECONDS, seed=100 + j, effects={"flux_harmonics": h}) for j in range(4)]
    preps = prepare(recs, GEAR)
    doc = explain(base80, preps)
    top = _top(doc)
    assert top["effect"] == "flux_harmonics" and top["significant"] and not top["at_bound"], doc["candidates"][:2]
    scale = max(h.get("psi_5", 0.0), h.get("psi_7", 0.0))
    for k in ("5", "7"):
        true = h.get(f"psi_{k}", 0.0)
        assert top["params"][f"psi_{k}_Wb"] == pytest.approx(true, abs=0.2 * (true or scale))
    r, fig = add_effects(base80, preps, ["flux_harmonics"])
    floor = heldout(r.model, preps)["noise_floor"]["total"]
    assert fig["nrmse_after"] <= fig["nrmse_control"] / 6 and fig["nrmse_after"] <= 2 * floor, (fig, floor)


# --- the voltage path: a lead, and the dq hold ------------------------------------------------------

def test_a_drive_reporting_its_command_one_sample_early_is_a_negative_delay(base80):
    """The record's voltage leads the applied one by a sample (a drive's command, applied one
    computation period later): voltage_delay first, significant, delay_samples < 0 (-1 within 20 %),
    not at a bound."""
    recs = [simulate(GEAR, "healthy", (60.0, 100.0)[j % 2], SECONDS, seed=820 + j, effects={"voltage_delay": -1.0})
            for j in range(4)]
    doc = explain(base80, prepare(recs, GEAR))
    top = _top(doc)
    assert top["effect"] == "voltage_delay" and top["significant"] and not top["at_bound"], doc["candidates"][:2]
    assert top["params"]["delay_samples"] == pytest.approx(-1.0, abs=0.2)
    assert "at bound" not in top.get("note", "") and "reach" not in top.get("note", "")


@pytest.mark.parametrize("delay", [1.7, -1.6])
def test_a_delay_beyond_one_sample_is_reached_by_moving_the_path(base80, delay):
    """The delay's columns interpolate within one sample: a DAQ lag of 1.7 samples was read as 0.86
    (the rest taken by the advance) before the path was moved by whole samples. Now named,
    significant, within 0.2 sample, not at the columns' reach."""
    recs = [simulate(GEAR, "healthy", (60.0, 100.0)[j % 2], SECONDS, seed=820 + j, effects={"voltage_delay": delay})
            for j in range(4)]
    doc = explain(base80, prepare(recs, GEAR))
    top = _top(doc)
    assert top["effect"] == "voltage_delay" and top["significant"] and not top["at_bound"], doc["candidates"][:2]
    assert top["params"]["delay_samples"] == pytest.approx(delay, abs=0.2)
    assert "reach" not in top.get("note", "")


def test_no_move_is_tried_where_the_delay_columns_explain_nothing(base80, monkeypatch):
    """A hidden flux harmonic leaves the delay's columns at their reach with no gain: that is no
    sign of a path off the stated one, and moving it would be a refit per direction for nothing
    (on the drive family such moves claimed the delay for a hidden flux harmonic and for a
    saturation)."""
    import agent.workbench.explain as explain_module

    moves = []
    monkeypatch.setattr(explain_module, "moved_path", lambda preps, n: moves.append(n) or [])
    recs = [simulate(GEAR, "healthy", (60.0, 100.0)[j % 2], SECONDS, seed=950 + j, effects={"flux_harmonics": None})
            for j in range(4)]
    doc = explain(base80, prepare(recs, GEAR))
    delay = next(c for c in doc["candidates"] if c["effect"] == "voltage_delay")
    assert _top(doc)["effect"] == "flux_harmonics" and not delay["significant"]
    assert delay["nrmse_after"] >= doc["nrmse_control"] * (1 - 1e-9) and moves == []


def test_moving_the_path_shifts_the_voltage_and_counts_it_in_the_totals():
    """moved_path: v(m + n) with the ends held, the current untouched, the stated path plus n."""
    from agent.workbench.fitting import moved_path

    rec = simulate(GEAR, "healthy", 60.0, 0.2, seed=830)
    (p,) = prepare([rec], GEAR)
    (m,) = moved_path([p], 2)
    assert np.allclose(m.sig.v_abc[:, :-2], p.sig.v_abc[:, 2:], rtol=0, atol=1e-9)  # through alpha-beta and back
    assert np.allclose(m.sig.v_abc[:, -1], p.sig.v_abc[:, -1], rtol=0, atol=1e-9)
    assert np.array_equal(m.sig.i_dq, p.sig.i_dq)
    d0, a0 = p.meta.get("voltage_path") or (0.0, 0.0)
    assert m.meta["voltage_path"] == (d0 + 2, a0)


RIG = dict(rs=2.1, ld=15e-3, lq=28e-3, psi=0.25, p=4, w=2 * np.pi * 100, ts=4e-5)


def dq_hold_drive(load_pct: float, seconds: float, seed: int, sigma_v: float = 0.5) -> Record:
    """A drive that holds its voltage constant in the rotor's dq frame over each sampling interval
    (a continuous inverter), written here from the machine equations: L di/dt = v - R i - w J L i -
    w psi_m e_q, solved exactly over each interval at constant speed; a 600 Hz PI current loop with
    decoupling on its own noisy current (0.05 A) at i_d = 0; the DAQ records the command as the
    drive converts it (at the interval's start angle), and the currents (5 mA noise), with the
    encoder's angle."""
    c = RIG
    rng = np.random.default_rng(seed)
    n, ts, w = int(round(seconds / c["ts"])), c["ts"], c["w"]
    a = np.array([[-c["rs"] / c["ld"], w * c["lq"] / c["ld"]], [-w * c["ld"] / c["lq"], -c["rs"] / c["lq"]]])
    phi = scipy.linalg.expm(a * ts)
    gam = np.linalg.solve(a, phi - np.eye(2)) @ np.diag([1 / c["ld"], 1 / c["lq"]])
    iq_ref = load_pct / 100.0 * 14.0 / (1.5 * c["p"] * c["psi"])
    bw = 2 * np.pi * 600.0
    i, xi = np.array([0.0, iq_ref]), np.array([0.0, c["rs"] * iq_ref])
    cur, volt = np.empty((2, n)), np.empty((2, n))
    noise = rng.normal(0, 0.05, (2, n))
    for k in range(n):
        cur[:, k] = i
        e = np.array([0.0, iq_ref]) - (i + noise[:, k])
        xi += ts * bw * c["rs"] * e
        v = bw * np.array([c["ld"], c["lq"]]) * e + xi + w * np.array([-c["lq"] * iq_ref, c["psi"]])
        volt[:, k] = v
        i = phi @ i + gam @ (v - np.array([0.0, w * c["psi"]]))
    th = w * np.arange(n) * ts + rng.uniform(0, 2 * np.pi)
    v_abc = dq_to_abc(volt, th) + rng.normal(0, sigma_v, (3, n))
    i_abc = dq_to_abc(cur, th) + rng.normal(0, 5e-3, (3, n))
    return Record(np.arange(n) * ts, v_abc, i_abc, np.mod(th, 2 * np.pi), np.full(n, w), source=f"dq_hold_{seed}",
                  meta={"load_pct": load_pct})


def test_a_drive_holding_dq_fits_to_its_noise_floor_once_the_hold_is_known():
    """The dq hold is a rotation of the applied voltage by omega_e T_s / 2 against the report:
    add-effect with voltage_delay reads advance_samples 0.5 and delay 0 and the held-out error goes
    to the noise floor, from a baseline of the same drive that lacks it."""
    base = __import__("agent.baseline", fromlist=["identify_baseline"]).identify_baseline(
        [dq_hold_drive(80.0, 1.0, 700 + j) for j in range(4)], GEAR, window_s=0.5)
    preps = prepare([dq_hold_drive((60.0, 100.0)[j % 2], SECONDS, 100 + j) for j in range(4)], GEAR)
    r, fig = add_effects(base, preps, ["voltage_delay"])
    floor = heldout(r.model, preps)["noise_floor"]["total"]
    p = fig["params"]["voltage_delay"]
    assert p["advance_samples"] == pytest.approx(0.5, abs=0.15) and p["delay_samples"] == pytest.approx(0.0, abs=0.1), p
    # the control in the speed form is already within 1.4x the floor (in the lumped form it was above 3x the refit)
    assert fig["nrmse_after"] <= floor and fig["nrmse_after"] <= 0.6 * fig["nrmse_control"], (fig, floor)


def test_an_effects_column_cache_neither_recomputes_a_live_record_nor_keeps_a_dead_one():
    """Effect.cols and smooth_current keep results per Signals object by identity (a fit turns
    from record to record), with weak references: the streaming agent builds new signals every
    hop, and a cache must not keep them alive."""
    import gc
    import weakref

    from agent.effects.base import ByIdentity

    cache, made = ByIdentity(2), []
    sig = lambda n: Signals(np.zeros((2, n)), np.zeros((2, n)), np.zeros(n), np.zeros(n), 1e-4)  # noqa: E731
    a, b = sig(5), sig(6)
    assert [cache.get(x, lambda s: made.append(s.n) or s.n) for x in (a, b, a, b)] == [5, 6, 5, 6] and made == [5, 6]
    gone = weakref.ref(a)
    del a
    gc.collect()
    assert gone() is None and len(cache.items) == 1
    c, d = sig(7), sig(8)
    cache.get(c, lambda s: s.n), cache.get(d, lambda s: s.n)
    assert len(cache.items) == 2 and all(ref() is x for (ref, _), x in zip(cache.items, (c, d)))  # the newest two


# --- the sensors' gains read off the phase currents' sum ----------------------------------------------

def _phase_currents(gains, offsets, noise, seed, n=20000, ts=4e-5, f=50.0, amp=10.0, computed=False):
    """A three-wire winding's currents (amp A at f Hz, a 3 Hz swing of amp/5), measured with the
    sensors' gains and offsets, white noise and a 12-bit ADC's quantisation (A)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * ts
    theta = 2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)
    level = amp * (1.0 + 0.2 * np.sin(2 * np.pi * 3.0 * t))
    true = np.stack([level * np.cos(theta - k * 2 * np.pi / 3) for k in range(3)])
    meas = (1.0 + np.asarray(gains)[:, None]) * true + np.asarray(offsets)[:, None]
    meas = np.round((meas + rng.normal(0.0, noise, meas.shape)) / (40.0 / 4096)) * (40.0 / 4096)
    if computed:
        meas[2] = -meas[0] - meas[1]
    v = np.zeros_like(meas)
    return Signals.from_abc(v, meas, theta, np.full(n, 2 * np.pi * f), ts)


def test_the_phase_currents_sum_reads_each_sensors_gain_against_phase_a(monkeypatch):
    """Gains (1 + g) of 0.5 %, 3 % and -2 % with offsets and noise: the sum's reading of phases b
    and c against phase a is (1 + g_x)/(1 + g_a) - 1 within three of its standard errors (the
    errors-in-variables correction matters at this noise: without it the figures sit several
    standard errors off); a computed phase c (two sensors) gives no reading."""
    from agent.effects import current_gain_mismatch as cgm
    from agent.effects.current_gain_mismatch import sensor_sum

    gains, offsets = np.array([0.005, 0.03, -0.02]), np.array([0.05, -0.02, 0.01])
    truth = (1 + gains[1:]) / (1 + gains[0]) - 1
    for seed in range(5):
        records = [_phase_currents(gains, offsets, 0.3, seed * 10 + k) for k in range(4)]
        g, se, _ = sensor_sum(records)
        assert np.all(np.abs(g - truth) <= 3.0 * se), (seed, g, truth, se)
        assert np.all(se < 5e-4)  # 0.05 % at a noise of 3 % of the amplitude
    assert sensor_sum([_phase_currents(gains, offsets, 0.3, 1, computed=True)]) is None
    monkeypatch.setattr(cgm, "zero_sequence_sigma", lambda m: 0.0)  # the regressors' noise left in
    g, se, _ = sensor_sum([_phase_currents(gains, offsets, 0.3, 40 + k) for k in range(4)])  # new records: not cached
    assert np.all(np.abs(g - truth) > 3.0 * se)


def test_the_sums_test_holds_its_level_on_equal_sensors_and_finds_half_a_percent():
    """The sum's test (``sum_p``, over records): on 80 independent sets of four records from equal
    sensors (offsets, noise, 12-bit ADC) no more than 5 % + 3 binomial standard deviations fall below
    0.05 (it is conservative: the larger of two standard errors, Bonferroni over two gains); sensors
    0.5 % and -0.3 % off phase a's at the same noise give p < 0.01. Fewer than two records: no test."""
    from agent.effects.current_gain_mismatch import sensor_sum, sum_p

    def p(gains, seed, k=4):
        return sum_p(*sensor_sum([_phase_currents(gains, [0.02, -0.01, 0.0], 0.3, 1000 * seed + j, n=5000)
                                  for j in range(k)]))

    null = np.array([p([0.0, 0.0, 0.0], s) for s in range(80)])
    assert np.sum(null < 0.05) <= 0.05 * 80 + 3 * np.sqrt(80 * 0.05 * 0.95), null
    assert max(p([0.0, 0.005, -0.003], s) for s in range(3)) < 0.01
    assert p([0.0, 0.005, -0.003], 0, k=1) is None


def test_a_fit_whose_mismatch_the_sum_does_not_show_is_contradicted():
    """Sensors that agree (the sum shows nothing) against a fit that took 3 % and -3 %: the reading
    contradicts the fit, no figure is given and the note says what the sum shows; sensors that do
    differ give the sum's figures, with their bounds, whatever the fit read."""
    from agent.effects.current_gain_mismatch import through_sum

    said = {"params": {"gain_b": 0.03, "gain_c": -0.03}, "params_bound": {"gain_b": 0.001, "gain_c": 0.001}}
    agree = [_phase_currents([0.0, 0.0, 0.0], [0.0] * 3, 0.05, k) for k in range(4)]
    got = through_sum(np.array([0.03, -0.03]), said, {"signals": agree}, {})
    assert got["contradicted"] and got["params"] == {"gain_b": None, "gain_c": None}
    assert "the sensors differ by less than a quarter of what the fit takes" in got["note"]
    differ = [_phase_currents([0.0, 0.02, 0.04], [0.0] * 3, 0.05, k) for k in range(4)]
    got = through_sum(np.array([0.01, 0.045]), said, {"signals": differ}, {})
    assert not got.get("contradicted")
    for key, true in (("gain_b", 0.02), ("gain_c", 0.04)):
        assert got["params"][key] == pytest.approx(true, abs=3e-4)
        assert abs(got["params"][key] - true) <= got["params_bound"][key]
    assert "phase currents' sum" in got["note"]


def test_a_family_drive_whose_controller_holds_the_mismatch_gets_its_gains_from_the_sum():
    """Family drive 20002 (its controller acts on the sensors, no nameplate): the fit reads the
    mismatch through the model's R_s,q, 2.7 times the winding's, rotated by -19 degrees, which put
    gain_b at 0.0036 against 0.0146. Read off the phase currents' sum, both figures are within 1 %
    of the truth and the truth within their bounds."""
    from bench.family import draw_effect, truth
    from tests.test_workbench_claims import _family_set

    drive, base, preps = _family_set(20002, "current_gain_mismatch")
    doc = explain(base, preps, candidates=["current_gain_mismatch"])
    row = doc["candidates"][0]
    true = truth(drive, "current_gain_mismatch", draw_effect(drive, "current_gain_mismatch", 20002), [])
    assert row["significant"] and "phase currents' sum" in row["note"]
    for key in ("gain_b", "gain_c"):
        assert row["params"][key] == pytest.approx(true[key], rel=0.01)
        assert abs(row["params"][key] - true[key]) <= row["params_bound"][key]


def test_a_mismatch_no_refit_gains_from_is_still_said_from_the_sum():
    """Family drive 20036 (no encoder, a load ripple, its controller acts on its sensors): with
    phase b 3.0 % above phase a, the gain mismatch's refit gains nothing (the model's impedance takes
    the voltage that holds the mismatch), so no candidate names it. The document's ``sensor_gains``
    read both within 0.05 percentage points and a warning says so; the same drive's null set reads
    zero within its bound and warns of nothing. The unidentified candidate's own figures are the
    sum's. A fit that leaves the figures unpinned (20007: "its response is pinned, no figure of it
    is") reports the sum's as well."""
    from bench.family import draw_effect, truth
    from tests.test_workbench_claims import _family_set

    drive, base, preps = _family_set(20036, "current_gain_mismatch")
    doc = explain(base, preps, candidates=["current_gain_mismatch"])
    assert not any(c["significant"] for c in doc["candidates"])
    true = truth(drive, "current_gain_mismatch", draw_effect(drive, "current_gain_mismatch", 20036), [])
    for key in ("gain_b", "gain_c"):
        assert doc["sensor_gains"][key] == pytest.approx(true[key], abs=5e-4)
    said = f"{100 * doc['sensor_gains']['gain_b']:+.2f} %"
    assert abs(true["gain_b"]) > 0.02 and any("phase currents' sum shows the current sensors" in w and said in w
                                              for w in doc["warnings"])
    row = doc["candidates"][0]  # unidentified, yet its figures are the sum's, and its note says both
    assert not row["identifiable"] and "not identifiable" in row["note"] and "phase currents' sum" in row["note"]
    assert row["params"] == pytest.approx({k: doc["sensor_gains"][k] for k in ("gain_b", "gain_c")})
    _, base, preps = _family_set(20036, None)
    doc = explain(base, preps, candidates=["current_gain_mismatch"])
    for key in ("gain_b", "gain_c"):
        assert abs(doc["sensor_gains"][key]) <= doc["sensor_gains"]["bound"][key]
    assert not any("phase currents' sum" in w for w in doc["warnings"])
    drive, base, preps = _family_set(20007, "current_gain_mismatch")
    row = explain(base, preps, candidates=["current_gain_mismatch"])["candidates"][0]
    true = truth(drive, "current_gain_mismatch", draw_effect(drive, "current_gain_mismatch", 20007), [])
    assert "not separable from these records" in row["note"] and "phase currents' sum" in row["note"]
    assert abs(row["params"]["gain_c"] - true["gain_c"]) <= row["params_bound"]["gain_c"]


def test_a_mismatch_the_sum_shows_is_claimed_on_the_sums_test(monkeypatch):
    """Family drive 20029 (constant references, its controller acts on its sensors): the mismatch's
    refit explains most of the error in every record, but its test over four records (p about 0.003)
    falls short of Holm's level over the eight candidates (0.00125). The sum shows the sensors apart
    beyond doubt, so the claim rests on it: significant, ``test`` "direct", and the note gives both
    tests. Where the sum does not show them apart, the same refit is not claimed, and the note says
    that what it takes is not shown to be the sensors."""
    from agent.effects import current_gain_mismatch as cgm
    from agent.workbench import explain as ex
    from tests.test_workbench_claims import _family_set

    _, base, preps = _family_set(20029, "current_gain_mismatch")
    row = _top(explain(base, preps))
    assert row["effect"] == "current_gain_mismatch" and row["significant"] and row["test"] == "direct"
    assert ex.ALPHA / len(EFFECTS) < row["p_value"] < ex.SHARE_CLEARS and row["p_value_direct"] < 1e-6
    assert "tested on the records' direct reading" in row["note"]
    monkeypatch.setattr(cgm, "sum_p", lambda g, se, k: 0.5)
    row = _top(explain(base, preps, candidates=["current_gain_mismatch"]))
    assert not row["significant"] and row["test"] == "direct" and "records_needed" not in row
    assert "not shown to be this effect" in row["note"]


def test_records_without_current_beyond_their_noise_give_no_sensor_reading():
    """At standstill with the pulses off (zero current, or only the channels' noise) the sum has
    nothing to read a gain from: no reading (it had raised a singular-matrix error on zeros and
    read -1650 % on noise alone). A record with current beside them is read on its own."""
    from agent.effects.current_gain_mismatch import sensor_sum

    n = 2000
    zeros = Signals.from_abc(np.zeros((3, n)), np.zeros((3, n)), np.zeros(n), np.zeros(n), 1e-4)
    noise_only = [_phase_currents([0.0, 0.02, 0.01], [0.0] * 3, 0.05, k, amp=0.0) for k in range(2)]
    assert sensor_sum([zeros]) is None and sensor_sum(noise_only) is None
    live = _phase_currents([0.0, 0.02, 0.01], [0.0] * 3, 0.05, 7)
    g, se, _ = sensor_sum(noise_only + [zeros, live])
    assert np.all(np.abs(g - [0.02, 0.01]) <= 3 * se)
