"""The workbench's figures and claims (issue: a workbench that is right on anyone's data): one error
figure everywhere, unstable free runs reported as such, nested refits never worse than their parent,
effects bounded to physics, the significance test over an effective sample size, and the short
form of ``bench.bench_workbench`` on the project's simulator and on motulator."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agent.cli import main
from agent.effects import EFFECTS
from agent.model import Signals
from agent.physical import zero_sequence_sigma
from agent.records import Record, save_record
from agent.simulator import simulate
from agent.workbench import explain as ex
from agent.workbench.fitting import base_model, fit_cost, heldout, noise_floor, noise_sse, prepare
from bench.workbench_evidence import GEAR
from tests.test_workbench import assert_renders, base80, workflow  # noqa: F401 (fixtures)


def _json(capsys, *argv):
    code = main([*argv, "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


def test_one_error_figure_in_compare_explain_add_effect_history(capsys, workflow):
    """The same model on the same records: the same NRMSE from every command, and fit % its complement."""
    d, data = workflow
    model = str(d / "m.json")
    comp = _json(capsys, "model", "compare", "--model", model, *data)
    expl = _json(capsys, "model", "explain", "--model", model, *data)
    add = _json(capsys, "model", "add-effect", "--model", model, "--effect", "current_offset",
                "--out", str(d / "m2.json"), *data)
    hist = _json(capsys, "model", "history", str(d / "m2.json"))
    figure = comp["nrmse"]["total"]
    assert expl["nrmse_before"] == pytest.approx(figure, rel=1e-9)
    assert add["nrmse_before"] == pytest.approx(figure, rel=1e-9)
    assert hist["versions"][1]["nrmse_before"] == pytest.approx(figure, rel=1e-9)
    for axis in ("d", "q", "total", "a", "b", "c"):
        assert comp["fit_pct"][axis] == pytest.approx(100 * (1 - comp["nrmse"][axis]))
    # the refitted model, compared afresh, shows the figure add-effect reported for it
    again = _json(capsys, "model", "compare", "--model", str(d / "m2.json"), *data)
    assert again["nrmse"]["total"] == pytest.approx(add["nrmse_after"], rel=0.02)
    assert again["coverage"]["load_pct_range"][0] < 70 < 90 < again["coverage"]["load_pct_range"][1]


def test_add_effect_never_overwrites_a_model(capsys, workflow):
    d, data = workflow
    target = d / "taken.json"
    target.write_text("{}")
    code = main(["model", "add-effect", "--model", str(d / "m.json"), "--effect", "current_offset",
                 "--out", str(target), *data])
    err = capsys.readouterr().err
    assert code == 2 and str(target) in err and "never overwritten" in err and err.count("\n") == 1
    assert target.read_text() == "{}"


def test_unstable_free_run_is_reported_not_a_number(base80, capsys, workflow, tmp_path):
    """A model whose free run diverges (negative resistance) has no NRMSE: a note says when it left
    and what the one-step figure is."""
    from agent.modelfile import load_baseline, save_baseline

    d, data = workflow
    bad = load_baseline(d / "m.json")
    p = bad.model.physical()
    bad.model.from_physical(-5 * p["Rs_q"], p["Ld"], p["Lq"], p["psi_m"])
    preps = prepare([simulate(GEAR, "healthy", 80.0, 0.6, seed=31)], GEAR)
    h = heldout(bad.model, preps)
    assert h["stable"] is False and h["nrmse"] is None and np.isfinite(h["one_step"]["total"])
    assert h["note"].startswith("free run unstable after") and "one-step NRMSE" in h["note"]
    path = tmp_path / "bad.json"
    save_baseline(bad, path)
    comp = _json(capsys, "model", "compare", "--model", str(path), *data[:2])
    assert comp["nrmse"] is None and comp["stable"] is False and "unstable" in comp["note"]
    assert all(v is None for r in comp["table"] for v in r["nrmse"].values())


def test_diagnose_report_has_the_cluster_and_each_spectrum(capsys, workflow, tmp_path):
    """`diagnose --report DIR`: the decision table, the cluster plot (Figs. 9, 11) and one spectrum
    plot per record with TH1-TH3 and the fault sidebands (Figs. 8, 10); rendered by Chromium."""
    d, data = workflow
    healthy = sorted(str(p) for p in d.glob("h80_*.npz"))[:2]
    severe = tmp_path / "severe.npz"
    save_record(simulate(GEAR, "gear_severe_wear", 80.0, 1.0, seed=830), severe)
    doc = _json(capsys, "diagnose", "--model", str(d / "m.json"), "--report", str(tmp_path / "dg"),
                *healthy, str(severe))
    page = Path(doc["report"])
    text = page.read_text()
    assert "cluster.png" in text and all(f"spectrum_{j}.png" in text for j in range(3))
    assert text.count("<tr>") == 4 and "warning" in text  # header + three records
    for png in ("cluster.png", "spectrum_0.png", "spectrum_2.png"):
        assert (page.parent / png).stat().st_size > 10_000
    assert_renders(page, tmp_path)


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(effect=st.sampled_from(sorted(EFFECTS)), load=st.sampled_from([50.0, 70.0, 95.0]),
       seed=st.integers(0, 10_000))
def test_nested_refit_is_never_worse_than_its_parent(base80, effect, load, seed):
    """On the fit segments: control <= the model; every candidate <= the control."""
    recs = [simulate(GEAR, "healthy", load + 10 * j, 0.6, seed=seed + j) for j in range(3)]
    preps = prepare(recs, GEAR)
    base = ex.drive_base(base80)
    ctrl = ex.control(base80.model, preps, base, prior=ex.physical_prior(base80))
    own = fit_cost(base80.model, preps)
    assert ctrl.cost <= own + 1e-9 * abs(own)
    cand = ex.nested(ctrl, preps, (effect,), base)
    assert cand.cost <= ctrl.cost + 1e-9 * abs(ctrl.cost)
    assert cand.effects == ctrl.effects + (effect,)


def test_effect_at_its_bound_is_never_significant(base80):
    """Voltage samples *lagging* the current by four samples want a delay beyond the voltage path's
    columns (they interpolate within a sample): the fit holds it at the bound and explain says so
    instead of claiming it, and names the profile keys that bring the path within reach (not
    "beyond its physical range": a four-sample lag is a path, only not the stated one). (A lead is a
    negative delay within range: tests/test_effect_families.py.)"""
    recs = []
    for j in range(4):
        r = simulate(GEAR, "healthy", (60.0, 100.0)[j % 2], 1.0, seed=820 + j)
        v = np.hstack((r.v_abc[:, :1].repeat(4, axis=1), r.v_abc[:, :-4]))
        recs.append(Record(r.t, v, r.i_abc, source=f"lag_{j}", meta=r.meta))
    doc = ex.explain(base80, prepare(recs, GEAR), candidates=["voltage_delay", "current_offset"])
    row = next(c for c in doc["candidates"] if c["effect"] == "voltage_delay")
    assert row["at_bound"] and not row["significant"], row
    assert "at the columns' reach" in row["note"] and "sampling.voltage_delay_samples" in row["note"]
    assert "beyond its physical range" not in row["note"]


@pytest.mark.parametrize("effect, value, key", [
    ("current_offset", 1.0, "offset_A"),  # 15 % of the rated 6.6 A; the bound is a sensor class's 5 %
    ("current_gain_mismatch", 0.3, "gain_b"),  # 30 % against a class limit of 10 %
])
def test_an_effect_beyond_its_sensor_class_is_at_bound_not_significant(base80, effect, value, key):
    """A sensor error three times its class limit: the refit stops at the limit, and explain says
    "at bound" instead of claiming a value physics does not allow."""
    recs = [simulate(GEAR, "healthy", (60.0, 100.0)[j % 2], 1.0, seed=840 + j, effects={effect: value})
            for j in range(4)]
    doc = ex.explain(base80, prepare(recs, GEAR), candidates=[effect, "voltage_delay"])
    row = next(c for c in doc["candidates"] if c["effect"] == effect)
    assert row["at_bound"] and not row["significant"] and "at bound" in row["note"], row
    fitted = {**row["params"], **row.get("unpinned_params", {})}[key]
    assert abs(fitted) < 0.6 * value  # held at the limit (a vector at its corners for the offset), not the value


def test_second_hidden_effect_is_claimed_given_the_first(base80):
    """Offset and delay hidden together at 60 and 100 % load: both are claimed. The offset's share
    varies with the load against a control that still lacks the delay; where it misses the level on
    its own it is judged again with the delay accepted (forward selection) and is significant then
    (the voltage path's one-step estimate now reads the delay with the offset unmodelled, and both
    are claimed on their own)."""
    eff = {"current_offset": 0.1, "voltage_delay": 1.0}
    recs = [simulate(GEAR, "healthy", (60.0, 100.0)[j % 2], 1.0, seed=300 + j, effects=eff) for j in range(4)]
    doc = ex.explain(base80, prepare(recs, GEAR))
    sig = {c["effect"]: c for c in doc["candidates"] if c["significant"]}
    assert set(sig) == set(eff), doc["candidates"][:3]
    for second in (c for c in sig.values() if "given" in c):
        assert second["given"] == [e for e in sig if e != second["effect"]]
        assert second["p_value_given"] < ex.ALPHA and second["explained_fraction_given"] >= ex.MIN_EXPLAINED


def test_effective_size_against_its_limits():
    """Independent blocks: n_eff near the block count; one level per record: n_eff = the records."""
    rng = np.random.default_rng(0)
    iid = [rng.normal(size=50) for _ in range(4)]
    _, _, n = ex.effective_size(iid)
    assert 120 <= n <= 200  # truncation at the first negative rho keeps some noise: conservative
    levels = [np.full(50, rng.normal()) + 1e-6 * rng.normal(size=50) for _ in range(4)]
    _, _, n = ex.effective_size(levels)
    assert n == pytest.approx(4, abs=0.5)
    ar = []  # AR(1) with phi = 0.8: n_eff = N (1 - phi) / (1 + phi) = N / 9
    for _ in range(20):
        x = np.zeros(400)
        for k in range(1, 400):
            x[k] = 0.8 * x[k - 1] + rng.normal()
        ar.append(x)
    _, _, n = ex.effective_size(ar)
    assert n == pytest.approx(8000 / 9, rel=0.3)


def test_holm_step_down():
    assert ex.holm([0.001, 0.004, 0.03], 0.01) == [True, True, False]
    assert ex.holm([0.004, 0.001, 0.006], 0.01) == [True, True, True]  # 0.001 <= a/3, 0.004 <= a/2, 0.006 <= a
    assert ex.holm([0.004, 0.001, 0.0045], 0.005) == [False, True, False]  # 0.004 > a/2 stops the rest
    assert ex.holm([0.02, 0.001], 0.01) == [False, True]


def test_block_p_uses_records_not_blocks():
    """A candidate that helps one record and hurts the others by the same amount per block is not
    significant, though its blocks, counted as independent, would be."""
    quiet = [np.zeros(20)] * 4
    ctrl = {"stable": True, "records": [np.ones(20)] * 4, "floor_records": quiet}
    cand = {"stable": True, "records": [np.full(20, 0.2), np.full(20, 0.9), np.full(20, 0.95), np.full(20, 0.9)],
            "floor_records": quiet}
    assert ex.block_p(ctrl, cand) > 0.05
    cand["records"] = [np.full(20, 0.5) + 0.01 * np.arange(20) % 0.03 for _ in range(4)]
    assert ex.block_p(ctrl, cand) < 1e-4


def test_records_needed_is_what_the_test_would_need_on_more_records_like_these():
    """A candidate that explains about 5 % of the error in one kind of record and 22 % in another
    (a delay at 60 and 100 % load): four records do not reach Holm's level; the count
    ``records_needed`` predicts is where the same test on that many records like these (the pair
    repeated) first does."""
    rng = np.random.default_rng(3)
    pair = [1.0 - (0.05 + 0.05 * rng.normal(size=5)), 1.0 - (0.22 + 0.05 * rng.normal(size=5))]

    def docs(n_pairs):
        cand = [x for _ in range(n_pairs) for x in pair]
        quiet = [np.zeros(5)] * len(cand)
        return ({"stable": True, "records": [np.ones(5)] * len(cand), "floor_records": quiet},
                {"stable": True, "records": cand, "floor_records": quiet})

    alpha = ex.ALPHA / 8
    assert ex.block_p(*docs(2)) > alpha
    need = ex.records_needed(*docs(2), alpha)
    assert need is not None and need > 4
    for n_pairs in range(2, 12):
        assert (ex.block_p(*docs(n_pairs)) < alpha) == (2 * n_pairs >= need), n_pairs
    assert ex.records_needed(*docs(2), 1e-30) is None  # beyond any sensible count: says so
    note = ex.too_few_note(*docs(2), alpha, ex.block_p(*docs(2)), need)
    assert f"about {need} records" in note and "with these 4 records" in note
    lo, hi = sorted(1.0 - float(np.mean(x)) for x in pair)
    assert f"{lo:.0%} to {hi:.0%}" in note
    assert "would not settle it" in ex.too_few_note(*docs(2), 1e-30, ex.block_p(*docs(2)), None)


def test_block_p_credits_no_model_for_responding_less_to_noise():
    """A candidate whose held-out error is lower only by its smaller response to the voltage noise
    (its noise floor lower by as much) explains nothing; one that removes error beyond that does."""
    ctrl = {"stable": True, "records": [np.ones(20)] * 4, "floor_records": [np.full(20, 0.5)] * 4}
    wobble = [np.full(20, 0.7) + 0.01 * (np.arange(20) % 3) for _ in range(4)]
    sluggish = {"stable": True, "records": wobble, "floor_records": [w - 0.5 for w in wobble]}
    assert ex.block_p(ctrl, sluggish) == 1.0
    better = {"stable": True, "records": wobble, "floor_records": [np.full(20, 0.5)] * 4}
    assert ex.block_p(ctrl, better) < 1e-4


@pytest.mark.slow
def test_bench_workbench_short_form_rig():
    """The short form of `make bench-workbench` on the project's simulator: the hidden effects of
    the pair scenario on top, two null sets claim nothing."""
    from bench.bench_workbench import Bench, Rig

    b = Bench(Rig(), 0.8, say=lambda s: None)
    assert b.null(2, first_seed=9000)["claiming"] == 0
    sc = __import__("bench.bench_workbench", fromlist=["scenarios"]).scenarios(b.sim)["current_offset"]
    row = b.scenario("current_offset", sc)
    assert row["rank"] == 1 and row["significant"] and row["gain"] >= 2 and abs(row["error"]) <= 0.2


@pytest.mark.slow
def test_bench_workbench_short_form_motulator():
    """The same on motulator's records: a null set claims nothing, the hidden offset is first,
    significant, not at a bound, at least 2x better than a wrong effect and within 20 %. The rest
    is tracked by `make bench-workbench` (docs/benchmarks.md)."""
    pytest.importorskip("motulator")
    from bench.bench_workbench import Bench, Motulator, scenarios

    b = Bench(Motulator(), 0.6, say=lambda s: None)
    assert b.null(1, first_seed=9100)["claiming"] == 0
    sc = scenarios(b.sim)["current_offset"]
    row = b.scenario("current_offset", sc)
    assert row["rank"] == 1 and row["significant"] and not row["bound"]
    assert row["gain"] >= 2 and abs(row["error"]) <= 0.2


@pytest.mark.slow
def test_saturation_under_mtpa_needs_the_nameplate_resistance():
    """motulator's MTPA drive: without a nameplate R_s, R_s i_d trades with the saturation's cubic
    term: explain may name the saturation (its response is pinned, 7x better than the control) but
    gives none of its figures, and names the nameplate's R_s as what separates them; with the
    nameplate R_s the saturation is first, significant and within 20 %."""
    pytest.importorskip("motulator")
    from bench.bench_workbench import Bench, Motulator, scenarios

    b = Bench(Motulator(), 1.0, say=lambda s: None)
    scs = scenarios(b.sim)
    without = b.scenario("magnetic_saturation", scs["magnetic_saturation"])
    assert not without["identifiable"] and "nameplate.rs_ohm" in without["note"]
    assert "not separable" in without["note"] or not without["significant"]
    with_plate = b.scenario("magnetic_saturation+nameplate", scs["magnetic_saturation+nameplate"])
    assert with_plate["rank"] == 1 and with_plate["significant"] and abs(with_plate["error"]) <= 0.2


@pytest.mark.slow
def test_a_delay_at_constant_speed_is_revealed_by_the_load_step_explain_names():
    """motulator's smooth voltage at one constant speed leaves a one-sample delay mostly a rotation
    the lumped parameters take; explain's note for it names load steps. With a 10 %-point load step
    in each record the delay is first, significant and within 20 %."""
    pytest.importorskip("motulator")
    from agent.effects import get
    from bench.bench_workbench import Bench, Motulator, scenarios

    assert "load steps" in get("voltage_delay").reveals
    b = Bench(Motulator(), 1.0, say=lambda s: None)
    row = b.scenario("voltage_delay+load_step", scenarios(b.sim)["voltage_delay+load_step"])
    assert row["rank"] == 1 and row["significant"] and abs(row["error"]) <= 0.2


def test_a_step_late_in_a_long_record_is_fitted_not_only_held_out(base80):
    """A load step 1.5 s into 2 s records: the fit segment moves to hold it (a quarter in), so the
    step separates the delay from the lumped R and L; fitted on the steady start alone, the refit
    would only extrapolate across it. Steady records keep the fit segment at their start."""
    eff = {"voltage_delay": 1.0}
    recs = [simulate(GEAR, "healthy", load, 2.0, seed=860 + j, effects=eff, load_step=(1.5, load + 10.0))
            for j, load in enumerate((60.0, 90.0, 60.0, 90.0))]
    preps = prepare(recs, GEAR)
    for p in preps:
        step_at = int(round(1.5 / p.sig.ts)) - (recs[0].t.size - p.sig.n)  # the PLL's lock-in is cut
        assert p.start < step_at < p.split and (step_at - p.start) == pytest.approx((p.split - p.start) / 4, rel=0.2)
    assert prepare([simulate(GEAR, "healthy", 60.0, 2.0, seed=870)], GEAR)[0].start == 0
    doc = ex.explain(base80, preps)
    top = doc["candidates"][0]
    assert top["effect"] == "voltage_delay" and top["significant"]
    assert top["params"]["delay_samples"] == pytest.approx(1.0, rel=0.1)
    assert top["nrmse_after"] < 0.3 * doc["nrmse_control"]


@pytest.mark.parametrize("w_ts", [0.025, 0.05])
def test_zoh2_matches_the_exact_hold_solution_where_euler_does_not(w_ts):
    """The refit's discretisation against the exact zero-order-hold solution of the continuous dq
    equations (scipy expm of the augmented system), at the rig's and motulator's omega_e T_s:
    transition and input matrices within a tenth of Euler's error."""
    import scipy.linalg

    from agent.workbench.fitting import base_model

    ts, r, ld, lq, psi = 1e-4, 3.6, 0.036, 0.051, 0.5
    w = w_ts / ts
    m = base_model("speed", ts, w / (2 * np.pi), {"Rs_d": r, "Rs_q": r, "Ld": ld, "Lq": lq, "Lq_x": lq, "psi_m": psi})
    ac = np.array([[-r / ld, w * lq / ld], [-w * ld / lq, -r / lq]])
    bc = np.diag([1 / ld, 1 / lq])
    aug = scipy.linalg.expm(np.block([[ac, bc], [np.zeros((2, 4))]]) * ts)
    phi, gamma = aug[:2, :2], aug[:2, 2:]
    a0, a1 = m.transition(w)
    euler = m.state_matrices()
    zoh2_a, euler_a = a0 + w * a1, euler[0] + w * euler[1]
    zoh2_b = 0.5 * (np.eye(2) + euler_a) @ np.diag([m.theta_d[2], m.theta_q[2]])
    euler_b = np.diag([m.theta_d[2], m.theta_q[2]])
    assert np.abs(zoh2_a - phi).max() < 0.1 * np.abs(euler_a - phi).max()
    assert np.abs(zoh2_b - gamma).max() < 0.1 * np.abs(euler_b - gamma).max()


def _machine_model(meta: dict, fe_hz: float, l_scale: float = 1.0, effects: dict | None = None, ts=GEAR.ts):
    """The simulated machine's own dq model (its true R_s, L_d, L_q, psi_m), inductances scaled."""
    phys = {"Rs_d": meta["R_s"], "Rs_q": meta["R_s"], "Ld": meta["L_d"] * l_scale, "Lq": meta["L_q"] * l_scale,
            "Lq_x": meta["L_q"], "psi_m": meta["psi_m"]}
    effects = effects or {}
    return base_model("speed", ts, fe_hz, phys, tuple(effects), {k: np.atleast_1d(v) for k, v in effects.items()})


def _record_and_machine(sim: str, effects: dict):
    """A healthy 1 s record with the encoder and the dq model of the machine that made it: the rig
    simulator's, or motulator's (MTPA, 10 kHz, its own solver; cached in bench/results)."""
    if sim == "rig":
        rec = simulate(GEAR, "healthy", 80.0, 1.0, seed=41, encoder=True)
        return rec, GEAR, _machine_model(rec.meta, rec.meta["fe_hz"], effects=effects)
    pytest.importorskip("motulator")
    from agent.profile import load_profile
    from agent.records import load_record
    from bench.thirdparty.motulator_drive import PROFILE, Run, cached

    prof = load_profile(PROFILE)
    path = cached(Run(load_pct=80.0, seconds=1.0, seed=0))
    truth = json.loads(str(np.load(path)["truth"]))
    rec = load_record(path, prof)
    fe = float(np.mean(rec.omega_e)) / (2 * np.pi)
    return rec, prof, _machine_model(truth, fe, effects=effects, ts=prof.ts)


@pytest.mark.parametrize("sim,effects", [("rig", {}), ("rig", {"voltage_delay": 0.5}), ("motulator", {})])
def test_noise_floor_is_the_models_response_to_the_channels_noise(sim, effects):
    """noise_floor against Monte Carlo, on both simulators' records: extra white noise (1 V rms) on
    the phase voltages raises the free run's mean squared deviation by the floor's voltage part per
    V^2, with a voltage effect that reads the voltage (a delay's interpolation) as without."""
    rec, prof, model = _record_and_machine(sim, effects)
    prep = prepare([rec], prof)[0]
    sig = prep.sig
    rng = np.random.default_rng(5)
    settled = int(0.2 / sig.ts)  # the noise response builds up over a few L/R
    y0, added = model.simulate(sig), []
    for _ in range(8):
        noisy = Signals.from_abc(sig.v_abc + rng.normal(0.0, 1.0, sig.v_abc.shape), sig.i_abc, sig.theta_e,
                                 sig.omega_e, sig.ts, sig.pole_pairs)
        added.append(np.mean((model.simulate(noisy) - y0)[:, settled:] ** 2, axis=1))
    gain = noise_floor(model, prep) - 2.0 / 3.0 * zero_sequence_sigma(sig.i_abc) ** 2
    gain /= zero_sequence_sigma(sig.v_abc) ** 2
    np.testing.assert_allclose(gain, np.mean(added, axis=0), rtol=0.1)


def test_a_model_of_the_machine_leaves_only_the_noise_floor():
    """On records with the voltage channel's noise, the machine's own model and one with inductances
    50 % too large have nearly the same raw held-out error (the larger L responds less to the noise);
    beyond the noise floor the machine's model leaves almost nothing and the wrong one 4x more."""
    recs = [simulate(GEAR, "healthy", 80.0, 1.0, seed=500 + j, encoder=True) for j in range(4)]
    preps = prepare(recs, GEAR)
    got = {}
    for scale in (1.0, 1.5):
        h = heldout(_machine_model(recs[0].meta, recs[0].meta["fe_hz"], scale), preps)
        got[scale] = (h["nrmse"]["total"], np.hypot(h["nrmse"]["total"], h["noise_floor"]["total"]))
    (true, true_raw), (wrong, wrong_raw) = got[1.0], got[1.5]
    assert abs(wrong_raw / true_raw - 1.0) < 0.05
    assert true < 0.25 * heldout(_machine_model(recs[0].meta, recs[0].meta["fe_hz"]), preps)["noise_floor"]["total"]
    assert wrong > 4.0 * true


def test_noise_sse_counts_the_free_runs_build_up():
    """noise_sse against Monte Carlo: a free run from the measured current has no noise response at
    its start; over its first 1000 samples (a few time constants) the expected voltage-noise sum is
    well below 1000 floors, and matches the mean over draws."""
    rec = simulate(GEAR, "healthy", 80.0, 0.5, seed=43, encoder=True)
    prep = prepare([rec], GEAR)[0]
    sig = prep.sig
    model = _machine_model(rec.meta, rec.meta["fe_hz"])
    var_i = 2.0 / 3.0 * zero_sequence_sigma(sig.i_abc) ** 2
    n = 1000
    expected = noise_sse(model, prep, n) - 2 * n * var_i
    assert expected < 0.9 * n * float(np.sum(noise_floor(model, prep) - var_i))
    rng = np.random.default_rng(8)
    sv = zero_sequence_sigma(sig.v_abc)
    y0, sums = model.simulate(sig), []
    for _ in range(200):
        noisy = Signals.from_abc(sig.v_abc + rng.normal(0.0, sv, sig.v_abc.shape), sig.i_abc, sig.theta_e,
                                 sig.omega_e, sig.ts, sig.pole_pairs)
        sums.append(np.sum((model.simulate(noisy) - y0)[:, :n] ** 2))
    assert expected == pytest.approx(np.mean(sums), rel=0.12)  # 200 draws: about 2 sd


def test_a_claim_is_withheld_where_an_unclaimed_candidate_fits_clearly_better_or_explains_more():
    """The best significant candidate is not claimed where another, not identifiable, at a bound, or
    claimable but short of Holm's level, leaves a held-out NRMSE below 0.8 of its own, or explains a
    larger share of the control's error (the records cannot tell them apart); at 0.9 of it with a
    smaller share, or where the better one is significant itself, the claim stands."""
    from agent.workbench.explain import _better_unclaimed

    def row(effect, nrmse, identifiable=True, at_bound=False, stage="free run"):
        return {"effect": effect, "nrmse_after": nrmse, "identifiable": identifiable, "at_bound": at_bound,
                "explained_fraction": 0.5, "identifiability": {"stage": stage}}

    first = row("flux_harmonics", 0.010)
    rival = row("inverter_deadtime", 0.0063, identifiable=False)
    assert _better_unclaimed([first, rival], first) is rival
    assert _better_unclaimed([first, row("inverter_deadtime", 0.0063, at_bound=True)], first)["effect"] == "inverter_deadtime"
    assert _better_unclaimed([first, row("inverter_deadtime", 0.009, identifiable=False)], first) is None
    more = {**row("current_gain_mismatch", 0.0101), "explained_fraction": 0.51}  # 20017: 93 % against 93 %
    assert _better_unclaimed([first, more], first) is more
    assert _better_unclaimed([first, {**more, "explained_fraction": 0.49}], first) is None
    assert _better_unclaimed([first, {**row("inverter_deadtime", 0.0063), "significant": True}], first) is None
    assert _better_unclaimed([first, row("inverter_deadtime", 0.0063)], first)["effect"] == "inverter_deadtime"
    assert _better_unclaimed([first, rival], None) is None
    # what the measurement cannot show is no rival (a dead time behind a measured voltage), unless it
    # is the model's input itself (the voltage path behind a pulse-cutting window)
    assert _better_unclaimed([first, row("inverter_deadtime", 0.0063, False, stage="unseen")], first) is None
    assert _better_unclaimed([first, row("voltage_delay", 0.0063, False, stage="unseen")], first)["effect"] == "voltage_delay"
    # a negligible fit that fits clearly better is a rival as well: the claim's share may be the base's own approximations'
    assert _better_unclaimed([first, {**row("voltage_delay", 0.0063), "negligible": True}], first)["effect"] == "voltage_delay"


def _shifted(shift: float) -> list:
    """Four rig records at 40-100 % load whose voltage channel lags by ``shift`` samples (linear
    interpolation: a DAQ filter the profile does not state)."""
    recs = []
    for j, load in enumerate((40.0, 60.0, 90.0, 100.0)):
        r = simulate(GEAR, "healthy", load, 1.0, seed=830 + j)
        k = np.arange(r.v_abc.shape[1], dtype=float)
        v = np.array([np.interp(k - shift, k, x) for x in r.v_abc])
        recs.append(Record(r.t, v, r.i_abc, theta_e=r.theta_e, omega_e=r.omega_e, source=f"lag_{j}", meta=r.meta))
    return recs


def test_a_path_change_below_a_tenth_of_a_sample_is_negligible_not_claimed(base80):
    """The voltage path's change is no finding below 0.1 sample (agent.effects.voltage_delay,
    NEGLIGIBLE): a 0.04-sample lag is fitted (a rotation of that size) and marked negligible, never
    significant, with the floor named; a 0.3-sample lag is fitted within 20 % and not marked."""
    rows = {}
    for shift in (0.04, 0.3):
        doc = ex.explain(base80, prepare(_shifted(shift), GEAR), candidates=["voltage_delay", "current_offset"])
        rows[shift] = next(c for c in doc["candidates"] if c["effect"] == "voltage_delay")
    small, large = rows[0.04], rows[0.3]
    assert small["identifiable"] and abs(small["params"]["rotation_samples"]) < 0.1, small
    assert small["negligible"] and not small["significant"]
    assert "negligible" in small["note"] and "0.1 samples" in small["note"]
    assert not large.get("negligible")
    assert large["params"]["rotation_samples"] == pytest.approx(0.3, rel=0.2)


def test_a_fit_is_negligible_where_what_the_records_pin_of_it_is_given_by_a_negligible_one():
    """negligible_as_pinned: a voltage path fitted as a 0.6-sample lead and a 0.6-sample advance
    whose only pinned figure, the rotation, did not change, is no finding; with its delay pinned as
    well it is one. Fully pinned, the figures decide, not the split (a 0.5 lag and a 0.45 lead are a
    0.05-sample change). An effect without floors is never negligible by size."""
    ctx = {"voltage_path": (-1.0, 0.0), "ts": 1e-4}
    only_rotation = {"delay_samples": None, "advance_samples": None, "rotation_samples": -1.0, "delay_us": None}
    every = {"delay_samples": 0.0, "advance_samples": 0.0, "rotation_samples": 0.0, "delay_us": 0.0}
    assert ex.negligible_as_pinned("voltage_delay", [0.0, 0.6, 0.6], only_rotation, ctx)
    assert not ex.negligible_as_pinned("voltage_delay", [0.0, 0.6, 0.6], {**only_rotation, "delay_samples": -1.6}, ctx)
    assert ex.negligible_as_pinned("voltage_delay", [0.5, 0.45, 0.05], every, ctx)
    assert not EFFECTS["voltage_delay"].negligible([0.5, 0.45, 0.05])  # the parameters alone would say otherwise
    assert not ex.negligible_as_pinned("voltage_delay", [0.15, 0.0, 0.0], every, ctx)
    assert not ex.negligible_as_pinned("voltage_delay", [0.0, 0.0, -0.12], every, ctx)
    assert not ex.negligible_as_pinned("current_offset", [0.0, 0.0], {"offset_A": 0.0}, ctx)
    assert not ex.negligible_as_pinned("voltage_delay", [np.nan, 0.0, 0.0], every, ctx)  # no traceback either


def test_an_effect_is_negligible_only_where_every_floored_parameter_is_below_its_floor():
    delay = EFFECTS["voltage_delay"]
    assert delay.negligible([0.05, 0.0, -0.09])
    assert not delay.negligible([0.0, 0.0, 0.12])
    assert not delay.negligible([0.0, 0.2, 0.0])
    assert not EFFECTS["current_offset"].negligible([0.0, 0.0])  # no floor: never negligible by size
    row = {"identifiable": True, "at_bound": False, "explained_fraction": 0.5}
    assert ex._claimable(row) and not ex._claimable({**row, "negligible": True})


def test_reproduced_share_of_one_effects_contribution_by_anothers_form(base80):
    """An effect reproduces itself; a 5th harmonic alone is not a dead time (whose 6 f_e lines are
    a 5th and a 7th in the ratio 49:25, with 11th and 13th besides); an output effect never
    reproduces a voltage effect."""
    preps = prepare([simulate(GEAR, "healthy", load, 0.6, seed=850 + j) for j, load in enumerate((50.0, 90.0))], GEAR)
    fifth = ex.contribution("flux_harmonics", np.array([0.004, 0.001, 0.0, 0.0]), preps)
    assert ex.reproduced(fifth, "voltage", "flux_harmonics", preps) == pytest.approx(1.0, abs=1e-9)
    assert ex.reproduced(fifth, "voltage", "inverter_deadtime", preps) < 0.5
    assert ex.reproduced(fifth, "voltage", "current_offset", preps) == 0.0


def _family_set(seed: int, effect: str | None):
    """A family drive's baseline (four 80 % records) and its four records with ``effect`` hidden
    (None: its null set)."""
    from bench.family import draw_drive, draw_effect, profile, simulate as family_simulate
    from agent.baseline import identify_baseline

    drive = draw_drive(seed)
    prof = profile(drive, timing=True)
    base = identify_baseline([family_simulate(drive, {}, 80.0, 1.0, seed=100 + j) for j in range(4)], prof,
                             window_s=0.5)
    hidden = {effect: draw_effect(drive, effect, seed)} if effect else {}
    return drive, base, prepare([family_simulate(drive, hidden, load, 1.0, seed=200 + j)
                                 for j, load in enumerate((40.0, 60.0, 90.0, 100.0))], prof)


def test_a_claim_whose_contribution_is_a_twins_pattern_is_withheld_naming_what_separates_them(monkeypatch):
    """A family drive (i_d = 0, one speed) with a hidden dead time: the flux harmonics' 5th and 7th
    take its 6 f_e lines (fitted in the ratio 1.9 against the dead time's 49:25, at one phase) and
    were claimed, fitting far better than the dead time's own refit (its fundamental taken by a base
    whose R_s these constant records do not pin). The dead time's form reproduces only 59 % of the
    harmonics' contribution (its 11th and 13th are the rest), but seen through the harmonics' form
    it reproduces more than 90 %: the claim is withheld, and the note says what separates the two.
    Without the projected form (its chance level at 0) the harmonics are claimed again."""
    _, base, preps = _family_set(20016, "inverter_deadtime")
    candidates = ["flux_harmonics", "inverter_deadtime"]
    row = next(c for c in ex.explain(base, preps, candidates=candidates)["candidates"] if c["effect"] == "flux_harmonics")
    assert not row["significant"] and row["twin"]["effect"] == "inverter_deadtime"
    assert row["twin"]["pattern"] >= ex.TWIN_SHARE
    assert "cannot tell flux_harmonics from inverter_deadtime" in row["note"] and "second speed" in row["note"]
    monkeypatch.setattr(ex, "TWIN_CHANCE", 0.0)
    row = next(c for c in ex.explain(base, preps, candidates=candidates)["candidates"] if c["effect"] == "flux_harmonics")
    assert row["significant"] and "twin" not in row


def test_the_pattern_is_checked_on_top_of_a_claim_whose_records_could_have_separated_the_pair():
    """A family drive (20038: MTPA, a speed step, no encoder) with a hidden 5.5 V dead time: its
    records' current angles (turned onto the rotor) span enough for ``separable`` to count them as
    able to tell the dead time from the magnet's harmonics. The dead time is claimed (fitted at 3.5 V); the harmonics,
    refitted on top of it, take the rest, most of it in the dead time's own pattern, and would have
    been claimed as a second effect. What the fit took decides: only what is beyond the pattern
    counts, and it explains less than a claim needs."""
    _, base, preps = _family_set(20038, "inverter_deadtime")
    doc = ex.explain(base, preps, candidates=["flux_harmonics", "inverter_deadtime"])
    rows = {c["effect"]: c for c in doc["candidates"]}
    assert rows["inverter_deadtime"]["significant"] and not rows["flux_harmonics"]["significant"]
    assert "of what its refit takes on top is inverter_deadtime's pattern" in rows["flux_harmonics"]["note"]
    beyond = float(re.search(r"the rest explains ([0-9]+)% of the error", rows["flux_harmonics"]["note"]).group(1))
    assert beyond < 100 * ex.MIN_EXPLAINED


def test_a_contribution_seen_through_its_own_form_is_reproduced_only_by_a_narrower_form(base80):
    """reproduced(..., through=): the dead time's columns projected onto the flux harmonics' (one
    direction of four) reproduce exactly that projection, and not a 7th harmonic alone (a dead
    time's 7th is 25/49 of its 5th, in flux); a form as
    wide as the target's (the harmonics through themselves) reproduces anything, so it counts for
    nothing (0)."""
    preps = prepare([simulate(GEAR, "healthy", load, 0.6, seed=850 + j) for j, load in enumerate((50.0, 90.0))], GEAR)
    own, dead = ex._design("flux_harmonics", preps), ex._design("inverter_deadtime", preps)
    pattern = np.linalg.lstsq(own, dead, rcond=None)[0][:, 0]  # the harmonics' values a dead time leaves
    target = ex.contribution("flux_harmonics", pattern, preps)
    seventh = ex.contribution("flux_harmonics", np.array([0.0, 0.0, 0.004, 0.001]), preps)
    assert ex.reproduced(target, "voltage", "inverter_deadtime", preps, through="flux_harmonics") == pytest.approx(1.0, abs=1e-6)
    negative = ex.contribution("flux_harmonics", -pattern, preps)  # what a negative dead time would leave: none
    assert ex.reproduced(negative, "voltage", "inverter_deadtime", preps, through="flux_harmonics") == 0.0
    assert ex.reproduced(negative, "voltage", "inverter_deadtime", preps) > 0.5  # the direct form ignores the sign
    assert ex.reproduced(seventh, "voltage", "inverter_deadtime", preps, through="flux_harmonics") < 0.5
    assert ex.reproduced(seventh, "voltage", "flux_harmonics", preps, through="flux_harmonics") == 0.0


def test_of_a_dead_time_and_the_magnets_harmonics_at_one_speed_the_one_that_fits_a_hair_better_is_not_claimed(
        monkeypatch):
    """A family drive (i_d = 0, a speed loop) with a hidden dead time: the flux harmonics explain
    79.7 % of the control's error, the dead time 79.5 %, and the harmonics were claimed. At one
    speed and one current angle the two leave the same lines, so neither is claimed unless it fits
    the held-out records significantly better than the other; the note names the records that
    would separate them. With that test at a level any difference passes, the harmonics are claimed.
    (The harmonics' fit is also the dead time's pattern: by default that withholds it first; here
    the pattern check is off, its chance level at 0.)"""
    _, base, preps = _family_set(20057, "inverter_deadtime")
    candidates = ["flux_harmonics", "inverter_deadtime"]
    doc = ex.explain(base, preps, candidates=candidates)
    assert not any(c["significant"] for c in doc["candidates"]), [(c["effect"], c.get("note")) for c in doc["candidates"]]
    monkeypatch.setattr(ex, "TWIN_CHANCE", 0.0)
    doc = ex.explain(base, preps, candidates=candidates)
    assert not any(c["significant"] for c in doc["candidates"]), [(c["effect"], c.get("note")) for c in doc["candidates"]]
    row = doc["candidates"][0]
    other = ({"flux_harmonics", "inverter_deadtime"} - {row["effect"]}).pop()
    assert row["twin"]["effect"] == other and row["twin"]["explains"] > 0.9
    assert f"cannot tell {row['effect']} from {other}" in row["note"] and "second speed" in row["note"]
    monkeypatch.setattr(ex, "TWIN_ALPHA", 1.01)
    doc = ex.explain(base, preps, candidates=candidates)
    assert [c["effect"] for c in doc["candidates"] if c["significant"]] == [row["effect"]]


def test_flux_harmonics_and_dead_time_are_separable_only_across_speeds_or_current_angles():
    """The pair's 6 f_e lines differ only in how they move: the magnet's with the speed, the dead
    time's with the current angle. Records at one speed and one current angle cannot separate them
    (and a second effect of the pair is then not claimed on top of the first); a 20 % speed spread
    or a 5 degree current-angle spread can. Any other pair is separable as far as this rule goes."""
    from types import SimpleNamespace

    def rec(omega, i_d, i_q):
        n = 100
        return SimpleNamespace(sig=SimpleNamespace(omega_e=np.full(n, omega), i_dq=np.stack((np.full(n, i_d),
                                                                                             np.full(n, i_q)))))

    one = [rec(600.0, 0.0, q) for q in (4.0, 6.0, 9.0, 10.0)]  # i_d = 0, loads differ, one speed
    assert not ex.separable("flux_harmonics", "inverter_deadtime", one)
    assert not ex.separable("inverter_deadtime", "flux_harmonics", one)
    assert ex.separable("flux_harmonics", "inverter_deadtime", one[:2] + [rec(730.0, 0.0, 9.0)])
    mtpa = [rec(600.0, -q * np.tan(a), q) for q, a in ((4.0, 0.02), (10.0, 0.02 + np.radians(6.0)))]
    assert ex.separable("flux_harmonics", "inverter_deadtime", mtpa)
    assert ex.separable("flux_harmonics", "current_offset", one)


def test_a_dead_time_is_never_claimed_behind_a_measured_voltage():
    """A family drive whose terminal voltage is measured (it holds the dead-time loss) with hidden
    harmonics of the magnet: the dead time's form takes a share of their lines (36 % on drive 20049;
    on drive 20048, a pure 5th, it was claimed before the harmonics' second, free fit found them:
    that drive's records no longer pin a base since identify leaves its L_d open). With the
    voltage's source known, the dead time is judged unseen by such records and the note says why;
    told the voltage is the command, the same records judge it as any other candidate."""
    drive, base, preps = _family_set(20049, "flux_harmonics")
    assert drive.voltage_source == "measured"
    candidates = ["flux_harmonics", "inverter_deadtime"]
    row = next(c for c in ex.explain(base, preps, candidates=candidates)["candidates"]
               if c["effect"] == "inverter_deadtime")
    assert not row["significant"] and "measured at the terminals" in row["note"], row["note"]
    assert row["identifiability"]["stage"] == "unseen"
    for p in preps:
        p.meta["voltage_source"] = "reference"
    row = next(c for c in ex.explain(base, preps, candidates=candidates)["candidates"]
               if c["effect"] == "inverter_deadtime")
    assert row["identifiability"]["stage"] != "unseen" and "measured at the terminals" not in row["note"]


def test_an_effect_the_one_step_misreads_is_fitted_again_by_the_free_run(monkeypatch):
    """A family drive averaging its current over the interval, with a hidden 5th harmonic of the
    magnet: the one-step regression's reading of the harmonics left the free run no better than
    the control, so they were zeroed ("no gain") and a dead time was claimed for their lines.
    Fitted again with the harmonics free, they are named, significant, the 5th within 20 %."""
    drive, base, preps = _family_set(20050, "flux_harmonics")
    assert drive.current_sampling == "average"
    from bench.family import draw_effect

    truth = draw_effect(drive, "flux_harmonics", 20050)
    assert truth["orders"] == [5]
    candidates = ["flux_harmonics", "inverter_deadtime"]
    doc = ex.explain(base, preps, candidates=candidates)
    assert [c["effect"] for c in doc["candidates"] if c["significant"]] == ["flux_harmonics"], doc["candidates"]
    flux = doc["candidates"][0]
    assert flux["params"]["psi_5_Wb"] == pytest.approx(truth["psi_wb"][0], rel=0.2)
    real = ex.refit
    monkeypatch.setattr(ex, "refit", lambda *a, free=(), **k: real(*a, **k))  # no second fit
    doc = ex.explain(base, preps, candidates=candidates)
    flux = next(c for c in doc["candidates"] if c["effect"] == "flux_harmonics")
    assert not flux["significant"] and "does not lower the error" in flux["note"]


def test_a_first_candidate_that_explains_little_and_misses_the_level_says_both():
    """A family drive (an encoder, i_d = 0, load ripple) with a warming winding: the drift is first
    but explains a few % of the control's error, and its p misses Holm's level. The row names both
    causes (before: no note at all, a first-ranked effect left unclaimed without a word)."""
    _, base, preps = _family_set(20008, "resistance_drift")
    doc = ex.explain(base, preps, candidates=["resistance_drift", "current_offset", "current_gain_mismatch",
                                              "speed_ripple"])
    row = doc["candidates"][0]
    assert row["effect"] == "resistance_drift" and not row["significant"]
    assert 0.0 < row["explained_fraction"] < ex.MIN_EXPLAINED and row["p_value"] >= ex.ALPHA / 4
    assert f"its test does not pass (p = {row['p_value']:.2g}, Holm needs < {ex.ALPHA / 4:.2g})" in row["note"]
    assert f"explains {row['explained_fraction']:.1%}" in row["note"] and "below the 10%" in row["note"]


def test_a_candidate_whose_test_passes_but_explains_little_says_why_it_is_not_claimed():
    """A family drive (no encoder, i_d = 0, asynchronous current sampling) with a 0.01 A offset: the
    offset is first and its test passes (p ~ 1e-14), but it explains about 1 % of a control whose
    error beyond the noise is 5 times the noise floor. Not claimed, and the row says so: its share, the 10 % a
    claim needs, and that a larger error is left (before: no note at all)."""
    _, base, preps = _family_set(20053, "current_offset")
    doc = ex.explain(base, preps, candidates=["current_offset", "current_gain_mismatch"])
    row = next(c for c in doc["candidates"] if c["effect"] == "current_offset")
    assert not row["significant"] and row["p_value"] < 1e-6
    assert 0.0 < row["explained_fraction"] < ex.MIN_EXPLAINED
    assert doc["nrmse_control"] > 2.0 * doc["noise_floor"]
    assert f"explains {row['explained_fraction']:.1%}" in row["note"] and "below the 10%" in row["note"]
    assert f"beyond the noise is {doc['nrmse_control'] / doc['noise_floor']:.3g} times the noise floor" in row["note"]


def test_a_rotation_the_linearisation_calls_unseen_is_kept_where_holding_it_costs_the_fit():
    """A family drive (a switched inverter reporting its command one period early, an encoder, load
    ripple, the current averaged over each interval) with a voltage lead of 0.37 sample on top of
    the stated path: the free run finds the rotation at -0.37 sample, 117 times below the control's
    fit cost, but beside the R_s,q it moved the linearisation called it unseen; held at zero with
    that R_s,q the refit ended 9 times above the control ("no gain", the delay unfound). Holding it
    is now tried with the base refitted, and costs the fit far more than the visible floor: the
    delay is first and claimed, its rotation within 2 % of the truth."""
    drive, base, preps = _family_set(20030, "voltage_delay")
    doc = ex.explain(base, preps)
    row = doc["candidates"][0]
    assert row["effect"] == "voltage_delay" and row["significant"], [(c["effect"], c.get("note")) for c in doc["candidates"]]
    from bench.family import draw_effect, truth

    true = truth(drive, "voltage_delay", draw_effect(drive, "voltage_delay", 20030), [])
    assert abs(row["params"]["rotation_samples"] - (true["delay_samples"] + true["advance_samples"])) < 0.02 * 1.37
    assert row["explained_fraction"] > 0.9


def test_a_figure_the_model_error_moves_is_given_with_a_bound_that_holds_the_truth():
    """A family drive reporting its command (switched, one period of computation delay) whose
    reported voltage lags the applied one by a further 1.33 samples through a window: the columns
    interpolate the report, the window smears it, so the delay and the advance split the rotation
    wrongly (delay -0.10 against the true +0.33, the rotation right within 0.02). Each figure is
    given with its bound, from the error the refit leaves along the step that moves it least: the
    truth lies within it for every figure, and the wrong split's bound is wider than its error."""
    drive, base, preps = _family_set(20005, "voltage_delay")
    doc = ex.explain(base, preps)
    row = doc["candidates"][0]
    assert row["effect"] == "voltage_delay" and row["significant"]
    from bench.family import draw_effect, truth

    true = truth(drive, "voltage_delay", draw_effect(drive, "voltage_delay", 20005), [])
    true["rotation_samples"] = true["delay_samples"] + true["advance_samples"]
    said, bound = row["params"], row["params_bound"]
    assert abs(said["delay_samples"] - true["delay_samples"]) > 0.3  # the split the window moves
    for key in ("delay_samples", "advance_samples", "rotation_samples"):
        assert said[key] is not None and abs(said[key] - true[key]) <= bound[key], (key, said, bound)
    assert bound["rotation_samples"] < bound["delay_samples"]


def test_a_sensor_offset_the_controller_acts_on_is_given_as_the_voltage_that_holds_it():
    """A family drive whose own current sensors carry the offset (its controller acts on them): the
    winding carries -o, the voltage R_s o holds it, and the model reads o R_s / R_s,q. Its R_s,q,
    pinned loosely, is 2.5 times the winding's, so the fit's o is 0.41 of the truth. The records'
    current has no stator-frame DC, so the claim gives the voltage R_s,q o (within 5 % of R_s o,
    agreeing with the records' stator-frame DC voltage and within its bound) and no offset_A, naming
    the nameplate's R_s; with a baseline R_s, offset_A is read through it (within 5 % of the truth
    for the winding's R_s)."""
    import re

    from agent.effects.current_offset import stator_dc, through_resistance
    from bench.family import draw_effect, truth

    drive, base, preps = _family_set(20008, "current_offset")
    doc = ex.explain(base, preps)
    row = doc["candidates"][0]
    assert row["effect"] == "current_offset" and row["significant"]
    true = truth(drive, "current_offset", draw_effect(drive, "current_offset", 20008), [])
    said, bound = row["params"], row["params_bound"]
    assert list(said)[0] == "offset_voltage_V" and said["offset_A"] is None and bound["offset_A"] is None
    assert said["offset_voltage_V"] == pytest.approx(true["offset_voltage_V"], rel=0.05)
    assert abs(said["offset_voltage_V"] - true["offset_voltage_V"]) <= bound["offset_voltage_V"]
    assert "nameplate.rs_ohm" in row["note"] and "stator-frame DC" in row["note"]
    fitted = row["unpinned_params"]["offset_A"]
    rs_q = float(re.search(r"through its R_s,q of ([0-9.]+) ohm", row["note"])[1])
    v_dc = float(re.search(r"stator-frame DC voltage is ([0-9.]+) V", row["note"])[1])
    assert v_dc == pytest.approx(true["offset_voltage_V"], rel=0.1)
    assert rs_q > 2 * drive.rs_ohm and fitted < 0.5 * true["offset_A"]  # the fit's o, read through R_s,q
    signals = [p.sig for p in preps]
    assert abs(stator_dc(signals)) < 0.05 * fitted
    # with the winding's R_s from the baseline (or the nameplate), offset_A is read through it
    ctx = {"Rs_q": rs_q, "signals": signals}
    fig = {"params": {"offset_A": fitted}, "params_bound": {"offset_A": 0.001}}
    got = through_resistance(np.array([fitted, 0.0]), fig, ctx, {"Rs": (drive.rs_ohm, 0.05)})
    assert got["params"]["offset_A"] == pytest.approx(true["offset_A"], rel=0.05)
    assert got["params_bound"]["offset_A"] >= 0.1 * got["params"]["offset_A"]
    assert "read through the baseline's R_s" in got["note"]


def test_a_bound_the_records_do_not_push_is_no_bound():
    """at_bound counts only the parameters the records push onto their bound (``pinned``, from the
    refit's normal equations): one left there for want of anything pulling it measures nothing
    (the zero of a split part never counts)."""
    from agent.effects import get as get_effect
    from agent.workbench.fitting import at_bound

    sat = get_effect("magnetic_saturation")
    bounds = (np.array([0.0, -0.1]), np.array([0.5, 0.1]))
    assert at_bound(np.array([0.2, 0.1]), bounds, sat)
    assert not at_bound(np.array([0.2, 0.1]), bounds, sat, pinned=[True, False])
    assert at_bound(np.array([0.5, 0.1]), bounds, sat, pinned=[True, False])
    assert not at_bound(np.array([0.2, 0.05]), bounds, sat, pinned=[True, True])


def test_a_saturation_whose_cross_term_the_records_cannot_see_is_claimed_by_what_they_pin():
    """Family drive 20043 (MTPA, an encoder, the q chord inductance 22 % lower at rated current):
    the refit's cross-saturation sat at its limit, where the records do not push it, and the claim was
    withheld as "at bound" although the saturation explained 99 % (p = 1.5e-8). Now it is claimed,
    the cross term is not said, and the L_q drop lies within its bound of the truth and within 25 %."""
    from bench.family import draw_effect, truth

    drive, base, preps = _family_set(20043, "magnetic_saturation")
    doc = ex.explain(base, preps)
    top = doc["candidates"][0]
    assert top["effect"] == "magnetic_saturation" and top["significant"] and not top["at_bound"], top
    true = truth(drive, "magnetic_saturation", draw_effect(drive, "magnetic_saturation", 20043), [])
    said, bound = top["params"], top["params_bound"]
    assert said["cross_dpsi_d_at_rated_Wb"] is None and "cross_dpsi_d_at_rated_Wb not separable" in top["note"]
    assert said["lq_drop_at_rated"] == pytest.approx(true["lq_drop_at_rated"], rel=0.25)
    assert abs(said["lq_drop_at_rated"] - true["lq_drop_at_rated"]) <= bound["lq_drop_at_rated"]


def test_the_saturation_drop_is_read_against_the_chord_inductance():
    """Family drive 20014 (i_d = 0, an encoder, a sharp knee: the q chord inductance 26 % lower at
    rated current). The refit's sample-to-sample L_q is the incremental inductance, which
    saturation lowers more than the chord (below 0.8 of the drive's L_q); its L_qx, the d axis's
    omega_e L_q i_q, is the drive's L_q within 10 %. The drop read against L_qx is the truth within
    20 %; read against the sample-to-sample L_q it would be 1.5 times it or more."""
    from bench.family import draw_effect, truth

    drive, base, preps = _family_set(20014, "magnetic_saturation")
    b, prior = ex.drive_base(base), ex.physical_prior(base)
    r = ex.nested(ex.control(base.model, preps, b, prior=prior), preps, ("magnetic_saturation",), b, prior)
    assert r.phys["Lq"] < 0.8 * drive.lq_h and r.phys["Lq_x"] == pytest.approx(drive.lq_h, rel=0.1)
    true = truth(drive, "magnetic_saturation", draw_effect(drive, "magnetic_saturation", 20014), [])["lq_drop_at_rated"]
    drop = ex.reported("magnetic_saturation", r, ex.context(r, preps, base.profile))
    drop = {**drop.get("unpinned_params", {}), **{k: v for k, v in drop["params"].items() if v is not None}}
    assert drop["lq_drop_at_rated"] == pytest.approx(true, rel=0.2)
    assert drop["lq_drop_at_rated"] * r.phys["Lq_x"] / r.phys["Lq"] > 1.5 * true


def test_nothing_is_claimed_where_the_voltage_path_behind_a_pulse_cutting_window_takes_the_error():
    """A family null drive (20776: a switched inverter, its voltage measured through a window 0.23
    sample late): the base leaves 30 times its noise floor, a change of the path (unseen behind the
    window) takes all but 0.2 % of it, and a gain mismatch took 98.6 % and was claimed. Now nothing
    is claimed: the current offset, which takes as much, is withheld with a note naming the path and
    the records that would tell; the gain mismatch is tested on the phase currents' sum, which shows
    the sensors equal, and its note says that what its refit takes is not shown to be the sensors."""
    _, base, preps = _family_set(20776, None)
    doc = ex.explain(base, preps)
    assert not any(c["significant"] for c in doc["candidates"])
    rows = {c["effect"]: c for c in doc["candidates"]}
    gain, delay, offset = rows["current_gain_mismatch"], rows["voltage_delay"], rows["current_offset"]
    assert gain["p_value"] < 1e-4 and (gain["explained_fraction"] or 0.0) > 0.9  # it would have been claimed
    assert gain["test"] == "direct" and gain["p_value_direct"] > 0.05 and "not shown to be this effect" in gain["note"]
    assert delay["identifiability"]["stage"] == "unseen" and delay["nrmse_after"] < 0.8 * offset["nrmse_after"]
    assert offset["p_value"] < 1e-4 and (offset["explained_fraction"] or 0.0) > 0.9
    assert "not claimed: voltage_delay fits the held-out records as well or better" in offset["note"]
    assert "cuts the PWM pulses" in offset["note"] and "sampling.voltage_source" in offset["note"]


def test_a_candidate_holm_passes_but_that_is_not_claimed_is_not_said_to_need_more_records():
    """A family drive with a hidden current offset (20026, an encoder): the saturation passes Holm's
    level against the control (p about 5e-9) but not on top of the offset, which is claimed. Its
    note says so; it names no count of records that would settle it (a drive like it had said "about
    4 records like these", with four records and a p far below the level)."""
    _, base, preps = _family_set(20026, "current_offset")
    doc = ex.explain(base, preps)
    assert [c["effect"] for c in doc["candidates"] if c["significant"]] == ["current_offset"]
    row = next(c for c in doc["candidates"] if c["effect"] == "magnetic_saturation")
    assert row["p_value"] < 1e-4 and "not on top of current_offset" in row["note"]
    assert "records_needed" not in row and ex.SETTLED_BY not in row["note"]