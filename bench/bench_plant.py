"""The agent at plant scale, measured on loopback: payload sizes, a router's throughput, the
historian's ingest and PostgreSQL store (the figures behind docs/scale.md).

    python -m bench.bench_plant [--smoke] [--out bench/results/plant.json]

Four measurements, each on this machine (loopback only, ephemeral ports, multicast scouting off):

1. **payloads**: the bytes of the real :class:`protocols.zenoh_sink.ZenohSink` puts (state,
   diagnostics, health), captured by a subscriber, for realistic statuses of the gear and chain
   profiles (the evidence of every family, 12/18 spectral peaks, a reason while alarmed);
2. **router**: one ``pmsm-agent router`` subprocess, publisher processes each holding several
   client sessions (gateways) that put state-sized JSON at a set total rate, one client
   subscriber on the historian's key expression counting; delivered messages/s and the router's
   CPU (``/proc/<pid>/stat``) per rate;
3. **ingest**: the historian's per-sample work (``json.loads``, :func:`agent.historian.ingest.sample_rows`,
   the fsync'd :class:`agent.historian.buffer.Buffer` append) at the shipped trend period;
4. **postgres**: a throw-away PostgreSQL (initdb/pg_ctl as tests/pg_support.py) filled through
   the historian's own writer path (buffer -> :class:`agent.historian.store.Writer` in batches of
   ``batch_size``, delete from the buffer); rows/s, CPU per row and bytes per row of each table
   (``pg_total_relation_size``, indexes included).

``run()`` returns the figures as a dict; ``main()`` writes them as JSON and prints a table.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results" / "plant.json"
CLK_TCK = os.sysconf("SC_CLK_TCK")
FAST = {"scouting/delay": 0}

#: the shipped defaults (config/agent.toml [zenoh], agent/historian/config.py)
STATE_PERIOD_S = 1.0
DIAGNOSTICS_PERIOD_S = 5.0
TREND_PERIOD_S = 10.0
BATCH_SIZE = 500
#: on-change state puts per drive and hour (state, quality, scheduled baseline): bench-alarms'
#: healthy day has 3 setpoint changes an hour (each may switch the baseline, ``model``) and no
#: alarm onset (95 % bound 1.5 a day); range assumed 0.1-10 an hour, the upper end for a plant
#: that changes its operating point every 6 min
CHANGES_PER_DRIVE_HOUR = {"low": 0.1, "typical": 3.0, "high": 10.0}
#: event rows per drive and day (state/quality/reason changes): alarm onsets are rare (bench-alarms:
#: 0 in 2 drive-days); assumed 0.1-10, the upper end for drives that alarm and clear daily
EVENTS_PER_DRIVE_DAY = {"low": 0.1, "typical": 1.0, "high": 10.0}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def us_per_row(cpu_s: float, rows: int) -> float | None:
    """CPU microseconds per row, or None where ``cpu_s`` (read from /proc, in clock ticks) is under two
    ticks: below its resolution (10 ms), a count of 0 or 1 tick says nothing about the cost."""
    return 1e6 * cpu_s / rows if cpu_s >= 2.0 / CLK_TCK else None


def per_row_text(value: float | None, rows: int) -> str:
    """A per-row CPU figure for the table, or the bound where /proc could not resolve it."""
    return f"{value:.1f} us" if value is not None else f"below /proc's resolution (< {2e6 / CLK_TCK / rows:.1f} us)"


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (its threads included), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime (fields 14 and 15)


# --- realistic statuses ------------------------------------------------------------------------

def realistic_status(drive: str, profile_name: str, state: str, seed: int = 0):
    """A :class:`DriveStatus` as the pipeline publishes it for a drive of ``profile_name``
    (``rig_gear`` / ``rig_chain``): every fault line as a peak, evidence per family, a reason
    when ``state`` is raised."""
    import random

    from agent.profile import load_profile
    from agent.frequencies import fault_frequencies
    from protocols.base import DriveStatus

    rng = random.Random(seed)
    profile = load_profile(ROOT / "config" / "profiles" / f"{profile_name}.toml")
    fe = round(rng.uniform(40.0, 60.0), 3)
    lines = fault_frequencies(profile, fe, 3)
    level = {"normal": "normal", "caution": "caution", "warning": "warning"}[state]
    peaks = []
    for family, items in lines.items():
        for line in items:
            mag = rng.uniform(1e-4, 5e-3)
            peaks.append({"freq_hz": round(line["freq_hz"] + rng.uniform(-0.2, 0.2), 4), "family": family,
                          "k": line["k"], "level": level if family == next(iter(lines)) else "normal",
                          "magnitude": mag, "th2": mag * rng.uniform(1.5, 3), "th3": mag * rng.uniform(3, 6),
                          "target_hz": round(line["freq_hz"], 4), "z": round(rng.uniform(-2, 4), 3)})
    evidence = {family: round(rng.uniform(0, 1.5 if state != "normal" else 0.6), 3) for family in lines}
    evidence["cluster"] = round(rng.uniform(0, 0.5), 3)
    reason = None
    if state != "normal":
        family = next(iter(lines))
        reason = {"path": "cusum", "feature": f"{family} k=1", "families": [family],
                  "evidence": round(rng.uniform(14, 20), 2), "threshold": 13.9,
                  "warning_evidence": round(rng.uniform(0, 10), 2),
                  "freqs_hz": [round(x["freq_hz"], 2) for x in lines[family] if x["k"] == 1]}
    return DriveStatus(drive, state=state, quality="good", spectrum_state=state, cluster_state="normal",
                       fe_hz=fe, load_pct=round(rng.uniform(55, 85), 2), t=time.time(),
                       model=f"{drive}_{round(fe)}hz_80pct", peaks=peaks, cluster_distance2=rng.uniform(0, 9),
                       window=rng.randrange(10**6), extra={"reason": reason, "evidence": evidence, "settling": False})


STATUS_KINDS = (("gear_normal", "rig_gear", "normal"), ("gear_caution", "rig_gear", "caution"),
                ("chain_normal", "rig_chain", "normal"), ("chain_warning", "rig_chain", "warning"))


# --- the router ---------------------------------------------------------------------------------

class Router:
    """``pmsm-agent router`` in a subprocess on an ephemeral loopback port."""

    def __init__(self, log_dir: Path):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.log = log_dir / "router.log"
        with open(self.log, "wb") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "router", "--listen", self.endpoint],
                                         cwd=ROOT, stdout=out, stderr=subprocess.STDOUT,
                                         env={**os.environ, "PYTHONPATH": str(ROOT)})
        end = time.monotonic() + 30
        while "listening on" not in self.log.read_text(errors="replace"):
            if self.proc.poll() is not None or time.monotonic() > end:
                self.stop()
                raise RuntimeError(f"the router did not start: {self.log.read_text(errors='replace')}")
            time.sleep(0.05)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def client(endpoint: str):
    import zenoh

    from protocols.zenoh_sink import zenoh_config

    return zenoh.open(zenoh_config("client", [], [endpoint], FAST))


# --- 1. payload sizes -----------------------------------------------------------------------------

def measure_payloads(endpoint: str, drives_per_gateway: int) -> dict:
    """Bytes of each kind of put of a real ZenohSink (one gateway of ``drives_per_gateway`` drives)."""
    from protocols.zenoh_sink import Providers, ZenohSink, zenoh_config

    sizes: dict[str, list[int]] = {}
    lock = threading.Lock()

    def on_sample(sample):
        key = str(sample.key_expr)
        kind = "health" if key.endswith("/health") else key.rsplit("/", 1)[-1]
        if kind == "state":
            kind = f"state:{json.loads(sample.payload.to_bytes()).get('drive', '').split('-')[0]}"
        with lock:
            sizes.setdefault(kind, []).append(len(sample.payload.to_bytes()))

    watcher = client(endpoint)
    sub = watcher.declare_subscriber("pmsm/**", on_sample)
    names = [f"{STATUS_KINDS[i % len(STATUS_KINDS)][0].replace('_', '')}-{i:03d}" for i in range(drives_per_gateway)]
    names[-2:] = ["nopeaksgear-000", "nopeakschain-001"]  # the same statuses without the spectral peaks
    kind_of = {n: STATUS_KINDS[i % len(STATUS_KINDS)] for i, n in enumerate(names)}
    kind_of.update({"nopeaksgear-000": STATUS_KINDS[1], "nopeakschain-001": STATUS_KINDS[3]})
    # the gateway's own providers, in the shape of agent/runtime/service.py (_diagnostics, _health)
    source_stats = {"opens": 1, "blocks": 123456, "samples": 3086400000, "errors": 0, "crc_errors": 0,
                    "gaps": 0, "reconnects": 0, "last_error": ""}
    providers = Providers(
        diagnostics=lambda d: {"source": source_stats, "queue": 0, "dropped_blocks": 0, "stream_gaps": 0,
                               "learning": False, "library": [f"{d}_50hz_80pct", f"{d}_50hz_60pct"]},
        health=lambda: {"site": "hall-3", "commands": {"accepted": 0, "refused": 0, "refused_by_reason": {}}})
    sink = ZenohSink(zenoh_config("client", [], [endpoint], FAST), "pmsm/hall-3/gw-001", "gw-001", drives=names,
                     providers=providers, period_s=3600.0, diagnostics_period_s=0.5, site="hall-3")
    sink.open()
    try:
        time.sleep(0.3)
        for i, name in enumerate(names):
            _, profile_name, state = kind_of[name]
            status = realistic_status(name, profile_name, state, seed=i)
            if name.startswith("nopeaks"):
                status.peaks = []
            sink.publish(status)
        end = time.monotonic() + 10
        while time.monotonic() < end:
            with lock:
                have = sum(len(v) for k, v in sizes.items() if k.startswith("state:"))
                done = have >= len(names) and "diagnostics" in sizes and "health" in sizes
            if done:
                break
            time.sleep(0.05)
    finally:
        sink.close()
        sub.undeclare()
        watcher.close()
    out = {}
    for label, _, _ in STATUS_KINDS:
        got = sizes.get(f"state:{label.replace('_', '')}", [])
        if not got:
            raise RuntimeError(f"no state of kind {label} arrived")
        out[f"state_{label}"] = sum(got) / len(got)
    out["state_mean"] = sum(out[f"state_{k}"] for k, _, _ in STATUS_KINDS) / len(STATUS_KINDS)
    for label in ("gear", "chain"):
        got = sizes.get(f"state:nopeaks{label}", [])
        if not got:
            raise RuntimeError(f"no state of kind nopeaks{label} arrived")
        out[f"state_{label}_alarmed_without_peaks"] = sum(got) / len(got)
    for kind in ("diagnostics", "health"):
        if kind not in sizes:
            raise RuntimeError(f"no {kind} arrived")
        out[kind] = sum(sizes[kind]) / len(sizes[kind])
    out["health_drives"] = drives_per_gateway
    return out


# --- 2. router throughput ------------------------------------------------------------------------

def _publisher(endpoint: str, sessions: int, drives: int, rate: float, seconds: float, payload: bytes,
               index: int, sent) -> None:
    """A process of ``sessions`` client sessions (gateways) putting ``payload`` at ``rate`` puts/s in all."""
    import zenoh

    ss = [client(endpoint) for _ in range(sessions)]
    keys = [(s, f"pmsm/bench/gw{index:02d}{j:02d}/d{k:03d}/state") for j, s in enumerate(ss) for k in range(drives)]
    time.sleep(0.5)  # the subscriber's declaration reaches everyone
    n, tick, t0 = 0, 0.01, time.monotonic()
    end = t0 + seconds
    while (now := time.monotonic()) < end:
        due = int((now - t0) * rate)
        while n < due:
            s, key = keys[n % len(keys)]
            s.put(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON,
                  congestion_control=zenoh.CongestionControl.DROP)
            n += 1
        time.sleep(tick)
    sent.value = n
    time.sleep(0.5)  # let the last puts drain before the sessions close
    for s in ss:
        s.close()


def measure_router(router: Router, payload_bytes: int, rates: list[float], seconds: float,
                   processes: int, sessions_per_process: int, drives_per_session: int) -> list[dict]:
    """Per total rate: puts sent, samples delivered to one subscriber on ``pmsm/**/state``, and
    the router's CPU seconds over the run."""
    payload = json.dumps({"pad": "x" * max(0, payload_bytes - 11)}).encode()
    count = [0]
    lock = threading.Lock()

    def on_sample(_sample):
        with lock:
            count[0] += 1

    historian = client(router.endpoint)
    sub = historian.declare_subscriber("pmsm/**/state", on_sample)
    ctx = multiprocessing.get_context("spawn")
    rows = []
    try:
        for rate in rates:
            sent = [ctx.Value("q", 0) for _ in range(processes)]
            procs = [ctx.Process(target=_publisher, args=(router.endpoint, sessions_per_process, drives_per_session,
                                                          rate / processes, seconds, payload, i, sent[i]))
                     for i in range(processes)]
            with lock:
                count[0] = 0
            for p in procs:
                p.start()
            time.sleep(0.4)  # sessions opening; count from here (puts start at +0.5 s)
            cpu0, wall0 = cpu_seconds(router.pid), time.monotonic()
            with lock:
                got0 = count[0]
            for p in procs:
                p.join(seconds + 30)
            time.sleep(0.3)
            cpu1, wall1 = cpu_seconds(router.pid), time.monotonic()
            with lock:
                got = count[0] - got0
            for p in procs:
                if p.is_alive():
                    p.kill()
                    p.join()
            total_sent = sum(v.value for v in sent)
            rows.append({"target_msgs_per_s": rate, "sent": total_sent, "delivered": got,
                         "sent_msgs_per_s": total_sent / seconds, "delivered_msgs_per_s": got / seconds,
                         "delivered_fraction": got / total_sent if total_sent else 0.0,
                         "router_cpu_s": cpu1 - cpu0, "router_cpu_fraction_of_core": (cpu1 - cpu0) / (wall1 - wall0),
                         "router_cpu_us_per_msg": 1e6 * (cpu1 - cpu0) / got if got else float("inf"),
                         "payload_bytes": len(payload)})
    finally:
        sub.undeclare()
        historian.close()
    return rows


# --- 3. historian ingest and 4. PostgreSQL ------------------------------------------------------

def state_docs(drives: int, seconds: int):
    """The historian's view of ``drives`` drives putting their state every ``STATE_PERIOD_S`` for
    ``seconds``: ``(key, payload bytes)`` in time order (the sink's JSON, as ZenohSink encodes it)."""
    from protocols.base import QUALITY_CODES, STATE_CODES
    from protocols.zenoh_sink import SCHEMA_VERSION

    base = []
    for i in range(drives):
        _, profile_name, state = STATUS_KINDS[i % len(STATUS_KINDS)]
        st = realistic_status(f"d{i:04d}", profile_name, state, seed=i)
        doc = st.to_json()
        doc.update(state_code=STATE_CODES[st.state], quality_code=QUALITY_CODES[st.quality], schema=SCHEMA_VERSION,
                   agent=f"gw{i // 100:03d}", boot_id="0123456789abcdef")
        base.append((f"pmsm/hall-{i // 1000}/gw{i // 100:03d}/d{i:04d}/state", doc))
    t0 = time.time() - 86400 * 30
    for s in range(seconds):
        for key, doc in base:
            yield key, json.dumps({**doc, "t": t0 + s * STATE_PERIOD_S, "seq": s + 1}).encode()


def measure_ingest(tmp: Path, drives: int, seconds: int) -> dict:
    """The historian's per-sample work on its zenoh thread: ``json.loads`` of the payload, then the
    real :meth:`agent.historian.service.Historian.ingest` (rows, fsync'd buffer append when due)."""
    from agent.historian.config import parse_historian_config
    from agent.historian.service import Historian

    cfg = parse_historian_config({"schema_version": 1, "historian_id": "bench", "state_dir": str(tmp / "historian"),
                                  "trend_period_s": TREND_PERIOD_S, "batch_size": BATCH_SIZE,
                                  "database": {"dsn": "host=127.0.0.1 port=1 dbname=unused"},
                                  "zenoh": {"mode": "client", "connect": ["tcp/127.0.0.1:1"], "prefix": "pmsm"}})
    historian = Historian(cfg)  # never started: no zenoh session, no writer thread
    samples = list(state_docs(drives, seconds))
    append_wall, appends = 0.0, 0
    real_append = historian.buffer.append

    def timed_append(*args):
        nonlocal append_wall, appends
        a0 = time.perf_counter()
        real_append(*args)
        append_wall += time.perf_counter() - a0
        appends += 1

    historian.buffer.append = timed_append
    try:
        cpu0, wall0 = time.process_time(), time.perf_counter()
        rows = sum(historian.ingest(key, json.loads(payload)) for key, payload in samples)
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    finally:
        historian.stop()
    return {"samples": len(samples), "appends": appends, "rows": rows, "cpu_s": cpu, "wall_s": wall,
            "cpu_us_per_sample": 1e6 * cpu / len(samples), "wall_us_per_sample": 1e6 * wall / len(samples),
            "samples_per_cpu_s": len(samples) / cpu, "samples_per_wall_s": len(samples) / wall,
            "append_wall_us": 1e6 * append_wall / max(appends, 1),
            "wall_us_per_sample_without_appends": 1e6 * (wall - append_wall) / len(samples)}


def trend_and_event_rows(drives: int, trend_rows: int, event_rows: int):
    """Rows as :func:`agent.historian.ingest.sample_rows` makes them: trend rows of ``drives``
    drives every ``TREND_PERIOD_S``, and state events with reasons."""
    from agent.historian import ingest

    docs = [(ingest.identity(k, d, "pmsm"), d) for k, d in
            ((k, json.loads(p)) for k, p in state_docs(drives, 1))]
    out, n = [], 0
    t_last = {}
    while n < trend_rows:
        for ident, doc in docs:
            doc = {**doc, "t": doc["t"] + TREND_PERIOD_S * (n // drives)}
            prev = t_last.get(ident)
            rows, t_last[ident] = ingest.sample_rows(ident, doc, prev, trend_period_s=TREND_PERIOD_S,
                                                     received_t=doc["t"])
            out += [r for r in rows if r[0] == "trend"]
            n += 1
            if n >= trend_rows:
                break
    events = tried = 0
    while events < event_rows:
        for ident, doc in docs:
            state = ("caution", "warning", "normal")[tried % 3]
            tried += 1
            doc = {**doc, "state": state, "t": doc["t"] + tried}
            if state == "normal":
                doc["reason"] = None
            elif not doc.get("reason"):
                doc["reason"] = {"path": "cusum", "feature": "gear_driven k=1", "families": ["gear_driven"],
                                 "evidence": 15.2, "threshold": 13.9, "warning_evidence": 3.1,
                                 "freqs_hz": [47.21, 52.79]}
            rows, _ = ingest.sample_rows(ident, doc, ingest.Last(0, 0, None, doc["t"]), trend_period_s=1e9,
                                         received_t=doc["t"])
            for r in rows:
                if r[0] == "event" and events < event_rows:
                    out.append(r)
                    events += 1
            if events >= event_rows:
                break
    return out


def measure_postgres(tmp: Path, drives: int, trend_rows: int, event_rows: int) -> dict:
    """Fill a throw-away PostgreSQL through the historian's writer path; rows/s and bytes per row."""
    sys.path.insert(0, str(ROOT / "tests"))
    from pg_support import PgServer, pg_bindir

    from agent.historian import store
    from agent.historian.buffer import Buffer
    from agent.historian.ingest import Last

    bindir = pg_bindir()
    if bindir is None:
        raise RuntimeError("PostgreSQL's initdb is not installed (Debian: apt-get install postgresql)")
    rows = trend_and_event_rows(drives, trend_rows, event_rows)
    server = PgServer(bindir)
    try:
        server.start()
        dsn = server.create_database()
        buf = Buffer(tmp / "pg-buffer.sqlite3")
        for i in range(0, len(rows), 5000):  # staging only: the historian appends per sample
            buf.append(rows[i:i + 5000], ("", "", ""), Last(0, 0, None, None))
        conn = store.connect(dsn, 5.0)
        store.migrate(conn)
        writer = store.Writer(conn, buf.buffer_id, "bench")
        backend = conn.info.backend_pid
        server_cpu0 = cpu_seconds(backend) if Path(f"/proc/{backend}").exists() else float("nan")
        cpu0, wall0, written, batches = time.process_time(), time.perf_counter(), 0, 0
        while True:  # the historian's writer loop (service._write_loop), without its waits
            batch = buf.oldest(BATCH_SIZE)
            if not batch:
                break
            written += writer.write(batch)
            buf.delete_through(batch[-1][0])
            batches += 1
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        server_cpu = cpu_seconds(backend) - server_cpu0 if Path(f"/proc/{backend}").exists() else float("nan")
        buf.close()
        conn.execute("VACUUM ANALYZE")
        sizes = {}
        for table in ("evidence_trend", "drive_event"):
            count = conn.execute(f"SELECT count(*) FROM {table}").fetchone()[0]
            total, heap = conn.execute(f"SELECT pg_total_relation_size('{table}'), pg_relation_size('{table}')"
                                       ).fetchone()
            sizes[table] = {"rows": count, "total_bytes": total, "heap_bytes": heap,
                            "bytes_per_row": total / count, "heap_bytes_per_row": heap / count}
        # retention as the writer runs it: every trend row is older than 0 days (events are kept)
        trend_count = sizes["evidence_trend"]["rows"]
        del_cpu0, del_wall0 = cpu_seconds(backend), time.perf_counter()
        deleted = store.apply_retention(conn, 0.0, 1e6)["evidence_trend"]
        delete_wall, delete_cpu = time.perf_counter() - del_wall0, cpu_seconds(backend) - del_cpu0
        if deleted != trend_count:
            raise RuntimeError(f"retention deleted {deleted} of {trend_count} trend rows")
        version = conn.execute("SHOW server_version").fetchone()[0]
        conn.close()
    finally:
        server.remove()
    return {"server_version": version, "rows_written": written, "batches": batches, "batch_size": BATCH_SIZE,
            "wall_s": wall, "rows_per_s": written / wall, "historian_cpu_us_per_row": 1e6 * cpu / written,
            "server_backend_cpu_us_per_row": us_per_row(server_cpu, written), "tables": sizes,
            "retention_deleted_rows_per_s": deleted / delete_wall,
            "retention_backend_cpu_us_per_row": us_per_row(delete_cpu, deleted),
            "note": "fsync=off, full_page_writes=off (tests/pg_support.py): the server's disk is not in these figures"}


# --- scaling ---------------------------------------------------------------------------------------

def scale(fig: dict, drives: int = 10_000, gateways: int = 100, routers=(1, 3, 10),
          trend_days: float = 90.0, events_days: float = 3650.0) -> dict:
    """The plant's figures from the measured ones (bases in docs/scale.md)."""
    p = fig["payloads"]
    overhead = fig["wire_overhead_bytes_per_msg"]
    ch_typ = CHANGES_PER_DRIVE_HOUR["typical"] / 3600.0
    state_rate = drives * (1.0 / STATE_PERIOD_S + ch_typ)
    diag_rate = drives / DIAGNOSTICS_PERIOD_S
    health_rate = gateways / DIAGNOSTICS_PERIOD_S
    in_rate = state_rate + diag_rate + health_rate
    in_bytes = (state_rate * (p["state_mean"] + overhead) + diag_rate * (p["diagnostics"] + overhead)
                + health_rate * (p["health"] + overhead))
    state_bytes = state_rate * (p["state_mean"] + overhead)
    measured = [r for r in fig["router"] if r["delivered"] > 0]

    def router_cores(msgs_in_plus_out: float) -> float:
        """Cores for a router forwarding ``msgs_in_plus_out / 2`` messages/s, at the CPU per message
        measured at the nearest delivered rate (zenoh batches more at higher rates)."""
        near = min(measured, key=lambda r: abs(math.log(r["delivered_msgs_per_s"] / max(msgs_in_plus_out / 2, 1))))
        return msgs_in_plus_out / 2 * near["router_cpu_us_per_msg"] / 1e6

    per_router = {}
    for k in routers:
        # gateways spread evenly; the historian hangs on one router, which forwards every state to it
        # (the others forward their share of states to it over the mesh)
        other = 0.0 if k == 1 else state_rate * (k - 1) / k
        hist_router_msgs = in_rate / k + other + state_rate
        plain_router_msgs = in_rate / k + (state_rate / k if k > 1 else 0.0)
        per_router[k] = {"gateways_per_router": gateways / k,
                         "in_msgs_per_s": in_rate / k, "in_bytes_per_s": in_bytes / k,
                         "historian_router_msgs_per_s_in_plus_out": hist_router_msgs,
                         "historian_router_bytes_per_s_out": state_bytes,
                         "other_router_msgs_per_s_in_plus_out": plain_router_msgs,
                         "historian_router_cores": router_cores(hist_router_msgs),
                         "other_router_cores": router_cores(plain_router_msgs)}
    t_bytes = fig["postgres"]["tables"]["evidence_trend"]["bytes_per_row"]
    e_bytes = fig["postgres"]["tables"]["drive_event"]["bytes_per_row"]
    trend_per_day = drives * 86400.0 / TREND_PERIOD_S
    events_per_day = {k: drives * v for k, v in EVENTS_PER_DRIVE_DAY.items()}
    trend_rows_per_s = trend_per_day / 86400.0
    ingest_cores = state_rate / fig["ingest"]["samples_per_cpu_s"]
    ingest_wall = state_rate / fig["ingest"]["samples_per_wall_s"]
    writer_cores = trend_rows_per_s * fig["postgres"]["historian_cpu_us_per_row"] / 1e6
    pg_row = fig["postgres"]["server_backend_cpu_us_per_row"]
    pg_cores = None if pg_row is None else trend_rows_per_s * pg_row / 1e6
    ing = fig["ingest"]
    # one historian's ingest thread: wall time per drive-second (a parse per state, an fsync'd append per trend row)
    ingest_s_per_drive_s = (ing["wall_us_per_sample_without_appends"] / STATE_PERIOD_S
                            + ing["append_wall_us"] / TREND_PERIOD_S) / 1e6
    return {
        "drives": drives, "gateways": gateways,
        "msgs_per_s": {"state": state_rate, "diagnostics": diag_rate, "health": health_rate, "total": in_rate},
        "bytes_per_s": {"state": state_bytes, "total": in_bytes},
        "routers": per_router,
        "rows_per_day": {"trend": trend_per_day, "events": events_per_day},
        "storage_gb": {
            "trend_at_retention": trend_per_day * trend_days * t_bytes / 1e9,
            "events_per_year": {k: v * 365 * e_bytes / 1e9 for k, v in events_per_day.items()},
            "events_at_retention": {k: v * events_days * e_bytes / 1e9 for k, v in events_per_day.items()},
            "trend_written_per_year": trend_per_day * 365 * t_bytes / 1e9},
        "historian": {"trend_rows_per_s": trend_rows_per_s, "ingest_samples_per_s": state_rate,
                      "ingest_cores": ingest_cores, "ingest_wall_fraction": ingest_wall,
                      "writer_cores": writer_cores, "postgres_cores": pg_cores,
                      "writer_headroom": fig["postgres"]["rows_per_s"] / trend_rows_per_s,
                      "ingest_wall_s_per_drive_s": ingest_s_per_drive_s,
                      "drives_per_historian": 1.0 / ingest_s_per_drive_s,
                      "historians_needed": math.ceil(drives * ingest_s_per_drive_s / 0.7)},
    }


# --- driver ------------------------------------------------------------------------------------------

SIZES = {
    "full": {"drives_per_gateway": 100, "rates": [2000, 5000, 10000, 20000, 40000, 60000], "seconds": 4.0,
             "processes": 2, "sessions": 5, "drives_per_session": 100, "ingest_drives": 1000,
             "ingest_seconds": 20, "trend_rows": 100_000, "event_rows": 10_000},
    "smoke": {"drives_per_gateway": 8, "rates": [200, 500], "seconds": 1.0, "processes": 1, "sessions": 2,
              "drives_per_session": 4, "ingest_drives": 20, "ingest_seconds": 12, "trend_rows": 500,
              "event_rows": 50},
}


def run(size: str = "full") -> dict:
    """Every measurement at ``size`` (``full`` or ``smoke``), then the scaled plant; returns the figures."""
    s = SIZES[size]
    fig = {"date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "size": size,
           "machine": {"cpus": os.cpu_count(), "cpu": _cpu_name(), "python": platform.python_version(),
                       "kernel": platform.release()}}
    with tempfile.TemporaryDirectory(prefix="pmsm-bench-plant-") as tmp_name:
        tmp = Path(tmp_name)
        router = Router(tmp)
        try:
            fig["payloads"] = measure_payloads(router.endpoint, s["drives_per_gateway"])
            fig["router"] = measure_router(router, round(fig["payloads"]["state_mean"]), s["rates"], s["seconds"],
                                           s["processes"], s["sessions"], s["drives_per_session"])
        finally:
            router.stop()
        fig["ingest"] = measure_ingest(tmp, s["ingest_drives"], s["ingest_seconds"])
        fig["postgres"] = measure_postgres(tmp, min(s["ingest_drives"], 1000), s["trend_rows"], s["event_rows"])
    lossless = [r for r in fig["router"] if r["delivered_fraction"] >= 0.99 and r["router_cpu_s"] > 0]
    best = lossless or fig["router"]
    # a message in and out counts once: the router's CPU per delivered message at the busiest lossless rate
    top = max(best, key=lambda r: r["delivered_msgs_per_s"])
    fig["router_msgs_per_core_s"] = 1e6 / top["router_cpu_us_per_msg"]
    fig["router_basis"] = (f"{top['delivered_msgs_per_s']:.0f} msgs/s delivered ({top['delivered_fraction']:.3f} of "
                           f"those sent) at {top['router_cpu_fraction_of_core']:.2f} of a core")
    # zenoh's frame and message headers plus the key (the key is sent in full on a put without a
    # declared publisher): an estimate, stated in docs/scale.md
    fig["wire_overhead_bytes_per_msg"] = 60
    fig["plant"] = scale(fig)
    return fig


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def table(fig: dict) -> str:
    """The figures as a markdown table."""
    p, pg, ing, plant = fig["payloads"], fig["postgres"], fig["ingest"], fig["plant"]
    lines = [f"Measured {fig['date_utc']} UTC on {fig['machine']['cpus']} x {fig['machine']['cpu']} ({fig['size']})", "",
             "| figure | value | basis |", "|---|---|---|"]
    for label, _, _ in STATUS_KINDS:
        lines.append(f"| state payload, {label} | {p[f'state_{label}']:.0f} B | real ZenohSink put |")
    lines += [f"| diagnostics payload | {p['diagnostics']:.0f} B | per drive, every {DIAGNOSTICS_PERIOD_S:g} s |",
              f"| state payload without peaks, gear / chain alarmed | {p['state_gear_alarmed_without_peaks']:.0f} / "
              f"{p['state_chain_alarmed_without_peaks']:.0f} B | the same statuses, peaks = [] |",
              f"| health payload ({p['health_drives']} drives) | {p['health']:.0f} B | per gateway, every "
              f"{DIAGNOSTICS_PERIOD_S:g} s |"]
    for r in fig["router"]:
        lines.append(f"| router at {r['target_msgs_per_s']:.0f} msgs/s asked | {r['delivered_msgs_per_s']:.0f} delivered/s, "
                     f"{r['delivered_fraction']:.3f} delivered, {r['router_cpu_fraction_of_core']:.2f} core, "
                     f"{r['router_cpu_us_per_msg']:.1f} us/msg | {r['payload_bytes']} B puts, one subscriber |")
    lines += [f"| router msgs per core-second | {fig['router_msgs_per_core_s']:.0f} | {fig['router_basis']} |",
              f"| historian ingest | {ing['cpu_us_per_sample']:.1f} us CPU, {ing['wall_us_per_sample']:.1f} us wall "
              f"per sample | {ing['samples']} samples, {ing['appends']} fsync'd appends |",
              f"| PostgreSQL writer path | {pg['rows_per_s']:.0f} rows/s | batches of {pg['batch_size']}, "
              f"{pg['rows_written']} rows |",
              f"| retention delete (apply_retention) | {pg['retention_deleted_rows_per_s']:.0f} rows/s, "
              f"{per_row_text(pg['retention_backend_cpu_us_per_row'], pg['tables']['evidence_trend']['rows'])} backend "
              f"CPU per row | every trend row, chunks of 10 000 |",
              f"| historian CPU per row written | {pg['historian_cpu_us_per_row']:.1f} us | buffer read + psycopg |",
              f"| PostgreSQL backend CPU per row | {per_row_text(pg['server_backend_cpu_us_per_row'], pg['rows_written'])} | "
              f"/proc of the backend |"]
    for t, v in pg["tables"].items():
        lines.append(f"| {t} bytes per row | {v['bytes_per_row']:.0f} B (heap {v['heap_bytes_per_row']:.0f}) | "
                     f"{v['rows']} rows, indexes included |")
    lines += ["", f"Plant: {plant['drives']} drives on {plant['gateways']} gateways", "",
              "| routers | gateways each | in msgs/s each | in MB/s each | historian's router msgs/s (in+out) | its cores |",
              "|---|---|---|---|---|---|"]
    for k, r in plant["routers"].items():
        lines.append(f"| {k} | {r['gateways_per_router']:.0f} | {r['in_msgs_per_s']:.0f} | {r['in_bytes_per_s'] / 1e6:.2f} | "
                     f"{r['historian_router_msgs_per_s_in_plus_out']:.0f} | {r['historian_router_cores']:.2f} |")
    h, st = plant["historian"], plant["storage_gb"]
    lines += ["", f"| rows/day trend | {plant['rows_per_day']['trend']:.3g} |",
              f"| trend GB at 90 days | {st['trend_at_retention']:.1f} |",
              f"| events GB/year (typical) | {st['events_per_year']['typical']:.3f} |",
              f"| historian ingest cores | {h['ingest_cores']:.2f} (wall {h['ingest_wall_fraction']:.2f}) |",
              f"| writer cores / PostgreSQL cores | {h['writer_cores']:.3f} / "
              f"{'n/a' if h['postgres_cores'] is None else format(h['postgres_cores'], '.3f')} |",
              f"| drives one historian ingests (ingest thread 100 % busy) | {h['drives_per_historian']:.0f} |",
              f"| historians for the plant (each at most 70 % busy) | {h['historians_needed']} |"]
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes (the test's form, about 20 s)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="where the JSON goes")
    args = ap.parse_args(argv)
    on_main = threading.current_thread() is threading.main_thread()
    if on_main:  # SIGTERM runs the clean-ups (router, PostgreSQL) before exiting
        before = signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    try:
        fig = run("smoke" if args.smoke else "full")
    finally:
        if on_main:
            signal.signal(signal.SIGTERM, before)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(fig, indent=1, default=str) + "\n")
    print(table(fig))
    return fig


if __name__ == "__main__":
    main()
