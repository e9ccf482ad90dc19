"""Stage 1b, isolated spikes: an IMU sample far off its neighbours in one unit while the other unit, at the same
instant (the coarse lag), shows nothing alike. A corrupt value (a flipped bit in a float, a torn record) is
one; a real impact is not (both units feel it: the real logs' impacts stand 26-940 local sigmas high in both).
Such a sample is replaced by its neighbours' mean in the logs the latency reads (and the alignment after it:
``mend``), and said as a warning.

Why: the latency fit is a least-squares fit; one gyro sample 0.54 rad/s off (20 flipped bytes of a ULog)
moved its estimate 5.3 sigma and the drift 6.4 sigma, its noise model none the wiser. One unit alone cannot
tell such a sample from a real impact; the other unit can.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from logtools.inslog import ACCEL, GYRO, Columns, InsLog
from logtools.latency.config import SpikeConfig


@dataclass(frozen=True)
class Spikes:
    """One unit's isolated spikes in one triad: the rows (into the log's IMU stream) and their local z."""

    rows: np.ndarray
    z: np.ndarray


@dataclass(frozen=True)
class Triad:
    """One unit's triad as its log holds it (three columns, not copied), its stamps, and the robust per-axis
    scale of its second differences."""

    t: np.ndarray
    cols: tuple[np.ndarray, ...]  # (a triad's three; any k columns of one stream: a quaternion's four)
    step_s: float  # median stamp step
    scale: np.ndarray  # (k,)


def _subsample(n: int) -> int:
    """A stride leaving about 100 000 of ``n`` samples: robust scales from them are the same to a percent."""
    return max(1, n // 100_000)


def triad(t: np.ndarray, cols) -> Triad:
    """The triad's scales: per axis 1.4826 x the median |second difference| (the motion's curvature is
    small at an IMU's rate, the noise is what is left), at least the series' quantum (integer counts: the
    median is 0 when still), from a regular subsample."""
    cols = tuple(np.asarray(c, dtype=float) for c in cols)
    n = len(t)
    k = _subsample(n)
    step = float(np.median(np.diff(t[::k]))) / k if n > 2 * k else float("nan")
    scale = np.full(len(cols), np.inf)
    if n >= 5 and step > 0:
        r = np.arange(1, n - 1, k)
        for j, x in enumerate(cols):
            d = np.abs(x[r] - 0.5 * (x[r - 1] + x[r + 1]))
            d = d[np.isfinite(d)]
            dx = np.abs(x[r + 1] - x[r])
            dx = dx[np.isfinite(dx) & (dx > 0)]
            if len(d) >= 10:
                scale[j] = max(1.4826 * float(np.median(d)), float(np.min(dx)) if len(dx) else 0.0, 1e-12)
    return Triad(t, cols, step, scale)


def _abs_d2(tr: Triad, rows: np.ndarray) -> np.ndarray:
    """(len(rows), k) |second differences| / scale at the given rows (1 .. N-2); 0 where the three stamps
    around a row are not regular or a value is not finite."""
    t = tr.t
    dt0, dt1 = t[rows] - t[rows - 1], t[rows + 1] - t[rows]
    lo, hi = 0.5 * tr.step_s, 1.5 * tr.step_s
    reg = (dt0 > lo) & (dt0 < hi) & (dt1 > lo) & (dt1 < hi)
    out = np.empty((len(rows), len(tr.cols)))
    for j, x in enumerate(tr.cols):
        out[:, j] = np.abs(x[rows] - 0.5 * (x[rows - 1] + x[rows + 1])) / tr.scale[j]
    out[~reg | ~np.all(np.isfinite(out), axis=1)] = 0.0
    return out


def _local_z(tr: Triad, rows: np.ndarray, half: int) -> np.ndarray:
    """Each row's z against the robust level of its neighbours within ``half`` samples (itself and its two
    neighbours, which a spike of its own raises, left out), that level at least the series' scale."""
    offs = np.r_[-half:-1, 2:half + 1]
    a = _abs_d2(tr, rows)
    win = _abs_d2(tr, (rows[:, None] + offs[None, :]).ravel()).reshape(len(rows), len(offs), len(tr.cols))
    loc = np.maximum(1.4826 * np.median(win, axis=1), 1.0)
    return np.max(a / loc, axis=1)


def isolated(tr: Triad, cfg: SpikeConfig) -> Spikes:
    """The samples of one unit's triad that stand ``cfg.min_sigmas`` or more above their neighbourhood and the
    whole series, and at least ``cfg.isolation`` times above both neighbours. One pass over the series per
    axis (no copy of it held); the rest on the few candidates."""
    n, h = len(tr.t), cfg.half_width
    if n < 2 * h + 3 or not np.all(np.isfinite(tr.scale)):
        return Spikes(np.zeros(0, dtype=np.intp), np.zeros(0))
    hit = np.zeros(n - 2, dtype=bool)
    for j, x in enumerate(tr.cols):
        d = x[:-2] + x[2:]
        d *= -0.5
        d += x[1:-1]
        np.abs(d, out=d)
        hit |= d >= cfg.min_sigmas * tr.scale[j]
    c = np.flatnonzero(hit) + 1
    c = c[(c >= h + 1) & (c < n - h - 1)]
    if not len(c):
        return Spikes(c, np.zeros(0))
    z3 = np.max(_abs_d2(tr, np.concatenate([c - 1, c, c + 1])).reshape(3, len(c), len(tr.cols)), axis=2)
    c = c[(z3[1] >= cfg.min_sigmas) & (z3[1] >= cfg.isolation * z3[0]) & (z3[1] >= cfg.isolation * z3[2])]
    zl = _local_z(tr, c, h) if len(c) else np.zeros(0)
    keep = zl >= cfg.min_sigmas
    return Spikes(c[keep], zl[keep])


def isolated_samples(t: np.ndarray, values: np.ndarray, min_sigmas: float, min_size: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(rows, how far off) of one stream's samples ``values`` (N, k) at ``t`` that :func:`isolated` finds (at
    ``min_sigmas``, the default isolation and neighbourhood) and that stand at least ``min_size`` (the values'
    unit, the largest column) off their two neighbours' mean: corrupt values of a quantity that cannot jump
    and come back within one sample (a navigation output's velocity)."""
    v = np.asarray(values, dtype=float)
    if len(v) < 5:
        return np.zeros(0, dtype=np.intp), np.zeros(0)
    rows = isolated(triad(t, tuple(v.T)), SpikeConfig(min_sigmas=min_sigmas)).rows
    off = np.max(np.abs(v[rows] - 0.5 * (v[rows - 1] + v[rows + 1])), axis=1) if len(rows) else np.zeros(0)
    keep = off >= min_size
    return rows[keep], off[keep]


def other_z(tr: Triad, t_q: np.ndarray, tol_s: float, cfg: SpikeConfig) -> np.ndarray:
    """The other unit's largest local z within ``tol_s`` of each instant ``t_q`` (its own clock); inf where it
    has no sample there (a gap: nothing says the spike is real, nor that it is not)."""
    t, h = tr.t, cfg.half_width
    j0 = np.searchsorted(t, t_q - tol_s, side="left")
    j1 = np.searchsorted(t, t_q + tol_s, side="right")
    width = int(max(1, np.max(j1 - j0))) if len(t_q) else 1
    rows = j0[:, None] + np.arange(width)[None, :]
    inside = (rows < j1[:, None]) & (rows >= h + 1) & (rows < len(t) - h - 1)
    rows = np.clip(rows, h + 1, max(h + 1, len(t) - h - 2))
    z = _local_z(tr, rows.ravel(), h).reshape(rows.shape)
    z = np.where(inside, z, 0.0)
    return np.where(inside.any(axis=1), z.max(axis=1), np.inf)


def _columns(log: InsLog, names: tuple[str, ...]) -> tuple:
    return tuple(log.imu_columns.data[c] for c in names)


@dataclass(frozen=True)
class Candidate:
    """One unit's isolated spikes in one triad, before the other unit is asked (``alone``)."""

    role: str  # "master" | "slave"
    names: tuple[str, ...]  # the triad's columns (GYRO, ACCEL)
    own: Triad
    other: Triad  # the other unit's same triad
    spikes: Spikes


def candidates(master: InsLog, slave: InsLog, cfg: SpikeConfig) -> list[Candidate]:
    """Each unit's isolated spikes (gyro; accelerometers where both units have them), judged on the unit
    alone: no lag needed, so none is searched where there are none (the common case). ``slave`` on the master's
    relative clock."""
    names = [GYRO] + ([ACCEL] if master.has_accel and slave.has_accel else [])
    tm, ts = master.t_imu_s(), slave.t_imu_s()
    if len(tm) < 5 or len(ts) < 5:
        return []
    out = []
    for triad_names in names:
        trm, trs = triad(tm, _columns(master, triad_names)), triad(ts, _columns(slave, triad_names))
        for role, own, other in (("master", trm, trs), ("slave", trs, trm)):
            sp = isolated(own, cfg)
            if len(sp.rows):
                out.append(Candidate(role, triad_names, own, other, sp))
    return out


def alone(cands: list[Candidate], lag_s: float, cfg: SpikeConfig) -> dict[tuple[str, tuple[str, ...]], Spikes]:
    """The candidates the other unit does not show at the same instant, where the slave's instant t is the
    master's t - ``lag_s``: {(role, triad): Spikes}."""
    found = {}
    for c in cands:
        tol = cfg.tolerance_steps * max(c.own.step_s, c.other.step_s)
        shift = lag_s if c.role == "master" else -lag_s
        zo = other_z(c.other, c.own.t[c.spikes.rows] + shift, tol, cfg)
        keep = zo <= cfg.other_max_sigmas
        if keep.any():
            found[(c.role, c.names)] = Spikes(c.spikes.rows[keep], c.spikes.z[keep])
    return found


def find(master: InsLog, slave: InsLog, lag_s: float, cfg: SpikeConfig
         ) -> dict[tuple[str, tuple[str, ...]], Spikes]:
    """``alone(candidates(...))``: each unit's isolated spikes the other unit does not show at the same
    instant. ``slave`` on the master's relative clock, where the slave's instant t is the master's t - ``lag_s``."""
    return alone(candidates(master, slave, cfg), lag_s, cfg)


def replaced_rows(log: InsLog, spikes: dict[tuple[str, ...], Spikes], stream: str = "imu") -> InsLog:
    """The log with each spike's sample replaced by its two neighbours' mean, per set of columns of ``stream``
    ("imu" or "nav") ({columns: Spikes})."""
    cols = log.imu_columns if stream == "imu" else log.nav_columns
    data = dict(cols.data)
    for names, sp in spikes.items():
        for c in names:
            col = np.array(data[c], dtype=float)
            col[sp.rows] = 0.5 * (col[sp.rows - 1] + col[sp.rows + 1])
            data[c] = col
    return log.with_streams(**{stream: Columns(cols.t_s, data)})


def instants(t_s: np.ndarray, rows: np.ndarray, t0_s: float) -> str:
    """The first three rows' instants on the log's own clock ("at" in a warning)."""
    return ", ".join(f"{t_s[i] + t0_s:.3f} s" for i in rows[:3]) + (" ..." if len(rows) > 3 else "")


SENSORS = {"gyro": GYRO, "accel": ACCEL}


def records(found: dict[tuple[str, tuple[str, ...]], Spikes], logs: dict[str, InsLog]) -> list[dict]:
    """The replaced samples as report.json holds them (``latency.quality.replaced_samples``): one dict per sample,
    {unit, sensor, row (of the log's IMU stream), t_s (on the log's own clock), local_sigmas}, in time order."""
    out = []
    for (role, triad_names), sp in found.items():
        t, t0 = logs[role].t_imu_s(), logs[role].t0_s
        sensor = next(k for k, v in SENSORS.items() if v == triad_names)
        out += [{"unit": role, "sensor": sensor, "row": int(i), "t_s": float(t[i] + t0), "local_sigmas": float(z)}
                for i, z in zip(sp.rows, sp.z)]
    return sorted(out, key=lambda r: (r["unit"], r["t_s"], r["sensor"]))


def mend(master: InsLog, slave: InsLog, replaced: list[dict]) -> tuple[InsLog, InsLog]:
    """(master, slave) with the samples of ``records`` replaced by their neighbours' mean (the logs the latency
    read): for the stages after it that read the IMUs (the alignment, the IMU-to-IMU fit)."""
    out = []
    for role, log in (("master", master), ("slave", slave)):
        mine: dict[tuple[str, ...], list[int]] = {}
        for r in replaced:
            if r["unit"] == role:
                mine.setdefault(SENSORS[r["sensor"]], []).append(int(r["row"]))
        out.append(replaced_rows(log, {k: Spikes(np.asarray(v, dtype=np.intp), np.zeros(len(v)))
                                       for k, v in mine.items()}) if mine else log)
    return out[0], out[1]


def describe(role: str, found: dict[tuple[str, tuple[str, ...]], Spikes], t_rel: np.ndarray, t0_s: float) -> str:
    """One warning for a unit's replaced samples."""
    parts = []
    for (r, triad), sp in found.items():
        if r != role:
            continue
        what = "gyro" if triad == GYRO else "accelerometer"
        parts.append(f"{len(sp.rows)} {what} sample(s) (at {instants(t_rel, sp.rows, t0_s)}; up to "
                     f"{float(np.max(sp.z)):.0f} local sigmas)")
    return (f"{role}: " + " and ".join(parts) + " far off their neighbours, with nothing alike in the other unit "
            "at the same instant, replaced by their neighbours' mean in the analysis (corrupt values?)")
