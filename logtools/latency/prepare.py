"""Stage 1, prepare: both units on the master's relative clock, on grids, low-passed at one cutoff;
stamp statistics; the accelerometer and velocity sources. Returns a frozen ``Ctx``."""
from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from logtools.errors import AnalysisError
from logtools.inslog import InsLog
from logtools.latency.beside import both
from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.latency.inputs import (Unit, band_limited_native, make_unit, series_on_grid, signal_band_hz,
                                     uniform_native, unit_rate)
from logtools.latency.system import Accel
from logtools.resample import Interpolant, interpolant, lowpass, median_rate_hz, smooth_interpolant, stamp_noise_s


class RawRates:
    """The two units' rates on their own uniform grids before the low-pass, (master, slave): what
    :func:`refiltered_ctx` low-passes again at another cutoff and the xcorr baseline correlates. Held while the
    stage may need them (its first fit); where they are large (``PrepareConfig.raw_hold_max_bytes``) let go
    then and made again from the logs when asked: the same numbers (4 h of two 200 Hz units: 138 MB held
    through the whole stage otherwise)."""

    def __init__(self, make: Callable[[], tuple], value: tuple | None, max_bytes: float):
        self._make, self._value, self._max_bytes = make, value, max_bytes

    def get(self) -> tuple:
        if self._value is None:
            self._value = self._make()
        return self._value

    def release(self) -> None:
        """Let the series go where they hold more than the threshold they were made with."""
        if self._value is not None and sum(u.values.nbytes for u in self._value) > self._max_bytes:
            self._value = None


@dataclass(frozen=True)
class Ctx:
    """Everything the stages read about the pair, frozen (a stage that changes it returns a new one)."""

    master: Unit
    slave: Unit
    dt_c: float  # common rate (the slower unit's, at most cfg.prepare.max_common_rate_hz)
    cutoff_hz: float
    max_lag_s: float | None
    band_cutoff_hz: float  # the motion's band (signal/noise, the velocities' low-pass)
    dt_s: float = 0.0  # integer-lag search grid
    dt_r: float = 0.0  # continuous refinement samples (master)
    raw: RawRates | None = None  # (master, slave) unfiltered native uniform series (refits, baseline method)
    adapted_cutoff: bool = False
    warnings: tuple[str, ...] = ()  # the inputs' warnings (the stages return their own as data)
    t0_abs_s: float = 0.0
    stamp_jitter_s: tuple[float, float] = (0.0, 0.0)  # (master, slave) white stamp noise, s
    stamp_resolution_s: tuple[float, float] = (0.0, 0.0)  # (master, slave) coarse stamp step of the rates' source
    #: (master, slave) sigma of the offset that put the rates' source on its log's clock (0 where both logs
    #: share it: two units of one tlog system, one SYSTEM_TIME)
    clock_sigma_s: tuple[float, float] = (0.0, 0.0)
    acc_src: tuple | None = None  # accel_pair's arguments, for the accelerometer-aided GLS
    vel_src: tuple | None = None  # (master, slave) for the velocity fit, both with NED velocity
    cfg: LatencyConfig = DEFAULT


def _shared_clock_mapping(master: InsLog, slave: InsLog, groups: tuple[str, str]) -> bool:
    """Both units' stamps put on UNIX time by the same offset (one file, one tlog system; or the very same
    offset, to the nanosecond, in two files: a log and its exported copy read back): its error cancels."""
    def sysid(log: InsLog) -> str | None:
        m = re.search(r"(?:^|,)sysid=(\d+)", log.meta.selector or "")
        return m.group(1) if m else None

    off_m, off_s = master.clock_offset_ns(groups[0]), slave.clock_offset_ns(groups[1])
    if off_m is not None and off_m == off_s:
        return True
    return bool(master.meta.source_path) and master.meta.source_path == slave.meta.source_path \
        and sysid(master) == sysid(slave)


def prepare(master: InsLog, slave: InsLog, max_lag_s: float | None, *, accelerometers: bool = True,
            velocity: bool = True, cfg: LatencyConfig = DEFAULT, threads: bool = False) -> Ctx:
    """Both units on the master's relative clock, gridded, low-passed at one cutoff; AnalysisError for
    no or too short overlap and unusable rates. ``threads``: the slave's grids and filters made in a thread
    beside the master's (``beside.both``; the same numbers)."""
    if max_lag_s is not None and not (np.isfinite(max_lag_s) and max_lag_s > 0):
        raise AnalysisError(f"max_lag_s must be positive or None (whole overlap), not {max_lag_s!r}")
    slave_r = slave.rebased(master.meta.t0_ns)
    tm, wm, srcm = unit_rate(master, "master")
    ts, ws, srcs = unit_rate(slave_r, "slave")
    fm, fs = median_rate_hz(tm), median_rate_hz(ts)
    f_c = min(fm, fs, cfg.prepare.max_common_rate_hz)
    dt_c = 1.0 / f_c
    # master and slave spans (finite samples), face value
    okm = np.all(np.isfinite(wm), axis=1) & np.isfinite(tm)
    oks = np.all(np.isfinite(ws), axis=1) & np.isfinite(ts)
    m0, m1 = float(np.min(tm[okm])), float(np.max(tm[okm]))
    s0, s1 = float(np.min(ts[oks])), float(np.max(ts[oks]))
    if min(m1 - m0, s1 - s0) < cfg.prepare.min_overlap_s:
        raise AnalysisError(f"logs too short for a latency estimate: master {m1 - m0:.1f} s, slave "
                            f"{s1 - s0:.1f} s of angular rate (need {cfg.prepare.min_overlap_s:g} s of overlap)")
    if max_lag_s is not None:
        ov = min(m1, s1 + max_lag_s) - max(m0, s0 - max_lag_s)
        if ov < cfg.prepare.min_overlap_s:
            raise AnalysisError(
                f"no overlap between master [{m0 + master.t0_s:.3f}, {m1 + master.t0_s:.3f}] s and slave "
                f"[{s0 + master.t0_s:.3f}, {s1 + master.t0_s:.3f}] s within +-{max_lag_s:g} s at face value "
                f"(clocks unrelated? use --max-lag auto)")
    (natm, nm, band_m), (nats, ns, band_s) = both(_native_and_band, (tm, wm, "master"), (ts, ws, "slave"), threads)
    # zero-phase low-pass of both units at the same cutoff: a few times the motion's band (the noise
    # between the motion's band and Nyquist would otherwise bias a spline-interpolated sub-sample delay)
    band = (min if cfg.prepare.band_common else max)(band_m, band_s)
    floor = min(cfg.prepare.min_cutoff_hz, max(cfg.prepare.band_min_cutoff_hz, cfg.prepare.min_cutoff_fraction * f_c))
    cutoff = float(np.clip(cfg.prepare.band_factor * band, floor, cfg.prepare.cutoff_fraction * f_c))
    band_cutoff = float(np.clip(cfg.prepare.band_factor * band, cfg.prepare.band_min_cutoff_hz,
                                cfg.prepare.cutoff_fraction * f_c))
    # both units are band-limited at the cutoff: refinement samples at 5x the cutoff carry all the
    # information (a denser grid only costs time; the residuals' correlation is handled by the HAC)
    f_r = min(f_c, max(cfg.prepare.refine_band_factor * cutoff, cfg.prepare.min_refine_rate_hz))
    f_s = min(f_r, cfg.prepare.max_coarse_rate_hz)
    (natm, um), (nats, us) = both(_unit, (natm, tm, wm, fm, nm, srcm, "master", f_s, cutoff, cfg),
                                  (nats, ts, ws, fs, ns, srcs, "slave", f_s, cutoff, cfg), threads)
    grp_m, grp_s = ("gyro" if src == "gyro" else "att" for src in (srcm, srcs))  # the rates' source channels
    res_s = (master.stamp_resolution_s(grp_m), slave.stamp_resolution_s(grp_s))
    clk_s = ((0.0, 0.0) if _shared_clock_mapping(master, slave, (grp_m, grp_s))
             else (master.clock_sigma_s(grp_m), slave.clock_sigma_s(grp_s)))
    warnings = list(um.native.warnings) + list(us.native.warnings)
    for role, q, log in zip(("master", "slave"), clk_s, (master, slave)):
        if q >= cfg.prepare.clock_sigma_warn_s:
            src = log.meta.stamp_source or ""
            why = ("its SYSTEM_TIME records in step with the millisecond" if "SYSTEM_TIME" in src else
                   "its GPS time's per-fix offsets spread (a varying logging delay, whole milliseconds)"
                   if "GPS" in src else "see its stamp source")
            warnings.append(f"{role} stamps put on UNIX time by an offset uncertain by {q * 1e3:.2g} ms (1 sigma; "
                            f"{why}): in the latency's sigma")
    acc_src = vel_src = None
    if (accelerometers and cfg.prepare.accel_aided and srcm == "gyro" and srcs == "gyro" and master.has_accel
            and slave_r.has_accel):
        # built when needed (accel_pair)
        acc_src = (master, slave_r, cutoff, um.itp, cfg.prepare.band_limited_fraction)
    if velocity and cfg.prepare.velocity_aided and master.has_vel and slave_r.has_vel:
        vel_src = (master, slave_r)  # built when needed (velocity_step)
    for role, q in zip(("master", "slave"), res_s):
        if q >= cfg.prepare.resolution_warn_s:
            warnings.append(f"{role} stamps are whole multiples of {q * 1e3:g} ms: the latency's sigma is "
                            f"at least {q / np.sqrt(12.0) * 1e3:.3g} ms (a fixed sampling phase offsets "
                            f"every stamp alike)")
    if srcm == "attitude" or srcs == "attitude":
        warnings.append("angular rate derived from attitude for the " +
                        " and ".join(r for r, s in (("master", srcm), ("slave", srcs)) if s == "attitude"))
    for role, src, w in (("master", srcm, wm), ("slave", srcs, ws)):
        n_bad = int(np.sum(~np.all(np.isfinite(w), axis=1))) if src == "attitude" else 0
        if n_bad:
            warnings.append(f"{role}: {n_bad} of {len(w)} attitude intervals frozen (an EKF not running) or "
                            f"at a reset left out of the rates")
    def raw_again() -> tuple:  # (prepare's own steps for the two series: the same numbers)
        out = []
        for log, role, rate_hz in ((master, "master", fm), (slave_r, "slave", fs)):
            t, w, _ = unit_rate(log, role)
            nat, _ = uniform_native(t, w, role)
            out.append(band_limited_native(nat, t, w, rate_hz, cutoff, cfg.prepare.band_limited_fraction, role))
        return tuple(out)

    return Ctx(um, us, dt_c, cutoff, max_lag_s, band_cutoff_hz=band_cutoff, t0_abs_s=master.t0_s,
               dt_s=1.0 / f_s, dt_r=1.0 / f_r, raw=RawRates(raw_again, (natm, nats), cfg.prepare.raw_hold_max_bytes),
               stamp_jitter_s=(stamp_noise_s(tm), stamp_noise_s(ts)), stamp_resolution_s=res_s, clock_sigma_s=clk_s,
               warnings=tuple(warnings), acc_src=acc_src, vel_src=vel_src, cfg=cfg)


def _native_and_band(t: np.ndarray, w: np.ndarray, name: str) -> tuple:
    """One unit's rates on their own uniform grid, their white-noise level and their motion's band."""
    nat, noise = uniform_native(t, w, name)
    return nat, noise, signal_band_hz(nat, noise)


def _unit(nat, t: np.ndarray, w: np.ndarray, rate_hz: float, noise: float, src: str, name: str, f_s: float,
          cutoff: float, cfg: LatencyConfig) -> tuple:
    """One unit band-limited where its cutoff asks for it (that series), low-passed and gridded (``make_unit``)."""
    nat = band_limited_native(nat, t, w, rate_hz, cutoff, cfg.prepare.band_limited_fraction, name)
    return nat, make_unit(nat, noise, src, name, rate_hz, 1.0 / f_s, cutoff)


def refiltered_ctx(ctx: "Ctx", cutoff_hz: float) -> "Ctx":
    """The units low-passed again (zero-phase) from their raw series at a new cutoff."""
    units = []
    for u, nat in zip((ctx.master, ctx.slave), ctx.raw.get()):
        lp = lowpass(nat, cutoff_hz)
        itp = interpolant(lp)
        units.append(replace(u, native=lp, itp=itp, grid=series_on_grid(itp, ctx.dt_s)))
    return replace(ctx, master=units[0], slave=units[1], cutoff_hz=cutoff_hz, adapted_cutoff=True)


def accel_pair(master: InsLog, slave: InsLog, cutoff_hz: float, master_rate: Interpolant,
               band_limited_fraction: float | None = None) -> Accel | None:
    """Both units' specific force, uniform and low-passed at the rates' cutoff (band-limited as the rates
    are, ``PrepareConfig.band_limited_fraction``); None when either unit has no (or too little finite)
    accelerometer data."""
    itps = []
    for log, role in ((master, "master"), (slave, "slave")):
        if not log.has_accel:
            return None
        t, f = log.t_imu_s(), log.accel_m_s2()
        ok = np.isfinite(t) & np.all(np.isfinite(f), axis=1)
        if ok.sum() < 256:
            return None
        try:
            itps.append(smooth_interpolant(t[ok], f[ok], cutoff_hz, name=f"{role} accelerometer",
                                              band_limited_fraction=band_limited_fraction))
        except ValueError:
            return None
    return Accel(itps[0], itps[1], master_rate)

