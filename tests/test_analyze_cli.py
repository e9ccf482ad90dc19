"""``tapost analyze`` end to end on files: outputs, summary, skipped steps, exit codes, config.

Two layers:
* orchestration tests run the CLI with small stand-in numerics (``fake_numerics``: a real
  cross-correlation of |omega| and an SVD mounting fit, independent of logtools), so the pipeline's
  behaviour (skips, failures, outputs) is checked whatever the state of the numerics;
* integration tests run the real numerics on a simulated pair (skipped while a module is absent).
"""
from __future__ import annotations

import json
import os
import math
import sys

import numpy as np
import pytest

from logtools.conventions import euler_from_dcm
from logtools.errors import AnalysisError
from logtools.inslog import InsLog
from logtools.results import AlignmentResult, LatencyResult, MethodEstimate
from parsers import registry
from pipelines import report as rp
from pipelines.analyze import Numerics, use_numerics
from pipelines.cli import main

sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from test_report import LATENCY_S, MOUNT_RPY_DEG, make_fake_analysis  # noqa: E402


# ---- stand-in numerics (orchestration tests only) --------------------------------------------
def _fake_estimate(master: InsLog, slave: InsLog, *, method="tapost", max_lag_s=2.0, compare=True,
                   progress=None) -> LatencyResult:
    s = slave.rebased(master.meta.t0_ns)
    tm, wm = master.t_imu_s(), np.linalg.norm(master.gyro_rad_s(), axis=1)
    ts, ws = s.t_imu_s(), np.linalg.norm(s.gyro_rad_s(), axis=1)
    if not (np.isfinite(wm).all() and np.isfinite(ws).all()):
        raise AnalysisError("NaN in angular rate")
    lo, hi = max(tm[0], ts[0]), min(tm[-1], ts[-1])
    if hi - lo < 5.0:
        raise AnalysisError("no overlap between the master and the slave stamps")
    if np.std(wm) < 1e-3:
        raise AnalysisError("not enough motion to estimate the latency")
    lags = np.arange(-(max_lag_s or 1.0), (max_lag_s or 1.0) + 1e-9, 0.001)
    grid = np.arange(lo + 1.0, hi - 1.0, 0.01)
    ref = np.interp(grid, tm, wm)
    cost = np.array([np.mean((ref - np.interp(grid + L, ts, ws)) ** 2) for L in lags])
    i = int(np.argmin(cost))
    if progress:
        progress(1.0, "fake")
    return LatencyResult(latency_s=float(lags[i]), sigma_s=0.001, drift_ppm=0.0, method=method,
                         window_s=(master.t0_s + lo, master.t0_s + hi), quality={"fake": True},
                         methods={method: MethodEstimate(float(lags[i]), 0.001)},
                         cost_lag_s=lags, cost=cost / cost.max(), t_mid_rel_s=(lo + hi) / 2)


def _fake_compensate(slave: InsLog, lat: LatencyResult, master: InsLog, *, method="interp") -> InsLog:
    s = slave.rebased(master.meta.t0_ns)
    return InsLog(imu=s.imu.set_axis(s.imu.index - lat.latency_s, axis=0),
                  nav=s.nav.set_axis(s.nav.index - lat.latency_s, axis=0), meta=s.meta)


def _fake_alignment(master: InsLog, slave: InsLog, *, filter="kf", match="vel+att", smoother=False,
                    progress=None, **_):
    tm, wm = master.t_imu_s(), master.gyro_rad_s()
    ts, ws = slave.t_imu_s(), slave.gyro_rad_s()
    g = np.column_stack([np.interp(tm, ts, ws[:, i]) for i in range(3)])
    ok = (tm > ts[0]) & (tm < ts[-1])
    u, _, vt = np.linalg.svd(g[ok].T @ wm[ok])  # v_slave = R v_master  (Wahba / Kabsch)
    R = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    resid = g[ok] - wm[ok] @ R.T
    rpy = tuple(np.degrees(euler_from_dcm(R)))
    return AlignmentResult(filter=filter, match=match, mounting_rpy_deg=rpy, mounting_sigma_deg=(0.01,) * 3,
                           gyro_bias_dph=(0.0,) * 3, accel_bias_mg=(0.0,) * 3, converged_s=1.0,
                           residual_rms={"gyro_rad_s": float(np.sqrt(np.mean(resid ** 2)))})


def install_fake_numerics() -> Numerics:
    """Make the stand-ins above the analysis's numerics (``pipelines.analyze.use_numerics``: this process,
    and processes forked from it); returns the numerics before, to restore."""
    return use_numerics(Numerics(estimate=_fake_estimate, compensate=_fake_compensate,
                                 run_alignment=_fake_alignment))


@pytest.fixture
def fake_numerics():
    before = install_fake_numerics()
    yield
    use_numerics(before)


def write_fake_pair(d, *, duration_s=40.0, slave_imu_only=True, slave_offset_ns=0, name=("m.csv", "s.csv"),
                    master_cols=None) -> tuple[str, str]:
    an = make_fake_analysis(duration_s=duration_s, with_alignment=False, slave_t0_offset_ns=slave_offset_ns)
    master = an.master
    if master_cols is not None:
        master = InsLog(imu=master.imu, nav=master.nav[master_cols], meta=master.meta)
    m, s = str(d / name[0]), str(d / name[1])
    registry.write(m, master, "csv")
    registry.write(s, an.slave, "csv")
    return m, s


# ---- orchestration ----------------------------------------------------------------------------
def test_analyze_writes_three_outputs_and_summary(tmp_path, fake_numerics, capsys):
    m, s = write_fake_pair(tmp_path)
    out = tmp_path / "out"
    assert main(["analyze", m, s, "-o", str(out), "--max-lag", "0.5"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""  # stderr is not a tty here: no progress bar
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    assert rep["status"] == "ok"
    assert rep["latency"]["latency_s"] == pytest.approx(LATENCY_S, abs=1.5e-3)
    assert rep["alignment"]["compensated"]["mounting_rpy_deg"] == pytest.approx(list(MOUNT_RPY_DEG), abs=0.05)
    # uncompensated on face-value stamps: same mounting (rates), worse residual
    assert (rep["alignment"]["uncompensated"]["residual_rms"]["gyro_rad_s"]
            > 3 * rep["alignment"]["compensated"]["residual_rms"]["gyro_rad_s"])
    assert rep["options"]["max_lag_s"] == 0.5
    assert rep["master"]["format"] == "csv" and rep["slave"]["contents"]["quat"] is False
    assert (out / "report.html").stat().st_size > 10_000
    assert (out / "recording.rrd").stat().st_size > 1000
    assert sorted(p.name for p in out.iterdir()) == ["recording.rrd", "report.html", "report.json"]
    text = captured.out
    assert "latency +25.0" in text and "ms" in text and "ppm" in text
    assert "mounting (compensated" in text and "deg" in text
    assert "report.json" in text and "recording.rrd" in text


def test_unrelated_clocks_latency_failure_is_recorded(tmp_path, fake_numerics, capsys):
    """Slave on a boot clock 1.7e9 s away: latency fails (exit 1, one line), report.json records it."""
    m, s = write_fake_pair(tmp_path, slave_offset_ns=-1_699_999_000 * 10**9)
    out = tmp_path / "o"
    # the fake estimator only searches +-max_lag around face value, so feed the known offset via the
    # compensated path: with unrelated clocks the real numerics use --max-lag auto
    rc = main(["analyze", m, s, "-o", str(out), "--no-recording"])
    assert rc == 1  # the stand-in cannot find a lag of 1.7e9 s: latency failure, one line
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "latency failed" in err[0] and "no overlap" in err[0]
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    assert rep["status"] == "failed" and "no overlap" in rep["latency"]["failed"]
    assert rep["alignment"]["compensated"]["skipped"] == "latency failed"
    assert "no time overlap" in rep["alignment"]["uncompensated"]["skipped"]
    assert not (out / "recording.rrd").exists()


def test_master_without_nav_skips_alignment_but_succeeds(tmp_path, fake_numerics, capsys):
    m, s = write_fake_pair(tmp_path, master_cols=["lat_deg", "lon_deg", "alt_m"])
    out = tmp_path / "o"
    assert main(["analyze", m, s, "-o", str(out), "--no-recording"]) == 0
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    assert rep["status"] == "partial"
    for run in rp.RUNS:
        assert "attitude and/or velocity" in rep["alignment"][run]["skipped"]
    assert "skipped" in capsys.readouterr().out
    assert not (out / "recording.rrd").exists()


def test_explicit_match_the_data_cannot_support(tmp_path, fake_numerics):
    m, s = write_fake_pair(tmp_path, master_cols=["vel_n_m_s", "vel_e_m_s", "vel_d_m_s"])
    out = tmp_path / "o"
    assert main(["analyze", m, s, "-o", str(out), "--no-recording", "--match", "att"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert "needs the master's attitude" in rep["alignment"]["compensated"]["skipped"]


def test_a_failure_names_a_log_read_as_another_format_than_its_name(tmp_path, fake_numerics, capsys):
    """A slave CSV saved as .mcap (another file than the one meant?): read by its content, and where the latency
    then fails, the failure's one line says so beside the warning in report.json."""
    m, s = write_fake_pair(tmp_path, slave_offset_ns=-1_699_999_000 * 10**9)
    renamed = tmp_path / "slave_unit.mcap"
    os.replace(s, renamed)
    rc = main(["analyze", m, str(renamed), "-o", str(tmp_path / "o"), "--no-recording"])
    err = capsys.readouterr().err.strip().splitlines()
    said = "the slave read as csv by its content, though its name (slave_unit.mcap) says mcap"
    assert rc == 1 and len(err) == 1 and "latency failed" in err[0] and said in err[0]
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert any(w["stage"] == "parse" and "slave: read as csv by its content" in w["text"] for w in rep["warnings"])


def test_no_motion_is_exit_1_one_line(tmp_path, fake_numerics, capsys):
    an = make_fake_analysis(duration_s=20, with_alignment=False)
    still = InsLog(imu=an.master.imu * 0.0, nav=an.master.nav, meta=an.master.meta)
    registry.write(str(tmp_path / "m.csv"), still, "csv")
    registry.write(str(tmp_path / "s.csv"), an.slave, "csv")
    rc = main(["analyze", str(tmp_path / "m.csv"), str(tmp_path / "s.csv"), "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1 and "not enough motion" in err[0]


def test_bad_inputs_exit_2_one_line(tmp_path, fake_numerics, capsys):
    m, s = write_fake_pair(tmp_path)
    garbage = tmp_path / "garbage.bin"
    garbage.write_bytes(b"\x00\x01 not a log at all" * 10)
    cases = [
        (["analyze", str(tmp_path / "missing.csv"), s], "missing.csv"),
        (["analyze", m, str(garbage)], "garbage.bin"),
        (["analyze", m, s, "--max-lag", "soon"], "max-lag"),
        (["analyze", m, s, "--config", str(tmp_path / "nope.toml")], "nope.toml"),
    ]
    for argv, needle in cases:
        rc = main(argv + ["-o", str(tmp_path / "x")])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2, argv
        assert len(err) == 1 and needle in err[0], err
        assert "Traceback" not in err[0]
    assert not (tmp_path / "x").exists()  # nothing written for unreadable input


def test_debug_shows_the_traceback_and_keeps_the_exit_code(tmp_path, fake_numerics, capsys):
    """--debug adds the traceback before the one line; the exit code is the one without it (an unreadable
    input was exit 1 with --debug: the exception left main)."""
    m, s = write_fake_pair(tmp_path)
    for argv, code in ((["analyze", str(tmp_path / "missing.csv"), s], 2),
                       (["analyze", m, s, "--lever-arm", "1,2"], 2)):
        assert main(argv + ["-o", str(tmp_path / "x")]) == code
        plain = capsys.readouterr().err.strip().splitlines()
        assert main(["--debug"] + argv + ["-o", str(tmp_path / "x")]) == code
        err = capsys.readouterr().err.strip().splitlines()
        assert "Traceback (most recent call last):" in err and err[-1] == plain[-1]


def test_config_file_toml_and_json(tmp_path, fake_numerics):
    m, s = write_fake_pair(tmp_path, duration_s=20)
    cfg = tmp_path / "c.toml"
    cfg.write_text('[analyze]\nmax-lag = 0.3\nfilter = "hinf"\nno_recording = true\n')
    out = tmp_path / "o1"
    assert main(["analyze", m, s, "-o", str(out), "--config", str(cfg)]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["options"]["max_lag_s"] == 0.3 and rep["options"]["filter"] == "hinf"
    assert rep["alignment"]["compensated"]["filter"] == "hinf"
    assert not (out / "recording.rrd").exists()
    # the command line wins over the file; JSON works too
    cj = tmp_path / "c.json"
    cj.write_text(json.dumps({"max_lag": "auto", "filter": "ahinf", "out": str(tmp_path / "o2")}))
    assert main(["analyze", m, s, "--config", str(cj), "--filter", "kf", "--no-recording"]) == 0
    rep = json.loads((tmp_path / "o2" / "report.json").read_text())
    assert rep["options"]["max_lag_s"] is None and rep["options"]["filter"] == "kf"
    bad = tmp_path / "bad.toml"
    bad.write_text("colour = 'red'\n")
    assert main(["analyze", m, s, "--config", str(bad)]) == 2


@pytest.mark.parametrize("text, needle", [
    ('recording_max_rows = "abc"\n', "recording_max_rows takes a whole number of rows (at least 1), not 'abc'"),
    ("recording_max_rows = -5\n", "recording_max_rows takes a whole number of rows (at least 1), not -5"),
    ("out = 5\n", "out takes a folder path, not 5"),
    ('out = " "\n', "out is an empty path"),
    ('smoother = "false"\n', "smoother takes true or false, not 'false'"),
    ('[analyze]\nno_html = "yes"\n', "no_html takes true or false, not 'yes'"),
    ('filter = 3\n', "filter must be one of"),
    ("[1, 2]", "config must hold a table of options (TOML) or a JSON object, not a list"),
])
def test_a_bad_config_value_is_one_line_naming_the_file(tmp_path, capsys, text, needle):
    """Every value of a config file is checked as the file is read, and a bad one is said with the file's
    name: a string where a number or a switch belongs was an internal error (ValueError, TypeError), or
    silently true ("false" as a switch)."""
    from pipelines import analyze

    m, s = write_fake_pair(tmp_path, duration_s=20)
    cfg = tmp_path / "c.toml"
    cfg.write_text(text)
    with pytest.raises(analyze.InputError) as info:
        analyze.read_config(str(cfg))
    assert needle in info.value.problem and info.value.path == str(cfg)
    assert main(["analyze", m, s, "-o", str(tmp_path / "x"), "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"tapost: {cfg}: ") and needle in err[0], err
    assert not (tmp_path / "x").exists()


def test_an_output_the_system_refuses_is_one_line_naming_it(tmp_path, fake_numerics, capsys):
    """report.json's place taken by a folder (or a full disk, no permission): one line naming the output as
    the user knows it (not the temporary file renamed onto it) and exit 2; it was an internal error."""
    m, s = write_fake_pair(tmp_path, duration_s=20)
    out = tmp_path / "o"
    (out / "report.json").mkdir(parents=True)
    assert main(["analyze", m, s, "-o", str(out), "--no-recording", "--no-html"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"tapost: {out / 'report.json'}: Is a directory", err
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_config_switches_and_rows_accept_their_types(tmp_path):
    from pipelines import analyze

    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"smoother": True, "no_html": 1, "compare": 0, "recording_max_rows": "5000"}))
    opts, _ = analyze.options_from({}, analyze.read_config(str(cfg)))
    assert (opts.smoother, opts.html, opts.compare, opts.recording_max_rows) == (True, False, False, 5000)


# ---- real numerics ----------------------------------------------------------------------------
def _real():
    sim = pytest.importorskip("logtools.sim")
    pytest.importorskip("logtools.latency")
    pytest.importorskip("logtools.compensate")
    return sim


@pytest.mark.parametrize("fmt", ["csv", "tlog", "mcap"])
def test_real_cli_on_simulated_files(tmp_path, capsys, fmt):
    sim = _real()
    from parsers.registry import format_by_name

    try:
        mod = format_by_name(fmt)
    except Exception:
        pytest.skip(f"no {fmt} parser yet")
    if not hasattr(mod, "write"):
        pytest.skip(f"no {fmt} writer yet")
    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=120.0))
    ext = mod.EXTENSIONS[0]
    m, s = str(tmp_path / f"m{ext}"), str(tmp_path / f"s{ext}")
    registry.write(m, pair.master, fmt)
    registry.write(s, pair.slave, fmt)
    out = tmp_path / "out"
    rc = main(["analyze", m, s, "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    truth = pair.truth.to_dict()
    assert rep["latency"]["latency_s"] == pytest.approx(truth["latency_s"], abs=2e-3)
    c = rep["alignment"]["compensated"]
    if "skipped" not in c:
        err = np.abs((np.array(c["mounting_rpy_deg"]) - np.array(truth["mounting_rpy_deg"]) + 180) % 360 - 180)
        assert err.max() < 0.5
    assert (out / "report.html").exists() and (out / "recording.rrd").exists()


def test_real_cli_a_master_with_velocity_alone_is_a_clear_latency_failure(tmp_path, capsys):
    """A master CSV with a time and a velocity alone (no rate, no attitude): the latency cannot be estimated,
    exit 1 with one line saying so, the report written; the uncompensated alignment run says the mounting is
    not determined. It was an internal error (UnboundLocalError in the alignment's master series)."""
    sim = _real()
    pair = sim.simulate(sim.scenario_config("vehicle", duration_s=60.0))
    full, s = str(tmp_path / "full.csv"), str(tmp_path / "s.csv")
    registry.write(full, pair.master, "csv")
    registry.write(s, pair.slave, "csv")
    lines = open(full).read().splitlines()
    head = lines[0].split(",")
    keep = [i for i, c in enumerate(head) if c == "time_s" or c.startswith("vel_")]
    assert len(keep) == 4
    m = str(tmp_path / "m.csv")
    with open(m, "w") as fh:
        for line in lines:
            cells = line.split(",")
            fh.write(",".join(cells[i] for i in keep) + "\n")
    out = tmp_path / "out"
    rc = main(["analyze", m, s, "-o", str(out), "--no-recording", "--no-html"])
    err = capsys.readouterr().err
    assert rc == 1
    assert "internal error" not in err and "Traceback" not in err
    assert "latency needs angular rate or attitude from both units; the master has neither" in err
    rep = json.loads((out / "report.json").read_text())
    assert rep["status"] == "failed"
    unc = rep["alignment"]["uncompensated"]
    assert unc.get("skipped") or unc["mounting_rpy_deg"] == [None, None, None]


def test_real_cli_a_stray_stamp_days_away_is_dropped_with_a_warning(tmp_path, capsys):
    """A corrupt time field (a flipped byte in a DataFlash TimeUS put one IMU sample 12 days after a 40 s
    log): the uniform grid over that span took 16 GB. The stray sample is dropped at the parser's edge,
    said in the warnings, and the pair is analysed as usual."""
    sim = _real()
    pair = sim.simulate(sim.scenario_config("vehicle", duration_s=60.0, latency_s=0.0371))
    m, s = str(tmp_path / "m.mcap"), tmp_path / "s.csv"
    registry.write(m, pair.master, "mcap")
    registry.write(str(s), pair.slave, "csv")
    lines = s.read_text().splitlines()
    head, rows = lines[0], lines[1:]
    k = len(rows) // 2
    f = rows[k].split(",")
    f[0] = repr(float(f[0]) + 1.04e6)
    rows[k] = ",".join(f)
    s.write_text("\n".join([head] + rows) + "\n")
    out = tmp_path / "out"
    rc = main(["analyze", m, str(s), "-o", str(out), "--no-recording"])
    assert rc == 0, capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    assert any("stray stamps dropped" in w for w in rep["slave"]["warnings"])
    assert rep["latency"]["latency_s"] == pytest.approx(pair.truth.to_dict()["latency_s"], abs=1e-3)


def test_real_cli_slave_on_boot_clock_searches_the_whole_overlap(tmp_path, capsys):
    """Master on UNIX time (MCAP), slave on its boot clock (CSV): without --max-lag the stamps cannot be
    compared at face value, so the whole overlap is searched; the report says so. With an explicit
    --max-lag the user's window is kept (and fails, naming --max-lag auto)."""
    sim = _real()
    pair = sim.simulate(sim.scenario_config("ship", duration_s=120.0, slave_clock="boot", latency_s=0.0731,
                                            mount_rpy_deg=(10.0, -20.0, 135.0), drift_ppm=30.0))
    assert pair.slave.meta.clock == "boot"
    m, s = str(tmp_path / "m.mcap"), str(tmp_path / "s.csv")
    registry.write(m, pair.master, "mcap")
    registry.write(s, pair.slave, "csv")
    out = tmp_path / "out"
    rc = main(["analyze", m, s, "-o", str(out), "--no-recording"])
    text = capsys.readouterr().out
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    assert "whole overlap" in rep["latency_search"] and "latency search: whole overlap" in text
    # the latency between the two clocks: the boot clock's offset plus the delay
    truth = pair.truth.latency_at(rep["latency"]["window_s"][0] + 0.5 * (rep["latency"]["window_s"][1]
                                  - rep["latency"]["window_s"][0]) - pair.master.t0_s)
    assert rep["latency"]["latency_s"] == pytest.approx(truth, abs=1e-3)
    rc = main(["analyze", m, s, "-o", str(tmp_path / "o2"), "--no-recording", "--max-lag", "2"])
    assert rc == 1 and "--max-lag auto" in capsys.readouterr().err


REALDATA = __import__("pathlib").Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


@pytest.mark.realdata
def test_real_log_two_imus_of_one_board(tmp_path, capsys):
    """ArduPlane log, IMU vs IMU2 of the same board: about -1.4 ms (MANIFEST cross-correlation)."""
    log = REALDATA / "arduplane_box_pilot.BIN"
    if not log.exists():
        pytest.skip("../shared/realdata absent")
    pytest.importorskip("logtools.latency")
    pytest.importorskip("parsers.dataflash")
    rc = main(["analyze", f"{log}::imu=IMU", f"{log}::imu=IMU2", "-o", str(tmp_path / "o"), "--no-recording"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    rp.validate(rep)
    assert abs(rep["latency"]["latency_s"] - (-1.4e-3)) < 5e-3
    assert rep["master"]["format"] == "dataflash"


def test_real_cli_lever_arm_estimated_by_default(tmp_path, capsys):
    """A vehicle whose slave sits 2 m from the master: the velocities differ by w x l in every turn. Not
    modelled (``--lever-arm off``, what the CLI did before), the mounting comes out 0.5 arcmin off (2.6
    sigma; 2-4 arcmin at 10-30 sigma in longer runs); by default the lever arm is estimated in the alignment filter (started from
    the latency's velocity fit) and reported; a known one can be given instead."""
    sim = _real()
    lever = (1.13, 0.29, -1.75)
    cfg = sim.scenario_config("vehicle", seed=62022, duration_s=120.0, latency_s=0.0421, drift_ppm=20.0,
                              mount_rpy_deg=(-44.4, -18.1, 33.4), lever_arm_m=lever, turn_amp_deg=40.0,
                              turn_period_s=40.0, speed_var_m_s=1.5, slave_nav_rate_hz=25.0)
    pair = sim.simulate(cfg)
    m, s = str(tmp_path / "m.csv"), str(tmp_path / "s.csv")
    registry.write(m, pair.master, "csv")
    registry.write(s, pair.slave, "csv")
    truth = np.array(pair.truth.to_dict()["mounting_rpy_deg"])

    def run(*extra):
        out = tmp_path / f"o{len(list(tmp_path.iterdir()))}"
        assert main(["analyze", m, s, "-o", str(out), "--no-recording", *extra]) == 0, capsys.readouterr().err
        rep = json.loads((out / "report.json").read_text())
        rp.validate(rep)
        c = rep["alignment"]["compensated"]
        err = np.abs((np.array(c["mounting_rpy_deg"]) - truth + 180) % 360 - 180) * 60  # arcmin
        return c, err, capsys.readouterr().out

    off, err_off, _ = run("--lever-arm", "off")
    assert off["lever_arm_m"] is None
    auto, err_auto, text = run()
    assert err_off.max() > 0.3 and err_off.max() > 4 * err_auto.max(), (err_off, err_auto)
    assert err_auto.max() < 0.15, err_auto
    assert np.all(err_auto / 60 <= 3 * np.asarray(auto["mounting_sigma_deg"]) + 1e-3)
    assert np.allclose(auto["lever_arm_m"], lever, atol=0.1), auto["lever_arm_m"]
    assert all(x > 0 for x in auto["lever_arm_sigma_m"]) and "lever arm x y z" in text
    given, err_given, text = run("--lever-arm", ",".join(str(x) for x in lever))
    assert given["lever_arm_m"] == pytest.approx(list(lever)) and given["lever_arm_sigma_m"] is None
    assert err_given.max() < 0.15 and "(given)" in text
    assert main(["analyze", m, s, "-o", str(tmp_path / "bad"), "--lever-arm", "1,2"]) == 2
    assert "--lever-arm" in capsys.readouterr().err


def test_real_cli_flexure_found_by_the_latency_fit_goes_into_the_alignment(tmp_path, capsys):
    """A ship whose slave flexes (seed 000's model, 0.05 deg, beta 2/s): without flexure states
    (``--flexure off``, what the CLI did before) the mounting came out 2.8 arcmin off at a sigma of 0.57
    (z 4.8); by default the flexure model the latency's rate fit found is carried into the alignment
    filter as states, the mounting is within its sigma and a note says so. Without flexure states the
    white model (``--board-errors off``) is overconfident; the default ``--board-errors auto`` sees the
    flexure's correlated innovations and takes the board's states, whose sigma then covers the error."""
    sim = _real()
    cfg = sim.scenario_config("ship", seed=61008, duration_s=120.0, latency_s=-0.8582, drift_ppm=15.1,
                              mount_rpy_deg=(-120.79, -127.59, -59.50), lever_arm_m=(-0.77, -0.48, -1.57),
                              master_imu_rate_hz=55.6, slave_imu_rate_hz=396.8, slave_nav_rate_hz=5.0,
                              sway_amp_deg=(1.55, 8.57, 8.05), sway_period_s=(6.69, 10.65, 18.25),
                              speed_m_s=11.6, slave_vel_noise_m_s=0.02, slave_att_noise_deg=0.01, flexure=True)
    pair = sim.simulate(cfg)
    m, s = str(tmp_path / "m.csv"), str(tmp_path / "s.csv")
    registry.write(m, pair.master, "csv")
    registry.write(s, pair.slave, "csv")
    from logtools.conventions import dcm_from_euler

    def run(flexure, *extra):
        out = tmp_path / (flexure + "".join(extra))
        assert main(["analyze", m, s, "-o", str(out), "--no-recording", "--flexure", flexure, *extra]) == 0
        rep = json.loads((out / "report.json").read_text())
        c = rep["alignment"]["compensated"]
        Re, Rt = dcm_from_euler(np.radians(c["mounting_rpy_deg"])), dcm_from_euler(np.radians(cfg.mount_rpy_deg))
        err = np.degrees(np.arccos(np.clip((np.trace(Re.T @ Rt) - 1) / 2, -1, 1)))  # deg
        return rep, c, err / max(c["mounting_sigma_deg"])

    rep, auto, z_auto = run("auto")
    assert rep["latency"]["quality"]["flexure_model"] is not None
    assert any(n.startswith("flexure states") for n in auto["notes"]) and "flex_ang_x_arcmin" in auto["states"]
    assert z_auto < 2.0
    _, off, z_off = run("off", "--board-errors", "off")
    assert not any(n.startswith("flexure states") for n in off["notes"])
    assert z_off > 3.0  # the overconfident result the default no longer gives
    _, off_auto, z_off_auto = run("off")
    assert off_auto["notes"][0].startswith("board error states added") and z_off_auto < 2.0


def test_flexure_options_take_only_a_structural_flexure_model():
    """--flexure auto carries the latency fit's flexure model into the alignment when it looks like a
    structure's (fast, small), not a slow wander of degrees (two MEMS IMUs' scale and bias errors:
    the ArduCopter log0036 pair gives 4.7 deg at beta 0.013 1/s, which would leave the mounting undetermined)."""
    from types import SimpleNamespace

    from pipelines.analyze import AnalyzeOptions, _flexure_options

    def lat(sigma_deg, beta):
        return SimpleNamespace(quality={"flexure_model": {"sigma_deg": sigma_deg, "beta_1_s": beta}})

    auto = AnalyzeOptions()
    got = _flexure_options(auto, lat([0.06, 0.07, 0.05], 1.4))
    assert got == {"flexure": True, "flex_sigma_deg": (0.06, 0.07, 0.05), "flex_beta": 1.4}
    # not structure-like, or none: the alignment decides from its own residuals
    assert _flexure_options(auto, lat([4.74, 4.73, 0.02], 0.0126)) == {"flexure": "auto"}
    assert _flexure_options(auto, SimpleNamespace(quality={"flexure_model": None})) == {"flexure": "auto"}
    assert _flexure_options(AnalyzeOptions(flexure="off"), lat([0.06, 0.07, 0.05], 1.4)) == {}
    on = _flexure_options(AnalyzeOptions(flexure="on"), None)
    assert on["flexure"] and on["flex_beta"] == 2.0 and on["flex_sigma_deg"] == 0.05
    with pytest.raises(Exception, match="--flexure"):
        AnalyzeOptions(flexure="sometimes")


def test_lever_arm_values_with_a_leading_minus(tmp_path, fake_numerics):
    """``--lever-arm -0.5,0.2,1`` as users type it (argparse alone took the value for an option)."""
    m, s = write_fake_pair(tmp_path, duration_s=20)
    out = tmp_path / "o"
    assert main(["analyze", m, s, "-o", str(out), "--no-recording", "--lever-arm", "-0.5,0.2,1"]) == 0
    assert json.loads((out / "report.json").read_text())["options"]["lever_arm"] == "-0.5,0.2,1"


def test_real_cli_board_errors(tmp_path, capsys):
    """``--board-errors on``: a vehicle whose master attitude carries a 0.12 deg Markov error (50 s) and whose
    slave accelerometer triad is 1.2 deg off its gyro triad, through the CLI on CSV files: the states in the
    compensated run (notes, their histories in ``states``) and the mounting within 2 sigma; with ``off`` the
    white-noise model's overconfident answer; by default (auto) the states are added, in both runs, because
    the white model's innovations are correlated; a bad value is one line and exit 2."""
    sim = _real()
    cfg = sim.scenario_config("vehicle", duration_s=120.0, seed=3, mount_rpy_deg=(2.0, -3.0, 40.0),
                              latency_s=0.03, slave_accel_misalign_rpy_deg=(0.9, -0.7, 0.4),
                              master_att_markov_deg=0.12, master_att_markov_tau_s=50.0)
    pair = sim.simulate(cfg)
    m, s = str(tmp_path / "m.csv"), str(tmp_path / "s.csv")
    registry.write(m, pair.master, "csv")
    registry.write(s, pair.slave, "csv")
    from logtools.conventions import dcm_from_euler

    def run(*flag):
        out = tmp_path / (flag[-1] if flag else "default")
        assert main(["analyze", m, s, "-o", str(out), "--no-recording", "--no-html", *flag]) == 0
        c = json.loads((out / "report.json").read_text())["alignment"]["compensated"]
        Re, Rt = dcm_from_euler(np.radians(c["mounting_rpy_deg"])), dcm_from_euler(np.radians(cfg.mount_rpy_deg))
        err = np.degrees(np.arccos(np.clip((np.trace(Re.T @ Rt) - 1) / 2, -1, 1)))
        return c, err / np.linalg.norm(c["mounting_sigma_deg"])

    on, z_on = run("--board-errors", "on")
    assert any(n.startswith("master attitude error states") for n in on["notes"])
    assert "master_att_err_n_arcmin" in on["states"] and "accel_misalign_z_deg" in on["states"]
    assert z_on <= 2.0
    off, z_off = run("--board-errors", "off")
    assert not any(n.startswith("master attitude error states") for n in off["notes"]) and z_off > 5.0
    auto, z_auto = run()
    assert auto["notes"][0].startswith("board error states added") and z_auto <= 2.0
    assert auto["mounting_rpy_deg"] == on["mounting_rpy_deg"]
    unc = json.loads((tmp_path / "default" / "report.json").read_text())["alignment"]["uncompensated"]
    assert "master_att_err_n_arcmin" in unc["states"]
    with pytest.raises(SystemExit) as bad:
        main(["analyze", m, s, "-o", str(tmp_path / "bad"), "--board-errors", "maybe"])
    assert bad.value.code == 2 and "--board-errors" in capsys.readouterr().err


def test_two_units_on_their_own_boot_clocks_without_overlap_leave_the_status_ok(tmp_path):
    """Master and slave each on the time since its own boot, the stamps 1000 s apart: the latency is found
    over the whole overlap; the uncompensated run has nothing to align at face value, which is no shortcoming
    of the analysis (a note, status ok), as for a slave on boot time against a master on UNIX time."""
    from dataclasses import replace as _replace

    sim = _real()
    pair = sim.simulate(sim.scenario_config("ship", duration_s=120.0, slave_clock="boot", slave_boot_start_s=1000.0,
                                            latency_s=0.0431, mount_rpy_deg=(2.0, -1.0, 45.0), drift_ppm=10.0))
    master = _replace(pair.master, meta=_replace(pair.master.meta, t0_ns=5_000_000_000, clock="boot"))
    m, s = str(tmp_path / "m.csv"), str(tmp_path / "s.csv")
    registry.write(m, master, "csv")
    registry.write(s, pair.slave, "csv")
    out = tmp_path / "out"
    assert main(["analyze", m, s, "-o", str(out), "--no-recording", "--no-html", "--max-lag", "auto"]) == 0
    rep = json.loads((out / "report.json").read_text())
    rp.validate(rep)
    assert rep["alignment"]["uncompensated"].get("not_applicable") is True
    assert rep["status"] == "ok", (rep["status"], rep["skipped"], [w["text"] for w in rep["warnings"]])
    assert rep["alignment"]["compensated"]["mounting_rpy_deg"] == pytest.approx([2.0, -1.0, 45.0], abs=0.05)


def test_progress_line_fits_the_terminal_and_says_the_sub_step(monkeypatch):
    """The bar's line is as wide as the terminal allows, never wider (a wider line wraps and every redraw adds
    a line), and a sub-step's label drops the stage's word it repeats: a long label was cut at 28 characters
    ("alignment (compensated): ali")."""
    import io
    import os

    from pipelines import progress as pg

    for cols in (60, 80, 120, 300):
        monkeypatch.setattr(pg.shutil, "get_terminal_size", lambda fallback=(80, 24), c=cols: os.terminal_size((c, 24)))
        out = io.StringIO()
        p = pg.Progress(out, enabled=True)
        sub = p.scaled(0.5, 0.7, "alignment (compensated)")
        sub(0.0, "alignment: preparing")
        sub(1.0, "alignment filter")
        p(1.0, "latency: coarse |w| and rotation-solved cost, and a label longer than any terminal line")
        lines = out.getvalue().split("\r")[1:]
        assert lines and all(len(x) <= cols - 1 for x in lines), (cols, lines)
        if cols >= 80:
            assert "alignment (compensated): preparing" in lines[0] and "alignment (compensated): filter" in lines[1]
        assert lines[2].rstrip().endswith("100.0%") and "..." in lines[2]
        p.done()
        assert out.getvalue().endswith("\r" + " " * len(lines[2]) + "\r")
    assert pg._without_head("latency: done", "latency") == "done"
    assert pg._without_head("latency done", "latency") == "done"
    assert pg._without_head("latent", "latency") == "latent"
    assert pg._without_head("alignment", "alignment (x)") == "alignment"


def test_a_fresh_tapost_process_imports_numpys_unused_submodules_only_when_used(tmp_path):
    """The console script's process (``main()`` without an argument list) analysing the sample pair: numpy.f2py
    and numpy.testing, which scipy's array-API layer would import at once (pipelines.cli.NUMPY_DEFERRED_SUBMODULES),
    are not loaded; numpy works as before (np.char, which some parsers use, is not deferred)."""
    import os
    import subprocess
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "sample_logs"
    code = ("import sys; from pipelines.cli import main; "
            f"sys.argv = ['tapost', 'analyze', {str(sample / 'master.mcap')!r}, {str(sample / 'slave.tlog')!r}, "
            f"'-o', {str(tmp_path / 'out')!r}]; rc = main(); import numpy as np; "
            "print(rc, 'scipy.linalg' in sys.modules, sorted(m for m in ('numpy.f2py.f2py2e', "
            "'numpy.testing._private.utils') if m in sys.modules), np.char.add(['a'], ['b']).tolist())")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "TAPOST_WARMUP": "0"}, cwd=str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "0 True [] ['ab']"


def test_a_chosen_method_far_from_taposts_own_estimate_is_a_warning():
    """--latency-method s000-rate-integral (or s002) on a pair its assumptions do not hold for (axes not
    aligned) was the headline with no word; beyond METHOD_DISAGREES_SIGMAS combined sigmas of tapost's own
    estimate (run beside it) it is a warning. Within them, or with tapost chosen, nothing."""
    from pipelines.analyze import METHOD_DISAGREES_SIGMAS, _chosen_method_disagrees

    own = MethodEstimate(0.011, 5e-6)

    def lat(method, value, sigma):
        return LatencyResult(value, sigma, 0.0, method, (0.0, 60.0), methods={"tapost": own})

    text = _chosen_method_disagrees(lat("s000-rate-integral", 0.295, 7.2e-4))
    assert text and "s000-rate-integral" in text and "+295.000 ms" in text and "+11.000" in text
    near = 0.011 + 0.9 * METHOD_DISAGREES_SIGMAS * math.hypot(7.2e-4, 5e-6)
    assert _chosen_method_disagrees(lat("s000-rate-integral", near, 7.2e-4)) is None
    assert _chosen_method_disagrees(lat("tapost", 0.011, 5e-6)) is None
    assert _chosen_method_disagrees(LatencyResult(0.2, 1e-3, 0.0, "xcorr-norm", (0.0, 1.0))) is None  # (no own)


def test_an_output_folder_inside_an_input_folder_is_refused(tmp_path, fake_numerics, capsys):
    """-o naming a ROS 2 bag's folder (an input), or a folder in it, or the bag a storage file given alone
    lies in: one line, exit 2, the bag unchanged (report.json, recording.rrd and the CSV were written into the
    input bag)."""
    sim = _real()
    pair = sim.simulate(sim.scenario_config("ship", duration_s=20.0))
    bag, s = tmp_path / "master_bag", str(tmp_path / "s.csv")
    registry.write(str(bag), pair.master, "rosbag2", storage="sqlite3")
    registry.write(s, pair.slave, "csv")
    before = sorted(os.listdir(bag))
    (db3,) = [f for f in before if f.endswith(".db3")]
    for master, out in ((bag, bag), (bag, bag / "sub"), (bag / db3, bag)):
        assert main(["analyze", str(master), s, "-o", str(out), "--no-recording"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "inside the input folder" in err[0] and str(bag) in err[0]
        assert sorted(os.listdir(bag)) == before


def test_config_values_true_for_seconds_and_a_byte_order_mark(tmp_path):
    """max_lag = true was taken for 1 s (a bool is an int); now refused naming the file. A config saved
    with a UTF-8 byte order mark was 'Invalid statement'; now read. api.options(no_compare="x") was taken
    for true; now refused as the other switches are."""
    from pipelines import api
    from pipelines.analyze import read_config

    bt = tmp_path / "bt.toml"
    bt.write_text("max_lag = true\n")
    with pytest.raises(api.InputError, match="max-lag takes seconds") as exc:
        read_config(str(bt))
    assert "bt.toml" in str(exc.value)
    with pytest.raises(api.InputError):
        api.options(max_lag=True)
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbfmax_lag = 0.5\n")
    assert read_config(str(bom)) == {"max_lag": 0.5}
    bomj = tmp_path / "bom.json"
    bomj.write_bytes(b'\xef\xbb\xbf{"max_lag": 0.25}')
    assert read_config(str(bomj)) == {"max_lag": 0.25}
    with pytest.raises(api.InputError, match="no_compare takes true or false"):
        api.options(no_compare="x")
    assert api.options(no_compare=None).compare and not api.options(no_compare=True).compare


def test_options_that_would_do_nothing_are_said(tmp_path, capsys):
    """--compensation split with a filter that has no delay state left up to half a sample in the slave
    without a word: refused (one line, exit 2, before the work). A lever arm given with attitude matching
    alone is not used: a note of each run says so."""
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "sample_logs"
    m, s = str(sample / "master.mcap"), str(sample / "slave.tlog")
    assert main(["analyze", m, s, "--compensation", "split", "--filter", "hinf", "-o", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--compensation split" in err[0] and "kf-split" in err[0]
    assert not (tmp_path / "x").exists()
    out = tmp_path / "o"
    assert main(["analyze", m, s, "--lever-arm", "1,2,3", "--match", "att", "-o", str(out), "--no-recording",
                 "--no-html"]) == 0
    rep = json.loads((out / "report.json").read_text())
    said = [n["text"] for n in rep["notes"] if "lever arm given" in n["text"]]
    assert len(said) == 2 and all("not used with attitude matching alone" in t for t in said)


def test_outputs_an_earlier_run_left_in_the_folder_are_said(tmp_path, fake_numerics, capsys):
    """An analysis rerun into its folder with --no-html and --no-recording left the earlier report.html and
    recording.rrd, which report.json does not list, without a word: a warning now names each."""
    m, s = write_fake_pair(tmp_path)
    out = tmp_path / "out"
    assert main(["analyze", m, s, "-o", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert not [w for w in rep["warnings"] if "earlier run" in w["text"]]
    capsys.readouterr()
    assert main(["analyze", m, s, "-o", str(out), "--no-html", "--no-recording"]) == 0
    rep = json.loads((out / "report.json").read_text())
    said = sorted(w["text"].split(" in ")[0] for w in rep["warnings"] if "left from an earlier run" in w["text"])
    assert said == ["recording.rrd", "report.html"]
    assert "left from an earlier run" in capsys.readouterr().out
    rp.validate(rep)


def test_an_empty_write_slave_is_refused(tmp_path, fake_numerics, capsys):
    """--write-slave= (an empty shell variable) wrote nothing without a word."""
    m, s = write_fake_pair(tmp_path)
    for value in ("", ",", " , "):
        assert main(["analyze", m, s, f"--write-slave={value}", "-o", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--write-slave names nothing" in err[0]
    assert not (tmp_path / "x").exists()


def test_a_rate_with_no_regular_stretch_is_said_so_not_as_no_motion(tmp_path, capsys):
    """The real sitl tlog's RAW_IMU on receive stamps (4 Hz telemetry received in bursts) was 'not enough
    motion: 0 deg/s RMS on the master' while the vehicle turns at ~20 deg/s: the rate has no stretch regular
    enough to read, and the message now says so and what to use."""
    real = REALDATA / "sitl_vtol.tlog"
    if not real.exists():
        pytest.skip("../shared/realdata absent")
    rc = main(["analyze", f"{real}::imu=RAW_IMU,att=AHRS2,time=receive", f"{real}::imu=SCALED_IMU2,att=AHRS2",
               "-o", str(tmp_path / "o"), "--no-recording", "--no-html"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and "no stretch regular enough to read" in err[-1] and "receive stamps" in err[-1]


@pytest.mark.parametrize("command", [["analyze", "M", "S"], ["batch", "CAMPAIGN"], ["simulate", "aircraft"],
                                     ["restamp", "S", "--from", "R"]])
def test_an_empty_output_path_is_refused(tmp_path, capsys, monkeypatch, command):
    """-o '' (a script's unset variable) is one line and exit 2 for every command that writes, nothing written:
    not the default folder taken instead."""
    monkeypatch.chdir(tmp_path)
    try:
        rc = main([*command, "-o", ""])
    except SystemExit as exc:  # (argparse's usage error, in-process)
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "empty output path" in err
    assert os.listdir(tmp_path) == []


def test_both_units_on_burst_receive_stamps_say_what_to_use(tmp_path, capsys):
    """Both units of the real sitl tlog read on their receive stamps (time=receive: 4 Hz telemetry received in
    bursts) left 0.2 s of usable rate, and the failure said only that the overlap was short; it now says the
    stamps are the tlog's receive stamps and what reads the messages' own time fields."""
    real = REALDATA / "sitl_vtol.tlog"
    if not real.exists():
        pytest.skip("../shared/realdata absent")
    rc = main(["analyze", f"{real}::imu=RAW_IMU,time=receive", f"{real}::imu=SCALED_IMU2,att=AHRS2,time=receive",
               "-o", str(tmp_path / "o"), "--no-recording", "--no-html"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and "receive stamps (time=receive)" in err[-1] and "time=message" in err[-1]
    assert "master and slave" in err[-1]
