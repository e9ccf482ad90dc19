"""MCAP with JSON-encoded messages (``message_encoding: json``, the ROS message's fields as JSON objects: what a
tool without ROS writes with the mcap library): read as the CDR encoding of the same messages is, and
exported natively with the header stamps' digits rewritten in the text, every other byte kept."""
from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from parsers import registry
from parsers.restamp import ClockShift
from pipelines import export

STAMP = re.compile(rb'"stamp"\s*:\s*\{[^{}]*\}')


def _as_json(obj, nsec_name: str):
    """A rosbags message as the plain JSON object a ROS-less writer makes (ROS time's nanoseconds under
    ``nsec_name``: ROS 2's nanosec, Foxglove's nsec, rosbridge's nsecs with secs)."""
    if dataclasses.is_dataclass(obj):
        d = {f.name: _as_json(getattr(obj, f.name), nsec_name) for f in dataclasses.fields(obj)
             if not f.name.startswith("__")}
        if set(d) == {"sec", "nanosec"}:
            d = {"secs" if nsec_name == "nsecs" else "sec": d["sec"], nsec_name: d["nanosec"]}
        return d
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


def _json_mcap(src: str, dst: str, nsec_name: str, indent: int | None = None, header: bool = True) -> None:
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with open(src, "rb") as f, open(dst, "wb") as out:
        w = Writer(out, compression=CompressionType.ZSTD)
        w.start()
        schemas, channels = {}, {}
        for schema, channel, msg in make_reader(f).iter_messages():
            if channel.id not in channels:
                if schema.name not in schemas:
                    schemas[schema.name] = w.register_schema(schema.name, "jsonschema", b"{}")
                channels[channel.id] = w.register_channel(channel.topic, "json", schemas[schema.name])
            obj = _as_json(store.deserialize_cdr(msg.data, schema.name), nsec_name)
            if not header:
                obj.pop("header")
            text = json.dumps(obj, indent=indent)
            w.add_message(channels[channel.id], msg.log_time, text.encode(), msg.publish_time, msg.sequence)
        w.finish()


@pytest.fixture(scope="module")
def cdr(tmp_path_factory):
    from logtools import sim

    pair = sim.simulate(sim.scenario_config("aircraft", duration_s=30.0, seed=2))
    path = tmp_path_factory.mktemp("json") / "cdr.mcap"
    registry.write(str(path), pair.slave, "mcap")
    return str(path)


def _stamps_ns(log, frame) -> np.ndarray:
    return log.meta.t0_ns + np.round(frame.index.to_numpy() * 1e9).astype(np.int64)


@pytest.mark.parametrize("nsec_name,indent", [("nanosec", None), ("nsec", None), ("nsecs", 2)])
def test_json_mcap_reads_as_its_cdr_twin(cdr, tmp_path, nsec_name, indent):
    """Every column and stamp the same as the CDR file's (JSON keeps a float64 exactly); ROS time under any of
    its JSON names; indented text too. Before, each topic was "message encoding 'json' not supported"."""
    path = str(tmp_path / "json.mcap")
    _json_mcap(cdr, path, nsec_name, indent)
    a, b = registry.load(cdr), registry.load(path)
    assert b.meta.clock == a.meta.clock and b.meta.t0_ns == a.meta.t0_ns
    for fa, fb in ((a.imu, b.imu), (a.nav, b.nav)):
        np.testing.assert_array_equal(fa.index.to_numpy(), fb.index.to_numpy())
        np.testing.assert_array_equal(fa.to_numpy(), fb.to_numpy())
    assert not [w for w in b.meta.warnings if not w.startswith("note")], b.meta.warnings


def test_json_mcap_native_export_rewrites_only_the_stamps(cdr, tmp_path):
    """The native export of a JSON MCAP: header stamps on the master's clock (read back: exactly the shift of
    the input's), every message kept per topic, each text the same but the stamp's digits (which may change
    its length: the record laid out anew); the mcap library reads it. Before, the text was copied unchanged
    and only the record times moved: the export read back on the slave's own clock."""
    from mcap.reader import make_reader

    src = str(tmp_path / "json.mcap")
    _json_mcap(cdr, src, "nanosec")
    a = registry.load(src)
    shift = ClockShift(0.0417, 15.0, a.meta.t0_ns + 15_000_000_000)
    dst = str(tmp_path / "out.mcap")
    st = export.write_native(src, dst, "mcap", shift, a.meta.selector)
    assert not st.damage
    b = registry.load(dst)
    for fa, fb in ((a.imu, b.imu), (a.nav, b.nav)):
        np.testing.assert_array_equal(_stamps_ns(b, fb), shift.to_master_ns(_stamps_ns(a, fa)))
        np.testing.assert_array_equal(fa.to_numpy(), fb.to_numpy())

    def texts(path):
        out: dict[str, list[bytes]] = {}
        with open(path, "rb") as f:
            for _s, ch, m in make_reader(f).iter_messages(log_time_order=False):
                out.setdefault(ch.topic, []).append(STAMP.sub(b"STAMP", m.data))
        return out

    ta, tb = texts(src), texts(dst)
    assert {k: len(v) for k, v in ta.items()} == {k: len(v) for k, v in tb.items()}
    assert all(sorted(ta[k]) == sorted(tb[k]) for k in ta)


def test_json_mcap_without_headers_is_read_on_its_record_times(cdr, tmp_path):
    """JSON objects without a header (a writer that leaves the time to the MCAP record): every message was
    "undecodable (damaged)" and the topic empty. Read on the record times, said; the native export shifts
    those (the text has no stamp to rewrite)."""
    with_hdr, src = str(tmp_path / "json.mcap"), str(tmp_path / "bare.mcap")
    _json_mcap(cdr, with_hdr, "nanosec")
    _json_mcap(cdr, src, "nanosec", header=False)
    a, ref = registry.load(src), registry.load(with_hdr)
    assert (len(a.imu), len(a.nav)) == (len(ref.imu), len(ref.nav))
    assert any("its JSON messages have no header stamp; log time used instead" in w for w in a.meta.warnings)
    np.testing.assert_array_equal(a.imu.to_numpy(), ref.imu.to_numpy())
    shift = ClockShift(0.0417, 15.0, a.meta.t0_ns + 15_000_000_000)
    dst = str(tmp_path / "out.mcap")
    export.write_native(src, dst, "mcap", shift, a.meta.selector)
    b = registry.load(dst)
    np.testing.assert_array_equal(_stamps_ns(b, b.imu), shift.to_master_ns(_stamps_ns(a, a.imu)))
