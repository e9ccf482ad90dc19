"""InsLog: the common, time-indexed frame every parser produces (DESIGN.md, "InsLog").

``imu`` and ``nav`` are pandas DataFrames indexed by ``t_s`` (float64 seconds relative to
``meta.t0_ns``); absolute time of a row is ``meta.t0_ns * 1e-9 + t_s`` (kept as int ns at the IO edge).
Column names carry their units and frames (FRD body, NED navigation), see the constants below.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import pandas as pd

# ---- column names: the one place they are spelled -------------------------------------------
T = "t_s"
GYRO = ("gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s")
ACCEL = ("accel_x_m_s2", "accel_y_m_s2", "accel_z_m_s2")
QUAT = ("quat_w", "quat_x", "quat_y", "quat_z")
VEL = ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s")
POS = ("lat_deg", "lon_deg", "alt_m")
IMU_COLUMNS = GYRO + ACCEL
NAV_COLUMNS = QUAT + VEL + POS

Clock = Literal["epoch", "boot", "unknown"]


@dataclass(frozen=True)
class ChannelInfo:
    """One stream of a log: where it came from, how often and how many samples."""

    rate_hz: float
    count: int
    source: str = ""  # e.g. "IMU2", "/xsens/imu_data", "HIGHRES_IMU"
    #: the stamps' step when the format's is coarse (MAVLink time_boot_ms: 1e-3 s); 0 when fine (us, ns)
    stamp_resolution_s: float = 0.0
    #: the sigma of the offset that put the stamps on the log's clock, common to all of them (a tlog's boot
    #: stamps mapped to UNIX time by SYSTEM_TIME, whose time_boot_ms is whole ms: up to 1 ms / sqrt(12)); 0 exact
    clock_sigma_s: float = 0.0
    #: that offset itself (ns), where one put the stamps on the log's clock: two units whose stamps were put on
    #: UNIX time by the very same offset (one file's two units, an exported copy read back) share its error
    clock_offset_ns: int | None = None


@dataclass(frozen=True)
class LogMeta:
    source_path: str
    format: str
    selector: str = ""
    clock: Clock = "unknown"
    t0_ns: int = 0
    stamp_source: str = ""
    channels: dict[str, ChannelInfo] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    def with_warning(self, *msgs: str) -> "LogMeta":
        return replace(self, warnings=self.warnings + tuple(msgs))


def _columns(frame: pd.DataFrame, cols: tuple[str, ...], order: str = "F") -> np.ndarray:
    """``frame[list(cols)].to_numpy(dtype=float)`` filled column by column (one copy of the values, not
    a sub-frame and then its array), in that array's memory order (F: each column contiguous) or C."""
    missing = [c for c in cols if c not in frame.columns]
    if missing:
        raise KeyError(f"{missing} not in index")
    out = np.empty((len(cols), len(frame))).T if order == "F" else np.empty((len(frame), len(cols)))
    for j, c in enumerate(cols):
        out[:, j] = frame[c].to_numpy(dtype=float)
    return out


def _empty(columns: tuple[str, ...]) -> pd.DataFrame:
    return pd.DataFrame({c: np.zeros(0) for c in columns}, index=pd.Index(np.zeros(0), name=T))


@dataclass(frozen=True)
class InsLog:
    """One unit's data. Treat the DataFrames as read-only; derive new logs with helpers below."""

    imu: pd.DataFrame
    nav: pd.DataFrame
    meta: LogMeta

    # -- construction ------------------------------------------------------------------------
    @staticmethod
    def from_arrays(
        meta: LogMeta,
        t_imu_s: np.ndarray | None = None,
        gyro_rad_s: np.ndarray | None = None,
        accel_m_s2: np.ndarray | None = None,
        t_nav_s: np.ndarray | None = None,
        quat_wxyz: np.ndarray | None = None,
        vel_ned_m_s: np.ndarray | None = None,
        lat_lon_alt: np.ndarray | None = None,
    ) -> "InsLog":
        """Build from arrays (times relative to ``meta.t0_ns``); absent groups are left out."""
        imu_cols: dict[str, np.ndarray] = {}
        if gyro_rad_s is not None:
            imu_cols.update(zip(GYRO, np.asarray(gyro_rad_s, float).T))
        if accel_m_s2 is not None:
            imu_cols.update(zip(ACCEL, np.asarray(accel_m_s2, float).T))
        nav_cols: dict[str, np.ndarray] = {}
        if quat_wxyz is not None:
            nav_cols.update(zip(QUAT, np.asarray(quat_wxyz, float).T))
        if vel_ned_m_s is not None:
            nav_cols.update(zip(VEL, np.asarray(vel_ned_m_s, float).T))
        if lat_lon_alt is not None:
            nav_cols.update(zip(POS, np.asarray(lat_lon_alt, float).T))
        imu = (pd.DataFrame(imu_cols, index=pd.Index(np.asarray(t_imu_s, float), name=T))
               if imu_cols else pd.DataFrame(index=pd.Index(np.zeros(0), name=T)))
        nav = (pd.DataFrame(nav_cols, index=pd.Index(np.asarray(t_nav_s, float), name=T))
               if nav_cols else pd.DataFrame(index=pd.Index(np.zeros(0), name=T)))
        return InsLog(imu=imu, nav=nav, meta=meta)

    # -- what the log holds ------------------------------------------------------------------
    @property
    def has_gyro(self) -> bool:
        return all(c in self.imu.columns for c in GYRO) and len(self.imu) > 0

    @property
    def has_accel(self) -> bool:
        return all(c in self.imu.columns for c in ACCEL) and len(self.imu) > 0

    @property
    def has_quat(self) -> bool:
        return all(c in self.nav.columns for c in QUAT) and self.nav[list(QUAT)].notna().any().all()

    @property
    def has_vel(self) -> bool:
        return all(c in self.nav.columns for c in VEL) and self.nav[list(VEL)].notna().any().all()

    @property
    def has_pos(self) -> bool:
        return all(c in self.nav.columns for c in POS) and self.nav[list(POS)].notna().any().all()

    def _channel(self, group: str) -> ChannelInfo | None:
        """A group's (``"gyro"``, ``"accel"``, ``"att"``, ``"vel"``, ``"pos"``) ChannelInfo; logs that name their
        channels by row kind (canonical CSV, the simulator: ``imu``, ``nav``) through those names."""
        kind = "imu" if group in ("gyro", "accel") else "nav"
        return next((ch for ch in (self.meta.channels.get(k) for k in (group, kind)) if ch is not None), None)

    def stamp_resolution_s(self, group: str) -> float:
        """The step of a group's stamps when coarse (``ChannelInfo.stamp_resolution_s``: MAVLink
        ``time_boot_ms``, DataFlash ``TimeMS``, a CSV's fixed decimals, stamps on a visible grid), else 0.
        Stamps rounded so may all be off by the same fraction of it (a fixed sampling phase): a delay bias
        of up to half of it."""
        ch = self._channel(group)
        return float(ch.stamp_resolution_s or 0.0) if ch is not None else 0.0

    def clock_sigma_s(self, group: str) -> float:
        """The sigma of the offset that put a group's stamps on the log's clock (``ChannelInfo.clock_sigma_s``),
        else 0."""
        ch = self._channel(group)
        return float(ch.clock_sigma_s or 0.0) if ch is not None else 0.0

    def clock_offset_ns(self, group: str) -> int | None:
        """The offset that put a group's stamps on the log's clock (``ChannelInfo.clock_offset_ns``), else None."""
        ch = self._channel(group)
        return ch.clock_offset_ns if ch is not None else None

    # -- array views -------------------------------------------------------------------------
    def t_imu_s(self) -> np.ndarray:
        return self.imu.index.to_numpy(dtype=float)

    def t_nav_s(self) -> np.ndarray:
        return self.nav.index.to_numpy(dtype=float)

    def gyro_rad_s(self) -> np.ndarray:
        return _columns(self.imu, GYRO)

    def accel_m_s2(self) -> np.ndarray:
        return _columns(self.imu, ACCEL)

    def nav_rows(self, cols: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(t_s, values) for the nav rows where every column of ``cols`` is present."""
        vals = _columns(self.nav, cols, "C")  # (the order of the original's masked copy)
        ok = ~np.isnan(vals).any(axis=1)
        t = self.nav.index.to_numpy(dtype=float)
        if ok.all():  # (no rows to drop: the arrays as they are)
            return t.copy() if np.shares_memory(t, self.nav.index.to_numpy()) else t, vals
        return t[ok], vals[ok]

    def quat_wxyz(self) -> tuple[np.ndarray, np.ndarray]:
        return self.nav_rows(QUAT)

    def vel_ned_m_s(self) -> tuple[np.ndarray, np.ndarray]:
        return self.nav_rows(VEL)

    def lat_lon_alt(self) -> tuple[np.ndarray, np.ndarray]:
        return self.nav_rows(POS)

    # -- time --------------------------------------------------------------------------------
    @property
    def t0_s(self) -> float:
        return self.meta.t0_ns * 1e-9

    def span_s(self) -> tuple[float, float]:
        """(first, last) relative time over all streams; (nan, nan) when empty."""
        ts = [s for s in (self.t_imu_s(), self.t_nav_s()) if len(s)]
        if not ts:
            return (float("nan"), float("nan"))
        return (min(float(s[0]) for s in ts), max(float(s[-1]) for s in ts))

    @property
    def duration_s(self) -> float:
        a, b = self.span_s()
        return float(b - a) if np.isfinite(a) else 0.0

    def between(self, t_start_s: float, t_end_s: float) -> "InsLog":
        """Rows with t_start_s <= t_s <= t_end_s (relative seconds); cheap (index slicing)."""
        return replace(
            self,
            imu=self.imu.loc[t_start_s:t_end_s],
            nav=self.nav.loc[t_start_s:t_end_s],
        )

    def rebased(self, t0_ns: int) -> "InsLog":
        """Same data expressed relative to another origin ``t0_ns`` (exact integer shift)."""
        d = (self.meta.t0_ns - int(t0_ns)) * 1e-9
        imu = self.imu.set_axis(self.imu.index + d, axis=0)
        nav = self.nav.set_axis(self.nav.index + d, axis=0)
        imu.index.name = T
        nav.index.name = T
        return replace(self, imu=imu, nav=nav, meta=replace(self.meta, t0_ns=int(t0_ns)))

    def with_meta(self, **changes) -> "InsLog":
        return replace(self, meta=replace(self.meta, **changes))
