"""Isolated spikes (``logtools.latency.spikes``): a corrupt IMU sample in one unit is replaced for the latency
and said; a real impact, felt by both units, is left alone; real logs' samples are never touched."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from logtools.inslog import InsLog
from logtools.latency import LatencyConfig, estimate
from logtools.latency import spikes
from test_latency import make_pair, random_rotation

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
CFG = LatencyConfig()
OFF = replace(CFG, spikes=replace(CFG.spikes, enabled=False))


def _with_gyro(log: InsLog, gyro: np.ndarray) -> InsLog:
    return InsLog.from_arrays(log.meta, log.t_imu_s(), gyro)


def _pair(seed: int):
    rng = np.random.default_rng(seed)
    return make_pair(rng, R=random_rotation(rng), f_m=100.0, f_s=200.0, drift_ppm=20.0, dur_s=90.0)


def _spike_warnings(res) -> list[str]:
    return [w for w in res.quality["warnings"] if "local sigmas" in w]


@pytest.mark.parametrize("seed", [1, 3])
def test_a_corrupt_slave_gyro_sample_is_replaced_and_said(seed):
    master, slave = _pair(seed)
    clean = estimate(master, slave, compare=False)
    g = slave.gyro_rad_s().copy()
    i = len(g) // 3
    g[i, 1] += 0.5  # one sample 0.5 rad/s off: a flipped exponent bit of a float32 does as much or more
    bad = _with_gyro(slave, g)
    res = estimate(master, bad, compare=False)
    assert abs(res.latency_s - clean.latency_s) < 0.1 * clean.sigma_s
    assert abs(res.drift_ppm - clean.drift_ppm) < 0.1
    assert res.sigma_s < 1.1 * clean.sigma_s
    (w,) = _spike_warnings(res)
    assert w.startswith("slave: 1 gyro sample(s)") and f"{bad.t_imu_s()[i] + bad.t0_s:.3f} s" in w
    # without the stage the one sample costs the fit (the sigma at least 3x, here 3.9x and 35x)
    raw = estimate(master, bad, compare=False, config=OFF)
    assert raw.sigma_s > 3.0 * clean.sigma_s
    assert not _spike_warnings(raw)
    assert bad.gyro_rad_s()[i, 1] == g[i, 1]  # the caller's log is not changed


def test_a_corrupt_master_accelerometer_sample_is_replaced_too():
    master, slave = _pair(2)
    n_m, n_s = master.n_imu, slave.n_imu
    rng = np.random.default_rng(7)
    acc_m = np.array([0.0, 0.0, -9.81]) + rng.normal(0, 0.02, (n_m, 3))
    acc_s = np.array([0.0, 0.0, -9.81]) + rng.normal(0, 0.02, (n_s, 3))
    acc_m[n_m // 2, 0] = 40.0
    m = InsLog.from_arrays(master.meta, master.t_imu_s(), master.gyro_rad_s(), acc_m)
    s = InsLog.from_arrays(slave.meta, slave.t_imu_s(), slave.gyro_rad_s(), acc_s)
    found = spikes.find(m, s.rebased(m.meta.t0_ns), 0.0373, CFG.spikes)
    assert list(found) == [("master", spikes.ACCEL)]
    assert found[("master", spikes.ACCEL)].rows.tolist() == [n_m // 2]
    fixed = spikes.replaced_rows(m, {spikes.ACCEL: found[("master", spikes.ACCEL)]})
    assert fixed.accel_m_s2()[n_m // 2, 0] == pytest.approx(-0.0, abs=0.1)
    assert m.accel_m_s2()[n_m // 2, 0] == 40.0  # the original log is not changed


def test_a_real_impact_felt_by_both_units_is_left_alone():
    master, slave = _pair(4)
    gm, gs = master.gyro_rad_s().copy(), slave.gyro_rad_s().copy()
    t_true = 31.0  # an impact at this instant of the master's clock: the slave stamps it 37.3 ms (+ drift) later
    im = int(np.argmin(np.abs(master.t_imu_s() - t_true)))
    s_rel = slave.rebased(master.meta.t0_ns).t_imu_s()
    i_s = int(np.argmin(np.abs(s_rel - (t_true + 0.0373 + 20e-6 * (t_true - 45.0)))))
    gm[im] += [0.6, -0.3, 0.2]
    gs[i_s] += [0.5, 0.4, -0.2]  # (another mounting: another direction, the same instant)
    m, s = _with_gyro(master, gm), _with_gyro(slave, gs)
    assert spikes.find(m, s.rebased(m.meta.t0_ns), 0.0373, CFG.spikes) == {}
    assert not _spike_warnings(estimate(m, s, compare=False))


def test_quantised_still_counts_and_smooth_motion_give_no_spike():
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 60.0, 0.01)
    counts = np.round(rng.normal(0, 0.4, (len(t), 3))) * 0.001  # mostly 0, a count here and there
    tr = spikes.triad(t, counts.T)
    assert len(spikes.isolated(tr, CFG.spikes).rows) == 0
    smooth = np.column_stack([0.5 * np.sin(2 * np.pi * f * t) for f in (0.2, 0.4, 0.7)])
    smooth += rng.normal(0, 0.003, smooth.shape)
    smooth[:, 0] += np.where(t > 30.0, 0.5, 0.0)  # a step (a rate change within a sample): two samples, no spike
    tr = spikes.triad(t, smooth.T)
    assert len(spikes.isolated(tr, CFG.spikes).rows) == 0
    smooth[1234, 2] += 0.5
    tr = spikes.triad(t, smooth.T)
    assert spikes.isolated(tr, CFG.spikes).rows.tolist() == [1234]


@pytest.mark.parametrize("log,ms,ss,lag_s", [
    ("arduplane_elevator.BIN", "imu=IMU", "imu=IMU2", -1.2e-3),  # strong pitch excitation: features up to 31 sigma
    ("arducopter_log0036.bin", "imu=IMU", "imu=IMU2", 2.5e-3),  # the mechanical failure's impact in both IMUs
    ("arducopter_2014-10-18_20-04-24.bin", "imu=IMU", "imu=IMU2", 2.5e-3),
    ("sitl_vtol.tlog", "imu=RAW_IMU", "imu=SCALED_IMU2", 0.0),  # integer counts
])
def test_real_logs_have_no_isolated_spike(log, ms, ss, lag_s):
    if not (REALDATA / log).exists():
        pytest.skip("../shared/realdata absent")
    from parsers import load

    m, s = load(f"{REALDATA / log}::{ms}"), load(f"{REALDATA / log}::{ss}")
    assert spikes.find(m, s.rebased(m.meta.t0_ns), lag_s, CFG.spikes) == {}


def test_ngimu_units_one_sample_impacts_are_shared():
    base = REALDATA / "ngimu_session"
    if not base.exists():
        pytest.skip("../shared/realdata absent")
    from parsers import load

    blue = load(str(base / "blue"))
    for other in ("green", "red"):
        o = load(str(base / other))
        assert spikes.find(blue, o.rebased(blue.meta.t0_ns), 0.0, CFG.spikes) == {}


def test_the_alignment_reads_the_mended_logs_and_the_outputs_the_logs_own_values():
    """analyze: the samples the latency replaced are replaced for the alignment and the IMU-to-IMU fit too (the
    same results as the undamaged log's); the compensated slave the exports and plots read keeps its value."""
    from logtools import sim
    from pipelines.analyze import AnalyzeOptions, compute

    p = sim.simulate(sim.scenario_config("aircraft", duration_s=60.0, seed=11, latency_s=0.25, drift_ppm=15.0))
    g = p.slave.gyro_rad_s().copy()
    i = len(g) // 2
    g[i, 2] += 0.6
    imu = dict(p.slave.imu_columns.data)
    imu["gyro_z_rad_s"] = g[:, 2]
    from logtools.inslog import Columns

    bad = p.slave.with_streams(imu=Columns(p.slave.t_imu_s(), imu))
    opts = AnalyzeOptions(compare=False)
    ref, an = compute(p.master, p.slave, opts), compute(p.master, bad, opts)
    (rec,) = an.latency.quality["replaced_samples"]
    assert (rec["unit"], rec["sensor"], rec["row"]) == ("slave", "gyro", i) and rec["local_sigmas"] > 50
    assert "replaced_samples" not in ref.latency.quality
    assert abs(an.latency.latency_s - ref.latency.latency_s) < 0.05 * ref.latency.sigma_s
    a, b = ref.alignment["compensated"], an.alignment["compensated"]
    assert np.allclose(a.mounting_rpy_deg, b.mounting_rpy_deg, atol=0.05 * min(a.mounting_sigma_deg))
    assert np.allclose(a.mounting_sigma_deg, b.mounting_sigma_deg, rtol=0.02)
    # the outputs' compensated slave: the log's own value at that row
    assert an.slave_comp.gyro_rad_s()[i, 2] == pytest.approx(g[i, 2])


def test_a_corrupt_master_velocity_or_attitude_sample_leaves_the_alignment_as_it_was():
    """One master velocity sample 3 m/s off (a flipped mantissa bit: within the parsers' 50 m/s limit), or one
    quaternion component 0.05 off (5.7 deg out and back), put the compensated mounting's sigma at 3.9' against
    0.028' (the board's states taken on to explain the innovations; the attitude's two jumps taken for two EKF
    resets). The velocity sample is replaced by its neighbours' mean for the alignment, with a warning; the
    attitude sample is one invalid sample (an update skipped), no reset. The undamaged pair's result is back."""
    from logtools import sim
    from logtools.inslog import QUAT, VEL, Columns
    from pipelines.analyze import AnalyzeOptions, compute

    p = sim.simulate(sim.scenario_config("aircraft", duration_s=60.0, seed=11, latency_s=0.25, drift_ppm=15.0))
    m = p.master
    i = len(m.t_nav_s()) // 2
    opts = AnalyzeOptions(compare=False)
    ref = compute(m, p.slave, opts)
    a = ref.alignment["compensated"]
    assert not [x for x in ref.extra.get("warnings", []) if "velocity sample" in x["text"]]
    for cols, delta in ((VEL, 3.0), (QUAT, 0.05)):
        nav = dict(m.nav_columns.data)
        x = np.array(nav[cols[1]], dtype=float)
        x[i] += delta
        nav[cols[1]] = x
        an = compute(m.with_streams(nav=Columns(m.t_nav_s(), nav)), p.slave, opts)
        b = an.alignment["compensated"]
        assert np.allclose(a.mounting_sigma_deg, b.mounting_sigma_deg, rtol=0.05), cols
        assert np.allclose(a.mounting_rpy_deg, b.mounting_rpy_deg, atol=0.1 * min(a.mounting_sigma_deg)), cols
        said = [x["text"] for x in an.extra["warnings"] if "velocity sample" in x["text"]]
        if cols == VEL:
            assert len(said) == 1 and said[0].startswith("master: 1 velocity sample(s)") and "up to 3 m/s" in said[0]
            assert an.master.vel_ned_m_s()[1][i, 1] == pytest.approx(x[i])  # the outputs' master: its own value
        else:
            assert not said  # (the attitude is not mended: one update skipped, no reset)
            assert any(n.startswith("1 of") and "updates skipped" in n for n in b.notes), b.notes


def test_an_attitude_sample_off_both_ways_is_one_invalid_sample_not_two_resets():
    from logtools.conventions import quat_from_rotvec, quat_mul
    from logtools.navcheck import output_validity

    t = np.arange(0.0, 10.0, 0.02)
    yaw_rate = 0.3
    q = quat_from_rotvec(np.column_stack([np.zeros_like(t), np.zeros_like(t), yaw_rate * t]))
    rate = np.full(len(t) - 1, yaw_rate)
    valid, resets = output_validity(t, q, rate_at_mid=rate)
    assert valid.all() and len(resets) == 0
    off = q.copy()
    off[200] = quat_mul(q[200:201], quat_from_rotvec(np.array([[0.1, 0.0, 0.0]])))[0]  # 5.7 deg, one sample
    valid, resets = output_validity(t, off, rate_at_mid=rate)
    assert np.flatnonzero(~valid).tolist() == [200] and len(resets) == 0
    step = q.copy()
    step[200:] = quat_mul(q[200:], quat_from_rotvec(np.tile([[0.1, 0.0, 0.0]], (len(t) - 200, 1))))  # a reset
    valid, resets = output_validity(t, step, rate_at_mid=rate)
    assert len(resets) == 1 and abs(resets[0] - 0.5 * (t[199] + t[200])) < 1e-9


def test_without_a_gyro_an_attitude_sample_off_both_ways_is_one_invalid_sample_too():
    """A master that logs no gyro: the attitude's increments alone show the corrupt sample (their size changes
    into it and out of it: two resets around it, the sample itself kept). Where its neighbours' rotation over
    the two steps is what their own increments make it, it is one invalid sample; a step stays a reset."""
    from logtools.conventions import quat_from_rotvec, quat_mul
    from logtools.navcheck import output_validity

    t = np.arange(0.0, 10.0, 0.02)
    rv = np.column_stack([0.2 * np.sin(2 * np.pi * 0.5 * t), 0.1 * np.sin(2 * np.pi * 0.3 * t), 0.3 * t])
    q = quat_from_rotvec(rv)
    valid, resets = output_validity(t, q)
    assert valid.all() and len(resets) == 0
    for i in (2, 300, len(t) - 3):
        off = q.copy()
        off[i] = quat_mul(q[i:i + 1], quat_from_rotvec(np.array([[0.0, 0.1, 0.0]])))[0]  # 5.7 deg, one sample
        valid, resets = output_validity(t, off)
        assert np.flatnonzero(~valid).tolist() == [i] and len(resets) == 0, i
    step = q.copy()
    step[300:] = quat_mul(q[300:], quat_from_rotvec(np.tile([[0.1, 0.0, 0.0]], (len(t) - 300, 1))))
    valid, resets = output_validity(t, step)
    assert len(resets) >= 1 and np.min(np.abs(resets - 0.5 * (t[299] + t[300]))) < 1e-9


def test_a_corrupt_attitude_sample_of_a_master_without_gyro_leaves_the_alignment_as_it_was():
    """The pipeline with a navigation-only master (attitude, velocity, position; no IMU) and one quaternion
    component 0.05 off: one update skipped, no EKF reset, the undamaged pair's mounting and sigma (two resets
    before: sigma 0.0278' against 0.0276')."""
    from logtools import sim
    from logtools.inslog import QUAT, Columns, InsLog
    from pipelines.analyze import AnalyzeOptions, compute

    p = sim.simulate(sim.scenario_config("aircraft", duration_s=60.0, seed=11, latency_s=0.25, drift_ppm=15.0))
    t, q = p.master.quat_wxyz()
    m = InsLog.from_arrays(p.master.meta, t_nav_s=t, quat_wxyz=q, vel_ned_m_s=p.master.vel_ned_m_s()[1],
                           lat_lon_alt=p.master.lat_lon_alt()[1])
    assert not m.has_gyro
    opts = AnalyzeOptions(compare=False)
    a = compute(m, p.slave, opts).alignment["compensated"]
    nav = dict(m.nav_columns.data)
    x = np.array(nav[QUAT[1]], dtype=float)
    x[len(t) // 2] += 0.05
    nav[QUAT[1]] = x
    b = compute(m.with_streams(nav=Columns(m.t_nav_s(), nav)), p.slave, opts).alignment["compensated"]
    assert not [n for n in b.notes if "reset" in n]
    assert any(n.startswith("1 of") and "updates skipped" in n for n in b.notes), b.notes
    assert np.allclose(a.mounting_sigma_deg, b.mounting_sigma_deg, rtol=0.002)
    # (the latency moves within its sigma, the compensation with it: the mounting within half its sigma)
    assert np.allclose(a.mounting_rpy_deg, b.mounting_rpy_deg, atol=0.5 * min(a.mounting_sigma_deg))
