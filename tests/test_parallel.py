"""pipelines.parallel: a stage in a forked child gives the same answer as in this process, exceptions
come back, and a child that dies falls back to running the call here."""
from __future__ import annotations

import dataclasses
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


def _big_and_small(n):
    import pandas as pd

    frame = pd.DataFrame({"a": np.arange(n, dtype=float), "b": -np.arange(n, dtype=float)},
                         index=pd.Index(np.arange(n) * 0.005, name="t_s"))
    return frame, np.arange(10.0), np.asfortranarray(np.arange(3.0 * n).reshape(n, 3))


def _maps(arr: np.ndarray) -> bool:
    """Whether the array's memory is a mapping (its base chain ends in a memoryview of an mmap)."""
    import mmap

    b = arr
    while isinstance(b, np.ndarray) and b.base is not None:
        b = b.base
    return isinstance(b, memoryview) and isinstance(b.obj, mmap.mmap)


@pytest.mark.skipif(not hasattr(os, "memfd_create"), reason="needs memfd (Linux)")
def test_an_answers_large_arrays_come_through_shared_memory_not_the_pipe():
    """_answer puts arrays of OOB_MIN_BYTES and more into the memfd and only a small pickle into the pipe;
    _read_answer maps them back: equal values, writable, small arrays still in the pickle."""
    n = parallel.OOB_MIN_BYTES // 8 + 1000
    r, w = os.pipe()
    memfd = parallel._memfd()
    try:
        parallel._answer(_big_and_small, (n,), {}, w, memfd)
        assert os.fstat(memfd).st_size >= 4 * n * 8  # (two columns, the index, the (n, 3) array's three)
        ok, (frame, small, f3) = parallel._read_answer(r, memfd=memfd)
    finally:
        parallel._close(memfd)
    want = _big_and_small(n)
    assert ok and frame.equals(want[0]) and np.array_equal(small, want[1]) and np.array_equal(f3, want[2])
    assert f3.flags.f_contiguous and _maps(f3) and not _maps(small)
    f3[0, 0] = -1.0  # (writable: a private, copy-on-write mapping)
    assert f3[0, 0] == -1.0


def test_without_a_memfd_the_answer_comes_through_the_pipe_alone():
    n = parallel.OOB_MIN_BYTES // 8 + 1000
    r, w = os.pipe()
    import threading

    th = threading.Thread(target=parallel._answer, args=(_big_and_small, (n,), {}, w, -1))
    th.start()  # (the whole pickle in the pipe: written beside the read, which empties it)
    ok, (frame, small, f3) = parallel._read_answer(r)
    th.join()
    assert ok and frame.equals(_big_and_small(n)[0]) and not _maps(f3)


def _open_fds():
    return set(int(x) for x in os.listdir("/proc/self/fd"))


@posix_fork
@pytest.mark.skipif(not os.path.isdir("/proc/self/fd") or not hasattr(os, "memfd_create"), reason="needs /proc, memfd")
def test_a_child_holds_no_other_childs_memfd_and_the_parent_none_once_answered(forking):
    """Each child's memfd is closed here once its answer is read; a child forked while another runs does
    not hold the other's (its pages would outlive the answer)."""
    before = _open_fds()
    first = parallel.submit(_big_and_small, 10)
    second = parallel.submit(_open_fds)
    assert first._memfd in _open_fds() and first._memfd not in second.result()
    first.result()
    assert _open_fds() <= before | {first._rfd}  # (the read end closed by its fdopen)


def _scribble(arr):
    arr[:] = 7.0
    return float(arr.sum())


@posix_fork
def test_a_mapped_answer_is_private_to_the_parent(forking):
    """An answer's mapped arrays are copy-on-write: a child forked later that writes into one changes
    neither the parent's copy nor anything the parent sees."""
    n = parallel.OOB_MIN_BYTES // 8 + 1000
    frame, _small, f3 = parallel.submit(_big_and_small, n).result()
    assert _maps(f3) or not hasattr(os, "memfd_create")
    assert parallel.submit(_scribble, f3).result() == 7.0 * f3.size
    assert np.array_equal(f3, _big_and_small(n)[2])


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
    # the IMU-to-IMU fit, computed in a second forked child beside the runs: the same triads' rotations
    here = an.align_sections["imu_to_imu"]
    for key in ("gyro_rpy_deg", "gyro_sigma_deg", "accel_rpy_deg", "accel_sigma_deg"):
        assert here[key] is not None and rep["alignment"]["imu_to_imu"][key] == pytest.approx(
            list(here[key]), rel=1e-12, abs=1e-12)


_WAIT_IMPORTS = """
import sys
from pipelines import analyze, parallel
parallel.enable(True)
opts = analyze.AnalyzeOptions(recording={rec}, html={html})
an = analyze.compute(sys.argv[1], sys.argv[2], opts)
assert an.alignment["compensated"] is not None
print(" ".join(m for m in ("rerun", "pipelines.recording", "pipelines.html") if m in sys.modules))
"""


@posix_fork
@pytest.mark.parametrize("rec,html", [(True, True), (False, True), (False, False)])
def test_while_the_alignment_children_run_the_outputs_modules_are_imported(rec, html):
    """compute() imports the outputs' modules (rerun's SDK: 0.4 s) where it would wait for the alignment's
    forked children; only those of the outputs asked for (a process without them never imports rerun)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.run([sys.executable, "-c", _WAIT_IMPORTS.format(rec=rec, html=html), str(SAMPLE / "master.mcap"),
                        str(SAMPLE / "slave.tlog")], capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr
    got = set(p.stdout.split())
    want = ({"rerun", "pipelines.recording"} if rec else set()) | ({"pipelines.html"} if html else set())
    assert got == want


_FORK_LIMIT = """
import sys
from pipelines import analyze, parallel
parallel.enable(True)
sent = []
submit = parallel.submit
def recording_submit(fn, *args, **kwargs):
    sent.append(getattr(fn, "__name__", str(fn)))
    return submit(fn, *args, **kwargs)
parallel.submit = recording_submit
opts = analyze.AnalyzeOptions(recording=False, html=False, compare=False)
figures = []
for limit in (parallel.FORK_ALIGNMENT_MAX_SAMPLES, 0):
    parallel.FORK_ALIGNMENT_MAX_SAMPLES = limit
    sent.clear()
    an = analyze.compute(sys.argv[1], sys.argv[2], opts)
    figures.append([list(an.alignment[r].mounting_rpy_deg) for r in ("uncompensated", "compensated")])
    print(limit, " ".join(sorted(set(sent))) or "-")
assert figures[0] == figures[1], figures
"""


@posix_fork
def test_long_logs_run_the_alignment_in_turn_not_in_a_forked_child():
    """Beyond FORK_ALIGNMENT_MAX_SAMPLES the uncompensated run is not forked beside the compensated one (their
    arrays would sit side by side: the 4 h pair's process tree peaked at 3.0 GB so), nor the IMU-to-IMU fit
    beside them; the same mounting figures either way."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.run([sys.executable, "-c", _FORK_LIMIT, str(SAMPLE / "master.mcap"), str(SAMPLE / "slave.tlog")],
                       capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr
    runs = dict(line.split(" ", 1) for line in p.stdout.strip().splitlines())
    assert "_alignment" in runs[str(parallel.FORK_ALIGNMENT_MAX_SAMPLES)].split()
    assert runs["0"] == "-"


def _import_state():
    return os.getpid(), "colorsys" in sys.modules


@posix_fork
def test_a_prepared_child_imports_ahead_and_runs_the_call_sent_later(forking):
    sys.modules.pop("colorsys", None)
    assert parallel.prepare("t", ("colorsys",))
    assert not parallel.prepare("t", ("colorsys",))  # one child per name
    assert parallel.is_prepared("t") and not parallel.is_prepared("other")
    pid, imported = parallel.call_prepared("t", _import_state)
    assert pid != os.getpid() and imported and "colorsys" not in sys.modules
    # used once: the next call of the name runs here
    assert parallel.call_prepared("t", _pid_and_sum, np.ones(2)) == (os.getpid(), 2.0)


def _mark_setup():
    os.environ["TAPOST_TEST_SETUP"] = str(os.getpid())


def _failing_setup():
    raise RuntimeError("a setup that fails")


def _setup_state():
    return os.getpid(), os.environ.get("TAPOST_TEST_SETUP")


@posix_fork
def test_a_prepared_child_runs_its_setup_after_its_imports_and_a_failing_one_changes_nothing(forking):
    os.environ.pop("TAPOST_TEST_SETUP", None)
    assert parallel.prepare("s", ("colorsys",), setup=(__name__, "_mark_setup"))
    pid, mark = parallel.call_prepared("s", _setup_state)
    assert pid != os.getpid() and mark == str(pid) and "TAPOST_TEST_SETUP" not in os.environ
    assert parallel.prepare("f", (), setup=(__name__, "_failing_setup"))
    assert parallel.call_prepared("f", _pid_and_sum, np.ones(3))[1] == 3.0
    assert parallel.prepare("m", (), setup=("no_such_module_here", "f"))
    assert parallel.call_prepared("m", _pid_and_sum, np.ones(2))[1] == 2.0


@posix_fork
def test_a_prepared_childs_exception_comes_back_and_what_cannot_travel_runs_here(forking):
    parallel.prepare("boom", ())
    with pytest.raises(ValueError, match="the child's own error"):
        parallel.call_prepared("boom", _boom)
    parallel.prepare("local", ())
    assert parallel.call_prepared("local", lambda: os.getpid()) == os.getpid()  # a lambda does not pickle


def _pid_after_flag(path):
    import time

    deadline = time.monotonic() + 30.0
    while not os.path.exists(path) and time.monotonic() < deadline:  # (runs beside the caller: waits for it)
        time.sleep(0.01)
    return os.getpid(), os.path.exists(path)


@posix_fork
def test_a_started_call_runs_beside_the_caller_in_the_prepared_child_or_a_forked_one(forking, tmp_path):
    """``start_prepared``: the call is under way when it returns (it sees a file the caller writes only
    afterwards), in the prepared child where there is one, else in a child forked for it; its exception
    comes back from ``result()``; without forking, it runs here at ``result()``."""
    parallel.prepare("rec", ())
    prepared_pid = parallel._PREPARED["rec"][0]
    flag = tmp_path / "html-written"
    job = parallel.start_prepared("rec", _pid_after_flag, str(flag))
    assert not parallel.is_prepared("rec")
    flag.write_text("x")
    assert job.result() == (prepared_pid, True)
    flag2 = tmp_path / "second"
    job = parallel.start_prepared("rec", _pid_after_flag, str(flag2))  # (none prepared any more: forked)
    flag2.write_text("x")
    pid, seen = job.result()
    assert seen and pid not in (os.getpid(), prepared_pid)
    with pytest.raises(ValueError, match="the child's own error"):
        parallel.start_prepared("none", _boom).result()
    parallel.enable(False)
    assert parallel.start_prepared("none", _pid_and_sum, np.ones(3)).result() == (os.getpid(), 3.0)


def _pid_flag_later(path, later):
    """Waits for the caller's flag (written after its ``send`` returned), then takes the later object."""
    pid, seen = _pid_after_flag(path)
    got = later()
    return pid, seen, len(got), float(got.sum())


def _later_or_marker(path, later):
    try:
        later()
    except EOFError:
        with open(path, "a") as fh:  # (appended: a second run of the call would show)
            fh.write("nothing came\n")
        raise
    return "got it"


@posix_fork
@pytest.mark.parametrize("prepared", [False, True])
def test_an_awaiting_call_starts_now_and_gets_its_later_object_without_blocking_the_sender(forking, tmp_path,
                                                                                            prepared):
    """``start_prepared_awaiting`` (and ``submit_awaiting`` under it): the call runs beside the caller from
    the start, in the prepared child where there is one, else in a forked one; ``send`` of an object larger
    than a pipe holds returns before the call asks for it (the call waits for a flag written after send);
    the call's ``later()`` gives that object."""
    if prepared:
        parallel.prepare("rec", ())
        prepared_pid = parallel._PREPARED["rec"][0]
    flag = tmp_path / "sent"
    job = parallel.start_prepared_awaiting("rec", _pid_flag_later, str(flag))
    big = np.arange(500_000.0)  # 4 MB: 60 times a pipe's buffer
    job.send(big)
    flag.write_text("x")
    pid, seen, n, total = job.result()
    assert seen and (n, total) == (len(big), float(big.sum()))
    assert pid == prepared_pid if prepared else pid not in (os.getpid(),)
    parallel.enable(False)  # without forking: the call runs here at result(), with the object sent
    flag.unlink()
    job = parallel.start_prepared_awaiting("rec", _pid_flag_later, str(flag))
    job.send(np.ones(3))
    flag.write_text("x")
    assert job.result() == (os.getpid(), True, 3, 3.0)


@posix_fork
@pytest.mark.parametrize("prepared", [False, True])
def test_an_abandoned_awaiting_call_ends_on_its_own_told_nothing_comes(forking, tmp_path, prepared):
    """``abandon`` before ``send``: the child's ``later()`` raises EOFError (a recording removes its temporary
    file then) and the child leaves; nothing is waited for here."""
    if prepared:
        parallel.prepare("rec", ())
    marker = tmp_path / "marker"
    job = parallel.start_prepared_awaiting("rec", _later_or_marker, str(marker))
    pid = job._pid
    job.abandon()
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and marker.read_text() == "nothing came\n"
    job.abandon()  # (twice: nothing)


@posix_fork
@pytest.mark.parametrize("prepared", [False, True])
def test_an_awaiting_call_never_sent_its_object_raises_eoferror(forking, tmp_path, prepared):
    """``result()`` without ``send``: the call's ``later()`` raises EOFError, which ``result()`` raises here
    (the child's marker shows it ran there, not again here)."""
    if prepared:
        parallel.prepare("rec", ())
    marker = tmp_path / "marker"
    job = parallel.start_prepared_awaiting("rec", _later_or_marker, str(marker))
    with pytest.raises(EOFError, match="nothing was sent"):
        job.result()
    assert marker.read_text() == "nothing came\n"


@posix_fork
def test_a_prepared_child_that_died_or_was_released_changes_nothing(forking):
    parallel.prepare("dead", ())
    pid = parallel._PREPARED["dead"][0]
    os.kill(pid, 9)
    assert parallel.call_prepared("dead", _pid_and_sum, np.ones(4)) == (os.getpid(), 4.0)
    parallel.prepare("unused", ())
    pid = parallel._PREPARED["unused"][0]
    parallel.release("unused")
    assert "unused" not in parallel._PREPARED
    try:
        _, status = os.waitpid(pid, 0)  # it saw its end of file and left on its own
    except ChildProcessError:  # ... so quickly that release() reaped it already (a race seen under load)
        return
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


def test_without_enable_nothing_is_prepared():
    parallel.enable(False)
    assert not parallel.prepare("x", ("colorsys",))
    assert parallel.call_prepared("x", _pid_and_sum, np.ones(1)) == (os.getpid(), 1.0)


@posix_fork
@pytest.mark.slow
def test_the_cli_recording_written_by_the_prepared_child_equals_the_in_process_one(tmp_path):
    """`tapost analyze` writes recording.rrd in the child that imported rerun during the parse: the same
    entities and rows as write_recording in this process."""
    from pipelines import api
    from pipelines.recording import read_entities, read_properties, write_recording

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "pipelines.cli", "analyze", str(SAMPLE / "master.mcap"),
                        str(SAMPLE / "slave.tlog"), "-o", str(out), "--no-html"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["outputs"]["recording"] == "recording.rrd" and not rep["skipped"]
    an = api.analyze(str(SAMPLE / "master.mcap"), str(SAMPLE / "slave.tlog"))
    write_recording(str(tmp_path / "here.rrd"), an, an.build_report(an.timings_s, {}))
    assert read_entities(str(out / "recording.rrd")) == read_entities(str(tmp_path / "here.rrd"))
    # (the child started before the report existed and logged its headline property last: the same property)
    assert read_properties(str(out / "recording.rrd")) == read_properties(str(tmp_path / "here.rrd"))


def test_a_recording_the_child_could_not_write_without_pandas_is_written_here(tmp_path):
    """Should rerun need pandas in the recording's child, which refuses it (pipelines.recording.without_pandas),
    write_outputs writes the recording in the analysing process: the report lists it, nothing is skipped."""
    from pipelines import api
    from pipelines.analyze import write_outputs
    from pipelines.recording import read_entities

    class _Refused:  # (the child's answer: the refusal, as it comes back through the pipe)
        def send(self, rep):
            pass

        def result(self):
            raise ModuleNotFoundError("No module named 'pandas' (refused in the recording's process)",
                                      name="pandas")

    an = api.analyze(str(SAMPLE / "master.mcap"), str(SAMPLE / "slave.tlog"))
    out = write_outputs(an, str(tmp_path / "out"), recording=_Refused())
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["outputs"]["recording"] == "recording.rrd" and not rep["skipped"]
    assert out.paths["recording"] and "/rates/x/master" in read_entities(out.paths["recording"])


def test_the_cli_runs_one_blas_thread_and_no_numpy_huge_pages_unless_the_user_chose(tmp_path):
    """`tapost` sets BLAS_THREADS and NUMPY_HUGEPAGES where the environment does not say, before numpy is
    imported (after, the variables would do nothing: numpy reads its page switch at import), and keeps a
    value the user set; its children inherit them."""
    from pipelines import cli

    probe = ("import os, sys, pipelines.cli as c\n"
             "assert 'numpy' not in sys.modules\n"
             "sys.argv = ['tapost', '--version']\n"
             "try:\n    c.main()\nexcept SystemExit:\n    pass\n"
             "import numpy\n"
             "print(os.environ['OPENBLAS_NUM_THREADS'], os.environ['OMP_NUM_THREADS'],\n"
             "      int(numpy._core.multiarray._get_madvise_hugepage()))")
    names = (*cli.BLAS_THREAD_VARIABLES, cli.NUMPY_HUGEPAGE_VARIABLE)
    env = {k: v for k, v in os.environ.items() if k not in names}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    p = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split()[-3:] == [cli.BLAS_THREADS, cli.BLAS_THREADS, cli.NUMPY_HUGEPAGES]
    p = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                       env={**env, "OPENBLAS_NUM_THREADS": "3", cli.NUMPY_HUGEPAGE_VARIABLE: "1"}, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split()[-3:] == ["3", cli.BLAS_THREADS, "1"]


@posix_fork
def test_large_inputs_parse_the_larger_file_in_a_child_with_the_same_log(forking, monkeypatch, tmp_path):
    """Above FORK_PARSE_MIN_INPUT_BYTES the larger file is parsed in a forked child while the other is parsed
    here: the same InsLogs as parsed in turn, whichever side the child has; and with both files bad, the
    master's error is the one raised (as in turn), whichever parse ends first."""
    from logtools.errors import InputError
    from parsers.registry import load
    from pipelines import analyze

    m, s = str(SAMPLE / "master.mcap"), str(SAMPLE / "slave.tlog")
    assert os.path.getsize(s) > os.path.getsize(m)
    monkeypatch.setattr(parallel, "FORK_PARSE_MIN_INPUT_BYTES", 0)
    calls = []
    monkeypatch.setattr(parallel, "submit", lambda *a, **k: calls.append(a) or parallel.Pending(a[0], a[1:], k))
    waited = []
    ref = {m: load(m), s: load(s)}
    for first, second in ((m, s), (s, m)):  # (the slave's file the larger, then the master's)
        calls.clear()
        master, slave = analyze.parse_pair(first, second, meanwhile=lambda: waited.append(len(calls)))
        assert len(calls) == 1 and calls[0][1] == s  # the larger file forked
        for got, want in ((master, ref[first]), (slave, ref[second])):
            assert got.imu.equals(want.imu) and got.nav.equals(want.nav) and got.meta == want.meta
    assert waited == [1, 1]  # the later stage's work done once a pair, while the child parsed
    for m_bytes, s_bytes in ((4096, 100), (100, 4096)):
        bad_m, bad_s = tmp_path / f"m{m_bytes}.mcap", tmp_path / f"s{s_bytes}.tlog"
        bad_m.write_bytes(b"\x00" * m_bytes)
        bad_s.write_bytes(b"\x00" * s_bytes)
        with pytest.raises(InputError) as err:
            analyze.parse_pair(str(bad_m), str(bad_s), meanwhile=lambda: waited.append("bad"))
        assert str(bad_m) in str(err.value) and waited == [1, 1]  # (not after a failed parse)
    parallel.enable(False)  # no fork: nothing to wait for, the later stage imports its own
    analyze.parse_pair(m, s, meanwhile=lambda: waited.append("no fork"))
    assert waited == [1, 1]


@posix_fork
def test_small_inputs_parse_both_files_in_a_child_with_the_same_logs(forking, tmp_path):
    """Below FORK_PARSE_MIN_INPUT_BYTES ``analyze.run`` forks one child that parses both files, and parse_pair
    calls ``meanwhile`` before it takes the answer: the same InsLogs as parsed here; with both files bad, the
    master's error, as in turn."""
    from logtools.errors import InputError
    from parsers.registry import load
    from pipelines import analyze

    m, s = str(SAMPLE / "master.mcap"), str(SAMPLE / "slave.tlog")
    waited = []
    master, slave = analyze.parse_pair(m, s, meanwhile=lambda: waited.append(1),
                                       there=parallel.submit(analyze._parse_both, m, s))
    for got, want in ((master, load(m)), (slave, load(s))):
        assert got.imu.equals(want.imu) and got.nav.equals(want.nav) and got.meta == want.meta
    assert waited == [1]
    bad_m, bad_s = tmp_path / "m.mcap", tmp_path / "s.tlog"
    bad_m.write_bytes(b"\x00" * 100)
    bad_s.write_bytes(b"\x00" * 4096)
    with pytest.raises(InputError) as err:
        analyze.parse_pair(str(bad_m), str(bad_s), there=parallel.submit(analyze._parse_both, str(bad_m), str(bad_s)))
    assert str(bad_m) in str(err.value)


def test_the_parse_goes_to_a_child_only_where_it_sets_up_no_kernels_there(monkeypatch):
    """The reference code or the ahead-of-time extension: the child's parse sets nothing up; kernels from
    numba's cache would be set up in the child again, so the parse stays in the analysing process."""
    from logtools import jit
    from pipelines import analyze

    for compiled, table, child in ((False, None, True), (True, {"k": 1}, True), (True, None, False)):
        monkeypatch.setattr(jit, "compiled", lambda c=compiled: c)
        monkeypatch.setattr(jit, "aot_table", lambda t=table: t)
        assert analyze._parse_child_sets_up_nothing() is child


def test_large_pairs_fix_the_mmap_threshold_and_the_user_setting_wins(monkeypatch):
    """From LARGE_PAIR_ROWS rows on, glibc's mmap threshold is fixed at MMAP_THRESHOLD_BYTES; below, in the
    CLI's process (forking enabled), at SMALL_PAIR_MMAP_BYTES with the trim threshold at SMALL_PAIR_TRIM_BYTES,
    and in a Python API caller's process malloc's policy is left alone; where the user exported
    MALLOC_MMAP_THRESHOLD_ or MALLOC_TRIM_THRESHOLD_, it is left alone too; malloc_trim between stages."""
    calls = []

    class FakeLibc:
        def mallopt(self, param, value):
            calls.append(("mallopt", param, value))

        def malloc_trim(self, pad):
            calls.append(("malloc_trim", pad))

    monkeypatch.setattr(parallel, "_libc", lambda: FakeLibc())
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.setitem(parallel._ENABLED, "on", False)
    parallel.malloc_policy(parallel.LARGE_PAIR_ROWS - 1)
    assert calls == []
    parallel.small_pair_malloc(1000)
    assert calls == []
    parallel.malloc_policy(parallel.LARGE_PAIR_ROWS)
    large = [("mallopt", parallel.M_MMAP_THRESHOLD, parallel.MMAP_THRESHOLD_BYTES),
             ("mallopt", parallel.M_TRIM_THRESHOLD, parallel.GLIBC_TRIM_THRESHOLD_BYTES)]
    assert calls == large
    monkeypatch.setitem(parallel._ENABLED, "on", True)
    small = [("mallopt", parallel.M_MMAP_THRESHOLD, parallel.SMALL_PAIR_MMAP_BYTES),
             ("mallopt", parallel.M_TRIM_THRESHOLD, parallel.SMALL_PAIR_TRIM_BYTES)]
    parallel.malloc_policy(parallel.LARGE_PAIR_ROWS - 1)
    assert calls[2:] == small
    del calls[:]
    parallel.small_pair_malloc(parallel.SMALL_PAIR_MAX_INPUT_BYTES + 1)
    parallel.small_pair_malloc(None)
    assert calls == []
    parallel.small_pair_malloc(parallel.SMALL_PAIR_MAX_INPUT_BYTES)
    assert calls == small
    for name in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"):
        del calls[:]
        monkeypatch.setenv(name, "131072")
        parallel.malloc_policy(10 * parallel.LARGE_PAIR_ROWS)
        parallel.malloc_policy(parallel.LARGE_PAIR_ROWS - 1)
        parallel.release_freed_memory()
        assert calls == [("malloc_trim", 0)]
        monkeypatch.delenv(name)


def test_a_restamp_process_takes_the_small_pair_malloc_policy(monkeypatch):
    """``tapost restamp`` forks nothing but its process is tapost's own (``own_malloc``): the small-pair
    policy is set there as in analyze's (a Python API caller's process: left alone)."""
    calls = []

    class FakeLibc:
        def mallopt(self, param, value):
            calls.append((param, value))

    monkeypatch.setattr(parallel, "_libc", lambda: FakeLibc())
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.setitem(parallel._ENABLED, "on", False)
    monkeypatch.setitem(parallel._ENABLED, "malloc", False)
    parallel.small_pair_malloc(1000)
    assert calls == []
    parallel.own_malloc()
    assert parallel._ENABLED == {"on": False, "malloc": True}  # (forking still not allowed)
    parallel.small_pair_malloc(1000)
    assert calls == [(parallel.M_MMAP_THRESHOLD, parallel.SMALL_PAIR_MMAP_BYTES),
                     (parallel.M_TRIM_THRESHOLD, parallel.SMALL_PAIR_TRIM_BYTES)]


def test_malloc_settings_are_accepted_by_glibc():
    """glibc takes both settings (mallopt returns 1; 32 MB is its largest mmap threshold on 64-bit)."""
    from parsers.base import glibc

    libc = glibc()
    if libc is None:
        pytest.skip("not glibc")
    import ctypes

    mallopt = libc.mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    assert ctypes.sizeof(ctypes.c_void_p) != 8 or mallopt(parallel.M_MMAP_THRESHOLD,
                                                           parallel.SMALL_PAIR_MMAP_BYTES) == 1
    assert mallopt(parallel.M_TRIM_THRESHOLD, parallel.SMALL_PAIR_TRIM_BYTES) == 1
    mallopt(parallel.M_TRIM_THRESHOLD, 128 * 1024)  # (back near glibc's default for this test process)


@posix_fork
def test_the_comparison_methods_beside_the_headline_give_the_same_estimates(forking):
    """`estimate(..., beside=parallel.submit)` (the CLI: the seeds' and cross-correlation methods in a forked
    child while the tapost estimate is computed) equals the in-process run, every method's figure."""
    from logtools import sim
    from logtools.latency import estimate

    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=40.0, seed=5, latency_s=0.031))
    here = estimate(pair.master, pair.slave)
    forked = estimate(pair.master, pair.slave, beside=parallel.submit)
    assert set(forked.methods) == set(here.methods) and len(here.methods) > 1
    for name, me in here.methods.items():
        assert (forked.methods[name].latency_s == me.latency_s
                or (np.isnan(me.latency_s) and np.isnan(forked.methods[name].latency_s))), name
        assert forked.methods[name].note == me.note
    assert forked.latency_s == here.latency_s and forked.sigma_s == here.sigma_s


@posix_fork
def test_a_failed_headline_ends_the_comparison_child(forking, monkeypatch):
    """The headline fails (its error is the run's): the child running the comparison is ended and reaped,
    not left behind."""
    from logtools import sim
    from logtools.errors import AnalysisError
    from logtools.latency import estimate, estimator

    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=20.0, seed=6))
    started = []

    def beside(fn, *args):
        job = parallel.submit(_sleep_then, 30.0)
        started.append(job)
        return job

    def fail(ctx, prog, overlap=False, threads_done=None, co=None):
        threads_done()  # (where the child is forked: no thread of the headline's left)
        raise AnalysisError("the headline's own failure")

    monkeypatch.setattr(estimator, "tapost", fail)
    with pytest.raises(AnalysisError, match="headline's own"):
        estimate(pair.master, pair.slave, beside=beside)
    (job,) = started
    assert job._pid is not None
    with pytest.raises(ChildProcessError):  # reaped already: no such child any more
        os.waitpid(job._pid, os.WNOHANG)


def test_the_velocity_pair_in_a_thread_gives_the_same_estimate_and_the_child_forks_after_it(forking):
    """``estimate(..., overlap=True)``: the velocity pair made in a thread beside the rate fit gives the
    estimate of the plain run to the bit; the comparison methods' child is forked once that thread has ended
    (a fork beside a running thread could copy a lock it holds), and gives the same comparison."""
    import threading

    from logtools import sim
    from logtools.latency import estimate, estimator

    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=60.0, seed=6))
    assert pair.master.has_vel and pair.slave.has_vel
    alive_at_fork, made = [], []
    real = estimator._velocity_pair

    def beside(fn, *args):
        alive_at_fork.append(sorted(t.name for t in threading.enumerate()))
        return parallel.submit(fn, *args)

    def counted(ctx):
        made.append(threading.current_thread().name)
        return real(ctx)

    estimator._velocity_pair = counted
    try:
        plain = estimate(pair.master, pair.slave)
        beside_run = estimate(pair.master, pair.slave, beside=beside, overlap=True)
    finally:
        estimator._velocity_pair = real
    assert made == ["MainThread", "tapost-latency"]
    assert alive_at_fork and all("tapost-latency" not in names for names in alive_at_fork)
    for f in dataclasses.fields(plain):  # (every array whole: a repr elides long ones)
        a, b = getattr(plain, f.name), getattr(beside_run, f.name)
        assert (np.array_equal(a, b) if isinstance(a, np.ndarray) else repr(a) == repr(b)), f.name


def _sleep_then(s):
    import time

    time.sleep(s)
    return s


@posix_fork
def test_a_consumer_boards_uncompensated_run_follows_the_compensated_runs_board_decision_in_its_child(
        forking, monkeypatch):
    """--board-errors auto on a consumer board's pair (a Markov master attitude error, a misaligned
    accelerometer triad): the compensated run takes the board's states, so the uncompensated one must too.
    Its child follows the compensated run's decision (the filter with them on its own preparation), rather
    than the run being redone here after the children; the answer is the one computed without forking."""
    from logtools import sim
    from pipelines import analyze

    p = sim.simulate(sim.scenario_config(
        "vehicle", duration_s=120.0, seed=3, mount_rpy_deg=(2.0, -3.0, 40.0), latency_s=0.05,
        slave_accel_misalign_rpy_deg=(0.9, -0.7, 0.4), master_att_markov_deg=0.12, master_att_markov_tau_s=50.0))
    opts = analyze.AnalyzeOptions()
    parallel.enable(False)
    ref = analyze.compute(p.master, p.slave, opts)
    parallel.enable(True)
    here = []  # the alignment runs computed in this process (a forked child's calls are its own)
    alignment = analyze._alignment

    def spy(master, slave, run, run_opts, *args, **kwargs):
        here.append((run, run_opts.board_errors))
        return alignment(master, slave, run, run_opts, *args, **kwargs)

    monkeypatch.setattr(analyze, "_alignment", spy)
    submitted = []
    submit = parallel.submit
    monkeypatch.setattr(parallel, "submit", lambda fn, *a, **k: submitted.append(a[2:3]) or submit(fn, *a, **k))
    an = analyze.compute(p.master, p.slave, opts)
    assert ref.alignment["compensated"].has_board_states and an.alignment["compensated"].has_board_states
    assert an.alignment["uncompensated"].has_board_states
    assert here == [("compensated", "auto")]  # (the uncompensated run: in its child)
    assert submitted.count(("uncompensated",)) == 1  # (one child, which followed the decision)
    for run in ("uncompensated", "compensated"):
        a, b = an.alignment[run], ref.alignment[run]
        assert a.mounting_rpy_deg == pytest.approx(b.mounting_rpy_deg, rel=1e-12, abs=1e-12)
        assert a.mounting_sigma_deg == pytest.approx(b.mounting_sigma_deg, rel=1e-9)
        assert a.notes == b.notes


@posix_fork
def test_where_the_boards_filter_does_not_follow_the_uncompensated_run_stays_without_the_states(
        forking, monkeypatch):
    """The compensated run decided for the board's states (the uncompensated one took them in its child),
    but its result came without them (that filter did not follow the data; simulated here): the
    uncompensated run is the one without them, as without forking."""
    from logtools import sim
    from pipelines import analyze

    p = sim.simulate(sim.scenario_config(
        "vehicle", duration_s=120.0, seed=3, mount_rpy_deg=(2.0, -3.0, 40.0), latency_s=0.05,
        slave_accel_misalign_rpy_deg=(0.9, -0.7, 0.4), master_att_markov_deg=0.12, master_att_markov_tau_s=50.0))
    monkeypatch.setattr(analyze, "_has_board_states", lambda res: False)
    opts = analyze.AnalyzeOptions()
    parallel.enable(False)
    ref = analyze.compute(p.master, p.slave, opts)
    parallel.enable(True)
    an = analyze.compute(p.master, p.slave, opts)
    assert not ref.alignment["uncompensated"].has_board_states
    assert not an.alignment["uncompensated"].has_board_states
    a, b = an.alignment["uncompensated"], ref.alignment["uncompensated"]
    assert a.mounting_rpy_deg == pytest.approx(b.mounting_rpy_deg, rel=1e-12, abs=1e-12) and a.notes == b.notes


def _freeze_count() -> int:
    import gc

    return gc.get_freeze_count()


def test_a_fork_freezes_the_collectors_objects_first(monkeypatch):
    """parallel's forks freeze the garbage collector's objects first (gc.freeze, as Python advises before a fork
    without exec): the child's collections neither scan nor copy the pages of what the parent made."""
    import gc

    monkeypatch.setitem(parallel._ENABLED, "on", True)
    if not parallel.available():
        pytest.skip("no fork here")
    try:
        job = parallel.submit(_freeze_count)
        assert job.result() > 0
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


_ANALYZE_MA = r"""
import importlib.abc
import os
import sys

me = os.getpid()


class Hook(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "numpy.ma.core":
            sys.stderr.write(f"numpy.ma.core imported in the {'analysing process' if os.getpid() == me else 'child'}\n")
        return None


sys.meta_path.insert(0, Hook())
real_fork = os.fork


def fork():
    pid = real_fork()
    if pid:
        sys.stderr.write("forked\n")
    return pid


os.fork = fork
from pipelines import cli

sys.argv = ["tapost", "analyze", *sys.argv[1:]]
cli.script()
"""


def test_analyze_loads_numpy_ma_once_before_its_children_fork(tmp_path):
    """numpy.ma, which the analysing process loads anyway, is loaded there before the parse's and the
    recording's children fork (``cli.preload_numpy_ma``): neither child loads it again."""
    sample = ROOT / "sample_logs"
    p = subprocess.run([sys.executable, "-c", _ANALYZE_MA, str(sample / "master.mcap"), str(sample / "slave.tlog"),
                        "-o", str(tmp_path / "out"), "--no-html"], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "TAPOST_WARMUP": "0"}, cwd=str(tmp_path))
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith(("numpy.ma", "forked"))]
    assert lines and lines[0] == "numpy.ma.core imported in the analysing process", p.stderr
    assert "numpy.ma.core imported in the child" not in lines
    if (os.cpu_count() or 1) > 1:
        assert "forked" in lines  # (the children this is about were there)
    assert (tmp_path / "out" / "recording.rrd").exists()
