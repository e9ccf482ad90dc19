"""Transfer-alignment filters: the time loop at the measurement rate with the slave mechanised between
updates (closed loop), the Kalman update (Joseph form, Cholesky solves), the delay-augmented KF
("kf-delay"), S004's split ("kf-split": the constant part shifted before the filter, the residual as a
delay state restricted to one update period), the H-infinity updates of ``hinf.py`` ("hinf", "ahinf")
and a Rauch-Tung-Striebel smoother over the stored forward pass.

Closed loop: after every update the attitude, velocity, mounting, lever-arm and delay estimates are fed
back into the nominal (slave mechanisation, mounting R_hat, lever arm, tau_hat) and those error states
reset to zero; gyro/accel biases and flexure stay in the state (their model is linear: exact).
The smoother runs on the error state relative to the post-feedback nominal of each epoch; the error of
the smoothed state at epoch k+1 relative to the pre-feedback nominal is x_s + fb_{k+1} (first order).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.lapack import dpotrf as _potrf, dpotrs as _potrs

from logtools import earth
from logtools.conventions import dcm_from_quat, quat_from_dcm
from logtools.errors import AnalysisError
from logtools.strapdown import HAVE_NUMBA, _WIE, _radii, nav_step, nav_step_np, njit, rotvec_times_quat

from .options import FilterKind
from .model import (StateLayout, _discretise_np, _discretise_ws, _fill_dynamics, _fill_h, att_residual_np,
                    discretise_step, discretise_workspace, discretise_workspace_np, exp_so3, exp_so3_np,
                    exp_so3_xyz, fill_dynamics_np, fill_h_np, rotvec_small)



# ---- measurement updates ------------------------------------------------------------------------
def kf_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Kalman update, Joseph form; gain from a Cholesky solve of the innovation covariance.
    Returns (x_post, P_post, info) with info = {innovation, nis}."""
    e = z - H @ x
    ph = P @ H.T
    s = H @ ph + R
    cf = cho_factor(s, lower=True, check_finite=False)
    k = cho_solve(cf, ph.T, check_finite=False).T
    x_post = x + k @ e
    ikh = np.eye(len(x)) - k @ H
    p_post = ikh @ P @ ikh.T + k @ R @ k.T
    p_post = 0.5 * (p_post + p_post.T)
    nis = float(e @ cho_solve(cf, e, check_finite=False))
    return x_post, p_post, {"innovation": e, "nis": nis}


@njit
def _chol(s):
    """Cholesky factor (lower) of a small SPD matrix (a loop: cheaper to compile than LAPACK)."""
    l = np.empty_like(s)
    _chol_into(s, l)
    return l


@njit
def _chol_solve_into(l, b, y):
    """Solve (L L^T) Y = B for lower-triangular L (forward then back substitution), into ``y``."""
    m = l.shape[0]
    for c in range(b.shape[1]):
        for i in range(m):
            acc = b[i, c]
            for k in range(i):
                acc -= l[i, k] * y[k, c]
            y[i, c] = acc / l[i, i]
        for i in range(m - 1, -1, -1):
            acc = y[i, c]
            for k in range(i + 1, m):
                acc -= l[k, i] * y[k, c]
            y[i, c] = acc / l[i, i]


@njit
def _chol_into(s, l):
    """:func:`_chol` into ``l`` (the same arithmetic; l's upper triangle zeroed)."""
    m = s.shape[0]
    for i in range(m):
        for j in range(m):
            l[i, j] = 0.0
    for j in range(m):
        d = s[j, j]
        for k in range(j):
            d -= l[j, k] * l[j, k]
        if d <= 0.0:
            d = 1e-300
        l[j, j] = np.sqrt(d)
        for i in range(j + 1, m):
            acc = s[i, j]
            for k in range(j):
                acc -= l[i, k] * l[j, k]
            l[i, j] = acc / l[j, j]


@njit
def kf_workspace(n, m):
    """The work arrays of :func:`kf_step_ws` for n states and m measurements: made once per filter run, not
    per epoch."""
    return (np.empty(n), np.empty(n), np.empty(m), np.empty(m), np.empty((n, n)), np.empty((n, n)),
            np.empty((n, n)), np.empty((n, n)), np.empty((n, m)), np.empty((n, m)), np.empty((n, m)),
            np.empty((n, m)), np.empty((m, n)), np.empty((m, n)), np.empty((m, m)), np.empty((m, m)),
            np.empty((m, 1)), np.empty((m, 1)))


@njit
def kf_step_ws(x, P, phi, qd, z, H, r_diag, e_out, ws):
    """Compiled predict (when phi has rows) + Joseph update, the same algebra as :func:`kf_update`, its
    intermediate arrays in ``ws`` (:func:`kf_workspace`; the filter loop's, made once per run: some twenty
    allocations per epoch fewer than the matrix expressions made; the same numbers to the bit,
    tests/test_alignment.py). Updates x, P in place, writes the prior innovation into e_out, returns the NIS."""
    (xn, kx, hx, e, t1, t2, t3, ikh, ph, k, negk, kr, pht, kt, s, l, e_col, se) = ws
    n = x.shape[0]
    m = z.shape[0]
    if phi.shape[0] == n:
        np.dot(phi, x, xn)
        np.dot(phi, P, t1)
        np.dot(t1, phi.T, t2)
        for i in range(n):
            x[i] = xn[i]
            for j in range(n):
                P[i, j] = t2[i, j] + qd[i, j]
    np.dot(H, x, hx)
    for i in range(m):
        e[i] = z[i] - hx[i]
        e_out[i] = e[i]
    np.dot(P, H.T, ph)
    np.dot(H, ph, s)
    for i in range(m):
        s[i, i] += r_diag[i]
    _chol_into(s, l)
    for i in range(m):
        for j in range(n):
            pht[i, j] = ph[j, i]
    _chol_solve_into(l, pht, kt)
    for i in range(n):
        for j in range(m):
            k[i, j] = kt[j, i]
    np.dot(k, e, kx)
    for i in range(n):
        x[i] += kx[i]
    for i in range(n):
        for j in range(m):
            negk[i, j] = -k[i, j]
            kr[i, j] = k[i, j] * r_diag[j]
    np.dot(negk, H, ikh)
    for i in range(n):
        ikh[i, i] += 1.0
    np.dot(ikh, P, t1)
    np.dot(t1, ikh.T, t2)
    np.dot(kr, k.T, t3)
    for i in range(n):
        for j in range(n):
            t1[i, j] = t2[i, j] + t3[i, j]
    for i in range(n):
        for j in range(n):
            P[i, j] = 0.5 * (t1[i, j] + t1[j, i])
    for i in range(m):
        e_col[i, 0] = e[i]
    _chol_solve_into(l, e_col, se)
    nis = 0.0
    for i in range(m):
        nis += e[i] * se[i, 0]
    return nis


@njit
def kf_step_nb(x, P, phi, qd, z, H, r_diag, e_out):
    """Compiled predict (when phi has rows) + Joseph update; same algebra as :func:`kf_update`.
    Updates x, P in place, writes the prior innovation into e_out, returns the NIS (:func:`kf_step_ws`
    with its work arrays made for this call)."""
    return kf_step_ws(x, P, phi, qd, z, H, r_diag, e_out, kf_workspace(x.shape[0], z.shape[0]))


@njit
def _dcm(q):
    w, x, y, z = q[0], q[1], q[2], q[3]
    nn = w * w + x * x + y * y + z * z
    w, x, y, z = w / np.sqrt(nn), x / np.sqrt(nn), y / np.sqrt(nn), z / np.sqrt(nn)
    m = np.empty((3, 3))
    m[0, 0] = 1 - 2 * (y * y + z * z)
    m[0, 1] = 2 * (x * y - w * z)
    m[0, 2] = 2 * (x * z + w * y)
    m[1, 0] = 2 * (x * y + w * z)
    m[1, 1] = 1 - 2 * (x * x + z * z)
    m[1, 2] = 2 * (y * z - w * x)
    m[2, 0] = 2 * (x * z - w * y)
    m[2, 1] = 2 * (y * z + w * x)
    m[2, 2] = 1 - 2 * (x * x + y * y)
    return m


@njit
def _q_left_rotvec(rv, q):
    """q(rv) * q, normalised"""
    ang = np.sqrt(rv[0] ** 2 + rv[1] ** 2 + rv[2] ** 2)
    k = np.sin(0.5 * ang) / ang if ang > 1e-8 else 0.5 - ang * ang / 48.0
    pw, px, py, pz = np.cos(0.5 * ang), rv[0] * k, rv[1] * k, rv[2] * k
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    out = np.empty(4)
    out[0] = pw * qw - px * qx - py * qy - pz * qz
    out[1] = pw * qx + px * qw + py * qz - pz * qy
    out[2] = pw * qy - px * qz + py * qw + pz * qx
    out[3] = pw * qz + px * qy - py * qx + pz * qw
    return out / np.sqrt((out * out).sum())


# ---- the reference loop's scalar helpers: the kernels' algebra with Python floats (the kernels themselves,
# element by element on numpy scalars, cost 2-4x more each as plain Python); checked against the kernels in
# tests/test_alignment.py
_Z3 = np.zeros(3)
_EYE3 = np.eye(3)
_Z3.flags.writeable = _EYE3.flags.writeable = False


def _dcm_np(q: np.ndarray) -> np.ndarray:
    """:func:`_dcm` for the reference loop."""
    w, x, y, z = q.tolist()
    nn = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / nn, x / nn, y / nn, z / nn
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _q_left_rotvec_np(rv: np.ndarray, q: np.ndarray) -> np.ndarray:
    """:func:`_q_left_rotvec` for the reference loop."""
    return _q_left_rotvec_xyz(*rv.tolist(), q)


def _q_left_rotvec_xyz(x: float, y: float, z: float, q: np.ndarray) -> np.ndarray:
    """:func:`_q_left_rotvec_np` of the rotation vector (x, y, z)."""
    ow, ox, oy, oz = rotvec_times_quat(x, y, z, *q.tolist())
    nn = math.sqrt(ow * ow + ox * ox + oy * oy + oz * oz)
    return np.array([ow / nn, ox / nn, oy / nn, oz / nn])


def _index_np(ts: np.ndarray, t: float) -> tuple[int, float]:
    """:func:`_index` for the reference loop."""
    i = min(max(int(ts.searchsorted(t, "right")) - 1, 0), len(ts) - 2)
    t0, t1 = ts[i:i + 2].tolist()
    return i, min(max((t - t0) / (t1 - t0), -1.0), 2.0)


def _rotvec_np(q: np.ndarray) -> np.ndarray:
    """:func:`_rotvec_nb` for the reference loop: the rotation vector of a quaternion."""
    w, x, y, z = q.tolist()
    vn = math.sqrt(x * x + y * y + z * z)
    if vn < 1e-12:
        return 2.0 * q[1:] / max(w, 1e-300)
    return q[1:] * (2.0 * math.atan2(vn, w) / vn)


def _cross3_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`_cross3` for the reference loop."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


# ---- inputs ---------------------------------------------------------------------------------------
@njit
def _index(ts: np.ndarray, t: float) -> tuple[int, float]:
    """(i, a): t between ts[i] and ts[i + 1] at the fraction a (clamped to [-1, 2] beyond the ends); the
    Python lookups' and the compiled loop's."""
    i = np.searchsorted(ts, t, side="right") - 1
    i = min(max(i, 0), len(ts) - 2)
    a = (t - ts[i]) / (ts[i + 1] - ts[i])
    return i, min(max(a, -1.0), 2.0)


@dataclass(frozen=True)
class MasterSeries:
    """Master quantities on the master's stamps (relative seconds), linearly interpolated on demand."""

    t_s: np.ndarray
    quat: np.ndarray | None  # (K, 4) continuous sign
    vel: np.ndarray | None  # (K, 3)
    acc: np.ndarray | None  # (K, 3) d(vel)/dt
    w_nm_m: np.ndarray | None  # (K, 3) master body rate relative to NED, master frame (lever arm)
    valid: np.ndarray | None = None  # (K,) False where the master's output is unusable (frozen, jumps)
    reset_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # attitude resets (jumps)
    #: the stamps of ``w_nm_m`` where they are not ``t_s``: the master's gyro at its own rate (a vibration
    #: between two navigation samples is in the slave's velocity through the lever arm, and rates
    #: interpolated from the navigation rate do not have it)
    w_t_s: np.ndarray | None = None
    #: (K-1,) True at the steps of ``t_s`` that are gaps in the master's output (run._nav_gaps: no measurement
    #: across them), worked out once by run._master_series
    gap: np.ndarray | None = None

    @property
    def w_stamps_s(self) -> np.ndarray:
        """The stamps of ``w_nm_m``."""
        return self.t_s if self.w_t_s is None else self.w_t_s

    def usable(self, t: float) -> bool:
        """Both master samples around t are valid."""
        return self._usable_at(self._idx(t)[0])

    def _usable_at(self, i: int) -> bool:
        return self.valid is None or bool(self.valid[i] and self.valid[i + 1])

    def _idx(self, t: float) -> tuple[int, float]:
        return _index_np(self.t_s, t)

    def sample(self, t: float) -> tuple:
        """(C_nm or None, v or None, a or None, w_nm_m or None) at relative time t."""
        return self._sample_at(*self._idx(t), t)

    def sample_epochs(self, t: np.ndarray) -> tuple[np.ndarray, tuple]:
        """:meth:`_usable_at` and :meth:`sample` at every ``t`` at once (the reference loop's epochs where the
        delay is not a state, so that the instants are known before the loop): (usable (K,), (C_nm (K, 3, 3),
        v, a, w_nm_m (K, 3)), each None where :meth:`sample` gives None). Element by element the same
        operations in the same order as the scalar lookups, so the same numbers."""
        ts = self.t_s
        i = np.clip(ts.searchsorted(t, "right") - 1, 0, len(ts) - 2)
        a = np.clip((t - ts[i]) / (ts[i + 1] - ts[i]), -1.0, 2.0)[:, None]
        b = 1.0 - a
        usable = np.ones(len(t), bool) if self.valid is None else (self.valid[i] & self.valid[i + 1])
        c_nm = v = acc = w = None
        if self.quat is not None:
            c_nm = dcm_from_quat(b * self.quat[i] + a * self.quat[i + 1])  # (_dcm_np's numbers)
        if self.vel is not None:
            v = b * self.vel[i] + a * self.vel[i + 1]
            acc = b * self.acc[i] + a * self.acc[i + 1]
        if self.w_nm_m is not None:
            tw = self.w_stamps_s
            j = np.clip(tw.searchsorted(t, "right") - 1, 0, len(tw) - 2)
            aw = np.clip((t - tw[j]) / (tw[j + 1] - tw[j]), -1.0, 2.0)[:, None]
            w = (1.0 - aw) * self.w_nm_m[j] + aw * self.w_nm_m[j + 1]
        return usable, (c_nm, v, acc, w)

    def _sample_at(self, i: int, a: float, t: float) -> tuple:
        """:meth:`sample` between master samples i and i + 1 at the fraction a (:meth:`_idx` of t)."""
        b = 1.0 - a
        c_nm = v = acc = w = None
        if self.quat is not None:
            c_nm = _dcm_np(b * self.quat[i] + a * self.quat[i + 1])
        if self.vel is not None:
            v = b * self.vel[i] + a * self.vel[i + 1]
            acc = b * self.acc[i] + a * self.acc[i + 1]
        if self.w_nm_m is not None:  # (on its own stamps)
            j, aw = _index_np(self.w_stamps_s, t)
            w = (1.0 - aw) * self.w_nm_m[j] + aw * self.w_nm_m[j + 1]
        return c_nm, v, acc, w


@dataclass(frozen=True)
class AlignInputs:
    """Everything the time loop needs, prepared by run.py (vectorised)."""

    t_epoch_s: np.ndarray  # (M+1,) slave stamps of the updates (relative to the master's t0)
    seg_dq: np.ndarray  # (M, 4) slave body rotation over each segment
    seg_dv_b: np.ndarray  # (M, 3) slave velocity increment, body frame at segment start
    seg_dt_s: np.ndarray  # (M,)
    master: MasterSeries
    q0: np.ndarray  # slave initial attitude (body->NED)
    v0: np.ndarray
    llh0: np.ndarray  # lat rad, lon rad, alt m
    r0: np.ndarray  # coarse mounting R (v_slave = R v_master)
    lever0_m: np.ndarray = field(default_factory=lambda: np.zeros(3))  # master frame, master -> slave
    tau0_s: float = 0.0  # initial delay estimate (known constant part for kf-split)
    #: (M+1,) True at the epochs that end a segment over a gap in the slave's IMU: the slave's navigation
    #: restarts there from the master (attitude through the mounting, velocity) and the gap's segment is not
    #: propagated (its increments are not known); empty: none
    restart: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


@dataclass(frozen=True)
class FilterSettings:
    kind: FilterKind
    layout: StateLayout
    p0_sigma: np.ndarray  # (n,) initial sigmas
    qc: np.ndarray  # (n,) continuous process noise densities^2 on each state
    r_vel_m_s: float
    r_att_rad: float
    flex_beta: float = 0.0
    master_att_tau_s: float = np.inf  # correlation time of the master's attitude error state (board_errors)
    delay_bounds_s: tuple[float, float] = (-1.0, 1.0)
    hinf_gamma: float = 1.0
    smoother: bool = False
    att_only_fej: bool = False  # AlignmentConfig.att_only_fej
    dynamics_fej: bool = False  # AlignmentConfig.dynamics_fej
    #: (n, n) initial covariance where the prior correlates states (the board's states: the coarse start's
    #: error and the accelerometer misalignment, run._board_prior_cov); its diagonal is p0_sigma^2.
    #: None: diag(p0_sigma^2)
    p0_cov: np.ndarray | None = None


@dataclass
class FilterRun:
    """Forward pass (and smoother) output. Arrays over epochs k = 0..M."""

    t_s: np.ndarray
    x: np.ndarray  # (M+1, n) posterior error state before feedback (biases, flexure: the estimate)
    p_diag: np.ndarray  # (M+1, n)
    r_hat: np.ndarray  # (M+1, 3, 3) mounting estimate after feedback
    p_mount: np.ndarray  # (M+1, 3, 3) covariance of the mounting error (slave frame) or of phi (vel)
    tau_hat: np.ndarray  # (M+1,)
    lever_hat: np.ndarray  # (M+1, 3)
    innov: np.ndarray  # (M+1, m) innovations (nan at epochs without update)
    nis: np.ndarray  # (M+1,)
    c_ns: np.ndarray  # (M+1, 3, 3) slave attitude after feedback
    c_nm: np.ndarray | None  # (M+1, 3, 3) master attitude at the measurement instants
    gamma: np.ndarray  # (M+1,) H-infinity gamma used (inf for the KF)
    n_skipped: int = 0  # epochs without a usable master sample (prediction only)
    n_reinit: int = 0  # slave attitude restarts at master attitude resets
    n_restart: int = 0  # slave navigation restarts after gaps in the slave's IMU
    smoothed: bool = False
    p_mount_fwd: np.ndarray | None = None  # forward-filter p_mount (kept when smoothed)


def _initial_cov(s: FilterSettings) -> np.ndarray:
    if s.p0_cov is not None:
        return np.array(s.p0_cov, float)
    return np.diag(np.asarray(s.p0_sigma, float) ** 2)


def _r_diag(lay: StateLayout, s: FilterSettings) -> np.ndarray:
    """The measurement noise variances (velocity rows, then attitude rows)."""
    return np.concatenate([[s.r_vel_m_s**2] * 3 if lay.uses_vel else [],
                           [s.r_att_rad**2] * 3 if lay.uses_att else []]).astype(float)


def _feedback_mask(lay: StateLayout) -> np.ndarray:
    """The states fed back into the nominal after each update (and reset to zero)."""
    mask = np.zeros(lay.n, np.bool_)
    for sl in (lay.att, lay.vel, lay.mount, lay.lever):
        if sl is not None:
            mask[sl] = True
    if lay.delay is not None:
        mask[lay.delay] = True
    return mask


def run_filter(inp: AlignInputs, s: FilterSettings, *, progress: Callable | None = None,
               compiled: bool = True) -> FilterRun:
    """The forward pass (closed loop), then the RTS smoother where asked for. Raises AnalysisError when
    the filter diverges (non-finite). The KF kinds run as one compiled loop (``compiled=True``, the
    default: :func:`run_filter_compiled`); this Python loop is the reference and runs the H-infinity kinds.

    Each epoch: :func:`_propagate` (error dynamics, slave mechanised over the segment) -> the master
    sampled at t_k - tau_hat -> :func:`_restarts` (master attitude resets, gaps in the slave's IMU) ->
    :func:`_measurement` -> :meth:`_Updater.update` -> :func:`_feedback` -> :meth:`_Histories.record`."""
    if compiled and HAVE_NUMBA and not s.kind.is_hinf:
        run = run_filter_compiled(inp, s)
        if progress is not None:
            progress(1.0, "alignment filter")
        return run
    lay = s.layout
    ne = len(inp.seg_dt_s) + 1
    seg = _Segments.of(inp)
    upd = _Updater.for_settings(s)
    hist = _Histories.empty(ne, lay, s.smoother, lay.uses_att or inp.master.quat is not None)
    st = _LoopState.start(inp, s)
    restart = np.zeros(ne, bool)
    if len(inp.restart):
        restart[:] = np.asarray(inp.restart, bool)
    master = inp.master
    prog_every = max(ne // 50, 1)
    restart_k, t_epoch = restart.tolist(), inp.t_epoch_s.tolist()
    # without a delay state the master's instants t_k - tau are known before the loop: sampled at once
    ms_all = fixed_all = None
    if lay.delay is None:
        usable_all, cols = master.sample_epochs(inp.t_epoch_s - st.tau)
        usable_all = usable_all.tolist()
        ms_all = list(zip(*(list(c) if c is not None else [None] * ne for c in cols)))
        fixed_all = _fixed_terms(st, lay, s.att_only_fej, cols, ne)
    for k in range(ne):
        phi_k, qd_k = _propagate(st, inp, seg, s, k, restart_k[k]) if k > 0 else (_NO_PHI, _NO_PHI)
        tk = t_epoch[k]
        if ms_all is None:
            t_m = tk - st.tau
            i_m, a_m = master._idx(t_m)
            ms_k = master._sample_at(i_m, a_m, t_m)
            usable = master._usable_at(i_m)
        else:
            ms_k = ms_all[k]
            usable = usable_all[k]
        st.c_nm_prev = ms_k[0]
        _restarts(st, inp, lay, k, restart_k[k], ms_k)
        if not usable:
            # no usable master sample: prediction only
            if k > 0:
                st.x = phi_k @ st.x
                st.P = phi_k @ st.P @ phi_k.T + qd_k
                hist.keep_prediction(k, phi_k, st.x, st.P)
            hist.record_state(k, st.x, st.P)
            hist.record(k, st, lay, ms_k[0], 0.0)
            st.n_skipped += 1
            continue
        z, H = _measurement(st, inp, lay, s.att_only_fej, k, ms_k, None if fixed_all is None else fixed_all[k])
        e_prior, nis_k, gam_k = upd.update(st, phi_k, qd_k, z, H, k)
        if hist.keep and k > 0:
            hist.keep_prediction(k, phi_k, phi_k @ hist.sm_xf[k - 1], phi_k @ hist.sm_pf[k - 1] @ phi_k.T + qd_k)
        hist.innov[k] = e_prior
        hist.nis[k] = nis_k
        hist.gamma[k] = gam_k
        if not (math.isfinite(st.x.sum()) and math.isfinite(st.P.sum())):  # (a NaN or inf anywhere: not finite)
            raise AnalysisError(f"alignment filter diverged at t = {tk:.2f} s (non-finite state)")
        hist.record_state(k, st.x, st.P)
        fb = _feedback(st, lay, s.delay_bounds_s)
        hist.record(k, st, lay, ms_k[0], fb)
        if progress is not None and k % prog_every == 0:
            progress(k / ne, "alignment filter")
    if st.n_skipped == ne:
        raise AnalysisError("the master's attitude/velocity is unusable (frozen or jumping) over the whole overlap")
    return hist.to_run(inp, lay, st)


_NO_PHI = np.zeros((0, 0))  # "no prediction" (the first epoch)


@dataclass(frozen=True)
class _Segments:
    """What the reference loop's propagation takes from each segment's increments alone, worked out before the
    loop (element by element the same operations as in it): the step as Python floats, the mean specific
    force in the body frame (dv / dt) and the turn over the segment's first half (the midpoint attitude,
    :func:`_mid_segment`)."""

    dt_s: list
    dv_dt: np.ndarray  # (M, 3)
    half_turn: np.ndarray  # (M, 3, 3): exp_so3_np(0.5 * _rotvec_np(seg_dq[j]))

    @classmethod
    def of(cls, inp: AlignInputs) -> "_Segments":
        dt = np.asarray(inp.seg_dt_s, float)
        return cls(dt.tolist(), inp.seg_dv_b / dt[:, None], _exp_so3_many(0.5 * _rotvec_many(inp.seg_dq)))


def _rotvec_many(q: np.ndarray) -> np.ndarray:
    """:func:`_rotvec_np` of each row of ``q`` (M, 4) (math's atan2, as the scalar code: numpy's may differ by
    an ulp)."""
    w, x, y, z = (np.asarray(c, float) for c in np.asarray(q, float).T)
    vn = np.sqrt(x * x + y * y + z * z)
    small = vn < 1e-12
    k = np.array([0.0 if s else 2.0 * math.atan2(a, b) / a for a, b, s in zip(vn.tolist(), w.tolist(), small.tolist())])
    out = q[:, 1:] * k[:, None]
    if small.any():
        out[small] = 2.0 * q[small, 1:] / np.maximum(w[small], 1e-300)[:, None]
    return out


def _exp_so3_many(rv: np.ndarray) -> np.ndarray:
    """:func:`exp_so3_np` of each row of ``rv`` (M, 3): (M, 3, 3), element by element the same operations."""
    x, y, z = (np.ascontiguousarray(c) for c in rv.T)
    ang = np.sqrt(x * x + y * y + z * z)
    tiny = ang < 1e-9
    safe = np.where(tiny, 1.0, ang)
    a = np.where(tiny, 1.0, np.sin(safe) / safe)
    b = np.where(tiny, 0.5, (1.0 - np.cos(safe)) / (safe * safe))
    ax, ay, az, bxy, bxz, byz = a * x, a * y, a * z, b * x * y, b * x * z, b * y * z
    m = np.empty((len(ang), 3, 3))
    m[:, 0, 0], m[:, 0, 1], m[:, 0, 2] = 1.0 - b * (y * y + z * z), bxy - az, bxz + ay
    m[:, 1, 0], m[:, 1, 1], m[:, 1, 2] = bxy + az, 1.0 - b * (x * x + z * z), byz - ax
    m[:, 2, 0], m[:, 2, 1], m[:, 2, 2] = bxz - ay, byz + ax, 1.0 - b * (x * x + y * y)
    return m


@dataclass
class _LoopState:
    """The reference loop's running values: the nominal (slave attitude, velocity, position, mounting,
    lever arm, delay), the error state and its covariance, and the event counts."""

    q: np.ndarray
    v: np.ndarray
    llh: np.ndarray
    r_hat: np.ndarray
    r_fej: np.ndarray  # the first-estimate mounting (H of velocity matching)
    lever: np.ndarray
    tau: float
    x: np.ndarray
    P: np.ndarray
    p0_var: np.ndarray
    qc: np.ndarray
    fb_mask: np.ndarray
    off: list  # the layout's offsets (StateLayout.offsets) as Python ints
    q_new: np.ndarray = field(default_factory=lambda: np.empty(4))  # nav_step's output buffers
    v_new: np.ndarray = field(default_factory=lambda: np.empty(3))
    llh_new: np.ndarray = field(default_factory=lambda: np.empty(3))
    n_reinit: int = 0
    n_restart: int = 0
    n_skipped: int = 0
    c_nm_prev: np.ndarray | None = None  # the master's attitude sampled at the previous epoch
    #: F of the last segment and H of the last epoch (their constant blocks written once: fill_dynamics_np and
    #: fill_h_np with constant=False after), Phi and Qd of the last segment (read within the epoch only)
    f_buf: np.ndarray | None = None
    h_buf: np.ndarray | None = None
    phi_buf: np.ndarray | None = None
    qd_buf: np.ndarray | None = None
    disc_ws: tuple | None = None  # _discretise_np's work arrays (reference mode; None: the compiled kernel)
    dynamics_fej: bool = False  # _dynamics_fej of the settings

    @classmethod
    def start(cls, inp: AlignInputs, s: FilterSettings) -> "_LoopState":
        r_hat = np.array(inp.r0, float)
        return cls(q=np.array(inp.q0, float), v=np.array(inp.v0, float), llh=np.array(inp.llh0, float),
                   r_hat=r_hat, r_fej=r_hat.copy(), lever=np.array(inp.lever0_m, float), tau=float(inp.tau0_s),
                   x=np.zeros(s.layout.n), P=np.ascontiguousarray(_initial_cov(s)),
                   p0_var=np.asarray(s.p0_sigma, float) ** 2, qc=np.asarray(s.qc, float),
                   fb_mask=_feedback_mask(s.layout), off=s.layout.offsets.tolist(),
                   phi_buf=np.empty((s.layout.n, s.layout.n)), qd_buf=np.empty((s.layout.n, s.layout.n)),
                   disc_ws=None if HAVE_NUMBA else discretise_workspace_np(np.asarray(s.qc, float)),
                   dynamics_fej=_dynamics_fej(s))

    def reset(self, sl: slice) -> None:
        """A state block back to its prior (``_reset_block`` of the compiled loop)."""
        self.P[sl, :] = 0.0
        self.P[:, sl] = 0.0
        self.P[sl, sl] = np.diag(self.p0_var[sl])
        self.x[sl] = 0.0


def _dynamics_fej(s: FilterSettings) -> bool:
    """Whether F is taken at the first estimate C_nm R0^T of the slave's attitude (where H takes the
    mounting's): AlignmentConfig.dynamics_fej, with the board's error states."""
    return bool(s.dynamics_fej and s.layout.has_board_states and (s.layout.uses_vel or s.att_only_fej))


@njit
def _mid_segment(c_ns, dq):
    """C_ns at the middle of a segment: its start turned by half the segment's body rotation ``dq``. The
    biases act through C_ns over the whole segment (the velocity error grows by the integral of C_ns b dt):
    taken at the segment's start, a turning car's lateral accelerometer bias of 12.5 mg leaked into the
    mounting's yaw as b dt / (2 v), 1.0 arcmin at 10 Hz updates and 10 m/s, 2.1 at 5 Hz, at sigmas of 0.37
    (tests/test_alignment.py); the midpoint is the integral to second order."""
    return c_ns @ exp_so3(0.5 * _rotvec_nb(dq))


def _propagate(st: _LoopState, inp: AlignInputs, seg: _Segments, s: FilterSettings, k: int, restart: bool
               ) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, Qd) of segment k-1 -> k from the error dynamics at the segment start; the slave mechanised
    over the segment (st.q, st.v, st.llh). Over a gap in the slave's IMU the error state is not
    propagated through the unknown motion (identity, white noise)."""
    lay = s.layout
    n = lay.n
    j = k - 1
    dt = seg.dt_s[j]
    c_ns = _dcm_np(st.q)
    lat, _, h = st.llh.tolist()
    v = st.v
    v0, v1, _ = v.tolist()
    r_m, r_n = _radii(lat)
    cl, sl_, tl = math.cos(lat), math.sin(lat), math.tan(lat)
    w_ie = (earth.OMEGA_IE_RAD_S * cl, 0.0, -earth.OMEGA_IE_RAD_S * sl_)
    w_en = (v1 / (r_n + h), -v0 / (r_m + h), -v1 * tl / (r_n + h))
    mav = np.array([[0.0, 1.0 / (r_n + h), 0.0], [-1.0 / (r_m + h), 0.0, 0.0], [0.0, -tl / (r_n + h), 0.0]])
    if st.c_nm_prev is not None and st.dynamics_fej:  # AlignmentConfig.dynamics_fej
        c_ns = st.c_nm_prev @ st.r_fej.T
    f_n = c_ns.dot(seg.dv_dt[j])
    c_mid = c_ns.dot(seg.half_turn[j])  # as _mid_segment
    first = st.f_buf is None
    if first:
        st.f_buf = np.zeros((n, n))
    f_buf = st.f_buf
    fill_dynamics_np(f_buf, st.off, c_mid, f_n, w_ie, w_en, v, mav, s.flex_beta, 1.0 / s.master_att_tau_s,
                     constant=first)
    phi_k, qd_k = st.phi_buf, st.qd_buf
    if st.disc_ws is None:
        discretise_step(f_buf, st.qc, dt, phi_k, qd_k)
    else:
        _discretise_np(f_buf, st.qc, dt, phi_k, qd_k, st.disc_ws)
    if restart:  # a gap: the error state is not propagated through unknown motion
        phi_k, qd_k = np.eye(n), np.diag(st.qc * dt)
    nav_step_np(st.q, st.v, st.llh, inp.seg_dq[j], inp.seg_dv_b[j], dt, st.q_new, st.v_new, st.llh_new)
    st.q, st.q_new = st.q_new, st.q
    st.v, st.v_new = st.v_new, st.v
    st.llh, st.llh_new = st.llh_new, st.llh
    return phi_k, qd_k


def _restarts(st: _LoopState, inp: AlignInputs, lay: StateLayout, k: int, restart: bool, ms_k: tuple) -> None:
    """The slave's attitude restarted from the master's where the master's attitude jumped (EKF reset)
    since the last epoch; its navigation restarted from the master's after a gap in its IMU (attitude
    through the mounting estimate, velocity with the lever arm), those error states from their priors."""
    if k == 0:
        return
    c_nm, v_m, _, w_m = ms_k
    resets = inp.master.reset_t_s
    if len(resets):
        t_prev = float(inp.t_epoch_s[k - 1]) - st.tau
        t_now = float(inp.t_epoch_s[k]) - st.tau
        if np.any((resets > t_prev) & (resets <= t_now)) and c_nm is not None:
            st.q = quat_from_dcm(c_nm @ st.r_hat.T)
            st.reset(lay.att)
            st.n_reinit += 1
    if restart:
        if c_nm is not None:
            st.q = quat_from_dcm(c_nm @ st.r_hat.T)
        if v_m is not None:
            cm = c_nm if c_nm is not None else _EYE3
            st.v = v_m + cm @ _cross3_np(w_m if w_m is not None else _Z3, st.lever)
        st.reset(lay.att)
        if lay.vel is not None:
            st.reset(lay.vel)
        st.n_restart += 1


def _fixed_terms(st: _LoopState, lay: StateLayout, att_only_fej: bool, cols: tuple, ne: int) -> list:
    """:func:`_measurement`'s terms that do not depend on the loop's state where the master's samples are
    known before it (``cols``: MasterSeries.sample_epochs'): the lever arm's velocity C_nm (w x l) where the
    lever arm is not a state, the first-estimate attitude C_nm R0^T; per epoch (None: worked out in the loop)."""
    c_nm, _, _, w_m = cols
    lever_v = c_ref = [None] * ne
    if lay.uses_vel and lay.lever is None:
        w = w_m if w_m is not None else np.zeros((ne, 3))
        lv = np.cross(w, st.lever)  # (as _cross3_np)
        lever_v = list(lv if c_nm is None else (c_nm @ lv[:, :, None])[:, :, 0])
    if c_nm is not None and (lay.uses_vel or att_only_fej):
        c_ref = list(c_nm @ st.r_fej.T)
    return list(zip(lever_v, c_ref))


def _measurement(st: _LoopState, inp: AlignInputs, lay: StateLayout, att_only_fej: bool, k: int, ms_k: tuple,
                 fixed_k: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(z, H) at epoch k: velocity (master's, lever arm carried) and/or attitude (through the mounting).
    ``fixed_k``: :func:`_fixed_terms` of the epoch."""
    c_nm, v_m, a_m, w_m = ms_k
    lever_v, c_ref = fixed_k if fixed_k is not None else (None, None)
    z3, eye3 = _Z3, _EYE3
    c_ns = _dcm_np(st.q)
    zs = []
    if lay.uses_vel:
        if lever_v is None:
            wl = w_m if w_m is not None else z3
            cm = c_nm if c_nm is not None else eye3
            lever_v = cm @ _cross3_np(wl, st.lever)
        zs.append(st.v - v_m - lever_v)
    if lay.uses_att:
        zs.append(att_residual_np(c_ns, c_nm, st.r_hat))
    z = np.concatenate(zs) if len(zs) > 1 else zs[0]
    w_ns_n = z3
    if lay.delay is not None and lay.uses_att:
        # slave rate relative to NED in NED: the segment's mean body rate (bias removed) minus w_in
        j = max(k - 1, 0)
        w_b = _rotvec_np(inp.seg_dq[j]) / float(inp.seg_dt_s[j]) - st.x[lay.gyro]
        lat, _, h = st.llh.tolist()
        v0, v1, _ = st.v.tolist()
        r_m, r_n = (float(r) for r in earth.radii_m(lat))
        w_in = np.array([earth.OMEGA_IE_RAD_S * math.cos(lat) + v1 / (r_n + h), -v0 / (r_m + h),
                         -earth.OMEGA_IE_RAD_S * math.sin(lat) - v1 * math.tan(lat) / (r_n + h)])
        w_ns_n = c_ns @ w_b - w_in
    # first-estimate Jacobian: the mounting enters H through the coarse mounting r0, not the running
    # r_hat; feeding back along an unobservable direction would otherwise rotate H and invent
    # information (the EKF inconsistency known from SLAM heading)
    if c_ref is None:
        c_ref = (c_nm @ st.r_fej.T) if c_nm is not None and (lay.uses_vel or att_only_fej) else c_ns
    first = st.h_buf is None
    if first:
        st.h_buf = np.zeros((lay.n_meas, lay.n))
    fill_h_np(st.h_buf, st.off, c_ref, c_nm if c_nm is not None else eye3, w_m if w_m is not None else z3,
              w_ns_n, a_m if a_m is not None else z3, constant=first)
    return z, st.h_buf


def kf_step_np(x, P, phi, qd, z, H, r_diag, e_out, ws=None):
    """numpy :func:`kf_step_nb` (the reference code: the same algebra with LAPACK's Cholesky). ``ws``:
    (diag(r_diag), I) of the loop, made once; adding them adds zeros off the diagonal, so the numbers are
    those of adding r_diag and 1 on the diagonal."""
    n = x.shape[0]
    r_mat, eye = ws if ws is not None else (np.diag(r_diag), np.eye(n))
    if phi.shape[0] == n:  # (ndarray.dot: numpy's matmul, 0.3-0.5 us less a call on these sizes)
        x[:] = phi.dot(x)
        np.dot(phi.dot(P), phi.T, out=P)
        P += qd
    e = e_out
    np.subtract(z, H.dot(x), out=e)
    ph = P.dot(H.T)
    s = H.dot(ph)
    s += r_mat
    l, info = _potrf(s, lower=1, clean=1, overwrite_a=1)
    if info != 0:  # not positive definite: the compiled loop's clamped factor
        l = _chol(H.dot(ph) + r_mat)
    rhs = np.empty((len(e), n + 1))  # [H P, e]: S^-1 of both in one solve
    rhs[:, :n] = ph.T
    rhs[:, n] = e
    sol, _ = _potrs(l, rhs, lower=1, overwrite_b=1)
    k = sol[:, :n].T
    x += k @ e
    ikh = eye - k.dot(H)
    pp = ikh.dot(P).dot(ikh.T)
    pp += (k * r_diag).dot(k.T)
    np.add(pp, pp.T, out=P)
    P *= 0.5
    return float(e @ sol[:, n])


#: the update the reference loop calls: compiled, or numpy in reference mode (logtools.jit)
kf_step = kf_step_nb if HAVE_NUMBA else kf_step_np


@dataclass
class _Updater:
    """The measurement update of one filter kind (KF: Joseph form; H-infinity: hinf.py, with the adaptive
    kind's gamma state)."""

    kind: FilterKind
    r_diag: np.ndarray
    R: np.ndarray
    hinf_gamma: float
    weight: np.ndarray | None = None
    gstate: object = None
    hinf: object = None
    step_ws: tuple | None = None  # kf_step_np's work arrays (reference mode)

    @classmethod
    def for_settings(cls, s: FilterSettings) -> "_Updater":
        r_diag = _r_diag(s.layout, s)
        upd = cls(s.kind, r_diag, np.diag(r_diag), s.hinf_gamma,
                  step_ws=None if HAVE_NUMBA else (np.diag(r_diag), np.eye(s.layout.n)))
        if s.kind.is_hinf:
            try:
                from . import hinf as _hinf
            except ImportError as exc:  # pragma: no cover
                raise AnalysisError(f"filter {s.kind.value} not available ({exc})") from exc
            upd.hinf = _hinf
            if s.kind.is_adaptive:
                upd.gstate = _hinf.initial_gamma_state(sigma0=s.p0_sigma)
            else:
                upd.weight = gstate_weight(s)
        return upd

    def update(self, st: _LoopState, phi_k: np.ndarray, qd_k: np.ndarray, z: np.ndarray, H: np.ndarray, k: int
               ) -> tuple[np.ndarray, float, float]:
        """Predict (k > 0) and update st.x, st.P; (prior innovation, NIS, gamma used)."""
        if not self.kind.is_hinf:
            e_buf = np.zeros(len(z))
            if self.step_ws is None:
                nis_k = kf_step(st.x, st.P, phi_k, qd_k, z, H, self.r_diag, e_buf)
            else:
                nis_k = kf_step_np(st.x, st.P, phi_k, qd_k, z, H, self.r_diag, e_buf, self.step_ws)
            return e_buf, nis_k, np.inf
        if k > 0:
            st.x = phi_k @ st.x
            st.P = phi_k @ st.P @ phi_k.T + qd_k
        e_prior = z - H @ st.x
        if self.kind.is_adaptive:
            st.x, st.P, self.gstate, info = self.hinf.ahinf_update(st.x, st.P, z, H, self.R, self.gstate)
        else:
            st.x, st.P, info = self.hinf.hinf_update(st.x, st.P, z, H, self.R, self.hinf_gamma, weight=self.weight)
        return e_prior, info["nis"], info["gamma"]


def _feedback(st: _LoopState, lay: StateLayout, delay_bounds_s: tuple[float, float]) -> np.ndarray:
    """The error estimates fed back into the nominal and reset to zero; returns what was fed back (the
    smoother's fb; the delay's as clamped to its bounds)."""
    x = st.x
    xl = x.tolist()
    fb = np.where(st.fb_mask, x, 0.0)
    a = lay.att.start  # (_q_left_rotvec_np and exp_so3_np on the floats)
    st.q = _q_left_rotvec_xyz(xl[a], xl[a + 1], xl[a + 2], st.q)
    if lay.vel is not None:
        st.v = st.v - x[lay.vel]
    if lay.mount is not None:
        m = lay.mount.start
        st.r_hat = exp_so3_xyz(-xl[m], -xl[m + 1], -xl[m + 2]).dot(st.r_hat)
    if lay.lever is not None:
        st.lever = st.lever + x[lay.lever]
    if lay.delay is not None:
        lo_tau, hi_tau = delay_bounds_s
        t_new = min(max(st.tau + x[lay.delay], lo_tau), hi_tau)
        fb[lay.delay] = t_new - st.tau
        st.tau = t_new
    st.x = np.where(st.fb_mask, 0.0, x)
    return fb


@dataclass
class _Histories:
    """The per-epoch outputs of the reference loop (and what the smoother needs)."""

    keep: bool
    xs: np.ndarray
    pd: np.ndarray
    r_hist: np.ndarray
    pm_hist: np.ndarray
    tau_hist: np.ndarray
    lev_hist: np.ndarray
    innov: np.ndarray
    nis: np.ndarray
    q_hist: np.ndarray
    cnm_hist: np.ndarray | None
    gamma: np.ndarray
    sm_phi: np.ndarray | None = None
    sm_xpred: np.ndarray | None = None
    sm_ppred: np.ndarray | None = None
    sm_xf: np.ndarray | None = None
    sm_pf: np.ndarray | None = None
    sm_fb: np.ndarray | None = None

    @classmethod
    def empty(cls, ne: int, lay: StateLayout, keep: bool, with_cnm: bool) -> "_Histories":
        n, m = lay.n, lay.n_meas
        h = cls(keep, np.zeros((ne, n)), np.zeros((ne, n)), np.zeros((ne, 3, 3)), np.zeros((ne, 3, 3)),
                np.zeros(ne), np.zeros((ne, 3)), np.full((ne, m), np.nan), np.full(ne, np.nan), np.zeros((ne, 4)),
                np.zeros((ne, 3, 3)) if with_cnm else None, np.full(ne, np.inf))
        if keep:
            h.sm_phi, h.sm_xpred, h.sm_ppred = np.zeros((ne, n, n)), np.zeros((ne, n)), np.zeros((ne, n, n))
            h.sm_xf, h.sm_pf, h.sm_fb = np.zeros((ne, n)), np.zeros((ne, n, n)), np.zeros((ne, n))
        return h

    def keep_prediction(self, k: int, phi_k: np.ndarray, x_pred: np.ndarray, p_pred: np.ndarray) -> None:
        if self.keep:
            self.sm_phi[k] = phi_k
            self.sm_xpred[k] = x_pred
            self.sm_ppred[k] = p_pred

    def record_state(self, k: int, x: np.ndarray, P: np.ndarray) -> None:
        """The posterior error state (before feedback) and its variances."""
        self.xs[k] = x
        self.pd[k] = P.diagonal()

    def record(self, k: int, st: _LoopState, lay: StateLayout, c_nm: np.ndarray | None, fb) -> None:
        """The nominal after epoch k's feedback (and the smoother's filtered values)."""
        self.r_hist[k] = st.r_hat
        if lay.mount is not None:
            self.pm_hist[k] = st.P[lay.mount, lay.mount]
        else:
            cq = _dcm_np(st.q)
            self.pm_hist[k] = cq.T @ st.P[lay.att, lay.att] @ cq
        self.tau_hist[k] = st.tau
        self.lev_hist[k] = st.lever
        self.q_hist[k] = st.q
        if self.cnm_hist is not None and c_nm is not None:
            self.cnm_hist[k] = c_nm
        if self.keep:
            self.sm_xf[k] = st.x
            self.sm_pf[k] = st.P
            self.sm_fb[k] = fb

    def to_run(self, inp: AlignInputs, lay: StateLayout, st: _LoopState) -> FilterRun:
        """The FilterRun (smoothed when asked for)."""
        cnm = self.cnm_hist if (self.cnm_hist is not None and inp.master.quat is not None) else None
        run = FilterRun(inp.t_epoch_s.copy(), self.xs, self.pd, self.r_hist, self.pm_hist, self.tau_hist,
                        self.lev_hist, self.innov, self.nis, dcm_from_quat(self.q_hist), cnm, self.gamma,
                        n_skipped=st.n_skipped, n_reinit=st.n_reinit, n_restart=st.n_restart)
        if self.keep:
            run.p_mount_fwd = run.p_mount.copy()
            _rts(run, lay, self.sm_phi, self.sm_xpred, self.sm_ppred, self.sm_xf, self.sm_pf, self.sm_fb)
        return run



@njit
def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def gstate_weight(s: FilterSettings) -> np.ndarray:
    """H-infinity weight S_bar = diag(1 / sigma0^2): every state measured in units of its prior."""
    sg = np.asarray(s.p0_sigma, float)
    return np.diag(1.0 / np.where(sg > 0, sg, 1.0) ** 2)


def _rts(run: FilterRun, lay: StateLayout, phi, xpred, ppred, xf, pf, fb) -> None:
    """Rauch-Tung-Striebel smoother over the stored forward pass (in place on ``run``)."""
    ne, n = xf.shape
    xs = xf.copy()
    ps = pf.copy()
    for k in range(ne - 2, -1, -1):
        pp = ppred[k + 1]
        cf = cho_factor(0.5 * (pp + pp.T), lower=True, check_finite=False)
        c = cho_solve(cf, phi[k + 1] @ pf[k], check_finite=False).T  # P_f Phi^T P_pred^-1
        x_next = xs[k + 1] + fb[k + 1]
        xs[k] = xf[k] + c @ (x_next - xpred[k + 1])
        pk = pf[k] + c @ (ps[k + 1] - pp) @ c.T
        ps[k] = 0.5 * (pk + pk.T)
    # smoothed totals: nominal after feedback at k combined with the smoothed error
    for k in range(ne):
        if lay.mount is not None:
            run.r_hat[k] = exp_so3(-xs[k, lay.mount]) @ run.r_hat[k]
            run.p_mount[k] = ps[k][lay.mount, lay.mount]
        else:
            c = run.c_ns[k]
            run.c_ns[k] = exp_so3(xs[k, lay.att]) @ c
            run.p_mount[k] = c.T @ ps[k][lay.att, lay.att] @ c
        if lay.lever is not None:
            run.lever_hat[k] = run.lever_hat[k] + xs[k, lay.lever]
        if lay.delay is not None:
            run.tau_hat[k] = run.tau_hat[k] + xs[k, lay.delay]
    run.x = xs
    run.p_diag = np.einsum("kii->ki", ps)
    run.smoothed = True


# ---- the compiled time loop (KF kinds). Same algebra as the Python loop above, which stays the
# reference (H-infinity kinds, compiled=False); tests/test_alignment.py checks they agree. -------------
@njit
def _quat_from_dcm_nb(m):
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    q = np.empty(4)
    if tr > max(m[0, 0], m[1, 1], m[2, 2]):
        s = np.sqrt(1.0 + tr) * 2.0
        q[0] = 0.25 * s
        q[1] = (m[2, 1] - m[1, 2]) / s
        q[2] = (m[0, 2] - m[2, 0]) / s
        q[3] = (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = np.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0)) * 2.0
        q[0] = (m[2, 1] - m[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (m[0, 1] + m[1, 0]) / s
        q[3] = (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] >= m[2, 2]:
        s = np.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0)) * 2.0
        q[0] = (m[0, 2] - m[2, 0]) / s
        q[1] = (m[0, 1] + m[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (m[1, 2] + m[2, 1]) / s
    else:
        s = np.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0)) * 2.0
        q[0] = (m[1, 0] - m[0, 1]) / s
        q[1] = (m[0, 2] + m[2, 0]) / s
        q[2] = (m[1, 2] + m[2, 1]) / s
        q[3] = 0.25 * s
    return q / np.sqrt((q * q).sum())


@njit
def _reset_block(P, x, p0, blk):
    """A 3-state block (from index blk) back to its prior: its covariance rows and columns cleared, its
    variances p0's, its estimate 0 (a restart of the nominal it corrects)."""
    n = P.shape[0]
    for ii in range(3):
        for jj in range(n):
            P[blk + ii, jj] = 0.0
            P[jj, blk + ii] = 0.0
        P[blk + ii, blk + ii] = p0[blk + ii, blk + ii]
        x[blk + ii] = 0.0


@njit
def _nb_propagate(q, v, llh, dq, dv_b, dt, restart_k, offs, qc, beta, mk_rate, f_buf, phi_k, qd_k, q_new, v_new,
                  llh_new, c_nm, r_fej, use_fej, ws):
    """:func:`_propagate` compiled: Phi, Qd of one segment (in place) from the error dynamics at its start,
    then the slave mechanised over it (q, v, llh in place). ``use_fej``: the dynamics at the slave
    attitude's first estimate ``c_nm r_fej^T``. ``ws``: ``model.discretise_workspace``'s arrays."""
    n = phi_k.shape[0]
    c_ns = c_nm @ r_fej.T if use_fej else _dcm(q)
    lat, h = llh[0], llh[2]
    r_m, r_n = _radii(lat)
    cl, sl, tl = np.cos(lat), np.sin(lat), np.tan(lat)
    w_ie = np.zeros(3)
    w_en = np.zeros(3)
    mav = np.zeros((3, 3))
    w_ie[0], w_ie[2] = _WIE * cl, -_WIE * sl
    w_en[0], w_en[1], w_en[2] = v[1] / (r_n + h), -v[0] / (r_m + h), -v[1] * tl / (r_n + h)
    mav[0, 1], mav[1, 0], mav[2, 1] = 1.0 / (r_n + h), -1.0 / (r_m + h), -tl / (r_n + h)
    f_n = c_ns @ (dv_b / dt)
    f_buf[:, :] = 0.0
    _fill_dynamics(f_buf, offs, _mid_segment(c_ns, dq), f_n, w_ie, w_en, v, mav, beta, mk_rate)
    _discretise_ws(f_buf, qc, dt, phi_k, qd_k, ws)
    if restart_k:  # a gap: the error state is not propagated through unknown motion
        for ii in range(n):
            for jj in range(n):
                phi_k[ii, jj] = 1.0 if ii == jj else 0.0
                qd_k[ii, jj] = qc[ii] * dt if ii == jj else 0.0
    nav_step(q, v, llh, dq, dv_b, dt, q_new, v_new, llh_new)
    q[:] = q_new
    v[:] = v_new
    llh[:] = llh_new


@njit
def _nb_master_at(mt, mq, mv, ma, mwt, mw, has_q, has_v, has_w, t, c_nm, v_m, a_m, w_m):
    """:meth:`MasterSeries.sample` compiled: the master at time t into c_nm, v_m, a_m, w_m (those it has; w on
    its own stamps mwt); returns the index of the master sample at or before t."""
    i, al = _index(mt, t)
    if has_q:
        c_nm[:, :] = _dcm((1.0 - al) * mq[i] + al * mq[i + 1])
    if has_v:
        v_m[:] = (1.0 - al) * mv[i] + al * mv[i + 1]
        a_m[:] = (1.0 - al) * ma[i] + al * ma[i + 1]
    if has_w:
        j, aw = _index(mwt, t)
        w_m[:] = (1.0 - aw) * mw[j] + aw * mw[j + 1]
    return i


@njit
def _nb_restarts(t_prev, t_now, resets, restart_k, has_q, has_v, c_nm, v_m, w_m, r_hat, lever, q, v, P, x, p0,
                 a0, v_off):
    """:func:`_restarts` compiled (q, v, P, x in place); returns (attitude restarts at master resets, 1 when
    the navigation restarted after a gap)."""
    n_reinit = 0
    if len(resets) > 0 and has_q:
        hit = False
        for rr in range(len(resets)):
            if resets[rr] > t_prev and resets[rr] <= t_now:
                hit = True
        if hit:
            q[:] = _quat_from_dcm_nb(c_nm @ r_hat.T)
            _reset_block(P, x, p0, a0)
            n_reinit += 1
    if not restart_k:
        return n_reinit, 0
    # after a gap in the slave's IMU: its navigation restarts from the master's (attitude through the
    # mounting estimate, velocity with the lever arm), those error states from their priors
    if has_q:
        q[:] = _quat_from_dcm_nb(c_nm @ r_hat.T)
    if has_v:
        lt = _cross3(w_m, lever)
        v[:] = v_m + c_nm @ lt
    _reset_block(P, x, p0, a0)
    if v_off >= 0:
        _reset_block(P, x, p0, v_off)
    return n_reinit, 1


@njit
def _nb_measurement(k, q, v, llh, x, r_hat, r_fej, lever, c_nm, v_m, a_m, w_m, seg_dq, seg_dt, offs, has_q,
                    att_only_fej, z, h_buf):
    """:func:`_measurement` compiled: z and H of epoch k (in place)."""
    g0, d_i = offs[2], offs[8]
    uses_vel, uses_att = offs[9] == 1, offs[10] == 1
    c_ns = _dcm(q)
    row = 0
    if uses_vel:
        lt = _cross3(w_m, lever)
        zv = v - v_m - c_nm @ lt
        z[0], z[1], z[2] = zv[0], zv[1], zv[2]
        row = 3
    if uses_att:
        za = rotvec_small(c_nm @ r_hat.T @ c_ns.T)
        z[row], z[row + 1], z[row + 2] = za[0], za[1], za[2]
    w_ns = np.zeros(3)
    if d_i >= 0 and uses_att:
        jj = max(k - 1, 0)
        w_b = _rotvec_nb(seg_dq[jj]) / seg_dt[jj] - x[g0:g0 + 3]
        lat, h = llh[0], llh[2]
        r_m, r_n = _radii(lat)
        w_in = np.array([_WIE * np.cos(lat) + v[1] / (r_n + h), -v[0] / (r_m + h),
                         -_WIE * np.sin(lat) - v[1] * np.tan(lat) / (r_n + h)])
        w_ns = c_ns @ w_b - w_in
    c_ref = c_nm @ r_fej.T if has_q and (uses_vel or att_only_fej) else c_ns
    h_buf[:, :] = 0.0
    _fill_h(h_buf, offs, c_ref, c_nm, w_m, w_ns, a_m)


@njit
def _nb_feedback(x, q, v, r_hat, lever, tau, offs, fb_mask, lo_tau, hi_tau, keep, sm_fb_k):
    """:func:`_feedback` compiled (q, v, r_hat, lever, x and the smoother's fb row in place); returns tau."""
    a0, v_off, mo, lev, d_i = offs[0], offs[1], offs[4], offs[7], offs[8]
    n = x.shape[0]
    q[:] = _q_left_rotvec(x[a0:a0 + 3].copy(), q)
    if v_off >= 0:
        v[:] = v - x[v_off:v_off + 3]
    if mo >= 0:
        r_hat[:, :] = exp_so3(-x[mo:mo + 3].copy()) @ r_hat
    if lev >= 0:
        lever[:] = lever + x[lev:lev + 3]
    if keep:
        for ii in range(n):
            sm_fb_k[ii] = x[ii] if fb_mask[ii] else 0.0
    if d_i >= 0:
        t_new = min(max(tau + x[d_i], lo_tau), hi_tau)
        if keep:
            sm_fb_k[d_i] = t_new - tau
        tau = t_new
    for ii in range(n):
        if fb_mask[ii]:
            x[ii] = 0.0
    return tau


@njit
def _nb_record(k, x, P, q, r_hat, tau, lever, c_nm, offs, keep, r_hist, pm_hist, tau_hist, lev_hist, q_hist,
               cnm_hist, sm_xf, sm_pf):
    """:meth:`_Histories.record` compiled."""
    a0, mo = offs[0], offs[4]
    r_hist[k] = r_hat
    if mo >= 0:
        pm_hist[k] = P[mo:mo + 3, mo:mo + 3]
    else:
        cq = _dcm(q)
        pm_hist[k] = cq.T @ np.ascontiguousarray(P[a0:a0 + 3, a0:a0 + 3]) @ cq
    tau_hist[k] = tau
    lev_hist[k] = lever
    q_hist[k] = q
    cnm_hist[k] = c_nm
    if keep:
        sm_xf[k] = x
        sm_pf[k] = P


@njit
def _nb_finite(x, P):
    for ii in range(x.shape[0]):
        if not np.isfinite(x[ii]) or not np.isfinite(P[ii, ii]):
            return False
    return True


@njit
def _kf_loop(t_ep, seg_dq, seg_dv, seg_dt, mt, mq, mv, ma, mwt, mw, mvalid, resets, restart, has_q, has_v, has_w,
             q0, v0, llh0, r0, lever0, tau0, offs, n, m_meas, p0, qc, r_diag, beta, mk_rate, lo_tau, hi_tau,
             fb_mask,
             att_only_fej, dyn_fej, keep, xs, pd, r_hist, pm_hist, tau_hist, lev_hist, innov, nis, q_hist, cnm_hist,
             sm_phi, sm_xpred, sm_ppred, sm_xf, sm_pf, sm_fb, counters):
    """The reference loop of :func:`run_filter` compiled, for the KF kinds, step for step (the ``_nb_*``
    functions). Histories filled in place; counters = [skipped, attitude restarts at resets, the epoch
    of a divergence or -1, restarts after gaps]."""
    ne = len(t_ep)
    a0, v_off = offs[0], offs[1]
    q, v, llh = q0.copy(), v0.copy(), llh0.copy()
    q_new, v_new, llh_new = np.empty(4), np.empty(3), np.empty(3)
    r_hat, r_fej, lever, tau = r0.copy(), r0.copy(), lever0.copy(), tau0
    x = np.zeros(n)
    P = p0.copy()
    f_buf, h_buf = np.zeros((n, n)), np.zeros((m_meas, n))
    e_buf, z = np.zeros(m_meas), np.zeros(m_meas)
    phi_k, qd_k, no_phi = np.eye(n), np.zeros((n, n)), np.zeros((0, 0))
    c_nm = np.eye(3)
    v_m, a_m, w_m = np.zeros(3), np.zeros(3), np.zeros(3)
    ws, dws = kf_workspace(n, m_meas), discretise_workspace(n)
    n_skip = 0
    n_reinit = 0
    for k in range(ne):
        if k > 0:
            j = k - 1
            _nb_propagate(q, v, llh, seg_dq[j], seg_dv[j], seg_dt[j], restart[k], offs, qc, beta, mk_rate, f_buf,
                          phi_k, qd_k, q_new, v_new, llh_new, c_nm, r_fej, dyn_fej, dws)
        tm_ = t_ep[k] - tau
        i = _nb_master_at(mt, mq, mv, ma, mwt, mw, has_q, has_v, has_w, tm_, c_nm, v_m, a_m, w_m)
        if k > 0:
            n_r, n_g = _nb_restarts(t_ep[k - 1] - tau, tm_, resets, restart[k], has_q, has_v, c_nm, v_m, w_m,
                                    r_hat, lever, q, v, P, x, p0, a0, v_off)
            n_reinit += n_r
            counters[3] += n_g
        usable = mvalid[i] and mvalid[i + 1]
        if not usable:  # prediction only
            if k > 0:
                x = phi_k @ x
                P = phi_k @ P @ phi_k.T + qd_k
                if keep:
                    sm_phi[k] = phi_k
                    sm_xpred[k] = x
                    sm_ppred[k] = P
            for ii in range(m_meas):
                innov[k, ii] = np.nan
            nis[k] = np.nan
            n_skip += 1
        else:
            _nb_measurement(k, q, v, llh, x, r_hat, r_fej, lever, c_nm, v_m, a_m, w_m, seg_dq, seg_dt, offs,
                            has_q, att_only_fej, z, h_buf)
            nis[k] = kf_step_ws(x, P, phi_k if k > 0 else no_phi, qd_k, z, h_buf, r_diag, e_buf, ws)
            innov[k] = e_buf
            if keep and k > 0:
                sm_phi[k] = phi_k
                sm_xpred[k] = phi_k @ sm_xf[k - 1]
                sm_ppred[k] = phi_k @ sm_pf[k - 1] @ phi_k.T + qd_k
        if not _nb_finite(x, P):
            counters[2] = k
            return
        xs[k] = x
        for ii in range(n):
            pd[k, ii] = P[ii, ii]
        if usable:  # feedback into the nominal
            tau = _nb_feedback(x, q, v, r_hat, lever, tau, offs, fb_mask, lo_tau, hi_tau, keep,
                               sm_fb[k] if keep else e_buf)
        _nb_record(k, x, P, q, r_hat, tau, lever, c_nm, offs, keep, r_hist, pm_hist, tau_hist, lev_hist, q_hist,
                   cnm_hist, sm_xf, sm_pf)
    counters[0] = n_skip
    counters[1] = n_reinit
    counters[2] = -1


@njit
def _rotvec_nb(q):
    vn = np.sqrt(q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    if vn < 1e-12:
        return 2.0 * q[1:] / max(q[0], 1e-300)
    return q[1:] * (2.0 * np.arctan2(vn, q[0]) / vn)


def run_filter_compiled(inp: AlignInputs, s: FilterSettings) -> FilterRun:
    """The KF kinds' forward pass as one compiled loop (same results as :func:`run_filter`)."""
    lay = s.layout
    n, m_meas = lay.n, lay.n_meas
    ne = len(inp.seg_dt_s) + 1
    ms = inp.master
    k_m = len(ms.t_s)
    z4, z3 = np.zeros((k_m, 4)), np.zeros((k_m, 3))
    xs, pd = np.zeros((ne, n)), np.zeros((ne, n))
    r_hist, pm_hist = np.zeros((ne, 3, 3)), np.zeros((ne, 3, 3))
    tau_hist, lev_hist = np.zeros(ne), np.zeros((ne, 3))
    innov, nis = np.full((ne, m_meas), np.nan), np.full(ne, np.nan)
    q_hist, cnm_hist = np.zeros((ne, 4)), np.zeros((ne, 3, 3))
    keep = bool(s.smoother)
    kk = ne if keep else 0
    sm = (np.zeros((kk, n, n)), np.zeros((kk, n)), np.zeros((kk, n, n)), np.zeros((kk, n)),
          np.zeros((kk, n, n)), np.zeros((kk, n)))
    fb_mask = _feedback_mask(lay)
    r_diag = _r_diag(lay, s)
    counters = np.zeros(4, np.int64)
    restart = np.zeros(ne, np.bool_)
    if len(inp.restart):
        restart[:] = np.asarray(inp.restart, np.bool_)
    valid = ms.valid if ms.valid is not None else np.ones(k_m, np.bool_)
    _kf_loop(np.ascontiguousarray(inp.t_epoch_s, float), np.ascontiguousarray(inp.seg_dq, float),
             np.ascontiguousarray(inp.seg_dv_b, float), np.ascontiguousarray(inp.seg_dt_s, float),
             np.ascontiguousarray(ms.t_s, float),
             np.ascontiguousarray(ms.quat if ms.quat is not None else z4, float),
             np.ascontiguousarray(ms.vel if ms.vel is not None else z3, float),
             np.ascontiguousarray(ms.acc if ms.acc is not None else z3, float),
             np.ascontiguousarray(ms.w_stamps_s if ms.w_nm_m is not None else ms.t_s, float),
             np.ascontiguousarray(ms.w_nm_m if ms.w_nm_m is not None else z3, float),
             np.ascontiguousarray(valid, np.bool_), np.ascontiguousarray(ms.reset_t_s, float), restart,
             ms.quat is not None, ms.vel is not None, ms.w_nm_m is not None,
             np.asarray(inp.q0, float).copy(), np.asarray(inp.v0, float).copy(),
             np.asarray(inp.llh0, float).copy(), np.ascontiguousarray(inp.r0, float),
             np.asarray(inp.lever0_m, float).copy(), float(inp.tau0_s), lay.offsets, n, m_meas,
             np.ascontiguousarray(_initial_cov(s)), np.asarray(s.qc, float), r_diag, float(s.flex_beta),
             1.0 / float(s.master_att_tau_s), float(s.delay_bounds_s[0]), float(s.delay_bounds_s[1]), fb_mask,
             bool(s.att_only_fej), bool(_dynamics_fej(s) and ms.quat is not None), keep,
             xs, pd, r_hist, pm_hist, tau_hist, lev_hist, innov, nis, q_hist, cnm_hist, *sm, counters)
    if counters[2] >= 0:
        raise AnalysisError(f"alignment filter diverged at t = {inp.t_epoch_s[counters[2]]:.2f} s "
                            "(non-finite state)")
    if counters[0] == ne:
        raise AnalysisError("the master's attitude/velocity is unusable (frozen or jumping) over the whole overlap")
    run = FilterRun(inp.t_epoch_s.copy(), xs, pd, r_hist, pm_hist, tau_hist, lev_hist, innov, nis,
                    dcm_from_quat(q_hist), cnm_hist if ms.quat is not None else None, np.full(ne, np.inf),
                    n_skipped=int(counters[0]), n_reinit=int(counters[1]), n_restart=int(counters[3]))
    if keep:
        run.p_mount_fwd = run.p_mount.copy()
        _rts(run, lay, *sm)
    return run
