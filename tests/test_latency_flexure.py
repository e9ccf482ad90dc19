"""The Kalman (state-space flexure model) whitening of the latency fit: kernel, likelihood, estimator."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from logtools.conventions import skew
from logtools.latency import LatencyConfig, Stages, estimate
from logtools.latency.flexure import FlexureModel, block_mean, fit_model, whitened_normal
from logtools.latency.kalman import refine_flex

DEG = np.pi / 180.0
#: the spectral GLS alone (no Kalman flexure-model stage)
NO_KALMAN = replace(LatencyConfig(), flexure=replace(LatencyConfig().flexure, kalman=False))


def _reference_kf(y, ws, fs, use, model):
    """Textbook Kalman filter (numpy, no tricks): innovations whitened by the Cholesky factor of S."""
    Phi, Qd, P0 = model.matrices()
    n, C, M = y.shape
    x, P = np.zeros((6, M)), P0.copy()
    out, logdet = np.zeros((n, C, M)), 0.0
    for k in range(n):
        if k:
            x, P = Phi @ x, Phi @ P @ Phi.T + Qd
        if not use[k]:
            continue
        H = np.zeros((C, 6))
        H[:3, :3], H[:3, 3:] = skew(ws[k]), np.eye(3)
        if C == 6:
            H[3:, :3] = skew(fs[k])
        S = H @ P @ H.T + np.diag(model.noise_var)
        Lc = np.linalg.cholesky(S)
        e = y[k] - H @ x
        out[k] = np.linalg.solve(Lc, e)
        logdet += 2 * np.sum(np.log(np.diag(Lc)))
        K = P @ H.T @ np.linalg.inv(S)
        x, P = x + K @ e, (np.eye(6) - K @ H) @ P
    return out, logdet


def _markov_flexure(rng, n, dt, sigma, beta):
    m = FlexureModel(np.asarray(sigma, float), beta, np.ones(6), dt)
    Phi, Qd, P0 = m.matrices()
    x = rng.multivariate_normal(np.zeros(6), P0)
    out = np.empty((n, 6))
    Lq = np.linalg.cholesky(Qd + 1e-30 * np.eye(6))
    for k in range(n):
        out[k] = x
        x = Phi @ x + Lq @ rng.standard_normal(6)
    return out


@pytest.mark.parametrize("C", [3, 6])
def test_kernel_matches_a_textbook_kalman_filter(C):
    rng = np.random.default_rng(C)
    n, M = 200, 4
    y = rng.standard_normal((n, C, M))
    ws, fs = 0.3 * rng.standard_normal((n, 3)), rng.standard_normal((n, 3)) + [0, 0, -9.8]
    use = rng.random(n) > 0.1
    model = FlexureModel(np.array([1e-3, 2e-3, 5e-4]), 1.7, np.linspace(0.5, 2.0, C) * 1e-2, 0.1)
    W, Mx, ld = whitened_normal(y, ws, fs if C == 6 else None, use, model)
    W0, ld0 = _reference_kf(y, ws, fs, use, model)
    np.testing.assert_allclose(W, W0, rtol=1e-8, atol=1e-10)
    assert ld == pytest.approx(ld0, rel=1e-10)
    Wf = W0.reshape(-1, M)
    np.testing.assert_allclose(Mx, Wf.T @ Wf, rtol=1e-9)
    _, M2, _ = whitened_normal(y, ws, fs if C == 6 else None, use, model, store=False)
    np.testing.assert_allclose(M2, Mx)


def test_model_matrices_give_the_stationary_variance():
    m = FlexureModel(np.array([0.05, 0.1, 0.02]) * DEG, 2.0, np.ones(6), 0.05)
    Phi, Qd, P0 = m.matrices()
    np.testing.assert_allclose(Phi @ P0 @ Phi.T + Qd, P0, rtol=1e-9, atol=1e-18)


def test_block_mean_drops_partial_and_masked_blocks():
    x = np.arange(10.0)[:, None]
    use = np.ones(10, bool)
    use[4] = False
    xb, ub = block_mean(x, use, 3)
    np.testing.assert_allclose(xb[:, 0], [1.0, 4.0, 7.0])
    assert ub.tolist() == [True, False, True]


def test_maximum_likelihood_recovers_the_flexure_and_the_regression():
    """Residuals made of seed 000's flexure (seen by both sensors, the specific force along gravity
    plus some manoeuvre) and white noise, plus a regressor with a known coefficient: the likelihood
    finds sigma and beta, and the Kalman-whitened least squares finds the coefficient within its sigma."""
    rng = np.random.default_rng(7)
    n, dt = 3000, 0.1
    sig, beta = np.array([0.05, 0.08, 0.03]) * DEG, 1.5
    lam = _markov_flexure(rng, n, dt, sig, beta)
    t = np.arange(n) * dt
    ws = 0.05 * np.stack([np.sin(0.3 * t), np.cos(0.21 * t), np.sin(0.13 * t)], axis=1)
    fs = np.stack([0.5 * np.sin(0.1 * t), 0.3 * np.cos(0.17 * t), -9.8 + 0 * t], axis=1)
    nv = np.array([1e-5] * 3 + [2e-3] * 3) ** 2
    resid = np.concatenate([np.einsum("nij,nj->ni", skew(ws), lam[:, :3]) + lam[:, 3:],
                            np.einsum("nij,nj->ni", skew(fs), lam[:, :3])], axis=1)
    resid += rng.standard_normal((n, 6)) * np.sqrt(nv)
    reg = np.concatenate([np.gradient(ws, dt, axis=0), np.gradient(fs, dt, axis=0)], axis=1)
    b_true = 2e-3
    y = np.stack([resid + b_true * reg, reg], axis=2)
    use = np.ones(n, bool)
    model = fit_model(y, ws, fs, use, dt, 1)
    assert model is not None
    np.testing.assert_allclose(model.sigma_rad, sig, rtol=0.35)
    assert model.beta_1_s == pytest.approx(beta, rel=0.35)
    _, M, _ = whitened_normal(y, ws, fs, use, model)
    b_hat, sd = M[1, 0] / M[1, 1], 1.0 / np.sqrt(M[1, 1])
    assert abs(b_hat - b_true) < 3 * sd


def _ship_flexure(seed: int):
    from logtools import sim

    cfg = sim.scenario_config("ship", seed=seed, flexure=True, latency_s=-0.3121, drift_ppm=-40.0,
                              mount_rpy_deg=(120.0, 35.0, -80.0))
    return sim.simulate(cfg)


def test_kalman_whitening_beats_the_spectral_gls_on_flexure():
    """Ship with seed 000's flexure, 120 s: the fit whitened by the flexure model is kept (quality says
    so), is more accurate than the spectral GLS alone over seeds, and its sigma covers its error. (On the
    rates and specific forces: the slave's velocity is left out, whose matching would blur the comparison.)"""
    e_flex, e_spec, z = [], [], []
    for seed in range(5):
        p = _ship_flexure(seed)
        res = estimate(p.master, p.slave, compare=False, velocity=False)
        truth = p.truth.latency_at(res.t_mid_rel_s)
        assert res.quality["flexure_model"] is not None
        assert 0.01 < min(res.quality["flexure_model"]["sigma_deg"]) < 0.2  # the simulator's 0.05 deg
        e_flex.append(res.latency_s - truth)
        z.append(abs(res.latency_s - truth) / res.sigma_s)
        spec = estimate(p.master, p.slave, compare=False, velocity=False, config=NO_KALMAN)
        assert spec.quality["flexure_model"] is None
        e_spec.append(spec.latency_s - p.truth.latency_at(spec.t_mid_rel_s))
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert rms(e_flex) < 0.7 * rms(e_spec)
    assert rms(e_flex) < 0.6e-3
    assert max(z) < 3.0


def test_without_flexure_the_kalman_stage_is_not_run():
    """A rigid mount: the spectral fit is already below ACCEL_MIN_SIGMA_S, nothing more is done."""
    from logtools import sim

    p = sim.simulate(sim.scenario_config("ship", seed=3, latency_s=0.021, mount_rpy_deg=(10.0, 80.0, -30.0)))
    res = estimate(p.master, p.slave, compare=False)
    assert res.quality["flexure_model"] is None
    assert abs(res.latency_s - p.truth.latency_at(res.t_mid_rel_s)) < 1e-4


def test_disagreeing_rate_models_both_go_to_the_windows_and_the_sigma_covers_them():
    """Where the Kalman (flexure) fit lands far from the spectral GLS (> FLEX_AGREE_SIGMAS), one of the
    two models is wrong: both are scored by their windows, and the sigma of the one kept covers the
    other (an aircraft with a lever arm, 300 s, once kept the spectral fit at 0.3 ms, 5.5 ms off, and
    dropped the Kalman fit that was 0.5 ms off). Here the Kalman fit is pushed 12 sigmas away."""
    p = _ship_flexure(1)
    base = estimate(p.master, p.slave, compare=False, velocity=False)
    assert base.quality["rate_models_gap_s"] == 0.0
    orig = refine_flex
    push = {}

    def pushed(*a, **k):
        f = orig(*a, **k)
        if k.get("model") is None and f.ok:  # the whole-overlap fit (window refits pass the model)
            push["gap"] = 12.0 * max(f.sigma_latency_s, k["h0"])  # h0: the spectral fit's sigma
        return replace(f, latency_s=f.latency_s + push.get("gap", 0.0)) if f.ok else f

    cfg = replace(LatencyConfig(), stages=Stages(refine_flex=pushed))
    res = estimate(p.master, p.slave, compare=False, velocity=False, config=cfg)
    gap = res.quality["rate_models_gap_s"]
    assert gap > 0.5 * push["gap"]
    assert res.sigma_s >= cfg.uncertainty.flex_gap_cover * gap
    assert any("disagree" in w for w in res.quality["warnings"])


def test_short_flexure_records_reach_the_kalman_stage():
    """30 s of a flexing ship's IMUs: the flexure model's likelihood asked for 4 blocks per unknown and
    such records stayed with the spectral fit (over 4 seeds 2.8 ms RMS, one 5.4 ms off). With 2 (each
    block has 6 rows) the Kalman stage runs; over 40 short (25-45 s) flexure runs of all scenarios the RMS
    went from 1.94 to 0.98 ms and the 2-sigma coverage from 92.5 to 97.5 %."""
    from logtools import sim

    errs, zs = [], []
    for seed in range(4):
        p = sim.simulate(sim.scenario_config("ship", seed=seed, flexure=True, duration_s=30.0, latency_s=0.2371,
                                             drift_ppm=30.0, mount_rpy_deg=(40.0, -60.0, 150.0), slave_nav=False))
        res = estimate(p.master, p.slave, compare=False)
        assert res.quality["flexure_model"] is not None
        e = res.latency_s - p.truth.latency_at(res.t_mid_rel_s)
        errs.append(e)
        zs.append(abs(e) / res.sigma_s)
    assert float(np.sqrt(np.mean(np.square(errs)))) < 1e-3
    assert max(zs) < 3.5

