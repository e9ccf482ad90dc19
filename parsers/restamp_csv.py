"""The slave on the master's clock, natively: canonical CSV and vendor CSV (the time column rewritten).

A text-level rewrite: every line is copied as it is except its time cell, which is replaced by the
master-clock time in the column's own unit at full precision (nanoseconds: 9 decimals of a second, 6 of
a millisecond, 3 of a microsecond). Other columns keep their exact text (no float re-formatting), the
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
import pandas as pd

from logtools.errors import InputError
from parsers.atomic import atomic_path
from parsers.base import Selector
from parsers.csvtable import decimal_text_to_int, delimiter
from parsers.restamp import ClockShift, RestampStats

HOW = "text rewrite of the time column (every other cell's text kept)"
_POW10 = {"s": 9, "sec": 9, "ms": 6, "us": 3, "ns": 0}


def _format(ns: np.ndarray, p: int) -> list[str]:
    ns = np.asarray(ns, dtype=np.int64)
    neg = ns < 0
    a = np.abs(ns)
    q = 10 ** p
    whole = (a // q).astype(str)
    if p:
        frac = np.char.zfill((a % q).astype(str), p)
        txt = np.char.add(np.char.add(whole, "."), frac)
    else:
        txt = whole
    return np.where(neg, np.char.add("-", txt), txt).tolist()


def restamp_text(text: str, time_col: str, unit: str, shift: ClockShift, path: str) -> tuple[str, int, int]:
    """(new text, data lines rewritten, damaged lines kept as they were)."""
    if unit not in _POW10:
        raise InputError(f"native CSV export: time unit {unit!r} not supported", path)
    p = _POW10[unit]
    lines = text.split("\n")
    head = lines[0]
    sep = delimiter(head)
    cols = [c.strip().strip('"').lstrip("\ufeff") for c in head.rstrip("\r").split(sep)]
    if time_col not in cols:
        raise InputError(f"native CSV export: no time column {time_col!r} in the header", path)
    k = cols.index(time_col)
    body = lines[1:]
    parts = [ln.split(sep, k + 1) for ln in body]
    cells = [pr[k] if len(pr) > k else "" for pr in parts]
    stripped = pd.Series([c.strip().strip('"') for c in cells], dtype=object)
    ns, ok, _ = decimal_text_to_int(stripped, p) if len(stripped) else (np.zeros(0, np.int64), np.zeros(0, bool), None)
    blank = np.array([not ln.strip() for ln in body], dtype=bool)
    ok = np.asarray(ok, bool) & ~blank
    # a value in the unit is value * 10**p == nanoseconds exactly (s: p=9, ms: 6, us: 3, ns: 0)
    new = np.asarray(ns, np.int64).copy()
    new[ok] = shift.to_master_ns(new[ok])
    txt = _format(new, p)
    out = [head]
    for i, pr in enumerate(parts):
        if ok[i]:
            cell = cells[i]
            lead = cell[:len(cell) - len(cell.lstrip())]
            trail = "\r" if cell.endswith("\r") else ""
            pr = list(pr)
            pr[k] = lead + txt[i] + trail
            out.append(sep.join(pr))
        else:
            out.append(body[i])
    return "\n".join(out), int(ok.sum()), int((~ok & ~blank).sum())


def _rewrite_file(src: str, dst: str, time_col: str, unit: str, shift: ClockShift) -> tuple[int, int]:
    with open(src, "rb") as fh:
        raw = fh.read()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError("native CSV export: the file is not UTF-8 text", src) from None
    new, n, bad = restamp_text(text, time_col, unit, shift, src)
    with atomic_path(dst) as tmp, open(tmp, "wb") as fh:
        fh.write(new.encode("utf-8"))
    return n, bad


def restamp_csv(src: str, dst: str, shift: ClockShift, *, selector=None) -> RestampStats:
    """Canonical CSV: the ``time_s`` column (UNIX or boot seconds)."""
    from parsers.csv_canonical import TIME

    n, bad = _rewrite_file(src, dst, TIME, "s", shift)
    return RestampStats(path=dst, format="csv", how=HOW, records=n, records_by_type={"rows": n},
                        time_fields=(TIME,),
                        damage=(f"{bad} line(s) without a readable time copied unchanged",) if bad else ())


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
        n, bad = _rewrite_file(src, dst, time_col, unit, shift)
        return RestampStats(path=dst, format="csv-vendor", how=HOW, records=n, records_by_type={"rows": n},
                            time_fields=(time_col,),
                            damage=(f"{bad} line(s) without a readable time copied unchanged",) if bad else ())
    unit_dir = os.path.dirname(s.table)
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
                n, bad = _rewrite_file(a, b, time_col, unit, shift)
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
