"""logtools.jit: compiled kernels or the reference code, one decision per process; the background
warm-up; the reference code gives the compiled code's answer."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from logtools import jit

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_logs"


def _env(tmp_path, **over) -> dict:
    return {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "xdg"),
            "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]), **over}


def _decide_in_child(tmp_path, code: str, **env) -> str:
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env=_env(tmp_path, **env), cwd=str(tmp_path))
    assert p.returncode == 0, p.stderr
    return p.stdout.strip()


def test_auto_runs_the_reference_code_until_the_stamp_and_compiles_for_large_inputs(tmp_path):
    pytest.importorskip("numba")
    ask = "from logtools import jit; {hint}print(jit.mode(), '|', jit.why())"
    # no stamp: reference code for a small input, compiled for a large one
    out = _decide_in_child(tmp_path, ask.format(hint="jit.hint_input_bytes(3_000_000); "), TAPOST_KERNELS="auto")
    assert out == "reference | kernels not compiled yet"
    big = jit.LARGE_INPUT_BYTES + 1
    out = _decide_in_child(tmp_path, ask.format(hint=f"jit.hint_input_bytes({big}); "), TAPOST_KERNELS="auto")
    assert out.startswith("compiled | large input")
    # the stamp (as the warm-up writes it once every kernel is cached): compiled for any input
    _decide_in_child(tmp_path, "from logtools import jit; jit.write_stamp(1.0)", TAPOST_KERNELS="compiled")
    out = _decide_in_child(tmp_path, ask.format(hint=""), TAPOST_KERNELS="auto")
    assert out == "compiled | kernels in numba's cache"
    # the user's override wins
    assert _decide_in_child(tmp_path, ask.format(hint=""), TAPOST_KERNELS="reference").startswith("reference")


def test_a_kernel_too_slow_as_python_compiles_on_first_use_even_in_reference_mode(tmp_path):
    """The flexure Kalman filter runs thousands of times inside L-BFGS-B's numerical gradient: as Python
    one real log took more than 13 min. In reference mode it compiles on its first call (one line on
    stderr); every other kernel stays the plain function."""
    pytest.importorskip("numba")
    (tmp_path / "kmod.py").write_text("def add(a, b):\n    return a + b\n")  # numba caches by source file
    code = ("import numpy as np; from logtools import jit; from logtools.latency import flexure as fx\n"
            "from kmod import add\n"
            "plain, always = jit.njit(add), jit.njit(add, always=True)\n"
            "assert jit.mode() == 'reference' and plain is add and always is not add and always.py_func is add\n"
            "assert fx._kf_whiten.py_func.__name__ == '_kf_whiten'\n"
            "print(always(np.arange(3.0), 1.0).tolist(), type(always.__closure__[0].cell_contents[0]).__name__)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env=_env(tmp_path, TAPOST_KERNELS="reference", NUMBA_CACHE_DIR=str(tmp_path / "nb"),
                                PYTHONPATH=os.pathsep.join([str(ROOT), str(tmp_path)])),
                       cwd=str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["[1.0,", "2.0,", "3.0]", "CPUDispatcher"]
    assert p.stderr.strip() == "tapost: compiling add (once; the reference code would take minutes)"


def test_the_stamp_is_keyed_on_the_kernel_sources(tmp_path, monkeypatch):
    pytest.importorskip("numba")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    a = jit.stamp_path()
    monkeypatch.setattr(jit, "KERNEL_MODULES", jit.KERNEL_MODULES[:-1])  # one source less: another key
    assert jit.stamp_path() != a
    assert Path(a).parent == tmp_path / "tapost"


def test_background_warmup_starts_once_detached_and_compiled(tmp_path, monkeypatch):
    pytest.importorskip("numba")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("TAPOST_KERNELS", "auto")
    monkeypatch.setenv("TAPOST_WARMUP", "1")
    started = []

    class FakePopen:
        def __init__(self, cmd, **kw):
            started.append((cmd, kw))
            self.pid = os.getpid()  # a live pid: the lock counts as held

    monkeypatch.setattr(jit.subprocess, "Popen", FakePopen)
    assert jit.start_background_warmup() is True
    cmd, kw = started[0]
    assert cmd[1:4] == ["-m", "pipelines.warmup", "--lock"]
    assert kw["env"]["TAPOST_KERNELS"] == "compiled" and kw["start_new_session"] is True
    assert kw["stdin"] is subprocess.DEVNULL
    assert jit.warmup_running()
    assert jit.start_background_warmup() is False and len(started) == 1  # one at a time
    Path(cmd[4]).unlink()
    monkeypatch.setenv("TAPOST_WARMUP", "0")
    assert jit.start_background_warmup() is False  # not wanted


@pytest.mark.slow
def test_the_reference_code_gives_the_compiled_answer_on_the_sample_pair(tmp_path):
    """The whole analyze of the sample pair in a child process running the reference code (no numba
    kernel at all), against this process's compiled kernels: the same latency and mountings."""
    from pipelines import api

    code = ("import json, sys; from pipelines import api; from logtools import jit; import sys as _s; "
            f"an = api.analyze({str(SAMPLE / 'master.mcap')!r}, {str(SAMPLE / 'slave.tlog')!r}); "
            "print(json.dumps({'mode': jit.mode(), 'numba': 'numba' in _s.modules, "
            "'lat': an.latency.latency_s, 'sig': an.latency.sigma_s, 'drift': an.latency.drift_ppm, "
            "'rpy': {r: list(a.mounting_rpy_deg) for r, a in an.alignment.items()}}))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600,
                       env=_env(tmp_path, TAPOST_KERNELS="reference"), cwd=str(tmp_path))
    assert p.returncode == 0, p.stderr
    ref = json.loads(p.stdout.strip().splitlines()[-1])
    assert ref["mode"] == "reference" and ref["numba"] is False  # numba not even imported
    an = api.analyze(str(SAMPLE / "master.mcap"), str(SAMPLE / "slave.tlog"))
    assert ref["lat"] == pytest.approx(an.latency.latency_s, rel=1e-9, abs=1e-12)
    assert ref["sig"] == pytest.approx(an.latency.sigma_s, rel=1e-6)
    assert ref["drift"] == pytest.approx(an.latency.drift_ppm, rel=1e-6, abs=1e-9)
    for run, res in an.alignment.items():
        assert ref["rpy"][run] == pytest.approx(list(res.mounting_rpy_deg), abs=1e-9)


@pytest.mark.slow
def test_warmup_compiles_every_reader_and_the_analysis_and_writes_the_stamp(tmp_path):
    pytest.importorskip("numba")
    env = _env(tmp_path, TAPOST_KERNELS="auto")
    p = subprocess.run([sys.executable, "-m", "pipelines.warmup"], capture_output=True, text=True, timeout=900,
                       env=env, cwd=str(tmp_path))
    assert p.returncode == 0, p.stdout + p.stderr
    for what in ("mcap reader", "tlog reader", "dataflash reader", "ulog reader", "csv reader",
                 "latency, compensation, alignment"):
        assert what in p.stdout, p.stdout
    stamps = list((tmp_path / "xdg" / "tapost").glob("kernels-*.json"))
    assert len(stamps) == 1 and json.loads(stamps[0].read_text())["compile_s"] > 0
    out = _decide_in_child(tmp_path, "from logtools import jit; print(jit.mode())", TAPOST_KERNELS="auto")
    assert out == "compiled"
