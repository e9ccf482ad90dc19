"""A tlog whose unit stamps HIGHRES_IMU in UNIX time and its attitude in boot time, without SYSTEM_TIME:
the boot streams are mapped onto UNIX time through the receive stamps (not the other way round), so a
master on UNIX/GPS time meets the slave on its own clock."""
from __future__ import annotations

import numpy as np
from pymavlink import mavutil

from parsers import registry
from tests.test_parsers_mavlink import abs_ns, make_log


def _drop_system_time(src: str, dst: str) -> int:
    """Copy a tlog without its SYSTEM_TIME records, through pymavlink (receive stamps kept to the us)."""
    raw = open(src, "rb").read()
    conn = mavutil.mavlink_connection(src)
    kept = dropped = 0
    with open(dst, "wb") as out:
        while True:
            m = conn.recv_match()
            if m is None:
                break
            if m.get_type() == "SYSTEM_TIME":
                dropped += 1
                continue
            buf = m.get_msgbuf()
            at = raw.find(buf)  # the record's own 8-byte receive stamp, byte-exact
            out.write(raw[at - 8:at] + buf)
            kept += 1
    assert kept and dropped
    return dropped


def test_unix_imu_and_boot_attitude_without_system_time_land_on_unix_time(tmp_path):
    log = make_log(clock="epoch")
    full = str(tmp_path / "full.tlog")
    registry.write(full, log, "tlog")
    path = str(tmp_path / "no_system_time.tlog")
    _drop_system_time(full, path)
    back = registry.load(path)
    assert back.meta.clock == "epoch"
    assert any("no SYSTEM_TIME" in w and "mapped to UNIX time" in w for w in back.meta.warnings)
    # the IMU keeps its own UNIX stamps exactly
    np.testing.assert_array_equal(abs_ns(back, back.t_imu_s()), abs_ns(log, log.t_imu_s()))
    # the attitude's boot stamps land on UNIX time within the writer's ms truncation (the writer's link
    # delay is constant, so the receive-stamp mapping itself is exact)
    tq, _ = back.quat_wxyz()
    err_ns = abs_ns(back, tq) - abs_ns(log, log.quat_wxyz()[0])
    assert np.abs(err_ns).max() <= 1_000_000


def _as_autopilot_sends_it(src: str, dst: str) -> int:
    """Copy a UNIX-clocked tlog as an autopilot on boot time writes it, through pymavlink: HIGHRES_IMU in boot
    microseconds, and SYSTEM_TIME taken at instants spread over their millisecond (time_unix_usec of the
    instant, time_boot_ms its whole milliseconds: truncated, as ArduPilot's millis() and PX4's are). Returns
    the boot epoch (UNIX us)."""
    raw = open(src, "rb").read()
    conn = mavutil.mavlink_connection(src)
    msgs = []
    while True:
        m = conn.recv_match()
        if m is None:
            break
        buf = m.get_msgbuf()
        msgs.append((m, raw[raw.find(buf) - 8:raw.find(buf)]))
    st = [m for m, _ in msgs if m.get_type() == "SYSTEM_TIME"]
    boot_epoch_us = st[0].time_unix_usec - st[0].time_boot_ms * 1000 - 500  # the writer's: mid-millisecond
    k = 0
    with open(dst, "wb") as out:
        for m, stamp in msgs:
            if m.get_type() in ("HIGHRES_IMU", "SYSTEM_TIME"):
                if m.get_type() == "HIGHRES_IMU":
                    m.time_usec -= boot_epoch_us
                else:  # the instant k * 0.618 of the way through its millisecond (spread, deterministic)
                    m.time_unix_usec = boot_epoch_us + m.time_boot_ms * 1000 + int(1000 * ((k * 0.6180339887) % 1))
                    k += 1
                mav = mavutil.mavlink.MAVLink(None, srcSystem=m.get_srcSystem(), srcComponent=m.get_srcComponent())
                mav.seq = m.get_seq()
                out.write(stamp + m.pack(mav))
            else:
                out.write(stamp + m.get_msgbuf())
    assert k > 10
    return boot_epoch_us


def test_boot_stamps_land_on_unix_time_through_system_time_without_the_half_millisecond(tmp_path):
    """SYSTEM_TIME's time_boot_ms is truncated: unix - boot_ms is on average half a millisecond above the
    boot -> UNIX offset. The IMU's boot-microsecond stamps are mapped onto UNIX time within 0.1 ms of the
    truth (without the half millisecond taken off: +0.5 ms, 80 sigma of a latency estimate on such a log)."""
    log = make_log(duration_s=30.0, clock="epoch")
    full = str(tmp_path / "unix.tlog")
    registry.write(full, log, "tlog")
    path = str(tmp_path / "boot.tlog")
    _as_autopilot_sends_it(full, path)
    back = registry.load(path)
    assert back.meta.clock == "epoch" and "SYSTEM_TIME" in back.meta.stamp_source
    err_ms = (abs_ns(back, back.t_imu_s()) - abs_ns(log, log.t_imu_s())) / 1e6
    assert np.ptp(err_ms) < 1e-3  # one offset for every sample
    assert abs(np.median(err_ms)) < 0.1, np.median(err_ms)
