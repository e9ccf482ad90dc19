"""The slave on the master's clock, written out (DESIGN.md, "The slave on the master's clock").

``write_slave(kinds, out_dir, slave_arg, slave, shift)`` writes, next to the report:

* ``csv``: ``slave_on_master_clock.csv``, the canonical CSV columns the slave has (IMU, attitude,
  velocity, position; FRD/NED), one row per sample (IMU and nav rows merged on equal stamps), ``time_s``
  on the master's clock with 9 decimals (exact nanoseconds);
* ``parquet``: ``slave_on_master_clock.parquet``, the same columns plus ``time_ns`` (int64, exact);
* ``native``: the slave's own format, every record kept and only its time fields rewritten, by the
  format's writer next to its reader (``parsers.restamp_*``): ``.tlog``, ``.bin``, ``.ulg``, ``.csv``
  (``.native.csv`` when ``csv`` is written too), ``.bag``, ``.mcap``, or a folder (rosbag2, NGIMU).

All use one :class:`parsers.restamp.ClockShift` (drift included, ``logtools.compensate``'s exact
``tau``), so the exports agree with each other and with the compensated analysis. The CSV/Parquet rows
are the slave's own samples (``--compensation restamp``), whatever compensation the alignment used.
Every file is written atomically; a failure of one export is recorded, the others still written.
"""
from __future__ import annotations

import importlib
import os
import struct
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from logtools.errors import InputError, os_error_path
from logtools.inslog import ACCEL, GYRO, POS, QUAT, VEL, InsLog
from parsers.atomic import atomic_path
from parsers.restamp import ClockShift, RestampStats

if TYPE_CHECKING:  # (pandas is imported where a table is made: a run that writes none never loads it)
    import pandas as pd

KINDS = ("csv", "parquet", "native")
BASENAME = "slave_on_master_clock"

#: reader format NAME -> (writer module, function, output suffix; "" = a folder)
NATIVE_WRITERS: dict[str, tuple[str, str, str]] = {
    "tlog": ("parsers.restamp_mavlink", "restamp_tlog", ".tlog"),
    "dataflash": ("parsers.restamp_mavlink", "restamp_dataflash", ".bin"),
    "ulog": ("parsers.restamp_ulog", "restamp_ulog", ".ulg"),
    "csv": ("parsers.restamp_csv", "restamp_csv", ".csv"),
    "csv-vendor": ("parsers.restamp_csv", "restamp_csv_vendor", ".csv"),
    "rosbag1": ("parsers.restamp_ros", "restamp_rosbag1", ".bag"),
    "rosbag2": ("parsers.restamp_ros", "restamp_rosbag2", ""),
    "mcap": ("parsers.restamp_ros", "restamp_mcap", ".mcap"),
    "parquet": ("parsers.restamp_parquet", "restamp_parquet", ".parquet"),
}


def parse_kinds(text, option: str = "--write-slave") -> tuple[str, ...]:
    """``csv,parquet,native`` -> ('csv', 'parquet', 'native'); InputError naming what is unknown (and the
    ``option`` it was given to)."""
    if text is None or text == "" or text == ():
        return ()
    items = text if isinstance(text, (list, tuple)) else str(text).split(",")
    out: list[str] = []
    for k in (str(x).strip().lower() for x in items):
        if not k:
            continue
        if k not in KINDS:
            raise InputError(f"{option} takes {', '.join(KINDS)} (comma-separated), not {k!r}")
        if k not in out:
            out.append(k)
    return tuple(out)


@dataclass(frozen=True)
class ExportEntry:
    """One written (or failed) export, as report.json ``slave_on_master_clock.files`` lists it."""

    kind: str
    path: str | None
    format: str
    how: str
    records: int = 0
    records_by_type: dict | None = None
    time_fields: tuple[str, ...] = ()
    damage: tuple[str, ...] = ()
    seconds: float = 0.0
    failed: str | None = None

    def as_dict(self) -> dict:
        d = {"kind": self.kind, "path": os.path.basename(self.path) if self.path else None,
             "format": self.format, "how": self.how, "records": self.records,
             "time_fields": list(self.time_fields), "damage": list(self.damage), "seconds": self.seconds}
        if self.records_by_type:
            d["records_by_type"] = dict(self.records_by_type)
        if self.failed:
            d["failed"] = self.failed
        return d


# ---- CSV / Parquet -------------------------------------------------------------------------------
def _abs_ns(log: InsLog, df: pd.DataFrame) -> np.ndarray:
    return np.int64(log.meta.t0_ns) + np.round(df.index.to_numpy(dtype=float) * 1e9).astype(np.int64)


def table_on_master_clock(slave: InsLog, shift: ClockShift) -> pd.DataFrame:
    """The slave's samples as one table: ``time_ns`` (master clock, int64) + canonical CSV columns."""
    import pandas as pd

    from parsers.csv_canonical import CSV_QUAT, HEADER

    parts = []
    if len(slave.imu):
        cols = [c for c in GYRO + ACCEL if c in slave.imu.columns]
        if cols:
            f = slave.imu[cols].copy()
            f.index = pd.Index(shift.to_master_ns(_abs_ns(slave, slave.imu)), name="time_ns")
            parts.append(f[~f.index.duplicated()])
    if len(slave.nav):
        cols = [c for c in QUAT + VEL + POS if c in slave.nav.columns]
        if cols:
            f = slave.nav[cols].rename(columns=dict(zip(QUAT, CSV_QUAT))).copy()
            f.index = pd.Index(shift.to_master_ns(_abs_ns(slave, slave.nav)), name="time_ns")
            parts.append(f[~f.index.duplicated()])
    if not parts:
        raise InputError("the slave holds no samples to export", slave.meta.source_path)
    merged = parts[0]
    for p in parts[1:]:
        merged = merged.join(p, how="outer")
    merged = merged.sort_index()
    cols = [c for c in HEADER[1:] if c in merged.columns]
    return merged[cols]


def write_csv(path: str, table: pd.DataFrame) -> int:
    """The canonical CSV: the time column as exact decimal seconds (9 decimals, from int64 ns), every
    value as the shortest decimal that reads back to the same float64, empty cells for NaN. Written by
    Arrow's CSV writer (pandas' ``to_csv`` took 44 s for a 1 h 200 Hz slave)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    from parsers.csv_canonical import TIME, ns_to_seconds_text

    cols = {TIME: pa.array(ns_to_seconds_text(table.index.to_numpy(np.int64), 9), pa.string())}
    for c in table.columns:
        cols[str(c)] = pa.array(table[c].to_numpy(float), pa.float64(), from_pandas=True)  # NaN -> empty
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write((",".join(cols) + "\n").encode())
            pacsv.write_csv(pa.table(cols), fh, write_options=pacsv.WriteOptions(
                include_header=False, quoting_style="none"))
    return len(table)


def write_parquet(path: str, table: pd.DataFrame, meta: dict[str, str]) -> int:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as exc:  # pragma: no cover - pyarrow is a dependency
        raise InputError(f"parquet export needs pyarrow ({exc})") from None
    from parsers.parquet_canonical import seconds_of_ns

    ns = table.index.to_numpy(np.int64)
    cols = {"time_ns": pa.array(ns, pa.int64()), "time_s": pa.array(seconds_of_ns(ns), pa.float64())}
    for c in table.columns:
        cols[c] = pa.array(table[c].to_numpy(float), pa.float64())
    tab = pa.table(cols).replace_schema_metadata({f"tapost.{k}": str(v) for k, v in meta.items()})
    with atomic_path(path) as tmp:
        pq.write_table(tab, tmp)
    return len(ns)


# ---- native --------------------------------------------------------------------------------------
def native_writer(fmt: str):
    """(function, suffix) of the native writer for reader format ``fmt``; InputError when there is none."""
    spec = NATIVE_WRITERS.get(fmt)
    if spec is None:
        raise InputError(f"native export for format {fmt!r} not available (known: {', '.join(NATIVE_WRITERS)})")
    mod_name, fn_name, suffix = spec
    try:
        mod = importlib.import_module(mod_name)
    except ModuleNotFoundError as exc:
        if exc.name != mod_name:
            raise
        raise InputError(f"native export for {fmt} not available in this installation ({mod_name} missing)") \
            from None
    fn = getattr(mod, fn_name, None)
    if fn is None:
        raise InputError(f"native export for {fmt} not available ({mod_name}.{fn_name} missing)")
    return fn, suffix


def native_path(out_dir: str, fmt: str, src_path: str, kinds: tuple[str, ...]) -> str:
    suffix = NATIVE_WRITERS.get(fmt, ("", "", ""))[2]
    if fmt == "csv-vendor" and os.path.isdir(src_path):
        suffix = ""
    if suffix in (".csv", ".parquet") and suffix[1:] in kinds:
        suffix = ".native" + suffix  # the canonical export owns slave_on_master_clock.csv / .parquet
    return os.path.join(out_dir, BASENAME + suffix)


def _is_input(dst: str, inputs: tuple[str, ...]) -> str | None:
    """The input ``dst`` would replace (the same file, also through a link or another spelling), or hold (a
    folder output replaces the folder whole: a ROS 2 bag's storage file given as the slave inside the folder
    the bag export goes to), else None."""
    for src in inputs:
        try:
            if src and os.path.exists(dst) and os.path.samefile(src, dst):
                return src
            if src and os.path.isdir(dst) and os.path.exists(src):
                inside = os.path.relpath(os.path.realpath(src), os.path.realpath(dst))
                if inside != os.curdir and not inside.startswith(os.pardir + os.sep) and inside != os.pardir:
                    return src
        except (OSError, ValueError):  # an input gone since it was read: nothing to protect
            pass
    return None


def write_native(src_path: str, dst: str, fmt: str, shift: ClockShift, selector: str | None) -> RestampStats:
    fn, _ = native_writer(fmt)
    if _is_input(dst, (src_path,)) is not None:
        raise InputError(f"native export would overwrite an input ({dst})", src_path)
    return fn(src_path, dst, shift, selector=selector or None)


# ---- orchestration -------------------------------------------------------------------------------
def write_slave(kinds: tuple[str, ...], out_dir: str, slave: InsLog, shift: ClockShift,
                *, out_path: str | None = None, inputs: tuple[str, ...] = ()) -> list[ExportEntry]:
    """Write each requested export of ``slave`` (its InsLog as parsed, on its own clock) in ``out_dir``.
    ``out_path`` (one kind only) names the file instead. Failures become entries with ``failed``. No
    output replaces the slave's file or any of ``inputs`` (the master's): that export fails instead."""
    entries: list[ExportEntry] = []
    table = None
    meta = slave.meta
    for kind in kinds:
        t = time.perf_counter()
        try:
            tabular = kind in ("csv", "parquet")
            path = out_path or (os.path.join(out_dir, f"{BASENAME}.{kind}") if tabular else
                                native_path(out_dir, meta.format, meta.source_path, kinds))
            hit = _is_input(path, (meta.source_path,) + tuple(inputs))
            if hit is not None:
                raise InputError(f"{kind} export would overwrite an input ({path})", hit)
            if tabular:
                if table is None:
                    table = table_on_master_clock(slave, shift)
                n = (write_csv(path, table) if kind == "csv" else
                     write_parquet(path, table, {"slave": meta.source_path, "selector": meta.selector,
                                                 "latency_s": shift.latency_s, "drift_ppm": shift.drift_ppm,
                                                 "t_ref_ns": shift.t_ref_ns}))
                entries.append(ExportEntry(kind, path, kind, "the slave's samples, stamps on the master's "
                                           "clock (canonical columns)", records=n,
                                           time_fields=("time_s",) + (("time_ns",) if kind == "parquet" else ()),
                                           seconds=time.perf_counter() - t))
            else:
                st = write_native(meta.source_path, path, meta.format, shift, meta.selector)
                entries.append(ExportEntry(kind, st.path, st.format, st.how, st.records, st.records_by_type,
                                           st.time_fields, st.damage, time.perf_counter() - t))
        except InputError as exc:
            entries.append(ExportEntry(kind, None, meta.format if kind == "native" else kind, "", failed=str(exc),
                                       seconds=time.perf_counter() - t))
        except OSError as exc:  # the output could not be written (disk full, permissions...)
            where = os_error_path(exc)
            why = f"cannot write: {exc.strerror or exc}" + (f" ({where})" if where else "")
            entries.append(ExportEntry(kind, None, meta.format if kind == "native" else kind, "", failed=why,
                                       seconds=time.perf_counter() - t))
        except (ValueError, IndexError, KeyError, struct.error) as exc:  # a damaged input a writer choked on
            entries.append(ExportEntry(kind, None, meta.format if kind == "native" else kind, "",
                                       failed=f"{meta.source_path}: cannot export: {type(exc).__name__}: {exc}",
                                       seconds=time.perf_counter() - t))
    return entries


def report_section(entries: list[ExportEntry], shift: ClockShift) -> dict:
    """report.json ``slave_on_master_clock``: the shift applied and every file written."""
    return {"latency_s": shift.latency_s, "drift_ppm": shift.drift_ppm, "t_ref_ns": int(shift.t_ref_ns),
            "formula": "t_master = t_slave - (latency_s + drift (t_slave - t_ref)) / (1 + drift)",
            "files": [e.as_dict() for e in entries]}


def output_keys(entries: list[ExportEntry]) -> dict[str, str | None]:
    """report.json ``outputs`` entries: ``slave_csv``, ``slave_parquet``, ``slave_native``."""
    return {f"slave_{e.kind}": e.path for e in entries}


def warnings_of(entries: list[ExportEntry]) -> list[str]:
    out = []
    for e in entries:
        if e.failed:
            out.append(f"slave export {e.kind} failed: {e.failed}")
        for d in e.damage:
            out.append(f"slave export {e.kind} ({os.path.basename(e.path or '')}): {d}")
    return out


def clock_step_caveat(quality: dict | None) -> str | None:
    """The warning for an export whose latency found a clock step (``quality["clock_step"]``): one line put
    through both sides of the step, so either side's stamps are off by about half the step."""
    step = quality.get("clock_step") if isinstance(quality, dict) else None
    if not isinstance(step, dict) or not isinstance(step.get("step_s"), (int, float)):
        return None
    half = 0.5 * abs(float(step["step_s"])) * 1e3
    t = step.get("t_rel_s")
    where = f" near {float(t):.1f} s into the master log" if isinstance(t, (int, float)) else ""
    return (f"the latency steps by {float(step['step_s']) * 1e3:+.1f} ms{where}: the export puts one line through "
            f"both sides, so its stamps are off by about {half:.1f} ms on either side (export each part apart)")


def attach_to_analysis(kinds: tuple[str, ...], out_dir: str, slave: InsLog, master: InsLog, latency,
                       paths: dict, extra: dict) -> list[ExportEntry]:
    """``tapost analyze --write-slave``: write the exports, list them in ``paths`` (report.json
    ``outputs``), the section ``slave_on_master_clock`` and any damage or failure as warnings."""
    shift = ClockShift.from_latency(latency, master.meta.t0_ns)
    entries = write_slave(tuple(kinds), out_dir, slave, shift, inputs=(master.meta.source_path,))
    paths.update(output_keys(entries))
    extra["slave_on_master_clock"] = report_section(entries, shift)
    warns = warnings_of(entries)
    caveat = clock_step_caveat(latency.quality) if entries else None
    if caveat:
        extra["slave_on_master_clock"]["clock_step"] = caveat
        warns.append(f"slave export: {caveat}")
    if warns:
        extra.setdefault("warnings", []).extend({"stage": "outputs", "text": w} for w in warns)
    return entries


def summary_from_report(rep: dict) -> list[str]:
    sec = rep.get("slave_on_master_clock") or {}
    out = []
    for f in sec.get("files", []):
        if f.get("failed"):
            out.append(f"slave on master clock ({f['kind']}): FAILED: {f['failed']}")
        else:
            dmg = f"; damage: {'; '.join(f['damage'])}" if f.get("damage") else ""
            out.append(f"slave on master clock ({f['kind']}): {f['path']} [{f['format']}, {f['records']} "
                       f"records{dmg}]")
    return out
