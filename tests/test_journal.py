"""The SQLite event journal: survives kill -9, bounded size, change detection, queries, CLI."""

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agent.cli import main
from agent.runtime.journal import Journal, JournalSink, journal_path
from protocols.base import DriveStatus

ROOT = Path(__file__).resolve().parent.parent

CHILD = """
import sys, time
from agent.runtime.journal import Journal
j = Journal(sys.argv[1], synchronous=sys.argv[2])
i = 0
while True:
    i += 1
    eid = j.record("state" if i % 2 else "quality", f"d{i % 3}", state=i % 3, quality=i % 5, detail={"i": i})
    print(eid, i, flush=True)
"""


@pytest.mark.parametrize("sync", ["FULL", "NORMAL"])
def test_every_committed_event_survives_kill_9(tmp_path, sync):
    path = tmp_path / "journal.sqlite3"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path), sync], stdout=subprocess.PIPE, text=True,
                             cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    committed = {}
    try:
        for line in child.stdout:  # each line is printed only after its commit returned
            eid, i = map(int, line.split())
            committed[eid] = i
            if len(committed) >= 300:
                break
    finally:
        child.send_signal(signal.SIGKILL)  # mid-write: the child keeps inserting until here
        child.wait(5)
    assert child.returncode == -signal.SIGKILL and len(committed) >= 300
    with Journal(path) as j:
        found = {e["id"]: e["detail"]["i"] for e in j.recent(limit=100_000)}
        assert sqlite3.connect(path).execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert all(found.get(eid) == i for eid, i in committed.items())
        assert j.record("start", detail={"after": "kill"}) > max(committed)  # writable again, ids go on


def test_record_and_query(tmp_path):
    with Journal(tmp_path / "j.sqlite3") as j:
        a = j.record("state", "d1", state="warning", quality="good", detail={"why": "peaks"}, t=100.0)
        j.record("learning", "d1", quality=2, detail={"windows": 12}, t=101.0)
        j.record("error", "d2", detail={"msg": "serial timeout"}, t=102.0)
        j.record("start", t=103.0)
        e = j.recent(limit=1)[0]
        assert e["kind"] == "start" and e["drive"] == "" and e["state_code"] is None
        first = j.recent("d1", kinds=["state"])[0]
        assert first["id"] == a and first["state"] == "warning" and first["state_code"] == 2
        assert first["quality"] == "good" and first["quality_code"] == 0 and first["detail"] == {"why": "peaks"}
        assert [e["kind"] for e in j.recent("d1")] == ["learning", "state"]
        assert [e["t"] for e in j.recent(since=102.0)] == [103.0, 102.0]
        assert len(j.recent(before_id=a + 1)) == 1 and j.count() == 4
        assert j.provider()("d1", {"limit": "1", "kind": "state,learning"})["events"][0]["kind"] == "learning"
        with pytest.raises(ValueError, match="bad query parameter"):
            j.provider()("d1", {"limit": "many"})


def test_repeated_errors_are_rate_limited(tmp_path, monkeypatch):
    clock = [1000.0]
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])
    with Journal(tmp_path / "j.sqlite3", error_holdoff_s=60.0) as j:
        assert j.record("error", "d1", detail={"event": "gap"}) is not None
        assert all(j.record("error", "d1", detail={"event": "gap"}) is None for _ in range(50))
        assert j.record("error", "d2", detail={"event": "gap"}) is not None  # another drive
        assert j.record("error", "d1", detail={"msg": "serial timeout"}) is not None  # another error
        clock[0] += 61.0
        assert j.record("error", "d1", detail={"event": "gap"}) is not None
        assert j.recent("d1", limit=1)[0]["detail"] == {"event": "gap", "suppressed": 50}
        assert j.count() == 4


def test_status_changes_are_logged_once_and_survive_restart(tmp_path):
    path = tmp_path / "j.sqlite3"
    with Journal(path) as j:
        s = DriveStatus("d1", state="normal", quality="learning", t=1.0)
        assert len(j.record_status(s)) == 2  # first sight: state and quality
        assert j.record_status(s) == []
        s.quality = "good"
        assert len(j.record_status(s)) == 1
        s.state, s.spectrum_state, s.peaks = "warning", "warning", [{"freq_hz": 87.5}]
        (eid,) = j.record_status(s)
        assert j.recent(limit=1)[0]["detail"]["from"] == "normal"
    with Journal(path) as j:  # the last logged state/quality are reloaded: no spurious change
        assert j.record_status(DriveStatus("d1", state="warning", quality="good")) == []
        assert j.recent(limit=1)[0]["id"] == eid


def test_retention_by_count_and_age_is_incremental(tmp_path):
    with Journal(tmp_path / "j.sqlite3", max_events=100, max_age_s=1000.0, prune_every=10, prune_batch=10) as j:
        now = time.time()
        for i in range(45):
            j.record("old", t=now - 5000 + i)  # beyond max_age_s
        assert j.count() == 5  # at most one batch of 10 deleted at inserts 10, 20, 30, 40
        for i in range(400):
            j.record("new", t=now)
        assert j.count() <= 100 + 10  # never more than max_events + prune_every
        while j.prune():
            pass
        assert j.count() == 100 and all(e["kind"] == "new" for e in j.recent(limit=1000))
    with pytest.raises(ValueError, match="prune_batch"):
        Journal(tmp_path / "k.sqlite3", prune_every=100, prune_batch=10)


def test_journal_sink_writes_changes_off_the_caller_thread(tmp_path):
    j = Journal(tmp_path / "j.sqlite3")
    sink = JournalSink(j)
    sink.open()
    s = DriveStatus("d1", state="normal", quality="good")
    for _ in range(100):
        sink.publish(s)
    sink.publish(DriveStatus("d1", state="caution", quality="good"))
    sink.close()
    assert [e["kind"] for e in j.recent()] == ["state", "quality", "state"]  # newest first
    j.close()


def test_events_cli(tmp_path, capsys):
    with Journal(journal_path(tmp_path)) as j:
        j.record("state", "d1", state=1, quality=0, detail={"from": "normal"})
        j.record("error", "d2", detail={"msg": "x"})
    assert main(["events", "--state-dir", str(tmp_path), "--drive", "d1", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [e["state"] for e in doc["events"]] == ["caution"]
    assert main(["events", "--state-dir", str(tmp_path), "--limit", "5"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2 and "state=caution(1)" in out[0] and "error" in out[1]
    assert main(["events", "--state-dir", str(tmp_path / "none")]) == 2
    assert "no journal" in capsys.readouterr().err


def test_events_text_and_json_agree_oldest_first(tmp_path, capsys):
    with Journal(journal_path(tmp_path)) as j:
        for k, state in enumerate((0, 1, 2)):
            j.record("state", "d1", state=state, quality=0, t=1000.0 + k)
    assert main(["events", "--state-dir", str(tmp_path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["order"] == "oldest first" and [e["t"] for e in doc["events"]] == [1000.0, 1001.0, 1002.0]
    assert main(["events", "--state-dir", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == [str(e["id"]) for e in doc["events"]]
    assert main(["events", "--state-dir", str(tmp_path), "--limit", "2", "--json"]) == 0  # the newest two, oldest first
    assert [e["t"] for e in json.loads(capsys.readouterr().out)["events"]] == [1001.0, 1002.0]


def test_status_of_a_stopped_agent_is_as_of_its_stop(tmp_path, capsys):
    """The states held for the time up to the stop, not up to now; the default state_dir is beside
    the config file wherever the command runs."""
    from agent.runtime.config import DEFAULT_CONFIG, check_config

    cfg = tmp_path / "agent.toml"
    text = DEFAULT_CONFIG.read_text().replace('profile = "profiles/', f'profile = "{DEFAULT_CONFIG.parent}/profiles/')
    cfg.write_text(text)
    c = check_config(cfg)
    assert c.state_dir == tmp_path / "state"
    now = time.time()
    with Journal(journal_path(tmp_path / "state")) as j:
        j.record("start", t=now - 3600)
        j.record("state", c.drives[0].name, state=0, quality=0, t=now - 3000)
        j.record("stop", t=now - 2400)
    assert main(["status", "--config", str(cfg), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["agent"] == "stopped" and doc["as_of"] == pytest.approx(now - 2400)
    assert doc["drives"][0]["age_s"] == pytest.approx(600.0, abs=0.2)
    assert main(["status", "--config", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "as of the stop" in out and "for 10.0 min" in out
