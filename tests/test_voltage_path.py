"""The drive's voltage path (agent.workbench.voltage_path): learned from healthy records against the
independent reference bench.family.effects.voltage_path, stored in the model file, applied by the
workbench before it fits."""

import dataclasses

import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt

from agent.baseline import identify_baseline
from agent.frames import CLARKE
from agent.model import Signals
from agent.modelfile import baseline_from_json, baseline_to_json
from agent.workbench.explain import explain
from agent.workbench.fitting import prepare
from agent.workbench.voltage_path import apply_path, path_of
from bench.family import draw_drive, profile, simulate
from bench.family.effects import voltage_path

SEED = 20005  #: reference voltage, abc hold, one computation period: the path is (-1, 0)


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


@pytest.fixture(scope="module")
def learned():
    drive = draw_drive(SEED)
    prof = profile(drive)
    healthy = [simulate(drive, {}, 80.0, 1.0, seed=100 + j) for j in range(4)]
    return drive, prof, identify_baseline(healthy, prof, window_s=0.5, learn_path=True)


def test_the_learned_path_is_the_drives(learned):
    drive, _, base = learned
    d, a = voltage_path(drive)
    assert (d, a) == (-1.0, 0.0)
    got = path_of(base.model.meta)
    assert got is not None, base.model.meta["voltage_path"]
    assert abs(got[0] - d) <= 0.15 and abs(got[1] - a) <= 0.3


def test_the_model_file_round_trips_the_path(learned):
    base = learned[2]
    again = baseline_from_json(baseline_to_json(base))
    assert path_of(again.model.meta) == path_of(base.model.meta)
    assert again.model.meta["voltage_path"]["source"] == "records"


def _smooth(rec):
    """The record with its voltage low-passed (zero phase) at a 20th of the sampling rate: no broadband left."""
    sos = butter(4, 0.05 * rec.rate_hz, fs=rec.rate_hz, output="sos")
    return dataclasses.replace(rec, v_abc=sosfiltfilt(sos, rec.v_abc, axis=1))


def test_records_that_cannot_pin_it_give_no_path_and_say_so(learned):
    drive, prof, _ = learned
    base = identify_baseline([_smooth(simulate(drive, {}, 80.0, 1.0, seed=100 + j)) for j in range(4)], prof,
                             window_s=0.5, learn_path=True)
    meta = base.model.meta["voltage_path"]
    assert path_of(base.model.meta) is None, meta
    assert meta["delay_samples"] is None and "pins it" in meta["note"]


@pytest.mark.xfail(strict=True, reason="known failure: at one load the lumped parameters absorb a measured voltage's "
                   "filter lag (0.92 samples) and the scan pins the path near 0")
def test_a_filter_lag_at_one_load_is_not_pinned_wrongly():
    drive = draw_drive(20003)  # measured voltage, filter lag 0.92 samples
    prof = profile(drive)
    base = identify_baseline([simulate(drive, {}, 80.0, 1.0, seed=100 + j) for j in range(4)], prof, window_s=0.5,
                             learn_path=True)
    got = path_of(base.model.meta)
    assert got is None or abs(got[0] - voltage_path(drive)[0]) <= 0.25


def test_explain_with_the_path_claims_nothing_and_fits_better(learned):
    drive, prof, base = learned
    recs = [simulate(drive, {}, load, 1.0, seed=200 + j) for j, load in enumerate((40.0, 60.0, 90.0, 100.0))]
    raw = explain(base, prepare(recs, prof))
    moved = explain(base, prepare(recs, prof, path=path_of(base.model.meta)))
    assert not [c["effect"] for c in moved["candidates"] if c["significant"]]
    ratio = lambda doc: doc["nrmse_control"] / doc["noise_floor"]  # noqa: E731
    assert ratio(moved) < 0.5 * ratio(raw), (ratio(moved), ratio(raw))
    row = next(c for c in moved["candidates"] if c["effect"] == "voltage_delay")
    total = row.get("unpinned_params", row["params"])  # reported as totals: the baseline's path plus the change
    assert abs(total["delay_samples"] - -1.0) <= 0.5
