"""``pmsm-agent learn`` on the command line: a baseline from recorded files with the agent's own
learning code, refusals with exit 2 and one line, and a library left unchanged by a refusal."""

from __future__ import annotations

import json

import pytest

from agent.cli import main
from agent.records import save_record
from runtime_support import PROFILE_PATH, sim

pytestmark = pytest.mark.timeout(300)


def config(tmp_path, learn_stretches=8, **pipeline):
    """An agent config with one simulated drive whose commissioning is short; ``pipeline`` keys override."""
    keys = {"learn_windows": 6, "learn_stretches": learn_stretches, "learn_min_s": 0.0, "stretch_s": 4.0, **pipeline}
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
""" + "".join(f"{k} = {v}\n" for k, v in keys.items()))
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


def test_a_live_relearn_of_a_drive_in_warning_is_refused_unless_accepted(tmp_path, capsys):
    """``learn --replace`` from the live source first reads the drive with the baseline it replaces: a
    drive whose gear is worn reads warning and is refused (the library unchanged); with
    --accept-fault-evidence it learns and the journal says so. The healthy drive is the control."""
    cfg = config(tmp_path)
    base = cfg.read_text()

    def live(condition: str) -> None:
        cfg.write_text(base.replace('kind = "simulated"', 'kind = "simulated"\nspeedup = 1000.0\nload_pct = 80.0\n'
                                    f'schedule = [{{ condition = "{condition}", seconds = 600.0 }}]'))

    live("healthy")
    rc, out, err = run(["learn", "--json", "--config", str(cfg), "--drive", "drive1", "--name", "live80",
                        "--max-seconds", "120"], capsys)
    assert rc == 0, err
    learned = (tmp_path / "state" / "library" / "live80.json").read_bytes()
    live("gear_severe_wear")
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", "--replace", "--max-seconds", "120"], capsys)
    assert rc == 2 and "reads as faulty against live80" in err and "gear_driven" in err, err
    assert "--accept-fault-evidence" in err and (tmp_path / "state" / "library" / "live80.json").read_bytes() == learned
    rc, out, err = run(["learn", "--json", "--config", str(cfg), "--drive", "drive1", "--replace",
                        "--accept-fault-evidence", "--max-seconds", "120"], capsys)
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["replaced"] == "live80" and "reads as faulty against live80" in doc["accepted_fault_evidence"][0]
    live("healthy")  # the control: a healthy drive relearns without the flag
    rc, out, err = run(["learn", "--json", "--config", str(cfg), "--drive", "drive1", "--replace",
                        "--max-seconds", "120"], capsys)
    assert rc == 0 and json.loads(out)["accepted_fault_evidence"] == [], err


def test_a_live_relearn_that_never_reads_the_drive_says_so(tmp_path, capsys):
    """``learn --replace`` from a live source that ends before its first span (3 s against a 4 s
    span): the relearn never reads the drive with the baseline it replaces, and says that (not
    "not enough healthy data"); the library is unchanged."""
    rec = save_record(sim("healthy", 80.0, 3.0, 900), tmp_path / "h.npz")
    cfg = config(tmp_path)
    cfg.write_text(cfg.read_text().replace('kind = "simulated"', f'kind = "replay"\nfiles = ["{rec}"]\nspeedup = 0.0'))
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", "--replace", "--max-seconds", "60"], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "no usable span to read the drive with the baseline it replaces" in err, err
    assert "not enough healthy data" not in err
    assert not list((tmp_path / "state" / "library").glob("*.json"))


def test_learn_from_a_live_source_that_is_not_there(tmp_path, capsys):
    cfg = config(tmp_path)
    cfg.write_text(cfg.read_text().replace('kind = "simulated"', f'kind = "serial"\nport = "{tmp_path}/no-tty"'))
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", "--max-seconds", "5"], capsys)
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert "cannot open its serial source" in err, err


def _stream_file(tmp_path, seconds: float, load: float = 80.0, seed: int = 700) -> str:
    """One uninterrupted healthy record of ``seconds`` (one stream: no per-file losses)."""
    from agent.simulator import simulate

    path = tmp_path / f"stream_{seconds:g}_{load:g}_{seed}.npz"
    return str(save_record(simulate(PROFILE_PATH, "healthy", load, seconds, seed=seed), path))


def _more_seconds(err: str) -> int:
    import re

    m = re.search(r"about (\d+) more (seconds|minutes) of steady operation at (\d+) % load", err)
    assert m and abs(int(m.group(3)) - 80) <= 5, err  # the load learned at (simulated at 80 % of rated torque)
    return int(m.group(1)) * (60 if m.group(2) == "minutes" else 1)


def test_a_refusal_for_too_little_data_says_how_much_more_and_it_is_enough(tmp_path, capsys):
    """The rule (6 spans of 4 s, then 8 stretches of 4 s: 56 s of steady operation) from the
    pipeline itself: after 40 s the refusal asks for 16 s more at the load learned; a stream that
    long learns, one 2 s shorter does not."""
    cfg = config(tmp_path)
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", _stream_file(tmp_path, 40.0)], capsys)
    assert rc == 2 and "not enough healthy data" in err and "learning reached" in err, err
    assert "56 s in all" in err and "about 1 more file of 40 s" in err, err
    more = _more_seconds(err)
    assert more == 16, err
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", _stream_file(tmp_path, 40.0 + more - 2)],
                       capsys)
    assert rc == 2 and _more_seconds(err) == 2, err
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", _stream_file(tmp_path, 40.0 + more)], capsys)
    assert rc == 0, err


def test_the_progress_says_how_many_minutes_remain():
    """The shipped rule: 30 spans of 4 s (2 min), then 40 stretches of 30 s over at least 20 min:
    22 minutes of steady operation before anything is learned."""
    from agent.library import ModelLibrary
    from agent.pipeline import DriveMonitor, PipelineConfig
    from agent.profile import load_profile
    import tempfile

    mon = DriveMonitor("d1", load_profile(PROFILE_PATH), ModelLibrary(tempfile.mkdtemp()), PipelineConfig())
    mon.start_learning()
    assert mon.learn_remaining_s == PipelineConfig().learn_total_s == 22 * 60.0
    assert mon.learn_needs_text({"fe_hz": 100.0, "load_pct": 92.0}) == (
        "learning reached 0 %: about 22 more minutes of steady operation at 92 % load (fe 100.0 Hz)")


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    """A library with one baseline learned from files at 80 % load, and the config."""
    tmp = tmp_path_factory.mktemp("learned")
    cfg = config(tmp)
    assert main(["learn", "--config", str(cfg), "--drive", "drive1", *records(tmp, 14)]) == 0
    return tmp, cfg


def _copy(learned, tmp_path):
    import shutil

    src, cfg = learned
    shutil.copytree(src / "state", tmp_path / "state")
    path = tmp_path / "agent.toml"
    path.write_text(cfg.read_text().replace(str(src / "state"), str(tmp_path / "state")))
    return path, tmp_path / "state" / "library"


def test_a_covered_point_is_refused_before_learning_whatever_the_amount_of_data(learned, tmp_path, capsys):
    cfg, lib = _copy(learned, tmp_path)
    before = {p.name: p.read_bytes() for p in lib.glob("*.json")}
    for files in (records(tmp_path, 1, seed=950), records(tmp_path, 14, seed=960)):
        rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", *files], capsys)
        assert rc == 2 and len(err.strip().splitlines()) == 1, err
        assert "already covers" in err and "--replace" in err and "not enough" not in err, err
        assert {p.name: p.read_bytes() for p in lib.glob("*.json")} == before


def test_replace_replaces_the_covering_baseline_whatever_its_name(learned, tmp_path, capsys):
    cfg, lib = _copy(learned, tmp_path)
    (old,) = [p.stem for p in lib.glob("*.json")]
    rc, out, err = run(["learn", "--json", "--config", str(cfg), "--drive", "drive1", "--replace", "--name", "fresh80",
                        *records(tmp_path, 14, load=81.0, seed=970)], capsys)
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["replaced"] == old and [p.stem for p in lib.glob("*.json")] == ["fresh80"]


def test_a_name_of_a_baseline_at_another_point_is_refused(learned, tmp_path, capsys):
    cfg, lib = _copy(learned, tmp_path)
    (old,) = [p.stem for p in lib.glob("*.json")]
    rc, out, err = run(["learn", "--config", str(cfg), "--drive", "drive1", "--name", old,
                        *records(tmp_path, 2, load=60.0, seed=980)], capsys)
    assert rc == 2 and f"--name {old}: a baseline of that name covers another operating point" in err, err
    assert [p.stem for p in lib.glob("*.json")] == [old]
