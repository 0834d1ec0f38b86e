"""Fault characteristic frequencies (paper eqs. 19-22) against the paper's rig numbers."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from agent.errors import InputError
from agent.frequencies import base_frequencies, fault_frequencies
from agent.profile import load_profile

PROFILES = Path(__file__).resolve().parents[1] / "config" / "profiles"
GEAR = load_profile(PROFILES / "rig_gear.toml")
CHAIN = load_profile(PROFILES / "rig_chain.toml")


def freqs(family):
    return [p["freq_hz"] for p in family]


def test_paper_gear_numbers():
    fam = fault_frequencies(GEAR, 100.0, k_max=2)
    assert set(fam) == {"gear_driving", "gear_driven"}
    assert freqs(fam["gear_driven"]) == pytest.approx([75.0, 87.5, 112.5, 125.0], abs=0.1)  # Fig. 8
    assert [p["k"] for p in fam["gear_driven"]] == [2, 1, 1, 2]
    assert freqs(fam["gear_driving"]) == pytest.approx([50.0, 75.0, 125.0, 150.0], abs=1e-12)


def test_paper_chain_numbers():
    fam = fault_frequencies(CHAIN)  # rated speed: fe = 1500 rpm / 60 * 4 = 100 Hz, k = 1..3
    assert set(fam) == {"gear_driving", "gear_driven", "chain"}
    assert freqs(fam["chain"]) == pytest.approx([74.4, 83.0, 91.5, 108.5, 117.0, 125.6], abs=0.1)  # Fig. 10c
    assert [p["k"] for p in fam["chain"]] == [3, 2, 1, 1, 2, 3]
    assert {75.0, 87.5, 125.0} <= set(freqs(fam["gear_driven"]))  # driven sprocket, 15/30 teeth


def test_base_frequencies():
    b = base_frequencies(GEAR)
    assert b == {"gear_driving": 25.0, "gear_driven": 12.5}  # eqs. 19-20 at fe = 100 Hz
    c = base_frequencies(CHAIN, fe_hz=60.0)
    assert c["gear_driving"] == pytest.approx(15.0) and c["gear_driven"] == pytest.approx(7.5)
    assert c["chain"] == pytest.approx(2 * math.pi * 0.045810 / 2 * 15.0 / 0.423)  # eq. 21 in SI


def test_families_scale_with_fe_and_are_sorted():
    a, b = fault_frequencies(CHAIN, 50.0, 3), fault_frequencies(CHAIN, 100.0, 3)
    for name in a:
        assert freqs(b[name]) == pytest.approx([2 * f for f in freqs(a[name])])
        assert freqs(a[name]) == sorted(freqs(a[name]))
        assert sorted(p["k"] for p in a[name]) == [1, 1, 2, 2, 3, 3]
    json.dumps(b)


def test_non_positive_sidebands_dropped():
    fam = fault_frequencies(GEAR, 100.0, k_max=6)  # f_gm = 25 Hz: fe - 4 f = 0, fe - 5 f < 0
    assert [(p["k"], p["freq_hz"]) for p in fam["gear_driving"]] == [
        (3, 25.0), (2, 50.0), (1, 75.0), (1, 125.0), (2, 150.0), (3, 175.0), (4, 200.0), (5, 225.0), (6, 250.0)]
    assert len(fam["gear_driven"]) == 12  # f_gl = 12.5 Hz: k <= 6 stays positive


@pytest.mark.parametrize("fe", [0.0, -5.0, math.nan, math.inf])
def test_bad_fe(fe):
    with pytest.raises(InputError, match="fe must be positive"):
        fault_frequencies(GEAR, fe)


@pytest.mark.parametrize("k", [0, -1, 1.5, True])
def test_bad_k(k):
    with pytest.raises(InputError, match="k must be a positive integer"):
        fault_frequencies(GEAR, k_max=k)


def test_numpy_integer_k():
    assert fault_frequencies(GEAR, k_max=np.int64(2)) == fault_frequencies(GEAR, k_max=2)
