"""A tlog whose unit stamps HIGHRES_IMU in UNIX time and its attitude in boot time, without SYSTEM_TIME:
the boot streams are mapped onto UNIX time through the receive stamps (not the other way round), so a
master on UNIX/GPS time meets the slave on its own clock."""
from __future__ import annotations

import numpy as np
import pytest
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


def _as_autopilot_sends_it(src: str, dst: str, phase=lambda k: (k * 0.6180339887) % 1) -> int:
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
    boot_epoch_us = st[0].time_unix_usec - st[0].time_boot_ms * 1000  # (the writer's first: on the whole ms)
    k = 0
    with open(dst, "wb") as out:
        for m, stamp in msgs:
            if m.get_type() in ("HIGHRES_IMU", "SYSTEM_TIME"):
                if m.get_type() == "HIGHRES_IMU":
                    m.time_usec -= boot_epoch_us
                else:  # the instant phase(k) of the way through its millisecond (spread by default)
                    m.time_unix_usec = boot_epoch_us + m.time_boot_ms * 1000 + int(1000 * phase(k))
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

    assert back.meta.channels["gyro"].clock_sigma_s < 0.03e-3  # (30 records spread over the millisecond)


@pytest.mark.parametrize("phase", [0.0, 0.37, 0.999])
def test_system_time_sent_in_step_with_the_millisecond_leaves_the_offset_uncertain_and_says_so(tmp_path, phase):
    """SYSTEM_TIME records all taken at one fraction of their millisecond (a simulator on whole milliseconds,
    a scheduler locked to it): the offset lies anywhere in one millisecond. The mapped stamps are within
    0.5 ms of the truth and their channels carry a sigma of 1 ms / sqrt(12) (the latency's sigma includes
    it: tests/test_mavlink_clock.py's CLI test)."""
    log = make_log(duration_s=30.0, clock="epoch")
    full = str(tmp_path / "unix.tlog")
    registry.write(full, log, "tlog")
    path = str(tmp_path / "boot.tlog")
    _as_autopilot_sends_it(full, path, phase=lambda k: phase)
    back = registry.load(path)
    err_ms = (abs_ns(back, back.t_imu_s()) - abs_ns(log, log.t_imu_s())) / 1e6
    assert np.abs(err_ms).max() <= 0.5 + 1e-6, err_ms[:3]
    assert back.meta.channels["gyro"].clock_sigma_s == pytest.approx(1e-3 / np.sqrt(12.0), rel=1e-3)
    assert back.meta.channels["att"].clock_sigma_s == pytest.approx(1e-3 / np.sqrt(12.0), rel=1e-3)


def test_the_latency_sigma_carries_the_system_time_offsets_uncertainty(tmp_path):
    """A tlog slave whose SYSTEM_TIME records sit on the whole millisecond (the offset uncertain by 1 ms): the
    latency's sigma carries 1 ms / sqrt(12) (sigma_budget.clock_mapping, a warning says why) and covers the
    error; with records spread over the millisecond it does not (the sample pair's 5 us)."""
    from logtools import sim
    from logtools.latency import estimate

    pair = sim.simulate(sim.scenario_config("ship", duration_s=60.0, latency_s=0.0417, drift_ppm=0.0,
                                            mount_rpy_deg=(1.0, -2.0, 30.0)))
    full = str(tmp_path / "s_unix.tlog")
    registry.write(full, pair.slave, "tlog")
    locked = str(tmp_path / "s_locked.tlog")
    _as_autopilot_sends_it(full, locked, phase=lambda k: 0.0)
    res = estimate(pair.master, registry.load(locked), compare=False)
    budget = res.quality["sigma_budget"]
    assert budget["clock_mapping"] == pytest.approx(1e-3 / np.sqrt(12.0), rel=0.01)
    assert res.sigma_s >= 0.999e-3 / np.sqrt(12.0)  # (time_unix_usec in whole us: 0 .. 999 us)
    assert abs(res.latency_s - pair.truth.latency_s) <= 3 * res.sigma_s
    assert any("SYSTEM_TIME" in w and "uncertain" in w for w in res.quality["warnings"]), res.quality["warnings"]
    spread = str(tmp_path / "s_spread.tlog")
    _as_autopilot_sends_it(full, spread)
    res2 = estimate(pair.master, registry.load(spread), compare=False)
    assert res2.quality["sigma_budget"].get("clock_mapping", 0.0) < 2e-5
    assert not any("SYSTEM_TIME" in w for w in res2.quality["warnings"])
    assert abs(res2.latency_s - pair.truth.latency_s) < 0.05e-3


def test_offset_sigma_counts_the_readings_spread_and_the_gps_milliseconds():
    from parsers.base import offset_sigma_s

    q = 1e-3 / np.sqrt(12.0)
    assert offset_sigma_s(np.full(50, 123_456_789_000), 1_000_000_000, 1e-3) == pytest.approx(q)
    rng = np.random.default_rng(3)
    d = 123_456_789_000 + rng.normal(0, 8e6, 400).astype(np.int64)  # a logging delay jittering by 8 ms
    assert offset_sigma_s(d, 1_000_000_000, 1e-3) == pytest.approx(np.hypot(8e-3, q), rel=0.15)


def test_a_dataflash_slave_on_gps_time_carries_its_offsets_sigma_into_the_latency(tmp_path):
    """A DataFlash slave put on UNIX time by its GPS week/ms (whole milliseconds) against a master on UNIX
    time: the latency's sigma counts the offset's (sigma_budget.clock_mapping, at least 1 ms / sqrt(12)) and a
    warning says it; two units of one DataFlash file share the offset and carry none."""
    from logtools import sim
    from logtools.latency import estimate

    pair = sim.simulate(sim.scenario_config("ship", duration_s=60.0, latency_s=0.0417, drift_ppm=0.0,
                                            mount_rpy_deg=(1.0, -2.0, 30.0)))
    path = str(tmp_path / "slave.bin")
    registry.write(path, pair.slave, "dataflash")
    slave = registry.load(path)
    assert slave.meta.clock == "epoch" and "1-sigma" in slave.meta.stamp_source
    assert slave.meta.channels["gyro"].clock_sigma_s == pytest.approx(1e-3 / np.sqrt(12.0), rel=1e-3)
    res = estimate(pair.master, slave, compare=False)
    assert res.quality["sigma_budget"]["clock_mapping"] == pytest.approx(1e-3 / np.sqrt(12.0), rel=0.01)
    assert res.sigma_s >= 0.999e-3 / np.sqrt(12.0)
    assert abs(res.latency_s - pair.truth.latency_s) <= 3 * res.sigma_s
    assert any("uncertain" in w for w in res.quality["warnings"]), res.quality["warnings"]
    same = estimate(registry.load(f"{path}::imu=IMU"), registry.load(f"{path}::imu=IMU"), compare=False,
                    max_lag_s=0.5)
    assert same.quality["sigma_budget"].get("clock_mapping", 0.0) == 0.0
    # a second file whose stamps were put on UNIX time by the very same offset (an exported copy read back):
    # shared too
    copy = str(tmp_path / "copy.bin")
    registry.write(copy, pair.slave, "dataflash")
    other = registry.load(copy)
    assert other.meta.channels["gyro"].clock_offset_ns == slave.meta.channels["gyro"].clock_offset_ns is not None
    both = estimate(slave, other, compare=False, max_lag_s=0.5)
    assert both.quality["sigma_budget"].get("clock_mapping", 0.0) == 0.0


def test_whole_millisecond_stamps_are_read_at_the_middle_of_their_millisecond(tmp_path):
    """time_boot_ms counts the whole milliseconds elapsed (ArduPilot's millis(), PX4's hrt_absolute_time() /
    1000: truncated), so a sample's instant lies anywhere in [ms, ms + 1). Read at the whole ms, every such
    stamp was early by half a millisecond on average: a tlog slave whose IMU is SCALED_IMU2 came out 0.5 ms
    early against a microsecond-stamped master (the simulator's 100 Hz tlog pairs -0.41 to -0.75 ms, the
    real SITL log's RAW_IMU against SCALED_IMU2 -0.52 ms). Here an autopilot's HIGHRES_IMU (microseconds)
    and SCALED_IMU2 (truncated milliseconds) of the same samples, at instants spread over their millisecond:
    the two read within half a millisecond of each other and unbiased (-0.5 ms before)."""
    rng = np.random.default_rng(4)
    t_us = np.cumsum(rng.integers(9_500, 10_500, 2000)) + 5_000_000  # ~100 Hz, boot microseconds
    mav = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    path = str(tmp_path / "autopilot.tlog")
    with open(path, "wb") as out:
        for k, tu in enumerate(t_us):
            g = [0.1 * np.sin(0.01 * k), 0.05, -0.02]
            for m in (mavutil.mavlink.MAVLink_highres_imu_message(int(tu), 0.1, 0.2, -9.8, *g, 0, 0, 0, 0, 0, 0, 20.0,
                                                                  0x3F),
                      mavutil.mavlink.MAVLink_scaled_imu2_message(int(tu // 1000), 10, 20, -1000,
                                                                  *[int(round(x * 1000)) for x in g], 0, 0, 0)):
                mav.seq = k % 256
                out.write(int(1_700_000_000_000_000 + tu + 3000).to_bytes(8, "big") + m.pack(mav))
    a = registry.load(f"{path}::imu=HIGHRES_IMU")
    b = registry.load(f"{path}::imu=SCALED_IMU2")
    err_ms = (abs_ns(b, b.t_imu_s()) - abs_ns(a, a.t_imu_s())) / 1e6
    assert len(err_ms) == len(t_us)
    assert np.all(np.abs(err_ms) <= 0.5 + 1e-6)
    assert abs(np.mean(err_ms)) < 0.05, np.mean(err_ms)


def test_the_tlog_writer_puts_whole_milliseconds_elapsed_in_time_boot_ms(tmp_path):
    """tapost's own tlog writer fills time_boot_ms as an autopilot does (truncated): attitude instants at
    random fractions of their millisecond come back within half a millisecond and unbiased."""
    from logtools.inslog import InsLog

    log = make_log(duration_s=20.0, clock="boot")
    rng = np.random.default_rng(4)
    tq, q = log.quat_wxyz()
    tq = tq + rng.uniform(0.0, 1e-3, len(tq))  # each instant somewhere in its millisecond
    _, v = log.vel_ned_m_s()
    _, p = log.lat_lon_alt()
    log = InsLog.from_arrays(log.meta, log.t_imu_s(), log.gyro_rad_s(), log.accel_m_s2(), tq, q, v, p)
    path = str(tmp_path / "unit.tlog")
    registry.write(path, log, "tlog")
    back = registry.load(path)
    err_ms = (abs_ns(back, back.quat_wxyz()[0]) - abs_ns(log, tq)) / 1e6
    assert np.all(np.abs(err_ms) <= 0.5 + 1e-6)
    assert abs(np.mean(err_ms)) < 0.05, np.mean(err_ms)
