"""Stage 4, refinement: the spectral GLS (``refine_gls``) and the accelerometer-aided passes
(``accel_aided``; the Kalman flexure-model fit is ``kalman.refine_flex``); every covariance through
``gls.gls_covariance``."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from logtools.conventions import median_step_s
from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.latency.fit import Fit, fit_start, motion_rms
from logtools.latency.gls import NoiseModel, delay_normal, delay_step, end_taper, gls_covariance, noise_model
from logtools.latency.system import Accel, accel_residual, check_columns, gls_system, gls_use
from logtools.resample import Interpolant


def refine_gls(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d0: float,
                drift0: float, t_mid: float, noise: NoiseModel, *, fit_drift: bool, iters: int | None = None,
                acc: Accel | None = None, cfg: LatencyConfig = DEFAULT) -> Fit:
    """Generalised least squares: Gauss-Newton on the whitened residual and whitened Jacobian of the
    joint (L[, drift], rotation, bias) problem; the L[, drift] part of each step is taken and R, b
    re-solved (Kabsch), whose fixed point is the joint GLS estimate. Covariance: the whitened
    curvature times the whitened residual variance (HAC-checked). With ``acc`` (and a 6-channel cross-spectral ``noise``), the accelerometers' residuals join the
    gyros' (accelerometer bias and lever arm as further linear unknowns, the rotation shared): the
    whitening then uses their coherence, i.e. the flexure seen as a tilt of the specific force is
    taken out of the differential rate, and the specific force's own motion adds delay information."""
    iters = cfg.refine.gls_iters if iters is None else iters
    d, dr, dt, tt, span, fail = fit_start(t_m, t_mid, d0, drift0)
    n, nd = len(t_m), 1 + int(fit_drift)
    # the samples used are fixed for all iterations (no sample switches in or out with d: a switch is
    # a step the whitening filter would amplify), and tapered at their ends and around gaps
    margin = (iters + 1) * dt  # the steps are clipped to 0.5 dt (latency) + 0.5 dt at the ends (drift)
    use, fm, lev = gls_use(t_m, valid, itp, d + dr * tt, margin, acc)
    if use.sum() < 20:
        return fail
    C = 3 if acc is None else 6
    taper = end_taper(use, int(np.ceil(cfg.refine.gls_taper_s / dt)))
    wts = noise.weights(n, dt)
    for it in range(iters + 1):
        sysm = gls_system(t_m, a, use, itp, d, dr, tt, fit_drift, acc, fm, lev)
        if sysm is None:
            return fail
        r, J, R, bias, _fv, Dm = sysm
        n_check = check_columns(acc)  # trailing columns only for the model check, not in the steps
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
    # per-sample whitened scores, the delay's [drift's] from the master's derivative (as in refine)
    Js = np.concatenate([Dw.reshape(n, C, nd), Jw[:, :, nd:]], axis=2)
    u = np.sum(Js * rw[:, :, None], axis=1) @ Ninv[:, :nd]
    # model check: the accelerometers' delay relative to the gyros' (0 when both come through the same
    # path; real IMUs may filter them differently), from the augmented normal equations
    check = None if not n_check else (Jx.T @ Jx, Jx.T @ rw.ravel())
    var, corr, fac, acc_lag = gls_covariance(Ninv, s2, u, dt, fit_drift, check=check, cfg=cfg,
                                             free_step=step if acc is not None and acc.lag_free else None)
    motion = motion_rms(a, use)
    raw_rms = float(np.sqrt(np.sum(r[:, :3] ** 2) / (3 * n_use)))
    return Fit(d, dr, R, bias, float(np.sqrt(var[0])), float(np.sqrt(var[1])) if fit_drift else 0.0,
                raw_rms, n_use, fac, motion, corr_ld=corr, accel_lag_s=acc_lag,
                accel_lag_free=acc is not None and acc.lag_free)


def accel_aided(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, acc: Accel, fin: Fit,
                t_mid: float, *, fit_drift: bool, cfg: LatencyConfig = DEFAULT
                ) -> tuple[Fit, NoiseModel | None, Accel | None]:
    """cfg.accel.gls_passes accelerometer-aided GLS passes from the gyro-only fit ``fin`` (the 6-channel residual
    cross-spectrum re-estimated before each); kept when its sigma is smaller (flagged ``aided``). Where
    the model check finds the accelerometers on a delay of their own, the passes again with that delay
    solved (cfg.accel.lag_free). Returns the fit kept and, when it is an aided one, its noise model and
    accelerometers (``lag_free`` or not)."""
    dt = median_step_s(t_m)

    def passes(ac: Accel) -> tuple[Fit, NoiseModel | None]:
        cur, nm = fin, None
        for _ in range(cfg.accel.gls_passes):
            r6 = accel_residual(t_m, a, valid, itp, ac, cur, t_mid)
            nm6 = noise_model(r6, np.any(r6 != 0.0, axis=1), dt, matrix=True, cfg=cfg)
            if nm6 is None:
                break
            f2 = refine_gls(t_m, a, valid, itp, cur.latency_s, cur.drift, t_mid, nm6, fit_drift=fit_drift, acc=ac,
                            cfg=cfg)
            if not f2.ok:
                break
            cur, nm = f2, nm6
        return cur, nm

    cur, nm = passes(acc)
    if cur is not fin and not accel_lag_agrees(cur, cfg) and cfg.accel.lag_free:
        free = replace(acc, lag_free=True)
        cur_f, nm_f = passes(free)
        if cur_f is not fin:
            cur, nm, acc = cur_f, nm_f, free
    if cur is not fin and cur.sigma_latency_s < fin.sigma_latency_s and accel_lag_agrees(cur, cfg):
        return replace(cur, aided=True), nm, acc
    return replace(fin, accel_lag_s=cur.accel_lag_s), None, None


def accel_lag_agrees(f: Fit, cfg: LatencyConfig = DEFAULT) -> bool:
    """The accelerometers' own delay relative to the gyros' (f's model check) is zero within cfg.accel.lag_sigmas;
    where the fit solved it (``accel_lag_free``), it is at most cfg.accel.lag_max_s."""
    lag, sig = f.accel_lag_s
    if f.accel_lag_free:
        return bool(abs(lag) <= cfg.accel.lag_max_s)
    return bool(abs(lag) <= cfg.accel.lag_sigmas * sig)

