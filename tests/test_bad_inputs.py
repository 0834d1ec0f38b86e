"""Everything a newcomer can type gives a result or one line: exit 2, one stderr line naming the
flag, file or value, never a traceback: ports in use, stopped drives, hypothesis for the numeric
flags. The table of bad inputs per subcommand is tests/test_quiet_wrong.py."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.cli import build_parser, main
from agent.records import save_record
from runtime_support import PROFILE_PATH, sim
from test_quiet_wrong import files  # noqa: F401 - the bad inputs' folder (a fixture)

pytestmark = pytest.mark.timeout(300)
P = str(PROFILE_PATH)


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
