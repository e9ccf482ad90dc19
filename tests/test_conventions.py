"""logtools.conventions and logtools.earth against independent computations (scipy Rotation,
closed forms, REP-103 geometry)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from logtools import conventions as cv
from logtools import earth

RNG = np.random.default_rng(20261123)


def _random_rpy(n: int) -> np.ndarray:
    return np.column_stack([RNG.uniform(-np.pi, np.pi, n), RNG.uniform(-1.5, 1.5, n),
                            RNG.uniform(-np.pi, np.pi, n)])


def _scipy_from_rpy(rpy: np.ndarray) -> Rotation:
    # intrinsic Z-Y-X: yaw, then pitch, then roll
    return Rotation.from_euler("ZYX", rpy[:, ::-1])


def _wxyz(r: Rotation) -> np.ndarray:
    return cv.quat_canonical(np.roll(r.as_quat(), 1, axis=-1))


def _same_rotation(q_a, q_b, tol=1e-12):
    d = np.abs(np.sum(cv.quat_normalize(q_a) * cv.quat_normalize(q_b), axis=-1))
    return np.all(d > 1 - tol)


# ---- units -------------------------------------------------------------------------------------
def test_units():
    assert cv.DEG_PER_H * 3600 == pytest.approx(math.radians(1))
    assert cv.DEG_PER_SQRT_H == pytest.approx(math.radians(1) / math.sqrt(3600))
    assert cv.MG == pytest.approx(9.80665e-3) and cv.UG == pytest.approx(9.80665e-6)
    assert cv.ARCMIN * 60 == pytest.approx(cv.DEG) and cv.ARCSEC * 3600 == pytest.approx(cv.DEG)
    assert cv.NS_PER_S == 10**9 and cv.PPM == 1e-6


# ---- Euler / DCM / quaternion vs scipy ---------------------------------------------------------
def test_euler_dcm_quat_match_scipy():
    rpy = _random_rpy(500)
    ref = _scipy_from_rpy(rpy)
    assert np.allclose(cv.dcm_from_euler(rpy), ref.as_matrix(), atol=1e-14)
    assert _same_rotation(cv.quat_from_euler(rpy), _wxyz(ref))
    assert np.allclose(cv.dcm_from_quat(cv.quat_from_euler(rpy)), ref.as_matrix(), atol=1e-14)
    # body -> NED: the body x axis (nose) of a yaw-only attitude points along the heading
    m = cv.dcm_from_euler(np.array([0.0, 0.0, math.radians(30)]))
    assert np.allclose(m @ [1, 0, 0], [math.cos(math.radians(30)), math.sin(math.radians(30)), 0])
    # positive pitch raises the nose (NED z is down)
    assert (cv.dcm_from_euler(np.array([0.0, 0.2, 0.0])) @ [1, 0, 0])[2] < 0
    # positive roll lowers the right wing (body y)
    assert (cv.dcm_from_euler(np.array([0.2, 0.0, 0.0])) @ [0, 1, 0])[2] > 0


def test_round_trips_euler_dcm_quat_rotvec():
    rpy = _random_rpy(1000)
    m = cv.dcm_from_euler(rpy)
    back = cv.euler_from_dcm(m)
    assert np.allclose(back, rpy, atol=1e-11)
    assert np.allclose(cv.euler_from_quat(cv.quat_from_euler(rpy)), rpy, atol=1e-11)
    assert np.allclose(cv.euler_from_dcm(m), _scipy_from_rpy(rpy).as_euler("ZYX")[:, ::-1], atol=1e-11)
    q = cv.quat_from_dcm(m)
    assert np.all(q[:, 0] >= 0) and np.allclose(np.linalg.norm(q, axis=1), 1)
    assert np.allclose(cv.dcm_from_quat(q), m, atol=1e-14)
    assert _same_rotation(q, _wxyz(Rotation.from_matrix(m)))
    rv = cv.rotvec_from_quat(q)
    assert np.allclose(rv, Rotation.from_matrix(m).as_rotvec(), atol=1e-10)
    assert _same_rotation(cv.quat_from_rotvec(rv), q)
    assert np.allclose(cv.dcm_from_rotvec(rv), m, atol=1e-13)
    assert np.allclose(cv.rotvec_from_dcm(m), rv, atol=1e-10)


def test_quat_from_dcm_every_shepperd_branch_and_edge_cases():
    # rotations of ~180 deg about each axis pick the x, y, z branches; identity the w branch
    for axis in np.eye(3):
        for ang in (math.pi, math.pi - 1e-9, 3.0):
            r = Rotation.from_rotvec(axis * ang)
            assert _same_rotation(cv.quat_from_dcm(r.as_matrix()), _wxyz(r))
    assert np.allclose(cv.quat_from_dcm(np.eye(3)), [1, 0, 0, 0])
    # tiny and zero rotation vectors are exact
    for rv in (np.zeros(3), np.array([1e-12, -2e-12, 3e-12]), np.array([1e-7, 0, 0])):
        q = cv.quat_from_rotvec(rv)
        assert np.allclose(q, _wxyz(Rotation.from_rotvec(rv)), atol=1e-18, rtol=1e-12)
        assert np.allclose(cv.rotvec_from_quat(q), rv, atol=1e-20, rtol=1e-9)
    # angle pi: rotation vector of length pi
    rv = cv.rotvec_from_quat(np.array([0.0, 0.0, 1.0, 0.0]))
    assert np.allclose(np.abs(rv), [0, math.pi, 0])


def test_hamilton_product_and_rotate():
    a, b = Rotation.random(200, random_state=1), Rotation.random(200, random_state=2)
    qa, qb = _wxyz(a), _wxyz(b)
    # Hamilton, body->nav: dcm(p*q) = dcm(p) dcm(q)
    assert _same_rotation(cv.quat_mul(qa, qb), _wxyz(a * b))
    assert np.allclose(cv.dcm_from_quat(cv.quat_mul(qa, qb)), a.as_matrix() @ b.as_matrix(), atol=1e-13)
    # the textbook product i*j = k, j*i = -k
    i, j, k = np.eye(4)[1], np.eye(4)[2], np.eye(4)[3]
    assert np.allclose(cv.quat_mul(i, j), k) and np.allclose(cv.quat_mul(j, i), -k)
    v = RNG.normal(size=(200, 3))
    assert np.allclose(cv.quat_rotate(qa, v), a.apply(v), atol=1e-13)
    # q * (0, v) * q^-1 equals the rotated vector
    qv = np.column_stack([np.zeros(200), v])
    rot = cv.quat_mul(cv.quat_mul(qa, qv), cv.quat_conj(qa))
    assert np.allclose(rot[:, 1:], a.apply(v), atol=1e-13) and np.allclose(rot[:, 0], 0, atol=1e-13)
    assert np.allclose(cv.skew(v) @ np.array([0.3, -1.0, 2.0]), np.cross(v, [0.3, -1.0, 2.0]))
    assert np.allclose(cv.angle_between_quats(qa, qb), (a.inv() * b).magnitude(), atol=1e-10)


def test_slerp_and_continuity():
    a, b = Rotation.random(50, random_state=3), Rotation.random(50, random_state=4)
    qa, qb = _wxyz(a), _wxyz(b)
    for frac in (0.0, 0.25, 0.5, 0.9, 1.0):
        got = cv.quat_slerp(qa, qb, np.full(50, frac))
        for n in range(0, 50, 7):
            ref = Slerp([0, 1], Rotation.concatenate([a[n], b[n]]))([frac])
            assert _same_rotation(got[n], _wxyz(ref)[0], tol=1e-12)
    # shortest path even when the inputs are in opposite hemispheres
    assert _same_rotation(cv.quat_slerp(qa, -qb, np.full(50, 0.5)), cv.quat_slerp(qa, qb, np.full(50, 0.5)))
    q = _wxyz(Rotation.from_euler("z", np.linspace(0, 6 * np.pi, 400)[:, None]))
    c = cv.quat_make_continuous(q)
    assert np.all(np.einsum("ij,ij->i", c[1:], c[:-1]) > 0) and _same_rotation(c, q)


# ---- ENU/FLU (ROS REP-103) <-> NED/FRD ---------------------------------------------------------
def test_enu_flu_vectors_round_trip():
    v = RNG.normal(size=(100, 3))
    assert np.allclose(cv.ned_to_enu(cv.enu_to_ned(v)), v) and np.allclose(cv.frd_to_flu(cv.flu_to_frd(v)), v)
    assert np.allclose(cv.enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])  # east, north, up -> N, E, D
    assert np.allclose(cv.flu_to_frd([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    assert np.allclose(cv.MAT_NED_FROM_ENU @ v.T, cv.enu_to_ned(v).T)
    assert np.allclose(cv.MAT_FRD_FROM_FLU @ v.T, cv.flu_to_frd(v).T)


def test_quat_enu_flu_to_ned_frd_against_independent_construction():
    # ROS roll/pitch/yaw (FLU body, ENU world, yaw counter-clockwise from east)
    ros_rpy = np.column_stack([RNG.uniform(-1.2, 1.2, 300), RNG.uniform(-1.2, 1.2, 300),
                               RNG.uniform(-np.pi, np.pi, 300)])
    r_ros = Rotation.from_euler("ZYX", ros_rpy[:, ::-1])  # FLU -> ENU
    q_ned = cv.quat_enu_flu_to_ned_frd(_wxyz(r_ros))
    # 1) geometry: the body axes expressed in the world must be the same physical directions
    m_ned = cv.dcm_from_quat(q_ned)
    m_ros = r_ros.as_matrix()
    fwd_enu, left_enu, up_enu = m_ros[:, :, 0], m_ros[:, :, 1], m_ros[:, :, 2]
    assert np.allclose(m_ned[:, :, 0], cv.enu_to_ned(fwd_enu), atol=1e-13)   # F = forward
    assert np.allclose(m_ned[:, :, 1], cv.enu_to_ned(-left_enu), atol=1e-13)  # R = -left
    assert np.allclose(m_ned[:, :, 2], cv.enu_to_ned(-up_enu), atol=1e-13)    # D = -up
    # 2) Euler angles: roll same, pitch negated (nose-down positive in FLU), heading = 90 deg - yaw
    rpy_ned = cv.euler_from_quat(q_ned)
    assert np.allclose(rpy_ned[:, 0], ros_rpy[:, 0], atol=1e-10)
    assert np.allclose(rpy_ned[:, 1], -ros_rpy[:, 1], atol=1e-10)
    dyaw = (rpy_ned[:, 2] - (np.pi / 2 - ros_rpy[:, 2]) + np.pi) % (2 * np.pi) - np.pi
    assert np.allclose(dyaw, 0, atol=1e-10)
    # 3) and back
    assert _same_rotation(cv.quat_ned_frd_to_enu_flu(q_ned), _wxyz(r_ros))
    # identity in ROS (facing east, level) is heading 90 deg in NED
    assert np.allclose(cv.euler_from_quat(cv.quat_enu_flu_to_ned_frd(np.array([1.0, 0, 0, 0]))),
                       [0, 0, np.pi / 2])


# ---- earth model vs closed forms ---------------------------------------------------------------
def test_radii_closed_forms():
    a, e2 = 6378137.0, 6.69437999014e-3
    b = a * math.sqrt(1 - e2)
    r_m, r_n = earth.radii_m(np.array([0.0, math.pi / 2]))
    assert r_n[0] == pytest.approx(a, abs=1e-6) and r_m[0] == pytest.approx(a * (1 - e2), abs=1e-3)
    assert r_m[1] == pytest.approx(a * a / b, abs=1e-3) and r_n[1] == pytest.approx(a * a / b, abs=1e-3)
    assert earth.B_M == pytest.approx(b, abs=1e-3) and earth.E2 == pytest.approx(e2, rel=1e-10)
    lat = np.radians(np.array([10.0, 30.0, 45.0, 60.0, 80.0]))
    r_m, r_n = earth.radii_m(lat)
    assert np.allclose(r_n, a / np.sqrt(1 - e2 * np.sin(lat) ** 2), rtol=1e-12)
    assert np.allclose(r_m, a * (1 - e2) / (1 - e2 * np.sin(lat) ** 2) ** 1.5, rtol=1e-12)


def test_gravity_closed_forms():
    assert float(earth.gravity_m_s2(0.0, 0.0)) == pytest.approx(9.7803253359, abs=1e-9)
    assert float(earth.gravity_m_s2(math.pi / 2, 0.0)) == pytest.approx(9.8321849378, abs=1e-9)
    # textbook value at 45 deg: 9.80619920 m/s^2
    assert float(earth.gravity_m_s2(math.radians(45), 0.0)) == pytest.approx(9.806199, abs=2e-6)
    # free-air gradient about -3.086e-6 s^-2 near the surface
    grad = (earth.gravity_m_s2(0.7, 100.0) - earth.gravity_m_s2(0.7, 0.0)) / 100.0
    assert float(grad) == pytest.approx(-3.086e-6, rel=0.01)
    g = earth.gravity_ned_m_s2(np.array([0.1, 0.5]), np.array([0.0, 1000.0]))
    assert g.shape == (2, 3) and np.all(g[:, :2] == 0) and np.all(g[:, 2] > 9.7)


def test_rates_and_ecef():
    lat = np.radians(np.array([0.0, 30.0, -45.0]))
    w = earth.earth_rate_ned(lat)
    assert np.allclose(np.linalg.norm(w, axis=1), 7.292115e-5)
    assert np.allclose(w[:, 0], 7.292115e-5 * np.cos(lat)) and np.allclose(w[:, 2], -7.292115e-5 * np.sin(lat))
    # pure east velocity on the equator: the frame turns about north at v/(R+h)
    wen = earth.transport_rate_ned(0.0, 100.0, np.array([0.0, 200.0, 0.0]))
    assert np.allclose(wen, [200.0 / (6378137.0 + 100.0), 0.0, 0.0])
    r = earth.llh_rates(np.radians(30.0), 10.0, np.array([10.0, 20.0, -3.0]))
    r_m, r_n = earth.radii_m(np.radians(30.0))
    assert np.allclose(r, [10 / (r_m + 10), 20 / ((r_n + 10) * math.cos(math.radians(30))), 3.0])
    assert np.allclose(earth.llh_to_ecef(0.0, 0.0, 0.0), [6378137.0, 0, 0])
    assert np.allclose(earth.llh_to_ecef(math.pi / 2, 0.0, 0.0), [0, 0, earth.B_M], atol=1e-6)
    m = earth.dcm_ecef_to_ned(np.radians(30.0), np.radians(110.0))
    assert np.allclose(m @ m.T, np.eye(3))
    # "down" in ECEF at a point: the ellipsoid normal, i.e. the ECEF difference of two altitudes
    p0 = earth.llh_to_ecef(np.radians(30.0), np.radians(110.0), 0.0)
    p1 = earth.llh_to_ecef(np.radians(30.0), np.radians(110.0), -1.0)
    assert np.allclose(m @ (p1 - p0), [0, 0, 1], atol=1e-9)


# ---- properties ---------------------------------------------------------------------------------
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_angle = st.floats(-3.1, 3.1, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(st.tuples(_angle, st.floats(-1.55, 1.55), _angle), st.tuples(_angle, _angle, _angle))
def test_property_round_trips(rpy, rv):
    rpy, rv = np.array(rpy), np.array(rv) / 3.2  # |rv| < pi
    q = cv.quat_from_euler(rpy)
    assert np.allclose(cv.euler_from_quat(q), rpy, atol=1e-9)
    assert np.allclose(cv.quat_from_dcm(cv.dcm_from_quat(q)), q, atol=1e-12)
    assert np.allclose(cv.rotvec_from_quat(cv.quat_from_rotvec(rv)), rv, atol=1e-12)
    # ENU/FLU <-> NED/FRD is an involution on attitudes
    assert _same_rotation(cv.quat_ned_frd_to_enu_flu(cv.quat_enu_flu_to_ned_frd(q)), q)


def test_wahba_recovers_a_known_rotation_and_never_a_reflection():
    from logtools.conventions import dcm_from_euler, median_step_s, wahba
    rng = np.random.default_rng(7)
    R = dcm_from_euler(np.array([0.4, -0.3, 2.0]))
    u = rng.normal(size=(200, 3))
    v = u @ R.T + 1e-4 * rng.normal(size=u.shape)
    Rh, score = wahba(v.T @ u)
    assert np.abs(Rh - R).max() < 1e-4
    assert score > 0.99 * np.sum(v * (u @ R.T))
    # a reflected profile still gives a proper rotation (det +1), batched
    B = np.stack([v.T @ u, -(v.T @ u), np.zeros((3, 3))])
    Rb, _ = wahba(B)
    assert np.allclose(np.linalg.det(Rb), 1.0)
    assert median_step_s(np.array([0.0, 0.01, 0.02, 0.05])) == 0.01
    assert median_step_s(np.array([1.0]), default=1.0) == 1.0


def test_typical_step_of_a_bursty_stream_is_its_long_step_and_of_a_regular_one_its_median():
    from logtools.conventions import median_step_s, typical_step_s
    burst = np.sort(np.concatenate([np.arange(100) * 0.47, np.arange(100) * 0.47 + 0.009]))  # a tlog's AHRS2
    assert median_step_s(burst) == pytest.approx(0.009)
    assert typical_step_s(burst) == pytest.approx(0.461)
    t = np.arange(0.0, 60.0, 0.005)
    gap = t[(t < 20.0) | (t > 25.0)]  # a 5 s dropout in 200 Hz
    assert typical_step_s(gap) == pytest.approx(0.005)
    assert typical_step_s(np.array([1.0])) == 0.0
