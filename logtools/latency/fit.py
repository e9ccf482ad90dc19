"""Stage 3, the delay problem and its first solution: the fit record ``Fit``, the joint Jacobian, the
residuals, and the Gauss-Newton refinement on the raw (unwhitened) residual with its HAC covariance."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from logtools import dsp
from logtools.conventions import median_step_s, wahba
from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.latency.flexure import FlexureModel
from logtools.latency.gls import delay_normal, gls_covariance, grid_derivative
from logtools.resample import Interpolant


@dataclass(frozen=True)
class Fit:
    latency_s: float
    drift: float  # s/s
    R: np.ndarray
    bias: np.ndarray  # rad/s, slave frame
    sigma_latency_s: float
    sigma_drift: float
    residual_rms: float  # rad/s
    n: int
    hac_factor: float  # variance inflation for correlated residuals
    motion_rms: float  # rad/s, master, in the used samples
    ok: bool = True
    corr_ld: float = 0.0  # correlation of the (L, drift) estimates
    aided: bool = False  # accelerometer-aided GLS
    flex: FlexureModel | None = None  # the state-space flexure model of a Kalman-whitened fit
    accel_lag_s: tuple[float, float] = (0.0, 0.0)  # accelerometers' extra delay and its sigma (aided fits)
    accel_lag_free: bool = False  # ... that delay an unknown of the fit (else the model check's figures)
    model_gap_s: float = 0.0  # |spectral - Kalman| latency when the two fits disagree (cfg.flexure.agree_sigmas)


def kabsch_bias(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    M = (a - ma).T @ (b - mb)
    R = np.ascontiguousarray(wahba(M)[0].T)  # b ~ R a (C order: the products as before, bit for bit)
    return R, mb - R @ ma


def rate_jacobian(bd: np.ndarray, tu: np.ndarray | None, Ra: np.ndarray) -> np.ndarray:
    """(3N, P) Jacobian of r = w_s(t + L + drift t) - R w_m - b w.r.t. (L[, drift], rotation, bias)."""
    n = len(bd)
    P = 8 if tu is not None else 7
    J = np.zeros((n, 3, P))
    J[:, :, 0] = bd
    k = 1
    if tu is not None:
        J[:, :, 1] = bd * tu[:, None]
        k = 2
    x, y, z = Ra[:, 0], Ra[:, 1], Ra[:, 2]
    # d(r)/d(theta) = [R a]x  (R -> exp([theta]x) R)
    J[:, 1, k], J[:, 2, k] = z, -y
    J[:, 0, k + 1], J[:, 2, k + 1] = -z, x
    J[:, 0, k + 2], J[:, 1, k + 2] = y, -x
    J[:, 0, k + 3] = J[:, 1, k + 4] = J[:, 2, k + 5] = -1.0
    return J.reshape(3 * n, P)


def residual(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, f: Fit,
              t_mid: float) -> np.ndarray:
    """Residuals (N, 3) of a fit on the refinement grid; 0 where masked."""
    bv, ok = itp(t_m + f.latency_s + f.drift * (t_m - t_mid))
    r = bv - a @ f.R.T - f.bias
    r[~(ok & valid)] = 0.0
    return r


def residuals(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d: float, dr: float,
               tt: np.ndarray):
    """Residuals of the slave read at t + d + dr*tt against R a + b (R, b by Kabsch with means):
    (slave derivative, master rows, tt rows, R, b, residuals, cost, rows used), or the number of usable
    samples when there are fewer than 20."""
    tau = t_m + d + dr * tt
    bv, ok = itp(tau)
    use = ok & valid
    if use.sum() < 20:
        return int(use.sum())
    bd, _ = itp(tau[use], 1)
    au, bu, tu = a[use], bv[use], tt[use]
    R, bias = kabsch_bias(au, bu)
    r = bu - au @ R.T - bias
    return bd, au, tu, R, bias, r, float(np.sum(r * r)), use


def refine(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d0: float,
            drift0: float, t_mid: float, *, fit_drift: bool, iters: int | None = None,
           cfg: LatencyConfig = DEFAULT) -> Fit:
    """Gauss-Newton on (L[, drift]) with R, b re-solved (Kabsch with means) at every step, the delay's
    gradient and curvature from the cleaner unit's derivative (``gls.delay_normal``); covariance of
    the joint (L, drift, rotation, bias) problem with a HAC score variance (``gls.gls_covariance``)."""
    iters = cfg.refine.gn_iters if iters is None else iters
    d, dr = float(d0), float(drift0)
    dt = median_step_s(t_m, 1.0)
    tt = t_m - t_mid
    ad, okd = grid_derivative(a, valid, dt)  # the master's derivative (delay_normal)

    def master_derivative(bd: np.ndarray, use: np.ndarray, R: np.ndarray) -> np.ndarray:
        """R a' at the used rows (the slave's derivative where the master's does not hold)."""
        return np.where(okd[use][:, None], ad[use] @ R.T, bd)

    prev = np.inf
    for _ in range(iters):
        ev = residuals(t_m, a, valid, itp, d, dr, tt)
        if isinstance(ev, int):
            return Fit(d, dr, np.eye(3), np.zeros(3), np.inf, np.inf, np.nan, ev, 1.0, 0.0, False)
        bd, au, tu, R, bias, r, cost, use = ev
        md = master_derivative(bd, use, R)
        # reduced Gauss-Newton step on (L[, drift]) (variable projection: R and b are re-solved
        # exactly at every iteration; the bias is projected out of the step by centring), the
        # curvature from the cleaner of the two units' derivatives (see delay_normal)
        J = [bd - bd.mean(axis=0)]
        Jm = [md - md.mean(axis=0)]
        if fit_drift:
            jd, jm = bd * tu[:, None], md * tu[:, None]
            J.append(jd - jd.mean(axis=0))
            Jm.append(jm - jm.mean(axis=0))
        Js = np.stack([x.ravel() for x in J], axis=1)
        Dm = np.stack([x.ravel() for x in Jm], axis=1)
        Nr, gr, _ = delay_normal(Js, Dm, r.ravel())
        try:
            step = -np.linalg.solve(Nr, gr)
        except np.linalg.LinAlgError:
            return Fit(d, dr, R, bias, np.inf, np.inf, np.sqrt(cost / max(1, r.size)), len(au), 1.0, 0.0, False)
        sd = float(np.clip(step[0], -0.5 * dt, 0.5 * dt))
        d += sd
        if fit_drift:
            span = max(1e-9, float(np.max(np.abs(tu))))
            dr += float(np.clip(step[1], -0.5 * dt / span, 0.5 * dt / span))
        if abs(sd) < 1e-4 * dt or abs(prev - cost) <= 1e-10 * max(cost, 1e-300):
            break
        prev = cost
    # covariance at the solution: joint (L[, drift], rotation, bias) normal equations, HAC-corrected
    nd = 1 + int(fit_drift)
    ev = residuals(t_m, a, valid, itp, d, dr, tt)
    if isinstance(ev, int):
        return Fit(d, dr, np.eye(3), np.zeros(3), np.inf, np.inf, np.nan, ev, 1.0, 0.0, False)
    bd, au, tu, R, bias, r, cost, use = ev
    Jfull = rate_jacobian(bd, tu if fit_drift else None, au @ R.T)
    Jm = rate_jacobian(master_derivative(bd, use, R), tu if fit_drift else None, au @ R.T)
    rr = r.ravel()
    Nm, _, master = delay_normal(Jfull, Jm[:, :nd], rr)
    if not master:
        Jm = Jfull
    try:
        Ninv = np.linalg.inv(Nm)
    except np.linalg.LinAlgError:
        return Fit(d, dr, R, bias, np.inf, np.inf, np.sqrt(cost / max(1, r.size)), len(au), 1.0, 0.0, False)
    # per-sample scores from the derivative the step took (a noisy slave's: products with the residual
    # that cancel only over long lags; a HAC of them was 100x too large)
    G = (Jm * rr[:, None]).reshape(len(r), 3, -1).sum(axis=1)
    u = G @ Ninv[:, :nd]  # contributions to the (L, drift) step
    dof = max(1, r.size - Nm.shape[0])
    var, corr, fac, _ = gls_covariance(Ninv, cost / dof, u, dt, fit_drift, hac_corr=True, cfg=cfg)
    motion = motion_rms(a, use)
    return Fit(d, dr, R, bias, float(np.sqrt(var[0])), float(np.sqrt(var[1])) if fit_drift else 0.0,
                float(np.sqrt(cost / r.size)), len(au), fac, motion, corr_ld=corr)


def best_cutoff(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, r: np.ndarray, dt_s: float,
                 cutoff_hz: float, overlap_s: float, cfg: LatencyConfig = DEFAULT) -> float:
    """Cutoff fc minimising the predicted variance of a least-squares delay on signals band-limited
    at fc: var(fc) ~ sum_{f<fc} w^2 S N / (sum_{f<fc} w^2 S)^2 (S: master rate PSD, N: residual PSD)."""
    if len(r) < 256:
        return cutoff_hz
    # periodograms over the whole overlap (the motion may be slower than any Welch segment); the
    # noise spectrum smoothed over a few bins
    am = np.where(valid[:, None], a - a[valid].mean(axis=0), 0.0)
    f = sfft.rfftfreq(len(r), dt_s)
    S = np.sum(np.abs(dsp.rfft(am, axis=0)) ** 2, axis=1)
    N = np.sum(np.abs(dsp.rfft(r, axis=0)) ** 2, axis=1)
    k = 9
    N = np.convolve(np.pad(N, k // 2, mode="edge"), np.ones(k) / k, mode="valid")
    w2s = (2 * np.pi * f) ** 2 * S
    num = np.cumsum(w2s * N)
    den = np.cumsum(w2s)
    f_min = max(cfg.refine.min_adapt_cutoff_hz, cfg.refine.min_adapt_cycles / max(overlap_s, 1.0))
    cand = (f >= f_min) & (f <= cutoff_hz) & (den > 0)
    if not cand.any():
        return cutoff_hz
    var = np.where(cand, num / np.where(den > 0, den, 1.0) ** 2, np.inf)
    k = int(np.argmin(var))
    # keep the full band unless narrowing gains clearly (>20 % in sigma)
    full = np.flatnonzero(cand)[-1]
    if not var[k] < cfg.refine.adapt_gain * var[full]:
        return cutoff_hz
    return float(min(cutoff_hz, 1.25 * f[k]))


def fit_start(t_m: np.ndarray, t_mid: float, d0: float, drift0: float
               ) -> tuple[float, float, float, np.ndarray, float, Fit]:
    """(d, drift, sample interval, t - t_mid, half span, the failed fit) at the start of a refinement."""
    d, dr = float(d0), float(drift0)
    dt = median_step_s(t_m, 1.0)
    tt = t_m - t_mid
    span = float(np.max(np.abs(tt))) if len(t_m) else 0.0
    return d, dr, dt, tt, span, Fit(d, dr, np.eye(3), np.zeros(3), np.inf, np.inf, np.nan, 0, 1.0, 0.0, False)


def motion_rms(a: np.ndarray, use: np.ndarray) -> float:
    """RMS of the master's rate about its mean over the used samples (rad/s)."""
    au = a[use]
    return float(np.sqrt(np.mean(np.sum((au - au.mean(axis=0)) ** 2, axis=1))))

