"""A newcomer's first hour: warnings vs notes, the same stream refused, ``--no-html``, the summary's words.

Orchestration tests run with the stand-in numerics of test_analyze_cli.py (fast); the real-data ones skip
when ../shared/realdata is absent.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

import pandas as pd
import pytest

from pipelines import report as rp
from pipelines.analyze import summary_lines
from pipelines.cli import main

sys.path.insert(0, str(Path(__file__).parent))
from test_analyze_cli import fake_numerics, write_fake_pair  # noqa: E402,F401

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_logs"
REAL = ROOT.parent / "shared" / "realdata"
PLANE = REAL / "arduplane_box_pilot.BIN"


def _report(**over) -> dict:
    """A small report dict as build_report makes it (sections only), for findings()."""
    rep = {
        "status": "ok",
        "master": {"path": "m.BIN", "format": "dataflash", "clock": "epoch", "duration_s": 90.0, "warnings": [
            "truncated DataFlash log: last 41 byte(s) hold an incomplete record",
            "no selector given: picked imu=IMU,nav=XKF1 (other units: imu=IMU2,nav=XKF6)",
            "gyro (IMU): 1 gap(s) in stamps, longest 1.240 s",
            "accel (IMU): 1 gap(s) in stamps, longest 1.240 s",
            "quat (XKQ1): 1 gap(s) in stamps, longest 1.240 s"]},
        "slave": {"path": "s.mcap", "format": "mcap", "clock": "epoch", "duration_s": 90.0, "warnings": [
            "note: selected imu=/imu", "note: selected att=/attitude"]},
        "latency": {"latency_s": 0.01, "sigma_s": 0.001, "drift_ppm": 0.0, "method": "tapost",
                    "window_s": [0.0, 90.0], "methods": {},
                    "quality": {"too_little_motion": False, "periodic": False,
                                "warnings": ["slave stamps are whole multiples of 1 ms: the latency's sigma is "
                                             "floored at 0.29 ms"]}},
        "alignment": {
            "uncompensated": {"filter": "kf", "match": "vel+att", "mounting_rpy_deg": [0, 0, 0], "mounting_sigma_deg": [0.1, 0.1, 0.1],
                              "converged_s": None, "notes": [
                                  "residuals 9.0x larger than the noise model: unmodelled flexure, lever arm "
                                  "or delay? sigmas are optimistic"]},
            "compensated": {"filter": "kf", "match": "vel+att", "mounting_rpy_deg": [0, 0, 0], "mounting_sigma_deg": [0.1, 0.1, 0.1],
                            "converged_s": 2.0,
                            "notes": ["flexure states added (mean NIS/dof 5.0 without them, 1.0 with)"]}},
        "skipped": {},
    }
    rep.update(over)
    return rep


def test_findings_split_warnings_from_notes_and_merge_a_gap_on_all_channels():
    warns, notes = rp.findings(_report())
    wtext = [w["text"] for w in warns]
    ntext = [n["text"] for n in notes]
    # the selector lines are notes, the ms-stamp line is a latency warning
    assert "slave: selected imu=/imu" in ntext and "slave: selected att=/attitude" in ntext
    assert any(t.startswith("master: no selector given: picked imu=IMU") for t in ntext)
    assert {"stage": "latency", "text": _report()["latency"]["quality"]["warnings"][0]} in warns
    assert not any("selected" in t or "picked" in t for t in wtext)
    # one line for the gap on three channels, naming them
    gaps = [t for t in wtext if "gap(s) in stamps" in t]
    assert gaps == ["master: 1 gap(s) in stamps, longest 1.240 s: gyro (IMU), accel (IMU), quat (XKQ1)"]
    assert "master: truncated DataFlash log: last 41 byte(s) hold an incomplete record" in wtext
    # the uncompensated run's trouble is what the delay does (a note); the compensated run's notes are notes
    assert any(t.startswith("uncompensated: residuals 9.0x") for t in ntext)
    assert any(t.startswith("compensated: flexure states added") for t in ntext)
    assert len(warns) == 3 and len(notes) == 5
    assert all(set(w) == {"stage", "text"} for w in warns + notes)
    # ... and the summary says under its mounting that the delay distorts it (not the compensated run)
    lines = summary_lines({**_report(), "warnings": warns, "notes": notes}, {})
    i = next(k for k, ln in enumerate(lines) if ln.startswith("mounting (uncompensated"))
    assert lines[i + 1].strip().startswith("residuals 9.0x its noise model: the delay left in distorts this run")
    assert sum("the delay left in distorts" in ln for ln in lines) == 1


def test_findings_say_too_little_motion_and_not_determined_in_words():
    rep = _report()
    rep["latency"]["quality"].update(too_little_motion=True, motion_snr=3.2, motion_dps=0.4)
    rep["alignment"]["compensated"].update(mounting_rpy_deg=[None, None, None], converged_s=None,
                                           notes=["mounting not determined: the master has no attitude"])
    warns, _ = rp.findings(rep)
    text = " | ".join(w["text"] for w in warns)
    assert "too little motion for a reliable latency (signal/noise 3.2, motion 0.4 deg/s)" in text
    assert "compensated: mounting not determined: the master has no attitude" in text
    assert "compensated: the mounting was not determined" in text
    lines = summary_lines({**rep, "warnings": warns, "notes": []}, {})
    assert any("too little motion" in ln for ln in lines)
    assert any(ln.startswith("mounting (compensated, kf/vel+att): not determined") for ln in lines)
    assert any(ln.startswith(f"status ok: {len(warns)} warning(s)") for ln in lines)


def test_noise_that_drowns_ample_motion_is_not_called_too_little_motion():
    """Heavy vibration: the vehicle turns at 6 deg/s but the rates' noise is larger still; the words name
    the noise, not the motion."""
    rep = _report()
    rep["latency"]["quality"].update(too_little_motion=True, motion_snr=3.2, motion_dps=6.4,
                                     low_motion_cause="noise")
    text = " | ".join(w["text"] for w in rp.findings(rep)[0])
    assert "the sensors' noise is large against the motion (signal/noise 3.2, motion 6.4 deg/s" in text
    assert "too little motion" not in text
    lines = summary_lines({**rep, "warnings": [], "notes": []}, {})
    assert any("noise large against the motion" in ln for ln in lines)


def test_summary_counts_warnings_not_notes_and_prints_the_status(tmp_path, fake_numerics, capsys):
    m, s = write_fake_pair(tmp_path)
    out = tmp_path / "out"
    assert main(["analyze", m, s, "-o", str(out), "--max-lag", "0.5", "--no-recording"]) == 0
    text = capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    assert rep["status"] == "ok"
    # a clean pair: nothing to warn about, and the summary says so with the status
    assert rep["warnings"] == []
    assert f"status ok: 0 warning(s), {len(rep['notes'])} note(s)" in text
    assert "  warning [" not in text
    # a damaged slave (rows written twice) gives a warning, counted and printed
    lines = Path(s).read_text().splitlines()
    Path(s).write_text("\n".join(lines[:1000] + lines[990:]) + "\n")
    out2 = tmp_path / "out2"
    assert main(["analyze", m, s, "-o", str(out2), "--max-lag", "0.5", "--no-recording"]) == 0
    text = capsys.readouterr().out
    rep = json.loads((out2 / "report.json").read_text())
    assert any("duplicate" in w["text"] for w in rep["warnings"])
    assert f"status {rep['status']}: {len(rep['warnings'])} warning(s)" in text
    assert all(f"  warning [{w['stage']}] {w['text']}" in text for w in rep["warnings"])


def test_no_html_writes_report_json_and_no_html(tmp_path, fake_numerics, capsys):
    m, s = write_fake_pair(tmp_path)
    out = tmp_path / "out"
    assert main(["analyze", m, s, "-o", str(out), "--max-lag", "0.5", "--no-html", "--no-recording"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["report.json"]
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    assert rep["outputs"] == {"report": "report.json", "html": None, "recording": None}
    assert rep["options"]["html"] is False
    assert "report.html" not in capsys.readouterr().out
    # the same from a config file, and in a batch manifest's per-pair options
    cfg = tmp_path / "c.toml"
    cfg.write_text("no_html = true\nno_recording = true\nmax_lag = 0.5\n")
    out2 = tmp_path / "out2"
    assert main(["analyze", m, s, "-o", str(out2), "--config", str(cfg)]) == 0
    assert sorted(p.name for p in out2.iterdir()) == ["report.json"]


def test_the_same_stream_on_both_sides_is_refused_in_one_line(tmp_path, capsys):
    log = str(SAMPLE / "master.mcap")
    assert main(["analyze", log, log, "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "master.mcap" in err and "same stream" in err
    assert not (tmp_path / "o").exists()
    # the same selector given on both sides, and a selector that resolves to the default's stream
    assert main(["analyze", f"{log}::imu=/imu", f"{log}::imu=/imu", "-o", str(tmp_path / "o")]) == 2
    assert "same stream" in capsys.readouterr().err
    from pipelines import api

    with pytest.raises(api.InputError, match="same stream"):
        api.analyze(log, api.load(log))


@pytest.mark.skipif(not PLANE.exists(), reason="real logs absent (../shared/realdata)")
def test_one_file_two_selectors_stays_allowed_and_the_default_is_its_own_stream(tmp_path, fake_numerics, capsys):
    p = str(PLANE)
    out = tmp_path / "o"
    assert main(["analyze", f"{p}::imu=IMU", f"{p}::imu=IMU2", "-o", str(out), "--no-html",
                 "--no-recording"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["master"]["selector"] != rep["slave"]["selector"]
    # one line for the 1.24 s gap on every channel of a side (it was one line per channel)
    gap_lines = [w for w in rep["warnings"] if "gap(s) in stamps" in w["text"]]
    assert len(gap_lines) == 2 and all(w["stage"] == "parse" for w in gap_lines)
    capsys.readouterr()
    # the default unit and its selector written out in full are the same stream
    from parsers import load

    default = load(p).meta.selector
    assert default.startswith("imu=IMU,")
    assert main(["analyze", p, f"{p}::{default}", "-o", str(tmp_path / "o3")]) == 2
    assert "same stream" in capsys.readouterr().err


def test_one_imu_read_twice_or_a_plain_copy_is_the_same_stream(tmp_path, capsys):
    """The same angular rates on both sides are refused in one line: one file's IMU with two navigation
    sources or on two clocks (the 'latency' would be 0, or the offset between the clocks), a plain copy of a
    file (same rates at the same stamps). A restamped copy (its stamps shifted) stays a pair."""
    import shutil

    from pipelines.analyze import same_imu, same_stream
    from parsers import load
    from parsers.restamp import ClockShift
    from pipelines import export

    log = str(SAMPLE / "slave.tlog")
    copy = tmp_path / "copy.tlog"
    shutil.copyfile(log, copy)
    for m, s in ((log, f"{log}::time=receive"), (log, str(copy))):
        a, b = load(m), load(s)
        assert a.meta.selector != b.meta.selector or m != s
        assert same_stream(a, b), (m, s)
    assert main(["analyze", log, str(copy), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "same stream" in err
    slave = load(log)
    (e,) = export.write_slave(("native",), str(tmp_path / "x"), slave, ClockShift(0.025, 0.0, slave.meta.t0_ns))
    assert not same_stream(slave, load(e.path))  # (the export's round trip: a pair)
    assert not same_stream(load(str(SAMPLE / "master.mcap")), slave)
    # one IMU with two attitude sources: a pair, said in a warning (the latency is 0 by construction)
    other_att = load(f"{log}::imu=HIGHRES_IMU,att=ATTITUDE")
    assert not same_stream(slave, other_att)
    assert "the same IMU stream (HIGHRES_IMU)" in same_imu(slave, other_att)
    assert same_imu(load(str(SAMPLE / "master.mcap")), slave) is None


def _readme_python_block() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    start = text.index("<!-- api-example -->")
    block = text[start:].split("```python\n", 1)[1].split("```", 1)[0]
    return block


def test_the_readme_api_example_runs_on_the_sample_logs(tmp_path, monkeypatch):
    block = _readme_python_block()
    assert "api.analyze(" in block and ".frames()" in block and ".write(" in block
    monkeypatch.chdir(ROOT)
    out = tmp_path / "api_out"
    ns: dict = {}
    exec(compile(block.replace('"api_out"', repr(str(out))), "README.md", "exec"), ns)  # noqa: S102
    an = ns["an"]
    assert an.ok and an.report["status"] in ("ok", "partial")
    # the sample pair's truth: 100 ms latency, mounting [0.3, 0.4, -1] deg
    truth = json.loads((SAMPLE / "truth.json").read_text())
    assert an.latency.latency_s == pytest.approx(truth["latency_s"], abs=1e-3)
    rpy = an.alignment["compensated"].mounting_rpy_deg
    assert rpy == pytest.approx(truth["mounting_rpy_deg"], abs=0.01)
    frames = an.frames()
    assert {"rates", "states_compensated", "residuals_compensated", "slave_on_master_clock_imu"} <= set(frames)
    assert len(frames["slave_on_master_clock_imu"]) == len(an.slave_on_master_clock.imu)
    assert (out / "report.json").exists() and (out / "report.html").exists()
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    assert rep["latency"]["latency_s"] == pytest.approx(an.report["latency"]["latency_s"])
    assert not any("selected" in w["text"] for w in rep["warnings"])  # the selector lines are notes
    import tapost

    assert tapost.analyze is ns["api"].analyze and callable(tapost.load)
    assert os.path.basename(rep["master"]["path"]) == "master.mcap"


def test_a_compile_is_announced_once_on_stderr(monkeypatch, capsys):
    numba = pytest.importorskip("numba")
    from pipelines import firstrun

    # a listener an earlier test registered may say it first (on stderr): one line in all, either way
    monkeypatch.setattr(firstrun, "_state", {"installed": False, "said": False})
    from logtools import jit

    monkeypatch.setitem(jit._state, "aot", None)  # (numba's cache, not kernels compiled ahead of time)
    assert firstrun.announce_compiling() is True

    @numba.njit  # not cached: compiles here, in this test
    def _twice(x):
        return 2.0 * x

    assert _twice(1.5) == 3.0
    assert _twice(2) == 4  # a second specialisation: no second line
    lines = capsys.readouterr().err.splitlines()
    assert lines == [lines[0]] and lines[0].startswith("tapost: compiling numerical kernels on first use (once")


def test_a_cold_cache_first_run_says_it_compiles_before_anything_else(tmp_path):
    """``tapost inspect`` of a tlog on an empty numba cache (NUMBA_CACHE_DIR): stderr, not a terminal, gets
    the compile line first."""
    pytest.importorskip("numba")
    import subprocess
    import time

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "nbcache"),
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "pipelines.cli", "inspect", str(SAMPLE / "slave.tlog")],
                       capture_output=True, text=True, env=env, cwd=str(tmp_path), timeout=600)
    took = time.monotonic() - t0
    assert p.returncode == 0, p.stderr
    err = p.stderr.splitlines()
    assert err and err[0].startswith("tapost: compiling numerical kernels on first use"), p.stderr
    assert "HIGHRES_IMU" in p.stdout
    print(f"cold inspect of the sample tlog: {took:.1f} s")


def test_a_fresh_analyze_on_a_cold_cache_says_so_before_its_imports(tmp_path):
    """The line comes from a file-system look before numpy/pandas/numba load (here followed by the
    same-stream refusal, so nothing heavy runs): kernels not compiled, the reference code runs."""
    import subprocess
    import time

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "nbcache"), "XDG_CACHE_HOME": str(tmp_path / "xdg"),
           "TAPOST_KERNELS": "auto", "TAPOST_WARMUP": "0",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    log = str(SAMPLE / "master.mcap")
    t0 = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "pipelines.cli", "analyze", log, log, "-o", str(tmp_path / "o")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=str(tmp_path))
    first = p.stderr.readline()
    t_first = time.monotonic() - t0
    rest = p.stderr.read()
    assert p.wait(timeout=600) == 2
    assert first.startswith("tapost: the numerical kernels are not compiled yet: this run uses the reference code"), \
        first + rest
    assert "python -m pipelines.warmup" in first
    assert len(rest.splitlines()) == 1 and "same stream" in rest
    print(f"kernels line after {t_first:.2f} s")


def test_a_first_run_byte_compiles_tapost_in_the_background_only_where_it_is_not(tmp_path, monkeypatch):
    """An editable install leaves tapost's modules without byte code; the first run (reference code) starts one
    low-priority ``compileall`` of its packages, and no other run does: not where the byte code is there, not
    where Python is told to write none."""
    import importlib.util
    import subprocess

    from pipelines import firstrun

    started: list = []
    monkeypatch.setattr(subprocess, "Popen", lambda cmd, **kw: started.append((cmd, kw)))
    monkeypatch.setattr(sys, "dont_write_bytecode", False)
    monkeypatch.delenv("PYTHONDONTWRITEBYTECODE", raising=False)
    pyc = tmp_path / "kf.cpython.pyc"
    monkeypatch.setattr(importlib.util, "cache_from_source", lambda path: str(pyc))
    assert firstrun.compile_bytecode_in_background()  # no byte code yet
    (cmd, kw), = started
    assert cmd[1:4] == ["-m", "compileall", "-q"] and [Path(c).name for c in cmd[4:]] == list(firstrun.PACKAGES)
    assert all(Path(c).is_dir() for c in cmd[4:]) and kw["start_new_session"]
    pyc.write_bytes(b"")
    assert not firstrun.compile_bytecode_in_background()  # compiled at install (or by an earlier run)
    pyc.unlink()
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    assert not firstrun.compile_bytecode_in_background()
    assert len(started) == 1


def test_batch_no_html_skips_every_pairs_report_html_and_links_report_json(tmp_path, fake_numerics):
    from test_batch import make_campaign

    camp = make_campaign(tmp_path, n_good=2, duration_s=20.0)
    out = tmp_path / "out"
    assert main(["batch", str(camp), "-o", str(out), "--no-html"]) == 0
    reports = sorted(out.glob("*/report.json"))
    assert len(reports) == 2
    assert not list(out.glob("*/report.html"))
    for r in reports:
        assert json.loads(r.read_text())["options"]["html"] is False
    summary = pd.read_csv(out / "summary.csv")
    ok = summary[summary.status != "failed"]
    assert len(ok) == 2 and all(str(x).endswith("report.json") for x in ok.report)
    assert (out / "index.html").exists()


@pytest.mark.parametrize("after_s", [0.15, 0.4])
def test_ctrl_c_while_the_command_loads_is_one_line(after_s):
    """Ctrl-C during the imports of a fresh `tapost analyze` printed 30-58 lines of KeyboardInterrupt
    traceback; it is the same one line as later in the run."""
    import signal
    import subprocess
    import time

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for _ in range(5):
        with tempfile.TemporaryDirectory() as out:
            p = subprocess.Popen([sys.executable, "-m", "pipelines.cli", "analyze",
                                  f"{root}/sample_logs/master.mcap", f"{root}/sample_logs/slave.tlog", "-o", out],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                 env={**os.environ, "TAPOST_WARMUP": "0"},
                                 # (a test worker may ignore SIGINT, and an ignored signal stays ignored across
                                 # exec: the child then never sees Ctrl-C; a user's shell leaves it at default)
                                 preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
            time.sleep(after_s)
            p.send_signal(signal.SIGINT)
            err = p.communicate(timeout=60)[1]
        if "init_import_site" not in err and p.returncode != 0:
            break
        # on a loaded machine the signal came while the interpreter itself started (its own fatal error,
        # before any of tapost runs), or before the child had left the test worker's ignored SIGINT for the
        # default (exec not reached: the run then completes, rc 0): later, until it lands in the imports
        after_s += 0.1
    assert "Traceback" not in err, err
    assert p.returncode in (130, -signal.SIGINT), (p.returncode, err)


class _Ended(Exception):
    pass


def test_the_command_runs_its_exit_handlers_then_ends_without_the_interpreters_teardown(monkeypatch, capsys):
    """cli.script (the `tapost` console script): main's exit code, stdout flushed, the exit handlers run (the
    background compile's start is one), then os._exit: the interpreter's teardown of numba, scipy and pandas
    (a third of a second) is skipped. With another thread still running it exits as usual instead."""
    import atexit
    import threading

    from pipelines import cli

    order = []
    monkeypatch.setattr(cli, "main", lambda: print("the summary", end="") or 3)
    monkeypatch.setattr(atexit, "_run_exitfuncs", lambda: order.append("exit handlers"))

    def ended(code):
        order.append(("os._exit", code))
        raise _Ended

    monkeypatch.setattr(os, "_exit", ended)
    # (this test's process may run threads of its own, a pytest-xdist worker's: the threads script sees are set)
    monkeypatch.setattr(threading, "enumerate", lambda: [threading.current_thread()])
    with pytest.raises(_Ended):
        cli.script()
    assert order == ["exit handlers", ("os._exit", 3)] and capsys.readouterr().out == "the summary"
    order.clear()
    gate = threading.Event()
    worker = threading.Thread(target=gate.wait)
    worker.start()
    monkeypatch.setattr(threading, "enumerate", lambda: [threading.current_thread(), worker])
    try:
        with pytest.raises(SystemExit) as exc:
            cli.script()
    finally:
        gate.set()
        worker.join()
    assert exc.value.code == 3 and order == []


def test_the_summary_marks_the_methods_that_assume_aligned_axes():
    rep = _report()
    rep["latency"]["methods"] = {
        "tapost": {"latency_s": 0.08, "sigma_s": 5e-6},
        "s000-rate-integral": {"latency_s": 0.416, "sigma_s": 5e-4, "note": "eqs 1-5, axes assumed aligned; t_s=2 ms"},
        "xcorr-norm": {"latency_s": 0.08, "sigma_s": 1e-3, "note": "peak correlation 1.000"}}
    line = next(ln for ln in summary_lines({**rep, "warnings": [], "notes": []}, {}) if "other methods" in ln)
    assert "s000-rate-integral +416.000 ms (axes assumed aligned)" in line and "xcorr-norm +80.000 ms" in line
    assert line.count("axes assumed aligned") == 1


def test_a_triad_at_the_gimbal_lock_says_so_in_the_summary_and_the_page():
    """An IMU-to-IMU triad whose pitch lies within its uncertainty of 90 deg is given as the gimbal lock's
    canonical triple (roll 0) with sigmas of thousands of arcmin: printed bare, it read as a failed fit.
    The summary line and report.html now say why, and where the rotation itself is."""
    from pipelines.analyze import _imu_to_imu_lines
    from pipelines.html import _imu_to_imu_html

    ii = {"gyro_rpy_deg": [10.0, 89.0, 30.0], "gyro_sigma_deg": [0.01, 0.0003, 0.01],
          "accel_rpy_deg": [0.0, 90.0, 20.0], "accel_sigma_deg": [44.6, 59.2, 45.8], "accel_gimbal_lock": True}
    rep = {"alignment": {"imu_to_imu": ii}}
    lines = _imu_to_imu_lines(rep["alignment"])
    assert len(lines) == 2 and "gimbal lock" not in lines[0]
    assert "gimbal lock" in lines[1] and "accel_quat_wxyz" in lines[1]
    page = _imu_to_imu_html(rep)
    assert page.count("gimbal lock") == 1 and "accel_quat_wxyz" in page
