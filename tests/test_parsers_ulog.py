"""PX4 ULog: round trips through our writer, pyulog as the reference reader, selectors, damage, real log."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from logtools.conventions import G0_M_S2, quat_from_euler, quat_rotate
from logtools.errors import InputError
from logtools.inslog import InsLog, LogMeta
from parsers import registry, ulog
from parsers.base import Selector

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
PX4_SAMPLE = REAL / "px4_sample.ulg"
EPOCH_T0_NS = 1_700_000_000_123_456_000


def make_log(duration_s: float = 20.0, clock: str = "epoch", imu_hz: float = 200.0, nav_hz: float = 50.0,
             t0_ns: int = EPOCH_T0_NS) -> InsLog:
    """A small InsLog with motion on every channel (truth for the round trips)."""
    ti = np.arange(0.0, duration_s, 1.0 / imu_hz)
    tn = np.arange(0.0, duration_s, 1.0 / nav_hz)
    gyro = np.c_[0.3 * np.sin(ti), 0.2 * np.cos(0.7 * ti), 0.1 * np.sin(0.3 * ti)]
    acc = np.c_[0.5 * np.cos(ti), 0.2 * np.sin(ti), -G0_M_S2 + 0.1 * np.sin(2 * ti)]
    q = quat_from_euler(np.c_[0.1 * np.sin(tn), 0.2 * np.cos(tn), 0.05 * tn])
    vel = np.c_[5 * np.sin(0.1 * tn), 5 * np.cos(0.1 * tn), 0.1 * tn]
    llh = np.c_[45.0 + 1e-5 * tn, 7.0 + 2e-5 * tn, 120.0 - 0.1 * tn]
    meta = LogMeta(source_path="sim", format="sim", clock=clock, t0_ns=t0_ns if clock == "epoch" else 5_000_000_000)
    return InsLog.from_arrays(meta, ti, gyro, acc, tn, q, vel, llh)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    log = make_log()
    path = tmp_path_factory.mktemp("ulog") / "sim.ulg"
    registry.write(str(path), log, "ulog")
    return log, path


def _compare(a: InsLog, b: InsLog, t_tol_s: float = 1.5e-6) -> None:
    """b (read back) holds a's numbers to the format's precision (float32, 1 us stamps)."""
    d = (b.meta.t0_ns - a.meta.t0_ns) * 1e-9 if a.meta.clock == b.meta.clock else 0.0
    np.testing.assert_allclose(b.t_imu_s() + d, a.t_imu_s(), atol=t_tol_s)
    np.testing.assert_allclose(b.gyro_rad_s(), a.gyro_rad_s(), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(b.accel_m_s2(), a.accel_m_s2(), rtol=1e-6, atol=1e-6)
    ta, qa = a.quat_wxyz()
    tb, qb = b.quat_wxyz()
    np.testing.assert_allclose(tb + d, ta, atol=t_tol_s)
    np.testing.assert_allclose(qb * np.sign(np.sum(qa * qb, axis=1))[:, None], qa, atol=1e-6)
    np.testing.assert_allclose(b.vel_ned_m_s()[1], a.vel_ned_m_s()[1], atol=1e-5)
    pa, pb = a.lat_lon_alt()[1], b.lat_lon_alt()[1]
    np.testing.assert_allclose(pb[:, :2], pa[:, :2], atol=1e-9)  # float64 lat/lon
    np.testing.assert_allclose(pb[:, 2], pa[:, 2], atol=1e-4)  # float32 alt


def test_sniff_by_magic(written):
    _, path = written
    assert ulog.sniff(path.read_bytes()[:64], str(path))
    assert not ulog.sniff(b"time_s,gyro_x_rad_s\n", "x.ulg")


def test_round_trip_boot_clock(written):
    log, path = written
    back = registry.load(f"{path}::clock=boot")
    assert back.meta.format == "ulog" and back.meta.clock == "boot"
    assert "timestamp" in back.meta.stamp_source
    assert back.meta.t0_ns == 10_000_000_000  # an epoch log is written with boot time from 10 s
    assert "imu=sensor_combined" in back.meta.selector and "pos=vehicle_global_position" in back.meta.selector
    _compare(log, back)


def test_round_trip_epoch_clock_from_gps_time(written):
    log, path = written
    back = registry.load(f"{path}::clock=epoch")
    assert back.meta.clock == "epoch" and "time_utc_usec" in back.meta.stamp_source
    assert abs(back.meta.t0_ns - log.meta.t0_ns) <= 1000
    _compare(log, back)
    # without a selector the log lands on the UNIX clock too, since its GPS gives the offset
    default = registry.load(str(path))
    assert default.meta.clock == "epoch" and default.meta.t0_ns == back.meta.t0_ns


def test_round_trip_boot_log_keeps_its_stamps(tmp_path):
    log = make_log(clock="boot", duration_s=5.0)
    p = tmp_path / "boot.ulg"
    ulog.write(str(p), log)
    back = ulog.load(str(p), Selector())
    assert back.meta.t0_ns == log.meta.t0_ns
    _compare(log, back)
    with pytest.raises(InputError, match="GPS time"):
        ulog.load(str(p), Selector.parse("clock=epoch"))


def test_position_from_local_position_reference(tmp_path):
    log = make_log(duration_s=5.0)
    p = tmp_path / "local.ulg"
    ulog.write(str(p), log, global_position=False)
    back = ulog.load(str(p), Selector())
    assert "pos=vehicle_local_position" in back.meta.selector
    llh_a, llh_b = log.lat_lon_alt()[1], back.lat_lon_alt()[1]
    # float32 x/y/z from the reference: better than a centimetre here
    np.testing.assert_allclose((llh_b[:, :2] - llh_a[:, :2]) * 111_000.0, 0.0, atol=0.01)
    np.testing.assert_allclose(llh_b[:, 2], llh_a[:, 2], atol=0.01)


def test_pyulog_reads_our_file(written):
    from pyulog import ULog

    log, path = written
    u = ULog(str(path))
    assert not u.file_corruption
    names = {d.name: d for d in u.data_list}
    assert set(names) >= {"sensor_combined", "vehicle_attitude", "vehicle_local_position",
                          "vehicle_global_position", "vehicle_gps_position"}
    sc = names["sensor_combined"].data
    assert len(sc["timestamp"]) == len(log.imu)
    np.testing.assert_allclose(np.c_[sc["gyro_rad[0]"], sc["gyro_rad[1]"], sc["gyro_rad[2]"]],
                               log.gyro_rad_s(), rtol=1e-6, atol=1e-7)
    va = names["vehicle_attitude"].data
    np.testing.assert_allclose(va["q[0]"], log.quat_wxyz()[1][:, 0], atol=1e-6)
    assert u.msg_info_dict["sys_name"] == "tapost"


def _same_topics(a: ulog.ULogTopics, b: ulog.ULogTopics) -> None:
    assert a.topics.keys() == b.topics.keys()
    for k in a.topics:
        assert a.topics[k].keys() == b.topics[k].keys()
        for f in a.topics[k]:
            x, y = a.topics[k][f], b.topics[k][f]
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), (k, f)


def test_fast_path_equals_pyulog_message_for_message(written):
    _, path = written
    fast = ulog.read_topics(str(path), None, engine="fast")
    ref = ulog.read_topics(str(path), None, engine="pyulog")
    assert fast.engine == "fast" and ref.engine == "pyulog"
    _same_topics(fast, ref)


@pytest.mark.skipif(not PX4_SAMPLE.exists(), reason="shared/realdata absent")
def test_fast_path_equals_pyulog_on_real_log():
    fast = ulog.read_topics(str(PX4_SAMPLE), None, engine="fast")
    ref = ulog.read_topics(str(PX4_SAMPLE), None, engine="pyulog")
    _same_topics(fast, ref)
    assert any("dropout" in w for w in fast.warnings) and any("dropout" in w for w in ref.warnings)


# ---- multi-instance and newer PX4 topics ------------------------------------------------------
_XYZ = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
        ("float", "x"), ("float", "y"), ("float", "z"), ("float", "temperature")]
_VEHICLE_IMU = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "accel_device_id"),
                ("uint32_t", "gyro_device_id"), ("float[3]", "delta_angle"), ("float[3]", "delta_velocity"),
                ("uint16_t", "delta_angle_dt"), ("uint16_t", "delta_velocity_dt"),
                ("uint8_t", "delta_angle_clipping"), ("uint8_t", "delta_velocity_clipping")]


def _multi_imu_file(path: Path, extra: list = ()) -> dict:
    t_us = 1_000_000 + np.arange(2000, dtype=np.int64) * 2500  # 400 Hz, 5 s
    ts = t_us * 1e-6
    truth = {}
    topics = []
    for inst in (0, 1):
        w = np.c_[np.sin(ts + inst), np.cos(ts), 0.1 * ts + inst]
        f = np.c_[0.2 * ts, -np.sin(ts), -G0_M_S2 + inst * np.ones_like(ts)]
        truth[inst] = (t_us, w, f)
        for name, vals in (("sensor_gyro", w), ("sensor_accel", f)):
            t = ulog.TopicRows.empty(name, _XYZ, len(t_us), multi_id=inst)
            t.rows["timestamp"] = t_us + 300
            t.rows["timestamp_sample"] = t_us
            t.rows["x"], t.rows["y"], t.rows["z"] = vals.T
            topics.append(t)
    # vehicle_imu[0]: 200 Hz deltas over 5 ms intervals ending at timestamp_sample, constant rate per interval
    tv_us = 1_000_000 + np.arange(1, 1000, dtype=np.int64) * 5000
    rate = np.c_[0.5 + 0.1 * np.arange(len(tv_us)) % 3, np.full(len(tv_us), -0.2), np.full(len(tv_us), 0.05)]
    spf = np.c_[np.zeros(len(tv_us)), np.full(len(tv_us), 0.3), np.full(len(tv_us), -G0_M_S2)]
    v = ulog.TopicRows.empty("vehicle_imu", _VEHICLE_IMU, len(tv_us))
    v.rows["timestamp"] = tv_us + 100
    v.rows["timestamp_sample"] = tv_us
    v.rows["delta_angle"] = rate * 0.005
    v.rows["delta_velocity"] = spf * 0.005
    v.rows["delta_angle_dt"] = v.rows["delta_velocity_dt"] = 5000
    topics.append(v)
    truth["vehicle_imu"] = (tv_us, rate, spf)
    ulog.encode(topics + list(extra)).tofile(path)
    return truth


def test_sensor_gyro_instance_selector_pairs_accel_of_same_instance(tmp_path):
    p = tmp_path / "multi.ulg"
    truth = _multi_imu_file(p)
    for inst in (0, 1):
        sel = "imu=sensor_gyro[1]" if inst else "imu=sensor_gyro"
        log = registry.load(f"{p}::{sel}")
        t_us, w, f = truth[inst]
        np.testing.assert_allclose(log.gyro_rad_s(), w, atol=1e-6)
        np.testing.assert_allclose(log.accel_m_s2(), f, atol=1e-5)
        assert log.meta.t0_ns == (t_us[0] + 300) * 1000  # 'timestamp' by default
    sample = registry.load(f"{p}::imu=sensor_gyro[1],time=sample")
    assert sample.meta.t0_ns == truth[1][0][0] * 1000 and "timestamp_sample" in sample.meta.stamp_source
    inv = registry.inspect_log(str(p))
    assert {"imu=sensor_gyro", "imu=sensor_gyro[1]", "imu=vehicle_imu"} <= set(inv.selectors)
    kinds = {s.name: s.kind for s in inv.streams}
    assert kinds["sensor_gyro[1]"] == "gyro" and kinds["sensor_accel[1]"] == "accel" and kinds["vehicle_imu"] == "imu"


def test_a_second_imu_instance_takes_the_same_instance_of_the_other_streams(tmp_path):
    """Two units in one ULog: sensor_gyro[1] goes with vehicle_attitude[1] (inspect's selector and a load
    naming the IMU only), not with instance 0's attitude (the other unit's); a stream the log has only as
    instance 0 is filled in with a warning that says so."""
    t_us = 1_000_000 + np.arange(500, dtype=np.int64) * 10_000
    extra = []
    for inst, yaw in ((0, 0.0), (1, np.pi / 2)):
        a = ulog.TopicRows.empty("vehicle_attitude", ulog._VEHICLE_ATTITUDE, len(t_us), multi_id=inst)
        a.rows["timestamp"] = a.rows["timestamp_sample"] = t_us
        a.rows["q"] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
        extra.append(a)
    lp = ulog.TopicRows.empty("vehicle_local_position", ulog._VEHICLE_LOCAL_POSITION, len(t_us))
    lp.rows["timestamp"] = lp.rows["timestamp_sample"] = t_us
    lp.rows["vx"] = 3.0
    lp.rows["v_xy_valid"] = lp.rows["v_z_valid"] = 1
    extra.append(lp)
    p = tmp_path / "two_units.ulg"
    _multi_imu_file(p, extra)
    inv = registry.inspect_log(str(p))
    assert "imu=sensor_gyro[1],att=vehicle_attitude[1],vel=vehicle_local_position" in inv.selectors
    assert "imu=sensor_gyro,att=vehicle_attitude,vel=vehicle_local_position" in inv.selectors
    log = registry.load(f"{p}::imu=sensor_gyro[1]")
    assert "att=vehicle_attitude[1]" in log.meta.selector
    np.testing.assert_allclose(np.abs(log.quat_wxyz()[1][:, [0, 3]]), np.sqrt(0.5), atol=1e-6)  # yaw 90 deg
    assert any("no instance 1 for vel=vehicle_local_position" in w for w in log.meta.warnings)
    unit0 = registry.load(f"{p}::imu=sensor_gyro")
    assert "att=vehicle_attitude," in unit0.meta.selector and not any("no instance" in w for w in unit0.meta.warnings)


def test_vehicle_imu_deltas_become_rates_at_interval_midpoints(tmp_path):
    p = tmp_path / "vimu.ulg"
    truth = _multi_imu_file(p)
    log = registry.load(f"{p}::imu=vehicle_imu")
    t_us, rate, spf = truth["vehicle_imu"]
    np.testing.assert_allclose(log.gyro_rad_s(), rate, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(log.accel_m_s2(), spf, rtol=1e-5, atol=1e-5)
    assert log.meta.t0_ns == (t_us[0] - 2500) * 1000  # mid-point of the first 5 ms interval
    assert "dt/2" in log.meta.stamp_source


def test_selector_errors_are_one_line(tmp_path, written):
    _, path = written
    with pytest.raises(InputError, match=r"no topic sensor_gyro\[3\].*has: sensor_combined") as e:
        registry.load(f"{path}::imu=sensor_gyro[3]")
    assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="unknown selector key"):
        registry.load(f"{path}::bogus=1")
    with pytest.raises(InputError, match="not an IMU topic"):
        registry.load(f"{path}::imu=vehicle_attitude")
    with pytest.raises(InputError, match="clock=boot or clock=epoch"):
        registry.load(f"{path}::clock=gps")
    no_att = registry.load(f"{path}::att=none,vel=none,pos=none")
    assert not no_att.has_quat and not no_att.has_vel and no_att.has_gyro


# ---- damage -----------------------------------------------------------------------------------
def test_truncated_file_uses_readable_part_and_warns(tmp_path, written):
    log, path = written
    data = path.read_bytes()
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(data[: int(len(data) * 0.6) + 7])  # mid-message
    back = registry.load(str(cut))
    assert any("truncated" in w for w in back.meta.warnings)
    assert 0.5 * len(log.imu) < len(back.imu) < 0.7 * len(log.imu)
    n = len(back.imu)
    np.testing.assert_allclose(back.gyro_rad_s(), log.gyro_rad_s()[:n], rtol=1e-6, atol=1e-7)


def test_zero_filled_tail_is_read_fast_and_named(tmp_path, written):
    """A preallocated log (or one cut by a power loss) ends in zero bytes: every message before them is read
    by the fast path, the same as the file without them, and the tail is named; no byte-wise resync."""
    log, path = written
    data = path.read_bytes()
    padded = tmp_path / "zero_tail.ulg"
    padded.write_bytes(data + bytes(1 << 20))
    fast = ulog.read_topics(str(padded), None)
    assert fast.engine == "fast"
    assert any("zero-filled tail" in w and str(1 << 20) in w for w in fast.warnings)
    _same_topics(fast, ulog.read_topics(str(path), None))
    back = registry.load(str(padded))
    assert any("zero-filled tail" in w for w in back.meta.warnings)
    _compare(log, back)


def test_flipped_header_byte_is_reported_and_rest_read(tmp_path, written):
    log, path = written
    buf = np.fromfile(path, np.uint8)
    offsets, sizes, types, _, status = ulog.kernel("_walk")(buf, 16, ulog._KNOWN_TYPES, ulog._MAX_MSG_SIZE)
    assert status == 0
    i = int(np.searchsorted(offsets, len(buf) // 2))
    bad = buf.copy()
    bad[offsets[i] + 2] = 0  # message type of a message in the middle -> 0
    p = tmp_path / "flip.ulg"
    bad.tofile(p)
    back = registry.load(str(p))
    assert any("damaged" in w or "corrupt" in w for w in back.meta.warnings)
    # pyulog resynchronises at the next sync message (our writer puts one every second)
    assert len(back.imu) >= len(log.imu) - 1.1 * 200
    assert back.duration_s == pytest.approx(log.duration_s, abs=0.01)


def test_garbage_and_header_only_inputs(tmp_path, written):
    _, path = written
    junk = tmp_path / "junk.ulg"
    junk.write_bytes(ulog.MAGIC + b"\x01")
    with pytest.raises(InputError, match="truncated ULog"):
        ulog.load(str(junk), Selector())
    head_only = tmp_path / "head.ulg"
    data = path.read_bytes()
    head_only.write_bytes(data[:200])  # definitions only, no data
    with pytest.raises(InputError, match="no IMU, attitude"):
        registry.load(str(head_only))


def test_a_damaged_header_is_read_past_where_the_messages_resume(tmp_path, written):
    """The magic bytes overwritten: every message read (the messages resume at byte 16), the damage named, the
    file untouched. The first 64 bytes overwritten (the flag bits and the start of the first definition): the
    messages from the next intact one on, named. Bytes that hold no ULog messages: not taken for one."""
    import hashlib

    log, path = written
    data = path.read_bytes()
    p = tmp_path / "magic.ulg"
    p.write_bytes(b"XXXXXXX" + data[7:])
    digest = hashlib.sha256(p.read_bytes()).hexdigest()
    back = registry.load(str(p))
    assert len(back.imu) == len(log.imu) and len(back.nav) == len(log.nav)
    assert any("damaged header" in w and "byte 16" in w for w in back.meta.warnings)
    assert hashlib.sha256(p.read_bytes()).hexdigest() == digest
    assert ulog.body_start(np.frombuffer(data, np.uint8)) == 16

    p64 = tmp_path / "head64.ulg"
    p64.write_bytes(bytes(range(64)) + data[64:])
    at = ulog.body_start(np.frombuffer(p64.read_bytes(), np.uint8))
    assert at is not None and at > 64
    try:
        back = registry.load(str(p64))
        assert any(f"read from byte {at}" in w for w in back.meta.warnings)
    except InputError as exc:  # (the lost definition may be the IMU's: then a one-line reason, never a traceback)
        assert "\n" not in str(exc)

    junk = tmp_path / "junk.ulg"
    junk.write_bytes(np.random.default_rng(0).integers(0, 256, 20000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match="unrecognised format"):
        registry.load(str(junk))


def test_damage_after_a_repaired_header_is_named_at_the_files_own_bytes(tmp_path, written):
    """A ULog with its first 64 bytes and its last message damaged: the reader and the native export say where
    the tail is cut in the file's own offsets (not in those of the repaired bytes, shifted by the resume offset
    less the new header's 16 bytes)."""
    import re

    from parsers.restamp import ClockShift
    from parsers.restamp_ulog import restamp_ulog

    _, path = written
    data = path.read_bytes()
    p = tmp_path / "head_and_tail.ulg"
    cut = len(data) - 5  # (inside the last message)
    p.write_bytes(bytes(range(64)) + data[64:cut])
    at = ulog.body_start(np.frombuffer(p.read_bytes(), np.uint8))
    assert at is not None and at > 16
    try:
        said = registry.load(str(p)).meta.warnings
    except InputError as exc:  # (the lost definition may be the IMU's)
        said = (str(exc),)
    out = tmp_path / "out.ulg"
    said += restamp_ulog(str(p), str(out), ClockShift(0.01, 0.0, 0)).damage
    cuts = [(int(a), int(b)) for w in said for a, b in re.findall(r"truncated last message at byte (\d+) of (\d+)", w)]
    assert cuts, said
    for a, b in cuts:
        assert b == cut and cut - 64 * 1024 < a < cut  # the file's size, and a byte inside its last message


def test_a_damaged_header_is_exported_behind_a_new_one(tmp_path, written):
    """The native export of a ULog whose magic is damaged: every message kept behind a header made anew, the
    damage named; pyulog reads the output with the original's topics and message counts."""
    from pyulog import ULog

    from parsers.restamp import ClockShift
    from parsers.restamp_ulog import restamp_ulog

    _, path = written
    data = path.read_bytes()
    p = tmp_path / "magic.ulg"
    p.write_bytes(b"\0" * 7 + data[7:])
    out = tmp_path / "out.ulg"
    st = restamp_ulog(str(p), str(out), ClockShift(0.01, 0.0, 0))
    assert any("damaged header" in d for d in st.damage)
    a, b = ULog(str(path)), ULog(str(out))
    assert sorted((d.name, len(d.data["timestamp"])) for d in a.data_list) == \
        sorted((d.name, len(d.data["timestamp"])) for d in b.data_list)


# ---- the real PX4 log -------------------------------------------------------------------------
@pytest.mark.skipif(not PX4_SAMPLE.exists(), reason="shared/realdata absent")
def test_real_px4_sample_rates_durations_and_frames():
    inv = registry.inspect_log(str(PX4_SAMPLE))
    assert inv.format == "ulog"
    by = {s.name: s for s in inv.streams}
    assert by["sensor_combined"].rate_hz == pytest.approx(248, rel=0.02)
    assert by["vehicle_attitude"].rate_hz == pytest.approx(94, rel=0.03)
    assert by["vehicle_local_position"].rate_hz == pytest.approx(10, rel=0.05)
    assert by["sensor_combined"].duration_s == pytest.approx(69, abs=0.5)
    assert inv.selectors[0].startswith("imu=sensor_combined,att=vehicle_attitude")
    log = registry.load(str(PX4_SAMPLE))
    assert log.meta.clock == "boot" and log.has_gyro and log.has_accel and log.has_quat
    assert log.duration_s == pytest.approx(69, abs=0.5)
    assert any("velocity flagged invalid" in w for w in log.meta.warnings)  # no GPS: never silently zero
    # FRD/NED consistency: specific force rotated by the attitude points up (-D) with gravity's size
    t_q, q = log.quat_wxyz()
    idx = np.searchsorted(log.t_imu_s(), t_q).clip(0, len(log.imu) - 1)
    f_ned = quat_rotate(q, log.accel_m_s2()[idx])
    np.testing.assert_allclose(np.median(f_ned, axis=0), [0, 0, -G0_M_S2], atol=0.4)
    with pytest.raises(InputError, match="GPS time"):
        registry.load(f"{PX4_SAMPLE}::clock=epoch")


def test_vehicle_angular_velocity_pairs_vehicle_acceleration(tmp_path):
    fields = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[3]", "xyz")]
    t_us = 2_000_000 + np.arange(800, dtype=np.int64) * 1250  # 800 Hz
    w = np.c_[np.sin(t_us * 1e-6), np.zeros(800), np.ones(800)]
    f = np.c_[np.zeros(800), np.cos(t_us * 1e-6), np.full(800, -G0_M_S2)]
    topics = []
    for name, vals in (("vehicle_angular_velocity", w), ("vehicle_acceleration", f)):
        t = ulog.TopicRows.empty(name, fields, len(t_us))
        t.rows["timestamp"] = t.rows["timestamp_sample"] = t_us
        t.rows["xyz"] = vals
        topics.append(t)
    p = tmp_path / "vav.ulg"
    ulog.encode(topics).tofile(p)
    log = registry.load(f"{p}::imu=vehicle_angular_velocity")
    np.testing.assert_allclose(log.gyro_rad_s(), w, atol=1e-6)
    np.testing.assert_allclose(log.accel_m_s2(), f, atol=1e-5)
    assert registry.load(str(p)).meta.selector == "imu=vehicle_angular_velocity"


def test_gyro_only_log_round_trips_without_accel(tmp_path):
    from dataclasses import replace

    log = make_log(duration_s=2.0)
    gyro_only = replace(log, imu=log.imu[["gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s"]])
    p = tmp_path / "g.ulg"
    ulog.write(str(p), gyro_only)
    back = ulog.load(str(p), Selector())
    assert back.has_gyro and not back.has_accel
    assert any("invalid relative stamp" in w for w in back.meta.warnings)


# ---- corrupt time fields (a damaged log): stamps stay sane, the clock honest --------------------------
@pytest.fixture(scope="module")
def sim_pair():
    sim = pytest.importorskip("logtools.sim")
    return sim.simulate(sim.scenario_config("aircraft", duration_s=30.0))


def _topics(log: InsLog) -> dict:
    return {t.name: t for t in ulog.topics_of(log)}


def test_corrupt_stamps_and_gps_times_keep_the_log_on_its_true_span(tmp_path, sim_pair):
    """A damaged ULog (the fuzzer's 100 flipped bytes): IMU and attitude stamps with corrupt high bytes, GPS
    fixes with an impossible or inconsistent UTC time or boot stamp. One IMU stamp of 9e15 us fits int64 ns
    but overflowed once the boot->UTC offset was added before the stray stamps were dropped (slave t0
    -8.1e18 ns, and --max-lag auto reported a latency of -2**64 ns); one of 2**64 - 5000 us read as 5 ms
    before boot, 10 s before the log. The bad samples and fixes go, the log stays on UNIX time within its
    true span, and the latency comes out right."""
    from logtools.latency import estimate

    slave = sim_pair.slave
    top = _topics(slave)
    sc = top["sensor_combined"].rows
    n = len(sc)
    sc["timestamp"][n // 3] = 9_000_000_000_000_000
    sc["timestamp"][n // 2] = 2**64 - 5000
    sc["timestamp"][2 * n // 3] |= np.uint64(1 << 63)
    att = top["vehicle_attitude"].rows
    att["timestamp"][len(att) // 2] = 9_100_000_000_000_000
    gps = top["vehicle_gps_position"].rows
    gps["time_utc_usec"][5] = 1 << 62  # year 146 000
    gps["time_utc_usec"][9] = 1_900_000_000_000_000  # 2030: plausible alone, not with the others
    gps["timestamp"][12] = 2**64 - 1
    p = tmp_path / "damaged.ulg"
    ulog.encode(list(top.values())).tofile(p)
    back = ulog.load(str(p), Selector())
    assert back.meta.clock == "epoch" and "time_utc_usec" in back.meta.stamp_source
    assert abs(back.meta.t0_ns - slave.meta.t0_ns) <= 1000  # its first sample, to the microsecond
    a, b = back.span_s()
    assert a == 0.0 and b == pytest.approx(slave.span_s()[1], abs=1e-5)
    assert len(back.imu) == n - 3
    warns = " ".join(back.meta.warnings)
    assert "impossible stamps dropped" in warns and "3 of" in warns and "GPS fixes ignored" in warns
    res = estimate(sim_pair.master, back, compare=False)
    assert res.latency_s == pytest.approx(sim_pair.truth.latency_s, abs=0.5e-3)


@pytest.mark.parametrize("how", ["beyond_2100", "disagree"])
def test_gps_time_without_a_trustworthy_offset_stays_on_the_boot_clock(tmp_path, how):
    """GPS UTC times that give no offset to trust (all past 2100, or no majority agreeing): the log stays on
    its boot clock with a warning naming the problem, not on a garbage (or int64-wrapped) epoch clock;
    clock=epoch asked for is a one-line InputError."""
    log = make_log(duration_s=5.0)
    top = _topics(log)
    gps = top["vehicle_gps_position"].rows
    if how == "beyond_2100":
        gps["time_utc_usec"] = np.uint64(8_000_000_000_000_000_000) + gps["time_utc_usec"]
    else:
        rng = np.random.default_rng(5)
        gps["time_utc_usec"] = rng.integers(1_000_000_000_000_001, 4_000_000_000_000_000, len(gps))
    p = tmp_path / f"{how}.ulg"
    ulog.encode(list(top.values())).tofile(p)
    back = ulog.load(str(p), Selector())
    assert back.meta.clock == "boot" and back.meta.t0_ns == 10_000_000_000  # written with boot time from 10 s
    assert "clock=epoch" not in back.meta.selector and "UTC" not in back.meta.stamp_source
    assert any("no trustworthy boot->UTC offset" in w and "kept on the boot clock" in w for w in back.meta.warnings)
    _compare(log, back)
    with pytest.raises(InputError, match="no trustworthy") as exc:
        ulog.load(str(p), Selector.parse("clock=epoch"))
    assert "\n" not in str(exc.value) and str(p) in str(exc.value)


def test_the_gps_utc_offset_carries_its_spread_as_a_sigma(tmp_path):
    """A ULog put on UNIX time by its GPS UTC time: the offset's sigma (the per-fix readings' spread, the
    microsecond of time_utc_usec) and the offset itself ride on every channel (the latency's clock_mapping;
    two files with the very same offset share it). A GPS whose UTC readings jitter by 3 ms gives ~3 ms."""
    from logtools import sim
    from parsers import registry, ulog as ul

    p = sim.simulate(sim.scenario_config("ship", duration_s=20.0))
    path = str(tmp_path / "s.ulg")
    registry.write(path, p.slave, "ulog")
    log = registry.load(path)
    ch = log.meta.channels["gyro"]
    assert log.meta.clock == "epoch" and ch.clock_offset_ns is not None
    assert ch.clock_sigma_s == pytest.approx(1e-6 / np.sqrt(12.0), rel=1e-3)
    assert all(c.clock_offset_ns == ch.clock_offset_ns for c in log.meta.channels.values())
    rng = np.random.default_rng(0)
    utc = 1_700_000_000_000_000 + np.arange(200) * 200_000
    topics = {("vehicle_gps_position", 0): {"time_utc_usec": (utc + rng.normal(0, 3000, 200)).astype(np.uint64),
                                            "timestamp": (np.arange(200) * 200_000 + 5_000_000).astype(np.uint64)}}
    off, _src, _w, problem, sigma = ul._utc_offset(topics)
    assert problem == "" and off is not None
    assert sigma == pytest.approx(3e-3, rel=0.2)


def test_a_data_message_of_no_subscription_is_left_out_alone(tmp_path, sim_pair):
    """One data message whose id byte a damage changed to an id nothing subscribed: the whole file went to
    pyulog, which resumes at the next sync message. The fast reader now leaves out that message alone, says
    so, and keeps every other sample; the native export copies it as it is, so its output reads the same."""
    from parsers import restamp_ulog
    from parsers.restamp import ClockShift

    p = tmp_path / "good.ulg"
    ulog.write(str(p), sim_pair.slave)
    buf = np.fromfile(p, np.uint8)
    offsets, _sizes, types, _end, _status = ulog.kernel("_walk")(buf, 16, ulog._KNOWN_TYPES, ulog._MAX_MSG_SIZE)
    data = offsets[types == ulog._T_DATA]
    bad = buf.copy()
    bad[data[len(data) // 2] + 4] ^= 0x7F  # (the id's high byte: an id nothing subscribed)
    q = tmp_path / "bad.ulg"
    bad.tofile(q)
    topics = ulog.read_topics(str(q))
    assert topics.engine == "fast"
    assert any("1 data message(s) of no subscription" in w for w in topics.warnings)
    full, back = ulog.load(str(p), Selector()), ulog.load(str(q), Selector())
    assert len(full.imu) - 1 <= len(back.imu) <= len(full.imu) and len(full.nav) - 1 <= len(back.nav)
    sh = ClockShift(0.02, 0.0, back.meta.t0_ns)
    restamp_ulog.restamp_ulog(str(q), str(tmp_path / "out.ulg"), sh)
    out = ulog.load(str(tmp_path / "out.ulg"), Selector())
    assert (len(out.imu), len(out.nav)) == (len(back.imu), len(back.nav))


def _fake_flag_bits(incompat: bytes) -> bytes:
    """A 'B' message (40 bytes: compat flags, incompat flags, 3 appended offsets) with these incompat flags."""
    payload = bytes(8) + incompat.ljust(8, b"\0") + bytes(24)
    return len(payload).to_bytes(2, "little") + b"B" + payload


def test_a_flag_bits_message_after_damage_decides_nothing(tmp_path, written):
    """A stretch in the data section overwritten, the walk resuming on a 'B' message made of the damaged bytes
    whose incompatible flags are not zero (a fuzzed PX4 log: refused whole, "unknown incompatible flags"). Only
    the flag bits message first after the header is the file's (ULog spec): the file reads, fast, the samples
    before and after the damage kept, the damage and the misplaced 'B' named; the native export copies it."""
    from parsers import restamp_ulog
    from parsers.restamp import ClockShift

    log, path = written
    buf = np.fromfile(path, np.uint8)
    offsets, sizes, types, _end, status = ulog.kernel("_walk")(buf, 16, ulog._KNOWN_TYPES, ulog._MAX_MSG_SIZE)
    assert status == 0 and types[0] == ulog._T_FLAGS and offsets[0] == 16
    i = int(np.searchsorted(offsets, len(buf) // 2))
    j = i + 40
    assert types[i - 1] == types[j] == ulog._T_DATA
    fake = _fake_flag_bits(b"\x02\x80")  # (unknown incompatible flags)
    bad = buf.copy()
    bad[offsets[i]:offsets[j]] = 0xFF  # (no header chains in there: size 0xFFFF)
    at = int(offsets[j]) - len(fake)  # (the fake 'B' ends where message j starts: the walk resumes on it)
    assert at > offsets[i] + 3
    bad[at:offsets[j]] = np.frombuffer(fake, np.uint8)
    p = tmp_path / "fake_b.ulg"
    bad.tofile(p)

    topics = ulog.read_topics(str(p))
    assert topics.engine == "fast"
    assert any(f"implausible message header at byte {offsets[i]}" in w and f"resume at byte {at}" in w
               for w in topics.warnings)
    assert any(f"flag bits message(s) not first after the header (at byte(s) {at})" in w for w in topics.warnings)
    # every data message kept but those the damage covers (and the one before the break): exactly
    lost = (offsets >= offsets[i - 1]) & (offsets < offsets[j])
    subs, _ = ulog.definitions(buf, offsets, sizes, types)
    d_off = offsets[types == ulog._T_DATA]
    ids = buf[d_off + 3].astype(np.int64) | (buf[d_off + 4].astype(np.int64) << 8)
    full = ulog.read_topics(str(path))
    kept_any = False
    for mid, add in subs.items():
        key = (add.message_name, int(add.multi_id))
        mine = d_off[ids == mid]
        keep = ~np.isin(mine, offsets[lost])
        kept_any |= not keep.all()
        for f, v in full.topics[key].items():
            assert np.array_equal(topics.topics[key][f], v[keep], equal_nan=True), (key, f)
    assert kept_any  # (the damage did cost samples; those before and after it are all there)

    back = registry.load(str(p))
    assert any("not first after the header" in w for w in back.meta.warnings)
    assert len(log.imu) - 45 <= len(back.imu) < len(log.imu)
    assert back.duration_s == pytest.approx(log.duration_s, abs=0.01)

    # the native export: the fake 'B' and the damaged bytes copied unchanged, the rest as the reader reads it
    st = restamp_ulog.restamp_ulog(str(p), str(tmp_path / "out.ulg"), ClockShift(0.02, 0.0, back.meta.t0_ns))
    assert any(f"resume at byte {at}" in d for d in st.damage)
    out_buf = np.fromfile(tmp_path / "out.ulg", np.uint8)
    assert len(out_buf) == len(bad) and np.array_equal(out_buf[offsets[i]:offsets[j]], bad[offsets[i]:offsets[j]])
    out = ulog.load(str(tmp_path / "out.ulg"), Selector())
    assert (len(out.imu), len(out.nav)) == (len(back.imu), len(back.nav))


def test_unknown_incompatible_flags_of_the_first_message_still_refuse_the_file(tmp_path, written):
    """The file's own flag bits (the first message after the header) with a flag tapost does not know: refused,
    one line, by both readers; a header made anew before messages resuming later does not take the 'B' it resumes
    on for the file's."""
    _, path = written
    data = bytearray(path.read_bytes())
    assert data[18] == ord("B")
    for k, v in ((0, 0x02), (1, 0x01), (7, 0x80)):  # (incompat[0] bit 0: data appended, known)
        bad = bytearray(data)
        bad[16 + 3 + 8 + k] = v
        p = tmp_path / f"flags{k}.ulg"
        p.write_bytes(bytes(bad))
        with pytest.raises(InputError, match="ULog with unknown incompatible flags: cannot be read"):
            ulog.read_topics(str(p))
        with pytest.raises(InputError, match="ULog with unknown incompatible flags: cannot be read"):
            registry.load(str(p))
        with pytest.raises(InputError, match="(?i)incompatible flag"):
            ulog.read_topics(str(p), engine="pyulog")

    # damaged header, the messages resuming (byte 75) on a 'B' that is not at the spec's place: not the file's
    first_def = 16 + 3 + (data[16] | data[17] << 8)
    fake = _fake_flag_bits(b"\x02")
    rebuilt = b"\xff" * 75 + fake + bytes(data[first_def:])
    p = tmp_path / "resumed_on_b.ulg"
    p.write_bytes(rebuilt)
    assert ulog.body_start(np.frombuffer(rebuilt, np.uint8)) == 75
    topics = ulog.read_topics(str(p))
    assert topics.engine == "fast" and any("not first after the header (at byte(s) 75)" in w for w in topics.warnings)
    _same_topics(topics, ulog.read_topics(str(path)))
