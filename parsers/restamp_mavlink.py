"""The slave on the master's clock, natively: MAVLink tlog and ArduPilot DataFlash (.bin).

Both are byte-level rewrites: the input is read once, copied, and only the bytes of the time fields
(and, in a tlog, the CRC of each changed frame) are overwritten, vectorised with numpy over the record
offsets the readers already find (``parsers.mavlink_common`` walkers). Every other byte -- FMT/FMTU/
UNIT/MULT records, parameters, messages, damaged stretches the reader skipped -- is copied unchanged, so
the output has the input's length and record order. Going through pymavlink instead would re-encode
every message (payload truncation, field order and float formatting would all have to round-trip) and
would take minutes on a 1 h log; the byte rewrite takes about the time of one walk of the file.

The clocks. A writer gets a :class:`parsers.restamp.ClockShift` on the slave's *analysis* clock (the
clock the reader put the slave on: UNIX time through GPS / SYSTEM_TIME, or boot time). Each time field
keeps its own clock domain (boot microseconds stay boot microseconds): the shift is evaluated at the
record's instant on the analysis clock and subtracted from the field in the field's unit. The records
that tie boot time to UNIX time (DataFlash GPS week/ms, tlog SYSTEM_TIME) get the same whole-millisecond
shift on both of their time fields, so that the boot -> UNIX offset a reader derives from them is exactly
the input's, and reading the output with the same selector gives the compensated stamps.
"""
from __future__ import annotations

import os
import shutil

import numpy as np

from logtools.errors import InputError
from parsers import threads
from parsers.atomic import atomic_path
from parsers.base import Selector
from parsers.filemap import FileMap
from parsers.restamp import (ClockShift, RestampStats, get_le, kernel_loader, mapped_copy,
                             nonneg_or_glitch, put_le, read_bytes, write_bytes_atomic)

HOW = "byte-level rewrite of the time fields (every other byte copied)"
MS_NS, US_NS = 1_000_000, 1_000
WEEK_MS = 604_800_000
PLAN_ROWS = 20_000  # rows per selected tlog stream decoded to rebuild the reader's clock plan


def _selector(selector) -> Selector:
    if selector is None:
        return Selector()
    if isinstance(selector, Selector):
        return selector
    return Selector.parse(str(selector))


def _shift_gps_week_ms(buf: np.ndarray, o_wk: np.ndarray, o_ms: np.ndarray, valid: np.ndarray,
                       k_ms: np.ndarray) -> None:
    """GPS week (u16) / ms of week (u32) minus ``k_ms`` whole milliseconds, with week carry."""
    if not valid.any():
        return
    wk = get_le(buf, o_wk[valid], 2)
    ms = get_le(buf, o_ms[valid], 4)
    tot = wk * WEEK_MS + ms - k_ms[valid]
    put_le(buf, o_wk[valid], tot // WEEK_MS, 2)
    put_le(buf, o_ms[valid], tot % WEEK_MS, 4)


# ==== DataFlash ========================================================================================
def restamp_dataflash(src: str, dst: str, shift: ClockShift, *, selector=None) -> RestampStats:
    """Rewrite ``TimeUS`` (old logs: ``TimeMS``; old GPS: ``T`` and ``Week``/``TimeMS``; GPS/GPS2
    ``GWk``/``GMS``) of every record of a DataFlash log; every other byte copied."""
    from parsers import dataflash as df

    sel = _selector(selector)
    log = df.read_log(src)
    buf = read_bytes(src)
    mode = (sel.get("time") or sel.get("clock") or "gps").lower()
    off = None if mode == "boot" else df._gps_epoch_offset_ns(log)[0]
    off_ns = np.int64(off or 0)
    by_type: dict[str, int] = {}
    fields_done: set[str] = set()
    glitch_notes: list[str] = []
    total = 0
    for typ, offs in log.offsets.items():
        f = log.formats.get(typ)
        if f is None:
            continue
        by_type[f.name] = by_type.get(f.name, 0) + len(offs)
        total += len(offs)
        if typ == df.FMT_TYPE or not len(offs):
            continue
        dt = f.dtype
        cols = dt.names or ()

        def at(col):
            return offs + 3 + dt.fields[col][1]

        gps = f.name.startswith("GPS")
        if "TimeUS" in cols:
            boot_ns = get_le(buf, at("TimeUS"), 8) * US_NS
        elif gps and "T" in cols:
            boot_ns = get_le(buf, at("T"), 4) * MS_NS
        elif "TimeMS" in cols:
            boot_ns = get_le(buf, at("TimeMS"), 4) * MS_NS
        else:
            continue  # a record without a time field (e.g. FMTU in some logs): copied as it is
        t_a = boot_ns + off_ns
        if gps:  # the boot -> UNIX anchor: whole milliseconds on boot and GPS time alike
            k_ms = shift.shift_units(t_a, MS_NS)
            if "TimeUS" in cols:
                old = get_le(buf, at("TimeUS"), 8)
                new = nonneg_or_glitch(old, old - k_ms * 1000, US_NS, f"{f.name}.TimeUS", src, glitch_notes)
                put_le(buf, at("TimeUS"), new, 8)
                fields_done.add(f"{f.name}.TimeUS")
            if "T" in cols and "TimeUS" not in cols:
                old = get_le(buf, at("T"), 4)
                new = nonneg_or_glitch(old, old - k_ms, MS_NS, f"{f.name}.T", src, glitch_notes, nbytes=4)
                put_le(buf, at("T"), new, 4)
                fields_done.add(f"{f.name}.T")
            for wk_col, ms_col in (("GWk", "GMS"), ("Week", "TimeMS")):
                if wk_col in cols and ms_col in cols:
                    wk = get_le(buf, at(wk_col), 2)
                    _shift_gps_week_ms(buf, at(wk_col), at(ms_col), wk > 0, k_ms)
                    fields_done.add(f"{f.name}.{wk_col}/{ms_col}")
            continue
        if "TimeUS" in cols:
            old = get_le(buf, at("TimeUS"), 8)
            new = nonneg_or_glitch(old, old - shift.shift_units(t_a, US_NS), US_NS, f"{f.name}.TimeUS", src,
                                    glitch_notes)
            put_le(buf, at("TimeUS"), new, 8)
            fields_done.add("TimeUS")
        elif "TimeMS" in cols:
            old = get_le(buf, at("TimeMS"), 4)
            new = nonneg_or_glitch(old, old - shift.shift_units(t_a, MS_NS), MS_NS, f"{f.name}.TimeMS", src,
                                    glitch_notes, nbytes=4)
            put_le(buf, at("TimeMS"), new, 4)
            fields_done.add("TimeMS")
    write_bytes_atomic(dst, buf)
    return RestampStats(path=dst, format="dataflash", how=HOW, records=total, records_by_type=by_type,
                        time_fields=tuple(sorted(fields_done)),
                        damage=tuple(w + " (those bytes copied unchanged)" for w in log.warnings)
                        + tuple(glitch_notes))


# ==== tlog =============================================================================================
#: message time fields rewritten (name -> (dtype size, unit ns)); time_usec is UNIX time above 1e15 us
_TLOG_FIELDS = (("time_usec", 8, US_NS), ("time_boot_ms", 4, MS_NS), ("time_unix_usec", 8, US_NS))


def _frames(path: str, buf: np.ndarray):
    """One walk + index of a tlog: (the reader's Frames of the intact frames, starts, index columns)."""
    from parsers import mavlink_tlog as tl
    from parsers.mavlink_common import index_tlog_frames, walk_tlog

    if len(buf) == 0:
        raise InputError("empty file", path)
    starts, skipped, resyncs, tail = walk_tlog(buf)
    if len(starts) == 0:
        raise InputError("no MAVLink frames found (not a tlog, or damaged beyond use)", path)
    idx = index_tlog_frames(buf, starts, tl._crc_extra_table(), parts=_parts(len(starts)))
    recv, v2, plen, sysid, compid, msgid, pay, status = idx
    ok = status == 0
    warns = []
    if skipped:
        warns.append(f"damaged tlog: skipped {skipped} bad bytes ({resyncs + (0 if resyncs else 1)} place(s))")
    n_bad = int(((status != 2) & ~ok).sum())
    if n_bad:
        warns.append(f"damaged tlog: {n_bad} frame(s) with bad CRC (copied unchanged but for the receive stamp)")
    if tail:
        warns.append(f"truncated tlog: last {tail} byte(s) hold an incomplete frame")
    fr = tl.Frames(buf=buf, recv_us=recv[ok], v2=v2[ok], plen=plen[ok], sysid=sysid[ok], compid=compid[ok],
                   msgid=msgid[ok], pay=pay[ok], warnings=tuple(warns), n_corrupt=n_bad)
    return fr, starts, idx


def _tlog_plan(path: str, sel: Selector, fr):
    """The reader's own clock plan for this selector: (sysid, compid, mode, plan, recv lag ns)."""
    from parsers import mavlink_tlog as tl

    cat = tl.catalog(fr)
    chosen, _ = tl._resolve(path, sel, cat)
    sysid, compid, mode = int(chosen["sysid"]), int(chosen["compid"]), chosen["time"]
    picked = []
    for key in ("imu", "att", "vel", "pos"):
        if key in chosen:
            name = tl._INST.match(chosen[key]).group(1)
            d = tl.msgdef(name)
            rows = fr.rows(d.id, sysid, compid)
            # the plan needs the clock kinds and the link lag: a uniform subsample of a long stream is enough
            rows = rows[::max(1, len(rows) // PLAN_ROWS)]
            if len(rows):
                picked.append(tl.RawStream(name, sysid, compid, fr.decode(rows, d), fr.recv_us[rows] * 1000))
    timing = [tl._msg_time(s) for s in picked]
    plan = tl.plan_clock([(k, t, s.recv_ns) for (k, t), s in zip(timing, picked)],
                         tl._system_time_offset_ns(fr, sysid, compid), mode)
    # receive stamp -> analysis clock: minus the median link lag of the selected timed streams
    lags = [s.recv_ns[k != 2] - tl.apply_clock(plan, k, t, s.recv_ns, mode)[k != 2]
            for (k, t), s in zip(timing, picked)]
    lags = np.concatenate(lags) if lags else np.zeros(0, np.int64)
    lag = 0 if mode == "receive" or not len(lags) else int(np.sort(lags)[len(lags) // 2])
    return sysid, compid, mode, plan, lag


def _crc_in_buf(buf: np.ndarray, starts: np.ndarray, lengths: np.ndarray, extra: int) -> np.ndarray:
    from parsers import mavlink_common as mc

    if mc.HAVE_NUMBA:  # straight from the buffer
        return mc._crc_var_nb(buf, np.asarray(starts, np.int64), np.asarray(lengths, np.int64), int(extra),
                              mc.CRC_TABLE)
    w = int(lengths.max())
    gather_rows, x25_crc_block = mc.gather_rows, mc.x25_crc_block
    block = gather_rows(buf, starts, w, lengths)
    return x25_crc_block(block, 0, lengths, extra)


def _tlog_kernel(buf, starts, pay, plen, status, msgid, v2, o_usec, o_boot, o_unix, extra, sys_id,
                 lag, add0, add1, receive, lat_s, d, t_ref, thr_us, table):  # pragma: no cover - compiled
    """One pass over the records: receive stamp, message time fields, CRC of changed frames.
    Returns (changed frames, signed changed frames, first record index whose new stamp is negative or beyond its
    field (time_boot_ms: uint32 ms) or -1,
    fields rewritten as bits: 1 time_usec, 2 time_boot_ms, 4 SYSTEM_TIME)."""
    n = starts.shape[0]
    changed_n = 0
    signed_n = 0
    negative = -1
    bits = 0
    for i in range(n):
        s = starts[i]
        recv = np.int64(0)
        for k in range(8):
            recv = (recv << 8) | np.int64(buf[s + k])
        t_a = recv * 1000 - lag
        sh = np.int64(np.rint((lat_s + d * ((t_a - t_ref) * 1e-9)) / (1.0 + d) * 1e9))
        new = recv - (sh + 500) // 1000
        if new < 0 and negative < 0:
            negative = i
        for k in range(8):
            buf[s + 7 - k] = np.uint8((new >> (8 * k)) & 0xFF)
        if status[i] != 0:
            continue
        mid = msgid[i]
        p0 = pay[i]
        pl = plen[i]
        changed = False
        if mid == sys_id:
            ob = o_boot[mid]
            ou = o_unix[mid]
            if pl >= ob + 4 and pl >= ou + 8:
                boot = np.int64(0)
                for k in range(4):
                    boot |= np.int64(buf[p0 + ob + k]) << (8 * k)
                unix = np.int64(0)
                for k in range(8):
                    unix |= np.int64(buf[p0 + ou + k]) << (8 * k)
                t_a = unix * 1000 + add1 if unix > thr_us else boot * 1000000 + add0
                sh = np.int64(np.rint((lat_s + d * ((t_a - t_ref) * 1e-9)) / (1.0 + d) * 1e9))
                k_ms = (sh + 500000) // 1000000
                nb = boot - k_ms
                if (nb < 0 or nb > 0xFFFFFFFF) and negative < 0:  # (a uint32 field: beyond it, no wrap)
                    negative = i
                for k in range(4):
                    buf[p0 + ob + k] = np.uint8((nb >> (8 * k)) & 0xFF)
                if unix > 0:
                    nu = unix - k_ms * 1000
                    for k in range(8):
                        buf[p0 + ou + k] = np.uint8((nu >> (8 * k)) & 0xFF)
                changed = True
                bits |= 4
        else:
            for which in range(2):
                o = o_usec[mid] if which == 0 else o_boot[mid]
                size = 8 if which == 0 else 4
                if o < 0 or pl < o + size:
                    continue
                v = np.int64(0)
                for k in range(size):
                    v |= np.int64(buf[p0 + o + k]) << (8 * k)
                if v <= 0:
                    continue
                if which == 0:
                    t_a = v * 1000 + (add1 if v > thr_us else add0)
                    unit = np.int64(1000)
                else:
                    t_a = v * 1000000 + add0
                    unit = np.int64(1000000)
                sh = np.int64(np.rint((lat_s + d * ((t_a - t_ref) * 1e-9)) / (1.0 + d) * 1e9))
                nv = v - (sh + unit // 2) // unit
                if (nv < 0 or (size == 4 and nv > 0xFFFFFFFF)) and negative < 0:  # (time_boot_ms: uint32)
                    negative = i
                for k in range(size):
                    buf[p0 + o + k] = np.uint8((nv >> (8 * k)) & 0xFF)
                changed = True
                bits |= 1 if which == 0 else 2
        if changed:
            changed_n += 1
            f = s + 8
            crc = np.uint16(0xFFFF)
            for j in range(f + 1, p0 + pl):
                crc = (crc >> 8) ^ table[(crc ^ buf[j]) & 0xFF]
            crc = (crc >> 8) ^ table[(crc ^ extra[mid]) & 0xFF]
            buf[p0 + pl] = np.uint8(crc & 0xFF)
            buf[p0 + pl + 1] = np.uint8(crc >> 8)
            if v2[i] and (buf[f + 2] & 1) == 1:
                signed_n += 1
    return changed_n, signed_n, negative, bits


_kernel = kernel_loader(globals())  # the numba kernels above, compiled (and cached) on first use


def _parts(n_records: int) -> int:
    """Runs of records the compiled tlog passes are split into (done in the I/O threads, each run's bytes
    written while the next runs): a few per worker, none under 64 k records."""
    from logtools import jit
    from parsers import threads

    if not jit.compiled() or threads.workers() <= 1 or n_records < 65_536:
        return 1
    return 4 * threads.workers()


def _field_tables(n_ids: int):
    """Per message id: byte offsets of time_usec, time_boot_ms, time_unix_usec in the payload (-1: none)."""
    from parsers import mavlink_tlog as tl

    o = {f: np.full(n_ids, -1, np.int64) for f in ("time_usec", "time_boot_ms", "time_unix_usec")}
    for mid in tl._table()["by_id"]:  # (the dialect's messages, from the reader's cached table)
        d = tl.msgdef_by_id(mid)
        if d is None:
            continue
        for f in o:
            if f in d.dtype.names:
                o[f][mid] = d.dtype.fields[f][1]
    return o


def restamp_tlog(src: str, dst: str, shift: ClockShift, *, selector=None) -> RestampStats:
    """Rewrite every record's 8-byte big-endian receive stamp (UNIX us) and, in every intact frame, the
    message time fields ``time_usec`` / ``time_boot_ms`` (and SYSTEM_TIME's ``time_unix_usec``); the CRC
    of each changed frame is recomputed. SYSTEM_TIME's two fields move by the same whole millisecond (its
    boot -> UNIX offset is kept). MAVLink 2 signatures cannot be recomputed without the key: they are kept
    as they are and the signed frames that changed are counted in ``damage`` (they no longer verify).
    One compiled pass over the records (numba), after the reader's walk and index; on a large file both the
    index and that pass run on runs of records in the I/O threads. The pass patches a copy of the input made
    by the kernel while the records are walked, mapped (or, where it cannot be mapped, a private copy of the
    bytes, written out run by run as each is done)."""
    from parsers import mavlink_common as mc
    from parsers import mavlink_tlog as tl

    sel = _selector(selector)
    if os.path.isdir(src):
        raise IsADirectoryError(src)
    with FileMap(src) as fmap, atomic_path(dst) as tmp:
        # the output starts as a copy of the input made by the kernel (sendfile) while the records are walked
        # in a read-only map of it; its time fields are then patched where they lie, in a map of the copy
        copied = threads.beside(shutil.copyfile, src, tmp)
        try:
            orig = fmap.array
            fr, starts, idx = _frames(src, orig)
            sysid, compid, mode, plan, lag = _tlog_plan(src, sel, fr)
            recv, v2, plen, sys_a, comp_a, msgid, pay, status = idx
            extra = tl._crc_extra_table().astype(np.int64)
            tabs = _field_tables(len(extra))
            ids = np.asarray(msgid, np.int64)
            stat = np.where(ids < len(extra), np.asarray(status), 2).astype(np.int64)
            ids = np.where(ids < len(extra), ids, 0)
            starts, pay, plen, v2 = (np.asarray(a, t) for a, t in ((starts, np.int64), (pay, np.int64),
                                                                    (plen, np.int64), (v2, np.bool_)))
            kernel = _kernel("_tlog_kernel")
            consts = (tabs["time_usec"], tabs["time_boot_ms"], tabs["time_unix_usec"], extra,
                      int(tl.msgdef("SYSTEM_TIME").id), int(0 if mode == "receive" else lag), int(plan.add_ns[0]),
                      int(plan.add_ns[1]), mode == "receive", float(shift.latency_s), float(shift.drift_ppm * 1e-6),
                      int(shift.t_ref_ns), int(tl.EPOCH_US_THRESHOLD), mc.CRC_TABLE)
            cuts = np.linspace(0, len(starts), _parts(len(starts)) + 1).astype(np.int64).tolist()
            runs = list(zip(cuts[:-1], cuts[1:]))
            copied.result()
            with mapped_copy(tmp, fmap.size) as out:
                # a run's bytes: from its first record to the next run's (the file's first and last bytes with the
                # first and last run: what precedes the first record and follows the last is copied as it is)
                edges = [0] + [int(starts[a]) for a, _ in runs[1:]] + [len(orig)]
                buf = out if out is not None else np.array(orig)  # (no map: a private copy, written run by run)

                def run(ab: tuple[int, int]):  # one run of records: its frames are its own bytes (a worker thread)
                    a, b = ab
                    return kernel(buf, starts[a:b], pay[a:b], plen[a:b], stat[a:b], ids[a:b], v2[a:b], *consts)

                changed = signed_changed = bits = 0
                negative = -1
                fh = open(tmp, "r+b") if out is None else None
                try:
                    for k, (c, sc, neg, bt) in enumerate(threads.ordered(run, runs)):
                        changed, signed_changed, bits = changed + c, signed_changed + sc, bits | bt
                        if neg >= 0 and negative < 0:
                            negative = runs[k][0] + neg
                        if fh is not None and negative < 0:
                            fh.write(memoryview(buf[edges[k]:edges[k + 1]]))  # (while the next runs are worked)
                    if fh is not None and negative < 0:
                        fh.truncate()  # (the copy's length, were it not the input's as it was read)
                finally:
                    if fh is not None:
                        fh.close()
                buf = out = None  # (no array left viewing the map: it closes as the block ends)
            if negative >= 0:
                raise InputError(f"native export: a shifted stamp of record {negative} would be negative or beyond "
                                 "its field (the master's clock lies where the field's clock cannot express it: a "
                                 "time_boot_ms holds 49.7 days of milliseconds; export csv/parquet instead)", src)
        finally:
            threads.drain([copied])
    u, c = np.unique(ids[stat == 0], return_counts=True)
    by_type = {tl.msgdef_by_id(int(m)).name: int(k) for m, k in zip(u, c)}
    fields_done = ["receive stamp"] + [name for bit, name in ((1, "time_usec"), (2, "time_boot_ms"),
                                                              (4, "SYSTEM_TIME.time_boot_ms/time_unix_usec"))
                                       if bits & bit]
    damage = [w + " (receive stamps rewritten where a record was walked; the rest copied unchanged)"
              for w in fr.warnings]
    n_unknown = int((stat == 2).sum())
    if n_unknown:
        damage.append(f"{n_unknown} frame(s) of unknown message ids: receive stamp rewritten, payload copied")
    if signed_changed:
        damage.append(f"{signed_changed} signed MAVLink 2 frame(s) changed: signatures kept as they were "
                      "and no longer verify (the key is needed to re-sign)")
    return RestampStats(path=dst, format="tlog", how=HOW + "; CRC recomputed for changed frames",
                        records=int(len(starts)), records_by_type=by_type,
                        time_fields=tuple(fields_done), damage=tuple(damage))
