"""Put irregular sensor streams on a uniform time grid, and interpolate them continuously.

Used by the latency estimator (``logtools.latency``): two units logged at different rates (50-1000 Hz),
through different clocks, with jittered stamps, gaps and duplicated stamps are brought onto one uniform
grid, and a continuous interpolant (cubic B-spline) evaluates a unit at arbitrary, sub-sample shifted
instants.

Rules (the failure modes of existing tools, avoided here):

* never extrapolate past the data ends: outside ``[t_first, t_last]`` the value is masked;
* never interpolate across a gap where more than ``max_gap_samples`` samples are missing: masked;
* duplicated stamps are merged (values averaged), stamps going backwards are sorted, non-finite rows
  dropped; every such repair is reported in ``warnings``.

Times are float64 seconds relative to a stated origin (see DESIGN.md, "Time").
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from logtools.dsp import butter_lowpass_sos, cubic_spline_at, sosfiltfilt_even, weighted_rows
from logtools.rows import BLOCK_ROWS

__all__ = ["CleanSamples", "UniformSeries", "Interpolant", "clean_samples", "median_rate_hz",
           "to_uniform", "to_uniform_band_limited", "band_limited_factor", "sample_clock", "lowpass", "interpolant",
           "smooth_interpolant", "stamp_noise_s"]


@dataclass(frozen=True)
class CleanSamples:
    """Sorted, finite, unique-stamp samples of one stream, and what was repaired."""

    t_s: np.ndarray  # (n,) strictly increasing
    values: np.ndarray  # (n, k)
    warnings: tuple[str, ...] = ()
    n_duplicates: int = 0
    n_nonfinite: int = 0
    n_unsorted: int = 0


@dataclass(frozen=True)
class UniformSeries:
    """Samples on the grid ``t_k = (i0 + k) * dt_s`` (k = 0..n-1); ``valid`` masks gaps/ends."""

    i0: int  # grid index of the first sample (grid phase shared by every series with the same dt)
    dt_s: float
    values: np.ndarray  # (n, k); invalid rows hold finite fill values (do not use them)
    valid: np.ndarray  # (n,) bool
    warnings: tuple[str, ...] = ()
    gaps_s: tuple[tuple[float, float], ...] = field(default=())  # masked spans (start, end)

    @property
    def t_s(self) -> np.ndarray:
        return (self.i0 + np.arange(len(self.values))) * self.dt_s

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.dt_s

    @property
    def nan_fraction(self) -> float:
        return float(1.0 - self.valid.mean()) if len(self.valid) else 1.0


def _as2d(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x[:, None] if x.ndim == 1 else x


def clean_samples(t_s: np.ndarray, values: np.ndarray, *, name: str = "stream") -> CleanSamples:
    """Sort by time, drop rows with a non-finite stamp or value, merge duplicated stamps (mean)."""
    t = np.asarray(t_s, dtype=float)
    x = _as2d(values)
    warns: list[str] = []
    ok = np.isfinite(t) & np.all(np.isfinite(x), axis=1)
    n_bad = int((~ok).sum())
    if n_bad:
        warns.append(f"{name}: {n_bad} of {len(t)} samples with NaN/inf dropped")
        t, x = t[ok], x[ok]
    n_unsorted = int(np.sum(np.diff(t) < 0)) if len(t) > 1 else 0
    if n_unsorted:
        order = np.argsort(t, kind="stable")
        t, x = t[order], x[order]
        warns.append(f"{name}: {n_unsorted} stamps going backwards (re-sorted)")
    n_dup = 0
    if len(t) > 1:
        new = np.concatenate([[True], np.diff(t) > 0])
        n_dup = int((~new).sum())
        if n_dup:
            grp = np.cumsum(new) - 1
            cnt = np.bincount(grp).astype(float)
            x = np.stack([np.bincount(grp, weights=x[:, j]) / cnt for j in range(x.shape[1])], axis=1)
            t = t[new]
            warns.append(f"{name}: {n_dup} duplicated stamps merged (values averaged)")
    return CleanSamples(t, x, tuple(warns), n_dup, n_bad, n_unsorted)


def median_rate_hz(t_s: np.ndarray) -> float:
    """Nominal rate from the median stamp interval (robust to jitter, gaps and duplicates)."""
    t = np.asarray(t_s, dtype=float)
    d = np.diff(t[np.isfinite(t)])
    d = d[d > 0]
    return float(1.0 / np.median(d)) if len(d) else float("nan")


def stamp_noise_s(t: np.ndarray) -> float:
    """White noise on a stream's stamps (s), from the robust spread (MAD) of its sample intervals, gaps
    and duplicates left out: a stamp error of sigma spreads the intervals by sqrt(2) sigma. The one
    measure of stamp noise (the resampling's warning, the latency's sigma floor)."""
    t = t[np.isfinite(t)]
    st = np.diff(t)
    if np.any(st < 0):  # (stamps in order, as nearly every log has them, need no sort: the same numbers)
        st = np.diff(np.sort(t))
    if len(st) < 10:
        return 0.0
    med = float(np.median(st))
    st = st[(st > 0) & (st < 2.0 * med)]
    if len(st) < 10:
        return 0.0
    return float(1.4826 * np.median(np.abs(st - np.median(st))) / np.sqrt(2.0))


#: to_uniform: an interval between two samples with more than this many samples missing is a gap (masked)
MAX_GAP_SAMPLES = 3.0
#: lowpass: the Butterworth filter's order (applied forward and backward)
LOWPASS_ORDER = 4

#: a uniform grid longer than both of these (per sample, in all) is refused: a stream whose stamps span
#: far more time than its samples cover (a corrupt stamp days away) would otherwise take gigabytes
MAX_GRID_PER_SAMPLE = 20.0
MAX_GRID_POINTS = 20_000_000


@dataclass(frozen=True)
class _Grid:
    """What :func:`to_uniform` resamples: the cleaned samples, the grid, and what is valid on it."""

    t_s: np.ndarray  # the cleaned samples' stamps and values
    values: np.ndarray
    t_grid_s: np.ndarray  # the grid's instants (clipped to the samples' span)
    i0: int
    dt_s: float
    valid: np.ndarray
    warnings: tuple[str, ...]
    gaps_s: tuple[tuple[float, float], ...]


def _gap_limit_s(dt_s: float, max_gap_samples: float) -> float:
    """The longest step between two samples of a stream at interval ``dt_s`` that is not a gap: a gap is an
    interval with more than ``max_gap_samples`` samples missing in it."""
    return (max_gap_samples + 1.5) * dt_s


def band_limited_factor(cutoff_hz: float, dt_s: float, fraction: float) -> int:
    """How many times denser than its interval ``dt_s`` a stream's grid must be for ``cutoff_hz`` to lie within
    ``fraction`` of its rate (1: its own interval is enough; :func:`to_uniform_band_limited`)."""
    return int(np.ceil(cutoff_hz * dt_s / fraction - 1e-9))


def _grid(t_s: np.ndarray, values: np.ndarray, dt_s: float | None, max_gap_samples: float, name: str) -> _Grid:
    cs = clean_samples(t_s, values, name=name)
    t, x = cs.t_s, cs.values
    warns = list(cs.warnings)
    if len(t) < 4:
        raise ValueError(f"{name}: only {len(t)} usable samples")
    dt_nat = float(np.median(np.diff(t)))
    dt = float(dt_s) if dt_s is not None else dt_nat
    i0 = int(np.ceil(t[0] / dt - 1e-9))
    i1 = int(np.floor(t[-1] / dt + 1e-9))
    if i1 - i0 + 1 > max(MAX_GRID_PER_SAMPLE * len(t), MAX_GRID_POINTS):
        raise ValueError(f"{name}: {len(t)} samples at {1 / dt_nat:.4g} Hz spread over {t[-1] - t[0]:.0f} s "
                         f"(mostly gaps: corrupt stamps, or logs joined across a long pause?); not resampled")
    tg = np.arange(i0, i1 + 1) * dt
    tg = np.clip(tg, t[0], t[-1])
    valid = np.ones(len(tg), dtype=bool)
    gaps: list[tuple[float, float]] = []
    steps = np.diff(t)
    jitter = stamp_noise_s(t) * np.sqrt(2.0) / dt_nat  # the intervals' spread, as a fraction of one
    big = np.flatnonzero(steps > _gap_limit_s(dt_nat, max_gap_samples))
    if len(big):
        # grid points strictly inside (t[j], t[j+1]) of a long interval are masked
        eps = 1e-6 * dt  # a grid point on a bounding sample (up to rounding) is that sample
        lo = np.searchsorted(tg, t[big] + eps, side="right")
        hi = np.searchsorted(tg, t[big + 1] - eps, side="left")
        cover = np.zeros(len(tg) + 1, dtype=int)
        np.add.at(cover, lo, 1)
        np.add.at(cover, hi, -1)
        valid &= np.cumsum(cover)[:-1] == 0
        gaps = [(float(t[j]), float(t[j + 1])) for j in big]
        tot = float(np.sum(steps[big]))
        warns.append(f"{name}: {len(big)} gaps of more than {max_gap_samples:g} missing samples "
                     f"({tot:.3f} s in all, longest {float(steps[big].max()):.3f} s) masked, not interpolated")
    if jitter > 0.05:
        warns.append(f"{name}: stamp jitter {100 * jitter:.0f} % of the {1 / dt_nat:.1f} Hz interval "
                     f"(spline through the actual stamps)")
    if dt_s is not None and abs(dt - dt_nat) > 0.01 * dt_nat:
        warns.append(f"{name}: resampled from {1 / dt_nat:.1f} Hz to {1 / dt:.1f} Hz")
    return _Grid(t, x, tg, i0, dt, valid, tuple(warns), tuple(gaps))


def to_uniform(
    t_s: np.ndarray,
    values: np.ndarray,
    *,
    dt_s: float | None = None,
    max_gap_samples: float = MAX_GAP_SAMPLES,
    name: str = "stream",
) -> UniformSeries:
    """Resample a stream on the uniform grid ``k * dt_s`` (default: its own median interval).

    A cubic spline through the (cleaned) samples gives the grid values; grid points farther than the
    data ends, or inside an interval between two samples where more than ``max_gap_samples`` samples
    (at the stream's median interval) are missing, are masked (``valid`` False), never interpolated.
    """
    g = _grid(t_s, values, dt_s, max_gap_samples, name)
    vg = np.empty((len(g.t_grid_s), g.values.shape[1]))
    for j in range(vg.shape[1]):
        vg[:, j] = _spline_column(g, j)
    return UniformSeries(g.i0, g.dt_s, vg, g.valid, g.warnings, g.gaps_s)


def _spline_column(g: _Grid, j: int) -> np.ndarray:
    # spline on the samples (not-a-knot cubic); gaps masked by the grid's valid. One column at a time: the
    # same numbers (each column is its own solve), a fraction of the temporaries of a many-column solve.
    # scipy's CubicSpline, computed by logtools.dsp.cubic_spline_at: bit for bit its numbers, without
    # building the spline object (0.07 against 0.29 s a column of 720 000 samples)
    return cubic_spline_at(g.t_s, g.values[:, j], g.t_grid_s)


def _filled(v: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """The column ``v`` with its invalid rows (``ok`` False) replaced, in place, by linear interpolation of
    the valid ones (for filtering)."""
    if ok.all() or not ok.any():
        return v
    idx = np.arange(len(v))
    v[~ok] = np.interp(idx[~ok], idx[ok], v[ok])
    return v


def _fill_invalid_column(series: UniformSeries, j: int) -> np.ndarray:
    """Column ``j`` of the values with invalid rows replaced by linear interpolation of the valid ones
    (for filtering; the columns are filled independently)."""
    return _filled(series.values[:, j].copy(), series.valid)


def _dilate(mask_bad: np.ndarray, n: int) -> np.ndarray:
    if n <= 0 or not mask_bad.any():
        return mask_bad
    k = np.ones(2 * n + 1)
    return np.convolve(mask_bad.astype(float), k, mode="same") > 0


def lowpass(series: UniformSeries, cutoff_hz: float, *, order: int = LOWPASS_ORDER) -> UniformSeries:
    """Zero-phase (forward-backward) Butterworth low-pass: no delay is introduced.

    Invalid rows are bridged linearly for the filter, then masked again, widened by the filter's
    settling length so that no masked value leaks into a valid one.
    """
    sos = _lowpass_sos(len(series.values), series.dt_s, cutoff_hz, order)
    if sos is None:
        return series
    v = np.empty(series.values.shape)  # column by column: the filter runs along each on its own
    for j in range(v.shape[1]):
        v[:, j] = sosfiltfilt_even(sos, _fill_invalid_column(series, j))
    valid = _lowpassed_valid(series.valid, series.dt_s, cutoff_hz)
    return UniformSeries(series.i0, series.dt_s, v, valid, series.warnings, series.gaps_s)


def _lowpass_sos(n: int, dt_s: float, cutoff_hz: float, order: int) -> np.ndarray | None:
    """The low-pass's sections, or None where it leaves a series as it is (cutoff at or above Nyquist,
    too few samples)."""
    nyq = 0.5 / dt_s
    if not (0 < cutoff_hz < 0.98 * nyq) or n < 8 * order:
        return None
    return butter_lowpass_sos(order, cutoff_hz / nyq)


def _lowpassed_valid(valid: np.ndarray, dt_s: float, cutoff_hz: float) -> np.ndarray:
    settle = int(np.ceil(1.0 / (cutoff_hz * dt_s)))
    out = ~_dilate(~valid, settle)
    out[:settle] = False  # the filter's start-up and run-out at the data ends
    out[-settle:] = False
    return out


@dataclass(frozen=True)
class Interpolant:
    """Continuous cubic B-spline through a uniform series (interpolating, mirror boundary);
    masked (NaN) off the data ends and near invalid samples: never extrapolated. It keeps the series'
    grid, validity and notes, not its values (the coefficients hold them: 4 h of 9 columns at 200 Hz
    is 207 MB a copy)."""

    i0: int  # the series' grid (UniformSeries.i0, dt_s) and its valid samples
    dt_s: float
    valid: np.ndarray
    warnings: tuple[str, ...]
    gaps_s: tuple[tuple[float, float], ...]
    _coef: np.ndarray  # (n + 3, k) B-spline coefficients, padded (1 before, 2 after)
    _bad: np.ndarray  # invalid samples dilated by 1: the 4 samples around a point must be valid

    @property
    def n(self) -> int:
        """Samples of the series."""
        return len(self.valid)

    @property
    def t_first_s(self) -> float:
        return float(self.i0 * self.dt_s)

    @property
    def t_last_s(self) -> float:
        return float((self.i0 + self.n - 1) * self.dt_s)

    def _pos(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = np.asarray(t, dtype=float) / self.dt_s - self.i0
        inside = (u >= -1e-9) & (u <= self.n - 1 + 1e-9)
        return np.clip(u, 0.0, self.n - 1), inside

    def ok(self, t_s: np.ndarray) -> np.ndarray:
        """True where an evaluation is supported by valid samples on both sides (no extrapolation)."""
        u, inside = self._pos(t_s)
        if self.valid.all():
            return inside
        n = self.n
        j = np.clip(np.floor(np.where(inside, u, 0)).astype(np.int64), 0, n - 1)
        return inside & ~self._bad[j] & ~self._bad[np.minimum(j + 1, n - 1)]

    def _eval(self, u: np.ndarray, nu: int) -> np.ndarray:
        n = self.n
        j = np.clip(np.floor(u).astype(np.int64), 0, n - 1)
        f = (u - j)[:, None]
        c = self._coef
        if nu == 0:
            w0 = (1 - f) ** 3 / 6.0
            w1 = (3 * f ** 3 - 6 * f ** 2 + 4) / 6.0
            w2 = (-3 * f ** 3 + 3 * f ** 2 + 3 * f + 1) / 6.0
            w3 = f ** 3 / 6.0
            scale = 1.0
        elif nu == 1:
            w0 = -0.5 * (1 - f) ** 2
            w1 = 1.5 * f ** 2 - 2 * f
            w2 = -1.5 * f ** 2 + f + 0.5
            w3 = 0.5 * f ** 2
            scale = 1.0 / self.dt_s
        else:
            raise ValueError("nu must be 0 or 1")
        # padded index: sample j sits at j + 1
        return weighted_rows(c, j, (w0, w1, w2, w3), scale)

    def transformed(self, M: np.ndarray) -> "Interpolant":
        """The interpolant of the values mapped by the matrix M (k, k): ``v -> M v`` (a spline is linear
        in its coefficients, so this is exact)."""
        M = np.asarray(M, dtype=float)
        return replace(self, _coef=self._coef @ M.T)

    def __call__(self, t_s: np.ndarray, nu: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(values (m, k), ok (m,)); values (or derivatives, nu=1, per second) are NaN where not ok."""
        t = np.asarray(t_s, dtype=float)
        ok = self.ok(t)
        out = np.full((len(t), self._coef.shape[1]), np.nan)
        if ok.all():  # (every point on its own: evaluated BLOCK_ROWS at a time, the same numbers)
            for i in range(0, len(t), BLOCK_ROWS):
                u, _ = self._pos(t[i:i + BLOCK_ROWS])
                out[i:i + BLOCK_ROWS] = self._eval(u, nu)
        elif ok.any():
            idx = np.flatnonzero(ok)
            for i in range(0, len(idx), BLOCK_ROWS):
                at = idx[i:i + BLOCK_ROWS]
                u, _ = self._pos(t[at])
                out[at] = self._eval(u, nu)
        return out, ok


def interpolant(series: UniformSeries) -> Interpolant:
    """Interpolating cubic B-spline of a uniform series (O(n) prefilter); gaps bridged then masked."""
    return _interpolant(series.i0, series.dt_s, series.valid, series.warnings, series.gaps_s, series.values.shape[1],
                        lambda j: _fill_invalid_column(series, j))


def smooth_interpolant(t_s: np.ndarray, values: np.ndarray, cutoff_hz: float, *, name: str = "stream",
                       band_limited_fraction: float | None = None) -> Interpolant:
    """``interpolant(lowpass(to_uniform(t_s, values, name=name), cutoff_hz))``, one column at a time: the
    same numbers without the two whole series between (4 h of 9 columns at 200 Hz: 207 MB each).

    With ``band_limited_fraction``, a stream whose cutoff exceeds that fraction of its rate is put on a grid
    ``up`` times denser by :func:`to_uniform_band_limited` instead (``up`` brings the cutoff within it)."""
    g = _grid(t_s, values, None, MAX_GAP_SAMPLES, name)
    if band_limited_fraction:
        up = band_limited_factor(cutoff_hz, g.dt_s, band_limited_fraction)
        if up > 1:
            return interpolant(lowpass(_band_limited(g, up, MAX_GAP_SAMPLES), cutoff_hz))
    sos = _lowpass_sos(len(g.t_grid_s), g.dt_s, cutoff_hz, LOWPASS_ORDER)
    valid = g.valid if sos is None else _lowpassed_valid(g.valid, g.dt_s, cutoff_hz)

    def column(j: int) -> np.ndarray:  # to_uniform's column, lowpass's, then filled as interpolant fills it
        v = _spline_column(g, j)
        if sos is not None:
            v = sosfiltfilt_even(sos, _filled(v, g.valid))
        return _filled(v, valid)

    return _interpolant(g.i0, g.dt_s, valid, g.warnings, g.gaps_s, g.values.shape[1], column)


def _interpolant(i0: int, dt_s: float, valid: np.ndarray, warnings: tuple[str, ...],
                 gaps_s: tuple[tuple[float, float], ...], k: int, column: Callable[[int], np.ndarray]
                 ) -> Interpolant:
    """The Interpolant of a series on grid (i0, dt_s) with ``valid`` samples, from its k columns
    ``column(j)`` (invalid rows filled), made one at a time."""
    n = len(valid)
    if n < 4:
        raise ValueError("an interpolant needs at least 4 samples")
    cp = np.empty((n + 3, k))  # the coefficients padded (1 before, 2 after), filled column by column
    for j in range(k):
        _coefficients(cp, j, column(j))
    return Interpolant(i0, dt_s, valid, warnings, gaps_s, cp, _dilate(~valid, 1))


def _coefficients(cp: np.ndarray, j: int, v: np.ndarray) -> None:
    """Column ``j`` of the padded coefficients ``cp`` from the column ``v`` (invalid rows filled)."""
    n = len(v)
    c = ndimage.spline_filter1d(v, order=3, axis=0, mode="mirror")
    cp[1:n + 1, j] = c
    cp[0, j], cp[n + 1, j], cp[n + 2, j] = c[1], c[-2], c[-3]


def sample_clock(t_s: np.ndarray, max_gap_samples: float = MAX_GAP_SAMPLES) -> tuple[float, float]:
    """(interval, phase) of the uniform clock that took a stream's samples: the stamps ``t`` are
    ``phase + k * interval`` up to their jitter. The interval is the stamps' span over the intervals they
    hold, each step counted as the whole number of median steps it spans (a jittered pair of 0.3 and 1.7
    steps as 0 and 2; gaps left out), the phase the circular mean of ``t mod interval``. Sorted, finite,
    unique stamps."""
    t = np.asarray(t_s, dtype=float)
    steps = np.diff(t)
    med = float(np.median(steps))
    k = np.rint(steps / med)
    use = steps <= _gap_limit_s(med, max_gap_samples)
    dt = float(steps[use].sum() / k[use].sum()) if k[use].sum() > 0 else med
    ang = 2.0 * np.pi * ((t - t[0]) / dt)
    phase = float(t[0] + dt * np.angle(np.mean(np.exp(1j * ang))) / (2.0 * np.pi))
    return dt, phase


def to_uniform_band_limited(t_s: np.ndarray, values: np.ndarray, up: int, *,
                            max_gap_samples: float = MAX_GAP_SAMPLES, name: str = "stream") -> UniformSeries:
    """A slow stream on the uniform grid ``k * dt / up`` (dt: its sample clock's interval,
    :func:`sample_clock`), band-limited: each gap-free run is put on its own sample instants (the spline
    moves each value by its stamp's jitter only), upsampled ``up`` times by a linear-phase polyphase filter
    (``scipy.signal.resample_poly``), and that dense series read on the grid by a cubic spline.

    :func:`to_uniform` reads a stream's samples by a cubic spline at the grid's fixed offset from them: a
    delay error that depends on that offset and grows towards the Nyquist frequency (up to 0.33 ms for a
    15 Hz motion sampled at 50 Hz). Here the spline only reads a series sampled ``up`` times faster than its
    content (0.3 % of that at 4x). Masking as :func:`to_uniform` (gaps, ends)."""
    return _band_limited(_grid(t_s, values, None, max_gap_samples, name), up, max_gap_samples)


def _band_limited(g: _Grid, up: int, max_gap_samples: float) -> UniformSeries:
    """:func:`to_uniform_band_limited` of a stream's cleaned samples and gaps (``_grid``, at its own interval)."""
    from scipy.signal import resample_poly

    up = max(int(up), 1)
    t, x = g.t_s, g.values
    dt, phase = sample_clock(t, max_gap_samples)
    dtf = dt / up
    i0 = int(np.ceil(t[0] / dtf - 1e-9))
    i1 = int(np.floor(t[-1] / dtf + 1e-9))
    n = i1 - i0 + 1
    vg = np.zeros((n, x.shape[1]))
    valid = np.zeros(n, dtype=bool)
    cuts = np.flatnonzero(np.diff(t) > _gap_limit_s(g.dt_s, max_gap_samples)) + 1
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)]):
        tr, xr = t[a:b], x[a:b]
        # the run's grid points, and its own sample instants (phase + k dt) inside it
        ga = int(np.ceil(tr[0] / dtf - 1e-9)) - i0
        gb = int(np.floor(tr[-1] / dtf + 1e-9)) - i0
        if gb < ga:
            continue
        tg = np.clip((i0 + np.arange(ga, gb + 1)) * dtf, tr[0], tr[-1])
        ka = int(np.ceil((tr[0] - phase) / dt - 1e-9))
        kb = int(np.floor((tr[-1] - phase) / dt + 1e-9))
        valid[ga:gb + 1] = True
        if b - a < 4:
            vg[ga:gb + 1] = np.array([np.interp(tg, tr, xr[:, j]) for j in range(x.shape[1])]).T
            continue
        if kb - ka + 1 < 16:  # too short for the filter: the spline on the samples themselves
            for j in range(x.shape[1]):
                vg[ga:gb + 1, j] = cubic_spline_at(tr, xr[:, j], tg)
            continue
        ts = phase + np.arange(ka, kb + 1) * dt
        dense_t = ts[0] + np.arange((len(ts) - 1) * up + 1) * dtf
        # the clock's instants lie inside the run's stamps (up to one interval in from either end): grid
        # points outside them are masked, never extrapolated
        eps = 1e-6 * dtf
        inside = (tg >= dense_t[0] - eps) & (tg <= dense_t[-1] + eps)
        valid[ga:gb + 1] = inside
        tq = np.clip(tg, dense_t[0], dense_t[-1])
        for j in range(x.shape[1]):
            own = cubic_spline_at(tr, xr[:, j], ts)
            dense = resample_poly(own, up, 1, padtype="line")[:len(dense_t)]
            vg[ga:gb + 1, j] = cubic_spline_at(dense_t, dense, tq)
    return UniformSeries(i0, dtf, vg, valid, g.warnings, g.gaps_s)
