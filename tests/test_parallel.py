"""pipelines.parallel: a stage in a forked child gives the same answer as in this process, exceptions
come back, and a child that dies falls back to running the call here."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipelines import parallel

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_logs"
posix_fork = pytest.mark.skipif(not hasattr(os, "fork") or (os.cpu_count() or 1) < 2, reason="needs fork and 2 cores")


def _pid_and_sum(x):
    return os.getpid(), float(np.sum(x))


def _boom():
    raise ValueError("the child's own error")


def _die():
    os._exit(3)


@pytest.fixture
def forking():
    parallel.enable(True)
    yield
    parallel.enable(False)


@posix_fork
def test_a_forked_call_returns_its_value_from_another_process(forking):
    x = np.arange(1000.0)
    pid, total = parallel.submit(_pid_and_sum, x).result()
    assert pid != os.getpid() and total == float(np.sum(x))


@posix_fork
def test_the_childs_exception_is_raised_here(forking):
    job = parallel.submit(_boom)
    with pytest.raises(ValueError, match="the child's own error"):
        job.result()


@posix_fork
def test_a_child_that_dies_falls_back_to_this_process(forking):
    job = parallel.submit(_pid_and_sum, np.ones(3))
    job._fn = _pid_and_sum  # (the child already runs: kill it to simulate a crash)
    if job._pid is not None:
        os.kill(job._pid, 9)
    pid, total = job.result()
    assert total == 3.0


def test_without_enable_nothing_forks():
    parallel.enable(False)
    assert parallel.submit(_pid_and_sum, np.ones(2)).result()[0] == os.getpid()


@posix_fork
@pytest.mark.slow
def test_the_cli_analyze_with_forked_alignment_equals_the_in_process_answer(tmp_path):
    """`tapost analyze` (its uncompensated run in a forked child) against the same analysis in this
    process with no fork: the same report figures."""
    from pipelines import api

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "pipelines.cli", "analyze", str(SAMPLE / "master.mcap"),
                        str(SAMPLE / "slave.tlog"), "-o", str(out), "--no-recording", "--no-html"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr
    rep = json.loads((out / "report.json").read_text())
    an = api.analyze(str(SAMPLE / "master.mcap"), str(SAMPLE / "slave.tlog"))
    for run in ("uncompensated", "compensated"):
        assert rep["alignment"][run]["mounting_rpy_deg"] == pytest.approx(
            list(an.alignment[run].mounting_rpy_deg), rel=1e-12, abs=1e-12)
        assert rep["alignment"][run]["mounting_sigma_deg"] == pytest.approx(
            list(an.alignment[run].mounting_sigma_deg), rel=1e-9)
