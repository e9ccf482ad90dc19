"""InsLog: the common, time-indexed frame every parser produces (DESIGN.md, "InsLog").

``imu`` and ``nav`` are pandas DataFrames indexed by ``t_s`` (float64 seconds relative to
``meta.t0_ns``); absolute time of a row is ``meta.t0_ns * 1e-9 + t_s`` (kept as int ns at the IO edge).
They are held as numpy arrays (:class:`Columns`) and made DataFrames when first asked for.
Column names carry their units and frames (FRD body, NED navigation), see the constants below.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal

import numpy as np

from logtools.errors import AnalysisError

if TYPE_CHECKING:  # (imported where a DataFrame is made: the analysis itself reads the arrays)
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
#: each column group's name, the ``has_*`` property that says whether a log holds it, and its accessor
_GROUPS = {GYRO: ("angular rate (gyro)", "has_gyro", "gyro_rad_s"),
           ACCEL: ("specific force (accel)", "has_accel", "accel_m_s2"),
           QUAT: ("attitude (quaternion)", "has_quat", "quat_wxyz"),
           VEL: ("velocity (NED)", "has_vel", "vel_ned_m_s"),
           POS: ("position (lat/lon/alt)", "has_pos", "lat_lon_alt")}

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


class MissingChannelError(AnalysisError, KeyError):
    """An InsLog accessor (``gyro_rad_s()``, ``quat_wxyz()``, ...) asked for a channel the log lacks. An
    ``AnalysisError`` (the data are read but lack what is asked: tapost's one-line error, exit 1) and a
    ``KeyError`` (what a missing column raised before, for callers that catch that). ``columns``: the missing
    ones."""

    def __init__(self, problem: str, path: str | None = None, columns: tuple[str, ...] = ()):
        super().__init__(problem, path)
        self.columns = columns

    __str__ = Exception.__str__  # (KeyError's would quote the message)


def _float(a) -> np.ndarray:
    return np.asarray(a, dtype=float)


@dataclass(frozen=True, eq=False)
class Columns:
    """One stream of an :class:`InsLog` as numpy arrays: ``t_s`` (float64 seconds from ``meta.t0_ns``) and
    named columns, each ``len(t_s)`` long. An InsLog holds its streams so; the pandas DataFrame
    (``InsLog.imu``, ``.nav``) is made from them when first asked for, without a copy when the columns are the
    rows of one (k, N) ``block`` (the layout pandas gives a frame built from k float columns). The analysis
    reads the arrays (``InsLog.gyro_rad_s()`` ...): a command that never asks for a DataFrame never imports
    pandas (about 0.17 s of every run)."""

    t_s: np.ndarray
    data: dict[str, np.ndarray]
    #: (k, N) whose rows are ``data``'s values in their order, or None
    block: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t_s)

    def __reduce__(self):
        # the block once (its rows, the columns, are views of it: pickled apart they would be copies, twice the
        # memory where a forked parse sends its log back)
        if self.block is not None:
            return (Columns.from_block, (self.t_s, tuple(self.data), self.block))
        return (Columns, (self.t_s, self.data))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.data)

    @staticmethod
    def empty() -> "Columns":
        return Columns(np.zeros(0), {})

    @staticmethod
    def from_block(t_s: np.ndarray, names, block: np.ndarray) -> "Columns":
        """Over ``block`` (k, N): column j is row j, not copied."""
        return Columns(t_s, dict(zip(list(names), block)), block)

    @staticmethod
    def from_dict(t_s, data: dict[str, np.ndarray]) -> "Columns":
        return Columns(_float(t_s), dict(data))

    @staticmethod
    def from_frame(frame) -> "Columns":
        """A DataFrame's index (as float) and columns (their arrays, not copied where pandas holds them so)."""
        return Columns(frame.index.to_numpy(dtype=float), {c: frame[c].to_numpy() for c in frame.columns})

    def frame(self):
        """The DataFrame (index ``t_s``): over ``block`` when there is one, else made from the columns."""
        import pandas as pd

        index = pd.Index(self.t_s, name=T)
        if not self.data:
            return pd.DataFrame(index=index)
        if self.block is not None:
            return pd.DataFrame(self.block.T, index=index, columns=list(self.data), copy=False)
        return pd.DataFrame(self.data, index=index)

    def with_t(self, t_s) -> "Columns":
        """The same values at other stamps (the DataFrame's ``set_axis``)."""
        return Columns(_float(t_s), self.data, self.block)

    def take(self, rows) -> "Columns":
        """The rows ``rows`` (a boolean mask or a slice) of every column."""
        if self.block is not None:
            block = self.block[:, rows]
            return Columns(self.t_s[rows], dict(zip(self.data, block)), block)
        return Columns(self.t_s[rows], {c: v[rows] for c, v in self.data.items()})

    def between(self, t_start_s: float, t_end_s: float) -> "Columns":
        """Rows with t_start_s <= t_s <= t_end_s (increasing stamps: the DataFrame's ``.loc[a:b]``)."""
        i0 = int(np.searchsorted(self.t_s, t_start_s, side="left"))
        i1 = int(np.searchsorted(self.t_s, t_end_s, side="right"))
        return self.take(slice(i0, max(i0, i1)))

    def values(self, cols: tuple[str, ...], order: str = "F") -> np.ndarray:
        """(N, len(cols)) float64 of those columns (one copy), in that memory order (F: each column
        contiguous, or C); KeyError naming the missing ones."""
        missing = [c for c in cols if c not in self.data]
        if missing:
            raise KeyError(f"{missing} not in index")
        out = np.empty((len(cols), len(self))).T if order == "F" else np.empty((len(self), len(cols)))
        for j, c in enumerate(cols):
            out[:, j] = self.data[c]
        return out

    def present(self, cols: tuple[str, ...]) -> bool:
        """Every column of ``cols`` there with at least one value (pandas' ``notna``: not NaN, not None)."""
        return all(c in self.data for c in cols) and all(_any_value(self.data[c]) for c in cols)


def _any_value(a: np.ndarray) -> bool:
    if a.dtype.kind in "biu":
        return len(a) > 0
    if a.dtype.kind in "fc":
        return bool((~np.isnan(a)).any())
    return any(x is not None and x == x for x in a.tolist())  # (object columns: None and NaN are missing)


def _as_columns(stream) -> Columns:
    return stream if isinstance(stream, Columns) else Columns.from_frame(stream)


@dataclass(frozen=True, eq=False, init=False, repr=False)
class InsLog:
    """One unit's data: ``imu`` and ``nav`` pandas DataFrames indexed by ``t_s``, and ``meta``. Read-only:
    derive new logs with the helpers below (``with_streams``, ``with_meta``, ``between``, ``rebased``) or
    ``dataclasses.replace``. ``imu``/``nav`` are given as DataFrames or as :class:`Columns` (what the parsers
    give); the array accessors (``t_imu_s()``, ``gyro_rad_s()``, ``nav_rows()``, ...) read the arrays, and a
    DataFrame is made on the first access of ``.imu``/``.nav``."""

    __slots__ = ("_imu", "_nav", "_frames", "meta", "__weakref__")

    imu: "pd.DataFrame"
    nav: "pd.DataFrame"
    meta: LogMeta

    def __init__(self, imu, nav, meta: LogMeta) -> None:
        frames = {k: v for k, v in (("imu", imu), ("nav", nav)) if not isinstance(v, Columns)}
        object.__setattr__(self, "_imu", _as_columns(imu))
        object.__setattr__(self, "_nav", _as_columns(nav))
        object.__setattr__(self, "_frames", frames)
        object.__setattr__(self, "meta", meta)

    def __reduce__(self):
        return (InsLog, (self._given("imu"), self._given("nav"), self.meta))

    def _given(self, kind: str):
        """The stream as it was given or last made: its DataFrame where there is one, else its Columns."""
        return self._frames.get(kind, self._imu if kind == "imu" else self._nav)

    def __repr__(self) -> str:
        return (f"InsLog({self.meta.format!r}, {self.meta.source_path!r}, imu: {len(self._imu)} rows "
                f"{list(self._imu.names)}, nav: {len(self._nav)} rows {list(self._nav.names)})")

    def _frame(self, kind: str):
        f = self._frames.get(kind)
        if f is None:
            f = self._frames[kind] = (self._imu if kind == "imu" else self._nav).frame()
        return f

    @property
    def imu_columns(self) -> Columns:
        """The IMU stream's arrays (no pandas)."""
        return self._imu

    @property
    def nav_columns(self) -> Columns:
        """The navigation stream's arrays (no pandas)."""
        return self._nav

    @property
    def n_imu(self) -> int:
        """IMU rows (``len(log.imu)`` without making the DataFrame)."""
        return len(self._imu)

    @property
    def n_nav(self) -> int:
        """Navigation rows (``len(log.nav)`` without making the DataFrame)."""
        return len(self._nav)

    def with_streams(self, imu=None, nav=None, meta: LogMeta | None = None) -> "InsLog":
        """A new log with the given streams (DataFrames or Columns) or meta, the others kept."""
        return InsLog(imu=self._given("imu") if imu is None else imu,
                      nav=self._given("nav") if nav is None else nav,
                      meta=self.meta if meta is None else meta)

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
            imu_cols.update(zip(GYRO, _float(gyro_rad_s).T))
        if accel_m_s2 is not None:
            imu_cols.update(zip(ACCEL, _float(accel_m_s2).T))
        nav_cols: dict[str, np.ndarray] = {}
        if quat_wxyz is not None:
            nav_cols.update(zip(QUAT, _float(quat_wxyz).T))
        if vel_ned_m_s is not None:
            nav_cols.update(zip(VEL, _float(vel_ned_m_s).T))
        if lat_lon_alt is not None:
            nav_cols.update(zip(POS, _float(lat_lon_alt).T))
        imu = Columns.from_dict(t_imu_s, imu_cols) if imu_cols else Columns.empty()
        nav = Columns.from_dict(t_nav_s, nav_cols) if nav_cols else Columns.empty()
        return InsLog(imu=imu, nav=nav, meta=meta)

    # -- what the log holds ------------------------------------------------------------------
    @property
    def has_gyro(self) -> bool:
        return all(c in self._imu.data for c in GYRO) and len(self._imu) > 0

    @property
    def has_accel(self) -> bool:
        return all(c in self._imu.data for c in ACCEL) and len(self._imu) > 0

    @property
    def has_quat(self) -> bool:
        return self._nav.present(QUAT)

    @property
    def has_vel(self) -> bool:
        return self._nav.present(VEL)

    @property
    def has_pos(self) -> bool:
        return self._nav.present(POS)

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
    def _missing(self, stream: Columns, cols: tuple[str, ...]) -> MissingChannelError:
        """The error for ``cols`` absent from ``stream``: which channel, which log, what to check first."""
        missing = tuple(c for c in cols if c not in stream.data)
        name, has, accessor = _GROUPS.get(cols, (f"columns {', '.join(cols)}", "", "nav_rows"))
        m = self.meta
        source = (m.source_path or "an InsLog made in memory") + (f"::{m.selector}" if m.selector else "")
        check = f"check log.{has} before calling {accessor}()" if has else "check log.nav_columns.names"
        return MissingChannelError(f"the log ({m.format or 'unknown format'}) has no {name}: no column(s) "
                                   f"{', '.join(missing)}; {check}", source, missing)

    def t_imu_s(self) -> np.ndarray:
        return self._imu.t_s

    def t_nav_s(self) -> np.ndarray:
        return self._nav.t_s

    def gyro_rad_s(self) -> np.ndarray:
        """(N, 3) angular rate, rad/s, FRD body; MissingChannelError where the log has none (``has_gyro``)."""
        try:
            return self._imu.values(GYRO)
        except KeyError:
            raise self._missing(self._imu, GYRO) from None

    def accel_m_s2(self) -> np.ndarray:
        """(N, 3) specific force, m/s^2, FRD body; MissingChannelError where the log has none (``has_accel``)."""
        try:
            return self._imu.values(ACCEL)
        except KeyError:
            raise self._missing(self._imu, ACCEL) from None

    def nav_rows(self, cols: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(t_s, values) for the nav rows where every column of ``cols`` is present (new arrays);
        MissingChannelError where the log lacks one of ``cols``."""
        try:
            vals = self._nav.values(cols, "C")  # (the order of the original's masked copy)
        except KeyError:
            raise self._missing(self._nav, cols) from None
        ok = ~np.isnan(vals).any(axis=1)
        t = self._nav.t_s
        if ok.all():  # (no rows to drop: the arrays as they are)
            return t.copy(), vals
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
        """Rows with t_start_s <= t_s <= t_end_s (relative seconds); cheap (views of the arrays)."""
        return InsLog(imu=self._imu.between(t_start_s, t_end_s), nav=self._nav.between(t_start_s, t_end_s),
                      meta=self.meta)

    def rebased(self, t0_ns: int) -> "InsLog":
        """Same data expressed relative to another origin ``t0_ns`` (exact integer shift)."""
        d = (self.meta.t0_ns - int(t0_ns)) * 1e-9
        return InsLog(imu=self._imu.with_t(self._imu.t_s + d), nav=self._nav.with_t(self._nav.t_s + d),
                      meta=replace(self.meta, t0_ns=int(t0_ns)))

    def with_meta(self, **changes) -> "InsLog":
        return self.with_streams(meta=replace(self.meta, **changes))


# (set after the dataclass is made: ``imu`` and ``nav`` stay its fields, for ``dataclasses.replace`` and
# ``fields``, and read through these)
InsLog.imu = property(lambda self: self._frame("imu"),
                      doc="The IMU stream as a pandas DataFrame (index ``t_s``; GYRO and ACCEL columns).")
InsLog.nav = property(lambda self: self._frame("nav"),
                      doc="The navigation stream as a pandas DataFrame (index ``t_s``; QUAT, VEL and POS columns).")
