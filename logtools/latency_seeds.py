"""The seed papers' latency estimators, as published, for comparison with tapost's default method.

Both functions work on the master-relative time axis (the slave is ``rebased(master.meta.t0_ns)``) and
return a :class:`~logtools.results.MethodEstimate` whose ``latency_s`` follows DESIGN.md: positive when
the slave's stamps are late (the slave's sample stamped ``t`` shows the motion the master stamped
``t - latency_s``).

``s000_rate_integral`` -- S000 (Lu & Cheng 2011), eqs 1-5
    Integrate each unit's angular rate over the record (eqs 1-2: ``I_i(j) = sum_{k<=j} w_i(k) t_s``),
    move the master's integral curve point by point over the candidate delays, sum the squared
    differences of the three axes (eq 3), take the minimum (eq 4) and ``t_delay = t_s n_t`` (eq 5).
    As published it compares the x, y, z integrals axis by axis, i.e. it ASSUMES THE TWO UNITS' AXES
    ARE ALIGNED. With a rotated mounting it does not raise (nothing in the published method detects it):
    it returns a wrong lag, typically hundreds of ms to seconds off, with its quantisation sigma (which
    then does not cover the error). Even a few degrees of mounting, or a gyro bias difference between the
    units, add a ramp ``(I - R) I_m`` or ``b t`` to the integrals that can outweigh the delay's effect on
    long records. This is deliberate (it is the baseline tapost is compared with); ``rotation`` lets a
    caller supply a known mounting rotation (a variant, not the paper's method).

``s002_attitude_shift`` -- S002 (Sensors 17:2753, 2017), eqs 10-12
    Shift the slave's attitude curves (heading, pitch, roll) point by point against the master's
    (eq 10: sum of squared heading, pitch and roll differences), take the shift with the least sum
    (eq 11) and ``tau = n_min T_SINS`` (eq 12). Needs attitude from both units; with a rotated mounting
    the Euler angles differ by more than a constant and the method fails as published (a wrong lag, not
    an error, as for S000).

Adaptations the papers do not need (each unit logs at its own rate through its own clock here):
- both units are linearly interpolated (angular rate) or slerped (attitude) onto one uniform grid whose
  phase is common to both units, so that every candidate lag is an integer number of grid steps. The grid
  step is the finer of the two units' IMU intervals for S000 (the papers' ``t_s``) and the slave's
  attitude interval for S002 (eq 12's ``T_SINS``);
- the record is by default the whole overlap usable for every candidate lag (the papers use 5 s / 6 s;
  ``record_s`` restores that), which helps the methods, it never hurts them;
- S000: each shifted master curve is integrated from the start of its own window (eq 2 with the origin
  at the record start), so that the constant of integration does not depend on the candidate lag;
- S002: heading and roll differences are wrapped to (-pi, pi] (a 359 deg vs 1 deg heading is 2 deg apart).

Sigma: both are grid searches; the reported ``sigma_s`` is the grid's quantisation, ``t_s / sqrt(12)``
(the standard deviation of a uniform error over one step). It is the resolution of the method, not a
statistical uncertainty: it does not grow when the method fails (e.g. rotated mounting).

The search costs are computed for every candidate lag at once (S000: expansion of eq 3 into sliding sums
and one FFT cross-correlation -- scipy's "auto" picks a slow direct sum for short lag ranges -- the few
best candidates re-evaluated exactly; S002: direct evaluation of eq 10 for every shift, numba-compiled).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from logtools.jit import njit  # compiled in compiled mode, plain Python otherwise

from logtools.conventions import euler_from_quat, quat_make_continuous, quat_slerp
from logtools.dsp import correlate_valid
from logtools.errors import AnalysisError
from logtools.inslog import InsLog
from logtools.results import MethodEstimate

S000_NAME = "s000-rate-integral"
S002_NAME = "s002-attitude-shift"
MIN_RECORD_SAMPLES = 20
MIN_MOTION_RAD_S = 1e-3  # S000 sec. 2: "not suitable for very low amplitudes" (mean/variance check)
MIN_ATT_MOTION_RAD = 1e-3


@dataclass(frozen=True)
class GridSearch:
    """The outcome of a lag grid search (diagnostics for tests and plots)."""

    lags_s: np.ndarray  # candidate latencies (DESIGN.md sign), ascending
    cost: np.ndarray  # the paper's sum of squares at each candidate
    best_s: float
    dt_s: float
    record_s: tuple[float, float]  # slave record, master-relative seconds
    near_equal_minima: int  # other local minima within 10 % of the best (S000 eq 6 caveat)


# ---- shared helpers -----------------------------------------------------------------------------
def _median_dt(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if len(d) else float("nan")


def _check_finite(name: str, what: str, arr: np.ndarray) -> None:
    if not np.all(np.isfinite(arr)):
        raise AnalysisError(f"{name}: {what} contains NaN or infinite values")


def _clean_times(t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort by time and drop duplicate stamps (np.interp needs increasing abscissae); the arrays as they are
    where their stamps already increase (a log's usual case: no copies of 4 h of samples)."""
    if len(t) < 2 or bool(np.all(t[1:] > t[:-1])):
        return t, v
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    return t[keep], v[keep]


def _phase_grid(t_first: float, t_last: float, dt: float, phase: float) -> np.ndarray:
    """Uniform grid ``phase + k dt`` covering [t_first, t_last] (inside it)."""
    k0 = int(np.ceil((t_first - phase) / dt - 1e-9))
    k1 = int(np.floor((t_last - phase) / dt + 1e-9))
    return phase + dt * np.arange(k0, k1 + 1, dtype=float)


def _record_indices(t_s_grid: np.ndarray, m_first: float, m_last: float, max_lag_s: float | None,
                    record_s: float | None, dt: float, record_start_s: float | None = None
                    ) -> tuple[int, int]:
    """Slave record [a, b) on its grid such that the master covers it for every candidate lag."""
    if max_lag_s is not None:
        lo, hi = m_first + max_lag_s, m_last - max_lag_s
        a = int(np.searchsorted(t_s_grid, lo - 1e-9))
        b = int(np.searchsorted(t_s_grid, hi + 1e-9, side="right"))
    else:  # clocks may be unrelated: a record of at most half the master's span, centred in the slave's
        n = min(len(t_s_grid), int((m_last - m_first) / dt / 2))
        a = (len(t_s_grid) - n) // 2
        b = a + n
    if record_start_s is not None:
        a = max(a, int(np.searchsorted(t_s_grid, record_start_s - 1e-9)))
    if record_s is not None:
        b = min(b, a + max(int(round(record_s / dt)), 1))
    return a, b


def _grid_search(lags: np.ndarray, cost: np.ndarray, dt: float, record_s: tuple[float, float]) -> GridSearch:
    """Candidate lags and their cost, sorted by lag, with the best one and its near-equal rivals."""
    order = np.argsort(lags)
    lags, cost = lags[order], cost[order]
    best = int(np.argmin(cost))
    return GridSearch(lags_s=lags, cost=cost, best_s=float(lags[best]), dt_s=dt, record_s=record_s,
                      near_equal_minima=_count_near_minima(cost, best))


def _count_near_minima(cost: np.ndarray, best: int, tol: float = 0.10, guard: int = 3) -> int:
    """Local minima (away from the best by more than ``guard`` steps) within ``tol`` of the best cost."""
    if len(cost) < 3:
        return 0
    c = cost
    interior = np.flatnonzero((c[1:-1] <= c[:-2]) & (c[1:-1] <= c[2:])) + 1
    span = float(np.max(c) - c[best])
    if span <= 0:
        return 0
    near = interior[(np.abs(interior - best) > guard) & (c[interior] - c[best] <= tol * span)]
    return int(len(near))


def _grids(name: str, tm: np.ndarray, ts: np.ndarray, dt: float, max_lag_s: float | None,
           record_s: float | None, record_start_s: float | None) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Master and slave grids of step dt with a common phase, and the slave record [a, b) on its grid;
    AnalysisError when the record is shorter than MIN_RECORD_SAMPLES."""
    phase = float(tm[0])
    gm = _phase_grid(tm[0], tm[-1], dt, phase)
    gs = _phase_grid(ts[0], ts[-1], dt, phase)
    a, b = _record_indices(gs, float(gm[0]), float(gm[-1]), max_lag_s, record_s, dt, record_start_s)
    if b - a < MIN_RECORD_SAMPLES:
        lag = "the whole overlap" if max_lag_s is None else f"a +-{max_lag_s:g} s search"
        raise AnalysisError(f"{name}: overlap too short for {lag} ({max(b - a, 0)} samples usable)")
    return gm, gs, a, b


# ---- S000: least-squares fit of integrated angular rates (eqs 1-5) -------------------------------
def s000_search(master: InsLog, slave: InsLog, *, max_lag_s: float | None = 1.0,
                record_s: float | None = None, record_start_s: float | None = None,
                rotation: np.ndarray | None = None) -> GridSearch:
    """Eq 3's cost for every candidate lag (see :func:`s000_rate_integral`)."""
    name = S000_NAME
    if not (master.has_gyro and slave.has_gyro):
        raise AnalysisError(f"{name} needs angular rate from both units")
    slave = slave.rebased(master.meta.t0_ns)
    tm, wm = _clean_times(master.t_imu_s(), master.gyro_rad_s())
    ts, ws = _clean_times(slave.t_imu_s(), slave.gyro_rad_s())
    _check_finite(name, "master angular rate", wm)
    _check_finite(name, "slave angular rate", ws)
    if len(tm) < MIN_RECORD_SAMPLES or len(ts) < MIN_RECORD_SAMPLES:
        raise AnalysisError(f"{name}: too few angular-rate samples ({len(tm)} master, {len(ts)} slave)")
    if rotation is not None:  # variant: slave rate rotated back into master axes (not the paper's)
        ws = ws @ np.asarray(rotation, float)  # v_master = R^T v_slave, row-wise v @ R
    # t_s: the finer of the two IMU intervals; grid phase common to both units
    dt = min(_median_dt(tm), _median_dt(ts))
    gm, gs, a, b = _grids(name, tm, ts, dt, max_lag_s, record_s, record_start_s)
    n_rec = b - a
    if max_lag_s is not None:  # the master only where a candidate window reads it
        lo = int(np.searchsorted(gm, gs[a] - max_lag_s - dt)) - 1
        hi = int(np.searchsorted(gm, gs[a] + max_lag_s + dt, side="right")) + n_rec + 1
        gm = gm[max(lo, 0):min(hi, len(gm))]
    w_m = np.stack([np.interp(gm, tm, wm[:, i]) for i in range(3)], axis=1)
    w_s = np.stack([np.interp(gs[a:b], ts, ws[:, i]) for i in range(3)], axis=1)
    if np.linalg.norm(w_m.std(axis=0)) < MIN_MOTION_RAD_S or np.linalg.norm(w_s.std(axis=0)) < MIN_MOTION_RAD_S:
        raise AnalysisError(f"{name}: too little angular motion to estimate a delay "
                            f"(rate std < {MIN_MOTION_RAD_S:g} rad/s)")
    # eq 2, origin at the record start: B(i) = sum_{k=a}^{a+i} w_s(k) t_s
    big_b = np.cumsum(w_s, axis=0) * dt
    # master running integral with a leading zero; window starting at p: Mc[p+1+i] - Mc[p]
    mc = np.vstack([np.zeros((1, 3)), np.cumsum(w_m, axis=0) * dt])
    mc -= mc.mean(axis=0)  # only differences enter eq 3: remove the mean for numerical range
    n_m = len(w_m)
    n_pos = n_m - n_rec + 1  # master window starts p = 0 .. n_m - n_rec
    if n_pos < 1:
        raise AnalysisError(f"{name}: master record shorter than the slave record")
    # eq 3 expanded: sum ||Mc[p+1+i] - Mc[p] - B(i)||^2 for all p at once
    body = mc[1:]
    c1 = np.vstack([np.zeros((1, 3)), np.cumsum(body, axis=0)])
    c2 = np.concatenate([[0.0], np.cumsum(np.sum(body * body, axis=1))])
    p = np.arange(n_pos)
    s1 = c1[p + n_rec] - c1[p]  # sum_i Mc[p+1+i]
    s2 = c2[p + n_rec] - c2[p]
    x = correlate_valid(body, big_b)
    x = np.asarray(x)[:n_pos]
    base = mc[p]
    cost = (s2 - 2.0 * np.sum(base * s1, axis=1) + n_rec * np.sum(base * base, axis=1) - 2.0 * x
            + 2.0 * base @ big_b.sum(axis=0) + float(np.sum(big_b * big_b)))
    # candidate latency: slave record start minus master window start (slave late => positive)
    lags = gs[a] - gm[p]
    if max_lag_s is not None:
        keep = np.abs(lags) <= max_lag_s + 1e-9
        p, lags, cost = p[keep], lags[keep], cost[keep]
    if len(p) == 0:
        raise AnalysisError(f"{name}: no candidate lag inside the search range")
    # re-evaluate the few best candidates exactly (guards against cancellation in the expansion)
    cand = np.argsort(cost)[: min(7, len(cost))]
    exact = np.array([np.sum((mc[p[c] + 1:p[c] + 1 + n_rec] - mc[p[c]] - big_b) ** 2) for c in cand])
    cost[cand] = exact
    return _grid_search(lags, cost, dt, (float(gs[a]), float(gs[b - 1])))  # eq 4: the argmin


def s000_rate_integral(master: InsLog, slave: InsLog, *, max_lag_s: float | None = 1.0,
                       record_s: float | None = None, record_start_s: float | None = None,
                       rotation: np.ndarray | None = None) -> MethodEstimate:
    """S000 eqs 1-5: delay by least squares over the integrated angular rates, axes assumed aligned.

    ``max_lag_s``: search range +-max_lag_s (S000 step 2, "e.g. 1 s"); None searches every lag for which
    the master covers the record. ``record_s``: record length (S000 step 1, "e.g. 5 s"; default the whole
    usable overlap); ``record_start_s``: where the record starts (slave stamp, master-relative; default
    the earliest usable instant). ``rotation``: optional known mounting R (v_slave = R v_master) applied to the slave
    rates first -- a variant, not the published method. Returns ``latency_s = t_s n_t`` (eq 5) with the
    DESIGN.md sign, ``sigma_s = t_s / sqrt(12)`` (grid quantisation).
    Raises AnalysisError when a unit has no angular rate, NaNs, too short an overlap or no motion.
    """
    g = s000_search(master, slave, max_lag_s=max_lag_s, record_s=record_s, record_start_s=record_start_s,
                    rotation=rotation)
    note = (f"eqs 1-5, axes assumed aligned{' (rotation variant)' if rotation is not None else ''}; "
            f"t_s={g.dt_s * 1e3:.3f} ms, record [{g.record_s[0]:.3f}, {g.record_s[1]:.3f}] s "
            f"(mid {0.5 * (g.record_s[0] + g.record_s[1]):.3f} s, master-relative); sigma = t_s/sqrt(12)")
    if g.near_equal_minima:
        note += f"; {g.near_equal_minima} other near-equal minima (eq 6: periodic motion?)"
    return MethodEstimate(latency_s=float(g.best_s), sigma_s=float(g.dt_s / np.sqrt(12.0)), note=note)


# ---- S002: attitude-curve shifting (eqs 10-12) -------------------------------------------------------
def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _euler_on_grid(t: np.ndarray, q: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Slerp the quaternions onto ``grid`` (inside [t0, t-1], increasing) and return [roll, pitch, yaw] rows.
    Only the samples around the grid are read (a record of seconds out of hours: their signs made continuous
    among themselves, which gives the same angles, as q and -q are one rotation)."""
    if len(grid) and len(t) > 2:
        i0 = max(int(np.searchsorted(t, grid[0], side="right")) - 2, 0)
        i1 = min(int(np.searchsorted(t, grid[-1], side="right")) + 1, len(t))
        t, q = t[i0:i1], q[i0:i1]
    q = quat_make_continuous(q)
    j = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 2)
    frac = np.clip((grid - t[j]) / (t[j + 1] - t[j]), 0.0, 1.0)
    return euler_from_quat(quat_slerp(q[j], q[j + 1], frac))


@njit(cache=True)
def _attitude_cost(e_m: np.ndarray, e_s: np.ndarray, starts: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Eq 10 for each master window start; roll and heading differences wrapped to (-pi, pi]."""
    n_rec = e_s.shape[0]
    out = np.empty(starts.shape[0])
    two_pi = 2.0 * np.pi
    for k in range(starts.shape[0]):
        p = starts[k]
        acc = 0.0
        for i in range(n_rec):
            for j in range(3):
                d = e_m[p + i, j] - e_s[i, j]
                if j != 1:  # Euler angles lie in [-pi, pi]: one correction wraps the difference
                    if d > np.pi:
                        d -= two_pi
                    elif d <= -np.pi:
                        d += two_pi
                acc += d * d
        out[k] = acc
    return out


def _attitude_cost_np(e_m: np.ndarray, e_s: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """numpy :func:`_attitude_cost` (the reference code), in blocks of window starts (bounded memory)."""
    n_rec = e_s.shape[0]
    win = np.lib.stride_tricks.sliding_window_view(e_m, n_rec, axis=0)  # (positions, 3, n_rec), a view
    out = np.empty(starts.shape[0])
    step = max(1, 4_000_000 // max(3 * n_rec, 1))
    for a in range(0, len(starts), step):
        d = win[starts[a:a + step]] - e_s.T
        for j in (0, 2):  # roll and heading wrap (Euler angles lie in [-pi, pi]: one correction)
            dj = d[:, j]
            dj[dj > np.pi] -= 2.0 * np.pi
            dj[dj <= -np.pi] += 2.0 * np.pi
        out[a:a + step] = np.einsum("kjn,kjn->k", d, d)
    return out


def _attitude_cost_kernel():
    from logtools import jit

    return _attitude_cost if jit.compiled() else _attitude_cost_np


def s002_search(master: InsLog, slave: InsLog, *, max_lag_s: float | None = 1.0,
                record_s: float | None = None, record_start_s: float | None = None) -> GridSearch:
    """Eq 10's cost for every candidate shift (see :func:`s002_attitude_shift`)."""
    name = S002_NAME
    if not (master.has_quat and slave.has_quat):
        raise AnalysisError(f"{name} needs attitude from both units")
    slave = slave.rebased(master.meta.t0_ns)
    tm, qm = _clean_times(*master.quat_wxyz())
    ts, qs = _clean_times(*slave.quat_wxyz())
    _check_finite(name, "master attitude", qm)
    _check_finite(name, "slave attitude", qs)
    if len(tm) < MIN_RECORD_SAMPLES or len(ts) < MIN_RECORD_SAMPLES:
        raise AnalysisError(f"{name}: too few attitude samples ({len(tm)} master, {len(ts)} slave)")
    dt = _median_dt(ts)  # eq 12: T_SINS, the slave's attitude update cycle
    gm, gs, a, b = _grids(name, tm, ts, dt, max_lag_s, record_s, record_start_s)
    n_rec = b - a
    n_pos = len(gm) - n_rec + 1
    if n_pos < 1:
        raise AnalysisError(f"{name}: master record shorter than the slave record")
    if max_lag_s is None:
        p_all = np.arange(n_pos)
    else:  # the shifts near the search range (two steps' margin: gm increases), then its test
        lo_p = max(int(np.searchsorted(gm, gs[a] - max_lag_s, side="left")) - 2, 0)
        hi_p = min(int(np.searchsorted(gm, gs[a] + max_lag_s, side="right")) + 2, n_pos)
        p_all = np.arange(lo_p, max(hi_p, lo_p))
        p_all = p_all[np.abs(gs[a] - gm[p_all]) <= max_lag_s + 1e-9]
    if len(p_all) == 0:
        raise AnalysisError(f"{name}: no candidate lag inside the search range")
    # the master's angles only where a candidate shift reads them
    lo, hi = int(p_all[0]), int(p_all[-1]) + n_rec
    e_m = _euler_on_grid(tm, qm, gm[lo:hi])
    e_s = _euler_on_grid(ts, qs, gs[a:b])
    spread_m = np.linalg.norm(np.std(np.unwrap(e_m, axis=0), axis=0))
    spread_s = np.linalg.norm(np.std(np.unwrap(e_s, axis=0), axis=0))
    if min(spread_m, spread_s) < MIN_ATT_MOTION_RAD:
        raise AnalysisError(f"{name}: attitude too constant to estimate a delay "
                            f"(Euler-angle std < {MIN_ATT_MOTION_RAD:g} rad)")
    # eq 10: sum over the record of (H_M - H_S)^2 + (P_M - P_S)^2 + (R_M - R_S)^2 at every shift
    cost = _attitude_cost_kernel()(np.ascontiguousarray(e_m), np.ascontiguousarray(e_s),
                                   (p_all - lo).astype(np.int64))
    lags = gs[a] - gm[p_all]
    return _grid_search(lags, cost, dt, (float(gs[a]), float(gs[b - 1])))  # eq 11: the argmin


def s002_attitude_shift(master: InsLog, slave: InsLog, *, max_lag_s: float | None = 1.0,
                        record_s: float | None = None, record_start_s: float | None = None) -> MethodEstimate:
    """S002 eqs 10-12: delay by shifting the slave's Euler-angle curves against the master's.

    ``latency_s = n_min T_SINS`` (eq 12, DESIGN.md sign), ``sigma_s = T_SINS / sqrt(12)`` (grid
    quantisation). Axes assumed aligned (as published). ``record_s`` / ``record_start_s``: the record
    (S002 uses the first 6 s; default the whole usable overlap). Raises AnalysisError("...needs attitude from
    both units") when either unit has no attitude, and on NaNs, too short an overlap or constant attitude.
    """
    g = s002_search(master, slave, max_lag_s=max_lag_s, record_s=record_s, record_start_s=record_start_s)
    note = (f"eqs 10-12, axes assumed aligned; T_SINS={g.dt_s * 1e3:.3f} ms, record "
            f"[{g.record_s[0]:.3f}, {g.record_s[1]:.3f}] s (mid {0.5 * (g.record_s[0] + g.record_s[1]):.3f} s, "
            "master-relative); sigma = T_SINS/sqrt(12)")
    if g.near_equal_minima:
        note += f"; {g.near_equal_minima} other near-equal minima (periodic motion?)"
    return MethodEstimate(latency_s=float(g.best_s), sigma_s=float(g.dt_s / np.sqrt(12.0)), note=note)
