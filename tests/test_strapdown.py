"""Strapdown mechanisation: closed forms and simulated truth."""
from __future__ import annotations


import numpy as np
import pytest

from logtools import earth
from logtools.conventions import ARCSEC, angle_between_quats, dcm_from_euler, quat_from_dcm
from logtools import strapdown as sd


# ---- a small analytic truth generator (ship sway on a moving ship), used until/besides logtools.sim ----
def sway_truth(t_s, *, lat0_deg=30.0, lon0_deg=110.0, alt0_m=0.0, vel_ned=(0.0, 0.0, 0.0),
               amp_deg=(8.0, 6.0, 4.0), period_s=(12.0, 10.0, 16.0), heading_deg=0.0,
               phase_rad=(0.0, 0.5, 1.0)):
    """True attitude/velocity/position and point-sampled IMU (gyro, specific force) at instants t_s.
    Constant NED velocity; attitude rpy = amp sin(2 pi t / period + phase) (+ heading on yaw)."""
    t = np.asarray(t_s, float)
    amp = np.radians(amp_deg)
    om = 2 * np.pi / np.asarray(period_s)
    ph = np.asarray(phase_rad)
    arg = t[:, None] * om + ph
    rpy = amp * np.sin(arg)
    rpy[:, 2] += np.radians(heading_deg)
    rpyd = amp * om * np.cos(arg)
    r, p = rpy[:, 0], rpy[:, 1]
    rd, pd, yd = rpyd.T
    w_nb_b = np.stack([rd - yd * np.sin(p), pd * np.cos(r) + yd * np.sin(r) * np.cos(p),
                       -pd * np.sin(r) + yd * np.cos(r) * np.cos(p)], axis=-1)
    v = np.broadcast_to(np.asarray(vel_ned, float), (len(t), 3)).copy()
    lat0 = np.radians(lat0_deg)
    r_m, r_n = earth.radii_m(lat0)
    lat = lat0 + v[:, 0] * t / (r_m + alt0_m)
    alt = alt0_m - v[:, 2] * t
    lon = np.radians(lon0_deg) + v[:, 1] * t / ((r_n + alt0_m) * np.cos(lat0))
    w_ie = earth.earth_rate_ned(lat)
    w_en = earth.transport_rate_ned(lat, alt, v)
    c_nb = dcm_from_euler(rpy)
    c_bn = np.swapaxes(c_nb, -1, -2)
    w_ib_b = w_nb_b + np.einsum("nij,nj->ni", c_bn, w_ie + w_en)
    f_n = np.cross(2 * w_ie + w_en, v) - earth.gravity_ned_m_s2(lat, alt)
    f_b = np.einsum("nij,nj->ni", c_bn, f_n)
    return dict(t=t, quat=quat_from_dcm(c_nb), rpy=rpy, vel=v, llh=np.stack([lat, lon, alt], -1),
                gyro=w_ib_b, accel=f_b)


def test_scalar_earth_model_matches_logtools_earth():
    for lat in (0.1, 0.5, 1.2):
        for h in (0.0, 1000.0):
            assert sd._gravity(lat, h) == pytest.approx(float(earth.gravity_m_s2(lat, h)), rel=1e-14)
            rm, rn = sd._radii(lat)
            erm, ern = earth.radii_m(lat)
            assert rm == pytest.approx(float(erm), rel=1e-14) and rn == pytest.approx(float(ern), rel=1e-14)


def test_stationary_at_latitude_attitude_and_velocity_stay():
    lat = np.radians(45.0)
    t = np.arange(0, 600.0, 0.01)
    c_nb = dcm_from_euler(np.radians([2.0, -3.0, 120.0]))
    w_b = c_nb.T @ earth.earth_rate_ned(lat)
    f_b = c_nb.T @ -earth.gravity_ned_m_s2(lat, 100.0)
    sol = sd.mechanise(t, np.tile(w_b, (len(t), 1)), np.tile(f_b, (len(t), 1)), quat_from_dcm(c_nb),
                       np.zeros(3), lat, 0.3, 100.0)
    att_err = angle_between_quats(sol.quat_wxyz, quat_from_dcm(c_nb))
    assert att_err.max() < 0.01 * ARCSEC
    assert np.abs(sol.vel_ned_m_s).max() < 1e-6
    assert np.abs(sol.llh[:, 0] - lat).max() < 1e-12 and np.abs(sol.llh[:, 2] - 100.0).max() < 1e-5


def test_constant_rate_coning_free_rotation_exact():
    # constant body rate about a fixed axis, no earth rate effect on attitude error check: compare with the
    # closed form q(t) = q0 * exp(w t) after removing the navigation-frame rotation (lat 0, earth rate in N)
    t = np.arange(0, 10.0, 0.005)
    w = np.array([0.3, -0.2, 0.5])
    q_inc = sd.body_increments(t, np.tile(w, (len(t), 1)), np.zeros((len(t), 3)))[0]
    assert np.allclose(q_inc, w * 0.005, atol=1e-15)


@pytest.mark.parametrize("vel", [(0.0, 0.0, 0.0), (8.0, 5.0, 0.0)])
def test_sway_against_truth_60s(vel):
    t = np.arange(0, 60.0 + 1e-9, 1 / 200)
    tr = sway_truth(t, vel_ned=vel, heading_deg=30.0)
    sol = sd.mechanise(t, tr["gyro"], tr["accel"], tr["quat"][0], tr["vel"][0], *tr["llh"][0])
    att_err_arcsec = angle_between_quats(sol.quat_wxyz, tr["quat"]) / ARCSEC
    vel_err = np.linalg.norm(sol.vel_ned_m_s - tr["vel"], axis=1)
    assert att_err_arcsec.max() < 0.5, att_err_arcsec.max()
    assert vel_err.max() < 2e-3, vel_err.max()  # mm/s over 60 s


def test_mechanise_one_hour_200hz_stays_finite():
    """1 h of 200 Hz samples in one call (its speed, 0.8 s compiled against 18 s as Python, is measured by
    benchmarks/bench_strapdown.py, not here)."""
    n = 3600 * 200
    t = np.arange(n) / 200.0
    rng = np.random.default_rng(1)
    gyro = rng.normal(0, 0.01, (n, 3))
    accel = rng.normal(0, 0.05, (n, 3)) + [0, 0, -9.79]
    sol = sd.mechanise(t, gyro, accel, [1, 0, 0, 0], np.zeros(3), 0.5, 0.0, 0.0)
    assert np.isfinite(sol.vel_ned_m_s).all() and np.isfinite(sol.quat_wxyz).all()


sim = pytest.importorskip("logtools.sim")


@pytest.mark.parametrize("scenario", ["ship", "aircraft"])
def test_simulated_master_and_slave_imu_against_truth_60s(scenario):
    """Integrate the simulator's (error-free) master and slave IMUs from the true initial state."""
    from logtools.conventions import quat_mul, dcm_from_euler
    cfg = sim.scenario_config(scenario, duration_s=60.0, latency_s=0.0, seed=3,
                              master_gyro_bias_dph=(0, 0, 0), master_accel_bias_mg=(0, 0, 0),
                              master_gyro_arw_dpsh=0.0, master_accel_vrw_ug_rthz=0.0,
                              slave_gyro_bias_dph=(0, 0, 0), slave_accel_bias_mg=(0, 0, 0),
                              slave_gyro_arw_dpsh=0.0, slave_accel_vrw_ug_rthz=0.0,
                              mount_rpy_deg=(2.0, -3.0, 40.0))
    pair = sim.simulate(cfg)
    r = dcm_from_euler(np.radians(cfg.mount_rpy_deg))
    q_ms = quat_from_dcm(r.T)  # slave body -> master body
    for unit in ("master", "slave"):
        log = getattr(pair, unit).rebased(pair.master.meta.t0_ns)
        t = log.t_imu_s()
        tr = sim.truth_trajectory(cfg, t)
        q_true = tr.quat_wxyz if unit == "master" else quat_mul(tr.quat_wxyz, q_ms)
        llh0 = np.radians(tr.lat_lon_alt[0, :2])
        sol = sd.mechanise(t, log.gyro_rad_s(), log.accel_m_s2(), q_true[0], tr.vel_ned_m_s[0],
                           llh0[0], llh0[1], tr.lat_lon_alt[0, 2])
        att_arcsec = angle_between_quats(sol.quat_wxyz, q_true) / ARCSEC
        vel_err = np.linalg.norm(sol.vel_ned_m_s - tr.vel_ned_m_s, axis=1)
        assert att_arcsec.max() < 0.5, (unit, att_arcsec.max())  # measured 0.04" ship, 0.16" aircraft
        assert vel_err.max() < 2e-4, (unit, vel_err.max())  # m/s; measured 0.01-0.05 mm/s


def test_the_reference_segment_composition_equals_the_kernel():
    """compose_segments' numpy copy (reference mode: the k-th interval of every segment at once) against the
    kernel, segments of 0 to 7 intervals, rotations from 1e-10 to 0.3 rad: the same numbers (numpy's
    vectorised sin/cos may differ from libm's by an ulp)."""
    rng = np.random.default_rng(11)
    n = 400
    rv = rng.normal(size=(n, 3)) * rng.choice([1e-10, 1e-4, 0.3], size=(n, 1))
    dv = rng.normal(size=(n, 3)) * 0.1
    cuts = np.sort(rng.choice(np.arange(n + 1), 90, replace=True))
    starts, stops = cuts[:-1].astype(np.int64), cuts[1:].astype(np.int64)
    assert (stops - starts).max() >= 5 and ((stops - starts) == 0).any()
    q1, d1 = np.empty((len(starts), 4)), np.empty((len(starts), 3))
    q2, d2 = np.empty((len(starts), 4)), np.empty((len(starts), 3))
    sd._compose(rv, dv, starts, stops, q1, d1)
    sd._compose_np(rv, dv, starts, stops, q2, d2)
    assert np.allclose(q1, q2, rtol=0, atol=1e-15) and np.allclose(d1, d2, rtol=0, atol=1e-15)
