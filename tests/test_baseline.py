"""Baseline statistics (Algs. 3-4), the Table 4 decision rule, and model files."""

from pathlib import Path

import numpy as np
import pytest
import scipy.spatial.distance
import scipy.stats

from agent.baseline import Cluster, centre_spread, identify_baseline, window_spectra
from agent.decision import diagnose, spectrum_decision
from agent.errors import InputError
from agent.modelfile import load_baseline, save_baseline, write_atomic
from agent.profile import load_profile
from agent.simulator import simulate

ROOT = Path(__file__).resolve().parent.parent
GEAR = load_profile(ROOT / "config" / "profiles" / "rig_gear.toml")


def test_centre_spread_mean_std_and_median_mad():
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 0.5, (31, 7))
    c, s = centre_spread(x, robust=False)
    np.testing.assert_allclose(c, x.mean(axis=0))
    np.testing.assert_allclose(s, x.std(axis=0, ddof=1))
    c, s = centre_spread(x, robust=True)
    np.testing.assert_allclose(c, np.median(x, axis=0))
    np.testing.assert_allclose(s, 1.4826 * np.median(np.abs(x - np.median(x, axis=0)), axis=0))


def test_one_outlier_record_hides_a_fault_from_mean_std_but_not_from_median_mad():
    """Alg. 3 thresholds with one faulty record slipped into the healthy set."""
    rng = np.random.default_rng(1)
    healthy = rng.normal(1.0, 0.05, 30)
    training = np.append(healthy, 3.0)  # the outlier: a faulty record among the healthy ones
    fault = 1.25  # a 5-sigma fault line
    c, s = centre_spread(training, robust=False)
    assert fault < c + 2 * s  # mean + 2 std: hidden
    c, s = centre_spread(training, robust=True)
    assert fault > c + 3 * s  # median + 3 MAD-sigma: warning


def test_window_spectra_one_per_window():
    fs = 1000.0
    t = np.arange(4500) / fs
    x = 0.3 * np.cos(2 * np.pi * 50 * t) * (1 + (t >= 2.0))  # amplitude doubles in the third window
    f, a = window_spectra(x, fs, window_s=1.0, f_max_hz=200.0)
    assert f[-1] == 200.0 and a.shape == (4, 201)
    np.testing.assert_allclose(a[:, 50], [0.3, 0.3, 0.6, 0.6], rtol=1e-9)
    with pytest.raises(ValueError, match="fewer than one window"):
        window_spectra(x[:900], fs, window_s=1.0)


def test_cluster_limits_and_distance():
    rng = np.random.default_rng(2)
    pts = rng.multivariate_normal([1e-3, 0.08], [[1e-10, 2e-9], [2e-9, 1e-7]], 30)
    chi2 = Cluster.fit(pts, region="chi2")
    assert chi2.limit == pytest.approx(5.9915, rel=1e-4)
    pred = Cluster.fit(pts, region="prediction")
    m, p = 30, 2
    want = p * (m - 1) * (m + 1) / (m * (m - p)) * scipy.stats.f.ppf(0.95, p, m - p)
    assert pred.limit == pytest.approx(want) and pred.limit > chi2.limit
    x = np.array([1.01e-3, 0.0805])
    vi = np.linalg.inv(np.cov(pts, rowvar=False))
    assert pred.distance2(x) == pytest.approx(scipy.spatial.distance.mahalanobis(x, pts.mean(0), vi) ** 2, rel=1e-6)


def test_prediction_region_covers_95_percent_of_fresh_healthy_points():
    """Monte Carlo: over many healthy trainings of m = 30, a fresh point falls inside the Hotelling
    prediction ellipse 95 % of the time; the chi-square ellipse covers less (its known optimism)."""
    rng = np.random.default_rng(3)
    inside = {"prediction": 0, "chi2": 0}
    trials = 4000
    for _ in range(trials):
        pts = rng.normal(size=(31, 2)) * [2.0, 0.5]
        for region in inside:
            cl = Cluster.fit(pts[:30], region=region)
            inside[region] += cl.distance2(pts[30]) <= cl.limit
    assert inside["prediction"] / trials == pytest.approx(0.95, abs=0.012)
    assert inside["chi2"] / trials < 0.94


def test_robust_cluster_ignores_an_outlier():
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(30, 2))
    pts[0] = (40.0, 40.0)
    cl = Cluster.fit(pts, robust=True)
    assert np.all(np.abs(cl.centre) < 0.6) and cl.distance2((4.0, 4.0)) > cl.limit
    assert Cluster.fit(pts).distance2((4.0, 4.0)) < Cluster.fit(pts).limit  # classical: swamped


def _line(family, k, level, f):
    return {"family": family, "k": k, "level": level, "freq_hz": f}


def test_pair_rule_needs_both_sidebands():
    one = [_line("gear_driven", 1, "warning", 87.5), _line("gear_driven", 1, "normal", 112.5)]
    both = [_line("gear_driven", 2, "caution", 75.0), _line("gear_driven", 2, "warning", 125.0)]
    assert spectrum_decision(one, "line")[0] == "warning"
    assert spectrum_decision(one, "pair") == ("normal", [])
    state, lines = spectrum_decision(one + both, "pair")
    assert state == "caution" and [p["freq_hz"] for p in lines] == [75.0, 125.0]
    with pytest.raises(ValueError):
        spectrum_decision(one, "majority")


@pytest.fixture(scope="module")
def small_baseline():
    recs = [simulate(GEAR, "healthy", 80.0, 1.2, seed=300 + j) for j in range(8)]
    return identify_baseline(recs, GEAR, window_s=0.5)


def test_model_file_round_trip_gives_identical_diagnosis(small_baseline, tmp_path):
    path = save_baseline(small_baseline, tmp_path / "m.json")
    loaded = load_baseline(path)
    np.testing.assert_array_equal(loaded.thresholds.th3, small_baseline.thresholds.th3)
    np.testing.assert_array_equal(loaded.model.theta_q, small_baseline.model.theta_q)
    rec = simulate(GEAR, "gear_severe_wear", 80.0, 1.2, seed=999)
    assert diagnose(loaded, rec).to_json() == diagnose(small_baseline, rec).to_json()


def test_operating_point_far_from_the_model_is_noted(small_baseline):
    d = diagnose(small_baseline, simulate(GEAR, "healthy", 40.0, 1.2, seed=5))
    assert any("load" in n for n in d.notes)
    assert not diagnose(small_baseline, simulate(GEAR, "healthy", 80.0, 1.2, seed=6)).notes


def test_write_atomic_keeps_the_old_file_when_writing_fails(tmp_path, monkeypatch):
    path = tmp_path / "m.json"
    write_atomic(path, b"good")
    import os

    def boom(*a):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(InputError, match="m.json: cannot write model: disk full"):
        write_atomic(path, b"partial")
    assert path.read_bytes() == b"good"
    assert [p.name for p in tmp_path.iterdir()] == ["m.json"]


def test_write_atomic_without_replace_keeps_a_file_that_appeared_meanwhile(tmp_path):
    """A model version is never overwritten, even one written while the caller was refitting."""
    path = tmp_path / "m.json"
    write_atomic(path, b"v1", replace=False)
    with pytest.raises(InputError, match="never overwritten"):
        write_atomic(path, b"v2", replace=False)
    assert path.read_bytes() == b"v1" and [p.name for p in tmp_path.iterdir()] == ["m.json"]
    write_atomic(path, b"v3")  # the library's own files are replaced
    assert path.read_bytes() == b"v3"


def test_too_few_records():
    with pytest.raises(ValueError, match="at least 4"):
        identify_baseline([simulate(GEAR, seconds=0.5, seed=1)] * 3, GEAR, window_s=0.2)


def test_unknown_model_effect_is_input_error(small_baseline, tmp_path):
    import json

    from agent.modelfile import baseline_to_json

    doc = baseline_to_json(small_baseline)
    doc["model"]["effects"] = ["warp_drive"]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=str(bad)):
        load_baseline(bad)


@pytest.mark.parametrize("n_eff", [[0.0], [float("nan")], "many"])
def test_bad_alarm_evidence_in_a_model_file_is_input_error(small_baseline, tmp_path, n_eff):
    """A model file whose independent-window counts are not counts is corrupt (exit 2 in the CLI,
    quality no_model in the agent), never a division by zero on the first hop."""
    import json

    from agent.modelfile import baseline_to_json

    doc = baseline_to_json(small_baseline)
    doc["evidence"]["window_n_eff"] = n_eff
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="corrupt model file"):
        load_baseline(bad)
