"""HTML report of ``model compare`` / ``model explain``: one page with PNG plots (matplotlib, Agg)."""

from __future__ import annotations

import html
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from agent.effects import params_text  # noqa: E402
from agent.frames import dq_to_abc  # noqa: E402


def report_folder(out_dir) -> Path:
    """``out_dir`` created (with parents) for a report; a path that cannot be a folder is the user's
    error (exit 2 naming ``--report``), not a crash."""
    from agent.errors import InputError

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise InputError(f"--report {out_dir}: cannot write a report folder there ({err.strerror or err})") from None
    return out


def _save(fig, out: Path, name: str) -> str:
    fig.tight_layout()
    fig.savefig(out / name, dpi=90)
    plt.close(fig)
    return name


def _plots(data: dict, ranking: dict | None, out: Path) -> list[tuple[str, str]]:
    figs = []
    sig = data["traces"][0][0]
    start = data.get("split", 0)  # the held-out segment, where the figures are measured
    n = min(sig.n - start, int(0.05 / sig.ts))
    cut = slice(start, start + n)
    t = (start + np.arange(n)) * sig.ts * 1e3
    fig, ax = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    for k, name in enumerate(("i_d", "i_q")):
        ax[k].plot(t, sig.i_dq[k, cut], lw=1.2, color="black", label="measured")
        ax[k].set_ylabel(f"{name} (A)")
    ax[2].plot(t, sig.i_abc[0, cut], lw=1.2, color="black", label="measured")
    short = [Path(tr[2]).name for tr in data["traces"]]
    names = short if len(set(short)) == len(short) else [tr[2] for tr in data["traces"]]  # m.json twice: the paths
    for j, (trace, name) in enumerate(zip(data["traces"], names)):
        y = trace[1]
        for k in (0, 1):
            ax[k].plot(t, y[k, cut], lw=0.8, ls=("-", "--", ":", "-.")[j % 4], label=f"{name} (free run)")
        ax[2].plot(t, dq_to_abc(y[:, cut], sig.theta_e[cut])[0], lw=0.8, ls=("-", "--", ":", "-.")[j % 4],
                   label=f"{name} (free run)")
    ax[2].set_ylabel("i_a (A)")
    ax[2].set_xlabel("time (ms)")
    ax[0].legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)
    figs.append(("Measured against every model compared (first record, 50 ms of its held-out part)",
                 _save(fig, out, "traces.png")))

    fig, ax = plt.subplots(figsize=(10, 4.5))
    f, a = data["freqs"], data["amp"]
    ax.semilogy(f, a, lw=0.7, label="residual, phase a")
    if data["th3"] is not None:
        ax.semilogy(f, data["th2"], lw=0.7, color="orange", label="TH2 (caution)")
        ax.semilogy(f, data["th3"], lw=0.7, color="red", label="TH3 (warning)")
    for k, pk in enumerate(data["peaks"]):  # numbered markers; the labels go in the legend's list below
        ax.annotate(str(k + 1), (pk["freq_hz"], pk["amplitude_a"]), xytext=(0, 6), textcoords="offset points",
                    fontsize=8, ha="center", color="darkred")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("amplitude (A)")
    ax.legend(loc="upper right", fontsize=8)
    peaks = "; ".join(f"{k + 1}: {pk['freq_hz']:.1f} Hz, {pk['label']}" for k, pk in enumerate(data["peaks"]))
    figs.append(("Residual spectrum with thresholds; numbered peaks" + (f" ({peaks})" if peaks else ""),
                 _save(fig, out, "spectrum.png")))

    fig, ax = plt.subplots(1, 3, figsize=(12, 3.8))
    deg = (np.arange(data["angle_bins"].shape[1]) + 0.5) * 360 / data["angle_bins"].shape[1]
    ax[0].plot(deg, data["angle_bins"][0], marker=".", label="d")
    ax[0].plot(deg, data["angle_bins"][1], marker=".", label="q")
    ax[0].set_xlabel("electrical angle (deg)")
    ax[0].set_ylabel("mean residual (A)")
    ax[0].legend()
    e = data["current_edges"]
    ax[1].plot(0.5 * (e[1:] + e[:-1]), data["current_bins"], marker=".")
    ax[1].axvline(0, color="grey", lw=0.5)
    ax[1].set_xlabel("phase-a current (A)")
    ax[1].set_ylabel("mean phase-a residual (A)")
    for row in data["time_bins"]:
        ax[2].plot(np.arange(row.size) + 1, row, marker=".", lw=0.7)
    ax[2].set_xlabel("tenth of the record")
    ax[2].set_ylabel("residual RMS (A)")
    figs.append(("Residual binned over angle, current and time", _save(fig, out, "bins.png")))

    fig, ax = plt.subplots(1, 2, figsize=(12, 3.8))
    lags, band = data["lags"], data["band"]
    pos = lags[lags > 0]
    ax[0].stem(pos, data["auto"][0], linefmt="C0-", markerfmt="C0.", basefmt=" ", label="d")
    ax[0].stem(pos + 0.3, data["auto"][1], linefmt="C1-", markerfmt="C1.", basefmt=" ", label="q")
    ax[0].set_title("autocorrelation of the one-step residual")
    ax[1].plot(lags, data["cross"][0], marker=".", label="e_q vs v_d")
    ax[1].plot(lags, data["cross"][1], marker=".", label="e_q vs v_q")
    ax[1].set_title("cross-correlation with the inputs")
    for a in ax:
        a.axhspan(-band, band, color="grey", alpha=0.25, label="99 % band")
        a.set_xlabel("lag (samples)")
        a.legend(fontsize=8)
    figs.append(("Residual whiteness and input correlation (as MATLAB resid)", _save(fig, out, "correlation.png")))

    if ranking:
        rows = ranking["candidates"][::-1]
        fig, ax = plt.subplots(figsize=(10, 0.45 * len(rows) + 1.2))
        colors = ["tab:green" if r["significant"] else "tab:grey" if r["identifiable"] else "tab:orange" for r in rows]
        ax.barh([r["effect"] for r in rows], [100 * (r["explained_fraction"] or 0.0) for r in rows], color=colors)
        ax.set_xlabel("share of the held-out residual explained (%) - green: significant, "
                      "orange: not identifiable from these records")
        ax.axvline(0, color="black", lw=0.5)
        figs.append(("Effect ranking", _save(fig, out, "ranking.png")))
    return figs


def _fmt(v) -> str:
    return "unstable" if v is None else f"{100 * v:.3f} %"


def _pct(v):
    """A fraction as a percentage; None (an unstable free run) as "unstable"."""
    return "unstable" if v is None else 100 * v


def _table(rows: list[list], head: list[str]) -> str:
    esc = lambda v: html.escape(f"{v:.4g}" if isinstance(v, float) else str(v))  # noqa: E731
    return ("<table><tr>" + "".join(f"<th>{esc(h)}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in rows) + "</table>")


def write_report(out_dir, title: str, doc: dict, data: dict, ranking: dict | None = None) -> Path:
    """Write ``index.html`` and its PNGs into ``out_dir``; returns the page's path."""
    out = report_folder(out_dir)
    figs = _plots(data, ranking, out)
    m = doc["modes"]
    keys = ("d", "q", "total", "a", "b", "c")
    fit = _table([[mode, *((_pct(m[mode]["nrmse"][k]) for k in keys) if m[mode]["nrmse"] else ["unstable"] * 6),
                   *((m[mode]["fit_pct"][k] for k in keys) if m[mode]["fit_pct"] else ["-"] * 6)]
                  for mode in ("free_run", "one_step")],
                 ["mode (held-out)", "NRMSE d %", "q %", "total %", "a %", "b %", "c %", "fit d %", "fit q %",
                  "fit total %", "fit a %", "fit b %", "fit c %"])
    fit += f"<p class='warn'>{html.escape(doc['note'])}</p>" if doc.get("note") else ""
    if doc.get("noise_floor"):
        fit += (f"<p>Free run: the error beyond the channels' noise floor ({100 * doc['noise_floor']['total']:.3f} % total, "
                "which no model removes); the one-step figure is raw.</p>")
    models = list(doc["table"][0]["nrmse"]) if doc["table"] else []
    if len(doc.get("models", {})) > 1:
        fit += "<h3>Every model on the whole record set (held-out free run)</h3>" + _table(
            [[k, _pct(v)] for k, v in doc["models"].items()], ["model", "NRMSE total %"])
    t5 = _table([[r["fe_hz"], r["load_pct"], r["records"], *(_pct(r["nrmse"][k]) for k in models)]
                 for r in doc["table"]], ["fe (Hz)", "load (%)", "records", *(f"{k}: NRMSE %" for k in models)])
    where = "".join(f"<li>{html.escape(w.get('summary') or w['label'] + ' at %.1f Hz' % w['freq_hz'])}"
                    + (f" <i>(look at: {html.escape(', '.join(w['effects']))})</i>" if w.get("effects") else "")
                    + "</li>" for w in doc["where"])
    rank = ""
    if ranking:
        rank = "<h2>Effect ranking (held-out, against a refit without effects)</h2>" + _table(
            [[r["effect"], _pct(r["explained_fraction"]), _pct(r["nrmse_after"]), r["significant"], r["identifiable"],
              params_text(r["params"], "=", r.get("params_bound")), r.get("note", "")]
             for r in ranking["candidates"]],
            ["effect", "explained %", "NRMSE after %", "significant", "identifiable",
             "parameters (+-: how far each may be from what the records show, a worst case)", "note"])
        rank = (f"<p>Held-out NRMSE of the model as it is: {_fmt(ranking['nrmse_before'])}; control (the model "
                f"refitted without new effects, or itself if better): {_fmt(ranking['nrmse_control'])}</p>") + rank
    warn = "".join(f"<li class='warn'>{html.escape(w)}</li>" for w in doc.get("warnings", []))
    imgs = "".join(f"<h2>{html.escape(cap)}</h2><img src='{name}' alt='{html.escape(cap)}'>" for cap, name in figs)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title><style>
body{{font-family:sans-serif;max-width:1200px;margin:1em auto;color:#222}} table{{border-collapse:collapse;margin:.5em 0}}
td,th{{border:1px solid #bbb;padding:2px 8px;text-align:right;font-size:13px}} img{{max-width:100%}}
.warn{{color:#b00}} h2{{font-size:1.1em;margin-top:1.4em}}</style></head><body>
<h1>{html.escape(title)}</h1><ul>{warn}</ul><h2>Fit</h2>{fit}<h2>By operating point (as the paper's Table 5)</h2>{t5}
{rank}<h2>Where it fails</h2><ul>{where}</ul>{imgs}</body></html>"""
    path = out / "index.html"
    path.write_text(page)
    return path


STATE_COLOURS = {"normal": "tab:green", "caution": "tab:orange", "warning": "tab:red"}


def _spectrum_plot(base, d, out: Path, name: str) -> str:
    """One record's residual spectrum (mean over its windows) with TH1..TH3 and its fault lines
    marked by level, as the paper's Figs. 8 and 10."""
    th = base.thresholds
    freqs, amp = d.spectrum
    a = np.atleast_2d(amp).mean(axis=0)
    fig, ax = plt.subplots(figsize=(10, 3.6))
    ax.semilogy(freqs, a, lw=0.7, color="tab:blue", label="residual, phase a")
    if freqs.size == th.freqs_hz.size:
        for level, style in ((th.centre, ("grey", "TH1 (healthy mean)")), (th.th2, ("orange", "TH2 (caution)")),
                             (th.th3, ("red", "TH3 (warning)"))):
            ax.semilogy(freqs, level, lw=0.7, color=style[0], label=style[1])
    for pk in d.peaks:
        colour = STATE_COLOURS.get(pk["level"], "tab:green")
        ax.axvline(pk["freq_hz"], color=colour, lw=0.6, ls=":", alpha=0.8)
        ax.plot(pk["freq_hz"], pk["magnitude"], "v", color=colour, ms=5)
    ax.set_xlim(0, min(freqs[-1], 4 * (d.operating_point.get("fe_hz") or freqs[-1] / 4)))
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("amplitude (A)")
    ax.set_title(f"{Path(d.record).name}: {d.state} (spectrum {d.spectrum_state}); dotted: fault sidebands "
                 f"(green normal, orange caution, red warning)", fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    return _save(fig, out, name)


def _cluster_plot(base, results, out: Path) -> str:
    """The healthy (Ts/Lq, B_GT) cluster with its region's edge and the records marked by state,
    as the paper's Figs. 9 and 11."""
    cl = base.cluster
    fig, ax = plt.subplots(figsize=(8.5, 5))
    ax.plot(cl.points[:, 0], cl.points[:, 1], "o", color="grey", ms=4, label="healthy (baseline)")
    vals, vecs = np.linalg.eigh(cl.cov)
    t = np.linspace(0, 2 * np.pi, 200)
    ring = cl.centre[:, None] + vecs @ (np.sqrt(np.maximum(vals, 0) * cl.limit)[:, None] * np.vstack((np.cos(t), np.sin(t))))
    ax.plot(ring[0], ring[1], color="black", lw=0.8, label=f"{100 * cl.confidence:.0f} % healthy region")
    for state, colour in STATE_COLOURS.items():
        pts = [(r.cluster["ts_over_lq"], r.cluster["b_gt"]) for r in results if r.cluster and r.cluster_state == state]
        if pts:
            p = np.array(pts)
            ax.plot(p[:, 0], p[:, 1], "s", color=colour, ms=6, label=f"records: cluster {state}")
    ax.set_xlabel("T_s / L_q (identified)")
    ax.set_ylabel("B_GT (N m s/rad)")
    ax.ticklabel_format(style="sci", axis="both", scilimits=(-3, 3))
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # outside: never over a point
    return _save(fig, out, "cluster.png")


def write_diagnosis_report(out_dir, base, results, model_name: str) -> Path:
    """``diagnose --report DIR``: the decision table, the parameter cluster and each record's
    residual spectrum with its thresholds and fault sidebands; returns the page's path."""
    out = report_folder(out_dir)
    good = [r for r in results if r.quality == "good"]
    rows = [[Path(r.record).name, r.state, r.spectrum_state, r.cluster_state,
             f"{r.cluster.get('distance2', float('nan')):.2f} / {r.cluster.get('limit', float('nan')):.2f}" if r.cluster else "-",
             ", ".join(f"{p['freq_hz']:.1f} Hz {p['family']} k={p['k']} {p['level']}" for p in r.peaks
                       if p["level"] != "normal") or "-", r.reason or "; ".join(r.notes)]
            for r in results]
    table = _table(rows, ["record", "state", "spectrum", "cluster", "cluster d2 / limit", "lines above TH2",
                          "note"])
    imgs = [("Parameter cluster (Ts/Lq against B_GT) with the healthy region", _cluster_plot(base, good, out))]
    imgs += [(f"Residual spectrum: {Path(r.record).name}", _spectrum_plot(base, r, out, f"spectrum_{j}.png"))
             for j, r in enumerate(good) if r.spectrum is not None]
    body = "".join(f"<h2>{html.escape(cap)}</h2><img src='{name}' alt='{html.escape(cap)}'>" for cap, name in imgs)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>Diagnosis with {html.escape(model_name)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:1em auto;color:#222}} table{{border-collapse:collapse;margin:.5em 0}}
td,th{{border:1px solid #bbb;padding:2px 8px;font-size:13px}} img{{max-width:100%}} h2{{font-size:1.1em;margin-top:1.4em}}</style>
</head><body><h1>Diagnosis with {html.escape(model_name)}</h1><h2>Decisions (paper Table 4 rule)</h2>{table}{body}</body></html>"""
    path = out / "index.html"
    path.write_text(page)
    return path
