"""A plant on zenoh's router network, all on loopback (no multicast): one router
(``pmsm-agent router``), three gateways (``pmsm-agent run`` subprocesses, ten drives each replaying
a short synthetic record, zenoh clients of the router with a 2 s lease), ``pmsm-agent fleet``,
and a historian writing to a real PostgreSQL.

The module fixture starts the plant once; the tests run in file order and each leaves it as it
found it (the router outage comes last). An observer session in this process records every
state sample and liveliness event.
"""

from __future__ import annotations

import json
import re
import shutil
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from agent.runtime.commands import sign
from agent.runtime.journal import Journal, journal_path
from agent.runtime.plant import drive_rows, format_table, gather, plant_view
from protocols.zenoh_sink import zenoh_config
from runtime_support import PROFILE_PATH, ROOT, free_port, wait_for

pytestmark = pytest.mark.timeout(170)

LEASE_MS = 2000  #: transport lease of every session in the test (default 10 s)
LEASE_S = LEASE_MS / 1000
ROOT_PREFIX = "pmsm"
SITES = {"gw1": "s1", "gw2": "s1", "gw3": "s2"}
DRIVES = [f"d{i}" for i in range(10)]
KEY_HEX = {"operator": "11" * 32, "engineer": "22" * 32}


def write_record(path: Path, seconds: float = 3.0, rate: float = 25_000.0) -> Path:
    """A balanced three-phase drive at fe 100 Hz (no simulator: the cheapest source that gives states)."""
    from agent.records import Record, save_record

    t = np.arange(int(seconds * rate)) / rate
    phase = 2 * np.pi * 100.0 * t[None, :] - np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])[:, None]
    return save_record(Record(t, 200.0 * np.cos(phase), 10.0 * np.cos(phase - 0.3)), path)


def write_keys(path: Path, keys: dict[str, str]) -> Path:
    path.write_text("[keys]\n" + "".join(f'{role} = "{key}"\n' for role, key in keys.items()))
    path.chmod(0o600)
    return path


def gateway_toml(tmp: Path, agent_id: str, site: str, endpoint: str, record: Path, keys: Path, mb_port: int,
                 name: str | None = None) -> Path:
    drives = "".join(f"""
[[drives]]
name = "{d}"
profile = "{PROFILE_PATH}"
[drives.source]
kind = "replay"
files = ["{record}"]
loop = true
""" for d in DRIVES)
    path = tmp / f"{name or agent_id}.toml"
    path.write_text(f"""
schema_version = 1
agent_id = "{agent_id}"
state_dir = "{tmp / (name or agent_id)}"
{drives}
[pipeline]
window_s = 0.5
hop_s = 0.5
auto_learn = false
learn_windows = 4
learn_stretches = 4
learn_min_s = 0.0
stretch_s = 1.0

[modbus_server]
host = "127.0.0.1"
port = {mb_port}

[zenoh]
mode = "client"
connect = ["{endpoint}"]
prefix = "{ROOT_PREFIX}"
site = "{site}"
period_s = 0.5
diagnostics_period_s = 5.0
retry_initial_s = 0.25
retry_max_s = 1.0

[zenoh.inline]
"transport/link/tx/lease" = {LEASE_MS}

[commands]
enabled = true
key_file = "{keys}"
acknowledge = ["operator", "engineer"]
relearn = ["engineer"]
max_skew_s = 30.0
""")
    return path


class Proc:
    """A ``pmsm-agent`` subprocess on the worktree's code, its output in a log file."""

    def __init__(self, args: list[str], log: Path):
        self.args, self.log = args, log
        self.proc: subprocess.Popen | None = None

    def start(self) -> Proc:
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "agent.cli", *self.args], cwd=ROOT, stdout=out,
                                         stderr=subprocess.STDOUT, env={**os.environ, "PYTHONPATH": str(ROOT)})
        return self

    def send(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int | None:
        if self.proc is None:
            return None
        self.send(sig)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(5)

    def text(self) -> str:
        return self.log.read_text(errors="replace")


class Observer:
    """Client sessions of the plant: one records every state sample's (time, seq, boot_id, state,
    quality) per key and every liveliness event (key, kind, time); the other asks what
    ``fleet status`` asks. (In zenoh 1.10 a liveliness get on a session that also holds a
    liveliness subscriber with history on those keys may return no tokens at all, at once.)"""

    def __init__(self, endpoint: str):
        cfg = lambda: zenoh_config("client", [], [endpoint], {"transport/link/tx/lease": LEASE_MS})  # noqa: E731
        self.session, self.query_session = zenoh.open(cfg()), zenoh.open(cfg())
        self.lock = threading.Lock()
        self.states: dict[str, list[tuple]] = {}
        self.alive: list[tuple[str, object, float]] = []
        self.inventory: dict | None = None
        self._subs = [self.session.declare_subscriber(f"{ROOT_PREFIX}/**/state", self._on_state),
                      self.session.liveliness().declare_subscriber(f"{ROOT_PREFIX}/**/alive", self._on_alive,
                                                                   history=True)]

    def _on_state(self, sample) -> None:
        doc = json.loads(sample.payload.to_string())
        with self.lock:
            self.states.setdefault(str(sample.key_expr), []).append(
                (time.monotonic(), doc["seq"], doc["boot_id"], doc["state"], doc["quality"]))

    def _on_alive(self, sample) -> None:
        with self.lock:
            self.alive.append((str(sample.key_expr), sample.kind, time.monotonic()))

    def latest(self) -> dict[str, tuple]:
        with self.lock:
            return {k: v[-1] for k, v in self.states.items()}

    def deleted_since(self, prefix: str, t0: float) -> dict[str, float]:
        with self.lock:
            return {k: t for k, kind, t in self.alive if k.startswith(prefix) and kind == zenoh.SampleKind.DELETE
                    and t >= t0}

    def gather(self) -> tuple[set[str], list[dict]]:
        return gather(self.query_session, ROOT_PREFIX, timeout=2.0)

    def view(self) -> dict:
        """The plant as ``fleet status`` sees it (remembering earlier views, like its inventory)."""
        self.inventory = plant_view(*self.gather(), self.inventory)
        return self.inventory

    def links(self) -> dict[tuple[str, str], str]:
        """(gateway, drive) -> live / LOST."""
        return {(r["gateway"], r["drive"]): r["link"] for r in drive_rows(self.view())}

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()
        self.query_session.close()


class Plant:
    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.record = write_record(tmp / "drive.npz")
        self.keys = write_keys(tmp / "keys.toml", KEY_HEX)
        (tmp / "router.json5").write_text(f"{{ transport: {{ link: {{ tx: {{ lease: {LEASE_MS} }} }} }} }}")
        self.router = Proc(["router", "--listen", self.endpoint, "--config", str(tmp / "router.json5")],
                           tmp / "router.log")
        self.mb_ports = {gw: free_port() for gw in SITES}
        self.configs = {gw: gateway_toml(tmp, gw, site, self.endpoint, self.record, self.keys, self.mb_ports[gw])
                        for gw, site in SITES.items()}
        self.gateways = {gw: Proc(["run", "--config", str(cfg)], tmp / f"{gw}.log") for gw, cfg in self.configs.items()}
        self.observer: Observer | None = None

    def prefix(self, gw: str) -> str:
        return f"{ROOT_PREFIX}/{SITES[gw]}/{gw}"

    def all_live(self) -> bool:
        links = self.observer.links()
        return len(links) == 30 and all(v == "live" for v in links.values())

    def journal(self, gw: str, kinds=None) -> list[dict]:
        with Journal(journal_path(self.tmp / gw), readonly=True) as j:
            return list(reversed(j.recent(None, kinds=kinds, limit=1000)))

    def close(self) -> None:
        for gw in self.gateways.values():
            gw.stop()
        if self.observer is not None:
            self.observer.close()
        self.router.stop()


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    plant = Plant(tmp_path_factory.mktemp("plant"))
    try:
        plant.router.start()
        wait_for(lambda: "listening on" in plant.router.text(), 30, what="the router")
        plant.observer = Observer(plant.endpoint)
        t0 = time.monotonic()
        for gw in plant.gateways.values():
            gw.start()
        wait_for(plant.all_live, 60, 0.5, what="30 live drives on 3 gateways")
        print(f"\nplant up: 3 gateways x 10 drives live {time.monotonic() - t0:.1f} s after start")
        yield plant
    finally:
        plant.close()
        for name in ("router", *SITES):
            log = plant.tmp / f"{name}.log"
            if log.exists() and log.stat().st_size:
                print(f"--- {name}.log (tail)\n" + "\n".join(log.read_text(errors="replace").splitlines()[-15:]))


def fleet_cli(plant: Plant, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "agent.cli", "fleet", *extra], cwd=ROOT, capture_output=True,
                          text=True, timeout=60, env={**os.environ, "PYTHONPATH": str(ROOT)})


# --- tests -----------------------------------------------------------------------------------------

def test_fleet_status_shows_every_drive_with_its_gateway(plant):
    inventory = plant.tmp / "fleet.json"
    r = fleet_cli(plant, "status", "--connect", plant.endpoint, "--inventory", str(inventory), "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    rows = doc["drives"]
    assert len(rows) == 30 and doc["lost"] == 0
    assert {(r["site"], r["gateway"]) for r in rows} == {(s, g) for g, s in SITES.items()}
    for row in rows:
        assert row["key"] == f"{plant.prefix(row['gateway'])}/{row['drive']}"
        assert row["link"] == "live" and row["state"] == "normal" and row["quality"] == "no_model"
        assert row["seq"] > 0 and row["since"] is not None and row["evidence"] == {}
    assert sorted(g["agent"] for g in doc["gateways"]) == sorted(SITES)
    text = fleet_cli(plant, "status", "--connect", plant.endpoint, "--inventory", str(inventory))
    lines = text.stdout.splitlines()
    assert lines[0].startswith("plant pmsm: 3/3 gateway(s) live, 30/30 drive(s) live"), text.stdout
    assert lines[1].split() == ["SITE", "GATEWAY", "DRIVE", "LINK", "STATE", "QUALITY", "EVIDENCE", "LAST",
                                "CHANGE", "SEQ"]
    assert len(lines) == 32 and lines[2].split()[:6] == ["s1", "gw1", "d0", "live", "normal", "no_model"]


def test_the_table_shows_evidence_per_family_and_lost_drives():
    answer = {"agent": "gw9", "site": "s9", "prefix": "pmsm/s9/gw9", "drives": {
        "d1": {"state": "caution", "quality": "good", "evidence": {"gear_driven": 0.71, "chain": 0.02},
               "since": 1.8e9, "t": 1.8e9, "seq": 41}}}
    view = plant_view({"pmsm/s9/gw9/agent/gw9/alive", "pmsm/s9/gw9/d1/alive"}, [answer], now=1.8e9)
    table = format_table(drive_rows(view))
    assert "CAUTION" in table and "chain=0.02 gear_driven=0.71" in table and " live " in table
    lost = plant_view(set(), [], view, now=1.8e9 + 5)  # the gateway's token is gone: it and its drives are LOST
    (row,) = drive_rows(lost)
    assert (row["link"], row["gateway_link"], row["state"]) == ("LOST", "LOST", "caution")
    assert lost["gateways"]["pmsm/s9/gw9"]["lost_since"] == 1.8e9 + 5


def test_a_killed_gateway_is_lost_within_the_lease_and_comes_back_alone(plant):
    obs = plant.observer
    obs.view()
    before = obs.latest()
    prefix = plant.prefix("gw2") + "/"
    t0 = time.monotonic()
    plant.gateways["gw2"].stop(signal.SIGKILL)
    tokens = {f"{prefix}agent/gw2/alive", *(f"{prefix}{d}/alive" for d in DRIVES)}
    gone = wait_for(lambda: (g := obs.deleted_since(prefix, t0)).keys() >= tokens and g, LEASE_S + 3,
                    what="gw2's tokens to go")
    lost_after = max(gone.values()) - t0
    links = wait_for(lambda: (v := obs.links()) and all(v[("gw2", d)] == "LOST" for d in DRIVES) and v, 5,
                     what="fleet shows gw2 LOST")
    print(f"\nSIGKILL: gw2 and its 10 drive tokens gone {lost_after * 1e3:.0f} ms later (lease {LEASE_S:g} s)")
    assert lost_after < LEASE_S
    assert all(v == "live" for (gw, _), v in links.items() if gw != "gw2"), links
    t1 = time.monotonic()
    plant.gateways["gw2"].start()
    wait_for(plant.all_live, 40, 0.5, what="gw2 back")
    print(f"gw2 restarted: its drives live again {time.monotonic() - t1:.1f} s later")
    after = obs.latest()
    for gw in ("gw1", "gw3"):  # nothing else disturbed: same boot, the same states, seq advanced
        for d in DRIVES:
            key = f"{plant.prefix(gw)}/{d}/state"
            (_, seq0, boot0, *st0), (_, seq1, boot1, *st1) = before[key], after[key]
            assert boot1 == boot0 and st1 == st0 and seq1 > seq0, (key, before[key], after[key])
    key = f"{prefix}d0/state"
    assert after[key][2] != before[key][2]  # gw2 itself: a new boot


def test_a_frozen_gateway_is_lost_at_lease_expiry(plant):
    """SIGSTOP (a hung PC: no TCP reset) is noticed by the router when the lease expires; after
    SIGCONT zenoh reconnects the gateway and declares its tokens again."""
    obs = plant.observer
    prefix = plant.prefix("gw3") + "/"
    t0 = time.monotonic()
    plant.gateways["gw3"].send(signal.SIGSTOP)
    try:
        gone = wait_for(lambda: obs.deleted_since(f"{prefix}agent/", t0), LEASE_S + 5, 0.05,
                        what="gw3's token to expire")
    finally:
        plant.gateways["gw3"].send(signal.SIGCONT)
    lost_after = min(gone.values()) - t0
    print(f"\nSIGSTOP: gw3's token gone {lost_after:.2f} s later (lease {LEASE_S:g} s)")
    assert 0.5 * LEASE_S < lost_after < LEASE_S + 1.5
    t1 = time.monotonic()
    wait_for(plant.all_live, 30, 0.5, what="gw3 back after SIGCONT")
    print(f"gw3 live again {time.monotonic() - t1:.1f} s after SIGCONT")


def test_a_second_gateway_with_the_same_id_is_refused(plant):
    obs = plant.observer
    cfg = gateway_toml(plant.tmp, "gw2", "s1", plant.endpoint, plant.record, plant.keys, free_port(), name="gw2-dup")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "agent.cli", "run", "--config", str(cfg)], cwd=ROOT,
                       capture_output=True, text=True, timeout=60, env={**os.environ, "PYTHONPATH": str(ROOT)})
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    print(f"\nsame id refused after {time.monotonic() - t0:.1f} s: {lines[-1] if lines else ''}")
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert "agent_id 'gw2' is already live" in lines[0] and "pmsm/s1/gw2/agent/gw2/alive" in lines[0]
    assert not obs.deleted_since(plant.prefix("gw2"), t0), "the live gw2 was disturbed"
    assert plant.all_live()


def test_signed_commands_from_an_authorised_role_only(plant):
    obs = plant.observer
    target = f"{plant.prefix('gw1')}/d3"
    r = fleet_cli(plant, "command", "relearn", "--connect", plant.endpoint, "--drive", target, "--role", "engineer",
                  "--key-file", str(plant.keys), "--by", "test")
    assert r.returncode == 0 and "relearn accepted" in r.stdout, r.stderr
    wait_for(lambda: obs.latest()[f"{target}/state"][4] == "learning", 10, what="d3 learning after RELEARN")

    def send(doc, drive_key=target):
        (reply,) = list(obs.session.get(f"{drive_key}/command", payload=json.dumps(doc), timeout=3.0))
        return (True, json.loads(reply.ok.payload.to_string())) if reply.ok else \
            (False, json.loads(reply.err.payload.to_string())["error"])

    key = {role: bytes.fromhex(k) for role, k in KEY_HEX.items()}
    ack = sign("acknowledge", target, "operator", key["operator"], by="op")
    assert send(ack) == (True, {"accepted": True, "command": "acknowledge", "drive": "d3", "role": "operator"})
    refusals = {
        "bad signature": sign("relearn", target, "engineer", b"\x33" * 32),  # a key that is not the engineer's
        "role not allowed": sign("relearn", target, "operator", key["operator"]),
        "replayed": ack,
        "stale": sign("acknowledge", target, "operator", key["operator"], t=time.time() - 120),
        "wrong target": sign("acknowledge", f"{plant.prefix('gw1')}/d4", "operator", key["operator"]),
        "unknown role": sign("acknowledge", target, "intruder", b"\x44" * 32),
    }
    for reason, doc in refusals.items():
        ok, error = send(doc)
        assert not ok and error.startswith(f"refused: {reason}"), (reason, error)
    intruder = write_keys(plant.tmp / "intruder.toml", {"engineer": "55" * 32})
    r = fleet_cli(plant, "command", "relearn", "--connect", plant.endpoint, "--drive", target, "--role", "engineer",
                  "--key-file", str(intruder))
    assert r.returncode == 2 and "refused: bad signature" in r.stderr, r.stderr
    (gw1,) = [a for a in obs.gather()[1] if a["agent"] == "gw1"]
    assert gw1["commands"]["accepted"] == 2 and gw1["commands"]["refused"] == 7
    assert gw1["commands"]["refused_by_reason"]["bad signature"] == 2
    events = [e for e in plant.journal("gw1", ["command", "learning"]) if e["drive"] == "d3"]
    accepted = [e["detail"]["command"] for e in events if e["kind"] == "command" and e["detail"]["accepted"]]
    refused = {e["detail"]["reason"] for e in events if e["kind"] == "command" and not e["detail"]["accepted"]}
    assert accepted == ["relearn", "acknowledge"] and refused == set(refusals)
    assert any("relearn requested over zenoh by test (engineer)" == e["detail"].get("event") for e in events)


def test_the_historian_records_every_drive_with_site_and_gateway(plant, pg, tmp_path):
    import psycopg
    from test_historian import started, write_config

    dsn = pg.create_database()
    historian = started(write_config(tmp_path, dsn, plant.endpoint))
    try:
        def drives():
            with psycopg.connect(dsn) as conn:
                try:
                    return set(conn.execute("SELECT site, gateway, drive FROM drive").fetchall())
                except psycopg.errors.UndefinedTable:  # the historian has not made its tables yet
                    return set()
        expected = {(SITES[gw], gw, d) for gw in SITES for d in DRIVES}
        found = wait_for(lambda: (ds := drives()) >= expected and ds, 30, 0.5, what="30 drives in PostgreSQL")
        assert found == expected
    finally:
        historian.stop()


@pytest.mark.slow
def test_gateways_die_and_return_again_and_again(plant, full_form):
    """Each gateway in turn is killed and restarted (once each; five rounds with PMSM_SLOW=full):
    each time it alone is LOST within the lease and then back, the others stay live throughout."""
    obs = plant.observer
    rounds = 5 if full_form else 1
    lost_s, back_s = [], []
    for _ in range(rounds):
        for gw in SITES:
            prefix = plant.prefix(gw) + "/"
            t0 = time.monotonic()
            plant.gateways[gw].stop(signal.SIGKILL)
            wait_for(lambda: f"{prefix}agent/{gw}/alive" in obs.deleted_since(prefix, t0), LEASE_S + 3,
                     what=f"{gw} lost")
            lost_s.append(max(obs.deleted_since(prefix, t0).values()) - t0)
            links = obs.links()
            assert all((v == "LOST") == (g == gw) for (g, _), v in links.items()), links
            t1 = time.monotonic()
            plant.gateways[gw].start()
            wait_for(plant.all_live, 40, 0.5, what=f"{gw} back")
            back_s.append(time.monotonic() - t1)
    print(f"\n{rounds} round(s) x 3 gateways: lost after at most {max(lost_s) * 1e3:.0f} ms, "
          f"back after {min(back_s):.1f}..{max(back_s):.1f} s")
    assert max(lost_s) < LEASE_S


def test_an_unreachable_router_leaves_monitoring_and_the_plc_alone(plant):
    """The router dies: every gateway keeps monitoring and serving its PLC registers, and one that
    starts meanwhile runs too; zenoh comes back by itself when the router does. Each journal notes
    the loss and the return."""
    from pymodbus.client import ModbusTcpClient

    from firmware_if import plc_registers as reg

    def plc(gw):
        client = ModbusTcpClient("127.0.0.1", port=plant.mb_ports[gw], timeout=2.0, retries=0)
        try:
            if not client.connect():
                return None
            r = client.read_input_registers(0, count=reg.DRIVE_BASE + 2, device_id=reg.DEVICE_ID)
            return None if r.isError() else list(r.registers)
        finally:
            client.close()

    t0 = time.time()
    plant.router.stop(signal.SIGKILL)
    wait_for(lambda: any(e["detail"].get("event") == "lost" and e["t"] >= t0 for e in plant.journal("gw1", ["zenoh"])),
             LEASE_S + 5, 0.2, what="gw1 journals the lost router")
    plant.gateways["gw3"].stop()  # a gateway (re)started while no router answers
    plant.gateways["gw3"].start()
    first = wait_for(lambda: plc("gw3"), 30, 0.2, what="gw3's PLC registers without a router")
    regs1 = {gw: wait_for(lambda gw=gw: plc(gw), 5, what=f"{gw} PLC") for gw in ("gw1", "gw2")}
    time.sleep(1.5)
    stale = reg.QUALITY_CODES["stale"]
    for gw, regs in regs1.items():  # the heartbeat advances and drive 0's input is live (not stale)
        now = plc(gw)
        assert now[1] != regs[1], f"{gw}'s heartbeat stopped"
        assert now[reg.DRIVE_BASE + 1] != stale, f"{gw} drive 0 went stale without the router"
    assert first[2] == 10
    wait_for(lambda: (r := plc("gw3")) and r[reg.DRIVE_BASE + 1] not in (stale,), 20, 0.3, what="gw3 monitoring")
    t1 = time.monotonic()
    plant.router.start()
    wait_for(plant.all_live, 40, 0.5, what="every gateway back on the router")
    print(f"\nrouter back: 30 drives live {time.monotonic() - t1:.1f} s later")
    for gw, first_event in (("gw1", "lost"), ("gw2", "lost"), ("gw3", "unreachable")):
        events = [e["detail"]["event"] for e in plant.journal(gw, ["zenoh"]) if e["t"] >= t0]
        assert first_event in events and events[-1] == "connected", (gw, events)


# --- configuration and deployment (no plant needed) -------------------------------------------------

def _agent_config(tmp_path, zenoh_keys: str, commands: str = "") -> Path:
    path = tmp_path / "agent.toml"
    path.write_text(f"""
schema_version = 1
agent_id = "gw7"
state_dir = "{tmp_path / 'state'}"
[[drives]]
name = "d1"
profile = "{PROFILE_PATH}"
[drives.source]
kind = "simulated"
[zenoh]
{zenoh_keys}
{commands}
""")
    return path


def test_the_plant_prefix_keeps_the_contracts_key_form(tmp_path):
    """With ``site`` the gateway's own prefix is <root>/<site>/<agent_id>: its drives still publish
    on <prefix>/<drive>/state (CONTRACT section 6), and the historian reads site and gateway from it."""
    from agent.historian.ingest import identity
    from agent.runtime.config import check_config

    z = check_config(_agent_config(tmp_path, 'mode = "client"\nconnect = ["tcp/r1:7447"]\nsite = "hall-3"')).zenoh
    assert (z.prefix, z.plant_prefix) == ("pmsm/hall-3/gw7", "pmsm")
    assert identity(f"{z.prefix}/d1/state", {}, "pmsm") == ("hall-3", "gw7", "d1")
    z = check_config(_agent_config(tmp_path, 'mode = "client"\nconnect = ["tcp/r1:7447"]\nsite = "s"\n'
                                             'prefix = "acme/pmsm"')).zenoh
    assert z.prefix == "acme/pmsm/s/gw7"
    z = check_config(_agent_config(tmp_path, 'prefix = "pmsm/demo"')).zenoh
    assert (z.prefix, z.plant_prefix, z.site) == ("pmsm/demo", "pmsm/demo", "")


@pytest.mark.parametrize("zenoh_keys, commands, message", [
    ('mode = "client"', "", "zenoh.connect: a client needs at least one router endpoint"),
    ('mode = "client"\nconnect = ["tcp/r:1"]\nlisten = ["tcp/0.0.0.0:7447"]', "", "zenoh.listen: only a peer"),
    ('site = "a/b"', "", "zenoh.site: 'a/b'"),
    ("", "[commands]\nenabled = true", "commands.key_file: missing"),
    ("", "[commands]\nenabled = true\nkey_file = \"keys.toml\"\nrelearn = [\"boss\"]",
     "commands.relearn[0]: role 'boss' has no key"),
    ("", "[commands]\nenabled = true\nkey_file = \"open.toml\"", "world-readable"),
    ("", "[commands]\nenabled = true\nkey_file = \"short.toml\"", "keys.operator: a hex string of at least 16 bytes"),
])
def test_plant_config_errors_name_the_key(tmp_path, zenoh_keys, commands, message):
    from agent.errors import InputError
    from agent.runtime.config import check_config

    write_keys(tmp_path / "keys.toml", KEY_HEX)
    write_keys(tmp_path / "open.toml", KEY_HEX).chmod(0o644)
    write_keys(tmp_path / "short.toml", {"operator": "ab" * 8, "engineer": "ab" * 15})
    with pytest.raises(InputError, match=re.escape(message)):
        check_config(_agent_config(tmp_path, zenoh_keys, commands))


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_the_router_unit_verifies(tmp_path):
    unit = tmp_path / "pmsm-router.service"
    text = (ROOT / "config" / "pmsm-router.service").read_text()
    assert "router --listen tcp/0.0.0.0:7447" in text and "Type=notify" in text
    unit.write_text(re.sub(r"^ExecStart=\S+", f"ExecStart={sys.executable}", text, flags=re.M))
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and not r.stderr.strip(), r.stderr


def test_fleet_without_a_router_is_one_line_and_exit_2(tmp_path, capsys):
    from agent.cli import main

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    assert main(["fleet", "status", "--connect", endpoint, "--inventory", str(tmp_path / "inv.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"pmsm-agent fleet: error: --connect {endpoint}: no zenoh router answers")
