"""``pmsm-agent learn`` on the command line: a baseline from recorded files with the agent's own
learning code, refusals with exit 2 and one line, and a library left unchanged by a refusal."""

from __future__ import annotations

import json

import pytest

from agent.cli import main
from agent.records import save_record
from runtime_support import PROFILE_PATH, sim

pytestmark = pytest.mark.timeout(300)


def config(tmp_path, learn_stretches=8):
    path = tmp_path / "agent.toml"
    path.write_text(f"""
schema_version = 1
agent_id = "learn"
state_dir = "{tmp_path / 'state'}"

[[drives]]
name = "drive1"
profile = "{PROFILE_PATH}"

[drives.source]
kind = "simulated"

[pipeline]
learn_windows = 6
learn_stretches = {learn_stretches}
learn_min_s = 0.0
stretch_s = 4.0
""")
    return path


def records(tmp_path, n, load=80.0, seed=800, condition="healthy"):
    return [str(save_record(sim(condition, load, 8.0, seed + j), tmp_path / f"{condition}_{load:g}_{seed + j}.npz"))
            for j in range(n)]


def run(argv, capsys):
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def test_learn_from_files_writes_the_drives_baseline(tmp_path, capsys):
    cfg = config(tmp_path)
    rc, out, err = run(["learn", "--json", "--config", str(cfg), "--drive", "drive1", *records(tmp_path, 14)], capsys)
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["drive"] == "drive1" and doc["name"].startswith("drive1_100hz_")
    lib = tmp_path / "state" / "library"
    assert [p.name for p in lib.glob("*.json")] == [f"{doc['name']}.json"]
    assert doc["stretches"] == 8 and abs(doc["operating_point"]["fe_hz"] - 100.0) < 0.5
    # the same point again: refused, the first baseline stays
    before = (lib / f"{doc['name']}.json").read_bytes()
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", *records(tmp_path, 14, seed=900)], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "already covers" in err and "Traceback" not in err
    assert (lib / f"{doc['name']}.json").read_bytes() == before


@pytest.mark.parametrize("case", ["too little", "unknown drive", "mixed loads"])
def test_learn_refuses_with_one_line_and_leaves_the_library_alone(tmp_path, capsys, case):
    cfg = config(tmp_path)
    if case == "too little":
        argv = ["--drive", "drive1", *records(tmp_path, 4)]
        expect = "not enough healthy data"
    elif case == "unknown drive":
        argv = ["--drive", "drive9", *records(tmp_path, 1)]
        expect = "--drive 'drive9'"
    else:
        argv = ["--drive", "drive1", *records(tmp_path, 5, 80.0), *records(tmp_path, 10, 70.0, seed=850)]
        expect = "healthy_80_800.npz"  # each file named with its operating point's group
    rc, out, err = run(["learn", "--config", str(cfg), *argv], capsys)
    assert rc == 2 and out == "" and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and expect in err, err
    assert not list((tmp_path / "state" / "library").glob("*.json"))


def test_learn_from_the_live_source(tmp_path, capsys):
    """Without files: the drive's configured source (here the simulated drive at 1000x real time)."""
    cfg = config(tmp_path)
    text = cfg.read_text().replace('kind = "simulated"', 'kind = "simulated"\nspeedup = 1000.0\nload_pct = 80.0\n'
                                   'schedule = [{ condition = "healthy", seconds = 600.0 }]')
    cfg.write_text(text)
    rc, out, err = run(["learn", "--json", "--config", str(cfg), "--drive", "drive1", "--name", "live80",
                        "--max-seconds", "120"], capsys)
    assert rc == 0, err
    assert json.loads(out)["name"] == "live80"
    assert (tmp_path / "state" / "library" / "live80.json").is_file()


def test_learn_from_a_live_source_that_is_not_there(tmp_path, capsys):
    cfg = config(tmp_path)
    cfg.write_text(cfg.read_text().replace('kind = "simulated"', f'kind = "serial"\nport = "{tmp_path}/no-tty"'))
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", "--max-seconds", "5"], capsys)
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert "cannot open its serial source" in err, err
