"""Scenario simulator: a master/slave INS pair with known truth (issue 2).

Truth comes from ANALYTIC attitude (Euler) and velocity profiles, carried with their time derivatives
by a small forward-mode differentiation helper (``_Jet``: value and derivatives up to third order).
The IMU outputs follow by inverse strapdown:

* ``omega_ib^b = omega_nb^b (from the Euler rates) + C_n^b (omega_ie^n + omega_en^n)``;
* ``f^b = C_n^b (dv^n/dt + (2 omega_ie^n + omega_en^n) x v^n - g^n)`` with ``dv^n/dt`` analytic;
* position (lat, lon, alt) integrates ``earth.llh_rates`` on a fixed 50 Hz grid anchored at t = 0
  (Simpson per interval with analytic mid-point velocities, Picard iterations for the weak latitude
  coupling) and is read between nodes by cubic Hermite interpolation with the exact rates.

IMU samples are POINT samples at the sample instant (not interval averages), so latency truth is exact.

Time model. "True time" ``t`` is the master's clock, in seconds relative to ``cfg.t0_ns``; the master
log spans ``[0, duration_s]``. The slave's clock reads ``sigma(t) = t + latency_s + d (t - t_mid)`` with
``d = drift_ppm * 1e-6`` and ``t_mid = duration_s / 2`` (the middle of the master log); its samples are
uniformly spaced on ITS clock (first sample at a random fraction of one period after ``sigma(0)``, the
"random start-up delay" of seed 004) and the physical values are evaluated at the true instants
``t = (sigma - latency_s + d t_mid) / (1 + d)``. Slave absolute stamps are ``cfg.t0_ns + sigma``
(``slave_clock="epoch"``) or start near ``slave_boot_start_s`` (``slave_clock="boot"``): then the
truth ``latency_s`` includes that huge clock offset (about -1.7e9 s for the default epoch; the
physical part is ``latency_excl_clock_offset_s``) so that ``slave stamp - master stamp = latency_at(t)``
holds for every sample in both cases.

Frames: NED/FRD; mounting ``R = dcm_from_euler(radians(mount_rpy_deg))`` with ``v_slave = R v_master``;
the lever arm r is the slave's location in the master body frame (m): the slave senses
``f + omega_dot x r + omega x (omega x r)`` minus the gravitation difference between the two points,
its velocity is ``v + C_b^n (omega_eb^b x r)`` (seed 003 eq. 3) and its nav output (attitude, velocity)
refers to ITS local level frame, tilted ~|r|/R from the master's; flexure (seed 000, eq. 8) is a
second-order Markov rotation ``lambda'' = -beta^2 lambda - 2 beta lambda' + eta`` of the slave sensor
frame: ``C_m^s = exp([lambda x])^T R`` and the slave gyro gets ``J_r(lambda) lambda'``.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Callable

import numpy as np
from scipy.interpolate import CubicHermiteSpline
from scipy.linalg import expm
from scipy.signal import lfilter

from logtools import earth
from logtools.conventions import (
    DEG,
    DEG_PER_H,
    DEG_PER_SQRT_H,
    G0_M_S2,
    MG,
    NS_PER_S,
    UG_PER_SQRT_HZ,
    dcm_from_euler,
    dcm_from_rotvec,
    euler_from_dcm,
    quat_conj,
    quat_from_dcm,
    quat_from_euler,
    quat_from_rotvec,
    quat_make_continuous,
    quat_mul,
    skew,
)
from logtools.errors import InputError
from logtools.inslog import ChannelInfo, InsLog, LogMeta

SCENARIOS = ("ship", "aircraft", "vehicle", "multirotor")
Vec3 = tuple[float, float, float]
_POS_STEP_S = 0.02  # position integration grid (Hermite interpolation in between)


# ==============================================================================================
# configuration
# ==============================================================================================
@dataclass(frozen=True)
class SimConfig:
    """Everything a simulation depends on. Build with ``scenario_config(name, **overrides)``.

    Profile fields (which scenario uses which):
      ship:       speed_m_s along course_deg; sway_amp_deg / sway_period_s (roll, pitch, yaw sway
                  about the course); heave_amp_m / heave_period_s; speed_var_m_s (surge).
      aircraft:   speed_m_s (+ speed_var_m_s over speed_var_period_s); S-turns: heading
                  course_deg + turn_amp_deg sin(2 pi (t - turn_start_s) / turn_period_s), ramped in
                  over ~3 s, coordinated bank atan(V psi' / g); flight path angle climb_amp_deg with
                  climb_period_s; pitch = flight path angle + 2 deg angle of attack.
      vehicle:    speed_m_s + speed_var_m_s (accelerations); turns turn_amp_deg / turn_period_s
                  (two harmonics); road grade climb_amp_deg / climb_period_s; body roll/squat.
      multirotor: hover, then (from turn_start_s) agile NED velocity sinusoids of amplitude ~speed_m_s
                  and periods of a few seconds; yaw swings turn_amp_deg / turn_period_s; roll/pitch
                  are the tilt the thrust needs for the acceleration.
    Sensor units: gyro bias deg/h, gyro ARW deg/sqrt(h), accel bias mg, accel VRW ug/sqrt(Hz);
    white noise is per point sample with std ARW*sqrt(rate). Nav errors are white per sample.
    Jitter (``*_jitter_s``): each stamp gets N(0, jitter) added (clipped to +-0.4 sample period) while
    the physical sample stays at its nominal instant, so ``latency_s`` stays the mean offset.
    Use ``cfg.noiseless()`` for error-free outputs (numerical checks).
    """

    scenario: str = "ship"
    duration_s: float = 120.0
    seed: int = 0
    t0_ns: int = 1_700_000_000_000_000_000
    # -- trajectory ---------------------------------------------------------------------------
    lat0_deg: float = 30.0
    lon0_deg: float = 110.0
    alt0_m: float = 0.0
    speed_m_s: float = 10.0
    course_deg: float = 45.0
    sway_amp_deg: Vec3 = (8.0, 6.0, 4.0)
    sway_period_s: Vec3 = (12.0, 10.0, 16.0)
    heave_amp_m: float = 0.5
    heave_period_s: float = 8.0
    turn_amp_deg: float = 0.0
    turn_period_s: float = 60.0
    turn_start_s: float = 0.0
    climb_amp_deg: float = 0.0
    climb_period_s: float = 50.0
    speed_var_m_s: float = 0.0
    speed_var_period_s: float = 60.0
    # -- master unit --------------------------------------------------------------------------
    master_imu_rate_hz: float = 200.0
    master_nav_rate_hz: float = 100.0
    master_gyro_bias_dph: Vec3 = (0.005, 0.005, 0.005)
    master_accel_bias_mg: Vec3 = (0.05, 0.05, 0.05)
    master_gyro_arw_dpsh: float = 0.001
    master_accel_vrw_ug_rthz: float = 10.0
    master_att_noise_deg: float = 0.0005
    master_vel_noise_m_s: float = 0.002
    master_pos_noise_m: float = 0.02
    master_jitter_s: float = 0.0
    # -- slave unit ---------------------------------------------------------------------------
    slave_imu_rate_hz: float = 200.0
    slave_nav_rate_hz: float = 50.0
    slave_nav: bool = True
    latency_s: float = 0.1
    drift_ppm: float = 0.0
    mount_rpy_deg: Vec3 = (0.3, 0.4, -1.0)
    lever_arm_m: Vec3 = (0.0, 0.0, 0.0)
    slave_gyro_bias_dph: Vec3 = (0.01, 0.01, 0.01)
    slave_accel_bias_mg: Vec3 = (0.1, 0.1, 0.1)
    slave_gyro_arw_dpsh: float = 0.005
    slave_accel_vrw_ug_rthz: float = 50.0
    slave_att_noise_deg: float = 0.0
    slave_vel_noise_m_s: float = 0.0
    slave_pos_noise_m: float = 0.0
    slave_jitter_s: float = 0.0
    slave_clock: str = "epoch"
    slave_boot_start_s: float = 50.0
    #: random start-up phase of the slave's sample grid, as a fraction of one IMU period
    #: (None: drawn from the seed, uniform in [0, 1) as in seed 004)
    slave_start_phase: float | None = None
    #: slave data dropped where the true time is in [start, start + length)
    slave_gaps_s: tuple[tuple[float, float], ...] = ()
    # -- real-board error sources (issue 22) ---------------------------------------------------
    #: the slave's accelerometer triad rotated from its gyro triad (deg, [r, p, y], v_accel = M v_gyro)
    slave_accel_misalign_rpy_deg: Vec3 = (0.0, 0.0, 0.0)
    #: the master's attitude output with a first-order Markov error (deg per axis, correlation time s):
    #: its EKF's attitude error, correlated in time, not white
    master_att_markov_deg: float = 0.0
    master_att_markov_tau_s: float = 30.0
    #: vibration on the slave's IMU (rms of a narrow band around vibration_hz, per axis); sampled as
    #: snapshots at a low slave_imu_rate_hz (25-50 Hz) it aliases into the band of the motion
    slave_vibration_accel_m_s2: float = 0.0
    slave_vibration_gyro_dps: float = 0.0
    vibration_hz: float = 97.0
    #: a rigid-body angular vibration of the whole vehicle (both units, and the lever arm between them, move
    #: with it): amplitude per Euler angle (deg, roll pitch yaw) at rigid_vibration_hz; a car's 8-20 Hz
    #: shake, which a 50 Hz slave samples below its Nyquist rate (0 = none)
    rigid_vibration_deg: Vec3 = (0.0, 0.0, 0.0)
    rigid_vibration_hz: Vec3 = (15.0, 12.0, 17.0)
    # -- flexure (seed 000 eq. 8) -------------------------------------------------------------
    flexure: bool = False
    flexure_sigma_deg: Vec3 = (0.05, 0.05, 0.05)
    flexure_beta_1_s: Vec3 = (2.0, 2.0, 2.0)
    flexure_step_s: float = 0.05  # seed 000: discrete step 0.05 s

    def __post_init__(self) -> None:
        _validate(self)

    def noiseless(self) -> "SimConfig":
        """The same scenario with every sensor/nav error, bias, noise and jitter set to zero."""
        z3 = (0.0, 0.0, 0.0)
        return replace(
            self, master_gyro_bias_dph=z3, master_accel_bias_mg=z3, master_gyro_arw_dpsh=0.0,
            master_accel_vrw_ug_rthz=0.0, master_att_noise_deg=0.0, master_vel_noise_m_s=0.0,
            master_pos_noise_m=0.0, master_jitter_s=0.0, slave_gyro_bias_dph=z3, slave_accel_bias_mg=z3,
            slave_gyro_arw_dpsh=0.0, slave_accel_vrw_ug_rthz=0.0, slave_att_noise_deg=0.0,
            slave_vel_noise_m_s=0.0, slave_pos_noise_m=0.0, slave_jitter_s=0.0, master_att_markov_deg=0.0,
            slave_vibration_accel_m_s2=0.0, slave_vibration_gyro_dps=0.0)


def _validate(c: SimConfig) -> None:
    def bad(msg: str) -> InputError:
        return InputError(f"simulate: {msg}")

    if c.scenario not in SCENARIOS:
        raise bad(f"unknown scenario {c.scenario!r}; known: {', '.join(SCENARIOS)}")
    if not (math.isfinite(c.duration_s) and 1.0 <= c.duration_s <= 48 * 3600):
        raise bad(f"duration_s must be in [1, 172800] s, got {c.duration_s}")
    for name in ("master_imu_rate_hz", "master_nav_rate_hz", "slave_imu_rate_hz", "slave_nav_rate_hz"):
        v = getattr(c, name)
        if not (math.isfinite(v) and 1.0 <= v <= 10000.0):
            raise bad(f"{name} must be in [1, 10000] Hz, got {v}")
    for name in ("sway_amp_deg", "sway_period_s", "master_gyro_bias_dph", "master_accel_bias_mg",
                 "mount_rpy_deg", "lever_arm_m", "slave_gyro_bias_dph", "slave_accel_bias_mg",
                 "flexure_sigma_deg", "flexure_beta_1_s", "slave_accel_misalign_rpy_deg", "rigid_vibration_deg",
                 "rigid_vibration_hz"):
        v = getattr(c, name)
        if len(v) != 3 or not all(math.isfinite(float(x)) for x in v):
            raise bad(f"{name} needs 3 finite numbers, got {v!r}")
    if min(c.sway_period_s) <= 0 or min(c.turn_period_s, c.climb_period_s, c.heave_period_s,
                                         c.speed_var_period_s) <= 0:
        raise bad("periods must be positive")
    if min(c.flexure_beta_1_s) <= 0 or c.flexure_step_s <= 0:
        raise bad("flexure_beta_1_s and flexure_step_s must be positive")
    if not (isinstance(c.seed, (int, np.integer)) and c.seed >= 0):
        raise bad(f"seed must be a non-negative integer, got {c.seed!r}")
    if not (isinstance(c.t0_ns, (int, np.integer)) and c.t0_ns >= 0):
        raise bad(f"t0_ns must be a non-negative integer (ns), got {c.t0_ns!r}")
    if c.slave_clock not in ("epoch", "boot"):
        raise bad(f"slave_clock must be 'epoch' or 'boot', got {c.slave_clock!r}")
    if not (math.isfinite(c.latency_s) and abs(c.latency_s) < 0.25 * c.duration_s + 10.0):
        raise bad(f"latency_s {c.latency_s} too large for a {c.duration_s} s log")
    if not (math.isfinite(c.drift_ppm) and abs(c.drift_ppm) < 1e4):
        raise bad(f"drift_ppm must be finite and below 1e4 in size, got {c.drift_ppm}")
    if c.slave_start_phase is not None and not 0.0 <= c.slave_start_phase < 1.0:
        raise bad("slave_start_phase must be in [0, 1)")
    if not -90.0 < c.lat0_deg < 90.0 or abs(c.lat0_deg) > 85.0:
        raise bad("lat0_deg must be within +-85 deg")
    for g in c.slave_gaps_s:
        if len(g) != 2 or g[1] < 0:
            raise bad(f"slave_gaps_s entries are (start_s, length_s), got {g!r}")
    if min(c.master_jitter_s, c.slave_jitter_s, c.master_gyro_arw_dpsh, c.slave_gyro_arw_dpsh,
           c.master_accel_vrw_ug_rthz, c.slave_accel_vrw_ug_rthz, c.master_att_noise_deg,
           c.master_vel_noise_m_s, c.master_pos_noise_m, c.slave_att_noise_deg,
           c.slave_vel_noise_m_s, c.slave_pos_noise_m, c.master_att_markov_deg, c.slave_vibration_accel_m_s2,
           c.slave_vibration_gyro_dps) < 0:
        raise bad("noise and jitter levels must be >= 0")
    if not (c.master_att_markov_tau_s > 0 and c.vibration_hz > 0 and min(c.rigid_vibration_hz) > 0):
        raise bad("master_att_markov_tau_s, vibration_hz and rigid_vibration_hz must be positive")


_SCENARIO_DEFAULTS: dict[str, dict] = {
    # seed 004: 30N 110E, sway 8/6/4 deg with periods 12/10/16 s, mounting [0.3, 0.4, -1] deg,
    # slave gyro 0.01 deg/h and accel 100 ug, 100 ms delay; master 0.005 deg/h, 50 ug
    "ship": dict(lat0_deg=30.0, lon0_deg=110.0, alt0_m=0.0, speed_m_s=10.0, course_deg=45.0,
                 sway_amp_deg=(8.0, 6.0, 4.0), sway_period_s=(12.0, 10.0, 16.0), heave_amp_m=0.5,
                 heave_period_s=8.0, speed_var_m_s=0.3, speed_var_period_s=40.0,
                 latency_s=0.1, mount_rpy_deg=(0.3, 0.4, -1.0),
                 slave_gyro_bias_dph=(0.01, 0.01, 0.01), slave_accel_bias_mg=(0.1, 0.1, 0.1),
                 slave_gyro_arw_dpsh=0.002, slave_accel_vrw_ug_rthz=20.0),
    # seed 000: 32N 118E, 1000 m, 200 m/s, S manoeuvre; slave gyro 1 deg/h + N(0, (1 deg/h)^2) per
    # 0.05 s sample (ARW ~ 0.0037 deg/sqrt(h)), accel 0.2 mg + N(0, (0.2 mg)^2) (VRW ~ 45 ug/sqrt(Hz))
    "aircraft": dict(lat0_deg=32.0, lon0_deg=118.0, alt0_m=1000.0, speed_m_s=200.0, course_deg=30.0,
                     sway_amp_deg=(0.0, 0.0, 0.0), heave_amp_m=0.0, turn_amp_deg=20.0,
                     turn_period_s=80.0, turn_start_s=10.0, climb_amp_deg=1.5, climb_period_s=50.0,
                     speed_var_m_s=5.0, speed_var_period_s=90.0, latency_s=0.06,
                     mount_rpy_deg=(1.5, -2.0, 3.0), slave_gyro_bias_dph=(1.0, -1.0, 1.0),
                     slave_accel_bias_mg=(0.2, -0.2, 0.2), slave_gyro_arw_dpsh=0.0037,
                     slave_accel_vrw_ug_rthz=45.0),
    # seed 002: 39N 116E, land vehicle, 200 Hz units, slave gyro 0.6 deg/h, accel 0.2 mg
    "vehicle": dict(lat0_deg=39.0, lon0_deg=116.0, alt0_m=50.0, speed_m_s=15.0, course_deg=60.0,
                    sway_amp_deg=(0.0, 0.0, 0.0), heave_amp_m=0.0, turn_amp_deg=40.0,
                    turn_period_s=45.0, climb_amp_deg=1.0, climb_period_s=30.0, speed_var_m_s=5.0,
                    speed_var_period_s=25.0, latency_s=0.08, mount_rpy_deg=(-0.5, 1.0, 2.0),
                    slave_gyro_bias_dph=(0.6, 0.6, 0.6), slave_accel_bias_mg=(0.2, 0.2, 0.2),
                    slave_gyro_arw_dpsh=0.01, slave_accel_vrw_ug_rthz=50.0),
    # a small multirotor with a MEMS slave
    "multirotor": dict(lat0_deg=47.4, lon0_deg=8.5, alt0_m=450.0, speed_m_s=3.0, course_deg=0.0,
                       sway_amp_deg=(0.0, 0.0, 0.0), heave_amp_m=0.0, turn_amp_deg=45.0,
                       turn_period_s=20.0, turn_start_s=5.0, latency_s=0.03,
                       mount_rpy_deg=(0.0, 0.0, 90.0), slave_gyro_bias_dph=(20.0, -15.0, 10.0),
                       slave_accel_bias_mg=(3.0, -2.0, 4.0), slave_gyro_arw_dpsh=0.2,
                       slave_accel_vrw_ug_rthz=150.0, master_gyro_bias_dph=(0.5, 0.5, 0.5),
                       master_accel_bias_mg=(0.1, 0.1, 0.1), master_gyro_arw_dpsh=0.02,
                       master_accel_vrw_ug_rthz=30.0),
}


def _coerce(name: str, value):
    """Overrides may come as lists (JSON) or strings of numbers; tuples are what the config holds."""
    if name == "slave_gaps_s":
        return tuple(tuple(float(x) for x in g) for g in value)
    if isinstance(_FIELD_DEFAULTS[name], tuple):
        try:
            return tuple(float(x) for x in value)
        except (TypeError, ValueError):
            raise InputError(f"simulate: {name} needs 3 numbers, got {value!r}") from None
    return value


def scenario_config(name: str, **overrides) -> SimConfig:
    """The configuration of a named scenario ("ship", "aircraft", "vehicle", "multirotor")."""
    if name not in _SCENARIO_DEFAULTS:
        raise InputError(f"simulate: unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    unknown = sorted(set(overrides) - set(_FIELD_DEFAULTS))
    if unknown:
        raise InputError(f"simulate: unknown option(s) {', '.join(unknown)}")
    kw = dict(_SCENARIO_DEFAULTS[name])
    kw.update({k: _coerce(k, v) for k, v in overrides.items()})
    kw["scenario"] = name
    try:
        return SimConfig(**kw)
    except (TypeError, ValueError) as exc:
        raise InputError(f"simulate: bad option: {exc}") from None


_FIELD_DEFAULTS = {f.name: f.default for f in fields(SimConfig)}


# ==============================================================================================
# forward-mode derivatives up to third order
# ==============================================================================================
def _is0(a) -> bool:
    return isinstance(a, float) and a == 0.0


def _mul(a, b):
    """a * b with python-float 0/1 shortcuts (the time jet is (t, 1, 0, 0))."""
    if _is0(a) or _is0(b):
        return 0.0
    if isinstance(a, float) and a == 1.0:
        return b
    if isinstance(b, float) and b == 1.0:
        return a
    return a * b


def _add(*xs):
    xs = [x for x in xs if not _is0(x)]
    if not xs:
        return 0.0
    out = xs[0]
    for x in xs[1:]:
        out = out + x
    return out


class _Jet:
    """A function of time and its derivatives ``c = (f, df, d2f, d3f)`` (arrays or python floats,
    any order <= 3). Python-float 0.0/1.0 entries stay symbolic so that unused terms cost nothing."""

    __slots__ = ("c",)

    def __init__(self, c):
        self.c = tuple(c)

    @staticmethod
    def time(t: np.ndarray) -> "_Jet":
        return _Jet((np.asarray(t, dtype=float), 1.0, 0.0, 0.0))

    def deriv(self) -> "_Jet":
        return _Jet(self.c[1:])

    def __add__(self, o):
        if isinstance(o, _Jet):
            return _Jet(_add(a, b) for a, b in zip(self.c, o.c))
        return _Jet((self.c[0] + o,) + self.c[1:])

    __radd__ = __add__

    def __neg__(self):
        return _Jet(0.0 if _is0(a) else -a for a in self.c)

    def __sub__(self, o):
        return self + (-o)

    def __rsub__(self, o):
        return (-self) + o

    def __mul__(self, o):
        if not isinstance(o, _Jet):
            return _Jet(_mul(a, float(o)) for a in self.c)
        a, b = self.c, o.c
        n = min(len(a), len(b))
        out = [_mul(a[0], b[0])]
        if n > 1:
            out.append(_add(_mul(a[1], b[0]), _mul(a[0], b[1])))
        if n > 2:
            out.append(_add(_mul(a[2], b[0]), _mul(2.0, _mul(a[1], b[1])), _mul(a[0], b[2])))
        if n > 3:
            out.append(_add(_mul(a[3], b[0]), _mul(3.0, _mul(a[2], b[1])),
                            _mul(3.0, _mul(a[1], b[2])), _mul(a[0], b[3])))
        return _Jet(out)

    __rmul__ = __mul__

    def __truediv__(self, o):
        if not isinstance(o, _Jet):
            return self * (1.0 / o)
        return self * o.recip()

    def compose(self, g: Callable[[np.ndarray], tuple]) -> "_Jet":
        """g(f) by Faa di Bruno; ``g(u)`` returns (g, g', g'', g''') at u."""
        f = self.c
        g0, g1, g2, g3 = g(f[0])
        out = [g0]
        if len(f) > 1:
            out.append(_mul(g1, f[1]))
        if len(f) > 2:
            out.append(_add(_mul(g2, _mul(f[1], f[1])), _mul(g1, f[2])))
        if len(f) > 3:
            out.append(_add(_mul(g3, _mul(f[1], _mul(f[1], f[1]))),
                            _mul(3.0, _mul(g2, _mul(f[1], f[2]))), _mul(g1, f[3])))
        return _Jet(out)

    def recip(self) -> "_Jet":
        def g(u):
            r = 1.0 / u
            r2 = r * r
            return r, -r2, 2 * r2 * r, -6 * r2 * r2

        return self.compose(g)


def _jsin(f: _Jet) -> _Jet:
    def g(u):
        s, c = np.sin(u), np.cos(u)
        return s, c, -s, -c

    return f.compose(g)


def _jcos(f: _Jet) -> _Jet:
    def g(u):
        s, c = np.sin(u), np.cos(u)
        return c, -s, -c, s

    return f.compose(g)


def _jatan(f: _Jet) -> _Jet:
    def g(u):
        d = 1.0 / (1.0 + u * u)
        return np.arctan(u), d, -2 * u * d**2, (6 * u * u - 2) * d**3

    return f.compose(g)


def _jtanh(f: _Jet) -> _Jet:
    def g(u):
        th = np.tanh(u)
        s2 = 1 - th * th
        return th, s2, -2 * th * s2, s2 * (6 * th * th - 2)

    return f.compose(g)


def _ramp(t: _Jet, t_on_s: float, width_s: float) -> _Jet:
    """Smooth 0 -> 1 step centred at t_on_s + 2 width (0.02 at t_on_s)."""
    return 0.5 * (1.0 + _jtanh((t - (t_on_s + 2.0 * width_s)) * (1.0 / width_s)))


def _sine(t: _Jet, amp: float, period_s: float, phase_rad: float = 0.0) -> _Jet:
    return amp * _jsin(t * (2 * np.pi / period_s) + phase_rad)


# ==============================================================================================
# scenario profiles: Euler angles (order >= 2) and NED velocity (order >= 1) as jets of time
# ==============================================================================================
Profile = tuple[list[_Jet], list[_Jet]]


def _profile_ship(c: SimConfig, t: _Jet) -> Profile:
    (ar, ap, ay), (tr, tp, ty) = c.sway_amp_deg, c.sway_period_s
    roll = _sine(t, ar * DEG, tr)
    pitch = _sine(t, ap * DEG, tp)
    yaw = c.course_deg * DEG + _sine(t, ay * DEG, ty)
    speed = c.speed_m_s + _sine(t, c.speed_var_m_s, c.speed_var_period_s)
    crs = c.course_deg * DEG
    om_h = 2 * np.pi / c.heave_period_s
    vd = _sine(t, c.heave_amp_m * om_h, c.heave_period_s, np.pi / 2)  # alt = alt0 - A sin(om t)
    return [roll, pitch, yaw], [speed * math.cos(crs), speed * math.sin(crs), vd]


def _profile_aircraft(c: SimConfig, t: _Jet) -> Profile:
    ramp = _ramp(t, c.turn_start_s, 1.5)
    psi = c.course_deg * DEG + ramp * _sine(t - c.turn_start_s, c.turn_amp_deg * DEG, c.turn_period_s)
    speed = c.speed_m_s + _sine(t, c.speed_var_m_s, c.speed_var_period_s)
    gamma = _sine(t, c.climb_amp_deg * DEG, c.climb_period_s)
    roll = _jatan(speed * psi.deriv() * (1.0 / G0_M_S2))  # coordinated turn
    pitch = gamma + 2.0 * DEG
    cg = _jcos(gamma)
    vel = [speed * cg * _jcos(psi), speed * cg * _jsin(psi), -(speed * _jsin(gamma))]
    return [roll, pitch, psi], vel


def _profile_vehicle(c: SimConfig, t: _Jet) -> Profile:
    a = c.turn_amp_deg * DEG
    psi = (c.course_deg * DEG + _sine(t, a, c.turn_period_s)
           + _sine(t, 0.5 * a, 0.37 * c.turn_period_s, 1.0))
    speed = c.speed_m_s + _sine(t, c.speed_var_m_s, c.speed_var_period_s, -np.pi / 2)
    grade = _sine(t, c.climb_amp_deg * DEG, c.climb_period_s)
    lat_acc = speed * psi.deriv()
    roll = lat_acc * (-0.5 * DEG)  # body roll outward, 0.5 deg per m/s^2
    pitch = grade + speed.deriv() * (0.3 * DEG)  # squat under acceleration
    cg = _jcos(grade)
    vel = [speed * cg * _jcos(psi), speed * cg * _jsin(psi), -(speed * _jsin(grade))]
    return [roll, pitch, psi], vel


def _profile_multirotor(c: SimConfig, t: _Jet) -> Profile:
    env = _ramp(t, c.turn_start_s, 1.0)
    a = c.speed_m_s
    vn = env * (_sine(t, a, 7.0) + _sine(t, 0.3 * a, 2.3, 0.4))
    ve = env * (_sine(t, 0.8 * a, 5.3, 1.0) + _sine(t, 0.25 * a, 1.9, 2.0))
    vd = env * _sine(t, 0.3 * a, 4.1, 0.5)
    psi = c.course_deg * DEG + env * _sine(t, c.turn_amp_deg * DEG, c.turn_period_s)
    an, ae, ad = vn.deriv(), ve.deriv(), vd.deriv()
    cpsi, spsi = _jcos(psi), _jsin(psi)
    a_fwd = an * cpsi + ae * spsi
    a_right = ae * cpsi - an * spsi
    lift = (G0_M_S2 - ad).recip()
    pitch = _jatan(-(a_fwd * lift))
    roll = _jatan(a_right * lift)
    return [roll, pitch, psi], [vn, ve, vd]


_PROFILES: dict[str, Callable[[SimConfig, _Jet], Profile]] = {
    "ship": _profile_ship, "aircraft": _profile_aircraft, "vehicle": _profile_vehicle,
    "multirotor": _profile_multirotor,
}


def _profile(cfg: SimConfig, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(rpy, rpy', rpy'', vel, vel') arrays (N, 3) at times t_s."""
    t_s = np.asarray(t_s, dtype=float)
    tj = _Jet.time(t_s)
    att, vel = _PROFILES[cfg.scenario](cfg, tj)
    att = [a + _sine(tj, amp * DEG, 1.0 / f, 0.7 * (i + 1)) if amp else a
           for i, (a, amp, f) in enumerate(zip(att, cfg.rigid_vibration_deg, cfg.rigid_vibration_hz))]

    def col(j, k):
        return np.broadcast_to(np.asarray(j.c[k], dtype=float), t_s.shape)

    rpy = np.stack([col(j, 0) for j in att], axis=-1)
    rpy_d = np.stack([col(j, 1) for j in att], axis=-1)
    rpy_dd = np.stack([col(j, 2) for j in att], axis=-1)
    v = np.stack([col(j, 0) for j in vel], axis=-1)
    v_d = np.stack([col(j, 1) for j in vel], axis=-1)
    return rpy, rpy_d, rpy_dd, v, v_d


def _velocity(cfg: SimConfig, t_s: np.ndarray) -> np.ndarray:
    return _profile(cfg, t_s)[3]


# ==============================================================================================
# position: llh_rates integrated on a grid anchored at t = 0
# ==============================================================================================
@dataclass(frozen=True)
class _PositionModel:
    spline: CubicHermiteSpline  # [lat_rad, lon_rad, alt_m] (t)
    t_lo_s: float
    t_hi_s: float

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        return self.spline(np.asarray(t_s, dtype=float))


def _position_model(cfg: SimConfig, t_lo_s: float, t_hi_s: float) -> _PositionModel:
    h = _POS_STEP_S
    k_lo = int(math.floor(min(t_lo_s, 0.0) / h)) - 2
    k_hi = int(math.ceil(max(t_hi_s, cfg.duration_s) / h)) + 2
    k = np.arange(k_lo, k_hi + 1)
    tn = k * h
    i0 = -k_lo
    v_n = _velocity(cfg, tn)
    v_m = _velocity(cfg, tn[:-1] + 0.5 * h)

    def cumint(f_n: np.ndarray, f_m: np.ndarray) -> np.ndarray:
        inc = (h / 6.0) * (f_n[:-1] + 4.0 * f_m + f_n[1:])
        c = np.concatenate([[0.0], np.cumsum(inc)])
        return c - c[i0]

    def mid(x_n: np.ndarray, f_n: np.ndarray) -> np.ndarray:  # cubic Hermite at interval centres
        return 0.5 * (x_n[:-1] + x_n[1:]) + (h / 8.0) * (f_n[:-1] - f_n[1:])

    lat0, lon0 = cfg.lat0_deg * DEG, cfg.lon0_deg * DEG
    alt_n = cfg.alt0_m + cumint(-v_n[:, 2], -v_m[:, 2])
    alt_m = mid(alt_n, -v_n[:, 2])
    lat_n = np.full(tn.shape, lat0)
    lat_m = np.full(tn.shape[0] - 1, lat0)

    def lat_rate(lat, alt, vn):
        return vn / (earth.radii_m(lat)[0] + alt)

    for _ in range(4):  # Picard: the latitude coupling is ~1e-3 over an hour, 4 passes -> < 1e-12
        lat_n = lat0 + cumint(lat_rate(lat_n, alt_n, v_n[:, 0]), lat_rate(lat_m, alt_m, v_m[:, 0]))
        lat_m = mid(lat_n, lat_rate(lat_n, alt_n, v_n[:, 0]))

    def lon_rate(lat, alt, ve):
        return ve / ((earth.radii_m(lat)[1] + alt) * np.cos(lat))

    lon_n = lon0 + cumint(lon_rate(lat_n, alt_n, v_n[:, 1]), lon_rate(lat_m, alt_m, v_m[:, 1]))
    pos = np.stack([lat_n, lon_n, alt_n], axis=-1)
    rates = earth.llh_rates(lat_n, alt_n, v_n)
    return _PositionModel(CubicHermiteSpline(tn, pos, rates, axis=0), float(tn[0]), float(tn[-1]))


# ==============================================================================================
# the truth trajectory (master body) at arbitrary instants
# ==============================================================================================
@dataclass(frozen=True)
class TruthTrajectory:
    """Analytic truth of the master body at ``t_s`` (master-relative seconds)."""

    t_s: np.ndarray
    rpy_rad: np.ndarray
    quat_wxyz: np.ndarray  # body -> NED
    dcm_nb: np.ndarray
    vel_ned_m_s: np.ndarray
    accel_ned_m_s2: np.ndarray  # dv^n/dt
    lat_lon_alt: np.ndarray  # deg, deg, m
    omega_nb_b_rad_s: np.ndarray
    omega_ib_b_rad_s: np.ndarray
    omega_dot_ib_b_rad_s2: np.ndarray
    omega_ie_n_rad_s: np.ndarray
    f_b_m_s2: np.ndarray
    gravity_ned_m_s2: np.ndarray


def _euler_body_rates(rpy, d, dd) -> tuple[np.ndarray, np.ndarray]:
    """omega_nb^b and its derivative from ZYX Euler angles and their derivatives."""
    r, p = rpy[:, 0], rpy[:, 1]
    r1, p1, y1 = d[:, 0], d[:, 1], d[:, 2]
    r2, p2, y2 = dd[:, 0], dd[:, 1], dd[:, 2]
    sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
    w = np.stack([r1 - y1 * sp, p1 * cr + y1 * sr * cp, -p1 * sr + y1 * cr * cp], axis=-1)
    wd = np.stack([
        r2 - y2 * sp - y1 * cp * p1,
        p2 * cr - p1 * sr * r1 + y2 * sr * cp + y1 * (cr * r1 * cp - sr * sp * p1),
        -p2 * sr - p1 * cr * r1 + y2 * cr * cp + y1 * (-sr * r1 * cp - cr * sp * p1),
    ], axis=-1)
    return w, wd


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def _mv(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", m, v)


def _mtv(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...ji,...j->...i", m, v)


def _take(tr: TruthTrajectory, idx: np.ndarray, names: tuple[str, ...] | None = None) -> TruthTrajectory:
    """Rows ``idx`` of a truth record (only ``names`` filled when given, the rest left empty)."""
    keep = names or tuple(f.name for f in fields(TruthTrajectory))
    return TruthTrajectory(**{f.name: getattr(tr, f.name)[idx] if f.name in keep else np.zeros(0)
                              for f in fields(TruthTrajectory)})


def _chunked(fn: Callable[[np.ndarray], tuple], t_s: np.ndarray, chunk: int = 1 << 16) -> tuple:
    """fn over slices of t_s, outputs concatenated (bounds the memory of the per-sample 3x3 work)."""
    if len(t_s) <= chunk:
        return tuple(fn(t_s))
    parts = [fn(t_s[i:i + chunk]) for i in range(0, len(t_s), chunk)]
    return tuple(np.concatenate(cols, axis=0) for cols in zip(*parts))


def _merged(a_ns: np.ndarray, b_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Sorted union of two sorted stamp arrays and where each lies in it (None: identity for a)."""
    if len(a_ns):
        i = np.clip(np.searchsorted(a_ns, b_ns), 0, len(a_ns) - 1)
        if np.array_equal(a_ns[i], b_ns):  # b is a subset of a (nav stamps on the IMU grid)
            return a_ns, None, i
    u = np.union1d(a_ns, b_ns)
    return u, np.searchsorted(u, a_ns), np.searchsorted(u, b_ns)


def _truth_at(cfg: SimConfig, pos: _PositionModel, t_s: np.ndarray) -> TruthTrajectory:
    t_s = np.asarray(t_s, dtype=float)
    rpy, rpy_d, rpy_dd, v, v_d = _profile(cfg, t_s)
    llh = pos(t_s)
    lat, alt = llh[:, 0], llh[:, 2]
    c_nb = dcm_from_euler(rpy)
    w_nb, w_nb_dot = _euler_body_rates(rpy, rpy_d, rpy_dd)
    w_ie = earth.earth_rate_ned(lat)
    w_en = earth.transport_rate_ned(lat, alt, v)
    w_in_b = _mtv(c_nb, w_ie + w_en)
    w_ib = w_nb + w_in_b
    # d/dt omega_in^n (first-order terms; the radius derivatives are ~1e-3 of these and ignored)
    r_m, r_n = earth.radii_m(lat)
    lat_dot = v[:, 0] / (r_m + alt)
    w_ie_dot = earth.OMEGA_IE_RAD_S * np.stack(
        [-np.sin(lat) * lat_dot, np.zeros_like(lat), -np.cos(lat) * lat_dot], axis=-1)
    w_en_dot = np.stack([
        v_d[:, 1] / (r_n + alt), -v_d[:, 0] / (r_m + alt),
        -(v_d[:, 1] * np.tan(lat) + v[:, 1] * lat_dot / np.cos(lat) ** 2) / (r_n + alt)], axis=-1)
    w_ib_dot = w_nb_dot - _cross(w_nb, w_in_b) + _mtv(c_nb, w_ie_dot + w_en_dot)
    g_n = earth.gravity_ned_m_s2(lat, alt)
    f_n = v_d + _cross(2.0 * w_ie + w_en, v) - g_n
    f_b = _mtv(c_nb, f_n)
    quat = quat_make_continuous(quat_from_euler(rpy)) if len(t_s) else np.zeros((0, 4))
    lla = np.stack([np.degrees(lat), np.degrees(llh[:, 1]), alt], axis=-1)
    return TruthTrajectory(t_s=t_s, rpy_rad=rpy, quat_wxyz=quat, dcm_nb=c_nb, vel_ned_m_s=v,
                           accel_ned_m_s2=v_d, lat_lon_alt=lla, omega_nb_b_rad_s=w_nb,
                           omega_ib_b_rad_s=w_ib, omega_dot_ib_b_rad_s2=w_ib_dot,
                           omega_ie_n_rad_s=w_ie, f_b_m_s2=f_b, gravity_ned_m_s2=g_n)


def truth_trajectory(cfg: SimConfig, t_s: np.ndarray) -> TruthTrajectory:
    """The analytic truth of the MASTER body at master-relative times ``t_s`` (any order, any range).

    Positions come from the same t = 0-anchored grid as ``simulate`` uses, so they agree with the
    simulated logs to far below a millimetre.
    """
    t_s = np.atleast_1d(np.asarray(t_s, dtype=float))
    lo, hi = (float(t_s.min()), float(t_s.max())) if len(t_s) else (0.0, 0.0)
    pos = _position_model(cfg, min(lo, -_MARGIN_S), max(hi, cfg.duration_s + _MARGIN_S))
    return _truth_at(cfg, pos, t_s)


_MARGIN_S = 2.0


# ==============================================================================================
# flexure: second-order Markov angles (seed 000 eq. 8), C1 interpolation with consistent rates
# ==============================================================================================
@dataclass(frozen=True)
class _Flexure:
    spline: CubicHermiteSpline | None

    def angles_rates(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.spline is None:
            z = np.zeros((len(t_s), 3))
            return z, z
        return self.spline(t_s), self.spline(t_s, 1)


def _flexure_model(cfg: SimConfig, rng: np.random.Generator, t_lo_s: float, t_hi_s: float) -> _Flexure:
    if not cfg.flexure:
        return _Flexure(None)
    h = cfg.flexure_step_s
    burn = 10.0 / min(cfg.flexure_beta_1_s)
    t0 = t_lo_s - burn
    n = int(math.ceil((t_hi_s + 2 * h - t0) / h)) + 1
    tg = t0 + h * np.arange(n)
    lam = np.zeros((n, 3))
    lam_d = np.zeros((n, 3))
    for ax in range(3):
        beta, sig = cfg.flexure_beta_1_s[ax], cfg.flexure_sigma_deg[ax] * DEG
        q = 4.0 * beta**3 * sig**2  # white-noise intensity giving stationary std sig
        a = np.array([[0.0, 1.0], [-beta**2, -2 * beta]])
        # Van Loan: exact discrete transition and process noise
        m = np.zeros((4, 4))
        m[:2, :2] = -a
        m[:2, 2:] = np.diag([0.0, q])
        m[2:, 2:] = a.T
        e = expm(m * h)
        phi = e[2:, 2:].T
        qd = phi @ e[:2, 2:]
        qd = 0.5 * (qd + qd.T)
        w = rng.standard_normal((n, 2)) @ np.linalg.cholesky(qd + 1e-30 * np.eye(2)).T
        den = [1.0, -np.trace(phi), np.linalg.det(phi)]
        # x_{k+1} = phi x_k + w_k  ->  lambda_k and lambda'_k by IIR filtering of w (zero start)
        lam[:, ax] = (lfilter([0.0, 1.0, -phi[1, 1]], den, w[:, 0])
                      + lfilter([0.0, 0.0, phi[0, 1]], den, w[:, 1]))
        lam_d[:, ax] = (lfilter([0.0, 0.0, phi[1, 0]], den, w[:, 0])
                        + lfilter([0.0, 1.0, -phi[0, 0]], den, w[:, 1]))
    return _Flexure(CubicHermiteSpline(tg, lam, lam_d, axis=0))


def _right_jacobian(rv: np.ndarray) -> np.ndarray:
    """J_r(rv): d/dt exp([rv x]) = exp([rv x]) [(J_r rv') x]."""
    th = np.linalg.norm(rv, axis=-1)[..., None, None]
    k = skew(rv)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th**2 / 24.0, (1 - np.cos(ths)) / ths**2)
    b = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (ths - np.sin(ths)) / ths**3)
    return np.eye(3) - a * k + b * (k @ k)


# ==============================================================================================
# truth record
# ==============================================================================================
@dataclass(frozen=True)
class Truth:
    """What the simulation put in: the numbers an estimator must recover."""

    scenario: str
    seed: int
    duration_s: float
    latency_s: float  # slave stamp - master stamp for the same instant, at t_mid (incl. clock offset)
    latency_excl_clock_offset_s: float
    clock_offset_s: float  # 0 for slave_clock="epoch"; boot start - master epoch otherwise
    clock_offset_ns: int
    drift_ppm: float
    t_mid_rel_s: float  # master-relative time where latency_s holds (middle of the master log)
    master_t0_ns: int
    slave_t0_ns: int
    master_clock: str
    slave_clock: str
    mounting_rpy_deg: Vec3
    lever_arm_m: Vec3
    slave_gyro_bias_dph: Vec3
    slave_accel_bias_mg: Vec3
    master_gyro_bias_dph: Vec3
    master_accel_bias_mg: Vec3
    slave_start_phase: float
    flexure: dict = field(default_factory=dict)
    rates_hz: dict = field(default_factory=dict)
    config: SimConfig | None = None
    #: the slave's gyro and accelerometer triads relative to the master's IMU (what alignment.imu_to_imu
    #: measures): the mounting, and the accelerometers' misalignment composed with it
    imu_to_imu_gyro_rpy_deg: Vec3 | None = None
    imu_to_imu_accel_rpy_deg: Vec3 | None = None

    @property
    def t_mid_s(self) -> float:
        """Absolute master stamp (s) where ``latency_s`` holds."""
        return self.master_t0_ns * 1e-9 + self.t_mid_rel_s

    @property
    def t_mid_ns(self) -> int:
        return int(self.master_t0_ns + round(self.t_mid_rel_s * NS_PER_S))

    def latency_at(self, t_master_rel_s) -> np.ndarray | float:
        """Latency (s) at master-relative time(s): slave stamp - master stamp of the same instant."""
        t = np.asarray(t_master_rel_s, dtype=float)
        out = self.latency_s + self.drift_ppm * 1e-6 * (t - self.t_mid_rel_s)
        return float(out) if out.ndim == 0 else out

    def true_time_of_slave_stamp(self, slave_stamp_ns) -> np.ndarray:
        """Master-relative true time (s) of the instant a slave stamp (absolute int ns) refers to."""
        s = np.asarray(slave_stamp_ns, dtype=np.int64) - np.int64(self.master_t0_ns + self.clock_offset_ns)
        sigma = s * 1e-9
        d = self.drift_ppm * 1e-6
        return (sigma - self.latency_excl_clock_offset_s + d * self.t_mid_rel_s) / (1.0 + d)

    def to_dict(self) -> dict:
        d = {
            "schema": "tapost.sim-truth/1",
            "scenario": self.scenario,
            "seed": int(self.seed),
            "duration_s": float(self.duration_s),
            "latency_s": float(self.latency_s),
            "latency_excl_clock_offset_s": float(self.latency_excl_clock_offset_s),
            "clock_offset_s": float(self.clock_offset_s),
            "clock_offset_ns": int(self.clock_offset_ns),
            "drift_ppm": float(self.drift_ppm),
            "t_mid_s": float(self.t_mid_s),
            "t_mid_ns": self.t_mid_ns,
            "t_mid_rel_s": float(self.t_mid_rel_s),
            "mounting_rpy_deg": [float(x) for x in self.mounting_rpy_deg],
            "lever_arm_m": [float(x) for x in self.lever_arm_m],
            "slave_gyro_bias_dph": [float(x) for x in self.slave_gyro_bias_dph],
            "slave_accel_bias_mg": [float(x) for x in self.slave_accel_bias_mg],
            "master_gyro_bias_dph": [float(x) for x in self.master_gyro_bias_dph],
            "master_accel_bias_mg": [float(x) for x in self.master_accel_bias_mg],
            "slave_start_phase": float(self.slave_start_phase),
            "rates_hz": {k: float(v) for k, v in self.rates_hz.items()},
            "clocks": {"master": self.master_clock, "slave": self.slave_clock,
                       "master_t0_ns": int(self.master_t0_ns), "slave_t0_ns": int(self.slave_t0_ns)},
            "flexure": dict(self.flexure),
            "imu_to_imu_gyro_rpy_deg": (list(self.imu_to_imu_gyro_rpy_deg)
                                        if self.imu_to_imu_gyro_rpy_deg is not None else None),
            "imu_to_imu_accel_rpy_deg": (list(self.imu_to_imu_accel_rpy_deg)
                                         if self.imu_to_imu_accel_rpy_deg is not None else None),
            "notes": ("latency_s = slave stamp - master stamp for the same physical instant at t_mid_s; "
                      "latency(t) = latency_s + drift_ppm*1e-6*(t - t_mid_s). With slave_clock='boot' "
                      "it includes clock_offset_s; latency_excl_clock_offset_s is the physical part."),
        }
        if self.config is not None:
            d["config"] = _jsonable(asdict(self.config))
        return d


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


@dataclass(frozen=True)
class SimPair:
    master: InsLog
    slave: InsLog
    truth: Truth


# ==============================================================================================
# simulation
# ==============================================================================================
def _uniform_stamps_ns(start_ns: int, rate_hz: float, n: int) -> np.ndarray:
    return np.int64(start_ns) + np.rint(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)


def _jitter_ns(rng: np.random.Generator, n: int, jitter_s: float, rate_hz: float) -> np.ndarray:
    if jitter_s <= 0 or n == 0:
        return np.zeros(n, dtype=np.int64)
    j = np.clip(rng.standard_normal(n) * jitter_s, -0.4 / rate_hz, 0.4 / rate_hz)
    return np.rint(j * 1e9).astype(np.int64)


def _perturb_quat(q: np.ndarray, sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    if sigma_rad <= 0:
        return q
    return quat_make_continuous(quat_mul(q, quat_from_rotvec(rng.standard_normal((len(q), 3)) * sigma_rad)))


def _perturb_llh(lla: np.ndarray, sigma_m: float, rng: np.random.Generator) -> np.ndarray:
    if sigma_m <= 0:
        return lla
    d = rng.standard_normal(lla.shape) * sigma_m
    r_m, r_n = earth.radii_m(np.radians(lla[:, 0]))
    out = lla.copy()
    out[:, 0] += np.degrees(d[:, 0] / (r_m + lla[:, 2]))
    out[:, 1] += np.degrees(d[:, 1] / ((r_n + lla[:, 2]) * np.cos(np.radians(lla[:, 0]))))
    out[:, 2] += d[:, 2]
    return out


def _offset_llh(lla: np.ndarray, d_ned_m: np.ndarray) -> np.ndarray:
    r_m, r_n = earth.radii_m(np.radians(lla[:, 0]))
    out = lla.copy()
    out[:, 0] += np.degrees(d_ned_m[:, 0] / (r_m + lla[:, 2]))
    out[:, 1] += np.degrees(d_ned_m[:, 1] / ((r_n + lla[:, 2]) * np.cos(np.radians(lla[:, 0]))))
    out[:, 2] -= d_ned_m[:, 2]
    return out


def _imu_errors(rng: np.random.Generator, n: int, rate_hz: float, gyro_bias_dph, gyro_arw_dpsh: float,
                accel_bias_mg, accel_vrw: float) -> tuple[np.ndarray, np.ndarray]:
    g = np.asarray(gyro_bias_dph, float) * DEG_PER_H + rng.standard_normal((n, 3)) * (
        gyro_arw_dpsh * DEG_PER_SQRT_H * math.sqrt(rate_hz))
    a = np.asarray(accel_bias_mg, float) * MG + rng.standard_normal((n, 3)) * (
        accel_vrw * UG_PER_SQRT_HZ * math.sqrt(rate_hz))
    return g, a


def _markov(rng: np.random.Generator, t_s: np.ndarray, sigma: float, tau_s: float) -> np.ndarray:
    """First-order Gauss-Markov process (n, 3) on the uniform stamps t_s: stationary sigma, correlation
    time tau_s (exact discretisation, run by lfilter)."""
    n = len(t_s)
    if n == 0:
        return np.zeros((0, 3))
    a = math.exp(-(float(np.median(np.diff(t_s))) if n > 1 else 0.0) / tau_s)
    w = rng.standard_normal((n, 3)) * (sigma * math.sqrt(1.0 - a * a))
    x0 = rng.standard_normal(3) * sigma
    return lfilter([1.0], [1.0, -a], w, axis=0, zi=(a * x0)[None, :])[0]


def _vibration(rng: np.random.Generator, t_s: np.ndarray, f_hz: float, rms: float) -> np.ndarray:
    """Narrow-band vibration (n, 3): per axis five tones within +-10 % of f_hz, random phases, total rms."""
    if rms <= 0:
        return np.zeros((len(t_s), 3))
    f = f_hz * rng.uniform(0.9, 1.1, (5, 3))
    ph = rng.uniform(0.0, 2 * np.pi, (5, 3))
    tones = np.sin(2 * np.pi * f[None] * t_s[:, None, None] + ph[None])  # (n, 5, 3)
    return tones.sum(axis=1) * (rms * np.sqrt(2.0 / 5.0))


def _keep_outside_gaps(t_s: np.ndarray, gaps) -> np.ndarray:
    keep = np.ones(t_s.shape, bool)
    for start, length in gaps:
        keep &= ~((t_s >= start) & (t_s < start + length))
    return keep


def _slave_body(cfg: SimConfig, tr: TruthTrajectory, flex: _Flexure, mat_sm0: np.ndarray):
    """Slave IMU truth (gyro, accel in the slave frame), attitude quat, velocity, lla at tr.t_s."""
    flexed = flex.spline is not None
    if flexed:
        lam, lam_d = flex.angles_rates(tr.t_s)
        mat_sm = np.swapaxes(dcm_from_rotvec(lam), -1, -2) @ mat_sm0  # C_m^s = C_{s0}^s R
    else:
        mat_sm = mat_sm0
    r = np.asarray(cfg.lever_arm_m, float)
    w = tr.omega_ib_b_rad_s
    f_m = tr.f_b_m_s2
    vel = tr.vel_ned_m_s
    lla = tr.lat_lon_alt
    if np.any(r != 0):
        wxr = _cross(w, r)
        f_m = f_m + _cross(tr.omega_dot_ib_b_rad_s2, r) + _cross(w, wxr)
        d_n = _mv(tr.dcm_nb, np.broadcast_to(r, w.shape))
        lla = _offset_llh(lla, d_n)
        # the slave's local level frame n_s is tilted from the master's n_m by ~|d|/R
        lat_m, lon_m = np.radians(tr.lat_lon_alt[:, 0]), np.radians(tr.lat_lon_alt[:, 1])
        lat_s, lon_s = np.radians(lla[:, 0]), np.radians(lla[:, 1])
        mat_nsnm = earth.dcm_ecef_to_ned(lat_s, lon_s) @ np.swapaxes(earth.dcm_ecef_to_ned(lat_m, lon_m), -1, -2)
        # gravitation difference between the two points, in n_m: normal gravity (incl. centrifugal) at
        # each point, plus the centrifugal difference
        g_s = _mtv(mat_nsnm, earth.gravity_ned_m_s2(lat_s, lla[:, 2]))
        w_ie = tr.omega_ie_n_rad_s
        dgrav_n = g_s - tr.gravity_ned_m_s2 + _cross(w_ie, _cross(w_ie, d_n))
        f_m = f_m - _mtv(tr.dcm_nb, dgrav_n)
        w_eb = w - _mtv(tr.dcm_nb, w_ie)
        vel = _mv(mat_nsnm, vel + _mv(tr.dcm_nb, _cross(w_eb, r)))
        q_att = quat_mul(quat_from_dcm(mat_nsnm), tr.quat_wxyz)
    else:
        q_att = tr.quat_wxyz
    gyro = _mv(mat_sm, w)
    accel = _mv(mat_sm, f_m)
    quat = quat_mul(q_att, quat_conj(quat_from_dcm(mat_sm0)))
    if flexed:
        gyro = gyro + _mv(_right_jacobian(lam), lam_d)
        quat = quat_mul(quat, quat_from_rotvec(lam))
    return gyro, accel, quat_make_continuous(quat) if len(quat) else quat, vel, lla


def simulate(cfg: SimConfig) -> SimPair:
    """Master and slave InsLogs plus the truth they were made from (deterministic for cfg.seed)."""
    ss = np.random.SeedSequence(int(cfg.seed))
    (rng_m_imu, rng_m_nav, rng_s_imu, rng_s_nav, rng_phase, rng_flex, rng_m_jit,
     rng_s_jit) = [np.random.default_rng(s) for s in ss.spawn(8)]
    dur = float(cfg.duration_s)
    t_mid = 0.5 * dur
    d = cfg.drift_ppm * 1e-6
    lat_s = float(cfg.latency_s)
    pos = _position_model(cfg, -_MARGIN_S, dur + _MARGIN_S)

    # ---- master: stamps = true time on the epoch clock ------------------------------------------
    def master_stream(rate):
        n = int(math.floor(dur * rate + 1e-9)) + 1
        rel_ns = _uniform_stamps_ns(0, rate, n)
        return rel_ns, rel_ns * 1e-9

    m_imu_ns, m_imu_t = master_stream(cfg.master_imu_rate_hz)
    m_nav_ns, m_nav_t = master_stream(cfg.master_nav_rate_hz)
    m_all_ns, i_imu, i_nav = _merged(m_imu_ns, m_nav_ns)
    def master_truth(t):
        tr = _truth_at(cfg, pos, t)
        return tr.omega_ib_b_rad_s, tr.f_b_m_s2, tr.quat_wxyz, tr.vel_ned_m_s, tr.lat_lon_alt

    m_w, m_f, m_q, m_v, m_p = _chunked(master_truth, m_all_ns * 1e-9)
    if i_imu is not None:
        m_w, m_f = m_w[i_imu], m_f[i_imu]
    g_err, a_err = _imu_errors(rng_m_imu, len(m_imu_t), cfg.master_imu_rate_hz, cfg.master_gyro_bias_dph,
                               cfg.master_gyro_arw_dpsh, cfg.master_accel_bias_mg,
                               cfg.master_accel_vrw_ug_rthz)
    m_gyro = m_w + g_err
    m_accel = m_f + a_err
    m_quat = _perturb_quat(quat_make_continuous(m_q[i_nav]), cfg.master_att_noise_deg * DEG, rng_m_nav)
    if cfg.master_att_markov_deg > 0:  # its own random stream: the other outputs stay as they were
        rng_mk = np.random.default_rng(ss.spawn(1)[0])
        err = _markov(rng_mk, m_nav_t, cfg.master_att_markov_deg * DEG, cfg.master_att_markov_tau_s)
        m_quat = quat_make_continuous(quat_mul(quat_from_rotvec(err), m_quat))
    m_vel = m_v[i_nav] + rng_m_nav.standard_normal((len(i_nav), 3)) * cfg.master_vel_noise_m_s
    m_lla = _perturb_llh(m_p[i_nav], cfg.master_pos_noise_m, rng_m_nav)
    del m_w, m_f, m_q, m_v, m_p
    m_imu_ns = m_imu_ns + _jitter_ns(rng_m_jit, len(m_imu_ns), cfg.master_jitter_s, cfg.master_imu_rate_hz)
    m_nav_ns = m_nav_ns + _jitter_ns(rng_m_jit, len(m_nav_ns), cfg.master_jitter_s, cfg.master_nav_rate_hz)
    master_meta = LogMeta(
        source_path=f"<sim:{cfg.scenario} seed={cfg.seed} master>", format="sim", clock="epoch",
        t0_ns=int(cfg.t0_ns), stamp_source="simulated (true time)",
        channels={"imu": ChannelInfo(cfg.master_imu_rate_hz, len(m_imu_ns), "sim master imu"),
                  "nav": ChannelInfo(cfg.master_nav_rate_hz, len(m_nav_ns), "sim master nav")})
    master = InsLog.from_arrays(master_meta, t_imu_s=m_imu_ns * 1e-9, gyro_rad_s=m_gyro, accel_m_s2=m_accel,
                                t_nav_s=m_nav_ns * 1e-9, quat_wxyz=m_quat, vel_ned_m_s=m_vel,
                                lat_lon_alt=m_lla)

    # ---- slave clock: sigma(t) = t + L + d (t - t_mid) (+ offset) ---------------------------
    if cfg.slave_clock == "boot":
        sigma0_ns = int(round((lat_s - d * t_mid) * NS_PER_S))
        offset_ns = int(round(cfg.slave_boot_start_s * NS_PER_S)) - int(cfg.t0_ns) - sigma0_ns
    else:
        offset_ns = 0
    phase = float(rng_phase.random()) if cfg.slave_start_phase is None else float(cfg.slave_start_phase)
    sigma_start = lat_s - d * t_mid + phase / cfg.slave_imu_rate_hz
    sigma_end = dur + lat_s + d * (dur - t_mid)
    start_ns = int(round(sigma_start * NS_PER_S))

    def slave_stream(rate):
        n = int(math.floor((sigma_end - start_ns * 1e-9) * rate + 1e-9)) + 1
        sig_ns = _uniform_stamps_ns(start_ns, rate, max(n, 0))
        t_true = (sig_ns * 1e-9 - lat_s + d * t_mid) / (1.0 + d)
        ok = (t_true <= dur) & _keep_outside_gaps(t_true, cfg.slave_gaps_s)
        return sig_ns[ok], t_true[ok]

    flex = _flexure_model(cfg, rng_flex, -_MARGIN_S, dur + _MARGIN_S)
    mat_sm0 = dcm_from_euler(np.radians(np.asarray(cfg.mount_rpy_deg, float)))
    s_imu_sig, s_imu_t = slave_stream(cfg.slave_imu_rate_hz)
    if cfg.slave_nav:
        s_nav_sig, s_nav_t = slave_stream(cfg.slave_nav_rate_hz)
    else:
        s_nav_sig, s_nav_t = np.zeros(0, np.int64), np.zeros(0)
    s_all_sig, i_imu, i_nav = _merged(s_imu_sig, s_nav_sig)
    s_all_t = s_imu_t if i_imu is None else (s_all_sig * 1e-9 - lat_s + d * t_mid) / (1.0 + d)
    body = _chunked(lambda t: _slave_body(cfg, _truth_at(cfg, pos, t), flex, mat_sm0), s_all_t)
    s_gyro, s_accel = (body[0], body[1]) if i_imu is None else (body[0][i_imu], body[1][i_imu])
    g_err, a_err = _imu_errors(rng_s_imu, len(s_imu_t), cfg.slave_imu_rate_hz, cfg.slave_gyro_bias_dph,
                               cfg.slave_gyro_arw_dpsh, cfg.slave_accel_bias_mg, cfg.slave_accel_vrw_ug_rthz)
    if any(cfg.slave_accel_misalign_rpy_deg):
        s_accel = _mv(dcm_from_euler(np.radians(np.asarray(cfg.slave_accel_misalign_rpy_deg, float))), s_accel)
    s_gyro, s_accel = s_gyro + g_err, s_accel + a_err
    if cfg.slave_vibration_accel_m_s2 > 0 or cfg.slave_vibration_gyro_dps > 0:
        rng_vib = np.random.default_rng(ss.spawn(1)[0])
        s_accel = s_accel + _vibration(rng_vib, s_imu_t, cfg.vibration_hz, cfg.slave_vibration_accel_m_s2)
        s_gyro = s_gyro + _vibration(rng_vib, s_imu_t, cfg.vibration_hz, cfg.slave_vibration_gyro_dps * DEG)
    s_imu_abs = int(cfg.t0_ns) + offset_ns + s_imu_sig + _jitter_ns(
        rng_s_jit, len(s_imu_sig), cfg.slave_jitter_s, cfg.slave_imu_rate_hz)
    nav_kw: dict = {}
    firsts = [int(s_imu_abs[0])] if len(s_imu_abs) else []
    s_nav_count = 0
    if cfg.slave_nav:
        s_quat, s_vel, s_lla = quat_make_continuous(body[2][i_nav]), body[3][i_nav], body[4][i_nav]
        s_quat = _perturb_quat(s_quat, cfg.slave_att_noise_deg * DEG, rng_s_nav)
        s_vel = s_vel + rng_s_nav.standard_normal(s_vel.shape) * cfg.slave_vel_noise_m_s
        s_lla = _perturb_llh(s_lla, cfg.slave_pos_noise_m, rng_s_nav)
        s_nav_abs = int(cfg.t0_ns) + offset_ns + s_nav_sig + _jitter_ns(
            rng_s_jit, len(s_nav_sig), cfg.slave_jitter_s, cfg.slave_nav_rate_hz)
        if len(s_nav_abs):
            firsts.append(int(s_nav_abs[0]))
        s_nav_count = len(s_nav_abs)
        nav_kw = dict(quat_wxyz=s_quat, vel_ned_m_s=s_vel, lat_lon_alt=s_lla)
    if not firsts:
        raise InputError("simulate: the slave has no samples (gaps cover the whole log?)")
    s_t0 = min(firsts)
    channels = {"imu": ChannelInfo(cfg.slave_imu_rate_hz, len(s_imu_abs), "sim slave imu")}
    if cfg.slave_nav:
        channels["nav"] = ChannelInfo(cfg.slave_nav_rate_hz, s_nav_count, "sim slave nav")
        nav_kw["t_nav_s"] = (s_nav_abs - s_t0) * 1e-9
    slave_meta = LogMeta(
        source_path=f"<sim:{cfg.scenario} seed={cfg.seed} slave>", format="sim", clock=cfg.slave_clock,
        t0_ns=s_t0, stamp_source="simulated (slave clock: latency + drift)", channels=channels)
    slave = InsLog.from_arrays(slave_meta, t_imu_s=(s_imu_abs - s_t0) * 1e-9, gyro_rad_s=s_gyro,
                               accel_m_s2=s_accel, **nav_kw)

    truth = Truth(
        scenario=cfg.scenario, seed=int(cfg.seed), duration_s=dur,
        latency_s=lat_s + offset_ns * 1e-9, latency_excl_clock_offset_s=lat_s,
        clock_offset_s=offset_ns * 1e-9, clock_offset_ns=int(offset_ns), drift_ppm=float(cfg.drift_ppm), t_mid_rel_s=t_mid,
        master_t0_ns=int(cfg.t0_ns), slave_t0_ns=s_t0, master_clock="epoch", slave_clock=cfg.slave_clock,
        mounting_rpy_deg=tuple(float(x) for x in cfg.mount_rpy_deg),
        lever_arm_m=tuple(float(x) for x in cfg.lever_arm_m),
        slave_gyro_bias_dph=tuple(float(x) for x in cfg.slave_gyro_bias_dph),
        slave_accel_bias_mg=tuple(float(x) for x in cfg.slave_accel_bias_mg),
        master_gyro_bias_dph=tuple(float(x) for x in cfg.master_gyro_bias_dph),
        master_accel_bias_mg=tuple(float(x) for x in cfg.master_accel_bias_mg),
        slave_start_phase=phase,
        flexure={"enabled": bool(cfg.flexure), "model": "second-order Markov (seed 000 eq. 8)",
                 "sigma_deg": list(cfg.flexure_sigma_deg), "beta_1_s": list(cfg.flexure_beta_1_s)},
        rates_hz={"master_imu": cfg.master_imu_rate_hz, "master_nav": cfg.master_nav_rate_hz,
                  "slave_imu": cfg.slave_imu_rate_hz,
                  "slave_nav": cfg.slave_nav_rate_hz if cfg.slave_nav else 0.0},
        config=cfg,
        imu_to_imu_gyro_rpy_deg=tuple(float(x) for x in cfg.mount_rpy_deg),
        imu_to_imu_accel_rpy_deg=tuple(float(x) for x in np.degrees(euler_from_dcm(
            dcm_from_euler(np.radians(np.asarray(cfg.slave_accel_misalign_rpy_deg, float))) @ mat_sm0))),
    )
    return SimPair(master=master, slave=slave, truth=truth)
