"""What every format module provides, and small shared helpers for them."""
from __future__ import annotations

import functools
import os
import sys
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from logtools.errors import InputError
from logtools.inslog import InsLog


@dataclass(frozen=True)
class Selector:
    """Parsed ``PATH::key=value,...`` selector. Keys: imu, nav, att, vel, pos, clock, time ..."""

    items: tuple[tuple[str, str], ...] = ()

    @staticmethod
    def parse(text: str) -> "Selector":
        items = []
        for part in filter(None, (p.strip() for p in text.split(","))):
            if "=" not in part:
                raise ValueError(f"selector item {part!r} is not key=value")
            k, v = part.split("=", 1)
            if not v.strip():  # (imu= read as "not given" chose nothing and said no INS messages were found)
                raise ValueError(f"selector item {part!r} gives {k.strip()} no value")
            items.append((k.strip().lower(), v.strip()))
        return Selector(tuple(items))

    def get(self, key: str, default: str | None = None) -> str | None:
        for k, v in self.items:
            if k == key:
                return v
        return default

    def __str__(self) -> str:
        return ",".join(f"{k}={v}" for k, v in self.items)

    def __bool__(self) -> bool:
        return bool(self.items)


@dataclass(frozen=True)
class StreamInfo:
    """One stream inside a log, as ``tapost inspect`` lists it."""

    name: str  # message/topic name, e.g. "IMU2", "/xsens/imu_data", "HIGHRES_IMU"
    kind: str  # "imu", "gyro", "accel", "att", "vel", "pos", "odom", "other"
    count: int
    rate_hz: float
    start_s: float  # absolute seconds on the stream's clock
    duration_s: float
    clock: str = "unknown"
    fields: tuple[str, ...] = ()


@dataclass(frozen=True)
class Inventory:
    path: str
    format: str
    streams: tuple[StreamInfo, ...]
    selectors: tuple[str, ...]  # ready-to-use selectors, one per unit found ("imu=IMU,nav=NKF1")
    warnings: tuple[str, ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)


class FormatModule(Protocol):
    NAME: str
    EXTENSIONS: tuple[str, ...]

    def sniff(self, head: bytes, path: str) -> bool: ...

    def load(self, path: str, selector: Selector) -> InsLog: ...

    def inventory(self, path: str) -> Inventory: ...


#: a stream whose stamps come in bursts (more than this share of its steps beyond BURST_STEP_RATIO of the median
#: step: telemetry received a few messages at a time) is given its mean rate over its bursts, not the rate
#: within a burst (a tlog's AHRS2 on receive stamps, 4.3 Hz delivered in groups 3-9 ms apart, was "111 Hz")
BURST_STEP_SHARE = 0.1
BURST_STEP_RATIO = 3.0
#: a step beyond this many typical steps of a bursty stream is a gap, not part of its rate
BURST_GAP_STEPS = 10.0


def rate_of(t_s: np.ndarray) -> float:
    """Robust sample rate (Hz) from stamps: 1 / the median of the positive steps; for a bursty stream (its
    long steps common, BURST_STEP_SHARE) the samples per second over its steps bar gaps (BURST_GAP_STEPS of
    ``typical_step``). A regular stream with gaps keeps its median: its long steps are few."""
    t = np.asarray(t_s, dtype=float)
    if len(t) < 2:
        return 0.0
    d = np.diff(t)
    d = d[d > 0]
    if not len(d):
        return 0.0
    med = float(np.median(d))
    if np.count_nonzero(d > BURST_STEP_RATIO * med) > BURST_STEP_SHARE * len(d):
        from logtools.conventions import typical_step

        keep = d <= BURST_GAP_STEPS * typical_step(d)
        return float(np.count_nonzero(keep) / d[keep].sum())
    return 1.0 / med


#: how far into a file whose start is damaged, or has bytes put before it (a transfer's garbage in front of
#: the file), a format's own start is looked for: ULog's messages, MCAP's records, SQLite's header, a canonical
#: CSV's header line
DAMAGED_HEAD_SEARCH_BYTES = 1 << 16
#: what is read to look over that window: the window and what a start needs after it (a header line, the
#: records that must chain), so that format detection and the readers judge a file's start alike
DAMAGED_HEAD_READ_BYTES = DAMAGED_HEAD_SEARCH_BYTES + (1 << 13)
#: stamps (int64 ns, any clock) beyond +-this are no clock's reading: 2**62 ns is 146 years, past any boot
#: clock and UNIX time up to 2116. It is also the int64 headroom: two stamps inside it differ by less than
#: 2**63 (their step cannot wrap), and adding a boot -> UTC offset (under EPOCH_MAX_NS) cannot wrap either.
#: A corrupt time field (a flipped high byte of a uint64 microsecond count) lies beyond it.
STAMP_LIMIT_NS = 1 << 62
#: what :func:`counts_to_ns` makes of a count beyond STAMP_LIMIT_NS: past the limit (assemble drops it as an
#: impossible stamp) and 73 years short of int64's end, so that a format's sub-stamp terms (PX4's relative
#: accelerometer stamp, half an IMU interval) added to it cannot wrap
STAMP_OUT_OF_RANGE_NS = 3 << 61
#: the UNIX time (ns) a GPS/UTC time field may give: GPS time's start (1980-01-06) to 2100-01-01. A fix
#: outside is a corrupt field; a boot -> UTC offset putting a log's stamps outside is not applied.
EPOCH_MIN_NS = 315_964_800 * 1_000_000_000
EPOCH_MAX_NS = 4_102_444_800 * 1_000_000_000


def counts_to_ns(counts: np.ndarray, ns_per_count: int) -> np.ndarray:
    """Integer clock counts (any integer dtype; a corrupt uint64 stamp may use every bit) -> int64 ns,
    checked: a count whose ns would lie beyond +-STAMP_LIMIT_NS (or wrap int64) becomes
    STAMP_OUT_OF_RANGE_NS, which :func:`parsers.assemble.clean_stream` drops with a warning. Counts in
    range give exactly ``counts.astype(np.int64) * ns_per_count``."""
    c = np.asarray(counts)
    lim = STAMP_LIMIT_NS // int(ns_per_count)
    if c.dtype.kind == "u":
        bad = c >= lim
    elif c.dtype.kind == "i":
        bad = (c >= lim) | (c <= -lim)
    else:  # (a float count: truncated as astype does; NaN/inf are impossible stamps too)
        with np.errstate(invalid="ignore"):
            bad = ~(np.abs(c) < lim)
    with np.errstate(invalid="ignore"):
        out = c.astype(np.int64) * int(ns_per_count)
    if bad.any():
        out[bad] = STAMP_OUT_OF_RANGE_NS
    return out


#: GPS/UTC fixes whose (UTC - boot) offset lies farther than this from the fixes' median are inconsistent with
#: the others (a corrupt field): a boot clock drifting 100 ppm moves the offset 3.6 s over a 10 h log, and real
#: GPS messages' logging latency scatters it by milliseconds
UTC_AGREE_S = 5.0


def consensus_offset(diff: np.ndarray, counts_per_s: int) -> tuple[np.ndarray, str]:
    """The fixes that agree, of ``diff`` (one (UTC - boot) offset reading per fix, int64 counts of
    ``1 / counts_per_s`` s, every fix already inside the plausible ranges): those within UTC_AGREE_S of the
    median of all, when they are more than half of them. Returns (mask of the agreeing fixes, problem): the
    mask is all False, and the problem says why, when no majority agrees (no offset to trust)."""
    d = np.asarray(diff, dtype=np.int64)
    if not len(d):
        return np.zeros(0, dtype=bool), "no valid fix"
    med = int(np.median(d))
    ok = np.abs(d - med) <= int(UTC_AGREE_S * counts_per_s)
    if 2 * int(ok.sum()) <= len(d):
        return np.zeros(len(d), dtype=bool), (f"the {len(d)} valid fixes disagree (only {int(ok.sum())} within "
                                             f"{UTC_AGREE_S:g} s of their median offset)")
    return ok, ""


def offset_sigma_s(diff: np.ndarray, counts_per_s: int, quantum_s: float) -> float:
    """The 1-sigma (s) of a boot -> UTC offset taken as the median of per-fix readings ``diff`` (int64 counts,
    the agreeing fixes): their robust spread (MAD x 1.4826: the logging delay's jitter, which the log cannot
    separate from the delay itself, so counted in full, not divided by the fixes' number) and the GPS time's
    own quantisation ``quantum_s`` (whole milliseconds: 0.29 ms), combined."""
    d = np.asarray(diff, dtype=np.int64)
    if not len(d):
        return float(quantum_s / np.sqrt(12.0))
    med = np.median(d)
    mad = float(np.median(np.abs(d - med))) * 1.4826 / counts_per_s
    return float(np.hypot(mad, quantum_s / np.sqrt(12.0)))


#: stamp grids tested for (s), coarsest first: stamps on one of these are quantised to it
STAMP_GRIDS_S = (1e-2, 1e-3, 1e-4)


def stamp_grid_s(t_ns: np.ndarray, steps: np.ndarray | None = None) -> float:
    """The grid (s) the stamps were quantised to, when that shows in the data, else 0.

    Stamps quantised to a grid q (whole milliseconds, say) all lie on it (one residue modulo q), and
    their steps differ by multiples of q where the true period is not a multiple of q or the phase
    walks (drift, jitter): steps that are not all multiples of the median step. Stamps that lie on the
    grid at an exact period (a synthetic log, or a quantised clock with an integer period and no drift)
    show no quantisation: the format's own resolution has to say it there. Exact int ns: no tolerance.
    ``steps``: ``np.diff(t_ns)`` when the caller has it."""
    t = np.asarray(t_ns, dtype=np.int64)
    if len(t) < 3:
        return 0.0
    d = np.diff(t) if steps is None else steps
    d = d[d > 0]
    if len(d) < 2:
        return 0.0
    rel = t - t[0]
    for q in STAMP_GRIDS_S:
        q_ns = int(round(q * 1e9))
        if np.any(rel % q_ns):
            continue
        del rel
        med = int(np.median(d))
        return q if med > 0 and np.any(d % med) else 0.0
    return 0.0


class DamagedRecords:
    """The damaged records of one kind a walk meets, said once at its end: how many, and where the first lies
    (``what``: their description, e.g. "index record(s) do not match the chunks")."""

    def __init__(self, what: str):
        self.what, self.count, self.first = what, 0, 0

    def add(self, at: int) -> None:
        if not self.count:
            self.first = at
        self.count += 1

    def said(self, then: str) -> str | None:
        """The one warning (``then``: what was done about them), or None where there were none."""
        return f"damaged: {self.count} {self.what} (the first at byte {self.first}): {then}" if self.count else None


@functools.cache
def libc():
    """The C library of this process (``ctypes.CDLL(None)``: the one already loaded, nothing looked up), for
    the few system calls numpy and the standard library do not offer (malloc controls, madvise, prctl); None
    elsewhere than Linux or where ctypes cannot load it. ``ctypes.util.find_library`` is not used: it runs
    ``ldconfig -p`` in a subprocess (a fork of the analysing process in every run)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True)
    except (ImportError, OSError):
        return None


def glibc():
    """:func:`libc` where it is glibc (it has ``malloc_trim``; musl has not), else None."""
    lib = libc()
    return lib if lib is not None and hasattr(lib, "malloc_trim") else None


def release_free_memory() -> None:
    """Hand the memory the allocator keeps free back to the system (glibc ``malloc_trim``; elsewhere
    nothing). A parse frees many mid-sized temporaries that glibc keeps in its heap for reuse: the next
    stage would otherwise start with them still counted in the process's resident memory."""
    lib = glibc()
    if lib is not None:
        try:
            lib.malloc_trim(0)
        except Exception:  # noqa: BLE001 - best effort
            pass


def check_readable(path: str) -> None:
    if not os.path.exists(path):
        raise InputError("no such file", path)
    if os.path.isdir(path):
        return
    if not os.access(path, os.R_OK):
        raise InputError("not readable (permission denied)", path)
    if os.path.getsize(path) == 0:
        raise InputError("empty file", path)
