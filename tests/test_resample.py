"""logtools.resample: uniform grids from irregular streams, gaps/duplicates reported, no extrapolation."""
from __future__ import annotations

import numpy as np
import pytest

from logtools.resample import (UniformSeries, clean_samples, interpolant, lowpass, median_rate_hz,
                               to_uniform)


def _sig(t: np.ndarray) -> np.ndarray:
    return np.stack([np.sin(2 * np.pi * 0.7 * t), np.cos(2 * np.pi * 1.3 * t + 0.2), 0.3 * np.sin(0.5 * t)], axis=1)


def test_clean_samples_reports_duplicates_nans_and_unsorted():
    t = np.array([0.0, 0.01, 0.01, 0.03, 0.02, np.nan, 0.05, 0.06])
    x = np.arange(len(t), dtype=float)[:, None] * np.ones((1, 3))
    x[6, 1] = np.nan
    cs = clean_samples(t, x, name="gyro")
    assert np.all(np.diff(cs.t_s) > 0)
    assert cs.n_duplicates == 1 and cs.n_nonfinite == 2 and cs.n_unsorted == 1
    np.testing.assert_allclose(cs.values[1], [1.5, 1.5, 1.5])  # duplicated stamp -> mean of the two rows
    text = " ".join(cs.warnings)
    assert "duplicated" in text and "NaN" in text and "backwards" in text


def test_to_uniform_jittered_stamps_is_accurate():
    rng = np.random.default_rng(1)
    t = np.arange(0, 20, 0.01) + rng.uniform(-0.003, 0.003, 2000)
    u = to_uniform(t, _sig(t), name="imu")
    assert abs(u.rate_hz - 100.0) < 1.0
    ok = u.valid
    err = np.abs(u.values[ok] - _sig(u.t_s[ok]))[20:-20]
    assert err.max() < 1e-4
    assert any("jitter" in w for w in u.warnings)


def test_gaps_are_masked_not_interpolated_and_reported():
    t = np.arange(0, 10, 0.005)
    keep = (t < 4.0) | (t > 4.5)  # 0.5 s gap = 100 samples
    u = to_uniform(t[keep], _sig(t[keep]), name="slave gyro")
    tg = u.t_s
    tk = t[keep]
    g0, g1 = tk[tk < 4.2].max(), tk[tk > 4.2].min()  # the samples bounding the gap
    inside = (tg > g0 + 1e-9) & (tg < g1 - 1e-9)
    assert inside.sum() > 90 and not u.valid[inside].any()
    assert u.valid[~inside].all()
    assert any("gap" in w for w in u.warnings)
    assert len(u.gaps_s) == 1 and u.gaps_s[0][0] == pytest.approx(3.995, abs=0.006)
    # short dropouts (2 samples) are interpolated
    keep2 = np.ones(len(t), bool)
    keep2[[500, 501]] = False
    u2 = to_uniform(t[keep2], _sig(t[keep2]))
    assert u2.valid.all()


def test_interpolant_never_extrapolates_and_is_accurate_subsample():
    dt = 0.01
    t = (5 + np.arange(1000)) * dt
    s = UniformSeries(5, dt, _sig(t), np.ones(1000, bool))
    itp = interpolant(s)
    q = np.linspace(t[0] - 0.5, t[-1] + 0.5, 4001)
    v, ok = itp(q)
    assert not ok[q < t[0] - 1e-9].any() and not ok[q > t[-1] + 1e-9].any()
    assert np.isnan(v[~ok]).all()
    mid = ok & (q > t[0] + 0.3) & (q < t[-1] - 0.3)
    assert np.abs(v[mid] - _sig(q[mid])).max() < 5e-6
    d, _ = itp(q[mid], 1)
    dtrue = (_sig(q[mid] + 1e-6) - _sig(q[mid] - 1e-6)) / 2e-6
    assert np.abs(d - dtrue).max() < 1e-3


def test_interpolant_masks_around_invalid_samples():
    dt = 0.01
    valid = np.ones(200, bool)
    valid[100:110] = False
    t = np.arange(200) * dt
    itp = interpolant(UniformSeries(0, dt, _sig(t), valid))
    _, ok = itp(np.array([0.5, 1.0, 1.05, 1.095, 1.5]))
    assert ok.tolist() == [True, False, False, False, True]


def test_lowpass_is_zero_phase():
    dt = 0.005
    t = np.arange(4000) * dt
    x = np.sin(2 * np.pi * 0.5 * t)[:, None]
    s = UniformSeries(0, dt, x + 0.1 * np.sin(2 * np.pi * 60 * t)[:, None], np.ones(len(t), bool))
    lp = lowpass(s, 5.0)
    mid = slice(500, -500)
    # a pure delay would show as an error ~ 2 pi f tau; zero-phase leaves only tiny amplitude change
    assert np.abs(lp.values[mid, 0] - x[mid, 0]).max() < 2e-3
    assert not lp.valid[0] and not lp.valid[-1]


def test_median_rate_robust_to_duplicates_and_gaps():
    t = np.concatenate([np.arange(0, 5, 0.02), np.arange(6, 8, 0.02)])
    t = np.sort(np.concatenate([t, t[:10]]))
    assert median_rate_hz(t) == pytest.approx(50.0, rel=1e-6)


def test_a_grid_far_longer_than_its_samples_is_refused_not_allocated():
    """2000 samples at 200 Hz with one of them 12 days away: the grid would hold 2e8 points (1.6 GB a
    column); it is refused with a reason instead."""
    t = np.arange(2000) * 0.005
    t[-1] = 1.04e6
    with pytest.raises(ValueError, match="spread over 1040000 s"):
        to_uniform(t, _sig(t), name="slave gyro")
    # a long pause between two real runs of data is still resampled (masked as a gap)
    t2 = np.concatenate([np.arange(2000) * 0.005, 300.0 + np.arange(2000) * 0.005])
    u = to_uniform(t2, _sig(t2))
    assert not u.valid.all() and u.gaps_s


def test_the_sample_clock_is_the_stamps_mean_interval_and_phase():
    """Stamps quantised to the microsecond of a 50 Hz clock running 75 ppm fast, with dropped samples:
    the interval is the clock's (the median step is the quantised 20 ms), the phase its offset."""
    from logtools.resample import sample_clock

    dt_true, phase = 0.02 * (1 - 75e-6), 0.0137
    k = np.arange(9000)
    k = k[(k % 1000) != 7]  # single samples dropped
    k = np.concatenate([k[:5000], k[5100:]])  # and a gap
    t = np.round((phase + k * dt_true) * 1e6) / 1e6
    dt, ph = sample_clock(t)
    assert abs(dt - dt_true) < 1e-10
    assert abs((ph - phase + dt / 2) % dt - dt / 2) < 2e-6
    # stamps jittered by 5 % of a step: the interval within 1e-5 of itself (larger jitter leaves the
    # samples at offsets from any uniform grid anyway: the band-limited grid then reads them as to_uniform)
    rng = np.random.default_rng(1)
    tj = np.sort(phase + k * dt_true + rng.normal(0.0, 0.05 * dt_true, len(k)))
    assert abs(sample_clock(tj)[0] / dt_true - 1) < 1e-5


@pytest.mark.parametrize("phase_frac", [0.1, 0.35, 0.6, 0.85])
def test_a_slow_stream_is_gridded_without_a_phase_error(phase_frac):
    """A 15 Hz tone sampled at 50 Hz with its samples at a fraction of the grid's interval: the cubic spline
    of to_uniform delays it by up to 0.33 ms depending on that fraction; the band-limited grid holds it
    within 2 microseconds, with the gaps masked as to_uniform masks them."""
    from logtools.resample import to_uniform_band_limited

    dt = 0.02
    t = (phase_frac + np.arange(3000)) * dt
    keep = (t < 20.0) | (t > 20.5)
    t = t[keep]
    f = 15.0
    x = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)])

    def delay(s: UniformSeries) -> float:
        tg, v, ok = s.t_s, s.values, s.valid.copy()
        ok &= (tg > 2.0) & (tg < tg[-1] - 2.0) & ((tg < 19.0) | (tg > 21.5))
        # the tone's phase on the grid against the truth: a delay (s)
        z = (v[ok, 1] + 1j * v[ok, 0]) * np.exp(-2j * np.pi * f * tg[ok])
        return float(-np.angle(np.mean(z)) / (2 * np.pi * f))

    plain = to_uniform(t, x)
    bl = to_uniform_band_limited(t, x, 4)
    assert bl.dt_s == pytest.approx(dt / 4)
    tg = bl.t_s
    assert not bl.valid[(tg > 20.0 + 4 * dt) & (tg < 20.5 - 4 * dt)].any()
    assert bl.valid[(tg > 1.0) & (tg < 19.0)].all()
    assert abs(delay(bl)) < 2e-6
    if abs(phase_frac - 0.5) > 0.2:  # (at half an interval the spline's error is symmetric: none)
        assert abs(delay(plain)) > 5e-5
