"""Shared by every format module: raw streams (int64 ns stamps + SI arrays in FRD/NED) -> InsLog.

Format modules convert units, axes and clocks, then call :func:`build_inslog`, which sorts, drops
duplicate stamps, reports gaps/resets/non-monotonic stamps as warnings and picks ``t0_ns``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from logtools.errors import InputError
from logtools.inslog import ACCEL, GYRO, POS, QUAT, T, VEL, ChannelInfo, InsLog, LogMeta
from parsers.base import rate_of, stamp_grid_s

#: a stamp step larger than this many median periods is reported as a gap
GAP_FACTOR = 5.0
#: a run of at most STRAY_MAX_SAMPLES samples cut off from the rest by steps longer than STRAY_GAP_S and
#: STRAY_GAP_PERIODS median periods holds stray stamps (a corrupt time field: one DataFlash TimeUS with
#: a flipped byte put a sample 12 days after a 40 s log, and a uniform grid over that span took 16 GB)
STRAY_GAP_S = 60.0
STRAY_GAP_PERIODS = 1000.0
STRAY_MAX_SAMPLES = 3


@dataclass(frozen=True)
class Stream:
    """One stream's samples: ``t_ns`` (int64, on the log's clock) and ``values`` (N, k) in SI."""

    t_ns: np.ndarray
    values: np.ndarray
    source: str = ""
    stamp_resolution_s: float = 0.0  # the format's stamp step when coarse (tlog time_boot_ms, DataFlash TimeMS: 1e-3)


def clean_stream(name: str, s: Stream, warnings: list[str]) -> Stream:
    """Sort by time, drop non-finite and duplicate stamps; report what was done."""
    t = np.asarray(s.t_ns, dtype=np.int64)
    v = np.asarray(s.values, dtype=float)
    v = v.reshape(len(t), -1) if len(t) else v.reshape(0, v.shape[-1] if v.ndim > 1 else 0)
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        warnings.append(f"{name} ({s.source}): {int((~finite).sum())} samples with NaN/inf dropped")
        t, v = t[finite], v[finite]
    bad = implausible(name, v)
    if bad.any():
        warnings.append(f"{name} ({s.source}): {int(bad.sum())} samples with impossible values dropped "
                        f"(corrupt data?)")
        t, v = t[~bad], v[~bad]
    if len(t) > 1 and np.any(np.diff(t) < 0):
        n_back = int(np.sum(np.diff(t) < 0))
        warnings.append(f"{name} ({s.source}): {n_back} backward time steps (clock reset or reordering); sorted")
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
    if len(t) > 1:
        dup = np.concatenate([[False], np.diff(t) == 0])
        if dup.any():
            warnings.append(f"{name} ({s.source}): {int(dup.sum())} duplicate stamps dropped")
            t, v = t[~dup], v[~dup]
    keep = drop_stray(t, f"{name} ({s.source}): ", warnings)
    t, v = t[keep], v[keep]
    if len(t) > 2:
        d = np.diff(t)
        med = np.median(d)
        big = d > GAP_FACTOR * med
        if big.any():
            warnings.append(
                f"{name} ({s.source}): {int(big.sum())} gap(s) in stamps, longest {d.max() * 1e-9:.3f} s")
    # the stamps' resolution: the format's (tlog time_boot_ms), or the grid the stamps show they are on
    return Stream(t, v, s.source, max(s.stamp_resolution_s, stamp_grid_s(t)))


#: physically impossible magnitudes per stream (SI): a sample beyond them is a corrupt value (a flipped
#: bit in a float without checksum), dropped with a warning. Generous: 10000 deg/s, about 500 g, 10 km/s.
LIMITS = {"gyro": 175.0, "accel": 5000.0, "vel": 1.0e4}


def implausible(name: str, values: np.ndarray) -> np.ndarray:
    """True for the rows of ``values`` (N, k) of stream ``name`` that no vehicle can produce: a component
    beyond LIMITS, a quaternion far from unit norm, or for positions a latitude beyond 90 deg, a longitude
    beyond 360 deg, an altitude beyond 1000 km."""
    v = np.abs(np.asarray(values, dtype=float))
    if name in LIMITS:
        return np.any(v > LIMITS[name], axis=1)
    if name == "quat" and v.ndim == 2 and v.shape[1] == 4:  # a rotation is a unit quaternion (not zeros)
        n = np.linalg.norm(v, axis=1)
        return ~((n > 0.5) & (n < 2.0))
    if name == "pos" and v.ndim == 2 and v.shape[1] >= 3:
        return (v[:, 0] > 90.0) | (v[:, 1] > 360.0) | (v[:, 2] > 1.0e6)
    return np.zeros(len(v), dtype=bool)


def drop_stray(t_ns: np.ndarray, label: str, warnings: list[str]) -> np.ndarray:
    """The samples to keep of sorted, unique stamps ``t_ns``: all but the stray ones (``not_stray``), which
    are said in ``warnings`` (prefixed with ``label``)."""
    keep = not_stray(t_ns)
    if not keep.all():
        bad = t_ns[~keep]
        warnings.append(f"{label}{int((~keep).sum())} sample(s) with stray stamps dropped ({bad.min() * 1e-9:.3f} .. "
                        f"{bad.max() * 1e-9:.3f} s, isolated from the rest: a corrupt time field?)")
    return keep


def not_stray(t_ns: np.ndarray) -> np.ndarray:
    """False for samples in runs of at most STRAY_MAX_SAMPLES cut off from longer runs by steps longer
    than STRAY_GAP_S and STRAY_GAP_PERIODS median periods (``t_ns`` sorted, unique)."""
    keep = np.ones(len(t_ns), dtype=bool)
    if len(t_ns) <= STRAY_MAX_SAMPLES + 1:
        return keep
    d = np.diff(t_ns)
    thr = max(STRAY_GAP_S * 1e9, STRAY_GAP_PERIODS * float(np.median(d)))
    cut = np.flatnonzero(d > thr) + 1
    if not len(cut):
        return keep
    bounds = np.concatenate([[0], cut, [len(t_ns)]])
    sizes = np.diff(bounds)
    if sizes.max() <= STRAY_MAX_SAMPLES:
        return keep  # nothing but small runs: nothing to tell the stray ones by
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a <= STRAY_MAX_SAMPLES:
            keep[a:b] = False
    return keep


def build_inslog(
    *,
    path: str,
    fmt: str,
    selector: str,
    clock: str,
    stamp_source: str,
    gyro: Stream | None = None,
    accel: Stream | None = None,
    quat: Stream | None = None,
    vel: Stream | None = None,
    pos: Stream | None = None,
    warnings: list[str] | tuple[str, ...] = (),
) -> InsLog:
    """Assemble an InsLog. gyro/accel must share stamps if both are given on one stream (IMU
    message); otherwise accel is interpolated onto the gyro stamps (reported). quat is normalised
    and sign-continuous. Raises InputError when nothing usable is left."""
    warns = list(warnings)
    streams = {k: clean_stream(k, s, warns) for k, s in
               dict(gyro=gyro, accel=accel, quat=quat, vel=vel, pos=pos).items() if s is not None}
    streams = {k: s for k, s in streams.items() if len(s.t_ns)}
    if not streams:
        raise InputError("no usable samples in the selected streams", path)
    t0_ns = int(min(int(s.t_ns[0]) for s in streams.values()))
    channels: dict[str, ChannelInfo] = {}

    def rel(t_ns):
        return (np.asarray(t_ns, np.int64) - t0_ns) * 1e-9

    imu = pd.DataFrame(index=pd.Index(np.zeros(0), name=T))
    g, a = streams.get("gyro"), streams.get("accel")
    base = g if g is not None else a
    if base is not None:
        cols: dict[str, np.ndarray] = {}
        t_imu = rel(base.t_ns)
        if g is not None:
            cols.update(zip(GYRO, g.values.T))
            channels["gyro"] = ChannelInfo(rate_of(t_imu), len(t_imu), g.source, g.stamp_resolution_s)
        if a is not None:
            if g is not None and not np.array_equal(a.t_ns, g.t_ns):
                ta = rel(a.t_ns)
                if len(ta) > 1:
                    cols.update(zip(ACCEL, [np.interp(t_imu, ta, c, left=np.nan, right=np.nan)
                                            for c in a.values.T]))
                    warns.append("accel interpolated onto gyro stamps (different stamps)")
            else:
                cols.update(zip(ACCEL, a.values.T))
            channels["accel"] = ChannelInfo(rate_of(rel(a.t_ns)), len(a.t_ns), a.source, a.stamp_resolution_s)
        imu = pd.DataFrame(cols, index=pd.Index(t_imu, name=T))
        imu = imu[imu.notna().all(axis=1)] if ACCEL[0] in imu.columns and g is not None else imu

    nav_parts = []
    for key, names in (("quat", QUAT), ("vel", VEL), ("pos", POS)):
        s = streams.get(key)
        if s is None:
            continue
        vals = s.values
        if key == "quat":
            from logtools.conventions import quat_make_continuous, quat_normalize
            vals = quat_make_continuous(quat_normalize(vals))
        df = pd.DataFrame(dict(zip(names, vals.T)), index=pd.Index(s.t_ns, name="t_ns"))
        nav_parts.append(df)
        channels[{"quat": "att", "vel": "vel", "pos": "pos"}[key]] = ChannelInfo(
            rate_of(rel(s.t_ns)), len(s.t_ns), s.source, s.stamp_resolution_s)
    if nav_parts:
        nav = nav_parts[0]
        for part in nav_parts[1:]:
            nav = nav.join(part, how="outer")
        nav = nav.sort_index()
        nav.index = pd.Index(rel(nav.index.to_numpy()), name=T)
    else:
        nav = pd.DataFrame(index=pd.Index(np.zeros(0), name=T))
    meta = LogMeta(source_path=path, format=fmt, selector=selector, clock=clock, t0_ns=t0_ns,
                   stamp_source=stamp_source, channels=channels, warnings=tuple(warns))
    return InsLog(imu=imu, nav=nav, meta=meta)
