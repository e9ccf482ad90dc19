"""Bare MCAP files holding ROS messages (ROS 2 CDR or ROS 1 encoding).

Reading: a linear scan of the MCAP records (own code, no per-message objects), chunks decompressed
(zstd/lz4) and CRC-checked, raw message bytes + log times collected per channel; message definitions
from the Schema records (``ros2msg``, ``ros2idl``, ``ros1msg``) registered in a rosbags typestore.
The content is decoded by :mod:`parsers.ros_common` (vectorised, library fallback). A damaged file
(truncated, bad chunk CRC, undecompressible chunk, broken record) gives the readable part plus a
warning in ``meta.warnings``; the ``mcap`` package's reader and ``mcap_ros2``/``mcap_ros1`` decoders are
the reference the tests compare against.

Writing (``write(path, log, encoding="cdr"|"ros1", log_delay_ns=0, compression="zstd"|"lz4"|"none")``): /imu sensor_msgs/Imu,
/velocity geometry_msgs/TwistStamped (ENU world, frame "map"), /fix sensor_msgs/NavSatFix, and
/attitude geometry_msgs/QuaternionStamped when the attitude is not at the IMU stamps; NED/FRD
converted to ENU/FLU; header stamps = t0_ns + t_s (exact ns); log time = stamp + log_delay_ns.
"""
from __future__ import annotations

import os
import struct
import threading
import zlib
from collections.abc import Callable, Iterator

import numpy as np

from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers import ros_common as rc
from parsers.atomic import atomic_path
from parsers.base import DAMAGED_HEAD_SEARCH_BYTES, DamagedRecords, Inventory, Selector, check_readable

NAME = "mcap"
EXTENSIONS = (".mcap",)
MAGIC = b"\x89MCAP0\r\n"

_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_DATA_END = 15
_OP_CHUNK_INDEX = 8
_OP_MESSAGE_INDEX = 7
_REC = struct.Struct("<BQ")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_ENCODINGS = {"cdr": "cdr", "ros1": "ros1", "json": "json"}
#: the message encodings read: ROS 2 CDR, ROS 1, and JSON with the ROS message's fields (ros_common.json_decode)
READ_ENCODINGS = ("cdr", "ros1", "json")


def sniff(head: bytes, path: str) -> bool:
    return head.startswith(MAGIC)


def sniff_damaged(head: bytes, path: str) -> bool:
    """An MCAP file whose first bytes are damaged: its footer and closing magic are there (the walk reads on
    from byte 8, at the summary's chunks where it must)."""
    return _tail_is_mcap(path)


def _tail_is_mcap(path: str) -> bool:
    """The file at ``path`` ends in an MCAP footer and magic (:func:`footer_start` of its last bytes)."""
    size = 2 * len(MAGIC) + 29
    try:
        with open(path, "rb") as fh:
            fh.seek(0, 2)
            if fh.tell() < size:
                return False
            fh.seek(-size, 2)
            tail = fh.read()
    except OSError:
        return False
    return footer_start(tail) is not None


def footer_start(buf) -> int | None:
    """The summary start the footer of ``buf`` (a whole MCAP file) gives, or None when the file does not end
    in a footer record and the closing magic."""
    n = len(buf)
    at = n - len(MAGIC) - 29  # footer: opcode, length 20, summary start, summary offset start, CRC
    if at < len(MAGIC) or bytes(buf[n - len(MAGIC):]) != MAGIC:
        return None
    op, ln = _REC.unpack_from(buf, at)
    if op != _OP_FOOTER or ln != 20:
        return None
    return int(_U64.unpack_from(buf, at + 9)[0])


def records_start(buf, search: int = DAMAGED_HEAD_SEARCH_BYTES + len(MAGIC) + 1) -> int | None:
    """Where the records of a file whose magic is damaged begin: the first Header record before byte ``search``
    (bytes put before the file: up to DAMAGED_HEAD_SEARCH_BYTES, then its magic) whose profile and library
    strings fit it and after which two more top-level records chain (valid opcodes, inside the file). Normally
    byte 8; elsewhere when bytes were put before it or lost from the start (a transfer's garbage before the
    file, a cut head). None when no such record is found."""
    n = len(buf)
    head = np.frombuffer(bytes(buf[:min(n, search + 9)]), np.uint8)
    for h in np.flatnonzero(head[:-9] == _OP_HEADER):
        h = int(h)
        off, ok = h, True
        for k in range(3):
            if off + 9 > n:
                ok = False
                break
            op, ln = _REC.unpack_from(buf, off)
            if op == 0 or op > 0x0F or off + 9 + ln > n or (k == 0 and not _header_fits(buf, off + 9, ln)):
                ok = False
                break
            off += 9 + ln
        if ok:
            return h
    return None


def records_shift(buf) -> int:
    """How far the records of a file whose magic is damaged are from where its footer and summary count them
    (bytes put before them: positive; lost from the start: negative; 0 when they are in place or no shift is
    found): from its Header record (:func:`records_start`), or where that is damaged too, from the summary
    section's chain to the footer (:func:`summary_shift`). The parser and the export judge a file alike."""
    h = records_start(buf)
    if h is not None:
        return h - len(MAGIC)
    return summary_shift(buf) or 0


#: the opcodes of the records a summary section holds (schema, channel, chunk index, attachment and metadata
#: indexes, statistics, summary offsets)
_SUMMARY_OPS = np.zeros(256, bool)
_SUMMARY_OPS[[_OP_SCHEMA, _OP_CHANNEL, _OP_CHUNK_INDEX, 0x0A, 0x0B, 0x0D, 0x0E]] = True


def _footer_at(buf) -> int:
    return len(buf) - len(MAGIC) - 29


def _reaches_footer(buf, at: int, foot: int) -> bool:
    """Summary records chain from ``at`` exactly up to the footer at ``foot``."""
    off = at
    while off + 9 <= foot:
        op, ln = _REC.unpack_from(buf, off)
        if not _SUMMARY_OPS[op] or off + 9 + ln > foot:
            return False
        off += 9 + ln
    return off == foot


def _first_chain(buf, lo: int, hi: int, foot: int) -> int | None:
    """The first offset in ``buf[lo:hi]`` from which summary records chain exactly up to the footer."""
    window = np.frombuffer(bytes(buf[lo:hi]), np.uint8)
    for i in np.flatnonzero(_SUMMARY_OPS[window]):
        if _reaches_footer(buf, lo + int(i), foot):
            return lo + int(i)
    return None


def summary_shift(buf, search: int = DAMAGED_HEAD_SEARCH_BYTES) -> int | None:
    """The shift of a file's records against the offsets its footer gives (bytes put before them: positive;
    lost from the start: negative), where the start is damaged past its Header record: the shift, within
    ``search``, at which the summary section's records chain from the footer's summary start exactly up to
    the footer. None without a footer, or when no such shift (other than 0) is found."""
    start = footer_start(buf)
    if start is None:
        return None
    foot = _footer_at(buf)
    lo, hi = max(len(MAGIC), start - search), min(foot, start + search)
    if hi <= lo:
        return None
    if _reaches_footer(buf, start, foot):
        return None  # (the summary where the footer says: no shift)
    # every record boundary inside the summary chains to the footer: its start is the earliest that does
    at = _first_chain(buf, lo, hi, foot)
    return None if at is None else at - start


def _opens_chunk(buf, at: int) -> bool:
    if at < len(MAGIC) or at + 9 > len(buf):
        return False
    op, ln = _REC.unpack_from(buf, at)
    return op == _OP_CHUNK and at + 9 + ln <= len(buf)


def _offsets_in_place(buf, start: int, at: int) -> bool:
    """The summary section's records chain to the footer from ``at``, not from the footer's summary start
    ``start``: True when the file's other offsets show that nothing moved (the bytes from ``start`` were
    overwritten: the records there are damaged in place), False when they are off by as much (bytes put in
    or lost before the summary, :func:`inner_shift`) or nothing tells. Judged by the footer's summary offset
    start (a summary offset record there and not ``at - start`` bytes on, or the other way), else by the
    chunk index records after ``at``: the last chunk whose record opens at exactly one of its offset and that
    offset moved."""
    foot = _footer_at(buf)
    d = at - start
    (so,) = _U64.unpack_from(buf, foot + 9 + 8)

    def offsets_record(k: int) -> bool:
        return at <= k < foot and buf[k] == 0x0E and _reaches_footer(buf, k, foot)

    if so and offsets_record(so) != offsets_record(so + d):
        return offsets_record(so)
    off, chunks = at, []
    while off + 9 <= foot:
        op, ln = _REC.unpack_from(buf, off)
        if op == _OP_CHUNK_INDEX and ln >= 32:
            chunks.append(int(_U64.unpack_from(buf, off + 9 + 16)[0]))
        off += 9 + ln
    for c in reversed(chunks):
        here, moved = _opens_chunk(buf, c), _opens_chunk(buf, c + d)
        if here != moved:
            return here
    return False


def inner_shift(buf) -> int:
    """Bytes put in (positive) or lost (negative) inside a file's data section: the summary section moved by as
    much from where its footer says (:func:`summary_shift`), the chunks after the damage with it. 0 when the
    summary is where the footer says, the file has no footer or no such shift is found, or when the file's
    offsets show that its summary is in place with its first bytes damaged (overwritten: a summary read from
    a later record boundary is not moved, :func:`summary_damaged_head`). The parser and the export judge a
    file alike."""
    start = footer_start(buf)
    if start is None or _summary_walk(buf, start):
        return 0
    d = summary_shift(buf)
    if not d or (d > 0 and _offsets_in_place(buf, start, start + d)):
        return 0
    return d


def summary_damaged_head(buf, search: int = DAMAGED_HEAD_SEARCH_BYTES) -> tuple[int, int] | None:
    """Where a summary section damaged in place (bytes overwritten, not put in or lost: :func:`inner_shift` is
    0) stops reading and where it reads again: (the end of the records that read from the footer's summary
    start, the first record boundary within ``search`` bytes after them from which the records chain exactly
    up to the footer, with the file's offsets in place: :func:`_offsets_in_place`). None when the summary
    reads up to the footer, is moved, the file has none, or no such boundary is found."""
    start = footer_start(buf)
    foot = _footer_at(buf)
    if start is None or not len(MAGIC) <= start < foot:
        return None
    recs = _summary_walk(buf, start)
    stop = recs[-1][2] if recs else start
    if stop == foot or (not recs and inner_shift(buf)):
        return None
    at = _first_chain(buf, stop, min(foot, stop + search), foot)
    if at is None or at == stop or not _offsets_in_place(buf, start, at):
        return None
    return stop, at


def _header_fits(buf, at: int, ln: int) -> bool:
    """The Header record's body ``buf[at:at + ln]``: its profile and library strings, exactly."""
    if ln < 8 or ln > 1 << 16:
        return False
    (a,) = _U32.unpack_from(buf, at)
    if 4 + a + 4 > ln:
        return False
    (b,) = _U32.unpack_from(buf, at + 4 + a)
    return 8 + a + b == ln


def derailed(buf, op: int, nxt: int, starts: list[int], last: int) -> tuple[str, int | None] | None:
    """The top-level walk's rule for a record it cannot follow, shared by the parser and the export: None
    when the record (opcode ``op``, ending at ``nxt``) reads, or is cut by the end of a file without a footer
    (truncation); else (what is wrong, the next chunk the summary lists after ``last``, the last record
    that started well (its length may be what was damaged), or None)."""
    bad_op = op == 0 or op > 0x0F
    if not (bad_op or (nxt > len(buf) and starts)):  # (a file with a footer is damaged there, not truncated)
        return None
    what = f"invalid record opcode {op}" if bad_op else f"a record (opcode {op}) running past the file"
    return what, resume_at(buf, starts, last)


class _Damage(Exception):
    def __init__(self, text: str = "", at: int | None = None):
        super().__init__(text)
        self.at = at  # where in its container the damage starts (records walk), if known


class _BadCrc(_Damage):
    """A chunk whose records do not give its CRC: a damaged byte somewhere in them. An uncompressed chunk's
    records (``content``) are still walked, and their messages kept as unverified, the way the formats without
    a checksum are read (the value limits and the spike check drop the impossible ones). A compressed chunk
    that decompresses to other bytes (``compressed``) is worse: from the damaged byte on, zstd's copies from
    wrong offsets repeat whole records with old times (read, they gave a 25 s latency). Its records are kept
    only as far as they agree with the chunk's message index (:func:`index_checked_prefix`), else dropped."""

    def __init__(self, text: str, content, compressed: bool = False):
        super().__init__(text)
        self.content = content
        self.compressed = compressed


class _Undecodable(_Damage):
    """A chunk whose compressed records stop decompressing part way (a flipped or zeroed byte): what
    decompresses before the damage can still be walked (:func:`ros_common.inflate_prefix`)."""


def _string(buf, off: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, off)
    off += 4
    if off + n > len(buf):
        raise _Damage("string runs past its record")
    return bytes(buf[off:off + n]).decode("utf-8", "replace"), off + n


def _decompress(kind: str, data: bytes, size: int) -> bytes:
    if kind == "":
        return data
    if kind == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if kind == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise _Damage(f"unsupported chunk compression {kind!r}")


# ---- record walk: a compiled kernel finds the message records of a chunk ---------------------
_E_CUT, _E_PAST_MSG, _E_OPCODE, _E_PAST = 1, 2, 3, 4


def _walk(b, start, end):  # compiled with numba (_walk_kernel); plain Python otherwise
    """Records of b[start:end] (uint8): messages as (channel, log time, data start, data end) arrays,
    other records as (opcode, offset, next) arrays, and the first error (code, offset) or (0, end)."""
    nmax = (end - start) // 9 + 1
    cid = np.empty(nmax, np.int64)
    t = np.empty(nmax, np.int64)
    s = np.empty(nmax, np.int64)
    e = np.empty(nmax, np.int64)
    oop = np.empty(nmax, np.int64)
    ooff = np.empty(nmax, np.int64)
    onxt = np.empty(nmax, np.int64)
    m = 0
    k = 0
    off = start
    while off < end:
        if off + 9 > end:
            return m, cid, t, s, e, k, oop, ooff, onxt, _E_CUT, off
        op = b[off]
        ln = 0
        for j in range(8):
            ln |= np.int64(b[off + 1 + j]) << (8 * j)
        past = ln < 0 or ln > end - off - 9  # (a length beyond the int64 range reads negative)
        nxt = off + 9 + ln
        if op == 5 and off + 31 <= end:
            if past or ln < 22:
                return m, cid, t, s, e, k, oop, ooff, onxt, _E_PAST_MSG, off
            cid[m] = np.int64(b[off + 9]) | (np.int64(b[off + 10]) << 8)
            tt = np.int64(0)
            for j in range(8):
                tt |= np.int64(b[off + 15 + j]) << (8 * j)
            t[m] = tt
            s[m] = off + 31
            e[m] = nxt
            m += 1
            off = nxt
            continue
        if past:
            return m, cid, t, s, e, k, oop, ooff, onxt, _E_PAST, off
        if op == 0 or op > 15:
            return m, cid, t, s, e, k, oop, ooff, onxt, _E_OPCODE, off
        if op == 3 or op == 4:
            oop[k] = op
            ooff[k] = off
            onxt[k] = nxt
            k += 1
        off = nxt
    return m, cid, t, s, e, k, oop, ooff, onxt, 0, end


_REC = struct.Struct("<BQ")


def _walk_py(b, start, end):
    """``_walk`` for the reference code: the same records and errors, read with struct over bytes (the
    byte-by-byte numpy version costs ~17 us a record in plain Python)."""
    nmax = (end - start) // 9 + 1
    cid, t, s, e = (np.empty(nmax, np.int64) for _ in range(4))
    oop, ooff, onxt = (np.empty(nmax, np.int64) for _ in range(3))
    ms, me, oo, of, on = [], [], [], [], []  # (a message's channel id and log time gathered after the loop)
    off = start
    err, eoff = 0, end
    while off < end:
        if off + 9 > end:
            err, eoff = _E_CUT, off
            break
        op, ln = _REC.unpack_from(b, off)
        past = ln > end - off - 9
        nxt = off + 9 + ln
        if op == 5 and off + 31 <= end:
            if past or ln < 22:
                err, eoff = _E_PAST_MSG, off
                break
            ms.append(off)
            me.append(nxt)
            off = nxt
            continue
        if past:
            err, eoff = _E_PAST, off
            break
        if op == 0 or op > 15:
            err, eoff = _E_OPCODE, off
            break
        if op == 3 or op == 4:
            oo.append(op)
            of.append(off)
            on.append(nxt)
        off = nxt
    m, k = len(ms), len(oo)
    for arr, vals in ((s, ms), (e, me), (oop, oo), (ooff, of), (onxt, on)):
        arr[:len(vals)] = vals
    if m:  # channel id (u16 at +9) and log time (i64 at +15) of every message, then its data's start
        from parsers.restamp import get_bytes

        raw = np.frombuffer(b, np.uint8)
        cid[:m] = get_bytes(raw, s[:m] + 9, 2).view("<u2")[:, 0]
        t[:m] = get_bytes(raw, s[:m] + 15, 8).view("<i8")[:, 0]
        s[:m] += 31
    return m, cid, t, s, e, k, oop, ooff, onxt, err, eoff


_WALK = []


def _walk_kernel():
    """``_walk`` compiled with numba on first use (cached on disk) when this process runs compiled kernels
    (logtools.jit); the plain Python function, over a memoryview (fast byte indexing), otherwise."""
    if not _WALK:
        from logtools import jit

        if jit.compiled():
            _WALK.append(jit.njit(_walk))
        else:
            _WALK.append(lambda arr, start, end: _walk_py(arr.tobytes() if isinstance(arr, np.ndarray) else arr,
                                                          start, end))
    return _WALK[0]


class _Scan:
    """State of one MCAP scan: schemas, channels, per-channel raw messages (``stream``: each kept channel's
    messages decoded as they come by a ``ros_common.StreamDecoder`` instead of kept as bytes)."""

    def __init__(self, keep: Callable[[str, str], bool], stream: bool = False, expect: Callable[[int], int] | None = None):
        self.keep = keep
        self.stream = stream
        self.expect = expect or (lambda count: 0)
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, tuple[str, int, str]] = {}
        self.times: dict[int, list[np.ndarray]] = {}
        self.counts: dict[int, int] = {}
        self.data: dict[int, list[bytes] | None] = {}
        self.kept: dict[int, bool] = {}
        self.decoders: dict[int, rc.StreamDecoder | None] = {}
        self.warnings: list[str] = []
        #: schema and channel ids defined by the summary section (read first): a definition in the data
        #: section (inside a CRC-checked chunk) replaces one of these that differs, while none of its
        #: messages was read (a damaged summary gave a channel the encoding 'cd\ufffd') ...
        self.provisional: set[tuple[str, int]] = set()
        #: ... but not from a chunk that failed its CRC (walked while this is set): there the damaged byte
        #: may be in the definition (a NavSatFix schema with a flipped byte made /fix an unknown topic, where
        #: the summary's, and the export, had it right)
        self.unverified = False

    def n_messages(self) -> int:
        return sum(self.counts.values())

    def schema(self, buf, off: int, end: int) -> None:
        (sid,) = _U16.unpack_from(buf, off)
        name, o = _string(buf, off + 2)
        enc, o = _string(buf, o)
        (n,) = _U32.unpack_from(buf, o)
        if o + 4 + n > end:
            raise _Damage("schema data runs past its record")
        new = (name, enc, bytes(buf[o + 4:o + 4 + n]))
        read = any(c_sid == sid and self.counts.get(c, 0) for c, (_t, c_sid, _e) in self.channels.items())
        if ("schema", sid) in self.provisional and not self.unverified and self.schemas.get(sid) != new and not read:
            self.provisional.discard(("schema", sid))
            self.schemas[sid] = new
            for c, (t, c_sid, e) in list(self.channels.items()):  # its channels set up again with it
                if c_sid == sid:
                    del self.channels[c]
                    self._define(c, t, sid, e)
            return
        if sid in self.schemas:
            return
        self.schemas[sid] = new
        # channels defined before their schema (its summary record damaged: they came from the summary with
        # no type, so their content was not kept) are judged again with it: the /imu of a file whose
        # summary's first record was overwritten had its 16128 messages counted, none read (analyze refused
        # the file while inspect listed the topic)
        for c, (t, c_sid, e) in list(self.channels.items()):
            if c_sid != sid or self.kept[c] or not self.keep(t, name):
                continue
            n = self.counts.get(c, 0)
            if n:  # (its messages so far were read without their content: left out, said so)
                self.warnings.append(f"damaged: {n} messages of {t} before its schema {name} (schema id {sid}) "
                                     "was read: their content was not kept; left out")
            del self.channels[c]
            self._define(c, t, sid, e)

    def channel(self, buf, off: int) -> None:
        cid, sid = struct.unpack_from("<HH", buf, off)
        topic, o = _string(buf, off + 4)
        enc, o = _string(buf, o)
        if cid in self.channels:
            if (("channel", cid) in self.provisional and not self.unverified
                    and self.channels[cid] != (topic, sid, enc) and not self.counts.get(cid, 0)):
                self.provisional.discard(("channel", cid))
                del self.channels[cid]
                self._define(cid, topic, sid, enc)
            return
        self._define(cid, topic, sid, enc)

    def _define(self, cid: int, topic: str, sid: int, enc: str) -> None:
        self.channels[cid] = (topic, sid, enc)
        self.times[cid] = []
        self.counts[cid] = 0
        msgtype = self.schemas.get(sid, ("", "", b""))[0]
        kept = self.keep(topic, msgtype)
        self.kept[cid] = kept
        self.data[cid] = [] if kept and not self.stream else None
        self.decoders[cid] = _decoder(topic, msgtype, enc, self.schemas.get(sid)) if kept and self.stream else None
        if kept and self.stream and self.decoders[cid] is None and _ENCODINGS.get(enc, enc) in READ_ENCODINGS:
            raise rc.NotStreamable(f"{topic}: kept, but not a type decoded while reading")

    def records(self, buf, start: int, end: int, where: str, *, cut_ok: bool = False) -> None:
        """Walk the records in ``buf[start:end]`` (a chunk's content or the top level): the compiled
        walk finds the message records, schema and channel records are read here in their order; a
        message whose channel is not defined before it, or a broken record, is damage. ``cut_ok``: a
        record cut by the end of ``buf`` (the partial content of a truncated file's last chunk) ends
        the walk quietly, the complete records before it kept. Nothing of the walked messages is kept
        unless the whole walk is sound (damage raises before any is added)."""
        arr = np.frombuffer(buf, np.uint8)
        m, cid, t, s, e, k, oop, ooff, onxt, err, eoff = _walk_kernel()(arr, start, end)
        defined_at: dict[int, int] = {}
        for op, off, nxt in zip(oop[:k].tolist(), ooff[:k].tolist(), onxt[:k].tolist()):
            if op == _OP_SCHEMA:
                self.schema(buf, off + 9, nxt)
            else:
                (c,) = _U16.unpack_from(buf, off + 9)
                new = c not in self.channels
                self.channel(buf, off + 9)
                if new:
                    defined_at[c] = off
        cid, t, s, e = cid[:m], t[:m], s[:m], e[:m]
        present = np.flatnonzero(np.bincount(cid)).tolist() if m else []  # channel ids are 16-bit
        groups = ([(present[0], None)] if len(present) == 1 else
                  [(c, np.flatnonzero(cid == c)) for c in present])
        first_bad = end
        for c, sel in groups:
            ss = s if sel is None else s[sel]
            if c not in self.times:
                first_bad = min(first_bad, int(ss[0]) - 31)
            elif c in defined_at and np.any(ss - 31 < defined_at[c]):
                first_bad = min(first_bad, int(ss[ss - 31 < defined_at[c]][0]) - 31)
        if err and cut_ok and err != _E_OPCODE:
            err = 0
        if err and eoff < first_bad:
            raise _Damage({
                _E_CUT: f"{where}: record header cut at byte {eoff}",
                _E_PAST_MSG: f"{where}: message record at byte {eoff} runs past its container",
                _E_OPCODE: f"{where}: invalid record opcode {int(arr[eoff])} at byte {eoff}",
                _E_PAST: f"{where}: record (opcode {int(arr[eoff])}) at byte {eoff} runs past its container",
            }[err], eoff)
        if first_bad < end:
            c = int(cid[s - 31 == first_bad][0])
            raise _Damage(f"{where}: message for unknown channel {c} at byte {first_bad}", first_bad)
        for c, sel in groups:
            tt, ss, ee = (t, s, e) if sel is None else (t[sel], s[sel], e[sel])
            self.times[c].append(tt.copy() if sel is None else tt)
            self.counts[c] += len(tt)
            d = self.data[c]
            if d is not None:
                d.extend([buf[a:b] for a, b in zip(ss.tolist(), ee.tolist())])
            dec = self.decoders.get(c)
            if dec is not None:
                dec.add(arr, ss, ee, self.expect(self.counts[c]))


def _decoder(topic: str, msgtype: str, enc: str, schema: tuple[str, str, bytes] | None) -> rc.StreamDecoder | None:
    """The streaming decoder of a kept channel (None for a type or encoding ros_common does not decode):
    layouts made with the channel's own schema, else the built-in definitions (``_rawlog`` checks them
    against the log's final ones)."""
    msgtype = rc.normalize_msgtype(msgtype) if msgtype else ""
    encoding = _ENCODINGS.get(enc, enc)
    if msgtype not in rc.SUPPORTED or encoding not in ("cdr", "ros1"):
        return None
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.EMPTY)
    name, senc, text = schema or ("", "", b"")
    if text and senc in ("ros2msg", "ros1msg", "ros2idl"):
        try:
            rc.register_msgdef(store, msgtype, text.decode("utf-8", "replace"), "idl" if senc == "ros2idl" else "msg")
        except Exception:  # noqa: BLE001 - _rawlog says so; the built-in definitions then
            pass
    try:
        register_builtin(store, {msgtype}, encoding)
    except Exception:  # noqa: BLE001 - no layout then: every message kept for the end
        pass
    return rc.StreamDecoder(topic, msgtype, encoding, store)


def resync_record(buf, start: int, end: int, channels, t_range: tuple[int, int] | None = None,
                  chain: int = 3) -> int | None:
    """The first offset >= ``start`` in ``buf[:end]`` (a chunk's records) where ``chain`` message records in a
    row (or fewer up to the end) look right: opcode 5, a length inside the chunk, a known channel, a log time
    inside ``t_range`` (the chunk's message start and end times). Where a walk broken by damage goes on;
    None if there is no such place (a byte 5 inside a payload rarely starts three such records)."""
    b = bytes(buf[:end]) if not isinstance(buf, bytes) else buf

    def message_at(k: int) -> int:  # the next offset after a plausible message record at k, or -1
        if k + 31 > end or b[k] != _OP_MESSAGE:
            return -1
        (ln,) = _U64.unpack_from(b, k + 1)
        nxt = k + 9 + ln
        if ln < 22 or nxt > end or _U16.unpack_from(b, k + 9)[0] not in channels:
            return -1
        if t_range is not None:
            (t,) = _U64.unpack_from(b, k + 15)
            if not t_range[0] <= t <= t_range[1]:
                return -1
        return nxt

    k = b.find(b"\x05", start, end)
    while 0 <= k:
        at, ok = k, True
        for _ in range(chain):
            at = message_at(at)
            if at < 0:
                ok = False
                break
            if at == end:
                break
        if ok:
            return k
        k = b.find(b"\x05", k + 1, end)
    return None


def _last_record_start(buf, pos: int, at: int) -> int:
    """The start of the last record that begins in ``buf[pos:at]`` and ends at ``at`` (the records chain from
    ``pos``), else ``at``."""
    last = at
    k = pos
    while k + 9 <= at:
        (ln,) = _U64.unpack_from(buf, k + 1)
        if k + 9 + ln > at:
            break
        last, k = k, k + 9 + ln
    return last if k == at else at


def walk_resyncing(records, buf, end: int, where: str, channels,
                   t_range: tuple[int, int] | None = None) -> tuple[int, int, int]:
    """``records(buf, a, b, where)`` over a chunk's records ``buf[:end]``, going on past damage: the
    complete records before a broken one are walked, then the walk resumes at the next record that looks
    right (:func:`resync_record`). Returns (damaged places, bytes skipped, first place); raises the first
    damage when nothing after it can be read and nothing before it was."""
    pos, places, skipped, first = 0, 0, 0, -1
    while True:
        try:
            records(buf, pos, end, where)
            return places, skipped, first
        except _Damage as exc:
            if exc.at is None or exc.at < pos:
                raise
            cut = _last_record_start(buf, pos, exc.at)  # (the record just before may hold damaged bytes too)
            if cut > pos:
                records(buf, pos, cut, where)  # the sound records before the damage
            nxt = resync_record(buf, exc.at + 1, end, channels, t_range)
            if nxt is None:
                if places == 0 and exc.at == 0:
                    raise
                return places + 1, skipped + end - exc.at, exc.at if first < 0 else first
            places += 1
            skipped += nxt - exc.at
            first = exc.at if first < 0 else first
            pos = nxt


def _partial_chunk(scan: _Scan, buf: bytes, off: int, end: int) -> int:
    """The complete messages of a chunk cut by the end of the file (a recording killed while writing
    its last chunk) or damaged part way: what of its compressed data is there, decompressed as far as it
    goes, walked up to the first cut record (what ``mcap recover`` does). Returns how many messages were
    added."""
    try:
        comp, o = _string(buf, off + 9 + 28)
        content = rc.inflate_prefix(comp, buf[o + 8:end])
    except Exception:  # a header cut too, or data that does not decompress at all: nothing to recover
        return 0
    before = scan.n_messages()
    scan.unverified = True  # (no CRC over it: the summary's definitions stand)
    try:
        scan.records(content, 0, len(content), f"partial chunk at byte {off}", cut_ok=True)
    except (_Damage, struct.error, UnicodeDecodeError):
        return 0
    finally:
        scan.unverified = False
    return scan.n_messages() - before


def read_raw(path: str, keep: Callable[[str, str], bool] = rc.keep_supported, fmt: str = NAME) -> rc.RawLog:
    """Scan an MCAP file into a :class:`ros_common.RawLog` (readable part + warnings if damaged)."""
    check_readable(path)
    return _rawlog(path, fmt, _scan_file(path, _Scan(keep)))


def read_streamed(path: str, keep: Callable[[str, str], bool] = rc.keep_supported, fmt: str = NAME) -> rc.RawLog:
    """:func:`read_raw` with every kept topic decoded while the file is read (``RawTopic.decoded``; only
    the first messages' bytes kept): the log in memory about once, in columns, instead of as per-message
    bytes. rc.NotStreamable where that cannot give exactly what read_raw + decode give."""
    check_readable(path)
    size = max(os.path.getsize(path), 1)
    scan = _Scan(keep, stream=True)
    done = [0]  # compressed bytes behind the scan: a topic's messages so far * size / done = its estimate
    scan.expect = lambda count: int(1.25 * count * size / max(done[0], 1)) + 1024
    return _rawlog(path, fmt, _scan_file(path, scan, done))


def _summary_walk(buf, start: int) -> list[tuple[int, int, int]]:
    """[(opcode, offset, next)] of the records from ``start`` up to the footer or the first that does not read."""
    at = _footer_at(buf)
    out = []
    off = int(start)
    while len(MAGIC) <= off < at and off + 9 <= at:
        op, ln = _REC.unpack_from(buf, off)
        nxt = off + 9 + ln
        if op == 0 or op > 0x0F or nxt > at:
            break
        out.append((op, off, nxt))
        off = nxt
    return out


def _summary_records(buf, shift: int = 0) -> tuple[int, list[tuple[int, int, int]]]:
    """(summary start, [(opcode, offset, next)] of the summary section's records), found through the footer
    (up to the first record that does not read), ``shift`` bytes from where it says (:func:`summary_shift`);
    (0, []) without a footer. A summary damaged in place (``shift`` 0, :func:`summary_damaged_head`): the
    records before the damage and those from where they chain to the footer again."""
    start = footer_start(buf)
    if start is None:
        return 0, []
    start += shift
    out = _summary_walk(buf, start)
    if not shift:
        head = summary_damaged_head(buf)
        if head is not None:
            out = [r for r in out if r[2] <= head[0]] + _summary_walk(buf, head[1])
    return start, out


def summary_definitions(buf, shift: int = 0) -> list[tuple[int, int, int]]:
    """(opcode, offset, next) of the schema and channel records in the summary section, found through the
    footer (``shift``: :func:`_summary_records`): every channel stays known when the chunk that defined it is
    damaged (a flipped byte in the first chunk left a file's later chunks with messages of undefined
    channels). [] without a footer."""
    out = [r for r in _summary_records(buf, shift)[1] if r[0] in (_OP_SCHEMA, _OP_CHANNEL)]
    return sorted(out, key=lambda r: r[0] != _OP_SCHEMA)  # schemas first: a channel is judged by its schema


def summary_chunk_starts(buf, shift: int = 0) -> list[int]:
    """The chunk offsets the summary's chunk index records give (ascending), found through the footer: where
    a damaged data section can be picked up again (a zeroed run of bytes otherwise ended the walk, and the
    file's later chunks were lost). With ``shift`` (bytes put in or lost inside the file, :func:`summary_shift`)
    each offset also moved by it: the chunks after the damage are there. [] without a footer or chunk
    indexes."""
    start, recs = _summary_records(buf, shift)
    out = []
    for op, off, nxt in recs:
        if op == _OP_CHUNK_INDEX and nxt - off - 9 >= 32:
            (c0,) = _U64.unpack_from(buf, off + 9 + 16)  # message start and end time, then the chunk's offset
            out += [int(c) for c in {c0, c0 + shift} if len(MAGIC) <= c < start]
    return sorted(set(out))


def resume_at(buf, starts: list[int], off: int) -> int | None:
    """The first chunk start of ``starts`` (:func:`summary_chunk_starts`) after ``off`` whose bytes still
    open a chunk record inside the file, or None."""
    import bisect

    end = len(buf)
    for c in starts[bisect.bisect_right(starts, off):]:
        if c + 9 <= end:
            op, ln = _REC.unpack_from(buf, c)
            if op == _OP_CHUNK and c + 9 + ln <= end:
                return c
    return None


def _chunk_header(buf, off: int, nxt: int) -> tuple[str, int, int, int, int]:
    """(compression, uncompressed size, CRC, start, length of the compressed records) of the chunk record at
    ``off`` (ending at ``nxt``); :class:`_Damage` when the records run past it."""
    _t0, _t1, usize, crc = struct.unpack_from("<QQQI", buf, off + 9)
    comp, o = _string(buf, off + 9 + 28)
    (clen,) = _U64.unpack_from(buf, o)
    if o + 8 + clen > nxt:
        raise _Damage(f"chunk at byte {off}: records run past the chunk")
    return comp, usize, crc, o + 8, clen


def inflate_chunk(buf, off: int, nxt: int) -> bytes:
    """The records of the chunk record at ``off`` (ending at ``nxt``): decompressed, size and CRC
    checked; :class:`_Damage` naming the chunk if not."""
    comp, usize, crc, o, clen = _chunk_header(buf, off, nxt)
    try:
        content = _decompress(comp, buf[o:o + clen], usize)
    except _Damage:
        raise
    except Exception as exc:
        raise _Undecodable(f"chunk at byte {off} cannot be decompressed ({type(exc).__name__})") from None
    if len(content) != usize:
        raise _Damage(f"chunk at byte {off}: size {len(content)} != {usize}")
    if crc and zlib.crc32(content) != crc:
        raise _BadCrc(f"chunk at byte {off}: CRC mismatch", content, compressed=comp != "")
    return content


def inflate_chunk_into(buf, off: int, nxt: int, out: np.ndarray, check_crc: bool = True) -> np.ndarray:
    """:func:`inflate_chunk` of a zstd chunk, decompressed straight into ``out`` (uint8, the chunk's
    uncompressed size; a slice of one buffer for the whole file, or a thread's buffer): no bytes object of
    its own. :class:`_Damage` as there; ``check_crc=False``: the CRC not computed (a chunk read again after a
    scan checked it)."""
    comp, usize, crc, o, clen = _chunk_header(buf, off, nxt)
    if comp != "zstd" or len(out) != usize:
        raise _Damage(f"chunk at byte {off}: not the zstd chunk of {len(out)} bytes planned")
    import zstandard

    try:
        reader = zstandard.ZstdDecompressor().stream_reader(buf[o:o + clen], read_size=max(clen, 1))
        view = memoryview(out)
        n = 0
        while n < usize:
            k = reader.readinto(view[n:])
            if not k:
                break
            n += k
        extra = reader.read(1)
    except Exception as exc:
        raise _Undecodable(f"chunk at byte {off} cannot be decompressed ({type(exc).__name__})") from None
    if n != usize or extra:
        raise _Damage(f"chunk at byte {off}: size {n + len(extra)}{'+' if extra else ''} != {usize}")
    if check_crc and crc and zlib.crc32(out) != crc:
        raise _BadCrc(f"chunk at byte {off}: CRC mismatch", out, compressed=True)
    return out


def message_index_damage(buf, off: int, nxt: int, chunk: tuple[int, int, int] | None) -> bool:
    """Whether the message index record at ``off`` (ending at ``nxt``) is damaged: its entries do not fill it
    exactly, or one of them lies outside the chunk before it (``chunk``: its (message start time, message end
    time, uncompressed size); None: not checked against one). The readers never need the message indexes (the
    messages are read from the chunks): a damaged one is only said, a byte changed there is otherwise silent."""
    ln = nxt - off - 9
    if ln < 6:
        return True
    (n,) = _U32.unpack_from(buf, off + 11)
    if n % 16 or 6 + n != ln:
        return True
    if chunk is None or not n:
        return False
    t0, t1, usize = chunk
    pairs = np.frombuffer(buf, "<u8", n // 8, off + 15).reshape(-1, 2)
    if int(pairs[:, 1].max()) >= usize:
        return True
    if t0 <= t1 and t1 > 0:  # (a chunk that states its messages' time span)
        return int(pairs[:, 0].min()) < t0 or int(pairs[:, 0].max()) > t1
    return False


#: damaged message index records (:func:`message_index_damage`), as ``base.DamagedRecords`` says them
MESSAGE_INDEX_DAMAGE = "message index record(s) do not match their chunks"
#: what the readers do about them, and about a damaged summary (:func:`summary_crc_damage`)
MESSAGE_INDEX_UNUSED = "not used, the messages are read from the chunks themselves"
SUMMARY_UNUSED = "the messages are read from the data section, not through the summary"


class IndexCheck:
    """The message index records one walk over an MCAP file meets, each checked against the chunk before it
    (:func:`message_index_damage`), tallied and said once at the walk's end (:meth:`said`)."""

    def __init__(self):
        self.chunk: tuple[int, int, int] | None = None  # the last chunk's (start, end time, uncompressed size)
        self.bad = DamagedRecords(MESSAGE_INDEX_DAMAGE)

    def chunk_at(self, buf, off: int) -> None:
        self.chunk = struct.unpack_from("<QQQ", buf, off + 9)

    def index_at(self, buf, off: int, nxt: int) -> None:
        if message_index_damage(buf, off, nxt, self.chunk):
            self.bad.add(off)

    def said(self, then: str) -> str | None:
        return self.bad.said(then)


def summary_crc_damage(buf) -> str | None:
    """What is wrong with a summary section whose CRC (the footer's, where the writer set one) does not match
    its bytes (the caller says what it does about it: SUMMARY_UNUSED for the readers), else None. The
    readers read the messages from the data section; the summary gives them only definitions and where
    chunks start, which the data section repeats."""
    start = footer_start(buf)
    foot = _footer_at(buf)
    if start is None or not len(MAGIC) <= start <= foot:
        return None
    (crc,) = _U32.unpack_from(buf, foot + 9 + 16)
    if not crc or zlib.crc32(buf[start:foot + 9 + 16]) == crc:
        return None
    return f"the summary section does not match its CRC (bytes changed between byte {start} and the footer)"


def _message_index(buf, nxt: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The message index records right after the chunk record that ends at ``nxt``: (record offsets in the
    chunk's records, channels, log times), sorted by offset; None where there is none or it does not read."""
    offs, chans, times = [], [], []
    end = len(buf)
    try:
        while nxt + 9 <= end:
            op, ln = _REC.unpack_from(buf, nxt)
            if op != _OP_MESSAGE_INDEX or nxt + 9 + ln > end or ln < 6:
                break
            (c,) = _U16.unpack_from(buf, nxt + 9)
            (n,) = _U32.unpack_from(buf, nxt + 11)
            if n % 16 or 6 + n > ln:
                return None
            pairs = np.frombuffer(buf, "<u8", n // 8, nxt + 15).reshape(-1, 2)
            times.append(pairs[:, 0].astype(np.int64))
            offs.append(pairs[:, 1].astype(np.int64))
            chans.append(np.full(len(pairs), c, np.int64))
            nxt += 9 + ln
    except (struct.error, ValueError):
        return None
    if not offs or not sum(map(len, offs)):
        return None
    o, c, t = np.concatenate(offs), np.concatenate(chans), np.concatenate(times)
    order = np.argsort(o, kind="stable")
    return o[order], c[order], t[order]


def index_checked_prefix(buf, nxt: int, content) -> tuple[int, int, int] | None:
    """How much of a compressed chunk's ``content`` that failed its CRC can be read: its records as far as
    each message record lies at an offset the chunk's message index (the records right after the chunk, at
    ``nxt``) lists, with the channel and log time listed there; the record just before the first one that
    does not is dropped too (the damage may begin in its bytes). Returns (bytes of ``content`` to walk,
    messages in them, messages the index lists), or None without a readable message index (then the chunk
    is dropped). A damaged byte that changed only message data, no record's framing, leaves every record
    in agreement: those are kept, unverified, as an uncompressed chunk's are."""
    index = _message_index(buf, nxt)
    if index is None:
        return None
    offs, chans, times = index
    arr = np.frombuffer(content, np.uint8)
    m, cid, t, s, _e, _k, _oop, _ooff, _onxt, err, eoff = _walk_kernel()(arr, 0, len(arr))
    rec = s[:m] - 31  # (a message record's header: opcode 1, length 8, channel 2, sequence 4, two times 16)
    pos = np.minimum(np.searchsorted(offs, rec), len(offs) - 1)
    ok = (offs[pos] == rec) & (chans[pos] == cid[:m]) & (times[pos] == t[:m])
    bad = int(np.argmin(ok)) if not ok.all() else m  # (the first message that disagrees; m: a broken record)
    if bad == m and not err:
        return len(arr), m, len(offs)
    keep = max(bad - 1, 0)  # (the message before the break dropped with it)
    return (int(rec[keep]) if keep < m else 0), keep, len(offs)


def crc_damage_content(exc: _BadCrc, buf, nxt: int):
    """(the part of a chunk that failed its CRC that is read, what was kept in words), the readers' and the
    native export's one rule; :class:`_Damage` when none of it is (a compressed chunk without a readable
    message index)."""
    if not exc.compressed:
        return exc.content, "its messages kept, unverified"
    cut = index_checked_prefix(buf, nxt, exc.content)
    if cut is None:
        raise _Damage(f"{exc} (compressed, and no message index to tell its sound records)")
    n_bytes, kept, listed = cut
    if n_bytes == len(exc.content):
        return exc.content, (f"its {kept} messages all where its message index lists them ({listed}): kept, "
                             "unverified (the damage is in message data)")
    return exc.content[:n_bytes], (f"its first {kept} of {listed} messages, up to where its records stop "
                                   "agreeing with its message index, kept, unverified; the rest dropped")


def chunk_records(buf, off: int, starts: list[int] | None = None) -> Iterator[tuple[int, int]]:
    """(offset, next) of the complete chunk records from ``off`` on, along the top-level records (up to
    the first invalid or cut record, then on from the next of the summary's chunk ``starts`` after it, as the
    scans do): what a scan will inflate, for :class:`parsers.threads.Prefetch`."""
    end = len(buf)
    while off + 9 <= end:
        op, ln = _REC.unpack_from(buf, off)
        nxt = off + 9 + ln
        if op == _OP_FOOTER:
            return
        if op == 0 or op > 0x0F or nxt > end:
            off = resume_at(buf, starts or [], off)
            if off is None:
                return
            continue
        if op == _OP_CHUNK:
            yield off, nxt
        off = nxt


def chunk_prefetch(buf, off: int, arena: tuple[np.ndarray, dict] | None = None, starts: list[int] | None = None):
    """The chunks of ``buf`` from ``off`` on, inflated ahead of the scan in worker threads (for a file
    read whole into memory; the parser's memory-mapped walk measured no gain from it). With ``arena``
    (one buffer and {(offset, next): (start, size)} in it, :func:`chunk_arena`) each chunk is
    decompressed into its place there (:func:`inflate_chunk_into`) and handed back as that view; with
    ``arena="own"`` each zstd chunk is decompressed into a new array of its own."""
    from parsers import threads

    if arena is None:
        return threads.Prefetch(lambda r: inflate_chunk(buf, r[0], r[1]), chunk_records(buf, off, starts))
    if arena == "own":  # (each zstd chunk into an array of its own: writable, as the compiled kernels want them)
        def own(r):
            comp, usize, _crc, _o, _clen = _chunk_header(buf, r[0], r[1])
            if comp != "zstd":
                return inflate_chunk(buf, r[0], r[1])
            return inflate_chunk_into(buf, r[0], r[1], np.empty(usize, np.uint8))

        return threads.Prefetch(own, chunk_records(buf, off, starts))
    out, where = arena

    def inflate(r):
        at = where.get(r)
        if at is None:
            return inflate_chunk(buf, r[0], r[1])
        return inflate_chunk_into(buf, r[0], r[1], out[at[0]:at[0] + at[1]])

    return threads.Prefetch(inflate, chunk_records(buf, off, starts))


#: the largest decompressed size the export's one buffer is made for, as a multiple of the file (plus 64 MiB):
#: zstd chunks of IMU and navigation messages decompress 3-5 fold; a damaged size field must not allocate
#: the machine's memory (beyond it the chunks are inflated one by one, their sizes checked as they come)
ARENA_MAX_RATIO = 64


def chunk_arena(buf, off: int, limit_bytes: int | None = None,
                starts: list[int] | None = None) -> tuple[np.ndarray, dict] | None:
    """One buffer for every zstd chunk of ``buf`` from ``off`` on and where each goes in it, when every
    chunk is zstd and their stated sizes add up to at most ``limit_bytes`` (default ARENA_MAX_RATIO times the
    file, plus 64 MiB); None otherwise (the chunks are inflated one by one)."""
    places = chunk_places(buf, off, limit_bytes, starts)
    return (np.empty(places[1], np.uint8), places[0]) if places is not None else None


def chunk_places(buf, off: int, limit_bytes: int | None = None,
                 starts: list[int] | None = None) -> tuple[dict, int] | None:
    """Where each zstd chunk of ``buf`` from ``off`` on would lie in one buffer for all of them
    ({(offset, next): (start, size)}) and that buffer's size, on :func:`chunk_arena`'s conditions; None where
    they do not hold (or there is no chunk)."""
    if limit_bytes is None:
        limit_bytes = ARENA_MAX_RATIO * len(buf) + (1 << 26)
    where, total = {}, 0
    for r in chunk_records(buf, off, starts):
        try:
            comp, usize, _crc, _o, _clen = _chunk_header(buf, r[0], r[1])
        except (_Damage, struct.error, UnicodeDecodeError):
            return None
        if comp != "zstd":
            return None
        where[r] = (total, usize)
        total += usize
        if total > limit_bytes:
            return None
    return (where, total) if where else None


def chunk_inflater(buf, records: list[tuple[int, int]]) -> Callable[[int], np.ndarray]:
    """``inflate(i)``: the zstd chunk record ``records[i]`` of ``buf`` decompressed into a buffer of the
    calling thread's own, reused for its next chunk (so valid until the thread's next call), CRC not checked:
    for a second pass over chunks a scan read and checked. A few MiB per thread instead of one buffer for
    the whole file, which the kernel had to zero page by page (0.2-0.3 s of system time for a 1 h
    log's 316 MB) and which stayed in no cache."""
    local = threading.local()

    def inflate(i: int) -> np.ndarray:
        off, nxt = records[i]
        _comp, usize, _crc, _o, _clen = _chunk_header(buf, off, nxt)
        scratch = getattr(local, "buf", None)
        if scratch is None or len(scratch) < usize:
            scratch = local.buf = np.empty(max(usize, 1 << 20), np.uint8)
        return inflate_chunk_into(buf, off, nxt, scratch[:usize], check_crc=False)

    return inflate


def _scan_file(path: str, scan: _Scan, done: list[int] | None = None) -> _Scan:
    """The top-level record walk of an MCAP file (memory-mapped, the pages behind the walk let go)."""
    from parsers.filemap import FileMap

    with FileMap(path) as fm:
        buf = fm.buf
        off, end = len(MAGIC), len(buf)
        if buf[:len(MAGIC)] != MAGIC:
            if footer_start(buf) is None:
                raise InputError("not an MCAP file (bad magic)", path)
            shift = records_shift(buf)
            h = len(MAGIC) + shift
            if not shift:
                scan.warnings.append("damaged: the file's first 8 bytes are not MCAP's magic (its footer is); "
                                     "read on from byte 8")
            else:
                # bytes put before the records (or lost from the start): the offsets the summary gives count
                # from a start that is not byte 0 here. A copy shifted so that they line up (damaged files only)
                buf = bytes(buf[shift:]) if shift > 0 else b"\0" * -shift + bytes(buf)
                end = len(buf)
                what = (f"the file's first {h} bytes are not MCAP's start" if shift > 0 else
                        f"the file's start is cut ({-shift} bytes fewer than its offsets count)")
                scan.warnings.append(f"damaged: {what}; its footer is there: read with the summary's offsets moved "
                                     f"by {shift:+d} bytes (the byte offsets below count as the summary does: the "
                                     f"file's byte = offset {shift:+d})")
        footer = False
        n_chunks = 0
        inner = inner_shift(buf)
        if inner:
            scan.warnings.append(f"damaged: the summary section is {inner:+d} bytes from where the footer says "
                                 "(bytes put in or lost inside the file): the chunks after the damage are "
                                 "read at the summary's offsets moved by as much")
        else:
            head = summary_damaged_head(buf)
            if head is not None:
                scan.warnings.append(f"damaged: the summary section does not read from byte {head[0]} to byte "
                                     f"{head[1]} (bytes overwritten: the footer's offsets are where the records "
                                     "are); its records after them used, the definitions lost with them read from "
                                     "the data section")
            elif (said := summary_crc_damage(buf)) is not None:
                scan.warnings.append(f"damaged: {said}: {SUMMARY_UNUSED}")
        for op, at, nxt in summary_definitions(buf, inner):
            try:
                scan.schema(buf, at + 9, nxt) if op == _OP_SCHEMA else scan.channel(buf, at + 9)
            except (_Damage, struct.error, UnicodeDecodeError):
                pass  # a damaged summary: the definitions come from the data section as before
        scan.provisional = {("schema", k) for k in scan.schemas} | {("channel", k) for k in scan.channels}
        starts = summary_chunk_starts(buf, inner)  # where the walk picks up again after a damaged stretch
        last = off
        indexes = IndexCheck()
        while off < end:
            if off + 9 > end:
                scan.warnings.append(f"file truncated at byte {off} of {end} (no footer): readable part used")
                break
            op, ln = _REC.unpack_from(buf, off)
            nxt = off + 9 + ln
            broken = derailed(buf, op, nxt, starts, last)
            if broken is not None:
                what, at = broken
                if at is None:
                    scan.warnings.append(f"damaged: {what} at byte {off}; rest of file ignored")
                    break
                scan.warnings.append(f"damaged: {what} at byte {off}; went on at the next chunk the summary lists "
                                     f"(byte {at})")
                last = off = at
                continue
            if nxt > end:
                got = _partial_chunk(scan, buf, off, end) if op == _OP_CHUNK else 0
                scan.warnings.append(f"file truncated at byte {end}: record at byte {off} (opcode {op}) incomplete; "
                                     + (f"{got} messages recovered from its complete part; " if got else "")
                                     + "readable part used")
                break
            if done is not None:
                done[0] = nxt
            try:
                if op == _OP_CHUNK:
                    n_chunks += 1
                    indexes.chunk_at(buf, off)
                    try:
                        content = inflate_chunk(buf, off, nxt)
                    except _Undecodable as exc:  # the complete messages before the damaged block are kept
                        got = _partial_chunk(scan, buf, off, nxt)
                        if not got:
                            raise
                        scan.warnings.append(f"damaged: {exc}; the {got} complete messages before the damage kept")
                        content = b""
                    except _BadCrc as exc:  # a damaged byte somewhere in it: read, its messages unverified
                        content, said = crc_damage_content(exc, buf, nxt)
                        scan.warnings.append(f"damaged: {exc}; {said} (impossible values and isolated spikes "
                                             "are dropped)")
                        scan.unverified = True
                    # a damaged record: the sound records around it kept (records() adds none of a broken walk)
                    try:
                        places, skipped, first = walk_resyncing(scan.records, content, len(content),
                                                                f"chunk at byte {off}", scan.channels,
                                                                struct.unpack_from("<QQ", buf, off + 9))
                    finally:
                        scan.unverified = False
                    if places:
                        scan.warnings.append(f"damaged: chunk at byte {off}: {places} damaged place(s) (first at "
                                             f"byte {first} of its records), {skipped} bytes skipped to the next "
                                             "readable record")
                    del content
                elif op == _OP_MESSAGE:
                    scan.records(buf, off, nxt, "data section")
                elif op == _OP_MESSAGE_INDEX:
                    indexes.index_at(buf, off, nxt)
                elif op == _OP_SCHEMA:
                    scan.schema(buf, off + 9, nxt)
                elif op == _OP_CHANNEL:
                    scan.channel(buf, off + 9)
                elif op == _OP_FOOTER:
                    footer = True
                    break
            except (_Damage, struct.error, UnicodeDecodeError) as exc:
                msg = str(exc) if isinstance(exc, _Damage) else f"record at byte {off} unreadable ({exc})"
                scan.warnings.append(f"damaged: {msg}; its messages dropped")
            last = off
            off = nxt
            fm.release_before(min(off, last))
        if (said := indexes.said(MESSAGE_INDEX_UNUSED)) is not None:
            scan.warnings.append(said)
        if not footer and not any("truncated" in w or "rest of file" in w for w in scan.warnings):
            scan.warnings.append("no MCAP footer (file truncated?): readable part used")
        del buf
    return scan


def _rawlog(path: str, fmt: str, scan: _Scan) -> rc.RawLog:
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.EMPTY)
    topics: dict[str, rc.RawTopic] = {}
    encodings = set()
    streamed: dict[str, rc.StreamDecoder] = {}
    for cid, (topic, sid, enc) in scan.channels.items():
        name, senc, text = scan.schemas.get(sid, ("", "", b""))
        msgtype = rc.normalize_msgtype(name) if name else ""
        encoding = _ENCODINGS.get(enc, enc)
        keep = scan.kept[cid]
        if keep and text and senc in ("ros2msg", "ros1msg", "ros2idl"):
            try:
                rc.register_msgdef(typestore, msgtype, text.decode("utf-8", "replace"),
                                   "idl" if senc == "ros2idl" else "msg")
            except Exception as exc:
                scan.warnings.append(f"{topic}: message definition of {msgtype} unusable ({type(exc).__name__}); "
                                     "using the built-in one")
        if keep:
            encodings.add(encoding)
        if encoding not in READ_ENCODINGS:
            keep = False
            if msgtype in rc.SUPPORTED:
                scan.warnings.append(f"{topic}: message encoding {enc!r} not supported; topic ignored")
                scan.times.pop(cid)  # (not offered as a topic it has no readable content for)
                continue
        times = scan.times.pop(cid)
        if scan.stream:
            if topic in topics:
                raise rc.NotStreamable(f"{topic}: on several channels")
            log_ns = np.concatenate(times) if times else np.zeros(0, np.int64)
            del times
            dec = scan.decoders.pop(cid)
            if keep and dec is not None:
                streamed[topic] = dec
            topics[topic] = rc.RawTopic(topic, msgtype, encoding, log_ns, [])
            continue
        log_ns = np.concatenate(times).tolist() if times else []
        raw = rc.RawTopic(topic, msgtype, encoding, log_ns, scan.data[cid] if keep else [])
        if topic in topics:  # same topic on several channels: merge
            old = topics[topic]
            old.log_ns.extend(raw.log_ns)
            if keep and len(old.data) == len(old.log_ns) - len(raw.log_ns):
                old.data.extend(raw.data)
            continue
        topics[topic] = raw
    for enc in encodings - {"json"}:  # types without a definition in the file: the built-in ones (loaded only then)
        try:
            register_builtin(typestore, {t.msgtype for t in topics.values()
                                         if t.encoding == enc and t.msgtype in rc.SUPPORTED}, enc)
        except Exception as exc:
            scan.warnings.append(f"built-in message definitions not usable: {exc}")
    for topic, dec in streamed.items():  # the rest of each streamed topic, with the final definitions
        topics[topic].decoded, topics[topic].data = dec.finish(typestore)
    return rc.RawLog(path=path, fmt=fmt, topics=topics, typestore=typestore, warnings=scan.warnings)


def _closure(store, names: set[str]) -> set[str]:
    out: set[str] = set()
    todo = [n for n in names if n in store.fielddefs]
    while todo:
        n = todo.pop()
        if n in out:
            continue
        out.add(n)
        for _f, (nt, detail) in store.fielddefs[n][1]:
            nt = int(nt)
            if nt == 2:
                todo.append(detail)
            elif nt in (3, 4) and int(detail[0][0]) == 2:
                todo.append(detail[0][1])
    return out


def register_builtin(typestore, msgtypes, encoding: str, base=None):
    """rosbags' built-in definitions (ROS 1 Noetic for ``encoding`` "ros1", else ROS 2 Humble) of those
    ``msgtypes`` ``typestore`` has no definition of, and of the types they use, registered in it (none it
    has replaced): a file that stores no definition, or a damaged one, is decoded by the built-in ones.
    Returns the built-in store (``base``: one loaded before, passed again: loading it costs)."""
    missing = {m for m in msgtypes if m not in typestore.fielddefs}
    if not missing:
        return base
    if base is None:
        base = rc.default_typestore(encoding)
    typestore.register({k: base.fielddefs[k] for k in _closure(base, missing) if k not in typestore.fielddefs})
    return base


def _read_for_decode(path: str) -> rc.RawLog:
    """The file decoded while read (:func:`read_streamed`), or read the classic way where that cannot be
    exact (rc.NotStreamable: a zoo of message lengths, a topic on several channels...)."""
    try:
        return read_streamed(path)
    except rc.NotStreamable:
        return read_raw(path, keep=rc.keep_supported)


def load(path: str, selector: Selector) -> InsLog:
    return rc.to_inslog(_read_for_decode(path), selector, release=True)


def inventory(path: str) -> Inventory:
    return rc.to_inventory(_read_for_decode(path))


# ---- writing ---------------------------------------------------------------------------------
def write_topics(stream, topics: list[rc.OutTopic], typestore, encoding: str, log_delay_ns: int = 0,
                 compression: str = "zstd") -> None:
    """Write ROS messages to an open binary stream as MCAP (chunks with CRCs and indexes)."""
    from mcap.writer import CompressionType, Writer

    w = Writer(stream, compression=CompressionType[compression.upper()])
    w.start(profile="ros2" if encoding == "cdr" else "ros1", library="tapost")
    chans = []
    for tp in topics:
        if encoding == "cdr":
            text, sname, senc = typestore.generate_msgdef(tp.msgtype, ros_version=2)[0], tp.msgtype, "ros2msg"
        else:
            text, sname, senc = (typestore.generate_msgdef(tp.msgtype, ros_version=1)[0],
                                 tp.msgtype.replace("/msg/", "/"), "ros1msg")
        sid = w.register_schema(name=sname, encoding=senc, data=text.encode())
        chans.append(w.register_channel(topic=tp.name, message_encoding=encoding, schema_id=sid))
    seq = [0] * len(topics)
    for t, k, i in rc.merged_order(topics, log_delay_ns):
        w.add_message(channel_id=chans[k], log_time=t, data=topics[k].data[i],
                      publish_time=int(topics[k].stamp_ns[i]), sequence=seq[k])
        seq[k] += 1
    w.finish()


def write(path: str, log: InsLog, *, encoding: str = "cdr", log_delay_ns: int = 0,
          compression: str = "zstd") -> None:
    """Write ``log`` as a ROS MCAP file (``encoding`` "cdr" = ROS 2, "ros1" = ROS 1;
    ``compression`` zstd, lz4 or none)."""
    if encoding not in ("cdr", "ros1"):
        raise InputError(f"mcap encoding must be cdr or ros1, not {encoding!r}", path)
    if compression not in ("zstd", "lz4", "none"):
        raise InputError(f"mcap compression must be zstd, lz4 or none, not {compression!r}", path)
    typestore = rc.default_typestore(encoding)
    topics = rc.ros_topics_from_inslog(log, typestore, encoding)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        write_topics(fh, topics, typestore, encoding, log_delay_ns, compression)
