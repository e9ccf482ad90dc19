"""``tapost batch``: discovery rules, parallel runs (processes and Dask) give identical summaries,
a corrupt pair is a failed row, a second run does no work, SIGINT leaves no half-written report.

The orchestration tests use the stand-in numerics of test_analyze_cli (forked worker processes and
an in-process Dask cluster inherit them); ``test_real_campaign`` runs the real numerics in spawned
processes and on a multi-process Dask LocalCluster when logtools.sim/latency/compensate exist.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipelines import batch
from pipelines import report as rp
from pipelines.cli import main

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
from test_analyze_cli import fake_numerics, install_fake_numerics, write_fake_pair  # noqa: E402,F401

COMPARE = ["pair", "status", "exit_code", "latency_s", "sigma_s", "drift_ppm", "mount_comp_roll_deg",
           "mount_comp_pitch_deg", "mount_comp_yaw_deg", "mount_unc_yaw_deg"]


def make_campaign(root: Path, n_good: int = 5, duration_s: float = 20.0) -> Path:
    """n_good pairs (subfolders, plus one flat pair) and one corrupt pair."""
    camp = root / "campaign"
    camp.mkdir()
    for i in range(n_good - 1):
        d = camp / f"run{i}"
        d.mkdir()
        write_fake_pair(d, duration_s=duration_s + 2 * i, name=("master.csv", "slave.csv"))
    write_fake_pair(camp, duration_s=duration_s, name=("flat.master.csv", "flat.slave.csv"))
    bad = camp / "broken"
    bad.mkdir()
    (bad / "master.csv").write_text("time_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n1.0,abc,0,0\n2.x,,\n")
    (bad / "slave.csv").write_bytes(b"\x89garbage\x00" * 50)
    (camp / "notes.txt").write_text("not a pair")
    return camp


def snapshot(out: Path) -> dict[str, int]:
    return {str(p.relative_to(out)): p.stat().st_mtime_ns for p in out.rglob("*")
            if p.is_file() and p.parent != out}


def test_discovery_rules(tmp_path):
    camp = tmp_path / "c"
    (camp / "a").mkdir(parents=True)
    (camp / "a" / "master.bin").write_text("x")
    (camp / "a" / "slave.tlog").write_text("x")
    (camp / "lonely").mkdir()
    (camp / "lonely" / "master.csv").write_text("x")
    (camp / "other").mkdir()  # unrelated folder: ignored
    (camp / "z.master.csv").write_text("x")
    (camp / "z.slave.mcap").write_text("x")
    jobs = {j.name: j for j in batch.discover(str(camp), str(tmp_path / "o"))}
    assert set(jobs) == {"a", "lonely", "z"}
    assert jobs["a"].master.endswith("a/master.bin") and jobs["a"].slave.endswith("a/slave.tlog")
    assert "found 1 master" in jobs["lonely"].problem and "0 slave" in jobs["lonely"].problem
    assert jobs["z"].slave.endswith("z.slave.mcap") and not jobs["z"].problem
    man = tmp_path / "m.csv"
    man.write_text("master,slave,options,name\nc/a/master.bin::imu=IMU2,c/a/slave.tlog,--max-lag auto,first\n"
                   "/abs/m.csv,/abs/s.csv,,\n")
    mj = batch.discover(str(man), str(tmp_path / "o"))
    assert mj[0].name == "first" and mj[0].master == str(camp / "a" / "master.bin") + "::imu=IMU2"
    assert mj[0].options == ("--max-lag", "auto") and mj[1].name == "pair002"
    with pytest.raises(Exception, match="no pairs found"):
        batch.discover(str(camp / "other"), str(tmp_path / "o"))
    # a folder that is itself one pair (the shipped sample_logs/): one job named after it
    (root := tmp_path / "flight7").mkdir()
    (root / "master.mcap").write_text("x")
    (root / "slave.tlog").write_text("x")
    (root / "truth.json").write_text("{}")
    (rj,) = batch.discover(str(root), str(root / "out"))
    assert rj.name == "flight7" and rj.master.endswith("master.mcap") and not rj.problem


def test_manifest_options_reach_the_analysis(tmp_path):
    """Every analyze option a manifest row may carry reaches AnalyzeOptions (the batch kept its own copy of
    the option names, and the lever-arm and flexure options did not reach it)."""
    from pipelines import analyze

    man = tmp_path / "m.csv"
    man.write_text('master,slave,options\nm.csv,s.csv,"--lever-arm -0.5,-0.2,1 --flexure off --filter hinf"\n')
    job = batch.discover(str(man), str(tmp_path / "o"))[0]
    ns = batch._parse_options(job.options)
    opts, _ = analyze.options_from(analyze.cli_values(ns))
    assert (opts.lever_arm, opts.flexure, opts.filter) == ("-0.5,-0.2,1", "off", "hinf")
    assert set(analyze.CLI_KEYS) <= set(vars(ns))


def test_a_manifest_rows_config_is_taken_from_the_manifests_folder(tmp_path, monkeypatch):
    """--config in a manifest row is a path relative to the manifest, as its master and slave are (it was
    taken from where batch ran: 'cannot read config')."""
    from pipelines import analyze

    camp = tmp_path / "campaign"
    camp.mkdir()
    (camp / "c.toml").write_text("max_lag = 0.25\n")
    man = camp / "m.csv"
    man.write_text('master,slave,options\nm.csv,s.csv,--config c.toml\nm.csv,s.csv,--config=c.toml\n'
                   f'm.csv,s.csv,--config {tmp_path / "abs.toml"}\n')
    (tmp_path / "abs.toml").write_text("max_lag = 0.5\n")
    monkeypatch.chdir(tmp_path)
    jobs = batch.discover(str(man), str(tmp_path / "o"))
    got = []
    for job in jobs:
        ns = batch._parse_options(job.options)
        opts, _ = analyze.options_from(analyze.cli_values(ns), analyze.read_config(ns.config))
        got.append(opts.max_lag_s)
    assert got == [0.25, 0.25, 0.5]


def test_manifest_row_with_an_unquoted_comma_is_a_failed_row_not_an_internal_error(tmp_path):
    """A selector holding commas left unquoted gives its row more fields than the header: that row fails
    with a reason saying to quote it (csv put the extra fields in a list, and the batch stopped with an
    AttributeError); the other rows are read as they are."""
    man = tmp_path / "m.csv"
    man.write_text("master,slave,options,name\n"
                   "a.BIN::imu=IMU,nav=XKF1,a.BIN::imu=IMU2,,first\n"
                   '"a.BIN::imu=IMU,nav=XKF1",a.BIN::imu=IMU2,--no-html,second\n')
    bad, good = batch.discover(str(man), str(tmp_path / "o"))
    assert bad.problem.startswith("manifest row 1 has 5 fields for the header's 4 columns: quote a field")
    assert bad.name == "pair001"
    assert not good.problem and good.name == "second" and good.options == ("--no-html",)
    assert good.master.endswith("a.BIN::imu=IMU,nav=XKF1")
    # a binary file given as the campaign (a log instead of its folder): one line saying what a campaign is
    binary = tmp_path / "master.mcap"
    binary.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)))
    with pytest.raises(batch.InputError, match="not a manifest CSV \\(not UTF-8 text\\): a campaign is a folder"):
        batch.discover(str(binary), str(tmp_path / "o"))


def test_an_output_folder_that_cannot_be_made_is_one_line_or_a_failed_row(tmp_path, fake_numerics, capsys):
    """-o naming a file: one line and exit 2 (it was an internal error: FileExistsError). A pair whose own
    folder cannot be made (a file in its place): that pair is a failed row saying so, the campaign's summary
    is written."""
    camp = tmp_path / "camp"
    (camp / "p1").mkdir(parents=True)
    m, s = write_fake_pair(camp / "p1", duration_s=20)
    os.replace(m, camp / "p1" / ("master" + Path(m).suffix))
    os.replace(s, camp / "p1" / ("slave" + Path(s).suffix))
    blocked = tmp_path / "file"
    blocked.write_text("x")
    assert main(["batch", str(camp), "-o", str(blocked)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"tapost: {blocked}: cannot create the output folder: File exists"
    out = tmp_path / "out"
    out.mkdir()
    (out / "p1").write_text("in the pair's way")
    assert main(["batch", str(camp), "-o", str(out), "--no-html"]) == 0
    row = pd.read_csv(out / "summary.csv").set_index("pair").loc["p1"]
    assert row.status == "failed" and "cannot create the pair's output folder" in row.reason


def test_a_scheduler_address_that_is_no_address_is_one_line(tmp_path, fake_numerics, capsys):
    """--scheduler bogus (no port) was 'internal error: ValueError: missing port number'."""
    pytest.importorskip("distributed")
    camp = tmp_path / "camp"
    (camp / "p1").mkdir(parents=True)
    m, s = write_fake_pair(camp / "p1", duration_s=20)
    os.replace(m, camp / "p1" / ("master" + Path(m).suffix))
    os.replace(s, camp / "p1" / ("slave" + Path(s).suffix))
    assert main(["batch", str(camp), "-o", str(tmp_path / "o"), "--scheduler", "bogus"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("tapost: bogus: not a Dask scheduler address") and "tcp://HOST:PORT" in err[-1]


def test_campaign_processes_and_dask_agree_and_rerun_does_nothing(tmp_path, fake_numerics, monkeypatch, capsys):
    camp = make_campaign(tmp_path)
    before = {str(p): p.stat().st_mtime_ns for p in camp.rglob("*")}
    monkeypatch.setenv("TAPOST_MP_START", "fork")  # forked workers inherit the stand-in numerics
    out1 = tmp_path / "out_jobs"
    assert main(["batch", str(camp), "-o", str(out1), "--jobs", "2"]) == 0
    s1 = pd.read_csv(out1 / "summary.csv")
    assert len(s1) == 6
    broken = s1.set_index("pair").loc["broken"]
    assert broken.status == "failed" and broken.exit_code == 2 and isinstance(broken.reason, str)
    good = s1[s1.pair != "broken"]
    assert (good.status == "ok").all()
    assert good.latency_s.sub(0.025).abs().max() < 1.5e-3
    assert good.mount_comp_yaw_deg.sub(30.0).abs().max() < 0.05
    for name in good.pair:
        rp.validate(json.loads((out1 / name / "report.json").read_text()))
        assert (out1 / name / "done.json").exists()
    pd.testing.assert_frame_equal(pd.read_parquet(out1 / "summary.parquet")[COMPARE], s1[COMPARE], check_dtype=False)
    index = (out1 / "index.html").read_text()
    assert 'href="run0/report.html"' in index and "1 failed" in index
    # inputs untouched
    assert {str(p): p.stat().st_mtime_ns for p in camp.rglob("*")} == before

    # the same campaign on a Dask cluster (in-process workers share the stand-in numerics)
    from distributed import LocalCluster

    out2 = tmp_path / "out_dask"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cl:
        assert main(["batch", str(camp), "-o", str(out2), "--scheduler", cl.scheduler_address]) == 0
        s2 = pd.read_csv(out2 / "summary.csv")
        pd.testing.assert_frame_equal(s1[COMPARE], s2[COMPARE])
        # a second run does no work: nothing rewritten in the pair folders
        snap = snapshot(out2)
        capsys.readouterr()
        assert main(["batch", str(camp), "-o", str(out2), "--scheduler", cl.scheduler_address, "--jobs", "3"]) == 0
        got = capsys.readouterr()
        assert "0 run now, 6 already done" in got.out
        assert "--jobs 3 is not used with --scheduler" in got.err  # (said, not silently dropped)
        assert snapshot(out2) == snap
    pd.testing.assert_frame_equal(pd.read_csv(out2 / "summary.csv")[COMPARE], s1[COMPARE])

    # a changed input is redone, the rest is not
    os.utime(camp / "run1" / "slave.csv", ns=(time.time_ns(), time.time_ns()))
    assert main(["batch", str(camp), "-o", str(out1), "--jobs", "2"]) == 0
    assert "1 run now, 5 already done" in capsys.readouterr().out


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_sigint_leaves_no_half_written_report_and_rerun_completes(tmp_path):
    camp = make_campaign(tmp_path, n_good=5, duration_s=30.0)
    out = tmp_path / "out"
    code = ("import sys; sys.path.insert(0, %r); from test_analyze_cli import install_fake_numerics; "
            "install_fake_numerics(); from pipelines.cli import main; sys.exit(main(sys.argv[1:]))" % str(HERE))
    argv = [sys.executable, "-c", code, "batch", str(camp), "-o", str(out), "--jobs", "1"]
    # SIGINT back to its default in the child: a runner started in the background by a non-interactive
    # shell (nohup, `cmd &`) ignores SIGINT, its children inherit that, and the batch rightly honours it
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path,
                            preexec_fn=_default_sigint)
    deadline = time.time() + 60
    while time.time() < deadline and len(list(out.glob("*/done.json"))) < 2:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err.decode()
    assert err.decode().strip().splitlines()[-1] == "tapost: interrupted"
    done = sorted(p.parent.name for p in out.glob("*/done.json"))
    assert 2 <= len(done) < 6
    assert not list(out.rglob("*.tmp"))  # no temp file left behind
    for rep in out.glob("*/report.json"):  # whatever exists is complete
        rp.validate(json.loads(rep.read_text()))
    summary = pd.read_csv(out / "summary.csv")
    assert (summary.status == "pending").sum() == 6 - len(done)
    first = {d: (out / d / "done.json").stat().st_mtime_ns for d in done}
    # the next run completes the rest without redoing what was done
    proc2 = subprocess.run(argv, capture_output=True, timeout=120)
    assert proc2.returncode == 0, proc2.stderr.decode()
    assert len(list(out.glob("*/done.json"))) == 6
    assert {d: (out / d / "done.json").stat().st_mtime_ns for d in done} == first
    assert (pd.read_csv(out / "summary.csv").status != "pending").all()


def test_an_interrupt_swallowed_inside_a_pair_still_stops_the_batch(monkeypatch):
    """Ctrl-C landing where Python swallows exceptions (a finaliser: "Exception ignored in ...") let a batch
    run on to exit 0 (a flake of the test above). The latch remembers it: no further pair starts."""
    ran = []

    def pair(job):
        ran.append(job)
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)  # the handler runs here
        except KeyboardInterrupt:
            pass  # swallowed, as in a finaliser
        return {"row": {}, "ran": True}

    monkeypatch.setattr(batch, "run_pair", pair)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a foreground process
    try:
        with pytest.raises(KeyboardInterrupt):
            with batch._SigintLatch() as latch:
                batch._run_local(["a", "b", "c"], 1, lambda j, r: None, latch)
        assert ran == ["a"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, old)


def test_real_campaign(tmp_path):
    """Real numerics, mixed formats, spawned processes vs a multi-process Dask LocalCluster."""
    sim = pytest.importorskip("logtools.sim")
    pytest.importorskip("logtools.latency")
    pytest.importorskip("logtools.compensate")
    from distributed import LocalCluster

    from parsers import registry

    fmts = [f for f in ("csv", "tlog", "mcap", "ulog", "rosbag1") if _writable(f)]
    camp = tmp_path / "camp"
    truth = {}
    for i in range(6):
        d = camp / f"p{i}"
        d.mkdir(parents=True)
        pair = sim.simulate(sim.scenario_config(("aircraft", "vehicle", "ship")[i % 3], duration_s=90.0, seed=i,
                                                latency_s=0.01 * (i + 1)))
        truth[f"p{i}"] = pair.truth.to_dict()["latency_s"]
        fm, fs = fmts[i % len(fmts)], fmts[(i + 1) % len(fmts)]
        registry.write(str(d / f"master{registry.format_by_name(fm).EXTENSIONS[0]}"), pair.master, fm)
        registry.write(str(d / f"slave{registry.format_by_name(fs).EXTENSIONS[0]}"), pair.slave, fs)
    # the sixth pair's slave is damaged beyond use: random bytes under its name
    (broken,) = (camp / "p5").glob("slave*")
    broken.write_bytes(np.random.default_rng(0).bytes(4096))
    out1, out2 = tmp_path / "o1", tmp_path / "o2"
    assert main(["batch", str(camp), "-o", str(out1), "--jobs", "2", ]) == 0
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        assert main(["batch", str(camp), "-o", str(out2), "--scheduler", cl.scheduler_address]) == 0
    s1, s2 = pd.read_csv(out1 / "summary.csv"), pd.read_csv(out2 / "summary.csv")
    pd.testing.assert_frame_equal(s1[COMPARE], s2[COMPARE])
    assert len(s1) == 6
    rows = s1.set_index("pair")
    assert rows.loc["p5", "status"] == "failed" and rows.loc["p5", "exit_code"] == 2
    for name in ("p0", "p1", "p2", "p3", "p4"):
        assert rows.loc[name, "status"] == "ok"
        assert abs(rows.loc[name, "latency_s"] - truth[name]) < 1e-3
    # a second run does no work
    snap = snapshot(out1)
    assert main(["batch", str(camp), "-o", str(out1), "--jobs", "2"]) == 0
    assert snapshot(out1) == snap


def _writable(fmt: str) -> bool:
    from parsers.registry import format_by_name

    try:
        return hasattr(format_by_name(fmt), "write")
    except Exception:
        return False


def _crashing_run_pair(job):
    """A stand-in run_pair whose worker dies on pair p1 (module level: the pool pickles it by name)."""
    if job.name == "p1":
        import faulthandler

        faulthandler.disable()  # (no dump of this deliberate crash in the test's output)
        os.kill(os.getpid(), signal.SIGSEGV)
    time.sleep(0.2)
    return {"row": {"pair": job.name, "status": "ok"}, "ran": True}


@pytest.mark.skipif(sys.platform == "win32", reason="fork start method and SIGSEGV: POSIX")
def test_a_pair_that_kills_its_worker_fails_alone(tmp_path, monkeypatch):
    """A worker process that dies (a crash in a native library on one pair's input: a compiled .db3 walk
    did, before its bounds checks) broke the whole process pool: the pairs in flight beside it failed
    ("BrokenProcessPool"), the ones after it never ran, and the batch ended in an exception. Now the pairs
    in flight run again one at a time: the one that kills its worker again is a failed row that says so,
    every other pair runs."""
    monkeypatch.setenv("TAPOST_MP_START", "fork")
    jobs = [batch.PairJob(f"p{i}", "m", "s", str(tmp_path / f"p{i}")) for i in range(6)]
    monkeypatch.setattr(batch, "run_pair", _crashing_run_pair)
    got = {}
    batch._run_local(jobs, 2, lambda j, r: got.setdefault(j.name, r["row"]))
    assert sorted(got) == [j.name for j in jobs]
    assert got["p1"]["status"] == "failed" and "died" in got["p1"]["reason"]
    assert all(got[n]["status"] == "ok" for n in got if n != "p1")


@pytest.mark.parametrize("address", ["", "127.0.0.1:99999", "tcp://host", "tcp://host:0"])
def test_a_scheduler_address_is_checked_before_any_pair_runs(tmp_path, capsys, address):
    """--scheduler '' ran the campaign here, and a port beyond 65535 waited 20 s for a connection: one line,
    exit 2, at once."""
    from pipelines.batch import scheduler_address

    camp = tmp_path / "camp"
    camp.mkdir()
    t = time.perf_counter()
    assert main(["batch", str(camp), "-o", str(tmp_path / "o"), "--scheduler", address]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a Dask scheduler address" in err[0] and time.perf_counter() - t < 5
    assert not (tmp_path / "o").exists()
    assert scheduler_address(" tcp://[::1]:8786 ") == "tcp://[::1]:8786"


def test_a_manifest_row_with_its_own_output_folder_is_a_failed_row(tmp_path):
    """-o in a manifest row's options was ignored without a word (the pair went to OUT/<name>)."""
    man = tmp_path / "m.csv"
    man.write_text('master,slave,options\nm.csv,s.csv,-o elsewhere\nm.csv,s.csv,--out=x\nm.csv,s.csv,--no-html\n')
    jobs = batch.discover(str(man), str(tmp_path / "o"))
    assert ["-o is no per-pair option" in j.problem for j in jobs] == [True, True, False]
