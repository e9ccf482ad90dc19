"""The canonical tapost CSV (DESIGN.md, "CSV contract").

Header ``time_s,gyro_x_rad_s,...,accel_z_m_s2,qw,qx,qy,qz,vel_n_m_s,vel_e_m_s,vel_d_m_s,lat_deg,lon_deg,alt_m``
(FRD/NED), one row per sample, any column group may be absent or empty on a row. ``time_s`` is UNIX
seconds or seconds since boot, written and read with full nanosecond precision (never via float64).
"""
from __future__ import annotations

import io
import os
from dataclasses import replace

import numpy as np
import pandas as pd

from logtools.conventions import quat_from_euler
from logtools.errors import InputError
from logtools.inslog import ACCEL, GYRO, POS, QUAT, VEL, ChannelInfo, InsLog, LogMeta
from parsers.assemble import (CLOCK_STEP, REPEATED_LINES_SAID, ClockStepConfig, drop_stray, gap_warning, implausible,
                              repeated_lines, split_at_clock_steps, stamp_outliers)
from parsers.atomic import atomic_path
from parsers.base import (DAMAGED_HEAD_READ_BYTES, DAMAGED_HEAD_SEARCH_BYTES, Inventory, Selector, StreamInfo, rate_of,
                          stamp_grid_s)
from parsers.csvtable import decimal_text_to_int, non_numeric_text, numeric_block, read_table

NAME = "csv"
EXTENSIONS = (".csv",)

TIME = "time_s"
CSV_GYRO = GYRO
CSV_ACCEL = ACCEL
CSV_QUAT = ("qw", "qx", "qy", "qz")
CSV_VEL = VEL
CSV_POS = POS
HEADER = (TIME,) + CSV_GYRO + CSV_ACCEL + CSV_QUAT + CSV_VEL + CSV_POS
#: read too, not written: the attitude as the body -> NED rotation's Z-Y-X angles (aerospace roll, pitch,
#: heading) where a CSV gives no quaternion (a hand-made file's habit); with one, the quaternion is used
CSV_EULER = ("roll_deg", "pitch_deg", "yaw_deg")
#: epoch stamps are larger than this (2001-09-09); boot-relative stamps are smaller
EPOCH_THRESHOLD_S = 1e9
#: the clock-step rule on a CSV's lines: a stretch of lines out of order (shuffled, or moved) is no clock step
#: (its times, sorted, consistent with the lines around: sorted, said once); a step back or reset is, the
#: times after it climbing from where they landed over times the lines before it already had (a fuzzed file
#: with 2000 lines shuffled lost the 6013 lines before one of them, taken for a reset)
CSV_CLOCK_STEP = replace(CLOCK_STEP, max_run_back_fraction=0.25, min_overlap_fraction=0.25)


def _is_header(line: bytes) -> bool:
    text = line.strip().lstrip(b"\xef\xbb\xbf").decode("utf-8", "replace")
    cols = [c.strip() for c in text.split(",")]
    return bool(cols) and cols[0] == TIME and any(c in HEADER[1:] for c in cols[1:])


def sniff(head: bytes, path: str) -> bool:
    return _is_header(head.split(b"\n", 1)[0])


def header_offset(head: bytes) -> int | None:
    """Where the canonical header line begins in ``head`` (a file's first bytes): 0 normally; after bytes
    put before it (a transfer's garbage in front of the file, up to DAMAGED_HEAD_SEARCH_BYTES) the first line
    start that holds it; None."""
    if _is_header(head.split(b"\n", 1)[0]):
        return 0
    key = TIME.encode() + b","
    at = head.find(key, 0, DAMAGED_HEAD_SEARCH_BYTES + len(key))
    while at >= 0:  # (the garbage need not end in a line break: the header is where its name begins)
        if _is_header(head[at:].split(b"\n", 1)[0]):
            return at
        at = head.find(key, at + 1, DAMAGED_HEAD_SEARCH_BYTES + len(key))
    return None


def sniff_damaged(head: bytes, path: str) -> bool:
    """A canonical CSV with bytes before its header line (they are skipped, saying so)."""
    return bool(header_offset(head))


def header_start(path: str) -> int:
    """The byte the canonical CSV at ``path`` starts at: its header line's (0, or past bytes put before it
    within DAMAGED_HEAD_READ_BYTES, as format detection reads it); 0 where none is found (the reader then says
    what is missing)."""
    with open(path, "rb") as fh:
        return header_offset(fh.read(DAMAGED_HEAD_READ_BYTES)) or 0


def seconds_text_to_ns(values: pd.Series) -> np.ndarray:
    """Decimal seconds as text -> int64 ns, exactly (no float64 rounding of epoch stamps)."""
    ns, ok, _ = decimal_text_to_int(values, 9)
    if not ok.all():
        raise ValueError("time column holds values that are not decimal seconds")
    return ns


#: at most this fraction of the time cells may be malformed (dropped with a warning: a damaged line);
#: beyond it the column is not a time in decimal seconds at all
MAX_BAD_TIME_FRACTION = 0.01


def _seconds_text(values: pd.Series) -> tuple[np.ndarray, np.ndarray, int | None]:
    """(int64 ns, the rows whose time is a decimal number, the fixed number of decimals or None)."""
    ns, ok, dec = decimal_text_to_int(values, 9)
    if not ok.any() or (~ok).sum() > MAX_BAD_TIME_FRACTION * len(ok):
        raise ValueError("time column holds values that are not decimal seconds")
    return ns, ok, dec


def ns_to_seconds_text(ns: np.ndarray, decimals: int = 9) -> np.ndarray:
    """int64 ns -> decimal seconds with ``decimals`` (1-9) digits, exactly (the ns already on that grid)."""
    ns = np.asarray(ns, dtype=np.int64)
    sign = np.where(ns < 0, "-", "")
    a = np.abs(ns)
    q = 10 ** (9 - decimals)
    return np.char.add(np.char.add(sign, np.char.mod("%d", a // 1_000_000_000)),
                       np.char.mod(f".%0{decimals}d", (a % 1_000_000_000) // q))


def _read_frame(path: str) -> tuple[pd.DataFrame, list[str]]:
    start = header_start(path)
    df, warnings = read_table(path, TIME, start=start)
    if start:
        warnings = [f"damaged: {os.path.basename(path)}: its first {start} bytes are not CSV before the header "
                    f"line; read from byte {start}"] + warnings
    if TIME not in df.columns:
        raise InputError(f"no '{TIME}' column (canonical CSV header expected)", path)
    return df, warnings


def _merge_same_stamp(t_ns: np.ndarray, df: pd.DataFrame, dup: np.ndarray
                      ) -> tuple[np.ndarray, pd.DataFrame, list[str]]:
    """Rows sharing a time stamp (``dup``: a row's stamp is the row's before it; sorted) as one row: each cell
    the first one given. A writer that puts each column group in rows of its own (the IMU's rows with the
    navigation cells empty, the navigation's at the same stamps with the IMU's empty) loses nothing: its
    navigation rows were dropped as duplicates. Returns the stamps, the rows, and the warnings on the later
    rows that added nothing: a row repeating an earlier one, and one with a value of its own that differs
    from the one kept (the first kept)."""
    run = np.cumsum(~dup) - 1  # each row's stamp group
    merged = df.groupby(run, sort=False).first()  # (per column, the first cell given)
    merged.index = df.index[~dup]  # (the first row's line number)
    later = np.flatnonzero(dup)
    mine, kept = df.iloc[later].to_numpy(), merged.iloc[run[later]].to_numpy()
    before = df.notna().groupby(run).cummax().groupby(run).shift(1, fill_value=False)  # (a cell given above)
    given = pd.notna(mine)
    clash = (given & (mine != kept)).any(axis=1)
    again = ~clash & ~(given & ~before.iloc[later].to_numpy()).any(axis=1)  # (only cells given above, the same)
    said = []
    if again.any():
        said.append(f"{int(again.sum())} duplicate row(s) (the stamp and cells of an earlier row) dropped")
    if clash.any():
        said.append(f"{int(clash.sum())} duplicate time stamps dropped")
    return t_ns[~dup], merged, said


def load(path: str, selector: Selector) -> InsLog:
    if selector:
        raise InputError(f"a canonical CSV holds one unit: selector '{selector}' does not apply", path)
    df, warnings = _read_frame(path)
    df = _drop_rows(df, df[TIME].isna().to_numpy(), "whose time is NaN or empty", warnings)
    try:
        t_ns, ok_t, dec = _seconds_text(df[TIME])
    except ValueError as exc:
        raise InputError(str(exc), path) from None
    if not ok_t.all():
        t_ns, df = t_ns[ok_t], _drop_rows(df, ~ok_t, "whose time is not a decimal number", warnings)
    empty = df.drop(columns=TIME).isna().all(axis=1).to_numpy()  # (text "nan" and empty cells read as NaN)
    if empty.any() and not empty.all():  # (none with a value: said as "no complete data rows")
        t_ns, df = t_ns[~empty], _drop_rows(df, empty, "whose every value is NaN or empty", warnings)
    return assemble_rows(path, df, t_ns, dec, warnings, fmt=NAME, time_col=TIME,
                         stamp_source="csv time_s column", clock_cfg=CSV_CLOCK_STEP)


def _drop_rows(df: pd.DataFrame, drop: np.ndarray, what: str, warnings: list[str]) -> pd.DataFrame:
    """``df`` without the rows ``drop``, said in ``warnings`` where there are any: their count, ``what`` they
    are, the first one's line (a CSV's header is line 1)."""
    if not drop.any():
        return df
    line = int(df.index[np.flatnonzero(drop)[0]]) + 2
    warnings.append(f"{int(drop.sum())} row(s) {what} dropped (damaged lines?; first at line {line})")
    return df[~drop]


def assemble_rows(path: str, df: pd.DataFrame, t_ns: np.ndarray, dec: int | None, warnings: list[str], *,
                  fmt: str, time_col: str, stamp_source: str, row: str = "line", first_row: int = 2,
                  clock_cfg: ClockStepConfig = CLOCK_STEP) -> InsLog:
    """The InsLog of canonical rows ``df`` (its columns by the canonical names; ``df.index`` the rows'
    places in the file, counted from ``first_row`` in the warnings, each a ``row``) at int64 stamps ``t_ns``
    (``dec``: the decimals the stamps were written with, None when unknown). ``clock_cfg``: the clock-step
    rule's (a CSV's: ``CSV_CLOCK_STEP``, rows out of order no step)."""
    groups = {"gyro": CSV_GYRO, "accel": CSV_ACCEL, "quat": CSV_QUAT, "euler": CSV_EULER, "vel": CSV_VEL,
              "pos": CSV_POS}
    present = {g: cols for g, cols in groups.items() if all(c in df.columns for c in cols)}
    partial = [g for g, cols in groups.items() if g not in present and any(c in df.columns for c in cols)]
    if partial:
        warnings.append(f"incomplete column group(s) ignored: {', '.join(partial)}")
    other = [str(c) for c in df.columns if c not in HEADER and c not in CSV_EULER and c != time_col]
    if other:
        warnings.append(f"note: column(s) not read (not the canonical CSV's): {', '.join(other[:8])}"
                        + (" ..." if len(other) > 8 else ""))
    if not present:
        raise InputError("no recognisable data columns (gyro/accel/quaternion/velocity/position)", path)
    if len(t_ns) == 0:
        raise InputError("no data rows", path)
    # lines whose times run back for another reason than the clock, dropped alone before the clock-step rule:
    # a stretch written twice (parsers.assemble.repeated_lines: the lines' cells compared by hash) and a
    # corrupt time cell (parsers.assemble.stamp_outliers)
    for find, said in ((lambda: repeated_lines(t_ns, df, time_col), REPEATED_LINES_SAID),
                       (lambda: stamp_outliers(t_ns), f"{time_col} column: {{n}} {{row}}(s) whose time jumps away "
                        "from the {row}s around and back dropped (a corrupt time field?; first at {row} {line})")):
        if not np.any(np.diff(t_ns) < 0):
            break
        drop = find()
        if drop.any():
            lines = (np.asarray(df.index, dtype=np.int64) + first_row)[drop]  # (a CSV's header is line 1)
            warnings.append(said.format(n=int(drop.sum()), line=int(lines[0]), row=row))
            t_ns, df = t_ns[~drop], df[~drop]
    if np.any(np.diff(t_ns) < 0):  # a clock step back or reset keeps one part (parsers.assemble.clock_steps)
        keep = split_at_clock_steps(t_ns, f"{time_col} column: ", warnings, unit=row,
                                    rows=np.asarray(df.index, dtype=np.int64) + first_row, cfg=clock_cfg)
        if keep is not None:
            t_ns, df = t_ns[keep], df.iloc[keep]
    order = np.argsort(t_ns, kind="stable")
    back = np.flatnonzero(np.diff(t_ns) < 0) + 1  # (a row whose time is below the one before it)
    if len(back):
        warnings.append(f"rows not in time order: sorted ({len(back)} {row}(s) with a time below the one before, "
                        f"first at {row} {int(df.index[back[0]]) + first_row})")
    t_ns = t_ns[order]
    df = df.iloc[order]
    dup = np.concatenate([[False], np.diff(t_ns) == 0])
    if dup.any():
        t_ns, df, said = _merge_same_stamp(t_ns, df, dup)
        warnings.extend(said)
    keep = drop_stray(t_ns, f"{time_col} column: ", warnings)
    t_ns, df = t_ns[keep], df[keep]
    t0_ns = int(t_ns[0])
    t_s = (t_ns - t0_ns) * 1e-9
    clock = "epoch" if t0_ns * 1e-9 > EPOCH_THRESHOLD_S else "boot"

    def block(g: str) -> np.ndarray:
        """Group ``g``'s columns as floats; a row with impossible values (corrupt) has the group missing."""
        x, _, text = numeric_block(df, present[g])
        non_numeric.update(text)
        bad = implausible(g, x)
        if bad.any():
            warnings.append(f"{g}: {int(bad.sum())} rows with impossible values ignored (corrupt data?)")
            x[bad] = np.nan
        return x

    non_numeric: dict[str, int] = {}
    blocks = {g: block(g) for g in present}
    if "euler" in blocks:
        rpy = blocks.pop("euler")
        present.pop("euler")
        if "quat" in blocks:
            warnings.append("note: roll_deg/pitch_deg/yaw_deg not used: the quaternion columns give the attitude")
        else:
            ok = np.isfinite(rpy).all(axis=1)
            blocks["quat"] = np.full((len(rpy), 4), np.nan)
            blocks["quat"][ok] = quat_from_euler(np.radians(rpy[ok]))
            present["quat"] = CSV_EULER
    if non_numeric:
        warnings.append(f"{os.path.basename(path)}: {non_numeric_text(non_numeric)} read as missing values "
                        "(damaged file?)")

    def resolution(mask: np.ndarray) -> float:
        """The stamps' step: the fixed number of decimals they are written with, or the grid they show."""
        return max(0.0 if dec is None else 10.0 ** -dec, stamp_grid_s(t_ns[mask]))

    channels: dict[str, ChannelInfo] = {}
    imu_mask = np.zeros(len(df), bool)
    for g in ("gyro", "accel"):
        if g in present:
            imu_mask |= np.isfinite(blocks[g]).all(axis=1)
    nav_mask = np.zeros(len(df), bool)
    for g in ("quat", "vel", "pos"):
        if g in present:
            nav_mask |= np.isfinite(blocks[g]).all(axis=1)
    kw: dict = {}
    if imu_mask.any():
        kw["t_imu_s"] = t_s[imu_mask]
        if "gyro" in present:
            kw["gyro_rad_s"] = blocks["gyro"][imu_mask]
        if "accel" in present:
            kw["accel_m_s2"] = blocks["accel"][imu_mask]
        channels["imu"] = ChannelInfo(rate_of(t_s[imu_mask]), int(imu_mask.sum()), fmt, resolution(imu_mask))
    if nav_mask.any():
        kw["t_nav_s"] = t_s[nav_mask]
        if "quat" in present:
            kw["quat_wxyz"] = blocks["quat"][nav_mask]
        if "vel" in present:
            kw["vel_ned_m_s"] = blocks["vel"][nav_mask]
        if "pos" in present:
            kw["lat_lon_alt"] = blocks["pos"][nav_mask]
        channels["nav"] = ChannelInfo(rate_of(t_s[nav_mask]), int(nav_mask.sum()), fmt, resolution(nav_mask))
    if not kw:
        raise InputError("no complete data rows", path)
    for name, mask in (("imu", imu_mask), ("nav", nav_mask)):
        said = gap_warning(f"{name} ({fmt})", np.diff(t_ns[mask])) if mask.sum() > 2 else None
        if said:
            warnings.append(said)
    meta = LogMeta(source_path=path, format=fmt, selector="", clock=clock, t0_ns=t0_ns,
                   stamp_source=stamp_source, channels=channels, warnings=tuple(warnings))
    return InsLog.from_arrays(meta, **kw)


def inventory(path: str) -> Inventory:
    return rows_inventory(path, load(path, Selector()))


def rows_inventory(path: str, log: InsLog) -> Inventory:
    """The inventory of a one-unit table (canonical CSV or Parquet): its IMU and navigation rows."""
    streams = []
    for name, ch in log.meta.channels.items():
        t = log.t_imu_s() if name == "imu" else log.t_nav_s()
        streams.append(StreamInfo(name=name, kind=name, count=ch.count, rate_hz=ch.rate_hz,
                                  start_s=log.t0_s + float(t[0]), duration_s=float(t[-1] - t[0]),
                                  clock=log.meta.clock))
    return Inventory(path=path, format=log.meta.format, streams=tuple(streams), selectors=("",),
                     warnings=log.meta.warnings)


def write(path: str, log: InsLog, *, time_decimals: int = 9) -> None:
    """Write an InsLog as canonical CSV; imu and nav rows are merged on their (exact) stamps.
    ``time_decimals`` < 9 writes the stamps rounded to that many decimals of a second, as a logger with a
    coarser clock would (3: whole milliseconds)."""
    if not 1 <= time_decimals <= 9:
        raise InputError(f"time_decimals must be 1..9, not {time_decimals}", path)
    q = 10 ** (9 - time_decimals)
    frames = []
    if len(log.imu):
        frames.append(log.imu[[c for c in GYRO + ACCEL if c in log.imu.columns]])
    if len(log.nav):
        nav = log.nav[[c for c in QUAT + VEL + POS if c in log.nav.columns]]
        frames.append(nav.rename(columns=dict(zip(QUAT, CSV_QUAT))))
    # merge on integer ns so that equal stamps share a row
    merged = None
    for f in frames:
        f = f.copy()
        abs_ns = np.round(f.index.to_numpy(float) * 1e9).astype(np.int64) + np.int64(log.meta.t0_ns)
        f.index = (abs_ns + q // 2) // q * q - np.int64(log.meta.t0_ns)
        f = f[~f.index.duplicated()]
        merged = f if merged is None else merged.join(f, how="outer")
    if merged is None:
        raise InputError("nothing to write", path)
    merged = merged.sort_index()
    cols = [c for c in HEADER[1:] if c in merged.columns]
    out = merged[cols]
    time_txt = ns_to_seconds_text(merged.index.to_numpy() + log.meta.t0_ns, time_decimals)
    buf = io.StringIO()
    out.insert(0, TIME, time_txt)
    out.to_csv(buf, index=False, float_format="%.17g", na_rep="")
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        fh.write(buf.getvalue())
