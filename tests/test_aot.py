"""Kernels compiled ahead of time (logtools.aot): the argument-type match is numba's own typing, an export
serves only exactly matching calls, anything else goes to numba's dispatcher with the same results, and a
run served by the extension never loads numba and reports the same numbers."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

numba = pytest.importorskip("numba")

from logtools import aot  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _values():
    base = np.arange(24, dtype=float).reshape(2, 3, 4)
    out = []
    for dt in ("f8", "f4", "i8", "i4", "i2", "u1", "u2", "u8", "b1"):
        a = base.astype(dt)
        out += [a, a[0], a[0, 0], np.asfortranarray(a), a[:, ::2], a[0, :, 1], a.T]
        ro = a.copy()
        ro.flags.writeable = False
        out += [ro, ro[1]]
    out += [np.zeros(0), np.zeros((0, 3)), np.ones(5)[::-1], np.frombuffer(bytes(16), np.uint8)]
    out += [True, False, 0, -7, 2 ** 62, 1.5, float("nan"), np.float64(2.0), np.float32(1.0), np.int64(3),
            np.int32(-1), np.uint8(7), np.bool_(True), None, (1.0, 2.0, 3.0), (1, 2.0), (np.ones(3), 4),
            ((1, 2), 3.0)]
    return out


@pytest.mark.parametrize("x", _values(), ids=lambda x: type(x).__name__)
def test_argument_keys_are_numbas_typing(x):
    """The key a call's argument gets here is the key of the type numba's dispatcher gives it."""
    assert aot.arg_key(x) == aot.numba_key(numba.typeof(x))


def test_arguments_numba_would_type_otherwise_match_nothing():
    for x in ("text", b"bytes", [1.0, 2.0], {"a": 1}, 1j, 2 ** 70, np.zeros(3, ">f8"), np.zeros(3, "c16"),
              np.zeros(2, [("a", "f8")]), object()):
        key = aot.arg_key(x)
        assert key is None or key != aot.numba_key(numba.typeof(np.zeros(3))), x


_KERNELS_SRC = '''
import numpy as np


def scale_rows(x, k, out):
    """rows of x times k (in place on out); returns their sum"""
    s = 0.0
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            out[i, j] = x[i, j] * k
            s += out[i, j]
    return s


def helper(v):
    return v * 2.0 + 1.0


def twice_plus_one(x):
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i] = helper(x[i])
    return out
'''


@pytest.fixture
def built(tmp_path, monkeypatch):
    """A two-kernel module (one calling a third) compiled ahead of time into a cache under tmp_path."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "tapost_aot_probe.py").write_text(_KERNELS_SRC)
    monkeypatch.syspath_prepend(str(src))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(aot, "_KERNELS", [])
    monkeypatch.setattr(aot, "_LOADED", {})
    import tapost_aot_probe as probe

    disp = {}
    for name, opts in (("scale_rows", {"nogil": True}), ("helper", {}), ("twice_plus_one", {})):
        disp[name] = (numba.njit(**opts)(getattr(probe, name)), opts)
    probe.helper = disp["helper"][0]  # (as jit.njit leaves a module: its callees compiled)
    x = np.arange(12.0).reshape(3, 4)
    disp["scale_rows"][0](x, 2.0, np.empty_like(x))
    disp["twice_plus_one"][0](np.arange(5.0))
    os.makedirs(tmp_path / "cache" / "tapost")
    try:
        aot.build(list(disp.values()), "probe0123456789ab")
    except Exception as exc:  # noqa: BLE001 - no C compiler here: what the warm-up then says and skips
        pytest.skip(f"no ahead-of-time build on this machine: {exc}")
    table = aot.load("probe0123456789ab")
    assert table is not None
    yield probe, disp, table
    sys.modules.pop("tapost_aot_probe", None)


def test_an_exact_match_runs_the_export_anything_else_numbas_dispatcher(built):
    probe, disp, table = built
    scale = aot.kernel(probe.scale_rows, {"nogil": True}, table)
    twice = aot.kernel(probe.twice_plus_one, {}, table)
    assert "tapost_aot_probe:scale_rows" in table and len(table["tapost_aot_probe:scale_rows"]) == 1
    x = np.random.default_rng(1).normal(size=(5, 7))
    out = np.empty_like(x)
    s = scale(x, 1.5, out)
    assert scale._dispatcher is None  # (served by the extension: numba's dispatcher never made)
    ref_out = np.empty_like(x)
    assert s == disp["scale_rows"][0](x, 1.5, ref_out) and np.array_equal(out, ref_out)
    y = twice(np.linspace(0.0, 1.0, 9))
    assert np.array_equal(y, 2.0 * np.linspace(0.0, 1.0, 9) + 1.0) and twice._dispatcher is None

    # a type the warm-up never passed (float32; a strided view; an int scale): numba compiles it, same result
    for args in ((x.astype(np.float32), 1.5, np.empty((5, 7), np.float32)), (x[:, ::2], 1.5, np.empty((5, 4))),
                 (x, 2, np.empty_like(x))):
        got_out = args[2]
        got = scale(*args)
        want_out = np.empty_like(args[2])
        assert got == disp["scale_rows"][0](args[0], args[1], want_out) and np.array_equal(got_out, want_out)
    assert isinstance(scale._dispatcher, numba.core.registry.CPUDispatcher)
    assert scale.dispatcher().signatures  # (the fallback compiled there)


def test_a_stand_in_pickles_by_name(built):
    import pickle

    probe, _, table = built
    k = aot.kernel(probe.scale_rows, {"nogil": True}, table)
    probe.scale_rows = k  # (as jit.njit leaves it in its module)
    assert pickle.loads(pickle.dumps(k)) is k


def test_numbas_fallback_rebinds_the_stand_ins_its_kernels_call(built):
    """A kernel numba compiles after the extension served calls reaches its callees through its module's
    globals: the stand-ins there become numba's dispatchers first."""
    probe, disp, table = built
    probe.helper = aot.kernel(disp["helper"][0].py_func, {}, table)
    twice = aot.kernel(probe.twice_plus_one, {}, table)
    assert np.array_equal(twice(np.arange(3.0)), 2.0 * np.arange(3.0) + 1.0)
    assert type(probe.helper) is aot.Kernel  # (the extension served it: nothing rebound)
    x = np.arange(4, dtype=np.float32)  # (not exported: numba compiles twice_plus_one, which calls helper)
    assert np.array_equal(twice(x), 2.0 * x + 1.0)
    assert isinstance(probe.helper, numba.core.registry.CPUDispatcher)


def test_an_extension_for_another_cpu_or_python_is_not_loaded(built, tmp_path):
    _, _, _ = built
    folder = aot.aot_dir("probe0123456789ab")
    meta_path = os.path.join(folder, aot.TABLE)
    with open(meta_path) as f:
        meta = json.load(f)
    for key, value in (("cpu", "0" * 16), ("python", "cpython-20"), ("numpy", "0.1")):
        with open(meta_path, "w") as f:
            json.dump(dict(meta, **{key: value}), f)
        aot._LOADED.clear()
        assert aot.load("probe0123456789ab") is None
    with open(meta_path, "w") as f:
        f.write("{not json")
    aot._LOADED.clear()
    assert aot.load("probe0123456789ab") is None
    aot._LOADED.clear()
    assert aot.load("") is None


_RUN = textwrap.dedent('''
    import json, sys
    from pipelines import cli
    rc = cli.main(["analyze", sys.argv[1], sys.argv[2], "-o", sys.argv[3], "--no-recording", "--no-html"])
    from logtools import jit
    print(json.dumps({"rc": rc, "numba": "numba" in sys.modules, "aot": jit.aot_table() is not None}))
''')


def _analyze(out: str, **env) -> dict:
    proc = subprocess.run([sys.executable, "-c", _RUN, os.path.join(ROOT, "sample_logs", "master.mcap"),
                           os.path.join(ROOT, "sample_logs", "slave.tlog"), out],
                          capture_output=True, text=True, env=dict(os.environ, TAPOST_WARMUP="0", **env), cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _numbers(path: str):
    with open(path) as f:
        rep = json.load(f)
    rep.pop("timings_s", None)
    rep.pop("outputs", None)
    return rep


def test_the_sample_pair_served_ahead_of_time_loads_no_numba_and_reports_the_same(tmp_path):
    """On an installation whose warm-up built the extension (scripts/test.sh runs it): the sample pair's
    analysis never imports numba, and its report.json is numba's cache's to the last bit."""
    ahead = _analyze(str(tmp_path / "ahead"), TAPOST_KERNELS="compiled")
    if not ahead["aot"]:
        pytest.skip("this installation has no ahead-of-time build (no C compiler, or the warm-up not run)")
    assert ahead["numba"] is False
    cached = _analyze(str(tmp_path / "cached"), TAPOST_KERNELS="compiled", TAPOST_AOT="0")
    assert cached["numba"] is True and cached["aot"] is False
    a, b = _numbers(str(tmp_path / "ahead" / "report.json")), _numbers(str(tmp_path / "cached" / "report.json"))
    for k in ("run", "generated_utc", "created_utc"):
        a.pop(k, None)
        b.pop(k, None)
    assert a == b


def test_a_failed_build_is_one_line_and_leaves_numbas_cache_in_use(monkeypatch, tmp_path, capsys):
    """No C compiler (numba.pycc's error): the warm-up says so in one line on stderr and goes on."""
    from pipelines import warmup

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))

    def no_compiler(*a, **k):
        raise RuntimeError("Attempted to compile AOT function without the compiler used by `numpy.distutils` "
                           "present. If using conda try:\n\n#> conda install gcc_linux-64")

    monkeypatch.setattr(aot, "build", no_compiler)
    assert warmup.build_ahead(quiet=True) is None
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no working C compiler" in err[0] and "numba's cache" in err[0]


def test_the_kernel_fingerprint_follows_numbas_installation_without_importing_it(monkeypatch, tmp_path):
    """``jit.kernel_fingerprint`` is keyed on where numba is installed and its files' sizes and mtimes (another
    numba installed there changes it), "" without numba; a fresh process computes it without importing numba
    or importlib.metadata."""
    import importlib.machinery
    import importlib.util

    from logtools import jit

    fake = tmp_path / "numba"
    fake.mkdir()
    (fake / "__init__.py").write_text("")
    (fake / "_version.py").write_text("version_json = '{\"version\": \"0.60.0\"}'\n")
    spec = importlib.machinery.ModuleSpec("numba", None, origin=str(fake / "__init__.py"))
    real_find = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: spec if name == "numba" else real_find(name, *a))
    before = jit.kernel_fingerprint()
    assert before and jit.kernel_fingerprint() == before
    (fake / "_version.py").write_text("version_json = '{\"version\": \"0.61.2\"}'\n")
    assert jit.kernel_fingerprint() != before
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "numba" else real_find(name, *a))
    assert jit.kernel_fingerprint() == ""
    monkeypatch.undo()
    code = ("import sys; from logtools import jit; f = jit.kernel_fingerprint(); "
            "print(len(f), 'numba' in sys.modules, 'importlib.metadata' in sys.modules)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["16", "False", "False"]
