"""The fleet page: every drive's state, quality, evidence trend and recent alarms, from PostgreSQL.

The historian serves it over HTTP (standard library ``http.server``, one thread per request) when
``page.enabled``, on ``page.host``:``page.port``:

* ``/``: one HTML page, no script; it reloads itself every ``page.refresh_s`` (meta refresh).
  Drives are grouped by site/gateway, worst first (warning, caution, silent, poor data quality,
  normal), each with one small inline SVG per fault family: the evidence over the last
  ``page.window_h`` hours, the dashed caution line at evidence 1 (docs/historian.md, the
  ``evidence_trend`` table), and the caution/warning periods shaded. Drives not heard from in
  the whole window are listed at the end, without plots. Beside them, the alarms raised now
  (worst first) and those cleared in the window (newest first), with their reasons.
* ``/fleet.json``: the same data.

The data is read with three queries whatever the number of drives (:func:`store.fleet_now`,
:func:`store.trend_samples`, :func:`store.plant_alarms`), at most once every
:data:`SNAPSHOT_MAX_AGE_S` however many screens ask; the trend has at most ``page.trend_points``
points per drive.
"""

from __future__ import annotations

import gzip
import html
import json
import logging
import socket
import socketserver
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from agent.errors import InputError
from agent.historian import store
from agent.historian.config import HistorianConfig, PageCfg

log = logging.getLogger("pmsm-agent.historian")
SNAPSHOT_MAX_AGE_S = 5.0  #: requests within this long of the last read share it, s
STATEMENT_TIMEOUT_MS = 20_000  #: the page's queries are cancelled after this long
CAUTION_LEVEL = 1.0  #: evidence is CUSUM / caution threshold: 1 is where caution is raised
ALARMS_SHOWN = 30  #: the page lists this many raised and this many cleared alarms; /fleet.json has them all
#: the order of "worst" for data quality (codes are CONTRACT section 6's, not an order of badness)
QUALITY_SEVERITY = {"bad_input": 4, "stale": 3, "no_model": 2, "learning": 1, "good": 0}


# --- the data ------------------------------------------------------------------------------------

def _name(d: dict) -> str:
    return "/".join(x for x in (d["site"], d["gateway"], d["drive"]) if x)


def _severity(d: dict) -> tuple:
    """Sort key, worst first when reversed: state, then silent, then data quality."""
    return (d["state_code"] if d["state_code"] is not None else -1, d["silent"],
            QUALITY_SEVERITY.get(d["quality"], 0))


def fleet_snapshot(conn, cfg: PageCfg, heard: dict | None = None, now: float | None = None) -> dict:
    """The fleet page's data (``/fleet.json``): drives worst first, grouped by site/gateway.

    ``heard`` maps (site, gateway, drive) to when this historian last received a sample of the
    drive: a drive without evidence (no model yet) writes no row while nothing changes."""
    now = time.time() if now is None else now
    heard = heard or {}
    since = now - cfg.window_h * 3600.0
    drives = store.fleet_now(conn)
    trends = store.trend_samples(conn, since, now, cfg.trend_points)
    alarms = sorted(store.plant_alarms(conn, since, now), key=lambda a: a["start"], reverse=True)
    alarms_of: dict[tuple, list] = {}
    for a in alarms:
        alarms_of.setdefault((a["site"], a["gateway"], a["drive"]), []).append(a)
    active, offline = [], []
    for d in drives:
        ident = (d["site"], d["gateway"], d["drive"])
        d["last_t"] = max((t for t in (d["last_t"], heard.get(ident)) if t is not None), default=None)
        samples = trends.get(ident, [])
        families = sorted({f for _, ev in samples for f in ev} | set(d["evidence"]))
        d["silent"] = d["last_t"] is None or now - d["last_t"] > cfg.silent_after_s
        d["trend"] = {"t": [t for t, _ in samples],
                      "evidence": {f: [ev.get(f) for _, ev in samples] for f in families}}
        d["alarms"] = [{k: a[k] for k in ("start", "end", "state")} for a in alarms_of.get(ident, [])]
        (active if d["last_t"] is not None and d["last_t"] >= since else offline).append(d)
    groups: dict[tuple[str, str], list] = {}
    for d in sorted(active, key=lambda d: (tuple(-x for x in _severity(d)), _name(d))):
        groups.setdefault((d["site"], d["gateway"]), []).append(d)
    ordered = sorted(groups.values(), key=lambda ds: (tuple(-x for x in _severity(ds[0])), _name(ds[0])))
    counts = {"drives": len(drives), **{s: sum(d["state"] == s for d in active) for s in store.STATE_CODES},
              "silent": sum(d["silent"] for d in active), "poor_quality": sum(d["quality"] != "good" for d in active),
              "offline": len(offline)}
    return {"since": since, "until": now, "window_h": cfg.window_h, "refresh_s": cfg.refresh_s,
            "trend_points": cfg.trend_points, "caution_level": CAUTION_LEVEL, "silent_after_s": cfg.silent_after_s,
            "counts": counts, "drives": [d for ds in ordered for d in ds],
            "offline": sorted(offline, key=lambda d: (-(d["last_t"] or 0), _name(d))), "alarms": alarms}


# --- the HTML ------------------------------------------------------------------------------------

_CSS = """
:root{color-scheme:dark}
body{margin:0;background:#0e1318;color:#d9e0e8;font:15px/1.35 "DejaVu Sans",system-ui,sans-serif}
header{display:flex;flex-wrap:wrap;align-items:center;gap:8px 18px;padding:10px 18px;background:#18212b;
 border-bottom:2px solid #2b3845}
h1{font-size:24px;margin:0 12px 0 0;font-weight:700}
h2{font-size:17px;margin:14px 14px 6px;color:#9fb2c4;font-weight:600}
.count{font-size:18px;font-weight:700;padding:3px 10px;border-radius:5px;background:#243140}
.meta{color:#8b9aab;font-size:13px;margin-left:auto;text-align:right}
.legend{color:#9fb2c4;font-size:13px}.legend svg{width:30px;height:8px}
.badge{display:inline-block;padding:1px 7px;border-radius:4px;font-weight:700;font-size:12px;letter-spacing:.05em;
 text-transform:uppercase;vertical-align:2px}
.s-warning{background:#e5383b;color:#fff}.s-caution{background:#f4a11d;color:#221500}
.s-normal{background:#2c9a55;color:#fff}.s-unknown,.s-silent{background:#6c5ce7;color:#fff}
.q-good{color:#7fd49c;border:1px solid #2c9a55}.q-learning{color:#8ec5ff;border:1px solid #3a7bd5}
.q-no_model{color:#b8c2cc;border:1px solid #6b7785}.q-stale,.q-bad_input{color:#ffb3c7;border:1px solid #d63a6a}
.q-unknown{color:#b8c2cc;border:1px solid #6b7785}
main{display:grid;grid-template-columns:minmax(0,1fr) 430px;align-items:start}
aside{border-left:2px solid #2b3845;min-height:100vh;padding-bottom:12px}
aside h2{margin-left:12px}
.alarm{margin:0 12px 6px;padding:5px 8px;background:#161e27;border-left:5px solid #f4a11d;border-radius:4px}
.alarm.warning{border-color:#e5383b}.alarm b{margin-left:6px}
.alarm .when{display:block;color:#9fb2c4;font-size:13px}
.alarm .why{color:#d9c7a0;font-size:12.5px;overflow-wrap:anywhere}
@media (max-width:1100px){main{grid-template-columns:1fr}aside{border-left:0;min-height:0}}
.cards{display:grid;grid-template-columns:repeat(auto-fill,minmax(390px,1fr));gap:10px;margin:0 14px}
.card{background:#161e27;border-left:7px solid #2c9a55;border-radius:5px;padding:7px 10px 8px}
.card.warning{border-color:#e5383b;background:#2b171a}.card.caution{border-color:#f4a11d;background:#2a2314}
.card.silent{border-color:#6c5ce7}.card.unknown{border-color:#6b7785}
.card .top{display:flex;align-items:baseline;gap:8px;flex-wrap:wrap}
.card .name{font-size:19px;font-weight:700;margin-right:auto}
.card .info{color:#9fb2c4;font-size:13px;margin-top:2px}.card .info span{white-space:nowrap}
.card .why{color:#ffd28a;font-size:13px;margin-top:2px;overflow-wrap:anywhere}
.card.warning .why{color:#ffb0b0}
.plots{display:grid;grid-template-columns:repeat(auto-fill,minmax(175px,1fr));gap:4px 10px;margin-top:6px}
.fam{font-size:12px;color:#9fb2c4;display:flex;justify-content:space-between}
.fam b{color:#d9e0e8}.fam b.over{color:#f4a11d}
svg.trend{display:block;width:100%;height:48px;background:#0f151b;border:1px solid #24303c}
.none{color:#6b7785;font-size:13px;margin:6px 12px 0 0}aside .none{margin-left:12px}
.offline{margin:4px 14px;color:#8b9aab;font-size:14px}
.error{margin:18px;padding:12px;background:#2b171a;border-left:7px solid #e5383b;font-size:17px}
footer{margin:18px;color:#6b7785;font-size:12px}footer a{color:#8ec5ff}
"""

_SVG_W, _SVG_H = 480, 92  #: the plots' user units (stretched to the card's width); integer coordinates
_BAND = {"caution": "#f4a11d", "warning": "#e5383b"}


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _clock(t: float | None, now: float) -> str:
    """``14:05`` today, ``26 Nov 14:05`` before (local time)."""
    if t is None:
        return "never"
    fmt = "%H:%M" if time.strftime("%Y%m%d", time.localtime(t)) == time.strftime("%Y%m%d", time.localtime(now)) \
        else "%d %b %H:%M"
    return time.strftime(fmt, time.localtime(t))


def _age(seconds: float) -> str:
    s = max(0, int(seconds))
    if s < 120:
        return f"{s} s"
    if s < 7200:
        return f"{s // 60} min"
    if s < 2 * 86400:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    return f"{s // 86400} d"


def _path(points: list[tuple[int, int | None]]) -> str:
    """SVG path data through the points, broken where a value is missing (``None``)."""
    parts, pen_down = [], False
    for x, y in points:
        if y is None:
            pen_down = False
            continue
        parts.append(f"{'L' if pen_down else 'M'}{x} {y}")
        pen_down = True
    return "".join(parts)


def trend_svg(plot_id: str, times: list[float], values: list, alarms: list[dict], since: float, until: float) -> str:
    """One family's evidence as a small inline SVG: the curve (amber above the caution level),
    the dashed caution line at evidence 1 and the drive's caution/warning periods shaded.
    ``plot_id`` is unique on the page (the curve's colour gradient is named after it)."""
    top = max([CAUTION_LEVEL * 1.6] + [v * 1.08 for v in values if v is not None])

    def x(t):
        return round((t - since) / (until - since) * _SVG_W)

    def y(v):
        return None if v is None else round(_SVG_H - 3 - min(v, top) / top * (_SVG_H - 6))

    caution_y = y(CAUTION_LEVEL)
    thin = 'vector-effect="non-scaling-stroke"'
    out = [f'<svg class="trend" viewBox="0 0 {_SVG_W} {_SVG_H}" preserveAspectRatio="none" role="img">']
    for a in alarms:
        x0, x1 = x(max(a["start"], since)), x(min(a["end"] if a["end"] is not None else until, until))
        out.append(f'<rect class="alarm-band" x="{x0}" y="0" width="{max(x1 - x0, 2)}" height="{_SVG_H}" '
                   f'fill="{_BAND.get(a["state"], _BAND["caution"])}" fill-opacity="0.25"/>')
    out.append("".join(f'<line x1="{_SVG_W * k // 4}" x2="{_SVG_W * k // 4}" y1="0" y2="{_SVG_H}" stroke="#24303c" '
                       f'{thin}/>' for k in (1, 2, 3)))  # a faint grid at each quarter of the window
    out.append(f'<line class="caution-line" x1="0" x2="{_SVG_W}" y1="{caution_y}" y2="{caution_y}" stroke="#f4a11d" '
               f'stroke-width="1.3" stroke-dasharray="6 4" {thin}/>')
    d = _path([(x(t), y(v)) for t, v in zip(times, values)])
    if d:  # one curve, coloured by a gradient that turns amber at the caution line
        out.append(f'<linearGradient id="{plot_id}" gradientUnits="userSpaceOnUse" x1="0" y1="0" x2="0" '
                   f'y2="{_SVG_H}"><stop offset="{caution_y / _SVG_H:.3f}" stop-color="#ffb347"/>'
                   f'<stop offset="{caution_y / _SVG_H:.3f}" stop-color="#7cc4ff"/></linearGradient>'
                   f'<path class="evidence" d="{d}" fill="none" stroke="url(#{plot_id})" stroke-width="2" '
                   f'stroke-linejoin="round" {thin}/>')
    out.append("</svg>")
    return "".join(out)


def _value(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def _card(d: dict, snap: dict, number: int) -> str:
    since, until = snap["since"], snap["until"]
    now = until
    state = d["state"]
    look = "silent" if d["silent"] and state == "normal" else state
    badges = [f'<span class="badge s-{_e(state)}">{_e(state)}</span>',
              f'<span class="badge q-{_e(d["quality"])}">{_e(d["quality"].replace("_", " "))}</span>']
    if d["silent"]:
        badges.append(f'<span class="badge s-silent">silent {_e(_age(now - d["last_t"]))}</span>')
    info = [f"{_e(state)} since {_e(_clock(d['state_since'], now))}"]
    if d["state_since"] is not None:
        info[0] += f" ({_e(_age(now - d['state_since']))})"
    if d["fe_hz"] is not None:
        info.append(f"{d['fe_hz']:.1f} Hz")
    if d["load_pct"] is not None:
        info.append(f"load {d['load_pct']:.0f} %")
    if d["model"]:
        info.append(f"model {_e(d['model'])}")
    info.append(f"last sample {_e(_clock(d['last_t'], now))}")
    parts = [f'<div class="card {_e(look)}" data-drive="{_e(_name(d))}">',
             f'<div class="top"><span class="name">{_e(d["drive"])}</span>{"".join(badges)}</div>',
             f'<div class="info">{" · ".join(f"<span>{i}</span>" for i in info)}</div>']
    if d["reason"]:
        parts.append(f'<div class="why">why: {_e(store.reason_text(d["reason"]))}</div>')
    trend = d["trend"]
    if trend["t"]:
        parts.append('<div class="plots">')
        for k, (family, values) in enumerate(trend["evidence"].items()):
            now_v = d["evidence"].get(family)
            over = ' class="over"' if now_v is not None and now_v >= CAUTION_LEVEL else ""
            peak = max((v for v in values if v is not None), default=None)
            parts.append(f'<div class="plot" data-family="{_e(family)}"><div class="fam"><span>{_e(family)}</span>'
                         f'<span><b{over}>{_e(_value(now_v))}</b> peak {_e(_value(peak))}</span></div>'
                         + trend_svg(f"e{number}-{k}", trend["t"], values, d["alarms"], since, until) + "</div>")
        parts.append("</div>")
    else:
        parts.append(f'<div class="none">no evidence trend in the last {snap["window_h"]:g} h</div>')
    parts.append("</div>")
    return "".join(parts)


def _alarm_items(alarms: list[dict], now: float) -> str:
    items = []
    for a in alarms:
        end = "ongoing" if a["end"] is None else _clock(a["end"], now)
        lasted = _age((a["end"] if a["end"] is not None else now) - a["start"])
        reasons = "".join(f"<div>{_e(store.reason_text(r))}</div>" for r in a["reasons"][:3])
        items.append(f'<div class="alarm {_e(a["state"])}"><div class="top"><span class="badge s-{_e(a["state"])}">'
                     f'{_e(a["state"])}</span><b>{_e(_name(a))}</b><span class="when">{_e(_clock(a["start"], now))} - '
                     f'{_e(end)} ({_e(lasted)})</span></div><div class="why">{reasons}</div></div>')
    return "".join(items)


def _page(title: str, refresh_s: float, header: str, body: str) -> str:
    return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
            f'<meta http-equiv="refresh" content="{refresh_s:g}"><meta name="viewport" content="width=device-width">'
            f"<title>{_e(title)}</title><style>{_CSS}</style></head>"
            f"<body><header>{header}</header>{body}</body></html>")


def render_html(snap: dict, historian: dict) -> str:
    """The fleet page for :func:`fleet_snapshot`'s data, with ``historian`` (its status) in the header."""
    now, c = snap["until"], snap["counts"]
    chips = [f'<span class="count s-warning">{c["warning"]} warning</span>' if c["warning"] else "",
             f'<span class="count s-caution">{c["caution"]} caution</span>' if c["caution"] else "",
             f'<span class="count s-normal">{c["normal"]} normal</span>',
             f'<span class="count s-silent">{c["silent"]} silent</span>' if c["silent"] else "",
             f'<span class="count">{c["poor_quality"]} data quality not good</span>' if c["poor_quality"] else ""]
    legend = (f'<span class="legend"><svg viewBox="0 0 30 8"><line x1="0" x2="30" y1="4" y2="4" stroke="#f4a11d" '
              f'stroke-width="1.5" stroke-dasharray="5 3"/></svg> caution level (evidence 1) · plots: the last '
              f'{snap["window_h"]:g} h, now at the right, grid every {snap["window_h"] / 4:g} h</span>')
    header = (f'<h1>Drive fleet</h1>{"".join(chips)}{legend}<span class="meta">{c["drives"]} drives · updated '
              f'{_e(time.strftime("%H:%M:%S", time.localtime(now)))} {_e(time.strftime("%Z"))} · reloads every '
              f'{snap["refresh_s"]:g} s<br>historian {_e(historian.get("historian", ""))}: database '
              f'{_e(historian.get("database", {}).get("state", "?"))}, '
              f'{_e(historian.get("buffered", 0))} row(s) buffered</span>')
    raised = sorted((a for a in snap["alarms"] if a["end"] is None),
                    key=lambda a: (-store.STATE_CODES[a["state"]], -a["start"]))
    cleared = [a for a in snap["alarms"] if a["end"] is not None]
    side = ["<aside>"]
    for title, alarms in ((f"Raised now ({len(raised)})", raised),
                          (f'Cleared, last {snap["window_h"]:g} h ({len(cleared)})', cleared)):
        more = len(alarms) - ALARMS_SHOWN
        side.append(f"<h2>{_e(title)}</h2>"
                    + (_alarm_items(alarms[:ALARMS_SHOWN], now) or '<div class="none">none</div>')
                    + (f'<div class="none">and {more} more in fleet.json</div>' if more > 0 else ""))
    side.append("</aside>")
    body = []
    groups: dict[tuple[str, str], list] = {}
    for number, d in enumerate(snap["drives"]):
        groups.setdefault((d["site"], d["gateway"]), []).append((number, d))
    for (site, gateway), drives in groups.items():
        label = " / ".join(x for x in (site, gateway) if x) or "(no gateway)"
        body.append(f'<h2 class="group">{_e(label)} <small>({len(drives)})</small></h2><div class="cards">'
                    + "".join(_card(d, snap, number) for number, d in drives) + "</div>")
    if snap["offline"]:
        names = ", ".join(f'{_e(_name(d))} ({_e(_clock(d["last_t"], now))}, {_e(d["state"])})' for d in snap["offline"])
        body.append(f'<h2>Not heard from in the last {snap["window_h"]:g} h ({len(snap["offline"])})</h2>'
                    f'<div class="offline">{names}</div>')
    body.append(f'<footer>Each plot: a fault family\'s evidence (CUSUM / caution threshold) over the last '
                f'{snap["window_h"]:g} h, up to {snap["trend_points"]} points; dashed line: evidence 1, where caution '
                f'is raised; shaded: caution (amber) and warning (red) periods; grid: quarters of the window. '
                f'Silent: no sample for {_e(_age(snap["silent_after_s"]))}. The same data: '
                f'<a href="fleet.json">fleet.json</a>.</footer>')
    return _page("Drive fleet", snap["refresh_s"], header, f'<main><div>{"".join(body)}</div>{"".join(side)}</main>')


def render_error(message: str, historian: dict, refresh_s: float) -> str:
    """The page while the database cannot be read: what is wrong; it keeps reloading."""
    header = (f'<h1>Drive fleet</h1><span class="meta">historian {_e(historian.get("historian", ""))}: '
              f'{_e(historian.get("buffered", 0))} row(s) buffered · reloads every {refresh_s:g} s</span>')
    return _page("Drive fleet: no data", refresh_s, header, f'<div class="error">{_e(message)}</div>')


# --- the server ----------------------------------------------------------------------------------

class FleetPage:
    """The page's data, read at most every :data:`SNAPSHOT_MAX_AGE_S` on a connection of its own,
    and its HTTP server (:meth:`start`, :meth:`stop`)."""

    def __init__(self, cfg: HistorianConfig, historian_status: Callable[[], dict],
                 heard: Callable[[], dict] = dict):
        """``historian_status()``: the historian's status; ``heard()``: when each drive's last
        sample arrived (see :func:`fleet_snapshot`)."""
        self.cfg, self.historian_status, self.heard = cfg, historian_status, heard
        self._lock = threading.Lock()  # one read at a time; the others wait and share it
        self._conn = None
        self._snapshot: dict | None = None
        self._error = ""  # why there is no snapshot
        self._read_at = -SNAPSHOT_MAX_AGE_S
        self._bodies: dict = {}  # kind or (kind, "gzip") -> (status, body), per read
        self._server: ThreadingHTTPServer | None = None
        self.url = ""

    def body(self, kind: str, gzipped: bool = False) -> tuple[int, bytes]:
        """``(HTTP status, UTF-8 body)`` of ``"html"`` or ``"json"``, gzip-compressed if asked."""
        with self._lock:
            if time.monotonic() - self._read_at >= SNAPSHOT_MAX_AGE_S:
                self._snapshot, self._error = self._read()
                self._read_at, self._bodies = time.monotonic(), {}
            if kind not in self._bodies:
                self._bodies[kind] = self._render(kind)
            if gzipped and (kind, "gzip") not in self._bodies:
                status, body = self._bodies[kind]
                self._bodies[kind, "gzip"] = status, gzip.compress(body, compresslevel=5)
            return self._bodies[(kind, "gzip") if gzipped else kind]

    def _read(self) -> tuple[dict | None, str]:
        psycopg = store.psycopg_module()
        try:
            if self._conn is None:
                db = self.cfg.database
                self._conn = store.connect(db.dsn, db.connect_timeout_s)
                self._conn.execute(f"SET statement_timeout = {STATEMENT_TIMEOUT_MS}")
            return fleet_snapshot(self._conn, self.cfg.page, self.heard()), ""
        except psycopg.errors.UndefinedTable:
            return None, "no history tables in the database yet (the historian creates them once it connects)"
        except psycopg.Error as err:
            self.close()
            return None, f"cannot read the database (database.dsn): {' '.join(str(err).split())}"

    def _render(self, kind: str) -> tuple[int, bytes]:
        snap, historian = self._snapshot, self.historian_status()
        if kind == "json":
            doc = snap if snap is not None else {"error": self._error}
            return (200 if snap is not None else 503), json.dumps(doc, default=str).encode()
        if snap is None:
            return 503, render_error(self._error, historian, self.cfg.page.refresh_s).encode()
        return 200, render_html(snap, historian).encode()

    def start(self) -> None:
        """Listen on ``page.host``:``page.port`` and serve in a thread; ``InputError`` naming the keys
        when the address cannot be used."""
        page = self.cfg.page
        try:
            family = socket.getaddrinfo(page.host, page.port, type=socket.SOCK_STREAM)[0][0]
            self._server = _Server((page.host, page.port), _handler(self), family)
        except OSError as err:
            raise InputError(f"page.host, page.port: cannot serve the fleet page on {page.host}:{page.port} "
                             f"({err.strerror or err})",
                             source=str(self.cfg.source) if self.cfg.source else None) from None
        host, port = self._server.server_address[:2]
        self.url = f"http://{f'[{host}]' if ':' in host else host}:{port}/"
        threading.Thread(target=self._server.serve_forever, name="historian-page", daemon=True).start()
        log.info("fleet page on %s", self.url)

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
        with self._lock:
            self.close()

    def close(self) -> None:
        """Close the page's database connection (the next read opens a new one)."""
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:
                pass
            self._conn = None


class _Server(ThreadingHTTPServer):
    """``ThreadingHTTPServer`` on the address's family (IPv4 or IPv6), without ``HTTPServer``'s
    reverse DNS lookup of its own address (slow where no DNS server answers)."""

    daemon_threads = True

    def __init__(self, address, handler, family):
        self.address_family = family
        super().__init__(address, handler)

    def server_bind(self):
        socketserver.TCPServer.server_bind(self)
        self.server_name, self.server_port = self.server_address[:2]


def _handler(fleet: FleetPage) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "pmsm-historian"
        timeout = 30  # s: a client that stalls gives its thread back

        def do_GET(self):  # noqa: N802 (http.server's name)
            path = self.path.split("?", 1)[0]
            kinds = {"/": ("html", "text/html; charset=utf-8"), "/fleet.json": ("json", "application/json")}
            if path not in kinds:
                self.send_error(404, "the fleet page is at / and its data at /fleet.json")
                return
            kind, content_type = kinds[path]
            gzipped = "gzip" in self.headers.get("Accept-Encoding", "")
            status, body = fleet.body(kind, gzipped)
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("Content-Security-Policy", "default-src 'none'; style-src 'unsafe-inline'")
            self.send_header("X-Content-Type-Options", "nosniff")
            if gzipped:
                self.send_header("Content-Encoding", "gzip")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, format, *args):  # noqa: A002 (http.server's signature)
            log.debug("page: " + format, *args)

    return Handler
