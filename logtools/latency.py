"""Latency (and clock drift) of the slave unit behind the master, from angular rate.

``estimate(master, slave)`` returns a :class:`~logtools.results.LatencyResult` whose ``latency_s``
follows DESIGN.md: positive when the slave's stamps are late, i.e. the slave sample stamped ``t + d``
shows the motion the master stamped ``t``.  Model (both units on the master's relative clock)::

    w_slave(t + d(t)) = R w_master(t) + b + noise,    d(t) = L + drift * (t - t_mid)

with R the unknown relative mounting (``v_slave = R v_master``, any rotation), b the difference of the
gyro biases, L the latency at the middle ``t_mid`` of the analysed window and ``drift`` the relative clock
rate (``drift_ppm`` = drift * 1e6).

tapost's method ("tapost")
  0. inputs: each unit's gyro (or body rate from its attitude quaternions, plus the earth and transport
     rates from the unit's position and velocity, so that it is inertial like a gyro's), on the master's relative
     clock (``slave.rebased(master.meta.t0_ns)``, exact), each on its own uniform grid
     (``logtools.resample``: duplicates, jitter, gaps masked), zero-phase low-passed at the same cutoff
     (3x the motion's band: the noise above it would bias a spline-interpolated sub-sample delay; at least
     MIN_CUTOFF_HZ, 4 Hz, for the Kalman flexure fit's blocks to resolve the flexure, at most a fifth of the
     common rate; the motion's signal/noise and the velocities at the motion's band, at least 1 Hz);
  1. coarse, rotation-invariant: normalised cross-correlation of |w| (mean removed and normalised over
     the overlap at each lag, FFT over the whole overlap) -- candidates, and the "xcorr-norm" baseline;
  2. rotation from the data: at every integer lag of the search range the rotation-solved vector cost
     ``min_{R,b} sum |w_s - R w_m - b|^2`` (Kabsch/Wahba with the means, i.e. the biases) is computed at
     once from 18 FFT cross-correlations and a batched 3x3 SVD: a cost curve that is rotation- and
     bias-invariant and uses all three axes (this is what makes slow, smooth motions work);
  3. full-vector refinement to a sub-sample delay: Gauss-Newton on the continuous delay (cubic B-spline
     of the slave, never extrapolated), R and b re-solved at every step (variable projection); the
     delay's gradient and curvature from the cleaner of the two units' derivatives, mostly the master's
     (``latency_gls.delay_normal``: a noisy slave's inflates the curvature and ripples with the
     sub-sample phase);
  3b. generalised least squares (GLS): the residual w_s(t + d) - R w_m(t) - b of that first fit is not
     white -- flexure adds a differential angular rate between the units, a coloured (second-order
     Markov) process concentrated at low frequency, on top of the gyros' white noise -- so its power
     spectrum is estimated (periodogram smoothed over GLS_SMOOTH_HZ) and the Gauss-Newton steps are
     taken on the whitened residual and the whitened joint Jacobian (zero-phase 1/sqrt(PSD) filter,
     the used samples fixed and tapered at their ends so that no step is amplified): each frequency
     weighs as (motion-derivative power / residual power), the maximum-likelihood weighting for a
     Gaussian disturbance. (Without a residual spectrum, e.g. very short data, the older heuristic
     is used: the low-pass band re-chosen from the residual spectrum and the units re-filtered.)
  3c. accelerometer-aided GLS (when both units log gyros and accelerometers and the gyro-only sigma
     exceeds ACCEL_MIN_SIGMA_S): flexure rotates the slave, so it tilts the slave's specific force as
     well as adding a differential rate; the accelerometer residual f_s(t + d) - R (f_m + ([w_m' x] +
     [w_m x]^2) r) - b_a (r: lever arm, b_a: accelerometer bias difference, both solved) joins the gyro
     residual, and the whitening uses their 6 x 6 cross-spectral density, so the part of the flexure
     that the accelerometers see is weighed out and the specific force's own motion (heave, turns,
     speed changes) adds delay information. (A rotation of the slave by flexure and a delay of its
     rotation look alike to gravity's direction, so the gain comes mostly from the non-rotational
     accelerations; the vertical-axis flexure is not seen at all.) Model check: a separate delay of
     the accelerometers is estimated alongside; beyond ACCEL_LAG_SIGMAS sigma (real IMUs may filter
     accelerometers and gyros differently) the fit is redone with that delay as a further unknown
     (ACCEL_LAG_FREE: the accelerometers' delay information is lost, their view of the flexure's tilt
     is kept); where that delay exceeds ACCEL_LAG_MAX_S or the sigma is not smaller, the gyro-only fit
     stays. (Assumed zero, an accelerometer delay of d moved a flexing ship's latency by about d: what
     the check cannot see, 1-2 of its sigmas, stays a bias of that size.)
  3d. Kalman whitening with a flexure model (``logtools.latency_flexure``; when the sigma so far exceeds
     ACCEL_MIN_SIGMA_S): the residual is modelled as seed 000's flexure -- a second-order Markov rotation
     lam of the slave per axis (eq. 8), which adds lam' + w x lam to its rates and f x lam to its specific
     force -- plus white noise per channel; the model's parameters (sigma per axis, beta, the noise) by
     restricted maximum likelihood, then the delay on the profile of the Kalman-whitened cost (every
     other unknown concentrated out) by Newton steps on parabolas through the cost itself, sigma from
     the profile's curvature (floored by the Gauss-Newton/HAC one). A stationary spectrum estimated
     from a few cycles of slow motion cannot tell the flexure from the delay as well as this model
     does, and it averages the gravity direction's modulation of the accelerometer rows that the
     Kalman filter keeps exact. A candidate when within FLEX_AGREE_SIGMAS of the spectral fit; kept
     unless its own drift windows (step 5, re-estimated with it) disagree beyond FLEX_WINDOWS_CHI2 and
     the spectral fit's window-checked sigma is the smaller (a real log whose disturbance is not
     flexure-like: vibration, filters). The quality key ``flexure_model`` then gives the fitted sigma
     (deg) and beta. On the benchmark's flexure runs the error is at the Cramer-Rao bound
     (``benchmarks/latency_bound.py``).
  4. drift: steps 3-3b in windows along the overlap (integer-lag search around the predicted lag, then
     refinement), a weighted line latency(t) = L + drift (t - t_mid) with windows beyond WINDOW_REJECT
     sigma rejected (a window with little motion can lock on a wrong minimum, where its linearised sigma
     means nothing), then a joint Gauss-Newton of (L, drift) with R, b over the whole overlap (started
     from the windows' line and from the central fit; the lower cost wins), then GLS_PASSES GLS passes
     over the whole overlap, the residual spectrum re-estimated before each;
  5. sigma: the joint (L, drift, rotation, bias) GLS covariance (whitened curvature x whitened residual
     variance) with a heteroscedasticity-and-autocorrelation-consistent (Bartlett/Newey-West) variance
     of the whitened scores as a floor (what whitening missed), inflated by the scatter of the window
     estimates about the drift line (with an accelerometer-aided or Kalman-whitened fit, the windows
     re-estimated with it; when fewer than 3 windows have the motion for that, no window check);
  5b. velocity matching (``logtools.latency_velocity``; when both units log NED velocity): a second
     estimate of (L, drift) from v_s(t + d) = v_m(t) + C_nb (w_m x l) + the slave's velocity error
     (offset, ramp, the (v - v_mid) x phi of a tilted slave INS, and a step at each reset of an aided
     filter's velocity), lever arm l and the rest solved, GLS-whitened, window-checked, with floors for
     a velocity or stamps logged on a coarse grid (MAVLink's cm/s and ms). Flexure rotates the slave
     without moving it, so the velocity keeps the delay information the rates lose to the flexure (and
     a slave without an IMU gains what its attitude-derived rates lack). Fused with the rate fit's
     (L, drift) by inverse covariance when the two agree (chi-square below VEL_AGREE_CHI2 with the
     sigmas as reported) and the velocity is the more precise or the rate fit had to model flexure;
     when they disagree the rate fit stays and ``velocity_disagrees`` is set (a nav output logged later
     than its IMU). Two units that carry the same nav samples (one EKF logged with two IMUs) are not
     matched. Then the drift prior;
  6. quality flags: motion level, too little motion, periodic motion (several near-equal minima of the
     cost: S000 eq 6's caveat; sigma then covers the ambiguity), windows disagreeing, overlap, rotation
     found, residual RMS, masked fraction.

"xcorr-norm": step 1 alone with a parabolic peak interpolation (what Kalibr / Twist-n-Sync do first).
The seeds' methods (``s000-rate-integral``, ``s002-attitude-shift``) live in ``logtools.latency_seeds``.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import fft as sfft

from logtools import earth
from logtools.conventions import (dcm_from_quat, euler_from_dcm, quat_conj, quat_make_continuous, quat_mul,
                                 rotvec_from_quat, skew)
from logtools.errors import AnalysisError
from logtools.inslog import InsLog
from logtools.navcheck import output_validity
from logtools.latency_gls import (NoiseModel, delay_normal, delay_step, delay_system, end_taper, gls_covariance,
                                  grid_derivative, grid_offset_sigma_s, hac_cov, noise_model, stamp_noise_variance,
                                  window_chi2)
from logtools.latency_velocity import VelocityPair, velocity_fit, velocity_pair
from logtools.latency_flexure import DECIMATE_FACTOR, FlexureModel, block_mean, fit_model, whitened_normal
from logtools.resample import (Interpolant, UniformSeries, interpolant, lowpass, median_rate_hz, stamp_noise_s,
                               to_uniform)
from logtools.results import LatencyResult, MethodEstimate

__all__ = ["estimate", "METHODS", "rate_from_attitude"]

METHODS = ("tapost", "s000-rate-integral", "s002-attitude-shift", "xcorr-norm")
MAX_COMMON_RATE_HZ = 200.0  # refinement grid cap (a 400-1000 Hz unit is low-passed then decimated)
MAX_COARSE_RATE_HZ = 100.0  # integer-lag search grid cap
CUTOFF_FRACTION = 0.4  # zero-phase low-pass at most at this fraction of the common rate
BAND_COMMON = True  # the motion's band: the smaller of the two units' (each unit's own noise, flexure, vibration
#                    widens its own band only; the larger took a ship's fast flexure for motion: a 49 Hz cutoff)
BAND_MIN_CUTOFF_HZ = 1.0  # 3x the motion's band, at least here: the band of the motion's signal/noise and of
#                          the velocities' low-pass (latency_velocity caps it further)
MIN_CUTOFF_HZ = 4.0  # the rates' low-pass: 3x the motion's band, at least here. The Kalman flexure fit's blocks
#   (DECIMATE_FACTOR x the cutoff) must resolve the flexure's own dynamics. At 1 Hz a 0.4 s block averaged a
#   flexure of beta 2/s: its model came out beta 1.1 with a white noise 5-30x the sensors', and turning cars'
#   IMU-only latencies had an RMS of 0.79 ms at sigmas of 1.5 ms against a bound of 0.53 ms (at 4 Hz, with
#   FLEX_ACCEL_OWN: 0.54 ms at 0.78 ms)
MIN_CUTOFF_FRACTION = 0.2  # ... that floor at most this fraction of the common rate (an attitude-only slave at
#   10 Hz, its rates low-passed at 80 % of their Nyquist, came out 7.7 ms off at sigma 1.7 ms; at 2 Hz right)
MIN_OVERLAP_S = 5.0
MIN_MOTION_SNR = 2.0  # in-band motion RMS / in-band noise RMS below this: no motion (AnalysisError)
LOW_MOTION_SNR = 10.0  # below this (or below LOW_MOTION_DPS): "too_little_motion" flag
LOW_MOTION_DPS = 0.5
WINDOW_S = 15.0  # nominal window length for the drift stage (3..MAX_WINDOWS windows)
MAX_WINDOWS = 16
WINDOW_DATA_FRACTION = 0.9  # data over less of the span than this (gaps): windows in the runs of data
MIN_WINDOW_S = 5.0  # ... each at least this long
WINDOWS3_MIN_S = 20.0  # overlaps this long get at least 3 drift windows (a drift fit checked by them)
STAMP_RESOLUTION_FLOOR = True  # stamps on a coarse grid floor the sigma at step / sqrt(12) per unit
DRIFT_FIT_ALWAYS = False  # a drift fitted without 3 windows (measured worse: short logs with flexure took
DRIFT_MIN_SPAN_S = 20.0  # drifts of 200 ppm at optimistic sigmas, coverage 0.83 against 0.96)
DRIFT_PRIOR_PPM = 100.0  # prior std of the relative clock drift (shrinks an undetermined drift)
DRIFT_SEARCH_PPM = 250.0  # window search band grows with distance from the middle at this rate
SIGMA_CALIBRATION = 1.2  # from a Monte Carlo over the simulator (|error| <= 2 sigma in ~95 % of runs)
ADAPT_BAND = True  # narrow the band where the residuals (flexure) outweigh the motion
ADAPT_SPAN_S = 300.0  # the band is chosen from a first fit on the central part of the overlap
MIN_ADAPT_CUTOFF_HZ = 0.05
MIN_ADAPT_CYCLES = 20.0  # the adapted cutoff keeps at least this many cycles over the overlap
ADAPT_GAIN = 0.7  # narrow only when the predicted variance drops below this fraction
SIGMA_FLOOR_S = 5e-6  # model floor (interpolation, numerics)
NO_MATCH_COST = 0.5  # the best lag leaves more than this fraction of the rates' variance unexplained: no match
#   (real pairs 1e-4 to 0.065: a car's wheel odometry, a 4 Hz SITL attitude; logs of different vehicles 0.91)
COARSE_PEAKS = 48  # an unbounded search evaluates the full-vector cost around this many best |w| peaks (6 before:
#   a ship whose yaw sway, period 7.66 s, dominates |w| has a |w| peak every period, and the true lag was not
#   among the best 6 of the 180 s record; the one kept was a yaw period off, its roll and pitch taken for a
#   180 deg rotation of the mounting (cost 0.0014), the velocity fit disagreeing at chi2 17616)
PERIODIC_MARGIN = 1e-4  # alternative minimum within this of the best normalised cost -> periodic (numerical floor:
#   noise-free data have best costs of 1e-6..1e-5; a course that nearly repeats 130 s later cost 3e-3 there,
#   1000x the best, and was flagged at 0.02; an aircraft's S-turns 200 s later 2.5e-4 against 9e-5 (the cost's
#   statistical spread is a few % of it: PERIODIC_REL_MARGIN covers that))
PERIODIC_REL_MARGIN = 0.1  # ... or within this fraction of the best cost (noisy data)
SEARCH_WIDEN = True  # a bounded search whose result is suspect (see _suspect) also searches the whole overlap
SEARCH_EDGE_FRACTION = 0.9  # ... a result beyond this fraction of --max-lag
SEARCH_SUSPECT_COST = 0.05  # ... or a normalised rate cost above this (good fits: <= 0.006 on the real logs,
#   0.03 for an EKF's attitude against its filtered gyro, <= 0.003 in the simulations; a wrong lag: 0.1-0.9)
SEARCH_WIDEN_GAIN = 0.5  # the whole-overlap result replaces the bounded one below this x its cost
PERIODIC_VELOCITY = True  # alternatives checked on the velocities where both units have them
PERIODIC_VELOCITY_RATIO = 2.0  # an alternative whose velocity residual RMS exceeds the estimate's this many
#   times is rejected (its mismatch then carries 3x the noise's power)
GLS = True  # weigh frequencies by motion / residual power (whitened Gauss-Newton), see _refine_gls
GLS_PASSES = 2  # whole-overlap GLS passes (residual spectrum re-estimated before each)
GLS_TAPER_S = 2.0  # ramp of the weights at the ends of the used data (whitening transients)
WINDOW_REJECT = 5.0  # a window this many sigma off the drift line is an outlier (wrong minimum)
WINDOW_DRIFT = True  # the drift windows' delays are fitted with the drift inside each window (see _fit_all)
WINDOW_DRIFT_FRACTION = 0.1  # ... where it moves a window's delay end to end by more than this x its sigma
WINDOW_INFLATE = True  # sigma inflated by the kept windows' scatter about the drift line (chi2 > 1)
FINE_COST_POINTS = 41  # continuous cost samples around the estimate (plots)
FINE_COST_SIGMAS = 5.0  # ... over +- this many sigma
FINE_COST_SAMPLES = 3  # ... or at least +- this many search-grid samples
FINE_COST_MAX_SAMPLES = 50_000
GLS_WINDOWS = False  # GLS also in each drift window
ACCEL_AIDED = True  # gyro + accelerometer residuals in the final GLS when both units have accelerometers
ACCEL_GLS_PASSES = 2  # accelerometer-aided passes (the 6-channel cross-spectrum re-estimated before each)
ACCEL_MIN_SIGMA_S = 1e-4  # ... and when the gyro-only sigma is above this (below it they cannot matter)
FLEX_SS = True  # Kalman (state-space flexure model) whitening after the spectral GLS, see _refine_flex
FLEX_AGREE_SIGMAS = 5.0  # ... farther than this many sigma from the spectral GLS, the two disagree: the
#                          fit kept has a sigma of at least FLEX_GAP_COVER x their difference
FLEX_GAP_COVER = 0.5
FLEX_WINDOWS_CHI2 = 4.0  # ... and kept unless its windows disagree beyond this (reduced chi-square) and the
#                          spectral fit's window-checked sigma is the smaller
FLEX_ITERS = 6  # profile Newton steps
FLEX_ACCEL_OWN = True  # the Kalman fit takes the accelerometers on its own delay check, whatever the spectral
#   6-channel fit decided (its coherence model of the flexure's tilt mismatched a turning car's: the aided
#   sigma no smaller, or an accelerometer delay of 3 sigma for nothing)
FLEX_REACH_MIN_S = 0.0  # the profile search may always go this far from its start (0: off. 20 ms let a
#   gently turning aircraft's Kalman fit land 1 ms from the truth, 5.7 ms from the spectral fit, and the
#   rule below then cover it; but it moved the 2014 ArduCopter's +37.3 ms shift to 38.5 ms, beyond 1 ms)
FLEX_BETA_MIN_1_S = 0.05  # a fitted flexure model correlated longer than 20 s, or of a sigma beyond FLEX_SIGMA_MAX_DEG,
FLEX_SIGMA_MAX_DEG = 1.0  # is not flexure: no Kalman candidate (seed 000: 0.05 deg at 2/s; the benchmarks 0.02-0.1 deg)
FLEX_ML_SPAN_S = 120.0  # the flexure model is fitted on at most this much of the overlap (its middle)
FLEX_ML_BLOCKS = 1500  # ... and on at most this many block samples
VELOCITY_AIDED = True  # velocity matching (logtools.latency_velocity) when both units log NED velocity,
VEL_AGREE_CHI2 = (8.8, 11.6)  # ... fused when it agrees (chi-square of (L) or (L, drift), 99.7 %) and its
#                               latency sigma is the smaller ...
VEL_FUSE_FLEXURE = True  # ... or the rate fit had to model flexure (what limits it there the velocity does not see)
VEL_FUSE_ALWAYS = False  # whatever the sigmas (measured worse: on smooth motion the rate fit's window-inflated
#                          drift sigma is conservative and would hand the drift to the velocity)
ACCEL_LAG_SIGMAS = 3.0  # ... unless the accelerometers' own delay differs from the gyros' by more sigmas
ACCEL_LAG_FREE = True  # ... and then an aided fit with that delay as a further unknown, rather than the gyros
#   alone (a ship with flexure: gyros alone 2.4 ms sigma, the accelerometers' delay solved 0.3 ms, with them
#   assumed on the gyros' delay 0.14-0.26 ms): the accelerometers still see the flexure's tilt
ACCEL_LAG_MAX_S = 0.01  # ... kept while that delay is at most this (a linearised unknown)

Progress = Callable[[float, str], None] | None


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------
def rate_from_attitude(t_s: np.ndarray, quat_wxyz: np.ndarray, *, drop_invalid: bool = False
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Body angular rate (rad/s, FRD) from body->NED quaternions by finite differences.

    ``q_{k+1} = q_k * dq``: ``w = rotvec(q_k^-1 q_{k+1}) / dt`` stamped at the interval's middle (the
    rate relative to the navigation frame; earth and transport rates, a few deg/h, are left out).
    ``drop_invalid``: NaN for the intervals that touch a frozen sample or a reset (``logtools.navcheck``:
    an EKF not yet running logs the identity; a board's first 19 s of it and a 169 deg yaw reset made a
    rate fit's cost 0.88 of the motion).
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
    if drop_invalid:
        valid, _ = output_validity(t, q)
        w[~(valid[:-1] & valid[1:])] = np.nan
    return 0.5 * (t[:-1] + t[1:]), w


def _unit_rate(log: InsLog, role: str) -> tuple[np.ndarray, np.ndarray, str]:
    name = f"{role} {log.meta.source_path or ''}".strip()
    gyro_ok = log.has_gyro and int(np.isfinite(log.gyro_rad_s()).all(axis=1).sum()) >= 20
    if gyro_ok or (log.has_gyro and not log.has_quat):
        t, w = log.t_imu_s(), log.gyro_rad_s()
        src = "gyro"
    elif log.has_quat:
        tq, q = log.quat_wxyz()
        t, w = rate_from_attitude(tq, q, drop_invalid=True)
        w = w + _nav_rate_in_body(log, t, tq, q)
        src = "attitude"
    else:
        raise AnalysisError(f"{name}: latency needs angular rate or attitude; the log has neither")
    ok = np.isfinite(t) & np.all(np.isfinite(w), axis=1)
    if ok.sum() < 20:
        raise AnalysisError(f"{name}: angular rate ({src}) has {int(ok.sum())} finite samples "
                            f"of {len(t)} (NaN-only or empty data)")
    return t, w, src


def _nav_rate_in_body(log: InsLog, t: np.ndarray, tq: np.ndarray, q: np.ndarray) -> np.ndarray:
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
class _Unit:
    name: str
    source: str  # "gyro" | "attitude"
    rate_hz: float
    native: UniformSeries  # on its own grid, low-passed
    itp: Interpolant  # continuous
    grid: UniformSeries  # on the common grid
    noise_dps: float  # white-noise level of the raw samples (deg/s per sample)


def _series_on_grid(itp: Interpolant, dt_s: float) -> UniformSeries:
    i0 = int(np.ceil(itp.t_first_s / dt_s - 1e-9))
    i1 = int(np.floor(itp.t_last_s / dt_s + 1e-9))
    t = np.arange(i0, i1 + 1) * dt_s
    v, ok = itp(t)
    v = np.where(ok[:, None], v, 0.0)
    return UniformSeries(i0, dt_s, v, ok, itp.series.warnings, itp.series.gaps_s)


def _uniform_native(t: np.ndarray, w: np.ndarray, name: str) -> tuple[UniformSeries, float]:
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


def _signal_band_hz(nat: UniformSeries, noise_rad_s: float) -> float:
    """Frequency below which 99.5 % of the motion power (PSD above 3x the white-noise floor) lies."""
    from scipy.signal import welch

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
    f, p = welch(v - v.mean(axis=0), fs=fs, nperseg=nper, axis=0)
    p = p.sum(axis=1)
    n0 = 3.0 * 3.0 * 2.0 * noise_rad_s ** 2 / fs  # 3x the one-sided white-noise PSD of 3 axes
    ex = np.clip(p - n0, 0.0, None)
    tot = ex.sum()
    if not tot > 0:
        return 0.4 * fs
    return float(f[min(len(f) - 1, int(np.searchsorted(np.cumsum(ex), 0.995 * tot)))])


def _make_unit(nat: UniformSeries, noise: float, src: str, name: str, rate: float, dt_c: float,
               cutoff_hz: float) -> _Unit:
    lp = lowpass(nat, cutoff_hz)
    itp = interpolant(lp)
    grid = _series_on_grid(itp, dt_c)
    return _Unit(name, src, rate, lp, itp, grid, float(np.degrees(noise)))


# ---------------------------------------------------------------------------------------------
# FFT machinery: correlations of masked series on a common grid
# ---------------------------------------------------------------------------------------------
class _Correlator:
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


def _norm_xcorr(m: UniformSeries, s: UniformSeries, lags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pearson correlation of |w| at each lag over the overlap (mean removed per lag), and counts."""
    c = _Correlator(m, s)
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


def _kabsch(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R maximising tr(R M) for M = sum a b^T (so that b ~ R a); batched. Returns (R, max value)."""
    U, S, Vt = np.linalg.svd(M)
    det = np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2))
    D = np.ones(S.shape)
    D[..., 2] = np.sign(det + (det == 0))
    R = np.swapaxes(Vt, -1, -2) @ (D[..., :, None] * np.swapaxes(U, -1, -2))
    return R, np.sum(S * D, axis=-1)


@dataclass(frozen=True)
class _VectorCost:
    lags: np.ndarray  # grid steps
    cost: np.ndarray  # normalised: (C_aa + C_bb - 2 max tr(R M)) / (C_aa + C_bb), in [0, 2]; NaN off-range
    count: np.ndarray
    R: np.ndarray  # (L, 3, 3)


def _vector_cost(m: UniformSeries, s: UniformSeries, lags: np.ndarray, min_count: float) -> _VectorCost:
    """Rotation- and bias-solved full-vector cost at every integer lag (18 FFT correlations)."""
    c = _Correlator(m, s)
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
    R, best = _kabsch(M)
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = (caa + cbb - 2.0 * best) / (caa + cbb)
    cost[~good | ~(caa + cbb > 0)] = np.nan
    return _VectorCost(lags, cost, n, R)


def _parabolic(y: np.ndarray, i: int) -> float:
    """Vertex offset (in steps, within +-0.5) of the parabola through y[i-1], y[i], y[i+1]."""
    if i <= 0 or i >= len(y) - 1 or not np.all(np.isfinite(y[i - 1:i + 2])):
        return 0.0
    den = y[i - 1] - 2 * y[i] + y[i + 1]
    return float(np.clip(0.5 * (y[i - 1] - y[i + 1]) / den, -0.5, 0.5)) if den != 0 else 0.0


def _local_minima(y: np.ndarray) -> np.ndarray:
    f = np.where(np.isfinite(y), y, np.inf)
    i = np.arange(1, len(f) - 1)
    return i[(f[i] <= f[i - 1]) & (f[i] < f[i + 1]) & np.isfinite(f[i])]


# ---------------------------------------------------------------------------------------------
# continuous refinement
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Fit:
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
    model_gap_s: float = 0.0  # |spectral - Kalman| latency when the two fits disagree (FLEX_AGREE_SIGMAS)


def _kabsch_bias(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    M = (a - ma).T @ (b - mb)
    R, _ = _kabsch(M)
    return R, mb - R @ ma


def _jacobian(bd: np.ndarray, tu: np.ndarray | None, Ra: np.ndarray) -> np.ndarray:
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


def _residual(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, f: _Fit,
              t_mid: float) -> np.ndarray:
    """Residuals (N, 3) of a fit on the refinement grid; 0 where masked."""
    bv, ok = itp(t_m + f.latency_s + f.drift * (t_m - t_mid))
    r = bv - a @ f.R.T - f.bias
    r[~(ok & valid)] = 0.0
    return r


def _best_cutoff(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, r: np.ndarray, dt_s: float,
                 cutoff_hz: float, overlap_s: float) -> float:
    """Cutoff fc minimising the predicted variance of a least-squares delay on signals band-limited
    at fc: var(fc) ~ sum_{f<fc} w^2 S N / (sum_{f<fc} w^2 S)^2 (S: master rate PSD, N: residual PSD)."""
    if len(r) < 256:
        return cutoff_hz
    # periodograms over the whole overlap (the motion may be slower than any Welch segment); the
    # noise spectrum smoothed over a few bins
    am = np.where(valid[:, None], a - a[valid].mean(axis=0), 0.0)
    f = sfft.rfftfreq(len(r), dt_s)
    S = np.sum(np.abs(sfft.rfft(am, axis=0)) ** 2, axis=1)
    N = np.sum(np.abs(sfft.rfft(r, axis=0)) ** 2, axis=1)
    k = 9
    N = np.convolve(np.pad(N, k // 2, mode="edge"), np.ones(k) / k, mode="valid")
    w2s = (2 * np.pi * f) ** 2 * S
    num = np.cumsum(w2s * N)
    den = np.cumsum(w2s)
    f_min = max(MIN_ADAPT_CUTOFF_HZ, MIN_ADAPT_CYCLES / max(overlap_s, 1.0))
    cand = (f >= f_min) & (f <= cutoff_hz) & (den > 0)
    if not cand.any():
        return cutoff_hz
    var = np.where(cand, num / np.where(den > 0, den, 1.0) ** 2, np.inf)
    k = int(np.argmin(var))
    # keep the full band unless narrowing gains clearly (>20 % in sigma)
    full = np.flatnonzero(cand)[-1]
    if not var[k] < ADAPT_GAIN * var[full]:
        return cutoff_hz
    return float(min(cutoff_hz, 1.25 * f[k]))


def _refiltered_ctx(ctx: "_Ctx", cutoff_hz: float) -> "_Ctx":
    """The units low-passed again (zero-phase) from their raw series at a new cutoff."""
    from dataclasses import replace as _rep

    units = []
    for u, nat in zip((ctx.master, ctx.slave), ctx.raw):
        lp = lowpass(nat, cutoff_hz)
        itp = interpolant(lp)
        units.append(_rep(u, native=lp, itp=itp, grid=_series_on_grid(itp, ctx.dt_s)))
    return _rep(ctx, master=units[0], slave=units[1], cutoff_hz=cutoff_hz, adapted_cutoff=True)


def _residuals(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d: float, dr: float,
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
    R, bias = _kabsch_bias(au, bu)
    r = bu - au @ R.T - bias
    return bd, au, tu, R, bias, r, float(np.sum(r * r)), use


def _refine(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d0: float,
            drift0: float, t_mid: float, *, fit_drift: bool, iters: int = 12) -> _Fit:
    """Gauss-Newton on (L[, drift]) with R, b re-solved (Kabsch with means) at every step, the delay's
    gradient and curvature from the cleaner unit's derivative (``latency_gls.delay_normal``); covariance of
    the joint (L, drift, rotation, bias) problem with a HAC score variance."""
    d, dr = float(d0), float(drift0)
    dt = float(np.median(np.diff(t_m))) if len(t_m) > 1 else 1.0
    tt = t_m - t_mid
    ad, okd = grid_derivative(a, valid, dt)  # the master's derivative (delay_normal)

    def master_derivative(bd: np.ndarray, use: np.ndarray, R: np.ndarray) -> np.ndarray:
        """R a' at the used rows (the slave's derivative where the master's does not hold)."""
        return np.where(okd[use][:, None], ad[use] @ R.T, bd)

    prev = np.inf
    for _ in range(iters):
        ev = _residuals(t_m, a, valid, itp, d, dr, tt)
        if isinstance(ev, int):
            return _Fit(d, dr, np.eye(3), np.zeros(3), np.inf, np.inf, np.nan, ev, 1.0, 0.0, False)
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
            return _Fit(d, dr, R, bias, np.inf, np.inf, np.sqrt(cost / max(1, r.size)), len(au), 1.0, 0.0, False)
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
    ev = _residuals(t_m, a, valid, itp, d, dr, tt)
    if isinstance(ev, int):
        return _Fit(d, dr, np.eye(3), np.zeros(3), np.inf, np.inf, np.nan, ev, 1.0, 0.0, False)
    bd, au, tu, R, bias, r, cost, use = ev
    Jfull = _jacobian(bd, tu if fit_drift else None, au @ R.T)
    Jm = _jacobian(master_derivative(bd, use, R), tu if fit_drift else None, au @ R.T)
    rr = r.ravel()
    Nm, _, master = delay_normal(Jfull, Jm[:, :nd], rr)
    if not master:
        Jm = Jfull
    try:
        Ninv = np.linalg.inv(Nm)
    except np.linalg.LinAlgError:
        return _Fit(d, dr, R, bias, np.inf, np.inf, np.sqrt(cost / max(1, r.size)), len(au), 1.0, 0.0, False)
    # per-sample scores from the derivative the step took (a noisy slave's: products with the residual
    # that cancel only over long lags; a HAC of them was 100x too large)
    G = (Jm * rr[:, None]).reshape(len(r), 3, -1).sum(axis=1)
    u = G @ Ninv[:, :nd]  # contributions to the (L, drift) step
    max_h = int(min(len(u) // 4, max(10, 20.0 / dt)))
    V_hac, _H = hac_cov(u, max_h)
    dof = max(1, r.size - Nm.shape[0])
    s2 = cost / dof
    var_cls = s2 * np.diag(Ninv)[:nd]
    var_h = np.diag(V_hac)
    var = np.maximum(np.maximum(var_h, 0.25 * var_cls), var_cls)
    corr = 0.0
    if fit_drift and var_h[0] > 0 and var_h[1] > 0:
        corr = float(np.clip(V_hac[0, 1] / np.sqrt(var_h[0] * var_h[1]), -0.99, 0.99))
    fac = float(var[0] / var_cls[0]) if var_cls[0] > 0 else 1.0
    motion = float(np.sqrt(np.mean(np.sum((au - au.mean(axis=0)) ** 2, axis=1))))
    return _Fit(d, dr, R, bias, float(np.sqrt(var[0])), float(np.sqrt(var[1])) if fit_drift else 0.0,
                float(np.sqrt(cost / r.size)), len(au), fac, motion, corr_ld=corr)


# ---------------------------------------------------------------------------------------------
# generalised least squares: the residual's spectrum (flexure, noise) whitened
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Accel:
    """Both units' specific force (low-passed like the rates) and the master's rate, continuous: the
    accelerometer rows of the accelerometer-aided fit (``f_s(t + d) = R (f_m + (w_m' x + [w_m x]^2) r)
    + b_a``, r the lever arm in the master frame)."""

    master: Interpolant
    slave: Interpolant
    master_rate: Interpolant
    lag_free: bool = False  # the accelerometers' own delay an unknown of the fit (else the model check)

    def master_rows(self, t_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(f_m, lever-arm matrix [w' x] + [w x]^2 (n, 3, 3), ok) at the master instants t_m."""
        f, okf = self.master(t_m)
        w, okw = self.master_rate(t_m)
        ok = okf & okw
        wd = np.zeros_like(w)
        if ok.any():
            wd[ok], _ = self.master_rate(t_m[ok], 1)
        f, w = np.where(ok[:, None], f, 0.0), np.where(ok[:, None], w, 0.0)
        sw = skew(w)
        return f, skew(wd) + sw @ sw, ok


def _lever_solve(r_a: np.ndarray, Jl: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Accelerometer residuals (n, 3) with the lever arm (Jacobian Jl (n, 3, 3)) and the accelerometer
    bias solved by ordinary least squares over the used rows (0 elsewhere)."""
    ru, Ju = r_a[use], Jl[use]
    Ju = Ju - Ju.mean(axis=0)
    ru = ru - ru.mean(axis=0)
    A = Ju.reshape(-1, Ju.shape[2])
    x, *_ = np.linalg.lstsq(A, ru.ravel(), rcond=None)
    out = np.zeros_like(r_a)
    out[use] = ru - (A @ x).reshape(-1, 3)
    return out


def _lever_jacobian(R: np.ndarray, lev: np.ndarray) -> np.ndarray:
    """(n, 3, 3) derivative of the accelerometer residual w.r.t. the lever arm (master frame)."""
    return -np.einsum("ij,njk->nik", R, lev)


def _accel_residual(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, acc: _Accel,
                    f: _Fit, t_mid: float) -> np.ndarray:
    """(N, 6) gyro and accelerometer residuals of a fit (lever arm and biases by least squares), 0 where
    masked: what the accelerometer-aided noise model is estimated from."""
    tau = t_m + f.latency_s + f.drift * (t_m - t_mid)
    fv, okf = acc.slave(tau)
    fm, lev, okm = acc.master_rows(t_m)
    use = itp.ok(tau) & okf & okm & valid
    out = np.zeros((len(t_m), 6))
    if use.sum() < 20:
        return out
    out[:, :3] = np.where(use[:, None], _residual(t_m, a, valid, itp, f, t_mid), 0.0)
    r_a = np.where(use[:, None], fv - fm @ f.R.T, 0.0)
    Jl = _lever_jacobian(f.R, lev)
    if acc.lag_free:  # the accelerometers' own delay solved too
        fd = np.zeros_like(fv)
        fd[use], _ = acc.slave(tau[use], 1)
        Jl = np.concatenate([Jl, fd[:, :, None]], axis=2)
    out[:, 3:] = _lever_solve(r_a, Jl, use)
    return out


def _flexure_like(model: FlexureModel) -> bool:
    """A fitted model that describes a structure's flexure: correlated over less than 1 / FLEX_BETA_MIN_1_S and
    within FLEX_SIGMA_MAX_DEG. Beyond, the residual is something else the model bends to (an attitude-only
    slave with jittered stamps: its rates' noise, proportional to the rate, came out as a 14 deg "flexure"
    of beta 0.013/s, the fit 3 ms off at a sigma of 0.6 ms and the velocity, right to 0.01 ms, left out)."""
    return bool(model.beta_1_s >= FLEX_BETA_MIN_1_S and np.degrees(np.max(model.sigma_rad)) <= FLEX_SIGMA_MAX_DEG)


def _n_check(acc: _Accel | None) -> int:
    """Trailing model-check columns of an aided fit's Jacobian: the accelerometers' own delay, checked
    (1) or an unknown of the fit (0: ``acc.lag_free``)."""
    return 0 if acc is None or acc.lag_free else 1


def _gls_use(t_m: np.ndarray, valid: np.ndarray, itp: Interpolant, lag: np.ndarray, margin: float,
             acc: _Accel | None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The samples a fit uses, fixed for all its iterations (slave data within +- margin of the lag
    everywhere), and with ``acc`` the master's accelerometer rows (f_m, lever-arm matrix) at t_m."""
    use = valid & itp.ok(t_m + lag - margin) & itp.ok(t_m + lag + margin)
    fm = lev = None
    if acc is not None:
        fm, lev, okm = acc.master_rows(t_m)
        use &= okm & acc.slave.ok(t_m + lag - margin) & acc.slave.ok(t_m + lag + margin)
    return use, fm, lev


def _gls_system(t_m: np.ndarray, a: np.ndarray, use: np.ndarray, itp: Interpolant, d: float, dr: float,
                tt: np.ndarray, fit_drift: bool, acc: _Accel | None, fm: np.ndarray | None,
                lev: np.ndarray | None, *, jacobian: bool = True) -> tuple | None:
    """Residuals r (n, C) and Jacobian J (n, C, P [+ 1]) of the joint fit at (d, dr), R and the gyro bias
    re-solved (Kabsch), 0 outside ``use``; C = 3 (gyros) or 6 (with ``acc``: accelerometer rows, their
    bias and the lever arm as further unknowns, and a trailing column for the accelerometers' own delay,
    the model check). Also the slave's specific force at the delayed instants (None without ``acc``) and
    Dm (n, C, nd): the delay's [and drift's] columns from the model's derivative, for the curvature
    (``latency_gls.delay_normal``). None when a used sample falls off the slave's data. Without ``jacobian``:
    (r, None, R, bias, fv, None)."""
    n = len(t_m)
    C = 3 if acc is None else 6
    nd = 1 + int(fit_drift)
    tau = t_m + d + dr * tt
    bv, ok = itp(tau)
    if not np.all(ok[use]):
        return None
    R, bias = _kabsch_bias(a[use], bv[use])
    r = np.zeros((n, C))
    r[use, :3] = bv[use] - a[use] @ R.T - bias
    fv = Rf = None
    if acc is not None:
        fv, _ = acc.slave(tau)
        Rf = np.where(use[:, None], fm @ R.T, 0.0)
        r[use, 3:] = fv[use] - Rf[use] - np.mean(fv[use] - Rf[use], axis=0)
    if not jacobian:
        return r, None, R, bias, fv, None
    bd = np.zeros((n, 3))
    bd[use], _ = itp(tau[use], 1)
    Ra = np.where(use[:, None], a @ R.T, 0.0)
    Jg = _jacobian(bd, tt if fit_drift else None, Ra).reshape(n, 3, -1)
    dt = float(t_m[1] - t_m[0]) if n > 1 else 1.0
    md, okd = grid_derivative(Ra, use, dt)
    Dm = np.zeros((n, C, nd))
    Dm[:, :3, 0] = np.where(okd[:, None], md, bd)
    if acc is None:
        J = Jg
    else:
        fd = np.zeros((n, 3))
        fd[use], _ = acc.slave(tau[use], 1)
        Ja = _jacobian(fd, tt if fit_drift else None, Rf).reshape(n, 3, -1)
        # the accelerometers' model, lever arm included (least squares here): the master's side
        Jl = _lever_jacobian(R, lev)
        model_a = np.where(use[:, None], fv - _lever_solve(r[:, 3:], Jl, use), 0.0)
        fmd, okf = grid_derivative(model_a, use, dt)
        Dm[:, 3:, 0] = np.where(okf[:, None], fmd, fd)
        pg = Jg.shape[2]  # L[, drift], rotation, gyro bias | accelerometer bias, lever arm
        J = np.zeros((n, 6, pg + 7))
        J[:, :3, :pg] = Jg
        J[:, 3:, :nd + 3] = Ja[:, :, :nd + 3]
        J[:, 3:, pg:pg + 3] = Ja[:, :, nd + 3:]
        J[:, 3:, pg + 3:pg + 6] = Jl
        J[:, 3:, pg + 6] = fd  # a delay of the accelerometers' own (model check, not in the steps)
    if fit_drift:
        Dm[:, :, 1] = Dm[:, :, 0] * tt[:, None]
    J[~use] = 0.0
    Dm[~use] = 0.0
    return r, J, R, bias, fv, Dm


def _fit_start(t_m: np.ndarray, t_mid: float, d0: float, drift0: float
               ) -> tuple[float, float, float, np.ndarray, float, _Fit]:
    """(d, drift, sample interval, t - t_mid, half span, the failed fit) at the start of a refinement."""
    d, dr = float(d0), float(drift0)
    dt = float(np.median(np.diff(t_m))) if len(t_m) > 1 else 1.0
    tt = t_m - t_mid
    span = float(np.max(np.abs(tt))) if len(t_m) else 0.0
    return d, dr, dt, tt, span, _Fit(d, dr, np.eye(3), np.zeros(3), np.inf, np.inf, np.nan, 0, 1.0, 0.0, False)


def _motion_rms(a: np.ndarray, use: np.ndarray) -> float:
    """RMS of the master's rate about its mean over the used samples (rad/s)."""
    au = a[use]
    return float(np.sqrt(np.mean(np.sum((au - au.mean(axis=0)) ** 2, axis=1))))


def _refine_gls(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d0: float,
                drift0: float, t_mid: float, noise: NoiseModel, *, fit_drift: bool, iters: int = 4,
                acc: _Accel | None = None) -> _Fit:
    """Generalised least squares: Gauss-Newton on the whitened residual and whitened Jacobian of the
    joint (L[, drift], rotation, bias) problem; the L[, drift] part of each step is taken and R, b
    re-solved (Kabsch), whose fixed point is the joint GLS estimate. Covariance: the whitened
    curvature times the whitened residual variance (HAC-checked).

    With ``acc`` (and a 6-channel cross-spectral ``noise``), the accelerometers' residuals join the
    gyros' (accelerometer bias and lever arm as further linear unknowns, the rotation shared): the
    whitening then uses their coherence, i.e. the flexure seen as a tilt of the specific force is
    taken out of the differential rate, and the specific force's own motion adds delay information."""
    d, dr, dt, tt, span, fail = _fit_start(t_m, t_mid, d0, drift0)
    n, nd = len(t_m), 1 + int(fit_drift)
    # the samples used are fixed for all iterations (no sample switches in or out with d: a switch is
    # a step the whitening filter would amplify), and tapered at their ends and around gaps
    margin = (iters + 1) * dt  # the steps are clipped to 0.5 dt (latency) + 0.5 dt at the ends (drift)
    use, fm, lev = _gls_use(t_m, valid, itp, d + dr * tt, margin, acc)
    if use.sum() < 20:
        return fail
    C = 3 if acc is None else 6
    taper = end_taper(use, int(np.ceil(GLS_TAPER_S / dt)))
    wts = noise.weights(n, dt)
    for it in range(iters + 1):
        sysm = _gls_system(t_m, a, use, itp, d, dr, tt, fit_drift, acc, fm, lev)
        if sysm is None:
            return fail
        r, J, R, bias, _fv, Dm = sysm
        n_check = _n_check(acc)  # trailing columns only for the model check, not in the steps
        P = J.shape[2] - n_check
        r = r * taper[:, None]
        J = J * taper[:, None, None]
        Dm = Dm * taper[:, None, None]
        X = np.concatenate([r[:, :, None], J, Dm], axis=2)  # (n, C, 1 + P + n_check + nd)
        if noise.psd.ndim == 1:
            Z = noise.whiten(X.reshape(n, -1), dt, wts).reshape(X.shape)
        else:
            Z = noise.whiten(X, dt, wts)
        rw = Z[:, :, 0]
        Jx = Z[:, :, 1:1 + P + n_check].reshape(C * n, P + n_check) if n_check else None
        Jw = Z[:, :, 1:P + 1]
        Jf = Jw.reshape(C * n, P)
        Dw = Z[:, :, 1 + P + n_check:].reshape(C * n, nd)
        Nm, g, master = delay_normal(Jf, Dw, rw.ravel())
        if not master:  # the ordinary Gauss-Newton step: its scores too
            Dw = Jf[:, :nd]
        try:
            step = -np.linalg.solve(Nm, g)
        except np.linalg.LinAlgError:
            return fail
        if it == iters:
            break
        sd, sdr = delay_step(step, dt, span, fit_drift)
        d, dr = d + sd, dr + sdr
        if abs(sd) < 1e-4 * dt:
            # one more pass for the covariance at the solution
            iters = it + 1
    try:
        Ninv = np.linalg.inv(Nm)
    except np.linalg.LinAlgError:
        return fail
    # the residual after the last step (the linear unknowns -- rotation, biases, lever arm -- at their
    # GLS values rather than the re-solved ones): what the variance and the scores are taken from
    rw = rw + (Jf @ step).reshape(n, C)
    n_use = int(use.sum())
    dof = max(1, C * n_use - P)
    s2 = float(np.sum(rw * rw)) / dof
    # per-sample whitened scores, the delay's [drift's] from the master's derivative (as in _refine)
    Js = np.concatenate([Dw.reshape(n, C, nd), Jw[:, :, nd:]], axis=2)
    u = np.sum(Js * rw[:, :, None], axis=1) @ Ninv[:, :nd]
    # model check: the accelerometers' delay relative to the gyros' (0 when both come through the same
    # path; real IMUs may filter them differently), from the augmented normal equations
    check = None if not n_check else (Jx.T @ Jx, Jx.T @ rw.ravel())
    var, corr, fac, acc_lag = gls_covariance(Ninv, s2, u, dt, fit_drift, check=check,
                                             free_step=step if acc is not None and acc.lag_free else None)
    motion = _motion_rms(a, use)
    raw_rms = float(np.sqrt(np.sum(r[:, :3] ** 2) / (3 * n_use)))
    return _Fit(d, dr, R, bias, float(np.sqrt(var[0])), float(np.sqrt(var[1])) if fit_drift else 0.0,
                raw_rms, n_use, fac, motion, corr_ld=corr, accel_lag_s=acc_lag,
                accel_lag_free=acc is not None and acc.lag_free)


def _refine_flex(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d0: float,
                 drift0: float, t_mid: float, cutoff_hz: float, *, fit_drift: bool, acc: _Accel | None = None,
                 model: FlexureModel | None = None, h0: float = 0.0, iters: int = FLEX_ITERS) -> _Fit:
    """Generalised least squares as ``_refine_gls``, whitened by a Kalman filter of seed 000's flexure
    model (``logtools.latency_flexure``) instead of a residual spectrum. The rows are block-averaged to
    DECIMATE_FACTOR x the cutoff; the model's parameters are fitted by restricted maximum likelihood at
    the start (on at most FLEX_ML_SPAN_S of blocks; unless ``model`` is given, e.g. for the drift windows).

    The delay is then found on the profile of the whitened cost (every other unknown -- drift, rotation,
    biases, lever arm -- concentrated out, linearised): Newton steps on a parabola through three cost
    evaluations (d - h, d, d + h), not Gauss-Newton steps on the Jacobian alone: the Kalman whitening
    weighs the fine structure of the signals heavily, where the slave's derivative is mostly its noise's,
    and the Gauss-Newton curvature exceeded the cost's own several times over. The drift's step and the
    covariance take the delay's [drift's] gradient and curvature from the master's derivative
    (``latency_gls.delay_normal``; stepping the delay that way too left a 30 s flexing ship's windows
    unchecked, z 3.6). The sigma is the larger of the profile's and the Gauss-Newton/HAC one. ``h0``:
    the first half-width (e.g. the spectral sigma)."""
    d, dr, dt, tt, span, fail = _fit_start(t_m, t_mid, d0, drift0)
    nd = 1 + int(fit_drift)
    h = float(np.clip(h0 if h0 > 0 else 0.05 * dt, 1e-3 * dt, 0.5 * dt))
    # how far the search may go: a few of its steps (at least FLEX_REACH_MIN_S; the spectral sigma it starts
    # from is optimistic exactly where this fit matters: a gently turning aircraft's Kalman fit walked 5.7 ms
    # from a spectral fit of sigma 0.13 ms, past 4 x 0.13 x 6 = 3.1 ms, and failed)
    reach = max(4.0 * h * iters, FLEX_REACH_MIN_S)
    use, fm, lev = _gls_use(t_m, valid, itp, d + dr * tt, reach + h + 2 * dt, acc)
    k = max(1, int(round(1.0 / (DECIMATE_FACTOR * cutoff_hz * dt))))
    if use.sum() < 20 * k:
        return fail
    C = 3 if acc is None else 6
    n_check = _n_check(acc)

    def blocks(x: np.ndarray) -> np.ndarray:
        return block_mean(np.where(use.reshape((-1,) + (1,) * (x.ndim - 1)), x, 0.0), use, k)[0]

    def system(dd: float, rr: float, jac: bool = True):
        """Block rows at (dd, rr): (X (nb, C, 1 [+ P + check]), used blocks, fs, ws, r, R, bias) or None."""
        sysm = _gls_system(t_m, a, use, itp, dd, rr, tt, fit_drift, acc, fm, lev, jacobian=jac)
        if sysm is None:
            return None
        r, J, R, bias, fv, Dm = sysm
        Xb, ub = block_mean(r[:, :, None] if J is None else np.concatenate([r[:, :, None], J, Dm], axis=2), use, k)
        fb = None if fv is None else blocks(fv)
        wb = blocks(r[:, :3] + a @ R.T + bias)  # the slave's rate
        return Xb, ub, fb, wb, r, R, bias

    sy = system(d, dr)
    if sy is None:
        return fail
    Xb, ub, fb, wb = sy[:4]
    P = Xb.shape[2] - 1 - n_check - nd
    if model is None:
        span_ml = min(FLEX_ML_SPAN_S, FLEX_ML_BLOCKS * k * dt)
        cen = np.abs((np.arange(len(ub)) + 0.5) * k * dt + t_m[0] - t_mid) <= 0.5 * span_ml
        # the model's likelihood without the accelerometers' own delay where it is an unknown (lag_free):
        # a flexure large enough to whiten the gyro rows away leaves the delay's accelerometer part and that
        # column alike, and the restricted likelihood's log det term then pulled the fit into that corner
        pm = P - int(acc is not None and acc.lag_free)
        model = fit_model(Xb[cen][:, :, :1 + pm], wb[cen], None if fb is None else fb[cen], ub[cen], k * dt, pm)
        if model is None or not _flexure_like(model):
            return fail
    # whitened columns: 3 residuals (at d - h, d, d + h; the Jacobian shared) then the Jacobian
    jc = list(range(3, 3 + P))  # the fit's unknowns (delay first)
    pc = jc[1:]  # ... all but the delay (the profile)
    dc = list(range(3 + P + n_check, 3 + P + n_check + nd))  # the delay's [drift's] columns, master side

    def profile(M: np.ndarray, col: int) -> float:
        s_ = M[pc, col]
        return float(M[col, col] - s_ @ np.linalg.solve(M[np.ix_(pc, pc)], s_))

    curv = 0.0
    at = (d, dr)  # where sy was evaluated
    for it in range(iters + 1):
        if (d, dr) != at:
            sy, at = system(d, dr), (d, dr)
        sp, sm = system(d + h, dr, False), system(d - h, dr, False)
        if sy is None or sp is None or sm is None:
            return fail
        Y = np.concatenate([sm[0], sy[0][:, :, :1], sp[0], sy[0][:, :, 1:]], axis=2)
        W, M, _ = whitened_normal(Y, sy[3], sy[2], sy[1], model, store=it == iters)
        try:
            cm, c0, cp = (profile(M, j) for j in range(3))
            # the GLS step, its delay's gradient and curvature from the cleaner derivative (delay_normal)
            Nj, g, _ = delay_system(M[np.ix_(jc, jc)], M[np.ix_(jc, dc)], M[np.ix_(dc, dc)], M[jc, 1], M[dc, 1])
            stp = -np.linalg.solve(Nj, g)
        except np.linalg.LinAlgError:
            return fail
        curv_h = (cp + cm - 2.0 * c0) / (2.0 * h * h)
        if it == iters:
            if curv_h > 0:
                curv = curv_h
            break
        if not curv_h > 0:
            h = min(2.0 * h, 0.5 * dt)
            continue
        curv = curv_h
        step = float(np.clip(-(cp - cm) / (2.0 * h) / (2.0 * curv), -3.0 * h, 3.0 * h))
        d += step
        if fit_drift:
            dr += float(np.clip(stp[1], -0.5 * dt / max(span, 1e-9), 0.5 * dt / max(span, 1e-9)))
        if abs(d - d0) > reach:
            return fail
        h = float(np.clip(np.sqrt(1.0 / curv), 1e-3 * dt, 0.5 * dt))  # the next bracket: ~1 sigma
        if abs(step) < 0.05 * h:
            iters = it + 1  # one more pass: the covariance and scores at the solution
    if not curv > 0:
        return fail
    # the final pass: residual column 1, the unknowns jc (+ the model check's column last)
    keep = [1] + jc + list(range(3 + P, 3 + P + n_check))
    JD, DD, gd = M[np.ix_(jc, dc)], M[np.ix_(dc, dc)], M[dc, 1]
    Wd = W[:, :, dc]
    M, W = M[np.ix_(keep, keep)], W[:, :, keep]
    ub = sy[1]
    r, R, bias = sy[4], sy[5], sy[6]
    Nm, g, master = delay_system(M[1:P + 1, 1:P + 1], JD, DD, M[1:P + 1, 0], gd)
    if not master:
        Wd = W[:, :, 1:nd + 1]
    try:
        Ninv = np.linalg.inv(Nm)
    except np.linalg.LinAlgError:
        return fail
    step = -Ninv @ g
    Wp = W[:, :, 1:P + 1]
    rw = W[:, :, 0] + Wp @ step
    nb = int(ub.sum())
    s2 = float(np.sum(rw * rw)) / max(1, C * nb - P)
    Ws = np.concatenate([Wd, Wp[:, :, nd:]], axis=2)  # the scores as in _refine_gls
    u = np.sum(Ws * rw[:, :, None], axis=1)[ub] @ Ninv[:, :nd]
    check = None if not n_check else (M[1:, 1:], M[1:, 0] + M[1:, 1:P + 1] @ step)
    # the profile's curvature floors the latency's variance (cost = sum of squares: var = s2 / curvature)
    var, corr, fac, acc_lag = gls_covariance(Ninv, s2, u, k * dt, fit_drift, check=check, var_floor=s2 / curv,
                                             free_step=step if acc is not None and acc.lag_free else None)
    motion = _motion_rms(a, use)
    raw_rms = float(np.sqrt(np.sum(r[use, :3] ** 2) / (3 * int(use.sum()))))
    return _Fit(d, dr, R, bias, float(np.sqrt(var[0])), float(np.sqrt(var[1])) if fit_drift else 0.0,
                raw_rms, int(use.sum()), fac, motion, corr_ld=corr, aided=acc is not None, accel_lag_s=acc_lag,
                flex=model, accel_lag_free=acc is not None and acc.lag_free)


# ---------------------------------------------------------------------------------------------
# the estimator
# ---------------------------------------------------------------------------------------------
@dataclass
class _Ctx:
    master: _Unit
    slave: _Unit
    dt_c: float  # common rate (the slower unit's, at most MAX_COMMON_RATE_HZ)
    cutoff_hz: float
    max_lag_s: float | None
    band_cutoff_hz: float  # the motion's band (signal/noise, the velocities' low-pass)
    dt_s: float = 0.0  # integer-lag search grid
    dt_r: float = 0.0  # continuous refinement samples (master)
    raw: tuple = ()  # (master, slave) unfiltered native uniform series (baseline method)
    adapted_cutoff: bool = False
    warnings: list[str] = field(default_factory=list)
    t0_abs_s: float = 0.0
    stamp_jitter_s: tuple[float, float] = (0.0, 0.0)  # (master, slave) white stamp noise, s
    stamp_resolution_s: tuple[float, float] = (0.0, 0.0)  # (master, slave) coarse stamp step of the rates' source
    acc_src: tuple | None = None  # (master, slave, cutoff, master rate) for the accelerometer-aided GLS
    vel_src: tuple | None = None  # (master, slave) for the velocity fit, both with NED velocity


def _prepare(master: InsLog, slave: InsLog, max_lag_s: float | None, *, accelerometers: bool = True,
             velocity: bool = True) -> _Ctx:
    if max_lag_s is not None and not (np.isfinite(max_lag_s) and max_lag_s > 0):
        raise AnalysisError(f"max_lag_s must be positive or None (whole overlap), not {max_lag_s!r}")
    slave_r = slave.rebased(master.meta.t0_ns)
    tm, wm, srcm = _unit_rate(master, "master")
    ts, ws, srcs = _unit_rate(slave_r, "slave")
    fm, fs = median_rate_hz(tm), median_rate_hz(ts)
    f_c = min(fm, fs, MAX_COMMON_RATE_HZ)
    dt_c = 1.0 / f_c
    # master and slave spans (finite samples), face value
    okm = np.all(np.isfinite(wm), axis=1) & np.isfinite(tm)
    oks = np.all(np.isfinite(ws), axis=1) & np.isfinite(ts)
    m0, m1 = float(np.min(tm[okm])), float(np.max(tm[okm]))
    s0, s1 = float(np.min(ts[oks])), float(np.max(ts[oks]))
    if min(m1 - m0, s1 - s0) < MIN_OVERLAP_S:
        raise AnalysisError(f"logs too short for a latency estimate: master {m1 - m0:.1f} s, slave "
                            f"{s1 - s0:.1f} s of angular rate (need {MIN_OVERLAP_S:g} s of overlap)")
    if max_lag_s is not None:
        ov = min(m1, s1 + max_lag_s) - max(m0, s0 - max_lag_s)
        if ov < MIN_OVERLAP_S:
            raise AnalysisError(
                f"no overlap between master [{m0 + master.t0_s:.3f}, {m1 + master.t0_s:.3f}] s and slave "
                f"[{s0 + master.t0_s:.3f}, {s1 + master.t0_s:.3f}] s within +-{max_lag_s:g} s at face value "
                f"(clocks unrelated? use --max-lag auto)")
    natm, nm = _uniform_native(tm, wm, "master")
    nats, ns = _uniform_native(ts, ws, "slave")
    # zero-phase low-pass of both units at the same cutoff: a few times the motion's band (the noise
    # between the motion's band and Nyquist would otherwise bias a spline-interpolated sub-sample delay)
    band = (min if BAND_COMMON else max)(_signal_band_hz(natm, nm), _signal_band_hz(nats, ns))
    floor = min(MIN_CUTOFF_HZ, max(BAND_MIN_CUTOFF_HZ, MIN_CUTOFF_FRACTION * f_c))
    cutoff = float(np.clip(3.0 * band, floor, CUTOFF_FRACTION * f_c))
    band_cutoff = float(np.clip(3.0 * band, BAND_MIN_CUTOFF_HZ, CUTOFF_FRACTION * f_c))
    # both units are band-limited at the cutoff: refinement samples at 5x the cutoff carry all the
    # information (a denser grid only costs time; the residuals' correlation is handled by the HAC)
    f_r = min(f_c, max(5.0 * cutoff, 20.0))
    f_s = min(f_r, MAX_COARSE_RATE_HZ)
    um = _make_unit(natm, nm, srcm, "master", fm, 1.0 / f_s, cutoff)
    us = _make_unit(nats, ns, srcs, "slave", fs, 1.0 / f_s, cutoff)
    ctx = _Ctx(um, us, dt_c, cutoff, max_lag_s, band_cutoff_hz=band_cutoff, t0_abs_s=master.t0_s,
               dt_s=1.0 / f_s, dt_r=1.0 / f_r,
               raw=(natm, nats), stamp_jitter_s=(stamp_noise_s(tm), stamp_noise_s(ts)),
               stamp_resolution_s=(master.stamp_resolution_s("gyro" if srcm == "gyro" else "att"),
                                   slave.stamp_resolution_s("gyro" if srcs == "gyro" else "att")))
    ctx.warnings += list(um.native.warnings) + list(us.native.warnings)
    if (accelerometers and ACCEL_AIDED and srcm == "gyro" and srcs == "gyro" and master.has_accel
            and slave_r.has_accel):
        ctx.acc_src = (master, slave_r, cutoff, um.itp)  # built when needed (_accel_pair)
    if velocity and VELOCITY_AIDED and master.has_vel and slave_r.has_vel:
        ctx.vel_src = (master, slave_r)  # built when needed (_velocity_step)
    for role, q in zip(("master", "slave"), ctx.stamp_resolution_s):
        if q > 0:
            ctx.warnings.append(f"{role} stamps are whole multiples of {q * 1e3:g} ms: the latency's sigma is "
                                f"at least {q / np.sqrt(12.0) * 1e3:.3g} ms (a fixed sampling phase offsets "
                                f"every stamp alike)")
    if srcm == "attitude" or srcs == "attitude":
        ctx.warnings.append("angular rate derived from attitude for the " +
                            " and ".join(r for r, s in (("master", srcm), ("slave", srcs)) if s == "attitude"))
    for role, src, w in (("master", srcm, wm), ("slave", srcs, ws)):
        n_bad = int(np.sum(~np.all(np.isfinite(w), axis=1))) if src == "attitude" else 0
        if n_bad:
            ctx.warnings.append(f"{role}: {n_bad} of {len(w)} attitude intervals frozen (an EKF not running) or "
                                f"at a reset left out of the rates")
    return ctx


def _accel_pair(master: InsLog, slave: InsLog, cutoff_hz: float, master_rate: Interpolant) -> _Accel | None:
    """Both units' specific force, uniform and low-passed at the rates' cutoff; None when either unit
    has no (or too little finite) accelerometer data."""
    itps = []
    for log, role in ((master, "master"), (slave, "slave")):
        if not log.has_accel:
            return None
        t, f = log.t_imu_s(), log.accel_m_s2()
        ok = np.isfinite(t) & np.all(np.isfinite(f), axis=1)
        if ok.sum() < 256:
            return None
        try:
            nat = to_uniform(t[ok], f[ok], name=f"{role} accelerometer")
            itps.append(interpolant(lowpass(nat, cutoff_hz)))
        except ValueError:
            return None
    return _Accel(itps[0], itps[1], master_rate)


def _jitter_sigma_s(ctx: _Ctx, w0: float, w1: float) -> float:
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


def _lag_window(ctx: _Ctx, corr: _Correlator, dt: float, min_frac: float) -> tuple[np.ndarray, float]:
    lo, hi = corr.lag_range()
    if ctx.max_lag_s is not None:
        k = int(np.floor(ctx.max_lag_s / dt + 1e-9))
        lo, hi = max(lo, -k), min(hi, k)
    lags = np.arange(lo, hi + 1)
    return lags, max(MIN_OVERLAP_S / dt, min_frac * corr.n_valid)


@dataclass(frozen=True)
class _Coarse:
    xc_lags_s: np.ndarray
    xc_rho: np.ndarray
    xcorr_latency_s: float
    xcorr_peak: float
    vc: _VectorCost
    dt_s: float  # coarse grid step
    d0_s: float  # coarse full-vector estimate (parabolic)
    best_cost: float
    alternatives_s: tuple[float, ...]  # near-equal other minima (periodic motion)
    alt_costs: tuple[float, ...]


def _coarse(ctx: _Ctx) -> _Coarse:
    m, s = ctx.master.grid, ctx.slave.grid
    dt = m.dt_s
    if len(m.values) < 10 or len(s.values) < 10:
        raise AnalysisError("too little data for a latency estimate (fewer than 10 coarse samples)")
    corr = _Correlator(m, s)
    # overlap needed at a candidate lag: half the shorter log with a bounded search, a quarter otherwise
    lags, min_count = _lag_window(ctx, corr, dt, 0.5 if ctx.max_lag_s is not None else 0.25)
    # 1) |w| normalised cross-correlation
    rho, n = _norm_xcorr(m, s, lags)
    rho[n < min_count] = np.nan
    if not np.any(np.isfinite(rho)):
        short = min(int(m.valid.sum()), int(s.valid.sum())) * dt
        hint = (f"the shorter log has {short:.1f} s of usable angular rate" if short < 2.0 * min_count * dt
                else "clocks unrelated? use --max-lag auto")
        raise AnalysisError(f"overlap shorter than {min_count * dt:.1f} s at every candidate lag ({hint})")
    ib = int(np.nanargmax(rho))
    xc_lat = (lags[ib] + _parabolic(-rho, ib)) * dt
    # 2) rotation-solved full-vector cost; in an unbounded search only around the best |w| peaks
    if ctx.max_lag_s is None and len(lags) > 4001:
        r = np.where(np.isfinite(rho), rho, -np.inf)
        pk = _local_minima(-r)
        pk = pk[np.argsort(-r[pk])][:COARSE_PEAKS] if len(pk) else np.array([ib])
        half = int(np.ceil(2.0 / dt))
        sel = np.unique(np.concatenate([np.arange(p - half, p + half + 1) for p in pk]))
        sel = sel[(sel >= 0) & (sel < len(lags))]
        vlags = lags[sel]
    else:
        vlags = lags
    vc = _vector_cost(m, s, vlags, min_count)
    if not np.any(np.isfinite(vc.cost)):
        raise AnalysisError("no lag with enough overlapping valid data")
    cost = vc.cost
    # contiguous segments only (selected lags may be disjoint): minima inside runs
    jb = int(np.nanargmin(cost))
    # periodic motion: other local minima (outside the main lobe) nearly as low
    best = float(cost[jb])
    mins = _local_minima(cost)
    lobe = _lobe_halfwidth(cost, jb)
    alts = [i for i in mins if abs(int(vlags[i]) - int(vlags[jb])) > lobe
            and cost[i] <= best + max(PERIODIC_MARGIN, PERIODIC_REL_MARGIN * best)]
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
    d0 = (vlags[jb] + (_parabolic(cost, jb) if contiguous else 0.0)) * dt
    return _Coarse(lags * dt, rho, float(xc_lat), float(rho[ib]), vc, dt, float(d0), best,
                   tuple(float(vlags[i] * dt) for i in alts), tuple(float(cost[i]) for i in alts))


def _lobe_halfwidth(cost: np.ndarray, j: int) -> int:
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


def _drift_without_windows(w0: float, w1: float) -> bool:
    """A drift is fitted over an overlap this long even without 3 drift windows (short logs, gaps): its
    sigma is then the fit's own, unchecked by windows, and the drift prior keeps an undetermined one small."""
    return DRIFT_FIT_ALWAYS and (w1 - w0) >= DRIFT_MIN_SPAN_S


def _windows(ctx: _Ctx, t0: float, t1: float, t_ok: np.ndarray | None = None) -> list[tuple[float, float]]:
    """The drift windows over [t0, t1]: about WINDOW_S each (3..MAX_WINDOWS). With ``t_ok`` (the instants
    that have data in both units) covering less than WINDOW_DATA_FRACTION of the span (gaps), windows are
    laid in the runs of data between the gaps instead (none across one), their number shared by the
    runs' lengths (runs shorter than MIN_WINDOW_S left out)."""
    T = t1 - t0
    if t_ok is not None and len(t_ok) > 1:
        d = np.diff(t_ok)
        dt = float(np.median(d))
        if len(t_ok) * dt < WINDOW_DATA_FRACTION * T:
            cut = np.flatnonzero(d > max(1.0, 10.0 * dt))
            runs = [(float(t_ok[a]), float(t_ok[b])) for a, b in
                    zip(np.concatenate([[0], cut + 1]), np.concatenate([cut, [len(t_ok) - 1]]))]
            runs = [r for r in runs if r[1] - r[0] >= MIN_WINDOW_S]
            T_ok = sum(b - a for a, b in runs)
            K = int(np.clip(np.floor(T_ok / WINDOW_S), 1, MAX_WINDOWS))
            if T_ok >= WINDOWS3_MIN_S:
                K = max(K, 3)
            K = min(K, int(sum(np.floor((b - a) / MIN_WINDOW_S) for a, b in runs)))
            if not runs or K < 1:
                return []
            # largest remainder: each run at least one window, the rest by length, none below MIN_WINDOW_S
            share = np.array([b - a for a, b in runs]) / T_ok * K
            k_run = np.maximum(1, np.floor(share)).astype(int)
            cap = np.floor(np.array([b - a for a, b in runs]) / MIN_WINDOW_S).astype(int)
            for j in np.argsort(-(share - np.floor(share))):
                if k_run.sum() >= K:
                    break
                if k_run[j] < cap[j]:
                    k_run[j] += 1
            out: list[tuple[float, float]] = []
            for (a, b), k in zip(runs, k_run):
                e = np.linspace(a, b, int(k) + 1)
                out += list(zip(e[:-1], e[1:]))
            return out
    K = int(np.clip(np.floor(T / WINDOW_S), 1, MAX_WINDOWS))
    if T >= WINDOWS3_MIN_S:
        K = max(K, 3)
    edges = np.linspace(t0, t1, K + 1)
    return list(zip(edges[:-1], edges[1:]))


def _motion_snr(u: _Unit, cutoff_hz: float) -> tuple[float, float]:
    """(motion RMS deg/s of the low-passed, mean-removed rate; in-band SNR)."""
    v = u.grid.values[u.grid.valid]
    if len(v) < 10:
        return 0.0, 0.0
    motion = float(np.degrees(np.sqrt(np.mean(np.sum((v - v.mean(axis=0)) ** 2, axis=1)))))
    noise_inband = u.noise_dps * np.sqrt(3.0) * np.sqrt(min(1.0, 2.0 * cutoff_hz / u.rate_hz))
    return motion, float(motion / noise_inband) if noise_inband > 0 else np.inf


def _tapost(ctx: _Ctx, progress: Progress) -> tuple[LatencyResult, _Coarse]:
    def prog(f: float, stage: str) -> None:
        if progress is not None:
            progress(f, stage)

    m, s = ctx.master, ctx.slave
    motion_dps, snr = _motion_snr(m, ctx.band_cutoff_hz)
    motion_s_dps, snr_s = _motion_snr(s, ctx.band_cutoff_hz)
    if min(snr, snr_s) < MIN_MOTION_SNR or motion_dps < 1e-3:
        if motion_dps >= 1e-3 and snr_s < MIN_MOTION_SNR <= snr:  # the master moves; the slave's rate is noise
            raise AnalysisError(
                f"the slave's angular rate is mostly noise (signal/noise {snr_s:.2g}, need {MIN_MOTION_SNR:g}) while "
                f"the master moves {motion_dps:.3g} deg/s RMS" + (
                    " (derived from attitude: its stamps too irregular or too coarse?)"
                    if s.source == "attitude" else ""))
        raise AnalysisError(
            f"not enough motion to estimate the latency: {motion_dps:.3g} deg/s RMS on the master "
            f"(signal/noise {min(snr, snr_s):.2g}, need {MIN_MOTION_SNR:g})")
    prog(0.1, "coarse |w| and rotation-solved cost")
    co = _coarse(ctx)
    prog(0.35, "refinement")
    # refinement samples: the master at ~5x the low-pass cutoff (both units are band-limited there, so
    # a denser grid adds no information, only time; the residuals' correlation is handled by the HAC)
    gr = _series_on_grid(m.itp, ctx.dt_r) if abs(ctx.dt_r - ctx.dt_s) > 1e-12 else m.grid
    t_m, a, valid = gr.t_s, gr.values, gr.valid
    # analysed window: master samples whose slave counterpart exists
    ok0 = valid & s.itp.ok(t_m + co.d0_s)
    if ok0.sum() * ctx.dt_r < MIN_OVERLAP_S:
        raise AnalysisError(f"overlap at the estimated lag {co.d0_s:.3f} s is only "
                            f"{ok0.sum() * ctx.dt_r:.1f} s (need {MIN_OVERLAP_S:g} s)")
    idx = np.flatnonzero(ok0)
    w0, w1 = float(t_m[idx[0]]), float(t_m[idx[-1]])
    t_mid = 0.5 * (w0 + w1)
    sel = (t_m >= w0) & (t_m <= w1)
    t_m, a, valid = t_m[sel], a[sel], valid[sel]
    # first fit on the central part (at most ADAPT_SPAN_S, where drift barely matters), no drift
    cs = np.abs(t_m - t_mid) <= 0.5 * ADAPT_SPAN_S
    first = _refine(t_m[cs], a[cs], valid[cs], s.itp, co.d0_s, 0.0, t_mid, fit_drift=False)
    d_center = first.latency_s if first.ok else co.d0_s
    # band selection: the residual spectrum tells where the noise is (flexure adds a rate noise at
    # the flexure's frequencies, large compared with slow motions); the low-pass cutoff that minimises
    # the predicted variance of the delay is chosen and the units are re-filtered there
    noise = None
    if GLS and first.ok:
        cr = _residual(t_m[cs], a[cs], valid[cs], s.itp, first, t_mid)
        noise = noise_model(cr, np.any(cr != 0.0, axis=1), ctx.dt_r)
    if ADAPT_BAND and first.ok and noise is None:
        new_cut = _best_cutoff(t_m[cs], a[cs], valid[cs], _residual(t_m[cs], a[cs], valid[cs], s.itp, first, t_mid),
                               ctx.dt_r, ctx.cutoff_hz, float(np.ptp(t_m[cs])))
        if new_cut < 0.7 * ctx.cutoff_hz:
            ctx = _refiltered_ctx(ctx, new_cut)
            m, s = ctx.master, ctx.slave
            gr = _series_on_grid(m.itp, ctx.dt_r) if abs(ctx.dt_r - ctx.dt_s) > 1e-12 else m.grid
            sel = (gr.t_s >= w0) & (gr.t_s <= w1)
            t_m, a, valid = gr.t_s[sel], gr.values[sel], gr.valid[sel]
    prog(0.55, "windows and drift")
    fin, centers, lats, sigs = _fit_all(ctx, t_m, a, valid, w0, w1, d_center, 0.0, DRIFT_SEARCH_PPM, noise)
    prog(0.8, "drift")
    fit_drift = len(centers) >= 3 or _drift_without_windows(w0, w1)
    # sigma: HAC-corrected GN sigma, inflated by the windows' scatter about the drift line
    chi2_red = _window_chi2(fin, centers, lats, sigs, t_mid)
    infl = np.sqrt(max(1.0, chi2_red)) if WINDOW_INFLATE else 1.0
    sig_l, sigma_drift = fin.sigma_latency_s * infl, fin.sigma_drift * infl
    latency, drift, corr_ld = fin.latency_s, fin.drift, fin.corr_ld
    extra_warnings: list[str] = []
    if fin.model_gap_s > 0:  # the spectral and the Kalman (flexure) fits disagree: cover the other one
        grown = max(sig_l, FLEX_GAP_COVER * fin.model_gap_s)
        corr_ld, sig_l = corr_ld * sig_l / grown, grown
        extra_warnings.append(f"the spectral and the flexure-model fits of the rates disagree by "
                              f"{fin.model_gap_s * 1e3:.3g} ms: sigma covers both")
    # stamps on a coarse grid (whole milliseconds) with a fixed sampling phase are all off by the same
    # fraction of it: a common offset, uniform over the grid step, that no residual shows (a floor in
    # quadrature; the drift is not affected, so the latency-drift covariance stays)
    res_sigma = grid_offset_sigma_s(ctx.stamp_resolution_s) if STAMP_RESOLUTION_FLOOR else 0.0
    if res_sigma > 0 and np.isfinite(sig_l) and sig_l > 0:
        grown = float(np.hypot(sig_l, res_sigma))
        corr_ld, sig_l = corr_ld * sig_l / grown, grown
    # velocity matching: a second estimate, fused when the two agree (see _velocity_step)
    vel_q, vp = None, None
    if ctx.vel_src is not None:
        prog(0.85, "velocity matching")
        vp = velocity_pair(*ctx.vel_src, ctx.band_cutoff_hz, ctx.master.itp)
        vel_q, fused = _velocity_step(ctx, vp, w0, w1, t_mid, fit_drift, latency, drift, sig_l, sigma_drift,
                                      corr_ld, flexure=fin.flex is not None)
        if fused is not None:
            latency, drift, sig_l, sigma_drift, corr_ld = fused
    # a drift the data cannot determine is pulled towards 0 by a Gaussian prior (crystal clocks:
    # DRIFT_PRIOR_PPM), and the latency with it through their correlation (Gaussian conditioning),
    # so that an undetermined slope does not become a large made-up one nor spoil the latency
    if fit_drift and np.isfinite(sigma_drift) and np.isfinite(sig_l):
        V = np.array([[sig_l ** 2, corr_ld * sig_l * sigma_drift],
                      [corr_ld * sig_l * sigma_drift, sigma_drift ** 2]])
        K = V[:, 1] / (V[1, 1] + (DRIFT_PRIOR_PPM * 1e-6) ** 2)
        latency, drift = latency - K[0] * drift, drift - K[1] * drift
        V = V - np.outer(K, V[1])
        sig_l, sigma_drift = float(np.sqrt(max(V[0, 0], 0.0))), float(np.sqrt(max(V[1, 1], 0.0)))
    # without a drift fit the latency is that of the information's centroid (the samples weighted by the
    # rate's change squared): where gaps or uneven motion move it off the middle of the window, the drift's
    # prior moves the middle's latency by drift x that distance
    if not fit_drift:
        ok_f = valid & s.itp.ok(t_m + latency)
        wd, ok_d = m.itp(t_m, 1)
        ok_f &= ok_d
        g = np.sum(np.where(ok_f[:, None], wd, 0.0) ** 2, axis=1)  # the delay's information per sample
        if g.sum() > 0:
            t_c = float(np.sum(g * t_m) / g.sum())
            sig_l = float(np.hypot(sig_l, DRIFT_PRIOR_PPM * 1e-6 * abs(t_c - t_mid)))
    # stamp noise: the error it causes is a floor (the aided fit does not see it in its residuals)
    jit_sigma = _jitter_sigma_s(ctx, w0, w1)
    sig_l = max(sig_l, jit_sigma)
    sigma = max(SIGMA_CALIBRATION * sig_l, SIGMA_FLOOR_S)
    # the instant where the latency is best determined (uncorrelated with the drift): the middle of the
    # window when the motion is spread evenly, elsewhere when it is not (DESIGN.md quotes the middle)
    t_best, lat_best, sig_best = t_mid, latency, sigma
    if fit_drift and np.isfinite(sigma_drift) and sigma_drift > 0 and np.isfinite(sig_l):
        t_best = float(np.clip(t_mid - V[0, 1] / V[1, 1], w0, w1))
        lat_best = float(latency + drift * (t_best - t_mid))
        v_best = V[0, 0] + 2 * (t_best - t_mid) * V[0, 1] + (t_best - t_mid) ** 2 * V[1, 1]
        sig_best = max(SIGMA_CALIBRATION * float(np.sqrt(max(v_best, 0.0))), SIGMA_FLOOR_S)
    alts, alts_out = list(co.alternatives_s), []
    if alts and PERIODIC_VELOCITY and vel_q is not None and vel_q["agrees"]:
        alts, alts_out = _periodic_by_velocity(ctx, vp, alts, co.d0_s, latency, drift, t_mid, fit_drift)
    periodic = len(alts) > 0
    if periodic:
        spread = max(abs(x - co.d0_s) for x in alts)
        sigma = max(sigma, 0.5 * spread)
    rpy = tuple(float(x) for x in np.degrees(euler_from_dcm(fin.R)))
    nanfrac = float(1.0 - np.mean(ok0[(gr.t_s >= w0) & (gr.t_s <= w1)]))
    too_little = bool(min(snr, snr_s) < LOW_MOTION_SNR or motion_dps < LOW_MOTION_DPS)
    # normalised cost curve around the minimum (coarse grid), for plots, with the continuous cost
    # (drift included) sampled finely near the estimate so that a zoom shows the parabola
    vc = co.vc
    near = np.abs(vc.lags * co.dt_s - co.d0_s) <= max(0.5, 10 * co.dt_s)
    c_lag, c_val = vc.lags[near] * co.dt_s, vc.cost[near]
    half = min(max(FINE_COST_SIGMAS * sigma, FINE_COST_SAMPLES * co.dt_s), max(0.5, 10 * co.dt_s))
    f_lag, f_val = _fine_cost(ctx, latency, drift, t_mid, w0, w1, half)
    if len(f_lag):
        out = (c_lag < f_lag[0]) | (c_lag > f_lag[-1])
        c_lag = np.concatenate([c_lag[out], f_lag])
        c_val = np.concatenate([c_val[out], f_val])
        o = np.argsort(c_lag, kind="stable")
        c_lag, c_val = c_lag[o], c_val[o]
    quality = {
        "motion_dps": motion_dps,
        "slave_motion_dps": motion_s_dps,
        "motion_snr": float(min(snr, snr_s)),
        "too_little_motion": too_little,
        "periodic": periodic,
        "periodic_alternatives_s": [float(x) for x in alts[:10]],
        "periodic_alternatives_rejected_s": [float(x) for x in alts_out[:10]],
        "windows_disagree": bool(chi2_red > 9.0),
        "window_chi2_red": chi2_red,
        "n_windows": int(len(centers)),
        "overlap_s": float(w1 - w0),
        "mounting_rpy_deg": list(rpy),
        "bias_diff_dph": [float(x) for x in np.degrees(fin.bias) * 3600.0],
        "residual_rms_dps": float(np.degrees(fin.residual_rms)),
        "vector_cost_min": co.best_cost,
        "gls": bool(noise is not None),
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
        "nan_fraction": nanfrac,
        "coarse_latency_s": co.d0_s,
        "xcorr_norm_latency_s": co.xcorr_latency_s,
        "xcorr_norm_peak": co.xcorr_peak,
        "residual_correlation_factor": fin.hac_factor,
        "drift_sigma_ppm": float(sigma_drift * 1e6) if fit_drift else None,
        "stamp_jitter_s": {"master": ctx.stamp_jitter_s[0], "slave": ctx.stamp_jitter_s[1]},
        "stamp_jitter_latency_sigma_s": jit_sigma,
        "stamp_resolution_s": {"master": ctx.stamp_resolution_s[0], "slave": ctx.stamp_resolution_s[1]},
        "stamp_resolution_latency_sigma_s": res_sigma,
        "best_instant_s": float(ctx.t0_abs_s + t_best),  # absolute, like window_s
        "latency_at_best_instant_s": float(lat_best),
        "sigma_at_best_instant_s": float(sig_best),
        "drift_estimated": fit_drift,
        "common_rate_hz": 1.0 / ctx.dt_c,
        "refine_rate_hz": 1.0 / ctx.dt_r,
        "lowpass_hz": ctx.cutoff_hz,
        "band_adapted": ctx.adapted_cutoff,
        "rates_hz": {"master": m.rate_hz, "slave": s.rate_hz},
        "rate_source": {"master": m.source, "slave": s.source},
        "warnings": list(ctx.warnings) + extra_warnings,
    }
    res = LatencyResult(
        latency_s=float(latency), sigma_s=float(sigma), drift_ppm=float(drift * 1e6) if fit_drift else 0.0,
        method="tapost", window_s=(ctx.t0_abs_s + w0, ctx.t0_abs_s + w1), quality=quality,
        cost_lag_s=c_lag, cost=c_val,
        window_centers_s=centers, window_latency_s=lats, mounting_rpy_deg=rpy, t_mid_rel_s=float(t_mid))
    return res, co


def _velocity_step(ctx: _Ctx, vp: VelocityPair | None, w0: float, w1: float, t_mid: float, fit_drift: bool,
                   latency: float, drift: float, sig_l: float, sig_dr: float, corr: float, *, flexure: bool = False
                   ) -> tuple[dict | None, tuple | None]:
    """The velocity-matched estimate (``logtools.latency_velocity``) and its fusion with the rate fit's
    (L[, drift]): inverse-covariance weighted when the two agree (chi-square below VEL_AGREE_CHI2; a nav
    velocity's delay need not be its IMU's: else ``agrees`` is False and the rate fit stays) and either
    the velocity's latency sigma is the smaller or the rate fit had to model flexure (``flexure``: what
    limits it there is what the velocity does not see). Returns (the quality entry or None, the
    fused (L, drift, sigma_L, sigma_drift, corr) or None). ``vp``: the units' velocity pair (None: no fit)."""
    vf = None if vp is None else velocity_fit(vp, w0, w1, latency, drift, t_mid, fit_drift=fit_drift,
                                              windows=_windows(ctx, w0, w1))
    if vf is None or not np.isfinite(sig_l):
        return None, None
    nd = 2 if fit_drift and sig_dr > 0 and vf.sigma_drift > 0 else 1

    def cov(s_l: float, s_d: float, c: float) -> np.ndarray:
        return np.array([[s_l ** 2, c * s_l * s_d], [c * s_l * s_d, s_d ** 2]])[:nd, :nd]

    x_r, x_v = np.array([latency, drift])[:nd], np.array([vf.latency_s, vf.drift])[:nd]
    V_r, V_v = cov(sig_l, sig_dr, corr), cov(vf.sigma_latency_s, vf.sigma_drift, vf.corr_ld)
    dx = x_v - x_r
    chi2 = float(dx @ np.linalg.solve(V_r + V_v, dx)) / SIGMA_CALIBRATION ** 2  # the sigmas as reported
    agrees = bool(chi2 <= VEL_AGREE_CHI2[nd - 1])
    use = bool(agrees and (VEL_FUSE_ALWAYS or (VEL_FUSE_FLEXURE and flexure) or vf.sigma_latency_s < sig_l))
    q = {"latency_s": vf.latency_s, "sigma_s": SIGMA_CALIBRATION * vf.sigma_latency_s,
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


def _periodic_by_velocity(ctx: _Ctx, vp: VelocityPair | None, alts: list[float], d0: float, latency: float,
                          drift: float, t_mid: float, fit_drift: bool) -> tuple[list[float], list[float]]:
    """The rates' near-equal other minima (motion that repeats: a ship's sway, S-turns) tried on the
    velocities, which a mounting rotation cannot fit and which seldom repeat with the attitude: an
    alternative whose velocity fit leaves PERIODIC_VELOCITY_RATIO x the residual of the estimate's (each
    over its own overlap, same fit) is rejected. Returns (kept, rejected) alternatives (coarse lags)."""
    if vp is None:
        return alts, []
    g = ctx.master.grid
    dr = drift if fit_drift else 0.0

    def rms_at(lag: float) -> float:
        ok = g.valid & ctx.slave.itp.ok(g.t_s + lag)
        if ok.sum() * g.dt_s < MIN_OVERLAP_S:
            return np.nan
        idx = np.flatnonzero(ok)
        a0, a1 = float(g.t_s[idx[0]]), float(g.t_s[idx[-1]])
        tm = 0.5 * (a0 + a1)
        vf = velocity_fit(vp, a0, a1, lag + dr * (tm - t_mid), dr, tm, fit_drift=False, windows=[])
        return np.nan if vf is None else vf.residual_rms_m_s

    best = rms_at(latency)
    if not (np.isfinite(best) and best > 0):
        return alts, []
    kept, out = [], []
    for x in alts:
        r = rms_at(latency + (x - d0))
        (out if np.isfinite(r) and r > PERIODIC_VELOCITY_RATIO * best else kept).append(x)
    return kept, out


def _fine_cost(ctx: _Ctx, latency_s: float, drift: float, t_mid: float, w0: float, w1: float,
               half_s: float, n: int = FINE_COST_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """The normalised rotation- and bias-solved cost (as the coarse curve) at n continuous lags
    latency_s +- half_s, with the drift, on at most FINE_COST_MAX_SAMPLES master samples (a strided
    subset of the search grid: the curve's shape, not its noise, is what a plot needs)."""
    g = ctx.master.grid
    sel = np.flatnonzero((g.t_s >= w0) & (g.t_s <= w1) & g.valid)
    if len(sel) < 20 or not np.isfinite(half_s) or half_s <= 0:
        return np.zeros(0), np.zeros(0)
    sel = sel[::max(1, int(np.ceil(len(sel) / FINE_COST_MAX_SAMPLES)))]
    t, a = g.t_s[sel], g.values[sel]
    lags = latency_s + np.linspace(-half_s, half_s, n)
    out = np.full(n, np.nan)
    shift = drift * (t - t_mid)
    for k, d in enumerate(lags):
        b, ok = ctx.slave.itp(t + d + shift)
        if ok.sum() < 20:
            continue
        aa, bb = a[ok] - a[ok].mean(axis=0), b[ok] - b[ok].mean(axis=0)
        _, best = _kabsch(aa.T @ bb)
        tot = float(np.sum(aa * aa) + np.sum(bb * bb))
        if tot > 0:
            out[k] = (tot - 2.0 * float(best)) / tot
    return lags, out


def _window_chi2(f: _Fit, centers: np.ndarray, lats: np.ndarray, sigs: np.ndarray, t_mid: float) -> float:
    """Reduced chi-square of the window estimates about f's line L + drift (t - t_mid) (1 below 3 windows)."""
    return window_chi2(centers, lats, sigs, f.latency_s, f.drift, t_mid)


def _fit_all(ctx: _Ctx, t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, w0: float, w1: float,
             d_center: float, drift_center: float, search_ppm: float, noise: NoiseModel | None = None
             ) -> tuple[_Fit, np.ndarray, np.ndarray, np.ndarray]:
    """Windows along the overlap (each: integer-lag search around the predicted lag, then refinement),
    a weighted line through them, then the joint (L, drift) fit over the whole overlap. With fewer than
    3 usable windows, one global fit without drift."""
    t_mid = 0.5 * (w0 + w1)
    itp = ctx.slave.itp
    wins = _windows(ctx, w0, w1, t_m[valid & itp.ok(t_m + d_center)])
    bounds: dict[float, tuple[float, float]] = {}

    def fit_windows(line: tuple[float, float] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each window's delay at its centre. The drift inside a window is that of ``line`` (L, drift at
        t_mid), else none: a window's delay without it is that of the window's motion centroid, not its
        centre (100 ppm over a 15 s window whose motion sits at one end: 0.7 ms)."""
        centers, lats, sigs, wmot = [], [], [], []
        for (a0, a1) in wins if len(wins) >= 3 else []:
            ws = (t_m >= a0) & (t_m <= a1)
            if ws.sum() < 50:
                continue
            tc = 0.5 * (a0 + a1)
            if line is None:
                dr_w = 0.0
                pred = d_center + drift_center * (tc - t_mid)
                band = search_ppm * 1e-6 * abs(tc - t_mid) + 2.0 * ctx.dt_s
                dw = _window_start(ctx, a0, a1, pred, band)
                if dw is None:
                    continue
            else:
                dr_w = line[1]
                dw = line[0] + dr_w * (tc - t_mid)
            f = _refine(t_m[ws], a[ws], valid[ws], itp, dw, dr_w, tc, fit_drift=False, iters=8)
            if GLS_WINDOWS and noise is not None and f.ok:
                f = _refine_gls(t_m[ws], a[ws], valid[ws], itp, f.latency_s, dr_w, tc, noise, fit_drift=False)
            if f.ok and np.isfinite(f.sigma_latency_s):
                bounds[float(tc)] = (a0, a1)
                centers.append(tc)
                lats.append(f.latency_s)
                sigs.append(max(f.sigma_latency_s, SIGMA_FLOOR_S))
                wmot.append(f.motion_rms)
        centers, lats, sigs, wmot = map(np.asarray, (centers, lats, sigs, wmot))
        if len(wmot):
            keep = wmot >= 0.2 * np.median(wmot)  # windows with enough motion
            centers, lats, sigs = centers[keep], lats[keep], sigs[keep]
        return centers, lats, sigs

    def reject(centers: np.ndarray, lats: np.ndarray, sigs: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Windows that locked on a wrong minimum (little motion in them: the linearised sigma does not
        hold there) are outliers of the line: rejected one at a time beyond WINDOW_REJECT sigma."""
        keep = np.ones(len(centers), bool)
        while keep.sum() > 3:
            L0, dr0, _ = _wls_line(centers[keep] - t_mid, lats[keep], sigs[keep])
            z = np.abs(lats - (L0 + dr0 * (centers - t_mid))) / sigs
            j = int(np.argmax(np.where(keep, z, -1.0)))
            if z[j] <= WINDOW_REJECT:
                break
            keep[j] = False
        centers, lats, sigs = centers[keep], lats[keep], sigs[keep]
        L0, dr0, _ = _wls_line(centers - t_mid, lats, sigs)
        return centers, lats, sigs, L0, dr0

    centers, lats, sigs = fit_windows(None)
    fin = None
    if len(centers) >= 3:
        centers, lats, sigs, L0, dr0 = reject(centers, lats, sigs)
        # two starts: the windows' line and the central fit without drift; the lower cost wins
        cands = [_refine(t_m, a, valid, itp, L0, dr0, t_mid, fit_drift=True),
                 _refine(t_m, a, valid, itp, d_center, 0.0, t_mid, fit_drift=True)]
        cands = [c for c in cands if c.ok]
        fin = min(cands, key=lambda c: c.residual_rms) if cands else None
        half = 0.5 * max(b - a for a, b in bounds.values())
        if (WINDOW_DRIFT and fin is not None
                and abs(fin.drift) * half > WINDOW_DRIFT_FRACTION * float(np.median(sigs))):
            # the windows again, with the joint fit's drift inside each (a window's own drift-free delay
            # is its motion centroid's: windows of uneven motion scatter about the line for nothing)
            c2, l2, s2 = fit_windows((fin.latency_s, fin.drift))
            if len(c2) >= 3:
                centers, lats, sigs, _, _ = reject(c2, l2, s2)
    if fin is None:
        centers = lats = sigs = np.zeros(0)
        fin = _refine(t_m, a, valid, itp, d_center, 0.0, t_mid, fit_drift=_drift_without_windows(w0, w1))
        if not fin.ok:
            raise AnalysisError("latency refinement failed (too little valid overlapping data)")
    if noise is not None:
        # GLS on the whole overlap, with the residual spectrum re-estimated from this fit
        fd = len(centers) >= 3 or _drift_without_windows(w0, w1)

        def wants_accel(f: _Fit) -> bool:  # below ACCEL_MIN_SIGMA_S the accelerometers cannot matter
            return ctx.acc_src is not None and f.sigma_latency_s > ACCEL_MIN_SIGMA_S

        # with accelerometers, one gyro-only pass (their start and fall-back), then the aided passes
        gls_done = False
        for k in range(GLS_PASSES):
            if k == 1 and wants_accel(fin):
                break
            r = _residual(t_m, a, valid, itp, fin, t_mid)
            nm = noise_model(r, np.any(r != 0.0, axis=1), float(np.median(np.diff(t_m)))) or noise
            f2 = _refine_gls(t_m, a, valid, itp, fin.latency_s, fin.drift, t_mid, nm, fit_drift=fd)
            if not f2.ok:
                break
            fin, gls_done = f2, True
        final_noise, final_acc = None, None
        acc = _accel_pair(*ctx.acc_src) if gls_done and wants_accel(fin) else None
        if acc is not None:
            fa, nm6, acc_used = _accel_aided(t_m, a, valid, itp, acc, fin, t_mid, fit_drift=fd)
            if fa.aided:
                fin, final_noise, final_acc = fa, nm6, acc_used
            else:
                fin = fa  # the gyro-only fit, with the model check's figures

        def windows(f: _Fit, refit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """The windows for the check of f's sigma: again with f's own estimator (``refit``: its noise
            model and channels; gyro-only windows scatter with the flexure it took out), else the ordinary
            ones (gyro-only spectral fits: the conservative check, GLS windows of gyros alone measured
            worse). Fewer than 3 windows with the motion for f's estimator: nothing checks its sigma (the
            ordinary windows' sigmas ignore the flexure and would inflate it for nothing)."""
            if not fd or refit is None:
                return centers, lats, sigs
            c2, l2, s2 = [], [], []
            for tc in centers:
                a0, a1 = bounds[float(tc)]
                ws = (t_m >= a0) & (t_m <= a1)
                fw = refit(ws, tc, f.latency_s + f.drift * (tc - t_mid), f.drift if WINDOW_DRIFT else 0.0)
                if fw.ok and np.isfinite(fw.sigma_latency_s):
                    c2.append(tc)
                    l2.append(fw.latency_s)
                    s2.append(max(fw.sigma_latency_s, SIGMA_FLOOR_S))
            if len(c2) >= 3:
                return np.asarray(c2), np.asarray(l2), np.asarray(s2)
            return centers, lats, np.full(len(sigs), np.inf)

        refit = None
        if final_acc is not None:
            def refit(ws, tc, lag, drift):
                return _refine_gls(t_m[ws], a[ws], valid[ws], itp, lag, drift, tc, final_noise, fit_drift=False,
                                   acc=final_acc)
        cands = [(fin, refit)]
        if FLEX_SS and gls_done and fin.sigma_latency_s > ACCEL_MIN_SIGMA_S:
            # Kalman whitening with the flexure model, from the spectral GLS fit, the second candidate
            # (a gyro-only Kalman fit keeps the accelerometer model check's figures)
            def flex_fit(acc: _Accel | None) -> _Fit:
                return _refine_flex(t_m, a, valid, itp, fin.latency_s, fin.drift, t_mid, ctx.cutoff_hz,
                                    fit_drift=fd, acc=acc, h0=fin.sigma_latency_s)

            acc_x = final_acc  # FLEX_ACCEL_OWN: the accelerometers whenever both units have them
            own = FLEX_ACCEL_OWN and acc_x is None and ctx.acc_src is not None
            if own:
                acc_x = _accel_pair(*ctx.acc_src)
            ff = flex_fit(acc_x)
            if acc_x is not None and not acc_x.lag_free and ff.ok and not _accel_lag_agrees(ff) and ACCEL_LAG_FREE:
                # the accelerometers' own delay differs from the gyros' (real IMUs may filter them
                # differently): solved as a further unknown
                acc_x = replace(acc_x, lag_free=True)
                ff = flex_fit(acc_x)
            if acc_x is not None and ((ff.ok and not _accel_lag_agrees(ff)) or ((own or acc_x.lag_free) and not ff.ok)):
                # that delay beyond what a linearised unknown allows, or the fit with the accelerometers
                # taken here failed: the gyros alone
                acc_x = None
                ff = flex_fit(None)
            if ff.ok and np.isfinite(ff.sigma_latency_s):
                ff = ff if ff.accel_lag_s[1] > 0 else replace(ff, accel_lag_s=fin.accel_lag_s,
                                                             accel_lag_free=fin.accel_lag_free)
                gap = abs(ff.latency_s - fin.latency_s)
                if gap > FLEX_AGREE_SIGMAS * max(ff.sigma_latency_s, fin.sigma_latency_s):
                    # one of the two models is wrong (the spectral sigma is optimistic where flexure is
                    # estimated from a few cycles; the Kalman fit where the disturbance is not flexure):
                    # both go to the windows' check, and the one kept covers the other in its sigma
                    fin = replace(fin, model_gap_s=gap)
                    ff = replace(ff, model_gap_s=gap)
                    cands[0] = (fin, refit)

                def refit_flex(ws, tc, lag, drift):
                    return _refine_flex(t_m[ws], a[ws], valid[ws], itp, lag, drift, tc, ctx.cutoff_hz,
                                        fit_drift=False, acc=acc_x, model=ff.flex, h0=ff.sigma_latency_s)
                cands.append((ff, refit_flex))
        if len(cands) == 1 or not fd:
            fin, refit = cands[-1]  # without windows the Kalman fit is taken (see FLEX_AGREE_SIGMAS)
            centers, lats, sigs = windows(fin, refit)
        else:
            # each candidate's sigma as checked by its own windows' scatter. The Kalman fit is kept unless
            # its windows disagree (the flexure model does not describe the data: vibration, filters) and
            # the spectral fit's checked sigma is smaller. Not the bare sigmas: where the spectrum is
            # estimated from a few cycles of slow motion, the spectral sigma is the optimistic one
            scored = []
            for f, rf in cands:
                w = windows(f, rf)
                chi2 = _window_chi2(f, *w, t_mid)
                scored.append((f.sigma_latency_s * np.sqrt(max(1.0, chi2)), chi2, f, w))
            (s_spec, chi2_spec, f_spec, w_spec), (s_flex, chi2_flex, f_flex, w_flex) = scored
            if chi2_flex > FLEX_WINDOWS_CHI2 and s_spec < s_flex:
                fin, (centers, lats, sigs), s_kept, chi2_kept = f_spec, w_spec, s_spec, chi2_spec
            else:
                fin, (centers, lats, sigs), s_kept, chi2_kept = f_flex, w_flex, s_flex, chi2_flex
            # the other model's estimate beyond FLEX_AGREE_SIGMAS of the kept one's checked sigma while the
            # kept one's windows disagree too: neither model is borne out, the sigma covers both (a gently
            # turning aircraft kept a spectral fit 4.75 ms from the Kalman one at a checked sigma of 0.28 ms,
            # both fits' windows at chi2 5-12, 5.7 ms off the truth: z 17). Where the kept fit's windows
            # agree (ships: the spectral fit right, the Kalman one 1 ms off) its checked sigma stands
            gap = abs(f_spec.latency_s - f_flex.latency_s)
            if fin.model_gap_s == 0 and gap > FLEX_AGREE_SIGMAS * s_kept and chi2_kept > FLEX_WINDOWS_CHI2:
                fin = replace(fin, model_gap_s=gap)
    return fin, centers, lats, sigs


def _accel_aided(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, acc: _Accel, fin: _Fit,
                 t_mid: float, *, fit_drift: bool) -> tuple[_Fit, NoiseModel | None, _Accel | None]:
    """ACCEL_GLS_PASSES accelerometer-aided GLS passes from the gyro-only fit ``fin`` (the 6-channel residual
    cross-spectrum re-estimated before each); kept when its sigma is smaller (flagged ``aided``). Where
    the model check finds the accelerometers on a delay of their own, the passes again with that delay
    solved (ACCEL_LAG_FREE). Returns the fit kept and, when it is an aided one, its noise model and
    accelerometers (``lag_free`` or not)."""
    dt = float(np.median(np.diff(t_m)))

    def passes(ac: _Accel) -> tuple[_Fit, NoiseModel | None]:
        cur, nm = fin, None
        for _ in range(ACCEL_GLS_PASSES):
            r6 = _accel_residual(t_m, a, valid, itp, ac, cur, t_mid)
            nm6 = noise_model(r6, np.any(r6 != 0.0, axis=1), dt, matrix=True)
            if nm6 is None:
                break
            f2 = _refine_gls(t_m, a, valid, itp, cur.latency_s, cur.drift, t_mid, nm6, fit_drift=fit_drift, acc=ac)
            if not f2.ok:
                break
            cur, nm = f2, nm6
        return cur, nm

    cur, nm = passes(acc)
    if cur is not fin and not _accel_lag_agrees(cur) and ACCEL_LAG_FREE:
        free = replace(acc, lag_free=True)
        cur_f, nm_f = passes(free)
        if cur_f is not fin:
            cur, nm, acc = cur_f, nm_f, free
    if cur is not fin and cur.sigma_latency_s < fin.sigma_latency_s and _accel_lag_agrees(cur):
        return replace(cur, aided=True), nm, acc
    return replace(fin, accel_lag_s=cur.accel_lag_s), None, None


def _accel_lag_agrees(f: _Fit) -> bool:
    """The accelerometers' own delay relative to the gyros' (f's model check) is zero within ACCEL_LAG_SIGMAS;
    where the fit solved it (``accel_lag_free``), it is at most ACCEL_LAG_MAX_S."""
    lag, sig = f.accel_lag_s
    if f.accel_lag_free:
        return bool(abs(lag) <= ACCEL_LAG_MAX_S)
    return bool(abs(lag) <= ACCEL_LAG_SIGMAS * sig)


def _window_start(ctx: _Ctx, a0: float, a1: float, d_center: float, band_s: float) -> float | None:
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
    vc = _vector_cost(ms, ss, lags, 0.8 * valid.sum())
    if not np.any(np.isfinite(vc.cost)):
        return None
    j = int(np.nanargmin(vc.cost))
    return float((lags[j] + _parabolic(vc.cost, j)) * dt)


def _wls_line(x: np.ndarray, y: np.ndarray, sig: np.ndarray) -> tuple[float, float, np.ndarray]:
    w = 1.0 / np.maximum(sig, 1e-12) ** 2
    A = np.stack([np.ones_like(x), x], axis=1)
    N = A.T @ (A * w[:, None])
    p = np.linalg.solve(N, A.T @ (w * y))
    return float(p[0]), float(p[1]), np.linalg.inv(N)


def _xcorr_estimate(ctx: _Ctx) -> MethodEstimate:
    """Baseline: |w| normalised cross-correlation on the common grid, parabolic peak interpolation."""
    m, s = (_series_on_grid(interpolant(lowpass(u, CUTOFF_FRACTION / ctx.dt_c)), ctx.dt_c) for u in ctx.raw)
    corr = _Correlator(m, s)
    lags, min_count = _lag_window(ctx, corr, ctx.dt_c, 0.5 if ctx.max_lag_s is not None else 0.25)
    rho, n = _norm_xcorr(m, s, lags)
    rho[n < min_count] = np.nan
    if not np.any(np.isfinite(rho)):
        raise AnalysisError("no lag with enough overlap")
    i = int(np.nanargmax(rho))
    d = (lags[i] + _parabolic(-rho, i)) * ctx.dt_c
    # sigma: width of the peak / sqrt(number of independent samples), at least the grid quantisation
    r = rho[np.isfinite(rho)]
    lobe = _lobe_halfwidth(-rho, i) * ctx.dt_c
    n_ind = max(1.0, n[i] * ctx.dt_c / max(lobe, ctx.dt_c))
    sig = max(ctx.dt_c / np.sqrt(12.0), lobe * np.sqrt(max(1e-6, 1 - rho[i] ** 2)) / np.sqrt(n_ind))
    note = f"peak correlation {rho[i]:.3f}" + ("" if len(r) else "")
    return MethodEstimate(float(d), float(sig), note)


#: record length (s) the seeds' grid searches get when they only run for comparison: their cost is
#: samples x candidate lags (a 4 h log took 19 s); the papers themselves use 5-6 s records
COMPARE_RECORD_S = 600.0


def _run_seed(name: str, master: InsLog, slave: InsLog, max_lag_s: float | None,
              headline: bool = False) -> MethodEstimate:
    """A seed's method. As the headline it runs as asked; for comparison only, on a record of at most
    COMPARE_RECORD_S and never over the whole overlap (``max_lag_s=None``: quadratic in the log length)."""
    if not headline and max_lag_s is None:
        return MethodEstimate(float("nan"), float("nan"),
                              "not run for comparison with --max-lag auto (a grid search over the whole "
                              "overlap); choose it with --latency-method to run it")
    kw = {} if headline else {"record_s": COMPARE_RECORD_S}
    try:
        from logtools import latency_seeds  # noqa: PLC0415 (lazy: written separately)
    except ImportError as exc:
        return MethodEstimate(float("nan"), float("nan"), f"not available ({exc})")
    fn = {"s000-rate-integral": "s000_rate_integral", "s002-attitude-shift": "s002_attitude_shift"}[name]
    f = getattr(latency_seeds, fn, None)
    if f is None:
        return MethodEstimate(float("nan"), float("nan"), f"not available (latency_seeds.{fn} missing)")
    return f(master, slave, max_lag_s=max_lag_s, **kw)


def _suspect(res: LatencyResult, max_lag_s: float) -> bool:
    """A bounded search's result that may be a minimum of the window, not of the data: at (or past) the
    window's edge, or fitting the rates poorly (the true delay beyond --max-lag: a car 3.5 s late came out
    3.08 s at sigma 25 ms, a multirotor 5 s late -1.81 s at sigma 0.5 ms)."""
    return bool(abs(res.latency_s) > SEARCH_EDGE_FRACTION * max_lag_s
                or res.quality.get("vector_cost_min", 0.0) > SEARCH_SUSPECT_COST)


def _widened(res: LatencyResult, ctx: _Ctx) -> LatencyResult:
    """The whole overlap searched as well (``ctx``, the bounded search's, unbounded); its result replaces the
    bounded one where it fits the rates clearly better (cost below SEARCH_WIDEN_GAIN x), and a warning says
    what was found either way."""
    max_lag_s = ctx.max_lag_s
    c0 = float(res.quality.get("vector_cost_min", np.nan))
    try:
        wide, _ = _tapost(replace(ctx, max_lag_s=None, warnings=list(ctx.warnings)), None)
    except AnalysisError as exc:
        wide, why = None, exc.problem
    c1 = float(wide.quality.get("vector_cost_min", np.nan)) if wide is not None else np.nan
    if wide is not None and c1 < SEARCH_WIDEN_GAIN * c0:
        q = dict(wide.quality)
        q["warnings"] = list(q.get("warnings", [])) + [
            f"the best match within +-{max_lag_s:g} s ({res.latency_s * 1e3:+.1f} ms) fitted the rates poorly "
            f"(cost {c0:.3g}) or lay at the edge: the whole overlap was searched and {wide.latency_s:+.4f} s "
            f"fits far better (cost {c1:.3g}); widen --max-lag or use --max-lag auto to search so directly"]
        q["search_widened"] = True
        return replace(wide, quality=q)
    q = dict(res.quality)
    q["search_widened"] = False
    note = (f"the whole overlap, searched as well, fits no better (cost {c1:.3g} at {wide.latency_s:+.4f} s)"
            if wide is not None else f"a whole-overlap search could not run ({why})")
    q["warnings"] = list(q.get("warnings", [])) + [
        f"the best match within +-{max_lag_s:g} s lies at its edge or fits the rates poorly (cost {c0:.3g}); "
        + note]
    return replace(res, quality=q)


def estimate(master: InsLog, slave: InsLog, *, method: str = "tapost", max_lag_s: float | None = 2.0,
             compare: bool = True, progress: Progress = None, accelerometers: bool = True,
             velocity: bool = True) -> LatencyResult:
    """Latency (s) and drift (ppm) of ``slave`` behind ``master``; see the module docstring.

    ``max_lag_s`` bounds the search at face value (both logs' absolute stamps); ``None`` searches the
    whole overlap (unrelated clocks). Raises AnalysisError (one line) for no/too short overlap, no motion,
    NaN-only data. With ``compare`` every other method that can run is stored in ``methods`` (a method
    that cannot run is stored with NaN and its reason). ``accelerometers=False`` keeps the tapost method
    on the gyros alone (no accelerometer-aided GLS); ``velocity=False`` leaves the units' velocities out
    (no velocity matching).
    """
    if method not in METHODS:
        raise AnalysisError(f"unknown latency method {method!r} (choose from {', '.join(METHODS)})")

    def prog(f: float, stage: str) -> None:
        if progress is not None:
            progress(float(f), stage)

    prog(0.0, "preparing")
    ctx = _prepare(master, slave, max_lag_s, accelerometers=accelerometers, velocity=velocity)
    methods: dict[str, MethodEstimate] = {}
    head: LatencyResult | None = None
    err: AnalysisError | None = None
    # the headline first: its failure is the run's failure
    if method == "tapost":
        head, _ = _tapost(ctx, lambda f, st: prog(0.05 + 0.75 * f, st))
        if max_lag_s is not None and SEARCH_WIDEN and _suspect(head, max_lag_s):
            prog(0.78, "whole-overlap search")
            head = _widened(head, ctx)
        cost = float(head.quality.get("vector_cost_min", 0.0))
        if cost > NO_MATCH_COST:
            raise AnalysisError(
                f"the two units' angular rates match at no lag searched (best normalised cost {cost:.2f}; "
                "0 = identical, 1 = unrelated): logs of different vehicles or of different times?")
        methods["tapost"] = MethodEstimate(head.latency_s, head.sigma_s, "")
    others = [x for x in METHODS if x != method] if compare else []
    for i, name in enumerate(([method] if method != "tapost" else []) + others):
        prog(0.8 + 0.2 * i / max(1, len(others) + 1), name)
        try:
            if name == "tapost":
                r, _ = _tapost(ctx, None)
                me = MethodEstimate(r.latency_s, r.sigma_s, "")
            elif name == "xcorr-norm":
                me = _xcorr_estimate(ctx)
            else:
                me = _run_seed(name, master, slave, max_lag_s, headline=name == method)
        except AnalysisError as exc:
            if name == method:
                err = exc
                break
            me = MethodEstimate(float("nan"), float("nan"), f"cannot run: {exc.problem}")
        except Exception as exc:  # noqa: BLE001 - a comparison method must never crash the run
            if name == method:
                raise
            me = MethodEstimate(float("nan"), float("nan"), f"failed: {type(exc).__name__}: {exc}")
        methods[name] = me
    if err is not None:
        raise err
    if head is None:
        me = methods[method]
        if not np.isfinite(me.latency_s):
            raise AnalysisError(f"latency method {method} could not run: {me.note}")
        g = ctx.master.grid
        head = LatencyResult(latency_s=me.latency_s, sigma_s=me.sigma_s, drift_ppm=0.0, method=method,
                             window_s=(ctx.t0_abs_s + float(g.t_s[0]), ctx.t0_abs_s + float(g.t_s[-1])),
                             quality={"note": me.note, "warnings": list(ctx.warnings)},
                             t_mid_rel_s=float(0.5 * (g.t_s[0] + g.t_s[-1])))
    prog(1.0, "done")
    return replace(head, methods={k: methods[k] for k in METHODS if k in methods})
