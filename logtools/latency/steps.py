"""Stage 6b, the clock-step check: does one line (L + drift (t - t_mid)) describe the windows' delays, or
one line with an offset step at one breakpoint (common drift)? A unit whose clock stepped or was reset
mid-log gives two latencies; one line through them turns a step into drift (sweep F1: a 20 ms step at
the middle of a 2 min log read as 240 ppm) and its sigma into a blend. Judged by ``StepConfig``."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from logtools.latency.coarse import window_start
from logtools.latency.fit import refine
from logtools.latency.prepare import Ctx
from logtools.latency.windows import Overlap, drift_windows


def step_windows(ctx: Ctx, ov: Overlap, latency_s: float, drift: float, band_s: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each check window's own delay at its centre (searched +- ``band_s`` about the line, then refined with
    the line's drift inside it), its sigma, and its bounds (K, 2); windows with little motion left out (as
    the drift windows)."""
    cfg = ctx.cfg
    sc = cfg.steps
    wctx = replace(ctx, cfg=replace(cfg, windows=replace(cfg.windows, window_s=sc.window_s,
                                                         max_windows=sc.max_windows)))
    t_m, a, valid, itp, t_mid = ov.t_m, ov.a, ov.valid, ov.itp, ov.t_mid
    wins = drift_windows(wctx, ov.w0, ov.w1, t_m[valid & itp.ok(t_m + latency_s)])  # (as the drift windows)
    out = []
    for a0, a1 in wins:
        ws = (t_m >= a0) & (t_m <= a1)
        if ws.sum() < cfg.windows.min_window_samples:
            continue
        tc = 0.5 * (a0 + a1)
        pred = latency_s + drift * (tc - t_mid)
        dw = window_start(ctx, a0, a1, pred, band_s)
        if dw is None:
            continue
        f = refine(t_m[ws], a[ws], valid[ws], itp, dw, drift, tc, fit_drift=False, iters=cfg.refine.window_iters,
                   cfg=cfg)
        if f.ok and np.isfinite(f.sigma_latency_s):
            out.append((tc, f.latency_s, max(f.sigma_latency_s, cfg.uncertainty.sigma_floor_s), f.motion_rms, a0, a1))
    if not out:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 2))
    c, lat, sig, mot, b0, b1 = map(np.asarray, zip(*out))
    keep = mot >= cfg.windows.window_motion_fraction * np.median(mot)
    return c[keep], lat[keep], sig[keep], np.stack([b0, b1], axis=1)[keep]


def _wls(A: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted least squares: (parameters, their covariance, chi-square)."""
    N = A.T @ (A * w[:, None])
    cov = np.linalg.pinv(N)
    p = cov @ (A.T @ (w * y))
    r = y - A @ p
    return p, cov, float(np.sum(w * r * r))


def step_test(x: np.ndarray, y: np.ndarray, s: np.ndarray, min_side: int) -> dict | None:
    """The best single offset step in the delays ``y`` (sigmas ``s``) at instants ``x`` (sorted, relative to
    the middle), common drift: breakpoints between windows, and inside one window (that window, a blend of
    both sides, left out). Returns the figures of the best breakpoint (largest chi-square drop, scaled by
    the step model's reduced chi-square where above 1), or None with too few windows."""
    n = len(x)
    best = None
    for j in range(min_side, n - min_side + 1):  # between windows j-1 and j
        for excl in (None, j):  # ... or inside window j (left out)
            use = np.ones(n, bool)
            if excl is not None:
                if j > n - min_side - 1:
                    continue
                use[excl] = False
            xs, ys, ws = x[use], y[use], 1.0 / s[use] ** 2
            after = (np.arange(n) >= (j if excl is None else j + 1))[use]
            m = int(use.sum())
            if m - 3 < 1:
                continue
            one = np.ones(m)
            _, _, chi_line = _wls(np.stack([one, xs], 1), ys, ws)
            _, _, chi_curve = _wls(np.stack([one, xs, xs * xs], 1), ys, ws)
            p, cov, chi_step = _wls(np.stack([one, xs, after.astype(float)], 1), ys, ws)
            scale = max(1.0, chi_step / (m - 3))
            score = (chi_line - chi_step) / scale
            if best is None or score > best["delta_chi2"]:
                best = {"delta_chi2": score, "delta_vs_curve": (chi_curve - chi_step) / scale, "scale": scale,
                        "p": p, "sigma_step": float(np.sqrt(max(cov[2, 2], 0.0)) * np.sqrt(scale)),
                        "cov": cov * scale, "j": j, "inside": excl is not None, "chi2_red": chi_step / (m - 3)}
    return best


def clock_step(ctx: Ctx, ov: Overlap, latency_s: float, drift: float, alternatives_s=(), d0_s: float = 0.0
               ) -> dict | None:
    """``latency.quality["clock_step"]``: where one line does not describe the windows' delays but one with
    an offset step does (``StepConfig``): {t_s (absolute master time of the step), t_rel_s, step_s, sigma_s,
    latency_before_s, latency_after_s (at the step), drift_ppm (common), delta_chi2, delta_vs_curve,
    n_windows, window_latency_s, window_centers_s (absolute)}; None without a step (or without the windows
    to judge)."""
    sc = ctx.cfg.steps
    if not sc.check:
        return None
    band = sc.search_s
    alts = [abs(float(x) - d0_s) for x in alternatives_s if abs(float(x) - d0_s) > 0]
    if alts:
        band = min(band, sc.periodic_band * min(alts))
    c, lat, sig, bounds = step_windows(ctx, ov, latency_s, drift, band)
    if len(c) < sc.min_windows:
        return None
    o = np.argsort(c)
    c, lat, sig, bounds = c[o], lat[o], sig[o], bounds[o]
    x = c - ov.t_mid
    b = step_test(x, lat, sig, sc.min_side)
    if b is None:
        return None
    step, s_step = float(b["p"][2]), b["sigma_step"]
    min_step = max(sc.min_step_s, sc.min_step_resolution * max(ctx.stamp_resolution_s))
    if not (b["delta_chi2"] >= sc.min_delta_chi2 and b["delta_vs_curve"] >= sc.min_delta_vs_curve
            and abs(step) >= min_step and abs(step) >= sc.min_step_sigmas * s_step):
        return None
    j = b["j"]
    if b["inside"]:  # inside window j: its middle (the window blends both sides)
        t_rel = float(c[j])
    else:  # between windows j-1 and j
        t_rel = float(0.5 * (bounds[j - 1, 1] + bounds[j, 0]))
    L0, dr = float(b["p"][0]), float(b["p"][1])
    before = L0 + dr * (t_rel - ov.t_mid)
    return {
        "t_s": float(ctx.t0_abs_s + t_rel),
        "t_rel_s": t_rel,
        "step_s": step,
        "sigma_s": float(s_step),
        "latency_before_s": float(before),
        "latency_after_s": float(before + step),
        "drift_ppm": float(dr * 1e6),
        "delta_chi2": float(b["delta_chi2"]),
        "delta_vs_curve": float(b["delta_vs_curve"]),
        "chi2_red": float(b["chi2_red"]),
        "n_windows": int(len(c)),
        "window_centers_s": [float(ctx.t0_abs_s + t) for t in c],
        "window_latency_s": [float(v) for v in lat],
        "window_sigma_s": [float(v) for v in sig],
    }
