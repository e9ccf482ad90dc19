"""H-infinity and adaptive H-infinity measurement updates for the transfer-alignment error-state filter.

Seed S002 ("Adaptive H-infinity filtering with delay compensation for SINS transfer alignment",
Sensors 17(12):2753, 2017) gives its equations only as images. What follows is what we derived from its
text and from the standard game-theoretic / Krein-space H-infinity filter (Hassibi, Sayed & Kailath,
"Indefinite-Quadratic Estimation and Control", thm 4.2.1, the *a posteriori* central filter; Simon,
"Optimal State Estimation", ch. 11). It is what this module implements.

Problem (S002 eqs 13-23)
------------------------
``x_k = Phi x_{k-1} + Gamma w_{k-1}``, ``y_k = H x_k + v_k``; the quantity to estimate is
``s_k = L x_k`` (S002 eq 15, L an n x n matrix; here ``weight`` = S_bar = L^T L, identity by default).
The filter ``s_hat_k = F(y_0..y_k)`` (a posteriori: ``y_k`` included, S002 eq 20) must keep the energy
gain from the disturbances to the estimation error below ``xi`` (S002 eqs 22-23; ``gamma`` here):

    sum |s_k - s_hat_k|^2  <  gamma^2 ( |x_0 - x_hat_0|^2_{P0^-1} + sum |w|^2_{Q^-1} + sum |v|^2_{R^-1} ).

Krein-space form (S002 eqs 16-19): stack ``[y_k; s_hat_k] = [H; L] x_k + [v_k; ...]`` with the
indefinite "covariance" ``R_e = diag(R, -gamma^2 I)`` (S002 eq 19: "an indefinite covariance matrix ...
diagonal"). The Krein-space Kalman recursion on that stacked system gives (S002 eqs 24-31):

    prediction    x_pred = Phi x,            P_pred = Phi P Phi^T + Gamma Q Gamma^T           (27, 28)
    gain          K = P_pred H^T (H P_pred H^T + R)^-1                                         (29)
    estimate      x = x_pred + K (y - H x_pred)                                                 (30)
    Riccati       P = P_pred - P_pred [H^T L^T] R_e,k^-1 [H; L] P_pred,                       (25, 26, 31)
                  R_e,k = [[R + H P_pred H^T, H P_pred L^T], [L P_pred H^T, -gamma^2 I + L P_pred L^T]]
    equivalently  P^-1 = P_pred^-1 + H^T R^-1 H - gamma^-2 L^T L                                (33-45)
    existence     P_pred^-1 + H^T R^-1 H - gamma^-2 L^T L > 0                                   (24)

The gain and the estimate are the Kalman filter's (with the H-infinity Riccati variable in place of the
KF covariance); only the covariance recursion differs: it shrinks less, by ``gamma^-2 L^T L`` in
information form. As ``gamma -> inf`` it is exactly the Kalman filter (S002: "When xi tends to infinity
H-inf filter degenerates to standard Kalman filter").

How we compute it (no explicit inverse of P): the KF posterior ``P_kf`` (Joseph form, Cholesky solve of
the innovation covariance) satisfies ``P_kf^-1 = P_pred^-1 + H^T R^-1 H``, so the existence condition
(24) is ``P_kf^-1 > gamma^-2 S_bar``, i.e. (S002 Theorem 2: ``A > B`` iff ``lambda_max(B A^-1) < 1``)

    gamma^2 > mu_max := lambda_max(S_bar P_kf)                                                  (55)

and with ``S_bar = L^T L`` (L diagonal for the usual diagonal weight), ``L P_kf L^T = V diag(mu) V^T``,
``W = P_kf L^T V``, ``theta = gamma^-2``, the Woodbury identity gives

    P = (P_kf^-1 - theta S_bar)^-1 = P_kf + W diag(theta / (1 - theta mu)) W^T,

a PSD increment added to a PSD matrix, from one symmetric eigen-decomposition of an n x n matrix (no
inverse of P_kf; zero weights allowed); the eigenvalues of ``S_bar P`` are ``mu / (1 - theta mu)``.

Fallback (ours, not in S002): gamma is raised, never lowered, to the largest of
  * the requested gamma;
  * ``sqrt(min_ratio * mu_max)``: the existence condition (55) with margin (the worst direction is
    inflated at most ``min_ratio / (min_ratio - 1)`` times, 2x for the default 2);
  * the growth guard ``gamma^2 >= 1 / (1/mu_max - 1/(max_growth * nu_pred))``, ``nu_pred =
    lambda_max(S_bar P_pred)``: after the update the worst weighted direction is at most ``max_growth``
    times as uncertain as before the measurement (default 1: never worse than the prior). When the
    worst weighted direction is one the measurement does not inform, ``mu_max = nu_pred`` and this
    makes the update the KF's; without it a finite gamma would double P there at every update until
    it overflows (the H-infinity problem has no solution for an undetectable penalised state).
so P stays finite, symmetric and positive definite whatever gamma is asked for.
``info["feasible"]`` says whether the requested gamma satisfied (55) strictly, ``info["fallback"]``
whether it was raised.

Delay compensation (S002 eq 32): the update estimates the error state at the measurement instant
``T_P - tau``; it is carried to the current instant by ``x(T_P) = Phi(T_P, T_P - tau) x(T_P - tau)``
(and ``P`` likewise plus the process noise over ``tau``): :func:`propagate_over_delay`.

Adaptive robustness factor (S002 eqs 54-57)
-------------------------------------------
Innovation ``e_k = y_k - H x_pred`` (54), predicted covariance ``S_k = H P_pred H^T + R``. The paper
compares the observed innovation energy ``e^T e`` with its predicted value and, as we read its text
around the images of eqs 55-57, sets ``gamma^2 = (1 + nu) lambda_max(...)`` (the bound of (55)) with
``nu = kappa N / (e^T e)`` (``kappa > 0`` tuned once by experiment, ``N`` the state dimension): gamma
falls when the innovation grows (more robust) and rises toward the KF when
it shrinks. ``e^T e`` has units (it mixes m/s and rad), so we use the scale-free form of the same rule,
driven by the EXCESS of the observed innovation energy over its prediction:

    rho_k   = e_k^T S_k^-1 e_k / m            (NIS per measurement; E = 1 when the model is right)
    rho_bar = mean of rho over the last ``window`` updates (the innovation statistics window)
    nu      = kappa / max(rho_bar - 1, 0)     (57: nu inversely proportional to the excess energy)
    gamma^2 = clip(1 + nu, ratio_min, ratio_max) * mu_max                                       (56)

so gamma always satisfies the existence condition (55) with margin ``>= ratio_min``. Innovations larger
than predicted (``rho_bar >> 1``) drive gamma down toward ``ratio_min`` (most robust: ``nu ~ kappa /
rho_bar``, the paper's inverse law); innovations no larger than predicted (``rho_bar <= 1``) give
``nu = inf`` clipped to ``ratio_max`` (practically the KF, which is optimal when the model holds). We
subtract the expected 1 (rather than the paper's plain inverse) so that a filter whose model is right is
the KF and not a permanently detuned one. The growth guard of the fixed-gamma update applies too
(gamma is raised when the worst weighted direction would end more uncertain than before the
measurement). The exact form of S002's eqs 56-57 is not recoverable from the text (images); what the
text fixes, and what we keep, is: the bound of (55) times a factor ``1 + nu``, ``nu > 0`` falling as
the innovation energy grows, with one tuning constant ``kappa``.

Units caveat: with ``S_bar = I`` the penalty mixes state units (rad, m/s, rad/s), so gamma is dominated by
the state with the largest variance in SI. Pass ``weight = diag(1 / sigma0^2)`` (states normalised by
their initial sigma; zeros for states not to be penalised, e.g. a delay state) to make gamma
dimensionless. States the measurements never inform make the growth guard return the KF update
whenever they are the worst weighted direction: keep them out of ``weight`` (weight 0) if the
H-infinity robustness is wanted for the others.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = [
    "AdaptiveGammaState",
    "ahinf_update",
    "hinf_update",
    "initial_gamma_state",
    "kf_posterior",
    "propagate_over_delay",
]

_JITTER = 1e-12


def _sym(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + a.T)


def _pd_matrix(s: np.ndarray) -> np.ndarray:
    """The symmetric matrix ``s`` (innovation covariance), with relative jitter added if the Cholesky
    test says it is not positive definite."""
    s = _sym(s)
    try:
        np.linalg.cholesky(s)
        return s
    except np.linalg.LinAlgError:
        scale = max(float(np.max(np.abs(np.diag(s)))), 1e-300)
        for k in range(1, 8):
            sj = s + np.eye(len(s)) * scale * _JITTER * 100.0**k
            try:
                np.linalg.cholesky(sj)
                return sj
            except np.linalg.LinAlgError:
                continue
        raise


def kf_posterior(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Kalman measurement update (Joseph form; the gain and NIS from one linear solve with the innovation
    covariance, positive definiteness checked by Cholesky).

    Returns ``(x_post, P_post, innovation, nis)`` with ``nis = e^T S^-1 e`` (not divided by m).
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    H = np.atleast_2d(np.asarray(H, dtype=float))
    R = np.atleast_2d(np.asarray(R, dtype=float))
    e = np.atleast_1d(np.asarray(z, dtype=float)) - H @ x
    PHt = P @ H.T
    S = _pd_matrix(H @ PHt + R)
    sol = np.linalg.solve(S, np.concatenate([PHt.T, e[:, None]], axis=1))  # [S^-1 H P, S^-1 e]
    K = sol[:, :-1].T  # P H^T S^-1
    nis = float(e @ sol[:, -1])
    IKH = -K @ H
    IKH[np.diag_indices_from(IKH)] += 1.0
    P_post = _sym(IKH @ P @ IKH.T + K @ R @ K.T)
    return x + K @ e, P_post, e, nis


def _weight_factor(weight: np.ndarray | None) -> np.ndarray | None:
    """``L`` with ``S_bar = L^T L``: None (identity), a vector (diagonal weight: ``sqrt(diag)``) or a matrix."""
    if weight is None:
        return None
    w = np.asarray(weight, dtype=float)
    if w.ndim == 1:
        return np.sqrt(np.clip(w, 0.0, None))
    d = np.diagonal(w)
    if not np.any(w - np.diag(d)):
        return np.sqrt(np.clip(d, 0.0, None))
    lam, U = np.linalg.eigh(_sym(w))
    return np.sqrt(np.clip(lam, 0.0, None))[:, None] * U.T


def _hinf_directions(P_kf: np.ndarray, lf: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(mu, W)``: ``mu`` the eigenvalues of ``S_bar P_kf`` (= of ``L P_kf L^T``, eigenvectors V) and
    ``W = P_kf L^T V``, so that (Woodbury) ``(P_kf^-1 - theta L^T L)^-1 = P_kf + W diag(theta / (1 - theta
    mu)) W^T``: a PSD increment, no inverse of P_kf, one symmetric eigen-decomposition."""
    if lf is None:
        G = P_kf
        M = P_kf
    elif lf.ndim == 1:
        G = P_kf * lf[None, :]
        M = G * lf[:, None]
    else:
        G = P_kf @ lf.T
        M = lf @ G
    mu, V = np.linalg.eigh(M)  # M symmetric by construction (eigh reads one triangle)
    return np.clip(mu, 0.0, None), G @ V


def _weighted_max_eig(P: np.ndarray, lf: np.ndarray | None) -> float:
    """``lambda_max(S_bar P)`` (= of ``L P L^T``)."""
    if lf is None:
        M = P
    elif lf.ndim == 1:
        M = P * np.outer(lf, lf)
    else:
        M = lf @ P @ lf.T
    return float(np.linalg.eigvalsh(M)[-1])


def _gamma_floor(mu_max: float, nu_pred: float, min_ratio: float, max_growth: float) -> float:
    """Smallest gamma^2 allowed: existence margin and growth guard (module doc, "Fallback")."""
    if mu_max <= 0.0:
        return 0.0
    floor = min_ratio * mu_max
    room = 1.0 / mu_max - 1.0 / (max_growth * nu_pred) if nu_pred > 0 else 0.0
    floor = max(floor, 1.0 / room) if room > 0 else float("inf")
    return floor


def _floor_check(gamma2: float, mu_max: float, P: np.ndarray, lf: np.ndarray | None, min_ratio: float,
                 max_growth: float) -> float:
    """The gamma^2 floor, computed exactly only when it may bind: ``max(diag(L P L^T)) <= nu_pred`` gives
    an upper bound of the floor; when gamma^2 clears it, the eigenvalue of ``L P L^T`` is not needed."""
    if lf is None:
        diag = np.diagonal(P)
    elif lf.ndim == 1:
        diag = np.diagonal(P) * lf * lf
    else:
        diag = np.einsum("ij,jk,ik->i", lf, P, lf)
    floor_ub = _gamma_floor(mu_max, float(np.max(diag)) if diag.size else 0.0, min_ratio, max_growth)
    if gamma2 >= floor_ub:
        return floor_ub
    return _gamma_floor(mu_max, _weighted_max_eig(P, lf), min_ratio, max_growth)


def _inflate(P_kf: np.ndarray, mu: np.ndarray, W: np.ndarray, gamma: float) -> np.ndarray:
    if not np.isfinite(gamma):
        return P_kf
    theta = 1.0 / (gamma * gamma)
    d = theta / (1.0 - theta * mu)
    return _sym(P_kf + (W * d) @ W.T)


def _check_inputs(x: np.ndarray, P: np.ndarray) -> None:
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        raise ValueError("H-infinity update: state or covariance is not finite")


def hinf_update(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    gamma: float,
    *,
    weight: np.ndarray | None = None,
    min_ratio: float = 2.0,
    max_growth: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """One a posteriori H-infinity measurement update (S002 eqs 24-31, derivation in the module doc).

    ``x, P``: predicted state and H-infinity Riccati variable; ``z = H x + v``; ``R``: measurement noise
    weight; ``gamma``: robustness factor (``xi`` in S002; ``np.inf`` gives the Kalman filter exactly);
    ``weight``: ``S_bar = L^T L`` (n x n PSD, default identity); ``min_ratio``, ``max_growth``: the
    fallback (module doc): gamma is raised to at least ``sqrt(min_ratio * mu_max)`` and so that the
    worst weighted direction grows at most ``max_growth`` times through the update.
    Returns ``(x_post, P_post, info)``, info = {gamma (used), gamma_requested, gamma_bound
    (sqrt(mu_max), the existence limit), feasible, fallback, innovation_ratio (NIS / m), nis}.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    _check_inputs(x, P)
    gamma = float(gamma)
    if not gamma > 0.0:
        raise ValueError(f"H-infinity update: gamma must be > 0, got {gamma}")
    w = _weight_factor(weight)
    x_post, P_kf, e, nis = kf_posterior(x, P, z, H, R)
    if not np.isfinite(gamma):  # the Kalman filter exactly
        info = {"gamma": gamma, "gamma_requested": gamma, "gamma_bound": float("nan"), "feasible": True,
                "fallback": False, "innovation_ratio": nis / max(len(e), 1), "nis": nis}
        return x_post, P_kf, info
    mu, W = _hinf_directions(P_kf, w)
    mu_max = float(mu[-1]) if mu.size else 0.0
    feasible = bool(gamma * gamma > mu_max)
    floor = _floor_check(gamma * gamma, mu_max, P, w, min_ratio, max_growth)
    fallback = bool(gamma * gamma < floor)
    gamma_used = float(np.sqrt(floor)) if fallback else gamma
    P_post = _inflate(P_kf, mu, W, gamma_used)
    info = {
        "gamma": gamma_used,
        "gamma_requested": gamma,
        "gamma_bound": float(np.sqrt(mu_max)),
        "feasible": feasible,
        "fallback": fallback,
        "innovation_ratio": nis / max(len(e), 1),
        "nis": nis,
    }
    return x_post, P_post, info


@dataclass(frozen=True, eq=False)
class AdaptiveGammaState:
    """State of the adaptive robustness factor (S002 eqs 54-57, our scale-free form; see module doc).

    ``gamma``: the last gamma used (``inf`` before the first update); ``ratio``: last
    ``gamma^2 / mu_max``; ``kappa``: the correlation coefficient of eq 57; ``ratio_min, ratio_max``:
    bounds on ``gamma^2 / mu_max`` (``ratio_min > 1`` keeps the existence condition with margin);
    ``window``: number of updates in the innovation statistics; ``innovation_ratios``: the last
    ``window`` values of ``e^T S^-1 e / m``; ``weight``: ``S_bar`` (None = identity).
    """

    gamma: float
    ratio: float
    kappa: float
    ratio_min: float
    ratio_max: float
    window: int
    innovation_ratios: tuple[float, ...] = ()
    weight: np.ndarray | None = None
    n_updates: int = 0
    max_growth: float = 1.0

    @property
    def mean_innovation_ratio(self) -> float:
        r = self.innovation_ratios
        return float(sum(r) / len(r)) if r else 1.0


def initial_gamma_state(
    *,
    kappa: float = 5.0,
    window: int = 10,
    ratio_min: float = 2.0,
    ratio_max: float = 1e6,
    weight: np.ndarray | None = None,
    sigma0: np.ndarray | None = None,
    max_growth: float = 1.0,
) -> AdaptiveGammaState:
    """Start of the adaptive robustness factor.

    ``sigma0`` (initial state sigmas, zeros/inf allowed) is a shortcut for ``weight = diag(1/sigma0^2)``
    (states with ``sigma0 <= 0`` or non-finite get weight 0: not penalised).
    """
    if not (kappa > 0 and window >= 1 and 1.0 < ratio_min <= ratio_max):
        raise ValueError("adaptive H-infinity: need kappa > 0, window >= 1, 1 < ratio_min <= ratio_max")
    if weight is None and sigma0 is not None:
        s = np.asarray(sigma0, dtype=float)
        ok = np.isfinite(s) & (s > 0)
        w = np.zeros_like(s)
        w[ok] = 1.0 / s[ok] ** 2
        weight = np.diag(w)
    elif weight is not None:
        weight = np.asarray(weight, dtype=float)
    return AdaptiveGammaState(
        gamma=float("inf"), ratio=float(ratio_max), kappa=float(kappa), ratio_min=float(ratio_min),
        ratio_max=float(ratio_max), window=int(window), weight=weight, max_growth=float(max_growth),
    )


def ahinf_update(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    gamma_state: AdaptiveGammaState,
) -> tuple[np.ndarray, np.ndarray, AdaptiveGammaState, dict]:
    """Adaptive H-infinity update: gamma from the innovation statistics, then :func:`hinf_update`'s update.

    Returns ``(x_post, P_post, new_gamma_state, info)``; info as :func:`hinf_update` plus ``ratio``
    (``gamma^2 / mu_max``), ``mean_innovation_ratio`` (window mean) and ``nu`` (eq 57).
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    _check_inputs(x, P)
    gs = gamma_state
    x_post, P_kf, e, nis = kf_posterior(x, P, z, H, R)
    rho = nis / max(len(e), 1)
    ratios = (gs.innovation_ratios + (rho,))[-gs.window:]
    rho_bar = float(sum(ratios) / len(ratios))
    excess = rho_bar - 1.0
    nu = gs.kappa / excess if excess > 0 else float("inf")
    ratio = float(np.clip(1.0 + nu, gs.ratio_min, gs.ratio_max))
    lf = _weight_factor(gs.weight)
    mu, W = _hinf_directions(P_kf, lf)
    mu_max = float(mu[-1]) if mu.size else 0.0
    gamma2 = ratio * mu_max
    floor = _floor_check(gamma2, mu_max, P, lf, gs.ratio_min, gs.max_growth)
    fallback = bool(gamma2 < floor)
    gamma2 = max(gamma2, floor)
    gamma = float(np.sqrt(gamma2)) if 0.0 < gamma2 < float("inf") else float("inf")
    P_post = _inflate(P_kf, mu, W, gamma)
    new_state = replace(
        gs, gamma=gamma, ratio=_gamma_ratio(gamma2, mu_max), innovation_ratios=ratios, n_updates=gs.n_updates + 1
    )
    info = {
        "gamma": gamma,
        "gamma_bound": float(np.sqrt(mu_max)),
        "feasible": True,
        "fallback": fallback,
        "ratio": _gamma_ratio(gamma2, mu_max),
        "nu": nu,
        "innovation_ratio": rho,
        "mean_innovation_ratio": rho_bar,
        "nis": nis,
    }
    return x_post, P_post, new_state, info


def _gamma_ratio(gamma2: float, mu_max: float) -> float:
    """``gamma^2 / mu_max``: how far gamma sits above the existence bound (inf for the KF)."""
    return float(gamma2 / mu_max) if mu_max > 0 and np.isfinite(gamma2) else float("inf")


def propagate_over_delay(
    x: np.ndarray, P: np.ndarray, Phi_tau: np.ndarray, Q_tau: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """S002 eq 32: carry the error state estimated at ``T_P - tau`` to the current instant ``T_P``.

    ``Phi_tau = Phi(T_P, T_P - tau)`` (product of the per-step transition matrices over the delay),
    ``Q_tau`` the process noise accumulated over it (optional).
    """
    x_now = Phi_tau @ x
    P_now = Phi_tau @ P @ Phi_tau.T
    if Q_tau is not None:
        P_now = P_now + Q_tau
    return x_now, _sym(P_now)
