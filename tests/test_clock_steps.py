"""A clock step or reset in one log mid-recording (sweep F1): told from reordering and stray stamps by the
parsers (a step back splits the log: one part kept, said in one line), and from drift by the latency
stage (``latency.quality.clock_step``: the status is not "ok")."""
from __future__ import annotations

import re

import numpy as np
import pytest

from logtools.inslog import InsLog
from logtools.latency import estimate
from parsers import csv_canonical as cc
from parsers.assemble import CLOCK_STEP_WORDS, Stream, clean_stream, clock_steps
from parsers.base import Selector
from pipelines import report as rp
from test_latency import T0_NS, make_pair, random_rotation

LAT_S = 0.12


def _stepped_slave(slave: InsLog, at_s: float, step_s: float) -> InsLog:
    """The slave with its stamps stepped by ``step_s`` from master time ``at_s`` on (kept in time order)."""
    t = slave.t_imu_s().copy()
    t[t >= at_s + LAT_S] += step_s
    return InsLog.from_arrays(slave.meta, t, slave.gyro_rad_s())


def _report(master, slave, res) -> dict:
    return rp.build_report(master, slave, latency=res, alignment={}, timings_s={})


# ---- the latency stage ------------------------------------------------------------------------------
def test_forward_clock_step_is_found_and_the_status_is_not_ok():
    """Slave stamps +20 ms from mid-log: one line turned this into ~240 ppm of drift with status ok."""
    rng = np.random.default_rng(1)
    master, slave = make_pair(rng, latency_s=LAT_S, drift_ppm=30.0, dur_s=120.0, R=random_rotation(rng))
    slave = _stepped_slave(slave, 60.0, 0.020)
    res = estimate(master, slave, compare=False)
    cs = res.quality["clock_step"]
    assert cs is not None
    assert abs(cs["step_s"] - 0.020) <= 3 * cs["sigma_s"] + 1e-5
    assert abs(cs["t_s"] - (T0_NS * 1e-9 + 60.0)) < 10.0  # near the step (the windows are 10 s)
    assert cs["latency_before_s"] == pytest.approx(LAT_S, abs=2e-3)
    assert cs["latency_after_s"] == pytest.approx(LAT_S + 0.020, abs=2e-3)
    rep = _report(master, slave, res)
    assert rep["status"] != "ok" and "latency steps by +20" in rep["status_reason"]
    texts = [w["text"] for w in rep["warnings"] if w["stage"] == "latency"]
    said = [t for t in texts if t.startswith("the latency steps by +") and "clock step or reset" in t]
    assert len(said) == 1, texts
    size, before, after = (float(re.search(pat, said[0]).group(1)) for pat in
                           (r"steps by ([-+.\d]+) ms", r"before ([-+.\d]+) ms", r"after ([-+.\d]+) ms"))
    assert size == pytest.approx(20.0, abs=1.0) and before == pytest.approx(120.0, abs=2.0)
    assert after == pytest.approx(140.0, abs=2.0)
    assert not any("differs between parts" in t for t in texts)  # the step says why


@pytest.mark.parametrize("drift_ppm", [100.0, -100.0])
def test_drift_without_a_step_is_not_a_step(drift_ppm):
    rng = np.random.default_rng(2)
    master, slave = make_pair(rng, latency_s=LAT_S, drift_ppm=drift_ppm, dur_s=120.0, R=random_rotation(rng))
    res = estimate(master, slave, compare=False)
    assert res.quality["clock_step"] is None
    assert res.drift_ppm == pytest.approx(drift_ppm, abs=2.0)
    rep = _report(master, slave, res)
    assert rep["status"] == "ok" and "status_reason" not in rep
    assert not any("latency steps" in w["text"] for w in rep["warnings"])


# ---- the parsers --------------------------------------------------------------------------------
def _csv_text(t_ns: np.ndarray, gyro: np.ndarray) -> str:
    body = "\n".join(",".join(r) for r in np.column_stack(
        [cc.ns_to_seconds_text(t_ns), np.char.mod("%.17g", np.asarray(gyro, float))]))
    return "time_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n" + body + "\n"


def test_csv_clock_step_back_keeps_one_part(tmp_path):
    """Rows in file order, the slave's stamps stepping back 2 s at 60 s: sorted, the two halves were
    interleaved (400 "duplicates" dropped) and the latency came out -1037 ms at status ok."""
    rng = np.random.default_rng(3)
    master, slave = make_pair(rng, latency_s=LAT_S, dur_s=120.0, R=random_rotation(rng))
    t_ns = slave.meta.t0_ns + np.round(slave.t_imu_s() * 1e9).astype(np.int64)
    at = int(np.searchsorted(t_ns, T0_NS + int((60.0 + LAT_S) * 1e9)))
    t_ns[at:] -= 2_000_000_000
    p = tmp_path / "slave.csv"
    p.write_text(_csv_text(t_ns, slave.gyro_rad_s()))
    log = cc.load(str(p), Selector())
    w = [x for x in log.meta.warnings if CLOCK_STEP_WORDS in x]
    assert len(w) == 1, log.meta.warnings
    assert f"at line {at + 2} " in w[0] and "-2.000 s" in w[0] and "left out lines" in w[0]
    assert f"{t_ns[at - 1] * 1e-9:.3f} s -> {t_ns[at] * 1e-9:.3f} s" in w[0]
    assert not any("duplicate" in x or "sorted" in x for x in log.meta.warnings)
    t = log.t_imu_s()
    assert len(t) == at and np.all(np.diff(t) > 0)  # the part before the step, not interleaved
    np.testing.assert_array_equal(log.gyro_rad_s(), slave.gyro_rad_s()[:at])
    res = estimate(master, log, compare=False)
    assert res.latency_s == pytest.approx(LAT_S, abs=0.5e-3)
    assert res.quality["clock_step"] is None
    rep = _report(master, log, res)
    assert rep["status"] == "partial" and "slave log's clock steps back" in rep["status_reason"]


def test_csv_corrupt_time_cell_is_dropped_alone(tmp_path):
    """One time cell with a wrong digit (30 s ahead) in a canonical CSV: that line dropped, said with its line
    number; not a clock step splitting the file."""
    rng = np.random.default_rng(3)
    _, slave = make_pair(rng, latency_s=LAT_S, dur_s=60.0, R=random_rotation(rng))
    t_ns = slave.meta.t0_ns + np.round(slave.t_imu_s() * 1e9).astype(np.int64)
    bad = t_ns.copy()
    bad[3000] += 30_000_000_000
    p = tmp_path / "slave.csv"
    p.write_text(_csv_text(bad, slave.gyro_rad_s()))
    log = cc.load(str(p), Selector())
    assert len(log.imu) == len(t_ns) - 1 and not any(CLOCK_STEP_WORDS in x for x in log.meta.warnings)
    assert any("1 line(s) whose time jumps away" in x and "first at line 3002" in x for x in log.meta.warnings)


def test_reordering_and_stray_stamps_are_no_clock_step():
    """Late samples (single ones, a burst) are sorted as before; a stray stamp is dropped as before."""
    t = np.arange(20_000, dtype=np.int64) * 5_000_000 + T0_NS  # 200 Hz
    late = t.copy()
    late[[500, 7000]] -= 200_000_000  # single samples 0.2 s late in the record
    idx = np.arange(len(t))
    burst = np.concatenate([idx[:8800], idx[8830:9030], idx[8800:8830], idx[9030:]])
    late = late[burst]  # a burst of 30 samples recorded 1 s late
    assert len(clock_steps(late)) == 0
    warns: list[str] = []
    out = clean_stream("gyro", Stream(late, np.zeros((len(t), 3)), "IMU"), warns)
    assert len(out.t_ns) == len(t) - 2  # sorted; the two single late ones land on stamps already taken
    assert any("backward time steps" in x and "sorted" in x for x in warns)
    assert not any(CLOCK_STEP_WORDS in x for x in warns)
    stray = t.copy()
    stray[100] += 12 * 86400 * 10**9  # one corrupt stamp 12 days on
    assert len(clock_steps(stray)) == 0
    warns: list[str] = []
    out = clean_stream("gyro", Stream(stray, np.zeros((len(t), 3)), "IMU"), warns)
    assert len(out.t_ns) == len(t) - 1 and not any(CLOCK_STEP_WORDS in x for x in warns)
    # a reset (the stamps back to the start of the clock) is one
    reset = t.copy()
    reset[12_000:] -= reset[12_000] - t[0] - 1_000_000_000
    assert clock_steps(reset).tolist() == [12_000]
    warns = []
    out = clean_stream("gyro", Stream(reset, np.zeros((len(t), 3)), "IMU"), warns)
    assert len(out.t_ns) == 12_000 and np.array_equal(out.t_ns, t[:12_000])
    assert any(CLOCK_STEP_WORDS in x and "at sample 12000" in x for x in warns)


def test_a_corrupt_stamp_repeated_by_a_compressor_is_stray_too():
    """One flipped bit of an LZ4 ROS 1 bag came out in 7 consecutive IMU stamps, 1.0e9 s before the other
    7789 (the compressor copies earlier bytes by reference); the analysis then refused the slave as "spread over
    1004176466 s". A run that small (at most 0.2 % of the stream) a minute or more from the rest is stray; a
    run larger than that beyond a pause is kept (logs joined across a pause)."""
    t = np.arange(7796, dtype=np.int64) * 5_000_000 + T0_NS  # 200 Hz
    bad = t.copy()
    bad[:7] -= 1_004_176_466 * 10**9
    warns: list[str] = []
    out = clean_stream("gyro", Stream(bad, np.zeros((len(t), 3)), "IMU"), warns)
    assert np.array_equal(out.t_ns, t[7:])
    assert any("7 sample(s) with stray stamps dropped" in w for w in warns)
    paused = t.copy()
    paused[:40] -= 120 * 10**9  # 0.2 s of data two minutes before the rest: kept (a gap, not stray)
    warns = []
    out = clean_stream("gyro", Stream(paused, np.zeros((len(t), 3)), "IMU"), warns)
    assert len(out.t_ns) == len(t) and not any("stray" in w for w in warns)
    long = np.arange(200_000, dtype=np.int64) * 5_000_000 + T0_NS  # 1000 s: 0.2 % would be 400 samples
    long[:100] -= 120 * 10**9  # half a second two minutes before the rest: beyond 64 samples, kept
    warns = []
    out = clean_stream("gyro", Stream(long, np.zeros((len(long), 3)), "IMU"), warns)
    assert len(out.t_ns) == len(long) and not any("stray" in w for w in warns)


def test_a_corrupt_stamp_is_dropped_not_taken_for_a_clock_step():
    """One flipped byte of a DataFlash TimeUS put a sample 3.5 s ahead; the stamps after it were taken for a
    clock stepping back, and the part before kept: a quarter of the log lost (bench_damage: DataFlash 0.63,
    ROS 2 sqlite3 0.69 of the samples kept). A stamp (or up to three) that jumps away from its neighbours and
    back, where the stream has no hole for it, is dropped alone; a late sample with its true stamp fills a
    hole and is sorted in as before; a clock that steps back keeps running from there and is still a step."""
    from parsers.assemble import stamp_outliers

    t = np.arange(8000, dtype=np.int64) * 5_000_000 + T0_NS  # 200 Hz
    for shift_ns, at in ((3_473_000_000, [6039]), (-2_000_000_000, [2500]), (900_000_000, [100, 101, 102])):
        bad = t.copy()
        bad[at] += shift_ns
        assert np.flatnonzero(stamp_outliers(bad)).tolist() == at
        warns: list[str] = []
        out = clean_stream("gyro", Stream(bad, np.zeros((len(t), 3)), "IMU"), warns)
        assert np.array_equal(out.t_ns, np.delete(t, at)), warns
        assert any("jump away from their neighbours and back dropped" in w for w in warns)
        assert not any(CLOCK_STEP_WORDS in w for w in warns)
    late = np.concatenate([t[:400], t[401:500], t[400:401], t[500:]])  # recorded late, its own stamp
    assert not stamp_outliers(late).any()
    stepped = t.copy()
    stepped[5000:] -= 3_000_000_000  # a clock set back 3 s: it runs on from there
    assert not stamp_outliers(stepped).any() and clock_steps(stepped).tolist() == [5000]
    jitter = t + np.random.default_rng(1).integers(-1_500_000, 1_500_000, len(t))
    assert not stamp_outliers(jitter).any()


def test_an_export_through_a_clock_step_says_so():
    """The export puts one line through both sides of a clock step: its section and a warning say how far
    off either side is; without a step, nothing."""
    from pipelines import export

    q = {"clock_step": {"step_s": 0.0202, "t_rel_s": 60.0, "latency_before_s": 0.1199, "latency_after_s": 0.1401}}
    text = export.clock_step_caveat(q)
    assert text is not None and "+20.2 ms near 60.0 s" in text and "about 10.1 ms on either side" in text
    assert export.clock_step_caveat({"clock_step": None}) is None and export.clock_step_caveat(None) is None


def test_a_stretch_recorded_twice_is_dropped_not_taken_for_a_clock_step():
    """A stretch of records written twice (a logger's buffer flushed again, a telemetry block resent): the
    stamps run back by the stretch's length and on again, and the clock-step rule kept one part of the log (a
    simulated tlog with 0.66 s of its bytes repeated kept 3652 of 6000 IMU samples). Samples that repeat an
    earlier one exactly, stamp and values, are dropped alone and said; a reset onto stamps already used, with
    other values, is still a clock step."""
    from parsers.assemble import repeated_samples

    rng = np.random.default_rng(5)
    t = np.arange(8000, dtype=np.int64) * 5_000_000 + T0_NS  # 200 Hz
    v = rng.standard_normal((len(t), 3))
    idx = np.concatenate([np.arange(3000), np.arange(2870, 8000)])  # samples 2870..2999 recorded twice
    warns: list[str] = []
    out = clean_stream("gyro", Stream(t[idx], v[idx], "IMU"), warns)
    np.testing.assert_array_equal(out.t_ns, t)
    np.testing.assert_array_equal(out.values, v)
    assert any("130 sample(s) repeating earlier ones exactly" in w for w in warns), warns
    assert not any(CLOCK_STEP_WORDS in w for w in warns)
    assert np.flatnonzero(repeated_samples(t[idx], v[idx])).tolist() == list(range(3000, 3130))
    other = v[idx].copy()
    other[3000:] += 1.0  # the same stamps again, other values: a clock reset, not a repeat
    assert not repeated_samples(t[idx], other).any()
    warns = []
    clean_stream("gyro", Stream(t[idx], other, "IMU"), warns)
    assert any(CLOCK_STEP_WORDS in w for w in warns)
    assert not repeated_samples(t, v).any()  # (stamps that never run back: one comparison pass)


def _read_with_a_stretch_repeated(tmp_path, log, fmt: str):
    """(the log written in ``fmt`` and read back, the same file with 2 % of its bytes repeated in place at 40 %
    and read back)."""
    from parsers import registry

    good = tmp_path / f"good.{fmt}"
    registry.write(str(good), log, fmt)
    raw = good.read_bytes()
    a, b = int(0.40 * len(raw)), int(0.42 * len(raw))
    bad = tmp_path / f"bad.{fmt}"
    bad.write_bytes(raw[:b] + raw[a:b] + raw[b:])
    return registry.load(str(good)), registry.load(str(bad))


@pytest.mark.parametrize("fmt", ["tlog", "csv"])
def test_a_log_file_with_a_stretch_of_bytes_repeated_reads_whole(tmp_path, fmt):
    """The same as the format sees it: a tlog's bytes (its frames resynchronised after the cut copy) or a
    canonical CSV's lines repeated in place; every sample read once, none lost to a clock step."""
    from logtools import sim

    pair = sim.simulate(sim.scenario_config("multirotor", duration_s=30.0, seed=3))
    full, back = _read_with_a_stretch_repeated(tmp_path, pair.slave, fmt)
    assert not any(CLOCK_STEP_WORDS in w for w in back.meta.warnings), back.meta.warnings
    assert any("repeating earlier ones exactly" in w for w in back.meta.warnings)
    assert len(full.imu) - 2 <= len(back.imu) <= len(full.imu)  # (the frame cut by the copy's ends: its CRC)
    assert len(full.nav) - 2 <= len(back.nav) <= len(full.nav)


@pytest.mark.parametrize("fmt", ["tlog", "ulog", "dataflash"])
def test_a_stretch_recorded_twice_with_a_constant_accelerometer_is_dropped_from_every_stream(tmp_path, fmt):
    """The streams of one record (a HIGHRES_IMU's gyro and accel) judged together: an accelerometer whose
    values do not change along the repeated stretch (at rest, quantised) was no repeat on its own, and the
    clock-step rule kept one part of it while the gyro kept the whole log (the IMU: 3599 of 6000 samples in
    a tlog and a ULog, 3604 in a DataFlash log). Judged side by side with the gyro, the stretch is a repeat
    for both."""
    from logtools import sim

    pair = sim.simulate(sim.scenario_config("multirotor", duration_s=30.0, seed=3))
    imu = pair.slave.imu.copy()
    imu[["accel_x_m_s2", "accel_y_m_s2", "accel_z_m_s2"]] = [0.0, 0.0, -9.81]
    slave = type(pair.slave)(imu=imu, nav=pair.slave.nav, meta=pair.slave.meta)
    full, back = _read_with_a_stretch_repeated(tmp_path, slave, fmt)
    assert not any(CLOCK_STEP_WORDS in w for w in back.meta.warnings), back.meta.warnings
    assert any(w.startswith("gyro+accel") and "repeating earlier ones exactly" in w for w in back.meta.warnings)
    assert len(full.imu) - 2 <= len(back.imu) <= len(full.imu)
