"""The slave on the master's clock, natively: PX4 ULog (``.ulg``).

A byte-level rewrite: the file is copied and, in every data message of every logged topic, the uint64
time fields (``timestamp``, ``timestamp_sample``, ``*_timestamp`` such as ``ref_timestamp``, nested ones
such as ``esc[0].timestamp``, and GPS ``time_utc_usec``) are overwritten, as are the timestamps of the
logged strings (``L``, ``C`` messages). The file header (magic, version, start timestamp), the flag
bits, the format, info, parameter and subscription messages, relative fields (``*_timestamp_relative``,
int32 offsets from ``timestamp``) and every other byte are kept unchanged. pyulog's ``write_ulog`` would
re-encode the whole file from its decoded arrays (and drop what it does not model); the byte rewrite
keeps the file identical outside the time fields and costs one walk of the message headers (the
reader's compiled walk) plus a gather/scatter per topic.

Clocks: every time field of a message moves by the same whole microseconds, the shift evaluated at the
message's ``timestamp`` on the slave's analysis clock (boot time, or UNIX time through the GPS offset,
as the reader puts it with the same selector). A GPS message's ``timestamp`` and ``time_utc_usec`` thus
move together and the boot -> UTC offset the reader derives is exactly the input's. Fields holding 0
(not set) are left at 0.
"""
from __future__ import annotations

import numpy as np

from logtools.errors import InputError
from parsers.base import Selector
from parsers.restamp import (ClockShift, RestampStats, get_le, glitches, nonneg_or_glitch, put_le, read_bytes,
                             write_bytes_atomic)

HOW = "byte-level rewrite of the time fields (header, definitions and every other byte copied)"
US_NS = 1000


def _is_time_field(name: str, base: np.dtype) -> bool:
    if base != np.dtype("<u8"):
        return False
    last = name.rsplit(".", 1)[-1]
    last = last.split("[", 1)[0]
    if "relative" in last:
        return False
    return last == "timestamp" or last.startswith("timestamp_") or last.endswith("_timestamp") \
        or last == "time_utc_usec"


def _walk_resyncing(buf: np.ndarray, damage: list[str], byte_shift: int = 0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(offsets, sizes, types) of every message the reader reaches (:func:`parsers.ulog.walk_resyncing`: after
    damage, where the headers chain again); bytes no message covers are copied unchanged, each such place
    named in ``damage`` at the input file's offsets (``byte_shift`` added: a repaired header's)."""
    from parsers import ulog as ul

    offsets, sizes, types, said, _tail = ul.walk_resyncing(buf, byte_shift)
    damage.extend(f"damaged ULog: {n}; those bytes copied unchanged" for n in said)
    return offsets, sizes, types


def restamp_ulog(src: str, dst: str, shift: ClockShift, *, selector=None) -> RestampStats:
    from parsers import ulog as ul

    sel = selector if isinstance(selector, Selector) else Selector.parse(str(selector or ""))
    buf = read_bytes(src)
    damage: list[str] = []
    buf, byte_shift, how, at = ul.located(buf)  # (as the parser reads it; byte_shift: what a byte offset of buf
    if how == "prefix":  # adds to be the input file's)
        damage.append(f"damaged: the first {at} bytes are not ULog (bytes put before its header); not copied")
    elif how == "repaired":
        damage.append(f"damaged header: the first {at} bytes are no ULog messages (bad magic bytes); a new "
                      f"header (start time 0) written before the messages from byte {at} on")
    if len(buf) < 16 or buf[:7].tobytes() != ul.MAGIC:
        raise InputError("not a ULog file (bad magic bytes)", src)
    offsets, sizes, types = _walk_resyncing(buf, damage, byte_shift)
    subs, unreadable = ul.definitions(buf, offsets, sizes, types,
                                      errors=(KeyError, ValueError, IndexError, UnicodeDecodeError))
    for o, err in unreadable:
        damage.append(f"unreadable definition at byte {o + byte_shift} ({err}): its data copied unchanged")
    data_idx = np.flatnonzero(types == ul._T_DATA)
    d_off = offsets[data_idx]
    d_size = sizes[data_idx]
    ids = buf[d_off + 3].astype(np.int64) | (buf[d_off + 4].astype(np.int64) << 8)
    # the clock: the reader's boot -> UTC offset for this selector (GPS time_utc_usec - timestamp, median)
    clock = (sel.get("clock") or "auto").lower()
    off_ns = 0
    if clock in ("epoch", "auto"):
        gps = {}
        for mid, add in subs.items():
            if add.message_name in ul.GPS_TOPICS:
                mine = d_off[(ids == mid) & (d_size - 2 >= add.dtype.itemsize)]
                if len(mine):
                    arr = ul.kernel("_gather")(buf, mine, 5, add.dtype.itemsize).view(add.dtype)
                    gps[(add.message_name, int(add.multi_id))] = {n: arr[n] for n in arr.dtype.names}
        try:
            off_ns = ul._utc_offset_ns(gps, src)[0]
        except InputError:
            if clock == "epoch":
                raise
    by_type: dict[str, int] = {}
    fields_done: set[str] = set()
    unknown = 0
    for mid in np.unique(ids).tolist():
        add = subs.get(mid)
        rows = np.flatnonzero(ids == mid)
        if add is None:
            unknown += len(rows)
            continue
        key = add.message_name if add.multi_id == 0 else f"{add.message_name}[{add.multi_id}]"
        by_type[key] = len(rows)
        tf = [(n, add.dtype.fields[n][1]) for n in add.dtype.names
              if _is_time_field(n, add.dtype.fields[n][0])]
        if not tf:
            continue
        base = d_off[rows] + 5  # 3-byte header + uint16 msg_id
        room = d_size[rows] - 2
        ts_o = add.dtype.fields["timestamp"][1] if "timestamp" in add.dtype.names else tf[0][1]
        ok = room >= ts_o + 8
        if not ok.all():
            damage.append(f"{key}: {int((~ok).sum())} message(s) shorter than their format: copied unchanged")
        base, room = base[ok], room[ok]
        t_us = get_le(buf, base + ts_o, 8)
        # the shift at each message's time; a damaged timestamp takes its neighbours' (its other fields shift
        # with them, the damaged value itself is kept below)
        k_us = shift.shift_units(glitches(t_us, US_NS)[1] * US_NS + off_ns, US_NS)
        for n, o in tf:
            fit = room >= o + 8
            at = base[fit] + o
            v = t_us[fit] if o == ts_o else get_le(buf, at, 8)
            live = v > 0
            new = nonneg_or_glitch(v[live], v[live] - k_us[fit][live], US_NS, f"{key}.{n}", src, damage,
                                   clock="boot time")
            put_le(buf, at[live], new, 8)
            fields_done.add(n.rsplit(".", 1)[-1].split("[", 1)[0])
    if unknown:
        damage.append(f"{unknown} data message(s) of unsubscribed ids: copied unchanged")
    # logged strings: L (level u8, timestamp u64), C (level u8, tag u16, timestamp u64)
    for typ, skip in ((ul._T_LOG, 1), (ul._T_LOG_TAGGED, 3)):
        sel_m = np.flatnonzero((types == typ) & (sizes >= skip + 8))
        if len(sel_m):
            at = offsets[sel_m] + 3 + skip
            v = get_le(buf, at, 8)
            live = v > 0
            new = v[live] - shift.shift_units(v[live] * US_NS + off_ns, US_NS)
            put_le(buf, at[live], np.maximum(new, 0), 8)
            fields_done.add("logged string timestamp")
            by_type["(logged strings)"] = by_type.get("(logged strings)", 0) + len(sel_m)
    write_bytes_atomic(dst, buf)
    return RestampStats(path=dst, format="ulog", how=HOW, records=int(len(offsets)), records_by_type=by_type,
                        time_fields=tuple(sorted(fields_done)), damage=tuple(damage))
