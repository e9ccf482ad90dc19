"""Parquet with the canonical columns: what ``--write-slave parquet`` writes, read back.

A table with ``time_ns`` (int64 nanoseconds, UNIX or since boot: exact) and/or ``time_s`` (float64 seconds)
and the canonical CSV's column names (DESIGN.md, "CSV contract"; FRD/NED), one row per sample, NaN where a
row lacks a group. ``time_ns`` is the stamp where both are there (``time_s`` as float64 holds epoch stamps
to about 0.2 us only). The rows are assembled as the canonical CSV's are (``csv_canonical.assemble_rows``):
the same checks, warnings and InsLog. Read with pyarrow; a file pyarrow cannot read (cut, damaged, not
Parquet after all) is one clear error.
"""
from __future__ import annotations

import os

import numpy as np

from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers.base import Inventory, Selector

NAME = "parquet"
EXTENSIONS = (".parquet", ".pq")
MAGIC = b"PAR1"  # (a Parquet file's first and last four bytes)

TIME_NS = "time_ns"


def sniff(head: bytes, path: str) -> bool:
    return head[:4] == MAGIC


def read_parquet(path: str):
    """The pyarrow table of ``path``; InputError for what pyarrow cannot read."""
    try:
        import pyarrow.parquet as pq
    except ImportError as exc:  # pragma: no cover - pyarrow is a dependency
        raise InputError(f"reading Parquet needs pyarrow ({exc})", path) from None
    with open(path, "rb") as fh:
        fh.seek(0, os.SEEK_END)
        size = fh.tell()
        fh.seek(max(0, size - 4))
        tail = fh.read(4)
    if size < 12 or tail != MAGIC:
        raise InputError("damaged Parquet file: its footer (the schema and where the rows are) is missing "
                         "(cut short while written or copied?)", path)
    try:
        return pq.read_table(path)
    except (OSError, ValueError) as exc:  # (pyarrow's ArrowInvalid / ArrowIOError are both)
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"damaged Parquet file ({text})", path) from None


def seconds_of_ns(ns: np.ndarray) -> np.ndarray:
    """The float64 ``time_s`` column written beside ``time_ns``: whole seconds plus the fraction (the nearest
    float to the stamp, about 0.2 us at UNIX epoch)."""
    return ns // 1_000_000_000 + (ns % 1_000_000_000) * 1e-9


def stamps_ns(table, path: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(int64 ns stamps, which rows have one, the column they come from) of a pyarrow table: ``time_ns``
    (integers, exact) where it is there, else ``time_s`` (float64 seconds, rounded to the ns); InputError for
    neither or a ``time_ns`` that is not integers."""
    from parsers.csv_canonical import TIME

    names = list(table.column_names)
    if TIME_NS in names:
        col = table.column(TIME_NS)
        if not str(col.type).startswith(("int", "uint")):
            raise InputError(f"column '{TIME_NS}' is {col.type}, not an integer count of nanoseconds", path)
        ok = ~np.asarray(col.is_null().to_numpy(zero_copy_only=False), bool)
        return np.asarray(col.to_numpy(zero_copy_only=False), dtype=np.int64), ok, TIME_NS
    if TIME in names:
        t = np.asarray(table.column(TIME).to_numpy(zero_copy_only=False), dtype=float)
        ok = np.isfinite(t)
        t_ns = np.zeros(len(t), np.int64)
        t_ns[ok] = np.round(t[ok] * 1e9).astype(np.int64)
        return t_ns, ok, TIME
    raise InputError(f"no '{TIME_NS}' or '{TIME}' column (tapost's Parquet export expected; columns: "
                     f"{', '.join(names[:8])}{' ...' if len(names) > 8 else ''})", path)


def load(path: str, selector: Selector) -> InsLog:
    import pandas as pd

    from parsers.csv_canonical import CSV_EULER, HEADER, TIME, assemble_rows

    if selector:
        raise InputError(f"a canonical Parquet file holds one unit: selector '{selector}' does not apply", path)
    table = read_parquet(path)
    t_ns, ok, time_col = stamps_ns(table, path)
    warnings: list[str] = []
    if time_col == TIME:
        warnings.append(f"note: stamps from the float64 '{TIME}' column (no '{TIME_NS}'): epoch stamps are "
                        "exact to about 0.2 us only")
    data = {}
    for c in table.column_names:
        if c in HEADER[1:] or c in CSV_EULER:
            arr = table.column(c).to_numpy(zero_copy_only=False)
            try:
                data[c] = np.asarray(arr, dtype=float)
            except (TypeError, ValueError):
                raise InputError(f"column '{c}' is {table.column(c).type}, not numbers", path) from None
        elif c not in (TIME, TIME_NS):
            data[c] = np.zeros(len(t_ns))  # (named in the warnings only; never read)
    df = pd.DataFrame(data, index=pd.RangeIndex(len(t_ns)))
    df.insert(0, time_col, t_ns)
    if not ok.all():
        warnings.append(f"{int((~ok).sum())} row(s) without a time dropped")
        t_ns, df = t_ns[ok], df[ok]
    if not len(df):
        raise InputError("no data rows", path)
    return assemble_rows(path, df, t_ns, 9 if time_col == TIME_NS else None, warnings, fmt=NAME,
                         time_col=time_col, stamp_source=f"parquet {time_col} column", row="row", first_row=0)


def inventory(path: str) -> Inventory:
    from parsers.csv_canonical import rows_inventory

    return rows_inventory(path, load(path, Selector()))
