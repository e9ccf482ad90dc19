"""A constant-frequency vibration common to both units (a rotor, a constant-RPM engine) on top of slow
manoeuvres: the rates' cost has a minimum every vibration period, and the integer-lag search favoured
whichever of them falls on a grid point. An independent simulator's aircraft vibrating at 8.56 Hz came out
one period (116 ms) off at a sigma of 0.05 ms, and the clock-step check's windows locked on such aliases
(false "clock steps" of whole periods). The slow manoeuvres decide between the lags: the latency must come
out right, without a step. And a 1 ms stamp grid whose truncation phase wraps under a drifting clock is no
clock step either."""
from __future__ import annotations

import numpy as np
import pytest

from logtools.conventions import dcm_from_quat
from logtools.inslog import InsLog, LogMeta
from logtools.latency import estimate

T0_NS = 1_700_000_000_000_000_000


class VibratingAircraft:
    """Slow manoeuvres (sums of sines of periods 15-200 s, about 1.6 deg/s RMS) plus a pure 8.56 Hz sinusoid
    on every axis (0.3-0.5 deg/s each: one rotor or engine at a constant RPM): the body rate at any instant,
    exactly."""

    def __init__(self, rng: np.random.Generator):
        n = 20
        self.f = rng.uniform(0.005, 0.07, (n, 3))
        self.ph = rng.uniform(0, 2 * np.pi, (n, 3))
        a = rng.normal(size=(n, 3))
        self.a = a * np.radians(1.6 / np.sqrt(3)) / np.sqrt((a ** 2).sum(0) / 2)
        self.vf = np.full(3, 8.56)
        self.va = np.radians([0.5, 0.4, 0.3])
        self.vph = rng.uniform(0, 2 * np.pi, 3)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        slow = np.sum(self.a * np.sin(2 * np.pi * self.f * t[:, None, None] + self.ph), axis=1)
        return slow + self.va * np.cos(2 * np.pi * self.vf * t[:, None] + self.vph)


def _pair(seed: int, latency_s: float, drift_ppm: float = 15.0, dur_s: float = 90.0):
    rng = np.random.default_rng(seed)
    w = VibratingAircraft(rng)
    q = rng.normal(size=4)
    R = dcm_from_quat(q / np.linalg.norm(q))
    tm = np.arange(0.0, dur_s, 1 / 400.0) + rng.uniform(0, 1 / 400.0)
    ts = np.arange(-1.0, dur_s + 1.0, 1 / 200.0) + rng.uniform(0, 1 / 200.0)
    stamp = ts + latency_s + drift_ppm * 1e-6 * (ts - 0.5 * dur_s)
    wm = w(tm) + np.radians(0.005) * rng.normal(size=(len(tm), 3))
    ws = w(ts) @ R.T + np.radians([0.02, -0.01, 0.03]) + np.radians(0.1) * rng.normal(size=(len(ts), 3))
    master = InsLog.from_arrays(LogMeta("master.csv", "csv", t0_ns=T0_NS), tm, wm)
    slave = InsLog.from_arrays(LogMeta("slave.csv", "csv", t0_ns=T0_NS), stamp, ws)
    return master, slave


def test_vibration_period_alias_is_not_taken():
    """75.2 ms late: the true lag lies half a step of the 100 Hz search grid off it, an alias one period
    earlier (-41.6 ms) 1.6 ms off a grid point. Before the fix: -41.6 ms at a sigma of a few us, and a
    "clock step" of whole periods."""
    truth = 0.0752
    master, slave = _pair(15, truth)
    res = estimate(master, slave, compare=False)
    err = res.latency_s - truth
    assert abs(err) < 1e-3, f"latency {res.latency_s * 1e3:.2f} ms, truth {truth * 1e3:.1f} ms"
    assert abs(err) < 5 * res.sigma_s + 2e-5
    assert not res.quality.get("periodic")
    assert res.quality.get("clock_step") is None


def test_alias_on_unrelated_clocks():
    """The same on clocks 1.7e9 s apart (--max-lag auto): the continuous check works in grid steps about
    each minimum (a bounded search about 1.7e9 s has no sub-millisecond resolution)."""
    truth = 0.0752
    master, slave = _pair(16, truth)
    off_ns = 1_700_000_000_000_000_000  # the slave's clock this much ahead (UNIX time against boot time)
    slave = InsLog.from_arrays(LogMeta("slave.csv", "csv", t0_ns=T0_NS + off_ns), slave.t_imu_s(), slave.gyro_rad_s())
    res = estimate(master, slave, compare=False, max_lag_s=None)
    lat = res.latency_s - off_ns * 1e-9
    assert abs(lat - truth) < 1e-3, f"latency {lat * 1e3:.2f} ms, truth {truth * 1e3:.1f} ms"
    assert res.quality.get("clock_step") is None


def test_clock_step_windows_stay_off_the_aliases():
    """The clock-step check's 10 s windows, each searched +-1 s about the line: their slow motion can hardly
    tell the vibration's periods apart, and the grid favoured an alias in every window (+-117, +-234 ms:
    false "clock steps" of whole periods on the independent simulator's pairs). Each window must take the
    minimum its data prefer at their continuous minima, the one nearest the line where they fit alike."""
    from logtools.latency.coarse import coarse
    from logtools.latency.estimator import analysed_window
    from logtools.latency.prepare import prepare
    from logtools.latency.steps import step_windows
    from logtools.latency.windows import Overlap

    truth, drift = 0.0752, 15e-6
    master, slave = _pair(16, truth, dur_s=120.0)
    ctx = prepare(master, slave, 2.0)
    smp = analysed_window(ctx, coarse(ctx))
    ov = Overlap(smp.t_m, smp.a, smp.valid, ctx.slave.itp, smp.w0, smp.w1)
    c, lat, _, _ = step_windows(ctx, ov, truth, drift, ctx.cfg.steps.search_s)
    assert len(c) >= 8
    off = lat - (truth + drift * (c - ov.t_mid))
    assert np.all(np.abs(off) < 1e-3), np.round(off * 1e3, 2)


def test_stamp_grid_wrap_is_no_clock_step():
    """A 50 Hz slave stamped in whole ms (MAVLink SCALED_IMU) on a clock drifting 5 ppm: the truncation's
    sawtooth wraps once mid-log, the windows' delays jump by one grid step (+1.0 ms at a sigma of 0.04 ms;
    the independent simulator's pair: +0.54 +- 0.075 ms), which is no clock step or reset."""
    from logtools.inslog import ChannelInfo

    rng = np.random.default_rng(1)
    dur = 180.0
    f = rng.uniform(0.03, 1.0, (30, 3))
    ph = rng.uniform(0, 2 * np.pi, (30, 3))
    amp = rng.normal(size=(30, 3))
    amp *= np.radians(10.0) / np.sqrt((amp ** 2).sum(0) / 2)

    def w(t):
        return np.sum(amp * np.sin(2 * np.pi * f * t[:, None, None] + ph), axis=1)

    tm = np.arange(0.0, dur, 1 / 400.0)
    ts = np.arange(-1.0, dur + 1.0, 1 / 50.0)
    stamp = np.floor((ts + 0.035 + 5e-6 * (ts - 0.5 * dur)) * 1000.0 + 1e-9) / 1000.0  # wraps at the middle
    master = InsLog.from_arrays(LogMeta("m.csv", "csv", t0_ns=T0_NS), tm,
                                w(tm) + np.radians(0.005) * rng.normal(size=(len(tm), 3)))
    meta = LogMeta("s.tlog", "tlog", t0_ns=T0_NS, channels={"imu": ChannelInfo(50.0, len(ts), "SCALED_IMU", 1e-3)})
    slave = InsLog.from_arrays(meta, stamp, w(ts) + np.radians(0.05) * rng.normal(size=(len(ts), 3)))
    assert slave.stamp_resolution_s("gyro") == 1e-3
    res = estimate(master, slave, compare=False)
    assert abs(res.latency_s - 0.035) < 1e-3
    assert res.quality.get("clock_step") is None


@pytest.mark.parametrize("scenario, phase", [("vehicle", 0.6), ("aircraft", 0.1)])
def test_a_50_hz_slave_on_a_vibrating_vehicle_gives_its_latency_at_any_sampling_phase(scenario, phase):
    """A 50 Hz slave and a 400 Hz master on a vehicle shaking 0.006-0.01 deg at 12-17 Hz, the slave's clock
    75 ppm slow. The delay's information is that shake's, near the slave's Nyquist rate; read by a cubic
    spline at a fixed offset from its samples it was delayed by up to 0.27 ms, by the offset (the sampling
    phase): 0.22-0.27 ms off at 2-16 sigma, the drift 4.5-5.5 ppm off. Read band-limited
    (``PrepareConfig.band_limited_fraction``): within 3 sigma and 0.01 ms, the drift within 0.5 ppm."""
    from logtools.sim import scenario_config, simulate

    cfg = scenario_config(scenario, duration_s=120.0, seed=5, master_imu_rate_hz=400.0, slave_imu_rate_hz=50.0,
                          latency_s=0.33, drift_ppm=-75.0, slave_start_phase=phase, slave_nav=False,
                          lever_arm_m=(0.4, -1.0, -0.8), rigid_vibration_deg=(0.01, 0.01, 0.006),
                          rigid_vibration_hz=(15.0, 12.0, 17.0))
    p = simulate(cfg)
    r = estimate(p.master, p.slave, compare=False)
    err = r.latency_s - p.truth.latency_s
    assert abs(err) < max(3.0 * r.sigma_s, 1e-5) and abs(err) < 1e-5
    assert abs(r.drift_ppm - p.truth.drift_ppm) < 0.5
