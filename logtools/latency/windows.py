"""Stage 5, windows and drift: the drift windows, their delays and line (outliers rejected), the joint
(L, drift) fit over the whole overlap started from them, and the windows' check of a fit's sigma."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from logtools.conventions import median_step_s
from logtools.errors import AnalysisError
from logtools.latency.coarse import window_start
from logtools.latency.fit import Fit, refine
from logtools.latency.gls import window_chi2
from logtools.latency.inputs import inband_noise_dps
from logtools.latency.prepare import Ctx
from logtools.resample import Interpolant


def _gaps(t_ok: np.ndarray, dt: float | None = None) -> np.ndarray:
    """Where the instants ``t_ok`` (sorted, s) have a gap: a step beyond max(1 s, 10 of their median steps;
    ``dt``: that median, where the caller has it)."""
    return np.flatnonzero(np.diff(t_ok) > max(1.0, 10.0 * (median_step_s(t_ok) if dt is None else dt)))


def _has_gap(t_ok: np.ndarray) -> bool:
    return len(t_ok) > 1 and len(_gaps(t_ok)) > 0


def drift_windows(ctx: Ctx, t0: float, t1: float, t_ok: np.ndarray | None = None, in_runs: bool = False
                  ) -> list[tuple[float, float]]:
    """The drift windows over [t0, t1]: about cfg.windows.window_s each (3..MAX_WINDOWS). With ``t_ok`` (the instants
    that have data in both units) covering less than cfg.windows.window_data_fraction of the span (gaps), or with
    ``in_runs``, windows are laid in the runs of data between the gaps instead (none across one), their number
    shared by the runs' lengths (runs shorter than cfg.windows.min_window_s left out)."""
    cfg = ctx.cfg
    T = t1 - t0
    if t_ok is not None and len(t_ok) > 1:
        dt = median_step_s(t_ok)
        if in_runs or len(t_ok) * dt < cfg.windows.window_data_fraction * T:
            cut = _gaps(t_ok, dt)
            runs = [(float(t_ok[a]), float(t_ok[b])) for a, b in
                    zip(np.concatenate([[0], cut + 1]), np.concatenate([cut, [len(t_ok) - 1]]))]
            runs = [r for r in runs if r[1] - r[0] >= cfg.windows.min_window_s]
            T_ok = sum(b - a for a, b in runs)
            K = int(np.clip(np.floor(T_ok / cfg.windows.window_s), 1, cfg.windows.max_windows))
            if T_ok >= cfg.windows.windows3_min_s:
                K = max(K, 3)
            K = min(K, int(sum(np.floor((b - a) / cfg.windows.min_window_s) for a, b in runs)))
            if not runs or K < 1:
                return []
            # largest remainder: each run at least one window, the rest by length, none below cfg.windows.min_window_s
            share = np.array([b - a for a, b in runs]) / T_ok * K
            k_run = np.maximum(1, np.floor(share)).astype(int)
            cap = np.floor(np.array([b - a for a, b in runs]) / cfg.windows.min_window_s).astype(int)
            for j in np.argsort(-(share - np.floor(share))):
                if k_run.sum() >= K:
                    break
                if k_run[j] < cap[j]:
                    k_run[j] += 1
            out: list[tuple[float, float]] = []
            for (a, b), k in zip(runs, k_run):
                e = np.linspace(a, b, int(k) + 1)
                out += list(zip(e[:-1], e[1:]))
            return out
    K = int(np.clip(np.floor(T / cfg.windows.window_s), 1, cfg.windows.max_windows))
    if T >= cfg.windows.windows3_min_s:
        K = max(K, 3)
    edges = np.linspace(t0, t1, K + 1)
    return list(zip(edges[:-1], edges[1:]))


def window_snr(ctx: Ctx, wmot: np.ndarray) -> np.ndarray:
    """Motion/noise RMS of windows whose master rate varies by ``wmot`` (RMS about the mean, rad/s, of the
    refinement samples: low-passed at ``ctx.cutoff_hz``, so the noise is counted in that band): the motion
    beyond the master's own noise (a window of noise alone is no motion, whichever unit is the noisier)
    against the noisier unit's noise; infinite where no unit's noise is known."""
    def noise_dps(u) -> float:  # (over the refinement's band; 0 where the unit's noise is not known)
        if not (np.isfinite(u.noise_dps) and u.noise_dps > 0 and u.rate_hz > 0):
            return 0.0
        return float(inband_noise_dps(u, ctx.cutoff_hz))
    n_m = noise_dps(ctx.master)
    noise = max(n_m, noise_dps(ctx.slave))
    if noise <= 0:
        return np.full(len(wmot), np.inf)
    return np.sqrt(np.maximum(np.degrees(np.asarray(wmot, float)) ** 2 - n_m ** 2, 0.0)) / noise


def wls_line(x: np.ndarray, y: np.ndarray, sig: np.ndarray) -> tuple[float, float, np.ndarray]:
    w = 1.0 / np.maximum(sig, 1e-12) ** 2
    A = np.stack([np.ones_like(x), x], axis=1)
    N = A.T @ (A * w[:, None])
    p = np.linalg.solve(N, A.T @ (w * y))
    return float(p[0]), float(p[1]), np.linalg.inv(N)


def fit_window_chi2(f: Fit, centers: np.ndarray, lats: np.ndarray, sigs: np.ndarray, t_mid: float) -> float:
    """Reduced chi-square of the window estimates about f's line L + drift (t - t_mid) (1 below 3 windows)."""
    return window_chi2(centers, lats, sigs, f.latency_s, f.drift, t_mid)


@dataclass(frozen=True)
class Overlap:
    """The refinement rows of the analysed window [w0, w1]: master instants, rates, validity, and the
    slave's interpolant."""

    t_m: np.ndarray
    a: np.ndarray
    valid: np.ndarray
    itp: Interpolant
    w0: float
    w1: float

    @property
    def t_mid(self) -> float:
        return 0.5 * (self.w0 + self.w1)


@dataclass(frozen=True)
class WindowSet:
    """Window delay estimates at their centres (s, master relative), their sigmas, and each centre's
    window bounds (every window that fitted, before the motion and outlier checks)."""

    centers: np.ndarray
    lats: np.ndarray
    sigs: np.ndarray
    bounds: dict

    @staticmethod
    def empty() -> "WindowSet":
        return WindowSet(np.zeros(0), np.zeros(0), np.zeros(0), {})

    def __len__(self) -> int:
        return len(self.centers)


def window_fits(ctx: Ctx, ov: Overlap, wins: list, line: tuple[float, float] | None, d_center: float,
                drift_center: float, search_ppm: float) -> WindowSet:
    """Each window's delay at its centre. The drift inside a window is that of ``line`` (L, drift at
    t_mid), else none: a window's delay without it is that of the window's motion centroid, not its
    centre (100 ppm over a 15 s window whose motion sits at one end: 0.7 ms). Windows with little motion
    (below a fifth of the median's; without the accelerometers' aid, not beyond the noise: ``window_snr``)
    are left out."""
    cfg = ctx.cfg
    t_m, a, valid, t_mid = ov.t_m, ov.a, ov.valid, ov.t_mid
    centers, lats, sigs, wmot, bounds = [], [], [], [], {}
    for (a0, a1) in wins if len(wins) >= 3 else []:
        ws = (t_m >= a0) & (t_m <= a1)
        if ws.sum() < cfg.windows.min_window_samples:
            continue
        tc = 0.5 * (a0 + a1)
        if line is None:
            dr_w = 0.0
            pred = d_center + drift_center * (tc - t_mid)
            band = search_ppm * 1e-6 * abs(tc - t_mid) + cfg.windows.window_search_margin_steps * ctx.dt_s
            dw = window_start(ctx, a0, a1, pred, band)
            if dw is None:
                continue
        else:
            dr_w = line[1]
            dw = line[0] + dr_w * (tc - t_mid)
        f = refine(t_m[ws], a[ws], valid[ws], ov.itp, dw, dr_w, tc, fit_drift=False, iters=cfg.refine.window_iters, cfg=cfg)
        if f.ok and np.isfinite(f.sigma_latency_s):
            bounds[float(tc)] = (a0, a1)
            centers.append(tc)
            lats.append(f.latency_s)
            sigs.append(max(f.sigma_latency_s, cfg.uncertainty.sigma_floor_s))
            wmot.append(f.motion_rms)
    centers, lats, sigs, wmot = map(np.asarray, (centers, lats, sigs, wmot))
    if len(wmot):
        keep = wmot >= cfg.windows.window_motion_fraction * np.median(wmot)  # windows with enough motion
        if ctx.acc_src is None:  # gyros alone: a window of noise carries no delay (the median may be one)
            keep &= window_snr(ctx, wmot) >= cfg.windows.window_min_snr
        centers, lats, sigs = centers[keep], lats[keep], sigs[keep]
    return WindowSet(centers, lats, sigs, bounds)


def reject_outliers(w: WindowSet, t_mid: float, reject_sigmas: float) -> tuple[WindowSet, float, float]:
    """Windows that locked on a wrong minimum (little motion in them: the linearised sigma does not
    hold there) are outliers of the line: rejected one at a time beyond ``reject_sigmas``. Returns the
    windows kept and their line (L, drift at t_mid)."""
    centers, lats, sigs = w.centers, w.lats, w.sigs
    keep = np.ones(len(centers), bool)
    while keep.sum() > 3:
        L0, dr0, _ = wls_line(centers[keep] - t_mid, lats[keep], sigs[keep])
        z = np.abs(lats - (L0 + dr0 * (centers - t_mid))) / sigs
        j = int(np.argmax(np.where(keep, z, -1.0)))
        if z[j] <= reject_sigmas:
            break
        keep[j] = False
    centers, lats, sigs = centers[keep], lats[keep], sigs[keep]
    L0, dr0, _ = wls_line(centers - t_mid, lats, sigs)
    return WindowSet(centers, lats, sigs, w.bounds), L0, dr0


def joint_fit(ctx: Ctx, ov: Overlap, d_center: float, drift_center: float, search_ppm: float
              ) -> tuple[Fit, WindowSet, dict]:
    """Windows along the overlap (each: integer-lag search around the predicted lag, then refinement),
    a weighted line through them, then the joint (L, drift) fit over the whole overlap, started from the
    line and from the central fit (the lower cost wins); the windows again with its drift where that
    matters. With fewer than 3 usable windows, one global fit without drift. Returns (fit, windows,
    the bounds of every window that fitted)."""
    cfg = ctx.cfg
    t_m, a, valid, itp, t_mid = ov.t_m, ov.a, ov.valid, ov.itp, ov.t_mid
    t_ok = t_m[valid & itp.ok(t_m + d_center)]
    wins = drift_windows(ctx, ov.w0, ov.w1, t_ok)
    w = window_fits(ctx, ov, wins, None, d_center, drift_center, search_ppm)
    if len(w) < 3 and _has_gap(t_ok):
        # a gap inside a window can make its lag search fail (a 5 s gap in one of a 60 s log's three
        # windows: no drift at all); where fewer than three windows fit, they are laid in the runs of data
        # between the gaps instead, as for a log with more gaps (nothing changes where three fitted, or
        # where the data have no gap)
        again = drift_windows(ctx, ov.w0, ov.w1, t_ok, in_runs=True)
        if again != wins:
            w2 = window_fits(ctx, ov, again, None, d_center, drift_center, search_ppm)
            if len(w2) >= 3:
                wins, w = again, w2
    bounds = dict(w.bounds)
    fin = None
    if len(w) >= 3:
        w, L0, dr0 = reject_outliers(w, t_mid, cfg.windows.window_reject)
        cands = [refine(t_m, a, valid, itp, L0, dr0, t_mid, fit_drift=True, cfg=cfg),
                 refine(t_m, a, valid, itp, d_center, 0.0, t_mid, fit_drift=True, cfg=cfg)]
        cands = [c for c in cands if c.ok]
        fin = min(cands, key=lambda c: c.residual_rms) if cands else None
        half = 0.5 * max(b - a for a, b in bounds.values())
        if (cfg.windows.window_drift and fin is not None
                and abs(fin.drift) * half > cfg.windows.window_drift_fraction * float(np.median(w.sigs))):
            # the windows again, with the joint fit's drift inside each (a window's own drift-free delay
            # is its motion centroid's: windows of uneven motion scatter about the line for nothing)
            w2 = window_fits(ctx, ov, wins, (fin.latency_s, fin.drift), d_center, drift_center, search_ppm)
            bounds.update(w2.bounds)
            if len(w2) >= 3:
                w, _, _ = reject_outliers(w2, t_mid, cfg.windows.window_reject)
    if fin is None:
        w = WindowSet.empty()
        fin = refine(t_m, a, valid, itp, d_center, 0.0, t_mid, fit_drift=False, cfg=cfg)
        if not fin.ok:
            raise AnalysisError("latency refinement failed (too little valid overlapping data)")
    return fin, w, bounds


#: a window refit: (rows of the window, its centre, start lag, drift) -> Fit
Refit = Callable[[np.ndarray, float, float, float], Fit]


def checked_windows(ov: Overlap, f: Fit, refit: Refit | None, fd: bool, w: WindowSet, bounds: dict,
                    ctx: Ctx) -> WindowSet:
    """The windows for the check of f's sigma: again with f's own estimator (``refit``: its noise model
    and channels; gyro-only windows scatter with the flexure it took out), else the ordinary ones ``w``
    (gyro-only spectral fits: the conservative check, GLS windows of gyros alone measured worse). Fewer
    than 3 windows with the motion for f's estimator: nothing checks its sigma (the ordinary windows'
    sigmas ignore the flexure and would inflate it for nothing)."""
    cfg = ctx.cfg
    if not fd or refit is None:
        return w
    t_m, t_mid = ov.t_m, ov.t_mid
    c2, l2, s2 = [], [], []
    for tc in w.centers:
        a0, a1 = bounds[float(tc)]
        ws = (t_m >= a0) & (t_m <= a1)
        fw = refit(ws, tc, f.latency_s + f.drift * (tc - t_mid), f.drift if cfg.windows.window_drift else 0.0)
        if fw.ok and np.isfinite(fw.sigma_latency_s):
            c2.append(tc)
            l2.append(fw.latency_s)
            s2.append(max(fw.sigma_latency_s, cfg.uncertainty.sigma_floor_s))
    if len(c2) >= 3:
        return WindowSet(np.asarray(c2), np.asarray(l2), np.asarray(s2), bounds)
    return WindowSet(w.centers, w.lats, np.full(len(w.sigs), np.inf), bounds)
