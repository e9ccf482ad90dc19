"""Transfer alignment: Jacobians vs finite differences, filter algebra, and recovery of simulated truth
(S004 ship sway: mounting [0.3, 0.4, -1] deg, slave gyro 0.01 deg/h, accel 0.1 mg, 120 s)."""
from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from logtools import earth
from logtools.alignment import CONFIG, AlignmentOptions, run_alignment
from logtools.alignment import kf as kfm
from logtools.alignment import model as mdl
from logtools.errors import AnalysisError

sim = pytest.importorskip("logtools.sim")
RNG = np.random.default_rng(7)


def _rot(rv):
    return mdl.exp_so3(np.asarray(rv, float))


# ---- Jacobians ------------------------------------------------------------------------------------
def _num_jac(fun, n, eps=1e-7):
    cols = []
    for i in range(n):
        d = np.zeros(n)
        d[i] = eps
        cols.append((fun(d) - fun(-d)) / (2 * eps))
    return np.stack(cols, axis=1)


def test_attitude_measurement_jacobian_matches_finite_differences():
    lay = mdl.make_layout("att", flexure=True, delay=True)
    c0 = _rot(RNG.normal(size=3))
    w_s = np.array([0.05, -0.08, 0.03])  # slave body rate relative to NED (slave frame)
    r_hat = _rot(RNG.normal(size=3))

    def c_ns(t):
        return c0 @ _rot(w_s * t)

    def z_of(d):  # d = [phi, mu, lam, dtau]
        phi, mu, lam, dtau = d[:3], d[3:6], d[6:9], d[9]
        r_true = _rot(-(mu + lam)) @ r_hat
        c_nm = c_ns(0.0) @ r_true
        c_hat = _rot(-phi) @ c_ns(-dtau)
        return mdl.att_residual(c_hat, c_nm, r_hat)

    num = _num_jac(z_of, 10)
    h = mdl.measurement_matrix(lay, c_ns(0.0), w_ns_n=c_ns(0.0) @ w_s)
    ana = np.concatenate([h[:, lay.att], h[:, lay.mount], h[:, lay.flex_ang], h[:, [lay.delay]]], axis=1)
    assert np.allclose(num, ana, atol=1e-6), np.abs(num - ana).max()


def test_velocity_measurement_jacobian_matches_finite_differences():
    lay = mdl.make_layout("vel", lever_arm=True, delay=True)
    c_nm = _rot(RNG.normal(size=3))
    w_m = np.array([0.1, -0.2, 0.05])
    a_n = np.array([0.3, -0.2, 0.1])
    l_hat = np.array([1.0, -2.0, 0.5])

    def v_m(t):
        return np.array([5.0, 2.0, 0.0]) + a_n * t

    def z_of(d):  # d = [dv, dl, dtau]
        dv, dl, dtau = d[:3], d[3:6], d[6]
        v_slave_true = v_m(-dtau) + c_nm @ np.cross(w_m, l_hat + dl)
        return mdl.vel_residual(v_slave_true + dv, v_m(0.0), c_nm, w_m, l_hat)

    num = _num_jac(z_of, 7)
    h = mdl.measurement_matrix(lay, np.eye(3), c_nm=c_nm, w_lever_m=w_m, a_m_n=a_n)
    ana = np.concatenate([h[:, lay.vel], h[:, lay.lever], h[:, [lay.delay]]], axis=1)
    assert np.allclose(num, ana, atol=1e-6), np.abs(num - ana).max()


def test_error_dynamics_match_nonlinear_mechanisation():
    """F x against the rates of the nonlinear phi and dv errors, for small errors."""
    lay = mdl.make_layout("vel+att")
    lat, h = np.radians(30.0), 100.0
    v = np.array([10.0, -6.0, 0.5])
    c = _rot([0.2, -0.1, 1.0])
    w_b = np.array([0.02, -0.05, 0.04])
    f_b = np.array([0.5, -0.3, -9.7])
    phi = np.array([2e-4, -3e-4, 5e-4])
    dv = np.array([0.02, -0.03, 0.01])
    eps = np.array([1e-5, -2e-5, 3e-5])
    nab = np.array([2e-3, -1e-3, 3e-3])
    r_m, r_n = earth.radii_m(lat)
    w_ie = earth.earth_rate_ned(lat)

    def w_in(vel):
        return w_ie + earth.transport_rate_ned(lat, h, vel)

    def vdot(cc, ff, vel):
        return cc @ ff + earth.gravity_ned_m_s2(lat, h) - np.cross(2 * w_ie + earth.transport_rate_ned(lat, h, vel), vel)

    dt = 1e-3
    c_hat = _rot(-phi) @ c
    v_hat = v + dv
    c1 = _rot(-w_in(v) * dt) @ c @ _rot(w_b * dt)
    c1_hat = _rot(-w_in(v_hat) * dt) @ c_hat @ _rot((w_b + eps) * dt)
    phi1 = -mdl.rotvec_small(c1_hat @ c1.T)
    phidot_nl = (phi1 - phi) / dt
    dvdot_nl = vdot(c_hat, f_b + nab, v_hat) - vdot(c, f_b, v)
    f = mdl.dynamics_matrix(lay, c, c @ f_b, w_ie, earth.transport_rate_ned(lat, h, v), v,
                            mdl.m_av(lat, h, r_m, r_n))
    x = np.zeros(lay.n)
    x[lay.att], x[lay.vel], x[lay.gyro], x[lay.accel] = phi, dv, eps, nab
    fx = f @ x
    assert np.allclose(fx[lay.att], phidot_nl, rtol=2e-3, atol=1e-10), (fx[lay.att], phidot_nl)
    assert np.allclose(fx[lay.vel], dvdot_nl, rtol=2e-3, atol=1e-6), (fx[lay.vel], dvdot_nl)


def test_flexure_block_is_seed000_second_order_markov():
    lay = mdl.make_layout("att", flexure=True)
    f = mdl.dynamics_matrix(lay, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros((3, 3)),
                            flex_beta=0.7)
    assert np.allclose(f[lay.flex_ang, lay.flex_rate], np.eye(3))
    assert np.allclose(f[lay.flex_rate, lay.flex_ang], -0.49 * np.eye(3))
    assert np.allclose(f[lay.flex_rate, lay.flex_rate], -1.4 * np.eye(3))


def test_board_error_states_master_attitude_and_accel_triad_jacobians():
    """The master's attitude error eta (n frame, C_nm_out = exp(eta) C_nm) enters z_att with +I; the slave's
    accelerometer triad misalignment alpha (measured f = exp(alpha) f^s) enters dv' as -[f^n x] C_ns;
    eta is first-order Markov (F = -1/tau)."""
    lay = mdl.make_layout("vel+att", board_errors=True)
    assert lay.master_att is not None and lay.accel_mis is not None
    assert lay.names[lay.master_att][0] == "master_att_err_n" and lay.names[lay.accel_mis][2] == "accel_misalign_z"
    c_ns = _rot(RNG.normal(size=3))
    r_hat = _rot(RNG.normal(size=3))
    c_nm = c_ns @ r_hat

    def z_of(eta):
        return mdl.att_residual(c_ns, _rot(eta) @ c_nm, r_hat)

    h = mdl.measurement_matrix(lay, c_ns, c_nm=c_nm)
    assert np.allclose(_num_jac(z_of, 3), h[3:, lay.master_att], atol=1e-6)
    assert np.allclose(h[:3, lay.master_att], 0.0)
    f_b = np.array([0.4, -0.7, -9.6])

    def dvdot(alpha):
        return c_ns @ (_rot(alpha) @ f_b) - c_ns @ f_b

    f = mdl.dynamics_matrix(lay, c_ns, c_ns @ f_b, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros((3, 3)),
                            master_att_tau_s=40.0)
    assert np.allclose(_num_jac(dvdot, 3), f[lay.vel, lay.accel_mis], atol=1e-6)
    assert np.allclose(f[lay.master_att, lay.master_att], -np.eye(3) / 40.0)
    # without them the layout is what it was
    assert mdl.make_layout("vel+att").n == lay.n - 6 and mdl.make_layout("att", board_errors=True).accel_mis is None


def test_compiled_kf_step_equals_reference_joseph_update():
    n, m = 12, 6
    a = RNG.normal(size=(n, n))
    P = a @ a.T + n * np.eye(n)
    x = RNG.normal(size=n)
    H = RNG.normal(size=(m, n))
    r = RNG.uniform(0.5, 2.0, m)
    z = RNG.normal(size=m)
    x_ref, p_ref, info = kfm.kf_update(x, P, z, H, np.diag(r))
    x2, p2, e = x.copy(), P.copy(), np.zeros(m)
    nis = kfm.kf_step_nb(x2, p2, np.zeros((0, 0)), np.zeros((0, 0)), z, H, r, e)
    assert np.allclose(x2, x_ref) and np.allclose(p2, p_ref)
    assert nis == pytest.approx(info["nis"]) and np.allclose(e, info["innovation"])


@pytest.mark.parametrize("match", mdl.MATCHES)
@pytest.mark.parametrize("flexure,lever,delay,board", [(False, False, False, False), (True, True, True, True),
                                                       (True, False, True, False), (False, True, False, True)])
def test_the_reference_loops_dynamics_and_measurement_matrices_equal_the_kernels(match, flexure, lever, delay,
                                                                                 board):
    """F and H as the reference loop assigns them (blocks, fill_dynamics_np / fill_h_np) against the
    compiled loop's element-by-element kernels, in every layout: the same matrices, bit for bit."""
    lay = mdl.make_layout(match, flexure=flexure, lever_arm=lever, delay=delay, board_errors=board)
    rng = np.random.default_rng(lay.n)
    for _ in range(5):
        c_ns, c_nm, mav = _rot(rng.normal(size=3)), _rot(rng.normal(size=3)), rng.normal(size=(3, 3))
        f_n, w_ie, w_en, vel, w_l, w_ns, a_m = (rng.normal(size=3) for _ in range(7))
        beta, mk_rate = rng.uniform(0.1, 3.0, 2)
        f1, f2 = np.zeros((lay.n, lay.n)), np.zeros((lay.n, lay.n))
        mdl._fill_dynamics(f1, lay.offsets, c_ns, f_n, w_ie, w_en, vel, mav, beta, mk_rate)
        mdl.fill_dynamics_np(f2, lay.offsets.tolist(), c_ns, f_n, w_ie, w_en, vel, mav, beta, mk_rate)
        assert np.array_equal(f1, f2)
        h1, h2 = np.zeros((lay.n_meas, lay.n)), np.zeros((lay.n_meas, lay.n))
        mdl._fill_h(h1, lay.offsets, c_ns, c_nm, w_l, w_ns, a_m)
        mdl.fill_h_np(h2, lay.offsets.tolist(), c_ns, c_nm, w_l, w_ns, a_m)
        assert np.array_equal(h1, h2)


def test_the_reference_loops_scalar_helpers_equal_the_kernels():
    """The reference loop's rotations, lookups and navigation step in Python floats against the kernels
    (math's sin/cos/atan2 may differ from numpy's by an ulp: 1e-15)."""
    from logtools import strapdown as sd

    rng = np.random.default_rng(3)
    ts = np.sort(rng.uniform(0.0, 100.0, 50))
    for scale in (1e-10, 1e-4, 0.3, 2.0):
        for _ in range(50):
            q, rv = rng.normal(size=4), rng.normal(size=3) * scale
            qn = q / np.linalg.norm(q)
            assert np.array_equal(kfm._dcm(q), kfm._dcm_np(q))
            assert np.allclose(kfm._q_left_rotvec(rv, q), kfm._q_left_rotvec_np(rv, q), rtol=0, atol=1e-15)
            assert np.allclose(mdl.exp_so3(rv), mdl.exp_so3_np(rv), rtol=0, atol=1e-15)
            assert np.allclose(kfm._rotvec_nb(qn), kfm._rotvec_np(qn), rtol=1e-14, atol=1e-15)
            m = mdl.exp_so3(rv)
            assert np.allclose(mdl.rotvec_small(m), mdl.rotvec_small_np(m), rtol=1e-14, atol=1e-15)
            a, b = rng.normal(size=3), rng.normal(size=3)
            assert np.array_equal(kfm._cross3(a, b), kfm._cross3_np(a, b))
            t = float(rng.uniform(-10.0, 110.0))
            assert kfm._index(ts, t) == kfm._index_np(ts, t)
            llh = np.array([rng.uniform(-1.4, 1.4), rng.uniform(-3.0, 3.0), rng.uniform(-100.0, 9000.0)])
            v, dv = rng.normal(size=3) * 30.0, rng.normal(size=3) * 0.2
            dq = np.r_[1.0, rv * 0.5]
            dq /= np.linalg.norm(dq)
            out1 = (np.empty(4), np.empty(3), np.empty(3))
            out2 = (np.empty(4), np.empty(3), np.empty(3))
            sd.nav_step(qn, v, llh, dq, dv, 0.01, *out1)
            sd.nav_step_np(qn, v, llh, dq, dv, 0.01, *out2)
            for o1, o2 in zip(out1, out2):
                assert np.allclose(o1, o2, rtol=1e-15, atol=1e-15)
        # the forms worked out for every epoch or segment before the reference loop: its scalar helpers'
        # numbers bit for bit
        qs = rng.normal(size=(40, 4)) * np.r_[1.0, scale, scale, scale]
        rvs = rng.normal(size=(40, 3)) * scale
        qns = qs / np.linalg.norm(qs, axis=1)[:, None]
        turns, rots, dcms = kfm._exp_so3_many(rvs), kfm._rotvec_many(qns), kfm.dcm_from_quat(qs)
        for k in range(40):
            assert np.array_equal(turns[k], mdl.exp_so3_np(rvs[k]))
            assert np.array_equal(rots[k], kfm._rotvec_np(qns[k]))
            assert np.array_equal(dcms[k], kfm._dcm_np(qs[k]))


@pytest.mark.parametrize("n,m,predict", [(18, 6, True), (21, 3, True), (12, 6, False)])
def test_the_filter_loops_workspace_step_equals_the_allocating_one_bit_for_bit(n, m, predict):
    """kf_step_ws with one set of work arrays through consecutive steps (the compiled loop's: made once per
    run) against kf_step_nb (fresh ones every call), and the discretisation into work arrays against the
    allocating one: the same numbers to the bit, the prediction included (no step's leftovers in the next)."""
    from logtools.alignment import model as mdl

    rng = np.random.default_rng(n + m)
    a = rng.normal(size=(n, n))
    P = a @ a.T + n * np.eye(n)
    x, z = rng.normal(size=n), rng.normal(size=m)
    H = np.where(rng.random((m, n)) < 0.5, rng.normal(size=(m, n)), 0.0)
    r = rng.uniform(0.5, 2.0, m)
    f = np.where(rng.random((n, n)) < 0.3, rng.normal(size=(n, n)), 0.0)
    qc = rng.uniform(1e-6, 1e-3, n)
    phi1, qd1, phi2, qd2 = (np.empty((n, n)) for _ in range(4))
    ws = kfm.kf_workspace(n, m)
    mdl._discretise(f, qc, 0.05, phi1, qd1)
    mdl._discretise_ws(f, qc, 0.05, phi2, qd2, mdl.discretise_workspace(n))
    assert np.array_equal(phi1, phi2) and np.array_equal(qd1, qd2)
    phi, qd = (phi1, qd1) if predict else (np.zeros((0, 0)), np.zeros((0, 0)))
    x1, p1, e1, x2, p2, e2 = x.copy(), P.copy(), np.zeros(m), x.copy(), P.copy(), np.zeros(m)
    for _ in range(3):  # (the work arrays' leftovers from a step must not leak into the next)
        nis1 = kfm.kf_step_nb(x1, p1, phi, qd, z, H, r, e1)
        nis2 = kfm.kf_step_ws(x2, p2, phi, qd, z, H, r, e2, ws)
        assert nis1 == nis2 and np.array_equal(x1, x2) and np.array_equal(p1, p2) and np.array_equal(e1, e2)


def test_the_masters_samples_at_every_epoch_at_once_are_its_samples_one_by_one():
    """MasterSeries.sample_epochs (the reference loop's master where the delay is not a state) against
    sample() and usable() at each instant, bit for bit: inside, beyond both ends (clamped fractions), on a
    stamp, with invalid samples and the gyro on its own stamps."""
    rng = np.random.default_rng(11)
    t = np.cumsum(rng.uniform(0.01, 0.03, 300))
    q = rng.normal(size=(300, 4))
    valid = rng.random(300) > 0.1
    w_t = np.cumsum(rng.uniform(0.002, 0.006, 1500))
    ms = kfm.MasterSeries(t, q, rng.normal(size=(300, 3)), rng.normal(size=(300, 3)), rng.normal(size=(1500, 3)),
                          valid=valid, w_t_s=w_t)
    at = np.r_[t[0] - 0.5, rng.uniform(t[0], t[-1], 200), t[37], t[-1] + 0.2]
    usable, cols = ms.sample_epochs(at)
    for k, tk in enumerate(at.tolist()):
        one = ms.sample(tk)
        assert usable[k] == ms.usable(tk)
        for a, b in zip(cols, one):
            assert np.array_equal(a[k], b)


@pytest.mark.parametrize("n,m,predict", [(18, 6, True), (24, 6, True), (12, 3, False)])
def test_the_reference_step_with_its_work_arrays_is_the_textbook_algebra(n, m, predict):
    """The reference loop's discretisation and update (numpy, work arrays made once, unit and R matrices
    added whole) give the numbers of the plain expressions, bit for bit (an added unit matrix adds zeros off
    the diagonal), and the compiled step's within rounding; an innovation covariance that is not positive
    definite takes the compiled loop's clamped factor in both."""
    from logtools.alignment import model as mdl

    rng = np.random.default_rng(7 * n + m)
    f = np.where(rng.random((n, n)) < 0.3, rng.normal(size=(n, n)), 0.0)
    qc, dt = rng.uniform(1e-6, 1e-3, n), 0.05
    phi, qd = np.empty((n, n)), np.empty((n, n))
    ws = mdl.discretise_workspace_np(qc)
    for _ in range(2):  # (the work arrays' leftovers must not leak into the next segment)
        mdl._discretise_np(f, qc, dt, phi, qd, ws)
        ft = f * dt
        want_phi = ft + 0.5 * (ft @ ft)
        want_phi[np.diag_indices(n)] += 1.0
        want_qd = (want_phi * qc) @ want_phi.T
        want_qd[np.diag_indices(n)] += qc
        assert np.array_equal(phi, want_phi) and np.array_equal(qd, 0.5 * dt * want_qd)
    a = rng.normal(size=(n, n))
    P = a @ a.T + n * np.eye(n)
    x, z = rng.normal(size=n), rng.normal(size=m)
    H = np.where(rng.random((m, n)) < 0.5, rng.normal(size=(m, n)), 0.0)
    ph, qd_ = (phi, qd) if predict else (np.zeros((0, 0)), np.zeros((0, 0)))
    r_pd = rng.uniform(0.5, 2.0, m)
    h_zero, r_zero = H.copy(), r_pd.copy()
    h_zero[-1], r_zero[-1] = 0.0, 0.0  # (a row that sees nothing, without noise: S singular)
    for H, r in ((H, r_pd), (h_zero, r_zero)):
        x1, p1, e1, x2, p2, e2 = x.copy(), P.copy(), np.zeros(m), x.copy(), P.copy(), np.zeros(m)
        nis1 = kfm.kf_step_np(x1, p1, ph, qd_, z, H, r, e1, (np.diag(r), np.eye(n)))
        if predict:
            px, pp = ph @ x, ph @ P @ ph.T + qd_
        else:
            px, pp = x.copy(), P.copy()
        e = z - H @ px
        s_ = H @ pp @ H.T + np.diag(r)
        assert np.array_equal(e1, e)
        if r[-1] > 0:  # the textbook Joseph update
            k = np.linalg.solve(s_, H @ pp).T
            ikh = np.eye(n) - k @ H
            assert np.allclose(x1, px + k @ e, rtol=1e-10, atol=1e-12)
            assert np.allclose(p1, ikh @ pp @ ikh.T + (k * r) @ k.T, rtol=1e-9, atol=1e-12)
        nis2 = kfm.kf_step_nb(x2, p2, ph, qd_, z, H, r, e2)
        assert nis1 == pytest.approx(nis2, rel=1e-9) and (nis1 > 1e200) == (r[-1] == 0)  # (1 / the 1e-300 pivot)
        assert np.isfinite(p1).all() and np.isfinite(x1).all()
        assert np.allclose(x1, x2, rtol=1e-9, atol=1e-12) and np.allclose(p1, p2, rtol=1e-9, atol=1e-9)


def test_discretise_matches_matrix_exponential_for_small_steps():
    from scipy.linalg import expm
    f = RNG.normal(size=(5, 5)) * 0.1
    phi, qd = mdl.discretise(f, np.ones(5), 0.01)
    assert np.allclose(phi, expm(f * 0.01), atol=1e-8)
    assert np.allclose(qd, qd.T) and np.all(np.linalg.eigvalsh(qd) > 0)


# ---- simulated S004 ship ------------------------------------------------------------------------
def _pair(**over):
    kw = dict(latency_s=0.0, seed=1)
    kw.update(over)
    p = sim.simulate(sim.scenario_config("ship", **kw))
    return p.master, p.slave.rebased(p.master.meta.t0_ns), p.truth


def _err_arcmin(res, truth):
    d = np.asarray(res.mounting_rpy_deg) - np.asarray(truth.mounting_rpy_deg)
    d = (d + 180.0) % 360.0 - 180.0
    return d * 60.0


def _within(err_arcmin, tol=(1.0, 1.0, 2.0)):
    return bool(np.all(np.abs(err_arcmin) < np.asarray(tol)))


def test_s004_ship_no_delay_accurate_and_quick():
    """(Its runtime is benchmarks/bench_alignment.py's S004 column, not a timed assertion here.)"""
    m, s, truth = _pair()
    res = run_alignment(m, s, filter="kf", match="vel+att")
    err = _err_arcmin(res, truth)
    # PSINS 21-state filter on this case: 0.12'/0.04'/0.02', ~12 s of computing
    assert np.all(np.abs(err) < [0.12, 0.04, 0.02]), err
    assert res.converged_s is not None and res.converged_s < 5.0
    # error history within 1' (roll/pitch) and 2' (yaw) after 3 s
    i = res.history_names.index("mount_roll_deg")
    t = res.history_t_s - res.history_t_s[0]
    e_hist = (res.history_x[:, i:i + 3] - np.asarray(truth.mounting_rpy_deg)) * 60.0
    assert np.all(np.abs(e_hist[t >= 3.0]) < [1.0, 1.0, 2.0])
    assert res.accel_bias_mg == pytest.approx(truth.slave_accel_bias_mg, abs=0.02)
    assert all(res.observability.values())
    assert res.residual_rms["vel_m_s"] < 0.005 and res.residual_rms["att_deg"] < 0.002
    assert len(res.history_t_s) <= 2001 and res.history_x.shape == res.history_sigma.shape


def test_s004_ship_100ms_delay_kf_delay_recovers_delay_and_mounting():
    m, s, truth = _pair(latency_s=0.1)
    # the delay left in spoils the plain filter (as in S004 Fig. 2 / PSINS) ...
    plain = run_alignment(m, s, filter="kf", options=AlignmentOptions(recalibrate_noise=False))
    assert not _within(_err_arcmin(plain, truth))
    assert plain.residual_rms["nis_mean"] > 100 * plain.residual_rms["nis_dof"]
    # ... the noise re-estimated from its residuals keeps it near, but far worse than with the delay state
    robust = run_alignment(m, s, filter="kf")
    assert any("re-estimated" in n for n in robust.notes)
    res = run_alignment(m, s, filter="kf-delay")  # delay state started from the rate magnitudes
    assert np.linalg.norm(_err_arcmin(robust, truth)) > 20 * np.linalg.norm(_err_arcmin(res, truth))
    assert res.delay_s == pytest.approx(0.1, abs=0.002)
    assert res.delay_sigma_s < 0.002
    assert _within(_err_arcmin(res, truth), (0.1, 0.1, 0.1))
    pure = run_alignment(m, s, filter="kf-delay", options=AlignmentOptions(delay_s=0.0))  # S004's augmentation alone, from 0
    assert pure.delay_s == pytest.approx(0.1, abs=0.002)
    assert _within(_err_arcmin(pure, truth), (0.1, 0.1, 0.1))
    split = run_alignment(m, s, filter="kf-split", options=AlignmentOptions(delay_s=0.08))
    assert split.delay_s == pytest.approx(0.1, abs=0.002)
    assert _within(_err_arcmin(split, truth), (0.1, 0.1, 0.1))


def test_nees_of_mounting_over_seeds_is_consistent():
    nees = []
    for seed in range(5):
        m, s, truth = _pair(seed=10 + seed, duration_s=60.0)
        res = run_alignment(m, s)
        e = _err_arcmin(res, truth) / 60.0
        nees.append(float(np.sum((e / np.asarray(res.mounting_sigma_deg)) ** 2)))
    k = 3 * len(nees)
    lo, hi = chi2.ppf(0.005, k) / len(nees), chi2.ppf(0.995, k) / len(nees)
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi, nees)


@pytest.mark.parametrize("mount", [(1.5, -2.0, 170.0), (25.0, -35.0, 120.0)])
def test_large_mounting_recovered(mount):
    m, s, truth = _pair(mount_rpy_deg=mount, slave_nav=False, duration_s=60.0)
    res = run_alignment(m, s)  # coarse mounting from the angular rates (Kabsch), then the filter
    assert _within(_err_arcmin(res, truth)), _err_arcmin(res, truth)


def test_no_manoeuvre_flags_yaw_mounting_not_observable():
    m, s, truth = _pair(sway_amp_deg=(0.0, 0.0, 0.0), heave_amp_m=0.0, speed_var_m_s=0.0, duration_s=60.0)
    res = run_alignment(m, s)
    assert res.observability["mounting_yaw"] is False
    assert res.observability["mounting_roll"] is True
    assert any("mounting_yaw" in n for n in res.notes)
    assert res.mounting_sigma_deg[2] > 10 * res.mounting_sigma_deg[0]
    assert res.observability["accel_bias_x"] is False  # horizontal accel bias vs tilt: no rotation, no split


def test_smoother_and_other_matches_run():
    m, s, truth = _pair(duration_s=60.0)
    fwd = run_alignment(m, s)
    sm = run_alignment(m, s, smoother=True)
    assert _within(_err_arcmin(sm, truth), (0.2, 0.2, 0.2))
    assert np.all(np.asarray(sm.mounting_sigma_deg) <= np.asarray(fwd.mounting_sigma_deg) * 1.5)
    att = run_alignment(m, s, match="att")
    assert _within(_err_arcmin(att, truth))
    assert np.all(np.isnan(att.accel_bias_mg))
    vel = run_alignment(m, s, match="vel")
    assert np.isfinite(vel.mounting_rpy_deg).all() and "vel_n_m_s" in vel.residual_names


@pytest.mark.parametrize("flt,latency,kw", [("hinf", 0.0, {}), ("ahinf", 0.0, {}),
                                            ("ahinf", 0.1, {"delay_state": True})])
def test_hinf_filters_run_on_ship(flt, latency, kw):
    pytest.importorskip("logtools.alignment.hinf")
    m, s, truth = _pair(duration_s=60.0, latency_s=latency)
    res = run_alignment(m, s, filter=flt, options=AlignmentOptions(**kw))
    assert _within(_err_arcmin(res, truth)), _err_arcmin(res, truth)
    if latency:
        assert res.delay_s == pytest.approx(latency, abs=0.002)


def test_errors_are_one_line_analysis_errors():
    m, s, truth = _pair(duration_s=20.0)
    with pytest.raises(AnalysisError, match="no time overlap"):
        run_alignment(m, s.with_meta(t0_ns=s.meta.t0_ns + 10**12))  # the slave 1000 s later
    no_imu = type(s)(imu=s.imu.iloc[:0], nav=s.nav, meta=s.meta)
    with pytest.raises(AnalysisError, match="slave's IMU"):
        run_alignment(m, no_imu)
    no_att = type(m)(imu=m.imu, nav=m.nav.drop(columns=["quat_w", "quat_x", "quat_y", "quat_z"]), meta=m.meta)
    with pytest.raises(AnalysisError, match="attitude"):
        run_alignment(no_att, s, match="att")
    with pytest.raises(AnalysisError, match="filter"):
        run_alignment(m, s, filter="magic")
    static = type(s)(imu=s.imu * 0 + 1.0, nav=s.nav, meta=s.meta)
    with pytest.raises(AnalysisError, match="no motion"):
        run_alignment(m, static)


@pytest.mark.parametrize("kw,latency,gaps", [({}, 0.0, ()), ({"filter": "kf-delay", "smoother": True}, 0.1, ()),
                                             ({"match": "att", "flexure": True}, 0.0, ()),
                                             ({}, 0.0, ((8.0, 3.0),))])
def test_compiled_loop_equals_python_reference_loop(kw, latency, gaps):
    m, s, truth = _pair(latency_s=latency, duration_s=20.0, slave_gaps_s=gaps)
    top = {k: kw[k] for k in ("filter", "smoother", "match") if k in kw}
    opts = AlignmentOptions(**{k: v for k, v in kw.items() if k not in top})
    fast = run_alignment(m, s, **top, options=opts)
    # the reference: the Python loop for the KF kinds too (every pass of the run)
    ref = run_alignment(m, s, **top, options=opts, config=replace(CONFIG, compiled_kf=False))
    assert np.allclose(fast.history_x, ref.history_x, rtol=1e-9, atol=1e-12)
    assert np.allclose(fast.history_sigma, ref.history_sigma, rtol=1e-9, atol=1e-12)
    assert np.allclose(fast.mounting_rpy_deg, ref.mounting_rpy_deg, rtol=1e-12, atol=1e-12)


def test_master_attitude_reset_and_frozen_start_are_handled():
    """An EKF that outputs identity until it starts, and a 30 deg yaw jump mid-run (EKF yaw reset)."""
    from logtools.conventions import quat_mul, quat_from_euler
    m, s, truth = _pair(duration_s=60.0)
    nav = m.nav.copy()
    t = nav.index.to_numpy()
    q = nav[["quat_w", "quat_x", "quat_y", "quat_z"]].to_numpy().copy()
    early = t < 5.0
    q[early] = [1.0, 0.0, 0.0, 0.0]
    nav.loc[early, ["vel_n_m_s", "vel_e_m_s", "vel_d_m_s"]] = 0.0
    # after 30 s the master's yaw jumps by 30 deg (a reset to another heading)
    late = t >= 30.0
    q[late] = quat_mul(quat_from_euler(np.radians([0.0, 0.0, 30.0])), q[late])
    nav[["quat_w", "quat_x", "quat_y", "quat_z"]] = q
    bad = type(m)(imu=m.imu, nav=nav, meta=m.meta)
    res = run_alignment(bad, s)
    assert res.history_t_s[0] >= 5.0  # started on the first usable master sample
    assert any("jumped 1 time" in n for n in res.notes), res.notes
    # roll and pitch of the mounting survive the reset (the yaw after it is the new master's)
    assert np.all(np.abs(_err_arcmin(res, truth)[:2]) < 1.0), _err_arcmin(res, truth)


@pytest.mark.parametrize("scenario", ["vehicle", "ship"])
def test_gaps_in_the_slave_imu_restart_its_navigation(scenario):
    """A slave whose IMU stops for 20 s and for 5 s (a logger's dropout): integrating across the gap
    (the increments taken as linear through it) put the mounting 3-25 deg off, not converged. The
    slave's navigation now restarts from the master after each gap and the mounting comes out as
    without gaps (within 1 arcmin)."""
    cfg = sim.scenario_config(scenario, seed=5, latency_s=0.0, drift_ppm=0.0, mount_rpy_deg=(-79.8, -170.9, -26.1),
                              slave_imu_rate_hz=60.0, slave_gaps_s=((30.0, 20.0), (70.0, 5.0)))
    p = sim.simulate(cfg)
    res = run_alignment(p.master, p.slave.rebased(p.master.meta.t0_ns))
    assert any("2 gap(s) in the slave's IMU" in n for n in res.notes), res.notes
    assert res.converged_s is not None
    from logtools.conventions import dcm_from_euler, rotvec_from_quat, quat_from_dcm
    e = dcm_from_euler(np.radians(res.mounting_rpy_deg)) @ dcm_from_euler(np.radians(cfg.mount_rpy_deg)).T
    err_arcmin = np.degrees(rotvec_from_quat(quat_from_dcm(e))) * 60.0  # (Euler angles past 90 deg pitch
    assert np.all(np.abs(err_arcmin) < 1.0), err_arcmin                #  have two forms)


REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["arducopter_log0036.bin", "arduplane_box_pilot.BIN"])
def test_real_ardupilot_imu2_aligned_to_imu_ekf(name):
    path = REAL / name
    if not path.exists():
        pytest.skip("../shared/realdata absent")
    from parsers import load
    m = load(f"{path}::imu=IMU,nav=NKF1")
    s = load(f"{path}::imu=IMU2,nav=NKF6").rebased(m.meta.t0_ns)
    res = run_alignment(m, s, filter="kf-delay")
    # the two IMUs sit on the same board: mounting near zero, with a sigma; biases of MEMS size
    assert np.all(np.abs(res.mounting_rpy_deg) < 2.0), res.mounting_rpy_deg
    assert np.all(np.asarray(res.mounting_sigma_deg) > 0)
    assert np.all(np.abs(res.gyro_bias_dph) < 3600.0) and np.all(np.abs(res.accel_bias_mg) < 100.0)
    assert abs(res.delay_s) < 0.05  # the EKF output and IMU2 are within tens of ms


def test_lever_arm_estimated_and_flexure_states_keep_the_filter_consistent():
    m, s, truth = _pair(lever_arm_m=(2.0, -1.0, 0.5), duration_s=60.0)
    res = run_alignment(m, s, options=AlignmentOptions(estimate_lever_arm=True))
    i = res.history_names.index("lever_arm_x_m")
    lev, sig = res.history_x[-1, i:i + 3], res.history_sigma[-1, i:i + 3]
    assert np.all(np.abs(lev - [2.0, -1.0, 0.5]) < np.maximum(4 * sig, 0.01)), (lev, sig)
    assert np.allclose(res.lever_arm_m, lev) and np.all(np.asarray(res.lever_arm_sigma_m) >= sig - 1e-12)
    given = run_alignment(m, s, options=AlignmentOptions(lever_arm_m=(2.0, -1.0, 0.5)))  # known: reported as given, no states
    assert given.lever_arm_m == (2.0, -1.0, 0.5) and given.lever_arm_sigma_m is None
    assert "lever_arm_x_m" not in given.history_names
    assert run_alignment(m, s).lever_arm_m is None  # not modelled
    assert _within(_err_arcmin(res, truth), (0.2, 0.2, 0.2))
    # flexure (S000 eq 8) in the data: without flexure states the residuals blow up, with them the
    # filter is consistent and the mounting within a few sigma
    m, s, truth = _pair(flexure=True, duration_s=60.0)
    rigid = run_alignment(m, s, options=AlignmentOptions(recalibrate_noise=False))
    flex = run_alignment(m, s, options=AlignmentOptions(flexure=True, flex_beta=2.0))
    assert rigid.residual_rms["nis_mean"] > 50 * rigid.residual_rms["nis_dof"]
    assert flex.residual_rms["nis_mean"] < 2 * flex.residual_rms["nis_dof"]
    z = _err_arcmin(flex, truth) / 60.0 / np.asarray(flex.mounting_sigma_deg)
    assert np.all(np.abs(z) < 4.0), z


def test_slave_with_its_own_time_origin_is_put_on_the_masters():
    """A slave InsLog whose relative times start at its own first sample (t0_ns differs from the
    master's): run_alignment puts it on the master's time origin itself. Compared as they were, the
    times were off by the slave's start-up phase (up to a sample) and a 60 Hz slave's mounting came out
    0.86 arcmin off at sigma 0.012."""
    p = sim.simulate(sim.scenario_config("aircraft", seed=5, latency_s=0.0, drift_ppm=0.0,
                                         mount_rpy_deg=(0.3, 0.4, -1.0), slave_imu_rate_hz=60.0, duration_s=60.0))
    assert p.slave.meta.t0_ns != p.master.meta.t0_ns
    own = run_alignment(p.master, p.slave)
    put = run_alignment(p.master, p.slave.rebased(p.master.meta.t0_ns))
    assert np.allclose(own.mounting_rpy_deg, put.mounting_rpy_deg, rtol=0, atol=1e-9)
    assert np.all(np.abs(_err_arcmin(put, p.truth)) < 0.2), _err_arcmin(put, p.truth)


@pytest.mark.parametrize("mount", [(180.0, 0.0, 0.0), (-80.0, 0.0, 0.0), (0.0, -170.0, 0.0)])
def test_attitude_only_matching_with_a_rolled_mounting_does_not_diverge(mount):
    """Attitude matching alone, aircraft, tight attitude noise (1.8 arcsec, what a 200 Hz master nav gives):
    with the first-estimate Jacobian the straight start drifted and the filter diverged (residuals of
    180 deg, mounting sigma 50 arcmin after the noise re-estimation) for mountings rolled past ~80 deg.
    The mounting's Jacobian is now taken at the running slave attitude for attitude-only matching."""
    cfg = sim.scenario_config("aircraft", seed=5, latency_s=0.0, drift_ppm=0.0, mount_rpy_deg=mount,
                              slave_imu_rate_hz=200.0, master_imu_rate_hz=400.0, master_nav_rate_hz=200.0,
                              duration_s=40.0)
    p = sim.simulate(cfg)
    res = run_alignment(p.master, p.slave, match="att", options=AlignmentOptions(recalibrate_noise=False, r_att_arcsec=1.83, update_hz=20.0))
    assert np.nanmax(np.linalg.norm(res.residuals, axis=1)) < 0.01  # deg
    from logtools.conventions import dcm_from_euler, quat_from_dcm, rotvec_from_quat
    e = dcm_from_euler(np.radians(res.mounting_rpy_deg)) @ dcm_from_euler(np.radians(mount)).T
    assert np.all(np.abs(np.degrees(rotvec_from_quat(quat_from_dcm(e))) * 60.0) < 0.5)


#: a multirotor whose slave flexes (with flexure=True) or not: the flexure="auto" tests' scenario
_FLEXING_MULTIROTOR = dict(latency_s=0.0, drift_ppm=0.0, mount_rpy_deg=(122.8, 135.2, -127.5),
                           master_imu_rate_hz=163.6, slave_imu_rate_hz=391.8, slave_nav_rate_hz=100.0,
                           lever_arm_m=(-0.17, 0.12, 1.21), slave_vel_noise_m_s=0.005, slave_att_noise_deg=0.01,
                           speed_m_s=4.0, turn_amp_deg=37.0, turn_period_s=44.3)


def test_flexure_auto_adds_the_states_where_the_residuals_call_for_them():
    """flexure="auto" (what the CLI passes when the latency fit found no flexure model: a multirotor's fast
    motion pins the latency without it): a flexing slave's residuals far beyond the noise model bring the
    flexure states in (the mounting was 1.2 arcmin off at sigma 0.18 without them); a rigid one is left
    as it was."""
    kw = dict(duration_s=90.0, **_FLEXING_MULTIROTOR)
    p = sim.simulate(sim.scenario_config("multirotor", seed=62015, flexure=True, **kw))
    rigid = run_alignment(p.master, p.slave, options=AlignmentOptions(estimate_lever_arm=True))
    auto = run_alignment(p.master, p.slave, options=AlignmentOptions(estimate_lever_arm=True, flexure="auto"))
    from logtools.conventions import dcm_from_euler

    def z(r):  # the rotation between estimate and truth over the largest sigma (Euler angles past 90 deg pitch)
        d = dcm_from_euler(np.radians(r.mounting_rpy_deg)).T @ dcm_from_euler(np.radians(p.truth.mounting_rpy_deg))
        return np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))) / max(r.mounting_sigma_deg)

    assert any(n.startswith("flexure states added") for n in auto.notes)
    assert z(rigid) > 3.0 and z(auto) < 2.5, (z(rigid), z(auto))
    p = sim.simulate(sim.scenario_config("multirotor", seed=62015, flexure=False, **kw))
    rigid = run_alignment(p.master, p.slave, options=AlignmentOptions(estimate_lever_arm=True))
    auto = run_alignment(p.master, p.slave, options=AlignmentOptions(estimate_lever_arm=True, flexure="auto"))
    assert not any("flexure" in n for n in auto.notes)
    assert auto.mounting_rpy_deg == rigid.mounting_rpy_deg


def test_a_lever_arm_that_absorbs_an_uncompensated_delay_is_called_implausible():
    """Velocity matching with the lever arm as states on a slave left 0.5 s late: the lever arm along the
    flight path takes the delay up (12 m on an aircraft); the result says so instead of reporting it
    plainly. The compensated pair has no such note."""
    kw = dict(seed=3, drift_ppm=0.0, duration_s=60.0, mount_rpy_deg=(10.0, 20.0, 30.0))
    late = sim.simulate(sim.scenario_config("aircraft", latency_s=0.5, **kw))
    res = run_alignment(late.master, late.slave, options=AlignmentOptions(estimate_lever_arm=True))
    assert np.linalg.norm(res.lever_arm_m) > 10.0
    assert any("far beyond its prior" in n for n in res.notes)
    ok = sim.simulate(sim.scenario_config("aircraft", latency_s=0.0, **kw))
    res = run_alignment(ok.master, ok.slave, options=AlignmentOptions(estimate_lever_arm=True))
    assert np.linalg.norm(res.lever_arm_m) < 0.1 and not any("far beyond" in n for n in res.notes)


def test_coarse_mounting_from_rates_and_specific_forces_when_a_car_turns_about_one_axis():
    """A car on a nearly level road turns about one axis: the rates alone do not fix the mounting (the
    second axis's rotation is below what the rate fit needs), and starting from a zero mounting a pitch of
    71 deg diverged (141 deg off, lever arm 84 m). The motion of the specific forces (speed changes along
    the track, centripetal across it) with the rates in one Wahba problem gives the start."""
    cfg = sim.scenario_config("vehicle", seed=66006, duration_s=300.0, latency_s=0.0, drift_ppm=0.0,
                              mount_rpy_deg=(-32.6, 70.9, 156.5), lever_arm_m=(-0.22, -1.14, 1.23),
                              slave_nav=False, speed_m_s=15.1, turn_amp_deg=23.0, turn_period_s=64.6,
                              climb_amp_deg=0.7, speed_var_m_s=3.0)
    p = sim.simulate(cfg)
    res = run_alignment(p.master, p.slave, options=AlignmentOptions(estimate_lever_arm=True))
    assert any("rates and specific forces together" in n for n in res.notes), res.notes
    from logtools.conventions import dcm_from_euler

    d = dcm_from_euler(np.radians(res.mounting_rpy_deg)).T @ dcm_from_euler(np.radians(cfg.mount_rpy_deg))
    err_arcmin = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))) * 60
    assert err_arcmin < 0.5 and err_arcmin / 60 < 3 * np.linalg.norm(res.mounting_sigma_deg), err_arcmin
    assert np.allclose(res.lever_arm_m, cfg.lever_arm_m, atol=0.1)


def test_coarse_mounting_of_a_master_that_logs_only_its_navigation_solution():
    """The same car with a master INS that logs its solution only (no IMU): the joint start needs the
    master's specific force, now C_bn (dv/dt - g) from its velocity and attitude. Without it the filter
    started from a zero mounting (a sweep's car: 77 arcmin off, measurement noise re-estimated to 6.6 m/s
    and 18 deg to hide the divergence)."""
    from logtools.conventions import dcm_from_euler
    from logtools.inslog import InsLog

    cfg = sim.scenario_config("vehicle", seed=66006, duration_s=300.0, latency_s=0.0, drift_ppm=0.0,
                              mount_rpy_deg=(-32.6, 70.9, 156.5), lever_arm_m=(-0.22, -1.14, 1.23),
                              slave_nav=False, speed_m_s=15.1, turn_amp_deg=23.0, turn_period_s=64.6,
                              climb_amp_deg=0.7, speed_var_m_s=3.0)
    p = sim.simulate(cfg)
    master = InsLog(imu=p.master.imu.iloc[:0], nav=p.master.nav, meta=p.master.meta)
    res = run_alignment(master, p.slave, options=AlignmentOptions(estimate_lever_arm=True))
    assert any("rates and specific forces together instead" in n for n in res.notes), res.notes
    d = dcm_from_euler(np.radians(res.mounting_rpy_deg)).T @ dcm_from_euler(np.radians(cfg.mount_rpy_deg))
    err_arcmin = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))) * 60
    assert err_arcmin < 1.0 and err_arcmin / 60 < 3 * np.linalg.norm(res.mounting_sigma_deg), err_arcmin


def test_coarse_mounting_weakly_determined_starts_from_the_joint_fit_with_a_wide_prior():
    """A ship that barely rolls or pitches (0.2 deg sway, yaw sway and heave along the same axis): rates and
    specific forces fix the mounting only weakly. Started from a zero mounting the filter diverged (38 deg off,
    z 26); from the weak joint fit with a 5 deg prior it stays within its sigma."""
    cfg = sim.scenario_config("ship", seed=830757919, duration_s=300.0, latency_s=0.0, drift_ppm=0.0,
                              mount_rpy_deg=(135.6, 44.2, 52.7), slave_nav=False, lever_arm_m=(0.11, -0.97, -0.03),
                              speed_var_m_s=0.21, sway_amp_deg=(0.2, 0.2, 3.0))
    p = sim.simulate(cfg)
    res = run_alignment(p.master, p.slave, options=AlignmentOptions(estimate_lever_arm=True))
    assert any("weakly determined" in n for n in res.notes), res.notes
    from logtools.conventions import dcm_from_euler

    d = dcm_from_euler(np.radians(res.mounting_rpy_deg)).T @ dcm_from_euler(np.radians(cfg.mount_rpy_deg))
    err_deg = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1)))
    assert err_deg < 0.5 and err_deg < 2.5 * np.linalg.norm(res.mounting_sigma_deg), (err_deg, res.mounting_sigma_deg)


def test_nav_only_master_rate_from_attitude_keeps_fast_motion_and_smooths_slow():
    """The lever arm's master rate of a master without a gyro, from its attitude at 100 Hz: a 1.5 Hz
    oscillation keeps its amplitude (a fixed +- 0.05 s difference took 4 % off it: a multirotor's
    mounting came out 2.5 arcmin off at a sigma of 0.37 arcmin), while a 0.08 Hz ship sway keeps the long
    span, whose rate is quieter for an attitude with noise."""
    from logtools.alignment.run import _rate_from_attitude
    from logtools.conventions import quat_from_euler

    t = np.arange(0.0, 60.0, 0.01)
    rng = np.random.default_rng(3)
    for f_hz, amp_deg, noise_deg in ((1.5, 10.0, 0.0), (0.08, 3.0, 0.002)):
        ang = np.radians(amp_deg) * np.sin(2 * np.pi * f_hz * t)
        eul = np.stack([ang, 0.5 * ang, np.zeros_like(t)], axis=1) + np.radians(noise_deg) * rng.standard_normal((len(t), 3))
        w = _rate_from_attitude(t, quat_from_euler(eul))
        mid = slice(100, -100)
        amp = np.sqrt(2.0) * np.std(w[mid, 0]) / (np.radians(amp_deg) * 2 * np.pi * f_hz)
        if noise_deg == 0.0:
            assert abs(amp - 1.0) < 2e-3  # the +- 0.05 s difference: 0.963
        else:
            # quieter than the +- one-sample difference's: the noise of the rate's roll-yaw axis (no motion)
            one = np.degrees(np.std(np.diff(np.unwrap(eul[:, 2]))[mid] / 0.01))
            assert np.degrees(np.std(w[mid, 2])) < 0.25 * one


def test_master_attitude_and_velocity_at_their_own_stamps_and_rates():
    """ATT at 10 Hz and GPS velocity at 5 Hz that never share a stamp (ArduPilot's ATT + GPS selector): each
    used at its own instant (the velocity's stamps, the attitude interpolated at them), not a failure."""
    import pandas as pd

    m, s, truth = _pair(duration_s=90.0)
    nav = m.nav
    t = nav.index.to_numpy()
    qc, vc = ["quat_w", "quat_x", "quat_y", "quat_z"], ["vel_n_m_s", "vel_e_m_s", "vel_d_m_s"]
    tq = np.arange(t[0] + 0.013, t[-1], 0.1)
    tv = np.arange(t[0] + 0.071, t[-1], 0.2)
    q = np.stack([np.interp(tq, t, nav[c].to_numpy()) for c in qc], -1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    v = np.stack([np.interp(tv, t, nav[c].to_numpy()) for c in vc], -1)
    both = pd.concat([pd.DataFrame(q, index=pd.Index(tq, name=nav.index.name), columns=qc),
                      pd.DataFrame(v, index=pd.Index(tv, name=nav.index.name), columns=vc)]).sort_index()
    assert len(np.intersect1d(tq, tv)) == 0
    split = type(m)(imu=m.imu, nav=both, meta=m.meta)
    res = run_alignment(split, s, match="vel+att")
    err = _err_arcmin(res, truth)
    assert _within(err, (1.0, 1.0, 2.0)), err
    sig = np.asarray(res.mounting_sigma_deg) * 60.0
    assert np.all(np.abs(err) < 3.0 * sig + 0.05), (err, sig)


def _rotation_arcmin(rpy_a, rpy_b) -> float:
    from logtools.conventions import dcm_from_euler
    d = dcm_from_euler(np.radians(rpy_a)).T @ dcm_from_euler(np.radians(rpy_b))
    return float(np.degrees(np.arccos(np.clip((np.trace(d) - 1.0) / 2.0, -1.0, 1.0))) * 60.0)


def test_board_errors_cover_a_markov_master_and_a_misaligned_accel_triad():
    """A consumer board's errors (issue 22): the master's attitude with a 0.12 deg first-order Markov error
    (50 s), the slave's accelerometer triad 1.2 deg off its gyro triad. The white-noise model puts the
    mounting tens of sigma off; with board_errors the states carry them, the truth is within 2 sigma and the
    accelerometer triad's misalignment is reported in a note."""
    p = sim.simulate(sim.scenario_config(
        "vehicle", duration_s=120.0, seed=3, mount_rpy_deg=(2.0, -3.0, 40.0), latency_s=0.0,
        slave_accel_misalign_rpy_deg=(0.9, -0.7, 0.4), master_att_markov_deg=0.12, master_att_markov_tau_s=50.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    z = {}
    for on in (False, True):
        res = run_alignment(m, s, filter="kf", match="vel+att", options=AlignmentOptions(board_errors=on))
        err = _rotation_arcmin(res.mounting_rpy_deg, p.truth.mounting_rpy_deg)
        z[on] = err / (np.linalg.norm(res.mounting_sigma_deg) * 60.0)
        assert any(n.startswith("slave accelerometer triad misalignment") for n in res.notes) == on
        assert ("master_att_err_d_arcmin" in res.history_names) == on
    assert z[False] > 5.0 and z[True] <= 2.0


def test_board_errors_on_a_navigation_grade_pair_cost_precision_not_coverage():
    """S004's ship has none of those errors: with board_errors the mounting's sigma grows (the master's
    attitude could be 0.1 deg off for all the filter knows) and the truth stays well within it."""
    m, s, truth = _pair()
    off = run_alignment(m, s, filter="kf", match="vel+att")
    on = run_alignment(m, s, filter="kf", match="vel+att", options=AlignmentOptions(board_errors=True))
    assert np.linalg.norm(on.mounting_sigma_deg) > 10 * np.linalg.norm(off.mounting_sigma_deg)
    assert _rotation_arcmin(on.mounting_rpy_deg, truth.mounting_rpy_deg) < 2.0 * np.linalg.norm(on.mounting_sigma_deg) * 60
    with pytest.raises(AnalysisError, match="board_errors"):
        AlignmentOptions(board_errors="maybe")
    # auto: the innovations of this navigation-grade pair are white, so the states stay out and the answer
    # is the off run's, to the bit
    auto = run_alignment(m, s, filter="kf", match="vel+att", options=AlignmentOptions(board_errors="auto"))
    assert auto.mounting_rpy_deg == off.mounting_rpy_deg and auto.mounting_sigma_deg == off.mounting_sigma_deg
    assert any(n.startswith("board error states not needed") for n in auto.notes)
    assert max(off.innovation_corr_epochs) < CONFIG.board_auto_corr_min


def test_board_errors_auto_adds_the_states_where_the_innovations_are_correlated(monkeypatch):
    """board_errors="auto" on the pair of the test above (a 0.12 deg Markov master error over 50 s, a
    misaligned accelerometer triad): the run without the states has innovations correlated over many
    epochs, so the states are added, the result is the on run's, and a note says why. Its two filters run
    on one preparation of the logs (the coarse mounting, the noise fit, the epochs: none of it depends on
    the board's states), and give what two runs preparing their own give, to the bit."""
    from logtools.alignment import run as run_mod

    p = sim.simulate(sim.scenario_config(
        "vehicle", duration_s=120.0, seed=3, mount_rpy_deg=(2.0, -3.0, 40.0), latency_s=0.0,
        slave_accel_misalign_rpy_deg=(0.9, -0.7, 0.4), master_att_markov_deg=0.12, master_att_markov_tau_s=50.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    off = run_alignment(m, s, filter="kf", match="vel+att", options=AlignmentOptions(board_errors=False))
    on = run_alignment(m, s, filter="kf", match="vel+att", options=AlignmentOptions(board_errors=True))
    calls = []
    prepare = run_mod._prepare
    monkeypatch.setattr(run_mod, "_prepare", lambda *a, **k: calls.append(1) or prepare(*a, **k))
    auto = run_alignment(m, s, filter="kf", match="vel+att", options=AlignmentOptions(board_errors="auto"))
    assert len(calls) == 1
    assert max(off.innovation_corr_epochs) > CONFIG.board_auto_corr_min
    assert auto.mounting_rpy_deg == on.mounting_rpy_deg and auto.mounting_sigma_deg == on.mounting_sigma_deg
    assert auto.notes[0].startswith("board error states added") and auto.notes[1:] == on.notes
    assert np.array_equal(auto.history_x, on.history_x) and np.array_equal(auto.residuals, on.residuals)
    assert auto.lever_arm_m == on.lever_arm_m and auto.gyro_bias_dph == on.gyro_bias_dph


def test_board_error_states_compiled_loop_equals_reference_loop_and_other_filters_run():
    p = sim.simulate(sim.scenario_config("ship", duration_s=40.0, seed=2, latency_s=0.0, master_att_markov_deg=0.1,
                                         slave_accel_misalign_rpy_deg=(0.5, 0.5, 0.5)))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    opts = AlignmentOptions(board_errors=True)
    a = run_alignment(m, s, match="vel+att", options=opts)
    b = run_alignment(m, s, match="vel+att", options=opts, config=replace(CONFIG, compiled_kf=False))
    assert np.allclose(a.mounting_rpy_deg, b.mounting_rpy_deg, atol=1e-9)
    assert np.allclose(a.mounting_sigma_deg, b.mounting_sigma_deg, rtol=1e-6)
    # the board's states as a result says: both with vel+att; the triad's misalignment alone with velocity
    # matching (no attitude matched, no master attitude error state), none without the option
    assert a.has_board_states and "master_att_err_n_arcmin" in a.history_names
    v = run_alignment(m, s, match="vel", options=opts)
    assert v.has_board_states and "master_att_err_n_arcmin" not in v.history_names
    assert not run_alignment(m, s, match="vel").has_board_states
    for kw in (dict(filter="hinf"), dict(filter="kf", smoother=True), dict(filter="kf-delay")):
        r = run_alignment(m, s, match="vel+att", options=opts, **kw)
        assert _rotation_arcmin(r.mounting_rpy_deg, p.truth.mounting_rpy_deg) < 3.0 * np.linalg.norm(
            r.mounting_sigma_deg) * 60.0, kw


def test_board_error_states_on_a_ship_that_barely_rolls_keep_their_sigma_honest():
    """A ship that turns about its vertical only, IMU-only slave, --board-errors on, no board error in the
    data: the accelerometer misalignment about the turn axis is the heading error there. With the error
    dynamics at the running slave attitude, feedback along that undetermined direction rotated F against H
    and the mounting came out 37' off at a 10' sigma; at the first estimate (AlignmentConfig.dynamics_fej,
    as H) the truth is within 2 sigma."""
    p = sim.simulate(sim.scenario_config(
        "ship", seed=1546029218, duration_s=300.0, sway_amp_deg=(0.2, 0.2, 3.0), turn_amp_deg=17.7,
        speed_var_m_s=0.12, master_imu_rate_hz=200.0, slave_imu_rate_hz=200.0, slave_nav=False, latency_s=0.0,
        drift_ppm=0.0, mount_rpy_deg=(-9.34, -10.79, 4.80), lever_arm_m=(-1.21, 1.71, -0.08),
        slave_gyro_bias_dph=(0.03,) * 3, slave_accel_bias_mg=(0.3,) * 3, slave_gyro_arw_dpsh=0.006,
        slave_accel_vrw_ug_rthz=60.0, slave_vel_noise_m_s=0.015))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    opts = AlignmentOptions(board_errors=True, estimate_lever_arm=True)
    z = {}
    for fej in (True, False):
        r = run_alignment(m, s, options=opts, config=replace(CONFIG, dynamics_fej=fej))
        z[fej] = _rotation_arcmin(r.mounting_rpy_deg, p.truth.mounting_rpy_deg) / (
            np.linalg.norm(r.mounting_sigma_deg) * 60.0)
    assert z[True] <= 2.0 and z[False] > 3.0, z


def test_coarse_fit_covariance_matches_the_scatter_and_the_accel_triad_shift():
    """The coarse start's error covariance (run._wahba_covariance), the mounting prior it sets: over 300
    noise draws of a one-axis motion (rates about z, specific forces in the x-y plane, AR(1) noise
    correlated over ~10 samples), the fitted rotations' scatter is what the covariance says (each axis
    within 20 %), and an accelerometer triad misaligned by a known alpha moves the fit by d_force @ alpha."""
    from scipy.signal import lfilter

    from logtools.alignment.run import _wahba_covariance
    from logtools.conventions import dcm_from_euler, dcm_from_rotvec, rotvec_from_dcm, wahba

    rng = np.random.default_rng(11)
    n = 3000
    t = np.arange(n) * 0.02
    w_m = np.stack([0.003 * np.sin(0.9 * t), 0.002 * np.cos(0.7 * t), 0.05 * np.sin(0.3 * t)], 1)
    f_m = np.stack([0.3 * np.sin(0.2 * t + 1), 0.2 * np.cos(0.25 * t), 0.02 * np.sin(0.5 * t)], 1)
    r_true = dcm_from_euler(np.radians([20.0, -35.0, 110.0]))

    def ar1(scale):  # correlated over ~10 samples
        return lfilter([1.0], [1.0, -0.8], rng.standard_normal((n, 3)) * scale, axis=0)

    def fit(alpha=np.zeros(3), noise=True):
        w_s = w_m @ r_true.T + (ar1(2e-4) if noise else 0.0)
        f_s = (f_m @ r_true.T) @ dcm_from_rotvec(alpha).T + (ar1(5e-3) if noise else 0.0)
        wm, ws, fm, fs = (x - x.mean(0) for x in (w_m, w_s, f_m, f_s))
        pw, pf = np.trace(wm.T @ wm), np.trace(fm.T @ fm)
        r = wahba(ws.T @ wm / pw + fs.T @ fm / pf)[0]
        mu = -rotvec_from_dcm(r_true @ r.T)  # R = (I - [mu x]) R_hat
        return mu, r, (wm, ws, fm, fs, pw, pf)

    mus, covs = [], []
    for _ in range(300):
        mu, r, (wm, ws, fm, fs, pw, pf) = fit()
        cov, _ = _wahba_covariance(r, [(1.0 / pw, wm, ws, False), (1.0 / pf, fm, fs, True)])
        mus.append(mu)
        covs.append(cov)
    emp = np.std(np.array(mus), axis=0)
    said = np.sqrt(np.diag(np.mean(covs, axis=0)))
    assert np.all(np.abs(emp / said - 1.0) < 0.2), (emp, said)
    alpha = np.radians([0.3, -0.8, 1.5])
    mu_a, r_a, (wm, ws, fm, fs, pw, pf) = fit(alpha, noise=False)
    _, d_force = _wahba_covariance(r_a, [(1.0 / pw, wm, ws, False), (1.0 / pf, fm, fs, True)])
    assert np.allclose(mu_a, d_force @ alpha, atol=0.03 * np.linalg.norm(alpha)), (mu_a, d_force @ alpha)


def test_board_errors_leave_an_undetermined_mounting_axis_at_its_prior():
    """A ship that does not move: the yaw mounting is not determined. With the board's states the slave's
    initial attitude carries the master's output frame off its IMU's (config.board_start_att_deg), so the
    attitude matching (phi - C_ns mu) no longer lends the mounting half the initial attitude's information:
    its yaw sigma stays near its 1 deg prior. Without that term (the premise) it fell to about 1/sqrt(2)."""
    import dataclasses

    m, s, _ = _pair(sway_amp_deg=(0.0, 0.0, 0.0), heave_amp_m=0.0, speed_var_m_s=0.0, duration_s=60.0)
    opts = AlignmentOptions(board_errors=True)
    res = run_alignment(m, s, options=opts)
    assert res.observability["mounting_yaw"] is False
    assert res.mounting_sigma_deg[2] > 0.85, res.mounting_sigma_deg
    tied = run_alignment(m, s, options=opts, config=dataclasses.replace(CONFIG, board_start_att_deg=0.0))
    assert tied.mounting_sigma_deg[2] < 0.75, tied.mounting_sigma_deg


@pytest.mark.parametrize("mount", [(20.0, 90.0, -35.0), (30.0, -90.0, 10.0)])
def test_a_mounting_at_the_gimbal_lock_is_determined_on_all_three_axes(mount):
    """A slave pitched +-90 deg (the roll and yaw axes coincide): the Euler roll and yaw sigmas are singular
    there (roll and yaw were nulled as "not observable with this motion" while the mounting was right);
    observability is judged on the rotation, the mounting reported as the canonical triple (roll 0, yaw the
    two's sum, as scipy's as_euler) with finite, small sigmas, the exact rotation as its quaternion."""
    from logtools.conventions import dcm_from_euler, dcm_from_quat
    from pipelines.report import alignment_section

    m, s, truth = _pair(mount_rpy_deg=mount, slave_nav=False, duration_s=60.0)
    res = run_alignment(m, s)
    sig = np.asarray(res.mounting_sigma_deg)
    assert np.all(np.isfinite(sig)) and sig.max() < 0.05, sig
    assert all(res.observability[f"mounting_{ax}"] for ax in ("roll", "pitch", "yaw")), res.observability
    assert not any("not observable" in n for n in res.notes), res.notes
    assert res.mounting_rpy_deg[0] == 0.0 and res.mounting_rpy_deg[1] == np.sign(mount[1]) * 90.0
    assert any("gimbal lock" in n for n in res.notes)
    tol = max(3.0 * sig.max() * 60.0, 0.5)  # arcmin
    assert _rotation_arcmin(res.mounting_rpy_deg, truth.mounting_rpy_deg) < tol
    q_err = dcm_from_quat(np.asarray(res.mounting_quat_wxyz)).T @ dcm_from_euler(np.radians(truth.mounting_rpy_deg))
    assert np.degrees(np.arccos(np.clip((np.trace(q_err) - 1.0) / 2.0, -1.0, 1.0))) * 60.0 < tol
    sec = alignment_section(res)
    assert None not in sec["mounting_rpy_deg"] and "mounting_not_determined" not in sec
    assert len(sec["mounting_quat_wxyz"]) == 4


@pytest.mark.parametrize("scenario", ["vehicle", "aircraft"])
def test_a_large_gyro_bias_is_seeded_from_the_rates_and_the_mounting_stays_right(scenario):
    """A MEMS turn-on bias of 1 deg/s (3600 deg/h) on a slave whose noise says navigation grade (bias prior
    2-3 deg/h): from a zero bias the filter never got there, and the mounting came out 0.8-3.3 deg off at z
    up to 14 with a lever arm of 22-80 m (sweep F3, C08/H04). The mean rate difference (the latency's
    bias_diff_dph, slave frame) seeds the bias states; the mounting is then as right as without the bias."""
    b = (3600.0, -3600.0, 3600.0)
    p = sim.simulate(sim.scenario_config(scenario, duration_s=120.0, mount_rpy_deg=(3.0, -2.0, 45.0),
                                         latency_s=0.0, seed=0, slave_gyro_bias_dph=b))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    opts = AlignmentOptions(estimate_lever_arm=True, flexure="auto")
    res = run_alignment(m, s, options=opts)
    assert any("slave gyro bias measured before the filter" in n for n in res.notes), res.notes
    err = _err_arcmin(res, p.truth) / 60.0
    assert np.all(np.abs(err) < 0.01) and np.all(np.abs(err) < 3.0 * np.asarray(res.mounting_sigma_deg)), err
    assert np.linalg.norm(res.lever_arm_m) < 0.1, res.lever_arm_m
    # the bias reported is the seed plus the states, in the slave's frame, with the truth's signs
    assert res.gyro_bias_dph == pytest.approx(b, abs=1.0)
    assert not any("far beyond its prior" in n or "larger than the noise model" in n for n in res.notes), res.notes
    # the premise: without the seed the same run is confidently wrong
    off = run_alignment(m, s, options=opts, config=replace(CONFIG, gyro_bias_seed=False))
    err0 = _err_arcmin(off, p.truth) / 60.0
    assert np.max(np.abs(err0 / np.asarray(off.mounting_sigma_deg))) > 3.0, (err0, off.mounting_sigma_deg)


def test_a_small_gyro_bias_is_left_to_the_filter_bit_for_bit():
    """Where the measured bias is within 3 x the grade's prior (the benchmarks' biases), nothing changes: the
    seed is not applied and the run is the run without it, bit for bit."""
    m, s, truth = _pair(duration_s=30.0)
    res = run_alignment(m, s)
    off = run_alignment(m, s, config=replace(CONFIG, gyro_bias_seed=False))
    assert not any("gyro bias measured" in n for n in res.notes)
    assert res.mounting_rpy_deg == off.mounting_rpy_deg and res.mounting_sigma_deg == off.mounting_sigma_deg
    assert res.gyro_bias_dph == off.gyro_bias_dph


def test_the_gyro_bias_seed_of_a_master_without_an_imu_takes_the_earth_rate():
    """A master that logs its solution only: its rate from the attitude is relative to NED, the slave's gyros
    also sense the earth's rate (15 deg/h); the seed adds it, so the bias comes out as the slave's own."""
    from logtools.inslog import InsLog

    b = (-2000.0, 1500.0, 2500.0)
    p = sim.simulate(sim.scenario_config("vehicle", duration_s=60.0, latency_s=0.0, seed=3, slave_gyro_bias_dph=b))
    master = InsLog(imu=p.master.imu.iloc[:0], nav=p.master.nav, meta=p.master.meta)
    res = run_alignment(master, p.slave.rebased(p.master.meta.t0_ns), options=AlignmentOptions(estimate_lever_arm=True))
    assert any("gyro bias measured" in n for n in res.notes), res.notes
    assert res.gyro_bias_dph == pytest.approx(b, abs=2.0)
    assert np.all(np.abs(_err_arcmin(res, p.truth)) < 1.0), _err_arcmin(res, p.truth)
    # the seed itself (the filter would take another 10 deg/h off in its own time): within 1 deg/h
    from logtools.alignment import run as run_mod
    from logtools.conventions import DEG_PER_H, dcm_from_euler

    s = p.slave.rebased(p.master.meta.t0_ns)
    t, g = s.t_imu_s(), s.gyro_rad_s()
    r0 = dcm_from_euler(np.radians(p.truth.mounting_rpy_deg))
    ms = run_mod._master_series(master)
    seed = run_mod._gyro_bias_seed(master, ms, run_mod._rates_on_grid(master, ms, t, g, 0.0), 0.0, r0,
                                   3.0 * DEG_PER_H, CONFIG, [])
    assert seed.applied and seed.b_rad_s / DEG_PER_H == pytest.approx(b, abs=1.0)


def test_still_converging_is_the_sigmas_fall_over_the_last_part_of_the_run():
    """_still_converging: the forward sigma of some angle fell by more than settle_fall_ratio over the last
    settle_tail_frac of the run (1/sqrt(t) all along: 1.12x over the last fifth, settled; the yaw still
    halving at the end: still converging)."""
    from logtools.alignment.options import CONFIG
    from logtools.alignment.run import _still_converging

    t = np.linspace(0.0, 600.0, 3001)
    settled = np.column_stack([1.0 / np.sqrt(1.0 + t)] * 3)
    assert _still_converging(t, settled, CONFIG) is False
    late = settled.copy()
    late[:, 2] = np.where(t < 480.0, 1.0, 1.0 - 0.5 * (t - 480.0) / 120.0)  # yaw learnt in the last 2 minutes
    assert _still_converging(t, late, CONFIG) is True
    assert _still_converging(t[:1], settled[:1], CONFIG) is None


def test_slave_noise_measured_once_per_run_and_master_prepared_once(monkeypatch):
    """The slave IMU's white noise (a median over the whole overlap per axis) is measured once per run, not
    by the prior, the seed and every pass's settings again (13 medians of 720k rows on the 1 h pair, 1 s);
    prepare_master (analyze calls it before the uncompensated run is forked) leaves nothing for the runs
    to prepare. Same results either way."""
    from logtools.alignment import run as run_mod

    m, s, _truth = _pair(duration_s=40.0)
    before = run_alignment(m, s, filter="kf", match="vel+att")
    run_mod.forget_master(m)
    calls = []
    orig = run_mod._hf_sigma
    monkeypatch.setattr(run_mod, "_hf_sigma", lambda y: calls.append(len(y)) or orig(y))
    prepared = []
    orig_series = run_mod._master_series
    monkeypatch.setattr(run_mod, "_master_series", lambda *a, **k: prepared.append(1) or orig_series(*a, **k))
    run_mod.prepare_master(m)
    assert len(prepared) == 1 and len(calls) == 2  # the master's series, its attitude's and velocity's noise
    calls.clear()
    after = run_alignment(m, s, filter="kf", match="vel+att")
    assert len(prepared) == 1  # nothing prepared again for the same master
    assert len(calls) == 2, calls  # the slave's gyros and accelerometers, once each
    assert np.array_equal(before.mounting_rpy_deg, after.mounting_rpy_deg)
    assert np.array_equal(before.mounting_sigma_deg, after.mounting_sigma_deg)
    assert before.notes == after.notes


def test_the_lever_arms_rate_is_the_masters_gyro_at_its_own_rate_not_the_navigation_rate():
    """A rigid-body vibration of 15 Hz under a 20 Hz navigation output: the slave's velocity carries w x r at
    every epoch, so the master's rate for the lever arm is its 200 Hz gyro interpolated at the epoch, not
    the gyro sampled at the navigation stamps and interpolated between them (an independent simulator's
    car: the lever arm 1.15 m off at a sigma of 0.023 m). The compiled lookup gives the same numbers."""
    from logtools.alignment import run as run_mod
    from logtools.inslog import InsLog, LogMeta

    t_imu = np.arange(0.0, 20.0, 0.005) + 0.0013
    w = np.stack([0.02 * np.sin(2 * np.pi * 15.0 * t_imu), 0.1 * np.sin(0.5 * t_imu), 0.01 + 0 * t_imu], -1)
    t_nav = np.arange(0.0, 20.0, 0.05)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_nav), 1))
    master = InsLog.from_arrays(LogMeta("m.csv", "csv"), t_imu, w, np.tile([0.0, 0.0, -9.8], (len(t_imu), 1)),
                                t_nav, q, np.zeros((len(t_nav), 3)), np.tile([0.7, 0.2, 10.0], (len(t_nav), 1)))
    ms = run_mod._master_series(master)
    inside = (t_imu >= t_nav[0]) & (t_imu <= t_nav[-1])
    assert ms.w_t_s is not None and ms.w_t_s[0] <= max(t_nav[0], t_imu[0])
    assert ms.w_t_s[-1] >= min(t_nav[-1], t_imu[-1])
    assert np.isin(t_imu[inside], ms.w_t_s).all()
    w_ie_b = earth.earth_rate_ned(np.radians(0.7))  # (a level, north-pointing master: the body frame is NED)
    for t in (5.0137, 7.02, 11.046):  # between navigation samples, at a vibration's crest or anywhere
        _, _, _, w_t = ms.sample(t)
        want = np.array([np.interp(t, t_imu, w[:, i]) for i in range(3)]) - w_ie_b
        assert w_t == pytest.approx(want, abs=1e-12)
        c_nm, v_m, a_m, w_nb = np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3)
        kfm._nb_master_at(ms.t_s, ms.quat, ms.vel, ms.acc, ms.w_stamps_s, ms.w_nm_m, True, True, True, t, c_nm,
                          v_m, a_m, w_nb)
        assert w_nb == pytest.approx(w_t, abs=1e-15)
    # the navigation rate's interpolation would have missed the vibration by most of its amplitude
    i = np.searchsorted(t_nav, 5.0137) - 1
    at_nav = np.interp(5.0137, t_nav[i:i + 2], np.interp(t_nav[i:i + 2], t_imu, w[:, 0]))
    assert abs(at_nav - np.interp(5.0137, t_imu, w[:, 0])) > 0.005


@pytest.mark.parametrize("master_hz, slave_hz", [(400.0, 50.0), (100.0, 200.0)])
def test_a_vibrating_car_gives_its_lever_arm_at_any_pair_of_imu_rates(master_hz, slave_hz):
    """A rigid-body angular vibration of 12-17 Hz (0.005-0.01 deg) on a car whose slave sits 1.3 m from its
    master. A 50 Hz slave's strapdown keeps only 0.41-0.77 of the vibration's w x r (the trapezoid on
    point samples): the lever arm came out at 0.63-0.8 of itself, 3-5 sigma off. A 100 Hz master's gyro read
    by linear interpolation loses up to a fifth of it between samples: the lever arm came out 7-9 % long,
    at 21-28 sigma. Both within 3 sigma now, the mounting within 0.01 deg."""
    from logtools.sim import scenario_config, simulate

    lever = np.array([0.4, -1.0, -0.8])
    cfg = scenario_config("vehicle", duration_s=120.0, seed=3, master_imu_rate_hz=master_hz,
                          master_nav_rate_hz=25.0, slave_imu_rate_hz=slave_hz, latency_s=0.0,
                          lever_arm_m=tuple(lever), rigid_vibration_deg=(0.01, 0.01, 0.005), slave_nav=False)
    p = simulate(cfg)
    # the vibration is in the master's gyro: 0.01 deg at 15 Hz is 0.94 deg/s
    t_m, g_m = p.master.t_imu_s(), p.master.gyro_rad_s()
    assert np.degrees(np.ptp(g_m[(t_m > 50) & (t_m < 51), 0])) > 1.5
    res = run_alignment(p.master, p.slave, filter="kf", match="vel+att",
                        options=AlignmentOptions(estimate_lever_arm=True))
    z = (np.asarray(res.lever_arm_m) - lever) / np.asarray(res.lever_arm_sigma_m)
    assert np.all(np.abs(z) < 3.0), (res.lever_arm_m, res.lever_arm_sigma_m)
    assert np.max(np.abs(np.asarray(res.mounting_rpy_deg) - np.asarray(cfg.mount_rpy_deg))) < 0.01


def test_a_mems_slave_at_50_hz_on_a_shaking_car_gives_its_lever_arm_to_centimetres():
    """The same car shaking 0.007-0.011 deg at 12.6-20 Hz, its slave a MEMS IMU at 50 Hz (0.5 deg/rt-h,
    340 ug/rt-Hz), the master's IMU at 400 Hz. The lever arm's share of the vibration (w' x r, ~1.6 m/s^2)
    counted as the slave's accelerometer noise (48x the true one): the filter let the slave's velocity
    wander by more than the lever arm's velocity and put the lever arm 0.54 m off at a 0.36 m sigma, the
    mounting at sigmas of 14-40 arcmin. Measured without it (alignment/noise.py) the lever arm comes out
    within 1 cm and the mounting at sigmas near 1 arcmin, both within 3 sigma."""
    from logtools.sim import scenario_config, simulate

    lever = np.array([0.326, -1.154, -0.823])
    cfg = scenario_config("vehicle", duration_s=180.0, seed=3, master_imu_rate_hz=400.0, master_nav_rate_hz=25.0,
                          slave_imu_rate_hz=50.0, latency_s=0.0, lever_arm_m=tuple(lever), slave_nav=False,
                          rigid_vibration_deg=(0.0113, 0.0097, 0.0069), rigid_vibration_hz=(20.0, 12.64, 17.35),
                          slave_gyro_arw_dpsh=0.5, slave_accel_vrw_ug_rthz=340.0,
                          slave_gyro_bias_dph=(20.0, -30.0, 40.0), slave_accel_bias_mg=(5.0, -8.0, 3.0))
    p = simulate(cfg)
    res = run_alignment(p.master, p.slave, filter="kf", match="vel+att",
                        options=AlignmentOptions(estimate_lever_arm=True))
    err = np.asarray(res.lever_arm_m) - lever
    assert np.all(np.abs(err) < 0.01) and np.all(np.abs(err) < 3 * np.asarray(res.lever_arm_sigma_m)), \
        (res.lever_arm_m, res.lever_arm_sigma_m)
    z = (np.asarray(res.mounting_rpy_deg) - np.asarray(cfg.mount_rpy_deg)) / np.asarray(res.mounting_sigma_deg)
    assert np.all(np.abs(z) < 3.0) and max(res.mounting_sigma_deg) * 60 < 3.0, (z, res.mounting_sigma_deg)


def test_the_accelerometers_noise_is_measured_without_the_lever_arms_acceleration():
    """A multirotor shaking 0.0035-0.0104 deg at 10-19 Hz, 1.7 m from its master: the third differences of
    the slave's 100 Hz accelerometers are 32x their noise. Less the master's specific force and the lever
    arm's acceleration they are within 30 % of it, and the same as the samples' own without a vibration. A
    master IMU at the slave's rate is not asked (one board's two IMUs alias a vibration alike)."""
    from logtools.alignment.noise import accel_noise_without_lever
    from logtools.alignment.run import _hf_sigma
    from logtools.inslog import InsLog, LogMeta
    from logtools.conventions import dcm_from_euler
    from logtools.sim import scenario_config, simulate

    kw = dict(max_samples=200_000, chunk_s=10.0, max_delay_s=0.01, min_rate_ratio=1.5)
    for vib, m_hz in (((0.0072, 0.0035, 0.0104), 200.0), ((0.0, 0.0, 0.0), 200.0), ((0.0072, 0.0035, 0.0104), 100.0)):
        cfg = scenario_config("multirotor", duration_s=60.0, seed=3, master_imu_rate_hz=m_hz, slave_imu_rate_hz=100.0,
                              latency_s=0.0, lever_arm_m=(-1.425, -0.017, 0.856), rigid_vibration_deg=vib,
                              rigid_vibration_hz=(10.28, 11.32, 18.99), slave_nav=False, slave_gyro_arw_dpsh=0.5,
                              slave_accel_vrw_ug_rthz=340.0)
        p = simulate(cfg)
        s = p.slave.rebased(p.master.meta.t0_ns)
        true_sigma = 340e-6 * 9.80665 * np.sqrt(100.0)  # (white noise of 340 ug/rt-Hz sampled at 100 Hz)
        own = _hf_sigma(s.accel_m_s2())
        # (1 ms off in the delay: refitted)
        got = accel_noise_without_lever(p.master, s.t_imu_s(), s.gyro_rad_s(), s.accel_m_s2(), 0.001,
                                        dcm_from_euler(np.radians(cfg.mount_rpy_deg)), **kw)
        if m_hz == 100.0:
            assert got is None
        elif vib[0]:
            assert own > 20 * true_sigma and abs(got / true_sigma - 1.0) < 0.3, (own, got, true_sigma)
            # a master with a 3 s gap and a few NaN rates: the chunks across them are left out
            tm, g = p.master.t_imu_s(), p.master.gyro_rad_s().copy()
            g[5000:5003] = np.nan
            keep = (tm < 20.0) | (tm > 23.0)
            gappy = InsLog.from_arrays(LogMeta("m.csv", "csv"), tm[keep], g[keep], p.master.accel_m_s2()[keep])
            got2 = accel_noise_without_lever(gappy, s.t_imu_s(), s.gyro_rad_s(), s.accel_m_s2(), 0.0,
                                             dcm_from_euler(np.radians(cfg.mount_rpy_deg)), **kw)
            assert abs(got2 / true_sigma - 1.0) < 0.3, (got2, true_sigma)
        else:
            assert abs(own / true_sigma - 1.0) < 0.1 and abs(got / own - 1.0) < 0.05, (own, got, true_sigma)


def test_a_lateral_accelerometer_bias_does_not_turn_a_cars_mounting():
    """A car at 10 m/s with a MEMS slave whose accelerometers have a 12.5 mg lateral bias, updates at 5 Hz.
    The biases act through C_ns over a whole segment; with C_ns taken at the segment's start a turning car's
    bias leaked into the mounting's yaw (b dt / (2 v): 2.1 arcmin here at a sigma of 0.37, z 5.6; 1.0 at the
    default 10 Hz of a 10 Hz navigation output). With the segment's midpoint the yaw is the same as without
    the bias, and the bias is estimated."""
    from logtools.sim import scenario_config, simulate

    yaw = []
    for bias in ((0.0, 12.5, 0.0), (0.0, 0.0, 0.0)):
        cfg = scenario_config("vehicle", duration_s=240.0, seed=4, latency_s=0.0, lever_arm_m=(0.28, -0.16, -0.16),
                              slave_nav=False, slave_gyro_arw_dpsh=0.5, slave_accel_vrw_ug_rthz=340.0,
                              slave_gyro_bias_dph=(8.0, 7.0, 37.0), slave_accel_bias_mg=bias)
        p = simulate(cfg)
        res = run_alignment(p.master, p.slave, filter="kf", match="vel+att",
                            options=AlignmentOptions(lever_arm_m=(0.28, -0.16, -0.16), update_hz=5.0))
        assert np.allclose(res.accel_bias_mg, bias, atol=0.5), res.accel_bias_mg
        from logtools.conventions import dcm_from_euler, quat_from_dcm, rotvec_from_quat
        e = dcm_from_euler(np.radians(res.mounting_rpy_deg)) @ dcm_from_euler(np.radians(cfg.mount_rpy_deg)).T
        err = np.degrees(rotvec_from_quat(quat_from_dcm(e))) * 60.0
        assert np.all(np.abs(err) < 3.0 * np.asarray(res.mounting_sigma_deg) * 60.0), (err, res.mounting_sigma_deg)
        yaw.append(err[2])
    assert abs(yaw[0] - yaw[1]) < 0.2, yaw


def _as_precise_and_right(res, ref, truth, slack_arcmin: float) -> None:
    """``res``'s mounting sigmas within 1.5 x ``ref``'s, and its error within 3 of them (+ slack, arcmin)."""
    sig, sig_ref = (np.asarray(r.mounting_sigma_deg) * 60.0 for r in (res, ref))
    assert np.all(sig < 1.5 * sig_ref), (sig, sig_ref)
    err = _err_arcmin(res, truth)
    assert np.all(np.abs(err) < 3.0 * sig + slack_arcmin), (err, sig)


@pytest.mark.parametrize("scenario,cut", [("aircraft", "nav"), ("aircraft", "nav-only master"),
                                          ("vehicle", "nav"), ("vehicle", "nav+imu"), ("multirotor", "nav+imu")])
def test_a_gap_in_the_master_gives_no_measurements_across_it(scenario, cut):
    """A master whose output stops for 15 s of 90 (its navigation; with "nav+imu" its IMU too; a "nav-only
    master" logs no IMU). Before: the attitude and velocity interpolated linearly across the gap were
    measurements of a motion the master never output (the aircraft's mounting sigma 0.01-0.03 -> 0.45-0.68
    arcmin, its pitch 3.7 arcmin off: 8 sigma); the rates interpolated across it went into the coarse
    mounting and the gyro-bias seed (thousands of deg/h); the attitude's change over the gap, judged
    against the rate at its middle, was an EKF reset, and the slave's attitude restarted from the master
    interpolated inside the gap (a car's mounting 18-73 arcmin off at sigmas of 1.5-2.9, a multirotor's
    24-45 at 2.7-4.4); a nav-only master's increment over the gap was two resets. Now: no update across a
    gap, no rate from inside one, and the mounting comes out as from the whole log."""
    p = sim.simulate(sim.scenario_config(scenario, seed=11, duration_s=90.0, latency_s=0.0, drift_ppm=0.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    if cut == "nav-only master":
        m = type(m)(imu=m.imu.iloc[:0], nav=m.nav, meta=m.meta)
    t, ti = m.nav.index.to_numpy(), m.imu.index.to_numpy()
    imu = m.imu[(ti < 20.0) | (ti > 35.0)] if cut == "nav+imu" else m.imu
    gapped = type(m)(imu=imu, nav=m.nav[(t < 20.0) | (t > 35.0)], meta=m.meta)
    whole, gap = run_alignment(m, s), run_alignment(gapped, s)
    assert any("1 gap(s) in the overlap" in n for n in gap.notes), gap.notes
    assert not any("jumped" in n for n in gap.notes), gap.notes
    _as_precise_and_right(gap, whole, p.truth, 0.05)


def test_a_master_that_resets_inside_a_gap_of_its_output_restarts_the_slave_after_it():
    """The master's attitude turns by 30 deg in yaw while its navigation output is missing (an EKF yaw reset
    inside a 15 s gap), its gyro logging through: its gyro integrated over the gap disagrees with the
    attitude's change, a reset, and the slave's attitude restarts at the gap's end from the master's
    output there; roll and pitch of the mounting stay right (the yaw after the reset is the new master's).
    Attitude matching: the reset leaves the master's velocity as it was, at odds with its new heading, which
    moves a car's velocity-matched roll by 4 arcmin with or without a gap."""
    from logtools.conventions import quat_from_euler, quat_mul

    p = sim.simulate(sim.scenario_config("vehicle", seed=11, duration_s=90.0, latency_s=0.0, drift_ppm=0.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    nav = m.nav[(m.nav.index < 20.0) | (m.nav.index > 35.0)].copy()
    qc = ["quat_w", "quat_x", "quat_y", "quat_z"]
    late = nav.index.to_numpy() > 35.0
    nav.loc[late, qc] = quat_mul(quat_from_euler(np.radians([0.0, 0.0, 30.0])), nav.loc[late, qc].to_numpy())
    res = run_alignment(type(m)(imu=m.imu, nav=nav, meta=m.meta), s, match="att")
    assert any("jumped 1 time" in n for n in res.notes), res.notes
    assert np.all(np.abs(_err_arcmin(res, p.truth)[:2]) < 1.0), _err_arcmin(res, p.truth)


def test_a_bursty_masters_regular_steps_are_no_gaps():
    """Telemetry delivers a 4 Hz AHRS2 in pairs 9 ms apart (a real tlog): 3 median steps (27 ms) would call
    every other step a gap and drop half the measurements; its typical step (0.47 s) does not."""
    from logtools.alignment.run import _nav_gaps
    burst = np.sort(np.concatenate([np.arange(100) * 0.47, np.arange(100) * 0.47 + 0.009]))
    assert not _nav_gaps(burst).any()
    dropout = np.concatenate([burst[:50], burst[60:] + 3.0])
    assert np.flatnonzero(_nav_gaps(dropout)).tolist() == [49]


def test_a_master_imu_that_covers_little_of_the_overlap_gives_no_rates_from_outside_it():
    """Rates interpolated beyond the master IMU's last sample are its last value held, no data: the coarse
    fit reads none (and with no stretch of both units' rates it says so and starts from the slave's own
    attitude); the navigation output still aligns the pair."""
    p = sim.simulate(sim.scenario_config("aircraft", seed=3, duration_s=40.0, latency_s=0.0, drift_ppm=0.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    res = run_alignment(type(m)(imu=m.imu.iloc[:2], nav=m.nav, meta=m.meta), s)
    assert any("no stretch where both units' rates are logged" in n for n in res.notes), res.notes
    err = _err_arcmin(res, p.truth)
    assert np.all(np.abs(err) < 3.0 * np.asarray(res.mounting_sigma_deg) * 60.0 + 0.05), err


def test_the_delay_states_coarse_start_reads_no_rate_from_inside_a_gap():
    """kf-delay starts its delay state from the lag that best matches the two units' rate magnitudes; with
    the master stopped for 15 s of a car's 90 the rates interpolated across the gap moved that start to
    +122 ms for a true +80."""
    p = sim.simulate(sim.scenario_config("vehicle", seed=11, duration_s=90.0, latency_s=0.08, drift_ppm=0.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    t, ti = m.nav.index.to_numpy(), m.imu.index.to_numpy()
    gapped = type(m)(imu=m.imu[(ti < 20.0) | (ti > 35.0)], nav=m.nav[(t < 20.0) | (t > 35.0)], meta=m.meta)
    res = run_alignment(gapped, s, filter="kf-delay")
    assert "delay state started at +80 ms (angular-rate magnitudes)" in res.notes, res.notes
    assert abs(res.delay_s - 0.08) < 3.0 * res.delay_sigma_s + 1e-4


def test_a_master_slower_than_the_update_rate_is_read_at_its_own_instants():
    """A master whose output comes in pairs 10 ms apart every 0.5 s (receive-time stamps): its median step
    (0.25 s) set a 4 Hz grid of updates, half of them reading the master interpolated across 0.49 s; the
    first pass's NIS/dof was 1900 and the mounting's sigma 0.19 arcmin where a plain 2 Hz master gives 0.03.
    Its noise, from plain third differences that mix its 10 ms and 0.49 s steps, came out at 0.53 deg and
    0.89 m/s for 0.0007 deg and 0.0025 m/s (the sigma 2.2 arcmin). Now the updates sit at the master's own
    instants and its noise is measured at its stamps."""
    p = sim.simulate(sim.scenario_config("aircraft", seed=11, duration_s=90.0, latency_s=0.0, drift_ppm=0.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    k = np.round(m.nav.index.to_numpy() / 0.005).astype(int)
    plain = run_alignment(type(m)(imu=m.imu, nav=m.nav[k % 100 == 0], meta=m.meta), s)
    pairs = run_alignment(type(m)(imu=m.imu, nav=m.nav[(k % 100 == 0) | (k % 100 == 2)], meta=m.meta), s)
    assert not any("re-estimated" in n for n in pairs.notes), pairs.notes
    _as_precise_and_right(pairs, plain, p.truth, 0.02)


def test_third_divided_differences_at_irregular_stamps_cancel_a_quadratic_and_scale_like_uniform_ones():
    from logtools.alignment.noise import d3_at, d3_sigma

    rng = np.random.default_rng(3)
    t = np.arange(200) * 0.01
    y = rng.normal(size=(200, 2))
    np.testing.assert_allclose(np.abs(d3_at(t, y)), np.abs(np.diff(y, n=3, axis=0)), rtol=1e-9)
    tb = np.sort(np.concatenate([np.arange(400) * 0.5, np.arange(400) * 0.5 + 0.01]))  # pairs
    quad = np.stack([3.0 + 2.0 * tb - 0.7 * tb**2, tb**2], -1)
    assert np.abs(d3_at(tb, quad)).max() < 1e-6
    noise = 0.01 * rng.normal(size=(len(tb), 2))
    assert d3_sigma(d3_at(tb, quad + noise)) == pytest.approx(0.01, rel=0.15)


def test_a_slow_masters_gap_is_crossed_in_steps_not_in_one():
    """Paced by a 10 Hz master, the updates had none inside its 15 s gap: the error state was carried across
    it in one step, and a multirotor's roll came out 2.6 sigma away from the run on a 10 Hz grid (which
    crosses the gap in 0.1 s steps without updates). The grid's epochs inside the gap now stay."""
    p = sim.simulate(sim.scenario_config("multirotor", seed=11, duration_s=90.0, latency_s=0.0, drift_ppm=0.0,
                                         master_nav_rate_hz=10.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    t = m.nav.index.to_numpy()
    gapped = type(m)(imu=m.imu, nav=m.nav[(t < 20.0) | (t > 35.0)], meta=m.meta)
    paced = run_alignment(gapped, s)
    grid = run_alignment(gapped, s, options=AlignmentOptions(update_hz=10.0))
    d = np.abs(np.asarray(paced.mounting_rpy_deg) - np.asarray(grid.mounting_rpy_deg))
    assert np.all(d < 0.2 * np.asarray(grid.mounting_sigma_deg)), (d * 60, np.asarray(grid.mounting_sigma_deg) * 60)


def test_velocity_matchings_mounting_is_averaged_over_epochs_with_an_update():
    """Velocity matching reports the mean of C_sn C_nm over its last tenth of epochs; that tenth took the
    epochs inside a gap of the master's output too, where its attitude is interpolated across the gap: a 5 Hz
    master's 1.8 s gap near the end of a 60 s aircraft log put the roll 0.9 arcmin off at a sigma of 0.14."""
    p = sim.simulate(sim.scenario_config("aircraft", seed=5, duration_s=60.0, latency_s=0.0, drift_ppm=0.0,
                                         master_nav_rate_hz=5.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    t = m.nav.index.to_numpy()
    res = run_alignment(type(m)(imu=m.imu, nav=m.nav[(t < 55.0) | (t > 56.7)], meta=m.meta), s, match="vel")
    err, sig = _err_arcmin(res, p.truth), np.asarray(res.mounting_sigma_deg) * 60.0
    assert np.all(np.abs(err) < 3.0 * sig), (err, sig)


def test_a_bursty_masters_long_steps_are_no_ekf_resets():
    """A multirotor's master output in pairs 0.2 s apart every 2 s: the attitude's change over each 1.8 s
    step, judged against the rate at its middle, was an EKF reset (26 of 30), and 53 of 59 updates were
    skipped. Its long steps are now judged against the gyro integrated over them, as gaps are."""
    p = sim.simulate(sim.scenario_config("multirotor", seed=3, duration_s=60.0, latency_s=0.0, drift_ppm=0.0,
                                         master_nav_rate_hz=5.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    pairs = type(m)(imu=m.imu, nav=m.nav[(np.arange(len(m.nav)) % 10) < 2], meta=m.meta)
    res = run_alignment(pairs, s, match="vel")
    assert not any("jumped" in n or "updates skipped" in n for n in res.notes), res.notes
    err, sig = _err_arcmin(res, p.truth), np.asarray(res.mounting_sigma_deg) * 60.0
    assert np.all(np.abs(err) < 3.0 * sig), (err, sig)


def test_a_slow_nav_only_masters_turns_are_no_ekf_resets_a_real_reset_is():
    """Without a gyro, a reset is an attitude increment unlike its neighbours; at 1 Hz an aircraft's
    S-turns change consecutive increments by several degrees (6 "resets" in 60 s, 8 of 59 updates skipped).
    The threshold now grows with what an angular acceleration of 20 deg/s^2 does over the step; a 30 deg yaw
    reset is still found."""
    from logtools.conventions import quat_from_euler, quat_mul

    p = sim.simulate(sim.scenario_config("aircraft", seed=3, duration_s=60.0, latency_s=0.0, drift_ppm=0.0,
                                         master_nav_rate_hz=10.0))
    m, s = p.master, p.slave.rebased(p.master.meta.t0_ns)
    nav = m.nav[np.arange(len(m.nav)) % 10 == 0]
    res = run_alignment(type(m)(imu=m.imu.iloc[:0], nav=nav, meta=m.meta), s, match="att")
    assert not any("jumped" in n for n in res.notes), res.notes
    qc = ["quat_w", "quat_x", "quat_y", "quat_z"]
    nav = nav.copy()
    late = nav.index.to_numpy() > 30.0
    nav.loc[late, qc] = quat_mul(quat_from_euler(np.radians([0.0, 0.0, 30.0])), nav.loc[late, qc].to_numpy())
    res = run_alignment(type(m)(imu=m.imu.iloc[:0], nav=nav, meta=m.meta), s, match="att")
    assert any("jumped" in n for n in res.notes), res.notes


def test_a_master_whose_navigation_comes_at_2_hz_gives_a_determined_mounting():
    """A master's attitude and velocity at 2 Hz (a telemetry log's streams): their third differences measure
    the multirotor's motion, not their noise, so the measurement noise came out far too large, the first pass's
    mean NIS at 0.0007 of its dof, and the mounting "not determined" (sigma 0.56-0.63 deg, not below half its
    prior) although its value was 0.02 deg off (random CLI pairs). The pass is rerun with the noise from its
    residuals (AlignmentConfig.recalibrate_low_nis_frac): the mounting determined, within 3 sigma."""
    from logtools import sim
    from logtools.conventions import dcm_from_euler, rotvec_from_dcm

    truth = (-139.777, 11.468, -12.667)
    cfg = sim.scenario_config("multirotor", duration_s=90.0, seed=59313, master_nav_rate_hz=2.0,
                              slave_nav_rate_hz=1.0, master_imu_rate_hz=50.0, slave_imu_rate_hz=50.0, latency_s=0.0,
                              drift_ppm=0.0, lever_arm_m=(0.475, -0.867, -0.758), mount_rpy_deg=truth)
    pair = sim.simulate(cfg)
    res = run_alignment(pair.master, pair.slave, options=AlignmentOptions(board_errors=False, estimate_lever_arm=True))
    assert all(res.observability[f"mounting_{ax}"] for ax in ("roll", "pitch", "yaw")), res.notes
    assert any("re-estimated from the residuals (first pass NIS/dof 0.0" in n for n in res.notes), res.notes
    err = np.degrees(np.abs(rotvec_from_dcm(dcm_from_euler(np.radians(res.mounting_rpy_deg))
                                            @ dcm_from_euler(np.radians(truth)).T)))
    assert np.all(err < 3 * np.asarray(res.mounting_sigma_deg)), (err, res.mounting_sigma_deg)
    assert max(res.mounting_sigma_deg) < 0.1


@pytest.mark.parametrize("gain", [0.5, 0.0])
def test_a_rigid_pass_not_held_beside_the_flexure_pass_gives_the_same_result(gain):
    """flexure="auto" on a long log (AlignmentConfig.hold_one_pass_min_bytes: 4 h of histories are 0.2 GB a
    pass) drops the rigid pass before the flexure pass and runs it again where the flexure states are not
    kept: the same result as holding both, figure for figure, whether they are kept (flex_auto_gain 0.5) or
    not (0: never)."""
    kw = dict(duration_s=60.0, **_FLEXING_MULTIROTOR)
    p = sim.simulate(sim.scenario_config("multirotor", seed=62015, flexure=True, **kw))
    opts = AlignmentOptions(estimate_lever_arm=True, flexure="auto")
    cfg = replace(CONFIG, flex_auto_gain=gain)
    held = run_alignment(p.master, p.slave, options=opts, config=cfg)
    dropped = run_alignment(p.master, p.slave, options=opts, config=replace(cfg, hold_one_pass_min_bytes=0))
    assert any(n.startswith("flexure states added") for n in held.notes) == (gain > 0)
    for f in fields(held):
        a, b = getattr(held, f.name), getattr(dropped, f.name)
        assert (np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b), f.name


class _Beside:
    """A stand-in for pipelines.parallel.submit that runs the call when its result is asked for and records
    what was started and what was dropped."""

    def __init__(self):
        self.started, self.cancelled, self.used = 0, 0, 0

    def __call__(self, fn, *args, **kwargs):
        outer = self
        outer.started += 1

        class _P:
            def result(self):
                outer.used += 1
                return fn(*args, **kwargs)

            def cancel(self):
                outer.cancelled += 1
        return _P()


@pytest.mark.parametrize("flexure", [True, False])
def test_the_flexure_pass_started_beside_gives_the_same_run(flexure):
    """run_alignment's ``beside``: the flexure pass (flexure="auto") starts beside the rigid one and is used
    where the residuals call for it, dropped where they do not; the result is the same to the bit as without
    it, in the Python loop (where the CLI gives it) and with a real forked child (pipelines.parallel)."""
    from pipelines import parallel

    kw = dict(duration_s=40.0, **_FLEXING_MULTIROTOR)
    p = sim.simulate(sim.scenario_config("multirotor", seed=62015, flexure=flexure, **kw))
    opts = AlignmentOptions(estimate_lever_arm=True, flexure="auto")
    cfg = replace(CONFIG, compiled_kf=False)
    alone = run_alignment(p.master, p.slave, options=opts, config=cfg)
    beside = _Beside()
    with_it = run_alignment(p.master, p.slave, options=opts, config=cfg, beside=beside)
    assert beside.started == 1 and (beside.used, beside.cancelled) == ((1, 0) if flexure else (0, 1))
    assert any(n.startswith("flexure states added") for n in alone.notes) == flexure
    assert alone.notes == with_it.notes and alone.mounting_rpy_deg == with_it.mounting_rpy_deg
    assert np.array_equal(alone.history_x, with_it.history_x)
    assert np.array_equal(alone.history_sigma, with_it.history_sigma)
    if flexure:
        parallel.enable(True)
        try:
            forked = run_alignment(p.master, p.slave, options=opts, config=cfg, beside=parallel.submit)
        finally:
            parallel.enable(False)
        assert forked.notes == alone.notes and forked.mounting_rpy_deg == alone.mounting_rpy_deg
        assert np.array_equal(forked.history_x, alone.history_x)
