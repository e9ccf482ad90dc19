"""Native restamped copies of ROS 1 bags, ROS 2 bags (sqlite3, mcap storage) and MCAP files.

Slaves written by the repo's own writers (and hand-built MCAPs for the message types tapost does not
write), restamped with a known latency and drift, then read back twice: by tapost (the stamps equal
``ClockShift.to_master_ns`` of the stamps it read from the input, ns exact; the data columns identical)
and by the formats' own readers (rosbags AnyReader, mcap reader: same messages per topic, payload
bytes equal except the header stamp, record times shifted by the same amount as the stamps).
"""
from __future__ import annotations

import hashlib
import os
import struct
from pathlib import Path

import numpy as np
import pytest

import parsers
from logtools import jit
from logtools.errors import InputError
from parsers import mcap_ros, registry, rosbag1, rosbag2
from parsers import restamp_ros as rr
from parsers.filemap import FileMap
from parsers.restamp import ClockShift
from tests.test_parsers_ros import CAR_BAG, WRITERS, mcap_with_a_flipped_chunk, synthetic_log

#: the exports in place (an uncompressed ROS 1 bag, a ROS 2 bag's .db3) walk the containers with the compiled
#: kernels; the reference code (TAPOST_KERNELS=reference: a first run before they are compiled) writes them
#: anew, the other tests' path
IN_PLACE = pytest.mark.skipif(not jit.compiled(), reason="the exports in place need the compiled kernels; the "
                              "reference code writes the output anew")

RESTAMP = {"mcap": rr.restamp_mcap, "rosbag1": rr.restamp_rosbag1, "rosbag2": rr.restamp_rosbag2}
LATENCY_S, DRIFT_PPM = 0.0123456789, 87.5


def _t_ns(log, frame) -> np.ndarray:
    return log.meta.t0_ns + np.round(frame.index.to_numpy() * 1e9).astype(np.int64)


def _shift_for(log) -> ClockShift:
    t = _t_ns(log, log.imu)
    return ClockShift(LATENCY_S, DRIFT_PPM, int(t[len(t) // 3]))


def _digest(path: str) -> str:
    h = hashlib.sha256()
    files = [path] if os.path.isfile(path) else sorted(
        os.path.join(d, f) for d, _, fs in os.walk(path) for f in fs)
    for f in files:
        h.update(os.path.relpath(f, path).encode())
        h.update(open(f, "rb").read())
    return h.hexdigest()


def _library_messages(path: str, fmt: str) -> dict[str, list[tuple[int, bytes]]]:
    """(record time, payload) per topic, in order, read by the format's own library."""
    out: dict[str, list[tuple[int, bytes]]] = {}
    if fmt == "mcap":
        from mcap.reader import make_reader

        with open(path, "rb") as fh:
            for _s, ch, m in make_reader(fh).iter_messages(log_time_order=False):
                out.setdefault(ch.topic, []).append((m.log_time, bytes(m.data)))
        return out
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(path)]) as rd:
        for c, t, raw in rd.messages():
            out.setdefault(c.topic, []).append((t, bytes(raw)))
    return out


def _sorted(msgs):
    """Per topic in header-stamp order (the shift keeps it), then record time."""
    return {k: sorted(v, key=lambda x: (_stamp(x[1]), x[0])) for k, v in msgs.items()}


def _stamp(raw: bytes) -> int:
    sec, nsec = np.frombuffer(raw[4:12], "<u4")
    return int(sec) * 1_000_000_000 + int(nsec)


@pytest.fixture(scope="module")
def slave():
    return synthetic_log(400, nav_same_stamps=False)


@pytest.fixture(scope="module")
def slaves(tmp_path_factory, slave) -> dict[str, str]:
    d = tmp_path_factory.mktemp("restamp_src")
    out = {}
    for fmt, opts, name in WRITERS:
        p = str(d / name)
        registry.write(p, slave, fmt, **opts, log_delay_ns=3_210_987)  # record time = stamp + 3.2 ms
        out[name] = p
    return out


# ---- tapost reads the export on the master's clock ------------------------------------------------
@pytest.mark.parametrize("fmt,opts,name", WRITERS)
def test_tapost_reads_the_compensated_stamps(slaves, fmt, opts, name, tmp_path):
    src = slaves[name]
    before = _digest(src)
    a = parsers.load(src)
    shift = _shift_for(a)
    dst = str(tmp_path / ("out_" + name))
    st = RESTAMP[fmt](src, dst, shift)
    assert _digest(src) == before  # the input is never modified
    assert st.format == fmt and st.damage == () and st.records == 1000  # imu 400; vel, fix, att 200 each
    assert st.records_by_type == {"/imu": 400, "/velocity": 200, "/fix": 200, "/attitude": 200}
    b = parsers.load(dst)
    assert b.meta.format == fmt and b.meta.clock == a.meta.clock
    for fa, fb in ((a.imu, b.imu), (a.nav, b.nav)):
        np.testing.assert_array_equal(_t_ns(b, fb), shift.to_master_ns(_t_ns(a, fa)))  # ns exact
        np.testing.assert_array_equal(fb.to_numpy(), fa.to_numpy())
        assert list(fb.columns) == list(fa.columns)
    lat = shift.shift_ns(_t_ns(a, a.imu))
    assert lat.min() != lat.max()  # the drift is in it


@pytest.mark.parametrize("fmt,opts,name", WRITERS)
def test_library_reads_same_messages_only_time_fields_changed(slaves, fmt, opts, name, tmp_path):
    src = slaves[name]
    shift = _shift_for(parsers.load(src))
    dst = str(tmp_path / ("lib_" + name))
    RESTAMP[fmt](src, dst, shift)
    a = _sorted(_library_messages(src, fmt))  # (message-compressed rosbag2: decompressed by rosbags)
    b = _sorted(_library_messages(dst, fmt))
    assert {k: len(v) for k, v in b.items()} == {k: len(v) for k, v in a.items()}
    for topic in a:
        for (ta, pa), (tb, pb) in zip(a[topic], b[topic]):
            assert len(pa) == len(pb) and pa[:4] == pb[:4] and pa[12:] == pb[12:]  # only the stamp differs
            sa, sb = _stamp(pa), _stamp(pb)
            assert sb == int(shift.to_master_ns(np.array([sa]))[0])
            assert ta - tb == sa - sb  # the record time moved by the stamp's shift


def _bag1_records(data: bytes, start: int, end: int):
    """(record start, {field: (value offset, value)}, data start, data end) of the ROS 1 records in
    data[start:end] (the format's framing, read here independently of tapost's scanner)."""
    off = start
    while off < end:
        (hlen,) = struct.unpack_from("<I", data, off)
        fields, p = {}, off + 4
        while p < off + 4 + hlen:
            (ln,) = struct.unpack_from("<I", data, p)
            name, _, value = data[p + 4:p + 4 + ln].partition(b"=")
            fields[name.decode()] = (p + 4 + len(name) + 1, value)
            p += 4 + ln
        (dlen,) = struct.unpack_from("<I", data, off + 4 + hlen)
        yield off, fields, off + 8 + hlen, off + 8 + hlen + dlen
        off += 8 + hlen + dlen


def _ros_ns(b: bytes) -> int:
    sec, nsec = struct.unpack("<II", b)
    return sec * 1_000_000_000 + nsec


def _reordered_index_headers(data: bytes, every: int) -> bytes:
    """``data`` (a ROS 1 bag) with the header fields of every ``every``-th index data record in reverse order
    (the same fields and length, laid out otherwise: as another writer may)."""
    out = bytearray(data)
    k = 0
    for off, f, _d0, _d1 in _bag1_records(data, len(rosbag1.MAGIC), len(data)):
        if f["op"][1] != b"\x04":
            continue
        if k % every == 0:
            (hlen,) = struct.unpack_from("<I", data, off)
            parts, p = [], off + 4
            while p < off + 4 + hlen:
                (ln,) = struct.unpack_from("<I", data, p)
                parts.append(data[p:p + 4 + ln])
                p += 4 + ln
            out[off + 4:off + 4 + hlen] = b"".join(reversed(parts))
        k += 1
    return bytes(out)


@IN_PLACE
@pytest.mark.parametrize("layout", ["as written", "index headers laid out otherwise"])
def test_uncompressed_bag_is_copied_with_only_its_time_fields_rewritten(slaves, tmp_path, layout):
    """Every time field of the copy is the shifted one, every other byte as it was; also where some index
    data records' headers are laid out otherwise than the others (read one by one, not with the rest)."""
    src = slaves["x.bag"]
    if layout != "as written":
        src = str(tmp_path / "reordered.bag")
        with open(src, "wb") as fh:
            fh.write(_reordered_index_headers(open(slaves["x.bag"], "rb").read(), 3))
    shift = _shift_for(parsers.load(src))
    dst = str(tmp_path / "out.bag")
    st = rr.restamp_rosbag1(src, dst, shift)
    assert st.how.startswith("the input's bytes copied") and st.records == 1000 and st.damage == ()
    a, b = open(src, "rb").read(), open(dst, "rb").read()
    assert len(a) == len(b)
    may_differ = np.zeros(len(a), bool)
    new_time = {}  # (record start in its chunk's data, chunk) -> its new record time
    chunks, counted = {}, {"msg": 0, "index": 0, "info": 0}
    for off, f, d0, d1 in _bag1_records(a, len(rosbag1.MAGIC), len(a)):
        op = f["op"][1][0]
        if op == 5:  # a chunk: its records
            assert f["compression"][1] == b"none"
            chunks[off] = []
            for r, g, e0, _e1 in _bag1_records(a, d0, d1):
                if g["op"][1][0] != 2:
                    continue
                t_at = g["time"][0]
                stamp_old, stamp_new = _ros_ns(a[e0 + 4:e0 + 12]), _ros_ns(b[e0 + 4:e0 + 12])
                assert stamp_new == int(shift.to_master_ns(np.array([stamp_old]))[0])
                t_new = _ros_ns(b[t_at:t_at + 8])
                assert _ros_ns(a[t_at:t_at + 8]) - t_new == stamp_old - stamp_new  # moved by the stamp's shift
                may_differ[t_at:t_at + 8] = may_differ[e0 + 4:e0 + 12] = True
                new_time[r - d0, off] = t_new
                chunks[off].append(t_new)
                counted["msg"] += 1
            last_chunk = off
        elif op == 4:  # index data: (time, offset in the chunk) entries
            for e in range(d0, d1, 12):
                (rel,) = struct.unpack_from("<I", a, e + 8)
                assert _ros_ns(b[e:e + 8]) == new_time[rel, last_chunk]
                may_differ[e:e + 8] = True
                counted["index"] += 1
        elif op == 6:  # chunk info: the first and last record time of its chunk
            (pos,) = struct.unpack("<Q", f["chunk_pos"][1])
            for name, want in (("start_time", min(chunks[pos])), ("end_time", max(chunks[pos]))):
                at = f[name][0]
                assert _ros_ns(b[at:at + 8]) == want
                may_differ[at:at + 8] = True
            counted["info"] += 1
    assert counted["msg"] == counted["index"] == 1000 and counted["info"] == len(chunks) > 0
    changed = np.flatnonzero(np.frombuffer(a, np.uint8) != np.frombuffer(b, np.uint8))
    assert len(changed) and may_differ[changed].all()  # every other byte as it was


class _RefusingMmap:
    """``mmap`` as a file system that cannot map a file for writing has it."""

    def __getattr__(self, name):
        import mmap

        return getattr(mmap, name)

    @staticmethod
    def mmap(*args, **kwargs):
        raise OSError(19, "No such device")


@pytest.mark.parametrize("why", ["an index entry points at no message", "the copy cannot be mapped"])
def test_a_bag_that_cannot_be_patched_in_place_is_written_anew(slaves, tmp_path, monkeypatch, why):
    src = slaves["x.bag"]
    if why.startswith("an index"):  # the first index entry's offset set to a place where no record starts
        data = bytearray(open(src, "rb").read())
        first = next(d0 for _off, f, d0, _d1 in _bag1_records(bytes(data), len(rosbag1.MAGIC), len(data))
                     if f["op"][1] == b"\x04")
        struct.pack_into("<I", data, first + 8, 7)
        src = str(tmp_path / "in" / "bad_index.bag")
        os.makedirs(os.path.dirname(src))
        open(src, "wb").write(bytes(data))
    else:
        from parsers import restamp

        monkeypatch.setattr(restamp, "mmap", _RefusingMmap())  # (where the copy is mapped: restamp.mapped_copy)
    a = parsers.load(src)
    shift = _shift_for(a)
    dst = tmp_path / "out.bag"
    st = rr.restamp_rosbag1(src, str(dst), shift)
    # (the scan finds no damage: the index entry's offset is what declines the patch in place)
    assert st.how.startswith("tapost's vectorised ROS 1 bag writer") and st.records == 1000 and st.damage == ()
    expected = ["in", "out.bag"] if why.startswith("an index") else ["out.bag"]
    assert sorted(os.listdir(tmp_path)) == expected  # the declined attempt's copy is gone
    b = parsers.load(str(dst))
    np.testing.assert_array_equal(_t_ns(b, b.imu), shift.to_master_ns(_t_ns(a, a.imu)))


@pytest.mark.parametrize("name", ["bag_sqlite", "bag_mcap", "bag_mcap_zfile", "bag_sqlite_zmsg"])
def test_rosbag2_metadata_times_and_counts(slaves, name, tmp_path):
    from rosbags.highlevel import AnyReader

    src = slaves[name]
    dst = tmp_path / name
    rr.restamp_rosbag2(src, str(dst), _shift_for(parsers.load(src)))
    with AnyReader([Path(src)]) as ra, AnyReader([dst]) as rb:
        times = [t for _c, t, _r in rb.messages()]
        assert (rb.start_time, rb.end_time) == (min(times), max(times) + 1)  # rosbags: end = last + 1 ns
        assert ra.start_time - rb.start_time > 0.9 * LATENCY_S * 1e9
        assert sorted((c.topic, c.msgcount, c.msgtype) for c in rb.connections) == \
            sorted((c.topic, c.msgcount, c.msgtype) for c in ra.connections)
        assert sorted(os.listdir(dst)) == sorted(os.listdir(src))  # same storage files (and compression)


def test_mcap_schemas_channels_metadata_attachments_kept(tmp_path, slave):
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    src = str(tmp_path / "extra.mcap")
    with open(src, "wb") as fh:
        mcap_ros.write_topics(fh, _topics(slave), _store("cdr"), "cdr", 1_000, "lz4")
    # append a metadata record and an attachment by writing a second file around the same content
    full = str(tmp_path / "full.mcap")
    with open(src, "rb") as fh:
        rd = make_reader(fh)
        summ = rd.get_summary()
        msgs = list(rd.iter_messages(log_time_order=False))
    with open(full, "wb") as fh:
        w = Writer(fh, compression=CompressionType.LZ4)
        w.start(profile="ros2", library="someone else 1.0")
        ids = {sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in summ.schemas.items()}
        chans = {cid: w.register_channel(c.topic, c.message_encoding, ids[c.schema_id], {"k": cid and "v" or "w"})
                 for cid, c in summ.channels.items()}
        w.add_metadata("calib", {"lever_arm_m": "0.1 0.2 0.3"})
        w.add_attachment(5, 6, "notes.txt", "text/plain", b"hello")
        for _s, ch, m in msgs:
            w.add_message(chans[ch.id], m.log_time, m.data, m.publish_time, m.sequence + 7)
        w.finish()
    dst = str(tmp_path / "out.mcap")
    shift = _shift_for(parsers.load(full))
    rr.restamp_mcap(full, dst, shift)
    from mcap.stream_reader import StreamReader

    with open(dst, "rb") as fb:  # every record, CRCs checked (chunks, attachments)
        kinds = [type(r).__name__ for r in StreamReader(fb, skip_magic=False, validate_crcs=True).records]
    assert kinds[0] == "Header" and kinds[-1] == "Footer" and "DataEnd" in kinds and "SummaryOffset" in kinds
    assert kinds.count("Message") == 1000 and "ChunkIndex" in kinds and "Statistics" in kinds
    with open(full, "rb") as fa, open(dst, "rb") as fb:
        ra, rb = make_reader(fa), make_reader(fb)
        ha, hb = ra.get_header(), rb.get_header()
        assert (ha.profile, ha.library) == (hb.profile, hb.library)
        sa, sb = ra.get_summary(), rb.get_summary()
        assert sorted((s.name, s.encoding, s.data) for s in sa.schemas.values()) == \
            sorted((s.name, s.encoding, s.data) for s in sb.schemas.values())
        assert sorted((c.topic, c.message_encoding, tuple(c.metadata.items())) for c in sa.channels.values()) == \
            sorted((c.topic, c.message_encoding, tuple(c.metadata.items())) for c in sb.channels.values())
        assert sb.statistics.message_count == sa.statistics.message_count
        assert sb.statistics.channel_message_counts == {
            c2: sa.statistics.channel_message_counts[c1] for c1, c2 in zip(sorted(sa.channels), sorted(sb.channels))}
        assert [(m.name, m.metadata) for m in rb.iter_metadata()] == [("calib", {"lever_arm_m": "0.1 0.2 0.3"})]
        assert [(x.name, x.media_type, x.data) for x in rb.iter_attachments()] == [("notes.txt", "text/plain", b"hello")]
        ma = list(ra.iter_messages(log_time_order=False))
        mb = list(rb.iter_messages(log_time_order=False))
        assert len(ma) == len(mb)
        d = np.array([a.log_time - b.log_time for (_1, _2, a), (_3, _4, b) in zip(ma, mb)])
        dp = np.array([a.publish_time - b.publish_time for (_1, _2, a), (_3, _4, b) in zip(ma, mb)])
        np.testing.assert_array_equal(d, dp)
        assert [a.sequence for *_x, a in ma] == [b.sequence for *_x, b in mb]
        # the statistics and the chunk indexes are the new times (rebuilt by the writer)
        assert sb.statistics.message_start_time == min(m.log_time for *_x, m in mb)
        assert max(ci.message_end_time for ci in sb.chunk_indexes) == max(m.log_time for *_x, m in mb)


def _store(encoding):
    from parsers import ros_common as rc

    return rc.default_typestore(encoding)


def _topics(log, encoding="cdr"):
    from parsers import ros_common as rc

    return rc.ros_topics_from_inslog(log, _store(encoding), encoding)


@pytest.mark.parametrize("encoding", ["cdr", "ros1"])
def test_nested_headers_and_headerless_types(tmp_path, slave, encoding):
    """tf2_msgs/TFMessage (Headers inside a sequence) restamped through rosbags; std_msgs/String
    (no Header) byte for byte; an Imu with a zero (unset) stamp keeps it."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    ts = _store(encoding)
    if "tf2_msgs/msg/TFMessage" not in ts.fielddefs:  # not in rosbags' noetic store
        from rosbags.typesys import get_types_from_msg

        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    ser = ts.serialize_cdr if encoding == "cdr" else ts.serialize_ros1
    des = ts.deserialize_cdr if encoding == "cdr" else ts.deserialize_ros1
    T = ts.types
    t0 = 1_700_000_000_000_000_000

    def header(t):
        return T["std_msgs/msg/Header"](**({"seq": 3} if encoding == "ros1" else {}),
                                         stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                                         frame_id="map")

    def tf(t):
        v = T["geometry_msgs/msg/Vector3"](x=1.0, y=2.0, z=3.0)
        q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        tr = [T["geometry_msgs/msg/TransformStamped"](header=header(t + k), child_frame_id=f"c{k}",
                                                       transform=T["geometry_msgs/msg/Transform"](translation=v, rotation=q))
              for k in range(2)]
        return T["tf2_msgs/msg/TFMessage"](transforms=tr)

    imu = _topics(slave, encoding)[0]
    src = str(tmp_path / "nested.mcap")
    types = ["tf2_msgs/msg/TFMessage", "std_msgs/msg/String", "sensor_msgs/msg/Imu"]
    with open(src, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2" if encoding == "cdr" else "ros1")
        ch = []
        for name in types:
            text = ts.generate_msgdef(name, ros_version=2 if encoding == "cdr" else 1)[0]
            sid = w.register_schema(name if encoding == "cdr" else name.replace("/msg/", "/"),
                                    "ros2msg" if encoding == "cdr" else "ros1msg", text.encode())
            ch.append(w.register_channel(f"/{name.split('/')[-1].lower()}", encoding, sid))
        zero = bytearray(imu.data[0])
        zero[4:12] = bytes(8)
        for i in range(50):
            t = t0 + i * 10_000_000
            w.add_message(ch[0], t + 1000, bytes(ser(tf(t), types[0])), t + 1000)
            w.add_message(ch[1], t + 2000, bytes(ser(T["std_msgs/msg/String"](data=f"s{i}"), types[1])), t + 2000)
            w.add_message(ch[2], int(imu.stamp_ns[i]), imu.data[i] if i else bytes(zero), 0)
        w.finish()
    dst = str(tmp_path / "nested_out.mcap")
    shift = ClockShift(0.5, 100.0, t0)
    st = rr.restamp_mcap(src, dst, shift, selector="imu=/imu")
    assert st.damage == () and st.records_by_type == {"/tfmessage": 50, "/string": 50, "/imu": 50}
    with open(src, "rb") as fa, open(dst, "rb") as fb:
        ma = list(make_reader(fa).iter_messages(log_time_order=False))
        mb = list(make_reader(fb).iter_messages(log_time_order=False))
    assert [c.topic for _s, c, _m in ma] == [c.topic for _s, c, _m in mb]
    for (_s, c, a), (_s2, _c2, b) in zip(ma, mb):
        d = a.log_time - b.log_time
        assert d > 0.49e9
        if c.topic == "/string":
            assert a.data == b.data
        elif c.topic == "/tfmessage":
            xa, xb = des(a.data, types[0]), des(b.data, types[0])
            for ta, tb in zip(xa.transforms, xb.transforms):
                na = ta.header.stamp.sec * 10**9 + ta.header.stamp.nanosec
                nb = tb.header.stamp.sec * 10**9 + tb.header.stamp.nanosec
                assert na - nb == d and ta.child_frame_id == tb.child_frame_id and ta.header.frame_id == "map"
            xa.transforms[0].header.stamp = xb.transforms[0].header.stamp
            xa.transforms[1].header.stamp = xb.transforms[1].header.stamp
            assert bytes(ser(xa, types[0])) == bytes(b.data)  # nothing else changed
        else:
            assert a.data[12:] == b.data[12:]
            if _stamp(a.data) == 0:
                assert _stamp(b.data) == 0  # an unset stamp stays unset
            else:
                assert _stamp(a.data) - _stamp(b.data) == d


def test_log_clock_selector(tmp_path, slave):
    """``time=log``: the shift is on the record-time clock; tapost reading with time=log gets the
    compensated record times, the header stamps moved by the same amounts."""
    src = str(tmp_path / "log.mcap")
    mcap_ros.write(src, slave, log_delay_ns=250_000_000)
    a = parsers.load(src + "::time=log")
    t = _t_ns(a, a.imu)
    shift = ClockShift(-0.02, -40.0, int(t[100]))
    dst = str(tmp_path / "log_out.mcap")
    rr.restamp_mcap(src, dst, shift, selector="time=log")
    b = parsers.load(dst + "::time=log")
    np.testing.assert_array_equal(_t_ns(b, b.imu), shift.to_master_ns(t))
    ha, hb = parsers.load(src), parsers.load(dst)
    np.testing.assert_array_equal(_t_ns(ha, ha.imu) - _t_ns(hb, hb.imu), shift.shift_ns(t))


# ---- real data --------------------------------------------------------------------------------------
def _plain_copy_by_rosbags(src: str, dst: Path) -> str:
    """``src`` written again by rosbags' own ROS 1 writer, chunks uncompressed (its layout, not tapost's)."""
    from rosbags.rosbag1 import Reader, Writer

    with Reader(Path(src)) as r, Writer(dst) as w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest,
                                        callerid=c.ext.callerid, latching=c.ext.latching) for c in r.connections}
        for c, t, raw in r.messages():
            w.write(conns[c.id], t, raw)
    return str(dst)


@pytest.mark.realdata
@pytest.mark.slow
@pytest.mark.skipif(not CAR_BAG.exists(), reason="../shared/realdata absent")
@pytest.mark.parametrize("chunks", ["bz2, as recorded", "uncompressed, by rosbags' writer"])
def test_real_car_bag(tmp_path, chunks):
    src = str(CAR_BAG) if chunks.startswith("bz2") else _plain_copy_by_rosbags(str(CAR_BAG), tmp_path / "plain.bag")
    before = _digest(src)
    sel = "imu=/xsens/imu_data"
    a = parsers.load(f"{src}::{sel}")
    shift = _shift_for(a)
    dst = str(tmp_path / "car_on_master.bag")
    st = rr.restamp_rosbag1(src, dst, shift, selector=sel)
    assert _digest(src) == before
    assert st.damage == ()
    # (a compressed bag is written anew; an uncompressed one, patched where its time fields lie, where the
    # compiled kernels read its chunks: the reference code reads them one by one and writes the bag anew)
    assert st.how.startswith("the input's bytes copied") is (chunks.startswith("uncompressed") and jit.compiled())
    b = parsers.load(f"{dst}::{sel}")
    np.testing.assert_array_equal(_t_ns(b, b.imu), shift.to_master_ns(_t_ns(a, a.imu)))
    np.testing.assert_array_equal(b.imu.to_numpy(), a.imu.to_numpy())
    la, lb = _sorted(_library_messages(src, "rosbag1")), _sorted(_library_messages(dst, "rosbag1"))
    assert {k: len(v) for k, v in lb.items()} == {k: len(v) for k, v in la.items()} == st.records_by_type
    for topic in la:
        for (ta, pa), (tb, pb) in zip(la[topic], lb[topic]):
            assert pa[:4] == pb[:4] and pa[12:] == pb[12:] and ta - tb == _stamp(pa) - _stamp(pb)
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(src)]) as ra, AnyReader([Path(dst)]) as rb:
        ca = sorted((c.topic, c.msgtype, c.digest, c.msgdef.data) for c in ra.connections)
        cb = sorted((c.topic, c.msgtype, c.digest, c.msgdef.data) for c in rb.connections)
        assert ca == cb


# ---- damage, atomicity -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def big(tmp_path_factory):
    d = tmp_path_factory.mktemp("restamp_big")
    log = synthetic_log(6000, rate_hz=200.0)
    out = {"log": log}
    for fmt, opts, name in [("mcap", {}, "b.mcap"), ("rosbag1", {"compression": "lz4"}, "b.bag"),
                            ("rosbag2", {"storage": "sqlite3"}, "bdir")]:
        p = str(d / name)
        registry.write(p, log, fmt, **opts)
        out[fmt] = p
    return out


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1"])
def test_truncated_input_writes_the_readable_part_and_names_the_damage(big, tmp_path, fmt):
    src = big[fmt]
    data = open(src, "rb").read()
    cut = str(tmp_path / ("cut_" + os.path.basename(src)))
    with open(cut, "wb") as fh:
        fh.write(data[: int(len(data) * 0.55)])
    a = parsers.load(cut)
    dst = str(tmp_path / ("out_" + os.path.basename(src)))
    shift = _shift_for(a)
    st = RESTAMP[fmt](cut, dst, shift)
    assert any("truncated" in d for d in st.damage)
    if fmt == "mcap":
        n_read = rr._scan_mcap(cut).count
    else:
        with FileMap(cut) as fmap:
            n_read = rr._scan_rosbag1(cut, fmap).count
    assert st.records == n_read and 0.3 * 3 * 6000 < st.records < 3 * 6000
    lib = _library_messages(dst, "mcap" if fmt == "mcap" else "rosbag1")
    assert sum(len(v) for v in lib.values()) == st.records  # the output is complete and indexed
    b = parsers.load(dst)
    assert len(b.imu) == len(a.imu)  # everything tapost reads from the damaged input is in the output
    np.testing.assert_array_equal(_t_ns(b, b.imu), shift.to_master_ns(_t_ns(a, a.imu)))


@pytest.mark.parametrize("case", ["zstd-crc", "zstd-undecodable", "uncompressed-crc"])
def test_damaged_mcap_chunk_is_named(big, tmp_path, case):
    """A zstd chunk that decompresses to other bytes (its CRC fails) keeps its records as far as they agree
    with its message index (here all: the inverted byte changed message data only), named as unverified; one
    that does not decompress at all is left out, named; an uncompressed chunk that fails its CRC is written as
    it is (its damage is local), named as unverified. Either way the output holds what the parser reads and
    is a complete, indexed file."""
    src = big["mcap"]
    if case == "uncompressed-crc":
        src = str(tmp_path / "plain.mcap")
        mcap_ros.write(src, big["log"], compression="none")
    data, off = mcap_with_a_flipped_chunk(src, 1, case == "zstd-undecodable")  # the second chunk's records
    bad = str(tmp_path / "flip.mcap")
    open(bad, "wb").write(data)
    st = rr.restamp_mcap(bad, str(tmp_path / "flip_out.mcap"), _shift_for(big["log"]))
    assert len(st.damage) == 1 and f"chunk at byte {off}" in st.damage[0]
    parsed = parsers.load(bad)
    if case == "uncompressed-crc":
        assert "CRC mismatch" in st.damage[0] and "unverified" in st.damage[0] and st.records == 3 * 6000
    elif case == "zstd-crc":
        assert "CRC mismatch" in st.damage[0] and "message index" in st.damage[0] and "unverified" in st.damage[0]
        assert 0 < st.records <= 3 * 6000
    else:
        assert "cannot be decompressed" in st.damage[0]
        assert 0 < st.records < 3 * 6000
    assert len(parsers.load(str(tmp_path / "flip_out.mcap")).imu) == len(parsed.imu)
    assert sum(map(len, _library_messages(str(tmp_path / "flip_out.mcap"), "mcap").values())) == st.records


@pytest.mark.parametrize("change", [777, -777])
def test_mcap_with_bytes_put_in_or_lost_inside_exports_what_the_parser_reads(big, tmp_path, change):
    """777 bytes put in (or lost) at 30 % of an MCAP move every offset after them, the summary's too. The
    parser finds the summary by its chain to the footer and reads the chunks after the damage at their moved
    offsets; the export used the footer's offsets only and stopped at the damage ("rest of file not read":
    7382 of 22518 IMU samples of a simulated multirotor written). It now writes what the parser reads."""
    raw = open(big["mcap"], "rb").read()
    k = int(0.3 * len(raw))
    bad = str(tmp_path / "moved.mcap")
    open(bad, "wb").write(raw[:k] + os.urandom(change) + raw[k:] if change > 0 else raw[:k] + raw[k - change:])
    parsed = parsers.load(bad)
    dst = str(tmp_path / "moved_out.mcap")
    shift = _shift_for(big["log"])
    st = rr.restamp_mcap(bad, dst, shift)
    assert any(f"the summary section is {change:+d} bytes from where the footer says" in d for d in st.damage)
    assert not any("rest of file not read" in d for d in st.damage), st.damage
    back = parsers.load(dst)
    assert len(back.imu) == len(parsed.imu) > 0.5 * len(big["log"].imu)  # (the damaged chunk's rest lost)
    assert parsed.imu.index[-1] == big["log"].imu.index[-1]  # (the last chunk read, and written: below)
    np.testing.assert_array_equal(_t_ns(back, back.imu), shift.to_master_ns(_t_ns(parsed, parsed.imu)))
    assert sum(map(len, _library_messages(dst, "mcap").values())) == st.records  # complete and indexed


def test_zstd_chunks_are_inflated_into_the_messages_buffer(big, tmp_path, monkeypatch):
    """A zstd MCAP's chunks are decompressed straight into one buffer, which is the messages' buffer the
    export patches (no second copy of the decompressed file); the output is byte for byte the one of the
    chunk-by-chunk path, and a damaged chunk is still named (its slice of the buffer left unused)."""
    src = big["mcap"]
    sc = rr._scan_mcap(src)
    assert sc.arena is not None and sc.compression == "zstd"
    msgs = rr._mcap_msgs(sc, sorted(sc.channels))[0]
    assert msgs.buf is sc.arena[0]
    shift = _shift_for(big["log"])
    monkeypatch.setattr(rr, "_streamed_ok", lambda *a: False)  # (the export's path that keeps the chunks)
    rr.restamp_mcap(src, str(tmp_path / "arena.mcap"), shift)
    monkeypatch.setattr(rr.mcap_ros, "chunk_arena", lambda *a, **k: None)
    assert rr._scan_mcap(src).arena is None
    rr.restamp_mcap(src, str(tmp_path / "chunks.mcap"), shift)
    assert _digest(str(tmp_path / "arena.mcap")) == _digest(str(tmp_path / "chunks.mcap"))
    monkeypatch.undo()
    data, off = mcap_with_a_flipped_chunk(src, 1)
    bad = str(tmp_path / "flip.mcap")
    open(bad, "wb").write(data)
    assert rr._scan_mcap(bad).arena is not None
    st = rr.restamp_mcap(bad, str(tmp_path / "flip_out.mcap"), shift)
    assert len(st.damage) == 1 and f"chunk at byte {off}" in st.damage[0]


@pytest.mark.parametrize("selector", [None, "time=log"])
def test_zstd_mcap_export_streams_its_chunks_with_the_bytes_of_the_path_that_keeps_them(big, tmp_path, monkeypatch,
                                                                                       selector):
    """A sound zstd MCAP of Header-first messages is exported from a streamed scan: no chunk's bytes are kept
    once walked (no buffer for the whole decompressed file: 316 MB for a 1 h IMU log), only the payloads the
    unit's planning reads (each channel's first 20, equal to the file's); the writer inflates each chunk again
    into its thread's buffer. The output is byte for byte that of the path that keeps every chunk, with
    several worker threads or one. A damaged file's streamed scan is not enough (the kept path then)."""
    from rosbags.typesys import Stores, get_typestore

    src = big["mcap"]
    shift = _shift_for(big["log"])
    sc = rr._scan_mcap(src, keep=False)
    assert sc.keep is False and sc.arena is None and all(isinstance(b[0], int) for b in sc.blocks)
    cids, streams = rr._mcap_streams(sc, get_typestore(Stores.EMPTY))
    assert rr._streamed_ok(sc, streams)
    streamed, kept = rr._mcap_msgs(sc, cids)[0], rr._mcap_msgs(rr._scan_mcap(src), cids)[0]
    assert len(streamed.buf) == 0 and streamed.kept
    assert all(streamed.payload(i) == kept.payload(i) for i in streamed.kept)
    per_channel = np.bincount(streamed.conn[sorted(streamed.kept)], minlength=len(cids))
    np.testing.assert_array_equal(per_channel, np.minimum(np.bincount(kept.conn, minlength=len(cids)),
                                                          rr._UNIT_SAMPLE))
    inflaters = []
    real = mcap_ros.chunk_inflater
    monkeypatch.setattr(mcap_ros, "chunk_inflater", lambda *a: inflaters.append(a) or real(*a))
    outs = {}
    for name, threads in (("streamed", None), ("streamed_one_thread", "1")):
        if threads:
            monkeypatch.setenv("TAPOST_IO_THREADS", threads)
        outs[name] = str(tmp_path / f"{name}.mcap")
        rr.restamp_mcap(src, outs[name], shift, selector=selector)
    assert len(inflaters) == 2
    monkeypatch.delenv("TAPOST_IO_THREADS")
    monkeypatch.setattr(rr, "_streamed_ok", lambda *a: False)
    outs["kept"] = str(tmp_path / "kept.mcap")
    rr.restamp_mcap(src, outs["kept"], shift, selector=selector)
    assert len(inflaters) == 2  # (the kept path inflates nothing again)
    assert len({_digest(p) for p in outs.values()}) == 1
    back = parsers.load(outs["streamed"] + ("::time=log" if selector else ""))
    parsed = parsers.load(src + ("::time=log" if selector else ""))
    np.testing.assert_array_equal(_t_ns(back, back.imu), shift.to_master_ns(_t_ns(parsed, parsed.imu)))
    monkeypatch.undo()
    data, _off = mcap_with_a_flipped_chunk(src, 1)
    bad = str(tmp_path / "flip.mcap")
    open(bad, "wb").write(data)
    sc = rr._scan_mcap(bad, keep=False)
    assert sc.damage and not rr._streamed_ok(sc, rr._mcap_streams(sc, get_typestore(Stores.EMPTY))[1])


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1"])
def test_mcap_and_bag_exports_turn_numpy_hugepages_on_for_their_time_only(big, slaves, tmp_path, monkeypatch, fmt):
    """The MCAP and ROS 1 bag exports run with numpy's huge-page advice on (their large buffers,
    parsers.restamp.EXPORT_HUGEPAGES) and give numpy's setting back as it was, also when they fail; the
    output bytes are those of an export with the advice off (the bag: compressed, and uncompressed in place)."""
    from numpy._core import multiarray as ma

    from parsers import restamp

    write = rr.restamp_mcap if fmt == "mcap" else rr.restamp_rosbag1
    sources = [big["mcap"]] if fmt == "mcap" else [big["rosbag1"], slaves["x.bag"]]
    seen = []
    apply = rr._apply
    monkeypatch.setattr(rr, "_apply", lambda *a: (seen.append(ma._set_madvise_hugepage(True)), apply(*a))[1])
    before = ma._set_madvise_hugepage(False)
    try:
        for k, src in enumerate(sources):
            shift = _shift_for(parsers.load(src))
            on, off = str(tmp_path / f"on{k}.{fmt}"), str(tmp_path / f"off{k}.{fmt}")
            monkeypatch.setattr(restamp, "EXPORT_HUGEPAGES", True)
            write(src, on, shift)
            assert seen[-1] is True and ma._set_madvise_hugepage(False) is False  # on inside, off again after
            with pytest.raises(InputError):
                write(str(tmp_path / "missing"), str(tmp_path / "x"), shift)
            assert ma._set_madvise_hugepage(False) is False
            monkeypatch.setattr(restamp, "EXPORT_HUGEPAGES", False)
            write(src, off, shift)
            assert seen[-1] is False
            ma._set_madvise_hugepage(False)  # (what the spy turned on, with nothing to turn it back)
            assert _digest(on) == _digest(off)
    finally:
        ma._set_madvise_hugepage(before)


@pytest.mark.parametrize("seed", range(4))
def test_far_stamps_decide_as_the_float_rule(seed):
    """rr._far_stamps (an int64 pre-check before the float64 rule) marks exactly the stamps the float64 rule
    marks: stamps near the one-day limit on either side, huge and negative record times (int64 wrap)."""
    rng = np.random.default_rng(seed)
    n = 4000
    log = rng.integers(0, 4_000_000_000_000_000_000, n)
    ref = int(rng.integers(-10**12, 10**12))
    off = rng.normal(0, 1e9, n).astype(np.int64)
    edge = rng.random(n) < 0.05  # within microseconds of the limit, or beyond
    off[edge] = (rng.choice([-1, 1], edge.sum()) * (rr._FAR_NS + rng.integers(-5000, 5000, edge.sum())))
    stamp = np.clip(log + ref + off, 1, 2**32 * 10**9 - 1)
    cases = [(stamp, log, True)]
    log2 = log.copy()
    log2[:5] = -(2**62) - rng.integers(0, 2**61, 5)  # a damaged record time read as a negative int64
    cases.append((stamp, log2, False))
    for st, lg, exact_ok in cases:
        exact = bool(int(lg.min()) >= 0 and int(st.min()) >= 0)
        assert exact is exact_ok
        for h in (np.arange(n), np.flatnonzero(~edge), np.flatnonzero(rng.random(n) < 0.5)):
            want = np.abs(st[h].astype(float) - lg[h].astype(float) - ref) > rr._FAR_NS
            got = rr._far_stamps(st, lg, h, (st - lg)[h], ref, exact)
            assert (got is None and not want.any()) or (got is not None and np.array_equal(got, want))


def test_unreadable_or_wrong_input_is_one_clear_error(big, tmp_path):
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag at all")
    with pytest.raises(InputError, match="not a ROS 1 bag"):
        rr.restamp_rosbag1(str(junk), str(tmp_path / "o.bag"), ClockShift(0.0, 0.0, 0))
    with pytest.raises(InputError, match="not an MCAP"):
        rr.restamp_mcap(str(junk), str(tmp_path / "o.mcap"), ClockShift(0.0, 0.0, 0))
    with pytest.raises(InputError):
        rr.restamp_rosbag2(str(tmp_path), str(tmp_path / "o_bag"), ClockShift(0.0, 0.0, 0))
    with pytest.raises(InputError, match="negative"):
        rr.restamp_mcap(big["mcap"], str(tmp_path / "neg.mcap"), ClockShift(2e9, 0.0, 0))
    assert not any(p.name.startswith(("o", "neg", ".o", ".neg")) for p in tmp_path.iterdir() if p.name != "junk.bag")


@pytest.mark.parametrize("fmt", ["mcap", "rosbag1", "rosbag2", "rosbag2-rows"])
def test_interrupted_write_leaves_no_partial_output(big, tmp_path, fmt, monkeypatch):
    rows = fmt == "rosbag2-rows"  # the sqlite3 bag through rosbags' writer (the path for what the byte walk
    fmt = "rosbag2" if rows else fmt  # does not take), else restamped in place at the byte level
    if fmt == "rosbag2" and not rows and not jit.compiled():
        pytest.skip(IN_PLACE.kwargs["reason"])  # (the writer's path then: the case "rosbag2-rows")
    src = big[fmt]
    before = _digest(src)
    dst = tmp_path / ("never" if fmt == "rosbag2" else f"never.{'mcap' if fmt == 'mcap' else 'bag'}")
    calls = {"n": 0}

    def boom(*_a, **_k):
        calls["n"] += 1
        if calls["n"] > 5000:
            raise KeyboardInterrupt  # the user pressing Ctrl-C half way

    if rows:  # the messages are in the database, the writer about to close (metadata.yaml)
        from rosbags.rosbag2 import Writer

        monkeypatch.setattr(rr, "_restamp_sqlite_in_place", lambda *a, **k: None)
        real = Writer.close
        calls["n"] = 5000
        monkeypatch.setattr(Writer, "close", lambda self: (boom(), real(self)))
    elif fmt == "rosbag2":  # the .db3 written, metadata.yaml about to be
        real_info = rr._write_bag_info
        calls["n"] = 5000
        monkeypatch.setattr(rr, "_write_bag_info", lambda *a: (boom(), real_info(*a)))
    else:  # our container writers: interrupted at the third chunk
        calls["n"] = 4998
        from parsers import ros_containers

        real = ros_containers.compress_chunk
        monkeypatch.setattr(ros_containers, "compress_chunk", lambda *a: (boom(), real(*a))[1])
    with pytest.raises(KeyboardInterrupt):
        RESTAMP[fmt](src, str(dst), _shift_for(big["log"]))
    assert calls["n"] > 5000
    assert list(tmp_path.iterdir()) == []  # neither the output nor a temporary file
    assert _digest(src) == before


def test_big_endian_cdr_stamps(tmp_path, slave):
    """CDR with a big-endian encapsulation header (00 00): the stamp is read and written big-endian."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    ts = _store("cdr")
    imu = _topics(slave)[0]
    src = str(tmp_path / "be.mcap")
    with open(src, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2")
        sid = w.register_schema(rr.rc.IMU, "ros2msg", ts.generate_msgdef(rr.rc.IMU, ros_version=2)[0].encode())
        ch = w.register_channel("/imu", "cdr", sid)
        for i in range(100):
            m = ts.deserialize_cdr(imu.data[i], rr.rc.IMU)
            w.add_message(ch, int(imu.stamp_ns[i]) + 1000, bytes(ts.serialize_cdr(m, rr.rc.IMU, little_endian=False)), 0)
        w.finish()
    a = parsers.load(src)
    shift = _shift_for(a)
    dst = str(tmp_path / "be_out.mcap")
    rr.restamp_mcap(src, dst, shift)
    b = parsers.load(dst)
    np.testing.assert_array_equal(_t_ns(b, b.imu), shift.to_master_ns(_t_ns(a, a.imu)))
    with open(src, "rb") as fa, open(dst, "rb") as fb:
        for (_1, _2, x), (_3, _4, y) in zip(make_reader(fa).iter_messages(), make_reader(fb).iter_messages()):
            assert y.data[:2] == b"\x00\x00" and x.data[12:] == y.data[12:]
            mx, my = ts.deserialize_cdr(x.data, rr.rc.IMU), ts.deserialize_cdr(y.data, rr.rc.IMU)
            tx = mx.header.stamp.sec * 10**9 + mx.header.stamp.nanosec
            ty = my.header.stamp.sec * 10**9 + my.header.stamp.nanosec
            assert tx - ty == x.log_time - y.log_time > 0


# ---- sqlite3 bags restamped at the byte level ----------------------------------------------------------
def _rows(db: str) -> list[tuple]:
    import sqlite3

    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        assert con.execute("PRAGMA integrity_check").fetchone() == ("ok",)  # pages, cells and the index
        return con.execute("SELECT id, topic_id, timestamp, data FROM messages ORDER BY id").fetchall()
    finally:
        con.close()


@IN_PLACE
def test_sqlite_in_place_gives_the_rows_the_rows_path_gives(big, tmp_path, monkeypatch):
    """The byte-level restamp of a .db3 and rosbags' re-insertion of its rows: the same rows (ids, topics,
    timestamps, payload bytes); the metadata table's copy of the bag information moved with them."""
    import sqlite3

    import yaml

    src, shift = big["rosbag2"], _shift_for(big["log"])
    before = _digest(src)
    st = rr.restamp_rosbag2(src, str(tmp_path / "fast"), shift)
    assert "byte level" in st.how and st.damage == ()
    with monkeypatch.context() as m:
        m.setattr(rr, "_restamp_sqlite_in_place", lambda *a, **k: None)
        st2 = rr.restamp_rosbag2(src, str(tmp_path / "rows"), shift)
    assert "rosbags" in st2.how and st2.records == st.records and st2.records_by_type == st.records_by_type
    assert _digest(src) == before
    a, b = _rows(str(tmp_path / "fast" / "bag.db3")), _rows(str(tmp_path / "rows" / "bag.db3"))
    assert len(a) == st.records and [r[1:] for r in a] == [r[1:] for r in b]
    assert [r[0] for r in a] == [r[0] for r in _rows(os.path.join(src, "bag.db3"))]  # the input's row ids
    con = sqlite3.connect(str(tmp_path / "fast" / "bag.db3"))
    (text,) = con.execute("SELECT metadata FROM metadata").fetchone()
    con.close()
    info = yaml.safe_load(text)
    info = info.get("rosbag2_bagfile_information", info)
    assert info["starting_time"]["nanoseconds_since_epoch"] == min(r[2] for r in a)
    assert parsers.load(str(tmp_path / "fast")).imu.equals(parsers.load(str(tmp_path / "rows")).imu)


def test_sqlite_rows_with_damaged_fields_are_dropped_and_named(big, tmp_path):
    """Rows a damaged page hands back with a NULL or unknown topic id or a non-integer timestamp are
    not written (the parser skips them too) and are named; every other row is exported."""
    import shutil
    import sqlite3

    src = str(tmp_path / "bag")
    shutil.copytree(big["rosbag2"], src)
    con = sqlite3.connect(os.path.join(src, "bag.db3"))
    n0 = con.execute("SELECT count(*) FROM messages").fetchone()[0]
    con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                    [(999, 1_700_000_000_000_000_000, b"x"), (1, "garbage", b"x")])  # (NULLs: NOT NULL)
    con.commit()
    con.close()
    st = rr.restamp_rosbag2(src, str(tmp_path / "out"), _shift_for(big["log"]))
    assert st.records == n0
    assert any("2 message row(s) with a damaged topic id, timestamp or data" in d for d in st.damage), st.damage
    assert len(_rows(str(tmp_path / "out" / "bag.db3"))) == n0


def test_truncated_sqlite_bag_exports_what_its_whole_pages_hold(big, tmp_path):
    """A bag whose .db3 was cut short: the export writes every row the page scan finds (no shorter file
    without a word: the damage names the truncation), and the output opens in rosbags with those rows."""
    import shutil

    from rosbags.highlevel import AnyReader

    src = str(tmp_path / "bag")
    shutil.copytree(big["rosbag2"], src)
    db = os.path.join(src, "bag.db3")
    data = open(db, "rb").read()
    with open(db, "wb") as fh:
        fh.write(data[: len(data) // 2])
    st = rr.restamp_rosbag2(src, str(tmp_path / "out"), _shift_for(big["log"]))
    n_all = len(_rows(os.path.join(big["rosbag2"], "bag.db3")))
    assert 0.35 * n_all < st.records < n_all
    assert any("page scan" in d and "truncated" in d for d in st.damage), st.damage
    with AnyReader([tmp_path / "out"]) as rd:
        assert sum(1 for _ in rd.messages()) == st.records


def test_sqlite_bag_with_bytes_put_before_its_database_exports_what_the_parse_reads(big, tmp_path):
    """A .db3 with bytes put before the database (a transfer's garbage in front of it) is read from its own
    header (tests/test_parsers_ros.py); its export stopped at 'file is not a database' (damage fuzz). The
    database from its header on is restamped, the prefix named: every row, the parse's samples on the
    master's clock, and the input untouched."""
    import shutil

    from rosbags.highlevel import AnyReader

    src = tmp_path / "bag"
    shutil.copytree(big["rosbag2"], src)
    db = src / "bag.db3"
    db.write_bytes(b"\x00garbage\xff" * 150 + db.read_bytes())
    before = _digest(str(src))
    shift = _shift_for(big["log"])
    st = rr.restamp_rosbag2(str(src), str(tmp_path / "out"), shift)
    assert _digest(str(src)) == before
    assert any("first 1350 bytes are not SQLite's" in d for d in st.damage), st.damage
    assert st.records == len(_rows(os.path.join(big["rosbag2"], "bag.db3")))
    with AnyReader([tmp_path / "out"]) as rd:
        assert sum(1 for _ in rd.messages()) == st.records
    a, b = parsers.load(str(src)), parsers.load(str(tmp_path / "out"))
    assert not any("SQLite" in w for w in b.meta.warnings)  # (a sound bag)
    np.testing.assert_array_equal(b.imu.to_numpy(), a.imu.to_numpy())
    np.testing.assert_array_equal(_t_ns(b, b.imu), shift.to_master_ns(_t_ns(a, a.imu)))
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # (no temporary left)


@pytest.mark.parametrize("cut,insert", [(8, 0), (4096, 0), (0, 100), (0, 3 * 4096)])
def test_sqlite_bag_with_bytes_cut_or_put_in_is_read_past_them(big, tmp_path, cut, insert):
    """Bytes cut from a .db3 or put into it (a transfer that lost or repeated a stretch): every later page is
    off the page grid by as much (or a whole number of pages: the b-tree's pointers land on other pages and
    SQLite answers without error but without those rows). Damage fuzz: an 8-byte cut at 2 % of a bag kept 78
    of its 8000 IMU samples, a 4 KiB cut 17. The pages are put back on the grid and the rows the b-tree does
    not lead to are found by the page scan: nearly every row read, the damage said, the export the same."""
    import shutil

    src = tmp_path / "bag"
    shutil.copytree(big["rosbag2"], src)
    db = src / "bag.db3"
    raw = db.read_bytes()
    at = len(raw) // 5 + 1234
    db.write_bytes(raw[:at] + raw[at - insert:at] + raw[at + cut:])
    full = parsers.load(big["rosbag2"])
    back = parsers.load(str(src))
    assert len(back.imu) >= 0.99 * len(full.imu), (len(back.imu), back.meta.warnings)
    assert any("page scan" in w for w in back.meta.warnings), back.meta.warnings
    assert all("\n" not in w for w in back.meta.warnings)
    t_full, t_back = _t_ns(full, full.imu), _t_ns(back, back.imu)
    assert np.isin(t_back, t_full).all()  # (rows of the bag, not bytes taken for rows)
    st = rr.restamp_rosbag2(str(src), str(tmp_path / "out"), _shift_for(full))
    assert any("page scan" in d for d in st.damage), st.damage
    assert len(parsers.load(str(tmp_path / "out")).imu) == len(back.imu)


def test_sqlite_byte_walk_survives_random_pages(big, tmp_path):
    """The compiled b-tree walks of the in-place export read page and cell offsets from the file: a page of
    random bytes put into a .db3 (damage fuzz: 4 KiB at 90 % of a bag) made one read past its buffer and the
    whole ``tapost analyze --write-slave native`` died of a segmentation fault, no line, no report. Random
    pages, flips and cuts at many places, walked in a child process (compiled kernels, as installed): it ends
    normally each time, with the walk or None (the export then re-inserts the rows)."""
    import subprocess
    import sys

    db = os.path.join(big["rosbag2"], "bag.db3")
    raw = open(db, "rb").read()
    rng = np.random.default_rng(11)
    paths = []
    for k in range(24):
        at = int(rng.integers(4096, len(raw) - 4096))
        junk = rng.integers(0, 256, 4096 if k % 3 else 64, dtype=np.uint8).tobytes()
        data = raw[:at] + junk + raw[at:] if k % 2 else raw[:at] + junk + raw[at + len(junk):]
        p = tmp_path / f"d{k}.db3"
        p.write_bytes(data)
        paths.append(str(p))
    code = ("import sys\nfrom parsers import restamp_sqlite as r\n"
            "for p in sys.argv[1:]:\n    w = r.walk(p)\n    rec = r.recover(p)\n"
            "    print(p, None if w is None else len(w.rowid), None if rec is None else len(rec.rowid))\n")
    res = subprocess.run([sys.executable, "-c", code, *paths], capture_output=True, text=True, timeout=600,
                         env={**os.environ, "TAPOST_KERNELS": "compiled"})
    assert res.returncode == 0, (res.returncode, res.stderr[-2000:])
    assert len(res.stdout.splitlines()) == len(paths)


@IN_PLACE
def test_sqlite_in_place_rebuilds_the_index_when_the_shift_reorders(tmp_path, slave):
    """Record times 1 us apart, header stamps 5 ms apart, 2000 ppm of drift: each message's shift grows by
    10 us, so the shifted record times run backwards and the index on them is rebuilt (by SQLite)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    imu = _topics(slave)[0]
    src = tmp_path / "reorder"
    ts = _store("cdr")
    with Writer(src, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        c = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=ts)
        t0 = int(imu.stamp_ns[0])
        for i in range(100):
            w.write(c, t0 + 1000 * i, imu.data[i])
    dst = tmp_path / "reorder_out"
    shift = ClockShift(0.01, 2000.0, t0)
    st = rr.restamp_rosbag2(str(src), str(dst), shift)
    assert "byte level" in st.how and "index rebuilt" in st.how
    rows = _rows(str(dst / "reorder.db3"))
    t = np.array([r[2] for r in rows])
    assert np.all(np.diff(t) < 0)  # the shift did reorder them
    stamps = np.array([int(s) for s in imu.stamp_ns[:100]])
    np.testing.assert_array_equal(t, t0 + 1000 * np.arange(100) - shift.shift_ns(stamps))
    import sqlite3

    con = sqlite3.connect(str(dst / "reorder.db3"))
    by_index = [r[0] for r in con.execute("SELECT id FROM messages INDEXED BY timestamp_idx ORDER BY timestamp")]
    con.close()
    assert by_index == [r[0] for r in sorted(rows, key=lambda r: (r[2], r[0]))]


def test_sqlite_walk_declines_what_it_does_not_expect(big, tmp_path):
    """A zeroed page, or a file that is not a rosbag2 .db3: the walk returns None and the restamp goes the
    tolerant way (which names the damage)."""
    import shutil

    from parsers import restamp_sqlite as rsq

    src = Path(big["rosbag2"])
    assert rsq.walk(str(src / "bag.db3")) is not None
    bad = tmp_path / "zeroed"
    shutil.copytree(src, bad)
    db = bad / "bag.db3"
    data = bytearray(db.read_bytes())
    page = 4096
    mid = (len(data) // page // 2) * page
    data[mid:mid + page] = bytes(page)  # a page of message rows lost
    db.write_bytes(bytes(data))
    assert rsq.walk(str(db)) is None
    st = rr.restamp_rosbag2(str(bad), str(tmp_path / "zeroed_out"), _shift_for(big["log"]))
    assert "rosbags" in st.how and any("damaged" in d for d in st.damage)
    junk = tmp_path / "junk.db3"
    junk.write_bytes(b"SQLite format 3\x00" + bytes(200))
    assert rsq.walk(str(junk)) is None


def test_io_threads_survive_a_fork(big, tmp_path):
    """A batch forks its workers after the parent may have used the chunk threads: the child starts its
    own (a pool inherited without its threads would never run the work)."""
    import multiprocessing as mp

    from parsers import threads

    if threads.workers() < 2 or "fork" not in mp.get_all_start_methods():
        pytest.skip("one core or no fork here")
    assert list(threads.ordered(lambda x: x * 2, range(5))) == [0, 2, 4, 6, 8]  # the parent's pool exists
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        res = pool.apply_async(_export_in_child, (big["mcap"], str(tmp_path / "child.mcap"), _shift_for(big["log"])))
        assert res.get(timeout=60) > 0


def _export_in_child(src: str, dst: str, shift: ClockShift) -> int:
    return rr.restamp_mcap(src, dst, shift).records


# ---- damaged stamps and bags rosbags cannot open -------------------------------------------------------
def _sqlite_copy(big, tmp_path, name: str) -> tuple[str, str]:
    import shutil

    src = str(tmp_path / name)
    shutil.copytree(big["rosbag2"], src)
    return src, os.path.join(src, "bag.db3")


def test_sqlite_row_with_a_damaged_record_time_is_left_out_and_named(big, tmp_path):
    """One row's timestamp flipped far below zero (a damaged byte): the export leaves that row out and says
    so, as the reader does, where before the 12 ms shift was refused as making record times negative."""
    import sqlite3

    src, db = _sqlite_copy(big, tmp_path, "bag_t")
    con = sqlite3.connect(db)
    n0 = con.execute("SELECT count(*) FROM messages").fetchone()[0]
    con.execute("UPDATE messages SET timestamp = ? WHERE id = ?", (-2_407_282_849_098_627_489, n0 // 2))
    con.commit()
    con.close()
    st = rr.restamp_rosbag2(src, str(tmp_path / "out"), _shift_for(big["log"]))
    assert st.records == n0 - 1
    assert any("1 message row(s) with a damaged topic id, timestamp" in d for d in st.damage), st.damage
    assert len(_rows(str(tmp_path / "out" / "bag.db3"))) == n0 - 1


def test_damaged_header_stamp_does_not_stop_the_export(big, tmp_path):
    """An /imu message whose header stamp a damaged byte set to 0.000001 s: written unchanged and named (its
    record shifted by its record time, as the reader drops a stray stamp), not "the shift would make header
    stamps negative"; every other stamp shifted as usual."""
    import sqlite3

    src, db = _sqlite_copy(big, tmp_path, "bag_h")
    con = sqlite3.connect(db)
    (tid,) = con.execute("SELECT id FROM topics WHERE name = '/imu'").fetchone()
    rid, data = con.execute("SELECT id, data FROM messages WHERE topic_id = ? ORDER BY id LIMIT 1 OFFSET 100",
                            (tid,)).fetchone()
    data = bytearray(data)
    data[4:12] = np.array([0, 1000], "<u4").tobytes()  # sec 0, nanosec 1000
    con.execute("UPDATE messages SET data = ? WHERE id = ?", (bytes(data), rid))
    con.commit()
    con.close()
    shift = _shift_for(big["log"])
    st = rr.restamp_rosbag2(src, str(tmp_path / "out"), shift)
    assert any("1 header stamp(s) more than a day from their record times (damaged?): written unchanged" in d
               for d in st.damage), st.damage
    out = dict((r[0], r[3]) for r in _rows(str(tmp_path / "out" / "bag.db3")))
    assert _stamp(out[rid]) == 1000
    a, b = parsers.load(src), parsers.load(str(tmp_path / "out"))
    np.testing.assert_array_equal(_t_ns(b, b.imu), shift.to_master_ns(_t_ns(a, a.imu)))


@pytest.mark.parametrize("damage", ["insert", "dup", "trunc"])
def test_mcap_storage_bag_rosbags_cannot_open_is_exported_from_tapost_scan(slaves, tmp_path, damage):
    """A ROS 2 bag with mcap storage whose damage stops rosbags' reader (MemoryError with no message,
    OverflowError, "File end magic is invalid"): the connections come from tapost's own scan of the
    storage file and the export writes what tapost reads, the damage named; before, the one-line error
    was rosbags' bare exception text."""
    import shutil

    from rosbags.rosbag2 import Reader

    src = str(tmp_path / "bag")
    shutil.copytree(slaves["bag_mcap"], src)
    f = os.path.join(src, [x for x in os.listdir(src) if x.endswith(".mcap")][0])
    data = open(f, "rb").read()
    n = len(data)
    new = {"insert": data[:n // 3] + bytes(range(90)) + data[n // 3:],
           "dup": data[:n * 2 // 3] + data[n // 2:n // 2 + n // 8] + data[n * 2 // 3:],
           "trunc": data[:-142]}[damage]
    with open(f, "wb") as fh:
        fh.write(new)
    with pytest.raises(Exception):
        with Reader(src) as rd:
            list(rd.connections)
    a = parsers.load(src)
    shift = _shift_for(a)
    st = rr.restamp_rosbag2(src, str(tmp_path / "out"), shift)
    b = parsers.load(str(tmp_path / "out"))
    assert len(a.imu) > 100 and abs(len(b.imu) - len(a.imu)) <= 2  # (a record the scans resynchronise on)
    assert st.records > 0.3 * sum(t.count for t in parsers.inspect_log(slaves["bag_mcap"]).streams)
    assert st.damage[0].startswith("damaged: rosbags' reader cannot open the bag ("), st.damage
    assert "\n" not in st.damage[0]


def test_damaged_mcap_storage_without_readable_channels_is_one_line(slaves, tmp_path):
    """rosbags cannot open it and tapost's scan finds no channel: one line naming the bag and the problem."""
    import shutil

    src = str(tmp_path / "bag")
    shutil.copytree(slaves["bag_mcap"], src)
    f = os.path.join(src, [x for x in os.listdir(src) if x.endswith(".mcap")][0])
    data = open(f, "rb").read()
    with open(f, "wb") as fh:
        fh.write(data[:8] + bytes(len(data) - 8))
    with pytest.raises(InputError) as ei:
        rr.restamp_rosbag2(src, str(tmp_path / "out"), ClockShift(0.01, 0.0, 0))
    text = str(ei.value)
    assert "\n" not in text and text.startswith(src) and "damaged: mcap storage unreadable by rosbags (" in text


def test_clock_shift_beyond_int64_is_a_clear_error_not_a_runtime_warning():
    """A latency no int64 nanosecond stamp can hold (an analysis of damaged stamps): a ValueError the
    export names, not numpy's "invalid value encountered in cast" on stderr and wrapped stamps."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match="beyond what int64 nanosecond stamps hold"):
            ClockShift(-18446744073.65, 0.0, 0).shift_ns(np.arange(3, dtype=np.int64))
        with pytest.raises(ValueError):
            ClockShift(float("nan"), 0.0, 0).shift_ns(np.int64(5))
        np.testing.assert_array_equal(ClockShift(1.5, 0.0, 0).shift_ns(np.arange(3, dtype=np.int64)),
                                      [1_500_000_000] * 3)


def test_a_compressed_bag_chunk_damaged_part_way_keeps_what_decompresses(tmp_path):
    """An lz4 chunk of a ROS 1 bag that stops decompressing part way (64 zeroed bytes at 70 % of its data)
    was lost whole ('cannot be decompressed': about 1500 of 12000 IMU samples). What decompresses before the
    damaged block is now walked, as an MCAP chunk's is; the native export writes the same messages."""
    import struct

    p = str(tmp_path / "z.bag")
    registry.write(p, synthetic_log(12000, rate_hz=200.0), "rosbag1", compression="lz4")
    data = bytearray(open(p, "rb").read())
    off, chunks = len(rosbag1.MAGIC), []
    while off < len(data):  # the top-level records: (header, data) pairs
        (hlen,) = struct.unpack_from("<I", data, off)
        (dlen,) = struct.unpack_from("<I", data, off + 4 + hlen)
        if b"op=\x05" in data[off + 4:off + 4 + hlen]:
            chunks.append((off, off + 8 + hlen, off + 8 + hlen + dlen))
        off += 8 + hlen + dlen
    at, d0, d1 = chunks[1]
    i = d0 + int(0.7 * (d1 - d0))
    data[i:i + 64] = bytes(64)
    bad = str(tmp_path / "bad.bag")
    open(bad, "wb").write(bytes(data))
    a = parsers.load(bad)
    said = [w for w in a.meta.warnings if f"chunk at byte {at} cannot be decompressed" in w]
    assert said and "read as far as it decompresses" in said[0]
    assert 0.9 * 12000 < len(a.imu) < 12000
    st = rr.restamp_rosbag1(bad, str(tmp_path / "out.bag"), _shift_for(a))
    assert any("read as far as it decompresses" in d for d in st.damage)
    b = parsers.load(str(tmp_path / "out.bag"))
    np.testing.assert_array_equal(_t_ns(b, b.imu), _shift_for(a).to_master_ns(_t_ns(a, a.imu)))


def test_a_damaged_record_time_is_set_anew_from_the_header_stamp(tmp_path):
    """A ROS 1 bag whose record time a damaged byte moved by decades (its header stamp sound): the parser,
    which reads header stamps, keeps the message; the export dropped it as unshiftable, so its output read
    back shorter than the parse (2 of 6000 IMU samples, found by a damage sweep). The record time is now set
    anew from the header stamp, and the output reads back as the parse, on the master's clock."""
    p = str(tmp_path / "a.bag")
    registry.write(p, synthetic_log(3000, rate_hz=200.0), "rosbag1")
    data = bytearray(open(p, "rb").read())
    field = b"\x0d\x00\x00\x00time="  # (a MSG_DATA record's time field: 13 bytes, sec then nsec)
    at, k = -1, 0
    while k < 1500:
        at = data.find(field, at + 1)
        k += 1
    data[at + len(field) + 3] ^= 0x10  # the sec's high byte: 8.6 years later
    bad = str(tmp_path / "bad.bag")
    open(bad, "wb").write(bytes(data))
    a = parsers.load(bad)
    sh = _shift_for(a)
    st = rr.restamp_rosbag1(bad, str(tmp_path / "out.bag"), sh)
    assert any("set anew from their header stamps" in d for d in st.damage)
    b = parsers.load(str(tmp_path / "out.bag"))
    assert (len(b.imu), len(b.nav)) == (len(a.imu), len(a.nav))
    np.testing.assert_array_equal(_t_ns(b, b.imu), sh.to_master_ns(_t_ns(a, a.imu)))


@pytest.mark.parametrize("name", ["xn.mcap", "x.bag"])
def test_a_damaged_message_definition_is_restamped_by_the_built_in_one_the_reader_uses(slaves, name, tmp_path):
    """The reader decodes a topic whose stored definition is unusable by rosbags' built-in one (and says
    so); the export kept such payloads unchanged, so the exported /fix stamps stayed on the slave's clock
    while its other topics moved (a bit-flipped MCAP's export read back 763 navigation rows for 382)."""
    data = Path(slaves[name]).read_bytes()
    assert b"float64 latitude" in data
    src = tmp_path / ("bad_" + name)
    src.write_bytes(data.replace(b"float64 latitude", b"float64 lat{tude"))  # (same length: offsets kept)
    a = parsers.load(str(src))
    assert any("/fix: message definition of sensor_msgs/msg/NavSatFix unusable" in w for w in a.meta.warnings)
    shift = _shift_for(a)
    dst = str(tmp_path / ("out_" + name))
    st = RESTAMP[name.endswith(".mcap") and "mcap" or "rosbag1"](str(src), dst, shift)
    assert not any("no definition" in n for n in st.damage), st.damage
    b = parsers.load(dst)
    np.testing.assert_array_equal(_t_ns(b, b.nav), shift.to_master_ns(_t_ns(a, a.nav)))
    np.testing.assert_array_equal(b.nav.to_numpy(), a.nav.to_numpy())


def test_time_field_kernels_equal_the_numpy_code(monkeypatch):
    """The kernels that read and write Header stamps and MCAP records' log/publish times (one pass, per chunk in
    the writer's threads) give the numpy code's bytes: little- and big-endian CDR stamps, unset (0) publish
    times left at 0, negative results wrapped as the uint64 fields hold them."""
    from logtools import jit

    rng = np.random.default_rng(11)
    n, size = 500, 64
    buf0 = rng.integers(0, 256, n * size, dtype=np.uint8)
    starts = np.arange(n, dtype=np.int64) * size + 20
    buf0[starts[::3] + 1] = 0  # CDR encapsulation 00 00: big endian
    buf0[starts[1::3] + 1] = 1
    pub_at = (starts - 8)[::4]
    buf0[pub_at[:, None] + np.arange(8)] = 0  # unset publish times
    new = rng.integers(0, 2**62, n)
    log = rng.integers(0, 2**62, n)
    delta = rng.integers(-(2**40), 2**40, n)
    delta[7] = 2**63 - 1  # (a publish time less a large delta: negative, wrapped)

    def run(use_kernels: bool):
        monkeypatch.setattr(jit, "compiled", lambda: use_kernels)
        buf = buf0.copy()
        stamp, be = rr.rcw.header_stamps(buf, starts, True)
        rr.rcw.put_header_stamps(buf, starts, new, be)
        rr.rcw.patch_mcap_times(buf, starts, log, delta)
        return stamp, be, buf

    kernels = jit.mode() == "compiled"
    want = run(False)
    stamp, be, buf = want
    assert be[::3].all() and not be[1::3].any()
    raw = buf0[(starts + 4)[:, None] + np.arange(8)].copy()
    raw[be] = raw[be].reshape(-1, 2, 4)[:, :, ::-1].reshape(-1, 8)  # (big-endian words as little-endian)
    sec_nsec = raw.view("<u4").astype(np.int64)
    np.testing.assert_array_equal(stamp, sec_nsec[:, 0] * 10**9 + sec_nsec[:, 1])
    pub = buf[(starts - 8)[:, None] + np.arange(8)].copy().view("<i8").ravel()
    pub0 = buf0[(starts - 8)[:, None] + np.arange(8)].copy().view("<i8").ravel()
    np.testing.assert_array_equal(pub, np.where(pub0 != 0, pub0 - delta, 0))
    np.testing.assert_array_equal(buf[(starts - 16)[:, None] + np.arange(8)].copy().view("<i8").ravel(), log)
    got_stamps = buf[(starts + 4)[:, None] + np.arange(8)].copy()
    got_stamps[be] = got_stamps[be].reshape(-1, 2, 4)[:, :, ::-1].reshape(-1, 8)
    v = got_stamps.view("<u4").astype(np.int64)
    np.testing.assert_array_equal(v[:, 0], (new // 10**9) % 2**32)
    np.testing.assert_array_equal(v[:, 1], new % 10**9)
    if not kernels:
        pytest.skip("numba kernels not in use in this process (the numpy code checked)")
    got = run(True)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


# ---- the Header stamps' fast path and the chunk-by-chunk stamp writes -----------------------------------
@pytest.mark.parametrize("n_streams", [4, 40])
def test_messages_by_stream_are_flatnonzero_of_each_stream(n_streams):
    conn = np.random.default_rng(n_streams).integers(0, n_streams, 5000)
    conn[conn == 2] = 1  # (a stream without messages)
    order, sls, where = rr._by_stream(conn, n_streams)
    for k in range(n_streams):
        want = np.flatnonzero(conn == k)
        assert np.array_equal(where[k], want) and np.array_equal(order[sls[k]], want)
    assert sls[-1].stop == len(conn)


def _apply_both_ways(path: str, shift: ClockShift, monkeypatch, change=None):
    """``_apply`` on ``path``'s messages (``change(msgs)`` first) as it runs, and with the all-stamped fast
    path turned off: (new record times, payload bytes after the stamps are written, notes) of each, and
    whether the fast path answered."""
    from rosbags.typesys import Stores, get_typestore

    out = []
    for fast in (True, False):
        sc = rr._scan_mcap(path)
        ts = get_typestore(Stores.EMPTY)
        cids, streams = rr._mcap_streams(sc, ts)
        msgs, _layout = rr._mcap_msgs(sc, cids)
        if change is not None:
            change(msgs)
        calls = []
        real = rr._all_stamped
        monkeypatch.setattr(rr, "_all_stamped", (lambda *a: calls.append(r := real(*a)) or r) if fast
                            else (lambda *a: None))
        later: list = []
        new_log, got, notes = rr._apply(streams, msgs, ts, shift, None, path, later)
        for patch in later:  # (as the writer writes them, chunk by chunk)
            for a in range(0, len(got.log_ns), 997):
                patch.write(got.buf, got.starts, slice(a, min(a + 997, len(got.log_ns))))
        out.append((new_log, got.buf.copy(), notes, bool(calls) and calls[0] is not None))
    return out


def test_all_stamped_fast_path_gives_the_general_numbers(big, monkeypatch):
    """An IMU log's topics (every message Header-first, stamped, on one clock): the fast path answers, with
    the record times, payload bytes and notes of the general path (stream order, medians)."""
    (a_log, a_buf, a_notes, used), (b_log, b_buf, b_notes, _) = _apply_both_ways(
        big["mcap"], _shift_for(big["log"]), monkeypatch)
    assert used
    assert np.array_equal(a_log, b_log) and np.array_equal(a_buf, b_buf) and a_notes == b_notes


def _put_stamp(msgs, i: np.ndarray, value_ns: int) -> None:
    """Message ``i``'s Header stamp set to ``value_ns`` (little-endian CDR), in its payload and in the scan's
    heads."""
    sec, nsec = divmod(int(value_ns), 1_000_000_000)
    b = np.frombuffer(struct.pack("<II", sec, nsec), np.uint8)
    for j in np.atleast_1d(i):
        msgs.buf[msgs.starts[j] + 4:msgs.starts[j] + 12] = b
        if msgs.heads is not None:
            msgs.heads[j, 4:12] = b


@pytest.mark.parametrize("case", ["an unset stamp", "a stamp a day off", "a topic 20 s off", "stamps 9 s apart"])
def test_all_stamped_fast_path_declines_what_the_medians_decide(big, monkeypatch, case):
    """Where a stamp is unset (0), damaged (a day from its record time), or a topic is on another clock, the
    fast path does not answer and the general path decides as before; stamps within 9 s of one another (the
    medians' decisions known without them): it answers, with the same numbers."""
    def change(msgs):
        k = np.flatnonzero(msgs.conn == msgs.conn[0])
        if case == "an unset stamp":
            _put_stamp(msgs, k[5], 0)
        elif case == "a stamp a day off":
            _put_stamp(msgs, k[5], int(msgs.log_ns[k[5]]) + 2 * 86_400_000_000_000)
        elif case == "a topic 20 s off":
            other = np.flatnonzero(msgs.conn == (msgs.conn[0] + 1) % 3)
            stamps = rr.rcw.header_stamps(msgs.buf, msgs.starts[other], True)[0]
            for j, s in zip(other.tolist(), stamps.tolist()):
                _put_stamp(msgs, j, s + 20_000_000_000)
        else:
            stamps = rr.rcw.header_stamps(msgs.buf, msgs.starts[k[:50]], True)[0]
            for j, s in zip(k[:50].tolist(), stamps.tolist()):
                _put_stamp(msgs, j, s + 9_000_000_000)

    (a_log, a_buf, a_notes, used), (b_log, b_buf, b_notes, _) = _apply_both_ways(
        big["mcap"], _shift_for(big["log"]), monkeypatch, change)
    assert used is (case == "stamps 9 s apart")
    assert np.array_equal(a_log, b_log) and np.array_equal(a_buf, b_buf) and a_notes == b_notes
    if case == "a stamp a day off":
        assert any("more than a day" in n for n in a_notes)


def test_mcap_export_input_is_mapped_copy_on_write(tmp_path, slave):
    """The scan's writable view of the input (uncompressed chunks are patched in it) is a private
    copy-on-write map: the export of an uncompressed MCAP leaves the file's bytes as they were."""
    src = str(tmp_path / "plain.mcap")
    mcap_ros.write(src, slave, compression="none")
    before = _digest(src)
    view = rr._private_map(src)
    assert view.flags.writeable
    view[:64] = 0
    st = rr.restamp_mcap(src, str(tmp_path / "out.mcap"), _shift_for(slave))
    assert _digest(src) == before and st.records > 0 and not st.damage
    assert rr._private_map(str(tmp_path / "out.mcap")).tobytes()[:8] == mcap_ros.MAGIC
