"""The rotation of the slave's IMU triads relative to the master's, measured directly from the two IMUs.

Where both units log an IMU, two rotations can be measured without any navigation solution:

- the **gyro triad**: Wahba on the angular rates, ``w_slave = R w_master`` (the same angular velocity
  everywhere on a rigid body);
- the **accelerometer triad**: Wahba on the part of the specific force that moves (high-passed: the
  biases and the mean gravity go), ``f_slave = R (f_master + K(w, dw/dt) r)`` with the lever arm ``r``
  (master frame) estimated with it: the slave's accelerometers sit elsewhere and feel the centripetal and
  angular accelerations of that offset.

Both in the convention of ``mounting_rpy_deg`` (DESIGN.md: ``v_slave_FRD = R v_master_FRD``, intrinsic
Z-Y-X, listed [roll, pitch, yaw] degrees). The slave must already be on the master's clock (the
compensated slave): a latency left in it turns into a rotation error where the rates change.

Each rotation is refined by Gauss-Newton from the Wahba (SVD) start (the accelerometers' also from the gyro
triad's rotation, the smaller residual kept), the perturbation on the slave's side
(``R = exp([d x]) R_hat``); its sigma is the sandwich ``J^-1 Omega J^-1`` with ``J = sum H^T H`` (the
master's own white noise taken out of it: errors in variables, see :func:`fit_rotation`) and ``Omega`` the
long-run covariance of the scores ``H^T e`` (Newey-West, Bartlett weights, bandwidth from
the scores' correlation time): residuals correlated in time (vibration, scale-factor errors, flexure)
count as the fewer independent samples they are. A residual delay between the two IMUs is estimated with
each rotation (it would turn into one). The rotation is fitted again on the slow and on the fast part of
the motion apart: a rotation is the same at every frequency, so where the two differ beyond 3 sigma the
triads differ by more than a rotation (filters, aliased vibration, scale factors) and half the spread
joins the sigma as the model's error. ``consistency`` compares the rotations with the
nav-referenced mounting of the transfer alignment and names the likely cause when they differ.
"""
from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import fft as sfft

from logtools import dsp, jit
from logtools.conventions import (dcm_from_euler, dcm_from_quat, dcm_from_rotvec, euler_from_dcm, median_step_s,
                                  quat_from_dcm, rotvec_from_dcm, skew, wahba)
from logtools.inslog import InsLog
from logtools.rows import BLOCK_ROWS



@dataclass(frozen=True)
class ImuToImuConfig:
    """Every tuning number of the IMU-to-IMU rotation and of the consistency check, with its reason
    (tests/test_imu_to_imu.py; docs/alignment_real_logs.md)."""

    highpass_s: float = 4.0  # the slow part (biases, mean gravity, earth rate) removed: a centred moving mean this long
    highpass_retry_s: tuple[float, ...] = (30.0,)  # ... longer where that leaves too little motion (a ship's sway)
    min_samples: int = 50  # fewer common samples: not measured
    min_explained: float = 0.5  # the fitted rotation must explain this fraction of the slave's (high-passed) power
    max_sigma_deg: float = 5.0  # an axis less determined than this: the triad's rotation is not reported (null)
    #: ... the reason then says the motion is along one direction only where the master's moving signal (its
    #: white noise taken out) has at most this fraction of its power on a second direction (level flight's
    #: specific force; fit_rotation's sigma then has no information about that direction: the reason why)
    one_direction_ratio: float = 0.01
    #: the master's white noise (taken out of its moments: errors in variables) from the third differences of
    #: at most this many rows, in blocks of noise_block_rows spread over a longer series (a robust MAD settles
    #: long before; 4 h of 200 Hz would otherwise be 2.9 M rows of differences per fit)
    noise_rows: int = 1 << 18
    noise_block_rows: int = 1024
    #: the fit's columns (u, v, the lever arm's and the delay's regressors) are built again for the fast band
    #: where one set holds at least this many bytes (:func:`_columns_again`: 4 h of 200 Hz accelerometers are
    #: 415 MB a set, and a second set beside the first took the 4 h pair past 2 GB); below, a copy of the
    #: first is kept for it (the same numbers: building them again cost 1.3 s of the 1 h pair's 6 s fit)
    rebuild_min_bytes: float = 150e6
    gap_steps: float = 3.0  # a step of a unit's stamps beyond this many of its median steps is a gap (not bridged)
    consistency_z: float = 3.0  # beyond this many combined sigmas the two views disagree
    #: a disagreement up to this many combined sigmas is said to be marginal, its causes possible rather than
    #: likely: pairs whose triads are one rotation reach it now and then (2 of 72 random simulated pairs, at
    #: z 3.0 and 3.3: the tails of the accelerometer triad's sigma, 96 % within 2 sigma in the benchmarks)
    consistency_marginal_z: float = 4.0
    #: ... the combined sigma taken as at least this (deg): a log against itself agrees to 1e-4 deg, which is
    #: no disagreement however small its sigma (interpolation between the two units' stamps)
    consistency_floor_deg: float = 0.005
    #: the lever arms of the transfer alignment and of the accelerometer triad compared with the combined sigma
    #: taken as at least this (m): two estimates of one offset from different signals (velocity against specific
    #: force) each carry model errors of a centimetre or so (the IMUs' sensing points, the strapdown's
    #: integration), which their sigmas do not count
    consistency_lever_floor_m: float = 0.02
    band_split_s: float = 0.4  # the slow and the fast part of the motion split at this period (moving mean)
    band_z: float = 3.0  # the two bands' rotations further apart than this many combined sigmas: not one rotation
    #: a band's rotation is determined only where the master's (fitted) and the slave's series share motion
    #: along two directions at least: their second canonical correlation, Fisher-transformed, at least this
    #: many of its standard errors under independence (1 / sqrt(samples / correlation time - 3)); a 3x3 of
    #: independent noises reaches 4 about once in a hundred. The fits' sigmas cannot judge that: they take
    #: the master's noise from its third differences, and an IMU's noise coloured by its own filter is larger
    #: in a band than they say (an aircraft's fast band, its common motion the vertical only, came out 130 deg
    #: from the slow band at a sigma of 1-3 deg; the triad was then called "not one rotation", its sigma
    #: inflated to 45-75 deg)
    band_min_canonical_z: float = 5.0
    lever_min_rate_rad_s: float = 0.3  # the accelerometers' lever arm is estimated where the rates move this (rms)
    #: ... or where a lever arm of lever_plausible_m would move the specific force by lever_min_effect of its
    #: moving part (rms): a ship's sway at 0.1 rad/s, a 1.5 m lever arm, was 2-3 deg off without it
    #: (benchmarks/bench_alignment_random.py --real-errors)
    lever_plausible_m: float = 2.0
    lever_min_effect: float = 0.01
    #: the lever arm's regressors (the master's angular rate and its derivative) carry the master gyro's white
    #: noise, differentiated (0.6 rad/s^2 a sample for a MEMS gyro at 400 Hz): their moment sum K^T K counts it
    #: as motion and shortens the lever arm (errors in variables), and with a vibrating mount the rotation
    #: takes up what the short lever arm leaves (a 1.5 m lever arm 2 % short turned an accelerometer triad
    #: 0.3 deg at sigma 0.02). That noise's moment, simulated through the same derivative, interpolation and
    #: filters (:func:`_regressor_noise_cov`), is taken out of K^T K, where that leaves every direction of the
    #: lever arm's regressors at least this fraction of its power (else the noise estimate would decide the lever
    #: arm: left as it is)
    regressor_noise_max_frac: float = 0.5
    #: ... and where some direction keeps less than this fraction, the lever arm is reported as not determined
    #: (its regressors are mostly noise there: a quiet vehicle's; the fit's lever arm tends to zero at a sigma
    #: that does not know it)
    lever_noise_undetermined_frac: float = 0.5
    #: ... unless a low-pass of every series of the fit brings it there: the cutoff halved from an eighth of the
    #: rate down to this (Hz; a vehicle's manoeuvres are slower than a hertz only at sea), Butterworth of this
    #: order, zero-phase (:func:`_lever_band`)
    lever_lowpass_min_hz: float = 0.5
    lever_lowpass_order: int = 4
    #: the angular acceleration of the lever arm's regressors by the five-point difference (5; 3: the
    #: three-point one, which keeps 0.987 of an 18 Hz vibration's derivative at 400 Hz and 0.76 of a 20 Hz one
    #: at 100 Hz: the lever arm then comes out that much too long; benchmarks/bench_imu_to_imu_vibration.py)
    lever_derivative_points: int = 5
    #: ... and the rates and angular acceleration interpolated onto the common stamps by four points (4; 2:
    #: linearly, which keeps 0.951 of a 20 Hz vibration half-way between 200 Hz samples: the lever arm came out
    #: 4.5 % long on a 100 Hz slave). The gyro noise this carries more of is taken out with the rest
    #: (regressor_noise_max_frac); the specific forces stay linear (their noise is not taken out of the fit)
    lever_interp_points: int = 4
    #: the gimbal lock (pitch +-90 deg, where the roll and yaw axes coincide): a rotation whose pitch is within
    #: this many of its sigmas of +-90 deg (or within gimbal_snap_min_deg, rounding) is reported as the
    #: canonical triple (roll 0, yaw the two's sum, scipy's as_euler) with the rotation's sigmas (see
    #: :func:`euler_with_sigma`): there the data cannot tell on which side of the lock, nor how far, the
    #: rotation is, and the Euler roll and yaw apart are not determined (a 0/90/0 gyro triad: sigma 46 deg,
    #: refused, while the rotation was right to 0.0003 deg). 3: the snap moves the triple by at most 3 sigma
    #: (added to the pitch's sigma), and outside the band roll and yaw apart keep Euler sigmas below 1/3 rad
    gimbal_snap_sigmas: float = 3.0
    gimbal_snap_min_deg: float = 1e-7  # euler_from_dcm's roll and yaw there are atan2 of rounding errors
    #: ... two triples compared (the consistency, the two bands) where one is that canonical triple and the
    #: other, less noisy, was not snapped: within this of the same lock the other's roll and yaw are written
    #: the canonical way too (_one_convention), else their Euler roll and yaw (each anything, only their sum
    #: determined) would differ by tens of degrees from the same rotation. 10 deg: beyond it a pitch
    #: difference that large is itself a disagreement (the pitch is compared as it is)
    gimbal_compare_deg: float = 10.0


DEFAULT = ImuToImuConfig()


@dataclass(frozen=True)
class TriadRotation:
    """One triad's rotation (slave relative to master) with its 1-sigma from the data."""

    rpy_deg: tuple[float, float, float]
    sigma_deg: tuple[float, float, float]
    n: int  # common samples used
    residual_rms: float  # of the fit, in the triad's units (rad/s or m/s^2)
    corr_time_s: float  # the scores' integrated correlation time (what inflated the white sigma)
    lever_arm_m: tuple[float, float, float] | None = None  # accelerometers: the offset estimated with it
    delay_s: float | None = None  # the delay left between the two units' samples, estimated with it
    #: the rotation fitted on the slow (periods > band_split_s) and on the fast part of the motion apart, and
    #: the largest z between them (beyond the config's band_z: the triads differ by more than a rotation)
    band_rpy_deg: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    band_z: float | None = None
    sigma_data_deg: tuple[float, float, float] | None = None  # the sigma from the residuals alone, where the
    # bands disagreed and half their spread was added to ``sigma_deg``
    rigid: bool | None = None  # one rotation at every frequency (band_z within the config's limit); None: not checked
    band_unchecked: str | None = None  # why the band check was not made (a band's rotation not determined)
    #: the rotation itself (body master -> slave, v_slave = R v_master, as conventions.quat_from_dcm): exact
    #: where ``rpy_deg`` is the canonical triple at the gimbal lock (``gimbal``)
    quat_wxyz: tuple[float, float, float, float] | None = None
    gimbal: bool = False  # rpy_deg is the canonical triple at the gimbal lock (roll 0, yaw the two's sum)
    lever_arm_sigma_m: tuple[float, float, float] | None = None  # lever_arm_m's 1-sigma from the data
    #: the low-pass every series of the fit went through (Hz), where the lever arm's regressors were mostly noise
    #: over the whole band (a quiet vehicle: :func:`_lever_band`); None: the whole band
    lowpass_hz: float | None = None


@dataclass(frozen=True)
class ImuToImu:
    gyro: TriadRotation | None
    accel: TriadRotation | None
    reasons: dict[str, str] = field(default_factory=dict)  # triad -> why it is not measured

    def section(self) -> dict:
        """The report.json form (DESIGN.md: ``alignment.imu_to_imu``)."""
        out: dict = {}
        for name, tr in (("gyro", self.gyro), ("accel", self.accel)):
            out[f"{name}_rpy_deg"] = list(tr.rpy_deg) if tr else None
            out[f"{name}_sigma_deg"] = list(tr.sigma_deg) if tr else None
            if tr:
                if tr.quat_wxyz is not None:
                    out[f"{name}_quat_wxyz"] = list(tr.quat_wxyz)
                if tr.gimbal:
                    out[f"{name}_gimbal_lock"] = True
                out[f"{name}_residual_rms"] = tr.residual_rms
                out[f"{name}_corr_time_s"] = tr.corr_time_s
                out[f"{name}_samples"] = tr.n
                out[f"{name}_delay_s"] = tr.delay_s
                if tr.band_z is not None:
                    out[f"{name}_band_z"] = tr.band_z
                    out[f"{name}_band_rpy_deg"] = {"slow": list(tr.band_rpy_deg[0]), "fast": list(tr.band_rpy_deg[1])}
                if tr.band_unchecked is not None:
                    out[f"{name}_band_unchecked"] = tr.band_unchecked
                if tr.sigma_data_deg is not None:
                    out[f"{name}_sigma_data_deg"] = list(tr.sigma_data_deg)
                if tr.lowpass_hz is not None:
                    out[f"{name}_lowpass_hz"] = tr.lowpass_hz
        if self.accel and self.accel.lever_arm_m is not None:
            out["accel_lever_arm_m"] = list(self.accel.lever_arm_m)
            if self.accel.lever_arm_sigma_m is not None:
                out["accel_lever_arm_sigma_m"] = [float(x) if np.isfinite(x) else None for x in self.accel.lever_arm_sigma_m]
        if self.reasons:
            out["reasons"] = dict(self.reasons)
        return out


# ---- common samples --------------------------------------------------------------------------------
def finite_increasing(t: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t, y (n, k)) without the rows whose stamp or values are not finite, sorted by time (stable), the first
    of each repeated stamp kept: strictly increasing stamps, for interpolation."""
    ok = np.isfinite(t) & np.isfinite(y).all(1)
    if ok.all() and (len(t) < 2 or bool(np.all(t[1:] > t[:-1]))):  # (the usual log: copies, nothing to sort)
        return t.copy(), y.copy()
    t, y = t[ok], y[ok]
    order = np.argsort(t, kind="stable")
    t, y = t[order], y[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
    return t[keep], y[keep]


def _interp_at(t: np.ndarray, tp: np.ndarray, yp: np.ndarray, gap_steps: float, points: int = 2,
               step: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """yp (n, k) at t, linearly, or with ``points`` 4 by the four-point (cubic Lagrange) interpolation on tp's
    own stamps (linear where the four samples would straddle a gap or an end); and the mask of t inside tp's
    span (its first and last stamps included) and not inside a gap of tp (a t on a sample of tp is that
    sample: inside). Half-way between two samples a vibration at a tenth of the rate keeps 0.951 of its
    amplitude linearly, 0.996 with four points. Each row of the answer depends on its own t alone (blocks of
    t give the same rows); ``step``: tp's median step where already known (``median_step_s(tp)``)."""
    step = median_step_s(tp, default=np.inf) if step is None else step
    jj = np.clip(np.searchsorted(tp, t, side="right"), 1, len(tp) - 1)  # t in [tp[jj-1], tp[jj]]
    inside = (t >= tp[0]) & (t <= tp[-1])
    inside &= ((tp[jj] - tp[jj - 1]) <= gap_steps * step) | (t == tp[jj - 1]) | (t == tp[jj])
    y = np.stack([np.interp(t, tp, yp[:, i]) for i in range(yp.shape[1])], -1)
    if points != 4 or len(tp) < 4:
        return y, inside
    i1 = jj - 1  # the samples i1 - 1 .. i1 + 2 around t
    idx = np.flatnonzero((i1 >= 1) & (i1 + 2 < len(tp)) & (t > tp[0]) & (t < tp[-1]))
    a = i1[idx]
    lim = gap_steps * step
    near = (tp[a] - tp[a - 1] <= lim) & (tp[a + 1] - tp[a] <= lim) & (tp[a + 2] - tp[a + 1] <= lim)
    idx, a = idx[near], a[near]
    if jit.compiled():  # one pass, the same arithmetic (tests/test_imu_to_imu.py)
        _lagrange4_kernel(t, tp, yp, idx, a, y)
        return y, inside
    for lo in range(0, len(idx), BLOCK_ROWS):  # row by row arithmetic: the blocks bound the temporaries
        ii, aa = idx[lo:lo + BLOCK_ROWS], a[lo:lo + BLOCK_ROWS]
        x = t[ii]
        nodes = [tp[aa + d] for d in (-1, 0, 1, 2)]
        acc = np.zeros((len(ii), yp.shape[1]))
        for jn in range(4):
            wgt = np.ones(len(ii))
            for mn in range(4):
                if mn != jn:
                    wgt *= (x - nodes[mn]) / (nodes[jn] - nodes[mn])
            acc += wgt[:, None] * yp[aa + jn - 1]
        y[ii] = acc
    return y, inside


@jit.njit
def _lagrange4_kernel(t, tp, yp, idx, a, y):  # pragma: no cover - compiled (_interp_at's numpy arithmetic)
    for q in range(idx.shape[0]):
        i, aa = idx[q], a[q]
        x = t[i]
        for c in range(yp.shape[1]):
            acc = 0.0
            for jn in range(4):
                wgt = 1.0
                for mn in range(4):
                    if mn != jn:
                        wgt *= (x - tp[aa + mn - 1]) / (tp[aa + jn - 1] - tp[aa + mn - 1])
                acc += wgt * yp[aa + jn - 1, c]
            y[i, c] = acc


def _highpass(y: np.ndarray, n_win: int, out: np.ndarray | None = None) -> np.ndarray:
    """y minus its centred moving mean over n_win samples (shorter at the ends), per column; into ``out``
    when given (``y`` itself allowed: a column's running sum is taken before any of it is written)."""
    n = len(y)
    h = max(n_win // 2, 1)
    out = np.empty(y.shape) if out is None else out
    if jit.compiled():  # one pass over the rows, the same arithmetic (tests/test_imu_to_imu.py)
        _highpass_kernel(y, h, out)
        return out
    for j in range(y.shape[1]):  # column by column (one column's running sum at a time: 4 h of the
        c = np.concatenate([[0.0], np.cumsum(y[:, j])])  # accelerometers' 12 regressors are 280 MB a copy)
        for a in range(0, n, BLOCK_ROWS):  # row by row arithmetic: blocks only bound the temporaries
            r = np.arange(a, min(n, a + BLOCK_ROWS))
            i0 = np.clip(r - h, 0, n)
            i1 = np.clip(r + h + 1, 0, n)
            out[a:a + len(r), j] = y[a:a + len(r), j] - (c[i1] - c[i0]) / (i1 - i0)
    return out


@jit.njit
def _highpass_kernel(y, h, out):  # pragma: no cover - compiled (_highpass's numpy arithmetic, same order)
    # every column's running sum c (np.cumsum: element after element) read at i1 = r + h + 1 and at
    # i0 = r - h (clipped) as two running sums, each advanced one element at a time, so no (n + 1, k) array
    # of them: c[i1] - c[i0] holds the same numbers. The rows i0 reads again are kept in a ring of h + 2
    # (``out`` may be ``y``: a row is overwritten once read into the ring)
    n, k = y.shape
    ring_n = h + 2
    ring = np.empty((ring_n, k))
    hi, lo = np.zeros(k), np.zeros(k)
    i_hi, i_lo = 0, 0  # hi = c[i_hi], lo = c[i_lo]
    for r in range(n):
        i0 = min(max(r - h, 0), n)
        i1 = min(max(r + h + 1, 0), n)
        while i_hi < i1:
            for j in range(k):
                hi[j] += y[i_hi, j]
            i_hi += 1
        while i_lo < i0:
            for j in range(k):
                lo[j] += ring[i_lo % ring_n, j]
            i_lo += 1
        for j in range(k):
            ring[r % ring_n, j] = y[r, j]
            out[r, j] = y[r, j] - (hi[j] - lo[j]) / (i1 - i0)


def _common(t_m: np.ndarray, y_m: np.ndarray, t_s: np.ndarray, y_s: np.ndarray, gap_steps: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(t, master, slave) on the sparser unit's stamps inside both spans, the other interpolated."""
    if len(t_m) < 2 or len(t_s) < 2:
        return None
    lo, hi = max(t_m[0], t_s[0]), min(t_m[-1], t_s[-1])
    if median_step_s(t_m) >= median_step_s(t_s):
        t = t_m[(t_m >= lo) & (t_m <= hi)]
        ym = y_m[(t_m >= lo) & (t_m <= hi)]
        ys, ok = _interp_at(t, t_s, y_s, gap_steps)
    else:
        t = t_s[(t_s >= lo) & (t_s <= hi)]
        ys = y_s[(t_s >= lo) & (t_s <= hi)]
        ym, ok = _interp_at(t, t_m, y_m, gap_steps)
    return t[ok], ym[ok], ys[ok]


#: :func:`_one_triad`'s answer where the two units have too few common samples (no retry helps)
TOO_FEW_COMMON = "too few common IMU samples of the two units"

# ---- the estimate ----------------------------------------------------------------------------------
#: lags of the scores' autocorrelation taken one by one while looking for its first zero crossing; a
#: longer correlation goes the FFT way (:func:`_corr_time_fft`), which costs about what 30-60 lags do (1 h of
#: 200 Hz: 0.15 s against 0.5-1.1 ms a lag; the same sums: the estimates agree to 1e-15)
DIRECT_LAGS = 32


def _bartlett_lags(n: int, tau: float) -> int:
    nw = 4.0 * (n / 100.0) ** (2.0 / 9.0)
    return int(min(max(np.ceil(nw), np.ceil(5.0 * tau)), n // 3))


def _moving_sum(x: np.ndarray, w: int) -> np.ndarray:
    """The full convolution of the series x (n,) with a box of w ones (n + w - 1 values)."""
    c = np.cumsum(np.concatenate([np.zeros(w), x, np.zeros(w - 1)]))
    return c[w:] - c[:len(x) + w - 1]


def _long_run_cov(s: np.ndarray, overwrite: bool = False) -> tuple[np.ndarray, float]:
    """Newey-West (Bartlett) long-run covariance of the score series s (n, p) summed over n; and the
    scores' integrated correlation time in samples (1 + 2 sum rho up to its first zero crossing).

    The autocorrelation is taken lag by lag up to its first zero crossing (by FFT where that is beyond
    DIRECT_LAGS samples: :func:`_corr_time_fft`), and the Bartlett sum
    sum_{|j| <= L} (1 - |j|/(L+1)) Gamma_j as s^T (T s) / (L+1), T s the scores convolved with the
    triangle L+1-|j| = two boxes of L+1 samples (moving sums): O(n p^2) whatever L.
    ``overwrite``: s (C-contiguous) may be centred in place (no copy of a million rows)."""
    n = len(s)
    if overwrite and s.flags.c_contiguous and s.flags.writeable:
        s -= s.mean(axis=0)
    else:
        s = s - s.mean(axis=0)
    flat = np.ascontiguousarray(s).ravel()  # rows back to back: lag j is an offset of j * p
    tot = float(np.dot(flat, flat))  # (no squared copy: 4 h of 200 Hz scores are 161 MB)
    if tot <= 0:
        return np.zeros((s.shape[1], s.shape[1])), 1.0
    rho, crossed = [], False
    p = s.shape[1]
    for j in range(1, min(DIRECT_LAGS, n - 1) + 1):
        a = float(np.dot(flat[:-j * p], flat[j * p:])) / tot
        if a <= 0:
            crossed = True
            break
        rho.append(a)
    tau = max(1.0 + 2.0 * float(np.sum(rho)), 1.0) if crossed else _corr_time_fft(s, tot)
    L = _bartlett_lags(n, tau)
    om = np.empty((p, p))
    for c in range(p):  # column by column: a few series of n values at a time (4 h of 200 Hz: 23 MB each)
        tri = _moving_sum(_moving_sum(s[:, c], L + 1), L + 1)[L:L + n]  # (T s)_k = sum_j (L+1-|j|) s_{k+j}
        om[:, c] = s.T @ tri
    om /= L + 1.0
    return 0.5 * (om + om.T), tau


def _corr_time_fft(s: np.ndarray, tot: float) -> float:
    """:func:`_long_run_cov`'s correlation time of centred scores correlated over many samples: their
    summed autocorrelation (up to its first zero crossing) from the power spectra, zero padded to at least
    2n (no wrap-around), one column's spectrum at a time (4 h of 200 Hz: 46 MB, not p of them)."""
    n = len(s)
    nfft = sfft.next_fast_len(2 * n, real=True)
    power = np.zeros(nfft // 2 + 1)
    for j in range(s.shape[1]):
        f = dsp.rfft(s[:, j], nfft)
        power += f.real ** 2
        power += f.imag ** 2
    del f
    ac = dsp.irfft(power, nfft)[:n] / tot
    del power
    neg = np.nonzero(ac[1:] <= 0)[0]
    m = int(neg[0]) if len(neg) else n - 1
    return max(1.0 + 2.0 * float(np.sum(ac[1:m + 1])), 1.0)


def _euler_sigma_deg(r: np.ndarray, cov_rad2: np.ndarray) -> np.ndarray:
    """1-sigma of euler(exp([d x]) R) (deg) for d with covariance cov (rad^2), central differences."""
    jac = np.zeros((3, 3))
    e = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = e
        diff = euler_from_dcm(dcm_from_rotvec(d) @ r) - euler_from_dcm(dcm_from_rotvec(-d) @ r)
        jac[:, i] = ((diff + np.pi) % (2 * np.pi) - np.pi) / (2 * e)
    return np.degrees(np.sqrt(np.maximum(np.diag(jac @ cov_rad2 @ jac.T), 0.0)))


# ---- Euler angles of a rotation and their sigmas, the gimbal lock included -------------------------------
def euler_axes(rpy_rad: np.ndarray) -> np.ndarray:
    """The unit axes (columns roll, pitch, yaw; batched) each Euler angle of R = Rz(yaw) Ry(pitch) Rx(roll)
    turns R about, in the frame of the left perturbation R = exp([d x]) R_hat (the slave's: the fits' and
    the filter's covariances are of that d): dR = [w_i x] R d(angle_i). Defined everywhere; at pitch +-90
    deg the roll and the yaw axis coincide (the gimbal lock)."""
    rpy = np.asarray(rpy_rad, dtype=float)
    _, p, y = np.moveaxis(rpy, -1, 0)
    w = np.zeros(rpy.shape[:-1] + (3, 3))
    w[..., 0, 0], w[..., 1, 0], w[..., 2, 0] = np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), -np.sin(p)
    w[..., 0, 1], w[..., 1, 1] = -np.sin(y), np.cos(y)
    w[..., 2, 2] = 1.0
    return w


def axis_sigmas(rpy_rad: np.ndarray, cov_rad2: np.ndarray) -> np.ndarray:
    """The rotation's 1-sigma (rad) about each Euler angle's own axis (:func:`euler_axes`), from the 3x3
    covariance of the perturbation d (batched: cov (..., 3, 3)): what the data determine of each angle's
    turn, well defined at the gimbal lock too (where the Euler angles' own sigmas are not)."""
    w = euler_axes(rpy_rad)
    return np.sqrt(np.maximum(np.einsum("...ji,...jk,...ki->...i", w, np.asarray(cov_rad2, float), w), 0.0))


def gimbal_canonical(r: np.ndarray, cov_rad2: np.ndarray, snap_sigmas: float, snap_min_rad: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rotation(s) r (..., 3, 3) at the gimbal lock: (snap, rpy, sigma, delta), batched.

    ``delta`` (rad) is 90 deg - |pitch|; ``snap`` where it is within ``snap_sigmas`` of the rotation's sigma
    off the lock (or within ``snap_min_rad``). There R's first column (the master's x axis) is near the
    slave's z axis; a perturbation about the slave's x or y axis moves it off by |d| whichever way, one about
    z turns roll and yaw together. ``rpy`` is the canonical triple there (scipy's ``as_euler("ZYX")`` at the
    lock: roll 0, pitch +-90 deg, yaw = atan2(-R01, R11), their sum or difference); ``sigma`` its sigmas:
    roll and yaw the rotation's about the shared axis (z; each with the other at its value), pitch the
    rms of the two off-lock axes' with ``delta`` (how far the snap moved the triple) added."""
    r = np.asarray(r, dtype=float)
    cov = np.asarray(cov_rad2, dtype=float)
    m20 = r[..., 2, 0]
    delta = np.arctan2(np.hypot(r[..., 0, 0], r[..., 1, 0]), np.abs(m20))  # cos(pitch) over |sin(pitch)|
    s_off2 = np.maximum(cov[..., 0, 0] + cov[..., 1, 1], 0.0)
    snap = delta <= np.maximum(snap_sigmas * np.sqrt(s_off2), snap_min_rad)
    yaw = np.arctan2(-r[..., 0, 1], r[..., 1, 1])
    rpy = np.stack([np.zeros_like(yaw), np.where(m20 < 0, 0.5 * np.pi, -0.5 * np.pi), yaw], axis=-1)
    s_z = np.sqrt(np.maximum(cov[..., 2, 2], 0.0))
    sig = np.stack([s_z, np.sqrt(s_off2 + delta ** 2), s_z], axis=-1)
    return snap, rpy, sig, delta


def euler_with_sigma(r: np.ndarray, cov_rad2: np.ndarray, snap_sigmas: float, snap_min_rad: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """One rotation's reported Euler angles, their sigmas, the rotation's sigma about each angle's axis
    (:func:`axis_sigmas`: what judges whether it is determined), all in degrees, and whether the triple is
    the canonical one at the gimbal lock (:func:`gimbal_canonical`). Away from the lock the angles are
    ``euler_from_dcm`` and the sigmas the Euler angles' own (the Jacobian's), as they always were."""
    snap, rpy_c, sig_c, _ = gimbal_canonical(r, cov_rad2, snap_sigmas, snap_min_rad)
    if bool(snap):
        return np.degrees(rpy_c), np.degrees(sig_c), np.degrees(axis_sigmas(rpy_c, cov_rad2)), True
    rpy = euler_from_dcm(r)
    return np.degrees(rpy), _euler_sigma_deg(r, cov_rad2), np.degrees(axis_sigmas(rpy, cov_rad2)), False


class _Moments:
    """The sums the Gauss-Newton steps of :func:`fit_rotation` need, taken once over the samples: with
    w = u + K r and p = R w, every sum of the normal equations (sum p p^T, sum p x e, sum p x (R K),
    sum (R K)^T e) is R times a combination of sum u u^T, sum u v^T, sum K (x) u, sum K (x) v and
    sum K (x) K (R a x R b = R (a x b)), so an iteration costs O(1) instead of passes over a million
    samples (the same numbers up to the order of the additions)."""

    def __init__(self, u: np.ndarray, v: np.ndarray, k: np.ndarray | None):
        self.uu, self.uv = u.T @ u, u.T @ v
        self.m = 0 if k is None else k.shape[2]
        if k is not None:
            kf = k.reshape(len(k), 3 * self.m)  # column (i, l) = K[:, i, l]
            self.ku = (kf.T @ u).reshape(3, self.m, 3)  # [i, l, j] = sum K[i, l] u[j]
            self.kv = (kf.T @ v).reshape(3, self.m, 3)
            self.kk = (kf.T @ kf).reshape(3, self.m, 3, self.m)  # [i, l, j, q] = sum K[i, l] K[j, q]
            self.ktk = np.einsum("iliq->lq", self.kk)

    def kept_fraction(self, noise_kk: np.ndarray) -> float:
        """:func:`_kept_fraction` of sum K (x) K with ``noise_kk`` ((3 m, 3 m), the regressors' columns as
        ``k.reshape(n, 3 m)``: the sum of their noise's moments); -inf without regressors."""
        if self.m == 0:
            return -np.inf
        return _kept_fraction(self.kk.reshape(3 * self.m, 3 * self.m), noise_kk)

    def without_regressor_noise(self, noise_kk: np.ndarray) -> None:
        """``noise_kk`` (:meth:`kept_fraction`) taken out of sum K (x) K."""
        self.kk = (self.kk.reshape(3 * self.m, 3 * self.m) - noise_kk).reshape(3, self.m, 3, self.m)
        self.ktk = np.einsum("iliq->lq", self.kk)

    def normal_equations(self, r_mat: np.ndarray, lev: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        ww, wv = self.uu, self.uv
        if lev is not None:
            kur = np.einsum("ilj,l->ij", self.ku, lev)  # sum (K r) u^T
            ww = ww + kur + kur.T + np.einsum("iljq,l,q->ij", self.kk, lev, lev)
            wv = wv + np.einsum("ilj,l->ij", self.kv, lev)
        m2 = r_mat @ ww @ r_mat.T  # sum p p^T
        a = np.trace(m2) * np.eye(3) - m2
        mm = r_mat @ wv  # sum p v^T; sum p x e = sum p x v
        rot = np.array([mm[1, 2] - mm[2, 1], mm[2, 0] - mm[0, 2], mm[0, 1] - mm[1, 0]])
        if lev is None:
            return a, rot
        t = self.ku + np.einsum("jqkl,q->klj", self.kk, lev)  # [k, l, j] = sum K[k, l] w[j]
        c = np.stack([t[2, :, 1] - t[1, :, 2], t[0, :, 2] - t[2, :, 0], t[1, :, 0] - t[0, :, 1]])  # sum w x K
        b = r_mat @ c
        kv_r = np.einsum("ji,ilj->l", r_mat, self.kv)  # sum K^T R^T v
        kw = np.einsum("ili->l", self.ku) + self.ktk @ lev  # sum K^T w
        jtj = np.block([[a, b], [b.T, self.ktk]])
        return jtj, np.concatenate([rot, kv_r - kw])


def _residual(u_m: np.ndarray, v_s: np.ndarray, r_mat: np.ndarray, k_lever: np.ndarray | None,
              lev: np.ndarray | None) -> np.ndarray:
    if lev is None:
        e = u_m @ r_mat.T
    else:  # (u + K r) R^T, the sum written over the einsum's own array
        um = np.einsum("kij,j->ki", k_lever, lev)
        np.add(u_m, um, out=um)
        e = um @ r_mat.T
        del um
    return np.subtract(v_s, e, out=e)


def _cost(u_m: np.ndarray, v_s: np.ndarray, r_mat: np.ndarray, k_lever: np.ndarray | None,
          lev: np.ndarray | None) -> float:
    """sum |v - R (u + K r)|^2, block by block (no whole residual: 4 h of 200 Hz are 69 MB of it)."""
    tot = 0.0
    for a in range(0, len(u_m), BLOCK_ROWS):
        b = slice(a, a + BLOCK_ROWS)
        e = _residual(u_m[b], v_s[b], r_mat, None if k_lever is None else k_lever[b], lev)
        tot += float(np.einsum("ij,ij->", e, e))
    return tot


def _white_noise_var(x: np.ndarray, cfg: ImuToImuConfig = DEFAULT) -> np.ndarray:
    """Each column's white-noise variance (n, k) -> (k,), from its third differences (the motion, smooth at
    the IMU's rate, cancels; 20 = 1 + 9 + 9 + 1 for white noise), robust (MAD); a long series in blocks
    spread over it (cfg.noise_rows at most). Zeros for fewer than 8 rows."""
    n = len(x)
    if n < 8:
        return np.zeros(x.shape[1])
    blk = cfg.noise_block_rows
    if n <= cfg.noise_rows:
        d3 = np.diff(x, n=3, axis=0)
    else:
        starts = np.linspace(0, n - blk, cfg.noise_rows // blk).astype(int)
        d3 = np.concatenate([np.diff(x[a:a + blk], n=3, axis=0) for a in starts])
    return dsp.mad_sigma(d3) ** 2 / 20.0


def _noise_floor_var(x: np.ndarray, seg: int = 1024, band: tuple[float, float] = (0.25, 0.5),
                     with_rel_sd: bool = False):
    """Each column's white-noise variance (n, k) -> (k,) from the floor of its spectrum: the median over the
    upper part of the band (``band``, fractions of the sampling rate, Nyquist's own bin left out) of Welch's
    periodogram (:func:`logtools.dsp.welch_psd`, segments of ``seg`` rows), a white noise's one-sided density
    being twice its variance per unit rate. A vibration is a few lines there and does not move the median;
    third differences (:func:`_white_noise_var`) keep (2 sin(pi f / fs))^3 of it, and a rigid-body vibration
    at a tenth of the rate read as gyro noise over-corrected the lever arm's regressors. ``with_rel_sd``: also
    its relative 1-sigma (the median of B bins each averaged over S segments: 1.2533 / sqrt(B S))."""
    from logtools.dsp import welch_psd

    n = len(x)
    seg = int(min(seg, n))
    if seg < 16:
        return (np.zeros(x.shape[1]), 1.0) if with_rel_sd else np.zeros(x.shape[1])
    f, psd = welch_psd(x, 1.0, seg)
    sel = (f >= band[0]) & (f < band[1])
    var = 0.5 * np.median(psd[sel], axis=0)
    n_seg = (n - seg) // (seg - seg // 2) + 1
    return (var, 1.2533 / np.sqrt(max(int(sel.sum()) * n_seg, 1))) if with_rel_sd else var


def _gauss_newton(mom: _Moments, r_mat: np.ndarray, lev: np.ndarray | None, iterations: int
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Gauss-Newton steps of :func:`fit_rotation` on the moments from (r_mat, lev)."""
    for _ in range(iterations):
        jtj, rhs = mom.normal_equations(r_mat, lev)
        x = np.linalg.solve(jtj, rhs)
        r_mat = dcm_from_rotvec(x[:3]) @ r_mat
        if lev is not None:
            lev = lev + x[3:]
        if np.linalg.norm(x[:3]) < 1e-12:
            break
    return r_mat, lev


def fit_rotation(u_m: np.ndarray, v_s: np.ndarray, k_lever: np.ndarray | None = None, *, dt_s: float = 1.0,
                 iterations: int = 5, starts: tuple[np.ndarray, ...] = (), k_noise_cov: np.ndarray | None = None,
                 k_noise_keep_frac: float = DEFAULT.regressor_noise_max_frac, k_noise_rel_sd: float = 0.0,
                 k_noise_undetermined_frac: float = DEFAULT.lever_noise_undetermined_frac,
                 u_noise_var: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, float, float, float]:
    """R (and nuisance parameters r with regressors ``k_lever`` (n, 3, m): a lever arm, a residual delay)
    minimising sum |v_s - R (u_m + K r)|^2, by Gauss-Newton from the Wahba solution and from each of
    ``starts`` (rotations), the smallest residual kept.

    Returns (R, cov of the slave-side rotation perturbation (rad^2, 3x3), r or None, cov of r or None,
    residual rms, the scores' correlation time in seconds (``dt_s`` per sample), and the mean square of the
    regressors' own noise in that residual where it was taken out, else 0). The covariance's information
    counts the master's motion without its white noise (:func:`_white_noise_var`); a direction with none
    beyond it has an infinite covariance (not determined). ``k_noise_cov``: the per-sample covariance of the
    regressors' own noise ((3 m, 3 m), as ``k_lever.reshape(n, 3 m)``), taken out of their moments (errors in
    variables: the estimate and its sigma; see ``ImuToImuConfig.regressor_noise_max_frac``), known to
    ``k_noise_rel_sd`` (relative 1-sigma), which the rotation's covariance counts. ``u_noise_var``: the variance
    of u_m's noise per column where u_m's third differences do not give it (a low-passed u_m)."""
    n = len(u_m)
    p = 3 if k_lever is None else 3 + k_lever.shape[2]
    best = None
    mom = _Moments(u_m, v_s, k_lever)
    # the regressors' motion beyond their noise in their weakest direction: their noise taken out where that
    # leaves it k_noise_keep_frac; below k_noise_undetermined_frac the lever arm is not determined (below)
    kept = mom.kept_fraction(n * k_noise_cov) if k_noise_cov is not None and k_lever is not None else np.inf
    noise_dominates = not kept >= k_noise_undetermined_frac
    noise_out = k_noise_cov is not None and k_lever is not None and kept >= k_noise_keep_frac
    if noise_out:
        mom.without_regressor_noise(n * k_noise_cov)
    for r_mat in (wahba(v_s.T @ u_m)[0], *starts):
        lev = np.zeros(k_lever.shape[2]) if k_lever is not None else None
        r_mat, lev = _gauss_newton(mom, r_mat, lev, iterations)
        cost = _cost(u_m, v_s, r_mat, k_lever, lev)
        if best is None or cost < best[0]:
            best = (cost, r_mat, lev)
    _, r_mat, lev = best
    # the noise correction's own uncertainty (its variance known to k_noise_rel_sd): the rotation refitted with
    # the noise taken out 1 sigma more and 1 sigma less; half the difference joins the rotation's covariance
    # (where the lever arm's signal dominates the slave's specific force, the rotation rests on the correction)
    d_noise = np.zeros(3)
    if noise_out and k_noise_rel_sd > 0:
        sols = []
        for sgn in (1.0, -1.0):
            mp = copy.copy(mom)
            mp.kk = mom.kk - sgn * k_noise_rel_sd * (n * np.asarray(k_noise_cov)).reshape(mom.kk.shape)
            mp.ktk = np.einsum("iliq->lq", mp.kk)
            sols.append(_gauss_newton(mp, r_mat, lev.copy(), iterations)[0])
        d_noise = rotvec_from_dcm(sols[0] @ sols[1].T) / 2.0
    # the sandwich's bread without the master's own white noise (errors in variables): Gauss-Newton's sum
    # p p^T counts it as motion, and where the master's signal moves along one direction only (level
    # flight's specific force: the vertical) its noise alone "determined" the rotation about that direction,
    # 0.8 deg for an accelerometer rotation 11-75 deg off (tests/test_imu_to_imu.py, the one-direction test)
    mom.uu = mom.uu - n * np.diag(_white_noise_var(u_m) if u_noise_var is None else np.asarray(u_noise_var))
    hess, _ = mom.normal_equations(r_mat, lev)
    scores = np.empty((n, p))  # per sample h^T e: p x e, and (R K)^T e = K^T (R^T e)
    ss = 0.0
    for a in range(0, n, BLOCK_ROWS):  # row by row arithmetic: the blocks bound the temporaries (the residual e
        b = slice(a, a + BLOCK_ROWS)  # among them)
        e = _residual(u_m[b], v_s[b], r_mat, None if k_lever is None else k_lever[b], lev)
        ss += float(np.einsum("ij,ij->", e, e))
        scores[b, :3] = np.cross(v_s[b] - e, e)
        if lev is not None:
            scores[b, 3:] = np.einsum("kjl,kj->kl", k_lever[b], e @ r_mat)
    rms = float(np.sqrt(ss / max(n, 1)))
    om, tau = _long_run_cov(scores, overwrite=True)
    del scores
    hess = 0.5 * (hess + hess.T)
    if np.linalg.eigvalsh(hess)[0] <= 1e-12 * max(float(np.abs(hess).max()), 1e-300):
        # the master's motion beyond its noise leaves a direction without information: not determined
        cov = np.full((p, p), np.inf)
    else:
        jinv = np.linalg.inv(hess)
        cov = jinv @ om @ jinv * (n / max(n - p, 1))
    if noise_dominates and lev is not None and len(lev) >= 3:
        # in some direction the regressors' moments are mostly their own noise (a quiet vehicle's differentiated
        # gyro noise; 97 % of them on a car without vibration): the lever arm (the first three of r) came out
        # near zero at a millimetre sigma, 1.8 m off. Not determined
        cov[np.arange(3, 6), np.arange(3, 6)] = np.inf
    # the regressors' own noise in the residual, per sample (|N r|^2: what they carry that no rotation explains)
    noise_ms = 0.0
    if noise_out and lev is not None:
        c4 = np.asarray(k_noise_cov).reshape(3, len(lev), 3, len(lev))
        noise_ms = float(sum(lev @ c4[i, :, i, :] @ lev for i in range(3)))
    return (r_mat, cov[:3, :3] + np.outer(d_noise, d_noise), lev, (cov[3:, 3:] if lev is not None else None), rms,
            tau * dt_s, noise_ms)


def _triad(u: np.ndarray, v: np.ndarray, k: np.ndarray | None, dt: float, cfg: ImuToImuConfig,
           min_explained: float | None = None, starts: tuple[np.ndarray, ...] = (),
           k_noise_cov: np.ndarray | None = None, k_noise_rel_sd: float = 0.0,
           u_noise_var: np.ndarray | None = None, min_canonical_z: float | None = None) -> TriadRotation | str:
    """One triad's rotation fitted on u (master), v (slave), k (the nuisance parameters' regressors), or why
    not. ``min_canonical_z``: a band's fit, determined only where the fitted master series and v share motion
    along two directions (:func:`_second_canonical_z`)."""
    if len(u) < cfg.min_samples:
        return f"only {len(u)} common samples (at least {cfg.min_samples} needed)"
    sv = np.linalg.svd(v.T @ u, compute_uv=False)
    if not sv[1] > 1e-6 * sv[0]:
        return "the motion is about one axis only: the rotation is not determined"
    try:
        r_mat, cov, lev, cov_lev, rms, tau_s, noise_ms = fit_rotation(
            u, v, k, dt_s=dt, starts=starts, k_noise_cov=k_noise_cov, k_noise_keep_frac=cfg.regressor_noise_max_frac,
            k_noise_rel_sd=k_noise_rel_sd, k_noise_undetermined_frac=cfg.lever_noise_undetermined_frac,
            u_noise_var=u_noise_var)
    except np.linalg.LinAlgError:
        return "the fit is singular (too little motion)"
    # (the master gyro's noise in the lever arm's regressors is no motion the rotation failed to explain)
    explained = 1.0 - max(rms ** 2 - noise_ms, 0.0) / max(float(np.mean(np.sum(v * v, axis=1))), 1e-300)
    min_explained = cfg.min_explained if min_explained is None else min_explained
    if min_canonical_z is not None:
        z2 = _second_canonical_z(u, v, k, lev, tau_s / dt)
        if not z2 >= min_canonical_z:
            return (f"the two units share motion along one direction only in this band (second canonical "
                    f"correlation {z2:.1f} standard errors, at least {min_canonical_z:g} needed)")
    if explained < min_explained:
        return (f"too little motion: the rotation explains {100 * max(explained, 0):.0f} % of the slave's "
                f"signal (at least {100 * cfg.min_explained:.0f} % needed)")
    # judged on the rotation (its sigma about each angle's axis), not on the Euler angles' sigmas: those
    # are singular at the gimbal lock (pitch +-90 deg), where the rotation is as determined as anywhere
    rpy, sig, sig_axes, gimbal = euler_with_sigma(r_mat, cov, cfg.gimbal_snap_sigmas,
                                                  np.radians(cfg.gimbal_snap_min_deg))
    if not np.all(np.isfinite(sig_axes)) or sig_axes.max() > cfg.max_sigma_deg:
        why = f"too little motion: sigma {' '.join(f'{x:.3g}' for x in sig_axes)} deg"
        # the master's moving signal beyond its own noise: along one direction only, nothing fixes the
        # rotation about it (level flight's specific force: the vertical)
        lam, vec = np.linalg.eigh(u.T @ u - len(u) * np.diag(
            _white_noise_var(u, cfg) if u_noise_var is None else np.asarray(u_noise_var)))
        if lam[2] > 0 and lam[1] <= cfg.one_direction_ratio * lam[2]:
            d = vec[:, 2] * np.sign(vec[np.argmax(np.abs(vec[:, 2])), 2])
            why += (" (the motion beyond the master's noise is along one direction only, master x/y/z "
                    f"{d[0]:+.2f}/{d[1]:+.2f}/{d[2]:+.2f}: the rotation about it is not determined)")
        return why
    lever = tuple(float(x) for x in lev[:3]) if lev is not None and len(lev) == 4 else None
    lever_sig = (tuple(float(np.sqrt(x)) for x in np.diag(cov_lev)[:3])
                 if lever is not None and cov_lev is not None else None)
    if lever_sig is not None and not np.all(np.isfinite(lever_sig)):  # (fit_rotation: not determined)
        lever = lever_sig = None
    return TriadRotation(tuple(float(x) for x in rpy), tuple(float(x) for x in sig), len(u),
                         rms, float(tau_s), lever, float(lev[-1]) if lev is not None else None,
                         quat_wxyz=tuple(float(x) for x in quat_from_dcm(r_mat)), gimbal=gimbal,
                         lever_arm_sigma_m=lever_sig)


def _second_canonical_z(u: np.ndarray, v: np.ndarray, k: np.ndarray | None, lev: np.ndarray | None,
                        tau_samples: float) -> float:
    """The second largest canonical correlation of the master's fitted series w = u + K lev (u without
    ``lev``) and the slave's v (n, 3), Fisher-transformed (atanh), in standard errors under independence
    (1 / sqrt(n / tau_samples - 3), tau_samples the fit's correlation time): how clearly they share motion
    along a second direction (a rotation needs two). 0 where either has no motion in some direction. Moments
    summed in blocks of rows (no copy of w: 4 h of 200 Hz are 69 MB a series)."""
    n = len(u)
    ww, vw = np.zeros((3, 3)), np.zeros((3, 3))
    for a in range(0, n, BLOCK_ROWS):
        b = slice(a, a + BLOCK_ROWS)
        w = u[b] if lev is None else u[b] + np.einsum("nij,j->ni", k[b], lev)
        ww += w.T @ w
        vw += v[b].T @ w

    def whitener(m: np.ndarray) -> np.ndarray | None:
        lam, vec = np.linalg.eigh(m)
        if not lam[0] > 1e-12 * max(float(lam[-1]), 1e-300):
            return None
        return vec @ np.diag(lam ** -0.5) @ vec.T

    w_w, w_v = whitener(ww), whitener(v.T @ v)
    if w_w is None or w_v is None:
        return 0.0
    rho = np.linalg.svd(w_v @ vw @ w_w, compute_uv=False)
    n_eff = n / max(float(tau_samples), 1.0)
    return float(np.arctanh(min(float(rho[1]), 1.0 - 1e-12)) * np.sqrt(max(n_eff - 3.0, 0.0)))


def _derivative(t: np.ndarray, y: np.ndarray, points: int = 5) -> np.ndarray:
    """dy/dt (n, k) by the five-point central difference on the stamps as they are (the derivative of the
    Lagrange polynomial through samples i-2..i+2: exact to the fourth degree, the fourth-order stencil on a
    uniform grid), np.gradient's second-order one at the two first and last samples. A vibration of 18 Hz
    sampled at 400 Hz keeps 0.9998 of its derivative's amplitude (the three-point difference: 0.987, and
    the lever arm came out 1.3 % long). ``points`` 3: np.gradient throughout."""
    n = len(t)
    if n < 5 or points == 3:
        return np.gradient(y, t, axis=0)
    d = np.empty(y.shape)
    d[:3], d[-3:] = np.gradient(y[:5], t[:5], axis=0)[:3], np.gradient(y[-5:], t[-5:], axis=0)[-3:]
    offs = (-2, -1, 1, 2)
    for a in range(2, n - 2, BLOCK_ROWS):  # row by row arithmetic: the blocks bound the temporaries
        b = min(a + BLOCK_ROWS, n - 2)
        dt = {k: t[a + k:b + k] - t[a:b] for k in offs}
        acc = -sum(1.0 / dt[k] for k in offs)[:, None] * y[a:b]  # the centre's weight: -sum 1 / d_m
        for k in offs:
            num = np.ones(b - a)
            den = dt[k].copy()
            for m in offs:
                if m != k:
                    num *= -dt[m]
                    den *= dt[k] - dt[m]
            acc += (num / den)[:, None] * y[a + k:b + k]
        d[a:b] = acc
    return d


def _lever_regressors(t: np.ndarray, tm: np.ndarray, gyro_m: np.ndarray, cfg: ImuToImuConfig, out: np.ndarray,
                      w: np.ndarray | None = None) -> None:
    """The lever arm's regressors at t (dw x r + w x (w x r) = K r) into ``out[:, :, :3]`` ((n, 3, >= 3)), from
    the master's gyro (tm, gyro_m): the angular acceleration differentiated on the master's own stamps, then
    interpolated (on the sparser unit's common stamps a central difference loses a vibration's amplitude,
    0.84 of it at 16 Hz on a 100 Hz grid, and the lever arm comes out that much too long, the rotation with
    it). ``w``: the rates at t, where already interpolated."""
    pts = cfg.lever_interp_points
    dg = _derivative(tm, gyro_m, cfg.lever_derivative_points)
    step = median_step_s(tm, default=np.inf)
    for a in range(0, len(t), BLOCK_ROWS):  # row by row arithmetic: the blocks bound the temporaries (4 h of
        b = slice(a, a + BLOCK_ROWS)  # 200 Hz is 207 MB for each (n, 3, 3) a whole-array expression makes,
        # 69 MB for each rate interpolated, and four times that for the interpolation's indices)
        wb = _interp_at(t[b], tm, gyro_m, cfg.gap_steps, pts, step)[0] if w is None else w[b]
        dw = _interp_at(t[b], tm, dg, cfg.gap_steps, pts, step)[0]
        out[b, :, :3] = skew(dw) + skew(wb) @ skew(wb)  # f at r = f + dw x r + w x (w x r)


def _regressor_noise_cov(parts: tuple[np.ndarray, np.ndarray, float], nwin: int, nlp: int,
                         sos: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """The per-sample covariance ((12, 12), as ``k.reshape(n, 12)``; the delay's column none) of the noise the
    master gyro's white noise puts into the lever arm's regressors, as the fits see them: the whole motion
    (high-passed over ``nwin``), its slow and its fast part (split over ``nlp``); their relative 1-sigma; and
    the per-sample moment of the regressors themselves (for :func:`_lever_kept_fraction`). From ``parts``,
    :func:`_noise_regressors`' simulation (computed once: the low-pass trials of :func:`_lever_band` share it).
    ``sos``: a zero-phase low-pass after the high-pass (:func:`_lowpassed`), as the fits then see them."""
    nf, sg, rel_var = parts
    rows = len(nf)
    if sos is not None:  # (on copies: the parts serve the next trial too)
        nf, sg = _lowpassed(nf.copy(), sos), _lowpassed(sg.copy(), sos)
    fast = _highpass(nf, nlp)
    slow = nf - fast
    cut = slice(nwin // 2, rows - nwin // 2)
    m = rows - 2 * (nwin // 2)  # (the rows the fits keep)
    # the moments' relative 1-sigma: the variance's, and the simulation's own (one draw over m rows of a noise
    # correlated over a few of them: 2 / sqrt(m))
    rel_sd = float(np.hypot(rel_var, 2.0 / np.sqrt(m)))
    return tuple((x[cut].T @ x[cut]) / m for x in (nf, slow, fast)) + (rel_sd, (sg[cut].T @ sg[cut]) / m)


def _noise_regressors(t: np.ndarray, gm: tuple[np.ndarray, np.ndarray], nwin: int, cfg: ImuToImuConfig
                      ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """:func:`_regressor_noise_cov`'s simulation, before any low-pass, on a stretch of at most cfg.noise_rows
    common samples in the middle of t: a white noise of the master gyro's own variance (its spectrum's floor,
    :func:`_noise_floor_var`, per axis; a fixed seed: the same log, the same answer) added to its rates there,
    pushed through :func:`_lever_regressors`, less the regressors without it; and the regressors themselves:
    both high-passed over ``nwin`` ((rows, 12) each), and the noise variance's relative 1-sigma. None where the
    stretch is too short for the filters."""
    n = len(t)
    rows = min(n, cfg.noise_rows)
    if rows < 2 * nwin + 1000:
        return None
    a = (n - rows) // 2
    tb = t[a:a + rows]
    tm, g = gm
    i0 = max(int(np.searchsorted(tm, tb[0])) - 3, 0)
    i1 = min(int(np.searchsorted(tm, tb[-1])) + 3, len(tm))
    tmb, gb = tm[i0:i1], g[i0:i1]
    var, rel_var = _noise_floor_var(gb, with_rel_sd=True)
    sig = np.sqrt(var)
    noisy = gb + np.random.default_rng(0).standard_normal(gb.shape) * sig
    k0, k1 = np.zeros((rows, 3, 4)), np.zeros((rows, 3, 4))
    _lever_regressors(tb, tmb, gb, cfg, k0)
    _lever_regressors(tb, tmb, noisy, cfg, k1)
    nf = _highpass((k1 - k0).reshape(rows, 12), nwin)
    sg = _highpass(k0.reshape(rows, 12), nwin)
    return nf, sg, rel_var


def _lowpassed(x: np.ndarray, sos: np.ndarray) -> np.ndarray:
    """Each column of x (n, k) through the zero-phase low-pass ``sos``, in place (x itself returned)."""
    from logtools.dsp import sosfiltfilt_even

    for j in range(x.shape[1]):
        x[:, j] = sosfiltfilt_even(sos, x[:, j])
    return x


def _noise_gains(sos: np.ndarray, nlp: int, rows: int = 1 << 16) -> tuple[float, float, float]:
    """The variances a unit white noise keeps (a fixed draw) through the zero-phase low-pass ``sos``: in all,
    in its slow part (the moving mean over ``nlp`` samples) and in its fast part (the rest), the whole fit
    and the two bands of :func:`_one_triad`."""
    x = np.random.default_rng(1).standard_normal((rows, 1))
    lp = _lowpassed(x, sos)
    hi = _highpass(lp, nlp)
    keep = slice(rows // 8, -rows // 8)
    return float(np.var(lp[keep])), float(np.var((lp - hi)[keep])), float(np.var(hi[keep]))


def _kept_fraction(kk: np.ndarray, noise_kk: np.ndarray) -> float:
    """The regressors' motion beyond their noise in their weakest direction: the smallest eigenvalue of their
    moment ``kk`` with their noise's ``noise_kk`` out, over the raw one's (-inf where the raw one has none)."""
    corr = kk - noise_kk
    lo_raw = float(np.linalg.eigvalsh(0.5 * (kk + kk.T))[0])
    lo = float(np.linalg.eigvalsh(0.5 * (corr + corr.T))[0])
    return lo / lo_raw if lo_raw > 0 else -np.inf


def _lever_kept_fraction(kk: np.ndarray, noise_kk: np.ndarray) -> float:
    """:func:`_kept_fraction` of the lever arm's columns of the (12, 12) moments (the delay's left out)."""
    cols = [j for j in range(12) if j % 4 != 3]
    return _kept_fraction(kk[np.ix_(cols, cols)], noise_kk[np.ix_(cols, cols)])


def _lever_band(parts: tuple, nwin: int, nlp: int, dt: float, ncov, cfg: ImuToImuConfig):
    """(sos, cutoff Hz, ncov) of the low-pass under which the lever arm's regressors are motion more than noise
    (:func:`_lever_kept_fraction` at least cfg.lever_noise_undetermined_frac), halving the cutoff from an eighth of the
    rate down to cfg.lever_lowpass_min_hz; (None, None, ncov) where the whole band is (or none is). A quiet
    vehicle's angular acceleration is a few hertz, the differentiated gyro noise rises with the frequency up to
    the Nyquist's: on a car without vibration the regressors' moments were 97 % noise, the lever arm came out at
    zero and the accelerometer triad 7.6 deg off at a sigma of 0.7 (4 Hz: 0.02 deg, the lever arm within 2 cm).
    Every series of the fit goes through the same low-pass (the model is linear in them)."""
    from logtools.dsp import butter_lowpass_sos

    if ncov is None or _lever_kept_fraction(ncov[4], ncov[0]) >= cfg.lever_noise_undetermined_frac:
        return None, None, ncov
    fc = 0.125 / dt
    while fc >= cfg.lever_lowpass_min_hz:
        sos = butter_lowpass_sos(cfg.lever_lowpass_order, 2.0 * fc * dt)  # (cutoff over Nyquist: at most 1/4)
        nc = _regressor_noise_cov(parts, nwin, nlp, sos)
        if _lever_kept_fraction(nc[4], nc[0]) >= cfg.lever_noise_undetermined_frac:
            return sos, fc, nc
        fc *= 0.5
    return None, None, ncov


def _lever_columns(t: np.ndarray, gm: tuple[np.ndarray, np.ndarray], nwin: int, cfg: ImuToImuConfig,
                   w: np.ndarray | None = None) -> np.ndarray:
    """(n, 3, 4): the lever arm's regressors at t (:func:`_lever_regressors`, from the master's gyro ``gm``; ``w``
    its rates at t where already interpolated), high-passed over ``nwin``, in the first three columns; the
    fourth (the delay's) left to :func:`_with_delay_column`."""
    n = len(t)
    k = np.empty((n, 3, 4))
    _lever_regressors(t, *gm, cfg, k, w)
    kf = k.reshape(n, 12)
    for j in range(12):
        if j % 4 != 3:
            _highpass(kf[:, j:j + 1], nwin, out=kf[:, j:j + 1])
    return k


def _with_delay_column(t: np.ndarray, u: np.ndarray, k: np.ndarray | None) -> np.ndarray:
    """The regressors with the delay's: a delay left between the two (the latency's error, the sensors' own
    sampling instants) as one more parameter, v(t) = R u(t - d) ~ R (u - d du/dt), in k's last column ((n, 3, 1)
    without the lever arm's); a delay of 1.4 ms turned the rotation of IMU2's gyro triad by 0.2 deg on a
    hand-carried ArduPlane (rates and their derivatives correlate across axes)."""
    if k is None:
        return -np.gradient(u, t, axis=0)[:, :, None]
    k[:, :, 3] = -np.gradient(u, t, axis=0)
    return k


def _rows(x: np.ndarray) -> np.ndarray:
    """x (n, ...) as (n, columns), a view: what is written into it is written into x (the fit's arrays are made
    C-contiguous)."""
    assert x.flags.c_contiguous
    return x.reshape(len(x), -1)


def _lowpassed_columns(sos: np.ndarray, *xs: np.ndarray) -> None:
    """Every series of the fit (u, v, k) through the zero-phase low-pass ``sos``, in place (the model is linear
    in them)."""
    for x in xs:
        _lowpassed(_rows(x), sos)


def _columns_again(common: Callable, master_gyro: Callable, nwin: int, lever: bool, sos: np.ndarray | None,
                   cfg: ImuToImuConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, k) as :func:`_one_triad` built them for its first fit, built again with its decisions (the lever
    arm's regressors or not, the low-pass or none): the same arithmetic, the same numbers."""
    t, u, v = common()
    u, v = _highpass(u, nwin, out=u), _highpass(v, nwin, out=v)
    k = _with_delay_column(t, u, _lever_columns(t, master_gyro(), nwin, cfg) if lever else None)
    if sos is not None:
        _lowpassed_columns(sos, u, v, k)
    return u, v, k


def _one_triad(name: str, common: Callable, master_gyro: Callable, highpass_s: float, cfg: ImuToImuConfig,
               starts: tuple[np.ndarray, ...] = ()) -> TriadRotation | str:
    """One triad's rotation on common samples (``common()``: t, master u, slave v, made anew at each call), the
    slow part out over highpass_s; ``master_gyro()``: the master's gyro (stamps, rates) or None; ``starts``:
    further starting rotations of the fit (the accelerometers': the gyro triad's). Where the fit's columns
    hold ``cfg.rebuild_min_bytes`` or more, they are built twice (the whole motion and its slow part are fitted
    on the first, its fast part on the second), so that no two sets of them are held at once: 4 h of 200 Hz
    accelerometers' are 415 MB a set."""
    com = common()
    if com is None or len(com[0]) < cfg.min_samples:
        return TOO_FEW_COMMON
    t, u, v = com
    del com
    dt = median_step_s(t)
    nwin = max(int(round(highpass_s / dt)), 3)
    # the slow part out, in place; the ends (shorter means) trimmed below
    u, v = _highpass(u, nwin, out=u), _highpass(v, nwin, out=v)
    n = len(t)
    k = w = None
    gm = master_gyro() if name == "accel" else None
    if gm is not None and len(gm[0]) >= 3:
        w, okw = _interp_at(t, *gm, cfg.gap_steps, cfg.lever_interp_points)
        if okw.all():
            k = _lever_columns(t, gm, nwin, cfg, w)  # (the delay's column below)
            moving = float(np.sqrt(np.einsum("ij,ij->", u, u) / n))  # (no squared copies: 4 h of 200 Hz
            power = float(np.einsum("kij,kij->", k[:, :, :3], k[:, :, :3]) / n)  # are 207 MB of the regressors')
    nlp = max(int(round(cfg.band_split_s / dt)), 2)  # (the slow and fast parts' split, below)
    # the noise the master gyro puts into the lever arm's regressors: taken out of their moments in each fit
    parts = _noise_regressors(t, gm, nwin, cfg) if k is not None else None  # (shared with _lever_band's trials)
    del gm
    ncov = _regressor_noise_cov(parts, nwin, nlp) if parts is not None else None
    if k is not None:
        # the lever arm's effect from the regressors' motion, their noise out: a quiet vehicle's differentiated
        # gyro noise alone passed the test, and the fit, its moments all noise in some directions (where the
        # correction is refused), put the lever arm at zero with a millimetre sigma (a car 1.8 m off)
        if ncov is not None:
            power -= float(np.trace(ncov[0]))  # (per sample, the delay's columns none)
        effect = cfg.lever_plausible_m * float(np.sqrt(max(power, 0.0) / 3.0))
        wh = _highpass(w, nwin)
        rate = float(np.sqrt(np.einsum("ij,ij->", wh, wh) / n))
        del wh
        if not (rate > cfg.lever_min_rate_rad_s or effect > cfg.lever_min_effect * moving):
            k, ncov = None, None
    del w
    k = _with_delay_column(t, u, k)
    lever = k.shape[2] == 4
    cut = slice(nwin // 2, len(t) - nwin // 2)
    sos = lp_hz = u_var = None
    band_var = (None, None)  # the master's white noise in the slow and the fast band (low-passed: below)
    if name == "accel" and lever:
        sos, lp_hz, ncov = _lever_band(parts, nwin, nlp, dt, ncov, cfg)
        if sos is not None:  # every series of the fit through the same low-pass
            # (the master's white noise as the fit sees it: measured before, times the low-pass's power gain;
            # third differences of a low-passed series see little of it, and straight and level flight's
            # horizontal specific force, its noise low-passed, came out "determined" 20 deg off)
            # ... and in each band apart: their own third differences see as little of it (the fast band of
            # an aircraft's accelerometers, 2.5-25 Hz, is mostly noise: "determined" 30-120 deg from the slow
            # band at a sigma of a degree, so the triad was called "not one rotation" and its sigma inflated to
            # tens of degrees)
            white = _white_noise_var(u[cut], cfg)
            u_var, *band_var = (white * g for g in _noise_gains(sos, nlp))
            _lowpassed_columns(sos, u, v, k)
    del parts
    rel = ncov[3] if ncov else 0.0
    res = _triad(u[cut], v[cut], k[cut], dt, cfg, starts=starts, k_noise_cov=ncov[0] if ncov else None,
                 k_noise_rel_sd=rel, u_noise_var=u_var)
    if isinstance(res, str):
        return res
    if lp_hz is not None:
        res = replace(res, lowpass_hz=float(lp_hz))
    # a rotation is the same at every frequency: fitted on the slow and on the fast part of the motion
    # apart, two figures beyond band_z sigmas say the triads differ by more than a rotation (the
    # sensors' own filters, vibration aliased into the snapshots, scale factors)
    # the fast part's columns: a copy of these, or (long logs) built again once the slow part is fitted
    held = tuple(x.copy(order="K") for x in (u, v, k)) if u.nbytes + v.nbytes + k.nbytes < cfg.rebuild_min_bytes \
        else None
    lo = (u, v, k)  # x - highpass(x), written over x column by column
    for x in lo:
        xf = _rows(x)
        for j in range(xf.shape[1]):
            np.subtract(xf[:, j], _highpass(xf[:, j:j + 1], nlp)[:, 0], out=xf[:, j])
    del u, v, k, x, xf
    # (a band the rotation explains poorly is itself the sign: no minimum there, the sigmas judge)
    band_lo = _triad(lo[0][cut], lo[1][cut], lo[2][cut], dt, cfg, min_explained=0.0, starts=starts,
                     k_noise_cov=ncov[1] if ncov else None, k_noise_rel_sd=rel, u_noise_var=band_var[0],
                     min_canonical_z=cfg.band_min_canonical_z)
    del lo
    hi = held if held is not None else _columns_again(common, master_gyro, nwin, lever, sos, cfg)
    del held
    for x in hi:  # the fast part, in place
        _highpass(_rows(x), nlp, out=_rows(x))
    del x
    bands = [band_lo, _triad(hi[0][cut], hi[1][cut], hi[2][cut], dt, cfg, min_explained=0.0, starts=starts,
                             k_noise_cov=ncov[2] if ncov else None, k_noise_rel_sd=rel, u_noise_var=band_var[1],
                             min_canonical_z=cfg.band_min_canonical_z)]
    del hi
    if all(isinstance(b, TriadRotation) for b in bands):
        zb, d = _z(bands[0].rpy_deg, bands[0].sigma_deg, bands[1].rpy_deg, bands[1].sigma_deg,
                   cfg.consistency_floor_deg, cfg.gimbal_compare_deg)
        res = replace(res, band_z=zb, band_rpy_deg=(bands[0].rpy_deg, bands[1].rpy_deg), rigid=bool(zb <= cfg.band_z))
        if zb > cfg.band_z:  # not one rotation: half the bands' spread joins the sigma (the model's error)
            res = replace(res, sigma_deg=tuple(float(x) for x in np.hypot(res.sigma_deg, 0.5 * d)),
                          sigma_data_deg=res.sigma_deg)
    else:
        res = replace(res, band_unchecked="; ".join(f"{part} band: {b}" for part, b in zip(("slow", "fast"), bands)
                                                    if isinstance(b, str)))
    return res


def imu_to_imu(master: InsLog, slave: InsLog, *, config: ImuToImuConfig = DEFAULT) -> ImuToImu:
    """The rotations of the slave's gyro and accelerometer triads relative to the master's (module doc).
    ``slave`` on the master's clock (compensated). A triad that cannot be measured is None with its reason."""
    if slave.meta.t0_ns != master.meta.t0_ns:
        slave = slave.rebased(master.meta.t0_ns)
    reasons: dict[str, str] = {}
    out: dict[str, TriadRotation | None] = {"gyro": None, "accel": None}
    def master_gyro() -> tuple[np.ndarray, np.ndarray] | None:  # (read anew where needed: not held between)
        return finite_increasing(master.t_imu_s(), master.gyro_rad_s()) if master.has_gyro else None

    for name, has, get in (("gyro", "has_gyro", "gyro_rad_s"), ("accel", "has_accel", "accel_m_s2")):
        if not (getattr(master, has) and getattr(slave, has)):
            who = " and ".join(r for r, lg in (("master", master), ("slave", slave)) if not getattr(lg, has))
            reasons[name] = f"the {who} logs no {'angular rate' if name == 'gyro' else 'specific force'}"
            continue
        def common() -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
            tm, ym = finite_increasing(master.t_imu_s(), getattr(master, get)())
            ts, ys = finite_increasing(slave.t_imu_s(), getattr(slave, get)())
            return _common(tm, ym, ts, ys, config.gap_steps)

        res: TriadRotation | str = ""
        # the accelerometers' fit also starts from the gyro triad's rotation (a board's two triads are
        # degrees apart at most): a multirotor's lever-arm accelerations can dominate the moving specific
        # force and put the Wahba start, and Gauss-Newton from it, 180 deg off with the lever arm flipped
        gyro = out["gyro"]
        starts = () if name != "accel" or gyro is None else (
            (dcm_from_quat(gyro.quat_wxyz),) if gyro.gimbal else (dcm_from_euler(np.radians(gyro.rpy_deg)),))
        for hp in (config.highpass_s, *config.highpass_retry_s):  # slow motion (a ship's sway, S-turns): a
            res = _one_triad(name, common, master_gyro, hp, config, starts=starts)  # longer window
            if isinstance(res, TriadRotation) or res == TOO_FEW_COMMON:
                break
        if isinstance(res, str):
            reasons[name] = res
            continue
        out[name] = res
    return ImuToImu(out["gyro"], out["accel"], reasons)


# ---- the two views compared ------------------------------------------------------------------------
def _at_lock(rpy: np.ndarray) -> bool:
    """The canonical triple at the gimbal lock (:func:`gimbal_canonical`: roll 0, pitch +-90 deg exactly)."""
    return bool(rpy[0] == 0.0 and abs(rpy[1]) == 90.0)


def _one_convention(a_rpy: np.ndarray, a_sig: np.ndarray, b_rpy: np.ndarray, b_sig: np.ndarray, lock_deg: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two triples (deg) in one convention for their difference: where one is the canonical triple at the
    gimbal lock and the other (less noisy: not snapped) is within lock_deg of the same lock, the other's roll
    and yaw are written the canonical way too (roll 0, yaw = atan2(-R01, R11); its pitch kept, so a pitch
    that differs still shows), their sigmas the smaller of its two (its Euler roll and yaw sigmas each hold
    the rotation's about the shared axis, and more). Else as they are."""
    a, sa, b, sb = _arr(a_rpy), _arr(a_sig), _arr(b_rpy), _arr(b_sig)
    if not (np.isfinite(a).all() and np.isfinite(b).all()) or _at_lock(a) == _at_lock(b):
        return a, sa, b, sb
    lock, other, s_other = (a, b, sb) if _at_lock(a) else (b, a, sa)
    if np.sign(other[1]) != np.sign(lock[1]) or 90.0 - abs(other[1]) > lock_deg:
        return a, sa, b, sb
    r = dcm_from_euler(np.radians(other))
    canon = np.array([0.0, other[1], np.degrees(np.arctan2(-r[0, 1], r[1, 1]))])
    s_ry = min(s_other[0], s_other[2])
    s_canon = np.array([s_ry, s_other[1], s_ry])
    return (a, sa, canon, s_canon) if _at_lock(a) else (canon, s_canon, b, sb)


def _z(a_rpy: np.ndarray, a_sig: np.ndarray, b_rpy: np.ndarray, b_sig: np.ndarray, floor_deg: float,
       lock_deg: float = 0.0) -> tuple[float, np.ndarray]:
    a_rpy, a_sig, b_rpy, b_sig = _one_convention(a_rpy, a_sig, b_rpy, b_sig, lock_deg)
    d = (_arr(a_rpy) - _arr(b_rpy) + 180.0) % 360.0 - 180.0
    s = np.sqrt(_arr(a_sig) ** 2 + _arr(b_sig) ** 2)
    z = np.abs(d) / np.maximum(s, floor_deg)
    return float(np.nanmax(z)), d  # axes not determined (null) are left out


def _arr(v) -> np.ndarray:
    return np.array([np.nan if x is None else float(x) for x in v])


def lever_arm_consistency(lever_m, lever_sigma_m, imu: ImuToImu, config: ImuToImuConfig = DEFAULT) -> dict | None:
    """The transfer alignment's lever arm (``lever_m``, ``lever_sigma_m``: the compensated run's, m, master body
    frame) against the accelerometer triad's (the same offset, from the specific forces' difference): ``{z,
    diff_m, agrees, warning}``, the largest per-axis difference over the combined sigma (at least
    ``config.consistency_lever_floor_m``); None where either is missing. Two lever arms apart say one of the two
    fits took up something else: the velocity matching a motion the master's navigation output does not
    resolve (vibration between its samples), the accelerometer fit too little rotation, a scale factor or a
    wrong sensing point: the warning names no winner."""
    acc = imu.accel
    if (lever_m is None or lever_sigma_m is None or acc is None or acc.lever_arm_m is None
            or acc.lever_arm_sigma_m is None):
        return None
    a, sa = _arr(lever_m), _arr(lever_sigma_m)
    b, sb = _arr(acc.lever_arm_m), _arr(acc.lever_arm_sigma_m)
    if not (len(a) == len(b) == 3 and np.isfinite(a).all() and np.isfinite(sa).all()
            and np.isfinite(b).all() and np.isfinite(sb).all()):
        return None
    d = a - b
    z = float(np.max(np.abs(d) / np.maximum(np.hypot(sa, sb), config.consistency_lever_floor_m)))
    out = {"z": z, "diff_m": [float(x) for x in d], "agrees": bool(z <= config.consistency_z), "warning": None}
    if not out["agrees"]:
        out["warning"] = (
            "lever arms disagree: transfer alignment x y z = " + " ".join(f"{x:+.3f}" for x in a) + " +/- "
            + " ".join(f"{x:.3f}" for x in sa) + " m, accelerometer triad " + " ".join(f"{x:+.3f}" for x in b)
            + " +/- " + " ".join(f"{x:.3f}" for x in sb) + f" m (z {z:.1f}): one of the two fits took up something "
            "else (the velocity matching: motion the master's navigation output does not resolve, such as vibration "
            "between its samples; the accelerometers: too little rotation, a scale factor or their sensing point), "
            "so neither lever arm is to be trusted at its sigma")
    return out


def consistency(mount_rpy_deg, mount_sigma_deg, imu: ImuToImu, config: ImuToImuConfig = DEFAULT, *,
                board_states: bool = False, lever_m=None, lever_sigma_m=None) -> dict:
    """``alignment.consistency``: the compensated nav-referenced mounting against the gyro triad's rotation
    (and the accelerometer triad's), ``{agrees, z, note}`` plus the per-view figures; ``warning`` holds the
    text of a disagreement (None when they agree). ``board_states``: the mounting came from a filter that
    carried the master's attitude error (``--board-errors on``); else the note says that option exists.
    ``lever_m``, ``lever_sigma_m``: the transfer alignment's lever arm, compared with the accelerometer triad's
    (:func:`lever_arm_consistency`: ``lever_arm_z``, ``lever_arm_diff_m``, ``lever_arm_agrees`` and, where they
    disagree, ``lever_arm_note``, the warning's text). ``agrees``, ``z`` and ``warning`` stay the rotations'."""
    out = _rotation_consistency(mount_rpy_deg, mount_sigma_deg, imu, config, board_states)
    lev = lever_arm_consistency(lever_m, lever_sigma_m, imu, config)
    if lev is not None:
        out["lever_arm_z"], out["lever_arm_diff_m"], out["lever_arm_agrees"] = lev["z"], lev["diff_m"], lev["agrees"]
        if lev["warning"]:
            out["lever_arm_note"] = lev["warning"]
    return out


def _rotation_consistency(mount_rpy_deg, mount_sigma_deg, imu: ImuToImu, config: ImuToImuConfig,
                          board_states: bool) -> dict:
    out: dict = {"agrees": None, "z": None, "note": "", "warning": None}
    mount_ok = (mount_rpy_deg is not None and mount_sigma_deg is not None
                and bool(np.isfinite(_arr(mount_rpy_deg) + _arr(mount_sigma_deg)).any()))
    views = {}
    if mount_ok and imu.gyro:
        views["z_mount_gyro"] = _z(mount_rpy_deg, mount_sigma_deg, imu.gyro.rpy_deg, imu.gyro.sigma_deg,
                                     config.consistency_floor_deg, config.gimbal_compare_deg)
    if mount_ok and imu.accel:
        views["z_mount_accel"] = _z(mount_rpy_deg, mount_sigma_deg, imu.accel.rpy_deg, imu.accel.sigma_deg,
                                      config.consistency_floor_deg, config.gimbal_compare_deg)
    if imu.gyro and imu.accel:
        views["z_gyro_accel"] = _z(imu.gyro.rpy_deg, imu.gyro.sigma_deg, imu.accel.rpy_deg, imu.accel.sigma_deg,
                                      config.consistency_floor_deg, config.gimbal_compare_deg)
    for k, (z, d) in views.items():
        out[k] = z
        out[k.replace("z_", "diff_") + "_deg"] = [float(x) if np.isfinite(x) else None for x in d]
    if not views or ("z_mount_gyro" not in views and "z_mount_accel" not in views and "z_gyro_accel" not in views):
        why = ("no nav-referenced mounting to compare" if not mount_ok else "no IMU-to-IMU rotation measured")
        out["note"] = f"not compared: {why}"
        return out
    z_all = max(z for z, _ in views.values())
    out["z"] = z_all
    out["agrees"] = bool(z_all <= config.consistency_z)
    causes = []
    zg = views.get("z_mount_gyro", (None,))[0]
    za = views.get("z_mount_accel", (None,))[0]
    zt = views.get("z_gyro_accel", (None,))[0]
    if zt is not None and zt > config.consistency_z:
        causes.append(f"the slave's accelerometer triad is not its gyro triad (or the master's is not its own: "
                      f"gyro vs accel triad rotations differ at z {zt:.1f})")
    if (zg is not None and zg > config.consistency_z) or (zg is None and za is not None and za > config.consistency_z):
        zz = zg if zg is not None else za
        causes.append(f"the master's navigation frame is not its IMU frame (board trim or its EKF's attitude "
                      f"error: the nav-referenced mounting differs from the IMU-to-IMU rotation at z {zz:.1f}"
                      + (")" if board_states else "; for a consumer-grade master, --board-errors on carries its "
                         "attitude error in the mounting's sigma)"))
    elif za is not None and za > config.consistency_z and not (zt is not None and zt > config.consistency_z):
        causes.append(f"the accelerometer triad's rotation differs from the mounting at z {za:.1f} while the gyro "
                      "triad's agrees: the accelerometers' scale factors, lever arm or vibration")
    for name, tr in (("gyro", imu.gyro), ("accel", imu.accel)):
        if tr is not None and tr.rigid is False:
            causes.append(f"the {name} triads differ by more than a rotation (slow and fast motion give rotations "
                          f"z {tr.band_z:.1f} apart: the sensors' filters, vibration aliased into the "
                          "snapshots or scale factors), so its rotation is a compromise")
    figures = ", ".join(f"{k[2:].replace('_', ' vs ')} z {z:.1f}" for k, (z, _) in views.items())
    if out["agrees"]:
        out["note"] = f"agree within {config.consistency_z:g} combined sigma ({figures})"
        loose = [n for n, tr in (("gyro", imu.gyro), ("accel", imu.accel)) if tr is not None and tr.rigid is False]
        if loose:
            out["note"] += (f"; but the {' and '.join(loose)} triads differ by more than a rotation (slow and fast "
                            "motion disagree), so their sigmas carry that spread and the check is weak")
    elif z_all <= config.consistency_marginal_z:
        out["note"] = (f"disagree marginally, beyond {config.consistency_z:g} but within "
                       f"{config.consistency_marginal_z:g} combined sigma ({figures}; one rigid board reaches this "
                       "now and then): possibly " + "; ".join(causes))
        out["warning"] = out["note"]
    else:
        out["note"] = f"disagree beyond {config.consistency_z:g} combined sigma ({figures}): likely " + "; ".join(causes)
        out["warning"] = out["note"]
    return out
