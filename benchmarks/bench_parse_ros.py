"""Parse throughput of the ROS formats against the plain library decode loops.

Synthetic master log, 200 Hz: sensor_msgs/Imu 200 Hz (with orientation), geometry_msgs/TwistStamped
200 Hz, sensor_msgs/NavSatFix 10 Hz, written by our writers as MCAP (ROS 2 CDR), ROS 1 bag and ROS 2
bags (sqlite3 and mcap storage). For each file:

* ``load``: ``parsers.load(path)`` -> InsLog (scan + vectorised decode + frames + assembly), wall
  and CPU time (the machine is shared: CPU time is the comparable figure), with its CPU split into
  raw read (``read_raw``) and the rest;
* the plain library loop a user would write, decoding every message and reading the same fields:
  ``mcap`` reader + ``mcap_ros2`` decoder (ROS 2 MCAP), ``rosbags`` ``AnyReader`` + ``deserialize``
  (ROS 1 bag, ROS 2 bags). The library loops run on the first ``--baseline-max`` messages (they are
  slow): their opening cost (index/summary) is measured once, their per-message CPU rate is
  extrapolated to the whole file (``full_file_cpu_s_extrapolated``).

    python benchmarks/bench_parse_ros.py            # 1 h log
    python benchmarks/bench_parse_ros.py --quick    # 10 min log

Figures go to ``benchmarks/results/parse_ros.json``.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
RESULTS = os.path.join(ROOT, "benchmarks", "results", "parse_ros.json")
IMU_HZ, VEL_HZ, FIX_HZ = 200.0, 200.0, 10.0
T0_NS = 1_700_000_000_000_000_000


def make_log(duration_s: float):
    from logtools.conventions import quat_from_euler
    from logtools.inslog import InsLog, LogMeta

    n = int(duration_s * IMU_HZ)
    t = np.arange(n) / IMU_HZ
    rng = np.random.default_rng(0)
    gyro = rng.normal(0, 0.01, (n, 3))
    accel = rng.normal(0, 0.1, (n, 3)) + [0, 0, -9.81]
    quat = quat_from_euler(np.stack([0.1 * np.sin(0.1 * t), 0.05 * np.cos(0.07 * t), 0.01 * t], axis=-1))
    vel = np.stack([10 * np.cos(0.01 * t), 10 * np.sin(0.01 * t), 0.1 * np.sin(t)], axis=-1)
    pos = np.full((n, 3), np.nan)
    every = int(round(IMU_HZ / FIX_HZ))
    pos[::every] = np.stack([47 + 1e-6 * t, 8 + 1e-6 * t, 400 + 0 * t], axis=-1)[::every]
    meta = LogMeta(source_path="bench", format="sim", clock="epoch", t0_ns=T0_NS)
    return InsLog.from_arrays(meta, t_imu_s=t, gyro_rad_s=gyro, accel_m_s2=accel, t_nav_s=t, quat_wxyz=quat,
                              vel_ned_m_s=vel, lat_lon_alt=pos)


def _size_mb(path: str) -> float:
    if os.path.isdir(path):
        return sum(os.path.getsize(os.path.join(path, f)) for f in os.listdir(path)) / 1e6
    return os.path.getsize(path) / 1e6


def _fields(msg, msgtype: str) -> tuple:
    """What a user's loop reads from each message (the same fields our parser extracts)."""
    s = msg.header.stamp
    if msgtype.endswith("Imu"):
        return (s.sec, s.nanosec, msg.orientation.w, msg.orientation.x, msg.orientation.y, msg.orientation.z,
                msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z,
                msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z)
    if msgtype.endswith("TwistStamped"):
        return (s.sec, s.nanosec, msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z)
    return (s.sec, s.nanosec, msg.latitude, msg.longitude, msg.altitude)


def baseline_mcap_ros2(path: str, max_msgs: int) -> tuple[int, float, float]:
    """(messages, open cpu s, loop cpu s) of mcap's reader + mcap_ros2 decoder."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    c = time.process_time()
    n = 0
    rows = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        reader.get_summary()
        c_open = time.process_time()
        for schema, _ch, _m, msg in reader.iter_decoded_messages():
            rows.append(_fields(msg, schema.name))
            n += 1
            if n >= max_msgs:
                break
    return n, c_open - c, time.process_time() - c_open


def baseline_rosbags(path: str, max_msgs: int) -> tuple[int, float, float]:
    """(messages, open cpu s, loop cpu s) of rosbags' AnyReader + deserialize."""
    from rosbags.highlevel import AnyReader

    c = time.process_time()
    n = 0
    rows = []
    with AnyReader([Path(path)]) as reader:
        c_open = time.process_time()
        for conn, _ts, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            rows.append(_fields(msg, conn.msgtype))
            n += 1
            if n >= max_msgs:
                break
    return n, c_open - c, time.process_time() - c_open


def run(duration_s: float, baseline_max: int, keep_dir: str | None) -> dict:
    import parsers
    from parsers import mcap_ros, registry, rosbag1, rosbag2
    from parsers import ros_common as rc

    log = make_log(duration_s)
    n_msgs = len(log.imu) + len(log.nav) + int(log.nav["lat_deg"].notna().sum())
    d = keep_dir or tempfile.mkdtemp(prefix="bench_ros_")
    cases = [
        ("mcap", {}, "log.mcap", mcap_ros.read_raw, [("mcap + mcap_ros2 decoder", baseline_mcap_ros2),
                                                     ("rosbags deserialize_cdr (via our scan)", None)]),
        ("rosbag1", {}, "log.bag", rosbag1.read_raw, [("rosbags AnyReader + deserialize", baseline_rosbags)]),
        ("rosbag2", {"storage": "sqlite3"}, "bag2_sqlite", rosbag2.read_raw,
         [("rosbags AnyReader + deserialize", baseline_rosbags)]),
        ("rosbag2", {"storage": "mcap"}, "bag2_mcap", rosbag2.read_raw,
         [("rosbags AnyReader + deserialize", baseline_rosbags)]),
    ]
    out = []
    for fmt, opts, name, read_raw, baselines in cases:
        path = os.path.join(d, name)
        if os.path.isdir(path):
            shutil.rmtree(path)
        elif os.path.exists(path):
            os.remove(path)
        t = time.perf_counter()
        registry.write(path, log, fmt, **opts)
        write_s = time.perf_counter() - t
        t, c = time.perf_counter(), time.process_time()
        back = parsers.load(path)
        load_s, load_cpu_s = time.perf_counter() - t, time.process_time() - c
        assert len(back.imu) == len(log.imu), "round trip lost samples"
        assert np.array_equal(back.gyro_rad_s(), log.gyro_rad_s()), "round trip changed values"
        c = time.process_time()
        raw = read_raw(path)
        raw_s = time.process_time() - c
        c = time.process_time()
        rc.to_inslog(raw, parsers.base.Selector())
        decode_s = time.process_time() - c
        entry = {"format": fmt, "options": opts, "file": name, "file_mb": round(_size_mb(path), 1),
                 "messages": n_msgs, "write_s": round(write_s, 3), "load_s": round(load_s, 3),
                 "load_cpu_s": round(load_cpu_s, 3), "load_msgs_per_s": round(n_msgs / load_s),
                 "load_msgs_per_cpu_s": round(n_msgs / load_cpu_s),
                 "cpu_split_s": {"read_raw": round(raw_s, 3), "decode_to_inslog": round(decode_s, 3)},
                 "baselines": []}
        for label, fn in baselines:
            t = time.perf_counter()
            if fn is None:  # rosbags' CDR deserialiser on the same raw messages, for reference
                c = time.process_time()
                k = 0
                for tp in raw.topics.values():
                    m = min(len(tp.data), max(0, baseline_max - k))
                    for i in range(m):
                        _fields(raw.typestore.deserialize_cdr(tp.data[i], tp.msgtype), tp.msgtype)
                    k += m
                n_b, open_cpu, loop_cpu = k, 0.0, time.process_time() - c
            else:
                n_b, open_cpu, loop_cpu = fn(path, baseline_max)
            wall = time.perf_counter() - t
            rate_cpu = n_b / loop_cpu
            full_cpu = open_cpu + n_msgs / rate_cpu
            entry["baselines"].append({"library_loop": label, "messages_decoded": n_b, "wall_s": round(wall, 3),
                                       "open_cpu_s": round(open_cpu, 3), "loop_cpu_s": round(loop_cpu, 3),
                                       "msgs_per_cpu_s": round(rate_cpu),
                                       "full_file_cpu_s_extrapolated": round(full_cpu, 2),
                                       "speedup_of_load_cpu": round(full_cpu / load_cpu_s, 1)})
        out.append(entry)
        print(f"{fmt:8s} {json.dumps(opts):24s} {entry['file_mb']:7.1f} MB  write {write_s:6.2f} s  "
              f"load {load_s:6.2f} s wall, {load_cpu_s:6.2f} s cpu ({entry['load_msgs_per_cpu_s'] / 1e3:5.0f} k msg/cpu-s)  "
              + "  ".join(f"{b['library_loop']}: {b['msgs_per_cpu_s'] / 1e3:.0f} k msg/cpu-s "
                          f"(load x{b['speedup_of_load_cpu']} faster)" for b in entry["baselines"]), flush=True)
    if not keep_dir:
        shutil.rmtree(d, ignore_errors=True)
    return {"duration_s": duration_s, "messages": n_msgs,
            "streams": {"imu_hz": IMU_HZ, "twist_hz": VEL_HZ, "navsatfix_hz": FIX_HZ}, "results": out}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min log instead of 1 h")
    ap.add_argument("--baseline-max", type=int, default=200_000,
                    help="messages decoded by each plain library loop (default 200000)")
    ap.add_argument("--keep", default=None, help="keep the generated files in this directory")
    args = ap.parse_args()
    duration = 600.0 if args.quick else 3600.0
    if args.keep:
        os.makedirs(args.keep, exist_ok=True)
    res = run(duration, args.baseline_max, args.keep)
    doc = {"benchmark": "parse_ros",
           "note": "wall times depend on the machine's load (2 shared cores); cpu times (process_time) "
                   "and msgs_per_cpu_s are the comparable figures", "created_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
           "mode": "quick" if args.quick else "full",
           "machine": {"python": platform.python_version(), "platform": platform.platform(),
                       "cpus": os.cpu_count()},
           "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1), **res}
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    with open(RESULTS, "w") as fh:
        json.dump(doc, fh, indent=1)
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
