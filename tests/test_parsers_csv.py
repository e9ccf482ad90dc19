"""CSV: vendor CSVs (units from headers, column maps, NGIMU) and the canonical CSV's edge cases."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from logtools.conventions import (DEG, G0_M_S2, MG, quat_conj, quat_from_euler,
                                  quat_from_rotvec, quat_mul, quat_normalize, quat_rotate, rotvec_from_quat)
from logtools.errors import InputError
from logtools.inslog import InsLog, LogMeta
from parsers import csv_canonical, csv_vendor, registry

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
NGIMU = REAL / "ngimu_session"
UNITS = ("blue", "green", "red")
needs_ngimu = pytest.mark.skipif(not NGIMU.exists(), reason="shared/realdata absent")


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _table(header: list[str], cols: list[np.ndarray], fmt: str = "%.9f") -> str:
    rows = np.column_stack(cols)
    body = "\n".join(",".join(fmt % v for v in r) for r in rows)
    return ",".join(header) + "\n" + body + "\n"


T = np.arange(0, 2.0, 0.01)
W_RAD_S = np.c_[np.sin(T), 0.5 * np.cos(T), 0.1 * T]
F_M_S2 = np.c_[0.1 * T, -0.2 * np.ones_like(T), -G0_M_S2 + 0.05 * np.sin(T)]


# ---- units from the header ---------------------------------------------------------------------
@pytest.mark.parametrize("header,t_scale,w_scale,f_scale", [
    (["Time (s)", "Gyro X (deg/s)", "Gyro Y (deg/s)", "Gyro Z (deg/s)", "Accel X (g)", "Accel Y (g)",
      "Accel Z (g)"], 1.0, 1 / DEG, 1 / G0_M_S2),
    (["timestamp (us)", "wx (dps)", "wy (dps)", "wz (dps)", "ax (m/s²)", "ay (m/s²)", "az (m/s²)"], 1e6, 1 / DEG, 1.0),
    (["time [ms]", "gyro_x [rad/s]", "gyro_y [rad/s]", "gyro_z [rad/s]", "acc_x [mg]", "acc_y [mg]",
      "acc_z [mg]"], 1e3, 1.0, 1 / MG),
    (["time_us", "gyro_x_deg_s", "gyro_y_deg_s", "gyro_z_deg_s", "accel_x_m_s2", "accel_y_m_s2",
      "accel_z_m_s2"], 1e6, 1 / DEG, 1.0),
    (["Time (s)", "GyroX (rad/s)", "GyroY (rad/s)", "GyroZ (rad/s)", "AccX (m/s^2)", "AccY (m/s^2)",
      "AccZ (m/s^2)", "Temperature (degC)"], 1.0, 1.0, 1.0),
    (["Time (s)", "Angular Rate X (deg/s)", "Angular Rate Y (deg/s)", "Angular Rate Z (deg/s)",
      "Acceleration X (m·s⁻²)", "Acceleration Y (m·s⁻²)", "Acceleration Z (m·s⁻²)"], 1.0, 1 / DEG, 1.0),
    (["Time (ms)", "Gyro X (rad/s)", "Gyro Y (rad/s)", "Gyro Z (rad/s)", "Specific Force X (g)",
      "Specific Force Y (g)", "Specific Force Z (g)"], 1e3, 1.0, 1 / G0_M_S2),
    # the ASL/EuRoC dataset layout (and Kalibr's with units): w_ and a_ with SI units written as powers
    (["#timestamp [ns]", "w_RS_S_x [rad s^-1]", "w_RS_S_y [rad s^-1]", "w_RS_S_z [rad s^-1]",
      "a_RS_S_x [m s^-2]", "a_RS_S_y [m s^-2]", "a_RS_S_z [m s^-2]"], 1e9, 1.0, 1.0),
])
def test_vendor_units_from_header(tmp_path, header, t_scale, w_scale, f_scale):
    t = T * t_scale
    fmt = "%.0f" if t_scale > 1 else "%.9f"
    cols = [t, *(W_RAD_S * w_scale).T, *(F_M_S2 * f_scale).T] + ([np.full(len(T), 25.0)] if len(header) > 7 else [])
    text = ",".join(header) + "\n" + "\n".join(
        ",".join([fmt % r[0]] + ["%.12g" % v for v in r[1:]]) for r in np.column_stack(cols)) + "\n"
    p = _write(tmp_path / "imu.dat", text)  # extension does not matter: detection is by content
    assert registry.detect(str(p)).NAME == "csv-vendor"
    log = registry.load(str(p))
    np.testing.assert_allclose(log.t_imu_s(), T, atol=1e-9)
    np.testing.assert_allclose(log.gyro_rad_s(), W_RAD_S, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(log.accel_m_s2(), F_M_S2, rtol=1e-9, atol=1e-9)
    assert log.meta.clock == "boot"
    assert any("FRD" in w for w in log.meta.warnings)  # the frame assumption is said, never silent


def _euler_csv(tmp_path: Path, header: list[str], rpy_deg: np.ndarray, name: str = "ins.csv") -> Path:
    text = ",".join(header) + "\n" + "\n".join(
        ",".join(["%.3f" % t] + ["%.12g" % v for v in (*w, *r)]) for t, w, r in zip(T, W_RAD_S, rpy_deg)) + "\n"
    return _write(tmp_path / name, text)


def test_vendor_attitude_as_euler_angles(tmp_path):
    """Roll, pitch, yaw (heading) columns: the Z-Y-X angles of the body -> nav rotation, FRD/NED by default;
    in a map's stated frames (FLU/ENU) the same angles of that rotation, converted like a quaternion."""
    rpy = np.c_[20 * np.sin(T), -10 + 5 * T, (350 + 30 * T) % 360]  # a heading on 0..360, through north
    q_ned_frd = quat_from_euler(np.radians(rpy))
    hdr = ["Time (s)", "Gyro X (rad/s)", "Gyro Y (rad/s)", "Gyro Z (rad/s)", "Roll (deg)", "Pitch (deg)",
           "Heading (deg)"]
    log = registry.load(str(_euler_csv(tmp_path, hdr, rpy)))
    _, q = log.quat_wxyz()
    np.testing.assert_allclose(q * np.sign(np.sum(q * q_ned_frd, axis=1))[:, None], q_ned_frd, atol=1e-9)
    np.testing.assert_allclose(log.gyro_rad_s(), W_RAD_S, atol=1e-9)
    # the same attitude as a ROS-style device gives its roll/pitch/yaw (FLU body in ENU), through a map
    from logtools.conventions import euler_from_quat, quat_ned_frd_to_enu_flu
    rpy_enu = np.degrees(euler_from_quat(quat_ned_frd_to_enu_flu(q_ned_frd)))
    p = _euler_csv(tmp_path, ["t", "gx", "gy", "gz", "r", "p", "y"], rpy_enu, "ros.csv")
    (tmp_path / "ros.csv.map.json").write_text(json.dumps(
        {"t": ["time", "s"], "gx": ["gyro_x", "rad/s"], "gy": ["gyro_y", "rad/s"], "gz": ["gyro_z", "rad/s"],
         "r": ["roll", "deg"], "p": ["pitch", "deg"], "y": ["yaw", "deg"], "_body_frame": "FLU", "_nav_frame": "ENU",
         "_quat": "nav_to_body"}))  # (a quaternion's convention: it does not apply to the angles)
    _, q = registry.load(str(p)).quat_wxyz()
    np.testing.assert_allclose(q * np.sign(np.sum(q * q_ned_frd, axis=1))[:, None], q_ned_frd, atol=1e-9)
    # a quaternion and angles in one file: the quaternion, the angles said to be left out
    both = _table(["Time (s)", "Quaternion W", "Quaternion X", "Quaternion Y", "Quaternion Z", "Roll (deg)",
                   "Pitch (deg)", "Yaw (deg)"], [T, *q_ned_frd.T, *(rpy + 5).T], fmt="%.12g")
    log = registry.load(str(_write(tmp_path / "both.csv", both)))
    _, q = log.quat_wxyz()
    np.testing.assert_allclose(q * np.sign(np.sum(q * q_ned_frd, axis=1))[:, None], q_ned_frd, atol=1e-9)
    assert any("roll/pitch/yaw columns not used" in w for w in log.meta.warnings)


def test_canonical_csv_reads_euler_columns_and_notes_the_columns_it_does_not_read(tmp_path):
    """A canonical CSV made by hand may carry the attitude as roll_deg/pitch_deg/yaw_deg (read as in the
    vendor CSVs: Z-Y-X, FRD/NED) and other columns (a temperature): those are named in a note, not silently
    dropped."""
    rpy = np.c_[20 * np.sin(T), -10 + 5 * T, (350 + 30 * T) % 360]
    text = _table(["time_s", "gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s", "roll_deg", "pitch_deg", "yaw_deg",
                   "temp_c"], [T, *W_RAD_S.T, *rpy.T, np.full(len(T), 21.0)])
    log = registry.load(str(_write(tmp_path / "hand.csv", text)))
    assert log.meta.format == "csv"
    q_ned_frd = quat_from_euler(np.radians(rpy))
    _, q = log.quat_wxyz()
    np.testing.assert_allclose(q * np.sign(np.sum(q * q_ned_frd, axis=1))[:, None], q_ned_frd, atol=1e-8)
    assert [w for w in log.meta.warnings] == ["note: column(s) not read (not the canonical CSV's): temp_c"]


def test_vendor_yaw_beside_a_heading_is_the_attitude_s_yaw(tmp_path):
    """Roll, pitch, yaw and a heading (a compass's): the yaw column is the attitude's, the heading named in a
    note (both were left out as 'yaw in more than one column', the file read without attitude)."""
    rpy = np.c_[20 * np.sin(T), -10 + 5 * T, (350 + 30 * T) % 360]
    hdr = ["Time (s)", "Gyro X (rad/s)", "Gyro Y (rad/s)", "Gyro Z (rad/s)", "Roll (deg)", "Pitch (deg)",
           "Yaw (deg)"]
    text = ",".join(hdr + ["Heading (deg)"]) + "\n" + "\n".join(
        ",".join(["%.3f" % t] + ["%.12g" % v for v in (*w, *r, (r[2] + 7.0) % 360)]) for t, w, r in zip(T, W_RAD_S, rpy)) + "\n"
    log = registry.load(str(_write(tmp_path / "ahrs.csv", text)))
    q_ned_frd = quat_from_euler(np.radians(rpy))
    _, q = log.quat_wxyz()
    np.testing.assert_allclose(q * np.sign(np.sum(q * q_ned_frd, axis=1))[:, None], q_ned_frd, atol=1e-8)
    assert any("'Heading (deg)' (beside 'Yaw (deg)')" in w for w in log.meta.warnings)


def test_vendor_acceleration_columns_beside_accelerometer_columns_are_left_out(tmp_path):
    """An INS export with the accelerometer's specific force and a kinematic 'Acceleration' group: since
    'Acceleration X' reads as an accelerometer column, the header was ambiguous (refused); the
    accelerometer's columns are taken and the others named in a note."""
    rows = [",".join(["%.3f" % t] + ["%.9f" % v for v in (*w, *f, *(f * 0.0))]) for t, w, f in zip(T, W_RAD_S, F_M_S2)]
    hdr = ("Time (s),Gyro X (rad/s),Gyro Y (rad/s),Gyro Z (rad/s),Accelerometer X (m/s^2),Accelerometer Y (m/s^2),"
           "Accelerometer Z (m/s^2),Acceleration X (m/s^2),Acceleration Y (m/s^2),Acceleration Z (m/s^2)")
    log = registry.load(str(_write(tmp_path / "ins.csv", hdr + "\n" + "\n".join(rows) + "\n")))
    np.testing.assert_allclose(log.accel_m_s2(), F_M_S2, atol=1e-9)
    assert any("'Acceleration X (m/s^2)' (beside 'Accelerometer X (m/s^2)')" in w for w in log.meta.warnings)


def test_vendor_csv_saved_with_decimal_commas_is_read(tmp_path):
    """A spreadsheet saved in a comma-decimal locale splits its cells with ';' and writes '1700000000,005':
    such a CSV was refused ("the numbers are written with decimal commas"). It is read, the time exactly,
    and the native export writes the new times with decimal commas too, every other cell as it was."""
    rows = [";".join(["%.9f" % (1.7e9 + t)] + ["%.9f" % v for v in w]).replace(".", ",") for t, w in zip(T, W_RAD_S)]
    p = _write(tmp_path / "excel.csv", "Time (s);Gyro X (rad/s);Gyro Y (rad/s);Gyro Z (rad/s)\n" + "\n".join(rows) + "\n")
    log = registry.load(str(p))
    assert log.meta.t0_ns == 1_700_000_000_000_000_000
    np.testing.assert_allclose(log.t_imu_s(), T, atol=1e-6)  # (the file's own %.9f of a float sum)
    np.testing.assert_allclose(log.gyro_rad_s(), W_RAD_S, atol=1e-9)
    from parsers.restamp import ClockShift
    from parsers.restamp_csv import restamp_csv_vendor

    sh = ClockShift(0.1, 0.0, log.meta.t0_ns)
    st = restamp_csv_vendor(str(p), str(tmp_path / "out.csv"), sh)
    assert st.records == len(T) and not st.damage
    out = (tmp_path / "out.csv").read_text().splitlines()
    assert out[1].startswith("1699999999,9") and out[1].split(";")[1:] == rows[0].split(";")[1:]
    back = registry.load(str(tmp_path / "out.csv"))
    np.testing.assert_array_equal(back.meta.t0_ns + np.round(back.t_imu_s() * 1e9).astype(np.int64),
                                  sh.to_master_ns(log.meta.t0_ns + np.round(log.t_imu_s() * 1e9).astype(np.int64)))


def test_vendor_csv_with_a_units_row_under_its_header(tmp_path):
    """Names on the header line and units on the next (``Time,GyroX,...`` / ``s,deg/s,...``: a logger's
    habit) were refused ('no unit'). The units row now completes the names; it is not data, and the native
    export copies it as it copies the header (its time cell is no damaged line)."""
    rpy = np.c_[20 * np.sin(T), -10 + 5 * T, (350 + 30 * T) % 360]
    text = ("Time,GyroX,GyroY,GyroZ,AccX,AccY,AccZ,Roll,Pitch,Yaw\n" + "s,deg/s,deg/s,deg/s,g,g,g,deg,deg,deg\n"
            + "".join(",".join(["%.3f" % (1.7e9 + t)] + ["%.12g" % v for v in (*w, *f, *r)]) + "\n"
                      for t, w, f, r in zip(T, np.degrees(W_RAD_S), F_M_S2 / G0_M_S2, rpy)))
    p = _write(tmp_path / "logger.csv", text)
    log = registry.load(str(p))
    assert len(log.imu) == len(T) and "units row" in log.meta.stamp_source
    np.testing.assert_allclose(log.gyro_rad_s(), W_RAD_S, atol=1e-9)
    np.testing.assert_allclose(log.accel_m_s2(), F_M_S2, atol=1e-9)
    _, q = log.quat_wxyz()
    q_ned_frd = quat_from_euler(np.radians(rpy))
    np.testing.assert_allclose(q * np.sign(np.sum(q * q_ned_frd, axis=1))[:, None], q_ned_frd, atol=1e-8)
    from parsers.restamp import ClockShift
    from parsers.restamp_csv import restamp_csv_vendor

    shift = ClockShift(0.25, 0.0, log.meta.t0_ns)
    st = restamp_csv_vendor(str(p), str(tmp_path / "out.csv"), shift)
    assert st.records == len(T) and not st.damage
    out = (tmp_path / "out.csv").read_text().splitlines()
    assert out[:2] == text.splitlines()[:2]
    back = registry.load(str(tmp_path / "out.csv"))
    np.testing.assert_array_equal(back.meta.t0_ns + np.round(back.t_imu_s() * 1e9).astype(np.int64),
                                  shift.to_master_ns(log.meta.t0_ns + np.round(log.t_imu_s() * 1e9).astype(np.int64)))
    semi = _write(tmp_path / "semi.csv", "\n".join(line.replace(",", ";") for line in text.splitlines()) + "\n")
    np.testing.assert_array_equal(registry.load(str(semi)).gyro_rad_s(), log.gyro_rad_s())  # (any delimiter)
    # a second line of numbers is data, not units: such a header stays unmappable, said as before
    with pytest.raises(InputError, match="no unit"):
        registry.load(str(_write(tmp_path / "plain.csv", "t,gx,gy,gz\n0.0,1,2,3\n0.01,1,2,3\n")))


def test_vendor_csv_stretch_written_twice_is_dropped_by_lines_even_where_a_group_is_constant(tmp_path):
    """A stretch of a vendor CSV's lines written twice, with the accelerometer at rest (its cells the same
    on every line): judged group by group the accelerometer's repeat, its values not changing, was left to
    the clock-step rule, which kept one part alone (the IMU kept 150 of its 200 samples).
    Judged by whole lines, as the canonical reader does, the repeat is dropped and every sample kept."""
    rows = [",".join(["%.3f" % t] + ["%.9f" % v for v in w] + ["0.01", "0.02", "-1.0"]) for t, w in zip(T, W_RAD_S)]
    rows = rows[:150] + rows[100:150] + rows[150:]  # lines 100..149 written again
    p = _write(tmp_path / "rest.csv", "Time (s),Gyro X (rad/s),Gyro Y (rad/s),Gyro Z (rad/s),Acc X (g),Acc Y (g),"
                                      "Acc Z (g)\n" + "\n".join(rows) + "\n")
    log = registry.load(str(p))
    assert len(log.imu) == len(T)
    np.testing.assert_allclose(log.gyro_rad_s(), W_RAD_S, atol=1e-9)
    said = [w for w in log.meta.warnings if "repeating earlier ones" in w]
    assert len(said) == 1 and "50 line(s)" in said[0] and "line 152" in said[0]


def test_vendor_partial_attitude_or_position_columns_are_left_out_and_said(tmp_path):
    """An IMU CSV with an altitude or a heading column alone, or a yaw and a heading, still reads (its IMU);
    the columns left out are named in a warning. A part of an IMU group is still refused (a misnamed axis)."""
    rpy = np.c_[T, T, T]
    for hdr, named in ((["Time (s)", "Gyro X (rad/s)", "Gyro Y (rad/s)", "Gyro Z (rad/s)", "Altitude (m)",
                         "Heading (deg)", "Course (deg)"], ("'Altitude (m)'", "'Heading (deg)'")),
                       (["Time (s)", "Gyro X (rad/s)", "Gyro Y (rad/s)", "Gyro Z (rad/s)", "Pitch (deg)",
                         "Heading (deg)", "Azimuth (deg)"], ("yaw in more than one column",)),
                       (["Time (s)", "Gyro X (rad/s)", "Gyro Y (rad/s)", "Gyro Z (rad/s)", "Roll", "Pitch",
                         "Yaw"], ("'Roll' (no angle unit)",))):
        log = registry.load(str(_euler_csv(tmp_path, hdr, rpy)))
        np.testing.assert_allclose(log.gyro_rad_s(), W_RAD_S, atol=1e-9)
        assert "att" not in log.meta.channels and "pos" not in log.meta.channels
        said = [w for w in log.meta.warnings if "not used" in w]
        assert len(said) == 1 and all(n in said[0] for n in named), log.meta.warnings


def test_vendor_tab_and_semicolon_delimited(tmp_path):
    for sep in ("\t", ";"):
        text = sep.join(["Time (s)", "Gyro X (deg/s)", "Gyro Y (deg/s)", "Gyro Z (deg/s)"]) + "\n" + "".join(
            sep.join(["%.3f" % t, "1", "2", "3"]) + "\n" for t in T[:50])
        log = registry.load(str(_write(tmp_path / "tab.txt", text)))
        np.testing.assert_allclose(log.gyro_rad_s()[0], np.radians([1, 2, 3]))
        assert len(log.imu) == 50


def test_vendor_epoch_time_exact_ns(tmp_path):
    t_text = ["1700000000.123456789", "1700000000.133456789", "1700000000.143456789"]
    text = "timestamp (s),Gyro X (rad/s),Gyro Y (rad/s),Gyro Z (rad/s)\n" + "".join(
        f"{t},0.1,0.2,0.3\n" for t in t_text)
    log = registry.load(str(_write(tmp_path / "e.csv", text)))
    assert log.meta.clock == "epoch" and log.meta.t0_ns == 1_700_000_000_123_456_789
    np.testing.assert_allclose(log.t_imu_s(), [0, 0.01, 0.02], atol=1e-12)


@pytest.mark.parametrize("header,why", [
    (["time", "gx", "gy", "gz"], "no unit"),
    (["t", "gyro_x", "gyro_y", "gyro_z"], "no unit"),
    (["Time (s)", "Gyro X (deg/s)", "Gyro Y (deg/s)", "Gyro Z (deg/s)", "Gyroscope X (rad/s)"], "all look like"),
    (["Time (s)", "Gyro X (deg/s)", "Gyro Y (deg/s)"], "incomplete"),
    (["Time (s)", "Gyro X (furlong/s)", "Gyro Y (deg/s)", "Gyro Z (deg/s)"], "unit not understood"),
    (["foo", "bar", "baz"], "no time column"),
])
def test_ambiguous_vendor_csv_is_one_line_input_error(tmp_path, header, why):
    p = _write(tmp_path / "amb.csv", ",".join(header) + "\n" + ",".join(["1"] * len(header)) + "\n")
    with pytest.raises(InputError) as e:
        registry.load(str(p))
    msg = str(e.value)
    assert "\n" not in msg and str(p) in msg and why in msg
    assert repr(header[0]) in msg and "map=FILE.json" in msg  # names the columns, says how to map


def test_column_map_with_frames_via_selector_and_sidecar(tmp_path):
    q_ned_frd = quat_from_euler(np.c_[0.1 * T, -0.2 * np.ones_like(T), 0.3 + 0.5 * T])
    # the same attitude, velocity and rates as a ROS-style device would log them (ENU world, FLU body)
    from logtools.conventions import quat_ned_frd_to_enu_flu
    q_enu_flu = quat_ned_frd_to_enu_flu(q_ned_frd)
    v_ned = np.c_[np.sin(T), 2 * np.cos(T), 0.3 * T]
    v_enu = np.c_[v_ned[:, 1], v_ned[:, 0], -v_ned[:, 2]]
    w_flu = W_RAD_S * [1, -1, -1]
    cols = ["ts", "GX", "GY", "GZ", "QW", "QX", "QY", "QZ", "VE", "VN", "VU"]
    text = _table(cols, [T * 1000, *(w_flu / DEG).T, *q_enu_flu.T, *v_enu.T], fmt="%.12g")
    p = _write(tmp_path / "dev.csv", text)
    with pytest.raises(InputError, match="cannot map"):
        registry.load(str(p))
    cmap = {"ts": ["time", "ms"], "GX": ["gyro_x", "deg/s"], "GY": ["gyro_y", "deg/s"], "GZ": ["gyro_z", "deg/s"],
            "QW": ["quat_w", ""], "QX": ["quat_x", ""], "QY": ["quat_y", ""], "QZ": ["quat_z", ""],
            "VE": ["vel_n", "m/s"], "VN": ["vel_e", "m/s"], "VU": ["vel_d", "m/s"],
            "_body_frame": "FLU", "_nav_frame": "ENU"}
    # ENU 'vel_n' slot holds the first ENU axis (east): the map names the nav-frame axes in order
    m = tmp_path / "map.json"
    m.write_text(json.dumps(cmap))
    for arg in (f"{p}::map={m}", None):
        if arg is None:
            (tmp_path / "dev.csv.map.json").write_text(json.dumps(cmap))
            arg = str(p)
        log = registry.load(arg)
        np.testing.assert_allclose(log.gyro_rad_s(), W_RAD_S, atol=1e-9)
        t, q = log.quat_wxyz()
        q = q * np.sign(np.sum(q * q_ned_frd, axis=1))[:, None]
        np.testing.assert_allclose(q, q_ned_frd, atol=1e-9)
        np.testing.assert_allclose(log.vel_ned_m_s()[1], v_ned, atol=1e-9)
        assert not any("FRD" in w for w in log.meta.warnings)
        assert "map" in log.meta.stamp_source


def test_bad_column_maps(tmp_path):
    p = _write(tmp_path / "d.csv", "a,b,c,d\n1,2,3,4\n")
    for content, match in (("{not json", "not valid JSON"), ('["x"]', "JSON object"),
                           ('{"a": ["time", "s"], "b": ["gyro_q", "rad/s"]}', "canonical_name"),
                           ('{"a": ["time", "s"], "b": ["gyro_x", "m/s"]}', "not a rate unit"),
                           ('{"b": ["gyro_x", "rad/s"]}', "no column to 'time'"),
                           ('{"zz": ["time", "s"]}', "not in the CSV")):
        m = tmp_path / "m.json"
        m.write_text(content)
        with pytest.raises(InputError, match=match) as e:
            registry.load(f"{p}::map={m}")
        assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="no such file|No such file"):
        registry.load(f"{p}::map={tmp_path / 'missing.json'}")


def _vendor_file(tmp_path: Path) -> tuple[Path, str]:
    header = ["Time (s)", "Gyroscope X (deg/s)", "Gyroscope Y (deg/s)", "Gyroscope Z (deg/s)"]
    text = _table(header, [T, *(W_RAD_S / DEG).T])
    return _write(tmp_path / "g.csv", text), text


def test_damaged_vendor_csv_uses_readable_rows_and_warns(tmp_path):
    p, text = _vendor_file(tmp_path)
    lines = text.splitlines(keepends=True)
    cut = _write(tmp_path / "cut.csv", "".join(lines[:120]) + lines[120][:15])  # cut mid-row
    log = registry.load(str(cut))
    assert len(log.imu) == 119 and any("dropped" in w for w in log.meta.warnings)
    mid = len(text) // 2
    i = text.index("1", mid)
    flipped = _write(tmp_path / "flip.csv", text[:i] + "x" + text[i + 1:])
    log = registry.load(str(flipped))
    assert len(log.imu) == len(T) - 1 and any("1 row(s)" in w for w in log.meta.warnings)
    raw = bytearray(text.encode())
    raw[mid] = 0xFF  # not UTF-8
    nonutf = tmp_path / "nonutf.csv"
    nonutf.write_bytes(bytes(raw))
    log = registry.load(str(nonutf))
    assert len(log.imu) >= len(T) - 1 and log.meta.warnings
    extra_text = "".join(lines[:50]) + lines[50].rstrip("\n") + ",7,8\n" + "".join(lines[51:])
    extra = _write(tmp_path / "extra.csv", extra_text)
    log = registry.load(str(extra))
    assert len(log.imu) == len(T) - 1 and any("malformed line" in w for w in log.meta.warnings)


def test_vendor_sniff_leaves_canonical_csv_and_binary_alone(tmp_path):
    canon = "time_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n0.0,0,0,0\n"
    assert not csv_vendor.sniff(canon.encode(), "x.csv")
    assert not csv_vendor.sniff(b"\xef\xbb\xbf" + canon.encode(), "x.csv")
    assert not csv_vendor.sniff(bytes(range(256)), "x.csv")
    assert not csv_vendor.sniff(b"1.0,2.0,3.0\n4,5,6\n", "x.csv")  # no header: not ours to guess
    p = _write(tmp_path / "c.csv", canon)
    assert registry.detect(str(p)).NAME == "csv"


# ---- NGIMU -----------------------------------------------------------------------------------
@needs_ngimu
def test_a_vendor_unit_folder_export_never_replaces_a_folder_of_other_things(tmp_path):
    """The native export of a vendor unit folder (NGIMU: sensors.csv, quaternion.csv, ...) is a folder: it
    replaces an earlier export of it, never a file or a folder of other things (one line, left as it was)."""
    if not NGIMU.is_dir():
        pytest.skip("../shared/realdata not present")
    from parsers.restamp import ClockShift
    from parsers.restamp_csv import restamp_csv_vendor

    src = str(NGIMU / "blue")
    shift = ClockShift(0.001, 0.0, 0)
    other = tmp_path / "out"
    other.mkdir()
    (other / "report.json").write_text("{}")
    with pytest.raises(InputError, match="holds other files than a CSV unit folder"):
        restamp_csv_vendor(src, str(other), shift)
    assert sorted(os.listdir(other)) == ["report.json"]
    note = tmp_path / "notes.txt"
    note.write_text("keep me")
    with pytest.raises(InputError, match="exists and is not a folder"):
        restamp_csv_vendor(src, str(note), shift)
    assert note.read_text() == "keep me"
    dst = tmp_path / "blue_shifted"
    restamp_csv_vendor(src, str(dst), shift)
    restamp_csv_vendor(src, str(dst), shift)  # (an earlier export is replaced)
    assert sorted(os.listdir(dst)) == sorted(os.listdir(src))


def test_ngimu_session_units_rates_and_paths():
    inv = registry.inspect_log(str(NGIMU))
    assert inv.format == "csv-vendor"
    assert inv.selectors == tuple(f"unit={u}" for u in UNITS)
    for u in UNITS:
        by_session = registry.load(f"{NGIMU}::unit={u}")
        by_dir = registry.load(str(NGIMU / u))
        by_file = registry.load(str(NGIMU / u / "sensors.csv"))
        for log in (by_session, by_dir, by_file):
            assert log.meta.format == "csv-vendor" and log.has_gyro and log.has_accel and log.has_quat
            assert log.meta.channels["gyro"].rate_hz == pytest.approx(50, rel=0.01)
            assert log.meta.channels["att"].rate_hz == pytest.approx(50, rel=0.01)
            assert log.duration_s == pytest.approx(10.6, abs=0.05)
            np.testing.assert_array_equal(log.gyro_rad_s(), by_session.gyro_rad_s())
        assert by_session.meta.selector == f"unit={u}"
    default = registry.load(str(NGIMU))
    assert default.meta.selector == "unit=blue" and any("picked unit=blue" in w for w in default.meta.warnings)
    with pytest.raises(InputError, match="no unit 'purple'.*blue, green, red"):
        registry.load(f"{NGIMU}::unit=purple")


@pytest.fixture(scope="module")
def ngimu_logs():
    if not NGIMU.exists():
        pytest.skip("shared/realdata absent")
    return {u: registry.load(f"{NGIMU}::unit={u}") for u in UNITS}


@needs_ngimu
def test_ngimu_three_units_agree(ngimu_logs):
    grid = np.arange(0.5, 10.0, 0.01)
    mags = {}
    for u, log in ngimu_logs.items():
        t_q, q = log.quat_wxyz()
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)  # raw files hold |q| = 0.9983
        w = np.linalg.norm(log.gyro_rad_s(), axis=1)
        mags[u] = np.interp(grid, log.t_imu_s() + log.t0_s, w)
        assert np.max(w) > np.radians(100)  # real motion: +-200 deg/s
    for a, b in (("blue", "green"), ("blue", "red"), ("green", "red")):
        assert np.corrcoef(mags[a], mags[b])[0, 1] > 0.97


def _integrate_body_rates(t_s: np.ndarray, w: np.ndarray, q0: np.ndarray) -> np.ndarray:
    """q_{k+1} = q_k (x) exp(w dt): body-frame rates integrated from q0 (trapezoid rates)."""
    dq = quat_from_rotvec(0.5 * (w[:-1] + w[1:]) * np.diff(t_s)[:, None])
    out = np.empty((len(t_s), 4))
    out[0] = q0
    for k in range(len(dq)):  # 530 samples: a short loop over a tiny log
        out[k + 1] = quat_normalize(quat_mul(out[k], dq[k]))
    return out


def _window_errors_deg(t_s: np.ndarray, w: np.ndarray, q: np.ndarray, win: int) -> tuple[np.ndarray, np.ndarray]:
    """Over half-overlapping windows of ``win`` samples: angle between the integrated and the logged
    attitude change, and the logged change itself (the swing)."""
    errs, swings = [], []
    for k0 in range(0, len(t_s) - win, win // 2):
        sl = slice(k0, k0 + win + 1)
        q_int = _integrate_body_rates(t_s[sl], w[sl], q[k0])[-1]
        errs.append(np.linalg.norm(rotvec_from_quat(quat_mul(quat_conj(q[k0 + win]), q_int))))
        swings.append(np.linalg.norm(rotvec_from_quat(quat_mul(quat_conj(q[k0]), q[k0 + win]))))
    return np.degrees(errs), np.degrees(swings)


@needs_ngimu
def test_ngimu_gyro_integration_matches_attitude_change(ngimu_logs):
    """Frame check independent of any reading of the docs: the loaded FRD rates, integrated over 1 s
    windows, reproduce the loaded body->NED quaternion's changes within a few degrees (50 Hz samples
    of +-200 deg/s motion limit the integration); the vendor's raw quaternion does not fit at all."""
    for u, log in ngimu_logs.items():
        t_imu, w = log.t_imu_s(), log.gyro_rad_s()
        t_q, q = log.quat_wxyz()
        pick = np.clip(np.searchsorted(t_q, t_imu), 0, len(t_q) - 1)
        err, swing = _window_errors_deg(t_imu, w, q[pick], 50)
        assert swing.max() > 90  # the check means something: large rotations happen
        assert err.max() < 7.0 and np.median(err) < 2.5, (u, err.max(), np.median(err))
        raw = pd.read_csv(NGIMU / u / "quaternion.csv").iloc[:, 1:5].to_numpy()
        raw_err, _ = _window_errors_deg(t_imu, w, quat_normalize(raw[pick]), 50)
        assert np.median(raw_err) > 10.0 and raw_err.max() > 90.0  # unconverted: does not fit


@needs_ngimu
def test_ngimu_gravity_down_and_magnetic_north(ngimu_logs):
    for u, log in ngimu_logs.items():
        t_q, q = log.quat_wxyz()
        f_ned = quat_rotate(q, log.accel_m_s2()[np.clip(np.searchsorted(log.t_imu_s(), t_q), 0, len(t_q) - 1)])
        np.testing.assert_allclose(np.median(f_ned, axis=0), [0, 0, -G0_M_S2], atol=0.3)
        raw = pd.read_csv(NGIMU / u / "sensors.csv")
        mag_frd = raw[["Magnetometer X (uT)", "Magnetometer Y (uT)", "Magnetometer Z (uT)"]].to_numpy() * [1, -1, -1]
        m_ned = np.median(quat_rotate(q[: len(mag_frd)], mag_frd[: len(q)]), axis=0)
        # the AHRS heading is magnetic: the field points north (x > 0, y ~ 0) and down (Bristol, UK)
        assert m_ned[0] > 10 and abs(m_ned[1]) < 3 and m_ned[2] > 30


# ---- canonical CSV edge cases ------------------------------------------------------------------
def _canon_log(clock: str = "epoch") -> InsLog:
    ti = np.arange(0, 1.0, 0.01)
    tn = np.arange(0, 1.0, 0.05)
    meta = LogMeta(source_path="x", format="sim", clock=clock,
                   t0_ns=1_700_000_000_000_000_001 if clock == "epoch" else 12_345_678_901)
    return InsLog.from_arrays(meta, ti, np.c_[ti, -ti, 2 * ti], np.c_[ti, ti, -G0_M_S2 + ti], tn,
                              quat_from_euler(np.c_[tn, -tn, tn]), np.c_[tn, tn, tn], np.c_[45 + tn, 7 + tn, tn])


@pytest.mark.parametrize("clock", ["epoch", "boot"])
def test_canonical_round_trip_exact_stamps(tmp_path, clock):
    log = _canon_log(clock)
    p = tmp_path / "c.csv"
    registry.write(str(p), log, "csv")
    back = registry.load(str(p))
    assert back.meta.format == "csv" and back.meta.clock == clock and back.meta.t0_ns == log.meta.t0_ns
    np.testing.assert_allclose(back.t_imu_s(), log.t_imu_s(), atol=1e-9)
    np.testing.assert_allclose(back.gyro_rad_s(), log.gyro_rad_s(), rtol=1e-15)
    np.testing.assert_allclose(back.quat_wxyz()[1], log.quat_wxyz()[1], rtol=1e-15)
    np.testing.assert_allclose(back.lat_lon_alt()[1], log.lat_lon_alt()[1], rtol=1e-15)


@pytest.mark.parametrize("garbage", [b"\x89\x00\xffbinary junk without a line break", b"a line\nmore,lines\n"])
def test_canonical_csv_with_bytes_before_its_header_is_read_from_the_header(tmp_path, garbage):
    """Bytes put before a canonical CSV's header line (a transfer's garbage, ending in a line break or not):
    the file was 'unrecognised format'. The header line is found within the first 64 KiB and the file read
    from there, saying so; the native export writes the file without those bytes."""
    from parsers.restamp import ClockShift
    from parsers.restamp_csv import restamp_csv

    log = _canon_log("epoch")
    good = tmp_path / "good.csv"
    registry.write(str(good), log, "csv")
    bad = tmp_path / "bad.csv"
    bad.write_bytes(garbage * 40 + good.read_bytes())
    full, back = registry.load(str(good)), registry.load(str(bad))
    np.testing.assert_array_equal(back.imu.to_numpy(), full.imu.to_numpy())
    assert back.meta.t0_ns == full.meta.t0_ns
    assert back.meta.warnings[0].startswith(f"damaged: bad.csv: its first {40 * len(garbage)} bytes are not CSV")
    out = tmp_path / "out.csv"
    st = restamp_csv(str(bad), str(out), ClockShift(0.0, 0.0, full.meta.t0_ns))
    assert out.read_bytes() == good.read_bytes() and st.damage and "left out" in st.damage[0]


def test_canonical_edge_cases(tmp_path):
    base = "time_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n"
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + (base + "0.0,1,2,3\n0.01,1,2,3\n").encode())
    assert registry.detect(str(bom)).NAME == "csv"
    assert len(registry.load(str(bom)).imu) == 2
    unsorted = registry.load(str(_write(tmp_path / "u.csv", base + "0.02,1,2,3\n0.0,1,2,3\n0.01,1,2,3\n0.01,4,5,6\n")))
    np.testing.assert_allclose(unsorted.t_imu_s(), [0, 0.01, 0.02])
    assert any("sorted" in w for w in unsorted.meta.warnings)
    assert any("duplicate" in w for w in unsorted.meta.warnings)
    partial = registry.load(str(_write(tmp_path / "p.csv", base.strip() + ",qw,qx\n0,1,2,3,1,0\n0.01,1,2,3,1,0\n")))
    assert any("incomplete column group" in w for w in partial.meta.warnings) and not partial.has_quat
    # header only: csv_canonical currently says "cannot read as csv: KeyError: 0" (one line, exit 2)
    for text, match in (("time_s,gyro_x_rad_s\n", None),
                        (base + "abc,1,2,3\n", "not decimal seconds"),
                        ("time_s,foo\n0,1\n", "cannot map CSV columns")):
        p = _write(tmp_path / "bad.csv", text)
        with pytest.raises(InputError, match=match) as e:
            registry.load(str(p))
        assert "\n" not in str(e.value)


def test_canonical_damaged_cells_drop_their_rows_not_the_file(tmp_path):
    """Flipped bytes in a CSV: a time cell that is no longer a number rejected the whole file; a gyro cell
    become 1e+30 went into the analysis (matrix overflows). Now the first drops its row, the second its
    row's gyro group, each with a warning; a time column that is mostly not numbers is still refused."""
    log = _canon_log()
    p = tmp_path / "c.csv"
    registry.write(str(p), log, "csv")
    lines = p.read_text().splitlines()
    cells = lines[11].split(",")
    cells[0] = cells[0].replace(".", "#")
    lines[11] = ",".join(cells)
    cells = lines[21].split(",")
    cells[1] = "1e+30"
    lines[21] = ",".join(cells)
    p.write_text("\n".join(lines) + "\n")
    back = registry.load(str(p))
    assert len(back.imu) == len(log.imu) - 1  # the damaged time's row
    g = back.gyro_rad_s()
    assert np.isnan(g).any(axis=1).sum() == 1 and np.nanmax(np.abs(g)) < 2.0  # the 1e+30 row: no gyro
    w = " ".join(back.meta.warnings)
    assert "1 row(s) whose time is not a decimal number dropped" in w and "gyro: 1 rows with impossible values" in w
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join([lines[0]] + [ln.replace(".", "#", 1) for ln in lines[1:]]) + "\n")
    with pytest.raises(InputError, match="not decimal seconds"):
        registry.load(str(bad))


def test_canonical_non_numeric_cells_are_counted_per_column_and_warned(tmp_path):
    """Damaged bytes in data cells (``1.0\\x83``): read as missing values as before, but no longer silently:
    one warning counting them per column (the wording shared with the vendor reader); a clean file has none
    and reads bit-identically."""
    log = _canon_log()
    p = tmp_path / "c.csv"
    registry.write(str(p), log, "csv")
    clean = registry.load(str(p))
    assert not any("non-numeric" in w for w in clean.meta.warnings)
    lines = p.read_text().splitlines(True)
    header = lines[0].strip().split(",")
    ax, qw = header.index("accel_x_m_s2"), header.index("qw")
    for i in range(1, len(lines), 10):
        c = lines[i].rstrip("\n").split(",")
        c[ax] = "1.0\x8300x"
        if i % 20 == 1 and c[qw]:
            c[qw] = "zz"
        lines[i] = ",".join(c) + "\n"
    bad = tmp_path / "garbage.csv"
    bad.write_text("".join(lines), encoding="latin-1")
    back = registry.load(str(bad))
    n_ax = len(range(1, len(lines), 10))
    n_qw = sum(1 for i in range(1, len(lines), 20) if p.read_text().splitlines()[i].split(",")[qw])
    hit = [w for w in back.meta.warnings if "non-numeric" in w]
    assert hit == [f"garbage.csv: {n_ax + n_qw} non-numeric cell(s) (accel_x_m_s2 {n_ax}, qw {n_qw}) read as "
                   "missing values (damaged file?)"], back.meta.warnings
    assert np.isnan(back.accel_m_s2()).any(axis=1).sum() == n_ax
    inv = registry.inspect_log(str(bad))
    assert any("non-numeric" in w for w in inv.warnings)
    rows = np.isfinite(back.accel_m_s2()).all(axis=1)
    np.testing.assert_array_equal(back.gyro_rad_s(), clean.gyro_rad_s())
    np.testing.assert_array_equal(back.accel_m_s2()[rows], clean.accel_m_s2()[rows])


def test_vendor_non_numeric_cells_counted_per_column_and_inf_without_runtime_warning(tmp_path):
    """A vendor CSV with text and ``inf`` in data cells: the rows are dropped as before, the warning now
    counts the text cells per column (the canonical reader's wording), and an ``inf`` in a quaternion
    converted between frames no longer prints numpy's "invalid value encountered" on stderr."""
    import warnings

    header = ["Time (s)", "Gyro X (deg/s)", "Gyro Y (deg/s)", "Gyro Z (deg/s)"]
    text = _table(header, [T, *(W_RAD_S / DEG).T]).splitlines(True)
    for i in (5, 9):
        c = text[i].split(",")
        c[2] = "1.\x00x"
        text[i] = ",".join(c)
    p = _write(tmp_path / "v.csv", "".join(text))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        log = registry.load(str(p))
    assert len(log.imu) == len(T) - 2
    assert any(w == "v.csv: 2 row(s) with unparseable or missing values dropped (damaged or truncated file?); "
               "2 non-numeric cell(s) (Gyro Y (deg/s) 2)" for w in log.meta.warnings), log.meta.warnings
    # a quaternion file in NWU/ZUP axes (the NGIMU profile's conversion) with one inf component
    d = tmp_path / "ng"
    d.mkdir()
    hdr = ("Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),Accelerometer X (g),"
           "Accelerometer Y (g),Accelerometer Z (g)")
    rows = "".join(f"{t:.3f},0.1,0.2,0.3,0,0,1\n" for t in T)
    (d / "sensors.csv").write_text(hdr + "\n" + rows)
    q = "".join(f"{t:.3f},1,0,0,0\n" if k != 7 else f"{t:.3f},inf,0,0,0\n" for k, t in enumerate(T))
    (d / "quaternion.csv").write_text("Time (s),W,X,Y,Z\n" + q)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ng = registry.load(str(d))
    assert len(ng.quat_wxyz()[0]) == len(T) - 1


def test_binary_junk_column_names_give_one_printable_line(tmp_path, capsys):
    """An NGIMU session whose quaternion.csv is random bytes: the error named the "columns" it found with
    their raw bytes (newlines, control characters: several lines of junk on stderr); now one printable
    line."""
    from pipelines.cli import main

    d = tmp_path / "ng"
    d.mkdir()
    hdr = ("Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),Accelerometer X (g),"
           "Accelerometer Y (g),Accelerometer Z (g)")
    (d / "sensors.csv").write_text(hdr + "\n" + "".join(f"{t:.3f},0.1,0.2,0.3,0,0,1\n" for t in T))
    rng = np.random.default_rng(7)
    junk = bytes(rng.integers(0, 256, 4000, dtype=np.uint8))
    junk = junk.replace(b"\n", b"\r")[:300] + b",\x0b\x1c\x85\x0c,\t" + junk[300:]
    (d / "quaternion.csv").write_bytes(junk)
    assert main(["inspect", str(d)]) == 2
    err = capsys.readouterr().err
    assert err.endswith("\n") and len(err.rstrip("\n").splitlines()) == 1, repr(err)
    assert err.rstrip("\n").isprintable() and "quaternion.csv" in err and "Traceback" not in err


def test_vendor_csv_time_column_of_iso_date_times_is_read_on_utc(tmp_path):
    """A time column of ISO 8601 date-times: unitless (pandas' ``to_csv`` of a DatetimeIndex, a logger's
    'UTC Time') or with '(ISO 8601)' as its unit. Read as UTC to the nanosecond (an offset converted; text
    without a zone taken as UTC, said), on the epoch clock, the fraction's digits the stamps' resolution.
    Before, no column map could be made ('no time column with a unit')."""
    t0 = pd.Timestamp("2024-05-01 12:00:00")
    idx = pd.date_range(t0, periods=len(T), freq="10ms")
    data = {f"gyro_{a} (rad/s)": W_RAD_S[:, i] for i, a in enumerate("xyz")}
    data.update({f"accel_{a} (m/s^2)": F_M_S2[:, i] for i, a in enumerate("xyz")})
    df = pd.DataFrame(data, index=pd.Index(idx, name="timestamp"))
    df.to_csv(tmp_path / "pandas.csv")  # '2024-05-01 12:00:00.010', no zone
    got = registry.load(str(tmp_path / "pandas.csv"))
    assert got.meta.clock == "epoch" and got.meta.t0_ns == t0.value
    np.testing.assert_array_equal(got.meta.t0_ns + np.round(got.t_imu_s() * 1e9).astype(np.int64),
                                  idx.as_unit("ns").asi8)
    np.testing.assert_allclose(got.gyro_rad_s(), W_RAD_S, atol=1e-12)
    assert got.meta.channels["gyro"].stamp_resolution_s == pytest.approx(1e-3)
    assert any("without a time zone taken as UTC" in w for w in got.meta.warnings), got.meta.warnings
    # the same instants written with an offset (local time 2 h ahead) under a stated unit: the same stamps
    local = [(x + pd.Timedelta(hours=2)).strftime("%Y-%m-%dT%H:%M:%S.%f") + "+02:00" for x in idx]
    p = tmp_path / "offset.csv"
    p.write_text("Time (ISO 8601)," + ",".join(data) + "\n" + "".join(
        f"{c}," + ",".join(repr(float(v)) for v in row) + "\n" for c, row in zip(local, np.column_stack(list(data.values())))))
    off = registry.load(str(p))
    assert off.meta.t0_ns == t0.value and not any("time zone" in w for w in off.meta.warnings)
    np.testing.assert_array_equal(off.t_imu_s(), got.t_imu_s())
    np.testing.assert_array_equal(off.imu.to_numpy(), got.imu.to_numpy())


def _rostopic_csv(bag: str, out: Path, style: str) -> None:
    """The /imu topic of ``bag`` as ROS users export it: ``rostopic echo -p`` (``%time`` and
    ``field.header.stamp`` in integer ns, ``field.angular_velocity.x``...) or PlotJuggler (``__time`` in s,
    ``/imu/angular_velocity/x``...); numbers printed as Python prints them (repr: the float exactly)."""
    from rosbags.highlevel import AnyReader

    rows = []
    with AnyReader([Path(bag)]) as r:
        for con, t_rec, raw in r.messages(connections=[c for c in r.connections if c.topic == "/imu"]):
            m = r.deserialize(raw, con.msgtype)
            st = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            o, w, a = m.orientation, m.angular_velocity, m.linear_acceleration
            rows.append((t_rec, st, [o.x, o.y, o.z, o.w], [w.x, w.y, w.z], [a.x, a.y, a.z]))
    if style == "rostopic":
        head = ("%time,field.header.seq,field.header.stamp,field.header.frame_id,field.orientation.x,"
                "field.orientation.y,field.orientation.z,field.orientation.w,field.orientation_covariance0,"
                "field.angular_velocity.x,field.angular_velocity.y,field.angular_velocity.z,"
                "field.linear_acceleration.x,field.linear_acceleration.y,field.linear_acceleration.z")
        lines = [f"{tr},{i},{st},imu_link," + ",".join(map(repr, o)) + ",0.0," + ",".join(map(repr, w + a))
                 for i, (tr, st, o, w, a) in enumerate(rows)]
    else:
        head = ("__time,/imu/angular_velocity/x,/imu/angular_velocity/y,/imu/angular_velocity/z,"
                "/imu/linear_acceleration/x,/imu/linear_acceleration/y,/imu/linear_acceleration/z,"
                "/imu/orientation/x,/imu/orientation/y,/imu/orientation/z,/imu/orientation/w")
        lines = [f"{st // 1_000_000_000}.{st % 1_000_000_000:09d}," + ",".join(map(repr, w + a + o))
                 for tr, st, o, w, a in rows]
    out.write_text(head + "\n" + "\n".join(lines) + "\n")


@pytest.mark.parametrize("style", ["rostopic", "plotjuggler"])
def test_ros_bag_exported_to_csv_reads_as_the_bag(tmp_path, style):
    """sensor_msgs/Imu exported from a bag to CSV by ROS users' tools (``rostopic echo -p``, PlotJuggler):
    no units in the header, which ROS's conventions give (SI, REP 103: FLU body, ENU world). Read as the bag
    itself reads: the same stamps (the header stamp), rates, specific forces and attitude in FRD/NED. Before,
    'no time column with a unit'."""
    from tests.test_parsers_ros import synthetic_log

    bag = str(tmp_path / "x.bag")
    registry.write(bag, synthetic_log(300), "rosbag1", log_delay_ns=3_210_987)  # (receive = stamp + 3.2 ms)
    want = registry.load(bag)
    _rostopic_csv(bag, tmp_path / "imu.csv", style)
    got = registry.load(str(tmp_path / "imu.csv"))
    assert got.meta.t0_ns == want.meta.t0_ns and got.meta.clock == "epoch"
    np.testing.assert_array_equal(got.t_imu_s(), want.t_imu_s())
    np.testing.assert_allclose(got.gyro_rad_s(), want.gyro_rad_s(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.accel_m_s2(), want.accel_m_s2(), rtol=0, atol=1e-12)
    tq, q = got.quat_wxyz()
    tw, qw = want.quat_wxyz()
    keep = np.isin(tw, tq)  # (the bag's attitude also at its velocity's stamps: the nav stream's union)
    np.testing.assert_allclose(np.abs(np.sum(q * qw[keep], axis=1)), 1.0, atol=1e-12)
    assert not any("axes taken" in w for w in got.meta.warnings)  # (the frames are stated by the convention)
    if style == "plotjuggler":  # two topics' series in one file: which is the unit? Said, not guessed
        lines = (tmp_path / "imu.csv").read_text().splitlines()
        cols = [c for c in lines[0].split(",") if "angular_velocity" in c]
        two = tmp_path / "two.csv"
        two.write_text(lines[0] + "," + ",".join(c.replace("/imu/", "/imu2/") for c in cols) + "\n" + "".join(
            f"{ln},0.1,0.2,0.3\n" for ln in lines[1:]))
        with pytest.raises(InputError, match="more than one topic .*'/imu', '/imu2'"):
            registry.load(str(two))


def test_ros_csv_export_restamps_the_header_stamp_and_the_receive_time(tmp_path):
    """A ``rostopic echo -p`` CSV's two time columns (the header stamp read, ``%time`` beside it) are both put
    on the master's clock by the native export: the stamp to the nanosecond, ``%time`` moved by its line's
    shift (every time field of a message by the same amount, as the bag export does), also where it is on
    another clock (a bag recorded in simulated time: its stamps from 0, the receive times wall time); every
    other cell's text kept."""
    import pandas as pd
    from parsers.restamp import ClockShift
    from parsers.restamp_csv import restamp_csv_vendor
    from tests.test_parsers_ros import synthetic_log

    bag = str(tmp_path / "x.bag")
    registry.write(bag, synthetic_log(300), "rosbag1", log_delay_ns=3_210_987)
    src = tmp_path / "imu.csv"
    _rostopic_csv(bag, src, "rostopic")
    x = pd.read_csv(src, dtype=str, keep_default_na=False)
    x["field.header.stamp"] = (x["field.header.stamp"].astype(np.int64) - 1_699_999_000_000_000_000).astype(str)
    x.to_csv(src, index=False)  # (stamps on a simulated clock: 1000 s from its start)
    a = registry.load(str(src))
    sh = ClockShift(0.0123456789, 87.5, a.meta.t0_ns + 1_000_000_000)
    st = restamp_csv_vendor(str(src), str(tmp_path / "out.csv"), sh)
    assert st.records == len(a.imu)
    x = pd.read_csv(src, dtype=str, keep_default_na=False)
    y = pd.read_csv(tmp_path / "out.csv", dtype=str, keep_default_na=False)
    pd.testing.assert_frame_equal(x.drop(columns=["%time", "field.header.stamp"]),
                                  y.drop(columns=["%time", "field.header.stamp"]))
    stamp_a, stamp_b = (d["field.header.stamp"].astype(np.int64).to_numpy() for d in (x, y))
    np.testing.assert_array_equal(stamp_b, sh.to_master_ns(stamp_a))
    np.testing.assert_array_equal(y["%time"].astype(np.int64).to_numpy() - x["%time"].astype(np.int64).to_numpy(),
                                  stamp_b - stamp_a)
    assert "%time" in st.time_fields


def _mavlogdump(log: str, types: str) -> str:
    """pymavlink's own ``mavlogdump.py --format csv --types TYPES LOG`` (the ArduPilot wiki's way to a CSV)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "pymavlink.tools.mavlogdump", "--format", "csv", "--types", types,
                        log], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-500:]
    return r.stdout


def test_mavlogdump_csv_of_a_dataflash_message_reads_as_the_log(tmp_path):
    """A DataFlash log's IMU dumped to CSV by pymavlink's mavlogdump (``timestamp,TimeUS,GyrX,...``: no units,
    ArduPilot's fields' own) reads as the log: the same samples in rad/s and m/s^2, FRD; on UNIX time by
    mavlogdump's ``timestamp`` (pymavlink's GPS mapping: a constant offset from tapost's own); the native export
    moves TimeUS by each line's shift. Interleaved instances are one clear error. Before: 'no unit for column(s)
    timestamp, GyrX'."""
    import pandas as pd
    from parsers.restamp import ClockShift
    from parsers.restamp_csv import restamp_csv_vendor
    from tests.test_parsers_ros import synthetic_log

    log = str(tmp_path / "x.bin")
    registry.write(log, synthetic_log(400), "dataflash")
    src = tmp_path / "imu.csv"
    src.write_text(_mavlogdump(log, "IMU"))
    want, got = registry.load(log), registry.load(str(src))
    assert got.meta.clock == "epoch" and len(got.imu) == len(want.imu) == 400
    np.testing.assert_array_equal(got.gyro_rad_s(), want.gyro_rad_s())
    np.testing.assert_array_equal(got.accel_m_s2(), want.accel_m_s2())
    d = (got.meta.t0_ns + np.round(got.t_imu_s() * 1e9)) - (want.meta.t0_ns + np.round(want.t_imu_s() * 1e9))
    assert np.ptp(d) < 1000 and abs(np.median(d)) < 0.01e9  # (pymavlink's offset; its float64 stamps: < 1 us)
    assert not any("axes taken" in w for w in got.meta.warnings)
    sh = ClockShift(0.0123456789, 87.5, got.meta.t0_ns + 1_000_000_000)
    restamp_csv_vendor(str(src), str(tmp_path / "out.csv"), sh)
    x = pd.read_csv(src, dtype=str)
    y = pd.read_csv(tmp_path / "out.csv", dtype=str)
    moved_s = (y["timestamp"].astype(float) - x["timestamp"].astype(float)).to_numpy()
    moved_us = (y["TimeUS"].astype(float) - x["TimeUS"].astype(float)).to_numpy()
    np.testing.assert_allclose(moved_us * 1e-6, moved_s, atol=2e-6)  # (the same shift on both clocks)
    assert abs(np.median(moved_s) + 0.0123456789) < 1e-3
    # two IMU instances interleaved in one dump (a newer log's IMU with its I field)
    lines = src.read_text().splitlines()
    two = tmp_path / "two.csv"
    two.write_text(lines[0] + ",I\n" + "".join(f"{ln},{i % 2}\n" for i, ln in enumerate(lines[1:])))
    with pytest.raises(InputError, match="interleaves instances I = 0, 1"):
        registry.load(str(two))


@pytest.mark.parametrize("msg,sel", [("HIGHRES_IMU", "imu=HIGHRES_IMU"), ("ATTITUDE_QUATERNION", "att=ATTITUDE_QUATERNION"),
                                     ("GLOBAL_POSITION_INT", "vel=GLOBAL_POSITION_INT")])
def test_mavlogdump_csv_of_a_tlog_message_reads_as_the_tlog(tmp_path, msg, sel):
    """One MAVLink message type dumped from a tlog by mavlogdump (``timestamp,HIGHRES_IMU.time_usec,...``, the
    type before every field, no units) reads as the tlog reader reads that message: its units, its own time
    field (UNIX time_usec here), FRD/NED."""
    from tests.test_parsers_ros import synthetic_log

    tlog = str(tmp_path / "x.tlog")
    registry.write(tlog, synthetic_log(300), "tlog")
    src = tmp_path / f"{msg}.csv"
    src.write_text(_mavlogdump(tlog, msg))
    got = registry.load(str(src))
    want = registry.load(f"{tlog}::{sel}")
    if msg == "HIGHRES_IMU":
        np.testing.assert_array_equal(got.meta.t0_ns + np.round(got.t_imu_s() * 1e9).astype(np.int64),
                                      want.meta.t0_ns + np.round(want.t_imu_s() * 1e9).astype(np.int64))
        np.testing.assert_allclose(got.gyro_rad_s(), want.gyro_rad_s(), rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(got.accel_m_s2(), want.accel_m_s2(), rtol=1e-7, atol=1e-9)
    elif msg == "ATTITUDE_QUATERNION":
        (tg, qg), (tw, qw) = got.quat_wxyz(), want.quat_wxyz()
        assert len(tg) == len(tw)
        np.testing.assert_allclose(np.abs(np.sum(qg * qw, axis=1)), 1.0, atol=1e-6)
    else:
        (tg, vg), (tw, vw) = got.vel_ned_m_s(), want.vel_ned_m_s()
        np.testing.assert_allclose(vg, vw, atol=1e-9)
    # (time_usec is UNIX time here; time_boot_ms since boot: the tlog reader puts it on UNIX by SYSTEM_TIME)
    assert got.meta.clock == ("epoch" if msg == "HIGHRES_IMU" else "boot")
    assert not any("axes taken" in w for w in got.meta.warnings)


@pytest.mark.parametrize("kind", ["canonical", "vendor"])
def test_a_delimiter_after_each_lines_last_value_shifts_no_column(tmp_path, kind):
    """Lines that end with a delimiter (many loggers write ``v1,v2,v3,``): one cell more than the header.
    pandas took the first column as the index and shifted every column left by one (the time became the gyro's
    x, silently: 'rows not in time order: sorted'); read as the same lines without it. Lines with more cells
    than the header (mavlogdump's unquoted arrays, ``[0.0, 0.0]``) keep their columns, said."""
    t = 1_700_000_000 + np.arange(200) * 0.01 if kind == "canonical" else np.arange(200) * 0.01
    head = ("time_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s" if kind == "canonical"
            else "Time (s),Gyro X (rad/s),Gyro Y (rad/s),Gyro Z (rad/s)")
    rows = [f"{x:.2f},{np.sin(x):.6f},0.25,-0.125" for x in t]
    clean, trailing, extra = (tmp_path / f"{n}.csv" for n in ("clean", "trailing", "extra"))
    clean.write_text(head + "\n" + "\n".join(rows) + "\n")
    trailing.write_text(head + "\n" + "".join(r + ",\n" for r in rows))
    extra.write_text(head + "\n" + "".join(r + ",[0.0, 0.0]\n" for r in rows))
    want = registry.load(str(clean))
    for f in (trailing, extra):
        got = registry.load(str(f))
        np.testing.assert_array_equal(got.t_imu_s(), want.t_imu_s())
        np.testing.assert_array_equal(got.gyro_rad_s(), want.gyro_rad_s())
        assert not any("sorted" in w or "dropped" in w for w in got.meta.warnings), got.meta.warnings
    assert any("more cells than the header" in w for w in registry.load(str(extra)).meta.warnings)


def test_vendor_csv_with_comment_lines_before_its_header(tmp_path):
    """Comment lines before the header (Xsens MT Manager's export: ``// General information:`` ...
    ``// Coordinate system: ENU``, a BOM first) were read as the header ('first line is no header').
    Skipped: the samples of the same file without them; the stated coordinate system gives the frames (ENU:
    FLU body; no 'axes taken' warning); the native export keeps the lines byte for byte."""
    from parsers.restamp import ClockShift
    from parsers.restamp_csv import restamp_csv_vendor

    head = "Time (s)\tGyro X (rad/s)\tGyro Y (rad/s)\tGyro Z (rad/s)\tAcc X (m/s^2)\tAcc Y (m/s^2)\tAcc Z (m/s^2)\n"
    rows = "".join(f"{1.7e9 + x:.3f}\t{np.sin(x):.6f}\t0.25\t-0.125\t0.5\t0.0\t-9.8\n" for x in T)
    pre = "\ufeff// General information:\n//  MT Manager version: 2022.2.0\n// Coordinate system: ENU\n"
    clean, xsens = tmp_path / "clean.csv", tmp_path / "xsens.csv"
    clean.write_text(head + rows)
    xsens.write_text(pre + head + rows, encoding="utf-8")
    want, got = registry.load(str(clean)), registry.load(str(xsens))
    np.testing.assert_array_equal(got.t_imu_s(), want.t_imu_s())
    flu = np.array([1.0, -1.0, -1.0])  # (FLU -> FRD)
    np.testing.assert_array_equal(got.gyro_rad_s(), want.gyro_rad_s() * flu)
    np.testing.assert_array_equal(got.accel_m_s2(), want.accel_m_s2() * flu)
    assert not any("axes taken" in w for w in got.meta.warnings)
    assert any("axes taken" in w for w in want.meta.warnings)
    sh = ClockShift(0.0123456789, 87.5, got.meta.t0_ns + 1_000_000_000)
    restamp_csv_vendor(str(xsens), str(tmp_path / "out.csv"), sh)
    out = (tmp_path / "out.csv").read_bytes()
    assert out.startswith(pre.encode("utf-8") + head.encode())
    back = registry.load(str(tmp_path / "out.csv"))
    ns = got.meta.t0_ns + np.round(got.t_imu_s() * 1e9).astype(np.int64)
    np.testing.assert_array_equal(back.meta.t0_ns + np.round(back.t_imu_s() * 1e9).astype(np.int64),
                                  sh.to_master_ns(ns))


def test_a_utf16_csv_is_named_as_such(tmp_path, capsys):
    """A CSV saved as UTF-16 text (Excel's "Unicode text"): one line that says so and what to do, not
    'damaged?'."""
    from pipelines.cli import main

    p = tmp_path / "unit.csv"
    p.write_text("Time (s),Gyro X (rad/s),Gyro Y (rad/s),Gyro Z (rad/s)\n" + "".join(
        f"{t:.2f},0.1,0.2,0.3\n" for t in T), encoding="utf-16")
    assert main(["inspect", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "UTF-16 text: save it as UTF-8" in err and "damaged" not in err


def test_ulog2csv_topics_read_as_the_ulog(tmp_path):
    """PX4 topics written to CSV by pyulog's own ``ulog2csv`` (``timestamp,gyro_rad[0],...``; no units, PX4's
    field names) read as the ULog does: sensor_combined's rates and specific forces (the accelerometer at its
    ``accelerometer_timestamp_relative``, PX4's invalid marker left out), vehicle_attitude's quaternion,
    FRD/NED, microseconds since boot. Before: 'no time column with a unit'."""
    import pandas as pd
    from pyulog.ulog2csv import convert_ulog2csv
    from tests.test_parsers_ros import synthetic_log

    ulg = str(tmp_path / "x.ulg")
    registry.write(ulg, synthetic_log(400), "ulog")
    convert_ulog2csv(ulg, "sensor_combined,vehicle_attitude", str(tmp_path), ",", None, None)
    imu_csv, att_csv = (next(tmp_path.glob(f"x_{t}_0.csv")) for t in ("sensor_combined", "vehicle_attitude"))
    want, got, att = registry.load(ulg), registry.load(str(imu_csv)), registry.load(str(att_csv))
    assert got.meta.clock == "boot"  # (the ULog's own reading puts it on UTC by its GPS time: one offset)
    def ns(log, t):
        return log.meta.t0_ns + np.round(t * 1e9).astype(np.int64)

    offset = ns(got, got.t_imu_s()) - ns(want, want.t_imu_s())
    assert np.ptp(offset) == 0
    np.testing.assert_allclose(got.gyro_rad_s(), want.gyro_rad_s(), rtol=1e-6, atol=1e-7)  # (float32 as printed)
    np.testing.assert_allclose(got.accel_m_s2(), want.accel_m_s2(), rtol=1e-6, atol=1e-6)
    (tq, q), (ta, qa) = want.quat_wxyz(), att.quat_wxyz()
    np.testing.assert_array_equal(ns(att, ta), ns(want, tq) + offset[0])
    np.testing.assert_allclose(np.abs(np.sum(q * qa, axis=1)), 1.0, atol=1e-6)
    assert not any("axes taken" in w for w in got.meta.warnings)
    # the accelerometer sampled 1 ms after its row's time, one row without a sample (PX4's marker)
    df = pd.read_csv(imu_csv, dtype=str)
    df["accelerometer_timestamp_relative"] = "1000"
    df.loc[5, "accelerometer_timestamp_relative"] = str(0x7FFFFFFF)
    df.to_csv(tmp_path / "rel.csv", index=False)
    rel = registry.load(str(tmp_path / "rel.csv"))
    assert any("1 accel sample(s) without a valid accelerometer_timestamp_relative" in w for w in rel.meta.warnings)
    t_row = got.meta.t0_ns + np.round(got.t_imu_s() * 1e9).astype(np.int64)
    ch = rel.meta.channels["accel"]
    assert ch.count == len(t_row) - 1  # (its stamps: the rows' + 1 ms, interpolated onto the gyro's by assembly)
    assert any("accel interpolated onto gyro stamps" in w for w in rel.meta.warnings)


@pytest.mark.parametrize("habit", ["decimal_comma", "datetime"])
def test_an_unreadable_vendor_csv_names_the_export_habit(tmp_path, capsys, habit):
    """Decimal commas in cells that commas also split (each number quoted: '"0,1"') or a time column of ISO
    date-times: no row reads, and the one line says why instead of only '0 valid times'. (Decimal commas
    in cells split by semicolons are read: test_vendor_csv_saved_with_decimal_commas_is_read.)"""
    from pipelines.cli import main

    hdr = "Time (s);Gyro X (deg/s);Gyro Y (deg/s);Gyro Z (deg/s);Accel X (g);Accel Y (g);Accel Z (g)"
    if habit == "decimal_comma":
        hdr = hdr.replace(";", ",")
        rows = "".join(",".join(f'"{v}"' for v in (f"{t:.3f}", "0.1", "0.2", "0.3", "0", "0", "1")).replace(".", ",")
                       + "\n" for t in T)
    else:
        rows = "".join(f"2024-05-01T12:00:{t:06.3f}Z;0.1;0.2;0.3;0;0;1\n" for t in T)
    p = tmp_path / "unit.csv"
    p.write_text(hdr + "\n" + rows)
    assert main(["analyze", str(p), str(p), "-o", str(tmp_path / "o")]) == 2  # (refused at the first load)
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert ("decimal commas" if habit == "decimal_comma" else "date-time text") in err


def test_implausible_values_are_dropped_where_every_format_meets():
    from parsers.assemble import Stream, build_inslog

    t = 1_700_000_000_000_000_000 + np.arange(200, dtype=np.int64) * 5_000_000
    g = np.tile([0.1, -0.2, 0.3], (200, 1))
    g[50] = [3.0e38, 0.0, 0.0]  # a float32 with a flipped exponent bit
    v = np.tile([10.0, 0.0, 0.0], (200, 1))
    v[70, 2] = -1e300
    q = np.tile([1.0, 0.0, 0.0, 0.0], (200, 1))
    q[90] = 0.0  # a record zeroed by damage
    q[95] = [1e300, 1e300, 0.0, 0.0]  # a damaged record whose norm overflows (it passed as "missing")
    log = build_inslog(path="x", fmt="test", selector="", clock="epoch", stamp_source="test",
                       gyro=Stream(t, g, "IMU"), vel=Stream(t, v, "NAV"), quat=Stream(t, q, "ATT"))
    assert len(log.imu) == 199 and log.nav["vel_d_m_s"].abs().max() < 1.0
    assert log.nav[["quat_w", "quat_x", "quat_y", "quat_z"]].dropna().shape[0] == 198
    assert np.isfinite(log.nav[["quat_w", "quat_x", "quat_y", "quat_z"]].to_numpy()).sum() == 4 * 198
    assert sum("impossible values dropped" in w for w in log.meta.warnings) == 3


def test_canonical_sniff_is_by_header_not_extension(tmp_path):
    log = _canon_log()
    p = tmp_path / "data.bin"
    csv_canonical.write(str(p), log)
    assert registry.detect(str(p)).NAME == "csv"
    assert csv_vendor.sniff(p.read_bytes()[:8192], str(p)) is False


# ---- the stamps' resolution -----------------------------------------------------------------------
def test_stamp_grid_is_seen_only_where_quantisation_shows():
    """Stamps rounded to whole ms from a clock whose period is not a whole number of ms: 1 ms. An
    exact 5 ms grid (with or without dropped samples) shows nothing; neither do us stamps."""
    from parsers.base import stamp_grid_s

    t0 = 1_700_000_000_123_456_789
    true_ns = t0 + np.rint(np.arange(2000) * 1e9 / 153.7).astype(np.int64)
    assert stamp_grid_s((true_ns + 500_000) // 1_000_000 * 1_000_000) == 1e-3
    assert stamp_grid_s((true_ns + 50_000) // 100_000 * 100_000) == 1e-4
    assert stamp_grid_s(true_ns // 1000 * 1000) == 0.0
    exact = 1_700_000_000_000_000_000 + np.arange(2000, dtype=np.int64) * 5_000_000
    assert stamp_grid_s(exact) == 0.0
    assert stamp_grid_s(np.delete(exact, [10, 11, 500])) == 0.0
    # a 200 Hz clock 30 ppm fast, stamped in whole ms: the phase walks, the steps are 4, 5 or 6 ms
    drifting = t0 + np.rint(np.arange(24000) * 5e6 * (1 + 30e-6)).astype(np.int64)
    assert stamp_grid_s(drifting // 1_000_000 * 1_000_000) == 1e-3


@pytest.mark.parametrize("fmt,expect", [("%.3f", 1e-3), ("%.6f", 1e-6), ("%.9f", 1e-9)])
def test_fixed_decimals_are_the_stamps_resolution(tmp_path, fmt, expect):
    """A CSV whose time is written with a fixed number of decimals says how coarse its stamps are,
    even on an exact grid (canonical and vendor CSV alike)."""
    t = 1_700_000_000.0 + np.arange(0, 20.0, 0.005)
    w = np.c_[np.sin(t - t[0]), np.cos(t - t[0]), 0.1 * np.ones_like(t)]
    canon = _write(tmp_path / "canon.csv", ",".join(["time_s", "gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s"]) + "\n"
                   + "\n".join(f"{fmt % a},{b:.6f},{c:.6f},{d:.6f}" for a, b, c, d in zip(t, *w.T)) + "\n")
    log = registry.load(str(canon))
    assert log.stamp_resolution_s("gyro") == pytest.approx(expect)
    vendor = _write(tmp_path / "vendor.csv", "Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s)\n"
                    + "\n".join(f"{fmt % a},{b:.6f},{c:.6f},{d:.6f}" for a, b, c, d in zip(t, *w.T)) + "\n")
    assert registry.load(str(vendor)).stamp_resolution_s("gyro") == pytest.approx(expect)


def test_canonical_csv_rows_without_a_quaternion_are_not_impossible_ones(tmp_path):
    """A canonical CSV of an IMU at 200 Hz and a navigation solution at 100 Hz leaves the quaternion
    cells of the IMU-only rows empty: those rows have no attitude, they are not corrupt (the reader said
    "quat: N rows with impossible values ignored" for every one of them). A zeroed quaternion still is."""
    from logtools import sim

    pair = sim.simulate(sim.scenario_config("vehicle", duration_s=10.0, seed=1))
    p = tmp_path / "m.csv"
    registry.write(str(p), pair.master, "csv")
    back = registry.load(str(p))
    assert not any("impossible" in w for w in back.meta.warnings), back.meta.warnings
    assert len(back.nav) == len(pair.master.nav)
    lines = p.read_text().splitlines()
    qcol = lines[0].split(",").index("qw")
    row = next(i for i, ln in enumerate(lines[1:], 1) if ln.split(",")[qcol])
    cells = lines[row].split(",")
    cells[qcol:qcol + 4] = ["0", "0", "0", "0"]
    lines[row] = ",".join(cells)
    p.write_text("\n".join(lines) + "\n")
    w = registry.load(str(p)).meta.warnings
    assert any("quat: 1 rows with impossible values" in x for x in w), w


def test_an_isolated_gyro_spike_is_dropped_a_real_shock_is_kept():
    """One gyro sample of -97 rad/s (a flipped exponent bit, inside LIMITS) among 0.09 rad/s neighbours made
    the latency fit choose a 25 s lag; it is dropped and named. A crash's single 14 g sample (both IMUs of
    ArduCopter log0036), a burst of several samples and fast but continuous motion are kept."""
    from parsers.assemble import Stream, build_inslog, impulsive
    from logtools import sim

    t = 1_700_000_000_000_000_000 + np.arange(400, dtype=np.int64) * 5_000_000
    g = np.tile([0.004, -0.007, 0.095], (400, 1))
    g[200, 2] = -97.2
    a = np.tile([-1.35, 1.79, -9.66], (400, 1))
    a[300] = [139.9, 123.1, 16.7]  # the crash: the samples after it are not back where they were
    a[301:] = [10.2, 7.6, 6.2]
    log = build_inslog(path="x", fmt="test", selector="", clock="epoch", stamp_source="test",
                       gyro=Stream(t, g, "IMU"), accel=Stream(t, a, "IMU"))
    assert len(log.imu) == 399 and float(np.abs(log.gyro_rad_s()).max()) < 1.0
    assert float(np.abs(log.accel_m_s2()).max()) > 130.0
    assert sum("isolated spike(s) dropped" in w for w in log.meta.warnings) == 1
    burst = g.copy()
    burst[200:203, 2] = -30.0  # three samples: not one value standing alone
    assert not impulsive("gyro", burst).any()
    for scen in ("multirotor", "aircraft", "vehicle", "ship"):  # fast, noisy, but continuous motion
        pair = sim.simulate(sim.scenario_config(scen, duration_s=60.0, seed=5))
        for u in (pair.master, pair.slave):
            assert not impulsive("gyro", u.gyro_rad_s()).any() and not impulsive("accel", u.accel_m_s2()).any()


def _decimal_reference(text: str) -> int | None:
    from decimal import ROUND_DOWN, Decimal, InvalidOperation

    try:
        x = Decimal(text.strip())
    except InvalidOperation:
        return None
    if not x.is_finite():
        return None
    q = int((x * 10 ** 9).to_integral_value(rounding=ROUND_DOWN))
    return q if abs(q) < 2 ** 63 else None


def test_time_text_with_an_exponent_is_read_exactly(monkeypatch):
    """``5e-05`` (pandas' to_csv for a time below 1e-4), ``1.700000000123456789e+09``: decimal text with an
    exponent is read exactly as the number it writes (truncated below the ns, as decimals are), in the plain
    and the compiled scan; text that is no number stays invalid. Before, such a time was "not a decimal
    number" and its row was dropped (a file of them: refused)."""
    import random

    from parsers import csvtable

    cases = ["5e-05", "1e-4", "-2.5E+3", "1.700000000123456789e+09", "1.7e9", ".5e-3", "1.5e-9", "0e5", "1e-10",
             "12345678901234567890e-10", "1700000000.123456789", "-0.000000001", "+4.", "  3.25  ",
             "1e", "e5", "1e+", "1.2e3.4", "1e5e5", "9e18", "abc", ""]
    rng = random.Random(3)
    for _ in range(3000):
        x = rng.choice([rng.uniform(-1e3, 1e3), rng.uniform(0, 2e9), rng.uniform(-1e-3, 1e-3)])
        cases.append(rng.choice([repr(x), f"{x:.6e}", f"{x:.12e}", f"{x:.9f}", f"{x:.3f}"]))
    chars = csvtable._text_bytes(pd.Series(cases))
    starts = np.arange(len(chars), dtype=np.int64) * chars.shape[1]
    scans = [csvtable._decimal_cells]
    try:
        import numba

        # its helper as numba's own dispatcher: where this process serves the kernels from the ahead-of-time
        # extension, csvtable's global is that extension's stand-in, which numba cannot type (the test
        # failed wherever an earlier test in its process had read a CSV with compiled kernels)
        helper = getattr(csvtable._cell_text, "py_func", csvtable._cell_text)
        monkeypatch.setattr(csvtable, "_cell_text", numba.njit(nogil=True)(helper))
        scans.append(numba.njit(csvtable._decimal_cells))
    except ImportError:
        pass
    want = [_decimal_reference(t) for t in cases]
    for scan in scans:
        with np.errstate(over="ignore"):
            ns, ok = scan(chars.reshape(-1), starts, starts + chars.shape[1], 9, ord("."))
        got = [int(v) if o else None for v, o in zip(ns, ok)]
        assert got == want
    # the same scan over cells of a file's bytes (the native CSV export's): quotes and a CR around them
    raw = "".join(f'"{c}"\r\n' if i % 2 else f"{c}\n" for i, c in enumerate(cases)).encode()
    ends = np.flatnonzero(np.frombuffer(raw, np.uint8) == 10)
    ns, ok = csvtable.decimal_cells_to_int(np.frombuffer(raw, np.uint8), np.r_[0, ends[:-1] + 1], ends, 9)
    assert [int(v) if o else None for v, o in zip(ns, ok)] == want


def test_canonical_csv_written_by_pandas_with_small_times_reads_every_row(tmp_path):
    """pandas' to_csv writes a float time below 1e-4 as 5e-05; that row was dropped as damaged."""
    t = np.concatenate([[0.0, 2.5e-5, 5e-5, 7.5e-5], np.arange(1e-4, 20.0, 0.005)])
    rng = np.random.default_rng(4)
    df = pd.DataFrame({"time_s": t, **{f"gyro_{c}_rad_s": rng.normal(size=len(t)) for c in "xyz"}})
    path = tmp_path / "slave.csv"
    df.to_csv(path, index=False)
    assert "\n5e-05," in path.read_text()
    log = registry.load(str(path))
    assert len(log.imu) == len(t) and not log.meta.warnings
    np.testing.assert_array_equal(np.round(log.t_imu_s() * 1e9).astype(np.int64)[:4], [0, 25_000, 50_000, 75_000])


def test_native_export_of_a_csv_with_exponent_times_rewrites_every_time(tmp_path):
    """The native CSV export reads the time cells with its own fast scan; a time written as 5e-05 was "a line
    without a readable time, copied unchanged" (its time left on the slave's clock). Every time the reader
    reads is now rewritten (as plain decimals)."""
    from parsers.restamp import ClockShift
    from pipelines import export

    t = np.concatenate([[0.0, 2.5e-5, 5e-5, 7.5e-5], np.arange(1e-4, 5.0, 0.005)])
    df = pd.DataFrame({"time_s": t, **{f"gyro_{c}_rad_s": np.sin(t * (i + 1)) for i, c in enumerate("xyz")}})
    src, dst = tmp_path / "slave.csv", tmp_path / "out.csv"
    df.to_csv(src, index=False)
    a = registry.load(str(src))
    shift = ClockShift(0.01, 5.0, a.meta.t0_ns)
    st = export.write_native(str(src), str(dst), "csv", shift, a.meta.selector)
    assert not st.damage and st.records == len(t)
    b = registry.load(str(dst))
    ta = a.meta.t0_ns + np.round(a.t_imu_s() * 1e9).astype(np.int64)
    tb = b.meta.t0_ns + np.round(b.t_imu_s() * 1e9).astype(np.int64)
    np.testing.assert_array_equal(tb, shift.to_master_ns(ta))
    assert dst.read_text().split("\n", 5)[2].split(",")[0] == "-0.009974950"  # (5e-05 on the master's clock)


def test_canonical_csv_with_each_group_in_rows_of_its_own_keeps_every_group(tmp_path):
    """A writer that puts the IMU's samples and the navigation's in rows of their own (the other group's cells
    empty), the navigation's at the same stamps as IMU rows: those rows were dropped as duplicate stamps and
    the navigation lost whole (0 of 3000 rows, no attitude, no velocity for the alignment). Rows sharing a
    stamp are one row now, each cell the first one given; rows that really repeat a stamp with other values
    are still duplicates (the first kept, said)."""
    from logtools import sim

    s = sim.simulate(sim.scenario_config("aircraft", duration_s=20.0, seed=5)).slave
    t0 = s.meta.t0_ns * 1e-9
    imu = s.imu.reset_index(drop=True)
    imu.insert(0, "time_s", t0 + s.imu.index.to_numpy())
    nav = s.nav.rename(columns={"quat_w": "qw", "quat_x": "qx", "quat_y": "qy", "quat_z": "qz"}).reset_index(drop=True)
    nav.insert(0, "time_s", t0 + s.nav.index.to_numpy())
    df = pd.concat([imu, nav], ignore_index=True).sort_values("time_s", kind="stable")
    path = tmp_path / "rows.csv"
    df.to_csv(path, index=False, float_format="%.10f")
    log = registry.load(str(path))
    assert (len(log.imu), len(log.nav)) == (len(s.imu), len(s.nav)) and not log.meta.warnings
    np.testing.assert_allclose(log.vel_ned_m_s()[1], s.vel_ned_m_s()[1], atol=1e-9)
    np.testing.assert_allclose(log.gyro_rad_s(), s.gyro_rad_s(), atol=1e-9)
    # two rows at one stamp with different gyro values: a duplicate, the first kept
    text = path.read_text().splitlines()
    row = text[5].split(",")
    row[1] = "0.5"
    path.write_text("\n".join(text[:6] + [",".join(row)] + text[6:]) + "\n")
    log = registry.load(str(path))
    assert "1 duplicate time stamps dropped" in log.meta.warnings and len(log.imu) == len(s.imu)
    # a row written twice, the same cells: dropped and said
    text = path.read_text().splitlines()
    path.write_text("\n".join(text[:9] + [text[8]] + text[9:]) + "\n")
    log = registry.load(str(path))
    assert "1 duplicate row(s) (the stamp and cells of an earlier row) dropped" in log.meta.warnings


def test_an_isolated_velocity_spike_is_dropped_a_real_manoeuvre_is_kept():
    """One east velocity of -4e-225 m/s among 148 m/s (a damaged MCAP chunk's message data, kept unverified)
    was ingested by the velocity-matched alignment, which did not converge; it is dropped and named. A hard
    but continuous velocity change (10 g at 5 Hz: 20 m/s per sample) and the simulated scenarios are kept."""
    from logtools import sim
    from parsers.assemble import Stream, build_inslog, impulsive

    t = 1_700_000_000_000_000_000 + np.arange(300, dtype=np.int64) * 10_000_000
    v = np.tile([0.0, 148.6, -0.3], (300, 1)) + np.random.default_rng(2).normal(0, 0.02, (300, 3))
    v[150, 1] = -3.9e-225
    log = build_inslog(path="x", fmt="test", selector="", clock="epoch", stamp_source="test",
                       gyro=Stream(t, np.zeros((300, 3)), "IMU"), vel=Stream(t, v, "NAV"))
    assert len(log.vel_ned_m_s()[0]) == 299 and float(log.vel_ned_m_s()[1][:, 1].min()) > 100.0
    assert sum("isolated spike(s) dropped" in w and "m/s" in w for w in log.meta.warnings) == 1
    pull = np.tile([0.0, 100.0, 0.0], (40, 1))
    pull[20:, 1] += 20.0 * np.arange(1, 21)  # 10 g along track, sampled at 5 Hz
    assert not impulsive("vel", pull).any()
    for scen in ("multirotor", "aircraft", "vehicle", "ship"):
        pair = sim.simulate(sim.scenario_config(scen, duration_s=60.0, seed=5))
        for u in (pair.master, pair.slave):
            if u.has_vel:
                assert not impulsive("vel", u.vel_ned_m_s()[1]).any()


def test_gaps_in_a_canonical_csvs_imu_or_navigation_rows_are_said(tmp_path):
    """Every other reader says where a stream's stamps have gaps (``gyro (IMU): 1 gap(s) in stamps``); the
    canonical CSV said nothing of 5 s without navigation rows, and the alignment then read the attitude and
    velocity interpolated across them."""
    from logtools import sim

    s = sim.simulate(sim.scenario_config("aircraft", duration_s=20.0, seed=5)).slave
    path = tmp_path / "s.csv"
    csv_canonical.write(str(path), s)
    header, *rows = path.read_text().splitlines()
    assert header.split(",")[1:7] == ["gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s",
                                      "accel_x_m_s2", "accel_y_m_s2", "accel_z_m_s2"]
    assert not registry.load(str(path)).meta.warnings
    cells = [r.split(",") for r in rows]
    inside = np.array([float(c[0]) for c in cells]) - s.meta.t0_ns * 1e-9
    inside = (inside > 8.0) & (inside < 13.0)

    def cleared(cols: slice) -> list[str]:  # that group's cells empty from 8 to 13 s
        out = []
        for c, cut in zip(cells, inside):
            c = list(c)
            if cut:
                c[cols] = [""] * len(c[cols])
            if any(c[1:]):  # (a line left without a value is not written: a damaged line, said as such)
                out.append(",".join(c))
        return out

    for name, cols in (("imu", slice(1, 7)), ("nav", slice(7, None))):
        path.write_text("\n".join([header] + cleared(cols)) + "\n")
        w = registry.load(str(path)).meta.warnings
        assert len(w) == 1 and w[0].startswith(f"{name} (csv): 1 gap(s) in stamps, longest 5.0"), w
    path.write_text("\n".join([header] + [r for r, cut in zip(rows, inside) if not cut]) + "\n")
    assert {w.split(":")[0] for w in registry.load(str(path)).meta.warnings} == {"imu (csv)", "nav (csv)"}



def _imu_csv(path: Path, t_ns: np.ndarray, gyro: np.ndarray) -> Path:
    body = "\n".join(",".join(r) for r in np.column_stack(
        [csv_canonical.ns_to_seconds_text(t_ns), np.char.mod("%.17g", gyro)]))
    return _write(path, "time_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n" + body + "\n")


def test_a_stretch_of_canonical_csv_lines_out_of_order_is_sorted_not_taken_for_a_clock_step(tmp_path):
    """2000 lines shuffled in a fuzzed canonical CSV: one of their steps back was taken for a clock reset, and
    the 6013 lines before it were left out, with "rows not in time order: sorted" beside it. Lines out of order
    whose times are consistent with the lines around (shuffled, or a stretch moved) are every one kept, sorted,
    said once; a clock that steps back or resets, its times climbing from there over times the lines before it
    already had, still keeps one part."""
    from parsers.assemble import CLOCK_STEP_WORDS

    rng = np.random.default_rng(0)
    n = 8000
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 5_000_000  # 200 Hz
    t += rng.integers(-200_000, 200_000, n)  # (jitter)
    shuffled = np.arange(n)
    shuffled[3000:5000] = rng.permutation(shuffled[3000:5000])  # (taken for two clock steps: 2 parts lost)
    moved = np.concatenate([np.arange(3000), np.arange(4000, 4500), np.arange(3000, 4000), np.arange(4500, n)])
    gyro = rng.standard_normal((n, 3))
    for name, idx in (("shuffled", shuffled), ("moved", moved)):
        log = registry.load(str(_imu_csv(tmp_path / f"{name}.csv", t[idx], gyro[idx])))
        assert len(log.imu) == n, (name, log.meta.warnings)
        np.testing.assert_array_equal(log.meta.t0_ns + np.round(log.t_imu_s() * 1e9).astype(np.int64), t)
        np.testing.assert_array_equal(log.gyro_rad_s(), gyro)
        first = 2 + int(np.flatnonzero(np.diff(t[idx]) < 0)[0]) + 1
        assert log.meta.warnings == (f"rows not in time order: sorted ({int(np.sum(np.diff(t[idx]) < 0))} line(s) "
                                     f"with a time below the one before, first at line {first})",), name
    # a clock step back 3 s at line 2502, and a reset to the log's first time: one part kept, nothing sorted
    for name, back_ns, kept in (("step", 3_000_000_000, slice(0, 5000)), ("reset", None, slice(2000, n))):
        at = 5000 if name == "step" else 2000
        stepped = t.copy()
        stepped[at:] -= back_ns if back_ns else stepped[at] - t[0]
        log = registry.load(str(_imu_csv(tmp_path / f"{name}.csv", stepped, gyro)))
        said = [w for w in log.meta.warnings if CLOCK_STEP_WORDS in w]
        assert len(said) == 1 and f"at line {at + 2} " in said[0], log.meta.warnings
        assert not any("sorted" in w for w in log.meta.warnings), log.meta.warnings
        np.testing.assert_array_equal(log.gyro_rad_s(), gyro[kept])


def test_canonical_csv_rows_with_a_nan_time_or_no_value_are_counted_in_a_warning(tmp_path):
    """Lines whose time is "nan" (or empty) and lines whose every value is NaN or empty were dropped without a
    word (the report said only that the stamps had a gap), where a time that is not a number was said: each
    kind is now counted and its first line named, as that one is."""
    n = 400
    t = np.arange(n) * 0.005
    lines = [f"{ti:.3f},{0.1 * i:.3f},0.2,0.3" for i, ti in enumerate(t)]
    for i in (50, 51, 52, 300):
        lines[i] = "nan" + lines[i][lines[i].index(","):]
    lines[60] = "," + lines[60].split(",", 1)[1]  # (an empty time cell)
    for i in range(100, 110):
        lines[i] = f"{t[i]:.3f},nan,nan,nan"
    lines[200] = f"{t[200]:.3f},,,"
    lines[250] = "x1.5" + lines[250][lines[250].index(","):]  # (not a number: said as before)
    log = registry.load(str(_write(tmp_path / "nan.csv", "time_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n"
                                   + "\n".join(lines) + "\n")))
    assert len(log.imu) == n - 5 - 11 - 1
    w = log.meta.warnings
    assert "5 row(s) whose time is NaN or empty dropped (damaged lines?; first at line 52)" in w, w
    assert "11 row(s) whose every value is NaN or empty dropped (damaged lines?; first at line 102)" in w, w
    assert "1 row(s) whose time is not a decimal number dropped (damaged lines?; first at line 252)" in w, w


def test_an_isolated_position_spike_is_dropped_real_tracks_are_kept():
    """A flipped exponent bit in a log without a checksum (a ROS 1 bag's NavSatFix) doubled one latitude,
    silently: a 4000 km jump of one sample, and back. It is dropped and named; the simulated tracks, a fast
    jet's 1 Hz fixes and a GNSS fix's glitch of tens of metres are kept."""
    from logtools import sim
    from parsers.assemble import Stream, build_inslog, impulsive

    n = 300
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000
    p = np.column_stack([37.4 + 1e-6 * np.arange(n), -122.1 + 2e-6 * np.arange(n), 120.0 + 0.01 * np.arange(n)])
    p[150, 0] *= 2.0
    log = build_inslog(path="x", fmt="test", selector="", clock="epoch", stamp_source="test",
                       gyro=Stream(t, np.zeros((n, 3)), "IMU"), pos=Stream(t, p, "FIX"))
    lat = log.nav["lat_deg"].dropna().to_numpy()
    assert len(lat) == n - 1 and float(lat.max()) < 38.0
    assert sum("isolated spike(s) dropped" in w and "latitude" in w for w in log.meta.warnings) == 1
    jet = np.column_stack([40.0 + 0.0022 * np.arange(60), 10.0 + 0.0 * np.arange(60), 11000.0 + np.zeros(60)])
    glitch = jet.copy()
    glitch[30, :2] += 30.0 / 111_000.0  # (30 m)
    glitch[30, 2] += 40.0
    assert not impulsive("pos", jet).any() and not impulsive("pos", glitch).any()
    for scen in ("multirotor", "aircraft", "vehicle", "ship"):
        pair = sim.simulate(sim.scenario_config(scen, duration_s=60.0, seed=5))
        for u in (pair.master, pair.slave):
            if u.has_pos:
                assert not impulsive("pos", u.nav[["lat_deg", "lon_deg", "alt_m"]].dropna().to_numpy()).any()
