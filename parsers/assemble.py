"""Shared by every format module: raw streams (int64 ns stamps + SI arrays in FRD/NED) -> InsLog.

Format modules convert units, axes and clocks, then call :func:`build_inslog`, which sorts, drops
duplicate stamps, reports gaps/resets/non-monotonic stamps as warnings and picks ``t0_ns``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from logtools.conventions import typical_step
from logtools.errors import InputError
from logtools.inslog import ACCEL, GYRO, POS, QUAT, VEL, ChannelInfo, Columns, InsLog, LogMeta
from parsers.base import EPOCH_MAX_NS, EPOCH_MIN_NS, STAMP_LIMIT_NS, rate_of, stamp_grid_s

#: a stamp step larger than this many typical periods is reported as a gap (gap_warning)
GAP_FACTOR = 5.0
#: a run of at most STRAY_MAX_SAMPLES samples cut off from the rest by steps longer than STRAY_GAP_S and
#: STRAY_GAP_PERIODS median periods holds stray stamps (a corrupt time field: one DataFlash TimeUS with
#: a flipped byte put a sample 12 days after a 40 s log, and a uniform grid over that span took 16 GB)
STRAY_GAP_S = 60.0
STRAY_GAP_PERIODS = 1000.0
STRAY_MAX_SAMPLES = 3
#: ... or of at most this fraction of the stream's samples: a compressed chunk (LZ4, zstd) repeats earlier bytes
#: by reference, so one flipped bit in a stamp can come out in several messages (an LZ4 ROS 1 bag: 7
#: consecutive IMU samples 1.0e9 s before the rest of a 7796-sample stream, which the analysis then refused as
#: "spread over 1004176466 s"); a run so small beyond a minute's gap holds nothing an analysis could use ...
STRAY_MAX_FRACTION = 0.002
#: ... and of at most this many samples whatever the stream's length (0.2 % of 4 h at 200 Hz would be 29 s of
#: data: a stretch recorded before a pause, not a stamp a compressor repeated)
STRAY_MAX_RUN = 64


@dataclass(frozen=True)
class ClockStepConfig:
    """When stamps that run backwards in record order are a clock step back or a reset (the unit's clock
    set back mid-recording: two stretches of the log on clocks that differ), not reordering (a few samples
    delivered late: sorted) nor stray stamps (:func:`not_stray`). Such a step splits the stream into parts;
    one part is kept (sorting would interleave the two stretches sample by sample, and the "duplicates"
    dropped would be half of the overlap)."""

    #: a backward step at least this large (s) may be a clock step: a logger's reordering (queues, USB/UDP
    #: transport, a ROS bag's receive order) moves a stamp by at most a few tens of milliseconds
    min_back_s: float = 0.1
    #: ... when at least this many samples after it stay below the stamp before it, the stamps climbing on
    #: from where they landed: a burst of packets delivered late is a few samples (sweep B10: single ones)
    min_run_samples: int = 10
    #: ... and those samples cover at least this fraction of the step back before the stamps are past the
    #: stamp before it again (or they never are: a reset); a late burst covers its own few periods, then the
    #: stamps jump forward by about the step
    min_cover_fraction: float = 0.5
    #: the part kept: the one with the most samples; the part before the step when the other holds at most
    #: this fraction more (the part on the clock the log started on: its t0, its clock, its metadata)
    tie_fraction: float = 0.1
    #: more clock steps than this in one stream: not a clock that was set back now and then but stamps
    #: that run back and forth (sorted as before, said in the warning)
    max_steps: int = 8
    #: rows out of order (a table's stretch of rows shuffled, or moved) are no clock step, where these are
    #: set (a canonical table's rows, ``parsers.csv_canonical``; the streams of a log: off). After a step
    #: the stamps run on increasing from where they landed: at most this fraction of the steps along the
    #: samples until they are past the stamp before the step again run back (1.0: not asked) ...
    max_run_back_fraction: float = 1.0
    #: ... and those samples overlap the stamps before the step: the samples before it within their span
    #: at least this fraction of their number (0.0: not asked). Rows out of order are globally consistent:
    #: a stretch moved fills a hole of the stamps around it, a shuffled one does not climb
    min_overlap_fraction: float = 0.0


CLOCK_STEP = ClockStepConfig()
#: the words every clock-step warning carries (pipelines.report finds them there)
CLOCK_STEP_WORDS = "clock step back"


@dataclass(frozen=True)
class Stream:
    """One stream's samples: ``t_ns`` (int64, on the log's clock) and ``values`` (N, k) in SI."""

    t_ns: np.ndarray
    values: np.ndarray
    source: str = ""
    stamp_resolution_s: float = 0.0  # the format's stamp step when coarse (tlog time_boot_ms, DataFlash TimeMS: 1e-3)
    clock_sigma_s: float = 0.0  # the sigma of the offset that put the stamps on the log's clock (ChannelInfo's)
    clock_offset_ns: int | None = None  # that offset itself, where one did (ChannelInfo's)


@dataclass(frozen=True)
class ClockOffset:
    """A shift of every stream onto another clock (a boot -> UTC offset from the log's GPS time), added by
    :func:`assemble_inslog` after the stamps are cleaned (stray and impossible stamps gone), checked: where
    it would put a stamp outside [EPOCH_MIN_NS, EPOCH_MAX_NS] the log stays on the clock it was given with
    a warning."""

    ns: int  # added to every stamp
    source: str  # the stamp source when applied ("... + boot->UTC offset from ...")
    selector: str  # the selector text when applied (else the one given: the boot clock's)
    clock: str = "epoch"
    #: the offset's 1-sigma (s): joins every shifted stream's ``clock_sigma_s`` (the latency's sigma counts it
    #: where the two units' stamps were not put on UNIX time by one and the same offset)
    sigma_s: float = 0.0


def clock_steps(t_ns: np.ndarray, cfg: ClockStepConfig = CLOCK_STEP) -> np.ndarray:
    """The record indices (into ``t_ns``, stamps in record order) where a clock step back or a reset starts
    a new part (``ClockStepConfig``); empty when the stamps only run back by reordering or stray stamps.
    Costs one comparison pass when no step runs back ``min_back_s`` (the usual stream)."""
    t = np.asarray(t_ns, dtype=np.int64)
    n = len(t)
    if n < cfg.min_run_samples + 2:
        return np.zeros(0, np.int64)
    back_ns = int(round(cfg.min_back_s * 1e9))
    cand = np.flatnonzero(np.diff(t) < -back_ns) + 1
    if not len(cand):
        return cand
    # stray stamps (a corrupt time field far from the rest) are no clock: found as drop_stray finds them,
    # on the sorted stamps, and left out of the judgement
    order = np.argsort(t, kind="stable")
    ok = np.ones(n, bool)
    ok[order] = not_stray(t[order])
    idx = np.flatnonzero(ok)  # record indices of the stamps judged
    tj = t[idx]
    cand = np.flatnonzero(np.diff(tj) < -back_ns) + 1
    steps = []
    for c in cand[:cfg.max_steps + 1]:  # a few candidates, each one vectorised pass
        before = tj[c - 1]
        above = np.flatnonzero(tj[c:] > before)
        j = int(above[0]) if len(above) else len(tj) - c  # samples until the stamps are past it again
        if j < cfg.min_run_samples:
            continue
        if len(above) and tj[c + j - 1] - tj[c] < cfg.min_cover_fraction * (before - tj[c]):
            continue  # a late burst: the stamps then jump forward past the step
        if cfg.max_run_back_fraction < 1.0 or cfg.min_overlap_fraction > 0.0:
            run = tj[c:c + j]
            if np.count_nonzero(np.diff(run) < 0) > cfg.max_run_back_fraction * (j - 1):
                continue  # rows shuffled: the stamps after it do not climb
            earlier = tj[:c]
            if np.count_nonzero((earlier >= run.min()) & (earlier <= run.max())) < cfg.min_overlap_fraction * j:
                continue  # rows moved: they fill a hole of the stamps before them, no clock's second pass
        steps.append(int(idx[c]))
    if len(steps) > cfg.max_steps:
        return np.zeros(0, np.int64)
    return np.asarray(steps, np.int64)


def kept_part(t_ns: np.ndarray, steps: np.ndarray, part: int | None = None,
              cfg: ClockStepConfig = CLOCK_STEP) -> int:
    """Which part (0 = before the first step) of ``t_ns`` split at ``steps`` is kept: ``part`` when given
    and there is one, else the one with the most samples (the earlier on a near tie, ``tie_fraction``)."""
    bounds = np.concatenate([[0], steps, [len(t_ns)]])
    sizes = np.diff(bounds)
    if part is not None and 0 <= part < len(sizes):
        return int(part)
    best = 0
    for k in range(1, len(sizes)):
        if sizes[k] > (1.0 + cfg.tie_fraction) * sizes[best]:
            best = k
    return best


def clock_step_text(t_ns: np.ndarray, steps: np.ndarray, part: int, unit: str = "sample",
                    rows: np.ndarray | None = None) -> str:
    """One line: where the stamps step back (the ``unit``'s number: its index, or ``rows[index]``; the stamps
    before and after; the size), what was kept and what was left out."""
    bounds = np.concatenate([[0], steps, [len(t_ns)]])

    def no(i: int) -> int:
        return int(i) if rows is None else int(rows[i])

    def span(k: int) -> str:
        a, b = int(bounds[k]), int(bounds[k + 1])
        return (f"{unit}s {no(a)}..{no(b - 1)} ({b - a} samples, {t_ns[a] * 1e-9:.3f} .. {t_ns[b - 1] * 1e-9:.3f} s, "
                f"{(t_ns[b - 1] - t_ns[a]) * 1e-9:.1f} s)")

    def size(i: int) -> float:  # the clock's step: the stamp step less the sampling period before it
        before = np.diff(t_ns[max(int(bounds[np.searchsorted(bounds, i) - 1]), i - 101):i])
        period = float(np.median(before)) if len(before) else 0.0
        return (int(t_ns[i]) - int(t_ns[i - 1]) - period) * 1e-9

    where = "; ".join(f"at {unit} {no(i)} (stamp {t_ns[i - 1] * 1e-9:.3f} s -> {t_ns[i] * 1e-9:.3f} s: "
                      f"a step of {size(i):+.3f} s)" for i in steps)
    left = ", ".join(span(k) for k in range(len(bounds) - 1) if k != part)
    return (f"{CLOCK_STEP_WORDS} or reset {where}, the stamps running on from there (not reordering): "
            f"kept {span(part)}; left out {left}, not interleaved")


def split_at_clock_steps(t_ns: np.ndarray, label: str, warnings: list[str], shared: dict | None = None,
                         unit: str = "sample", rows: np.ndarray | None = None,
                         cfg: ClockStepConfig = CLOCK_STEP) -> np.ndarray | None:
    """The record indices to keep of stamps in record order (None: all): one part where a clock step back
    or reset splits them (said in ``warnings``, prefixed with ``label``). ``shared``: the choice of the
    first stream of the log with a step ({"part", "parts"}), set here if empty; a stream split into as many
    parts keeps the same one (the streams of one log stay on one stretch of it). ``cfg``: the rule's
    (``ClockStepConfig``)."""
    steps = clock_steps(t_ns, cfg)
    if not len(steps):
        return None
    n_parts = len(steps) + 1
    given = shared.get("part") if shared and shared.get("parts") == n_parts else None
    k = kept_part(t_ns, steps, given)
    if shared is not None and "part" not in shared:
        shared.update(part=k, parts=n_parts)
    warnings.append(label + clock_step_text(t_ns, steps, k, unit, rows))
    bounds = np.concatenate([[0], steps, [len(t_ns)]])
    return np.arange(bounds[k], bounds[k + 1])


#: a stamp out of line with its neighbours in record order (a corrupt time field: one flipped byte of a
#: DataFlash TimeUS moved a sample 3.5 s ahead, and the stamps after it were taken for a clock stepping back,
#: which cost a quarter of the log): the jump at least this many median sampling periods, and the stamps
#: either side of at most OUTLIER_MAX_SAMPLES such samples a normal step apart (at most their count + 2
#: periods)
OUTLIER_MIN_PERIODS = 10.0
OUTLIER_MAX_SAMPLES = 3


def stamp_outliers(t_ns: np.ndarray, steps: np.ndarray | None = None) -> np.ndarray:
    """True for the samples (record order) whose stamps alone jump away from the stream and back: a run of
    at most OUTLIER_MAX_SAMPLES samples between two stamps that are a normal step apart, the jump in or out
    of it OUTLIER_MIN_PERIODS median periods or more, one way or the other. A clock that steps back keeps
    running from its new value, so it is never one. One comparison pass when no stamp runs back."""
    t = np.asarray(t_ns, dtype=np.int64)
    n = len(t)
    out = np.zeros(n, bool)
    d = np.diff(t) if steps is None else steps
    back = np.flatnonzero(d < 0) + 1  # t[c] < t[c - 1]
    if n < 5 or not len(back):
        return out
    pos = d[d > 0]
    if not len(pos):
        return out
    med = float(np.median(pos))
    jump = OUTLIER_MIN_PERIODS * med
    for c in back[:10_000]:  # (a stream that runs back this often is reordered, not corrupt: sorted as before)
        if t[c - 1] - t[c] < jump:
            continue
        for m in range(1, OUTLIER_MAX_SAMPLES + 1):
            a = c - 1 - m  # samples a+1 .. c-1 ahead of the stream (too late), t[a] and t[c] a normal step apart
            if a >= 0 and 0 < t[c] - t[a] <= (m + 2) * med:
                out[a + 1:c] = True
                break
            b = c - 1 + m  # samples c .. b-1 behind it (too early), t[c - 1] and t[b] a normal step apart
            if b < n and 0 < t[b] - t[c - 1] <= (m + 2) * med:
                out[c:b] = True
                break
    if out.any():
        # a sample recorded late with its true stamp (a ROS bag's message that arrived late, a tlog's delayed
        # packet) fills a hole of the stream where its stamp belongs: kept (sorted in, as before). A corrupt
        # stamp lands where the stream has no hole (between two samples a period apart): dropped
        rest = np.sort(t[~out])
        odd = np.flatnonzero(out)
        i = np.searchsorted(rest, t[odd])
        inside = (i > 0) & (i < len(rest))
        hole = np.zeros(len(odd), bool)
        hole[inside] = rest[i[inside]] - rest[i[inside] - 1] > 1.5 * med
        # (a stamp beyond either end of the stream: the stray-stamp rule's, as before; inside it, a corrupt
        # stamp is what the clock-step rule would take for a step)
        out[odd[hole | ~inside]] = False
    return out


def repeated_samples(t_ns: np.ndarray, values, cfg: ClockStepConfig = CLOCK_STEP) -> np.ndarray:
    """True for the samples (record order) of a stretch of the log recorded twice (a logger's buffer flushed
    again, a telemetry link's resent block): a run of consecutive samples repeating a run of consecutive
    earlier ones exactly, stamps and values (NaN equal to NaN), the values changing along it. Its stamps run
    back by the stretch's length and on again, which the clock-step rule took for a clock set back, keeping
    one part (a tlog with 0.66 s of records repeated lost 39 % of its samples). A stretch whose values do not
    change (a unit at rest, quantised) cannot be told from a clock reset onto the same stamps: left to that
    rule, as is a single sample. Looked for only where the stamps run back by a clock step's ``min_back_s``;
    ``values`` (n, k) of any dtype whose equal rows are the same sample (a CSV's lines: their cells' hashes),
    or a function that makes them (called only then). One comparison pass otherwise."""
    t = np.asarray(t_ns, dtype=np.int64)
    n = len(t)
    out = np.zeros(n, bool)
    if n < 3 or not np.any(np.diff(t) < -int(round(cfg.min_back_s * 1e9))):
        return out
    order = np.lexsort((np.arange(n), t))  # by stamp, then record order
    ts = t[order]
    new_stamp = np.concatenate([[True], ts[1:] != ts[:-1]])
    again = np.flatnonzero(~new_stamp)
    if not len(again):
        return out
    first = np.maximum.accumulate(np.where(new_stamp, np.arange(n), 0))  # each stamp's first sample (sorted)
    rows, firsts = order[again], order[first[again]]  # (a repeat comes later in record order than its first)
    v = np.asarray(values() if callable(values) else values).reshape(n, -1)

    def equal(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        same = a == b
        if a.dtype.kind == "f":
            same |= np.isnan(a) & np.isnan(b)
        return same.all(axis=1)

    keep = equal(v[rows], v[firsts])
    rows, firsts = rows[keep], firsts[keep]
    o = np.argsort(rows)
    rows, firsts = rows[o], firsts[o]
    if len(rows) < 2:
        return out
    # runs: consecutive repeats of consecutive samples
    cut = np.flatnonzero((np.diff(rows) != 1) | (np.diff(firsts) != 1)) + 1
    a_s, b_s = np.concatenate([[0], cut]), np.concatenate([cut, [len(rows)]])
    moves = np.concatenate([[False], ~equal(v[rows[1:]], v[rows[1:] - 1])])  # a value changed from the last
    moved = np.add.reduceat(moves.astype(np.int64), a_s) - moves[a_s]  # (the run's first row: no "last")
    for a, b in zip(a_s[(b_s - a_s >= 2) & (moved > 0)].tolist(), b_s[(b_s - a_s >= 2) & (moved > 0)].tolist()):
        out[rows[a:b]] = True
    return out


#: what the drop of a stretch recorded twice says, of samples and of a table's rows (``row``: "line" in a CSV,
#: "row" in a Parquet file)
REPEATED_SAMPLES_SAID = ("repeating earlier ones exactly (stamp and values: a stretch of the log recorded twice?) "
                         "dropped")
REPEATED_LINES_SAID = ("{n} {row}(s) repeating earlier ones exactly (a stretch of the file written twice?) dropped "
                       "(first at {row} {line})")


def repeated_lines(t_ns: np.ndarray, df, time_col: str) -> np.ndarray:
    """:func:`repeated_samples` of a CSV's lines (rows of ``df``, ``t_ns`` their times), their data cells
    compared by hash: a column that does not change along the stretch (an accelerometer at rest) goes with
    its line, where judged alone it would leave the stretch to the clock-step rule."""
    import pandas as pd  # (its callers, the CSV readers, hold a DataFrame)

    return repeated_samples(t_ns, lambda: pd.util.hash_pandas_object(df.drop(columns=time_col),
                                                                     index=False).to_numpy())


def _drop_joint_repeats(streams: dict[str, Stream | None], warnings: list[str],
                        cfg: ClockStepConfig = CLOCK_STEP) -> None:
    """Streams made from the same records (the same stamps: a MAVLink HIGHRES_IMU's gyro and accel, an
    Odometry's attitude and velocity) judged together for a stretch recorded twice (:func:`repeated_samples`
    over their values side by side), its samples dropped from each, in ``streams``. Judged one by one, a
    stream whose values do not change along the stretch (an accelerometer at rest, quantised) is no repeat,
    and the clock-step rule kept one part of it alone, while the others kept the whole log."""
    keys = [k for k, s in streams.items() if s is not None and len(s.t_ns) >= 3]
    back = -int(round(cfg.min_back_s * 1e9))
    seen: set[str] = set()
    for i, k in enumerate(keys):
        s = streams[k]
        if k in seen or not np.any(np.diff(np.asarray(s.t_ns, np.int64)) < back):
            continue
        group = [k] + [j for j in keys[i + 1:] if j not in seen and len(streams[j].t_ns) == len(s.t_ns)
                       and (streams[j].t_ns is s.t_ns or np.array_equal(streams[j].t_ns, s.t_ns))]
        seen.update(group)
        if len(group) < 2:
            continue
        n = len(s.t_ns)
        rep = repeated_samples(s.t_ns, lambda: np.concatenate(
            [np.asarray(streams[j].values, float).reshape(n, -1) for j in group], axis=1), cfg)
        if rep.any():
            warnings.append(f"{'+'.join(group)} ({s.source}): {int(rep.sum())} sample(s) {REPEATED_SAMPLES_SAID}")
            for j in group:
                streams[j] = replace(streams[j], t_ns=np.asarray(streams[j].t_ns)[~rep],
                                     values=np.asarray(streams[j].values)[~rep])


def clean_stream(name: str, s: Stream, warnings: list[str], clock: dict | None = None) -> Stream:
    """Sort by time, drop non-finite and duplicate stamps; report what was done. A clock step back or reset
    (``clock_steps``) keeps one part of the stream; ``clock`` (shared by the streams of one log) says which
    part the first stream with a step kept, and the others with as many parts keep the same one."""
    t = np.asarray(s.t_ns, dtype=np.int64)
    v = np.asarray(s.values, dtype=float)
    v = v.reshape(len(t), -1) if len(t) else v.reshape(0, v.shape[-1] if v.ndim > 1 else 0)
    wild = (t >= STAMP_LIMIT_NS) | (t <= -STAMP_LIMIT_NS)
    if wild.any():  # (parsers.base.counts_to_ns puts a count it cannot hold there)
        warnings.append(f"{name} ({s.source}): {int(wild.sum())} samples with impossible stamps dropped "
                        f"(beyond +-{STAMP_LIMIT_NS * 1e-9 / 31_557_600:.0f} years: a corrupt time field?)")
        t, v = t[~wild], v[~wild]
    del wild
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        warnings.append(f"{name} ({s.source}): {int((~finite).sum())} samples with NaN/inf dropped")
        t, v = t[finite], v[finite]
    bad = implausible(name, v)
    if bad.any():
        warnings.append(f"{name} ({s.source}): {int(bad.sum())} samples with impossible values dropped "
                        f"(corrupt data?)")
        t, v = t[~bad], v[~bad]
    d = np.diff(t) if len(t) > 1 else None  # the stamp steps, reused while no sample is dropped
    # samples whose stamps run back for another reason than the clock: dropped alone, before the clock-step rule
    for find, what in ((lambda: repeated_samples(t, v), REPEATED_SAMPLES_SAID),
                       (lambda: stamp_outliers(t, d), "whose stamps jump away from their neighbours and back "
                        "dropped (a corrupt time field?)")):
        if d is None or not np.any(d < 0):
            break
        drop = find()
        if drop.any():
            warnings.append(f"{name} ({s.source}): {int(drop.sum())} sample(s) {what}")
            t, v = t[~drop], v[~drop]
            d = np.diff(t) if len(t) > 1 else None
        del drop
    if d is not None and np.any(d < 0):
        keep_idx = split_at_clock_steps(t, f"{name} ({s.source}): ", warnings, clock)
        if keep_idx is not None:
            t, v = t[keep_idx], v[keep_idx]
            d = np.diff(t) if len(t) > 1 else None
        del keep_idx
    if d is not None and np.any(d < 0):
        n_back = int(np.sum(d < 0))
        warnings.append(f"{name} ({s.source}): {n_back} backward time steps (clock reset or reordering); sorted")
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
        del order
        d = np.diff(t)
    if d is not None:
        dup = d == 0
        if dup.any():
            dup = np.concatenate([[False], dup])
            warnings.append(f"{name} ({s.source}): {int(dup.sum())} duplicate stamps dropped")
            t, v = t[~dup], v[~dup]
            d = None
        del dup
    keep = drop_stray(t, f"{name} ({s.source}): ", warnings, steps=d)
    if not keep.all():  # (all kept: the arrays as they are, no copies)
        t, v = t[keep], v[keep]
        d = None
    del keep
    if name in SPIKE_FLOOR and len(t) >= 5:
        spike = impulsive(name, v)
        if spike.any():
            floor = SPIKE_FLOOR[name]
            floor = "/".join(f"{x:g}" for x in floor) if isinstance(floor, tuple) else f"{floor:g}"
            warnings.append(f"{name} ({s.source}): {int(spike.sum())} isolated spike(s) dropped (one sample "
                            f"beyond {floor} {SPIKE_UNIT[name]} from its neighbours and back: corrupt data?)")
            t, v = t[~spike], v[~spike]
            d = None
        del spike
    if len(t) > 2:
        d = np.diff(t) if d is None else d
        said = gap_warning(f"{name} ({s.source})", d)
        if said:
            warnings.append(said)
    # the stamps' resolution: the format's (tlog time_boot_ms), or the grid the stamps show they are on
    return Stream(t, v, s.source, max(s.stamp_resolution_s, stamp_grid_s(t, steps=d if len(t) > 2 else None)),
                  s.clock_sigma_s, s.clock_offset_ns)


#: physically impossible magnitudes per stream (SI): a sample beyond them is a corrupt value (a flipped
#: bit in a float without checksum), dropped with a warning. Generous: 10000 deg/s, about 500 g, 10 km/s.
LIMITS = {"gyro": 175.0, "accel": 5000.0, "vel": 1.0e4}


#: rows of a stream checked at a time (bounds the temporary copies of the checks)
CHECK_ROWS = 1 << 18

#: a single sample this far (SI) from the median of its two neighbours each side, beyond SPIKE_SIGMAS of the
#: stream's own sample-to-sample scatter, with its neighbours on either side agreeing (SPIKE_BACK: the signal
#: goes on as if it were not there), is a corrupt value, not motion: a flipped exponent bit gave a -97 rad/s
#: gyro sample inside LIMITS, and the latency fit chose a 25 s lag to avoid it. 10 rad/s (573 deg/s) in one
#: sample and back is no rigid vehicle's rotation. Specific force is left alone up to 1000 m/s^2 (100 g): a
#: crash is one sample of 12-14 g at 25 Hz in both IMUs of ArduCopter log0036, a real event. A velocity
#: 50 m/s from both neighbours, which agree, is no vehicle's either (10 g over a 5 Hz GPS's 0.2 s is 20 m/s,
#: and it would not come back): a damaged MCAP chunk kept unverified gave one east velocity of -4e-225 m/s
#: among 148 m/s, and the velocity-matched alignment ingested it and did not converge.
#: how far (at least) an isolated sample stands from both neighbours to be dropped as a spike, per stream (a
#: position per column: latitude and longitude in deg, 0.01 deg = 1.1 km; altitude in m): beyond any motion
#: between two samples at a vehicle's rates, the size of a corrupt byte's jump (a flipped exponent bit in a
#: latitude doubles it), far above a GNSS fix's single-sample glitch (tens of m)
SPIKE_FLOOR = {"gyro": 10.0, "accel": 1000.0, "vel": 50.0, "pos": (0.01, 0.01, 1000.0)}
SPIKE_BACK = 0.25
SPIKE_UNIT = {"gyro": "rad/s", "accel": "m/s^2", "vel": "m/s", "pos": "deg (latitude, longitude) or m (altitude)"}
SPIKE_SIGMAS = 20.0


def impulsive(name: str, values: np.ndarray) -> np.ndarray:
    """True for the samples of a time-ordered stream ``values`` (N, k) that stand alone far from their
    neighbours (:data:`SPIKE_FLOOR` from both, :data:`SPIKE_SIGMAS` of the sample-to-sample scatter, the
    neighbours on either side agreeing); the first and last two samples are never. The usual stream has no
    sample this far from both neighbours, and costs two passes (0.02 s for 720 000 samples)."""
    v = np.asarray(values, dtype=float)
    n = len(v)
    out = np.zeros(n, dtype=bool)
    if n < 5:
        return out
    floor = np.asarray(SPIKE_FLOOR[name], dtype=float)
    if floor.ndim and floor.shape[0] != v.shape[1]:  # (a per-column floor for another layout: not checked)
        return out
    d = np.abs(np.diff(v, axis=0))
    cand = np.flatnonzero(np.any(np.minimum(d[:-1], d[1:]) > floor, axis=1)) + 1  # away from both neighbours
    cand = cand[(cand >= 2) & (cand <= n - 3)]
    if not len(cand):
        return out
    scale = 1.4826 * np.median(d, axis=0)  # the stream's sample-to-sample scatter
    nb = np.sort(np.stack([v[cand - 2], v[cand - 1], v[cand + 1], v[cand + 2]]), axis=0)
    res = np.abs(v[cand] - 0.5 * (nb[1] + nb[2]))  # from the median of two neighbours each side
    lo = np.minimum(np.abs(v[cand] - v[cand - 1]), np.abs(v[cand] - v[cand + 1]))
    back = np.abs(v[cand + 1] - v[cand - 1]) <= SPIKE_BACK * lo  # ... and the signal goes on past it
    out[cand[np.any((res > floor) & (res > SPIKE_SIGMAS * scale) & (lo > floor) & back, axis=1)]] = True
    return out


def implausible(name: str, values: np.ndarray) -> np.ndarray:
    """True for the rows of ``values`` (N, k) of stream ``name`` that no vehicle can produce: a component
    beyond LIMITS, a quaternion far from unit norm, or for positions a latitude beyond 90 deg, a longitude
    beyond 360 deg, an altitude beyond 1000 km. (Checked CHECK_ROWS rows at a time: the same answer
    without a full-size copy of the values.)"""
    values = np.asarray(values, dtype=float)
    if len(values) > CHECK_ROWS:
        return np.concatenate([implausible(name, values[i:i + CHECK_ROWS])
                               for i in range(0, len(values), CHECK_ROWS)])
    v = np.abs(values)
    if name in LIMITS:
        return np.any(v > LIMITS[name], axis=1)
    if name == "quat" and v.ndim == 2 and v.shape[1] == 4:  # a rotation is a unit quaternion (not zeros)
        with np.errstate(over="ignore", invalid="ignore"):  # (a damaged component: 1e300 -> norm inf)
            n = np.linalg.norm(v, axis=1)
        return ~np.isnan(n) & ~((n > 0.5) & (n < 2.0))  # a missing (NaN) row is not an impossible one
    if name == "pos" and v.ndim == 2 and v.shape[1] >= 3:
        return (v[:, 0] > 90.0) | (v[:, 1] > 360.0) | (v[:, 2] > 1.0e6)
    return np.zeros(len(v), dtype=bool)


def gap_warning(label: str, steps_ns: np.ndarray) -> str | None:
    """``label: N gap(s) in stamps, longest X s`` where steps of a stream's stamps (ns) exceed GAP_FACTOR
    typical steps (``conventions.typical_step_s``: a telemetry stream's bursts, two messages 9 ms apart
    every 0.47 s, are not 288 gaps); None where none does."""
    if len(steps_ns) < 2:
        return None
    big = steps_ns > GAP_FACTOR * typical_step(steps_ns)
    if not big.any():
        return None
    return f"{label}: {int(big.sum())} gap(s) in stamps, longest {steps_ns.max() * 1e-9:.3f} s"


def drop_stray(t_ns: np.ndarray, label: str, warnings: list[str], steps: np.ndarray | None = None) -> np.ndarray:
    """The samples to keep of sorted, unique stamps ``t_ns``: all but the stray ones (``not_stray``), which
    are said in ``warnings`` (prefixed with ``label``). ``steps``: ``np.diff(t_ns)`` when the caller has it."""
    keep = not_stray(t_ns, steps)
    if not keep.all():
        bad = t_ns[~keep]
        warnings.append(f"{label}{int((~keep).sum())} sample(s) with stray stamps dropped ({bad.min() * 1e-9:.3f} .. "
                        f"{bad.max() * 1e-9:.3f} s, isolated from the rest: a corrupt time field?)")
    return keep


def not_stray(t_ns: np.ndarray, steps: np.ndarray | None = None) -> np.ndarray:
    """False for samples in runs of at most max(STRAY_MAX_SAMPLES, STRAY_MAX_FRACTION of the samples up to
    STRAY_MAX_RUN) cut off from longer runs by steps longer than STRAY_GAP_S and STRAY_GAP_PERIODS median periods
    (``t_ns`` sorted, unique)."""
    keep = np.ones(len(t_ns), dtype=bool)
    small = max(STRAY_MAX_SAMPLES, min(STRAY_MAX_RUN, int(STRAY_MAX_FRACTION * len(t_ns))))
    if len(t_ns) <= small + 1:
        return keep
    d = np.diff(t_ns) if steps is None else steps
    thr = max(STRAY_GAP_S * 1e9, STRAY_GAP_PERIODS * float(np.median(d)))
    cut = np.flatnonzero(d > thr) + 1
    if not len(cut):
        return keep
    bounds = np.concatenate([[0], cut, [len(t_ns)]])
    sizes = np.diff(bounds)
    if sizes.max() <= small:
        return keep  # nothing but small runs: nothing to tell the stray ones by
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a <= small:
            keep[a:b] = False
    return keep


def build_inslog(
    *,
    path: str,
    fmt: str,
    selector: str,
    clock: str,
    stamp_source: str,
    gyro: Stream | None = None,
    accel: Stream | None = None,
    quat: Stream | None = None,
    vel: Stream | None = None,
    pos: Stream | None = None,
    warnings: list[str] | tuple[str, ...] = (),
    offset: ClockOffset | None = None,
) -> InsLog:
    """Assemble an InsLog. gyro/accel must share stamps if both are given on one stream (IMU
    message); otherwise accel is interpolated onto the gyro stamps (reported). quat is normalised
    and sign-continuous. ``offset``: a clock shift added once the stamps are cleaned (``ClockOffset``).
    Raises InputError when nothing usable is left."""
    streams = dict(gyro=gyro, accel=accel, quat=quat, vel=vel, pos=pos)
    del gyro, accel, quat, vel, pos
    return assemble_inslog(streams, path=path, fmt=fmt, selector=selector, clock=clock,
                           stamp_source=stamp_source, warnings=warnings, offset=offset)


def _unit_continuous_into(q: np.ndarray, rows: np.ndarray, at: np.ndarray | None) -> None:
    """``rows[:, at] = quat_make_continuous(quat_normalize(q)).T`` (``at`` None: every column), CHECK_ROWS
    quaternions at a time: the same numbers (normalised row by row, the hemisphere flips counted along
    the whole stream) without two full-size copies of the stream."""
    from logtools.conventions import quat_normalize

    n = len(q)
    prev = None  # the previous chunk's last normalised quaternion (before its flip)
    parity = 0
    for i in range(0, n, CHECK_ROWS):
        qn = quat_normalize(q[i:i + CHECK_ROWS])
        ext = qn if prev is None else np.concatenate([prev, qn])
        if len(ext) > 1:  # what quat_make_continuous does, the flips counted on from the chunk before
            dots = np.einsum("ij,ij->i", ext[1:], ext[:-1])
            flips = (parity + np.cumsum(dots < 0)) % 2
            parity = int(flips[-1])
            prev = qn[-1:].copy()
            if len(flips) == len(qn):  # a later chunk: its first row has a dot with the previous one
                qn[flips == 1] *= -1
            else:
                qn[1:][flips == 1] *= -1
        else:
            prev = qn[-1:].copy()
        if at is None:
            rows[:, i:i + len(qn)] = qn.T
        else:
            rows[:, at[i:i + len(qn)]] = qn.T
        del qn, ext


def _union_sorted(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.union1d of two sorted arrays of unique stamps (``a`` itself when ``b`` is in it)."""
    if b is a or len(b) == 0:
        return a
    if len(a) == len(b) and np.array_equal(a, b):
        return a
    at = np.searchsorted(a, b)
    if len(a) and np.all(at < len(a)) and np.array_equal(a[np.minimum(at, len(a) - 1)], b):
        return a
    c = np.concatenate([a, b])
    c.sort(kind="stable")  # two sorted runs: a merge
    return c[np.concatenate([[True], c[1:] != c[:-1]])]


def _shifted(cleaned: dict[str, Stream], offset: ClockOffset, clock: str, stamp_source: str, selector: str,
             warns: list[str]) -> tuple[dict[str, Stream], str, str, str]:
    """The cleaned streams with ``offset`` added (and the clock, stamp source, selector it gives), or as they
    are with a warning when it would put a stamp outside [EPOCH_MIN_NS, EPOCH_MAX_NS]. Checked in Python
    integers: the addition can never wrap (the stamps are inside +-STAMP_LIMIT_NS)."""
    lo = min(int(s.t_ns[0]) for s in cleaned.values()) + int(offset.ns)
    hi = max(int(s.t_ns[-1]) for s in cleaned.values()) + int(offset.ns)
    if not (EPOCH_MIN_NS <= lo and hi <= EPOCH_MAX_NS):
        warns.append(f"the offset onto the {offset.clock} clock ({int(offset.ns) * 1e-9:.3f} s) would put the "
                     f"stamps at {lo * 1e-9:.3f} .. {hi * 1e-9:.3f} s, outside UNIX time 1980..2100 (a corrupt "
                     f"time field?): kept on the {clock} clock")
        return cleaned, clock, stamp_source, selector
    out = {k: Stream(s.t_ns + int(offset.ns), s.values, s.source, s.stamp_resolution_s,
                     float(np.hypot(s.clock_sigma_s, offset.sigma_s)), int(offset.ns) + (s.clock_offset_ns or 0))
           for k, s in cleaned.items()}
    return out, offset.clock, offset.source, offset.selector


def assemble_inslog(streams: dict[str, Stream | None], *, path: str, fmt: str, selector: str, clock: str,
                    stamp_source: str, warnings: list[str] | tuple[str, ...] = (),
                    offset: ClockOffset | None = None) -> InsLog:
    """:func:`build_inslog` of the streams in ``streams`` (keys gyro, accel, quat, vel, pos; None or absent
    for none), taking them out of the dict as it goes: a stream's arrays go as soon as its columns are in
    the frame (a caller that keeps no other reference holds each sample about once)."""
    warns = list(warnings)
    _drop_joint_repeats(streams, warns)
    cleaned: dict[str, Stream] = {}
    step_part: dict = {}  # the part of the log kept at a clock step (the first stream with one decides)
    for k in ("gyro", "accel", "quat", "vel", "pos"):
        s = streams.pop(k, None)
        if s is None:
            continue
        c = clean_stream(k, s, warns, step_part)
        del s
        if len(c.t_ns):
            cleaned[k] = c
        del c
    streams.clear()
    if not cleaned:
        raise InputError("no usable samples in the selected streams", path)
    if offset is not None:
        cleaned, clock, stamp_source, selector = _shifted(cleaned, offset, clock, stamp_source, selector, warns)
    t0_ns = int(min(int(s.t_ns[0]) for s in cleaned.values()))
    channels: dict[str, ChannelInfo] = {}

    def rel(t_ns):
        return (np.asarray(t_ns, np.int64) - t0_ns) * 1e-9

    imu = Columns.empty()
    g, a = cleaned.pop("gyro", None), cleaned.pop("accel", None)
    base = g if g is not None else a
    if base is not None:
        t_imu = rel(base.t_ns)
        rate_imu = rate_of(t_imu)
        rows: list[tuple[tuple[str, ...], np.ndarray]] = []
        if g is not None:
            rows.append((GYRO, g.values))
            channels["gyro"] = ChannelInfo(rate_imu, len(t_imu), g.source, g.stamp_resolution_s, g.clock_sigma_s,
                                           g.clock_offset_ns)
        if a is not None:
            same = g is None or a.t_ns is g.t_ns or np.array_equal(a.t_ns, g.t_ns)
            if not same:
                ta = rel(a.t_ns)
                if len(ta) > 1:
                    rows.append((ACCEL, np.stack([np.interp(t_imu, ta, c, left=np.nan, right=np.nan)
                                                  for c in a.values.T], axis=-1)))
                    warns.append("accel interpolated onto gyro stamps (different stamps)")
                channels["accel"] = ChannelInfo(rate_of(ta), len(a.t_ns), a.source, a.stamp_resolution_s,
                                               a.clock_sigma_s, a.clock_offset_ns)
                del ta
            else:
                rows.append((ACCEL, a.values))
                channels["accel"] = ChannelInfo(rate_imu, len(a.t_ns), a.source, a.stamp_resolution_s, a.clock_sigma_s,
                                                a.clock_offset_ns)
        del g, a, base
        names = [n for group, _v in rows for n in group]
        block = np.empty((len(names), len(t_imu)))
        r = 0
        while rows:
            group, vals = rows.pop(0)
            block[r:r + len(group)] = vals.T
            r += len(group)
            del vals
        if ACCEL[0] in names and GYRO[0] in names:  # rows with a NaN accel (interpolated past its ends) go
            keep = ~np.isnan(block).any(axis=0)
            if not keep.all():
                block, t_imu = block[:, keep], t_imu[keep]
            del keep
        imu = Columns.from_block(t_imu, names, block)  # (the columns are its rows: no copy)
        del block, t_imu

    parts = [(key, names, cleaned.pop(key)) for key, names in (("quat", QUAT), ("vel", VEL), ("pos", POS))
             if key in cleaned]
    if parts:
        t_nav = parts[0][2].t_ns
        for _k, _n, s in parts[1:]:  # the sorted union of the stamps (an outer join of the parts)
            t_nav = _union_sorted(t_nav, s.t_ns)
        names = [n for _k, group, _s in parts for n in group]
        block = np.empty((len(names), len(t_nav)))  # rows written part by part (pages touched as they are)
        r = 0
        while parts:
            key, group, s = parts.pop(0)
            rows = block[r:r + len(group)]
            full = len(s.t_ns) == len(t_nav)  # a sorted unique subset as long as the union is the union
            at = None if full else np.searchsorted(t_nav, s.t_ns)
            if not full:
                rows.fill(np.nan)
            if key == "quat":
                _unit_continuous_into(s.values, rows, at)
            elif full:
                rows[:] = s.values.T
            else:
                rows[:, at] = s.values.T
            r += len(group)
            channels[{"quat": "att", "vel": "vel", "pos": "pos"}[key]] = ChannelInfo(
                rate_of(rel(s.t_ns)), len(s.t_ns), s.source, s.stamp_resolution_s, s.clock_sigma_s, s.clock_offset_ns)
            del s, rows, at
        nav = Columns.from_block(rel(t_nav), names, block)
        del block, t_nav
    else:
        nav = Columns.empty()
    meta = LogMeta(source_path=path, format=fmt, selector=selector, clock=clock, t0_ns=t0_ns,
                   stamp_source=stamp_source, channels=channels, warnings=tuple(warns))
    return InsLog(imu=imu, nav=nav, meta=meta)
