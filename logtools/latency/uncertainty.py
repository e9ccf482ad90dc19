"""Stage 7, the uncertainty: every term of ``sigma_s`` as a named field of one ``SigmaBudget``."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from logtools.latency.gls import grid_offset_sigma_s, stamp_noise_variance
from logtools.latency.prepare import Ctx


def jitter_sigma_s(ctx: Ctx, w0: float, w1: float) -> float:
    """The latency error that stamp noise alone causes: a least-squares delay is a weighted mean of
    the stamp errors, weights |w'|^2 per sample, so its variance is sigma_t^2 sum |w'|^4 / (sum |w'|^2)^2
    per unit (samples of each unit in the analysed window). It is not seen as a residual by the
    accelerometer-aided fit (the gyros and accelerometers share the stamps)."""
    var = 0.0
    for u, sj in zip((ctx.master, ctx.slave), ctx.stamp_jitter_s):
        if not sj > 0:
            continue
        nat = u.native
        t = nat.t_s
        sel = nat.valid & (t >= w0) & (t <= w1)
        if sel.sum() < 10:
            continue
        wd = np.gradient(nat.values, nat.dt_s, axis=0)[sel]
        var += stamp_noise_variance(sj, np.sum(wd * wd, axis=1))
    return float(np.sqrt(var))



@dataclass(frozen=True)
class RateSigma:
    """The rate fit's (L, drift) after the window check, the model gap and the stamp grid: the estimate the
    velocity fusion and the drift prior start from. ``terms``: variance contributions (s^2, before the
    calibration) whose sum is ``sigma_latency_s ** 2``."""

    latency_s: float
    drift: float
    sigma_latency_s: float
    sigma_drift: float
    corr_ld: float
    terms: dict = field(default_factory=dict)
    window_chi2_red: float = 1.0
    resolution_sigma_s: float = 0.0
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class SigmaBudget:
    """``sigma_s`` and its named terms (seconds, calibrated): ``sqrt(sum(t ** 2 for t in terms)) == sigma_s``.

    How each step of the sigma enters (so that ``sigma_s`` is the value the steps give, bit for bit):
    a term added in quadrature (stamp resolution, the drift prior's centroid offset) is that term; a step
    that takes a maximum (window scatter: sigma x sqrt(chi2); the model gap's cover; the stamp jitter floor;
    the model floor; the periodic spread) is the term that makes the root-sum-square come out at the maximum,
    sqrt(new^2 - old^2); a step that shrinks the sigma (the velocity fusion, the drift prior's conditioning)
    and the calibration scale every term so far alike."""

    sigma_s: float
    terms: dict
    sigma_at_best_instant_s: float


def _scaled(terms: dict, new: float, old: float) -> dict:
    if not (old > 0 and np.isfinite(old)) or new == old:
        return dict(terms)
    f = (new / old) ** 2
    return {k: v * f for k, v in terms.items()}


def _grown(terms: dict, name: str, new: float, old: float) -> dict:
    """terms with ``name`` the variance that takes the RSS from ``old`` to ``new`` (>= old)."""
    out = dict(terms)
    if new > old:
        out[name] = out.get(name, 0.0) + (new * new - old * old)
    return out


def rate_sigma(fin, centers: np.ndarray, lats: np.ndarray, sigs: np.ndarray, t_mid: float, ctx: Ctx,
               window_chi2: float) -> RateSigma:
    """The rate fit's sigma: its covariance (curvature, and the HAC's excess for correlated residuals),
    inflated by the windows' scatter about the drift line, grown to cover a disagreeing flexure model
    (``model_gap_s``), and the stamps' grid offset in quadrature."""
    cfg = ctx.cfg
    s_fit = fin.sigma_latency_s
    fac = fin.hac_factor if fin.hac_factor >= 1.0 else 1.0
    terms = {"fit_curvature": s_fit ** 2 / fac, "residual_correlation": s_fit ** 2 - s_fit ** 2 / fac}
    if not np.isfinite(s_fit):
        terms = {"fit_curvature": s_fit ** 2}
    infl = np.sqrt(max(1.0, window_chi2)) if cfg.windows.window_inflate else 1.0
    sig_l, sigma_drift = fin.sigma_latency_s * infl, fin.sigma_drift * infl
    terms = _grown(terms, "window_scatter", sig_l, s_fit)
    corr_ld = fin.corr_ld
    warnings = []
    if fin.model_gap_s > 0:  # the spectral and the Kalman (flexure) fits disagree: cover the other one
        grown = max(sig_l, cfg.uncertainty.flex_gap_cover * fin.model_gap_s)
        terms = _grown(terms, "model_gap", grown, sig_l)
        corr_ld, sig_l = corr_ld * sig_l / grown, grown
        warnings.append(f"the spectral and the flexure-model fits of the rates disagree by "
                        f"{fin.model_gap_s * 1e3:.3g} ms: sigma covers both")
    # stamps on a coarse grid (whole milliseconds) with a fixed sampling phase are all off by the same
    # fraction of it: a common offset, uniform over the grid step, that no residual shows (a floor in
    # quadrature; the drift is not affected, so the latency-drift covariance stays)
    res_sigma = grid_offset_sigma_s(ctx.stamp_resolution_s) if cfg.uncertainty.stamp_resolution_floor else 0.0
    if res_sigma > 0 and np.isfinite(sig_l) and sig_l > 0:
        grown = float(np.hypot(sig_l, res_sigma))
        terms = _grown(terms, "stamp_resolution", grown, sig_l)
        corr_ld, sig_l = corr_ld * sig_l / grown, grown
    return RateSigma(fin.latency_s, fin.drift, sig_l, sigma_drift, corr_ld, terms, window_chi2, res_sigma,
                     tuple(warnings))


def fused(rs: RateSigma, fusion: tuple | None) -> RateSigma:
    """``rs`` with the velocity fusion's (L, drift, sigma_L, sigma_drift, corr) (None: unchanged); the
    terms scaled by the fused sigma's share."""
    if fusion is None:
        return rs
    latency, drift, sig_l, sig_dr, corr = fusion
    return replace(rs, latency_s=latency, drift=drift, sigma_latency_s=sig_l, sigma_drift=sig_dr, corr_ld=corr,
                   terms=_scaled(rs.terms, sig_l, rs.sigma_latency_s))


def drift_prior(rs: RateSigma, fit_drift: bool, cfg) -> tuple[RateSigma, np.ndarray | None]:
    """A drift the data cannot determine is pulled towards 0 by a Gaussian prior (crystal clocks:
    ``drift_prior_ppm``), and the latency with it through their correlation (Gaussian conditioning).
    Returns the conditioned estimate and its (L, drift) covariance (None without a drift fit)."""
    sig_l, sigma_drift, corr_ld = rs.sigma_latency_s, rs.sigma_drift, rs.corr_ld
    if not (fit_drift and np.isfinite(sigma_drift) and np.isfinite(sig_l)):
        return rs, None
    V = np.array([[sig_l ** 2, corr_ld * sig_l * sigma_drift],
                  [corr_ld * sig_l * sigma_drift, sigma_drift ** 2]])
    K = V[:, 1] / (V[1, 1] + (cfg.uncertainty.drift_prior_ppm * 1e-6) ** 2)
    latency, drift = rs.latency_s - K[0] * rs.drift, rs.drift - K[1] * rs.drift
    V = V - np.outer(K, V[1])
    s_l, s_d = float(np.sqrt(max(V[0, 0], 0.0))), float(np.sqrt(max(V[1, 1], 0.0)))
    return replace(rs, latency_s=latency, drift=drift, sigma_latency_s=s_l, sigma_drift=s_d,
                   terms=_scaled(rs.terms, s_l, sig_l)), V


def centroid_term(rs: RateSigma, ctx: Ctx, t_m: np.ndarray, valid: np.ndarray, t_mid: float) -> RateSigma:
    """Without a drift fit the latency is that of the information's centroid (the samples weighted by the
    rate's change squared): where gaps or uneven motion move it off the middle of the window, the drift's
    prior moves the middle's latency by drift x that distance (in quadrature)."""
    ok_f = valid & ctx.slave.itp.ok(t_m + rs.latency_s)
    wd, ok_d = ctx.master.itp(t_m, 1)
    ok_f &= ok_d
    g = np.sum(np.where(ok_f[:, None], wd, 0.0) ** 2, axis=1)  # the delay's information per sample
    if not g.sum() > 0:
        return rs
    t_c = float(np.sum(g * t_m) / g.sum())
    sig_l = float(np.hypot(rs.sigma_latency_s, ctx.cfg.uncertainty.drift_prior_ppm * 1e-6 * abs(t_c - t_mid)))
    return replace(rs, sigma_latency_s=sig_l, terms=_grown(rs.terms, "drift_prior", sig_l, rs.sigma_latency_s))


def _finish(sig_l: float, terms: dict, jit_sigma: float, spread: float | None, cfg,
            clock_sigma: float = 0.0) -> tuple[float, dict]:
    """The floors after the fits: stamp jitter (the aided fit does not see it in its residuals), the
    calibration, the model floor, the periodic spread (sigma covers the ambiguity), and in quadrature the
    offsets that put the units' stamps on their clocks (``Ctx.clock_sigma_s``: common to every stamp, no
    residual shows it)."""
    grown = max(sig_l, jit_sigma)
    terms = _grown(terms, "stamp_jitter", grown, sig_l)
    cal = cfg.uncertainty.sigma_calibration
    sigma = max(cal * grown, cfg.uncertainty.sigma_floor_s)
    terms = {k: v * cal * cal for k, v in terms.items()}
    terms = _grown(terms, "model_floor", sigma, cal * grown)
    if spread is not None:
        new = max(sigma, 0.5 * spread)
        terms, sigma = _grown(terms, "periodic_spread", new, sigma), new
    if clock_sigma > 0:
        new = float(np.hypot(sigma, clock_sigma))
        terms, sigma = _grown(terms, "clock_mapping", new, sigma), new
    return sigma, terms


def budget(rs: RateSigma, V: np.ndarray | None, v_best: float | None, jit_sigma: float, spread: float | None,
           cfg, clock_sigma: float = 0.0) -> SigmaBudget:
    """``sigma_s`` and ``sigma_at_best_instant_s`` through the same floors; ``v_best``: the latency's variance
    at the best-determined instant (from ``V``; None: the middle)."""
    sigma, terms = _finish(rs.sigma_latency_s, rs.terms, jit_sigma, spread, cfg, clock_sigma)
    sig_best = sigma
    if v_best is not None:
        s_b = float(np.sqrt(max(v_best, 0.0)))
        sig_best, _ = _finish(s_b, _scaled(rs.terms, s_b, rs.sigma_latency_s), jit_sigma, spread, cfg, clock_sigma)
    return SigmaBudget(float(sigma), {k: float(np.sqrt(max(v, 0.0))) for k, v in terms.items()}, float(sig_best))
