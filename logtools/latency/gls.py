"""Generalised least squares helpers of the latency fits (``logtools.latency``): the residual spectrum
(one shared, or a cross-spectral matrix) and its zero-phase whitening filter, the taper of the used
samples, and the covariance of a whitened fit with a Newey-West (HAC) floor."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from logtools import dsp
from logtools.latency.config import DEFAULT, LatencyConfig


def hac_cov(u: np.ndarray, max_lag: int, cfg: LatencyConfig = DEFAULT) -> tuple[np.ndarray, float]:
    """Newey-West (Bartlett) covariance of sum_k u_k for serially correlated u (N, p); the bandwidth is
    cfg.gls.hac_bandwidth_factor times the lag where u's mean autocorrelation first drops below 0.1.
    Returns (covariance (p, p), bandwidth in samples)."""
    N, p = u.shape
    nfft = sfft.next_fast_len(2 * N, real=True)
    F = dsp.rfft(u, nfft, axis=0)
    nl = min(N, max_lag + 1)
    # ac[h, i, j] = sum_k u_i[k] u_j[k + h]
    ac = np.empty((nl, p, p))
    for i in range(p):
        for j in range(p):
            ac[:, i, j] = dsp.irfft(np.conj(F[:, i]) * F[:, j], nfft)[:nl]
    g0 = np.diag(ac[0]).copy()
    g0[g0 <= 0] = np.finfo(float).tiny
    rho = (np.diagonal(ac, axis1=1, axis2=2) / g0).mean(axis=1)
    below = np.flatnonzero(rho < 0.1)
    h1 = int(below[0]) if len(below) else nl - 1
    H = int(np.clip(cfg.gls.hac_bandwidth_factor * h1, 1, nl - 1)) if nl > 1 else 0
    if H == 0:
        return ac[0], 0.0
    w = 1.0 - np.arange(1, H + 1) / (H + 1.0)
    S = np.sum(w[:, None, None] * ac[1:H + 1], axis=0)
    V = ac[0] + S + S.T
    return V, float(H)


@dataclass(frozen=True)
class NoiseModel:
    """Smoothed power spectrum of the residual w_s(t + d) - R w_m(t) - b on ``f_hz``: flexure's
    differential rate (a second-order Markov process, coloured, low frequency), the gyros' white noise
    and what the low-pass leaves, i.e. the disturbance a delay fit must weigh.

    ``psd`` is either one spectrum shared by the channels, (nf,), or a cross-spectral density matrix
    (nf, C, C) of C channels (gyro and accelerometer residuals: flexure tilts the specific force as it
    rotates the slave, so the two are coherent and the accelerometers tell the flexure apart from the
    delay); ``floor`` is then one number per channel."""

    f_hz: np.ndarray
    psd: np.ndarray
    floor: float | np.ndarray  # numerical floor (the low-pass stop band)
    tail_s: float  # length of the whitening filter's impulse response (zero padding)

    def weights(self, n: int, dt_s: float) -> tuple[int, np.ndarray]:
        """(nfft, W): W = PSD^-1/2 on the rfft bins of nfft, (nfreq,) or (nfreq, C, C)."""
        pad = min(n, int(np.ceil(self.tail_s / dt_s)))
        nfft = sfft.next_fast_len(n + pad, real=True)
        f = sfft.rfftfreq(nfft, dt_s)
        if self.psd.ndim == 1:
            return nfft, 1.0 / np.sqrt(np.interp(f, self.f_hz, self.psd) + self.floor)
        C = self.psd.shape[1]
        flat = self.psd.reshape(len(self.f_hz), C * C)
        S = np.empty((len(f), C * C), complex)
        for j in range(C * C):
            S[:, j] = (np.interp(f, self.f_hz, flat[:, j].real)
                       + 1j * np.interp(f, self.f_hz, flat[:, j].imag))
        S = S.reshape(len(f), C, C) + np.diag(np.asarray(self.floor, float))
        lam, V = np.linalg.eigh(S)
        lam = np.maximum(lam, 1e-300)
        return nfft, np.einsum("fij,fj,fkj->fik", V, 1.0 / np.sqrt(lam), np.conj(V))

    def whiten(self, x: np.ndarray, dt_s: float, weights: tuple[int, np.ndarray] | None = None) -> np.ndarray:
        """The zero-phase whitening filter PSD^-1/2 applied along axis 0 (zero-filled masks); with a
        cross-spectral matrix, x is (n, C, K) and the channels are mixed bin by bin. ``weights``:
        ``self.weights(len(x), dt_s)`` when already computed."""
        n = len(x)
        nfft, w = weights if weights is not None else self.weights(n, dt_s)
        X = dsp.rfft(x, nfft, axis=0)
        if w.ndim == 1:
            Z = X * w.reshape((len(w),) + (1,) * (x.ndim - 1))
        else:
            Z = np.matmul(w, X)
        return dsp.irfft(Z, nfft, axis=0)[:n]


def end_taper(use: np.ndarray, n_ramp: int) -> np.ndarray:
    """Weights rising as a raised cosine over n_ramp samples from every end of the used runs."""
    if n_ramp <= 1:
        return use.astype(float)
    from scipy import ndimage as _nd

    dist = _nd.distance_transform_edt(np.pad(use, 1, constant_values=False))[1:-1]
    x = np.clip(dist / n_ramp, 0.0, 1.0)
    return np.where(use, 0.5 - 0.5 * np.cos(np.pi * x), 0.0)


def leverage_spectrum(J: np.ndarray, use: np.ndarray) -> np.ndarray:
    """The fraction of a white noise's power at each rfft frequency that a least-squares fit with design
    J (n, C, P; 0 where unused) takes out of its residual: mean over the C channels of
    sum_k |FFT(q_k)|^2 / n_used, q_k the orthonormal columns of J. A residual's periodogram divided by
    (1 - that) is unbiased for white noise (the fitted columns empty the low frequencies of a short
    record, and a spectrum estimated from it would overweight exactly there)."""
    n, C, P = J.shape
    A = np.where(use[:, None, None], J, 0.0).reshape(n * C, P)
    keep = np.linalg.norm(A, axis=0) > 0
    if not keep.any():
        return np.zeros(n // 2 + 1)
    Q, Rq = np.linalg.qr(A[:, keep])
    d = np.abs(np.diag(Rq))
    Q = Q[:, d > 1e-10 * d.max()].reshape(n, C, -1)
    F = dsp.rfft(Q, axis=0)
    return np.sum(np.abs(F) ** 2, axis=2).mean(axis=1) / max(1.0, float(use.sum()))


def noise_model(r: np.ndarray, use: np.ndarray, dt_s: float, *, matrix: bool = False,
                leverage: np.ndarray | None = None, cfg: LatencyConfig = DEFAULT) -> NoiseModel | None:
    """Residual spectrum from one fit's residuals (N, C) (0 where unused): periodogram over the whole
    span smoothed over cfg.gls.smooth_hz (a 2nd-order Markov spectrum is smooth on that scale); averaged
    over the axes (one spectrum), or with ``matrix`` the C x C cross-spectral density, smoothed over at
    least cfg.gls.csd_bins bins so that it is well conditioned. ``leverage`` (``leverage_spectrum`` of the
    fit's design; single spectrum only): the periodogram is divided by 1 - leverage (at most by
    1 / cfg.gls.leverage_min_keep) before smoothing."""
    n, C = r.shape
    if n < 256 or use.sum() < 128:
        return None
    x = np.where(use[:, None], r, 0.0)
    X = dsp.rfft(x, axis=0)
    f = sfft.rfftfreq(n, dt_s)
    k = max(3, int(round(cfg.gls.smooth_hz * n * dt_s))) | 1
    if matrix:
        k = max(k, cfg.gls.csd_bins | 1)
    k = min(k, (len(f) // 4) | 1)
    norm = max(1.0, float(use.sum()))
    if not matrix:
        p = np.mean(np.abs(X) ** 2, axis=1) / norm
        if leverage is not None:
            p = p / np.clip(1.0 - leverage, cfg.gls.leverage_min_keep, 1.0)
        ps = np.convolve(np.pad(p, k // 2, mode="reflect"), np.ones(k) / k, mode="valid")
        top = float(ps.max())
        if not top > 0:
            return None
        return NoiseModel(f, ps, cfg.gls.floor * top, 1.0 / cfg.gls.smooth_hz)
    from scipy.ndimage import uniform_filter1d

    P = (X[:, :, None] * np.conj(X[:, None, :])).reshape(len(f), C * C) / norm
    P = (uniform_filter1d(P.real, k, axis=0, mode="reflect")
         + 1j * uniform_filter1d(P.imag, k, axis=0, mode="reflect")).reshape(len(f), C, C)
    top = np.max(np.real(np.diagonal(P, axis1=1, axis2=2)), axis=0)
    if not np.all(top > 0):
        return None
    return NoiseModel(f, P, cfg.gls.floor * top, 1.0 / cfg.gls.smooth_hz)


def gls_covariance(Ninv: np.ndarray, s2: float, u: np.ndarray, dt_s: float, fit_drift: bool, *,
                    check: tuple[np.ndarray, np.ndarray] | None = None, free_step: np.ndarray | None = None,
                    var_floor: float = 0.0, hac_corr: bool = False, cfg: LatencyConfig = DEFAULT
                    ) -> tuple[np.ndarray, float, float, tuple[float, float]]:
    """Variances of (L[, drift]) of a (whitened) least-squares fit -- every fit's covariance comes from here: the curvature's (s2 diag(Ninv)) with the
    Newey-West variance of the per-sample scores u (n, nd) as a floor (what the whitening missed; lags
    up to 20 s at the samples' interval dt_s), and the latency's at least ``var_floor`` (the drift's
    scaled alike). Returns (var (nd,), corr(L, drift), variance factor over the curvature's, (delay of the
    accelerometers' own, its sigma)) -- the last from ``check`` = (augmented normal matrix, right-hand
    side) with the model-check column last, or, where that delay is the fit's last unknown, from
    ``free_step`` (the fit's last step, its last element that delay) and Ninv; else (0, 0). ``hac_corr``
    (the unwhitened first fit, ``fit.refine``): corr(L, drift) from the HAC covariance alone."""
    nd = u.shape[1]
    var_cls = s2 * np.diag(Ninv)[:nd]
    V_hac, _H = hac_cov(u, int(min(len(u) // 4, max(10, 20.0 / dt_s))), cfg)
    var_h = np.diag(V_hac)
    var = np.maximum(var_h, var_cls)
    up = max(1.0, var_floor / var[0]) if var[0] > 0 else 1.0
    var = var * up
    corr = 0.0
    if hac_corr:
        if fit_drift and var_h[0] > 0 and var_h[1] > 0:
            corr = float(np.clip(V_hac[0, 1] / np.sqrt(var_h[0] * var_h[1]), -cfg.gls.corr_max, cfg.gls.corr_max))
    elif fit_drift and var[0] > 0 and var[1] > 0:
        cv = (V_hac[0, 1] if var_h[0] >= var_cls[0] else s2 * Ninv[0, 1]) * up
        corr = float(np.clip(cv / np.sqrt(var[0] * var[1]), -cfg.gls.corr_max, cfg.gls.corr_max))
    fac = float(var[0] / var_cls[0]) if var_cls[0] > 0 else 1.0
    acc_lag = (0.0, 0.0)
    if check is not None:
        try:
            Nx, b = check
            sx = np.linalg.solve(Nx, b)
            vx = float(np.linalg.inv(Nx)[-1, -1]) * s2 * max(1.0, fac)
            acc_lag = (-float(sx[-1]), float(np.sqrt(max(vx, 0.0))))
        except np.linalg.LinAlgError:
            acc_lag = (np.inf, np.inf)
    elif free_step is not None:
        acc_lag = (float(free_step[-1]), float(np.sqrt(max(s2 * Ninv[-1, -1] * max(1.0, fac), 0.0))))
    return var, corr, fac, acc_lag


def window_chi2(centers: np.ndarray, lats: np.ndarray, sigs: np.ndarray, latency_s: float, drift: float,
                t_mid: float) -> float:
    """Reduced chi-square of window delay estimates (at ``centers``, sigmas ``sigs``) about the line
    latency_s + drift (t - t_mid); 1 below 3 windows (nothing to check against)."""
    if len(centers) < 3:
        return 1.0
    res = np.asarray(lats) - (latency_s + drift * (np.asarray(centers) - t_mid))
    return float(np.sum((res / np.asarray(sigs)) ** 2) / max(1, len(centers) - 2))


def grid_derivative(y: np.ndarray, ok: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """d/dt of the rows y (n, k) of a uniform grid (4th-order central differences: 0.1 % low at a fifth
    of the sampling rate, where the fits' motion lies at most), and where it holds (the five samples
    around a row all ok; 0 elsewhere)."""
    n = len(y)
    d = np.zeros(y.shape)
    okd = np.zeros(n, bool)
    if n >= 5:
        yz = np.where(ok.reshape((-1,) + (1,) * (y.ndim - 1)), y, 0.0)
        d[2:-2] = (yz[:-4] - 8.0 * yz[1:-3] + 8.0 * yz[3:-1] - yz[4:]) / (12.0 * dt_s)
        okd[2:-2] = ok[:-4] & ok[1:-3] & ok[2:-2] & ok[3:-1] & ok[4:]
        d[~okd] = 0.0
    return d, okd


def delay_normal(Jf: np.ndarray, Dm: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(normal matrix, gradient, master's side taken) of a delay fit (Jacobian Jf (m, P), residual r (m,)),
    its delay's [and drift's] columns -- the first nd of Jf, the slave's derivative -- replaced by Dm (m, nd),
    the same columns from the model's (the master's) derivative, where that derivative is the cleaner of
    the two (the smaller energy in the delay's column: both carry the signal's, each its own noise's); the
    delay's gradient then comes from Dm too (Dm^T r: the delay seen as a shift of the master). Where the
    slave's is the cleaner: the ordinary Gauss-Newton system (Jf^T Jf, Jf^T r) and False.

    Why: a derivative's noise energy counts in the Gauss-Newton curvature as delay information. It
    grows with the band (flexure, vibration): an aircraft with seed 000's flexure at a 7 Hz cutoff had
    18x its motion's in the slave's derivative, so each step went a few % of the way and the sigma was
    far too small; a ship's fast flexure at a 49 Hz cutoff, 1800x (45 ms off at z 800). And the gradient
    sum s' r of a spline-interpolated noisy slave ripples with the sub-sample phase (the interpolant's
    noise power does), which pulled the aircraft's delay 10 ms towards one phase in every noise seed.
    (The cross-product sum s' m', unbiased for the signal's curvature, drowned in the noise's products
    there and came out negative.)"""
    return delay_system(Jf.T @ Jf, Jf.T @ Dm, Dm.T @ Dm, Jf.T @ r, Dm.T @ r)


def delay_system(N: np.ndarray, JD: np.ndarray, DD: np.ndarray, g: np.ndarray, gd: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, bool]:
    """``delay_normal`` from the products: N = Jf^T Jf (P, P), JD = Jf^T Dm (P, nd), DD = Dm^T Dm,
    g = Jf^T r (P,), gd = Dm^T r (nd,)."""
    nd = DD.shape[0]
    if not DD[0, 0] < N[0, 0]:
        return N, g, False
    Nm = N.copy()
    Nm[:, :nd] = JD
    Nm[:nd, :] = JD.T
    Nm[:nd, :nd] = DD
    try:
        np.linalg.cholesky(Nm)
    except np.linalg.LinAlgError:
        return N, g, False
    gm = np.array(g, dtype=float)
    gm[:nd] = gd
    return Nm, gm, True


def gn_step(Jf: np.ndarray, rw: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(normal matrix, Gauss-Newton step) of a whitened least-squares problem (Jacobian (m, P), residual
    (m,) or any shape of m elements); None when the normal matrix is singular."""
    Nm = Jf.T @ Jf
    try:
        return Nm, -np.linalg.solve(Nm, Jf.T @ rw.ravel())
    except np.linalg.LinAlgError:
        return None


def delay_step(step: np.ndarray, dt_s: float, span_s: float, fit_drift: bool) -> tuple[float, float]:
    """The (latency, drift) part of a step, clipped to half a sample (the drift: half a sample at the
    ends of the span, +- span_s from the middle): a delay fit never jumps over a sample at once."""
    sd = float(np.clip(step[0], -0.5 * dt_s, 0.5 * dt_s))
    if not fit_drift:
        return sd, 0.0
    lim = 0.5 * dt_s / max(span_s, 1e-9)
    return sd, float(np.clip(step[1], -lim, lim))


def grid_offset_sigma_s(resolutions_s) -> float:
    """Sigma of a delay from stamps on coarse grids (one step per unit): with a fixed sampling phase every
    stamp of a unit is off by the same fraction of its step, uniform over it: sqrt(sum step^2 / 12)."""
    return float(np.sqrt(sum(q * q / 12.0 for q in resolutions_s)))


def stamp_noise_variance(sigma_stamp_s: float, g: np.ndarray, samples_per_point: float = 1.0) -> float:
    """Variance of a least-squares delay from white stamp noise: the delay is a weighted mean of the
    stamps' errors, weights ``g`` per point (|signal'|^2), so sigma_t^2 sum g^2 / (sum g)^2; with
    ``samples_per_point`` stamps behind each point (a fit grid coarser than the samples) it divides."""
    den = float(np.sum(g)) ** 2
    if not (sigma_stamp_s > 0 and den > 0 and samples_per_point > 0):
        return 0.0
    return sigma_stamp_s ** 2 * float(np.sum(g * g)) / den / samples_per_point

