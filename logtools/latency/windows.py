"""Stage 5, windows and drift: the drift windows, their line, the joint (L, drift) fit over the whole
overlap, the GLS / aided / Kalman candidates and the windows' check of the one kept."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from logtools.conventions import median_step_s
from logtools.errors import AnalysisError
from logtools.latency.coarse import window_start
from logtools.latency.fit import Fit, refine, residual
from logtools.latency.gls import NoiseModel, noise_model, window_chi2
from logtools.latency.prepare import Ctx, accel_pair
from logtools.latency.refine import accel_aided as _accel_aided_builtin
from logtools.latency.refine import accel_lag_agrees, refine_gls
from logtools.latency.refine import refine_flex as _refine_flex_builtin
from logtools.latency.system import Accel


def drift_windows(ctx: Ctx, t0: float, t1: float, t_ok: np.ndarray | None = None) -> list[tuple[float, float]]:
    """The drift windows over [t0, t1]: about cfg.windows.window_s each (3..MAX_WINDOWS). With ``t_ok`` (the instants
    that have data in both units) covering less than cfg.windows.window_data_fraction of the span (gaps), windows are
    laid in the runs of data between the gaps instead (none across one), their number shared by the
    runs' lengths (runs shorter than cfg.windows.min_window_s left out)."""
    cfg = ctx.cfg
    T = t1 - t0
    if t_ok is not None and len(t_ok) > 1:
        d = np.diff(t_ok)
        dt = median_step_s(t_ok)
        if len(t_ok) * dt < cfg.windows.window_data_fraction * T:
            cut = np.flatnonzero(d > max(1.0, 10.0 * dt))
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


def wls_line(x: np.ndarray, y: np.ndarray, sig: np.ndarray) -> tuple[float, float, np.ndarray]:
    w = 1.0 / np.maximum(sig, 1e-12) ** 2
    A = np.stack([np.ones_like(x), x], axis=1)
    N = A.T @ (A * w[:, None])
    p = np.linalg.solve(N, A.T @ (w * y))
    return float(p[0]), float(p[1]), np.linalg.inv(N)


def fit_window_chi2(f: Fit, centers: np.ndarray, lats: np.ndarray, sigs: np.ndarray, t_mid: float) -> float:
    """Reduced chi-square of the window estimates about f's line L + drift (t - t_mid) (1 below 3 windows)."""
    return window_chi2(centers, lats, sigs, f.latency_s, f.drift, t_mid)


def fit_all(ctx: Ctx, t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, w0: float, w1: float,
             d_center: float, drift_center: float, search_ppm: float, noise: NoiseModel | None = None
             ) -> tuple[Fit, np.ndarray, np.ndarray, np.ndarray]:
    """Windows along the overlap (each: integer-lag search around the predicted lag, then refinement),
    a weighted line through them, then the joint (L, drift) fit over the whole overlap. With fewer than
    3 usable windows, one global fit without drift."""
    cfg = ctx.cfg
    refine_flex = cfg.stages.refine_flex or _refine_flex_builtin
    accel_aided = cfg.stages.accel_aided or _accel_aided_builtin
    t_mid = 0.5 * (w0 + w1)
    itp = ctx.slave.itp
    wins = drift_windows(ctx, w0, w1, t_m[valid & itp.ok(t_m + d_center)])
    bounds: dict[float, tuple[float, float]] = {}

    def fit_windows(line: tuple[float, float] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each window's delay at its centre. The drift inside a window is that of ``line`` (L, drift at
        t_mid), else none: a window's delay without it is that of the window's motion centroid, not its
        centre (100 ppm over a 15 s window whose motion sits at one end: 0.7 ms)."""
        centers, lats, sigs, wmot = [], [], [], []
        for (a0, a1) in wins if len(wins) >= 3 else []:
            ws = (t_m >= a0) & (t_m <= a1)
            if ws.sum() < 50:
                continue
            tc = 0.5 * (a0 + a1)
            if line is None:
                dr_w = 0.0
                pred = d_center + drift_center * (tc - t_mid)
                band = search_ppm * 1e-6 * abs(tc - t_mid) + 2.0 * ctx.dt_s
                dw = window_start(ctx, a0, a1, pred, band)
                if dw is None:
                    continue
            else:
                dr_w = line[1]
                dw = line[0] + dr_w * (tc - t_mid)
            f = refine(t_m[ws], a[ws], valid[ws], itp, dw, dr_w, tc, fit_drift=False, iters=8, cfg=cfg)
            if f.ok and np.isfinite(f.sigma_latency_s):
                bounds[float(tc)] = (a0, a1)
                centers.append(tc)
                lats.append(f.latency_s)
                sigs.append(max(f.sigma_latency_s, cfg.uncertainty.sigma_floor_s))
                wmot.append(f.motion_rms)
        centers, lats, sigs, wmot = map(np.asarray, (centers, lats, sigs, wmot))
        if len(wmot):
            keep = wmot >= 0.2 * np.median(wmot)  # windows with enough motion
            centers, lats, sigs = centers[keep], lats[keep], sigs[keep]
        return centers, lats, sigs

    def reject(centers: np.ndarray, lats: np.ndarray, sigs: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Windows that locked on a wrong minimum (little motion in them: the linearised sigma does not
        hold there) are outliers of the line: rejected one at a time beyond cfg.windows.window_reject sigma."""
        keep = np.ones(len(centers), bool)
        while keep.sum() > 3:
            L0, dr0, _ = wls_line(centers[keep] - t_mid, lats[keep], sigs[keep])
            z = np.abs(lats - (L0 + dr0 * (centers - t_mid))) / sigs
            j = int(np.argmax(np.where(keep, z, -1.0)))
            if z[j] <= cfg.windows.window_reject:
                break
            keep[j] = False
        centers, lats, sigs = centers[keep], lats[keep], sigs[keep]
        L0, dr0, _ = wls_line(centers - t_mid, lats, sigs)
        return centers, lats, sigs, L0, dr0

    centers, lats, sigs = fit_windows(None)
    fin = None
    if len(centers) >= 3:
        centers, lats, sigs, L0, dr0 = reject(centers, lats, sigs)
        # two starts: the windows' line and the central fit without drift; the lower cost wins
        cands = [refine(t_m, a, valid, itp, L0, dr0, t_mid, fit_drift=True, cfg=cfg),
                 refine(t_m, a, valid, itp, d_center, 0.0, t_mid, fit_drift=True, cfg=cfg)]
        cands = [c for c in cands if c.ok]
        fin = min(cands, key=lambda c: c.residual_rms) if cands else None
        half = 0.5 * max(b - a for a, b in bounds.values())
        if (cfg.windows.window_drift and fin is not None
                and abs(fin.drift) * half > cfg.windows.window_drift_fraction * float(np.median(sigs))):
            # the windows again, with the joint fit's drift inside each (a window's own drift-free delay
            # is its motion centroid's: windows of uneven motion scatter about the line for nothing)
            c2, l2, s2 = fit_windows((fin.latency_s, fin.drift))
            if len(c2) >= 3:
                centers, lats, sigs, _, _ = reject(c2, l2, s2)
    if fin is None:
        centers = lats = sigs = np.zeros(0)
        fin = refine(t_m, a, valid, itp, d_center, 0.0, t_mid, fit_drift=False, cfg=cfg)
        if not fin.ok:
            raise AnalysisError("latency refinement failed (too little valid overlapping data)")
    if noise is not None:
        # GLS on the whole overlap, with the residual spectrum re-estimated from this fit
        fd = len(centers) >= 3

        def wants_accel(f: Fit) -> bool:  # below cfg.accel.min_sigma_s the accelerometers cannot matter
            return ctx.acc_src is not None and f.sigma_latency_s > cfg.accel.min_sigma_s

        # with accelerometers, one gyro-only pass (their start and fall-back), then the aided passes
        gls_done = False
        for k in range(cfg.refine.gls_passes):
            if k == 1 and wants_accel(fin):
                break
            r = residual(t_m, a, valid, itp, fin, t_mid)
            nm = noise_model(r, np.any(r != 0.0, axis=1), median_step_s(t_m), cfg=cfg) or noise
            f2 = refine_gls(t_m, a, valid, itp, fin.latency_s, fin.drift, t_mid, nm, fit_drift=fd, cfg=cfg)
            if not f2.ok:
                break
            fin, gls_done = f2, True
        final_noise, final_acc = None, None
        acc = accel_pair(*ctx.acc_src) if gls_done and wants_accel(fin) else None
        if acc is not None:
            fa, nm6, acc_used = accel_aided(t_m, a, valid, itp, acc, fin, t_mid, fit_drift=fd, cfg=cfg)
            if fa.aided:
                fin, final_noise, final_acc = fa, nm6, acc_used
            else:
                fin = fa  # the gyro-only fit, with the model check's figures

        def windows(f: Fit, refit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """The windows for the check of f's sigma: again with f's own estimator (``refit``: its noise
            model and channels; gyro-only windows scatter with the flexure it took out), else the ordinary
            ones (gyro-only spectral fits: the conservative check, GLS windows of gyros alone measured
            worse). Fewer than 3 windows with the motion for f's estimator: nothing checks its sigma (the
            ordinary windows' sigmas ignore the flexure and would inflate it for nothing)."""
            if not fd or refit is None:
                return centers, lats, sigs
            c2, l2, s2 = [], [], []
            for tc in centers:
                a0, a1 = bounds[float(tc)]
                ws = (t_m >= a0) & (t_m <= a1)
                fw = refit(ws, tc, f.latency_s + f.drift * (tc - t_mid), f.drift if cfg.windows.window_drift else 0.0)
                if fw.ok and np.isfinite(fw.sigma_latency_s):
                    c2.append(tc)
                    l2.append(fw.latency_s)
                    s2.append(max(fw.sigma_latency_s, cfg.uncertainty.sigma_floor_s))
            if len(c2) >= 3:
                return np.asarray(c2), np.asarray(l2), np.asarray(s2)
            return centers, lats, np.full(len(sigs), np.inf)

        refit = None
        if final_acc is not None:
            def refit(ws, tc, lag, drift):
                return refine_gls(t_m[ws], a[ws], valid[ws], itp, lag, drift, tc, final_noise, fit_drift=False,
                                  acc=final_acc, cfg=cfg)
        cands = [(fin, refit)]
        if cfg.flexure.kalman and gls_done and fin.sigma_latency_s > cfg.accel.min_sigma_s:
            # Kalman whitening with the flexure model, from the spectral GLS fit, the second candidate
            # (a gyro-only Kalman fit keeps the accelerometer model check's figures)
            def flex_fit(acc: Accel | None) -> Fit:
                return refine_flex(t_m, a, valid, itp, fin.latency_s, fin.drift, t_mid, ctx.cutoff_hz,
                                   fit_drift=fd, acc=acc, h0=fin.sigma_latency_s, cfg=cfg)

            acc_x = final_acc  # cfg.flexure.accel_own: the accelerometers whenever both units have them
            own = cfg.flexure.accel_own and acc_x is None and ctx.acc_src is not None
            if own:
                acc_x = accel_pair(*ctx.acc_src)
            ff = flex_fit(acc_x)
            if acc_x is not None and not acc_x.lag_free and ff.ok and not accel_lag_agrees(ff, cfg) and cfg.accel.lag_free:
                # the accelerometers' own delay differs from the gyros' (real IMUs may filter them
                # differently): solved as a further unknown
                acc_x = replace(acc_x, lag_free=True)
                ff = flex_fit(acc_x)
            if acc_x is not None and ((ff.ok and not accel_lag_agrees(ff, cfg)) or ((own or acc_x.lag_free) and not ff.ok)):
                # that delay beyond what a linearised unknown allows, or the fit with the accelerometers
                # taken here failed: the gyros alone
                acc_x = None
                ff = flex_fit(None)
            if ff.ok and np.isfinite(ff.sigma_latency_s):
                ff = ff if ff.accel_lag_s[1] > 0 else replace(ff, accel_lag_s=fin.accel_lag_s,
                                                             accel_lag_free=fin.accel_lag_free)
                gap = abs(ff.latency_s - fin.latency_s)
                if gap > cfg.flexure.agree_sigmas * max(ff.sigma_latency_s, fin.sigma_latency_s):
                    # one of the two models is wrong (the spectral sigma is optimistic where flexure is
                    # estimated from a few cycles; the Kalman fit where the disturbance is not flexure):
                    # both go to the windows' check, and the one kept covers the other in its sigma
                    fin = replace(fin, model_gap_s=gap)
                    ff = replace(ff, model_gap_s=gap)
                    cands[0] = (fin, refit)

                def refit_flex(ws, tc, lag, drift):
                    return refine_flex(t_m[ws], a[ws], valid[ws], itp, lag, drift, tc, ctx.cutoff_hz,
                                       fit_drift=False, acc=acc_x, model=ff.flex, h0=ff.sigma_latency_s, cfg=cfg)
                cands.append((ff, refit_flex))
        if len(cands) == 1 or not fd:
            fin, refit = cands[-1]  # without windows the Kalman fit is taken (see cfg.flexure.agree_sigmas)
            centers, lats, sigs = windows(fin, refit)
        else:
            # each candidate's sigma as checked by its own windows' scatter. The Kalman fit is kept unless
            # its windows disagree (the flexure model does not describe the data: vibration, filters) and
            # the spectral fit's checked sigma is smaller. Not the bare sigmas: where the spectrum is
            # estimated from a few cycles of slow motion, the spectral sigma is the optimistic one
            scored = []
            for f, rf in cands:
                w = windows(f, rf)
                chi2 = fit_window_chi2(f, *w, t_mid)
                scored.append((f.sigma_latency_s * np.sqrt(max(1.0, chi2)), chi2, f, w))
            (s_spec, chi2_spec, f_spec, w_spec), (s_flex, chi2_flex, f_flex, w_flex) = scored
            if chi2_flex > cfg.flexure.windows_chi2 and s_spec < s_flex:
                fin, (centers, lats, sigs), s_kept, chi2_kept = f_spec, w_spec, s_spec, chi2_spec
            else:
                fin, (centers, lats, sigs), s_kept, chi2_kept = f_flex, w_flex, s_flex, chi2_flex
            # the other model's estimate beyond cfg.flexure.agree_sigmas of the kept one's checked sigma while the
            # kept one's windows disagree too: neither model is borne out, the sigma covers both (a gently
            # turning aircraft kept a spectral fit 4.75 ms from the Kalman one at a checked sigma of 0.28 ms,
            # both fits' windows at chi2 5-12, 5.7 ms off the truth: z 17). Where the kept fit's windows
            # agree (ships: the spectral fit right, the Kalman one 1 ms off) its checked sigma stands
            gap = abs(f_spec.latency_s - f_flex.latency_s)
            if fin.model_gap_s == 0 and gap > cfg.flexure.agree_sigmas * s_kept and chi2_kept > cfg.flexure.windows_chi2:
                fin = replace(fin, model_gap_s=gap)
    return fin, centers, lats, sigs

