"""Latency compensation: the slave on the master's clock (restamp, interp, shift, poly2, split)."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from logtools.compensate import (
    METHODS, _poly2_group, compensate, split_latency, split_residual_s, true_time_s,
)
from logtools.conventions import angle_between_quats, quat_from_rotvec
from logtools.errors import AnalysisError, InputError
from logtools.inslog import InsLog, LogMeta
from logtools.results import LatencyResult

T0_NS = 1_600_000_000_000_000_000
W_AXIS = np.array([0.3, -0.5, 0.8])  # constant angular rate (rad/s): attitude exp(W t), exact for slerp


def f_rate(t):  # a smooth angular rate, analytic
    t = np.asarray(t, float)[:, None]
    return np.hstack([0.2 * np.sin(2 * np.pi * 0.3 * t), 0.1 * np.cos(2 * np.pi * 0.7 * t + 0.4),
                      0.05 * np.sin(2 * np.pi * 1.1 * t) + 0.01 * t])


def f_quad(t):  # a quadratic signal (S003 eqs 1-2 are exact for it)
    t = np.asarray(t, float)[:, None]
    return np.hstack([1.0 + 0.5 * t - 0.02 * t ** 2, -2.0 + 0.01 * t ** 2, 0.3 * t])


def f_quat(t):
    return quat_from_rotvec(np.asarray(t, float)[:, None] * W_AXIS * 0.1)


def make_pair(lat_s, drift_ppm=0.0, *, rate_m=100.0, rate_s=250.0, dur=30.0, signal=f_rate, offset_s=0.789,
              jitter_s=0.0):
    tm = np.arange(0.0, dur, 1.0 / rate_m)
    stamp = np.arange(0.0, dur, 1.0 / rate_s) + 0.41 / rate_s
    if jitter_s:
        stamp = stamp + np.random.default_rng(0).uniform(-jitter_s, jitter_s, len(stamp))
    d = drift_ppm * 1e-6
    t_mid = dur / 2
    tau = (stamp - lat_s + d * t_mid) / (1 + d)
    m = InsLog.from_arrays(LogMeta("m.csv", "csv", t0_ns=T0_NS), tm, signal(tm), signal(tm), tm, f_quat(tm),
                           signal(tm))
    s = InsLog.from_arrays(LogMeta("s.csv", "csv", t0_ns=T0_NS + int(offset_s * 1e9),
                                   warnings=("existing",)),
                           stamp - offset_s, signal(tau), signal(tau), stamp - offset_s, f_quat(tau), signal(tau))
    lat = LatencyResult(latency_s=lat_s, sigma_s=1e-5, drift_ppm=drift_ppm, method="truth",
                        window_s=(0.0, dur), t_mid_rel_s=t_mid)
    return m, s, lat


@pytest.mark.parametrize("lat_s,drift_ppm", [(0.0573, 80.0), (-0.4321, -100.0), (1.7, 0.0)])
def test_restamp_recovers_the_original_exactly(lat_s, drift_ppm):
    m, s, lat = make_pair(lat_s, drift_ppm)
    c = compensate(s, lat, m)  # default: restamp
    assert c.meta.t0_ns == m.meta.t0_ns
    assert len(c.imu) == len(s.imu) and len(c.nav) == len(s.nav)  # no sample lost
    t = c.t_imu_s()
    assert np.max(np.abs(c.gyro_rad_s() - f_rate(t))) < 1e-10
    tq, q = c.quat_wxyz()
    assert np.max(angle_between_quats(q, f_quat(tq))) < 1e-10
    assert c.meta.warnings[0] == "existing"
    assert "restamp" in c.meta.warnings[-1] and f"{drift_ppm:+.3f} ppm" in c.meta.warnings[-1]


def test_true_time_inverts_latency_at():
    _, _, lat = make_pair(0.3, 90.0)
    tau = np.linspace(-5, 40, 7)
    stamps = tau + lat.latency_at(tau)
    assert np.allclose(true_time_s(stamps, lat), tau, atol=1e-12)


def test_interp_onto_master_instants_linear_precision():
    m, s, lat = make_pair(0.0573, 60.0)
    c = compensate(s, lat, m, method="interp")
    t = c.t_imu_s()
    assert np.all(np.isin(t, m.t_imu_s()))  # master instants
    assert t[0] >= 0.0 and len(t) > 0.9 * len(m.imu)
    # linear interpolation error <= h^2/8 max|f''| (h = 4 ms, max|f''| = 0.05 (2 pi 1.1)^2 < 2.4)
    assert np.max(np.abs(c.gyro_rad_s() - f_rate(t))) < (0.004 ** 2) / 8 * 2.4 * 1.01
    assert c.meta.channels == {} or all(v.count > 0 for v in c.meta.channels.values())


def test_interp_slerp_is_exact_for_a_constant_rate_rotation():
    m, s, lat = make_pair(0.0211, 30.0, rate_s=50.0)
    c = compensate(s, lat, m, method="interp")
    tq, q = c.quat_wxyz()
    assert np.all(np.isin(tq, m.t_nav_s()))
    assert np.max(angle_between_quats(q, f_quat(tq))) < 1e-9


def test_interp_does_not_bridge_gaps():
    m, s, lat = make_pair(0.05)
    imu = pd.concat([s.between(-10.0, 10.0).imu, s.between(12.0, 99.0).imu])  # 2 s gap (slave stamps)
    c = compensate(InsLog(imu=imu, nav=s.nav, meta=s.meta), lat, m, method="interp")
    t = c.t_imu_s()
    gap = (10.0 + 0.789 - 0.05, 12.0 + 0.789 - 0.05)  # on the master's clock
    assert not np.any((t > gap[0] + 0.005) & (t < gap[1] - 0.005))
    assert np.any(t < gap[0]) and np.any(t > gap[1])


def test_poly2_exact_for_quadratic_signals_and_equal_to_eq2():
    m, s, lat = make_pair(0.0377, 0.0, signal=f_quad)
    c = compensate(s, lat, m, method="poly2")
    t = c.t_imu_s()
    assert np.max(np.abs(c.gyro_rad_s() - f_quad(t))) < 1e-9
    _, v = c.vel_ned_m_s()
    assert np.max(np.abs(v - f_quad(c.t_nav_s()))) < 1e-9
    # eq 2 written out on a uniform grid (T = 4 ms) for one instant
    T, n_t = 0.004, 0.01234
    x = np.array([np.sin(5 * k * T) for k in range(3)])  # X[(n-2)T], X[(n-1)T], X(nT)
    a0, a1, a2 = x[2], (3 * x[2] - 4 * x[1] + x[0]) / (2 * T), (x[2] - 2 * x[1] + x[0]) / (2 * T ** 2)
    tt = np.array([0.0, T, 2 * T])
    val, ok = _poly2_group(tt, x[:, None], np.array([2 * T + n_t * T]), False)
    assert ok[0] and val[0, 0] == pytest.approx(a0 + a1 * n_t * T + a2 * (n_t * T) ** 2, abs=1e-12)


def test_poly2_attitude_extrapolation():
    m, s, lat = make_pair(0.0377, 20.0, rate_s=50.0)
    c = compensate(s, lat, m, method="poly2")
    tq, q = c.quat_wxyz()
    assert len(tq) > 0.9 * len(m.nav)
    assert np.max(angle_between_quats(q, f_quat(tq))) < 1e-9  # constant-rate rotation: exact


def test_poly2_error_scales_with_the_cube_of_the_step():
    errs = []
    for rate in (100.0, 200.0):
        m, s, lat = make_pair(0.0377, 0.0, rate_s=rate)
        c = compensate(s, lat, m, method="poly2")
        errs.append(np.max(np.abs(c.gyro_rad_s() - f_rate(c.t_imu_s()))))
    assert 4.0 < errs[0] / errs[1] < 12.0  # ~8 for a third-order error


@pytest.mark.parametrize("lat_s", [0.0573, -0.0312])
def test_shift_integer_samples(lat_s):
    m, s, lat = make_pair(lat_s, 50.0)
    c = compensate(s, lat, m, method="shift")
    dt = 1.0 / 250.0
    k = int(round(lat_s / dt))
    assert f"k={k} samples" in c.meta.warnings[-1]
    # the remainder L - k dt is still in the data: values at stamp t are the truth at t - remainder
    rem = lat_s - k * dt
    assert abs(rem) <= dt / 2 + 1e-12
    t = c.t_imu_s()
    assert np.max(np.abs(c.gyro_rad_s() - f_rate(t - rem))) < 1e-9
    assert len(c.imu) == len(s.imu)


def test_shift_exact_when_latency_is_whole_samples():
    m, s, lat = make_pair(0.048, 0.0)  # 12 samples of 4 ms
    c = compensate(s, lat, m, method="shift")
    assert np.max(np.abs(c.gyro_rad_s() - f_rate(c.t_imu_s()))) < 1e-9


@pytest.mark.parametrize("lat_s", [0.1, 0.0573, -0.0312])
def test_split_bookkeeping(lat_s):
    m, s, lat = make_pair(lat_s, -40.0)
    c = compensate(s, lat, m, method="split")
    dt = 1.0 / 250.0
    sp = split_latency(lat_s, dt)
    assert 0.0 <= sp.residual_s < dt and sp.k_samples * dt + sp.residual_s == pytest.approx(lat_s)
    assert split_residual_s(c) == pytest.approx(sp.residual_s, abs=1e-9)
    assert f"k={sp.k_samples} samples" in c.meta.warnings[-1]
    # the output still lags the master by exactly the residual (DESIGN.md sign): for the delay state
    assert np.max(np.abs(c.gyro_rad_s() - f_rate(c.t_imu_s() - sp.residual_s))) < 1e-9
    tq, q = c.quat_wxyz()
    assert np.max(angle_between_quats(q, f_quat(tq - sp.residual_s))) < 1e-9
    assert split_residual_s(compensate(s, lat, m, method="shift")) is None


def test_with_the_simulator_restamp_matches_truth():
    sim = pytest.importorskip("logtools.sim")
    p = sim.simulate(sim.scenario_config("vehicle", latency_s=0.2345, drift_ppm=70.0, duration_s=30.0,
                                         slave_imu_rate_hz=333.0, seed=2))
    tr = p.truth
    lat = LatencyResult(latency_s=tr.latency_at(tr.t_mid_rel_s), sigma_s=1e-5, drift_ppm=tr.drift_ppm,
                        method="truth", window_s=(0.0, 30.0), t_mid_rel_s=tr.t_mid_rel_s)
    c = compensate(p.slave, lat, p.master)
    abs_ns = p.slave.meta.t0_ns + np.rint(p.slave.t_imu_s() * 1e9).astype(np.int64)
    assert np.max(np.abs(c.t_imu_s() - tr.true_time_of_slave_stamp(abs_ns))) < 2e-9
    for meth in METHODS:
        out = compensate(p.slave, lat, p.master, method=meth)
        assert out.meta.t0_ns == p.master.meta.t0_ns and len(out.imu) > 0 and out.has_quat


def test_bad_inputs():
    m, s, lat = make_pair(0.05)
    with pytest.raises(InputError, match="compensation method"):
        compensate(s, lat, m, method="magic")
    nan_lat = LatencyResult(latency_s=float("nan"), sigma_s=0.0, drift_ppm=0.0, method="x", window_s=(0, 1))
    with pytest.raises(AnalysisError, match="not a finite estimate"):
        compensate(s, nan_lat, m)
    far = LatencyResult(latency_s=500.0, sigma_s=0.0, drift_ppm=0.0, method="x", window_s=(0, 1))
    with pytest.raises(AnalysisError, match="no master instant"):
        compensate(s, far, m, method="interp")


def test_the_channels_stamps_are_the_grouped_rows_stamps_without_their_values():
    """``_group_stamps`` (what the channels' rates and counts are refreshed from) gives ``_group_rows``'s
    stamps to the bit: rows with a column unset left out, unsorted stamps sorted, repeated ones once;
    empty where a column is missing or the frame is empty."""
    import pandas as pd

    from logtools.compensate import _group_rows, _group_stamps
    from logtools.inslog import Columns

    rng = np.random.default_rng(3)
    t = rng.random(2000) * 100.0
    t[5] = t[7]
    v = rng.standard_normal((2000, 3))
    v[3, 1] = v[11, 0] = np.nan
    for idx in (t, np.sort(t)):
        df = Columns.from_frame(pd.DataFrame(v, columns=["a", "b", "c"], index=pd.Index(idx)))
        for cols in (("a", "b", "c"), ("c",), ("a", "x")):
            assert np.array_equal(_group_stamps(df, cols), _group_rows(df, cols)[0])
    assert len(_group_stamps(Columns.from_frame(pd.DataFrame({"a": []})), ("a",))) == 0
