"""logtools.dsp against scipy.signal, whose algorithms it carries: the Butterworth design and the zero-phase
filter bit-equal (compiled kernel and reference path alike), Welch's spectrum and the FFT correlation equal
to rounding; the analysis path no longer imports scipy.signal."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from logtools import dsp, jit

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("order", [2, 4, 6, 8])
def test_the_butterworth_design_is_scipys_bit_for_bit(order):
    rng = np.random.default_rng(order)
    for wn in np.concatenate([[1e-4, 0.01, 0.5, 0.97, 0.999], rng.uniform(1e-4, 0.999, 200)]):
        got = dsp.butter_lowpass_sos(order, float(wn))
        want = signal.butter(order, float(wn), output="sos")
        assert got.shape == want.shape
        assert np.array_equal(got, want), (order, wn, np.max(np.abs(got - want)))


def test_odd_orders_and_bad_arguments():
    assert np.array_equal(dsp.butter_lowpass_sos(3, 0.2), signal.butter(3, 0.2, output="sos"))
    for order, wn in ((0, 0.2), (4, 0.0), (4, 1.0), (4, -0.1)):
        with pytest.raises(ValueError):
            dsp.butter_lowpass_sos(order, wn)


def test_the_step_initial_states_are_scipys():
    sos = signal.butter(4, 0.07, output="sos")
    assert np.allclose(dsp.sosfilt_zi(sos), signal.sosfilt_zi(sos), rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("compiled", [True, False])
def test_zero_phase_filter_equals_scipys_sosfiltfilt_even(compiled, monkeypatch):
    monkeypatch.setattr(jit, "compiled", lambda: compiled)  # the reference path: scipy's sosfilt loop
    rng = np.random.default_rng(7)
    t = np.arange(5000) / 200.0
    x = np.sin(2 * np.pi * 0.7 * t) + 0.3 * rng.standard_normal(t.size) + 5.0
    for order, wn in ((2, 0.3), (4, 0.05), (4, 0.004), (6, 0.2)):
        sos = signal.butter(order, wn, output="sos")
        want = signal.sosfiltfilt(sos, x, padtype="even")
        got = dsp.sosfiltfilt_even(sos, x)
        assert got.shape == x.shape
        assert np.max(np.abs(got - want)) <= 1e-12 * np.max(np.abs(want)), (order, wn, compiled)
    with pytest.raises(ValueError):
        dsp.sosfiltfilt_even(signal.butter(4, 0.1, output="sos"), x[:15])  # edge: 3 x 5 taps


@pytest.mark.parametrize("loaded", [True, False])
def test_the_reference_filter_is_scipys_sosfilt_bit_for_bit(loaded, monkeypatch):
    """Reference mode: scipy's C loop loaded from its extension module (or, where it cannot be, scipy.signal's
    sosfilt itself) gives sosfilt's output exactly, and leaves the caller's state untouched."""
    monkeypatch.setattr(jit, "compiled", lambda: False)
    if not loaded:
        monkeypatch.setattr(dsp, "_scipy_sosfilt_loop", lambda: None)
    else:
        assert dsp._scipy_sosfilt_loop() is not None  # (scipy's layout as this module expects it)
    rng = np.random.default_rng(3)
    for order, wn in ((2, 0.3), (4, 0.05), (6, 0.2), (8, 0.01)):
        sos = signal.butter(order, wn, output="sos")
        x = rng.standard_normal(3000) + 2.0
        zi = dsp.sosfilt_zi(sos) * x[0]
        x0, zi0 = x.copy(), zi.copy()
        got = dsp._sosfilt(sos, x, zi)
        assert np.array_equal(got, signal.sosfilt(sos, x, zi=zi)[0]), (order, wn)
        assert np.array_equal(x, x0) and np.array_equal(zi, zi0)


def test_reference_filtering_does_not_import_scipy_signal():
    """The first run after installing filters in reference mode without importing scipy.signal (0.8-1.3 s of
    imports on a 2-core machine)."""
    code = ("import sys, numpy as np\n"
            "from logtools import dsp, jit\n"
            "assert not jit.compiled()\n"
            "y = dsp.sosfiltfilt_even(dsp.butter_lowpass_sos(4, 0.1), np.random.default_rng(0).standard_normal(500))\n"
            "print(sorted(m for m in ('scipy.signal', 'scipy.stats', 'scipy.interpolate') if m in sys.modules))\n"
            "from scipy import signal\n"  # (imported afterwards, scipy.signal still works, with the same loop)
            "sos = dsp.butter_lowpass_sos(4, 0.1)\n"
            "assert np.array_equal(signal.sosfiltfilt(sos, y, padtype='even'), signal.sosfiltfilt(sos, y, padtype='even'))\n"
            "assert np.array_equal(dsp._sosfilt(sos, y, dsp.sosfilt_zi(sos)), signal.sosfilt(sos, y, zi=dsp.sosfilt_zi(sos))[0])\n")
    env = {**os.environ, "TAPOST_KERNELS": "reference",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]", p.stdout


def test_the_compiled_kernel_is_the_python_loop():
    if not jit.compiled():
        pytest.skip("kernels run as Python in this session")
    sos = signal.butter(4, 0.1, output="sos")
    x = np.random.default_rng(1).standard_normal(3000)
    zi = dsp.sosfilt_zi(sos) * x[0]
    a = dsp._sosfilt_kernel(sos, x, zi.copy())
    b = dsp._sosfilt_kernel.py_func(sos, x, zi.copy())
    c = signal.sosfilt(sos, x, zi=zi.copy())[0]
    assert np.array_equal(a, b) and np.max(np.abs(a - c)) <= 1e-13 * np.max(np.abs(c))


@pytest.mark.parametrize("spacing", ["jittered", "uneven", "few"])
def test_the_spline_kernel_is_scipys_cubic_spline_bit_for_bit(spacing):
    """logtools.dsp.cubic_spline_at against scipy's CubicSpline(x, y)(xs): the same numbers to the bit, on
    jittered stamps with a grid inside them (to_uniform's case), on intervals spread over three decades
    (rows swapped in the tridiagonal solve, its other branch), at the knots and at both ends; the Python
    function and the reference mode's numpy copy give them too."""
    from scipy.interpolate import CubicSpline

    rng = np.random.default_rng(3)
    n = {"jittered": 20000, "uneven": 3000, "few": 4}[spacing]
    if spacing == "jittered":
        x = 1.7e3 + np.arange(n) * 0.005 + rng.normal(0.0, 4e-4, n)
    else:
        x = np.cumsum(10.0 ** rng.uniform(-3, 0, n))
    y = np.sin(0.9 * x) + 0.1 * rng.standard_normal(n)
    xs = np.sort(np.concatenate([rng.uniform(x[0], x[-1], 5 * n), x, [x[0], x[-1]]]))
    want = CubicSpline(x, y)(xs)
    python = getattr(dsp._not_a_knot_at_kernel, "py_func", dsp._not_a_knot_at_kernel)  # (as Python)
    assert np.array_equal(python(x, y, xs, np.empty(len(xs))), want)
    assert np.array_equal(dsp._not_a_knot_at_np(x, y, xs), want)  # the reference mode's numpy copy
    if spacing == "uneven":  # the solve's row interchanges happen on this input
        d = 2 * (np.diff(x)[:-1] + np.diff(x)[1:])
        assert np.any(np.abs(d[:-1]) < np.diff(x)[2:])
    got = dsp.cubic_spline_at(x, y, xs)
    assert np.array_equal(got, want), float(np.max(np.abs(got - want)))


@pytest.mark.parametrize("n, nperseg", [(4096, 1024), (5000, 1024), (777, 256), (300, 300), (1001, 333)])
def test_welch_equals_scipys(n, nperseg):
    x = np.random.default_rng(n).standard_normal((n, 3)) + np.array([1.0, -2.0, 0.5])
    f, p = dsp.welch_psd(x, 200.0, nperseg)
    fw, pw = signal.welch(x, fs=200.0, nperseg=nperseg, axis=0)
    assert np.array_equal(f, fw)
    assert p.shape == pw.shape
    assert np.max(np.abs(p - pw)) <= 1e-12 * np.max(pw)
    f1, p1 = dsp.welch_psd(x[:, 0], 200.0, nperseg)  # 1-D in, 1-D out
    assert p1.shape == pw[:, 0].shape and np.allclose(p1, pw[:, 0], rtol=1e-12, atol=0)


def test_correlate_valid_is_the_sum_of_scipys_per_column_correlations():
    rng = np.random.default_rng(3)
    a, b = rng.standard_normal((2000, 3)), rng.standard_normal((500, 3))
    want = sum(signal.correlate(a[:, i], b[:, i], mode="valid", method="fft") for i in range(3))
    got = dsp.correlate_valid(a, b)
    assert got.shape == want.shape == (1501,)
    assert np.max(np.abs(got - want)) <= 1e-12 * np.max(np.abs(want))
    assert np.allclose(dsp.correlate_valid(a[:, 0], b[:, 0]),
                       signal.correlate(a[:, 0], b[:, 0], mode="valid", method="fft"), rtol=0, atol=1e-10)
    with pytest.raises(ValueError):
        dsp.correlate_valid(b, a)


@pytest.mark.parametrize("shape, n, axis", [((1000,), None, -1), ((997,), 2048, -1), ((1009,), 500, -1),
                                             ((3001, 3), 6144, 0), ((4, 3, 256), None, 2), ((600, 3, 14), None, 0),
                                             ((dsp.PLAN_FREE_MIN_LENGTH + 7,), None, -1)])
@pytest.mark.parametrize("plan_free_from", ["default", 0])
def test_the_plan_free_real_ffts_are_scipys_bit_for_bit_in_c_order(shape, n, axis, plan_free_from, monkeypatch):
    """dsp.rfft / dsp.irfft (numpy's pocketfft, which keeps no plans, for long transforms; with the threshold
    at 0 for every one) against scipy.fft: the same values to the bit and the same memory order, so that
    every reduction over their output rounds as before."""
    from scipy import fft as sfft

    if plan_free_from != "default":
        monkeypatch.setattr(dsp, "PLAN_FREE_MIN_LENGTH", plan_free_from)
    rng = np.random.default_rng(11)
    x = rng.standard_normal(shape)
    want, got = sfft.rfft(x, n, axis=axis), dsp.rfft(x, n, axis=axis)
    assert np.array_equal(got, want) and got.flags.c_contiguous and got.strides == want.strides
    m = n or shape[axis]
    for nn in (m, m + 1):  # (an even and an odd output length from the same spectrum)
        back_want, back = sfft.irfft(want, nn, axis=axis), dsp.irfft(want, nn, axis=axis)
        assert np.array_equal(back, back_want) and back.flags.c_contiguous and back.strides == back_want.strides


@pytest.mark.parametrize("kernels", ["compiled", "reference"])
def test_the_analysis_does_not_import_scipys_heavy_subpackages(tmp_path, kernels):
    """A whole analyze of the sample pair (report and recording too) imports none of scipy.signal,
    scipy.stats, scipy.interpolate, scipy.optimize or scipy.sparse, in compiled or reference mode: together
    about 300 modules and 0.3 s of a short log's run, for functions tapost computes itself (the reference
    code's zero-phase filter loads scipy's C loop of sosfilt alone, logtools.dsp._scipy_sosfilt_loop)."""
    sample = Path(__file__).resolve().parents[1] / "sample_logs"
    heavy = ("scipy.signal", "scipy.stats", "scipy.interpolate", "scipy.optimize", "scipy.sparse")
    code = ("import sys; from pipelines.cli import main; "  # (every stage in this one process)
            f"rc = main(['analyze', {str(sample / 'master.mcap')!r}, {str(sample / 'slave.tlog')!r}, "
            f"'-o', {str(tmp_path / 'out')!r}]); "
            f"print(rc, sorted(m for m in sys.modules if m.startswith({heavy!r}) and m != 'scipy.signal._sosfilt'))")
    env = {**os.environ, "TAPOST_KERNELS": kernels, "TAPOST_WARMUP": "0"}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env,
                       cwd=str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "0 []"


@pytest.mark.parametrize("kernels", ["compiled", "reference"])
def test_the_analysing_process_never_imports_pandas(tmp_path, kernels):
    """``tapost analyze`` of the sample pair as a user runs it: the process that parses and analyses never
    imports pandas (about 0.17 s of a short log's run; the logs are numpy arrays, their DataFrames made only
    when asked for). The recording's prepared child refuses it (test_recording)."""
    sample = Path(__file__).resolve().parents[1] / "sample_logs"
    argv = ["tapost", "analyze", str(sample / "master.mcap"), str(sample / "slave.tlog"), "-o", str(tmp_path / "out")]
    code = "\n".join([  # (the console script ends the process after its exit handlers: one prints)
        "import atexit, runpy, sys",
        "atexit.register(lambda: print(sorted(m for m in sys.modules if m.partition('.')[0] == 'pandas')))",
        f"sys.argv = {argv!r}",
        "runpy.run_module('pipelines.cli', run_name='__main__', alter_sys=True)"])
    env = {**os.environ, "TAPOST_KERNELS": kernels, "TAPOST_WARMUP": "0"}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env,
                       cwd=str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "[]", p.stdout[-500:]
    assert (tmp_path / "out" / "report.json").exists() and (tmp_path / "out" / "recording.rrd").exists()


_PROBE = '''
from pipelines import cli
cli.keep_scipy_docstrings()
from scipy._lib import _array_api as api
def f():
    """One line.

    More.
    """
table = {}
api.xp_capabilities(capabilities_table=table, cpu_only=True)(f)
print(api.FunctionDoc.__name__, f in table, repr(f.__doc__))
import scipy.fft
print(scipy.fft.fft.__doc__.startswith("Compute the 1-D discrete Fourier Transform."))
from scipy._lib import _util
import numpy as np, scipy.linalg
batched = scipy.linalg.det(np.stack([np.eye(2) * 2, np.eye(2) * 4]))
print(_util.FunctionDoc.__name__, np.allclose(batched, [4.0, 16.0]),
      "Solve the equation" in scipy.linalg.solve.__doc__)
'''

_STRICT = '''
from scipy._lib import _array_api as api
real = api.FunctionDoc
def strict(*args, **kwargs):
    def deco(f):
        api.FunctionDoc(f)["Parameters"][0]
        return f
    return deco
api.xp_capabilities = strict
from pipelines import cli
cli.keep_scipy_docstrings()
print(api.FunctionDoc is real)
'''


def test_scipys_docstrings_are_kept_as_they_are_in_a_log_commands_process():
    """``cli.keep_scipy_docstrings``: scipy's array-API decorator still records a function's capabilities but
    leaves its docstring as written (no scraping), and its batching decorator still batches (scipy.linalg);
    where the decorator is not the one known (here: one that reads a section the stand-in does not have),
    scipy's own scraper is put back."""
    p = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines() == ["_DocAsIs True 'One line.\\n\\n    More.\\n    '", "True",
                                             "_DocAsIs True True"]
    p = subprocess.run([sys.executable, "-c", _STRICT], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "True"


_ANALYZE_DOCS = '''
import atexit, sys
def said():
    import scipy.fft, scipy.linalg
    from scipy._lib import _array_api as api
    print(api.FunctionDoc.__name__, "Array API Standard Support" in (scipy.fft.fft.__doc__ or ""),
          "Array API Standard Support" in (scipy.linalg.solve.__doc__ or ""))
atexit.register(said)
from pipelines import cli
sys.argv = ["tapost", "analyze"] + sys.argv[1:]
cli.script()
'''


def test_scipys_docstrings_are_kept_in_an_analyze_process(tmp_path):
    """``tapost analyze`` keeps them once it has forked its parse's and recording's children (not before its
    first imports, as the other log commands): scipy's modules, imported after, still have them as written."""
    sample = ROOT / "sample_logs"
    p = subprocess.run([sys.executable, "-c", _ANALYZE_DOCS, str(sample / "master.mcap"), str(sample / "slave.tlog"),
                        "-o", str(tmp_path / "out"), "--no-recording", "--no-html"], capture_output=True, text=True,
                       timeout=300, env={**os.environ, "TAPOST_WARMUP": "0"})
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "_DocAsIs False False"


@pytest.mark.parametrize("k", [1, 3, 9])
def test_weighted_rows_is_numpys_broadcast_expression_bit_for_bit(k):
    """The B-spline evaluation's weighted sum of four coefficient rows (logtools.resample.Interpolant):
    the kernel gives numpy's ``scale * (w0 * c[j] + ... + w3 * c[j + 3])`` to the bit."""
    rng = np.random.default_rng(k)
    c = rng.standard_normal((1000, k)) * 1e3
    j = rng.integers(0, 997, 5000)
    f = rng.uniform(0.0, 1.0, (5000, 1))
    w = ((1 - f) ** 3 / 6.0, (3 * f ** 3 - 6 * f ** 2 + 4) / 6.0, (-3 * f ** 3 + 3 * f ** 2 + 3 * f + 1) / 6.0,
         f ** 3 / 6.0)
    for scale in (1.0, 1.0 / 0.005):
        want = scale * (w[0] * c[j] + w[1] * c[j + 1] + w[2] * c[j + 2] + w[3] * c[j + 3])
        assert np.array_equal(dsp.weighted_rows(c, j, w, scale), want)


def test_as_trapezoid_integrates_is_what_a_strapdown_integrates_from_point_samples():
    """A velocity made of a slow swing, a ramp and 8-20 Hz vibrations: its derivative sampled at 50 Hz and
    integrated by the trapezoid (what the slave's strapdown does) equals the velocity put through
    as_trapezoid_integrates at 50 Hz, while the velocity itself differs from it by 0.09-0.59 of each
    vibration's amplitude (0.8 peak to peak here); upsampled, the samples in between are the band-limited
    series'."""
    tones = [(0.8, 15.0, 0.3), (0.5, 8.0, 1.1), (0.3, 20.0, 2.0), (2.0, 0.05, 0.4)]
    rate = 50.0

    def vel(t):
        return 0.01 * t + sum(a * np.sin(2 * np.pi * f * t + p) for a, f, p in tones)

    def acc(t):
        return 0.01 + sum(a * 2 * np.pi * f * np.cos(2 * np.pi * f * t + p) for a, f, p in tones)

    t_m = np.arange(0.0, 100.0, 1.0 / 400.0) + 0.0011  # the master's 400 Hz gyro
    t_s = np.arange(20.0, 80.0, 1.0 / rate) + 0.0037  # the slave's samples
    a = acc(t_s)
    trap = vel(t_s[0]) + np.concatenate([[0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) / rate)])
    tt, seen = dsp.as_trapezoid_integrates(t_m, vel(t_m), rate, gap_s=1.0)
    assert np.array_equal(tt, t_m)
    at_s = np.interp(t_s, tt, seen)
    # equal but for the integration's constant (the linear interpolation between 400 Hz samples costs up
    # to 1.2 % of a 20 Hz tone)
    assert np.ptp(at_s - trap) < 0.02
    assert np.ptp(vel(t_s) - trap) > 0.5
    # x / tan(x) on a single tone, to the FFT's edge effects
    x = np.pi * 15.0 / rate
    _, one = dsp.as_trapezoid_integrates(t_m, np.sin(2 * np.pi * 15.0 * t_m), rate, gap_s=1.0)
    mid = (t_m > 10) & (t_m < 90)
    assert np.max(np.abs(one[mid] - x / np.tan(x) * np.sin(2 * np.pi * 15.0 * t_m[mid]))) < 1e-3
    # above half the rate: nothing; 2-D input column by column; a gap splits the runs
    _, hi = dsp.as_trapezoid_integrates(t_m, np.sin(2 * np.pi * 30.0 * t_m), rate, gap_s=1.0)
    assert np.max(np.abs(hi[mid])) < 1e-3
    t_gap = np.concatenate([t_m[t_m < 40], t_m[t_m > 45]])
    two = np.stack([vel(t_gap), np.sin(2 * np.pi * 15.0 * t_gap)], -1)
    tg, both = dsp.as_trapezoid_integrates(t_gap, two, rate, gap_s=1.0)
    assert np.array_equal(tg, t_gap) and both.shape == two.shape
    _, first = dsp.as_trapezoid_integrates(t_gap[t_gap < 40], two[t_gap < 40, 0], rate, gap_s=1.0)
    assert np.allclose(both[t_gap < 40, 0], first, atol=1e-12)
    # upsampled: 4 samples per 100 Hz step, the in-between ones the band-limited tone's
    t_c = np.arange(0.0, 60.0, 0.01)
    tu, up = dsp.as_trapezoid_integrates(t_c, np.sin(2 * np.pi * 15.0 * t_c), 1e6, gap_s=1.0, upsample=4)
    assert len(tu) == 4 * (len(t_c) - 1) + 1 and np.allclose(tu[::4], t_c)
    inner = (tu > 5) & (tu < 55)
    assert np.max(np.abs(up[inner] - np.sin(2 * np.pi * 15.0 * tu[inner]))) < 1e-3


@pytest.mark.parametrize("shape", [(1001, 3), (720, 1), (64, 12), (500,)])
def test_mad_sigma_is_the_columns_median_absolute_deviation_whatever_the_layout(shape):
    """mad_sigma (its medians along contiguous rows of a transposed copy) gives each column's 1.4826 x
    median |x - median x| to the bit, for C- and F-ordered and strided inputs alike."""
    rng = np.random.default_rng(7)
    x = rng.standard_normal(shape) * 3.0 + 1.0
    want = np.median(np.abs(x - np.median(x, axis=0)), axis=0) * 1.4826
    for v in (x, np.asfortranarray(x), np.repeat(x, 2, axis=0)[::2]):
        assert np.array_equal(dsp.mad_sigma(v), want)
    if x.ndim == 2:
        assert np.array_equal(dsp.mad_sigma(x)[0], dsp.mad_sigma(x[:, :1].copy())[0])
