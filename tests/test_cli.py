"""The pmsm-agent command line: JSON contract (CONTRACT section 2) and bad input (exit 2, one line)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.cli import main

ROOT = Path(__file__).resolve().parent.parent
GEAR = str(ROOT / "config" / "profiles" / "rig_gear.toml")
CHAIN = str(ROOT / "config" / "profiles" / "rig_chain.toml")


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def run_json(capsys, *argv):
    code, out, err = run(capsys, *argv, "--json")
    assert code == 0, err
    return json.loads(out)


@pytest.fixture(scope="module")
def healthy(tmp_path_factory):
    d = tmp_path_factory.mktemp("healthy")
    assert main(["simulate", "--profile", GEAR, "--seconds", "1.2", "--seed", "1", "--count", "6",
                 "--out", str(d / "h.npz")]) == 0
    return sorted(str(p) for p in d.glob("h_*.npz"))


@pytest.fixture(scope="module")
def model(healthy, tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "m.json"
    assert main(["identify", "--profile", GEAR, "--window", "0.5", "--out", str(path), *healthy]) == 0
    return str(path)


@pytest.mark.parametrize("ext", ["csv", "npz", "tdms"])
def test_simulate_writes_each_format(capsys, tmp_path, ext):
    doc = run_json(capsys, "simulate", "--profile", GEAR, "--condition", "gear_slight_wear", "--load", "60",
                   "--seconds", "0.2", "--seed", "3", "--out", str(tmp_path / f"r.{ext}"))
    assert doc["out"] == str(tmp_path / f"r.{ext}") and doc["samples"] == 5000
    assert Path(doc["out"]).stat().st_size > 0


def test_frequencies_json(capsys):
    gear = run_json(capsys, "frequencies", "--profile", GEAR)["families"]
    assert {"gear_driving", "gear_driven"} <= set(gear)
    assert [round(p["freq_hz"], 2) for p in gear["gear_driven"]] == [62.5, 75.0, 87.5, 112.5, 125.0, 137.5]
    chain = run_json(capsys, "frequencies", "--profile", CHAIN, "--fe", "100", "--k", "2")["families"]
    assert [p["k"] for p in chain["chain"]] == [2, 1, 1, 2]
    freqs = [p["freq_hz"] for p in chain["chain"]]
    assert freqs == sorted(freqs)


def test_identify_and_diagnose_json(capsys, healthy, model, tmp_path):
    doc = json.loads(Path(model).read_text())
    assert doc["format"] == "pmsm-agent-model" and doc["version"] == 1
    ident = run_json(capsys, "identify", "--profile", GEAR, "--window", "0.5", "--out", str(tmp_path / "m2.json"),
                     *healthy)
    assert ident["records"] == len(healthy) and ident["model"] == str(tmp_path / "m2.json")
    # a baseline is re-identified in place (CONTRACT section 2's form); a model with workbench versions is
    # kept, said so in one line, unless --replace
    m2 = str(tmp_path / "m2.json")
    assert run_json(capsys, "identify", "--profile", GEAR, "--window", "0.5", "--out", m2, *healthy)["model"] == m2
    doc = json.loads(Path(m2).read_text())
    doc["history"] = [{"version": 1, "added": ["current_offset"]}]
    Path(m2).write_text(json.dumps(doc))
    before = Path(m2).read_bytes()
    code, out, err = run(capsys, "identify", "--profile", GEAR, "--window", "0.5", "--out", m2, *healthy)
    assert code == 2 and "m2.json: a model with workbench versions" in err and "--replace" in err
    assert len(err.strip().splitlines()) == 1 and Path(m2).read_bytes() == before
    assert run_json(capsys, "identify", "--profile", GEAR, "--window", "0.5", "--replace", "--out", m2,
                    *healthy)["model"] == m2
    assert json.loads(Path(m2).read_text())["history"] == []
    assert ident["operating_point"]["fe_hz"] == pytest.approx(100.0, rel=1e-3)
    assert 70 < ident["operating_point"]["load_pct"] < 95
    assert set(ident["params"]) >= {"d", "q", "physical"}
    # few records are few independent stretches: the one-window threshold is wide, and says so
    lo, hi = ident["alarm"]["gross_threshold_z"]
    assert ident["alarm"]["stretches"] == len(healthy) and 8.0 < lo <= hi
    faulty = tmp_path / "f.csv"
    main(["simulate", "--profile", GEAR, "--condition", "gear_severe_wear", "--seconds", "1.2", "--seed", "77",
          "--out", str(faulty)])
    capsys.readouterr()
    res = run_json(capsys, "diagnose", "--model", model, healthy[0], str(faulty))["results"]
    assert [r["record"] for r in res] == [healthy[0], str(faulty)]
    for r in res:
        assert r["state"] in ("normal", "caution", "warning")
        assert {"spectrum_state", "cluster_state", "peaks"} <= set(r)
        for p in r["peaks"]:
            assert {"freq_hz", "family", "k", "level", "magnitude", "th2", "th3"} <= set(p)
            assert p["level"] in ("caution", "warning")
            assert p["magnitude"] > (p["th3"] if p["level"] == "warning" else p["th2"])
    assert res[1]["state"] != "normal"


def _bad_csv(tmp_path, healthy, mutate):
    from agent.records import load_record, save_record

    rec = load_record(healthy[0])
    mutate(rec)
    path = tmp_path / "bad.csv"
    save_record(rec, path)
    return path


@pytest.mark.parametrize("mutate, needle", [
    (lambda r: r.i_abc.__setitem__((1, 500), np.nan), "ib"),
    (lambda r: setattr(r, "t", r.t * 1.01), "sample rate"),
    (lambda r: r.t.__setitem__(slice(1000, None), r.t[1000:] + 1e-4), "uniform"),
])
def test_bad_records_exit_2_with_one_line(capsys, tmp_path, healthy, model, mutate, needle):
    path = _bad_csv(tmp_path, healthy, mutate)
    code, out, err = run(capsys, "diagnose", "--model", model, str(path))
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1
    assert str(path) in err and needle in err


def test_missing_column_and_short_record(capsys, tmp_path, healthy, model):
    path = tmp_path / "cols.csv"
    path.write_text("t,va,vb,vc,ia,ib\n0,1,2,3,4,5\n")
    code, _, err = run(capsys, "diagnose", "--model", model, str(path))
    assert code == 2 and "ic" in err and str(path) in err
    short = tmp_path / "short.npz"
    main(["simulate", "--profile", GEAR, "--seconds", "0.1", "--out", str(short)])
    capsys.readouterr()
    code, _, err = run(capsys, "diagnose", "--model", model, str(short))
    assert code == 2 and "too short" in err


def test_bad_model_files(capsys, tmp_path, healthy, model):
    corrupt = tmp_path / "corrupt.json"
    corrupt.write_text("{not json")
    code, _, err = run(capsys, "diagnose", "--model", str(corrupt), healthy[0])
    assert code == 2 and str(corrupt) in err
    doc = json.loads(Path(model).read_text())
    doc["version"] = 99
    future = tmp_path / "future.json"
    future.write_text(json.dumps(doc))
    code, _, err = run(capsys, "diagnose", "--model", str(future), healthy[0])
    assert code == 2 and "version" in err and str(future) in err
    del doc["thresholds"]
    doc["version"] = 1
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps(doc))
    code, _, err = run(capsys, "diagnose", "--model", str(partial), healthy[0])
    assert code == 2 and "thresholds" in err


def test_bad_options(capsys, tmp_path):
    code, _, err = run(capsys, "simulate", "--profile", GEAR, "--condition", "chain_offset", "--out",
                       str(tmp_path / "x.csv"))
    assert code == 2 and "chain_offset" in err
    code, _, err = run(capsys, "simulate", "--profile", GEAR, "--effect", "warp_drive", "--out", str(tmp_path / "x.csv"))
    assert code == 2 and "inverter_deadtime" in err
    with pytest.raises(SystemExit) as exc:
        main(["identify", "--profile", GEAR])
    assert exc.value.code == 2


def test_console_script_no_traceback(tmp_path):
    exe = Path(sys.executable).parent / "pmsm-agent"
    bad = tmp_path / "p.toml"
    bad.write_text((ROOT / "config/profiles/rig_gear.toml").read_text().replace("[motor]", "[motor]\nfoo = 1"))
    proc = subprocess.run([str(exe), "frequencies", "--profile", str(bad), "--json"], capture_output=True, text=True)
    assert proc.returncode == 2 and json.loads(proc.stdout) == {"error": proc.stderr.split("error: ", 1)[1].strip(),
                                                                 "exit": 2}
    assert "Traceback" not in proc.stderr and "motor.foo" in proc.stderr
    proc = subprocess.run([str(exe), "frequencies", "--profile", GEAR, "--json"], capture_output=True, text=True)
    assert proc.returncode == 0 and "families" in json.loads(proc.stdout)


def test_demo_ends_on_sigterm_and_leaves_no_temp_dir(tmp_path, demo_ports):
    """SIGTERM ends the demo at once (exit 0) and removes its state directory."""
    import os
    import signal
    import subprocess
    import sys
    import time

    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "demo", "--seconds", "60"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        first = proc.stdout.readline()  # printed once the service is set up, inside the temp dir
        assert first.startswith("demo: simulated gear drive"), first
        t_end = time.monotonic() + 30
        while not list(tmp_path.glob("pmsm-demo-*")) and time.monotonic() < t_end:
            time.sleep(0.05)
        assert list(tmp_path.glob("pmsm-demo-*"))
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, out
    assert "demo: done after" in out
    assert not list(tmp_path.glob("pmsm-demo-*"))


def _arguments(parser, path: str):
    """(command path, argument) for every option and positional of ``parser`` and its subcommands."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _arguments(sub, f"{path} {name}")
        else:
            yield path, action


def test_every_option_and_positional_has_help():
    """Walks the whole argparse tree of ``pmsm-agent``: an option without help is a flag a user
    must guess at."""
    from agent.cli import build_parser

    seen = list(_arguments(build_parser(), "pmsm-agent"))
    missing = [f"{path}: {'/'.join(a.option_strings) or a.dest}" for path, a in seen
               if not (a.help or "").strip()]
    assert len(seen) > 60 and not missing, missing
