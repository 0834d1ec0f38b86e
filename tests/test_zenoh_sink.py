"""ZenohSink on real zenoh sessions over tcp/127.0.0.1 (no multicast): state, liveliness, queryables,
diagnostics, a dead peer that must not stall publish(), and the latency on loopback."""

import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from protocols.base import DriveStatus, Sink
from protocols.zenoh_sink import AgentIdInUse, Providers, ZenohSink, zenoh_config

ROOT = Path(__file__).resolve().parent.parent
PREFIX = "test/pmsm"
FAST = {"scouting/delay": 0}  # do not wait 500 ms for peers in open()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Collector:
    """Thread-safe list of (key, payload, kind) with a wait helper."""

    def __init__(self):
        self.items, self.cond = [], threading.Condition()

    def __call__(self, sample):
        with self.cond:
            self.items.append((str(sample.key_expr), sample.payload.to_string(), sample.kind, time.perf_counter()))
            self.cond.notify_all()

    def wait(self, pred, timeout=5.0):
        with self.cond:
            assert self.cond.wait_for(lambda: any(pred(*i[:3]) for i in self.items), timeout), self.items[-5:]
            return [i for i in self.items if pred(*i[:3])][-1]  # the latest match


@pytest.fixture
def link():
    """(port, scada session listening on it); the agent under test connects to it."""
    port = free_port()
    scada = zenoh.open(zenoh_config("peer", [f"tcp/127.0.0.1:{port}"], [], FAST))
    yield port, scada
    scada.close()


def make_sink(port, **kw):
    cfg = zenoh_config("peer", [], [f"tcp/127.0.0.1:{port}"], FAST)
    return ZenohSink(cfg, PREFIX, "edge1", drives=["d1"], **kw)


def status(state="normal", quality="good", **kw):
    return DriveStatus("d1", state=state, quality=quality, fe_hz=100.0, load_pct=80.0, t=time.time(), **kw)


def test_config_helper_never_enables_multicast(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "client", scouting: { multicast: { enabled: true }, gossip: { enabled: true } },'
                 ' connect: { endpoints: ["tcp/127.0.0.1:1"] } }')
    for cfg in (zenoh_config(), zenoh_config(extra={"scouting/multicast/enabled": True}), zenoh_config(path=f)):
        assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
        assert json.loads(cfg.get_json("scouting/gossip/enabled")) is False
    assert json.loads(zenoh_config().get_json("listen/endpoints")) == []  # not the default tcp/[::]:0
    from_file = zenoh_config(None, path=f)
    assert json.loads(from_file.get_json("mode")) == "client"
    assert json.loads(from_file.get_json("connect/endpoints")) == ["tcp/127.0.0.1:1"]
    with pytest.raises(ValueError, match="no/such/key"):
        zenoh_config(extra={"no/such/key": 1})


def test_state_on_change_and_periodically(link):
    port, scada = link
    got = Collector()
    sub = scada.declare_subscriber(f"{PREFIX}/**", got)
    sink = make_sink(port, period_s=0.2, diagnostics_period_s=0.3)
    assert isinstance(sink, Sink)
    with sink:
        time.sleep(0.2)  # let the subscription reach the agent
        sink.publish(status())
        # the first message of this drive (a periodic repeat may follow it before we look)
        _, payload, *_ = got.wait(lambda k, p, _: k == f"{PREFIX}/d1/state" and json.loads(p)["seq"] == 1)
        doc = json.loads(payload)
        assert {"state", "quality", "spectrum_state", "cluster_state", "fe_hz", "load_pct", "t"} <= set(doc)
        assert (doc["state"], doc["quality"], doc["state_code"], doc["quality_code"]) == ("normal", "good", 0, 0)
        assert doc["agent"] == "edge1" and doc["seq"] == 1 and doc["schema"] == 3
        got.wait(lambda k, p, _: k.endswith("/state") and json.loads(p)["seq"] >= 3)  # periodic repeats
        sink.publish(status("warning", spectrum_state="warning", peaks=[{"freq_hz": 87.5}]))
        _, payload, *_ = got.wait(lambda k, p, _: k.endswith("/state") and json.loads(p)["state"] == "warning")
        assert json.loads(payload)["state_code"] == 2 and json.loads(payload)["peaks"] == [{"freq_hz": 87.5}]
        _, payload, *_ = got.wait(lambda k, p, _: k == f"{PREFIX}/d1/diagnostics")
        assert json.loads(payload)["zenoh"]["changes"] >= 1
        _, payload, *_ = got.wait(lambda k, p, _: k == f"{PREFIX}/agent/edge1/health")
        assert json.loads(payload)["drives"]["d1"]["state"] in ("normal", "warning")
    sub.undeclare()


def test_liveliness_put_then_delete_on_close(link):
    port, scada = link
    got = Collector()
    sub = scada.liveliness().declare_subscriber(f"{PREFIX}/**/alive", got, history=True)
    sink = make_sink(port)
    sink.open()
    key = f"{PREFIX}/agent/edge1/alive"
    got.wait(lambda k, p, kind: k == key and kind == zenoh.SampleKind.PUT)
    sink.close()
    got.wait(lambda k, p, kind: k == key and kind == zenoh.SampleKind.DELETE)
    sink.close()  # safe twice
    sub.undeclare()


CHILD = """
import sys, time
from protocols.zenoh_sink import ZenohSink, zenoh_config
sink = ZenohSink(zenoh_config("peer", [], [sys.argv[1]], {"scouting/delay": 0}), "test/pmsm", "child",
                 drives=["d1"])
sink.open()
print("open", flush=True)
if sys.argv[2] == "exit":
    sys.exit(0)  # without close(): atexit must close the session or the interpreter hangs
time.sleep(60)
"""


def _child(port, mode):
    return subprocess.Popen([sys.executable, "-c", CHILD, f"tcp/127.0.0.1:{port}", mode], cwd=ROOT,
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_liveliness_delete_when_the_agent_is_killed(link):
    port, scada = link
    got = Collector()
    sub = scada.liveliness().declare_subscriber(f"{PREFIX}/**/alive", got, history=True)
    child = _child(port, "sleep")
    try:
        assert child.stdout.readline().strip() == "open"
        key = f"{PREFIX}/agent/child/alive"
        got.wait(lambda k, p, kind: k == key and kind == zenoh.SampleKind.PUT)
        t0 = time.perf_counter()
        child.send_signal(signal.SIGKILL)
        *_, t1 = got.wait(lambda k, p, kind: k == key and kind == zenoh.SampleKind.DELETE, timeout=5.0)
        print(f"\nliveliness DELETE {1e3 * (t1 - t0):.1f} ms after SIGKILL")
    finally:
        child.kill()
        child.wait(5)
    sub.undeclare()


def test_exit_without_close_does_not_hang():
    child = _child(free_port(), "exit")
    assert child.wait(15) == 0


def test_queryables_answer_from_providers(link):
    port, scada = link
    calls = []

    def model(drive, params):
        calls.append((drive, params))
        return {"drive": drive, "model": "m-1", "params": params}

    def thresholds(drive, params):
        raise KeyError("no baseline yet")

    providers = Providers(model=model, thresholds=thresholds, health=lambda: {"sources": {"d1": "open"}},
                          events=lambda d, p: {"events": [{"kind": "state", "limit": p.get("limit")}]})
    with make_sink(port, providers=providers):
        time.sleep(0.2)

        def get(selector):
            replies = list(scada.get(selector, timeout=2.0))
            assert len(replies) == 1, selector
            r = replies[0]
            return (True, json.loads(r.ok.payload.to_string())) if r.ok else \
                (False, json.loads(r.err.payload.to_string()))

        assert get(f"{PREFIX}/d1/model?verbose=1") == (True, {"drive": "d1", "model": "m-1",
                                                              "params": {"verbose": "1"}})
        assert calls == [("d1", {"verbose": "1"})]
        assert get(f"{PREFIX}/d1/events?limit=5;kind=state") == (True, {"events": [{"kind": "state", "limit": "5"}]})
        ok, err = get(f"{PREFIX}/d1/thresholds")
        assert not ok and "not found" in err["error"]
        ok, err = get(f"{PREFIX}/d1/spectrum")
        assert not ok and "not provided" in err["error"]
        ok, health = get(f"{PREFIX}/agent/edge1/health")
        assert ok and health["sources"] == {"d1": "open"} and health["agent"] == "edge1"
        keys = sorted(str(r.ok.key_expr) for r in scada.get(f"{PREFIX}/d1/*", timeout=2.0) if r.ok)
        assert keys == [f"{PREFIX}/d1/events", f"{PREFIX}/d1/model"]


def test_dead_peer_never_stalls_publish():
    port = free_port()  # nobody listens here: zenoh keeps retrying in the background
    sink = make_sink(port, period_s=0.01, diagnostics_period_s=0.01)
    t0 = time.perf_counter()
    sink.open()
    t_open = time.perf_counter() - t0
    calls = []
    for i in range(5000):
        s = status(("normal", "caution", "warning")[i % 3])  # every call a change: worst case
        t = time.perf_counter()
        sink.publish(s)
        calls.append(time.perf_counter() - t)
    t = time.perf_counter()
    sink.close()
    t_close = time.perf_counter() - t
    print(f"\ndead peer: open {t_open * 1e3:.1f} ms, publish median {statistics.median(calls) * 1e6:.0f} us, "
          f"worst {max(calls) * 1e3:.1f} ms, close {t_close * 1e3:.1f} ms, {sink.stats}")
    # no network wait (500 ms scouting delay, 10 s lease) ever reaches the caller; the worst case
    # is the GIL handing over from the sender thread (switch interval 5 ms)
    assert t_open < 1.0 and statistics.median(calls) < 1e-3 and max(calls) < 0.2 and t_close < 2.5


def test_publish_latency_on_loopback(link):
    """publish() call -> subscriber callback, on change (BLOCK, express)."""
    port, scada = link
    got = Collector()
    sub = scada.declare_subscriber(f"{PREFIX}/d1/state", got)
    with make_sink(port, period_s=60.0) as sink:
        time.sleep(0.2)
        lat, call = [], []
        for i in range(200):
            n = len(got.items)
            t0 = time.perf_counter()
            sink.publish(status(("normal", "caution")[i % 2]))
            call.append(time.perf_counter() - t0)
            with got.cond:
                assert got.cond.wait_for(lambda: len(got.items) > n, 2.0)
                lat.append(got.items[n][3] - t0)
    sub.undeclare()
    q = statistics.quantiles(lat, n=100)
    print(f"\nzenoh loopback latency publish->subscriber: median {statistics.median(lat) * 1e6:.0f} us, "
          f"p99 {q[98] * 1e6:.0f} us; publish() call median {statistics.median(call) * 1e6:.0f} us")
    assert statistics.median(lat) < 0.05


def test_peer_restart_zenoh_reconnects_and_publish_never_waits():
    port = free_port()
    listen = zenoh_config("peer", [f"tcp/127.0.0.1:{port}"], [], FAST)
    scada = zenoh.open(listen)
    got = Collector()
    scada.declare_subscriber(f"{PREFIX}/d1/state", got)
    with make_sink(port, period_s=0.1) as sink:
        sink.publish(status("normal"))
        got.wait(lambda k, p, _: json.loads(p)["state"] == "normal")
        scada.close()  # the SCADA side goes away
        t0 = time.perf_counter()
        for i in range(1000):
            sink.publish(status(("caution", "normal")[i % 2]))
        assert time.perf_counter() - t0 < 0.5
        sink.publish(status("warning"))
        t_back = time.perf_counter()
        scada = zenoh.open(listen)  # ... and comes back on the same endpoint
        got2 = Collector()
        scada.declare_subscriber(f"{PREFIX}/d1/state", got2)
        *_, t_seen = got2.wait(lambda k, p, _: json.loads(p)["state"] == "warning", timeout=10.0)  # periodic repeat
        print(f"\nreconnected: latest state seen {t_seen - t_back:.2f} s after the peer came back")
    scada.close()


def test_drive_token_follows_the_input(link):
    """``<prefix>/<drive>/alive`` is live while the drive's input is (its quality not stale)."""
    port, scada = link
    got = Collector()
    sub = scada.liveliness().declare_subscriber(f"{PREFIX}/d1/alive", got, history=True)
    with make_sink(port) as sink:
        time.sleep(0.2)
        assert not got.items  # no status yet: no token
        sink.publish(status(quality="no_model"))
        got.wait(lambda k, p, kind: kind == zenoh.SampleKind.PUT)
        sink.publish(status(quality="stale"))
        got.wait(lambda k, p, kind: kind == zenoh.SampleKind.DELETE)
        assert sink.fleet()["drives"]["d1"]["alive"] is False
        n = len(got.items)
        sink.publish(status(quality="good"))
        with got.cond:  # a PUT after the DELETE
            assert got.cond.wait_for(lambda: any(i[2] == zenoh.SampleKind.PUT for i in got.items[n:]), 5.0), got.items
        deadline = time.monotonic() + 2.0  # the sender sets it once declare_token has returned
        while not sink.fleet()["drives"]["d1"]["alive"] and time.monotonic() < deadline:
            time.sleep(0.01)
        assert sink.fleet()["drives"]["d1"]["alive"] is True
    sub.undeclare()


def _router(port):
    return zenoh.open(zenoh_config("router", [f"tcp/127.0.0.1:{port}"], [], FAST))


def test_a_client_opens_in_the_background_once_a_router_answers():
    """Client mode: no router at open() is no error; the sink retries with back-off, then
    declares everything and reports each loss and return of its router."""
    port = free_port()
    events = []
    providers = Providers(link=lambda event, detail: events.append(event))
    cfg = zenoh_config("client", [], [f"tcp/127.0.0.1:{port}"], FAST)
    sink = ZenohSink(cfg, PREFIX, "edge1", drives=["d1"], providers=providers, period_s=0.1,
                     retry_initial_s=0.1, retry_max_s=0.4)
    t0 = time.perf_counter()
    sink.open()
    assert time.perf_counter() - t0 < 1.0 and events == ["unreachable"] and not sink.connected
    sink.publish(status())  # monitoring goes on without a router
    router = _router(port)
    try:
        scada = zenoh.open(zenoh_config("client", [], [f"tcp/127.0.0.1:{port}"], FAST))
        got = Collector()
        scada.declare_subscriber(f"{PREFIX}/d1/state", got)
        got.wait(lambda k, p, _: json.loads(p)["state"] == "normal", timeout=10.0)
        assert events == ["unreachable", "connected"] and sink.connected
        scada.close()
        router.close()
        deadline = time.monotonic() + 5
        while events[-1] != "lost" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert events[-1] == "lost" and sink.stats.link_losses == 1
    finally:
        router.close()
        sink.close()


def test_a_second_agent_with_the_same_id_is_refused():
    port = free_port()
    router = _router(port)
    lease = {**FAST, "transport/link/tx/lease": 1000}
    cfg = lambda: zenoh_config("client", [], [f"tcp/127.0.0.1:{port}"], lease)  # noqa: E731
    try:
        with ZenohSink(cfg(), PREFIX, "edge1"):
            second = ZenohSink(cfg(), PREFIX, "edge1")
            t0 = time.perf_counter()
            with pytest.raises(AgentIdInUse, match=f"agent_id 'edge1' is already live .*{PREFIX}/agent/edge1/alive"):
                second.open()
            assert 1.0 <= time.perf_counter() - t0 < 5.0  # it waited one lease for a dead predecessor's token
            other = ZenohSink(cfg(), PREFIX, "edge2")  # another id is welcome
            other.open()
            other.close()
        again = ZenohSink(cfg(), PREFIX, "edge1")  # the first one has gone: its id is free
        again.open()
        again.close()
    finally:
        router.close()
