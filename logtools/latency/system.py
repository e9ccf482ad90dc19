"""The whitened fits' shared system: the accelerometer rows (``Accel``), the used samples, and the
residuals and Jacobian of the joint (L[, drift], rotation, biases[, lever arm]) problem."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from logtools.conventions import skew
from logtools.latency.fit import Fit, kabsch_bias, rate_jacobian, residual
from logtools.latency.gls import grid_derivative
from logtools.resample import Interpolant


@dataclass(frozen=True)
class Accel:
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


def lever_solve(r_a: np.ndarray, Jl: np.ndarray, use: np.ndarray) -> np.ndarray:
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


def lever_jacobian(R: np.ndarray, lev: np.ndarray) -> np.ndarray:
    """(n, 3, 3) derivative of the accelerometer residual w.r.t. the lever arm (master frame)."""
    return -np.einsum("ij,njk->nik", R, lev)


def accel_residual(t_m: np.ndarray, a: np.ndarray, valid: np.ndarray, itp: Interpolant, acc: Accel,
                    f: Fit, t_mid: float) -> np.ndarray:
    """(N, 6) gyro and accelerometer residuals of a fit (lever arm and biases by least squares), 0 where
    masked: what the accelerometer-aided noise model is estimated from."""
    tau = t_m + f.latency_s + f.drift * (t_m - t_mid)
    fv, okf = acc.slave(tau)
    fm, lev, okm = acc.master_rows(t_m)
    use = itp.ok(tau) & okf & okm & valid
    out = np.zeros((len(t_m), 6))
    if use.sum() < 20:
        return out
    out[:, :3] = np.where(use[:, None], residual(t_m, a, valid, itp, f, t_mid), 0.0)
    r_a = np.where(use[:, None], fv - fm @ f.R.T, 0.0)
    Jl = lever_jacobian(f.R, lev)
    if acc.lag_free:  # the accelerometers' own delay solved too
        fd = np.zeros_like(fv)
        fd[use], _ = acc.slave(tau[use], 1)
        Jl = np.concatenate([Jl, fd[:, :, None]], axis=2)
    out[:, 3:] = lever_solve(r_a, Jl, use)
    return out


def check_columns(acc: Accel | None) -> int:
    """Trailing model-check columns of an aided fit's Jacobian: the accelerometers' own delay, checked
    (1) or an unknown of the fit (0: ``acc.lag_free``)."""
    return 0 if acc is None or acc.lag_free else 1


def gls_use(t_m: np.ndarray, valid: np.ndarray, itp: Interpolant, lag: np.ndarray, margin: float,
             acc: Accel | None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The samples a fit uses, fixed for all its iterations (slave data within +- margin of the lag
    everywhere), and with ``acc`` the master's accelerometer rows (f_m, lever-arm matrix) at t_m."""
    use = valid & itp.ok(t_m + lag - margin) & itp.ok(t_m + lag + margin)
    fm = lev = None
    if acc is not None:
        fm, lev, okm = acc.master_rows(t_m)
        use &= okm & acc.slave.ok(t_m + lag - margin) & acc.slave.ok(t_m + lag + margin)
    return use, fm, lev


def gls_system(t_m: np.ndarray, a: np.ndarray, use: np.ndarray, itp: Interpolant, d: float, dr: float,
                tt: np.ndarray, fit_drift: bool, acc: Accel | None, fm: np.ndarray | None,
                lev: np.ndarray | None, *, jacobian: bool = True) -> tuple | None:
    """Residuals r (n, C) and Jacobian J (n, C, P [+ 1]) of the joint fit at (d, dr), R and the gyro bias
    re-solved (Kabsch), 0 outside ``use``; C = 3 (gyros) or 6 (with ``acc``: accelerometer rows, their
    bias and the lever arm as further unknowns, and a trailing column for the accelerometers' own delay,
    the model check). Also the slave's specific force at the delayed instants (None without ``acc``) and
    Dm (n, C, nd): the delay's [and drift's] columns from the model's derivative, for the curvature
    (``gls.delay_normal``). None when a used sample falls off the slave's data. Without ``jacobian``:
    (r, None, R, bias, fv, None)."""
    n = len(t_m)
    C = 3 if acc is None else 6
    nd = 1 + int(fit_drift)
    tau = t_m + d + dr * tt
    bv, ok = itp(tau)
    if not np.all(ok[use]):
        return None
    R, bias = kabsch_bias(a[use], bv[use])
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
    Jg = rate_jacobian(bd, tt if fit_drift else None, Ra).reshape(n, 3, -1)
    dt = float(t_m[1] - t_m[0]) if n > 1 else 1.0
    md, okd = grid_derivative(Ra, use, dt)
    Dm = np.zeros((n, C, nd))
    Dm[:, :3, 0] = np.where(okd[:, None], md, bd)
    if acc is None:
        J = Jg
    else:
        fd = np.zeros((n, 3))
        fd[use], _ = acc.slave(tau[use], 1)
        Ja = rate_jacobian(fd, tt if fit_drift else None, Rf).reshape(n, 3, -1)
        # the accelerometers' model, lever arm included (least squares here): the master's side
        Jl = lever_jacobian(R, lev)
        model_a = np.where(use[:, None], fv - lever_solve(r[:, 3:], Jl, use), 0.0)
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

