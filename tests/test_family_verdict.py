"""diagnose's family verdict: the component most likely at fault from all its sideband pairs
together, lines shared by two families listed once and marked ``shared_with`` (agent.decision).
On the rig's 20/40 gears the driving gear's k=1 pair is the driven gear's k=2 (shared); on 20/37
gears no pair is shared."""

from __future__ import annotations

import functools
import json

import pytest

from agent.cli import main
from agent.decision import diagnose
from agent.modelfile import save_baseline
from agent.records import save_record
from agent.simulator import simulate
from runtime_support import PROFILE_PATH, healthy_baseline, profile

pytestmark = pytest.mark.timeout(300)

#: condition -> the family at fault (the simulator's table: gl is the driven gear, gm the driving gear)
AT_FAULT = {"gear_severe_wear": "gear_driven", "gear_slight_wear": "gear_driven",
            "gear_no_lubricant": "gear_driven", "gear_driving_wear": "gear_driving"}


@functools.lru_cache(maxsize=None)
def odd_ratio():
    """A 20/37 gear profile (no shared lines) and a baseline from 8 healthy 2 s records on it."""
    import tempfile
    from pathlib import Path

    from agent.baseline import identify_baseline
    from agent.profile import load_profile

    path = Path(tempfile.mkdtemp()) / "gear_20_37.toml"
    path.write_text(PROFILE_PATH.read_text().replace("driven_teeth = 40", "driven_teeth = 37")
                    .replace('name = "rig_gear"', 'name = "gear_20_37"'))
    prof = load_profile(path)
    recs = [simulate(prof, "healthy", 80.0, 2.0, seed=600 + j) for j in range(8)]
    return prof, identify_baseline(recs, prof, window_s=1.0)


@pytest.mark.parametrize("condition, severity", [("gear_severe_wear", 1.0), ("gear_slight_wear", 1.0),
                                                 ("gear_no_lubricant", 1.0), ("gear_driving_wear", 1.0),
                                                 ("gear_driving_wear", 0.3)])
def test_the_verdict_names_the_worn_gear_where_lines_coincide(condition, severity):
    d = diagnose(healthy_baseline(), simulate(profile(), condition, 80.0, 4.0, seed=300, severity=severity))
    assert d.state == "warning" and d.verdict["family"] == AT_FAULT[condition], d.reason
    assert d.reason.startswith(f"{AT_FAULT[condition]} most likely at fault"), d.reason
    assert d.peaks[0]["family"] == AT_FAULT[condition]  # the lines of the family at fault come first
    # the shared pair (driving k=1 = driven k=2) is listed once, marked, under the family at fault
    listed = [(p["family"], p["k"], p["freq_hz"]) for p in d.peaks]
    assert len({f for *_, f in listed}) == len(listed), listed
    shared = [p for p in d.peaks if p["shared_with"]]
    other = ({"gear_driven", "gear_driving"} - {AT_FAULT[condition]}).pop()
    for p in shared:
        assert p["family"] == AT_FAULT[condition] and p["shared_with"][0].startswith(other)
        assert min(abs(p["target_hz"] - 75.0), abs(p["target_hz"] - 125.0)) < 0.2
    fams = {f["family"]: f for f in d.verdict["families"]}
    rows = {r["k"]: r for r in fams["gear_driving"]["pairs"]}
    assert rows[1]["shared_with"] == ["gear_driven k=2"] and rows[2]["shared_with"] == []


def test_a_healthy_record_has_no_family():
    d = diagnose(healthy_baseline(), simulate(profile(), "healthy", 80.0, 4.0, seed=301))
    assert d.state == "normal" and d.verdict["family"] is None and "no sideband pair" in d.reason


@pytest.mark.parametrize("condition", ["gear_severe_wear", "gear_driving_wear"])
def test_the_verdict_where_no_lines_coincide(condition):
    prof, base = odd_ratio()
    d = diagnose(base, simulate(prof, condition, 80.0, 2.0, seed=310))
    assert d.verdict["family"] == AT_FAULT[condition], d.reason
    assert all(not p["shared_with"] for p in d.peaks) and "shared lines" not in d.reason
    assert all(not r["shared_with"] for f in d.verdict["families"] for r in f["pairs"])


def test_diagnose_prints_and_reports_the_verdict(tmp_path, capsys):
    model = str(save_baseline(healthy_baseline(), tmp_path / "m.json"))
    rec = str(save_record(simulate(profile(), "gear_severe_wear", 80.0, 4.0, seed=302), tmp_path / "s.npz"))
    assert main(["diagnose", "--model", model, rec]) == 0
    text = capsys.readouterr().out
    assert "verdict: gear_driven most likely at fault" in text and "(shared with gear_driving k=1)" in text, text
    assert text.index("gear_driven k=1") < text.index("peaks:") + 40  # the driven gear's k=1 listed first
    assert main(["diagnose", "--json", "--model", model, rec]) == 0
    r = json.loads(capsys.readouterr().out)["results"][0]
    assert r["reason"].startswith("gear_driven most likely at fault") and r["verdict"]["family"] == "gear_driven"
    assert any(p["shared_with"] == ["gear_driving k=1"] for p in r["peaks"])
