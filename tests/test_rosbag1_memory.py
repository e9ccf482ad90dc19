"""ROS 1 bags decoded while read (rosbag1.read_streamed, what ``load`` and ``inventory`` use): record times
as int64 arrays and payloads fed to the streaming column decoder instead of one bytes object per message.
The result must be exactly that of the classic read (every message's bytes, then decode_topic), and the
numbers those of the rosbags library's own reader, for clean bags of several chunks (uncompressed, lz4,
bz2) and damaged ones (cut in the middle of a chunk, a zeroed block), on both record paths (vectorised
runs and record by record)."""
from __future__ import annotations

import types

import numpy as np
import pytest

import parsers
from parsers import registry, rosbag1
from parsers import ros_common as rc
from parsers.base import Selector


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """A 1 kHz IMU + 100 Hz nav bag of several chunks, written uncompressed, lz4 and bz2."""
    from logtools import sim

    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=8.0, slave_imu_rate_hz=1000.0,
                                            slave_nav_rate_hz=100.0))
    d = tmp_path_factory.mktemp("rb1mem")
    out = {}
    for comp in ("none", "lz4", "bz2"):
        p = str(d / f"s_{comp}.bag")
        registry.write(p, pair.slave, "rosbag1", compression=comp)
        out[comp] = p
    return out


@pytest.fixture(params=[True, False], ids=["vectorised", "one_by_one"])
def path_kind(request, monkeypatch):
    """Both record paths of rosbag1._Scan.records, whatever the process's kernel mode (reference mode: the
    vectorised path runs the Python walk)."""
    monkeypatch.setattr(rosbag1, "jit", types.SimpleNamespace(compiled=lambda: request.param))
    return request.param


def _chunks(data: bytes) -> int:
    return sum(1 for _o, _n, op in _top_records(data) if op == b"\x05")


def _top_records(data: bytes) -> list[tuple[int, int, bytes]]:
    out, off = [], len(rosbag1.MAGIC)
    while off + 8 <= len(data):
        hlen = int.from_bytes(data[off:off + 4], "little")
        if off + 8 + hlen > len(data):
            break
        dlen = int.from_bytes(data[off + 4 + hlen:off + 8 + hlen], "little")
        out.append((off, off + 8 + hlen + dlen, rosbag1._fields(data[off + 4:off + 4 + hlen]).get("op")))
        off += 8 + hlen + dlen
    return out


def _same_inslog(a, b) -> None:
    from pandas.testing import assert_frame_equal

    assert_frame_equal(a.imu, b.imu, check_exact=True)
    assert_frame_equal(a.nav, b.nav, check_exact=True)
    assert a.meta == b.meta


def _streamed_equals_classic(p: str) -> rc.RawLog:
    raw = rosbag1.read_raw(p)
    st = rosbag1.read_streamed(p)
    assert st.warnings == raw.warnings
    assert set(st.topics) == set(raw.topics)
    kept = [n for n, t in st.topics.items() if t.decoded is not None]
    assert "/imu" in kept
    for name, t in st.topics.items():
        r = raw.topics[name]
        assert isinstance(t.log_ns, np.ndarray) and t.log_ns.dtype == np.int64
        np.testing.assert_array_equal(t.log_ns, np.asarray(r.log_ns, np.int64), err_msg=name)
        if t.decoded is None:
            continue
        assert t.data == r.data[:rc.HEAD_MESSAGES]
        dec = rc.decode_topic(raw.typestore, r, {**rc.FIELDS[t.msgtype], **rc.STAMP_FIELDS})
        pre = t.decoded
        assert len(pre.stamp_ns) == r.count
        assert (pre.n_fast, len(pre.slow_idx)) == (dec.n_fast, dec.n_slow)
        for k, v in pre.columns.items():
            np.testing.assert_array_equal(v, dec.columns[k], err_msg=f"{name} {k}")
        np.testing.assert_array_equal(pre.stamp_ns, dec.columns["sec"].astype(np.int64) * 1_000_000_000
                                      + dec.columns["nsec"].astype(np.int64))
    for sel in ("", "time=log"):
        s = Selector.parse(sel)
        _same_inslog(rc.to_inslog(rosbag1.read_streamed(p), s, release=True), rc.to_inslog(rosbag1.read_raw(p), s))
    _same_inslog(parsers.load(p), rc.to_inslog(raw, Selector()))
    assert rosbag1.inventory(p) == rc.to_inventory(rosbag1.read_raw(p))
    return st


@pytest.mark.parametrize("comp", ["none", "lz4", "bz2"])
def test_streamed_read_equals_classic_and_rosbags(bags, comp, path_kind):
    from rosbags.highlevel import AnyReader
    from pathlib import Path

    p = bags[comp]
    assert _chunks(open(p, "rb").read()) > 2
    st = _streamed_equals_classic(p)
    # the numbers against the rosbags library's own reader and deserialiser, message by message
    imu = st.topics["/imu"]
    paths = rc.FIELDS[imu.msgtype]
    got_t, got = [], {k: [] for k in paths}
    stamps = []
    with AnyReader([Path(p)]) as reader:
        conns = [c for c in reader.connections if c.topic == "/imu"]
        for conn, t, data in reader.messages(connections=conns):
            msg = reader.deserialize(data, conn.msgtype)
            got_t.append(t)
            stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            for k, path in paths.items():
                got[k].append(float(rc._getpath(msg, path)))
    np.testing.assert_array_equal(imu.log_ns, np.array(got_t, np.int64))
    np.testing.assert_array_equal(imu.decoded.stamp_ns, np.array(stamps, np.int64))
    for k in imu.decoded.columns:
        np.testing.assert_array_equal(imu.decoded.columns[k], np.array(got[k]), err_msg=k)


def _damaged(src: str, dst: str, how: str) -> str:
    data = bytearray(open(src, "rb").read())
    chunks = [(o, n) for o, n, op in _top_records(bytes(data)) if op == b"\x05"]
    o, n = chunks[len(chunks) // 2]
    if how == "cut":
        data = data[:(o + n) // 2]
    else:
        k = (o + n) // 2
        data[k:k + 4096] = bytes(4096)
    with open(dst, "wb") as fh:
        fh.write(bytes(data))
    return dst


@pytest.mark.parametrize("comp", ["none", "lz4"])
@pytest.mark.parametrize("how", ["cut", "zeroed"])
def test_damaged_bags_give_the_same_warnings_and_log(bags, tmp_path, comp, how, path_kind):
    p = _damaged(bags[comp], str(tmp_path / f"{how}_{comp}.bag"), how)
    st = _streamed_equals_classic(p)
    want = {("cut", "none"): "truncated", ("cut", "lz4"): "truncated",
            ("zeroed", "none"): "damaged record(s)", ("zeroed", "lz4"): "cannot be decompressed"}[how, comp]
    assert any(want in w for w in st.warnings), st.warnings
    back = parsers.load(p)
    assert any(want in w for w in back.meta.warnings)
    full = parsers.load(bags[comp])
    assert 0 < len(back.imu) < len(full.imu)


def test_kept_topic_on_two_connections_is_read_the_classic_way(bags, tmp_path):
    """read_raw merges such a topic in time order: the streamed read gives up (NotStreamable) and load
    falls back to the classic read."""
    from rosbags.rosbag1 import Writer

    ts = rc.default_typestore("ros1")
    log = parsers.load(bags["none"])
    topics = rc.ros_topics_from_inslog(log, ts, "ros1")
    imu = next(t for t in topics if t.name == "/imu")
    p = str(tmp_path / "two.bag")
    with Writer(p) as w:
        conns = [w.add_connection("/imu", imu.msgtype, typestore=ts, callerid=f"/node{i}") for i in range(2)]
        for i, (t, d) in enumerate(zip(imu.stamp_ns.tolist(), imu.data)):
            w.write(conns[i % 2], t, d)
    with pytest.raises(rc.NotStreamable):
        rosbag1.read_streamed(p)
    _same_inslog(parsers.load(p), rc.to_inslog(rosbag1.read_raw(p), Selector()))
