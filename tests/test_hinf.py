"""H-infinity / adaptive H-infinity measurement updates (logtools.alignment.hinf) on linear toy systems."""
from __future__ import annotations

import numpy as np
import pytest

from logtools.alignment.hinf import (
    ahinf_update,
    hinf_update,
    initial_gamma_state,
    kf_posterior,
    propagate_over_delay,
)

DT_S = 0.1
N_STEPS = 600
MANOEUVRE = (200, 230)  # steps with an unmodelled 2 m/s^2 acceleration
F = np.array([[1.0, DT_S], [0.0, 1.0]])
Q_ACC = 1e-4
Q = Q_ACC * np.array([[DT_S**3 / 3, DT_S**2 / 2], [DT_S**2 / 2, DT_S]])
H = np.array([[1.0, 0.0]])
R = np.array([[0.5**2]])
P0 = np.diag([10.0, 4.0])
WEIGHT = np.diag(1.0 / np.diag(P0))  # states normalised by their initial sigma


def _truth(seed: int, accel_m_s2: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Constant-velocity track (position, velocity) with an unmodelled manoeuvre, and noisy positions."""
    rng = np.random.default_rng(seed)
    acc = np.where((np.arange(N_STEPS) >= MANOEUVRE[0]) & (np.arange(N_STEPS) < MANOEUVRE[1]), accel_m_s2, 0.0)
    vel = 1.0 + np.cumsum(acc * DT_S + rng.normal(size=N_STEPS) * np.sqrt(Q_ACC * DT_S))
    pos = np.cumsum(vel * DT_S)
    truth = np.stack([pos, vel], axis=1)
    return truth, pos + rng.normal(size=N_STEPS) * np.sqrt(R[0, 0])


def _textbook_kf(x, P, z, H_, R_):
    S = H_ @ P @ H_.T + R_
    K = P @ H_.T @ np.linalg.inv(S)
    return x + K @ (z - H_ @ x), P - K @ S @ K.T


def _run(mode: str, seed: int, gamma: float = np.inf, accel_m_s2: float = 2.0, **kw):
    truth, z = _truth(seed, accel_m_s2)
    x, P = np.zeros(2), P0.copy()
    gs = initial_gamma_state(weight=WEIGHT, **kw) if mode == "ahinf" else None
    est, ratios, gammas = [], [], []
    for k in range(N_STEPS):
        x, P = F @ x, F @ P @ F.T + Q
        zk = z[k : k + 1]
        if mode == "kf":
            x, P = _textbook_kf(x, P, zk, H, R)
        elif mode == "hinf":
            x, P, info = hinf_update(x, P, zk, H, R, gamma, weight=WEIGHT, **kw)
            gammas.append(info["gamma"])
        else:
            x, P, gs, info = ahinf_update(x, P, zk, H, R, gs)
            ratios.append(info["ratio"])
            gammas.append(info["gamma"])
        assert np.all(np.isfinite(P)) and np.all(np.isfinite(x))
        est.append(x)
    return np.array(est) - truth, np.array(ratios), np.array(gammas), P


def test_gamma_infinite_is_the_kalman_filter():
    err_kf, *_ = _run("kf", 0)
    err_inf, *_ = _run("hinf", 0, gamma=np.inf)
    err_big, *_ = _run("hinf", 0, gamma=1e9)
    np.testing.assert_allclose(err_inf, err_kf, rtol=0, atol=1e-9)
    np.testing.assert_allclose(err_big, err_kf, rtol=0, atol=1e-7)


def test_gamma_infinite_is_the_kalman_filter_random_systems():
    rng = np.random.default_rng(1)
    for _ in range(20):
        n, m = rng.integers(3, 16), rng.integers(1, 7)
        A = rng.normal(size=(n, n))
        P = A @ A.T + 0.1 * np.eye(n)
        H_ = rng.normal(size=(m, n))
        B = rng.normal(size=(m, m))
        R_ = B @ B.T + 0.5 * np.eye(m)
        x, z = rng.normal(size=n), rng.normal(size=m)
        x_ref, P_ref = _textbook_kf(x, P, z, H_, R_)
        for gamma in (np.inf, 1e10):
            x_h, P_h, info = hinf_update(x, P, z, H_, R_, gamma)
            np.testing.assert_allclose(x_h, x_ref, atol=1e-8 * (1 + np.abs(x_ref).max()))
            np.testing.assert_allclose(P_h, P_ref, atol=1e-8 * np.abs(P_ref).max())
            assert info["feasible"] and not info["fallback"]


@pytest.mark.parametrize("use_weight", [False, True])
def test_riccati_and_existence_condition_match_the_information_form(use_weight):
    """P_post^-1 = P^-1 + H^T R^-1 H - gamma^-2 S and gamma_bound^2 = 1 / lambda_min-condition (S002 24, 55)."""
    rng = np.random.default_rng(2)
    n, m = 8, 3
    A = rng.normal(size=(n, n))
    P = A @ A.T + 0.2 * np.eye(n)
    H_ = rng.normal(size=(m, n))
    R_ = np.diag(rng.uniform(0.5, 2.0, m))
    S_bar = np.diag(rng.uniform(0.0, 3.0, n)) if use_weight else np.eye(n)
    info_prior = np.linalg.inv(P) + H_.T @ np.linalg.inv(R_) @ H_
    # existence: info_prior - theta S_bar > 0  <=>  theta < 1 / lambda_max(S_bar info_prior^-1)
    bound2 = np.max(np.linalg.eigvals(S_bar @ np.linalg.inv(info_prior)).real)
    kw = {"weight": S_bar} if use_weight else {}
    _, _, info = hinf_update(np.zeros(n), P, np.zeros(m), H_, R_, 10.0, **kw)
    assert info["gamma_bound"] ** 2 == pytest.approx(bound2, rel=1e-9)
    gamma = np.sqrt(1.5 * bound2)  # feasible, inside the default fallback margin: ask for no fallback
    _, P_h, info = hinf_update(np.zeros(n), P, np.zeros(m), H_, R_, gamma, min_ratio=1.01, max_growth=np.inf, **kw)
    assert info["feasible"] and not info["fallback"] and info["gamma"] == gamma
    np.testing.assert_allclose(np.linalg.inv(P_h), info_prior - S_bar / gamma**2, rtol=1e-7, atol=1e-9)
    # a gamma below the bound is infeasible: raised, P stays positive definite
    _, P_f, info = hinf_update(np.zeros(n), P, np.zeros(m), H_, R_, 0.5 * np.sqrt(bound2), max_growth=np.inf, **kw)
    assert not info["feasible"] and info["fallback"] and info["gamma"] ** 2 == pytest.approx(2.0 * bound2)
    np.linalg.cholesky(P_f)


def test_finite_gamma_is_more_robust_than_kf_under_an_unmodelled_manoeuvre():
    for seed in range(3):
        err_kf, *_ = _run("kf", seed)
        err_h, _, gammas, _ = _run("hinf", seed, gamma=0.05)
        err_a, *_ = _run("ahinf", seed)
        after = slice(100, None)
        max_kf = np.abs(err_kf[after, 0]).max()
        assert np.abs(err_h[after, 0]).max() < 0.3 * max_kf
        assert np.abs(err_a[after, 0]).max() < 0.6 * max_kf
        # and they still converge: over the last 100 steps the fixed small gamma (a high-gain filter) beats
        # the raw measurement (sigma 0.5 m); the adaptive one is back near the (recovered) KF
        tail = slice(-100, None)
        rms = lambda e: np.sqrt(np.mean(e[tail, 0] ** 2))  # noqa: E731
        assert rms(err_h) < 0.4
        assert rms(err_a) < 2.0 * rms(err_kf) + 0.05


def test_finite_gamma_converges_without_mismatch():
    err_kf, *_ = _run("kf", 5, accel_m_s2=0.0)
    err_h, *_ = _run("hinf", 5, gamma=0.2, accel_m_s2=0.0)
    err_a, *_ = _run("ahinf", 5, accel_m_s2=0.0)
    tail = slice(-200, None)
    rms = lambda e: np.sqrt(np.mean(e[tail] ** 2, axis=0))  # noqa: E731
    # position within the measurement sigma, velocity within 0.1 m/s, and not much worse than the KF
    for e in (err_h, err_a):
        assert rms(e)[0] < 0.5 and rms(e)[1] < 0.1
        assert np.all(rms(e) < 2.0 * rms(err_kf) + 0.02)


def test_adaptive_gamma_drops_when_the_innovation_grows_and_recovers():
    _, ratios, gammas, _ = _run("ahinf", 0)
    # gamma^2 / bound: near the KF (ratio_max) while the innovations match their prediction
    before = np.median(ratios[100 : MANOEUVRE[0]])
    during = np.median(ratios[MANOEUVRE[0] + 5 : MANOEUVRE[1]])
    late = np.median(ratios[-150:])
    assert before > 1e3 and late > 1e3
    assert during < 100.0
    # the absolute gamma follows: lower during the manoeuvre than before or after
    g_during = np.median(gammas[MANOEUVRE[0] + 5 : MANOEUVRE[1]])
    assert g_during < 0.2 * np.median(gammas[100 : MANOEUVRE[0]]) and g_during < 0.2 * np.median(gammas[-150:])


def test_adaptive_gamma_state_window_and_bounds():
    gs = initial_gamma_state(kappa=5.0, window=3, ratio_min=1.5, ratio_max=50.0)
    x, P = np.zeros(2), P0.copy()
    for z in (0.0, 0.0, 100.0, 100.0, 100.0):  # huge innovations
        x, P, gs, info = ahinf_update(x, P, np.array([z]), H, R, gs)
        assert len(gs.innovation_ratios) <= 3
        assert 1.5 - 1e-9 <= info["ratio"] and gs.gamma == info["gamma"]
    assert gs.n_updates == 5 and gs.mean_innovation_ratio > 10
    assert info["ratio"] == pytest.approx(1.5) or info["fallback"]
    with pytest.raises(ValueError):
        initial_gamma_state(ratio_min=1.0)
    st = initial_gamma_state(sigma0=np.array([2.0, 0.0, np.inf]))
    np.testing.assert_allclose(np.diag(st.weight), [0.25, 0.0, 0.0])


@pytest.mark.parametrize("mode", ["hinf", "ahinf"])
def test_fallback_never_gives_nan_or_indefinite_P(mode):
    """Tiny gamma, an unobservable random-walk state, near-singular priors: P stays finite and PD."""
    rng = np.random.default_rng(3)
    n = 6
    F6 = np.eye(n)
    F6[0:3, 3:6] = DT_S * np.eye(3)  # 3 random walks driven by 3 biases
    Q6 = np.diag([1e-4] * 3 + [1e-8] * 3)
    H6 = np.zeros((2, n))
    H6[0, 0] = H6[1, 1] = 1.0  # state 2 and bias 5 are never observed
    R6 = np.eye(2) * 0.01
    x, P = np.zeros(n), np.diag([1.0, 1.0, 1.0, 1e-2, 1e-2, 1e-2])
    gs = initial_gamma_state(ratio_min=1.01, kappa=1e-3)
    for k in range(2000):
        x, P = F6 @ x, F6 @ P @ F6.T + Q6
        if k == 50:
            P = P + 1e-14 * np.ones((n, n))  # nearly singular perturbation
        z = rng.normal(size=2) * (50.0 if k % 97 == 0 else 0.1)  # heavy-tailed outliers
        if mode == "hinf":
            x, P, info = hinf_update(x, P, z, H6, R6, 1e-9)
            assert info["fallback"] and not info["feasible"]
        else:
            x, P, gs, info = ahinf_update(x, P, z, H6, R6, gs)
        assert np.all(np.isfinite(x)) and np.all(np.isfinite(P))
        np.testing.assert_allclose(P, P.T, atol=1e-12 * np.abs(P).max())
        np.linalg.cholesky(P)
    assert np.max(np.diag(P)) < 1e3  # no geometric blow-up of the unobserved states


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="gamma"):
        hinf_update(np.zeros(2), P0, np.zeros(1), H, R, 0.0)
    with pytest.raises(ValueError, match="not finite"):
        hinf_update(np.zeros(2), np.full((2, 2), np.nan), np.zeros(1), H, R, 1.0)
    with pytest.raises(ValueError, match="not finite"):
        ahinf_update(np.array([np.nan, 0.0]), P0, np.zeros(1), H, R, initial_gamma_state())


def test_propagate_over_delay_is_eq32():
    x, P = np.array([1.0, 2.0]), np.diag([1.0, 0.5])
    Phi = np.linalg.matrix_power(F, 3)
    x3, P3 = propagate_over_delay(x, P, Phi, 3 * Q)
    np.testing.assert_allclose(x3, [1.0 + 3 * DT_S * 2.0, 2.0])
    np.testing.assert_allclose(P3, Phi @ P @ Phi.T + 3 * Q)


def test_kf_posterior_nis_is_chi2_on_average():
    rng = np.random.default_rng(4)
    nis = []
    for _ in range(400):
        x_true = rng.normal(size=2) * np.sqrt(np.diag(P0))
        z = H @ x_true + rng.normal(size=1) * np.sqrt(R[0, 0])
        nis.append(kf_posterior(np.zeros(2), P0, z, H, R)[3])
    assert 0.8 < np.mean(nis) < 1.2
