"""Transfer-alignment error-state model: state layout per matching mode, continuous dynamics F,
measurement functions and their analytic Jacobians H (tested against finite differences).

Definitions (NED navigation frame n, slave body s, master body m; DESIGN.md mounting R = C_sm):

* slave attitude error phi (n frame):  C_ns_hat = (I - [phi x]) C_ns            (phi-angle model)
* velocity error:                      dv = v_hat - v
* gyro drift eps, accel bias nabla (s frame): measured = true + bias
* mounting error mu (s frame): with the running mounting estimate R_hat,  R = (I - [mu x]) R_hat
* flexure (S000 eq 8): angle lam (s frame) and rate w_f, second-order Markov
  lam' = w_f,  w_f' = -beta^2 lam - 2 beta w_f + eta; the effective mounting is mu + lam
* lever arm error dl (m frame): l = l_hat + dl, slave velocity v_s = v_m + C_nm (w_nm^m x l)  (S003 eq 3)
* master attitude error eta (n frame): the master's attitude output C_nm_out = (I + [eta x]) C_nm, a first-order
  Markov process (its EKF's attitude error, correlated over tau_m): eta' = -eta / tau_m + w
* slave accelerometer triad misalignment alpha (s frame): the accelerometers measure (I + [alpha x]) f^s in the
  gyro triad's frame s (two chips, or one chip's axes not orthogonal to the other's): a constant
* delay dtau (s): the slave's data stamped t describe the physical instant t - tau (tau > 0: slave
  stamps late, DESIGN.md latency); the master is read at t - tau_hat and dtau = tau - tau_hat. The
  measurement is linearised in the delay (S001/S004): dz/dtau = -(rate of the master quantity).

Dynamics (phi-angle model, position errors neglected):
  phi' = -w_in x phi + M_av dv - C_ns eps
  dv'  = f^n x phi + C_ns nabla - f^n x (C_ns alpha) - (2 w_ie + w_en) x dv + v x (M_av dv)
Measurements:
  attitude  z_att = rotvec(C_ns_ref C_ns_hat^T),  C_ns_ref = C_nm R_hat^T (master with the mounting
            estimate); z_att = phi - C_ns (mu + lam) + eta + w_ns^n dtau
  velocity  z_vel = v_hat - (v_m + C_nm (w x l_hat)) = dv + C_nm [w x] dl - a_m^n dtau
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from logtools.strapdown import HAVE_NUMBA, njit

MATCHES = ("vel", "att", "vel+att")


@dataclass(frozen=True)
class StateLayout:
    """Which states the filter carries and where. Slices index the state vector; None = absent."""

    match: str
    names: tuple[str, ...]
    att: slice
    vel: slice | None
    gyro: slice
    accel: slice | None
    mount: slice | None
    flex_ang: slice | None
    flex_rate: slice | None
    lever: slice | None
    delay: int | None
    master_att: slice | None = None  # the master's attitude error (first-order Markov), attitude matching
    accel_mis: slice | None = None  # the slave's accelerometer triad off its gyro triad, velocity matching

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def has_board_states(self) -> bool:
        """The board's error states (the master's attitude error, the accelerometer triad misalignment)."""
        return self.master_att is not None or self.accel_mis is not None

    @property
    def uses_vel(self) -> bool:
        return "vel" in self.match

    @property
    def uses_att(self) -> bool:
        return "att" in self.match

    @property
    def n_meas(self) -> int:
        return 3 * (self.uses_vel + self.uses_att)

    @cached_property
    def offsets(self) -> np.ndarray:
        """Start index of each group (-1 when absent), for the compiled kernels (made once per layout):
        [att, vel, gyro, accel, mount, flex_ang, flex_rate, lever, delay, uses_vel, uses_att, master_att,
        accel_mis]."""
        def o(s):
            return -1 if s is None else s.start
        return np.array([o(self.att), o(self.vel), o(self.gyro), o(self.accel), o(self.mount),
                         o(self.flex_ang), o(self.flex_rate), o(self.lever),
                         -1 if self.delay is None else self.delay, int(self.uses_vel), int(self.uses_att),
                         o(self.master_att), o(self.accel_mis)], dtype=np.int64)


def make_layout(match: str, *, flexure: bool = False, lever_arm: bool = False, delay: bool = False,
                board_errors: bool = False) -> StateLayout:
    """State layout per matching mode. Velocity states (and the accel bias, which only acts through
    them) are carried when velocity is matched; mounting (and flexure) when attitude is matched.
    ``board_errors``: the master's attitude error as a Markov state (attitude matched) and the slave's
    accelerometer triad misalignment (velocity matched), appended after the others."""
    if match not in MATCHES:
        raise ValueError(f"match must be one of {MATCHES}, not {match!r}")
    names: list[str] = []

    def add(prefix: str, axes: str = "xyz") -> slice:
        s = slice(len(names), len(names) + len(axes))
        names.extend(f"{prefix}_{a}" for a in axes)
        return s

    use_vel = "vel" in match
    use_att = "att" in match
    att = add("att_err", "ned")
    vel = add("vel_err", "ned") if use_vel else None
    gyro = add("gyro_bias")
    accel = add("accel_bias") if use_vel else None
    mount = None
    if use_att:
        mount = slice(len(names), len(names) + 3)
        names.extend(["mount_roll", "mount_pitch", "mount_yaw"])
    flex_ang = add("flex_ang") if (flexure and use_att) else None
    flex_rate = add("flex_rate") if (flexure and use_att) else None
    lever = add("lever_arm") if (lever_arm and use_vel) else None
    d = None
    if delay:
        d = len(names)
        names.append("delay")
    master_att = add("master_att_err", "ned") if (board_errors and use_att) else None
    accel_mis = add("accel_misalign") if (board_errors and use_vel) else None
    return StateLayout(match, tuple(names), att, vel, gyro, accel, mount, flex_ang, flex_rate, lever, d,
                       master_att, accel_mis)


def m_av(lat_rad: float, alt_m: float, r_m: float, r_n: float) -> np.ndarray:
    """d(omega_en^n)/d(v^n) (position errors neglected)."""
    return np.array([[0.0, 1.0 / (r_n + alt_m), 0.0],
                     [-1.0 / (r_m + alt_m), 0.0, 0.0],
                     [0.0, -np.tan(lat_rad) / (r_n + alt_m), 0.0]])


def dynamics_matrix(lay: StateLayout, c_ns: np.ndarray, f_n: np.ndarray, w_ie_n: np.ndarray,
                    w_en_n: np.ndarray, vel_n: np.ndarray, mav: np.ndarray,
                    flex_beta: float = 0.0, master_att_tau_s: float = np.inf) -> np.ndarray:
    """Continuous-time error dynamics F (n x n)."""
    f = np.zeros((lay.n, lay.n))
    _fill_dynamics(f, lay.offsets, np.ascontiguousarray(c_ns, float), np.asarray(f_n, float),
                   np.asarray(w_ie_n, float), np.asarray(w_en_n, float), np.asarray(vel_n, float),
                   np.ascontiguousarray(mav, float), float(flex_beta), 1.0 / float(master_att_tau_s))
    return f


@njit
def _sk(v, out, r0, c0, sign):
    """out[r0:r0+3, c0:c0+3] = sign * [v x]"""
    out[r0, c0 + 1] = -sign * v[2]
    out[r0, c0 + 2] = sign * v[1]
    out[r0 + 1, c0] = sign * v[2]
    out[r0 + 1, c0 + 2] = -sign * v[0]
    out[r0 + 2, c0] = -sign * v[1]
    out[r0 + 2, c0 + 1] = sign * v[0]


@njit
def _fill_dynamics(f, off, c_ns, f_n, w_ie, w_en, vel, mav, beta, mk_rate):
    a, v, g, acc = off[0], off[1], off[2], off[3]
    fa, fr = off[5], off[6]
    mk, am = off[11], off[12]
    w_in = w_ie + w_en
    _sk(w_in, f, a, a, -1.0)
    for i in range(3):
        for j in range(3):
            f[a + i, g + j] = -c_ns[i, j]
    if v >= 0:
        _sk(f_n, f, v, a, 1.0)
        cor = 2.0 * w_ie + w_en
        _sk(cor, f, v, v, -1.0)
        # + [vel x] mav
        for i in range(3):
            for j in range(3):
                f[a + i, v + j] = mav[i, j]
                f[v + i, acc + j] = c_ns[i, j]
        vm = np.zeros((3, 3))
        vm[0, 1] = -vel[2]
        vm[0, 2] = vel[1]
        vm[1, 0] = vel[2]
        vm[1, 2] = -vel[0]
        vm[2, 0] = -vel[1]
        vm[2, 1] = vel[0]
        t = vm @ mav
        for i in range(3):
            for j in range(3):
                f[v + i, v + j] += t[i, j]
        if am >= 0:  # - [f^n x] C_ns alpha
            fx = np.zeros((3, 3))
            _sk(f_n, fx, 0, 0, 1.0)
            t = fx @ c_ns
            for i in range(3):
                for j in range(3):
                    f[v + i, am + j] = -t[i, j]
    if mk >= 0:
        for i in range(3):
            f[mk + i, mk + i] = -mk_rate
    if fa >= 0:
        for i in range(3):
            f[fa + i, fr + i] = 1.0
            f[fr + i, fa + i] = -beta * beta
            f[fr + i, fr + i] = -2.0 * beta


# ---- the reference loop's copies (logtools.alignment.kf.run_filter's Python loop): the same blocks as the
# kernels above, each assigned at once, with the scalars as Python floats (tested equal in tests/test_alignment.py).
# Run as plain Python, the element-by-element kernels made the loop about 150 us an epoch; with these, 100 us
def _set_diag3(m: np.ndarray, r: int, c: int, value: float) -> None:
    """m[r + i, c + i] = value, i = 0..2 (m C-contiguous; a strided view, no index arrays)."""
    ncol = m.shape[1]
    start = r * ncol + c
    m.reshape(-1)[start:start + 2 * (ncol + 1) + 1:ncol + 1] = value


def skew3(x: float, y: float, z: float) -> np.ndarray:
    """[v x] of v = (x, y, z)."""
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _neg_skew3(x: float, y: float, z: float) -> np.ndarray:
    """-[v x] of v = (x, y, z) (as ``-skew3``, its zeros negative)."""
    return np.array([[-0.0, z, -y], [-z, -0.0, x], [y, -x, -0.0]])


def fill_dynamics_np(f, off, c_ns, f_n, w_ie, w_en, vel, mav, beta, mk_rate, constant=True):
    """:func:`_fill_dynamics` for the reference loop (``off``: the offsets as a list; ``w_ie``, ``w_en``: any
    sequences of 3 floats). ``constant=False``: the blocks that do not change from segment to segment (the
    Markov and flexure states') are left as they are (the loop's F written over, segment after segment)."""
    a, v, g, acc, _, fa, fr, _, _, _, _, mk, am = off
    ie0, ie1, ie2 = w_ie
    en0, en1, en2 = w_en
    f[a:a + 3, a:a + 3] = _neg_skew3(ie0 + en0, ie1 + en1, ie2 + en2)
    f[a:a + 3, g:g + 3] = -c_ns
    if v >= 0:
        f_x = skew3(*f_n.tolist())
        f[v:v + 3, a:a + 3] = f_x
        f[v:v + 3, v:v + 3] = (_neg_skew3(2.0 * ie0 + en0, 2.0 * ie1 + en1, 2.0 * ie2 + en2)
                               + skew3(*vel.tolist()).dot(mav))
        f[a:a + 3, v:v + 3] = mav
        f[v:v + 3, acc:acc + 3] = c_ns
        if am >= 0:  # - [f^n x] C_ns alpha
            f[v:v + 3, am:am + 3] = -(f_x @ c_ns)
    if not constant:
        return
    if mk >= 0:
        _set_diag3(f, mk, mk, -mk_rate)
    if fa >= 0:
        _set_diag3(f, fa, fr, 1.0)
        _set_diag3(f, fr, fa, -beta * beta)
        _set_diag3(f, fr, fr, -2.0 * beta)


def fill_h_np(h, off, c_ns, c_nm, w_l, w_ns, a_m, constant=True):
    """:func:`_fill_h` for the reference loop (``off``: the offsets as a list). ``constant=False``: the unit
    blocks are left as they are (the loop's H written over, epoch after epoch)."""
    a, v, _, _, mo, fa, _, lev, d, uses_vel, uses_att, mk, _ = off
    row = 0
    if uses_vel:
        if constant:
            _set_diag3(h, 0, v, 1.0)
        if lev >= 0:
            h[0:3, lev:lev + 3] = c_nm @ skew3(*w_l.tolist())
        if d >= 0:
            h[0:3, d] = -a_m
        row = 3
    if uses_att:
        if constant:
            _set_diag3(h, row, a, 1.0)
        h[row:row + 3, mo:mo + 3] = -c_ns
        if fa >= 0:
            h[row:row + 3, fa:fa + 3] = -c_ns
        if d >= 0:
            h[row:row + 3, d] = w_ns
        if mk >= 0 and constant:
            _set_diag3(h, row, mk, 1.0)
    return h


def exp_so3_np(rv: np.ndarray) -> np.ndarray:
    """:func:`exp_so3` for the reference loop."""
    return exp_so3_xyz(*rv.tolist())


def exp_so3_xyz(x: float, y: float, z: float) -> np.ndarray:
    """:func:`exp_so3_np` of the rotation vector (x, y, z)."""
    ang = math.sqrt(x * x + y * y + z * z)
    if ang < 1e-9:
        a, b = 1.0, 0.5
    else:
        a, b = math.sin(ang) / ang, (1.0 - math.cos(ang)) / (ang * ang)
    # I + a [rv x] + b [rv x]^2, element by element
    ax, ay, az, bxy, bxz, byz = a * x, a * y, a * z, b * x * y, b * x * z, b * y * z
    return np.array([[1.0 - b * (y * y + z * z), bxy - az, bxz + ay],
                     [bxy + az, 1.0 - b * (x * x + z * z), byz - ax],
                     [bxz - ay, byz + ax, 1.0 - b * (x * x + y * y)]])


def rotvec_small_np(m: np.ndarray) -> np.ndarray:
    """:func:`rotvec_small` for the reference loop."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = m.tolist()
    c = min(max((m00 + m11 + m22 - 1.0) / 2.0, -1.0), 1.0)
    ang = math.acos(c)
    k = 0.5 if ang < 1e-6 else ang / (2.0 * math.sin(ang))
    return np.array([(m21 - m12) * k, (m02 - m20) * k, (m10 - m01) * k])


def att_residual_np(c_ns_hat: np.ndarray, c_nm: np.ndarray, r_hat: np.ndarray) -> np.ndarray:
    """:func:`att_residual` for the reference loop."""
    return rotvec_small_np(c_nm.dot(r_hat.T).dot(c_ns_hat.T))


def discretise(f: np.ndarray, qc_diag: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Phi = I + F T + (F T)^2 / 2; Qd by the trapezoid (Qc + Phi Qc Phi^T) T / 2 (Qc diagonal)."""
    phi = np.empty_like(f)
    qd = np.empty_like(f)
    _discretise(np.ascontiguousarray(f), np.asarray(qc_diag, float), float(dt_s), phi, qd)
    return phi, qd


@njit
def _discretise(f, qc, dt, phi, qd):
    _discretise_ws(f, qc, dt, phi, qd, discretise_workspace(f.shape[0]))


@njit
def discretise_workspace(n):
    """The work arrays (ft, p, pq, q: (n, n) each) of :func:`_discretise_ws`."""
    return np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))


@njit
def _discretise_ws(f, qc, dt, phi, qd, ws):
    """:func:`_discretise` with its intermediate arrays in ``ws`` (:func:`discretise_workspace`; the filter
    loop's, made once per run): the same operations, none allocated."""
    ft, p, pq, q = ws
    n = f.shape[0]
    for i in range(n):
        for j in range(n):
            ft[i, j] = f[i, j] * dt
    np.dot(ft, ft, p)
    for i in range(n):
        for j in range(n):
            phi[i, j] = ft[i, j] + 0.5 * p[i, j]
        phi[i, i] += 1.0
    for i in range(n):
        for j in range(n):
            pq[i, j] = phi[i, j] * qc[j]  # scales columns
    np.dot(pq, phi.T, q)
    for i in range(n):
        q[i, i] += qc[i]
    for i in range(n):
        for j in range(n):
            qd[i, j] = 0.5 * dt * q[i, j]


def discretise_workspace_np(qc: np.ndarray) -> tuple:
    """The work arrays of :func:`_discretise_np` for one run's loop (made once): F T, Phi Qc, I and diag(Qc)."""
    n = len(qc)
    return np.empty((n, n)), np.empty((n, n)), np.eye(n), np.diag(np.asarray(qc, float))


def _discretise_np(f, qc, dt, phi, qd, ws=None):
    """numpy ``_discretise`` (the reference code: same algebra, array operations, the same numbers as
    ``phi = F T + (F T)^2 / 2`` with 1 added on the diagonal, and so on; a unit matrix added adds zeros
    elsewhere). ``ws``: :func:`discretise_workspace_np`."""
    ft, pq, eye, qcm = ws if ws is not None else discretise_workspace_np(qc)
    np.multiply(f, dt, out=ft)
    np.dot(ft, ft, out=phi)
    phi *= 0.5
    phi += ft
    phi += eye
    np.multiply(phi, qc, out=pq)
    np.dot(pq, phi.T, out=qd)
    qd += qcm
    qd *= 0.5 * dt


#: the discretisation the filter loop calls: compiled, or numpy in reference mode (logtools.jit)
discretise_step = _discretise if HAVE_NUMBA else _discretise_np


def measurement_matrix(lay: StateLayout, c_ns: np.ndarray, *, c_nm: np.ndarray | None = None,
                       w_lever_m: np.ndarray | None = None, w_ns_n: np.ndarray | None = None,
                       a_m_n: np.ndarray | None = None) -> np.ndarray:
    """H for the stacked measurement [z_vel (if matched), z_att (if matched)].
    c_ns: slave attitude (reference, from the master and the mounting estimate); c_nm: master attitude
    (lever arm); w_lever_m: master angular rate used for the lever arm (rad/s, m frame);
    w_ns_n: slave angular rate relative to n, in n (delay); a_m_n: master acceleration in n (delay)."""
    h = np.zeros((lay.n_meas, lay.n))
    z3 = np.zeros(3)
    _fill_h(h, lay.offsets, np.ascontiguousarray(c_ns, float),
            np.eye(3) if c_nm is None else np.ascontiguousarray(c_nm, float),
            z3 if w_lever_m is None else np.asarray(w_lever_m, float),
            z3 if w_ns_n is None else np.asarray(w_ns_n, float),
            z3 if a_m_n is None else np.asarray(a_m_n, float))
    return h


@njit
def _fill_h(h, off, c_ns, c_nm, w_l, w_ns, a_m):
    a, v, mo, fa, lev, d, mk = off[0], off[1], off[4], off[5], off[7], off[8], off[11]
    row = 0
    if off[9]:
        for i in range(3):
            h[i, v + i] = 1.0
        if lev >= 0:
            sk = np.zeros((3, 3))
            _sk(w_l, sk, 0, 0, 1.0)
            t = c_nm @ sk
            for i in range(3):
                for j in range(3):
                    h[i, lev + j] = t[i, j]
        if d >= 0:
            for i in range(3):
                h[i, d] = -a_m[i]
        row = 3
    if off[10]:
        for i in range(3):
            h[row + i, a + i] = 1.0
            for j in range(3):
                h[row + i, mo + j] = -c_ns[i, j]
                if fa >= 0:
                    h[row + i, fa + j] = -c_ns[i, j]
            if d >= 0:
                h[row + i, d] = w_ns[i]
            if mk >= 0:
                h[row + i, mk + i] = 1.0
    return h


# ---- nonlinear measurement functions (what the filter feeds in; Jacobians above are their derivatives)
@njit
def rotvec_small(m: np.ndarray) -> np.ndarray:
    """Rotation vector of a DCM close to identity (exact log map for angles < pi)."""
    c = min(max((m[0, 0] + m[1, 1] + m[2, 2] - 1.0) / 2.0, -1.0), 1.0)
    ang = np.arccos(c)
    w = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    k = 0.5 if ang < 1e-6 else ang / (2.0 * np.sin(ang))
    return w * k


def att_residual(c_ns_hat: np.ndarray, c_nm: np.ndarray, r_hat: np.ndarray) -> np.ndarray:
    """z_att = rotvec(C_ns_ref C_ns_hat^T), C_ns_ref = C_nm R_hat^T."""
    return rotvec_small(c_nm @ r_hat.T @ c_ns_hat.T)


def vel_residual(v_hat_n: np.ndarray, v_m_n: np.ndarray, c_nm: np.ndarray, w_lever_m: np.ndarray,
                 lever_m: np.ndarray) -> np.ndarray:
    """z_vel = v_hat - (v_m + C_nm (w x l_hat))."""
    return v_hat_n - v_m_n - c_nm @ np.cross(w_lever_m, lever_m)


@njit
def exp_so3(rv: np.ndarray) -> np.ndarray:
    """DCM of a rotation vector (Rodrigues)."""
    ang = np.sqrt(rv[0] ** 2 + rv[1] ** 2 + rv[2] ** 2)
    k = np.zeros((3, 3))
    _sk(rv, k, 0, 0, 1.0)
    if ang < 1e-9:
        a, b = 1.0, 0.5
    else:
        a, b = np.sin(ang) / ang, (1.0 - np.cos(ang)) / ang**2
    return np.eye(3) + a * k + b * (k @ k)
