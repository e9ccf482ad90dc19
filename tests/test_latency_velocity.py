"""Velocity matching in the latency estimate (logtools.latency.velocity): recovery of a known delay with
a lever arm and a slave INS's tilt error, the fusion rule, shared nav streams, slaves without an IMU."""
from __future__ import annotations

import numpy as np
import pytest

from logtools import sim
from logtools.inslog import VEL, InsLog
from logtools.latency import estimate
from logtools.latency.velocity_pair import velocity_pair

G_NED = np.array([0.0, 0.0, 9.81])


def _pair(scenario="vehicle", **kw):
    base = dict(seed=3, latency_s=0.2345, drift_ppm=40.0, mount_rpy_deg=(20.0, -40.0, 100.0))
    base.update(kw)
    return sim.simulate(sim.scenario_config(scenario, **base))


def _with_velocity(log: InsLog, vel: np.ndarray) -> InsLog:
    nav = log.nav.copy()
    nav[list(VEL)] = vel
    return InsLog(imu=log.imu, nav=nav, meta=log.meta)


def _error_s(p, res):
    return res.latency_s - p.truth.latency_at(res.t_mid_rel_s)


def test_velocity_recovers_delay_with_lever_arm_and_slave_tilt_error():
    """Flexure on the aircraft: the rates alone cannot beat ~1.7 ms (the bound, benchmarks/latency_bound.py).
    The slave's velocity carries the delay untouched by the flexure: with a 3 m lever arm and the velocity
    of a slave INS whose attitude is off by (1, -0.5, 2) deg (exactly, not to first order: the linear tilt
    model alone had sigma 209 ms and the lever arm 2.7 m off), the delay comes out within 0.5 ms, the
    lever arm within 5 cm, and the result is within 3 sigma."""
    p = _pair("aircraft", flexure=True, lever_arm_m=(3.0, -1.5, 0.5))
    t, v = p.slave.vel_ned_m_s()
    k = len(t) // 2
    from logtools.conventions import dcm_from_rotvec

    R = dcm_from_rotvec(np.radians([1.0, -0.5, 2.0]))
    # an INS whose attitude is off by R integrates R C f: its velocity is R (v - g t) + g t (+ a constant),
    # to first order v + phi x (v - g t), phi R's rotation vector
    gt = G_NED * (t - t[k])[:, None]
    slave = _with_velocity(p.slave, (v - gt) @ R.T + gt + np.array([0.3, -0.2, 0.05]))
    res = estimate(p.master, slave, compare=False)
    vq = res.quality["velocity_fit"]
    assert vq is not None and vq["fused"] and not res.quality["velocity_disagrees"]
    e = _error_s(p, res)
    assert abs(e) < 0.5e-3 and abs(e) < 3 * res.sigma_s, (e, res.sigma_s)
    assert np.allclose(vq["lever_arm_m"], (3.0, -1.5, 0.5), atol=0.05)
    # the same without the velocities: the rate fit alone, over twice less precise (2.7x before the velocity
    # fit's residual spectrum was corrected for its fitted columns, which raised its sigma 0.21 -> 0.28 ms)
    res_r = estimate(p.master, slave, compare=False, velocity=False)
    assert res_r.quality["velocity_fit"] is None
    assert res_r.sigma_s > 2.0 * res.sigma_s


def test_velocity_moves_with_a_known_shift():
    """Shifting the slave's stamps (IMU and nav) by +37.3 ms moves the estimate by 37.3 ms."""
    p = _pair("vehicle", flexure=True)
    r0 = estimate(p.master, p.slave, compare=False)
    shifted = p.slave.with_meta(t0_ns=p.slave.meta.t0_ns + 37_300_000)
    r1 = estimate(p.master, shifted, compare=False)
    assert r0.quality["velocity_fit"]["fused"] and r1.quality["velocity_fit"]["fused"]
    assert abs((r1.latency_s - r0.latency_s) - 0.0373) < 0.2e-3


def test_velocity_late_beyond_the_rates_is_not_fused():
    """A slave whose nav output is 40 ms later than its IMU: the two disagree, the rate fit stays, and the
    flag says so (a nav velocity's delay need not be its IMU's)."""
    p = _pair("vehicle")
    t, v = p.slave.vel_ned_m_s()
    nav = p.slave.nav.copy()
    nav.index = nav.index + 0.040
    late = InsLog(imu=p.slave.imu, nav=nav, meta=p.slave.meta)
    res = estimate(p.master, late, compare=False)
    vq = res.quality["velocity_fit"]
    assert vq is not None and not vq["fused"] and res.quality["velocity_disagrees"]
    assert abs(vq["latency_s"] - res.latency_s - 0.040) < 1e-3  # the velocity saw its own 40 ms
    assert abs(_error_s(p, res)) < 0.2e-3  # the rates' estimate, untouched


def test_shared_nav_stream_is_not_matched():
    """Two IMUs of one log carrying the same EKF output: the velocities are the same samples, which say
    nothing about the IMUs' delay; no velocity fit."""
    p = _pair("vehicle")
    m = p.master
    shared = InsLog(imu=p.slave.rebased(m.meta.t0_ns).imu, nav=m.nav, meta=m.meta)
    assert velocity_pair(m, shared, 2.0, None) is None
    res = estimate(m, shared, compare=False)
    assert res.quality["velocity_fit"] is None and not res.quality["velocity_disagrees"]


@pytest.mark.parametrize("nav_rate_hz", [10.0, 50.0])
def test_attitude_only_slave_with_flexure(nav_rate_hz):
    """A slave without an IMU (attitude and velocity at 10-50 Hz) on the vehicle with flexure: from its
    attitude-derived rates alone the error was 4.6 ms (4.8 sigma); with its velocity, within 0.2 ms."""
    p = _pair("vehicle", seed=1, flexure=True, slave_nav_rate_hz=nav_rate_hz, slave_imu_rate_hz=100.0)
    s = p.slave
    tn, q = s.quat_wxyz()
    _, v = s.vel_ned_m_s()
    _, lla = s.lat_lon_alt()
    att_only = InsLog.from_arrays(s.meta, t_nav_s=tn, quat_wxyz=q, vel_ned_m_s=v, lat_lon_alt=lla)
    res = estimate(p.master, att_only, compare=False)
    assert res.quality["rate_source"]["slave"] == "attitude"
    assert res.quality["velocity_fit"]["fused"]
    e = _error_s(p, res)
    assert abs(e) < 0.2e-3 and abs(e) < 3 * res.sigma_s, (e, res.sigma_s)


def test_velocity_quantum_is_recognised():
    from logtools.latency.velocity_pair import velocity_quantum_m_s

    rng = np.random.default_rng(0)
    v = rng.normal(0.0, 3.0, (500, 3))
    assert velocity_quantum_m_s(np.round(v * 100) / 100) == 0.01  # MAVLink GLOBAL_POSITION_INT: cm/s
    assert velocity_quantum_m_s(np.round(v * 10) / 10) == 0.1
    assert velocity_quantum_m_s(v) == 0.0


def test_quantized_slave_velocity_keeps_an_honest_sigma():
    """A slow ship whose slave logs its velocity in whole cm/s (a MAVLink tlog): the quantization is not
    white where the velocity changes slowly; the velocity fit's sigma accounts for it (its error within
    3 sigma; without the quantization floor it was 2-4 sigma off on these seeds)."""
    for seed in (5, 7):
        p = _pair("ship", seed=seed, flexure=True)
        t, v = p.slave.vel_ned_m_s()
        res = estimate(p.master, _with_velocity(p.slave, np.round(v * 100.0) / 100.0), compare=False)
        vq = res.quality["velocity_fit"]
        err = vq["latency_s"] - p.truth.latency_at(res.t_mid_rel_s)
        assert abs(err) < 3 * vq["sigma_s"], (seed, err, vq["sigma_s"])
        assert abs(_error_s(p, res)) < 3 * res.sigma_s


def test_velocity_resets_are_found_and_solved():
    """An aided slave whose velocity jumps twice (filter resets of 0.5 m/s): the steps are found in the
    velocity difference and solved, so the velocity still carries the delay (without them its estimate
    was 150 ms off, its sigma 100 ms); the result stays within 3 sigma."""
    p = _pair("aircraft", seed=2, flexure=True, slave_vel_noise_m_s=0.005)
    t, v = p.slave.vel_ned_m_s()
    jump = 0.5 * (t > t[len(t) // 3])[:, None] * np.array([1.0, -0.6, 0.2]) - 0.35 * (t > t[2 * len(t) // 3])[:, None]
    res = estimate(p.master, _with_velocity(p.slave, v + jump), compare=False)
    vq = res.quality["velocity_fit"]
    # the two resets (at the 1.0 Hz low-pass of the common motion band the detector also cuts once more,
    # where there is no reset: a step more to solve costs a little information, and no bias)
    assert vq["velocity_steps"] in (2, 3)
    assert abs(vq["latency_s"] - p.truth.latency_at(res.t_mid_rel_s)) < 3 * vq["sigma_s"] < 5e-3
    assert abs(_error_s(p, res)) < 3 * res.sigma_s


def test_millisecond_stamps_floor_the_velocity_sigma(tmp_path):
    """A MAVLink tlog stamps its velocity (GLOBAL_POSITION_INT) in whole boot milliseconds while its IMU
    (HIGHRES_IMU) has microseconds: the parser says so, and the velocity's sigma does not go below
    1 ms / sqrt(12) (with a fixed sampling phase every stamp is off by the same fraction of a
    millisecond). The multirotor's velocity alone had 0.014 ms and missed by 0.44 ms."""
    from parsers import registry

    p = _pair("multirotor", flexure=True, slave_imu_rate_hz=75.0)
    path = str(tmp_path / "slave.tlog")
    registry.write(path, p.slave, "tlog")
    slave = registry.load(path)
    assert slave.meta.channels["vel"].stamp_resolution_s == 1e-3
    assert slave.meta.channels["gyro"].stamp_resolution_s == 0.0
    res = estimate(p.master, slave, compare=False)
    vq = res.quality["velocity_fit"]
    assert vq["sigma_s"] >= 1e-3 / np.sqrt(12.0)
    assert abs(vq["latency_s"] - p.truth.latency_at(res.t_mid_rel_s)) < 3 * vq["sigma_s"]


@pytest.mark.parametrize("scenario,rpy_deg", [("aircraft", (0.5, -0.3, 5.0)), ("aircraft", (10.0, -5.0, 40.0)),
                                              ("vehicle", (10.0, -5.0, 40.0))])
def test_velocity_in_a_rotated_frame(scenario, rpy_deg):
    """A slave INS with a heading error (or a velocity in another frame): the linear tilt model erred by
    |v| angle^2 / 2 and 2 deg of heading on the aircraft made the velocity useless (sigma 258 ms, the
    rates' 1.7-2 ms bound left). The rotation is found (Kabsch; heading alone where the velocity varies
    in one direction, the aircraft's S-turns), undone, the fitted tilt undone exactly: the flexure
    aircraft is back within 0.5 ms."""
    from logtools.conventions import dcm_from_euler

    p = _pair(scenario, flexure=True)
    R = dcm_from_euler(np.radians(rpy_deg))
    slave = _with_velocity(p.slave, p.slave.nav[list(VEL)].to_numpy() @ R.T)
    res = estimate(p.master, slave, compare=False)
    vq = res.quality["velocity_fit"]
    angle = np.degrees(np.arccos((np.trace(R) - 1.0) / 2.0))
    assert vq["frame_rotation_deg"] == pytest.approx(angle, abs=0.1)
    err_v = vq["latency_s"] - p.truth.latency_at(res.t_mid_rel_s)
    assert vq["fused"] and vq["sigma_s"] < 0.5e-3 and abs(err_v) < 3 * vq["sigma_s"]
    assert abs(_error_s(p, res)) < 0.5e-3


def test_leverage_corrected_residual_spectrum_is_unbiased_for_white_noise():
    """A short record's fitted columns (offset, ramp, a slow manoeuvre's shape) take most of the low
    frequencies out of the residual; a noise spectrum estimated from it is low exactly there, and the GLS
    overweights them (the velocity fit's sigma on a 45 s car came out 1.4x small). Divided by
    1 - leverage, the residual periodogram of white noise is unbiased again."""
    from logtools.latency.gls import leverage_spectrum, noise_model

    rng = np.random.default_rng(1)
    n, dt, sigma = 900, 0.05, 0.003
    t = np.arange(n) * dt
    cols = [np.ones(n), t / t[-1], np.sin(2 * np.pi * t / 40.0), np.cos(2 * np.pi * t / 25.0)]
    J = np.zeros((n, 3, 3 * len(cols)))
    for c in range(3):
        for k, col in enumerate(cols):
            J[:, c, 3 * c + k] = col
    use = np.ones(n, bool)
    A = J.reshape(3 * n, -1)
    H = A @ np.linalg.pinv(A)
    lev = leverage_spectrum(J, use)
    assert lev.shape == (n // 2 + 1,) and np.all(lev >= -1e-12) and lev[:3].max() > 0.5
    raw, fixed = [], []
    for _ in range(200):
        e = rng.standard_normal(3 * n) * sigma
        r = (e - H @ e).reshape(n, 3)
        raw.append(noise_model(r, use, dt).psd[:4])
        fixed.append(noise_model(r, use, dt, leverage=lev).psd[:4])
    low_raw, low_fixed = np.mean(raw), np.mean(fixed)
    assert low_raw < 0.75 * sigma ** 2  # the plain estimate is low at the lowest frequencies
    assert abs(low_fixed / sigma ** 2 - 1.0) < 0.15


def test_nav_only_master_lever_arm_rows_are_low_passed_like_the_velocities():
    """A master logging its navigation solution alone: its rate comes from its (noisy) attitude. The
    lever-arm rows C_nb [w x] are low-passed like the velocities; at the rate fit's 4 Hz their noise above
    the velocities' cutoff diluted the lever arm's regression (along-track 14 % short) and the velocity's
    latency came out 1.5-2.2 ms late at sigmas of 0.3-0.6 ms on this aircraft (sweep seed 103, run 1)."""
    cfg = sim.scenario_config(
        "aircraft", seed=103001, duration_s=180.0, latency_s=-0.3, drift_ppm=-95.6, master_imu_rate_hz=294.0,
        slave_imu_rate_hz=211.0, slave_nav_rate_hz=10.0, lever_arm_m=(-1.486, 0.682, -0.880),
        slave_vel_noise_m_s=0.005, slave_att_noise_deg=0.01, speed_m_s=89.0, turn_amp_deg=11.9,
        turn_period_s=31.1, climb_amp_deg=4.9, speed_var_m_s=12.1, mount_rpy_deg=(30.0, -20.0, 140.0))
    p = sim.simulate(cfg)
    master = InsLog(imu=p.master.imu.iloc[:0], nav=p.master.nav, meta=p.master.meta)
    res = estimate(master, p.slave, compare=False)
    assert res.quality["rate_source"]["master"] == "attitude"
    vf = res.quality["velocity_fit"]
    err = vf["latency_s"] - p.truth.latency_at(res.t_mid_rel_s)
    assert abs(err) < 2.5 * vf["sigma_s"] and vf["sigma_s"] < 1e-3
    assert np.allclose(vf["lever_arm_m"], cfg.lever_arm_m, atol=0.05)
