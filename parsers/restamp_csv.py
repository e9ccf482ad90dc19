"""The slave on the master's clock, natively: canonical CSV and vendor CSV (the time column rewritten).

A text-level rewrite: every line is copied as it is except its time cell, which is replaced by the
master-clock time in the column's own unit at full precision (nanoseconds: 9 decimals of a second, 6 of
a millisecond, 3 of a microsecond; an ISO 8601 date-time written as the cell was, its zone kept, with 9
fractional digits), and any other time column of the same clock the column map names (a ROS export's
receive time beside its header stamp). Other columns keep their exact text (no float re-formatting), the
header and line endings are kept, and a line whose time cell is not a decimal number (a damaged line)
is copied unchanged and counted in ``damage``. A vendor session folder (NGIMU: ``sensors.csv``,
``quaternion.csv``...) is written as a folder: every CSV of the unit whose header has the same time
column is restamped, every other file copied byte for byte.
"""
from __future__ import annotations

import os
import shutil
import tempfile

import numpy as np

from logtools.errors import InputError
from parsers.atomic import atomic_path, check_replaceable
from parsers.base import Selector
from parsers.csvtable import decimal_cells_to_int, delimiter, iso_cells_to_ns
from parsers.restamp import ClockShift, RestampStats, kernel_loader

HOW = "text rewrite of the time column (every other cell's text kept)"
_UNREAD = np.iinfo(np.int64).min
_POW10 = {"s": 9, "sec": 9, "ms": 6, "us": 3, "ns": 0}


def _cells(buf, k, sep):  # pragma: no cover - compiled
    """Per data line (after the header): (line start, line end, time cell start, end) of column k."""
    n = buf.shape[0]
    nl = 0
    for i in range(n):
        if buf[i] == 10:
            nl += 1
    ls = np.empty(nl + 1, np.int64)
    le = np.empty(nl + 1, np.int64)
    cs = np.empty(nl + 1, np.int64)
    ce = np.empty(nl + 1, np.int64)
    pos = 0
    # skip the header
    while pos < n and buf[pos] != 10:
        pos += 1
    pos += 1
    m = 0
    while pos < n:
        start = pos
        col = 0
        c0 = -1
        c1 = -1
        if k == 0:
            c0 = start
        while pos < n and buf[pos] != 10:
            if buf[pos] == sep:
                if col == k:
                    c1 = pos
                col += 1
                if col == k:
                    c0 = pos + 1
            pos += 1
        end = pos
        if c0 >= 0 and c1 < 0:
            c1 = end - 1 if end > start and buf[end - 1] == 13 else end
        ls[m] = start
        le[m] = end
        cs[m] = c0
        ce[m] = c1
        m += 1
        pos += 1
    return ls[:m], le[:m], cs[:m], ce[:m]


def _emit(buf, ls, le, cs, ce, ok, new, p, point, off, sep, zone, out):  # pragma: no cover - compiled
    """Copy the data lines into ``out``, the time cell of each ``ok`` line replaced by ``new`` (the cell's
    surrounding spaces/quotes kept). A decimal number with ``p`` decimals after the mark ``point`` (46 '.',
    44 ','), or, where ``off`` has a value per line, an ISO 8601 date-time (csvtable._iso_cells; ``new`` in
    ns, UTC): at the cell's own offset ``off`` (s) from UTC, with its separator ``sep``, nine fractional
    digits and its zone text as it was (from ``zone`` to the cell's end). Returns the bytes written."""
    iso = off.shape[0] > 0
    o = 0
    digits = np.empty(24, np.uint8)
    scale = np.int64(1)
    for _ in range(p):
        scale *= 10
    fields = np.zeros(6, np.int64)
    widths = np.array([4, 2, 2, 2, 2, 2], np.int64)
    marks = np.array([45, 45, 84, 58, 58, 46], np.uint8)  # - - T : : .
    for i in range(ls.shape[0]):
        if not ok[i]:
            for j in range(ls[i], le[i]):
                out[o] = buf[j]
                o += 1
        else:
            a = cs[i]
            b = ce[i]
            while a < b and (buf[a] == 32 or buf[a] == 34):
                a += 1
            while b > a and (buf[b - 1] == 32 or buf[b - 1] == 34 or buf[b - 1] == 13):
                b -= 1
            for j in range(ls[i], a):
                out[o] = buf[j]
                o += 1
            if iso:
                t = new[i] + off[i] * np.int64(1_000_000_000)
                sub = t % np.int64(1_000_000_000)
                secs = (t - sub) // np.int64(1_000_000_000)
                sod = secs % 86400
                z = (secs - sod) // 86400 + 719468  # civil date from days (H. Hinnant's algorithm)
                era = (z if z >= 0 else z - 146096) // 146097
                doe = z - era * 146097
                yoe = (doe - doe // 1460 + doe // 36524 - doe // 146096) // 365
                y = yoe + era * 400
                doy = doe - (365 * yoe + yoe // 4 - yoe // 100)
                mp = (5 * doy + 2) // 153
                d = doy - (153 * mp + 2) // 5 + 1
                m = mp + (3 if mp < 10 else -9)
                if m <= 2:
                    y += 1
                fields[0], fields[1], fields[2] = y, m, d
                fields[3], fields[4], fields[5] = sod // 3600, (sod // 60) % 60, sod % 60
                marks[2] = sep[i]
                for f in range(6):
                    v = fields[f]
                    for k in range(widths[f] - 1, -1, -1):
                        out[o + k] = 48 + v % 10
                        v //= 10
                    o += widths[f]
                    out[o] = marks[f]
                    o += 1
                v = sub
                for k in range(8, -1, -1):
                    out[o + k] = 48 + v % 10
                    v //= 10
                o += 9
                for j in range(zone[i], b):
                    out[o] = buf[j]
                    o += 1
            else:
                v = new[i]
                if v < 0:
                    out[o] = 45
                    o += 1
                    v = -v
                w = v // scale
                f = v % scale
                nd = 0
                if w == 0:
                    digits[0] = 48
                    nd = 1
                while w > 0:
                    digits[nd] = 48 + w % 10
                    w //= 10
                    nd += 1
                for j in range(nd):
                    out[o] = digits[nd - 1 - j]
                    o += 1
                if p > 0:
                    out[o] = point
                    o += 1
                    for j in range(p):
                        digits[p - 1 - j] = 48 + f % 10
                        f //= 10
                    for j in range(p):
                        out[o] = digits[j]
                        o += 1
            for j in range(b, le[i]):
                out[o] = buf[j]
                o += 1
        if le[i] < buf.shape[0]:
            out[o] = 10
            o += 1
    return o


_kernel = kernel_loader(globals())  # the numba kernels above, compiled (and cached) on first use


def restamp_bytes(raw: bytes, time_col: str, unit: str, shift: ClockShift, path: str, units_row: bool = False,
                  decimal: str = ".", moved: np.ndarray | None = None
                  ) -> tuple[np.ndarray, int, int, np.ndarray]:
    """(new file bytes, data lines rewritten, damaged lines kept as they were, each data line's shift in ns:
    master-clock time minus its time, int64 with the minimum int64 where the line's time was not read);
    ``units_row``: the line after the header (the columns' units) is copied as the header is; ``decimal``:
    the numbers' decimal mark (a comma-decimal CSV's time is written back with a comma). ``moved``: the
    shifts of another time column's pass over the same lines, applied instead of the shift at this column's
    own times (every time field of a line moved by the same amount, whatever clock it is on)."""
    from parsers.csv_vendor import DATETIME_UNITS

    dated = unit in DATETIME_UNITS
    if unit not in _POW10 and not dated:
        raise InputError(f"native CSV export: time unit {unit!r} not supported", path)
    p = _POW10.get(unit, 0)
    buf = np.frombuffer(raw, dtype=np.uint8)
    nl = raw.find(b"\n")
    head = (raw if nl < 0 else raw[:nl]).decode("utf-8", "replace")
    sep = delimiter(head)
    cols = [c.strip().strip('"').lstrip("\ufeff") for c in head.rstrip("\r").split(sep)]
    if time_col not in cols:
        raise InputError(f"native CSV export: no time column {time_col!r} in the header", path)
    k = cols.index(time_col)
    base = nl + 1 if units_row and nl >= 0 else 0  # (the kernel skips the first line of what it is given)
    body = buf[base:]
    ls, le, cs, ce = _kernel("_cells")(body, k, ord(sep))
    if dated:  # ISO 8601 text: the readers' scan (csvtable.iso_cells_to_ns)
        ns, ok, off, dsep, _nfrac, zone, _zkind = iso_cells_to_ns(body, cs, ce)
    else:
        ns, ok = decimal_cells_to_int(body, cs, ce, p, decimal)  # (the readers' scan: every time they read)
        off, dsep, zone = np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.int64)  # (no date-times)
    blank = le <= ls
    # a value in the unit times 10**p is nanoseconds exactly (s: p=9, ms: 6, us: 3, ns: 0)
    new = ns.copy()
    if moved is None:
        new[ok] = shift.to_master_ns(ns[ok])
    else:  # (a line whose other time was not read keeps this one as it is: counted with the damaged lines)
        ok &= moved != _UNREAD
        new[ok] = ns[ok] + moved[ok]
    shifts = np.full(len(ns), _UNREAD, np.int64)
    shifts[ok] = new[ok] - ns[ok]
    last = raw.find(b"\n", base) if base else nl  # (the last header line's end)
    head_end = len(raw) if last < 0 else last + 1
    # (a cell grows by at most 24 bytes: a number's digits; a date-time's 13, 'YYYY-MM-DDTHH:MM' given seconds
    # and nine fractional digits)
    out = np.empty(len(raw) + 24 * len(ls) + 1, dtype=np.uint8)
    out[:head_end] = buf[:head_end]
    n = _kernel("_emit")(body, ls, le, cs, ce, ok, new, p, ord(decimal), off, dsep, zone, out[head_end:])
    return out[:head_end + n], int(ok.sum()), int((~ok & ~blank).sum()), shifts


def _rewrite_file(src: str, dst: str, time_col: str, unit: str, shift: ClockShift, start: int = 0,
                  units_row: bool = False, decimal: str = ".", also: tuple[tuple[str, str], ...] = (),
                  preamble: int = 0) -> tuple[int, int]:
    """``src`` from byte ``start`` restamped into ``dst``: (data lines rewritten, damaged lines kept as they
    were); ``also``: more time columns (column, unit) rewritten the same way; ``preamble``: bytes after
    ``start`` before the header line (comment lines) copied as they are."""
    with open(src, "rb") as fh:
        fh.seek(start)
        raw = fh.read()
    new, n, bad, shifts = restamp_bytes(raw[preamble:], time_col, unit, shift, src, units_row, decimal)
    for col, u in also:  # (moved by each line's shift: a column on another clock too)
        new = restamp_bytes(new.tobytes(), col, u, shift, src, units_row, decimal, moved=shifts)[0]
    with atomic_path(dst) as tmp, open(tmp, "wb") as out:
        out.write(raw[:preamble])
        new.tofile(out)
    return n, bad


def restamp_csv(src: str, dst: str, shift: ClockShift, *, selector=None) -> RestampStats:
    """Canonical CSV: the ``time_s`` column (UNIX or boot seconds). Bytes before the header line (the parser
    skips them: ``csv_canonical.header_offset``) are left out of the output."""
    from parsers.csv_canonical import TIME, header_start

    start = header_start(src)
    n, bad = _rewrite_file(src, dst, TIME, "s", shift, start)
    damage = (f"the first {start} bytes, before the header line, are not CSV: left out",) if start else ()
    if bad:
        damage += (f"{bad} line(s) without a readable time copied unchanged",)
    return RestampStats(path=dst, format="csv", how=HOW, records=n, records_by_type={"rows": n},
                        time_fields=(TIME,), damage=damage)


def _is_csv_unit_folder(path: str) -> bool:
    """A vendor unit's folder of CSV files (no subfolders): what its folder export may replace."""
    names = os.listdir(path)
    return any(f.lower().endswith(".csv") for f in names) and not any(
        os.path.isdir(os.path.join(path, f)) for f in names)


def _replace_dir(tmp_dir: str, dst: str) -> None:
    if os.path.isdir(dst):
        old = dst + ".old-" + os.path.basename(tmp_dir)
        os.replace(dst, old)
        os.replace(tmp_dir, dst)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp_dir, dst)


def restamp_csv_vendor(src: str, dst: str, shift: ClockShift, *, selector=None) -> RestampStats:
    """Vendor CSV (a column map's time column, in its unit); a session/unit folder -> a folder."""
    from parsers import csv_vendor as cv

    sel = selector if isinstance(selector, Selector) else Selector.parse(str(selector or ""))
    s = cv._resolve(src, sel)
    cmap = cv.column_map_for(s, sel)
    time_col = cmap.column_for("time")
    unit = cmap.columns[time_col][1]
    if not os.path.isdir(src):
        n, bad = _rewrite_file(src, dst, time_col, unit, shift, units_row=cmap.units_row, decimal=cmap.decimal,
                               also=cmap.also_time, preamble=cv.header_offset(src))
        return RestampStats(path=dst, format="csv-vendor", how=HOW, records=n, records_by_type={"rows": n},
                            time_fields=(time_col,) + tuple(c for c, _u in cmap.also_time),
                            damage=(f"{bad} line(s) without a readable time copied unchanged",) if bad else ())
    unit_dir = os.path.dirname(s.table)
    check_replaceable(dst, _is_csv_unit_folder, "CSV unit folder")  # (an earlier export of it, nothing else)
    parent = os.path.dirname(os.path.abspath(dst)) or "."
    os.makedirs(parent, exist_ok=True)
    tmp_dir = tempfile.mkdtemp(prefix="." + os.path.basename(dst) + ".", suffix=".tmp", dir=parent)
    by_file: dict[str, int] = {}
    damage: list[str] = []
    try:
        for name in sorted(os.listdir(unit_dir)):
            a, b = os.path.join(unit_dir, name), os.path.join(tmp_dir, name)
            if os.path.isdir(a):
                continue
            header = cv._header_of(a) if name.lower().endswith(".csv") else []
            if time_col in header:
                n, bad = _rewrite_file(a, b, time_col, unit, shift, preamble=cv.header_offset(a))
                by_file[name] = n
                if bad:
                    damage.append(f"{name}: {bad} line(s) without a readable time copied unchanged")
            else:
                shutil.copyfile(a, b)
        os.chmod(tmp_dir, 0o755)
        _replace_dir(tmp_dir, dst)
    except BaseException:
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise
    return RestampStats(path=dst, format="csv-vendor", how=HOW + "; a folder: other files copied",
                        records=sum(by_file.values()), records_by_type=by_file, time_fields=(time_col,),
                        damage=tuple(damage))
