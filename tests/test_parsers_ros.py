"""ROS parsers: MCAP (ROS 2 CDR and ROS 1), ROS 1 bag, ROS 2 bag (sqlite3 and mcap storage).

Round trips through our writers, a frames check on hand-built messages that does not use our writer,
the vectorised fast path against the libraries' decoders message for message, the real car bag, and
damaged input.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import parsers
from logtools.conventions import (
    DEG,
    dcm_from_quat,
    euler_from_quat,
    quat_from_euler,
)
from logtools.errors import InputError
from logtools.inslog import InsLog, LogMeta
from parsers import mcap_ros, registry, rosbag1, rosbag2
from parsers.restamp import ClockShift
from parsers import ros_common as rc
from pipelines.cli import main as cli_main

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
CAR_BAG = REALDATA / "car_xsens_stereo_test1.bag"
T0_NS = 1_700_000_000_123_456_789

WRITERS = [
    ("mcap", {}, "x.mcap"),
    ("mcap", {"encoding": "ros1", "compression": "lz4"}, "x1.mcap"),
    ("mcap", {"compression": "none"}, "xn.mcap"),
    ("rosbag1", {}, "x.bag"),
    ("rosbag1", {"compression": "lz4"}, "xlz4.bag"),
    ("rosbag1", {"compression": "bz2"}, "xbz2.bag"),
    ("rosbag2", {"storage": "sqlite3"}, "bag_sqlite"),
    ("rosbag2", {"storage": "mcap"}, "bag_mcap"),
    ("rosbag2", {"storage": "sqlite3", "compression": "file"}, "bag_sqlite_zfile"),
    ("rosbag2", {"storage": "sqlite3", "compression": "message"}, "bag_sqlite_zmsg"),
    ("rosbag2", {"storage": "mcap", "compression": "file"}, "bag_mcap_zfile"),
    ("rosbag2", {"storage": "mcap", "compression": "message"}, "bag_mcap_zmsg"),
]


def synthetic_log(n: int = 400, rate_hz: float = 100.0, nav_same_stamps: bool = True, seed: int = 1) -> InsLog:
    """FRD/NED log with a non-trivial attitude (yaw near 170 deg), velocity, position, epoch clock."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    gyro = rng.normal(0, 0.2, (n, 3))
    accel = rng.normal(0, 1.0, (n, 3)) + [0.0, 0.0, -9.81]
    t_nav = t if nav_same_stamps else np.arange(n // 2) / (rate_hz / 2) + 0.0037
    m = len(t_nav)
    rpy = np.stack([0.2 * np.sin(t_nav), -0.1 * np.cos(0.5 * t_nav), 170 * DEG + 0.05 * t_nav], axis=-1)
    quat = quat_from_euler(rpy)
    vel = np.stack([10 * np.cos(t_nav), -3 + 0.1 * t_nav, 0.5 * np.sin(t_nav)], axis=-1)
    pos = np.stack([47.1 + 1e-5 * t_nav, 8.5 - 1e-5 * t_nav, 430.0 + 0.2 * t_nav], axis=-1)
    meta = LogMeta(source_path="synthetic", format="sim", clock="epoch", t0_ns=T0_NS)
    assert m > 10
    return InsLog.from_arrays(meta, t_imu_s=t, gyro_rad_s=gyro, accel_m_s2=accel, t_nav_s=t_nav,
                              quat_wxyz=quat, vel_ned_m_s=vel, lat_lon_alt=pos)


def abs_ns(log: InsLog, t_s: np.ndarray) -> np.ndarray:
    return log.meta.t0_ns + np.round(np.asarray(t_s) * 1e9).astype(np.int64)


def same_quat(a: np.ndarray, b: np.ndarray, tol: float = 1e-12) -> bool:
    d = np.minimum(np.abs(a - b).max(axis=1), np.abs(a + b).max(axis=1))
    return bool(d.max() < tol)


@pytest.fixture(scope="module")
def log() -> InsLog:
    return synthetic_log()


@pytest.fixture(scope="module")
def written(tmp_path_factory, log) -> dict[str, str]:
    d = tmp_path_factory.mktemp("ros_rt")
    out = {}
    for fmt, opts, name in WRITERS:
        p = str(d / name)
        registry.write(p, log, fmt, **opts)
        out[name] = p
    return out


# ---- round trips ------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt,opts,name", WRITERS)
def test_round_trip_same_numbers(written, log, fmt, opts, name):
    path = written[name]
    assert registry.detect(path).NAME == fmt
    back = parsers.load(path)
    assert back.meta.format == fmt
    assert back.meta.clock == "epoch"
    assert "header.stamp" in back.meta.stamp_source
    assert back.meta.t0_ns == log.meta.t0_ns
    np.testing.assert_array_equal(abs_ns(back, back.t_imu_s()), abs_ns(log, log.t_imu_s()))
    np.testing.assert_array_equal(back.gyro_rad_s(), log.gyro_rad_s())  # sign flips are exact
    np.testing.assert_array_equal(back.accel_m_s2(), log.accel_m_s2())
    tq, q = back.quat_wxyz()
    np.testing.assert_array_equal(abs_ns(back, tq), abs_ns(log, log.quat_wxyz()[0]))
    assert same_quat(q, log.quat_wxyz()[1])
    yaw, yaw_in = euler_from_quat(q)[:, 2], euler_from_quat(log.quat_wxyz()[1])[:, 2]
    assert np.abs(np.angle(np.exp(1j * (yaw - yaw_in)))).max() < 1e-12
    assert yaw_in[0] == pytest.approx(170 * DEG) and yaw.min() < -170 * DEG  # crosses +-180 deg
    tv, v = back.vel_ned_m_s()
    np.testing.assert_array_equal(abs_ns(back, tv), abs_ns(log, log.vel_ned_m_s()[0]))
    np.testing.assert_array_equal(v, log.vel_ned_m_s()[1])
    tp, p = back.lat_lon_alt()
    np.testing.assert_array_equal(p, log.lat_lon_alt()[1])
    assert {"gyro", "accel", "att", "vel", "pos"} <= set(back.meta.channels)
    assert back.meta.channels["gyro"].rate_hz == pytest.approx(100.0)


@pytest.mark.parametrize("fmt,opts,ext", [("mcap", {}, ".mcap"), ("rosbag1", {}, ".bag"),
                                          ("rosbag2", {"storage": "sqlite3"}, "")])
def test_round_trip_attitude_on_other_stamps(tmp_path, fmt, opts, ext):
    """Attitude not at the IMU stamps: written as /attitude QuaternionStamped, read back exactly."""
    log = synthetic_log(300, nav_same_stamps=False)
    p = str(tmp_path / ("y" + ext))
    registry.write(p, log, fmt, **opts)
    back = parsers.load(p)
    assert any("att=/attitude" in w for w in back.meta.warnings)
    tq, q = back.quat_wxyz()
    np.testing.assert_array_equal(abs_ns(back, tq), abs_ns(log, log.quat_wxyz()[0]))
    assert same_quat(q, log.quat_wxyz()[1])
    np.testing.assert_array_equal(back.gyro_rad_s(), log.gyro_rad_s())
    inv = parsers.inspect_log(p)
    kinds = {s.name: s.kind for s in inv.streams}
    assert kinds == {"/imu": "imu", "/attitude": "att", "/velocity": "vel", "/fix": "pos"}
    assert inv.selectors == ("imu=/imu,att=/attitude,vel=/velocity,pos=/fix",)
    assert parsers.load(f"{p}::{inv.selectors[0]}").has_quat


def test_rosbag2_accepts_dir_yaml_and_db3(written, log):
    d = written["bag_sqlite"]
    db3 = [f for f in os.listdir(d) if f.endswith(".db3")][0]
    for p in (d, os.path.join(d, "metadata.yaml"), os.path.join(d, db3)):
        back = parsers.load(p)
        assert back.meta.format == "rosbag2"
        np.testing.assert_array_equal(back.gyro_rad_s(), log.gyro_rad_s())
    assert back.meta.stamp_source == "header.stamp (/imu, /velocity, /fix)"


def test_rosbag2_write_replaces_existing_bag(tmp_path):
    p = str(tmp_path / "bag")
    rosbag2.write(p, synthetic_log(50), storage="sqlite3")
    rosbag2.write(p, synthetic_log(80), storage="mcap")
    assert sorted(os.listdir(p)) == ["bag.mcap", "metadata.yaml"]
    assert sorted(os.listdir(tmp_path)) == ["bag"]  # no temporary leftovers
    assert len(parsers.load(p).imu) == 80


def test_a_bag_never_replaces_a_file_or_a_folder_of_other_things(written, tmp_path, capsys):
    """A ROS 2 bag is a folder, written in place of an earlier bag. `tapost restamp BAG --from DIR -o README.md`
    replaced the file README.md with a bag folder, and `-o DIR` (the report's own folder) deleted report.json
    with the rest of it. A file, or a non-empty folder that is no bag, is now refused in one line and left as
    it was; an empty folder or an earlier bag is written."""
    from parsers import restamp_ros

    src = written["bag_sqlite"]
    shift = ClockShift(0.01, 0.0, parsers.load(src).meta.t0_ns)
    note = tmp_path / "README.md"
    note.write_text("keep me")
    other = tmp_path / "out"
    other.mkdir()
    (other / "report.json").write_text("{}")
    for dst in (note, other):
        with pytest.raises(InputError, match="not replaced"):
            restamp_ros.restamp_rosbag2(src, str(dst), shift)
        with pytest.raises(InputError, match="not replaced"):
            rosbag2.write(str(dst), synthetic_log(50))
    assert note.read_text() == "keep me" and (other / "report.json").read_text() == "{}"
    assert sorted(os.listdir(other)) == ["report.json"]
    empty = tmp_path / "empty"
    empty.mkdir()
    restamp_ros.restamp_rosbag2(src, str(empty), shift)
    restamp_ros.restamp_rosbag2(src, str(empty), shift)  # (an earlier bag is replaced)
    assert os.path.isfile(empty / "metadata.yaml")


def test_a_bag_export_never_replaces_the_folder_its_input_is_in(written, tmp_path):
    """The slave given as the storage file of a bag that sits where the export goes
    (OUT/slave_on_master_clock/bag.db3, an earlier export read back, with -o OUT): the export replaced that
    folder whole, input and all. It now fails with 'would overwrite an input', the input's bytes unchanged."""
    import hashlib

    from pipelines import export

    out = tmp_path / "out"
    bag = out / export.BASENAME
    shutil.copytree(written["bag_sqlite"], bag)
    db = next(p for p in bag.iterdir() if p.suffix == ".db3")
    before = hashlib.sha256(db.read_bytes()).hexdigest()
    slave = parsers.load(str(db))
    (e,) = export.write_slave(("native",), str(out), slave, ClockShift(0.01, 0.0, slave.meta.t0_ns))
    assert e.failed and "would overwrite an input" in e.failed, e
    assert hashlib.sha256(db.read_bytes()).hexdigest() == before
    assert sorted(p.name for p in out.iterdir()) == [export.BASENAME]


def test_log_time_selector(tmp_path, log):
    p = str(tmp_path / "d.mcap")
    mcap_ros.write(p, log, log_delay_ns=5_000_123)
    hdr = parsers.load(p)
    lg = parsers.load(p + "::time=log")
    assert hdr.meta.t0_ns == log.meta.t0_ns
    assert lg.meta.t0_ns == log.meta.t0_ns + 5_000_123
    assert "log time" in lg.meta.stamp_source and "header.stamp" in hdr.meta.stamp_source
    np.testing.assert_array_equal(lg.gyro_rad_s(), log.gyro_rad_s())


def test_vel_frame_body_rotates_with_attitude(written, log):
    """vel_frame=body reads TwistStamped.linear as FLU body velocity, rotated with the attitude."""
    p = written["x.mcap"]
    body = parsers.load(p + "::imu=/imu,vel=/velocity,vel_frame=body")
    enu = parsers.load(p + "::imu=/imu,vel=/velocity")
    _, q = enu.quat_wxyz()
    _, v_world_as_read = enu.vel_ned_m_s()  # = NED(v_enu)
    # the same stored numbers taken as FLU body: v_enu -> (FLU) -> FRD -> NED with q
    from logtools.conventions import flu_to_frd, ned_to_enu

    v_frd = flu_to_frd(ned_to_enu(v_world_as_read))
    expect = np.einsum("nij,nj->ni", dcm_from_quat(q), v_frd)
    np.testing.assert_allclose(body.vel_ned_m_s()[1], expect, atol=1e-12)
    assert "(body)" in body.meta.channels["vel"].source


# ---- frames, independent of our writer --------------------------------------------------------
def _hand_mcap(path: str, msgs: list[tuple[str, str, object, int]]) -> None:
    """Write messages built by hand (rosbags classes) with the mcap package's writer."""
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        chans: dict[str, int] = {}
        for topic, msgtype, msg, t_ns in msgs:
            if topic not in chans:
                sid = w.register_schema(name=msgtype, encoding="ros2msg",
                                        data=ts.generate_msgdef(msgtype, ros_version=2)[0].encode())
                chans[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
            w.add_message(chans[topic], log_time=t_ns, data=bytes(ts.serialize_cdr(msg, msgtype)),
                          publish_time=t_ns)
        w.finish()


def _ros_types():
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = {k.split("/")[-1]: ts.types[k] for k in (
        "builtin_interfaces/msg/Time", "std_msgs/msg/Header", "geometry_msgs/msg/Quaternion",
        "geometry_msgs/msg/Vector3", "sensor_msgs/msg/Imu", "geometry_msgs/msg/Twist",
        "geometry_msgs/msg/TwistStamped", "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseWithCovariance",
        "geometry_msgs/msg/TwistWithCovariance", "geometry_msgs/msg/Pose", "geometry_msgs/msg/Point")}
    return T


def _imu_msg(T, t_ns: int, q_xyzw, gyro, accel, frame="imu_link"):
    hdr = T["Header"](stamp=T["Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=frame)
    return T["Imu"](header=hdr, orientation=T["Quaternion"](*q_xyzw), orientation_covariance=np.zeros(9),
                    angular_velocity=T["Vector3"](*gyro), angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=T["Vector3"](*accel), linear_acceleration_covariance=np.zeros(9))


def _odom_north_msg(T, t_ns: int):
    """An Odometry heading north (ENU orientation +90 deg about up), forward 3 m/s, turning left 0.1 rad/s."""
    c45 = np.sqrt(0.5)
    hdr = T["Header"](stamp=T["Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id="odom")
    return T["Odometry"](
        header=hdr, child_frame_id="base_link",
        pose=T["PoseWithCovariance"](pose=T["Pose"](position=T["Point"](0.0, 0.0, 0.0),
                                                   orientation=T["Quaternion"](0.0, 0.0, c45, c45)),
                                     covariance=np.zeros(36)),
        twist=T["TwistWithCovariance"](twist=T["Twist"](linear=T["Vector3"](3.0, 0.0, 0.0),
                                                        angular=T["Vector3"](0.0, 0.0, 0.1)),
                                       covariance=np.zeros(36)))


def test_a_frame_id_with_a_ned_suffix_is_read_as_frd_ned(tmp_path):
    """REP-103 marks NED frames with a "_ned" suffix (MAVROS and PX4 name the body "base_link_frd"): such an
    Imu's vectors and orientation are FRD/NED already. Heading east (NED yaw +90 deg), turning right (FRD yaw
    rate +0.1), at rest (FRD accel z -9.81): read as they are, with a note; the same numbers under a plain
    frame_id are converted from FLU/ENU as before."""
    T = _ros_types()
    c45 = np.sqrt(0.5)
    msgs = []
    for k in range(20):
        t = T0_NS + k * 10_000_000
        for topic, frame in (("/imu_ned", "imu_link_ned"), ("/imu_frd", "base_link_FRD"), ("/imu", "imu_link")):
            msgs.append((topic, "sensor_msgs/msg/Imu",
                         _imu_msg(T, t, (0.0, 0.0, c45, c45), (0.0, 0.0, 0.1), (0.0, 0.0, -9.81), frame=frame), t))
    p = str(tmp_path / "ned.mcap")
    _hand_mcap(p, msgs)
    for topic in ("/imu_ned", "/imu_frd"):
        log = parsers.load(p + f"::imu={topic}")
        np.testing.assert_allclose(log.gyro_rad_s(), np.tile([0.0, 0.0, 0.1], (20, 1)), atol=1e-15)
        np.testing.assert_allclose(log.accel_m_s2(), np.tile([0.0, 0.0, -9.81], (20, 1)), atol=1e-15)
        np.testing.assert_allclose(euler_from_quat(log.quat_wxyz()[1]), np.tile([0.0, 0.0, np.pi / 2], (20, 1)),
                                   atol=1e-12)
        assert any(w.startswith(f"note: {topic}: frame_id") and "NED/FRD" in w for w in log.meta.warnings)
    plain = parsers.load(p + "::imu=/imu")  # FLU/ENU: turning left, upside down, heading north
    np.testing.assert_allclose(plain.gyro_rad_s(), np.tile([0.0, 0.0, -0.1], (20, 1)), atol=1e-15)
    assert not any("NED/FRD" in w for w in plain.meta.warnings)


def test_a_constant_placeholder_orientation_is_not_an_attitude(tmp_path):
    """Drivers without an AHRS publish identity with covariance 0 (not REP-145's -1): one bit-identical
    quaternion in every message is no attitude; the IMU itself is read."""
    T = _ros_types()
    msgs = []
    for k in range(80):
        t = T0_NS + k * 10_000_000
        msgs.append(("/imu", "sensor_msgs/msg/Imu",
                     _imu_msg(T, t, (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.1 * np.sin(k)), (0.0, 0.0, 9.81)), t))
        msgs.append(("/imu_real", "sensor_msgs/msg/Imu",
                     _imu_msg(T, t, (0.0, 0.0, np.sin(1e-3 * k), np.cos(1e-3 * k)), (0.0, 0.0, 0.1), (0.0, 0.0, 9.81)),
                     t))
    p = str(tmp_path / "placeholder.mcap")
    _hand_mcap(p, msgs)
    log = parsers.load(p + "::imu=/imu")
    assert log.has_gyro and not log.has_quat
    assert any("one constant quaternion" in w and w.startswith("note:") for w in log.meta.warnings)
    real = parsers.load(p + "::imu=/imu_real")
    assert real.has_quat and not any("constant quaternion" in w for w in real.meta.warnings)


def test_enu_flu_hand_built_messages(tmp_path):
    """Heading north, turning left (FLU yaw rate +0.1), at rest (FLU accel z +9.81); ENU identity
    quaternion = heading east; Odometry forward 3 m/s heading north; TwistStamped ENU east 5 m/s."""
    T = _ros_types()
    c45 = np.sqrt(0.5)
    msgs = []
    for k in range(20):
        t = T0_NS + k * 10_000_000
        # heading north in ENU: FLU x axis along ENU y = rotation +90 deg about up
        msgs.append(("/imu_north", "sensor_msgs/msg/Imu",
                     _imu_msg(T, t, (0.0, 0.0, c45, c45), (0.0, 0.0, 0.1), (0.0, 0.0, 9.81)), t))
        msgs.append(("/imu_east", "sensor_msgs/msg/Imu",
                     _imu_msg(T, t, (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 9.81)), t))
        hdr = T["Header"](stamp=T["Time"](sec=t // 10**9, nanosec=t % 10**9), frame_id="odom")
        msgs.append(("/odom", "nav_msgs/msg/Odometry", _odom_north_msg(T, t), t))
        tw = T["TwistStamped"](header=hdr, twist=T["Twist"](linear=T["Vector3"](5.0, 0.0, 1.0),
                                                            angular=T["Vector3"](0.0, 0.0, 0.0)))
        msgs.append(("/vel", "geometry_msgs/msg/TwistStamped", tw, t))
    p = str(tmp_path / "hand.mcap")
    _hand_mcap(p, msgs)

    north = parsers.load(p + "::imu=/imu_north,vel=/vel")
    np.testing.assert_allclose(north.gyro_rad_s(), np.tile([0.0, 0.0, -0.1], (20, 1)), atol=1e-15)
    np.testing.assert_allclose(north.accel_m_s2(), np.tile([0.0, 0.0, -9.81], (20, 1)), atol=1e-15)
    rpy = euler_from_quat(north.quat_wxyz()[1])
    np.testing.assert_allclose(rpy, np.zeros((20, 3)), atol=1e-12)  # heading north = yaw 0
    np.testing.assert_allclose(north.vel_ned_m_s()[1], np.tile([0.0, 5.0, -1.0], (20, 1)), atol=1e-15)

    east = parsers.load(p + "::imu=/imu_east")
    rpy = euler_from_quat(east.quat_wxyz()[1])
    np.testing.assert_allclose(rpy[:, 2], 90 * DEG, atol=1e-12)
    np.testing.assert_allclose(rpy[:, :2], 0.0, atol=1e-12)

    od = parsers.load(p + "::odom=/odom")
    np.testing.assert_allclose(od.gyro_rad_s(), np.tile([0.0, 0.0, -0.1], (20, 1)), atol=1e-15)
    np.testing.assert_allclose(od.vel_ned_m_s()[1], np.tile([3.0, 0.0, 0.0], (20, 1)), atol=1e-12)
    assert not od.has_accel


def test_attitude_from_odometry_when_the_imu_has_none(tmp_path):
    """An Imu that says "no orientation" (orientation_covariance[0] = -1, the ROS convention) beside an
    Odometry: with no selector, the attitude comes from the Odometry's pose (heading north: yaw 0)."""
    T = _ros_types()
    msgs = []
    for k in range(20):
        t = T0_NS + k * 10_000_000
        msgs.append(("/imu", "sensor_msgs/msg/Imu", _rates_only_imu_msg(T, t), t))
        msgs.append(("/odom", "nav_msgs/msg/Odometry", _odom_north_msg(T, t), t))
    p = str(tmp_path / "odom_att.mcap")
    _hand_mcap(p, msgs)
    _assert_heading_north_turning_left(parsers.load(p))


def _rates_only_imu_msg(T, t_ns: int):
    """An Imu turning left at 0.1 rad/s, level, that says "no orientation" (orientation_covariance[0] = -1)."""
    imu = _imu_msg(T, t_ns, (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.1), (0.0, 0.0, 9.81))
    imu.orientation_covariance[0] = -1.0
    return imu


def _assert_heading_north_turning_left(log, n: int = 20) -> None:
    assert log.has_quat, log.meta.warnings
    np.testing.assert_allclose(euler_from_quat(log.quat_wxyz()[1]), np.zeros((n, 3)), atol=1e-12)
    np.testing.assert_allclose(log.gyro_rad_s(), np.tile([0.0, 0.0, -0.1], (n, 1)), atol=1e-15)


# ---- the fast path against the libraries --------------------------------------------------------
def _fields_equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_fast_path_matches_mcap_ros2_decoder(written):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    p = written["x.mcap"]
    raw = mcap_ros.read_raw(p)
    with open(p, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        ref: dict[str, list] = {}
        for _s, ch, _m, msg in reader.iter_decoded_messages():
            ref.setdefault(ch.topic, []).append(msg)
    assert set(ref) == {"/imu", "/velocity", "/fix"}
    for topic, msgs in ref.items():
        rt = raw.topics[topic]
        paths = {**rc.FIELDS[rt.msgtype], **rc.STAMP_FIELDS}
        dec = rc.decode_topic(raw.typestore, rt, paths)
        assert dec.n_fast == len(msgs) and dec.n_slow == 0
        lib = {k: np.array([float(rc._getpath(m, pth)) for m in msgs]) for k, pth in paths.items()}
        _fields_equal(dec.columns, lib)


@pytest.mark.parametrize("name", ["x.bag", "x1.mcap", "bag_sqlite"])
def test_fast_path_matches_rosbags(written, name):
    """Per message: our vectorised decode == rosbags deserialiser (ROS 1 and CDR)."""
    p = written[name]
    raw = (rosbag1.read_raw(p) if name.endswith(".bag") else
           mcap_ros.read_raw(p) if name.endswith(".mcap") else rosbag2.read_raw(p))
    for rt in raw.topics.values():
        paths = {**rc.FIELDS[rt.msgtype], **rc.STAMP_FIELDS}
        fast = rc.decode_topic(raw.typestore, rt, paths)
        assert fast.n_fast == rt.count > 0
        _fields_equal(fast.columns, rc.library_decode(raw.typestore, rt, paths))
    if name == "x.bag":  # and rosbags' own reader sees the same raw bytes and record times
        from rosbags.highlevel import AnyReader

        with AnyReader([Path(p)]) as r:
            got = {}
            for conn, t, data in r.messages():
                got.setdefault(conn.topic, []).append((t, bytes(data)))
        for topic, items in got.items():
            assert [t for t, _ in items] == raw.topics[topic].log_ns
            assert [d for _, d in items] == [bytes(d) for d in raw.topics[topic].data]


@pytest.mark.parametrize("encoding", ["cdr", "ros1"])
def test_fast_path_mixed_frames_and_odd_messages(encoding):
    """Two frame_id lengths (two fixed-layout groups) decode like the library, message for message;
    a message whose string length field does not match its group's layout goes to the library."""
    ts = rc.default_typestore(encoding)
    n = 50
    cols = {"header.stamp.sec": np.arange(n) + 1_700_000_000, "header.stamp.nanosec": np.arange(n) * 1000,
            "angular_velocity.x": np.linspace(-1, 1, n), "linear_acceleration.z": np.linspace(9, 10, n),
            "orientation.w": np.ones(n)}
    a = rc.encode_messages(ts, rc.IMU, rc._template(ts, rc.IMU, "imu", encoding), encoding, cols)
    b = rc.encode_messages(ts, rc.IMU, rc._template(ts, rc.IMU, "imu_link_long", encoding), encoding, cols)
    data = [a[i] if i % 3 else b[i] for i in range(n)]
    assert len({len(d) for d in data}) == 2
    paths = {**rc.FIELDS[rc.IMU], **rc.STAMP_FIELDS}
    raw = rc.RawTopic("/imu", rc.IMU, encoding, list(range(n)), data)
    fast = rc.decode_topic(ts, raw, paths)
    slow = rc.decode_topic(ts, raw, paths, fast=False)
    assert fast.n_fast == n and slow.n_slow == n
    _fields_equal(fast.columns, slow.columns)
    np.testing.assert_array_equal(fast.columns["gx"], cols["angular_velocity.x"])
    if encoding == "cdr":
        # frame_id "imu\0" (length 4) rewritten as "im\0" + pad (length 3): same size, same alignment of what
        # follows, but not the group's layout -> the check rejects it, the library decodes it
        odd = bytearray(data[1])
        assert int.from_bytes(odd[12:16], "little") == 4
        odd[12:16] = (3).to_bytes(4, "little")
        odd[18] = 0  # "im\0" + one padding byte
        data2 = list(data)
        data2[1] = bytes(odd)
        raw2 = rc.RawTopic("/imu", rc.IMU, encoding, list(range(n)), data2)
        dec = rc.decode_topic(ts, raw2, paths)  # a second layout of the same length takes it
        assert dec.n_fast == n and dec.n_slow == 0
        _fields_equal(dec.columns, rc.library_decode(ts, raw2, paths))
        assert ts.deserialize_cdr(data2[1], rc.IMU).header.frame_id == "im"
        # unknown encapsulation: no layout, the library is asked, cannot decode it -> NaN row
        data2[2] = b"\x00\x07" + data2[2][2:]
        dec = rc.decode_topic(ts, rc.RawTopic("/imu", rc.IMU, encoding, list(range(n)), data2), paths)
        assert dec.n_fast == n - 1 and dec.n_slow == 1
        assert np.isnan(dec.columns["gx"][2]) and np.isfinite(np.delete(dec.columns["gx"], 2)).all()


@pytest.mark.parametrize("encoding", ["cdr", "ros1"])
def test_the_frame_id_read_in_place_is_the_libraries(encoding):
    """``header_frame_id`` (the frame_id where the encoding puts it) gives what rosbags' deserialiser gives, for
    every header-first type tapost reads, empty and long and non-ASCII frame ids, big-endian CDR; None for a
    type without a header first, a short or damaged message (the library is asked then)."""
    ts = rc.default_typestore(encoding)
    deser = ts.deserialize_cdr if encoding == "cdr" else ts.deserialize_ros1
    cols = {"header.stamp.sec": np.array([1_700_000_000]), "header.stamp.nanosec": np.array([5])}
    seen = 0
    for msgtype in sorted(rc.SUPPORTED):
        if ts.fielddefs[msgtype][1][0][0] != "header":
            continue
        for frame in ("", "imu", "base_link_with_a_long_name", "capteur_é"):
            data = rc.encode_messages(ts, msgtype, rc._template(ts, msgtype, frame, encoding), encoding, cols)[0]
            assert rc.header_frame_id(ts, msgtype, data, encoding) == deser(data, msgtype).header.frame_id == frame
            seen += 1
            if encoding == "cdr":
                big = ts.serialize_cdr(deser(data, msgtype), msgtype, little_endian=False)
                assert big[1] == 0 and rc.header_frame_id(ts, msgtype, big, encoding) == frame
    assert seen >= 8
    data = rc.encode_messages(ts, rc.IMU, rc._template(ts, rc.IMU, "imu", encoding), encoding, cols)[0]
    assert rc.header_frame_id(ts, rc.IMU, data[:14], encoding) is None  # (cut inside the string)
    assert rc.header_frame_id(ts, "geometry_msgs/msg/Vector3", data, encoding) is None
    bad = bytearray(data)
    bad[12:16] = (1000).to_bytes(4, "little")  # a length past the message's end
    assert rc.header_frame_id(ts, rc.IMU, bytes(bad), encoding) is None


# ---- real data ---------------------------------------------------------------------------------
@pytest.mark.skipif(not CAR_BAG.exists(), reason="../shared/realdata absent")
def test_real_car_bag():
    inv = parsers.inspect_log(str(CAR_BAG))
    assert inv.format == "rosbag1"
    by = {s.name: s for s in inv.streams}
    assert by["/xsens/imu_data"].kind == "imu" and by["/xsens/imu_data"].rate_hz == pytest.approx(100, rel=0.02)
    assert by["/stereo_odometer/odometry"].rate_hz == pytest.approx(10, rel=0.05)
    assert by["/wheel_odometry"].kind == "odom"
    assert by["/xsens/imu_data"].duration_s == pytest.approx(134, abs=1.5)
    assert "imu=/xsens/imu_data" in inv.selectors and "odom=/stereo_odometer/odometry" in inv.selectors
    assert by["/xsens/imu_data"].clock.startswith("epoch")

    imu = parsers.load(f"{CAR_BAG}::imu=/xsens/imu_data")
    assert imu.meta.clock == "epoch" and imu.meta.selector == "imu=/xsens/imu_data"
    assert len(imu.imu) == pytest.approx(13334, abs=20)
    assert imu.duration_s == pytest.approx(134, abs=1.5)
    acc = imu.accel_m_s2()
    assert np.linalg.norm(acc.mean(axis=0)) == pytest.approx(9.8, abs=0.3)
    assert acc[:, 2].mean() < -9.0  # FLU z up at rest -> FRD z = -g
    assert imu.has_quat and np.abs(imu.gyro_rad_s()).max() > 0.05

    odo = parsers.load(f"{CAR_BAG}::odom=/stereo_odometer/odometry")
    assert odo.has_gyro and not odo.has_accel
    assert len(odo.imu) == pytest.approx(1313, abs=5)
    assert odo.meta.channels["gyro"].rate_hz == pytest.approx(10, rel=0.05)
    assert np.abs(odo.gyro_rad_s()[:, 2]).max() > 0.05  # the car turns
    # default pick: the first Imu topic in the bag, reported
    dflt = parsers.load(str(CAR_BAG))
    assert dflt.meta.channels["gyro"].source == "/xsens/imu_data"
    assert any("selected imu=/xsens/imu_data" in w for w in dflt.meta.warnings)


# ---- bad input ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def big_files(tmp_path_factory) -> dict[str, str]:
    """Multi-chunk files (so that damage in one chunk leaves readable chunks)."""
    d = tmp_path_factory.mktemp("ros_big")
    log = synthetic_log(12000, rate_hz=200.0)
    out = {}
    for fmt, opts, name in [("mcap", {}, "b.mcap"), ("rosbag1", {}, "b.bag"), ("rosbag2", {"storage": "sqlite3"}, "bdir")]:
        p = str(d / name)
        registry.write(p, log, fmt, **opts)
        out[fmt] = p if fmt != "rosbag2" else os.path.join(p, [f for f in os.listdir(p) if f.endswith(".db3")][0])
    out["log"] = log
    return out


def _copy_with(src: str, dst: str, data: bytes) -> str:
    with open(dst, "wb") as fh:
        fh.write(data)
    return dst


def _cli_fails(path: str, capsys) -> str:
    assert cli_main(["inspect", path]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and path in err
    return err


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1", "rosbag2"])
def test_truncated_file_uses_readable_part(big_files, tmp_path, fmt):
    src = big_files[fmt]
    data = open(src, "rb").read()
    p = _copy_with(src, str(tmp_path / ("t_" + os.path.basename(src))), data[: int(len(data) * 0.6)])
    # (sqlite3: SQLite cannot follow the messages' b-tree of a cut file, whose interior pages are written
    # late; its leaf pages are read one by one, parsers.restamp_sqlite.recover)
    back = parsers.load(p)
    n_full = len(big_files["log"].imu)
    assert 0.3 * n_full < len(back.imu) < n_full
    assert any("truncated" in w for w in back.meta.warnings)
    ref = big_files["log"]
    k = len(back.imu)
    np.testing.assert_array_equal(back.gyro_rad_s(), ref.gyro_rad_s()[:k])


def mcap_with_a_flipped_chunk(path: str, k: int, undecodable: bool = False) -> tuple[bytes, int]:
    """The MCAP file's bytes with one byte inverted in the middle of its k-th chunk's (compressed) records,
    and that chunk's offset; ``undecodable``: the first 32 bytes of its compressed records zeroed instead
    (the zstd frame header gone: nothing of the chunk decompresses)."""
    import struct

    data = bytearray(open(path, "rb").read())
    off, chunks = 8, []
    while data[off] != 2:  # the top-level records up to the footer
        op, ln = struct.unpack_from("<BQ", data, off)
        if op == 6:
            chunks.append((off, ln))
        off += 9 + ln
    assert len(chunks) > 2
    at, ln = chunks[k]
    if undecodable:
        comp_len = struct.unpack_from("<I", data, at + 9 + 28)[0]
        c0 = at + 9 + 28 + 4 + comp_len + 8  # the compressed records: after the compression name and their size
        data[c0:c0 + 32] = bytes(32)
    else:
        data[at + 9 + ln // 2] ^= 0xFF
    return bytes(data), at


def test_mcap_damaged_first_chunk_keeps_the_channels_it_defined(big_files, tmp_path):
    """The writer puts schema and channel records in the first chunk (and again in the summary). Damage
    there dropped the definitions with the chunk, and every later message was of an undefined channel:
    nothing readable. The summary's definitions (through the footer) keep the later chunks."""
    src = big_files["mcap"]
    data, first = mcap_with_a_flipped_chunk(src, 0, undecodable=True)
    p = _copy_with(src, str(tmp_path / "first.mcap"), data)
    back = parsers.load(p)
    n_full = len(big_files["log"].imu)
    assert 0.3 * n_full < len(back.imu) < n_full
    assert any(f"chunk at byte {first}" in w for w in back.meta.warnings)
    rr = pytest.importorskip("parsers.restamp_ros")
    st = rr.restamp_mcap(p, str(tmp_path / "first_out.mcap"), ClockShift(0.001, 0.0, big_files["log"].meta.t0_ns))
    assert st.records > 0.3 * n_full and any(f"chunk at byte {first}" in d for d in st.damage)


def _mcap_chunks(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of the chunk records along the top-level records up to the footer."""
    import struct

    off, out = 8, []
    while data[off] != 2:
        op, ln = struct.unpack_from("<BQ", data, off)
        if op == 6:
            out.append((off, ln))
        off += 9 + ln
    return out


def test_a_compressed_chunk_failing_its_crc_is_read_as_far_as_its_message_index_agrees(big_files):
    """A zstd chunk that decompresses to other bytes was dropped whole (8 inverted bytes in a 40 s MCAP: a
    median 22 % of the IMU samples kept, 4 copies of 20 refused). Its records are now read as far as each
    message record lies where the chunk's message index says, with its channel and log time, the record
    before the first disagreement dropped too. Here on a real chunk's decompressed records: intact; a log
    time changed; records repeated from an earlier offset with old times (what zstd's copies from wrong
    offsets make); no message index after the chunk."""
    import struct

    data = open(big_files["mcap"], "rb").read()
    off, ln = _mcap_chunks(data)[1]
    nxt = off + 9 + ln
    content = mcap_ros.inflate_chunk(data, off, nxt)
    arr = np.frombuffer(content, np.uint8)
    m, _cid, _t, s, *_ = mcap_ros._walk_kernel()(arr, 0, len(arr))
    rec = (s[:m] - 31).tolist()
    assert m > 100 and mcap_ros.index_checked_prefix(data, nxt, content) == (len(content), m, m)
    j = m // 3
    changed = bytearray(content)
    struct.pack_into("<Q", changed, rec[j] + 15, struct.unpack_from("<Q", content, rec[j] + 15)[0] + 1)
    assert mcap_ros.index_checked_prefix(data, nxt, bytes(changed)) == (rec[j - 1], j - 1, m)
    repeated = bytearray(content)
    repeated[rec[j]:] = content[rec[0]:rec[0] + len(content) - rec[j]]
    assert mcap_ros.index_checked_prefix(data, nxt, bytes(repeated)) == (rec[j - 1], j - 1, m)
    # the kept part walks as the intact chunk's first j - 1 messages
    m2, *_ = mcap_ros._walk_kernel()(np.frombuffer(bytes(repeated[:rec[j - 1]]), np.uint8), 0, rec[j - 1])
    assert m2 == j - 1
    assert mcap_ros.index_checked_prefix(data, off, content) is None  # (at ``off``: a chunk, no message index)
    empty = b"\x07" + struct.pack("<Q", 6) + struct.pack("<HI", 1, 0)  # (a message index listing nothing)
    assert mcap_ros.index_checked_prefix(empty, 0, content) is None
    bad = mcap_ros._BadCrc("chunk: CRC mismatch", bytes(repeated), compressed=True)
    kept, said = mcap_ros.crc_damage_content(bad, data, nxt)
    assert len(kept) == rec[j - 1] and f"first {j - 1} of {m} messages" in said
    with pytest.raises(mcap_ros._Damage, match="no message index"):
        mcap_ros.crc_damage_content(bad, data, off)


def test_the_python_mcap_record_walk_equals_the_compiled_one(big_files):
    """mcap_ros._walk_py (the plain Python code's walk of a chunk's records: offsets in the loop, channel
    ids and log times gathered after it) against the compiled _walk on a real chunk: whole, cut inside a
    record, a length made to run past the end, an opcode zeroed: the same messages, records and error."""
    import struct

    numba = pytest.importorskip("numba")
    data = open(big_files["mcap"], "rb").read()
    off, ln = _mcap_chunks(data)[1]
    content = mcap_ros.inflate_chunk(data, off, off + 9 + ln)
    m, _cid, _t, s, *_ = mcap_ros._walk_kernel()(np.frombuffer(content, np.uint8), 0, len(content))
    rec = (s[:m] - 31).tolist()
    long_len = bytearray(content)
    struct.pack_into("<Q", long_len, rec[m // 2] + 1, len(content))
    zero_op = bytearray(content)
    zero_op[rec[m // 3]] = 0
    compiled = numba.njit(cache=True)(mcap_ros._walk)
    for name, b in (("whole", content), ("cut", content[:rec[m // 2] + 20]), ("long", bytes(long_len)),
                    ("opcode", bytes(zero_op)), ("tail", content[rec[5]:])):
        want = compiled(np.frombuffer(b, np.uint8), 0, len(b))
        got = mcap_ros._walk_py(b, 0, len(b))
        k_want, k_got = want[0], got[0]
        assert k_want == k_got and want[5] == got[5] and want[9:] == got[9:], name
        for a, c, n in zip(want[1:5] + want[6:9], got[1:5] + got[6:9], (k_want,) * 4 + (want[5],) * 3):
            np.testing.assert_array_equal(a[:n], c[:n], err_msg=name)


def test_mcap_zeroed_stretch_goes_on_at_the_next_chunk_the_summary_lists(big_files, tmp_path):
    """4 KiB zeroed across the end of a chunk and the records after it: the walk met opcode 0 and ignored the
    rest of the file. It now goes on at the next chunk the summary's chunk index lists (parse and export)."""
    src = big_files["mcap"]
    data = bytearray(open(src, "rb").read())
    chunks = _mcap_chunks(bytes(data))
    at, ln = chunks[1]
    end = at + 9 + ln
    data[end - 100:end + 3996] = bytes(4096)
    p = _copy_with(src, str(tmp_path / "zero.mcap"), bytes(data))
    back = parsers.load(p)
    n_full = len(big_files["log"].imu)
    assert len(back.imu) > (1 - 2 / len(chunks)) * n_full  # the damaged chunk (and at most one more) lost
    nxt = next(c for c, _ in chunks if c > end)
    assert any(f"went on at the next chunk the summary lists (byte {nxt})" in w for w in back.meta.warnings)
    rr = pytest.importorskip("parsers.restamp_ros")
    st = rr.restamp_mcap(p, str(tmp_path / "zero_out.mcap"), ClockShift(0.001, 0.0, big_files["log"].meta.t0_ns))
    assert any(f"(byte {nxt})" in d for d in st.damage)
    assert len(parsers.load(str(tmp_path / "zero_out.mcap")).imu) == len(back.imu)


def test_mcap_chunk_damaged_late_keeps_the_messages_before_the_damage(big_files, tmp_path):
    """Bytes inverted late in a zstd chunk's compressed records: the blocks before them still decompress and
    their complete messages are kept (parse and export), the rest of that chunk is named as lost."""
    src = big_files["mcap"]
    clean = bytes(open(src, "rb").read())
    at, ln = _mcap_chunks(clean)[1]
    for frac in np.linspace(0.9, 0.5, 21):  # 16 bytes inverted: where zstd itself finds the damage
        data = bytearray(clean)
        k = at + 9 + int(ln * frac)
        data[k:k + 16] = bytes(b ^ 0xFF for b in data[k:k + 16])
        try:
            mcap_ros.inflate_chunk(memoryview(bytes(data)), at, at + 9 + ln)
        except mcap_ros._Undecodable:
            break
        except mcap_ros._Damage:  # (decompressed to other bytes: the CRC check's case, not this test's)
            continue
    else:
        pytest.fail("no damage zstd detects")
    p = _copy_with(src, str(tmp_path / "late.mcap"), bytes(data))
    full = mcap_ros.read_raw(src)
    raw = mcap_ros.read_raw(p)
    n_full = sum(t.count for t in full.topics.values())
    n = sum(t.count for t in raw.topics.values())
    w = [x for x in raw.warnings if f"chunk at byte {at}" in x]
    assert len(w) == 1 and "complete messages before the damage kept" in w[0], raw.warnings
    kept = int(w[0].split("; the ")[-1].split(" complete")[0])
    per_chunk = n_full / len(_mcap_chunks(bytes(data)))
    assert 0.5 * per_chunk < kept < per_chunk and n_full - per_chunk < n < n_full  # the chunk's first part kept
    rr = pytest.importorskip("parsers.restamp_ros")
    st = rr.restamp_mcap(p, str(tmp_path / "late_out.mcap"), ClockShift(0.001, 0.0, big_files["log"].meta.t0_ns))
    assert st.records == n and any(f"the {kept} complete messages before the damage kept" in d for d in st.damage)


def test_rosbag1_damaged_record_in_a_chunk_loses_that_record_not_the_rest_of_the_chunk(big_files, tmp_path):
    """A record's data length damaged in the middle of a chunk: the walk resynchronises at the next
    record of a known layout (before, the rest of the chunk, up to 1 MB of messages, was dropped)."""
    import struct

    src = big_files["rosbag1"]
    data = bytearray(open(src, "rb").read())
    k = data.find(b"op=\x02", len(data) // 2)
    r = next(r for r in range(k - 64, k - 7)  # the record start: its header holds the op field at k - 4
             if k + 4 <= r + 4 + struct.unpack_from("<I", data, r)[0] < r + 200
             and rosbag1._fields(bytes(data[r + 4:r + 4 + struct.unpack_from("<I", data, r)[0]])).get("op") == b"\x02")
    hlen = struct.unpack_from("<I", data, r)[0]
    struct.pack_into("<I", data, r + 4 + hlen, 0xFFFFFF00)  # the data length: runs past the chunk
    p = _copy_with(src, str(tmp_path / "d.bag"), bytes(data))
    n_all = sum(len(t.log_ns) for t in rosbag1.read_raw(src).topics.values())
    raw = rosbag1.read_raw(p)
    assert sum(len(t.log_ns) for t in raw.topics.values()) == n_all - 1
    assert any("1 damaged record(s)" in w for w in raw.warnings)
    back = parsers.load(p)
    assert len(back.imu) >= len(big_files["log"].imu) - 1


@pytest.mark.parametrize("frac", [0.95, 0.3])
def test_truncated_sqlite3_bag_reads_every_whole_page(big_files, tmp_path, frac):
    """A .db3 cut short (a copy interrupted): every row on the pages that are whole is read, in order, by
    the page scan, and the warning says the file is truncated and up to which row; the IMU samples are
    the input's first ones exactly."""
    src = big_files["rosbag2"]
    data = open(src, "rb").read()
    p = _copy_with(src, str(tmp_path / "cut.db3"), data[: int(len(data) * frac)])
    back = parsers.load(p)
    ref = big_files["log"]
    k = len(back.imu)
    assert (frac - 0.1) * len(ref.imu) < k < len(ref.imu)
    np.testing.assert_array_equal(back.gyro_rad_s(), ref.gyro_rad_s()[:k])
    np.testing.assert_allclose(back.t_imu_s() + (back.meta.t0_ns - ref.meta.t0_ns) * 1e-9, ref.t_imu_s()[:k],
                               rtol=0, atol=1e-9)
    (w,) = [w for w in back.meta.warnings if "sqlite3 storage damaged" in w]
    assert "read from its intact pages by a page scan" in w and "truncated" in w, w


def test_sqlite3_page_scan_finds_every_row_of_a_whole_file(big_files):
    """The page scan of an undamaged .db3 gives exactly what SQLite gives: every row, in id order."""
    import sqlite3

    from parsers import restamp_sqlite

    src = big_files["rosbag2"]
    rec = restamp_sqlite.recover(src)
    con = sqlite3.connect(f"file:{src}?mode=ro", uri=True)
    rows = con.execute("SELECT id, topic_id, timestamp, data FROM messages ORDER BY id").fetchall()
    con.close()
    assert not rec.truncated and rec.cells_passed_over == 0
    assert rec.rowid.tolist() == [r[0] for r in rows]
    assert rec.topic.tolist() == [r[1] for r in rows] and rec.timestamp.tolist() == [r[2] for r in rows]
    assert rec.data == [r[3] for r in rows]


def test_sqlite3_bag_with_a_zeroed_page_loses_only_that_page(big_files, tmp_path):
    """A zeroed 4 KiB page of the storage file: the rows on it are lost and named; the batch of 2000 rows
    around it is not (the reader bisects a batch that fails)."""
    src = big_files["rosbag2"]
    data = bytearray(open(src, "rb").read())
    page = len(data) // 4096 // 2 * 4096
    data[page:page + 4096] = bytes(4096)
    p = _copy_with(src, str(tmp_path / "z.db3"), bytes(data))
    back = parsers.load(p)
    n_full = len(big_files["log"].imu)
    assert 0.98 * n_full < len(back.imu) < n_full  # one page holds a few records of each topic
    assert any("sqlite3 storage damaged" in w for w in back.meta.warnings)
    ref = big_files["log"]
    kept = np.isin(np.round(ref.t_imu_s() * 1e6), np.round(back.t_imu_s() * 1e6))  # to the us
    np.testing.assert_array_equal(back.gyro_rad_s(), ref.gyro_rad_s()[kept])


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_mcap_cut_inside_its_only_chunk_keeps_the_chunks_complete_messages(big_files, tmp_path, compression):
    """A recording killed while writing its (last, here only) chunk: the whole chunk was dropped, so a
    short MCAP cut anywhere read nothing. Its compressed part is now decompressed as far as it goes and
    the complete messages in it kept (what ``mcap recover`` does), identical to the written ones."""
    ref = big_files["log"]
    short = InsLog(imu=ref.imu.iloc[:1500], nav=ref.nav.iloc[:0], meta=ref.meta)
    src = str(tmp_path / f"one_{compression}.mcap")
    mcap_ros.write(src, short, compression=compression)
    data = open(src, "rb").read()
    p = _copy_with(src, str(tmp_path / "cut.mcap"), data[: int(len(data) * 0.5)])
    back = parsers.load(p)
    k = len(back.imu)
    assert 0.2 * len(short.imu) < k < len(short.imu)
    assert any("messages recovered" in w for w in back.meta.warnings)
    np.testing.assert_array_equal(back.gyro_rad_s(), short.gyro_rad_s()[:k])


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1", "rosbag2"])
def test_flipped_byte_is_reported_or_contained(big_files, tmp_path, fmt):
    src = big_files[fmt]
    data = bytearray(open(src, "rb").read())
    data[len(data) // 2] ^= 0xFF
    p = _copy_with(src, str(tmp_path / ("f_" + os.path.basename(src))), bytes(data))
    back = parsers.load(p)
    ref = big_files["log"]
    damage = [w for w in back.meta.warnings if not w.startswith("note")]
    if fmt == "mcap":  # chunk CRC: damage detected and reported, the other chunks used
        assert damage, back.meta.warnings
        assert 0.5 * len(ref.imu) < len(back.imu) < len(ref.imu)
    else:  # no checksum on ROS 1 bags / sqlite blobs: at most the message holding the byte differs,
        # or the damage is reported
        common = min(len(back.imu), len(ref.imu))
        diff = np.any(back.gyro_rad_s()[:common] != ref.gyro_rad_s()[:common], axis=1) | \
            np.any(back.accel_m_s2()[:common] != ref.accel_m_s2()[:common], axis=1)
        assert damage or diff.sum() <= 1


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1", "rosbag2"])
def test_random_empty_and_garbage_exit_2(big_files, tmp_path, fmt, capsys):
    src = big_files[fmt]
    head = open(src, "rb").read(64)
    rnd = np.random.default_rng(3).bytes(20000)
    ext = os.path.splitext(src)[1]
    p = _copy_with(src, str(tmp_path / f"rand{ext}"), rnd)
    assert "unrecognised format" in _cli_fails(p, capsys)
    p = _copy_with(src, str(tmp_path / f"empty{ext}"), b"")
    assert "empty file" in _cli_fails(p, capsys)
    p = _copy_with(src, str(tmp_path / f"magic_then_garbage{ext}"), head[:16] + rnd)
    _cli_fails(p, capsys)
    with pytest.raises(InputError):
        parsers.load(p)


def test_directory_without_metadata_exit_2(tmp_path, capsys, written):
    d = tmp_path / "not_a_bag"
    d.mkdir()
    shutil.copy(os.path.join(written["bag_sqlite"], [f for f in os.listdir(written["bag_sqlite"])
                                                      if f.endswith(".db3")][0]), d / "x.db3")
    err = _cli_fails(str(d), capsys)
    assert "metadata.yaml" in err
    with pytest.raises(InputError, match="no metadata.yaml"):
        rosbag2.load(str(d), parsers.base.Selector())


@pytest.mark.parametrize("name", ["x.mcap", "x.bag", "bag_mcap"])
def test_missing_or_wrong_topic_in_selector(written, name):
    p = written[name]
    with pytest.raises(InputError) as exc:
        parsers.load(p + "::imu=/nope")
    msg = str(exc.value)
    assert "\n" not in msg and "/nope" in msg and "no such topic" in msg and p in msg
    with pytest.raises(InputError, match="expected sensor_msgs/msg/Imu"):
        parsers.load(p + "::imu=/velocity")
    with pytest.raises(InputError, match="unknown selector key"):
        parsers.load(p + "::gyro=/imu")
    with pytest.raises(InputError, match="time="):
        parsers.load(p + "::time=gps")


def test_inspect_cli_lists_topics_and_selectors(written, capsys):
    assert cli_main(["inspect", written["x.bag"]]) == 0
    out = capsys.readouterr().out
    for s in ("/imu", "/velocity", "/fix", "imu=/imu,vel=/velocity,pos=/fix", "epoch"):
        assert s in out


def test_sim_time_clock_and_zero_stamps(tmp_path):
    """Small stamps are sim/boot time; all-zero header stamps fall back to log time (reported)."""
    log = synthetic_log(200)
    boot = log.with_meta(t0_ns=12_345_678_901)  # 12.3 s after boot / sim start
    p = str(tmp_path / "boot.bag")
    rosbag1.write(p, boot)
    back = parsers.load(p)
    assert back.meta.clock == "boot" and back.meta.t0_ns == 12_345_678_901
    assert parsers.inspect_log(p).streams[0].clock.startswith("boot")

    T = _ros_types()
    msgs = [("/imu", "sensor_msgs/msg/Imu", _imu_msg(T, 0, (0, 0, 0, 1), (0.0, 0.0, 0.1), (0, 0, 9.81)),
             T0_NS + k * 5_000_000) for k in range(30)]
    p = str(tmp_path / "zero.mcap")
    _hand_mcap(p, msgs)
    z = parsers.load(p)
    assert z.meta.t0_ns == T0_NS and z.meta.clock == "epoch"
    assert "log time" in z.meta.stamp_source
    assert any("header stamps are all zero" in w for w in z.meta.warnings)
    assert z.meta.channels["gyro"].rate_hz == pytest.approx(200.0)


def test_odometry_only_log_defaults_to_odom_gyro(tmp_path):
    T = _ros_types()
    msgs = []
    for k in range(25):
        t = T0_NS + k * 100_000_000
        hdr = T["Header"](stamp=T["Time"](sec=t // 10**9, nanosec=t % 10**9), frame_id="odom")
        msgs.append(("/wheel", "nav_msgs/msg/Odometry", T["Odometry"](
            header=hdr, child_frame_id="base_link",
            pose=T["PoseWithCovariance"](pose=T["Pose"](position=T["Point"](0.0, 0.0, 0.0),
                                                       orientation=T["Quaternion"](0.0, 0.0, 0.0, 1.0)),
                                         covariance=np.zeros(36)),
            twist=T["TwistWithCovariance"](twist=T["Twist"](linear=T["Vector3"](2.0, 0.0, 0.0),
                                                            angular=T["Vector3"](0.0, 0.0, -0.2)),
                                           covariance=np.zeros(36))), t))
    p = str(tmp_path / "odo.mcap")
    _hand_mcap(p, msgs)
    back = parsers.load(p)
    assert any("gyro from odom=/wheel" in w for w in back.meta.warnings)
    np.testing.assert_allclose(back.gyro_rad_s()[:, 2], 0.2)  # FLU right turn -> FRD +z
    np.testing.assert_allclose(back.vel_ned_m_s()[1], np.tile([0.0, 2.0, 0.0], (25, 1)), atol=1e-12)  # east
    assert parsers.inspect_log(p).selectors == ("odom=/wheel",)


def test_fast_quaternion_transform_equals_conventions():
    from logtools.conventions import quat_enu_flu_to_ned_frd, quat_ned_frd_to_enu_flu

    q = np.random.default_rng(5).normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    assert same_quat(rc.quat_enu_flu_to_ned_frd_fast(q), quat_enu_flu_to_ned_frd(q), 1e-15)
    assert same_quat(rc.quat_enu_flu_to_ned_frd_fast(q), quat_ned_frd_to_enu_flu(q), 1e-15)


@pytest.mark.parametrize("name", ["bag_sqlite_zfile", "bag_sqlite_zmsg", "bag_mcap_zfile", "bag_mcap_zmsg"])
def test_compressed_rosbag2_reads_as_rosbags_does(written, name):
    """zstd file- and message-compressed ROS 2 bags: the same raw messages and record times as rosbags'
    own reader, and the input files untouched."""
    from rosbags.highlevel import AnyReader

    p = written[name]
    before = {f: os.path.getsize(os.path.join(p, f)) for f in os.listdir(p)}
    raw = rosbag2.read_raw(p)
    with AnyReader([Path(p)]) as r:
        got = {}
        for conn, t, data in r.messages():
            got.setdefault(conn.topic, []).append((t, bytes(data)))
    assert got
    for topic, items in got.items():
        assert [t for t, _ in items] == raw.topics[topic].log_ns
        assert [d for _, d in items] == [bytes(d) for d in raw.topics[topic].data]
    assert {f: os.path.getsize(os.path.join(p, f)) for f in os.listdir(p)} == before


@pytest.mark.parametrize("name", ["bag_sqlite", "bag_mcap", "bag_sqlite_zfile", "bag_sqlite_zmsg", "bag_mcap_zfile",
                                  "bag_mcap_zmsg"])
@pytest.mark.parametrize("damage", [b"\x00" * 40, b"rosbag2_bagfile_information: [\xff\xfe"])
def test_rosbag2_with_a_damaged_metadata_yaml_is_read_from_its_storage(written, tmp_path, name, damage):
    """A ROS 2 bag whose metadata.yaml is damaged (zeroed bytes, garbage): its storage files name their topics
    and types themselves, so the bag is read from them with the damage said (it was refused with
    'metadata.yaml unreadable'); a per-message compressed bag is recognised by its zstd frames. The native
    export writes the messages read, with rosbags' writer making metadata.yaml anew (it was refused, as the
    export copies a sound metadata.yaml): the same samples on the master's clock, the damage named."""
    src = written[name]
    bad = tmp_path / "bad"
    shutil.copytree(src, bad)
    meta = bad / "metadata.yaml"
    meta.write_bytes(damage + meta.read_bytes()[len(damage):])
    want, got = parsers.load(src), parsers.load(str(bad))
    np.testing.assert_array_equal(got.imu.to_numpy(), want.imu.to_numpy())
    np.testing.assert_array_equal(got.nav.to_numpy(), want.nav.to_numpy())
    assert got.meta.t0_ns == want.meta.t0_ns
    assert any(w.startswith("damaged: metadata.yaml") and "read without it" in w for w in got.meta.warnings)
    shift = ClockShift(0.01, 0.0, got.meta.t0_ns)
    from parsers import restamp_ros

    st = restamp_ros.restamp_rosbag2(str(bad), str(tmp_path / "out"), shift)
    assert any("metadata.yaml" in d and "not copied" in d for d in st.damage)
    back = parsers.load(str(tmp_path / "out"))
    assert not any("metadata.yaml" in w for w in back.meta.warnings)  # (a sound bag)
    np.testing.assert_array_equal(back.imu.to_numpy(), got.imu.to_numpy())
    t_in = got.meta.t0_ns + np.round(got.t_imu_s() * 1e9).astype(np.int64)
    t_out = back.meta.t0_ns + np.round(back.t_imu_s() * 1e9).astype(np.int64)
    np.testing.assert_array_equal(t_out, shift.to_master_ns(t_in))
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "out"]) as r:  # (the format's own reader: every message there)
        assert sum(1 for _ in r.messages()) == st.records


def test_rosbag2_sqlite_storage_with_bytes_put_before_it_is_read_from_its_header(written, tmp_path):
    """A .db3 with bytes put before the database (a transfer's garbage in front of it) was refused ('not an
    SQLite database'); SQLite reads a file from its start, so a copy from the database's own header (found
    within the first 64 KiB) is read, saying so: the same samples."""
    src = written["bag_sqlite"]
    bad = tmp_path / "bad"
    shutil.copytree(src, bad)
    db = next(p for p in bad.iterdir() if p.suffix == ".db3")
    db.write_bytes(b"\x00garbage\xff" * 150 + db.read_bytes())
    want, got = parsers.load(src), parsers.load(str(bad))
    np.testing.assert_array_equal(got.imu.to_numpy(), want.imu.to_numpy())
    np.testing.assert_array_equal(got.nav.to_numpy(), want.nav.to_numpy())
    assert any(f"its first 1350 bytes are not SQLite's" in w for w in got.meta.warnings), got.meta.warnings
    assert [p.name for p in bad.iterdir() if "tapost" in p.name] == []


def test_truncated_compressed_rosbag2_is_one_clear_error(written, tmp_path, capsys):
    src = written["bag_sqlite_zfile"]
    bad = tmp_path / "bad"
    shutil.copytree(src, bad)
    z = [f for f in os.listdir(bad) if f.endswith(".zstd")][0]
    data = (bad / z).read_bytes()
    (bad / z).write_bytes(data[: len(data) // 2])
    rc_ = cli_main(["inspect", str(bad)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc_ == 2 and len(err) == 1 and "decompress" in err[0]


# ---- decoding while reading (mcap_ros.read_streamed): the same as reading the bytes, then decoding --------
def _same_inslog(a: InsLog, b: InsLog) -> None:
    from pandas.testing import assert_frame_equal

    assert_frame_equal(a.imu, b.imu, check_exact=True)
    assert_frame_equal(a.nav, b.nav, check_exact=True)
    assert a.meta == b.meta


def _streamed_equals_classic(p: str, selector: str = "") -> None:
    from parsers.base import Selector

    sel = Selector.parse(selector)
    classic = rc.to_inslog(mcap_ros.read_raw(p), sel)
    streamed_raw = mcap_ros.read_streamed(p)
    assert any(t.decoded is not None for t in streamed_raw.topics.values())
    _same_inslog(rc.to_inslog(streamed_raw, sel, release=True), classic)
    _same_inslog(parsers.load(f"{p}::{selector}" if selector else p), classic)
    assert rc.to_inventory(mcap_ros.read_streamed(p)) == rc.to_inventory(mcap_ros.read_raw(p))
    raw = mcap_ros.read_raw(p)
    for name, st in mcap_ros.read_streamed(p).topics.items():
        if st.decoded is None:
            continue
        dec = rc.decode_topic(raw.typestore, raw.topics[name], {**rc.FIELDS[st.msgtype], **rc.STAMP_FIELDS})
        pre = st.decoded
        assert (pre.n_fast, len(pre.slow_idx)) == (dec.n_fast, dec.n_slow)
        slow = np.isin(np.arange(st.count), pre.slow_idx)
        for k, v in pre.columns.items():
            np.testing.assert_array_equal(v[~slow], dec.columns[k][~slow], err_msg=k)
        sec, nsec = dec.columns["sec"][~slow], dec.columns["nsec"][~slow]
        np.testing.assert_array_equal(pre.stamp_ns[~slow], sec.astype(np.int64) * 1_000_000_000 + nsec.astype(np.int64))
        assert st.data == raw.topics[name].data[:rc.HEAD_MESSAGES]
        np.testing.assert_array_equal(st.log_ns, raw.topics[name].log_ns)


@pytest.mark.parametrize("name", ["x.mcap", "x1.mcap", "xn.mcap"])
def test_streamed_decode_equals_classic(written, name):
    _streamed_equals_classic(written[name])
    _streamed_equals_classic(written[name], "time=log")


def test_streamed_decode_of_damaged_files_equals_classic(big_files, tmp_path):
    src = big_files["mcap"]
    data = open(src, "rb").read()
    _streamed_equals_classic(_copy_with(src, str(tmp_path / "cut.mcap"), data[: int(len(data) * 0.6)]))
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0xFF
    _streamed_equals_classic(_copy_with(src, str(tmp_path / "flip.mcap"), bytes(flipped)))
    ref = big_files["log"]
    short = InsLog(imu=ref.imu.iloc[:1500], nav=ref.nav.iloc[:0], meta=ref.meta)
    one = str(tmp_path / "one.mcap")
    mcap_ros.write(one, short)
    data = open(one, "rb").read()
    _streamed_equals_classic(_copy_with(one, str(tmp_path / "onecut.mcap"), data[: int(len(data) * 0.5)]))


def _odd_imu_messages(n: int = 3000) -> tuple[object, list[bytes], np.ndarray]:
    """Imu messages with two frame_id lengths, one of the same length but another layout, one the library
    cannot read: every branch of the streaming decode (first layout, later tries, library, damaged)."""
    ts = rc.default_typestore("cdr")
    t_ns = T0_NS + np.arange(n, dtype=np.int64) * 5_000_000
    cols = {"header.stamp.sec": t_ns // 1_000_000_000, "header.stamp.nanosec": t_ns % 1_000_000_000,
            "angular_velocity.x": np.linspace(-1, 1, n), "linear_acceleration.z": np.linspace(9, 10, n),
            "orientation.w": np.ones(n)}
    a = rc.encode_messages(ts, rc.IMU, rc._template(ts, rc.IMU, "imu", "cdr"), "cdr", cols)
    b = rc.encode_messages(ts, rc.IMU, rc._template(ts, rc.IMU, "imu_link_long", "cdr"), "cdr", cols)
    data = [a[i] if i % 3 else b[i] for i in range(n)]
    odd = bytearray(data[2000])  # "imu\0" as "im\0" + pad: same length, a second layout
    odd[12:16] = (3).to_bytes(4, "little")
    odd[18] = 0
    data[2000] = bytes(odd)
    data[2500] = b"\x00\x07" + data[2500][2:]  # unknown encapsulation: the library, which cannot read it
    return ts, data, t_ns


def test_streamed_decode_of_odd_messages_equals_classic(tmp_path):
    ts, data, t_ns = _odd_imu_messages()
    p = str(tmp_path / "odd.mcap")
    with open(p, "wb") as fh:
        mcap_ros.write_topics(fh, [rc.OutTopic("/imu", rc.IMU, t_ns, data)], ts, "cdr")
    st = mcap_ros.read_streamed(p).topics["/imu"]
    assert len(st.decoded.slow_idx) == 1 and st.decoded.n_fast == len(data) - 1
    _streamed_equals_classic(p)
    back = parsers.load(p)
    assert any("1 of 3000 messages decoded by the library" in w for w in back.meta.warnings)
    assert any("undecodable" in w for w in back.meta.warnings) and len(back.imu) == len(data) - 1


def test_topic_on_two_channels_is_read_the_classic_way(tmp_path, log):
    from mcap.writer import Writer

    ts = rc.default_typestore("cdr")
    topics = rc.ros_topics_from_inslog(log, ts, "cdr")
    imu = next(t for t in topics if t.name == "/imu")
    p = str(tmp_path / "two.mcap")
    with open(p, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(name=rc.IMU, encoding="ros2msg", data=ts.generate_msgdef(rc.IMU, ros_version=2)[0].encode())
        chans = [w.register_channel(topic="/imu", message_encoding="cdr", schema_id=sid) for _ in range(2)]
        for i, (t, d) in enumerate(zip(imu.stamp_ns.tolist(), imu.data)):
            w.add_message(channel_id=chans[i % 2], log_time=t, data=d, publish_time=t)
        w.finish()
    with pytest.raises(rc.NotStreamable):
        mcap_ros.read_streamed(p)
    _same_inslog(parsers.load(p), rc.to_inslog(mcap_ros.read_raw(p), parsers.base.Selector()))


def test_mcap_damaged_records_inside_an_unchecked_chunk_lose_that_stretch_only(tmp_path):
    """An uncompressed chunk without a CRC (rosbags' mcap storage writes none) with 4 KiB zeroed among its
    records: the records before the damage and from the next readable record on are kept (the chunk was
    dropped whole, a quarter of the file), in the parse and in the export."""
    from parsers import restamp_ros as rr

    log = synthetic_log(3000, rate_hz=200.0)
    bag = str(tmp_path / "bag")
    registry.write(bag, log, "rosbag2", storage="mcap")
    f = os.path.join(bag, next(x for x in os.listdir(bag) if x.endswith(".mcap")))
    data = bytearray(open(f, "rb").read())
    (at, ln), *rest = _mcap_chunks(bytes(data))
    assert rest and mcap_ros._chunk_header(memoryview(bytes(data)), at, at + 9 + ln)[2] == 0  # no CRC
    k = at + 9 + ln // 2
    data[k:k + 4096] = bytes(4096)
    open(f, "wb").write(bytes(data))
    back = parsers.load(bag)
    lost = len(log.imu) - len(back.imu)
    assert 0 < lost < 0.05 * len(log.imu), lost
    assert any("damaged place(s)" in w for w in back.meta.warnings), back.meta.warnings
    st = rr.restamp_rosbag2(bag, str(tmp_path / "out"), ClockShift(0.001, 0.0, log.meta.t0_ns))
    assert any("damaged place(s)" in d for d in st.damage), st.damage
    assert len(parsers.load(str(tmp_path / "out")).imu) == len(back.imu)


def test_rosbag1_damaged_top_level_record_goes_on_at_the_next_chunk(big_files, tmp_path):
    """4 KiB zeroed across the end of a chunk and the index records after it: the top-level walk ignored the
    rest of the bag; it now goes on at the next chunk record (parse and export)."""
    import struct

    from parsers import restamp_ros as rr

    src = big_files["rosbag1"]
    data = bytearray(open(src, "rb").read())
    chunks, off = [], len(rosbag1.MAGIC)
    while off + 8 <= len(data):
        (hlen,) = struct.unpack_from("<I", data, off)
        (dlen,) = struct.unpack_from("<I", data, off + 4 + hlen)
        if rosbag1._fields(bytes(data[off + 4:off + 4 + hlen])).get("op") == b"\x05":
            chunks.append((off, off + 8 + hlen + dlen))
        off += 8 + hlen + dlen
    assert len(chunks) > 3
    a, b = chunks[1]
    data[b - 100:b + 3996] = bytes(4096)
    p = _copy_with(src, str(tmp_path / "z.bag"), bytes(data))
    back = parsers.load(p)
    n_full = len(big_files["log"].imu)
    raw = rosbag1.read_raw(p)
    n_msgs = sum(t.count for t in raw.topics.values())
    assert 3 * n_full - 100 < n_msgs <= 3 * n_full  # the messages under the zeros only, none read twice
    assert n_full - 50 < len(back.imu) <= n_full
    assert any(f"went on at the next chunk or connection record (byte {chunks[2][0]})" in w
               for w in back.meta.warnings), back.meta.warnings
    st = rr.restamp_rosbag1(p, str(tmp_path / "z_out.bag"), ClockShift(0.001, 0.0, big_files["log"].meta.t0_ns))
    assert any("went on at the next chunk" in d for d in st.damage)
    assert len(parsers.load(str(tmp_path / "z_out.bag")).imu) == len(back.imu)


def test_mcap_damaged_summary_definition_yields_to_the_data_sections(big_files, tmp_path):
    """A flipped byte in a channel record of the summary (read first, so that a lost first chunk does not
    orphan the later messages) gave /fix the encoding 'cd\\ufffd': its messages were counted, not kept, and
    the unit's position made the load fail ('message content was not read'). The data section's own
    definition now replaces a differing summary one; with the defining chunk lost too, the topic is left
    out (named) and the rest is read."""
    import struct

    src = big_files["mcap"]
    data = bytearray(open(src, "rb").read())
    ch = [(op, at, nxt) for op, at, nxt in mcap_ros.summary_definitions(memoryview(bytes(data))) if op == 4]
    at = next(a for op, a, nxt in ch if b"/fix" in data[a:nxt])
    enc_at = at + 9 + 4 + 4 + struct.unpack_from("<I", data, at + 9 + 4)[0]  # id, schema id, topic
    data[enc_at + 4 + 2] ^= 0xFF  # 'cdr' -> 'cd?'
    p = _copy_with(src, str(tmp_path / "summary.mcap"), bytes(data))
    full, back = parsers.load(src), parsers.load(p)
    assert back.nav["lat_deg"].notna().sum() == full.nav["lat_deg"].notna().sum()  # the data section's /fix
    data2, first = mcap_with_a_flipped_chunk(p, 0, undecodable=True)  # ... and the chunk defining it lost
    p2 = _copy_with(src, str(tmp_path / "summary2.mcap"), data2)
    back2 = parsers.load(p2)
    assert any("/fix: message encoding" in w and "topic ignored" in w for w in back2.meta.warnings)
    assert 0.5 * len(full.imu) < len(back2.imu) < len(full.imu)
    assert "lat_deg" not in back2.nav or back2.nav["lat_deg"].isna().all()


def _rosbag1_top_records(data: bytes) -> list[tuple[int, int, bytes]]:
    """(start, end, op) of the top-level records of a ROS 1 bag."""
    import struct

    out, off = [], len(rosbag1.MAGIC)
    while off + 8 <= len(data):
        (hlen,) = struct.unpack_from("<I", data, off)
        (dlen,) = struct.unpack_from("<I", data, off + 4 + hlen)
        out.append((off, off + 8 + hlen + dlen, rosbag1._fields(bytes(data[off + 4:off + 4 + hlen])).get("op")))
        off += 8 + hlen + dlen
    return out


def test_rosbag1_cut_exactly_at_a_record_boundary_is_reported(big_files, tmp_path):
    """A bag cut between two chunks reads without a broken record, but the index its bag header points to
    lies past the end of the file: a truncation warning (inspect, the InsLog's warnings, the export's
    damage), where before the shorter log came without a word."""
    from parsers import restamp_ros as rr

    src = big_files["rosbag1"]
    data = open(src, "rb").read()
    chunks = [(a, b) for a, b, op in _rosbag1_top_records(data) if op == b"\x05"]
    assert len(chunks) > 3
    cut = chunks[len(chunks) // 2][1]
    p = _copy_with(src, str(tmp_path / "cut.bag"), data[:cut])
    full = parsers.load(src)
    assert not any("truncated" in w for w in full.meta.warnings)
    back = parsers.load(p)
    n_full = len(big_files["log"].imu)
    assert 0.2 * n_full < len(back.imu) < 0.8 * n_full
    hit = [w for w in back.meta.warnings if w.startswith("truncated: the bag header puts the index at byte")]
    assert len(hit) == 1 and f"beyond the end of the file ({cut} bytes)" in hit[0], back.meta.warnings
    import re

    m = re.search(r"; (\d+\.\d) s of record time read up to the cut$", hit[0])
    assert m and abs(float(m.group(1)) - float(back.t_imu_s()[-1] - back.t_imu_s()[0])) < 0.2, hit
    inv = parsers.inspect_log(p)
    assert any(w.startswith("truncated: the bag header") for w in inv.warnings)
    st = rr.restamp_rosbag1(p, str(tmp_path / "cut_out.bag"), ClockShift(0.001, 0.0, big_files["log"].meta.t0_ns))
    assert any(d.startswith("truncated: the bag header") and "up to the cut" in d for d in st.damage), st.damage
    st_full = rr.restamp_rosbag1(src, str(tmp_path / "full_out.bag"), ClockShift(0.001, 0.0, big_files["log"].meta.t0_ns))
    assert not any("truncated" in d for d in st_full.damage)


def test_imu_orientation_marked_absent_is_a_note_not_a_warning(tmp_path):
    """orientation_covariance[0] = -1 is ROS's documented "no orientation" (REP-145): the orientations so
    marked are left out with a note (meta line "note: ...", a report note), not a warning; a quaternion
    that is no rotation is still a warning."""
    from pipelines.report import _is_parse_note

    T = _ros_types()
    msgs = []
    for k in range(40):
        t = T0_NS + k * 10_000_000
        q = (0.0, 0.0, 0.0, 1.0) if k % 10 else (0.0, 0.0, 0.0, 0.0)  # 4 with no rotation
        imu = _imu_msg(T, t, q, (0.0, 0.0, 0.1), (0.0, 0.0, 9.81))
        if 10 <= k < 15:
            imu.orientation_covariance[0] = -1.0  # 5 marked absent
        msgs.append(("/imu", "sensor_msgs/msg/Imu", imu, t))
    p = str(tmp_path / "absent.mcap")
    _hand_mcap(p, msgs)
    log = parsers.load(p + "::imu=/imu,att=/imu")
    w = log.meta.warnings
    absent = [x for x in w if "marked absent" in x]
    assert len(absent) == 1 and absent[0].startswith("note: /imu: 5 of 40 orientations marked absent"), w
    assert _is_parse_note(absent[0])
    bad = [x for x in w if "not unit quaternions" in x]
    assert len(bad) == 1 and bad[0] == "/imu: 3 of 40 orientations not unit quaternions; dropped", w
    assert not _is_parse_note(bad[0])
    assert len(log.quat_wxyz()[0]) == 40 - 5 - 3


def test_an_attitude_published_as_an_imu_is_the_units_attitude(tmp_path):
    """A unit publishing its rates on /imu (orientation_covariance[0] = -1: none) and its attitude as another
    Imu, /attitude, with zero rates and specific forces (REP-145's -1 covariances): with no selector the IMU
    is /imu (not the all-zero topic, which sorts first) and the attitude /attitude's orientation (heading
    north: yaw 0); inspect offers it as att=."""
    T = _ros_types()
    c45 = np.sqrt(0.5)
    msgs = []
    for k in range(20):
        t = T0_NS + k * 10_000_000
        att = _imu_msg(T, t, (0.0, 0.0, c45, c45), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        att.angular_velocity_covariance[0] = att.linear_acceleration_covariance[0] = -1.0
        msgs.append(("/attitude", "sensor_msgs/msg/Imu", att, t))
        msgs.append(("/imu", "sensor_msgs/msg/Imu", _rates_only_imu_msg(T, t), t))
    p = str(tmp_path / "att_as_imu.mcap")
    _hand_mcap(p, msgs)
    _assert_heading_north_turning_left(parsers.load(p))
    inv = registry.inspect_log(p)
    assert any("att=/attitude" in s and "imu=/imu" in s for s in inv.selectors), inv.selectors


def test_a_definition_in_a_chunk_that_failed_its_crc_does_not_replace_the_summarys(tmp_path):
    """A schema record inside a chunk whose CRC fails (or inside the part of a damaged chunk that still
    decompressed) may carry the damaged byte: /fix's type name garbled there made /fix an unknown topic,
    where the summary section (and the native export, which reads the summary's) had it right."""
    log = synthetic_log(200)
    path = tmp_path / "x.mcap"
    registry.write(str(path), log, "mcap", compression="none")
    data = path.read_bytes()
    name = b"sensor_msgs/msg/NavSatFix"
    first = data.index(name)
    assert data.index(name, first + 1) > first  # (the summary's copy, after the data section's)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data[:first] + b"sensor_msgs/msg/NavSatFiX" + data[first + len(name):])
    got = registry.load(str(bad))
    assert any("CRC mismatch" in w for w in got.meta.warnings), got.meta.warnings
    assert got.has_pos and len(got.nav) == len(registry.load(str(path)).nav)


@pytest.mark.parametrize("reach", ["summary", "data_end"])
def test_mcap_with_its_summarys_first_record_overwritten_reads_every_readable_message(big_files, tmp_path, reach):
    """Fuzz case (5 random blocks overwritten, one over the summary section's start): the summary's first
    record, the /imu schema, was garbage. The chain of summary records to the footer was found one record on
    and taken for bytes put in (a +877-byte "shift"), and the /imu channel, defined from the summary before
    its schema, had no type: its messages were counted, none kept. inspect listed 16128 /imu messages, analyze
    stopped at 'topic /imu: message content was not read' (no file named). The summary is now read as damaged
    in place (the footer's offsets are where the records are), the schema from the data section sets the
    channel up again, and every readable message is read. ``data_end``: the random block starts inside the
    last chunk's compressed records, as in the fuzz file (that chunk's tail, its message indexes and the data
    end record lost too)."""
    src = big_files["mcap"]
    data = bytearray(open(src, "rb").read())
    start = mcap_ros.footer_start(memoryview(bytes(data)))
    imu = [(a, nxt) for op, a, nxt in mcap_ros.summary_definitions(memoryview(bytes(data)))
           if op == 3 and b"sensor_msgs/msg/Imu" in data[a:nxt]]
    assert imu and imu[0][0] == start  # (the writer's first summary record: the /imu schema)
    last, ln = _mcap_chunks(bytes(data))[-1]
    lo = last + 9 + ln - 2000 if reach == "data_end" else start
    data[lo:imu[0][1]] = np.random.default_rng(5).integers(0, 256, imu[0][1] - lo, dtype=np.uint8).tobytes()
    data[start] = 0  # (the summary's first record does not read)
    p = _copy_with(src, str(tmp_path / f"summary_head_{reach}.mcap"), bytes(data))
    assert mcap_ros.inner_shift(memoryview(bytes(data))) == 0  # (overwritten: nothing moved)
    full, back = parsers.load(src), parsers.load(p)
    said = [w for w in back.meta.warnings if "summary section does not read" in w]
    assert said and f"from byte {start} to byte {imu[0][1]}" in said[0], back.meta.warnings
    assert not any("put in or lost" in w for w in back.meta.warnings), back.meta.warnings
    if reach == "summary":
        assert len(back.imu) == len(full.imu)
        np.testing.assert_array_equal(back.gyro_rad_s(), full.gyro_rad_s())
    else:
        assert any(f"byte {last}" in w for w in back.meta.warnings), back.meta.warnings  # (the last chunk named)
        assert 0.8 * len(full.imu) < len(back.imu) < len(full.imu)
        np.testing.assert_array_equal(back.gyro_rad_s(), full.gyro_rad_s()[:len(back.imu)])
    # inspect and analyze agree: the /imu inspect lists is the one loaded, on its header stamps
    st = {s.name: s for s in registry.inspect_log(p).streams}["/imu"]
    assert st.count == len(back.imu) and "header.stamp" in st.clock, st
    raw = mcap_ros.read_raw(p)
    assert len(raw.topics["/imu"].data) == raw.topics["/imu"].count == len(back.imu)


def test_a_topic_whose_content_was_not_read_is_an_error_naming_the_file(written):
    """A reader that counted a topic's messages without their content (a damaged file): the load stops with
    one line that names the file, not 'topic /imu: message content was not read' alone."""
    raw = mcap_ros.read_raw(written["x.mcap"])
    t = raw.topics["/imu"]
    t.data = t.data[:-5]
    with pytest.raises(InputError) as exc:
        rc.to_inslog(raw, parsers.base.Selector())
    assert exc.value.path == written["x.mcap"] and "/imu" in str(exc.value) and written["x.mcap"] in str(exc.value)


@pytest.mark.parametrize("name", ["bag_sqlite", "bag_mcap"])
def test_rosbag2_topic_with_fewer_messages_than_its_metadata_declares_is_said(written, tmp_path, name):
    """metadata.yaml counts each topic's messages: a topic read with fewer (its messages lost, or the count
    damaged) is named in a warning, with its count read and declared; the data read is used as it is."""
    import yaml

    src = written[name]
    bad = tmp_path / "bad"
    shutil.copytree(src, bad)
    meta_p = bad / "metadata.yaml"
    meta = yaml.safe_load(meta_p.read_text())
    entries = meta["rosbag2_bagfile_information"]["topics_with_message_count"]
    (imu,) = [e for e in entries if e["topic_metadata"]["name"] == "/imu"]
    n = imu["message_count"]
    imu["message_count"] = 99_999_999
    meta_p.write_text(yaml.safe_dump(meta))
    want, got = parsers.load(src), parsers.load(str(bad))
    np.testing.assert_array_equal(got.imu.to_numpy(), want.imu.to_numpy())
    assert not any("per topic" in w for w in want.meta.warnings)
    (w,) = [w for w in got.meta.warnings if "per topic" in w]
    assert f"/imu {n} of 99999999" in w


def test_mcap_damaged_message_index_or_summary_is_said_and_the_messages_read_in_full(big_files, tmp_path):
    """A byte changed in a message index record (a quarter of a zstd MCAP's bytes) or in the middle of the
    summary was silent: the readers never need them (the messages come from the chunks), so every message is
    still read, and the damage is now said, by the parser and by the native export (whose output's indexes
    and summary are made anew)."""
    import struct
    from mcap.reader import make_reader

    from parsers.restamp_ros import restamp_mcap

    src = big_files["mcap"]
    data = bytearray(open(src, "rb").read())
    clean = registry.load(src)
    with open(src, "rb") as fh:
        summary = make_reader(fh).get_summary()
    idx_at = min(o for ci in summary.chunk_indexes for o in ci.message_index_offsets.values())
    assert struct.unpack_from("<B", data, idx_at)[0] == 7
    (foot_start,) = struct.unpack_from("<Q", data, len(data) - 8 - 29 + 9)
    cases = {"index": (idx_at + 9 + 6 + 16, "message index record(s) do not match their chunks"),
             "summary": ((foot_start + len(data) - 8 - 29) // 2, "summary section does not match its CRC")}
    shift = ClockShift(0.01, 0.0, int(clean.meta.t0_ns))
    for name, (at, said) in cases.items():
        bad = bytearray(data)
        bad[at:at + 16] = b"\xab" * 16
        path = _copy_with(src, str(tmp_path / f"{name}.mcap"), bytes(bad))
        got = registry.load(path)
        assert any(said in w for w in got.meta.warnings), (name, got.meta.warnings)
        np.testing.assert_array_equal(got.imu.to_numpy(), clean.imu.to_numpy())
        st = restamp_mcap(path, str(tmp_path / f"{name}_out.mcap"), shift)
        assert any(said in d for d in st.damage) and st.records == int(summary.statistics.message_count)
    assert not any("damaged" in w for w in clean.meta.warnings)
    assert not restamp_mcap(src, str(tmp_path / "clean_out.mcap"), shift).damage


def test_rosbag1_damaged_index_is_said_and_the_messages_read_in_full(big_files, tmp_path):
    """A ROS 1 bag's index data (after each chunk) and chunk infos (at the end) are never needed by the
    readers here, but rosbag's and rosbags' readers go by them: bytes changed there were silent. Now said by
    the parser and the export (whose output rosbags reads in full); every message still read."""
    from rosbags.highlevel import AnyReader

    from parsers.restamp_ros import restamp_rosbag1

    src = big_files["rosbag1"]
    data = open(src, "rb").read()
    clean = registry.load(src)
    recs, off = [], len(rosbag1.MAGIC)
    while off < len(data):
        header, op, hlen, nxt = rosbag1.top_record(data, off, len(data))
        recs.append((op[0], off, hlen))
        off = nxt
    index = next(r for r in recs if r[0] == rosbag1._OP_INDEX)
    info = next(r for r in recs if r[0] == rosbag1._OP_CHUNKINFO)
    shift = ClockShift(0.01, 0.0, int(clean.meta.t0_ns))
    for name, (_op, at, hlen) in {"index": index, "chunk info": info}.items():
        bad = bytearray(data)
        start = at + 8 + hlen + (20 if name == "index" else 0)  # (the 2nd entry's offset; a chunk info's 1st)
        bad[start:start + 8] = b"\xab" * 8
        path = _copy_with(src, str(tmp_path / f"{name.replace(' ', '_')}.bag"), bytes(bad))
        got = registry.load(path)
        assert any("index record(s) do not match the chunks" in w for w in got.meta.warnings), (name, got.meta.warnings)
        np.testing.assert_array_equal(got.imu.to_numpy(), clean.imu.to_numpy())
        out = tmp_path / f"{name.replace(' ', '_')}_out.bag"
        st = restamp_rosbag1(path, str(out), shift)
        assert any("index record(s) do not match the chunks" in d for d in st.damage)
        with AnyReader([out]) as r:
            assert sum(1 for _ in r.messages()) == st.records
    assert not any("index record" in w for w in clean.meta.warnings)
    assert not restamp_rosbag1(src, str(tmp_path / "clean_out.bag"), shift).damage
