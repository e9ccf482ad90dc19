"""Parse speed of PX4 ULog and vendor (NGIMU-style) CSV, against the plain library calls.

ULog: a 1 h log at 200 Hz (sensor_combined 200 Hz; vehicle_attitude, vehicle_local_position and
vehicle_global_position 50 Hz; vehicle_gps_position 5 Hz) written by ``parsers.ulog.write``. Timed:
* plain pyulog ``ULog(path, message_name_filter_list=[the topics we need])`` (the baseline: pyulog
  decodes columnar already, but walks the messages one by one in Python);
* our reader ``parsers.ulog.read_topics`` (compiled header walk + gather into pyulog's dtypes;
  identical arrays, checked here) and the whole ``parsers.ulog.load`` -> InsLog;
* the writer.
CSV: an NGIMU-style session unit (sensors.csv + quaternion.csv, 1 h at 200 Hz) through
``parsers.csv_vendor.load`` against plain ``pandas.read_csv`` of the two files; the canonical CSV of the
same length through ``parsers.csv_canonical.load``. Real logs (when ``shared/realdata`` is present):
px4_sample.ulg and the three NGIMU units.

    python benchmarks/bench_parse_ulog_csv.py            # 1 h logs
    python benchmarks/bench_parse_ulog_csv.py --quick    # 10 min logs

Figures go to ``benchmarks/results/parse_ulog_csv.json``. Times are the best of ``--repeat`` runs.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results" / "parse_ulog_csv.json"
REAL = ROOT.parent / "shared" / "realdata"
IMU_HZ, NAV_HZ = 200.0, 50.0


def synthetic_log(duration_s: float):
    from logtools.conventions import G0_M_S2, quat_from_euler
    from logtools.inslog import InsLog, LogMeta

    ti = np.arange(0.0, duration_s, 1.0 / IMU_HZ)
    tn = np.arange(0.0, duration_s, 1.0 / NAV_HZ)
    rng = np.random.default_rng(0)
    gyro = 0.2 * np.c_[np.sin(ti), np.cos(0.7 * ti), np.sin(0.3 * ti)] + 1e-3 * rng.standard_normal((len(ti), 3))
    acc = np.c_[0.3 * np.cos(ti), 0.1 * np.sin(ti), -G0_M_S2 + 0.05 * np.sin(2 * ti)]
    q = quat_from_euler(np.c_[0.1 * np.sin(tn), 0.1 * np.cos(tn), 0.01 * tn])
    vel = np.c_[10 * np.cos(0.01 * tn), 10 * np.sin(0.01 * tn), 0.0 * tn]
    llh = np.c_[45.0 + 1e-6 * tn, 7.0 + 1e-6 * tn, 200.0 + 0.0 * tn]
    meta = LogMeta(source_path="bench", format="sim", clock="epoch", t0_ns=1_700_000_000_000_000_000)
    return InsLog.from_arrays(meta, ti, gyro, acc, tn, q, vel, llh)


def best_of(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def bench_ulog(d: Path, duration_s: float, repeat: int) -> dict:
    from pyulog import ULog

    from parsers import ulog
    from parsers.base import Selector

    log = synthetic_log(duration_s)
    p = d / "bench.ulg"
    t_write, _ = best_of(lambda: ulog.write(str(p), log), 1)
    names = ["sensor_combined", "vehicle_attitude", "vehicle_local_position", "vehicle_global_position"]
    ulog.read_topics(str(p), set(names))  # compile / load the numba cache outside the timing
    t_py, u = best_of(lambda: ULog(str(p), names), repeat)
    t_py_all, _ = best_of(lambda: ULog(str(p)), 1)
    t_fast, fast = best_of(lambda: ulog.read_topics(str(p), set(names)), repeat)
    t_load, inslog = best_of(lambda: ulog.load(str(p), Selector()), repeat)
    ref = {(x.name, x.multi_id): x.data for x in u.data_list}
    identical = ref.keys() == fast.topics.keys() and all(
        np.array_equal(ref[k][f], fast.topics[k][f], equal_nan=True) for k in ref for f in ref[k])
    n_msgs = sum(len(v["timestamp"]) for v in ref.values())
    n_all = n_msgs + int(duration_s * 5)  # + gps
    return {
        "duration_s": duration_s, "file_mb": round(p.stat().st_size / 1e6, 2), "messages_read": n_msgs,
        "write_s": round(t_write, 3),
        "pyulog_filtered_s": round(t_py, 3), "pyulog_all_topics_s": round(t_py_all, 3),
        "ours_read_topics_s": round(t_fast, 3), "ours_load_to_inslog_s": round(t_load, 3),
        "pyulog_msg_per_s": round(n_all / t_py), "ours_msg_per_s": round(n_all / t_fast),
        "speedup_read_vs_pyulog": round(t_py / t_fast, 2), "speedup_load_vs_pyulog": round(t_py / t_load, 2),
        "identical_to_pyulog": bool(identical), "inslog_imu_rows": len(inslog.imu),
    }


def _ngimu_files(d: Path, duration_s: float) -> Path:
    unit = d / "unit"
    unit.mkdir(exist_ok=True)
    t = np.arange(0.0, duration_s, 1.0 / IMU_HZ)
    rng = np.random.default_rng(1)
    sens = np.c_[t, 50 * rng.standard_normal((len(t), 3)), 0.1 * rng.standard_normal((len(t), 2)),
                 1 + 0.01 * rng.standard_normal(len(t)), 20 * rng.standard_normal((len(t), 3)), np.full(len(t), 1013.0)]
    head = ("Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),Accelerometer X (g),"
            "Accelerometer Y (g),Accelerometer Z (g),Magnetometer X (uT),Magnetometer Y (uT),Magnetometer Z (uT),"
            "Barometer (hPa)")
    np.savetxt(unit / "sensors.csv", sens, delimiter=",", header=head, comments="",
               fmt=["%.9f"] + ["%.7g"] * 10)
    q = rng.standard_normal((len(t), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.savetxt(unit / "quaternion.csv", np.c_[t, q], delimiter=",", header="Time (s),W,X,Y,Z", comments="",
               fmt=["%.9f"] + ["%.7g"] * 4)
    return unit


def bench_csv(d: Path, duration_s: float, repeat: int) -> dict:
    import pandas as pd

    from parsers import csv_canonical, csv_vendor
    from parsers.base import Selector

    unit = _ngimu_files(d, duration_s)
    rows = sum(1 for _ in open(unit / "sensors.csv")) - 1
    t_pd, _ = best_of(lambda: (pd.read_csv(unit / "sensors.csv"), pd.read_csv(unit / "quaternion.csv")), repeat)
    t_v, log = best_of(lambda: csv_vendor.load(str(unit), Selector()), repeat)
    canon = d / "canon.csv"
    csv_canonical.write(str(canon), synthetic_log(duration_s))
    t_c, clog = best_of(lambda: csv_canonical.load(str(canon), Selector()), repeat)
    mb = ((unit / "sensors.csv").stat().st_size + (unit / "quaternion.csv").stat().st_size) / 1e6
    return {
        "duration_s": duration_s, "ngimu_rows_per_file": rows, "ngimu_mb": round(mb, 1),
        "pandas_read_csv_s": round(t_pd, 3), "ngimu_load_s": round(t_v, 3),
        "ngimu_rows_per_s": round(2 * rows / t_v), "ngimu_mb_per_s": round(mb / t_v, 1),
        "ngimu_load_vs_pandas": round(t_v / t_pd, 2), "ngimu_imu_rows": len(log.imu),
        "canonical_mb": round(canon.stat().st_size / 1e6, 1), "canonical_load_s": round(t_c, 3),
        "canonical_rows": len(clog.imu),
    }


def bench_real(repeat: int) -> dict:
    from pyulog import ULog

    from parsers import registry

    out = {}
    px4 = REAL / "px4_sample.ulg"
    if px4.exists():
        out["px4_sample_pyulog_all_s"] = round(best_of(lambda: ULog(str(px4)), repeat)[0], 4)
        out["px4_sample_load_s"] = round(best_of(lambda: registry.load(str(px4)), repeat)[0], 4)
        out["px4_sample_inventory_s"] = round(best_of(lambda: registry.inspect_log(str(px4)), repeat)[0], 4)
    ng = REAL / "ngimu_session"
    if ng.exists():
        out["ngimu_3_units_load_s"] = round(best_of(
            lambda: [registry.load(f"{ng}::unit={u}") for u in ("blue", "green", "red")], repeat)[0], 4)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min logs instead of 1 h")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    duration = 600.0 if a.quick else 3600.0
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        res = {"ulog": bench_ulog(d, duration, a.repeat), "csv": bench_csv(d, duration, a.repeat),
               "real": bench_real(a.repeat)}
    res["meta"] = {"quick": a.quick, "repeat": a.repeat, "python": platform.python_version(),
                   "machine": platform.machine(), "cpus": os.cpu_count(),
                   "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
