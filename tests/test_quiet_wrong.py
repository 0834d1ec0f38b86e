"""No quiet wrong answers: a table of bad inputs to every command, each refused with exit 2, one
line on stderr naming its true cause (the file, key or value), the JSON error object with
``--json``, and nothing refused changes a file: no model, no library, no journal, no output.

(Moved here from tests/test_bad_inputs.py and extended; that file keeps the other bad-input tests.)"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from agent.cli import main
from agent.modelfile import FORMAT, save_baseline
from agent.records import save_record
from runtime_support import PROFILE_PATH, healthy_baseline, sim

pytestmark = pytest.mark.timeout(600)
P = str(PROFILE_PATH)
RATE = 25_000.0


def _profile(d: Path, name: str, old: str, new: str) -> None:
    text = PROFILE_PATH.read_text()
    assert old in text, old
    (d / name).write_text(text.replace(old, new))


def _csv(d: Path, name: str, header: str, rows: list[str]) -> None:
    (d / name).write_text(header + "\n" + "\n".join(rows) + "\n")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Every bad input of the table, in one folder (``{name}`` placeholders, dots as underscores)."""
    d = tmp_path_factory.mktemp("bad")
    rec = str(save_record(sim("healthy", 80.0, 2.0, 3), d / "rec.npz"))
    model = str(save_baseline(healthy_baseline(), d / "model.json"))
    n = 50_000
    zeros = {k: np.zeros(n) for k in ("va", "vb", "vc", "ia", "ib", "ic")}
    np.savez(d / "zeros.npz", t=np.arange(n) / RATE, **zeros)
    np.savez(d / "idle5.npz", t=np.arange(5 * n // 2) / RATE, **{k: np.zeros(5 * n // 2) for k in zeros})
    full = sim("healthy", 80.0, 2.0, 3)
    np.savez(d / "no_t.npz", **{k: v for k, v in zip(("va", "vb", "vc"), full.v_abc)},
             **{k: v for k, v in zip(("ia", "ib", "ic"), full.i_abc)})
    np.savez(d / "rate10k.npz", t=np.arange(full.n) / 10_000.0, **{k: v for k, v in zip(("va", "vb", "vc"), full.v_abc)},
             **{k: v for k, v in zip(("ia", "ib", "ic"), full.i_abc)})
    save_record(sim("healthy", 80.0, 0.5, 4), d / "short.npz")
    for j in range(4):
        save_record(sim("healthy", 80.0, 1.0, 40 + j), d / f"h80_{j}.npz")
    for j in range(2):
        save_record(sim("healthy", 60.0, 1.0, 50 + j), d / f"h60_{j}.npz")
    for j in range(5):
        save_record(sim("healthy", 80.0, 2.0, 60 + j), d / f"g80_{j}.npz")
    save_record(sim("gear_severe_wear", 80.0, 2.0, 70), d / "severe.npz")
    (d / "empty.csv").write_text("")
    (d / "header.csv").write_text("t,va,vb,vc,ia,ib,ic\n")
    (d / "missing.csv").write_text("t,va,vb,vc,ia,ib\n0,1,2,3,4,5\n")
    (d / "text.csv").write_text("t,va,vb,vc,ia,ib,ic\n0,1,2,3,4,5,x\n")
    rows = [f"{k / RATE:.9f},1,2,3,4,5,6" for k in range(10)]
    _csv(d, "unit.csv", "t,va,vb,vc,ia[furlong],ib,ic", rows)
    _csv(d, "dup.csv", "t,va,vb,vc,ia,ib,ic,ia", [r + ",7" for r in rows])
    _csv(d, "nan.csv", "t,va,vb,vc,ia,ib,ic", rows[:5] + [f"{5 / RATE:.9f},1,2,3,nan,5,6"] + rows[6:])
    _csv(d, "backwards.csv", "t,va,vb,vc,ia,ib,ic", rows[:5] + [f"{3 / RATE:.9f},1,2,3,4,5,6"] + rows[6:])
    _csv(d, "gap.csv", "t,va,vb,vc,ia,ib,ic", rows[:5] + [f"{7 / RATE:.9f},1,2,3,4,5,6"])
    _csv(d, "ragged.csv", "t,va,vb,vc,ia,ib,ic", rows[:3] + ["0.0002,1,2"])
    (d / "notzip.npz").write_text("not a zip")
    (d / "rec.txt").write_text("t,va\n")
    (d / "bad.json").write_text("{")
    (d / "other.json").write_text(json.dumps({"format": "something-else"}))
    (d / "future.json").write_text(json.dumps({"format": FORMAT, "version": 99}))
    (d / "bad.toml").write_text("[motor\n")
    (d / "unknown.toml").write_text(open(P).read() + "\n[extra]\nx = 1\n")
    (d / "dir.npz").mkdir()
    _profile(d, "motorkey.toml", "[motor]", "[motor]\npole_pair = 4")
    _profile(d, "belt.toml", 'kind = "gear"', 'kind = "belt"')
    _profile(d, "teeth.toml", "driving_teeth = 20", "driving_teeth = 0")
    _profile(d, "power.toml", "rated_power_w = 2200.0", "rated_power_w = -2200.0")
    _profile(d, "nopoles.toml", "pole_pairs = 4\n", "")
    _profile(d, "text_speed.toml", "rated_speed_rpm = 1500.0", 'rated_speed_rpm = "1500"')
    _profile(d, "source.toml", 'voltage_source = "measured"', 'voltage_source = "guessed"')
    _profile(d, "chain.toml", 'kind = "gear"', 'kind = "chain"')
    _profile(d, "rate10k.toml", "rate_hz = 25000.0", "rate_hz = 10000.0")
    _profile(d, "inf.toml", "rated_torque_nm = 14.0", "rated_torque_nm = inf")
    shipped = (PROFILE_PATH.parents[1] / "agent.toml").read_text().replace("profiles/", f"{PROFILE_PATH.parent}/")
    shipped = shipped.replace("# state_dir defaults", f'state_dir = "{d / "state"}"\n# state_dir defaults')
    (d / "agent.toml").write_text(shipped)
    for name, old, new in (("window.toml", "window_s = 2.0", "window_s = 1e12"),
                           ("hop.toml", "hop_s = 1.0", "hop_s = -1"),
                           ("stretches.toml", "learn_stretches = 40", "learn_stretches = 0"),
                           ("cfgkey.toml", "hop_s = 1.0", "hop_s = 1.0\nhop = 2"),
                           ("kind.toml", 'kind = "simulated"', 'kind = "telepathy"'),
                           ("noprofile.toml", 'profile = "', 'profile = "missing/'),
                           ("port.toml", "port = 5020", "port = 70000"),
                           ("tol.toml", "schedule_load_tol_pct = 5.0", "schedule_load_tol_pct = -5.0")):
        assert old in shipped, old
        (d / name).write_text(shipped.replace(old, new))
    drive = shipped[shipped.index("[[drives]]"):shipped.index("[pipeline]")]  # more drives than memory allows
    (d / "buffers.toml").write_text(shipped.replace("[pipeline]", "".join(
        drive.replace('name = "drive1"', f'name = "drive{j}"') for j in range(2, 200)) + "[pipeline]"))
    names = [p.name for p in d.iterdir()]
    return {"dir": str(d), "rec": rec, "model": model, **{k.replace(".", "_"): str(d / k) for k in names}}


#: (argv with {placeholders}, the cause the one line must name). Every case: exit 2.
CASES = [
    # simulate: options, conditions, effects, profiles, outputs
    (["simulate", "--profile", P, "--seconds", "-1", "--out", "{dir}/x.npz"], "--seconds: -1 is outside > 0"),
    (["simulate", "--profile", P, "--seconds", "1e12", "--out", "{dir}/x.npz"], "--seconds: 1e12 is outside"),
    (["simulate", "--profile", P, "--load", "nan", "--out", "{dir}/x.npz"], "--load: 'nan' is not finite"),
    (["simulate", "--profile", P, "--load", "80%", "--out", "{dir}/x.npz"], "--load: '80%' is not a number"),
    (["simulate", "--profile", P, "--count", "0", "--out", "{dir}/x.npz"], "--count: 0 is outside >= 1"),
    (["simulate", "--profile", P, "--seed", "-3", "--out", "{dir}/x.npz"], "--seed: -3 is outside >= 0"),
    (["simulate", "--profile", P, "--condition", "broken", "--out", "{dir}/x.npz"], "unknown condition 'broken'"),
    (["simulate", "--profile", P, "--condition", "chain_offset", "--out", "{dir}/x.npz"],
     "condition 'chain_offset' needs a chain transmission"),
    (["simulate", "--profile", P, "--effect", "warp_drive", "--out", "{dir}/x.npz"], "unknown effect 'warp_drive'"),
    (["simulate", "--profile", P, "--effect", "inverter_deadtime=abc", "--out", "{dir}/x.npz"],
     "--effect 'inverter_deadtime=abc': the value after '=' must be a number"),
    (["simulate", "--profile", P, "--effect", "voltage_delay=100", "--out", "{dir}/x.npz"],
     "effect 'voltage_delay': delay must be within -4..64 samples"),
    (["simulate", "--profile", P, "--out", "{dir}/x.txt"], "unknown record format '.txt'"),
    (["simulate", "--profile", "{bad_toml}", "--out", "{dir}/x.npz"], "bad.toml"),
    (["simulate", "--profile", "{unknown_toml}", "--out", "{dir}/x.npz"], "unknown key 'extra'"),
    (["simulate", "--profile", "{dir}/nope.toml", "--out", "{dir}/x.npz"], "nope.toml"),
    (["simulate", "--out", "{dir}/x.npz"], "the following arguments are required: --profile"),
    # frequencies: options and profiles with bad keys
    (["frequencies", "--profile", P, "--fe", "0"], "--fe: 0 is outside > 0"),
    (["frequencies", "--profile", P, "--fe", "-50"], "--fe: -50 is outside > 0"),
    (["frequencies", "--profile", P, "--k", "0"], "--k: 0 is outside >= 1"),
    (["frequencies", "--profile", P, "--k", "2.5"], "--k: '2.5' is not a whole number"),
    (["frequencies", "--profile", "{motorkey_toml}"], "unknown key 'motor.pole_pair'"),
    (["frequencies", "--profile", "{belt_toml}"], "key 'transmission.kind' must be \"gear\" or \"chain\""),
    (["frequencies", "--profile", "{teeth_toml}"], "key 'transmission.driving_teeth' must be positive, got 0"),
    (["frequencies", "--profile", "{power_toml}"], "key 'motor.rated_power_w' must be positive, got -2200"),
    (["frequencies", "--profile", "{nopoles_toml}"], "missing key 'motor.pole_pairs'"),
    (["frequencies", "--profile", "{text_speed_toml}"], "key 'motor.rated_speed_rpm' has the wrong type (str)"),
    (["frequencies", "--profile", "{source_toml}"], "key 'sampling.voltage_source' must be \"measured\" or"),
    (["frequencies", "--profile", "{chain_toml}"], "missing key 'transmission.driving_pitch_diameter_mm'"),
    (["frequencies", "--profile", "{inf_toml}"], "key 'motor.rated_torque_nm' must be finite"),
    # identify: options, records (files, columns, units, rates, too short, idle), training data
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"], "at least 4 healthy records"),
    (["identify", "--profile", P, "--confidence", "95", "--out", "{dir}/m.json", "{rec}"],
     "--confidence: 95 is not within (0, 1) (a fraction: 0.95 for 95 %)"),
    (["identify", "--profile", P, "--confidence", "1", "--out", "{dir}/m.json", "{rec}"], "--confidence: 1 is not within"),
    (["identify", "--profile", P, "--window", "0", "--out", "{dir}/m.json", "{rec}"], "--window: 0 is outside >= 0.1"),
    (["identify", "--profile", P, "--window", "-2", "--out", "{dir}/m.json", "{rec}"], "--window: -2 is outside"),
    (["identify", "--profile", P, "--form", "cubic", "--out", "{dir}/m.json", "{rec}"], "--form: invalid choice: 'cubic'"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{zeros_npz}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"], "not running"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{empty_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"], "empty.csv"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{header_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "header.csv: no samples: the file has no data rows"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{missing_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "missing required column 'ic'"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{text_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "non-numeric value 'x' in column 'ic'"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{unit_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "column 'ia[furlong]': unit 'furlong'"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{dup_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"], "duplicate column 'ia'"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{nan_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "NaN in column 'ia' at sample 5"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{backwards_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "time is not increasing at sample 5"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{gap_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"], "non-uniform time"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{ragged_csv}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"], "ragged.csv"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{no_t_npz}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "missing required column 't'"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{rate10k_npz}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "sample rate 10000 Hz disagrees with the profile's"),
    (["identify", "--profile", "{rate10k_toml}", "--out", "{dir}/m.json", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}", "{g80_3_npz}"],
     "sample rate 25000 Hz disagrees with the profile's"),
    (["identify", "--profile", P, "--window", "2", "--out", "{dir}/m.json", "{short_npz}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "short.npz: too short for the window: 12500 samples, need 50000"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{notzip_npz}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"], "not a zip file"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{dir_npz}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"], "dir.npz: is a folder"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{rec_txt}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}"],
     "rec.txt: unknown record format '.txt'"),
    (["identify", "--profile", P, "--window", "0.5", "--out", "{dir}", "{g80_0_npz}", "{g80_1_npz}", "{g80_2_npz}", "{g80_3_npz}"],
     "cannot write model: Is a directory"),
    (["identify", "--profile", P, "--window", "0.5", "--out", "{dir}/m.json", "{h80_0_npz}", "{h80_1_npz}",
      "{h80_2_npz}", "{h80_3_npz}", "{h60_0_npz}", "{h60_1_npz}"],
     "the training records spread over load"),  # mixed operating points, named in groups
    (["identify", "--profile", P, "--window", "1", "--out", "{dir}/m.json", "{g80_0_npz}", "{g80_1_npz}",
      "{g80_2_npz}", "{g80_3_npz}", "{g80_4_npz}", "{severe_npz}"],
     "severe.npz (the other records' baseline reads sidebands above 5 sigma"),  # faulty training data
    (["identify", "--profile", P, "--window", "0.5", "--out", "{dir}/m.json", "{h80_0_npz}", "{h80_1_npz}",
      "{h80_2_npz}", "{h80_0_npz}"], "h80_0.npz: given twice"),  # a record counted twice
    # diagnose: models and records
    (["diagnose", "--model", "{bad_json}", "{rec}"], "bad.json: corrupt model file"),
    (["diagnose", "--model", "{other_json}", "{rec}"], "other.json: not a "),
    (["diagnose", "--model", "{future_json}", "{rec}"], "unsupported model version 99"),
    (["diagnose", "--model", P, "{rec}"], "rig_gear.toml: corrupt model file"),
    (["diagnose", "--model", "{dir}/none.json", "{rec}"], "none.json: no such model file"),
    (["diagnose", "--model", "{model}", "{dir}/none.npz"], "none.npz: no such record file"),
    (["diagnose", "--model", "{model}", "{short_npz}"], "short.npz: too short for the window"),
    (["diagnose", "--model", "{model}", "{rate10k_npz}"], "sample rate 10000 Hz disagrees"),
    (["diagnose", "--model", "{model}", "--report", "{rec}", "{rec}"], "--report"),
    (["diagnose", "--model", "{model}", "--report", "/proc/nope", "{rec}"], "--report"),
    # the model workbench
    (["model", "compare", "--model", "{model}", "--report", "{rec}", "{rec}"], "--report"),
    (["model", "compare", "--model", "{model}", "--model", "{model}", "{rec}"], "given twice"),
    (["model", "explain", "--model", "{model}", "--report", "{bad_json}", "{rec}"], "--report"),
    (["model", "explain", "--model", "{model}", "--effect", "warp_drive", "{rec}"], "warp_drive"),
    (["model", "add-effect", "--model", "{model}", "--effect", "current_offset", "--out", "{model}", "{rec}"],
     "never overwritten"),
    (["model", "add-effect", "--model", "{model}", "--effect", "warp_drive", "--out", "{dir}/m2.json", "{rec}"],
     "warp_drive"),
    (["model", "add-effect", "--model", "{model}", "--effect", "current_offset", "--out", "{dir}/m2.json", "{rec}",
      "{rec}"], "given twice"),
    (["model", "compare", "--model", "{model}", "{zeros_npz}"], "not running"),
    (["model", "explain", "--model", "{model}", "{zeros_npz}"], "not running"),
    # the agent: configs, journal, commissioning
    (["events", "--state-dir", "{dir}", "--limit", "-1"], "--limit must be >= 0, got -1"),
    (["events", "--config", "{agent_toml}", "--drive", "drive9"], "--drive 'drive9': no such drive"),
    (["run", "--check-config", "{bad_toml}"], "bad.toml"),
    (["run", "--check-config", "{dir}/nope.toml"], "nope.toml"),
    (["run", "--check-config", "{window_toml}"], "pipeline.window_s"),
    (["run", "--check-config", "{hop_toml}"], "pipeline.hop_s"),
    (["run", "--check-config", "{stretches_toml}"], "pipeline.learn_stretches"),
    (["run", "--check-config", "{cfgkey_toml}"], "pipeline.hop"),
    (["run", "--check-config", "{kind_toml}"], "telepathy"),
    (["run", "--check-config", "{noprofile_toml}"], "drives[0].profile"),
    (["run", "--check-config", "{port_toml}"], "modbus_server.port"),
    (["run", "--check-config", "{tol_toml}"], "pipeline.schedule_load_tol_pct"),
    (["run", "--config", "{window_toml}"], "pipeline.window_s"),
    (["run", "--check-config", "{buffers_toml}"], "199 drive(s) would take about"),
    (["status", "--config", "{agent_toml}"], "no journal at"),
    (["learn", "--config", "{dir}/nope.toml", "--drive", "d1"], "nope.toml"),
    (["learn", "--config", "{agent_toml}", "--drive", "drive9", "{rec}"], "--drive 'drive9': no such drive"),
    (["learn", "--config", "{agent_toml}", "--drive", "drive1", "--max-seconds", "-5"], "--max-seconds: -5 is outside"),
    (["learn", "--config", "{agent_toml}", "--drive", "drive1", "{idle5_npz}"],
     "nothing to learn for drive drive1: the drive was not running"),
    (["learn", "--config", "{agent_toml}", "--drive", "drive1", "{zeros_npz}"],
     "shorter than one span (4 s), so nothing learned from"),
    (["learn", "--config", "{agent_toml}", "--drive", "drive1", "{rec}", "{rec}"], "given twice"),
    (["learn", "--config", "{agent_toml}", "--drive", "drive1", "{h80_0_npz}", "{h60_0_npz}"],
     "the training records spread over load"),
    (["learn", "--config", "{agent_toml}", "--drive", "drive1", "{rec}"], "about 22 more minutes"),
    (["learn", "--config", "{agent_toml}", "--drive", "drive1", "{rate10k_npz}"], "sample rate 10000 Hz disagrees"),
    (["demo", "--seconds", "0"], "--seconds: 0 is outside > 0"),
    # the plant: routers, fleet, historian, history
    (["router", "--listen", "nonsense"], "zenoh config key 'listen/endpoints' = ['nonsense']"),
    (["fleet", "status"], "the following arguments are required: --connect"),
    (["fleet", "status", "--connect", "nonsense"], "zenoh config key 'connect/endpoints' = ['nonsense']"),
    (["fleet", "command", "--connect", "tcp/127.0.0.1:1"], "the following arguments are required: action, --drive"),
    (["historian", "--config", "{dir}/nope.toml"], "nope.toml: no such historian config file"),
    (["history", "--drive", "d1", "--since", "24h"], "one of the arguments --config --dsn is required"),
    (["history", "--drive", "d1", "--since", "yesterday", "--dsn", "postgresql://x"],
     "--since 'yesterday': give an age like 30s"),
    (["nosuchcommand"], "invalid choice: 'nosuchcommand'"),
]


def _snapshot(folder: str) -> dict[str, str]:
    """Every file under ``folder`` and a digest of its bytes."""
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(Path(folder).rglob("*")) if p.is_file()}


@pytest.mark.parametrize("argv, cause", CASES, ids=[" ".join(c[0][:4]) + f" [{c[1][:30]}]" for c in CASES])
def test_a_refusal_names_its_cause_and_changes_nothing(files, capsys, argv, cause):
    argv = [a.format(**files) for a in argv] + ["--json"]
    before = _snapshot(files["dir"])
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse's own refusals
        rc = exc.code
    out, err = capsys.readouterr()
    assert rc == 2, (rc, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert cause in err, err
    doc = json.loads(out)  # exactly one JSON object: the error, as on stderr
    assert doc["exit"] == 2 and doc["error"] in err, (doc, err)
    assert _snapshot(files["dir"]) == before  # no model, library, journal or output changed


def test_the_table_covers_every_command_with_enough_cases():
    from agent.cli import build_parser

    commands = {c[0][0] if c[0][0] != "model" else " ".join(c[0][:2]) for c in CASES}
    parser_commands = set(build_parser()._subparsers._group_actions[0].choices) - {"model"}
    assert len(CASES) >= 60
    assert parser_commands - {c.split()[0] for c in commands} == set(), parser_commands - commands
