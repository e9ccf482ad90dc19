"""Stage 5b, the refinement candidates over the whole overlap: the spectral GLS passes (gyros, then the
accelerometer-aided ones), the Kalman flexure-model fit, and the choice between them by their own windows'
check (``fit_all``: the joint fit of ``windows`` followed by these)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from logtools.conventions import median_step_s
from logtools.latency.fit import Fit, residual
from logtools.latency.gls import NoiseModel, noise_model
from logtools.latency.prepare import Ctx, accel_pair
from logtools.latency.refine import accel_aided as _accel_aided_builtin
from logtools.latency.refine import accel_lag_agrees, refine_gls
from logtools.latency.kalman import refine_flex as _refine_flex_builtin
from logtools.latency.system import Accel
from logtools.latency.windows import (Overlap, Refit, WindowSet, checked_windows, fit_window_chi2, joint_fit)


@dataclass(frozen=True)
class Spectral:
    """The spectral GLS result: the fit, whether a GLS pass succeeded, and for an accelerometer-aided fit
    its noise model and accelerometers (else None)."""

    fit: Fit
    gls_done: bool
    noise: NoiseModel | None = None
    acc: Accel | None = None


def spectral_passes(ctx: Ctx, ov: Overlap, fin: Fit, noise: NoiseModel, fd: bool) -> Spectral:
    """GLS on the whole overlap, the residual spectrum re-estimated from the fit before each pass; with
    accelerometers one gyro-only pass (their start and fall-back), then the aided passes."""
    cfg = ctx.cfg
    accel_aided = cfg.stages.accel_aided or _accel_aided_builtin
    t_m, a, valid, itp, t_mid = ov.t_m, ov.a, ov.valid, ov.itp, ov.t_mid

    def wants_accel(f: Fit) -> bool:  # below accel.min_sigma_s the accelerometers cannot matter
        return ctx.acc_src is not None and f.sigma_latency_s > cfg.accel.min_sigma_s

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
    acc = accel_pair(*ctx.acc_src) if gls_done and wants_accel(fin) else None
    if acc is not None:
        fa, nm6, acc_used = accel_aided(t_m, a, valid, itp, acc, fin, t_mid, fit_drift=fd, cfg=cfg)
        if fa.aided:
            return Spectral(fa, gls_done, nm6, acc_used)
        fin = fa  # the gyro-only fit, with the model check's figures
    return Spectral(fin, gls_done)


def kalman_fit(ctx: Ctx, ov: Overlap, sp: Spectral, fd: bool) -> tuple[Fit, Accel | None]:
    """The Kalman flexure-model fit from the spectral one (the accelerometers whenever both units have
    them, ``flexure.accel_own``; their own delay solved where it differs from the gyros'; the gyros alone
    where that fails). A gyro-only Kalman fit keeps the accelerometer model check's figures."""
    cfg = ctx.cfg
    refine_flex = cfg.stages.refine_flex or _refine_flex_builtin
    fin = sp.fit

    def flex_fit(acc: Accel | None) -> Fit:
        return refine_flex(ov.t_m, ov.a, ov.valid, ov.itp, fin.latency_s, fin.drift, ov.t_mid, ctx.cutoff_hz,
                           fit_drift=fd, acc=acc, h0=fin.sigma_latency_s, cfg=cfg)

    acc_x = sp.acc
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
    if ff.ok and np.isfinite(ff.sigma_latency_s) and not ff.accel_lag_s[1] > 0:
        ff = replace(ff, accel_lag_s=fin.accel_lag_s, accel_lag_free=fin.accel_lag_free)
    return ff, acc_x


def choose(ctx: Ctx, ov: Overlap, cands: list[tuple[Fit, Refit | None]], fd: bool, w: WindowSet, bounds: dict
           ) -> tuple[Fit, WindowSet]:
    """Each candidate's sigma as checked by its own windows' scatter. The Kalman fit is kept unless its
    windows disagree (the flexure model does not describe the data: vibration, filters) and the spectral
    fit's checked sigma is smaller. Not the bare sigmas: where the spectrum is estimated from a few cycles
    of slow motion, the spectral sigma is the optimistic one. Without windows the last candidate is taken."""
    cfg = ctx.cfg
    if len(cands) == 1 or not fd:
        fin, refit = cands[-1]
        return fin, checked_windows(ov, fin, refit, fd, w, bounds, ctx)
    scored = []
    for f, rf in cands:
        ws = checked_windows(ov, f, rf, fd, w, bounds, ctx)
        chi2 = fit_window_chi2(f, ws.centers, ws.lats, ws.sigs, ov.t_mid)
        scored.append((f.sigma_latency_s * np.sqrt(max(1.0, chi2)), chi2, f, ws))
    (s_spec, chi2_spec, f_spec, w_spec), (s_flex, chi2_flex, f_flex, w_flex) = scored
    if chi2_flex > cfg.flexure.windows_chi2 and s_spec < s_flex:
        fin, w_kept, s_kept, chi2_kept = f_spec, w_spec, s_spec, chi2_spec
    else:
        fin, w_kept, s_kept, chi2_kept = f_flex, w_flex, s_flex, chi2_flex
    # the other model's estimate beyond agree_sigmas of the kept one's checked sigma while the kept one's
    # windows disagree too: neither model is borne out, the sigma covers both (a gently turning aircraft
    # kept a spectral fit 4.75 ms from the Kalman one at a checked sigma of 0.28 ms, both fits' windows at
    # chi2 5-12, 5.7 ms off the truth: z 17). Where the kept fit's windows agree (ships: the spectral fit
    # right, the Kalman one 1 ms off) its checked sigma stands
    gap = abs(f_spec.latency_s - f_flex.latency_s)
    if fin.model_gap_s == 0 and gap > cfg.flexure.agree_sigmas * s_kept and chi2_kept > cfg.flexure.windows_chi2:
        fin = replace(fin, model_gap_s=gap)
    return fin, w_kept


def fit_all(ctx: Ctx, ov: Overlap, d_center: float, drift_center: float, search_ppm: float,
            noise: NoiseModel | None = None) -> tuple[Fit, np.ndarray, np.ndarray, np.ndarray]:
    """The joint fit and its windows (``windows.joint_fit``); with a residual spectrum the spectral GLS
    candidate, the Kalman candidate where the sigma is still above ``accel.min_sigma_s``, and the one
    their windows' check keeps. Returns (fit, window centres, delays, sigmas)."""
    cfg = ctx.cfg
    fin, w, bounds = joint_fit(ctx, ov, d_center, drift_center, search_ppm)
    if noise is None:
        return fin, w.centers, w.lats, w.sigs
    fd = len(w) >= 3
    sp = spectral_passes(ctx, ov, fin, noise, fd)
    fin = sp.fit
    t_m, a, valid, itp = ov.t_m, ov.a, ov.valid, ov.itp
    refit = None
    if sp.acc is not None:
        def refit(ws, tc, lag, drift):
            return refine_gls(t_m[ws], a[ws], valid[ws], itp, lag, drift, tc, sp.noise, fit_drift=False,
                              acc=sp.acc, cfg=cfg)
    cands = [(fin, refit)]
    if cfg.flexure.kalman and sp.gls_done and fin.sigma_latency_s > cfg.accel.min_sigma_s:
        ff, acc_x = kalman_fit(ctx, ov, sp, fd)
        if ff.ok and np.isfinite(ff.sigma_latency_s):
            gap = abs(ff.latency_s - fin.latency_s)
            if gap > cfg.flexure.agree_sigmas * max(ff.sigma_latency_s, fin.sigma_latency_s):
                # one of the two models is wrong (the spectral sigma is optimistic where flexure is
                # estimated from a few cycles; the Kalman fit where the disturbance is not flexure):
                # both go to the windows' check, and the one kept covers the other in its sigma
                fin = replace(fin, model_gap_s=gap)
                ff = replace(ff, model_gap_s=gap)
                cands[0] = (fin, refit)
            refine_flex = cfg.stages.refine_flex or _refine_flex_builtin

            def refit_flex(ws, tc, lag, drift):
                return refine_flex(t_m[ws], a[ws], valid[ws], itp, lag, drift, tc, ctx.cutoff_hz,
                                   fit_drift=False, acc=acc_x, model=ff.flex, h0=ff.sigma_latency_s, cfg=cfg)
            cands.append((ff, refit_flex))
    fin, w = choose(ctx, ov, cands, fd, w, bounds)
    return fin, w.centers, w.lats, w.sigs
