"""A log file mapped read-only into memory, for readers that go through it front to back.

Reading a whole log with ``fh.read()`` / ``np.fromfile`` costs its size in private memory for as long as
the reader holds it (a 4-hour tlog: 660 MB). A memory map costs nothing up front, but every page the reader
touches stays resident (and counts in the process's RSS) until it is unmapped. :meth:`FileMap.release_before`
lets the pages behind a sequential reader go (``madvise(MADV_DONTNEED)``: the kernel keeps them in its
page cache, a later touch maps them again), so a reader holds about one window of the file at a time.
"""
from __future__ import annotations

import mmap
import os

import numpy as np

#: pages are let go in steps of at least this many bytes (one madvise call per step)
RELEASE_STEP = 16 << 20


class FileMap:
    """``path`` mapped read-only: ``buf`` (the mmap: slicing gives bytes) and ``array`` (uint8 view of it).
    Use as a context manager; an empty file maps to empty buffers."""

    def __init__(self, path: str):
        self._fh = open(path, "rb")
        try:
            self.size = os.fstat(self._fh.fileno()).st_size
            self._mm = mmap.mmap(self._fh.fileno(), 0, access=mmap.ACCESS_READ) if self.size else None
        except BaseException:
            self._fh.close()
            raise
        self._released = 0

    @property
    def buf(self):
        return self._mm if self._mm is not None else b""

    @property
    def array(self) -> np.ndarray:
        return np.frombuffer(self._mm, dtype=np.uint8) if self._mm is not None else np.zeros(0, np.uint8)

    def release_before(self, offset: int, *, force: bool = False) -> None:
        """Let the resident pages before byte ``offset`` go (in RELEASE_STEP steps, or now with ``force``).
        Where the platform has no madvise this does nothing (the pages then stay until ``close``)."""
        if self._mm is None or not hasattr(mmap, "MADV_DONTNEED") or not hasattr(self._mm, "madvise"):
            return
        end = min(int(offset), self.size) // mmap.PAGESIZE * mmap.PAGESIZE
        if end - self._released < (1 if force else RELEASE_STEP):
            return
        try:
            self._mm.madvise(mmap.MADV_DONTNEED, self._released, end - self._released)
        except (OSError, ValueError):
            return
        self._released = end

    def close(self) -> None:
        if self._mm is not None:
            self.release_before(self.size, force=True)
            try:
                self._mm.close()
            except BufferError:  # an array still views the map: it is unmapped when that goes
                pass
            self._mm = None
        self._fh.close()

    def __enter__(self) -> "FileMap":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
