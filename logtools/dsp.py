"""Signal processing tapost needs, without scipy.signal: a Butterworth low-pass in second-order sections
with zero-phase filtering, Welch's power spectral density, and FFT cross-correlation.

scipy.signal costs ~0.3-0.5 s to import (it imports scipy.stats and scipy.interpolate with it and rewrites
hundreds of docstrings on the way), more than every filter of a 2-minute analysis together. These are the
algorithms of scipy's ``butter(N, Wn, output="sos")`` (analog prototype, pre-warped bilinear transform,
each conjugate pole pair with two of the zeros at z = -1, the sections closest to the unit circle last, the
gain in the first section; even orders, the odd ones are scipy's own), ``sosfiltfilt(..., padtype="even")``
(even extension of 3 x the filter's taps at each end, the sections' step-response initial states, forward
then backward), ``welch`` (periodic Hann window, half overlap, each segment's mean removed, one-sided
density) and ``correlate(..., mode="valid", method="fft")``; ``tests/test_dsp.py`` compares each with
scipy's (bit-equal for the design and the filter, equal to rounding for the others).

The filter's recursion runs as a numba kernel in compiled mode (logtools.jit); in reference mode (the first
run after installing, before the kernels are compiled) scipy's own C loop of ``sosfilt`` stands in for it (a
Python loop over the samples would cost seconds), loaded from its extension module without importing
scipy.signal (see :func:`_scipy_sosfilt_loop`).
"""
from __future__ import annotations

import functools
import os

import numpy as np
from scipy import fft as sfft

from logtools import jit

__all__ = ["butter_lowpass_sos", "sosfiltfilt_even", "sosfilt_zi", "welch_psd", "correlate_valid",
           "cubic_spline_at", "weighted_rows", "as_trapezoid_integrates", "mad_sigma", "rfft", "irfft"]


# ---- real FFTs that keep no plans of long transforms ----------------------------------------------
#: transform length from which rfft / irfft run numpy.fft rather than scipy.fft. scipy.fft keeps the plans of
#: its last 16 lengths for the life of the process, and a plan holds its twiddle factors: 45-90 MB at the
#: lengths of a 4 h log (spectra zero padded to 2n), 1-2 MB at 2^16. numpy.fft runs the same pocketfft
#: transforms, equal to scipy.fft's bit for bit (tests/test_dsp.py), and keeps none; it makes its plan anew
#: each call, 5-12 % slower on the short transforms the latency repeats hundreds of times, no slower on
#: the long ones. From 2^18 points on (4 MB plans and more): the 4 h pair's peak memory 2.67 -> 2.55 GB (whole
#: processes alternated with scipy.fft for every length), the 1 h pair's latency as fast as before.
PLAN_FREE_MIN_LENGTH = 1 << 18


def _fft_module(x: np.ndarray, n: int | None, axis: int):
    length = n if n is not None else np.shape(x)[axis]
    return np.fft if length >= PLAN_FREE_MIN_LENGTH else sfft


def rfft(x: np.ndarray, n: int | None = None, axis: int = -1) -> np.ndarray:
    """``scipy.fft.rfft(x, n, axis=axis)``, bit for bit, in C order as scipy returns it (numpy's own layout
    puts the transformed axis last in memory, and reductions over the other axes then round differently);
    through numpy.fft from PLAN_FREE_MIN_LENGTH on."""
    return np.ascontiguousarray(_fft_module(x, n, axis).rfft(x, n, axis=axis))


def irfft(x: np.ndarray, n: int | None = None, axis: int = -1) -> np.ndarray:
    """``scipy.fft.irfft(x, n, axis=axis)``, bit for bit, in C order (see :func:`rfft`); ``n`` is the output
    length (default 2 (m - 1) for m input bins, as scipy's)."""
    length = n if n is not None else 2 * (np.shape(x)[axis] - 1)
    return np.ascontiguousarray(_fft_module(x, length, axis).irfft(x, n, axis=axis))


def butter_lowpass_sos(order: int, wn: float) -> np.ndarray:
    """Digital Butterworth low-pass of ``order`` with cutoff ``wn`` (fraction of the Nyquist frequency,
    0 < wn < 1) as (n_sections, 6) second-order sections [b0 b1 b2 1 a1 a2] (scipy's ``butter(order, wn,
    output="sos")``)."""
    order = int(order)
    if order < 1 or not 0.0 < wn < 1.0:
        raise ValueError(f"Butterworth low-pass: order {order} >= 1 and 0 < wn {wn} < 1 needed")
    if order % 2:  # an odd order's lone zero: scipy's pairing rules decide its section (not used by tapost)
        from scipy.signal import butter

        return np.asarray(butter(order, wn, output="sos"), dtype=float)
    fs = 2.0
    warped = 2.0 * fs * np.tan(np.pi * wn / fs)  # pre-warped analog cutoff (rad/s)
    m = np.arange(-order + 1, order, 2)
    p = warped * -np.exp(1j * np.pi * m / (2 * order))  # analog prototype poles, scaled to the cutoff
    k = warped ** order
    fs2 = 2.0 * fs  # bilinear transform: z = (fs2 + s) / (fs2 - s), every zero at z = -1
    pz = (fs2 + p) / (fs2 - p)
    kz = float(np.real(k / np.prod(fs2 - p)))
    pairs = pz[np.imag(pz) > 0]  # one pole of each conjugate pair (an even order has no real pole)
    sos = np.zeros((order // 2, 6))
    # "worst" (closest to the unit circle) last, as scipy's zpk2sos pairs them
    pairs = pairs[np.argsort(np.abs(1.0 - np.abs(pairs)), kind="stable")[::-1]]
    for s, pk in enumerate(pairs):  # each conjugate pair with two of the zeros at z = -1
        sos[s] = [1.0, 2.0, 1.0, 1.0, -float(np.real(pk + np.conj(pk))), float(np.real(pk * np.conj(pk)))]
    sos[0, :3] *= kz
    return sos


def _lfilter_zi2(b: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Initial state of one section for a unit step's steady state (scipy's ``lfilter_zi``)."""
    i_minus_a = np.eye(2) - np.array([[-a[1], -a[2]], [1.0, 0.0]]).T
    return np.linalg.solve(i_minus_a, b[1:] - a[1:] * b[0])


def sosfilt_zi(sos: np.ndarray) -> np.ndarray:
    """(n_sections, 2) initial states for a unit step (scipy's ``sosfilt_zi``)."""
    zi = np.empty((len(sos), 2))
    scale = 1.0
    for s in range(len(sos)):
        b, a = sos[s, :3], sos[s, 3:]
        zi[s] = scale * _lfilter_zi2(b, a)
        scale *= b.sum() / a.sum()
    return zi


@jit.njit
def _sosfilt_kernel(sos, x, zi):  # pragma: no cover - compiled (scipy's _sosfilt loop, same order)
    n_sections = sos.shape[0]
    out = np.empty(x.shape[0])
    for n in range(x.shape[0]):
        x_cur = x[n]
        for s in range(n_sections):
            x_new = sos[s, 0] * x_cur + zi[s, 0]
            zi[s, 0] = sos[s, 1] * x_cur - sos[s, 4] * x_new + zi[s, 1]
            zi[s, 1] = sos[s, 2] * x_cur - sos[s, 5] * x_new
            x_cur = x_new
        out[n] = x_cur
    return out


@functools.cache
def _scipy_sosfilt_loop():
    """scipy's C loop of ``sosfilt`` (``_sosfilt(sos, x, zi)``, in place on C-ordered (1, n) ``x`` and
    (1, sections, 2) ``zi``) from its extension module, loaded without running scipy.signal's ``__init__``:
    importing scipy.signal took 0.8-1.3 s on a 2-core machine (scipy.stats, scipy.interpolate and the
    docstrings it rewrites), a quarter of the first run after installing, which filters in reference mode.
    None where scipy has no such module (then scipy.signal.sosfilt itself)."""
    import importlib.machinery
    import importlib.util
    import sys

    name = "scipy.signal._sosfilt"
    mod = sys.modules.get(name)
    if mod is None:
        try:
            import scipy

            folder = os.path.join(os.path.dirname(scipy.__file__), "signal")
            path = next((os.path.join(folder, "_sosfilt" + sfx) for sfx in importlib.machinery.EXTENSION_SUFFIXES
                         if os.path.exists(os.path.join(folder, "_sosfilt" + sfx))), None)
            if path is None:
                return None
            spec = importlib.util.spec_from_file_location(name, path)
            mod = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(mod)
        except Exception:  # noqa: BLE001 - another layout, a loader that refuses: scipy.signal.sosfilt
            return None
    return getattr(mod, "_sosfilt", None)


def _sosfilt(sos: np.ndarray, x: np.ndarray, zi: np.ndarray) -> np.ndarray:
    if jit.compiled():
        return _sosfilt_kernel(sos, np.ascontiguousarray(x, dtype=float), zi)
    loop = _scipy_sosfilt_loop()  # reference mode: scipy's C loop, as sosfilt(sos, x, zi=zi) runs it
    if loop is not None:
        out = np.array(np.reshape(x, (1, -1)), dtype=float, order="C")  # (copies: filtered in place)
        state = np.array(np.reshape(zi, (1, len(sos), 2)), dtype=float, order="C")
        loop(np.asarray(sos, dtype=float), out, state)
        return out[0]
    from scipy.signal import sosfilt

    return sosfilt(sos, x, zi=zi)[0]


def sosfiltfilt_even(sos: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Zero-phase filtering of the 1-D ``x`` by ``sos``: forward and backward, the ends extended by their
    mirror images (scipy's ``sosfiltfilt(sos, x, padtype="even")``)."""
    x = np.asarray(x, dtype=float)
    ntaps = 2 * len(sos) + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    edge = 3 * ntaps
    if x.ndim != 1 or len(x) <= edge:
        raise ValueError(f"zero-phase filter: a 1-D series longer than {edge} samples needed")
    ext = np.concatenate([x[edge:0:-1], x, x[-2:-(edge + 2):-1]])
    zi = sosfilt_zi(sos)
    y = _sosfilt(sos, ext, zi * ext[0])
    y = _sosfilt(sos, y[::-1], zi * y[-1])[::-1]
    return y[edge:-edge]


@jit.njit
def _not_a_knot_end_rows(x, dx, slope, dl, d, du, b):  # pragma: no cover - compiled in its callers
    """The not-a-knot system's first and last rows, as ``CubicSpline.__init__`` sets them (the kernel's and
    the numpy copy's)."""
    n = x.shape[0]
    d0 = x[2] - x[0]
    d[0] = dx[1]
    du[0] = d0
    b[0] = ((dx[0] + 2 * d0) * dx[1] * slope[0] + dx[0] * dx[0] * slope[1]) / d0
    d1 = x[n - 1] - x[n - 3]
    d[n - 1] = dx[n - 3]
    dl[n - 2] = d1
    b[n - 1] = (dx[n - 2] * dx[n - 2] * slope[n - 3] + (2 * d1 + dx[n - 2]) * dx[n - 3] * slope[n - 2]) / d1


@jit.njit
def _not_a_knot_at_kernel(x, y, xs, out):  # pragma: no cover - compiled (scipy's operations, same order)
    """scipy's ``CubicSpline(x, y)(xs)`` for 1-D y (n >= 4, x strictly increasing, xs within [x0, x(n-1)]):
    the not-a-knot system of ``CubicSpline.__init__``, solved as LAPACK's ``dgtsv`` solves it (Gaussian
    elimination with partial pivoting, one right-hand side: scipy's ``solve_banded`` of a (1, 1) band), the
    coefficients of ``CubicHermiteSpline``, and ``PPoly``'s evaluation (interval x[i] <= v < x[i+1], the last
    closed; powers summed from the constant term), each expression in scipy's order."""
    n = x.shape[0]
    dx = np.empty(n - 1)
    slope = np.empty(n - 1)
    for i in range(n - 1):
        dx[i] = x[i + 1] - x[i]
        slope[i] = (y[i + 1] - y[i]) / dx[i]
    dl = np.empty(n - 1)
    d = np.empty(n)
    du = np.empty(n - 1)
    b = np.empty(n)
    for i in range(1, n - 1):
        d[i] = 2 * (dx[i - 1] + dx[i])
        b[i] = 3 * (dx[i] * slope[i - 1] + dx[i - 1] * slope[i])
    for i in range(1, n - 1):
        du[i] = dx[i - 1]
    for i in range(n - 2):
        dl[i] = dx[i + 1]
    _not_a_knot_end_rows(x, dx, slope, dl, d, du, b)
    # dgtsv, NRHS = 1: forward elimination with row interchanges, then the back solve
    for i in range(n - 2):
        if abs(d[i]) >= abs(dl[i]):
            fact = dl[i] / d[i]
            d[i + 1] = d[i + 1] - fact * du[i]
            b[i + 1] = b[i + 1] - fact * b[i]
            dl[i] = 0.0
        else:
            fact = d[i] / dl[i]
            d[i] = dl[i]
            temp = d[i + 1]
            d[i + 1] = du[i] - fact * temp
            dl[i] = du[i + 1]
            du[i + 1] = -fact * dl[i]
            du[i] = temp
            temp = b[i]
            b[i] = b[i + 1]
            b[i + 1] = temp - fact * b[i + 1]
    i = n - 2
    if abs(d[i]) >= abs(dl[i]):
        fact = dl[i] / d[i]
        d[i + 1] = d[i + 1] - fact * du[i]
        b[i + 1] = b[i + 1] - fact * b[i]
    else:
        fact = d[i] / dl[i]
        d[i] = dl[i]
        temp = d[i + 1]
        d[i + 1] = du[i] - fact * temp
        du[i] = temp
        temp = b[i]
        b[i] = b[i + 1]
        b[i + 1] = temp - fact * b[i + 1]
    b[n - 1] = b[n - 1] / d[n - 1]
    b[n - 2] = (b[n - 2] - du[n - 2] * b[n - 1]) / d[n - 2]
    for i in range(n - 3, -1, -1):
        b[i] = (b[i] - du[i] * b[i + 1] - dl[i] * b[i + 2]) / d[i]
    # b: the slopes at the knots; evaluate each point in its interval (xs sorted: a forward walk)
    j = 0
    for k in range(xs.shape[0]):
        v = xs[k]
        if v >= x[n - 1]:
            j = n - 2
        else:
            if v < x[j]:
                j = 0
            while j < n - 2 and v >= x[j + 1]:
                j += 1
        t = (b[j] + b[j + 1] - 2 * slope[j]) / dx[j]
        c0 = t / dx[j]
        c1 = (slope[j] - b[j]) / dx[j] - t
        sv = v - x[j]
        z = sv * sv
        out[k] = ((y[j] + b[j] * sv) + c1 * z) + c0 * (z * sv)
    return out


def _not_a_knot_at_np(x: np.ndarray, y: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """numpy :func:`_not_a_knot_at_kernel` (the reference code, n >= 4): the same system solved by LAPACK's
    ``dgtsv`` itself (as scipy's ``solve_banded`` calls it), the same evaluation for all points at once.
    scipy.interpolate is not imported: with scipy.optimize, scipy.sparse and scipy.spatial, which it
    imports, that is about 230 modules and 0.08-0.09 s of a short log's first run."""
    from scipy.linalg.lapack import dgtsv

    n = x.shape[0]
    dx = x[1:] - x[:-1]
    slope = (y[1:] - y[:-1]) / dx
    d, b = np.empty(n), np.empty(n)
    dl, du = np.empty(n - 1), np.empty(n - 1)
    d[1:n - 1] = 2 * (dx[:n - 2] + dx[1:])
    b[1:n - 1] = 3 * (dx[1:] * slope[:n - 2] + dx[:n - 2] * slope[1:])
    du[1:] = dx[:n - 2]
    dl[:n - 2] = dx[1:]
    _not_a_knot_end_rows(x, dx, slope, dl, d, du, b)
    _, _, _, b, info = dgtsv(dl, d, du, b, overwrite_dl=1, overwrite_d=1, overwrite_du=1, overwrite_b=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"cubic spline: singular system (dgtsv info {info})")
    # b: the slopes at the knots; each point in its interval x[j] <= v < x[j + 1] (the last closed)
    j = np.clip(np.searchsorted(x, xs, side="right") - 1, 0, n - 2)
    dxj, bj, sj = dx[j], b[j], slope[j]
    t = (bj + b[j + 1] - 2 * sj) / dxj
    c0 = t / dxj
    c1 = (sj - bj) / dxj - t
    sv = xs - x[j]
    z = sv * sv
    return ((y[j] + bj * sv) + c1 * z) + c0 * (z * sv)


def cubic_spline_at(x: np.ndarray, y: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """``scipy.interpolate.CubicSpline(x, y)(xs)`` (not-a-knot) for one column ``y`` at sorted points ``xs``
    inside [x[0], x[-1]], bit for bit: a numba kernel with scipy's operations in scipy's order in compiled
    mode (no spline object: a tenth of the time and of the temporaries), the same in numpy in reference
    mode, scipy itself for fewer than 4 points."""
    x = np.ascontiguousarray(x, dtype=float)
    y = np.ascontiguousarray(y, dtype=float)
    xs = np.ascontiguousarray(xs, dtype=float)
    if len(x) >= 4:
        if jit.compiled():
            return _not_a_knot_at_kernel(x, y, xs, np.empty(len(xs)))
        return _not_a_knot_at_np(x, y, xs)
    from scipy.interpolate import CubicSpline

    return CubicSpline(x, y)(xs)


@jit.njit
def _weighted_rows_kernel(c, j, w0, w1, w2, w3, scale, out):  # pragma: no cover - compiled
    """out[m, :] = scale * (w0[m] c[j[m]] + w1[m] c[j[m]+1] + w2[m] c[j[m]+2] + w3[m] c[j[m]+3]), summed in
    that order (numpy's broadcast expression, element by element)."""
    for m in range(j.shape[0]):
        i = j[m]
        for q in range(c.shape[1]):
            out[m, q] = scale * (w0[m] * c[i, q] + w1[m] * c[i + 1, q] + w2[m] * c[i + 2, q] + w3[m] * c[i + 3, q])
    return out


def weighted_rows(c: np.ndarray, j: np.ndarray, w: tuple, scale: float) -> np.ndarray:
    """``scale * (w0 * c[j] + w1 * c[j + 1] + w2 * c[j + 2] + w3 * c[j + 3])`` for weights (m, 1) and rows
    ``c`` (n, k): a cubic B-spline's four coefficients weighed (logtools.resample.Interpolant). A numba
    kernel in compiled mode (no gathered copies of c: a fifth of the time), the same numbers."""
    if jit.compiled():
        w0, w1, w2, w3 = (np.ascontiguousarray(x.reshape(-1), dtype=float) for x in w)
        return _weighted_rows_kernel(np.ascontiguousarray(c, dtype=float), np.ascontiguousarray(j, np.int64),
                                     w0, w1, w2, w3, float(scale), np.empty((len(j), c.shape[1])))
    w0, w1, w2, w3 = w
    return scale * (w0 * c[j] + w1 * c[j + 1] + w2 * c[j + 2] + w3 * c[j + 3])


def welch_psd(x: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density of each column of ``x`` (n, k) by Welch's method: periodic Hann
    window of ``nperseg`` samples, half overlap, each segment's mean removed, the segments' mean
    (scipy's ``welch(x, fs, nperseg=nperseg, axis=0)``). Returns (frequencies in Hz, psd (nf, k))."""
    x = np.asarray(x, dtype=float)
    x2 = x[:, None] if x.ndim == 1 else x
    n = len(x2)
    nperseg = int(min(nperseg, n))
    if nperseg < 1:
        raise ValueError("Welch spectrum of an empty series")
    step = nperseg - nperseg // 2
    nseg = (n - nperseg) // step + 1
    win = 0.5 + 0.5 * np.cos(np.linspace(-np.pi, np.pi, nperseg + 1)[:-1])  # periodic Hann
    segs = np.lib.stride_tricks.sliding_window_view(x2, nperseg, axis=0)[::step][:nseg]  # (nseg, k, nperseg)
    segs = segs - segs.mean(axis=2, keepdims=True)
    spec = rfft(segs * win, axis=2)
    p = (spec.real ** 2 + spec.imag ** 2).mean(axis=0).T * (1.0 / (fs * float((win * win).sum())))
    if nperseg % 2:
        p[1:] *= 2.0
    else:
        p[1:-1] *= 2.0
    f = sfft.rfftfreq(nperseg, 1.0 / fs)
    return f, (p[:, 0] if x.ndim == 1 else p)


def as_trapezoid_integrates(t_s: np.ndarray, x: np.ndarray, rate_hz: float, gap_s: float, upsample: int = 1
                            ) -> tuple[np.ndarray, np.ndarray]:
    """The columns of ``x`` (n, k) on sorted stamps ``t_s`` as a strapdown sampling their derivative at
    ``rate_hz`` and integrating it by the trapezoid (point samples, linear between them) reproduces them:
    each frequency f below rate_hz/2 scaled by x / tan(x), x = pi f / rate_hz (exact for a sinusoid at the
    sample instants), nothing above rate_hz/2 (an unknown alias: the derivative's noise there has no bound
    once integrated). A 15 Hz vibration keeps 0.68 of itself at 50 Hz, 0.93 at 200 Hz; a slow motion all of it.

    Returns (stamps, series) with ``upsample`` - 1 band-limited samples between two of ``t_s`` (their
    stamps interpolated linearly between the neighbours'): a series read by linear interpolation between
    coarse samples loses a fast motion (a 20 Hz vibration on a 100 Hz grid: 19 % at the midpoints).

    By FFT over each gap-free run (steps beyond ``gap_s`` split runs), at the run's median step; the straight
    line through each run's ends is taken out first (the trapezoid integrates it exactly) so that the run
    wraps without a jump."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(x, dtype=float)
    x2 = x[:, None] if x.ndim == 1 else x
    u = max(int(upsample), 1)
    cuts = np.flatnonzero(np.diff(t) > gap_s) + 1
    runs = [(int(a), int(b)) for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)])]
    # (one output array, filled a column at a time: at 4 h of a 200 Hz gyro the batched temporaries cost
    # 0.3 GB more at the alignment's peak)
    sizes = [(b - a - 1) * u + 1 if b - a >= 4 else b - a for a, b in runs]
    tt = np.empty(sum(sizes))
    xx = np.empty((len(tt), x2.shape[1]))
    o = 0
    for (a, b), size in zip(runs, sizes):
        n = b - a
        seg, ts = x2[a:b], t[a:b]
        if n < 4:
            tt[o:o + n], xx[o:o + n] = ts, seg
            o += n
            continue
        pos = np.arange(size, dtype=float) / u
        dt = float(np.median(np.diff(ts)))
        nfft = sfft.next_fast_len(n, real=True)
        arg = np.pi * sfft.rfftfreq(nfft, dt) / float(rate_hz)
        gain = np.zeros_like(arg)
        inside = arg < 0.5 * np.pi
        gain[inside] = 1.0
        nz = inside & (arg > 0.0)
        gain[nz] = arg[nz] / np.tan(arg[nz])
        if u > 1 and nfft % 2 == 0:
            gain[-1] *= 0.5  # (the Nyquist bin split between its two images)
        idx = np.arange(n, dtype=float)
        tt[o:o + size] = np.interp(pos, idx, ts)
        for j in range(x2.shape[1]):
            c = seg[:, j]
            step = (c[-1] - c[0]) / (n - 1)
            spec = rfft(c - c[0] - idx * step, nfft)
            spec *= gain
            col = xx[o:o + size, j]
            col[:] = irfft(spec, nfft * u)[:size]
            col *= u
            col += c[0]
            col += pos * step
        o += size
    return tt, (xx[:, 0] if x.ndim == 1 else xx)


def mad_sigma(x: np.ndarray) -> np.ndarray:
    """Each column's robust standard deviation (n, k) -> (k,): 1.4826 x its median absolute deviation."""
    x = np.asarray(x)
    if x.ndim != 2:
        return np.median(np.abs(x - np.median(x, axis=0)), axis=0) * 1.4826
    # each column's values contiguous, one column at a time: the medians' partitions run 20-30 % faster than
    # along the strided first axis, and give the same values (a median does not depend on the layout); the
    # copies are a column's (4 h of a 200 Hz triad's third differences: 23 MB, not 69 MB each)
    out = np.empty(x.shape[1])
    for j in range(x.shape[1]):
        c = np.ascontiguousarray(x[:, j])
        out[j] = np.median(np.abs(c - np.median(c)))
    return out * 1.4826


def correlate_valid(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross-correlation of the columns of ``a`` (n, k) with those of ``b`` (m, k), summed over the columns,
    at the lags where ``b`` lies inside ``a`` (n >= m): out[j] = sum_i sum_c a[j + i, c] b[i, c], by FFT
    (the sum over the columns of scipy's ``correlate(a[:, c], b[:, c], mode="valid", method="fft")``)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a2, b2 = (a[:, None], b[:, None]) if a.ndim == 1 else (a, b)
    n, m = len(a2), len(b2)
    if m > n:
        raise ValueError("correlate_valid: the second series is longer than the first")
    full = n + m - 1
    nfft = sfft.next_fast_len(full, real=True)
    prod = (rfft(a2, nfft, axis=0) * rfft(b2[::-1], nfft, axis=0)).sum(axis=1)
    return irfft(prod, nfft)[m - 1:n]
