"""``model compare``'s "where it fails" (agent.workbench.compare.where): fault lines at their exact
frequencies (agent.frequencies, not the FFT bin), and suggestions that follow from the residual's
own evidence: a DC in the phase residual is a current offset, a correlation with the voltage's
sample-to-sample change is a voltage delay; neither is suggested without its evidence."""

from __future__ import annotations

import pytest

from agent.frequencies import fault_frequencies
from agent.simulator import simulate
from agent.workbench.compare import compare
from agent.workbench.fitting import prepare
from runtime_support import healthy_baseline, profile

pytestmark = pytest.mark.timeout(300)


def where(condition: str = "healthy", effects: dict | None = None) -> tuple[dict, list]:
    recs = [simulate(profile(), condition, 80.0, 2.0, seed=900 + j, effects=effects or {}) for j in range(2)]
    preps = prepare(recs, profile())
    doc, _ = compare(healthy_baseline(), preps)
    return {w["kind"]: w for w in doc["where"] if w["kind"] != "spectrum_peak"}, \
        ([w for w in doc["where"] if w["kind"] == "spectrum_peak"], sum(p.op["fe_hz"] for p in preps) / len(preps))


def test_sidebands_are_named_at_their_exact_frequencies():
    _, (peaks, fe) = where("gear_severe_wear")
    exact = {line["freq_hz"] for line in fault_frequencies(profile(), fe, 3)["gear_driven"]}
    driven = [p for p in peaks if p["label"].startswith("gear_driven k=1")]
    assert sorted(round(p["freq_hz"], 1) for p in driven) == [87.5, 112.5], driven
    for p in driven:
        assert p["freq_hz"] in exact and p["bin_hz"] != p["freq_hz"] and abs(p["bin_hz"] - p["freq_hz"]) < 1.5


@pytest.mark.parametrize("effects, offset, delay", [
    ({}, False, False),
    ({"current_offset": 0.1}, True, False),
    ({"current_offset": 0.02}, True, False),
    ({"voltage_delay": 1.0}, False, True),
    ({"voltage_delay": 0.3}, False, True),
    ({"current_offset": 0.1, "voltage_delay": 1.0}, True, True),
    ({"flux_harmonics": 0.005}, False, False),
])
def test_offset_and_delay_are_suggested_by_their_own_evidence(effects, offset, delay):
    found, _ = where(effects=effects)
    assert ("current_offset" in found["offset"]["effects"]) is offset, found["offset"]["summary"]
    cross = found["cross_correlation"]
    assert ("voltage_delay" in cross["effects"]) is delay, cross["summary"]
    if offset and not delay:  # the slow cross-correlation an offset leaves is named as the offset's
        assert "current_offset" in cross["effects"] and "not a delay" not in cross["summary"]
    assert "current_offset" not in found["current"]["effects"]  # the offset has its own finding
