"""The historian against a real PostgreSQL server (the ``pg`` fixture: tests/pg_support.py) and a
real zenoh router on loopback; stand-in agents publish drive states exactly as ZenohSink does."""

import json
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import psycopg
import pytest
import zenoh

from agent.cli import main
from agent.historian import store
from agent.historian.buffer import Buffer
from agent.historian.config import load_historian_config, parse_historian_config
from agent.historian.ingest import Last, identity, sample_rows
from agent.historian.service import WAITING_FOR_DATABASE, Historian
from agent.errors import InputError
from protocols.base import QUALITY_CODES, STATE_CODES, DriveStatus
from protocols.zenoh_sink import SCHEMA_VERSION, ZenohSink, zenoh_config
from runtime_support import free_port

ROOT = Path(__file__).resolve().parent.parent
FAST = {"scouting/delay": 0}


def wait_for(pred, timeout=15.0, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture(scope="module")
def router():
    """A zenoh router on an ephemeral loopback port; yields its endpoint."""
    session = zenoh.open(zenoh_config("router", ["tcp/127.0.0.1:0"], [], {**FAST, "adminspace/enabled": True}))
    replies = list(session.get(f"@/{session.zid()}/router", timeout=5))
    locators = json.loads(replies[0].ok.payload.to_string())["locators"]
    yield next(loc for loc in locators if loc.startswith("tcp/127.0.0.1:"))
    session.close()


def write_config(tmp_path, dsn, endpoint, zenoh_mode="client", **top):
    """A historian config in ``tmp_path``; ``top`` overrides top-level keys and ``retention``."""
    retention = top.pop("retention", {"trend_days": 30.0, "events_days": 365.0, "interval_s": 3600.0})
    keys = {"schema_version": 1, "historian_id": "test-historian", "state_dir": str(tmp_path / "state"),
            "batch_size": 7, "trend_period_s": 10.0, **top}
    lines = [f"{k} = {json.dumps(v)}" for k, v in keys.items()]
    lines += ["[database]", f"dsn = {json.dumps(dsn)}", "connect_timeout_s = 2.0", "retry_initial_s = 0.2",
              "retry_max_s = 1.0", "[zenoh]", f"mode = {json.dumps(zenoh_mode)}", f"connect = [{json.dumps(endpoint)}]",
              'prefix = "pmsm"', "retry_initial_s = 0.2", "retry_max_s = 1.0", "inline = { \"scouting/delay\" = 0 }",
              "[retention]"] + [f"{k} = {v}" for k, v in retention.items()]
    path = tmp_path / "historian.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


class StandInAgent:
    """Puts drive states on ``<prefix>/<drive>/state`` with ZenohSink's payload (its fields and
    ``schema``, ``state_code``, ``quality_code``, ``agent``, ``boot_id``, ``seq``), with the time
    ``t`` chosen by the test."""

    def __init__(self, endpoint, prefix, agent_id="edge1"):
        self.session = zenoh.open(zenoh_config("client", [], [endpoint], FAST))
        self.prefix, self.agent_id, self.boot_id = prefix, agent_id, uuid.uuid4().hex[:16]
        self.pubs, self.seq, self.count = {}, {}, 0

    def publish(self, drive, t, state="normal", quality="good", reason=None, evidence=None):
        if drive not in self.pubs:
            pub = self.session.declare_publisher(f"{self.prefix}/{drive}/state",
                                                 congestion_control=zenoh.CongestionControl.BLOCK)
            wait_for(lambda: pub.matching_status.matching, 10, "the historian's subscription")
            self.pubs[drive], self.seq[drive] = pub, 0
        status = DriveStatus(drive=drive, state=state, quality=quality, t=t, fe_hz=50.0, load_pct=80.0,
                             model="op-50hz", extra={"reason": reason, "settling": False,
                                                     "evidence": evidence or {"gear_driving": 0.1, "cluster": 0.0}})
        doc = {**status.to_json(), "state_code": STATE_CODES[state], "quality_code": QUALITY_CODES[quality]}
        self.seq[drive] += 1
        self.pubs[drive].put(json.dumps({"schema": SCHEMA_VERSION, **doc, "agent": self.agent_id,
                                         "boot_id": self.boot_id, "seq": self.seq[drive]}))
        self.count += 1

    def close(self):
        self.session.close()


REASON_A = {"path": "cusum", "feature": "gear_driven k=1", "families": ["gear_driven"], "evidence": 5.1,
            "threshold": 4.2}
REASON_B = {"path": "gross", "feature": "cluster", "families": ["cluster"], "z": 9.5, "threshold": 6.0}


def schedule(t0):
    """60 samples 1 s apart: learning 0-4, good from 5; caution 20-39 (reason A, then B from 30); normal 40-59."""
    for i in range(60):
        state = "caution" if 20 <= i < 40 else "normal"
        reason = (REASON_A if i < 30 else REASON_B) if state == "caution" else None
        yield i, dict(t=t0 + i, state=state, quality="learning" if i < 5 else "good", reason=reason,
                      evidence={"gear_driven": round(i / 20, 3), "cluster": 0.0})


#: what the historian must write for one drive's schedule (trend period 10 s): offsets from t0
EXPECTED_EVENTS = [(0, "state"), (0, "quality"), (5, "quality"), (20, "state"), (30, "reason"), (40, "state")]
EXPECTED_TRENDS = [0, 5, 15, 20, 30, 40, 50]


def db_rows(dsn):
    """({(site, gateway, drive): [(t, kind), ...]}, {ident: [t, ...]}) from PostgreSQL, duplicates kept."""
    with psycopg.connect(dsn) as conn:
        events, trends = {}, {}
        for site, gw, d, t, kind in conn.execute(
                "SELECT site, gateway, drive, extract(epoch FROM t)::float8, kind FROM drive_event "
                "JOIN drive USING (drive_id) ORDER BY t, event_id"):
            events.setdefault((site, gw, d), []).append((round(t, 3), kind))
        for site, gw, d, t in conn.execute("SELECT site, gateway, drive, extract(epoch FROM t)::float8 "
                                           "FROM evidence_trend JOIN drive USING (drive_id) ORDER BY t"):
            trends.setdefault((site, gw, d), []).append(round(t, 3))
    return events, trends


def expected(t0):
    return ([(round(t0 + i, 3), kind) for i, kind in EXPECTED_EVENTS], [round(t0 + i, 3) for i in EXPECTED_TRENDS])


def started(cfg_path):
    h = Historian(load_historian_config(cfg_path))
    h.start()
    assert h.open_zenoh()
    return h


# --- tests ---------------------------------------------------------------------------------------

def test_states_reasons_quality_and_trends_land(pg, router, tmp_path):
    dsn = pg.create_database()
    h = started(write_config(tmp_path, dsn, router))
    site_agent = StandInAgent(router, "pmsm/site-a/gw2")  # <prefix>/<site>/<gateway>/<drive>/state
    sink = ZenohSink(zenoh_config("client", [], [router], FAST), "pmsm", "gw9", drives=["d9"], period_s=0.2)
    try:
        t0 = time.time() - 120
        for i, kw in schedule(t0):
            site_agent.publish("d2", **kw)
        wait_for(lambda: h.counters["samples"] == 60 and h.buffer.count() == 0, what="60 samples written")
        events, trends = db_rows(dsn)
        want_events, want_trends = expected(t0)
        assert events[("site-a", "gw2", "d2")] == want_events
        assert trends[("site-a", "gw2", "d2")] == want_trends

        sink.open()  # the real sink, key <prefix>/<drive>/state: the gateway comes from the payload's agent
        for state, quality, reason, n_events in (("normal", "learning", None, 2), ("normal", "good", None, 3),
                                                 ("warning", "good", REASON_B, 4)):
            sink.publish(DriveStatus(drive="d9", state=state, quality=quality, t=time.time(),
                                     extra={"reason": reason, "evidence": {"chain": 0.5}, "settling": False}))
            wait_for(lambda: len(db_rows(dsn)[0].get(("", "gw9", "d9"), [])) == n_events, what=f"{state}/{quality}")
        with psycopg.connect(dsn) as conn:
            rows = conn.execute("SELECT kind, state, quality, prev_state, prev_quality, reason, agent, seq "
                                "FROM drive_event JOIN drive USING (drive_id) WHERE drive = 'd9' "
                                "ORDER BY event_id").fetchall()
            assert [r[:5] for r in rows] == [("state", 0, 2, None, None), ("quality", 0, 2, None, None),
                                             ("quality", 0, 0, 0, 2), ("state", 2, 0, 0, 0)]
            assert rows[-1][5] == REASON_B and rows[-1][6] == "gw9" and rows[-1][7] >= 3
            evidence = conn.execute("SELECT evidence FROM evidence_trend JOIN drive USING (drive_id) "
                                    "WHERE drive = 'd2' ORDER BY t DESC LIMIT 1").fetchone()[0]
            assert evidence == {"gear_driven": 2.5, "cluster": 0.0}
            assert conn.execute("SELECT version FROM schema_version").fetchall() == [(store.SCHEMA_VERSION,)]
        with psycopg.connect(dsn, autocommit=True) as conn:  # migrations re-run: no-ops
            assert store.migrate(conn) == store.SCHEMA_VERSION == store.migrate(conn)
            assert conn.execute("SELECT count(*) FROM schema_version").fetchone()[0] == len(store.MIGRATIONS)
        assert db_rows(dsn)[1][("site-a", "gw2", "d2")] == want_trends  # the data is untouched

        h.write_status()
        status = json.loads(h.cfg.status_path.read_text())
        assert status["database"]["state"] == "connected" and status["buffered"] == 0
        assert status["database"]["schema_version"] == store.SCHEMA_VERSION
        replies = list(site_agent.session.get("pmsm/historian/test-historian/health", timeout=5))
        assert json.loads(replies[0].ok.payload.to_string())["historian"] == "test-historian"
    finally:
        sink.close()
        site_agent.close()
        h.stop()


def test_peer_mode(pg, router, tmp_path):
    """A historian in peer mode connected to listed endpoints (here the router's) records too."""
    dsn = pg.create_database()
    h = started(write_config(tmp_path, dsn, router, zenoh_mode="peer"))
    agent = StandInAgent(router, "pmsm/gw1")
    try:
        agent.publish("d1", t=time.time(), state="caution", reason=REASON_A)
        wait_for(lambda: h.counters["rows_written"] == 3, what="state, quality and trend written")
        events, trends = db_rows(dsn)
        assert [kind for _, kind in events[("", "gw1", "d1")]] == ["state", "quality"]
        assert h.status()["zenoh"]["routers"] == 1
    finally:
        agent.close()
        h.stop()


def test_outage_loses_nothing_and_writes_each_row_once(pg, router, tmp_path):
    """PostgreSQL stops in the middle of a run while two drives keep publishing; after its restart
    every row is there exactly once (the lists below keep duplicates)."""
    dsn = pg.create_database()
    h = started(write_config(tmp_path, dsn, router))
    agents = {("", "gw1", "d1"): StandInAgent(router, "pmsm/gw1"),
              ("s1", "gw2", "d2"): StandInAgent(router, "pmsm/s1/gw2")}
    t0 = time.time() - 600
    samples = list(schedule(t0))
    try:
        def publish(part):
            for i, kw in part:
                for ident, agent in agents.items():
                    agent.publish(ident[2], **kw)

        publish(samples[:25])
        wait_for(lambda: h.counters["samples"] == 50 and h.buffer.count() == 0, what="the first part written")
        pg.stop()
        publish(samples[25:])
        # the rows of the second half wait in the buffer: events 30 and 40, trends 30, 40, 50 per drive
        wait_for(lambda: h.counters["samples"] == 120, what="all samples received")
        wait_for(lambda: h.database["state"] == WAITING_FOR_DATABASE, what="the writer to notice the outage")
        assert h.buffer.count() == 2 * 5
        pg.start()
        wait_for(lambda: h.buffer.count() == 0, 20, "the buffer to drain")
        events, trends = db_rows(dsn)
        want_events, want_trends = expected(t0)
        for ident in agents:
            assert events[ident] == want_events, ident
            assert trends[ident] == want_trends, ident
        assert h.counters["rows_written"] == h.counters["rows_buffered"] == 2 * (6 + 7)
        assert h.database["state"] == "connected"
    finally:
        for agent in agents.values():
            agent.close()
        h.stop()


def test_a_batch_sent_twice_is_written_once(pg, tmp_path):
    """A commit whose buffer delete never happened (the process died in between) is skipped on resend."""
    dsn = pg.create_database()
    buffer = Buffer(tmp_path / "b.sqlite3")
    row = {"site": "", "gateway": "gw1", "drive": "d1", "t": 1.0e9, "state": 0, "quality": 0, "evidence": {"x": 1}}
    for k in range(3):
        buffer.append([("trend", {**row, "t": row["t"] + k})], ("", "gw1", "d1"), Last(0, 0, None, row["t"] + k))
    with store.connect(dsn, 2) as conn:
        store.migrate(conn)
        writer = store.Writer(conn, buffer.buffer_id, "h")
        batch = buffer.oldest(10)
        assert writer.write(batch[:2]) == 2
        assert writer.write(batch) == 1  # the first two again (no delete in between) and one new
        assert store.Writer(conn, buffer.buffer_id, "h").write(batch) == 0  # a restarted writer too
        assert conn.execute("SELECT count(*) FROM evidence_trend").fetchone()[0] == 3
    buffer.close()


def test_buffered_rows_survive_a_restart_and_a_refused_row_is_set_aside(pg, router, tmp_path):
    """Rows buffered while PostgreSQL is down are written by the next run (the drive's last state
    is kept with them: a repeated sample adds nothing); a row PostgreSQL refuses for its data is
    set aside without holding up the rows behind it."""
    dsn = pg.create_database()
    cfg = load_historian_config(write_config(tmp_path, dsn, router, batch_size=50))
    samples = list(schedule(time.time() - 900))
    pg.stop()
    first = Historian(cfg)
    first.start()
    for i, kw in samples[:30]:
        first.ingest("pmsm/gw1/d1/state", {"drive": "d1", "agent": "gw1", **kw})
    wait_for(lambda: first.database["state"] == WAITING_FOR_DATABASE, what="the writer to wait")
    assert first.stop() == 8  # samples 0-29: events at 0 (state, quality), 5, 20; trends at 0, 5, 15, 20
    pg.start()
    second = Historian(cfg)
    poison = {"site": "", "gateway": "gw1", "drive": "d1", "t": samples[29][1]["t"], "state": 7, "quality": 0,
              "evidence": {}}
    second.buffer.append([("trend", poison)], ("", "gw1", "d1"), second._last[("", "gw1", "d1")])
    for i, kw in samples[29:]:  # sample 29 again: already recorded, no row
        second.ingest("pmsm/gw1/d1/state", {"drive": "d1", "agent": "gw1", **kw})
    second.start()
    try:
        wait_for(lambda: second.buffer.count() == 0, 20, "the buffer to drain")
        events, trends = db_rows(dsn)
        assert (events[("", "gw1", "d1")], trends[("", "gw1", "d1")]) == expected(samples[0][1]["t"])
        assert second.counters["rows_set_aside"] == 1
        import sqlite3
        with sqlite3.connect(cfg.buffer_path) as db:
            (error,) = db.execute("SELECT error FROM set_aside").fetchone()
        assert "evidence_trend" in error or "check constraint" in error
    finally:
        second.stop()


def test_database_down_at_start(pg, router, tmp_path):
    """The CLI historian waits for PostgreSQL (stderr and status file say so), keeps buffering and
    writes everything once the server starts; SIGTERM stops it with status 0."""
    dsn = pg.create_database()
    cfg_path = write_config(tmp_path, dsn, router)
    status_path = tmp_path / "state" / "historian-status.json"
    pg.stop()
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "historian", "--config", str(cfg_path)],
                                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err)
    agent = StandInAgent(router, "pmsm/gw1")
    try:
        def status():
            try:
                return json.loads(status_path.read_text())
            except (OSError, ValueError):
                return None

        wait_for(lambda: (s := status()) and s["database"]["state"] == WAITING_FOR_DATABASE
                 and s["zenoh"]["state"] == "subscribed", 20, "the status file to say it waits")
        assert WAITING_FOR_DATABASE in err_path.read_text()
        assert proc.poll() is None
        t0 = time.time() - 300
        for i, kw in schedule(t0):
            agent.publish("d1", **kw)
        wait_for(lambda: (s := status()) and s["buffered"] == 13, 10, "13 rows buffered")
        pg.start()
        wait_for(lambda: (s := status()) and s["buffered"] == 0 and s["database"]["state"] == "connected", 20,
                 "the backlog written")
        events, trends = db_rows(dsn)
        assert (events[("", "gw1", "d1")], trends[("", "gw1", "d1")]) == expected(t0)
        assert proc.poll() is None  # it never exited
    finally:
        agent.close()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=20)
    assert rc == 0, err_path.read_text()


def test_retention_deletes_old_trend_rows(pg, router, tmp_path):
    dsn = pg.create_database()
    h = started(write_config(tmp_path, dsn, router, retention={"trend_days": 30.0, "events_days": 365.0,
                                                                "interval_s": 1.0}))
    agent = StandInAgent(router, "pmsm/gw1")
    now = time.time()
    ages = {"recent": 600.0, "old": 40 * 86400.0, "ancient": 400 * 86400.0}  # s before now
    try:
        for drive, age in ages.items():
            for i, kw in schedule(now - age):
                agent.publish(drive, **kw)
        wait_for(lambda: h.counters["samples"] == 180 and h.buffer.count() == 0, what="all written")

        def counts():
            events, trends = db_rows(dsn)
            return {d: (len(events.get(("", "gw1", d), [])), len(trends.get(("", "gw1", d), []))) for d in ages}

        # trend rows beyond 30 days go, events stay for 365 days
        wait_for(lambda: counts() == {"recent": (6, 7), "old": (6, 0), "ancient": (0, 0)}, 10, "retention")
        assert h.retention["last_run"] is not None
    finally:
        agent.close()
        h.stop()


def test_history_queries_from_the_cli(pg, router, tmp_path, capsys):
    dsn = pg.create_database()
    cfg_path = write_config(tmp_path, dsn, router)
    h = started(cfg_path)
    agent, site_agent = StandInAgent(router, "pmsm/gw1"), StandInAgent(router, "pmsm/s1/gw2")
    t0 = time.time() - 3600
    try:
        for i, kw in schedule(t0):
            agent.publish("d1", **kw)
            if i < 25:  # d2 raises its alarm and keeps it
                site_agent.publish("d2", **kw)
        wait_for(lambda: h.counters["samples"] == 85 and h.buffer.count() == 0, what="all written")
    finally:
        agent.close()
        site_agent.close()
        h.stop()

    def run(*argv):
        capsys.readouterr()
        rc = main(list(argv))
        return rc, capsys.readouterr()

    rc, out = run("history", "--drive", "d1", "--since", "2h", "--config", str(cfg_path), "--json")
    assert rc == 0
    doc = json.loads(out.out)
    assert [(round(e["t"] - t0), e["kind"]) for e in doc["events"]] == EXPECTED_EVENTS
    raised = doc["events"][3]
    assert (raised["state"], raised["from"], raised["reason"]) == ("caution", "normal", REASON_A)
    rc, out = run("history", "--drive", "d1", "--since", "2h", "--dsn", dsn)
    assert rc == 0 and len(out.out.splitlines()) == 6 and "normal -> caution" in out.out and "gear_driven" in out.out

    rc, out = run("history", "--alarms", "--since", "7d", "--config", str(cfg_path), "--json")
    assert rc == 0
    doc = json.loads(out.out)
    assert doc["drives_alarmed"] == ["gw1/d1", "s1/gw2/d2"]
    by_drive = {a["drive"]: a for a in doc["alarms"]}
    assert by_drive["d1"]["reasons"] == [REASON_A, REASON_B] and by_drive["d1"]["state"] == "caution"
    assert round(by_drive["d1"]["start"] - t0) == 20 and round(by_drive["d1"]["duration_s"]) == 20
    assert by_drive["d2"]["end"] is None  # still raised
    # a period that starts inside d1's alarm still shows it, from its real start
    rc, out = run("history", "--alarms", "--since", _iso(t0 + 25), "--until", _iso(t0 + 26), "--dsn", dsn, "--json")
    assert rc == 0 and {a["drive"] for a in json.loads(out.out)["alarms"]} == {"d1", "d2"}
    rc, out = run("history", "--alarms", "--since", "7d", "--dsn", dsn)
    assert rc == 0 and "2 alarm(s) on 2 drive(s)" in out.out and "ongoing" in out.out and "CAUTION" in out.out

    rc, out = run("history", "--alarms", "--since", "yesterday", "--dsn", dsn)
    assert rc == 2 and "--since 'yesterday'" in out.err
    rc, out = run("history", "--alarms", "--dsn", f"host=127.0.0.1 port={free_port()} user=postgres "
                  "connect_timeout=2")
    assert rc == 2 and "cannot reach the database (--dsn)" in out.err


def test_samples_are_made_fit_for_postgresql():
    """Non-finite numbers and NUL characters (which jsonb and text refuse) are cleaned at ingest;
    a payload that is not a drive state is refused with the reason."""
    doc = {"drive": "d1", "state": "warning", "quality": "good", "t": 100.0, "model": "m\x00",
           "reason": {"path": "gross", "feature": "a\x00b", "z": float("nan"), "lines": [float("inf"), 1.5]},
           "evidence": {"chain": float("nan"), "cluster": 0.5}}
    ident = identity("pmsm/d1/state", {**doc, "agent": "gw7"}, "pmsm")
    assert ident == ("", "gw7", "d1")
    rows, last = sample_rows(ident, doc, None, trend_period_s=10.0, received_t=200.0)
    event, trend = rows[0][1], rows[-1][1]
    assert event["reason"] == {"path": "gross", "feature": "ab", "z": None, "lines": [None, 1.5]}
    assert event["model"] == "m" and trend["evidence"] == {"chain": None, "cluster": 0.5} and last.state == 2
    for bad, why in (([1], "not a JSON object"), ({"drive": "d1", "state": "alarm", "quality": "good"}, "'state'")):
        with pytest.raises(ValueError, match=why):
            sample_rows(identity("pmsm/d1/state", bad, "pmsm"), bad, None, trend_period_s=10.0, received_t=1.0)


def _iso(t):
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t))


@pytest.mark.parametrize("edit, key", [
    ({"batch_sise": 3}, "batch_sise: unknown key"),
    ({"database": {"dsn": "host=db port"}}, "database.dsn: not a libpq connection string"),
    ({"database": {}}, "database.dsn: missing"),
    ({"retention": {"trend_days": 0}}, "retention.trend_days: must be > 0"),
    ({"retention": {"trend_days": 30, "events_days": 7}}, "retention.events_days: state changes are kept"),
    ({"zenoh": {"mode": "router", "connect": ["tcp/127.0.0.1:7447"]}}, "zenoh.mode: must be one of"),
    ({"zenoh": {"mode": "client"}}, "zenoh.connect: a client needs at least one router"),
    ({"zenoh": {"connect": ["tcp/127.0.0.1:7447"], "inline": {"scouting/multicast/enabled": True}}},
     "zenoh.inline.scouting/multicast/enabled"),
    ({"zenoh": {"connect": ["tcp/127.0.0.1:7447"], "key_expr": "@/admin/**"}}, "zenoh.key_expr"),
    ({"zenoh": {"connect": ["tcp/127.0.0.1:7447"], "prefix": "pmsm/*"}}, "zenoh.prefix"),
    ({"schema_version": 2}, "schema_version: this historian reads version 1"),
])
def test_bad_config_keys_are_named(edit, key):
    data = {"schema_version": 1, "database": {"dsn": "host=db.plant.local dbname=pmsm"},
            "zenoh": {"connect": ["tcp/127.0.0.1:7447"]}}
    data.update(edit)
    with pytest.raises(InputError, match=re.escape(key)):
        parse_historian_config(data, "historian.toml")


def test_check_config_cli(tmp_path, capsys):
    assert main(["historian", "--check-config", str(ROOT / "config" / "historian.toml"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["key_expr"] == "pmsm/**/state" and doc["historian_id"] == "plant-1"
    bad = tmp_path / "h.toml"
    bad.write_text('schema_version = 1\n[database]\ndsn = "dbname=x"\n[zenoh]\nconnect = ["tcp/127.0.0.1:7447"]\n'
                   '[retention]\ntrend_dayz = 3\n')
    assert main(["historian", "--check-config", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{bad}: retention.trend_dayz: unknown key" in err


def test_systemd_unit():
    unit = (ROOT / "config" / "pmsm-historian.service").read_text()
    for line in ("Type=notify", "Restart=on-failure", "StateDirectory=pmsm-historian",
                 "ConfigurationDirectory=pmsm-historian", "DynamicUser=yes"):
        assert f"\n{line}\n" in unit, line
    assert re.search(r"^ExecStart=\S+ historian --config /etc/pmsm-historian/historian.toml$", unit, re.M)
    if shutil.which("systemd-analyze") is None:
        return
    path = Path(tempfile.mkdtemp()) / "pmsm-historian.service"
    path.write_text(re.sub(r"^ExecStart=\S+", f"ExecStart={sys.executable}", unit, flags=re.M))
    r = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True, text=True, timeout=60)
    shutil.rmtree(path.parent)
    assert r.returncode == 0 and not r.stderr.strip(), r.stderr
