"""Units a log may have been written in by mistake, told from the magnitudes of its measurements.

A rotation keeps a vector's length, so whatever the mounting, the two units of one vehicle see angular
rates of the same size and specific forces of the same size (gravity's 9.81 m/s^2 at rest, about that in
flight). A gyro logged in deg/s under a rad/s column makes the slave's rates 57.3 times the master's; an
accelerometer logged in g makes its specific force about 1 instead of 9.8. Neither then matches the other
at any lag, and without this check the user hears "logs of different vehicles?".

:func:`scale_findings` compares the sizes (robust quantiles over the whole logs, decimated) and returns
one sentence per likely mistake, for the report's warnings and the latency's failure message."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from logtools.conventions import G0_M_S2
from logtools.inslog import ACCEL, GYRO, InsLog

DEG_PER_RAD = float(np.degrees(1.0))


@dataclass(frozen=True)
class UnitsCheckConfig:
    #: samples looked at per series at most (a stride over longer logs): quantiles of |x| settle long before
    max_samples: int = 200_000
    #: the angular rate's quantile compared: the moving part of a log (a vehicle at rest half the time still
    #: turns in its top decile), where the noise of either sensor no longer decides the size
    rate_quantile: float = 0.9
    #: below this (rad/s, about 1 deg/s) the master barely turns: the rates' sizes are the sensors' noise,
    #: which differs between units by any factor, so no conclusion
    min_rate_rad_s: float = 0.02
    #: a ratio within this factor of 57.3 (or of 1/57.3) is the deg/rad mix-up: lever-arm and vibration
    #: differences move the ratio of two rigidly mounted units' rates by tens of percent at most
    ratio_tolerance: float = 1.3
    #: a unit's median |specific force| (m/s^2) inside this band is in g, not m/s^2 (a vehicle's median is
    #: gravity's 9.8 within a few tens of percent)
    g_band: tuple[float, float] = (0.6, 1.6)
    #: ... and inside this band it is in m/s^2
    m_s2_band: tuple[float, float] = (6.0, 16.0)


CONFIG = UnitsCheckConfig()


def _norms(log: InsLog, cols: tuple[str, ...], cfg: UnitsCheckConfig) -> np.ndarray:
    """|x| of the IMU columns ``cols``, every k-th row (at most ``max_samples``; the rows taken first, so
    that a long log is not copied whole for them)."""
    step = max(1, log.n_imu // cfg.max_samples)
    x = log.imu_columns.take(slice(None, None, step)).values(cols, "C")
    n = np.sqrt(np.sum(x ** 2, axis=1))
    return n[np.isfinite(n)]


def scale_findings(master: InsLog, slave: InsLog, cfg: UnitsCheckConfig = CONFIG) -> list[str]:
    """Sentences naming a likely unit mistake in either log (empty when the sizes agree)."""
    out: list[str] = []
    if master.has_gyro and slave.has_gyro:
        wm, ws = _norms(master, GYRO, cfg), _norms(slave, GYRO, cfg)
        if len(wm) and len(ws):
            qm, qs = float(np.quantile(wm, cfg.rate_quantile)), float(np.quantile(ws, cfg.rate_quantile))
            if min(qm, qs) * DEG_PER_RAD >= cfg.min_rate_rad_s and qm > 0:  # (the smaller one may be the rad/s)
                r = qs / qm
                for who, ratio in (("slave", r), ("master", 1.0 / r)):
                    if DEG_PER_RAD / cfg.ratio_tolerance <= ratio <= DEG_PER_RAD * cfg.ratio_tolerance:
                        out.append(f"the {who}'s angular rates are {ratio:.1f} times the other unit's "
                                   f"({100 * cfg.rate_quantile:.0f}th percentile of |rate|): logged in deg/s "
                                   "where rad/s is read? (a rotation keeps a rate's size)")
    for who, log in (("master", master), ("slave", slave)):
        if not log.has_accel:
            continue
        f = _norms(log, ACCEL, cfg)
        if not len(f):
            continue
        med = float(np.median(f))
        if cfg.g_band[0] <= med <= cfg.g_band[1]:
            out.append(f"the {who}'s specific force has a median size of {med:.3g}: logged in g where m/s^2 is "
                       f"read? (gravity alone is {G0_M_S2:.2f} m/s^2)")
        elif not cfg.m_s2_band[0] <= med <= cfg.m_s2_band[1]:
            out.append(f"the {who}'s specific force has a median size of {med:.3g} m/s^2, far from gravity's "
                       f"{G0_M_S2:.2f}: wrong units or scale?")
    return out
