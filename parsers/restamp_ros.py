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

The containers are written by the formats' own libraries (``rosbags.rosbag1.Writer``,
``rosbags.rosbag2.Writer`` with the input's storage plugin and compression, ``mcap.writer.Writer``
with the input's chunk compression; schemas, channels, metadata and attachments copied) so that every
index, statistic and summary is the library's own; the inputs are read by tapost's tolerant scanners
(what a damaged file still holds is written, the damage is named in :attr:`RestampStats.damage`).

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
import os
import shutil
import sqlite3
import struct
import tempfile
import zlib

import numpy as np

from logtools.errors import InputError
from parsers import mcap_ros, rosbag1, rosbag2
from parsers import ros_common as rc
from parsers.atomic import atomic_path
from parsers.base import Selector, check_readable
from parsers.restamp import ClockShift, RestampStats

HEADER = "std_msgs/msg/Header"
#: a topic whose header stamps are this far from the unit's clock is on another clock
_SAME_CLOCK_NS = 10_000_000_000
_FIRST, _NESTED, _NONE = "first", "nested", "none"


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
    conn: np.ndarray  # int64 index into the streams
    log_ns: np.ndarray  # int64 record times
    data: list  # payloads (bytes)


def _gather(arr: np.ndarray, pos: np.ndarray, width: int) -> np.ndarray:
    return arr[pos[:, None] + np.arange(width)]


def _unit(streams: list[_Stream], msgs: _Msgs, typestore, selector: str | None, path: str) -> tuple[set[str], str]:
    """The topics tapost reads the slave from (with ``selector``) and the time mode (header/log)."""
    sel = Selector.parse(selector or "")
    mode = (sel.get("time") or "header").lower()
    topics: dict[str, rc.RawTopic] = {}
    for k, s in enumerate(streams):
        if s.msgtype in rc.SUPPORTED and s.encoding in ("ros1", "cdr") and s.topic not in topics:
            idx = np.flatnonzero(msgs.conn == k)
            topics[s.topic] = rc.RawTopic(s.topic, s.msgtype, s.encoding, msgs.log_ns[idx].tolist(),
                                          [msgs.data[i] for i in idx[:20].tolist()])
    raw = rc.RawLog(path=path, fmt="", topics=topics, typestore=typestore)
    try:
        plan, _ = rc.plan_unit(raw, sel)
    except InputError:
        if selector:
            raise
        return set(topics), mode
    unit = {t for t in (plan.imu, plan.gyro_odom, plan.att, plan.vel, plan.pos) if t}
    return unit, plan.time_mode


def _apply(streams: list[_Stream], msgs: _Msgs, typestore, shift: ClockShift, selector: str | None,
           path: str) -> tuple[np.ndarray, list, list[str]]:
    """New record times and payloads; notes on what was left as it was."""
    n = len(msgs.log_ns)
    unit, mode = _unit(streams, msgs, typestore, selector, path)
    stamp = np.zeros(n, np.int64)  # header stamp of Header-first messages (0: none / unset)
    bufs: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    notes: list[str] = []
    for k, s in enumerate(streams):
        if s.kind != _FIRST or s.encoding not in ("ros1", "cdr"):
            continue
        idx = np.flatnonzero(msgs.conn == k)
        if not len(idx):
            continue
        parts = [msgs.data[i] for i in idx.tolist()]
        lens = np.fromiter(map(len, parts), np.int64, len(parts))
        ok = lens >= 12
        if not ok.all():
            notes.append(f"{s.topic}: {int((~ok).sum())} messages too short for a header; kept unchanged")
            idx, parts, lens = idx[ok], [p for p, g in zip(parts, ok.tolist()) if g], lens[ok]
        arr = np.frombuffer(bytearray(b"".join(parts)), np.uint8)
        starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
        sn = _gather(arr, starts + 4, 8).copy().view("<u4").reshape(-1, 2).astype(np.int64)
        if s.encoding == "cdr" and arr[starts[0] + 1] == 0:  # big-endian CDR (encapsulation 00 00)
            sn = _gather(arr, starts + 4, 8).copy().view(">u4").reshape(-1, 2).astype(np.int64)
        stamp[idx] = sn[:, 0] * 1_000_000_000 + sn[:, 1]
        bufs[k] = (idx, arr, starts)
    log = msgs.log_ns
    if mode == "log":
        t_an = log.copy()
    else:
        is_unit = np.isin(msgs.conn, [k for k, s in enumerate(streams) if s.topic in unit])
        have = is_unit & (stamp != 0)
        ref = int(np.median(stamp[have] - log[have])) if have.any() else 0
        t_an = log + ref
        for k in bufs:
            idx = bufs[k][0]
            h = idx[stamp[idx] != 0]
            if len(h) and abs(int(np.median(stamp[h] - log[h])) - ref) < _SAME_CLOCK_NS:
                t_an[h] = stamp[h]
    delta = shift.shift_ns(t_an)
    new_log = log - delta
    if n and int(new_log.min()) < 0:
        raise InputError("the shift would make record times negative (latency larger than the stamps)", path)
    data = list(msgs.data)
    for k, (idx, arr, starts) in bufs.items():
        s = streams[k]
        st = stamp[idx]
        new = np.where(st != 0, st - delta[idx], 0)
        if int(new.min()) < 0:
            raise InputError(f"{s.topic}: the shift would make header stamps negative", path)
        sn = np.stack([new // 1_000_000_000, new % 1_000_000_000], axis=1)
        be = s.encoding == "cdr" and arr[starts[0] + 1] == 0
        vals = sn.astype(">u4" if be else "<u4").view(np.uint8).reshape(-1, 8)
        arr[starts[:, None] + 4 + np.arange(8)] = vals
        mv = memoryview(arr)
        ends = np.append(starts[1:], len(arr)).tolist()
        for i, a, b in zip(idx.tolist(), starts.tolist(), ends):
            data[i] = mv[a:b]
    for k, s in enumerate(streams):
        if s.kind == _NESTED and s.encoding in ("ros1", "cdr"):
            bad = 0
            des = typestore.deserialize_cdr if s.encoding == "cdr" else typestore.deserialize_ros1
            ser = typestore.serialize_cdr if s.encoding == "cdr" else typestore.serialize_ros1
            for i in np.flatnonzero(msgs.conn == k).tolist():
                try:
                    m = des(bytes(data[i]), s.msgtype)
                    _restamp_obj(m, int(delta[i]))
                    data[i] = bytes(ser(m, s.msgtype))
                except ValueError as exc:
                    if str(exc) == "negative stamp":
                        raise InputError(f"{s.topic}: the shift would make header stamps negative", path) from None
                    bad += 1
                except Exception:
                    bad += 1
            if bad:
                notes.append(f"{s.topic} ({s.msgtype}): {bad} messages do not deserialise; written with "
                             "their header stamps unchanged")
        elif s.kind == "unknown" and np.any(msgs.conn == k) and s.encoding in ("ros1", "cdr"):
            notes.append(f"{s.topic}: no definition of {s.msgtype}; payloads kept unchanged (record times shifted)")
    return new_log, data, notes


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

    def connection(self, header, data):
        (cid,) = rosbag1._U32.unpack_from(header["conn"], 0)
        if cid not in self.conns:
            self.fields[cid] = rosbag1._fields(data)
        super().connection(header, data)

    def chunk(self, header, buf, d0, d1, where):
        if self.compression is None:
            self.compression = header.get("compression", b"none").decode("ascii", "replace")
        super().chunk(header, buf, d0, d1, where)


def _scan_rosbag1(path: str) -> _Scan1:
    """The top-level record walk of :func:`parsers.rosbag1.read_raw` (same damage rules) with our scan."""
    check_readable(path)
    with open(path, "rb") as fh:
        buf = fh.read()
    if not buf.startswith(rosbag1.MAGIC):
        raise InputError("not a ROS 1 bag (magic '#ROSBAG V2.0' missing)", path)
    scan = _Scan1()
    u32 = rosbag1._U32.unpack_from
    off, end = len(rosbag1.MAGIC), len(buf)
    while off < end:
        try:
            if off + 4 > end:
                raise rosbag1._Damage(f"file truncated at byte {end}: record at byte {off} incomplete")
            (hlen,) = u32(buf, off)
            if off + 8 + hlen > end:
                raise rosbag1._Damage(f"file truncated at byte {end}: record at byte {off} incomplete")
            (dlen,) = u32(buf, off + 4 + hlen)
            nxt = off + 8 + hlen + dlen
            if nxt > end:
                raise rosbag1._Damage(f"file truncated at byte {end}: record at byte {off} incomplete")
            header = rosbag1._fields(buf[off + 4:off + 4 + hlen])
            op = header.get("op", b"\xff")[:1]
        except (rosbag1._Damage, struct.error) as exc:
            scan.warnings.append(f"{exc}; the rest is not in the output" if "truncated" in str(exc)
                                 else f"damaged at byte {off} ({exc}); the rest of the file is not in the output")
            break
        try:
            if op == bytes([rosbag1._OP_CHUNK]):
                scan.chunk(header, buf, off + 8 + hlen, nxt, off)
            elif op in (bytes([rosbag1._OP_CONN]), bytes([rosbag1._OP_MSG])):
                scan.records(buf, off, nxt, "top level")
            elif op not in (bytes([rosbag1._OP_BAGHEADER]), bytes([rosbag1._OP_INDEX]),
                            bytes([rosbag1._OP_CHUNKINFO])):
                raise rosbag1._Damage(f"unknown record op {op!r} at byte {off}")
        except (rosbag1._Damage, struct.error, KeyError, ValueError) as exc:
            scan.warnings.append(f"damaged: {exc}; its other messages are not in the output")
        off = nxt
    return scan


def restamp_rosbag1(src: str, dst: str, shift: ClockShift, *, selector: str | None = None) -> RestampStats:
    """A ROS 1 bag with every message kept, header stamps and record times on the master's clock."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    scan = _scan_rosbag1(src)
    typestore = get_typestore(Stores.EMPTY)
    cids = sorted(scan.conns)
    streams = []
    for cid in cids:
        topic, msgtype, msgdef = scan.conns[cid]
        _registered(typestore, msgtype, msgdef, "msg")
        streams.append(_Stream(topic, msgtype, "ros1", _header_kind(typestore, msgtype)))
    conn = np.concatenate([np.full(len(scan.times[c]), k, np.int64) for k, c in enumerate(cids)] or [np.zeros(0, np.int64)])
    log = np.concatenate([np.asarray(scan.times[c], np.int64) for c in cids] or [np.zeros(0, np.int64)])
    data = [d for c in cids for d in scan.data[c]]
    order = np.argsort(log, kind="stable")
    msgs = _Msgs(conn[order], log[order], [data[i] for i in order.tolist()])
    new_log, new_data, notes = _apply(streams, msgs, typestore, shift, selector, src)
    comp = scan.compression or "none"
    with atomic_path(dst) as tmp:
        os.remove(tmp)  # the rosbags writer refuses to overwrite
        w = Writer(tmp)
        if comp in ("bz2", "lz4"):
            w.set_compression(Writer.CompressionFormat[comp.upper()])
        with w:
            out = {}
            wconns = []
            for cid, s in zip(cids, streams):
                f = scan.fields[cid]
                key = tuple(sorted(f.items()))
                if key not in out:
                    lat = f.get("latching")
                    out[key] = w.add_connection(
                        s.topic, s.msgtype, msgdef=f.get("message_definition", b"").decode("utf-8", "replace"),
                        md5sum=f.get("md5sum", b"*").decode("ascii", "replace") or "*",
                        callerid=f["callerid"].decode("utf-8", "replace") if "callerid" in f else None,
                        latching=int(lat) if lat and lat.strip().isdigit() else None)
                wconns.append(out[key])
            write = w.write
            for k, t, d in zip(msgs.conn.tolist(), new_log.tolist(), new_data):
                write(wconns[k], t, d)
    return RestampStats(path=dst, format="rosbag1", how="rosbags.rosbag1.Writer; Header stamps patched in the "
                        "payload bytes (nested Headers through rosbags (de)serialisation)",
                        records=len(new_log), records_by_type=_counts(streams, msgs.conn),
                        time_fields=("record time", "header.stamp", "chunk info start/end", "index entries"),
                        damage=tuple(scan.warnings) + tuple(notes))


# ---- MCAP ----------------------------------------------------------------------------------------
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_OP = {"header": 1, "footer": 2, "schema": 3, "channel": 4, "message": 5, "chunk": 6,
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
        self.pub: list[np.ndarray] = []
        self.seq: list[np.ndarray] = []
        self.data: list = []
        self.extras: list[tuple[str, tuple]] = []  # ("attachment"|"metadata", args) in file order
        self.damage: list[str] = []
        self.compression: str | None = None
        self.chunk_size = 0

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

    def records(self, buf, start: int, end: int, where: str, cut_ok: bool = False) -> int:
        arr = np.frombuffer(buf, np.uint8)
        m, cid, t, s, e, k, oop, ooff, onxt, err, eoff = mcap_ros._walk_kernel()(arr, start, end)
        if err and not (cut_ok and err != mcap_ros._E_OPCODE):
            raise mcap_ros._Damage(f"{where}: broken record at byte {eoff}")
        for op, off in zip(oop[:k].tolist(), ooff[:k].tolist()):
            (self.schema if op == _OP["schema"] else self.channel)(buf, off + 9)
        cid, s, e = cid[:m], s[:m], e[:m]
        unknown = set(np.unique(cid).tolist()) - set(self.channels)
        if unknown:
            raise mcap_ros._Damage(f"{where}: messages for undefined channel(s) {sorted(unknown)}")
        self.cid.append(cid.copy())
        self.log.append(t[:m].copy())
        self.seq.append(_gather(arr, s - 20, 4).copy().view("<u4").ravel().astype(np.int64))
        self.pub.append(_gather(arr, s - 8, 8).copy().view("<u8").ravel().astype(np.int64))
        self.data.extend(buf[a:b] for a, b in zip(s.tolist(), e.tolist()))
        return m

    def chunk(self, buf, off: int, nxt: int) -> None:
        _t0, _t1, usize, crc = struct.unpack_from("<QQQI", buf, off + 9)
        comp, o = mcap_ros._string(buf, off + 9 + 28)
        (clen,) = _U64.unpack_from(buf, o)
        if o + 8 + clen > nxt:
            raise mcap_ros._Damage(f"chunk at byte {off}: records run past the chunk")
        if self.compression is None:
            self.compression, self.chunk_size = comp, usize
        try:
            content = mcap_ros._decompress(comp, bytes(buf[o + 8:o + 8 + clen]), usize)
        except mcap_ros._Damage:
            raise
        except Exception as exc:
            raise mcap_ros._Damage(f"chunk at byte {off} cannot be decompressed ({type(exc).__name__})") from None
        if len(content) != usize:
            raise mcap_ros._Damage(f"chunk at byte {off}: size {len(content)} != {usize}")
        if crc and zlib.crc32(content) != crc:
            raise mcap_ros._Damage(f"chunk at byte {off}: CRC mismatch")
        n = len(self.cid)
        try:
            self.records(content, 0, len(content), f"chunk at byte {off}")
        except (mcap_ros._Damage, struct.error, UnicodeDecodeError):
            del self.cid[n:], self.log[n:], self.seq[n:], self.pub[n:]
            raise

    def partial_chunk(self, buf, off: int, end: int) -> int:
        try:
            comp, o = mcap_ros._string(buf, off + 9 + 28)
            data = bytes(buf[o + 8:end])
            if comp == "zstd":
                import zstandard

                content = zstandard.ZstdDecompressor().decompressobj().decompress(data)
            elif comp == "lz4":
                import lz4.frame

                content = lz4.frame.LZ4FrameDecompressor().decompress(data)
            else:
                content = data
            return self.records(content, 0, len(content), f"partial chunk at byte {off}", cut_ok=True)
        except Exception:
            return 0


def _scan_mcap(path: str) -> _McapScan:
    check_readable(path)
    with open(path, "rb") as fh:
        buf = fh.read()
    if not buf.startswith(mcap_ros.MAGIC):
        raise InputError("not an MCAP file (bad magic)", path)
    sc = _McapScan()
    off, end = len(mcap_ros.MAGIC), len(buf)
    footer = False
    while off < end:
        if off + 9 > end:
            sc.damage.append(f"file truncated at byte {off} of {end} (no footer)")
            break
        op, ln = mcap_ros._REC.unpack_from(buf, off)
        nxt = off + 9 + ln
        if op == 0 or op > 0x0F:
            sc.damage.append(f"invalid record opcode {op} at byte {off}; rest of file not read")
            break
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
                sc.chunk(buf, off, nxt)
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
        off = nxt
    if not footer and not sc.damage:
        sc.damage.append("no MCAP data end / footer (file truncated?)")
    return sc


def _mcap_streams(sc: _McapScan, typestore) -> tuple[list[int], list[_Stream]]:
    cids = sorted(sc.channels)
    streams = []
    for c in cids:
        topic, enc, sid, _meta = sc.channels[c]
        name, senc, text = sc.schemas.get(sid, ("", "", b""))
        msgtype = rc.normalize_msgtype(name) if name else ""
        if senc in ("ros2msg", "ros1msg", "ros2idl"):
            _registered(typestore, msgtype, text.decode("utf-8", "replace"), "idl" if senc == "ros2idl" else "msg")
        streams.append(_Stream(topic, msgtype, enc, _header_kind(typestore, msgtype) if enc in ("cdr", "ros1") else _NONE))
    return cids, streams


def _mcap_msgs(sc: _McapScan, cids: list[int]) -> tuple[_Msgs, np.ndarray, np.ndarray]:
    cat = (lambda v: np.concatenate(v) if v else np.zeros(0, np.int64))
    pos = {c: k for k, c in enumerate(cids)}
    raw = cat(sc.cid)
    conn = np.array([pos[c] for c in raw.tolist()], np.int64) if len(raw) else np.zeros(0, np.int64)
    return _Msgs(conn, cat(sc.log), sc.data), cat(sc.pub), cat(sc.seq)


def restamp_mcap(src: str, dst: str, shift: ClockShift, *, selector: str | None = None) -> RestampStats:
    """An MCAP file with every message kept, header stamps and log/publish times on the master's clock."""
    from mcap.writer import CompressionType, Writer
    from rosbags.typesys import Stores, get_typestore

    sc = _scan_mcap(src)
    typestore = get_typestore(Stores.EMPTY)
    cids, streams = _mcap_streams(sc, typestore)
    msgs, pub, seq = _mcap_msgs(sc, cids)
    new_log, new_data, notes = _apply(streams, msgs, typestore, shift, selector, src)
    delta = msgs.log_ns - new_log
    new_pub = np.where(pub != 0, pub - delta, 0)
    comp = {"": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}.get(
        sc.compression if sc.compression is not None else "zstd", CompressionType.ZSTD)
    with atomic_path(dst) as tmp, open(tmp, "wb") as fh:
        w = Writer(fh, compression=comp, chunk_size=max(sc.chunk_size, 1024 * 64) if sc.chunk_size else 1024 * 1024)
        w.start(profile=sc.profile, library=sc.library)
        sids = {}
        for sid in sorted(sc.schemas):
            name, senc, text = sc.schemas[sid]
            sids[sid] = w.register_schema(name=name, encoding=senc, data=text)
        wch = [w.register_channel(topic=sc.channels[c][0], message_encoding=sc.channels[c][1],
                                  schema_id=sids.get(sc.channels[c][2], 0), metadata=sc.channels[c][3]) for c in cids]
        for kind, args in sc.extras:
            if kind == "attachment":
                w.add_attachment(*args)
            else:
                w.add_metadata(*args)
        add = w.add_message
        for k, t, d, p, q in zip(msgs.conn.tolist(), new_log.tolist(), new_data, new_pub.tolist(), seq.tolist()):
            add(channel_id=wch[k], log_time=t, data=d, publish_time=p, sequence=q)
        w.finish()
    return RestampStats(path=dst, format="mcap", how="mcap.writer.Writer; Header stamps patched in the payload "
                        "bytes (nested Headers through rosbags (de)serialisation)",
                        records=len(new_log), records_by_type=_counts(streams, msgs.conn),
                        time_fields=("log_time", "publish_time", "header.stamp"),
                        damage=tuple(sc.damage) + tuple(notes))


# ---- ROS 2 ---------------------------------------------------------------------------------------
def _sqlite_rows(path: str, damage: list[str]) -> tuple[dict[int, tuple[str, str, str]], list[tuple]]:
    check_readable(path)
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True)
        topics = {r[0]: (r[1], r[2], r[3]) for r in con.execute(
            "SELECT id, name, type, serialization_format FROM topics")}
        (max_id,) = con.execute("SELECT max(id) FROM messages").fetchone()
    except sqlite3.DatabaseError as exc:
        raise InputError(f"sqlite3 storage unreadable ({exc})", path) from None
    rows: list[tuple] = []
    lost = []
    try:
        for a in range(0, int(max_id or 0) + 1, rosbag2._BATCH):
            try:
                rows += con.execute("SELECT topic_id, timestamp, data FROM messages WHERE id >= ? AND id < ? "
                                    "ORDER BY id", (a, a + rosbag2._BATCH)).fetchall()
            except sqlite3.DatabaseError:
                lost.append(f"{a}-{a + rosbag2._BATCH - 1}")
    finally:
        con.close()
    if lost:
        damage.append(f"{os.path.basename(path)}: sqlite3 storage damaged: message rows {', '.join(lost)} "
                      "unreadable; not in the output")
    return topics, rows


def restamp_rosbag2(src: str, dst: str, shift: ClockShift, *, selector: str | None = None) -> RestampStats:
    """A ROS 2 bag folder (same storage plugin and compression) on the master's clock."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    from rosbags.typesys import Stores, get_typestore

    check_readable(src)
    bagdir, meta, files = rosbag2._resolve(src)
    if meta is None:
        raise InputError("no metadata.yaml next to the storage file (restamp the bag folder)", src)
    storage = str(meta.get("storage_identifier") or ("mcap" if files[0].endswith((".mcap", ".mcap.zstd")) else "sqlite3"))
    mode, cfmt = rosbag2._compression(meta)
    if mode in ("file", "message") and cfmt != "zstd":
        raise InputError(f"compression format {cfmt!r} not supported (zstd is)", bagdir)
    try:
        with Reader(bagdir) as rd:
            conns = list(rd.connections)
    except Exception as exc:
        raise InputError(f"ROS 2 bag unreadable by rosbags ({type(exc).__name__}: {exc})", bagdir) from None
    typestore = get_typestore(Stores.EMPTY)
    base = rc.default_typestore("cdr")
    streams: list[_Stream] = []
    by_key: dict[tuple[str, str], int] = {}
    for c in conns:
        fmt = "idl" if c.msgdef.format.name == "IDL" else "msg"
        _registered(typestore, c.msgtype, c.msgdef.data, fmt)
        if c.msgtype not in typestore.fielddefs and c.msgtype in base.fielddefs:
            typestore.register({k: base.fielddefs[k] for k in mcap_ros._closure(base, {c.msgtype})
                                if k not in typestore.fielddefs})
        enc = c.ext.serialization_format
        by_key[(c.topic, c.msgtype)] = len(streams)
        streams.append(_Stream(c.topic, c.msgtype, enc, _header_kind(typestore, c.msgtype) if enc == "cdr" else _NONE))
    damage: list[str] = []
    conn_l, log_l, data = [], [], []
    import zstandard

    with tempfile.TemporaryDirectory(prefix="tapost-restamp-") as tmpd:
        for f in files:
            g = rosbag2._unzstd_file(f, tmpd) if (mode == "file" or f.endswith(".zstd")) else f
            if g.endswith(".mcap") or storage == "mcap":
                sc = _scan_mcap(g)
                damage += [f"{os.path.basename(f)}: {d}" for d in sc.damage]
                cids = sorted(sc.channels)
                m, _pub, _seq = _mcap_msgs(sc, cids)
                keys = []
                for c in cids:
                    topic, _enc, sid, _meta = sc.channels[c]
                    keys.append(by_key.get((topic, rc.normalize_msgtype(sc.schemas.get(sid, ("", "", b""))[0]))))
                if any(k is None for k in keys):
                    raise InputError("an mcap channel is not in metadata.yaml's topics", f)
                conn_l.append(np.asarray(keys, np.int64)[m.conn] if len(m.conn) else np.zeros(0, np.int64))
                log_l.append(m.log_ns)
                data += m.data
            else:
                topics, rows = _sqlite_rows(g, damage)
                tk = {}
                for tid, (name, ttype, _fmt) in topics.items():
                    tk[tid] = by_key.get((name, rc.normalize_msgtype(ttype)))
                    if tk[tid] is None:
                        raise InputError(f"topic {name} of the storage file is not in the bag's connections", f)
                conn_l.append(np.fromiter((tk[r[0]] for r in rows), np.int64, len(rows)))
                log_l.append(np.fromiter((r[1] for r in rows), np.int64, len(rows)))
                data += [r[2] for r in rows]
    msgs = _Msgs(np.concatenate(conn_l) if conn_l else np.zeros(0, np.int64),
                 np.concatenate(log_l) if log_l else np.zeros(0, np.int64), data)
    if mode == "message":
        dctx = zstandard.ZstdDecompressor()
        keep = []
        for i, d in enumerate(msgs.data):
            try:
                msgs.data[i] = dctx.decompressobj().decompress(d)
                keep.append(i)
            except zstandard.ZstdError:
                pass
        if len(keep) < len(msgs.data):
            damage.append(f"{len(msgs.data) - len(keep)} compressed messages do not decompress; not in the output")
            msgs = _Msgs(msgs.conn[keep], msgs.log_ns[keep], [msgs.data[i] for i in keep])
    declared = int(meta.get("message_count") or 0)
    if declared and len(msgs.log_ns) < declared:
        damage.append(f"read {len(msgs.log_ns)} of the {declared} messages metadata.yaml declares")
    new_log, new_data, notes = _apply(streams, msgs, typestore, shift, selector, bagdir)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    parent = os.path.dirname(os.path.abspath(dst)) or "."
    os.makedirs(parent, exist_ok=True)
    tmpdir = tempfile.mkdtemp(prefix="." + os.path.basename(dst) + ".", dir=parent)
    tmp = os.path.join(tmpdir, "bag")
    try:
        w = Writer(tmp, version=int(meta.get("version") or 9) if int(meta.get("version") or 9) >= 8 else 8,
                   storage_plugin=plugin)
        if mode in ("file", "message"):
            w.set_compression(CompressionMode[mode.upper()], CompressionFormat.ZSTD)
        for key, value in (meta.get("custom_data") or {}).items():
            w.set_custom_data(str(key), str(value))
        with w:
            wc = [w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data or None, rihs01=c.digest or None,
                                   typestore=base, serialization_format=c.ext.serialization_format,
                                   offered_qos_profiles=c.ext.offered_qos_profiles) for c in conns]
            write = w.write
            for k, t, d in zip(msgs.conn.tolist(), new_log.tolist(), new_data):
                write(wc[k], t, d)
        old = None
        if os.path.exists(dst):
            old = tmpdir + ".old"
            os.rename(dst, old)
        os.rename(tmp, dst)
        if old:
            shutil.rmtree(old, ignore_errors=True) if os.path.isdir(old) else os.remove(old)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return RestampStats(path=dst, format="rosbag2", how=f"rosbags.rosbag2.Writer ({storage} storage); Header "
                        "stamps patched in the payload bytes (nested Headers through rosbags (de)serialisation)",
                        records=len(new_log), records_by_type=_counts(streams, msgs.conn),
                        time_fields=("messages.timestamp" if storage != "mcap" else "log_time", "header.stamp",
                                     "metadata.yaml starting_time/duration"),
                        damage=tuple(damage) + tuple(notes))
