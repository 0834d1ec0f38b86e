"""Model workbench (docs/workbench.md): effect library, compare / explain / add-effect / history, on
simulator records with hidden effects. ``PMSM_SLOW=full`` runs the per-effect suite on longer records."""

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from agent.baseline import identify_baseline
from agent.cli import main
from agent.effects import EFFECTS, get, model_terms, params_text
from agent.errors import InputError
from agent.frames import dq_to_abc
from agent.model import DQModel, Signals, Term, lumped_params
from agent.records import save_record
from agent.simulator import simulate
from agent.workbench.explain import add_effects, explain
from agent.workbench.fitting import base_model, prepare
from bench.workbench_evidence import GEAR, GEAR_PATH, SCENARIOS, baseline, judge, scenario_records

FULL = os.environ.get("PMSM_SLOW") == "full"
SECONDS = 2.0 if FULL else 1.2
CONTRACT_IDS = ("inverter_deadtime", "flux_harmonics", "voltage_delay", "current_offset",
                "current_gain_mismatch", "resistance_drift", "magnetic_saturation", "speed_ripple")


@pytest.fixture(scope="module")
def base80():
    return baseline(GEAR)


# --- the library -----------------------------------------------------------------------------------

def test_library_has_the_contract_ids_and_describes_each():
    assert set(CONTRACT_IDS) <= set(EFFECTS)
    for e in EFFECTS.values():
        assert e.physics and e.signature and e.reveals and e.params and e.kind in ("voltage", "output")
        assert all(p.unit and p.meaning and p.typical > 0 for p in e.params)


def test_unknown_effect_lists_the_known_ids():
    with pytest.raises(InputError, match="known: inverter_deadtime, flux_harmonics"):
        get("warp_drive")


def _sig(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    w = np.full(n, 2 * np.pi * 100)
    th = np.cumsum(w) * GEAR.ts
    i_dq = np.vstack((rng.normal(0, 0.1, n), 8 + rng.normal(0, 0.1, n)))
    v_dq = np.vstack((-w * 0.028 * 8, 2.3 * 8 + w * 0.25)) + rng.normal(0, 2, (2, n))
    return Signals.from_abc(dq_to_abc(v_dq, th + 0.5 * w * GEAR.ts), dq_to_abc(i_dq, th), th, w, GEAR.ts, 4)


@pytest.mark.parametrize("effect", sorted(EFFECTS))
def test_effect_columns_shape_and_model_round_trip(effect):
    """Every effect's columns are (m, 2, N); a model built with given values gives them back."""
    sig, eff = _sig(), EFFECTS[effect]
    assert eff.cols(sig).shape == (len(eff.params), 2, sig.n)
    values = np.linspace(0.5, 1.5, len(eff.params)) * [p.typical for p in eff.params]
    m = base_model("lumped", GEAR.ts, 100.0, dict(Rs_d=2.3, Rs_q=2.3, Ld=0.015, Lq=0.028, Lq_x=0.028, psi_m=0.25),
                   (effect,), {effect: values})
    np.testing.assert_allclose(eff.values_from_model(m), values, rtol=1e-12)
    assert np.all(np.isfinite(m.simulate(sig)))


def test_output_terms_simulate_and_predict_exactly():
    """An output term adds c(k) theta to the measured current; checked against a plain loop."""
    sig = _sig(n=500, seed=3)
    d, q = lumped_params("speed", GEAR.ts, 2.3, 0.015, 0.028, 0.25, 0.0)
    off = Term("off", exo=lambda s: np.cos(s.theta_e), output=True)
    m = DQModel("speed", GEAR.ts, np.append(d, 0.1), np.append(q, -0.05), (off,), (off,), fe_hz=100.0)
    a0, a1 = m.state_matrices()
    o = np.vstack((0.1, -0.05)) * np.cos(sig.theta_e)
    u = m.exogenous(sig)
    x = sig.i_dq[:, 0] - o[:, 0]
    ref = [x + o[:, 0]]
    for k in range(sig.n - 1):
        x = (a0 + sig.omega_e[k] * a1) @ x + u[:, k]
        ref.append(x + o[:, k + 1])
    np.testing.assert_allclose(m.simulate(sig), np.array(ref).T, atol=1e-10)
    step = (a0[None] + sig.omega_e[:-1, None, None] * a1[None]) @ (sig.i_dq - o)[:, :-1].T[:, :, None]
    np.testing.assert_allclose(m.one_step(sig)[:, 1:], step[:, :, 0].T + u[:, :-1] + o[:, 1:], atol=1e-10)


def test_model_terms_concatenates_in_order():
    d, q = model_terms(["current_offset", "flux_harmonics"])
    assert [t.name for t in d] == ["current_offset.o_alpha", "current_offset.o_beta",
                                   "flux_harmonics.psi_5c", "flux_harmonics.psi_5s",
                                   "flux_harmonics.psi_7c", "flux_harmonics.psi_7s"]
    assert all(t.output for t in d[:2]) and not any(t.output for t in q[2:])


# --- the refit's parts ------------------------------------------------------------------------------

def _noisy_plant(n=40_000, sigma_v=0.5, sigma_i=0.005, seed=4):
    """Eq. 6 (speed form) driven by a steady voltage plus white excitation (a current loop's), measured
    through phase channels with white noise (V, A per phase); returns (Prepared, true values)."""
    from agent.workbench.fitting import Prepared

    rng = np.random.default_rng(seed)
    rs, ld, lq, psi, w = 2.3, 0.015, 0.028, 0.25, 2 * np.pi * 100
    ts = GEAR.ts
    th = np.arange(n) * w * ts
    v = np.vstack((np.full(n, -w * lq * 8.0), np.full(n, rs * 8.0 + w * psi))) + rng.normal(0, 2.5, (2, n))
    i = np.zeros((2, n))
    i[:, 0] = (0.0, 8.0)
    for k in range(n - 1):
        d, q = i[:, k]
        i[0, k + 1] = d + ts / ld * (v[0, k] - rs * d + w * lq * q)
        i[1, k + 1] = q + ts / lq * (v[1, k] - rs * q - w * ld * d - w * psi)
    v_abc = dq_to_abc(v, th + 0.5 * w * ts) + rng.normal(0, sigma_v, (3, n))
    i_abc = dq_to_abc(i, th) + rng.normal(0, sigma_i, (3, n))
    sig = Signals.from_abc(v_abc, i_abc, th, np.full(n, w), ts, 4)
    return Prepared("plant", sig, {"fe_hz": 100.0, "load_pct": 80.0}, n), dict(Rs=rs, Ld=ld, Lq=lq)


def test_zero_sequence_gives_the_channel_noise():
    from agent.physical import zero_sequence_sigma

    rng = np.random.default_rng(1)
    t = np.arange(50_000) * GEAR.ts
    x = dq_to_abc(np.vstack((0 * t, 300 + 0 * t)), 2 * np.pi * 100 * t) + rng.normal(0, 0.5, (3, t.size))
    x += 5.0 * np.sin(2 * np.pi * 300 * t)  # a third-harmonic line in the zero sequence
    assert zero_sequence_sigma(x) == pytest.approx(0.5, rel=0.03)


def test_one_step_compensates_the_channel_noise():
    """L_d, L_q within 3 % with the compensation (their spread over noise draws is ~1 %, the bias
    < 0.5 %); plain least squares on the same regressors (the reference written here) is biased by
    the noise on the voltage and current samples."""
    from agent.model import BASE_TERMS, regressors
    from agent.workbench.fitting import one_step

    prep, true = _noisy_plant(sigma_v=1.0)
    got = one_step([prep])
    assert got.ld == pytest.approx(true["Ld"], rel=0.03) and got.lq == pytest.approx(true["Lq"], rel=0.03)
    assert got.rs_d == pytest.approx(true["Rs"], rel=0.25)
    s = prep.sig.slice(0, prep.split)
    x = np.column_stack((regressors(BASE_TERMS["speed"][0], s)[:-1], np.ones(s.n - 1)))
    plain = np.linalg.lstsq(x, s.i_dq[0, 1:], rcond=None)[0]
    assert s.ts / plain[2] > 1.06 * true["Ld"]


def test_bounded_lstsq_matches_scipy():
    import scipy.optimize

    from agent.workbench.fitting import bounded_lstsq

    rng = np.random.default_rng(2)
    a = rng.normal(size=(200, 5))
    y = a @ np.array([1.0, -2.0, 0.5, -0.3, 2.0]) + rng.normal(0, 0.1, 200)
    lower = np.array([-np.inf, 0.0, -np.inf, 0.0, -np.inf])
    got = bounded_lstsq(a.T @ a, a.T @ y, lower)
    ref = scipy.optimize.lsq_linear(a, y, bounds=(lower, np.inf)).x
    np.testing.assert_allclose(got, ref, atol=1e-8)
    assert got[1] == 0.0 and got[3] == 0.0
    upper = np.array([0.5, np.inf, 0.2, np.inf, 1.0])  # box: three held at their upper bound
    got = bounded_lstsq(a.T @ a, a.T @ y, lower, upper)
    ref = scipy.optimize.lsq_linear(a, y, bounds=(lower, upper)).x
    np.testing.assert_allclose(got, ref, atol=1e-8)
    assert got[0] == 0.5 and got[2] == 0.2 and got[4] == 1.0


def test_workbench_angle_follows_the_rotor():
    """Without an encoder the workbench's angle is within a few mrad of the rotor's, where the
    agent's 3 Hz PLL lags the shaft-frequency speed ripple by tens of mrad."""
    from agent.identify import record_signals
    from agent.workbench.fitting import SETTLE_S

    kw = dict(condition="healthy", load_pct=80.0, seconds=1.2, seed=9, effects={"speed_ripple": 1.0})
    truth = np.unwrap(simulate(GEAR, encoder=True, **kw).theta_e)
    rec = simulate(GEAR, **kw)
    cut = int(SETTLE_S / GEAR.ts)
    err = lambda th: np.std(np.unwrap(th - truth[cut:]))  # noqa: E731 (the mean is the PLL's convention)
    assert err(prepare([rec], GEAR)[0].sig.theta_e) < 2e-3
    assert err(record_signals(rec, GEAR).theta_e[cut:]) > 10e-3


# --- hidden effects ---------------------------------------------------------------------------------

_cache: dict = {}


def _explained(effect):
    if effect not in _cache:
        prof = SCENARIOS[effect][2]
        base = _cache.setdefault(prof.name, baseline(prof))
        recs = scenario_records(effect, SECONDS)
        _cache[effect] = (recs, explain(base, prepare(recs, prof)))
    return _cache[effect]


@pytest.mark.slow
@pytest.mark.parametrize("effect", list(SCENARIOS))
def test_hidden_effect_is_ranked_first_halves_the_error_and_is_measured(effect):
    """The brief's figures: first and significant; the refit with it at most half the free-run
    NRMSE (held out) of the refit without it and of the refit with any wrong effect; the headline
    parameter within 20 % of the simulator's value."""
    got = judge(effect, *_explained(effect))
    assert got["rank"] == 1 and got["significant"], _explained(effect)[1]["candidates"][:3]
    assert got["nrmse_after"] <= 0.5 * got["nrmse_control"]
    assert got["nrmse_after"] <= 0.5 * got["nrmse_best_wrong"]
    assert abs(got["error"]) <= 0.2, got


@pytest.mark.slow
def test_null_set_claims_nothing(base80):
    recs = scenario_records(None, SECONDS, seed=200)
    doc = explain(base80, prepare(recs, GEAR))
    assert not [c["effect"] for c in doc["candidates"] if c["significant"]], doc["candidates"]
    assert all(c["explained_fraction"] < 0.3 for c in doc["candidates"])


def test_speed_ripple_stays_in_the_agents_residual():
    """The effect's speed error line carries the rotor's ripple in the workbench's frame (within
    10 %) and about a tenth of it in the agent's PLL frame, where angle and speed agree."""
    from agent.effects.speed_ripple import speed_error_line
    from agent.identify import record_signals

    rec = simulate(GEAR, "healthy", 80.0, 1.2, seed=5, effects={"speed_ripple": 1.0})
    amp = lambda sig: np.sqrt(2.0) * np.std(speed_error_line(sig))  # noqa: E731
    true = rec.meta["speed_ripple_omega_e"]
    assert amp(prepare([rec], GEAR)[0].sig) == pytest.approx(true, rel=0.1)
    agent = record_signals(rec, GEAR)
    assert amp(agent.slice(int(0.1 / GEAR.ts), agent.n)) < 0.15 * true  # after the PLL's lock-in


@pytest.mark.parametrize("beta", [0.0, 0.4, -1.2])
def test_speed_ripple_column_is_the_flux_times_the_speed_error_in_any_frame(beta):
    """A frame that turns at omega_e + dw (dw at the shaft frequency) with the stator flux psi_s at
    any angle beta in it (a rotor frame: 0; a current-vector frame under MTPA: not 0): the speed
    column is -j dw psi_s, the angle column is in quadrature with it, and the reported ripple is the
    measured line (the frame follows the rotor here)."""
    from agent.effects.speed_ripple import EFFECT, speed_error_line
    from agent.model import Signals

    ts, w, p, amp, n = 4e-5, 2 * np.pi * 100.0, 4, 3.0, 25000
    t = np.arange(n) * ts
    dw = amp * np.cos(w * t / p + 0.3)
    theta = w * t + amp * p / w * np.sin(w * t / p + 0.3)
    psi = 0.3 * np.exp(1j * beta)
    v = 1j * w * psi  # steady state, R_s i left out
    sig = Signals(np.zeros((2, n)), np.vstack((np.full(n, v.real), np.full(n, v.imag))), theta, np.full(n, w), ts,
                  pole_pairs=p)
    speed, angle = EFFECT.columns(sig)
    want = -1j * dw * psi
    tol = 0.01 * np.abs(want).max()  # the shaft angle theta / p carries the ripple itself
    assert np.allclose(speed[0], want.real, atol=tol) and np.allclose(speed[1], want.imag, atol=tol)
    assert abs(np.sum(speed * angle)) < 1e-3 * np.sqrt(np.sum(speed ** 2) * np.sum(angle ** 2))
    assert np.sqrt(2.0) * np.std(speed_error_line(sig)) == pytest.approx(amp, rel=0.01)
    rep = EFFECT.report(np.array([1.5, 0.0]), {"signals": [sig], "psi_m": 0.3})
    assert rep["omega_e_ripple_rad_s"] == pytest.approx(amp, rel=0.01)  # the rotor's: k_w is the model's gain


@pytest.mark.parametrize("share,beta0", [(0.0, 0.0), (-0.1, 0.15), (-0.1, -0.3), (0.2, -0.3)])
def test_speed_ripple_reports_the_rotors_ripple_when_the_frame_turns_against_the_rotor(share, beta0):
    """A current-vector frame turns against the rotor by delta beta = s theta_w (a share s of its own
    angle ripple theta_w): the frame's speed error is then the rotor's ripple / (1 - s). The exact
    voltage the base model misses (flux psi_m on the rotor's d axis at -beta in the frame, L_d !=
    L_q, the current held in the frame), fitted with the effect's two columns by least squares,
    gives the rotor's ripple within 3 % and s within 0.02."""
    from agent.effects.speed_ripple import EFFECT
    from agent.model import Signals

    ts, w, p, amp, n, psi_m, ld, lq, rs = 1e-4, 2 * np.pi * 75, 3, 3.0, 20000, 0.545, 0.036, 0.051, 2.0
    t = np.arange(n) * ts
    theta_w = amp / (w / p) * np.sin(w / p * t + 0.3) / (1 - share)  # the frame's angle ripple
    theta_f = w * t + theta_w
    i_f = complex(-1.0, 7.5)

    def flux(beta):  # stator flux in the frame whose d axis leads the rotor's by beta
        i_r = i_f * np.exp(1j * beta)
        return np.exp(-1j * beta) * (psi_m + ld * i_r.real + 1j * lq * i_r.imag)

    psi = flux(beta0 + share * theta_w)
    v = rs * i_f + np.gradient(psi) / ts + 1j * np.gradient(theta_f) / ts * psi
    missed = v - (rs * i_f + 1j * w * flux(np.full(n, beta0)))
    sig = Signals(np.vstack((np.full(n, i_f.real), np.full(n, i_f.imag))), np.vstack((v.real, v.imag)), theta_f,
                  np.full(n, w), ts, pole_pairs=p)
    cut = slice(50, -50)
    cols = EFFECT.columns(sig)[:, :, cut].reshape(2, -1).T  # the effect's voltage is the missed one, negated
    k = np.linalg.lstsq(cols, -np.concatenate((missed.real[cut], missed.imag[cut])), rcond=None)[0]
    rep = EFFECT.report(k, {"signals": [sig], "psi_m": psi_m})
    assert rep["omega_e_ripple_rad_s"] == pytest.approx(amp, rel=0.03)
    assert rep["frame_angle_share"] == pytest.approx(share, abs=0.02)


def test_explain_with_every_candidate_claimed(base80):
    """Holm rejects every candidate (one asked for, and it is there): nothing is left for the next
    level in Holm's order, and explain must still answer."""
    doc = explain(base80, prepare(scenario_records("current_offset", 0.8), GEAR), candidates=["current_offset"])
    assert [c["effect"] for c in doc["candidates"] if c["significant"]] == ["current_offset"]


def test_one_load_saturation_is_reported_not_identifiable(base80):
    recs = [simulate(GEAR, "healthy", 80.0, 1.0, seed=210 + j, effects={"magnetic_saturation": 0.15})
            for j in range(4)]
    doc = explain(base80, prepare(recs, GEAR), candidates=["magnetic_saturation", "current_offset"])
    sat = next(c for c in doc["candidates"] if c["effect"] == "magnetic_saturation")
    assert not sat["identifiable"] and not sat["significant"] and "several loads" in sat["note"]
    # its value is not reported as a measurement, here or by add-effect; what the fit landed on is kept apart
    assert set(sat["params"].values()) == {None} and set(sat["unpinned_params"]) == set(sat["params"])
    assert params_text(sat["params"]) == "not identifiable"
    _, fig = add_effects(base80, prepare(recs, GEAR), ["magnetic_saturation"])
    assert set(fig["params"]["magnetic_saturation"].values()) == {None}
    assert fig["params_bound"]["magnetic_saturation"] is None  # no figure, no bound
    assert any(w.startswith("magnetic_saturation: not identifiable") for w in fig["warnings"])


@pytest.mark.slow
def test_two_hidden_effects_both_on_top_and_both_beat_either(base80):
    eff = {"current_offset": 0.1, "current_gain_mismatch": 0.03}
    recs = [simulate(GEAR, "healthy", 80.0, SECONDS, seed=300 + j, effects=eff) for j in range(4)]
    preps = prepare(recs, GEAR)
    doc = explain(base80, preps)
    assert {c["effect"] for c in doc["candidates"][:2]} == set(eff)
    both = add_effects(base80, preps, list(eff))[1]["nrmse_after"]
    for e in eff:
        assert both < add_effects(base80, preps, [e])[1]["nrmse_after"]


# --- the command line: realistic workflow ------------------------------------------------------------

def run_json(capsys, *argv):
    code = main([*argv, "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


@pytest.fixture(scope="module")
def workflow(tmp_path_factory):
    """Baseline identified at 80 % load; records with a hidden sensor offset at 60 and 100 %."""
    d = tmp_path_factory.mktemp("wb")
    for j in range(4):
        save_record(simulate(GEAR, "healthy", 80.0, 1.0, seed=400 + j), d / f"h80_{j}.npz")
        save_record(simulate(GEAR, "healthy", (60.0, 100.0)[j % 2], 1.0, seed=410 + j,
                             effects={"current_offset": 0.1}), d / f"x_{j}.csv")
    assert main(["identify", "--profile", str(GEAR_PATH), "--window", "0.5", "--out", str(d / "m.json"),
                 *map(str, sorted(d.glob("h80_*.npz")))]) == 0
    return d, sorted(str(p) for p in d.glob("x_*.csv"))


def test_workflow_compare_explain_add_effect_history(capsys, workflow):
    d, data = workflow
    model = str(d / "m.json")
    comp = run_json(capsys, "model", "compare", "--model", model, *data)
    assert set(comp["nrmse"]) >= {"d", "q", "total"} and set(comp["fit_pct"]) >= {"d", "q", "a", "b", "c"}
    assert comp["where"] and any("load" in w for w in comp["warnings"])
    assert {r["load_pct"] for r in comp["table"]} and len(comp["table"]) == 2
    one = run_json(capsys, "model", "compare", "--one-step", "--model", model, *data)
    assert one["nrmse"]["total"] < comp["nrmse"]["total"]
    expl = run_json(capsys, "model", "explain", "--model", model, *data)
    assert expl["candidates"][0]["effect"] == "current_offset" and expl["candidates"][0]["significant"]
    assert expl["candidates"][0]["nrmse_after"] < 0.5 * min(expl["nrmse_before"], expl["nrmse_control"])
    add = run_json(capsys, "model", "add-effect", "--model", model, "--effect", "current_offset",
                   "--out", str(d / "m2.json"), *data)
    assert add["model"] == str(d / "m2.json") and add["effect"] == "current_offset"
    assert all(any("far from the model's" in w for w in doc["warnings"]) for doc in (comp, expl, add))
    assert add["nrmse_after"] < 0.6 * add["nrmse_control"] < add["nrmse_before"]
    assert add["params"]["current_offset"]["offset_A"] == pytest.approx(0.1, rel=0.2)
    assert add["params_bound"]["current_offset"]["offset_A"] > 0  # each figure with its bound
    # the text gives the bound after each figure and says once what it means
    from agent.workbench.cli import BOUND_LEGEND

    assert main(["model", "explain", "--model", model, *data]) == 0
    text = capsys.readouterr().out
    assert re.search(r"offset_A [0-9.]+ \+-[0-9.e-]+", text) and " ".join(BOUND_LEGEND.split()[:8]) in text
    hist = run_json(capsys, "model", "history", str(d / "m2.json"))
    assert [v["version"] for v in hist["versions"]] == [0, 1] and hist["effects"] == ["current_offset"]
    assert hist["versions"][1]["parent"] == model
    assert hist["versions"][1]["nrmse_basis"] == "beyond_noise_floor"
    # a version written before the figure left out the noise floor says its figures are raw
    old = json.loads((d / "m2.json").read_text())
    del old["history"][0]["nrmse_basis"]
    (d / "m_old.json").write_text(json.dumps(old))
    assert main(["model", "history", str(d / "m2.json")]) == 0
    assert "raw figures" not in capsys.readouterr().out
    assert main(["model", "history", "--model", str(d / "m_old.json")]) == 0  # as the other actions take it
    assert "raw figures: written before" in capsys.readouterr().out
    assert main(["model", "history"]) == 2 and "--model M" in capsys.readouterr().err
    diag = run_json(capsys, "diagnose", "--model", str(d / "m2.json"), data[0])  # used everywhere a model is
    assert diag["results"][0]["state"] in ("normal", "caution", "warning")
    again = run_json(capsys, "model", "compare", "--model", str(d / "m2.json"), *data)
    assert again["nrmse"]["total"] < comp["nrmse"]["total"]
    # several models: each one's figure over the whole set, the same as compared alone, in the report too
    (d / "other").mkdir(exist_ok=True)
    same_stem = str(d / "other" / "m.json")
    (d / "other" / "m.json").write_bytes((d / "m2.json").read_bytes())
    both = run_json(capsys, "model", "compare", "--model", model, "--model", same_stem, *data,
                    "--report", str(d / "two"))
    assert both["models"] == {model: comp["nrmse"]["total"], same_stem: again["nrmse"]["total"]}
    assert all(set(r["nrmse"]) == {model, same_stem} for r in both["table"])
    page = (d / "two" / "index.html").read_text()
    assert f"<td>{100 * again['nrmse']['total']:.4g}</td>" in page and f"<td>{100 * comp['nrmse']['total']:.4g}</td>" in page
    assert main(["model", "compare", "--model", model, "--model", model, *data]) == 2
    assert f"--model {model}: given twice" in capsys.readouterr().err


def test_bad_input_exits_2(capsys, workflow):
    d, data = workflow
    code = main(["model", "add-effect", "--model", str(d / "m.json"), "--effect", "warp_drive",
                 "--out", str(d / "x.json"), *data])
    err = capsys.readouterr().err
    assert code == 2 and "inverter_deadtime" in err and "speed_ripple" in err and err.count("\n") == 1
    bad = d / "bad.json"
    bad.write_text("{not json")
    assert main(["model", "compare", "--model", str(bad), *data]) == 2
    assert str(bad) in capsys.readouterr().err
    doc = json.loads((d / "m.json").read_text())
    doc["version"] = 99
    future = d / "future.json"
    future.write_text(json.dumps(doc))
    assert main(["model", "explain", "--model", str(future), *data]) == 2
    assert str(future) in capsys.readouterr().err


def test_report_page_renders(capsys, workflow, tmp_path):
    d, data = workflow
    doc = run_json(capsys, "model", "compare", "--model", str(d / "m.json"), "--report", str(tmp_path / "rep"),
                   "--no-rank", *data[:2])
    page = Path(doc["report"])
    text = page.read_text()
    for png in ("traces.png", "spectrum.png", "bins.png", "correlation.png"):
        assert png in text and (page.parent / png).stat().st_size > 10_000
    assert_renders(page, tmp_path)


def assert_renders(page: Path, tmp_path: Path) -> None:
    """Headless Chromium renders ``page`` into a screenshot that is not blank (skips without a browser)."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no headless Chromium installed (apt-get install -y chromium)")
    shot = tmp_path / "shot.png"
    subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
                    "--disable-background-networking", "--disable-component-update", "--disable-sync",
                    f"--user-data-dir={tmp_path / 'chromium'}", "--window-size=1250,2400", f"--screenshot={shot}",
                    page.as_uri()],
                   capture_output=True, timeout=120, check=False)
    assert shot.exists() and shot.stat().st_size > 50_000  # a blank page is a few kB


# --- why it matters for detection --------------------------------------------------------------------

LOWER_SIDEBANDS = (87.5, 75.0, 62.5)  #: Hz, fe - k f_gl, k = 1..3 (gear_driven family at 100 Hz)


@pytest.fixture(scope="module")
def delay_baselines():
    """Eight healthy 2 s records with a hidden one-sample voltage-channel delay: the paper's baseline
    identified on them, the same on records without the delay, and the model `add-effect` writes
    (its thresholds relearned on the same records)."""
    recs = [simulate(GEAR, "healthy", 80.0, 2.0, seed=500 + j, effects={"voltage_delay": 1.0}) for j in range(8)]
    clean = identify_baseline([simulate(GEAR, "healthy", 80.0, 2.0, seed=500 + j) for j in range(8)], GEAR,
                              window_s=1.0)
    hidden = identify_baseline(recs, GEAR, window_s=1.0)
    ref, fig = add_effects(hidden, prepare(recs, GEAR), ["voltage_delay"])
    # add-effect gives each figure with its bound, as explain does; the delay's holds the truth
    said, bound = fig["params"]["voltage_delay"], fig["params_bound"]["voltage_delay"]
    assert abs(said["delay_samples"] - 1.0) <= bound["delay_samples"]
    return clean, hidden, identify_baseline(recs, GEAR, window_s=1.0, model=ref.model)


def _th3(base, freqs):
    from agent.spectrum import nearest_bin

    return base.thresholds.th3[[nearest_bin(base.thresholds.freqs_hz, f) for f in freqs]]


def test_hidden_effect_inflates_thresholds_and_adding_it_lowers_them(delay_baselines):
    """The delay makes the baseline's response to the current loop's broadband voltage wrong; the
    residual floor rises at the fault lines, and falls again once the model has the effect."""
    clean, hidden, fixed = delay_baselines
    assert np.all(_th3(hidden, LOWER_SIDEBANDS) > 1.25 * _th3(clean, LOWER_SIDEBANDS))
    assert np.all(_th3(fixed, LOWER_SIDEBANDS) < 0.8 * _th3(hidden, LOWER_SIDEBANDS))


def test_after_adding_the_effect_the_slight_fault_shows(delay_baselines):
    """A slight tooth wear (10 % of the severe one) that the hidden effect's inflated thresholds read
    as normal is flagged with the model that has the effect."""
    from agent.decision import diagnose

    _, hidden, fixed = delay_baselines
    faults = [simulate(GEAR, "gear_severe_wear", 80.0, 2.0, seed=600 + j, severity=0.1,
                       effects={"voltage_delay": 1.0}) for j in range(6)]
    before = [diagnose(hidden, r).spectrum_state for r in faults]
    after = [diagnose(fixed, r).spectrum_state for r in faults]
    assert any(b == "normal" and a != "normal" for b, a in zip(before, after)), (before, after)
    assert sum(s != "normal" for s in after) > sum(s != "normal" for s in before)
    healthy = [simulate(GEAR, "healthy", 80.0, 2.0, seed=900 + j, effects={"voltage_delay": 1.0}) for j in range(6)]
    assert all(diagnose(fixed, r).spectrum_state == "normal" for r in healthy)
