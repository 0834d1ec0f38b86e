"""Everything a newcomer can type gives a result or one line: exit 2, one stderr line naming the
flag, file or value, never a traceback (a table of bad inputs per subcommand, and hypothesis for
the numeric flags)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.cli import build_parser, main
from agent.modelfile import save_baseline
from agent.records import save_record
from runtime_support import PROFILE_PATH, healthy_baseline, sim

pytestmark = pytest.mark.timeout(300)
P = str(PROFILE_PATH)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    rec = str(save_record(sim("healthy", 80.0, 2.0, 3), d / "rec.npz"))
    model = str(save_baseline(healthy_baseline(), d / "model.json"))
    n = 50_000
    zeros = {k: np.zeros(n) for k in ("va", "vb", "vc", "ia", "ib", "ic")}
    np.savez(d / "zeros.npz", t=np.arange(n) / 25_000.0, **zeros)
    (d / "empty.csv").write_text("")
    (d / "header.csv").write_text("t,va,vb,vc,ia,ib,ic\n")
    (d / "missing.csv").write_text("t,va,vb,vc,ia,ib\n0,1,2,3,4,5\n")
    (d / "text.csv").write_text("t,va,vb,vc,ia,ib,ic\n0,1,2,3,4,5,x\n")
    (d / "notzip.npz").write_text("not a zip")
    (d / "bad.json").write_text("{")
    (d / "bad.toml").write_text("[motor\n")
    (d / "unknown.toml").write_text(open(P).read() + "\n[extra]\nx = 1\n")
    (d / "dir.npz").mkdir()
    shipped = (PROFILE_PATH.parents[1] / "agent.toml").read_text().replace("profiles/", f"{PROFILE_PATH.parent}/")
    for name, old, new in (("window.toml", "window_s = 2.0", "window_s = 1e12"),
                           ("hop.toml", "hop_s = 1.0", "hop_s = -1"),
                           ("stretches.toml", "learn_stretches = 40", "learn_stretches = 0")):
        (d / name).write_text(shipped.replace(old, new))
    drive = shipped[shipped.index("[[drives]]"):shipped.index("[pipeline]")]  # more drives than memory allows
    (d / "buffers.toml").write_text(shipped.replace("[pipeline]", "".join(
        drive.replace('name = "drive1"', f'name = "drive{j}"') for j in range(2, 200)) + "[pipeline]"))
    return {"dir": str(d), "rec": rec, "model": model, **{k.replace(".", "_"): str(d / k) for k in (
        "zeros.npz", "empty.csv", "header.csv", "missing.csv", "text.csv", "notzip.npz", "bad.json",
        "bad.toml", "unknown.toml", "dir.npz", "window.toml", "hop.toml", "stretches.toml", "buffers.toml")}}


#: (argv with {placeholders}, a word the one line must contain)
CASES = [
    (["simulate", "--profile", P, "--seconds", "-1", "--out", "{dir}/x.npz"], "--seconds"),
    (["simulate", "--profile", P, "--seconds", "1e12", "--out", "{dir}/x.npz"], "--seconds"),
    (["simulate", "--profile", P, "--load", "nan", "--out", "{dir}/x.npz"], "--load"),
    (["simulate", "--profile", P, "--load", "80%", "--out", "{dir}/x.npz"], "--load"),
    (["simulate", "--profile", P, "--count", "0", "--out", "{dir}/x.npz"], "--count"),
    (["simulate", "--profile", P, "--seed", "-3", "--out", "{dir}/x.npz"], "--seed"),
    (["simulate", "--profile", P, "--condition", "broken", "--out", "{dir}/x.npz"], "broken"),
    (["simulate", "--profile", P, "--out", "{dir}/x.txt"], ".txt"),
    (["simulate", "--profile", "{bad_toml}", "--out", "{dir}/x.npz"], "bad.toml"),
    (["simulate", "--profile", "{unknown_toml}", "--out", "{dir}/x.npz"], "extra"),
    (["simulate", "--profile", "{dir}/nope.toml", "--out", "{dir}/x.npz"], "nope.toml"),
    (["simulate", "--out", "{dir}/x.npz"], "--profile"),
    (["frequencies", "--profile", P, "--fe", "0"], "--fe"),
    (["frequencies", "--profile", P, "--fe", "-50"], "--fe"),
    (["frequencies", "--profile", P, "--k", "0"], "--k"),
    (["frequencies", "--profile", P, "--k", "2.5"], "--k"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{rec}", "{rec}", "{rec}"], "at least 4"),
    (["identify", "--profile", P, "--confidence", "95", "--out", "{dir}/m.json", "{rec}"], "--confidence"),
    (["identify", "--profile", P, "--confidence", "1", "--out", "{dir}/m.json", "{rec}"], "--confidence"),
    (["identify", "--profile", P, "--window", "0", "--out", "{dir}/m.json", "{rec}"], "--window"),
    (["identify", "--profile", P, "--window", "-2", "--out", "{dir}/m.json", "{rec}"], "--window"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{zeros_npz}", "{rec}", "{rec}", "{rec}"], "not running"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{empty_csv}", "{rec}", "{rec}", "{rec}"], "empty.csv"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{header_csv}", "{rec}", "{rec}", "{rec}"], "no data rows"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{missing_csv}", "{rec}", "{rec}", "{rec}"], "'ic'"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{text_csv}", "{rec}", "{rec}", "{rec}"], "'ic'"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{notzip_npz}", "{rec}", "{rec}", "{rec}"], "not a zip file"),
    (["identify", "--profile", P, "--out", "{dir}/m.json", "{dir_npz}", "{rec}", "{rec}", "{rec}"], "dir.npz: is a folder"),
    (["identify", "--profile", P, "--window", "0.5", "--out", "{dir}", "{rec}", "{rec}", "{rec}", "{rec}"],
     "cannot write model: Is a directory"),
    (["diagnose", "--model", "{bad_json}", "{rec}"], "bad.json"),
    (["diagnose", "--model", "{dir}/none.json", "{rec}"], "none.json"),
    (["diagnose", "--model", "{model}", "{dir}/none.npz"], "none.npz"),
    (["diagnose", "--model", "{model}", "--report", "{rec}", "{rec}"], "--report"),
    (["diagnose", "--model", "{model}", "--report", "/proc/nope", "{rec}"], "--report"),
    (["model", "compare", "--model", "{model}", "--report", "{rec}", "{rec}"], "--report"),
    (["model", "explain", "--model", "{model}", "--report", "{bad_json}", "{rec}"], "--report"),
    (["model", "add-effect", "--model", "{model}", "--effect", "current_offset", "--out", "{model}", "{rec}"],
     "never overwritten"),
    (["model", "compare", "--model", "{model}", "{zeros_npz}"], "not running"),
    (["model", "explain", "--model", "{model}", "{zeros_npz}"], "not running"),
    (["events", "--state-dir", "{dir}", "--limit", "-1"], "--limit"),
    (["run", "--check-config", "{bad_toml}"], "bad.toml"),
    (["run", "--check-config", "{dir}/nope.toml"], "nope.toml"),
    (["run", "--check-config", "{window_toml}"], "pipeline.window_s"),
    (["run", "--check-config", "{hop_toml}"], "pipeline.hop_s"),
    (["run", "--check-config", "{stretches_toml}"], "pipeline.learn_stretches"),
    (["run", "--config", "{window_toml}"], "pipeline.window_s"),
    (["run", "--check-config", "{buffers_toml}"], "MB"),
    (["learn", "--config", "{dir}/nope.toml", "--drive", "d1"], "nope.toml"),
    (["demo", "--seconds", "0"], "--seconds"),
    (["nosuchcommand"], "nosuchcommand"),
]


@pytest.mark.parametrize("argv, word", CASES, ids=[" ".join(c[0][:4]) for c in CASES])
def test_bad_input_is_one_line_and_exit_2(files, capsys, argv, word):
    argv = [a.format(**files) for a in argv]
    with pytest.raises(SystemExit) if _usage_error(argv) else _no_exit():
        rc = main(argv)
    out, err = capsys.readouterr()
    rc = 2 if _usage_error(argv) else rc
    assert rc == 2, (out, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert word in err, err


@pytest.mark.parametrize("what", ["modbus", "zenoh"])
def test_a_port_in_use_is_one_line_naming_the_key(files, capsys, tmp_path, what):
    import socket

    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    try:
        cfg = tmp_path / "agent.toml"
        cfg.write_text(f"""schema_version = 1
state_dir = "{tmp_path / 'state'}"
[[drives]]
name = "d1"
profile = "{P}"
[drives.source]
kind = "replay"
files = ["{files['rec']}"]
[modbus_server]
enabled = {str(what == "modbus").lower()}
port = {port}
[zenoh]
enabled = {str(what == "zenoh").lower()}
listen = ["tcp/127.0.0.1:{port}"]
""")
        rc = main(["run", "--config", str(cfg)])
        err = capsys.readouterr().err
        assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert ("modbus_server.port" if what == "modbus" else "zenoh.listen") in err and str(port) in err
    finally:
        busy.close()


def test_diagnose_of_a_stopped_drive_is_no_diagnosis_not_an_alarm(files, capsys):
    assert main(["diagnose", "--json", "--model", files["model"], files["zeros_npz"]]) == 0
    import json

    r = json.loads(capsys.readouterr().out)["results"][0]
    assert r["state"] == "normal" and r["quality"] == "no_model" and r["reason"].startswith("not running")


def test_output_folders_are_created(files, capsys):
    out = f"{files['dir']}/new/folder/h.npz"
    assert main(["simulate", "--profile", P, "--seconds", "0.2", "--out", out]) == 0
    assert "new/folder/h.npz" in capsys.readouterr().out


def test_a_record_as_long_as_the_window_is_accepted(files, capsys):
    """2 s records with the 2 s window (a record of exactly one window)."""
    args = ["identify", "--profile", P, "--out", f"{files['dir']}/m2.json"]
    recs = [str(save_record(sim("healthy", 80.0, 2.0, 50 + j), f"{files['dir']}/w{j}.npz")) for j in range(4)]
    assert main(args + recs) == 0, capsys.readouterr().err
    assert main(["diagnose", "--model", f"{files['dir']}/m2.json", recs[0]]) == 0


def test_closing_the_pipe_early_exits_quietly(tmp_path):
    import subprocess
    import sys

    proc = subprocess.run(f"{sys.executable} -m agent.cli frequencies --profile {P} --k 50 | head -1",
                          shell=True, capture_output=True, text=True, cwd=str(PROFILE_PATH.parents[2]))
    assert proc.stdout.startswith("fe = ") and "Traceback" not in proc.stderr and "Error" not in proc.stderr


NUMERIC = [("simulate", "--load"), ("simulate", "--seconds"), ("simulate", "--count"), ("simulate", "--seed"),
           ("simulate", "--severity"), ("frequencies", "--fe"), ("frequencies", "--k"), ("identify", "--window"),
           ("identify", "--confidence"), ("identify", "--prefilter"), ("demo", "--seconds")]
REQUIRED = {"simulate": ["--profile", P, "--out", "x.npz"], "frequencies": ["--profile", P],
            "identify": ["--profile", P, "--out", "m.json", "r.npz"], "demo": []}


@settings(max_examples=60, deadline=None)
@given(flag=st.sampled_from(NUMERIC),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers().map(str),
                       st.sampled_from(["", "abc", "1e400", "-0", "95%", "0x10", "1,5"])))
def test_numeric_flags_parse_or_fail_with_one_line(flag, value):
    """Any text for a numeric flag: the parser accepts a finite value in range, or exits 2 with one
    line naming the flag (the handlers then get only physical values)."""
    import contextlib
    import io

    command, name = flag
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            args = build_parser().parse_args([command, *REQUIRED[command], f"{name}={value}"])
        except SystemExit as exc:
            assert exc.code == 2
            text = err.getvalue()
            assert len(text.strip().splitlines()) == 1 and name in text and "Traceback" not in text
            return
    parsed = getattr(args, name.lstrip("-").replace("-", "_"))
    assert np.isfinite(parsed)


def _usage_error(argv) -> bool:
    """Does argparse itself reject argv (it exits with SystemExit(2) before any handler)?"""
    import contextlib
    import io

    with contextlib.redirect_stderr(io.StringIO()):
        try:
            build_parser().parse_args(argv)
        except SystemExit:
            return True
    return False


class _no_exit:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
