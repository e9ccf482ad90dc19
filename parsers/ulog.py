"""PX4 ULog (``.ulg``): sensor_combined / sensor_gyro+sensor_accel / vehicle_imu / vehicle_angular_velocity
+vehicle_acceleration (IMU), vehicle_attitude (attitude), vehicle_local_position (velocity, position via
its reference), vehicle_global_position (position).

Conventions: PX4 is FRD body / NED earth already and its quaternions are Hamilton ``q(w, x, y, z)``
rotating FRD -> NED (PX4 msg docs, VehicleAttitude), so no axis conversion is needed here. Stamps are
``timestamp`` (microseconds since boot): clock ``boot``. ``clock=epoch`` adds the boot -> UTC offset
found from GPS (``vehicle_gps_position`` / ``sensor_gps``: ``time_utc_usec - timestamp``, median over the
fixes whose UTC time is plausible and that agree with the majority; stray stamps are dropped on the boot
clock before it is added, and a log whose GPS time gives no trustworthy offset stays on the boot clock
with a warning).

Reading: pyulog is the reference implementation (tolerant of damage: skips bad messages, resyncs).
Clean files take a fast path: one compiled walk over the 3-byte message headers, then each wanted
topic's payloads are gathered into pyulog's own structured dtype (built by pyulog's classes from the
file's format messages) -- the same arrays pyulog returns, message for message, at a fraction of the
cost. Damage in the middle (an implausible message header) or a truncated tail is read past by the same
walk (:func:`walk_resyncing`: on where the headers chain again), as the native export rewrites it; what it
cannot judge (appended data, removed subscriptions, data before its subscription) sends the file to
pyulog; a data message of no subscription or of a wrong size is left out alone. The damage is reported as a warning.
Only the flag bits message at the spec's place, the first message after the header, is the file's (its unknown
incompatible flags refuse the file); a 'B' further on (bytes the walk resumed on after damage) is left out, named.

Selector keys: ``imu=`` (``sensor_combined`` | ``sensor_gyro[i]`` (pairs ``sensor_accel[i]``) |
``vehicle_imu[i]`` (delta angle / delta velocity over dt) | ``vehicle_angular_velocity[i]`` (pairs
``vehicle_acceleration[i]``)), ``att=`` (an attitude topic, e.g. ``vehicle_attitude``,
``estimator_attitude[1]``), ``vel=`` / ``pos=`` (``vehicle_local_position``, ``vehicle_global_position``),
``clock=boot|epoch|auto`` (default auto: epoch where the log's GPS UTC time gives the offset, else boot), ``time=timestamp|sample`` (``timestamp_sample`` where a topic has it); ``none``
drops a group.
"""
from __future__ import annotations

import contextlib
import io
import os
import re
import struct
from dataclasses import dataclass, replace

import numpy as np

from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers.assemble import ClockOffset, Stream, build_inslog
from parsers.atomic import atomic_path
from parsers.base import (DAMAGED_HEAD_SEARCH_BYTES, EPOCH_MAX_NS, STAMP_LIMIT_NS, Inventory, Selector, StreamInfo,
                          check_readable, consensus_offset, counts_to_ns, offset_sigma_s)

NAME = "ulog"
EXTENSIONS = (".ulg",)
MAGIC = b"ULog\x01\x12\x35"
SYNC_BYTES = b"\x2f\x73\x13\x20\x25\x0c\xbb\x12"

#: ULog message types
_T_FORMAT, _T_DATA, _T_INFO, _T_INFO_MULTI = ord("F"), ord("D"), ord("I"), ord("M")
_T_PARAM, _T_PARAM_DEFAULT, _T_ADD, _T_REMOVE = ord("P"), ord("Q"), ord("A"), ord("R")
_T_SYNC, _T_DROPOUT, _T_LOG, _T_LOG_TAGGED, _T_FLAGS = ord("S"), ord("O"), ord("L"), ord("C"), ord("B")
_KNOWN_TYPES = np.zeros(256, dtype=np.bool_)
for _t in "FDIMPQARSOLCB":
    _KNOWN_TYPES[ord(_t)] = True
#: pyulog's limit for a plausible message size
_MAX_MSG_SIZE = 10000

#: topics this module turns into InsLog streams, and their inventory kinds
IMU_TOPICS = ("sensor_combined", "vehicle_imu", "sensor_gyro", "vehicle_angular_velocity")
ACCEL_PARTNER = {"sensor_gyro": "sensor_accel", "vehicle_angular_velocity": "vehicle_acceleration"}
ATT_TOPICS = ("vehicle_attitude", "vehicle_attitude_groundtruth", "estimator_attitude",
              "external_ins_attitude")
VEL_TOPICS = ("vehicle_local_position", "vehicle_local_position_groundtruth", "estimator_local_position",
              "external_ins_local_position")
POS_TOPICS = ("vehicle_global_position", "vehicle_global_position_groundtruth", "estimator_global_position",
              "external_ins_global_position")
GPS_TOPICS = ("vehicle_gps_position", "sensor_gps")
KIND = {"sensor_combined": "imu", "vehicle_imu": "imu", "sensor_gyro": "gyro", "sensor_accel": "accel",
        "vehicle_angular_velocity": "gyro", "vehicle_acceleration": "accel",
        **{t: "att" for t in ATT_TOPICS}, **{t: "odom" for t in VEL_TOPICS},
        **{t: "pos" for t in POS_TOPICS}, **{t: "pos" for t in GPS_TOPICS}}
#: PX4's marker for an invalid relative timestamp (sensor_combined.accelerometer_timestamp_relative)
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF
#: a GPS UTC time later than 2001 (microseconds) counts as valid (earlier, 0 included: no fix yet) ...
_MIN_UTC_US = 1_000_000_000_000_000
#: ... up to 2100 (later: a corrupt field); a fix's boot stamp must be a possible one too
_MAX_UTC_US = EPOCH_MAX_NS // 1000
_MAX_STAMP_US = STAMP_LIMIT_NS // 1000


def sniff(head: bytes, path: str) -> bool:
    return head[:7] == MAGIC


#: consecutive plausible message headers (a format definition among them) that mark the messages' start there
DAMAGED_HEAD_CHAIN = 8
_FORMAT_TEXT = re.compile(rb"[A-Za-z_][A-Za-z0-9_]*:[a-z]")


def body_start(buf, search: int = DAMAGED_HEAD_SEARCH_BYTES) -> int | None:
    """Where the messages of a ULog whose header is damaged resume: the first offset from 16 on (within
    ``search`` bytes) from which DAMAGED_HEAD_CHAIN message headers follow one another plausibly (known
    type, size 1..10000, inside the file) and one of them is a format definition ("F", its text ``name:type
    ...``). None where there is no such offset: not a ULog's messages."""
    b = memoryview(buf).cast("B") if not isinstance(buf, (bytes, bytearray)) else buf
    n = len(b)
    for at in range(16, min(n - 3, 16 + search)):
        pos, chain, fmt = at, 0, False
        while chain < DAMAGED_HEAD_CHAIN and pos + 3 <= n:
            size, typ = b[pos] | (b[pos + 1] << 8), b[pos + 2]
            if size == 0 or size > _MAX_MSG_SIZE or not _KNOWN_TYPES[typ] or pos + 3 + size > n:
                break
            fmt = fmt or (typ == _T_FORMAT and _FORMAT_TEXT.match(bytes(b[pos + 3:pos + 3 + min(size, 64)])) is not None)
            chain += 1
            pos += 3 + size
        if chain >= DAMAGED_HEAD_CHAIN and fmt:
            return at
    return None


def magic_start(buf) -> int | None:
    """Where a ULog with bytes put before it (a transfer's garbage in front of the file) starts: the first
    offset within DAMAGED_HEAD_SEARCH_BYTES that holds its magic, a 16-byte header, and then messages that chain
    as :func:`body_start` wants them. None where there is none."""
    b = bytes(buf[:DAMAGED_HEAD_SEARCH_BYTES + len(MAGIC)])
    at = b.find(MAGIC, 1)
    while at >= 0:
        if body_start(buf[at:at + 16 + 4 * _MAX_MSG_SIZE], search=1) == 16:
            return at
        at = b.find(MAGIC, at + 1)
    return None


def repaired_head(buf: np.ndarray) -> tuple[np.ndarray, int] | None:
    """A ULog's bytes whose header is damaged, as they read: a header made anew (start time 0) before the
    messages from where they resume (:func:`body_start`), and that offset; None where they do not resume."""
    at = body_start(buf[:16 + DAMAGED_HEAD_SEARCH_BYTES + 4 * _MAX_MSG_SIZE])
    if at is None:
        return None
    return np.concatenate([np.frombuffer(MAGIC + bytes(9), np.uint8), buf[at:]]), at


def located(buf: np.ndarray) -> tuple[np.ndarray, int, str | None, int]:
    """A ULog's bytes as the reader and the export take them: (the bytes from its header on, what an offset into
    them adds to be the file's, how they were found, the offset in the file where they were). ``how``: None (a
    ULog at byte 0, or no ULog found: the bytes unchanged), "prefix" (bytes put before its magic and header:
    :func:`magic_start`), "repaired" (a damaged header: a header made anew before its messages, from where they
    resume: :func:`repaired_head`)."""
    if len(buf) < 16 or buf[:7].tobytes() == MAGIC:
        return buf, 0, None, 0
    at = magic_start(buf)
    if at is not None:
        return buf[at:], at, "prefix", at
    repaired = repaired_head(buf)
    if repaired is None:
        return buf, 0, None, 0
    out, at = repaired
    return out, at - 16, "repaired", at


def sniff_damaged(head: bytes, path: str) -> bool:
    """A ULog with bytes put before it (its magic and header further on: :func:`magic_start`), or whose first
    bytes (its magic among them) are damaged (its messages resume within the first bytes read: :func:`body_start`)."""
    return len(head) > 16 and head[:7] != MAGIC and (magic_start(head) is not None or body_start(head) is not None)


# ============================================================================================
# reading: topics as {field: array}, like pyulog's Data.data
# ============================================================================================
TopicKey = tuple[str, int]  # (topic name, multi_id)


@dataclass(frozen=True)
class ULogTopics:
    """The decoded topics of one file (only those asked for) and what was noticed on the way."""

    topics: dict[TopicKey, dict[str, np.ndarray]]
    info: dict[str, object]
    warnings: tuple[str, ...]
    engine: str  # "fast" or "pyulog"


def _walk(buf, start, known, max_size):  # pragma: no cover - compiled
    """Follow the chain of 3-byte headers from ``start``. Returns (offsets, sizes, types, end, status):
    status 0 = clean end of file, 1 = truncated last message, 2 = implausible header at ``end``."""
    n = buf.shape[0]
    count = 0
    pos = start
    status = 0
    while pos + 3 <= n:
        size = np.int64(buf[pos]) | (np.int64(buf[pos + 1]) << 8)
        typ = buf[pos + 2]
        if size == 0 or size > max_size or not known[typ]:
            status = 2
            break
        if pos + 3 + size > n:
            status = 1
            break
        count += 1
        pos += 3 + size
    if status == 0 and pos != n:
        status = 1
    end = pos
    offsets = np.empty(count, np.int64)
    sizes = np.empty(count, np.int64)
    types = np.empty(count, np.uint8)
    pos = start
    for i in range(count):
        size = np.int64(buf[pos]) | (np.int64(buf[pos + 1]) << 8)
        offsets[i] = pos
        sizes[i] = size
        types[i] = buf[pos + 2]
        pos += 3 + size
    return offsets, sizes, types, end, status


def _chain_at(buf, start, known, max_size, dsize, chain):  # pragma: no cover - compiled
    """The first offset from ``start`` on where ``chain`` message headers follow one another plausibly (known
    type, size 1..max_size inside the file; a data message of a subscribed id with that subscription's size,
    ``dsize[msg_id]``), or where fewer do and end exactly at the file's end; -1 where there is none."""
    n = buf.shape[0]
    for at in range(start, n - 2):
        pos = at
        k = 0
        while k < chain and pos + 3 <= n:
            size = np.int64(buf[pos]) | (np.int64(buf[pos + 1]) << 8)
            typ = buf[pos + 2]
            if size == 0 or size > max_size or not known[typ] or pos + 3 + size > n:
                break
            if typ == 68:  # 'D': msg_id, then the topic's fields
                if size < 2:
                    break
                mid = np.int64(buf[pos + 3]) | (np.int64(buf[pos + 4]) << 8)
                if dsize[mid] != size:
                    break
            k += 1
            pos += 3 + size
        if k >= chain or (k > 0 and pos == n):
            return at
    return -1


def _gather(buf, offsets, skip, itemsize):  # pragma: no cover - compiled
    """Copy ``itemsize`` bytes from ``buf[offsets[i] + skip]`` for every i into one contiguous array."""
    out = np.empty(offsets.shape[0] * itemsize, np.uint8)
    for i in range(offsets.shape[0]):
        s = offsets[i] + skip
        o = i * itemsize
        for j in range(itemsize):
            out[o + j] = buf[s + j]
    return out


def _scatter(out, rows, dst):  # pragma: no cover - compiled
    """out[dst[i]: dst[i] + rows.shape[1]] = rows[i] for every row."""
    w = rows.shape[1]
    for i in range(rows.shape[0]):
        d = dst[i]
        for j in range(w):
            out[d + j] = rows[i, j]


_COMPILED: dict[str, object] = {}


def _gather_np(buf, offsets, skip, itemsize):
    """numpy ``_gather`` (the reference code)."""
    idx = (np.asarray(offsets, np.int64) + skip)[:, None] + np.arange(itemsize)
    return buf[idx].reshape(-1)


def _scatter_np(out, rows, dst):
    """numpy ``_scatter`` (the reference code)."""
    out[np.asarray(dst, np.int64)[:, None] + np.arange(rows.shape[1])] = rows


def kernel(name: str):
    """``_walk`` / ``_gather`` / ``_scatter``: numba-compiled on first use (cached on disk) when this process
    runs compiled kernels (logtools.jit), else the reference code (numpy; the walk in plain Python over a
    memoryview)."""
    fn = _COMPILED.get(name)
    if fn is None:
        from logtools import jit

        if jit.compiled():
            fn = jit.njit(globals()[name])
        elif name in ("_walk", "_chain_at"):
            fn = (lambda f: lambda buf, *a: f(memoryview(buf), *a))(globals()[name])
        else:
            fn = {"_gather": _gather_np, "_scatter": _scatter_np}[name]
        _COMPILED[name] = fn
    return fn


#: consecutive plausible message headers (data messages of subscribed ids, of their size) after damage in the
#: middle of a ULog that mark where its messages resume (pyulog resumes at the next sync message, logged
#: about once a second: what lies before it was lost)
RESYNC_CHAIN = 8


def definitions(buf: np.ndarray, offsets: np.ndarray, sizes: np.ndarray, types: np.ndarray,
                errors: tuple[type[Exception], ...] = (KeyError, ValueError, IndexError, struct.error,
                                                       UnicodeDecodeError)
                ) -> tuple[dict[int, object], list[tuple[int, str]]]:
    """The subscriptions (message id -> pyulog's ``_MessageAddLogged``, the first of an id) that the format and
    subscription messages among (offsets, sizes, types) define, read with pyulog's classes, and (offset, error
    name) of those that do not read (``errors``)."""
    from pyulog import ULog

    header = ULog._MessageHeader()
    formats: dict[str, object] = {}
    subs: dict[int, object] = {}
    unreadable: list[tuple[int, str]] = []
    for i in np.flatnonzero((types == _T_FORMAT) | (types == _T_ADD)).tolist():
        o, sz = int(offsets[i]), int(sizes[i])
        header.msg_size, header.msg_type = sz, int(types[i])
        data = buf[o + 3:o + 3 + sz].tobytes()
        try:
            if types[i] == _T_FORMAT:
                fmt = ULog.MessageFormat(data, header)
                formats[fmt.name] = fmt
            else:
                add = ULog._MessageAddLogged(data, header, formats)
                subs.setdefault(add.msg_id, add)
        except errors as exc:
            unreadable.append((o, type(exc).__name__))
    return subs, unreadable


def walk_resyncing(buf: np.ndarray, byte_shift: int = 0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str], str | None]:
    """(offsets, sizes, types) of the messages the chain of headers reaches from byte 16, going on past damage:
    after an implausible header, at the first offset where RESYNC_CHAIN headers chain plausibly
    (:func:`_chain_at`; a data message must be of an id subscribed before the damage, with its size). The
    message just before each break is left out (its size may be what was damaged); a zero-filled tail and a
    truncated last message end the walk. Also the damage, in words at the file's offsets (``byte_shift``
    added), and the zero-filled tail's note (or None: no damage, the file ended so). One rule for the reader
    and the native export: the export keeps the file's structure, so reading it back resumes at the same
    places."""
    walk = kernel("_walk")
    parts, walked, damage = [], [], []  # (walked: each walk's messages, the one before its break among them)
    start = 16
    while True:
        offsets, sizes, types, end, status = walk(buf, start, _KNOWN_TYPES, _MAX_MSG_SIZE)
        end = int(end)
        broken = status == 2 and bool(buf[end:].any())  # (else nothing but zero bytes follow)
        if not broken:
            parts.append((offsets, sizes, types))
            tail = None
            if status == 1:
                damage.append(f"truncated last message at byte {end + byte_shift} of {len(buf) + byte_shift}")
            elif status == 2:
                tail = (f"zero-filled tail: the last {len(buf) - end} bytes (from byte {end + byte_shift}) hold no "
                        "messages (a preallocated file, or cut by a power loss)")
            return (*(np.concatenate([p[k] for p in parts]) for k in range(3)), damage, tail)
        # what a data message after the damage may be: the subscriptions before it
        walked.append((offsets, sizes, types))
        dsize = np.full(1 << 16, -1, np.int64)
        for msg_id, add in definitions(buf, *(np.concatenate([p[k] for p in walked]) for k in range(3)))[0].items():
            dsize[msg_id] = add.dtype.itemsize + 2
        at = int(kernel("_chain_at")(buf, end + 1, _KNOWN_TYPES, _MAX_MSG_SIZE, dsize, RESYNC_CHAIN))
        keep = max(len(offsets) - 1, 0)  # (the message before the break left out)
        parts.append((offsets[:keep], sizes[:keep], types[:keep]))
        cut = int(offsets[keep]) if keep < len(offsets) else end
        if at < 0:
            damage.append(f"implausible message header at byte {end + byte_shift}; no messages follow (bytes "
                          f"{cut + byte_shift}-{len(buf) - 1 + byte_shift} not read)")
            return (*(np.concatenate([p[k] for p in parts]) for k in range(3)), damage, None)
        damage.append(f"implausible message header at byte {end + byte_shift}; bytes {cut + byte_shift}-"
                      f"{at - 1 + byte_shift} skipped, the messages resume at byte {at + byte_shift}")
        start = at


class _Fallback(Exception):
    """The fast path met something only pyulog should judge (damage, appended data...)."""


def _read_fast(path: str, buf: np.ndarray, names: set[str] | None, byte_shift: int = 0,
               flags_here: bool = True) -> ULogTopics:
    """The topics by the compiled walk; ``byte_shift``: what a byte offset of ``buf`` adds to be the file's
    (a damaged header's repair, :func:`repaired_head`: the resume offset less the new header's 16 bytes).
    Only a flag bits message that is the first one after the header (byte 16; the ULog spec's place for it)
    is the file's: one further on is left out and named; ``flags_here`` False (a header made anew before
    messages resumed later than byte 16): none is."""
    from pyulog import ULog

    # damage in the middle: read on where the headers chain again (pyulog, byte by byte to the next sync
    # message, lost about a second at each place); a zero-filled tail (a file preallocated by the logger, an SD
    # card's zeroed blocks after a power loss) ends the messages, every one before it intact
    offsets, sizes, types, damage, tail = walk_resyncing(buf, byte_shift)
    warns = [f"damaged ULog: {n}" for n in damage] + ([tail] if tail else [])
    formats: dict[str, object] = {}
    subs: dict[int, object] = {}
    sub_at: dict[int, int] = {}  # file offset of each subscription
    info: dict[str, object] = {}
    misplaced: list[int] = []  # file offsets of flag bits messages not at byte 16
    header = ULog._MessageHeader()

    def payload(i: int) -> bytes:
        o, s = int(offsets[i]), int(sizes[i])
        return buf[o + 3:o + 3 + s].tobytes()

    for i in np.flatnonzero(types != _T_DATA):
        t = int(types[i])
        header.msg_size, header.msg_type = int(sizes[i]), t
        if t == _T_FORMAT:
            fmt = ULog.MessageFormat(payload(i), header)
            formats[fmt.name] = fmt
        elif t == _T_FLAGS:
            if i != 0 or int(offsets[0]) != 16 or not flags_here:
                # not at the spec's place (the first message after the header): no flag bits of this file, but
                # random bytes the walk resumed on after damage (or a writer's fault); they decide nothing
                misplaced.append(int(offsets[i]) + byte_shift)
                continue
            incompat = payload(i)[8:16]
            if any(incompat[1:]) or incompat[0] & ~1:
                raise InputError("ULog with unknown incompatible flags: cannot be read", path)
            if incompat[0] & 1:
                raise _Fallback("data appended")
        elif t == _T_ADD:
            add = ULog._MessageAddLogged(payload(i), header, formats)
            if add.msg_id in subs:
                raise _Fallback("message id subscribed twice")
            subs[add.msg_id] = add
            sub_at[add.msg_id] = int(offsets[i])
        elif t == _T_REMOVE:
            raise _Fallback("subscription removed")
        elif t == _T_INFO:
            msg = ULog._MessageInfo(payload(i), header)
            info[msg.key] = msg.value
    if misplaced:
        warns.append(f"damaged ULog: {len(misplaced)} flag bits message(s) not first after the header (at byte(s) "
                     f"{', '.join(map(str, misplaced[:5]))}) left out: only the first message's flags count")
    data_idx = np.flatnonzero(types == _T_DATA)
    d_off = offsets[data_idx]
    ids = buf[d_off + 3].astype(np.int64) | (buf[d_off + 4].astype(np.int64) << 8)
    # data messages of no subscription or not of its size: damaged bytes (a flipped id byte; read past a break)
    # or a writer's fault, left out alone (pyulog, which read such a file, resynchronised to the next sync
    # message); the native export copies them as they are, so its output reads the same
    want = np.full(1 << 16, -1, np.int64)
    for msg_id, add in subs.items():
        want[msg_id] = add.dtype.itemsize + 2
    odd = want[ids] != sizes[data_idx]
    if odd.any():
        bad_ids = np.unique(ids[odd])
        warns.append(f"damaged ULog: {int(odd.sum())} data message(s) of no subscription or of a wrong size left "
                     f"out (message id(s) {', '.join(map(str, bad_ids[:5].tolist()))})")
        data_idx, d_off, ids = data_idx[~odd], d_off[~odd], ids[~odd]
    topics: dict[TopicKey, dict[str, np.ndarray]] = {}
    for msg_id, add in subs.items():
        if names is not None and add.message_name not in names:
            continue
        mine = ids == msg_id
        if not mine.any():
            continue
        itemsize = add.dtype.itemsize
        if d_off[mine][0] < sub_at[msg_id]:
            raise _Fallback(f"data for {add.message_name} before its subscription")
        arr = kernel("_gather")(buf, d_off[mine], 5, itemsize).view(add.dtype)
        topics[(add.message_name, int(add.multi_id))] = {n: arr[n] for n in arr.dtype.names}
    n_drop = int(np.sum(types == _T_DROPOUT))
    if n_drop:
        drop_idx = np.flatnonzero(types == _T_DROPOUT)
        ms = sum(struct.unpack("<H", payload(i)[:2])[0] for i in drop_idx)
        warns.append(f"{n_drop} logging dropout(s), {ms} ms in total (PX4 logger buffer overruns)")
    return ULogTopics(topics, info, tuple(warns), "fast")


def _read_pyulog(path: str, names: set[str] | None, why: str = "", source: np.ndarray | None = None) -> ULogTopics:
    """pyulog's reading of ``path`` (or of ``source``, the file's bytes behind a header made anew)."""
    from pyulog import ULog
    from pyulog.core import ULogException

    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):  # pyulog prints its complaints
            ulog = ULog(path if source is None else io.BytesIO(source.tobytes()),
                        sorted(names) if names is not None else None, disable_str_exceptions=True)
    except ULogException as exc:
        raise InputError(f"not a readable ULog: {exc}", path) from None
    except (struct.error, ValueError, IndexError, KeyError, OverflowError) as exc:
        raise InputError(f"damaged ULog, unreadable: {type(exc).__name__}: {exc}", path) from None
    warns = []
    if why:
        warns.append(f"damaged ULog ({why}): read with pyulog, readable part used")
    if ulog.file_corruption:
        warns.append("pyulog detected file corruption: damaged messages skipped")
    said = sorted({ln.strip() for ln in out.getvalue().splitlines() if ln.strip()})
    warns.extend(f"pyulog: {s}" for s in said[:5])
    if ulog.dropouts:
        ms = sum(d.duration for d in ulog.dropouts)
        warns.append(f"{len(ulog.dropouts)} logging dropout(s), {ms} ms in total (PX4 logger buffer overruns)")
    topics = {(d.name, int(d.multi_id)): d.data for d in ulog.data_list}
    return ULogTopics(topics, dict(ulog.msg_info_dict), tuple(warns), "pyulog")


def read_topics(path: str, names: set[str] | None = None, *, engine: str = "auto") -> ULogTopics:
    """Decode the topics named in ``names`` (all when None). ``engine``: auto | fast | pyulog."""
    check_readable(path)
    if os.path.isdir(path):
        raise InputError("is a directory, not a ULog file", path)
    if engine == "pyulog":
        return _read_pyulog(path, names)
    buf = np.fromfile(path, dtype=np.uint8)
    if len(buf) < 16:
        raise InputError(f"truncated ULog: {len(buf)} bytes, header needs 16", path)
    # bytes put before the file: read from its header on; a damaged header: the messages read from where they
    # resume, behind a header made anew (in memory; the file is not touched), what lay before them (the flag
    # bits, the first definitions) lost. byte_shift: the read bytes' offsets as the file's in what is said
    buf, byte_shift, how, at = located(buf)
    head_note = None
    if how == "prefix":
        head_note = f"damaged: the first {at} bytes are not ULog (bytes put before its header); read from byte {at}"
    elif how == "repaired":
        head_note = (f"damaged header: the first {at} bytes are no ULog messages (bad magic bytes); read from byte "
                     f"{at}, where its messages resume")
    elif buf[:7].tobytes() != MAGIC:
        raise InputError("not a ULog file (bad magic bytes)", path)
    try:
        res = _read_fast(path, buf, names, byte_shift, flags_here=how != "repaired" or at == 16)
    except InputError:
        raise
    except _Fallback as why:
        if engine == "fast":
            raise InputError(f"fast ULog reader refused: {why}", path) from None
        res = _read_pyulog(path, names, str(why), source=buf if head_note else None)
    except (KeyError, ValueError, IndexError, struct.error, UnicodeDecodeError) as exc:
        if engine == "fast":
            raise InputError(f"fast ULog reader refused: {type(exc).__name__}: {exc}", path) from None
        res = _read_pyulog(path, names, f"definitions unreadable: {type(exc).__name__}",
                           source=buf if head_note else None)
    return replace(res, warnings=(head_note,) + res.warnings) if head_note else res


# ============================================================================================
# topics -> streams
# ============================================================================================
_TOPIC_RE = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?$")


def parse_topic(text: str, path: str) -> TopicKey:
    m = _TOPIC_RE.match(text.strip())
    if not m:
        raise InputError(f"bad topic {text!r} in selector (expected NAME or NAME[i])", path)
    return m.group(1), int(m.group(2) or 0)


def _fmt_key(key: TopicKey) -> str:
    """``name`` for instance 0, ``name[i]`` otherwise (both parse back with :func:`parse_topic`)."""
    return f"{key[0]}[{key[1]}]" if key[1] else key[0]


def _vec(d: dict[str, np.ndarray], fields: list[str]) -> np.ndarray:
    return np.stack([np.asarray(d[f], dtype=float) for f in fields], axis=1)


def _stamps_ns(d: dict[str, np.ndarray], use_sample: bool) -> tuple[np.ndarray, str]:
    """Checked us -> ns (a corrupt uint64 stamp becomes one assemble drops, never a wrapped one)."""
    if use_sample and "timestamp_sample" in d:
        return counts_to_ns(d["timestamp_sample"], 1000), "timestamp_sample"
    return counts_to_ns(d["timestamp"], 1000), "timestamp"


def _first_present(d: dict, *names: str) -> str | None:
    return next((n for n in names if n in d), None)


def _imu_streams(topics, key: TopicKey, use_sample: bool, path: str, warns: list[str]):
    name, inst = key
    d = topics[key]
    if name == "sensor_combined":
        t_ns, src = _stamps_ns(d, use_sample)
        gyro = Stream(t_ns, _vec(d, [f"gyro_rad[{i}]" for i in range(3)]), "sensor_combined.gyro_rad")
        acc = _vec(d, [f"accelerometer_m_s2[{i}]" for i in range(3)])
        rel = d.get("accelerometer_timestamp_relative")
        if rel is not None:
            rel = rel.astype(np.int64)
            ok = rel != RELATIVE_TIMESTAMP_INVALID
            if not ok.all():
                warns.append(f"sensor_combined: {int((~ok).sum())} accel samples with invalid relative stamp dropped")
            t_acc = t_ns[ok] + rel[ok] * 1000
            acc = acc[ok]
        else:
            t_acc = t_ns
        acc_stream = Stream(t_acc, acc, "sensor_combined.accelerometer_m_s2") if len(t_acc) else None
        return gyro, acc_stream, f"{src} (+accelerometer_timestamp_relative)"
    if name == "vehicle_imu":
        da = _vec(d, [f"delta_angle[{i}]" for i in range(3)])
        dv = _vec(d, [f"delta_velocity[{i}]" for i in range(3)])
        dt_a = np.asarray(d["delta_angle_dt"], float) * 1e-6
        dt_v = np.asarray(d["delta_velocity_dt"], float) * 1e-6
        ok_a, ok_v = dt_a > 0, dt_v > 0
        t_end = counts_to_ns(d["timestamp_sample"] if "timestamp_sample" in d else d["timestamp"], 1000)
        # an average over [t_end - dt, t_end] belongs to the middle of the interval
        t_a = t_end - np.round(dt_a * 0.5e9).astype(np.int64)
        t_v = t_end - np.round(dt_v * 0.5e9).astype(np.int64)
        gyro = Stream(t_a[ok_a], da[ok_a] / dt_a[ok_a, None], f"{_fmt_key(key)}.delta_angle/dt")
        acc = Stream(t_v[ok_v], dv[ok_v] / dt_v[ok_v, None], f"{_fmt_key(key)}.delta_velocity/dt")
        return gyro, acc, "timestamp_sample - dt/2 (interval mid-point of vehicle_imu deltas)"
    # sensor_gyro / vehicle_angular_velocity: x,y,z (older: xyz[3]); partner accel topic, same instance
    t_ns, src = _stamps_ns(d, use_sample)
    fields = ["x", "y", "z"] if "x" in d else [f"xyz[{i}]" for i in range(3)]
    gyro = Stream(t_ns, _vec(d, fields), _fmt_key(key))
    pkey = (ACCEL_PARTNER[name], inst)
    acc = None
    if pkey in topics:
        pd_ = topics[pkey]
        ta, _ = _stamps_ns(pd_, use_sample)
        fields = ["x", "y", "z"] if "x" in pd_ else [f"xyz[{i}]" for i in range(3)]
        acc = Stream(ta, _vec(pd_, fields), _fmt_key(pkey))
    else:
        warns.append(f"no {_fmt_key(pkey)} to pair with {_fmt_key(key)}: gyro only")
    return gyro, acc, src


def _att_stream(d, key: TopicKey, use_sample: bool) -> Stream:
    t_ns, _ = _stamps_ns(d, use_sample)
    return Stream(t_ns, _vec(d, [f"q[{i}]" for i in range(4)]), f"{_fmt_key(key)}.q")


def _flag(d, name: str, n: int) -> np.ndarray:
    return d[name].astype(bool) if name in d else np.ones(n, bool)


def _vel_stream(d, key: TopicKey, use_sample: bool, warns: list[str]) -> Stream | None:
    t_ns, _ = _stamps_ns(d, use_sample)
    ok = _flag(d, "v_xy_valid", len(t_ns)) & _flag(d, "v_z_valid", len(t_ns))
    if not ok.any():
        warns.append(f"{_fmt_key(key)}: velocity flagged invalid (v_xy_valid/v_z_valid) in all "
                     f"{len(t_ns)} samples: not used")
        return None
    if not ok.all():
        warns.append(f"{_fmt_key(key)}: {int((~ok).sum())} samples with invalid velocity dropped")
    return Stream(t_ns[ok], _vec(d, ["vx", "vy", "vz"])[ok], f"{_fmt_key(key)}.v[xyz]")


def local_to_llh(ref_lat_deg, ref_lon_deg, ref_alt_m, x_m, y_m, z_m) -> np.ndarray:
    """NED offsets from a reference point -> (lat_deg, lon_deg, alt_m) on the WGS84 ellipsoid's local
    radii (PX4 uses an azimuthal equidistant projection; the two agree to mm over km)."""
    from logtools.earth import radii_m

    lat0 = np.radians(np.asarray(ref_lat_deg, float))
    r_m, r_n = radii_m(lat0)
    lat = np.degrees(lat0 + np.asarray(x_m, float) / r_m)
    lon = np.asarray(ref_lon_deg, float) + np.degrees(np.asarray(y_m, float) / (r_n * np.cos(lat0)))
    return np.stack([lat, lon, np.asarray(ref_alt_m, float) - np.asarray(z_m, float)], axis=1)


def llh_to_local(ref_llh, llh) -> np.ndarray:
    """Inverse of :func:`local_to_llh`: (N, 3) lat/lon/alt -> NED offsets from ``ref_llh``."""
    from logtools.earth import radii_m

    lat0 = np.radians(ref_llh[0])
    r_m, r_n = radii_m(lat0)
    x = np.radians(llh[:, 0] - ref_llh[0]) * r_m
    y = np.radians(llh[:, 1] - ref_llh[1]) * r_n * np.cos(lat0)
    return np.stack([x, y, ref_llh[2] - llh[:, 2]], axis=1)


def _pos_stream(d, key: TopicKey, use_sample: bool, warns: list[str]) -> Stream | None:
    t_ns, _ = _stamps_ns(d, use_sample)
    if "lat" in d and "ref_lat" not in d:  # vehicle_global_position
        lat, lon = np.asarray(d["lat"], float), np.asarray(d["lon"], float)
        if np.issubdtype(d["lat"].dtype, np.integer):  # very old logs: degE7
            lat, lon = lat * 1e-7, lon * 1e-7
        return Stream(t_ns, np.stack([lat, lon, np.asarray(d["alt"], float)], axis=1), f"{_fmt_key(key)}.lat/lon/alt")
    # vehicle_local_position: reference + x, y, z
    ok = _flag(d, "xy_global", len(t_ns)) & _flag(d, "z_global", len(t_ns)) \
        & _flag(d, "xy_valid", len(t_ns)) & _flag(d, "z_valid", len(t_ns))
    if "ref_lat" not in d or not ok.any():
        warns.append(f"{_fmt_key(key)}: no valid global reference (xy_global/z_global): no position")
        return None
    if not ok.all():
        warns.append(f"{_fmt_key(key)}: {int((~ok).sum())} samples without global reference dropped")
    llh = local_to_llh(d["ref_lat"][ok], d["ref_lon"][ok], d["ref_alt"][ok], d["x"][ok], d["y"][ok], d["z"][ok])
    return Stream(t_ns[ok], llh, f"{_fmt_key(key)}.ref+x/y/z")


def _utc_offset(topics) -> tuple[int | None, str, list[str], str, float]:
    """(UTC - boot) offset in ns from GPS messages, its source, warnings, the problem ("" when the log has
    no GPS UTC time at all), and the offset's 1-sigma in s (``offset_sigma_s``: the readings' spread, the
    microseconds of time_utc_usec). The offset is the median over the fixes whose UTC time lies in 2001..2100
    and whose boot stamp is a possible one, kept to those agreeing with the majority (``consensus_offset``); a
    topic whose fixes have no majority gives none (None, and the problem says why)."""
    problems = []
    for name in GPS_TOPICS:
        for (n, inst), d in sorted(topics.items()):
            if n != name or "time_utc_usec" not in d:
                continue
            utc, ts = np.asarray(d["time_utc_usec"]), np.asarray(d["timestamp"])  # (uint64: compared as it is)
            fix = utc > _MIN_UTC_US  # earlier: no fix yet (0), not a corrupt one
            if not fix.any():
                continue
            ok = fix & (utc <= _MAX_UTC_US) & (ts < _MAX_STAMP_US) & (ts >= 0)
            label = f"{_fmt_key((n, inst))}.time_utc_usec"
            n_bad = int(fix.sum() - ok.sum())
            if not ok.any():
                problems.append(f"{label}: all {n_bad} fixes hold an impossible UTC time or boot stamp")
                continue
            diff = utc[ok].astype(np.int64) - ts[ok].astype(np.int64)  # (both in range: no wrap)
            agree, why = consensus_offset(diff, 1_000_000)
            if why:
                problems.append(f"{label}: {why}")
                continue
            if not agree.all():
                diff = diff[agree]
            n_bad += int((~agree).sum())
            off = int(np.median(diff))
            spread_ms = float(np.median(np.abs(diff - off))) * 1e-3
            warns = [f"GPS UTC offset spread {spread_ms:.1f} ms (median abs deviation)"] if spread_ms > 10 else []
            if n_bad:
                warns.append(f"{label}: {n_bad} of {int(fix.sum())} GPS fixes ignored for the boot->UTC offset "
                             "(an impossible UTC time or boot stamp, or inconsistent with the others: corrupt?)")
            return off * 1000, f"{label} (median of {len(diff)})", warns, "", offset_sigma_s(diff, 1_000_000, 1e-6)
    return None, "", [], "; ".join(problems), 0.0


def _utc_offset_ns(topics, path: str) -> tuple[int, str, list[str], float]:
    """(UTC - boot) offset in ns from GPS messages, its source, warnings and its 1-sigma (s); InputError when
    the log gives none (no GPS UTC time, or none to trust)."""
    off, src, warns, problem, sigma = _utc_offset(topics)
    if off is None:
        if problem:
            raise InputError(f"clock=epoch: the GPS UTC time gives no trustworthy boot->UTC offset ({problem})",
                             path)
        raise InputError("clock=epoch needs GPS time (vehicle_gps_position/sensor_gps time_utc_usec); "
                         "the log has none", path)
    return off, src, warns, sigma


def _default_topic(keys, candidates: tuple[str, ...], inst: int | None = None) -> TopicKey | None:
    """The stream a unit gets where no selector names one: of the candidate topics (in their order), instance
    ``inst`` where one has it (a second unit's IMU, vehicle_imu[1], goes with estimator_attitude[1]: the
    estimator running on it), else the first candidate's lowest instance."""
    if inst:
        for name in candidates:
            if (name, inst) in keys:
                return name, inst
    for name in candidates:
        insts = sorted(i for n, i in keys if n == name)
        if insts:
            return name, insts[0]
    return None


def _pick(topics, wanted: str | None, candidates: tuple[str, ...], path: str, what: str,
          inst: int | None = None) -> TopicKey | None:
    if wanted is not None:
        if wanted.lower() == "none":
            return None
        key = parse_topic(wanted, path)
        if key not in topics:
            have = ", ".join(_fmt_key(k) for k in sorted(topics)) or "nothing"
            raise InputError(f"no topic {_fmt_key(key)} in log for {what}= (has: {have})", path)
        return key
    return _default_topic(topics.keys(), candidates, inst)


def load(path: str, selector: Selector, *, engine: str = "auto") -> InsLog:
    known = {"imu", "att", "vel", "pos", "clock", "time"}
    bad = [k for k, _ in selector.items if k not in known]
    if bad:
        raise InputError(f"unknown selector key(s) {', '.join(bad)} for ULog (use imu=, att=, vel=, pos=, "
                         f"clock=, time=)", path)
    clock = (selector.get("clock") or "auto").lower()
    if clock not in ("boot", "epoch", "auto"):
        raise InputError(f"clock={clock}: ULog offers clock=boot or clock=epoch", path)
    timesel = (selector.get("time") or "timestamp").lower()
    if timesel not in ("timestamp", "sample"):
        raise InputError(f"time={timesel}: use time=timestamp or time=sample", path)
    use_sample = timesel == "sample"
    names = set(IMU_TOPICS) | set(ACCEL_PARTNER.values()) | set(ATT_TOPICS) | set(VEL_TOPICS) | set(POS_TOPICS)
    for k in ("imu", "att", "vel", "pos"):
        v = selector.get(k)
        if v and v.lower() != "none":
            names.add(parse_topic(v, path)[0])
    if clock in ("epoch", "auto"):
        names |= set(GPS_TOPICS)
    data = read_topics(path, names, engine=engine)
    topics = data.topics
    warns = list(data.warnings)
    chosen: list[str] = []

    gyro = acc = quat = vel = pos = None
    imu_src = "timestamp"
    k_imu = _pick(topics, selector.get("imu"), IMU_TOPICS, path, "imu")
    if k_imu is not None:
        if k_imu[0] not in IMU_TOPICS:
            raise InputError(f"imu={_fmt_key(k_imu)}: not an IMU topic (use one of {', '.join(IMU_TOPICS)})", path)
        gyro, acc, imu_src = _imu_streams(topics, k_imu, use_sample, path, warns)
        chosen.append(f"imu={_fmt_key(k_imu)}")
    # a unit whose IMU is a further instance takes the same instance of the other streams where the log has it
    inst = k_imu[1] if k_imu is not None and k_imu[1] > 0 else None
    k_att = _pick(topics, selector.get("att"), ATT_TOPICS, path, "att", inst)
    if k_att is not None:
        if not all(f"q[{i}]" in topics[k_att] for i in range(4)):
            raise InputError(f"att={_fmt_key(k_att)}: topic has no q[4] quaternion", path)
        quat = _att_stream(topics[k_att], k_att, use_sample)
        chosen.append(f"att={_fmt_key(k_att)}")
    k_vel = _pick(topics, selector.get("vel"), VEL_TOPICS, path, "vel", inst)
    if k_vel is not None:
        if "vx" not in topics[k_vel]:
            raise InputError(f"vel={_fmt_key(k_vel)}: topic has no vx/vy/vz", path)
        vel = _vel_stream(topics[k_vel], k_vel, use_sample, warns)
        if vel is not None or selector.get("vel"):
            chosen.append(f"vel={_fmt_key(k_vel)}")
    k_pos = _pick(topics, selector.get("pos"), POS_TOPICS + VEL_TOPICS, path, "pos", inst)
    if k_pos is not None:
        pos = _pos_stream(topics[k_pos], k_pos, use_sample, warns)
        if pos is not None or selector.get("pos"):
            chosen.append(f"pos={_fmt_key(k_pos)}")
    if gyro is None and quat is None and vel is None and pos is None:
        have = ", ".join(_fmt_key(k) for k in sorted(topics)) or "none of the known topics"
        raise InputError(f"no IMU, attitude, velocity or position topic in ULog (found: {have})", path)
    stamp = f"PX4 {imu_src if k_imu else ('timestamp_sample' if use_sample else 'timestamp')} (us since boot)"
    offset = None
    if clock in ("epoch", "auto"):
        if clock == "epoch":
            off_ns, src, w, off_sigma = _utc_offset_ns(topics, path)
        else:  # auto: UNIX time where the log's GPS gives it
            off_ns, src, w, problem, off_sigma = _utc_offset(topics)
            if problem:
                warns.append(f"GPS UTC time gives no trustworthy boot->UTC offset ({problem}): kept on the boot "
                             "clock")
        if off_ns is not None:
            warns.extend(w)
            # added by build_inslog once the stamps are cleaned on the boot clock (stray stamps gone), checked
            offset = ClockOffset(off_ns, f"{stamp} + boot->UTC offset from {src}, 1-sigma {off_sigma * 1e3:.2g} ms",
                                 ",".join(chosen + ["clock=epoch"]), sigma_s=off_sigma)
    if not selector:
        warns.append(f"no selector given: picked {','.join(chosen)}")
    elif inst:
        other = [f"{k}={_fmt_key(key)}" for k, key in (("att", k_att), ("vel", k_vel), ("pos", k_pos))
                 if key is not None and selector.get(k) is None and key[1] != inst]
        if other:  # (another unit's streams, maybe: said, with the way to leave them out)
            warns.append(f"imu={_fmt_key(k_imu)} is instance {inst}, but the log has no instance {inst} for "
                         f"{', '.join(other)}: filled in from that instance; give att=none,vel=none,pos=none "
                         "to leave them out")
    return build_inslog(path=path, fmt=NAME, selector=",".join(chosen),
                        clock="boot", stamp_source=stamp, gyro=gyro, accel=acc, quat=quat, vel=vel, pos=pos,
                        warnings=warns, offset=offset)


def inventory(path: str) -> Inventory:
    data = read_topics(path, None)
    streams = []
    for (name, inst), d in sorted(data.topics.items()):
        t = d["timestamp"].astype(np.int64) * 1e-6
        span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
        rate = (len(t) - 1) / span if span > 0 else 0.0  # mean rate: PX4 publishes irregularly
        streams.append(StreamInfo(name=_fmt_key((name, inst)), kind=KIND.get(name, "other"),
                                  count=len(t), rate_hz=rate, start_s=float(t[0]) if len(t) else 0.0,
                                  duration_s=float(t[-1] - t[0]) if len(t) else 0.0, clock="boot",
                                  fields=tuple(d.keys())))
    keys = set(data.topics)

    def nav_of(inst: int | None) -> list[str]:
        """The att/vel/pos selectors of a unit: those :func:`load` fills in for its IMU instance."""
        out = []
        for k, cands in (("att", ATT_TOPICS), ("vel", VEL_TOPICS), ("pos", POS_TOPICS)):
            key = _default_topic(keys, cands, inst)
            if key is not None:
                out.append(f"{k}={_fmt_key(key)}")
        return out

    nav = nav_of(None)
    selectors = []
    for name in IMU_TOPICS:
        for inst in sorted(i for m, i in keys if m == name):
            sel = [f"imu={_fmt_key((name, inst))}"]
            est = ("estimator_attitude", inst)
            if name == "vehicle_imu" and est in keys and sum(1 for m, _ in keys if m == "estimator_attitude") > 1:
                sel.append(f"att={_fmt_key(est)}")  # multi-EKF: the estimator running on this IMU
                sel += [s for s in nav_of(inst) if not s.startswith("att=")]
            else:
                sel += nav_of(inst)
            selectors.append(",".join(sel))
    if not selectors and nav:
        selectors.append(",".join(nav))
    notes = ["stamps: us since boot; PX4 data are FRD/NED already"]
    if any(n in GPS_TOPICS and "time_utc_usec" in d for (n, _), d in data.topics.items()):
        notes.append("GPS UTC time present: loaded on the epoch clock (UNIX time) by default, as analyze reports "
                     "it; clock=boot keeps boot time")
    return Inventory(path=path, format=NAME, streams=tuple(streams), selectors=tuple(selectors),
                     warnings=data.warnings, notes=tuple(notes))


# ============================================================================================
# writing: a minimal valid ULog (header, flag bits, formats, info, subscriptions, data)
# ============================================================================================
_SENSOR_COMBINED = [("uint64_t", "timestamp"), ("float[3]", "gyro_rad"), ("uint32_t", "gyro_integral_dt"),
                    ("int32_t", "accelerometer_timestamp_relative"), ("float[3]", "accelerometer_m_s2"),
                    ("uint32_t", "accelerometer_integral_dt"), ("uint8_t", "accelerometer_clipping"),
                    ("uint8_t", "gyro_clipping"), ("uint8_t", "accel_calibration_count"),
                    ("uint8_t", "gyro_calibration_count")]
_VEHICLE_ATTITUDE = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("float[4]", "q"),
                     ("float[4]", "delta_q_reset"), ("uint8_t", "quat_reset_counter")]
_VEHICLE_LOCAL_POSITION = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                           ("uint64_t", "ref_timestamp"), ("double", "ref_lat"), ("double", "ref_lon"),
                           ("float", "ref_alt"), ("float", "x"), ("float", "y"), ("float", "z"),
                           ("float", "vx"), ("float", "vy"), ("float", "vz"),
                           ("bool", "xy_valid"), ("bool", "z_valid"), ("bool", "v_xy_valid"),
                           ("bool", "v_z_valid"), ("bool", "xy_global"), ("bool", "z_global")]
_VEHICLE_GLOBAL_POSITION = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("double", "lat"),
                            ("double", "lon"), ("float", "alt")]
_VEHICLE_GPS_POSITION = [("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec"), ("int32_t", "lat"),
                         ("int32_t", "lon"), ("int32_t", "alt"), ("uint8_t", "fix_type")]
_NP = {"uint64_t": "<u8", "int64_t": "<i8", "uint32_t": "<u4", "int32_t": "<i4", "uint16_t": "<u2",
       "int16_t": "<i2", "uint8_t": "u1", "int8_t": "i1", "bool": "u1", "float": "<f4", "double": "<f8"}


def _format_msg(name: str, fields) -> bytes:
    body = (name + ":" + "".join(f"{t} {n};" for t, n in fields)).encode()
    return struct.pack("<HB", len(body), _T_FORMAT) + body


def _row_dtype(fields) -> np.dtype:
    """Header (size, type, msg_id) + the payload, packed (ULog has no alignment)."""
    parts = [("msg_size", "<u2"), ("msg_type", "u1"), ("msg_id", "<u2")]
    for t, n in fields:
        base, _, arr = t.partition("[")
        parts.append((n, _NP[base], (int(arr[:-1]),)) if arr else (n, _NP[base]))
    return np.dtype(parts)


def _info_msg(key: str, value: str) -> bytes:
    v = value.encode()
    k = f"char[{len(v)}] {key}".encode()
    body = struct.pack("<B", len(k)) + k + v
    return struct.pack("<HB", len(body), _T_INFO) + body


def write(path: str, log: InsLog, *, boot_start_s: float = 10.0, global_position: bool = True,
          gps_rate_hz: float = 5.0) -> None:
    """Write ``log`` as a minimal valid ULog (the topics of :func:`topics_of`)."""
    topics = topics_of(log, boot_start_s=boot_start_s, global_position=global_position, gps_rate_hz=gps_rate_hz,
                       path=path)
    with atomic_path(path) as tmp:
        encode(topics).tofile(tmp)


def topics_of(log: InsLog, *, boot_start_s: float = 10.0, global_position: bool = True, gps_rate_hz: float = 5.0,
              path: str = "") -> list["TopicRows"]:
    """The topics :func:`write` writes for ``log`` (``encode`` makes the file's bytes): sensor_combined
    (IMU), vehicle_attitude (quaternion), vehicle_local_position (velocity, and x/y/z with its global
    reference when the log has a position), vehicle_global_position (when ``global_position``). Stamps are
    microseconds since boot;
    a log on the epoch clock is written with boot time starting at ``boot_start_s`` and a
    vehicle_gps_position topic (``gps_rate_hz``) whose ``time_utc_usec`` restores the epoch clock
    (``clock=epoch``). Precision: float32 for IMU/attitude/velocity, float64 lat/lon, 1 us stamps."""
    t0_ns = int(log.meta.t0_ns)
    epoch = log.meta.clock == "epoch"
    if epoch:
        boot0_ns = int(round(boot_start_s * 1e9))
        start_s = min(log.span_s()[0], 0.0) if np.isfinite(log.span_s()[0]) else 0.0
        boot0_ns -= int(round(start_s * 1e9))
    else:
        boot0_ns = t0_ns

    def us(t_rel_s):
        ns = boot0_ns + np.round(np.asarray(t_rel_s, float) * 1e9).astype(np.int64)
        return np.round(ns / 1000.0).astype(np.int64)

    topics: list[TopicRows] = []

    def rows(name, fields, n):
        t = TopicRows.empty(name, fields, n)
        topics.append(t)
        return t.rows

    if log.has_gyro or log.has_accel:
        t = log.t_imu_s()
        r = rows("sensor_combined", _SENSOR_COMBINED, len(t))
        r["timestamp"] = us(t)
        if log.has_gyro:
            r["gyro_rad"] = log.gyro_rad_s()
        if log.has_accel:
            r["accelerometer_m_s2"] = log.accel_m_s2()
        else:  # PX4's way of saying "no accelerometer sample with this message"
            r["accelerometer_m_s2"] = np.nan
            r["accelerometer_timestamp_relative"] = RELATIVE_TIMESTAMP_INVALID
        if not log.has_gyro:
            r["gyro_rad"] = np.nan
        dt_us = np.round(np.diff(r["timestamp"].astype(np.int64), prepend=r["timestamp"][0]))
        r["gyro_integral_dt"] = r["accelerometer_integral_dt"] = np.clip(dt_us, 0, 2**31)
    if log.has_quat:
        t, q = log.quat_wxyz()
        r = rows("vehicle_attitude", _VEHICLE_ATTITUDE, len(t))
        r["timestamp"] = r["timestamp_sample"] = us(t)
        r["q"] = q
    tv, v = log.vel_ned_m_s() if log.has_vel else (np.zeros(0), np.zeros((0, 3)))
    tp, llh = log.lat_lon_alt() if log.has_pos else (np.zeros(0), np.zeros((0, 3)))
    if len(tv) or len(tp):
        t_all = np.union1d(tv, tp)
        r = rows("vehicle_local_position", _VEHICLE_LOCAL_POSITION, len(t_all))
        r["timestamp"] = r["timestamp_sample"] = us(t_all)
        if len(tv):
            iv = np.searchsorted(t_all, tv)
            r["vx"][iv], r["vy"][iv], r["vz"][iv] = v.T
            r["v_xy_valid"][iv] = r["v_z_valid"][iv] = 1
        if len(tp):
            ref = llh[0]
            ned = llh_to_local(ref, llh)
            ip = np.searchsorted(t_all, tp)
            r["ref_timestamp"] = us(tp[0])
            r["ref_lat"], r["ref_lon"], r["ref_alt"] = ref
            r["x"][ip], r["y"][ip], r["z"][ip] = ned.T
            r["xy_valid"][ip] = r["z_valid"][ip] = r["xy_global"][ip] = r["z_global"][ip] = 1
        if len(tp) and global_position:
            g = rows("vehicle_global_position", _VEHICLE_GLOBAL_POSITION, len(tp))
            g["timestamp"] = g["timestamp_sample"] = us(tp)
            g["lat"], g["lon"], g["alt"] = llh.T
    if epoch:
        a, b = log.span_s()
        tg = np.arange(a, b + 1e-9, 1.0 / gps_rate_hz) if np.isfinite(a) else np.zeros(0)
        g = rows("vehicle_gps_position", _VEHICLE_GPS_POSITION, len(tg))
        g["timestamp"] = us(tg)
        g["time_utc_usec"] = np.round((t0_ns + np.round(tg * 1e9).astype(np.int64)) / 1000.0).astype(np.int64)
        g["fix_type"] = 3
        if len(tp):
            lp = np.stack([np.interp(tg, tp, c) for c in llh.T], axis=1)
            g["lat"], g["lon"] = np.round(lp[:, 0] * 1e7), np.round(lp[:, 1] * 1e7)
            g["alt"] = np.round(lp[:, 2] * 1e3)
    if not topics:
        raise InputError("nothing to write (no IMU, attitude, velocity or position)", path)
    if not all(np.all(np.diff(t.rows["timestamp"].astype(np.int64)) >= 0) for t in topics):
        raise InputError("stamps go backwards: cannot write a ULog", path)
    return topics


@dataclass(frozen=True)
class TopicRows:
    """One topic instance to write: ULog field list [(type, name)], rows with the message header."""

    name: str
    fields: list
    rows: np.ndarray
    multi_id: int = 0

    @staticmethod
    def empty(name: str, fields: list, n: int, multi_id: int = 0) -> "TopicRows":
        arr = np.zeros(n, dtype=_row_dtype(fields))
        arr["msg_size"] = arr.dtype.itemsize - 3
        arr["msg_type"] = _T_DATA
        return TopicRows(name, fields, arr, multi_id)

    def stamps(self) -> np.ndarray:
        return self.rows["timestamp"].astype(np.int64)


@dataclass(frozen=True)
class _SyncRows:
    rows: np.ndarray
    at_us: np.ndarray

    def stamps(self) -> np.ndarray:
        return self.at_us.astype(np.int64)


def encode(topics: list[TopicRows], info: dict[str, str] | None = None,
           sync_interval_us: int = 1_000_000) -> np.ndarray:
    """The bytes of a ULog holding ``topics`` (msg ids assigned in order; data interleaved by timestamp),
    with a sync message every ``sync_interval_us`` of data time (as PX4 does) so that readers can
    resynchronise after damage (0: none)."""
    info = {"sys_name": "tapost", "ver_sw": "tapost-ulog-writer"} if info is None else info
    formats: dict[str, list] = {}
    for t in topics:
        if formats.setdefault(t.name, t.fields) != t.fields:
            raise ValueError(f"two different formats for topic {t.name}")
    for msg_id, t in enumerate(topics):
        t.rows["msg_id"] = msg_id
    n_data = len(topics)
    head = bytearray(MAGIC + bytes([1]))
    first_us = min((int(t.rows["timestamp"][0]) for t in topics if len(t.rows)), default=0)
    head += struct.pack("<Q", max(first_us, 0))
    flags = bytes(8) + bytes(8) + bytes(24)
    head += struct.pack("<HB", len(flags), _T_FLAGS) + flags
    for name, fields in formats.items():
        head += _format_msg(name, fields)
    for k, v in info.items():
        head += _info_msg(k, v)
    for msg_id, t in enumerate(topics[:n_data]):
        body = struct.pack("<BH", t.multi_id, msg_id) + t.name.encode()
        head += struct.pack("<HB", len(body), _T_ADD) + body
    stamped = [t.rows["timestamp"].astype(np.int64) for t in topics if len(t.rows)]
    if sync_interval_us > 0 and stamped:
        lo = min(int(s[0]) for s in stamped)
        hi = max(int(s[-1]) for s in stamped)
        sync = np.zeros(len(range(lo + sync_interval_us, hi, sync_interval_us)),
                        dtype=np.dtype([("msg_size", "<u2"), ("msg_type", "u1"), ("sync", "u1", (8,))]))
        sync["msg_size"], sync["msg_type"] = 8, _T_SYNC
        sync["sync"] = np.frombuffer(SYNC_BYTES, np.uint8)
        # sync messages sit between the data messages by their time (after data with the same stamp)
        topics = topics + [_SyncRows(sync, np.arange(lo + sync_interval_us, hi, sync_interval_us)[:len(sync)])]
    # interleave every topic's rows by timestamp (stable: topic order breaks ties), vectorised
    stamps = np.concatenate([t.stamps() for t in topics])
    widths = np.concatenate([np.full(len(t.rows), t.rows.dtype.itemsize, np.int64) for t in topics])
    order = np.argsort(stamps, kind="stable")
    starts_sorted = np.concatenate([[0], np.cumsum(widths[order])[:-1]]).astype(np.int64) + len(head)
    starts = np.empty_like(starts_sorted)
    starts[order] = starts_sorted
    out = np.empty(len(head) + int(widths.sum()), np.uint8)
    out[:len(head)] = np.frombuffer(bytes(head), np.uint8)
    k = 0
    for t in topics:
        n = len(t.rows)
        if n:
            kernel("_scatter")(out, np.ascontiguousarray(t.rows).view(np.uint8).reshape(n, t.rows.dtype.itemsize),
                     starts[k:k + n])
        k += n
    return out
