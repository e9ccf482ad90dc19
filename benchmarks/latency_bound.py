"""Cramer-Rao bound of the latency for a simulated pair: what no estimator can beat on that run.

For a pair from ``logtools.sim`` the disturbance of the latency fit is known exactly: the slave's
flexure (seed 000 eq. 8, the simulator's second-order Markov rotation with its sigma and beta) and both
units' white sensor noise (ARW, VRW). The signals are known too, noise-free, from the simulator's truth.
The residual model is the one ``logtools.latency.flexure`` whitens::

    y_k = J_k p + H_k x_k + v_k,   x = (lam, lam'),   H_k = [[[w_k x], I], [[f_k x], 0]]

with p = (delay, drift, rotation, gyro bias, accelerometer bias, lever arm) and J their Jacobian built
from the truth (slave frame: w, w', f, f' of the master rotated by the mounting). The Fisher information
of p is sum_k Jw_k^T Jw_k with Jw the Kalman-whitened columns of J (innovations of the exact model);
the bound on the latency is sqrt(inv(F)[0, 0]), the other unknowns estimated jointly, the drift with the
Gaussian prior tapost's estimator uses (its configuration's drift_prior_ppm; a Bayesian bound for that part). It is evaluated on
samples every ``dt_s`` (the truth is smooth; the flexure model is exact at any step) over the pair's
overlap, and with the gyros alone (``gyro``) as well as gyros and accelerometers (``aided``); when the
slave logs a nav velocity, also with the velocity matching's information added (``aided+velocity``).

Used by ``bench_latency.py`` for the flexure runs (without flexure the bound is the sensors' white noise
alone, far below what interpolation and stamps allow, and is not reported).
"""
from __future__ import annotations

import numpy as np

from logtools import sim
from logtools.conventions import DEG, DEG_PER_SQRT_H, UG_PER_SQRT_HZ, dcm_from_euler, skew
from logtools.latency import LatencyConfig
from logtools.latency.flexure import FlexureModel, whitened_normal

DRIFT_PRIOR_PPM = LatencyConfig().uncertainty.drift_prior_ppm  # the prior tapost's estimator uses


def latency_bound_s(cfg: "sim.SimConfig", truth: "sim.Truth", dt_s: float = 0.05) -> dict:
    """{"aided": s, "gyro": s}: the Cramer-Rao bound of the latency (at the middle of the overlap)."""
    lat = truth.latency_excl_clock_offset_s
    t0, t1 = max(0.0, -lat) + 0.5, cfg.duration_s - max(0.0, lat) - 0.5
    t = np.arange(t0, t1, dt_s)
    n = len(t)
    tr = sim.truth_trajectory(cfg, t)
    h = 1e-3
    fd_m = (sim.truth_trajectory(cfg, t + h).f_b_m_s2 - sim.truth_trajectory(cfg, t - h).f_b_m_s2) / (2 * h)
    R = dcm_from_euler(np.radians(np.asarray(cfg.mount_rpy_deg, float)))  # v_slave = R v_master
    w, wd = tr.omega_ib_b_rad_s @ R.T, tr.omega_dot_ib_b_rad_s2 @ R.T
    f, fd = tr.f_b_m_s2 @ R.T, fd_m @ R.T
    tt = t - 0.5 * (t0 + t1)
    I3 = np.broadcast_to(np.eye(3), (n, 3, 3))
    Z3 = np.zeros((n, 3, 3))
    delay = np.concatenate([wd, fd], axis=1)
    cols = [delay[:, :, None], (delay * tt[:, None])[:, :, None],
            np.concatenate([skew(w), skew(f)], axis=1),  # rotation
            np.concatenate([I3, Z3], axis=1), np.concatenate([Z3, I3], axis=1),  # biases
            np.concatenate([Z3, skew(wd) + skew(w) @ skew(w)], axis=1)]  # lever arm
    J = np.concatenate(cols, axis=2)  # (n, 6, 14)
    y = np.concatenate([np.zeros((n, 6, 1)), J], axis=2)
    # white noise of both units, per dt_s sample (the simulator's convention: std N sqrt(rate) per sample)
    arw = np.hypot(cfg.slave_gyro_arw_dpsh, cfg.master_gyro_arw_dpsh) * DEG_PER_SQRT_H
    vrw = np.hypot(cfg.slave_accel_vrw_ug_rthz, cfg.master_accel_vrw_ug_rthz) * UG_PER_SQRT_HZ
    noise = np.array([arw ** 2] * 3 + [vrw ** 2] * 3) / dt_s
    sig = np.asarray(cfg.flexure_sigma_deg, float) * DEG if cfg.flexure else np.full(3, 1e-12)
    beta = float(np.mean(cfg.flexure_beta_1_s))
    use = np.ones(n, bool)
    out = {}
    S_vel = _velocity_information(cfg, tr, tt, dt_s) if cfg.slave_nav else None
    for name, rows, cols_used in (("aided", slice(None), list(range(15))),
                                  ("gyro", slice(0, 3), list(range(9)))):  # residual, delay .. gyro bias
        model = FlexureModel(sig, beta, noise[rows], dt_s)
        yy = np.ascontiguousarray(y[:, rows][:, :, cols_used])
        _, M, _ = whitened_normal(yy, w, f if name == "aided" else None, use, model, store=False)
        S = _schur2(M[1:, 1:])
        S[1, 1] += 1.0 / (DRIFT_PRIOR_PPM * 1e-6) ** 2  # the drift prior tapost's estimator uses
        out[name] = float(np.sqrt(np.linalg.inv(S)[0, 0]))
        if name == "aided" and S_vel is not None:  # independent noise: the informations add
            out["aided+velocity"] = float(np.sqrt(np.linalg.inv(S + S_vel)[0, 0]))
    return out


def _schur2(F: np.ndarray) -> np.ndarray:
    """The information of the first two parameters (delay, drift) with the others estimated jointly."""
    return F[:2, :2] - F[:2, 2:] @ np.linalg.solve(F[2:, 2:], F[2:, :2])


def _velocity_information(cfg: "sim.SimConfig", tr, tt: np.ndarray, dt_s: float) -> np.ndarray:
    """(delay, drift) information of the velocity matching (``logtools.latency.velocity``'s model: lever
    arm, offset, ramp and tilt estimated jointly) from both units' white velocity noise (the simulator's
    per-sample std at each unit's nav rate, as a density on the dt_s grid). Flexure rotates the slave
    without moving it: it does not enter."""
    n = len(tt)
    T = float(np.max(np.abs(tt)))
    a = tr.accel_ned_m_s2
    r = np.asarray(cfg.lever_arm_m, float)
    v = tr.vel_ned_m_s + np.einsum("nij,nj->ni", tr.dcm_nb, np.cross(tr.omega_nb_b_rad_s, r))
    lever = tr.dcm_nb @ skew(tr.omega_nb_b_rad_s)
    I3 = np.broadcast_to(np.eye(3), (n, 3, 3))
    J = np.concatenate([a[:, :, None], (a * tt[:, None])[:, :, None], lever, I3, I3 * (tt / T)[:, None, None],
                        skew(v - v[n // 2])], axis=2)
    m_rate = min(cfg.master_nav_rate_hz, 1.0 / dt_s)
    s_rate = min(cfg.slave_nav_rate_hz, 1.0 / dt_s)
    var = cfg.master_vel_noise_m_s ** 2 / (m_rate * dt_s) + cfg.slave_vel_noise_m_s ** 2 / (s_rate * dt_s)
    Jf = J.reshape(3 * n, -1)
    return _schur2(Jf.T @ Jf / var)
