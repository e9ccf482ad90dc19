"""The sqlite3 storage file of a ROS 2 bag restamped in place, at the byte level of SQLite's file format.

A rosbag2 ``.db3`` holds ``messages(id INTEGER PRIMARY KEY, topic_id, timestamp, data)`` and the index
``timestamp_idx`` on ``timestamp``. Re-inserting 1.26 M rows through sqlite3 (what ``rosbags``' writer
does) took four times tapost's parse of the same file; the rows' time fields, though, sit at fixed
places of the file (https://www.sqlite.org/fileformat2.html):

* the table b-tree of ``messages``: leaf pages (flag 13) hold cells ``payload size, rowid, record``; the
  record header lists each column's serial type, ``timestamp`` an 8-byte big-endian integer (serial
  type 6 for nanoseconds since 1970), ``data`` a blob (the serialised message, its header stamp at
  bytes 4..12);
* the index b-tree of ``timestamp_idx``: cells (leaf and interior) hold the record ``timestamp, rowid``.

So a copy of the file is walked (two numba kernels), each row's timestamp and header stamp and each
index entry's timestamp are overwritten (same sizes: no page changes), and the file is written whole.
If the new keys are no longer in index order (two messages whose order the shift swaps), the index is
rebuilt by SQLite (``REINDEX``); the ``metadata`` table's copy of metadata.yaml is updated through
SQLite. Every byte else (free pages, other tables, the schema) is the input's.

Whatever the walk does not expect (another page size than it reads, overflow pages, a timestamp stored
in fewer than 8 bytes, a damaged page) makes :func:`walk` return None, and the caller falls back to
re-inserting the rows (the tolerant path that also recovers damaged files).
"""
from __future__ import annotations

import dataclasses
import os
import sqlite3

import numpy as np

from parsers.restamp import kernel_loader

#: the walk kernels' error codes: a page out of range or of another kind, a cell outside its page, a
#: payload on overflow pages, a record not as rosbag2 writes it, the output arrays full (retried larger)
_OK, _E_PAGE, _E_CELL, _E_OVERFLOW, _E_RECORD, _E_FULL = 0, 1, 2, 3, 4, 5


# ---- kernels (numba in compiled mode; plain Python otherwise) ---------------------------------------
def _varint(b, p):
    """SQLite varint at b[p]: (value, next position)."""
    v = 0
    for i in range(8):
        c = int(b[p + i])  # (int: plain Python on a uint8 array would shift within 8 bits)
        v = (v << 7) | (c & 0x7F)
        if c < 0x80:
            return v, p + i + 1
    return (v << 8) | int(b[p + 8]), p + 9


def _be(b, p, n):
    v = 0
    for i in range(n):
        v = (v << 8) | int(b[p + i])
    return v


def _int(b, p, st):
    """The (non-negative) integer of serial type ``st`` at b[p] (types 8 and 9 are the constants 0, 1)."""
    if st == 8:
        return 0
    if st == 9:
        return 1
    return _be(b, p, st if st < 5 else (6 if st == 5 else 8))


def _is_int(st):
    return 1 <= st <= 6 or st == 8 or st == 9


def _sizeof(st):
    if st <= 4:
        return st
    if st == 5:
        return 6
    if st == 6 or st == 7:
        return 8
    if st < 12:
        return 0
    return (st - 12) // 2 if st % 2 == 0 else (st - 13) // 2


def _columns(b, p, q, hsize, max_cols):
    """The header of the record at b[p] (``hsize`` bytes, its serial types from b[q]): (columns, where the
    header's reading ended, where the values end, serial type of column 0, serial type and value offset of
    columns 1, 2 and 3: a messages row's topic_id, timestamp and data)."""
    val = p + hsize
    ncol = 0
    st0 = -1
    st1 = 0
    st2 = 0
    st3 = 0
    v1 = 0
    v2 = 0
    v3 = 0
    while q < p + hsize and ncol < max_cols:
        st, q = _varint(b, q)
        if ncol == 0:
            st0 = st
        elif ncol == 1:
            st1, v1 = st, val
        elif ncol == 2:
            st2, v2 = st, val
        elif ncol == 3:
            st3, v3 = st, val
        val += _sizeof(st)
        ncol += 1
    return ncol, q, val, st0, st1, v1, st2, v2, st3, v3


def _walk_table(b, page_size, usable, root, n_pages, rowid, topic, ts_off, data_off, data_len):
    """Rows of the table b-tree at page ``root`` in rowid order: (rowid, topic_id, offset of the 8-byte
    timestamp, offset and length of the data blob). Returns (rows, error code)."""
    n = 0
    cap = len(rowid)
    stack = np.empty(n_pages + 2, np.int64)  # a valid tree pushes each page once
    stack[0] = root
    sp = 1
    visits = 0
    max_local = usable - 35
    while sp > 0:
        sp -= 1
        pg = stack[sp]
        visits += 1
        if pg < 1 or pg > n_pages or visits > n_pages:
            return n, _E_PAGE
        base = (pg - 1) * page_size
        h = base + (100 if pg == 1 else 0)
        flag = b[h]
        ncell = _be(b, h + 3, 2)
        if flag == 5:  # interior table page: children left to right (pushed in reverse)
            if sp + ncell + 1 > len(stack) or h + 12 + 2 * ncell > base + usable:
                return n, _E_PAGE
            stack[sp] = _be(b, h + 8, 4)
            sp += 1
            for i in range(ncell - 1, -1, -1):
                c = base + _be(b, h + 12 + 2 * i, 2)
                if c < h + 12 or c + 4 > base + usable:  # (a damaged page: no reading beyond it)
                    return n, _E_CELL
                stack[sp] = _be(b, c, 4)
                sp += 1
        elif flag == 13:
            if h + 8 + 2 * ncell > base + usable:
                return n, _E_PAGE
            for i in range(ncell):
                c = base + _be(b, h + 8 + 2 * i, 2)
                if c < h + 8 or c >= base + page_size:
                    return n, _E_CELL
                size, p = _varint(b, c)
                rid, p = _varint(b, p)
                if size > max_local or p + size > base + usable:
                    return n, _E_OVERFLOW
                hsize, q = _varint(b, p)
                if hsize < 1 or hsize > size:  # (a damaged header length: its serial types run off the page)
                    return n, _E_RECORD
                ncol, q, val, _st0, st_topic, v_topic, st_ts, v_ts, st_data, v_data = \
                    _columns(b, p, q, hsize, 1 << 30)
                if ncol != 4 or val != p + size or st_ts != 6 or st_data < 12 or st_data % 2 == 1 \
                        or not _is_int(st_topic):
                    return n, _E_RECORD
                if n >= cap:
                    return n, _E_FULL
                rowid[n] = rid
                topic[n] = _int(b, v_topic, st_topic)
                ts_off[n] = v_ts
                data_off[n] = v_data
                data_len[n] = (st_data - 12) // 2
                n += 1
        else:
            return n, _E_PAGE
    return n, _OK


def _walk_index(b, page_size, usable, root, n_pages, rowid, ts_off):
    """Entries of the index b-tree at page ``root`` in key order: (rowid, offset of the 8-byte timestamp).
    Returns (entries, error code)."""
    n = 0
    cap = len(rowid)
    pages = np.empty(64, np.int64)
    state = np.empty(64, np.int64)
    pages[0] = root
    state[0] = 0
    sp = 1
    visits = 0
    steps = 0
    max_local = (usable - 12) * 64 // 255 - 23
    while sp > 0:
        steps += 1
        if steps > 3 * cap + 2 * n_pages + 16:  # a cycle of interior pages
            return n, _E_PAGE
        pg = pages[sp - 1]
        s = state[sp - 1]
        if pg < 1 or pg > n_pages:
            return n, _E_PAGE
        base = (pg - 1) * page_size
        h = base + (100 if pg == 1 else 0)
        flag = b[h]
        ncell = _be(b, h + 3, 2)
        if (flag == 10 or flag == 2) and h + (8 if flag == 10 else 12) + 2 * ncell > base + usable:
            return n, _E_PAGE
        if flag == 10 or (flag == 2 and s % 2 == 1):  # a leaf's cells, or an interior cell's own key
            if flag == 10:
                visits += 1
                if visits > n_pages:
                    return n, _E_PAGE
                first, last, skip = 0, ncell, 0
            else:
                first, last, skip = (s - 1) // 2, (s - 1) // 2 + 1, 4
            for i in range(first, last):
                c = base + _be(b, h + (8 if flag == 10 else 12) + 2 * i, 2) + skip
                if c < h + 8 or c >= base + page_size:
                    return n, _E_CELL
                size, p = _varint(b, c)
                if size > max_local or p + size > base + usable:
                    return n, _E_OVERFLOW
                hsize, q = _varint(b, p)
                if hsize < 1 or hsize > size:
                    return n, _E_RECORD
                st_ts, q = _varint(b, q)
                st_id, q = _varint(b, q)
                if q != p + hsize or st_ts != 6 or not _is_int(st_id) or p + hsize + 8 + _sizeof(st_id) != p + size:
                    return n, _E_RECORD
                if n >= cap:
                    return n, _E_FULL
                ts_off[n] = p + hsize
                rowid[n] = _int(b, p + hsize + 8, st_id)
                n += 1
            if flag == 10:
                sp -= 1
            else:
                state[sp - 1] = s + 1
        elif flag == 2:
            if s == 2 * ncell:  # the right-most child replaces this page
                pages[sp - 1] = _be(b, h + 8, 4)
                state[sp - 1] = 0
            else:
                if sp >= len(pages):
                    return n, _E_PAGE
                state[sp - 1] = s + 1
                c = base + _be(b, h + 12 + 2 * (s // 2), 2)
                if c < h + 12 or c + 4 > base + usable:
                    return n, _E_CELL
                pages[sp] = _be(b, c, 4)
                state[sp] = 0
                sp += 1
        else:
            return n, _E_PAGE
    return n, _OK


def _scan_leaves(b, page_size, usable, n_pages, rowid, topic, ts, data_off, data_len):
    """Every table-leaf cell of the file shaped like a ``messages`` row (record: NULL, integer, integer,
    blob), page by page, whatever points to it: the rows of a file whose b-tree's interior pages are lost
    (a truncated copy) or damaged. A page or cell that does not parse is passed over. Returns (rows,
    cells passed over, error code: _E_FULL when the outputs are full)."""
    n = 0
    bad = 0
    cap = len(rowid)
    max_local = usable - 35
    for pg in range(1, n_pages + 1):
        base = (pg - 1) * page_size
        h = base + (100 if pg == 1 else 0)
        if b[h] != 13:
            continue
        ncell = _be(b, h + 3, 2)
        if h + 8 + 2 * ncell > base + usable:
            bad += 1
            continue
        for i in range(ncell):
            c = base + _be(b, h + 8 + 2 * i, 2)
            if c < h + 8 + 2 * ncell or c >= base + usable:
                bad += 1
                continue
            size, p = _varint(b, c)
            rid, p = _varint(b, p)
            if size > max_local or size < 4 or p + size > base + usable:
                bad += 1  # (a payload on overflow pages is not followed: INS messages are far smaller)
                continue
            hsize, q = _varint(b, p)
            if hsize < 1 or hsize > size:
                bad += 1
                continue
            ncol, q, val, st0, st_topic, v_topic, st_ts, v_ts, st_data, v_data = _columns(b, p, q, hsize, 64)
            if q != p + hsize or val != p + size:
                bad += 1
                continue
            if ncol != 4 or st0 != 0 or not _is_int(st_topic) or not _is_int(st_ts) or st_data < 12 \
                    or st_data % 2 == 1:
                continue  # a row of another table (topics, metadata, the schema)
            if n >= cap:
                return n, bad, _E_FULL
            rowid[n] = rid
            topic[n] = _int(b, v_topic, st_topic)
            ts[n] = _int(b, v_ts, st_ts)
            data_off[n] = v_data
            data_len[n] = (st_data - 12) // 2
            n += 1
    return n, bad, _OK


_loader = kernel_loader(globals())
_HELPERS = ("_varint", "_be", "_int", "_is_int", "_sizeof", "_columns")


_HELPERS_DONE: list[bool] = []


def _kernel(name: str):
    """A kernel above, compiled (its helpers compiled first, so that the kernel calls them natively)."""
    if not _HELPERS_DONE:
        for h in _HELPERS:
            globals()[h] = _loader(h)
        _HELPERS_DONE.append(True)
    return _loader(name)


# ---- the file --------------------------------------------------------------------------------------
@dataclasses.dataclass
class Walk:
    """Where the time fields of a .db3 file lie in ``buf`` (a private copy of the file)."""

    buf: np.ndarray  # uint8, writable
    rowid: np.ndarray
    topic: np.ndarray
    ts_off: np.ndarray  # the table rows' timestamp fields (8 bytes, big endian)
    data_off: np.ndarray
    data_len: np.ndarray
    idx_rowid: np.ndarray  # timestamp_idx entries in key order
    idx_ts_off: np.ndarray

    def timestamps(self) -> np.ndarray:
        from parsers.restamp import get_bytes

        return get_bytes(self.buf, self.ts_off, 8).view(">i8").ravel().astype(np.int64)


def _pages(buf: np.ndarray, size: int) -> tuple[int, int] | None:
    """(page size, usable bytes of a page) from the header of a .db3 of ``size`` bytes in ``buf``; None when
    it is no SQLite database or its page size is below SQLite's least (512)."""
    if size < 100 or bytes(buf[:16]) != b"SQLite format 3\x00":
        return None
    page_size = int(buf[16]) << 8 | int(buf[17])
    page_size = 65536 if page_size == 1 else page_size
    if page_size < 512:
        return None
    return page_size, page_size - int(buf[20])


def _read_padded(path: str) -> tuple[np.ndarray, int]:
    """The file's bytes followed by 32 zeros (a damaged cell's varints never read beyond them), and its size."""
    size = os.path.getsize(path)
    buf = np.zeros(size + 32, np.uint8)
    with open(path, "rb") as fh:
        fh.readinto(memoryview(buf)[:size])
    return buf, size


def walk(path: str) -> Walk | None:
    """The table and index of a rosbag2 .db3 walked at the byte level, or None where this does not apply
    (any layout the kernels do not expect: the caller then re-inserts the rows)."""
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True)
        try:
            roots = dict(con.execute("SELECT name, rootpage FROM sqlite_master WHERE name IN "
                                     "('messages', 'timestamp_idx')").fetchall())
            indexes = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='index' AND "
                                                 "tbl_name='messages' AND sql IS NOT NULL")]
            (cols,) = con.execute("SELECT group_concat(name) FROM pragma_table_info('messages')").fetchone()
        finally:
            con.close()
    except sqlite3.DatabaseError:
        return None
    if cols != "id,topic_id,timestamp,data" or "messages" not in roots or indexes not in ([], ["timestamp_idx"]):
        return None
    padded, size = _read_padded(path)
    buf = padded[:size]
    geometry = _pages(buf, len(buf))
    if geometry is None or len(buf) % geometry[0] or buf[18] != 1 or buf[19] != 1:  # (18/19 = 2: WAL mode)
        return None
    page_size, usable = geometry
    n_pages = len(buf) // page_size
    cap = max(1024, len(buf) // 48)
    while True:
        out = [np.empty(cap, np.int64) for _ in range(5)]
        n, err = _kernel("_walk_table")(padded, page_size, usable, int(roots["messages"]), n_pages, *out)
        if err != _E_FULL:
            break
        cap *= 4
    if err:
        return None
    rowid, topic, ts_off, data_off, data_len = (a[:n] for a in out)
    if n > 1 and not np.all(np.diff(rowid) > 0):
        return None
    idx_rowid = idx_ts = np.zeros(0, np.int64)
    if "timestamp_idx" in indexes:
        cap_i = n + 16
        ir, io = np.empty(cap_i, np.int64), np.empty(cap_i, np.int64)
        m, err = _kernel("_walk_index")(padded, page_size, usable, int(roots["timestamp_idx"]), n_pages, ir, io)
        if err or m != n:
            return None
        idx_rowid, idx_ts = ir[:m], io[:m]
        if not np.array_equal(np.sort(idx_rowid), rowid):
            return None
    return Walk(buf, rowid, topic, ts_off, data_off, data_len, idx_rowid, idx_ts)


#: at most this many places where two pages running are no b-tree pages are searched for a new page grid
#: (:func:`_page_grid`; a bag of large messages has long runs of overflow pages, each searched once)
_GRID_SEARCHES = 256


def _page_headers(buf: np.ndarray, offs: np.ndarray, size: int, usable: int) -> np.ndarray:
    """Whether a b-tree page header could start at each offset of ``offs`` (type 2, 5, 10 or 13; first
    freeblock, cell count, cell content start and fragmented bytes inside a page; the first cell pointer in
    the content area). Random bytes pass at about one offset in 10^9."""
    offs = np.asarray(offs, np.int64)
    inside = (offs >= 0) & (offs + 14 <= size)
    h = buf[offs[inside][:, None] + np.arange(14)].astype(np.int32)
    typ, frag = h[:, 0], h[:, 7]
    free, ncell, start = (h[:, 1] << 8) | h[:, 2], (h[:, 3] << 8) | h[:, 4], (h[:, 5] << 8) | h[:, 6]
    start = np.where(start == 0, 65536, start)
    interior = (typ == 2) | (typ == 5)
    hdr = np.where(interior, 12, 8)
    ptr0 = np.where(interior, (h[:, 12] << 8) | h[:, 13], (h[:, 8] << 8) | h[:, 9])
    ok = interior | (typ == 10) | (typ == 13)
    ok &= (free == 0) | ((free >= 8) & (free < usable))
    ok &= (ncell >= 1) & (hdr + 2 * ncell <= start) & (start <= usable) & (frag <= 60)
    ok &= (ptr0 >= start) & (ptr0 < usable)
    out = np.zeros(len(offs), bool)
    out[np.flatnonzero(inside)] = ok
    return out


def _page_grid(buf: np.ndarray, size: int, page_size: int, usable: int) -> tuple[np.ndarray, int, list[str]] | None:
    """``buf`` with its pages put back on the page grid where bytes were lost from inside the file or put in
    (a cut or an insertion moves every later page off the grid, and a page scan at multiples of the page size
    then finds nothing after it: an 8-byte cut at 2 % of a bag lost 99 % of its rows). Where two pages
    running have no page header at the grid (moved by the shift found so far), the nearest offset within one
    page either way from which three page headers follow at the page size gives the new shift; where there is
    none (overflow or free pages, or damage), the walk goes on at the next page that has one. Returns (the
    bytes on the grid, their page count, what was said); None where nothing moved."""
    n_pages = size // page_size
    shift, shifts, said = 0, [], []
    pg = 2  # (page 1 holds the database header)
    for _ in range(_GRID_SEARCHES):
        pages = np.arange(pg, n_pages + 1)
        good = _page_headers(buf, (pages - 1) * page_size + shift, size, usable)
        two_bad = np.flatnonzero(~good[:-1] & ~good[1:])
        if not len(two_bad):
            break
        k = int(two_bad[0])
        pg = int(pages[k])
        base = (pg - 1) * page_size + shift
        offs = np.arange(max(base - page_size, 0), min(base + page_size, size) + 1)
        c = offs[_page_headers(buf, offs, size, usable)]
        c = c[_page_headers(buf, c + page_size, size, usable) & _page_headers(buf, c + 2 * page_size, size, usable)]
        if len(c):
            new = int(c[np.argmin(np.abs(c - base))]) - (pg - 1) * page_size
            shifts.append((pg, new))
            said.append(f"pages from {pg} on are {new:+d} bytes off the page grid (bytes "
                        f"{'lost' if new < 0 else 'put in'} before them): read back on it")
            shift = new
            pg += 1
        else:
            nxt = np.flatnonzero(good[k:])
            if not len(nxt):
                break
            pg = int(pages[k + nxt[0]])
    if not shifts:
        return None
    out_pages = n_pages + max(0, -min(s for _, s in shifts)) // page_size + 1
    out = np.zeros(out_pages * page_size + 32, np.uint8)
    bounds = [(1, 0)] + shifts
    last_page = 0
    for k, (p0, sh) in enumerate(bounds):
        p1 = bounds[k + 1][0] if k + 1 < len(bounds) else out_pages + 1
        a = (p0 - 1) * page_size
        src0, src1 = max(a + sh, 0), min((p1 - 1) * page_size + sh, size)
        if src1 > src0:
            out[a:a + src1 - src0] = buf[src0:src1]
            last_page = max(last_page, (a + src1 - src0) // page_size)
    return out, last_page, said


@dataclasses.dataclass
class Recovered:
    """``messages`` rows found by a page scan of a damaged .db3 (:func:`recover`), in rowid order."""

    rowid: np.ndarray
    topic: np.ndarray
    timestamp: np.ndarray  # int64 ns
    data: list  # bytes per row
    cells_passed_over: int  # leaf cells that did not parse (damaged)
    pages_declared: int  # the page count the file's header gives (0: not stated)
    pages_present: int  # whole pages in the file
    #: pages found off the page grid (bytes lost or put in inside the file) and read back on it (:func:`_page_grid`)
    moved: tuple[str, ...] = ()

    @property
    def truncated(self) -> bool:
        return self.pages_present < self.pages_declared


def recover(path: str) -> Recovered | None:
    """The ``messages`` rows of a rosbag2 .db3 that SQLite cannot read whole (a truncated copy: its b-tree's
    interior pages, written late, are among the pages lost), found page by page (``_scan_leaves``); a row
    held twice (a freed page's stale copy) is kept once. None when the file is no SQLite database."""
    buf, size = _read_padded(path)
    geometry = _pages(buf, size)
    if geometry is None or geometry[0] & (geometry[0] - 1):
        return None
    page_size, usable = geometry
    n_pages = size // page_size  # (a partial last page: its cells, written from the page's end, are lost)
    declared = int.from_bytes(bytes(buf[28:32]), "big")
    grid = _page_grid(buf, size, page_size, usable)
    said: list[str] = []
    if grid is not None:  # (bytes lost or put in inside the file: its later pages back on the page grid)
        buf, n_pages, said = grid
    cap = max(1024, size // 48)
    while True:
        out = [np.empty(cap, np.int64) for _ in range(5)]
        n, bad, err = _kernel("_scan_leaves")(buf, page_size, usable, n_pages, *out)
        if err != _E_FULL:
            break
        cap *= 4
    rowid, topic, ts, off, ln = (a[:n] for a in out)
    rowid, first = np.unique(rowid, return_index=True)
    topic, ts, off, ln = topic[first], ts[first], off[first], ln[first]
    data = [buf[o:o + k].tobytes() for o, k in zip(off.tolist(), ln.tolist())]
    return Recovered(rowid, topic, ts, data, int(bad), declared, n_pages, tuple(said))


def _be8(v: np.ndarray) -> np.ndarray:
    """int64 values as rows of 8 big-endian bytes (SQLite's serial type 6)."""
    return np.ascontiguousarray(v.astype(">i8")).view(np.uint8).reshape(-1, 8)


def write(w: Walk, new_ts: np.ndarray, dst: str, info: dict | None) -> bool:
    """``w.buf`` with the rows' timestamps ``new_ts`` (row order) and the index's written to ``dst``
    (the payloads are already patched in ``w.buf``), the metadata table's bag information replaced by
    ``info`` (in the form it had: with or without the ``rosbag2_bagfile_information`` root). Returns
    whether the index had to be rebuilt."""
    import yaml

    from parsers.restamp import put_bytes

    new_ts = np.ascontiguousarray(new_ts, np.int64)
    put_bytes(w.buf, w.ts_off, _be8(new_ts))
    rebuilt = False
    if len(w.idx_rowid):
        key = new_ts[np.searchsorted(w.rowid, w.idx_rowid)]
        put_bytes(w.buf, w.idx_ts_off, _be8(key))
        dk, dr = np.diff(key), np.diff(w.idx_rowid)
        rebuilt = bool(np.any((dk < 0) | ((dk == 0) & (dr < 0))))
    w.buf.tofile(dst)
    con = sqlite3.connect(dst)
    try:
        con.execute("PRAGMA journal_mode=OFF")  # (the file is a temporary one, renamed into place when whole)
        con.execute("PRAGMA synchronous=OFF")
        if rebuilt:
            con.execute("REINDEX timestamp_idx")
        has_meta = con.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='metadata'").fetchone()
        if info is not None and has_meta:
            for rid, text in con.execute("SELECT id, metadata FROM metadata").fetchall():
                rooted = isinstance(text, str) and text.lstrip().startswith("rosbag2_bagfile_information")
                new = yaml.safe_dump({"rosbag2_bagfile_information": info} if rooted else info, sort_keys=False)
                con.execute("UPDATE metadata SET metadata = ? WHERE id = ?", (new, rid))
        con.commit()
    finally:
        con.close()
    return rebuilt


def connections(path: str) -> list | None:
    """The bag's connections as ``rosbags`` lists them (topic, type, definition, serialisation, QoS) from
    the topics and message_definitions tables, without the reader's count over every message row (a
    second of a 1 h bag); None where the tables are not as rosbag2 writes them."""
    from rosbags.interfaces import Connection, ConnectionExtRosbag2, MessageDefinition, MessageDefinitionFormat
    from rosbags.rosbag2.metadata import parse_qos

    from parsers.rosbag2 import connect_ro

    try:
        con = connect_ro(path)
        try:
            cur = con.execute("SELECT * FROM topics ORDER BY id")
            names = [d[0] for d in cur.description]
            topics = [dict(zip(names, r)) for r in cur.fetchall()]
            defs = {}
            if con.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='message_definitions'").fetchone():
                for name, enc, text in con.execute("SELECT topic_type, encoding, encoded_message_definition "
                                                   "FROM message_definitions ORDER BY id"):
                    defs.setdefault(name, (enc, text))
        finally:
            con.close()
    except sqlite3.DatabaseError:
        return None
    fmt = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
    out = []
    for t in topics:
        if not {"id", "name", "type", "serialization_format"} <= set(t):
            return None
        enc, text = defs.get(t["type"], ("", ""))
        msgdef = MessageDefinition(fmt[enc], text) if enc in fmt else \
            MessageDefinition(MessageDefinitionFormat.NONE, "")
        qos = parse_qos(t["offered_qos_profiles"]) if t.get("offered_qos_profiles") else []
        out.append(Connection(t["id"], t["name"], t["type"], msgdef, t.get("type_description_hash") or "", 0,
                              ConnectionExtRosbag2(t["serialization_format"], qos), None))
    return out
