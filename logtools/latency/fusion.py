"""Stage 6, the velocity fit's use: fusion with the rate fit's (L, drift) and the periodic alternatives
tried on the velocities."""
from __future__ import annotations

import numpy as np

from logtools.latency.prepare import Ctx
from logtools.latency.velocity import velocity_fit
from logtools.latency.velocity_pair import VelocityPair
from logtools.latency.windows import drift_windows


def velocity_step(ctx: Ctx, vp: VelocityPair | None, w0: float, w1: float, t_mid: float, fit_drift: bool,
                  latency: float, drift: float, sig_l: float, sig_dr: float, corr: float, *, flexure: bool = False
                  ) -> tuple[dict | None, tuple | None]:
    """The velocity-matched estimate (``latency.velocity``) and its fusion with the rate fit's
    (L[, drift]): inverse-covariance weighted when the two agree (chi-square below cfg.velocity.agree_chi2; a nav
    velocity's delay need not be its IMU's: else ``agrees`` is False and the rate fit stays) and either
    the velocity's latency sigma is the smaller or the rate fit had to model flexure (``flexure``: what
    limits it there is what the velocity does not see). Returns (the quality entry or None, the
    fused (L, drift, sigma_L, sigma_drift, corr) or None). ``vp``: the units' velocity pair (None: no fit)."""
    cfg = ctx.cfg
    vf = None if vp is None else velocity_fit(vp, w0, w1, latency, drift, t_mid, fit_drift=fit_drift,
                                              windows=drift_windows(ctx, w0, w1), cfg=cfg)
    if vf is None or not np.isfinite(sig_l):
        return None, None
    nd = 2 if fit_drift and sig_dr > 0 and vf.sigma_drift > 0 else 1

    def cov(s_l: float, s_d: float, c: float) -> np.ndarray:
        return np.array([[s_l ** 2, c * s_l * s_d], [c * s_l * s_d, s_d ** 2]])[:nd, :nd]

    x_r, x_v = np.array([latency, drift])[:nd], np.array([vf.latency_s, vf.drift])[:nd]
    V_r, V_v = cov(sig_l, sig_dr, corr), cov(vf.sigma_latency_s, vf.sigma_drift, vf.corr_ld)
    dx = x_v - x_r
    chi2 = float(dx @ np.linalg.solve(V_r + V_v, dx)) / cfg.uncertainty.sigma_calibration ** 2  # the sigmas as reported
    agrees = bool(chi2 <= cfg.velocity.agree_chi2[nd - 1])
    use = bool(agrees and ((cfg.velocity.fuse_flexure and flexure) or vf.sigma_latency_s < sig_l))
    q = {"latency_s": vf.latency_s, "sigma_s": cfg.uncertainty.sigma_calibration * vf.sigma_latency_s,
         "drift_ppm": vf.drift * 1e6 if nd == 2 else None, "lever_arm_m": vf.lever_arm_m,
         "residual_rms_m_s": vf.residual_rms_m_s, "window_chi2_red": vf.window_chi2_red,
         "n_windows": vf.n_windows, "velocity_steps": vf.n_steps, "lowpass_hz": vp.cutoff_hz,
         "frame_rotation_deg": vf.frame_rotation_deg,
         "agreement_chi2": chi2, "agrees": agrees, "fused": use}
    if not use:
        return q, None
    Wi = np.linalg.inv(np.linalg.inv(V_r) + np.linalg.inv(V_v))
    x = Wi @ (np.linalg.solve(V_r, x_r) + np.linalg.solve(V_v, x_v))
    s_l = float(np.sqrt(Wi[0, 0]))
    if nd == 1:
        return q, (float(x[0]), drift, s_l, sig_dr, corr)
    s_d = float(np.sqrt(Wi[1, 1]))
    return q, (float(x[0]), float(x[1]), s_l, s_d, float(Wi[0, 1] / (s_l * s_d)))


def periodic_by_velocity(ctx: Ctx, vp: VelocityPair | None, alts: list[float], d0: float, latency: float,
                         drift: float, t_mid: float, fit_drift: bool) -> tuple[list[float], list[float]]:
    """The rates' near-equal other minima (motion that repeats: a ship's sway, S-turns) tried on the
    velocities, which a mounting rotation cannot fit and which seldom repeat with the attitude: an
    alternative whose velocity fit leaves cfg.search.periodic_velocity_ratio x the residual of the estimate's (each
    over its own overlap, same fit) is rejected. Returns (kept, rejected) alternatives (coarse lags)."""
    if vp is None:
        return alts, []
    cfg = ctx.cfg
    g = ctx.master.grid
    dr = drift if fit_drift else 0.0

    def rms_at(lag: float) -> float:
        ok = g.valid & ctx.slave.itp.ok(g.t_s + lag)
        if ok.sum() * g.dt_s < cfg.prepare.min_overlap_s:
            return np.nan
        idx = np.flatnonzero(ok)
        a0, a1 = float(g.t_s[idx[0]]), float(g.t_s[idx[-1]])
        tm = 0.5 * (a0 + a1)
        vf = velocity_fit(vp, a0, a1, lag + dr * (tm - t_mid), dr, tm, fit_drift=False, windows=[], cfg=cfg)
        return np.nan if vf is None else vf.residual_rms_m_s

    best = rms_at(latency)
    if not (np.isfinite(best) and best > 0):
        return alts, []
    kept, out = [], []
    for x in alts:
        r = rms_at(latency + (x - d0))
        (out if np.isfinite(r) and r > cfg.search.periodic_velocity_ratio * best else kept).append(x)
    return kept, out

