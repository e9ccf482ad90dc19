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
