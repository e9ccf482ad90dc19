"""Stage 2, the coarse search: FFT correlations of masked series, the |w| normalised cross-correlation
(the "xcorr-norm" baseline) and the rotation- and bias-solved full-vector cost at every integer lag."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from logtools.conventions import wahba
from logtools.errors import AnalysisError
from logtools.latency.inputs import series_on_grid
from logtools.latency.prepare import Ctx
from logtools.resample import UniformSeries, interpolant, lowpass
from logtools.results import MethodEstimate


class Correlator:
    """corr(x, y)[L] = sum_i x[i] y[i + L + off] for a master and a slave series on one grid."""

    def __init__(self, m: UniformSeries, s: UniformSeries):
        self.n, self.m_len = len(m.values), len(s.values)
        self.n_valid = min(int(m.valid.sum()), int(s.valid.sum()))  # gaps and masked ends left out
        self.nfft = sfft.next_fast_len(self.n + self.m_len - 1, real=True)
        self.off = m.i0 - s.i0

    def fa(self, x: np.ndarray) -> np.ndarray:
        return np.conj(sfft.rfft(x, self.nfft, axis=0))

    def fb(self, y: np.ndarray) -> np.ndarray:
        return sfft.rfft(y, self.nfft, axis=0)

    def lag_range(self) -> tuple[int, int]:
        """Lags (grid steps) with at least one overlapping pair."""
        return -(self.n - 1) - self.off, self.m_len - 1 - self.off

    def corr(self, FA: np.ndarray, FB: np.ndarray, lags: np.ndarray) -> np.ndarray:
        c = sfft.irfft(FA * FB, self.nfft, axis=0)
        return c[(lags + self.off) % self.nfft]


def norm_xcorr(m: UniformSeries, s: UniformSeries, lags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pearson correlation of |w| at each lag over the overlap (mean removed per lag), and counts."""
    c = Correlator(m, s)
    va, vb = m.valid.astype(float), s.valid.astype(float)
    a = np.linalg.norm(m.values, axis=1) * va
    b = np.linalg.norm(s.values, axis=1) * vb
    FA = c.fa(np.stack([va, a, a * a], axis=1))
    FB = c.fb(np.stack([vb, b, b * b], axis=1))
    n = c.corr(FA[:, 0], FB[:, 0], lags)
    sa = c.corr(FA[:, 1], FB[:, 0], lags)
    saa = c.corr(FA[:, 2], FB[:, 0], lags)
    sb = c.corr(FA[:, 0], FB[:, 1], lags)
    sbb = c.corr(FA[:, 0], FB[:, 2], lags)
    sab = c.corr(FA[:, 1], FB[:, 1], lags)
    n = np.round(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sab - sa * sb / n
        var_a = saa - sa * sa / n
        var_b = sbb - sb * sb / n
        rho = cov / np.sqrt(var_a * var_b)
    rho[~(n > 3) | ~(var_a > 0) | ~(var_b > 0)] = np.nan
    return rho, n


@dataclass(frozen=True)
class VectorCost:
    lags: np.ndarray  # grid steps
    cost: np.ndarray  # normalised: (C_aa + C_bb - 2 max tr(R M)) / (C_aa + C_bb), in [0, 2]; NaN off-range
    count: np.ndarray
    R: np.ndarray  # (L, 3, 3)


def vector_cost(m: UniformSeries, s: UniformSeries, lags: np.ndarray, min_count: float) -> VectorCost:
    """Rotation- and bias-solved full-vector cost at every integer lag (18 FFT correlations)."""
    c = Correlator(m, s)
    va, vb = m.valid.astype(float), s.valid.astype(float)
    a = m.values * va[:, None]
    b = s.values * vb[:, None]
    FA = c.fa(np.column_stack([va, a, np.sum(a * a, axis=1)]))
    FB = c.fb(np.column_stack([vb, b, np.sum(b * b, axis=1)]))
    n = np.round(c.corr(FA[:, 0], FB[:, 0], lags))
    sa = np.stack([c.corr(FA[:, 1 + p], FB[:, 0], lags) for p in range(3)], axis=-1)
    sb = np.stack([c.corr(FA[:, 0], FB[:, 1 + q], lags) for q in range(3)], axis=-1)
    saa = c.corr(FA[:, 4], FB[:, 0], lags)
    sbb = c.corr(FA[:, 0], FB[:, 4], lags)
    M = np.empty((len(lags), 3, 3))
    for p in range(3):
        for q in range(3):
            M[:, p, q] = c.corr(FA[:, 1 + p], FB[:, 1 + q], lags)
    good = n >= max(min_count, 10)
    nn = np.where(good, n, 1.0)
    M -= sa[:, :, None] * sb[:, None, :] / nn[:, None, None]
    caa = saa - np.sum(sa * sa, axis=1) / nn
    cbb = sbb - np.sum(sb * sb, axis=1) / nn
    Rw, best = wahba(M)
    R = np.ascontiguousarray(np.swapaxes(Rw, -1, -2))  # b ~ R a
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = (caa + cbb - 2.0 * best) / (caa + cbb)
    cost[~good | ~(caa + cbb > 0)] = np.nan
    return VectorCost(lags, cost, n, R)


def parabolic(y: np.ndarray, i: int) -> float:
    """Vertex offset (in steps, within +-0.5) of the parabola through y[i-1], y[i], y[i+1]."""
    if i <= 0 or i >= len(y) - 1 or not np.all(np.isfinite(y[i - 1:i + 2])):
        return 0.0
    den = y[i - 1] - 2 * y[i] + y[i + 1]
    return float(np.clip(0.5 * (y[i - 1] - y[i + 1]) / den, -0.5, 0.5)) if den != 0 else 0.0


def local_minima(y: np.ndarray) -> np.ndarray:
    f = np.where(np.isfinite(y), y, np.inf)
    i = np.arange(1, len(f) - 1)
    return i[(f[i] <= f[i - 1]) & (f[i] < f[i + 1]) & np.isfinite(f[i])]


def lobe_halfwidth(cost: np.ndarray, j: int) -> int:
    """Steps from the minimum j to where the cost rises half-way to its median (main lobe)."""
    fin = cost[np.isfinite(cost)]
    level = cost[j] + 0.5 * (np.median(fin) - cost[j])
    k = 1
    n = len(cost)
    while True:
        left = j - k < 0 or not np.isfinite(cost[j - k]) or cost[j - k] > level
        right = j + k >= n or not np.isfinite(cost[j + k]) or cost[j + k] > level
        if (left and right) or k > n:
            return k
        k += 1


def lag_window(ctx: Ctx, corr: Correlator, dt: float, min_frac: float) -> tuple[np.ndarray, float]:
    lo, hi = corr.lag_range()
    if ctx.max_lag_s is not None:
        k = int(np.floor(ctx.max_lag_s / dt + 1e-9))
        lo, hi = max(lo, -k), min(hi, k)
    lags = np.arange(lo, hi + 1)
    return lags, max(ctx.cfg.prepare.min_overlap_s / dt, min_frac * corr.n_valid)


@dataclass(frozen=True)
class Coarse:
    xc_lags_s: np.ndarray
    xc_rho: np.ndarray
    xcorr_latency_s: float
    xcorr_peak: float
    vc: VectorCost
    dt_s: float  # coarse grid step
    d0_s: float  # coarse full-vector estimate (parabolic)
    best_cost: float
    alternatives_s: tuple[float, ...]  # near-equal other minima (periodic motion)
    alt_costs: tuple[float, ...]


def coarse(ctx: Ctx) -> Coarse:
    cfg = ctx.cfg
    m, s = ctx.master.grid, ctx.slave.grid
    dt = m.dt_s
    if len(m.values) < 10 or len(s.values) < 10:
        raise AnalysisError("too little data for a latency estimate (fewer than 10 coarse samples)")
    corr = Correlator(m, s)
    # overlap needed at a candidate lag: half the shorter log with a bounded search, a quarter otherwise
    lags, min_count = lag_window(ctx, corr, dt, 0.5 if ctx.max_lag_s is not None else 0.25)
    # 1) |w| normalised cross-correlation
    rho, n = norm_xcorr(m, s, lags)
    rho[n < min_count] = np.nan
    if not np.any(np.isfinite(rho)):
        short = min(int(m.valid.sum()), int(s.valid.sum())) * dt
        hint = (f"the shorter log has {short:.1f} s of usable angular rate" if short < 2.0 * min_count * dt
                else "clocks unrelated? use --max-lag auto")
        raise AnalysisError(f"overlap shorter than {min_count * dt:.1f} s at every candidate lag ({hint})")
    ib = int(np.nanargmax(rho))
    xc_lat = (lags[ib] + parabolic(-rho, ib)) * dt
    # 2) rotation-solved full-vector cost; in an unbounded search only around the best |w| peaks
    if ctx.max_lag_s is None and len(lags) > 4001:
        r = np.where(np.isfinite(rho), rho, -np.inf)
        pk = local_minima(-r)
        pk = pk[np.argsort(-r[pk])][:cfg.search.coarse_peaks] if len(pk) else np.array([ib])
        half = int(np.ceil(2.0 / dt))
        sel = np.unique(np.concatenate([np.arange(p - half, p + half + 1) for p in pk]))
        sel = sel[(sel >= 0) & (sel < len(lags))]
        vlags = lags[sel]
    else:
        vlags = lags
    vc = vector_cost(m, s, vlags, min_count)
    if not np.any(np.isfinite(vc.cost)):
        raise AnalysisError("no lag with enough overlapping valid data")
    cost = vc.cost
    # contiguous segments only (selected lags may be disjoint): minima inside runs
    jb = int(np.nanargmin(cost))
    # periodic motion: other local minima (outside the main lobe) nearly as low
    best = float(cost[jb])
    mins = local_minima(cost)
    lobe = lobe_halfwidth(cost, jb)
    alts = [i for i in mins if abs(int(vlags[i]) - int(vlags[jb])) > lobe
            and cost[i] <= best + max(cfg.search.periodic_margin, cfg.search.periodic_rel_margin * best)]
    if alts:
        # near-equal minima (motion that repeats): the one with the most overlapping data is the better
        # supported (the same residual per sample over more samples); the others stay the alternatives
        cand = [jb] + alts
        jn = max(cand, key=lambda i: (float(vc.count[i]), -float(cost[i])))
        if jn != jb and vc.count[jn] > vc.count[jb]:
            alts = [i for i in cand if i != jn]
            jb = jn
            best = float(cost[jb])
    contiguous = (0 < jb < len(vlags) - 1 and vlags[jb + 1] - vlags[jb - 1] == 2)
    d0 = (vlags[jb] + (parabolic(cost, jb) if contiguous else 0.0)) * dt
    return Coarse(lags * dt, rho, float(xc_lat), float(rho[ib]), vc, dt, float(d0), best,
                   tuple(float(vlags[i] * dt) for i in alts), tuple(float(cost[i]) for i in alts))


def window_start(ctx: Ctx, a0: float, a1: float, d_center: float, band_s: float) -> float | None:
    """Integer-lag full-vector search of the window [a0, a1] (master relative s) within
    d_center +- band_s, on the search grid."""
    dt = ctx.dt_s
    mg = ctx.master.grid
    j0 = max(0, int(np.ceil(a0 / dt)) - mg.i0)
    j1 = min(len(mg.values), int(np.floor(a1 / dt)) - mg.i0 + 1)
    if j1 - j0 < 20:
        return None
    ms = UniformSeries(mg.i0 + j0, dt, mg.values[j0:j1], mg.valid[j0:j1])
    t = ms.t_s
    valid = ms.valid
    # slave samples covering the window shifted by the band
    sg = ctx.slave.grid
    lo = int(np.floor((t[0] + d_center - band_s) / dt)) - 2 - sg.i0
    hi = int(np.ceil((t[-1] + d_center + band_s) / dt)) + 2 - sg.i0
    lo, hi = max(lo, 0), min(hi, len(sg.values))
    if hi - lo < 20:
        return None
    ss = UniformSeries(sg.i0 + lo, dt, sg.values[lo:hi], sg.valid[lo:hi])
    kc = int(round(d_center / dt))
    kb = int(np.ceil(band_s / dt))
    lags = np.arange(kc - kb, kc + kb + 1)
    vc = vector_cost(ms, ss, lags, 0.8 * valid.sum())
    if not np.any(np.isfinite(vc.cost)):
        return None
    j = int(np.nanargmin(vc.cost))
    return float((lags[j] + parabolic(vc.cost, j)) * dt)


def xcorr_estimate(ctx: Ctx) -> MethodEstimate:
    """Baseline: |w| normalised cross-correlation on the common grid, parabolic peak interpolation."""
    m, s = (series_on_grid(interpolant(lowpass(u, ctx.cfg.prepare.cutoff_fraction / ctx.dt_c)), ctx.dt_c) for u in ctx.raw)
    corr = Correlator(m, s)
    lags, min_count = lag_window(ctx, corr, ctx.dt_c, 0.5 if ctx.max_lag_s is not None else 0.25)
    rho, n = norm_xcorr(m, s, lags)
    rho[n < min_count] = np.nan
    if not np.any(np.isfinite(rho)):
        raise AnalysisError("no lag with enough overlap")
    i = int(np.nanargmax(rho))
    d = (lags[i] + parabolic(-rho, i)) * ctx.dt_c
    # sigma: width of the peak / sqrt(number of independent samples), at least the grid quantisation
    r = rho[np.isfinite(rho)]
    lobe = lobe_halfwidth(-rho, i) * ctx.dt_c
    n_ind = max(1.0, n[i] * ctx.dt_c / max(lobe, ctx.dt_c))
    sig = max(ctx.dt_c / np.sqrt(12.0), lobe * np.sqrt(max(1e-6, 1 - rho[i] ** 2)) / np.sqrt(n_ind))
    note = f"peak correlation {rho[i]:.3f}" + ("" if len(r) else "")
    return MethodEstimate(float(d), float(sig), note)

