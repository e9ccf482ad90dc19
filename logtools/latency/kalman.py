"""Stage 4b, the Kalman refinement: the delay on the profile of the cost whitened by a Kalman filter of seed
000's flexure model (``flexure``), and the one criterion of what a fitted model must be to count as flexure."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.latency.fit import Fit, fit_start, motion_rms
from logtools.latency.flexure import FlexureModel, block_mean, fit_model, whitened_normal
from logtools.latency.gls import delay_system, gls_covariance
from logtools.latency.system import Accel, check_columns, gls_system, gls_use
from logtools.resample import Interpolant


def flexure_like(model: FlexureModel, cfg: LatencyConfig = DEFAULT) -> bool:
    """A fitted model that describes a structure's flexure: correlated over less than 1 / cfg.flexure.beta_min_1_s and
    within cfg.flexure.sigma_max_deg. Beyond, the residual is something else the model bends to (an attitude-only
    slave with jittered stamps: its rates' noise, proportional to the rate, came out as a 14 deg "flexure"
    of beta 0.013/s, the fit 3 ms off at a sigma of 0.6 ms and the velocity, right to 0.01 ms, left out)."""
    return cfg.flexure.is_flexure(model.beta_1_s, np.degrees(np.max(model.sigma_rad)))


@dataclass(frozen=True)
class BlockSystem:
    """The joint system's rows block-averaged (k samples a block) over the samples ``use``, fixed for a fit."""

    t_m: np.ndarray
    a: np.ndarray
    use: np.ndarray
    itp: Interpolant
    tt: np.ndarray
    fit_drift: bool
    acc: Accel | None
    fm: np.ndarray | None
    lev: np.ndarray | None
    k: int

    def blocks(self, x: np.ndarray) -> np.ndarray:
        use = self.use
        return block_mean(np.where(use.reshape((-1,) + (1,) * (x.ndim - 1)), x, 0.0), use, self.k)[0]

    def at(self, dd: float, rr: float, jac: bool = True):
        """Block rows at (dd, rr): (X (nb, C, 1 [+ P + check]), used blocks, fs, ws, r, R, bias) or None."""
        sysm = gls_system(self.t_m, self.a, self.use, self.itp, dd, rr, self.tt, self.fit_drift, self.acc, self.fm,
                          self.lev, jacobian=jac)
        if sysm is None:
            return None
        r, J, R, bias, fv, Dm = sysm
        Xb, ub = block_mean(r[:, :, None] if J is None else np.concatenate([r[:, :, None], J, Dm], axis=2),
                            self.use, self.k)
        fb = None if fv is None else self.blocks(fv)
        wb = self.blocks(r[:, :3] + self.a @ R.T + bias)  # the slave's rate
        return Xb, ub, fb, wb, r, R, bias


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
    # how far the search may go: a few of its steps (the spectral sigma it starts from is optimistic exactly
    # where this fit matters: a gently turning aircraft's Kalman fit walked 5.7 ms from a spectral fit of
    # sigma 0.13 ms, past 4 x 0.13 x 6 = 3.1 ms, and failed)
    reach = 4.0 * h * iters
    use, fm, lev = gls_use(t_m, valid, itp, d + dr * tt, reach + h + 2 * dt, acc)
    k = max(1, int(round(1.0 / (cfg.flexure.decimate_factor * cutoff_hz * dt))))
    if use.sum() < 20 * k:
        return fail
    bs = BlockSystem(t_m, a, use, itp, tt, fit_drift, acc, fm, lev, k)
    sy = bs.at(d, dr)
    if sy is None:
        return fail
    P = sy[0].shape[2] - 1 - check_columns(acc) - nd
    if model is None:
        model = _fitted_model(bs, sy, P, t_mid, dt, cfg)
        if model is None:
            return fail
    found = _profile_newton(bs, sy, model, P, d, dr, h, dt, span, d0, reach, iters)
    if found is None:
        return fail
    return _flex_result(bs, found, model, P, dt, cfg) or fail


def _fitted_model(bs: BlockSystem, sy: tuple, P: int, t_mid: float, dt: float, cfg: LatencyConfig
                  ) -> FlexureModel | None:
    """The flexure model by restricted maximum likelihood on the middle of the overlap (at most
    ``ml_span_s`` / ``ml_blocks``); None where it fails or is not flexure (``flexure_like``)."""
    Xb, ub, fb, wb = sy[:4]
    k, acc = bs.k, bs.acc
    span_ml = min(cfg.flexure.ml_span_s, cfg.flexure.ml_blocks * k * dt)
    cen = np.abs((np.arange(len(ub)) + 0.5) * k * dt + bs.t_m[0] - t_mid) <= 0.5 * span_ml
    # the model's likelihood without the accelerometers' own delay where it is an unknown (lag_free):
    # a flexure large enough to whiten the gyro rows away leaves the delay's accelerometer part and that
    # column alike, and the restricted likelihood's log det term then pulled the fit into that corner
    pm = P - int(acc is not None and acc.lag_free)
    model = fit_model(Xb[cen][:, :, :1 + pm], wb[cen], None if fb is None else fb[cen], ub[cen], k * dt, pm, cfg)
    if model is None or not flexure_like(model, cfg):
        return None
    return model


def _profile_newton(bs: BlockSystem, sy: tuple, model: FlexureModel, P: int, d: float, dr: float, h: float,
                    dt: float, span: float, d0: float, reach: float, iters: int) -> tuple | None:
    """Newton steps on parabolas through the whitened profile cost at d - h, d, d + h (the drift by the GLS
    step); returns (d, dr, the profile's curvature, the system at d, W, M of the last pass) or None."""
    nd = 1 + int(bs.fit_drift)
    n_check = check_columns(bs.acc)
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
            sy, at = bs.at(d, dr), (d, dr)
        sp, sm = bs.at(d + h, dr, False), bs.at(d - h, dr, False)
        if sy is None or sp is None or sm is None:
            return None
        Y = np.concatenate([sm[0], sy[0][:, :, :1], sp[0], sy[0][:, :, 1:]], axis=2)
        W, M, _ = whitened_normal(Y, sy[3], sy[2], sy[1], model, store=it == iters)
        try:
            cm, c0, cp = (profile(M, j) for j in range(3))
            # the GLS step, its delay's gradient and curvature from the cleaner derivative (delay_normal)
            Nj, g, _ = delay_system(M[np.ix_(jc, jc)], M[np.ix_(jc, dc)], M[np.ix_(dc, dc)], M[jc, 1], M[dc, 1])
            stp = -np.linalg.solve(Nj, g)
        except np.linalg.LinAlgError:
            return None
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
        if bs.fit_drift:
            dr += float(np.clip(stp[1], -0.5 * dt / max(span, 1e-9), 0.5 * dt / max(span, 1e-9)))
        if abs(d - d0) > reach:
            return None
        h = float(np.clip(np.sqrt(1.0 / curv), 1e-3 * dt, 0.5 * dt))  # the next bracket: ~1 sigma
        if abs(step) < 0.05 * h:
            iters = it + 1  # one more pass: the covariance and scores at the solution
    if not curv > 0:
        return None
    return d, dr, curv, sy, W, M


def _flex_result(bs: BlockSystem, found: tuple, model: FlexureModel, P: int, dt: float, cfg: LatencyConfig
                 ) -> Fit | None:
    """The fit at the profile's solution: the final pass's GLS step and covariance (``gls_covariance``,
    the latency's variance at least the profile curvature's), None where its normal matrix is singular."""
    d, dr, curv, sy, W, M = found
    acc, fit_drift, use, k = bs.acc, bs.fit_drift, bs.use, bs.k
    nd = 1 + int(fit_drift)
    n_check = check_columns(acc)
    C = 3 if acc is None else 6
    jc = list(range(3, 3 + P))
    dc = list(range(3 + P + n_check, 3 + P + n_check + nd))
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
        return None
    step = -Ninv @ g
    Wp = W[:, :, 1:P + 1]
    rw = W[:, :, 0] + Wp @ step
    nb = int(ub.sum())
    s2 = float(np.sum(rw * rw)) / max(1, C * nb - P)
    Ws = np.concatenate([Wd, Wp[:, :, nd:]], axis=2)  # the scores as in refine_gls
    u = np.sum(Ws * rw[:, :, None], axis=1)[ub] @ Ninv[:, :nd]
    check = None if not n_check else (M[1:, 1:], M[1:, 0] + M[1:, 1:P + 1] @ step)
    # the profile's curvature floors the latency's variance (cost = sum of squares: var = s2 / curvature)
    var, corr, fac, acc_lag = gls_covariance(Ninv, s2, u, k * dt, fit_drift, check=check, var_floor=s2 / curv,
                                             free_step=step if acc is not None and acc.lag_free else None, cfg=cfg)
    motion = motion_rms(bs.a, use)
    raw_rms = float(np.sqrt(np.sum(r[use, :3] ** 2) / (3 * int(use.sum()))))
    return Fit(d, dr, R, bias, float(np.sqrt(var[0])), float(np.sqrt(var[1])) if fit_drift else 0.0,
               raw_rms, int(use.sum()), fac, motion, corr_ld=corr, aided=acc is not None, accel_lag_s=acc_lag,
               flex=model, accel_lag_free=acc is not None and acc.lag_free)
