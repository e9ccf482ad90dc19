"""Vectorised writers of the ROS 1 bag and MCAP containers, for :mod:`parsers.restamp_ros`.

Messages come as one packed byte array (``msgs.buf``; ``msgs.starts``, ``msgs.lens`` per message,
``msgs.conn`` their stream) with their new record times. A numba kernel lays out all the records of a
chunk in one pass (record prefix + payload); chunks are compressed with the input's compression, and
the indexes (ROS 1 index data and chunk infos; MCAP message indexes, chunk indexes, statistics,
summary) are built from the new times. The per-message writers of rosbags and mcap took 4-7 times
tapost's parse time of the same file; these files are checked against rosbags' AnyReader and the mcap
readers in tests/test_export_ros.py.
"""
from __future__ import annotations

import dataclasses
import struct
import threading
import zlib

import numpy as np

from parsers import mcap_ros, rosbag1, threads

# ---- vectorised record writing ---------------------------------------------------------------------
def _lay_out(out, rec_off, prefix, src, starts, lens):  # compiled with numba (_kernel)
    """Record i = prefix[i] then src[starts[i]:starts[i] + lens[i]], at out[rec_off[i]:]."""
    p = prefix.shape[1]
    for i in range(len(rec_off)):
        o = rec_off[i]
        out[o:o + p] = prefix[i]
        out[o + p:o + p + lens[i]] = src[starts[i]:starts[i] + lens[i]]


def _bag1_record_times(buf, t_at, times):  # compiled with numba (_kernel)
    """times[i] (8 bytes: a ROS time) written at buf[t_at[i]:], where the 4-byte length before ``time=``
    (buf[t_at[i] - 9]) says 13; returns the first i where it does not (len(t_at): every record written)."""
    for i in range(len(t_at)):
        o = t_at[i]
        if buf[o - 9] != 13 or buf[o - 8] != 0 or buf[o - 7] != 0 or buf[o - 6] != 0:
            return i
        for j in range(8):
            buf[o + j] = times[i, j]
    return len(t_at)


def _bag1_index_times(buf, pos, base, rec_at, conn, want, times):  # compiled with numba (_kernel)
    """ROS 1 index entries (12 bytes: time, offset of the record in its chunk's data) at buf[pos[i]:]: the
    message whose record starts at base[i] + that offset (rec_at: increasing) and is of connection want[i]
    (conn: each message's) gets its time times[m] written in the entry. Returns the first i that points at
    no such message (len(pos): every entry written)."""
    n = len(rec_at)
    lo = 0
    for i in range(len(pos)):
        p = pos[i]
        at = base[i] + (np.int64(buf[p + 8]) | (np.int64(buf[p + 9]) << 8) | (np.int64(buf[p + 10]) << 16)
                        | (np.int64(buf[p + 11]) << 24))
        # (an entry's message is a few places after the previous entry's, most often: looked for there first)
        k = lo + 1
        while k < n and k < lo + 16 and rec_at[k] < at:
            k += 1
        if k < n and k < lo + 16 and rec_at[k] == at and (k == 0 or rec_at[k - 1] < at):
            lo = k
        else:
            lo, hi = 0, n
            while lo < hi:
                mid = (lo + hi) // 2
                if rec_at[mid] < at:
                    lo = mid + 1
                else:
                    hi = mid
        if lo == n or rec_at[lo] != at or conn[lo] != want[i]:
            return i
        for j in range(8):
            buf[p + j] = times[lo, j]
    return len(pos)


def _mcap_record_times(buf, starts, log_ns, delta):  # compiled with numba (_kernel)
    """MCAP message records' log and publish times (the 16 bytes before each payload at ``starts``) set: the
    log time to ``log_ns[i]``, a publish time other than 0 (unset) moved by ``-delta[i]``."""
    for i in range(len(starts)):
        o = starts[i] - 16
        t = log_ns[i]
        for j in range(8):
            buf[o + j] = (t >> (8 * j)) & 0xFF
        pub = np.int64(0)
        for j in range(8):
            pub |= np.int64(buf[o + 8 + j]) << (8 * j)
        if pub != 0:
            pub -= delta[i]
            for j in range(8):
                buf[o + 8 + j] = (pub >> (8 * j)) & 0xFF


def _header_stamps_get(buf, at, cdr, stamp, be):  # compiled with numba (_kernel)
    """stamp[i]: the Header stamp (uint32 sec, uint32 nanosec, ns) at buf[at[i] + 4:] (after ROS 1's seq, after
    CDR's encapsulation); be[i]: big endian (``cdr`` and the encapsulation's second byte 0)."""
    for i in range(len(at)):
        s = at[i]
        big = cdr and buf[s + 1] == 0
        be[i] = big
        sec = np.int64(0)
        nsec = np.int64(0)
        for j in range(4):
            k = 3 - j if big else j
            sec |= np.int64(buf[s + 4 + j]) << (8 * k)
            nsec |= np.int64(buf[s + 8 + j]) << (8 * k)
        stamp[i] = sec * 1_000_000_000 + nsec


def _header_stamps_put(buf, at, new, be):  # compiled with numba (_kernel)
    """The Header stamps at buf[at[i] + 4:] set to new[i] (ns, >= 0; uint32 sec and nanosec, big endian where
    be[i])."""
    for i in range(len(at)):
        s = at[i] + 4
        sec = new[i] // 1_000_000_000
        nsec = new[i] - sec * 1_000_000_000
        for j in range(4):
            k = 3 - j if be[i] else j
            buf[s + j] = (sec >> (8 * k)) & 0xFF
            buf[s + 4 + j] = (nsec >> (8 * k)) & 0xFF


_KERNELS: dict = {}


def _kernel(name: str = "_lay_out"):
    fn = _KERNELS.get(name)
    if fn is None:
        from logtools import jit  # compiled in compiled mode (cached on disk), plain Python otherwise

        fn = _KERNELS[name] = jit.njit(globals()[name], nogil=True)  # (_lay_out runs in the writer's threads)
    return fn


def header_stamps(buf: np.ndarray, starts: np.ndarray, cdr: bool) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, ns; big-endian mask) of the Header-first messages whose payloads (12 bytes or more) start at
    ``starts``: the stamp's sec and nanosec at bytes 4..12 (after ROS 1's seq, after CDR's encapsulation, whose
    second byte 0 says big endian)."""
    from logtools import jit
    from parsers.restamp import get_bytes

    starts = np.asarray(starts, np.int64)
    if len(starts) and (int(starts.min()) < 0 or int(starts.max()) + 12 > len(buf)):
        raise IndexError("a Header stamp lies outside the buffer")
    if jit.compiled():
        stamp, be = np.empty(len(starts), np.int64), np.empty(len(starts), np.bool_)
        _kernel("_header_stamps_get")(buf, starts, cdr, stamp, be)
        return stamp, be
    raw = get_bytes(buf, starts + 4, 8)
    be = (buf[starts + 1] == 0) if cdr else np.zeros(len(starts), bool)  # CDR 00 00: big endian
    le_v = raw.view("<u4").astype(np.int64)
    if be.any():
        le_v[be] = raw[be].view(">u4").astype(np.int64)
    return le_v[:, 0] * 1_000_000_000 + le_v[:, 1], be


def put_header_stamps(buf: np.ndarray, starts: np.ndarray, new: np.ndarray, be: np.ndarray) -> None:
    """The Header stamps of the messages at ``starts`` (as :func:`header_stamps` reads them) set to ``new``
    (ns, >= 0), in their byte order ``be``."""
    from logtools import jit
    from parsers.restamp import put_bytes

    starts = np.asarray(starts, np.int64)
    if not len(starts):
        return
    if int(starts.min()) < 0 or int(starts.max()) + 12 > len(buf):
        raise IndexError("a Header stamp lies outside the buffer")
    if jit.compiled():
        _kernel("_header_stamps_put")(buf, starts, np.asarray(new, np.int64), np.asarray(be, np.bool_))
        return
    sn = np.stack([new // 1_000_000_000, new % 1_000_000_000], axis=1)
    vals = sn.astype("<u4").view(np.uint8).reshape(-1, 8)
    if be.any():
        vals[be] = sn[be].astype(">u4").view(np.uint8).reshape(-1, 8)
    put_bytes(buf, starts + 4, vals)


def patch_mcap_times(buf: np.ndarray, starts: np.ndarray, log_ns: np.ndarray, delta: np.ndarray) -> None:
    """The log and publish times of MCAP message records in ``buf`` (payloads at ``starts``) rewritten where
    they lie: log time ``log_ns``, a set publish time (not 0) less ``delta`` (both ns). In compiled mode one
    pass of a kernel that releases the GIL (run per chunk in the writer's threads); else numpy."""
    from logtools import jit
    from parsers.restamp import get_bytes, put_bytes

    if not len(starts):
        return
    if int(starts.min()) < 16 or int(starts.max()) > len(buf):
        raise IndexError("an MCAP message record's times lie outside the buffer")
    if jit.compiled():
        _kernel("_mcap_record_times")(buf, starts, log_ns, delta)
        return
    pub = get_bytes(buf, starts - 8, 8).view("<i8").ravel()
    times = np.empty((len(starts), 2), "<i8")
    times[:, 0], times[:, 1] = log_ns, np.where(pub != 0, pub - delta, 0)
    put_bytes(buf, starts - 16, times.view(np.uint8).reshape(len(starts), 16))


def patch_bag1_times(buf: np.ndarray, t_at: np.ndarray, times: np.ndarray) -> bool:
    """The record times of a ROS 1 bag's messages rewritten where they lie (``t_at``: each record's time
    value in ``buf``; ``times``: (n, 8) bytes); False (some written) where a record's time field is not 8
    bytes long."""
    if len(t_at) and (int(t_at.min()) < 9 or int(t_at.max()) + 8 > len(buf)):
        return False
    return _kernel("_bag1_record_times")(buf, t_at, times) == len(t_at)


def patch_bag1_index(buf: np.ndarray, pos: np.ndarray, base: np.ndarray, rec_at: np.ndarray, conn: np.ndarray,
                     want: np.ndarray, times: np.ndarray) -> bool:
    """The times of a ROS 1 bag's index entries (at ``pos``, in the index data records after the chunks whose
    data start at ``base``) set to their messages' ``times`` (messages: records at the increasing ``rec_at``,
    of connections ``conn``; ``want``: each entry's connection); False (some written) where an entry points
    at no message of its connection."""
    if len(pos) and (int(pos.min()) < 0 or int(pos.max()) + 12 > len(buf)):
        return False
    return _kernel("_bag1_index_times")(buf, pos, base, rec_at, conn, want, times) == len(pos)


def _records(prefix: np.ndarray, msgs, sel: slice) -> np.ndarray:
    """The records (prefix + payload) of messages ``sel``, concatenated."""
    lens = msgs.lens[sel]
    size = prefix.shape[1] + lens
    rec_off = np.cumsum(size) - size
    out = np.empty(int(size.sum()), np.uint8)
    _kernel()(out, rec_off, prefix, msgs.buf, msgs.starts[sel], lens)
    return out


def _chunks(size: np.ndarray, target: int) -> list[slice]:
    """Consecutive message ranges of about ``target`` record bytes each."""
    if not len(size):
        return []
    cum = np.cumsum(size)
    cut = np.flatnonzero(np.diff(cum // max(target, 1)) > 0) + 1
    edges = [0, *cut.tolist(), len(size)]
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _by_key(key: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """The (key, positions) groups of one chunk's messages (``key``: their channel or connection ids), keys
    ascending, positions in message order (one stable sort: a radix sort of 16-bit ids), for the chunk's
    message indexes; computed in the writer's threads, chunk by chunk."""
    if not len(key):
        return []
    order = np.argsort(key, kind="stable")
    kk = key[order]
    cut = np.flatnonzero(kk[1:] != kk[:-1]) + 1
    return [(int(kk[a]), order[a:b]) for a, b in zip(np.r_[0, cut].tolist(), np.r_[cut, len(key)].tolist())]


_LOCAL = threading.local()


#: zstd level of the chunks tapost writes: -1 (zstd's fast mode) compresses a 1 h IMU slave's 316 MB of
#: records 24 % faster than level 1 (0.22 against 0.30 s of CPU) into 2 % more bytes (57.7 against 56.5 MB,
#: level 3's size; the input, from the mcap library's writer, was 78 MB); every zstd reader reads it
ZSTD_LEVEL = -1


def _zstd_compressor():
    """This thread's zstd compressor (ZSTD_LEVEL), made once: a new context per 1 MiB chunk cost 10 % more."""
    c = getattr(_LOCAL, "zstd", None)
    if c is None:
        import zstandard

        c = _LOCAL.zstd = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    return c


def compress_chunk(kind: str, data: np.ndarray):
    """``data`` compressed (bytes), or ``data`` itself (uncompressed)."""
    if kind in ("", "none"):
        return data
    if kind == "zstd":
        return _zstd_compressor().compress(data)
    if kind == "lz4":
        import lz4.frame

        return lz4.frame.compress(data)
    if kind == "bz2":
        import bz2

        return bz2.compress(data, 9)
    raise ValueError(f"unsupported compression {kind!r}")


# ---- ROS 1 bag writer --------------------------------------------------------------------------------
def _bag1_header(fields: list[tuple[bytes, bytes]]) -> bytes:
    body = b"".join(struct.pack("<I", len(k) + 1 + len(v)) + k + b"=" + v for k, v in fields)
    return struct.pack("<I", len(body)) + body


def _bag1_record(fields: list[tuple[bytes, bytes]], data: bytes) -> bytes:
    return _bag1_header(fields) + struct.pack("<I", len(data)) + data


def _bag1_time(t_ns: int) -> bytes:
    return struct.pack("<II", t_ns // 1_000_000_000, t_ns % 1_000_000_000)


def bag1_times(t_ns: np.ndarray) -> np.ndarray:
    """(n, 8) bytes of ROS 1 times (uint32 seconds, uint32 nanoseconds, little-endian): :func:`_bag1_time` of
    each of ``t_ns``."""
    sec, nsec = np.divmod(np.asarray(t_ns, np.int64), 1_000_000_000)
    tt = np.empty((len(sec), 2), "<u4")
    tt[:, 0], tt[:, 1] = sec, nsec
    return tt.view(np.uint8)


def _bag1_conn(cid: int, f: dict[str, bytes]) -> bytes:
    data = b"".join(struct.pack("<I", len(k) + 1 + len(v)) + k.encode() + b"=" + v for k, v in f.items())
    return _bag1_record([(b"op", b"\x07"), (b"conn", struct.pack("<I", cid)), (b"topic", f.get("topic", b""))], data)


def write_bag1(fh, fields: list[dict[str, bytes]], cids: list[int], msgs, log_ns: np.ndarray,
                comp: str, chunk_bytes: int = 1 << 20) -> None:
    """A ROS 1 (V2.0) bag: chunks of MSG_DATA records (op, conn, time, as rosbag writes them), index data
    after each chunk, connection and chunk info records at the end, the bag header pointing to them."""
    comp = comp if comp in ("none", "bz2", "lz4") else "none"
    n = len(log_ns)
    # MSG_DATA prefix: header length 38 = op (4+4) + conn (4+9) + time (4+13), then the data length
    pre = np.zeros((n, 46), np.uint8)
    pre[:, 0:4] = np.frombuffer(struct.pack("<I", 38), np.uint8)
    pre[:, 4:12] = np.frombuffer(struct.pack("<I", 4) + b"op=\x02", np.uint8)
    pre[:, 12:21] = np.frombuffer(struct.pack("<I", 9) + b"conn=", np.uint8)
    pre[:, 21:25] = np.asarray(cids, np.uint32)[msgs.conn].astype("<u4").view(np.uint8).reshape(n, 4) if n else 0
    pre[:, 25:34] = np.frombuffer(struct.pack("<I", 13) + b"time=", np.uint8)
    pre[:, 34:42] = bag1_times(log_ns)
    pre[:, 42:46] = msgs.lens.astype("<u4").view(np.uint8).reshape(n, 4)
    size = 46 + msgs.lens
    pos = 0

    def put(b) -> None:  # (the position counted here: BufferedWriter.tell() flushes, 40 ms on a 1 h bag)
        nonlocal pos
        fh.write(b)
        pos += len(b)

    put(rosbag1.MAGIC)
    head_at = pos
    put(bytes(4096))  # the bag header, written last
    conn_recs = {c: _bag1_conn(c, f) for c, f in zip(cids, fields)}
    infos = []
    slices = _chunks(size, chunk_bytes)
    lead_all = b"".join(conn_recs.values())

    def work(sl: slice) -> tuple[int, bytes, list]:  # in the writer's threads: lay out and compress one chunk
        body = _records(pre[sl], msgs, sl)
        if sl.start == 0 and lead_all:
            body = np.concatenate([np.frombuffer(lead_all, np.uint8), body])
        return len(body), compress_chunk(comp, body), _by_key(msgs.conn[sl])

    for sl, (body_len, data, by_conn) in zip(slices, threads.ordered(work, slices)):
        lead = lead_all if sl.start == 0 else b""  # (the connection records open the first chunk)
        at = pos
        put(_bag1_header([(b"op", b"\x05"), (b"compression", comp.encode()),
                          (b"size", struct.pack("<I", body_len))]) + struct.pack("<I", len(data)))
        put(data)
        t = log_ns[sl]
        off = len(lead) + np.cumsum(size[sl]) - size[sl]
        counts = []
        for kk, m in by_conn:
            ent = np.empty((len(m), 3), "<u4")
            ent[:, 0], ent[:, 1], ent[:, 2] = t[m] // 1_000_000_000, t[m] % 1_000_000_000, off[m]
            put(_bag1_record([(b"op", b"\x04"), (b"ver", struct.pack("<I", 1)),
                              (b"conn", struct.pack("<I", cids[kk])), (b"count", struct.pack("<I", len(ent)))],
                             ent.tobytes()))
            counts.append((cids[kk], len(ent)))
        infos.append((at, int(t.min()), int(t.max()), counts))
    index_pos = pos
    for rec in conn_recs.values():
        put(rec)
    for at, t0, t1, counts in infos:
        put(_bag1_record([(b"op", b"\x06"), (b"ver", struct.pack("<I", 1)), (b"chunk_pos", struct.pack("<Q", at)),
                          (b"start_time", _bag1_time(t0)), (b"end_time", _bag1_time(t1)),
                          (b"count", struct.pack("<I", len(counts)))],
                         b"".join(struct.pack("<II", c, m) for c, m in counts)))
    hdr = _bag1_header([(b"op", b"\x03"), (b"index_pos", struct.pack("<Q", index_pos)),
                        (b"conn_count", struct.pack("<I", len(cids))), (b"chunk_count", struct.pack("<I", len(infos)))])
    pad = 4096 - len(hdr) - 4
    fh.seek(head_at)
    fh.write(hdr + struct.pack("<I", pad) + b" " * pad)


# ---- MCAP writer ----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ChunkLayout:
    """Where the input's chunks lie in ``msgs.buf``: chunk i is ``buf[base[i]:base[i] + size[i]]`` and holds
    messages ``count[:i].sum()`` to ``count[:i + 1].sum()`` (in order), with whatever else it held
    (schema and channel records). The writer then patches the time fields of those records in place and
    compresses the chunks as they are, instead of laying every record out again."""

    base: np.ndarray
    size: np.ndarray
    count: np.ndarray


def _mrec(op: int, body: bytes) -> bytes:
    return struct.pack("<BQ", op, len(body)) + body


def _mstr(text: str) -> bytes:
    b = text.encode()
    return struct.pack("<I", len(b)) + b


def _mmap(d: dict[str, str]) -> bytes:
    body = b"".join(_mstr(k) + _mstr(v) for k, v in d.items())
    return struct.pack("<I", len(body)) + body


def write_mcap(fh, sc, cids: list[int], msgs, log_ns: np.ndarray, pub_ns: np.ndarray | None,
                seq: np.ndarray | None, comp: str, chunk_bytes: int, layout: ChunkLayout | None = None,
                delta: np.ndarray | None = None, stamps=None, inflate=None) -> None:
    """An MCAP file: header, schemas and channels, chunks of message records (each followed by its message
    indexes), metadata and attachments, data end; summary (schemas, channels, statistics, chunk, metadata
    and attachment indexes), summary offsets, footer. Ids as in the input.

    With ``layout`` (the messages are the input's records, in its chunks, in ``msgs.buf``) the chunks are
    the input's: each chunk's records get their log times ``log_ns`` and their publish times (where set)
    moved by ``-delta`` where they lie in ``msgs.buf`` (:func:`patch_mcap_times`, in the writer's threads,
    chunk by chunk), and each chunk is compressed as it lies (``pub_ns`` and ``seq`` are not read). Without
    it, the records are laid out anew in chunks of ``chunk_bytes`` with publish times ``pub_ns`` and sequence
    numbers ``seq``. ``stamps`` (with ``layout``): Header stamps to write into the payloads as well, chunk by
    chunk (``write(buf, starts, slice, base)``: ``restamp_ros._StampPatch``). ``inflate`` (with ``layout``):
    ``inflate(i)`` gives the input's chunk ``i`` (in a buffer of the calling thread's own, valid until its
    next call), whose place in ``msgs.buf`` ``layout`` counts but ``msgs.buf`` does not hold (a streamed
    scan)."""
    if stamps is not None and layout is None:
        raise ValueError("write_mcap: Header stamps are written chunk by chunk in the input's chunks (layout)")
    comp = comp if comp in ("", "zstd", "lz4") else "zstd"
    n = len(log_ns)
    size = 31 + msgs.lens
    key = np.asarray(cids, np.uint16)[msgs.conn] if n else np.zeros(0, np.uint16)  # channel id per message
    if layout is not None:  # record: opcode, length, channel, sequence (4), log time (8), publish time (8), data
        if delta is None:
            raise ValueError("write_mcap: the input's chunks (layout) are patched with each message's delta")
        ends = np.cumsum(layout.count)
        slices = [slice(int(e - c), int(e)) for e, c in zip(ends.tolist(), layout.count.tolist())]
        spans = list(zip(layout.base.tolist(), layout.size.tolist()))
        rec_off = msgs.starts - 31 - np.repeat(layout.base, layout.count)  # record offsets in their chunk
    else:
        dt = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")])
        pre = np.empty(n, dt)
        pre["op"] = 5
        pre["len"] = 22 + msgs.lens
        pre["ch"] = np.asarray(cids, np.int64)[msgs.conn] if n else 0
        pre["seq"], pre["log"], pre["pub"] = seq, log_ns, pub_ns
        pre = pre.view(np.uint8).reshape(n, 31)
        slices = _chunks(size, chunk_bytes)
        spans = [None] * len(slices)
        rec_off = None
    out = [mcap_ros.MAGIC, _mrec(1, _mstr(sc.profile) + _mstr(sc.library))]
    pos = sum(map(len, out))

    def put(b) -> int:  # bytes, or a uint8 array / memoryview (a chunk's data: written without a copy)
        nonlocal pos
        at = pos
        pos += len(b)
        if len(b) >= 1 << 16:
            if out:
                fh.write(b"".join(out))
                out.clear()
            fh.write(b)
            return at
        out.append(b)
        if len(out) > 64:
            fh.write(b"".join(out))
            out.clear()
        return at

    schema_recs = [_mrec(3, struct.pack("<H", sid) + _mstr(nm) + _mstr(enc) + struct.pack("<I", len(d)) + d)
                   for sid, (nm, enc, d) in sorted(sc.schemas.items())]
    chan_recs = [_mrec(4, struct.pack("<HH", c, sc.channels[c][2]) + _mstr(sc.channels[c][0])
                       + _mstr(sc.channels[c][1]) + _mmap(sc.channels[c][3])) for c in cids]
    for r in schema_recs + chan_recs:
        put(r)
    chunk_index = []

    def work(job: tuple[slice, tuple[int, int] | None, int]) -> tuple[int, int, bytes, list]:  # in the writer's threads
        sl, span, i = job
        if span is None:
            body = _records(pre[sl], msgs, sl)
        else:  # (the chunk's bytes; its messages' offsets in them: their offsets in msgs.buf less its place)
            body = inflate(i) if inflate is not None else msgs.buf[span[0]:span[0] + span[1]]
            patch_mcap_times(body, msgs.starts[sl] - span[0], log_ns[sl], delta[sl])
            if stamps is not None:
                stamps.write(body, msgs.starts, sl, span[0])
        data = compress_chunk(comp, body)
        if inflate is not None and data is body:  # (an uncompressed output: not the thread's reused buffer)
            data = body.tobytes()
        return len(body), zlib.crc32(body), data, _by_key(key[sl])

    jobs = list(zip(slices, spans, range(len(slices))))
    for sl, (body_len, crc, data, by_channel) in zip(slices, threads.ordered(work, jobs)):
        t = log_ns[sl]
        t0, t1 = (int(t.min()), int(t.max())) if len(t) else (0, 0)
        head = struct.pack("<QQQI", t0, t1, body_len, crc) + _mstr(comp) + struct.pack("<Q", len(data))
        at = put(struct.pack("<BQ", 6, len(head) + len(data)) + head)
        put(data)
        rec_len = 9 + len(head) + len(data)
        off = np.cumsum(size[sl]) - size[sl] if rec_off is None else rec_off[sl]
        idx_offsets = {}
        idx_start = pos
        for c, m in by_channel:
            ent = np.empty((len(m), 2), "<u8")
            ent[:, 0], ent[:, 1] = t[m], off[m]
            idx_offsets[c] = put(_mrec(7, struct.pack("<HI", c, ent.nbytes) + ent.tobytes()))
        chunk_index.append((t0, t1, at, rec_len, idx_offsets, pos - idx_start, comp, len(data), body_len))
    att_index, meta_index = [], []
    for kind, args in sc.extras:
        if kind == "attachment":
            create_t, log_t, name, media, data = args
            body = struct.pack("<QQ", log_t, create_t) + _mstr(name) + _mstr(media) + struct.pack("<Q", len(data)) + data
            rec = _mrec(9, body + struct.pack("<I", zlib.crc32(body)))
            att_index.append((put(rec), len(rec), log_t, create_t, len(data), name, media))
        else:
            name, meta = args
            rec = _mrec(12, _mstr(name) + _mmap(meta))
            meta_index.append((put(rec), len(rec), name))
    put(_mrec(15, struct.pack("<I", 0)))
    summary_start = pos
    groups = []

    def group(op: int, recs: list[bytes]) -> None:
        if recs:
            at = pos
            for r in recs:
                put(r)
            groups.append((op, at, pos - at))

    group(3, schema_recs)
    group(4, chan_recs)
    counts = np.bincount(msgs.conn, minlength=len(cids)) if n else np.zeros(len(cids), np.int64)
    cmc = b"".join(struct.pack("<HQ", c, int(k)) for c, k in zip(cids, counts.tolist()) if k)
    group(11, [_mrec(11, struct.pack("<QHIIIIQQ", n, len(sc.schemas), len(cids), len(att_index), len(meta_index),
                                     len(chunk_index), int(log_ns.min()) if n else 0, int(log_ns.max()) if n else 0)
                     + struct.pack("<I", len(cmc)) + cmc)])
    group(8, [_mrec(8, struct.pack("<QQQQ", t0, t1, at, ln)
                    + struct.pack("<I", 10 * len(io)) + b"".join(struct.pack("<HQ", c, o) for c, o in io.items())
                    + struct.pack("<Q", il) + _mstr(cp) + struct.pack("<QQ", cs, us))
              for t0, t1, at, ln, io, il, cp, cs, us in chunk_index])
    group(10, [_mrec(10, struct.pack("<QQQQQ", at, ln, lt, ct, ds) + _mstr(nm) + _mstr(md))
               for at, ln, lt, ct, ds, nm, md in att_index])
    group(13, [_mrec(13, struct.pack("<QQ", at, ln) + _mstr(nm)) for at, ln, nm in meta_index])
    offsets_start = pos
    for op, at, ln in list(groups):
        put(_mrec(14, struct.pack("<BQQ", op, at, ln)))
    put(_mrec(2, struct.pack("<QQI", summary_start, offsets_start, 0)))
    out.append(mcap_ros.MAGIC)
    fh.write(b"".join(out))
