"""The slave on the master's clock, in its own ROS format: ROS 1 bags, ROS 2 bags, MCAP files.

Every message of the input is written, in its order, with only its time fields rewritten:

* the header stamp of every message whose type has a ``std_msgs/Header``: a Header as the first field
  (Imu, Odometry, NavSatFix, every ``*Stamped``...) is patched in place in the serialised bytes (its
  stamp is at bytes 4..12 of both a CDR payload, after the 4-byte encapsulation header, and a ROS 1
  payload, after the ``seq`` field), vectorised over all the messages of a topic; a type with Headers
  elsewhere (``tf2_msgs/TFMessage``, ``nav_msgs/Path``...) is deserialised, its Headers restamped and
  serialised again with rosbags. Zero stamps (unset) stay zero; every other byte is kept;
* the record time of every message (ROS 1 ``time`` of the message record, hence the chunk infos and
  index entries the writer derives from it; ROS 2 ``messages.timestamp`` and metadata.yaml start and
  duration; MCAP ``log_time`` and ``publish_time``, hence the statistics, chunk and message indexes).

Containers: a sound ROS 1 bag of uncompressed chunks is copied and its time fields rewritten where they lie
(record times, Header stamps, index entries, chunk infos: :func:`_restamp_bag1_in_place`). Other ROS 1 bags
and MCAP files (also the storage files of mcap-storage ROS 2 bags) go through the
vectorised writers of :mod:`parsers.ros_containers` (a numba kernel lays out the records of a chunk;
indexes, statistics and summary rebuilt from the new times): the ``rosbags``/``mcap`` per-message
writers took 4-7 times tapost's parse time.
Their output is checked against rosbags' AnyReader and the mcap readers in the tests. An MCAP input
whose messages all sit in whole chunks keeps its chunks (times patched in place, each chunk compressed
as it lies). sqlite3 ROS 2 bags: restamped at the byte level of the .db3 (:mod:`parsers.restamp_sqlite`),
else by ``rosbags.rosbag2.Writer`` (rows in one executemany). Schemas, channels, connection headers,
QoS, metadata, attachments and compression are the input's. The inputs are read by tapost's tolerant
scanners (what a damaged file still holds is written, the damage is named in
:attr:`RestampStats.damage`). See docs/export_ros.md.

Clocks: a message's shift is ``ClockShift.shift_ns`` at its instant on the slave's *analysis clock*
(the clock tapost read the slave on): its header stamp by default, the record time with ``time=log``
in the selector (or for a unit whose header stamps are all zero). The same shift is subtracted from
every time field of that message, so header and record times stay as far apart as they were and the
exported file read by tapost gives the compensated stamps (ns exact) whichever clock it is read on.
A message without a header stamp on the analysis clock gets the shift at its record time mapped to
the analysis clock (record time + the median header-minus-record offset of the unit's topics).
"""
from __future__ import annotations

import dataclasses
import json
import mmap
import os
import re
import shutil
import sqlite3
import struct
import tempfile

import numpy as np

from logtools.errors import InputError
from parsers import mcap_ros, rosbag1, rosbag2, threads
from parsers import ros_containers as rcw
from parsers import ros_common as rc
from parsers.atomic import atomic_folder, atomic_path, check_replaceable
from parsers.base import Selector, check_readable
from parsers.filemap import FileMap
from parsers.restamp import ClockShift, RestampStats, export_hugepages, get_bytes, mapped_copy

HEADER = "std_msgs/msg/Header"
#: a topic whose header stamps are this far from the unit's clock is on another clock
_SAME_CLOCK_NS = 10_000_000_000
_FIRST, _NESTED, _NONE = "first", "nested", "none"
#: an MCAP channel of JSON-encoded ROS-shaped messages of a type tapost reads (its header.stamp in the text)
_JSON = "json"
#: a JSON message's stamp object and its two numbers (ros_common.JSON_ALIASES' names): the digits are
#: replaced, every other byte of the text kept
_JSON_STAMP = re.compile(rb'"stamp"\s*:\s*\{[^{}]*\}')
_JSON_SEC = re.compile(rb'("(?:sec|secs)"\s*:\s*)(-?\d+)')
_JSON_NSEC = re.compile(rb'("(?:nanosec|nsec|nsecs)"\s*:\s*)(-?\d+)')


def _json_stamp_ns(payload: bytes) -> int:
    """The header stamp (ns) of a JSON-encoded message as the parser reads it; 0 where it has none."""
    try:
        msg = json.loads(payload)
        sec, nsec = rc.json_getpath(msg, "header.stamp.sec"), rc.json_getpath(msg, "header.stamp.nanosec")
        return int(sec) * 1_000_000_000 + int(nsec)
    except (ValueError, KeyError, IndexError, TypeError, UnicodeDecodeError):
        return 0


def _json_restamped(payload: bytes, new_ns: int) -> bytes | None:
    """The message's text with its header stamp's two numbers replaced by ``new_ns`` (every other byte kept);
    None where the text holds no single stamp object whose numbers are the header's."""
    sec, nsec = divmod(int(new_ns), 1_000_000_000)
    m = _JSON_STAMP.search(payload)
    if m is None or _JSON_STAMP.search(payload, m.end()) is not None:
        return None
    obj, n1 = _JSON_SEC.subn(lambda g: g.group(1) + str(sec).encode(), m.group(0))
    obj, n2 = _JSON_NSEC.subn(lambda g: g.group(1) + str(nsec).encode(), obj)
    out = payload[:m.start()] + obj + payload[m.end():]
    if n1 != 1 or n2 != 1 or _json_stamp_ns(out) != new_ns:
        return None
    return out


# ---- message types: where the Headers are --------------------------------------------------------
def _header_kind(typestore, msgtype: str) -> str:
    """``first``: one Header, the first field (stamp at bytes 4..12); ``nested``: Headers elsewhere;
    ``none``: no Header; ``unknown``: no definition."""
    defs = getattr(typestore, "fielddefs", {})
    if msgtype not in defs:
        return "unknown"
    fields = defs[msgtype][1]
    first = bool(fields) and fields[0][0] == "header" and int(fields[0][1][0]) == 2 and fields[0][1][1] == HEADER
    rest = mcap_ros._closure(typestore, {_ftype(f) for f in fields[1 if first else 0:]} - {None})
    if HEADER in rest:
        return _NESTED
    return _FIRST if first else _NONE


def _ftype(field) -> str | None:
    nt, detail = field[1]
    if int(nt) == 2:
        return detail
    if int(nt) in (3, 4) and int(detail[0][0]) == 2:
        return detail[0][1]
    return None


def _restamp_obj(obj, delta_ns: int) -> None:
    """Subtract ``delta_ns`` from every non-zero Header stamp inside a deserialised message."""
    if getattr(obj, "__msgtype__", "") == HEADER:
        st = obj.stamp
        t = int(st.sec) * 1_000_000_000 + int(st.nanosec)
        if t:
            t -= delta_ns
            if t < 0:
                raise ValueError("negative stamp")
            obj.stamp = type(st)(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
        return
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            _restamp_obj(v, delta_ns)
        elif isinstance(v, list) and v and dataclasses.is_dataclass(v[0]):
            for x in v:
                _restamp_obj(x, delta_ns)


# ---- the shift of every message ------------------------------------------------------------------
@dataclasses.dataclass
class _Stream:
    """One connection / channel / topic row."""

    topic: str
    msgtype: str
    encoding: str  # "ros1", "cdr" or another (payload then never touched)
    kind: str = _NONE


@dataclasses.dataclass
class _Msgs:
    """All messages in output order, payloads packed in one writable byte array."""

    conn: np.ndarray  # int64 index into the streams
    log_ns: np.ndarray  # int64 record times
    buf: np.ndarray  # uint8, writable
    starts: np.ndarray  # int64 payload offsets in buf
    lens: np.ndarray  # int64 payload lengths
    #: (n, 12) uint8: each payload's first 12 bytes (zeros past a shorter payload's end), gathered by the scan
    #: while its chunk was in the cache (:func:`_payload_heads`), where the Header stamps are read; None: read
    #: from ``buf``
    heads: np.ndarray | None = None
    #: where ``buf`` does not hold the payloads (an MCAP scan that streamed its chunks: ``buf`` is empty,
    #: ``starts`` count in the chunks one after another): the payloads the scan kept, by message (the first
    #: _UNIT_SAMPLE of each channel, what :func:`_unit` reads)
    kept: dict[int, bytes] | None = None

    def payload(self, i: int) -> bytes:
        if self.kept is not None:
            return self.kept[i]
        a = int(self.starts[i])
        return self.buf[a:a + int(self.lens[i])].tobytes()

    def views(self) -> list[memoryview]:
        mv = memoryview(self.buf)
        return [mv[a:a + n] for a, n in zip(self.starts.tolist(), self.lens.tolist())]

    def take(self, keep: np.ndarray) -> "_Msgs":
        if self.kept is not None:
            raise ValueError("_Msgs.take: the payloads are not in buf (a streamed scan)")
        return _Msgs(self.conn[keep], self.log_ns[keep], self.buf, self.starts[keep], self.lens[keep],
                     None if self.heads is None else self.heads[keep])


def _pack(conn: np.ndarray, log_ns: np.ndarray, parts: list) -> _Msgs:
    lens = np.fromiter(map(len, parts), np.int64, len(parts))
    buf = np.frombuffer(bytearray(b"".join(parts)), np.uint8)
    starts = np.cumsum(lens) - lens
    return _Msgs(np.asarray(conn, np.int64), np.asarray(log_ns, np.int64), buf, starts, lens)


#: messages of each stream whose payloads :func:`_unit` reads (as the readers plan a unit from a topic's first few)
_UNIT_SAMPLE = 20


def _unit(streams: list[_Stream], msgs: _Msgs, typestore, selector: str | None, path: str,
          where: list[np.ndarray], logs: list[np.ndarray]) -> tuple[set[str], str]:
    """The topics tapost reads the slave from (with ``selector``) and the time mode (header/log); ``where``:
    each stream's message indexes, ``logs`` their record times."""
    sel = Selector.parse(selector or "")
    mode = (sel.get("time") or "header").lower()
    topics: dict[str, rc.RawTopic] = {}
    for k, s in enumerate(streams):
        if s.msgtype in rc.SUPPORTED and s.encoding in mcap_ros.READ_ENCODINGS and s.topic not in topics:
            idx = where[k]
            topics[s.topic] = rc.RawTopic(s.topic, s.msgtype, s.encoding, logs[k],
                                          [msgs.payload(i) for i in idx[:_UNIT_SAMPLE].tolist()])
    raw = rc.RawLog(path=path, fmt="", topics=topics, typestore=typestore)
    try:
        plan, _ = rc.plan_unit(raw, sel)
    except InputError:
        if selector:
            raise
        return set(topics), mode
    unit = {t for t in (plan.imu, plan.gyro_odom, plan.att, plan.vel, plan.pos) if t}
    return unit, plan.time_mode


def _by_stream(conn: np.ndarray, n_streams: int) -> tuple[np.ndarray, list[slice], list[np.ndarray]]:
    """The messages in stream order (each stream's messages in their order), each stream's slice of it and
    its messages (``np.flatnonzero(conn == k)``). Gathered once into this order, each stream's columns are
    contiguous slices (no gather per stream and column)."""
    if n_streams <= 32:  # (a few streams: one comparison each, of 8-bit keys)
        small = conn.astype(np.uint8)
        where = [np.flatnonzero(small == k) for k in range(n_streams)]
        order = np.concatenate(where) if where else np.zeros(0, np.int64)
    else:
        order = np.argsort(conn, kind="stable")
        where = []
    ends = np.cumsum([len(w) for w in where] if where else np.bincount(conn, minlength=n_streams)).tolist()
    sls = [slice(a, b) for a, b in zip([0] + ends[:-1], ends)]
    return order, sls, where or [order[sl] for sl in sls]


def _without_far(streams: list[_Stream], msgs: _Msgs, what: str) -> tuple[_Msgs, list[str]]:
    """``msgs`` less the messages whose record time (``what``: the format's name for it) a damaged byte put
    more than a day from the others' (:func:`_far_times`; they cannot be shifted), but for those with a sound
    header stamp, whose record time is set anew from it (:func:`_far_repaired`); and what was done, said."""
    far = _far_times(msgs.log_ns)
    said: list[str] = []
    if not far.any():
        return msgs, said
    fixed = _far_repaired(streams, msgs, far)
    far &= ~fixed
    if fixed.any():
        said.append(f"{int(fixed.sum())} {what}(s) more than a day from the others' (damaged) set anew from their "
                    "header stamps")
    if far.any():
        msgs = msgs.take(~far)
        said.append(f"{int(far.sum())} message(s) with a damaged record time (more than a day from the others') "
                    "not in the output")
    return msgs, said


def _far_repaired(streams: list[_Stream], msgs: _Msgs, far: np.ndarray) -> np.ndarray:
    """Of the messages whose record time a damaged byte put far from the others (``far``), those with a sound
    header stamp: their record time set anew from it, in ``msgs.log_ns`` (the stamp less its stream's usual
    stamp - record time), as the parser, which reads header stamps, reads them. Returns their mask."""
    fixed = np.zeros(len(far), bool)
    for k, s in enumerate(streams):
        if s.kind != _FIRST or s.encoding not in ("ros1", "cdr"):
            continue
        idx = np.flatnonzero((msgs.conn == k) & (msgs.lens >= 12))
        if not len(idx) or not far[idx].any():
            continue
        stamp, _be = rcw.header_stamps(msgs.buf, msgs.starts[idx], s.encoding == "cdr")
        good = ~far[idx] & (stamp != 0)
        if good.sum() < 10:
            continue
        lo, hi = np.percentile(stamp[good], [1.0, 99.0])
        bad = far[idx] & (stamp >= lo - _FAR_NS) & (stamp <= hi + _FAR_NS)
        off = int(np.median(stamp[good] - msgs.log_ns[idx[good]]))
        msgs.log_ns[idx[bad]] = stamp[bad] - off
        fixed[idx[bad]] = True
    return fixed


def _apply(streams: list[_Stream], msgs: _Msgs, typestore, shift: ClockShift, selector: str | None,
           path: str, later: list | None = None) -> tuple[np.ndarray, _Msgs, list[str]]:
    """New record times; the payloads restamped (in ``msgs.buf``, in place); notes on what was left. With
    ``later`` (a list), the Header stamps of Header-first messages are not written but appended to it as one
    :class:`_StampPatch` (the MCAP writer writes them chunk by chunk, in its threads), unless the payloads
    are repacked (then written here).

    The columns are taken once in stream order (:func:`_by_stream`), where each stream is a slice; the
    medians and the shift are of the same numbers in any order, and the shift goes back to message order."""
    n = len(msgs.log_ns)
    order, sls, where = _by_stream(msgs.conn, len(streams))  # (``where``: each stream's messages)
    log_s = msgs.log_ns[order]  # record times in stream order
    unit, mode = _unit(streams, msgs, typestore, selector, path, where, [log_s[sl] for sl in sls])
    if mode != "log" and (done := _all_stamped(streams, msgs, unit, [sl.stop > sl.start for sl in sls], shift,
                                              later)) is not None:
        return done
    stamp_s = np.zeros(n, np.int64)  # header stamp of Header-first messages (0: none / unset), stream order
    #: stream -> (positions in stream order: a slice, or an index array where short payloads are left out,
    #: big endian)
    first: dict[int, tuple[slice | np.ndarray, np.ndarray]] = {}
    notes: list[str] = []
    buf = msgs.buf
    short = n > 0 and int(msgs.lens.min()) < 12  # (payloads too short for a Header, somewhere)
    for k, s in enumerate(streams):
        if s.kind != _FIRST or s.encoding not in ("ros1", "cdr") or sls[k].start == sls[k].stop:
            continue
        pos: slice | np.ndarray = sls[k]
        ok = msgs.lens[where[k]] >= 12 if short else None
        if ok is not None and not ok.all():
            notes.append(f"{s.topic}: {int((~ok).sum())} messages too short for a header; kept unchanged")
            pos = _positions(pos)[ok]
            if not len(pos):
                continue
        idx = order[pos]
        # (from the heads the scan gathered, where it did: one cache miss per message less)
        at, src = (idx * 12, msgs.heads.reshape(-1)) if msgs.heads is not None else (msgs.starts[idx], buf)
        stamp_s[pos], be = rcw.header_stamps(src, at, s.encoding == "cdr")
        first[k] = (pos, be)
    texts: dict[int, slice] = {}  # JSON-encoded streams: their slice (their stamps read from the text)
    for k, s in enumerate(streams):
        if s.kind == _JSON:
            stamp_s[sls[k]] = [_json_stamp_ns(msgs.payload(i)) for i in where[k].tolist()]
            texts[k] = sls[k]
    wild_s = np.zeros(n, bool)  # a header stamp far from its record's time: a damaged stamp, written unchanged
    if mode == "log":
        t_an_s = log_s.copy()
    else:
        d = stamp_s - log_s  # (each message's stamp - record time, int64 as the medians take it)
        exact = n > 0 and int(log_s.min()) >= 0 and int(stamp_s.min()) >= 0  # (then no wrap in ``d``)
        groups = [pos for pos, _be in first.values()] + list(texts.values())
        t_an_s = stamp_s if exact and _stamps_decide(d, stamp_s, groups, [streams[k].topic in unit
                                                     for k in list(first) + list(texts)]) else None
        if t_an_s is None:
            unit_d = [d[sl][stamp_s[sl] != 0] for k, sl in enumerate(sls) if streams[k].topic in unit]
            unit_d = [x for x in unit_d if len(x)]
            ref = int(np.median(unit_d[0] if len(unit_d) == 1 else np.concatenate(unit_d))) if unit_d else 0
            t_an_s = log_s + ref
            for pos in groups:
                h = _positions(pos)[stamp_s[pos] != 0]
                dh = d[h]
                if len(h) and abs(int(np.median(dh)) - ref) < _SAME_CLOCK_NS:
                    # (as the reader's stray-stamp policy, parsers.assemble: a stamp a day away from where its
                    # record puts it is a damaged field, not an instant: the record's time gives its shift)
                    far = _far_stamps(stamp_s, log_s, h, dh, ref, exact)
                    if far is not None:
                        wild_s[h[far]] = True
                        h = h[~far]
                    t_an_s[h] = stamp_s[h]
    delta_s = shift.shift_ns(t_an_s)
    delta = np.empty(n, np.int64)
    delta[order] = delta_s
    log = msgs.log_ns
    new_log = log - delta
    if n and int(new_log.min()) < 0:
        i = int(np.argmin(new_log))
        raise InputError(f"{streams[int(msgs.conn[i])].topic}: message {i} (record time {int(log[i]) * 1e-9:.3f} s) "
                         f"would get a negative record time from a {int(delta[i]) * 1e-9:.6g} s shift "
                         "(a damaged record time, or a latency larger than the stamps)", path)
    any_wild = bool(wild_s.any())
    if any_wild:
        notes.append(f"{int(wild_s.sum())} header stamp(s) more than a day from their record times (damaged?): "
                     "written unchanged, their records shifted by their record times")
    patch = _StampPatch.empty(n) if later is not None and first else None
    for k, (pos, be) in first.items():
        st = stamp_s[pos]
        keep = (st == 0) | wild_s[pos] if any_wild else st == 0  # (unset or damaged stamps: written unchanged)
        new = st - delta_s[pos]
        if keep.any():
            new = np.where(keep, st, new)
        if int(new.min()) < 0:
            j = int(np.argmin(new))
            raise InputError(f"{streams[k].topic}: the shift would make header stamps negative (message "
                             f"{int(order[pos][j])}: header stamp {int(st[j]) * 1e-9:.3f} s, shift "
                             f"{int(delta_s[pos][j]) * 1e-9:.6g} s)", path)
        if patch is not None:
            patch.put(order[pos], new, be)
        else:
            rcw.put_header_stamps(buf, msgs.starts[order[pos]], new, be)
    if texts:  # (message order, for the text rewrite below)
        stamp, wild = np.empty(n, np.int64), np.empty(n, bool)
        stamp[order], wild[order] = stamp_s, wild_s
        texts_idx = {k: where[k] for k in texts}
    else:
        texts_idx = {}
    grown: dict[int, bytes] = {}
    for k, idx in texts_idx.items():  # the stamp's digits replaced in the text (a longer number: repacked below)
        bad = 0
        for i in idx.tolist():
            if stamp[i] == 0 or wild[i]:
                continue
            new_ns = int(stamp[i]) - int(delta[i])
            if new_ns < 0:
                raise InputError(f"{streams[k].topic}: the shift would make header stamps negative (message {i})",
                                 path)
            out = _json_restamped(msgs.payload(i), new_ns)
            if out is None:
                bad += 1
            else:
                _new_payload(msgs, i, out, grown)
        if bad:
            notes.append(f"{streams[k].topic} (JSON): {bad} messages without one readable header stamp object; "
                         "written with their text unchanged (record times shifted)")
    for k, s in enumerate(streams):
        if s.kind == _NESTED and s.encoding in ("ros1", "cdr"):
            bad = 0
            des = typestore.deserialize_cdr if s.encoding == "cdr" else typestore.deserialize_ros1
            ser = typestore.serialize_cdr if s.encoding == "cdr" else typestore.serialize_ros1
            for i in np.flatnonzero(msgs.conn == k).tolist():
                try:
                    m = des(msgs.payload(i), s.msgtype)
                    _restamp_obj(m, int(delta[i]))
                    out = bytes(ser(m, s.msgtype))
                except ValueError as exc:
                    if str(exc) == "negative stamp":
                        raise InputError(f"{s.topic}: the shift would make header stamps negative", path) from None
                    bad += 1
                    continue
                except Exception:
                    bad += 1
                    continue
                _new_payload(msgs, i, out, grown)
            if bad:
                notes.append(f"{s.topic} ({s.msgtype}): {bad} messages do not deserialise; written with "
                             "their header stamps unchanged")
        elif s.kind == "unknown" and np.any(msgs.conn == k) and s.encoding in ("ros1", "cdr"):
            notes.append(f"{s.topic}: no definition of {s.msgtype}; payloads kept unchanged (record times shifted)")
    if grown:  # a re-serialised message of another length (e.g. CDR padding): repack
        if patch is not None:  # (the repacked payloads carry their new stamps)
            patch.write(buf, msgs.starts)
            patch = None
        parts = [grown[i] if i in grown else msgs.payload(i) for i in range(n)]
        msgs = _pack(msgs.conn, msgs.log_ns, parts)
    if patch is not None:
        later.append(patch)
    return new_log, msgs, notes


@dataclasses.dataclass
class _StampPatch:
    """Header stamps to write, by message (message order): ``on`` the messages that get one (None: every
    message), their ``new`` stamps (ns) in byte order ``be`` (as :func:`ros_containers.put_header_stamps`
    takes them)."""

    on: np.ndarray | None
    new: np.ndarray
    be: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "_StampPatch":
        return cls(np.zeros(n, bool), np.zeros(n, np.int64), np.zeros(n, bool))

    def put(self, idx: np.ndarray, new: np.ndarray, be: np.ndarray) -> None:
        self.on[idx], self.new[idx], self.be[idx] = True, new, be

    def write(self, buf: np.ndarray, starts: np.ndarray, sel: slice = slice(None), base: int = 0) -> None:
        """The stamps of messages ``sel`` (a slice of consecutive messages) written into their payloads, which
        lie at ``starts`` less ``base`` in ``buf``."""
        if self.on is None:
            at = starts[sel]
            rcw.put_header_stamps(buf, at - base if base else at, self.new[sel], self.be[sel])
            return
        i = np.flatnonzero(self.on[sel])
        if sel.start:
            i += sel.start
        rcw.put_header_stamps(buf, starts[i] - base if base else starts[i], self.new[i], self.be[i])


def _all_stamped(streams: list[_Stream], msgs: _Msgs, unit: set[str], present: list[bool], shift: ClockShift,
                 later: list | None) -> tuple[np.ndarray, _Msgs, list[str]] | None:
    """:func:`_apply` (header time mode) where every message is a Header-first one of one encoding with a set
    stamp that :func:`_stamps_decide` finds decisive (an IMU log's topics, as a rule): each message's time is
    its stamp, taken in message order, in one pass over the scan's heads, without the stream order and
    medians the general case needs; the same numbers. None where that does not hold, or where a time would
    become negative (the general case says which)."""
    n = len(msgs.log_ns)
    kinds = {(s.kind, s.encoding) for s, there in zip(streams, present) if there}
    if not n or len(kinds) != 1 or next(iter(kinds)) not in ((_FIRST, "ros1"), (_FIRST, "cdr")):
        return None
    if int(msgs.lens.min()) < 12 or not any(s.topic in unit for s, there in zip(streams, present) if there):
        return None
    cdr = next(iter(kinds))[1] == "cdr"
    if msgs.heads is not None:
        stamp, be = rcw.header_stamps(msgs.heads.reshape(-1), np.arange(0, 12 * n, 12, dtype=np.int64), cdr)
    else:
        stamp, be = rcw.header_stamps(msgs.buf, msgs.starts, cdr)
    log = msgs.log_ns
    if int(log.min()) < 0 or not _stamps_decide(stamp - log, stamp, [slice(0, n)], [True]):
        return None
    delta = shift.shift_ns(stamp)
    new_log = log - delta
    new = stamp - delta
    if int(new_log.min()) < 0 or int(new.min()) < 0:
        return None
    patch = _StampPatch(None, new, be)
    if later is not None:
        later.append(patch)
    else:
        patch.write(msgs.buf, msgs.starts)
    return new_log, msgs, []


def _stamps_decide(d: np.ndarray, stamp: np.ndarray, groups: list, in_unit: list[bool]) -> bool:
    """Whether every message's time is its Header stamp, as the medians of :func:`_apply` would decide, known
    without them: every message is in one of ``groups`` (the Header-first and JSON streams' positions;
    ``in_unit``: whether each is a unit topic) with a stamp (not 0), some unit stream has one, and all the
    stamps' ``d`` (stamp - record time, exact: no int64 wrap) lie within a span below both the same-clock
    limit and the damaged-stamp limit (less 1 ms each: the float64 medians' rounding). Each median, the unit's
    included, lies in that span, so every stream is on the unit's clock and no stamp is far from it."""
    n = len(d)
    if not any(in_unit) or sum(len(p) if isinstance(p, np.ndarray) else p.stop - p.start for p in groups) != n:
        return False
    lo, hi = None, None
    for pos in groups:
        st = stamp[pos]
        if not len(st) or not bool(st.all()):
            return False
        dd = d[pos]
        a, b = int(dd.min()), int(dd.max())
        lo, hi = (a, b) if lo is None else (min(lo, a), max(hi, b))
    return lo is not None and hi - lo < min(_SAME_CLOCK_NS, _FAR_NS - 1_000_000) - 1_000_000


def _positions(pos: slice | np.ndarray) -> np.ndarray:
    """A slice's positions as an index array (an index array as it is)."""
    return np.arange(pos.start, pos.stop) if isinstance(pos, slice) else pos


def _far_stamps(stamp: np.ndarray, log: np.ndarray, h: np.ndarray, dh: np.ndarray, ref: int,
                exact: bool) -> np.ndarray | None:
    """Of the messages ``h`` (``dh``: their stamp - record time, int64), those whose header stamp is more than
    _FAR_NS from where their record time and ``ref`` put it, as float64 arithmetic decides (the reader's
    policy); None where there is none. Where ``dh`` is exact (``exact``: stamps and record times >= 0, so no
    int64 wrap) and every ``dh`` is within _FAR_NS less 1 ms of ``ref``, there is none, decided without the
    float64 pass (its rounding of such nanosecond counts stays below 10 us)."""
    lim = _FAR_NS - 1_000_000
    if exact and bool(((dh >= ref - lim) & (dh <= ref + lim)).all()):
        return None
    far = np.abs(stamp[h].astype(float) - log[h].astype(float) - ref) > _FAR_NS
    return far if far.any() else None


def _new_payload(msgs: _Msgs, i: int, out: bytes, grown: dict[int, bytes]) -> None:
    """Message ``i``'s payload replaced by ``out``: in place where it has the same length, else kept in
    ``grown`` for the repack (a re-serialised message padded otherwise, a JSON stamp with more digits)."""
    if len(out) == msgs.lens[i]:
        msgs.buf[msgs.starts[i]:msgs.starts[i] + len(out)] = np.frombuffer(out, np.uint8)
    else:
        grown[i] = out


#: a record time this far outside the central 98 % of a file's record times is a damaged value
_FAR_NS = 86_400_000_000_000


def _far_times(t_ns: np.ndarray) -> np.ndarray:
    """The record times a damaged byte put far from the others (more than a day outside their central 98 %)."""
    if len(t_ns) < 10:
        return np.zeros(len(t_ns), bool)
    lo, hi = np.percentile(t_ns, [1.0, 99.0])
    return (t_ns < lo - _FAR_NS) | (t_ns > hi + _FAR_NS)


def _counts(streams: list[_Stream], conn: np.ndarray) -> dict[str, int]:
    out: dict[str, int] = {}
    for k, c in zip(*np.unique(conn, return_counts=True)):
        out[streams[int(k)].topic] = out.get(streams[int(k)].topic, 0) + int(c)
    return out


def _registered(typestore, msgtype: str, text: str, fmt: str) -> None:
    if not text or msgtype in typestore.fielddefs:
        return
    try:
        rc.register_msgdef(typestore, msgtype, text, fmt)
    except Exception:
        pass  # no definition: the payload is kept as it is (noted)


# ---- ROS 1 ---------------------------------------------------------------------------------------
class _Scan1(rosbag1._Scan):
    """tapost's ROS 1 scan, also keeping each connection's full header and the chunk compression."""

    def __init__(self):
        super().__init__(lambda topic, msgtype: True)
        self.fields: dict[int, dict[str, bytes]] = {}
        self.compression: str | None = None
        self.index_pos: int | None = None  # the bag header's (a cut bag's lies past ``size``)
        self.size = 0
        #: the vectorised runs' messages, not copied one by one: (container bytes, conn ids, times,
        #: payload starts, lengths, record starts, record time places); the record-by-record path still
        #: fills ``times``/``data``
        self.blocks: list[tuple[np.ndarray, ...]] = []
        #: top-level records, for the export in place (:func:`_restamp_bag1_in_place`): chunks (record start,
        #: data start, data end, compression), index data (record start, header length, end, the chunk
        #: before: its place in ``chunk_recs``), chunk infos (record start, header length, end)
        self.chunk_recs: list[tuple[int, int, int, str]] = []
        self.index_recs: list[tuple[int, int, int, int]] = []
        self.info_recs: list[tuple[int, int, int]] = []

        self._in_blocks = 0  # messages in ``blocks`` (counted after each chunk: not summed again each time)

    @property
    def count(self) -> int:
        return super().count + self._in_blocks

    def _keep(self, buf, arr, cid, t_ns, d0, lens, rec_at, t_at):
        if len(cid):
            self.blocks.append((arr, cid.copy(), t_ns, d0, lens, rec_at, t_at))
            self._in_blocks += len(cid)

    def messages(self, cids: list[int]) -> _Msgs:
        """Every message, connections numbered by their place in ``cids``, in the order of the input
        grouped by connection (the stable time sort of the caller then breaks ties by connection)."""
        ids = np.asarray(cids, np.int64)  # sorted: a connection's number is its place
        conn, log, seq, bufs, starts, lens = [], [], [], [], [], []
        base = n = 0
        placed: dict[tuple[int, int], int] = {}  # a container's bytes (the file's, a decompressed chunk's): once
        for arr, cid, t_ns, d0, ln, _rec, _t in self.blocks:
            key = (arr.__array_interface__["data"][0], len(arr))
            at = placed.get(key)
            if at is None:
                at = placed[key] = base
                bufs.append(arr)
                base += len(arr)
            conn.append(np.searchsorted(ids, cid))
            log.append(t_ns)
            seq.append(np.arange(n, n + len(cid)))
            starts.append(d0 + at)
            lens.append(ln)
            n += len(cid)
        rest = [(k, t, d) for k, c in enumerate(cids) for t, d in zip(self.times[c], self.data[c])]
        if rest:  # records read one by one (a header layout the vectorised path does not know)
            tail = _pack(np.array([r[0] for r in rest], np.int64), np.array([r[1] for r in rest], np.int64),
                         [r[2] for r in rest])
            conn.append(tail.conn), log.append(tail.log_ns), seq.append(np.arange(n, n + len(rest)))
            bufs.append(tail.buf), starts.append(tail.starts + base), lens.append(tail.lens)
        if not bufs:
            return _pack(np.zeros(0, np.int64), np.zeros(0, np.int64), [])
        conn_a, seq_a = np.concatenate(conn), np.concatenate(seq)
        group = np.lexsort((seq_a, conn_a))
        # the containers' bytes in one writable buffer: the file's own (uncompressed chunks) or a copy
        buf = bufs[0] if len(bufs) == 1 and bufs[0].flags.writeable else np.concatenate(bufs)
        return _Msgs(conn_a, np.concatenate(log), buf, np.concatenate(starts), np.concatenate(lens)).take(group)

    def connection(self, header, data):
        data = bytes(data)
        (cid,) = rosbag1._U32.unpack_from(header["conn"], 0)
        if cid not in self.conns:
            self.fields[cid] = rosbag1._fields(data)
        super().connection(header, data)

    def chunk(self, header, buf, d0, d1, where):
        comp = header.get("compression", b"none").decode("ascii", "replace")
        if self.compression is None:
            self.compression = comp
        self.chunk_recs.append((where, d0, d1, comp))
        super().chunk(header, buf, d0, d1, where)

    def in_file(self, cids: list[int], file: np.ndarray) -> tuple[_Msgs, np.ndarray, np.ndarray] | None:
        """Every message, in the file's order, its payload in ``file`` (a copy of the input's bytes), with
        where their records and record times lie in it; None unless every message was read where it lies in
        the input (uncompressed chunks of known record layouts)."""
        if any(self.times[c] for c in self.times) or not self.blocks:
            return None  # (records read one by one, or none)
        src = self.blocks[0][0]
        if len(src) != len(file) or any(b[0].__array_interface__["data"][0] != src.__array_interface__["data"][0]
                                        or len(b[0]) != len(src) for b in self.blocks):
            return None  # (a decompressed chunk's messages)
        cid, log_ns, starts, lens, rec_at, t_at = (np.concatenate([b[k] for b in self.blocks]) for k in range(1, 7))
        return _Msgs(np.searchsorted(np.asarray(cids, np.int64), cid), log_ns, file, starts, lens), rec_at, t_at


def _scan_rosbag1(path: str, fmap: FileMap) -> _Scan1:
    """The top-level record walk of :func:`parsers.rosbag1.read_raw` (same damage rules) with our scan, over
    ``path`` mapped read-only (``fmap``: the scan's messages view its pages)."""
    buf = fmap.buf
    scan = _Scan1()
    off, end = len(rosbag1.MAGIC), len(buf)
    if bytes(buf[:len(rosbag1.MAGIC)]) != rosbag1.MAGIC:  # (the parser's rules: the first chunk or connection)
        off = rosbag1.resync_top(buf, 0, end)
        if off is None:
            raise InputError("not a ROS 1 bag (magic '#ROSBAG V2.0' missing)", path)
        scan.warnings.append(f"the file does not start as a ROS 1 bag; read from the first chunk or connection "
                             f"record (byte {off}), the bytes before not in the output")
    good, floor = off, -1
    indexes = rosbag1.IndexCheck()  # (index records: checked as the parser does)
    while off < end:
        try:
            header, op, hlen, nxt = rosbag1.top_record(buf, off, end)  # (as the parser reads its records)
        except (rosbag1._Damage, struct.error) as exc:
            at = rosbag1.resume_top(buf, off, good, floor, end)  # (as the parser's walk goes on)
            if at is None:
                scan.warnings.append(f"{exc}; the rest is not in the output" if "truncated" in str(exc)
                                     else f"damaged at byte {off} ({exc}); the rest of the file is not in the output")
                break
            scan.warnings.append(f"damaged at byte {off} ({exc}); went on at the next chunk or connection record "
                                 f"(byte {at}), the bytes between not in the output")
            floor = off = at
            continue
        try:
            if op == bytes([rosbag1._OP_BAGHEADER]):
                (scan.index_pos,) = struct.unpack_from("<Q", header.get("index_pos", b"\0" * 8), 0)
            elif op == bytes([rosbag1._OP_CHUNK]):
                indexes.chunk_at(off, header)
                scan.chunk(header, buf, off + 8 + hlen, nxt, off)
            elif op in (bytes([rosbag1._OP_CONN]), bytes([rosbag1._OP_MSG])):
                scan.records(buf, off, nxt, "top level")
            elif op in (bytes([rosbag1._OP_INDEX]), bytes([rosbag1._OP_CHUNKINFO])):
                indexes.index_at(op, header, buf, off, off + 8 + hlen, nxt, scan.conns)
                if op == bytes([rosbag1._OP_INDEX]):
                    scan.index_recs.append((off, hlen, nxt, len(scan.chunk_recs) - 1))
                else:
                    scan.info_recs.append((off, hlen, nxt))
            else:
                raise rosbag1._Damage(f"unknown record op {op!r} at byte {off}")
        except (rosbag1._Damage, struct.error, KeyError, ValueError) as exc:
            scan.warnings.append(f"damaged: {exc}; its other messages are not in the output")
        good = off = nxt  # (its framing read: a later resynchronisation starts after it)
    if (said := indexes.said("the output's index is made from its chunks")) is not None:
        scan.warnings.append(said)
    scan.size = end
    return scan


class _NotInPlace(Exception):
    """A ROS 1 bag that cannot be restamped where its time fields lie (the reason in the text): written anew."""


def restamp_rosbag1(src: str, dst: str, shift: ClockShift, *, selector: str | None = None) -> RestampStats:
    """A ROS 1 bag with every message kept, header stamps and record times on the master's clock: a sound
    bag of uncompressed chunks copied and its time fields rewritten where they lie
    (:func:`_restamp_bag1_in_place`), any other (compressed chunks, damage) written anew by
    :func:`parsers.ros_containers.write_bag1` from what the scan read."""
    with export_hugepages():  # (its columns of message offsets, times and stamps, over the whole bag)
        return _restamp_rosbag1(src, dst, shift, selector)


def _restamp_rosbag1(src: str, dst: str, shift: ClockShift, selector: str | None) -> RestampStats:
    check_readable(src)
    with FileMap(src) as fmap:
        scan = None
        if _first_chunk_uncompressed(fmap.buf):
            try:
                with atomic_path(dst) as tmp:
                    copied = threads.beside(shutil.copyfile, src, tmp)  # (sendfile: in the kernel, beside the scan)
                    try:
                        scan = _scan_rosbag1(src, fmap)
                        if (scan.warnings or not all(c[3] == "none" for c in scan.chunk_recs)
                                or not scan.index_pos or scan.index_pos >= scan.size):
                            raise _NotInPlace("damage, compressed chunks or no index")
                        copied.result()
                        stats = _restamp_bag1_in_place(src, tmp, dst, scan, shift, selector)
                    finally:
                        threads.drain([copied])
                return stats
            except _NotInPlace:
                pass
        scan = scan or _scan_rosbag1(src, fmap)
        typestore, cids, streams = _bag1_streams(scan)
        msgs = scan.messages(cids)
        # (a record time a damaged byte moved, or a record the resynchronised walk read from damaged bytes)
        msgs, far_said = _without_far(streams, msgs, "record time")
        msgs = msgs.take(np.argsort(msgs.log_ns, kind="stable"))  # the bag's time order
        span = float(msgs.log_ns[-1] - msgs.log_ns[0]) * 1e-9 if len(msgs.log_ns) else None
        new_log, msgs, notes = _apply(streams, msgs, typestore, shift, selector, src)
        notes.extend(far_said)
        if not any("truncated" in w for w in scan.warnings):
            cut = rosbag1.index_past_end(scan.index_pos, scan.size, span)
            if cut:
                notes.append(cut + "; the output holds the part up to the cut")
        comp = scan.compression or "none"
        # (a bag with the topic only in the connection record's header: kept in the record header)
        fields = [{"topic": scan.conns[c][0].encode(), **scan.fields[c]} for c in cids]
        with atomic_path(dst) as tmp, open(tmp, "wb") as fh:
            rcw.write_bag1(fh, fields, cids, msgs, new_log, comp)
    return RestampStats(path=dst, format="rosbag1", how="tapost's vectorised ROS 1 bag writer (records as the "
                        "input's, chunk compression kept); Header stamps patched in the payload bytes "
                        "(nested Headers through rosbags (de)serialisation)",
                        records=len(new_log), records_by_type=_counts(streams, msgs.conn),
                        time_fields=_BAG1_TIME_FIELDS, damage=tuple(scan.warnings) + tuple(notes))


_BAG1_TIME_FIELDS = ("record time", "header.stamp", "chunk info start/end", "index entries")


def _bag1_streams(scan: _Scan1) -> tuple[object, list[int], list[_Stream]]:
    """(typestore with the bag's definitions, connection ids in order, their streams)."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.EMPTY)
    cids = sorted(scan.conns)
    streams = []
    base = None
    for cid in cids:
        topic, msgtype, msgdef = scan.conns[cid]
        _registered(typestore, msgtype, msgdef, "msg")
        base = mcap_ros.register_builtin(typestore, {msgtype}, "ros1", base)  # (a damaged definition: as the reader)
        streams.append(_Stream(topic, msgtype, "ros1", _header_kind(typestore, msgtype)))
    return typestore, cids, streams


def _first_chunk_uncompressed(buf) -> bool:
    """Whether the bag's first top-level records are its header and an uncompressed chunk (the export in place
    then copies the file while the scan reads it)."""
    try:
        off = len(rosbag1.MAGIC)
        for _ in range(2):
            header, op, _hlen, nxt = rosbag1.top_record(buf, off, len(buf))
            if op == bytes([rosbag1._OP_CHUNK]):
                return header.get("compression", b"none") == b"none"
            off = nxt
    except (rosbag1._Damage, struct.error):
        pass
    return False


def _restamp_bag1_in_place(src: str, tmp: str, dst: str, scan: _Scan1, shift: ClockShift,
                           selector: str | None) -> RestampStats:
    """The sound, uncompressed bag ``src``, copied byte for byte to ``tmp``, with its time fields rewritten in
    the copy (mapped): record times, Header stamps, index entries, chunk infos' start and end times; its
    chunks, record order, connections and index otherwise as they are. Writing the whole bag anew cost two
    to three times tapost's parse of it (a 1 h 200 Hz bag: 347 MB through the writer). _NotInPlace where
    a message's payload changes length (a nested Header re-serialised otherwise) or a record is not where
    the scan expects it."""
    # (every page is patched: its write faults taken in one call, in a thread while the patch reads)
    with mapped_copy(tmp, scan.size, populate_beside=True) as file:
        if file is None:  # (a file system that cannot map a file for writing, or the input changed size)
            raise _NotInPlace("the copy cannot be mapped, or is not the size the scan read")
        records, by_type, notes = _patch_bag1(file, src, scan, shift, selector)
        file = None  # (no array left viewing the map: it closes as the block ends)
    return RestampStats(path=dst, format="rosbag1", how="the input's bytes copied, only its time fields rewritten "
                        "where they lie (chunks, record order, connections and index kept); Header stamps "
                        "patched in the payload bytes (nested Headers through rosbags (de)serialisation)",
                        records=records, records_by_type=by_type, time_fields=_BAG1_TIME_FIELDS, damage=tuple(notes))


def _bag1_places(file: np.ndarray, off: int, hlen: int) -> dict[str, tuple[int, int]]:
    """Where each field value of the record header at ``file[off + 4:off + 4 + hlen]`` lies: name ->
    (byte, length)."""
    out: dict[str, tuple[int, int]] = {}
    at, end = off + 4, off + 4 + hlen
    while at < end:
        if at + 4 > end:
            raise _NotInPlace(f"record header at byte {off} cut")
        ln = int(file[at:at + 4].view("<u4")[0])
        field = file[at + 4:at + 4 + ln].tobytes()
        eq = field.find(b"=")
        if eq < 0 or at + 4 + ln > end:
            raise _NotInPlace(f"record header at byte {off} not of fields")
        out[field[:eq].decode("ascii", "replace")] = (at + 4 + eq + 1, ln - eq - 1)
        at += 4 + ln
    return out


def _bag1_index_entries(file: np.ndarray, scan: _Scan1) -> tuple[list, list, list]:
    """The entries of the bag's index data records (version 1, each after a chunk): where each lies in
    ``file``, the data start of its chunk, its connection id (as lists of arrays). The records whose headers
    are laid out as the first one's of their length (the same fields in the same order: a writer's records)
    are read together, column by column; any other one by one."""
    pos, base, want = [], [], []
    recs = np.asarray(scan.index_recs, np.int64).reshape(-1, 4)
    data0 = np.asarray([c[1] for c in scan.chunk_recs] or [0], np.int64)
    alone = np.zeros(len(recs), bool)
    for hlen in np.unique(recs[:, 1]).tolist():
        rows = np.flatnonzero(recs[:, 1] == hlen)
        off, nxt, ci = recs[rows, 0], recs[rows, 2], recs[rows, 3]
        places = _bag1_places(file, int(off[0]), hlen)
        head = get_bytes(file, off + 4, hlen)  # (n, hlen): each record's header
        layout = np.ones(hlen, bool)  # the bytes other than the field values: lengths, names, '='
        for at, ln in places.values():
            layout[at - int(off[0]) - 4:at - int(off[0]) - 4 + ln] = False
        same = (head[:, layout] == head[0, layout]).all(axis=1)
        alone[rows[~same]] = True
        rows, off, nxt, ci, head = rows[same], off[same], nxt[same], ci[same], head[same]
        if not len(rows):
            continue
        value = {}
        for name in ("count", "ver", "conn"):
            at, ln = places.get(name, (0, -1))
            if ln != 4:
                raise _NotInPlace(f"a record header's {name} field missing or not of 4 bytes")
            rel = at - int(off[0]) - 4
            value[name] = np.ascontiguousarray(head[:, rel:rel + 4]).view("<u4").ravel().astype(np.int64)
        count = value["count"]
        bad = (ci < 0) | (value["ver"] != 1) | (nxt - (off + 8 + hlen) != 12 * count)
        if bad.any():
            raise _NotInPlace(f"index data record at byte {int(off[np.argmax(bad)])} not of version 1 after a chunk")
        first = np.cumsum(count) - count
        k = np.arange(int(count.sum()), dtype=np.int64) - np.repeat(first, count)  # entry number in its record
        pos.append(np.repeat(off + 8 + hlen, count) + 12 * k)
        base.append(np.repeat(data0[np.maximum(ci, 0)], count))
        want.append(np.repeat(value["conn"], count))
    for off, hlen, nxt, ci in recs[alone].tolist():
        places = _bag1_places(file, off, hlen)
        count = _uint_field(file, places, "count")
        if ci < 0 or _uint_field(file, places, "ver") != 1 or nxt - (off + 8 + hlen) != 12 * count:
            raise _NotInPlace(f"index data record at byte {off} not of version 1 after a chunk")
        pos.append(off + 8 + hlen + 12 * np.arange(count, dtype=np.int64))
        base.append(np.full(count, scan.chunk_recs[ci][1], np.int64))
        want.append(np.full(count, _uint_field(file, places, "conn"), np.int64))
    return pos, base, want


def _uint_field(file: np.ndarray, places: dict[str, tuple[int, int]], name: str, size: int = 4) -> int:
    """The little-endian unsigned value (``size`` bytes: 4 or 8) of header field ``name`` (:func:`_bag1_places`)."""
    at, ln = places.get(name, (0, -1))
    if ln != size:
        raise _NotInPlace(f"a record header's {name} field missing or not of {size} bytes")
    return int(file[at:at + size].view("<u4" if size == 4 else "<u8")[0])


def _patch_bag1(file: np.ndarray, src: str, scan: _Scan1, shift: ClockShift,
                selector: str | None) -> tuple[int, dict[str, int], list[str]]:
    """The time fields of the bag copy ``file`` (writable) rewritten: (messages, per topic, notes)."""
    typestore, cids, streams = _bag1_streams(scan)
    got = scan.in_file(cids, file)
    if got is None:
        raise _NotInPlace("messages read one by one or from compressed chunks")
    msgs, rec_at, t_at = got
    msgs, far_said = _without_far(streams, msgs, "record time")
    if far_said:
        raise _NotInPlace("damaged record times")
    # (in the file's order, where the writer's path sorts them by record time: the same fields, patched in
    # the order they lie)
    new_log, out, notes = _apply(streams, msgs, typestore, shift, selector, src)  # (Header stamps, in ``file``)
    if out.buf is not file:
        raise _NotInPlace("a restamped payload changed length")
    times = rcw.bag1_times(new_log)
    if not rcw.patch_bag1_times(file, t_at, times):
        raise _NotInPlace("a record time field that is not 8 bytes")
    n = len(new_log)
    if n > 1 and not bool((rec_at[1:] > rec_at[:-1]).all()):  # (the scan's blocks are in the file's order)
        raise _NotInPlace("messages not in the file's order")
    # index data (ver 1): per connection and chunk, (time, offset of the record in the chunk's data) entries
    pos, base, want = _bag1_index_entries(file, scan)
    if pos:
        ids = np.asarray(cids, np.int64)  # (each entry's connection as the messages' number of it, -1: none)
        want_k = np.minimum(np.searchsorted(ids, np.concatenate(want)), len(ids) - 1)
        want_k[ids[want_k] != np.concatenate(want)] = -1
        if not rcw.patch_bag1_index(file, np.concatenate(pos), np.concatenate(base), rec_at, msgs.conn, want_k,
                                    times):
            raise _NotInPlace("an index entry that points at no message of its connection")
    # chunk infos: the first and last record time of each chunk
    chunks = {c[0]: (c[1], c[2]) for c in scan.chunk_recs}
    for off, hlen, _nxt in scan.info_recs:
        places = _bag1_places(file, off, hlen)
        span = chunks.get(_uint_field(file, places, "chunk_pos", 8))
        if span is None or _uint_field(file, places, "ver") != 1:
            raise _NotInPlace(f"chunk info record at byte {off} points at no chunk")
        a, b = np.searchsorted(rec_at, span)
        if a == b:
            raise _NotInPlace(f"chunk info record at byte {off}: its chunk holds no message")
        t = new_log[a:b]
        for name, value in (("start_time", int(t.min())), ("end_time", int(t.max()))):
            at, ln = places.get(name, (0, -1))
            if ln != 8:
                raise _NotInPlace(f"chunk info record at byte {off}: no 8-byte {name}")
            file[at:at + 8] = np.frombuffer(rcw._bag1_time(value), np.uint8)
    return n, _counts(streams, msgs.conn), notes


# ---- MCAP ----------------------------------------------------------------------------------------
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_OP = {"header": 1, "footer": 2, "schema": 3, "channel": 4, "message": 5, "chunk": 6, "message_index": 7,
       "attachment": 9, "metadata": 12, "data_end": 15}


def _map(buf, off: int) -> tuple[dict[str, str], int]:
    (n,) = _U32.unpack_from(buf, off)
    off += 4
    end = off + n
    out = {}
    while off < end:
        k, off = mcap_ros._string(buf, off)
        v, off = mcap_ros._string(buf, off)
        out[k] = v
    return out, end


class _McapScan:
    """Every record of an MCAP file that the output needs, in order; damage noted."""

    def __init__(self):
        self.profile, self.library = "", ""
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, tuple[str, str, int, dict]] = {}  # topic, encoding, schema, metadata
        self.cid: list[np.ndarray] = []
        self.log: list[np.ndarray] = []
        self.blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (bytes, payload starts, lengths)
        self.heads: list[np.ndarray] = []  # per block: its payloads' first 12 bytes (_payload_heads)
        self.whole: list[bool] = []  # per block: the records of one whole chunk (else a record or a cut chunk)
        self.file: np.ndarray | None = None  # the file's bytes (uncompressed chunks' blocks are views of it)
        #: (buffer, placement) the zstd chunks were decompressed into (their blocks are views of it), or None
        self.arena: tuple[np.ndarray, dict] | None = None
        self.extras: list[tuple[str, tuple]] = []  # ("attachment"|"metadata", args) in file order
        self.damage: list[str] = []
        self.compression: str | None = None
        self.chunk_size = 0
        #: the channel ids defined so far, as a mask over all 65536 (set as each is defined, checked per chunk)
        self.known = np.zeros(1 << 16, bool)
        #: False: a streamed scan (:func:`_scan_mcap` with ``keep=False``): the chunks' bytes are not kept,
        #: each block holds its size instead, ``spans`` its chunk record (None: not a whole chunk's) for the
        #: writer to inflate again, ``kept`` the payloads of each channel's first _UNIT_SAMPLE messages
        self.keep = True
        self.spans: list[tuple[int, int] | None] = []
        self.kept: dict[int, bytes] = {}
        self._left = np.full(1 << 16, _UNIT_SAMPLE, np.int32)  # (payloads still to keep, by channel)
        self._at: tuple[int, int] | None = None  # (the chunk record being walked)

    def schema(self, buf, off):
        (sid,) = _U16.unpack_from(buf, off)
        name, o = mcap_ros._string(buf, off + 2)
        enc, o = mcap_ros._string(buf, o)
        (n,) = _U32.unpack_from(buf, o)
        self.schemas.setdefault(sid, (name, enc, bytes(buf[o + 4:o + 4 + n])))

    def channel(self, buf, off):
        cid, sid = struct.unpack_from("<HH", buf, off)
        topic, o = mcap_ros._string(buf, off + 4)
        enc, o = mcap_ros._string(buf, o)
        meta, _ = _map(buf, o)
        self.channels.setdefault(cid, (topic, enc, sid, meta))
        self.known[cid] = True

    def records(self, buf, start: int, end: int, where: str, cut_ok: bool = False, whole_chunk: bool = False) -> int:
        arr = np.frombuffer(buf, np.uint8)
        m, cid, t, s, e, k, oop, ooff, onxt, err, eoff = mcap_ros._walk_kernel()(arr, start, end)
        if err and not (cut_ok and err != mcap_ros._E_OPCODE):
            raise mcap_ros._Damage(f"{where}: broken record at byte {eoff}", eoff)
        for op, off in zip(oop[:k].tolist(), ooff[:k].tolist()):
            (self.schema if op == _OP["schema"] else self.channel)(buf, off + 9)
        cid, s, e = cid[:m], s[:m], e[:m]
        known = self.known
        unknown = set(np.unique(cid[~known[cid]]).tolist()) if m and not known[cid].all() else set()
        if unknown:
            raise mcap_ros._Damage(f"{where}: messages for undefined channel(s) {sorted(unknown)}")
        self.cid.append(cid.copy())
        self.log.append(t[:m].copy())
        if self.keep:
            self.blocks.append((arr[start:end], s - start, e - s))
        else:
            self.blocks.append((end - start, s - start, e - s))
            self.spans.append(self._at if whole_chunk else None)
            self._keep_first(arr, cid, s, e)
        self.heads.append(_payload_heads(arr, s))
        self.whole.append(whole_chunk)
        return m

    def _keep_first(self, arr: np.ndarray, cid: np.ndarray, s: np.ndarray, e: np.ndarray) -> None:
        """The payloads of the block's messages (the last block's) among the first _UNIT_SAMPLE of their
        channel, kept."""
        left = self._left[cid]
        if not left.any():
            return
        at = self.count - len(cid)  # (the block's first message)
        for c in np.unique(cid[left > 0]).tolist():
            idx = np.flatnonzero(cid == c)[:int(self._left[c])]
            for j in idx.tolist():
                self.kept[at + j] = arr[s[j]:e[j]].tobytes()
            self._left[c] -= len(idx)

    @property
    def count(self) -> int:
        return int(sum(len(c) for c in self.cid))

    def chunk(self, buf, off: int, nxt: int, chunks=None) -> None:
        _t0, _t1, usize, _crc = struct.unpack_from("<QQQI", buf, off + 9)
        comp, _o = mcap_ros._string(buf, off + 9 + 28)
        if self.compression is None:
            self.compression, self.chunk_size = comp, usize
        self._at = (off, nxt)
        try:
            content = chunks.get((off, nxt)) if chunks is not None else mcap_ros.inflate_chunk(buf, off, nxt)
        except mcap_ros._Undecodable as exc:  # the complete messages before the damaged block are kept
            got = self.partial_chunk(buf, off, nxt)
            if not got:
                raise
            self.damage.append(f"damaged: {exc}; the {got} complete messages before the damage kept, the rest "
                               "of the chunk not in the output")
            return
        except mcap_ros._BadCrc as exc:  # as the parser reads it (the part it keeps: unverified)
            content, said = mcap_ros.crc_damage_content(exc, buf, nxt)
            self.damage.append(f"damaged: {exc}; {said}, written as they decompressed, the chunk's CRC computed "
                               "anew")
        n = len(self.cid)
        try:  # a damaged record: the sound records around it kept, as the parser keeps them
            places, skipped, first = mcap_ros.walk_resyncing(
                lambda b, a, e, w: self.records(b, a, e, w, whole_chunk=True), content, len(content),
                f"chunk at byte {off}", self.channels, (int(_t0), int(_t1)))
        except (mcap_ros._Damage, struct.error, UnicodeDecodeError):
            del self.cid[n:], self.log[n:], self.blocks[n:], self.whole[n:], self.heads[n:]
            raise
        if places:
            self.whole[n:] = [False] * (len(self.whole) - n)  # (its records are laid out anew)
            self.damage.append(f"damaged: chunk at byte {off}: {places} damaged place(s) (first at byte {first} "
                               f"of its records), {skipped} bytes skipped to the next readable record; those "
                               "bytes not in the output")

    def partial_chunk(self, buf, off: int, end: int) -> int:
        """The complete messages of a cut or part-way damaged chunk (:func:`ros_common.inflate_prefix`)."""
        n = len(self.cid)
        try:
            comp, o = mcap_ros._string(buf, off + 9 + 28)
            content = rc.inflate_prefix(comp, buf[o + 8:end])
            return self.records(content, 0, len(content), f"partial chunk at byte {off}", cut_ok=True)
        except Exception:
            del self.cid[n:], self.log[n:], self.blocks[n:], self.whole[n:], self.heads[n:]
            return 0


def _payload_heads(arr: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(m, 12) uint8: the 12 bytes from each of ``s`` (payload starts in ``arr``), where a Header's stamp lies
    (bytes 4..12; byte 1: CDR's byte order). Taken as the scan walks each chunk (its bytes in the cache): read
    later, each message's stamp was a cache miss, 0.05-0.09 s of a 1 h export. A payload shorter than 12
    bytes gets what follows it (or zeros): such a message has no Header (:func:`_apply` skips it)."""
    if len(arr) < 12:
        return np.zeros((len(s), 12), np.uint8)
    return get_bytes(arr, np.minimum(s, len(arr) - 12), 12)  # (a cut chunk's inflated bytes: read-only)


def _private_map(path: str) -> np.ndarray:
    """The file's bytes as a private, writable, copy-on-write map (``mmap.ACCESS_COPY``): what is written
    to it stays in this process (the file is never changed), and only the pages written are copied. A 1 h
    zstd MCAP file's bytes were read into a copy before anything else could start (0.05 s of 78 MB), of
    which the export patches nothing (its compressed chunks are inflated elsewhere)."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if not size:
            return np.zeros(0, np.uint8)
        try:
            return np.frombuffer(mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_COPY), np.uint8)
        except (OSError, ValueError):  # (a file that cannot be mapped: read into a copy)
            return np.fromfile(fh, np.uint8)


def _scan_mcap(path: str, keep: bool = True) -> _McapScan:
    """Every record of the MCAP file ``path`` the export needs (:class:`_McapScan`). ``keep=False``: where
    every chunk is zstd (as :func:`mcap_ros.chunk_arena` plans them), a streamed scan, which keeps each
    chunk's bytes only while it walks them (``sc.keep`` says which it was)."""
    check_readable(path)
    file = _private_map(path)  # (uncompressed chunks are patched in it: the file's pages copied where written)
    buf = memoryview(file)
    sc = _McapScan()
    if bytes(buf[:len(mcap_ros.MAGIC)]) != mcap_ros.MAGIC:
        if mcap_ros.footer_start(buf) is None:
            raise InputError("not an MCAP file (bad magic)", path)
        moved = mcap_ros.records_shift(buf)  # (the parser's rule: where the records are against the offsets)
        h = len(mcap_ros.MAGIC) + moved
        if moved < 0:
            raise InputError(f"damaged: the file's start is cut ({-moved} bytes fewer than its offsets count); "
                             "the native export rewrites a file whose records are where its offsets say (the "
                             "CSV and Parquet exports write what the parser read)", path)
        if moved > 0:  # bytes put before the records: the output is the file without them
            file = file[moved:]
            buf = memoryview(file)
            sc.damage.append(f"the file's first {h} bytes are not MCAP's start; its records, {moved} bytes on, are "
                             "written without the bytes before them, the output starting with a valid magic")
        else:
            sc.damage.append("the file's first 8 bytes are not MCAP's magic (its footer is); read on from byte 8, "
                             "the output starts with a valid magic")
    sc.file = file
    off, end = len(mcap_ros.MAGIC), len(buf)
    footer = False
    inner = mcap_ros.inner_shift(buf)  # (bytes put in or lost inside: the parser's rule)
    if inner:
        sc.damage.append(f"the summary section is {inner:+d} bytes from where the footer says (bytes put in or "
                         "lost inside the file): the chunks after the damage read at the summary's offsets moved by "
                         "as much")
    elif (head := mcap_ros.summary_damaged_head(buf)) is not None:
        sc.damage.append(f"the summary section does not read from byte {head[0]} to byte {head[1]} (bytes "
                         "overwritten); the output's summary is written anew")
    elif (said := mcap_ros.summary_crc_damage(buf)) is not None:
        sc.damage.append(f"{said}: {mcap_ros.SUMMARY_UNUSED}; the output's summary is written anew")
    for op, at, _nxt in mcap_ros.summary_definitions(buf, inner):  # channels known even if their chunk is damaged
        try:
            (sc.schema if op == _OP["schema"] else sc.channel)(buf, at + 9)
        except (mcap_ros._Damage, struct.error, UnicodeDecodeError):
            pass
    starts = mcap_ros.summary_chunk_starts(buf, inner)  # where the walk picks up again after a damaged stretch
    sc.keep = keep or mcap_ros.chunk_places(buf, off, starts=starts) is None
    # kept: zstd chunks decompressed into one buffer (the messages' buffer of the export: not held twice;
    # None where chunk_places is: a streamed scan that found none keeps its chunks one by one); streamed: each
    # into an array of its own, let go once walked
    sc.arena = mcap_ros.chunk_arena(buf, off, starts=starts) if keep else None
    last = off
    indexes = mcap_ros.IndexCheck()  # (damaged ones: the output's are written anew)
    # (decompression and CRC ahead, in threads)
    with mcap_ros.chunk_prefetch(buf, off, sc.arena if sc.keep else "own", starts) as chunks:
        while off < end:
            if off + 9 > end:
                sc.damage.append(f"file truncated at byte {off} of {end} (no footer)")
                break
            op, ln = mcap_ros._REC.unpack_from(buf, off)
            nxt = off + 9 + ln
            broken = mcap_ros.derailed(buf, op, nxt, starts, last)  # (the parser's rule)
            if broken is not None:
                what, at = broken
                if at is None:
                    sc.damage.append(f"{what} at byte {off}; rest of file not read")
                    break
                sc.damage.append(f"{what} at byte {off}; went on at the next chunk the summary lists (byte {at}), "
                                 "the bytes between not in the output")
                last = off = at
                continue
            if nxt > end:
                got = sc.partial_chunk(buf, off, end) if op == _OP["chunk"] else 0
                sc.damage.append(f"file truncated at byte {end}: record at byte {off} (opcode {op}) incomplete"
                                 + (f"; its {got} complete messages kept" if got else ""))
                break
            try:
                p = off + 9
                if op == _OP["header"]:
                    sc.profile, o = mcap_ros._string(buf, p)
                    sc.library, _ = mcap_ros._string(buf, o)
                elif op == _OP["chunk"]:
                    indexes.chunk_at(buf, off)
                    sc.chunk(buf, off, nxt, chunks)
                elif op == _OP["message_index"]:
                    indexes.index_at(buf, off, nxt)
                elif op == _OP["message"]:
                    sc.records(buf, off, nxt, "data section")
                elif op == _OP["schema"]:
                    sc.schema(buf, p)
                elif op == _OP["channel"]:
                    sc.channel(buf, p)
                elif op == _OP["attachment"]:
                    log_t, create_t = struct.unpack_from("<QQ", buf, p)
                    name, o = mcap_ros._string(buf, p + 16)
                    media, o = mcap_ros._string(buf, o)
                    (n,) = _U64.unpack_from(buf, o)
                    sc.extras.append(("attachment", (create_t, log_t, name, media, bytes(buf[o + 8:o + 8 + n]))))
                elif op == _OP["metadata"]:
                    name, o = mcap_ros._string(buf, p)
                    meta, _ = _map(buf, o)
                    sc.extras.append(("metadata", (name, meta)))
                elif op in (_OP["data_end"], _OP["footer"]):
                    footer = True
                    break  # the summary is rebuilt by the writer
            except (mcap_ros._Damage, struct.error, UnicodeDecodeError) as exc:
                msg = str(exc) if isinstance(exc, mcap_ros._Damage) else f"record at byte {off} unreadable ({exc})"
                sc.damage.append(f"damaged: {msg}; its messages are not in the output")
            last = off
            off = nxt
    if (said := indexes.said("the output's message indexes are made anew from its chunks")) is not None:
        sc.damage.append(said)
    if not footer and not sc.damage:
        sc.damage.append("no MCAP data end / footer (file truncated?)")
    return sc


def _mcap_streams(sc: _McapScan, typestore) -> tuple[list[int], list[_Stream]]:
    cids = sorted(sc.channels)
    streams = []
    bases: dict = {}  # (the built-in stores by encoding)
    for c in cids:
        topic, enc, sid, _meta = sc.channels[c]
        name, senc, text = sc.schemas.get(sid, ("", "", b""))
        msgtype = rc.normalize_msgtype(name) if name else ""
        if senc in ("ros2msg", "ros1msg", "ros2idl"):
            _registered(typestore, msgtype, text.decode("utf-8", "replace"), "idl" if senc == "ros2idl" else "msg")
        if enc in ("cdr", "ros1"):  # (as the readers decode such a message)
            bases[enc] = mcap_ros.register_builtin(typestore, {msgtype}, enc, bases.get(enc))
        kind = (_header_kind(typestore, msgtype) if enc in ("cdr", "ros1") else
                _JSON if enc == "json" and msgtype in rc.SUPPORTED else _NONE)
        streams.append(_Stream(topic, msgtype, enc, kind))
    return cids, streams


def _mcap_msgs(sc: _McapScan, cids: list[int]) -> tuple[_Msgs, rcw.ChunkLayout | None]:
    """All messages (payloads in one writable buffer, each after its record's head) and where the input's
    chunks lie in that buffer (None unless every message came from a whole chunk)."""
    cat = (lambda v: np.concatenate(v) if v else np.zeros(0, np.int64))
    lut = np.zeros(max(cids, default=0) + 1, np.int64)
    lut[cids] = np.arange(len(cids))
    conn = lut[cat(sc.cid)]
    blens = [b[0] if not sc.keep else len(b[0]) for b in sc.blocks]
    base = buf = None
    if not sc.keep:  # (a streamed scan: the chunks one after another, in no buffer)
        base, buf = (np.cumsum(blens) - blens).tolist(), np.zeros(0, np.uint8)
    else:  # blocks that all view one buffer are patched there: the file's bytes (uncompressed chunks) or the
        # buffer the zstd chunks were inflated into
        for cand in (sc.file, sc.arena[0] if sc.arena is not None else None):
            if cand is not None and (base := _views_of(cand, sc.blocks)) is not None:
                buf = cand
                break
    if base is None:
        base = (np.cumsum(blens) - blens).tolist() if sc.blocks else []
        buf = np.concatenate([b[0] for b in sc.blocks]) if sc.blocks else np.zeros(0, np.uint8)
    starts = cat([b[1] + o for b, o in zip(sc.blocks, base)])
    lens = cat([b[2] for b in sc.blocks])
    layout = None
    if sc.blocks and all(sc.whole):
        layout = rcw.ChunkLayout(np.asarray(base, np.int64), np.asarray(blens, np.int64),
                                 np.asarray([len(c) for c in sc.cid], np.int64))
    heads = np.concatenate(sc.heads) if sc.heads else np.zeros((0, 12), np.uint8)
    return _Msgs(conn, cat(sc.log), buf, starts, lens, heads, None if sc.keep else sc.kept), layout


def _streamed_ok(sc: _McapScan, streams: list[_Stream]) -> bool:
    """Whether a streamed scan is all the export needs: every message in a whole, sound chunk, each chunk
    walked once, and no stream whose payloads are read or rewritten beyond their Header stamps (JSON text,
    nested Headers: those take the chunks kept)."""
    return (not sc.keep and not sc.damage and bool(sc.blocks) and all(sc.whole)
            and len(sc.spans) == len(sc.blocks) and None not in sc.spans and len(set(sc.spans)) == len(sc.spans)
            and all(s.kind in (_FIRST, _NONE, "unknown") for s in streams))


def _mcap_heads(msgs: _Msgs) -> tuple[np.ndarray, np.ndarray]:
    """The publish times and sequence numbers of the message records whose payloads ``msgs`` holds (each after
    its record's head, as :func:`_mcap_msgs` gives them): what a writer laying the records out anew needs."""
    # a message record is opcode, length, channel, sequence (4 bytes), log time, publish time (8 each), data
    head = get_bytes(msgs.buf, msgs.starts - 20, 20)  # sequence, log and publish times in one pass over the records
    seq = head[:, :4].copy().view("<u4").ravel().astype(np.int64)
    pub = head[:, 12:].copy().view("<u8").ravel().astype(np.int64)
    return pub, seq


def _views_of(base: np.ndarray, blocks: list) -> list[int] | None:
    """The blocks' offsets in ``base`` when every block is a view inside it, else None."""
    if not blocks:
        return None
    at0 = base.__array_interface__["data"][0]
    out = []
    for b, _s, _e in blocks:
        o = b.__array_interface__["data"][0] - at0
        if not 0 <= o <= len(base) - len(b):
            return None
        out.append(o)
    return out


def _chunk_bytes(sc: _McapScan) -> int:
    """The input's chunk size (its first chunk's, at least 64 KiB); 1 MiB for an unchunked input."""
    return max(sc.chunk_size, 1 << 16) if sc.chunk_size else 1 << 20


def restamp_mcap(src: str, dst: str, shift: ClockShift, *, selector: str | None = None) -> RestampStats:
    """An MCAP file with every message kept, header stamps and log/publish times on the master's clock."""
    with export_hugepages():  # (its few large buffers: the decompressed chunks, the columns over all messages)
        return _restamp_mcap(src, dst, shift, selector)


def _restamp_mcap(src: str, dst: str, shift: ClockShift, selector: str | None) -> RestampStats:
    from rosbags.typesys import Stores, get_typestore

    # first a streamed scan (each chunk's bytes let go once walked; the writer inflates them again, one by
    # one into each thread's buffer); where it is not enough (damage, payloads to rewrite), the chunks kept
    sc = _scan_mcap(src, keep=False)
    typestore = get_typestore(Stores.EMPTY)
    cids, streams = _mcap_streams(sc, typestore)
    if not sc.keep and not _streamed_ok(sc, streams):
        sc = _scan_mcap(src)
        typestore = get_typestore(Stores.EMPTY)
        cids, streams = _mcap_streams(sc, typestore)
    msgs0, layout = _mcap_msgs(sc, cids)
    later: list[_StampPatch] = []  # (the Header stamps, written by the writer's threads chunk by chunk)
    new_log, msgs, notes = _apply(streams, msgs0, typestore, shift, selector, src, later)  # (payloads only)
    delta = msgs.log_ns - new_log
    comp = sc.compression if sc.compression is not None else "zstd"
    if layout is not None and msgs.buf is msgs0.buf:  # the input's chunks, their records' times patched
        new_pub = seq = None
    else:  # records laid out anew (a payload grew, or a chunk was damaged)
        pub, seq = _mcap_heads(msgs0)
        new_pub, layout = np.where(pub != 0, pub - delta, 0), None
    stamps = later[0] if later else None
    if stamps is not None and layout is None:  # (laid out anew: from payloads that carry their stamps)
        stamps.write(msgs.buf, msgs.starts)
        stamps = None
    inflate = None if sc.keep else mcap_ros.chunk_inflater(memoryview(sc.file), sc.spans)
    with atomic_path(dst) as tmp, open(tmp, "wb") as fh:
        rcw.write_mcap(fh, sc, cids, msgs, new_log, new_pub, seq, comp, _chunk_bytes(sc), layout=layout, delta=delta,
                       stamps=stamps, inflate=inflate)
    return RestampStats(path=dst, format="mcap", how="tapost's vectorised MCAP writer (chunk compression kept, "
                        "CRCs, message indexes and summary rebuilt); Header stamps patched in the payload "
                        "bytes (nested Headers through rosbags (de)serialisation; JSON-encoded messages: the "
                        "stamp's digits in the text)",
                        records=len(new_log), records_by_type=_counts(streams, msgs.conn),
                        time_fields=("log_time", "publish_time", "header.stamp"),
                        damage=tuple(sc.damage) + tuple(notes))


# ---- ROS 2 ---------------------------------------------------------------------------------------
def _sqlite_rows(path: str, damage: list[str]) -> tuple[dict[int, tuple[str, str, str]], list[tuple]]:
    check_readable(path)
    try:
        con = rosbag2.connect_ro(path)
        topics = {r[0]: (r[1], r[2], r[3]) for r in con.execute(
            "SELECT id, name, type, serialization_format FROM topics")}
    except sqlite3.DatabaseError as exc:
        raise InputError(f"sqlite3 storage unreadable ({exc})", path) from None
    max_id, why = rosbag2.max_message_id(con)
    lost_ids: list[tuple[int, int]] | None = None if max_id is None else []
    rows: list[tuple] = []
    gaps: list[tuple[int, int]] = []
    try:  # (the export keeps every row: all of them are written)
        if max_id is not None:
            rows = [r for batch in rosbag2.message_rows(con, max_id, lost_ids, gaps) for r in batch]
            lost_ids, why_gaps = rosbag2.unreached(con, max_id, lost_ids, gaps)
            why = why or why_gaps
    finally:
        con.close()
    if lost_ids is None or lost_ids:  # what SQLite cannot reach, looked for page by page
        found, note = rosbag2.recovered_rows(path, lost_ids, why or "pages unreadable")
        if found and rows:  # back among the rows read in id order (rosbag2 inserts in time order)
            rows = sorted(rows + found, key=lambda r: r[1] if isinstance(r[1], int) else -1)
        else:
            rows += found
        damage.append(note + "; the rest is not in the output")
    return topics, rows


def _concat(parts: list[_Msgs]) -> _Msgs:
    if not parts:
        return _pack(np.zeros(0, np.int64), np.zeros(0, np.int64), [])
    base = np.cumsum([len(m.buf) for m in parts]) - [len(m.buf) for m in parts]
    return _Msgs(np.concatenate([m.conn for m in parts]), np.concatenate([m.log_ns for m in parts]),
                 np.concatenate([m.buf for m in parts]) if len(parts) > 1 else parts[0].buf,
                 np.concatenate([m.starts + o for m, o in zip(parts, base)]), np.concatenate([m.lens for m in parts]))


@dataclasses.dataclass
class _Part:
    """One storage file of a ROS 2 bag: its messages (``conn`` = bag stream) and, for mcap, its scan."""

    name: str  # storage file name in the output (compressed name for file compression)
    msgs: _Msgs
    scan: _McapScan | None = None
    local: np.ndarray | None = None  # index into sorted(scan.channels) per message
    pub: np.ndarray | None = None
    seq: np.ndarray | None = None
    layout: rcw.ChunkLayout | None = None  # where its chunks lie in msgs.buf (mcap, whole chunks only)


def _ros2_streams(conns, typestore) -> tuple[list[_Stream], dict[tuple[str, str], int]]:
    base = None
    streams: list[_Stream] = []
    by_key: dict[tuple[str, str], int] = {}
    for c in conns:
        fmt = "idl" if c.msgdef.format.name == "IDL" else "msg"
        _registered(typestore, c.msgtype, c.msgdef.data, fmt)
        base = mcap_ros.register_builtin(typestore, {c.msgtype}, "cdr", base)  # (old bags store no definitions)
        enc = c.ext.serialization_format
        by_key[(c.topic, c.msgtype)] = len(streams)
        streams.append(_Stream(c.topic, c.msgtype, enc, _header_kind(typestore, c.msgtype) if enc == "cdr" else _NONE))
    return streams, by_key


def _read_ros2_part(f: str, g: str, storage: str, by_key, damage: list[str]) -> _Part:
    name = os.path.basename(f)
    if g.endswith(".mcap") or storage == "mcap":
        sc = _scan_mcap(g)
        damage += [f"{name}: {d}" for d in sc.damage]
        cids = sorted(sc.channels)
        m, layout = _mcap_msgs(sc, cids)
        pub, seq = _mcap_heads(m)
        keys = [by_key.get((sc.channels[c][0], rc.normalize_msgtype(sc.schemas.get(sc.channels[c][2], ("", "", b""))[0])))
                for c in cids]
        if any(k is None for k in keys):
            raise InputError("an mcap channel is not among metadata.yaml's topics", f)
        local = m.conn
        m.conn = np.asarray(keys, np.int64)[local] if len(local) else np.zeros(0, np.int64)
        return _Part(name, m, sc, local, pub, seq, layout)
    topics, rows = _sqlite_rows(g, damage)
    tk = {}
    for tid, (tname, ttype, _fmt) in topics.items():
        tk[tid] = by_key.get((tname, rc.normalize_msgtype(ttype)))
        if tk[tid] is None:
            raise InputError(f"topic {tname} of the storage file is not among the bag's connections", f)
    # a damaged page can hand back rows whose topic id, time or data are of another type (or NULL): not
    # messages that can be written; dropped and named, as the parser drops them
    good = [r for r in rows if isinstance(r[0], int) and r[0] in tk and isinstance(r[1], int) and r[1] >= 0
            and isinstance(r[2], (bytes, bytearray, memoryview))]
    if len(good) < len(rows):
        damage.append(f"{name}: {len(rows) - len(good)} message row(s) with a damaged topic id, timestamp or "
                      "data; not in the output")
        rows = good
    conn = np.fromiter((tk[r[0]] for r in rows), np.int64, len(rows))
    log = np.fromiter((r[1] for r in rows), np.int64, len(rows))
    return _Part(name, _pack(conn, log, [r[2] for r in rows]))


def _unzstd_part(part: _Part, damage: list[str]) -> None:
    """Message compression undone (a message that does not decompress is dropped, named)."""
    import zstandard

    dctx = zstandard.ZstdDecompressor()
    m = part.msgs
    out, keep = [], []
    for i, d in enumerate(m.views()):
        try:
            out.append(dctx.decompressobj().decompress(d))
            keep.append(i)
        except zstandard.ZstdError:
            pass
    if len(keep) < len(m.lens):
        damage.append(f"{part.name}: {len(m.lens) - len(keep)} compressed messages do not decompress; "
                      "not in the output")
    part.msgs = _pack(m.conn[keep], m.log_ns[keep], out)
    if part.local is not None:
        part.local, part.pub, part.seq = part.local[keep], part.pub[keep], part.seq[keep]


def restamp_rosbag2(src: str, dst: str, shift: ClockShift, *, selector: str | None = None) -> RestampStats:
    """A ROS 2 bag folder (same storage plugin and compression) on the master's clock."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    check_readable(src)
    check_replaceable(dst, rosbag2.is_bag_folder, "ROS 2 bag")  # (before the work: the same check as the write's)
    bagdir, meta, files, meta_damage = rosbag2._resolve(src)
    damage: list[str] = []
    if meta_damage is not None:  # the storage files name their topics and types: the parser reads them alone
        if not os.path.isdir(src):
            raise InputError(f"{meta_damage}: restamp the bag folder", src)
        meta = {"compression_mode": "FILE", "compression_format": "zstd"} if all(
            f.endswith(".zstd") for f in files) else {}
        damage.append(f"damaged: {meta_damage}; not copied: the output's metadata.yaml is rosbags' writer's, made "
                      "from the messages read (QoS profiles and custom data of the input are lost)")
    if meta is None:
        raise InputError("no metadata.yaml next to the storage file (restamp the bag folder)", src)
    storage = str(meta.get("storage_identifier") or ("mcap" if files[0].endswith((".mcap", ".mcap.zstd")) else "sqlite3"))
    mode, cfmt = rosbag2._compression(meta)
    if mode in ("file", "message") and cfmt != "zstd":
        raise InputError(f"compression format {cfmt!r} not supported (zstd is)", bagdir)
    if storage == "sqlite3" and mode != "file":
        starts = {f: rosbag2.sqlite_start(f) for f in files if f.endswith(".db3")}
        if any(k > 0 for k in starts.values()):
            return _restamp_from_databases(src, bagdir, files, starts, dst, shift, selector)
    if storage == "sqlite3" and mode == "none" and len(files) == 1 and meta_damage is None:
        done = _restamp_sqlite_in_place(files[0], bagdir, meta, dst, shift, selector)
        if done is not None:
            return done
    conns = None
    opened = None  # why rosbags' reader could not open the bag, where tapost's scan listed its connections
    if meta_damage is None:  # (else rosbags' reader, which reads metadata.yaml, cannot: the storage files say)
        if storage == "sqlite3" and len(files) == 1 and mode != "file":  # (rosbags' reader counts every row
            from parsers import restamp_sqlite  # first, which a damaged page stops)

            conns = restamp_sqlite.connections(files[0])
        try:
            if not conns:
                with Reader(bagdir) as rd:
                    conns = list(rd.connections)
        except Exception as exc:
            why = f"{type(exc).__name__}: {exc}".strip().rstrip(":")
            why = " ".join(why.split())[:200]  # (one line)
            if storage != "mcap" or mode == "file":
                raise InputError(f"damaged: {storage} storage unreadable by rosbags ({why})", bagdir) from None
            conns = _mcap_connections(files, bagdir, why)  # (our own scan reads past the damage)
            opened = why
    typestore = get_typestore(Stores.EMPTY)
    if opened is not None:
        damage.append(f"damaged: rosbags' reader cannot open the bag ({opened}); its connections taken from "
                      "tapost's scan of the mcap storage")
    parts: list[_Part] = []
    with tempfile.TemporaryDirectory(prefix="tapost-restamp-") as tmpd:
        plain = [rosbag2._unzstd_file(f, tmpd) if (mode == "file" or f.endswith(".zstd")) else f for f in files]
        if conns is None:
            conns = _storage_connections(plain, storage, bagdir, meta_damage or "")
        streams, by_key = _ros2_streams(conns, typestore)
        for f, g in zip(files, plain):
            parts.append(_read_ros2_part(f, g, storage, by_key, damage))
    if meta_damage is not None and mode == "none" and any(  # (per-message compression told by its frames, as
            len(p.msgs.log_ns) and bytes(p.msgs.payload(0)[:4]) == rosbag2.ZSTD_MAGIC for p in parts):  # read)
        mode = "message"
    if mode == "message":
        for part in parts:
            _unzstd_part(part, damage)
    msgs = _concat([p.msgs for p in parts])
    declared = int(meta.get("message_count") or 0)
    if declared and len(msgs.log_ns) < declared:
        damage.append(f"damaged or cut short: read {len(msgs.log_ns)} of the {declared} messages metadata.yaml "
                      "declares")
    far_said: list[str] = []
    if not (storage == "mcap" and mode != "message"):  # (the mcap writer keeps its parts' records aligned)
        msgs, far_said = _without_far(streams, msgs, "row timestamp")  # (moved by a damaged byte)
    packed = msgs.buf
    new_log, msgs, notes = _apply(streams, msgs, typestore, shift, selector, bagdir)
    notes.extend(far_said)
    with atomic_folder(dst, same_kind=rosbag2.is_bag_folder, what="ROS 2 bag") as tmp:
        if storage == "mcap" and mode != "message" and all(p.scan is not None for p in parts) and meta_damage is None:
            _write_ros2_mcap(tmp, meta, mode, parts, streams, msgs, new_log, in_place=msgs.buf is packed)
            how = ("mcap storage files by tapost's vectorised MCAP writer (schemas, channels, metadata as the "
                   "input's), metadata.yaml times and counts updated")
        else:
            _write_ros2_rosbags(tmp, meta, mode, storage, conns, msgs, new_log)
            how = f"rosbags.rosbag2.Writer ({storage} storage)"
    return RestampStats(path=dst, format="rosbag2", how=how + "; Header stamps patched in the payload bytes "
                        "(nested Headers through rosbags (de)serialisation)",
                        records=len(new_log), records_by_type=_counts(streams, msgs.conn),
                        time_fields=("messages.timestamp" if storage != "mcap" else "log_time", "header.stamp",
                                     "metadata.yaml starting_time/duration"),
                        damage=tuple(damage) + tuple(notes))


def _restamp_from_databases(src: str, bagdir: str, files: list[str], starts: dict[str, int], dst: str,
                            shift: ClockShift, selector: str | None) -> RestampStats:
    """A sqlite3 bag some of whose .db3 files have bytes put before their database (``starts``:
    rosbag2.sqlite_start of each): restamped from a copy of the bag whose storage files start at their
    databases, as the parser reads them; the prefixes named in the damage."""
    with tempfile.TemporaryDirectory(prefix="tapost-restamp-") as tmpd:
        bag = os.path.join(tmpd, "bag")
        os.makedirs(bag)
        meta_path = os.path.join(bagdir, "metadata.yaml")
        if os.path.isfile(meta_path):
            shutil.copyfile(meta_path, os.path.join(bag, "metadata.yaml"))
        damage = []
        for f in files:
            rel = os.path.relpath(f, bagdir)
            os.makedirs(os.path.dirname(os.path.join(bag, rel)), exist_ok=True)
            k = starts.get(f, 0)
            if k > 0:
                rosbag2.database_copy(f, k, bag, rel)
                damage.append(rosbag2.prefix_damage(f, k))
            else:
                os.symlink(os.path.abspath(f), os.path.join(bag, rel))
        try:
            st = restamp_rosbag2(bag, dst, shift, selector=selector)
        except InputError as exc:
            raise InputError(exc.problem, src) from None
    return dataclasses.replace(st, damage=tuple(damage) + st.damage)


def _storage_connections(files: list[str], storage: str, bagdir: str, why: str) -> list:
    """The connections of a ROS 2 bag from its (uncompressed) storage files alone, each (topic, type) once:
    for a bag whose metadata.yaml is damaged (``why``)."""
    if storage == "mcap":
        return _mcap_connections(files, bagdir, why)
    from rosbags.interfaces import Connection

    from parsers import restamp_sqlite

    out, seen = [], set()
    for f in files:
        for c in restamp_sqlite.connections(f) or []:
            if (c.topic, c.msgtype) not in seen:
                seen.add((c.topic, c.msgtype))
                out.append(Connection(len(out) + 1, c.topic, c.msgtype, c.msgdef, c.digest, 0, c.ext, None))
    if not out:
        raise InputError(f"damaged: {why}, and the sqlite3 storage lists no topic either", bagdir)
    return out


def _mcap_connections(files: list[str], bagdir: str, why: str) -> list:
    """The connections of a ROS 2 bag's mcap storage files from tapost's own scan of them (their channels
    and schemas, as rosbags would list them), for a bag whose damage stops rosbags' reader (``why``)."""
    from rosbags.interfaces import Connection, ConnectionExtRosbag2, MessageDefinition, MessageDefinitionFormat
    from rosbags.rosbag2.metadata import parse_qos

    fmt = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
    out, seen = [], set()
    for f in files:
        sc = _scan_mcap(f)
        for cid in sorted(sc.channels):
            topic, enc, sid, meta = sc.channels[cid]
            name, senc, text = sc.schemas.get(sid, ("", "", b""))
            key = (topic, rc.normalize_msgtype(name))
            if not name or key in seen:
                continue
            seen.add(key)
            msgdef = MessageDefinition(fmt[senc], text.decode("utf-8", "replace")) if senc in fmt else \
                MessageDefinition(MessageDefinitionFormat.NONE, "")
            try:
                qos = parse_qos(meta.get("offered_qos_profiles", "")) if meta.get("offered_qos_profiles") else []
            except Exception:
                qos = []
            out.append(Connection(len(out) + 1, topic, key[1], msgdef, "", 0, ConnectionExtRosbag2(enc, qos), None))
    if not out:
        raise InputError(f"damaged: mcap storage unreadable by rosbags ({why}) and no channel readable by tapost's "
                         "scan either", bagdir)
    return out


def _restamp_sqlite_in_place(f: str, bagdir: str, meta: dict, dst: str, shift: ClockShift,
                             selector: str | None) -> RestampStats | None:
    """An uncompressed one-file sqlite3 bag restamped at the byte level of its .db3 (parsers.restamp_sqlite);
    None where that does not apply (reference kernels, a layout the walk does not expect, a message whose
    re-serialised Headers change its length): the caller then re-inserts the rows."""
    from logtools import jit
    from rosbags.typesys import Stores, get_typestore

    from parsers import restamp_sqlite as rsq

    if not jit.compiled():  # the byte walk in plain Python would cost more than re-inserting the rows
        return None
    conns = rsq.connections(f)
    w = rsq.walk(f) if conns else None
    if w is None:
        return None
    typestore = get_typestore(Stores.EMPTY)
    streams, by_key = _ros2_streams(conns, typestore)
    lut = {}
    for c in conns:
        k = by_key.get((c.topic, c.msgtype))
        if k is None:
            return None
        lut[c.id] = k
    if not set(np.unique(w.topic).tolist()) <= set(lut):
        return None  # rows of a topic the topics table does not list: the tolerant path names them
    ids = np.fromiter(lut, np.int64, len(lut))
    table = np.zeros(int(ids.max()) + 1 if len(ids) else 1, np.int64)
    table[ids] = [lut[i] for i in ids.tolist()]
    msgs = _Msgs(table[w.topic], w.timestamps(), w.buf, w.data_off, w.data_len)
    declared = int(meta.get("message_count") or 0)
    if declared and len(msgs.log_ns) < declared:
        return None  # rows missing: the tolerant path reads and names what is there
    if np.any(msgs.log_ns < 0) or _far_times(msgs.log_ns).any():
        return None  # a damaged row timestamp: the tolerant path leaves that row out, named
    new_log, out, notes = _apply(streams, msgs, typestore, shift, selector, bagdir)
    if out.buf is not w.buf:
        return None
    name = os.path.basename(f)
    n = len(new_log)
    files_meta = [{"path": name, "starting_time": {"nanoseconds_since_epoch": int(new_log.min()) if n else 0},
                   "duration": {"nanoseconds": int(new_log.max() - new_log.min()) if n else 0}, "message_count": n}]
    info = _bag_info(meta, files_meta, streams, out, new_log)
    with atomic_folder(dst, same_kind=rosbag2.is_bag_folder, what="ROS 2 bag") as tmp:
        os.makedirs(tmp)
        rebuilt = rsq.write(w, new_log, os.path.join(tmp, name), info)
        _write_bag_info(tmp, info)
    how = ("the .db3 restamped in place at the byte level of SQLite's file format (rows' timestamps, index "
           "keys" + (", index rebuilt by SQLite as the shift reordered it" if rebuilt else "") + "; every other "
           "byte the input's), metadata table and metadata.yaml times and counts updated")
    return RestampStats(path=dst, format="rosbag2", how=how + "; Header stamps patched in the payload bytes",
                        records=n, records_by_type=_counts(streams, out.conn),
                        time_fields=("messages.timestamp", "header.stamp", "metadata.yaml starting_time/duration"),
                        damage=tuple(notes))


def _write_ros2_rosbags(tmp: str, meta: dict, mode: str, storage: str, conns, msgs: _Msgs, new_log: np.ndarray) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    version = int(meta.get("version") or 9)
    w = Writer(tmp, version=max(version, 8), storage_plugin=plugin)
    if mode in ("file", "message"):
        w.set_compression(CompressionMode[mode.upper()], CompressionFormat.ZSTD)
    for key, value in (meta.get("custom_data") or {}).items():
        w.set_custom_data(str(key), str(value))
    base = None
    with w:
        wc = []
        for c in conns:
            if not (c.msgdef.data and c.digest):
                base = base or rc.default_typestore("cdr")
            wc.append(w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data or None, rihs01=c.digest or None,
                                       typestore=base, serialization_format=c.ext.serialization_format,
                                       offered_qos_profiles=c.ext.offered_qos_profiles))
        cur = getattr(w.storage, "cursor", None)
        if plugin == StoragePlugin.SQLITE3 and mode != "message" and cur is not None and len(new_log):
            # one executemany (what Writer.write does row by row), the writer's counts kept in step
            ids = np.asarray([c.id for c in wc], np.int64)[msgs.conn]
            # the timestamp index built once after the rows (the schema ends up as the writer's own)
            idx_sql = w.storage.conn.execute("SELECT sql FROM sqlite_master WHERE type='index' AND "
                                             "name='timestamp_idx'").fetchone()
            if idx_sql:
                w.storage.conn.execute("DROP INDEX timestamp_idx")
            cur.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES(?, ?, ?)",
                            zip(ids.tolist(), new_log.tolist(), msgs.views()))
            if idx_sql:
                w.storage.conn.execute(idx_sql[0])
            for k, c in zip(*np.unique(msgs.conn, return_counts=True)):
                w.counts[wc[int(k)].id] += int(c)
            w.min_timestamp = min(w.min_timestamp, int(new_log.min()))
            w.max_timestamp = max(w.max_timestamp, int(new_log.max()))
        else:
            write = w.write
            for k, t, d in zip(msgs.conn.tolist(), new_log.tolist(), msgs.views()):
                write(wc[k], t, d)


def _write_ros2_mcap(tmp: str, meta: dict, mode: str, parts: list[_Part], streams: list[_Stream], msgs: _Msgs,
                     new_log: np.ndarray, in_place: bool = False) -> None:
    """mcap storage: each storage file rewritten like a bare MCAP file, metadata.yaml updated."""
    os.makedirs(tmp)
    delta = msgs.log_ns - new_log
    files_meta = []
    at = 0
    for part in parts:
        n = len(part.msgs.log_ns)
        sl = slice(at, at + n)
        at += n
        sc = part.scan
        cids = sorted(sc.channels)
        sub = _Msgs(part.local, msgs.log_ns[sl], msgs.buf, msgs.starts[sl], msgs.lens[sl])
        t = new_log[sl]
        pub = np.where(part.pub != 0, part.pub - delta[sl], 0)
        name = part.name[:-5] if part.name.endswith(".zstd") else part.name
        path = os.path.join(tmp, name)
        layout = None
        if in_place and part.layout is not None and n:  # its chunks, moved by where _concat put the part
            o = int(msgs.starts[sl.start] - part.msgs.starts[0])
            layout = rcw.ChunkLayout(part.layout.base + o, part.layout.size, part.layout.count)
        with open(path, "wb") as fh:
            rcw.write_mcap(fh, sc, cids, sub, t, pub, part.seq, sc.compression if sc.compression is not None else "zstd",
                           _chunk_bytes(sc), layout=layout, delta=delta[sl])
        if mode == "file":
            import zstandard

            with open(path, "rb") as fi, open(path + ".zstd", "wb") as fo:
                zstandard.ZstdCompressor().copy_stream(fi, fo)
            os.remove(path)
            name += ".zstd"
        files_meta.append({"path": name, "starting_time": {"nanoseconds_since_epoch": int(t.min()) if n else 0},
                           "duration": {"nanoseconds": int(t.max() - t.min()) if n else 0}, "message_count": n})
    _write_bag_info(tmp, _bag_info(meta, files_meta, streams, msgs, new_log))


def _bag_info(meta: dict, files_meta: list[dict], streams: list[_Stream], msgs: _Msgs, new_log: np.ndarray) -> dict:
    """metadata.yaml's bag information with the new start, duration and counts."""
    info = dict(meta)
    n = len(new_log)
    info["starting_time"] = {"nanoseconds_since_epoch": int(new_log.min()) if n else 0}
    info["duration"] = {"nanoseconds": int(new_log.max() - new_log.min()) if n else 0}
    info["message_count"] = n
    counts = _counts(streams, msgs.conn)
    twc = []
    for entry in meta.get("topics_with_message_count") or []:
        e = dict(entry)
        e["message_count"] = counts.get((entry.get("topic_metadata") or {}).get("name"), 0)
        twc.append(e)
    info["topics_with_message_count"] = twc
    info["relative_file_paths"] = [f["path"] for f in files_meta]
    if "files" in meta:
        info["files"] = files_meta
    return info


def _write_bag_info(folder: str, info: dict) -> None:
    import yaml

    with open(os.path.join(folder, "metadata.yaml"), "w", encoding="utf-8") as fh:
        yaml.safe_dump({"rosbag2_bagfile_information": info}, fh, sort_keys=False)
