"""The slave on the master's clock (pipelines.export, parsers.restamp*): the shift's arithmetic, the
byte-level writers (only the time fields change: message counts per type, payloads compared with the
formats' own readers), damaged input, unchanged inputs, atomic outputs, the CLI. The latency round trips
(analysis -> export -> analysis) are in test_export_roundtrip.py."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import mmap
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from logtools import sim
from logtools.compensate import true_time_s
from logtools.errors import InputError
from logtools.results import LatencyResult
from parsers import registry
from parsers.restamp import ClockShift
from pipelines import export
from pipelines.cli import main as cli_main

LAT_S, DRIFT_PPM = 0.0372, 30.0
EXT = {"tlog": ".tlog", "dataflash": ".bin", "ulog": ".ulg", "csv": ".csv"}


def sha(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def pair():
    cfg = sim.scenario_config("ship", duration_s=12.0, seed=3, latency_s=LAT_S, drift_ppm=DRIFT_PPM)
    return sim.simulate(cfg)


@pytest.fixture(scope="module")
def slaves(pair, tmp_path_factory):
    d = tmp_path_factory.mktemp("slaves")
    out = {}
    for fmt, ext in EXT.items():
        p = d / f"slave{ext}"
        registry.write(str(p), pair.slave, fmt)
        out[fmt] = p
    return out


def shift_of(pair) -> ClockShift:
    t = pair.truth
    return ClockShift(t.latency_s, t.drift_ppm, int(t.t_mid_ns))


# ---- the shift ------------------------------------------------------------------------------------
def test_clock_shift_is_compensate_tau():
    """ClockShift gives logtools.compensate's exact tau = (t - L0 + d t_mid)/(1 + d), to the ns."""
    t0 = 1_700_000_000_000_000_000
    lat = LatencyResult(latency_s=0.25, sigma_s=1e-4, drift_ppm=120.0, method="x", window_s=(0.0, 1.0),
                        quality={}, methods={}, t_mid_rel_s=1800.0)
    rel = np.linspace(-10.0, 3700.0, 101)
    t_ns = t0 + np.round(rel * 1e9).astype(np.int64)
    sh = ClockShift.from_latency(lat, t0)
    tau_rel = true_time_s((t_ns - t0) * 1e-9, lat)
    got_rel = (sh.to_master_ns(t_ns) - t0) * 1e-9
    assert np.max(np.abs(got_rel - tau_rel)) < 2e-9
    # the shift differs from the first-order t - L(t) by d L: 30 ns here, and is not the same thing
    first_order = 0.25 + 120e-6 * ((t_ns - t0) * 1e-9 - 1800.0)
    assert np.max(np.abs(sh.shift_ns(t_ns) * 1e-9 - first_order)) > 1e-8


def test_clock_shift_from_report_uses_master_t0_and_t_mid():
    rep = {"master": {"t0_ns": 5_000_000_000}, "latency": {"latency_s": 0.01, "drift_ppm": 2.0, "t_mid_rel_s": 1.5,
                                                          "window_s": [0.0, 100.0]}}
    sh = ClockShift.from_report(rep)
    assert sh.t_ref_ns == 6_500_000_000 and sh.latency_s == 0.01 and sh.drift_ppm == 2.0
    with pytest.raises(ValueError, match="no latency"):
        ClockShift.from_report({"latency": {"failed": "no motion", "latency_s": None}})


@pytest.mark.parametrize("lat,drift", [(float("nan"), 0.0), (1e300, 0.0), (0.01, -1e6), (0.01, float("inf"))])
def test_clock_shift_from_report_refuses_unusable_numbers(lat, drift):
    """A damaged or hand-edited report (NaN, 1e300 s, a clock at -100 %) is refused, not written out."""
    rep = {"master": {"t0_ns": 5_000_000_000}, "latency": {"latency_s": lat, "drift_ppm": drift, "t_mid_rel_s": 1.5}}
    with pytest.raises(ValueError, match="not a usable"):
        ClockShift.from_report(rep)


@pytest.mark.parametrize("kind", ["csv", "parquet", "native"])
def test_export_never_replaces_an_input(slaves, pair, tmp_path, kind):
    """An export whose output path is the slave's or the master's file fails (one line in the report)
    and leaves that file's bytes as they were."""
    src = tmp_path / f"{export.BASENAME}.{'csv' if kind != 'parquet' else 'parquet'}"
    registry.write(str(tmp_path / "slave.csv"), pair.slave, "csv")
    os.replace(tmp_path / "slave.csv", src)
    if kind == "parquet":  # the slave is elsewhere; the master's file sits where the parquet would go
        slave = registry.load(str(slaves["csv"]))
        before = sha(src)
        (e,) = export.write_slave(("parquet",), str(tmp_path), slave, shift_of(pair), inputs=(str(src),))
    else:
        slave = registry.load(str(src))
        before = sha(src)
        out = str(src) if kind == "native" else None
        (e,) = export.write_slave((kind,), str(tmp_path), slave, shift_of(pair), out_path=out)
    assert e.failed and "overwrite an input" in e.failed, e
    assert sha(src) == before


def test_restamp_never_writes_over_the_reports_master(tmp_path, capsys):
    """`tapost restamp SLAVE --from REPORT -o MASTER`: the report's master is an input as well."""
    import shutil

    from pipelines.cli import main

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for f in ("master.mcap", "slave.tlog"):
        shutil.copy(os.path.join(root, "sample_logs", f), tmp_path / f)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert main(["analyze", "master.mcap", "slave.tlog", "-o", "out", "--no-html", "--no-recording"]) == 0
        before = sha(tmp_path / "master.mcap")
        assert main(["restamp", "slave.tlog", "--from", "out/report.json", "-o", "master.mcap"]) == 2
        assert main(["restamp", "slave.tlog", "--from", "out/report.json", "-o", "master.mcap",
                     "--format", "csv"]) == 2
    finally:
        os.chdir(cwd)
    assert sha(tmp_path / "master.mcap") == before
    assert "overwrite an input" in capsys.readouterr().err


def test_restamp_says_what_is_wrong_with_a_hand_edited_report(tmp_path, capsys):
    """`tapost restamp` reads a report a person may have edited or a copy may have damaged: a section that is
    not an object, a value that is not a number, a log of another format than the report's slave. Each is
    one line naming the file (they were internal errors: AttributeError, TypeError, or the report's tlog
    selector tried on an MCAP file)."""
    import copy
    import shutil

    from pipelines.cli import main

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for f in ("master.mcap", "slave.tlog"):
        shutil.copy(os.path.join(root, "sample_logs", f), tmp_path / f)
    assert main(["analyze", str(tmp_path / "master.mcap"), str(tmp_path / "slave.tlog"), "-o", str(tmp_path / "out"),
                 "--no-html", "--no-recording"]) == 0
    good = json.loads((tmp_path / "out" / "report.json").read_text())
    cases = [
        (lambda r: r.__setitem__("slave", 5), "the report's slave is not an object (int)"),
        (lambda r: r.__setitem__("latency", [1]), "the report's latency is not an object (list)"),
        (lambda r: r["latency"].__setitem__("quality", 5), "the report's latency.quality is not an object (int)"),
        (lambda r: r["latency"].__setitem__("latency_s", "abc"), "the report's latency_s 'abc' is not a number"),
        (lambda r: r["latency"].__setitem__("t_mid_rel_s", [2]), "the report's t_mid_rel_s [2] is not a number"),
        (lambda r: r["master"].__setitem__("t0_ns", "x"), "the report's master.t0_ns 'x' is not a whole number"),
        (lambda r: (r["latency"].pop("t_mid_rel_s"), r["latency"].__setitem__("window_s", 5)),
         "the report states neither latency.t_mid_rel_s nor latency.window_s"),
    ]
    capsys.readouterr()
    for i, (edit, needle) in enumerate(cases):
        rep = copy.deepcopy(good)
        edit(rep)
        path = tmp_path / f"r{i}.json"
        path.write_text(json.dumps(rep))
        assert main(["restamp", str(tmp_path / "slave.tlog"), "--from", str(path), "-o", str(tmp_path / "x.tlog")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(path) in err[0] and needle in err[0], (needle, err)
    # the master given as the slave: its format is not the report's slave's
    assert main(["restamp", str(tmp_path / "master.mcap"), "--from", str(tmp_path / "out"), "-o",
                 str(tmp_path / "x.mcap")]) == 2
    assert "the report's slave is tlog, this log is mcap" in capsys.readouterr().err
    assert not (tmp_path / "x.tlog").exists() and not (tmp_path / "x.mcap").exists()


def test_parse_kinds():
    assert export.parse_kinds("csv, native,csv") == ("csv", "native")
    assert export.parse_kinds(None) == ()
    with pytest.raises(InputError, match="--write-slave takes"):
        export.parse_kinds("csv,hdf5")
    with pytest.raises(InputError, match="--format takes"):  # (restamp's option)
        export.parse_kinds("xml", "--format")


def test_missing_ros_writer_is_one_clear_error(monkeypatch):
    import importlib

    real = importlib.import_module

    def fake(name, *a, **k):
        if name == "parsers.restamp_ros":
            err = ModuleNotFoundError(f"No module named {name!r}")
            err.name = name
            raise err
        return real(name, *a, **k)

    monkeypatch.setattr(export.importlib, "import_module", fake)
    with pytest.raises(InputError, match="native export for rosbag1 not available"):
        export.native_writer("rosbag1")
    with pytest.raises(InputError, match="not available"):
        export.native_writer("hdf5")


# ---- format by format: only the time fields change ---------------------------------------------------
def _tlog_msgs(path):
    from parsers.mavlink_tlog import reference_messages

    return reference_messages(str(path))


TLOG_TIME = {"time_usec", "time_boot_ms", "time_unix_usec"}


def test_tlog_only_time_fields_change(slaves, pair, tmp_path):
    from parsers.restamp_mavlink import restamp_tlog

    src = slaves["tlog"]
    h = sha(src)
    dst = tmp_path / "out.tlog"
    sh = shift_of(pair)
    st = restamp_tlog(str(src), str(dst), sh)
    assert sha(src) == h
    assert dst.stat().st_size == src.stat().st_size
    a, b = _tlog_msgs(src), _tlog_msgs(dst)  # pymavlink mavutil: every CRC must check
    assert len(a) == len(b) and len(a) == st.records
    ca = pd.Series([m.get_type() for m in a]).value_counts().to_dict()
    cb = pd.Series([m.get_type() for m in b]).value_counts().to_dict()
    assert ca == cb == st.records_by_type
    n_time = 0
    for ma, mb in zip(a, b):
        assert ma.get_type() == mb.get_type()
        da, db = ma.to_dict(), mb.to_dict()
        for k in da:
            if k in TLOG_TIME:
                n_time += da[k] != db[k]
            else:
                assert da[k] == db[k], (ma.get_type(), k)
        # the receive stamp moves by the shift (to the microsecond)
        assert abs((ma._timestamp - mb._timestamp) - LAT_S) < 2e-3
    assert n_time > 0.9 * len(a)
    # SYSTEM_TIME keeps its boot -> UNIX offset exactly
    sa = [m for m in a if m.get_type() == "SYSTEM_TIME"]
    sb = [m for m in b if m.get_type() == "SYSTEM_TIME"]
    assert sa and all(x.time_unix_usec - x.time_boot_ms * 1000 == y.time_unix_usec - y.time_boot_ms * 1000
                      for x, y in zip(sa, sb))


def test_dataflash_only_time_fields_change(slaves, pair, tmp_path):
    from parsers.dataflash import reference_messages
    from parsers.restamp_mavlink import restamp_dataflash

    src = slaves["dataflash"]
    h = sha(src)
    dst = tmp_path / "out.bin"
    st = restamp_dataflash(str(src), str(dst), shift_of(pair))
    assert sha(src) == h and dst.stat().st_size == src.stat().st_size
    a, b = reference_messages(str(src)), reference_messages(str(dst))
    assert [m.get_type() for m in a] == [m.get_type() for m in b]
    assert pd.Series([m.get_type() for m in a]).value_counts().to_dict() == \
        {k: v for k, v in st.records_by_type.items() if k in {m.get_type() for m in a}}
    time_cols = {"TimeUS", "TimeMS", "GMS", "GWk", "T"}
    for ma, mb in zip(a, b):
        da, db = ma.to_dict(), mb.to_dict()
        for k in da:
            if k not in time_cols:
                assert da[k] == db[k], (ma.get_type(), k)
        if ma.get_type() == "IMU":
            assert abs((ma.TimeUS - mb.TimeUS) * 1e-6 - LAT_S) < 1e-3
    # FMT records byte-identical
    raw_a, raw_b = src.read_bytes(), dst.read_bytes()
    fmt_at = [i for i in range(len(raw_a) - 2) if raw_a[i:i + 3] == b"\xa3\x95\x80"][:5]
    assert fmt_at and all(raw_a[i:i + 89] == raw_b[i:i + 89] for i in fmt_at)


def test_ulog_only_time_fields_change(slaves, pair, tmp_path):
    from pyulog import ULog

    from parsers.restamp_ulog import restamp_ulog

    src = slaves["ulog"]
    h = sha(src)
    dst = tmp_path / "out.ulg"
    restamp_ulog(str(src), str(dst), shift_of(pair))
    assert sha(src) == h and dst.stat().st_size == src.stat().st_size
    a, b = ULog(str(src)), ULog(str(dst))
    assert a.start_timestamp == b.start_timestamp  # header kept
    assert a.msg_info_dict == b.msg_info_dict
    da = {(d.name, d.multi_id): d.data for d in a.data_list}
    db = {(d.name, d.multi_id): d.data for d in b.data_list}
    assert da.keys() == db.keys()
    for key in da:
        assert da[key].keys() == db[key].keys()
        for f in da[key]:
            assert len(da[key][f]) == len(db[key][f])
            if f in ("timestamp", "timestamp_sample", "ref_timestamp", "time_utc_usec"):
                d = (da[key][f].astype(np.int64) - db[key][f].astype(np.int64)) * 1e-6
                assert np.all(np.abs(d[da[key][f] > 0] - LAT_S) < 1e-3), (key, f)
            else:
                np.testing.assert_array_equal(da[key][f], db[key][f], err_msg=f"{key}.{f}")
    gps = [k for k in da if k[0] == "vehicle_gps_position"]
    for k in gps:  # the boot -> UTC offset is kept exactly
        off_a = da[k]["time_utc_usec"].astype(np.int64) - da[k]["timestamp"].astype(np.int64)
        off_b = db[k]["time_utc_usec"].astype(np.int64) - db[k]["timestamp"].astype(np.int64)
        np.testing.assert_array_equal(off_a, off_b)


def test_csv_only_time_column_changes(slaves, pair, tmp_path):
    from parsers.restamp_csv import restamp_csv

    src = slaves["csv"]
    h = sha(src)
    dst = tmp_path / "out.csv"
    sh = shift_of(pair)
    st = restamp_csv(str(src), str(dst), sh)
    assert sha(src) == h
    a = pd.read_csv(src, dtype=str, keep_default_na=False)
    b = pd.read_csv(dst, dtype=str, keep_default_na=False)
    assert len(a) == len(b) == st.records and list(a.columns) == list(b.columns)
    pd.testing.assert_frame_equal(a.drop(columns="time_s"), b.drop(columns="time_s"))
    from parsers.csv_canonical import seconds_text_to_ns

    ta, tb = seconds_text_to_ns(a["time_s"]), seconds_text_to_ns(b["time_s"])
    np.testing.assert_array_equal(tb, sh.to_master_ns(ta))  # exact to the nanosecond
    assert b["time_s"].str.split(".").str[1].str.len().eq(9).all()


def test_vendor_csv_folder(tmp_path):
    """An NGIMU-style folder: every CSV with the time column restamped in its unit, other files copied."""
    from parsers.restamp_csv import restamp_csv_vendor

    d = tmp_path / "unit"
    d.mkdir()
    t = np.arange(0, 2.0, 0.02)
    g = pd.DataFrame({"Time (s)": [f"{x:.3f}" for x in t], **{f"Gyroscope {a} (deg/s)": np.sin(t + i)
                                                            for i, a in enumerate("XYZ")},
                      **{f"Accelerometer {a} (g)": np.cos(t + i) for i, a in enumerate("XYZ")}})
    g.to_csv(d / "sensors.csv", index=False)
    pd.DataFrame({"Time (s)": [f"{x:.3f}" for x in t], "W": 1.0, "X": 0.0, "Y": 0.0, "Z": 0.0}).to_csv(
        d / "quaternion.csv", index=False)
    (d / "Settings.txt").write_text("keep me\n")
    sh = ClockShift(0.0015, 0.0, 0)
    st = restamp_csv_vendor(str(d), str(tmp_path / "out"), sh)
    assert st.records_by_type == {"quaternion.csv": len(t), "sensors.csv": len(t)}
    assert (tmp_path / "out" / "Settings.txt").read_text() == "keep me\n"
    b = pd.read_csv(tmp_path / "out" / "sensors.csv", dtype=str)
    assert b["Time (s)"].iloc[1] == "0.018500000"
    reread = registry.load(str(tmp_path / "out"))
    assert abs(reread.meta.t0_ns - (-1_500_000)) == 0


def test_vendor_csv_of_iso_date_times_is_restamped_in_its_own_writing(tmp_path):
    """A time column of ISO 8601 date-times (the parser reads them: tests/test_parsers_csv.py): each cell
    written back as it was written (its date/time separator, its zone: Z, an offset as local time at that
    offset, none), nanoseconds in full; a damaged line and every other cell's text kept; read back, the
    stamps are the shifted ones to the nanosecond."""
    from parsers.restamp_csv import restamp_csv_vendor

    t0 = pd.Timestamp("2024-05-01T12:00:00", tz="UTC")
    n = 400
    utc = [t0 + pd.Timedelta(milliseconds=5 * i) for i in range(n)]
    text = []
    for i, x in enumerate(utc):  # three writings in one column
        if i % 3 == 0:
            text.append(x.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z")
        elif i % 3 == 1:
            text.append((x + pd.Timedelta(hours=2)).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "+02:00")
        else:
            text.append(x.strftime("%Y-%m-%d %H:%M:%S.%f"))
    k = np.arange(n)
    rows = [f"{c},{np.sin(i / 30):.6f},0.25,-0.125,0.5,0.0,-9.80665" for c, i in zip(text, k)]
    rows[7] = "garbled,0.1,0.2,0.3,0.0,0.0,-9.8"
    src = tmp_path / "unit.csv"
    src.write_text("UTC Time,Gyro X (rad/s),Gyro Y (rad/s),Gyro Z (rad/s),Accel X (m/s^2),Accel Y (m/s^2),"
                   "Accel Z (m/s^2)\n" + "\n".join(rows) + "\n")
    h = sha(src)
    a = registry.load(str(src))
    sh = ClockShift(0.0123456789, 87.5, a.meta.t0_ns + 1_000_000_000)
    st = restamp_csv_vendor(str(src), str(tmp_path / "out.csv"), sh)
    assert sha(src) == h and st.records == n - 1 and "1 line(s)" in st.damage[0]
    out = (tmp_path / "out.csv").read_text().splitlines()
    assert out[0] == src.read_text().splitlines()[0] and out[8] == rows[7]  # (header, damaged line: as they were)
    for i in (0, 1, 2):  # each cell in its own writing, nanoseconds in full
        cell, rest = out[1 + i].split(",", 1)
        assert rest == rows[i].split(",", 1)[1]
        want = sh.to_master_ns(np.array([utc[i].value]))[0] + (7_200_000_000_000 if i == 1 else 0)
        iso = str(np.datetime_as_string(np.int64(want).view("datetime64[ns]"), unit="ns"))  # (local time)
        assert cell == {0: iso + "Z", 1: iso + "+02:00", 2: iso.replace("T", " ")}[i]
        assert len(iso.split(".")[1]) == 9
    b = registry.load(str(tmp_path / "out.csv"))
    ta = a.meta.t0_ns + np.round(a.t_imu_s() * 1e9).astype(np.int64)
    tb = b.meta.t0_ns + np.round(b.t_imu_s() * 1e9).astype(np.int64)
    np.testing.assert_array_equal(tb, sh.to_master_ns(ta))
    np.testing.assert_array_equal(b.imu.to_numpy(), a.imu.to_numpy())


# ---- damage, atomicity, the CLI ----------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["tlog", "dataflash", "ulog"])
def test_damaged_input_written_whole_and_named(slaves, pair, tmp_path, fmt):
    from parsers import restamp_mavlink, restamp_ulog

    raw = bytearray(slaves[fmt].read_bytes())
    cut = len(raw) - 7
    mid = len(raw) // 2
    raw[mid:mid + 5] = b"\x00\x01\x02\x03\x04" if fmt != "ulog" else raw[mid:mid + 5]
    src = tmp_path / f"bad{EXT[fmt]}"
    src.write_bytes(bytes(raw[:cut]))
    dst = tmp_path / f"out{EXT[fmt]}"
    fn = {"tlog": restamp_mavlink.restamp_tlog, "dataflash": restamp_mavlink.restamp_dataflash,
          "ulog": restamp_ulog.restamp_ulog}[fmt]
    st = fn(str(src), str(dst), shift_of(pair))
    assert dst.stat().st_size == src.stat().st_size  # never a silently shorter file
    assert st.damage and any("trunc" in d or "damaged" in d for d in st.damage)
    # the readable part reads back, compensated
    log = registry.load(str(dst))
    assert len(log.imu) > 0.9 * len(pair.slave.imu)


@pytest.mark.parametrize("damaged", [False, True])
def test_tlog_runs_in_threads_write_the_same_bytes(slaves, pair, tmp_path, monkeypatch, damaged):
    """The tlog export splits the records into runs done in threads (large files): any split gives the
    file one run gives, damaged bytes between the runs included, and a negative stamp still fails."""
    from parsers import restamp_mavlink, threads

    raw = bytearray(slaves["tlog"].read_bytes())
    if damaged:
        mid = len(raw) // 3
        raw[mid:mid + 5] = b"\x00\x01\x02\x03\x04"
        raw = raw[:-7]
    src = tmp_path / "in.tlog"
    src.write_bytes(bytes(raw))
    outs = {}
    for parts in (1, 7):
        monkeypatch.setattr(restamp_mavlink, "_parts", lambda n, k=parts: k)
        monkeypatch.setattr(threads, "workers", lambda: 2)
        dst = tmp_path / f"out{parts}.tlog"
        st = restamp_mavlink.restamp_tlog(str(src), str(dst), shift_of(pair))
        outs[parts] = (dst.read_bytes(), st)
    assert outs[1][0] == outs[7][0]
    assert outs[1][1] == dataclasses.replace(outs[7][1], path=outs[1][1].path)
    assert bool(outs[1][1].damage) == damaged
    # a shift larger than the stamps: no output, one clear error
    t = pair.truth
    with pytest.raises(InputError, match="negative"):
        restamp_mavlink.restamp_tlog(str(src), str(tmp_path / "neg.tlog"), ClockShift(4e9, 0.0, int(t.t_mid_ns)))
    assert not (tmp_path / "neg.tlog").exists()


def test_tlog_time_boot_ms_is_never_wrapped(tmp_path):
    """A slave on its boot clock against a master on UNIX time (the latency ~ -1.7e9 s): its time_boot_ms
    fields (uint32 ms, 49.7 days) cannot hold the master's clock. The native export used to write them
    wrapped modulo 2**32; it now refuses with one line (as where a field would go negative), and the CSV is the
    way out."""
    from parsers import restamp_mavlink

    boot = sim.simulate(sim.scenario_config("ship", duration_s=12.0, seed=3, latency_s=LAT_S, slave_clock="boot"))
    src = tmp_path / "boot.tlog"
    registry.write(str(src), boot.slave, "tlog")
    before = sha(src)
    t = boot.truth
    with pytest.raises(InputError, match="beyond its field .*time_boot_ms holds 49.7 days"):
        restamp_mavlink.restamp_tlog(str(src), str(tmp_path / "out.tlog"), ClockShift(t.latency_s, 0.0,
                                                                                      int(t.t_mid_ns)))
    assert not (tmp_path / "out.tlog").exists() and sha(src) == before
    assert t.latency_s < -1e9  # (the boot clock's offset from UNIX time: what the fields cannot take)


def test_a_shifted_millisecond_field_beyond_32_bits_is_refused():
    """DataFlash's old TimeMS and GPS T (uint32 ms): a shifted value beyond the field is one clear error, never
    a value written wrapped (``put_le`` would keep its low 32 bits); within it, the values as they are."""
    from parsers.restamp import nonneg_or_glitch
    from parsers.restamp_mavlink import MS_NS

    old = np.array([50_000, 50_010, 50_020], np.int64)
    ok = nonneg_or_glitch(old, old + 1_000, MS_NS, "IMU.TimeMS", "x.bin", [], nbytes=4)
    assert ok.tolist() == [51_000, 51_010, 51_020]
    with pytest.raises(InputError, match=r"x\.bin: native export: shifted IMU\.TimeMS would be beyond its field "
                                         r"\(32-bit"):
        nonneg_or_glitch(old, old + 1_700_000_000_000, MS_NS, "IMU.TimeMS", "x.bin", [], nbytes=4)


@pytest.mark.parametrize("damaged", [False, True])
def test_tlog_patched_in_a_mapped_copy_or_written_gives_the_same_bytes(slaves, pair, tmp_path, monkeypatch, damaged):
    """The tlog export patches a kernel-made copy of the input where it lies (a shared map); where the copy
    cannot be mapped it writes the patched bytes itself, run by run: the same file either way, the input's
    bytes unchanged, and a shift the stamps cannot take leaves neither output nor temporary file."""
    from parsers import restamp_mavlink

    raw = bytearray(slaves["tlog"].read_bytes())
    if damaged:
        raw[len(raw) // 2:len(raw) // 2 + 9] = bytes(9)
        raw = raw[:-5]
    src = tmp_path / "in.tlog"
    src.write_bytes(bytes(raw))
    before = sha(src)
    mapped = tmp_path / "mapped.tlog"
    st_m = restamp_mavlink.restamp_tlog(str(src), str(mapped), shift_of(pair))

    real_map = mmap.mmap
    refused = []

    def no_map(fileno, length, *args, **kw):  # (the input's read-only map still works)
        if kw.get("access") == mmap.ACCESS_READ:
            return real_map(fileno, length, *args, **kw)
        refused.append(length)
        raise OSError("this file system cannot map a file for writing")

    monkeypatch.setattr(mmap, "mmap", no_map)
    written = tmp_path / "written.tlog"
    st_w = restamp_mavlink.restamp_tlog(str(src), str(written), shift_of(pair))
    assert refused  # (the copy's map was asked for, refused, and the bytes written instead)
    assert mapped.read_bytes() == written.read_bytes() != bytes(raw)
    assert st_m == dataclasses.replace(st_w, path=st_m.path)
    assert bool(st_m.damage) == damaged
    assert sha(src) == before
    with pytest.raises(InputError, match="negative"):  # (the map refused: the written path)
        restamp_mavlink.restamp_tlog(str(src), str(tmp_path / "neg_written.tlog"),
                                     ClockShift(4e9, 0.0, int(pair.truth.t_mid_ns)))
    monkeypatch.undo()
    with pytest.raises(InputError, match="negative"):
        restamp_mavlink.restamp_tlog(str(src), str(tmp_path / "neg_mapped.tlog"),
                                     ClockShift(4e9, 0.0, int(pair.truth.t_mid_ns)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.tlog", "mapped.tlog", "written.tlog"]


def test_dataflash_damaged_time_value_is_copied_and_named(slaves, pair, tmp_path):
    """A flipped byte that makes one record's TimeUS absurd (here: negative once shifted) does not stop the
    export: that record keeps its bytes and is named; a shift the clock cannot express is still an error."""
    from parsers import dataflash as df
    from parsers import restamp_mavlink

    log = df.read_log(str(slaves["dataflash"]))
    typ = next(t for t, f in log.formats.items() if f.name == "IMU")
    f = log.formats[typ]
    at = int(log.offsets[typ][len(log.offsets[typ]) // 2]) + 3 + f.dtype.fields["TimeUS"][1]
    raw = bytearray(slaves["dataflash"].read_bytes())
    raw[at + 7] ^= 0xFF  # the most significant byte: beyond int64, read back as a large negative number
    src = tmp_path / "glitch.bin"
    src.write_bytes(bytes(raw))
    dst = tmp_path / "out.bin"
    st = restamp_mavlink.restamp_dataflash(str(src), str(dst), shift_of(pair))
    assert any("IMU.TimeUS: 1 record(s) with a damaged time value" in d for d in st.damage), st.damage
    out = dst.read_bytes()
    assert out[at:at + 8] == bytes(raw[at:at + 8])  # copied unchanged
    assert len(out) == len(raw)
    with pytest.raises(InputError, match="negative"):
        restamp_mavlink.restamp_dataflash(str(slaves["dataflash"]), str(tmp_path / "neg.bin"),
                                          ClockShift(1e6, 0.0, int(pair.truth.t_mid_ns)))


def test_ulog_damaged_timestamp_keeps_its_bytes_and_shifts_nothing_else_wrong(slaves, pair, tmp_path):
    """A flipped byte in one data message's ``timestamp``: the shift of that message's time fields is taken at
    its neighbours' time (at a timestamp near 2^62 us the drift made it absurd, the other fields went
    negative and the whole export failed), so every field moves by about the latency."""
    from parsers import restamp_ulog
    from parsers import ulog as ul

    raw = bytearray(slaves["ulog"].read_bytes())
    buf = np.frombuffer(bytes(raw), np.uint8)
    offsets, sizes, types = restamp_ulog._walk_resyncing(buf, [])
    data = offsets[types == ul._T_DATA]
    at = int(data[len(data) // 2]) + 5  # a data message's first field: its timestamp (after the msg_id)
    raw[at + 7] ^= 0x40  # near 2^62 us
    src = tmp_path / "glitch.ulg"
    src.write_bytes(bytes(raw))
    st = restamp_ulog.restamp_ulog(str(src), str(tmp_path / "out.ulg"), shift_of(pair))
    out = (tmp_path / "out.ulg").read_bytes()
    moved_us = int.from_bytes(bytes(raw[at:at + 8]), "little") - int.from_bytes(out[at:at + 8], "little")
    assert abs(moved_us - LAT_S * 1e6) < 1000 and len(out) == len(raw) and st.records > 0
    back = registry.load(str(tmp_path / "out.ulg"))
    assert len(back.imu) >= len(pair.slave.imu) - 1


def test_interrupted_write_leaves_nothing(slaves, pair, tmp_path, monkeypatch):
    import parsers.atomic as atomic

    def boom(a, b):
        raise KeyboardInterrupt

    slave = registry.load(str(slaves["tlog"]))
    monkeypatch.setattr(atomic.os, "replace", boom)
    for kind in ("native", "csv", "parquet"):
        with pytest.raises(KeyboardInterrupt):
            export.write_slave((kind,), str(tmp_path), slave, shift_of(pair))
    assert os.listdir(tmp_path) == []


def test_restamp_cli(slaves, pair, tmp_path, capsys):
    t = pair.truth
    rep = {"schema": "tapost.report/1", "master": {"t0_ns": int(t.t_mid_ns) - 6_000_000_000},
           "slave": {"path": str(slaves["ulog"]), "format": "ulog", "selector": "", "clock": "epoch"},
           "latency": {"latency_s": t.latency_s, "drift_ppm": t.drift_ppm, "t_mid_rel_s": 6.0}}
    (tmp_path / "report.json").write_text(json.dumps(rep))
    h = sha(slaves["ulog"])
    code = cli_main(["restamp", str(slaves["ulog"]), "--from", str(tmp_path / "report.json"),
                     "--format", "native,csv,parquet"])
    assert code == 0
    assert sha(slaves["ulog"]) == h
    for name in ("slave_on_master_clock.ulg", "slave_on_master_clock.csv", "slave_on_master_clock.parquet"):
        assert (tmp_path / name).stat().st_size > 0
    pq = pd.read_parquet(tmp_path / "slave_on_master_clock.parquet")
    assert pq["time_ns"].dtype == np.int64
    csv = registry.load(str(tmp_path / "slave_on_master_clock.csv"))
    native = registry.load(str(tmp_path / "slave_on_master_clock.ulg"))
    # the exports agree: same IMU stamps to the microsecond (ULog's resolution)
    a = csv.meta.t0_ns + np.round(csv.imu.dropna().index.to_numpy() * 1e9)
    b = native.meta.t0_ns + np.round(native.imu.index.to_numpy() * 1e9)
    assert len(a) == len(b) and np.max(np.abs(a - b)) <= 1000
    capsys.readouterr()
    assert cli_main(["restamp", str(slaves["ulog"]), "--from", str(tmp_path / "nope.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nope.json" in err
    rep["latency"] = {"failed": "no motion", "latency_s": None}
    (tmp_path / "failed.json").write_text(json.dumps(rep))
    assert cli_main(["restamp", str(slaves["ulog"]), "--from", str(tmp_path / "failed.json")]) == 2
    assert "no latency estimate" in capsys.readouterr().err


def test_restamp_cli_takes_a_report_of_unrelated_clocks(slaves, pair, tmp_path, capsys):
    """A slave stamped in time since boot against a master in UNIX time: the latency is ~-1.7e9 s, a legitimate
    estimate that `analyze --write-slave` exports; `restamp --from` that report must write the same (it refused
    anything beyond a day)."""
    t = pair.truth
    offset_s = -1_700_000_000.0  # slave clock = master clock - 1.7e9 s
    rep = {"schema": "tapost.report/1", "master": {"t0_ns": int(t.t_mid_ns) - 6_000_000_000},
           "slave": {"path": str(slaves["csv"]), "format": "csv", "selector": "", "clock": "epoch"},
           "latency": {"latency_s": t.latency_s + offset_s, "drift_ppm": t.drift_ppm, "t_mid_rel_s": 6.0}}
    (tmp_path / "report.json").write_text(json.dumps(rep))
    assert ClockShift.from_report(rep).latency_s == t.latency_s + offset_s
    code = cli_main(["restamp", str(slaves["csv"]), "--from", str(tmp_path / "report.json"), "--format", "csv"])
    assert code == 0, capsys.readouterr().err
    out = registry.load(str(tmp_path / "slave_on_master_clock.csv"))
    src = registry.load(str(slaves["csv"]))
    # every IMU stamp moved by -latency(t): 1.7e9 s later, to the ns the CSV keeps
    t_src = src.meta.t0_ns + np.round(src.imu.index.to_numpy() * 1e9).astype(np.int64)
    t_out = out.meta.t0_ns + np.round(out.imu.dropna().index.to_numpy() * 1e9).astype(np.int64)
    want = ClockShift.from_report(rep).to_master_ns(t_src)
    assert len(t_out) == len(want) and np.max(np.abs(t_out - want)) <= 1000
    rep["latency"]["latency_s"] = 5e9  # beyond any two clocks up to 2100: a damaged report
    with pytest.raises(ValueError, match="not a usable"):
        ClockShift.from_report(rep)


def test_restamp_cli_refuses_a_report_of_another_log(slaves, pair, tmp_path, capsys):
    """A report whose slave section describes another log (other rates, another span): exit 2, one line
    saying what differs, nothing written; --force applies it with a warning. The report's own log: no
    warning. (restamp applied any report of the same format silently.)"""
    from pipelines.report import log_section

    t = pair.truth
    own = log_section(registry.load(str(slaves["tlog"])))
    rep = {"schema": "tapost.report/1", "master": {"t0_ns": int(t.t_mid_ns) - 6_000_000_000},
           "slave": own, "latency": {"latency_s": t.latency_s, "drift_ppm": t.drift_ppm, "t_mid_rel_s": 6.0}}
    (tmp_path / "report.json").write_text(json.dumps(rep))
    assert cli_main(["restamp", str(slaves["tlog"]), "--from", str(tmp_path / "report.json")]) == 0
    assert "warning" not in capsys.readouterr().out
    other = json.loads(json.dumps(own))
    for ch in other["channels"].values():
        ch["rate_hz"] *= 4
    other["start_s"] += 30.0
    (tmp_path / "slave_on_master_clock.tlog").unlink()
    rep["slave"] = other
    (tmp_path / "other.json").write_text(json.dumps(rep))
    assert cli_main(["restamp", str(slaves["tlog"]), "--from", str(tmp_path / "other.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not the log this report analysed" in err and "the report's at" in err
    assert "do not overlap" in err and "--force" in err
    assert not (tmp_path / "slave_on_master_clock.tlog").exists()
    assert cli_main(["restamp", str(slaves["tlog"]), "--from", str(tmp_path / "other.json"), "--force"]) == 0
    out = capsys.readouterr().out
    assert "warning: this log differs from the report's slave" in out
    assert (tmp_path / "slave_on_master_clock.tlog").exists()
    # the same log cut short or read with one more channel: a warning, not a refusal
    cut = json.loads(json.dumps(own))
    cut["duration_s"] += 5.0
    cut["channels"].pop("pos", None)
    (tmp_path / "cut.json").write_text(json.dumps({**rep, "slave": cut}))
    assert cli_main(["restamp", str(slaves["tlog"]), "--from", str(tmp_path / "cut.json")]) == 0
    out = capsys.readouterr().out
    assert "warning: this log differs from the report's slave" in out and "spans" in out


def test_export_table_has_every_channel(pair):
    sh = shift_of(pair)
    tab = export.table_on_master_clock(pair.slave, sh)
    for c in ("gyro_x_rad_s", "accel_z_m_s2", "qw", "vel_n_m_s", "lat_deg", "alt_m"):
        assert c in tab.columns
    assert tab.index.dtype == np.int64 and tab.index.is_monotonic_increasing
    n_imu = len(pair.slave.imu)
    assert tab["gyro_x_rad_s"].notna().sum() == n_imu


def test_unwritable_output_is_a_failed_entry(slaves, pair, tmp_path):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    slave = registry.load(str(slaves["csv"]))
    (e,) = export.write_slave(("csv",), str(blocker / "sub"), slave, shift_of(pair))
    assert e.failed and e.failed.startswith("cannot write") and e.path is None
    assert export.warnings_of([e]) == [f"slave export csv failed: {e.failed}"]


def test_batch_passes_write_slave_to_every_pair(slaves, tmp_path, monkeypatch):
    """tapost batch --write-slave: each pair's analysis gets it, unless its manifest options set it."""
    from pipelines import analyze, batch

    seen = {}

    def fake(master, slave, out_dir, opts, progress=None):
        seen[os.path.basename(out_dir)] = opts.write_slave
        raise InputError("stub: not analysed", slave)

    monkeypatch.setattr(analyze, "analyze_pair", fake)
    man = tmp_path / "campaign.csv"
    s = slaves["csv"]
    man.write_text(f"master,slave,options,name\n{s},{s},,a\n{s},{s},--write-slave parquet,b\n")
    batch.run_batch(str(man), str(tmp_path / "out"), write_slave="native,csv", log=lambda m: None)
    assert seen == {"a": ("native", "csv"), "b": ("parquet",)}


def test_csv_and_parquet_exports_hold_the_table_exactly(pair, tmp_path):
    """Every value of the CSV export reads back to the same float64 (shortest round-trip decimals), NaN as
    empty cells; its time column is the int64 ns stamps exactly (9 decimals); the Parquet export too."""
    from parsers.csv_canonical import seconds_text_to_ns

    sh = shift_of(pair)
    tab = export.table_on_master_clock(pair.slave, sh)
    entries = export.write_slave(("csv", "parquet"), str(tmp_path), pair.slave, sh)
    assert [e.failed for e in entries] == [None, None]
    csv = pd.read_csv(tmp_path / "slave_on_master_clock.csv", dtype={"time_s": str})
    assert list(csv.columns) == ["time_s", *map(str, tab.columns)]
    np.testing.assert_array_equal(seconds_text_to_ns(csv["time_s"]), tab.index.to_numpy(np.int64))
    pq = pd.read_parquet(tmp_path / "slave_on_master_clock.parquet")
    np.testing.assert_array_equal(pq["time_ns"].to_numpy(), tab.index.to_numpy(np.int64))
    for c in tab.columns:
        want = tab[c].to_numpy(float)
        np.testing.assert_array_equal(csv[str(c)].to_numpy(float), want)  # NaN where NaN (assert_array_equal)
        np.testing.assert_array_equal(pq[str(c)].to_numpy(float), want)


def test_ulog_damaged_header_in_the_middle_rewrites_the_rest_after_the_next_sync(slaves, pair, tmp_path):
    """A message header damaged in the middle of a ULog: the export resumes where the headers chain again, as
    tapost's reader does (``ulog.walk_resyncing``; it resumed at the next sync message, as pyulog does, and
    lost the second before it). Before that, everything after the damage was copied with its old stamps: half
    the exported log on the slave's clock. Read by tapost or by pyulog, the output has the input's samples,
    each on the master's clock."""
    from parsers import restamp_ulog
    from parsers import ulog as ul

    buf = np.fromfile(slaves["ulog"], np.uint8)
    offsets = ul.kernel("_walk")(buf, 16, ul._KNOWN_TYPES, ul._MAX_MSG_SIZE)[0]
    bad = buf.copy()
    bad[offsets[int(np.searchsorted(offsets, len(buf) // 2))] + 2] = 0  # a message type -> 0
    src, dst = tmp_path / "bad.ulg", tmp_path / "out.ulg"
    bad.tofile(src)
    sh = shift_of(pair)
    st = restamp_ulog.restamp_ulog(str(src), str(dst), sh)
    assert dst.stat().st_size == src.stat().st_size
    assert any("the messages resume at byte" in d for d in st.damage)
    a, b = registry.load(str(src)), registry.load(str(dst))
    assert len(a.imu) == len(b.imu) >= len(pair.slave.imu) - 2  # (the damaged message, the one before it)
    t_b = b.meta.t0_ns + np.round(b.t_imu_s() * 1e9).astype(np.int64)
    t_a = sh.to_master_ns(a.meta.t0_ns + np.round(a.t_imu_s() * 1e9).astype(np.int64))
    assert np.abs(t_b - t_a).max() <= 500  # (ULog stamps are whole microseconds)
    from pyulog import ULog

    def stamps(path):  # sensor_combined's raw timestamps (boot us), as pyulog reads the damaged file
        (d,) = [x for x in ULog(str(path), ["sensor_combined"]).data_list]
        return d.data["timestamp"].astype(np.int64)

    t_a, t_b = stamps(src), stamps(dst)
    assert len(t_a) == len(t_b) > 0.8 * len(pair.slave.imu)
    moved = t_a - t_b  # the shift of each sample, us
    late = np.arange(len(t_a)) > 0.6 * len(t_a)  # samples after the damage
    assert np.all(np.abs(moved[late] - LAT_S * 1e6) < 1000)  # 37.2 ms, plus the drift over 6 s: < 1 ms
    assert np.all(np.abs(moved[~late] - LAT_S * 1e6) < 1000)
