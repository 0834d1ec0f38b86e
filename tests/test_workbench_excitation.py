"""Records with little excitation: explain answers "no dynamics" instead of ranking effects against a
base the records cannot pin down, names what would, and ranks once a nameplate carries the
inductances (issue: the workbench across the family of real drives, point 3)."""

import json
import tomllib

import numpy as np
import pytest

from agent.baseline import identify_baseline
from agent.cli import main
from agent.profile import parse_profile
from agent.records import save_record
from agent.simulator import simulate
from agent.simulator.rig import RigParams
from agent.workbench.excitation import dynamics
from agent.workbench.explain import explain, physical_prior
from agent.workbench.fitting import prepare
from bench.workbench_evidence import GEAR, GEAR_PATH

QUIET = RigParams(sigma_i_drive=1e-4)  #: a drive whose own current sensing is nearly noise-free: a smooth voltage


def _plated(rig: RigParams):
    """The rig's profile with a nameplate: R_s, psi_m and both inductances within a few %."""
    doc = tomllib.loads(GEAR_PATH.read_text())
    doc["nameplate"] = {"rs_ohm": rig.R_s, "psi_m_wb": rig.psi_m * 1.02, "ld_h": rig.L_d * 0.97, "lq_h": rig.L_q * 1.03}
    return parse_profile(doc, source="rig_gear with nameplate")


@pytest.fixture(scope="module")
def quiet_sets():
    base = [simulate(GEAR, "healthy", 80.0, 1.0, seed=700 + j, rig=QUIET) for j in range(4)]
    other = [simulate(GEAR, "healthy", load, 1.0, seed=100 + j, rig=QUIET) for j, load in enumerate((40, 60, 90, 100))]
    return base, other


def test_constant_references_give_the_no_dynamics_answer_not_a_ranking(quiet_sets, tmp_path, capsys):
    base, other = quiet_sets
    for j, r in enumerate(base):
        save_record(r, tmp_path / f"b{j}.npz")
    for j, r in enumerate(other):
        save_record(r, tmp_path / f"x{j}.npz")
    assert main(["identify", "--profile", str(GEAR_PATH), "--window", "0.5", "--out", str(tmp_path / "m.json"),
                 *map(str, sorted(tmp_path.glob("b*.npz")))]) == 0
    capsys.readouterr()
    data = list(map(str, sorted(tmp_path.glob("x*.npz"))))
    assert main(["model", "explain", "--model", str(tmp_path / "m.json"), *data, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["candidates"] == []
    assert doc["note"].startswith("these records carry almost no dynamics (voltage spread ")
    assert "record a load or speed step" in doc["note"] and "nameplate.lq_h" in doc["note"]
    dyn = doc["dynamics"]
    # the figures the note gives are the records' own: the spread hardly above the channel's noise
    assert dyn["voltage_spread_v"] < 2 * dyn["voltage_noise_v"]
    assert dyn["quiet"] and "Lq" in dyn["unpinned"] and dyn["inductance_rel_se"]["Lq"] > 0.1
    assert main(["model", "explain", "--model", str(tmp_path / "m.json"), *data]) == 0
    out = capsys.readouterr().out
    assert "no effect ranked: these records carry almost no dynamics" in out


def test_the_drive_s_own_noise_is_dynamics_enough():
    """The rig as it is (its current sensing's noise drives the current loop): both inductances pinned."""
    recs = [simulate(GEAR, "healthy", 80.0, 0.6, seed=700 + j) for j in range(3)]
    dyn = dynamics(prepare(recs, GEAR), {})
    assert dyn["unpinned"] == [] and max(dyn["inductance_rel_se"].values()) < 0.05
    assert dyn["voltage_spread_v"] > 3 * dyn["voltage_noise_v"]


def test_with_the_nameplate_the_same_records_are_ranked(quiet_sets):
    """The nameplate carries the inductances the records cannot: explain ranks, and claims nothing on
    a drive that has no hidden effect."""
    base, other = quiet_sets
    plated = _plated(QUIET)
    b = identify_baseline(base, plated, window_s=0.5)
    assert {"Ld", "Lq"} <= set(physical_prior(b))
    doc = explain(b, prepare(other, plated))
    assert "note" not in doc and len(doc["candidates"]) >= 7
    assert not [c["effect"] for c in doc["candidates"] if c["significant"]]
    assert doc["nrmse_control"] is not None and np.isfinite(doc["nrmse_control"])
