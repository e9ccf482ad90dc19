"""Cramer-Rao bound of the latency for a simulated pair: what no estimator can beat on that run.

For a pair from ``logtools.sim`` the disturbance of the latency fit is known exactly: the slave's
flexure (seed 000 eq. 8, the simulator's second-order Markov rotation with its sigma and beta) and both
units' white sensor noise (ARW, VRW). The signals are known too, noise-free, from the simulator's truth.
The residual model is the one ``logtools.latency_flexure`` whitens::

    y_k = J_k p + H_k x_k + v_k,   x = (lam, lam'),   H_k = [[[w_k x], I], [[f_k x], 0]]

with p = (delay, drift, rotation, gyro bias, accelerometer bias, lever arm) and J their Jacobian built
from the truth (slave frame: w, w', f, f' of the master rotated by the mounting). The Fisher information
of p is sum_k Jw_k^T Jw_k with Jw the Kalman-whitened columns of J (innovations of the exact model);
the bound on the latency is sqrt(inv(F)[0, 0]), the other unknowns estimated jointly, the drift with the
Gaussian prior tapost's estimator uses (DRIFT_PRIOR_PPM; a Bayesian bound for that part). It is evaluated on
samples every ``dt_s`` (the truth is smooth; the flexure model is exact at any step) over the pair's
overlap, and with the gyros alone (``gyro``) as well as gyros and accelerometers (``aided``).

Used by ``bench_latency.py`` for the flexure runs (without flexure the bound is the sensors' white noise
alone, far below what interpolation and stamps allow, and is not reported).
"""
from __future__ import annotations

import numpy as np

from logtools import sim
from logtools.conventions import DEG, DEG_PER_SQRT_H, UG_PER_SQRT_HZ, dcm_from_euler, skew
from logtools.latency import DRIFT_PRIOR_PPM
from logtools.latency_flexure import FlexureModel, whitened_normal


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
    for name, rows, cols_used in (("aided", slice(None), list(range(15))),
                                  ("gyro", slice(0, 3), list(range(9)))):  # residual, delay .. gyro bias
        model = FlexureModel(sig, beta, noise[rows], dt_s)
        yy = np.ascontiguousarray(y[:, rows][:, :, cols_used])
        _, M, _ = whitened_normal(yy, w, f if name == "aided" else None, use, model, store=False)
        F = M[1:, 1:].copy()
        F[1, 1] += 1.0 / (DRIFT_PRIOR_PPM * 1e-6) ** 2  # the drift prior tapost's estimator uses
        out[name] = float(np.sqrt(np.linalg.inv(F)[0, 0]))
    return out
