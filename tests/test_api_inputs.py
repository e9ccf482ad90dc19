"""The Python API's inputs (DESIGN.md, "Python API"): paths as str or any os.PathLike, wrong types refused at the
boundary with one InputError naming what was given and what is expected, a channel a log lacks said as such.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

import parsers
from logtools.errors import AnalysisError, InputError
from logtools.inslog import ChannelInfo, InsLog, LogMeta, MissingChannelError
from pipelines import api

ROOT = Path(__file__).resolve().parents[1]
M = ROOT / "sample_logs" / "master.mcap"
S = ROOT / "sample_logs" / "slave.tlog"
FAST = dict(max_lag=0.5, no_recording=True, no_html=True, no_compare=True)


class _PathLike:
    """An os.PathLike that is not a pathlib.Path."""

    def __init__(self, p):
        self.p = str(p)

    def __fspath__(self):
        return self.p


def _numbers(an) -> dict:
    rep = an.report
    lat = rep["latency"]
    out = {k: lat[k] for k in ("latency_s", "sigma_s", "drift_ppm")}
    for run in ("uncompensated", "compensated"):
        sec = rep["alignment"][run]
        out[run] = (sec["mounting_rpy_deg"], sec["mounting_sigma_deg"])
    out["status"] = rep["status"]
    return out


@pytest.fixture(scope="module")
def by_str():
    return api.analyze(str(M), str(S), **FAST)


# ---- 1. os.PathLike wherever a path string goes ---------------------------------------------------------
def test_load_takes_a_path_object_and_gives_what_the_string_gives():
    a, b, c = api.load(str(M)), api.load(M), api.load(_PathLike(M))
    for log in (b, c):
        assert log.meta.source_path == a.meta.source_path and log.meta.selector == a.meta.selector
        np.testing.assert_array_equal(log.gyro_rad_s(), a.gyro_rad_s())
        np.testing.assert_array_equal(log.quat_wxyz()[1], a.quat_wxyz()[1])


def test_a_path_objects_text_carries_a_selector_as_a_strings_does():
    sel = "imu=/imu,att=/attitude"
    a = api.load(f"{M}::{sel}")
    b = api.load(Path(f"{M}::{sel}"))
    assert b.meta.selector == a.meta.selector and b.has_quat and not b.has_vel
    with pytest.raises(InputError, match="bad selector|no|not"):
        api.load(Path(f"{M}::imu=/no_such_topic"))


def test_analyze_with_path_objects_gives_the_strings_numbers(by_str):
    calls = []
    an = api.analyze(M, _PathLike(S), progress=lambda f, stage: calls.append((f, stage)), **FAST)
    assert an.ok and _numbers(an) == _numbers(by_str)
    assert calls and all(isinstance(s, str) for _, s in calls)
    # the report records str paths (JSON), as the strings' run does
    assert an.report["options"]["master"] == str(M) and an.report["options"]["slave"] == str(S)
    json.dumps(an.report)
    # an InsLog on one side, a Path on the other
    an2 = api.analyze(api.load(M), S, **FAST)
    assert _numbers(an2) == _numbers(by_str)


def test_write_takes_a_path_object(by_str, tmp_path):
    out = tmp_path / "o"
    outcome = by_str.write(out)
    assert (out / "report.json").exists()
    assert json.loads((out / "report.json").read_text())["latency"]["latency_s"] == by_str.latency.latency_s
    assert isinstance(outcome.out_dir, str)


def test_config_inspect_and_parsers_write_take_path_objects(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("max_lag = 0.25\n")
    assert api.options(config=cfg) == api.options(config=str(cfg)) == api.options(max_lag=0.25)
    assert parsers.inspect_log(M) == parsers.inspect_log(str(M))
    log = api.load(S)
    parsers.write(tmp_path / "s.csv", log, "csv")
    back = api.load(tmp_path / "s.csv")
    assert back.n_imu == log.n_imu


# ---- 2. wrong types: one InputError naming what was given and what is expected -------------------------
@pytest.mark.parametrize("bad, named", [(None, "None"), (5, "int 5"), ([str(M)], "list"), ({str(M): 1}, "dict"),
                                        (str(M).encode(), "bytes"), (3.5, "float 3.5")])
def test_load_refuses_a_wrong_type_in_one_line(bad, named):
    with pytest.raises(InputError) as ei:
        api.load(bad)
    msg = str(ei.value)
    assert named in msg and "must be a path" in msg and "os.PathLike" in msg and "\n" not in msg


def test_load_returns_an_inslog_as_it_is_and_path_only_functions_refuse_one():
    log = api.load(M)
    assert api.load(log) is log
    for call in (lambda: parsers.inspect_log(log), lambda: parsers.load(log)):
        with pytest.raises(InputError, match="InsLog .*log.meta.source_path"):
            call()


@pytest.mark.parametrize("bad", [None, 5, b"x.mcap", ["a", "b"]])
def test_analyze_refuses_a_wrong_log_type_naming_the_side(bad):
    with pytest.raises(InputError, match=r"the slave log must be an InsLog \(api.load\) or a path"):
        api.analyze(M, bad, **FAST)
    with pytest.raises(InputError, match="the master log must be"):
        api.analyze(bad, S, **FAST)


def test_config_of_a_wrong_type_is_refused():
    with pytest.raises(InputError, match="config must be a path.*int 5"):
        api.options(config=5)


# ---- 3. a channel the log lacks ----------------------------------------------------------------------
def _imu_only() -> InsLog:
    meta = LogMeta(source_path="/data/u.bin", format="dataflash", selector="imu=IMU",
                   channels={"imu": ChannelInfo(100.0, 50)})
    t = np.arange(50) * 0.01
    return InsLog.from_arrays(meta, t_imu_s=t, gyro_rad_s=np.zeros((50, 3)))


@pytest.mark.parametrize("accessor, has, words", [
    ("quat_wxyz", "has_quat", "attitude"), ("vel_ned_m_s", "has_vel", "velocity"),
    ("lat_lon_alt", "has_pos", "position"), ("accel_m_s2", "has_accel", "specific force")])
def test_an_accessor_names_the_missing_channel_and_the_source(accessor, has, words):
    log = _imu_only()
    assert not getattr(log, has)
    with pytest.raises(MissingChannelError) as ei:
        getattr(log, accessor)()
    err = ei.value
    msg = str(err)
    assert words in msg and f"log.{has}" in msg and f"{accessor}()" in msg
    assert msg.startswith("/data/u.bin::imu=IMU: ") and "dataflash" in msg and "\n" not in msg
    assert isinstance(err, AnalysisError) and isinstance(err, KeyError)  # (KeyError: what it raised before)
    assert err.columns and err.path == "/data/u.bin::imu=IMU"
    assert api.MissingChannelError is MissingChannelError


def test_the_accessors_are_unchanged_where_the_channel_is_there():
    log = _imu_only()
    g = log.gyro_rad_s()
    assert g.shape == (50, 3) and g.flags.f_contiguous
    full = api.load(M)
    t, q = full.quat_wxyz()
    assert q.shape == (len(t), 4) and q.flags.c_contiguous


def test_a_real_log_without_velocity_says_so():
    log = api.load(Path(f"{M}::imu=/imu,att=/attitude"))
    with pytest.raises(MissingChannelError, match=f"{M}.*has_vel"):
        log.vel_ned_m_s()


# ---- 4. write's folder and progress callbacks checked at the boundary ----------------------------------
@pytest.mark.parametrize("bad", [None, 5, b"out", ["o"]])
def test_write_refuses_a_wrong_folder(by_str, bad, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="the output folder must be a path"):
        by_str.write(bad)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("bad, words", [
    (5, "progress must be None or a callable progress\\(fraction, stage\\); got int 5"),
    ("bar", "got str 'bar'"),
    (lambda f: None, "must take two arguments"),
    (lambda: None, "must take two arguments"),
    (lambda f, s, x: None, "must take two arguments")])
def test_a_wrong_progress_is_refused_before_any_work(bad, words, by_str, tmp_path):
    with pytest.raises(InputError, match=words):
        api.analyze(M, S, progress=bad, **FAST)
    with pytest.raises(InputError, match=words):
        by_str.write(tmp_path / "o", progress=bad)
    assert not (tmp_path / "o").exists()


def test_progress_callables_of_other_shapes_are_taken(tmp_path, by_str):
    from pipelines.progress import Progress

    seen = []

    def cb(fraction, stage="", *rest):
        seen.append(fraction)

    by_str.write(tmp_path / "a", progress=cb)
    by_str.write(tmp_path / "b", progress=Progress(enabled=False))
    assert seen and (tmp_path / "b" / "report.json").exists()
