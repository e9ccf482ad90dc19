"""Vendor CSVs (anything that is not the canonical tapost CSV) through a column map with units.

Six ways to get a column map, tried in this order:

1. ``PATH::map=FILE.json`` or a sidecar ``PATH.map.json`` next to the CSV: a JSON object
   ``{column: [canonical_name, unit], ...}``; canonical names are ``time``, ``gyro_x|y|z``,
   ``accel_x|y|z``, ``quat_w|x|y|z`` (or ``roll``, ``pitch``, ``yaw``), ``vel_n|e|d``, ``lat``, ``lon``, ``alt``.
   Optional keys:
   ``"_body_frame": "FRD"|"FLU"|"ZUP"``, ``"_nav_frame": "NED"|"ENU"|"NWU"``,
   ``"_quat": "body_to_nav"|"nav_to_body"`` (defaults FRD, NED, body_to_nav).
2. The NGIMU profile (x-io Technologies NGIMU logs: ``sensors.csv`` with ``Time (s)``,
   ``Gyroscope X (deg/s)``, ``Accelerometer X (g)``..., plus ``quaternion.csv`` ``Time (s),W,X,Y,Z``
   next to it). A directory holding ``sensors.csv`` is one log; a session directory whose
   sub-directories hold ``sensors.csv`` is several units (selector ``unit=NAME``).
3. A sensor_msgs/Imu topic exported from a ROS bag by ROS users' tools (``rostopic echo -p``:
   ``%time,field.header.stamp,...,field.angular_velocity.x``; PlotJuggler: ``__time,/imu/angular_velocity/x``;
   bagpy: ``Time,...,angular_velocity.x``): no units in the header, ROS's conventions give them (SI, REP 103:
   FLU body, ENU world, the orientation body -> world). The time is the header stamp where the file has it
   (rostopic's, integer ns), else the receive time; rostopic's other time column is restamped with it by the
   native export (``ColumnMap.also_time``). An orientation the IMU does not give (covariance -1, zeros) is
   left out.
4. One ArduPilot DataFlash message type dumped by pymavlink's ``mavlogdump.py --format csv --types IMU``
   (``timestamp,TimeUS,GyrX,...``): ArduPilot's field names in their logged units (:data:`_AP_FIELDS`),
   FRD/NED; the time mavlogdump's ``timestamp`` (pymavlink's UNIX mapping) or, without one, ``TimeUS``. One
   MAVLink message type dumped from a tlog the same way (``timestamp,HIGHRES_IMU.time_usec,...``): the tlog
   reader's units, the message's own time (:func:`_mavlink_dump_map`).
5. A PX4 topic written by pyulog's ``ulog2csv`` (``timestamp,gyro_rad[0],...,accelerometer_m_s2[0]``,
   ``q[0..3]``, vehicle_local_position's ``vx,vy,vz``): PX4's units, FRD/NED, microseconds since boot; the
   accelerometer of sensor_combined at its ``accelerometer_timestamp_relative`` (``ColumnMap.group_time``).
6. The header alone, when every needed column names its quantity, axis and unit unambiguously
   (``Gyro X (deg/s)``, ``gyro_x [rad/s]``, ``accel_z_m_s2``, ``wx (dps)``, ``timestamp (us)``, the
   ASL/EuRoC dataset's ``#timestamp [ns]``, ``w_RS_S_x [rad s^-1]``, ``a_RS_S_x [m s^-2]``...); a time
   column without a unit whose cells are ISO 8601 date-times (pandas' ``to_csv``) is read as UTC.
   Anything else is an InputError naming the columns found and how to write a map. A position or Euler
   angle group found in part (``Altitude (m)`` alone, ``Heading (deg)`` alone) is left out, said in a note.

Attitude as Euler angles (``Roll (deg)``, ``Pitch (deg)``, ``Yaw (deg)``; ``Heading`` and ``Azimuth`` are the
yaw): the Z-Y-X (yaw, pitch, roll) angles of the body -> nav rotation in the file's frames (FRD/NED unless a
map says otherwise: the aerospace roll, pitch and heading). A file with a quaternion too: the quaternion.

Units understood (header ``(unit)``/``[unit]``, a snake-case suffix, or a units row: the line under a header
of bare names giving each column's unit, ``s,deg/s,...``): rad/s, deg/s, dps, mrad/s,
deg/h; m/s^2, m/s2, m/s², g, mg, ug; s, ms, us, ns, ISO 8601 (date-time text); m/s, km/h, cm/s, mm/s, kn;
deg, rad, degE7;
m, cm, mm, ft; negative powers written out too (``rad s^-1``, ``m s^-2``, ``m·s⁻²``).

Comment lines before the header (``// ...``, Xsens MT Manager's export) are skipped; a ``// Coordinate system:
ENU|NED|NWU`` line among them states the frames (:data:`_PREAMBLE_FRAMES`).

Frames. Generic CSVs without a stated frame are taken as FRD/NED (said in the warnings).

NGIMU conventions, settled here and nowhere else. x-io's AHRS code (the Fusion library's
FusionConvention.h, found with the search tool) offers NWU / ENU / NED earth axes with North-West-Up
first; the NGIMU documentation itself was not reachable, so the convention was checked on the real
logs in ``shared/realdata/ngimu_session`` (three units, MANIFEST.md) and tests keep checking it:
* at rest the accelerometer reads about +1 g on z: the sensor frame is right-handed, z up
  (x forward, y left: FLU-like), so FRD = (x, -y, -z);
* rotating the accelerometer by the *conjugate* of the logged quaternion gives +1 g on the earth z
  axis (earth z up) and the magnetic field rotated the same way has ~0 y and positive x (x = magnetic
  north, y = west): the earth frame is NWU;
* body-frame gyro integration matches the conjugate's changes within a few degrees over +-150 deg
  swings and misses the logged quaternion's by up to 150 deg: the logged ``W,X,Y,Z`` rotates earth ->
  sensor (the conjugate of a Hamilton sensor -> earth quaternion).
Hence ``q_ned_frd = A conj(q) B^T`` with A = B = diag(1, -1, -1): ``(W, -X, Y, Z)``.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from logtools.conventions import DEG, G0_M_S2, quat_conj, quat_from_dcm, quat_from_euler, quat_mul
from logtools.errors import InputError
from logtools.inslog import InsLog
from parsers import csv_canonical
from parsers.assemble import REPEATED_LINES_SAID, Stream, build_inslog, repeated_lines
from parsers.base import DAMAGED_HEAD_SEARCH_BYTES, Inventory, Selector, StreamInfo
from parsers.csvtable import datetime_text_to_ns, decimal_text_to_int, delimiter as _delimiter, non_numeric_text
from parsers.csvtable import numeric_block, printable
from parsers.csvtable import read_table as _read_table

NAME = "csv-vendor"
EXTENSIONS = (".csv", ".txt")

CANONICAL = ("time", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z",
             "quat_w", "quat_x", "quat_y", "quat_z", "roll", "pitch", "yaw", "vel_n", "vel_e", "vel_d",
             "lat", "lon", "alt")
GROUPS = {"gyro": ("gyro_x", "gyro_y", "gyro_z"), "accel": ("accel_x", "accel_y", "accel_z"),
          "quat": ("quat_w", "quat_x", "quat_y", "quat_z"), "euler": ("roll", "pitch", "yaw"),
          "vel": ("vel_n", "vel_e", "vel_d"), "pos": ("lat", "lon", "alt")}
#: groups a header may give in part without being refused (an altitude or a heading column next to an IMU's):
#: the part is left out, said in a note
OPTIONAL_PARTS = ("euler", "pos")
#: quantity of each canonical name (decides which units are acceptable)
QUANTITY = {"time": "time", **{c: "rate" for c in GROUPS["gyro"]}, **{c: "accel" for c in GROUPS["accel"]},
            **{c: "unitless" for c in GROUPS["quat"]}, **{c: "angle" for c in GROUPS["euler"]},
            **{c: "speed" for c in GROUPS["vel"]}, "lat": "angle", "lon": "angle", "alt": "length"}
#: unit text (normalised) -> (quantity, factor to SI; time in ns; angles in degrees)
UNITS: dict[str, tuple[str, float]] = {
    "s": ("time", 1e9), "sec": ("time", 1e9), "ms": ("time", 1e6), "us": ("time", 1e3), "ns": ("time", 1.0),
    "rad/s": ("rate", 1.0), "deg/s": ("rate", DEG), "dps": ("rate", DEG), "mrad/s": ("rate", 1e-3),
    "deg/h": ("rate", DEG / 3600.0), "rad/sec": ("rate", 1.0), "deg/sec": ("rate", DEG),
    "m/s^2": ("accel", 1.0), "m/s2": ("accel", 1.0), "ms^-2": ("accel", 1.0), "m/s/s": ("accel", 1.0),
    "g": ("accel", G0_M_S2), "mg": ("accel", 1e-3 * G0_M_S2), "ug": ("accel", 1e-6 * G0_M_S2),
    "m/s": ("speed", 1.0), "km/h": ("speed", 1 / 3.6), "cm/s": ("speed", 0.01), "mm/s": ("speed", 1e-3),
    "kn": ("speed", 0.514444), "knots": ("speed", 0.514444),
    "deg": ("angle", 1.0), "rad": ("angle", 180.0 / np.pi), "dege7": ("angle", 1e-7),
    "m": ("length", 1.0), "cm": ("length", 0.01), "mm": ("length", 1e-3), "ft": ("length", 0.3048),
    "": ("unitless", 1.0), "-": ("unitless", 1.0), "1": ("unitless", 1.0),
    **{u: ("time", 1.0) for u in ("datetime", "date-time", "date/time", "iso", "iso8601")},
}
#: the "units" of a time column of ISO 8601 date-time text (``Time (ISO 8601)``, or a unitless time column
#: whose first cells are date-times: :func:`_datetime_named`), read by :func:`datetime_text_to_ns`
DATETIME_UNITS = frozenset({"datetime", "date-time", "date/time", "iso", "iso8601"})
#: the unit a time column found to hold date-time text is mapped with
DATETIME = "datetime"
#: snake-case unit suffixes (token tuples at the end of a name) -> unit text
SUFFIX_UNITS = {("rad", "s"): "rad/s", ("deg", "s"): "deg/s", ("dps",): "dps", ("m", "s2"): "m/s^2",
                ("m", "s", "2"): "m/s^2", ("mps2",): "m/s^2", ("mg",): "mg", ("g",): "g", ("m", "s"): "m/s",
                ("s",): "s", ("ms",): "ms", ("us",): "us", ("ns",): "ns", ("deg",): "deg", ("m",): "m"}

BODY_FRAMES = {"FRD": np.eye(3), "FLU": np.diag([1.0, -1.0, -1.0]), "ZUP": np.diag([1.0, -1.0, -1.0])}
NAV_FRAMES = {"NED": np.eye(3), "ENU": np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]]),
              "NWU": np.diag([1.0, -1.0, -1.0])}

NGIMU_SENSORS = "sensors.csv"
NGIMU_QUAT = "quaternion.csv"
_NGIMU_HEAD = ("Time (s)", "Gyroscope X (deg/s)", "Gyroscope Y (deg/s)", "Gyroscope Z (deg/s)",
               "Accelerometer X (g)", "Accelerometer Y (g)", "Accelerometer Z (g)")


@dataclass(frozen=True)
class ColumnMap:
    """csv column -> (canonical name, unit), the frames the data are in, and where the map came from."""

    columns: dict[str, tuple[str, str]]
    body_frame: str = "FRD"
    nav_frame: str = "NED"
    quat: str = "body_to_nav"
    origin: str = "header"
    frame_stated: bool = False
    ignored: tuple[str, ...] = field(default_factory=tuple)
    notes: tuple[str, ...] = ()  # "note: ..." lines: columns that look like a group but are left out, and why
    units_row: bool = False  # the line after the header gives the columns' units (skipped as data)
    decimal: str = "."  # the decimal mark: "," in a CSV saved in a comma-decimal locale (cells split by ';' or tab)
    #: other columns stamping the same rows (column, unit; a ROS export's receive time beside its header stamp,
    #: a DataFlash dump's TimeUS beside its UNIX time): not read, moved by the native export by each row's shift
    also_time: tuple[tuple[str, str], ...] = ()
    #: groups sampled at an offset from their row's time, given in a column: (group, column, unit, the value that
    #: marks no sample); PX4's sensor_combined accelerometer (accelerometer_timestamp_relative, us)
    group_time: tuple[tuple[str, str, str, int], ...] = ()

    def column_for(self, canonical: str) -> str | None:
        return next((c for c, (n, _) in self.columns.items() if n == canonical), None)


# ============================================================================================
# header -> column map
# ============================================================================================
_UNIT_RE = re.compile(r"^(?P<name>.*?)\s*[\(\[](?P<unit>[^\)\]]*)[\)\]]\s*$")
_AXIS = {"x": "x", "y": "y", "z": "z"}
_GYRO_WORDS = {"gyro", "gyroscope", "gyr", "omega", "angular", "angularrate", "angularvelocity", "rate"}
_ACC_WORDS = {"accel", "accelerometer", "acc", "acceleration", "specificforce"}
_QUAT_WORDS = {"quat", "quaternion", "q", "orientation"}
_VEL_WORDS = {"vel", "velocity", "v", "speed"}
_NOT_RAW = {"linear", "earth", "filtered", "bias", "std", "sigma", "var", "cov", "error", "err", "mag",
            "magnetometer", "magnetic", "raw", "setpoint", "sp", "cmd", "target", "gravity"}
_EULER_NAMES = {"roll": "roll", "pitch": "pitch", "yaw": "yaw", "heading": "yaw", "trueheading": "yaw",
                "azimuth": "yaw"}
#: a unit's first letter naming its quantity, as the ASL/EuRoC headers do (``w_RS_S_x [rad s^-1]``, ``a_RS_S_x
#: [m s^-2]``): read so only with a unit of that quantity
_LETTER_QUANTITY = {"w": ("rate", "gyro"), "omega": ("rate", "gyro"), "a": ("accel", "accel")}
#: written-out negative powers of seconds -> a slash (``rad s^-1`` -> ``rad/s``, ``m.s-2`` -> ``m/s^2``)
_PER_S = re.compile(r"\s*[.·*]?\s*s\s*\^?\s*-\s*([12])$")


def norm_unit(text: str) -> str:
    u = text.strip().lower().replace("⁻¹", "^-1").replace("⁻²", "^-2")
    u = u.replace("²", "^2").replace("°", "deg").replace("µ", "u").replace("μ", "u")
    u = _PER_S.sub(lambda m: "/s" if m.group(1) == "1" else "/s^2", u)
    u = u.replace(" ", "").replace("sec", "s") if u not in ("sec",) else u
    u = u.replace("degrees", "deg").replace("degree", "deg").replace("rads", "rad")
    return {"deg/s": "deg/s", "rad/s": "rad/s", "s": "s"}.get(u, u)


def _tokens(name: str) -> list[str]:
    n = re.sub(r"([a-z])([A-Z])", r"\1 \2", name.strip())
    return [t for t in re.split(r"[^A-Za-z0-9]+", n.lower()) if t]


def split_name_unit(col: str) -> tuple[list[str], str | None]:
    """``'Gyroscope X (deg/s)'`` -> (['gyroscope', 'x'], 'deg/s'); ``'accel_z_m_s2'`` -> (['accel', 'z'], 'm/s^2')."""
    m = _UNIT_RE.match(col)
    if m:
        return _tokens(m.group("name")), norm_unit(m.group("unit"))
    toks = _tokens(col)
    for n in (3, 2, 1):
        if len(toks) > n and tuple(toks[-n:]) in SUFFIX_UNITS:
            return toks[:-n], SUFFIX_UNITS[tuple(toks[-n:])]
    return toks, None


def classify(tokens: list[str], quat_file: bool = False, unit: str | None = None) -> str | None:
    """Canonical name a column's name tokens (and unit, where given) stand for, or None."""
    if not tokens or set(tokens) & _NOT_RAW:
        return None
    t = tokens
    joined = "".join(t)
    if joined in _EULER_NAMES:
        return _EULER_NAMES[joined]
    if joined in ("time", "timestamp", "t", "stamp", "timeus", "times", "sampletime", "utctime", "timeutc",
                  "datetime", "utc", "utctimestamp", "timestamputc"):
        return "time"
    if joined in ("lat", "latitude"):
        return "lat"
    if joined in ("lon", "lng", "long", "longitude"):
        return "lon"
    if joined in ("alt", "altitude", "height", "altmsl", "altitudemsl"):
        return "alt"
    if quat_file and len(t) == 1 and t[0] in ("w", "x", "y", "z"):
        return f"quat_{t[0]}"
    head, axis = t[:-1], t[-1]
    if not head and len(axis) >= 2:  # single token like 'wx', 'gyrox', 'accz', 'qw', 'vn'
        for pre, kind in (("gyro", "gyro"), ("gyr", "gyro"), ("w", "gyro"), ("omega", "gyro"),
                          ("accel", "accel"), ("acc", "accel"), ("a", "accel"), ("q", "quat"), ("quat", "quat"),
                          ("v", "vel")):
            if axis.startswith(pre) and len(axis) == len(pre) + 1:
                head, axis = [kind], axis[len(pre):]
                break
    words = set(head) | {"".join(head)}  # ('Specific Force X': 'specificforce')
    if head and head[0] in _LETTER_QUANTITY and axis in _AXIS and unit is not None:
        quantity, kind = _LETTER_QUANTITY[head[0]]
        if UNITS.get(unit, ("?",))[0] == quantity:
            return f"{kind}_{axis}"
    if words & _GYRO_WORDS or head == ["gyro"]:
        return f"gyro_{axis}" if axis in _AXIS else None
    if words & _ACC_WORDS or head == ["accel"]:
        return f"accel_{axis}" if axis in _AXIS else None
    if words & _QUAT_WORDS or head == ["quat"]:
        return f"quat_{axis}" if axis in ("w", "x", "y", "z") else None
    if words & _VEL_WORDS or head == ["vel"]:
        ax = {"n": "n", "north": "n", "e": "e", "east": "e", "d": "d", "down": "d"}.get(axis)
        return f"vel_{ax}" if ax else None
    return None


class MapError(ValueError):
    """Why the header cannot be mapped on its own."""


def map_from_header(columns: list[str], *, quat_file: bool = False) -> ColumnMap:
    """Build a column map from the header alone; MapError (with the reason) when not unambiguous."""
    found: dict[str, tuple[str, str]] = {}
    by_target: dict[str, list[str]] = {}
    no_unit: list[str] = []
    bad_unit: list[str] = []
    ignored = []
    left_out: list[str] = []  # why columns of an optional group are not used
    for col in columns:
        toks, unit = split_name_unit(col)
        target = classify(toks, quat_file=quat_file, unit=unit)
        if target is None:
            ignored.append(col)
            continue
        q = QUANTITY[target]
        if target in GROUPS["euler"] and UNITS.get(unit or "?", ("?",))[0] != q:
            # (names like 'Heading' are also used for other things: without an angle unit, not an attitude)
            ignored.append(col)
            left_out.append(f"{col!r} (no angle unit)")
            continue
        if unit is None:
            if q == "unitless":
                unit = ""
            else:
                no_unit.append(col)
                continue
        if UNITS.get(unit, ("?",))[0] != q:
            bad_unit.append(f"{col} ({unit!r} is not a {q} unit)")
            continue
        found[col] = (target, unit)
        by_target.setdefault(target, []).append(col)
    def prefer(targets, named) -> None:
        """Where a target has several columns and exactly one whose name tokens ``named`` says, that one: the
        others left out, said."""
        for t in targets:
            cs = by_target.get(t, [])
            keep = [c for c in cs if named(split_name_unit(c)[0])]
            if len(cs) > 1 and len(keep) == 1:
                left_out.append(f"{', '.join(repr(c) for c in cs if c not in keep)} (beside {keep[0]!r})")
                for c in cs:
                    if c not in keep:
                        ignored.append(c)
                        found.pop(c)
                by_target[t] = keep

    prefer(("yaw",), lambda toks: "".join(toks) == "yaw")  # 'Yaw' beside a 'Heading' (a compass's): the yaw
    # an accelerometer's column beside an 'Acceleration' one (an INS export's kinematic acceleration)
    prefer(GROUPS["accel"], lambda toks: "acceleration" not in toks)
    for g in OPTIONAL_PARTS:  # in part or twice: left out, said
        names = GROUPS[g]
        cols = [c for n in names for c in by_target.get(n, [])]
        if cols and (not all(n in by_target for n in names) or len(cols) > len(names)):
            twice = [n for n in names if len(by_target.get(n, [])) > 1]
            left_out.append(f"{', '.join(map(repr, cols))} (" + (f"{'/'.join(twice)} in more than one column"
                            if twice else f"no complete {'/'.join(names)} group") + ")")
            ignored.extend(cols)
            for c in cols:
                found.pop(c)
            for n in names:
                by_target.pop(n, None)
    dup = {t: cs for t, cs in by_target.items() if len(cs) > 1}
    if dup:
        t, cs = next(iter(dup.items()))
        raise MapError(f"columns {', '.join(cs)} all look like {t}")
    if bad_unit:
        raise MapError(f"unit not understood: {bad_unit[0]}")
    if "time" not in by_target:
        raise MapError("no time column with a unit" + (f" ({no_unit[0]} has no unit)" if no_unit else ""))
    if no_unit:
        raise MapError(f"no unit for column(s) {', '.join(no_unit[:4])}")
    complete = [g for g, names in GROUPS.items() if all(n in by_target for n in names)]
    partial = [g for g, names in GROUPS.items() if g not in complete and any(n in by_target for n in names)]
    if partial:
        raise MapError(f"incomplete column group(s): {', '.join(partial)}")
    if not complete:
        raise MapError("no complete gyro/accel/quaternion/velocity/position column group")
    notes = (f"note: column(s) not used: {'; '.join(left_out)}",) if left_out else ()
    return ColumnMap(found, ignored=tuple(ignored), notes=notes)


def load_map_file(map_path: str, csv_path: str) -> ColumnMap:
    try:
        with open(map_path) as fh:
            raw = json.load(fh)
    except OSError as exc:
        raise InputError(f"column map {map_path}: {exc.strerror}", csv_path) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"column map {map_path} is not valid JSON: {exc.msg} (line {exc.lineno})", csv_path) from None
    if not isinstance(raw, dict):
        raise InputError(f"column map {map_path} must be a JSON object {{column: [name, unit]}}", csv_path)
    cols: dict[str, tuple[str, str]] = {}
    for col, spec in raw.items():
        if col.startswith("_"):
            continue
        if (not isinstance(spec, (list, tuple)) or len(spec) != 2 or spec[0] not in CANONICAL
                or not isinstance(spec[1], str)):
            raise InputError(f"column map {map_path}: entry {col!r} must be [canonical_name, unit] with a name "
                             f"from {', '.join(CANONICAL)}", csv_path)
        unit = norm_unit(spec[1])
        if UNITS.get(unit, ("?",))[0] != QUANTITY[spec[0]]:
            raise InputError(f"column map {map_path}: unit {spec[1]!r} of {col!r} is not a "
                             f"{QUANTITY[spec[0]]} unit", csv_path)
        cols[col] = (spec[0], unit)
    body = str(raw.get("_body_frame", "FRD")).upper()
    nav = str(raw.get("_nav_frame", "NED")).upper()
    quat = str(raw.get("_quat", "body_to_nav")).lower()
    if body not in BODY_FRAMES or nav not in NAV_FRAMES or quat not in ("body_to_nav", "nav_to_body"):
        raise InputError(f"column map {map_path}: _body_frame must be one of {', '.join(BODY_FRAMES)}, "
                         f"_nav_frame one of {', '.join(NAV_FRAMES)}, _quat body_to_nav|nav_to_body", csv_path)
    if not any(n == "time" for n, _ in cols.values()):
        raise InputError(f"column map {map_path} maps no column to 'time'", csv_path)
    stated = any(k in raw for k in ("_body_frame", "_nav_frame"))
    return ColumnMap(cols, body, nav, quat, origin=f"map {os.path.basename(map_path)}", frame_stated=stated)


def _ngimu_map(columns: list[str]) -> ColumnMap | None:
    if tuple(columns[:len(_NGIMU_HEAD)]) != _NGIMU_HEAD:
        return None
    cmap = map_from_header(columns)
    return ColumnMap(cmap.columns, body_frame="ZUP", nav_frame="NWU", quat="nav_to_body", origin="NGIMU profile",
                     frame_stated=True, ignored=cmap.ignored, notes=cmap.notes)


def _complete_groups(found: dict[str, tuple[str, str]]) -> dict[str, tuple[str, str]]:
    """``found`` (column -> (canonical name, unit)) without the columns of groups it has in part (empty where
    no group is complete)."""
    names = {v[0] for v in found.values()}
    complete = [g for g, ns in GROUPS.items() if set(ns) <= names]
    return {c: v for c, v in found.items() if any(v[0] in GROUPS[g] for g in complete)}


def _format_map(found: dict[str, tuple[str, str]], columns: list[str], frames: tuple[str, str], origin: str,
                **more) -> ColumnMap:
    """The column map of a CSV a log format's own tool wrote (its columns' units and frames known by the
    format's conventions): every other column ignored, the frames (body, navigation) stated."""
    return ColumnMap(found, body_frame=frames[0], nav_frame=frames[1], quat="body_to_nav", origin=origin,
                     frame_stated=True, ignored=tuple(c for c in columns if c not in found), **more)


#: ROS message fields as CSV exports of bags name them (``rostopic echo -p``: ``field.angular_velocity.x``;
#: PlotJuggler: ``/imu/angular_velocity/x``; bagpy: ``angular_velocity.x``): sensor_msgs/Imu's rates,
#: specific forces and orientation, in SI units and REP 103's frames (body FLU, world ENU) by convention
_ROS_GROUPS = {"angular_velocity": "gyro", "linear_acceleration": "accel", "orientation": "quat"}
#: such a column's name: the field's own spelling, after a '.' or '/' (or nothing) and before the axis
_ROS_FIELD = re.compile(r"(?:^|[./])(?P<field>angular_velocity|linear_acceleration)[./](?P<axis>[xyz])$"
                        r"|(?:^|[./])(?P<q>orientation)[./](?P<qaxis>[xyzw])$")
#: their time columns, the first present wanted: the header stamp (``rostopic echo -p`` writes integer ns),
#: then the receive time (rostopic's ``%time``, ns; PlotJuggler's ``__time`` and bagpy's ``Time``, seconds)
_ROS_TIMES = (("field.header.stamp", "ns"), ("%time", "ns"), ("__time", "s"), ("Time", "s"))


def _ros_fields_map(path: str, columns: list[str], sample: int = 20) -> ColumnMap | None:
    """The column map of a CSV exported from a ROS bag's sensor_msgs/Imu topic (:data:`_ROS_GROUPS`,
    :data:`_ROS_TIMES`), whose columns carry no units; None where the header is not one (no rates); an
    InputError for the fields of several topics in one file."""
    found: dict[str, tuple[str, str]] = {}
    for col in columns:
        m = _ROS_FIELD.search(col.strip())
        if m is None:
            continue
        kind = _ROS_GROUPS[m.group("field") or m.group("q")]
        name = f"{kind}_{m.group('axis') or m.group('qaxis')}"
        if name in (v[0] for v in found.values()):  # two topics' fields (PlotJuggler's export of many series)
            other = next(c for c, v in found.items() if v[0] == name)
            topics = ", ".join(repr(c[:len(c) - len(_ROS_FIELD.search(c.strip()).group(0))] or "(none)")
                               for c in (other, col))
            raise InputError(f"ROS message fields of more than one topic ({topics}): export one topic per file, "
                             f"or name the columns to read in a column map ({os.path.basename(path)}.map.json)", path)
        found[col] = (name, {"gyro": "rad/s", "accel": "m/s^2", "quat": ""}[kind])
    names = {v[0] for v in found.values()}
    if not {"gyro_x", "gyro_y", "gyro_z"} <= names:
        return None
    if not {"accel_x", "accel_y", "accel_z"} <= names:
        found = {c: v for c, v in found.items() if not v[0].startswith("accel_")}
    notes: list[str] = []
    rows = _first_rows(path, sample)

    def first(col: str) -> list[float]:
        k = columns.index(col)
        out = []
        for r in rows:
            try:
                out.append(float(r[k]))
            except (IndexError, ValueError):
                pass
        return out

    quat = [c for c, v in found.items() if v[0].startswith("quat_")]
    if quat:
        cov = next((c for c in columns if re.search(r"(?:^|[./])orientation_covariance[./]?0$", c.strip())), None)
        unset = (cov is not None and any(v == -1.0 for v in first(cov))) or all(
            v == 0.0 for c in quat for v in first(c))
        if len(quat) != 4 or unset:
            for c in quat:
                found.pop(c)
            if unset:
                notes.append("note: the orientation columns not used: the IMU gives none (covariance -1 or zeros)")
    times = [(c, u) for c, u in _ROS_TIMES if c in columns]
    if not times:
        return None
    col, unit = times[0]
    if len(times) > 1 and col == "field.header.stamp" and all(v == 0.0 for v in first(col)):
        notes.append("note: header stamps unset (0): the receive time %time read")
        col, unit = times[1]
    found[col] = ("time", unit)
    also = tuple((c, u) for c, u in times if c != col and c in ("field.header.stamp", "%time"))
    return _format_map(found, columns, ("FLU", "ENU"),
                       "ROS message fields (SI units, REP 103 frames: FLU body, ENU world)", notes=tuple(notes),
                       also_time=also)


#: ArduPilot DataFlash messages dumped to CSV by pymavlink's ``mavlogdump.py --format csv --types IMU`` (the
#: ArduPilot wiki's way to a spreadsheet): their fields' own names, in the units ArduPilot logs them in (IMU's
#: GyrX rad/s and AccX m/s/s, ATT's and XKF1's Roll/Pitch/Yaw deg, XKF1's VN/VE/VD m/s, POS's Lat/Lng deg and
#: Alt m), body FRD, navigation NED
_AP_FIELDS = {"GyrX": ("gyro_x", "rad/s"), "GyrY": ("gyro_y", "rad/s"), "GyrZ": ("gyro_z", "rad/s"),
              "AccX": ("accel_x", "m/s^2"), "AccY": ("accel_y", "m/s^2"), "AccZ": ("accel_z", "m/s^2"),
              "Roll": ("roll", "deg"), "Pitch": ("pitch", "deg"), "Yaw": ("yaw", "deg"),
              "VN": ("vel_n", "m/s"), "VE": ("vel_e", "m/s"), "VD": ("vel_d", "m/s"),
              "Lat": ("lat", "deg"), "Lng": ("lon", "deg"), "Alt": ("alt", "m")}
#: the instance fields of multi-instance messages (IMU's I, an EKF core's C): one instance per file
_AP_INSTANCE = ("I", "C")


def _ardupilot_map(path: str, columns: list[str], sample: int = 40) -> ColumnMap | None:
    """The column map of a mavlogdump CSV of one ArduPilot DataFlash message type (:data:`_AP_FIELDS`): the
    time mavlogdump's ``timestamp`` (UNIX seconds where pymavlink put the log on GPS time), else ``TimeUS``
    (microseconds since boot), the other restamped with it by the native export; None where the header is not
    one; an InputError for several instances (IMU's I, an EKF core's C) interleaved in one file."""
    if "TimeUS" not in columns or "timestamp" not in columns:
        return None
    found = _complete_groups({c: _AP_FIELDS[c] for c in columns if c in _AP_FIELDS})
    if not found:
        return None
    rows = _first_rows(path, sample)
    for inst in _AP_INSTANCE:
        if inst in columns:
            k = columns.index(inst)
            seen = sorted({r[k] for r in rows if len(r) > k})
            if len(seen) > 1:
                raise InputError(f"the CSV interleaves instances {inst} = {', '.join(seen)} of one message type: "
                                 f"dump one (mavlogdump.py --condition \"IMU.{inst}=={seen[0]}\", the message's "
                                 "name in place of IMU)", path)
    k = columns.index("timestamp")
    try:
        unix = bool(rows) and float(rows[0][k]) > csv_canonical.EPOCH_THRESHOLD_S
    except (IndexError, ValueError):
        unix = False
    time, other = (("timestamp", "s"), ("TimeUS", "us")) if unix else (("TimeUS", "us"), ("timestamp", "s"))
    found[time[0]] = ("time", time[1])
    return _format_map(found, columns, ("FRD", "NED"),
                       "ArduPilot DataFlash fields (mavlogdump CSV: their own units, FRD/NED)", also_time=(other,))


def _mavlink_dump_map(columns: list[str]) -> ColumnMap | None:
    """The column map of one MAVLink message type dumped from a tlog by ``mavlogdump.py --format csv --types
    HIGHRES_IMU`` (``timestamp,HIGHRES_IMU.time_usec,HIGHRES_IMU.xacc,...``): the message's fields in the
    units the tlog reader takes them in (:mod:`parsers.mavlink_tlog`: its IMU scales, ATTITUDE's radians,
    GLOBAL_POSITION_INT's degE7, mm and cm/s), NED/FRD; the time the message's own (``time_usec``: UNIX time
    above 1e15 us, else since boot; ``time_boot_ms``), the receive ``timestamp`` moved with it by the export.
    None where the header is not one message's dump (a dump of several types interleaves their rows)."""
    from parsers import mavlink_tlog as mt

    if not columns or columns[0] != "timestamp" or len(columns) < 3:
        return None
    types = {c.split(".", 1)[0] for c in columns[1:] if "." in c}
    if len(types) != 1 or any("." not in c for c in columns[1:]):
        return None
    msg = types.pop()
    fields: dict[str, tuple[str, str]] = {}
    if msg in mt.IMU_SCALE:
        g, a = mt.IMU_SCALE[msg]
        gu = {1.0: "rad/s", mt.MRAD_TO_RAD: "mrad/s"}[g]
        au = {1.0: "m/s^2", mt.MG_TO_M_S2: "mg"}[a]
        fields = {**{f"{x}gyro": (f"gyro_{x}", gu) for x in "xyz"}, **{f"{x}acc": (f"accel_{x}", au) for x in "xyz"}}
    elif msg == "ATTITUDE":
        fields = {f: (f, "rad") for f in ("roll", "pitch", "yaw")}
    elif msg == "ATTITUDE_QUATERNION":
        fields = {f"q{i + 1}": (f"quat_{x}", "") for i, x in enumerate("wxyz")}
    elif msg == "GLOBAL_POSITION_INT":
        fields = {"lat": ("lat", "dege7"), "lon": ("lon", "dege7"), "alt": ("alt", "mm"),
                  **{f"v{x}": (f"vel_{n}", "cm/s") for x, n in zip("xyz", "ned")}}
    elif msg == "LOCAL_POSITION_NED":
        fields = {f"v{x}": (f"vel_{n}", "m/s") for x, n in zip("xyz", "ned")}
    found = {f"{msg}.{f}": v for f, v in fields.items() if f"{msg}.{f}" in columns}
    time = next(((f"{msg}.{f}", u) for f, u in (("time_usec", "us"), ("time_boot_ms", "ms"))
                 if f"{msg}.{f}" in columns), None)
    if not found or time is None:
        return None
    found[time[0]] = ("time", time[1])
    return _format_map(found, columns, ("FRD", "NED"),
                       f"MAVLink {msg} fields (mavlogdump CSV: the message's units, FRD/NED)",
                       also_time=(("timestamp", "s"),))


#: PX4 topics written to CSV by pyulog's ``ulog2csv`` (one file per topic: ``LOG_sensor_combined_0.csv``...),
#: named as PX4's message definitions name their fields, in their units (rad/s, m/s^2; the attitude
#: quaternion w, x, y, z from FRD body to NED; vehicle_local_position's velocity NED, m/s; vehicle_global_position
#: deg and m), ``timestamp`` in microseconds since boot. The field that tells each topic apart from other CSVs
_PX4_TOPICS = (
    ("gyro_rad[0]", {**{f"gyro_rad[{i}]": (f"gyro_{a}", "rad/s") for i, a in enumerate("xyz")},
                     **{f"accelerometer_m_s2[{i}]": (f"accel_{a}", "m/s^2") for i, a in enumerate("xyz")}}),
    ("q[0]", {f"q[{i}]": (f"quat_{a}", "") for i, a in enumerate("wxyz")}),
    ("v_xy_valid", {"vx": ("vel_n", "m/s"), "vy": ("vel_e", "m/s"), "vz": ("vel_d", "m/s")}),
    ("eph", {"lat": ("lat", "deg"), "lon": ("lon", "deg"), "alt": ("alt", "m")}),
)


def _px4_map(columns: list[str]) -> ColumnMap | None:
    """The column map of a PX4 topic written by pyulog's ``ulog2csv`` (:data:`_PX4_TOPICS`); None where the
    header is not one. sensor_combined's accelerometer at its own stamps (``accelerometer_timestamp_relative``,
    as tapost's ULog reader takes it)."""
    if "timestamp" not in columns:
        return None
    found: dict[str, tuple[str, str]] = {}
    for mark, fields in _PX4_TOPICS:
        if mark in columns:
            found.update({c: v for c, v in fields.items() if c in columns})
    found = _complete_groups(found)
    if not found:
        return None
    found["timestamp"] = ("time", "us")
    from parsers.ulog import RELATIVE_TIMESTAMP_INVALID

    rel = (("accel", "accelerometer_timestamp_relative", "us", RELATIVE_TIMESTAMP_INVALID),) if (
        "accel_x" in (v[0] for v in found.values()) and "accelerometer_timestamp_relative" in columns) else ()
    return _format_map(found, columns, ("FRD", "NED"), "PX4 topic fields (ulog2csv: PX4's units, FRD/NED)",
                       group_time=rel)


# ============================================================================================
# files and directories
# ============================================================================================
#: comment lines a vendor CSV may carry before its header (Xsens MT Manager's export: ``// General
#: information:`` ... ``// Coordinate system: ENU``): skipped by the readers, kept by the native export. (Not
#: '%' nor '#': rostopic's header starts with ``%time``, the EuRoC dataset's with ``#timestamp``)
_PREAMBLE_MARKS = (b"//",)


def _skip_preamble(head: bytes) -> int:
    """The byte offset of the header line in ``head`` (a file's first bytes): after the comment lines
    (:data:`_PREAMBLE_MARKS`) before it; 0 without any."""
    off = 0
    while True:
        end = head.find(b"\n", off)
        if end < 0 or not head[off:end].lstrip(b"\xef\xbb\xbf").lstrip().startswith(_PREAMBLE_MARKS):
            return off
        off = end + 1


def header_offset(path: str) -> int:
    """The byte offset of a vendor CSV's header line (:func:`_skip_preamble`)."""
    with open(path, "rb") as fh:
        return _skip_preamble(fh.read(DAMAGED_HEAD_SEARCH_BYTES))


def _head_lines(path: str, n: int) -> list[str]:
    """The header line (its BOM left out) and the ``n`` lines after it, as text."""
    start = header_offset(path)
    with open(path, "rb") as fh:
        fh.seek(start)
        lines = [fh.readline(65536) for _ in range(n + 1)]
    return [lines[0].lstrip(b"\xef\xbb\xbf").decode("utf-8", "replace")] + [
        ln.decode("utf-8", "replace") for ln in lines[1:]]


def _first_rows(path: str, n: int) -> list[list[str]]:
    """The cells of the first ``n`` data lines (after the header), split as the header is, unquoted."""
    head, *lines = _head_lines(path, n)
    sep = _delimiter(head)
    return [[c.strip().strip('"') for c in line.strip().split(sep)] for line in lines if line.strip()]


def _header_of(path: str) -> list[str]:
    text = _head_lines(path, 0)[0].strip()
    return [c.strip().strip('"') for c in text.split(_delimiter(text))]


def _units_of(path: str, columns: list[str]) -> list[str] | None:
    """The units of a header's columns given on the next line (``Time,GyroX,...`` then ``s,deg/s,...``: a
    logger's habit), or None where that line is data (or anything but units)."""
    head, line = _head_lines(path, 1)
    text = line.strip()
    cells = [c.strip().strip('"').strip() for c in text.split(_delimiter(head))]
    if len(cells) != len(columns):
        return None
    units = []
    for c in cells:
        u = c[1:-1] if len(c) >= 2 and c[0] + c[-1] in ("()", "[]") else c
        if u and not (norm_unit(u) in UNITS and re.search(r"[A-Za-z/°²µ]", u) or u in ("-", "1")):
            return None  # a number, or text that is no unit
        units.append(u)
    return units if any(UNITS.get(norm_unit(u), ("unitless",))[0] != "unitless" for u in units) else None


_COMMA_NUMBER = re.compile(r"^\s*\"?[-+]?\d+,\d+(?:[eE][-+]?\d+)?\"?\s*$")
_POINT_NUMBER = re.compile(r"^\s*\"?[-+]?(?:\d+\.\d*|\.\d+)(?:[eE][-+]?\d+)?\"?\s*$")


def _decimal_mark(path: str, skip: int, sample: int = 50) -> str:
    """"," where the data lines (after ``skip`` header lines) of a CSV whose cells are split by ';' or a tab
    write their numbers with decimal commas (a spreadsheet saved in a comma-decimal locale), else "."."""
    lines = _head_lines(path, skip - 1 + sample)
    sep = _delimiter(lines[0])
    if sep == ",":
        return "."
    lines = lines[skip:]
    cells = [c for line in lines for c in line.strip().split(sep) if c.strip()]
    comma = sum(bool(_COMMA_NUMBER.match(c)) for c in cells)
    point = sum(bool(_POINT_NUMBER.match(c)) for c in cells)
    return "," if comma > point else "."


def _looks_like_csv_header(head: bytes) -> bool:
    first = head.split(b"\n", 1)[0].lstrip(b"\xef\xbb\xbf").rstrip(b"\r")
    if not first or len(first) > 8000:
        return False
    try:
        text = first.decode("utf-8")
    except UnicodeDecodeError:
        return False
    if not text.replace("\t", " ").isprintable() or not any(d in text for d in (",", ";", "\t")):
        return False
    cells = [c.strip() for c in text.split(_delimiter(text))]
    # a header has named cells: most are not numbers
    named = sum(1 for c in cells if c and not re.fullmatch(r"[-+0-9.eE]+", c))
    return named >= max(1, len(cells) // 2)


def _unit_dirs(path: str) -> list[str]:
    """Sub-directories of a session directory that hold a sensors.csv (sorted)."""
    try:
        names = sorted(os.listdir(path))
    except OSError:
        return []
    return [n for n in names if os.path.isfile(os.path.join(path, n, NGIMU_SENSORS))]


def sniff(head: bytes, path: str) -> bool:
    if os.path.isdir(path):
        return os.path.isfile(os.path.join(path, NGIMU_SENSORS)) or bool(_unit_dirs(path))
    if csv_canonical.sniff(head, path):
        return False
    return _looks_like_csv_header(head[_skip_preamble(head):])


@dataclass(frozen=True)
class _Source:
    """What one log of this format is made of."""

    table: str  # the CSV with time (+ gyro/accel...)
    quat_table: str | None  # a separate quaternion CSV (NGIMU) or None
    unit: str  # unit name ('' for a single log)


def _resolve(path: str, selector: Selector) -> _Source:
    unit = selector.get("unit")
    if os.path.isdir(path):
        if os.path.isfile(os.path.join(path, NGIMU_SENSORS)) and unit is None:
            d = path
            unit = ""
        else:
            units = _unit_dirs(path)
            if not units and os.path.isfile(os.path.join(path, NGIMU_SENSORS)):
                raise InputError(f"unit={unit}: this folder is one unit's (it holds {NGIMU_SENSORS}): give it "
                                 "without unit=, or its session's folder with unit=", path)
            if not units:
                raise InputError("directory holds no sensors.csv (nor unit folders with one)", path)
            if unit is None:
                unit = units[0]
            elif unit not in units:
                raise InputError(f"no unit {unit!r} in session (has: {', '.join(units)})", path)
            d = os.path.join(path, unit)
        table = os.path.join(d, NGIMU_SENSORS)
    else:
        if unit is not None:
            raise InputError("unit= selects a unit folder of a session directory; this is a single CSV", path)
        table, unit = path, ""
    q = os.path.join(os.path.dirname(table), NGIMU_QUAT)
    quat_table = q if os.path.basename(table) == NGIMU_SENSORS and os.path.isfile(q) else None
    return _Source(table, quat_table, unit)


#: a preamble line stating the data's frames (Xsens MT Manager: ``// Coordinate system: ENU``; its sensor
#: frame is the case's x forward, z up in ENU and NWU, and turned to z down in NED): (body, navigation)
_STATED_FRAMES = re.compile(rb"^\s*//\s*coordinate system\s*:\s*(ENU|NED|NWU)\s*$", re.IGNORECASE | re.MULTILINE)
_PREAMBLE_FRAMES = {"ENU": ("FLU", "ENU"), "NED": ("FRD", "NED"), "NWU": ("FLU", "NWU")}


def column_map_for(src: _Source, selector: Selector) -> ColumnMap:
    cmap = _column_map(src, selector)
    mark = _decimal_mark(src.table, 2 if cmap.units_row else 1)
    if mark != cmap.decimal:
        cmap = replace(cmap, decimal=mark)
    if not cmap.frame_stated and (start := header_offset(src.table)):
        with open(src.table, "rb") as fh:
            m = _STATED_FRAMES.search(fh.read(start))
        if m is not None:  # (the preamble says the frames: no guess, no warning)
            body, nav = _PREAMBLE_FRAMES[m.group(1).decode().upper()]
            cmap = replace(cmap, body_frame=body, nav_frame=nav, frame_stated=True,
                           origin=cmap.origin + f"; frames {body}/{nav} from its '{m.group(0).decode().strip()}'")
    return cmap


def _column_map(src: _Source, selector: Selector) -> ColumnMap:
    columns = _header_of(src.table)
    map_file = selector.get("map")
    if map_file is None and os.path.isfile(src.table + ".map.json"):
        map_file = src.table + ".map.json"
    if map_file is not None:
        cmap = load_map_file(map_file, src.table)
        missing = [c for c in cmap.columns if c not in columns]
        if missing:
            raise InputError(f"column map names column(s) not in the CSV: {', '.join(missing[:4])} "
                             f"(CSV has: {', '.join(printable(c) for c in columns[:12])})", src.table)
        return cmap
    ng = _ngimu_map(columns)
    if ng is not None:
        return ng
    known = (_ros_fields_map(src.table, columns) or _ardupilot_map(src.table, columns)
             or _mavlink_dump_map(columns) or _px4_map(columns))
    if known is not None:
        return known
    try:
        return map_from_header(columns)
    except MapError as first:
        why = first
        units = _units_of(src.table, columns)
        # names on the header line, units on the next; a time column without a unit whose cells are date-times
        for named, origin in (([f"{c} ({u})" if u else c for c, u in zip(columns, units)] if units else None,
                               "header and units row"),
                              (_datetime_named(src.table, columns), "header and date-time cells")):
            if named is None:
                continue
            try:
                m = map_from_header(named)
            except MapError as again:
                why = again
            else:
                back = dict(zip(named, columns))
                return ColumnMap({back[c]: v for c, v in m.columns.items()}, origin=origin,
                                 ignored=tuple(back[c] for c in m.ignored), notes=m.notes,
                                 units_row=origin == "header and units row")
        shown = ", ".join(repr(printable(c)) for c in columns[:10]) + (", ..." if len(columns) > 10 else "")
        raise InputError(
            f"cannot map CSV columns unambiguously ({printable(why, 200)}); columns found: {shown}; write a column map "
            f"JSON {{column: [canonical_name, unit]}} (names: time, gyro_x.., accel_x.., quat_w.. or roll/pitch/yaw, "
            f"vel_n.., lat, lon, alt) and pass PATH::map=FILE.json or save it as "
            f"{os.path.basename(src.table)}.map.json", src.table) from None


def _datetime_named(path: str, columns: list[str], sample: int = 20) -> list[str] | None:
    """The header with ``(datetime)`` after each time column that has no unit and whose first ``sample`` data
    cells are mostly ISO 8601 date-times (``Timestamp``, ``UTC Time``: a logger's or pandas' export); None
    where there is none."""
    rows = _first_rows(path, sample)
    out, found = list(columns), False
    for k, col in enumerate(columns):
        toks, unit = split_name_unit(col)
        if unit is not None or classify(toks) != "time":
            continue
        cells = [r[k] for r in rows if len(r) > k]
        if cells and sum(bool(_DATETIME.match(c)) for c in cells) > len(cells) // 2:
            out[k], found = f"{col} ({DATETIME})", True
    return out if found else None


#: a value beyond this magnitude in a data column is no reading (damaged digits: ``1e300``, ``inf``)
_ABSURD = 1e300

_SCALE_POW10 = {"s": 9, "sec": 9, "ms": 6, "us": 3, "ns": 0}


def time_to_ns(text: pd.Series, unit: str, decimal: str = ".", warns: list[str] | None = None,
               what: str = "") -> tuple[np.ndarray, np.ndarray, float]:
    """Time column text -> (int64 ns, valid mask, resolution s), from the decimal text exactly (no float
    rounding; ``decimal``: the decimal mark). The resolution is that of a fixed number of decimals (``%.3f``
    seconds: 1 ms), else 0. A date-time unit (DATETIME_UNITS): :func:`datetime_text_to_ns`, a note in
    ``warns`` (naming ``what``) where the text gives no time zone."""
    if unit in DATETIME_UNITS:
        ns, ok, res, naive = datetime_text_to_ns(text)
        if naive and warns is not None:
            warns.append(f"{what}: date-times without a time zone taken as UTC")
        return ns, ok, res
    ns, ok, dec = decimal_text_to_int(text, _SCALE_POW10[unit], decimal)
    if len(ok) and not ok.any():  # text no decimal scan reads: float64 is all it offers
        if decimal != ".":
            text = text.str.replace(decimal, ".", regex=False)
        v = pd.to_numeric(text, errors="coerce").to_numpy(float) * UNITS[unit][1]
        ok = np.isfinite(v) & (np.abs(v) < 9e18)
        ns = np.where(ok, np.round(np.where(ok, v, 0.0)), 0).astype(np.int64)
        dec = None
    return ns, ok, 0.0 if dec is None else 10.0 ** (_SCALE_POW10[unit] - dec - 9)


def _rotate_rows(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v @ m.T`` for (N, 3) rows, as three scaled column sums (a BLAS matmul with threads is slower
    than this on a busy machine)."""
    if np.array_equal(m, np.eye(3)):
        return v
    return np.stack([m[i, 0] * v[:, 0] + m[i, 1] * v[:, 1] + m[i, 2] * v[:, 2] for i in range(3)], axis=1)


def _convert_frames(cmap: ColumnMap, groups: dict[str, np.ndarray], quat: str | None = None) -> dict[str, np.ndarray]:
    """The groups in FRD/NED; ``quat``: how the quaternion is given (the map's unless said)."""
    b = BODY_FRAMES[cmap.body_frame]
    a = NAV_FRAMES[cmap.nav_frame]
    out = dict(groups)
    for g in ("gyro", "accel"):
        if g in out:
            out[g] = _rotate_rows(b, out[g])
    if "vel" in out:
        out["vel"] = _rotate_rows(a, out["vel"])
    if "quat" in out:
        q = out["quat"]
        if (quat or cmap.quat) == "nav_to_body":
            q = quat_conj(q)
        if cmap.body_frame != "FRD" or cmap.nav_frame != "NED":
            # R_ned_frd = A R B^T  <=>  q_ned_frd = q(A) q q(B)^-1 (A, B proper rotations): a constant
            # linear map of q's components, applied as column sums
            qa, qb_inv = quat_from_dcm(a), quat_conj(quat_from_dcm(b))
            m = np.stack([quat_mul(quat_mul(qa, e), qb_inv) for e in np.eye(4)], axis=1)
            q = np.stack([sum(m[i, k] * q[:, k] for k in range(4) if m[i, k] != 0.0) + 0.0 * q[:, 0]
                          for i in range(4)], axis=1)
        out["quat"] = q
    return out


def _streams_from_table(path: str, cmap: ColumnMap, groups_wanted: tuple[str, ...],
                        warns: list[str]) -> dict[str, Stream]:
    time_col = cmap.column_for("time")
    df, w = _read_table(path, time_col, header_offset(path), units_row=cmap.units_row, decimal=cmap.decimal)
    warns.extend(w)
    if time_col not in df.columns:
        raise InputError(f"no column {time_col!r} in CSV", path)
    if len(df) == 0:
        raise InputError("no data rows", path)
    t_ns, ok_t, res = time_to_ns(df[time_col], cmap.columns[time_col][1], cmap.decimal, warns,
                                 f"{os.path.basename(path)} column {time_col!r}")
    groups: dict[str, np.ndarray] = {}
    masks: dict[str, np.ndarray] = {}
    damaged = ~ok_t
    # a stretch of the file written twice, judged by whole lines as the canonical reader does: judged group by
    # group (parsers.assemble), a group whose values do not change along it (an accelerometer at rest,
    # quantised) is no repeat there, and the clock-step rule kept part of it alone
    valid = np.flatnonzero(ok_t)
    fresh = ok_t.copy()
    if len(valid) > 2 and np.any(np.diff(t_ns[valid]) < 0):
        rep = repeated_lines(t_ns[valid], df.iloc[valid], time_col)
        if rep.any():
            line = int(df.index[valid[rep][0]]) + 2 + int(cmap.units_row)  # (the header is line 1)
            said = REPEATED_LINES_SAID.format(n=int(rep.sum()), line=line, row="line")
            warns.append(f"{os.path.basename(path)}: {said}")
            fresh[valid[rep]] = False
    non_numeric: dict[str, int] = {}
    for g in groups_wanted:
        cols = [cmap.column_for(n) for n in GROUPS[g]]
        if any(c is None for c in cols):
            continue
        missing = [c for c in cols if c not in df.columns]
        if missing:
            raise InputError(f"no column(s) {', '.join(missing)} in CSV", path)
        vals, text_rows, text = numeric_block(df, cols)
        # inf and absurd magnitudes (damaged digits) are missing values like text: not scaled into overflows
        # nor rotated into inf - inf in the frame conversion (their rows are dropped below in any case)
        vals[~(np.abs(vals) <= _ABSURD)] = np.nan
        vals *= np.array([UNITS[cmap.columns[c][1]][1] for c in cols])
        damaged |= text_rows  # text where a number belongs
        non_numeric.update(text)
        fin = np.isfinite(vals)
        damaged |= fin.any(axis=1) & ~fin.all(axis=1)  # a group cut short
        groups[g] = vals
        masks[g] = fresh & fin.all(axis=1)
    if not groups:
        raise InputError("no complete gyro/accel/quaternion/velocity/position column group mapped", path)
    n_bad = int(damaged.sum())
    if n_bad:
        warns.append(f"{os.path.basename(path)}: {n_bad} row(s) with unparseable or missing values dropped "
                     f"(damaged or truncated file?)" + (f"; {non_numeric_text(non_numeric)}" if non_numeric else ""))
    quat_given = cmap.quat
    if "euler" in groups:  # roll, pitch, yaw (degrees here): the body -> nav rotation's Z-Y-X angles
        rpy, ok = groups.pop("euler"), masks.pop("euler")
        if "quat" in groups:
            warns.append(f"{os.path.basename(path)}: attitude from the quaternion columns; the roll/pitch/yaw "
                         "columns not used")
        else:
            groups["quat"], masks["quat"] = quat_from_euler(np.where(ok[:, None], rpy, 0.0) * DEG), ok
            quat_given = "body_to_nav"
    groups = _convert_frames(cmap, groups, quat_given)
    # stamps written with a fixed number of decimals are that coarse (the grid the data shows is found
    # later, parsers.assemble)
    stamps = {g: t_ns for g in groups}
    for g, col, unit, none in cmap.group_time:  # (a group sampled at an offset from its row's time)
        if g in groups and col in df.columns:
            rel, ok_rel, _ = time_to_ns(df[col], unit, cmap.decimal)
            ok_rel &= rel != none * round(UNITS[unit][1])
            if (masks[g] & ~ok_rel).any():
                warns.append(f"{os.path.basename(path)}: {int((masks[g] & ~ok_rel).sum())} {g} sample(s) without "
                             f"a valid {col} left out")
            masks[g] &= ok_rel
            stamps[g] = t_ns + rel
    streams = {g: Stream(stamps[g][masks[g]], v[masks[g]], f"{os.path.basename(path)}:{g}", res)
               for g, v in groups.items() if masks[g].any()}
    if not streams:
        raise InputError(f"no row with a valid time and complete values ({int(ok_t.sum())} valid times "
                         f"in {len(ok_t)} rows){_why_no_rows(df, time_col)}", path)
    return streams


_DECIMAL_COMMA = re.compile(r"^\s*[-+]?\d+,\d+(?:[eE][-+]?\d+)?\s*$")
_DATETIME = re.compile(r"^\s*\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}")


def _why_no_rows(df: pd.DataFrame, time_col: str, sample: int = 200) -> str:
    """What the cells of a CSV none of whose rows could be read look like, where it is a known export habit:
    numbers with decimal commas (a spreadsheet in a comma-decimal locale), date-time text in the time column."""
    head = df.head(sample)
    cells = [str(x) for c in head.columns for x in head[c].dropna().tolist()]
    times = [str(x) for x in head[time_col].dropna().tolist()] if time_col in head.columns else []
    if times and sum(bool(_DATETIME.match(x)) for x in times) > len(times) // 2:
        return (f": the time column {printable(time_col)!r} holds date-time text (e.g. {printable(times[0])!r}), "
                "not a number of the unit its header says: give the column the unit '(ISO 8601)' (or none) "
                "to read the date-times, or write it as seconds")
    if cells and sum(bool(_DECIMAL_COMMA.match(x)) for x in cells) > len(cells) // 2:
        return (f": the numbers are written with decimal commas (e.g. {printable(cells[0])!r}): save the CSV "
                "with decimal points")
    return ""


def _time_note(cmap: ColumnMap, path: str) -> str:
    col = cmap.column_for("time")
    return f"{os.path.basename(path)} column {col!r} ({cmap.columns[col][1]})"


def load(path: str, selector: Selector) -> InsLog:
    bad = [k for k, _ in selector.items if k not in ("map", "unit")]
    if bad:
        raise InputError(f"unknown selector key(s) {', '.join(bad)} for vendor CSV (use map=FILE.json, unit=NAME)",
                         path)
    src = _resolve(path, selector)
    cmap = column_map_for(src, selector)
    warns: list[str] = []
    warns.extend(cmap.notes)
    streams = _streams_from_table(src.table, cmap, tuple(GROUPS), warns)
    stamp = _time_note(cmap, src.table)
    if src.quat_table is not None and "quat" not in streams:
        qcols = _header_of(src.quat_table)
        try:
            qmap = map_from_header(qcols, quat_file=True)
        except MapError as why:
            raise InputError(f"quaternion file not understood ({printable(why, 200)}); columns: "
                             f"{', '.join(printable(c) for c in qcols[:6])}", src.quat_table) from None
        qmap = ColumnMap(qmap.columns, cmap.body_frame, cmap.nav_frame, cmap.quat, cmap.origin, cmap.frame_stated)
        streams.update(_streams_from_table(src.quat_table, qmap, ("quat",), warns))
        stamp += f"; attitude: {_time_note(qmap, src.quat_table)}"
    if not cmap.frame_stated:
        warns.append("axes taken as FRD body / NED (no frame stated: add _body_frame/_nav_frame to a column map "
                     "to convert from FLU/ENU)")
    t_first = min((int(s.t_ns[0]) for s in streams.values() if len(s.t_ns)), default=0)
    clock = "epoch" if t_first * 1e-9 > csv_canonical.EPOCH_THRESHOLD_S else "boot"
    if cmap.origin == "NGIMU profile":
        stamp += " (NGIMU: seconds from the logging session start, shared by the session's units)"
    sel = [f"unit={src.unit}"] if src.unit else []
    sel += [f"map={selector.get('map')}"] if selector.get("map") else []
    if os.path.isdir(path) and not selector.get("unit") and src.unit:
        warns.append(f"no selector given: picked unit={src.unit}")
    return build_inslog(path=path, fmt=NAME, selector=",".join(sel), clock=clock,
                        stamp_source=f"{stamp}; columns via {cmap.origin}",
                        gyro=streams.get("gyro"), accel=streams.get("accel"), quat=streams.get("quat"),
                        vel=streams.get("vel"), pos=streams.get("pos"), warnings=warns)


def inventory(path: str) -> Inventory:
    units = [""]
    if os.path.isdir(path) and not os.path.isfile(os.path.join(path, NGIMU_SENSORS)):
        units = _unit_dirs(path)
    streams: list[StreamInfo] = []
    selectors: list[str] = []
    warns: list[str] = []
    notes: list[str] = []
    for unit in units:
        sel = Selector((("unit", unit),)) if unit else Selector()
        log = load(path, sel)
        src = _resolve(path, sel)
        prefix = f"{unit}/" if unit else ""
        for ch, info in log.meta.channels.items():
            if ch == "accel" and "gyro" in log.meta.channels:
                continue
            t = log.t_imu_s() if ch in ("gyro", "accel") else log.nav_rows(
                {"att": ("quat_w",), "vel": ("vel_n_m_s",), "pos": ("lat_deg",)}[ch])[0]
            name = info.source.split(":")[0]
            kind = "imu" if ch == "gyro" and "accel" in log.meta.channels else ch
            streams.append(StreamInfo(name=prefix + name + ("" if ch in ("gyro", "accel") else f":{ch}"),
                                      kind=kind,
                                      count=info.count, rate_hz=info.rate_hz,
                                      start_s=log.t0_s + float(t[0]) if len(t) else 0.0,
                                      duration_s=float(t[-1] - t[0]) if len(t) > 1 else 0.0, clock=log.meta.clock))
        selectors.append(f"unit={unit}" if unit else "")
        warns.extend(f"{prefix}{w}" for w in log.meta.warnings if not w.startswith("no selector given"))
        cmap = column_map_for(src, Selector())
        if cmap.ignored and unit == units[0]:
            notes.append(f"columns not used: {', '.join(cmap.ignored[:8])}" + (" ..." if len(cmap.ignored) > 8 else ""))
        if unit == units[0]:
            notes.append(f"stamps: {log.meta.stamp_source}")
    return Inventory(path=path, format=NAME, streams=tuple(streams), selectors=tuple(selectors),
                     warnings=tuple(warns), notes=tuple(notes))
