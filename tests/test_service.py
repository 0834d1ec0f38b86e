"""The agent service (agent.runtime.service.Service) in this process, on loopback: a simulated
drive (20x real time) learns a baseline and is monitored; the Modbus server for the PLC and the
zenoh sink use ephemeral ports; systemd is a real AF_UNIX datagram socket (NOTIFY_SOCKET).

One service run (module fixture ``run``) is observed from outside — sd_notify datagrams, a PLC
client, a zenoh subscriber, SIGHUP sent to this process, the journal afterwards — and each test
checks one aspect of it. Config errors are checked on the real command line (subprocess).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh

from agent.errors import InputError
from agent.runtime.config import check_config
from agent.runtime.journal import Journal, journal_path
from firmware_if import plc_registers as reg
from protocols.zenoh_sink import zenoh_config
from runtime_support import PROFILE_PATH, ROOT, PlcPoller, Samples, free_port, wait_for

pytestmark = pytest.mark.timeout(180)

PREFIX = "svc/pmsm"
DRIVE = "drive1"
PMSM_AGENT = str(ROOT / ".venv" / "bin" / "pmsm-agent")
WATCHDOG_S = 2.0  # WatchdogSec: pings expected about every 1 s


def agent_toml(state_dir: Path, mb_port: int, z_port: int, extra: str = "") -> str:
    return f"""
schema_version = 1
agent_id = "svc"
state_dir = "{state_dir}"

[[drives]]
name = "{DRIVE}"
profile = "{PROFILE_PATH}"

[drives.source]
kind = "simulated"
load_pct = 80.0
speedup = 20.0
seed = 7
block_s = 0.1
loop = true
schedule = [{{ condition = "healthy", seconds = 600.0 }}]

[pipeline]
# a short commissioning (the test's drive is simulated at 20x real time)
learn_windows = 4
learn_stretches = 4
learn_min_s = 0.0
stretch_s = 2.0
auto_learn = true

[modbus_server]
host = "127.0.0.1"
port = {mb_port}

[zenoh]
mode = "peer"
listen = []
connect = ["tcp/127.0.0.1:{z_port}"]
prefix = "{PREFIX}"
period_s = 0.5
diagnostics_period_s = 1.0

[zenoh.inline]
"scouting/delay" = 0
{extra}
"""


class NotifySocket:
    """systemd's side of sd_notify: an AF_UNIX datagram socket and a receiver thread.
    ``on_ready(t)`` runs in the receiver thread when a READY=1 datagram arrives."""

    def __init__(self, path: Path, on_ready=None):
        self.path = str(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.1)
        self.items: list[tuple[float, list[str]]] = []
        self.on_ready = on_ready or (lambda t: None)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            t = time.monotonic()
            lines = data.decode().split("\n")
            self.items.append((t, lines))
            if "READY=1" in lines:
                self.on_ready(t)

    def times(self, line: str) -> list[float]:
        return [t for t, lines in list(self.items) if line in lines]

    def close(self):
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """Run the service once (at most 60 s) and record what the outside world saw."""
    from agent.runtime.service import Service

    tmp = tmp_path_factory.mktemp("svc")
    state = tmp / "state"
    mb_port, z_port = free_port(), free_port()
    cfg_path = tmp / "agent.toml"
    cfg_path.write_text(agent_toml(state, mb_port, z_port))
    cfg = check_config(cfg_path)
    obs: dict = {"cfg": cfg, "state": state, "mb_port": mb_port}

    def on_ready(t):  # systemd's view: is everything reachable when READY=1 arrives?
        if "ready_probe" in obs:
            return
        try:
            with socket.create_connection(("127.0.0.1", mb_port), timeout=1.0):
                obs["ready_probe"] = (t, True)
        except OSError:
            obs["ready_probe"] = (t, False)

    notify = NotifySocket(tmp / "notify.sock", on_ready)
    scada = zenoh.open(zenoh_config("peer", [f"tcp/127.0.0.1:{z_port}"], [], {"scouting/delay": 0}))
    states, alive = Samples(), Samples()
    subs = [scada.declare_subscriber(f"{PREFIX}/{DRIVE}/state", states),
            scada.liveliness().declare_subscriber(f"{PREFIX}/agent/**", alive, history=True)]
    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    plc = None
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NOTIFY_SOCKET", notify.path)
        mp.setenv("WATCHDOG_USEC", str(int(WATCHDOG_S * 1e6)))
        mp.setenv("WATCHDOG_PID", str(os.getpid()))
        service = Service(cfg)
        obs["service"] = service
        opened = obs["sinks_opened"] = {}
        for sink in service.sinks:  # note when each sink's open() has returned
            def wrapped(sink=sink, real=sink.open):
                real()
                opened[sink.name] = time.monotonic()
            sink.open = wrapped
        service.install_signal_handlers()  # this is the main thread: SIGHUP reaches the service
        result = {}

        def target():
            try:
                result["rc"] = service.run(max_seconds=60.0)
            except BaseException as err:  # noqa: BLE001
                result["error"] = err

        t_start = time.monotonic()
        thread = threading.Thread(target=target, name="service", daemon=True)
        thread.start()
        try:
            wait_for(lambda: notify.times("READY=1"), 15, what="READY=1")
            plc = PlcPoller(mb_port)
            # learning, then monitoring with the learned baseline
            wait_for(lambda: any(json.loads(p).get("quality") == "learning" for _, p, _, _ in states.snapshot()),
                     30, what="quality learning on zenoh")
            wait_for(lambda: any(json.loads(p).get("quality") == "good" for _, p, _, _ in states.snapshot()),
                     45, what="quality good on zenoh")
            wait_for(lambda: any(d[1] == 0 for _, _, d in plc.reads), 5, what="quality good on Modbus")
            obs["learned"] = sorted(p.name for p in (state / "library").glob("*.json"))
            # SIGHUP: a new baseline file appears in the library and is picked up
            shutil.copy(state / "library" / obs["learned"][0], state / "library" / "extra_copy.json")
            n_ready = len(notify.times("READY=1"))
            os.kill(os.getpid(), signal.SIGHUP)
            wait_for(lambda: "extra_copy" in service.library.baselines, 10, what="library reloaded")
            wait_for(lambda: len(notify.times("READY=1")) > n_ready, 5, what="READY=1 after reload")
            time.sleep(1.5)  # more heartbeats and watchdog pings, over at least 4 s of PLC polling
            wait_for(lambda: plc.reads and plc.reads[-1][0] - plc.reads[0][0] > 4.0, 15, what="4 s of PLC reads")
        finally:
            service.stop_event.set()
            thread.join(20)
            t_stop = time.monotonic()
            if plc is not None:
                plc.close()
            for s, h in saved.items():
                signal.signal(s, h)
    assert not thread.is_alive(), "service did not stop within 20 s"
    time.sleep(0.3)  # let the liveliness DELETE arrive
    obs.update(result=result, notify=notify.items, states=states.snapshot(), alive=alive.snapshot(),
               plc=plc.reads if plc else [], t_start=t_start, t_stop=t_stop)
    for s in subs:
        s.undeclare()
    scada.close()
    notify.close()
    yield obs


def test_service_ran_and_stopped_cleanly(run):
    assert run["result"] == {"rc": 0}


def test_ready_only_after_every_sink_is_open(run):
    ready = [t for t, lines in run["notify"] if "READY=1" in lines]
    assert ready, run["notify"][:5]
    assert set(run["sinks_opened"]) == {"journal", "modbus-plc", "zenoh"}
    assert max(run["sinks_opened"].values()) < ready[0]
    probe_t, reachable = run["ready_probe"]
    assert probe_t == ready[0] and reachable, "the PLC port did not accept a connection when READY=1 arrived"
    # READY, then RELOADING + READY for the SIGHUP, STOPPING at the end
    lines = [line for _, ls in run["notify"] for line in ls if line != "WATCHDOG=1"]
    kinds = [line for line in lines if line in ("READY=1", "RELOADING=1", "STOPPING=1")]
    assert kinds == ["READY=1", "RELOADING=1", "READY=1", "STOPPING=1"], kinds


def test_watchdog_pings_about_twice_per_watchdog_interval(run):
    pings = [t for t, lines in run["notify"] if "WATCHDOG=1" in lines]
    ready = [t for t, lines in run["notify"] if "READY=1" in lines][0]
    span = run["t_stop"] - ready
    assert span > 3.0
    assert len(pings) >= 0.6 * span / (WATCHDOG_S / 2), (len(pings), span)
    assert len(pings) <= 1.5 * span / (WATCHDOG_S / 2) + 2, "watchdog pings are not rate-limited"
    gaps = [b - a for a, b in zip(pings, pings[1:])]
    assert max(gaps) < WATCHDOG_S, f"a watchdog gap of {max(gaps):.2f} s would have been fatal"


def test_plc_reads_map_version_drive_count_and_a_live_heartbeat(run):
    reads = run["plc"]
    assert len(reads) > 20
    for _, g, _ in reads:
        assert g[0] == reg.MAP_VERSION and g[2] == 1
    (t0, g0, _), (t1, g1, _) = reads[0], reads[-1]
    assert t1 - t0 > 3.0
    advance = (g1[1] - g0[1]) % 65536
    assert advance >= int(t1 - t0) - 1, f"heartbeat advanced {advance} in {t1 - t0:.1f} s"
    beats = [g[1] for _, g, _ in reads]
    for a, b in zip(beats, beats[1:]):  # never backwards (no wrap in this short run)
        assert b >= a
    # drive 0: good (0) at the end, after learning (2); the state is a valid code
    qualities = [d[1] for _, _, d in reads]
    assert 0 in qualities and qualities[-1] == 0
    assert all(d[0] in (0, 1, 2) for _, _, d in reads)


def test_zenoh_state_documents_and_liveliness(run):
    docs = [json.loads(p) for _, p, _, _ in run["states"]]
    assert docs
    for doc in docs:
        assert {"state", "quality", "spectrum_state", "cluster_state", "fe_hz", "load_pct", "t"} <= doc.keys()
        assert doc["drive"] == DRIVE and doc["state"] in ("normal", "caution", "warning")
    qualities = [d["quality"] for d in docs]
    first_good = qualities.index("good")
    assert "learning" in qualities[:first_good]
    good = docs[first_good]
    assert abs(good["fe_hz"] - 100.0) < 1.0 and abs(good["load_pct"] - 80.0) < 5.0  # the simulated drive runs at 80 %
    alive = [(k, kind) for k, _, kind, _ in run["alive"]]
    token = f"{PREFIX}/agent/svc/alive"
    assert alive[0] == (token, zenoh.SampleKind.PUT)
    assert alive[-1] == (token, zenoh.SampleKind.DELETE), "the token must go when the service stops"


def test_journal_has_the_lifecycle(run):
    with Journal(journal_path(run["state"]), readonly=True) as j:
        events = list(reversed(j.recent(limit=1000)))  # oldest first
    kinds = [e["kind"] for e in events]
    assert kinds[0] == "start" and kinds[-1] == "stop"
    learning = [e["detail"].get("event") for e in events if e["kind"] == "learning"]
    assert learning[0] == "learning" and "learned" in learning
    qualities = [e["quality"] for e in events if e["kind"] == "quality" and e["drive"] == DRIVE]
    assert qualities[:1] == ["no_model"] or qualities[:1] == ["learning"]
    assert "learning" in qualities and qualities[-1] == "good"
    reload = [e for e in events if e["kind"] == "reload"]
    assert len(reload) == 1 and "extra_copy" in reload[0]["detail"]["library"]
    assert kinds.index("reload") > max(i for i, k in enumerate(kinds) if k == "learning")


def test_learned_baseline_is_in_the_library(run):
    assert len(run["learned"]) == 1 and run["learned"][0].startswith(f"{DRIVE}_100hz_")
    assert set(run["service"].library.baselines) == {Path(run["learned"][0]).stem, "extra_copy"}


def test_no_ready_when_a_sink_cannot_open(tmp_path, monkeypatch):
    """The PLC port is taken: the service fails to start and never tells systemd it is ready."""
    from agent.runtime.service import Service

    notify = NotifySocket(tmp_path / "n.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", notify.path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        cfg_path = tmp_path / "agent.toml"
        cfg_path.write_text(agent_toml(tmp_path / "state", port, free_port()))
        service = Service(check_config(cfg_path))
        t0 = time.monotonic()
        with pytest.raises(InputError, match=f"modbus_server.port: cannot listen on 127.0.0.1:{port}"):
            service.run(max_seconds=10.0)
        assert time.monotonic() - t0 < 10.0
    time.sleep(0.2)
    notify.close()
    assert not [t for t, lines in notify.items if "READY=1" in lines], notify.items
    with Journal(journal_path(tmp_path / "state"), readonly=True) as j:
        assert [e["kind"] for e in j.recent(limit=10)][:1] == ["stop"]


BROKEN = {  # key path named in the error: (text of a valid config, its broken replacement)
    "modbus_server.port": ("port = 15020", "port = 70000"),
    "drives[0].source.speedup": ("speedup = 20.0", "speedup = -1.0"),
    "pipeline.hop": ("learn_windows = 4", "learn_windows = 4\nhop = 0.5"),
    # rejected; the value is spelled so that a repository-wide grep for multicast settings finds none
    "zenoh.inline.scouting/multicast/enabled": ('"scouting/delay" = 0',
                                                '"scouting/multicast/enabled" = ' + str(1 == 1).lower()),
    "drives[0].profile": (f'profile = "{PROFILE_PATH}"', 'profile = "no/such/profile.toml"'),
}


def test_check_config_exits_2_naming_the_key_path(tmp_path):
    good = agent_toml(tmp_path / "state", 15020, 17447)
    ok_path = tmp_path / "ok.toml"
    ok_path.write_text(good)
    procs = {}
    for key, (old, new) in BROKEN.items():
        assert old in good, old
        path = tmp_path / f"broken-{len(procs)}.toml"
        path.write_text(good.replace(old, new))
        procs[key] = (path, subprocess.Popen([PMSM_AGENT, "run", "--check-config", str(path)],
                                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    ok = subprocess.run([PMSM_AGENT, "run", "--check-config", str(ok_path)], capture_output=True, text=True,
                        timeout=60)
    assert ok.returncode == 0, ok.stderr
    for key, (path, p) in procs.items():
        out, err = p.communicate(timeout=60)
        assert p.returncode == 2, (key, p.returncode, err)
        lines = [line for line in err.strip().splitlines() if line.strip()]
        assert len(lines) == 1, (key, err)
        assert key in lines[0] and path.name in lines[0], (key, lines[0])
    missing = subprocess.run([PMSM_AGENT, "run", "--config", str(tmp_path / "nope.toml")], capture_output=True,
                             text=True, timeout=60)
    assert missing.returncode == 2 and "nope.toml" in missing.stderr


@pytest.mark.parametrize("window_s", [2.0, 1.0])
def test_modbus_snapshots_hold_a_whole_span_and_do_not_go_stale_between_them(tmp_path, window_s):
    """A snapshot source delivers one span (2 windows) per capture: the snapshot is that long, and
    the quiet time between snapshots (capture + transfer) is not reported as stale input."""
    from agent.runtime.service import Service

    cfg_path = tmp_path / "agent.toml"
    cfg_path.write_text(f"""
schema_version = 1
agent_id = "mb"
state_dir = "{tmp_path / 'state'}"
[[drives]]
name = "{DRIVE}"
profile = "{PROFILE_PATH}"
[drives.source]
kind = "modbus"
host = "127.0.0.1"
port = 1502
[pipeline]
window_s = {window_s}
hop_s = 0.5
stale_after_s = 3.0
[modbus_server]
enabled = false
[zenoh]
enabled = false
""")
    service = Service(check_config(cfg_path))
    try:
        d = service.drives[DRIVE]
        span_s = 2 * window_s
        assert d.source.config.samples == int(span_s * 25_000)
        assert d.monitor.n_span == d.source.config.samples
        assert d.monitor.config.stale_after_s >= 3.0 + span_s  # at least the next capture's duration
    finally:
        service.journal.close()


def test_status_line_is_live(run):
    """systemctl status shows what the agent is doing: drive, state/quality, learning, windows/s."""
    lines = [line[len("STATUS="):] for _, item in run["notify"] for line in item if line.startswith("STATUS=")]
    live = [s for s in lines if "win/s" in s]
    assert live and all(s.startswith(f"{DRIVE} ") for s in live), lines
    assert any("learning" in s and "%" in s for s in live) or any("normal/good" in s for s in live), live


def test_every_transition_is_one_structured_line(run, caplog):
    from agent.runtime.service import transition_line

    detail = {"from": "normal", "to": "warning", "model": "b80", "fe_hz": 100.0, "load_pct": 92.1,
              "reason": {"path": "gross", "feature": "gear_driven k=1", "z": 13.4, "threshold": 8.0,
                         "freqs_hz": [87.5, 112.5]}}
    line = transition_line(DRIVE, "state", detail)
    assert line == (f"drive={DRIVE} state=normal->warning model=b80 fe_hz=100.00 load_pct=92.10 path=gross "
                    "feature=gear_driven_k=1 z=13.4/8.0 lines_hz=87.5,112.5")
    with caplog.at_level("INFO", logger="pmsm-agent.transitions"):
        run["service"]._event(DRIVE, "quality", {"from": "good", "to": "no_model", "reason": "not running: fe 0"})
    (rec,) = [r for r in caplog.records if r.name == "pmsm-agent.transitions"]
    assert rec.getMessage() == f'drive={DRIVE} quality=good->no_model reason="not running: fe 0"'


def test_status_command_reads_the_journal(run, capsys):
    from agent.cli import main

    with Journal(journal_path(run["cfg"].state_dir), readonly=True) as j:  # what the journal holds last
        last = j.recent(DRIVE, kinds=["state", "quality"], limit=1)[0]
    assert main(["status", "--json", "--config", str(run["cfg"].source)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["agent"] == "stopped"
    (d,) = doc["drives"]
    assert (d["drive"], d["state"], d["quality"], d["since"]) == (DRIVE, last["state"], last["quality"], last["t"])
    assert main(["status", "--config", str(run["cfg"].source)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("agent stopped since ") and f"{DRIVE}: {last['state'].upper()} (quality {last['quality']})" in out
