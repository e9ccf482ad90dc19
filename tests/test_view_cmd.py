"""``tapost view``: a bad --port is one line and exit 2 before anything starts; a folder's recording that
its report.json does not list (left from another run) is refused, one it lists is opened; on Linux the
viewer ends with tapost even when tapost is killed outright (SIGKILL). No viewer is started but by the
last test (the real one, on 127.0.0.1, stopped)."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_outputs_19 import _listening, _tiny_rrd  # noqa: E402

from pipelines import view_cmd
from pipelines.cli import main

HERE = Path(__file__).parent
ROOT = HERE.parent
SAMPLE = ROOT / "sample_logs"
_REAL_POPEN = subprocess.Popen




def _report(folder: Path, recording: str | None, **fields) -> None:
    """A report.json as write_outputs writes its ``outputs`` (file names in the folder, null: not written)."""
    rep = {"schema": "tapost.report/1", "status": "ok", "skipped": {}, "options": {"recording": True},
           "latency": {"latency_s": 0.01}, "outputs": {"report": "report.json", "html": None, "recording": recording}}
    rep.update(fields)
    (folder / "report.json").write_text(json.dumps(rep))


@pytest.fixture
def launches(monkeypatch):
    """What would start: the viewer (its command) and the web viewer's file server; neither really starts."""
    started = {"viewer": [], "server": []}

    def fake_viewer(cmd, *, on_started=None):
        started["viewer"].append(list(cmd))
        return 0

    class FakeServer:
        server_address = ("127.0.0.1", 1)

        def shutdown(self):
            pass

        def server_close(self):
            pass

    def fake_serve(path, host, port=0):
        started["server"].append(path)
        return FakeServer(), os.path.basename(path)

    def no_process(*a, **k):
        raise AssertionError("no process may be started here")

    monkeypatch.setattr(view_cmd, "_run_viewer", fake_viewer)
    monkeypatch.setattr(view_cmd, "serve_file", fake_serve)
    monkeypatch.setattr(view_cmd, "has_display", lambda environ=None: True)
    monkeypatch.setattr(view_cmd.webbrowser, "open", no_process)
    monkeypatch.setattr(subprocess, "Popen", no_process)
    return started


# ---- --port -----------------------------------------------------------------------------------
@pytest.mark.parametrize("port", ["70000", "-1", "65536", "abc", "8080.5"])
def test_a_bad_port_is_one_line_naming_it_and_exit_2_before_anything_starts(tmp_path, port, launches, capsys):
    _tiny_rrd(tmp_path / "recording.rrd")
    with pytest.raises(SystemExit) as exc:
        main(["view", str(tmp_path), "--web", "--port", port])
    assert exc.value.code == 2
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert len(err) == 1 and cap.out == "", cap
    assert "--port" in err[0] and repr(port) in err[0] and "1..65535" in err[0], err
    assert launches == {"viewer": [], "server": []}


@pytest.mark.parametrize("port", ["1", "8080", "65535"])
def test_a_good_port_goes_to_the_web_viewer(tmp_path, port, launches):
    _tiny_rrd(tmp_path / "recording.rrd")
    assert main(["view", str(tmp_path), "--web", "--port", port]) == 0
    [cmd] = launches["viewer"]
    assert cmd[cmd.index("--web-viewer-port") + 1] == port and cmd[cmd.index("--bind") + 1] == "127.0.0.1"


def test_port_0_or_none_is_a_free_one(tmp_path, launches, monkeypatch):
    assert view_cmd.port_number("0") == 0
    monkeypatch.setattr(view_cmd, "free_port", lambda host: 54321)
    _tiny_rrd(tmp_path / "recording.rrd")
    for extra in ([], ["--port", "0"]):
        assert main(["view", str(tmp_path), "--web", *extra]) == 0
        assert launches["viewer"][-1][launches["viewer"][-1].index("--web-viewer-port") + 1] == "54321"


# ---- the recording a folder's report.json lists ----------------------------------------------------
def test_a_recording_report_json_does_not_list_is_refused_in_one_line(tmp_path, launches, capsys):
    _tiny_rrd(tmp_path / "recording.rrd")
    _report(tmp_path, None, options={"recording": False})
    for web in ([], ["--web"]):
        assert main(["view", str(tmp_path), *web]) == 2
        cap = capsys.readouterr()
        err = cap.err.strip().splitlines()
        assert len(err) == 1 and cap.out == "", cap
        assert str(tmp_path / "recording.rrd") in err[0] and "not this analysis' recording" in err[0]
        assert "report.json" in err[0] and "--no-recording" in err[0], err
    assert launches == {"viewer": [], "server": []}


@pytest.mark.parametrize("fields, says", [
    ({"skipped": {"recording": "ImportError: no rerun"}, "status": "partial"}, "skipped: ImportError: no rerun"),
    ({"status": "failed", "latency": {"failed": "no overlap"}}, "failed analysis"),
    ({"outputs": {"report": "report.json"}}, "lists no recording"),
])
def test_why_the_report_lists_no_recording_is_said(tmp_path, fields, says, launches, capsys):
    _tiny_rrd(tmp_path / "recording.rrd")
    _report(tmp_path, None, **fields)
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err
    assert launches["viewer"] == []


def test_no_recording_and_a_report_that_lists_none_says_why(tmp_path, launches, capsys):
    _report(tmp_path, None, options={"recording": False})
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no recording" in err[0] and "--no-recording" in err[0], err


def test_a_recording_report_json_lists_is_opened(tmp_path, launches):
    rrd = _tiny_rrd(tmp_path / "recording.rrd")
    _report(tmp_path, "recording.rrd")
    assert main(["view", str(tmp_path)]) == 0
    assert main(["view", str(tmp_path), "--web"]) == 0
    assert launches["viewer"][0][-1] == str(rrd)  # native: the file
    assert launches["server"] == [str(rrd)]  # web: the file served


@pytest.mark.parametrize("report", [None, "not json {", '{"schema": "tapost.report/1"}'])
def test_without_a_report_that_says_the_recording_is_opened_as_before(tmp_path, report, launches):
    """No report.json, an unreadable one, one without ``outputs``: the folder's recording as before."""
    rrd = _tiny_rrd(tmp_path / "recording.rrd")
    if report is not None:
        (tmp_path / "report.json").write_text(report)
    assert main(["view", str(tmp_path)]) == 0
    assert launches["viewer"][-1][-1] == str(rrd)


def test_a_recording_named_directly_is_opened_as_named(tmp_path, launches):
    rrd = _tiny_rrd(tmp_path / "recording.rrd")
    _report(tmp_path, None, options={"recording": False})
    assert main(["view", str(rrd)]) == 0
    assert launches["viewer"][-1][-1] == str(rrd)


@pytest.mark.skipif(not (SAMPLE / "master.mcap").exists(), reason="needs sample_logs")
def test_a_folder_reused_with_no_recording_refuses_the_old_recording(tmp_path, launches, capsys):
    """The fuzz run's case, with the real report.json: analyze, then analyze into the same folder with
    --no-recording --no-html; view refuses the first run's recording; analyzing again with one opens it."""
    out = tmp_path / "stale"
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}

    def analyze(*extra):  # (the real Popen: the fixture's starts nothing)
        run = _REAL_POPEN([sys.executable, "-m", "pipelines.cli", "analyze", str(SAMPLE / "master.mcap"),
                           str(SAMPLE / "slave.tlog"), "-o", str(out), *extra], env=env,
                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        assert run.wait(300) == 0

    analyze("--no-html")
    analyze("--no-recording", "--no-html")
    assert (out / "recording.rrd").exists()
    assert main(["view", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not this analysis' recording" in err[0] and "--no-recording" in err[0], err
    assert launches["viewer"] == []
    analyze("--no-html")
    assert main(["view", str(out)]) == 0
    assert launches["viewer"][-1][-1] == str(out / "recording.rrd")


# ---- the viewer dies with tapost -----------------------------------------------------------------
def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[1]) == pid:
                out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2] not in "ZX"  # (a zombie: ended, not reaped by its new parent)


def test_the_viewer_starts_as_rerun_s_binary_told_to_end_with_its_parent():
    if not sys.platform.startswith("linux"):
        assert view_cmd._die_with_parent() is None
        return
    assert callable(view_cmd._die_with_parent())
    exe = view_cmd.rerun_cli()[0]
    if view_cmd._rerun_binary() is not None:  # (rerun_cli installed): the binary, not a script wrapping it
        with open(exe, "rb") as fh:
            assert fh.read(4) == b"\x7fELF", exe


@pytest.mark.skipif(not sys.platform.startswith("linux") or not Path("/proc/net/tcp").exists(),
                    reason="PR_SET_PDEATHSIG and /proc are Linux's")
def test_the_web_viewer_stops_listening_when_tapost_is_killed(tmp_path):
    _tiny_rrd(tmp_path / "recording.rrd")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "pipelines.cli", "view", str(tmp_path), "--web"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    viewers: list[int] = []
    try:
        line = proc.stdout.readline()
        m = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
        assert m, line
        web = int(m[1])
        deadline = time.time() + 30
        while not _listening(web) and time.time() < deadline:
            time.sleep(0.2)
        assert _listening(web)
        viewers = _children(proc.pid)
        assert viewers
        proc.kill()  # SIGKILL: no handler of tapost's runs
        proc.wait(10)
        deadline = time.time() + 10
        while (_listening(web) or any(_alive(p) for p in viewers)) and time.time() < deadline:
            time.sleep(0.1)
        assert not _listening(web) and not any(_alive(p) for p in viewers)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        for pid in viewers:  # (should it have outlived us: its process group, started by this test)
            if _alive(pid):
                try:
                    os.killpg(pid, signal.SIGKILL)
                except OSError:
                    pass
