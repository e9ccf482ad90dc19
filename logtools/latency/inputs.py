"""Stage 0, the inputs: each unit's angular rate (gyro, or from attitude plus the earth and transport
rates), on its own uniform grid, its white-noise level and the motion's band."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from logtools import earth
from logtools.conventions import dcm_from_quat, quat_conj, quat_make_continuous, quat_mul, rotvec_from_quat
from logtools.errors import AnalysisError
from logtools.inslog import InsLog
from logtools.navcheck import nav_gaps, output_validity
from logtools.resample import (Interpolant, UniformSeries, band_limited_factor, interpolant, lowpass,
                               to_uniform, to_uniform_band_limited)


def rate_from_attitude(t_s: np.ndarray, quat_wxyz: np.ndarray, *, drop_invalid: bool = False
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Body angular rate (rad/s, FRD) from body->NED quaternions by finite differences.

    ``q_{k+1} = q_k * dq``: ``w = rotvec(q_k^-1 q_{k+1}) / dt`` stamped at the interval's middle (the
    rate relative to the navigation frame; earth and transport rates, a few deg/h, are left out).
    ``drop_invalid``: NaN for the intervals that touch a frozen sample or a reset (``logtools.navcheck``:
    an EKF not yet running logs the identity; a board's first 19 s of it and a 169 deg yaw reset made a
    rate fit's cost 0.88 of the motion). The intervals over a gap (``navcheck.nav_gaps``) are left out.
    """
    t = np.asarray(t_s, dtype=float)
    q = np.asarray(quat_wxyz, dtype=float)
    ok = np.isfinite(t) & np.all(np.isfinite(q), axis=1)
    t, q = t[ok], q[ok]
    order = np.argsort(t, kind="stable")
    t, q = t[order], quat_make_continuous(q[order])
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, q = t[keep], q[keep]
    if len(t) < 2:
        return np.zeros(0), np.zeros((0, 3))
    dq = quat_mul(quat_conj(q[:-1]), q[1:])
    w = rotvec_from_quat(dq) / np.diff(t)[:, None]
    gap = nav_gaps(t)
    if drop_invalid:
        valid, _ = output_validity(t, q, gap=gap)
        w[~(valid[:-1] & valid[1:])] = np.nan
    # an increment over a gap is no rate at any instant: left out (the series has a gap there)
    return 0.5 * (t[:-1] + t[1:])[~gap], w[~gap]


def unit_rate(log: InsLog, role: str) -> tuple[np.ndarray, np.ndarray, str]:
    name = f"{role} {log.meta.source_path or ''}".strip()
    gyro_ok = log.has_gyro and int(np.isfinite(log.gyro_rad_s()).all(axis=1).sum()) >= 20
    if gyro_ok or (log.has_gyro and not log.has_quat):
        t, w = log.t_imu_s(), log.gyro_rad_s()
        src = "gyro"
    elif log.has_quat:
        tq, q = log.quat_wxyz()
        t, w = rate_from_attitude(tq, q, drop_invalid=True)
        w = w + nav_rate_in_body(log, t, tq, q)
        src = "attitude"
    else:
        raise AnalysisError(f"{name}: latency needs angular rate or attitude; the log has neither")
    ok = np.isfinite(t) & np.all(np.isfinite(w), axis=1)
    if ok.sum() < 20:
        why = ("NaN-only or empty data" if ok.sum() < len(t) or not len(t)
               else "too few for a latency: a longer log, or a faster stream")
        raise AnalysisError(f"{name}: angular rate ({src}) has {int(ok.sum())} finite samples "
                            f"of {len(t)}, 20 needed ({why})")
    return t, w, src


def nav_rate_in_body(log: InsLog, t: np.ndarray, tq: np.ndarray, q: np.ndarray) -> np.ndarray:
    """omega_in (earth + transport rate) in the body frame at t, to make an attitude-derived rate
    (relative to NED) comparable with a gyro's (inertial): 15 deg/h plus v/R change direction in the
    body as the vehicle turns, a slowly varying difference a delay fit would otherwise absorb. Zero
    when the log has no position."""
    if len(t) == 0 or not log.has_pos:
        return np.zeros((len(t), 3))
    tp, lla = log.lat_lon_alt()
    okp = np.isfinite(tp) & np.all(np.isfinite(lla), axis=1)
    if okp.sum() < 1:
        return np.zeros((len(t), 3))
    tp, lla = tp[okp], lla[okp]
    lat = np.radians(np.interp(t, tp, lla[:, 0]))
    alt = np.interp(t, tp, lla[:, 2])
    vel = np.zeros((len(t), 3))
    if log.has_vel:
        tv, v = log.vel_ned_m_s()
        okv = np.isfinite(tv) & np.all(np.isfinite(v), axis=1)
        if okv.sum() >= 1:
            vel = np.stack([np.interp(t, tv[okv], v[okv, i]) for i in range(3)], axis=1)
    w_n = earth.earth_rate_ned(lat) + earth.transport_rate_ned(lat, alt, vel)
    okq = np.isfinite(tq) & np.all(np.isfinite(q), axis=1)
    tq, q = tq[okq], q[okq]
    order = np.argsort(tq, kind="stable")
    tq, q = tq[order], q[order]
    j = np.clip(np.searchsorted(tq, t), 0, len(tq) - 1)
    c_nb = dcm_from_quat(q[j])
    return np.einsum("kji,kj->ki", c_nb, w_n)


@dataclass(frozen=True)
class Unit:
    name: str
    source: str  # "gyro" | "attitude"
    rate_hz: float
    native: UniformSeries  # on its own grid, low-passed
    itp: Interpolant  # continuous
    grid: UniformSeries  # on the common grid
    noise_dps: float  # white-noise level of the raw samples (deg/s per sample)


def series_on_grid(itp: Interpolant, dt_s: float) -> UniformSeries:
    i0 = int(np.ceil(itp.t_first_s / dt_s - 1e-9))
    i1 = int(np.floor(itp.t_last_s / dt_s + 1e-9))
    t = np.arange(i0, i1 + 1) * dt_s
    v, ok = itp(t)
    v = np.where(ok[:, None], v, 0.0)
    return UniformSeries(i0, dt_s, v, ok, itp.warnings, itp.gaps_s)


def uniform_native(t: np.ndarray, w: np.ndarray, name: str) -> tuple[UniformSeries, float]:
    """The unit on its own uniform grid, and its white-noise level (rad/s per raw sample)."""
    try:
        nat = to_uniform(t, w, name=name)
    except ValueError as exc:
        msg = str(exc)
        raise AnalysisError(msg if msg.startswith(name) else f"{name}: {msg}") from None
    # noise per raw sample (second differences remove smooth motion): std(d2) = sqrt(6) sigma
    d2 = np.diff(nat.values[nat.valid], n=2, axis=0)
    noise = float(np.sqrt(np.mean((np.median(np.abs(d2), axis=0) * 1.4826) ** 2)) / np.sqrt(6.0)) if len(d2) else 0.0
    return nat, noise


def band_limited_native(nat: UniformSeries, t: np.ndarray, w: np.ndarray, rate_hz: float, cutoff_hz: float,
                        fraction: float, name: str) -> UniformSeries:
    """The unit on a grid ``up`` times denser than its rate, band-limited (``to_uniform_band_limited``), when
    its cutoff exceeds ``fraction`` of its rate (``up`` brings the cutoff within that fraction); else ``nat``."""
    up = band_limited_factor(cutoff_hz, 1.0 / rate_hz, fraction) if rate_hz > 0 else 1
    # (the same stamps as uniform_native's: its checks passed, so this grid's do)
    return to_uniform_band_limited(t, w, up, name=name) if up > 1 else nat


def signal_band_hz(nat: UniformSeries, noise_rad_s: float) -> float:
    """Frequency below which 99.5 % of the motion power (PSD above 3x the white-noise floor) lies."""
    from logtools.dsp import welch_psd

    # the longest run of valid samples: valid samples joined across a gap make a step, whose spectrum
    # (1/f^2) would pass for motion up to the Nyquist frequency
    ok = np.concatenate([[False], nat.valid, [False]])
    edges = np.flatnonzero(np.diff(ok.astype(np.int8)))
    starts, stops = edges[::2], edges[1::2]
    j = int(np.argmax(stops - starts)) if len(starts) else 0
    v = nat.values[starts[j]:stops[j]] if len(starts) else nat.values[:0]
    if len(v) > 2 ** 18:  # the central part is enough for a spectrum (speed)
        c = len(v) // 2
        v = v[c - 2 ** 17:c + 2 ** 17]
    fs = nat.rate_hz
    if len(v) < 64:
        return 0.4 * fs
    nper = int(min(len(v), 2 ** int(np.ceil(np.log2(max(64.0, 60.0 * fs))))))
    f, p = welch_psd(v - v.mean(axis=0), fs, nper)
    p = p.sum(axis=1)
    n0 = 3.0 * 3.0 * 2.0 * noise_rad_s ** 2 / fs  # 3x the one-sided white-noise PSD of 3 axes
    ex = np.clip(p - n0, 0.0, None)
    tot = ex.sum()
    if not tot > 0:
        return 0.4 * fs
    return float(f[min(len(f) - 1, int(np.searchsorted(np.cumsum(ex), 0.995 * tot)))])


def make_unit(nat: UniformSeries, noise: float, src: str, name: str, rate: float, dt_c: float,
               cutoff_hz: float) -> Unit:
    lp = lowpass(nat, cutoff_hz)
    itp = interpolant(lp)
    grid = series_on_grid(itp, dt_c)
    return Unit(name, src, rate, lp, itp, grid, float(np.degrees(noise)))


def inband_noise_dps(u: Unit, cutoff_hz: float) -> float:
    """The unit's white rate noise over the band below ``cutoff_hz``, as an RMS of the three axes (deg/s)."""
    return u.noise_dps * np.sqrt(3.0) * np.sqrt(min(1.0, 2.0 * cutoff_hz / u.rate_hz))


def motion_snr(u: Unit, cutoff_hz: float) -> tuple[float, float]:
    """(motion RMS deg/s of the low-passed, mean-removed rate; in-band SNR)."""
    v = u.grid.values[u.grid.valid]
    if len(v) < 10:
        return 0.0, 0.0
    motion = float(np.degrees(np.sqrt(np.mean(np.sum((v - v.mean(axis=0)) ** 2, axis=1)))))
    noise_inband = inband_noise_dps(u, cutoff_hz)
    return motion, float(motion / noise_inband) if noise_inband > 0 else np.inf

