"""MAVLink telemetry logs (``.tlog``, as Mission Planner / QGroundControl / MAVProxy record them).

A tlog is a sequence of records ``[8-byte big-endian uint64 receive time, UNIX us][MAVLink v1 (0xFE)
or v2 (0xFD) frame]``. MAVLink is NED / FRD already: no axis conversion here.

Streams read (units converted to SI here, and only here):

* IMU: ``HIGHRES_IMU`` (rad/s, m/s^2, ``time_usec``; instance ``id``), ``SCALED_IMU``,
  ``SCALED_IMU2``, ``SCALED_IMU3`` (mG, mrad/s, ``time_boot_ms``), ``RAW_IMU`` (ArduPilot sends it in
  mG / mrad/s like SCALED_IMU, ``time_usec``).
* attitude: ``ATTITUDE_QUATERNION`` (q1..q4 = w,x,y,z), ``ATTITUDE`` (roll/pitch/yaw rad),
  ``AHRS2`` / ``AHRS3`` (roll/pitch/yaw rad; no time field: their receive stamp is mapped onto the
  unit's clock, with a warning).
* velocity: ``GLOBAL_POSITION_INT`` (vx/vy/vz cm/s NED), ``LOCAL_POSITION_NED`` (vx/vy/vz m/s).
* position: ``GLOBAL_POSITION_INT`` (degE7, alt mm MSL), ``AHRS2``/``AHRS3`` (degE7, m),
  ``GPS_RAW_INT`` (degE7, mm).

Clocks (selector ``time=``):

* ``time=message`` (default): each message's own time field. ``time_usec`` is UNIX time when larger
  than 1e15 us, time since boot otherwise (MAVLink spec); ``time_boot_ms`` is boot time.
  ``SYSTEM_TIME`` (time_unix_usec, time_boot_ms) of the same system relates boot to UNIX time, so all
  of one unit's streams land on one clock: ``epoch`` when SYSTEM_TIME carries UNIX time, else ``boot``.
  Reported in ``meta.stamp_source``.
* ``time=receive``: the tlog's receive stamps (the ground station's UNIX clock, includes the
  telemetry link's delay and jitter).

Selector keys: ``imu=HIGHRES_IMU|HIGHRES_IMU[1]|SCALED_IMU|SCALED_IMU2|SCALED_IMU3|RAW_IMU``,
``att=ATTITUDE_QUATERNION|ATTITUDE|AHRS2|AHRS3``, ``vel=GLOBAL_POSITION_INT|LOCAL_POSITION_NED``,
``pos=GLOBAL_POSITION_INT|AHRS2|AHRS3|GPS_RAW_INT``, ``time=message|receive``, ``sysid=N``,
``compid=N``; ``nav=X`` sets att/vel/pos to X where X has them; ``none`` drops a group.

Decoding is vectorised: frames are walked once (numba), CRCs checked column-wise, payloads gathered
per message id and viewed through numpy structured dtypes built from pymavlink's own message classes
(field order, types, CRC_EXTRA). pymavlink stays the reference the tests compare against.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from logtools.conventions import euler_from_quat, quat_from_euler
from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers.assemble import Stream, assemble_inslog
from parsers.atomic import atomic_path
from parsers.base import (DAMAGED_HEAD_SEARCH_BYTES, Inventory, Selector, StreamInfo, check_readable, rate_of,
                          release_free_memory)
from parsers.mavlink_common import (dtype_from_struct, gather_rows, index_tlog_frames, records_view,
                                    scatter_rows, walk_tlog, x25_crc_block)

NAME = "tlog"
EXTENSIONS = (".tlog",)

G0 = 9.80665
EPOCH_US_THRESHOLD = 1e15  # MAVLink: time_usec above this is UNIX time
MG_TO_M_S2 = G0 * 1e-3
MRAD_TO_RAD = 1e-3

IMU_PREF = ("HIGHRES_IMU", "SCALED_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")
ATT_PREF = ("ATTITUDE_QUATERNION", "ATTITUDE", "AHRS2", "AHRS3")
VEL_PREF = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED")
POS_PREF = ("GLOBAL_POSITION_INT", "AHRS2", "AHRS3", "GPS_RAW_INT")
#: name -> (gyro scale to rad/s, accel scale to m/s^2)
IMU_SCALE = {"HIGHRES_IMU": (1.0, 1.0), "SCALED_IMU": (MRAD_TO_RAD, MG_TO_M_S2),
             "SCALED_IMU2": (MRAD_TO_RAD, MG_TO_M_S2), "SCALED_IMU3": (MRAD_TO_RAD, MG_TO_M_S2),
             "RAW_IMU": (MRAD_TO_RAD, MG_TO_M_S2)}
#: attitude messages whose body rates (rollspeed, pitchspeed, yawspeed; rad/s) can stand in for a
#: gyro when a tlog has no IMU message (``imu=ATTITUDE``): angular rate only, no specific force
RATE_ONLY = ("ATTITUDE", "ATTITUDE_QUATERNION")
KIND = {**{n: "imu" for n in IMU_PREF}, "ATTITUDE_QUATERNION": "att", "ATTITUDE": "att",
        "AHRS2": "att", "AHRS3": "att", "GLOBAL_POSITION_INT": "vel", "LOCAL_POSITION_NED": "vel",
        "GPS_RAW_INT": "pos", "SYSTEM_TIME": "other"}
DEFAULT_TIME = "message"


# ---- pymavlink message definitions -> numpy --------------------------------------------------
DIALECT_MODULE = "pymavlink.dialects.v20.ardupilotmega"
_TABLE_LAYOUT = 1  # (the cached table's layout: a new one is made when this changes)


@lru_cache(maxsize=1)
def _dialect():
    from pymavlink.dialects.v20 import ardupilotmega
    return ardupilotmega


def dialect_table_from_module(mod) -> dict:
    """What the reader takes from pymavlink's dialect: {"by_id": {id: (name, CRC extra, struct format,
    field names)}, "by_name": {name: id}} (the MAVLINK_MSG_ID_ constants)."""
    by_id = {int(mid): (cls.msgname, int(cls.crc_extra), cls.unpacker.format, list(cls.ordered_fieldnames))
             for mid, cls in mod.mavlink_map.items()}
    by_name = {k[len("MAVLINK_MSG_ID_"):]: int(v) for k, v in vars(mod).items()
               if k.startswith("MAVLINK_MSG_ID_") and isinstance(v, int)}
    return {"by_id": by_id, "by_name": by_name}


@lru_cache(maxsize=1)
def _table() -> dict:
    """:func:`dialect_table_from_module` of pymavlink's dialect, kept in tapost's cache directory and keyed
    on the dialect module's file (path, size, modification time): importing the dialect costs about 30 ms of
    every run that reads a tlog, the table's file about 1 ms. Made (and written, atomically) where it is
    missing or stale; where the directory cannot be written, made every time."""
    import importlib.util
    import json
    import os

    from logtools import jit

    try:
        origin = importlib.util.find_spec(DIALECT_MODULE).origin
        st = os.stat(origin)
        key = f"{_TABLE_LAYOUT}|{origin}|{st.st_size}|{st.st_mtime_ns}"
    except (ImportError, AttributeError, OSError, ValueError):
        return dialect_table_from_module(_dialect())
    path = os.path.join(jit.cache_home(), "mavlink-dialect.json")
    try:
        with open(path) as fh:
            saved = json.load(fh)
        if saved.get("key") == key:
            return {"by_id": {int(k): tuple(v) for k, v in saved["by_id"].items()}, "by_name": saved["by_name"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    table = dialect_table_from_module(_dialect())
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with atomic_path(path) as tmp, open(tmp, "w") as fh:
            json.dump({"key": key, "by_id": {str(k): list(v) for k, v in table["by_id"].items()},
                       "by_name": table["by_name"]}, fh)
    except OSError:
        pass
    return table


@dataclass(frozen=True)
class MsgDef:
    id: int
    name: str
    crc_extra: int
    dtype: np.dtype  # wire layout (ordered fields), packed little-endian
    wire_len: int


@lru_cache(maxsize=None)
def msgdef_by_id(msgid: int) -> MsgDef | None:
    d = _table()["by_id"].get(int(msgid))
    if d is None:
        return None
    name, crc_extra, fmt, names = d
    dt = dtype_from_struct(fmt, list(names))
    return MsgDef(int(msgid), name, int(crc_extra), dt, dt.itemsize)


@lru_cache(maxsize=None)
def msgdef(name: str) -> MsgDef:
    mid = _table()["by_name"].get(name)
    d = msgdef_by_id(mid) if mid is not None else None
    if d is None:
        raise KeyError(name)
    return d


@lru_cache(maxsize=1)
def _crc_extra_table() -> np.ndarray:
    by_id = _table()["by_id"]
    tab = np.full(max(by_id) + 1, -1, dtype=np.int16)
    for mid, d in by_id.items():
        tab[mid] = d[1]
    return tab


# ---- frames ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Frames:
    """Every valid frame of a tlog, columnar. ``pay`` is the payload offset in ``buf``."""

    buf: np.ndarray
    recv_us: np.ndarray
    v2: np.ndarray
    plen: np.ndarray
    sysid: np.ndarray
    compid: np.ndarray
    msgid: np.ndarray
    pay: np.ndarray
    warnings: tuple[str, ...]
    n_corrupt: int

    def rows(self, msgid: int, sysid: int | None = None, compid: int | None = None) -> np.ndarray:
        m = self.msgid == msgid
        if sysid is not None:
            m &= self.sysid == sysid
        if compid is not None:
            m &= self.compid == compid
        return np.flatnonzero(m)

    def decode(self, rows: np.ndarray, d: MsgDef) -> np.ndarray:
        """Structured records (wire dtype) of the frames ``rows`` (zero-padded like pymavlink)."""
        block = gather_rows(self.buf, self.pay[rows], d.wire_len,
                            np.minimum(self.plen[rows], d.wire_len))
        return records_view(block, d.dtype)

    def take(self, msgid: int, sysid: int, compid: int | None = None, *, pop: bool = False
             ) -> tuple[np.ndarray, np.ndarray]:
        """(records, receive us) of ``msgid`` from ``sysid`` (and ``compid``), like :meth:`FrameStore.take`."""
        rows = self.rows(msgid, sysid, compid)
        return self.decode(rows, msgdef_by_id(msgid)), self.recv_us[rows]


def _frame_warnings(skipped: int, resyncs: int, n_bad: int, tail: int, n_unknown: int) -> list[str]:
    warns: list[str] = []
    if skipped:
        warns.append(f"damaged tlog: skipped {skipped} bad bytes ({resyncs + (0 if resyncs else 1)} "
                     f"place(s)) and resynchronised")
    if n_bad:
        warns.append(f"damaged tlog: {n_bad} frame(s) with bad CRC dropped")
    if tail:
        warns.append(f"truncated tlog: last {tail} byte(s) hold an incomplete frame")
    if n_unknown:
        warns.append(f"{n_unknown} frame(s) of message ids unknown to the dialect ignored")
    return warns


def read_frames(path: str, buf: np.ndarray | None = None, engine: str = "auto") -> Frames:
    """Walk, CRC-check and index every frame of a tlog; damage goes into ``warnings``.
    ``engine``: auto (numba when installed) | numba | numpy (column-wise CRC per message group)."""
    if buf is None:
        buf = np.fromfile(path, dtype=np.uint8)
    if len(buf) == 0:
        raise InputError("empty file", path)
    starts, skipped, resyncs, tail = walk_tlog(buf)
    if len(starts) == 0:
        raise InputError("no MAVLink frames found (not a tlog, or damaged beyond use)", path)
    recv, v2, plen, sysid, compid, msgid, pay, status = index_tlog_frames(
        buf, starts, _crc_extra_table(), engine)
    del starts
    ok = status == 0
    known = status != 2
    n_bad = int((known & ~ok).sum())
    n_unknown = int((~known).sum())
    warns = _frame_warnings(skipped, resyncs, n_bad, tail, n_unknown)
    if ok.all():  # no copies of the index columns
        return Frames(buf=buf, recv_us=recv, v2=v2, plen=plen, sysid=sysid, compid=compid, msgid=msgid, pay=pay,
                      warnings=tuple(warns), n_corrupt=n_bad + (1 if skipped else 0))
    keep = ok
    return Frames(buf=buf, recv_us=recv[keep], v2=v2[keep], plen=plen[keep], sysid=sysid[keep],
                  compid=compid[keep], msgid=msgid[keep], pay=pay[keep],
                  warnings=tuple(warns), n_corrupt=n_bad + (1 if skipped else 0))


# ---- the reader's scan: the file in windows, the frames of the messages it reads gathered -------------
#: bytes of the file walked, indexed and gathered at a time (and so about the file's share of the memory)
SCAN_WINDOW = 16 << 20
#: a window ends at least this far before the end of the file (a record and the header after it fit)
_WINDOW_SLACK = 4096


@dataclass
class MessageFrames:
    """The intact frames of one message id, in file order: records (wire dtype, zero-padded like
    pymavlink), receive stamps (UNIX us), system and component ids."""

    rec: np.ndarray
    recv_us: np.ndarray
    sysid: np.ndarray
    compid: np.ndarray

    def select(self, sysid: int, compid: int | None = None) -> np.ndarray | None:
        """Row mask of one system (and component); None when every row is it."""
        m = self.sysid == sysid
        if compid is not None:
            m &= self.compid == compid
        return None if m.all() else m


@dataclass
class FrameStore:
    """What :func:`scan_frames` keeps of a tlog: the catalog counts of every intact frame, the frames of the
    message ids it was asked for (:class:`MessageFrames`), the damage warnings."""

    counts: dict[tuple[int, int, str], int]
    n_valid: int
    by_id: dict[int, MessageFrames]
    warnings: tuple[str, ...]
    n_corrupt: int

    def take(self, msgid: int, sysid: int, compid: int | None = None, *, pop: bool = False
             ) -> tuple[np.ndarray, np.ndarray]:
        """(records, receive us) of ``msgid`` from ``sysid`` (and ``compid``); ``pop``: the store lets go of
        them (a reader that reads each stream once keeps no second copy)."""
        mf = self.by_id.pop(msgid, None) if pop else self.by_id.get(msgid)
        d = msgdef_by_id(msgid)
        if mf is None:
            return np.zeros(0, dtype=d.dtype), np.zeros(0, np.int64)
        m = mf.select(sysid, compid)
        if m is None:
            return mf.rec, mf.recv_us
        if pop:  # the other systems' rows stay for later takes
            self.by_id[msgid] = mf
        return mf.rec[m], mf.recv_us[m]


class _Growing:
    """Rows appended window by window into one preallocated array, grown when full. The capacity is an
    estimate from the rows per byte so far; what is never filled is never touched (np.empty pages are not
    resident), so a generous estimate costs no memory, and the rows need no concatenation at the end."""

    def __init__(self, dtype):
        self.arr = np.empty(0, dtype=dtype)
        self.n = 0

    def append(self, rows: np.ndarray, estimate: int) -> None:
        need = self.n + len(rows)
        if need > len(self.arr):
            grown = np.empty(max(need, int(estimate), 2 * len(self.arr)), dtype=self.arr.dtype)
            grown[:self.n] = self.arr[:self.n]
            self.arr = grown
        self.arr[self.n:need] = rows
        self.n = need

    def result(self) -> np.ndarray:
        return self.arr[:self.n]


def _kind_ids() -> tuple[int, ...]:
    return tuple(sorted(msgdef(n).id for n in KIND))


#: the fields this reader reads of any message (time fields, instance id, IMU axes, attitude, rates,
#: velocity, position, SYSTEM_TIME's UNIX time): what :func:`scan_frames` keeps with ``project``
READ_FIELDS = frozenset({
    "time_usec", "time_boot_ms", "time_unix_usec", "id", "xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro",
    "q1", "q2", "q3", "q4", "roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed",
    "vx", "vy", "vz", "lat", "lon", "lng", "alt", "altitude"})


@lru_cache(maxsize=None)
def _read_dtype(msgid: int) -> np.dtype:
    """The packed dtype of the READ_FIELDS of a message (its wire dtype where it has no other field)."""
    d = msgdef_by_id(msgid)
    return np.dtype([(n, d.dtype.fields[n][0]) for n in d.dtype.names if n in READ_FIELDS])


def _project(rec: np.ndarray, dtype: np.dtype) -> np.ndarray:
    if rec.dtype == dtype:
        return rec
    out = np.empty(len(rec), dtype=dtype)
    for n in dtype.names:
        out[n] = rec[n]
    return out


def scan_frames(path: str, want: tuple[int, ...] | None = None, engine: str = "auto",
                window: int = SCAN_WINDOW, project: bool = False) -> FrameStore:
    """Walk, CRC-check and index a tlog window by window (memory-mapped, the pages behind let go), keeping
    only the catalog counts and the frames of the message ids ``want`` (default: every message this reader
    knows, ``KIND``); ``project``: of their records only the READ_FIELDS. The same frames, counts and
    warnings as :func:`read_frames`, without the whole file and its index columns in memory."""
    from parsers.filemap import FileMap
    from parsers.mavlink_common import walk_tlog_part

    want = _kind_ids() if want is None else tuple(want)
    tab = _crc_extra_table()
    key_counts: dict[int, int] = {}
    grow: dict[int, tuple[_Growing, _Growing, _Growing, _Growing]] = {}
    skipped = resyncs = n_bad = n_unknown = n_valid = n_found = 0
    with FileMap(path) as fm:
        buf = fm.array
        n = len(buf)
        if n == 0:
            raise InputError("empty file", path)
        i, in_sync, prev_t = 0, False, -1
        while True:
            i0 = i
            stop = n if n - i <= window + _WINDOW_SLACK else i + window
            starts, sk, rs, i, in_sync, prev_t = walk_tlog_part(buf, i, stop, in_sync, prev_t, n_found > 0)
            skipped += sk
            resyncs += rs
            n_found += len(starts)
            if len(starts):
                recv, _v2, plen, sysid, compid, msgid, pay, status = index_tlog_frames(buf, starts, tab, engine)
                del starts, _v2
                ok = status == 0
                known = status != 2
                n_bad += int((known & ~ok).sum())
                n_unknown += int((~known).sum())
                if not ok.all():
                    recv, plen, sysid, compid, msgid, pay = (a[ok] for a in (recv, plen, sysid, compid, msgid, pay))
                n_valid += len(msgid)
                key = (sysid << 32) | (compid << 24) | msgid
                for k, c in zip(*(a.tolist() for a in np.unique(key, return_counts=True))):
                    key_counts[k] = key_counts.get(k, 0) + c
                del key
                # rows still to come, from this window's rows per byte (+25 %): the arrays' first capacity
                scale = 1.25 * (n - i0) / max(i - i0, 1)
                for mid in np.intersect1d(np.unique(msgid), np.asarray(want, np.int64)).tolist():
                    d = msgdef_by_id(mid)
                    rows = np.flatnonzero(msgid == mid)
                    block = gather_rows(buf, pay[rows], d.wire_len, np.minimum(plen[rows], d.wire_len))
                    rdt = _read_dtype(mid) if project else d.dtype
                    g = grow.get(mid)
                    if g is None:
                        g = grow[mid] = (_Growing(rdt), _Growing(np.int64), _Growing(np.uint8), _Growing(np.uint8))
                    est = g[0].n + len(rows) * scale + 1024
                    rec = _project(records_view(block, d.dtype), rdt)
                    for col, vals in zip(g, (rec, recv[rows], sysid[rows], compid[rows])):
                        col.append(vals, est)
                    del block, rows, rec
                del recv, plen, sysid, compid, msgid, pay, status, ok, known
            fm.release_before(i - _WINDOW_SLACK)
            if stop == n:
                break
        tail = n - i
        del buf
    if n_found == 0:
        raise InputError("no MAVLink frames found (not a tlog, or damaged beyond use)", path)
    counts: dict[tuple[int, int, str], int] = {}
    for k in sorted(key_counts):
        d = msgdef_by_id(k & 0xFFFFFF)
        if d is not None and d.name in KIND:
            counts[(k >> 32, (k >> 24) & 0xFF, d.name)] = key_counts[k]
    by_id = {mid: MessageFrames(*(col.result() for col in grow.pop(mid))) for mid in sorted(grow)}
    warns = _frame_warnings(skipped, resyncs, n_bad, tail, n_unknown)
    return FrameStore(counts=counts, n_valid=n_valid, by_id=by_id, warnings=tuple(warns),
                      n_corrupt=n_bad + (1 if skipped else 0))


# ---- sniff -------------------------------------------------------------------------------------
def sniff(head: bytes, path: str) -> bool:
    """A tlog: at offset 0, records chain with valid magic and plausible, close receive stamps."""
    buf = np.frombuffer(head, dtype=np.uint8)
    n = len(buf)
    i, good, prev = 0, 0, None
    while good < 4 and i + 16 <= n:
        magic = buf[i + 8]
        if magic not in (0xFE, 0xFD):
            return False
        plen = int(buf[i + 9])
        size = 16 + plen if magic == 0xFE else 20 + plen + (13 if buf[i + 10] & 1 else 0)
        t = int.from_bytes(bytes(buf[i:i + 8]), "big")
        if t >= 1 << 62 or (prev is not None and not (prev - 60e6 <= t <= prev + 86400e6)):
            return False
        prev = t
        good += 1
        i += size
    return good >= 4 or (good >= 1 and i >= n)


#: the largest tlog record: the 8-byte receive stamp and a MAVLink 2 frame with a 255-byte payload and a signature
_MAX_RECORD_BYTES = 8 + 12 + 255 + 13


def sniff_damaged(head: bytes, path: str) -> bool:
    """A tlog whose first bytes are damaged, or with bytes put before it: four records chain (as :func:`sniff`
    wants them) from an offset up to DAMAGED_HEAD_SEARCH_BYTES (the walk skips the bytes before, and says so).
    Only offsets with room for four records after them: one record running past the end of the bytes read is
    enough for :func:`sniff` at a file's start, and random bytes held such a "record" near their end."""
    last = min(len(head) - 4 * _MAX_RECORD_BYTES, DAMAGED_HEAD_SEARCH_BYTES)
    buf = np.frombuffer(head, np.uint8)[9:max(last + 9, 9)]
    magic = np.flatnonzero((buf == 0xFE) | (buf == 0xFD)) + 1
    return any(sniff(head[i:], path) for i in magic.tolist())


# ---- streams and clocks ------------------------------------------------------------------------
@dataclass(frozen=True)
class RawStream:
    """One message stream of one (sysid, compid): decoded records + receive stamps."""

    name: str
    sysid: int
    compid: int
    rec: np.ndarray
    recv_ns: np.ndarray


def _time_field(name: str) -> str | None:
    fields = msgdef(name).dtype.names
    for f in ("time_usec", "time_boot_ms"):
        if f in fields:
            return f
    return None


def _msg_time(s: RawStream) -> tuple[np.ndarray, np.ndarray]:
    """(kind, t_ns) per sample: kind 0 = boot, 1 = epoch, 2 = receive (no time field)."""
    tf = _time_field(s.name)
    n = len(s.rec)
    if tf is None:
        return np.full(n, 2, np.int8), s.recv_ns.copy()
    if tf == "time_boot_ms":  # whole ms elapsed (truncated, BOOT_MS_NS): the instant lies in [ms, ms + 1), read mid
        return np.zeros(n, np.int8), s.rec[tf].astype(np.int64) * BOOT_MS_NS + BOOT_MS_NS // 2
    us = s.rec[tf].astype(np.uint64)
    epoch = us > EPOCH_US_THRESHOLD
    return epoch.astype(np.int8), us.astype(np.int64) * 1000


#: SYSTEM_TIME's time_boot_ms counts the whole milliseconds elapsed since boot (ArduPilot's millis(), PX4's
#: hrt_absolute_time() / 1000: truncated), taken with time_unix_usec at one instant that lies anywhere in
#: that millisecond: each record's time_unix_usec - time_boot_ms is the offset plus that fraction, in
#: [0, 1 ms). The median alone was half a millisecond too large on average (a tlog slave's latency +0.5 ms,
#: 80 sigma; a master's -0.5 ms)
BOOT_MS_NS = 1_000_000
#: ... the records' fractions spread over the millisecond (a unit's scheduler: they vary) bound the offset from
#: both sides; records sent in step with the millisecond (a fixed phase) leave it anywhere in one millisecond
#: (sigma 0.29 ms). The spread is read between these quantiles of the records within 2 ms of their median
#: (a clock step of the unit's UNIX time elsewhere in the log not counted)
SYSTEM_TIME_SPREAD_QUANTILES = (0.02, 0.98)


def _system_time_offset_ns(fr: "Frames | FrameStore", sysid: int, compid: int) -> int | None:
    """UNIX ns - boot ns from SYSTEM_TIME of this system (same component preferred): :func:`system_time_offset`."""
    got = system_time_offset(fr, sysid, compid)
    return None if got is None else got[0]


def system_time_offset(fr: "Frames | FrameStore", sysid: int, compid: int) -> tuple[int, float] | None:
    """(UNIX ns - boot ns, its sigma in s) from SYSTEM_TIME of this system (same component preferred). Each
    record's d = time_unix_usec - time_boot_ms is the offset plus the fraction of a millisecond its instant
    lay past the whole ms (``BOOT_MS_NS``; 0 to 999 us): the offset lies in [max d - 999 us, min d], taken at
    the middle,
    its sigma that interval's width / sqrt(12) (``SYSTEM_TIME_SPREAD_QUANTILES`` for max and min)."""
    d = msgdef("SYSTEM_TIME")
    r, _recv = fr.take(d.id, sysid, compid)
    if len(r) == 0:
        r, _recv = fr.take(d.id, sysid)
    if len(r) == 0:
        return None
    unix = r["time_unix_usec"].astype(np.int64)
    good = unix > EPOCH_US_THRESHOLD
    if not good.any():
        return None
    d = np.sort(unix[good] * 1000 - r["time_boot_ms"][good].astype(np.int64) * BOOT_MS_NS)  # (int64: float64
    med = d[len(d) // 2]                                                                  # loses ns at 1e18)
    d = d[np.abs(d - med) < 2 * BOOT_MS_NS]
    q0, q1 = SYSTEM_TIME_SPREAD_QUANTILES
    lo, hi = d[int(q0 * (len(d) - 1))], d[int(np.ceil(q1 * (len(d) - 1)))]
    span = BOOT_MS_NS - 1000  # the fraction in time_unix_usec's whole microseconds: 0 .. 999 us
    width = max(span - int(hi - lo), 0)
    return int(lo + hi - span) // 2, width / np.sqrt(12.0) * 1e-9


@dataclass(frozen=True)
class ClockPlan:
    clock: str
    source: str
    warnings: tuple[str, ...]
    #: offset (ns) added to a sample of kind k (0 boot, 1 epoch, 2 receive) to put it on ``clock``
    add_ns: tuple[int, int, int]


def _low(x: np.ndarray) -> int:
    """The 1st percentile, in integers (the element a sort would put at len // 100; partitioned in place:
    ``x`` is the caller's scratch array)."""
    if not len(x):
        return 0
    k = len(x) // 100
    x.partition(k)
    return int(x[k])


#: the stamp source of a tlog read on its receive stamps by choice (selector time=receive)
RECEIVE_CHOSEN = "tlog receive time (ground station UNIX clock, includes link delay)"


def plan_clock(streams: list[tuple[np.ndarray, np.ndarray, np.ndarray]], sys_off: int | None,
               mode: str) -> ClockPlan:
    """``streams``: (kind, t_ns, recv_ns) per selected stream -> how to put all on one clock."""
    if mode == "receive":
        return ClockPlan("epoch", RECEIVE_CHOSEN, (), (0, 0, 0))
    kinds = set()
    for k, _, _ in streams:
        kinds |= set(np.unique(k).tolist())
    # receive - message time, per kind: how far the ground station's clock is from each clock
    lag = {}
    for kind in (0, 1):
        d, same = [], {}  # a stream given twice (vel and pos of one message): its lags once, counted twice
        for k, t, r in streams:
            m = k == kind
            if m.any():
                key = (id(k), id(t), id(r))
                if key not in same:
                    same[key] = (r - t) if m.all() else (r[m] - t[m])
                d.append(same[key])
            del m
        if d:
            lag[kind] = _low(np.concatenate(d))
    warns: list[str] = []
    if sys_off is not None:
        clock, add = "epoch", {0: sys_off, 1: 0}
        src = "MAVLink message time fields; boot time mapped to UNIX time by SYSTEM_TIME"
    elif kinds <= {1, 2} and 1 in kinds:
        clock, add = "epoch", {0: 0, 1: 0}
        src = "MAVLink message time fields (time_usec, UNIX time)"
    elif 0 in kinds and 1 in kinds:
        # no SYSTEM_TIME, but the unit stamps some streams in UNIX time (HIGHRES_IMU.time_usec on a GPS-synced
        # autopilot): keep UNIX time, the clock a master is most likely on, and map the boot streams onto it
        # through the receive stamps (t_unix = t_boot + lag_boot - lag_unix)
        clock, add = "epoch", {0: lag[0] - lag[1], 1: 0}
        src = "MAVLink message time fields; boot time mapped to UNIX time through the tlog receive stamps"
        warns.append("streams mix UNIX and boot time and there is no SYSTEM_TIME: boot stamps mapped to "
                     "UNIX time through the receive stamps (offset uncertain by the link delay's spread)")
    elif 0 in kinds:
        clock, add = "boot", {0: 0, 1: 0}
        src = "MAVLink message time fields (time since boot)"
    else:
        return ClockPlan("epoch", "tlog receive time (selected messages have no time field)", (),
                         (0, 0, 0))
    if 2 in kinds and not lag:
        # only messages without a time field selected (att=AHRS2 with imu=none; the clock is then UNIX time,
        # SYSTEM_TIME's: a boot clock needs a timed stream): nothing to map the receive stamps by, used as is
        add2 = 0
        warns.append("message(s) without a time field (AHRS2/AHRS3) stamped with the tlog's receive time "
                     "(includes the link delay and its jitter)")
    elif 2 in kinds:
        ref = 0 if 0 in lag else 1
        # receive -> clock: t_clock = recv - lag[ref] + add[ref]
        add2 = -lag[ref] + add[ref]
        warns.append("message(s) without a time field (AHRS2/AHRS3) stamped with receive time mapped "
                     "onto the unit's clock (link delay jitter remains)")
    else:
        add2 = 0
    return ClockPlan(clock, src, tuple(warns), (int(add[0]), int(add[1]), int(add2)))


def apply_clock(plan: ClockPlan, kind: np.ndarray, t_ns: np.ndarray, recv_ns: np.ndarray,
                mode: str) -> np.ndarray:
    if mode == "receive":
        return recv_ns
    return t_ns + np.asarray(plan.add_ns, dtype=np.int64)[kind]


# ---- selection ---------------------------------------------------------------------------------
_INST = re.compile(r"^([A-Z0-9_]+)(?:\[(\d+)\])?$")


def _parse_name(text: str, allowed: tuple[str, ...], key: str, path: str) -> tuple[str, int | None]:
    m = _INST.match(text.strip().upper())
    if not m or m.group(1) not in allowed:
        raise InputError(f"selector {key}={text}: not one of {', '.join(allowed)}", path)
    return m.group(1), (int(m.group(2)) if m.group(2) else None)


@dataclass(frozen=True)
class Catalog:
    """Which (sysid, compid, message) streams a tlog holds, with counts."""

    counts: dict[tuple[int, int, str], int]

    def units(self) -> list[tuple[int, int]]:
        return sorted({(s, c) for (s, c, n) in self.counts if KIND.get(n) in ("imu", "att")})

    def has(self, sysid: int, compid: int, name: str) -> bool:
        return self.counts.get((sysid, compid, name), 0) > 0


def catalog(fr: "Frames | FrameStore") -> Catalog:
    if isinstance(fr, FrameStore):
        return Catalog(dict(fr.counts))
    counts: dict[tuple[int, int, str], int] = {}
    if len(fr.msgid) == 0:
        return Catalog(counts)
    key = (fr.sysid << 32) | (fr.compid << 24) | fr.msgid
    u, c = np.unique(key, return_counts=True)
    for k, n in zip(u.tolist(), c.tolist()):
        d = msgdef_by_id(k & 0xFFFFFF)
        if d is not None and d.name in KIND:
            counts[(k >> 32, (k >> 24) & 0xFF, d.name)] = n
    return Catalog(counts)


def unit_selectors(cat: Catalog) -> list[dict[str, str]]:
    """Ready selectors, one per unit: IMU k paired with attitude source k of each system."""
    out = []
    units = cat.units()
    multi = len(units) > 1
    for sysid, compid in units:
        def have(n):
            return cat.has(sysid, compid, n)
        imus = [n for n in ("HIGHRES_IMU",) if have(n)]
        first = next((n for n in ("SCALED_IMU", "RAW_IMU") if have(n)), None)
        imus += ([first] if first else []) + [n for n in ("SCALED_IMU2", "SCALED_IMU3") if have(n)]
        main_att = next((n for n in ("ATTITUDE_QUATERNION", "ATTITUDE") if have(n)), None)
        atts = ([main_att] if main_att else []) + [n for n in ("AHRS2", "AHRS3") if have(n)]
        vel = next((n for n in VEL_PREF if have(n)), None)
        pos = next((n for n in POS_PREF if have(n)), None)
        for k in range(max(len(imus), len(atts))):
            sel: dict[str, str] = {}
            if multi:
                sel["sysid"] = str(sysid)
                sel["compid"] = str(compid)
            if k < len(imus):
                sel["imu"] = imus[k]
            if k < len(atts):
                sel["att"] = atts[k]
            if k == 0:
                if vel:
                    sel["vel"] = vel
                if pos:
                    sel["pos"] = pos
            if "imu" not in sel and sel.get("att") in NO_TIME_FIELD and "vel" not in sel:
                # an attitude-only unit whose attitude has no time field: its stamps are the tlog's receive
                # times (link delay, bursts), and the latency would rest on them alone: not offered
                continue
            if "imu" in sel or "att" in sel:
                out.append(sel)
    return out


NO_TIME_FIELD = ("AHRS2", "AHRS3")  # messages stamped with their receive time (see _stamp_kinds)


def _sel_text(sel: dict[str, str]) -> str:
    return ",".join(f"{k}={v}" for k, v in sel.items())


def _resolve(path: str, selector: Selector, cat: Catalog) -> tuple[dict[str, str], list[str]]:
    """Selector -> dict(sysid, compid, imu, att, vel, pos, time); default unit when empty."""
    notes: list[str] = []
    allowed = {"imu", "att", "vel", "pos", "nav", "time", "sysid", "compid", "clock"}
    for k, _ in selector.items:
        if k not in allowed:
            raise InputError(f"selector key {k!r} not understood by tlog (use {', '.join(sorted(allowed))})",
                             path)
    units = cat.units()
    if not units:
        raise InputError("no IMU or attitude messages (HIGHRES_IMU, SCALED_IMU*, RAW_IMU, ATTITUDE*, "
                         "AHRS2/3) in this tlog", path)
    sysid = selector.get("sysid")
    compid = selector.get("compid")
    try:
        sysid_i = int(sysid) if sysid is not None else None
        compid_i = int(compid) if compid is not None else None
    except ValueError:
        raise InputError(f"selector sysid/compid must be integers, got {sysid!r}/{compid!r}", path) from None
    cands = [u for u in units if (sysid_i is None or u[0] == sysid_i) and (compid_i is None or u[1] == compid_i)]
    if not cands:
        raise InputError(f"no IMU/attitude messages from sysid={sysid} compid={compid} "
                         f"(present: {', '.join(f'{s}/{c}' for s, c in units)})", path)
    explicit = {k for k, _ in selector.items if k in ("imu", "att", "vel", "pos", "nav")}
    out: dict[str, str] = {}
    if not explicit:
        presets = [s for s in unit_selectors(cat)
                   if all(str(v) == s.get(k, str(v)) for k, v in (("sysid", sysid_i), ("compid", compid_i))
                          if v is not None)]
        complete = [s for s in presets if "imu" in s and "att" in s]
        pick = (complete or presets)[0]
        out.update({k: v for k, v in pick.items() if k in ("imu", "att", "vel", "pos")})
        s_c = next(u for u in cands if all(str(x) == pick.get(k, str(x)) for k, x in
                                           (("sysid", u[0]), ("compid", u[1]))))
        out["sysid"], out["compid"] = str(s_c[0]), str(s_c[1])
        if len(presets) > 1 or len(units) > 1:
            others = [_sel_text(s) for s in unit_selectors(cat) if _sel_text(s) != _sel_text(pick)]
            notes.append(f"no selector given: picked sysid={s_c[0]} {_sel_text(pick)}"
                         + (f" (other units: {'; '.join(others)})" if others else ""))
    else:
        nav = selector.get("nav")
        for key, allowed_names in (("imu", IMU_PREF + RATE_ONLY), ("att", ATT_PREF), ("vel", VEL_PREF),
                                   ("pos", POS_PREF)):
            v = selector.get(key)
            if v is None and nav is not None and _INST.match(nav.upper()) and \
                    _INST.match(nav.upper()).group(1) in allowed_names:
                v = nav
            if v is None or v.lower() == "none":
                continue
            _parse_name(v, allowed_names, key, path)
            out[key] = v.upper()
        # the unit: the system/component holding the selected streams
        names = [_INST.match(v).group(1) for k, v in out.items() if k in ("imu", "att", "vel", "pos")]
        holding = [u for u in cands if all(cat.has(u[0], u[1], n) for n in names)]
        if not holding:
            missing = [n for n in names if not any(cat.has(u[0], u[1], n) for u in cands)]
            raise InputError(f"selector {selector}: no {', '.join(missing) or 'matching'} stream in this "
                             f"tlog (use `tapost inspect` to list streams)", path)
        out["sysid"], out["compid"] = str(holding[0][0]), str(holding[0][1])
    mode = (selector.get("time") or selector.get("clock") or DEFAULT_TIME).lower()
    if mode not in ("message", "receive"):
        raise InputError(f"selector time={mode}: use time=message or time=receive", path)
    out["time"] = mode
    return out, notes


def _raw(fr: "Frames | FrameStore", name: str, sysid: int, compid: int, *, pop: bool = False) -> RawStream:
    d = msgdef(name)
    rec, recv_us = fr.take(d.id, sysid, compid, pop=pop)
    return RawStream(name, sysid, compid, rec, recv_us * 1000)


def _instance_filter(s: RawStream, inst: int | None, notes: list[str]) -> RawStream:
    field = "id" if "id" in s.rec.dtype.names else None
    if field is None or len(s.rec) == 0:
        return s
    ids = s.rec[field]
    present = np.unique(ids)
    if inst is None:
        if len(present) <= 1:
            return s
        inst = int(present[0])
        notes.append(f"{s.name} holds instances {present.tolist()}: picked {s.name}[{inst}]")
    keep = ids == inst
    if not keep.any():
        raise InputError(f"{s.name}[{inst}]: no such instance (present: {present.tolist()})")
    return RawStream(s.name, s.sysid, s.compid, s.rec[keep], s.recv_ns[keep])


def _imu_values(s: RawStream) -> tuple[np.ndarray, np.ndarray]:
    g_s, a_s = IMU_SCALE[s.name]
    r = s.rec
    gyro = _columns(r, ("xgyro", "ygyro", "zgyro"))
    gyro *= g_s  # in place: the same products as ``gyro * g_s``, without a second array
    acc = _columns(r, ("xacc", "yacc", "zacc"))
    acc *= a_s
    return gyro, acc


def _columns(r: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """``np.column_stack([r[n] for n in names]).astype(float)``, filled in place (no intermediate copy)."""
    out = np.empty((len(r), len(names)))
    for j, n in enumerate(names):
        out[:, j] = r[n]
    return out


def _quat_values(s: RawStream) -> np.ndarray:
    r = s.rec
    if s.name == "ATTITUDE_QUATERNION":
        return _columns(r, ("q1", "q2", "q3", "q4"))
    rpy = _columns(r, ("roll", "pitch", "yaw"))
    return quat_from_euler(rpy)


def _vel_values(s: RawStream) -> np.ndarray:
    r = s.rec
    v = _columns(r, ("vx", "vy", "vz"))
    if s.name == "GLOBAL_POSITION_INT":
        v *= 0.01
    return v


def _pos_values(s: RawStream) -> tuple[np.ndarray, np.ndarray]:
    r = s.rec
    vals = np.empty((len(r), 3))  # the products ``r["lat"] * 1e-7`` ... written in place
    if s.name in ("AHRS2", "AHRS3"):
        np.multiply(r["lat"], 1e-7, out=vals[:, 0])
        np.multiply(r["lng"], 1e-7, out=vals[:, 1])
        vals[:, 2] = r["altitude"]
    else:
        np.multiply(r["lat"], 1e-7, out=vals[:, 0])
        np.multiply(r["lon"], 1e-7, out=vals[:, 1])
        np.multiply(r["alt"], 1e-3, out=vals[:, 2])
    valid = ~((r["lat"] == 0) & ((r["lng"] if "lng" in r.dtype.names else r["lon"]) == 0))
    return vals, valid


def load(path: str, selector: Selector) -> InsLog:
    check_readable(path)
    fr = scan_frames(path, project=True)
    cat = catalog(fr)
    sel, notes = _resolve(path, selector, cat)
    sysid, compid, mode = int(sel["sysid"]), int(sel["compid"]), sel["time"]
    warns = list(fr.warnings) + notes
    picked: dict[str, RawStream] = {}
    raws: dict[str, RawStream] = {}  # one per message (vel and pos both GLOBAL_POSITION_INT: one stream)
    for key in ("imu", "att", "vel", "pos"):
        if key not in sel:
            continue
        m = _INST.match(sel[key])
        name, inst = m.group(1), (int(m.group(2)) if m.group(2) else None)
        s = raws.get(name) or raws.setdefault(name, _raw(fr, name, sysid, compid))
        if len(s.rec) == 0:
            raise InputError(f"no {name} messages from sysid={sysid} compid={compid}", path)
        try:
            picked[key] = _instance_filter(s, inst, warns)
        except InputError as exc:
            raise InputError(exc.problem, path) from None
        del s
    sys_time = system_time_offset(fr, sysid, compid)
    sys_off = None if sys_time is None else sys_time[0]
    fr.by_id.clear()  # what is left of the frames is in ``picked``: each stream goes once read below
    raws.clear()
    release_free_memory()  # the scan's window temporaries
    by_stream: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # the same stream twice: one timing
    timing = {k: by_stream.get(id(s)) or by_stream.setdefault(id(s), _msg_time(s)) for k, s in picked.items()}
    plan = plan_clock([(k_, t_, s.recv_ns) for (k_, t_), s in
                       ((timing[k], picked[k]) for k in picked)], sys_off, mode)
    warns += list(plan.warnings)
    # boot stamps put on UNIX time by SYSTEM_TIME carry its offset's sigma
    mapped = {k: (sys_time is not None and mode != "receive" and plan.add_ns[0] == sys_off
                  and bool(np.any(timing[k][0] == 0))) for k in timing}
    map_sigma = {k: sys_time[1] if mapped[k] else 0.0 for k in timing}
    map_off = {k: int(sys_off) if mapped[k] else None for k in timing}

    del by_stream

    made: dict[int, np.ndarray] = {}  # vel and pos of one stream: one stamp array (until both are made)

    def stamps(key):
        k_, t_ = timing.pop(key)
        shared = sum(1 for kt in timing.values() if kt[1] is t_)
        t = made.pop(id(t_), None)
        if t is None:
            t = apply_clock(plan, k_, t_, picked[key].recv_ns, mode)
        if shared:
            made[id(t_)] = t
        return t

    def resolution(key) -> float:  # time_boot_ms stamps are whole milliseconds
        return 1e-3 if mode != "receive" and _time_field(picked[key].name) == "time_boot_ms" else 0.0

    kw: dict[str, Stream] = {}
    if "imu" in picked:
        s = picked["imu"]
        t, res = stamps("imu"), resolution("imu")
        if s.name in RATE_ONLY:
            r = s.rec
            gyro = _columns(r, ("rollspeed", "pitchspeed", "yawspeed"))
            kw["gyro"] = Stream(t, gyro, f"{s.name} body rates", res, map_sigma["imu"], map_off["imu"])
            warns.append(f"gyro from {s.name} rollspeed/pitchspeed/yawspeed (estimator output, no accel)")
            del r
        else:
            gyro, acc = _imu_values(s)
            kw["gyro"] = Stream(t, gyro, s.name, res, map_sigma["imu"], map_off["imu"])
            kw["accel"] = Stream(t, acc, s.name, res, map_sigma["imu"], map_off["imu"])
            del acc
        del s, t, gyro
        picked.pop("imu")
    if "att" in picked:
        s = picked["att"]
        kw["quat"] = Stream(stamps("att"), _quat_values(s), s.name, resolution("att"), map_sigma["att"], map_off["att"])
        del s
        picked.pop("att")
    if "vel" in picked:
        s = picked["vel"]
        kw["vel"] = Stream(stamps("vel"), _vel_values(s), s.name, resolution("vel"), map_sigma["vel"], map_off["vel"])
        del s
        picked.pop("vel")
    if "pos" in picked:
        s = picked["pos"]
        vals, valid = _pos_values(s)
        if not valid.all():
            warns.append(f"{s.name}: {int((~valid).sum())} samples without a position fix (0,0) dropped")
        if valid.any():
            t, res = stamps("pos"), resolution("pos")
            kw["pos"] = (Stream(t, vals, s.name, res, map_sigma["pos"], map_off["pos"]) if valid.all() else
                         Stream(t[valid], vals[valid], s.name, res, map_sigma["pos"], map_off["pos"]))
            del t
        del s, vals, valid
        picked.pop("pos")
    eff = ",".join(f"{k}={sel[k]}" for k in ("imu", "att", "vel", "pos") if k in sel)
    eff = f"sysid={sysid},compid={compid},{eff},time={mode}"
    return assemble_inslog(kw, path=path, fmt=NAME, selector=eff, clock=plan.clock, stamp_source=plan.source,
                           warnings=warns)


def _stream_rate(t_sorted_ns: np.ndarray, receive: bool) -> float:
    """Median-step rate; for receive stamps (bursty: the link delivers in packets) count/span."""
    if len(t_sorted_ns) < 2:
        return 0.0
    if receive:
        span = (t_sorted_ns[-1] - t_sorted_ns[0]) * 1e-9
        return float((len(t_sorted_ns) - 1) / span) if span > 0 else 0.0
    return rate_of((t_sorted_ns - t_sorted_ns[0]) * 1e-9)


def inventory(path: str) -> Inventory:
    check_readable(path)
    fr = scan_frames(path, project=True)
    cat = catalog(fr)
    streams = []
    systems = {(s, c) for (s, c, _) in cat.counts}
    multi = len(systems) > 1
    for (sysid, compid, name) in sorted(cat.counts, key=lambda k: (k[0], k[1], IMU_PREF.index(k[2])
                                                                  if k[2] in IMU_PREF else 9, k[2])):
        s = _raw(fr, name, sysid, compid)
        kind_arr, t_ns = _msg_time(s)
        if np.all(kind_arr == 2):
            clock = "receive (no time field)"
        elif np.all(kind_arr == 1):
            clock = "epoch (time_usec)"
        elif np.all(kind_arr == 0):
            clock = "boot (" + (_time_field(name) or "") + ")"
        else:
            clock = "mixed boot/epoch"
        t_sorted = np.sort(t_ns)
        t_s = t_sorted * 1e-9
        label = name if not multi else f"{name} (sys {sysid} comp {compid})"
        streams.append(StreamInfo(name=label, kind=KIND[name], count=len(t_s),
                                  rate_hz=_stream_rate(t_sorted, receive=bool(np.all(kind_arr == 2))),
                                  start_s=float(t_s[0]) if len(t_s) else 0.0,
                                  duration_s=float(t_sorted[-1] - t_sorted[0]) * 1e-9 if len(t_s) else 0.0,
                                  clock=clock, fields=tuple(msgdef(name).dtype.names)))
    sels = tuple(_sel_text(s) for s in unit_selectors(cat))
    notes = [f"{fr.n_valid} valid frames; default clock time=message (message time fields, "
             f"SYSTEM_TIME maps boot to UNIX time); time=receive uses the tlog receive stamps"]
    return Inventory(path=path, format=NAME, streams=tuple(streams), selectors=sels,
                     warnings=fr.warnings, notes=tuple(notes))


# ---- reference decoder (pymavlink) ---------------------------------------------------------------
def reference_messages(path: str, types: list[str] | None = None) -> list:
    """pymavlink's own decode of a tlog (the slow reference the fast path is tested against)."""
    import os

    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil
    conn = mavutil.mavlink_connection(path, dialect="ardupilotmega", robust_parsing=True)
    out = []
    try:
        while True:
            m = conn.recv_match(type=types)
            if m is None:
                break
            if m.get_type() != "BAD_DATA":
                out.append(m)
    finally:
        conn.close()
    return out


# ---- writer --------------------------------------------------------------------------------------
BOOT_LEAD_S = 30  # boot time of the first sample when writing an epoch-clocked log
RECEIVE_EPOCH_NS = 1_735_689_600 * 1_000_000_000  # 2025-01-01: receive clock of boot-clocked logs


@dataclass
class _Pending:
    d: MsgDef
    rec: np.ndarray  # structured, wire dtype
    recv_us: np.ndarray


def _records(name: str, n: int) -> tuple[MsgDef, np.ndarray]:
    d = msgdef(name)
    return d, np.zeros(n, dtype=d.dtype)


def pack_frames(d: MsgDef, rec: np.ndarray, seq: np.ndarray, sysid: int, compid: int,
                recv_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised MAVLink 2 packing of N messages of one type, with tlog receive stamps.
    Returns (rows (N, W) uint8, lengths (N,)): row i's first lengths[i] bytes are its tlog record.
    Byte-identical to pymavlink's ``msg.pack(mav)`` (trailing-zero payload truncation included)."""
    n = len(rec)
    payload = np.ascontiguousarray(rec).view(np.uint8).reshape(n, d.wire_len)
    nz = payload != 0
    last = np.where(nz.any(axis=1), d.wire_len - np.argmax(nz[:, ::-1], axis=1), 0)
    plen = np.maximum(last, 1).astype(np.int64)
    hdr = np.zeros((n, 9), dtype=np.uint8)  # len, incompat, compat, seq, sys, comp, id0..2
    hdr[:, 0] = plen
    hdr[:, 3] = seq & 0xFF
    hdr[:, 4] = sysid
    hdr[:, 5] = compid
    hdr[:, 6] = d.id & 0xFF
    hdr[:, 7] = (d.id >> 8) & 0xFF
    hdr[:, 8] = (d.id >> 16) & 0xFF
    w = 8 + 10 + d.wire_len + 2
    rows = np.zeros((n, w), dtype=np.uint8)
    rows[:, :8] = np.ascontiguousarray(recv_us.astype(">u8")).view(np.uint8).reshape(n, 8)
    rows[:, 8] = 0xFD
    rows[:, 9:18] = hdr
    rows[:, 18:18 + d.wire_len] = payload
    crc = x25_crc_block(rows, 9, 9 + plen, extra=d.crc_extra)
    ar = np.arange(n)
    rows[ar, 18 + plen] = (crc & 0xFF).astype(np.uint8)
    rows[ar, 19 + plen] = (crc >> 8).astype(np.uint8)
    return rows, 20 + plen


def _abs_ns(log: InsLog, t_s: np.ndarray) -> np.ndarray:
    return log.meta.t0_ns + np.round(np.asarray(t_s, float) * 1e9).astype(np.int64)


def write(path: str, log: InsLog, *, sysid: int = 1, compid: int = 1, transport_delay_s: float = 0.005,
          boot_epoch_ns: int | None = None) -> None:
    """Write ``log`` (FRD/NED) as a tlog a ground station would record.

    HIGHRES_IMU (time_usec: UNIX us if ``log.meta.clock == "epoch"`` else boot us), ATTITUDE_QUATERNION
    and ATTITUDE (time_boot_ms), GLOBAL_POSITION_INT (when the log has position; LOCAL_POSITION_NED
    when it has velocity only), SYSTEM_TIME and HEARTBEAT at 1 Hz. Receive stamps = message time +
    ``transport_delay_s``. Boot time 0 is ``boot_epoch_ns`` (UNIX ns; default: 30 s before the first
    sample, on a whole millisecond) for epoch logs; boot-clocked logs keep their stamps as boot time
    and SYSTEM_TIME carries time_unix_usec = 0 (no UNIX time known).
    """
    epoch = log.meta.clock == "epoch"
    a, b = log.span_s()
    if not np.isfinite(a):
        raise InputError("nothing to write (empty log)", path)
    first_ns, last_ns = _abs_ns(log, [a])[0], _abs_ns(log, [b])[0]
    if epoch:
        if boot_epoch_ns is None:
            boot_epoch_ns = (first_ns // 1_000_000 - BOOT_LEAD_S * 1000) * 1_000_000
        boot_of = lambda t_ns: t_ns - boot_epoch_ns  # noqa: E731
        recv_epoch_of = lambda t_ns: t_ns  # noqa: E731
    else:
        if first_ns < 0:
            raise InputError("boot-clocked log with negative stamps cannot be written as tlog", path)
        boot_of = lambda t_ns: t_ns  # noqa: E731
        recv_epoch_of = lambda t_ns: t_ns + RECEIVE_EPOCH_NS  # noqa: E731
    delay_ns = int(round(transport_delay_s * 1e9))
    pend: list[_Pending] = []

    def add(d, rec, t_abs_ns):
        pend.append(_Pending(d, rec, (recv_epoch_of(t_abs_ns) + delay_ns) // 1000))

    def boot_ms(t_ns):  # the whole milliseconds elapsed, as an autopilot's millis() gives them (BOOT_MS_NS)
        return np.floor(boot_of(t_ns) / 1e6).astype(np.int64)

    t_imu_ns = None
    if log.has_gyro or log.has_accel:
        t_imu_ns = _abs_ns(log, log.t_imu_s())
        d, r = _records("HIGHRES_IMU", len(t_imu_ns))
        r["time_usec"] = np.round((t_imu_ns if epoch else boot_of(t_imu_ns)) / 1e3).astype(np.uint64)
        bits = 0
        if log.has_accel:
            acc = log.accel_m_s2()
            r["xacc"], r["yacc"], r["zacc"] = acc.T
            bits |= 0x7
        if log.has_gyro:
            gyr = log.gyro_rad_s()
            r["xgyro"], r["ygyro"], r["zgyro"] = gyr.T
            bits |= 0x38
        r["fields_updated"] = bits
        add(d, r, t_imu_ns)
    if log.has_quat:
        t_q, q = log.quat_wxyz()
        tq_ns = _abs_ns(log, t_q)
        rates = np.zeros((len(q), 3))
        if log.has_gyro and t_imu_ns is not None and len(t_imu_ns) > 1:
            gyr = log.gyro_rad_s()
            ti = (t_imu_ns - t_imu_ns[0]) * 1e-9
            tqr = (tq_ns - t_imu_ns[0]) * 1e-9
            rates = np.column_stack([np.interp(tqr, ti, g) for g in gyr.T])
        d, r = _records("ATTITUDE_QUATERNION", len(q))
        r["time_boot_ms"] = boot_ms(tq_ns)
        r["q1"], r["q2"], r["q3"], r["q4"] = q.T
        r["rollspeed"], r["pitchspeed"], r["yawspeed"] = rates.T
        add(d, r, tq_ns)
        d, r2 = _records("ATTITUDE", len(q))
        rpy = euler_from_quat(q)
        r2["time_boot_ms"] = r["time_boot_ms"]
        r2["roll"], r2["pitch"], r2["yaw"] = rpy.T
        r2["rollspeed"], r2["pitchspeed"], r2["yawspeed"] = rates.T
        add(d, r2, tq_ns)
    if log.has_pos:
        t_p, p = log.lat_lon_alt()
        tp_ns = _abs_ns(log, t_p)
        d, r = _records("GLOBAL_POSITION_INT", len(p))
        r["time_boot_ms"] = boot_ms(tp_ns)
        r["lat"] = np.round(p[:, 0] * 1e7).astype(np.int32)
        r["lon"] = np.round(p[:, 1] * 1e7).astype(np.int32)
        r["alt"] = np.round(p[:, 2] * 1e3).astype(np.int32)
        r["relative_alt"] = np.round((p[:, 2] - p[0, 2]) * 1e3).astype(np.int32)
        r["hdg"] = 65535
        if log.has_vel:
            t_v, v = log.vel_ned_m_s()
            tv_ns = _abs_ns(log, t_v)
            idx = np.searchsorted(tv_ns, tp_ns)
            same = (idx < len(tv_ns)) & (tv_ns[np.minimum(idx, len(tv_ns) - 1)] == tp_ns)
            if not same.all():  # velocity at other stamps: interpolate onto the position stamps
                vv = np.column_stack([np.interp((tp_ns - tv_ns[0]) * 1e-9, (tv_ns - tv_ns[0]) * 1e-9, c)
                                      for c in v.T])
            else:
                vv = v[idx]
            cms = np.clip(np.round(vv * 100.0), -32768, 32767).astype(np.int16)
            r["vx"], r["vy"], r["vz"] = cms.T
        add(d, r, tp_ns)
    elif log.has_vel:
        t_v, v = log.vel_ned_m_s()
        tv_ns = _abs_ns(log, t_v)
        d, r = _records("LOCAL_POSITION_NED", len(v))
        r["time_boot_ms"] = boot_ms(tv_ns)
        r["vx"], r["vy"], r["vz"] = v.T
        add(d, r, tv_ns)
    # 1 Hz housekeeping after each whole boot second: SYSTEM_TIME as an autopilot sends it, time_unix_usec of
    # the instant and time_boot_ms its whole milliseconds, the instants at fractions of the millisecond that
    # vary from record to record (the first two at 0 and 999 us, which bound the offset exactly; then k x the
    # golden ratio's: spread evenly over it, as a scheduler's do)
    b0 = int(np.ceil(boot_of(first_ns) / 1e9))
    b1 = int(np.floor(boot_of(last_ns) / 1e9))
    sec_boot_ns = np.arange(b0, b1 + 1, dtype=np.int64) * 1_000_000_000
    if len(sec_boot_ns):
        frac_ns = (np.mod(np.arange(len(sec_boot_ns)) * 0.6180339887498949, 1.0) * 1000).astype(np.int64) * 1000
        frac_ns[1:2] = BOOT_MS_NS - 1000
        t_abs = sec_boot_ns + frac_ns + (boot_epoch_ns if epoch else 0)
        d, r = _records("SYSTEM_TIME", len(sec_boot_ns))
        r["time_boot_ms"] = sec_boot_ns // 1_000_000
        r["time_unix_usec"] = (t_abs // 1000).astype(np.uint64) if epoch else 0
        add(d, r, t_abs)
        d, r = _records("HEARTBEAT", len(sec_boot_ns))
        r["type"], r["autopilot"], r["base_mode"], r["system_status"], r["mavlink_version"] = 1, 3, 81, 4, 3
        add(d, r, t_abs)
    if not pend:
        raise InputError("nothing to write (no IMU, attitude, velocity or position)", path)
    # global order by receive time (ties: the order added), then sequence numbers, then pack
    recv = np.concatenate([p.recv_us for p in pend])
    which = np.concatenate([np.full(len(p.recv_us), i) for i, p in enumerate(pend)])
    order = np.lexsort((which, recv))
    seq = np.empty(len(recv), dtype=np.int64)
    seq[order] = np.arange(len(recv)) & 0xFF
    packed = []
    lens = np.empty(len(recv), dtype=np.int64)
    o = 0
    for p in pend:
        n = len(p.recv_us)
        rows, ln = pack_frames(p.d, p.rec, seq[o:o + n], sysid, compid, p.recv_us)
        packed.append(rows)
        lens[o:o + n] = ln
        o += n
    pos = np.empty(len(recv), dtype=np.int64)
    pos[order] = np.concatenate([[0], np.cumsum(lens[order])[:-1]])
    out = np.empty(int(lens.sum()), dtype=np.uint8)
    o = 0
    for rows in packed:
        n = len(rows)
        scatter_rows(out, rows, pos[o:o + n], lens[o:o + n])
        o += n
    with atomic_path(path) as tmp:
        out.tofile(tmp)
