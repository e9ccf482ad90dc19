"""Stage 4, refinement: the spectral GLS (``refine_gls``), the accelerometer-aided passes
(``accel_aided``) and the Kalman flexure-model fit (``refine_flex``); every covariance through
``gls.gls_covariance``."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from logtools.conventions import median_step_s
from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.latency.fit import Fit, fit_start, motion_rms
from logtools.latency.flexure import FlexureModel, block_mean, fit_model, whitened_normal
from logtools.latency.gls import NoiseModel, delay_normal, delay_step, delay_system, end_taper, gls_covariance, noise_model
from logtools.latency.system import Accel, accel_residual, check_columns, gls_system, gls_use
from logtools.resample import Interpolant


def refine_gls(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d0: float,
                drift0: float, t_mid: float, noise: NoiseModel, *, fit_drift: bool, iters: int = 4,
                acc: Accel | None = None, cfg: LatencyConfig = DEFAULT) -> Fit:
    """Generalised least squares: Gauss-Newton on the whitened residual and whitened Jacobian of the
    joint (L[, drift], rotation, bias) problem; the L[, drift] part of each step is taken and R, b
    re-solved (Kabsch), whose fixed point is the joint GLS estimate. Covariance: the whitened
    curvature times the whitened residual variance (HAC-checked).

    With ``acc`` (and a 6-channel cross-spectral ``noise``), the accelerometers' residuals join the
    gyros' (accelerometer bias and lever arm as further linear unknowns, the rotation shared): the
    whitening then uses their coherence, i.e. the flexure seen as a tilt of the specific force is
    taken out of the differential rate, and the specific force's own motion adds delay information."""
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


def flexure_like(model: FlexureModel, cfg: LatencyConfig = DEFAULT) -> bool:
    """A fitted model that describes a structure's flexure: correlated over less than 1 / cfg.flexure.beta_min_1_s and
    within cfg.flexure.sigma_max_deg. Beyond, the residual is something else the model bends to (an attitude-only
    slave with jittered stamps: its rates' noise, proportional to the rate, came out as a 14 deg "flexure"
    of beta 0.013/s, the fit 3 ms off at a sigma of 0.6 ms and the velocity, right to 0.01 ms, left out)."""
    return bool(model.beta_1_s >= cfg.flexure.beta_min_1_s and np.degrees(np.max(model.sigma_rad)) <= cfg.flexure.sigma_max_deg)


def refine_flex(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, d0: float,
                drift0: float, t_mid: float, cutoff_hz: float, *, fit_drift: bool, acc: Accel | None = None,
                model: FlexureModel | None = None, h0: float = 0.0, iters: int | None = None,
                cfg: LatencyConfig = DEFAULT) -> Fit:
    """Generalised least squares as ``refine_gls``, whitened by a Kalman filter of seed 000's flexure
    model (``latency.flexure``) instead of a residual spectrum. The rows are block-averaged to
    cfg.flexure.decimate_factor x the cutoff; the model's parameters are fitted by restricted maximum likelihood at
    the start (on at most cfg.flexure.ml_span_s of blocks; unless ``model`` is given, e.g. for the drift windows).

    The delay is then found on the profile of the whitened cost (every other unknown -- drift, rotation,
    biases, lever arm -- concentrated out, linearised): Newton steps on a parabola through three cost
    evaluations (d - h, d, d + h), not Gauss-Newton steps on the Jacobian alone: the Kalman whitening
    weighs the fine structure of the signals heavily, where the slave's derivative is mostly its noise's,
    and the Gauss-Newton curvature exceeded the cost's own several times over. The drift's step and the
    covariance take the delay's [drift's] gradient and curvature from the master's derivative
    (``gls.delay_normal``; stepping the delay that way too left a 30 s flexing ship's windows
    unchecked, z 3.6). The sigma is the larger of the profile's and the Gauss-Newton/HAC one. ``h0``:
    the first half-width (e.g. the spectral sigma)."""
    iters = cfg.flexure.iters if iters is None else iters
    d, dr, dt, tt, span, fail = fit_start(t_m, t_mid, d0, drift0)
    nd = 1 + int(fit_drift)
    h = float(np.clip(h0 if h0 > 0 else 0.05 * dt, 1e-3 * dt, 0.5 * dt))
    # how far the search may go: a few of its steps (the spectral sigma it starts from is optimistic exactly where this fit matters: a gently turning aircraft's Kalman fit walked 5.7 ms
    # from a spectral fit of sigma 0.13 ms, past 4 x 0.13 x 6 = 3.1 ms, and failed)
    reach = 4.0 * h * iters
    use, fm, lev = gls_use(t_m, valid, itp, d + dr * tt, reach + h + 2 * dt, acc)
    k = max(1, int(round(1.0 / (cfg.flexure.decimate_factor * cutoff_hz * dt))))
    if use.sum() < 20 * k:
        return fail
    C = 3 if acc is None else 6
    n_check = check_columns(acc)

    def blocks(x: np.ndarray) -> np.ndarray:
        return block_mean(np.where(use.reshape((-1,) + (1,) * (x.ndim - 1)), x, 0.0), use, k)[0]

    def system(dd: float, rr: float, jac: bool = True):
        """Block rows at (dd, rr): (X (nb, C, 1 [+ P + check]), used blocks, fs, ws, r, R, bias) or None."""
        sysm = gls_system(t_m, a, use, itp, dd, rr, tt, fit_drift, acc, fm, lev, jacobian=jac)
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
        span_ml = min(cfg.flexure.ml_span_s, cfg.flexure.ml_blocks * k * dt)
        cen = np.abs((np.arange(len(ub)) + 0.5) * k * dt + t_m[0] - t_mid) <= 0.5 * span_ml
        # the model's likelihood without the accelerometers' own delay where it is an unknown (lag_free):
        # a flexure large enough to whiten the gyro rows away leaves the delay's accelerometer part and that
        # column alike, and the restricted likelihood's log det term then pulled the fit into that corner
        pm = P - int(acc is not None and acc.lag_free)
        model = fit_model(Xb[cen][:, :, :1 + pm], wb[cen], None if fb is None else fb[cen], ub[cen], k * dt, pm, cfg)
        if model is None or not flexure_like(model, cfg):
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
    Ws = np.concatenate([Wd, Wp[:, :, nd:]], axis=2)  # the scores as in refine_gls
    u = np.sum(Ws * rw[:, :, None], axis=1)[ub] @ Ninv[:, :nd]
    check = None if not n_check else (M[1:, 1:], M[1:, 0] + M[1:, 1:P + 1] @ step)
    # the profile's curvature floors the latency's variance (cost = sum of squares: var = s2 / curvature)
    var, corr, fac, acc_lag = gls_covariance(Ninv, s2, u, k * dt, fit_drift, check=check, var_floor=s2 / curv, cfg=cfg,
                                             free_step=step if acc is not None and acc.lag_free else None)
    motion = motion_rms(a, use)
    raw_rms = float(np.sqrt(np.sum(r[use, :3] ** 2) / (3 * int(use.sum()))))
    return Fit(d, dr, R, bias, float(np.sqrt(var[0])), float(np.sqrt(var[1])) if fit_drift else 0.0,
                raw_rms, int(use.sum()), fac, motion, corr_ld=corr, aided=acc is not None, accel_lag_s=acc_lag,
                flex=model, accel_lag_free=acc is not None and acc.lag_free)


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

