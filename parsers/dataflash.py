"""ArduPilot DataFlash binary logs (``.bin``, written to the autopilot's SD card).

A DataFlash log is a sequence of fixed-length records ``0xA3 0x95 TYPE body`` whose layouts are
defined in the log itself by ``FMT`` records (type 128). The whole file is decoded by record type
with numpy structured dtypes (``np.frombuffer`` semantics) built from the FMT definitions, applying
ArduPilot's format-character scaling (c/C/e/E x0.01, L x1e-7) exactly as pymavlink's DFReader does;
DFReader stays the reference the tests compare against, message for message.

Streams (FRD / NED already; units converted here):

* IMU: ``IMU``, ``IMU2``, ``IMU3`` (older logs) or ``IMU`` with instance field ``I`` (newer):
  GyrX/Y/Z rad/s, AccX/Y/Z m/s^2.
* attitude: ``ATT`` and ``AHR2`` (Roll/Pitch/Yaw deg; AHR2's Q1..Q4 when logged), EKF2 ``NKF1`` /
  ``NKF6`` (core 0 / 1 in older logs), EKF3 ``XKF1`` / ``XKF6`` or ``XKF1`` with core field ``C``;
  with ``nav=<EKF message>`` the attitude comes from the same core's quaternion message
  (``NKQ1``/``NKQ2``, ``XKQ1``/``XKQ2``, ``XKQ[C]``) when logged (float precision, not centidegrees).
* velocity: EKF ``VN/VE/VD`` m/s, or ``GPS`` (Spd, GCrs, VZ -> NED).
* position: ``GPS`` / ``AHR2`` (Lat/Lng deg, Alt m), or EKF ``PN/PE/PD`` about the ``ORGN`` origin.

Clock: ``TimeUS`` (``TimeMS`` in old logs) is time since boot. When GPS messages carry GPS time
(``GWk``/``GMS``, or ``Week``/``TimeMS`` in old logs) with a fix, the log is put on UNIX time (the
median offset GPS time - boot time over the fixed GPS messages whose GPS time is plausible and that agree
with the majority; the GPS message's own logging latency is not removed). Stray stamps are dropped on the
boot clock before the offset is added; GPS time that gives no trustworthy offset leaves the log on the boot
clock with a warning. ``meta.stamp_source`` says which. Selector ``time=boot`` keeps boot time.

Selectors: ``imu=IMU2``, ``imu=IMU[1]`` (instance), ``att=AHR2``, ``nav=NKF6`` (att+vel(+pos) of that
EKF core), ``nav=XKF1[1]`` (EKF3 core 1), ``vel=GPS``, ``pos=GPS``, ``time=boot|gps``.

Damaged logs: bytes that do not start a known record are skipped up to the next valid header (the
count is reported in ``meta.warnings``); the readable part is used.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from logtools.conventions import DEG, quat_from_euler
from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers.assemble import ClockOffset, Stream, build_inslog, implausible
from parsers.base import (DAMAGED_HEAD_SEARCH_BYTES, EPOCH_MAX_NS, STAMP_LIMIT_NS, Inventory, Selector, StreamInfo,
                          check_readable, consensus_offset, counts_to_ns, offset_sigma_s, rate_of)
from parsers.mavlink_common import GPS_EPOCH_UNIX_S, gather_rows, gps_to_unix_ns, scatter_rows, walk_dataflash

NAME = "dataflash"
EXTENSIONS = (".bin", ".BIN")

HEAD1, HEAD2, FMT_TYPE, FMT_LEN = 0xA3, 0x95, 0x80, 89
#: the last GPS week a fix may name (its UNIX time before EPOCH_MAX_NS, 2100; a later one is a corrupt field)
_MAX_GPS_WEEK = (EPOCH_MAX_NS // 1_000_000_000 - GPS_EPOCH_UNIX_S) // 604_800
_WEEK_MS = 604_800_000

#: DataFlash format char -> (numpy dtype, multiplier) as pymavlink.DFReader.FORMAT_TO_STRUCT
DF_TYPES: dict[str, tuple[object, float | None]] = {
    "a": (("<i2", (32,)), None), "b": ("i1", None), "B": ("u1", None), "g": ("<f2", None),
    "h": ("<i2", None), "H": ("<u2", None), "i": ("<i4", None), "I": ("<u4", None),
    "f": ("<f4", None), "n": ("S4", None), "N": ("S16", None), "Z": ("S64", None),
    "c": ("<i2", 0.01), "C": ("<u2", 0.01), "e": ("<i4", 0.01), "E": ("<u4", 0.01),
    "L": ("<i4", 1e-7), "d": ("<f8", None), "M": ("i1", None), "q": ("<i8", None),
    "Q": ("<u8", None),
}

IMU_NAMES = ("IMU", "IMU2", "IMU3")
EKF_NAV = ("NKF1", "NKF6", "XKF1", "XKF6")
ATT_NAMES = ("ATT", "AHR2") + EKF_NAV + ("NKQ1", "NKQ2", "NKQ3", "NKQ", "XKQ1", "XKQ2", "XKQ3", "XKQ")
VEL_NAMES = EKF_NAV + ("GPS", "GPS2")
POS_NAMES = ("GPS", "GPS2", "AHR2") + EKF_NAV
#: EKF attitude/velocity message -> the quaternion message of the same core
QUAT_OF = {"NKF1": "NKQ1", "NKF6": "NKQ2", "XKF1": "XKQ1", "XKF6": "XKQ2"}
INSTANCE_GUESS = {"IMU": "I", "XKF1": "C", "XKQ": "C", "NKF1": "C", "NKQ": "C", "GPS": "I", "AHR2": None}


@dataclass(frozen=True)
class DfFormat:
    type: int
    name: str
    length: int
    fmt: str
    columns: tuple[str, ...]
    instance: str | None = None

    @cached_property
    def dtype(self) -> np.dtype:
        fields, seen = [], {}
        for c, col in zip(self.fmt, self.columns):
            k = seen.get(col, 0)
            seen[col] = k + 1
            name = col if k == 0 else f"{col}_{k}"
            dt = DF_TYPES[c][0]
            fields.append((name,) + (dt if isinstance(dt, tuple) else (dt,)))
        return np.dtype(fields)

    def scale(self, col: str) -> float | None:
        return DF_TYPES[self.fmt[self.columns.index(col)]][1]


def _body_size(fmt: str) -> int | None:
    try:
        return sum(np.dtype(DF_TYPES[c][0] if not isinstance(DF_TYPES[c][0], tuple)
                            else [("x",) + DF_TYPES[c][0]]).itemsize for c in fmt)
    except KeyError:
        return None


def _cstr(b: bytes) -> str:
    return b.split(b"\0", 1)[0].decode("ascii", "replace").strip()


#: bytes searched at a time for a record header: bounds the search's temporaries (a whole-file expression made
#: five file-sized arrays: 2.5 GB for a 500 MB log)
_SEARCH_BLOCK = 1 << 24


def _find_header(buf: np.ndarray, typ: int) -> np.ndarray:
    """Offsets of every ``HEAD1 HEAD2 typ`` byte triple in ``buf``, block by block (one pass of a compare over
    each block, the other two bytes checked at its hits only)."""
    n = len(buf)
    out = [np.zeros(0, np.int64)]
    for a in range(0, max(n - 2, 0), _SEARCH_BLOCK):
        hit = np.flatnonzero(buf[a:min(a + _SEARCH_BLOCK, n - 2)] == HEAD1) + a
        out.append(hit[(buf[hit + 1] == HEAD2) & (buf[hit + 2] == typ)])
    return np.concatenate(out)


def find_formats(buf: np.ndarray) -> tuple[dict[int, DfFormat], int]:
    """Every valid FMT record anywhere in the file (newer logs write FMTs lazily, mid-log).
    Returns (formats by type, number of rejected FMT-looking candidates)."""
    n = len(buf)
    if n < FMT_LEN:
        return {}, 0
    cand = _find_header(buf, FMT_TYPE)
    cand = cand[cand + FMT_LEN <= n]
    fmts: dict[int, DfFormat] = {}
    rejected = 0
    for off in cand.tolist():
        rec = bytes(buf[off + 3: off + FMT_LEN])
        typ, length = rec[0], rec[1]
        name, fmt, cols = _cstr(rec[2:6]), _cstr(rec[6:22]), _cstr(rec[22:86])
        columns = tuple(c.strip() for c in cols.split(",")) if cols else ()
        ok = (re.fullmatch(r"[A-Za-z0-9_]{1,4}", name or "") is not None
              and (_body_size(fmt) is not None and _body_size(fmt) + 3 == length)
              and len(columns) == len(fmt))
        if typ == FMT_TYPE:
            ok = ok and name == "FMT" and length == FMT_LEN
        if not ok:
            rejected += 1
            continue
        if typ not in fmts:
            fmts[typ] = DfFormat(typ, name, length, fmt, columns)
    return fmts, rejected


def sniff(head: bytes, path: str) -> bool:
    """DataFlash: starts with 0xA3 0x95 and holds FMT records in the first bytes."""
    if len(head) < 3 or head[0] != HEAD1 or head[1] != HEAD2:
        return False
    return b"\xa3\x95\x80" in head[:4096]


def sniff_damaged(head: bytes, path: str) -> bool:
    """A DataFlash log whose first bytes are damaged, or with bytes put before it: an FMT record (89 bytes)
    followed by another record, from an offset up to DAMAGED_HEAD_SEARCH_BYTES (the walk skips the bytes before
    it, and says so)."""
    i = head.find(b"\xa3\x95\x80", 0, DAMAGED_HEAD_SEARCH_BYTES + 3)
    while i >= 0:
        if head[i + 89:i + 91] == bytes([HEAD1, HEAD2]):
            return True
        i = head.find(b"\xa3\x95\x80", i + 1, DAMAGED_HEAD_SEARCH_BYTES + 3)
    return False


@dataclass
class DfLog:
    """A walked DataFlash file: record offsets grouped by type, formats, damage."""

    path: str
    buf: np.ndarray
    formats: dict[int, DfFormat]
    offsets: dict[int, np.ndarray]  # type -> record start offsets (file order)
    warnings: list[str] = field(default_factory=list)

    @cached_property
    def by_name(self) -> dict[str, DfFormat]:
        out = {}
        for f in self.formats.values():
            if len(self.offsets.get(f.type, ())) and f.name not in out:
                out[f.name] = f
        return out

    def records(self, name: str) -> np.ndarray:
        """Raw structured records (unscaled) of message ``name``."""
        f = self.by_name.get(name)
        if f is None:
            return np.zeros(0, dtype=np.dtype([]))
        offs = self.offsets[f.type]
        block = gather_rows(self.buf, offs + 3, f.length - 3)
        return block.view(f.dtype).reshape(-1)

    def column(self, name: str, rec: np.ndarray, col: str) -> np.ndarray:
        """One column as float64 with DFReader's scaling (divide by 1/mult like pymavlink)."""
        f = self.by_name[name]
        v = rec[col].astype(np.float64)
        m = f.scale(col)
        if m is not None:
            v = v / (1.0 / m) if 0.0 < m < 1.0 else v * m
        return v

    def has(self, name: str) -> bool:
        return name in self.by_name

    def time_ns(self, name: str, rec: np.ndarray) -> np.ndarray:
        """Boot-time stamps (ns) of records (TimeUS, or TimeMS in old logs; old GPS: T), converted checked
        (``counts_to_ns``: a corrupt count becomes a stamp the assembly drops, never a wrapped one)."""
        cols = rec.dtype.names
        if name.startswith("GPS") and "TimeUS" not in cols and "T" in cols:
            return counts_to_ns(rec["T"], 1_000_000)
        if "TimeUS" in cols:
            return counts_to_ns(rec["TimeUS"], 1000)
        if "TimeMS" in cols:
            return counts_to_ns(rec["TimeMS"], 1_000_000)
        raise KeyError(f"{name} has no TimeUS/TimeMS")

    def time_resolution_s(self, name: str) -> float:
        """The step of the message's stamps: 1 ms for TimeMS (old logs) and old GPS T, else 0 (TimeUS)."""
        f = self.by_name.get(name)
        cols = f.columns if f is not None else ()
        return 0.0 if "TimeUS" in cols or not cols else 1e-3


def read_log(path: str) -> DfLog:
    buf = np.fromfile(path, dtype=np.uint8)
    if len(buf) == 0:
        raise InputError("empty file", path)
    fmts, _ = find_formats(buf)
    if not fmts:
        raise InputError("no FMT records: not an ArduPilot DataFlash log, or damaged beyond use", path)
    fmts.setdefault(FMT_TYPE, DfFormat(FMT_TYPE, "FMT", FMT_LEN, "BBnNZ",
                                       ("Type", "Length", "Name", "Format", "Columns")))
    lengths = np.zeros(256, dtype=np.int64)
    for t, f in fmts.items():
        lengths[t] = f.length
    lengths[FMT_TYPE] = FMT_LEN
    starts, skipped, resyncs, tail = walk_dataflash(buf, lengths)
    warns = []
    if skipped:
        warns.append(f"damaged DataFlash log: skipped {skipped} bad bytes at {max(resyncs, 1)} place(s) "
                     f"to the next valid record header")
    if tail and tail >= 3:
        warns.append(f"truncated DataFlash log: last {tail} byte(s) hold an incomplete record")
    types = buf[starts + 2]
    order = np.argsort(types, kind="stable")
    ts = types[order]
    bounds = np.flatnonzero(np.diff(ts)) + 1
    offsets = {int(types[g[0]]): starts[g]
               for g in np.split(order, bounds) if len(g)}
    log = DfLog(path, buf, fmts, offsets, warns)
    _apply_fmtu(log)
    return log


def _apply_fmtu(log: DfLog) -> None:
    """Instance fields: FMTU's '#' unit marks them (newer logs); else known names (IMU I, XKF C)."""
    inst: dict[int, str] = {}
    if log.has("FMTU"):
        rec = log.records("FMTU")
        for typ, units in zip(rec["FmtType"].tolist(), rec["UnitIds"].tolist()):
            u = units.split(b"\0", 1)[0].decode("ascii", "replace")
            f = log.formats.get(int(typ))
            if f is not None and "#" in u and u.index("#") < len(f.columns):
                inst[f.type] = f.columns[u.index("#")]
    for t, f in list(log.formats.items()):
        col = inst.get(t)
        if col is None:
            guess = INSTANCE_GUESS.get(f.name) or (INSTANCE_GUESS.get("XKF1") if f.name.startswith("XK")
                                                   and f.name[-1:].isalpha() else None)
            if guess and guess in f.columns:
                col = guess
        if col is not None:
            log.formats[t] = DfFormat(f.type, f.name, f.length, f.fmt, f.columns, col)
    log.__dict__.pop("by_name", None)


# ---- streams -------------------------------------------------------------------------------------
_SEL = re.compile(r"^([A-Z0-9_]{1,4})(?:\[(\d+)\])?$")


@dataclass(frozen=True)
class Src:
    name: str
    inst: int | None = None

    def __str__(self) -> str:
        return self.name if self.inst is None else f"{self.name}[{self.inst}]"


def _parse_src(text: str, path: str) -> Src:
    m = _SEL.match(text.strip().upper())
    if not m:
        raise InputError(f"selector value {text!r} is not a message name like IMU2 or XKF1[1]", path)
    return Src(m.group(1), int(m.group(2)) if m.group(2) else None)


def _select(log: DfLog, src: Src) -> tuple[np.ndarray, np.ndarray]:
    """(records, boot ns) of a source, instance filtered; raises InputError when absent."""
    if not log.has(src.name):
        raise InputError(f"no {src.name} messages in this log (use `tapost inspect` to list streams)",
                         log.path)
    rec = log.records(src.name)
    f = log.by_name[src.name]
    if f.instance is not None and src.inst is not None:
        rec = rec[rec[f.instance] == src.inst]
        if len(rec) == 0:
            raise InputError(f"no {src} messages (instance {src.inst} of {src.name} absent)", log.path)
    elif f.instance is None and src.inst not in (None, 0):
        raise InputError(f"{src.name} has no instance field: use the numbered message name "
                         f"(e.g. IMU2, NKF6) instead of {src}", log.path)
    elif f.instance is not None and src.inst is None:
        inst = np.unique(rec[f.instance])
        if len(inst) > 1:
            rec = rec[rec[f.instance] == inst[0]]
    return rec, log.time_ns(src.name, rec)


def _instances(log: DfLog, name: str) -> list[int]:
    f = log.by_name.get(name)
    if f is None:
        return []
    if f.instance is None:
        return [0]
    return sorted(set(log.records(name)[f.instance].tolist()))


def _quat_source(log: DfLog, src: Src) -> Src | None:
    """The quaternion message of the same EKF core as ``src`` (or of AHR2 itself)."""
    if src.name in QUAT_OF:
        multi = src.name[:2] + "Q"  # the core-instanced quaternion of newer logs: XKF1[C] -> XKQ[C], NKF1 -> NKQ
        if src.inst is not None and log.has(multi) and src.name in ("XKF1", "NKF1"):
            return Src(multi, src.inst)
        q = QUAT_OF[src.name]
        if log.has(q):
            return Src(q)
        if log.has(multi):
            core = src.inst if src.inst is not None else (1 if src.name.endswith("6") else 0)
            return Src(multi, core)
    return None


def _att(log: DfLog, src: Src) -> tuple[np.ndarray, np.ndarray, str]:
    rec, t = _select(log, src)
    cols = rec.dtype.names
    euler = all(c in cols for c in ("Roll", "Pitch", "Yaw"))
    if all(c in cols for c in ("Q1", "Q2", "Q3", "Q4")):
        q = np.column_stack([log.column(src.name, rec, c) for c in ("Q1", "Q2", "Q3", "Q4")])
        good = ~implausible("quat", q)
        # all of them unit quaternions; else most of them (the rest damaged records, dropped and said);
        # a message whose Q fields are not filled (zeros: older AHR2) falls back on its Euler angles
        if good.all() or (good.any() and (good.mean() >= 0.5 or not euler)):
            bad = int((~good).sum())
            return t[good], q[good], f"{src} quaternion" + (
                f" ({bad} samples with a non-unit quaternion dropped)" if bad else "")
    if not euler:
        raise InputError(f"{src} carries no attitude (Roll/Pitch/Yaw or Q1..Q4): not a navigation output "
                         "(`tapost inspect` lists those)", log.path)
    rpy = np.column_stack([log.column(src.name, rec, c) for c in ("Roll", "Pitch", "Yaw")]) * DEG
    return t, quat_from_euler(rpy), f"{src} Euler angles"


def _vel(log: DfLog, src: Src) -> tuple[np.ndarray, np.ndarray]:
    rec, t = _select(log, src)
    cols = rec.dtype.names
    if all(c in cols for c in ("VN", "VE", "VD")):
        return t, np.column_stack([log.column(src.name, rec, c) for c in ("VN", "VE", "VD")])
    if all(c in cols for c in ("Spd", "GCrs", "VZ")):
        spd = log.column(src.name, rec, "Spd")
        crs = log.column(src.name, rec, "GCrs") * DEG
        v = np.column_stack([spd * np.cos(crs), spd * np.sin(crs), log.column(src.name, rec, "VZ")])
        fix = _gps_fix(rec)
        return t[fix], v[fix]
    raise InputError(f"{src} carries no velocity (VN/VE/VD or Spd/GCrs/VZ)", log.path)


def _gps_fix(rec: np.ndarray) -> np.ndarray:
    return rec["Status"] >= 3 if "Status" in rec.dtype.names else np.ones(len(rec), bool)


def _pos(log: DfLog, src: Src) -> tuple[np.ndarray, np.ndarray]:
    rec, t = _select(log, src)
    cols = rec.dtype.names
    if all(c in cols for c in ("Lat", "Lng", "Alt")):
        p = np.column_stack([log.column(src.name, rec, c) for c in ("Lat", "Lng", "Alt")])
        ok = ~((p[:, 0] == 0) & (p[:, 1] == 0)) & _gps_fix(rec)
        return t[ok], p[ok]
    if all(c in cols for c in ("PN", "PE", "PD")) and log.has("ORGN"):
        org = log.records("ORGN")
        o = np.array([log.column("ORGN", org, c)[0] for c in ("Lat", "Lng", "Alt")])
        from logtools.earth import radii_m  # local: only needed here
        rm, rn = (float(x) for x in radii_m(np.radians(o[0])))
        pn, pe, pd = (log.column(src.name, rec, c) for c in ("PN", "PE", "PD"))
        p = np.column_stack([o[0] + np.degrees(pn / (rm + o[2])),
                             o[1] + np.degrees(pe / ((rn + o[2]) * np.cos(np.radians(o[0])))),
                             o[2] - pd])
        return t, p
    raise InputError(f"{src} carries no position (Lat/Lng/Alt, or PN/PE/PD with an ORGN origin)", log.path)


def _gps_epoch_offset(log: DfLog) -> tuple[int | None, str, list[str], str, float]:
    """UNIX ns - boot ns from GPS week/ms of fixed GPS messages (upper median over the fixes whose GPS time
    lies in 1980..2100 with a boot stamp that is a possible one, kept to those agreeing with the majority:
    ``consensus_offset``), the message, warnings, the problem ("" when the log has no fixed GPS time), and
    the offset's 1-sigma in s (``offset_sigma_s``: the readings' spread and the milliseconds of GMS)."""
    problems = []
    for name in ("GPS", "GPS2"):
        if not log.has(name):
            continue
        rec = log.records(name)
        cols = rec.dtype.names
        if "GWk" in cols and "GMS" in cols:
            wk, ms = rec["GWk"], rec["GMS"]
        elif "Week" in cols and "TimeMS" in cols and "T" in cols:
            wk, ms = rec["Week"], rec["TimeMS"]
        else:
            continue
        ok = (wk > 0) & _gps_fix(rec)
        if not ok.any():
            continue
        boot = log.time_ns(name, rec)
        good = ok & (wk <= _MAX_GPS_WEEK) & (ms >= 0) & (ms < _WEEK_MS) & (np.abs(boot) < STAMP_LIMIT_NS)
        n_bad = int(ok.sum() - good.sum())
        if not good.any():
            problems.append(f"{name}: all {n_bad} fixed GPS messages hold an impossible GPS time or boot stamp")
            continue
        diff = gps_to_unix_ns(wk[good], ms[good]) - boot[good]  # (both in range: no wrap)
        agree, why = consensus_offset(diff, 1_000_000_000)
        if why:
            problems.append(f"{name}: {why}")
            continue
        warns = []
        if not agree.all():
            diff = diff[agree]
            n_bad += int((~agree).sum())
        if n_bad:
            warns.append(f"{name}: {n_bad} of {int(ok.sum())} fixed GPS messages ignored for the boot->UNIX offset "
                         "(an impossible GPS time or boot stamp, or inconsistent with the others: corrupt?)")
        off = np.sort(diff)
        return int(off[len(off) // 2]), name, warns, "", offset_sigma_s(diff, 1_000_000_000, 1e-3)
    return None, "", [], "; ".join(problems), 0.0


def _gps_epoch_offset_ns(log: DfLog) -> tuple[int | None, str]:
    """UNIX ns - boot ns from GPS week/ms of fixed GPS messages (``_gps_epoch_offset``), or None."""
    off, name, _w, _p, _sig = _gps_epoch_offset(log)
    return off, name


def _ekf_type(log: DfLog) -> int | None:
    if not log.has("PARM"):
        return None
    rec = log.records("PARM")
    names = np.char.rstrip(rec["Name"].astype("S16"), b"\0")
    hit = np.flatnonzero(names == b"AHRS_EKF_TYPE")
    return int(rec["Value"][hit[-1]]) if len(hit) else None


def unit_selectors(log: DfLog) -> list[str]:
    """Ready selectors, one per unit: IMU k with EKF core k (EKF2 and EKF3), ATT and AHR2."""
    imus: list[str] = []
    for name in IMU_NAMES:
        for i in _instances(log, name):
            f = log.by_name[name]
            imus.append(name if f.instance is None else f"{name}[{i}]")
    out: list[str] = []
    fams = [("NKF1", "NKF6"), ("XKF1", "XKF6")]
    if _ekf_type(log) == 3:
        fams.reverse()
    for a, b in fams:
        cores: list[str] = []
        if log.has(a):
            f = log.by_name[a]
            if f.instance is not None:
                cores += [f"{a}[{i}]" for i in _instances(log, a)]
            else:
                cores.append(a)
                if log.has(b):
                    cores.append(b)
        for k, core in enumerate(cores):
            sel = (f"imu={imus[k]}," if k < len(imus) else "") + f"nav={core}"
            out.append(sel)
    if log.has("ATT") and imus:
        out.append(f"imu={imus[0]},att=ATT" + (",vel=GPS,pos=GPS" if log.has("GPS") else ""))
    if log.has("AHR2") and len(imus) > 1:
        out.append(f"imu={imus[1]},att=AHR2")
    used = {p.split(",")[0] for p in out}
    out += [f"imu={i}" for i in imus if f"imu={i}" not in used]  # IMU-only units (IMU3, ...)
    return out


def _resolve(path: str, selector: Selector, log: DfLog) -> tuple[dict[str, Src], str, list[str]]:
    allowed = {"imu", "att", "vel", "pos", "nav", "time", "clock"}
    for k, _ in selector.items:
        if k not in allowed:
            raise InputError(f"selector key {k!r} not understood by dataflash (use "
                             f"{', '.join(sorted(allowed))})", path)
    notes: list[str] = []
    sel_items = dict(selector.items)
    explicit = {k for k in sel_items if k in ("imu", "att", "vel", "pos", "nav")}
    if not explicit:
        presets = unit_selectors(log)
        if not presets:
            raise InputError("no IMU, ATT, AHR2 or EKF messages in this DataFlash log", path)
        pick = next((p for p in presets if "imu=" in p and ("nav=" in p or "att=" in p)), presets[0])
        sel_items.update(Selector.parse(pick).items)
        if len(presets) > 1:
            notes.append(f"no selector given: picked {pick} (other units: "
                         f"{'; '.join(p for p in presets if p != pick)})")
    out: dict[str, Src] = {}
    for k in ("imu", "att", "vel", "pos"):
        v = sel_items.get(k)
        if v is not None and v.lower() != "none":
            out[k] = _parse_src(v, path)
    nav = sel_items.get("nav")
    if nav is not None and nav.lower() != "none":
        src = _parse_src(nav, path)
        if not log.has(src.name):
            raise InputError(f"no {src.name} messages in this log (use `tapost inspect` to list streams)",
                             path)
        cols = log.by_name[src.name].columns
        if "att" not in out:
            q = _quat_source(log, src)
            out["att"] = q if q is not None else src
        if "vel" not in out and "VN" in cols:
            out["vel"] = src
        if "pos" not in out and ("Lat" in cols or ("PN" in cols and log.has("ORGN"))):
            out["pos"] = src
        elif "pos" not in out and log.has("GPS"):
            out["pos"] = Src("GPS")
            notes.append(f"{src} position needs an ORGN origin (absent): position from GPS")
    mode = (sel_items.get("time") or sel_items.get("clock") or "gps").lower()
    if mode in ("epoch", "unix"):
        mode = "gps"
    if mode not in ("gps", "boot"):
        raise InputError(f"selector time={mode}: use time=gps (UNIX via GPS time, default) or time=boot",
                         path)
    for k, s in out.items():
        if not log.has(s.name):
            raise InputError(f"selector {k}={s}: no {s.name} messages in this log "
                             f"(use `tapost inspect` to list streams)", path)
    return out, mode, notes


def load(path: str, selector: Selector) -> InsLog:
    check_readable(path)
    log = read_log(path)
    srcs, mode, notes = _resolve(path, selector, log)
    warns = list(log.warnings) + notes
    kw: dict[str, Stream] = {}
    if "imu" in srcs:
        s = srcs["imu"]
        rec, t = _select(log, s)
        if not all(c in rec.dtype.names for c in ("GyrX", "AccX")):
            raise InputError(f"{s} is not an IMU message (no GyrX/AccX)", path)
        g = np.column_stack([log.column(s.name, rec, c) for c in ("GyrX", "GyrY", "GyrZ")])
        a = np.column_stack([log.column(s.name, rec, c) for c in ("AccX", "AccY", "AccZ")])
        res = log.time_resolution_s(s.name)
        kw["gyro"], kw["accel"] = Stream(t, g, str(s), res), Stream(t, a, str(s), res)
    att_desc = ""
    if "att" in srcs:
        t, q, att_desc = _att(log, srcs["att"])
        kw["quat"] = Stream(t, q, str(srcs["att"]), log.time_resolution_s(srcs["att"].name))
    if "vel" in srcs:
        t, v = _vel(log, srcs["vel"])
        kw["vel"] = Stream(t, v, str(srcs["vel"]), log.time_resolution_s(srcs["vel"].name))
    if "pos" in srcs:
        t, p = _pos(log, srcs["pos"])
        if len(t):
            kw["pos"] = Stream(t, p, str(srcs["pos"]), log.time_resolution_s(srcs["pos"].name))
        else:
            warns.append(f"{srcs['pos']}: no valid positions (no fix); position left out")
    if not kw:
        raise InputError("selector picks no streams", path)
    off, gps_name, problem = None, "", ""
    if mode != "boot":
        off, gps_name, w, problem, off_sigma = _gps_epoch_offset(log)
        warns.extend(w)
        if problem:
            warns.append(f"GPS time gives no trustworthy boot->UNIX offset ({problem}): kept on the boot clock")
    att_txt = f"; attitude from {att_desc}" if att_desc else ""
    sel_txt = ",".join(f"{k}={v}" for k, v in srcs.items())
    src = "DataFlash TimeUS (time since boot)" + ("" if mode == "boot" else
                                                  "; GPS time untrustworthy" if problem else "; no GPS time in log")
    offset = None
    if off is not None:  # added by build_inslog once the stamps are cleaned on the boot clock, checked
        offset = ClockOffset(off, f"DataFlash TimeUS (boot) mapped to UNIX time by {gps_name} week/ms (median "
                                  f"offset over fixed GPS messages, 1-sigma {off_sigma * 1e3:.2g} ms; GPS logging "
                                  f"latency not removed){att_txt}", sel_txt + ",time=gps", sigma_s=off_sigma)
    return build_inslog(path=path, fmt=NAME, selector=sel_txt + ",time=boot", clock="boot",
                        stamp_source=src + att_txt, warnings=warns, offset=offset, **kw)


KIND_OF = {**{n: "imu" for n in IMU_NAMES}, "ATT": "att", "AHR2": "att", "NKF1": "odom", "NKF6": "odom",
           "XKF1": "odom", "XKF6": "odom", "NKQ1": "att", "NKQ2": "att", "NKQ3": "att", "NKQ": "att",
           "XKQ1": "att", "XKQ2": "att", "XKQ3": "att", "XKQ": "att", "GPS": "pos", "GPS2": "pos",
           "ORGN": "other"}


def inventory(path: str) -> Inventory:
    check_readable(path)
    log = read_log(path)
    streams = []
    for name in [n for n in KIND_OF if log.has(n)]:
        f = log.by_name[name]
        rec = log.records(name)
        t_all = log.time_ns(name, rec)
        insts = [None] if f.instance is None else sorted(set(rec[f.instance].tolist()))
        for i in insts:
            t = t_all if i is None else t_all[rec[f.instance] == i]
            t_s = np.sort(t) * 1e-9
            streams.append(StreamInfo(
                name=name if i is None else f"{name}[{i}]", kind=KIND_OF[name], count=len(t_s),
                rate_hz=rate_of(t_s - t_s[:1].sum()), start_s=float(t_s[0]) if len(t_s) else 0.0,
                duration_s=float(t_s[-1] - t_s[0]) if len(t_s) else 0.0, clock="boot (TimeUS)",
                fields=f.columns))
    off, gps_name, _w, problem, _sig = _gps_epoch_offset(log)
    notes = [f"{sum(len(v) for v in log.offsets.values())} records, {len(log.by_name)} message types; "
             + (f"stamps are boot time (TimeUS); loaded on the epoch clock (UNIX time from {gps_name} week/ms, "
                "time=gps) by default, as analyze reports it; time=boot keeps boot time" if off is not None
                else f"GPS time gives no trustworthy offset ({problem}): loaded on the boot clock (TimeUS)"
                if problem else "no GPS time: loaded on the boot clock (TimeUS)")]
    return Inventory(path=path, format=NAME, streams=tuple(streams), selectors=tuple(unit_selectors(log)),
                     warnings=tuple(log.warnings), notes=tuple(notes))


# ---- reference (pymavlink DFReader) and a small writer for round-trip tests ------------------------
def reference_messages(path: str, types: list[str] | None = None) -> list:
    """pymavlink DFReader's decode (the slow reference the fast path is tested against)."""
    from pymavlink import DFReader
    r = DFReader.DFReader_binary(path)
    out = []
    while True:
        m = r.recv_match(type=types)
        if m is None:
            break
        out.append(m)
    return out


def _fmt_record(f: DfFormat) -> bytes:
    body = bytes([f.type, f.length]) + f.name.encode().ljust(4, b"\0") + f.fmt.encode().ljust(16, b"\0") \
        + ",".join(f.columns).encode().ljust(64, b"\0")
    return bytes([HEAD1, HEAD2, FMT_TYPE]) + body


def write(path: str, log: InsLog, *, imu_name: str = "IMU", imu_instance: int | None = None,
          boot_start_s: float = 10.0) -> None:
    """A small DataFlash writer (for round-trip tests): IMU (TimeUS, Gyr, Acc float), NKF1 (Euler in
    centidegrees, VN/VE/VD), NKQ1 (quaternion), GPS at the nav rate (GWk/GMS from the log's UNIX
    stamps when the log is on the epoch clock). TimeUS = boot time; boot 0 is ``boot_start_s`` before
    the first sample for epoch logs. ``imu_instance`` writes IMU with an instance column ``I`` (the
    newer ArduPilot layout, selected as ``IMU[k]``)."""
    from logtools.conventions import euler_from_quat
    from parsers.atomic import atomic_path
    a, b = log.span_s()
    if not np.isfinite(a):
        raise InputError("nothing to write (empty log)", path)
    t0 = log.meta.t0_ns
    epoch = log.meta.clock == "epoch"
    first_abs = t0 + int(round(a * 1e9))
    boot_zero = (first_abs // 1000 * 1000 - int(boot_start_s * 1e9)) if epoch else 0

    def time_us(t_s):
        return ((t0 + np.round(np.asarray(t_s) * 1e9).astype(np.int64)) - boot_zero + 500) // 1000

    defs = {
        "FMT": DfFormat(128, "FMT", 89, "BBnNZ", ("Type", "Length", "Name", "Format", "Columns")),
        "IMU": (DfFormat(130, imu_name, 3 + 8 + 24, "Qffffff", ("TimeUS", "GyrX", "GyrY", "GyrZ", "AccX",
                                                                 "AccY", "AccZ"))
                if imu_instance is None else
                DfFormat(130, imu_name, 3 + 8 + 1 + 24, "QBffffff", ("TimeUS", "I", "GyrX", "GyrY", "GyrZ",
                                                                     "AccX", "AccY", "AccZ"))),
        "NKF1": DfFormat(131, "NKF1", 3 + 8 + 6 + 12, "QccCfff", ("TimeUS", "Roll", "Pitch", "Yaw", "VN",
                                                                  "VE", "VD")),
        "NKQ1": DfFormat(132, "NKQ1", 3 + 8 + 16, "Qffff", ("TimeUS", "Q1", "Q2", "Q3", "Q4")),
        "GPS": DfFormat(133, "GPS", 3 + 8 + 1 + 4 + 2 + 4 + 4 + 4 + 4 + 4 + 4, "QBIHLLefff",
                        ("TimeUS", "Status", "GMS", "GWk", "Lat", "Lng", "Alt", "Spd", "GCrs", "VZ")),
    }
    chunks: list[tuple[np.ndarray, np.ndarray]] = []  # (time_us, records as (N, L) bytes)

    def add(f: DfFormat, rec: np.ndarray):
        rows = np.empty((len(rec), f.length), dtype=np.uint8)
        rows[:, 0], rows[:, 1], rows[:, 2] = HEAD1, HEAD2, f.type
        rows[:, 3:] = np.ascontiguousarray(rec).view(np.uint8).reshape(len(rec), -1)
        chunks.append((rec["TimeUS"].astype(np.int64), rows))

    if log.has_gyro and log.has_accel:
        f = defs["IMU"]
        rec = np.zeros(len(log.imu), f.dtype)
        rec["TimeUS"] = time_us(log.t_imu_s())
        if imu_instance is not None:
            rec["I"] = imu_instance
        for c, v in zip(("GyrX", "GyrY", "GyrZ"), log.gyro_rad_s().T):
            rec[c] = v
        for c, v in zip(("AccX", "AccY", "AccZ"), log.accel_m_s2().T):
            rec[c] = v
        add(f, rec)
    if log.has_quat:
        tq, q = log.quat_wxyz()
        f = defs["NKQ1"]
        rec = np.zeros(len(q), f.dtype)
        rec["TimeUS"] = time_us(tq)
        for c, v in zip(("Q1", "Q2", "Q3", "Q4"), q.T):
            rec[c] = v
        add(f, rec)
        f = defs["NKF1"]
        rec = np.zeros(len(q), f.dtype)
        rec["TimeUS"] = time_us(tq)
        rpy = np.degrees(euler_from_quat(q))
        rec["Roll"] = np.round(rpy[:, 0] * 100)
        rec["Pitch"] = np.round(rpy[:, 1] * 100)
        rec["Yaw"] = np.round(np.mod(rpy[:, 2], 360.0) * 100) % 36000
        if log.has_vel:
            tv, v = log.vel_ned_m_s()
            for j, c in enumerate(("VN", "VE", "VD")):
                rec[c] = np.interp(tq, tv, v[:, j])
        add(f, rec)
    if log.has_pos:
        tp, p = log.lat_lon_alt()
        f = defs["GPS"]
        rec = np.zeros(len(p), f.dtype)
        rec["TimeUS"] = time_us(tp)
        rec["Status"] = 3
        if epoch:
            unix_ns = t0 + np.round(tp * 1e9).astype(np.int64)
            from parsers.mavlink_common import gps_leap_s
            gps_ns = unix_ns + gps_leap_s(unix_ns * 1e-9).astype(np.int64) * 1_000_000_000 \
                - 315_964_800 * 1_000_000_000
            rec["GWk"] = gps_ns // (604_800 * 1_000_000_000)
            rec["GMS"] = (gps_ns % (604_800 * 1_000_000_000)) // 1_000_000
            # GPS time has whole ms: stamp the record at the instant its GMS names, so that the
            # reader's boot -> UNIX offset is exact to the microsecond
            rec["TimeUS"] = (unix_ns - (gps_ns % 1_000_000) - boot_zero) // 1000
        rec["Lat"] = np.round(p[:, 0] * 1e7)
        rec["Lng"] = np.round(p[:, 1] * 1e7)
        rec["Alt"] = np.round(p[:, 2] * 100)
        if log.has_vel:
            tv, v = log.vel_ned_m_s()
            vv = np.column_stack([np.interp(tp, tv, v[:, j]) for j in range(3)])
            rec["Spd"] = np.hypot(vv[:, 0], vv[:, 1])
            rec["GCrs"] = np.mod(np.degrees(np.arctan2(vv[:, 1], vv[:, 0])), 360.0)
            rec["VZ"] = vv[:, 2]
        add(f, rec)
    if not chunks:
        raise InputError("nothing to write (no IMU, attitude or position)", path)
    head = b"".join(_fmt_record(f) for f in defs.values())
    t_all = np.concatenate([c[0] for c in chunks])
    order = np.argsort(t_all, kind="stable")
    lens = np.concatenate([np.full(len(c[0]), c[1].shape[1]) for c in chunks])
    pos = np.empty(len(t_all), dtype=np.int64)
    pos[order] = np.concatenate([[0], np.cumsum(lens[order])[:-1]])
    out = np.empty(int(lens.sum()), dtype=np.uint8)
    o = 0
    for _, rows in chunks:
        n, w = rows.shape
        scatter_rows(out, rows, pos[o:o + n], np.full(n, w))
        o += n
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(head)
        fh.write(out.tobytes())
