"""What every CSV reader shares: a tolerant table read (delimiter, malformed and cut-short rows reported)
and decimal text -> exact int64 for time columns (no float64 rounding of epoch stamps; a compiled scan,
numba imported lazily and cached on disk)."""
from __future__ import annotations

import os
import unicodedata
import warnings as _warnings

import numpy as np
import pandas as pd

from logtools.errors import InputError


def _cell_text(buf, j, end):  # pragma: no cover - compiled
    """The text of the cell ``buf[j:end]`` as the cell scans read it: up to a NUL (the padding of a column's
    text), without the spaces and quotes around it and a CR at its end: (its first byte, its end)."""
    w = j
    while w < end and buf[w] != 0:
        w += 1
    while j < w and (buf[j] == 32 or buf[j] == 34):
        j += 1
    while w > j and (buf[w - 1] == 32 or buf[w - 1] == 34 or buf[w - 1] == 13):
        w -= 1
    return j, w


def _decimal_cells(buf, starts, ends, scale_pow10, point):  # pragma: no cover - compiled
    """Decimal text in cells ``buf[starts[i]:ends[i]]`` (bytes; a cell ends at a NUL; spaces and quotes
    around the number, and a CR after it, are allowed; ``starts[i] < 0``: no cell) -> int64 value *
    10**scale_pow10, exactly (digits beyond the scale are truncated), and a validity mask. At most 18
    significant digits before the scale point fit int64. A decimal exponent (``5e-05``,
    ``1.7000000001e+09``: what float formatting writes, pandas' ``to_csv`` for values below 1e-4) is taken
    exactly as well: the number's significant digits (as many as int64 holds: 18-19) scaled by it
    (truncated below the scale, as without one). ``point``: the decimal mark's byte (46 '.', 44 ','). The one
    scan of time text: the readers' columns and the native CSV export's cells."""
    n = starts.shape[0]
    limit = np.int64(9223372036854775807)
    for _ in range(scale_pow10):
        limit //= 10
    limit -= 1
    top = np.int64(922337203685477580)  # (a value that can still be multiplied by 10 within int64)
    out = np.zeros(n, np.int64)
    ok = np.zeros(n, np.bool_)
    for i in range(n):
        j = starts[i]
        if j < 0:
            continue
        j, w = _cell_text(buf, j, ends[i])
        neg = False
        if j < w and (buf[j] == 45 or buf[j] == 43):
            neg = buf[j] == 45
            j += 1
        whole = np.int64(0)
        frac = np.int64(0)
        nfrac = 0
        ndig = 0
        seen_dot = False
        good = True
        whole_over = False  # the whole part beyond int64 once scaled (without an exponent: invalid)
        mant = np.int64(0)  # the significant digits, as many as int64 holds (for an exponent)
        nsig = 0
        shift = 0  # the mantissa's own power of ten
        has_exp = False
        exp_neg = False
        exp = 0
        ndig_exp = 0
        while j < w:
            c = np.int64(buf[j])
            if has_exp:
                if 48 <= c <= 57:
                    exp = min(exp * 10 + (c - 48), 1000)
                    ndig_exp += 1
                else:
                    good = False
            elif c == point and not seen_dot:
                seen_dot = True
            elif 48 <= c <= 57:
                ndig += 1
                d = c - 48
                if nsig > 0 or d != 0:
                    if mant < top or (mant == top and d <= 7):  # (int64: 19 digits up to 9.22e18)
                        mant = mant * 10 + d
                        nsig += 1
                        if seen_dot:
                            shift -= 1
                    elif not seen_dot:
                        shift += 1
                elif seen_dot:
                    shift -= 1
                if seen_dot:
                    if nfrac < scale_pow10:
                        frac = frac * 10 + d
                        nfrac += 1
                elif not whole_over:
                    whole = whole * 10 + d
                    if whole > limit:  # would overflow int64 once scaled
                        whole_over = True
                        whole = 0
            elif (c == 101 or c == 69) and ndig > 0:  # e, E: the exponent, its sign, then digits
                has_exp = True
                if j + 1 < w and (buf[j + 1] == 45 or buf[j + 1] == 43):
                    exp_neg = buf[j + 1] == 45
                    j += 1
            else:
                good = False
            j += 1
        if not good or ndig == 0:
            continue
        if has_exp:
            if ndig_exp == 0:
                continue
            p = scale_pow10 + shift + (-exp if exp_neg else exp)
            v = mant
            while p > 0 and v > 0:
                if v > top:
                    good = False
                    break
                v *= 10
                p -= 1
            while p < 0 and v > 0:
                v //= 10
                p += 1
            if not good:
                continue
        else:
            if whole_over:
                continue
            v = whole
            for _ in range(scale_pow10):
                v *= 10
            f = frac
            for _ in range(scale_pow10 - nfrac):
                f *= 10
            v += f
        out[i] = -v if neg else v
        ok[i] = True
    return out, ok


_KERNELS: dict = {}


def _cells_kernel(fn):
    """The cell scan ``fn`` compiled with numba on first use (cached on disk) when this process runs compiled
    kernels (logtools.jit); the plain function otherwise, with numpy's overflow warnings off (plain Python
    over numpy scalars: the overflow guards' wrap-around warns there)."""
    kernel = _KERNELS.get(fn.__name__)
    if kernel is None:
        from logtools import jit

        if jit.compiled():
            if not hasattr(_cell_text, "py_func"):  # (the scans' helper compiled first: they call it natively)
                globals()["_cell_text"] = jit.njit(_cell_text, nogil=True)
            kernel = jit.njit(fn, nogil=True)
        else:
            def kernel(*args, _fn=fn):
                with np.errstate(over="ignore"):
                    return _fn(*args)
        _KERNELS[fn.__name__] = kernel
    return kernel


def decimal_cells_to_int(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, scale_pow10: int,
                         decimal: str = ".") -> tuple[np.ndarray, np.ndarray]:
    """(int64 value * 10**scale_pow10, valid mask) of the decimal text in cells ``buf[starts[i]:ends[i]]``
    (:func:`_decimal_cells`, :func:`_cells_kernel`)."""
    return _cells_kernel(_decimal_cells)(buf, np.asarray(starts, np.int64), np.asarray(ends, np.int64),
                                         scale_pow10, ord(decimal))


def _iso_cells(buf, starts, ends):  # pragma: no cover - compiled
    """ISO 8601 date-time text in cells ``buf[starts[i]:ends[i]]`` (as :func:`_decimal_cells` takes them:
    spaces, quotes and a CR around, a NUL ending; ``starts[i] < 0``: no cell): ``YYYY-MM-DD`` then ``T``, ``t``
    or a space, ``HH:MM`` and optionally ``:SS`` and a fraction (``.`` or ``,``; digits beyond nanoseconds
    truncated), then nothing (no zone: UTC), ``Z`` or an offset ``+HH``, ``+HH:MM``, ``+HHMM``. Returns int64
    ns since the UNIX epoch (UTC), the validity mask, and per cell: its offset from UTC (s), its separator's
    byte, its fraction's digits, where its zone text starts and its kind (0 none, 1 ``Z``, 2 an offset). The
    one scan of date-time text: the readers' columns and the native CSV export's cells."""
    n = starts.shape[0]
    out = np.zeros(n, np.int64)
    ok = np.zeros(n, np.bool_)
    off = np.zeros(n, np.int64)
    sep = np.full(n, 84, np.uint8)
    nfrac = np.zeros(n, np.int64)
    zone = np.zeros(n, np.int64)
    zkind = np.zeros(n, np.int64)
    for i in range(n):
        j = starts[i]
        if j < 0:
            continue
        j, w = _cell_text(buf, j, ends[i])
        # the fields' digits at their fixed places: year, month, day, hour, minute, second (-1: not digits)
        vals = np.full(6, -1, np.int64)
        for f in range(6):
            p0 = j + (0, 5, 8, 11, 14, 17)[f]
            nd = 4 if f == 0 else 2
            if p0 + nd <= w:
                v = np.int64(0)
                for q in range(p0, p0 + nd):
                    c = np.int64(buf[q])  # (not uint8 arithmetic)
                    if c < 48 or c > 57:
                        v = -1
                        break
                    v = v * 10 + (c - 48)
                vals[f] = v
        y, mo, d, h, mi = vals[0], vals[1], vals[2], vals[3], vals[4]
        if (j + 16 > w or y < 0 or mo < 1 or mo > 12 or d < 1 or h < 0 or h > 23 or mi < 0 or mi > 59 or buf[j + 4] != 45
                or buf[j + 7] != 45 or buf[j + 13] != 58 or not (buf[j + 10] == 84 or buf[j + 10] == 116
                                                                 or buf[j + 10] == 32)):
            continue
        leap = (y % 4 == 0 and y % 100 != 0) or y % 400 == 0
        mdays = 31
        if mo == 2:
            mdays = 29 if leap else 28
        elif mo == 4 or mo == 6 or mo == 9 or mo == 11:
            mdays = 30
        if d > mdays:
            continue
        k = j + 16
        sec = 0
        frac = np.int64(0)
        nf = 0
        if k < w and buf[k] == 58:
            sec = vals[5]
            if sec < 0 or sec > 59:
                continue
            k += 3
            if k < w and (buf[k] == 46 or buf[k] == 44):
                k += 1
                while k < w and 48 <= buf[k] <= 57:
                    if nf < 9:
                        frac = frac * 10 + (np.int64(buf[k]) - 48)
                        nf += 1
                    k += 1
                if nf == 0:
                    continue
        scale = np.int64(1)
        for _ in range(9 - nf):
            scale *= 10
        o = 0
        zk = 0
        if k < w:
            if (buf[k] == 90 or buf[k] == 122) and k + 1 == w:
                zk = 1
            elif buf[k] == 43 or buf[k] == 45:
                zk = 2
                # +HH, +HH:MM or +HHMM: its digits at their places
                q0 = k + 4 if (k + 6 == w and buf[k + 3] == 58) else k + 3
                zh = zm = np.int64(0)
                good = k + 3 == w or k + 5 == w or (k + 6 == w and buf[k + 3] == 58)
                for q in range(k + 1, w):
                    if q == k + 3 and q0 == k + 4:
                        continue
                    c = np.int64(buf[q])
                    if c < 48 or c > 57:
                        good = False
                        break
                    if q < k + 3:
                        zh = zh * 10 + (c - 48)
                    else:
                        zm = zm * 10 + (c - 48)
                if not good:
                    zh = -1
                if zh < 0 or zh > 23 or zm < 0 or zm > 59:
                    continue
                o = zh * 3600 + zm * 60
                if buf[k] == 45:
                    o = -o
            else:
                continue
        # days from the civil date (H. Hinnant's algorithm), proleptic Gregorian
        yy = y - (1 if mo <= 2 else 0)
        era = (yy if yy >= 0 else yy - 399) // 400
        yoe = yy - era * 400
        doy = (153 * (mo + (-3 if mo > 2 else 9)) + 2) // 5 + d - 1
        doe = yoe * 365 + yoe // 4 - yoe // 100 + doy
        days = np.int64(era * 146097 + doe - 719468)
        out[i] = ((days * 86400 + h * 3600 + mi * 60 + sec - o) * np.int64(1_000_000_000) + frac * scale)
        ok[i] = True
        off[i] = o
        sep[i] = buf[j + 10]
        nfrac[i] = nf
        zone[i] = k
        zkind[i] = zk
    return out, ok, off, sep, nfrac, zone, zkind


def iso_cells_to_ns(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray):
    """:func:`_iso_cells` (:func:`_cells_kernel`)."""
    return _cells_kernel(_iso_cells)(buf, np.asarray(starts, np.int64), np.asarray(ends, np.int64))


def datetime_text_to_ns(text: pd.Series) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """ISO 8601 date-time text (:func:`_iso_cells`: ``2024-05-01T12:00:00.125Z``, ``2024-05-01 12:00:00.125``,
    an offset ``+02:00``) -> (int64 ns since the UNIX epoch, UTC; valid mask; resolution s: that of a fixed
    number of fractional digits, else 0; True where some text gives no time zone: taken as UTC)."""
    raw = _text_bytes(text)
    starts = np.arange(len(raw), dtype=np.int64) * raw.shape[1]
    ends = starts + raw.shape[1]
    ns, ok, _off, _sep, nfrac, _zone, zkind = iso_cells_to_ns(raw.reshape(-1), starts, ends)
    if not ok.any():
        return ns, ok, 0.0, False
    nf = nfrac[ok]
    res = 10.0 ** -int(nf[0]) if np.all(nf == nf[0]) else 0.0
    return ns, ok, res, bool(np.any(zkind[ok] == 0))


def _text_bytes(text: pd.Series) -> np.ndarray:
    """The column's text as a (n, width) uint8 array, NUL-padded."""
    t = text.fillna("").astype(str)
    width = max(1, int(t.str.len().max())) if len(t) else 1
    try:
        chars = t.to_numpy(dtype=f"S{width}")
    except UnicodeEncodeError:  # non-ASCII bytes from a damaged file: they make their rows invalid
        chars = np.char.encode(t.to_numpy(dtype=str), "ascii", "replace").astype(f"S{width}")
    return np.frombuffer(chars.tobytes(), np.uint8).reshape(len(t), width) if len(t) else np.zeros((0, 1), np.uint8)


def decimal_text_to_int(text: pd.Series, scale_pow10: int, decimal: str = "."
                        ) -> tuple[np.ndarray, np.ndarray, int | None]:
    """Decimal numbers as text -> (int64 value * 10**scale_pow10, valid mask, fixed decimals), exactly.
    The last is the number of decimals every valid value is written with when it is the same for all
    (a writer's fixed format, ``%.3f``: the values' resolution is 10**-decimals), else None. ``decimal``: the
    decimal mark ("," in a CSV saved in a comma-decimal locale)."""
    raw = _text_bytes(text)
    starts = np.arange(len(raw), dtype=np.int64) * raw.shape[1]
    ns, ok = decimal_cells_to_int(raw.reshape(-1), starts, starts + raw.shape[1], scale_pow10, decimal)
    return ns, ok, _fixed_decimals(raw[ok], decimal)


def _fixed_decimals(raw: np.ndarray, decimal: str = ".") -> int | None:
    """The common number of decimals of text rows (None: they differ, or exponents)."""
    if len(raw) == 0 or np.any((raw == ord("e")) | (raw == ord("E"))):
        return None
    body = (raw != 0) & (raw != ord(" "))
    last = raw.shape[1] - 1 - np.argmax(body[:, ::-1], axis=1)  # last non-blank character
    dot = raw == ord(decimal)
    pos = np.where(dot.any(axis=1), np.argmax(dot, axis=1), last)
    dec = last - pos
    return int(dec[0]) if np.all(dec == dec[0]) else None


def numeric_block(df: pd.DataFrame, cols) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Columns ``cols`` of ``df`` as float64 (n, len(cols)), a cell holding text that is not a number
    (damaged bytes) read as NaN; also the rows holding such a cell and how many such cells each column has
    (only the columns that have any, for :func:`non_numeric_text`)."""
    parts, rows, counts = [], np.zeros(len(df), bool), {}
    for c in cols:
        num = pd.to_numeric(df[c], errors="coerce")
        text = (df[c].notna() & num.isna()).to_numpy()
        if text.any():
            counts[str(c)] = int(text.sum())
            rows |= text
        parts.append(num.to_numpy(float))
    return (np.stack(parts, axis=1) if parts else np.zeros((len(df), 0))), rows, counts


def non_numeric_text(counts: dict[str, int]) -> str:
    """``numeric_block``'s per-column counts in words: ``3 non-numeric cell(s) (accel_x_m_s2 2, qw 1)``."""
    return (f"{sum(counts.values())} non-numeric cell(s) ("
            + ", ".join(f"{printable(c)} {n}" for c, n in counts.items()) + ")")


def printable(text: str, limit: int = 40) -> str:
    """``text`` (a column name from a damaged file, say) on one line of printable characters: anything else
    shown as ``?``, long text cut with ``...``."""
    s = "".join(ch if ch.isprintable() and (ch.isascii() or not unicodedata.combining(ch)) else "?"
                for ch in str(text).replace("\ufffd", "?"))
    return s if len(s) <= limit else s[:limit] + "..."


def delimiter(header: str) -> str:
    counts = {d: header.count(d) for d in (",", ";", "\t")}
    return max(counts, key=counts.get)


def read_table(path: str, time_col: str, start: int = 0, units_row: bool = False, decimal: str = "."
               ) -> tuple[pd.DataFrame, list[str]]:
    """The CSV at ``path`` from byte ``start`` (its header line: bytes before it skipped), as text columns
    where the time is, and the warnings of its damaged lines; ``units_row``: the line after the header gives
    units, not data (skipped); ``decimal``: the numbers' decimal mark."""
    warns: list[str] = []
    with open(path, "rb") as fh:
        fh.seek(start)
        first = fh.readline(65536).decode("utf-8", "replace")
    sep = delimiter(first)
    with _warnings.catch_warnings(record=True) as caught, open(path, "rb") as src:
        _warnings.simplefilter("always")
        src.seek(start)
        try:
            # index_col=False: lines with more cells than the header (a delimiter after the last value, as
            # many loggers write) keep their columns; pandas would take the extra cells' count of first
            # columns as the index and shift every column by it, time into the index, silently
            df = pd.read_csv(src if start else path, sep=sep, dtype={time_col: str}, skipinitialspace=True,
                             on_bad_lines="warn", encoding_errors="replace", skiprows=[1] if units_row else None,
                             decimal=decimal, index_col=False)
        except pd.errors.EmptyDataError:
            raise InputError("empty CSV (no header)", path) from None
        except pd.errors.ParserError as exc:
            raise InputError(f"malformed CSV: {str(exc).splitlines()[0]}", path) from None
    if any("does not match length of data" in str(w.message) for w in caught):
        warns.append(f"{os.path.basename(path)}: its lines hold more cells than the header names columns: the cells "
                     "beyond the header's columns are not read")
    bad = [w for w in caught if "Skipping line" in str(w.message) or "expected" in str(w.message)]
    if bad:
        n = sum(str(w.message).count("Skipping line") or 1 for w in bad)
        first_msg = str(bad[0].message).strip().splitlines()[0]
        warns.append(f"{os.path.basename(path)}: {n} malformed line(s) skipped (first: {first_msg})")
    df.columns = [str(c).strip().strip('"') for c in df.columns]
    with open(path, "rb") as fh:
        fh.seek(max(0, os.path.getsize(path) - 65536))
        tail = fh.read()
    if tail and not tail.endswith(b"\n") and len(df):
        last = tail.rsplit(b"\n", 1)[-1].decode("utf-8", "replace")
        if last.count(sep) < len(df.columns) - 1:
            warns.append(f"{os.path.basename(path)}: last row cut short (file truncated?): dropped")
            df = df.iloc[:-1]
    return df, warns
