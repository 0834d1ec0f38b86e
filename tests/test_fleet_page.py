"""The historian's fleet page (agent/historian/page.py) against a real PostgreSQL server (the ``pg``
fixture: tests/pg_support.py): rows written by the historian itself from drive-state samples, the
page and /fleet.json read over HTTP on an ephemeral loopback port, and rendered by headless Chromium."""

import gzip
import json
import math
import re
import shutil
import subprocess
import time
import urllib.error
import urllib.request

import psycopg
import pytest

from agent.errors import InputError
from agent.historian import store
from agent.historian.config import parse_historian_config
from agent.historian.page import ALARMS_SHOWN, CAUTION_LEVEL, fleet_snapshot
from agent.historian.service import Historian

HOUR = 3600.0
STEP_S = 300.0  #: one sample every 5 min of the drives' time
TREND_POINTS = 60
FAMILIES = ("bearing_outer", "cluster", "gear_driven", "gear_driving")
REASON_GEAR = {"path": "cusum", "feature": "gear_driven k=1", "families": ["gear_driven"], "evidence": 5.6,
               "threshold": 4.2}
REASON_GROSS = {"path": "gross", "feature": "cluster", "families": ["cluster"], "z": 11.2, "threshold": 6.0}
REASON_ESCAPED = {"path": "cusum", "feature": "<b>bpfo</b> & \"sidebands\"", "families": ["bearing_outer"],
                  "evidence": 4.9, "threshold": 4.2}


def page_config(tmp_path, dsn, **page):
    """A historian config serving the page on an ephemeral loopback port (zenoh is never opened here:
    the tests hand samples to ``Historian.ingest``)."""
    data = {"schema_version": 1, "historian_id": "page-test", "state_dir": str(tmp_path / "state"),
            "trend_period_s": 60.0, "database": {"dsn": dsn, "connect_timeout_s": 2.0, "retry_initial_s": 0.2,
                                                   "retry_max_s": 1.0},
            "zenoh": {"connect": ["tcp/127.0.0.1:7447"]},
            "page": {"enabled": True, "host": "127.0.0.1", "port": 0, "trend_points": TREND_POINTS, **page}}
    return parse_historian_config(data, tmp_path / "historian.toml")


def evidence_at(drive: str, age_h: float) -> dict:
    """Each drive's evidence per family ``age_h`` hours ago (1 = the caution threshold); none
    for d9, which has no model yet."""
    if drive == "d9":
        return {}
    wobble = 0.5 + 0.5 * math.sin(age_h * 1.7 + int(drive[1:]))  # a healthy drive's evidence moves a little
    ev = {"bearing_outer": round(0.08 + 0.1 * wobble, 3), "cluster": 0.05, "gear_driven": round(0.3 * wobble, 3),
          "gear_driving": round(0.15 + 0.05 * wobble, 3)}
    if drive == "d3":  # gear_driven creeps up over the last 2 h and crosses 1 about 37 min ago
        ev["gear_driven"] = round(0.2 + 1.4 * max(0.0, (2.0 - age_h) / 2.0) ** 1.5, 3)
    if drive == "d1" and age_h < 0.7:  # a gross cluster jump 40 min ago
        ev["cluster"] = 3.2
    if drive == "d6" and 2.5 < age_h < 3.0:  # a bearing episode 3 h ago that cleared
        ev["bearing_outer"] = 1.4
    return ev


def state_at(drive: str, age_h: float, ev: dict) -> tuple[str, str, dict | None]:
    """(state, quality, reason) of the stand-in drive at that time."""
    if drive == "d1" and age_h < 0.7:
        return "warning", "good", REASON_GROSS
    if drive == "d3" and ev["gear_driven"] >= 1.0:
        return "caution", "good", REASON_GEAR
    if drive == "d6" and ev["bearing_outer"] >= 1.0:
        return "caution", "good", REASON_ESCAPED
    if drive == "d4":
        return "normal", "learning", None
    if drive == "d9":
        return "normal", "no_model", None
    if drive == "d5" and age_h < 1.0:
        return "normal", "stale", None
    return "normal", "good", None


#: (key, drive, hours of history, hours since its last sample)
PLANT = [("pmsm/hall-a/gw1/d1/state", "d1", 26, 0), ("pmsm/hall-a/gw1/d2/state", "d2", 26, 0),
         ("pmsm/hall-a/gw1/d3/state", "d3", 26, 0), ("pmsm/gw2/d4/state", "d4", 26, 0),
         ("pmsm/gw2/d5/state", "d5", 26, 0), ("pmsm/gw2/d6/state", "d6", 8, 0),
         ("pmsm/gw2/d9/state", "d9", 26, 0),  # no model: no trend rows, and one state event 26 h ago
         ("pmsm/gw3/d7/state", "d7", 26, 0.4),  # silent for 24 min
         ("pmsm/gw3/d8/state", "d8", 2, 72)]  # not heard from for 3 days


def publish_plant(h: Historian, now: float) -> int:
    """Hand the plant's samples, oldest first per drive, to the historian as if each had arrived
    at its time ``t``; returns their count."""
    n = 0
    for key, drive, hours, silent_h in PLANT:
        for k in range(round(hours * HOUR / STEP_S) + 1):
            age = silent_h + hours - k * STEP_S / HOUR
            ev = evidence_at(drive, age)
            state, quality, reason = state_at(drive, age, ev)
            t = now - age * HOUR
            h.ingest(key, {"drive": drive, "agent": key.split("/")[-3], "t": t, "state": state, "quality": quality,
                           "reason": reason, "evidence": ev, "fe_hz": 50.0, "load_pct": 75.0,
                           "model": "" if drive == "d9" else "op-50hz"}, received_t=t)
            n += 1
    return n


@pytest.fixture(scope="module")
def plant(pg, tmp_path_factory):
    """A historian with the fleet page on, after it wrote the plant's history; yields (historian, now)."""
    tmp_path = tmp_path_factory.mktemp("fleet")
    h = Historian(page_config(tmp_path, pg.create_database()))
    h.start()
    now = time.time()
    try:
        n = publish_plant(h, now)
        end = time.monotonic() + 60
        while not (h.counters["samples"] == n and h.buffer.count() == 0):
            assert time.monotonic() < end, "the historian did not write the plant's history in 60 s"
            time.sleep(0.1)
        yield h, now
    finally:
        h.stop()


def get(url: str, gzipped: bool = False) -> tuple[int, dict, bytes]:
    request = urllib.request.Request(url, headers={"Accept-Encoding": "gzip"} if gzipped else {})
    try:
        with urllib.request.urlopen(request, timeout=30) as r:
            status, headers, body = r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as err:
        status, headers, body = err.code, dict(err.headers), err.read()
    return status, headers, gzip.decompress(body) if headers.get("Content-Encoding") == "gzip" else body


def card_of(page: str, drive: str) -> str:
    """The card of ``drive`` (its full name) on the page."""
    return page.split(f'data-drive="{drive}"', 1)[1].split('<div class="card', 1)[0]


def svg_of(page: str, drive: str, family: str) -> str:
    """The trend SVG of ``family`` in the card of ``drive``."""
    return card_of(page, drive).split(f'data-family="{family}"', 1)[1].split("</svg>", 1)[0]


def above_caution_line(svg: str) -> int:
    """How many points of the evidence curve lie above the dashed caution line (SVG y grows downwards)."""
    line_y = int(re.search(r'class="caution-line"[^>]* y1="(\d+)"', svg).group(1))
    path = re.search(r'class="evidence" d="([^"]+)"', svg).group(1)
    return sum(int(y) < line_y for y in re.findall(r"[ML]\d+ (\d+)", path))


# --- tests ---------------------------------------------------------------------------------------

def test_fleet_json_worst_first_with_trends_and_reasons(plant):
    h, now = plant
    url = h.status()["page"]["url"]
    assert re.fullmatch(r"http://127\.0\.0\.1:\d+/", url)
    status, headers, body = get(url + "fleet.json")
    assert status == 200 and headers["Content-Type"] == "application/json"
    doc = json.loads(body)
    order = [(d["site"], d["gateway"], d["drive"]) for d in doc["drives"]]
    # groups by their worst drive: warning, then the silent drive's gateway, then the poor data quality
    assert order == [("hall-a", "gw1", "d1"), ("hall-a", "gw1", "d3"), ("hall-a", "gw1", "d2"),
                     ("", "gw3", "d7"), ("", "gw2", "d5"), ("", "gw2", "d9"), ("", "gw2", "d4"), ("", "gw2", "d6")]
    by_name = {d["drive"]: d for d in doc["drives"]}
    looks = [(by_name[n]["state"], by_name[n]["quality"], by_name[n]["silent"])
             for n in ("d1", "d3", "d7", "d5", "d9", "d4")]
    assert looks == [("warning", "good", False), ("caution", "good", False), ("normal", "good", True),
                     ("normal", "stale", False), ("normal", "no_model", False), ("normal", "learning", False)]
    # d9 wrote nothing since its first sample 26 h ago, but the historian heard it just now: not silent
    assert by_name["d9"]["last_t"] == pytest.approx(now) and by_name["d9"]["trend"] == {"t": [], "evidence": {}}
    assert by_name["d1"]["reason"] == REASON_GROSS and by_name["d3"]["reason"] == REASON_GEAR
    assert by_name["d2"]["reason"] is None
    assert abs(by_name["d1"]["state_since"] - (now - 0.7 * HOUR)) < 2 * STEP_S
    assert [d["drive"] for d in doc["offline"]] == ["d8"]
    assert doc["counts"] == {"drives": 9, "normal": 6, "caution": 1, "warning": 1, "silent": 1, "poor_quality": 3,
                             "offline": 1}
    for d in (d for d in doc["drives"] if d["drive"] != "d9"):
        trend = d["trend"]
        assert sorted(trend["evidence"]) == list(FAMILIES), d["drive"]
        full_day = d["drive"] not in ("d6", "d7")  # d6 began 8 h ago, d7 fell silent
        assert (len(trend["t"]) == TREND_POINTS) if full_day else (0 < len(trend["t"]) < TREND_POINTS), d["drive"]
        assert trend["t"] == sorted(trend["t"]) and all(len(v) == len(trend["t"]) for v in trend["evidence"].values())
    assert max(by_name["d3"]["trend"]["evidence"]["gear_driven"]) > CAUTION_LEVEL > max(
        max(v) for v in by_name["d2"]["trend"]["evidence"].values())
    # the alarms of the window, newest first: what raised each one, and whether it is over
    alarms = {a["drive"]: a for a in doc["alarms"]}
    assert [a["drive"] for a in doc["alarms"]] == ["d3", "d1", "d6"]
    assert alarms["d1"]["end"] is None and alarms["d1"]["state"] == "warning"
    assert alarms["d1"]["reasons"] == [REASON_GROSS]
    assert alarms["d6"]["end"] is not None and alarms["d6"]["reasons"] == [REASON_ESCAPED]
    assert by_name["d6"]["alarms"] == [{k: alarms["d6"][k] for k in ("start", "end", "state")}]


def test_fleet_page_html(plant):
    h, now = plant
    status, headers, body = get(h.status()["page"]["url"], gzipped=True)
    assert status == 200 and headers["Content-Type"] == "text/html; charset=utf-8"
    assert headers["Content-Encoding"] == "gzip" and "script-src" not in headers["Content-Security-Policy"]
    page = body.decode()
    assert '<meta http-equiv="refresh" content="30">' in page and "<script" not in page
    cards = re.findall(r'<div class="card (\w+)" data-drive="([^"]+)"', page)
    assert cards == [("warning", "hall-a/gw1/d1"), ("caution", "hall-a/gw1/d3"), ("normal", "hall-a/gw1/d2"),
                     ("silent", "gw3/d7"), ("normal", "gw2/d5"), ("normal", "gw2/d9"), ("normal", "gw2/d4"),
                     ("normal", "gw2/d6")]
    assert re.findall(r'<h2 class="group">([^<]+)', page) == ["hall-a / gw1 ", "gw3 ", "gw2 "]
    # one plot per family and drive, each with its caution line
    assert page.count('<svg class="trend"') == page.count('class="caution-line"') == 7 * len(FAMILIES)
    assert above_caution_line(svg_of(page, "hall-a/gw1/d3", "gear_driven")) > 0
    assert above_caution_line(svg_of(page, "hall-a/gw1/d1", "cluster")) > 0
    assert all(above_caution_line(svg_of(page, "hall-a/gw1/d2", f)) == 0 for f in FAMILIES)
    assert 'class="alarm-band"' in svg_of(page, "gw2/d6", "bearing_outer")  # the cleared episode, shaded
    assert 'class="alarm-band"' not in svg_of(page, "hall-a/gw1/d2", "cluster")
    # beside the cards: the alarms raised now, worst first, then those cleared in the window
    side = page.split("<aside>", 1)[1]
    assert "Raised now (2)" in side and "Cleared, last 24 h (1)" in side
    assert re.findall(r'<div class="alarm (\w+)">.*?<b>([^<]+)</b>', side) == [
        ("warning", "hall-a/gw1/d1"), ("caution", "hall-a/gw1/d3"), ("caution", "gw2/d6")]
    # the reasons, escaped; the drive not heard from in the window is listed without plots
    assert "why: path=gross feature=cluster z=11.2 threshold=6.0" in page
    assert "&lt;b&gt;bpfo&lt;/b&gt; &amp; &quot;sidebands&quot;" in page and "<b>bpfo" not in page
    assert "no evidence trend in the last 24 h" in card_of(page, "gw2/d9") and "<svg" not in card_of(page, "gw2/d9")
    assert "Not heard from in the last 24 h (1)" in page and "gw3/d8" in page
    assert 'data-drive="gw3/d8"' not in page
    assert "historian page-test: database connected" in page


def test_fleet_page_in_headless_chromium(plant, tmp_path):
    """Chromium loads the page from the historian: the DOM has every drive and plot, and the
    screenshot is not blank (tmp_path/fleet.png)."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no headless Chromium installed (apt-get install -y chromium); .ci/run installs it")
    h, _ = plant
    url = h.status()["page"]["url"]
    flags = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp_path / 'chromium'}", "--window-size=1280,1600"]
    dom = subprocess.run(flags + ["--dump-dom", url], capture_output=True, text=True, timeout=120).stdout
    assert len(re.findall(r'<div class="card \w+" data-drive=', dom)) == 8
    assert dom.count('class="caution-line"') == 7 * len(FAMILIES) and "ongoing" in dom
    shot = tmp_path / "fleet.png"
    subprocess.run(flags + [f"--screenshot={shot}", url], capture_output=True, timeout=120, check=False)
    assert shot.exists() and shot.stat().st_size > 50_000  # a blank page is a few kB


def test_other_paths_and_an_unreachable_database(plant, tmp_path):
    h, _ = plant
    status, _, body = get(h.status()["page"]["url"] + "drives")
    assert status == 404 and b"/fleet.json" in body
    closed = f"host=127.0.0.1 port={h.cfg.database.dsn.split('port=')[1].split()[0]} user=nobody dbname=none"
    down = Historian(page_config(tmp_path, closed))
    down.page.start()
    try:
        status, _, body = get(down.page.url)
        assert status == 503 and "cannot read the database (database.dsn)" in body.decode()
        assert '<meta http-equiv="refresh"' in body.decode()
        status, _, body = get(down.page.url + "fleet.json")
        assert status == 503 and "database.dsn" in json.loads(body)["error"]
    finally:
        down.stop()


def test_a_taken_port_is_named_and_recording_goes_on(plant, pg, tmp_path):
    """A page whose address is taken is reported (naming the keys) and retried; the historian
    records meanwhile."""
    h, now = plant
    port = int(h.status()["page"]["url"].rsplit(":", 1)[1].strip("/"))
    other = Historian(page_config(tmp_path, pg.create_database(), port=port))
    other.start()
    try:
        page = other.status()["page"]
        assert page["url"] is None
        assert f"page.host, page.port: cannot serve the fleet page on 127.0.0.1:{port}" in page["error"]
        assert "the fleet page is not served (page.host, page.port)" in other.status_line()
        assert other.ingest("pmsm/gw9/d9/state", {"t": now, "state": "normal", "quality": "good"}) == 2
    finally:
        other.stop()


@pytest.mark.parametrize("page, message", [
    ({"port": 70000}, "page.port: must be <= 65535"),
    ({"host": "127.0.0.1:8470"}, "page.host: '127.0.0.1:8470': an IP address or host name, e.g. '127.0.0.1' "
                                 "(the port is page.port)"),
    ({"host": "::1"}, None),
    ({"host": "historian.plant.local"}, None),
    ({"trend_points": 1}, "page.trend_points: must be >= 2"),
    ({"refresh": 10}, "page.refresh: unknown key"),
])
def test_bad_page_keys_are_named(tmp_path, page, message):
    if message is None:
        page_config(tmp_path, "dbname=x", **page)
        return
    with pytest.raises(InputError, match=re.escape(message)):
        page_config(tmp_path, "dbname=x", **page)


class CountingConnection:
    """A connection that counts the queries run through it."""

    def __init__(self, conn):
        self.conn, self.queries = conn, 0

    def execute(self, *args, **kwargs):
        self.queries += 1
        return self.conn.execute(*args, **kwargs)


def test_hundreds_of_drives_take_three_queries_and_bounded_points(pg, tmp_path):
    """300 drives with a day of trend (a row every 2 min): three queries in all, at most
    ``trend_points`` points per drive, read and rendered in seconds."""
    dsn = pg.create_database()
    with psycopg.connect(dsn, autocommit=True) as conn:
        store.migrate(conn)
        conn.execute("INSERT INTO drive(site, gateway, drive) SELECT 'site-' || (g % 3), 'gw' || (g % 25), "
                     "'d' || g FROM generate_series(1, 300) g")
        conn.execute("INSERT INTO drive_event(drive_id, t, kind, state, quality, reason) SELECT drive_id, "
                     "now() - interval '5 hours', 'state', (drive_id % 50 = 0)::int, 0, "
                     "CASE WHEN drive_id % 50 = 0 THEN '{\"path\": \"cusum\"}'::jsonb END FROM drive")
        conn.execute("INSERT INTO evidence_trend(drive_id, t, state, quality, evidence) SELECT drive_id, "
                     "now() - make_interval(secs => k * 120), 0, 0, jsonb_build_object('gear_driven', "
                     "round((k % 97)::numeric / 80, 3), 'cluster', 0.1) FROM drive, generate_series(0, 719) k")
        conn.execute("ANALYZE")
    cfg = page_config(tmp_path, dsn).page
    with store.connect(dsn, 5) as conn:
        counting = CountingConnection(conn)
        started = time.monotonic()
        snap = fleet_snapshot(counting, cfg)
        took = time.monotonic() - started
    assert counting.queries == 3
    assert len(snap["drives"]) == 300 and snap["counts"]["caution"] == 6
    assert all(0 < len(d["trend"]["t"]) <= TREND_POINTS for d in snap["drives"])
    assert took < 20, f"the fleet's data took {took:.1f} s"
    from agent.historian.page import render_html

    html = render_html(snap, {"historian": "h", "database": {"state": "connected"}, "buffered": 0})
    assert html.count('<svg class="trend"') == 600
    assert len(re.findall(r'class="alarm (caution|warning)"', html)) == min(6, ALARMS_SHOWN)
