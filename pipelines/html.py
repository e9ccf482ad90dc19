"""report.html: one self-contained page (inline CSS, inline SVG figures, no script, no network). A
reviewer can open it offline, print it, and paste it into a flight-test report.

Sections:

* the headline: status and warning count; latency ± sigma and the instant it is quoted at; drift;
  mounting ± sigma; converged or not
* summary table
* latency quality: a grouped table, with the raw values in a collapsed block
* angular rates before and after compensation (the slave rotated into the master frame, so the two
  overlay)
* latency cost curve(s)
* drift (the latency per window)
* alignment state histories with 3-sigma bounds, for both runs
* residuals
* warnings

The figures are ``<svg>`` elements drawn straight from the numpy arrays by ``pipelines.svgplot``,
in tens of milliseconds per page. They need no plotting library, and ``render`` is a pure function,
safe to call from several threads at once.
"""
from __future__ import annotations

import html
import json
import math
from collections.abc import Sequence

import numpy as np

from pipelines.report import (GIMBAL_LOCK_SAID, RUNS, Analysis, input_damage, latency_instant, report_warnings,
                              write_text_atomic)
from pipelines.svgplot import Figure

AXES = ("x", "y", "z")
RUN_STYLE = {"uncompensated": dict(color="uncompensated", dash="--"),
             "compensated": dict(color="compensated", dash="-")}
#: plot-area sizes (px) of the figures' panels: the figures come out about 1170 px wide, the page's
#: content width, and scale down with the page
PANEL_RATES = (515, 150)
PANEL_COST = (500, 230)
PANEL_DRIFT = (1090, 220)
PANEL_GRID = (335, 165)  # the state and residual grids, three columns


# ---- small helpers ---------------------------------------------------------------------------
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
    fig = Figure(3, len(cols), panel=PANEL_RATES, sharex=True,
                 title=f"Angular rate, master vs slave, busiest {b - a:.1f} s window "
                       f"(slave rotated by mounting from {mount_src})")
    mm = (tm >= a) & (tm <= b)
    for j, (title, ts, gs, note) in enumerate(cols):
        ms = (ts >= a) & (ts <= b)
        for i, ax_name in enumerate(AXES):
            ax = fig.ax(i, j)
            ax.line(tm[mm], gm[mm, i], color="master", width=1.1, label="master")
            ax.line(ts[ms], gs[ms, i], color="slave", dash="--", width=1.3, opacity=0.9,
                    label="slave (in master frame)")
            ax.ylabel(f"ω{ax_name} (deg/s)")
            if i == 0:
                ax.title(f"{title}\n({note})" if note else title)
                ax.legend("best")
        fig.ax(2, j).xlabel("time since master start (s)")
    return fig.to_svg("angular rates, master vs slave, before and after compensation")


def fig_cost(an: Analysis) -> str | None:
    lat = an.latency
    if lat is None or len(lat.cost_lag_s) == 0:
        return None
    lag_ms = np.asarray(lat.cost_lag_s) * 1e3
    cost = np.asarray(lat.cost, float)
    L, S = lat.latency_s * 1e3, lat.sigma_s * 1e3
    fig = Figure(1, 2, panel=PANEL_COST)
    for k, zoom in enumerate((False, True)):
        ax = fig.ax(0, k)
        ax.line(lag_ms, cost, color="C0", width=1.2, label=f"cost ({lat.method})")
        ax.vline(L, color="C3", width=1.0, label=f"minimum {L:+.3f} ms")
        if math.isfinite(S) and S > 0:
            ax.vspan(L - 3 * S, L + 3 * S, color="C3", opacity=0.15, label=f"±3σ ({3 * S:.3f} ms)")
        for n, (name, me) in enumerate(lat.methods.items()):
            if name != lat.method and math.isfinite(me.latency_s):
                ax.vline(me.latency_s * 1e3, color=f"C{(n + 2) % 10}", width=0.9, dash=":",
                         label=f"{name}: {me.latency_s * 1e3:+.3f} ms")
        ax.xlabel("lag of slave behind master (ms)")
        ax.ylabel("normalised cost (-)")
        if zoom:
            half = max(10 * S if math.isfinite(S) else 0.0,
                       5 * float(np.median(np.diff(lag_ms))) if len(lag_ms) > 1 else 1.0, 2.0)
            ax.xlim(L - half, L + half)
            m = (lag_ms >= L - half) & (lag_ms <= L + half) & np.isfinite(cost)
            if m.any():
                lo, hi = float(np.min(cost[m])), float(np.max(cost[m]))
                pad = 0.05 * (hi - lo or 1.0)
                ax.ylim(lo - pad, hi + pad)
            ax.title("zoom on the minimum")
        else:
            ax.title("latency cost over the search window")
            ax.legend("best")
    return fig.to_svg("latency cost curve and a zoom on its minimum")


def fig_drift(an: Analysis) -> str | None:
    lat = an.latency
    if lat is None or len(lat.window_latency_s) == 0:
        return None
    tc = np.asarray(lat.window_centers_s, float)
    wl = np.asarray(lat.window_latency_s, float) * 1e3
    fig = Figure(1, 1, panel=PANEL_DRIFT)
    ax = fig.ax(0)
    ax.points(tc, wl, color="C0", size=4, label="per-window latency")
    if np.isfinite(tc).any():
        tt = np.linspace(np.nanmin(tc), np.nanmax(tc), 50)
        ax.line(tt, lat.latency_at(tt) * 1e3, color="C3", width=1.2,
                label=f"fit: {lat.latency_s * 1e3:+.3f} ms at mid, "
                      + (f"drift {lat.drift_ppm:+.2f} ppm" if lat.drift_reported_ppm is not None
                         else "no drift fitted"))
    ax.xlabel("time since master start (s)")
    ax.ylabel("latency (ms)")
    ax.title("Latency over the log (clock drift)")
    ax.legend("best")
    return fig.to_svg("latency per window and the drift fit")


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


def _grid(n: int, title: str, sharex: bool = False) -> Figure:
    """A figure of ``n`` panels in rows of three; the cells left over are hidden."""
    ncol = min(3, n)
    nrow = int(math.ceil(n / ncol))
    fig = Figure(nrow, ncol, panel=PANEL_GRID, sharex=sharex, title=title)
    for ax in fig.axes[n:]:
        ax.hide()
    return fig


def state_figures(an: Analysis) -> list[tuple[str, Figure]]:
    """The state-history figures, one per state group: (group, Figure), both runs overlaid with their
    3-sigma envelopes, each state matched between the runs by name."""
    runs = {r: res for r, res in an.alignment.items() if res is not None and res.history_x.size}
    if not runs:
        return []
    # the runs' states by name (the runs may differ: flexure or lever-arm states in one only)
    names, col = _by_name({r: res.history_names for r, res in runs.items()})
    out = []
    for group, idx in _state_groups(names).items():
        fig = _grid(len(idx), f"Transfer alignment: {group} (estimate and 3-sigma bound)")
        for k, i in enumerate(idx):
            ax = fig.axes[k]
            for run, res in runs.items():
                j = col[run].get(names[i])
                if j is None or j >= res.history_x.shape[1]:
                    continue
                t, x, s = res.history_t_s, res.history_x[:, j], res.history_sigma[:, j]
                st = RUN_STYLE.get(run, {})
                ax.line(t, x, width=1.1, label=f"{run}", **st)
                ax.band(t, x - 3 * s, x + 3 * s, color=st.get("color", "C7"), opacity=0.12, label=f"{run} ±3σ")
            ax.title(names[i])
            ax.xlabel("time (s)")
            if k == 0:
                ax.legend("best")
        out.append((group, fig))
    return out


def fig_states(an: Analysis) -> list[tuple[str, str]]:
    """One figure (SVG markup) per state group; both runs overlaid with their 3-sigma envelopes."""
    return [(group, fig.to_svg(f"alignment states: {group}")) for group, fig in state_figures(an)]


def fig_residuals(an: Analysis) -> str | None:
    runs = {r: res for r, res in an.alignment.items() if res is not None and res.residuals.size}
    if not runs:
        return None
    names, col = _by_name({r: res.residual_names for r, res in runs.items()})
    fig = _grid(len(names), "Measurement residuals (innovations) of the alignment filter", sharex=True)
    for ax, name in zip(fig.axes, names):
        for run, res in runs.items():
            j = col[run].get(name)
            if j is not None and j < res.residuals.shape[1]:
                r = res.residuals[:, j]
                rms = float(np.sqrt(np.nanmean(r ** 2))) if np.isfinite(r).any() else float("nan")
                ax.line(res.residual_t_s, r, width=0.8, label=f"{run} (rms {rms:.3g})",
                        color=RUN_STYLE.get(run, {}).get("color", "C7"), opacity=0.8)
        ax.title(name)
        ax.xlabel("time (s)")
        ax.legend("best")
    return fig.to_svg("alignment filter residuals")


# ---- headline and latency quality --------------------------------------------------------------
#: the latency quality keys, grouped for a reader: (group, [(key, label, unit kind)]); keys not listed
#: here are shown under "other" (the raw values are always in the collapsed block below the table)
QUALITY_GROUPS: tuple[tuple[str, tuple[tuple[str, str, str], ...]], ...] = (
    ("Motion", (
        ("motion_dps", "master angular motion (rms)", "dps"),
        ("slave_motion_dps", "slave angular motion (rms)", "dps"),
        ("motion_snr", "motion signal-to-noise ratio", "num"),
        ("too_little_motion", "too little motion to estimate", "flag"),
        ("nan_fraction", "fraction of samples missing (NaN)", "num"),
    )),
    ("Search and fit", (
        ("coarse_latency_s", "coarse search minimum", "ms"),
        ("xcorr_norm_latency_s", "normalised cross-correlation peak at", "ms"),
        ("xcorr_norm_peak", "normalised cross-correlation peak value", "num"),
        ("vector_cost_min", "vector cost at the minimum", "num"),
        ("gls", "generalised least squares (noise model fitted)", "bool"),
        ("residual_rms_dps", "angular-rate residual (rms)", "dps"),
        ("residual_correlation_factor", "residual correlation factor (sigma inflation)", "num"),
        ("overlap_s", "overlap analysed", "s"),
        ("common_rate_hz", "common rate", "hz"),
        ("refine_rate_hz", "refinement rate", "hz"),
        ("lowpass_hz", "low-pass", "hz"),
        ("band_adapted", "band adapted to the motion", "bool"),
        ("rates_hz", "input rates", "hz"),
        ("rate_source", "angular rate taken from", "text"),
        ("periodic", "motion periodic (ambiguous minimum)", "flag"),
        ("periodic_alternatives_s", "other minima (periodic motion)", "ms"),
        ("periodic_alternatives_rejected_s", "other minima rejected", "ms"),
        ("rate_models_gap_s", "gap between the spectral and Kalman fits", "ms"),
        ("mounting_rpy_deg", "mounting from the rate fit (r/p/y)", "deg"),
        ("bias_diff_dph", "gyro bias difference", "dph"),
        ("accel_aided", "accelerometers aid the fit", "bool"),
        ("accel_minus_gyro_lag_s", "accelerometer minus gyro delay", "ms"),
        ("accel_minus_gyro_lag_sigma_s", "&nbsp;&nbsp;its 1&sigma;", "ms"),
        ("accel_lag_solved", "accelerometer delay solved separately", "bool"),
    )),
    ("Windows and drift", (
        ("n_windows", "windows", "int"),
        ("window_chi2_red", "window scatter (reduced chi-square)", "num"),
        ("windows_disagree", "windows disagree", "flag"),
        ("drift_estimated", "drift estimated", "bool"),
        ("drift_sigma_ppm", "drift 1&sigma;", "ppm"),
        ("best_instant_s", "best-determined instant (master clock)", "abs_s"),
        ("latency_at_best_instant_s", "latency at that instant", "ms"),
        ("sigma_at_best_instant_s", "&nbsp;&nbsp;its 1&sigma;", "ms"),
    )),
    ("Noise and flexure", (
        ("flexure_model", "flexure model (Kalman-whitened fit)", "flex"),
    )),
    ("Velocity fit", (
        ("velocity_disagrees", "velocity estimate disagrees", "flag"),
    )),
    ("Stamps", (
        ("stamp_resolution_s", "stamp resolution", "ms"),
        ("stamp_resolution_latency_sigma_s", "&nbsp;&nbsp;its share of the latency 1&sigma;", "ms"),
        ("stamp_jitter_s", "stamp jitter", "ms"),
        ("stamp_jitter_latency_sigma_s", "&nbsp;&nbsp;its share of the latency 1&sigma;", "ms"),
    )),
)
VELOCITY_FIT_KEYS = (
    ("latency_s", "latency (velocity matching)", "ms"), ("sigma_s", "&nbsp;&nbsp;its 1&sigma;", "ms"),
    ("drift_ppm", "drift", "ppm"), ("lever_arm_m", "lever arm x/y/z", "m"),
    ("residual_rms_m_s", "velocity residual (rms)", "m_s"), ("window_chi2_red", "window scatter (reduced chi-square)", "num"),
    ("n_windows", "windows", "int"), ("velocity_steps", "velocity steps removed", "int"),
    ("lowpass_hz", "low-pass", "hz"), ("frame_rotation_deg", "frame rotation", "deg"),
    ("agreement_chi2", "agreement with the rate fit (chi-square)", "num"), ("agrees", "agrees with the rate fit", "bool"),
    ("fused", "fused into the latency", "bool"),
)
_UNITS = {"ms": "ms", "s": "s", "dps": "deg/s", "hz": "Hz", "ppm": "ppm", "deg": "deg", "dph": "deg/h", "m": "m",
          "m_s": "m/s"}


def _qnum(x, kind: str) -> str:
    if isinstance(x, bool):
        return "yes" if x else "no"
    if not isinstance(x, (int, float)) or (isinstance(x, float) and not math.isfinite(x)):
        return _esc(x)
    if kind == "ms":
        ms = x * 1e3
        return f"{ms:.3f}" if ms == 0 or 0.01 <= abs(ms) < 1e5 else f"{ms:.3g}"
    if kind == "deg":
        return f"{x:.4f}" if x == 0 or abs(x) >= 1e-3 else f"{x:.3g}"
    if kind == "int":
        return f"{int(x)}"
    if kind == "abs_s":
        return f"{x:.3f}"
    return f"{x:.4g}"


def _qvalue(x, kind: str, epoch: bool = False) -> str:
    """A quality value for a reader: units, yes/no, per-unit dicts, "not determined" for None."""
    if x is None:
        return "<span class=note>not determined</span>"
    if kind in ("bool", "flag"):
        yes = bool(x)
        cls = " class=warn" if (kind == "flag" and yes) else ""
        return f"<span{cls}>{'yes' if yes else 'no'}</span>"
    if kind == "flex" and isinstance(x, dict):
        return (f"&sigma; {_vec(x.get('sigma_deg'), '.3g')} deg, correlation time "
                f"{_fmt(x.get('beta_1_s'), '.3g', 's')}")
    unit = _UNITS.get(kind, "")
    if isinstance(x, dict):
        return ", ".join(f"{_esc(k)} {_qvalue(v, kind, epoch)}" for k, v in x.items())
    if isinstance(x, (list, tuple)):
        if not x:
            return "none"
        return " / ".join(_qnum(v, kind) for v in x) + (f" {unit}" if unit else "")
    if kind == "text":
        return _esc(x)
    if kind == "abs_s" and isinstance(x, (int, float)):
        s = f"{x:.3f} s"
        if epoch and math.isfinite(x):
            import datetime as dt

            s += " (" + dt.datetime.fromtimestamp(x, dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC)"
        return s
    return _qnum(x, kind) + (f" {unit}" if unit else "")


def _auto_kind(key: str) -> str:
    for suffix, kind in (("_latency_s", "ms"), ("_sigma_s", "ms"), ("_s", "ms"), ("_ppm", "ppm"), ("_hz", "hz"),
                         ("_dps", "dps"), ("_dph", "dph"), ("_deg", "deg"), ("_m_s", "m_s"), ("_m", "m")):
        if key.endswith(suffix):
            return kind
    return "num"


def quality_html(lat: dict, epoch: bool = False) -> str:
    """The latency quality as a grouped table, the raw values in a collapsed <details> block."""
    q = dict(lat.get("quality") or {})
    if not q:
        return "<p class=note>No quality figures (the latency was not estimated).</p>"
    rows: list[str] = []
    shown: set[str] = {"warnings", "velocity_fit", "sigma_budget"}

    def group(title: str, items: list[tuple[str, str]]) -> None:
        if items:
            rows.append(f"<tr><th colspan=2 class=grp>{_esc(title)}</th></tr>")
            rows.extend(f"<tr><td>{label}</td><td class=num>{value}</td></tr>" for label, value in items)

    for title, keys in QUALITY_GROUPS:
        items = [(label, _qvalue(q[k], kind, epoch)) for k, label, kind in keys if k in q]
        shown.update(k for k, _, _ in keys)
        if title == "Velocity fit":
            vf = q.get("velocity_fit")
            if isinstance(vf, dict):
                items = [(label, _qvalue(vf[k], kind)) for k, label, kind in VELOCITY_FIT_KEYS if k in vf] + items
                known = {k for k, _, _ in VELOCITY_FIT_KEYS}
                items += [(_esc(k.replace("_", " ")), _qvalue(v, _auto_kind(k))) for k, v in vf.items() if k not in known]
            elif "velocity_fit" in q:
                items = [("velocity matching", "<span class=note>not run (a unit has no NED velocity)</span>")] + items
        group(title, items)
    budget = q.get("sigma_budget")
    if isinstance(budget, dict) and budget:
        vals = {k: v for k, v in budget.items() if isinstance(v, (int, float))}
        rss = math.sqrt(sum(v * v for v in vals.values())) if vals else float("nan")
        items = [(_esc(k.replace("_", " ")), _qvalue(v, "ms")) for k, v in budget.items()]
        items.append(("<b>root-sum-square</b>", f"<b>{_qvalue(rss, 'ms')}</b> (quoted 1&sigma; "
                      f"{_qvalue(lat.get('sigma_s'), 'ms')})"))
        group("Sigma budget (what makes up the 1\u03c3)", items)
    other = [(_esc(k.replace("_", " ")), _qvalue(v, _auto_kind(k), epoch)) for k, v in q.items() if k not in shown]
    group("Other", other)
    warns = q.get("warnings") or []
    if warns:
        group("Latency warnings", [("warning", f"<span class=warn>{_esc(w)}</span>") for w in warns])
    raw = html.escape(json.dumps(q, indent=1, default=str))
    return ("<table class=quality>" + "".join(rows) + "</table>"
            f"<details><summary>raw values (report.json latency.quality)</summary><pre>{raw}</pre></details>")


def _arcmin(v) -> str:
    if v is None:
        return "&ndash;"
    return " ".join("&ndash;" if x is None else f"{x * 60:.3g}&prime;" for x in v)


def headline_html(rep: dict) -> str:
    """The verdict at the top: latency +- sigma (and when), drift, mounting +- sigma, converged, status."""
    status = rep.get("status", "ok")
    lat = rep.get("latency") or {}
    cells: list[tuple[str, str, str]] = []  # (title, big value, small print)
    if "failed" in lat or lat.get("latency_s") is None:
        cells.append(("latency", "<span class=fail>not determined</span>", _esc(lat.get("failed", ""))))
    else:
        t_at, utc = latency_instant(rep)
        when = (f"at {_esc(utc)}" if utc else (f"at {t_at:.3f} s (master clock)" if t_at is not None else ""))
        sig = lat.get("sigma_s")
        cells.append(("latency (slave behind master)",
                      f"{lat['latency_s'] * 1e3:+.3f} ms <small>&plusmn; {_fmt(None if sig is None else sig * 1e3, '.3f')}"
                      " ms (1&sigma;)</small>", f"{when}, the middle of the analysed window; method {_esc(lat.get('method'))}"))
        dsig = (lat.get("quality") or {}).get("drift_sigma_ppm")
        why = (lat.get("quality") or {}).get("drift_not_estimated")
        if lat.get("drift_ppm") is None and why:
            cells.append(("clock drift", "not estimated", _esc(why)))
        else:
            cells.append(("clock drift", f"{_fmt(lat.get('drift_ppm'), '+.2f')} ppm"
                          + (f" <small>&plusmn; {dsig:.2f} ppm (1&sigma;)</small>" if isinstance(dsig, (int, float))
                             else ""),
                          "the slave's clock rate error (&micro;s per s)"))
    align = rep.get("alignment") or {}
    run = next((r for r in ("compensated", "uncompensated")
                if (align.get(r) or {}).get("mounting_rpy_deg") and None not in align[r]["mounting_rpy_deg"]), None)
    if run:
        a = align[run]
        cells.append((f"mounting r/p/y ({run})", f"{_vec(a['mounting_rpy_deg'], '+.4f')} <small>deg</small>",
                      f"&plusmn; {_arcmin(a.get('mounting_sigma_deg'))} (1&sigma;, arcmin)"))
    else:
        why = "; ".join(f"{r}: {(align.get(r) or {}).get('skipped', 'not determined')}" for r in RUNS)
        cells.append(("mounting", "<span class=fail>not determined</span>", _esc(why)))
    conv = []
    for r in RUNS:
        a = align.get(r) or {}
        if "skipped" in a:
            conv.append(f"{r}: <span class=warn>skipped</span>")
        elif a.get("converged_s") is not None:
            conv.append(f"{r}: <span class=ok>yes</span>, {a['converged_s']:.1f} s")
        elif a.get("still_converging") is False:
            conv.append(f"{r}: <span class=ok>settled</span> (above the navigation-grade thresholds)")
        else:
            conv.append(f"{r}: <span class=warn>not converged</span>")
    main_conv = align.get(run or "compensated") or {}
    big = ("<span class=warn>skipped</span>" if "skipped" in main_conv or not main_conv
           else "<span class=ok>converged</span>" if main_conv.get("converged_s") is not None
           else "<span class=ok>settled</span>" if main_conv.get("still_converging") is False
           else "<span class=warn>not converged</span>")
    cells.append(("alignment", big, "; ".join(conv)))
    warns = report_warnings(rep)
    damage = input_damage(rep)
    nw = f"{len(warns)} warning{'s' if len(warns) != 1 else ''}"
    verdict = (f"<p class=verdict>Status <span class={_status_cls(status)}>{_esc(status)}</span>"
               + (" <span class=warn>(damaged input)</span>" if damage else "")
               + f" &middot; {nw}" + (" (<a href='#warnings'>listed below</a>)" if warns else "") + "</p>")
    out = [verdict, "<div class=headline>"]
    out += [f"<div class='cell{' wide' if t.startswith('mounting') else ''}'><div class=t>{t}</div>"
            f"<div class=v>{v}</div><div class=s>{s}</div></div>" for t, v, s in cells]
    out.append("</div>")
    if damage:
        out.append(f"<p class=warn>Damaged input: {_esc(damage)}. The readable part was analysed.</p>")
    skipped = rep.get("skipped") or {}
    if skipped:
        out.append("<p class=warn>" + "; ".join(f"skipped {_esc(k)}: {_esc(v)}" for k, v in skipped.items()) + "</p>")
    return "".join(out)


#: report.json's residual_rms keys of the residuals' size, as the summary says them: (label, unit)
RESIDUAL_LABELS = {"vel_m_s": ("velocity", "m/s"), "att_deg": ("attitude", "deg")}


def _convergence_text(a: dict) -> str:
    """An alignment run's convergence as the headline card says it."""
    if a.get("converged_s") is not None:
        return f"converged after {a['converged_s']:.1f} s"
    if a.get("still_converging") is False:
        return "settled (above the navigation-grade thresholds)"
    return "not converged"


def _residual_text(rms: dict) -> str:
    """report.json's residual_rms of a run in words: the residuals' rms per measurement, then the mean
    normalised innovation squared over its degrees of freedom."""
    parts = [f"{label} {_fmt(rms[k], '.4g', unit)}" for k, (label, unit) in RESIDUAL_LABELS.items() if k in rms]
    parts += [f"{_esc(k)} {_fmt(v, '.4g')}" for k, v in rms.items() if k not in RESIDUAL_LABELS
              and k not in ("nis_mean", "nis_dof")]
    out = "residual rms " + ", ".join(parts) if parts else "no residuals"
    if rms.get("nis_mean") is not None:
        dof = rms.get("nis_dof")
        out += f"; mean NIS {_fmt(rms['nis_mean'], '.4g')}" + (f" ({dof:g} dof)" if isinstance(dof, (int, float)) else "")
    return out


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
th{background:#eef2f6;font-weight:600;overflow-wrap:normal} td.num{text-align:right;font-family:Menlo,Consolas,monospace}
figure{margin:8px 0} figure svg{display:block}
.ok{color:#2a9d8f;font-weight:600} .warn{color:#e76f51;font-weight:600} .fail{color:#c1121f;font-weight:600}
.note{color:#5c6b7a;font-size:12px} ul{margin:4px 0 4px 18px;font-size:13px}
.headline{display:flex;flex-wrap:wrap;gap:10px;margin:4px 0 8px}
.headline .cell{flex:1 1 170px} .headline .wide{flex:2 1 330px}
.verdict{font-size:18px;margin:2px 0 8px} .verdict span{font-size:20px}
.headline .cell{border:1px solid #dde3ea;border-radius:6px;padding:8px 12px;background:#fafbfc}
.headline .t{font-size:12px;color:#5c6b7a;text-transform:uppercase;letter-spacing:.03em}
.headline .v{font-size:20px;font-weight:600;margin:2px 0;font-family:Menlo,Consolas,monospace}
.headline .v small{font-size:13px;font-weight:400} .headline .s{font-size:12px;color:#5c6b7a}
table.quality td:first-child{min-width:330px} th.grp{background:#1d3557;color:#fff}
details{margin:8px 0;font-size:12px} summary{cursor:pointer;color:#1d3557}
pre{background:#f4f6f8;border:1px solid #dde3ea;padding:8px;max-height:420px;overflow:auto;font-size:11px}
"""


def _status_cls(status: str) -> str:
    return {"ok": "ok", "partial": "warn"}.get(status, "fail")


def _method_caveat(name: str, me: dict, lat: dict) -> str:
    """What a reader must know beside a comparison method's figure: the seeds' methods assume the units'
    axes aligned (a mounting rotation makes their figure meaningless), and their sigma is their grid's
    resolution, not an uncertainty: a figure that differs from the headline by more than 3 combined sigma
    is said to."""
    if name == lat.get("method"):
        return ""
    said = []
    if "axes assumed aligned" in str(me.get("note", "")):
        said.append("axes assumed aligned")
    ls, ss, L, S = me.get("latency_s"), me.get("sigma_s"), lat.get("latency_s"), lat.get("sigma_s")
    if all(isinstance(x, (int, float)) and math.isfinite(x) for x in (ls, ss, L, S)):
        if abs(ls - L) > 3.0 * math.hypot(ss, S):
            said.append(f"differs from {lat.get('method')} by {(ls - L) * 1e3:+.3f} ms")
    return f" ({'; '.join(said)})" if said else ""


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
        dsig = (lat.get("quality") or {}).get("drift_sigma_ppm")
        why = (lat.get("quality") or {}).get("drift_not_estimated")
        if lat["drift_ppm"] is None and why:
            t.append(f"<tr><th>clock drift</th><td colspan=2>not estimated: {_esc(why)}</td></tr>")
        else:
            t.append(f"<tr><th>clock drift</th><td class=num>{_fmt(lat['drift_ppm'], '+.2f', 'ppm')}</td>"
                     f"<td class=num>{_fmt(dsig if isinstance(dsig, (int, float)) else None, '.2f', 'ppm')}</td></tr>")
        w = lat.get("window_s") or [None, None]
        t.append(f"<tr><th>method / window (master stamps)</th><td colspan=2>{_esc(lat['method'])}, "
                 f"[{_fmt(w[0], '.3f')}, {_fmt(w[1], '.3f')}] s</td></tr>")
        for name, me in lat.get("methods", {}).items():
            ls, ss = me.get("latency_s"), me.get("sigma_s")
            t.append(f"<tr><th title='{_esc(me.get('note') or '')}'>&nbsp;&nbsp;method {_esc(name)}"
                     f"{_esc(_method_caveat(name, me, lat))}</th><td class=num>{_fmt(None if ls is None else ls * 1e3, '+.3f', 'ms')}</td>"
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
        t.append(f"<tr><th>&nbsp;&nbsp;converged / residual rms ({run})</th><td colspan=2>"
                 f"{_convergence_text(a)}; {_residual_text(a.get('residual_rms') or {})}</td></tr>")
    t.append("</table>")
    out.append("".join(t))
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
            if ii.get(f"{name}_gimbal_lock"):
                said = GIMBAL_LOCK_SAID.format(quat=f"{name}_quat_wxyz")
                t.append(f"<tr><td></td><td colspan=2 class=note>{_esc(said)}</td></tr>")
    t.append("</table>")
    cons = al.get("consistency")
    if cons and cons.get("note"):
        cls = "warn" if cons.get("agrees") is False else "note"
        t.append(f"<p class={cls}>{'WARNING: ' if cons.get('agrees') is False else ''}{_esc(cons['note'])}</p>")
    return "".join(t)


def render(rep: dict, an: Analysis) -> str:
    """The report page as a string (pure function of the report dict and the analysis data)."""
    R, mount_src = an.mounting()
    sections: list[tuple[str, str, str]] = []  # (id, title, html)
    status = rep.get("status", "ok")
    sections.append(("headline", "Result", headline_html(rep)))
    sections.append(("summary", "Summary",
                     f"<p>Status: <span class={_status_cls(status)}>{_esc(status)}</span></p>" + _summary_html(rep)
                     + _imu_to_imu_html(rep)))
    sections.append(("quality", "Latency quality",
                     quality_html(rep.get("latency") or {}, epoch=rep["master"].get("clock") == "epoch")))

    def img(svg: str | None, alt: str, missing: str) -> str:
        return f'<figure aria-label="{_esc(alt)}">{svg}</figure>' if svg else f"<p class=note>{_esc(missing)}</p>"

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

    # the warnings the headline counts first (every stage's, as report.json lists them), then the notes
    warnings = report_warnings(rep)
    warn = [f"<li class=warnitem><b>{_esc(st or 'warning')}</b>: <span class=warn>{_esc(w)}</span></li>"
            for st, w in warnings]
    said = [w for _, w in warnings]

    def fresh(text: str) -> bool:  # (not one of the warnings above, in its own words)
        return text not in said

    for role in ("master", "slave"):
        warn += [f"<li><b>{role}</b>: {_esc(w)}</li>" for w in rep[role].get("warnings", []) if fresh(w)]
    warn += [f"<li><b>skipped {_esc(k)}</b>: {_esc(v)}</li>" for k, v in rep.get("skipped", {}).items()
             if fresh(f"{k}: {v}") and not any(str(v) in w for w in said)]
    for run in RUNS:
        warn += [f"<li><b>alignment {run}</b>: {_esc(n)}</li>" for n in rep["alignment"].get(run, {}).get("notes", [])
                 if fresh(n) and fresh(f"{run}: {n}")]
    sections.append(("warnings", "Warnings and notes", "<ul>" + "".join(warn) + "</ul>" if warn
                     else "<p class=note>None.</p>"))
    tim = rep.get("timings_s", {})
    # this page is written before the report's and the recording's stages end: their times are report.json's
    later = {k for k in ("report", "recording") if k in tim and not tim[k]}
    sections.append(("timings", "Timings", "<table><tr>" + "".join(f"<th>{_esc(k)}</th>" for k in tim)
                     + "</tr><tr>" + "".join("<td class=note>in report.json</td>" if k in later
                                             else f"<td class=num>{_fmt(v, '.2f', 's')}</td>" for k, v in tim.items())
                     + "</tr></table>"
                     + ("<p class=note>The report and the recording are written after this page; their times and "
                        "the total are in report.json.</p>" if later else "")))
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
