"""Helpers shared by the MAVLink tlog and ArduPilot DataFlash parsers.

* record walkers: the one inherently sequential step (each record's length says where the next
  one starts). Compiled with numba when it is importable (``cache=True``: compiled once per
  machine, then loaded from ``__pycache__``), otherwise the same code runs as plain Python on a
  ``bytes`` object (correct but some 100x slower: a few hundred k records/s).
* gather / CRC / scatter kernels: numba when available, column-wise numpy otherwise; the tests
  check both give identical results.
* X.25 CRC (CRC-16/MCRF4XX, what MAVLink calls ``crc_accumulate``), vectorised column-wise over
  all frames of one message type.
* struct format -> numpy structured dtype (little-endian, packed), so a block of payloads can be
  viewed as records with ``ndarray.view``.
* GPS week/ms -> UNIX time with leap seconds.
"""
from __future__ import annotations

import re

import numpy as np

from logtools import jit

HAVE_NUMBA = jit.compiled()  # compiled kernels in this process (logtools.jit decides: cache, input size)
_njit = jit.njit  # numba.njit(cache=True) in compiled mode; the plain function otherwise


# ---- X.25 CRC ----------------------------------------------------------------------------------
def _crc_table() -> np.ndarray:
    tab = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0x8408 if c & 1 else c >> 1
        tab[i] = c
    return tab


CRC_TABLE = _crc_table()


def x25_accumulate(crc: np.ndarray, byte_col: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """One X.25 step for every row: ``crc`` (uint16, N) accumulates ``byte_col`` (uint8, N).
    Rows where ``mask`` is False keep their CRC (used for variable-length frames)."""
    new = (crc >> 8) ^ CRC_TABLE[(crc ^ byte_col) & 0xFF]
    if mask is None:
        return new
    return np.where(mask, new, crc)


def x25_crc_rows(block: np.ndarray, lengths: np.ndarray | None = None, extra: int | None = None) -> np.ndarray:
    """X.25 CRC of each row of ``block`` (N, W) uint8 over its first ``lengths[i]`` bytes (all W
    when None), then the byte ``extra`` (MAVLink's CRC_EXTRA) if given. Column-wise: W numpy steps."""
    block = np.asarray(block, dtype=np.uint8)
    n, w = block.shape
    crc = np.full(n, 0xFFFF, dtype=np.uint16)
    for j in range(w):
        crc = x25_accumulate(crc, block[:, j].astype(np.uint16),
                             None if lengths is None else (lengths > j))
    if extra is not None:
        crc = x25_accumulate(crc, np.full(n, extra, dtype=np.uint16))
    return crc.astype(np.uint16)


# ---- struct format -> numpy dtype ---------------------------------------------------------------
_STRUCT_TO_NP = {"b": "i1", "B": "u1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "l": "<i4",
                 "L": "<u4", "q": "<i8", "Q": "<u8", "f": "<f4", "d": "<f8", "e": "<f2", "c": "S1",
                 "?": "u1"}
_TOKEN = re.compile(r"(\d*)([a-zA-Z?])")


def dtype_from_struct(fmt: str, names: list[str] | tuple[str, ...]) -> np.dtype:
    """Packed little-endian numpy dtype for a ``struct`` format whose fields are ``names`` (an
    ``Ns`` string is one field of N bytes; ``Nf`` etc. is one field holding an array of N)."""
    fmt = fmt.lstrip("<>=!@")
    toks = _TOKEN.findall(fmt)
    if len(toks) != len(names):
        raise ValueError(f"struct format {fmt!r} has {len(toks)} fields, {len(names)} names")
    fields = []
    for (count, ch), name in zip(toks, names):
        n = int(count) if count else 1
        if ch in "sp":
            fields.append((name, f"S{n}"))
        elif ch == "x":
            raise ValueError("pad bytes not supported")
        else:
            base = _STRUCT_TO_NP[ch]
            fields.append((name, base, (n,)) if n > 1 else (name, base))
    return np.dtype(fields)


def gather_rows_np(buf: np.ndarray, starts: np.ndarray, width: int,
                   lengths: np.ndarray | None = None) -> np.ndarray:
    """numpy version of :func:`gather_rows` (column by column into a transposed block)."""
    n = len(starts)
    if n == 0 or width == 0:
        return np.zeros((n, width), dtype=np.uint8)
    starts = np.asarray(starts, dtype=np.int64)
    lengths = None if lengths is None else np.asarray(lengths, dtype=np.int64)
    last = len(buf) - 1
    out_t = np.empty((width, n), dtype=np.uint8)
    for j in range(width):
        idx = starts + j
        col = buf[np.minimum(idx, last)]
        bad = idx > last
        if lengths is not None:
            bad |= lengths <= j
        col[bad] = 0
        out_t[j] = col
    return np.ascontiguousarray(out_t.T)


@_njit(cache=True)
def _gather_nb(buf, starts, width, lengths):  # pragma: no cover - compiled
    n = len(starts)
    nbuf = len(buf)
    out = np.zeros((n, width), dtype=np.uint8)
    for i in range(n):
        s = starts[i]
        m = min(width, lengths[i], nbuf - s)
        for j in range(m):
            out[i, j] = buf[s + j]
    return out


def gather_rows(buf: np.ndarray, starts: np.ndarray, width: int,
                lengths: np.ndarray | None = None) -> np.ndarray:
    """(N, width) uint8 block of ``buf[starts[i]: starts[i] + width]``; bytes at or past
    ``lengths[i]`` (and past the end of ``buf``) are zero (MAVLink 2 payload truncation)."""
    if not HAVE_NUMBA or len(starts) == 0 or width == 0:
        return gather_rows_np(buf, starts, width, lengths)
    ln = (np.full(len(starts), width, dtype=np.int64) if lengths is None
          else np.asarray(lengths, dtype=np.int64))
    return _gather_nb(buf, np.asarray(starts, dtype=np.int64), int(width), ln)


def x25_crc_at_np(buf: np.ndarray, starts: np.ndarray, width: int, extra: int | None = None) -> np.ndarray:
    """numpy version of :func:`x25_crc_at`: column-wise, straight from the buffer."""
    starts = np.asarray(starts, dtype=np.int64)
    crc = np.full(len(starts), 0xFFFF, dtype=np.uint16)
    for j in range(width):
        crc = x25_accumulate(crc, buf[starts + j].astype(np.uint16))
    if extra is not None:
        crc = x25_accumulate(crc, np.full(len(starts), extra, dtype=np.uint16))
    return crc


@_njit(cache=True)
def _crc_var_nb(buf, starts, lengths, extra, table):  # pragma: no cover - compiled
    n = len(starts)
    out = np.empty(n, dtype=np.uint16)
    for i in range(n):
        crc = np.uint16(0xFFFF)
        s = starts[i]
        for j in range(lengths[i]):
            crc = (crc >> 8) ^ table[(crc ^ buf[s + j]) & 0xFF]
        if extra >= 0:
            crc = (crc >> 8) ^ table[(crc ^ extra) & 0xFF]
        out[i] = crc
    return out


def x25_crc_block(block: np.ndarray, offset: int, lengths: np.ndarray, extra: int | None = None) -> np.ndarray:
    """X.25 CRC of row i of ``block`` (N, W) uint8 over columns ``offset .. offset + lengths[i]``
    (then CRC_EXTRA): compiled when numba is there, else column-wise numpy with a length mask."""
    block = np.ascontiguousarray(block, dtype=np.uint8)
    n, w = block.shape
    lengths = np.asarray(lengths, dtype=np.int64)
    if HAVE_NUMBA and n:
        starts = np.arange(n, dtype=np.int64) * w + offset
        return _crc_var_nb(block.reshape(-1), starts, lengths, -1 if extra is None else int(extra),
                           CRC_TABLE)
    return x25_crc_rows(block[:, offset:], lengths, extra)


def x25_crc_at(buf: np.ndarray, starts: np.ndarray, width: int, extra: int | None = None) -> np.ndarray:
    """X.25 CRC of ``buf[starts[i]: starts[i] + width]`` for every i (then CRC_EXTRA)."""
    if not HAVE_NUMBA:
        return x25_crc_at_np(buf, starts, width, extra)
    starts = np.asarray(starts, dtype=np.int64)
    return _crc_var_nb(buf, starts, np.full(len(starts), int(width), dtype=np.int64),
                       -1 if extra is None else int(extra), CRC_TABLE)


def records_view(block: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """View an (N, itemsize) uint8 block as N structured records (copy made contiguous)."""
    block = np.ascontiguousarray(block[:, : dtype.itemsize])
    if block.shape[1] < dtype.itemsize:
        block = np.pad(block, ((0, 0), (0, dtype.itemsize - block.shape[1])))
    return block.view(dtype).reshape(-1)


@_njit(cache=True)
def _scatter_nb(out, rows, pos, lens):  # pragma: no cover - compiled
    for i in range(len(pos)):
        p = pos[i]
        for j in range(lens[i]):
            out[p + j] = rows[i, j]


def scatter_rows(out: np.ndarray, rows: np.ndarray, pos: np.ndarray, lens: np.ndarray) -> None:
    """``out[pos[i]: pos[i] + lens[i]] = rows[i, :lens[i]]`` for every row (ragged concatenation)."""
    pos = np.asarray(pos, dtype=np.int64)
    lens = np.asarray(lens, dtype=np.int64)
    if HAVE_NUMBA:
        _scatter_nb(out, np.ascontiguousarray(rows), pos, lens)
        return
    for j in range(rows.shape[1]):  # column-wise: O(N) index memory per step
        m = lens > j
        out[pos[m] + j] = rows[m, j]


@_njit(cache=True, nogil=True)  # (the native export runs it on parts of a file in threads)
def _index_tlog_nb(buf, starts, extra_tab, table):  # pragma: no cover - compiled
    n = len(starts)
    recv = np.empty(n, dtype=np.int64)
    v2 = np.empty(n, dtype=np.bool_)
    plen = np.empty(n, dtype=np.int64)
    sysid = np.empty(n, dtype=np.int64)
    compid = np.empty(n, dtype=np.int64)
    msgid = np.empty(n, dtype=np.int64)
    pay = np.empty(n, dtype=np.int64)
    status = np.zeros(n, dtype=np.int8)
    n_tab = len(extra_tab)
    for k in range(n):
        s = starts[k]
        t = 0
        for j in range(8):
            t = (t << 8) | buf[s + j]
        recv[k] = t
        f = s + 8
        is2 = buf[f] == 0xFD
        ln = buf[f + 1]
        v2[k] = is2
        plen[k] = ln
        if is2:
            sysid[k] = buf[f + 5]
            compid[k] = buf[f + 6]
            mid = np.int64(buf[f + 7]) | (np.int64(buf[f + 8]) << 8) | (np.int64(buf[f + 9]) << 16)
            hdr = 10
        else:
            sysid[k] = buf[f + 3]
            compid[k] = buf[f + 4]
            mid = np.int64(buf[f + 5])
            hdr = 6
        msgid[k] = mid
        pay[k] = f + hdr
        ex = extra_tab[mid] if mid < n_tab else -1
        if ex < 0:
            status[k] = 2
            continue
        crc = np.uint16(0xFFFF)
        for j in range(f + 1, f + hdr + ln):
            crc = (crc >> 8) ^ table[(crc ^ buf[j]) & 0xFF]
        crc = (crc >> 8) ^ table[(crc ^ ex) & 0xFF]
        got = np.int64(buf[f + hdr + ln]) | (np.int64(buf[f + hdr + ln + 1]) << 8)
        if crc != got:
            status[k] = 1
    return recv, v2, plen, sysid, compid, msgid, pay, status


def index_tlog_frames_np(buf: np.ndarray, starts: np.ndarray, extra_tab: np.ndarray):
    """numpy version of :func:`index_tlog_frames`: header fields by fancy indexing, CRCs checked
    column-wise per (version, msgid, length) group."""
    f = starts + 8
    last = len(buf) - 1
    v2 = buf[f] == 0xFD
    plen = buf[f + 1].astype(np.int64)
    hdr = np.where(v2, 10, 6)
    sysid = np.where(v2, buf[np.minimum(f + 5, last)], buf[f + 3]).astype(np.int64)
    compid = np.where(v2, buf[np.minimum(f + 6, last)], buf[f + 4]).astype(np.int64)
    id3 = gather_rows_np(buf, f + 7, 3).astype(np.int64)
    msgid = np.where(v2, id3[:, 0] | (id3[:, 1] << 8) | (id3[:, 2] << 16), buf[f + 5].astype(np.int64))
    crc_pos = f + hdr + plen
    crc_read = buf[crc_pos].astype(np.uint16) | (buf[crc_pos + 1].astype(np.uint16) << 8)
    extra = np.where(msgid < len(extra_tab), extra_tab[np.minimum(msgid, len(extra_tab) - 1)], -1)
    status = np.where(extra >= 0, 1, 2).astype(np.int8)
    key = np.where(extra >= 0, (v2.astype(np.int64) << 40) | (msgid << 8) | plen, -1)
    order = np.argsort(key, kind="stable")
    bounds = np.flatnonzero(np.diff(key[order])) + 1
    for grp in np.split(order, bounds):
        if len(grp) == 0 or key[grp[0]] < 0:
            continue
        width = int(hdr[grp[0]] - 1 + plen[grp[0]])
        crc = x25_crc_at_np(buf, f[grp] + 1, width, extra=int(extra[grp[0]]))
        status[grp[crc == crc_read[grp]]] = 0
    recv = np.ascontiguousarray(gather_rows_np(buf, starts, 8)).view(">u8").reshape(-1).astype(np.int64)
    return recv, v2, plen, sysid, compid, msgid, f + hdr, status


def index_tlog_frames(buf: np.ndarray, starts: np.ndarray, extra_tab: np.ndarray, engine: str = "auto",
                      parts: int = 1):
    """Per walked tlog record: (recv_us, v2, plen, sysid, compid, msgid, payload offset, status),
    status 0 = CRC good, 1 = bad CRC, 2 = message id unknown to the dialect (CRC not checkable).
    ``extra_tab[msgid]`` is the CRC_EXTRA (-1 unknown). ``engine``: auto | numba | numpy. ``parts`` > 1:
    the compiled index of that many runs of records in the I/O threads (the kernel releases the GIL)."""
    starts = np.asarray(starts, dtype=np.int64)
    if engine == "numpy" or (engine == "auto" and not HAVE_NUMBA):
        return index_tlog_frames_np(buf, starts, extra_tab)
    tab = extra_tab.astype(np.int16)
    cuts = np.linspace(0, len(starts), max(1, min(parts, len(starts) // 4096 + 1)) + 1).astype(np.int64)
    if len(cuts) <= 2:
        return _index_tlog_nb(buf, starts, tab, CRC_TABLE)
    from parsers import threads

    done = list(threads.ordered(lambda ab: _index_tlog_nb(buf, starts[ab[0]:ab[1]], tab, CRC_TABLE),
                                list(zip(cuts[:-1].tolist(), cuts[1:].tolist()))))
    return tuple(np.concatenate(cols) for cols in zip(*done))


# ---- record walkers ----------------------------------------------------------------------------
MAX_BACK_US = 60_000_000  # a tlog receive stamp may go back at most this much
MAX_FWD_US = 86_400_000_000  # ... and forward at most a day between two frames


def _tlog_frame_size(buf, i, n):
    """Size (stamp + frame) of a tlog record at i, or -1 if the bytes at i cannot start one."""
    if i + 8 + 8 > n:
        return -1
    magic = buf[i + 8]
    plen = buf[i + 9]
    if magic == 0xFE:
        return 8 + 8 + plen
    if magic == 0xFD:
        if i + 8 + 12 > n:
            return -1
        size = 8 + 12 + plen
        if buf[i + 10] & 1:
            size += 13
        return size
    return -1


def _tlog_stamp(buf, i):
    t = 0
    for k in range(8):
        t = (t << 8) | buf[i + k]
    return t


def _walk_tlog_part(buf, i, stop, in_sync, prev_t, found):
    """The tlog walk from byte ``i`` while ``i < stop`` (a window of a sequential read; ``stop = len(buf)``
    for the rest of the file), in state ``in_sync``, ``prev_t`` (the last accepted stamp, -1 none),
    ``found`` (a record was accepted before ``i``). Every bound is the buffer's own end, so walking a
    buffer window by window (``stop`` at least 1 KiB before the end but for the last window) accepts and
    skips exactly what one walk of it does. Returns (starts, n_skipped_bytes, n_resyncs, i, in_sync,
    prev_t): ``i`` past ``stop`` after a record that crosses it, before ``stop`` where a truncated last
    record ended the walk."""
    n = len(buf)
    starts = np.empty(max(stop - i, 0) // 16 + 1, dtype=np.int64)
    k = 0
    skipped = 0
    resyncs = 0
    while i < stop:
        if in_sync and (n - i < 16 or (n - i < 20 and buf[i + 8] == 0xFD)):
            break  # a truncated last record (shorter than the smallest frame: 16 bytes, a MAVLink 2 one 20)
        size = _tlog_frame_size(buf, i, n)
        ok = size > 0 and i + size <= n
        if ok:
            t = _tlog_stamp(buf, i)
            if t < 0 or t >= (1 << 62):
                ok = False
            elif prev_t >= 0 and (t < prev_t - MAX_BACK_US or t > prev_t + MAX_FWD_US):
                ok = False
        if ok and not in_sync:
            # out of sync: demand that the following record also looks right (or that we are at EOF)
            j = i + size
            if j < n:
                s2 = _tlog_frame_size(buf, j, n)
                if s2 < 0:
                    ok = False
                elif prev_t < 0:
                    t2 = _tlog_stamp(buf, j)
                    if t2 < t - MAX_BACK_US or t2 > t + MAX_FWD_US:
                        ok = False
        if ok and in_sync and prev_t >= 0 and t > prev_t + MAX_BACK_US:
            # a jump forward: a gap in the log, or a damaged stamp (the 8 bytes are outside the frame's
            # CRC). Damaged when the next record's stamp is back near the previous one: that record is
            # dropped (its bytes counted as skipped) and the walk goes on from the previous stamp, so one
            # bad byte cannot make every later stamp look like a step back
            j = i + size
            if j + 16 <= n and _tlog_frame_size(buf, j, n) > 0:
                t2 = _tlog_stamp(buf, j)
                if prev_t - MAX_BACK_US <= t2 < t - MAX_BACK_US:
                    skipped += size
                    resyncs += 1
                    i += size
                    continue
        if ok:
            if not in_sync and (k > 0 or found):
                resyncs += 1
            in_sync = True
            starts[k] = i
            k += 1
            prev_t = _tlog_stamp(buf, i)
            i += size
        else:
            if size > 0 and i + size > n and in_sync:
                break  # truncated last record
            in_sync = False
            skipped += 1
            i += 1
    return starts[:k], skipped, resyncs, i, in_sync, prev_t


def _walk_tlog_impl(buf):
    """Record starts of a tlog ([8-byte BE us stamp][MAVLink frame]...), resyncing byte by byte
    past damage. Returns (starts, n_skipped_bytes, n_resyncs, n_tail_bytes)."""
    starts, skipped, resyncs, i, _in_sync, _prev_t = _walk_tlog_part(buf, 0, len(buf), False, -1, False)
    return starts, skipped, resyncs, len(buf) - i


def _walk_df_impl(buf, lengths):
    """Record starts of a DataFlash log (0xA3 0x95 type ...). ``lengths[type]`` is the record
    length (0 = unknown type; FMT = 128 is always 89). Returns (starts, skipped, resyncs, tail)."""
    n = len(buf)
    starts = np.empty(n // 3 + 1, dtype=np.int64)
    k = 0
    i = 0
    skipped = 0
    resyncs = 0
    in_sync = False
    while i + 3 <= n:
        ok = False
        size = 0
        if buf[i] == 0xA3 and buf[i + 1] == 0x95:
            size = lengths[buf[i + 2]]
            if size >= 3:
                ok = True
        if ok and i + size > n:
            break
        if ok and not in_sync:
            j = i + size
            if j + 3 <= n:
                ok = buf[j] == 0xA3 and buf[j + 1] == 0x95 and lengths[buf[j + 2]] >= 3
        if ok:
            if not in_sync and k > 0:
                resyncs += 1
            in_sync = True
            starts[k] = i
            k += 1
            i += size
        else:
            in_sync = False
            skipped += 1
            i += 1
    return starts[:k], skipped, resyncs, n - i


def _walk_tlog_chain(buf, i, stop, in_sync, prev_t, found):
    """:func:`_walk_tlog_part` for the plain Python code where the log is whole: each record where the one
    before ended, every stamp within MAX_BACK_US of the one before (no gap, nothing to resync). The loop
    follows the chain of frame sizes alone and the stamps are checked at once afterwards (a third of the
    careful walk's time a record); None where anything else is met (then the careful walk decides, from
    the same place). Its result is the careful walk's wherever it gives one (tests/test_parsers_mavlink.py)."""
    n = len(buf)
    starts = []
    while i < stop:
        if n - i < 16:
            return None
        magic = buf[i + 8]
        if magic == 0xFE:
            size = 16 + buf[i + 9]
        elif magic == 0xFD and n - i >= 20:
            size = 20 + buf[i + 9] + (13 if buf[i + 10] & 1 else 0)
        else:
            return None
        if i + size > n:
            return None
        starts.append(i)
        i += size
    if not starts:
        return np.zeros(0, np.int64), 0, 0, i, in_sync, prev_t
    at = np.asarray(starts, np.int64)
    t = gather_rows_np(np.frombuffer(buf, np.uint8), at, 8).view(">u8")[:, 0].astype(np.int64)
    if t.max() >= (1 << 62) or t.min() < 0:
        return None
    back = np.diff(t) if prev_t < 0 else np.diff(t, prepend=prev_t)
    if len(back) and (back.min() < -MAX_BACK_US or back.max() > MAX_BACK_US):
        return None
    if not in_sync and len(at) == 1 and i < n:
        # the first record out of sync: the careful walk looks at the next one too (here, where the chain
        # ended; a second record of the chain passed the same tests above)
        if _tlog_frame_size(buf, i, n) < 0:
            return None
        t2 = _tlog_stamp(buf, i)
        if prev_t < 0 and not (int(t[0]) - MAX_BACK_US <= t2 <= int(t[0]) + MAX_FWD_US):
            return None
    return at, 0, int(not in_sync and found), i, True, int(t[-1])


def walk_tlog(buf: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    if HAVE_NUMBA:
        return _walk_tlog_impl(buf)
    b = bytes(buf)
    fast = _walk_tlog_chain(b, 0, len(b), False, -1, False)
    if fast is not None:
        return fast[0], fast[1], fast[2], len(b) - fast[3]
    return _walk_tlog_impl(b)


def walk_tlog_part(buf: np.ndarray, i: int, stop: int, in_sync: bool, prev_t: int, found: bool):
    """One window of a sequential tlog walk (:func:`_walk_tlog_part`): ``buf`` the whole file (a memory map:
    the kernel reads only around the window)."""
    if HAVE_NUMBA:
        return _walk_tlog_part(buf, int(i), int(stop), bool(in_sync), int(prev_t), bool(found))
    args = (memoryview(buf), int(i), int(stop), bool(in_sync), int(prev_t), bool(found))
    fast = _walk_tlog_chain(*args)
    return fast if fast is not None else _walk_tlog_part(*args)


def walk_dataflash(buf: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, int, int, int]:
    if HAVE_NUMBA:
        return _walk_df_impl(buf, lengths.astype(np.int64))
    return _walk_df_impl(bytes(buf), [int(x) for x in lengths])


if not HAVE_NUMBA:  # the reference walker runs over bytes: one C call per stamp
    def _tlog_stamp(buf, i):  # noqa: F811
        return int.from_bytes(buf[i:i + 8], "big")

if HAVE_NUMBA:  # the helpers the compiled walkers call must be compiled too
    _tlog_frame_size = _njit(cache=True)(_tlog_frame_size)
    _tlog_stamp = _njit(cache=True)(_tlog_stamp)
    _walk_tlog_part = _njit(cache=True)(_walk_tlog_part)
    _walk_tlog_impl = _njit(cache=True)(_walk_tlog_impl)
    _walk_df_impl = _njit(cache=True)(_walk_df_impl)


# ---- time --------------------------------------------------------------------------------------
GPS_EPOCH_UNIX_S = 315_964_800  # 1980-01-06T00:00:00Z
#: (UNIX second from which, GPS-UTC leap seconds)
_LEAPS = ((362_793_600, 1), (394_329_600, 2), (425_865_600, 3), (489_024_000, 4), (567_993_600, 5),
          (631_152_000, 6), (662_688_000, 7), (709_948_800, 8), (741_484_800, 9), (773_020_800, 10),
          (820_454_400, 11), (867_715_200, 12), (915_148_800, 13), (1_136_073_600, 14),
          (1_230_768_000, 15), (1_341_100_800, 16), (1_435_708_800, 17), (1_483_228_800, 18))


def gps_leap_s(unix_s: np.ndarray) -> np.ndarray:
    u = np.asarray(unix_s, dtype=float)
    starts = np.array([s for s, _ in _LEAPS], dtype=float)
    vals = np.array([0] + [v for _, v in _LEAPS])
    return vals[np.searchsorted(starts, u, side="right")]


def gps_to_unix_ns(week: np.ndarray, ms: np.ndarray) -> np.ndarray:
    """GPS week + ms of week -> UNIX ns (UTC, leap seconds removed)."""
    gps_ns = (GPS_EPOCH_UNIX_S + np.asarray(week, np.int64) * 604_800) * 1_000_000_000 \
        + np.asarray(ms, np.int64) * 1_000_000
    leap = gps_leap_s(gps_ns * 1e-9 - 18)
    return gps_ns - leap.astype(np.int64) * 1_000_000_000
