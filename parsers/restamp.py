"""The slave on the master's clock, written in its own format: the shared types of the native writers.

A native writer copies every record of a slave log and rewrites only its time fields with a
:class:`ClockShift`. Each format's writer lives beside its reader (it knows the format's time fields,
units and clocks); this module holds what they share.
"""
from __future__ import annotations

import contextlib
import mmap
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from logtools.errors import InputError
from logtools.latency.config import SearchConfig
from parsers import threads
from parsers.atomic import atomic_path


@dataclass(frozen=True)
class ClockShift:
    """``t_master = t_slave - latency``, with ``latency`` linear in time (drift), exactly as
    ``logtools.compensate`` applies it.

    Instants are int64 nanoseconds on the slave's analysis clock (``meta.t0_ns + t_s 1e9`` of the slave's
    InsLog: UNIX or boot, whichever the parser put it on; the master's stamps use the same numbers, the
    latency holds any offset between the two clocks). The slave stamp ``t`` of the physical instant
    ``tau`` (master's clock) is ``t = tau + L0 + d (tau - t_ref)`` (``L0 = latency_s``, ``d = drift_ppm
    1e-6``, ``t_ref_ns`` the master-clock instant where ``latency_s`` holds: the middle of the analysed
    window, report.json ``master.t0_ns + latency.t_mid_rel_s 1e9``), hence
    ``tau = (t - L0 + d t_ref) / (1 + d)`` and the shift ``t - tau = (L0 + d (t - t_ref)) / (1 + d)``."""

    latency_s: float
    drift_ppm: float
    t_ref_ns: int

    def shift_ns(self, t_ns: np.ndarray) -> np.ndarray:
        """The nanoseconds to subtract from each slave instant (int64, rounded to the nearest ns)."""
        t = np.asarray(t_ns, dtype=np.int64)
        d = self.drift_ppm * 1e-6
        # (latency + d * dt_s) / (1 + d) * 1e9 with dt_s = (t - t_ref) 1e-9 (the exact difference first), each
        # operation in place on one array (a million stamps: one temporary instead of eight), the same numbers
        s = np.atleast_1d(t - np.int64(self.t_ref_ns)).astype(np.float64)
        s *= 1e-9
        s *= d
        s += self.latency_s
        s /= 1.0 + d
        s *= 1e9
        if len(s) and not (float(s.max()) < _INT64_NS and float(s.min()) > -_INT64_NS):  # (NaN fails too)
            worst = float(s[~(np.abs(s) < _INT64_NS)][0]) * 1e-9  # no clock offset: stamps cannot hold it
            raise ValueError(f"a shift of {worst:.6g} s (latency {self.latency_s:.6g} s, drift {self.drift_ppm:.6g} "
                             "ppm) is beyond what int64 nanosecond stamps hold: not a usable clock offset")
        np.rint(s, out=s)
        out = s.astype(np.int64)
        return out if np.ndim(t) else out[0]

    def to_master_ns(self, t_ns: np.ndarray) -> np.ndarray:
        t = np.asarray(t_ns, dtype=np.int64)
        return t - self.shift_ns(t)

    def shift_units(self, t_ns: np.ndarray, unit_ns: int) -> np.ndarray:
        """The shift at each instant in whole ``unit_ns`` (1000: microseconds), rounded to the nearest."""
        s = self.shift_ns(t_ns)
        return np.floor_divide(s + unit_ns // 2, unit_ns)

    @classmethod
    def from_latency(cls, lat, master_t0_ns: int) -> ClockShift:
        """From a ``logtools.results.LatencyResult`` (``t_mid_rel_s`` relative to the master's t0)."""
        return cls(float(lat.latency_s), float(lat.drift_ppm),
                   int(master_t0_ns) + int(round(float(lat.t_mid_rel_s) * 1e9)))

    @classmethod
    def from_report(cls, rep: dict) -> ClockShift:
        """From a report.json dict; raises ValueError when it holds no usable latency estimate."""
        lat = rep.get("latency") or {}
        if not isinstance(lat, dict):
            raise ValueError("the report's latency section is not an object")
        if lat.get("failed") or lat.get("latency_s") is None:
            raise ValueError(f"the report holds no latency estimate ({lat.get('failed') or 'latency_s is null'})")

        def num(name: str, value) -> float:
            try:
                return float(value)
            except (TypeError, ValueError):
                raise ValueError(f"the report's {name} {value!r} is not a number") from None

        drift = lat.get("drift_ppm")
        drift = 0.0 if drift is None else num("drift_ppm", drift)
        master = rep.get("master") if isinstance(rep.get("master"), dict) else {}
        window = lat.get("window_s")
        if lat.get("t_mid_rel_s") is not None and master.get("t0_ns") is not None:
            t0 = master["t0_ns"]
            if isinstance(t0, bool) or not isinstance(t0, int):
                raise ValueError(f"the report's master.t0_ns {t0!r} is not a whole number of nanoseconds")
            t_ref = t0 + int(round(num("t_mid_rel_s", lat["t_mid_rel_s"]) * 1e9))
        elif isinstance(window, (list, tuple)) and len(window) == 2:
            t_ref = int(round(0.5 * (num("window_s", window[0]) + num("window_s", window[1])) * 1e9))
        else:
            raise ValueError("the report states neither latency.t_mid_rel_s nor latency.window_s")
        latency = num("latency_s", lat["latency_s"])
        # a damaged or hand-edited report: stamps moved by more than any two clocks can differ, or a clock running
        # at another rate altogether, are no latency estimate (and would overflow or divide by zero below)
        if not (np.isfinite(latency) and abs(latency) <= MAX_REPORT_LATENCY_S):
            raise ValueError(f"the report's latency_s {latency!r} is not a usable latency "
                             f"(finite, within +-{MAX_REPORT_LATENCY_S:g} s)")
        if not (np.isfinite(drift) and abs(drift) <= MAX_REPORT_DRIFT_PPM):
            raise ValueError(f"the report's drift_ppm {drift!r} is not a usable drift "
                             f"(finite, within +-{MAX_REPORT_DRIFT_PPM:g} ppm)")
        return cls(latency, drift, t_ref)


#: shifts (ns) at or beyond this do not fit int64 stamps (2**63 rounded down to a float that is exact)
_INT64_NS = 9.2e18

#: the largest latency and drift a report may hand to ``tapost restamp``: the latency estimator's own bound
#: (a slave on time since boot against a master on UNIX time differs by ~1.7e9 s, a legitimate estimate that
#: ``analyze --write-slave`` exports; no two clocks up to 2100 differ by more than 4.2e9 s), and 1 % drift
MAX_REPORT_LATENCY_S = SearchConfig().max_latency_s
MAX_REPORT_DRIFT_PPM = 10_000.0


@dataclass(frozen=True)
class RestampStats:
    """What a native writer did: for the report's ``outputs`` entry and the summary."""

    path: str
    format: str
    how: str  # e.g. "byte-level rewrite of the time fields" or "rewritten through pymavlink"
    records: int  # records written (== records read that were intact)
    records_by_type: dict[str, int] = field(default_factory=dict)
    time_fields: tuple[str, ...] = ()  # which fields were rewritten
    damage: tuple[str, ...] = ()  # what could not be read and is therefore not in the output


def write_bytes_atomic(dst: str, buf: np.ndarray | bytes) -> None:
    """Write ``buf`` to ``dst`` atomically (temporary sibling + rename)."""
    with atomic_path(dst) as tmp:
        if isinstance(buf, np.ndarray):
            buf.tofile(tmp)
        else:
            with open(tmp, "wb") as fh:
                fh.write(buf)


def read_bytes(src: str) -> np.ndarray:
    """The whole file as a writable uint8 copy (the input is never written)."""
    if os.path.isdir(src):
        raise IsADirectoryError(src)
    return np.fromfile(src, dtype=np.uint8)


#: numpy's huge-page advice (madvise(MADV_HUGEPAGE) on arrays of 4 MB and more) on while an MCAP or a ROS 1 bag
#: export runs. A tapost process keeps it off (``pipelines.cli.NUMPY_HUGEPAGES``: its analysis stages allocate
#: and free many arrays); these exports instead allocate a few large buffers that they fill once, whole (the
#: file's copy, its decompressed chunks, the columns of message offsets, times and stamps), and with 4 KiB
#: pages each page of them is one fault. Measured on the 1 h 200 Hz slaves, the export in one process: MCAP
#: (316 MB of chunks) 125 000 page faults and 0.26-0.32 s of system time with it off, 11 000-13 000 and
#: 0.10-0.20 s with it on, 0.63-0.68 s against 0.45-0.57 s wall; ROS 1 bag (347 MB) 0.50 against 0.47 s
#: (medians of 5 processes). The same output bytes. Not for the other formats' exports: tried on all of them,
#: the ROS 2 sqlite3 and CSV exports got slower in some runs (the kernel compacting memory to find huge
#: pages), and they allocate no such buffers. (Since an MCAP file of zstd chunks is exported from a streamed
#: scan, without the buffer for its decompressed chunks, its export measures the same with it and without:
#: it serves the MCAP exports that keep their chunks, and the ROS 1 bag's.)
EXPORT_HUGEPAGES = True


@contextlib.contextmanager
def export_hugepages() -> Iterator[None]:
    """EXPORT_HUGEPAGES for the time of the block (numpy's own switch, as ``NUMPY_MADVISE_HUGEPAGE`` sets it
    at import), then numpy's setting as it was. Where this numpy has no such switch, nothing."""
    try:
        from numpy._core import multiarray as _ma
    except ImportError:  # (numpy < 2)
        from numpy.core import multiarray as _ma
    switch = getattr(_ma, "_set_madvise_hugepage", None)
    if switch is None or not EXPORT_HUGEPAGES:
        yield
        return
    before = switch(True)
    try:
        yield
    finally:
        switch(before)


def populate_for_write(buf: np.ndarray, mm: mmap.mmap) -> None:
    """``madvise(MADV_POPULATE_WRITE)`` (Linux 5.14) over the shared map ``mm`` (``buf`` viewing it) of a copy
    about to be patched: its pages' write faults taken in one call instead of one by one. Through libc, which
    releases the GIL for the call (0.03-0.04 s for a 347 MB copy; a caller may run it in a thread beside its
    reads); ``mmap.madvise`` where ctypes cannot. A kernel without it (EINVAL): nothing, the pages fault as
    they are written; elsewhere than Linux, nothing."""
    if not sys.platform.startswith("linux"):
        return
    advice = getattr(mmap, "MADV_POPULATE_WRITE", 23)
    try:
        import ctypes

        from parsers.base import libc

        lib = libc()
        lib.madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
        lib.madvise(buf.ctypes.data, buf.nbytes, advice)
    except (OSError, AttributeError):
        with contextlib.suppress(OSError, ValueError):
            mm.madvise(advice)


@contextlib.contextmanager
def mapped_copy(path: str, size: int, *, populate_beside: bool = False) -> Iterator[np.ndarray | None]:
    """``path`` (a finished copy of ``size`` bytes, about to be patched) mapped shared and writable: a uint8 array
    over it, written back by the kernel, its pages populated for writing (:func:`populate_for_write`: now, or
    with ``populate_beside`` in a worker thread while the caller begins, waited for before the map goes); None
    where it cannot be (another size, an empty file, a file system that cannot map a file for writing)."""
    mm = None
    try:
        with open(path, "r+b") as fh:
            if os.fstat(fh.fileno()).st_size == size and size:
                mm = mmap.mmap(fh.fileno(), 0)
    except (OSError, ValueError):
        mm = None
    if mm is None:
        yield None
        return
    out = np.frombuffer(mm, np.uint8)
    populated = None
    try:
        if populate_beside:
            populated = threads.beside(populate_for_write, out, mm)
        else:
            populate_for_write(out, mm)
        yield out
    finally:
        if populated is not None:
            threads.drain([populated])  # (before the map goes)
        del out
        with contextlib.suppress(BufferError):  # (an array still viewing the map: unmapped when it goes)
            mm.close()


_LE = {1: "<u1", 2: "<u2", 4: "<u4", 8: "<u8"}
_LE_SIGNED = {1: "<i1", 2: "<i2", 4: "<i4", 8: "<i8"}


def _put_bytes(buf, offs, block):  # compiled with numba (kernel "_put_bytes"); plain Python otherwise
    """buf[offs[i]:offs[i] + w] = block[i] for every row of ``block`` (w columns)."""
    w = block.shape[1]
    for i in range(len(offs)):
        o = offs[i]
        for j in range(w):
            buf[o + j] = block[i, j]


def _get_bytes(buf, offs, block):  # compiled with numba (kernel "_get_bytes"); plain Python otherwise
    """block[i] = buf[offs[i]:offs[i] + w] for every row of ``block`` (w columns)."""
    w = block.shape[1]
    for i in range(len(offs)):
        o = offs[i]
        for j in range(w):
            block[i, j] = buf[o + j]


def _in_bounds(buf: np.ndarray, offs: np.ndarray, nbytes: int) -> None:
    if int(offs.min()) < 0 or int(offs.max()) + nbytes > len(buf):
        raise IndexError(f"a {nbytes}-byte field at byte {int(offs.max())} runs past the buffer ({len(buf)} bytes)")


def put_le(buf: np.ndarray, offsets: np.ndarray, values: np.ndarray, nbytes: int) -> None:
    """Write little-endian unsigned ``values`` of ``nbytes`` bytes at byte ``offsets`` of ``buf``."""
    offs = np.asarray(offsets, dtype=np.int64)
    if not len(offs):
        return
    raw = np.ascontiguousarray(np.asarray(values).astype(np.int64).astype(_LE[nbytes]))
    put_bytes(buf, offs, raw.view(np.uint8).reshape(len(offs), nbytes))


def put_bytes(buf: np.ndarray, offs: np.ndarray, block: np.ndarray) -> None:
    """``buf[offs[i]:offs[i] + w] = block[i]`` for the rows of the (n, w) uint8 ``block`` (numba kernel in
    compiled mode: the fancy-indexed assignment costs 5-10 times more on a 1 h log's million fields)."""
    from logtools import jit

    offs = np.asarray(offs, dtype=np.int64)
    if not len(offs):
        return
    if jit.compiled():
        _in_bounds(buf, offs, block.shape[1])
        _kernel("_put_bytes")(buf, offs, np.ascontiguousarray(block, dtype=np.uint8))
    else:
        buf[offs[:, None] + np.arange(block.shape[1])] = block


def get_bytes(buf: np.ndarray, offs: np.ndarray, width: int) -> np.ndarray:
    """The (n, width) uint8 block of ``buf[offs[i]:offs[i] + width]`` (numba kernel in compiled mode)."""
    from logtools import jit

    offs = np.asarray(offs, dtype=np.int64)
    if not len(offs):
        return np.zeros((0, width), np.uint8)
    if not jit.compiled() or not buf.flags.writeable:  # (the kernel is compiled for writable arrays: a
        return np.ascontiguousarray(buf[offs[:, None] + np.arange(width)])  # read-only one would compile it)
    _in_bounds(buf, offs, width)
    block = np.empty((len(offs), width), np.uint8)
    _kernel("_get_bytes")(buf, offs, block)
    return block


def get_le(buf: np.ndarray, offsets: np.ndarray, nbytes: int, signed: bool = False) -> np.ndarray:
    """Little-endian unsigned (or signed) integers of ``nbytes`` bytes at ``offsets`` (int64)."""
    offs = np.asarray(offsets, dtype=np.int64)
    if not len(offs):
        return np.zeros(0, dtype=np.int64)
    block = get_bytes(buf, offs, nbytes)
    return block.view((_LE_SIGNED if signed else _LE)[nbytes]).reshape(-1).astype(np.int64)


def glitches(old: np.ndarray, unit_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """(mask, repaired) of a time field of one message type in file order: a value more than 1 s from both
    its neighbours and from the median of its 3 neighbours each side is a damaged value (a flipped byte);
    ``repaired`` has that median in its place (for the shift of the message's other time fields). Costs
    two vectorised passes when there is none."""
    old = np.asarray(old, dtype=np.int64)
    n = len(old)
    mask = np.zeros(n, dtype=bool)
    lim = 1_000_000_000 // unit_ns
    if n < 3:
        return mask, old
    d = np.abs(np.diff(old))
    cand = np.flatnonzero((d[:-1] > lim) & (d[1:] > lim)) + 1  # away from both neighbours
    ends = [i for i, far in ((0, d[0] > lim), (n - 1, d[-1] > lim)) if far]  # (one neighbour each)
    cand = np.concatenate([cand, np.asarray(ends, np.int64)])
    if not len(cand):
        return mask, old
    k = 3
    pad = np.pad(old, k, mode="edge")
    win = np.stack([pad[cand + j] for j in range(2 * k + 1) if j != k], axis=1)
    nb = np.median(win, axis=1).astype(np.int64)
    bad = np.abs(old[cand] - nb) > lim
    mask[cand[bad]] = True
    repaired = old.copy()
    repaired[cand[bad]] = nb[bad]
    return mask, repaired


def nonneg_or_glitch(old: np.ndarray, new: np.ndarray, unit_ns: int, what: str, path: str, damage: list[str],
                     clock: str = "this field's clock", nbytes: int = 8) -> np.ndarray:
    """``new`` (a time field of one message type, in file order, shifted) where every value is >= 0. A
    negative one at a record whose field is a glitch (:func:`glitches`) keeps its ``old`` value and is
    counted in ``damage``; any other negative value is the clock's limit (the master's clock starting later
    than ``clock`` can express): one clear error. So is a value beyond the field's ``nbytes`` (a uint32
    millisecond field cannot hold UNIX time: a boot-clocked slave put on a master's UNIX clock), which would
    be written wrapped."""
    if nbytes < 8 and len(new) and int(new.max()) > (1 << (8 * nbytes)) - 1:
        raise InputError(f"native export: shifted {what} would be beyond its field ({8 * nbytes}-bit: the "
                         f"master's clock lies where {clock} cannot express it; export csv/parquet instead)", path)
    neg = new < 0
    if not len(new) or not neg.any():
        return new
    glitch = neg & glitches(old, unit_ns)[0]
    if (neg & ~glitch).any():
        raise InputError(f"native export: shifted {what} would be negative (the master's clock starts later "
                         f"than {clock} can express; export csv/parquet instead)", path)
    damage.append(f"{what}: {int(glitch.sum())} record(s) with a damaged time value (far from their neighbours'); "
                  "copied unchanged")
    return np.where(glitch, old, new)


def kernel_loader(namespace: dict):
    """``kernel(name)``: the plain-Python function ``namespace[name]`` compiled by numba on first use (cached
    on disk) when this process runs compiled kernels (logtools.jit), else the function itself; importing a
    writer costs no compile and numba loads only when a native export runs."""
    compiled: dict[str, object] = {}

    def kernel(name: str):
        fn = compiled.get(name)
        if fn is None:
            from logtools import jit

            fn = compiled[name] = jit.njit(namespace[name], nogil=True)  # (some run on parts in threads)
        return fn

    return kernel


_kernel = kernel_loader(globals())  # the numba kernels above, compiled (and cached) on first use
