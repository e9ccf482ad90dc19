"""Shared by the ROS format modules (rosbag1, rosbag2, mcap_ros): raw messages -> InsLog.

The readers (``rosbag1``, ``rosbag2``, ``mcap_ros``) only deliver raw serialised messages per topic
(:class:`RawLog`: bytes + log/record time + the message definitions as a rosbags ``Typestore``).
Everything ROS-specific about the *content* lives here:

* **Vectorised decode** (:func:`decode_topic`). Messages of one topic that have the same length
  (Imu, TwistStamped, NavSatFix, Odometry... whose only variable part is the ``frame_id`` string)
  are decoded as one group with ``np.frombuffer`` on a numpy structured dtype built from the message
  definition (:func:`build_layout`: CDR alignment relative to the payload after the 4-byte
  encapsulation header; ROS 1 packed little-endian). String/sequence lengths are read from a sample
  message and checked on every message of the group; anything that does not fit is decoded by the
  rosbags deserialiser (the reference implementation), message by message.
* **Frames** (REP-103/105): ROS world frames are ENU, body frames FLU. Converted here (and only
  here) to NED/FRD with :mod:`logtools.conventions`:
  ``sensor_msgs/Imu``: angular_velocity, linear_acceleration FLU -> FRD; orientation (FLU body in ENU
  world) -> body FRD to NED. ``covariance[0] == -1`` marks a field as absent (REP-145).
  ``nav_msgs/Odometry``: pose orientation as attitude, twist in ``child_frame_id`` = body (REP-105):
  twist.angular is a body rate (usable as gyro), twist.linear is rotated to NED with the message's
  own pose orientation. ``geometry_msgs/TwistStamped``, ``TwistWithCovarianceStamped``,
  ``Vector3Stamped``: velocity, **assumed ENU world** unless the selector says ``vel_frame=body``
  (then FLU body, rotated to NED with the selected attitude). ``sensor_msgs/NavSatFix``: lat, lon,
  alt (status < 0 = no fix, dropped). ``geometry_msgs/QuaternionStamped``, ``PoseStamped``,
  ``PoseWithCovarianceStamped``: attitude (FLU body in ENU world).
* **Clock**: ``header.stamp`` by default (``stamp_source`` says so); ``time=log`` uses the bag's
  log/record time. Epoch or sim/boot time is decided by magnitude (> 1e9 s = epoch). A topic whose
  header stamps are all zero falls back to log time, with a warning.
* **Selector** keys: ``imu=/topic`` (sensor_msgs/Imu), ``odom=/topic`` (Odometry: gyro from
  twist.angular, attitude, velocity), ``att=/topic``, ``vel=/topic``, ``pos=/topic``,
  ``time=header|log``, ``vel_frame=enu|body``. Without a selector: the first Imu topic (in the log's order) and
  the best navigation topics; the choice is reported in ``meta.warnings`` ("selected: ...").
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from logtools.conventions import (
    dcm_from_quat,
    ned_to_enu,
    frd_to_flu,
    quat_mul,
    quat_slerp,
    quat_make_continuous,
)
from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers.assemble import Stream, assemble_inslog
from parsers.base import Inventory, Selector, StreamInfo, rate_of

# ---- message types --------------------------------------------------------------------------
IMU = "sensor_msgs/msg/Imu"
ODOM = "nav_msgs/msg/Odometry"
TWIST = "geometry_msgs/msg/TwistStamped"
TWIST_COV = "geometry_msgs/msg/TwistWithCovarianceStamped"
VEC3 = "geometry_msgs/msg/Vector3Stamped"
FIX = "sensor_msgs/msg/NavSatFix"
QUAT_STAMPED = "geometry_msgs/msg/QuaternionStamped"
POSE = "geometry_msgs/msg/PoseStamped"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"

#: the kind of stream each supported type provides (StreamInfo.kind)
KIND = {IMU: "imu", ODOM: "odom", TWIST: "vel", TWIST_COV: "vel", VEC3: "vel", FIX: "pos",
        QUAT_STAMPED: "att", POSE: "att", POSE_COV: "att"}
SUPPORTED = frozenset(KIND)

_Q = ("x", "y", "z", "w")
_V = ("x", "y", "z")
#: field paths (dotted; a trailing integer indexes a fixed array) extracted per type
FIELDS: dict[str, dict[str, str]] = {
    IMU: {**{f"q{c}": f"orientation.{c}" for c in _Q},
          **{f"g{c}": f"angular_velocity.{c}" for c in _V},
          **{f"a{c}": f"linear_acceleration.{c}" for c in _V},
          "q_cov0": "orientation_covariance.0", "g_cov0": "angular_velocity_covariance.0",
          "a_cov0": "linear_acceleration_covariance.0"},
    ODOM: {**{f"q{c}": f"pose.pose.orientation.{c}" for c in _Q},
           **{f"p{c}": f"pose.pose.position.{c}" for c in _V},
           **{f"v{c}": f"twist.twist.linear.{c}" for c in _V},
           **{f"g{c}": f"twist.twist.angular.{c}" for c in _V}},
    TWIST: {**{f"v{c}": f"twist.linear.{c}" for c in _V}, **{f"g{c}": f"twist.angular.{c}" for c in _V}},
    TWIST_COV: {**{f"v{c}": f"twist.twist.linear.{c}" for c in _V},
                **{f"g{c}": f"twist.twist.angular.{c}" for c in _V}},
    VEC3: {f"v{c}": f"vector.{c}" for c in _V},
    FIX: {"lat": "latitude", "lon": "longitude", "alt": "altitude", "status": "status.status"},
    QUAT_STAMPED: {f"q{c}": f"quaternion.{c}" for c in _Q},
    POSE: {**{f"q{c}": f"pose.orientation.{c}" for c in _Q}, **{f"p{c}": f"pose.position.{c}" for c in _V}},
    POSE_COV: {**{f"q{c}": f"pose.pose.orientation.{c}" for c in _Q},
               **{f"p{c}": f"pose.pose.position.{c}" for c in _V}},
}
STAMP_FIELDS = {"sec": "header.stamp.sec", "nsec": "header.stamp.nanosec"}

#: stamps above this many seconds are UNIX epoch, below it sim/boot time
EPOCH_THRESHOLD_S = 1e9
SELECTOR_KEYS = ("imu", "odom", "att", "vel", "pos", "nav", "time", "vel_frame")


def normalize_msgtype(name: str) -> str:
    """``sensor_msgs/Imu`` (ROS 1 / schema names) -> ``sensor_msgs/msg/Imu``."""
    parts = name.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name.strip()


# ---- raw messages, as the readers deliver them ----------------------------------------------
@dataclass
class RawTopic:
    """One topic's raw messages. ``data`` is empty for topics whose content was not kept."""

    name: str
    msgtype: str  # normalised, e.g. sensor_msgs/msg/Imu
    encoding: str  # "cdr", "ros1" or "json" (MCAP's JSON-encoded ROS-shaped messages)
    log_ns: list[int] = field(default_factory=list)
    data: list[bytes] = field(default_factory=list)
    #: the topic decoded while it was read (:class:`StreamDecoder`): then ``log_ns`` is an int64 array and
    #: ``data`` holds only the first HEAD_MESSAGES messages (what the unit selection looks at)
    decoded: "Predecoded | None" = None

    @property
    def count(self) -> int:
        return len(self.log_ns)


@dataclass
class RawLog:
    """A whole ROS log as raw messages; ``typestore`` knows every kept message type."""

    path: str
    fmt: str
    topics: dict[str, RawTopic]
    typestore: object
    warnings: list[str] = field(default_factory=list)


def keep_supported(topic: str, msgtype: str) -> bool:
    """Default predicate for readers: keep the content of the types this module decodes."""
    return normalize_msgtype(msgtype) in SUPPORTED


def default_typestore(encoding: str):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if encoding == "ros1" else Stores.ROS2_HUMBLE)


def register_msgdef(typestore, msgtype: str, text: str, fmt: str = "msg") -> None:
    """Register a message definition (``msg`` text with ``MSG:`` sections, or ``idl``)."""
    typs = {k: v for k, v in _parsed_msgdef(text, normalize_msgtype(msgtype), fmt) if k not in typestore.fielddefs}
    if typs:
        typestore.register(typs)


@functools.lru_cache(maxsize=64)
def _parsed_msgdef(text: str, msgtype: str, fmt: str) -> tuple:
    """rosbags' parse of a message definition, as (type name, definition) pairs: once per text in a process (a
    log's reader registers each channel's schema in the channel's decoder and in the log's typestore; the
    parse is rosbags' PEG grammar, about 2-5 ms a definition)."""
    from rosbags.typesys import get_types_from_idl, get_types_from_msg

    if fmt == "idl":
        typs: dict = {}
        sep = "=" * 80 + "\n"
        if text.startswith(f"{sep}IDL: "):
            for part in text.split(sep)[1:]:
                _hdr, idl = part.split("\n", 1)
                typs.update(get_types_from_idl(idl))
        else:
            typs.update(get_types_from_idl(text))
    else:
        typs = get_types_from_msg(text, msgtype)
    return tuple(typs.items())


# ---- vectorised decode: numpy structured dtypes from message definitions ---------------------
_BASE_DT = {"bool": "u1", "byte": "u1", "char": "u1", "int8": "i1", "uint8": "u1", "int16": "i2",
            "uint16": "u2", "int32": "i4", "uint32": "u4", "int64": "i8", "uint64": "u8",
            "float32": "f4", "float64": "f8"}


class _NoLayout(Exception):
    """The message cannot be described by one fixed layout (caller falls back to the library)."""


@dataclass(frozen=True)
class Layout:
    """A fixed byte layout of one message length: structured dtype + the length fields to check."""

    dtype: np.dtype
    checks: tuple[tuple[str, int], ...]  # (field name, value every message must hold)


def build_layout(typestore, msgtype: str, sample: bytes, encoding: str) -> Layout | None:
    """Structured dtype describing ``sample`` (and every message of the same shape), or None.

    CDR: 4-byte encapsulation header (``00 01`` little endian, ``00 00`` big endian), primitives
    aligned to their size relative to the payload start; strings ``uint32 n`` (incl. NUL) + bytes.
    ROS 1: packed little endian, strings ``uint32 n`` + bytes. Fixed arrays inline; sequences
    ``uint32 count`` + elements. String and sequence lengths come from ``sample`` and become checks.
    """
    names: list[str] = []
    formats: list = []
    offsets: list[int] = []
    checks: list[tuple[str, int]] = []
    if encoding == "cdr":
        if len(sample) < 4 or sample[0] != 0 or sample[1] not in (0, 1):
            return None
        endian, base, pos = ("<" if sample[1] == 1 else ">"), 4, 4
        names.append("__encap")
        formats.append(">u2")
        offsets.append(0)
        checks.append(("__encap", int.from_bytes(sample[:2], "big")))
    elif encoding == "ros1":
        endian, base, pos = "<", 0, 0
    else:
        return None
    cdr = encoding == "cdr"
    # rosbags Nodetype values: BASE=1, NAME=2, ARRAY=3, SEQUENCE=4

    def align(p: int, a: int) -> int:
        return p if not cdr or a <= 1 else base + -(-(p - base) // a) * a

    def u32(p: int) -> int:
        if p + 4 > len(sample):
            raise _NoLayout
        return int.from_bytes(sample[p:p + 4], "little" if endian == "<" else "big")

    def add(name: str, fmt, p: int) -> None:
        names.append(name)
        formats.append(fmt)
        offsets.append(p)

    def walk(typename: str, p: int, prefix: str) -> int:
        try:
            fields = typestore.fielddefs[typename][1]
        except KeyError:
            raise _NoLayout from None
        for fname, desc in fields:
            p = one(desc, p, prefix + fname)
        return p

    def one(desc, p: int, name: str) -> int:
        nt, detail = desc
        nt = int(nt)
        if nt == 2:  # NAME
            return walk(detail, p, name + ".")
        if nt == 1:  # BASE
            tname = detail[0]
            if tname == "string":
                p = align(p, 4)
                n = u32(p)
                add(name + ".len", endian + "u4", p)
                checks.append((name + ".len", n))
                p += 4
                if n:
                    add(name, f"V{n}", p)
                    if cdr:  # CDR strings end with NUL (the library insists too)
                        add(name + ".nul", "u1", p + n - 1)
                        checks.append((name + ".nul", 0))
                return p + n
            dt = _BASE_DT.get(tname)
            if dt is None:
                raise _NoLayout
            size = int(dt[1])
            p = align(p, size)
            add(name, endian + dt, p)
            return p + size
        if nt in (3, 4):  # ARRAY, SEQUENCE
            sub, count = detail
            if nt == 4:
                p = align(p, 4)
                count = u32(p)
                add(name + ".count", endian + "u4", p)
                checks.append((name + ".count", count))
                p += 4
            if int(sub[0]) == 1 and sub[1][0] in _BASE_DT:
                dt = _BASE_DT[sub[1][0]]
                size = int(dt[1])
                if count:
                    p = align(p, size)
                    add(name, (endian + dt, (count,)), p)
                return p + size * count
            for i in range(count):
                p = one(sub, p, f"{name}.{i}")
            return p
        raise _NoLayout

    try:
        end = walk(msgtype, pos, "")
    except (_NoLayout, KeyError, ValueError, TypeError):
        return None
    if end > len(sample) or (not cdr and end != len(sample)) or (cdr and len(sample) - end > 8):
        return None
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": len(sample)})
    return Layout(dtype, tuple(checks))


def _take(arr: np.ndarray, path: str) -> np.ndarray:
    head, _, last = path.rpartition(".")
    if last.isdigit() and head in arr.dtype.names:
        return arr[head][:, int(last)]
    return arr[path]


def _getpath(msg, path: str):
    for part in path.split("."):
        msg = msg[int(part)] if part.isdigit() else getattr(msg, part)
    return msg


@dataclass(frozen=True)
class Decoded:
    """Decoded columns of one topic (message order), and how many took the fast path."""

    columns: dict[str, np.ndarray]
    n_fast: int
    n_slow: int


#: ROS time's field names as JSON encoders of ROS messages write them: ROS 2 (sec, nanosec), Foxglove's
#: (sec, nsec), ROS 1's rosbridge (secs, nsecs)
JSON_ALIASES = {"sec": ("sec", "secs"), "nanosec": ("nanosec", "nsec", "nsecs")}


def json_getpath(msg, path: str):
    """:func:`_getpath` in a JSON-decoded message (dicts and lists; ROS time under any of JSON_ALIASES);
    KeyError, IndexError or TypeError where the message lacks the field."""
    for part in path.split("."):
        if part.isdigit():
            msg = msg[int(part)]
            continue
        for name in JSON_ALIASES.get(part, (part,)):
            if name in msg:
                msg = msg[name]
                break
        else:
            raise KeyError(part)
    return msg


def json_decode(raw: RawTopic, paths: dict[str, str], index=None) -> dict[str, np.ndarray]:
    """Columns ``paths`` of JSON-encoded messages (MCAP ``message_encoding: json``, ROS-shaped fields),
    message by message; a field a message lacks (or a message that is no JSON: damaged) is NaN."""
    import json

    idx = range(raw.count) if index is None else index
    cols: dict[str, list] = {k: [] for k in paths}
    for i in idx:
        try:
            msg = json.loads(bytes(raw.data[i]))
        except (ValueError, UnicodeDecodeError):
            msg = None
        for k, p in paths.items():
            try:
                v = json_getpath(msg, p)
                cols[k].append(float(v) if v is not None else math.nan)
            except (KeyError, IndexError, TypeError, ValueError):
                cols[k].append(math.nan)
    return {k: np.asarray(v, dtype=float) for k, v in cols.items()}


def library_decode(typestore, raw: RawTopic, paths: dict[str, str], index=None) -> dict[str, np.ndarray]:
    """Reference decode with the rosbags deserialiser, message by message. A message the library
    cannot decode (damaged) gives NaN in every column. JSON-encoded messages: :func:`json_decode`."""
    if raw.encoding == "json":
        return json_decode(raw, paths, index)
    idx = range(raw.count) if index is None else index
    deser = typestore.deserialize_cdr if raw.encoding == "cdr" else typestore.deserialize_ros1
    cols: dict[str, list] = {k: [] for k in paths}
    for i in idx:
        try:
            msg = deser(raw.data[i], raw.msgtype)
            vals = [float(_getpath(msg, p)) for p in paths.values()]
        except Exception:  # damaged message: the library's own error is not ours to raise
            vals = [math.nan] * len(paths)
        for k, v in zip(cols, vals):
            cols[k].append(v)
    return {k: np.asarray(v, dtype=float) for k, v in cols.items()}


#: layouts tried per message length before the rest goes to the library
LAYOUT_TRIES = 6
#: more message lengths than this in one topic: not a fixed-layout stream (all to the library)
MAX_LENGTH_GROUPS = 64


def _layout_tries(typestore, msgtype: str, encoding: str, paths: dict[str, str], idx: np.ndarray, blob: bytes,
                  message, left: np.ndarray, out: dict, n: int, slow_idx: list, first_try: int = 0) -> int:
    """The fixed-layout tries of one length group (:func:`decode_topic`): ``idx`` the group's message
    indices, ``blob`` their bytes end to end, ``message(j)`` the bytes of ``idx[j]``, ``left`` (updated)
    those not decoded yet; decoded values go to ``out[k][idx]``, messages without a layout to ``slow_idx``.
    Tries ``first_try`` .. LAYOUT_TRIES - 1 (a reader that made the first try itself goes on from 1).
    Returns how many were decoded."""
    n_fast = 0
    for _attempt in range(first_try, LAYOUT_TRIES):
        first = int(np.argmax(left))
        layout = build_layout(typestore, msgtype, message(first), encoding)
        if layout is None:  # this message is odd: the library's turn; try the next one
            slow_idx.append(idx[first:first + 1])
            left[first] = False
            if not left.any():
                break
            continue
        arr = np.frombuffer(blob, dtype=layout.dtype)
        ok = left.copy()
        for name, value in layout.checks:
            ok &= arr[name] == value
        if not ok.any():
            break
        try:
            if len(idx) == n and ok.all():  # the common case: one layout for the whole topic
                for k, p in paths.items():
                    out[k] = _take(arr, p).astype(float)
            else:
                sel = idx[ok]
                for k, p in paths.items():
                    out[k][sel] = _take(arr, p)[ok]
        except (KeyError, ValueError, IndexError):
            break
        n_fast += int(ok.sum())
        left &= ~ok
        if not left.any():
            break
    return n_fast


def decode_topic(typestore, raw: RawTopic, paths: dict[str, str], *, fast: bool = True,
                 path: str | None = None) -> Decoded:
    """Columns ``paths`` of every message of ``raw`` (float64), vectorised where possible (``path``: the log's
    file, named by the InputError of a topic whose message content was not read).

    Messages are grouped by length; each group is decoded with the layout of its first message, the
    messages that fail the layout's checks get another try with the layout of the first of them (a
    few times); a message without a layout, and whatever is left, go to the library."""
    n = raw.count
    out = {k: np.full(n, np.nan) for k in paths}
    if n == 0:
        return Decoded(out, 0, 0)
    if len(raw.data) != n:
        raise InputError(f"topic {raw.name}: message content was not read ({len(raw.data)} of {n} messages)", path)
    if raw.encoding == "json":  # (text: no fixed layout; every message through the JSON decoder)
        return Decoded(json_decode(raw, paths), n, 0)
    lens = np.fromiter(map(len, raw.data), dtype=np.int64, count=n)
    slow_idx: list[np.ndarray] = []
    n_fast = 0
    groups = np.unique(lens) if fast else []
    if fast and len(groups) > MAX_LENGTH_GROUPS:  # a zoo of lengths: not a fixed-layout stream
        groups, slow_idx = [], [np.arange(n)]
    elif not fast:
        slow_idx = [np.arange(n)]
    for length in groups:
        idx = np.flatnonzero(lens == length) if len(groups) > 1 else np.arange(n)
        blob = b"".join(raw.data) if len(idx) == n else b"".join([raw.data[i] for i in idx.tolist()])
        left = np.ones(len(idx), bool)
        n_fast += _layout_tries(typestore, raw.msgtype, raw.encoding, paths, idx, blob,
                                lambda j: raw.data[idx[j]], left, out, n, slow_idx)
        if left.any():
            slow_idx.append(idx[left])
    n_slow = 0
    if slow_idx:
        idx = np.sort(np.concatenate(slow_idx))
        vals = library_decode(typestore, raw, paths, idx.tolist())
        for k in paths:
            out[k][idx] = vals[k]
        n_slow = len(idx)
    return Decoded(out, n_fast, n_slow)


# ---- decoding while reading: one topic's messages batch by batch ------------------------------------
#: the columns ``to_inslog`` reads of each type (the others of FIELDS are decoded only by decode_topic)
USED_FIELDS: dict[str, tuple[str, ...]] = {
    IMU: tuple(FIELDS[IMU]),
    ODOM: ("qx", "qy", "qz", "qw", "vx", "vy", "vz", "gx", "gy", "gz"),
    TWIST: ("vx", "vy", "vz"), TWIST_COV: ("vx", "vy", "vz"), VEC3: ("vx", "vy", "vz"),
    FIX: ("lat", "lon", "alt", "status"),
    QUAT_STAMPED: ("qx", "qy", "qz", "qw"), POSE: ("qx", "qy", "qz", "qw"), POSE_COV: ("qx", "qy", "qz", "qw"),
}
#: messages whose bytes a streamed topic keeps (the unit selection decodes the first 20 / 200 itself)
HEAD_MESSAGES = 200


class NotStreamable(Exception):
    """A topic the streaming decode cannot give exactly what :func:`decode_topic` gives (a zoo of message
    lengths, a layout the final message definitions change): the reader reads the file the classic way."""


@dataclass
class Predecoded:
    """A topic decoded as it was read (:class:`StreamDecoder`): float64 columns of USED_FIELDS and the
    header stamps (int64 ns), NaN / 0 at ``slow_idx``, the messages the library decodes (their bytes in
    ``slow_data``), as ``decode_topic`` would split them."""

    columns: dict[str, np.ndarray]
    stamp_ns: np.ndarray
    slow_idx: np.ndarray
    slow_data: list[bytes]
    n_fast: int


class _Discard:
    """A column nobody reads: what is written to it goes nowhere."""

    def __setitem__(self, key, value) -> None:
        pass


class _Column:
    """A float64 or int64 column filled batch by batch, its capacity grown ahead from an estimate (pages
    never written are never touched, so a generous estimate costs no memory)."""

    def __init__(self, dtype):
        self.arr = np.empty(0, dtype=dtype)

    def reserve(self, n: int, estimate: int) -> np.ndarray:
        if n > len(self.arr):
            grown = np.empty(max(n, int(estimate), 2 * len(self.arr)), dtype=self.arr.dtype)
            grown[:len(self.arr)] = self.arr
            self.arr = grown
        return self.arr


@dataclass
class _Group:
    """One message length of a streamed topic: its first message and the layout made from it."""

    sample: bytes
    layout: Layout | None  # made from ``sample`` while reading (checked against the final definitions)
    tries: int  # tries made while reading: 0 the whole group is left to the end, 1 the first one applied,
    #             LAYOUT_TRIES: decode_topic would give the group up (every message to the library)


class StreamDecoder:
    """Decodes one topic batch by batch as a reader meets its messages (each batch: the messages' start and
    end offsets in a byte buffer, in order), into growing columns, keeping only the bytes of the messages
    the fixed-layout fast path does not take and of the first HEAD_MESSAGES. The same split and the same
    numbers as :func:`decode_topic` over the whole topic: each message length's first layout (made from its
    first message) is applied as the messages come; the messages it does not fit get the remaining tries at
    :meth:`finish`, with the final message definitions, which must give the layouts used (else
    NotStreamable, as for more than MAX_LENGTH_GROUPS lengths).

    ``typestore``: message definitions to make the layouts while reading (the channel's own schema);
    ``expect``: a guess of the topic's message count (the columns' first capacity)."""

    def __init__(self, name: str, msgtype: str, encoding: str, typestore):
        self.name, self.msgtype, self.encoding = name, msgtype, encoding
        self.typestore = typestore
        self.all_paths = {**FIELDS[msgtype], **STAMP_FIELDS}
        self.used = {k: FIELDS[msgtype][k] for k in USED_FIELDS[msgtype]}
        self.cols = {k: _Column(np.float64) for k in self.used}
        self.stamp = _Column(np.int64)
        self.n = 0
        self.groups: dict[int, _Group] = {}
        self.residue: dict[int, tuple[list[int], list[bytes]]] = {}  # length -> (indices, bytes)
        self.head: list[bytes] = []
        self.n_fast = 0

    def _rest(self, length: int, base: int, buf, s: np.ndarray, e: np.ndarray, sel: np.ndarray) -> None:
        idx, data = self.residue.setdefault(length, ([], []))
        for j in sel.tolist():
            idx.append(base + j)
            data.append(bytes(buf[int(s[j]):int(e[j])]))

    def add(self, buf: np.ndarray, s: np.ndarray, e: np.ndarray, expect: int = 0) -> None:
        """The next messages: ``buf[s[i]:e[i]]`` (``buf`` uint8)."""
        m = len(s)
        if m == 0:
            return
        base = self.n
        self.n += m
        if len(self.head) < HEAD_MESSAGES:
            self.head += [bytes(buf[a:b]) for a, b in zip(s[:HEAD_MESSAGES - len(self.head)].tolist(),
                                                          e[:HEAD_MESSAGES - len(self.head)].tolist())]
        est = max(expect, self.n + 1024)
        out = {k: c.reserve(self.n, est) for k, c in self.cols.items()}
        stamp = self.stamp.reserve(self.n, est)
        lens = e - s
        lo, hi = int(lens.min()), int(lens.max())
        for length in ([lo] if lo == hi else np.unique(lens).tolist()):
            sel = np.arange(m) if lo == hi else np.flatnonzero(lens == length)
            g = self.groups.get(length)
            if g is None:
                if len(self.groups) >= MAX_LENGTH_GROUPS:
                    raise NotStreamable(f"{self.name}: more than {MAX_LENGTH_GROUPS} message lengths")
                sample = bytes(buf[int(s[sel[0]]):int(s[sel[0]]) + length])
                layout = build_layout(self.typestore, self.msgtype, sample, self.encoding)
                tries = 0
                if layout is not None:
                    tries = 1
                    try:  # what decode_topic's first try would raise on (the dtype decides, not the data)
                        empty = np.zeros(0, dtype=layout.dtype)
                        for p in self.all_paths.values():
                            _take(empty, p).astype(float)
                    except (KeyError, ValueError, IndexError):
                        tries = LAYOUT_TRIES  # decode_topic gives the whole group up
                g = self.groups[length] = _Group(sample, layout, tries)
            if g.tries != 1:
                self._rest(length, base, buf, s, e, sel)
                continue
            rows = np.lib.stride_tricks.sliding_window_view(buf, length)[s[sel]]
            arr = rows.view(g.layout.dtype).reshape(-1)
            ok = np.ones(len(sel), bool)
            for name, value in g.layout.checks:
                ok &= arr[name] == value
            if not ok.all():
                self._rest(length, base, buf, s, e, sel[~ok])
            at = base + (sel if ok.all() else sel[ok])
            if lo == hi and ok.all():
                at = slice(base, base + m)
            for k, p in self.used.items():
                out[k][at] = _take(arr, p)[ok] if not ok.all() else _take(arr, p)
            sec = _take(arr, STAMP_FIELDS["sec"])
            nsec = _take(arr, STAMP_FIELDS["nsec"])
            if not ok.all():
                sec, nsec = sec[ok], nsec[ok]
            # decode_topic's float64 sec / nanosec as int64 ns (the same: both are 32-bit integers)
            stamp[at] = sec.astype(np.int64) * 1_000_000_000 + nsec.astype(np.int64)
            self.n_fast += int(ok.sum())
            del rows, arr

    def finish(self, typestore) -> tuple[Predecoded, list[bytes]]:
        """The topic with the final message definitions ``typestore``: the remaining layout tries of the
        messages left, then (Predecoded, the first messages' bytes). NotStreamable when the layouts used
        while reading are not the ones these definitions give."""
        for length, g in self.groups.items():
            if g.tries and build_layout(typestore, self.msgtype, g.sample, self.encoding) != g.layout:
                raise NotStreamable(f"{self.name}: the message definitions changed after its first messages")
        n = self.n
        cols = {k: c.arr[:n] for k, c in self.cols.items()}
        stamp = self.stamp.arr[:n]
        self.cols = self.stamp = None
        slow: list[np.ndarray] = []
        slow_data: dict[int, bytes] = {}
        n_fast = self.n_fast
        for length in sorted(self.residue):
            idx_l, data_l = self.residue.pop(length)
            idx = np.asarray(idx_l, dtype=np.int64)
            g = self.groups[length]
            for i, d in zip(idx_l, data_l):
                slow_data[i] = d
            if g.tries >= LAYOUT_TRIES:
                slow.append(idx)
                continue
            left = np.ones(len(idx), bool)
            out = {k: (cols[k] if k in cols else _Discard()) for k in self.all_paths}
            sec = np.full(n, np.nan) if len(idx) == n else _Stamps(stamp)
            nsec = np.full(n, np.nan) if len(idx) == n else _Stamps(stamp, nano=True)
            out["sec"], out["nsec"] = sec, nsec
            n_fast += _layout_tries(typestore, self.msgtype, self.encoding, self.all_paths, idx, b"".join(data_l),
                                    lambda j: data_l[j], left, out, n, slow, first_try=g.tries)
            for k in cols:
                cols[k] = out[k] if isinstance(out[k], np.ndarray) else cols[k]
            if isinstance(out["sec"], np.ndarray) and isinstance(out["nsec"], np.ndarray):  # the whole topic
                ok = ~(np.isnan(out["sec"]) | np.isnan(out["nsec"]))
                stamp[ok] = out["sec"][ok].astype(np.int64) * 1_000_000_000 + out["nsec"][ok].astype(np.int64)
            if left.any():
                slow.append(idx[left])
        slow_idx = np.sort(np.concatenate(slow)) if slow else np.zeros(0, np.int64)
        for k in cols:
            cols[k][slow_idx] = np.nan
        stamp[slow_idx] = 0
        head = self.head
        self.head, self.residue = [], {}
        return Predecoded(cols, stamp, slow_idx, [slow_data[i] for i in slow_idx.tolist()], n_fast), head


class _Stamps:
    """The header stamp's sec or nanosec column of a later layout try, written into the int64 stamps (a try
    writes sec before nanosec, so nanosec adds to the seconds already there)."""

    def __init__(self, stamp: np.ndarray, nano: bool = False):
        self.stamp, self.nano = stamp, nano

    def __setitem__(self, sel, vals) -> None:
        v = np.asarray(vals).astype(np.int64)
        if self.nano:
            self.stamp[sel] += v
        else:
            self.stamp[sel] = v * 1_000_000_000


def encode_messages(typestore, msgtype: str, template, encoding: str, columns: dict[str, np.ndarray]) -> list[bytes]:
    """Serialise many messages at once: ``template`` (a message object) fixes strings and constant
    fields; ``columns`` (field path -> array, one value per message) fill the rest."""
    ser = typestore.serialize_cdr if encoding == "cdr" else typestore.serialize_ros1
    sample = bytes(ser(template, msgtype))
    layout = build_layout(typestore, msgtype, sample, encoding)
    if layout is None:
        raise ValueError(f"cannot build a layout for {msgtype}")
    n = len(next(iter(columns.values())))
    arr = np.empty(n, dtype=layout.dtype)
    raw = arr.view(np.uint8).reshape(n, len(sample))
    raw[:] = np.frombuffer(sample, np.uint8)
    for path, vals in columns.items():
        head, _, last = path.rpartition(".")
        if last.isdigit() and head in layout.dtype.names:
            arr[head][:, int(last)] = vals
        else:
            arr[path] = vals
    blob = arr.tobytes()
    size = len(sample)
    return [blob[i:i + size] for i in range(0, n * size, size)]


# ---- stamps and clocks ----------------------------------------------------------------------
def clock_of(t_ns: np.ndarray, *, scratch: bool = False) -> str:
    """"epoch" or "boot" by the stamps' median; ``scratch``: ``t_ns`` is the caller's to reorder."""
    if len(t_ns) == 0:
        return "unknown"
    return "epoch" if float(np.median(t_ns, overwrite_input=scratch)) * 1e-9 > EPOCH_THRESHOLD_S else "boot"


@dataclass(frozen=True)
class TopicData:
    """One decoded topic: stamps (int64 ns) on the chosen clock, and its columns."""

    name: str
    msgtype: str
    t_ns: np.ndarray
    cols: dict[str, np.ndarray]
    stamp_source: str
    frame_id: str = ""


#: the fields of std_msgs/Header by encoding (ROS 1's has a sequence number first)
_HEADER_FIELDS = {"cdr": ["stamp", "frame_id"], "ros1": ["seq", "stamp", "frame_id"]}


def header_frame_id(typestore, msgtype: str, data, encoding: str) -> str | None:
    """``header.frame_id`` of one serialised message, read where the encoding puts it, for a message whose first
    field is a std_msgs Header of the standard definition: CDR, after the 4-byte encapsulation header and the
    stamp (int32 sec, uint32 nanosec), a uint32 length (with its NUL) then the bytes; ROS 1, after seq and the
    stamp, a uint32 length then the bytes. None where the type or the bytes are not that (the library's
    deserialiser then: it builds a message class per type, about 3 ms each, for one string)."""
    try:
        name, (kind, htype) = typestore.fielddefs[msgtype][1][0]
        hfields = typestore.fielddefs[htype][1]
        stamp = [d for f, d in hfields if f == "stamp"][0]
        tfields = typestore.fielddefs[stamp[1]][1]
    except (KeyError, IndexError, TypeError, ValueError):
        return None
    if (name != "header" or int(kind) != 2 or [f for f, _ in hfields] != _HEADER_FIELDS.get(encoding)
            or int(stamp[0]) != 2 or [(int(d[0]), d[1][0]) for _f, d in tfields] != [(1, "int32"), (1, "uint32")]):
        return None
    b = bytes(data[:4096])
    if encoding == "cdr":
        if len(b) < 16 or b[0] != 0 or b[1] not in (0, 1):
            return None
        order, at, nul = ("little" if b[1] == 1 else "big"), 12, 1
    else:
        order, at, nul = "little", 12, 0
    n = int.from_bytes(b[at:at + 4], order)
    text = b[at + 4:at + 4 + n]
    if len(text) != n or n < nul or (nul and text[-1:] != b"\0"):
        return None
    try:
        return text[:n - nul].decode()
    except UnicodeDecodeError:
        return None


def _frame_id(typestore, raw: RawTopic) -> str:
    try:
        if raw.encoding in ("cdr", "ros1"):
            fast = header_frame_id(typestore, raw.msgtype, raw.data[0], raw.encoding)
            if fast is not None:
                return fast
        if raw.encoding == "json":
            import json

            return str(json_getpath(json.loads(bytes(raw.data[0])), "header.frame_id"))
        deser = typestore.deserialize_cdr if raw.encoding == "cdr" else typestore.deserialize_ros1
        return str(deser(raw.data[0], raw.msgtype).header.frame_id)
    except Exception:
        return ""


def topic_data(rawlog: RawLog, name: str, time_mode: str, warnings: list[str],
               keys: tuple[str, ...] | None = None) -> TopicData:
    raw = rawlog.topics[name]
    paths = dict(FIELDS[raw.msgtype])
    if keys is not None:
        paths = {k: v for k, v in paths.items() if k in keys}
    if raw.decoded is not None:
        return _streamed_topic_data(rawlog, raw, paths, time_mode, warnings)
    dec = decode_topic(rawlog.typestore, raw, {**paths, **STAMP_FIELDS}, path=rawlog.path)
    if dec.n_slow:
        warnings.append(f"{name}: {dec.n_slow} of {raw.count} messages decoded by the library "
                        "(not the fixed-layout fast path)")
    cols = dec.columns
    log_ns = np.asarray(raw.log_ns, dtype=np.int64)
    bad = np.isnan(cols["sec"]) | np.isnan(cols["nsec"])
    headless = raw.encoding == "json" and raw.count and bad.all()  # (JSON objects without a header)
    if headless:
        cols["sec"], cols["nsec"] = np.zeros(raw.count), np.zeros(raw.count)
        bad = np.zeros(raw.count, bool)
    if bad.any():
        warnings.append(f"{name}: {int(bad.sum())} of {raw.count} messages undecodable (damaged); dropped")
        cols = {k: v[~bad] for k, v in cols.items()}
        log_ns = log_ns[~bad]
    stamp_ns = cols.pop("sec").astype(np.int64) * 1_000_000_000 + cols.pop("nsec").astype(np.int64)
    if time_mode == "log":
        t_ns, src = log_ns, "log time"
    elif raw.count and not np.any(stamp_ns):
        warnings.append(f"{name}: " + ("its JSON messages have no header stamp" if headless else
                                       "header stamps are all zero") + "; log time used instead")
        t_ns, src = log_ns, "log time"
    else:
        t_ns, src = stamp_ns, "header.stamp"
    return TopicData(name, raw.msgtype, t_ns, cols, src, _frame_id(rawlog.typestore, raw) if raw.count else "")


def _streamed_topic_data(rawlog: RawLog, raw: RawTopic, paths: dict[str, str], time_mode: str,
                         warnings: list[str]) -> TopicData:
    """:func:`topic_data` of a topic decoded while it was read (``raw.decoded``): its columns of ``paths``
    (those of USED_FIELDS), the messages left to the library decoded now, with ``paths`` as decode_topic
    would (a message the library cannot read is NaN in every column: dropped as damaged)."""
    pre, name, n = raw.decoded, raw.name, raw.count
    cols = {k: pre.columns[k] for k in paths if k in pre.columns}
    stamp_ns = pre.stamp_ns
    log_ns = np.asarray(raw.log_ns, dtype=np.int64)
    bad = None
    slow = pre.slow_idx
    if len(slow):
        warnings.append(f"{name}: {len(slow)} of {n} messages decoded by the library "
                        "(not the fixed-layout fast path)")
        sub = RawTopic(raw.name, raw.msgtype, raw.encoding, list(range(len(slow))), pre.slow_data)
        vals = library_decode(rawlog.typestore, sub, {**paths, **STAMP_FIELDS})
        cols = {k: v.copy() for k, v in cols.items()}
        for k in cols:
            cols[k][slow] = vals[k]
        lost = np.isnan(vals["sec"]) | np.isnan(vals["nsec"])
        stamp_ns = stamp_ns.copy()
        stamp_ns[slow[~lost]] = (vals["sec"][~lost].astype(np.int64) * 1_000_000_000
                                 + vals["nsec"][~lost].astype(np.int64))
        if lost.any():
            bad = np.zeros(n, dtype=bool)
            bad[slow[lost]] = True
    if bad is not None:
        warnings.append(f"{name}: {int(bad.sum())} of {n} messages undecodable (damaged); dropped")
        cols = {k: v[~bad] for k, v in cols.items()}
        log_ns, stamp_ns = log_ns[~bad], stamp_ns[~bad]
    if time_mode == "log":
        t_ns, src = log_ns, "log time"
    elif n and not np.any(stamp_ns):
        warnings.append(f"{name}: header stamps are all zero; log time used instead")
        t_ns, src = log_ns, "log time"
    else:
        t_ns, src = stamp_ns, "header.stamp"
    return TopicData(name, raw.msgtype, t_ns, cols, src, _frame_id(rawlog.typestore, raw) if n else "")


# ---- ROS (ENU/FLU) -> tapost (NED/FRD) --------------------------------------------------------
#: the axis swaps as rotation quaternions (both 180 deg rotations, each its own inverse):
#: NED <- ENU about (1, 1, 0)/sqrt(2), FLU <- FRD about x. ``a * q * b`` is the same similarity
#: transform as ``conventions.quat_enu_flu_to_ned_frd`` (tested) at a sixth of the cost.
_Q_NED_ENU = np.array([0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0])
_Q_FLU_FRD = np.array([0.0, 1.0, 0.0, 0.0])


def quat_enu_flu_to_ned_frd_fast(q_wxyz: np.ndarray) -> np.ndarray:
    """FLU->ENU attitude quaternions -> FRD->NED (and back: the transform is an involution)."""
    return quat_mul(quat_mul(_Q_NED_ENU, q_wxyz), _Q_FLU_FRD)


#: quaternions converted at a time (row by row arithmetic: the chunks only bound the temporaries)
QUAT_ROWS = 1 << 19
#: an Imu orientation bit-identical in at least this many messages is a driver's placeholder (drivers without an
#: AHRS fill identity with covariance 0 instead of REP-145's -1): a real attitude's last bits move even at rest
PLACEHOLDER_MIN_SAMPLES = 50


def _placeholder(q: np.ndarray, ok: np.ndarray) -> bool:
    """The valid rows of ``q`` (n, 4) are all one and the same quaternion, over PLACEHOLDER_MIN_SAMPLES or more."""
    if int(ok.sum()) < PLACEHOLDER_MIN_SAMPLES:
        return False
    v = q[ok] if not ok.all() else q
    return bool(np.all(v == v[0]))


def quat_ros_to_ned_frd(cols: dict[str, np.ndarray], ned: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """ROS (x, y, z, w) FLU->ENU columns -> (quat_wxyz FRD->NED, valid mask). ``ned``: the columns are already
    FRD->NED (a frame_id with a NED/FRD suffix, :func:`is_ned_frame`): normalised and reordered only."""
    n = len(cols["qw"])
    out = np.empty((n, 4))
    ok = np.empty(n, dtype=bool)
    conv = (lambda x: x) if ned else quat_enu_flu_to_ned_frd_fast  # noqa: E731
    for i in range(0, n, QUAT_ROWS):
        j = min(n, i + QUAT_ROWS)
        q = np.stack([cols["qw"][i:j], cols["qx"][i:j], cols["qy"][i:j], cols["qz"][i:j]], axis=-1)
        with np.errstate(over="ignore", invalid="ignore"):  # (a damaged component: the norm inf, not valid)
            norm = np.linalg.norm(q, axis=-1)
        good = np.isfinite(norm) & (np.abs(norm - 1.0) < 0.1)
        ok[i:j] = good
        part = out[i:j]
        if good.all():
            part[:] = conv(q / norm[:, None])
        else:
            part[:] = np.nan
            if good.any():
                part[good] = conv(q[good] / norm[good, None])
        del q, norm, good, part
    return out, ok


def _vec(cols: dict[str, np.ndarray], prefix: str) -> np.ndarray:
    return np.stack([cols[prefix + c] for c in _V], axis=-1)


def _quat_at(t_ns: np.ndarray, q_t_ns: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Attitude interpolated (slerp) at ``t_ns``; NaN outside the attitude's span."""
    out = np.full((len(t_ns), 4), np.nan)
    if len(q_t_ns) < 2:
        return out
    order = np.argsort(q_t_ns, kind="stable")
    qt, qq = q_t_ns[order], quat_make_continuous(q[order])
    i = np.searchsorted(qt, t_ns, side="right") - 1
    ok = (i >= 0) & (t_ns <= qt[-1])
    i = np.clip(i, 0, len(qt) - 2)
    frac = (t_ns - qt[i]) / np.maximum(qt[i + 1] - qt[i], 1)
    res = quat_slerp(qq[i], qq[i + 1], np.clip(frac, 0.0, 1.0))
    out[ok] = res[ok]
    return out


def body_to_ned(v_frd: np.ndarray, q_ned_frd: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj->ni", dcm_from_quat(q_ned_frd), v_frd)


# ---- unit selection ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Plan:
    imu: str | None = None  # Imu topic (gyro + accel)
    gyro_odom: str | None = None  # Odometry topic used as gyro (twist.angular)
    att: str | None = None
    vel: str | None = None
    pos: str | None = None
    time_mode: str = "header"
    vel_frame: str | None = None  # None = by type (Odometry body, others enu)


def _topics_of(rawlog: RawLog, *types: str) -> list[str]:
    """Topics of these types holding messages, in the order the log declares them."""
    return [n for n, t in rawlog.topics.items() if t.msgtype in types and t.count]


def _need(rawlog: RawLog, key: str, topic: str, types: tuple[str, ...]) -> str:
    t = rawlog.topics.get(topic)
    if t is None:
        have = ", ".join(sorted(rawlog.topics)) or "none"
        raise InputError(f"selector {key}={topic}: no such topic (topics: {have})", rawlog.path)
    if t.msgtype not in types:
        raise InputError(f"selector {key}={topic}: topic is {t.msgtype}, expected "
                         f"{' or '.join(types)}", rawlog.path)
    if t.count == 0:
        damage = [w for w in rawlog.warnings if not w.startswith("note")]
        raise InputError(f"selector {key}={topic}: topic holds no messages"
                         + (f" ({damage[0]})" if damage else ""), rawlog.path)
    return topic


def _imu_has_orientation(rawlog: RawLog, topic: str) -> bool:
    raw = rawlog.topics[topic]
    n = min(20, len(raw.data))
    if n == 0:
        return False
    sub = RawTopic(raw.name, raw.msgtype, raw.encoding, raw.log_ns[:n], raw.data[:n])
    c = decode_topic(rawlog.typestore, sub, {k: FIELDS[IMU][k] for k in ("qx", "qy", "qz", "qw", "q_cov0")},
                     path=rawlog.path).columns
    _q, ok = quat_ros_to_ned_frd(c)
    return bool(np.any(ok & (c["q_cov0"] != -1)))


def _imu_all_zero(rawlog: RawLog, topic: str, n: int = 200) -> bool:
    """True when the first ``n`` messages of an Imu topic hold only zero rates and specific forces (a
    placeholder topic: nothing to estimate from, so not offered as a unit)."""
    raw = rawlog.topics[topic]
    n = min(n, len(raw.data))  # (a reader that reads the times only, the restamp's, holds a few contents)
    if n == 0:
        return False
    sub = RawTopic(raw.name, raw.msgtype, raw.encoding, raw.log_ns[:n], raw.data[:n])
    keys = [f"g{c}" for c in "xyz"] + [f"a{c}" for c in "xyz"]
    c = decode_topic(rawlog.typestore, sub, {k: FIELDS[IMU][k] for k in keys}, path=rawlog.path).columns
    vals = np.stack([np.asarray(c[k], float) for k in keys])
    return bool(vals.size) and bool(np.all(vals == 0.0))


def _orientation_only_imus(rawlog: RawLog, but: str | None = None) -> list[str]:
    """Imu topics (other than ``but``) whose rates and specific forces are all zero while their orientation is
    given: an attitude published as an Imu (REP-145's -1 covariances on what it does not carry)."""
    return [n for n in _topics_of(rawlog, IMU)
            if n != but and _imu_all_zero(rawlog, n) and _imu_has_orientation(rawlog, n)]


def plan_unit(rawlog: RawLog, selector: Selector) -> tuple[Plan, list[str]]:
    """Decide the topics of the unit (selector, else defaults); notes say what was picked."""
    notes: list[str] = []
    for k, _v in selector.items:
        if k not in SELECTOR_KEYS:
            raise InputError(f"unknown selector key {k!r} for a ROS log (keys: {', '.join(SELECTOR_KEYS)})",
                             rawlog.path)
    time_mode = (selector.get("time") or "header").lower()
    if time_mode not in ("header", "log"):
        raise InputError(f"selector time={time_mode}: expected header or log", rawlog.path)
    vel_frame = selector.get("vel_frame")
    if vel_frame is not None and vel_frame.lower() not in ("enu", "body"):
        raise InputError(f"selector vel_frame={vel_frame}: expected enu or body", rawlog.path)
    vel_frame = vel_frame.lower() if vel_frame else None
    imu = selector.get("imu")
    odom = selector.get("odom")
    att, vel, pos = selector.get("att"), selector.get("vel"), selector.get("pos")
    nav = selector.get("nav")
    if nav:
        t = rawlog.topics.get(nav)
        _need(rawlog, "nav", nav, tuple(SUPPORTED))
        kind = KIND[t.msgtype]
        if kind == "odom":
            odom = odom or nav
        elif kind == "pos":
            pos = pos or nav
        elif kind == "vel":
            vel = vel or nav
        else:
            att = att or nav
    if imu:
        _need(rawlog, "imu", imu, (IMU,))
    if odom:
        _need(rawlog, "odom", odom, (ODOM,))
    if att:
        _need(rawlog, "att", att, (IMU, ODOM, QUAT_STAMPED, POSE, POSE_COV))
    if vel:
        _need(rawlog, "vel", vel, (ODOM, TWIST, TWIST_COV, VEC3))
    if pos:
        _need(rawlog, "pos", pos, (FIX,))
    explicit = bool(selector and any(k in ("imu", "odom", "att", "vel", "pos", "nav") for k, _ in selector.items))
    gyro_odom = None
    if not imu:
        if odom:
            gyro_odom = odom
        elif not explicit:
            imus = _topics_of(rawlog, IMU)
            if len(imus) > 1:  # one with readings first (not an attitude-only Imu topic)
                moving = [n for n in imus if not _imu_all_zero(rawlog, n)]
                imus = moving + [n for n in imus if n not in moving]
            if imus:
                imu = imus[0]
                more = f" (other Imu topics: {', '.join(imus[1:])})" if len(imus) > 1 else ""
                notes.append(f"selected imu={imu}{more}")
            else:
                odoms = _topics_of(rawlog, ODOM)
                if odoms:
                    gyro_odom = odom = odoms[0]
                    notes.append(f"no sensor_msgs/Imu topic: gyro from odom={odom} twist.angular")
    if not att:
        if odom:
            att = odom
        elif imu and _imu_has_orientation(rawlog, imu):
            att = imu
        elif not explicit:
            # an Odometry's pose orientation last (an Imu may say "no orientation": covariance[0] = -1), after
            # an attitude-only Imu topic
            cands = (_topics_of(rawlog, QUAT_STAMPED, POSE, POSE_COV) or _orientation_only_imus(rawlog, imu)
                     or _topics_of(rawlog, ODOM))
            if cands:
                att = cands[0]
        if att and not explicit:
            notes.append(f"selected att={att}")
    if not vel:
        if odom:
            vel = odom
        elif not explicit:
            cands = _topics_of(rawlog, TWIST, TWIST_COV, VEC3) or _topics_of(rawlog, ODOM)
            if cands:
                vel = cands[0]
                notes.append(f"selected vel={vel}" + (" (TwistStamped/Vector3Stamped assumed ENU world frame; "
                                                      "override with vel_frame=body)"
                                                      if rawlog.topics[vel].msgtype != ODOM else
                                                      " (Odometry twist.linear in child frame, rotated "
                                                      "with its pose orientation)"))
    if not pos and not explicit:
        cands = _topics_of(rawlog, FIX)
        if cands:
            pos = cands[0]
            notes.append(f"selected pos={pos}")
    if not (imu or gyro_odom or att or vel or pos):
        damage = [w for w in rawlog.warnings if not w.startswith("note")]
        if damage:
            raise InputError(f"no readable INS messages left; {damage[0]}", rawlog.path)
        have = ", ".join(f"{n} ({t.msgtype}, {t.count} msgs)" for n, t in rawlog.topics.items()) or "no topics"
        raise InputError(f"no INS messages (Imu, Odometry, TwistStamped, NavSatFix...) in topics: {have}",
                         rawlog.path)
    return Plan(imu, gyro_odom, att, vel, pos, time_mode, vel_frame), notes


def unit_selector(plan: Plan) -> str:
    items = []
    if plan.imu:
        items.append(f"imu={plan.imu}")
    if plan.gyro_odom:
        items.append(f"odom={plan.gyro_odom}")
    for k in ("att", "vel", "pos"):
        v = getattr(plan, k)
        if v and v not in (plan.gyro_odom,) and not (k == "att" and v == plan.imu):
            items.append(f"{k}={v}")
    if plan.time_mode != "header":
        items.append(f"time={plan.time_mode}")
    if plan.vel_frame:
        items.append(f"vel_frame={plan.vel_frame}")
    return ",".join(items)


#: frame_id suffixes that mark a NED world / FRD body frame (REP-103's "_ned" suffix; MAVROS and PX4 name their
#: body frame "base_link_frd"): such a message's vectors and orientation are already FRD/NED, not ENU/FLU
NED_FRAME_SUFFIXES = ("_ned", "_frd")


def is_ned_frame(frame_id: str) -> bool:
    """A frame_id that says its frame is NED/FRD (:data:`NED_FRAME_SUFFIXES`)."""
    return frame_id.strip().lower().endswith(NED_FRAME_SUFFIXES)


def _body_vec(d: "TopicData", prefix: str) -> np.ndarray:
    """A body-frame vector of ``d`` in FRD: converted from FLU, or as it is where the frame_id says FRD/NED."""
    return _vec(d.cols, prefix) if is_ned_frame(d.frame_id) else _vec_frd(d.cols, prefix)


def _vec_frd(cols: dict[str, np.ndarray], prefix: str) -> np.ndarray:
    """``flu_to_frd(_vec(cols, prefix))`` without the intermediate array."""
    x = cols[prefix + "x"]
    out = np.empty((len(x), 3))
    out[:, 0] = x
    np.negative(cols[prefix + "y"], out=out[:, 1])
    np.negative(cols[prefix + "z"], out=out[:, 2])
    return out


def _vec_enu_to_ned(cols: dict[str, np.ndarray], prefix: str) -> np.ndarray:
    """``enu_to_ned(_vec(cols, prefix))`` without the intermediate array."""
    x = cols[prefix + "x"]
    out = np.empty((len(x), 3))
    out[:, 0] = cols[prefix + "y"]
    out[:, 1] = x
    np.negative(cols[prefix + "z"], out=out[:, 2])
    return out


def to_inslog(rawlog: RawLog, selector: Selector, *, release: bool = False) -> InsLog:
    """Decode the selected unit of ``rawlog`` into an InsLog (NED/FRD, header stamps by default).
    ``release``: let each topic's decoded columns go once its streams are made (a reader handing over a
    streamed RawLog it has no further use for: the log is then held about once, not twice)."""
    plan, notes = plan_unit(rawlog, selector)
    warnings = list(rawlog.warnings)
    warnings += [f"note: {n}" for n in notes]
    cache: dict[str, TopicData] = {}
    # the columns each role reads, in the order the roles come (with ``release`` a column goes once the
    # last role reading it is done: the decoded topics are let go while the streams are made)
    roles = [(plan.imu, ("g_cov0", "a_cov0", "gx", "gy", "gz", "ax", "ay", "az")), (plan.gyro_odom, ("gx", "gy", "gz")),
             (plan.att, ("qx", "qy", "qz", "qw", "q_cov0")), (plan.vel, ("vx", "vy", "vz", "qx", "qy", "qz", "qw")),
             (plan.pos, ("status", "lat", "lon", "alt"))]
    pending = [(name, set(cols)) for name, cols in roles if name]

    def get(name: str) -> TopicData:
        if name not in cache:
            cache[name] = topic_data(rawlog, name, plan.time_mode, warnings)
            if is_ned_frame(cache[name].frame_id):
                warnings.append(f"note: {name}: frame_id '{cache[name].frame_id}' names a NED/FRD frame (REP-103 "
                                "suffix): its vectors and orientation read as FRD/NED, not converted from ENU/FLU")
            if release:  # the TopicData holds what is needed of the topic from now on
                raw = rawlog.topics[name]
                raw.decoded, raw.log_ns, raw.data = None, np.zeros(0, np.int64), []
        return cache[name]

    def drop(name: str, cols: tuple[str, ...] = ()) -> None:
        """``cols`` of topic ``name`` are read (and, when no role still to come reads them, let go); with
        no ``cols``: the role reading ``name`` is done."""
        if not release or name not in cache:
            return
        if not cols:
            pending.pop(0)
            if not any(n == name for n, _ in pending):
                cache.pop(name)
            return
        later = set().union(*[c for n, c in pending[1:] if n == name])
        for k in cols:
            if k not in later:
                cache[name].cols.pop(k, None)

    def done(name: str) -> None:
        drop(name)

    streams: dict[str, Stream] = {}
    sources: list[str] = []
    if plan.imu:
        d = get(plan.imu)
        c = d.cols
        if np.all(c["g_cov0"] == -1):
            warnings.append(f"{d.name}: angular_velocity marked absent (covariance[0] = -1)")
        else:
            streams["gyro"] = Stream(d.t_ns, _body_vec(d, "g"), d.name)
        drop(plan.imu, ("g_cov0", "gx", "gy", "gz"))
        if np.all(c["a_cov0"] == -1):
            warnings.append(f"{d.name}: linear_acceleration marked absent (covariance[0] = -1)")
        else:
            streams["accel"] = Stream(d.t_ns, _body_vec(d, "a"), d.name)
        drop(plan.imu, ("a_cov0", "ax", "ay", "az"))
        sources.append(f"{d.stamp_source} ({d.name})")
        del d, c
        done(plan.imu)
    if plan.gyro_odom:
        d = get(plan.gyro_odom)
        streams["gyro"] = Stream(d.t_ns, _body_vec(d, "g"), d.name + " twist.angular")
        sources.append(f"{d.stamp_source} ({d.name})")
        del d
        done(plan.gyro_odom)
    q_t = q_v = None
    if plan.att:
        d = get(plan.att)
        q, ok = quat_ros_to_ned_frd(d.cols, is_ned_frame(d.frame_id))
        drop(plan.att, ("qx", "qy", "qz", "qw"))
        if d.msgtype == IMU:  # orientation_covariance[0] = -1: no orientation (REP-145), said as a note
            absent = d.cols["q_cov0"] == -1
            if absent.any():
                warnings.append(f"note: {d.name}: {int(absent.sum())} of {len(ok)} orientations marked absent "
                                "(orientation_covariance[0] = -1, REP-145); not used")
            bad = ~ok & ~absent
            ok &= ~absent
            if _placeholder(q, ok):
                warnings.append(f"note: {d.name}: the orientation is one constant quaternion in all {int(ok.sum())} "
                                "messages (a driver's placeholder, not an attitude); not used")
                ok[:] = False
        else:
            bad = ~ok
        if bad.any():
            warnings.append(f"{d.name}: {int(bad.sum())} of {len(ok)} orientations not unit quaternions; dropped")
        if ok.any():
            q_t, q_v = (d.t_ns, q) if ok.all() else (d.t_ns[ok], q[ok])
            streams["quat"] = Stream(q_t, q_v, d.name)
        if plan.att not in (plan.imu, plan.gyro_odom):
            sources.append(f"{d.stamp_source} ({d.name})")
        del d, q, ok
        done(plan.att)
    if plan.vel:
        d = get(plan.vel)
        body = d.msgtype == ODOM if plan.vel_frame is None else plan.vel_frame == "body"
        if body:
            v = _body_vec(d, "v")
            if d.msgtype == ODOM and plan.vel_frame is None:
                qv, okq = quat_ros_to_ned_frd(d.cols, is_ned_frame(d.frame_id))
                qv[~okq] = np.nan
            else:
                if q_t is None:
                    raise InputError(f"vel={d.name} in body frame needs an attitude (att=/topic)", rawlog.path)
                qv = _quat_at(d.t_ns, q_t, q_v)
            v_ned = body_to_ned(v, qv)
            del v, qv
        else:
            v_ned = _vec(d.cols, "v") if is_ned_frame(d.frame_id) else _vec_enu_to_ned(d.cols, "v")
        world = "NED" if is_ned_frame(d.frame_id) else "ENU"
        streams["vel"] = Stream(d.t_ns, v_ned, d.name + (" (body)" if body else f" ({world})"))
        if plan.vel not in (plan.imu, plan.gyro_odom, plan.att):
            sources.append(f"{d.stamp_source} ({d.name})")
        del d, v_ned
        done(plan.vel)
    del q_t, q_v
    if plan.pos:
        d = get(plan.pos)
        fix = d.cols["status"] >= 0
        if not fix.all():
            warnings.append(f"{d.name}: {int((~fix).sum())} messages without a fix (status < 0) dropped")
        p = np.stack([d.cols["lat"], d.cols["lon"], d.cols["alt"]], axis=-1)
        streams["pos"] = Stream(d.t_ns, p, d.name) if fix.all() else Stream(d.t_ns[fix], p[fix], d.name)
        sources.append(f"{d.stamp_source} ({d.name})")
        del d, p, fix
        done(plan.pos)
    by_src: dict[str, list[str]] = {}
    for item in dict.fromkeys(sources):
        src, _, topic = item.partition(" (")
        by_src.setdefault(src, []).append(topic.rstrip(")"))
    stamp_source = "; ".join(f"{src} ({', '.join(topics)})" for src, topics in by_src.items())
    all_t = [streams[k].t_ns for k in ("gyro", "accel", "quat", "vel", "pos")
             if k in streams and len(streams[k].t_ns)]
    clock = clock_of(np.concatenate(all_t), scratch=True) if all_t else "unknown"
    del all_t
    sel = str(selector) if selector else unit_selector(plan)
    return assemble_inslog(streams, path=rawlog.path, fmt=rawlog.fmt, selector=sel, clock=clock,
                           stamp_source=stamp_source, warnings=warnings)


def to_inventory(rawlog: RawLog) -> Inventory:
    """Topics, types, counts, rates, durations, clocks and ready selectors (one per unit)."""
    streams: list[StreamInfo] = []
    warnings = list(rawlog.warnings)
    notes: list[str] = []
    if not any(t.count for t in rawlog.topics.values()):
        damage = [w for w in rawlog.warnings if not w.startswith("note")]
        raise InputError("no readable messages" + (f"; {damage[0]}" if damage else " (empty log)"), rawlog.path)
    for name in sorted(rawlog.topics):
        raw = rawlog.topics[name]
        if raw.msgtype in SUPPORTED and (raw.decoded is not None or len(raw.data) == raw.count) and raw.count:
            d = topic_data(rawlog, name, "header", warnings, keys=())
            t_ns, src = d.t_ns, d.stamp_source
            fields = tuple(FIELDS[raw.msgtype])
        else:
            t_ns, src, fields = np.asarray(raw.log_ns, np.int64), "log time", ()
        t_sorted = np.sort(t_ns)
        kind = KIND.get(raw.msgtype, "other")
        streams.append(StreamInfo(
            name=name, kind=kind, count=raw.count, rate_hz=rate_of((t_sorted - t_sorted[0]) * 1e-9) if raw.count else 0.0,
            start_s=float(t_sorted[0]) * 1e-9 if raw.count else float("nan"),
            duration_s=float(t_sorted[-1] - t_sorted[0]) * 1e-9 if raw.count else 0.0,
            clock=f"{clock_of(t_ns)} ({src})", fields=(raw.msgtype,) + fields))
    selectors: list[str] = []
    nav_extra = []
    vels = _topics_of(rawlog, TWIST, TWIST_COV, VEC3)
    fixes = _topics_of(rawlog, FIX)
    atts = _topics_of(rawlog, QUAT_STAMPED, POSE, POSE_COV) + _orientation_only_imus(rawlog)
    if vels:
        nav_extra.append(f"vel={vels[0]}")
    if fixes:
        nav_extra.append(f"pos={fixes[0]}")
    for imu in _topics_of(rawlog, IMU):
        if _imu_all_zero(rawlog, imu):
            notes.append(f"{imu}: rates and specific forces all zero (orientation only): offered as att={imu}"
                         if imu in atts else f"{imu}: every reading zero (a placeholder topic): not offered as a unit")
            continue
        items = [f"imu={imu}"]
        if atts and not _imu_has_orientation(rawlog, imu):
            items.append(f"att={atts[0]}")
        selectors.append(",".join(items + nav_extra))
    for odom in _topics_of(rawlog, ODOM):
        selectors.append(f"odom={odom}")
    if not selectors and (vels or fixes or atts):
        selectors.append(",".join(([f"att={atts[0]}"] if atts else []) + nav_extra))
    if len(vels) > 1 or len(fixes) > 1:
        notes.append("several velocity/fix topics: change vel=/pos= in the selectors as needed")
    if vels:
        notes.append("TwistStamped/Vector3Stamped velocity is taken as ENU world frame; "
                     "add vel_frame=body if it is in the body (FLU) frame")
    notes.append("types: " + ", ".join(f"{n} {t.msgtype or '?'}" for n, t in rawlog.topics.items()))
    notes.append("clock: header.stamp by default; add time=log to use the bag's record time")
    return Inventory(path=rawlog.path, format=rawlog.fmt, streams=tuple(streams), selectors=tuple(selectors),
                     warnings=tuple(warnings), notes=tuple(notes))


# ---- InsLog (NED/FRD) -> ROS messages (ENU/FLU), for the writers -----------------------------
@dataclass(frozen=True)
class OutTopic:
    name: str
    msgtype: str
    stamp_ns: np.ndarray
    data: list[bytes]


def _stamp_cols(t_ns: np.ndarray) -> dict[str, np.ndarray]:
    t_ns = np.asarray(t_ns, np.int64)
    return {"header.stamp.sec": t_ns // 1_000_000_000, "header.stamp.nanosec": t_ns % 1_000_000_000}


def _abs_ns(log: InsLog, t_s: np.ndarray) -> np.ndarray:
    return int(log.meta.t0_ns) + np.round(np.asarray(t_s, float) * 1e9).astype(np.int64)


def _template(typestore, msgtype: str, frame_id: str, encoding: str):
    """A zero message of ``msgtype`` with ``frame_id`` in its header (built generically)."""
    def make(typename: str, depth: int = 0):
        cls = typestore.types[typename]
        kwargs = {}
        for fname, (nt, detail) in typestore.fielddefs[typename][1]:
            nt = int(nt)
            if nt == 2:
                kwargs[fname] = make(detail, depth + 1)
            elif nt == 1:
                kwargs[fname] = "" if detail[0] == "string" else (False if detail[0] == "bool" else 0)
            elif nt == 3:
                sub, count = detail
                dt = _BASE_DT.get(sub[1][0], "f8") if int(sub[0]) == 1 else None
                kwargs[fname] = np.zeros(count, dtype=dt) if dt else [make(sub[1]) for _ in range(count)]
            else:
                sub = detail[0]
                dt = _BASE_DT.get(sub[1][0], "f8") if int(sub[0]) == 1 else None
                kwargs[fname] = np.zeros(0, dtype=dt) if dt else []
        return cls(**kwargs)

    msg = make(msgtype)
    msg.header.frame_id = frame_id
    return msg


def ros_topics_from_inslog(log: InsLog, typestore, encoding: str, *, imu_topic: str = "/imu",
                           vel_topic: str = "/velocity", fix_topic: str = "/fix", att_topic: str = "/attitude",
                           body_frame: str = "base_link", world_frame: str = "map") -> list[OutTopic]:
    """The messages a writer stores for ``log``: /imu (Imu; orientation when the log has attitude at
    the IMU stamps, else orientation_covariance[0] = -1 and a separate /attitude QuaternionStamped),
    /velocity (TwistStamped, ENU world frame), /fix (NavSatFix). NED/FRD -> ENU/FLU."""
    out: list[OutTopic] = []
    t_q, q = log.quat_wxyz() if log.has_quat else (np.zeros(0), np.zeros((0, 4)))
    q_ns = _abs_ns(log, t_q)
    q_enu = quat_enu_flu_to_ned_frd_fast(q) if len(q) else np.zeros((0, 4))
    att_in_imu = False
    if log.has_gyro or log.has_accel:
        t_ns = _abs_ns(log, log.t_imu_s())
        n = len(t_ns)
        cols = _stamp_cols(t_ns)
        g = frd_to_flu(log.gyro_rad_s()) if log.has_gyro else np.zeros((n, 3))
        a = frd_to_flu(log.accel_m_s2()) if log.has_accel else np.zeros((n, 3))
        for i, c in enumerate(_V):
            cols[f"angular_velocity.{c}"] = g[:, i]
            cols[f"linear_acceleration.{c}"] = a[:, i]
        if not log.has_gyro:
            cols["angular_velocity_covariance.0"] = np.full(n, -1.0)
        if not log.has_accel:
            cols["linear_acceleration_covariance.0"] = np.full(n, -1.0)
        qi = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        if len(q_ns) and np.isin(t_ns, q_ns).all() and len(q_ns) == n:
            att_in_imu = True
            pos_idx = np.searchsorted(q_ns, t_ns)
            qi = q_enu[pos_idx]
        else:
            cols["orientation_covariance.0"] = np.full(n, -1.0)
        for i, c in enumerate(("w", "x", "y", "z")):
            cols[f"orientation.{c}"] = qi[:, i]
        tmpl = _template(typestore, IMU, body_frame, encoding)
        out.append(OutTopic(imu_topic, IMU, t_ns, encode_messages(typestore, IMU, tmpl, encoding, cols)))
    if len(q_ns) and not att_in_imu:
        cols = _stamp_cols(q_ns)
        for i, c in enumerate(("w", "x", "y", "z")):
            cols[f"quaternion.{c}"] = q_enu[:, i]
        tmpl = _template(typestore, QUAT_STAMPED, world_frame, encoding)
        out.append(OutTopic(att_topic, QUAT_STAMPED, q_ns,
                            encode_messages(typestore, QUAT_STAMPED, tmpl, encoding, cols)))
    if log.has_vel:
        t_v, v = log.vel_ned_m_s()
        t_ns = _abs_ns(log, t_v)
        cols = _stamp_cols(t_ns)
        v_enu = ned_to_enu(v)
        for i, c in enumerate(_V):
            cols[f"twist.linear.{c}"] = v_enu[:, i]
        tmpl = _template(typestore, TWIST, world_frame, encoding)
        out.append(OutTopic(vel_topic, TWIST, t_ns, encode_messages(typestore, TWIST, tmpl, encoding, cols)))
    if log.has_pos:
        t_p, p = log.lat_lon_alt()
        t_ns = _abs_ns(log, t_p)
        cols = _stamp_cols(t_ns)
        cols.update({"latitude": p[:, 0], "longitude": p[:, 1], "altitude": p[:, 2]})
        tmpl = _template(typestore, FIX, "gps", encoding)
        tmpl.status.service = 1
        out.append(OutTopic(fix_topic, FIX, t_ns, encode_messages(typestore, FIX, tmpl, encoding, cols)))
    if not out:
        raise InputError("nothing to write (the log has no IMU, attitude, velocity or position)",
                         log.meta.source_path)
    return out


def merged_order(topics: list[OutTopic], log_delay_ns: int = 0) -> list[tuple[int, int, int]]:
    """(log time ns, topic index, message index) of every message, in log-time order."""
    t = np.concatenate([tp.stamp_ns + int(log_delay_ns) for tp in topics])
    ti = np.concatenate([np.full(len(tp.stamp_ns), k) for k, tp in enumerate(topics)])
    mi = np.concatenate([np.arange(len(tp.stamp_ns)) for tp in topics])
    order = np.lexsort((ti, t))
    return list(zip(t[order].tolist(), ti[order].tolist(), mi[order].tolist()))


# ---- damaged compressed chunks (MCAP, ROS 1 bags) ----------------------------------------------------
def inflate_prefix(comp: str, data) -> bytes:
    """What of a chunk's compressed records decompresses, up to the end of ``data`` (a cut chunk) or the
    first damaged block (fed in 16 KiB steps: the blocks before it come out); b"" for another compression.
    ``comp``: MCAP's names ("" uncompressed, "zstd", "lz4") or a ROS 1 bag's ("none", "bz2", "lz4"). Not
    checked: the records walk of it is the check on its structure."""
    if comp in ("", "none"):
        return bytes(data)
    if comp == "zstd":
        import zstandard

        dec = zstandard.ZstdDecompressor().decompressobj()
    elif comp == "lz4":
        import lz4.frame

        dec = lz4.frame.LZ4FrameDecompressor()
    elif comp == "bz2":
        import bz2

        dec = bz2.BZ2Decompressor()
    else:
        return b""
    out = []
    for i in range(0, len(data), 1 << 14):
        try:
            out.append(dec.decompress(bytes(data[i:i + (1 << 14)])))
        except Exception:  # the damaged block: what came before it is kept
            break
    return b"".join(out)


__all__ = [
    "IMU", "ODOM", "TWIST", "TWIST_COV", "VEC3", "FIX", "QUAT_STAMPED", "POSE", "POSE_COV", "KIND",
    "FIELDS", "RawTopic", "RawLog", "Layout", "build_layout", "decode_topic", "library_decode",
    "encode_messages", "to_inslog", "to_inventory", "ros_topics_from_inslog", "merged_order",
    "normalize_msgtype", "register_msgdef", "default_typestore", "keep_supported", "plan_unit",
]
