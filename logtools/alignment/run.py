"""``run_alignment``: transfer alignment of the slave to the master (both on the master's clock).

Steps: check the inputs -> master quality (frozen output, attitude jumps = EKF resets) -> overlap ->
coarse mounting (Wahba/Kabsch on the angular rates of both units,
SVD) -> update epochs on the slave's IMU stamps (``update_hz``, default 20 Hz) -> body increments of
the slave IMU folded per segment (vectorised + numba) -> slave initialised from the master at the first
epoch -> closed-loop filter (kf.py) -> optional RTS smoother -> AlignmentResult with totals (coarse
mounting combined with the filter's residual), sigmas, convergence time, residual RMS, observability
flags and decimated histories.

Options (keyword, all optional): update_hz, lever_arm_m (3, master frame, master -> slave: known, or the
start of the estimate), estimate_lever_arm (velocity matching: the lever arm as 3 more states; the
result then reports it), lever_arm_sigma_m (its prior sigma, default LEVER_ARM_SIGMA_M), flexure (seed
000's second-order Markov flexure as 6 more states; "auto": added when the residuals call for them, see
FLEX_AUTO_NIS), flex_beta (1/s), flex_sigma_deg (one or per axis),
mounting_sigma_deg, gyro_bias_sigma_dph,
accel_bias_sigma_mg, gyro_arw_dpsh, accel_vrw_ug_psh (noise densities; estimated from the data when
absent), r_vel_m_s, r_att_arcsec (measurement noise; estimated when absent), delay_s (initial delay;
for kf-split the constant part shifted before the filter; for kf-delay, when absent, the delay state
starts from a coarse fit of the angular-rate magnitudes; delay_s=0 gives S004's augmentation alone),
delay_sigma_s, delay_max_s, delay_state (carry the delay state with any filter, e.g. hinf/ahinf:
S002's H-infinity filter with delay compensation), hinf_gamma,
lat_deg (when neither log has a position), mounting_guess_rpy_deg (skip the coarse step),
max_history_rows, recalibrate_noise (default True: when the first pass's mean NIS exceeds 3 x its
degrees of freedom, rerun with the measurement noise taken from the residual RMS).
"""
from __future__ import annotations

import weakref
from dataclasses import fields, replace
from typing import Callable

import numpy as np

from logtools.conventions import (ARCMIN, ARCSEC, DEG, DEG_PER_H, G0_M_S2, MG, UG, dcm_from_euler, dcm_from_quat,
                                  euler_from_dcm, quat_from_dcm, quat_make_continuous, quat_mul,
                                  rotvec_from_quat, quat_conj)
from logtools import earth
from logtools.errors import AnalysisError
from logtools.inslog import InsLog
from logtools.navcheck import output_validity
from logtools.results import AlignmentResult
from logtools.strapdown import body_increments, compose_segments

from .kf import FILTERS, AlignInputs, FilterRun, FilterSettings, MasterSeries, run_filter
from .model import MATCHES, StateLayout, exp_so3, make_layout

CONVERGED_ARCMIN = (1.0, 1.0, 2.0)  # roll, pitch, yaw thresholds on the mounting sigma
IMU_GAP_S = 0.25  # a step of the slave's IMU stamps beyond this (and beyond IMU_GAP_PERIODS of its median step)
IMU_GAP_PERIODS = 10.0  # is a gap: the slave's navigation restarts from the master after it (not bridged)
#: flexure="auto": without flexure states first; when the mean NIS exceeds FLEX_AUTO_NIS x dof, again with
#: them (FLEX_AUTO_MODEL unless flex_sigma_deg / flex_beta are given: seed 000's flexure), kept when the
#: mean NIS falls below FLEX_AUTO_GAIN x the first pass's
FLEX_AUTO_NIS = 10.0
FLEX_AUTO_GAIN = 0.5
FLEX_AUTO_MODEL = {"flex_sigma_deg": 0.05, "flex_beta": 2.0}
IMPLAUSIBLE_R_VEL_M_S = 1.0  # re-estimated measurement noise beyond these: a note that the filter did
IMPLAUSIBLE_R_ATT_DEG = 2.0  # ... not follow the data (no navigation output is that noisy)
COARSE_JOINT = True  # where the rates turn about one axis, rates and specific forces in one Wahba problem
COARSE_JOINT_RATIO = 0.05  # rates + specific forces: a start when the 2nd singular value is this much of the 1st
COARSE_MIN_FORCE_M_S2 = 0.02  # ... and the specific forces move (rms, 2nd principal axis) at least this much
LEVER_RATE_MAX_HALF_SPAN_S = 0.05  # a nav-only master's rate (lever arm) from its attitude differenced over
LEVER_RATE_ATTENUATION = 1e-4  # ... +- this at most, shorter where the motion would be attenuated beyond this
LEVER_ARM_SIGMA_M = 1.0  # prior sigma of an estimated lever arm (per axis, m)
LEVER_ARM_IMPLAUSIBLE_SIGMAS = 10.0  # an estimate beyond this many prior sigmas gets a note
OBSERVABLE_SHRINK = 0.5  # a state is observable when its sigma fell below this fraction of its prior
_KNOWN_OPTIONS = {
    "update_hz", "lever_arm_m", "estimate_lever_arm", "lever_arm_sigma_m", "flexure", "flex_beta", "flex_sigma_deg",
    "mounting_sigma_deg", "gyro_bias_sigma_dph", "accel_bias_sigma_mg", "gyro_arw_dpsh", "accel_vrw_ug_psh",
    "r_vel_m_s", "r_att_arcsec", "delay_s", "delay_sigma_s", "delay_max_s", "hinf_gamma", "lat_deg",
    "mounting_guess_rpy_deg", "max_history_rows", "recalibrate_noise", "delay_state",
}


def run_alignment(master: InsLog, slave: InsLog, *, filter: str = "kf", match: str = "vel+att",
                  smoother: bool = False, progress: Callable | None = None, **options) -> AlignmentResult:
    """Transfer alignment; ``slave`` already on the master's clock (DESIGN.md). See the module doc."""
    unknown = set(options) - _KNOWN_OPTIONS
    if unknown:
        raise AnalysisError(f"unknown alignment option(s): {', '.join(sorted(unknown))}")
    if filter not in FILTERS:
        raise AnalysisError(f"filter must be one of {', '.join(FILTERS)}, not {filter!r}")
    if match not in MATCHES:
        raise AnalysisError(f"match must be one of {', '.join(MATCHES)}, not {match!r}")
    src = slave.meta.source_path or "slave"
    # one time base: relative times of logs with different t0 are not comparable (a no-op when the slave
    # is already rebased, as compensate() leaves it)
    if slave.meta.t0_ns != master.meta.t0_ns:
        slave = slave.rebased(master.meta.t0_ns)
    if not (slave.has_gyro and slave.has_accel):
        raise AnalysisError(f"{src}: alignment needs the slave's IMU (angular rate and specific force)")
    if "att" in match and not master.has_quat:
        raise AnalysisError(f"{master.meta.source_path or 'master'}: match {match} needs the master's attitude")
    if "vel" in match and not master.has_vel:
        raise AnalysisError(f"{master.meta.source_path or 'master'}: match {match} needs the master's velocity")
    if filter in ("hinf", "ahinf"):
        try:
            from . import hinf  # noqa: F401
        except ImportError as exc:
            raise AnalysisError(f"filter {filter} not available ({exc})") from exc
    notes: list[str] = []
    prog = progress or (lambda f, s="": None)
    prog(0.0, "alignment: preparing")

    # ---- slave IMU, master series
    t_imu, gyro, accel = _slave_imu(slave, src)
    ms = _master_series_cached(master)
    # default update rate: 20 Hz, but not faster than the master's navigation output (interpolated
    # master samples between two updates would count the same information twice)
    nav_hz = 1.0 / float(np.median(np.diff(ms.t_s)))
    update_hz = float(options.get("update_hz", min(20.0, nav_hz)))
    delay_mode = filter in ("kf-delay", "kf-split") or bool(options.get("delay_state", False))
    tau0 = float(options.get("delay_s", 0.0))
    if delay_mode and filter != "kf-split" and "delay_s" not in options:
        # start the delay state near the answer: the EKF's linearisation in the delay holds over a
        # fraction of the motion's period only (S004), so a coarse start keeps it from diverging
        tau0, why = _coarse_delay(master, ms, t_imu, gyro, float(options.get("delay_max_s", 1.0)))
        notes.append(why)
    dt_upd = 1.0 / update_hz
    if filter == "kf-split":
        lo_tau, hi_tau = tau0 - dt_upd, tau0 + dt_upd
    else:
        dmax = float(options.get("delay_max_s", 1.0))
        lo_tau, hi_tau = (-dmax, dmax) if delay_mode else (tau0, tau0)
    # overlap: slave stamps t read the master at t - tau, tau within [lo, hi]; start and end on usable
    # master output (an EKF that has not started yet outputs frozen values)
    good = np.nonzero(ms.valid)[0] if ms.valid is not None else np.arange(len(ms.t_s))
    if len(good) < 3:
        raise AnalysisError(f"{master.meta.source_path or 'master'}: the master's attitude/velocity is frozen "
                            "or jumping over the whole log")
    t_a = max(t_imu[0], ms.t_s[good[0]] + hi_tau)
    t_b = min(t_imu[-1], ms.t_s[good[-1]] + lo_tau)
    if not t_b - t_a > 5 * dt_upd:
        raise AnalysisError(f"{src}: no time overlap between the master's nav and the slave's IMU "
                            f"(slave {t_imu[0]:.2f}..{t_imu[-1]:.2f} s, master {ms.t_s[0]:.2f}..{ms.t_s[-1]:.2f} s)")
    sel = (t_imu >= t_a) & (t_imu <= t_b)
    t_imu, gyro, accel = t_imu[sel], gyro[sel], accel[sel]
    if len(t_imu) < 10:
        raise AnalysisError(f"{src}: too few slave IMU samples in the overlap ({len(t_imu)})")
    _check_motion(gyro, accel, src)

    # ---- coarse mounting
    if "mounting_guess_rpy_deg" in options:
        r0 = dcm_from_euler(np.radians(np.asarray(options["mounting_guess_rpy_deg"], float)))
        coarse_ok = True
    else:
        r0, coarse_ok, why = _coarse_mounting(master, slave, ms, t_imu, gyro, tau0, accel)
        if why:
            notes.append(why)

    # ---- epochs and segments
    grid = np.arange(t_imu[0], t_imu[-1] + 1e-9, dt_upd)
    idx = np.unique(np.clip(np.searchsorted(t_imu, grid - 1e-9), 0, len(t_imu) - 1))
    if len(idx) < 5:
        raise AnalysisError(f"{src}: overlap too short for alignment ({t_b - t_a:.2f} s)")
    rv, dv, _ = body_increments(t_imu[idx[0]:idx[-1] + 1], gyro[idx[0]:idx[-1] + 1], accel[idx[0]:idx[-1] + 1])
    starts, stops = idx[:-1] - idx[0], idx[1:] - idx[0]
    seg_dq, seg_dv = compose_segments(rv, dv, starts, stops)
    t_ep = t_imu[idx]
    seg_dt = np.diff(t_ep)
    # gaps in the slave's IMU: the motion over them is unknown, so the slave's navigation restarts from
    # the master after each one (the mounting, biases and their covariance carry on)
    steps = np.diff(t_imu[idx[0]:idx[-1] + 1])
    gap_s = max(IMU_GAP_S, IMU_GAP_PERIODS * float(np.median(steps)))
    seg_max = np.maximum.reduceat(steps, starts)
    restart = np.concatenate([[False], seg_max > gap_s])
    if restart.any():
        notes.append(f"{int(restart.sum())} gap(s) in the slave's IMU (longest {float(seg_max.max()):.2f} s): "
                     "its navigation restarted from the master after each")

    # ---- initial state from the master at the first epoch
    lever0 = np.asarray(options.get("lever_arm_m", np.zeros(3)), float)
    c_nm0, v_m0, _, w_m0 = ms.sample(t_ep[0] - tau0)
    if c_nm0 is not None:
        q0 = quat_from_dcm(c_nm0 @ r0.T)
    elif slave.has_quat:
        tq, qs = slave.quat_wxyz()
        q0 = qs[int(np.clip(np.searchsorted(tq, t_ep[0]), 0, len(tq) - 1))]
        notes.append("initial slave attitude from the slave's own attitude (the master has none)")
    else:
        raise AnalysisError(f"{src}: velocity matching needs an initial attitude: neither the master nor "
                            "the slave log has one")
    if v_m0 is not None:
        cm = c_nm0 if c_nm0 is not None else np.eye(3)
        v0 = v_m0 + cm @ np.cross(w_m0 if w_m0 is not None else np.zeros(3), lever0)
    elif slave.has_vel:
        tv, vs = slave.vel_ned_m_s()
        v0 = vs[int(np.clip(np.searchsorted(tv, t_ep[0]), 0, len(tv) - 1))]
    else:
        v0 = np.zeros(3)
        notes.append("initial slave velocity set to zero (neither log has a velocity)")
    llh0 = _initial_position(master, slave, t_ep[0], options, notes)

    # ---- settings
    flex_opt = options.get("flexure", False)
    flex_auto = isinstance(flex_opt, str) and flex_opt == "auto"

    def setup(flexure: bool) -> tuple[StateLayout, FilterSettings, np.ndarray]:
        ly = make_layout(match, flexure=flexure, lever_arm=bool(options.get("estimate_lever_arm", False)),
                         delay=delay_mode)
        opts = {**FLEX_AUTO_MODEL, **options} if flex_auto else options
        st, s0 = _settings(filter, ly, master, t_imu, gyro, accel, opts, coarse_ok, dt_upd, tau0,
                           (lo_tau, hi_tau), smoother)
        return ly, st, s0

    lay, settings, sig0 = setup(bool(flex_opt) and not flex_auto)
    if smoother:
        need_gb = len(t_ep) * lay.n**2 * 8 * 3 / 1e9
        if need_gb > 2.0:
            raise AnalysisError(f"{src}: the RTS smoother would store {need_gb:.1f} GB for {t_b - t_a:.0f} s at "
                                f"{update_hz:g} Hz; lower update_hz or run without the smoother")
    inp = AlignInputs(t_ep, seg_dq, seg_dv, seg_dt, ms, q0, v0, llh0, r0, lever0, tau0, restart)
    prog(0.05, "alignment filter")
    sub = (lambda f, s="": prog(0.05 + 0.9 * f, s)) if progress else None
    run = run_filter(inp, settings, progress=sub)
    nis_rigid = _mean_nis(run)
    if flex_auto and lay.flex_ang is None and nis_rigid > FLEX_AUTO_NIS * lay.n_meas:
        # residuals far beyond the noise model: is it a flexing slave? The flexure states are kept when
        # they explain most of the excess (mean NIS down by FLEX_AUTO_GAIN at least)
        lay_f, st_f, sig0_f = setup(True)
        run_f = run_filter(inp, st_f, progress=None)
        if _mean_nis(run_f) < FLEX_AUTO_GAIN * nis_rigid:
            notes.append(f"flexure states added (mean NIS/dof {nis_rigid / lay.n_meas:.1f} without them, "
                         f"{_mean_nis(run_f) / lay_f.n_meas:.1f} with)")
            lay, settings, sig0, run = lay_f, st_f, sig0_f, run_f
    if lay.flex_ang is not None:
        notes.append(f"flexure states (seed 000 eq 8): sigma {_fmt3(np.degrees(sig0[lay.flex_ang]))} deg, "
                     f"beta {settings.flex_beta:.3g} 1/s")
    recal = _recalibrated(run, lay, settings, options) if options.get("recalibrate_noise", True) else None
    if recal is not None:
        # the residuals are far larger than the noise model says (real data: vibration, EKF smoothing,
        # flexure): rerun with the measurement noise taken from the first pass's residuals
        nis0 = _mean_nis(run)
        settings = recal
        run = run_filter(inp, settings, progress=None)
        notes.append(f"measurement noise re-estimated from the residuals (first pass NIS/dof "
                     f"{nis0 / lay.n_meas:.1f}): velocity {settings.r_vel_m_s:.3g} m/s, attitude "
                     f"{settings.r_att_rad / DEG:.3g} deg")
        if settings.r_vel_m_s > IMPLAUSIBLE_R_VEL_M_S or settings.r_att_rad > IMPLAUSIBLE_R_ATT_DEG * DEG:
            notes.append("residuals this large are no INS's noise: the filter did not follow the data (a wrong "
                         "start, an uncompensated delay or reset, other units); the mounting is doubtful")
    res = _result(run, lay, settings, sig0, filter, match, options, notes)
    prog(1.0, "alignment done")
    return res


# ---- inputs ---------------------------------------------------------------------------------------
def _slave_imu(slave: InsLog, src: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = slave.t_imu_s()
    g = slave.gyro_rad_s()
    a = slave.accel_m_s2()
    ok = np.isfinite(t) & np.isfinite(g).all(1) & np.isfinite(a).all(1)
    t, g, a = t[ok], g[ok], a[ok]
    if len(t) < 10:
        raise AnalysisError(f"{src}: the slave's IMU has fewer than 10 finite samples")
    order = np.argsort(t, kind="stable")
    t, g, a = t[order], g[order], a[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    return t[keep], g[keep], a[keep]


_LAST_MASTER: list = []  # [(weak ref to the master, its series)]: the one most recently prepared


def _master_series_cached(master: InsLog) -> MasterSeries:
    """:func:`_master_series`, prepared once for the same master object (analyze runs the alignment
    before and after compensation against one master; InsLog is immutable)."""
    if _LAST_MASTER and _LAST_MASTER[0][0]() is master:
        return _LAST_MASTER[0][1]
    ms = _master_series(master)
    for f in fields(ms):  # shared between runs: read-only
        v = getattr(ms, f.name)
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
    # held weakly: the series goes when the master does (a batch does not keep the last pair's master)
    ref = weakref.ref(master)
    _LAST_MASTER[:] = [(ref, ms)]
    weakref.finalize(master, _forget_master, ref)
    return ms


def _forget_master(ref) -> None:
    if _LAST_MASTER and _LAST_MASTER[0][0] is ref:
        _LAST_MASTER.clear()


def _master_series(master: InsLog) -> MasterSeries:
    src = master.meta.source_path or "master"
    t_nav = master.t_nav_s()
    if len(t_nav) < 3:
        raise AnalysisError(f"{src}: the master has fewer than 3 navigation samples")
    quat = vel = acc = w = None
    cols_t = []
    if master.has_quat:
        tq, q = master.quat_wxyz()
        cols_t.append(tq)
    if master.has_vel:
        tv, v = master.vel_ned_m_s()
        cols_t.append(tv)
    if master.has_quat and master.has_vel:
        t, q, v = _nav_common_stamps(tq, q, tv, v)  # q, v at t
    else:
        t = np.unique(cols_t[0])
        if master.has_quat:
            q = q[np.searchsorted(tq, t)]
        else:
            v = v[np.searchsorted(tv, t)]
    if len(t) < 3:
        raise AnalysisError(f"{src}: the master's attitude and velocity overlap in fewer than 3 samples")
    if master.has_quat:
        ok = np.isfinite(q).all(1)
        quat = quat_make_continuous(q / np.linalg.norm(q, axis=1, keepdims=True))
    else:
        ok = np.ones(len(t), bool)
    if master.has_vel:
        ok &= np.isfinite(v).all(1)
    t = t[ok]
    if len(t) < 3:
        raise AnalysisError(f"{src}: the master has fewer than 3 finite navigation samples")
    if quat is not None:
        quat = quat[ok]
        # body rate relative to NED in the master frame (lever arm): from the master's gyro when it has
        # one (minus the earth rate), else from its attitude differenced over ~0.1 s (a noisy rate in H
        # would bias the lever-arm estimate toward zero: errors in variables)
        w = None
        if master.has_gyro:
            tg, g = master.t_imu_s(), master.gyro_rad_s()
            okg = np.isfinite(g).all(1)
            if okg.sum() >= 2:
                w_ib = _interp_cols(t, tg[okg], g[okg])
                lat = np.radians(master.lat_lon_alt()[1][0, 0]) if master.has_pos else np.radians(45.0)
                w_ie_m = np.einsum("kji,j->ki", dcm_from_quat(quat), earth.earth_rate_ned(lat))
                w = w_ib - w_ie_m
        if w is None:
            w = _rate_from_attitude(t, quat)
    if master.has_vel:
        vel = v[ok]
        acc = _derivative(t, vel, span_s=0.1)
    valid, resets = _master_quality(master, t, quat, vel)
    return MasterSeries(t, quat, vel, acc, w, valid, resets)


#: the attitude's and the velocity's stamps are taken as one set when they share at least this fraction of
#: the sparser stream's stamps (one EKF output); else each is a stream of its own (ATT 10 Hz, GPS 5 Hz)
NAV_SHARED_STAMPS = 0.9
NAV_GAP_STEPS = 3.0  # an interpolated stream's step beyond this many of its median steps is a gap (dropped)


def _nav_common_stamps(tq: np.ndarray, q: np.ndarray, tv: np.ndarray, v: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, quat, vel) of a master whose attitude and velocity come with their own stamps and rates.

    Where they share (nearly) all stamps (one EKF output), the shared stamps. Else the sparser stream's
    stamps inside the other's span, the denser interpolated at them (the attitude by normalised linear
    interpolation of sign-continuous quaternions, the velocity linearly; samples in a gap of the
    interpolated stream dropped): each measurement used once, at its own instant, at the sparser rate
    (the filter's update rate follows it), the interpolation's small error left to the measurement noise
    the filter estimates from its residuals."""
    t_shared = np.intersect1d(tq, tv)
    if len(t_shared) >= NAV_SHARED_STAMPS * min(len(np.unique(tq)), len(np.unique(tv))):
        return t_shared, q[np.searchsorted(tq, t_shared)], v[np.searchsorted(tv, t_shared)]
    okq, okv = np.isfinite(q).all(1), np.isfinite(v).all(1)
    tq, q, tv, v = tq[okq], q[okq], tv[okv], v[okv]
    tq, iq = np.unique(tq, return_index=True)
    tv, iv = np.unique(tv, return_index=True)
    q, v = q[iq], v[iv]
    if len(tq) < 2 or len(tv) < 2:
        return np.zeros(0), q[:0], v[:0]
    q = quat_make_continuous(q / np.linalg.norm(q, axis=1, keepdims=True))
    if len(tv) <= len(tq):  # attitude onto the velocity's stamps
        t = tv[(tv >= tq[0]) & (tv <= tq[-1])]
        src_t, src_y = tq, q
    else:
        t = tq[(tq >= tv[0]) & (tq <= tv[-1])]
        src_t, src_y = tv, v
    j = np.clip(np.searchsorted(src_t, t), 1, len(src_t) - 1)
    keep = (src_t[j] - src_t[j - 1]) <= NAV_GAP_STEPS * float(np.median(np.diff(src_t)))
    t = t[keep]
    y = _interp_cols(t, src_t, src_y)
    if len(tv) <= len(tq):
        return t, y / np.linalg.norm(y, axis=1, keepdims=True), v[np.searchsorted(tv, t)]
    return t, q[np.searchsorted(tq, t)], y


def _rate_from_attitude(t: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Body rate relative to NED (master frame) from the attitude, central differences over +- h.

    h is the longest span (at most LEVER_RATE_MAX_HALF_SPAN_S: the fewer the samples differenced, the noisier
    the rate, and a noisy rate in H biases the lever arm toward zero, errors in variables) whose
    attenuation of the motion stays below LEVER_RATE_ATTENUATION at its rate-weighted mean frequency (the
    difference quotient's gain is sin(2 pi f h) / (2 pi f h)). A fixed +- 0.05 s took 2-6 % off a
    multirotor's 1-2 Hz rates: with a 2.9 m lever arm and flexure states its mounting came out 2.5 arcmin
    off at a sigma of 0.37 arcmin; +- one 100 Hz sample: 0.6 arcmin."""
    dt_med = float(np.median(np.diff(t)))

    def diff_rate(y: np.ndarray, half_s: float, rot: bool) -> np.ndarray:
        kk = max(int(round(half_s / dt_med)), 1)
        i0 = np.clip(np.arange(len(t)) - kk, 0, len(t) - 1)
        i1 = np.clip(np.arange(len(t)) + kk, 0, len(t) - 1)
        span = np.maximum(t[i1] - t[i0], 1e-9)[:, None]
        return (rotvec_from_quat(quat_mul(quat_conj(y[i0]), y[i1])) if rot else y[i1] - y[i0]) / span

    w = diff_rate(quat, LEVER_RATE_MAX_HALF_SPAN_S, True)
    dw = diff_rate(w, LEVER_RATE_MAX_HALF_SPAN_S, False)
    motion = float(np.sqrt(np.mean(np.sum((w - w.mean(axis=0)) ** 2, axis=1))))
    f_hz = float(np.sqrt(np.mean(np.sum(dw ** 2, axis=1)))) / (2.0 * np.pi * motion) if motion > 0 else 0.0
    # sin(x)/x = 1 - x^2/6: below the attenuation a up to x = sqrt(6 a)
    h = np.sqrt(6.0 * LEVER_RATE_ATTENUATION) / (2.0 * np.pi * f_hz) if f_hz > 0 else np.inf
    if h >= LEVER_RATE_MAX_HALF_SPAN_S:
        return w
    return diff_rate(quat, h, True)


def _master_quality(master: InsLog, t: np.ndarray, quat: np.ndarray | None, vel: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(valid mask, reset times) of the master's output (``logtools.navcheck``), its attitude increments
    checked against its own gyro where it logs one."""
    rate = None
    if quat is not None and len(t) > 3 and master.has_gyro:
        tg, g = master.t_imu_s(), master.gyro_rad_s()
        okg = np.isfinite(g).all(1)
        mid = 0.5 * (t[:-1] + t[1:])
        rate = np.linalg.norm(_interp_cols(mid, tg[okg], g[okg]), axis=1)
    return output_validity(t, quat, vel, rate)


def _interp_cols(t: np.ndarray, tp: np.ndarray, yp: np.ndarray) -> np.ndarray:
    """Each column of ``yp`` (n, k), sampled at ``tp``, linearly interpolated at ``t`` (clamped at the ends)."""
    return np.stack([np.interp(t, tp, yp[:, i]) for i in range(yp.shape[1])], -1)


def _derivative(t: np.ndarray, y: np.ndarray, span_s: float) -> np.ndarray:
    """Central difference over ~span_s (noise-tolerant), one-sided at the ends."""
    dt = float(np.median(np.diff(t)))
    k = max(int(round(0.5 * span_s / dt)), 1)
    n = len(t)
    i0 = np.clip(np.arange(n) - k, 0, n - 1)
    i1 = np.clip(np.arange(n) + k, 0, n - 1)
    return (y[i1] - y[i0]) / np.maximum(t[i1] - t[i0], 1e-9)[:, None]


def _check_motion(gyro: np.ndarray, accel: np.ndarray, src: str) -> None:
    if np.ptp(gyro, axis=0).max() < 1e-9 and np.ptp(accel, axis=0).max() < 1e-9:
        raise AnalysisError(f"{src}: no motion: the slave's IMU readings are constant over the overlap")


def _coarse_mounting(master: InsLog, slave: InsLog, ms: MasterSeries, t_imu: np.ndarray, gyro: np.ndarray,
                     tau0: float, accel: np.ndarray | None = None) -> tuple[np.ndarray, bool, str]:
    """(R0, ok, note). Wahba/Kabsch on angular rates: min sum |w_s - R w_m|^2 by SVD of sum w_s w_m^T. Where
    the rates turn about one axis only, the specific forces' motion joins them (``accel``: the slave's, at
    t_imu); then the slave's own attitude; then that joint fit however weakly it is determined (not ok: a
    wider prior); else the identity (not ok)."""
    grid = np.arange(t_imu[0], t_imu[-1], 0.02)
    if master.has_gyro:
        tm = master.t_imu_s()
        gm = master.gyro_rad_s()
        okm = np.isfinite(gm).all(1)
        w_m = _interp_cols(grid - tau0, tm[okm], gm[okm])
    elif ms.w_nm_m is not None:
        w_m = _interp_cols(grid - tau0, ms.t_s, ms.w_nm_m)
    else:
        w_m = None
    weak = None  # a joint rate + specific-force start that is only weakly determined

    def wahba(B: np.ndarray) -> np.ndarray:
        u, _, vt = np.linalg.svd(B)
        return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt

    if w_m is not None:
        w_s = _interp_cols(grid, t_imu, gyro)
        # remove slow parts (biases, earth rate) so the fit sees the motion
        w_s = w_s - w_s.mean(0)
        w_m = w_m - w_m.mean(0)
        b = w_s.T @ w_m
        sv = np.linalg.svd(b, compute_uv=False)
        motion = np.sqrt(sv / max(len(grid), 1))  # rms rate on the principal axes
        if sv[0] > 0 and motion[1] > 2e-3 and sv[1] / sv[0] > 1e-3:
            return wahba(b), True, ""
        why = "coarse mounting: too little rotation about two axes for the rate fit"
        # a car turning on a level road rotates about one axis: its accelerations (speed changes along the
        # track, centripetal across it) give another direction, and two fix a rotation. Rates and specific
        # forces (motion parts, each set normalised by its power) in one Wahba problem
        f_m = _master_specific_force(master, ms, grid - tau0) if COARSE_JOINT and accel is not None else None
        if f_m is not None:
            f_s = _interp_cols(grid, t_imu, accel)
            f_m, f_s = f_m - f_m.mean(0), f_s - f_s.mean(0)
            pw, pf = float(np.trace(w_m.T @ w_m)), float(np.trace(f_m.T @ f_m))
            bf = f_s.T @ f_m
            motion_f = np.sqrt(np.linalg.svd(bf, compute_uv=False) / max(len(grid), 1))  # m/s^2 rms
            # two directions of real motion, not noise: the rates' first and the specific forces' first, or
            # the specific forces' first two (whether they differ, the joint fit's singular values say)
            real = motion_f[0] > COARSE_MIN_FORCE_M_S2 and (motion[0] > 2e-3 or motion_f[1] > COARSE_MIN_FORCE_M_S2)
            if real and pw > 0 and pf > 0:
                B = b / pw + bf / pf
                svj = np.linalg.svd(B, compute_uv=False)
                if svj[1] / svj[0] >= COARSE_JOINT_RATIO:
                    return wahba(B), True, why + "; rates and specific forces together instead"
                weak = wahba(B)
    else:
        why = "coarse mounting: the master has no angular rate or attitude"
    if slave.has_quat and ms.quat is not None:
        ts, qs = slave.quat_wxyz()
        qm = _interp_cols(ts - tau0, ms.t_s, ms.quat)
        inside = (ts - tau0 >= ms.t_s[0]) & (ts - tau0 <= ms.t_s[-1])
        if inside.sum() >= 1:
            m = np.einsum("kji,kjl->il", dcm_from_quat(qs[inside]), dcm_from_quat(qm[inside]))  # sum C_sn C_nm
            return wahba(m), True, why + "; used the slave's own attitude instead"
    if weak is not None:
        return weak, False, why + "; rates and specific forces together, weakly determined (wider prior)"
    return np.eye(3), False, why + "; started from a zero mounting"


def _master_specific_force(master: InsLog, ms: MasterSeries, t: np.ndarray) -> np.ndarray | None:
    """The master's specific force (m/s^2, master body frame) at t: its accelerometers where it logs them,
    else from its navigation solution (an INS logging only its output), C_bn (dv/dt - g_n), the small
    Coriolis and transport terms left out (a coarse start). None without either."""
    if master.has_accel:
        ta, fa = master.t_imu_s(), master.accel_m_s2()
        ok = np.isfinite(fa).all(1)
        if ok.sum() >= 2:
            return _interp_cols(t, ta[ok], fa[ok])
    if ms.acc is None or ms.quat is None:
        return None
    ok = np.isfinite(ms.acc).all(1) & np.isfinite(ms.quat).all(1)
    if ok.sum() < 2:
        return None
    a_n = _interp_cols(t, ms.t_s[ok], ms.acc[ok])
    q = _interp_cols(t, ms.t_s[ok], ms.quat[ok])
    f_n = a_n - np.array([0.0, 0.0, G0_M_S2])
    return np.einsum("kji,kj->ki", dcm_from_quat(q / np.linalg.norm(q, axis=1, keepdims=True)), f_n)


def _coarse_delay(master: InsLog, ms: MasterSeries, t_imu: np.ndarray, gyro: np.ndarray, max_s: float
                  ) -> tuple[float, str]:
    """(tau0, note): the lag (slave stamp - master stamp) minimising the mismatch of the angular-rate
    MAGNITUDES (independent of the mounting), coarse (10 ms) then fine (1 ms)."""
    if master.has_gyro:
        tm, gm = master.t_imu_s(), master.gyro_rad_s()
        okm = np.isfinite(gm).all(1)
        tm, wm = tm[okm], np.linalg.norm(gm[okm], axis=1)
    elif ms.w_nm_m is not None:
        tm, wm = ms.t_s, np.linalg.norm(ms.w_nm_m, axis=1)
    else:
        return 0.0, "delay state started at 0 (the master has no angular rate or attitude)"
    ws = np.linalg.norm(gyro, axis=1)
    lo, hi = max(t_imu[0], tm[0] + max_s), min(t_imu[-1], tm[-1] - max_s)
    if hi - lo < 2.0 or np.std(ws) < 1e-3:
        return 0.0, "delay state started at 0 (too little motion or overlap for a coarse delay)"

    def cost(lags: np.ndarray, step: float) -> np.ndarray:
        grid = np.arange(lo, hi, step)
        s_w = np.interp(grid, t_imu, ws)
        return np.array([np.mean((s_w - np.interp(grid - lag, tm, wm)) ** 2) for lag in lags])

    lags = np.arange(-max_s, max_s + 1e-9, 0.01)
    best = lags[int(np.argmin(cost(lags, 0.01)))]
    fine = np.arange(best - 0.015, best + 0.015 + 1e-9, 0.001)
    tau0 = float(fine[int(np.argmin(cost(fine, 0.0025)))])
    return tau0, f"delay state started at {tau0 * 1e3:+.0f} ms (angular-rate magnitudes)"


def _initial_position(master: InsLog, slave: InsLog, t0: float, options: dict, notes: list[str]) -> np.ndarray:
    for log in (master, slave):
        if log.has_pos:
            tp, p = log.lat_lon_alt()
            i = int(np.clip(np.searchsorted(tp, t0), 0, len(tp) - 1))
            return np.array([np.radians(p[i, 0]), np.radians(p[i, 1]), p[i, 2]])
    lat = float(options.get("lat_deg", 45.0))
    notes.append(f"no position in either log: latitude {lat:g} deg assumed (earth rate, gravity)")
    return np.array([np.radians(lat), 0.0, 0.0])


# ---- noise and priors -----------------------------------------------------------------------------
def _hf_sigma(y: np.ndarray) -> float:
    """White-noise sigma from third differences (robust: MAD); smooth motion cancels."""
    if len(y) < 8:
        return 0.0
    d3 = np.diff(y, n=3, axis=0)
    mad = np.median(np.abs(d3 - np.median(d3, axis=0)), axis=0) * 1.4826
    return float(np.max(mad) / np.sqrt(20.0))


def _settings(kind: str, lay: StateLayout, master: InsLog, t_imu, gyro, accel, options: dict, coarse_ok: bool,
              dt_upd: float, tau0: float, tau_bounds: tuple[float, float], smoother: bool
              ) -> tuple[FilterSettings, np.ndarray]:
    dt_imu = float(np.median(np.diff(t_imu)))
    # slave noise densities from the data (sample sigma * sqrt(dt)), with floors
    if "gyro_arw_dpsh" in options:
        arw = float(options["gyro_arw_dpsh"]) * DEG / 60.0
    else:
        arw = max(_hf_sigma(gyro) * np.sqrt(dt_imu), 0.002 * DEG / 60.0)
    if "accel_vrw_ug_psh" in options:
        vrw = float(options["accel_vrw_ug_psh"]) * UG
    else:
        vrw = max(_hf_sigma(accel) * np.sqrt(dt_imu), 5.0 * UG)
    arw_dpsh = arw / (DEG / 60.0)
    vrw_ug = vrw / UG
    # bias priors from the sensor grade its noise reveals (navigation grade ~0.002 deg/rt-h, 20 ug/rt-Hz;
    # MEMS ~0.2-1 deg/rt-h, 150-400 ug/rt-Hz); options override
    sg_gyro = float(options.get("gyro_bias_sigma_dph", np.clip(300.0 * arw_dpsh, 2.0, 2000.0))) * DEG_PER_H
    sg_acc = float(options.get("accel_bias_sigma_mg",
                               np.clip(0.01 * vrw_ug * max(1.0, vrw_ug / 50.0), 0.1, 50.0))) * MG
    sg_mount = float(options.get("mounting_sigma_deg", 1.0 if coarse_ok else 5.0)) * DEG
    # measurement noise from the master's data, with floors
    tq, q = master.quat_wxyz() if master.has_quat else (None, None)
    if "r_att_arcsec" in options:
        r_att = float(options["r_att_arcsec"]) * ARCSEC
    elif q is not None and len(q) > 8:
        rv = rotvec_from_quat(quat_mul(quat_conj(q[:1]), quat_make_continuous(q)))
        r_att = max(_hf_sigma(rv), 1.0 * ARCSEC)
    else:
        r_att = 10.0 * ARCSEC
    if "r_vel_m_s" in options:
        r_vel = float(options["r_vel_m_s"])
    elif master.has_vel:
        r_vel = max(_hf_sigma(master.vel_ned_m_s()[1]), 5e-4)
    else:
        r_vel = 0.01
    n = lay.n
    sig = np.zeros(n)
    qc = np.zeros(n)
    sig[lay.att] = sg_mount
    qc[lay.att] = arw**2
    sig[lay.gyro] = sg_gyro
    qc[lay.gyro] = (0.01 * sg_gyro) ** 2 / 3600.0
    if lay.vel is not None:
        sig[lay.vel] = 0.1
        qc[lay.vel] = vrw**2
        sig[lay.accel] = sg_acc
        qc[lay.accel] = (0.01 * sg_acc) ** 2 / 3600.0
    if lay.mount is not None:
        sig[lay.mount] = sg_mount
    beta = float(options.get("flex_beta", 0.5))
    if lay.flex_ang is not None:
        s_l = np.broadcast_to(np.asarray(options.get("flex_sigma_deg", 0.05), float), (3,)) * DEG
        sig[lay.flex_ang] = s_l
        sig[lay.flex_rate] = s_l * beta
        qc[lay.flex_rate] = 4.0 * beta**3 * s_l**2
    if lay.lever is not None:
        sig[lay.lever] = float(options.get("lever_arm_sigma_m", LEVER_ARM_SIGMA_M))
    if lay.delay is not None:
        if kind == "kf-split":
            sig[lay.delay] = dt_upd / np.sqrt(3.0)
        else:
            sig[lay.delay] = float(options.get("delay_sigma_s", 0.1))
    st = FilterSettings(kind=kind, layout=lay, p0_sigma=sig, qc=qc, r_vel_m_s=r_vel, r_att_rad=r_att,
                        flex_beta=beta, delay_bounds_s=tau_bounds,
                        hinf_gamma=float(options.get("hinf_gamma", 1.0)), smoother=smoother)
    return st, sig


def _mean_nis(run: FilterRun) -> float:
    v = run.nis[np.isfinite(run.nis)]
    return float(np.mean(v[len(v) // 10:])) if len(v) else float("nan")


def _recalibrated(run: FilterRun, lay: StateLayout, st: FilterSettings, options: dict) -> FilterSettings | None:
    """Settings with the measurement noise from the residual RMS when the mean NIS exceeds 3 x dof
    (and the user did not fix the noise)."""
    nis = _mean_nis(run)
    if not (nis > 3.0 * lay.n_meas):
        return None
    e = run.innov[np.isfinite(run.innov).all(1)]
    e = e[len(e) // 10:]
    r_vel, r_att = st.r_vel_m_s, st.r_att_rad
    col = 0
    if lay.uses_vel:
        if "r_vel_m_s" not in options:
            r_vel = max(r_vel, float(np.sqrt(np.mean(e[:, :3] ** 2))))
        col = 3
    if lay.uses_att and "r_att_arcsec" not in options:
        r_att = max(r_att, float(np.sqrt(np.mean(e[:, col:col + 3] ** 2))))
    if r_vel == st.r_vel_m_s and r_att == st.r_att_rad:
        return None
    return replace(st, r_vel_m_s=r_vel, r_att_rad=r_att)


# ---- result ---------------------------------------------------------------------------------------
def _euler_jacobian(r: np.ndarray) -> np.ndarray:
    """d euler(exp(-[mu x]) R) / d mu at mu = 0 (central differences)."""
    j = np.zeros((3, 3))
    e = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = e
        a = euler_from_dcm(exp_so3(-d) @ r)
        b = euler_from_dcm(exp_so3(d) @ r)
        diff = a - b
        diff = (diff + np.pi) % (2 * np.pi) - np.pi
        j[:, i] = diff / (2 * e)
    return j


def _mean_rotation(ms: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(ms.sum(0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _result(run: FilterRun, lay: StateLayout, st: FilterSettings, sig0: np.ndarray, kind: str, match: str,
            options: dict, notes: list[str]) -> AlignmentResult:
    ne = len(run.t_s)
    k_rep = ne // 2 if run.smoothed else ne - 1
    # a-posteriori variance factor: when the residuals exceed the noise model (mean NIS > dof), the
    # reported sigmas are scaled by sqrt(NIS/dof) (the filter's own histories are left as they are)
    nis_m = _mean_nis(run)
    sig_scale = float(np.sqrt(max(1.0, nis_m / lay.n_meas))) if np.isfinite(nis_m) else 1.0
    if sig_scale > 1.05:
        notes.append(f"reported sigmas scaled by {sig_scale:.2f} = sqrt(mean NIS / dof)")
    # mounting totals per epoch
    if lay.mount is not None:
        r_ep = run.r_hat
    elif run.c_nm is not None:
        r_ep = np.einsum("kji,kjl->kil", run.c_ns, run.c_nm)  # C_sn C_nm
    else:
        r_ep = None
    if r_ep is not None:
        if lay.mount is None:  # velocity matching: average the last tenth (master attitude noise)
            r_fin = _mean_rotation(r_ep[max(k_rep - max(ne // 10, 1), 0):k_rep + 1])
        else:
            r_fin = r_ep[k_rep]
        jac = _euler_jacobian(r_fin)
        rpy = euler_from_dcm(r_fin)
        cov_e = np.einsum("ij,kjl,ml->kim", jac, run.p_mount, jac)
        sig_e = np.sqrt(np.maximum(np.einsum("kii->ki", cov_e), 0.0))
        mount_rpy = tuple(float(x) for x in np.degrees(rpy))
        mount_sig = tuple(float(x) for x in sig_scale * np.degrees(sig_e[k_rep]))
        hist_mount = np.degrees(euler_from_dcm(r_ep))
        # keep yaw continuous around the final value
        hist_mount = rpy_unwrap(hist_mount, np.degrees(rpy))
    else:
        notes.append("mounting not determined: the master has no attitude")
        mount_rpy = (float("nan"),) * 3
        mount_sig = (float("nan"),) * 3
        sig_e = np.full((ne, 3), np.nan)
        hist_mount = np.full((ne, 3), np.nan)
    # convergence (forward filter sigma; the smoother's is not a convergence)
    conv = None
    if r_ep is not None:
        p_fwd = run.p_mount_fwd if run.p_mount_fwd is not None else run.p_mount
        cov_f = np.einsum("ij,kjl,ml->kim", jac, p_fwd, jac)
        sig_f = np.sqrt(np.maximum(np.einsum("kii->ki", cov_f), 0.0))
        thr = np.array(CONVERGED_ARCMIN) * ARCMIN / DEG
        ok = (np.degrees(sig_f) < thr).all(1)
        if ok[-1]:
            bad = np.nonzero(~ok)[0]
            first = 0 if len(bad) == 0 else bad[-1] + 1
            conv = float(run.t_s[first] - run.t_s[0])
    gb = run.x[k_rep, lay.gyro] / DEG_PER_H
    gbs = sig_scale * np.sqrt(run.p_diag[k_rep, lay.gyro]) / DEG_PER_H
    if lay.accel is not None:
        ab = run.x[k_rep, lay.accel] / MG
        abs_ = sig_scale * np.sqrt(run.p_diag[k_rep, lay.accel]) / MG
    else:
        ab = np.full(3, np.nan)
        abs_ = np.full(3, np.nan)
        notes.append("accelerometer bias not estimated: attitude matching only")
    # observability: sigma shrink relative to the prior
    obs: dict[str, bool] = {}
    p_fin = np.sqrt(run.p_diag[k_rep])
    if r_ep is not None:
        s0m = np.degrees(sig0[lay.mount] if lay.mount is not None else sig0[lay.att])
        for i, ax in enumerate(("roll", "pitch", "yaw")):
            obs[f"mounting_{ax}"] = bool(np.degrees(sig_e[k_rep, i]) < OBSERVABLE_SHRINK * s0m[i])
    for name, sl in (("gyro_bias", lay.gyro), ("accel_bias", lay.accel), ("lever_arm", lay.lever)):
        if sl is None:
            continue
        for i, ax in enumerate("xyz"):
            obs[f"{name}_{ax}"] = bool(p_fin[sl][i] < OBSERVABLE_SHRINK * sig0[sl][i])
    if lay.delay is not None:
        obs["delay"] = bool(p_fin[lay.delay] < OBSERVABLE_SHRINK * sig0[lay.delay])
    unobs = [k for k, v in obs.items() if not v]
    if unobs:
        notes.append("not observable with this motion (sigma did not shrink below "
                     f"{OBSERVABLE_SHRINK:g} x prior): {', '.join(unobs)}; values are the prior, not estimates")
    # residuals
    rn: list[str] = []
    scale = []
    if lay.uses_vel:
        rn += ["vel_n_m_s", "vel_e_m_s", "vel_d_m_s"]
        scale += [1.0] * 3
    if lay.uses_att:
        rn += ["att_n_deg", "att_e_deg", "att_d_deg"]
        scale += [1.0 / DEG] * 3
    resid = run.innov * np.array(scale)
    rms: dict[str, float] = {}
    valid = np.isfinite(resid).all(1)
    half = valid & (np.arange(ne) >= ne // 10)  # skip the initial transient
    if lay.uses_vel:
        rms["vel_m_s"] = float(np.sqrt(np.mean(resid[half, :3] ** 2)))
    if lay.uses_att:
        a0 = 3 if lay.uses_vel else 0
        rms["att_deg"] = float(np.sqrt(np.mean(resid[half, a0:a0 + 3] ** 2)))
    nis = run.nis[valid]
    rms["nis_mean"] = float(np.mean(nis[len(nis) // 10:])) if len(nis) else float("nan")
    rms["nis_dof"] = float(lay.n_meas)
    if rms["nis_mean"] > 3.0 * lay.n_meas:
        notes.append(f"residuals {np.sqrt(rms['nis_mean'] / lay.n_meas):.1f}x larger than the noise model: "
                     "unmodelled flexure, lever arm or delay? sigmas are optimistic")
    if run.n_reinit:
        notes.append(f"the master's attitude jumped {run.n_reinit} time(s) (EKF reset): slave attitude restarted")
    if run.n_skipped:
        notes.append(f"{run.n_skipped} of {ne} updates skipped: the master's output was frozen or jumping")
    # histories
    names, cols, sigs = _histories(run, lay, hist_mount, sig_e)
    max_rows = int(options.get("max_history_rows", 2000))
    step = max(int(np.ceil(ne / max_rows)), 1)
    rows = np.arange(0, ne, step)
    if rows[-1] != ne - 1:
        rows = np.append(rows, ne - 1)
    # the lever arm: estimated (a state), or the one given (not estimated), else not modelled (None)
    lever_m = lever_sig = None
    if lay.lever is not None:
        lever_m = tuple(float(x) for x in run.lever_hat[k_rep])
        lever_sig = tuple(float(x) for x in sig_scale * np.sqrt(np.maximum(run.p_diag[k_rep, lay.lever], 0.0)))
        prior = float(sig0[lay.lever][0])
        if np.linalg.norm(lever_m) > LEVER_ARM_IMPLAUSIBLE_SIGMAS * prior:
            notes.append(f"lever arm estimate {np.linalg.norm(lever_m):.3g} m is far beyond its prior "
                         f"({prior:g} m per axis): it is absorbing something else (an uncompensated delay?)")
    elif "lever_arm_m" in options and lay.uses_vel:
        lever_m = tuple(float(x) for x in np.asarray(options["lever_arm_m"], float))
    delay_s = delay_sig = None
    if lay.delay is not None:
        delay_s = float(run.tau_hat[k_rep])
        delay_sig = float(sig_scale * np.sqrt(run.p_diag[k_rep, lay.delay]))
    if run.smoothed:
        notes.append("RTS smoother: values are the smoothed estimates at the middle of the run")
    if np.isfinite(run.gamma).any():
        g = run.gamma[np.isfinite(run.gamma)]
        notes.append(f"H-infinity gamma: median {np.median(g):.3g}, min {g.min():.3g}")
    return AlignmentResult(
        filter=kind, match=match, mounting_rpy_deg=mount_rpy, mounting_sigma_deg=mount_sig,
        gyro_bias_dph=tuple(float(x) for x in gb), accel_bias_mg=tuple(float(x) for x in ab),
        converged_s=conv, residual_rms=rms,
        gyro_bias_sigma_dph=tuple(float(x) for x in gbs), accel_bias_sigma_mg=tuple(float(x) for x in abs_),
        delay_s=delay_s, delay_sigma_s=delay_sig, lever_arm_m=lever_m, lever_arm_sigma_m=lever_sig,
        observability=obs, notes=tuple(notes),
        history_t_s=run.t_s[rows].copy(), history_names=tuple(names), history_x=cols[rows],
        history_sigma=sigs[rows], residual_t_s=run.t_s[rows].copy(), residual_names=tuple(rn),
        residuals=resid[rows],
    )


def _fmt3(v) -> str:
    return "/".join(f"{float(x):.3g}" for x in v)


def rpy_unwrap(hist_deg: np.ndarray, ref_deg: np.ndarray) -> np.ndarray:
    """Wrap each angle history to within 180 deg of the reference value."""
    return ref_deg + (hist_deg - ref_deg + 180.0) % 360.0 - 180.0


def _histories(run: FilterRun, lay: StateLayout, hist_mount: np.ndarray, sig_e: np.ndarray
               ) -> tuple[list[str], np.ndarray, np.ndarray]:
    names: list[str] = []
    cols: list[np.ndarray] = []
    sigs: list[np.ndarray] = []
    sd = np.sqrt(np.maximum(run.p_diag, 0.0))

    def add(sl, labels, scale):
        names.extend(labels)
        cols.append(run.x[:, sl] * scale)
        sigs.append(sd[:, sl] * scale)

    names.extend(["mount_roll_deg", "mount_pitch_deg", "mount_yaw_deg"])
    cols.append(hist_mount)
    sigs.append(np.degrees(sig_e))
    add(lay.att, ["att_err_n_arcmin", "att_err_e_arcmin", "att_err_d_arcmin"], 1.0 / ARCMIN)
    if lay.vel is not None:
        add(lay.vel, ["vel_err_n_m_s", "vel_err_e_m_s", "vel_err_d_m_s"], 1.0)
    add(lay.gyro, ["gyro_bias_x_dph", "gyro_bias_y_dph", "gyro_bias_z_dph"], 1.0 / DEG_PER_H)
    if lay.accel is not None:
        add(lay.accel, ["accel_bias_x_mg", "accel_bias_y_mg", "accel_bias_z_mg"], 1.0 / MG)
    if lay.flex_ang is not None:
        add(lay.flex_ang, ["flex_ang_x_arcmin", "flex_ang_y_arcmin", "flex_ang_z_arcmin"], 1.0 / ARCMIN)
    if lay.lever is not None:
        names.extend(["lever_arm_x_m", "lever_arm_y_m", "lever_arm_z_m"])
        cols.append(run.lever_hat)
        sigs.append(sd[:, lay.lever])
    if lay.delay is not None:
        names.append("delay_s")
        cols.append(run.tau_hat[:, None])
        sigs.append(sd[:, [lay.delay]])
    return names, np.concatenate(cols, axis=1), np.concatenate(sigs, axis=1)
