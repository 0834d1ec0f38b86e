"""Drive profile parsing (CONTRACT section 4)."""

from pathlib import Path

import pytest

from agent.errors import InputError
from agent.profile import load_profile

ROOT = Path(__file__).resolve().parent.parent
GEAR = (ROOT / "config" / "profiles" / "rig_gear.toml").read_text()


def write(tmp_path, text):
    p = tmp_path / "p.toml"
    p.write_text(text)
    return p


def test_shipped_profiles_load():
    gear = load_profile(ROOT / "config" / "profiles" / "rig_gear.toml")
    chain = load_profile(ROOT / "config" / "profiles" / "rig_chain.toml")
    assert gear.rated_fe_hz == pytest.approx(100.0)
    assert gear.transmission.ratio == 2.0 and chain.transmission.kind == "chain"
    assert gear.ts == pytest.approx(40e-6)
    assert gear.torque_per_watt == pytest.approx(14.0 / 2200.0)


def test_contract_minimal_profile(tmp_path):
    p = write(tmp_path, """[motor]
pole_pairs = 4
rated_power_w = 2200.0
rated_torque_nm = 14.0
rated_speed_rpm = 1500.0
[sampling]
rate_hz = 25000.0
voltage_source = "reference"
[transmission]
kind = "gear"
driving_teeth = 20
driven_teeth = 40
""")
    prof = load_profile(p)
    assert prof.sampling.voltage_source == "reference" and prof.motor.rated_current_a is None


@pytest.mark.parametrize("edit, needle", [
    (lambda t: t.replace("[sampling]", "[sampling]\nratehz = 1.0"), "unknown key 'sampling.ratehz'"),
    (lambda t: t + "\n[extra]\nx = 1\n", "unknown key 'extra'"),
    (lambda t: t.replace("pole_pairs = 4\n", ""), "missing key 'motor.pole_pairs'"),
    (lambda t: t.replace("pole_pairs = 4", 'pole_pairs = "four"'), "'motor.pole_pairs' has the wrong type"),
    (lambda t: t.replace("rate_hz = 25000.0", "rate_hz = -1.0"), "'sampling.rate_hz' must be positive"),
    (lambda t: t.replace('kind = "gear"', 'kind = "belt"'), "transmission.kind"),
    (lambda t: t.replace('kind = "gear"', 'kind = "chain"'), "missing key 'transmission.driving_pitch_diameter_mm'"),
    (lambda t: t.replace('voltage_source = "measured"', 'voltage_source = "x"'), "sampling.voltage_source"),
    (lambda t: t.replace("[motor]", "[motor"), "not valid TOML"),
    (lambda t: t.replace("[sampling]", '[sampling]\nvoltage_hold = "alpha-beta"'), "sampling.voltage_hold"),
    (lambda t: t.replace("[sampling]", '[sampling]\nvoltage_hold = "dq"'), 'needs sampling.inverter = "continuous"'),
    (lambda t: t.replace("control_rate_hz = 25000.0", "control_rate_hz = 0.0"), "'sampling.control_rate_hz' must be positive"),
])
def test_bad_profiles_name_the_key(tmp_path, edit, needle):
    p = write(tmp_path, edit(GEAR))
    with pytest.raises(InputError) as err:
        load_profile(p)
    assert needle in str(err.value)
    assert str(p) in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such profile file"):
        load_profile(tmp_path / "nope.toml")
