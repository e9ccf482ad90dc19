"""MAVLink tlog and ArduPilot DataFlash parsers: round trips, the fast path against pymavlink (message
for message), real logs (skipped when ../shared/realdata is absent), damaged and bad input."""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from logtools.conventions import quat_from_euler
from logtools.errors import InputError
from logtools.inslog import InsLog, LogMeta
from parsers import dataflash as D
from parsers import mavlink_common as C
from parsers import mavlink_tlog as T
from parsers import registry
from parsers.base import Selector
from pipelines.cli import main as cli_main

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
EPOCH_T0_NS = 1_700_000_000_000_000_000
BOOT_T0_NS = 12_000_000_000


def make_log(duration_s: float = 6.0, imu_hz: float = 200.0, nav_hz: float = 50.0,
             clock: str = "epoch", seed: int = 0) -> InsLog:
    """A small synthetic FRD/NED unit with moving attitude, velocity and position."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * imu_hz)
    t = np.arange(n) / imu_hz
    gyro = 0.3 * np.column_stack([np.sin(2 * t), np.cos(1.3 * t), np.sin(0.7 * t)]) + rng.normal(0, 0.01, (n, 3))
    acc = np.column_stack([np.sin(t), np.cos(t), -9.8 + 0.2 * np.sin(3 * t)]) + rng.normal(0, 0.05, (n, 3))
    m = int(duration_s * nav_hz)
    tn = np.arange(m) / nav_hz
    q = quat_from_euler(np.column_stack([0.2 * np.sin(tn), 0.3 * np.cos(0.5 * tn), 2.5 * np.sin(0.2 * tn)]))
    v = np.column_stack([5 * np.sin(0.3 * tn), 5 * np.cos(0.3 * tn), 0.5 * np.sin(tn)])
    p = np.column_stack([45.1 + 1e-5 * tn, 7.2 + 2e-5 * tn, 250.0 + np.sin(0.5 * tn)])
    meta = LogMeta(source_path="sim", format="sim", clock=clock,
                   t0_ns=EPOCH_T0_NS if clock == "epoch" else BOOT_T0_NS)
    return InsLog.from_arrays(meta, t, gyro, acc, tn, q, v, p)


def abs_ns(log: InsLog, t_s: np.ndarray) -> np.ndarray:
    return log.meta.t0_ns + np.round(np.asarray(t_s) * 1e9).astype(np.int64)


def quat_err(q1: np.ndarray, q2: np.ndarray) -> float:
    return float(np.max(1.0 - np.abs(np.sum(q1 * q2, axis=1))))


# ---- low level: CRC, gather, packing against pymavlink -----------------------------------------------
def test_crc_and_gather_match_reference():
    from pymavlink import mavutil
    rng = np.random.default_rng(1)
    buf = rng.integers(0, 256, 5000).astype(np.uint8)
    starts = rng.integers(0, 4900, 300)
    for s in starts[:20]:
        assert C.x25_crc_at(buf, [s], 37, extra=50)[0] == mavutil.x25crc(bytes(buf[s:s + 37]) + bytes([50])).crc
    np.testing.assert_array_equal(C.x25_crc_at(buf, starts, 40, 7), C.x25_crc_at_np(buf, starts, 40, 7))
    lens = rng.integers(0, 60, 300)
    np.testing.assert_array_equal(C.gather_rows(buf, starts, 60, lens), C.gather_rows_np(buf, starts, 60, lens))
    block = C.gather_rows(buf, starts, 60)
    lens = np.minimum(lens, 57)  # at most the block's width after the offset
    np.testing.assert_array_equal(C.x25_crc_block(block, 3, lens, 9), C.x25_crc_rows(block[:, 3:], lens, 9))


@pytest.mark.parametrize("name", ["HIGHRES_IMU", "ATTITUDE_QUATERNION", "ATTITUDE", "GLOBAL_POSITION_INT",
                                  "SYSTEM_TIME", "HEARTBEAT", "SCALED_IMU2", "RAW_IMU", "AHRS2"])
def test_vectorised_packer_is_byte_identical_to_pymavlink(name):
    from pymavlink.dialects.v20 import ardupilotmega as mav_dialect
    d = T.msgdef(name)
    rng = np.random.default_rng(2)
    n = 64
    raw = rng.integers(0, 256, (n, d.wire_len)).astype(np.uint8)
    raw[: n // 2, d.wire_len // 2:] = 0  # trailing zeros: MAVLink 2 truncation
    rec = raw.view(d.dtype).reshape(-1).copy()
    for f in d.dtype.names:  # no NaN payloads (NaN != NaN would make the comparison ambiguous)
        if rec[f].dtype.kind == "f":
            rec[f] = np.nan_to_num(rec[f], nan=1.5, posinf=2.5, neginf=-2.5)
    seq = np.arange(n) * 7 % 256
    recv = 1_700_000_000_000_000 + np.arange(n) * 5000
    rows, lens = T.pack_frames(d, rec, seq, 3, 7, recv)
    cls = mav_dialect.mavlink_map[d.id]
    mav = mav_dialect.MAVLink(None, srcSystem=3, srcComponent=7)
    for i in range(n):
        vals = {f: (rec[f][i].tolist() if rec[f].dtype.kind != "S" else rec[f][i]) for f in d.dtype.names}
        msg = cls(**{f: vals[f] for f in cls.fieldnames})
        mav.seq = int(seq[i])
        ref = msg.pack(mav)
        assert bytes(rows[i, 8:lens[i]]) == bytes(ref), f"{name} row {i}"
        assert int.from_bytes(bytes(rows[i, :8]), "big") == recv[i]


# ---- tlog round trips --------------------------------------------------------------------------------
@pytest.mark.parametrize("clock", ["epoch", "boot"])
def test_tlog_round_trip(tmp_path, clock):
    log = make_log(clock=clock)
    path = str(tmp_path / "unit.tlog")
    registry.write(path, log, "tlog")
    assert registry.detect(path).NAME == "tlog"
    back = registry.load(path)
    m = back.meta
    assert m.format == "tlog" and m.clock == clock and m.warnings == ()
    assert "imu=HIGHRES_IMU" in m.selector and "att=ATTITUDE_QUATERNION" in m.selector
    assert ("SYSTEM_TIME" in m.stamp_source) == (clock == "epoch")
    # IMU: float32 values, time_usec (us) stamps
    np.testing.assert_array_equal(abs_ns(back, back.t_imu_s()), abs_ns(log, log.t_imu_s()))
    np.testing.assert_allclose(back.gyro_rad_s(), log.gyro_rad_s().astype(np.float32), rtol=0, atol=1e-7)
    np.testing.assert_allclose(back.accel_m_s2(), log.accel_m_s2().astype(np.float32), rtol=0, atol=1e-6)
    # attitude (float32 quaternion, time_boot_ms mapped back through SYSTEM_TIME), vel (cm/s), pos. The
    # writer puts the whole milliseconds elapsed in time_boot_ms, as an autopilot's millis() does; the reader
    # takes the middle of that millisecond: these whole-ms instants come back half a millisecond later
    tq, q = back.quat_wxyz()
    np.testing.assert_array_equal(abs_ns(back, tq), abs_ns(log, log.quat_wxyz()[0]) + 500_000)
    assert quat_err(q, log.quat_wxyz()[1]) < 1e-12 + 1e-7
    tv, v = back.vel_ned_m_s()
    np.testing.assert_allclose(v, log.vel_ned_m_s()[1], atol=0.005 + 1e-9)
    tp, p = back.lat_lon_alt()
    np.testing.assert_allclose(p[:, :2], log.lat_lon_alt()[1][:, :2], atol=0.6e-7)
    np.testing.assert_allclose(p[:, 2], log.lat_lon_alt()[1][:, 2], atol=0.0005 + 1e-9)
    # the receive clock: message time + the writer's transport delay, on the UNIX clock
    rx = registry.load(path + "::time=receive")
    assert rx.meta.clock == "epoch" and "receive" in rx.meta.stamp_source
    rx_ns = abs_ns(rx, rx.t_imu_s())
    expect = abs_ns(log, log.t_imu_s()) + 5_000_000 + (0 if clock == "epoch" else T.RECEIVE_EPOCH_NS)
    np.testing.assert_array_equal(rx_ns, expect)


def test_tlog_selectors_and_euler_attitude(tmp_path):
    log = make_log()
    path = str(tmp_path / "unit.tlog")
    T.write(path, log)
    att = registry.load(path + "::imu=HIGHRES_IMU,att=ATTITUDE,vel=none,pos=none")
    assert att.has_quat and not att.has_vel and not att.has_pos
    assert quat_err(att.quat_wxyz()[1], log.quat_wxyz()[1]) < 1e-10 + 1e-6
    rates = registry.load(path + "::imu=ATTITUDE,att=none,vel=none,pos=none")  # body rates as gyro
    assert rates.has_gyro and not rates.has_accel
    g_at_nav = np.column_stack([np.interp(log.t_nav_s(), log.t_imu_s(), c) for c in log.gyro_rad_s().T])
    np.testing.assert_allclose(rates.gyro_rad_s(), g_at_nav, atol=1e-6)
    inst = registry.load(path + "::imu=HIGHRES_IMU[0]")
    assert len(inst.imu) == len(log.imu)
    with pytest.raises(InputError, match="no such instance"):
        registry.load(path + "::imu=HIGHRES_IMU[2]")
    with pytest.raises(InputError, match="SCALED_IMU3"):
        registry.load(path + "::imu=SCALED_IMU3")
    with pytest.raises(InputError, match="not one of"):
        registry.load(path + "::imu=BOGUS")
    with pytest.raises(InputError, match="time="):
        registry.load(path + "::time=never")
    inv = registry.inspect_log(path)
    names = {s.name: s for s in inv.streams}
    assert names["HIGHRES_IMU"].rate_hz == pytest.approx(200.0, rel=1e-6)
    assert names["ATTITUDE_QUATERNION"].count == len(log.nav)
    assert inv.selectors[0].startswith("imu=HIGHRES_IMU,att=ATTITUDE_QUATERNION")


def test_tlog_two_systems(tmp_path):
    a, b = make_log(seed=1), make_log(seed=2)
    pa, pb = tmp_path / "a.tlog", tmp_path / "b.tlog"
    T.write(str(pa), a, sysid=1)
    T.write(str(pb), b, sysid=2)
    both = tmp_path / "both.tlog"
    both.write_bytes(pa.read_bytes() + pb.read_bytes())
    inv = T.inventory(str(both))
    assert any("sysid=2" in s for s in inv.selectors) and any("sysid=1" in s for s in inv.selectors)
    two = registry.load(f"{both}::sysid=2")
    np.testing.assert_allclose(two.gyro_rad_s(), b.gyro_rad_s().astype(np.float32), atol=1e-7)
    one = registry.load(str(both))
    assert "sysid=1" in one.meta.selector and any("picked" in w for w in one.meta.warnings)
    np.testing.assert_allclose(one.gyro_rad_s(), a.gyro_rad_s().astype(np.float32), atol=1e-7)


def _compare_tlog_with_pymavlink(path: str) -> int:
    """Every frame the fast path keeps == pymavlink's decode, field for field, in file order."""
    ref = T.reference_messages(path)
    fr = T.read_frames(path)
    assert len(ref) == len(fr.msgid)
    decoded: list = [None] * len(fr.msgid)
    for mid in np.unique(fr.msgid):
        d = T.msgdef_by_id(int(mid))
        rows = np.flatnonzero(fr.msgid == mid)
        for i, r in zip(rows.tolist(), fr.decode(rows, d)):
            decoded[i] = (d, r)
    for k, msg in enumerate(ref):
        d, r = decoded[k]
        assert msg.get_type() == d.name
        assert msg.get_srcSystem() == fr.sysid[k] and msg.get_srcComponent() == fr.compid[k]
        assert abs(msg._timestamp * 1e6 - fr.recv_us[k]) < 1.0
        for f in d.dtype.names:
            a, b = getattr(msg, f), r[f]
            if isinstance(a, (str, bytes)):
                aa = a.encode("utf-8", "replace") if isinstance(a, str) else a
                assert aa.split(b"\0")[0] == bytes(b).split(b"\0")[0] or isinstance(a, str)
            elif isinstance(a, list):
                np.testing.assert_array_equal(np.array(a, dtype=b.dtype), b)
            else:
                assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), (d.name, f)
    return len(ref)


def test_tlog_fast_reader_matches_pymavlink_on_written_file(tmp_path):
    path = str(tmp_path / "unit.tlog")
    T.write(path, make_log(duration_s=3.0))
    assert _compare_tlog_with_pymavlink(path) > 900


# ---- DataFlash round trip ----------------------------------------------------------------------------
@pytest.mark.parametrize("clock", ["epoch", "boot"])
def test_dataflash_round_trip(tmp_path, clock):
    log = make_log(clock=clock)
    path = str(tmp_path / "unit.bin")
    registry.write(path, log, "dataflash")
    assert registry.detect(path).NAME == "dataflash"
    back = registry.load(path)
    assert back.meta.clock == clock and back.meta.format == "dataflash"
    assert back.meta.selector.startswith("imu=IMU,att=NKQ1,vel=NKF1")
    np.testing.assert_array_equal(abs_ns(back, back.t_imu_s()), abs_ns(log, log.t_imu_s()))
    np.testing.assert_allclose(back.gyro_rad_s(), log.gyro_rad_s().astype(np.float32), atol=1e-7)
    assert quat_err(back.quat_wxyz()[1], log.quat_wxyz()[1]) < 1e-7
    np.testing.assert_allclose(back.vel_ned_m_s()[1], log.vel_ned_m_s()[1], atol=1e-5)
    np.testing.assert_allclose(back.lat_lon_alt()[1][:, 2], log.lat_lon_alt()[1][:, 2], atol=0.005 + 1e-9)
    euler = registry.load(path + "::imu=IMU,att=NKF1,vel=none,pos=none")  # centidegree Euler angles
    assert quat_err(euler.quat_wxyz()[1], log.quat_wxyz()[1]) < 1e-7
    boot = registry.load(path + "::time=boot")
    assert boot.meta.clock == "boot"


def _same(a, b) -> bool:
    if isinstance(a, bytes):
        return a.rstrip(b"\0") == bytes(b).rstrip(b"\0")
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    if not isinstance(a, (int, float)):  # 'a' arrays
        return list(a) == list(b)
    return a == b


def _compare_dataflash_with_dfreader(path: str, scaled_every: int = 1) -> int:
    """Every record == DFReader's, in file order: raw elements for all, scaled values (pymavlink's
    multipliers, string decoding) for every ``scaled_every``-th message."""
    log = D.read_log(path)
    ref = D.reference_messages(path)
    offs = np.concatenate(list(log.offsets.values()))
    typ = np.concatenate([np.full(len(o), t) for t, o in log.offsets.items()])
    order = np.argsort(offs)
    recs = {t: log.records(f.name) for t, f in log.formats.items()
            if t in log.offsets and log.by_name.get(f.name) is f}
    lists = {t: r.tolist() for t, r in recs.items()}
    seen: dict[int, int] = {}
    assert len(ref) == len(order)
    for n, (msg, k) in enumerate(zip(ref, order.tolist())):
        t = int(typ[k])
        i = seen.get(t, 0)
        seen[t] = i + 1
        f = log.formats[t]
        assert msg.get_type() == f.name
        if t not in recs or f.name == "FMT":
            continue
        assert all(_same(a, b) for a, b in zip(msg._elements, lists[t][i])), (f.name, i)
        if n % scaled_every:
            continue
        r = recs[t][i]
        for col in f.columns:
            if col not in msg._fieldnames:
                continue
            a = getattr(msg, col)
            c = f.fmt[f.columns.index(col)]
            if isinstance(a, str):
                raw = r[col].split(b"\0")[0]
                try:
                    b = raw.decode("utf-8")
                except UnicodeDecodeError:
                    b = raw.decode("ISO-8859-1")
                assert a == b
            elif c == "a":
                np.testing.assert_array_equal(np.array(a), r[col])
            else:
                v = log.column(f.name, r.reshape(1), col)[0] if D.DF_TYPES[c][1] else r[col].item()
                assert a == v or (isinstance(a, float) and math.isnan(a) and math.isnan(v)), (f.name, col)
    return len(ref)


def test_dataflash_fast_reader_matches_dfreader_on_written_file(tmp_path):
    path = str(tmp_path / "unit.bin")
    D.write(path, make_log(duration_s=3.0))
    assert _compare_dataflash_with_dfreader(path) > 700


# ---- real logs ---------------------------------------------------------------------------------------
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="../shared/realdata absent")

#: MANIFEST.md: IMU rate, approx. duration, EKF messages (cores), other streams
DF_EXPECT = {
    "arduplane_box_pilot.BIN": (50.0, 92.0, ("NKF1", "NKF6", "XKF1", "XKF6"), {"ATT": 25.0, "AHR2": 25.0, "GPS": 5.0}),
    "arduplane_elevator.BIN": (50.0, 64.0, ("NKF1", "NKF6", "XKF1", "XKF6"), {"ATT": 25.0}),
    "arducopter_log0036.bin": (25.0, 151.0, ("NKF1", "NKF6"), {"ATT": 10.0, "AHR2": 10.0, "GPS": 5.0}),
    "arducopter_2014-10-18_20-04-24.bin": (50.0, 333.0, (), {"ATT": 10.0, "GPS": 5.0}),
}


@needs_real
@pytest.mark.realdata
@pytest.mark.parametrize("fname", sorted(DF_EXPECT))
def test_real_dataflash_logs(fname):
    path = REAL / fname
    if not path.exists():
        pytest.skip(f"{fname} absent")
    imu_hz, dur_s, ekf, others = DF_EXPECT[fname]
    inv = registry.inspect_log(str(path))
    assert inv.format == "dataflash"
    streams = {s.name: s for s in inv.streams}
    for name in ("IMU", "IMU2"):
        assert streams[name].rate_hz == pytest.approx(imu_hz, rel=0.02)
        assert dur_s - 6 < streams[name].duration_s <= dur_s + 1
    for name in ekf:
        assert streams[name].count > 100
    for name, hz in others.items():
        assert streams[name].rate_hz == pytest.approx(hz, rel=0.03)
    for i, core in enumerate(ekf[:2]):  # IMU k with EKF core k: a complete unit each
        log = registry.load(f"{path}::imu={'IMU' if i == 0 else 'IMU2'},nav={core}")
        assert log.has_gyro and log.has_accel and log.has_quat and log.has_vel
    # parser-level gyro sign sanity: IMU and IMU2 of one board agree in sign and magnitude
    a = registry.load(f"{path}::imu=IMU,att=none")
    b = registry.load(f"{path}::imu=IMU2,att=none")
    assert a.meta.t0_ns == b.meta.t0_ns or abs(a.meta.t0_ns - b.meta.t0_ns) < 1e9
    gb = np.column_stack([np.interp(a.t_imu_s(), b.rebased(a.meta.t0_ns).t_imu_s(), c)
                          for c in b.gyro_rad_s().T])
    ga = a.gyro_rad_s()
    for ax in range(3):
        if np.std(ga[:, ax]) > 0.05:  # an axis that moved
            corr = np.corrcoef(ga[:, ax], gb[:, ax])[0, 1]
            assert corr > 0.9, (fname, ax, corr)
            assert np.std(gb[:, ax]) / np.std(ga[:, ax]) == pytest.approx(1.0, abs=0.15)
    # ArduCopter 3.1 stamps in whole milliseconds (TimeMS), later versions in microseconds (TimeUS)
    assert a.stamp_resolution_s("gyro") == (1e-3 if fname.startswith("arducopter_2014") else 0.0)
    if fname != "arduplane_elevator.BIN":  # no GPS there: stays on boot time
        assert a.meta.clock == "epoch" and "GPS" in a.meta.stamp_source
    else:
        assert a.meta.clock == "boot"


@needs_real
@pytest.mark.realdata
@pytest.mark.parametrize("fname", ["arducopter_2014-10-18_20-04-24.bin", "arduplane_box_pilot.BIN"])
def test_real_dataflash_fast_reader_matches_dfreader(fname):
    path = REAL / fname
    if not path.exists():
        pytest.skip(f"{fname} absent")
    assert _compare_dataflash_with_dfreader(str(path), scaled_every=7) > 40_000


@needs_real
@pytest.mark.realdata
def test_real_sitl_tlog():
    path = REAL / "sitl_vtol.tlog"
    if not path.exists():
        pytest.skip("sitl_vtol.tlog absent")
    inv = registry.inspect_log(str(path))
    assert inv.format == "tlog"
    streams = {s.name: s for s in inv.streams}
    for name in ("RAW_IMU", "SCALED_IMU2", "ATTITUDE", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"):
        assert streams[name].rate_hz == pytest.approx(4.0, abs=0.5)
        assert streams[name].duration_s == pytest.approx(208.0, abs=2.0)
    assert "imu=RAW_IMU,att=ATTITUDE" in inv.selectors[0]
    assert any(s.startswith("imu=SCALED_IMU2,att=AHRS2") for s in inv.selectors)
    log = registry.load(str(path))
    assert log.meta.clock == "epoch" and "SYSTEM_TIME" in log.meta.stamp_source
    assert log.duration_s == pytest.approx(208.0, abs=2.0)
    # at rest on the ground at first: specific force ~ -g on z (FRD), units mG -> m/s^2 right
    assert np.median(log.accel_m_s2()[:20, 2]) == pytest.approx(-9.8, abs=0.3)
    two = registry.load(f"{path}::imu=SCALED_IMU2,att=AHRS2")
    assert two.has_quat and any("without a time field" in w for w in two.meta.warnings)
    # AHRS2 alone (no timed stream to map its receive stamps by) was a KeyError; now receive time as is
    alone = registry.load(f"{path}::imu=none,att=AHRS2")
    assert alone.has_quat and not alone.has_gyro and alone.meta.clock == "epoch"
    assert any("tlog's receive time" in w for w in alone.meta.warnings)
    assert _compare_tlog_with_pymavlink(str(path)) == 23894


# ---- damaged and bad input -----------------------------------------------------------------------------
def _cli_inspect(path: str, capsys) -> tuple[int, str, str]:
    code = cli_main(["inspect", path])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("ext", [".tlog", ".bin"])
def test_empty_and_random_files_exit_2(tmp_path, capsys, ext):
    empty = tmp_path / f"empty{ext}"
    empty.write_bytes(b"")
    code, _, err = _cli_inspect(str(empty), capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "empty" in err and str(empty) in err
    rnd = tmp_path / f"random{ext}"
    rnd.write_bytes(np.random.default_rng(3).integers(0, 256, 20000).astype(np.uint8).tobytes())
    code, _, err = _cli_inspect(str(rnd), capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and str(rnd) in err
    assert "Traceback" not in err
    with pytest.raises(InputError):
        registry.load(str(rnd))


def test_tlog_cut_anywhere_in_its_last_record_is_called_truncated(tmp_path):
    """A tlog cut at every byte of a record (its stamp, its MAVLink 2 header, its payload, its CRC) keeps
    the records before it and says the file is truncated; the 8-byte stamp and the first bytes of a MAVLink 2
    header (16-19 bytes, more than the smallest MAVLink 1 frame) were counted as damaged bytes skipped."""
    log = make_log(duration_s=2.0)
    good = tmp_path / "good.tlog"
    T.write(str(good), log)
    data = good.read_bytes()
    fr = T.read_frames(str(good))
    k = len(fr.pay) // 2
    assert fr.v2[k]
    start = int(fr.pay[k]) - 10 - 8  # (the record: stamp, then the 10-byte MAVLink 2 header)
    size = 8 + 10 + int(fr.plen[k]) + 2
    cut = tmp_path / "cut.tlog"
    for extra in range(1, size):
        cut.write_bytes(data[:start + extra])
        back = T.read_frames(str(cut))
        assert len(back.pay) == k, extra
        assert any("truncated" in w for w in back.warnings), (extra, back.warnings)
        assert not any("bad bytes" in w for w in back.warnings), (extra, back.warnings)


def test_tlog_truncated_and_flipped_byte(tmp_path, capsys):
    log = make_log(duration_s=4.0)
    good = tmp_path / "good.tlog"
    T.write(str(good), log)
    data = good.read_bytes()
    n_ref = len(T.load(str(good), Selector()).imu)
    # truncated in the middle of a frame: the readable part is used, the damage reported
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 7])
    half = registry.load(str(cut))
    assert 0.4 * n_ref < len(half.imu) < 0.6 * n_ref
    assert any("truncated" in w for w in half.meta.warnings)
    code, out, _ = _cli_inspect(str(cut), capsys)
    assert code == 0 and "truncated" in out
    # a few bytes only: not recognisable, one line, exit 2
    tiny = tmp_path / "tiny.tlog"
    tiny.write_bytes(data[:12])
    code, _, err = _cli_inspect(str(tiny), capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    # one flipped byte inside an IMU payload in the middle: that frame dropped (bad CRC), rest used
    fr = T.read_frames(str(good))
    imu_rows = fr.rows(T.msgdef("HIGHRES_IMU").id)
    k = imu_rows[len(imu_rows) // 2]
    flipped = bytearray(data)
    flipped[int(fr.pay[k]) + 10] ^= 0xFF
    bad = tmp_path / "flipped.tlog"
    bad.write_bytes(bytes(flipped))
    one = registry.load(str(bad))
    assert len(one.imu) == n_ref - 1
    assert any("bad CRC" in w for w in one.meta.warnings)
    # a flipped magic byte: the walker skips to the next frame and says so
    flipped = bytearray(data)
    flipped[int(fr.pay[k]) - 10] ^= 0xFF  # the 0xFD of that frame
    bad.write_bytes(bytes(flipped))
    two = registry.load(str(bad))
    assert len(two.imu) == n_ref - 1 and any("skipped" in w for w in two.meta.warnings)


@pytest.mark.parametrize("jump_us", [2 ** 32, 2 ** 28])
def test_tlog_one_damaged_receive_stamp_loses_one_record_not_the_rest(tmp_path, jump_us):
    """The 8-byte receive stamp is outside the frame's CRC: a flipped high byte makes one stamp jump
    forward (here by about 72 min or 4.5 min). Taken as the reference, it made every later stamp a step back
    beyond the limit, and the walker skipped the rest of the file byte by byte (one flipped byte lost 97 %
    of a 40 s tlog). That record alone is dropped now."""
    log = make_log(duration_s=4.0)
    good = tmp_path / "good.tlog"
    T.write(str(good), log)
    data = good.read_bytes()
    n_ref = len(T.load(str(good), Selector()).imu)
    from parsers.mavlink_common import walk_tlog

    starts = walk_tlog(np.frombuffer(data, np.uint8))[0]  # record starts: the 8-byte stamp, then the frame
    at = int(starts[len(starts) // 3])
    flipped = bytearray(data)
    old = int.from_bytes(flipped[at:at + 8], "big")
    flipped[at:at + 8] = (old + jump_us).to_bytes(8, "big")  # one bit of a high byte set
    bad = tmp_path / "stamp.tlog"
    bad.write_bytes(bytes(flipped))
    one = registry.load(str(bad))
    assert n_ref - 1 <= len(one.imu) <= n_ref
    assert one.duration_s == pytest.approx(registry.load(str(good)).duration_s, abs=0.05)
    assert any("skipped" in w for w in one.meta.warnings)


def test_dataflash_damage_reported(tmp_path, capsys):
    log = make_log(duration_s=4.0)
    good = tmp_path / "good.bin"
    D.write(str(good), log)
    data = good.read_bytes()
    n_ref = len(D.load(str(good), Selector()).imu)
    dl = D.read_log(str(good))
    imu_offs = dl.offsets[dl.by_name["IMU"].type]
    k = int(imu_offs[len(imu_offs) // 2])
    flipped = bytearray(data)
    flipped[k] ^= 0xFF  # header byte of one IMU record in the middle
    bad = tmp_path / "flipped.bin"
    bad.write_bytes(bytes(flipped))
    back = registry.load(str(bad))
    assert len(back.imu) == n_ref - 1
    assert any("skipped" in w and "bad bytes" in w for w in back.meta.warnings)
    code, out, _ = _cli_inspect(str(bad), capsys)
    assert code == 0 and "skipped" in out
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[: len(data) // 2 + 5])
    half = registry.load(str(cut))
    assert 0.4 * n_ref < len(half.imu) < 0.6 * n_ref
    assert any("truncated" in w for w in half.meta.warnings)
    with pytest.raises(InputError, match="no IMU3 messages") as exc:
        registry.load(f"{good}::imu=IMU3")
    assert str(good) in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(InputError, match="no instance field"):
        registry.load(f"{good}::imu=IMU[1]")


def test_missing_selector_stream_is_one_line_exit_2(tmp_path, capsys):
    path = tmp_path / "unit.tlog"
    T.write(str(path), make_log(duration_s=2.0))
    with pytest.raises(InputError) as exc:
        registry.load(f"{path}::imu=SCALED_IMU2")
    assert exc.value.exit_code == 2 and str(path) in str(exc.value) and "\n" not in str(exc.value)
    assert "SCALED_IMU2" in str(exc.value)
    bpath = tmp_path / "unit.bin"
    D.write(str(bpath), make_log(duration_s=2.0))
    for arg in (f"{path}::imu=SCALED_IMU2", f"{bpath}::nav=XKF1[1]", f"{path}::bogus=1"):
        code = cli_main(["inspect", arg])
        out, err = capsys.readouterr()
        assert code == 2, arg
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
        assert str(path if arg.startswith(str(path)) else bpath) in err
    assert cli_main(["inspect", f"{bpath}::imu=IMU,nav=NKF1"]) == 0
    assert "NKF1" in capsys.readouterr().out


def test_sniffers_are_exclusive(tmp_path):
    log = make_log(duration_s=1.0)
    T.write(str(tmp_path / "a.tlog"), log)
    D.write(str(tmp_path / "a.bin"), log)
    ta = (tmp_path / "a.tlog").read_bytes()[:8192]
    da = (tmp_path / "a.bin").read_bytes()[:8192]
    assert T.sniff(ta, "a.tlog") and not D.sniff(ta, "a.tlog")
    assert D.sniff(da, "a.bin") and not T.sniff(da, "a.bin")
    os.replace(tmp_path / "a.tlog", tmp_path / "renamed.bin")  # content decides, not the name
    assert registry.detect(str(tmp_path / "renamed.bin")).NAME == "tlog"


def test_dataflash_instance_selector(tmp_path):
    a, b = make_log(duration_s=2.0, seed=4), make_log(duration_s=2.0, seed=5)
    pa, pb = tmp_path / "a.bin", tmp_path / "b.bin"
    D.write(str(pa), a, imu_instance=0)
    D.write(str(pb), b, imu_instance=1)
    both = tmp_path / "new.bin"
    both.write_bytes(pa.read_bytes() + pb.read_bytes())
    inv = registry.inspect_log(str(both))
    names = [s.name for s in inv.streams]
    assert "IMU[0]" in names and "IMU[1]" in names
    assert any(s.startswith("imu=IMU[1]") for s in inv.selectors)
    one = registry.load(f"{both}::imu=IMU[1],att=none")
    np.testing.assert_allclose(one.gyro_rad_s(), b.gyro_rad_s().astype(np.float32), atol=1e-7)
    with pytest.raises(InputError, match=r"IMU\[7\]"):
        registry.load(f"{both}::imu=IMU[7]")


@pytest.mark.skipif(not C.HAVE_NUMBA, reason="numba absent: the plain Python walkers are the only path")
def test_python_walkers_equal_compiled(tmp_path):
    path = tmp_path / "unit.tlog"
    T.write(str(path), make_log(duration_s=1.0))
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x5A
    data[len(data) // 3] ^= 0xFF
    buf = np.frombuffer(bytes(data[:-5]), dtype=np.uint8)
    fast = C.walk_tlog(buf)
    slow = C._walk_tlog_impl.py_func(bytes(buf))
    np.testing.assert_array_equal(fast[0], slow[0])
    assert fast[1:] == tuple(slow[1:])
    damaged = tmp_path / "damaged.tlog"
    damaged.write_bytes(bytes(data[:-5]))
    a, b = T.read_frames(str(damaged), engine="numba"), T.read_frames(str(damaged), engine="numpy")
    for k in ("recv_us", "v2", "plen", "sysid", "compid", "msgid", "pay"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert a.warnings == b.warnings and a.n_corrupt == b.n_corrupt >= 1
    bpath = tmp_path / "unit.bin"
    D.write(str(bpath), make_log(duration_s=1.0))
    data = bytearray(bpath.read_bytes())
    data[len(data) // 2] ^= 0xFF
    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    fmts, _ = D.find_formats(buf)
    lengths = np.zeros(256, dtype=np.int64)
    for t, f in fmts.items():
        lengths[t] = f.length
    fast = C.walk_dataflash(buf, lengths)
    slow = C._walk_df_impl.py_func(bytes(buf), [int(x) for x in lengths])
    np.testing.assert_array_equal(fast[0], slow[0])
    assert fast[1:] == tuple(slow[1:])


@pytest.mark.parametrize("fmt", ["tlog", "dataflash"])
def test_simulated_slave_round_trip(tmp_path, fmt):
    """logtools.sim's slave (stamps not on whole ms) -> tlog / .bin -> same numbers: IMU stamps to
    the microsecond, nav stamps to the format's millisecond (tlog time_boot_ms), values float32."""
    sim = pytest.importorskip("logtools.sim")
    slave = sim.simulate(sim.scenario_config("aircraft", duration_s=8.0)).slave
    path = str(tmp_path / ("slave.tlog" if fmt == "tlog" else "slave.bin"))
    registry.write(path, slave, fmt)
    back = registry.load(path)
    assert back.meta.clock == slave.meta.clock
    d_us = np.abs(abs_ns(back, back.t_imu_s()) - abs_ns(slave, slave.t_imu_s()))
    assert d_us.max() <= 500  # rounded to whole microseconds
    np.testing.assert_allclose(back.gyro_rad_s(), slave.gyro_rad_s().astype(np.float32), atol=1e-7)
    np.testing.assert_allclose(back.accel_m_s2(), slave.accel_m_s2().astype(np.float32), atol=1e-6)
    tq, q = back.quat_wxyz()
    t_ref, q_ref = slave.quat_wxyz()
    dt_ns = np.abs(abs_ns(back, tq) - abs_ns(slave, t_ref))
    assert dt_ns.max() <= (500_000 if fmt == "tlog" else 500)
    assert quat_err(q, q_ref) < 1e-7


# ---- DataFlash: corrupt time fields (a damaged log) keep the stamps sane, the clock honest -------------
def _patch_df(path: Path, name: str, field: str, values: dict[int, int]) -> None:
    """Overwrite ``field`` of the ``name`` records numbered in ``values`` (record index -> raw value)."""
    dl = D.read_log(str(path))
    f = dl.by_name[name]
    ftype, at = f.dtype.fields[field][:2]
    offs = dl.offsets[f.type]
    data = bytearray(path.read_bytes())
    for i, v in values.items():
        p = int(offs[i]) + 3 + at
        data[p:p + ftype.itemsize] = np.array(v).astype(ftype).tobytes()  # (wraps as a flipped byte would)
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def sim_pair():
    sim = pytest.importorskip("logtools.sim")
    return sim.simulate(sim.scenario_config("aircraft", duration_s=30.0))


def test_dataflash_corrupt_stamps_and_gps_times_keep_the_log_on_its_true_span(tmp_path, sim_pair):
    """A damaged DataFlash log: IMU/NKQ1 TimeUS with corrupt high bytes (9e15 us fits int64 ns but
    overflowed once the GPS boot->UNIX offset was added before the stray stamps were dropped: a master at
    -1.7e10 s in the fuzzer's case 0228), GPS fixes with an impossible week, ms of week or boot stamp, or a
    week inconsistent with the others. The bad samples and fixes go, the log stays on UNIX time within its
    true span, and the latency comes out right."""
    from logtools.latency import estimate

    slave = sim_pair.slave
    path = tmp_path / "damaged.bin"
    D.write(str(path), slave)
    ref = D.load(str(path), Selector())  # undamaged (the writer's GPS ms put it 0.26 ms off the simulation)
    n = len(slave.imu)
    _patch_df(path, "IMU", "TimeUS", {n // 3: 9_000_000_000_000_000, n // 2: 2**64 - 5000})
    _patch_df(path, "NKQ1", "TimeUS", {700: 9_100_000_000_000_000})
    _patch_df(path, "GPS", "GWk", {5: 65535, 12: 2400})
    _patch_df(path, "GPS", "GMS", {9: 4_000_000_000})
    _patch_df(path, "GPS", "TimeUS", {15: 2**64 - 1})
    back = D.load(str(path), Selector())
    assert back.meta.clock == "epoch" and back.meta.selector.endswith("time=gps")
    assert back.meta.t0_ns == ref.meta.t0_ns  # the undamaged log's first sample and clock
    assert back.span_s() == ref.span_s()
    assert len(back.imu) == n - 2
    warns = " ".join(back.meta.warnings)
    assert "impossible stamps dropped" in warns and "GPS: 4 of" in warns
    res = estimate(sim_pair.master, back, compare=False)
    assert res.latency_s == pytest.approx(sim_pair.truth.latency_s, abs=0.5e-3)


@pytest.mark.parametrize("how", ["week_65535", "disagree"])
def test_dataflash_gps_time_without_a_trustworthy_offset_stays_on_the_boot_clock(tmp_path, how):
    """GPS week/ms that give no offset to trust (every week 65535: int64 overflow in the GPS -> UNIX
    conversion; or no majority agreeing): boot clock with a warning naming the problem, not garbage."""
    log = make_log(duration_s=4.0)
    path = tmp_path / f"{how}.bin"
    D.write(str(path), log)
    n_gps = len(D.read_log(str(path)).records("GPS"))
    rng = np.random.default_rng(3)
    weeks = np.full(n_gps, 65535) if how == "week_65535" else rng.integers(1, 6000, n_gps)
    _patch_df(path, "GPS", "GWk", dict(enumerate(weeks.tolist())))
    back = D.load(str(path), Selector())
    assert back.meta.clock == "boot" and back.meta.selector.endswith("time=boot")
    assert any("no trustworthy boot->UNIX offset" in w and "kept on the boot clock" in w for w in back.meta.warnings)
    assert back.duration_s == pytest.approx(log.duration_s, abs=0.01)
    assert 9.0 < back.meta.t0_ns * 1e-9 < 11.0  # boot time: the writer's boot 0 is 10 s before the log
    inv = D.inventory(str(path))
    assert any("no trustworthy offset" in x for x in inv.notes)


# ---- the reader's windowed scan: the same frames as one walk of the whole file -------------------------
@pytest.mark.parametrize("window", [997, 4096, 1 << 20])
@pytest.mark.parametrize("engine", ["auto", "numpy"])
def test_windowed_scan_equals_whole_file_walk(tmp_path, window, engine):
    """scan_frames walks the file in windows (pages let go behind it), keeping only what the reader reads:
    the catalog, the records of its messages, the damage warnings all as read_frames (one walk of the
    whole file) gives them, on a damaged file too (resyncs, bad CRCs, a truncated last frame)."""
    path = tmp_path / "unit.tlog"
    T.write(str(path), make_log(duration_s=3.0))
    data = bytearray(path.read_bytes())
    for at in (len(data) // 2, len(data) // 3, len(data) // 5 + 7):
        data[at] ^= 0x5A
    damaged = tmp_path / "damaged.tlog"
    damaged.write_bytes(bytes(data[:-5]))
    for p in (path, damaged):
        fr = T.read_frames(str(p), engine=engine)
        st = T.scan_frames(str(p), engine=engine, window=window)
        assert st.counts == T.catalog(fr).counts
        assert st.n_valid == len(fr.msgid) and st.warnings == fr.warnings and st.n_corrupt == fr.n_corrupt
        assert set(st.by_id) == set(np.unique(fr.msgid).tolist()) & set(T._kind_ids())
        for mid, mf in st.by_id.items():
            rows = np.flatnonzero(fr.msgid == mid)
            np.testing.assert_array_equal(mf.rec, fr.decode(rows, T.msgdef_by_id(mid)))
            np.testing.assert_array_equal(mf.recv_us, fr.recv_us[rows])
            np.testing.assert_array_equal(mf.sysid, fr.sysid[rows])
            np.testing.assert_array_equal(mf.compid, fr.compid[rows])
        proj = T.scan_frames(str(p), engine=engine, window=window, project=True)
        for mid, mf in proj.by_id.items():
            for name in mf.rec.dtype.names:
                np.testing.assert_array_equal(mf.rec[name], st.by_id[mid].rec[name])
    assert any("damaged" in w for w in T.scan_frames(str(damaged), window=window).warnings)


def test_windowed_walk_python_equals_compiled(tmp_path):
    path = tmp_path / "unit.tlog"
    T.write(str(path), make_log(duration_s=1.0))
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x5A
    buf = np.frombuffer(bytes(data[:-5]), dtype=np.uint8)
    whole = C.walk_tlog(buf)
    py = getattr(C._walk_tlog_part, "py_func", C._walk_tlog_part)
    i, in_sync, prev_t, starts, skipped, resyncs = 0, False, -1, [], 0, 0
    while True:  # 1000-byte windows through the plain Python walker
        stop = len(buf) if len(buf) - i <= 1000 + 1024 else i + 1000
        s, sk, rs, i, in_sync, prev_t = py(bytes(buf), i, stop, in_sync, prev_t, bool(starts))
        starts += list(s)
        skipped += sk
        resyncs += rs
        if stop == len(buf):
            break
    np.testing.assert_array_equal(np.asarray(starts, np.int64), whole[0])
    assert (skipped, resyncs, len(buf) - i) == tuple(whole[1:])


def _tlog_variants(tmp_path) -> dict[str, bytes]:
    path = tmp_path / "unit.tlog"
    T.write(str(path), make_log(duration_s=1.0))
    clean = path.read_bytes()
    frames = getattr(C._walk_tlog_impl, "py_func", C._walk_tlog_impl)(clean)[0]
    mid = int(frames[len(frames) // 2])
    late = bytearray(clean)  # every stamp from the middle on 2 min later: a gap (the careful walk's case)
    for st in frames[frames >= mid]:
        t = int.from_bytes(late[st:st + 8], "big") + 120_000_000
        late[st:st + 8] = t.to_bytes(8, "big")
    flipped = bytearray(clean)
    flipped[len(clean) // 2] ^= 0x5A
    return {"clean": clean, "cut": clean[:-5], "flipped": bytes(flipped), "gap": bytes(late),
            "garbage first": b"\x01\x02\x03" + clean, "stamp back": clean[mid:] + clean[:mid]}


def test_the_python_chain_walk_is_the_careful_walk_where_it_answers(tmp_path):
    """The plain Python code's tlog walk follows the chain of frame sizes and checks the stamps at once
    (mavlink_common._walk_tlog_chain) and leaves everything else to the careful walk: where it answers, its
    answer is the careful walk's, whole file or window by window; on an undamaged log it answers."""
    careful = getattr(C._walk_tlog_part, "py_func", C._walk_tlog_part)
    answered = set()
    for name, data in _tlog_variants(tmp_path).items():
        for window in (None, 997, 5000):
            i, in_sync, prev_t, found = 0, False, -1, False
            while True:
                stop = len(data) if window is None or len(data) - i <= window + 1024 else i + window
                args = (data, i, stop, in_sync, prev_t, found)
                ref = careful(*args)
                got = C._walk_tlog_chain(*args)
                if got is not None:
                    answered.add(name)
                    np.testing.assert_array_equal(got[0], ref[0])
                    assert tuple(got[1:]) == tuple(ref[1:]), (name, window, i)
                _, _, _, i, in_sync, prev_t = ref
                found = found or len(ref[0]) > 0
                if stop == len(data):
                    break
    assert "clean" in answered
    for name, data in _tlog_variants(tmp_path).items():  # and the whole-file walk of the plain code
        buf = np.frombuffer(data, np.uint8)
        ref = getattr(C._walk_tlog_impl, "py_func", C._walk_tlog_impl)(data)
        chain = C._walk_tlog_chain(data, 0, len(data), False, -1, False)
        if name == "clean" or name in ("cut", "gap", "garbage first"):  # (a flipped byte in a
            assert (chain is not None) == (name == "clean"), name  # payload leaves the framing as it was)
        if chain is not None:
            np.testing.assert_array_equal(chain[0], ref[0])
            assert (chain[1], chain[2], len(data) - chain[3]) == tuple(ref[1:])
        assert len(buf) == len(data)


@pytest.mark.parametrize("block", [1, 3, 7, 4096])
def test_fmt_search_by_blocks_finds_every_header_a_whole_file_search_finds(tmp_path, monkeypatch, block):
    log = make_log(duration_s=2.0)
    path = tmp_path / "unit.bin"
    registry.write(str(path), log, "dataflash")
    buf = np.frombuffer(path.read_bytes() + b"\xa3\x95\x80", np.uint8)  # one more header, at the very end
    whole = np.flatnonzero((buf[:-2] == D.HEAD1) & (buf[1:-1] == D.HEAD2) & (buf[2:] == D.FMT_TYPE))
    monkeypatch.setattr(D, "_SEARCH_BLOCK", block)
    np.testing.assert_array_equal(D._find_header(buf, D.FMT_TYPE), whole)
    assert len(whole) > 5 and whole[-1] == len(buf) - 3


@pytest.mark.parametrize("ekf,inst,quat", [("XKF1", 0, ("XKQ", 0)), ("XKF1", 1, ("XKQ", 1)), ("NKF1", 1, ("NKQ", 1)),
                                           ("XKF6", None, ("XKQ", 1))])
def test_an_ekf_cores_attitude_is_its_instanced_quaternion(ekf, inst, quat):
    """Newer logs write one XKF1/XKQ per core with the core in field C: nav=XKF1[1] takes XKQ[1] (a
    quaternion), not XKF1's centidegree Euler angles."""
    class Log:
        def has(self, name):
            return name in ("XKF1", "XKF6", "XKQ", "NKF1", "NKQ", "IMU")

    q = D._quat_source(Log(), D.Src(ekf, inst))
    assert q is not None and (q.name, q.inst) == quat


def test_a_telemetry_streams_bursts_are_no_gaps_a_dropout_is():
    """A tlog's AHRS2 arrives in pairs 9 ms apart every 0.47 s: against its median step (9 ms) every pair was
    a gap (288 of them in a real SITL log); against its typical step none is, and a 4 s dropout still is."""
    from parsers.assemble import gap_warning

    t = np.sort(np.concatenate([np.arange(100) * 0.47, np.arange(100) * 0.47 + 0.009]))
    assert gap_warning("quat (AHRS2)", np.diff(np.round(t * 1e9))) is None
    t = np.concatenate([t[:100], t[100:] + 4.0])
    assert gap_warning("quat (AHRS2)", np.diff(np.round(t * 1e9))) == \
        "quat (AHRS2): 1 gap(s) in stamps, longest 4.461 s"


def test_the_dialect_table_is_pymavlinks_read_from_the_cache_and_made_anew_when_stale(tmp_path, monkeypatch):
    """The reader's table of pymavlink's dialect (id -> name, CRC extra, wire format, field names) is kept in
    tapost's cache directory (importing the dialect costs about 30 ms a run): made and written the first time,
    read back as the same table, made anew where the file is stale or unreadable, the message layouts and
    CRC extras those of pymavlink's classes."""
    from pymavlink.dialects.v20 import ardupilotmega

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    want = T.dialect_table_from_module(ardupilotmega)
    path = tmp_path / "tapost" / "mavlink-dialect.json"
    try:
        T._table.cache_clear()
        assert T._table() == want and path.exists()
        T._table.cache_clear()
        assert T._table() == want  # (read from the file)
        for junk in ('{"key": "stale", "by_id": {}, "by_name": {}}', "{not json"):
            path.write_text(junk)
            T._table.cache_clear()
            assert T._table() == want and "stale" not in path.read_text()
        for cls in (ardupilotmega.MAVLink_highres_imu_message, ardupilotmega.MAVLink_attitude_quaternion_message):
            T.msgdef.cache_clear()
            T.msgdef_by_id.cache_clear()
            d = T.msgdef(cls.msgname)
            assert (d.id, d.crc_extra, d.wire_len) == (cls.id, cls.crc_extra, C.dtype_from_struct(
                cls.unpacker.format, list(cls.ordered_fieldnames)).itemsize)
        T._crc_extra_table.cache_clear()
        tab = T._crc_extra_table()
        assert all(tab[mid] == cls.crc_extra for mid, cls in ardupilotmega.mavlink_map.items())
    finally:
        for f in (T._table, T.msgdef, T.msgdef_by_id, T._crc_extra_table):
            f.cache_clear()
