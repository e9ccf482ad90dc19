"""Velocity matching: the slave's delay from the two units' NED velocities (the measurement of seeds
001 and 004's delay-state filters), as a second, independent estimate for ``logtools.latency``.

Model, on the master's relative clock like ``logtools.latency``::

    v_s(t + L + drift (t - t_mid)) = v + c0 + c1 (t - t_mid) / T + (v - v(t_mid)) x phi + e,
    v = v_m(t) + C_nb(t) (w_m(t) x l)

with l the lever arm (the slave's position in the master's body frame, m; seed 003 eq. 3), c0 and c1 an
offset and a ramp per axis and phi a tilt: the slave's own velocity error (a slave INS whose attitude
is off by a rotation R integrates R C f: its velocity is R (v - g t) + g t, the ramp takes the g t part),
T the half span, and e
the rest: noise, and the slave's slower errors (a coloured disturbance, weighed out by generalised
least squares with its spectrum estimated from a first fit, as the rate fit does). A velocity logged
on a grid (MAVLink's cm/s) adds a quantization floor to the sigma. The tilt is linear in phi; a rotation
beyond a fraction of a degree (an INS's heading error, an odometry's frame) errs by |v| angle^2 / 2 in it,
so the rotation is found first (Kabsch on the velocities' changes, or the heading alone where they vary
in one direction only) and undone, and the fitted tilt is undone exactly and the fit redone
(``frame_rotation_deg``).

Why it matters: flexure rotates the slave without moving it, so the velocity carries the delay
untouched by the flexure, where the angular rate carries it only through the flexure's noise (on an
aircraft with seed 000's flexure, 120 s, no rate-based estimator can do better than 1.6-2 ms;
``benchmarks/latency_bound.py``). The velocity's information is the acceleration's change: turns,
speed changes, heave.

What it does not know: a nav velocity is an estimator's output. An aided autopilot's velocity is
pulled towards its GNSS and its own filter; a slave that logs it late or early relative to its IMU
has a nav delay that is not the IMU's. ``logtools.latency`` therefore fuses this estimate with the
rate fit's only where the two agree (chi-square) and the velocity is the more precise, and reports it
either way (``latency.quality.velocity_fit``). Units sharing one nav stream (two IMUs of one log
with the same EKF output) are recognised and not fitted.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from logtools.conventions import dcm_from_rotvec, skew
from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.latency.gls import (NoiseModel, delay_step, end_taper, gls_covariance, gn_step, grid_offset_sigma_s,
                                  leverage_spectrum, noise_model, stamp_noise_variance, window_chi2)
from logtools.latency.velocity_pair import (VelocityFit, VelocityPair, angle_deg, frame_rotation, near,
                                            quantization_sigma_s)


@dataclass(frozen=True)
class _Solved:
    d: float
    dr: float
    var: np.ndarray  # (nd,)
    corr: float
    lever: np.ndarray | None  # m, master body frame
    tilt: np.ndarray | None  # rad, the slave velocity frame's small rotation (v_s = (I + [tilt x]) v)
    fixed: np.ndarray  # (n, 3) the lever-arm, tilt and step terms of the residual at the solution
    rms: float  # m/s, over the used samples
    resid: np.ndarray  # (n, 3), 0 where unused
    leverage: np.ndarray | None = None  # the fit's leverage spectrum (latency_gls.leverage_spectrum)


def _solve(vp: VelocityPair, t: np.ndarray, vm: np.ndarray, Lr: np.ndarray | None, use0: np.ndarray,
           d0: float, dr0: float, t_mid: float, noise: NoiseModel | None, fit_drift: bool, *,
           tilt: bool, steps: np.ndarray | None = None, leverage: bool = False, cfg: LatencyConfig = DEFAULT
           ) -> _Solved | None:
    """Gauss-Newton on (L[, drift] | lever arm (with Lr), tilt, steps, offset, ramp), whitened with
    ``noise`` (None: unweighted). The residual is r = v_s(t + L + drift (t - t_mid)) - v_m + J_lin x_lin;
    ``steps``: sample indices where the slave's velocity jumps (a reset), a step per axis from each.
    ``leverage``: also the design's leverage spectrum (for a noise model estimated from this fit)."""
    n, dt = len(t), vp.dt_s
    tt = t - t_mid
    T = max(float(np.max(np.abs(tt))), dt)
    nd = 1 + int(fit_drift)
    margin = (cfg.velocity.iters + 1) * dt
    use = use0 & vp.slave.ok(t + d0 + dr0 * tt - margin) & vp.slave.ok(t + d0 + dr0 * tt + margin)
    nl, nt = (0 if Lr is None else 3), (3 if tilt else 0)
    steps = np.zeros(0, int) if steps is None else np.asarray(steps, int)
    nf = nl + nt + 3 * len(steps)  # the columns kept by the windows (``fixed``)
    P = nd + nf + 6
    if use.sum() < max(20, 2 * P):
        return None
    J_lin, k_mid = _linear_columns(vm, Lr, use, tt, T, steps, nt, P - nd)
    tap = end_taper(use, int(np.ceil(cfg.velocity.taper_s / dt)))
    wts = noise.weights(n, dt) if noise is not None else None
    lin = np.zeros(P - nd)
    d, dr = float(d0), float(dr0)
    iters = cfg.velocity.iters
    for it in range(iters + 1):
        tau = t + d + dr * tt
        vs, ok = vp.slave(tau)
        if not np.all(ok[use]):
            return None
        vd = np.zeros((n, 3))
        vd[use], _ = vp.slave(tau[use], 1)
        J = np.zeros((n, 3, P))
        J[:, :, 0] = vd
        if fit_drift:
            J[:, :, 1] = vd * tt[:, None]
        J[:, :, nd:] = J_lin
        r = np.where(use[:, None], vs - vm, 0.0) + J_lin @ lin
        J[~use] = 0.0
        X = np.concatenate([r[:, :, None], J], axis=2) * tap[:, None, None]
        Z = X if noise is None else noise.whiten(X.reshape(n, -1), dt, wts).reshape(X.shape)
        rw, Jw = Z[:, :, 0], Z[:, :, 1:]
        Jf = Jw.reshape(3 * n, P)
        solved = gn_step(Jf, rw)
        if solved is None:
            return None
        Nm, step = solved
        if it == iters:
            break
        sd, sdr = delay_step(step, dt, T, fit_drift)
        d, dr = d + sd, dr + sdr
        lin = lin + step[nd:]
        if nt and nl:
            _tilt_columns(J_lin, vm, Lr, lin[:3], use, k_mid)
        if abs(sd) < 1e-4 * dt:
            iters = it + 1
    return _solved(J, Jw, Jf, Nm, step, lin, rw, r, J_lin, tap, use, d, dr, nd, nl, nt, nf, fit_drift, dt,
                   leverage and cfg.velocity.leverage, cfg)


def _linear_columns(vm: np.ndarray, Lr: np.ndarray | None, use: np.ndarray, tt: np.ndarray, T: float,
                    steps: np.ndarray, nt: int, n_lin: int) -> tuple[np.ndarray, int]:
    """The linear columns (n, 3, n_lin): lever arm, tilt, steps, offset, ramp (the tilt's follow the lever
    arm); and the row of t_mid (the tilt's reference)."""
    n = len(tt)
    nl = 0 if Lr is None else 3
    nf = nl + nt + 3 * len(steps)
    eye = np.eye(3)
    J_lin = np.zeros((n, 3, n_lin))
    if nl:
        J_lin[:, :, :3] = -Lr
    k_mid = np.flatnonzero(use)[np.argmin(np.abs(tt[use]))]
    for j, k in enumerate(steps):
        J_lin[k:, :, nl + nt + 3 * j:nl + nt + 3 * j + 3] = -eye
    J_lin[:, :, nf:nf + 3] = -eye
    J_lin[:, :, nf + 3:] = -eye * (tt / T)[:, None, None]
    J_lin[~use] = 0.0
    if nt:
        _tilt_columns(J_lin, vm, Lr, None, use, k_mid)
    return J_lin, k_mid


def _tilt_columns(J_lin: np.ndarray, vm: np.ndarray, Lr: np.ndarray | None, lever: np.ndarray | None,
                  use: np.ndarray, k_mid: int) -> None:
    """d(delta v)/d(phi) = [(v - v_mid) x] into J_lin's tilt columns (in place: the design being built): the
    velocity change since t_mid seen through the slave's tilt, v the slave's true velocity (the master's
    plus the lever arm's, at the current lever arm)."""
    nl = 0 if Lr is None else 3
    v = vm if lever is None else vm + Lr @ lever
    J_lin[:, :, nl:nl + 3] = np.where(use[:, None, None], skew(v - v[k_mid]), 0.0)


def _solved(J, Jw, Jf, Nm, step, lin, rw, r, J_lin, tap, use, d, dr, nd, nl, nt, nf, fit_drift, dt, leverage, cfg
            ) -> _Solved | None:
    """The fit at the last step: covariance (``gls_covariance``), the linear unknowns, the residual, the
    columns the windows keep fixed, and the leverage spectrum where asked (``lin``: the linear unknowns
    before the last step)."""
    n = len(use)
    try:
        Ninv = np.linalg.inv(Nm)
    except np.linalg.LinAlgError:
        return None
    rw = rw + (Jf @ step).reshape(n, 3)
    n_use = int(use.sum())
    P = Jf.shape[1]
    s2 = float(np.sum(rw * rw)) / max(1, 3 * n_use - P)
    u = np.sum(Jw * rw[:, :, None], axis=1) @ Ninv[:, :nd]
    var, corr, _fac, _ = gls_covariance(Ninv, s2, u, dt, fit_drift, cfg=cfg)
    lin = lin + step[nd:]
    resid = r + J_lin @ step[nd:]
    resid[~use] = 0.0
    fixed = J_lin[:, :, :nf] @ lin[:nf]
    rms = float(np.sqrt(np.sum(resid ** 2) / (3 * n_use)))
    lev = leverage_spectrum(J * tap[:, None, None], use) if leverage else None
    return _Solved(d, dr, var, corr, lin[:3] if nl else None, lin[nl:nl + 3] if nt else None, fixed, rms, resid,
                   lev)


def _step_score(S: np.ndarray, C: np.ndarray, k: np.ndarray, half: int) -> np.ndarray:
    """|(C - B) - (D - A) / 3| at samples k, A, B, C, D the means of four runs of ``half`` samples (two before
    k, two after; S, C the cumulative sums of the values and of the used flags): zero on a straight
    line, 2/3 of a step, and a curvature's half^2; NaN where a run has too few used samples."""
    def mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        c = C[b] - C[a]
        return np.where((c > half // 2)[:, None], (S[b] - S[a]) / np.maximum(c, 1)[:, None], np.nan)

    mA, mB = mean(k - 2 * half, k - half), mean(k - half, k)
    mC, mD = mean(k, k + half), mean(k + half, k + 2 * half)
    return np.linalg.norm((mC - mB) - (mD - mA) / 3.0, axis=1)


def _find_steps(x: np.ndarray, use: np.ndarray, half: int, cfg: LatencyConfig = DEFAULT) -> np.ndarray:
    """Sample indices where x (n, 3) jumps: local maxima of the step score (``_step_score``) beyond
    cfg.velocity.step_ratio times its median that are sharp, i.e. keep at least cfg.velocity.step_sharp of their score at
    half the scale (a step keeps it all, the curvature of a manoeuvre a quarter)."""
    n = len(x)
    if n < 8 * half or half < 4:
        return np.zeros(0, int)
    xs = np.where(use[:, None], x, 0.0)
    S = np.concatenate([np.zeros((1, 3)), np.cumsum(xs, axis=0)])
    C = np.concatenate([[0], np.cumsum(use)])
    k = np.arange(2 * half, n - 2 * half + 1)
    m = _step_score(S, C, k, half)
    ok = np.isfinite(m)
    if not ok.any():
        return np.zeros(0, int)
    m = np.where(ok, m, 0.0)
    thr = cfg.velocity.step_ratio * float(np.median(m[ok]))
    out: list[int] = []
    for i in np.argsort(-m):
        if m[i] <= thr:
            break
        if any(abs(int(i) - j) <= 2 * half for j in out):
            continue
        fine = _step_score(S, C, k[i:i + 1], half // 2)[0]
        if np.isfinite(fine) and fine >= cfg.velocity.step_sharp * m[i]:
            out.append(int(i))
    return np.sort(np.asarray(out, int) + 2 * half)


def velocity_fit(vp: VelocityPair, w0: float, w1: float, d0: float, drift0: float, t_mid: float, *,
                 fit_drift: bool, windows: list[tuple[float, float]], cfg: LatencyConfig = DEFAULT
                 ) -> VelocityFit | None:
    """The velocity-matched (L, drift) over [w0, w1] (master's relative clock), started from the rate fit's
    (d0, drift0): the resets found (steps), one unweighted pass, then ``velocity.gls_passes`` whitened ones;
    sigma from the whitened curvature with a HAC floor, inflated by the scatter of the windows' delays (each
    window: the delay alone, whitened alike) about the fit's line when their reduced chi-square exceeds
    1, and floored by the velocity's and the stamps' quantization. None when the data do not support a
    fit (too few samples, a singular system, more than ``velocity.max_steps`` resets)."""
    vp, t, vm, okm, Lr = _fit_rows(vp, w0, w1, d0, drift0, t_mid, cfg)
    framed = _frame_and_steps(vp, t, vm, okm, d0, drift0, t_mid, cfg)
    if framed is None:
        return None  # a velocity that jumps this often carries no delay worth the risk
    vp, slave0, R_f, steps, okm = framed
    s = _solve(vp, t, vm, Lr, okm, d0, drift0, t_mid, None, fit_drift, tilt=cfg.velocity.tilt, steps=steps,
               leverage=True, cfg=cfg)
    vp, s, R_f = _tilt_undone(vp, s, R_f, slave0, t, vm, Lr, okm, t_mid, fit_drift, steps, cfg)
    rot_deg = angle_deg(R_f)
    noise = None
    for k in range(cfg.velocity.gls_passes):
        if s is None:
            return None
        nm = noise_model(s.resid, np.any(s.resid != 0.0, axis=1), vp.dt_s, leverage=s.leverage, cfg=cfg)
        if nm is None:
            break
        s2 = _solve(vp, t, vm, Lr, okm, s.d, s.dr, t_mid, nm, fit_drift, tilt=cfg.velocity.tilt, steps=steps,
                    leverage=k < cfg.velocity.gls_passes - 1, cfg=cfg)
        if s2 is None:
            break
        s, noise = s2, nm
    if s is None or not np.all(np.isfinite(s.var)) or s.var[0] <= 0:
        return None
    c, lat, sig = _window_delays(vp, s, t, vm, okm, t_mid, noise, windows, cfg)
    chi2 = window_chi2(c, lat, sig, s.d, s.dr, t_mid)
    infl = float(np.sqrt(max(1.0, chi2)))
    s_q = _quantization_floor(vp, t, okm, cfg)
    s_l = float(np.sqrt(s.var[0])) * infl
    q_infl = float(np.sqrt(1.0 + (s_q / s_l) ** 2))
    sd = float(np.sqrt(s.var[1])) * infl * q_infl if fit_drift else 0.0
    return VelocityFit(
        latency_s=s.d, drift=s.dr, sigma_latency_s=s_l * q_infl, sigma_drift=sd,
        corr_ld=s.corr, lever_arm_m=None if s.lever is None else tuple(float(x) for x in s.lever),
        residual_rms_m_s=s.rms, window_chi2_red=chi2, n_windows=len(c), n_steps=int(len(steps)),
        frame_rotation_deg=rot_deg)


def _fit_rows(vp: VelocityPair, w0: float, w1: float, d0: float, drift0: float, t_mid: float,
              cfg: LatencyConfig) -> tuple:
    """(pair on the fit's grid, t, master velocity, usable rows, lever-arm rows or None): at most
    ``max_fit_samples`` samples, still above twice the cutoff (band-limited data), the series' ends left out."""
    dt = max(vp.dt_s, min((w1 - w0) / cfg.velocity.max_fit_samples, 1.0 / (2.5 * vp.cutoff_hz)))
    vp = replace(vp, dt_s=dt)
    t = np.arange(np.ceil(w0 / dt), np.floor(w1 / dt) + 1) * dt
    edge = cfg.velocity.edge_cycles / vp.cutoff_hz
    vm, okm = vp.master(t)
    okm &= (t >= vp.master.t_first_s + edge) & (t <= vp.master.t_last_s - edge)
    lag = d0 + drift0 * (t - t_mid)
    okm &= (t + lag >= vp.slave.t_first_s + edge) & (t + lag <= vp.slave.t_last_s - edge)
    Lr = vp.lever(t) if vp.lever is not None else None
    if Lr is not None and not np.any(Lr):
        Lr = None
    vm = np.where(okm[:, None], vm, 0.0)
    return vp, t, vm, okm, Lr


def _frame_and_steps(vp: VelocityPair, t: np.ndarray, vm: np.ndarray, okm: np.ndarray, d0: float, drift0: float,
                     t_mid: float, cfg: LatencyConfig) -> tuple | None:
    """A slave whose velocity frame is rotated from the master's (an INS with a heading error, an odometry
    frame): the rotation found (Wahba) and undone, the tilt then solves what is left (the linear tilt model
    alone errs by |v| angle^2 / 2: 0.1 m/s at 200 m/s and 2 deg). Then the resets of the slave's velocity
    (an aided filter's jumps), found in the raw difference at the rate fit's (L, drift), the low-passed
    transition around each left out. Returns (pair, the slave's velocity as logged, R_f, steps, rows) or
    None beyond ``max_steps`` resets."""
    dt = vp.dt_s
    half = max(2, int(round(cfg.velocity.step_cycles / (vp.cutoff_hz * dt))))
    vs0, ok0 = vp.slave(t + d0 + drift0 * (t - t_mid))
    slave0 = vp.slave
    R_f = frame_rotation(vs0, vm, okm & ok0, cfg)
    if R_f is not None and angle_deg(R_f) > cfg.velocity.frame_min_deg:
        vp = replace(vp, slave=slave0.transformed(R_f.T))
        vs0, ok0 = vp.slave(t + d0 + drift0 * (t - t_mid))
    else:
        R_f = np.eye(3)
    steps = _find_steps(np.where(ok0[:, None], vs0, 0.0) - vm, okm & ok0, half, cfg)
    if len(steps) > cfg.velocity.max_steps:
        return None
    if len(steps):
        okm = okm & ~near(t, t[steps], half * dt)
    return vp, slave0, R_f, steps, okm


def _tilt_undone(vp: VelocityPair, s, R_f: np.ndarray, slave0, t: np.ndarray, vm: np.ndarray, Lr, okm: np.ndarray,
                 t_mid: float, fit_drift: bool, steps: np.ndarray, cfg: LatencyConfig) -> tuple:
    """The tilt found is a rotation: undone exactly (and the fit redone) where its square would show
    (``slave0``: the slave's velocity as logged)."""
    for _ in range(cfg.velocity.frame_iters):
        if s is None or s.tilt is None or np.degrees(np.linalg.norm(s.tilt)) <= cfg.velocity.tilt_exact_deg:
            break
        R_f = R_f @ dcm_from_rotvec(s.tilt)  # slave_now = R_f^T v_s = (I + [tilt x]) v
        vp = replace(vp, slave=slave0.transformed(R_f.T))
        s = _solve(vp, t, vm, Lr, okm, s.d, s.dr, t_mid, None, fit_drift, tilt=cfg.velocity.tilt, steps=steps,
                   leverage=True, cfg=cfg)
    return vp, s, R_f


def _window_delays(vp: VelocityPair, s, t: np.ndarray, vm: np.ndarray, okm: np.ndarray, t_mid: float,
                   noise: NoiseModel | None, windows: list, cfg: LatencyConfig) -> tuple[list, list, list]:
    """The windows' delays, each with the whole fit's drift, lever arm and tilt (constants of the pair; a
    window cannot tell a lever arm along the flight path from a delay in a level turn)."""
    vm_w = vm - s.fixed
    c, lat, sig = [], [], []
    for a0, a1 in windows if len(windows) >= 3 else []:
        ws = (t >= a0) & (t <= a1)
        if ws.sum() < cfg.velocity.window_min:
            continue
        tc = 0.5 * (a0 + a1)
        pred = s.d + s.dr * (tc - t_mid)
        sw = _solve(vp, t[ws], vm_w[ws], None, okm[ws], pred, s.dr, tc, noise, False, tilt=False, cfg=cfg)
        if sw is not None and np.isfinite(sw.var[0]) and sw.var[0] > 0:
            c.append(tc)
            lat.append(sw.d)
            sig.append(float(np.sqrt(sw.var[0])))
    return c, lat, sig


def _quantization_floor(vp: VelocityPair, t: np.ndarray, okm: np.ndarray, cfg: LatencyConfig) -> float:
    """The velocity fit's floors, in quadrature: the velocity grid's, the stamps' grid offset (a common offset
    of up to half a step, uniform; the velocity's stamps, not the rates'), and white stamp noise (the delay
    a weighted mean of the stamps' errors, weights |a|^2 per sample; f dt stamps behind each fit point)."""
    acc, ok_a = vp.master(t, 1)
    s_q = quantization_sigma_s(vp, np.mean(acc[ok_a & okm] ** 2, axis=0)) if (ok_a & okm).any() else 0.0
    if cfg.velocity.stamp_resolution_floor:
        s_q = float(np.hypot(s_q, grid_offset_sigma_s(vp.stamp_resolutions_s)))
    g = np.sum(acc[ok_a & okm] ** 2, axis=1)
    return float(np.sqrt(s_q ** 2 + sum(stamp_noise_variance(sj, g, f * vp.dt_s) for sj, f in vp.stamp_jitter)))
