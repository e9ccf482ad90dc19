"""Stage 8, quality and result: the flags and figures of ``latency.quality`` and the cost curve the plots
show around the estimate."""
from __future__ import annotations

import numpy as np

from logtools.latency.coarse import Coarse, rotation_solved_cost
from logtools.latency.fit import Fit
from logtools.latency.prepare import Ctx
from logtools.latency.uncertainty import RateSigma, SigmaBudget


def fine_cost(ctx: Ctx, latency_s: float, drift: float, t_mid: float, w0: float, w1: float,
              half_s: float, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The normalised rotation- and bias-solved cost (as the coarse curve) at n continuous lags
    latency_s +- half_s, with the drift, on at most cfg.output.fine_cost_max_samples master samples (a strided
    subset of the search grid: the curve's shape, not its noise, is what a plot needs)."""
    cfg = ctx.cfg
    n = cfg.output.fine_cost_points if n is None else n
    g = ctx.master.grid
    sel = np.flatnonzero((g.t_s >= w0) & (g.t_s <= w1) & g.valid)
    if len(sel) < 20 or not np.isfinite(half_s) or half_s <= 0:
        return np.zeros(0), np.zeros(0)
    sel = sel[::max(1, int(np.ceil(len(sel) / cfg.output.fine_cost_max_samples)))]
    t, a = g.t_s[sel], g.values[sel]
    lags = latency_s + np.linspace(-half_s, half_s, n)
    out = np.full(n, np.nan)
    shift = drift * (t - t_mid)
    for k, d in enumerate(lags):
        b, ok = ctx.slave.itp(t + d + shift)
        out[k] = rotation_solved_cost(a, b, ok, 20)
    return lags, out


def cost_curve(ctx: Ctx, co: Coarse, latency: float, drift: float, t_mid: float, w0: float, w1: float,
               sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalised cost curve around the minimum (coarse grid), for plots, with the continuous cost (drift
    included) sampled finely near the estimate so that a zoom shows the parabola."""
    cfg = ctx.cfg
    vc = co.vc
    near = np.abs(vc.lags * co.dt_s - co.d0_s) <= max(0.5, 10 * co.dt_s)
    c_lag, c_val = vc.lags[near] * co.dt_s, vc.cost[near]
    half = min(max(cfg.output.fine_cost_sigmas * sigma, cfg.output.fine_cost_samples * co.dt_s),
               max(0.5, 10 * co.dt_s))
    f_lag, f_val = fine_cost(ctx, latency, drift, t_mid, w0, w1, half)
    if len(f_lag):
        out = (c_lag < f_lag[0]) | (c_lag > f_lag[-1])
        c_lag = np.concatenate([c_lag[out], f_lag])
        c_val = np.concatenate([c_val[out], f_val])
        o = np.argsort(c_lag, kind="stable")
        c_lag, c_val = c_lag[o], c_val[o]
    return c_lag, c_val


def quality_record(ctx: Ctx, co: Coarse, fin: Fit, motion: tuple, rs: RateSigma, sb: SigmaBudget, *,
                   fit_drift: bool, gls: bool, n_windows: int, window: tuple[float, float], nan_fraction: float,
                   vel_q: dict | None, alts: list, alts_out: list, jit_sigma: float, best: tuple[float, float],
                   rpy: tuple) -> dict:
    """``latency.quality``: motion, periodicity, windows, the fit's figures, stamps, the sigma budget."""
    cfg = ctx.cfg
    motion_dps, snr, motion_s_dps, snr_s = motion
    m, s = ctx.master, ctx.slave
    w0, w1 = window
    return {
        "motion_dps": motion_dps,
        "slave_motion_dps": motion_s_dps,
        "motion_snr": float(min(snr, snr_s)),
        "too_little_motion": bool(min(snr, snr_s) < cfg.prepare.low_motion_snr
                                  or motion_dps < cfg.prepare.low_motion_dps),
        # what limits it: the vehicle barely turning, or the sensors' noise (vibration) drowning ample motion
        "low_motion_cause": ("motion" if motion_dps < cfg.prepare.low_motion_dps
                             else "noise" if min(snr, snr_s) < cfg.prepare.low_motion_snr else None),
        "periodic": len(alts) > 0,
        "periodic_alternatives_s": [float(x) for x in alts[:10]],
        "periodic_alternatives_rejected_s": [float(x) for x in alts_out[:10]],
        "windows_disagree": bool(rs.window_chi2_red > cfg.output.windows_disagree_chi2),
        "window_chi2_red": rs.window_chi2_red,
        "n_windows": int(n_windows),
        "overlap_s": float(w1 - w0),
        "mounting_rpy_deg": list(rpy),
        "bias_diff_dph": [float(x) for x in np.degrees(fin.bias) * 3600.0],
        "residual_rms_dps": float(np.degrees(fin.residual_rms)),
        "vector_cost_min": co.best_cost,
        "gls": bool(gls),
        "accel_aided": bool(fin.aided),
        # |spectral - Kalman| latency of the rate fits when they disagree (0: they agree or one ran)
        "rate_models_gap_s": float(fin.model_gap_s),
        # the Kalman-whitened fit's flexure model (seed 000 eq. 8), when that fit was kept
        "flexure_model": None if fin.flex is None else {
            "sigma_deg": [float(x) for x in np.degrees(fin.flex.sigma_rad)], "beta_1_s": float(fin.flex.beta_1_s)},
        # the velocity-matched estimate (both units with NED velocity) and whether it was fused
        "velocity_fit": vel_q,
        "velocity_disagrees": bool(vel_q is not None and not vel_q["agrees"]),
        "accel_minus_gyro_lag_s": float(fin.accel_lag_s[0]) if fin.accel_lag_s[1] > 0 else None,
        "accel_minus_gyro_lag_sigma_s": float(fin.accel_lag_s[1]) if fin.accel_lag_s[1] > 0 else None,
        "accel_lag_solved": bool(fin.accel_lag_free),
        "nan_fraction": nan_fraction,
        "coarse_latency_s": co.d0_s,
        "xcorr_norm_latency_s": co.xcorr_latency_s,
        "xcorr_norm_peak": co.xcorr_peak,
        "residual_correlation_factor": fin.hac_factor,
        "drift_sigma_ppm": float(rs.sigma_drift * 1e6) if fit_drift else None,
        "stamp_jitter_s": {"master": ctx.stamp_jitter_s[0], "slave": ctx.stamp_jitter_s[1]},
        "stamp_jitter_latency_sigma_s": jit_sigma,
        "stamp_resolution_s": {"master": ctx.stamp_resolution_s[0], "slave": ctx.stamp_resolution_s[1]},
        "stamp_resolution_latency_sigma_s": rs.resolution_sigma_s,
        "clock_mapping_sigma_s": {"master": ctx.clock_sigma_s[0], "slave": ctx.clock_sigma_s[1]},
        "best_instant_s": float(ctx.t0_abs_s + best[0]),  # absolute, like window_s
        "latency_at_best_instant_s": float(best[1]),
        "sigma_at_best_instant_s": float(sb.sigma_at_best_instant_s),
        # the named terms of sigma_s (s): their root-sum-square is sigma_s (uncertainty.SigmaBudget)
        "sigma_budget": dict(sb.terms),
        "drift_estimated": fit_drift,
        **({} if fit_drift else {"drift_not_estimated": (
            f"a drift needs 3 windows with enough motion (about {cfg.windows.window_s:g} s each) and this log "
            f"gives {n_windows}: one latency for the whole window (drift taken as 0 ppm, its prior in the sigma "
            "budget; the compensation applies none)")}),
        "common_rate_hz": 1.0 / ctx.dt_c,
        "refine_rate_hz": 1.0 / ctx.dt_r,
        "lowpass_hz": ctx.cutoff_hz,
        "band_adapted": ctx.adapted_cutoff,
        "rates_hz": {"master": m.rate_hz, "slave": s.rate_hz},
        "rate_source": {"master": m.source, "slave": s.source},
        "warnings": list(ctx.warnings) + list(rs.warnings),
    }
