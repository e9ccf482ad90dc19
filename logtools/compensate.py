"""Latency compensation: the slave put on the master's clock.

``compensate(slave, lat, master, method=...)`` returns a new slave :class:`InsLog` whose times are
master-relative (``meta.t0_ns == master.meta.t0_ns``) and from which the estimated latency (drift
included, ``lat.latency_at``) has been removed. DESIGN.md sign: ``latency_s > 0`` means the slave's
stamps are late, so compensation subtracts it.

The slave stamp ``t`` (master-relative) of the physical instant ``tau`` (master's clock) is
``t = tau + L(tau)`` with ``L(tau) = L0 + d (tau - t_mid)`` (``L0 = lat.latency_s``, ``d = drift_ppm
1e-6``, ``t_mid = lat.t_mid_rel_s``), so ``tau = (t - L0 + d t_mid) / (1 + d)`` exactly (it differs from
``t - L(t)`` by ``d L``, 0.1 ms for 100 ppm and 1 s).

Methods (which output is which):

``restamp`` (the default of this function)
    The slave's OWN samples, every stream at its own rate, with corrected stamps ``tau``. Exact, no
    information lost: use it for transfer alignment (the slave IMU keeps its rate).
``interp``
    The slave RESAMPLED onto master instants inside the overlap: IMU (angular rate, specific force)
    linearly onto the master's IMU instants; attitude by slerp (``quat_slerp``), velocity and position
    linearly onto the master's nav instants (the master's IMU instants when the master has no nav).
    Instants whose bracketing slave samples are more than 3 median intervals apart (a gap) are dropped.
``shift``
    S000 (Lu & Cheng 2011, Fig. 2) local data shifting: the slave data moved by an integer number of
    its IMU samples ``k = round(L0 / dt)``, i.e. every sample gets the stamp ``k dt`` earlier (on a
    uniform grid: the stamp of the sample k places before). The drift part ``L(tau) - L0`` is removed
    from the stamps exactly (S000 has no drift). A residual ``L0 - k dt`` (|.| <= dt/2) remains.
``poly2``
    S003 (Wang & Liu) eqs 1-2: the slave value at each master instant extrapolated by the second-order
    polynomial through the last three slave samples at or before it (corrected stamps). Eq 2 as printed
    has a typo in ``a1`` (``X[(n-1)T]`` twice); the correct backward-difference form
    ``a1 = (3 X_n - 4 X_{n-1} + X_{n-2}) / 2T`` is used (it makes eq 1 exact for quadratics); with
    non-uniform stamps the same polynomial is built by divided differences (identical on a uniform grid).
    Attitude: the polynomial is applied to rotation vectors relative to the last sample, then mapped back.
``split``
    S004 (Chen, Zhou, Liu 2014) separate compensation: the integer part ``k = floor(L0 / dt)`` samples is
    applied as in ``shift`` (drift removed from the stamps); the residual ``L0 - k dt`` in [0, dt) is NOT
    applied: it is left for the delay-state filter (``kf-split``) and recorded in ``meta.warnings`` as
    ``residual_s=...`` (read it with :func:`split_residual_s`). The output therefore still lags the master
    by ``residual_s`` (DESIGN.md sign).

Every output carries a ``meta.warnings`` note stating the method, latency, drift and what was applied.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, replace

import numpy as np

from logtools.conventions import (
    quat_conj, quat_from_rotvec, quat_make_continuous, quat_mul, quat_normalize, quat_slerp, rotvec_from_quat,
)
from logtools.errors import AnalysisError, InputError
from logtools.inslog import ACCEL, GYRO, POS, QUAT, VEL, ChannelInfo, Columns, InsLog
from logtools.results import LatencyResult

METHODS = ("restamp", "interp", "shift", "poly2", "split")
GAP_FACTOR = 3.0  # interp: bracketing samples further apart than this many median intervals = a gap
_NAV_CHANNEL = {QUAT: "att", VEL: "vel", POS: "pos"}
_RESIDUAL_RE = re.compile(r"residual_s=([-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)")


@dataclass(frozen=True)
class SplitLatency:
    """S004's split of a latency into an integer number of samples and a residual."""

    k_samples: int
    dt_s: float
    integer_s: float  # k_samples * dt_s, applied by lagging the slave data
    residual_s: float  # latency - integer_s, left to the filter's delay state


def split_latency(latency_s: float, dt_s: float, *, rounding: str = "floor") -> SplitLatency:
    """``floor`` (S004: residual in [0, dt)) or ``round`` (S000 shifting: |residual| <= dt/2)."""
    if not (np.isfinite(latency_s) and np.isfinite(dt_s) and dt_s > 0):
        raise AnalysisError(f"cannot split latency {latency_s!r} s on a sample interval of {dt_s!r} s")
    k = int(np.floor(latency_s / dt_s + 1e-9)) if rounding == "floor" else int(np.round(latency_s / dt_s))
    return SplitLatency(k_samples=k, dt_s=float(dt_s), integer_s=k * dt_s, residual_s=latency_s - k * dt_s)


def split_residual_s(log: InsLog) -> float | None:
    """The residual latency a ``split`` compensation left for the delay-state filter (None if not split)."""
    for w in reversed(log.meta.warnings):
        if w.startswith("compensated (split)"):
            m = _RESIDUAL_RE.search(w)
            if m:
                return float(m.group(1))
    return None


def true_time_s(t_slave_rel_s: np.ndarray, lat: LatencyResult) -> np.ndarray:
    """Master-clock instants tau of slave stamps t (both master-relative): t = tau + lat.latency_at(tau)."""
    d = lat.drift_ppm * 1e-6
    return (np.asarray(t_slave_rel_s, float) - lat.latency_s + d * lat.t_mid_rel_s) / (1.0 + d)


# ---- helpers ------------------------------------------------------------------------------------
def _median_dt(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if len(d) else float("nan")


def _group_rows(st: Columns, cols: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    if not all(c in st.data for c in cols) or len(st) == 0:
        return np.zeros(0), np.zeros((0, len(cols)))
    v = st.values(cols, "C")
    ok = ~np.isnan(v).any(axis=1)
    t = st.t_s[ok]
    v = v[ok]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
    return t[keep], v[keep]


def _group_stamps(st: Columns, cols: tuple[str, ...]) -> np.ndarray:
    """``_group_rows(st, cols)[0]`` (the stamps of the rows with every column set, increasing, each once)
    without its values: the channels' rates and counts need only these."""
    if not all(c in st.data for c in cols) or len(st) == 0:
        return np.zeros(0)
    ok = np.ones(len(st), bool)
    for c in cols:
        ok &= ~np.isnan(np.asarray(st.data[c], float))
    t = st.t_s[ok]
    if len(t) > 1 and not np.all(t[1:] >= t[:-1]):
        t = np.sort(t, kind="stable")
    return t[np.concatenate([[True], np.diff(t) > 0])] if len(t) else t


def _bracket(t_src: np.ndarray, t_dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index j (t_src[j] <= t_dst <= t_src[j+1]), fraction, and a mask of usable (in span, no gap)."""
    j = np.clip(np.searchsorted(t_src, t_dst, side="right") - 1, 0, len(t_src) - 2)
    h = t_src[j + 1] - t_src[j]
    frac = (t_dst - t_src[j]) / h
    gap = GAP_FACTOR * _median_dt(t_src)
    ok = (t_dst >= t_src[0]) & (t_dst <= t_src[-1]) & (h <= gap)
    return j, np.clip(frac, 0.0, 1.0), ok


def _interp_group(t_src: np.ndarray, v: np.ndarray, t_dst: np.ndarray, is_quat: bool
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(values at t_dst, usable mask): slerp for quaternions, linear otherwise."""
    if len(t_src) < 2:
        return np.full((len(t_dst), v.shape[1]), np.nan), np.zeros(len(t_dst), bool)
    j, frac, ok = _bracket(t_src, t_dst)
    if is_quat:
        q = quat_make_continuous(quat_normalize(v))
        out = quat_slerp(q[j], q[j + 1], frac)
    else:
        out = v[j] + (v[j + 1] - v[j]) * frac[:, None]
    return out, ok


def _poly2_group(t_src: np.ndarray, v: np.ndarray, t_dst: np.ndarray, is_quat: bool
                 ) -> tuple[np.ndarray, np.ndarray]:
    """S003 eqs 1-2: quadratic through samples n-2, n-1, n (t_src[n] <= t_dst) evaluated at t_dst."""
    out = np.full((len(t_dst), v.shape[1]), np.nan)
    if len(t_src) < 3:
        return out, np.zeros(len(t_dst), bool)
    n = np.searchsorted(t_src, t_dst, side="right") - 1
    dt_med = _median_dt(t_src)
    ok = n >= 2
    nn = np.clip(n, 2, len(t_src) - 1)
    delta = t_dst - t_src[nn]  # eq 1's Delta T
    h1 = t_src[nn] - t_src[nn - 1]
    h2 = t_src[nn - 1] - t_src[nn - 2]
    ok &= (delta <= GAP_FACTOR * dt_med) & (h1 <= GAP_FACTOR * dt_med) & (h2 <= GAP_FACTOR * dt_med)
    if is_quat:
        q = quat_make_continuous(quat_normalize(v))
        qn_inv = quat_conj(q[nn])
        x0 = np.zeros((len(nn), 3))
        x1 = rotvec_from_quat(quat_mul(qn_inv, q[nn - 1]))
        x2 = rotvec_from_quat(quat_mul(qn_inv, q[nn - 2]))
    else:
        x0, x1, x2 = v[nn], v[nn - 1], v[nn - 2]
    f1 = (x0 - x1) / h1[:, None]  # divided differences; on a uniform grid these give eq 2's a1, a2
    f12 = (x1 - x2) / h2[:, None]
    f2 = (f1 - f12) / (h1 + h2)[:, None]
    val = x0 + delta[:, None] * f1 + (delta * (delta + h1))[:, None] * f2
    if is_quat:
        val = quat_mul(q[nn], quat_from_rotvec(val))
    out[:] = val
    return out, ok


def _resample(slave_true: InsLog, master: InsLog, kind: str) -> tuple[Columns, Columns]:
    """IMU onto master IMU instants, nav onto master nav instants (IMU instants if no master nav)."""
    fn = _interp_group if kind == "interp" else _poly2_group
    t_m_imu = master.t_imu_s()
    t_m_nav = master.t_nav_s() if master.n_nav else t_m_imu
    # IMU
    imu_cols: dict[str, np.ndarray] = {}
    ok_imu = np.zeros(len(t_m_imu), bool)
    for cols in (GYRO, ACCEL):
        t_src, v = _group_rows(slave_true.imu_columns, cols)
        if len(t_src) == 0:
            continue
        val, ok = fn(t_src, v, t_m_imu, False)
        ok_imu |= ok
        val[~ok] = np.nan
        imu_cols.update(zip(cols, val.T))
    imu = Columns.from_dict(t_m_imu, imu_cols).take(ok_imu) if imu_cols else Columns.empty()
    # nav
    nav_cols: dict[str, np.ndarray] = {}
    ok_nav = np.zeros(len(t_m_nav), bool)
    for cols in (QUAT, VEL, POS):
        t_src, v = _group_rows(slave_true.nav_columns, cols)
        if len(t_src) == 0:
            continue
        val, ok = fn(t_src, v, t_m_nav, cols == QUAT)
        ok_nav |= ok
        val[~ok] = np.nan
        nav_cols.update(zip(cols, val.T))
    nav = Columns.from_dict(t_m_nav, nav_cols).take(ok_nav) if nav_cols else Columns.empty()
    return imu, nav


def _rate_hz(t: np.ndarray) -> float:
    dt = _median_dt(t)
    return float(1.0 / dt) if np.isfinite(dt) and dt > 0 else 0.0


def _update_channels(log: InsLog) -> dict[str, ChannelInfo]:
    """Refresh rate and count of the channels the log already lists (names as the parsers use them)."""
    imu, nav = log.imu_columns, log.nav_columns
    groups = {"imu": (imu, ()), "nav": (nav, ()), "gyro": (imu, GYRO), "accel": (imu, ACCEL)}
    groups.update({name: (nav, cols) for cols, name in _NAV_CHANNEL.items()})
    ch = dict(log.meta.channels)
    for name, old in log.meta.channels.items():
        if name not in groups:
            continue
        st, cols = groups[name]
        t = st.t_s if not cols else _group_stamps(st, cols)
        ch[name] = ChannelInfo(_rate_hz(t), int(len(t)), old.source)
    return ch


# ---- the entry point ----------------------------------------------------------------------------
def compensate(slave: InsLog, lat: LatencyResult, master: InsLog, *, method: str = "restamp") -> InsLog:
    """The slave on the master's clock with ``lat`` (latency and drift) removed; see the module doc.

    ``method``: restamp (own samples, corrected stamps; exact), interp (resampled onto master instants),
    shift (S000 integer-sample shifting), poly2 (S003 extrapolation onto master instants), split (S004:
    integer part applied, residual recorded for the delay-state filter).
    """
    if method not in METHODS:
        raise InputError(f"compensation method must be one of {', '.join(METHODS)}, not {method!r}")
    if not (np.isfinite(lat.latency_s) and np.isfinite(lat.drift_ppm) and np.isfinite(lat.t_mid_rel_s)):
        raise AnalysisError(f"cannot compensate: latency {lat.latency_s!r} s / drift {lat.drift_ppm!r} ppm "
                            "is not a finite estimate")
    if slave.n_imu == 0 and slave.n_nav == 0:
        raise AnalysisError(f"{slave.meta.source_path}: slave log holds no samples to compensate")
    s = slave.rebased(master.meta.t0_ns)
    head = (f"compensated ({method}): latency {lat.latency_s * 1e3:+.4f} ms at master t={lat.t_mid_rel_s:.3f} s, "
            f"drift {lat.drift_ppm:+.3f} ppm (method {lat.method})")

    if method in ("restamp", "interp", "poly2"):
        true_imu = s.imu_columns.with_t(true_time_s(s.t_imu_s(), lat))
        true_nav = s.nav_columns.with_t(true_time_s(s.t_nav_s(), lat))
        if method == "restamp":
            out = s.with_streams(imu=true_imu, nav=true_nav)
            note = f"{head}; slave's own samples, stamps tau = (t - L0 + d t_mid)/(1 + d)"
        else:
            imu, nav = _resample(s.with_streams(imu=true_imu, nav=true_nav), master, method)
            if len(imu) == 0 and len(nav) == 0:
                raise AnalysisError(f"{slave.meta.source_path}: no master instant inside the compensated "
                                    f"slave's span ({method} needs an overlap)")
            out = s.with_streams(imu=imu, nav=nav)
            what = ("linear (IMU, velocity, position) / slerp (attitude) interpolation" if method == "interp"
                    else "S003 eqs 1-2 second-order polynomial extrapolation")
            note = f"{head}; {what} onto master instants ({len(imu)} IMU, {len(nav)} nav rows)"
    else:  # shift / split: integer number of slave IMU samples, drift removed from the stamps
        t_ref = s.t_imu_s() if s.n_imu > 1 else s.t_nav_s()
        dt = _median_dt(t_ref)
        sp = split_latency(lat.latency_s, dt, rounding="round" if method == "shift" else "floor")

        def restamp(t: np.ndarray) -> np.ndarray:
            tau = true_time_s(t, lat)
            return tau + lat.latency_s - sp.integer_s  # = t - (drift part) - k dt

        out = s.with_streams(imu=s.imu_columns.with_t(restamp(s.t_imu_s())),
                             nav=s.nav_columns.with_t(restamp(s.t_nav_s())))
        if method == "shift":
            note = (f"{head}; S000 data shifting by k={sp.k_samples} samples x dt={dt:.6g} s "
                    f"({sp.integer_s * 1e3:+.4f} ms), drift removed from the stamps; "
                    f"unapplied remainder {sp.residual_s * 1e3:+.4f} ms")
        else:
            note = (f"{head}; S004 split: integer lag k={sp.k_samples} samples x dt={dt:.6g} s "
                    f"({sp.integer_s * 1e3:+.4f} ms) applied, drift removed from the stamps; "
                    f"residual_s={sp.residual_s:+.9f} left for the delay-state filter")
    out = out.with_streams(meta=replace(out.meta, t0_ns=int(master.meta.t0_ns)))
    out = out.with_streams(meta=replace(out.meta.with_warning(note), channels=_update_channels(out)))
    return out
