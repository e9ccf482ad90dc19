"""report.html: one self-contained page (inline base64 PNG from matplotlib/Agg, inline CSS, no
script, no network) a reviewer can open offline and paste into a flight-test report.

Sections: summary table, angular rates before/after compensation (slave rotated into the master
frame so they overlay), latency cost curve(s), drift (per-window latency), alignment state histories
with 3-sigma bounds (both runs), residuals, warnings.
"""
from __future__ import annotations

import base64
import html
import io
import math
import threading
from collections.abc import Sequence

import numpy as np

from logtools.inslog import InsLog
from logtools.results import AlignmentResult
from pipelines.report import RUNS, Analysis, write_text_atomic

AXES = ("x", "y", "z")
RUN_STYLE = {"uncompensated": dict(color="#d62728", ls="--"), "compensated": dict(color="#1f77b4", ls="-")}
MAX_PLOT_POINTS = 4000
#: matplotlib (pyplot, mathtext) is not thread-safe: one page is drawn at a time per process
#: (Dask workers with several threads render concurrently otherwise)
_MPL_LOCK = threading.RLock()


# ---- small helpers ---------------------------------------------------------------------------
def _mpl():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    plt.rcParams.update({
        "figure.dpi": 100, "savefig.dpi": 110, "font.size": 9, "axes.titlesize": 10,
        "axes.grid": True, "grid.alpha": 0.3, "axes.spines.top": False, "axes.spines.right": False,
        "legend.fontsize": 8, "legend.framealpha": 0.85,
    })
    return plt


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")  # the figures are laid out (tight_layout) already
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _decimate(t: np.ndarray, *ys: np.ndarray, n: int = MAX_PLOT_POINTS):
    """Stride-decimate for plotting (at most ``n`` points); arrays returned as given if shorter."""
    if len(t) <= n:
        return (t, *ys)
    k = int(math.ceil(len(t) / n))
    return (t[::k], *(y[::k] for y in ys))


def _fmt(x, spec: str = ".3f", unit: str = "") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "&ndash;"
    return f"{x:{spec}}{(' ' + unit) if unit else ''}"


def _vec(v, spec: str = ".3f") -> str:
    if v is None:
        return "&ndash;"
    return " / ".join(_fmt(x, spec) for x in v)


def _esc(s) -> str:
    return html.escape(str(s))


# ---- figures ---------------------------------------------------------------------------------
def _busy_window(t: np.ndarray, gyro: np.ndarray, span_s: float) -> tuple[float, float]:
    """The ``span_s`` window of the master log with the most angular-rate variation."""
    if len(t) < 2 or t[-1] - t[0] <= span_s:
        return (float(t[0]), float(t[-1])) if len(t) else (0.0, 1.0)
    step = max(span_s / 4, float(np.median(np.diff(t))))
    starts = np.arange(t[0], t[-1] - span_s, step)
    mag = np.linalg.norm(gyro - np.nanmean(gyro, axis=0), axis=1)
    c = np.concatenate([[0.0], np.cumsum(np.nan_to_num(mag) ** 2)])
    i0 = np.searchsorted(t, starts)
    i1 = np.searchsorted(t, starts + span_s)
    energy = (c[i1] - c[i0]) / np.maximum(i1 - i0, 1)
    s = float(starts[int(np.argmax(energy))])
    return s, s + span_s


def fig_rates(an: Analysis, R: np.ndarray, mount_src: str, span_s: float | None = None) -> str | None:
    """3x2 grid: per axis, master vs slave (rotated into the master frame), before / after.

    The window (``span_s``, default 40 x |latency| clipped to 1..10 s) is the busiest one of the log,
    so that the shift is visible."""
    if not (an.master.has_gyro and an.slave.has_gyro):
        return None
    plt = _mpl()
    tm, gm = an.master.t_imu_s(), np.degrees(an.master.gyro_rad_s())
    raw = an.slave_face_value()
    ts_raw, gs_raw = raw.t_imu_s(), np.degrees(raw.gyro_rad_s() @ R)  # (R.T @ w)^T = w^T R
    note_before = "slave stamps at face value"
    overlap = min(tm[-1], ts_raw[-1]) - max(tm[0], ts_raw[0])
    if overlap <= 0:  # unrelated clocks: show the slave from its own start
        ts_raw = ts_raw - ts_raw[0] + tm[0]
        note_before = "clocks unrelated: slave start placed at master start"
    if span_s is None:
        L = abs(an.latency.latency_s) if an.latency is not None else 0.25
        span_s = float(np.clip(40.0 * L, 1.0, 10.0))
    a, b = _busy_window(tm, gm, span_s)
    cols = [("before compensation", ts_raw, gs_raw, note_before)]
    if an.slave_comp is not None and an.slave_comp.has_gyro:
        sc = an.slave_comp
        cols.append(("after compensation", sc.t_imu_s(), np.degrees(sc.gyro_rad_s() @ R),
                     f"latency {an.latency.latency_s * 1e3:+.2f} ms removed" if an.latency else ""))
    fig, axs = plt.subplots(3, len(cols), figsize=(6.2 * len(cols), 7.0), sharex=True, squeeze=False)
    for j, (title, ts, gs, note) in enumerate(cols):
        mm = (tm >= a) & (tm <= b)
        ms = (ts >= a) & (ts <= b)
        for i, ax_name in enumerate(AXES):
            ax = axs[i, j]
            ax.plot(tm[mm], gm[mm, i], color="black", lw=1.1, label="master")
            ax.plot(ts[ms], gs[ms, i], color="#ff7f0e", lw=1.3, ls="--", alpha=0.9,
                    label="slave (in master frame)")
            ax.set_ylabel(f"$\\omega_{ax_name}$ (deg/s)")
            if i == 0:
                ax.set_title(f"{title}\n({note})" if note else title)
                ax.legend(loc="upper right")
        axs[-1, j].set_xlabel("time since master start (s)")
    fig.suptitle(f"Angular rate, master vs slave, busiest {b - a:.1f} s window "
                 f"(slave rotated by mounting from {mount_src})", fontsize=11)
    fig.tight_layout()
    return _png(fig)


def fig_cost(an: Analysis) -> str | None:
    lat = an.latency
    if lat is None or len(lat.cost_lag_s) == 0:
        return None
    plt = _mpl()
    lag_ms = np.asarray(lat.cost_lag_s) * 1e3
    cost = np.asarray(lat.cost, float)
    fig, axs = plt.subplots(1, 2, figsize=(12.4, 3.8))
    for ax, zoom in zip(axs, (False, True)):
        ax.plot(lag_ms, cost, color="#1f77b4", lw=1.2, label=f"cost ({lat.method})")
        L, S = lat.latency_s * 1e3, lat.sigma_s * 1e3
        ax.axvline(L, color="#d62728", lw=1.0, label=f"minimum {L:+.3f} ms")
        if math.isfinite(S) and S > 0:
            ax.axvspan(L - 3 * S, L + 3 * S, color="#d62728", alpha=0.15, label=f"$\\pm3\\sigma$ ({3 * S:.3f} ms)")
        for k, (name, me) in enumerate(lat.methods.items()):
            if name != lat.method and math.isfinite(me.latency_s):
                ax.axvline(me.latency_s * 1e3, color=f"C{k + 2}", lw=0.9, ls=":",
                           label=f"{name}: {me.latency_s * 1e3:+.3f} ms")
        ax.set_xlabel("lag of slave behind master (ms)")
        ax.set_ylabel("normalised cost (-)")
        if zoom:
            half = max(10 * S if math.isfinite(S) else 0.0, 5 * float(np.median(np.diff(lag_ms))) if len(lag_ms) > 1 else 1.0, 2.0)
            ax.set_xlim(L - half, L + half)
            m = (lag_ms >= L - half) & (lag_ms <= L + half)
            if m.any():
                lo, hi = float(np.nanmin(cost[m])), float(np.nanmax(cost[m]))
                pad = 0.05 * (hi - lo or 1.0)
                ax.set_ylim(lo - pad, hi + pad)
            ax.set_title("zoom on the minimum")
        else:
            ax.set_title("latency cost over the search window")
            ax.legend(loc="best")
    fig.tight_layout()
    return _png(fig)


def fig_drift(an: Analysis) -> str | None:
    lat = an.latency
    if lat is None or len(lat.window_latency_s) == 0:
        return None
    plt = _mpl()
    tc = np.asarray(lat.window_centers_s, float)
    wl = np.asarray(lat.window_latency_s, float) * 1e3
    fig, ax = plt.subplots(figsize=(12.4, 3.4))
    ax.plot(tc, wl, "o", ms=3.5, color="#1f77b4", label="per-window latency")
    tt = np.linspace(np.nanmin(tc), np.nanmax(tc), 50) if len(tc) else tc
    ax.plot(tt, lat.latency_at(tt) * 1e3, color="#d62728", lw=1.2,
            label=f"fit: {lat.latency_s * 1e3:+.3f} ms at mid, drift {lat.drift_ppm:+.2f} ppm")
    ax.set_xlabel("time since master start (s)")
    ax.set_ylabel("latency (ms)")
    ax.set_title("Latency over the log (clock drift)")
    ax.legend(loc="best")
    fig.tight_layout()
    return _png(fig)


def _state_groups(names: Sequence[str]) -> dict[str, list[int]]:
    groups: dict[str, list[int]] = {}
    for i, n in enumerate(names):
        ln = n.lower()
        if "mount" in ln or ln.startswith(("roll", "pitch", "yaw", "psi", "phi")):
            g = "mounting angles"
        elif "gyro" in ln or ln.startswith("bg"):
            g = "gyro biases"
        elif "accel" in ln or ln.startswith("ba"):
            g = "accelerometer biases"
        elif "delay" in ln or "lat" in ln:
            g = "delay"
        else:
            g = "other states"
        groups.setdefault(g, []).append(i)
    return groups


def _by_name(names_of: dict[str, Sequence[str]]) -> tuple[list[str], dict[str, dict[str, int]]]:
    """The union of the runs' column names (first run's order, then the others' extras) and each run's
    column index by name: runs may carry different columns (flexure, lever-arm states in one only)."""
    names: list[str] = []
    for ns in names_of.values():
        names += [n for n in ns if n not in names]
    return names, {r: {n: i for i, n in enumerate(ns)} for r, ns in names_of.items()}


def fig_states(an: Analysis) -> list[tuple[str, str]]:
    """One figure per state group; both runs overlaid with their 3-sigma envelopes."""
    runs = {r: res for r, res in an.alignment.items() if res is not None and res.history_x.size}
    if not runs:
        return []
    plt = _mpl()
    # the runs' states by name (the runs may differ: flexure or lever-arm states in one only)
    names, col = _by_name({r: res.history_names for r, res in runs.items()})
    out = []
    for group, idx in _state_groups(names).items():
        ncol = min(3, len(idx))
        nrow = int(math.ceil(len(idx) / ncol))
        fig, axs = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 2.9 * nrow), squeeze=False)
        for k, i in enumerate(idx):
            ax = axs[k // ncol, k % ncol]
            for run, res in runs.items():
                j = col[run].get(names[i])
                if j is None or j >= res.history_x.shape[1]:
                    continue
                t, x, s = _decimate(res.history_t_s, res.history_x[:, j], res.history_sigma[:, j])
                st = RUN_STYLE.get(run, {})
                ax.plot(t, x, lw=1.1, label=f"{run}", **st)
                ax.fill_between(t, x - 3 * s, x + 3 * s, color=st.get("color"), alpha=0.12,
                                label=f"{run} $\\pm3\\sigma$")
            ax.set_title(names[i])
            ax.set_xlabel("time (s)")
            if k == 0:
                ax.legend(loc="best")
        for k in range(len(idx), nrow * ncol):
            axs[k // ncol, k % ncol].set_visible(False)
        fig.suptitle(f"Transfer alignment: {group} (estimate and 3-sigma bound)", fontsize=11)
        fig.tight_layout()
        out.append((group, _png(fig)))
    return out


def fig_residuals(an: Analysis) -> str | None:
    runs = {r: res for r, res in an.alignment.items() if res is not None and res.residuals.size}
    if not runs:
        return None
    plt = _mpl()
    names, col = _by_name({r: res.residual_names for r, res in runs.items()})
    ncol = min(3, len(names))
    nrow = int(math.ceil(len(names) / ncol))
    fig, axs = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 2.7 * nrow), squeeze=False, sharex=True)
    for i, name in enumerate(names):
        ax = axs[i // ncol, i % ncol]
        for run, res in runs.items():
            j = col[run].get(name)
            if j is not None and j < res.residuals.shape[1]:
                t, r = _decimate(res.residual_t_s, res.residuals[:, j])
                st = RUN_STYLE.get(run, {})
                rms = float(np.sqrt(np.nanmean(res.residuals[:, j] ** 2)))
                ax.plot(t, r, lw=0.8, label=f"{run} (rms {rms:.3g})", color=st.get("color"), alpha=0.8)
        ax.set_title(name)
        ax.set_xlabel("time (s)")
        ax.legend(loc="best")
    for k in range(len(names), nrow * ncol):
        axs[k // ncol, k % ncol].set_visible(False)
    fig.suptitle("Measurement residuals (innovations) of the alignment filter", fontsize=11)
    fig.tight_layout()
    return _png(fig)


# ---- page ------------------------------------------------------------------------------------
CSS = """
body{font-family:-apple-system,'Segoe UI',Helvetica,Arial,sans-serif;margin:0;color:#1d2733;background:#f4f6f8}
header{background:#1d3557;color:#fff;padding:18px 32px}
header h1{margin:0;font-size:22px;font-weight:600} header p{margin:4px 0 0;opacity:.85;font-size:13px}
main{max-width:1280px;margin:0 auto;padding:16px 32px 40px}
section{background:#fff;border:1px solid #dde3ea;border-radius:6px;padding:14px 20px;margin:16px 0}
h2{font-size:17px;margin:4px 0 10px;color:#1d3557;border-bottom:2px solid #e63946;display:inline-block;padding-bottom:2px}
table{border-collapse:collapse;font-size:13px;margin:6px 0}
th,td{border:1px solid #dde3ea;padding:4px 10px;text-align:left;vertical-align:top;overflow-wrap:anywhere}
th{background:#eef2f6;font-weight:600} td.num{text-align:right;font-family:Menlo,Consolas,monospace}
img{max-width:100%;display:block;margin:8px 0}
.ok{color:#2a9d8f;font-weight:600} .warn{color:#e76f51;font-weight:600} .fail{color:#c1121f;font-weight:600}
.note{color:#5c6b7a;font-size:12px} ul{margin:4px 0 4px 18px;font-size:13px}
"""


def _status_cls(status: str) -> str:
    return {"ok": "ok", "partial": "warn"}.get(status, "fail")


def _summary_html(rep: dict) -> str:
    m, s, lat = rep["master"], rep["slave"], rep["latency"]
    rows = ["<table><tr><th></th><th>master</th><th>slave</th></tr>"]
    for key, label in (("path", "file"), ("format", "format"), ("selector", "selector"), ("clock", "clock"),
                       ("stamp_source", "stamps from")):
        rows.append(f"<tr><th>{label}</th><td>{_esc(m.get(key) or '')}</td><td>{_esc(s.get(key) or '')}</td></tr>")
    rows.append(f"<tr><th>duration</th><td class=num>{_fmt(m.get('duration_s'), '.1f', 's')}</td>"
                f"<td class=num>{_fmt(s.get('duration_s'), '.1f', 's')}</td></tr>")
    ch = lambda d: "<br>".join(f"{_esc(k)}: {_fmt(v.get('rate_hz'), '.1f', 'Hz')} &times; {v.get('count')}"
                               for k, v in d["channels"].items())
    rows.append(f"<tr><th>channels</th><td>{ch(m)}</td><td>{ch(s)}</td></tr></table>")
    out = ["".join(rows)]
    t = ["<table><tr><th>quantity</th><th>value</th><th>1&sigma;</th></tr>"]
    if "failed" in lat:
        t.append(f"<tr><th>latency</th><td colspan=2 class=fail>failed: {_esc(lat['failed'])}</td></tr>")
    else:
        t.append(f"<tr><th>latency (slave behind master)</th><td class=num>{_fmt(lat['latency_s'] * 1e3, '+.3f', 'ms')}</td>"
                 f"<td class=num>{_fmt(None if lat['sigma_s'] is None else lat['sigma_s'] * 1e3, '.3f', 'ms')}</td></tr>")
        t.append(f"<tr><th>clock drift</th><td class=num>{_fmt(lat['drift_ppm'], '+.2f', 'ppm')}</td><td></td></tr>")
        w = lat.get("window_s") or [None, None]
        t.append(f"<tr><th>method / window (master stamps)</th><td colspan=2>{_esc(lat['method'])}, "
                 f"[{_fmt(w[0], '.3f')}, {_fmt(w[1], '.3f')}] s</td></tr>")
        for name, me in lat.get("methods", {}).items():
            ls, ss = me.get("latency_s"), me.get("sigma_s")
            t.append(f"<tr><th>&nbsp;&nbsp;method {_esc(name)}</th><td class=num>{_fmt(None if ls is None else ls * 1e3, '+.3f', 'ms')}</td>"
                     f"<td class=num>{_fmt(None if ss is None else ss * 1e3, '.3f', 'ms')}</td></tr>")
        vf = (lat.get("quality") or {}).get("velocity_fit")
        if isinstance(vf, dict):  # the velocity-matched estimate, and what became of it
            use = "fused" if vf.get("fused") else ("agrees, not used (less precise)" if vf.get("agrees")
                                                   else "disagrees, not used")
            ls, ss = vf.get("latency_s"), vf.get("sigma_s")
            t.append(f"<tr><th>&nbsp;&nbsp;velocity matching ({use}; lever arm {_vec(vf.get('lever_arm_m'), '.3f')} m)"
                     f"</th><td class=num>{_fmt(None if ls is None else ls * 1e3, '+.3f', 'ms')}</td>"
                     f"<td class=num>{_fmt(None if ss is None else ss * 1e3, '.3f', 'ms')}</td></tr>")
    for run in RUNS:
        a = rep["alignment"].get(run, {})
        if "skipped" in a:
            t.append(f"<tr><th>mounting r/p/y ({run})</th><td colspan=2 class=warn>skipped: {_esc(a['skipped'])}</td></tr>")
            continue
        t.append(f"<tr><th>mounting r/p/y ({run}, {_esc(a['filter'])}, {_esc(a['match'])})</th>"
                 f"<td class=num>{_vec(a['mounting_rpy_deg'])} deg</td><td class=num>{_vec(a['mounting_sigma_deg'], '.4f')} deg</td></tr>")
        t.append(f"<tr><th>&nbsp;&nbsp;slave gyro bias ({run})</th><td class=num>{_vec(a['gyro_bias_dph'], '.2f')} deg/h</td>"
                 f"<td class=num>{_vec(a.get('gyro_bias_sigma_dph'), '.2f')}</td></tr>")
        t.append(f"<tr><th>&nbsp;&nbsp;slave accel bias ({run})</th><td class=num>{_vec(a['accel_bias_mg'], '.3f')} mg</td>"
                 f"<td class=num>{_vec(a.get('accel_bias_sigma_mg'), '.3f')}</td></tr>")
        if a.get("lever_arm_m") is not None:
            how = "estimated" if a.get("lever_arm_sigma_m") is not None else "given"
            t.append(f"<tr><th>&nbsp;&nbsp;lever arm x/y/z ({run}, {how})</th><td class=num>{_vec(a['lever_arm_m'], '.3f')} m</td>"
                     f"<td class=num>{_vec(a.get('lever_arm_sigma_m'), '.3f')}</td></tr>")
        rr = ", ".join(f"{_esc(k)} {_fmt(v, '.4g')}" for k, v in a.get("residual_rms", {}).items())
        t.append(f"<tr><th>&nbsp;&nbsp;converged / residual rms ({run})</th><td colspan=2>"
                 f"{_fmt(a.get('converged_s'), '.1f', 's')}; {rr}</td></tr>")
    t.append("</table>")
    out.append("".join(t))
    q = lat.get("quality") or {}
    if q:
        out.append("<p class=note>latency quality: " + ", ".join(f"{_esc(k)}={_esc(v)}" for k, v in q.items()
                                                                 if k != "velocity_fit") + "</p>")
    return "".join(out)


def _imu_to_imu_html(rep: dict) -> str:
    """The IMU-to-IMU block of the summary: each triad's rotation beside the nav-referenced mounting, and
    whether they agree (empty when the report has no ``alignment.imu_to_imu``)."""
    al = rep.get("alignment", {})
    ii = al.get("imu_to_imu")
    if not ii:
        return ""
    t = ["<h3>IMU-to-IMU rotation (slave triads relative to the master's)</h3><table>"
         "<tr><th></th><th>roll / pitch / yaw</th><th>1 sigma</th></tr>"]
    comp = al.get("compensated", {})
    if "mounting_rpy_deg" in comp:
        t.append(f"<tr><th>nav-referenced mounting (compensated)</th><td class=num>{_vec(comp['mounting_rpy_deg'])} deg"
                 f"</td><td class=num>{_vec(comp['mounting_sigma_deg'], '.4f')} deg</td></tr>")
    for name, label in (("gyro", "gyro triad"), ("accel", "accelerometer triad")):
        rpy = ii.get(f"{name}_rpy_deg")
        if rpy is None:
            why = (ii.get("reasons") or {}).get(name, "not measured")
            t.append(f"<tr><th>{label}</th><td colspan=2 class=warn>not measured: {_esc(why)}</td></tr>")
        else:
            t.append(f"<tr><th>{label}</th><td class=num>{_vec(rpy)} deg</td>"
                     f"<td class=num>{_vec(ii.get(f'{name}_sigma_deg'), '.4f')} deg</td></tr>")
    t.append("</table>")
    cons = al.get("consistency")
    if cons and cons.get("note"):
        cls = "warn" if cons.get("agrees") is False else "note"
        t.append(f"<p class={cls}>{'WARNING: ' if cons.get('agrees') is False else ''}{_esc(cons['note'])}</p>")
    return "".join(t)


def render(rep: dict, an: Analysis) -> str:
    """The report page as a string (pure function of the report dict and the analysis data)."""
    with _MPL_LOCK:
        return _render(rep, an)


def _render(rep: dict, an: Analysis) -> str:
    R, mount_src = an.mounting()
    sections: list[tuple[str, str, str]] = []  # (id, title, html)
    status = rep.get("status", "ok")
    sections.append(("summary", "Summary",
                     f"<p>Status: <span class={_status_cls(status)}>{_esc(status)}</span></p>" + _summary_html(rep)
                     + _imu_to_imu_html(rep)))

    def img(b64: str | None, alt: str, missing: str) -> str:
        return (f'<img alt="{_esc(alt)}" src="data:image/png;base64,{b64}">' if b64
                else f"<p class=note>{_esc(missing)}</p>")

    sections.append(("rates", "Angular rates before and after compensation",
                     img(fig_rates(an, R, mount_src), "angular rates",
                         "Not available: both logs need angular rate.")))
    sections.append(("latency", "Latency cost curve",
                     img(fig_cost(an), "latency cost", "Not available: latency was not estimated.")))
    sections.append(("drift", "Clock drift (latency per window)",
                     img(fig_drift(an), "drift", "Not available: no per-window latency estimates.")))
    states = fig_states(an)
    body = "".join(f"<h3>{_esc(g)}</h3>" + img(b, g, "") for g, b in states)
    skipped = [f"<li>{_esc(r)}: {_esc(a['skipped'])}</li>" for r, a in rep["alignment"].items() if "skipped" in a]
    if skipped:
        body = "<ul>" + "".join(skipped) + "</ul>" + body
    sections.append(("alignment", "Transfer alignment state histories", body or
                     "<p class=note>No alignment run produced state histories.</p>"))
    sections.append(("residuals", "Residuals",
                     img(fig_residuals(an), "residuals", "No residuals were recorded.")))
    warn = []
    for role in ("master", "slave"):
        warn += [f"<li><b>{role}</b>: {_esc(w)}</li>" for w in rep[role].get("warnings", [])]
    warn += [f"<li><b>skipped {_esc(k)}</b>: {_esc(v)}</li>" for k, v in rep.get("skipped", {}).items()]
    for run in RUNS:
        warn += [f"<li><b>alignment {run}</b>: {_esc(n)}</li>" for n in rep["alignment"].get(run, {}).get("notes", [])]
    sections.append(("warnings", "Warnings and notes", "<ul>" + "".join(warn) + "</ul>" if warn
                     else "<p class=note>None.</p>"))
    tim = rep.get("timings_s", {})
    sections.append(("timings", "Timings", "<table><tr>" + "".join(f"<th>{_esc(k)}</th>" for k in tim)
                     + "</tr><tr>" + "".join(f"<td class=num>{_fmt(v, '.2f', 's')}</td>" for v in tim.values())
                     + "</tr></table>"))
    nav = " &middot; ".join(f'<a href="#{i}" style="color:#fff">{_esc(t)}</a>' for i, t, _ in sections)
    parts = [
        "<!DOCTYPE html><html lang=en><head><meta charset=utf-8>",
        "<meta name=viewport content='width=device-width,initial-scale=1'>",
        f"<title>tapost report: {_esc(rep['master']['path'])} vs {_esc(rep['slave']['path'])}</title>",
        f"<style>{CSS}</style></head><body>",
        f"<header><h1>tapost latency and transfer-alignment report</h1><p>master "
        f"<b>{_esc(rep['master']['path'])}</b> &nbsp;vs&nbsp; slave <b>{_esc(rep['slave']['path'])}</b>"
        f" &middot; {_esc(rep['created_utc'])} &middot; tapost {_esc(rep['tapost_version'])} "
        f"({_esc(rep['schema'])})</p><p>{nav}</p></header><main>",
    ]
    parts += [f'<section id="{i}"><h2>{_esc(t)}</h2>{h}</section>' for i, t, h in sections]
    parts.append("<p class=note>Conventions: NED/FRD; latency positive when the slave's stamps lag the "
                 "master's; mounting R with v_slave = R v_master, intrinsic Z-Y-X angles listed roll/pitch/yaw."
                 "</p></main></body></html>\n")
    return "".join(parts)


def write_html(path: str, rep: dict, an: Analysis) -> None:
    """Render and write report.html atomically."""
    write_text_atomic(path, render(rep, an))
