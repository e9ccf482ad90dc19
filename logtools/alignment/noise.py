"""The slave's accelerometer noise as the filter needs it: without the lever arm's acceleration.

The filter's velocity random walk and its accelerometer-bias prior come from the slave's samples' white noise,
measured from third differences (smooth motion cancels, ``d3_sigma``). A rigid-body vibration does not cancel
there: at 50-100 Hz the lever arm's share of an 8-20 Hz vibration (w' x r, metres per second squared at a
metre) is most of the accelerometers' third differences, and counted as their noise (31-69x the true one on
an independent simulator's multirotor and car) it let the slave's velocity wander by more than the lever
arm's velocity over one update: the lever arm came out at 0.3-0.84 of itself, 3.7-5.4 sigma off (one car 0.79 m
off). The filter models that acceleration (its lever-arm states, the rate as the slave's strapdown integrates
it: ``run._lever_rate_as_integrated``), so it is motion, not noise.

``accel_noise_without_lever`` measures the third differences of f_s - R0 f_m - R0 (w_m' x r + w_m x (w_m x r)):
the master's specific force and the lever arm's acceleration through the coarse mounting R0 at the slave's
stamps (cubic splines of the master's IMU), r fitted by least squares on the same third differences, f_m, w_m
and w_m' with nothing above the slave's Nyquist rate (what the filter models: the slave's samples alias what
is above it into motion the master's navigation output does not have; and the master's gyro noise,
differentiated, would otherwise swamp the slave's noise). The delay is refitted per chunk from the gyros'
third differences against the master's angular acceleration (the latency's residual and a drift move it). The
caller keeps the smaller of this and the samples' own, so a master that explains less (a noisy one, a
drifting clock) changes nothing.

The gyros keep their samples' own noise: the slave's strapdown integrates a vibration's rate with the
trapezoid's error, which the filter does not model, and taking the vibration out of their noise put the
simulator's mountings 1.4-3.9 arcmin off at sigmas of 0.5 (z up to 7.5). A master IMU less than
``min_rate_ratio`` times as fast as the slave's is not asked: two IMUs of one board logged at one rate alias a
motor's vibration alike, which the master's navigation output (from its full-rate IMU) does not carry, so for
the filter those aliases are the slave's noise.
"""
from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from logtools.conventions import skew
from logtools.dsp import cubic_spline_at, irfft, mad_sigma, rfft
from logtools.inslog import InsLog

from .imu_to_imu import finite_increasing


def d3_sigma(d3: np.ndarray) -> float:
    """White-noise sigma from third differences ``d3`` (n, k) of a series: robust (MAD), the largest column's
    (a white sample noise s gives third differences of variance 20 s^2)."""
    if len(d3) < 5:
        return 0.0
    return float(np.max(mad_sigma(d3)) / np.sqrt(20.0))


def d3_at(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Third differences of ``y`` (n, k) sampled at sorted stamps ``t`` that need not be uniform: the third
    divided difference of each four consecutive samples (zero for any quadratic motion), scaled so that white
    noise of sigma s gives variance 20 s^2 as :func:`d3_sigma` expects (the uniform case's y0 - 3 y1 + 3 y2 -
    y3, up to sign). Windows with repeated stamps are left out."""
    t = np.asarray(t, float)
    if len(t) < 4:
        return np.zeros((0,) + y.shape[1:])
    w = np.stack([t[i:len(t) - 3 + i] for i in range(4)], -1)  # (n-3, 4) the windows' stamps
    c = np.ones_like(w)
    for i in range(4):
        for j in range(4):
            if i != j:
                c[:, i] *= w[:, i] - w[:, j]
    with np.errstate(divide="ignore", invalid="ignore"):
        c = 1.0 / c
        c *= np.sqrt(20.0 / np.sum(c * c, axis=1, keepdims=True))
    ok = np.isfinite(c).all(axis=1)
    return sum(c[ok, i, None] * y[i:len(t) - 3 + i][ok] for i in range(4))


def _d3(x: np.ndarray) -> np.ndarray:
    return np.diff(x, n=3, axis=0)


def _cols_at(t: np.ndarray, y: np.ndarray, ts: np.ndarray) -> np.ndarray:
    return np.stack([cubic_spline_at(t, y[:, i], ts) for i in range(y.shape[1])], -1)


def _below(t: np.ndarray, y: np.ndarray, f_max_hz: float, with_rate: bool = True
           ) -> tuple[np.ndarray, np.ndarray | None]:
    """The columns of ``y`` on near-uniform stamps ``t`` and (``with_rate``) their d/dt, nothing above
    ``f_max_hz`` in either (FFT; the line through the ends taken out first, so that the series wraps without
    a jump)."""
    n = len(t)
    dt = (t[-1] - t[0]) / (n - 1)
    slope = (y[-1] - y[0]) / (n - 1)
    line = y[0] + np.arange(n, dtype=float)[:, None] * slope
    nfft = sfft.next_fast_len(n, real=True)
    f = sfft.rfftfreq(nfft, dt)
    spec = rfft(y - line, nfft, axis=0) * (f <= f_max_hz)[:, None]
    value = irfft(spec, nfft, axis=0)[:n] + line
    if not with_rate:
        return value, None
    return value, irfft(spec * (2j * np.pi * f)[:, None], nfft, axis=0)[:n] + slope / dt


def accel_noise_without_lever(master: InsLog, t_imu: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                              tau0_s: float, r0: np.ndarray, *, max_samples: int, chunk_s: float,
                              max_delay_s: float, min_rate_ratio: float) -> float | None:
    """The accelerometers' white-noise sigma (m/s^2) of the slave's samples (``t_imu`` relative seconds,
    ``gyro``, ``accel`` (N, 3)) less the master's specific force and the lever arm's acceleration through the
    coarse mounting ``r0`` (C_sm) at the delay ``tau0_s`` (slave stamp - master stamp), refitted per chunk of
    ``chunk_s`` within +-``max_delay_s``; at most ``max_samples`` slave samples in chunks spread over the
    overlap. None where the master has no gyro or accelerometers, its IMU is less than ``min_rate_ratio`` times
    as fast as the slave's, or they overlap too little."""
    if not (master.has_gyro and master.has_accel):
        return None
    tm, gm = finite_increasing(master.t_imu_s(), master.gyro_rad_s())
    ta, fm = finite_increasing(master.t_imu_s(), master.accel_m_s2())
    if min(len(tm), len(ta), len(t_imu)) < 64:
        return None
    dt_s = float(np.median(np.diff(t_imu)))
    dt_m = float(np.median(np.diff(tm)))
    if dt_m * min_rate_ratio > dt_s:
        return None
    margin = max_delay_s + 64 * dt_m
    ts = t_imu - tau0_s
    inside = np.flatnonzero((ts > tm[0] + margin) & (ts < tm[-1] - margin))
    size = int(min(max(chunk_s / dt_s, 64), len(inside)))
    if size < 64:
        return None
    n_chunks = max(1, min(len(inside) // size, max_samples // size))
    f_max = 0.5 / dt_s
    y_a, a_a = [], []
    for s0 in np.linspace(0, len(inside) - size, n_chunks).astype(int):
        idx = inside[s0:s0 + size]
        if np.diff(t_imu[idx]).max() > 10 * dt_s:
            continue  # (a gap: third differences across it are not noise)
        t = ts[idx]
        j0 = max(int(np.searchsorted(tm, t[0] - margin)), 0)
        j1 = min(int(np.searchsorted(tm, t[-1] + margin)), len(tm))
        tmc = tm[j0:j1]
        if (len(tmc) < 64 or tmc[0] > t[0] - max_delay_s or tmc[-1] < t[-1] + max_delay_s
                or np.diff(tmc).max() > 10 * dt_m):
            continue  # (a gap in the master's gyro: no spline across it, no FFT over it)
        gmc, gdc = _below(tmc, gm[j0:j1], f_max)
        # the delay's residual: g_s = R w(t - dtau) ~ R w(t) - R w'(t) dtau
        y, x = _d3(gyro[idx] - _cols_at(tmc, gmc, t) @ r0.T), _d3(_cols_at(tmc, gdc, t) @ r0.T)
        dtau = float(np.clip(-np.sum(x * y) / max(float(np.sum(x * x)), 1e-300), -max_delay_s, max_delay_s))
        t = t - dtau
        k0 = max(int(np.searchsorted(ta, t[0])) - 8, 0)
        k1 = min(int(np.searchsorted(ta, t[-1])) + 8, len(ta))
        if k1 - k0 < 64 or ta[k0] > t[0] or ta[k1 - 1] < t[-1] or np.diff(ta[k0:k1]).max() > 10 * dt_m:
            continue
        f = _cols_at(ta[k0:k1], _below(ta[k0:k1], fm[k0:k1], f_max, with_rate=False)[0], t)
        sw = skew(_cols_at(tmc, gmc, t))
        rk = np.einsum("ij,njk->nik", r0, skew(_cols_at(tmc, gdc, t)) + sw @ sw)  # R0 K: lever accel = R0 K r
        y_a.append(_d3(accel[idx] - f @ r0.T))
        a_a.append(_d3(rk))
    if not y_a:
        return None
    ya, aa = np.concatenate(y_a), np.concatenate(a_a)
    r, *_ = np.linalg.lstsq(aa.reshape(-1, 3), ya.reshape(-1), rcond=None)
    return d3_sigma(ya - np.einsum("nij,j->ni", aa, r))
