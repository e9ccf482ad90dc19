"""Frames, attitude representations and units: the one place tapost defines them.

Conventions (see DESIGN.md):

* navigation frame NED, body frame FRD;
* quaternions are ``quat_wxyz``: Hamilton product, scalar first, rotating body -> NED
  (``v_ned = q * v_frd * q^-1``);
* a DCM ``mat_nb`` maps body vectors into NED (``v_n = mat_nb @ v_b``);
* Euler angles are intrinsic Z-Y-X (yaw, pitch, roll), ``mat_nb = Rz(yaw) Ry(pitch) Rx(roll)``,
  returned and accepted as ``rpy`` = [roll, pitch, yaw] in radians;
* ROS data (ENU world, FLU body, REP-103) converts here and nowhere else.

All functions are vectorised: a leading batch dimension ``(..., 4)`` / ``(..., 3, 3)`` is accepted.
"""
from __future__ import annotations

import numpy as np

# --------------------------------------------------------------------------------------------
# units (SI inside; these constants convert *from* the named unit to SI)
# --------------------------------------------------------------------------------------------
G0_M_S2 = 9.80665
DEG = np.pi / 180.0
ARCMIN = DEG / 60.0
ARCSEC = DEG / 3600.0
DEG_PER_H = DEG / 3600.0  # rad/s in one deg/h
DEG_PER_SQRT_H = DEG / 60.0  # rad/sqrt(s) in one deg/sqrt(h) (angle random walk)
MG = 1e-3 * G0_M_S2
UG = 1e-6 * G0_M_S2
UG_PER_SQRT_HZ = UG  # m/s^2/sqrt(Hz)
PPM = 1e-6
NS_PER_S = 1_000_000_000

# --------------------------------------------------------------------------------------------
# ENU/FLU <-> NED/FRD
# --------------------------------------------------------------------------------------------
#: maps ENU vector components to NED (and back: the matrix is its own inverse)
MAT_NED_FROM_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: maps FLU vector components to FRD (and back)
MAT_FRD_FROM_FLU = np.diag([1.0, -1.0, -1.0])


def enu_to_ned(vec_enu: np.ndarray) -> np.ndarray:
    """ENU vector(s) -> NED."""
    v = np.asarray(vec_enu, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


ned_to_enu = enu_to_ned  # the permutation is an involution


def flu_to_frd(vec_flu: np.ndarray) -> np.ndarray:
    """FLU body vector(s) -> FRD."""
    v = np.asarray(vec_flu, dtype=float)
    return np.stack([v[..., 0], -v[..., 1], -v[..., 2]], axis=-1)


frd_to_flu = flu_to_frd


def quat_enu_flu_to_ned_frd(quat_wxyz_enu_flu: np.ndarray) -> np.ndarray:
    """Attitude quaternion FLU->ENU (ROS REP-103) -> FRD->NED."""
    mat = dcm_from_quat(quat_wxyz_enu_flu)
    return quat_from_dcm(MAT_NED_FROM_ENU @ mat @ MAT_FRD_FROM_FLU)


quat_ned_frd_to_enu_flu = quat_enu_flu_to_ned_frd  # same similarity transform both ways


# --------------------------------------------------------------------------------------------
# quaternions (wxyz, Hamilton)
# --------------------------------------------------------------------------------------------
def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_conj(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p * q (wxyz)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vector(s) v by quaternion(s) q: q * v * q^-1."""
    return np.einsum("...ij,...j->...i", dcm_from_quat(q), np.asarray(v, dtype=float))


def quat_canonical(q: np.ndarray) -> np.ndarray:
    """Sign-fix so that w >= 0 (q and -q are the same rotation)."""
    q = np.asarray(q, dtype=float)
    return np.where(q[..., :1] < 0, -q, q)


def quat_make_continuous(q: np.ndarray) -> np.ndarray:
    """Flip signs along axis 0 so consecutive quaternions are in the same hemisphere."""
    q = np.array(q, dtype=float, copy=True)
    if len(q) < 2:
        return q
    dots = np.einsum("ij,ij->i", q[1:], q[:-1])
    flips = np.cumsum(dots < 0) % 2
    q[1:][flips == 1] *= -1
    return q


def dcm_from_quat(q: np.ndarray) -> np.ndarray:
    """Quaternion(s) (wxyz, body->nav) -> DCM mat_nb."""
    q = quat_normalize(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    m = np.empty(q.shape[:-1] + (3, 3))
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - w * z)
    m[..., 0, 2] = 2 * (x * z + w * y)
    m[..., 1, 0] = 2 * (x * y + w * z)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - w * x)
    m[..., 2, 0] = 2 * (x * z - w * y)
    m[..., 2, 1] = 2 * (y * z + w * x)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return m


def quat_from_dcm(m: np.ndarray) -> np.ndarray:
    """DCM(s) -> quaternion(s) wxyz with w >= 0 (Shepperd's method, branch per sample)."""
    m = np.asarray(m, dtype=float)
    tr = np.trace(m, axis1=-2, axis2=-1)
    cand = np.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], axis=-1)
    k = np.argmax(cand, axis=-1)
    q = np.empty(m.shape[:-2] + (4,))
    # branch 0: w largest
    s0 = np.sqrt(np.maximum(1.0 + tr, 0.0)) * 2
    s1 = np.sqrt(np.maximum(1.0 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], 0.0)) * 2
    s2 = np.sqrt(np.maximum(1.0 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 0.0)) * 2
    s3 = np.sqrt(np.maximum(1.0 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2], 0.0)) * 2
    with np.errstate(divide="ignore", invalid="ignore"):
        b0 = np.stack(
            [0.25 * s0, (m[..., 2, 1] - m[..., 1, 2]) / s0, (m[..., 0, 2] - m[..., 2, 0]) / s0,
             (m[..., 1, 0] - m[..., 0, 1]) / s0], axis=-1)
        b1 = np.stack(
            [(m[..., 2, 1] - m[..., 1, 2]) / s1, 0.25 * s1, (m[..., 0, 1] + m[..., 1, 0]) / s1,
             (m[..., 0, 2] + m[..., 2, 0]) / s1], axis=-1)
        b2 = np.stack(
            [(m[..., 0, 2] - m[..., 2, 0]) / s2, (m[..., 0, 1] + m[..., 1, 0]) / s2, 0.25 * s2,
             (m[..., 1, 2] + m[..., 2, 1]) / s2], axis=-1)
        b3 = np.stack(
            [(m[..., 1, 0] - m[..., 0, 1]) / s3, (m[..., 0, 2] + m[..., 2, 0]) / s3,
             (m[..., 1, 2] + m[..., 2, 1]) / s3, 0.25 * s3], axis=-1)
    kk = k[..., None]
    q = np.where(kk == 0, b0, np.where(kk == 1, b1, np.where(kk == 2, b2, b3)))
    return quat_canonical(quat_normalize(q))


def dcm_from_euler(rpy: np.ndarray) -> np.ndarray:
    """[roll, pitch, yaw] (rad, intrinsic Z-Y-X) -> mat_nb = Rz(yaw) Ry(pitch) Rx(roll)."""
    rpy = np.asarray(rpy, dtype=float)
    r, p, y = np.moveaxis(rpy, -1, 0)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    m = np.empty(rpy.shape[:-1] + (3, 3))
    m[..., 0, 0] = cp * cy
    m[..., 0, 1] = sr * sp * cy - cr * sy
    m[..., 0, 2] = cr * sp * cy + sr * sy
    m[..., 1, 0] = cp * sy
    m[..., 1, 1] = sr * sp * sy + cr * cy
    m[..., 1, 2] = cr * sp * sy - sr * cy
    m[..., 2, 0] = -sp
    m[..., 2, 1] = sr * cp
    m[..., 2, 2] = cr * cp
    return m


def euler_from_dcm(m: np.ndarray) -> np.ndarray:
    """mat_nb -> [roll, pitch, yaw] (rad), yaw in (-pi, pi]."""
    m = np.asarray(m, dtype=float)
    roll = np.arctan2(m[..., 2, 1], m[..., 2, 2])
    pitch = -np.arcsin(np.clip(m[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def quat_from_euler(rpy: np.ndarray) -> np.ndarray:
    rpy = np.asarray(rpy, dtype=float)
    hr, hp, hy = np.moveaxis(rpy / 2.0, -1, 0)
    cr, sr, cp, sp, cy, sy = np.cos(hr), np.sin(hr), np.cos(hp), np.sin(hp), np.cos(hy), np.sin(hy)
    q = np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )
    return quat_canonical(q)


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    return euler_from_dcm(dcm_from_quat(q))


def quat_from_rotvec(rv: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) -> quaternion; exact, stable near zero."""
    rv = np.asarray(rv, dtype=float)
    ang = np.linalg.norm(rv, axis=-1, keepdims=True)
    half = 0.5 * ang
    # sin(half)/ang with a Taylor series near zero
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(ang > 1e-8, np.sin(half) / np.where(ang > 0, ang, 1.0),
                     0.5 - ang**2 / 48.0)
    return np.concatenate([np.cos(half), rv * k], axis=-1)


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Quaternion -> rotation vector (rad), angle in [0, pi]."""
    q = quat_canonical(quat_normalize(q))
    w = np.clip(q[..., :1], -1.0, 1.0)
    vn = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(vn, w)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(vn > 1e-12, ang / np.where(vn > 0, vn, 1.0), 2.0 / np.maximum(w, 1e-300))
    return q[..., 1:] * k


def dcm_from_rotvec(rv: np.ndarray) -> np.ndarray:
    return dcm_from_quat(quat_from_rotvec(rv))


def rotvec_from_dcm(m: np.ndarray) -> np.ndarray:
    return rotvec_from_quat(quat_from_dcm(m))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v x] for vector(s) v."""
    v = np.asarray(v, dtype=float)
    m = np.zeros(v.shape[:-1] + (3, 3))
    m[..., 0, 1] = -v[..., 2]
    m[..., 0, 2] = v[..., 1]
    m[..., 1, 0] = v[..., 2]
    m[..., 1, 2] = -v[..., 0]
    m[..., 2, 0] = -v[..., 1]
    m[..., 2, 1] = v[..., 0]
    return m


def quat_slerp(q0: np.ndarray, q1: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """Spherical interpolation between q0 and q1 (arrays of the same shape) at frac in [0, 1]."""
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dq = quat_mul(quat_conj(q0), q1)
    rv = rotvec_from_quat(dq)
    frac = np.asarray(frac, dtype=float)[..., None]
    return quat_normalize(quat_mul(q0, quat_from_rotvec(rv * frac)))


def angle_between_quats(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of q0^-1 q1."""
    return np.linalg.norm(rotvec_from_quat(quat_mul(quat_conj(q0), q1)), axis=-1)


# --------------------------------------------------------------------------------------------
# shared estimation primitives (one implementation each)
# --------------------------------------------------------------------------------------------
def wahba(B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wahba/Kabsch: the proper rotation R maximising tr(R^T B) for the attitude profile matrix
    B = sum_k v_k u_k^T, i.e. the R with v_k ~ R u_k in least squares; batched over leading axes.

    Returns (R, score) with score = max tr(R^T B) = sum of B's singular values with the smallest's sign
    set by det (a reflection is never returned; a singular B counts as det +1). For M = sum a b^T (b ~ R a)
    the rotation is ``wahba(M)[0]`` transposed, i.e. ``wahba(M.T)`` up to rounding."""
    U, S, Vt = np.linalg.svd(B)
    det = np.linalg.det(U @ Vt)
    D = np.ones(S.shape)
    D[..., 2] = np.sign(det + (det == 0))
    return U @ (D[..., :, None] * Vt), np.sum(S * D, axis=-1)


def median_step_s(t_s: np.ndarray, default: float | None = None) -> float:
    """The median sampling step of sorted stamps (seconds); ``default`` where fewer than two stamps
    (a ValueError without one)."""
    t_s = np.asarray(t_s, dtype=float)
    if len(t_s) < 2:
        if default is None:
            raise ValueError("fewer than two stamps: no sampling step")
        return float(default)
    return float(np.median(np.diff(t_s)))


def typical_step_s(t_s: np.ndarray) -> float:
    """The sampling step that a typical instant of sorted stamps falls in (seconds): the median of the steps
    weighted by their length. A regular stream's median step (while gaps cover less than half of it); a
    bursty one's longer step: telemetry that delivers two messages 9 ms apart every 0.47 s (a tlog's AHRS2)
    has a median step of 9 ms, and every one of its regular steps would look like a gap of 50 of them.
    0.0 with fewer than two stamps."""
    return typical_step(np.diff(np.asarray(t_s, dtype=float)))


def typical_step(steps: np.ndarray) -> float:
    """:func:`typical_step_s` of the steps themselves (any unit); 0.0 without any."""
    d = np.sort(np.asarray(steps, dtype=float))
    if len(d) == 0:
        return 0.0
    c = np.cumsum(d)
    return float(d[min(int(np.searchsorted(c, 0.5 * c[-1])), len(d) - 1)])
