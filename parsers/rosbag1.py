"""ROS 1 bags (``#ROSBAG V2.0``).

Reading: a linear scan of the bag's records (own code: the index at the end is not needed, so a
bag cut off while recording still gives its readable part), chunks decompressed (none/bz2/lz4),
raw message bytes + record times collected per connection, message definitions from the connection
records registered in a rosbags typestore. Content decoded by :mod:`parsers.ros_common` (vectorised,
with the rosbags deserialiser as reference and fallback). Damage (truncation, a chunk that does not
decompress, a broken record) is reported in ``meta.warnings`` and the readable part is used.
``load`` and ``inventory`` use :func:`read_streamed`: the file memory-mapped, record times kept as int64
arrays and each kept topic decoded while read (ros_common.StreamDecoder), not one bytes object and one int
per message; the classic :func:`read_raw` where that cannot be exact (rc.NotStreamable).

Writing (``write(path, log, log_delay_ns=0, compression="none"|"bz2"|"lz4")``) with ``rosbags.rosbag1.Writer``: same topics as
:mod:`parsers.mcap_ros` (/imu, /velocity, /fix, /attitude), ENU/FLU, header stamps exact ns.
"""
from __future__ import annotations

import bz2
import os
import struct
from collections.abc import Callable

import numpy as np

from logtools import jit
from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers import ros_common as rc
from parsers.atomic import atomic_path
from parsers.base import DamagedRecords, Inventory, Selector, check_readable

NAME = "rosbag1"
EXTENSIONS = (".bag",)
MAGIC = b"#ROSBAG V2.0\n"

_OP_MSG, _OP_BAGHEADER, _OP_INDEX, _OP_CHUNK, _OP_CHUNKINFO, _OP_CONN = 2, 3, 4, 5, 6, 7
_U32 = struct.Struct("<I")
_TIME = struct.Struct("<II")


def sniff(head: bytes, path: str) -> bool:
    return head.startswith(MAGIC)


def sniff_damaged(head: bytes, path: str) -> bool:
    """A bag whose first bytes (magic, bag header) are damaged: a chunk or connection record further on in
    the first 8 KiB (the walk starts there, and says so)."""
    return resync_top(head, 0, len(head), partial_ok=True) is not None


def resync_top(buf, start: int, end: int, partial_ok: bool = False) -> int | None:
    """The first offset >= ``start`` where a top-level chunk or connection record starts whose header reads
    and whose data fits in ``buf[:end]`` (``partial_ok``: may run past ``end``, for a file's first bytes):
    where a walk of the top-level records goes on after damage. None if there is none."""
    b = bytes(buf[start:end]) if not isinstance(buf, bytes) else buf[start:end]
    for k in _find_first(b, (b"op=\x05", b"op=\x07")):
        for r in range(max(0, k - 128), k - 7):
            (hlen,) = _U32.unpack_from(b, r)
            if not (k + 4 <= r + 4 + hlen <= len(b) - 4 and hlen < 1 << 16):
                continue
            try:
                op = _fields(b[r + 4:r + 4 + hlen]).get("op", b"")[:1]
            except (_Damage, struct.error):
                continue
            (dlen,) = _U32.unpack_from(b, r + 4 + hlen)
            if op in (bytes([_OP_CHUNK]), bytes([_OP_CONN])) and (partial_ok or r + 8 + hlen + dlen <= len(b)):
                return start + r
    return None


def top_record(buf, off: int, end: int) -> tuple[dict[str, bytes], bytes, int, int]:
    """The top-level record at ``off``: (header fields, op byte, header length, where the next record starts);
    _Damage for a record the file's end cuts or one without an op field (zeroed bytes read as empty records:
    framing lost, not a record). The parser's and the export's walks read their records with it."""
    if off + 4 > end:
        raise _Damage(f"file truncated at byte {end}: record at byte {off} incomplete")
    (hlen,) = _U32.unpack_from(buf, off)
    if off + 8 + hlen > end:
        raise _Damage(f"file truncated at byte {end}: record at byte {off} incomplete")
    (dlen,) = _U32.unpack_from(buf, off + 4 + hlen)
    nxt = off + 8 + hlen + dlen
    if nxt > end:
        raise _Damage(f"file truncated at byte {end}: record at byte {off} incomplete")
    header = _fields(bytes(buf[off + 4:off + 4 + hlen]))
    if "op" not in header:
        raise _Damage(f"record at byte {off} has no op field")
    return header, header["op"][:1], hlen, nxt


def resume_top(buf, off: int, good: int, floor: int, end: int) -> int | None:
    """Where a top-level walk that failed to read the record at ``off`` goes on: the next chunk or connection
    record (:func:`resync_top`) after ``good`` (the end of the last record whose framing read) and past
    ``floor`` (where it went on before: every resynchronisation moves forward), not ``off`` itself."""
    at = resync_top(buf, max(good, floor + 1), end)
    return resync_top(buf, off + 1, end) if at == off else at


def _find_first(b: bytes, tags: tuple[bytes, ...]):
    """The places of any of ``tags`` in ``b``, ascending, found as they are needed (not all of a file)."""
    nxt = {t: b.find(t) for t in tags}
    while True:
        live = [(k, t) for t, k in nxt.items() if k >= 0]
        if not live:
            return
        k, t = min(live)
        yield k
        nxt[t] = b.find(t, k + 1)


class _Damage(Exception):
    def __init__(self, text: str, at: int | None = None):
        super().__init__(text)
        self.at = at  # byte offset of the damaged record inside its container, where known


def _fields(header: bytes) -> dict[str, bytes]:
    header = bytes(header)  # (a memoryview slice from the export's scan; bytes stay as they are)
    out: dict[str, bytes] = {}
    off, n = 0, len(header)
    while off < n:
        if off + 4 > n:
            raise _Damage("header field cut")
        (ln,) = _U32.unpack_from(header, off)
        off += 4
        if off + ln > n:
            raise _Damage("header field runs past its header")
        name, sep, value = header[off:off + ln].partition(b"=")
        if not sep:
            raise _Damage("header field without '='")
        out[name.decode("ascii", "replace")] = value
        off += ln
    return out


def _walk_records(buf, start, end):  # compiled with numba (logtools.jit), one pass over a container
    """Offsets, header and data lengths of the records in buf[start:end] up to the first that does not fit;
    returns (offsets, header lengths, data lengths, error: 0 none / 1 record cut / 2 header / 3 data, at)."""
    cap = (end - start) // 8 + 1
    offs = np.empty(cap, np.int64)
    hls = np.empty(cap, np.int64)
    dls = np.empty(cap, np.int64)
    n = 0
    off = start
    err = 0
    while off < end:
        if off + 4 > end:
            err = 1
            break
        hlen = np.int64(buf[off]) | (np.int64(buf[off + 1]) << 8) | (np.int64(buf[off + 2]) << 16) | \
            (np.int64(buf[off + 3]) << 24)
        h0 = off + 4
        if h0 + hlen + 4 > end:
            err = 2
            break
        q = h0 + hlen
        dlen = np.int64(buf[q]) | (np.int64(buf[q + 1]) << 8) | (np.int64(buf[q + 2]) << 16) | \
            (np.int64(buf[q + 3]) << 24)
        if q + 4 + dlen > end:
            err = 3
            break
        offs[n] = off
        hls[n] = hlen
        dls[n] = dlen
        n += 1
        off = q + 4 + dlen
    return offs[:n], hls[:n], dls[:n], err, off


_walk = jit.lazy(_walk_records)
_RUN_BYTES = 4096  # a container shorter than this is walked record by record (no numpy set-up per record)
_WALK_ERRORS = {1: "record cut at byte {}", 2: "record header at byte {} runs past its container",
                3: "record data at byte {} runs past its container"}


class _Scan:
    def __init__(self, keep: Callable[[str, str], bool]):
        self.keep = keep
        self.conns: dict[int, tuple[str, str, str]] = {}  # id -> topic, msgtype, msgdef
        self.times: dict[int, list[int]] = {}
        self.data: dict[int, list[bytes] | None] = {}
        self.warnings: list[str] = []
        self.layout: dict[int, tuple[int, int, int] | None] = {}  # header length -> op/conn/time offsets

    def connection(self, header: dict[str, bytes], data: bytes) -> None:
        (cid,) = _U32.unpack_from(header["conn"], 0)
        if cid in self.conns:
            return
        f = _fields(data)
        topic = (f.get("topic") or header.get("topic") or b"").decode("utf-8", "replace")
        msgtype = rc.normalize_msgtype(f.get("type", b"").decode("utf-8", "replace"))
        msgdef = f.get("message_definition", b"").decode("utf-8", "replace")
        self.conns[cid] = (topic, msgtype, msgdef)
        self.times[cid] = []
        self.data[cid] = [] if self.keep(topic, msgtype) else None

    @property
    def count(self) -> int:
        """Messages read so far."""
        return sum(map(len, self.times.values()))

    def _msg_layout(self, hdr: bytes) -> tuple[int, int, int] | None:
        """Offsets (inside the header) of the op, conn and time values of a MSG_DATA header."""
        pos: dict[str, int] = {}
        off = 0
        hdr = bytes(hdr)
        while off < len(hdr):
            (ln,) = _U32.unpack_from(hdr, off)
            eq = hdr.index(b"=", off + 4, off + 4 + ln)
            pos[hdr[off + 4:eq].decode("ascii", "replace")] = eq + 1
            off += 4 + ln
        if set(pos) != {"op", "conn", "time"}:
            return None
        return pos["op"], pos["conn"], pos["time"]

    def records(self, buf: bytes, start: int, end: int, where: str) -> None:
        """The records of buf[start:end] in order: MSG_DATA records of a known header layout in vectorised
        runs (compiled mode: the walk is one numba pass), every other record one by one."""
        if not jit.compiled() or end - start < _RUN_BYTES:  # (a top-level record of an unchunked bag: one)
            return self._records_one_by_one(buf, start, end, where)
        arr = np.frombuffer(buf, np.uint8)
        offs, hls, dls, err, at = _walk()(arr, start, end)
        fast = np.zeros(len(offs), bool)
        lay = np.full((len(offs), 3), -1, np.int64)
        for h in np.unique(hls).tolist():
            rows = np.flatnonzero(hls == h)
            got = self.layout.get(h, 0)
            if got == 0:
                o = int(offs[rows[0]]) + 4
                try:
                    got = self._msg_layout(buf[o:o + h])
                except (ValueError, struct.error):
                    got = None
                self.layout[h] = got
            if got is not None:
                lay[rows] = got
                op_at = offs[rows] + 4 + got[0]
                fast[rows] = (arr[op_at] == _OP_MSG) & (arr[op_at - 3] == ord("o")) & \
                    (arr[op_at - 2] == ord("p")) & (arr[op_at - 1] == ord("="))
        slow = np.flatnonzero(~fast).tolist()
        a = 0
        for b in slow + [len(offs)]:
            if b > a:
                self._messages(buf, arr, offs[a:b], hls[a:b], dls[a:b], lay[a:b], where)
            if b < len(offs):
                o = int(offs[b])
                self._records_one_by_one(buf, o, o + 8 + int(hls[b]) + int(dls[b]), where)
            a = b + 1
        if err:
            raise _Damage(f"{where}: " + _WALK_ERRORS[int(err)].format(int(at)), int(at))

    def _messages(self, buf: bytes, arr: np.ndarray, offs, hls, dls, lay, where: str) -> None:
        """A run of MSG_DATA records with known layouts: times and payloads appended per connection."""
        h0 = offs + 4
        c_at = h0 + lay[:, 1]
        cid = (arr[c_at].astype(np.int64) | (arr[c_at + 1].astype(np.int64) << 8) |
               (arr[c_at + 2].astype(np.int64) << 16) | (arr[c_at + 3].astype(np.int64) << 24))
        t_at = h0 + lay[:, 2]
        sn = arr[t_at[:, None] + np.arange(8)].view("<u4").astype(np.int64)
        t_ns = sn[:, 0] * 1_000_000_000 + sn[:, 1]
        d0 = h0 + hls + 4
        known = np.isin(cid, np.fromiter(self.times, np.int64, len(self.times)))
        stop = len(cid) if known.all() else int(np.argmin(known))
        self._keep(buf, arr, cid[:stop], t_ns[:stop], d0[:stop], dls[:stop], offs[:stop], t_at[:stop])
        if stop < len(cid):
            raise _Damage(f"{where}: message for unknown connection {int(cid[stop])} at byte {int(offs[stop])}",
                          int(offs[stop]))

    def _keep(self, buf: bytes, arr: np.ndarray, cid, t_ns, d0, lens, rec_at, t_at) -> None:
        """Messages of known connections, in file order: record times and payload bytes per connection
        (``d0``: where the payloads start in ``arr``; ``rec_at``, ``t_at``: where their records and their
        record times lie, for the export)."""
        d1 = d0 + lens
        for c in np.unique(cid).tolist():
            rows = np.flatnonzero(cid == c)
            self.times[c].extend(t_ns[rows].tolist())
            d = self.data[c]
            if d is not None:
                d.extend([buf[x:y] for x, y in zip(d0[rows].tolist(), d1[rows].tolist())])

    def _records_one_by_one(self, buf: bytes, start: int, end: int, where: str) -> None:
        off = start
        u32 = _U32.unpack_from
        tm = _TIME.unpack_from
        layouts = self.layout
        times, data = self.times, self.data
        while off < end:
            if off + 4 > end:
                raise _Damage(f"{where}: record cut at byte {off}", off)
            (hlen,) = u32(buf, off)
            h0 = off + 4
            if h0 + hlen + 4 > end:
                raise _Damage(f"{where}: record header at byte {off} runs past its container", off)
            (dlen,) = u32(buf, h0 + hlen)
            d0 = h0 + hlen + 4
            nxt = d0 + dlen
            if nxt > end:
                raise _Damage(f"{where}: record data at byte {off} runs past its container", off)
            lay = layouts.get(hlen, 0)
            if lay == 0:
                try:
                    lay = self._msg_layout(buf[h0:h0 + hlen])
                except (ValueError, struct.error):
                    lay = None
                layouts[hlen] = lay
            if lay is not None and buf[h0 + lay[0]] == _OP_MSG and buf[h0 + lay[0] - 3:h0 + lay[0]] == b"op=":
                (cid,) = u32(buf, h0 + lay[1])
                sec, nsec = tm(buf, h0 + lay[2])
                lst = times.get(cid)
                if lst is None:
                    raise _Damage(f"{where}: message for unknown connection {cid} at byte {off}", off)
                lst.append(sec * 1_000_000_000 + nsec)
                d = data[cid]
                if d is not None:
                    d.append(buf[d0:nxt])
                off = nxt
                continue
            try:
                header = _fields(buf[h0:h0 + hlen])
            except _Damage as exc:
                raise _Damage(f"{where}: record at byte {off}: {exc}", off) from None
            op = header.get("op", b"\xff")[:1]
            if op == bytes([_OP_CONN]):
                self.connection(header, buf[d0:nxt])
            elif op == bytes([_OP_MSG]):
                try:
                    (cid,) = _U32.unpack_from(header["conn"], 0)
                    sec, nsec = _TIME.unpack_from(header["time"], 0)
                except (KeyError, struct.error):
                    raise _Damage(f"{where}: message record at byte {off} without conn/time", off) from None
                if cid not in times:
                    raise _Damage(f"{where}: message for unknown connection {cid} at byte {off}", off)
                times[cid].append(sec * 1_000_000_000 + nsec)
                if data[cid] is not None:
                    data[cid].append(buf[d0:nxt])
            elif op == bytes([_OP_CHUNK]):
                self.chunk(header, buf, d0, nxt, off)
            elif op not in (bytes([_OP_BAGHEADER]), bytes([_OP_INDEX]), bytes([_OP_CHUNKINFO])):
                raise _Damage(f"{where}: unknown record op {op!r} at byte {off}", off)
            off = nxt

    def chunk(self, header: dict[str, bytes], buf: bytes, d0: int, d1: int, where: int) -> None:
        comp = header.get("compression", b"none").decode("ascii", "replace")
        size = _U32.unpack_from(header.get("size", b"\0\0\0\0"), 0)[0]
        c0, c1 = d0, d1  # an uncompressed chunk's records are walked where they lie (not copied out)
        try:
            if comp == "none":
                content = buf
            elif comp == "bz2":
                content = bz2.decompress(buf[d0:d1])
            elif comp == "lz4":
                import lz4.frame

                content = lz4.frame.decompress(buf[d0:d1])
            else:
                raise _Damage(f"chunk at byte {where}: unsupported compression {comp!r}")
        except _Damage:
            raise
        except Exception as exc:  # what decompresses before the damaged block is walked (bz2: 900 kB blocks)
            why = f"chunk at byte {where} cannot be decompressed ({type(exc).__name__})"
            content = rc.inflate_prefix(comp, buf[d0:d1])
            if not content:
                raise _Damage(why) from None
            self.warnings.append(f"damaged: {why}; read as far as it decompresses ({len(content)} of {size} "
                                 "bytes), the rest of the chunk lost")
            size = len(content)
        if comp != "none":
            c0, c1 = 0, len(content)
        if c1 - c0 != size:
            raise _Damage(f"chunk at byte {where}: size {c1 - c0} != {size}")
        before = self.count
        pos, places, skipped = c0, [], 0
        while True:
            try:
                self.records(content, pos, c1, f"chunk at byte {where}")
                break
            except (_Damage, struct.error, KeyError, ValueError) as exc:  # keep what was read before
                at = exc.at if isinstance(exc, _Damage) else None
                nxt = None if at is None else self._resync(content, at + 1, c1)
                if nxt is None:
                    n_new = self.count - before
                    text = str(exc) if isinstance(exc, _Damage) else f"chunk at byte {where}: {type(exc).__name__} {exc}"
                    if places:
                        text += f" (after {len(places)} damaged place(s) skipped, {skipped} bytes)"
                    raise _Damage(f"{text} (kept the {n_new} messages of that chunk before the damage)") from None
                places.append(at - c0)
                skipped += nxt - at
                pos = nxt
        if places:
            self.warnings.append(f"damaged: chunk at byte {where}: {len(places)} damaged record(s) (first at byte "
                                 f"{places[0]} of the chunk), {skipped} bytes skipped to the next readable record")

    def _resync(self, buf: bytes, start: int, end: int) -> int | None:
        """The first offset >= ``start`` where a MSG_DATA record of a header layout seen before starts, with
        its conn= and time= fields where that layout has them, a known connection and data inside ``end``;
        None if there is none."""
        known = [(h, lay) for h, lay in self.layout.items() if lay is not None]
        if not known:
            return None
        u32 = _U32.unpack_from
        if not isinstance(buf, bytes):  # (the export's memoryview of the file: its find() is that of bytes)
            base = start
            buf = bytes(buf[base:end])
            r = self._resync(buf, 0, end - base)
            return None if r is None else r + base
        k = buf.find(b"op=\x02", start)
        while k >= 0:
            for hlen, (o_op, o_conn, o_time) in known:
                h0 = k + 3 - o_op
                r = h0 - 4
                if r < start or h0 + hlen + 4 > end or u32(buf, r)[0] != hlen:
                    continue
                if buf[h0 + o_conn - 5:h0 + o_conn] != b"conn=" or buf[h0 + o_time - 5:h0 + o_time] != b"time=":
                    continue
                if u32(buf, h0 + o_conn)[0] not in self.times or h0 + hlen + 4 + u32(buf, h0 + hlen)[0] > end:
                    continue
                return r
            k = buf.find(b"op=\x02", k + 1)
        return None


def read_raw(path: str, keep: Callable[[str, str], bool] = rc.keep_supported, fmt: str = NAME) -> rc.RawLog:
    check_readable(path)
    with open(path, "rb") as fh:
        buf = fh.read()
    scan = _Scan(keep)
    _walk_file(buf, scan, path)
    return _rawlog(path, fmt, scan)


def _walk_file(buf, scan: _Scan, path: str, progress: Callable[[int], None] | None = None) -> _Scan:
    """The top-level record walk of a bag's bytes ``buf`` (bytes or a read-only map of the file) into
    ``scan``, damage noted in ``scan.warnings``; ``progress(offset)``: called after each top-level record
    (the streamed read lets the pages behind it go)."""
    off, end = len(MAGIC), len(buf)
    if bytes(buf[:len(MAGIC)]) != MAGIC:
        off = resync_top(buf, 0, end)
        if off is None:
            raise InputError("not a ROS 1 bag (magic '#ROSBAG V2.0' missing)", path)
        scan.warnings.append(f"damaged: the file does not start as a ROS 1 bag; read from the first chunk or "
                             f"connection record (byte {off})")
    index_pos = None
    good = off  # the end of the last record read well: a walk derailed by damage goes on after it
    floor = -1
    indexes = IndexCheck()
    while off < end:
        try:
            header, op, hlen, nxt = top_record(buf, off, end)
        except (_Damage, struct.error) as exc:
            at = resume_top(buf, off, good, floor, end)
            if at is None:
                scan.warnings.append(f"{exc}; readable part used" if "truncated" in str(exc)
                                     else f"damaged at byte {off} ({exc}); rest of file ignored")
                break
            scan.warnings.append(f"damaged at byte {off} ({exc}); went on at the next chunk or connection "
                                 f"record (byte {at})")
            floor = off = at
            continue
        scan.done = nxt
        try:
            if op == bytes([_OP_BAGHEADER]):
                (index_pos,) = struct.unpack_from("<Q", header.get("index_pos", b"\0" * 8), 0)
            elif op == bytes([_OP_CHUNK]):
                indexes.chunk_at(off, header)
                scan.chunk(header, buf, off + 8 + hlen, nxt, off)
            elif op in (bytes([_OP_CONN]), bytes([_OP_MSG])):
                scan.records(buf, off, nxt, "top level")
            elif op in (bytes([_OP_INDEX]), bytes([_OP_CHUNKINFO])):
                indexes.index_at(op, header, buf, off, off + 8 + hlen, nxt, scan.conns)
            else:
                raise _Damage(f"unknown record op {op!r} at byte {off}")
        except (_Damage, struct.error, KeyError, ValueError) as exc:
            scan.warnings.append(f"damaged: {exc}; its messages dropped" if not isinstance(exc, _Damage)
                                 else f"damaged: {exc}")
        good = off = nxt  # (its framing read: a later resynchronisation starts after it)
        if progress is not None:
            progress(off)
    if (said := indexes.said(INDEX_UNUSED)) is not None:
        scan.warnings.append(said)
    if index_pos == 0:
        scan.warnings.append("bag has no index (recording interrupted?): messages read by a linear scan")
    elif index_pos is not None and index_pos >= end and not any("truncated" in w for w in scan.warnings):
        span = _time_span(scan)
        scan.warnings.append(index_past_end(index_pos, end, span) + " up to the cut")
    return scan


def index_damaged(op: bytes, header: dict[str, bytes], buf, d0: int, d1: int, chunk_size: int | None,
                  chunk_offsets: set[int], conns) -> bool:
    """Whether an index record (index data, op 4: after each chunk; chunk info, op 6: at the end) is damaged:
    its entries do not fill its data, it names a connection the file does not define (``conns``: the ids read
    so far), an index entry points past the chunk before it (``chunk_size``: that chunk's uncompressed size;
    None: not checked), or a chunk info names no chunk record of the file (``chunk_offsets``: where they start)
    or ends before it starts. The readers here never need the index (the messages are read from the chunks): a
    damaged one is only said; rosbag's and rosbags' readers go by it."""
    def u32(name: str) -> int | None:
        v = header.get(name)
        return _U32.unpack_from(v, 0)[0] if v is not None and len(v) == 4 else None

    count = u32("count")
    if count is None:
        return True
    if op == bytes([_OP_INDEX]):
        if d1 - d0 != 12 * count or u32("conn") not in conns:
            return True
        if chunk_size is None or not count:
            return False
        offs = np.frombuffer(buf, "<u4", 3 * count, d0).reshape(-1, 3)[:, 2]
        return int(offs.max()) >= chunk_size
    pos, t0, t1 = (header.get(k) for k in ("chunk_pos", "start_time", "end_time"))
    if d1 - d0 != 8 * count or any(v is None or len(v) != 8 for v in (pos, t0, t1)):
        return True
    start, end = (struct.unpack("<II", v) for v in (t0, t1))
    ids = np.frombuffer(buf, "<u4", 2 * count, d0)[::2] if count else ()
    return struct.unpack("<Q", pos)[0] not in chunk_offsets or start > end or any(int(c) not in conns for c in ids)


class IndexCheck:
    """The index records one walk over a ROS 1 bag meets, each checked against the chunks before it
    (:func:`index_damaged`), tallied and said once at the walk's end (:meth:`said`)."""

    def __init__(self):
        self.chunk_size: int | None = None  # the last chunk's uncompressed size (None: not stated)
        self.chunk_offsets: set[int] = set()  # where the chunk records start
        self.bad = DamagedRecords(INDEX_DAMAGE)

    def chunk_at(self, off: int, header: dict[str, bytes]) -> None:
        self.chunk_offsets.add(off)
        size = header.get("size", b"")
        self.chunk_size = _U32.unpack_from(size, 0)[0] if len(size) == 4 else None

    def index_at(self, op: bytes, header: dict[str, bytes], buf, off: int, d0: int, d1: int, conns) -> None:
        if index_damaged(op, header, buf, d0, d1, self.chunk_size, self.chunk_offsets, conns):
            self.bad.add(off)

    def said(self, then: str) -> str | None:
        return self.bad.said(then)


#: damaged index records (:func:`index_damaged`), as ``base.DamagedRecords`` says them, and what the readers
#: do about them
INDEX_DAMAGE = "index record(s) do not match the chunks"
INDEX_UNUSED = ("not used, the messages are read from the chunks themselves (rosbag's and rosbags' readers, "
                "which go by the index, may fail on this file)")


def _time_span(scan: _Scan) -> float | None:
    """The record time the messages read cover (s), None without messages."""
    ranges = []
    for t in scan.times.values():
        if not len(t):
            continue
        if isinstance(t, _Times):
            a = t.array()
            ranges.append((int(a.min()), int(a.max())))
        else:
            ranges.append((min(t), max(t)))
    if not ranges:
        return None
    return (max(r[1] for r in ranges) - min(r[0] for r in ranges)) * 1e-9


# ---- the streamed read: kept topics decoded while the bag is read -----------------------------------
class _Times:
    """One connection's record times as int64 arrays, batch by batch (the one-by-one path's ints are
    gathered in a short list first). Has ``append`` and ``len`` as the plain scan's lists."""

    __slots__ = ("parts", "pending", "n")

    def __init__(self):
        self.parts: list[np.ndarray] = []
        self.pending: list[int] = []
        self.n = 0

    def append(self, t: int) -> None:
        self.pending.append(t)
        self.n += 1

    def add(self, t_ns: np.ndarray) -> None:
        self._flush()
        self.parts.append(t_ns)
        self.n += len(t_ns)

    def _flush(self) -> None:
        if self.pending:
            self.parts.append(np.array(self.pending, np.int64))
            self.pending = []

    def __len__(self) -> int:
        return self.n

    def array(self) -> np.ndarray:
        self._flush()
        if len(self.parts) != 1:
            self.parts = [np.concatenate(self.parts) if self.parts else np.zeros(0, np.int64)]
        return self.parts[0]


class _Feed:
    """One kept connection's payloads handed to its StreamDecoder as they are read: vectorised runs as
    (buffer, starts, ends), the one-by-one path's ``append``-ed bytes in batches, the order of the file
    kept."""

    __slots__ = ("dec", "pending", "expect")
    BATCH = 4096

    def __init__(self, dec: rc.StreamDecoder, expect: Callable[[], int]):
        self.dec, self.expect = dec, expect
        self.pending: list[bytes] = []

    def append(self, payload: bytes) -> None:
        self.pending.append(payload)
        if len(self.pending) >= self.BATCH:
            self.flush()

    def add(self, arr: np.ndarray, s: np.ndarray, e: np.ndarray) -> None:
        self.flush()
        self.dec.add(arr, s, e, self.expect())

    def flush(self) -> None:
        if self.pending:
            p, self.pending = self.pending, []
            lens = np.fromiter(map(len, p), np.int64, len(p))
            e = np.cumsum(lens)
            self.dec.add(np.frombuffer(b"".join(p), np.uint8), e - lens, e, self.expect())


def _decoder(topic: str, msgtype: str, msgdef: str) -> rc.StreamDecoder:
    """The streaming decoder of a kept connection: layouts made with the connection's own message
    definition, else the built-in one (``_rawlog_streamed`` checks them against the bag's final ones)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.EMPTY)
    try:  # (an unusable definition is said by _rawlog_streamed, not here)
        _register_type(store, topic, msgtype, msgdef, [])
    except Exception:  # noqa: BLE001 - no layout then: every message kept for the end
        pass
    return rc.StreamDecoder(topic, msgtype, "ros1", store)


class _StreamScan(_Scan):
    """The scan of :func:`read_streamed`: record times as int64 arrays (:class:`_Times`), the payloads of
    kept connections fed to a StreamDecoder per connection (:class:`_Feed`) instead of kept as bytes."""

    def __init__(self, keep: Callable[[str, str], bool], size: int):
        super().__init__(keep)
        self.size = max(size, 1)
        self.done = 0  # the end of the top-level record being read (the decoders' capacity estimates)
        self.decoders: dict[int, rc.StreamDecoder] = {}

    def connection(self, header: dict[str, bytes], data: bytes) -> None:
        (cid,) = _U32.unpack_from(header["conn"], 0)
        if cid in self.conns:
            return
        super().connection(header, data)
        topic, msgtype, msgdef = self.conns[cid]
        times = self.times[cid] = _Times()
        if self.data[cid] is not None:
            if msgtype not in rc.SUPPORTED:
                raise rc.NotStreamable(f"{topic}: kept, but not a type decoded while reading")
            dec = self.decoders[cid] = _decoder(topic, msgtype, msgdef)
            self.data[cid] = _Feed(dec, lambda: int(1.25 * len(times) * self.size / max(self.done, 1)) + 1024)

    def _keep(self, buf: bytes, arr: np.ndarray, cid, t_ns, d0, lens, rec_at, t_at) -> None:
        d1 = d0 + lens
        present = np.unique(cid).tolist()
        for c in present:
            rows = None if len(present) == 1 else np.flatnonzero(cid == c)
            self.times[c].add(t_ns.copy() if rows is None else t_ns[rows])
            d = self.data[c]
            if d is not None:
                d.add(arr, d0 if rows is None else d0[rows], d1 if rows is None else d1[rows])


def read_streamed(path: str, keep: Callable[[str, str], bool] = rc.keep_supported, fmt: str = NAME) -> rc.RawLog:
    """:func:`read_raw` with every kept topic decoded while the bag is read (``RawTopic.decoded``, only the
    first messages' bytes kept; record times as int64 arrays), the file memory-mapped and its pages let go
    behind the walk: the log in memory about once, in columns, instead of as per-message bytes and ints.
    rc.NotStreamable where that cannot give exactly what read_raw + decode give."""
    from parsers.filemap import FileMap

    check_readable(path)
    with FileMap(path) as fm:
        scan = _StreamScan(keep, fm.size)
        _walk_file(fm.buf, scan, path, fm.release_before)
    return _rawlog_streamed(path, fmt, scan)


def _register_type(typestore, topic: str, msgtype: str, msgdef: str, warnings: list[str]) -> None:
    """A kept connection's message type in ``typestore``: from the bag's own definition, else (none, or
    unusable: said in ``warnings``) the built-in one of a supported type."""
    if msgdef and msgtype not in typestore.fielddefs:
        try:
            rc.register_msgdef(typestore, msgtype, msgdef, "msg")
        except Exception as exc:
            warnings.append(f"{topic}: message definition of {msgtype} unusable ({type(exc).__name__})")
    if msgtype in rc.SUPPORTED:
        from parsers.mcap_ros import register_builtin

        register_builtin(typestore, {msgtype}, "ros1")


def _rawlog_streamed(path: str, fmt: str, scan: _StreamScan) -> rc.RawLog:
    """:func:`_rawlog` of a streamed scan: the same typestore and warnings, the kept topics' decoders
    finished with the bag's final message definitions."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.EMPTY)
    topics: dict[str, rc.RawTopic] = {}
    streamed: dict[str, rc.StreamDecoder] = {}
    for cid, (topic, msgtype, msgdef) in scan.conns.items():
        keep = scan.data[cid] is not None
        if keep:
            _register_type(typestore, topic, msgtype, msgdef, scan.warnings)
            scan.data[cid].flush()
        log_ns = scan.times.pop(cid).array()
        if topic in topics:
            old = topics[topic]
            if keep or topic in streamed:  # (read_raw merges the messages in time order)
                raise rc.NotStreamable(f"{topic}: kept, on several connections")
            old.log_ns = np.sort(np.concatenate([old.log_ns, log_ns]), kind="stable")
            continue
        topics[topic] = rc.RawTopic(topic, msgtype, "ros1", log_ns, [])
        if keep:
            streamed[topic] = scan.decoders.pop(cid)
    for topic, dec in streamed.items():  # the rest of each streamed topic, with the final definitions
        topics[topic].decoded, topics[topic].data = dec.finish(typestore)
    return rc.RawLog(path=path, fmt=fmt, topics=topics, typestore=typestore, warnings=scan.warnings)


def _read_for_decode(path: str) -> rc.RawLog:
    """The bag decoded while read (:func:`read_streamed`), or read the classic way where that cannot be
    exact (rc.NotStreamable: a zoo of message lengths, a kept topic on several connections...)."""
    try:
        return read_streamed(path)
    except rc.NotStreamable:
        return read_raw(path, keep=rc.keep_supported)


def index_past_end(index_pos: int | None, size: int, span_s: float | None) -> str | None:
    """The warning for a bag cut exactly between two records (every record reads whole, so the walk sees no
    damage): the index the bag header points to, written last at the end of the bag, lies at or past the
    end of the file. None for a bag whose index is inside it (or that has none). ``span_s``: the record
    time the readable part covers (None: no messages)."""
    if not index_pos or index_pos < size:
        return None
    return (f"truncated: the bag header puts the index at byte {index_pos}, beyond the end of the file "
            f"({size} bytes); " + (f"{span_s:.1f} s of record time read" if span_s is not None else "no messages read"))


def _rawlog(path: str, fmt: str, scan: _Scan) -> rc.RawLog:
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.EMPTY)
    topics: dict[str, rc.RawTopic] = {}
    for cid, (topic, msgtype, msgdef) in scan.conns.items():
        keep = scan.data[cid] is not None
        if keep:
            _register_type(typestore, topic, msgtype, msgdef, scan.warnings)
        raw = rc.RawTopic(topic, msgtype, "ros1", scan.times[cid], scan.data[cid] if keep else [])
        if topic in topics:
            old = topics[topic]
            merged = sorted(zip(old.log_ns + raw.log_ns, range(old.count + raw.count)))
            data = old.data + raw.data if keep and old.data is not None else []
            old.log_ns = [t for t, _ in merged]
            old.data = [data[i] for _, i in merged] if data else []
            continue
        topics[topic] = raw
    return rc.RawLog(path=path, fmt=fmt, topics=topics, typestore=typestore, warnings=scan.warnings)


def load(path: str, selector: Selector) -> InsLog:
    if os.path.isdir(path):
        raise InputError("is a directory, not a ROS 1 bag", path)
    return rc.to_inslog(_read_for_decode(path), selector, release=True)


def inventory(path: str) -> Inventory:
    return rc.to_inventory(_read_for_decode(path))


def write(path: str, log: InsLog, *, log_delay_ns: int = 0, compression: str = "none") -> None:
    """Write ``log`` as a ROS 1 bag (rosbags.rosbag1.Writer), ENU/FLU, exact ns stamps;
    ``compression`` none, bz2 or lz4 (chunks)."""
    from rosbags.rosbag1 import Writer

    if compression not in ("none", "bz2", "lz4"):
        raise InputError(f"rosbag1 compression must be none, bz2 or lz4, not {compression!r}", path)
    typestore = rc.default_typestore("ros1")
    topics = rc.ros_topics_from_inslog(log, typestore, "ros1")
    with atomic_path(path) as tmp:
        os.remove(tmp)  # the rosbags writer refuses to overwrite
        w = Writer(tmp)
        if compression != "none":
            w.set_compression(Writer.CompressionFormat[compression.upper()])
        with w:
            conns = [w.add_connection(tp.name, tp.msgtype, typestore=typestore) for tp in topics]
            for t, k, i in rc.merged_order(topics, log_delay_ns):
                w.write(conns[k], t, topics[k].data[i])
