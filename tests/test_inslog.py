"""InsLog (the common frame) and the canonical CSV reader/writer."""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from logtools.errors import InputError
from logtools.inslog import ACCEL, GYRO, POS, QUAT, VEL, ChannelInfo, InsLog, LogMeta
from parsers import csv_canonical as cc
from parsers.base import Selector

T0_NS = 1_700_000_000_123_456_789  # an epoch stamp with every nanosecond digit used


def _log(n_imu=400, n_nav=100, t0_ns=T0_NS, clock="epoch", seed=0) -> InsLog:
    rng = np.random.default_rng(seed)
    t_imu = np.arange(n_imu) * 0.005
    t_nav = np.arange(n_nav) * 0.02 + 0.0025  # nav stamps between IMU stamps
    q = rng.normal(size=(n_nav, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    meta = LogMeta(source_path="mem", format="test", clock=clock, t0_ns=t0_ns, stamp_source="unit test",
                   channels={"imu": ChannelInfo(200.0, n_imu), "nav": ChannelInfo(50.0, n_nav)})
    return InsLog.from_arrays(
        meta, t_imu_s=t_imu, gyro_rad_s=rng.normal(size=(n_imu, 3)) * 0.1,
        accel_m_s2=rng.normal(size=(n_imu, 3)) + [0, 0, -9.8], t_nav_s=t_nav, quat_wxyz=q,
        vel_ned_m_s=rng.normal(size=(n_nav, 3)) * 10,
        lat_lon_alt=np.column_stack([30 + rng.normal(size=n_nav) * 1e-4, 110 + rng.normal(size=n_nav) * 1e-4,
                                     rng.normal(size=n_nav)]))


def test_construction_and_accessors():
    log = _log()
    assert list(log.imu.columns) == list(GYRO + ACCEL) and list(log.nav.columns) == list(QUAT + VEL + POS)
    assert log.imu.index.name == "t_s" and log.nav.index.name == "t_s"
    assert log.has_gyro and log.has_accel and log.has_quat and log.has_vel and log.has_pos
    assert log.gyro_rad_s().shape == (400, 3) and log.accel_m_s2().shape == (400, 3)
    t, q = log.quat_wxyz()
    assert t.shape == (100,) and q.shape == (100, 4)
    assert log.span_s() == (0.0, pytest.approx(399 * 0.005))
    assert log.duration_s == pytest.approx(1.995)
    assert log.t0_s == pytest.approx(T0_NS * 1e-9)
    with pytest.raises(dataclasses.FrozenInstanceError):
        log.meta = log.meta  # type: ignore[misc]
    # absent groups: an IMU-only log
    imu_only = InsLog.from_arrays(LogMeta("m", "t"), t_imu_s=np.arange(5.0), gyro_rad_s=np.zeros((5, 3)))
    assert imu_only.has_gyro and not imu_only.has_accel and not imu_only.has_quat and len(imu_only.nav) == 0
    empty = InsLog.from_arrays(LogMeta("m", "t"))
    assert empty.duration_s == 0.0 and np.isnan(empty.span_s()[0])


def test_nav_rows_skip_incomplete():
    log = _log()
    nav = log.nav.copy()
    nav.iloc[3, nav.columns.get_loc("vel_e_m_s")] = np.nan
    log2 = dataclasses.replace(log, nav=nav)
    t, v = log2.vel_ned_m_s()
    assert len(t) == 99 and np.isfinite(v).all()
    assert len(log2.quat_wxyz()[0]) == 100


def test_between_is_inclusive_and_cheap():
    log = _log()
    sub = log.between(0.5, 1.0)
    t = sub.t_imu_s()
    assert t[0] == pytest.approx(0.5) and t[-1] == pytest.approx(1.0) and len(t) == 101
    assert np.all((sub.t_nav_s() >= 0.5) & (sub.t_nav_s() <= 1.0)) and len(sub.nav) == 25
    assert sub.meta is log.meta


def test_rebased_is_an_exact_integer_shift():
    log = _log()
    new_t0 = T0_NS - 1_500_000_001  # 1.500000001 s earlier
    r = log.rebased(new_t0)
    assert r.meta.t0_ns == new_t0 and isinstance(r.meta.t0_ns, int)
    assert np.allclose(r.t_imu_s() - log.t_imu_s(), 1.500000001, rtol=0, atol=1e-12)
    assert np.allclose(r.t_nav_s() - log.t_nav_s(), 1.500000001, rtol=0, atol=1e-12)
    # absolute stamps are unchanged to the nanosecond
    abs_a = log.meta.t0_ns + np.round(log.t_imu_s() * 1e9).astype(np.int64)
    abs_b = r.meta.t0_ns + np.round(r.t_imu_s() * 1e9).astype(np.int64)
    assert np.array_equal(abs_a, abs_b)
    back = r.rebased(T0_NS)
    assert np.allclose(back.t_imu_s(), log.t_imu_s(), rtol=0, atol=1e-12)
    assert back.imu.index.name == "t_s" and back.gyro_rad_s().tolist() == log.gyro_rad_s().tolist()


def test_meta_helpers():
    log = _log()
    w = log.meta.with_warning("gap at 3 s")
    assert w.warnings == ("gap at 3 s",) and log.meta.warnings == ()
    assert log.with_meta(clock="boot").meta.clock == "boot" and log.meta.clock == "epoch"


def _abs_ns(log: InsLog, t: np.ndarray) -> np.ndarray:
    return log.meta.t0_ns + np.round(t * 1e9).astype(np.int64)


def _pandas_log(log: InsLog) -> InsLog:
    """``log`` rebuilt from DataFrames made by pandas itself (what every InsLog held before its arrays)."""
    def frame(cols):
        if not cols.data:
            return pd.DataFrame(index=pd.Index(np.zeros(0), name="t_s"))
        return pd.DataFrame(dict(cols.data), index=pd.Index(cols.t_s.copy(), name="t_s"))

    return InsLog(imu=frame(log.imu_columns), nav=frame(log.nav_columns), meta=log.meta)


def test_the_arrays_and_the_dataframes_give_the_same_log():
    """An InsLog held as arrays (the parsers', from_arrays) and the same built from pandas DataFrames give the
    same DataFrames, accessors, slices and rebased copies to the bit; a parser's frame views its one block."""
    from logtools.inslog import Columns

    for log in (_log(), _log(n_nav=0)):
        ref = _pandas_log(log)
        assert isinstance(log.imu_columns, Columns) and "imu" not in log._frames
        for a, b in ((log, ref), (log.between(0.3, 1.2), ref.between(0.3, 1.2)),
                     (log.rebased(T0_NS - 10**9), ref.rebased(T0_NS - 10**9))):
            pd.testing.assert_frame_equal(a.imu, b.imu, check_exact=True)
            if len(b.nav):
                pd.testing.assert_frame_equal(a.nav, b.nav, check_exact=True)
            assert len(a.nav) == len(b.nav) == a.n_nav and len(a.imu) == a.n_imu
            for name in ("has_gyro", "has_accel", "has_quat", "has_vel", "has_pos", "duration_s"):
                assert getattr(a, name) == getattr(b, name), name
            assert np.array_equal(a.gyro_rad_s(), b.gyro_rad_s()) and np.array_equal(a.t_nav_s(), b.t_nav_s())
            if a.has_quat:
                for x, y in zip(a.quat_wxyz(), b.quat_wxyz()):
                    assert np.array_equal(x, y)
        # slicing as pandas' own .loc does it
        pd.testing.assert_frame_equal(log.between(0.3, 1.2).imu, ref.imu.loc[0.3:1.2], check_exact=True)
    block = np.arange(12.0).reshape(3, 4)
    cols = Columns.from_block(np.arange(4.0), GYRO, block)
    frame = InsLog(imu=cols, nav=Columns.empty(), meta=LogMeta("mem", "test")).imu
    assert np.shares_memory(frame.to_numpy(), block) and list(frame.columns) == list(GYRO)


def test_a_log_of_arrays_is_a_dataclass_that_replaces_pickles_and_stays_read_only():
    import pickle

    log = _log()
    assert [f.name for f in dataclasses.fields(log)] == ["imu", "nav", "meta"]
    moved = dataclasses.replace(log, meta=dataclasses.replace(log.meta, t0_ns=5))
    assert moved.meta.t0_ns == 5 and np.array_equal(moved.gyro_rad_s(), log.gyro_rad_s())
    other = dataclasses.replace(log, nav=log.nav.iloc[:10])
    assert other.n_nav == 10 and other.n_imu == log.n_imu
    back = pickle.loads(pickle.dumps(log))
    pd.testing.assert_frame_equal(back.imu, log.imu, check_exact=True)
    with pytest.raises(dataclasses.FrozenInstanceError):
        log.meta = log.meta
    assert "400 rows" in repr(log)


@pytest.mark.parametrize("col", [[np.nan, 1.0], [np.nan, np.nan], [None, "x"], [None, None], [1, 2]])
def test_a_group_is_present_as_pandas_notna_says(col):
    """``has_quat`` and the like on a log given as DataFrames of any column type: pandas' notna's answer."""
    nav = pd.DataFrame({c: np.array(col, dtype=object if None in col else None) for c in QUAT},
                       index=pd.Index([0.0, 1.0], name="t_s"))
    log = InsLog(imu=pd.DataFrame(index=pd.Index([], name="t_s", dtype=float)), nav=nav, meta=LogMeta("m", "t"))
    assert log.has_quat == bool(nav[list(QUAT)].notna().any().all())


def test_a_pickled_log_carries_its_block_once():
    """A parser's stream (columns viewing one block) pickles as the block and the stamps, out of band as a
    forked parse sends it back (pipelines.parallel): its rows apart would be a second copy of the data."""
    import pickle

    from logtools.inslog import Columns

    n = 5000
    block = np.random.default_rng(1).normal(size=(6, n))
    log = InsLog(imu=Columns.from_block(np.arange(n) * 0.005, GYRO + ACCEL, block), nav=Columns.empty(),
                 meta=LogMeta("mem", "test"))
    bufs: list = []
    data = pickle.dumps(log, protocol=5, buffer_callback=bufs.append)
    assert sum(b.raw().nbytes for b in bufs) == block.nbytes + n * 8
    back = pickle.loads(data, buffers=bufs)
    assert np.shares_memory(back.imu_columns.data[GYRO[1]], back.imu_columns.block)
    assert np.array_equal(back.gyro_rad_s(), log.gyro_rad_s()) and np.array_equal(back.t_imu_s(), log.t_imu_s())


def test_canonical_csv_round_trip_epoch_ns(tmp_path):
    log = _log()
    p = str(tmp_path / "unit.csv")
    cc.write(p, log)
    head = open(p).readline().strip().split(",")
    assert head == list(cc.HEADER)
    first = open(p).readlines()[1].split(",")[0]
    assert first == "1700000000.123456789"  # full precision text, not float64 seconds
    assert cc.sniff(open(p, "rb").read(200), p)
    back = cc.load(p, Selector())
    assert back.meta.clock == "epoch" and back.meta.format == "csv"
    assert back.meta.t0_ns == T0_NS
    assert np.array_equal(_abs_ns(back, back.t_imu_s()), _abs_ns(log, log.t_imu_s()))
    assert np.array_equal(_abs_ns(back, back.t_nav_s()), _abs_ns(log, log.t_nav_s()))
    assert np.array_equal(back.gyro_rad_s(), log.gyro_rad_s())  # %.17g: bit exact
    assert np.array_equal(back.accel_m_s2(), log.accel_m_s2())
    for get in ("quat_wxyz", "vel_ned_m_s", "lat_lon_alt"):
        assert np.array_equal(getattr(back, get)()[1], getattr(log, get)()[1])
    assert back.meta.channels["imu"].count == 400 and back.meta.channels["nav"].count == 100
    assert back.meta.channels["imu"].rate_hz == pytest.approx(200.0, rel=1e-3)


def test_canonical_csv_boot_clock_and_partial_groups(tmp_path):
    meta = LogMeta("m", "t", clock="boot", t0_ns=50_000_000_007)
    log = InsLog.from_arrays(meta, t_nav_s=np.arange(10) * 0.1, vel_ned_m_s=np.ones((10, 3)))
    p = str(tmp_path / "vel.csv")
    cc.write(p, log)
    back = cc.load(p, Selector())
    assert back.meta.clock == "boot" and back.meta.t0_ns == 50_000_000_007
    assert back.has_vel and not back.has_quat and not back.has_gyro and len(back.imu) == 0
    # an incomplete group is ignored with a warning
    (tmp_path / "part.csv").write_text("time_s,gyro_x_rad_s,gyro_y_rad_s,vel_n_m_s,vel_e_m_s,vel_d_m_s\n"
                                       "1.0,0.1,0.2,1,2,3\n1.1,0.1,0.2,1,2,3\n")
    part = cc.load(str(tmp_path / "part.csv"), Selector())
    assert part.has_vel and not part.has_gyro
    assert any("incomplete" in w for w in part.meta.warnings)


def test_canonical_csv_sorting_and_duplicates(tmp_path):
    p = tmp_path / "messy.csv"
    p.write_text("time_s,vel_n_m_s,vel_e_m_s,vel_d_m_s\n"
                 "1700000000.2,2,0,0\n1700000000.1,1,0,0\n1700000000.2,9,0,0\n1700000000.3,3,0,0\n")
    log = cc.load(str(p), Selector())
    t, v = log.vel_ned_m_s()
    assert np.allclose(t, [0.0, 0.1, 0.2]) and v[:, 0].tolist() == [1.0, 2.0, 3.0]
    assert any("sorted" in w for w in log.meta.warnings) and any("duplicate" in w for w in log.meta.warnings)


@pytest.mark.parametrize("text,msg", [
    ("", "empty CSV"),
    ("a,b,c\n1,2,3\n", "no 'time_s' column"),
    ("time_s,colour,size\n1,2,3\n", "no recognisable data columns"),
    ("time_s,vel_n_m_s,vel_e_m_s,vel_d_m_s\nabc,1,2,3\n", "not decimal seconds"),
])
def test_canonical_csv_errors_name_the_file(tmp_path, text, msg):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError) as ei:
        cc.load(str(p), Selector())
    assert msg in str(ei.value) and str(p) in str(ei.value) and "\n" not in str(ei.value)


def test_seconds_text_ns_conversions_exact():
    s = pd.Series(["1700000000.123456789", "0.5", "-1.25", "12", "3.1234567891234"])
    ns = cc.seconds_text_to_ns(s)
    assert ns.tolist() == [1700000000123456789, 500000000, -1250000000, 12000000000, 3123456789]
    assert cc.ns_to_seconds_text(np.array([1700000000123456789, -1250000000])).tolist() == [
        "1700000000.123456789", "-1.250000000"]
