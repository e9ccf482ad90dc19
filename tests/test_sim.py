"""The scenario simulator (logtools.sim) checked against an independent strapdown integration.

The strapdown below is written here, on purpose without logtools.conventions: its own Hamilton
product, DCM and WGS84 radii, NED mechanisation with earth and transport rate, RK4 over pairs of point
samples (stages at t_k, t_k+1, t_k+2). Only the normal-gravity model is shared (a convention, tested
against closed forms in test_conventions.py).
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from logtools import earth, sim
from logtools.conventions import dcm_from_euler, dcm_from_quat
from logtools.errors import InputError

ARCSEC = math.pi / 180 / 3600
A_M, E2, OMEGA = 6378137.0, 6.69437999014e-3, 7.292115e-5


# ---- an independent strapdown (batched over runs; component-major state: rows of length B) ----
def _deriv(y, w_ib, f_b):
    """d/dt of the state rows [qw qx qy qz vn ve vd lat lon alt] given body rate and specific force
    rows (3, B): quaternion kinematics with omega_in^n, NED velocity with Coriolis/transport/gravity."""
    qw, qx, qy, qz, vn, ve, vd, lat, _lon, h = y
    sl, cl = np.sin(lat), np.cos(lat)
    den = 1 - E2 * sl * sl
    rn, rm = A_M / np.sqrt(den), A_M * (1 - E2) / den**1.5
    rnh, rmh = rn + h, rm + h
    wie_n, wie_d = OMEGA * cl, -OMEGA * sl
    wen_n, wen_e, wen_d = ve / rnh, -vn / rmh, -ve * sl / cl / rnh
    win_n, win_e, win_d = wie_n + wen_n, wen_e, wie_d + wen_d
    wx, wy, wz = w_ib
    # q' = 0.5 q*(0,w_ib) - 0.5 (0,w_in)*q
    dqw = 0.5 * (-qx * wx - qy * wy - qz * wz) - 0.5 * (-win_n * qx - win_e * qy - win_d * qz)
    dqx = 0.5 * (qw * wx + qy * wz - qz * wy) - 0.5 * (win_n * qw + win_e * qz - win_d * qy)
    dqy = 0.5 * (qw * wy - qx * wz + qz * wx) - 0.5 * (-win_n * qz + win_e * qw + win_d * qx)
    dqz = 0.5 * (qw * wz + qx * wy - qy * wx) - 0.5 * (win_n * qy - win_e * qx + win_d * qw)
    fx, fy, fz = f_b
    s = 1.0 / (qw * qw + qx * qx + qy * qy + qz * qz)
    fn = s * ((qw * qw + qx * qx - qy * qy - qz * qz) * fx + 2 * (qx * qy - qw * qz) * fy
              + 2 * (qx * qz + qw * qy) * fz)
    fe = s * (2 * (qx * qy + qw * qz) * fx + (qw * qw - qx * qx + qy * qy - qz * qz) * fy
              + 2 * (qy * qz - qw * qx) * fz)
    fd = s * (2 * (qx * qz - qw * qy) * fx + 2 * (qy * qz + qw * qx) * fy
              + (qw * qw - qx * qx - qy * qy + qz * qz) * fz)
    an, ae, ad = 2 * wie_n + wen_n, wen_e, 2 * wie_d + wen_d  # (2 w_ie + w_en) x v
    g = earth.gravity_m_s2(lat, h)
    return np.stack([dqw, dqx, dqy, dqz,
                     fn - (ae * vd - ad * ve), fe - (ad * vn - an * vd), fd - (an * ve - ae * vn) + g,
                     vn / rmh, ve / (rnh * cl), -vd])


def strapdown(t, gyro, accel, q0, v0, lla0):
    """RK4 over sample pairs (stages at samples k, k+1, k+2) for B runs at once.

    t (B, N) true sample instants, gyro/accel (B, N, 3), q0 (B, 4), v0 (B, 3), lla0 (B, 3) in deg/m.
    Returns the state at every second sample: q (B, M, 4), v (B, M, 3), lla (B, M, 3) deg/m.
    """
    y = np.concatenate([q0, v0, np.radians(lla0[:, :2]), lla0[:, 2:]], axis=1).T.copy()
    w = np.transpose(gyro, (1, 2, 0)).copy()  # (N, 3, B)
    f = np.transpose(accel, (1, 2, 0)).copy()
    out = [y.copy()]
    for k in range(0, t.shape[1] - 2, 2):
        h = t[:, k + 2] - t[:, k]
        k1 = _deriv(y, w[k], f[k])
        k2 = _deriv(y + 0.5 * h * k1, w[k + 1], f[k + 1])
        k3 = _deriv(y + 0.5 * h * k2, w[k + 1], f[k + 1])
        k4 = _deriv(y + h * k3, w[k + 2], f[k + 2])
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        y[:4] /= np.sqrt((y[:4] ** 2).sum(axis=0))
        out.append(y)
    ys = np.transpose(np.stack(out), (2, 0, 1))  # (B, M, 10)
    lla = np.concatenate([np.degrees(ys[..., 7:9]), ys[..., 9:]], axis=-1)
    return ys[..., :4], ys[..., 4:7], lla


def _angle_err(q_a, q_b):
    """Rotation angle (rad) between attitude quaternions, computed from DCMs."""
    m = np.einsum("nji,njk->nik", dcm_from_quat(q_a), dcm_from_quat(q_b))
    c = (np.trace(m, axis1=1, axis2=2) - 1) / 2
    sv = 0.5 * np.linalg.norm(np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0],
                                        m[:, 1, 0] - m[:, 0, 1]], axis=1), axis=1)
    return np.arctan2(sv, c)


def _ned_err_m(lla_a, lla_b):
    rm, rn = earth.radii_m(np.radians(lla_a[:, 0]))
    dn = np.radians(lla_a[:, 0] - lla_b[:, 0]) * rm
    de = np.radians(lla_a[:, 1] - lla_b[:, 1]) * rn * np.cos(np.radians(lla_a[:, 0]))
    return np.sqrt(dn**2 + de**2 + (lla_a[:, 2] - lla_b[:, 2]) ** 2)


def _nav_at(log, t):
    """Nav rows at exactly the relative times t (nav stamps are a subset of the IMU stamps here)."""
    tn = log.t_nav_s()
    idx = np.searchsorted(tn, t - 1e-7)
    assert np.allclose(tn[idx], t, atol=1e-9)
    return log.quat_wxyz()[1][idx], log.vel_ned_m_s()[1][idx], log.lat_lon_alt()[1][idx]


# ---- strapdown checks: master and slave stay on the truth for 60 s --------------------------
SLAVE_CASES = {
    "aircraft 170deg mount + lever arm + 80 ppm": ("aircraft", dict(
        mount_rpy_deg=(170.0, -35.0, 120.0), lever_arm_m=(2.0, -1.5, 0.7), drift_ppm=80.0)),
    "aircraft 170deg mount + lever arm + flexure + 80 ppm": ("aircraft", dict(
        mount_rpy_deg=(170.0, -35.0, 120.0), lever_arm_m=(2.0, -1.5, 0.7), drift_ppm=80.0, flexure=True,
        flexure_step_s=0.1)),
    "ship 10 m lever arm, 400 Hz, boot clock": ("ship", dict(
        mount_rpy_deg=(0.3, 0.4, -1.0), lever_arm_m=(10.0, 3.0, -5.0), slave_imu_rate_hz=400.0,
        slave_nav_rate_hz=100.0, slave_clock="boot", latency_s=0.25)),
    "multirotor 90deg + flexure": ("multirotor", dict(
        mount_rpy_deg=(0.0, 0.0, 90.0), lever_arm_m=(0.1, 0.05, -0.03), flexure=True,
        flexure_sigma_deg=(0.2, 0.2, 0.2), flexure_beta_1_s=(1.0, 1.0, 1.0), flexure_step_s=0.1)),
}
STRAPDOWN_S = 60.0


@pytest.fixture(scope="module")
def strapdown_errors():
    """Integrate every master scenario and every slave case over 60 s (one batched loop); return the
    max attitude (arcsec), velocity (m/s) and position (m) errors against the truth per run."""
    runs = []  # (name, true sample instants, log, config, slave-clock times or None)
    for sc in sim.SCENARIOS:
        cfg = sim.scenario_config(sc, duration_s=STRAPDOWN_S).noiseless()
        m = sim.simulate(cfg).master
        runs.append((f"master {sc}", m.t_imu_s(), m, cfg, None))
    for name, (sc, extra) in SLAVE_CASES.items():
        cfg = sim.scenario_config(sc, duration_s=STRAPDOWN_S, **extra).noiseless()
        pair = sim.simulate(cfg)
        s = pair.slave
        t = s.t_imu_s()
        # the slave's clock runs drift_ppm fast: integrate over the TRUE instants its stamps stand for
        t_true = pair.truth.true_time_of_slave_stamp(s.meta.t0_ns + np.round(t * 1e9).astype(np.int64))
        runs.append((f"slave {name}", t_true, s, cfg, t))
    # RK4 step 10 ms with its mid-point sample: every 200 Hz sample, every second 400 Hz one
    strides = [max(1, int(round(0.005 / np.median(np.diff(r[1]))))) for r in runs]
    n = min(len(r[1][::st]) for r, st in zip(runs, strides))
    n -= (n - 1) % 2
    t = np.stack([r[1][::st][:n] for r, st in zip(runs, strides)])
    gyro = np.stack([r[2].gyro_rad_s()[::st][:n] for r, st in zip(runs, strides)])
    accel = np.stack([r[2].accel_m_s2()[::st][:n] for r, st in zip(runs, strides)])
    init = [_nav_at(r[2], r[2].t_imu_s()[:1]) for r in runs]
    q, v, lla = strapdown(t, gyro, accel, np.stack([i[0][0] for i in init]), np.stack([i[1][0] for i in init]),
                          np.stack([i[2][0] for i in init]))
    errors = {}
    for b, ((name, _, log, cfg, t_clock), st) in enumerate(zip(runs, strides)):
        tb = t[b, ::2]
        if t_clock is None:  # master: against the analytic truth, and the logged nav against it too
            tr = sim.truth_trajectory(cfg, tb)
            ref_q, ref_v, ref_p = tr.quat_wxyz, tr.vel_ned_m_s, tr.lat_lon_alt
            qn, vn, pn = _nav_at(log, tb[np.isin(np.round(tb * 1e9), np.round(log.t_nav_s() * 1e9))])
            keep_all = np.isin(np.round(tb * 1e9), np.round(log.t_nav_s() * 1e9))
            assert _angle_err(qn, ref_q[keep_all]).max() < 1e-9
            assert np.abs(vn - ref_v[keep_all]).max() < 1e-9
            assert _ned_err_m(pn, ref_p[keep_all]).max() < 1e-6
            keep = np.ones(len(tb), bool)
        else:  # slave: against its own logged (true) nav at the same stamps
            t_sl = t_clock[::st][:n][::2]
            keep = np.isin(np.round(t_sl * 1e9), np.round(log.t_nav_s() * 1e9))
            ref_q, ref_v, ref_p = _nav_at(log, t_sl[keep])
        errors[name] = (_angle_err(q[b][keep], ref_q).max() / ARCSEC, np.abs(v[b][keep] - ref_v).max(),
                        _ned_err_m(lla[b][keep], ref_p).max(), float(tb[-1] - tb[0]))
        print(f"strapdown {name}: att {errors[name][0]:.3g} arcsec, vel {errors[name][1]:.3g} m/s, "
              f"pos {errors[name][2]:.3g} m over {errors[name][3]:.1f} s")
    return errors


@pytest.mark.parametrize("name", [f"master {s}" for s in sim.SCENARIOS] + [f"slave {n}" for n in SLAVE_CASES])
def test_imu_integrates_onto_truth(strapdown_errors, name):
    """The generated IMU, integrated from the true initial state by the strapdown above, stays on the
    truth for a minute: master (all scenarios) and slave (mounting of any size, lever arm, flexure,
    drift, other rates, boot clock)."""
    att, vel, pos, span = strapdown_errors[name]
    assert span > STRAPDOWN_S - 0.5
    # the flexure path is C1 (Hermite through the Markov samples): its rate has kinks that RK4 over
    # point samples resolves to ~1 arcsec / mm/s; everything else is exact to numerical precision
    lim = (2.0, 3e-3, 0.05) if "flexure" in name else (0.01, 1e-5, 1e-3)
    assert att < lim[0], f"{name}: attitude {att:.3g} arcsec"
    assert vel < lim[1], f"{name}: velocity {vel:.3g} m/s"
    assert pos < lim[2], f"{name}: position {pos:.3g} m"


# ---- time, mounting and latency truth -------------------------------------------------------
def test_slave_gyro_is_mounted_master_rate_at_the_instant_its_stamp_says():
    cfg = sim.scenario_config("vehicle", duration_s=40.0, latency_s=0.137, drift_ppm=250.0,
                              mount_rpy_deg=(5.0, -170.0, 33.0), slave_imu_rate_hz=333.0,
                              slave_start_phase=0.4).noiseless()
    pair = sim.simulate(cfg)
    m, s, truth = pair.master, pair.slave, pair.truth
    # the truth dict says what the config said
    d = truth.to_dict()
    assert d["latency_s"] == 0.137 and d["drift_ppm"] == 250.0
    assert d["mounting_rpy_deg"] == [5.0, -170.0, 33.0] and d["t_mid_rel_s"] == 20.0
    assert d["t_mid_s"] == pytest.approx(m.t0_s + 20.0)
    # invert the slave clock independently: sigma = t + L + d (t - t_mid)
    stamp_rel = (s.meta.t0_ns - m.meta.t0_ns) * 1e-9 + s.t_imu_s()
    dr = 250e-6
    t_true = (stamp_rel - 0.137 + dr * 20.0) / (1 + dr)
    stamps_ns = s.meta.t0_ns + np.round(s.t_imu_s() * 1e9).astype(np.int64)
    assert np.allclose(t_true, truth.true_time_of_slave_stamp(stamps_ns), atol=2e-9)
    assert np.allclose(stamp_rel - t_true, truth.latency_at(t_true), atol=2e-9)
    # slave stamps uniform on the slave clock
    assert np.ptp(np.diff(s.t_imu_s())) < 2e-9 and np.diff(s.t_imu_s()).mean() == pytest.approx(1 / 333.0)
    # slave gyro = R @ omega_ib(t_true) and the master's gyro is omega_ib at its stamps
    R = dcm_from_euler(np.radians(cfg.mount_rpy_deg))
    w_true = sim.truth_trajectory(cfg, t_true).omega_ib_b_rad_s
    assert np.abs(s.gyro_rad_s() - w_true @ R.T).max() < 1e-12
    assert np.abs(m.gyro_rad_s() - sim.truth_trajectory(cfg, m.t_imu_s()).omega_ib_b_rad_s).max() < 1e-12
    # slave nav: C_s^n = C_m^n R^T at the true instants of its stamps, same velocity and position
    tn, qn = s.quat_wxyz()
    tn_true = truth.true_time_of_slave_stamp(s.meta.t0_ns + np.round(tn * 1e9).astype(np.int64))
    trn = sim.truth_trajectory(cfg, tn_true)
    assert np.abs(dcm_from_quat(qn) - dcm_from_quat(trn.quat_wxyz) @ R.T).max() < 1e-12
    assert np.abs(s.vel_ned_m_s()[1] - trn.vel_ned_m_s).max() < 1e-9
    assert np.abs(s.lat_lon_alt()[1] - trn.lat_lon_alt).max() < 1e-9
    # |omega| is mounting-invariant: shifting the slave by the true latency lines it up with the
    # master's samples; 2 ms off does not
    tm, wm = m.t_imu_s(), np.linalg.norm(m.gyro_rad_s(), axis=1)
    ws = np.linalg.norm(s.gyro_rad_s(), axis=1)
    inner = (t_true > 1) & (t_true < 39)

    def mismatch(shift_s):
        return np.abs(np.interp(stamp_rel[inner] - shift_s, tm, wm) - ws[inner]).mean()

    exact = mismatch(truth.latency_at(t_true[inner]))
    assert exact < 0.02 * mismatch(truth.latency_at(t_true[inner]) + 0.002)


def test_latency_drift_and_boot_clock():
    cfg = sim.scenario_config("ship", duration_s=100.0, latency_s=0.1, drift_ppm=20.0, slave_clock="boot",
                              slave_boot_start_s=50.0)
    pair = sim.simulate(cfg)
    tr = pair.truth
    assert pair.slave.meta.clock == "boot" and pair.master.meta.clock == "epoch"
    assert 50.0 <= pair.slave.t0_s < 50.2
    assert tr.latency_excl_clock_offset_s == 0.1
    assert tr.latency_s == pytest.approx(0.1 + tr.clock_offset_s, abs=1e-6)
    assert tr.clock_offset_s == pytest.approx(50.0 - pair.master.t0_s, abs=0.2)
    # drift: 20 ppm over 100 s = 2 ms between the ends, latency_s holds at the middle
    # (with the boot offset, latency_s ~ -1.7e9 s: float64 resolves it to ~0.2 us)
    assert tr.latency_at(100.0) - tr.latency_at(0.0) == pytest.approx(2e-3, abs=1e-6)
    assert tr.latency_at(tr.t_mid_rel_s) == tr.latency_s
    # every slave stamp: slave stamp - master stamp of that instant == latency_at(instant)
    st_ns = pair.slave.meta.t0_ns + np.round(pair.slave.t_imu_s() * 1e9).astype(np.int64)
    t_true = tr.true_time_of_slave_stamp(st_ns)
    diff_s = (st_ns - pair.master.meta.t0_ns).astype(np.float64) * 1e-9 - t_true
    assert np.allclose(diff_s, tr.latency_at(t_true), rtol=0, atol=1e-6)
    # ... and those instants are the ones the (noiseless) slave gyro measured
    R = dcm_from_euler(np.radians(cfg.mount_rpy_deg))
    clean = sim.simulate(cfg.noiseless())
    assert np.array_equal(clean.slave.t_imu_s(), pair.slave.t_imu_s())
    w = sim.truth_trajectory(cfg, t_true).omega_ib_b_rad_s @ R.T
    assert np.abs(clean.slave.gyro_rad_s() - w).max() < 1e-12
    d = json.loads(json.dumps(tr.to_dict()))
    assert d["clocks"]["slave"] == "boot" and d["latency_s"] < -1e9


def test_seeded_reproducibility_and_noise_levels():
    cfg = sim.scenario_config("aircraft", duration_s=30.0, seed=7)
    a, b = sim.simulate(cfg), sim.simulate(cfg)
    for x, y in ((a.master.imu, b.master.imu), (a.slave.imu, b.slave.imu), (a.slave.nav, b.slave.nav)):
        assert x.equals(y)
    assert a.truth.to_dict() == b.truth.to_dict()
    c = sim.simulate(sim.scenario_config("aircraft", duration_s=30.0, seed=8))
    assert not np.allclose(a.slave.gyro_rad_s(), c.slave.gyro_rad_s())
    # errors = configured bias + white noise of the configured density
    clean = sim.simulate(cfg.noiseless())
    err = a.slave.gyro_rad_s() - clean.slave.gyro_rad_s()
    bias = np.radians(np.array(cfg.slave_gyro_bias_dph)) / 3600
    assert np.allclose(err.mean(axis=0), bias, atol=4 * err.std() / np.sqrt(len(err)))
    sd = cfg.slave_gyro_arw_dpsh * math.radians(1) / 60 * math.sqrt(cfg.slave_imu_rate_hz)
    assert err.std(axis=0) == pytest.approx([sd] * 3, rel=0.05)
    aerr = a.slave.accel_m_s2() - clean.slave.accel_m_s2()
    assert np.allclose(aerr.mean(axis=0) / 9.80665e-3, cfg.slave_accel_bias_mg, atol=0.01)


def test_scenarios_follow_the_seeds():
    ship = sim.scenario_config("ship")
    assert (ship.lat0_deg, ship.lon0_deg) == (30.0, 110.0)
    assert ship.sway_amp_deg == (8.0, 6.0, 4.0) and ship.sway_period_s == (12.0, 10.0, 16.0)
    assert ship.mount_rpy_deg == (0.3, 0.4, -1.0) and ship.latency_s == 0.1
    t = np.arange(0.0, 240.0, 0.01)
    tr = sim.truth_trajectory(ship, t)
    rpy = np.degrees(tr.rpy_rad)
    rpy[:, 2] -= ship.course_deg
    assert np.abs(rpy).max(axis=0) == pytest.approx([8.0, 6.0, 4.0], abs=1e-3)
    for ax, period in enumerate((12.0, 10.0, 16.0)):
        spec = np.abs(np.fft.rfft(rpy[:, ax]))
        f = np.fft.rfftfreq(len(t), 0.01)
        assert 1 / f[np.argmax(spec)] == pytest.approx(period, rel=0.01)
    assert np.linalg.norm(tr.vel_ned_m_s[:, :2], axis=1).mean() == pytest.approx(10.0, abs=0.1)
    air = sim.scenario_config("aircraft")
    tra = sim.truth_trajectory(air, np.arange(0.0, 200.0, 0.1))
    assert tra.lat_lon_alt[0].tolist() == pytest.approx([32.0, 118.0, 1000.0])
    assert np.linalg.norm(tra.vel_ned_m_s, axis=1) == pytest.approx(200.0, abs=5.01)
    head = np.degrees(tra.rpy_rad[:, 2])
    assert np.ptp(head) > 30.0  # S-turns
    bank = np.degrees(tra.rpy_rad[:, 0])
    assert bank.max() > 15.0 and bank.min() < -15.0
    veh = sim.truth_trajectory(sim.scenario_config("vehicle"), np.arange(0.0, 120.0, 0.1))
    assert veh.lat_lon_alt[0, :2].tolist() == pytest.approx([39.0, 116.0])
    speed = np.linalg.norm(veh.vel_ned_m_s, axis=1)
    assert 9.0 < speed.min() and speed.max() < 21.0 and np.ptp(speed) > 5.0
    mr = sim.truth_trajectory(sim.scenario_config("multirotor"), np.arange(0.0, 60.0, 0.05))
    assert np.linalg.norm(mr.vel_ned_m_s[0]) < 0.1  # hover first
    assert 2.0 < np.linalg.norm(mr.vel_ned_m_s, axis=1).max() < 8.0


def test_options_nav_off_gaps_jitter_flexure():
    cfg = sim.scenario_config("ship", duration_s=60.0, slave_nav=False, slave_gaps_s=((10.0, 5.0),),
                              slave_jitter_s=2e-4, master_jitter_s=1e-4, slave_imu_rate_hz=100.0)
    pair = sim.simulate(cfg)
    assert len(pair.slave.nav) == 0 and not pair.slave.has_quat
    dt = np.diff(pair.slave.t_imu_s())
    assert dt.max() == pytest.approx(5.0, abs=0.02)  # the gap
    assert dt.min() > 0 and np.std(dt[dt < 0.1]) > 1e-4  # jitter, still monotonic
    assert 0 < np.std(np.diff(pair.master.t_imu_s())) < 1e-3
    # flexure: slave-vs-mounted-master attitude wanders with about the configured std
    fc = sim.scenario_config("ship", duration_s=400.0, flexure=True, flexure_sigma_deg=(0.1, 0.05, 0.02),
                             flexure_beta_1_s=(2.0, 2.0, 2.0), mount_rpy_deg=(0, 0, 0)).noiseless()
    fp = sim.simulate(fc)
    ts, qs = fp.slave.quat_wxyz()
    t_true = fp.truth.true_time_of_slave_stamp(fp.slave.meta.t0_ns + np.round(ts * 1e9).astype(np.int64))
    cm = dcm_from_quat(sim.truth_trajectory(fc, t_true).quat_wxyz)
    rel = np.einsum("nji,njk->nik", cm, dcm_from_quat(qs))  # C_s^m = exp([lambda x])
    lam = np.stack([rel[:, 2, 1], rel[:, 0, 2], rel[:, 1, 0]], axis=1)
    assert np.degrees(lam.std(axis=0)) == pytest.approx([0.1, 0.05, 0.02], rel=0.35)


def test_bad_configs_raise_input_error():
    with pytest.raises(InputError, match="unknown scenario"):
        sim.scenario_config("boat")
    with pytest.raises(InputError, match="unknown option"):
        sim.scenario_config("ship", latency=0.1)
    with pytest.raises(InputError, match="slave_imu_rate_hz"):
        sim.scenario_config("ship", slave_imu_rate_hz=0.0)
    with pytest.raises(InputError, match="mount_rpy_deg"):
        sim.scenario_config("ship", mount_rpy_deg=(1.0, 2.0))
    with pytest.raises(InputError, match="slave_clock"):
        sim.scenario_config("ship", slave_clock="gps")


# ---- CLI --------------------------------------------------------------------------------------
def test_cli_simulate_writes_logs_and_truth(tmp_path, capsys):
    from parsers import load
    from pipelines.cli import main

    out = tmp_path / "sim"
    rc = main(["simulate", "ship", "-o", str(out), "--latency", "0.1", "--mount", "0.3,0.4,-1",
               "--duration", "20", "--drift", "20", "--master-format", "csv", "--slave-format", "csv",
               "--seed", "3"])
    assert rc == 0, capsys.readouterr().err
    truth = json.loads((out / "truth.json").read_text())
    assert truth["latency_s"] == 0.1 and truth["drift_ppm"] == 20.0
    assert truth["mounting_rpy_deg"] == [0.3, 0.4, -1.0] and truth["seed"] == 3
    m, s = load(str(out / "master.csv")), load(str(out / "slave.csv"))
    ref = sim.simulate(sim.scenario_config("ship", duration_s=20.0, latency_s=0.1, drift_ppm=20.0,
                                           mount_rpy_deg=(0.3, 0.4, -1.0), seed=3))
    assert m.meta.t0_ns == ref.master.meta.t0_ns and s.meta.t0_ns == ref.slave.meta.t0_ns
    assert np.array_equal(s.t_imu_s(), ref.slave.t_imu_s())
    assert np.allclose(s.gyro_rad_s(), ref.slave.gyro_rad_s(), rtol=0, atol=1e-15)
    assert np.allclose(m.lat_lon_alt()[1], ref.master.lat_lon_alt()[1], rtol=0, atol=1e-12)


def test_cli_simulate_truth_follows_a_slave_file_written_on_its_boot_clock(tmp_path, capsys):
    """A DataFlash slave without nav has no GPS records, the only way that format puts its stamps on UNIX
    time: it is written on its time since boot. truth.json said the latency on UNIX time (0.0213 s) while the
    file read back was 1.7e9 s away; it now gives the latency with that clock's offset in it (as for
    --slave-clock boot), and the analysis of the pair recovers it."""
    from parsers import load
    from pipelines.api import analyze
    from pipelines.cli import main

    out = tmp_path / "sim"
    rc = main(["simulate", "aircraft", "-o", str(out), "--duration", "60", "--latency", "0.0213", "--drift",
               "12", "--slave-format", "dataflash", "--no-slave-nav", "--slave-clock", "epoch"])
    said = capsys.readouterr().out
    assert rc == 0 and "slave.bin is on its boot clock" in said
    truth = json.loads((out / "truth.json").read_text())
    s = load(str(out / "slave.bin"))
    assert s.meta.clock == "boot" and truth["clocks"]["slave"] == "boot"
    assert truth["latency_excl_clock_offset_s"] == 0.0213
    assert truth["latency_s"] == pytest.approx(0.0213 + truth["clock_offset_s"], abs=1e-9)
    assert truth["clock_offset_s"] == pytest.approx(s.meta.t0_ns * 1e-9 - 1.7e9 - 0.0213, abs=0.01)
    lat = analyze(str(out / "master.mcap"), str(out / "slave.bin")).latency
    assert abs(lat.latency_s - truth["latency_s"]) < max(4 * lat.sigma_s, 1e-4)
    # (a format that keeps UNIX time: the truth as simulated)
    rc = main(["simulate", "aircraft", "-o", str(tmp_path / "t"), "--duration", "20", "--latency", "0.0213",
               "--slave-format", "tlog", "--no-slave-nav"])
    got = capsys.readouterr()
    assert rc == 0 and "boot clock" not in got.out and "existed and are replaced" not in got.err
    assert json.loads((tmp_path / "t" / "truth.json").read_text())["latency_s"] == 0.0213
    # the same folder again: the files it replaces are named (a folder of real logs is not changed unnoticed)
    assert main(["simulate", "aircraft", "-o", str(tmp_path / "t"), "--duration", "20", "--latency", "0.03",
                 "--slave-format", "tlog", "--no-slave-nav"]) == 0
    assert "master.mcap, slave.tlog, truth.json in" in capsys.readouterr().err
    assert json.loads((tmp_path / "t" / "truth.json").read_text())["latency_s"] == 0.03


@pytest.mark.parametrize("argv,msg", [
    (["--mount", "1,2"], "--mount needs 3"),
    (["--lever-arm", "a,b,c"], "--lever-arm needs 3"),
    (["--set", "nope=1"], "--set needs FIELD=VALUE"),
    (["--set", "heave_amp_m=x"], "bad value for heave_amp_m"),
    (["--slave-rate", "-5"], "slave_imu_rate_hz"),
    (["--master-format", "nosuch"], "unknown format"),
    (["--gyro-bias=1e9,0,0"], "--gyro-bias beyond"),  # (written, then dropped by the readers as impossible)
    (["--accel-bias=1e9,0,0"], "--accel-bias beyond"),
    (["--lever-arm=1e9,0,0"], "--lever-arm beyond"),
])
def test_cli_simulate_bad_options_one_line(tmp_path, capsys, argv, msg):
    from pipelines.cli import main

    rc = main(["simulate", "ship", "-o", str(tmp_path / "o"), "--duration", "5"] + argv)
    err = capsys.readouterr().err
    assert rc == 2 and msg in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "truth.json").exists()
