"""The velocity matching's inputs and records: both units' NED velocities (``VelocityPair``), the
velocity grid and its quantization floor, the frame rotation between the units' velocities."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from logtools.conventions import dcm_from_quat, skew, wahba
from logtools.inslog import InsLog
from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.resample import Interpolant, median_rate_hz, smooth_interpolant, stamp_noise_s
from logtools.rows import BLOCK_ROWS, by_rows


@dataclass(frozen=True)
class VelocityPair:
    """Both units' NED velocities, low-passed at the same cutoff, continuous; and the master's lever-arm
    rows C_nb [w x] (None without the master's attitude: no lever arm then)."""

    master: Interpolant
    slave: Interpolant
    lever: Callable[[np.ndarray], np.ndarray] | None
    cutoff_hz: float
    dt_s: float
    #: per unit: (quantum of the logged velocity in m/s or 0, total variation per axis (3,) m/s)
    steps: tuple[tuple[float, np.ndarray], ...] = ()
    #: per unit: the step of the velocity's stamps when coarse (s; 0 when fine)
    stamp_resolutions_s: tuple[float, ...] = ()
    #: per unit: (white noise on the velocity's stamps, s; the velocity's sample rate, Hz)
    stamp_jitter: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class VelocityFit:
    latency_s: float
    drift: float  # s/s
    sigma_latency_s: float  # window-checked (inflated by the windows' scatter when chi2 > 1)
    sigma_drift: float
    corr_ld: float
    lever_arm_m: tuple[float, float, float] | None
    residual_rms_m_s: float
    window_chi2_red: float
    n_windows: int
    n_steps: int = 0  # resets of the slave's velocity found and solved
    frame_rotation_deg: float = 0.0  # the rotation between the velocities' frames undone before the fit


def _finite(t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows with a finite stamp and values (the arrays themselves where all are: no copies of 4 h)."""
    ok = np.isfinite(t) & np.all(np.isfinite(v), axis=1)
    return (t, v) if ok.all() else (t[ok], v[ok])


def _same_stream(tm: np.ndarray, vm: np.ndarray, ts: np.ndarray, vs: np.ndarray) -> bool:
    """True when the slave's velocity is the master's own samples (one nav solution logged for both)."""
    if len(tm) != len(ts):
        return False
    return bool(np.allclose(tm, ts, rtol=0.0, atol=1e-6) and np.allclose(vm, vs, rtol=0.0, atol=1e-9))


def velocity_pair(master: InsLog, slave: InsLog, cutoff_hz: float, master_rate: Interpolant,
                  cfg: LatencyConfig = DEFAULT) -> VelocityPair | None:
    """The pair for a velocity fit (``slave`` already on the master's relative clock), or None when either
    unit has no (or too little finite) velocity, or both carry the same nav stream."""
    if not (master.has_vel and slave.has_vel):
        return None
    tm, vm = _finite(*master.vel_ned_m_s())
    ts, vs = _finite(*slave.vel_ned_m_s())
    if min(len(tm), len(ts)) < cfg.velocity.min_samples or _same_stream(tm, vm, ts, vs):
        return None
    f_min = min(median_rate_hz(tm), median_rate_hz(ts))
    cut = float(min(cutoff_hz, cfg.velocity.max_cutoff_hz, cfg.velocity.cutoff_fraction * f_min))
    try:
        itps = [smooth_interpolant(t, v, cut, name=f"{role} velocity",
                                   band_limited_fraction=cfg.prepare.band_limited_fraction)
                for t, v, role in ((tm, vm, "master"), (ts, vs, "slave"))]
    except ValueError:
        return None
    steps = tuple((velocity_quantum_m_s(v, cfg), np.sum(np.abs(np.diff(v, axis=0)), axis=0)) for v in (vm, vs))
    jitter = tuple((stamp_noise_s(t), median_rate_hz(t)) for t in (tm, ts))
    del tm, vm, ts, vs  # (each unit's finite copy: what follows needs only the interpolants)
    lever = None
    if master.has_quat:
        tq, q = _finite(*master.quat_wxyz())
        if not np.all(tq[1:] >= tq[:-1]):  # (sorted already: the stable sort leaves it as it is)
            o = np.argsort(tq, kind="stable")
            tq, q = tq[o], q[o]
            del o
        w, okw = master_rate(tq) if len(tq) else (np.zeros((0, 3)), np.zeros(0, bool))
        if okw.sum() >= cfg.velocity.min_samples:
            # C_nb [w x] at the attitude's instants, low-passed like the velocities: the lever arm's part of
            # the slave's velocity is filtered with it, and noise in the rows above the velocities' cutoff
            # (a rate from a noisy attitude: a master logging its navigation solution alone) would only
            # dilute the lever arm's regression (measured: an aircraft's along-track lever arm 14 % short,
            # its latency 2 ms off at a sigma of 0.5 ms, with the rows at the rate fit's 4 Hz)
            if not okw.all():  # (each unit's copy rebound at once: never the series and their copies together)
                q = q[okw]
                w = w[okw]
                tq = tq[okw]
            del okw
            rows = _lever_rows(q, w)
            t_rows = tq
            del q, w, tq
            try:  # (column by column: 4 h of 9 columns is 207 MB a copy)
                lev_itp = smooth_interpolant(t_rows, rows, cut, name="master lever-arm rows",
                                             band_limited_fraction=cfg.prepare.band_limited_fraction)
            except ValueError:
                lev_itp = None
            del rows, t_rows
            if lev_itp is not None:
                def lever(t: np.ndarray) -> np.ndarray:
                    """C_nb(t) [w(t) x] (n, 3, 3), low-passed: d(v_s)/d(l)."""
                    v, ok = lev_itp(t)
                    return np.where(ok[:, None, None], v.reshape(-1, 3, 3), 0.0)
    dt = 1.0 / min(max(5.0 * cut, cfg.velocity.min_grid_hz), f_min)
    stamps = (master.stamp_resolution_s("vel"), slave.stamp_resolution_s("vel"))
    return VelocityPair(itps[0], itps[1], lever, cut, dt, steps, stamps, jitter)


def _lever_rows(q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``(dcm_from_quat(q) @ skew(w)).reshape(-1, 9)``, a block of rows at a time."""
    return by_rows(lambda qb, wb: (dcm_from_quat(qb) @ skew(wb)).reshape(-1, 9), q, w)


def velocity_quantum_m_s(v: np.ndarray, cfg: LatencyConfig = DEFAULT) -> float:
    """The step the velocity was logged with (MAVLink GLOBAL_POSITION_INT: 0.01 m/s), 0 when it is not on
    a grid: the largest of cfg.velocity.quanta_m_s that every sample is a whole multiple of."""
    for q in cfg.velocity.quanta_m_s:
        for a in range(0, len(v), BLOCK_ROWS):  # (in blocks: the first row off the grid ends the test)
            x = v[a:a + BLOCK_ROWS] / q
            if not np.all(np.abs(x - np.round(x)) < 1e-3):
                break
        else:
            return q
    return 0.0


def quantization_sigma_s(vp: VelocityPair, accel: np.ndarray) -> float:
    """Latency sigma from the velocities' quantization: a logged velocity on a grid of step q errs by a
    sawtooth that is not white where the velocity changes slowly (one error per level crossing, with
    variance q^2 / 12), which the residual spectrum does not show. Per axis the level crossings are
    total variation / q, each weighed by the acceleration's mean square ``accel`` (3,)."""
    info = 0.0
    for q, tv in vp.steps:
        if q > 0:
            info += float(np.sum(accel * (tv / q))) / (q * q / 12.0)
    return float(1.0 / np.sqrt(info)) if info > 0 else 0.0


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def frame_rotation(vs: np.ndarray, vm: np.ndarray, use: np.ndarray, cfg: LatencyConfig = DEFAULT
                   ) -> np.ndarray | None:
    """The rotation R with v_s ~ R v_m + c, from the velocities' changes about their means: Kabsch when the
    velocity varies in two directions or more; else (an aircraft's S-turns, a straight road) the rotation
    about the one is undetermined and only a heading rotation is found (2-D, from the horizontal changes,
    which one direction determines); None when neither is determined."""
    if use.sum() < cfg.velocity.min_samples:
        return None
    a, b = vs[use] - vs[use].mean(axis=0), vm[use] - vm[use].mean(axis=0)
    H = a.T @ b
    sv = np.linalg.svd(H, compute_uv=False)
    if not sv[0] > 0:
        return None
    if sv[1] > cfg.velocity.frame_min_rank * sv[0]:
        return wahba(H)[0]
    h = H[:2, :2]
    if np.linalg.norm(h) < 0.1 * sv[0]:  # the changes are vertical: the heading is not seen
        return None
    psi = float(np.arctan2(h[1, 0] - h[0, 1], h[0, 0] + h[1, 1]))
    c, s_ = np.cos(psi), np.sin(psi)
    return np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])


def near(t: np.ndarray, at: np.ndarray, half_s: float) -> np.ndarray:
    """True where t is within half_s of any of the (sorted) instants ``at``."""
    j = np.searchsorted(at, t)
    before = np.abs(t - at[np.clip(j - 1, 0, len(at) - 1)])
    after = np.abs(t - at[np.clip(j, 0, len(at) - 1)])
    return np.minimum(before, after) <= half_s

