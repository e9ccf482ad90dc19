"""State-space (Kalman) whitening of the latency fit's residuals with a flexure model.

The residuals of the latency fit (``logtools.latency``, gyro rows ``w_s(t + d) - R w_m - b`` and, when
both units log accelerometers, rows ``f_s(t + d) - R (f_m + lever arm terms) - b_a``) are, at the true
delay, what flexure and the sensors' noise leave. Seed 000 (eq. 8) models flexure as a second-order
Markov rotation ``lam`` of the slave per axis::

    lam'' = -beta^2 lam - 2 beta lam' + eta,      var(lam_i) = sigma_i^2

A rotation ``lam`` of the slave adds ``lam' + w_s x lam`` to its rates and ``f_s x lam`` to its specific
force, so the residual is, per sample k (slave frame)::

    y_k = J_k p + H_k x_k + v_k,   x = (lam, lam'),   H_k = [[[w_s,k x], I], [[f_s,k x], 0]],   v_k white

with p the fit's unknowns (delay, drift, rotation, biases, lever arm; J their Jacobian). The Kalman filter
of that model turns ``y`` and every column of ``J`` into innovations whitened by their covariance: least
squares on them is the generalised least squares (maximum likelihood) estimate of p, with the gravity
direction's modulation of the accelerometer rows (``f_s`` varies with the attitude) exact rather than
averaged as a stationary cross-spectrum would. The model's few parameters (sigma per axis, beta, the
white noise per channel) are fitted by maximising the restricted likelihood (p concentrated out).

Rates: the rows are block-averaged to ``~DECIMATE_FACTOR x`` the low-pass cutoff, where the low-passed
sensor noise is close to white (a Kalman filter on samples much denser than the band would read the
filter's correlation as information).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg as sla

from logtools.latency.config import DEFAULT, LatencyConfig

from logtools.jit import njit


__all__ = ["FlexureModel", "block_mean", "fit_model", "whitened_normal"]


@dataclass(frozen=True)
class FlexureModel:
    """Second-order Markov flexure per axis plus white noise per residual channel."""

    sigma_rad: np.ndarray  # (3,) flexure angle std per slave axis
    beta_1_s: float  # flexure bandwidth (s^-1), shared by the axes
    noise_var: np.ndarray  # (C,) white noise variance per channel, per block sample
    dt_s: float  # block sample interval

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(Phi, Qd, P0): exact discretisation over dt_s (Van Loan) and the stationary covariance."""
        b, s2 = self.beta_1_s, self.sigma_rad ** 2
        A = np.zeros((6, 6))
        A[:3, 3:] = np.eye(3)
        A[3:, :3] = -b * b * np.eye(3)
        A[3:, 3:] = -2.0 * b * np.eye(3)
        Qc = np.zeros((6, 6))
        Qc[3:, 3:] = np.diag(4.0 * b ** 3 * s2)
        M = sla.expm(np.block([[-A, Qc], [np.zeros((6, 6)), A.T]]) * self.dt_s)
        Phi = M[6:, 6:].T
        Qd = Phi @ M[:6, 6:]
        Qd = 0.5 * (Qd + Qd.T)
        P0 = np.diag(np.concatenate([s2, b * b * s2]))
        return Phi, Qd, P0


def block_mean(x: np.ndarray, use: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Means over consecutive blocks of k samples along axis 0 (the tail that does not fill a block is
    dropped); a block is used only when all its samples are."""
    nb = len(x) // k
    xs = x[:nb * k].reshape((nb, k) + x.shape[1:]).mean(axis=1)
    ub = use[:nb * k].reshape(nb, k).all(axis=1)
    return xs, ub


@njit(always=True)  # inside L-BFGS-B's numerical gradient: as Python, one real log took more than 13 min
def _kf_whiten(y, ws, fs, use, Phi, Qd, P0, noise_var, store):  # pragma: no cover - compiled
    """Innovations of every column of y (n, C, M), whitened by the innovation covariance's Cholesky
    factor, and the sum of log det of that covariance. C = 3 (gyro rows) or 6 (gyro + accelerometer);
    ws, fs (n, 3): the slave's rate and specific force (a rotation lam of the slave adds v x lam to a
    vector v it measures). Also the cross-products sum W^T W (M, M); the innovations themselves only
    with ``store`` (else an empty array). Explicit loops on preallocated buffers (no temporaries per step)."""
    n, C, M = y.shape
    out = np.zeros((n if store else 0, C, M))
    MM = np.zeros((M, M))
    x = np.zeros((6, M))
    x2 = np.zeros((6, M))
    P = P0.copy()
    P2 = np.zeros((6, 6))
    H = np.zeros((C, 6))
    PHt = np.zeros((6, C))
    S = np.zeros((C, C))
    L = np.zeros((C, C))
    w = np.zeros((C, M))
    G = np.zeros((C, 6))
    for i in range(3):
        H[i, 3 + i] = 1.0
    logdet = 0.0
    for k in range(n):
        if k > 0:
            for i in range(6):
                for m in range(M):
                    acc = 0.0
                    for j in range(6):
                        acc += Phi[i, j] * x[j, m]
                    x2[i, m] = acc
            for i in range(6):
                for m in range(M):
                    x[i, m] = x2[i, m]
            for i in range(6):  # P2 = Phi P
                for j in range(6):
                    acc = 0.0
                    for l in range(6):
                        acc += Phi[i, l] * P[l, j]
                    P2[i, j] = acc
            for i in range(6):  # P = P2 Phi^T + Qd
                for j in range(6):
                    acc = Qd[i, j]
                    for l in range(6):
                        acc += P2[i, l] * Phi[j, l]
                    P[i, j] = acc
        if not use[k]:
            continue
        w0, w1, w2 = ws[k, 0], ws[k, 1], ws[k, 2]
        H[0, 1], H[0, 2] = -w2, w1
        H[1, 0], H[1, 2] = w2, -w0
        H[2, 0], H[2, 1] = -w1, w0
        if C == 6:
            f0, f1, f2 = fs[k, 0], fs[k, 1], fs[k, 2]
            H[3, 1], H[3, 2] = -f2, f1
            H[4, 0], H[4, 2] = f2, -f0
            H[5, 0], H[5, 1] = -f1, f0
        for i in range(6):  # PHt = P H^T
            for c in range(C):
                acc = 0.0
                for j in range(6):
                    acc += P[i, j] * H[c, j]
                PHt[i, c] = acc
        for a in range(C):  # S = H PHt + R
            for b in range(C):
                acc = 0.0
                for j in range(6):
                    acc += H[a, j] * PHt[j, b]
                S[a, b] = acc
            S[a, a] += noise_var[a]
        for a in range(C):  # Cholesky S = L L^T
            for b in range(a + 1):
                acc = S[a, b]
                for j in range(b):
                    acc -= L[a, j] * L[b, j]
                if a == b:
                    L[a, a] = np.sqrt(max(acc, 1e-300))
                else:
                    L[a, b] = acc / L[b, b]
        for a in range(C):  # w = L^-1 (y - H x)
            for m in range(M):
                acc = y[k, a, m]
                for j in range(6):
                    acc -= H[a, j] * x[j, m]
                for j in range(a):
                    acc -= L[a, j] * w[j, m]
                w[a, m] = acc / L[a, a]
                if store:
                    out[k, a, m] = w[a, m]
            logdet += 2.0 * np.log(L[a, a])
        for m1 in range(M):
            for m2 in range(m1 + 1):
                acc = 0.0
                for a in range(C):
                    acc += w[a, m1] * w[a, m2]
                MM[m1, m2] += acc
        for a in range(C):  # G = L^-1 PHt^T   (K = G^T L^-1)
            for i in range(6):
                acc = PHt[i, a]
                for j in range(a):
                    acc -= L[a, j] * G[j, i]
                G[a, i] = acc / L[a, a]
        for i in range(6):  # x += G^T w ; P -= G^T G
            for m in range(M):
                acc = 0.0
                for a in range(C):
                    acc += G[a, i] * w[a, m]
                x[i, m] += acc
            for j in range(i + 1):
                acc = 0.0
                for a in range(C):
                    acc += G[a, i] * G[a, j]
                v = P[i, j] - acc
                P[i, j] = v
                P[j, i] = v
            if P[i, i] < 0.0:
                P[i, i] = 0.0
    for m1 in range(M):
        for m2 in range(m1):
            MM[m2, m1] = MM[m1, m2]
    return out, MM, logdet


def whitened_normal(y: np.ndarray, ws: np.ndarray, fs: np.ndarray | None, use: np.ndarray,
                    model: FlexureModel, *, store: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
    """(W, M, logdet): the Kalman-whitened innovations W (n, C, M) of the columns of y (empty unless
    ``store``), their cross-products M = sum W^T W (M, M) and sum log det of the innovation covariance."""
    Phi, Qd, P0 = model.matrices()
    C = y.shape[1]
    f = np.zeros((len(y), 3)) if fs is None else np.ascontiguousarray(fs, dtype=float)
    return _kf_whiten(np.ascontiguousarray(y, dtype=float), np.ascontiguousarray(ws, dtype=float), f,
                      np.ascontiguousarray(use), Phi, Qd, P0, np.asarray(model.noise_var, float).reshape(C), store)


def _nll(M: np.ndarray, logdet: float, p: int) -> float:
    """Restricted negative log-likelihood with the p regression unknowns concentrated out
    (columns 1..p of M; column 0 the residual)."""
    F, s, q = M[1:p + 1, 1:p + 1], M[1:p + 1, 0], M[0, 0]
    try:
        c = np.linalg.cholesky(F)
    except np.linalg.LinAlgError:
        return np.inf
    z = np.linalg.solve(c, s)
    return 0.5 * (logdet + q - float(z @ z) + 2.0 * float(np.sum(np.log(np.diag(c)))))


def _model(theta: np.ndarray, C: int, dt_s: float) -> FlexureModel:
    return FlexureModel(np.exp(theta[:3]), float(np.exp(theta[3])), np.exp(theta[4:4 + C]), dt_s)


def fit_model(y: np.ndarray, ws: np.ndarray, fs: np.ndarray | None, use: np.ndarray, dt_s: float, p: int,
              cfg: LatencyConfig = DEFAULT) -> FlexureModel | None:
    """Maximum (restricted) likelihood flexure and noise parameters for the residual column y[:, :, 0]
    with the p regressors y[:, :, 1:p + 1] concentrated out; None when the data cannot support it."""
    n, C, _ = y.shape
    if use.sum() < cfg.flexure.ml_blocks_per_unknown * (p + 4 + C):
        return None
    y = y[:, :, :p + 1]
    # column scaling: the likelihood is invariant to it up to a constant, the numerics are not
    sc = np.sqrt(np.sum(y[use] ** 2, axis=(0, 1)))
    sc[sc == 0] = 1.0
    y = y / sc
    r = y[use, :, 0]
    v = np.maximum(np.var(r, axis=0), 1e-300)
    beta0 = 2.0 * np.pi * 0.1
    # start: half the variance to white noise, half to flexure (gyro rows see beta sigma)
    sig0 = np.sqrt(0.5 * v[:3]) / beta0
    theta0 = np.concatenate([np.log(sig0), [np.log(beta0)], np.log(0.5 * v)])
    lo = np.concatenate([np.log(sig0) - 12.0, [np.log(2 * np.pi * 0.002)], np.log(v) - 14.0])
    hi = np.concatenate([np.log(sig0) + 6.0, [np.log(np.pi / dt_s)], np.log(v) + 2.0])

    def f(theta):
        _, M, ld = whitened_normal(y, ws, fs, use, _model(theta, C, dt_s), store=False)
        val = _nll(M, ld, p)
        return val if np.isfinite(val) else 1e300

    from scipy import optimize  # (here: scipy.optimize and what it imports cost 0.2-0.3 s, and a short log's
    # analysis never gets this far)

    res = optimize.minimize(f, theta0, method="L-BFGS-B", bounds=list(zip(lo, hi)),
                            options={"maxiter": cfg.flexure.max_ml_iter})
    if not np.isfinite(res.fun):
        return None
    m = _model(res.x, C, dt_s)
    return FlexureModel(m.sigma_rad * sc[0], m.beta_1_s, m.noise_var * sc[0] ** 2, dt_s)

