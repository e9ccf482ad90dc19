"""Stage 2, the coarse search: FFT correlations of masked series, the |w| normalised cross-correlation
(the "xcorr-norm" baseline) and the rotation- and bias-solved full-vector cost at every integer lag."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from logtools import dsp
from logtools.conventions import wahba
from logtools.errors import AnalysisError
from logtools.latency.config import LatencyConfig
from logtools.latency.inputs import series_on_grid
from logtools.latency.prepare import Ctx
from logtools.resample import Interpolant, UniformSeries, interpolant, lowpass
from logtools.results import MethodEstimate


class Correlator:
    """corr(x, y)[L] = sum_i x[i] y[i + L + off] for a master and a slave series on one grid."""

    def __init__(self, m: UniformSeries, s: UniformSeries):
        self.n, self.m_len = len(m.values), len(s.values)
        self.n_valid = min(int(m.valid.sum()), int(s.valid.sum()))  # gaps and masked ends left out
        self.nfft = sfft.next_fast_len(self.n + self.m_len - 1, real=True)
        self.off = m.i0 - s.i0

    def fa(self, x: np.ndarray) -> np.ndarray:
        return np.conj(dsp.rfft(x, self.nfft, axis=0))

    def fb(self, y: np.ndarray) -> np.ndarray:
        return dsp.rfft(y, self.nfft, axis=0)

    def lag_range(self) -> tuple[int, int]:
        """Lags (grid steps) with at least one overlapping pair."""
        return -(self.n - 1) - self.off, self.m_len - 1 - self.off

    def corr(self, FA: np.ndarray, FB: np.ndarray, lags: np.ndarray) -> np.ndarray:
        c = dsp.irfft(FA * FB, self.nfft, axis=0)
        return c[(lags + self.off) % self.nfft]


def norm_xcorr(m: UniformSeries, s: UniformSeries, lags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pearson correlation of |w| at each lag over the overlap (mean removed per lag), and counts."""
    c = Correlator(m, s)
    va, vb = m.valid.astype(float), s.valid.astype(float)
    a = np.linalg.norm(m.values, axis=1) * va
    b = np.linalg.norm(s.values, axis=1) * vb
    # the six correlations from each series' own transform, few held at once (the transforms of one column
    # are those of the stacked columns, bit for bit; 4 h at 200 Hz: 46 MB each, 0.3 GB all six at once)
    fa0, fb0 = c.fa(va), c.fb(vb)
    n = np.round(c.corr(fa0, fb0, lags))
    fa1 = c.fa(a)
    sa = c.corr(fa1, fb0, lags)
    saa = c.corr(c.fa(a * a), fb0, lags)
    del fb0
    fb1 = c.fb(b)
    sb = c.corr(fa0, fb1, lags)
    sab = c.corr(fa1, fb1, lags)
    del fa1, fb1
    sbb = c.corr(fa0, c.fb(b * b), lags)
    del fa0
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


def rotation_solved_cost(a: np.ndarray, b: np.ndarray, use: np.ndarray, min_count: float) -> float:
    """The normalised rotation- and bias-solved cost of ``vector_cost`` between the master's rates ``a`` and the
    slave's ``b`` read at the same instants, over the rows ``use``: NaN for fewer than ``min_count`` rows or
    no motion."""
    if use.sum() < min_count:
        return float("nan")
    au = a[use]
    bu = b[use]
    au = au - au.mean(axis=0)
    bu = bu - bu.mean(axis=0)
    caa, cbb = float(np.sum(au * au)), float(np.sum(bu * bu))
    if not caa + cbb > 0:
        return float("nan")
    best = float(wahba(au.T @ bu)[1])
    return (caa + cbb - 2.0 * best) / (caa + cbb)


def continuous_cost(t_s: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d_s: float,
                    min_count: float) -> float:
    """:func:`rotation_solved_cost` at a continuous lag ``d_s``: the master's rows (instants ``t_s``, rates
    ``a``) against the slave's interpolant read at t + d_s (on the grid's instants and at d_s = k dt, the same
    series as lag k)."""
    b, ok = itp(t_s + d_s)
    return rotation_solved_cost(a, b, ok & valid, max(min_count, 10))


def substep_penalty(m: UniformSeries, s: UniformSeries) -> float:
    """The most a lag half a grid step off the cost's true minimum adds to the normalised cost:
    (dt / 2)^2 sum |w'|^2 / (C_aa + C_bb), the rates' derivative from the master's grid. A vibration near the
    grid's Nyquist makes it large: a minimum that falls between grid points then looks worse at the integer
    lags than an alias that falls on one."""
    dt = m.dt_s
    va = m.valid
    pair = va[1:] & va[:-1]
    if pair.sum() < 10 or va.sum() < 10 or s.valid.sum() < 10:
        return 0.0
    da = np.diff(m.values, axis=0)[pair] / dt
    a = m.values[va]
    b = s.values[s.valid]
    caa = float(np.sum((a - a.mean(axis=0)) ** 2)) / len(a)
    cbb = float(np.sum((b - b.mean(axis=0)) ** 2)) / len(b)
    if not caa + cbb > 0:
        return 0.0
    return float((0.5 * dt) ** 2 * np.mean(np.sum(da * da, axis=1)) / (caa + cbb))


def subsample_minima(m: UniformSeries, s: UniformSeries, itp: Interpolant, lags: np.ndarray, cost: np.ndarray,
                     best: int, mins: np.ndarray, min_count: float, margin: float, cfg: LatencyConfig,
                     keep: int | None = None) -> dict[int, tuple[float, float]]:
    """The integer-lag minima that the grid may rank wrongly, each at its continuous minimum: {index: (lag s,
    cost)} for the best and every other minimum whose integer-lag cost lies within ``margin`` (the periodic
    test's) or ``subsample_margin`` x the sub-step penalty (``substep_penalty``) of the best's, at most
    ``subsample_candidates`` of them (and the minimum ``keep``, where it is such a rival, whatever its rank);
    empty when the best has no such rival (nothing to re-rank)."""
    sc = cfg.search
    if not sc.subsample_rank:
        return {}
    dt = m.dt_s
    reach = cost[best] + max(margin, sc.subsample_margin * substep_penalty(m, s))
    rivals = [int(i) for i in mins if i != best and np.isfinite(cost[i]) and cost[i] <= reach]
    if not rivals:
        return {}
    rivals = sorted(rivals, key=lambda i: (i != keep, float(cost[i])))[:max(0, sc.subsample_candidates - 1)]
    # (every stride-th row of a long log: the ranking needs the cost's level, not every sample's share)
    stride = max(1, int(np.ceil(len(m.values) / sc.subsample_max_rows)))
    t, a, va = m.t_s[::stride], m.values[::stride], m.valid[::stride]
    from scipy import optimize  # (here: its import costs 0.2-0.3 s, and only logs with rival lags get this far)

    out = {}
    for i in [best] + rivals:
        k = float(lags[i])  # (searched in grid steps about it: a lag may be 1.7e9 s, clocks unrelated)
        r = optimize.minimize_scalar(lambda u: continuous_cost(t, a, va, itp, (k + float(u)) * dt, min_count / stride),
                                     bounds=(-1.0, 1.0), method="bounded", options={"xatol": sc.subsample_xtol})
        c = float(r.fun)
        if not np.isfinite(c) or c > cost[i]:  # (a gap at the bracket's end: the grid's own value)
            out[i] = (k * dt, float(cost[i]))
        else:
            out[i] = ((k + float(r.x)) * dt, c)
    return out


def periodic_margin(c: float, cfg: LatencyConfig) -> float:
    """How far above a best normalised cost ``c`` another minimum still fits nearly as well (periodic)."""
    return max(cfg.search.periodic_margin, cfg.search.periodic_rel_margin * c)


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
    best = float(cost[jb])
    mins = local_minima(cost)

    def near(c: float) -> float:
        return periodic_margin(c, cfg)

    # the grid's ranking checked at the continuous minima: a constant-frequency vibration makes minima one
    # period apart, and the integer lags favour whichever falls on a grid point, not the one where the
    # low-frequency motion fits too (an aircraft vibrating at 8.56 Hz: its true lag 4.7 ms off the 100 Hz
    # grid cost 0.0106 against 0.0045 for an alias one period away; continuously 0.09 against 0.15 deg/s RMS)
    sub = subsample_minima(m, s, ctx.slave.itp, vlags, cost, jb, mins, min_count, near(best), cfg)
    j_grid = jb
    if sub:
        jb = min(sub, key=lambda i: sub[i][1])

    def eff(i: int) -> float:
        return sub[i][1] if i in sub else float(cost[i])

    # periodic motion: other local minima (outside the main lobe) nearly as low
    lobe = lobe_halfwidth(cost, jb)
    alts = [i for i in mins if abs(int(vlags[i]) - int(vlags[jb])) > lobe
            and (eff(i) <= eff(jb) + near(eff(jb)) if i in sub else cost[i] <= best + near(best))]
    if alts:
        # near-equal minima (motion that repeats): the one with the most overlapping data is the better
        # supported (the same residual per sample over more samples); the others stay the alternatives
        cand = [jb] + alts
        jn = max(cand, key=lambda i: (float(vc.count[i]), -eff(i)))
        if jn != jb and vc.count[jn] > vc.count[jb]:
            alts = [i for i in cand if i != jn]
            jb = jn
    if jb != j_grid and jb in sub:  # a minimum between grid points: where it lies
        d0, best = sub[jb]
    else:  # the grid's parabolic vertex, as ever
        best = float(cost[jb])
        contiguous = (0 < jb < len(vlags) - 1 and vlags[jb + 1] - vlags[jb - 1] == 2)
        d0 = (vlags[jb] + (parabolic(cost, jb) if contiguous else 0.0)) * dt
    return Coarse(lags * dt, rho, float(xc_lat), float(rho[ib]), vc, dt, float(d0), float(best),
                  tuple(float(vlags[i] * dt) for i in alts), tuple(eff(i) for i in alts))


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
    min_count = 0.8 * valid.sum()
    vc = vector_cost(ms, ss, lags, min_count)
    if not np.any(np.isfinite(vc.cost)):
        return None
    j = int(np.nanargmin(vc.cost))
    # (a vibration's minima a period apart: the one the grid favours is checked continuously, as ``coarse``)
    mins = local_minima(vc.cost)
    sub = subsample_minima(ms, ss, ctx.slave.itp, lags, vc.cost, j, mins, min_count,
                           periodic_margin(float(vc.cost[j]), ctx.cfg), ctx.cfg,
                           keep=int(mins[np.argmin(np.abs(lags[mins] - kc))]) if len(mins) else None)
    if sub:
        # minima that fit the window nearly alike (its slow motion too little to tell a vibration's periods
        # apart): the one nearest the line's prediction, not the noise's pick (an alias is no step)
        c_best = min(c for _, c in sub.values())
        alike = [i for i in sub if sub[i][1] <= c_best + periodic_margin(c_best, ctx.cfg)]
        jn = min(alike, key=lambda i: (abs(sub[i][0] - d_center), sub[i][1]))
        if jn != j:
            return sub[jn][0]
    return float((lags[j] + parabolic(vc.cost, j)) * dt)


def xcorr_estimate(ctx: Ctx) -> MethodEstimate:
    """Baseline: |w| normalised cross-correlation on the common grid, parabolic peak interpolation."""
    m, s = (series_on_grid(interpolant(lowpass(u, ctx.cfg.prepare.cutoff_fraction / ctx.dt_c)), ctx.dt_c)
            for u in ctx.raw.get())
    ctx.raw.release()  # (not held beside the correlation where large)
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

