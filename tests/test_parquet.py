"""tapost's Parquet export read back (parsers.parquet_canonical) and restamped natively
(parsers.restamp_parquet): the same InsLog as the canonical CSV export of the same table, a latency of zero
against the master, only the time columns changed by a native export, damaged and foreign files refused in
one line."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from logtools import sim
from parsers import load, registry
from parsers.restamp import ClockShift
from pipelines import export
from pipelines.cli import main as cli_main

LAT_S, DRIFT_PPM = 0.0413, -25.0


@pytest.fixture(scope="module")
def pair():
    return sim.simulate(sim.scenario_config("vehicle", duration_s=40.0, seed=11, latency_s=LAT_S,
                                            drift_ppm=DRIFT_PPM))


@pytest.fixture(scope="module")
def exported(pair, tmp_path_factory):
    """The slave's CSV and Parquet exports on the master's clock (the true shift) and the master as MCAP."""
    d = tmp_path_factory.mktemp("pq")
    t = pair.truth
    entries = export.write_slave(("csv", "parquet"), str(d), pair.slave, ClockShift(t.latency_s, t.drift_ppm,
                                                                                     int(t.t_mid_ns)))
    assert [e.failed for e in entries] == [None, None]
    master = d / "master.mcap"
    registry.write(str(master), pair.master, "mcap")
    return d, master


def _sha(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def test_the_parquet_export_reads_as_its_csv_twin(exported):
    d, _ = exported
    a, b = load(str(d / "slave_on_master_clock.parquet")), load(str(d / "slave_on_master_clock.csv"))
    assert a.meta.format == "parquet" and b.meta.format == "csv"
    assert a.meta.t0_ns == b.meta.t0_ns and a.meta.clock == b.meta.clock
    for f in (lambda x: x.t_imu_s(), lambda x: x.t_nav_s(), lambda x: x.gyro_rad_s(), lambda x: x.accel_m_s2(),
              lambda x: x.quat_wxyz()[0], lambda x: x.quat_wxyz()[1], lambda x: x.vel_ned_m_s()[1]):
        np.testing.assert_array_equal(f(a), f(b))
    assert registry.detect(str(d / "slave_on_master_clock.parquet")).NAME == "parquet"


def test_analysing_the_parquet_export_against_the_master_finds_no_latency(exported, tmp_path, capsys):
    d, master = exported
    out = tmp_path / "out"
    rc = cli_main(["analyze", str(master), str(d / "slave_on_master_clock.parquet"), "-o", str(out),
                   "--no-html", "--no-recording", "--no-compare"])
    assert rc == 0, capsys.readouterr().err
    import json

    rep = json.loads((out / "report.json").read_text())
    lat = rep["latency"]
    assert abs(lat["latency_s"]) <= max(3 * lat["sigma_s"], 5e-5)
    assert abs(lat["drift_ppm"]) < 1.0


def test_a_native_export_of_a_parquet_slave_changes_only_its_time_columns(exported, tmp_path):
    d, _ = exported
    src = d / "slave_on_master_clock.parquet"
    before = _sha(src)
    shift = ClockShift(0.0123, 40.0, int(pq.read_table(src).column("time_ns")[0].as_py()))
    dst = tmp_path / "restamped.parquet"
    st = export.write_native(str(src), str(dst), "parquet", shift, "")
    assert _sha(src) == before and st.time_fields == ("time_ns", "time_s") and not st.damage
    a, b = pq.read_table(src), pq.read_table(dst)
    assert a.schema.equals(b.schema, check_metadata=False) and a.num_rows == b.num_rows == st.records
    new_ns = shift.to_master_ns(a.column("time_ns").to_numpy())
    for c in a.column_names:
        x, y = a.column(c).to_numpy(), b.column(c).to_numpy()
        if c == "time_ns":
            np.testing.assert_array_equal(y, new_ns)
        elif c == "time_s":  # (as the Parquet export writes it: whole seconds plus the fraction)
            np.testing.assert_array_equal(y, new_ns // 1_000_000_000 + (new_ns % 1_000_000_000) * 1e-9)
        else:
            np.testing.assert_array_equal(x, y)  # (NaN where NaN)
    meta = b.schema.metadata
    assert meta[b"tapost.slave"] == a.schema.metadata[b"tapost.slave"]  # (the file's metadata kept)
    assert float(meta[b"tapost.restamp.latency_s"]) == 0.0123


def test_export_kinds_beside_a_native_parquet_do_not_collide(exported, tmp_path):
    d, _ = exported
    slave = load(str(d / "slave_on_master_clock.parquet"))
    entries = export.write_slave(("parquet", "native"), str(tmp_path), slave, ClockShift(0.0, 0.0, slave.meta.t0_ns))
    assert [e.failed for e in entries] == [None, None]
    assert sorted(os.listdir(tmp_path)) == ["slave_on_master_clock.native.parquet", "slave_on_master_clock.parquet"]


def _cli_error(capsys, *argv) -> str:
    assert cli_main(list(argv)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_damaged_or_foreign_parquet_files_are_one_line(exported, tmp_path, capsys):
    d, master = exported
    raw = (d / "slave_on_master_clock.parquet").read_bytes()
    cut = tmp_path / "cut.parquet"
    cut.write_bytes(raw[: len(raw) // 2])
    assert "damaged Parquet file" in _cli_error(capsys, "inspect", str(cut)) and "cut.parquet" in \
        _cli_error(capsys, "analyze", str(master), str(cut), "-o", str(tmp_path / "o1"))
    flipped = bytearray(raw)
    mid = len(raw) - 200
    flipped[mid:mid + 40] = b"\xff" * 40  # (the footer's schema garbled)
    bad = tmp_path / "garbled.parquet"
    bad.write_bytes(bytes(flipped))
    line = _cli_error(capsys, "inspect", str(bad))
    assert "garbled.parquet" in line and "Parquet" in line
    foreign = tmp_path / "foreign.parquet"
    pq.write_table(pa.table({"stamp": [1, 2, 3], "value": [0.1, 0.2, 0.3]}), foreign)
    assert "no 'time_ns' or 'time_s' column" in _cli_error(capsys, "inspect", str(foreign))


def test_a_parquet_of_float_seconds_only_is_read_and_says_so(pair, tmp_path):
    t = np.round(pair.slave.t_imu_s() * 1e9).astype(np.int64) + pair.slave.meta.t0_ns
    g = pair.slave.gyro_rad_s()
    path = tmp_path / "seconds.parquet"
    pq.write_table(pa.table({"time_s": t * 1e-9, "gyro_x_rad_s": g[:, 0], "gyro_y_rad_s": g[:, 1],
                             "gyro_z_rad_s": g[:, 2], "extra": np.zeros(len(t))}), path)
    log = load(str(path))
    assert len(log.imu) == len(t) and not len(log.nav)
    said = " ".join(log.meta.warnings)
    assert "float64 'time_s'" in said and "extra" in said
    np.testing.assert_allclose(log.t_imu_s() + log.meta.t0_ns * 1e-9, t * 1e-9, atol=1e-6)
