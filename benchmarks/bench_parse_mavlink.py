"""Parse throughput of the MAVLink tlog and DataFlash parsers against pymavlink's plain loops.

* tlog: a synthetic slave, 1 h at 200 Hz (HIGHRES_IMU 200 Hz + ATTITUDE_QUATERNION + ATTITUDE +
  GLOBAL_POSITION_INT at the nav rate, SYSTEM_TIME + HEARTBEAT 1 Hz), from ``logtools.sim`` when it is
  importable (else built from arrays), written by ``parsers.mavlink_tlog.write`` (vectorised packer).
  Timed: our ``parsers.load`` (walk + CRC + vectorised decode + InsLog) and its raw frame read, against
  pymavlink's plain ``recv_match()`` loop over every message (the loop a user would write).
* DataFlash: the real ``../shared/realdata/arduplane_box_pilot.BIN`` (when present) and a synthetic
  1 h / 200 Hz .bin written by ``parsers.dataflash.write``: our load against DFReader's
  ``recv_match()`` loop.

    python benchmarks/bench_parse_mavlink.py            # 1 h logs
    python benchmarks/bench_parse_mavlink.py --quick    # 10 min logs

Figures go to ``benchmarks/results/parse_mavlink.json``.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
RESULTS = os.path.join(ROOT, "benchmarks", "results", "parse_mavlink.json")
REAL = Path(ROOT).parent / "shared" / "realdata"
IMU_HZ, NAV_HZ = 200.0, 50.0
T0_NS = 1_700_000_000_000_000_000


def slave_from_arrays(duration_s: float):
    from logtools.conventions import quat_from_euler
    from logtools.inslog import InsLog, LogMeta
    rng = np.random.default_rng(0)
    n, m = int(duration_s * IMU_HZ), int(duration_s * NAV_HZ)
    t, tn = np.arange(n) / IMU_HZ, np.arange(m) / NAV_HZ
    gyro = 0.1 * np.column_stack([np.sin(0.5 * t), np.cos(0.3 * t), np.sin(0.1 * t)]) + rng.normal(0, 0.01, (n, 3))
    acc = np.column_stack([np.sin(0.2 * t), np.cos(0.2 * t), -9.8 + 0.1 * np.sin(t)]) + rng.normal(0, 0.05, (n, 3))
    rpy = np.column_stack([0.1 * np.sin(tn), 0.2 * np.cos(0.5 * tn), np.mod(0.01 * tn, 2 * np.pi) - np.pi])
    q = quat_from_euler(rpy)
    v = np.column_stack([10 * np.sin(0.01 * tn), 10 * np.cos(0.01 * tn), 0.5 * np.sin(0.1 * tn)])
    p = np.column_stack([45 + 1e-5 * tn, 7 + 1e-5 * tn, 100 + np.sin(0.01 * tn)])
    meta = LogMeta(source_path="arrays", format="sim", clock="epoch", t0_ns=T0_NS)
    return InsLog.from_arrays(meta, t, gyro, acc, tn, q, v, p), "arrays"


def make_slave(duration_s: float):
    try:
        from logtools import sim
        cfg = sim.scenario_config("aircraft", duration_s=duration_s, slave_imu_rate_hz=IMU_HZ,
                                  slave_nav_rate_hz=NAV_HZ)
        return sim.simulate(cfg).slave, "logtools.sim aircraft"
    except Exception as exc:  # the simulator is someone else's module: fall back, say so
        print(f"logtools.sim unavailable ({type(exc).__name__}: {exc}); building from arrays")
        return slave_from_arrays(duration_s)


def pymavlink_tlog_loop(path: str) -> tuple[int, float]:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil
    t = time.perf_counter()
    conn = mavutil.mavlink_connection(path, dialect="ardupilotmega")
    n = 0
    while True:
        m = conn.recv_match()
        if m is None:
            break
        n += 1
    conn.close()
    return n, time.perf_counter() - t


def dfreader_loop(path: str) -> tuple[int, float]:
    from pymavlink import DFReader
    t = time.perf_counter()
    r = DFReader.DFReader_binary(path)
    n = 0
    while True:
        m = r.recv_match()
        if m is None:
            break
        n += 1
    return n, time.perf_counter() - t


def timed(fn, *a, repeat: int = 2):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn(*a)
        best = min(best, time.perf_counter() - t)
    return out, best


def bench_tlog(slave, d: str) -> dict:
    from parsers import load
    from parsers import mavlink_tlog as T
    path = os.path.join(d, "slave.tlog")
    t = time.perf_counter()
    T.write(path, slave)
    write_s = time.perf_counter() - t
    T.read_frames(path)  # warm-up: numba's cached machine code loaded once per process
    fr, raw_s = timed(T.read_frames, path)
    log, load_s = timed(load, path)
    n = len(fr.msgid)
    n_ref, ref_s = pymavlink_tlog_loop(path)
    return {"format": "tlog", "file_mb": round(os.path.getsize(path) / 1e6, 1), "messages": n,
            "write_s": round(write_s, 3), "write_msgs_per_s": int(n / write_s),
            "read_frames_s": round(raw_s, 3), "load_s": round(load_s, 3), "load_msgs_per_s": int(n / load_s),
            "selector": log.meta.selector, "warnings": list(log.meta.warnings),
            "baseline": {"library_loop": "pymavlink mavutil recv_match()", "messages_decoded": n_ref,
                         "seconds": round(ref_s, 2), "msgs_per_s": int(n_ref / ref_s),
                         "speedup_of_load": round(ref_s / load_s, 1)}}


def bench_dataflash(path: str, label: str, write_s: float | None = None) -> dict:
    from parsers import load
    from parsers import dataflash as D
    D.read_log(path)
    dl, raw_s = timed(D.read_log, path)
    n = int(sum(len(v) for v in dl.offsets.values()))
    log, load_s = timed(load, path)
    n_ref, ref_s = dfreader_loop(path)
    out = {"format": "dataflash", "file": label, "file_mb": round(os.path.getsize(path) / 1e6, 1),
           "records": n, "read_records_s": round(raw_s, 3), "load_s": round(load_s, 3),
           "load_records_per_s": int(n / load_s), "selector": log.meta.selector,
           "baseline": {"library_loop": "pymavlink DFReader recv_match()", "messages_decoded": n_ref,
                        "seconds": round(ref_s, 2), "msgs_per_s": int(n_ref / ref_s),
                        "speedup_of_load": round(ref_s / load_s, 1)}}
    if write_s is not None:
        out["write_s"] = round(write_s, 3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min logs instead of 1 h")
    args = ap.parse_args(argv)
    duration_s = 600.0 if args.quick else 3600.0
    t = time.perf_counter()
    slave, source = make_slave(duration_s)
    sim_s = time.perf_counter() - t
    results = []
    with tempfile.TemporaryDirectory() as d:
        r = bench_tlog(slave, d)
        print(f"tlog: {r['messages']} msgs, load {r['load_s']} s ({r['load_msgs_per_s']} msg/s), "
              f"pymavlink {r['baseline']['seconds']} s ({r['baseline']['msgs_per_s']} msg/s), "
              f"x{r['baseline']['speedup_of_load']}; write {r['write_s']} s")
        results.append(r)
        real = REAL / "arduplane_box_pilot.BIN"
        if real.exists():
            r = bench_dataflash(str(real), real.name)
            print(f"dataflash real: {r['records']} records, load {r['load_s']} s, DFReader "
                  f"{r['baseline']['seconds']} s, x{r['baseline']['speedup_of_load']}")
            results.append(r)
        from parsers import dataflash as D
        path = os.path.join(d, "slave.bin")
        t = time.perf_counter()
        D.write(path, slave)
        r = bench_dataflash(path, f"synthetic {duration_s / 60:.0f} min", time.perf_counter() - t)
        print(f"dataflash synthetic: {r['records']} records, load {r['load_s']} s, DFReader "
              f"{r['baseline']['seconds']} s, x{r['baseline']['speedup_of_load']}")
        results.append(r)
    from parsers.mavlink_common import HAVE_NUMBA
    out = {"benchmark": "parse_mavlink",
           "created_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
           "mode": "quick" if args.quick else "full",
           "machine": {"python": platform.python_version(), "platform": platform.platform(),
                       "cpus": os.cpu_count(), "numba": HAVE_NUMBA},
           "duration_s": duration_s, "slave_source": source, "simulate_s": round(sim_s, 2),
           "streams": {"imu_hz": IMU_HZ, "nav_hz": NAV_HZ},
           "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
           "results": results}
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    with open(RESULTS, "w") as fh:
        json.dump(out, fh, indent=1)
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
